//! Camera noise: variance against signal (`shot_noise`, `gaussian_noise`) and the dark level.
//!
//! The residual `r = real - sim` is high-passed along x with the second difference
//! `h = r(x) - (r(x-1) + r(x+1)) / 2`, only where the sim is locally linear (so every smooth or
//! deterministic difference — vignetting, stray light, gain, blur of a linear ramp — cancels) and
//! nothing is clipped. For white noise `var(h) = 1.5 var(n)`. Binned by sim level `s`, the
//! variance follows `var(s) = a + b s + c s^2`: `a` is read noise (plus quantisation `q^2/12`),
//! `b = 1 / gain_e_per_dn` is photon noise and `c = prnu sigma^2` (fixed pattern, measured
//! separately across frames and then held fixed here).
//!
//! The dark level (sim = 0) is measured by an interval-censored normal fit, which removes the
//! bias of clipping at 0 (the plain mean of clipped N(0, s^2) is 0.4 s, not 0).

use super::img::{FS, Pair};
use super::locate::Masks;
use super::stats::{self, Wls};

/// Noise model in 8-bit DN.
#[derive(Debug, Clone, serde::Serialize)]
pub struct NoiseModel {
    /// Variance intercept (DN^2), including quantisation.
    pub a: f64,
    pub se_a: f64,
    /// Variance per DN of signal (1 / gain_e_per_dn).
    pub b: f64,
    pub se_b: f64,
    /// Variance per DN^2 of signal (prnu sigma^2).
    pub c: f64,
    /// Quantisation step of the real data (1 for 8-bit files, 1/257 for 16-bit).
    pub quant: f64,
    /// Binned measurements: (level, variance, count).
    pub bins: Vec<(f64, f64, usize)>,
    /// Censored-normal fit of real where sim is black, far from anything bright.
    pub dark: Option<DarkLevel>,
    /// Levels used by the fit.
    pub fit_range: (f64, f64),
}

/// Dark level where the sim is black.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct DarkLevel {
    pub mu: f64,
    pub sigma: f64,
    pub se_mu: f64,
    pub n: usize,
}

impl NoiseModel {
    /// Predicted noise variance (DN^2) at signal `s` (DN).
    #[inline]
    pub fn var(&self, s: f64) -> f64 {
        let s = s.clamp(0.0, FS as f64);
        (self.a + self.b * s + self.c * s * s).max(self.quant * self.quant / 12.0 + 0.02)
    }
    pub fn sd(&self, s: f64) -> f64 {
        self.var(s).sqrt()
    }
    /// Read noise standard deviation without quantisation (DN).
    pub fn read_sigma(&self) -> f64 {
        (self.a - self.quant * self.quant / 12.0).max(0.0).sqrt()
    }
    /// A flat prior model for the start of the analysis.
    pub fn prior(quant: f64) -> NoiseModel {
        NoiseModel {
            a: 4.0,
            se_a: f64::INFINITY,
            b: 0.1,
            se_b: f64::INFINITY,
            c: 0.0,
            quant,
            bins: Vec::new(),
            dark: None,
            fit_range: (0.0, FS as f64),
        }
    }
}

const BIN: f64 = 4.0;
const NBINS: usize = 64;

/// Collect the high-pass samples per level bin. `skip` marks pixels to leave out (hot pixels).
fn collect(pairs: &[Pair], masks: &[Masks], skip: Option<&[Vec<bool>]>) -> Vec<Vec<f32>> {
    let mut bins: Vec<Vec<f32>> = vec![Vec::new(); NBINS];
    for (k, p) in pairs.iter().enumerate() {
        let m = &masks[k];
        let (w, h) = (p.w(), p.h());
        // Subsample large frames: at most ~600k samples per frame and channel.
        let step = ((w * h) / 600_000).max(1);
        for c in 0..p.channels() {
            let s = &p.sim[c].data;
            let r = &p.real[c].data;
            for y in 0..h {
                if y % step != 0 {
                    continue;
                }
                for x in 1..w - 1 {
                    let i = y * w + x;
                    if !(m.linear[i - 1] && m.linear[i] && m.linear[i + 1]) || m.sat_near[i] {
                        continue;
                    }
                    if let Some(sk) = skip
                        && (sk[k][i - 1] || sk[k][i] || sk[k][i + 1])
                    {
                        continue;
                    }
                    let (r0, r1, r2) = (r[i - 1], r[i], r[i + 1]);
                    if r0 <= 0.0 || r1 <= 0.0 || r2 <= 0.0 || r0 >= FS || r1 >= FS || r2 >= FS {
                        continue;
                    }
                    let hp = (r1 - s[i]) - 0.5 * ((r0 - s[i - 1]) + (r2 - s[i + 1]));
                    let b = ((s[i] as f64 / BIN) as usize).min(NBINS - 1);
                    bins[b].push(hp);
                }
            }
        }
    }
    bins
}

/// Estimate the noise model. `prnu_c` is the fixed-pattern variance coefficient (sigma^2)
/// measured across frames (0 if none); `skip` excludes hot pixels.
pub fn estimate(pairs: &[Pair], masks: &[Masks], quant: f64, prnu_c: f64, skip: Option<&[Vec<bool>]>) -> NoiseModel {
    let raw = collect(pairs, masks, skip);
    let mut bins = Vec::new();
    for (i, v) in raw.iter().enumerate() {
        if v.len() < 200 {
            continue;
        }
        let vv: Vec<f64> = v.iter().map(|&x| x as f64).collect();
        let lvl = {
            // mean level of the bin is its centre (sim values are spread within it)
            (i as f64 + 0.5) * BIN
        };
        let (var, n) = stats::clipped_variance(&vv, 5.0);
        if var.is_finite() {
            bins.push((lvl, var / 1.5, n));
        }
    }
    let dark = dark_level(pairs, masks, quant);
    let mut model = NoiseModel::prior(quant);
    model.c = prnu_c;
    model.bins = bins.clone();
    model.dark = dark;
    // Iterate: the usable range depends on the noise level (clipping within 3 sigma of 0/FS).
    let mut lo = 6.0;
    for _ in 0..3 {
        let hi_sd = model.sd(FS as f64);
        let hi = FS as f64 - 3.0 * hi_sd - BIN;
        let use_bins: Vec<&(f64, f64, usize)> = bins.iter().filter(|b| b.0 >= lo && b.0 <= hi).collect();
        let fitted = if use_bins.len() >= 2 {
            let mut w = Wls::new(2);
            for (i, &&(l, v, n)) in use_bins.iter().enumerate() {
                let y = v - prnu_c * l * l;
                let guess = model.var(l).max(0.05);
                // var of a variance estimate ~ 2 v^2 / n
                w.push(&[1.0, l], y, n as f64 / (2.0 * guess * guess), i as u32);
            }
            w.fit().map(|f| (f.beta[0], f.se(0), f.beta[1], f.se(1)))
        } else {
            None
        };
        match fitted {
            Some((a, se_a, b, se_b)) => {
                // A negative slope is not physical: refit the intercept alone.
                if b < 0.0 {
                    let (m, se) = weighted_mean(&use_bins, prnu_c);
                    model.a = m;
                    model.se_a = se;
                    model.b = 0.0;
                    model.se_b = se_b;
                } else {
                    model.a = a;
                    model.se_a = se_a;
                    model.b = b;
                    model.se_b = se_b;
                }
            }
            None => {
                if !use_bins.is_empty() {
                    let (m, se) = weighted_mean(&use_bins, prnu_c);
                    let l = use_bins[0].0;
                    // One level only: split between read and photon noise is unknown; take it as read
                    // noise unless the dark fit says the intercept is smaller.
                    match dark {
                        Some(d) if d.sigma * d.sigma < m && l > 0.0 => {
                            model.a = d.sigma * d.sigma;
                            model.b = ((m - model.a) / l).max(0.0);
                        }
                        _ => {
                            model.a = m;
                            model.b = 0.0;
                        }
                    }
                    model.se_a = se;
                    model.se_b = f64::INFINITY;
                } else if let Some(d) = dark {
                    model.a = d.sigma * d.sigma + quant * quant / 12.0;
                    model.se_a = model.a * (2.0 / d.n as f64).sqrt();
                    model.b = 0.0;
                    model.se_b = f64::INFINITY;
                }
            }
        }
        model.fit_range = (lo, hi);
        lo = (3.0 * model.read_sigma()).max(4.0);
    }
    model.a = model.a.max(quant * quant / 12.0);
    model
}

fn weighted_mean(bins: &[&(f64, f64, usize)], prnu_c: f64) -> (f64, f64) {
    let mut sw = 0.0;
    let mut s = 0.0;
    for &&(l, v, n) in bins {
        let w = n as f64 / (2.0 * v.max(0.05).powi(2));
        s += w * (v - prnu_c * l * l);
        sw += w;
    }
    (s / sw, (1.0 / sw).sqrt())
}

/// Censored-normal fit of the real values where the sim is black and far from edges and
/// saturation.
pub fn dark_level(pairs: &[Pair], masks: &[Masks], quant: f64) -> Option<DarkLevel> {
    let mut vals = Vec::new();
    for (k, p) in pairs.iter().enumerate() {
        let m = &masks[k];
        for c in 0..p.channels() {
            let s = &p.sim[c].data;
            let r = &p.real[c].data;
            for i in 0..s.len() {
                if s[i] <= 0.25 && m.flat[i] && m.dist_sat[i] > 15.0 && m.dist_edge[i] > 6.0 {
                    vals.push(r[i] as f64);
                }
            }
        }
    }
    if vals.len() < 500 {
        return None;
    }
    // Cap the sample (deterministic thinning) to keep the fit fast.
    if vals.len() > 400_000 {
        let step = vals.len() / 400_000 + 1;
        vals = vals.into_iter().step_by(step).collect();
    }
    let n = vals.len();
    stats::censored_normal_mle(&vals, quant, 0.0, FS as f64).map(|(mu, sigma, se_mu)| DarkLevel { mu, sigma, se_mu, n })
}
