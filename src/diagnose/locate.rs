//! Locate: masks from the sim, a first noise model, the global photometric alignment, the
//! residual maps and the signature test of every deterministic effect.
//!
//! The signatures are cheap, targeted statistics (regressions of the residual on the sim's level,
//! position and derivatives, profiles around saturated pixels). They say *where* real and sim
//! differ and give each effect's initial parameters; the decision which effects are present is
//! taken by the forward-model selection ([`super::select`]), which also resolves effects that
//! mimic each other in a single statistic (an unmodelled gain looks like blur at edges, for
//! example). The stochastic effects are tested after that, on the residual of the fitted model
//! ([`super::fit`]).

use super::common::{Masks, NoiseModel};
use super::img::{FS, Pair, Plane};
use super::noise;
use super::photometric::{self, Photometric};
use super::{Options, Signature, edges, fixed, flare, psf, saturation};
use rayon::prelude::*;

/// Everything the signature stage found.
pub struct Located {
    pub masks: Vec<Masks>,
    /// Noise model measured on real - sim (used by the signatures and the forward-model fit).
    pub noise: NoiseModel,
    pub photo: Photometric,
    /// Per-frame hot-pixel candidate masks (left out of every loss and statistic).
    pub hot: Vec<Vec<bool>>,
    /// All signature tests, in test order (deterministic effects first; the stochastic effects
    /// and camera noise are added by the fit).
    pub signatures: Vec<Signature>,
    pub notes: Vec<String>,
    /// Quantisation step of the real data (8-bit DN).
    pub quant: f64,
    /// The blur kernel measured tap by tap ([`psf`]), when there are enough usable edges.
    pub psf: Option<psf::Psf>,
    /// Per frame, the pixels over-exposed sources' spilled charge reaches
    /// ([`saturation::spill_skip`]; None without over-exposed sources): left out of the noise
    /// estimates as the hot pixels are.
    pub spill: Option<Vec<Vec<bool>>>,
}

impl Located {
    pub fn signature(&self, effect: &str) -> Option<&Signature> {
        self.signatures.iter().find(|s| s.effect == effect)
    }
    pub fn detected(&self) -> impl Iterator<Item = &Signature> {
        self.signatures.iter().filter(|s| s.detected)
    }
}

/// Prediction (Q: sim through the photometric model) and residual (real − Q) planes under a
/// photometric model, per pair and channel (pairs in parallel, collected in pair order).
pub fn predict_planes(pairs: &[Pair], ph: &Photometric) -> (Vec<Vec<Plane>>, Vec<Vec<Plane>>) {
    pairs.par_iter().map(|p| predict_pair(p, ph)).unzip()
}

/// [`predict_planes`] of one pair.
fn predict_pair(p: &Pair, ph: &Photometric) -> (Vec<Plane>, Vec<Plane>) {
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
    (pq, pr)
}

/// Quantisation step (8-bit DN) of the real data (see [`super::img::code_step`]).
pub fn quantisation(pairs: &[Pair]) -> f64 {
    // The coarsest step of any frame (10-bit data in 16-bit PNG: FS/1023; 8-bit formats: 1).
    pairs.iter().map(|p| super::img::code_step(&p.real_frame)).fold(0.0, f64::max)
}

/// Run the signature tests of the deterministic effects.
pub fn locate(pairs: &[Pair], opts: &Options) -> Located {
    let notes = Vec::new();
    let quant = quantisation(pairs);
    // Each pair's masks on its own (in parallel; collected in pair order).
    let masks: Vec<Masks> = pairs.par_iter().map(|p| Masks::compute(&p.sim)).collect();
    let sims: Vec<Vec<Plane>> = pairs.iter().map(|p| p.sim.clone()).collect();
    // First pass: noise and photometric model; hot pixels; second pass without them.
    super::progress("locate: masks");
    let noise0 = noise::estimate(pairs, &masks, &sims, quant, 0.0, None);
    let photo0 = photometric::fit(pairs, &masks, &noise0);
    let (pred0, _) = predict_planes(pairs, &photo0);
    let quiet: Vec<Vec<bool>> = masks.iter().map(|m| m.quiet.to_bools()).collect();
    super::progress("locate: first pass");
    let (_, hot, _) = fixed::hot_pixels(pairs, &masks, &quiet, &pred0, &noise0);
    // The first pass's planes are done with: a frame's worth of memory per pair less at the
    // peak of the signature tests below.
    drop((pred0, quiet));
    let noise = noise::estimate(pairs, &masks, &sims, quant, 0.0, Some(&hot));
    drop(sims);
    let photo = photometric::fit(pairs, &masks, &noise);
    let (pred, resid) = predict_planes(pairs, &photo);
    super::progress("locate: second pass");
    let z = opts.z_threshold;

    let mut sigs: Vec<Signature> = Vec::new();
    // Photometric.
    let pt = photometric::tests(&photo, pairs, &masks, z);
    let (gain_sig, gamma_sig, vig, stray) = (pt.gain, pt.gamma, pt.vignetting, pt.stray);
    // Additive level: dark blocks when there are several, else the regression intercept.
    let (off, off_se, off_src) = match noise.dark_level() {
        Some((mu, se, n)) if n >= 4 => (mu, se, format!("censored fits of {n} dark blocks")),
        _ => (pt.offset, pt.offset_se, "photometric regression intercept".to_string()),
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
    dark.profiles.push(dark_profile(&noise));
    // Edges (Taylor regression on the photometric prediction).
    super::progress("locate: photometric tests");
    let et = edges::tests(pairs, &masks, &pred, &noise, z);
    let (mut defocus, mut motion, cs) = (et.defocus, et.motion, et.channel_shift);
    // The kernel itself, tap by tap: its direction (motion or not) and its best-fitting Gaussian.
    super::progress("locate: edges");
    let psf = psf::measure(pairs, &masks, &pred, &noise, &hot);
    if let Some(k) = &psf {
        let [sxx, sxy, syy] = k.moments;
        defocus.evidence = format!(
            "{}; measured PSF ({}x{} taps on {} edge pixels): moments Σ = [[{sxx:.3}, {sxy:.3}], [{sxy:.3}, {syy:.3}]] px²",
            defocus.evidence,
            2 * psf::HALF + 1,
            2 * psf::HALF + 1,
            k.n
        );
        motion.set_param(psf::ANISO_Z_PARAM, k.aniso_z);
        let half_diff = k.aniso.0.hypot(k.aniso.1);
        motion.evidence = format!(
            "{}; measured PSF anisotropy (λ1 − λ2)/2 = {half_diff:.3} px² along {:.0}° (chi2 = {:.1} on 2 df, z = {:.1})",
            motion.evidence, k.angle_deg, k.aniso_chi2, k.aniso_z
        );
        if k.aniso_z >= z {
            // The direction of the measured kernel starts the forward fit (the line scan on the
            // edges can settle on another local minimum for short streaks); a streak of length L
            // has (λ1 − λ2) = L²/12.
            motion.set_param("angle_deg", k.angle_deg);
            motion.set_param("length_px", (24.0 * half_diff).sqrt());
        }
    }
    let mut notes = notes;
    if et.global_shift.0.abs().max(et.global_shift.1.abs()) > 0.2 {
        notes.push(format!(
            "real is shifted by ({:+.2}, {:+.2}) px relative to sim in all channels (not an effect of the vocabulary; check the geometric alignment)",
            et.global_shift.0, et.global_shift.1
        ));
    }
    let blur_sigma = defocus.size.max(0.0);
    // Saturation neighbourhoods.
    super::progress("locate: psf");
    let bloom = saturation::blooming(pairs, &masks, &pred, &resid, &noise, blur_sigma);
    let smear = saturation::smear(pairs, &masks, &resid, &pred, &noise);
    super::progress("locate: saturation");
    // Over-exposed sources: the plateau their spilled charge grew in the real frames (and its
    // halo) is no sample of the camera noise at the sim's level there (a star's wing at 5 DN in
    // the sim reads the well in the real frame): the fit's noise estimates leave it out with the
    // hot pixels (the forward-model selection starts from the noise model above and measures it
    // again on the fitted model's residual).
    // Per frame, the pixels over-exposed sources' spill reaches (computed once; None without
    // over-exposed sources).
    let spill_masks: Option<Vec<Vec<bool>>> = bloom.param("halo_px").map(|_| {
        pairs.par_iter().zip(&masks).map(|(p, m)| saturation::spill_skip(p, m, &bloom).unwrap_or_default()).collect()
    });
    let spill: Option<Vec<Vec<bool>>> = spill_masks.as_ref().map(|sm| {
        hot.iter()
            .zip(sm)
            .map(|(h, s)| h.iter().enumerate().map(|(i, &hv)| hv || s.get(i).copied().unwrap_or(false)).collect())
            .collect()
    });
    // The ghost scan leaves out, per frame, the pixels over-exposed sources' spill reaches.
    let flare = flare::lens_flare(pairs, &masks, &pred, &resid, &noise, z, spill_masks.as_deref());
    sigs.extend([gain_sig, gamma_sig, vig, stray, dark, defocus, motion, cs, bloom, smear, flare]);
    // The prediction and residual planes are not used after this stage (the fit works on the
    // forward models' own planes): released here, a frame per pair and channel each.
    drop((pred, resid));
    Located { masks, noise, photo, hot, signatures: sigs, notes, quant, psf, spill }
}

/// Dark-block additive levels against their base level.
fn dark_profile(n: &NoiseModel) -> super::Profile {
    let mut pts: Vec<(f64, f64)> = n.low.iter().map(|b| (b.base, b.mu)).collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    super::Profile {
        title: "dark level: censored fits of dark blocks".into(),
        x_label: "mean sim level of the block (DN)".into(),
        y_label: "real - sim (DN)".into(),
        x: pts.iter().map(|p| p.0).collect(),
        series: vec![("block level".into(), pts.iter().map(|p| p.1).collect())],
    }
}

/// Camera-noise signatures from a noise model.
pub fn camera_noise(noise: &NoiseModel, z: f64) -> (Signature, Signature) {
    let mut gn = Signature::new("gaussian_noise");
    let read = noise.read_sigma();
    gn.z = noise.a / noise.se_a.max(1e-9);
    gn.size = read;
    gn.size_unit = "DN";
    gn.set_param("sigma_dn", read);
    gn.stderr = vec![("sigma_dn".into(), noise.se_a / (2.0 * read.max(0.1)))];
    gn.where_ = "everywhere (variance intercept at zero signal)".into();
    gn.evidence = format!(
        "noise variance {:.3} ± {:.3} DN² at zero signal (quantisation {:.3} DN² removed), from {} level bins and {} dark blocks",
        noise.a,
        noise.se_a,
        noise.quant * noise.quant / 12.0,
        noise.bins.len(),
        noise.low.len()
    );
    gn.profiles.push(noise_profile(noise));
    let mut sn = Signature::new("shot_noise");
    sn.z = if noise.slope_identified { noise.b / noise.se_b.max(1e-12) } else { 0.0 };
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
    gn.detected = gn.z > z && read >= 0.1;
    sn.detected = sn.z > z && noise.b > 1e-3;
    (gn, sn)
}

fn noise_profile(n: &NoiseModel) -> super::Profile {
    let mut x: Vec<f64> = n.bins.iter().map(|b| b.level).collect();
    let mut meas: Vec<f64> = n.bins.iter().map(|b| b.var).collect();
    for l in &n.low {
        x.push(l.base + l.mu);
        meas.push(l.sigma * l.sigma);
    }
    let mut idx: Vec<usize> = (0..x.len()).collect();
    idx.sort_by(|&a, &b| x[a].total_cmp(&x[b]));
    let x: Vec<f64> = idx.iter().map(|&i| x[i]).collect();
    let meas: Vec<f64> = idx.iter().map(|&i| meas[i]).collect();
    let q12 = n.quant * n.quant / 12.0;
    super::Profile {
        title: "camera noise: variance against signal".into(),
        x_label: "level (DN)".into(),
        y_label: "noise variance (DN²)".into(),
        series: vec![
            ("measured (high-pass bins, dark-block fits)".into(), meas),
            ("fitted a + b·s + c·s²".into(), x.iter().map(|&s| n.var(s) - q12).collect()),
        ],
        x,
    }
}
