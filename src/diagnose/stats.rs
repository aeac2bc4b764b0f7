//! Small statistics toolbox for diagnosis: robust location/scale, normal distribution,
//! weighted least squares with cluster-robust (sandwich) covariance, interval-censored normal
//! maximum likelihood, and derivative-free 1-D / n-D minimisers.
//!
//! Everything here is plain `f64` arithmetic with no allocation beyond the obvious vectors.

/// Median of a slice (reorders it). `NaN` for an empty slice.
pub fn median_mut(v: &mut [f64]) -> f64 {
    quantile_mut(v, 0.5)
}

/// Quantile `q` in [0, 1] with linear interpolation between order statistics (reorders `v`).
pub fn quantile_mut(v: &mut [f64], q: f64) -> f64 {
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    let pos = q.clamp(0.0, 1.0) * (n - 1) as f64;
    let lo = pos.floor() as usize;
    let frac = pos - lo as f64;
    let (_, &mut a, rest) = v.select_nth_unstable_by(lo, |a, b| a.total_cmp(b));
    if frac == 0.0 || rest.is_empty() {
        return a;
    }
    let b = rest.iter().copied().fold(f64::INFINITY, f64::min);
    a + frac * (b - a)
}

/// Mean of the samples between the `trim` and `1 - trim` order statistics, `floor(trim n)`
/// cut from each end (reorders `v`).
pub fn trimmed_mean_mut(v: &mut [f64], trim: f64) -> f64 {
    v.sort_unstable_by(f64::total_cmp);
    let k = (trim * v.len() as f64).floor() as usize;
    let mid = &v[k..v.len() - k];
    mid.iter().sum::<f64>() / mid.len() as f64
}

/// Median of a copy of the slice.
pub fn median(v: &[f64]) -> f64 {
    let mut c = v.to_vec();
    median_mut(&mut c)
}

/// Median absolute deviation scaled to a normal standard deviation (1.4826 * MAD).
pub fn mad_sigma(v: &[f64]) -> f64 {
    let m = median(v);
    let mut d: Vec<f64> = v.iter().map(|x| (x - m).abs()).collect();
    1.4826 * median_mut(&mut d)
}

/// Mean and standard error of the mean.
pub fn mean_se(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let m = v.iter().sum::<f64>() / n;
    if v.len() < 2 {
        return (m, f64::INFINITY);
    }
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, (var / n).sqrt())
}

/// Variance after rejecting values further than `k` robust sigmas from the median; the
/// rejection is iterated twice. Returns (variance, number of values kept). Robust to a few
/// outliers (hot pixels) while staying efficient for discrete (rounded) data, where the MAD
/// alone is too coarse.
pub fn clipped_variance(v: &[f64], k: f64) -> (f64, usize) {
    if v.len() < 3 {
        return (f64::NAN, v.len());
    }
    let mut centre = median(v);
    let mut scale = mad_sigma(v).max(1e-6);
    // Rounded data can have MAD 0; fall back to the plain standard deviation then.
    if scale <= 1e-6 {
        let (m, _) = mean_se(v);
        scale = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt().max(1e-6);
    }
    let mut var = f64::NAN;
    let mut kept = 0;
    for _ in 0..2 {
        let lim = k * scale;
        let (mut s, mut s2, mut n) = (0.0, 0.0, 0usize);
        for &x in v {
            if (x - centre).abs() <= lim {
                s += x;
                s2 += x * x;
                n += 1;
            }
        }
        if n < 3 {
            break;
        }
        let m = s / n as f64;
        var = (s2 / n as f64 - m * m).max(0.0) * n as f64 / (n - 1) as f64;
        kept = n;
        centre = m;
        scale = var.sqrt().max(1e-6);
    }
    (var, kept)
}

/// Standard normal cumulative distribution function (|error| < 1.5e-7).
pub fn norm_cdf(x: f64) -> f64 {
    0.5 * erfc(-x / std::f64::consts::SQRT_2)
}

/// Complementary error function (W. J. Cody style rational approximation, Numerical Recipes
/// `erfcc`, fractional error < 1.2e-7).
pub fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let r = t
        * (-z * z - 1.265_512_23
            + t * (1.000_023_68
                + t * (0.374_091_96
                    + t * (0.096_784_18
                        + t * (-0.186_288_06
                            + t * (0.278_868_07
                                + t * (-1.135_203_98
                                    + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77)))))))))
            .exp();
    if x >= 0.0 { r } else { 2.0 - r }
}

/// Standard normal density.
pub fn norm_pdf(x: f64) -> f64 {
    (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// Two-sided p-value of a z statistic.
pub fn p_two_sided(z: f64) -> f64 {
    (2.0 * norm_cdf(-z.abs())).clamp(0.0, 1.0)
}

/// Upper-tail probability of a chi-square variable with `k` degrees of freedom, through the
/// Wilson–Hilferty normal approximation (good to a few per cent in the tail we use).
pub fn chi2_sf(x: f64, k: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let h = 2.0 / (9.0 * k);
    let z = ((x / k).powf(1.0 / 3.0) - (1.0 - h)) / h.sqrt();
    norm_cdf(-z)
}

/// Equivalent one-sided normal z of a chi-square statistic with `k` degrees of freedom
/// (Wilson–Hilferty), so tests with different degrees of freedom share one threshold.
pub fn chi2_to_z(x: f64, k: f64) -> f64 {
    if x <= 0.0 {
        return -10.0;
    }
    let h = 2.0 / (9.0 * k);
    ((x / k).powf(1.0 / 3.0) - (1.0 - h)) / h.sqrt()
}

/// Solve the symmetric positive (semi-)definite system `a x = b` (row-major `n x n`) by
/// Cholesky with a tiny relative ridge; returns `None` if it is singular.
pub fn solve_spd(a: &[f64], b: &[f64], n: usize) -> Option<Vec<f64>> {
    let inv = invert_spd(a, n)?;
    Some((0..n).map(|i| (0..n).map(|j| inv[i * n + j] * b[j]).sum()).collect())
}

/// Inverse of a symmetric positive definite matrix (row-major), with a relative ridge of 1e-12
/// on the diagonal. `None` if not positive definite.
pub fn invert_spd(a: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    let maxdiag = (0..n).map(|i| a[i * n + i].abs()).fold(0.0, f64::max).max(1e-300);
    for i in 0..n {
        for j in 0..=i {
            let mut s = a[i * n + j];
            if i == j {
                s += 1e-12 * maxdiag;
            }
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            if i == j {
                if s <= 0.0 || !s.is_finite() {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    // inverse of L
    let mut li = vec![0.0; n * n];
    for i in 0..n {
        li[i * n + i] = 1.0 / l[i * n + i];
        for j in 0..i {
            let mut s = 0.0;
            for k in j..i {
                s -= l[i * n + k] * li[k * n + j];
            }
            li[i * n + j] = s / l[i * n + i];
        }
    }
    // A^-1 = L^-T L^-1
    let mut inv = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = 0.0;
            for k in i..n {
                s += li[k * n + i] * li[k * n + j];
            }
            inv[i * n + j] = s;
            inv[j * n + i] = s;
        }
    }
    Some(inv)
}

/// Weighted linear regression with cluster-robust (sandwich) covariance.
///
/// Rows are added one at a time with a weight (inverse noise variance) and a cluster id (e.g. a
/// 32x32 block of one frame). Pixel noise is independent, but model misfit is spatially
/// correlated; clustering the score makes the standard errors honest about that, so that the
/// significance tests do not fire on a misfit that one block happens to contain.
#[derive(Debug, Clone)]
pub struct Wls {
    k: usize,
    xs: Vec<f64>,
    ys: Vec<f64>,
    ws: Vec<f64>,
    cl: Vec<u32>,
}

/// Result of [`Wls::fit`].
#[derive(Debug, Clone)]
pub struct WlsFit {
    pub beta: Vec<f64>,
    /// Cluster-robust covariance of `beta` (row-major k x k).
    pub cov: Vec<f64>,
    /// Model-based covariance (X'WX)^-1 scaled by the residual variance factor.
    pub cov_model: Vec<f64>,
    /// Weighted residual sum of squares divided by the degrees of freedom (1 when the noise
    /// model is right and the model fits).
    pub dispersion: f64,
    pub n: usize,
    pub clusters: usize,
}

impl WlsFit {
    pub fn se(&self, i: usize) -> f64 {
        let k = self.beta.len();
        self.cov[i * k + i].max(self.cov_model[i * k + i]).sqrt()
    }
    /// Wald chi-square of a group of coefficients against zero, using the larger of the
    /// cluster-robust and the model covariance (conservative).
    pub fn wald(&self, idx: &[usize]) -> f64 {
        let k = self.beta.len();
        let m = idx.len();
        let mut c = vec![0.0; m * m];
        for (a, &i) in idx.iter().enumerate() {
            for (b, &j) in idx.iter().enumerate() {
                let r = self.cov[i * k + j];
                let mo = self.cov_model[i * k + j];
                // Elementwise max on the diagonal keeps the matrix conservative.
                c[a * m + b] = if a == b { r.max(mo) } else { r };
            }
        }
        let b: Vec<f64> = idx.iter().map(|&i| self.beta[i]).collect();
        match invert_spd(&c, m) {
            Some(inv) => {
                let mut s = 0.0;
                for a in 0..m {
                    for bb in 0..m {
                        s += b[a] * inv[a * m + bb] * b[bb];
                    }
                }
                s
            }
            None => 0.0,
        }
    }
}

impl Wls {
    pub fn new(k: usize) -> Wls {
        Wls { k, xs: Vec::new(), ys: Vec::new(), ws: Vec::new(), cl: Vec::new() }
    }
    pub fn len(&self) -> usize {
        self.ys.len()
    }
    pub fn is_empty(&self) -> bool {
        self.ys.is_empty()
    }
    /// The same rows restricted to the columns `cols` (in that order).
    pub fn select(&self, cols: &[usize]) -> Wls {
        let mut out = Wls::new(cols.len());
        for i in 0..self.ys.len() {
            let x = &self.xs[i * self.k..(i + 1) * self.k];
            out.xs.extend(cols.iter().map(|&c| x[c]));
            out.ys.push(self.ys[i]);
            out.ws.push(self.ws[i]);
            out.cl.push(self.cl[i]);
        }
        out
    }

    /// Fit only the columns `cols`; the others get coefficient 0 and an unbounded variance.
    pub fn fit_cols(&self, cols: &[usize]) -> Option<WlsFit> {
        let sub = self.select(cols).fit()?;
        let k = self.k;
        let m = cols.len();
        let mut beta = vec![0.0; k];
        let mut cov = vec![0.0; k * k];
        let mut cov_model = vec![0.0; k * k];
        for i in 0..k {
            cov[i * k + i] = 1e30;
            cov_model[i * k + i] = 1e30;
        }
        for (a, &i) in cols.iter().enumerate() {
            beta[i] = sub.beta[a];
            for (b, &j) in cols.iter().enumerate() {
                cov[i * k + j] = sub.cov[a * m + b];
                cov_model[i * k + j] = sub.cov_model[a * m + b];
            }
        }
        Some(WlsFit { beta, cov, cov_model, dispersion: sub.dispersion, n: sub.n, clusters: sub.clusters })
    }

    pub fn push(&mut self, x: &[f64], y: f64, w: f64, cluster: u32) {
        debug_assert_eq!(x.len(), self.k);
        if !(y.is_finite() && w.is_finite() && w > 0.0) || x.iter().any(|v| !v.is_finite()) {
            return;
        }
        self.xs.extend_from_slice(x);
        self.ys.push(y);
        self.ws.push(w);
        self.cl.push(cluster);
    }

    /// Fit; `None` when the design is singular or there are too few rows.
    pub fn fit(&self) -> Option<WlsFit> {
        let k = self.k;
        let n = self.ys.len();
        if n <= k {
            return None;
        }
        let mut xtx = vec![0.0; k * k];
        let mut xty = vec![0.0; k];
        for i in 0..n {
            let x = &self.xs[i * k..(i + 1) * k];
            let w = self.ws[i];
            for a in 0..k {
                let wa = w * x[a];
                xty[a] += wa * self.ys[i];
                for b in 0..=a {
                    xtx[a * k + b] += wa * x[b];
                }
            }
        }
        for a in 0..k {
            for b in 0..a {
                xtx[b * k + a] = xtx[a * k + b];
            }
        }
        let inv = invert_spd(&xtx, k)?;
        let beta: Vec<f64> = (0..k).map(|i| (0..k).map(|j| inv[i * k + j] * xty[j]).sum()).collect();
        // Residuals, dispersion and cluster scores.
        let mut rss = 0.0;
        // Scores per cluster in a sorted map: the meat is summed in cluster order, so the
        // covariance is the same bits on every run and thread count.
        let mut scores: std::collections::BTreeMap<u32, Vec<f64>> = std::collections::BTreeMap::new();
        for i in 0..n {
            let x = &self.xs[i * k..(i + 1) * k];
            let pred: f64 = x.iter().zip(&beta).map(|(a, b)| a * b).sum();
            let e = self.ys[i] - pred;
            rss += self.ws[i] * e * e;
            let s = scores.entry(self.cl[i]).or_insert_with(|| vec![0.0; k]);
            for a in 0..k {
                s[a] += self.ws[i] * x[a] * e;
            }
        }
        let dispersion = rss / (n - k) as f64;
        let g = scores.len();
        let mut meat = vec![0.0; k * k];
        for s in scores.values() {
            for a in 0..k {
                for b in 0..k {
                    meat[a * k + b] += s[a] * s[b];
                }
            }
        }
        // Small-sample correction g/(g-1).
        let corr = if g > 1 { g as f64 / (g - 1) as f64 } else { 1.0 };
        let mut cov = vec![0.0; k * k];
        for i in 0..k {
            for j in 0..k {
                let mut s = 0.0;
                for a in 0..k {
                    for b in 0..k {
                        s += inv[i * k + a] * meat[a * k + b] * inv[b * k + j];
                    }
                }
                cov[i * k + j] = s * corr;
            }
        }
        let cov_model: Vec<f64> = inv.iter().map(|v| v * dispersion.max(1.0)).collect();
        Some(WlsFit { beta, cov, cov_model, dispersion, n, clusters: g })
    }
}

/// Maximum-likelihood mean and standard deviation of a normal variable observed through
/// rounding to a grid of step `q` (`q = 0` for continuous data) and clipping to `[lo, hi]`
/// (interval-censored / Tobit model). `values` are the observations.
///
/// Camera data near black are clipped at 0: the plain mean of a dark region is biased upward by
/// about 0.4 sigma, and its variance downward. This estimator removes both biases.
/// Returns (mu, sigma, se_mu).
pub fn censored_normal_mle(values: &[f64], q: f64, lo: f64, hi: f64) -> Option<(f64, f64, f64)> {
    if values.len() < 20 {
        return None;
    }
    // Histogram on the grid (or on fine bins for continuous data).
    let step = if q > 0.0 { q } else { 1.0 / 64.0 };
    let mut hist: std::collections::BTreeMap<i64, f64> = std::collections::BTreeMap::new();
    for &v in values {
        *hist.entry((v / step).round() as i64).or_insert(0.0) += 1.0;
    }
    let cells: Vec<(f64, f64)> = hist.into_iter().map(|(k, c)| (k as f64 * step, c)).collect();
    let half = if q > 0.0 { q / 2.0 } else { 0.0 };
    let nll = |mu: f64, sigma: f64| -> f64 {
        let mut s = 0.0;
        for &(v, c) in &cells {
            let p = if v <= lo + half * 0.5 {
                norm_cdf((lo + half - mu) / sigma)
            } else if v >= hi - half * 0.5 {
                1.0 - norm_cdf((hi - half - mu) / sigma)
            } else if q > 0.0 {
                norm_cdf((v + half - mu) / sigma) - norm_cdf((v - half - mu) / sigma)
            } else {
                norm_pdf((v - mu) / sigma) / sigma * step
            };
            s -= c * p.max(1e-300).ln();
        }
        s
    };
    // Start from the plain moments.
    let n = values.len() as f64;
    let m0 = values.iter().sum::<f64>() / n;
    let s0 = (values.iter().map(|v| (v - m0).powi(2)).sum::<f64>() / n).sqrt().max(step * 0.3);
    let f = |p: &[f64]| nll(p[0], p[1].exp());
    let best = nelder_mead(&f, &[m0, s0.ln()], &[s0.max(0.2), 0.3], 300, 1e-9);
    let (mu, sigma) = (best[0], best[1].exp());
    // Standard error of mu from the numerical curvature of the log-likelihood.
    let h = (sigma * 0.02).max(1e-4);
    let c = (nll(mu + h, sigma) - 2.0 * nll(mu, sigma) + nll(mu - h, sigma)) / (h * h);
    let se = if c > 0.0 { 1.0 / c.sqrt() } else { sigma / n.sqrt() };
    Some((mu, sigma, se))
}

/// Nelder–Mead simplex minimiser. `step` gives the initial simplex size per coordinate.
pub fn nelder_mead(f: &dyn Fn(&[f64]) -> f64, x0: &[f64], step: &[f64], max_eval: usize, tol: f64) -> Vec<f64> {
    let n = x0.len();
    let mut pts: Vec<Vec<f64>> = vec![x0.to_vec()];
    for i in 0..n {
        let mut p = x0.to_vec();
        p[i] += step[i];
        pts.push(p);
    }
    let mut vals: Vec<f64> = pts.iter().map(|p| f(p)).collect();
    let mut evals = n + 1;
    while evals < max_eval {
        // order
        let mut idx: Vec<usize> = (0..=n).collect();
        idx.sort_by(|&a, &b| vals[a].total_cmp(&vals[b]));
        pts = idx.iter().map(|&i| pts[i].clone()).collect();
        vals = idx.iter().map(|&i| vals[i]).collect();
        if (vals[n] - vals[0]).abs() <= tol * (1.0 + vals[0].abs()) {
            break;
        }
        let mut c = vec![0.0; n];
        for p in &pts[..n] {
            for i in 0..n {
                c[i] += p[i] / n as f64;
            }
        }
        let lerp = |t: f64| -> Vec<f64> { (0..n).map(|i| c[i] + t * (pts[n][i] - c[i])).collect() };
        let xr = lerp(-1.0);
        let fr = f(&xr);
        evals += 1;
        if fr < vals[0] {
            let xe = lerp(-2.0);
            let fe = f(&xe);
            evals += 1;
            if fe < fr {
                pts[n] = xe;
                vals[n] = fe;
            } else {
                pts[n] = xr;
                vals[n] = fr;
            }
        } else if fr < vals[n - 1] {
            pts[n] = xr;
            vals[n] = fr;
        } else {
            let (xc, fc) = if fr < vals[n] {
                let x = lerp(-0.5);
                let v = f(&x);
                (x, v)
            } else {
                let x = lerp(0.5);
                let v = f(&x);
                (x, v)
            };
            evals += 1;
            if fc < vals[n].min(fr) {
                pts[n] = xc;
                vals[n] = fc;
            } else {
                // shrink
                for j in 1..=n {
                    for i in 0..n {
                        pts[j][i] = pts[0][i] + 0.5 * (pts[j][i] - pts[0][i]);
                    }
                    vals[j] = f(&pts[j]);
                    evals += 1;
                }
            }
        }
    }
    let best = (0..=n).min_by(|&a, &b| vals[a].total_cmp(&vals[b])).unwrap_or(0);
    pts[best].clone()
}

/// Golden-section minimisation of a unimodal function on [a, b]; returns (x, f(x)).
pub fn golden(f: &mut dyn FnMut(f64) -> f64, mut a: f64, mut b: f64, iters: usize) -> (f64, f64) {
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let mut c = b - g * (b - a);
    let mut d = a + g * (b - a);
    let mut fc = f(c);
    let mut fd = f(d);
    for _ in 0..iters {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = f(d);
        }
    }
    if fc < fd { (c, fc) } else { (d, fd) }
}

/// Refines the minimum of `f` found on a grid (ascending `grid`, `vals` = f there) by
/// [`golden`] between the best node's neighbours (`iters` steps); returns (x, f(x)). The grid
/// guards against the local minima a golden search alone would settle in.
pub fn golden_around_best(f: &mut dyn FnMut(f64) -> f64, grid: &[f64], vals: &[f64], iters: usize) -> (f64, f64) {
    let ib = (0..grid.len()).min_by(|&a, &b| vals[a].total_cmp(&vals[b])).unwrap_or(0);
    let (lo, hi) = (grid[ib.saturating_sub(1)], grid[(ib + 1).min(grid.len() - 1)]);
    if hi > lo { golden(f, lo, hi, iters) } else { (grid[ib], vals[ib]) }
}

/// Pool-adjacent-violators: the non-increasing sequence closest (weighted least squares) to `y`.
pub fn isotonic_decreasing(y: &[f64], w: &[f64]) -> Vec<f64> {
    let mut blocks: Vec<(f64, f64, usize)> = Vec::new(); // (mean, weight, count)
    for (i, &v) in y.iter().enumerate() {
        blocks.push((v, w[i].max(1e-12), 1));
        while blocks.len() > 1 {
            let n = blocks.len();
            if blocks[n - 2].0 >= blocks[n - 1].0 {
                break;
            }
            let (m2, w2, c2) = blocks[n - 1];
            let (m1, w1, c1) = blocks[n - 2];
            blocks.truncate(n - 2);
            blocks.push(((m1 * w1 + m2 * w2) / (w1 + w2), w1 + w2, c1 + c2));
        }
    }
    blocks.iter().flat_map(|&(m, _, c)| std::iter::repeat_n(m, c)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn quantiles_and_robust_scale() {
        let mut v: Vec<f64> = (0..101).map(|i| i as f64).collect();
        assert_eq!(quantile_mut(&mut v, 0.5), 50.0);
        assert_eq!(quantile_mut(&mut v, 0.25), 25.0);
        let mut r = Rng::new(1);
        let v: Vec<f64> = (0..20000).map(|_| 3.0 * r.normal()).collect();
        assert!((mad_sigma(&v) - 3.0).abs() < 0.1);
        let (var, _) = clipped_variance(&v, 6.0);
        assert!((var.sqrt() - 3.0).abs() < 0.06, "{var}");
    }

    #[test]
    fn normal_functions() {
        assert!((norm_cdf(0.0) - 0.5).abs() < 1e-7);
        assert!((norm_cdf(1.959964) - 0.975).abs() < 1e-6);
        assert!((chi2_sf(3.84, 1.0) - 0.05).abs() < 0.01);
    }

    #[test]
    fn wls_recovers_coefficients_with_honest_errors() {
        let mut r = Rng::new(7);
        let mut w = Wls::new(2);
        for i in 0..5000 {
            let x = r.uniform() * 10.0;
            w.push(&[1.0, x], 2.0 + 0.5 * x + r.normal(), 1.0, (i / 50) as u32);
        }
        let f = w.fit().unwrap();
        assert!((f.beta[0] - 2.0).abs() < 5.0 * f.se(0));
        assert!((f.beta[1] - 0.5).abs() < 5.0 * f.se(1));
        assert!((f.dispersion - 1.0).abs() < 0.1);
    }

    #[test]
    fn censored_mle_removes_clipping_bias() {
        // N(1.0, 2.0) rounded and clipped at 0: the plain mean is biased high.
        let mut r = Rng::new(3);
        let v: Vec<f64> = (0..40000).map(|_| (1.0 + 2.0 * r.normal()).round().max(0.0)).collect();
        let plain = v.iter().sum::<f64>() / v.len() as f64;
        let (mu, sigma, se) = censored_normal_mle(&v, 1.0, 0.0, 255.0).unwrap();
        assert!(plain > 1.3, "plain mean {plain} should be biased");
        assert!((mu - 1.0).abs() < 5.0 * se + 0.02, "mu {mu} se {se}");
        assert!((sigma - 2.0).abs() < 0.06, "sigma {sigma}");
    }

    #[test]
    fn isotonic_is_monotone() {
        let y = [5.0, 6.0, 4.0, 4.5, 1.0];
        let f = isotonic_decreasing(&y, &[1.0; 5]);
        for i in 1..f.len() {
            assert!(f[i] <= f[i - 1] + 1e-12);
        }
    }

    #[test]
    fn minimisers_find_minimum() {
        let f = |p: &[f64]| (p[0] - 1.0).powi(2) + 3.0 * (p[1] + 2.0).powi(2);
        let x = nelder_mead(&f, &[0.0, 0.0], &[0.5, 0.5], 500, 1e-14);
        assert!((x[0] - 1.0).abs() < 1e-3 && (x[1] + 2.0).abs() < 1e-3);
        let (x, _) = golden(&mut |t| (t - 0.3).powi(2), -1.0, 2.0, 60);
        assert!((x - 0.3).abs() < 1e-6);
    }
}
