//! Edges: blur (`defocus`, `motion_blur`) and per-channel registration (`channel_shift`).
//!
//! **Detection** is a linear regression of the residual `real - Q` (Q = sim after the
//! photometric model) on the derivatives of Q at edge pixels, per channel:
//!
//! ```text
//! real - Q ≈ -dx Q_x - dy Q_y + ½ Σxx Q_xx + Σxy Q_xy + ½ Σyy Q_yy + c
//! ```
//!
//! which is the second-order Taylor expansion of `k * Q` for a kernel `k` with first moment
//! (dx, dy) (a translation) and second central moments Σ (a blur). A Gaussian defocus has
//! Σ = σ² I; a motion blur of length L along the unit vector u has Σ = (L²/12) u uᵀ. The
//! eigenvalues λ1 >= λ2 of Σ separate them: λ2 is the isotropic part (defocus σ² = λ2) and
//! λ1 - λ2 the directional part (motion L² = 12 (λ1 - λ2)). Significance comes from
//! cluster-robust Wald tests (clusters: 16x16 blocks).
//!
//! **Estimates**: the Taylor form is biased for sharp steps, so the parameters are measured by
//! direct scans of the loss with exact kernels evaluated at the edge pixels: a Gaussian σ scan, a
//! line-kernel (length, angle) scan, and a per-channel sub-pixel shift minimisation.

use super::common::{Masks, NoiseModel};
use super::img::{FS, Pair, Plane};
use super::stats::{self, Wls, WlsFit};
use super::types::{Profile, Signature};

/// Signature parameter (on `defocus`) holding the σ of the continuous Gaussian PSF whose
/// pixel-integrated kernel ([`pixel_gaussian`]) best reproduces the blur at the sim's edges
/// (pixels within 2 px of an edge, away from saturated regions): the PSF's equivalent Gaussian
/// whatever its form (about 0.42 λN for an Airy pattern, R/2 for a pillbox of radius R), read
/// where the PSF's core shapes the edge spread. Not a library parameter (the fit's initial
/// values do not see it); the report's `sigma_px` is this reading. The library's defocus kernel
/// is not pixel-integrated (variance σ², not σ² + 1/12), and a forward fit over the whole image
/// also weighs the PSF's far tails, which show around bright sources: its σ runs higher.
pub const EDGE_SIGMA_PARAM: &str = "edge_sigma_px";

/// Variance (px²) of the unit pixel's box along one axis: a continuous PSF integrated over the
/// pixel area has this much more variance than the PSF.
pub const PIXEL_VARIANCE: f64 = 1.0 / 12.0;

/// One axis of a continuous Gaussian PSF of std `sigma` (px) integrated over unit pixels:
/// `k[n] = Φ((n + ½)/σ) − Φ((n − ½)/σ)`, |n| ≤ ceil(4σ) + 1, normalised (σ = 0: the identity):
/// the kernel a camera applies to a pixel-integrated scene when its optics blur with that
/// Gaussian. Its variance tends to σ² + 1/12 ([`PIXEL_VARIANCE`]) from σ ≈ 0.5 px on; below,
/// the pixel grid aliases it (σ = 0.3: 0.096 px²).
pub fn pixel_gaussian(sigma: f64) -> Vec<f32> {
    pixel_gaussian_shifted(sigma, 0.0)
}

/// [`pixel_gaussian`] of a PSF centred at `d` px (tap j at offset n = j − len/2 weighs the
/// sample at x + n for an output at x, so the content moves by +d):
/// `k[n] = Φ((n + d + ½)/σ) − Φ((n + d − ½)/σ)`.
pub fn pixel_gaussian_shifted(sigma: f64, d: f64) -> Vec<f32> {
    if sigma <= 1e-3 && d.abs() < 1e-6 {
        return vec![1.0];
    }
    let s = sigma.max(1e-3);
    let r = (4.0 * s + d.abs()).ceil() as i64 + 1;
    let k: Vec<f64> = (-r..=r)
        .map(|n| stats::norm_cdf((n as f64 + d + 0.5) / s) - stats::norm_cdf((n as f64 + d - 0.5) / s))
        .collect();
    let t: f64 = k.iter().sum();
    k.iter().map(|v| (v / t) as f32).collect()
}

/// Per-axis variance (px²) of a 1-D kernel about its centroid.
fn kernel_variance(k: &[f32]) -> f64 {
    let r = (k.len() / 2) as f64;
    let m: f64 = k.iter().enumerate().map(|(i, &v)| v as f64 * (i as f64 - r)).sum();
    k.iter().enumerate().map(|(i, &v)| v as f64 * (i as f64 - r - m).powi(2)).sum()
}

/// Edge sample: frame, channel, pixel index, weight.
#[derive(Clone, Copy)]
struct Pt {
    k: u16,
    c: u8,
    i: u32,
    w: f32,
}

/// Edge pixels used by the tests.
fn select(pairs: &[Pair], masks: &[Masks], q: &[Vec<Plane>], noise: &NoiseModel, cap: usize) -> Vec<Pt> {
    let lo = (4.0 * noise.sd(0.0)).max(4.0) as f32;
    let hi = (FS as f64 - 3.0 * noise.sd(FS as f64) - 1.0) as f32;
    let mut pts = Vec::new();
    for (k, p) in pairs.iter().enumerate() {
        let m = &masks[k];
        let (w, h) = (p.w(), p.h());
        for c in 0..p.channels() {
            let qd = &q[k][c].data;
            let r = &p.real[c].data;
            for y in 2..h.saturating_sub(2) {
                for x in 2..w.saturating_sub(2) {
                    let i = y * w + x;
                    if m.dist_edge.get(i) > 2.0 || m.dist_sat.get(i) <= 6.0 {
                        continue;
                    }
                    let v = qd[i];
                    if v < lo || v > hi || r[i] <= 0.0 || r[i] >= FS {
                        continue;
                    }
                    pts.push(Pt { k: k as u16, c: c as u8, i: i as u32, w: (1.0 / noise.var(v as f64)) as f32 });
                }
            }
        }
    }
    if pts.len() > cap {
        let step = pts.len().div_ceil(cap);
        pts = pts.into_iter().step_by(step).collect();
    }
    pts
}

/// Taylor regression of one channel (all frames pooled).
fn taylor(pairs: &[Pair], q: &[Vec<Plane>], pts: &[Pt], c: usize) -> Option<WlsFit> {
    let mut wls = Wls::new(6);
    for p in pts.iter().filter(|p| p.c as usize == c) {
        let k = p.k as usize;
        let qp = &q[k][c];
        let w = qp.w;
        let i = p.i as usize;
        let d = &qp.data;
        let qx = 0.5 * (d[i + 1] - d[i - 1]) as f64;
        let qy = 0.5 * (d[i + w] - d[i - w]) as f64;
        let qxx = (d[i + 1] - 2.0 * d[i] + d[i - 1]) as f64;
        let qyy = (d[i + w] - 2.0 * d[i] + d[i - w]) as f64;
        let qxy = 0.25 * (d[i + w + 1] - d[i + w - 1] - d[i - w + 1] + d[i - w - 1]) as f64;
        let y = (pairs[k].real[c].data[i] - d[i]) as f64;
        let (xx, yy) = (i % w, i / w);
        let cl = (k as u32) * 100_000 + ((yy / 16) * w.div_ceil(16) + xx / 16) as u32;
        wls.push(&[-qx, -qy, 0.5 * qxx, qxy, 0.5 * qyy, 1.0], y, p.w as f64, cl);
    }
    wls.fit()
}

/// Separable blur of Q evaluated at one pixel: `kx` along x, `ky` along y, tap j at offset
/// j − len/2.
#[inline]
fn blur_at(qp: &Plane, x: isize, y: isize, kx: &[f32], ky: &[f32]) -> f32 {
    let (rx, ry) = ((kx.len() / 2) as isize, (ky.len() / 2) as isize);
    let mut s = 0.0;
    for (a, &ka) in ky.iter().enumerate() {
        let yy = y + a as isize - ry;
        let mut t = 0.0;
        for (b, &kb) in kx.iter().enumerate() {
            t += kb * qp.at_clamped(x + b as isize - rx, yy);
        }
        s += ka * t;
    }
    s
}

/// Line kernel (motion blur) of length `len` along angle `theta` (radians, counter-clockwise
/// from +x as displayed, i.e. y up), evaluated at a pixel by sampling the line.
#[inline]
fn line_at(qp: &Plane, x: f32, y: f32, len: f32, theta: f32) -> f32 {
    let n = (len.ceil() as usize * 2 + 1).max(3);
    let (ux, uy) = (theta.cos(), -theta.sin());
    let mut s = 0.0;
    for j in 0..n {
        let t = (j as f32 / (n - 1) as f32 - 0.5) * len;
        s += qp.bilinear(x + t * ux, y + t * uy);
    }
    s / n as f32
}

/// Result of the edge tests.
pub struct EdgeTests {
    pub defocus: Signature,
    pub motion: Signature,
    pub channel_shift: Signature,
    /// Shift of the green (or only) channel, px: a global misregistration, reported as a note.
    pub global_shift: (f64, f64),
    pub n_points: usize,
}

pub fn tests(pairs: &[Pair], masks: &[Masks], q: &[Vec<Plane>], noise: &NoiseModel, z_thr: f64) -> EdgeTests {
    let mut defocus = Signature::new("defocus");
    let mut motion = Signature::new("motion_blur");
    let mut cs = Signature::new("channel_shift");
    let channels = pairs[0].channels();
    let pts = select(pairs, masks, q, noise, 400_000);
    let n_points = pts.len();
    if pts.len() < 200 {
        for s in [&mut defocus, &mut motion, &mut cs] {
            s.evidence = format!("too few usable edge pixels ({})", pts.len());
        }
        return EdgeTests { defocus, motion, channel_shift: cs, global_shift: (0.0, 0.0), n_points };
    }
    let fits: Vec<Option<WlsFit>> = (0..channels).map(|c| taylor(pairs, q, &pts, c)).collect();
    // --- channel shift (Taylor first, refined by a direct minimisation) -----------------------
    let ref_c = if channels == 3 { 1 } else { 0 };
    let mut shifts = vec![(0.0f64, 0.0f64); channels];
    let scan_pts: Vec<Pt> = {
        let cap = 60_000 * channels;
        let step = pts.len().div_ceil(cap).max(1);
        pts.iter().copied().step_by(step).collect()
    };
    for c in 0..channels {
        if let Some(f) = &fits[c] {
            let init = [f.beta[0].clamp(-3.0, 3.0), f.beta[1].clamp(-3.0, 3.0)];
            let loss = |d: &[f64]| -> f64 {
                let mut s = 0.0;
                for p in scan_pts.iter().filter(|p| p.c as usize == c) {
                    let k = p.k as usize;
                    let qp = &q[k][c];
                    let i = p.i as usize;
                    let (x, y) = ((i % qp.w) as f32, (i / qp.w) as f32);
                    let pred = qp.bilinear(x - d[0] as f32, y - d[1] as f32);
                    let e = (pairs[k].real[c].data[i] - pred) as f64;
                    s += p.w as f64 * e * e;
                }
                s
            };
            let best = stats::nelder_mead(&loss, &init, &[0.3, 0.3], 120, 1e-10);
            shifts[c] = (best[0], best[1]);
        }
    }
    let global_shift = shifts[ref_c];
    if channels == 3 {
        let (fr, fg, fb) = (&fits[0], &fits[1], &fits[2]);
        if let (Some(fr), Some(fg), Some(fb)) = (fr, fg, fb) {
            let se = |f: &WlsFit, i: usize| f.se(i);
            let dxr = fr.beta[0] - fg.beta[0];
            let dyr = fr.beta[1] - fg.beta[1];
            let dxb = fb.beta[0] - fg.beta[0];
            let dyb = fb.beta[1] - fg.beta[1];
            let ser = ((se(fr, 0).powi(2) + se(fg, 0).powi(2)).sqrt(), (se(fr, 1).powi(2) + se(fg, 1).powi(2)).sqrt());
            let seb = ((se(fb, 0).powi(2) + se(fg, 0).powi(2)).sqrt(), (se(fb, 1).powi(2) + se(fg, 1).powi(2)).sqrt());
            let chi = (dxr / ser.0).powi(2) + (dyr / ser.1).powi(2) + (dxb / seb.0).powi(2) + (dyb / seb.1).powi(2);
            cs.z = stats::chi2_to_z(chi, 4.0);
            let est = [
                shifts[0].0 - shifts[1].0,
                shifts[0].1 - shifts[1].1,
                shifts[2].0 - shifts[1].0,
                shifts[2].1 - shifts[1].1,
            ];
            for (n, v) in ["dx_r", "dy_r", "dx_b", "dy_b"].iter().zip(est) {
                cs.set_param(n, v);
            }
            cs.stderr =
                vec![("dx_r".into(), ser.0), ("dy_r".into(), ser.1), ("dx_b".into(), seb.0), ("dy_b".into(), seb.1)];
            cs.size = est.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            cs.size_unit = "px (largest component)";
            cs.where_ = "all edges; red and blue planes against green".into();
            cs.evidence = format!(
                "edge registration real vs sim: R {:+.2},{:+.2} px, G {:+.2},{:+.2} px, B {:+.2},{:+.2} px (Taylor Wald chi2 = {:.1} on 4 df, z = {:.1})",
                shifts[0].0, shifts[0].1, shifts[1].0, shifts[1].1, shifts[2].0, shifts[2].1, chi, cs.z
            );
        }
    } else {
        cs.evidence = "mono images: no channels to register".into();
    }
    // --- blur ----------------------------------------------------------------------------------
    // Pool Σ over channels (inverse-variance weights).
    let mut sig = [0.0f64; 3];
    let mut cov = [[0.0f64; 3]; 3];
    let mut wsum = 0.0;
    for f in fits.iter().flatten() {
        let k = f.beta.len();
        let ws = 1.0 / (f.se(2).powi(2) + f.se(4).powi(2)).max(1e-18);
        wsum += ws;
        for a in 0..3 {
            sig[a] += ws * f.beta[2 + a];
            for b in 0..3 {
                cov[a][b] += ws
                    * ws
                    * f.cov[(2 + a) * k + (2 + b)].max(if a == b {
                        f.cov_model[(2 + a) * k + 2 + b]
                    } else {
                        f64::MIN
                    });
            }
        }
    }
    if wsum > 0.0 {
        for a in 0..3 {
            sig[a] /= wsum;
            for b in 0..3 {
                cov[a][b] /= wsum * wsum;
            }
        }
    }
    let (sxx, sxy, syy) = (sig[0], sig[1], sig[2]);
    let tr = sxx + syy;
    let det = sxx * syy - sxy * sxy;
    let disc = (tr * tr / 4.0 - det).max(0.0).sqrt();
    let (l1, l2) = (tr / 2.0 + disc, tr / 2.0 - disc);
    // Eigenvector of l1 (image coordinates, y down).
    let (vx, vy) = if sxy.abs() > 1e-12 {
        (l1 - syy, sxy)
    } else if sxx >= syy {
        (1.0, 0.0)
    } else {
        (0.0, 1.0)
    };
    let angle_img = vy.atan2(vx); // y down
    let mut angle_deg = (-angle_img).to_degrees();
    angle_deg = angle_deg.rem_euclid(180.0);
    // Standard errors: isotropic part ~ trace/2, directional part ~ disc.
    let se_tr = (cov[0][0] + cov[2][2] + 2.0 * cov[0][2]).max(0.0).sqrt();
    let se_l2 = (0.5 * se_tr).max(1e-9) * 1.2;
    let se_dir = (0.5 * (cov[0][0] + cov[2][2]) + cov[1][1]).max(0.0).sqrt().max(1e-9);
    let z_iso = l2 / se_l2;
    let z_dir = (l1 - l2) / se_dir;
    // Direct scans for the estimates (green/only channel, shift applied).
    let sc = ref_c;
    let gpts: Vec<Pt> = scan_pts.iter().copied().filter(|p| p.c as usize == sc).collect();
    let (dx0, dy0) = shifts[sc];
    // A continuous Gaussian PSF of σ integrated over the pixel (see `pixel_gaussian`).
    // The global shift of this channel from the Taylor regression (its first moments are not
    // confounded with the blur, which has its own second-order terms; the bilinear shift search
    // above absorbs part of a blur into its interpolation), built into the pixel-integrated
    // kernels so that the shift adds no blur of its own.
    let (tdx, tdy) =
        fits[sc].as_ref().map(|f| (f.beta[0].clamp(-3.0, 3.0), f.beta[1].clamp(-3.0, 3.0))).unwrap_or((0.0, 0.0));
    let gauss_loss = |sigma: f64| -> f64 {
        let (kx, ky) = (pixel_gaussian_shifted(sigma, tdx), pixel_gaussian_shifted(sigma, tdy));
        let mut s = 0.0;
        for p in &gpts {
            let k = p.k as usize;
            let qp = &q[k][sc];
            let i = p.i as usize;
            let (x, y) = ((i % qp.w) as isize, (i / qp.w) as isize);
            let pred = blur_at(qp, x, y, &kx, &ky);
            let e = (pairs[k].real[sc].data[i] - pred) as f64;
            s += p.w as f64 * e * e;
        }
        s
    };
    let grid: Vec<f64> = (0..=16).map(|i| i as f64 * 0.25).collect();
    let gl: Vec<f64> = grid.iter().map(|&s| gauss_loss(s)).collect();
    let (sigma_best, _) = stats::golden_around_best(&mut |s| gauss_loss(s), &grid, &gl, 12);
    let n_g = gpts.len().max(1) as f64;
    defocus.profiles.push(Profile {
        title: "defocus: edge loss against Gaussian blur".into(),
        x_label: "sigma_px of the Gaussian applied to the sim".into(),
        y_label: "mean weighted squared residual at edges".into(),
        x: grid.clone(),
        series: vec![("loss".into(), gl.iter().map(|v| v / n_g).collect())],
    });
    defocus.z = z_iso;
    defocus.size = sigma_best;
    defocus.size_unit = "px (Gaussian sigma, continuous PSF)";
    // The library's kernel (variance σ², no pixel integration) of the same variance starts the
    // forward fit; the report reads the continuous σ.
    defocus.set_param("sigma_px", kernel_variance(&pixel_gaussian(sigma_best)).sqrt());
    defocus.set_param(EDGE_SIGMA_PARAM, sigma_best.max(0.0));
    defocus.stderr = vec![("sigma_px".into(), se_l2 / (2.0 * l2.max(0.05).sqrt()))];
    defocus.where_ = format!("edges ({n_points} edge pixels)");
    defocus.evidence = format!(
        "edge blur moments Σ = [[{sxx:.3}, {sxy:.3}], [{sxy:.3}, {syy:.3}]] px² (isotropic part λ2 = {l2:.3} ± {se_l2:.3}, z = {z_iso:.1}); best Gaussian sigma {sigma_best:.2} px (edge loss {:.1} → {:.1})",
        gl[0] / n_g,
        gauss_loss(sigma_best) / n_g
    );
    // Motion: scan length and angle around the Taylor direction.
    let line_loss = |len: f64, theta_deg: f64| -> f64 {
        let th = theta_deg.to_radians() as f32;
        let mut s = 0.0;
        for p in &gpts {
            let k = p.k as usize;
            let qp = &q[k][sc];
            let i = p.i as usize;
            let (x, y) = ((i % qp.w) as f32 - dx0 as f32, (i / qp.w) as f32 - dy0 as f32);
            let pred = if len < 1e-3 { qp.bilinear(x, y) } else { line_at(qp, x, y, len as f32, th) };
            let e = (pairs[k].real[sc].data[i] - pred) as f64;
            s += p.w as f64 * e * e;
        }
        s
    };
    let l_init = (12.0 * (l1 - l2).max(0.0)).sqrt();
    let mut best_m = (l_init.max(1.0), angle_deg, f64::INFINITY);
    let mut curve = Vec::new();
    if z_dir > 2.0 {
        for i in 0..12 {
            let th = i as f64 * 15.0;
            let (len, v) = stats::golden(&mut |l| line_loss(l, th), 0.0, (3.0 * l_init).clamp(3.0, 40.0), 14);
            curve.push((th, v));
            if v < best_m.2 {
                best_m = (len, th, v);
            }
        }
        let (th_b, _) = stats::golden(&mut |t| line_loss(best_m.0, t), best_m.1 - 15.0, best_m.1 + 15.0, 10);
        let (len_b, v_b) =
            stats::golden(&mut |l| line_loss(l, th_b), (best_m.0 * 0.5).max(0.0), best_m.0 * 1.5 + 1.0, 14);
        best_m = (len_b, th_b.rem_euclid(180.0), v_b);
    }
    motion.z = z_dir;
    motion.size = if z_dir > 2.0 { best_m.0 } else { l_init };
    motion.size_unit = "px (line length)";
    motion.set_param("length_px", motion.size.max(0.0));
    motion.set_param("angle_deg", if z_dir > 2.0 { best_m.1 } else { angle_deg });
    motion.stderr = vec![("length_px".into(), 6.0 * se_dir / motion.size.max(0.5))];
    motion.where_ = format!("edges perpendicular to {:.0}° blur most", motion.param("angle_deg").unwrap_or(0.0));
    motion.evidence = format!(
        "directional edge spread: λ1 - λ2 = {:.3} ± {:.3} px² (z = {:.1}) along {:.0}°",
        l1 - l2,
        se_dir,
        z_dir,
        angle_deg
    );
    if !curve.is_empty() {
        motion.profiles.push(Profile {
            title: "motion blur: best edge loss per blur direction".into(),
            x_label: "angle_deg (counter-clockwise from +x, y up)".into(),
            y_label: "mean weighted squared residual at edges".into(),
            x: curve.iter().map(|c| c.0).collect(),
            series: vec![("loss".into(), curve.iter().map(|c| c.1 / n_g).collect())],
        });
    }
    let _ = z_thr;
    EdgeTests { defocus, motion, channel_shift: cs, global_shift, n_points }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// J1(x) = (1/π) ∫₀^π cos(τ − x sin τ) dτ (midpoint rule).
    fn j1(x: f64) -> f64 {
        let n = 200;
        (0..n).map(|j| (j as f64 + 0.5) * std::f64::consts::PI / n as f64).map(|t| (t - x * t.sin()).cos()).sum::<f64>()
            / n as f64
    }

    /// Pixel-area kernel (16x16 samples per pixel, half-size `half`) of a radial PSF, unit sum.
    fn area_kernel(half: usize, f: impl Fn(f64) -> f64) -> Vec<f64> {
        let n = 2 * half + 1;
        let mut k = vec![0.0; n * n];
        for j in 0..n {
            for i in 0..n {
                let mut acc = 0.0;
                for sj in 0..16 {
                    for si in 0..16 {
                        let x = i as f64 - half as f64 - 0.5 + (si as f64 + 0.5) / 16.0;
                        let y = j as f64 - half as f64 - 0.5 + (sj as f64 + 0.5) / 16.0;
                        acc += f((x * x + y * y).sqrt());
                    }
                }
                k[j * n + i] = acc;
            }
        }
        let s: f64 = k.iter().sum();
        k.iter().map(|v| v / s).collect()
    }

    /// σ read on the edge spread of a scene through `k`.
    fn edge_sigma(k: &[f64], half: usize) -> f64 {
        let pairs = super::super::common::blurred_test_pairs(k, half, 3);
        let masks: Vec<Masks> = pairs.iter().map(|p| Masks::compute(&p.sim)).collect();
        let q: Vec<Vec<Plane>> = pairs.iter().map(|p| p.sim.clone()).collect();
        let mut noise = NoiseModel::prior(1.0);
        noise.a = 1.0;
        noise.b = 1.0 / 8.0;
        let t = tests(&pairs, &masks, &q, &noise, 6.0);
        t.defocus.param(EDGE_SIGMA_PARAM).expect("edge sigma")
    }

    /// The pixel-integrated Gaussian has unit sum and variance σ² + 1/12 (from σ ≈ 0.5 px on);
    /// a shift moves its centroid without widening it.
    #[test]
    fn pixel_gaussian_adds_the_pixel_variance() {
        for s in [0.3, 0.5, 0.8, 1.5] {
            let k = pixel_gaussian(s);
            let sum: f64 = k.iter().map(|&v| v as f64).sum();
            let var = kernel_variance(&k);
            assert!((sum - 1.0).abs() < 1e-6);
            if s >= 0.5 {
                assert!((var - s * s - PIXEL_VARIANCE).abs() < 0.01, "sigma {s}: var {var}");
            } else {
                assert!(var < s * s + PIXEL_VARIANCE, "sigma {s}: var {var}");
            }
        }
        assert_eq!(pixel_gaussian(0.0), vec![1.0]);
        // A shifted kernel moves the centroid by -d in tap offsets (content moves by +d).
        let k = pixel_gaussian_shifted(0.6, 0.4);
        let r = (k.len() / 2) as f64;
        let m: f64 = k.iter().enumerate().map(|(i, &v)| v as f64 * (i as f64 - r)).sum();
        assert!((m + 0.4).abs() < 0.01, "centroid {m}");
        assert!((kernel_variance(&k) - kernel_variance(&pixel_gaussian(0.6))).abs() < 0.01);
    }

    /// The defocus σ read on the edge spread is the PSF's equivalent Gaussian whatever its form:
    /// an Airy pattern (pixel-area weights) reads near 0.42 λN, a pillbox of radius R near R/2, a
    /// Gaussian its σ (issue 13: an Airy of 0.55 px read 0.81 px, a 0.45 px one 0.71 px).
    #[test]
    fn edge_sigma_is_the_equivalent_gaussian_of_any_psf() {
        for truth in [0.45, 0.55] {
            let ln = truth / 0.42;
            let k = area_kernel(5, |r| {
                let x = std::f64::consts::PI * r / ln;
                if x < 1e-9 { 1.0 } else { (2.0 * j1(x) / x).powi(2) }
            });
            let s = edge_sigma(&k, 5);
            eprintln!("Airy 0.42 λN = {truth}: edge sigma {s:.3}");
            assert!((s - truth).abs() <= 0.25 * truth, "Airy 0.42 λN = {truth}: read {s:.3}");
        }
        for rad in [1.1, 1.4] {
            let k = area_kernel(2, |r| if r <= rad { 1.0 } else { 0.0 });
            let s = edge_sigma(&k, 2);
            eprintln!("pillbox R {rad}: edge sigma {s:.3}");
            assert!((s - rad / 2.0).abs() <= 0.25 * rad / 2.0, "pillbox R {rad}: read {s:.3}");
        }
        let k = area_kernel(4, |r| (-r * r / (2.0 * 0.7 * 0.7)).exp());
        let s = edge_sigma(&k, 4);
        assert!((s - 0.7).abs() <= 0.07, "Gaussian 0.7: read {s:.3}");
    }
}
