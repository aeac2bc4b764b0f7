//! Level response: what a tone curve, a gain and offset and a dark level each do to the mapping
//! from the model's level to the real level, told apart by its shape.
//!
//! The library's tone effects (`gamma`: a pure power law, `gain_offset`: a straight line,
//! `dark_current`: an additive level) are each one shape. A camera's tone curve is often neither
//! a pure power nor a line: sRGB-like curves have a linear toe from the origin and an offset power
//! law above it, which over the mid-tones is close to a gain and offset. The physics that tells
//! them apart is in the level response `m(s) = E[real | model level s]`:
//!
//! * a **tone curve** fixes 0 and full scale (`m(0) = 0`, `m(FS) = FS`) and bends in between;
//! * a **gain and offset** is straight, with `m(0) = offset` and `m(FS) = gain·FS + offset`;
//! * a **dark level under a tone curve** is a tone curve of `s + d`: an offset at zero signal,
//!   full scale still fixed, and the curvature of the tone curve.
//!
//! [`level_response`] measures `m(s)` in 1-DN bins of the model level on pixels away from edges
//! and saturation, with a censored (Tobit) mean where the real values are clipped at 0, so that
//! the offset at zero signal is measured on black regions too. [`readings`] fits each reading's
//! shape to it by weighted least squares — the tone curves in a generalised sRGB family (linear
//! toe tangent to an offset power law, in the encoding form `(1+a)x^q − a` or the decoding form
//! `((x+a)/(1+a))^q`, which include the pure power law as a → 0) — and compares them by an
//! information criterion with a quasi-likelihood scale (the χ² of the best reading per degree of
//! freedom, when above 1). A tone curve's `gamma` is reported as the power law closest to the
//! fitted curve in least squares over [0, FS] (the usual convention for a non-power curve).
//!
//! The module depends only on shared types (planes, the noise model); the selection
//! ([`super::select`]) decides what to do with the readings.

use super::common::NoiseModel;
use super::img::FS;
use super::stats;

/// One bin of the level response.
#[derive(Debug, Clone, Copy)]
pub struct LevelPoint {
    /// Mean model level of the bin (8-bit DN).
    pub s: f64,
    /// Mean real level (censored estimate where real is clipped at 0), DN.
    pub m: f64,
    /// Standard error of `m`, DN.
    pub se: f64,
    /// Pixels in the bin.
    pub n: usize,
}

/// Accumulates real values per 1-DN bin of the model level.
pub struct LevelAcc {
    sum_s: Vec<f64>,
    sum_r: Vec<f64>,
    zeros: Vec<usize>,
    fulls: Vec<usize>,
    n: Vec<usize>,
}

impl Default for LevelAcc {
    fn default() -> Self {
        LevelAcc {
            sum_s: vec![0.0; 256],
            sum_r: vec![0.0; 256],
            zeros: vec![0; 256],
            fulls: vec![0; 256],
            n: vec![0; 256],
        }
    }
}

impl LevelAcc {
    /// Add one pixel: model level `s`, real value `r` (DN).
    #[inline]
    pub fn push(&mut self, s: f64, r: f64) {
        let b = s.round().clamp(0.0, 255.0) as usize;
        self.sum_s[b] += s;
        self.sum_r[b] += r;
        self.n[b] += 1;
        if r <= 0.0 {
            self.zeros[b] += 1;
        }
        if r >= FS as f64 {
            self.fulls[b] += 1;
        }
    }
}

/// Mean of the read value of X ~ N(μ, σ²) when values below `c` read 0 and values above `h` read
/// full scale (the ADC's range; `c` and `h` half a quantisation step inside it).
fn censored_mean(mu: f64, sd: f64, c: f64, h: f64) -> f64 {
    let (a, b) = ((c - mu) / sd, (h - mu) / sd);
    let (pa, pb) = (stats::norm_cdf(a), stats::norm_cdf(b));
    mu * (pb - pa) + sd * (stats::norm_pdf(a) - stats::norm_pdf(b)) + FS as f64 * (1.0 - pb)
}

/// The level response from the accumulated pixels. Bins with fewer than 30 pixels, and bins
/// where more than half of the real values are clipped (at 0 or at full scale), are left out;
/// in the others the clipped values are censored observations (a two-sided Tobit mean), so that
/// the offset at zero signal is measured on black regions and the response near full scale on
/// bright ones — where a gain and offset (which moves full scale) and a tone curve (which fixes
/// it) differ most.
pub fn level_response(acc: &LevelAcc, noise: &NoiseModel) -> Vec<LevelPoint> {
    let c = 0.5 * noise.quant;
    let h = FS as f64 - 0.5 * noise.quant;
    let mut out = Vec::new();
    for b in 0..256 {
        let n = acc.n[b];
        if n < 30 {
            continue;
        }
        let s = acc.sum_s[b] / n as f64;
        let mean = acc.sum_r[b] / n as f64;
        let sd = noise.sd(mean.clamp(0.0, FS as f64)).max(0.3);
        let clipped = acc.zeros[b] + acc.fulls[b];
        if 2 * clipped > n {
            continue;
        }
        let m = if clipped > 0 {
            // Solve censored_mean(μ) = mean for μ (monotone increasing).
            let (mut lo, mut hi) = (-10.0 * sd, FS as f64 + 10.0 * sd);
            for _ in 0..80 {
                let mid = 0.5 * (lo + hi);
                if censored_mean(mid, sd, c, h) < mean {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            0.5 * (lo + hi)
        } else {
            mean
        };
        // Clipped values carry less information: inflate by the censored fraction.
        let frac = clipped as f64 / n as f64;
        let se = sd / (n as f64 * (1.0 - frac).max(0.05)).sqrt();
        out.push(LevelPoint { s, m, se: (se * se + SYS_DN * SYS_DN).sqrt(), n });
    }
    out
}

/// Systematic floor of a bin's standard error (DN): the level response of the model is not
/// known better than this (scene structure, noise-model mismatch).
const SYS_DN: f64 = 0.05;

/// A shape of the level response.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// `s + d`.
    Dark,
    /// `g·s + o`.
    Affine,
    /// Generalised sRGB tone curve of `s` (encoding or decoding form; `a → 0` is a power law).
    Tone,
    /// Tone curve of `s + d`.
    DarkTone,
    /// Power law of `g·s + o` (the library's gain_offset followed by gamma).
    AffinePower,
}

impl Shape {
    /// The library effects that model this shape.
    pub fn effects(self) -> &'static [&'static str] {
        match self {
            Shape::Dark => &["dark_current"],
            Shape::Affine => &["gain_offset"],
            Shape::Tone => &["gamma"],
            Shape::DarkTone => &["dark_current", "gamma"],
            Shape::AffinePower => &["gain_offset", "gamma"],
        }
    }
    pub fn describe(self) -> &'static str {
        match self {
            Shape::Dark => "an offset (dark level)",
            Shape::Affine => "a straight gain and offset",
            Shape::Tone => "a tone curve fixing 0 and full scale",
            Shape::DarkTone => "a dark level under a tone curve",
            Shape::AffinePower => "a gain and offset under a power law",
        }
    }
}

/// The fitted reading of one shape.
#[derive(Debug, Clone)]
pub struct Reading {
    pub shape: Shape,
    /// Parameters: `d` (dark, DN), `g`, `o` (gain, offset DN), `q`, `a` (tone curve), and for
    /// a tone curve `gamma` = the least-squares power law of the fitted curve.
    pub d: f64,
    pub g: f64,
    pub o: f64,
    pub q: f64,
    pub a: f64,
    pub encode: bool,
    pub gamma: f64,
    /// Weighted sum of squares.
    pub chi2: f64,
    /// Parameters fitted.
    pub k: usize,
    /// Information criterion on the quasi-likelihood scale (filled by [`readings`]).
    pub bic: f64,
}

/// Generalised sRGB tone curve at x in [0, 1]: an offset power law with a linear toe from the
/// origin tangent to it. `encode`: `(1+a)x^q − a` (q < 1); else `((x+a)/(1+a))^q` (q > 1). With
/// a = 0 (or q = 1) it is the power law `x^q`.
pub fn tone_curve(x: f64, q: f64, a: f64, encode: bool) -> f64 {
    let x = x.clamp(0.0, 1.0);
    if a <= 0.0 || (q - 1.0).abs() < 1e-9 {
        return x.powf(q);
    }
    let f = |x: f64| if encode { (1.0 + a) * x.powf(q) - a } else { ((x + a) / (1.0 + a)).powf(q) };
    let x0 = if encode { (a / ((1.0 + a) * (1.0 - q))).powf(1.0 / q) } else { a / (q - 1.0) };
    if x0 >= 1.0 {
        return x * f(1.0);
    }
    if x < x0 { x * f(x0) / x0 } else { f(x) }
}

/// The power law closest to `f` in least squares over 1001 evenly spaced x in [0, 1].
pub fn ls_power(f: &dyn Fn(f64) -> f64) -> f64 {
    let xs: Vec<(f64, f64)> = (0..=1000).map(|i| i as f64 / 1000.0).map(|x| (x, f(x))).collect();
    let mut cost = |g: f64| xs.iter().map(|&(x, y)| (x.powf(g) - y).powi(2)).sum::<f64>();
    stats::golden(&mut cost, 0.3, 3.0, 80).0
}

fn predict(r: &Reading, s: f64) -> f64 {
    let fs = FS as f64;
    match r.shape {
        Shape::Dark => s + r.d,
        Shape::Affine => r.g * s + r.o,
        Shape::Tone => fs * tone_curve(s / fs, r.q, r.a, r.encode),
        Shape::DarkTone => fs * tone_curve((s + r.d) / fs, r.q, r.a, r.encode),
        Shape::AffinePower => fs * ((r.g * s + r.o).clamp(0.0, fs) / fs).powf(r.q),
    }
}

/// Largest difference (DN) between the responses two readings predict over the levels the
/// data have (the bins' sim levels): where it is small, the readings make the same claim about
/// every pixel there is, and what distinguishes them lies outside the data.
pub fn max_difference(a: &Reading, b: &Reading, pts: &[LevelPoint]) -> f64 {
    pts.iter().map(|p| (predict(a, p.s) - predict(b, p.s)).abs()).fold(0.0, f64::max)
}

fn chi2(r: &Reading, pts: &[LevelPoint]) -> f64 {
    pts.iter().map(|p| ((p.m - predict(r, p.s)) / p.se).powi(2)).sum()
}

/// Nelder–Mead over bounded parameters (clamped into their ranges), restarted from its best
/// point, from each of `starts`.
fn minimise(r: &mut Reading, pts: &[LevelPoint], coords: &[Coord1], starts: &[Vec<f64>]) {
    let k = coords.len();
    let eval = |x: &[f64], r: &Reading| -> f64 {
        let mut t = r.clone();
        for (c, &v) in coords.iter().zip(x) {
            *(c.0)(&mut t) = v.clamp(c.1, c.2);
        }
        chi2(&t, pts)
    };
    let mut best: Option<(Vec<f64>, f64)> = None;
    for start in starts {
        let mut x0 = start.clone();
        for _restart in 0..3 {
            let mut simplex: Vec<(Vec<f64>, f64)> = Vec::with_capacity(k + 1);
            let f0 = eval(&x0, r);
            simplex.push((x0.clone(), f0));
            for i in 0..k {
                let mut x = x0.clone();
                let step = 0.1 * (coords[i].2 - coords[i].1);
                x[i] = if x[i] + step <= coords[i].2 { x[i] + step } else { x[i] - step };
                let f = eval(&x, r);
                simplex.push((x, f));
            }
            for _ in 0..400 {
                simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
                let worst = simplex[k].clone();
                let centroid: Vec<f64> =
                    (0..k).map(|i| simplex[..k].iter().map(|p| p.0[i]).sum::<f64>() / k as f64).collect();
                let at = |t: f64| -> Vec<f64> {
                    centroid
                        .iter()
                        .zip(&worst.0)
                        .enumerate()
                        .map(|(i, (c, w))| (c + t * (w - c)).clamp(coords[i].1, coords[i].2))
                        .collect()
                };
                let xr = at(-1.0);
                let fr = eval(&xr, r);
                if fr < simplex[0].1 {
                    let xe = at(-2.0);
                    let fe = eval(&xe, r);
                    simplex[k] = if fe < fr { (xe, fe) } else { (xr, fr) };
                } else if fr < simplex[k - 1].1 {
                    simplex[k] = (xr, fr);
                } else {
                    let xc = at(0.5);
                    let fc = eval(&xc, r);
                    if fc < worst.1 {
                        simplex[k] = (xc, fc);
                    } else {
                        let b = simplex[0].0.clone();
                        for p in simplex.iter_mut().skip(1) {
                            p.0 = p.0.iter().zip(&b).map(|(x, y)| y + 0.5 * (x - y)).collect();
                            p.1 = eval(&p.0, r);
                        }
                    }
                }
                if (simplex[k].1 - simplex[0].1).abs() <= 1e-9 * (1.0 + simplex[0].1.abs()) {
                    break;
                }
            }
            simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
            x0 = simplex[0].0.clone();
            if best.as_ref().is_none_or(|b| simplex[0].1 < b.1) {
                best = Some(simplex[0].clone());
            }
        }
    }
    if let Some((x, _)) = best {
        for (c, &v) in coords.iter().zip(&x) {
            *(c.0)(r) = v.clamp(c.1, c.2);
        }
    }
    r.chi2 = chi2(r, pts);
}

fn q_of(r: &mut Reading) -> &mut f64 {
    &mut r.q
}
fn a_of(r: &mut Reading) -> &mut f64 {
    &mut r.a
}
fn d_of(r: &mut Reading) -> &mut f64 {
    &mut r.d
}
fn g_of(r: &mut Reading) -> &mut f64 {
    &mut r.g
}
fn o_of(r: &mut Reading) -> &mut f64 {
    &mut r.o
}

type Coord1 = (fn(&mut Reading) -> &mut f64, f64, f64);

fn blank(shape: Shape, k: usize) -> Reading {
    Reading { shape, d: 0.0, g: 1.0, o: 0.0, q: 1.0, a: 0.0, encode: true, gamma: 1.0, chi2: 0.0, k, bic: 0.0 }
}

/// Fit every shape to the level response and score it. `n_values` is the number of pixel values
/// behind the bins (the BIC's sample size). Sorted best (lowest `bic`) first.
pub fn readings(pts: &[LevelPoint], n_values: usize) -> Vec<Reading> {
    if pts.len() < 8 {
        return Vec::new();
    }
    let fs = FS as f64;
    let mut out = Vec::new();
    // Dark: closed form.
    let mut dark = blank(Shape::Dark, 1);
    let (sw, swd) = pts.iter().fold((0.0, 0.0), |(a, b), p| (a + 1.0 / (p.se * p.se), b + (p.m - p.s) / (p.se * p.se)));
    dark.d = swd / sw;
    dark.chi2 = chi2(&dark, pts);
    out.push(dark);
    // Affine: weighted least squares.
    let mut aff = blank(Shape::Affine, 2);
    let (mut s0, mut s1, mut s2, mut t0, mut t1) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in pts {
        let w = 1.0 / (p.se * p.se);
        s0 += w;
        s1 += w * p.s;
        s2 += w * p.s * p.s;
        t0 += w * p.m;
        t1 += w * p.s * p.m;
    }
    let det = s0 * s2 - s1 * s1;
    if det > 0.0 {
        aff.g = (s0 * t1 - s1 * t0) / det;
        aff.o = (t0 - aff.g * s1) / s0;
    }
    aff.chi2 = chi2(&aff, pts);
    out.push(aff);
    // Tone curves, both forms (each includes the power law as a → 0).
    for with_dark in [false, true] {
        let mut best: Option<Reading> = None;
        for encode in [true, false] {
            let (shape, k) = if with_dark { (Shape::DarkTone, 3) } else { (Shape::Tone, 2) };
            let mut r = blank(shape, k);
            r.encode = encode;
            let (qlo, qhi) = if encode { (0.5, 0.9999) } else { (1.0001, 2.0) };
            let mut coords: Vec<Coord1> = vec![(q_of as fn(&mut Reading) -> &mut f64, qlo, qhi), (a_of, 0.0, 0.25)];
            let qs: &[f64] = if encode { &[0.95, 0.85, 0.7] } else { &[1.05, 1.15, 1.4] };
            let mut starts: Vec<Vec<f64>> = Vec::new();
            for &q in qs {
                for a in [0.0, 0.03, 0.1] {
                    if with_dark {
                        for d in [0.0, dark_guess(&out[0])] {
                            starts.push(vec![q, a, d]);
                        }
                    } else {
                        starts.push(vec![q, a]);
                    }
                }
            }
            if with_dark {
                coords.push((d_of, -10.0, 30.0));
            }
            minimise(&mut r, pts, &coords, &starts);
            if best.as_ref().is_none_or(|b| r.chi2 < b.chi2) {
                best = Some(r);
            }
        }
        if let Some(mut r) = best {
            let (q, a, enc) = (r.q, r.a, r.encode);
            r.gamma = ls_power(&|x| tone_curve(x, q, a, enc));
            out.push(r);
        }
    }
    // Gain and offset under a power law (gain_offset then gamma).
    let mut ap = blank(Shape::AffinePower, 3);
    let starts: Vec<Vec<f64>> = [0.9, 1.0, 1.1].iter().map(|&q| vec![q, out[1].g, out[1].o]).collect();
    minimise(
        &mut ap,
        pts,
        &[(q_of as fn(&mut Reading) -> &mut f64, 0.5, 2.0), (g_of, 0.7, 1.3), (o_of, -20.0, 30.0)],
        &starts,
    );
    ap.gamma = ap.q;
    out.push(ap);
    // Quasi-likelihood scale: the best reading's χ² per degree of freedom, when above 1.
    let best = out.iter().map(|r| r.chi2 / (pts.len() - r.k).max(1) as f64).fold(f64::INFINITY, f64::min);
    let phi = best.max(1.0);
    let ln_n = (n_values.max(2) as f64).ln();
    for r in &mut out {
        r.bic = r.chi2 / phi + r.k as f64 * ln_n;
    }
    let _ = fs;
    out.sort_by(|a, b| a.bic.total_cmp(&b.bic));
    out
}

fn dark_guess(dark: &Reading) -> f64 {
    dark.d.clamp(-5.0, 20.0)
}

/// Best reading whose effect set is exactly `effects` (any order).
pub fn reading_of<'a>(rs: &'a [Reading], effects: &[&str]) -> Option<&'a Reading> {
    rs.iter().find(|r| {
        let e = r.shape.effects();
        e.len() == effects.len() && e.iter().all(|x| effects.contains(x))
    })
}

impl Reading {
    /// One line for the report.
    pub fn describe(&self) -> String {
        let fs = FS as f64;
        let curve = match self.shape {
            Shape::Dark => format!("real = sim {:+.2} DN", self.d),
            Shape::Affine => format!("real = {:.4}·sim {:+.2} DN", self.g, self.o),
            Shape::Tone | Shape::DarkTone => format!(
                "{} tone curve q = {:.3}, a = {:.3} (closest power law gamma = {:.3}){}",
                if self.a < 1e-3 {
                    "power-law"
                } else if self.encode {
                    "generalised sRGB (1+a)x^q−a"
                } else {
                    "generalised sRGB ((x+a)/(1+a))^q"
                },
                self.q,
                self.a,
                self.gamma,
                if self.shape == Shape::DarkTone { format!(" of sim {:+.2} DN", self.d) } else { String::new() }
            ),
            Shape::AffinePower => format!("power {:.3} of {:.4}·sim {:+.2} DN", self.q, self.g, self.o),
        };
        format!(
            "{} ({curve}; response at zero signal {:.2} DN, at full scale {:.1} DN; χ² {:.1}, BIC {:.1})",
            self.shape.describe(),
            predict(self, 0.0),
            predict(self, fs),
            self.chi2,
            self.bic
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pts_of(f: &dyn Fn(f64) -> f64) -> Vec<LevelPoint> {
        (2..240).step_by(2).map(|s| LevelPoint { s: s as f64, m: f(s as f64), se: 0.1, n: 1000 }).collect()
    }

    #[test]
    fn tone_curve_fixes_zero_and_full_scale_and_is_continuous() {
        for (q, a, enc) in [(0.9, 0.02, true), (1.1, 0.02, false), (0.8, 0.1, true), (1.3, 0.05, false)] {
            assert_eq!(tone_curve(0.0, q, a, enc), 0.0);
            assert!((tone_curve(1.0, q, a, enc) - 1.0).abs() < 1e-12);
            let mut prev = 0.0;
            for i in 1..=1000 {
                let y = tone_curve(i as f64 / 1000.0, q, a, enc);
                assert!(y > prev && y - prev < 0.01, "q {q} a {a}: not continuous and increasing at {i}");
                prev = y;
            }
        }
        assert!((ls_power(&|x| x.powf(0.9)) - 0.9).abs() < 1e-4);
    }

    /// h27tone: bins whose real values are partly clipped (at 0 below, at full scale above) are
    /// read as censored means, so the level near full scale — where a tone curve and a gain and
    /// offset differ most — is measured without the clipping's bias.
    #[test]
    fn clipped_bins_are_read_as_censored_means_at_both_ends() {
        let noise = NoiseModel::prior(1.0);
        let mut rng = crate::rng::Rng::new(27);
        let mut acc = LevelAcc::default();
        for (s, mu) in [(2.0, 1.5), (250.0, 252.0), (120.0, 121.0)] {
            let sd = noise.sd(mu);
            for _ in 0..20_000 {
                let r = (mu + sd * rng.normal()).round().clamp(0.0, FS as f64);
                acc.push(s, r);
            }
        }
        let pts = level_response(&acc, &noise);
        assert_eq!(pts.len(), 3);
        for (p, mu) in pts.iter().zip([1.5, 121.0, 252.0]) {
            let raw = acc.sum_r[p.s.round() as usize] / acc.n[p.s.round() as usize] as f64;
            assert!((p.m - mu).abs() < 0.25, "bin {}: censored mean {:.2} vs truth {mu} (raw {raw:.2})", p.s, p.m);
        }
        // The raw mean of the top bin is biased low by the clipping, the censored one is not.
        let raw_top = acc.sum_r[250] / acc.n[250] as f64;
        assert!(252.0 - raw_top > 0.5, "raw top mean {raw_top:.2}");
    }

    /// Each shape, made exactly, is read as itself; a gain and offset is not read as a tone
    /// curve and a tone curve not as a gain and offset.
    #[test]
    fn each_shape_is_read_as_itself() {
        let fs = FS as f64;
        type ShapeCase = (Shape, Box<dyn Fn(f64) -> f64>);
        let cases: Vec<ShapeCase> = vec![
            (Shape::Affine, Box::new(|s| 1.05 * s - 2.0)),
            (Shape::Dark, Box::new(|s| s + 3.0)),
            (Shape::Tone, Box::new(move |s| fs * tone_curve(s / fs, 0.9, 0.02, true))),
            (Shape::Tone, Box::new(move |s| fs * (s / fs).powf(0.92))),
            (Shape::DarkTone, Box::new(move |s| fs * tone_curve((s + 3.0) / fs, 0.9, 0.02, true))),
        ];
        for (shape, f) in cases {
            let rs = readings(&pts_of(&*f), 100_000);
            assert_eq!(rs[0].shape, shape, "{shape:?} read as {}", rs[0].describe());
        }
    }
}
