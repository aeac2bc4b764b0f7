//! Level or position: does a residual depend on the pixel's own level (a tone curve, a gain and
//! offset) or on where the pixel is (stray light, veiling glare, vignetting)?
//!
//! On a smoothly lit scene (a lamp-lit wall) the level varies smoothly over the frame, so a tone
//! curve's change `T(s) − s` is itself a smooth field, which an additive field (stray light, a
//! veiling glare) or a radial gain (vignetting) can imitate. What tells them apart is the
//! physics of each: a tone curve acts on each pixel's own level, whatever its position (texture,
//! objects and patches of other levels at the same place are changed by different amounts); a
//! spatial effect acts on a position, whatever the level there (additive: the same amount on
//! dark and bright pixels side by side; multiplicative: a gain that depends on the radius).
//!
//! One weighted regression of `real − base` (the model without the spatial and tone effects) on
//! interior pixels:
//!
//! ```text
//! real − base = o + g s + Σ_j c_j (s − k_j)₊          (any smooth level response)
//!             + Σ a_ij P_i(x̃) P_j(ỹ) + s (v2 ρ² + v4 ρ⁴)   (additive field, radial gain)
//! ```
//!
//! with hinge knots `k_j` every [`KNOT_DN`] DN inside the levels the data have, so the level
//! response is free (piecewise linear) and its approximation error is far below the noise; the
//! position terms are the photometric ones (Legendre polynomials of total degree 1..3, ρ² = 1 at
//! the corners). Two Wald tests with a cluster-robust covariance (clusters: 32x32 blocks of one
//! frame and channel, so spatially correlated misfit does not count as evidence):
//! **position given level** (the 11 position terms) and **curvature given position** (the hinge
//! terms: a nonlinear level response). The orchestrator decides what the outcome means.

use super::common::NoiseModel;
use super::img::{FS, Plane};
use super::stats::{self, Wls};

/// Spacing of the hinge knots of the free level response (8-bit DN).
pub const KNOT_DN: f64 = 16.0;

/// Position terms: (i, j) Legendre degrees of the additive field, then s·ρ², s·ρ⁴.
const STRAY_TERMS: [(usize, usize); 9] = [(1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3)];
const N_POS: usize = STRAY_TERMS.len() + 2;

/// Largest number of pixel rows the regression takes (evenly subsampled above).
const MAX_ROWS: usize = 250_000;

/// Outcome of the level-or-position test.
#[derive(Debug, Clone)]
pub struct LevelPosition {
    /// Wald χ² of the position terms given a free level response, its df and normal z.
    pub chi_position: f64,
    pub df_position: usize,
    pub z_position: f64,
    /// Wald χ² of the hinge (curvature) terms given the position terms, its df and z.
    pub chi_curve: f64,
    pub df_curve: usize,
    pub z_curve: f64,
    /// Each spatial effect's own terms given the free level response and the other position
    /// terms (a matched test of one physical signature instead of the 11 terms together):
    /// the radial gain `s (v2 ρ² + v4 ρ⁴)` (vignetting: the ratio real/sim falls with the radius
    /// whatever the level, 2 df) and the additive field (stray light, veiling glare: the same
    /// amount on dark and bright pixels at one place, 9 df). χ² and normal z.
    pub chi_radial: f64,
    pub z_radial: f64,
    pub chi_additive: f64,
    pub z_additive: f64,
    /// Wald χ² of the whole level response (offset, gain and hinges) given the position terms:
    /// whether anything depends on the pixel's own level once the place is accounted for (the
    /// symmetric test of a level effect), its df and z.
    pub chi_level: f64,
    pub df_level: usize,
    pub z_level: f64,
    /// Radial gain given the level response only, and the level response given the radial gain
    /// only (the additive field left out): z.
    pub z_radial_level: f64,
    pub z_level_radial: f64,
    /// Pixels and clusters in the regression.
    pub n: usize,
    pub clusters: usize,
}

impl LevelPosition {
    pub fn describe(&self) -> String {
        format!(
            "level or position (real − model without the spatial and tone effects on {} interior pixels, {} clusters of 32x32): position terms given a free level response χ² {:.1} on {} df (z = {:.1}); curvature of the level response given the position terms χ² {:.1} on {} df (z = {:.1}); each signature given all other terms: radial gain (vignetting) χ² {:.1} on 2 df (z = {:.1}), additive field (stray light, glare) χ² {:.1} on {} df (z = {:.1}), level response (offset, gain, curvature) χ² {:.1} on {} df (z = {:.1}); without the additive field: radial gain given the level response z = {:.1}, level response given the radial gain z = {:.1}",
            self.n,
            self.clusters,
            self.chi_position,
            self.df_position,
            self.z_position,
            self.chi_curve,
            self.df_curve,
            self.z_curve,
            self.chi_radial,
            self.z_radial,
            self.chi_additive,
            STRAY_TERMS.len(),
            self.z_additive,
            self.chi_level,
            self.df_level,
            self.z_level,
            self.z_radial_level,
            self.z_level_radial
        )
    }
}

fn legendre(n: usize, t: f64) -> f64 {
    match n {
        0 => 1.0,
        1 => t,
        2 => 0.5 * (3.0 * t * t - 1.0),
        _ => 0.5 * (5.0 * t * t * t - 3.0 * t),
    }
}

/// Hinge knots inside the levels the data have: every [`KNOT_DN`] DN, each with at least 2 % of
/// the values (and 200) above it and below it.
fn knots(levels: &[f64]) -> Vec<f64> {
    let mut v = levels.to_vec();
    if v.len() < 1000 {
        return Vec::new();
    }
    let n = v.len();
    let margin = (n / 50).max(200);
    let (_, lo, _) = v.select_nth_unstable_by(margin, |a, b| a.total_cmp(b));
    let lo = *lo;
    let (_, hi, _) = v.select_nth_unstable_by(n - 1 - margin, |a, b| a.total_cmp(b));
    let hi = *hi;
    let mut out = Vec::new();
    let mut k = (lo / KNOT_DN).ceil() * KNOT_DN;
    while k < hi {
        if k > lo {
            out.push(k);
        }
        k += KNOT_DN;
    }
    out
}

/// The test on pixels `keep[k][i]` of pairs `k` (real planes `real[k]`, base planes `base[k]`).
/// None when there are too few pixels or levels.
pub fn test(real: &[&[Plane]], base: &[Vec<Plane>], keep: &[Vec<bool>], noise: &NoiseModel) -> Option<LevelPosition> {
    let lo = 1.0;
    let hi = FS as f64 - 3.0 * noise.sd(FS as f64) - 1.0;
    let total: usize = base.iter().map(|b| b.iter().map(|p| p.data.len()).sum::<usize>()).sum();
    let step = (total / MAX_ROWS).max(1);
    // Pixels: (k, c, x, y, s, r).
    let mut px: Vec<(usize, usize, usize, usize, f64, f64)> = Vec::new();
    let mut counter = 0usize;
    for (k, bp) in base.iter().enumerate() {
        for (c, plane) in bp.iter().enumerate() {
            let r = &real[k][c].data;
            let (w, h) = (plane.w, plane.h);
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    if !keep[k][i] {
                        continue;
                    }
                    counter += 1;
                    if !counter.is_multiple_of(step) {
                        continue;
                    }
                    let (s, rv) = (plane.data[i] as f64, r[i] as f64);
                    if s < lo || s > hi || rv <= 0.0 || rv >= FS as f64 {
                        continue;
                    }
                    px.push((k, c, x, y, s, rv));
                }
            }
        }
    }
    let ks = knots(&px.iter().map(|p| p.4).collect::<Vec<_>>());
    if ks.len() < 2 {
        return None;
    }
    let nl = 2 + ks.len();
    let kk = nl + N_POS;
    let (w0, h0) = (base[0][0].w, base[0][0].h);
    let fill = |s: f64, x: usize, y: usize, row: &mut Vec<f64>| {
        row.clear();
        row.push(1.0);
        row.push(s);
        row.extend(ks.iter().map(|&k| (s - k).max(0.0)));
        let cx = (w0 as f64 - 1.0) / 2.0;
        let cy = (h0 as f64 - 1.0) / 2.0;
        let (dx, dy) = (x as f64 - cx, y as f64 - cy);
        let (xn, yn) = (dx / cx.max(1e-9), dy / cy.max(1e-9));
        let rho2 = (dx * dx + dy * dy) / (cx * cx + cy * cy).max(1e-9);
        row.extend(STRAY_TERMS.iter().map(|&(i, j)| legendre(i, xn) * legendre(j, yn)));
        row.push(s * rho2);
        row.push(s * rho2 * rho2);
    };
    let mut beta: Option<Vec<f64>> = None;
    let mut fit = None;
    let mut last: Option<Wls> = None;
    let mut row = Vec::with_capacity(kk);
    let bw = w0.div_ceil(32);
    for _pass in 0..2 {
        let mut wls = Wls::new(kk);
        for &(k, c, x, y, s, rv) in &px {
            fill(s, x, y, &mut row);
            let var = noise.var(s);
            if let Some(b) = &beta {
                let pred = s + row.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
                if (rv - pred).abs() > 5.0 * var.sqrt() + 1.0 {
                    continue; // hot pixel or local artefact
                }
            }
            let cl = (k * 4 + c) * 1_000_000 + (y / 32) * bw + x / 32;
            wls.push(&row, rv - s, 1.0 / var, cl as u32);
        }
        let f = wls.fit()?;
        beta = Some(f.beta.clone());
        fit = Some(f);
        last = Some(wls);
    }
    let f = fit?;
    let wls = last?;
    let pos: Vec<usize> = (nl..kk).collect();
    let curve: Vec<usize> = (2..nl).collect();
    let chi_position = f.wald(&pos);
    let chi_curve = f.wald(&curve);
    let radial: Vec<usize> = (nl + STRAY_TERMS.len()..kk).collect();
    let additive: Vec<usize> = (nl..nl + STRAY_TERMS.len()).collect();
    let level: Vec<usize> = (0..nl).collect();
    let (chi_radial, chi_additive, chi_level) = (f.wald(&radial), f.wald(&additive), f.wald(&level));
    // The radial gain against the level response alone (no additive field: the selection did
    // not choose one), and the level response against the radial gain alone.
    let cols: Vec<usize> = level.iter().chain(&radial).copied().collect();
    let (chi_radial_level, chi_level_radial) =
        wls.fit_cols(&cols).map(|g| (g.wald(&radial), g.wald(&level))).unwrap_or((0.0, 0.0));
    Some(LevelPosition {
        chi_radial,
        z_radial: stats::chi2_to_z(chi_radial, radial.len() as f64),
        chi_additive,
        z_additive: stats::chi2_to_z(chi_additive, additive.len() as f64),
        chi_level,
        df_level: level.len(),
        z_level: stats::chi2_to_z(chi_level, level.len() as f64),
        z_radial_level: stats::chi2_to_z(chi_radial_level, radial.len() as f64),
        z_level_radial: stats::chi2_to_z(chi_level_radial, level.len() as f64),
        chi_position,
        df_position: pos.len(),
        z_position: stats::chi2_to_z(chi_position, pos.len() as f64),
        chi_curve,
        df_curve: curve.len(),
        z_curve: stats::chi2_to_z(chi_curve, curve.len() as f64),
        n: f.n,
        clusters: f.clusters,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured, smoothly lit frame: level falls from the upper left; texture varies the
    /// level locally.
    fn scene(w: usize, h: usize) -> Plane {
        let mut p = Plane::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let (u, v) = (x as f64 / w as f64 - 0.2, y as f64 / h as f64 - 0.2);
                let lamp = 40.0 + 150.0 * (-(u * u + v * v) / 0.25).exp();
                let tex = 0.8 + 0.4 * (((x / 7 + y / 5) * 2654435761usize) % 1000) as f64 / 1000.0;
                p.data[y * w + x] = (lamp * tex) as f32;
            }
        }
        p
    }

    fn noisy(p: &Plane, f: &dyn Fn(f64, usize, usize) -> f64, seed: u64) -> Plane {
        let mut rng = crate::rng::Rng::new(seed);
        let mut out = p.clone();
        for y in 0..p.h {
            for x in 0..p.w {
                let s = p.data[y * p.w + x] as f64;
                out.data[y * p.w + x] = (f(s, x, y) + 1.2 * rng.normal()).round().clamp(0.0, 255.0) as f32;
            }
        }
        out
    }

    fn run(f: &dyn Fn(f64, usize, usize) -> f64) -> LevelPosition {
        let (w, h) = (256, 192);
        let sim = scene(w, h);
        let noise = NoiseModel::prior(1.0);
        let base: Vec<Vec<Plane>> = (0..3).map(|_| vec![sim.clone()]).collect();
        let reals: Vec<Vec<Plane>> = (0..3).map(|k| vec![noisy(&sim, f, 7 + k)]).collect();
        let real: Vec<&[Plane]> = reals.iter().map(|r| r.as_slice()).collect();
        let keep = vec![vec![true; w * h]; 3];
        test(&real, &base, &keep, &noise).expect("test runs")
    }

    /// A tone curve on a smoothly lit scene is a function of the level: the position terms are
    /// not needed, the curvature is. Stray light (a lobe from a corner) is a function of the
    /// position: the position terms are needed. A gain and offset is neither curved nor placed.
    #[test]
    fn tone_is_level_and_stray_light_is_position() {
        let fs = FS as f64;
        let tone = run(&|s, _, _| {
            let x = s / fs;
            let t = if x < 0.27 { x * 1.12 } else { 1.04 * x.powf(0.88) - 0.04 };
            fs * t
        });
        assert!(tone.z_curve > 6.0 && tone.z_position < 3.0, "tone: {}", tone.describe());
        let stray = run(&|s, x, y| {
            let d2 = ((x as f64 + 40.0).powi(2) + (y as f64 + 30.0).powi(2)) / (150.0f64 * 150.0);
            s + 5.0 * (1.0 + d2).powf(-1.5)
        });
        assert!(stray.z_position > 6.0, "stray: {}", stray.describe());
        // Each signature alone: a radial fall-off is the radial gain's (real/sim falls with the
        // radius at every level), not the level response's; a tone curve the reverse.
        let vig = run(&|s, x, y| {
            let (dx, dy) = (x as f64 - 127.5, y as f64 - 95.5);
            let rho2 = (dx * dx + dy * dy) / (127.5f64 * 127.5 + 95.5 * 95.5);
            s / (1.0 + 0.04 * rho2).powi(2)
        });
        assert!(vig.z_radial_level > 6.0 && vig.z_level_radial < 3.0, "vignetting: {}", vig.describe());
        assert!(tone.z_level_radial > 6.0 && tone.z_radial_level < 3.0, "tone: {}", tone.describe());
        let lin = run(&|s, _, _| 1.02 * s + 1.0);
        assert!(lin.z_curve < 3.0 && lin.z_position < 3.0, "gain/offset: {}", lin.describe());
    }
}
