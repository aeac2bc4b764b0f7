//! PSF: the blur kernel that maps the sim to the real image, measured directly, whatever its form.
//!
//! The real image of a blurred camera is `real ≈ K * Q + c` near edges (Q = the sim through the
//! photometric model), with `K` the discrete point-spread function sampled on the pixel grid
//! (the pixel integration included). `K` is estimated by weighted least squares over its
//! `(2 HALF + 1)²` taps and an offset, on the pixels near the sim's edges whose window holds no
//! saturated sim pixel (a clipped sim pixel does not hold the scene's irradiance) and whose real
//! value is not clipped. Nothing is assumed about the PSF's form: a Gaussian, a pillbox, an Airy
//! pattern or a motion streak are all a set of taps. Standard errors are cluster-robust (16x16
//! blocks of one frame).
//!
//! From `K` (normalised to unit sum):
//! * **Direction** — the central second moments `Σ` (px²). A PSF with no preferred direction
//!   (defocus of any form: Gaussian, pillbox, Airy) has `Σxx = Σyy` and `Σxy = 0`; a motion
//!   streak of length L along u adds `(L²/12) u uᵀ`. The anisotropy `a = ((Σxx − Σyy)/2, Σxy)`
//!   (half the eigenvalue difference, its orientation) gets a Wald chi-square on 2 degrees of
//!   freedom from the taps' covariance: a blur is directional only when `|a|` is beyond its noise.
//!
//! The kernel's second moments are not the defocus `sigma_px`: a long-tailed PSF (the Airy
//! pattern's rings) has a second moment far above its core's (it diverges without truncation),
//! so the equivalent Gaussian is read at the edges instead (`edges::EDGE_SIGMA_PARAM`).

use super::common::{Masks, NoiseModel};
use super::img::{FS, Pair, Plane};
use super::stats;

/// Half-size of the measured kernel (7x7 taps): holds a Gaussian of σ ≤ 1.2 px to 2.5 σ, the
/// Airy pattern's first ring for λN ≤ 1.6 px, a pillbox of radius ≤ 3 px and a streak ≤ 6 px.
pub const HALF: usize = 3;
const N: usize = 2 * HALF + 1;
const K: usize = N * N + 1;
/// Signature parameter (on `motion_blur`) holding [`Psf::aniso_z`].
pub const ANISO_Z_PARAM: &str = "psf_anisotropy_z";
/// Largest number of samples per channel (every `s`-th usable pixel above it).
const CAP: usize = 250_000;

/// The measured PSF of one channel.
#[derive(Debug, Clone)]
pub struct Psf {
    /// Channel the kernel was measured on (green, or the only one).
    pub channel: usize,
    /// Taps, row-major `N x N`, normalised to unit sum.
    pub kernel: Vec<f64>,
    /// Sum of the taps before normalisation (the local gain of real over Q).
    pub gain: f64,
    /// Centroid (px, image axes, y down).
    pub centre: (f64, f64),
    /// Central second moments Σxx, Σxy, Σyy (px², image axes).
    pub moments: [f64; 3],
    /// Anisotropy `(Σxx − Σyy)/2`, `Σxy` and its chi-square (2 df) against isotropy.
    pub aniso: (f64, f64),
    pub aniso_chi2: f64,
    /// One-sided z of the anisotropy (from the chi-square).
    pub aniso_z: f64,
    /// Direction of the larger eigenvalue, degrees counter-clockwise from +x (y up), in [0, 180).
    pub angle_deg: f64,
    /// Samples used.
    pub n: usize,
}

/// Measure the PSF on the reference channel (green, or the only one). `skip`: pixels to leave
/// out (hot pixels), per pair. None when too few usable pixels or a singular design.
pub fn measure(
    pairs: &[Pair],
    masks: &[Masks],
    q: &[Vec<Plane>],
    noise: &NoiseModel,
    skip: &[Vec<bool>],
) -> Option<Psf> {
    let c = if pairs[0].channels() == 3 { 1 } else { 0 };
    let lo = (4.0 * noise.sd(0.0)).max(4.0);
    let hi = FS as f64 - 3.0 * noise.sd(FS as f64) - 1.0;
    // Usable samples: (pair, pixel index, weight).
    let mut pts: Vec<(u16, u32, f64)> = Vec::new();
    let margin = HALF + 1;
    for (k, p) in pairs.iter().enumerate() {
        let m = &masks[k];
        let (w, h) = (p.w(), p.h());
        if w <= 2 * margin || h <= 2 * margin {
            continue;
        }
        let qd = &q[k][c].data;
        let r = &p.real[c].data;
        for y in margin..h - margin {
            for x in margin..w - margin {
                let i = y * w + x;
                if m.dist_edge.get(i) > (HALF + 1) as f32 || m.dist_sat.get(i) <= (HALF as f32) * 1.5 + 1.0 {
                    continue;
                }
                if skip.get(k).is_some_and(|s| s.get(i).copied().unwrap_or(false)) {
                    continue;
                }
                let (rv, qv) = (r[i] as f64, qd[i] as f64);
                if rv <= 0.0 || rv >= FS as f64 || qv < lo || qv > hi {
                    continue;
                }
                pts.push((k as u16, i as u32, 1.0 / noise.var(qv)));
            }
        }
    }
    if pts.len() < 20 * K {
        return None;
    }
    if pts.len() > CAP {
        let step = pts.len().div_ceil(CAP);
        pts = pts.into_iter().step_by(step).collect();
    }
    let row = |k: usize, i: usize, x: &mut [f64; K]| {
        let qp = &q[k][c];
        let w = qp.w;
        let (px, py) = (i % w, i / w);
        // Tap (dx, dy) is K at offset d = (dx − HALF, dy − HALF) and weighs Q(p − d): K * Q.
        for dy in 0..N {
            let yq = py + HALF - dy;
            for dx in 0..N {
                x[dy * N + dx] = qp.data[yq * w + px + HALF - dx] as f64;
            }
        }
        x[N * N] = 1.0;
    };
    // Cluster-robust standard errors over 16x16 blocks of one frame: the clusters get dense ids
    // in frame, block order (the samples are in frame, row, column order, so the fit is the same
    // on any thread count).
    let mut first_block = Vec::with_capacity(pairs.len() + 1);
    let mut nblocks = 0u64;
    for p in pairs {
        first_block.push(nblocks);
        nblocks += (p.w().div_ceil(16) * p.h().div_ceil(16)) as u64;
    }
    let cluster_id = |k: usize, i: usize| -> Option<u32> {
        let w = pairs[k].w();
        u32::try_from(first_block[k] + (((i / w) / 16) * w.div_ceil(16) + (i % w) / 16) as u64).ok()
    };
    let mut wls = stats::Wls::new(K);
    let mut x = [0.0f64; K];
    for &(k, i, wt) in &pts {
        let (k, i) = (k as usize, i as usize);
        row(k, i, &mut x);
        wls.push(&x, pairs[k].real[c].data[i] as f64, wt, cluster_id(k, i)?);
    }
    let fit = wls.fit()?;
    let beta = fit.beta;
    // The cluster-robust covariance is floored at the model covariance: a tap whose robust
    // variance is below it gets its row and column scaled up to it (keeping the correlations).
    let mut cov = fit.cov;
    for a in 0..K {
        let model = fit.cov_model[a * K + a];
        if cov[a * K + a] < model {
            let scale = (model / cov[a * K + a].max(1e-300)).sqrt();
            for b in 0..K {
                cov[a * K + b] *= scale;
                cov[b * K + a] *= scale;
            }
        }
    }
    let taps = &beta[..N * N];
    let gain: f64 = taps.iter().sum();
    if gain.abs() < 0.2 {
        return None;
    }
    let kernel: Vec<f64> = taps.iter().map(|v| v / gain).collect();
    let m = moments(&kernel);
    // Delta method: gradients of the anisotropy components with respect to the raw taps (numerical, central differences on the raw taps).
    let stat = |t: &[f64]| -> [f64; 2] {
        let s: f64 = t.iter().sum();
        let kk: Vec<f64> = t.iter().map(|v| v / s).collect();
        let mm = moments(&kk);
        [0.5 * (mm.1[0] - mm.1[2]), mm.1[1]]
    };
    let nt = N * N;
    let mut grads = vec![[0.0f64; 2]; nt];
    let hstep = 1e-6;
    let mut t = taps.to_vec();
    for j in 0..nt {
        let v0 = t[j];
        t[j] = v0 + hstep;
        let a = stat(&t);
        t[j] = v0 - hstep;
        let b = stat(&t);
        t[j] = v0;
        grads[j] = [(a[0] - b[0]) / (2.0 * hstep), (a[1] - b[1]) / (2.0 * hstep)];
    }
    let mut va = [[0.0f64; 2]; 2];
    for i in 0..nt {
        for j in 0..nt {
            let cij = cov[i * K + j];
            for p in 0..2 {
                for r in 0..2 {
                    va[p][r] += grads[i][p] * cij * grads[j][r];
                }
            }
        }
    }
    let a = stat(taps);
    let det = va[0][0] * va[1][1] - va[0][1] * va[1][0];
    let chi2 = if det > 0.0 {
        (a[0] * a[0] * va[1][1] - 2.0 * a[0] * a[1] * va[0][1] + a[1] * a[1] * va[0][0]) / det
    } else {
        0.0
    };
    let aniso_z = stats::chi2_to_z(chi2, 2.0);
    // Direction of the larger eigenvalue (image axes, y down) → counter-clockwise from +x, y up.
    let angle_img = 0.5 * (2.0 * a[1]).atan2(2.0 * a[0]);
    let angle_deg = (-angle_img).to_degrees().rem_euclid(180.0);
    Some(Psf {
        channel: c,
        kernel,
        gain,
        centre: m.0,
        moments: m.1,
        aniso: (a[0], a[1]),
        aniso_chi2: chi2,
        aniso_z,
        angle_deg,
        n: fit.n,
    })
}

/// Centroid and central second moments (Σxx, Σxy, Σyy) of a unit-sum `N x N` kernel.
pub fn moments(k: &[f64]) -> ((f64, f64), [f64; 3]) {
    let (mut mx, mut my) = (0.0, 0.0);
    for dy in 0..N {
        for dx in 0..N {
            let v = k[dy * N + dx];
            mx += v * (dx as f64 - HALF as f64);
            my += v * (dy as f64 - HALF as f64);
        }
    }
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for dy in 0..N {
        for dx in 0..N {
            let v = k[dy * N + dx];
            let (x, y) = (dx as f64 - HALF as f64 - mx, dy as f64 - HALF as f64 - my);
            sxx += v * x * x;
            sxy += v * x * y;
            syy += v * y * y;
        }
    }
    ((mx, my), [sxx, sxy, syy])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pixel-area-weighted kernel of a radial profile `f(r)` on the `N x N` window (16x16
    /// samples per pixel), unit sum (written here from the physics, independent of realcam).
    fn area_kernel(f: impl Fn(f64) -> f64) -> Vec<f64> {
        let mut k = vec![0.0; N * N];
        const S: usize = 16;
        for dy in 0..N {
            for dx in 0..N {
                let mut acc = 0.0;
                for sy in 0..S {
                    for sx in 0..S {
                        let x = dx as f64 - HALF as f64 - 0.5 + (sx as f64 + 0.5) / S as f64;
                        let y = dy as f64 - HALF as f64 - 0.5 + (sy as f64 + 0.5) / S as f64;
                        acc += f((x * x + y * y).sqrt());
                    }
                }
                k[dy * N + dx] = acc;
            }
        }
        let s: f64 = k.iter().sum();
        k.iter_mut().for_each(|v| *v /= s);
        k
    }

    /// Isotropic kernels have no anisotropy; a streak has it along its direction.
    #[test]
    fn moments_tell_a_streak_from_a_disc() {
        let disc = area_kernel(|x| if x <= 1.4 { 1.0 } else { 0.0 });
        let (c, m) = moments(&disc);
        assert!(c.0.abs() < 1e-12 && c.1.abs() < 1e-12);
        assert!((m[0] - m[2]).abs() < 1e-12 && m[1].abs() < 1e-12);
        // A streak of 3 px along 30° (counter-clockwise, y up): samples on the line.
        let mut k = vec![0.0; N * N];
        let th = 30f64.to_radians();
        for j in 0..300 {
            let t = (j as f64 + 0.5) / 300.0 - 0.5;
            let (x, y) = (HALF as f64 + 3.0 * t * th.cos(), HALF as f64 - 3.0 * t * th.sin());
            let (xi, yi) = (x.round() as usize, y.round() as usize);
            k[yi * N + xi] += 1.0 / 300.0;
        }
        let (_, m) = moments(&k);
        let a = (0.5 * (m[0] - m[2]), m[1]);
        let ang = (-(0.5 * (2.0 * a.1).atan2(2.0 * a.0))).to_degrees().rem_euclid(180.0);
        assert!((ang - 30.0).abs() < 8.0, "angle {ang}");
        assert!((a.0 * a.0 + a.1 * a.1).sqrt() > 0.2);
    }

    /// The kernel measured on a textured scene: a pillbox (isotropic, non-Gaussian) has no
    /// significant anisotropy, a 2.2 px streak at 35° has it along 35° (issue 13: pillbox blurs
    /// were reported as motion_blur).
    #[test]
    fn measured_psf_tells_a_streak_from_a_pillbox() {
        let noise = {
            let mut n = NoiseModel::prior(1.0);
            n.a = 1.0;
            n.b = 1.0 / 8.0;
            n
        };
        let run = |k: &[f64], half: usize| -> Psf {
            let pairs = super::super::common::blurred_test_pairs(k, half, 5);
            let masks: Vec<Masks> = pairs.iter().map(|p| Masks::compute(&p.sim)).collect();
            let q: Vec<Vec<Plane>> = pairs.iter().map(|p| p.sim.clone()).collect();
            measure(&pairs, &masks, &q, &noise, &[]).expect("psf measured")
        };
        let disc = area_kernel(|x| if x <= 1.4 { 1.0 } else { 0.0 });
        let p = run(&disc, HALF);
        assert!(p.aniso_z < 4.0, "pillbox anisotropy z {}", p.aniso_z);
        assert!(
            (p.moments[0] - p.moments[2]).abs() < 0.05 && (p.moments[0] - 0.745f64.powi(2)).abs() < 0.08,
            "{:?}",
            p.moments
        );
        // Streak: 2.2 px along 35° (y up), box-filtered line sampled densely, pixel-area spread.
        let mut k = vec![0.0; N * N];
        let th = 35f64.to_radians();
        for j in 0..2000 {
            let t = (j as f64 + 0.5) / 2000.0 - 0.5;
            let (x, y) = (HALF as f64 + 2.2 * t * th.cos(), HALF as f64 - 2.2 * t * th.sin());
            let (x0, y0) = (x.floor(), y.floor());
            let (fx, fy) = (x - x0, y - y0);
            for (dx, dy, w) in
                [(0, 0, (1.0 - fx) * (1.0 - fy)), (1, 0, fx * (1.0 - fy)), (0, 1, (1.0 - fx) * fy), (1, 1, fx * fy)]
            {
                k[(y0 as usize + dy) * N + x0 as usize + dx] += w / 2000.0;
            }
        }
        let p = run(&k, HALF);
        assert!(p.aniso_z > 8.0, "streak anisotropy z {}", p.aniso_z);
        assert!((p.angle_deg - 35.0).abs() < 6.0, "streak angle {}", p.angle_deg);
        let len = (24.0 * p.aniso.0.hypot(p.aniso.1)).sqrt();
        assert!((len - 2.2).abs() < 0.4, "streak length {len}");
    }
}
