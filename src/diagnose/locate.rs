//! Locate: masks from the sim, the noise model, the photometric model, the residual maps and
//! every signature test; then the decision which effects are candidates.

use super::img::{FS, Pair, Plane, distance_transform};
use super::noise::{self, NoiseModel};
use super::photometric::{self, Photometric};
use super::{Options, Signature, edges, fixed, jpeg, saturation};

/// Per-pair masks computed from the sim image (all channels).
#[derive(Debug, Clone)]
pub struct Masks {
    /// Any channel at full scale.
    pub sat: Vec<bool>,
    /// Within 2 px of a saturated pixel.
    pub sat_near: Vec<bool>,
    /// Distance to the nearest saturated pixel (px; infinite without saturation).
    pub dist_sat: Vec<f32>,
    /// Inside saturated regions: distance to the nearest unsaturated pixel.
    pub dist_in: Vec<f32>,
    /// Locally linear (curvature <= 1 DN in a 3x3 window): smooth differences cancel in a
    /// second difference.
    pub linear: Vec<bool>,
    /// Flat (gradient <= 2 DN/px and linear in a 5x5 window).
    pub flat: Vec<bool>,
    /// Distance to the nearest edge pixel (gradient > 8 DN/px).
    pub dist_edge: Vec<f32>,
    /// Distance to the nearest edge pixel that is not the border of a saturated region.
    pub dist_edge_unsat: Vec<f32>,
}

impl Masks {
    pub fn compute(sim: &[Plane]) -> Masks {
        let (w, h) = (sim[0].w, sim[0].h);
        let n = w * h;
        let mut grad = Plane::new(w, h);
        let mut curv = Plane::new(w, h);
        let mut sat = vec![false; n];
        for s in sim {
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    let (xi, yi) = (x as isize, y as isize);
                    let c = s.at(x, y);
                    let l = s.at_clamped(xi - 1, yi);
                    let r = s.at_clamped(xi + 1, yi);
                    let u = s.at_clamped(xi, yi - 1);
                    let d = s.at_clamped(xi, yi + 1);
                    let g = 0.5 * ((r - l).abs() + (d - u).abs());
                    let cxx = (r - 2.0 * c + l).abs();
                    let cyy = (d - 2.0 * c + u).abs();
                    let cxy = 0.25
                        * (s.at_clamped(xi + 1, yi + 1) - s.at_clamped(xi - 1, yi + 1) - s.at_clamped(xi + 1, yi - 1)
                            + s.at_clamped(xi - 1, yi - 1))
                        .abs();
                    grad.data[i] = grad.data[i].max(g);
                    curv.data[i] = curv.data[i].max(cxx.max(cyy).max(cxy));
                    if c >= 254.5 {
                        sat[i] = true;
                    }
                }
            }
        }
        let curv3 = curv.extreme_filter(1, true);
        let curv5 = curv.extreme_filter(2, true);
        let grad5 = grad.extreme_filter(2, true);
        let linear: Vec<bool> = curv3.data.iter().map(|&v| v <= 1.01).collect();
        let flat: Vec<bool> = (0..n).map(|i| curv5.data[i] <= 1.01 && grad5.data[i] <= 2.0).collect();
        let dist_sat = distance_transform(&sat, w, h);
        let unsat: Vec<bool> = sat.iter().map(|&s| !s).collect();
        let dist_in = distance_transform(&unsat, w, h);
        let edge: Vec<bool> = grad.data.iter().map(|&g| g > 8.0).collect();
        let dist_edge = distance_transform(&edge, w, h);
        let edge_unsat: Vec<bool> = (0..n).map(|i| edge[i] && dist_sat[i] > 3.0).collect();
        let dist_edge_unsat = distance_transform(&edge_unsat, w, h);
        let sat_near = dist_sat.iter().map(|&d| d <= 2.0).collect();
        Masks { sat, sat_near, dist_sat, dist_in, linear, flat, dist_edge, dist_edge_unsat }
    }
}

/// Everything the signature stage found.
pub struct Located {
    pub masks: Vec<Masks>,
    pub noise: NoiseModel,
    pub photo: Photometric,
    /// Q: sim through the photometric model, per pair and channel.
    pub pred: Vec<Vec<Plane>>,
    /// real - Q.
    pub resid: Vec<Vec<Plane>>,
    /// Per-frame hot-pixel candidate masks.
    pub hot: Vec<Vec<bool>>,
    /// All signature tests (detected or not), in test order.
    pub signatures: Vec<Signature>,
    pub notes: Vec<String>,
    /// Quantisation step of the real data (8-bit DN).
    pub quant: f64,
}

impl Located {
    pub fn signature(&self, effect: &str) -> Option<&Signature> {
        self.signatures.iter().find(|s| s.effect == effect)
    }
    pub fn detected(&self) -> impl Iterator<Item = &Signature> {
        self.signatures.iter().filter(|s| s.detected)
    }
}

/// Prediction and residual planes under a photometric model.
pub fn predict_planes(pairs: &[Pair], ph: &Photometric) -> (Vec<Vec<Plane>>, Vec<Vec<Plane>>) {
    let mut pred = Vec::new();
    let mut resid = Vec::new();
    for p in pairs {
        let (w, h) = (p.w(), p.h());
        let mut pq = Vec::new();
        let mut pr = Vec::new();
        // The model is separable: precompute the position terms once per pixel.
        let mut add = vec![0f32; w * h];
        let mut rho = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let (xn, yn, r2) = photometric::coords(x, y, w, h);
                add[y * w + x] = ph.additive(xn, yn) as f32;
                rho[y * w + x] = r2 as f32;
            }
        }
        let b = &ph.beta;
        for c in 0..p.channels() {
            let s = &p.sim[c].data;
            let mut q = Plane::new(w, h);
            for i in 0..w * h {
                let sv = s[i] as f64;
                let r2 = rho[i] as f64;
                let gam = if sv > 0.0 { sv * (sv / FS as f64).ln() } else { 0.0 };
                let v = sv
                    + add[i] as f64
                    + b[photometric::I_GAIN] * sv
                    + b[photometric::I_GAMMA] * gam
                    + sv * (b[photometric::I_V2] * r2 + b[photometric::I_V4] * r2 * r2);
                q.data[i] = v.clamp(0.0, FS as f64) as f32;
            }
            let r = p.real[c].sub(&q);
            pq.push(q);
            pr.push(r);
        }
        pred.push(pq);
        resid.push(pr);
    }
    (pred, resid)
}

/// Run every signature test and decide the candidates.
pub fn locate(pairs: &[Pair], opts: &Options) -> Located {
    let mut notes = Vec::new();
    let quant =
        if pairs.iter().all(|p| p.real_frame.format == crate::frame::PixelFormat::Mono16) { 1.0 / 257.0 } else { 1.0 };
    let masks: Vec<Masks> = pairs.iter().map(|p| Masks::compute(&p.sim)).collect();
    // First pass: noise, photometric model, residuals.
    let noise0 = noise::estimate(pairs, &masks, quant, 0.0, None);
    let photo0 = photometric::fit(pairs, &masks, &noise0);
    let (pred0, _) = predict_planes(pairs, &photo0);
    // Fixed patterns: hot pixels (excluded from everything after), prnu.
    let (hot_sig, hot, _hot_excess) = fixed::hot_pixels(pairs, &masks, &pred0, &noise0);
    let (prnu_sig, prnu_c) = fixed::prnu(pairs, &masks, &noise0, &hot);
    // Second pass with the fixed-pattern variance and hot pixels removed.
    let noise = noise::estimate(pairs, &masks, quant, prnu_c, Some(&hot));
    let photo = photometric::fit(pairs, &masks, &noise);
    let (pred, resid) = predict_planes(pairs, &photo);
    let z = opts.z_threshold;

    let mut sigs: Vec<Signature> = Vec::new();
    // Camera noise.
    let mut gn = Signature::new("gaussian_noise");
    let read = noise.read_sigma();
    let q12 = quant * quant / 12.0;
    gn.z = (noise.a - q12) / noise.se_a.max(1e-9);
    gn.size = read;
    gn.size_unit = "DN";
    gn.set_param("sigma_dn", read);
    gn.stderr = vec![("sigma_dn".into(), noise.se_a / (2.0 * read.max(0.1)))];
    gn.where_ = "everywhere (variance intercept at zero signal)".into();
    gn.evidence = format!(
        "noise variance {:.3} DN² at zero signal (quantisation {:.3} DN²); dark-region fit sigma {}",
        noise.a,
        q12,
        noise.dark.map(|d| format!("{:.3} DN (n = {})", d.sigma, d.n)).unwrap_or_else(|| "n/a".into())
    );
    gn.profiles.push(noise_profile(&noise));
    let mut sn = Signature::new("shot_noise");
    sn.z = noise.b / noise.se_b.max(1e-12);
    sn.size = noise.b;
    sn.size_unit = "DN² per DN";
    let gain = if noise.b > 0.0 { 1.0 / noise.b } else { 1e6 };
    sn.set_param("gain_e_per_dn", gain);
    sn.stderr = vec![("gain_e_per_dn".into(), noise.se_b * gain * gain)];
    sn.where_ = "everywhere (noise variance grows with the signal)".into();
    sn.evidence = format!(
        "variance slope {:.4} ± {:.4} DN²/DN over levels {:.0}..{:.0} DN (z = {:.1}) → {:.2} e-/DN",
        noise.b, noise.se_b, noise.fit_range.0, noise.fit_range.1, sn.z, gain
    );
    gn.detected = gn.z > z && read >= 0.2;
    sn.detected = sn.z > z && noise.b > 1e-3;
    // Photometric.
    let pt = photometric::tests(&photo, pairs, &masks, z);
    let mut gain_sig = pt.gain;
    let mut gamma_sig = pt.gamma;
    let mut vig = pt.vignetting;
    let mut stray = pt.stray;
    gamma_sig.detected = gamma_sig.z > z && gamma_sig.size >= 0.02;
    vig.detected = vig.z > z && vig.size >= 0.015;
    stray.detected = stray.z > z && stray.size >= 0.8;
    let gain_dev = gain_sig.z > z && gain_sig.size >= 0.01;
    // Additive level: from black regions when there are any (censored fit), else the regression.
    let (off, off_se, off_src) = match noise.dark {
        Some(d) if d.n >= 2000 => (d.mu, d.se_mu.max(0.02), "black sim regions (censored fit)"),
        _ => (pt.offset, pt.offset_se, "photometric regression intercept"),
    };
    // With stray light the additive level is the field's minimum, not its mean.
    let (off, off_se) = if stray.detected {
        let (lo, _hi, _) = photo.additive_range();
        (lo.min(off), off_se)
    } else {
        (off, off_se)
    };
    let off_z = off / off_se;
    let mut dark = Signature::new("dark_current");
    dark.z = off_z;
    dark.size = off;
    dark.size_unit = "DN additive level";
    dark.set_param("mean_dn", off.max(0.0));
    dark.set_param("hot_pixel_rate", 0.0);
    dark.stderr = vec![("mean_dn".into(), off_se)];
    dark.where_ = "dark regions / everywhere (additive level)".into();
    dark.evidence = format!("additive level {off:.3} ± {off_se:.3} DN from {off_src} (z = {off_z:.1})");
    let off_sig = off_z.abs() > z && off.abs() >= 0.4;
    if gain_dev || (off_sig && off < 0.0) {
        gain_sig.detected = true;
        gain_sig.set_param("offset_dn", if off_sig { off } else { 0.0 });
        if !gain_dev {
            gain_sig.set_param("gain", 1.0);
            gain_sig.z = off_z.abs();
        }
    } else if off_sig {
        dark.detected = true;
    }
    // Hot pixels: part of dark current when there is a dark level too.
    let mut hot_sig = hot_sig;
    hot_sig.detected = hot_sig.z > z && hot_sig.size > 0.0;
    if hot_sig.detected && dark.detected {
        dark.set_param("hot_pixel_rate", hot_sig.size);
        dark.evidence.push_str(&format!("; with {}", hot_sig.evidence));
        hot_sig.detected = false;
        hot_sig.evidence.push_str(" (reported as dark_current.hot_pixel_rate)");
    }
    let mut prnu_sig = prnu_sig;
    prnu_sig.detected = prnu_sig.z > z && prnu_sig.size >= 0.003;
    // Edges.
    let et = edges::tests(pairs, &masks, &pred, &noise, z);
    let mut defocus = et.defocus;
    let mut motion = et.motion;
    let mut cs = et.channel_shift;
    motion.detected = motion.z > z && motion.size >= 1.0;
    defocus.detected = defocus.z > z && defocus.size >= 0.3;
    cs.detected = cs.z > z && cs.size >= 0.15;
    if et.global_shift.0.abs().max(et.global_shift.1.abs()) > 0.2 {
        notes.push(format!(
            "real is shifted by ({:+.2}, {:+.2}) px relative to sim in all channels (not an effect of the vocabulary; check the geometric alignment)",
            et.global_shift.0, et.global_shift.1
        ));
    }
    let blur_sigma = if defocus.detected { defocus.size } else { 0.0 };
    // Saturation neighbourhoods.
    let mut bloom = saturation::blooming(pairs, &masks, &pred, &resid, &noise, blur_sigma);
    bloom.detected = bloom.z > z && bloom.size >= 1.5;
    let mut smear = saturation::smear(pairs, &masks, &resid, &pred, &noise);
    smear.detected = smear.z > z && smear.size >= 0.02;
    let mut flare = saturation::lens_flare(pairs, &masks, &resid, &noise);
    flare.detected = flare.z > z && flare.param("intensity").unwrap_or(0.0) >= 0.005;
    // Row noise, JPEG.
    let mut row = fixed::row_noise(pairs, &masks, &resid, &pred, &noise);
    row.detected = row.z > z && row.size >= 0.1;
    let mut jp = jpeg::test(pairs);
    jp.detected = jp.z > z.max(8.0) && jp.param("quality").unwrap_or(100.0) < 98.0;

    sigs.extend([
        gn, sn, gain_sig, gamma_sig, vig, stray, dark, hot_sig, prnu_sig, defocus, motion, cs, bloom, smear, flare,
        row, jp,
    ]);
    Located { masks, noise, photo, pred, resid, hot, signatures: sigs, notes, quant }
}

fn noise_profile(n: &NoiseModel) -> super::Profile {
    let x: Vec<f64> = n.bins.iter().map(|b| b.0).collect();
    super::Profile {
        title: "camera noise: variance against signal".into(),
        x_label: "sim level (DN)".into(),
        y_label: "noise variance (DN²)".into(),
        series: vec![
            ("measured (high-pass)".into(), n.bins.iter().map(|b| b.1).collect()),
            ("fitted a + b·s + c·s²".into(), x.iter().map(|&s| n.var(s)).collect()),
        ],
        x,
    }
}
