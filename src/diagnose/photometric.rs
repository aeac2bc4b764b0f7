//! Global photometric alignment: one weighted regression of `real - sim` on smooth, low-order
//! functions of the sim level and the position, fitted on flat regions far from saturation.
//!
//! ```text
//! real - sim = o + (g-1) s + G(γ-1) s ln(s/FS) + s (v2 ρ² + v4 ρ⁴) + Σ a_ij P_i(x̃) P_j(ỹ)
//! ```
//!
//! * `o` — additive level (dark current or an offset), also measured on black regions by a
//!   censored-normal fit per 32x32 block (those blocks enter as extra rows with no signal term);
//! * `g` — gain (`gain_offset`); `γ` — tone curve (`gamma`, linearised at γ = 1);
//! * `v2, v4` — radial multiplicative falloff (`vignetting`; ρ = 1 at the corners, so the gain at
//!   the corners relative to the centre is `1 + (v2 + v4) / g`);
//! * `a_ij` — smooth additive field (`stray_light`): Legendre polynomials of total degree 1..3.
//!
//! Every column is a linear function of the unknowns, so one weighted least-squares solve gives
//! all estimates and a cluster-robust covariance (clusters: 32x32 blocks of one frame). Each
//! effect is then a Wald test on its group of coefficients.

use super::common::{Masks, NoiseModel};
use super::img::{FS, Pair};
use super::stats::{self, Wls, WlsFit};
use super::types::{Profile, Signature};

pub const K: usize = 14;
pub const I_OFF: usize = 0;
pub const I_GAIN: usize = 1;
pub const I_GAMMA: usize = 2;
pub const I_V2: usize = 3;
pub const I_V4: usize = 4;
pub const I_STRAY: usize = 5;

/// Legendre polynomial P_n(t), n <= 3.
#[inline]
pub fn legendre(n: usize, t: f64) -> f64 {
    match n {
        0 => 1.0,
        1 => t,
        2 => 0.5 * (3.0 * t * t - 1.0),
        _ => 0.5 * (5.0 * t * t * t - 3.0 * t),
    }
}

/// Degree pairs (i, j) of the stray-light basis.
pub const STRAY_TERMS: [(usize, usize); 9] = [(1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3)];

/// Normalised coordinates: x̃, ỹ in [-1, 1], ρ² = 1 at the corners.
#[inline]
pub fn coords(x: usize, y: usize, w: usize, h: usize) -> (f64, f64, f64) {
    let cx = (w as f64 - 1.0) / 2.0;
    let cy = (h as f64 - 1.0) / 2.0;
    let dx = x as f64 - cx;
    let dy = y as f64 - cy;
    let xn = if cx > 0.0 { dx / cx } else { 0.0 };
    let yn = if cy > 0.0 { dy / cy } else { 0.0 };
    let rho2 = (dx * dx + dy * dy) / (cx * cx + cy * cy).max(1e-9);
    (xn, yn, rho2)
}

/// Regressor row for a pixel with sim level `s` (8-bit DN) at normalised position.
#[inline]
pub fn row(s: f64, xn: f64, yn: f64, rho2: f64, out: &mut [f64; K]) {
    out[I_OFF] = 1.0;
    out[I_GAIN] = s;
    out[I_GAMMA] = if s > 0.0 { s * (s / FS as f64).ln() } else { 0.0 };
    out[I_V2] = s * rho2;
    out[I_V4] = s * rho2 * rho2;
    for (k, &(i, j)) in STRAY_TERMS.iter().enumerate() {
        out[I_STRAY + k] = legendre(i, xn) * legendre(j, yn);
    }
}

/// The fitted photometric model.
#[derive(Debug, Clone)]
pub struct Photometric {
    pub beta: [f64; K],
    pub fit: Option<WlsFit>,
    pub n_pixels: usize,
    pub n_dark_blocks: usize,
}

impl Photometric {
    pub fn identity() -> Photometric {
        Photometric { beta: [0.0; K], fit: None, n_pixels: 0, n_dark_blocks: 0 }
    }
    /// Predicted real level for sim level `s` at a position.
    #[inline]
    pub fn predict(&self, s: f64, xn: f64, yn: f64, rho2: f64) -> f64 {
        let mut r = [0.0; K];
        row(s, xn, yn, rho2, &mut r);
        s + r.iter().zip(&self.beta).map(|(a, b)| a * b).sum::<f64>()
    }
    /// Additive field (offset + stray terms) at a position.
    pub fn additive(&self, xn: f64, yn: f64) -> f64 {
        let mut v = self.beta[I_OFF];
        for (k, &(i, j)) in STRAY_TERMS.iter().enumerate() {
            v += self.beta[I_STRAY + k] * legendre(i, xn) * legendre(j, yn);
        }
        v
    }
    /// Multiplicative gain (relative to 1) at radius ρ².
    pub fn gain_at(&self, rho2: f64) -> f64 {
        1.0 + self.beta[I_GAIN] + self.beta[I_V2] * rho2 + self.beta[I_V4] * rho2 * rho2
    }
    /// Extremes of the smooth additive field over the frame (min, max, argmax (xn, yn)).
    pub fn additive_range(&self) -> (f64, f64, (f64, f64)) {
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        let mut at = (0.0, 0.0);
        for a in 0..=32 {
            for b in 0..=32 {
                let (xn, yn) = (a as f64 / 16.0 - 1.0, b as f64 / 16.0 - 1.0);
                let v = self.additive(xn, yn);
                lo = lo.min(v);
                if v > hi {
                    hi = v;
                    at = (xn, yn);
                }
            }
        }
        (lo, hi, at)
    }
}

/// Fit the photometric model on smooth pixels (rows of the regression) and on the censored fits
/// of the dark blocks of the noise model (rows with the block's mean base level).
pub fn fit(pairs: &[Pair], masks: &[Masks], noise: &NoiseModel) -> Photometric {
    let lo = (3.0 * noise.sd(0.0)).max(3.0);
    let hi = FS as f64 - 3.0 * noise.sd(FS as f64) - 1.0;
    let total: usize = pairs.iter().map(|p| p.w() * p.h() * p.channels()).sum();
    let step = (total / 400_000).max(1);
    let mut pass_beta: Option<[f64; K]> = None;
    let mut result = Photometric::identity();
    for _pass in 0..2 {
        let mut wls = Wls::new(K);
        let mut rowbuf = [0.0; K];
        let mut n_pix = 0usize;
        let mut counter = 0usize;
        for (k, p) in pairs.iter().enumerate() {
            let m = &masks[k];
            let (w, h) = (p.w(), p.h());
            let bw = w.div_ceil(32);
            for c in 0..p.channels() {
                let s = &p.sim[c].data;
                let r = &p.real[c].data;
                for y in 0..h {
                    for x in 0..w {
                        counter += 1;
                        if !counter.is_multiple_of(step) {
                            continue;
                        }
                        let i = y * w + x;
                        let sv = s[i] as f64;
                        if !m.smooth.get(i) || m.dist_sat.get(i) <= 8.0 || sv < lo || sv > hi {
                            continue;
                        }
                        let rv = r[i] as f64;
                        if rv <= 0.0 || rv >= FS as f64 {
                            continue;
                        }
                        let (xn, yn, rho2) = super::photometric::coords(x, y, w, h);
                        row(sv, xn, yn, rho2, &mut rowbuf);
                        let var = noise.var(sv);
                        if let Some(b) = &pass_beta {
                            let pred = sv + rowbuf.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
                            if (rv - pred).abs() > 5.0 * var.sqrt() + 1.0 {
                                continue; // hot pixel, edge or local artefact
                            }
                        }
                        let cl = (k * 4 + c) * 1_000_000 + (y / 32) * bw + x / 32;
                        wls.push(&rowbuf, rv - sv, 1.0 / var, cl as u32);
                        n_pix += 1;
                    }
                }
            }
        }
        // Dark blocks: the additive level by censored fits (little multiplicative information).
        let mut n_dark = 0;
        for b in &noise.low {
            let p = &pairs[b.k];
            let (w, h) = (p.w(), p.h());
            let (xc, yc) =
                (b.xc.round().clamp(0.0, w as f64 - 1.0) as usize, b.yc.round().clamp(0.0, h as f64 - 1.0) as usize);
            let (xn, yn, rho2) = coords(xc, yc, w, h);
            row(b.base, xn, yn, rho2, &mut rowbuf);
            let bw = w.div_ceil(32);
            let cl = (b.k * 4 + b.c) * 1_000_000 + (yc / 32) * bw + xc / 32;
            wls.push(&rowbuf, b.mu, 1.0 / (b.se_mu * b.se_mu).max(1e-6), cl as u32);
            n_dark += 1;
        }
        let Some(f) = fit_reduced(&wls) else {
            return result;
        };
        let mut beta = [0.0; K];
        beta.copy_from_slice(&f.beta);
        pass_beta = Some(beta);
        result = Photometric { beta, fit: Some(f), n_pixels: n_pix, n_dark_blocks: n_dark };
    }
    result
}

/// Fit, dropping the signal-dependent columns when the sim has no usable signal range (e.g.
/// only black and saturated pixels), so the additive part can still be estimated.
fn fit_reduced(wls: &Wls) -> Option<WlsFit> {
    if let Some(f) = wls.fit() {
        return Some(f);
    }
    // Without a signal range only the additive field is identifiable.
    let cols: Vec<usize> = std::iter::once(I_OFF).chain(I_STRAY..K).collect();
    if let Some(f) = wls.fit_cols(&cols) {
        return Some(f);
    }
    wls.fit_cols(&[I_OFF])
}

/// Signature tests derived from the photometric fit: gain_offset, gamma, vignetting,
/// stray_light, and the additive level (resolved into dark_current or gain_offset by the caller).
pub struct PhotoTests {
    pub gain: Signature,
    pub gamma: Signature,
    pub vignetting: Signature,
    pub stray: Signature,
    /// Additive level over the frame (offset term), DN, with z.
    pub offset: f64,
    pub offset_z: f64,
    pub offset_se: f64,
}

pub fn tests(ph: &Photometric, pairs: &[Pair], masks: &[Masks], z_thr: f64) -> PhotoTests {
    let mut gain = Signature::new("gain_offset");
    let mut gamma = Signature::new("gamma");
    let mut vig = Signature::new("vignetting");
    let mut stray = Signature::new("stray_light");
    let Some(f) = &ph.fit else {
        for s in [&mut gain, &mut gamma, &mut vig, &mut stray] {
            s.evidence = "photometric fit not possible (no flat unsaturated pixels)".into();
        }
        return PhotoTests {
            gain,
            gamma,
            vignetting: vig,
            stray,
            offset: 0.0,
            offset_z: 0.0,
            offset_se: f64::INFINITY,
        };
    };
    let b = &ph.beta;
    let g = 1.0 + b[I_GAIN];
    // gain
    let zg = b[I_GAIN].abs() / f.se(I_GAIN);
    gain.z = zg;
    gain.size = (g - 1.0).abs();
    gain.size_unit = "|gain-1|";
    gain.set_param("gain", g);
    gain.set_param("offset_dn", b[I_OFF]);
    gain.stderr = vec![("gain".into(), f.se(I_GAIN)), ("offset_dn".into(), f.se(I_OFF))];
    gain.where_ = "whole frame (tone curve on flat regions)".into();
    gain.evidence = format!(
        "real = {:.4}·sim {:+.3} DN on {} flat pixels and {} black blocks; gain z = {:.1}",
        g, b[I_OFF], ph.n_pixels, ph.n_dark_blocks, zg
    );
    // gamma
    let gm = 1.0 + b[I_GAMMA] / g;
    let zgm = b[I_GAMMA].abs() / f.se(I_GAMMA);
    gamma.z = zgm;
    gamma.size = (gm - 1.0).abs();
    gamma.size_unit = "|gamma-1|";
    gamma.set_param("gamma", gm);
    gamma.stderr = vec![("gamma".into(), f.se(I_GAMMA) / g)];
    gamma.where_ = "whole frame (tone curve)".into();
    gamma.evidence = format!("curvature of real vs sim: gamma = {gm:.4} ± {:.4}, z = {zgm:.1}", f.se(I_GAMMA) / g);
    // vignetting
    let chi = f.wald(&[I_V2, I_V4]);
    let zv = stats::chi2_to_z(chi, 2.0);
    let strength = -(b[I_V2] + b[I_V4]) / g;
    let k = b.len();
    let var_s = (f.cov[I_V2 * k + I_V2] + f.cov[I_V4 * k + I_V4] + 2.0 * f.cov[I_V2 * k + I_V4])
        .max(f.cov_model[I_V2 * k + I_V2] + f.cov_model[I_V4 * k + I_V4] + 2.0 * f.cov_model[I_V2 * k + I_V4]);
    vig.z = zv;
    vig.size = strength;
    vig.size_unit = "1 - corner gain";
    vig.set_param("strength", strength.clamp(0.0, 1.0));
    vig.stderr = vec![("strength".into(), var_s.max(0.0).sqrt() / g)];
    vig.where_ = "radial, centred on the frame centre; darkest in the corners".into();
    vig.evidence = format!(
        "relative gain real/sim falls from 1 at the centre to {:.3} at the corners (Wald chi2 = {:.1} on 2 df, z = {:.1})",
        1.0 - strength,
        chi,
        zv
    );
    vig.profiles.push(radial_profile(ph, pairs, masks));
    // stray light
    let idx: Vec<usize> = (I_STRAY..K).collect();
    let chi_s = f.wald(&idx);
    let zs = stats::chi2_to_z(chi_s, idx.len() as f64);
    let (lo, hi, at) = ph.additive_range();
    let amp = hi - lo;
    stray.z = zs;
    stray.size = amp;
    stray.size_unit = "DN peak-to-valley";
    stray.set_param("amplitude_dn", amp.max(0.0));
    stray.where_ = format!(
        "smooth additive field, brightest at ({:.0}%, {:.0}%) of the frame width/height",
        (at.0 + 1.0) * 50.0,
        (at.1 + 1.0) * 50.0
    );
    stray.evidence = format!(
        "low-order additive field from {:.2} to {:.2} DN (Wald chi2 = {:.1} on {} df, z = {:.1})",
        lo,
        hi,
        chi_s,
        idx.len(),
        zs
    );
    stray.profiles.push(additive_profile(ph));
    let _ = z_thr;
    PhotoTests {
        gain,
        gamma,
        vignetting: vig,
        stray,
        offset: b[I_OFF],
        offset_z: b[I_OFF] / f.se(I_OFF),
        offset_se: f.se(I_OFF),
    }
}

/// Ratio of real to sim (additive field removed) against the normalised radius.
fn radial_profile(ph: &Photometric, pairs: &[Pair], masks: &[Masks]) -> Profile {
    const NB: usize = 20;
    let mut acc: Vec<Vec<f64>> = vec![Vec::new(); NB];
    for (k, p) in pairs.iter().enumerate() {
        let m = &masks[k];
        let (w, h) = (p.w(), p.h());
        for c in 0..p.channels() {
            let s = &p.sim[c].data;
            let r = &p.real[c].data;
            for y in (0..h).step_by(2) {
                for x in (0..w).step_by(2) {
                    let i = y * w + x;
                    if !m.smooth.get(i) || m.dist_sat.get(i) <= 12.0 || s[i] < 20.0 || r[i] >= FS {
                        continue;
                    }
                    let (xn, yn, rho2) = coords(x, y, w, h);
                    let ratio = (r[i] as f64 - ph.additive(xn, yn)) / s[i] as f64;
                    let b = ((rho2.sqrt() * NB as f64) as usize).min(NB - 1);
                    acc[b].push(ratio);
                }
            }
        }
    }
    let x: Vec<f64> = (0..NB).map(|i| (i as f64 + 0.5) / NB as f64).collect();
    let meas: Vec<f64> = acc.iter_mut().map(|v| if v.len() < 30 { f64::NAN } else { stats::median_mut(v) }).collect();
    let model: Vec<f64> = x.iter().map(|&r| ph.gain_at(r * r) + ph.beta[I_GAMMA] * 0.0).collect();
    Profile {
        title: "vignetting: real/sim gain against radius".into(),
        x_label: "normalised radius (1 = corner)".into(),
        y_label: "median (real - additive) / sim".into(),
        x,
        series: vec![("measured".into(), meas), ("fitted".into(), model)],
    }
}

/// The additive field along the horizontal and vertical centre lines.
fn additive_profile(ph: &Photometric) -> Profile {
    let x: Vec<f64> = (0..=40).map(|i| i as f64 / 20.0 - 1.0).collect();
    let hx: Vec<f64> = x.iter().map(|&t| ph.additive(t, 0.0)).collect();
    let vy: Vec<f64> = x.iter().map(|&t| ph.additive(0.0, t)).collect();
    let d1: Vec<f64> = x.iter().map(|&t| ph.additive(t, t)).collect();
    Profile {
        title: "stray light: fitted additive field".into(),
        x_label: "normalised position (-1 = left/top edge, 1 = right/bottom)".into(),
        y_label: "additive level (DN)".into(),
        x,
        series: vec![
            ("horizontal centre line".into(), hx),
            ("vertical centre line".into(), vy),
            ("diagonal".into(), d1),
        ],
    }
}
