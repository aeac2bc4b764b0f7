//! Model: select and fit the deterministic effects on the library's forward models
//! ([`super::select`]), then test and fit the stochastic ones on the residual of that model, and
//! measure the fit before and after.
//!
//! * **Deterministic effects** (optics, blooming, smear, gain_offset, gamma, the mean of the dark
//!   current): forward selection with a robust likelihood, an information criterion and a
//!   significance test; parameters fitted jointly (coordinate-wise golden sections in normalised
//!   parameter space, log space for parameters declared `.log()`), initialised from the
//!   signature estimates.
//! * **Stochastic effects** are tested on `real - model` of every pair with statistics whose
//!   null distribution does not depend on the noise model: prnu by the covariance of the
//!   residual between frames, row noise by the covariance of row offsets between even and odd
//!   columns, hot pixels by recurrence at the same place, JPEG by the DCT quantisation lattice.
//!   Camera noise (variance against signal) is re-measured on the same residual. They are fitted
//!   by moment matching through the library's own effects ([`super::moments`]).

use super::common::{NoiseModel, QUIET_LAPLACIAN, params_from_signature};
use super::img::{FS, Pair, Plane, frame_from_planes};
use super::locate::{self, Located};
use super::noise;
use super::select::{self, Candidate, Evidence, FitCtx, LossData};
use super::{DiagnoseError, Options, Signature, fixed, jpeg};
use crate::config::FaultConfig;
use crate::faults::{ParamKind, Params, registry};
use crate::frame::Frame;
use rayon::prelude::*;

/// One reported effect.
#[derive(Debug, Clone)]
pub struct FittedEffect {
    pub name: &'static str,
    /// Library parameters (None when the effect is not registered).
    pub params: Option<Params>,
    /// Canonical parameters for the report (name, value).
    pub canonical: Vec<(String, serde_json::Value)>,
    pub stderr: Vec<(String, f64)>,
    pub loss_before: f64,
    pub loss_after: f64,
    pub z: f64,
    pub where_: String,
    pub evidence: String,
    /// How the parameters were obtained.
    pub method: String,
    /// Ranking key (larger = more important).
    pub importance: f64,
    /// Other readings that explain the data about as well (effects, description, BIC
    /// difference), from the level-response check of the tone effects.
    pub alternatives: Vec<(Vec<&'static str>, String, f64)>,
}

/// Image metrics of a comparison.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct FitMetrics {
    pub rmse: f64,
    pub fqi: Option<f64>,
    pub hist_corr: f64,
}

/// Everything the fit produced.
pub struct Fitted {
    pub effects: Vec<FittedEffect>,
    pub config: FaultConfig,
    pub before: FitMetrics,
    pub after: FitMetrics,
    /// RMSE of the full model including its noise (for transparency; pixel noise cannot agree).
    pub rmse_after_with_noise: f64,
    /// Deterministic model output per pair (8-bit DN planes) for residual maps.
    pub model_planes: Vec<Vec<Plane>>,
    pub notes: Vec<String>,
    pub dropped: Vec<String>,
    /// Every forward-model test (all candidates, all rounds).
    pub selection_tests: Vec<Evidence>,
    /// Noise model measured on the residual of the fitted model.
    pub noise: NoiseModel,
}

fn cand(name: &'static str, label: &str, params: Params, fit: &[&'static str]) -> Candidate {
    Candidate { name, label: label.to_string(), params, fit: fit.to_vec(), well_ceiling: None }
}

/// Every applicable deterministic candidate, initialised from the signatures.
pub fn candidates(pairs: &[Pair], loc: &Located) -> Vec<Candidate> {
    let mut out = Vec::new();
    let init = |name: &str| -> Option<Params> {
        match loc.signature(name) {
            Some(s) => params_from_signature(s),
            None => registry::find(name).map(|r| Params::defaults(r.info)),
        }
    };
    let channels = pairs[0].channels();
    let any_sat = loc.masks.iter().any(|m| m.sat.any());
    let set = |p: &mut Params, n: &str, v: f64| {
        if let Some((_, spec)) = p.info().param(n) {
            let _ = p.set(n, v.clamp(spec.min, spec.max));
        }
    };
    if let Some(mut p) = init("vignetting") {
        let s = p.get("strength");
        set(&mut p, "strength", if s > 0.01 { s } else { 0.05 });
        out.push(cand("vignetting", "vignetting", p, &["strength", "field_deg"]));
    }
    if let Some(mut p) = init("dark_current") {
        let m = p.get("mean_dn");
        set(&mut p, "mean_dn", if m > 0.2 { m } else { 1.0 });
        set(&mut p, "hot_pixel_rate", 0.0);
        out.push(cand("dark_current", "dark_current", p, &["mean_dn"]));
    }
    if let Some(p) = init("gain_offset") {
        out.push(cand("gain_offset", "gain_offset", p, &["gain", "offset_dn"]));
    }
    if let Some(mut p) = init("gamma") {
        let g = p.get("gamma");
        set(&mut p, "gamma", g.clamp(0.75, 1.3));
        out.push(cand("gamma", "gamma", p, &["gamma"]));
    }
    if let Some(mut p) = init("stray_light") {
        let photo = &loc.photo;
        let (lo, hi, at) = photo.additive_range();
        set(&mut p, "amplitude_dn", (hi - lo).clamp(1.0, 60.0));
        // Direction of the brightest point from the centre (angle counter-clockwise, y up).
        let ang = (-at.1).atan2(at.0).to_degrees().rem_euclid(360.0);
        set(&mut p, "angle_deg", ang);
        set(&mut p, "distance", 1.3);
        set(&mut p, "width", 0.8);
        out.push(cand("stray_light", "stray_light", p, &["amplitude_dn", "angle_deg", "distance", "width"]));
    }
    if let Some(mut p) = init("veiling_glare") {
        // Initial values from the residual floor against the glare the sim's scene predicts.
        let (f, core, slope) = match super::glare::paired_init(pairs) {
            Some((f, core, slope, _)) => (f, core, slope),
            None => (0.01, 20.0, 1.5),
        };
        set(&mut p, "fraction", f.clamp(2e-3, 0.3));
        set(&mut p, "core_px", core);
        set(&mut p, "slope", slope);
        out.push(cand("veiling_glare", "veiling_glare", p, &["fraction", "core_px"]));
    }
    if let Some(mut p) = init("defocus") {
        let s = p.get("sigma_px");
        set(&mut p, "sigma_px", s.clamp(0.3, 6.0));
        out.push(cand("defocus", "defocus", p, &["sigma_px"]));
    }
    if let Some(mut p) = init("motion_blur") {
        let l = p.get("length_px");
        set(&mut p, "length_px", l.clamp(1.0, 30.0));
        out.push(cand("motion_blur", "motion_blur", p, &["length_px", "angle_deg"]));
    }
    if channels == 3
        && let Some(p) = init("channel_shift")
    {
        out.push(cand("channel_shift", "channel_shift", p, &["dx_r", "dy_r", "dx_b", "dy_b"]));
    }
    if any_sat {
        if let Some(mut p) = init("smear") {
            let s = p.get("strength");
            set(&mut p, "strength", if s > 1e-4 { s } else { 0.002 });
            for dir in ["vertical", "horizontal"] {
                let mut q = p;
                let _ = q.set_choice("direction", dir);
                out.push(cand("smear", &format!("smear ({dir})"), q, &["strength"]));
            }
        }
        if let Some(mut p) = init("blooming") {
            let f = p.get("full_well_fraction");
            set(&mut p, "full_well_fraction", f.clamp(0.5, 0.995));
            // Read on small saturated cores, the plateau is the well itself: it is held there and
            // only the spread is fitted, so that a halo the clipped sim cannot feed (over-exposed
            // sources spill more than the sim's excess over the well) is not bought by lowering
            // the well. From interiors the plateau only starts the fit (as before).
            // The spread read on the halo's shape (smear's column offsets removed first;
            // saturation::halo_shape_spread) is held: fitted freely, the spread trades against
            // smear and against the over-exposure (a wider kernel buys a larger saturated
            // footprint, which takes smear's column signal and starves smear). Only the well is
            // then fitted.
            let shape = loc.signature("blooming").and_then(|g| g.param(super::saturation::SHAPE_SPREAD_PARAM));
            if let Some(v) = shape {
                set(&mut p, "spread_px", v);
            }
            let fit: &[&'static str] = match (well_basis(loc), shape) {
                (WellBasis::Cores, _) => &["spread_px"],
                (_, Some(_)) => &["full_well_fraction"],
                _ => &["full_well_fraction", "spread_px"],
            };
            let mut c = cand("blooming", "blooming", p, fit);
            c.well_ceiling = well_ceiling(loc);
            out.push(c);
        }
        if let Some(mut p) = init("lens_flare") {
            let i = p.get("intensity");
            set(&mut p, "intensity", i.clamp(0.005, 0.2));
            let _ = p.set_choice("tint", "white");
            out.push(cand("lens_flare", "lens_flare", p, &["intensity", "size"]));
        }
    }
    out
}

/// The largest full well (fraction of FS) the selection reports as overflow when the blooming
/// signature saw the saturated plateau below the top code (its `plateau` choice): one ADC step
/// under full scale. None (the default floor of `select::above_floor`) otherwise.
pub fn well_ceiling(loc: &Located) -> Option<f64> {
    let below = loc
        .signature("blooming")
        .is_some_and(|s| s.choices.iter().any(|(n, v)| n == "plateau" && v == "below_top_code"));
    below.then(|| 1.0 - loc.noise.quant.max(1.0 / 257.0) / FS as f64)
}

/// Where the blooming signature read the saturated plateau (its `well_basis` choice).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WellBasis {
    /// Saturated regions deeper than the blur: the plateau initialises a free fit of the well.
    Interior,
    /// Only the cores of small saturated regions (pixels whose four neighbours are saturated),
    /// no measurable blur: the well is held at their plateau.
    Cores,
    /// No saturated plateau at all: the data do not constrain the well.
    Untestable,
}

pub fn well_basis(loc: &Located) -> WellBasis {
    let basis = loc
        .signature("blooming")
        .and_then(|s| s.choices.iter().find(|(n, _)| n == "well_basis").map(|(_, v)| v.as_str()));
    match basis {
        Some("interior") => WellBasis::Interior,
        Some("cores") => WellBasis::Cores,
        _ => WellBasis::Untestable,
    }
}

/// Pick up to `n` pairs evenly.
fn choose_frames(pairs: &[Pair], n: usize) -> Vec<usize> {
    if pairs.len() <= n {
        return (0..pairs.len()).collect();
    }
    let step = pairs.len() as f64 / n as f64;
    (0..n).map(|i| ((i as f64 + 0.5) * step) as usize).collect()
}

/// Apply the full fitted chain (with noise) to a sim frame.
fn apply_config(cfg: &FaultConfig, f: &Frame) -> Result<Frame, DiagnoseError> {
    let mut chain = crate::faults::chain::Chain::from_config(cfg)?;
    let mut out = f.clone();
    let mut rep = crate::faults::chain::FrameReport::default();
    chain.apply(&mut out, &mut rep)?;
    Ok(out)
}

pub fn metrics_of(a: &Frame, b: &Frame) -> FitMetrics {
    let ga = crate::metrics::Grey::from_frame(a);
    let gb = crate::metrics::Grey::from_frame(b);
    FitMetrics {
        rmse: crate::metrics::rmse(&ga, &gb).unwrap_or(f64::NAN),
        fqi: crate::metrics::fqi(&ga, &gb).ok().flatten(),
        hist_corr: crate::metrics::hist_correlation(&ga, &gb),
    }
}

/// The `rmse` of [`metrics_of`] alone (without the ORB features of the FQI).
fn rmse_of(a: &Frame, b: &Frame) -> f64 {
    crate::metrics::rmse(&crate::metrics::Grey::from_frame(a), &crate::metrics::Grey::from_frame(b)).unwrap_or(f64::NAN)
}

pub fn mean_metrics(v: &[FitMetrics]) -> FitMetrics {
    let n = v.len().max(1) as f64;
    let fq: Vec<f64> = v.iter().filter_map(|m| m.fqi).collect();
    FitMetrics {
        rmse: v.iter().map(|m| m.rmse).sum::<f64>() / n,
        fqi: if fq.is_empty() { None } else { Some(fq.iter().sum::<f64>() / fq.len() as f64) },
        hist_corr: v.iter().map(|m| m.hist_corr).sum::<f64>() / n,
    }
}

pub fn canonical_of(p: &Params) -> Vec<(String, serde_json::Value)> {
    p.iter()
        .filter(|(s, _)| s.canonical)
        .map(|(s, v)| {
            let val = match s.kind {
                ParamKind::Choice(c) => serde_json::Value::from(c.get(v as usize).copied().unwrap_or("")),
                ParamKind::Bool => serde_json::Value::from(v != 0.0),
                ParamKind::Int => serde_json::Value::from(v as i64),
                ParamKind::Float => serde_json::Value::from(round_sig(v, 5)),
            };
            (s.name.to_string(), val)
        })
        .collect()
}

/// Round to `n` significant digits (report readability).
pub fn round_sig(v: f64, n: i32) -> f64 {
    if v == 0.0 || !v.is_finite() {
        return v;
    }
    let m = 10f64.powi(n - 1 - v.abs().log10().floor() as i32);
    (v * m).round() / m
}

/// The stochastic tests on the residual of the deterministic model.
struct Stochastic {
    noise: NoiseModel,
    hot_sig: Signature,
    prnu: Signature,
    row: Signature,
    jpeg: Signature,
    gaussian: Signature,
    shot: Signature,
}

fn stochastic_tests(
    pairs: &[Pair],
    loc: &Located,
    model: &[Vec<Plane>],
    z_det: f64,
    jpeg_present: bool,
) -> (Stochastic, Vec<Vec<bool>>) {
    // These statistics have a null distribution that does not depend on any model (covariances
    // between independent measurements, recurrence), so they need less margin than the
    // forward-model tests.
    let z = (z_det - 1.0).max(3.0);
    let quiet: Vec<Vec<bool>> = model.iter().map(|m| noise::quiet_mask(m, QUIET_LAPLACIAN)).collect();
    let (mut hot_sig, hot, _) = fixed::hot_pixels(pairs, &loc.masks, &quiet, model, &loc.noise);
    hot_sig.detected = hot_sig.z > z && hot_sig.size > 0.0;
    // JPEG blocks and ringing mimic fixed patterns and row structure: those tests are not
    // trusted under compression.
    let under_jpeg = |s: &mut Signature| {
        if jpeg_present {
            s.detected = false;
            s.evidence.push_str(" (not tested under JPEG compression: block artefacts mimic it)");
        }
    };
    under_jpeg(&mut hot_sig);
    // The pixels over-exposed sources' spill reaches are no noise samples (`Located::spill`).
    let hot: Vec<Vec<bool>> = match loc.spill.as_ref() {
        Some(sp) => hot.iter().zip(sp).map(|(h, s)| h.iter().zip(s).map(|(&a, &b)| a || b).collect()).collect(),
        None => hot,
    };
    let noise1 = noise::estimate(pairs, &loc.masks, model, loc.quant, 0.0, Some(&hot));
    let (mut prnu, prnu_c) = fixed::prnu(pairs, &loc.masks, &quiet, model, &noise1, &hot);
    prnu.detected = prnu.z > z;
    under_jpeg(&mut prnu);
    let noise2 = if prnu.detected && prnu_c > 0.0 {
        noise::estimate(pairs, &loc.masks, model, loc.quant, prnu_c, Some(&hot))
    } else {
        noise1
    };
    let resid: Vec<Vec<Plane>> =
        pairs.iter().zip(model).map(|(p, m)| p.real.iter().zip(m).map(|(r, q)| r.sub(q)).collect()).collect();
    let mut row = fixed::row_noise(pairs, &loc.masks, &quiet, &resid, model, &noise2);
    row.detected = row.z > z;
    under_jpeg(&mut row);
    // Row offsets are part of the per-pixel variance: measure the camera noise without them.
    let noise2 = if row.detected {
        let offsets = fixed::row_offsets(pairs, &loc.masks, &resid, &hot);
        let c = if prnu.detected { prnu_c } else { 0.0 };
        noise::estimate_with_rows(pairs, &loc.masks, model, loc.quant, c, Some(&hot), Some(&offsets))
    } else {
        noise2
    };
    let (gaussian, shot) = locate::camera_noise(&noise2, z);
    (Stochastic { noise: noise2, hot_sig, prnu, row, jpeg: Signature::new("jpeg"), gaussian, shot }, hot)
}

/// Camera noise through the fitted model: the noise measured on the real images is the noise
/// after every effect that follows it in the signal chain (a gain or tone curve scales it, JPEG
/// removes part of it, dark current adds its own shot noise). Read-noise sigma and conversion gain
/// are therefore found by moment matching through the library's forward models: a few sim frames
/// go through the fitted chain with trial noise parameters, the same noise measurement is made
/// on the result against the noise-free model, and the parameters are scaled until it matches the
/// measurement on the real images. Returns (sigma_dn, gain_e_per_dn if the slope is identified).
fn noise_through_model(
    pairs: &[Pair],
    loc: &Located,
    model: &[Vec<Plane>],
    measured: &NoiseModel,
    chain: &[Params],
    seed: u64,
) -> Result<(f64, Option<f64>), DiagnoseError> {
    let idx = choose_frames(pairs, 3);
    let (a_t, b_t) = (measured.a.max(1e-3), measured.b);
    let use_b = measured.slope_identified && b_t > 1e-4;
    let (mut a, mut b) = (a_t, b_t);
    for it in 0..5 {
        let mut ps: Vec<Params> = chain.to_vec();
        if use_b && let Some(r) = registry::find("shot_noise") {
            let mut p = Params::defaults(r.info);
            let _ = p.set("gain_e_per_dn", (1.0 / b).clamp(0.01, 1e6));
            ps.push(p);
        }
        if let Some(r) = registry::find("gaussian_noise") {
            let mut p = Params::defaults(r.info);
            let _ = p.set("sigma_dn", a.sqrt().clamp(0.0, 64.0));
            ps.push(p);
        }
        let cfg = FaultConfig::from_effects(seed ^ (it as u64 + 17), ps);
        let mut sims = Vec::new();
        let mut masks = Vec::new();
        let mut bases = Vec::new();
        for &k in &idx {
            let p = &pairs[k];
            let mut f = p.sim_frame.clone();
            f.seq = k as u64;
            let out = apply_config(&cfg, &f)?;
            sims.push(Pair {
                name: p.name.clone(),
                sim_frame: p.sim_frame.clone(),
                real: super::img::planes_of(&out),
                real_frame: out,
                sim: p.sim.clone(),
            });
            masks.push(loc.masks[k].clone());
            bases.push(model[k].clone());
        }
        let m = noise::estimate(&sims, &masks, &bases, loc.quant, 0.0, None);
        a *= (a_t / m.a.max(1e-3)).clamp(0.25, 4.0);
        if use_b && m.b > 1e-6 {
            b *= (b_t / m.b).clamp(0.25, 4.0);
        }
    }
    Ok((a.sqrt(), if use_b { Some(1.0 / b) } else { None }))
}

/// The selection again from `start` (a JPEG step's dither re-read from the current noise model),
/// with the earlier pass `prev`'s best z per candidate as the prior; the earlier pass's trials
/// stay in the report's table before the new ones.
fn reselect(
    ctx: &FitCtx,
    cands: &[Candidate],
    z: f64,
    start: &[select::Step],
    prev: select::Selection,
) -> Result<select::Selection, DiagnoseError> {
    let start: Vec<select::Step> = start
        .iter()
        .map(|s| {
            let mut c = s.boxed_clone();
            if c.dither.is_some() {
                c.dither = Some(ctx.loss.noise().clone());
            }
            c
        })
        .collect();
    let mut sel = select::select(ctx, cands, z, start, Some(&prev.best_z), None)?;
    let mut tests = prev.tests;
    tests.append(&mut sel.tests);
    sel.tests = tests;
    Ok(sel)
}

/// Whether the selection holds a fitted `gamma` step away from identity (a tone curve the noise
/// passed through).
fn tone_selected(steps: &[select::Step]) -> bool {
    steps.iter().filter(|s| !s.fixed && s.name == "gamma").any(|s| {
        let g = s.params.get("gamma");
        g.is_finite() && (g - 1.0).abs() > 1e-6
    })
}

fn det_names_of(sel: &select::Selection) -> Vec<&'static str> {
    sel.steps.iter().filter(|s| !s.fixed).map(|s| s.name).collect()
}

/// Select, fit and measure.
pub fn fit(pairs: &[Pair], loc: &mut Located, opts: &Options) -> Result<Fitted, DiagnoseError> {
    let mut notes = Vec::new();
    let seed = opts.seed;
    let z = opts.z_threshold;
    // ---- deterministic: forward-model selection on the fit frames -------------------------------
    let mut cands = candidates(pairs, loc);
    // A motion streak is a blur with a direction: without anisotropy of the measured PSF beyond
    // its noise (an isotropic blur of any form, e.g. a pillbox or an Airy pattern that the
    // library's Gaussian does not fit exactly), motion_blur is not a candidate.
    if let Some(k) = &loc.psf
        && k.aniso_z < z
        && cands.iter().any(|c| c.name == "motion_blur")
    {
        cands.retain(|c| c.name != "motion_blur");
        notes.push(format!(
            "motion_blur not tried: the measured PSF has no direction beyond its noise (anisotropy (λ1 − λ2)/2 = {:.3} px², z = {:.1} < {z})",
            k.aniso.0.hypot(k.aniso.1),
            k.aniso_z
        ));
    }
    // A blurred scene changes levels near edges and bright sources by the PSF (its tails carry
    // light from saturated regions into their surroundings and take contrast from small bright
    // features). The effects whose forward models can mimic that must show their own signature
    // beyond the blur: blooming the plateau deficit of saturated interiors deeper than the blur
    // (or the over-exposure halo), smear the column/row profile of saturated counts, gain_offset
    // a gain on flat pixels (an offset alone is the dark level's candidate).
    // The blur must be one the data establish: an isotropic spread of the edges (defocus), or a
    // directional one whose measured PSF shows the direction (motion_blur still a candidate
    // after the test above). A directional edge spread without a direction in the PSF is the
    // statistic that test has just ruled out as a motion streak (fiducials spilling over a full
    // well, a colour channel misregistered, move edges one way without any blur): it must not
    // stand in for a blur here either, or a smear column or a blooming halo it cannot explain is
    // never tried and a wide effect (a veiling glare) takes its signal.
    let sig_z = |name: &str| loc.signature(name).map(|g| g.z).unwrap_or(0.0);
    let directional = sig_z("motion_blur") >= z && cands.iter().any(|c| c.name == "motion_blur");
    if sig_z("defocus") >= z || directional {
        for (name, own) in
            [("blooming", sig_z("blooming")), ("smear", sig_z("smear")), ("gain_offset", sig_z("gain_offset"))]
        {
            if own < z && cands.iter().any(|c| c.name == name) {
                cands.retain(|c| c.name != name);
                notes.push(format!(
                    "{name} not tried: the scene is blurred and {name}'s own signature is not beyond its noise (z = {own:.1} < {z}); the blur explains the level changes near edges and bright sources"
                ));
            }
        }
    }
    // Enough pairs for about 300k values per loss evaluation (at least 2, at most fit_frames).
    let per_pair = pairs[0].w() * pairs[0].h() * pairs[0].channels();
    let n_fit = (300_000 / per_pair.max(1)).clamp(2, opts.fit_frames.max(2)).min(opts.fit_frames.max(1));
    let fidx = choose_frames(pairs, n_fit);
    let mut inputs = Vec::new();
    for &k in &fidx {
        inputs.push(select::work_planes(&pairs[k].sim_frame, k as u64)?);
    }
    let values: usize = fidx.iter().map(|&k| pairs[k].w() * pairs[k].h() * pairs[k].channels()).sum();
    // About 300k values per loss evaluation at most (statistically ample for a handful of
    // parameters; the forward models still run on the whole frames).
    let row_step = values.div_ceil(300_000).max(1);
    // JPEG is found by its own test (the quantisation lattice does not depend on any model);
    // when present it is part of every model, so that its softening and blocking are not taken
    // for blur or anything else.
    super::progress("fit: frames chosen");
    let mut jp = jpeg::test(pairs);
    super::progress("fit: jpeg test");
    jp.detected = jp.z > (z - 1.0).max(8.0) && jp.param("quality").unwrap_or(100.0) < 98.0;
    let mut start = Vec::new();
    if jp.detected
        && let Some(p) = params_from_signature(&jp)
    {
        let mut step = select::Step::fixed("jpeg", p)?;
        step.dither = Some(loc.noise.clone());
        start.push(step);
    }
    // Over-exposed sources (blooming signature): the region their spilled charge fills and lights
    // (`saturation::spill_skip`: the ring around the sim's saturated regions and the real plateau
    // grown from them with its halo) is left out of the loss, with the hot pixels.
    let bloom_sig = loc.signature("blooming");
    let halo_px = bloom_sig.and_then(|s| s.param("halo_px"));
    // (`Located::spill`: the hot pixels with the spill, computed once in `locate`.)
    let skip: Vec<Vec<bool>> = fidx.iter().map(|&k| loc.spill.as_ref().unwrap_or(&loc.hot)[k].clone()).collect();
    if let Some(r) = halo_px {
        let reach = bloom_sig.and_then(|s| s.param(super::saturation::SPILL_REACH_PARAM)).unwrap_or(r);
        notes.push(format!(
            "over-exposed sources: pixels within {r:.0} px of saturated regions, and the real plateau grown from them with {reach:.0} px around it, are left out of the forward-model fit (their charge spilled from sources the clipped sim does not hold)"
        ));
    }
    // With a dithered JPEG step (three JPEG round trips per frame and evaluation, most of the cost
    // of a fit) the fit reads whole bands of rows instead of every `row_step`-th row, and the JPEG
    // runs on those bands only: rows 1..=14 of every `s`-th 16-row band (a whole number of MCU
    // rows, so the block grid is the image's; rows 0 and 15 take chroma from the neighbouring
    // band in libjpeg's fancy upsampling and are not read), about as many rows as before.
    let h = pairs[fidx[0]].h();
    let bands: Option<Vec<usize>> = (!start.is_empty() && row_step > 1 && h >= 2 * select::BAND).then(|| {
        let s = ((row_step * (select::BAND - 2)) as f64 / select::BAND as f64).round().max(1.0) as usize;
        let nb = h / select::BAND;
        (s / 2..nb).step_by(s).map(|j| j * select::BAND).collect()
    });
    let mut ctx = FitCtx {
        inputs,
        seqs: fidx.iter().map(|&k| k as u64).collect(),
        loss: LossData::new(
            fidx.iter().map(|&k| &pairs[k]).collect(),
            skip.iter().map(|v| v.as_slice()).collect(),
            fidx.iter()
                .map(|&k| {
                    let m = &loc.masks[k];
                    (0..m.sat.len()).map(|i| m.dist_edge.get(i) > 2.0 && m.dist_sat.get(i) > 4.0).collect()
                })
                .collect(),
            loc.noise.clone(),
            row_step,
        ),
        seed,
        bands: bands.clone(),
        evals: std::sync::atomic::AtomicUsize::new(0),
    };
    ctx.loss.set_well_sd(loc.signature("blooming").and_then(|s| s.param(super::saturation::PLATEAU_SD_PARAM)));
    if let Some(b) = &bands {
        let mut rows = vec![false; h];
        for &y0 in b {
            rows[y0 + 1..y0 + select::BAND - 1].iter_mut().for_each(|r| *r = true);
        }
        ctx.loss.rows = Some(rows);
    }
    // The proper likelihood trusts the noise model's level dependence, which a tone curve the
    // library's power law does not match bends (see `LossData::set_exact`): once a tone curve
    // is chosen, the pass stops and the selection is repeated in the Gaussian form, from the
    // fixed steps (the effects chosen in the proper form are candidates again, not a start).
    let start_fixed: Vec<select::Step> = start.iter().filter(|s| s.fixed).map(select::Step::boxed_clone).collect();
    let mut sel = select::select(&ctx, &cands, z, start, None, Some(tone_selected))?;
    let selection_done = |ctx: &FitCtx| {
        super::progress(&format!(
            "selection done ({} evaluations)",
            ctx.evals.load(std::sync::atomic::Ordering::Relaxed)
        ))
    };
    selection_done(&ctx);
    if tone_selected(&sel.steps) {
        ctx.loss.set_exact(false);
        notes.push(
            "a tone curve (gamma) was selected: the selection is repeated with the Gaussian form of the likelihood (without the density's normalisation and the exact Poisson–Gaussian probability at few electrons), which does not trust the noise model's level dependence under a curve the power law does not match".into(),
        );
        super::progress("tone curve selected: selection repeated");
        sel = reselect(&ctx, &cands, z, &start_fixed, sel)?;
        selection_done(&ctx);
    }
    // The noise model was measured on real - sim; with the fitted effects taken out it may
    // differ (structure such as smear rows inflates it). If it changed, select again with it,
    // starting from the model found.
    let mut model_planes = Vec::with_capacity(pairs.len());
    for (k, p) in pairs.iter().enumerate() {
        model_planes.push(select::apply_steps(&mut sel.steps, &p.sim_frame, k as u64, seed)?);
    }
    super::progress("fit: model planes");
    let renoise =
        noise::estimate(pairs, &loc.masks, &model_planes, loc.quant, 0.0, Some(loc.spill.as_ref().unwrap_or(&loc.hot)));
    let change = [2.0, 30.0, 100.0, 200.0]
        .iter()
        .map(|&l| (renoise.var(l) / ctx.loss.noise().var(l) - 1.0).abs())
        .fold(0.0f64, f64::max);
    if change > 0.15 {
        notes.push(format!(
            "noise model re-measured on the residual of the fitted model (variance changed by up to {:.0} %): selection repeated with it",
            100.0 * change
        ));
        ctx.loss.set_noise(renoise);
        super::progress("noise model changed: selection repeated");
        let found: Vec<select::Step> = sel.steps.iter().map(select::Step::boxed_clone).collect();
        sel = reselect(&ctx, &cands, z, &found, sel)?;
        selection_done(&ctx);
        model_planes.clear();
        for (k, p) in pairs.iter().enumerate() {
            model_planes.push(select::apply_steps(&mut sel.steps, &p.sim_frame, k as u64, seed)?);
        }
    }
    // The tone effects read by the shape of the level response (a tone curve fixes 0 and full
    // scale, a gain and offset does not).
    super::progress("fit: before tone check");
    let before_tone: Vec<&str> = sel.steps.iter().map(|s| s.name).collect();
    select::tone_check(&ctx, &mut sel, z)?;
    if sel.steps.iter().map(|s| s.name).ne(before_tone.iter().copied()) {
        model_planes.clear();
        for (k, p) in pairs.iter().enumerate() {
            model_planes.push(select::apply_steps(&mut sel.steps, &p.sim_frame, k as u64, seed)?);
        }
    }
    // The fitted model must not fit the images worse than the sim did: while the RMSE of the
    // deterministic model against the real images is above that of the sim, the effect whose
    // removal lowers it most is dropped (a significant robust-loss drop can come from a few
    // pixels while every other pixel gets worse, e.g. a well lowered to feed a halo).
    // The sim's metrics per pair in parallel (also the report's "before"), RMSEs summed in pair order.
    let before: Vec<FitMetrics> = pairs.par_iter().map(|p| metrics_of(&p.sim_frame, &p.real_frame)).collect();
    let rmse_before = before.iter().map(|m| m.rmse).sum::<f64>() / pairs.len().max(1) as f64;
    let rmse_model = |planes: &[Vec<Plane>]| -> f64 {
        let each: Vec<f64> = pairs
            .par_iter()
            .zip(planes)
            .map(|(p, m)| rmse_of(&frame_from_planes(m, &p.real_frame), &p.real_frame))
            .collect();
        each.iter().sum::<f64>() / pairs.len().max(1) as f64
    };
    let mut rmse_after = rmse_model(&model_planes);
    super::progress("fit: rmse");
    if std::env::var_os("FAULTCAM_DIAG_DEBUG").is_some() {
        for s in sel.steps.iter().filter(|s| !s.fixed) {
            eprintln!(
                "RMSE check: {} {:?} (RMSE {rmse_after:.3} against the sim's {rmse_before:.3} DN)",
                s.label, s.params
            );
        }
    }
    while rmse_after > rmse_before && sel.steps.iter().any(|s| !s.fixed) {
        let mut best: Option<(usize, f64, Vec<Vec<Plane>>)> = None;
        for j in (0..sel.steps.len()).filter(|&j| !sel.steps[j].fixed) {
            let mut trial: Vec<select::Step> =
                sel.steps.iter().enumerate().filter(|(i, _)| *i != j).map(|(_, s)| s.boxed_clone()).collect();
            let mut planes = Vec::with_capacity(pairs.len());
            for (k, p) in pairs.iter().enumerate() {
                planes.push(select::apply_steps(&mut trial, &p.sim_frame, k as u64, seed)?);
            }
            let r = rmse_model(&planes);
            if best.as_ref().is_none_or(|b| r < b.1) {
                best = Some((j, r, planes));
            }
        }
        let Some((j, r, planes)) = best else { break };
        let s = sel.steps.remove(j);
        sel.evidence.remove(j);
        sel.notes.push(format!(
            "{}: dropped because the fitted model fitted the images worse than the sim (RMSE {rmse_after:.3} against {rmse_before:.3} DN; without it {r:.3} DN)",
            s.label
        ));
        model_planes = planes;
        rmse_after = r;
    }
    notes.push(format!(
        "forward-model selection: {} candidates, {} loss evaluations on {} of {} pairs{}",
        cands.len(),
        ctx.evals.load(std::sync::atomic::Ordering::Relaxed),
        fidx.len(),
        pairs.len(),
        match &bands {
            Some(b) => format!(
                " (rows 1-{} of {} bands of {} rows, the JPEG run on those bands only)",
                select::BAND - 2,
                b.len(),
                select::BAND
            ),
            None if row_step > 1 => format!(" (one row in {row_step})"),
            None => String::new(),
        }
    ));
    let dropped = sel.notes.clone();
    // ---- stochastic tests on the residual of the deterministic model ----------------------------
    super::progress("tone check and RMSE check done; stochastic tests");
    let (mut st, _hot) = stochastic_tests(pairs, loc, &model_planes, z, jp.detected);
    super::progress("fit: stochastic tests done");
    st.jpeg = jp;
    // ---- findings --------------------------------------------------------------------------------
    let mut results: Vec<FittedEffect> = Vec::new();
    let nv = sel.loss_final.n.max(1) as f64;
    let mut dark_params: Option<Params> = None;
    for (j, s) in sel.steps.iter().enumerate() {
        if s.fixed {
            continue;
        }
        let ev = &sel.evidence[j];
        let sig = loc.signature(s.name);
        let mut params = s.params;
        if s.name == "dark_current" {
            // The library model adds the dark signal's shot noise at the camera's gain.
            let gain = if st.shot.detected { st.shot.param("gain_e_per_dn").unwrap_or(1.0) } else { 1e3 };
            let _ = params.set("gain_e_per_dn", gain.clamp(0.01, 1000.0));
            if st.hot_sig.detected {
                let _ = params.set("hot_pixel_rate", st.hot_sig.size.clamp(0.0, 0.05));
                let excess = st.hot_sig.param("offset_dn").unwrap_or(60.0);
                let m = params.get("mean_dn").max(0.1);
                let _ = params.set("hot_factor", ((excess + m) / m).clamp(1.0, 1000.0));
            }
            dark_params = Some(params);
        }
        let mut stderr = sig.map(|g| g.stderr.clone()).unwrap_or_default();
        let tone = sel.tone.as_ref().filter(|t| t.effects.contains(&s.name));
        let mut sig_evidence = sig.map(|g| g.evidence.clone()).unwrap_or_default();
        if let Some(t) = tone {
            if s.fit.is_empty() {
                // Parameters from the level response: the photometric signature's are not these.
                stderr.clear();
                sig_evidence = t.evidence.clone();
            } else {
                sig_evidence = format!("{sig_evidence}; {}", t.evidence);
            }
        }
        if let Some(lp) = &sel.level_position
            && (select::SPATIAL_ALIASES.contains(&s.name) || select::TONE_EFFECTS.contains(&s.name))
        {
            sig_evidence = format!("{sig_evidence}; {lp}");
        }
        let mut canonical = canonical_of(&params);
        // A reported value other than the fitted one: null for a parameter the data cannot
        // test, or a direct reading.
        let mut report_as = |name: &str, value: serde_json::Value| {
            canonical.iter_mut().filter(|(n, _)| n == name).for_each(|(_, v)| *v = value.clone())
        };
        if s.name == "blooming" {
            // The spread is a decay length, read on the halo's shape (saturation::halo_shape_spread)
            // and held in the forward fit. Over-exposed sources: the forward fit cannot match the
            // halo's size (the clipped sim lacks the charge), so without a shape reading there is
            // no number (null).
            let over = if halo_px.is_some() { " (the over-exposed halo's size is not fitted)" } else { "" };
            match sig.and_then(|g| g.param(super::saturation::SHAPE_SPREAD_PARAM)) {
                Some(v) => {
                    report_as("spread_px", serde_json::json!(v));
                    sig_evidence = format!("{sig_evidence}; spread_px read on the halo's shape: {v:.3} px{over}");
                }
                None if halo_px.is_some() => report_as("spread_px", serde_json::Value::Null),
                None => {}
            }
        }
        if s.name == "blooming" && well_basis(loc) == WellBasis::Untestable {
            // No saturated plateau: the fitted well only shapes the halo (it trades against the
            // unknown excess of clipped sources), so no number is reported for it.
            report_as("full_well_fraction", serde_json::Value::Null);
            sig_evidence = format!(
                "{sig_evidence}; full_well_fraction untestable (null): no saturated plateau in the data, so the well is not constrained (fitted.toml keeps the value that shapes the halo, {:.3})",
                params.get("full_well_fraction")
            );
        }
        if s.name == "defocus"
            && !sel.steps.iter().any(|t| t.name == "motion_blur")
            && let Some(v) = sig.and_then(|g| g.param(super::edges::EDGE_SIGMA_PARAM))
        {
            // EFFECTS.md's sigma_px is the PSF's equivalent Gaussian: read where the PSF's core
            // shapes the edge spread (edges::EDGE_SIGMA_PARAM). The forward fit over the whole
            // image also weighs the far tails around bright sources, where a non-Gaussian PSF
            // (Airy rings, a pillbox's flat top) differs from a Gaussian of the same core, and
            // runs high for those forms.
            report_as("sigma_px", serde_json::Value::from(round_sig(v, 5)));
            sig_evidence = format!(
                "{sig_evidence}; sigma_px read on the edge spread: {v:.3} px (fitted.toml keeps the forward fit's {:.3}, the Gaussian that best reproduces the whole image)",
                params.get("sigma_px")
            );
        }
        if s.name == "lens_flare"
            && let Some(n) = sig.and_then(|g| g.param(super::flare::COUNT_PARAM))
        {
            // The number of ghost plateaus found on the source–centre line (the forward fit keeps
            // the library's layout of 3).
            report_as("ghosts", serde_json::Value::from(n));
        }
        if s.name == "lens_flare"
            && let Some(pl) = sig.and_then(|g| g.param(super::flare::PLATEAU_PARAM))
            && pl > 0.0
        {
            // EFFECTS.md's intensity is the ghosts' mean plateau: read on the ghost cores by the
            // signature. The forward fit scales the library's ghost layout (its places and sizes
            // are not the lens's), so its value is diluted where those ghosts miss the real ones.
            report_as("intensity", serde_json::Value::from(round_sig(pl, 5)));
            sig_evidence = format!(
                "{sig_evidence}; intensity read on the ghosts' plateau, {pl:.4} of FS (fitted.toml keeps the forward fit's {:.4}, which scales the library's ghost layout)",
                params.get("intensity")
            );
        }
        results.push(FittedEffect {
            name: s.name,
            params: Some(params),
            canonical,
            stderr,
            loss_before: ev.loss_without,
            loss_after: ev.loss_with,
            z: ev.z,
            where_: sig.map(|g| g.where_.clone()).unwrap_or_default(),
            evidence: format!(
                "{}; forward model: removing it raises the loss by {:.4} per value (ΔL = {:.1}, design effect {:.2}, z = {:.1} on {} parameter(s))",
                sig_evidence,
                ev.delta / nv,
                ev.delta,
                ev.design,
                ev.z,
                ev.k
            ),
            method: if s.fit.is_empty() {
                "level response (real against the model level, censored bin means) fitted by the shape it reads as; a tone curve's gamma is its least-squares power law".into()
            } else {
                "joint forward-model fit on the library effect (Huber loss on noise-standardised residuals)".into()
            },
            importance: ev.delta / ev.design,
            alternatives: {
                let mut a = tone.map(|t| t.alternatives.clone()).unwrap_or_default();
                if select::SPATIAL_ALIASES.contains(&s.name) {
                    a.extend(sel.spatial_alternatives.iter().cloned());
                }
                a
            },
        });
    }
    // Lens flare found by its plateau signature while the library's ghost layout (its places and
    // sizes are not the lens's) did not pay for itself in the forward selection: reported from
    // the plateau reading (intensity = mean plateau / FS, ghosts = plateaus found). The fitted
    // config gets the library effect with that intensity and count; it is not part of the
    // deterministic model (its ghosts would land elsewhere), so the RMSE is that of the rest.
    if !results.iter().any(|r| r.name == "lens_flare")
        && let Some(sig) = loc.signature("lens_flare").filter(|s| s.detected)
        && let Some(pl) = sig.param(super::flare::PLATEAU_PARAM)
        && let Some(mut p) = registry::find("lens_flare").map(|r| Params::defaults(r.info))
    {
        let n = sig.param(super::flare::COUNT_PARAM).unwrap_or(3.0);
        let _ = p.set("intensity", pl.clamp(0.0, 1.0));
        let _ = p.set("ghosts", n.clamp(1.0, 16.0));
        let _ = p.set_choice("tint", "white");
        let mut canonical = canonical_of(&p);
        canonical.iter_mut().filter(|(k, _)| k == "intensity").for_each(|(_, v)| *v = round_sig(pl, 5).into());
        results.push(FittedEffect {
            name: "lens_flare",
            canonical,
            params: Some(p),
            stderr: sig.stderr.clone(),
            loss_before: f64::NAN,
            loss_after: f64::NAN,
            z: sig.z,
            where_: sig.where_.clone(),
            evidence: format!(
                "{}; not in the forward model: the library's ghost layout does not reproduce the lens's ghost places, so it is reported from the plateau reading",
                sig.evidence
            ),
            method: "matched search for ghost plateaus on the source–centre line (core against ring, noise-model weights, frames combined at the same line parameter)".into(),
            importance: 1e-6 * sig.z.min(1e4),
            alternatives: Vec::new(),
        });
    }
    let flare_reported = results.iter().any(|r| r.name == "lens_flare");
    // Hot pixels are part of the dark current when there is one.
    let mut hot_sig = st.hot_sig.clone();
    if hot_sig.detected && dark_params.is_some() {
        hot_sig.detected = false;
        hot_sig.evidence.push_str(" (reported as dark_current.hot_pixel_rate)");
        if let Some(r) = results.iter_mut().find(|r| r.name == "dark_current") {
            r.evidence.push_str(&format!("; hot pixels: {}", st.hot_sig.evidence));
        }
    }
    // The dark signal's shot noise is already in the slope of the noise curve (levels include the
    // dark signal), so the read noise takes nothing off for it.
    let dark_var = 0.0;
    let fmt_like = &pairs[0].real_frame;
    // The deterministic chain (with the dark current's own noise and the JPEG) the camera noise
    // goes through.
    let mut chain: Vec<Params> =
        results.iter().filter(|r| det_names_of(&sel).contains(&r.name)).filter_map(|r| r.params).collect();
    if st.jpeg.detected
        && let Some(p) = params_from_signature(&st.jpeg)
    {
        chain.push(p);
    }
    // Only effects after the noise in the signal chain change what is measured (a gain or tone
    // curve scales it, JPEG removes part of it); without them the direct estimate is the answer.
    let after_noise = chain.iter().any(|p| matches!(p.info().name, "gain_offset" | "gamma" | "jpeg"));
    let through_model = if after_noise && (st.gaussian.detected || st.shot.detected) {
        super::progress("camera noise through the fitted chain");
        Some(noise_through_model(pairs, loc, &model_planes, &st.noise, &chain, seed)?)
    } else {
        None
    };
    for sig in [&st.gaussian, &st.shot, &st.prnu, &st.row, &hot_sig, &st.jpeg] {
        if !sig.detected {
            continue;
        }
        let (mut params, mut method, lb, la) = match super::moments::calibrate(sig, &st.noise, dark_var, fmt_like, seed)
        {
            Some(x) => (Some(x.0), x.1, x.2, x.3),
            None => (None, "signature estimate (effect not in the library)".to_string(), f64::NAN, f64::NAN),
        };
        if let (Some((sigma, gain)), Some(p)) = (through_model, params.as_mut()) {
            let note = "moment matching through the library's forward models: sim through the fitted chain with trial noise, variance against level measured as on the real images";
            match sig.effect {
                "gaussian_noise" => {
                    let _ = p.set("sigma_dn", sigma.clamp(0.0, 64.0));
                    method = note.into();
                }
                "shot_noise" => {
                    if let Some(g) = gain {
                        let _ = p.set("gain_e_per_dn", g.clamp(0.01, 1e6));
                        method = note.into();
                    }
                }
                _ => {}
            }
        }
        results.push(FittedEffect {
            name: sig.effect,
            canonical: params.as_ref().map(canonical_of).unwrap_or_default(),
            params,
            stderr: sig.stderr.clone(),
            loss_before: lb,
            loss_after: la,
            z: sig.z,
            where_: sig.where_.clone(),
            evidence: sig.evidence.clone(),
            method,
            importance: 1e-6 * sig.z.min(1e4),
            alternatives: Vec::new(),
        });
    }
    // Deterministic findings by evidence, then the stochastic ones by significance.
    results.sort_by(|a, b| b.importance.total_cmp(&a.importance));
    // The signature table shows the final decision (taken by the forward-model selection).
    for sig in loc.signatures.iter_mut() {
        sig.detected = sel.steps.iter().any(|s| !s.fixed && s.name == sig.effect)
            || (sig.effect == "lens_flare" && flare_reported);
    }
    for s in [&st.gaussian, &st.shot, &st.prnu, &st.row, &hot_sig, &st.jpeg] {
        loc.signatures.push(s.clone());
    }
    // ---- the fitted config and before/after metrics ---------------------------------------------
    // Deterministic steps first, in the fit's physical order, so that each keeps its generator
    // index (lens_flare's ghost pattern depends on it).
    let det_names: Vec<&str> = sel.steps.iter().filter(|s| !s.fixed).map(|s| s.name).collect();
    let mut cfg_params: Vec<Params> =
        det_names.iter().filter_map(|n| results.iter().find(|r| r.name == *n).and_then(|r| r.params)).collect();
    cfg_params.extend(results.iter().filter(|r| !det_names.contains(&r.name)).filter_map(|r| r.params));
    let mut config = FaultConfig::from_effects(seed, cfg_params);
    config.origin = "fitted by faultcam diagnose".into();
    let mut after = Vec::new();
    let mut rmse_noise = Vec::new();
    // Pairs in parallel (each through its own chain), collected in pair order.
    let per_pair: Vec<Result<(FitMetrics, f64), DiagnoseError>> = pairs
        .par_iter()
        .enumerate()
        .map(|(k, p)| {
            let mut sim = p.sim_frame.clone();
            sim.seq = k as u64;
            let det = frame_from_planes(&model_planes[k], &p.real_frame);
            let full = apply_config(&config, &sim)?;
            let mut m = metrics_of(&full, &p.real_frame);
            let with_noise = m.rmse;
            m.rmse = rmse_of(&det, &p.real_frame);
            Ok((m, with_noise))
        })
        .collect();
    for r in per_pair {
        let (m, with_noise) = r?;
        rmse_noise.push(with_noise);
        after.push(m);
    }
    notes.extend(sel.notes.iter().filter(|n| !n.contains("backward check")).cloned());
    super::progress("fit: metrics");
    Ok(Fitted {
        effects: results,
        config,
        before: mean_metrics(&before),
        after: mean_metrics(&after),
        rmse_after_with_noise: rmse_noise.iter().sum::<f64>() / rmse_noise.len().max(1) as f64,
        model_planes,
        notes,
        dropped,
        selection_tests: sel.tests,
        noise: st.noise,
    })
}
