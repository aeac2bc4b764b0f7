//! Forward-model selection of the deterministic effects.
//!
//! The sim frames are pushed through the library's effects (`faults::create`, `Effect::apply`) in
//! physical order, and the output is compared with the real frames by a robust likelihood:
//! Huber (δ = 3) on the residual standardised by the noise model where real is inside (0, FS),
//! plus the density's normalisation ln σ (so every term is a negative log-probability and a model
//! cannot gain by predicting more noise), the exact Poisson–Gaussian probability of the rounded
//! value at up to [`PG_MAX_ELECTRONS`] photo-electrons (8-bit data), the interval-censored
//! likelihood where real is clipped. The fit works on 16-bit copies
//! of the sim (one Mono16 frame per channel), so that the library's rounding happens at 1/257 DN
//! and the loss is smooth in every parameter; `channel_shift`, which needs the three planes of a
//! colour frame together, runs on an Rgb8 frame assembled from them.
//!
//! **Selection** (forward stepwise, then backward):
//! 1. every applicable candidate effect (initialised from its signature estimate) is added in
//!    turn to the current model and its parameters fitted; the loss drop ΔL is its evidence;
//! 2. the evidence is scaled by the *design effect* D of the candidate model's residuals (the
//!    mean squared sum of standardised residuals over 16x16 blocks; 1 for white noise that the
//!    noise model describes, larger when residuals are correlated or the noise is underestimated)
//!    — a quasi-likelihood correction that keeps the test honest when the residual is not white;
//! 3. a candidate is significant when `2ΔL/D`, a chi-square with k degrees of freedom (k fitted
//!    parameters) under "absent", reaches the z threshold, and when it pays its parameters by the
//!    Bayesian information criterion (`2ΔL/D > k ln n`);
//! 4. the most important significant candidate (largest `ΔL/D`) joins the model, all parameters
//!    are refined jointly, and the round repeats;
//! 5. finally each selected effect must still be significant when dropped from the full model
//!    (the others fixed); the weakest that is not is removed and the rest refitted.

use super::common::NoiseModel;
use super::img::{FS, Pair, Plane, planes_of};
use super::{DiagnoseError, dither, levelmap, stats, tone};
use crate::faults::{self, Effect, EffectCtx, ParamKind, Params, Scale, Stage, registry};
use crate::frame::{Frame, FrameData, PixelFormat};
use rayon::prelude::*;
use std::f64::consts::LN_2;

/// Effects fitted by pixel loss, in physical order.
pub const DETERMINISTIC: &[&str] = &[
    "lens_flare",
    "veiling_glare",
    "stray_light",
    "vignetting",
    "defocus",
    "motion_blur",
    "channel_shift",
    "dark_current",
    "blooming",
    "smear",
    "gain_offset",
    "gamma",
];

/// A candidate for the model: an effect with initial parameters and the parameters to fit.
#[derive(Debug, Clone)]
pub struct Candidate {
    pub name: &'static str,
    /// Label in the report (e.g. "smear (vertical)").
    pub label: String,
    pub params: Params,
    /// Names of the parameters fitted.
    pub fit: Vec<&'static str>,
    /// blooming only: the largest `full_well_fraction` that counts as charge overflow when the
    /// data show the saturated plateau below the top code (None: [`above_floor`]'s default).
    pub well_ceiling: Option<f64>,
}

/// One step of the deterministic model.
pub struct Step {
    pub name: &'static str,
    pub label: String,
    effect: Option<Box<dyn Effect>>,
    pub params: Params,
    key: (Stage, u16),
    /// Indices (into the effect's parameter list) of the fitted parameters.
    pub fit: Vec<usize>,
    /// Part of the model from the start (e.g. JPEG found by its own test): never tested or
    /// dropped by the selection.
    pub fixed: bool,
    /// JPEG of a noisy image is not the JPEG of its expectation (the coefficient rounding is
    /// dithered by the noise): with a noise model the step returns the mean of several JPEG round
    /// trips of the image plus noise, which approximates the expected output.
    pub dither: Option<NoiseModel>,
    dither_draws: DitherDraws,
    /// See [`Candidate::well_ceiling`].
    pub well_ceiling: Option<f64>,
}

/// Noise draws averaged by a dithered JPEG step.
const DITHER_DRAWS: u64 = 3;

/// Standard normal draws of the dithered JPEG step, per (seed, frame seq, step index, values):
/// the same for every evaluation of a frame, so they are drawn once (for the first few frames;
/// further frames draw without keeping them). Shared by the clones of a step.
#[derive(Clone, Default)]
pub struct DitherDraws(std::sync::Arc<std::sync::Mutex<Vec<KeptDraws>>>, std::sync::Arc<std::sync::Mutex<SdTable>>);

/// The dither sigma of each 16-bit level for one noise model (a, b, c, quant as bits).
type SdTable = Option<([u64; 4], std::sync::Arc<Vec<f64>>)>;

/// Key of one kept set of dither draws: (seed, frame seq, step index, values).
type DrawKey = (u64, u64, usize, usize);

/// One kept set of draws with its key.
type KeptDraws = (DrawKey, std::sync::Arc<Vec<f64>>);

/// One forward-selection trial: its evidence, its fitted steps and its evaluation count.
type TrialResult = Result<(Evidence, Vec<Step>, usize), DiagnoseError>;

impl DitherDraws {
    const KEEP: usize = 8;

    fn draw(seed: u64, seq: u64, index: usize, n: usize) -> Vec<f64> {
        let mut out = Vec::with_capacity(DITHER_DRAWS as usize * n);
        for k in 0..DITHER_DRAWS {
            let mut rng = crate::rng::Rng::new(crate::rng::mix_seed(&[seed, seq, index as u64, k]));
            out.extend((0..n).map(|_| rng.normal()));
        }
        out
    }

    /// Dither sigma (DN) of each 16-bit level: `sqrt(1.5 var(v / 257))`.
    fn sd_table(&self, nm: &NoiseModel) -> std::sync::Arc<Vec<f64>> {
        let key = [nm.a.to_bits(), nm.b.to_bits(), nm.c.to_bits(), nm.quant.to_bits()];
        if let Ok(t) = self.1.lock()
            && let Some((k, v)) = t.as_ref()
            && *k == key
        {
            return v.clone();
        }
        let v =
            std::sync::Arc::new((0..65536u32).map(|v| (1.5 * nm.var(v as f64 / 257.0)).sqrt()).collect::<Vec<f64>>());
        if let Ok(mut t) = self.1.lock() {
            *t = Some((key, v.clone()));
        }
        v
    }

    fn get(&self, seed: u64, seq: u64, index: usize, n: usize) -> std::sync::Arc<Vec<f64>> {
        let key = (seed, seq, index, n);
        if let Ok(c) = self.0.lock()
            && let Some((_, d)) = c.iter().find(|(k, _)| *k == key)
        {
            return d.clone();
        }
        let d = std::sync::Arc::new(Self::draw(seed, seq, index, n));
        if let Ok(mut c) = self.0.lock()
            && c.len() < Self::KEEP
            && !c.iter().any(|(k, _)| *k == key)
        {
            c.push((key, d.clone()));
        }
        d
    }
}

impl Step {
    /// A step that is part of the model from the start and never tested (no fitted parameters).
    pub fn fixed(name: &'static str, params: Params) -> Result<Step, DiagnoseError> {
        let c = Candidate { name, label: name.to_string(), params, fit: Vec::new(), well_ceiling: None };
        let mut s = Step::new(&c)?;
        s.fixed = true;
        Ok(s)
    }

    pub fn new(c: &Candidate) -> Result<Step, DiagnoseError> {
        let reg = registry::find(c.name).ok_or_else(|| {
            DiagnoseError::Fault(faults::FaultError::UnknownEffect { name: c.name.to_string(), known: String::new() })
        })?;
        let fit = c.fit.iter().filter_map(|n| reg.info.param(n).map(|(i, _)| i)).collect();
        // dark_current is fitted as its mean only (its shot noise and hot pixels are stochastic).
        let effect = if c.name == "dark_current" { None } else { Some((reg.create)()) };
        Ok(Step {
            name: c.name,
            label: c.label.clone(),
            effect,
            params: c.params,
            key: (reg.info.stage, reg.info.order),
            fit,
            fixed: false,
            dither: None,
            dither_draws: DitherDraws::default(),
            well_ceiling: c.well_ceiling,
        })
    }

    pub fn boxed_clone(&self) -> Step {
        Step {
            name: self.name,
            label: self.label.clone(),
            effect: self.effect.as_ref().and_then(|_| faults::create(self.name).ok()),
            params: self.params,
            key: self.key,
            fit: self.fit.clone(),
            fixed: self.fixed,
            dither: self.dither.clone(),
            dither_draws: self.dither_draws.clone(),
            well_ceiling: self.well_ceiling,
        }
    }

    /// Apply to the planes of one image (Mono16 frames, one per channel). `bands`: start rows of
    /// the [`BAND`]-row bands a dithered JPEG step runs on (None: the whole frame); rows outside
    /// them are left as they came in, and the loss must not read them (see [`LossData::rows`]).
    fn apply(
        &mut self,
        img: &mut [Frame],
        seed: u64,
        seq: u64,
        index: usize,
        bands: Option<&[usize]>,
    ) -> Result<(), DiagnoseError> {
        if self.name == "dark_current" {
            let off = self.params.get("mean_dn") * 257.0;
            for f in img.iter_mut() {
                if let Some(d) = f.as_u16_mut() {
                    for v in d.iter_mut() {
                        *v = (*v as f64 + off).round().min(65535.0) as u16;
                    }
                }
            }
            return Ok(());
        }
        if self.name == "jpeg"
            && let Some(nm) = self.dither.clone()
        {
            if let Some(b) = bands.filter(|b| !b.is_empty()) {
                let mut sub: Vec<Frame> = Vec::with_capacity(img.len());
                for f in img.iter() {
                    sub.push(stack_bands(f, b)?);
                }
                self.dithered_jpeg(&mut sub, &nm, seed, seq, index)?;
                for (f, s) in img.iter_mut().zip(&sub) {
                    unstack_bands(s, f, b);
                }
                return Ok(());
            }
            return self.dithered_jpeg(img, &nm, seed, seq, index);
        }
        let Some(e) = self.effect.as_mut() else { return Ok(()) };
        if self.name == "channel_shift" || (self.name == "jpeg" && img.len() == 3) {
            if img.len() == 3 {
                let mut rgb = assemble_rgb8(img)?;
                rgb.seq = seq;
                let mut ctx = EffectCtx::new(seed, seq, index);
                e.apply(&mut rgb, &self.params, &mut ctx)?;
                split_rgb8(&rgb, img);
            }
            return Ok(());
        }
        for f in img.iter_mut() {
            let mut ctx = EffectCtx::new(seed, seq, index);
            e.apply(f, &self.params, &mut ctx)?;
        }
        Ok(())
    }

    /// The mean of [`DITHER_DRAWS`] JPEG round trips of `img` plus noise of the model `nm`.
    fn dithered_jpeg(
        &mut self,
        img: &mut [Frame],
        nm: &NoiseModel,
        seed: u64,
        seq: u64,
        index: usize,
    ) -> Result<(), DiagnoseError> {
        let n_values: usize = img.iter().map(|f| f.as_u16().map(|d| d.len()).unwrap_or(0)).sum();
        // The dither sigma of each 16-bit level (cached per noise model), and the normal draws
        // (the same for every evaluation of this frame: cached).
        let sd_table = self.dither_draws.sd_table(nm);
        let sd_of: &[f64; 65536] = sd_table.as_slice().try_into().map_err(|_| {
            DiagnoseError::Fault(faults::FaultError::Failed { effect: "jpeg", reason: "dither table size".into() })
        })?;
        // Keyed by the frame, not by the step's place in the chain: a candidate inserted before
        // the JPEG must not change its noise draws (a different draw changes the loss by
        // chance, by as much as a weak effect, for every candidate alike).
        let draws = self.dither_draws.get(seed, seq, 0, n_values);
        let mut acc: Vec<Vec<u32>> = img.iter().map(|f| vec![0; f.as_u16().map(|d| d.len()).unwrap_or(0)]).collect();
        let mut plain = Step { dither: None, effect: faults::create("jpeg").ok(), ..self.boxed_clone() };
        let mut noisy: Vec<Frame> = img.to_vec();
        for k in 0..DITHER_DRAWS {
            let dk = &draws[k as usize * n_values..(k as usize + 1) * n_values];
            let mut at = 0;
            for (f, o) in noisy.iter_mut().zip(img.iter()) {
                if let (Some(d), Some(src)) = (f.as_u16_mut(), o.as_u16()) {
                    dither::add_noise(d, src, &dk[at..], sd_of);
                    at += d.len();
                }
            }
            plain.apply(&mut noisy, seed, seq, index, None)?;
            for (a, f) in acc.iter_mut().zip(&noisy) {
                if let Some(d) = f.as_u16() {
                    for (x, &v) in a.iter_mut().zip(d) {
                        *x += v as u32;
                    }
                }
            }
        }
        // round(x / D) of a non-negative integer sum x, exactly (ties away from zero).
        let dd = DITHER_DRAWS as u32;
        for (f, a) in img.iter_mut().zip(&acc) {
            if let Some(d) = f.as_u16_mut() {
                for (v, &x) in d.iter_mut().zip(a) {
                    *v = ((2 * x + dd) / (2 * dd)).min(65535) as u16;
                }
            }
        }
        Ok(())
    }
}

/// Height of the row bands a dithered JPEG step can be restricted to (a whole number of JPEG
/// MCU rows for 4:2:0 and 4:4:4, so the stacked bands keep the image's block grid).
pub const BAND: usize = 16;

/// The rows of `bands` (each [`BAND`] rows from its start) of a Mono16 frame, stacked.
fn stack_bands(f: &Frame, bands: &[usize]) -> Result<Frame, DiagnoseError> {
    let w = f.width as usize;
    let src = f.as_u16().unwrap_or(&[]);
    let mut data = Vec::with_capacity(w * BAND * bands.len());
    for &b in bands {
        data.extend_from_slice(&src[b * w..(b + BAND) * w]);
    }
    let mut out = Frame::from_data(f.width, (BAND * bands.len()) as u32, w, PixelFormat::Mono16, FrameData::U16(data))
        .map_err(|e| DiagnoseError::Fault(faults::FaultError::Failed { effect: "jpeg", reason: e.to_string() }))?;
    out.seq = f.seq;
    Ok(out)
}

/// Write stacked bands back into their rows.
fn unstack_bands(sub: &Frame, f: &mut Frame, bands: &[usize]) {
    let w = f.width as usize;
    let (Some(s), Some(d)) = (sub.as_u16(), f.as_u16_mut()) else { return };
    for (j, &b) in bands.iter().enumerate() {
        d[b * w..(b + BAND) * w].copy_from_slice(&s[j * BAND * w..(j + 1) * BAND * w]);
    }
}

/// Rgb8 frame from three Mono16 planes (rounded to 8 bits).
fn assemble_rgb8(planes: &[Frame]) -> Result<Frame, DiagnoseError> {
    let (w, h) = (planes[0].width, planes[0].height);
    let n = w as usize * h as usize;
    let mut data = vec![0u8; n * 3];
    if let [r, g, b, ..] = planes
        && let (Some(r), Some(g), Some(b)) = (r.as_u16(), g.as_u16(), b.as_u16())
    {
        dither::interleave_rgb8(&mut data, &r[..n], &g[..n], &b[..n]);
    }
    Frame::from_data(w, h, 3 * w as usize, PixelFormat::Rgb8, FrameData::U8(data)).map_err(|e| {
        DiagnoseError::Fault(faults::FaultError::Failed { effect: "channel_shift", reason: e.to_string() })
    })
}

fn split_rgb8(rgb: &Frame, planes: &mut [Frame]) {
    let Some(src) = rgb.as_u8() else { return };
    if let [r, g, b, ..] = planes
        && let (Some(r), Some(g), Some(b)) = (r.as_u16_mut(), g.as_u16_mut(), b.as_u16_mut())
    {
        dither::split_rgb8(src, r, g, b);
    }
}

/// The planes of a frame as Mono16 frames (8-bit DN × 257).
pub fn work_planes(frame: &Frame, seq: u64) -> Result<Vec<Frame>, DiagnoseError> {
    let planes = planes_of(frame);
    let mut out = Vec::with_capacity(planes.len());
    for p in &planes {
        let data: Vec<u16> = p.data.iter().map(|&v| (v * 257.0).round().clamp(0.0, 65535.0) as u16).collect();
        let mut f = Frame::from_data(p.w as u32, p.h as u32, p.w, PixelFormat::Mono16, FrameData::U16(data))
            .map_err(|e| DiagnoseError::Fault(faults::FaultError::Failed { effect: "fit", reason: e.to_string() }))?;
        f.seq = seq;
        out.push(f);
    }
    Ok(out)
}

/// Planes (8-bit DN) of Mono16 work frames.
pub fn planes_of_work(img: &[Frame]) -> Vec<Plane> {
    img.iter().map(|f| planes_of(f).remove(0)).collect()
}

/// Result of a loss evaluation.
#[derive(Debug, Clone, Copy, Default)]
pub struct LossEval {
    pub total: f64,
    /// Number of values in the loss.
    pub n: usize,
    /// Design effect of the standardised residuals over 16x16 blocks.
    pub design: f64,
}

/// The real data the loss compares with.
pub struct LossData<'a> {
    pub pairs: Vec<&'a Pair>,
    pub skip: Vec<&'a [bool]>,
    /// Pixels away from edges and saturation (global tone effects must show there).
    pub interior: Vec<Vec<bool>>,
    noise: NoiseModel,
    /// Row subsampling of the loss (1 = every row).
    pub row_step: usize,
    /// Rows the loss reads instead of every `row_step`-th (per row of the frames; set with the
    /// JPEG bands of [`FitCtx::bands`], whose rows are the only ones the model completes).
    pub rows: Option<Vec<bool>>,
    tables: LossTables,
    /// The proper likelihood (see [`Self::set_exact`]).
    exact: bool,
    /// Finer-than-8-bit data: how many real values sit at each level (for the tables' rows).
    real_counts: Vec<u32>,
    /// Scatter (DN) of a full photosite's value, measured on the saturated plateau (see
    /// [`Self::set_well_sd`]); None: the read noise and ADC step.
    well_sd: Option<f64>,
}

const DBLOCK: usize = 16;

/// Loss terms tabulated over the values a model plane can take. Model planes come from Mono16
/// work frames, so a model value is one of 65536 levels `v·255/65535` (8-bit DN): the noise
/// sigma, the censored losses of clipped real values and their generalised residuals, and the
/// interval losses of small integer real values, are exact functions of `v` (and of the real
/// value), computed once per noise model instead of once per pixel and evaluation. A value that is
/// not such a level (or outside a table) is computed directly, with the same formulas.
struct LossTables {
    /// The model value of each level, as the work planes hold it (to check a lookup).
    level: Vec<f32>,
    sd: Vec<f64>,
    /// Real clipped at 0: (loss, generalised residual).
    low: Vec<(f64, f64)>,
    /// Real clipped at full scale: (loss, generalised residual).
    high: Vec<(f64, f64)>,
    /// 8-bit real data only: interval loss for real value r (integer DN) and the model levels
    /// `first[r] .. first[r] + rows[r].len()`; empty when the data are not 8-bit.
    interval_first: Vec<usize>,
    interval_rows: Vec<Vec<f64>>,
    /// Finer-than-8-bit real data (10-, 12-, 16-bit): the same interval loss tabulated for the
    /// real values the data hold (keyed by the value's level index, `u32::MAX`: not tabulated)
    /// near a clipping bound, most frequent values first within [`QROW_BUDGET`] entries; the
    /// rest are computed per pixel. The entries are [`interval`] at the very arguments the
    /// per-pixel call would use, so a table hit changes no bit of the loss.
    qrow_of: Vec<u32>,
    qrow_first: Vec<usize>,
    qrows: Vec<Vec<f64>>,
    /// ln sd of each level (the normalisation of the Gaussian density; see [`eval_plane`]).
    ln_sd: Vec<f64>,
    /// 8-bit real data with shot noise: for the levels of at most [`PG_MAX_ELECTRONS`]
    /// photo-electrons (levels `0..pg_rows.len()`), the loss of real value `r` for `r` in
    /// `pg_first[v] .. pg_first[v] + pg_rows[v].len()` from the exact Poisson–Gaussian probability
    /// of the rounded, clipped value ([`pg_row`]); index 0 of a row starting at 0 is the clipped
    /// value (real <= 0).
    pg_first: Vec<usize>,
    pg_rows: Vec<Vec<f64>>,
}

/// Photo-electrons up to which the loss takes the exact Poisson–Gaussian probability of a
/// rounded value instead of its Gaussian approximation. At a few electrons the Poisson skew
/// moves the level that a Gaussian likelihood prefers by a fraction of a DN (at 12 electrons,
/// about 0.1 DN up); summed over the millions of dark pixels of a large frame, that bias
/// outweighs a real effect (a 12 % cos⁴ vignetting on a 1920x1200 frame of dark sky lost to a
/// plain gain and offset). Above this the skew (1/√λ ≤ 0.13) is left to the Gaussian form.
const PG_MAX_ELECTRONS: f64 = 60.0;

/// Read-noise sds beyond which a photo-electron count's share of P(x < t) is taken as all or
/// nothing in [`pg_row`] (Phi(-9) = 1.1e-19).
const PG_TAIL_Z: f64 = 9.0;

/// Entries of the interval-loss table of finer-than-8-bit data (f64; 32 MB), and the number of
/// distinct real values considered for it.
const QROW_BUDGET: usize = 4 << 20;
const QROW_MAX_VALUES: usize = 8192;

/// Losses `-ln P(real = r) + ln(q/√(2π))` (r >= 1) and `-ln P(real <= 0)` (r = 0) of 8-bit real
/// values `r_lo..=r_hi` for the noise-free level `m` (DN): photo-electrons k ~ Poisson(m / b),
/// each worth `b` DN, plus Gaussian read noise of variance `a + c m²` (the noise model's),
/// rounded to integers and clipped at 0.
fn pg_row(noise: &NoiseModel, m: f64, r_lo: usize, r_hi: usize) -> Vec<f64> {
    let b = noise.b;
    let x = m;
    let lam = (x / b).max(0.0);
    let s = (noise.a + noise.c * x * x).max(0.02).sqrt();
    let k_hi = (lam + 10.0 * lam.sqrt() + 12.0).ceil() as usize;
    let k_lo = (lam - 10.0 * lam.sqrt() - 2.0).floor().max(0.0) as usize;
    // P(x < t) for x = k b + n, at the boundaries t = r ± ½.
    let ln_pk = |k: usize| {
        if lam <= 0.0 {
            if k == 0 { 0.0 } else { f64::NEG_INFINITY }
        } else {
            k as f64 * lam.ln() - lam - crate::rng::ln_gamma(k as f64 + 1.0)
        }
    };
    let pk: Vec<f64> = (k_lo..=k_hi).map(|k| ln_pk(k).exp()).collect();
    // P(x < t) = sum_k p_k Phi((t - k b) / s). Only the electron counts within PG_TAIL_Z read-noise
    // sds of t take a fraction of their probability; those below take all of it (Phi = 1 to
    // within 1e-19), those above none. `below[i]` = p_0 + .. + p_(i-1) (counts from k_lo). The
    // cost per boundary is then about 2 PG_TAIL_Z s / b terms instead of every count: with a
    // read noise much smaller than one electron's step (or a first noise estimate near a = 0),
    // a handful instead of hundreds.
    let mut below_k = Vec::with_capacity(pk.len() + 1);
    below_k.push(0.0f64);
    for &p in &pk {
        below_k.push(below_k.last().copied().unwrap_or(0.0) + p);
    }
    let cdf = |t: f64| {
        let first = (((t - PG_TAIL_Z * s) / b).ceil().max(k_lo as f64) as usize).min(k_hi + 1) - k_lo;
        let last = (((t + PG_TAIL_Z * s) / b).floor().min(k_hi as f64).max(k_lo as f64 - 1.0) + 1.0) as usize - k_lo;
        below_k[first]
            + (first..last.max(first)).map(|i| pk[i] * stats::norm_cdf((t - (k_lo + i) as f64 * b) / s)).sum::<f64>()
    };
    let shift = (1.0 / (2.0 * std::f64::consts::PI).sqrt()).ln();
    let mut below = cdf(r_lo as f64 - 0.5);
    (r_lo..=r_hi)
        .map(|r| {
            let above = cdf(r as f64 + 0.5);
            let l = if r == 0 { -above.max(1e-300).ln() } else { -(above - below).max(1e-300).ln() + shift };
            below = above;
            l
        })
        .collect()
}

const LEVELS: usize = 65536;
const LEVEL_SCALE: f32 = 255.0f32 / 65535.0f32;

impl LossTables {
    fn new(noise: &NoiseModel) -> LossTables {
        let t0 = std::time::Instant::now();
        let q = noise.quant;
        let fs = FS as f64;
        let level: Vec<f32> = (0..LEVELS).map(|v| v as f32 * LEVEL_SCALE).collect();
        let sd: Vec<f64> = level.iter().map(|&m| noise.sd(m as f64)).collect();
        let mut low = Vec::with_capacity(LEVELS);
        let mut high = Vec::with_capacity(LEVELS);
        for (v, &mf) in level.iter().enumerate() {
            let (m, s) = (mf as f64, sd[v]);
            low.push(low_term(m, s, q));
            high.push(high_term(m, s, q, fs));
        }
        let mut interval_first = Vec::new();
        let mut interval_rows = Vec::new();
        if q == 1.0 {
            // Real values r = 1..254 for which the interval form can apply (r < 3 sd or
            // r > FS - 3 sd), for model levels within 3 sd of r (|z| <= 3).
            let sd_max = sd.iter().fold(0.0f64, |a, &b| a.max(b));
            for r in 0..=255usize {
                let rv = r as f64;
                let Some((lo, hi)) = interval_window(rv, sd_max) else {
                    interval_first.push(0);
                    interval_rows.push(Vec::new());
                    continue;
                };
                interval_first.push(lo);
                interval_rows.push((lo..=hi).map(|v| interval(rv, level[v] as f64, sd[v], q)).collect());
            }
        }
        let ln_sd: Vec<f64> = sd.iter().map(|s| s.ln()).collect();
        let (mut pg_first, mut pg_rows) = (Vec::new(), Vec::new());
        if q == 1.0 && noise.b > 1e-3 {
            let n = level.iter().take_while(|&&m| (m as f64) / noise.b <= PG_MAX_ELECTRONS).count();
            let rows: Vec<(usize, Vec<f64>)> = (0..n)
                .into_par_iter()
                .map(|v| {
                    let m = level[v] as f64;
                    let r_lo = (m - 4.0 * sd[v]).floor().max(0.0) as usize;
                    let r_hi = ((m + 5.0 * sd[v]).ceil() as usize).min(254);
                    (r_lo, pg_row(noise, m, r_lo, r_hi))
                })
                .collect();
            for (f, r) in rows {
                pg_first.push(f);
                pg_rows.push(r);
            }
        }
        if std::env::var_os("FAULTCAM_DIAG_DEBUG").is_some() {
            let cells: usize = pg_rows.iter().map(|r| r.len()).sum();
            eprintln!(
                "loss tables: a {:.4} b {:.4} c {:.6} quant {} pg levels {} cells {} in {:.2} s",
                noise.a,
                noise.b,
                noise.c,
                q,
                pg_rows.len(),
                cells,
                t0.elapsed().as_secs_f64()
            );
        }
        LossTables {
            level,
            sd,
            low,
            high,
            interval_first,
            interval_rows,
            qrow_of: Vec::new(),
            qrow_first: Vec::new(),
            qrows: Vec::new(),
            ln_sd,
            pg_first,
            pg_rows,
        }
    }

    /// Tabulate the interval loss for finer-than-8-bit real data (see `qrows`): `counts[v]` is
    /// the number of real values at level `v` in the fitted planes.
    fn add_real_rows(&mut self, noise: &NoiseModel, counts: &[u32]) {
        let q = noise.quant;
        if q >= 1.0 || counts.len() != LEVELS {
            return;
        }
        let sd_max = self.sd.iter().fold(0.0f64, |a, &b| a.max(b));
        let (level, sd) = (&self.level, &self.sd);
        // The condition under which `term` takes the interval form.
        let used = |rv: f64, v: usize| {
            let (m, s) = (level[v] as f64, sd[v]);
            interval_form(rv, (rv - m) / s, s)
        };
        let mut cand: Vec<usize> =
            (0..LEVELS).filter(|&v| counts[v] > 0 && interval_window(level[v] as f64, sd_max).is_some()).collect();
        cand.sort_by(|&a, &b| counts[b].cmp(&counts[a]).then(a.cmp(&b)));
        cand.truncate(QROW_MAX_VALUES);
        let spans: Vec<Option<(usize, usize)>> = cand
            .par_iter()
            .map(|&r| {
                let rv = level[r] as f64;
                let (lo, hi) = interval_window(rv, sd_max)?;
                let first = (lo..=hi).find(|&v| used(rv, v))?;
                let last = (first..=hi).rev().find(|&v| used(rv, v))?;
                Some((first, last))
            })
            .collect();
        let mut take = Vec::new();
        let mut total = 0usize;
        for (&r, span) in cand.iter().zip(&spans) {
            if let Some((f, l)) = *span {
                if total + (l - f + 1) > QROW_BUDGET {
                    continue;
                }
                total += l - f + 1;
                take.push((r, f, l));
            }
        }
        let rows: Vec<Vec<f64>> = take
            .par_iter()
            .map(|&(r, f, l)| {
                let rv = level[r] as f64;
                (f..=l).map(|v| interval(rv, level[v] as f64, sd[v], q)).collect()
            })
            .collect();
        self.qrow_of = vec![u32::MAX; LEVELS];
        for (i, &(r, f, _)) in take.iter().enumerate() {
            self.qrow_of[r] = i as u32;
            self.qrow_first.push(f);
        }
        self.qrows = rows;
        if std::env::var_os("FAULTCAM_DIAG_DEBUG").is_some() {
            eprintln!("loss tables: {} real values near a bound tabulated ({} entries)", take.len(), total);
        }
    }

    /// Loss of real value `rv` for model value `mf` (a negative log-probability up to a constant)
    /// and its generalised residual (E[z | clipped] for clipped values, so that block sums are
    /// not biased by clipping at 0 in dark regions).
    #[inline]
    ///
    /// `exact`: the proper likelihood (the density's normalisation ln sd, the exact
    /// Poisson–Gaussian probability at a few photo-electrons); without it the Gaussian form on
    /// the scale of ½z² (no ln sd), the loss used where a tone curve is selected (see
    /// [`LossData::set_exact`]).
    fn term(&self, noise: &NoiseModel, rv: f64, mf: f32, exact: bool) -> (f64, f64) {
        let tab = self;
        let q = noise.quant;
        let fs = FS as f64;
        let m = mf as f64;
        // A level outside the tables: the same forms computed directly.
        let Some(v) = tab.index(mf) else {
            return direct_term(rv, m, noise.sd(m), q, exact);
        };
        let sd = tab.sd[v];
        if rv <= 0.0 {
            let (l, g) = tab.low[v];
            if exact { (tab.pg_at(0.0, v).map_or(l, |p| p.min(l + LN_2)), g) } else { (l, g) }
        } else if rv >= fs {
            tab.high[v]
        } else {
            let z = (rv - m) / sd;
            let ln_sd = tab.ln_sd[v];
            let gauss = if interval_form(rv, z, sd) {
                let l = tab.interval_at(rv, v).unwrap_or_else(|| interval(rv, m, sd, q));
                if exact { l } else { l - ln_sd }
            } else if exact {
                huber(z) + ln_sd
            } else {
                huber(z)
            };
            if !exact {
                return (gauss, z.clamp(-4.0, 4.0));
            }
            // At a few photo-electrons: the exact Poisson–Gaussian probability (robust
            // like the Huber form beyond it).
            let l = match tab.pg_at(rv, v) {
                Some(p) => p.min(huber(z) + ln_sd + LN_2),
                None => gauss,
            };
            (l, z.clamp(-4.0, 4.0))
        }
    }

    /// Exact Poisson–Gaussian loss of real value `r` (integer, 0 = clipped low) at level `v`.
    #[inline]
    fn pg_at(&self, r: f64, v: usize) -> Option<f64> {
        let row = self.pg_rows.get(v)?;
        let ri = r as usize;
        let first = self.pg_first[v];
        if ri < first || ri as f64 != r {
            return None;
        }
        row.get(ri - first).copied()
    }

    /// Level index of a model value, if it is a tabulated level.
    #[inline]
    fn index(&self, m: f32) -> Option<usize> {
        let v = Self::level_index(m)?;
        debug_assert_eq!(self.level[v].to_bits(), m.to_bits());
        Some(v)
    }

    /// Level index of a value that is exactly one of the levels (`v as f32 * (255/65535)`).
    #[inline]
    fn level_index(m: f32) -> Option<usize> {
        if m.is_nan() || m < 0.0 {
            return None;
        }
        // floor(x + ½) is the nearest level for m >= 0 (the check below catches any other value).
        let v = (m * 257.0 + 0.5) as usize;
        if v >= LEVELS {
            return None;
        }
        ((v as f32 * LEVEL_SCALE).to_bits() == m.to_bits()).then_some(v)
    }

    #[inline]
    fn interval_at(&self, r: f64, v: usize) -> Option<f64> {
        if !self.qrow_of.is_empty() {
            let row = *self.qrow_of.get(self.index(r as f32)?)?;
            let (row, first) = (self.qrows.get(row as usize)?, self.qrow_first[row as usize]);
            return if v < first { None } else { row.get(v - first).copied() };
        }
        let ri = r as usize;
        if ri as f64 != r {
            return None;
        }
        let row = self.interval_rows.get(ri)?;
        let first = self.interval_first[ri];
        if v < first {
            return None;
        }
        row.get(v - first).copied()
    }
}

/// Loss and generalised residual of a real value clipped at 0 for model `m` and sigma `sd`.
#[inline]
fn low_term(m: f64, sd: f64, q: f64) -> (f64, f64) {
    let t = (0.5 * q - m) / sd;
    (censored(m - 0.5 * q, sd), -(stats::norm_pdf(t) / stats::norm_cdf(t).max(1e-12)).max(-4.0))
}

/// Loss and generalised residual of a real value clipped at full scale.
#[inline]
fn high_term(m: f64, sd: f64, q: f64, fs: f64) -> (f64, f64) {
    let t = (m - (fs - 0.5 * q)) / sd;
    (censored(fs - 0.5 * q - m, sd), (stats::norm_pdf(t) / stats::norm_cdf(t).max(1e-12)).min(4.0))
}

impl<'a> LossData<'a> {
    pub fn new(
        pairs: Vec<&'a Pair>,
        skip: Vec<&'a [bool]>,
        interior: Vec<Vec<bool>>,
        noise: NoiseModel,
        row_step: usize,
    ) -> LossData<'a> {
        let mut real_counts = Vec::new();
        if noise.quant < 1.0 {
            real_counts = vec![0u32; LEVELS];
            for p in &pairs {
                for plane in &p.real {
                    for &r in &plane.data {
                        if let Some(v) = LossTables::level_index(r) {
                            real_counts[v] = real_counts[v].saturating_add(1);
                        }
                    }
                }
            }
        }
        let mut tables = LossTables::new(&noise);
        tables.add_real_rows(&noise, &real_counts);
        LossData { pairs, skip, interior, noise, row_step, rows: None, tables, exact: true, real_counts, well_sd: None }
    }

    /// The scatter (DN) of a full photosite's value as the real plateau shows it (robust, floored
    /// at the read noise and ADC step; `saturation::plateau_scatter`): a camera whose full
    /// photosites read the clip level plus read noise shows the read noise there, one that adds
    /// more (a well that varies from pixel to pixel, compression) shows that, and the loss at the
    /// well then trusts no more than the data show.
    pub fn set_well_sd(&mut self, sd: Option<f64>) {
        self.well_sd = sd.filter(|v| v.is_finite() && *v > 0.0);
    }

    pub fn noise(&self) -> &NoiseModel {
        &self.noise
    }

    /// Choose the loss's form: `true` (the default) the proper likelihood; `false` the Gaussian
    /// form without the density's normalisation ln sd and without the exact Poisson–Gaussian
    /// probability. The proper form trusts the noise model's level dependence; under a tone
    /// curve the library's power law does not reproduce (realcam's generalised sRGB curves with
    /// a linear toe), it buys a false `gain_offset` beside `gamma` (a gain and offset bends the
    /// power law towards the curve, and the variance predicted at each level moves with it), so
    /// the selection is repeated in the Gaussian form when it chose a tone curve.
    pub fn set_exact(&mut self, exact: bool) {
        self.exact = exact;
    }

    /// Replace the noise model (and its tables).
    pub fn set_noise(&mut self, noise: NoiseModel) {
        self.tables = LossTables::new(&noise);
        self.tables.add_real_rows(&noise, &self.real_counts);
        self.noise = noise;
    }
}

impl LossData<'_> {
    /// Robust negative log-likelihood of the real planes given model planes, optionally on the
    /// interior pixels only; `well` is the work-frame level
    /// (16-bit) of the model's full well when it holds clipped photosites below the top code
    /// ([`well_level`]): a model value at that level is a full photosite, whose value is the clip
    /// level and not a Poisson draw, so its loss takes the read noise and ADC step only (see
    /// `term_at_well`). The planes are evaluated in parallel (one task per pair and
    /// channel) and their sums combined in a fixed order, so the result does not depend on the
    /// number of threads.
    pub fn eval_on(&self, model: &[Vec<Plane>], interior_only: bool, well: Option<usize>) -> LossEval {
        use rayon::prelude::*;
        let jobs: Vec<(usize, usize)> =
            model.iter().enumerate().flat_map(|(k, mp)| (0..mp.len()).map(move |c| (k, c))).collect();
        let parts: Vec<(f64, usize, f64, usize)> =
            jobs.par_iter().map(|&(k, c)| self.eval_plane(k, c, &model[k][c], interior_only, well)).collect();
        let (mut total, mut n, mut dsum, mut dn) = (0.0, 0usize, 0.0, 0usize);
        for p in parts {
            total += p.0;
            n += p.1;
            dsum += p.2;
            dn += p.3;
        }
        LossEval { total, n, design: if dn > 0 { dsum / dn as f64 } else { 1.0 } }
    }

    /// Loss of one plane of pair `k`, channel `c`: (total, values, design sum, design blocks).
    fn eval_plane(
        &self,
        k: usize,
        c: usize,
        plane: &Plane,
        interior_only: bool,
        well: Option<usize>,
    ) -> (f64, usize, f64, usize) {
        // Read noise and ADC step: the scatter of a full photosite's value (or more, when the
        // plateau shows more).
        let read = self.noise.var(0.0).sqrt();
        let sd_well = self.well_sd.map_or(read, |s| s.max(read));
        let mut total = 0.0;
        let mut n = 0usize;
        let mut dsum = 0.0;
        let mut dn = 0usize;
        let p = self.pairs[k];
        let (w, h) = (p.w(), p.h());
        let bw = w.div_ceil(DBLOCK);
        let nb = bw * h.div_ceil(DBLOCK);
        let r = &p.real[c].data;
        let tab = &self.tables;
        let mut bs = vec![0.0f64; nb];
        let mut bc = vec![0u32; nb];
        let ys: Vec<usize> = match &self.rows {
            Some(r) => (0..h).filter(|&y| r.get(y).copied().unwrap_or(false)).collect(),
            None => (0..h).step_by(self.row_step).collect(),
        };
        for y in ys {
            for x in 0..w {
                let i = y * w + x;
                if self.skip[k][i] || (interior_only && !self.interior[k][i]) {
                    continue;
                }
                let mf = plane.data[i];
                let at_well = well.is_some_and(|wl| tab.index(mf).is_some_and(|v| v.abs_diff(wl) <= 1));
                let (l, g) = if at_well {
                    // A full photosite, or (where the sim's footprint is not the real one) a
                    // pixel at that level with the noise of its level: the mixture of the two,
                    // min of the losses + ln 2 for the second (as the exact Poisson–Gaussian form
                    // is capped), so a footprint mismatch costs at most ln 2 more than before.
                    let (lw, gw) = term_at_well(&self.noise, r[i] as f64, mf as f64, sd_well, self.exact);
                    let (ls, gs) = tab.term(&self.noise, r[i] as f64, mf, self.exact);
                    if lw <= ls + LN_2 { (lw, gw) } else { (ls + LN_2, gs) }
                } else {
                    tab.term(&self.noise, r[i] as f64, mf, self.exact)
                };
                let b = (y / DBLOCK) * bw + x / DBLOCK;
                bs[b] += g;
                bc[b] += 1;
                total += l;
                n += 1;
            }
        }
        for (s, &cnt) in bs.iter().zip(&bc) {
            if cnt >= 32 {
                dsum += s * s / cnt as f64;
                dn += 1;
            }
        }
        (total, n, dsum, dn)
    }
}

/// The model levels (work-frame indices `lo..=hi`) whose loss for the unclipped real value `rv`
/// may take the interval form ([`interval_form`]) when no level's sd exceeds `sd_max`: those
/// within 3 sd_max (+ 1 DN) of `rv`; None when `rv` is clipped or not within 3 sd_max of a
/// bound. The rows of both interval tables (8-bit and finer) span this window.
fn interval_window(rv: f64, sd_max: f64) -> Option<(usize, usize)> {
    let fs = FS as f64;
    if !(rv > 0.0 && rv < fs && (rv < 3.0 * sd_max || rv > fs - 3.0 * sd_max)) {
        return None;
    }
    let lo = ((rv - 3.0 * sd_max - 1.0) * 257.0).floor().clamp(0.0, (LEVELS - 1) as f64) as usize;
    let hi = ((rv + 3.0 * sd_max + 1.0) * 257.0).ceil().clamp(0.0, (LEVELS - 1) as f64) as usize;
    Some((lo, hi))
}

/// Whether the loss of real value `rv` (generalised residual `z`, noise sd `sd`) takes the
/// interval form: within 3 sd of a clipping bound the rounding interval matters, and the exact
/// probability of the rounded value (consistent with the censored likelihood of the clipped
/// ones) replaces the density. One condition for [`LossTables::term`], [`direct_term`] and the
/// finer-than-8-bit table (`LossTables::add_real_rows`), so a table hit is the per-pixel value.
#[inline]
fn interval_form(rv: f64, z: f64, sd: f64) -> bool {
    let fs = FS as f64;
    (rv < 3.0 * sd || rv > fs - 3.0 * sd) && z.abs() <= 3.0
}

/// Loss and generalised residual of real value `rv` at model level `m` with noise sd `sd`
/// (continuous noise, without the quantisation `q` of the data), computed without tables: the
/// forms of [`LossTables::term`] for a level outside the tables, and the loss at a full
/// photosite (`term_at_well`). Censored at the bounds (clipped values), the exact probability of
/// the rounded value within 3 sd of a bound, elsewhere Huber; every term is a negative
/// log-probability of the observed value up to a constant, so with `exact` the Gaussian
/// density's normalisation ln sd is part of it (or a model would gain by raising the noise it
/// predicts: a bias of about b/2 DN towards brighter levels under shot noise).
fn direct_term(rv: f64, m: f64, sd: f64, q: f64, exact: bool) -> (f64, f64) {
    let fs = FS as f64;
    if rv <= 0.0 {
        return low_term(m, sd, q);
    }
    if rv >= fs {
        return high_term(m, sd, q, fs);
    }
    let z = (rv - m) / sd;
    let l = if interval_form(rv, z, sd) {
        let l = interval(rv, m, sd, q);
        if exact { l } else { l - sd.ln() }
    } else if exact {
        huber(z) + sd.ln()
    } else {
        huber(z)
    };
    (l, z.clamp(-4.0, 4.0))
}

/// Loss and generalised residual of real value `rv` where the model holds a full photosite at
/// level `m` (its full well, below the top code). Blooming clips the charge at the well and
/// spills the rest: the value read is the clip level itself, not a Poisson draw around it, so it
/// carries the read noise and the ADC step (`sd`) but no shot noise. With the shot noise of its
/// level (≈ 5 DN at 250 DN and 10 e-/DN) a plateau 2.5 DN under the top code is hardly told from
/// a clipped sim at the top code, and blooming's evidence at the well is lost.
fn term_at_well(noise: &NoiseModel, rv: f64, m: f64, sd: f64, exact: bool) -> (f64, f64) {
    direct_term(rv, m, sd, noise.quant, exact)
}

/// Work-frame level (16-bit) at which the model's blooming step leaves its full photosites,
/// when that is below the top code (at the top code a model value means "at or above full
/// scale", the clipped sim's meaning, whose likelihood is that of the level itself).
pub fn well_level(steps: &[Step]) -> Option<usize> {
    let s = steps.iter().find(|s| s.name == "blooming")?;
    let f = s.params.get("full_well_fraction");
    let v = (f * 65535.0).round();
    (v < 65535.0 - 1.0 && v > 0.0).then_some(v as usize)
}

#[inline]
fn huber(z: f64) -> f64 {
    let a = z.abs();
    if a <= 3.0 { 0.5 * a * a } else { 3.0 * a - 4.5 }
}

/// -ln P(round(m + n) = r) for n ~ N(0, sd_c²) (sd_c: the noise without quantisation), shifted
/// so that it equals ½z² where the density approximation holds.
#[inline]
fn interval(r: f64, m: f64, sd: f64, q: f64) -> f64 {
    let sd_c = (sd * sd - q * q / 12.0).max(0.01 * sd * sd).sqrt();
    let p = stats::norm_cdf((r + 0.5 * q - m) / sd_c) - stats::norm_cdf((r - 0.5 * q - m) / sd_c);
    -p.max(1e-300).ln() + (q / (2.0 * std::f64::consts::PI).sqrt()).ln()
}

/// Loss of a value clipped at a bound when the model is `t` noise sigmas inside the bound
/// (`t = (m - bound) / sd` for the lower bound): -ln Φ(-t), capped by the Huber loss of t.
#[inline]
fn censored(t_dn: f64, sd: f64) -> f64 {
    let t = t_dn / sd;
    if t <= 0.0 {
        return -stats::norm_cdf(-t).max(1e-300).ln();
    }
    (-stats::norm_cdf(-t).max(1e-300).ln()).min(huber(t) + std::f64::consts::LN_2)
}

/// The fit frames and the loss.
pub struct FitCtx<'a> {
    /// Per fitted pair: Mono16 work frames (one per channel).
    pub inputs: Vec<Vec<Frame>>,
    pub seqs: Vec<u64>,
    pub loss: LossData<'a>,
    pub seed: u64,
    /// Start rows of the [`BAND`]-row bands the dithered JPEG step runs on during the fit (None:
    /// whole frames); the loss then reads only their rows ([`LossData::rows`]).
    pub bands: Option<Vec<usize>>,
    /// Number of loss evaluations (for the report).
    pub evals: std::sync::atomic::AtomicUsize,
}

/// Keep coupled parameters consistent: after blooming, saturated pixels read the full well, so
/// smear must count pixels at the well (the library's documented `sat_level` rule). Without
/// blooming a saturated pixel is one at the top code of the 16-bit work frames (where every ADC
/// depth puts its top code, see [`super::img::SAT_DN`]): a lower level would count bright but
/// unsaturated features (fiducials at 250 DN, the rim of a glint) and read the smear too weak.
fn sync_coupled(steps: &mut [Step]) {
    let well = steps.iter().find(|s| s.name == "blooming").map(|s| s.params.get("full_well_fraction"));
    for s in steps.iter_mut().filter(|s| s.name == "smear") {
        let lvl = match well {
            Some(f) => (f - 0.75 / 255.0).clamp(0.5, 1.0),
            None => 1.0 - 0.5 / 65535.0,
        };
        let _ = s.params.set("sat_level", lvl);
        // A full photosite cannot take the smear charge its column's transfer adds (it
        // overflows): with blooming the smear stops at the well, so a saturated plateau reads W
        // beside a smear streak instead of W + smear clipped at FS. Without it the well would
        // have to trade against the smear (a strong smear column hid the plateau deficit).
        let _ = s.params.set("well", well.unwrap_or(1.0));
    }
}

impl FitCtx<'_> {
    fn count_eval(&self) {
        self.evals.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }
    /// Run `steps[from..]` on `start` (outputs of the steps before `from`).
    fn run_from(
        &self,
        steps: &mut [Step],
        from: usize,
        start: &[Vec<Frame>],
        bands: Option<&[usize]>,
    ) -> Result<Vec<Vec<Plane>>, DiagnoseError> {
        sync_coupled(steps);
        let mut out = Vec::with_capacity(start.len());
        for (k, img) in start.iter().enumerate() {
            let mut img = img.clone();
            for (j, s) in steps.iter_mut().enumerate().skip(from) {
                s.apply(&mut img, self.seed, self.seqs[k], j, bands)?;
            }
            out.push(planes_of_work(&img));
        }
        Ok(out)
    }
    /// Frames after `steps[..upto]`.
    fn prefix(&self, steps: &mut [Step], upto: usize) -> Result<Vec<Vec<Frame>>, DiagnoseError> {
        sync_coupled(steps);
        let mut out = Vec::with_capacity(self.inputs.len());
        for (k, img) in self.inputs.iter().enumerate() {
            let mut img = img.clone();
            for (j, s) in steps.iter_mut().enumerate().take(upto) {
                s.apply(&mut img, self.seed, self.seqs[k], j, self.bands.as_deref())?;
            }
            out.push(img);
        }
        Ok(out)
    }
    pub fn eval(&self, steps: &mut [Step]) -> Result<LossEval, DiagnoseError> {
        self.count_eval();
        let planes = self.run_from(steps, 0, &self.inputs, self.bands.as_deref())?;
        Ok(self.loss.eval_on(&planes, false, well_level(steps)))
    }
    /// Model planes of the fit frames (whole frames, also with JPEG bands).
    pub fn model_planes(&self, steps: &mut [Step]) -> Result<Vec<Vec<Plane>>, DiagnoseError> {
        self.run_from(steps, 0, &self.inputs, None)
    }
    /// Model planes without the fixed steps (materiality is judged before JPEG, whose
    /// quantisation turns tiny input changes into whole-DN output changes).
    pub fn physical_planes(&self, steps: &[Step]) -> Result<Vec<Vec<Plane>>, DiagnoseError> {
        let mut st: Vec<Step> = steps.iter().filter(|s| !s.fixed).map(Step::boxed_clone).collect();
        self.run_from(&mut st, 0, &self.inputs, None)
    }
}

/// Apply a model to any frame (for residual maps and the stochastic tests on every pair).
pub fn apply_steps(steps: &mut [Step], frame: &Frame, seq: u64, seed: u64) -> Result<Vec<Plane>, DiagnoseError> {
    sync_coupled(steps);
    let mut img = work_planes(frame, seq)?;
    for (j, s) in steps.iter_mut().enumerate() {
        s.apply(&mut img, seed, seq, j, None)?;
    }
    Ok(planes_of_work(&img))
}

/// A fitted coordinate.
#[derive(Debug, Clone, Copy)]
struct Coord {
    step: usize,
    pidx: usize,
    lo: f64,
    hi: f64,
    log: bool,
}

impl Coord {
    fn to_u(self, v: f64) -> f64 {
        if self.log {
            let (a, b) = (self.lo.max(1e-6).ln(), self.hi.ln());
            (v.max(1e-6).ln() - a) / (b - a)
        } else {
            (v - self.lo) / (self.hi - self.lo)
        }
    }
    fn value_at(self, u: f64) -> f64 {
        let u = u.clamp(0.0, 1.0);
        if self.log {
            let (a, b) = (self.lo.max(1e-6).ln(), self.hi.ln());
            (a + u * (b - a)).exp()
        } else {
            self.lo + u * (self.hi - self.lo)
        }
    }
}

/// Practical search range of a parameter around its initial value (narrower than the declared
/// range where that is huge compared with plausible values, so golden sections converge).
fn search_range(effect: &str, name: &str, lo: f64, hi: f64, init: f64) -> (f64, f64) {
    let r = match (effect, name) {
        ("defocus", "sigma_px") => (0.0, (init * 3.0).clamp(2.5, 20.0)),
        ("motion_blur", "length_px") => (0.0, (init * 2.5).clamp(4.0, 100.0)),
        ("motion_blur", "angle_deg") => (0.0, 180.0),
        ("channel_shift", _) => (init - 2.0, init + 2.0),
        ("gain_offset", "gain") => (init - 0.15, init + 0.15),
        ("gain_offset", "offset_dn") => (init - 10.0, init + 10.0),
        ("dark_current", "mean_dn") => (0.0, (init * 3.0).max(6.0)),
        ("gamma", "gamma") => (init * 0.8, init * 1.25),
        ("vignetting", "strength") => (0.0, (init * 2.5).clamp(0.2, 1.0)),
        ("vignetting", "field_deg") => (5.0, 75.0),
        ("stray_light", "amplitude_dn") => (0.0, (init * 2.5).max(8.0)),
        ("veiling_glare", "fraction") => (0.0, (init * 3.0).clamp(0.02, hi)),
        ("veiling_glare", "core_px") => ((init / 8.0).max(lo), (init * 8.0).min(hi)),
        ("stray_light", "distance") => (0.0, 3.0),
        ("stray_light", "width") => (0.2, 3.0),
        ("smear", "strength") => (0.0, (init * 3.0).max(0.002)),
        ("blooming", "full_well_fraction") => ((init - 0.2).max(lo), 1.0),
        ("blooming", "spread_px") => (lo.max(0.3), (init * 3.0).clamp(3.0, hi)),
        ("lens_flare", "intensity") => (0.0, (init * 3.0).max(0.03)),
        ("lens_flare", "size") => (0.01, 0.15),
        _ => (lo, hi),
    };
    (r.0.max(lo), r.1.min(hi))
}

fn coords_of(steps: &[Step], only: Option<usize>) -> Vec<Coord> {
    let mut cs = Vec::new();
    for (si, s) in steps.iter().enumerate() {
        if only.is_some_and(|o| o != si) {
            continue;
        }
        for &pi in &s.fit {
            let spec = &s.params.info().params[pi];
            if spec.kind != ParamKind::Float {
                continue;
            }
            let v = s.params.at(pi);
            let (lo, hi) = search_range(s.name, spec.name, spec.min, spec.max, v);
            if hi <= lo {
                continue;
            }
            cs.push(Coord { step: si, pidx: pi, lo, hi, log: spec.scale == Scale::Log && lo > 0.0 });
        }
    }
    cs
}

fn set_coord(steps: &mut [Step], c: &Coord, v: f64) {
    let spec = &steps[c.step].params.info().params[c.pidx];
    let _ = steps[c.step].params.set(spec.name, v.clamp(spec.min, spec.max));
}

/// Coordinate-wise golden-section descent over `coords`; the frames before the step of each
/// coordinate are cached during its search. Returns the final loss.
fn optimise(
    ctx: &FitCtx,
    steps: &mut [Step],
    coords: &[Coord],
    widths: &[(f64, usize)],
) -> Result<LossEval, DiagnoseError> {
    let mut best = ctx.eval(steps)?;
    for &(width, iters) in widths {
        for c in coords {
            let prefix = ctx.prefix(steps, c.step)?;
            let cur = steps[c.step].params.at(c.pidx);
            let u0 = c.to_u(cur);
            let (a, b) = ((u0 - width).max(0.0), (u0 + width).min(1.0));
            let mut err = None;
            // Every point the search evaluates, so the point it returns needs no second
            // evaluation (the prefix's outputs are those of a whole-chain run: the same loss).
            let mut seen: Vec<(u64, LossEval)> = Vec::with_capacity(iters + 2);
            let mut eval = |u: f64| -> f64 {
                set_coord(steps, c, c.value_at(u));
                ctx.count_eval();
                match ctx.run_from(steps, c.step, &prefix, ctx.bands.as_deref()) {
                    Ok(o) => {
                        let ev = ctx.loss.eval_on(&o, false, well_level(steps));
                        seen.push((u.to_bits(), ev));
                        ev.total
                    }
                    Err(e) => {
                        err = Some(e);
                        f64::INFINITY
                    }
                }
            };
            let (u, v) = stats::golden(&mut eval, a, b, iters);
            if let Some(e) = err {
                return Err(e);
            }
            if std::env::var_os("FAULTCAM_DIAG_DEBUG").is_some() {
                eprintln!(
                    "opt {} {} [{:.4},{:.4}] cur {:.4} -> {:.4}: {:.1} vs best {:.1}",
                    steps[c.step].name,
                    steps[c.step].params.info().params[c.pidx].name,
                    c.value_at(a),
                    c.value_at(b),
                    cur,
                    c.value_at(u),
                    v,
                    best.total
                );
            }
            if v < best.total {
                set_coord(steps, c, c.value_at(u));
                best = match seen.iter().find(|(b, _)| *b == u.to_bits()) {
                    Some(&(_, ev)) => ev,
                    None => ctx.eval(steps)?,
                };
            } else {
                set_coord(steps, c, cur);
            }
        }
    }
    Ok(best)
}

/// Smallest change of the expected image (DN) an effect must make to be reported: the value
/// exceeded by at least 20 values (or 0.05 % of them, if more) of the fitted frames. Below half a
/// quantisation step of 8-bit data, a "significant" effect only reflects how far the real
/// camera's noise departs from the idealised noise model (e.g. the skew of Poisson noise at a
/// few electrons, which biases a Gaussian likelihood by hundredths of a DN), not a physical
/// effect worth modelling.
pub const MATERIAL_DN: f64 = 0.5;

/// Materiality threshold of an effect (DN). Tone and additive effects act on every pixel, so a
/// slight mismatch of the noise or interpolation model anywhere adds up in them: they must
/// change the expected image by a whole DN.
pub fn material_threshold(effect: &str) -> f64 {
    match effect {
        "gain_offset" | "gamma" | "dark_current" | "stray_light" | "veiling_glare" => 2.0 * MATERIAL_DN,
        _ => MATERIAL_DN,
    }
}

/// Joint refinement of every parameter of a model: coordinate sweeps of shrinking width until a
/// sweep gains less than one unit of loss.
fn refine(ctx: &FitCtx, steps: &mut [Step]) -> Result<LossEval, DiagnoseError> {
    let coords = coords_of(steps, None);
    let mut cur = ctx.eval(steps)?;
    for &(w, it) in &[(0.25, 10), (0.12, 8), (0.06, 8), (0.03, 6)] {
        let next = optimise(ctx, steps, &coords, &[(w, it)])?;
        let gain = cur.total - next.total;
        cur = next;
        if gain < 1.0 && w < 0.2 {
            break;
        }
    }
    Ok(cur)
}

/// Evidence of one candidate (or of one selected effect in the backward check).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Evidence {
    pub effect: String,
    pub label: String,
    /// Loss without and with the effect (per value).
    pub loss_without: f64,
    pub loss_with: f64,
    /// Total loss drop.
    pub delta: f64,
    pub design: f64,
    /// Fitted parameters (count).
    pub k: usize,
    /// Significance: chi-square 2ΔL/D on k df as a one-sided normal z.
    pub z: f64,
    /// Passes the information criterion (2ΔL/D > k ln n).
    pub bic: bool,
    /// Size of the effect's change of the expected image (DN; see [`MATERIAL_DN`]).
    pub material_dn: f64,
    pub accepted: bool,
    /// Selection round (0 = the final backward check).
    pub round: usize,
    /// For a candidate that passed in a forward round: how far its penalised loss drop was
    /// behind the round's winner, in units of the round's design effect (half a BIC
    /// difference; 0 for the winner).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gap_to_best: Option<f64>,
    #[serde(skip)]
    pub params: Option<Params>,
}

/// Outcome of the selection.
pub struct Selection {
    pub steps: Vec<Step>,
    /// Final drop-one evidence of each selected step (same order as `steps`).
    pub evidence: Vec<Evidence>,
    /// Every candidate test (all rounds), for the report.
    pub tests: Vec<Evidence>,
    pub loss_null: LossEval,
    pub loss_final: LossEval,
    pub notes: Vec<String>,
    /// Best significance of each candidate over all rounds.
    pub best_z: Vec<f64>,
    /// The level-response check of the tone effects ([`tone_check`]), when it ran.
    pub tone: Option<ToneOutcome>,
    /// The level-or-position check of the spatial effects ([`level_position_check`]), when it
    /// ran: its evidence line.
    pub level_position: Option<String>,
    /// Level-response readings the level-or-position check could not tell from the spatial
    /// effects it kept (effects, evidence, NaN: no BIC on a common scale), for their findings'
    /// alternatives.
    pub spatial_alternatives: Vec<(Vec<&'static str>, String, f64)>,
}

/// The parts of a [`Selection`] a tentative replacement changes ([`replace_by_reading`]), kept
/// to go back to.
struct Kept {
    steps: Vec<Step>,
    evidence: Vec<Evidence>,
    loss_final: LossEval,
}

impl Selection {
    fn keep(&self) -> Kept {
        Kept { steps: clone_steps(&self.steps), evidence: self.evidence.clone(), loss_final: self.loss_final }
    }

    fn restore(&mut self, k: Kept) {
        (self.steps, self.evidence, self.loss_final) = (k.steps, k.evidence, k.loss_final);
    }
}

/// Effects that shape the level response (see [`super::tone`]).
pub const TONE_EFFECTS: [&str; 3] = ["dark_current", "gain_offset", "gamma"];

/// How much better (BIC) another reading of the level response must be to replace the tone
/// effects the selection chose ("very strong" evidence on Kass and Raftery's scale): the
/// forward-model selection sees every pixel, the level response only the shape.
pub const TONE_REPLACE_BIC: f64 = 10.0;

/// BIC difference below which two readings of the level response are listed as near-equal.
pub const TONE_ALTERNATIVE_BIC: f64 = 2.0;

/// Outcome of the level-response check.
#[derive(Debug, Clone)]
pub struct ToneOutcome {
    /// The tone effects of the final model.
    pub effects: Vec<&'static str>,
    /// Evidence line for their findings.
    pub evidence: String,
    /// Readings with other effects that explain the level response about as well or better:
    /// (effects, description, BIC difference to the final reading; negative when the
    /// alternative reads the response better and was not kept, e.g. a gain and offset that moves
    /// full scale by an amount the scene's levels do not reach).
    pub alternatives: Vec<(Vec<&'static str>, String, f64)>,
}

fn tone_params(name: &'static str, r: &tone::Reading) -> Option<Params> {
    let reg = registry::find(name)?;
    let mut p = Params::defaults(reg.info);
    let mut set = |n: &str, v: f64| {
        if let Some((_, spec)) = p.info().param(n) {
            let _ = p.set(n, v.clamp(spec.min, spec.max));
        }
    };
    match name {
        "dark_current" => {
            set("mean_dn", r.d);
            set("hot_pixel_rate", 0.0);
        }
        "gain_offset" => {
            set("gain", r.g);
            set("offset_dn", r.o);
        }
        _ => set("gamma", r.gamma),
    }
    Some(p)
}

/// Whether a reading can be expressed by the library's effects above their floors.
fn tone_reading_valid(r: &tone::Reading) -> bool {
    r.shape.effects().iter().all(|&e| match e {
        "dark_current" => r.d >= 0.5,
        "gamma" => (r.gamma - 1.0).abs() >= 0.01,
        _ => true,
    })
}

/// The reading of the level response that replaces the selection's tone effects `chosen`, if
/// any: the best valid reading, when it is a tone-curve shape with other effects and better than
/// the chosen effects' reading by more than [`TONE_REPLACE_BIC`]. Only shapes that the library's
/// effects cannot represent exactly (a tone curve that fixes 0 and FS, a dark level under one)
/// may replace: between the others (an offset, a straight gain and offset, a power law of one)
/// the forward-model selection has already judged on every pixel with its materiality rule, and
/// the bins' small standard errors would let a slight nonlinearity of the camera decide instead.
pub fn tone_replacement(rs: &[tone::Reading], chosen: &[&str], pts: &[tone::LevelPoint]) -> Option<tone::Reading> {
    let same = |a: &[&str], b: &[&str]| a.len() == b.len() && a.iter().all(|x| b.contains(x));
    let cur = tone::reading_of(rs, chosen)?;
    let b = best_reading(rs, &|r| tone_reading_valid(r) || same(r.shape.effects(), chosen))?;
    if !same(b.shape.effects(), chosen)
        && matches!(b.shape, tone::Shape::Tone | tone::Shape::DarkTone)
        && cur.bic - b.bic > TONE_REPLACE_BIC
    {
        return Some(b.clone());
    }
    // A gain and offset moves full scale (m(FS) = g·FS + o); a tone curve, alone or over a dark
    // level, fixes it. Where the level response does not show the moved full scale beyond what
    // the tone-curve family explains, gain_offset's own signature is not there: the tone-curve
    // reading replaces it (and the gain and offset stays listed as an alternative).
    if chosen.contains(&"gain_offset") {
        let t = rs
            .iter()
            .find(|r| matches!(r.shape, tone::Shape::Tone | tone::Shape::DarkTone) && tone_reading_valid(r))?;
        if t.bic - cur.bic < TONE_GAIN_FS_BIC {
            return Some(t.clone());
        }
        // Nor is it there when a tone-curve reading with no more parameters predicts the same
        // response, within the materiality of a global tone effect, at every level the data
        // have: a tone curve with a linear toe is a gain through the origin up to where it
        // bends, so on a scene whose levels end inside the toe the full scale a gain and offset
        // moves lies beyond the data, and its BIC advantage comes from a misfit below what
        // counts as a change of the image (e.g. a tenth of a DN at the censored dark end). The
        // tone curve — what every camera's response has — is then reported, the gain and offset
        // listed as an alternative. A reading that needs an extra parameter to follow the
        // straight line (a dark level under a tone curve standing in for an offset at zero
        // signal) is not simpler than it, and the BIC stays the judge.
        if let Some(t) = rs.iter().find(|r| {
            matches!(r.shape, tone::Shape::Tone | tone::Shape::DarkTone)
                && tone_reading_valid(r)
                && r.k <= cur.k
                && tone::max_difference(r, cur, pts) < material_threshold("gain_offset")
        }) {
            return Some(t.clone());
        }
    }
    None
}

/// A reading that extends the selection's tone effects `chosen` by another tone effect (a dark
/// level under the chosen tone curve): the best valid reading whose effects include every chosen
/// one and more (other readings may read the response as well or better: they stay listed as
/// alternatives with their evidence), when it reads the level response better than the chosen effects by more than
/// [`TONE_ALTERNATIVE_BIC`] (positive evidence), a reading with `gain_offset` counted
/// [`TONE_GAIN_FS_BIC`] worse as in [`best_reading`]. The forward-model selection adds one effect
/// at a time with the others held at their fit: a dark level `d` under a power law is absorbed by
/// a stronger power (over mid-tones, `((s + d)/FS)^q ≈ (s/FS)^q'` with `q' < q`), so added to the
/// chosen power law alone it fits to nothing — the two parameters must move together (the dark
/// level up, the power back towards 1), which the level response's joint fit does. The physics
/// that separates them is the local log-log slope `d ln m / d ln s = q·s/(s + d)`: constant for a
/// power law, rising with the level under a dark level.
pub fn tone_extension(rs: &[tone::Reading], chosen: &[&str]) -> Option<tone::Reading> {
    let cur = tone::reading_of(rs, chosen)?;
    let extends = |r: &tone::Reading| {
        tone_reading_valid(r)
            && chosen.iter().all(|c| r.shape.effects().contains(c))
            && r.shape.effects().len() > chosen.len()
    };
    let b = best_reading(rs, &extends)?;
    let cost = b.bic + if b.shape.effects().contains(&"gain_offset") { TONE_GAIN_FS_BIC } else { 0.0 };
    (cur.bic - cost > TONE_ALTERNATIVE_BIC).then(|| b.clone())
}

/// The best reading among those `ok` accepts, a reading with gain_offset counted
/// [`TONE_GAIN_FS_BIC`] worse (its moved full scale is the extra claim it must show: a power law
/// of a gain and offset clipped at full scale otherwise passes for a dark level under a tone
/// curve).
fn best_reading<'a>(rs: &'a [tone::Reading], ok: &dyn Fn(&tone::Reading) -> bool) -> Option<&'a tone::Reading> {
    let cost =
        |r: &tone::Reading| r.bic + if r.shape.effects().contains(&"gain_offset") { TONE_GAIN_FS_BIC } else { 0.0 };
    rs.iter().filter(|r| ok(r)).min_by(|a, b| cost(a).total_cmp(&cost(b)))
}

/// BIC advantage a reading with gain_offset needs over the best tone-curve reading (which fixes
/// full scale) for gain_offset to stand: "strong" evidence on Kass and Raftery's scale that
/// full scale moved, since a tone curve and a dark level are what every camera's level response
/// has, and a gain and offset is the extra claim.
pub const TONE_GAIN_FS_BIC: f64 = 6.0;

/// Replace the steps `remove` selects (fixed steps stay) by the effects of the level-response
/// reading `b` with its parameters, refit the other effects and recompute every effect's
/// drop-one evidence. False when a reading's effect cannot be built.
fn replace_by_reading(
    ctx: &FitCtx,
    sel: &mut Selection,
    remove: &dyn Fn(&str) -> bool,
    b: &tone::Reading,
    z_thr: f64,
) -> Result<bool, DiagnoseError> {
    let mut steps: Vec<Step> = sel.steps.iter().filter(|s| s.fixed || !remove(s.name)).map(Step::boxed_clone).collect();
    for &e in b.shape.effects() {
        let Some(params) = tone_params(e, b) else { return Ok(false) };
        insert_sorted(
            &mut steps,
            Step::new(&Candidate { name: e, label: e.to_string(), params, fit: Vec::new(), well_ceiling: None })?,
        );
    }
    if !coords_of(&steps, None).is_empty() {
        refine(ctx, &mut steps)?;
    }
    let current = ctx.eval(&mut steps)?;
    let planes = ctx.physical_planes(&steps)?;
    let jobs: Vec<(usize, Vec<Step>)> = (0..steps.len()).map(|j| (j, clone_steps(&steps))).collect();
    let evs: Vec<Evidence> = jobs
        .into_par_iter()
        .map(|(j, mut st)| drop_one(ctx, &mut st, j, current, &planes, z_thr))
        .collect::<Result<_, _>>()?;
    sel.steps = steps;
    sel.evidence = evs;
    sel.loss_final = current;
    Ok(true)
}

/// Spatial effects a tone curve can imitate where the scene's level varies smoothly over the
/// frame (see [`super::levelmap`]).
pub const SPATIAL_ALIASES: [&str; 3] = ["stray_light", "veiling_glare", "vignetting"];

/// Level-or-position check of the spatial effects the selection chose (`stray_light`,
/// `veiling_glare`, `vignetting`): the residual of the model without them and without the tone
/// effects is regressed on a free level response and on the position terms
/// ([`super::levelmap::test`]). When the position terms are not significant given the level
/// response, the spatial effects' own signature (a change that depends on the place, whatever the
/// level there) is absent: the change depends on each pixel's level — a tone curve, a dark level
/// or a gain and offset, which the spatial effects only imitated through the scene's lighting
/// (a smooth lamp-lit wall, a frame-filling planetary surface under a veiling glare's nearly
/// uniform pedestal, fiducials of one level in the corners).
/// They are then replaced (with the tone effects) by the best reading of the level response
/// ([`super::tone::readings`]), whose shape [`tone_check`] judges next — provided the reading's
/// effects pass their drop-one tests on the forward model (a weak vignetting on a scene whose
/// level falls off towards the corners passes neither test of the regression, and a straight
/// gain and offset that explains nothing must not take its place).
pub fn level_position_check(ctx: &FitCtx, sel: &mut Selection, z_thr: f64) -> Result<(), DiagnoseError> {
    let spatial: Vec<&'static str> =
        sel.steps.iter().filter(|s| !s.fixed && SPATIAL_ALIASES.contains(&s.name)).map(|s| s.name).collect();
    if spatial.is_empty() {
        return Ok(());
    }
    let removed = |n: &str| SPATIAL_ALIASES.contains(&n) || TONE_EFFECTS.contains(&n);
    let mut base: Vec<Step> = sel.steps.iter().filter(|s| !removed(s.name)).map(Step::boxed_clone).collect();
    let planes = ctx.model_planes(&mut base)?;
    let keep: Vec<Vec<bool>> = (0..planes.len())
        .map(|k| ctx.loss.skip[k].iter().zip(&ctx.loss.interior[k]).map(|(&s, &i)| !s && i).collect())
        .collect();
    let real: Vec<&[Plane]> = ctx.loss.pairs.iter().map(|p| p.real.as_slice()).collect();
    let Some(lp) = levelmap::test(&real, &planes, &keep, ctx.loss.noise()) else {
        return Ok(());
    };
    let mut line = lp.describe();
    if std::env::var_os("FAULTCAM_DIAG_DEBUG").is_some() {
        eprintln!("{line}");
    }
    // Each chosen spatial effect's own signature, tested alone given the free level response (a
    // matched test: the 11 position terms together dilute one effect's signature among terms
    // the selection did not choose). Vignetting is a gain that depends on the radius whatever the
    // level (real/sim falls with r within every level), against the level response and — when
    // the selection also chose an additive field — that field; stray light and veiling glare
    // add the same amount to dark and bright pixels at one place.
    let additive_chosen = spatial.iter().any(|&e| e != "vignetting");
    let own_z = |e: &str| match e {
        "vignetting" if additive_chosen => lp.z_radial,
        "vignetting" => lp.z_radial_level,
        _ => lp.z_additive,
    };
    let shown: Vec<String> =
        spatial.iter().filter(|&&e| own_z(e) >= z_thr).map(|&e| format!("{e} z = {:.1}", own_z(e))).collect();
    if lp.z_position < z_thr && !shown.is_empty() {
        sel.notes.push(format!(
            "level or position: the position terms together are weak given a free level response, but {} shows its own signature ({}): kept ({line})",
            spatial.join(" + "),
            shown.join(", ")
        ));
        line = format!(
            "{line}: {} kept, its own signature given the level response is significant ({})",
            spatial.join(" + "),
            shown.join(", ")
        );
    }
    if lp.z_position < z_thr && shown.is_empty() {
        let mut acc = tone::LevelAcc::default();
        let mut n_values = 0usize;
        for (k, mp) in planes.iter().enumerate() {
            for (c, plane) in mp.iter().enumerate() {
                let r = &real[k][c].data;
                for (i, &m) in plane.data.iter().enumerate() {
                    if keep[k][i] || (!ctx.loss.skip[k][i] && smooth_at(plane, i)) {
                        acc.push(m as f64, r[i] as f64);
                        n_values += 1;
                    }
                }
            }
        }
        let pts = tone::level_response(&acc, ctx.loss.noise());
        let rs = tone::readings(&pts, n_values);
        // The symmetric test: a level effect's own signature is a change that depends on the
        // pixel's level at a given place (the level response given the position terms — the
        // radial gain alone when only vignetting was chosen). When that is not significant
        // either, the decorrelated test tells neither reading from the other (on a scene whose
        // level and radius go together, e.g. a bright Earth in the centre and dark sky towards
        // the corners, a weak radial fall-off and a slight tone curve are the same function of
        // the pixel): the forward model's choice, made on every pixel, stays and the level
        // reading is listed as an alternative with both tests.
        let z_level = if additive_chosen { lp.z_level } else { lp.z_level_radial };
        if z_level < z_thr {
            if let Some(b) = best_reading(&rs, &tone_reading_valid) {
                let why = format!(
                    "the level response reads as {}; but given the place, the level response is not significant either (z = {z_level:.1} < {z_thr}), while given the level the position terms reach z = {:.1}: the test that decorrelates level and place does not tell them apart, and the forward model, which compared them on every pixel, chose {}",
                    b.describe(),
                    lp.z_position.max(spatial.iter().map(|&e| own_z(e)).fold(f64::NEG_INFINITY, f64::max)),
                    spatial.join(" + ")
                );
                sel.spatial_alternatives.push((b.shape.effects().to_vec(), why.clone(), f64::NAN));
                sel.notes.push(format!(
                    "level or position: {} kept, the level response listed as an alternative ({why}; {line})",
                    spatial.join(" + ")
                ));
                line = format!("{line}: {} kept; {why}", spatial.join(" + "));
            }
            sel.level_position = Some(line);
            return Ok(());
        }
        // Kept to go back to: a reading whose effects have no evidence of their own on the
        // forward model (each one's drop-one test fails) explains nothing the spatial effects
        // did not, so it cannot replace them.
        let kept = sel.keep();
        if let Some(b) = best_reading(&rs, &tone_reading_valid).cloned()
            && replace_by_reading(ctx, sel, &removed, &b, z_thr)?
        {
            // The reading's effects must show their own evidence on the forward model (a drop-one
            // test each, at least one accepted): a reading that explains nothing the spatial
            // effects did not cannot replace them. (Comparing the two models' losses by BIC was
            // tried and dropped: the library's tone effects are narrower than the free level
            // response, so true tone curves lost to the spatial effects that imitated them.)
            let new_ev: Vec<(&str, &Evidence)> = sel
                .steps
                .iter()
                .zip(&sel.evidence)
                .filter(|(s, _)| b.shape.effects().contains(&s.name))
                .map(|(s, e)| (s.name, e))
                .collect();
            if !new_ev.iter().any(|(_, e)| e.accepted) {
                let zs: Vec<String> = new_ev.iter().map(|(n, e)| format!("{n} z = {:.1}", e.z)).collect();
                let why = format!(
                    "the level response read as {} has no evidence of its own in the forward model (drop-one {})",
                    b.describe(),
                    zs.join(", ")
                );
                sel.restore(kept);
                sel.notes.push(format!(
                    "level or position: {} kept although its position terms are weak given a free level response ({line}): {why}",
                    spatial.join(" + ")
                ));
                line = format!("{line}: {} kept: {why}", spatial.join(" + "));
                sel.level_position = Some(line);
                return Ok(());
            }
            sel.notes.push(format!(
                "level or position: {} replaced by {} (the change follows each pixel's level, not its place: {line})",
                spatial.join(" + "),
                b.shape.effects().join(" + ")
            ));
            line = format!(
                "{line}: the change follows the level, not the place, so {} (which only imitated it through the scene's smooth lighting) gave way to the level response read as {}",
                spatial.join(" + "),
                b.describe()
            );
        }
    }
    sel.level_position = Some(line);
    Ok(())
}

/// Largest 3x3 range (8-bit DN) of the model level at which a pixel off the interior mask still
/// reads the level response: textured regions (cloud tops, a planet's surface, a lit wall's grain)
/// carry the bright and mid levels that tell a tone curve (full scale fixed) from a gain and
/// offset (full scale moved), while on steep edges a small error of the model's blur or
/// registration would move a bin's mean by more than its noise.
pub const TONE_SMOOTH_RANGE_DN: f32 = 24.0;

/// Whether the 3x3 neighbourhood of pixel `i` of `plane` spans at most [`TONE_SMOOTH_RANGE_DN`].
fn smooth_at(plane: &Plane, i: usize) -> bool {
    let (w, h) = (plane.w, plane.h);
    let (x, y) = (i % w, i / w);
    if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
        return false;
    }
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for yy in y - 1..=y + 1 {
        for &v in &plane.data[yy * w + x - 1..=yy * w + x + 1] {
            lo = lo.min(v);
            hi = hi.max(v);
        }
    }
    hi - lo <= TONE_SMOOTH_RANGE_DN
}

/// Level-response check of the tone effects the selection chose (`dark_current`, `gain_offset`,
/// `gamma`): the real level against the level of the model without them, read as each physical
/// shape ([`super::tone::readings`]). When a tone-curve reading (a tone curve that fixes 0 and
/// full scale, alone or over a dark level: shapes the library's pure power law cannot represent,
/// and which it fits worse than a straight line over the mid-tones) is better by more than
/// [`TONE_REPLACE_BIC`], its effects replace the
/// chosen ones with the reading's parameters (a tone curve's `gamma` is the least-squares power
/// law of the fitted curve), the other effects are refitted and every effect's drop-one evidence
/// recomputed. Readings within [`TONE_ALTERNATIVE_BIC`] of the final one are kept as
/// alternatives.
pub fn tone_check(ctx: &FitCtx, sel: &mut Selection, z_thr: f64) -> Result<(), DiagnoseError> {
    level_position_check(ctx, sel, z_thr)?;
    let chosen: Vec<&'static str> =
        sel.steps.iter().filter(|s| !s.fixed && TONE_EFFECTS.contains(&s.name)).map(|s| s.name).collect();
    if chosen.is_empty() {
        return Ok(());
    }
    let mut base: Vec<Step> =
        sel.steps.iter().filter(|s| !TONE_EFFECTS.contains(&s.name)).map(Step::boxed_clone).collect();
    let planes = ctx.model_planes(&mut base)?;
    let mut acc = tone::LevelAcc::default();
    let mut n_values = 0usize;
    for (k, mp) in planes.iter().enumerate() {
        let p = ctx.loss.pairs[k];
        for (c, plane) in mp.iter().enumerate() {
            let r = &p.real[c].data;
            for (i, &m) in plane.data.iter().enumerate() {
                if ctx.loss.skip[k][i] || !(ctx.loss.interior[k][i] || smooth_at(plane, i)) {
                    continue;
                }
                acc.push(m as f64, r[i] as f64);
                n_values += 1;
            }
        }
    }
    let pts = tone::level_response(&acc, ctx.loss.noise());
    let rs = tone::readings(&pts, n_values);
    if std::env::var_os("FAULTCAM_DIAG_DEBUG").is_some() {
        for p in &pts {
            eprintln!("level response: s {:.1} m {:.2} se {:.3} n {}", p.s, p.m, p.se, p.n);
        }
        for r in &rs {
            eprintln!("reading: {}", r.describe());
        }
    }
    let Some(cur) = tone::reading_of(&rs, &chosen).cloned() else {
        return Ok(());
    };
    let same = |a: &[&str], b: &[&str]| a.len() == b.len() && a.iter().all(|x| b.contains(x));
    let replacement = tone_replacement(&rs, &chosen, &pts);
    let mut final_reading = cur.clone();
    let mut evidence = format!(
        "level response (real against the model without {}, {} bins of {} values): the chosen effects read it as {}",
        chosen.join(" and "),
        pts.len(),
        n_values,
        cur.describe()
    );
    if let Some(b) = replacement {
        if !replace_by_reading(ctx, sel, &|n| TONE_EFFECTS.contains(&n), &b, z_thr)? {
            return Ok(());
        }
        sel.notes.push(format!(
            "level response: {} replaced by {} (BIC better by {:.1}; the shape, not the library's fit of it, decides: {})",
            chosen.join(" + "),
            b.shape.effects().join(" + "),
            cur.bic - b.bic,
            b.describe()
        ));
        evidence = format!(
            "level response (real against the model without the tone effects, {} bins of {} values) read as {}; {} (the forward-model choice) reads it as {}, BIC worse by {:.1}",
            pts.len(),
            n_values,
            b.describe(),
            chosen.join(" + "),
            cur.describe(),
            cur.bic - b.bic
        );
        final_reading = b;
    }
    // An extension the forward model did not keep, with its evidence (for its alternative).
    let mut untaken: Option<(tone::Shape, String)> = None;
    if final_reading.shape == cur.shape
        && let Some(b) = tone_extension(&rs, &chosen)
    {
        // The forward model judges the extension on every pixel, started at the joint optimum
        // the level response located: kept only when each of its effects passes its drop-one
        // test (removing it and refitting the rest raises the loss significantly and materially).
        // Also as a whole: the extended model against the chosen one as fitted, both evaluated
        // here (the selection's final loss may come from another likelihood form or subsample).
        let kept = sel.keep();
        let mut st0 = clone_steps(&sel.steps);
        let l0 = ctx.eval(&mut st0)?;
        let p0 = ctx.physical_planes(&st0)?;
        let added: Vec<&str> = b.shape.effects().iter().copied().filter(|e| !chosen.contains(e)).collect();
        let mut ok = replace_by_reading(ctx, sel, &|n| TONE_EFFECTS.contains(&n), &b, z_thr)?;
        let mut drops: Vec<String> = Vec::new();
        if ok {
            let p1 = ctx.physical_planes(&sel.steps)?;
            let whole = self::evidence(
                added[0],
                added[0],
                l0,
                sel.loss_final,
                added.len(),
                material(added[0], &p1, &p0),
                z_thr,
                0,
            );
            ok = whole.accepted
                && b.shape.effects().iter().all(|e| sel.evidence.iter().any(|ev| ev.effect == *e && ev.accepted));
            drops.push(format!(
                "against {} as fitted z = {:.1} (threshold {z_thr}), change {:.2} DN",
                chosen.join(" + "),
                whole.z,
                whole.material_dn
            ));
        }
        // The drop-one tests refit the remaining effects quickly: the comparison with the chosen
        // model as fitted (above) is the one that decides.
        drops.extend(
            sel.evidence
                .iter()
                .filter(|ev| b.shape.effects().contains(&ev.effect.as_str()))
                .map(|ev| format!("drop-one {} z = {:.1}", ev.effect, ev.z)),
        );
        if ok {
            sel.notes.push(format!(
                "level response: {} extended to {} (BIC better by {:.1}; forward model on every pixel: {}): {}",
                chosen.join(" + "),
                b.shape.effects().join(" + "),
                cur.bic - b.bic,
                drops.join(", "),
                b.describe()
            ));
            evidence = format!(
                "level response (real against the model without the tone effects, {} bins of {} values) read as {}; {} alone (the forward-model choice, which adds one effect at a time and cannot move two aliased parameters together) reads it as {}, BIC worse by {:.1}; the forward model, started at the level response's reading, keeps each effect ({})",
                pts.len(),
                n_values,
                b.describe(),
                chosen.join(" + "),
                cur.describe(),
                cur.bic - b.bic,
                drops.join(", ")
            );
            final_reading = b;
        } else {
            sel.notes.push(format!(
                "level response: {} read better as {} (BIC better by {:.1}), but the forward model does not keep it (on every pixel: {}); listed as an alternative",
                chosen.join(" + "),
                b.shape.effects().join(" + "),
                cur.bic - b.bic,
                drops.join(", ")
            ));
            untaken = Some((
                b.shape,
                format!(
                    "; the forward model started at this reading does not tell it from {} ({})",
                    chosen.join(" + "),
                    drops.join(", ")
                ),
            ));
            sel.restore(kept);
        }
    }
    let effects: Vec<&'static str> = final_reading.shape.effects().to_vec();
    let mut alternatives: Vec<(Vec<&'static str>, String, f64)> = Vec::new();
    for r in &rs {
        let gap = r.bic - final_reading.bic;
        if gap < TONE_ALTERNATIVE_BIC
            && !same(r.shape.effects(), &effects)
            && tone_reading_valid(r)
            && !alternatives.iter().any(|a| same(&a.0, r.shape.effects()))
        {
            let fwd = untaken.as_ref().filter(|u| u.0 == r.shape).map(|u| u.1.as_str()).unwrap_or("");
            alternatives.push((r.shape.effects().to_vec(), format!("{}{fwd}", r.describe()), gap));
        }
    }
    sel.tone = Some(ToneOutcome { effects, evidence, alternatives });
    Ok(())
}

fn insert_sorted(steps: &mut Vec<Step>, s: Step) -> usize {
    let pos = steps.iter().position(|t| t.key > s.key).unwrap_or(steps.len());
    steps.insert(pos, s);
    pos
}

/// Effects whose change is confined by construction to a few pixels the sim names: blooming
/// is the identity wherever no charge exceeds the well, and changes only the photosites over
/// it and the neighbours its overflow reaches. Their materiality is judged on those pixels
/// (see [`material`]).
fn local_support(effect: &str) -> bool {
    effect == "blooming"
}

/// The `m`-th largest |with - without|, m = max(20, 0.05 % of the values): at least 20 values,
/// and a share of the image, must change by the returned amount. The share guards against a
/// mismatch of the noise or interpolation model that a global effect gathers from every pixel
/// (hundredths of a DN each). For a [`local_support`] effect the share is of the values the
/// effect changes at all (its support): a local effect cannot gather such a mismatch from the
/// rest of the frame, and a 3 DN plateau at the 80 photosites of one small glint is as material
/// as at 8000 (the 0.05 % of a whole 640x400 frame pair would ask for 256 of them, so the rule
/// would weigh the image's size, not the effect). A global effect keeps the whole image's share.
fn material(effect: &str, with: &[Vec<Plane>], without: &[Vec<Plane>]) -> f64 {
    let mut d: Vec<f64> = Vec::new();
    for (a, b) in with.iter().zip(without) {
        for (pa, pb) in a.iter().zip(b) {
            d.extend(pa.data.iter().zip(&pb.data).map(|(x, y)| (x - y).abs() as f64));
        }
    }
    if d.is_empty() {
        return 0.0;
    }
    let population = if local_support(effect) { d.iter().filter(|&&v| v > 0.0).count() } else { d.len() };
    let m = (population / 2000).max(20).min(d.len());
    let idx = d.len() - m;
    let (_, v, _) = d.select_nth_unstable_by(idx, |a, b| a.total_cmp(b));
    *v
}

/// Practical floor of an effect's parameters: below these values an effect is physically
/// negligible (e.g. a blur narrower than the pixel's own aperture, σ ≈ 0.29 px) and a "fit" of
/// it only absorbs the difference between two models of the same thing (a pillbox and a
/// Gaussian PSF, bilinear and Lanczos interpolation). They sit far below the strengths that are
/// invisible to the eye yet matter (e.g. 8 % vignetting, 1 px defocus, 3 DN dark current).
pub fn above_floor(p: &Params) -> bool {
    let g = |n: &str| p.get(n);
    match p.info().name {
        "defocus" => g("sigma_px") >= 0.3,
        "motion_blur" => g("length_px") >= 1.0,
        "channel_shift" => ["dx_r", "dy_r", "dx_b", "dy_b"].iter().any(|n| g(n).abs() >= 0.1),
        "vignetting" => g("strength") >= 0.02,
        "stray_light" => g("amplitude_dn") >= 1.0,
        "veiling_glare" => g("fraction") >= 1e-3,
        "dark_current" => g("mean_dn") >= 0.5,
        "gain_offset" => (g("gain") - 1.0).abs() >= 0.005 || g("offset_dn").abs() >= 0.5,
        "gamma" => (g("gamma") - 1.0).abs() >= 0.01,
        "smear" => g("strength") >= 2e-4,
        // A well within 2 % of full scale caps only the brightest few DN: indistinguishable from
        // what PRNU, noise or JPEG ringing do to clipped pixels (the fitted "well" then only
        // lowers the mean of clipped samples), so it is not reported as charge overflow.
        "blooming" => g("full_well_fraction") <= 0.98,
        "lens_flare" => g("intensity") >= 0.003,
        _ => true,
    }
}

/// [`above_floor`] of a step, with its own ceiling of the full well: a well one ADC step or more
/// below the top code counts as overflow when the saturated plateau shows it (the plateau sits
/// below the top code; see `saturation::blooming`'s `plateau` choice).
pub fn step_above_floor(s: &Step) -> bool {
    match (s.name, s.well_ceiling) {
        ("blooming", Some(c)) => s.params.get("full_well_fraction") <= c,
        _ => above_floor(&s.params),
    }
}

#[allow(clippy::too_many_arguments)]
fn evidence(
    name: &str,
    label: &str,
    without: LossEval,
    with: LossEval,
    k: usize,
    material_dn: f64,
    z_thr: f64,
    round: usize,
) -> Evidence {
    let delta = without.total - with.total;
    let design = with.design.max(0.8);
    let chi = 2.0 * delta / design;
    let k = k.max(1);
    let z = stats::chi2_to_z(chi, k as f64);
    let bic = chi > k as f64 * (with.n.max(2) as f64).ln();
    let nv = with.n.max(1) as f64;
    Evidence {
        effect: name.to_string(),
        label: label.to_string(),
        loss_without: without.total / nv,
        loss_with: with.total / nv,
        delta,
        design,
        k,
        z,
        bic,
        material_dn,
        accepted: z >= z_thr && bic && material_dn >= material_threshold(name),
        round,
        gap_to_best: None,
        params: None,
    }
}

fn clone_steps(steps: &[Step]) -> Vec<Step> {
    steps.iter().map(Step::boxed_clone).collect()
}

/// Add `cand` to a copy of `steps`, fit its parameters, and measure its evidence against the
/// current model (loss `current`, physical planes `current_planes`).
#[allow(clippy::too_many_arguments)]
fn try_candidate(
    ctx: &FitCtx,
    mut trial: Vec<Step>,
    cand: &Candidate,
    current: LossEval,
    current_planes: &[Vec<Plane>],
    z_thr: f64,
    round: usize,
    widths: &[(f64, usize)],
) -> Result<(Evidence, Vec<Step>, usize), DiagnoseError> {
    let pos = insert_sorted(&mut trial, Step::new(cand)?);
    let mut coords = coords_of(&trial, Some(pos));
    // The candidate's own parameters are its degrees of freedom.
    let k = coords.len();
    if cand.name == "vignetting" {
        profile_start(ctx, &mut trial, &coords, "field_deg", &VIGNETTING_FIELDS_DEG)?;
    }
    // Coupled parameters: with blooming, smear counts the photosites at the well (more of them
    // than the sim's top code holds: the rim of a bright feature that the spill fills up), so
    // a smear strength fitted to the sim's counts overshoots once blooming is in; it is refitted
    // with the well (it was free in the model without blooming, so it adds no degree of freedom).
    if cand.name == "blooming"
        && let Some(j) = trial.iter().position(|s| s.name == "smear" && !s.fixed)
    {
        coords.extend(coords_of(&trial, Some(j)));
    }
    let with = optimise(ctx, &mut trial, &coords, widths)?;
    let planes = ctx.physical_planes(&trial)?;
    let mut ev =
        evidence(cand.name, &cand.label, current, with, k, material(cand.name, &planes, current_planes), z_thr, round);
    ev.accepted &= step_above_floor(&trial[pos]);
    ev.params = Some(trial[pos].params);
    Ok((ev, trial, pos))
}

/// Field angles (degrees) at which [`profile_start`] fits the vignetting strength: from an
/// almost pure ρ² fall-off (a long lens) to a strongly curved cos⁴ (a wide one).
const VIGNETTING_FIELDS_DEG: [f64; 6] = [6.0, 12.0, 20.0, 30.0, 45.0, 65.0];

/// Start of a fit whose parameters trade off along a curved valley. Vignetting's strength (the
/// corner loss) and field angle (the shape) do so whenever the frame's corners hold little
/// signal (a spacecraft in the middle of dark space): the fall-off where the signal is can be
/// matched by a weaker, more curved shape or a stronger, flatter one, and coordinate sweeps from
/// the default field angle stall on the valley's side. So the `shape` parameter is first set to
/// each value of `grid` with the other parameters fitted at each, and the best point starts the
/// sweeps.
fn profile_start(
    ctx: &FitCtx,
    trial: &mut [Step],
    coords: &[Coord],
    shape: &str,
    grid: &[f64],
) -> Result<(), DiagnoseError> {
    let is_shape = |s: &[Step], c: &Coord| s[c.step].params.info().params[c.pidx].name == shape;
    let Some(sc) = coords.iter().find(|c| is_shape(trial, c)).copied() else {
        return Ok(());
    };
    let others: Vec<Coord> = coords.iter().filter(|c| !is_shape(trial, c)).copied().collect();
    let start: Vec<f64> = others.iter().map(|c| trial[c.step].params.at(c.pidx)).collect();
    let mut best: Option<(f64, f64, Vec<f64>)> = None;
    for &v in grid {
        set_coord(trial, &sc, v);
        for (c, &s) in others.iter().zip(&start) {
            set_coord(trial, c, s);
        }
        let ev = optimise(ctx, trial, &others, &[(0.5, 12)])?;
        if best.as_ref().is_none_or(|b| ev.total < b.0) {
            best = Some((ev.total, v, others.iter().map(|c| trial[c.step].params.at(c.pidx)).collect()));
        }
    }
    if let Some((_, v, vals)) = best {
        set_coord(trial, &sc, v);
        for (c, &s) in others.iter().zip(&vals) {
            set_coord(trial, c, s);
        }
    }
    Ok(())
}

/// One swap trial of the selection's swap pass, on its own copy of the model: selected effect
/// `j` of `steps` (whose model has loss `full`, `k_full` parameters and penalised loss `p_full`)
/// replaced by `cand`, refitted.
/// The new model if the replacement passes: its extra parameters (if any) change the expected
/// image by a material amount, and its penalised loss is below `p_full` by the margin (2, or with
/// as many parameters a tenth of what the replaced effect explains).
#[allow(clippy::too_many_arguments)]
fn swap_trial(
    ctx: &FitCtx,
    steps: Vec<Step>,
    j: usize,
    cand: &Candidate,
    full: LossEval,
    k_full: usize,
    p_full: f64,
    full_planes: &[Vec<Plane>],
    z_thr: f64,
    round: usize,
) -> Result<Option<Vec<Step>>, DiagnoseError> {
    let design = full.design.max(0.8);
    let k_j = coords_of(&steps, Some(j)).len();
    let rest: Vec<Step> = steps.into_iter().enumerate().filter(|(i, _)| *i != j).map(|(_, s)| s).collect();
    let mut rest_c = clone_steps(&rest);
    let rest_eval = ctx.eval(&mut rest_c)?;
    let rest_planes = ctx.physical_planes(&rest_c)?;
    let (_, mut trial, _) =
        try_candidate(ctx, clone_steps(&rest), cand, rest_eval, &rest_planes, z_thr, round, &[(0.5, 10), (0.12, 6)])?;
    // More parameters must buy a material change of the expected image (judged with the other
    // effects as they were).
    let k_c = coords_of(&trial, None).len() + k_j - k_full;
    let material_ok =
        k_c <= k_j || material(cand.name, &ctx.physical_planes(&trial)?, full_planes) >= material_threshold(cand.name);
    if !material_ok {
        return Ok(None);
    }
    let ev = refine_quick(ctx, &mut trial)?;
    // Same number of parameters: the replacement must be clearly better (a tenth of what the
    // replaced effect explains), not one of two near-equivalent readings.
    let margin = if k_c < k_j {
        2.0
    } else {
        let mut without = clone_steps(&rest);
        let lw = ctx.eval(&mut without)?;
        (0.1 * (lw.total - full.total) / design).max(2.0)
    };
    Ok((penalised(ev, coords_of(&trial, None).len(), design) < p_full - margin).then_some(trial))
}

/// Penalised loss of a model (for swaps): L/D + ½ k ln n.
fn penalised(ev: LossEval, k: usize, design: f64) -> f64 {
    ev.total / design + 0.5 * k as f64 * (ev.n.max(2) as f64).ln()
}

/// Effects that can stand in for each other (the swap pass only exchanges within a family).
fn family(name: &str) -> u8 {
    match name {
        "dark_current" | "gain_offset" | "gamma" | "stray_light" | "vignetting" | "veiling_glare" => 1,
        "defocus" | "motion_blur" => 2,
        _ => 0,
    }
}

/// Refinement after dropping an effect: shorter than [`refine`].
fn refine_quick(ctx: &FitCtx, steps: &mut [Step]) -> Result<LossEval, DiagnoseError> {
    let coords = coords_of(steps, None);
    optimise(ctx, steps, &coords, &[(0.2, 8), (0.06, 6)])
}

/// Evidence of the selected step `j` of `steps` (the model whose loss is `current` and physical
/// planes `planes`): the loss with it dropped and the others refitted, and for tone and additive
/// effects and motion blur the extra checks of the backward pass.
fn drop_one(
    ctx: &FitCtx,
    steps: &mut [Step],
    j: usize,
    current: LossEval,
    planes: &[Vec<Plane>],
    z_thr: f64,
) -> Result<Evidence, DiagnoseError> {
    if steps[j].fixed {
        return Ok(Evidence {
            effect: steps[j].name.to_string(),
            label: steps[j].label.clone(),
            loss_without: f64::NAN,
            loss_with: current.total / current.n.max(1) as f64,
            delta: f64::NAN,
            design: current.design,
            k: 0,
            z: f64::NAN,
            bic: true,
            material_dn: f64::NAN,
            accepted: true,
            round: 0,
            gap_to_best: None,
            params: Some(steps[j].params),
        });
    }
    let mut without: Vec<Step> =
        steps.iter().enumerate().filter(|(i, _)| *i != j).map(|(_, s)| s.boxed_clone()).collect();
    let lw = if without.iter().any(|s| !s.fixed) { refine_quick(ctx, &mut without)? } else { ctx.eval(&mut without)? };
    let pw = ctx.physical_planes(&without)?;
    let k = coords_of(steps, Some(j)).len();
    let mut ev =
        evidence(steps[j].name, &steps[j].label, lw, current, k, material(steps[j].name, planes, &pw), z_thr, 0);
    ev.accepted &= step_above_floor(&steps[j]);
    ev.params = Some(steps[j].params);
    if std::env::var_os("FAULTCAM_DIAG_DEBUG").is_some() {
        eprintln!(
            "drop-one {}: z {:.1}, change {:.3} DN, above floor {}, accepted {} ({})",
            steps[j].label,
            ev.z,
            ev.material_dn,
            step_above_floor(&steps[j]),
            ev.accepted,
            steps.iter().map(|s| format!("{} {:?}", s.label, s.params)).collect::<Vec<_>>().join("; ")
        );
    }
    if matches!(steps[j].name, "gain_offset" | "gamma" | "dark_current" | "stray_light" | "vignetting") && ev.accepted {
        // A global tone or additive effect must be supported away from edges and saturated
        // pixels; evidence only there is the shape of a PSF or an interpolation that another
        // effect models imperfectly.
        let li = ctx.loss.eval_on(&ctx.model_planes(&mut without)?, true, well_level(&without));
        let ci = ctx.loss.eval_on(&ctx.model_planes(steps)?, true, well_level(steps));
        let inner = evidence(steps[j].name, &steps[j].label, li, ci, k, f64::INFINITY, z_thr, 0);
        if !inner.accepted {
            ev.accepted = false;
            ev.z = ev.z.min(inner.z);
        }
    }
    if steps[j].name == "motion_blur" && ev.accepted {
        // A motion blur must show its direction: the same streak turned by 90° has to fit
        // significantly worse. Otherwise it only reshapes an isotropic blur (e.g. a pillbox PSF
        // seen through a Gaussian one) along edges it cannot tell apart.
        let mut turned = clone_steps(steps);
        let a = turned[j].params.get("angle_deg");
        let _ = turned[j].params.set("angle_deg", (a + 90.0).rem_euclid(180.0));
        let lt = ctx.eval(&mut turned)?;
        let dir = evidence(steps[j].name, &steps[j].label, lt, current, 1, f64::INFINITY, z_thr, 0);
        if !dir.accepted {
            ev.accepted = false;
            ev.z = ev.z.min(dir.z);
        }
    }
    Ok(ev)
}
/// Backward check: every selected effect must still be significant, material and above its
/// floor when it is dropped and the others are refitted; the weakest that is not is dropped and
/// the check repeats. Returns the drop-one evidence of the effects kept and the model's loss.
fn backward(
    ctx: &FitCtx,
    steps: &mut Vec<Step>,
    z_thr: f64,
    notes: &mut Vec<String>,
) -> Result<(Vec<Evidence>, LossEval), DiagnoseError> {
    loop {
        let current = ctx.eval(steps)?;
        let planes = ctx.physical_planes(steps)?;
        let mut evidence = Vec::new();
        let mut weakest: Option<(usize, f64)> = None;
        // Drop-one tests of the selected effects, in parallel on copies of the model; taken in
        // step order.
        let jobs: Vec<(usize, Vec<Step>)> = (0..steps.len()).map(|j| (j, clone_steps(steps))).collect();
        let results: Vec<Result<Evidence, DiagnoseError>> =
            jobs.into_par_iter().map(|(j, mut steps)| drop_one(ctx, &mut steps, j, current, &planes, z_thr)).collect();
        for (j, ev) in results.into_iter().enumerate() {
            let ev = ev?;
            if !steps[j].fixed && !ev.accepted && weakest.is_none_or(|(_, z)| ev.z < z) {
                weakest = Some((j, ev.z));
            }
            evidence.push(ev);
        }
        let Some((j, z)) = weakest else { return Ok((evidence, current)) };
        let s = steps.remove(j);
        notes.push(format!(
            "{}: dropped in the backward check (z = {z:.1} given the other effects refitted, or too small to matter)",
            s.label
        ));
        if steps.iter().any(|s| !s.fixed) {
            refine(ctx, steps)?;
        }
    }
}

/// Forward selection, swaps of selected effects for simpler or better ones, and a backward check.
/// `start` is the initial model (fixed steps, or the model of an earlier pass).
pub fn select(
    ctx: &FitCtx,
    candidates: &[Candidate],
    z_thr: f64,
    start: Vec<Step>,
    prior_z: Option<&[f64]>,
    stop_on: Option<fn(&[Step]) -> bool>,
) -> Result<Selection, DiagnoseError> {
    let mut steps: Vec<Step> = start;
    let mut notes = Vec::new();
    let mut fixed_only: Vec<Step> = steps.iter().filter(|s| s.fixed).map(Step::boxed_clone).collect();
    let loss_null = ctx.eval(&mut fixed_only)?;
    // A repeated selection with a re-measured noise model starts from the model found before
    // (the other repeats start from the fixed steps). An effect found under the old likelihood
    // that fails its drop-one test under the new one is dropped before the forward rounds build
    // on it: effects added to make up for it would only be undone by the backward check at the
    // end, at the cost of many fits. Its result stands for that final check while the model
    // stays as it left it.
    let mut checked: Option<(Vec<Evidence>, LossEval)> = None;
    if steps.iter().any(|s| !s.fixed) {
        checked = Some(backward(ctx, &mut steps, z_thr, &mut notes)?);
    }
    let mut tests: Vec<Evidence> = Vec::new();
    let mut best_z: Vec<f64> = vec![f64::NEG_INFINITY; candidates.len()];
    let mut round = 0;
    let mut swapped: Vec<(String, String)> = Vec::new();
    'outer: loop {
        // ---- forward ----
        loop {
            round += 1;
            let current = ctx.eval(&mut steps)?;
            let current_planes = ctx.physical_planes(&steps)?;
            let mut accepted: Vec<(Evidence, Vec<Step>)> = Vec::new();
            // Every candidate is tried on its own copy of the model, in parallel; the results are
            // taken in candidate order, so the selection does not depend on the thread count.
            let jobs: Vec<(usize, Vec<Step>)> = candidates
                .iter()
                .enumerate()
                .filter(|(_, cand)| !steps.iter().any(|s| s.name == cand.name))
                .map(|(ci, _)| (ci, clone_steps(&steps)))
                .collect();
            let results: Vec<(usize, TrialResult)> = jobs
                .into_par_iter()
                .map(|(ci, trial)| {
                    // Candidates without any evidence so far get a shorter search.
                    let quiet = best_z[ci] < 2.0 && (round > 1 || prior_z.is_some_and(|p| p[ci] < 2.0));
                    let widths: &[(f64, usize)] = if quiet { &[(0.5, 8)] } else { &[(0.5, 12), (0.12, 8)] };
                    (ci, try_candidate(ctx, trial, &candidates[ci], current, &current_planes, z_thr, round, widths))
                })
                .collect();
            for (ci, res) in results {
                let (ev, trial, _) = res?;
                best_z[ci] = best_z[ci].max(ev.z);
                tests.push(ev.clone());
                if ev.accepted {
                    accepted.push((ev, trial));
                }
            }
            // Rank the significant candidates on a common scale: loss drop less the price of
            // the parameters, both in units of the largest design effect among them (a model
            // that fits worse must not win because its residual happens to be less correlated).
            let d_ref = accepted.iter().map(|a| a.0.design).fold(1.0f64, f64::max);
            let ln_n = (current.n.max(2) as f64).ln();
            let score = |e: &Evidence| e.delta - 0.5 * e.k as f64 * ln_n * d_ref;
            let best_score = accepted.iter().map(|a| score(&a.0)).fold(f64::NEG_INFINITY, f64::max);
            for t in tests.iter_mut().filter(|t| t.round == round && t.accepted) {
                t.gap_to_best = Some((best_score - score(t)) / d_ref);
            }
            let best = accepted.into_iter().max_by(|a, b| score(&a.0).total_cmp(&score(&b.0)));
            let Some((ev, trial)) = best else { break };
            for t in tests.iter_mut().filter(|t| t.round == round) {
                t.accepted = t.label == ev.label;
            }
            steps = trial;
            checked = None;
            refine(ctx, &mut steps)?;
            if stop_on.is_some_and(|f| f(&steps)) {
                // The caller repeats the selection in another form once this holds (a tone
                // curve chosen: see `LossData::set_exact`), so the rest of this pass (further
                // rounds, swaps, the backward check) would be discarded: stop here.
                let current = ctx.eval(&mut steps)?;
                return Ok(Selection {
                    steps,
                    evidence: Vec::new(),
                    tests,
                    loss_null,
                    loss_final: current,
                    notes,
                    best_z,
                    tone: None,
                    level_position: None,
                    spatial_alternatives: Vec::new(),
                });
            }
            if steps.len() >= 8 {
                notes.push("selection stopped at 8 deterministic effects".into());
                break;
            }
        }
        // ---- swaps within a family: replace a selected effect by another candidate when that
        // is as good with fewer parameters, or better by a material amount (e.g. an offset taken
        // by gain_offset that is really dark current).
        if steps.iter().all(|s| s.fixed) {
            break;
        }
        let full = ctx.eval(&mut steps)?;
        let k_full = coords_of(&steps, None).len();
        let design = full.design.max(0.8);
        let p_full = penalised(full, k_full, design);
        let full_planes = ctx.physical_planes(&steps)?;
        // The swap trials (a selected effect j replaced by a candidate of its family), in the
        // order the pass takes them; the first one that passes is applied and the pass starts
        // over. Every trial starts from the same model and reads nothing another one writes, so
        // they run in parallel and the first passing one in this order is the one a trial-by-trial
        // pass would take (the trials after it are discarded; only the count of loss evaluations
        // in the notes can differ).
        let mut pairs: Vec<(usize, usize)> = Vec::new();
        for j in 0..steps.len() {
            if steps[j].fixed || swapped.len() >= 4 || family(steps[j].name) == 0 {
                continue;
            }
            for (ci, cand) in candidates.iter().enumerate() {
                if family(cand.name) != family(steps[j].name)
                    || cand.name == steps[j].name
                    || steps.iter().enumerate().any(|(i, s)| i != j && s.name == cand.name)
                    || best_z[ci] < 3.0
                {
                    continue;
                }
                let key = (steps[j].label.clone(), cand.label.clone());
                if swapped.contains(&key) || swapped.iter().any(|s| s.1 == key.0 && s.0 == key.1) {
                    continue;
                }
                pairs.push((j, ci));
            }
        }
        let jobs: Vec<(usize, usize, Vec<Step>)> = pairs.iter().map(|&(j, ci)| (j, ci, clone_steps(&steps))).collect();
        let trials: Vec<Result<Option<Vec<Step>>, DiagnoseError>> = jobs
            .into_par_iter()
            .map(|(j, ci, own)| {
                swap_trial(ctx, own, j, &candidates[ci], full, k_full, p_full, &full_planes, z_thr, round)
            })
            .collect();
        for (&(j, ci), trial) in pairs.iter().zip(trials) {
            if let Some(trial) = trial? {
                let key = (steps[j].label.clone(), candidates[ci].label.clone());
                notes.push(format!(
                    "{} replaced by {} (as good a fit with fewer or better-placed parameters)",
                    key.0, key.1
                ));
                swapped.push(key);
                steps = trial;
                checked = None;
                continue 'outer;
            }
        }
        break;
    }
    // ---- backward check: every selected effect must still be significant, material and above
    // its floor when it is dropped and the others are refitted.
    let (evidence_final, current) = match checked {
        Some(c) => c,
        None => backward(ctx, &mut steps, z_thr, &mut notes)?,
    };
    Ok(Selection {
        steps,
        evidence: evidence_final,
        tests,
        loss_null,
        loss_final: current,
        notes,
        best_z,
        tone: None,
        level_position: None,
        spatial_alternatives: Vec::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn material_is_the_twentieth_largest_change() {
        let a = vec![vec![Plane::filled(100, 10, 10.0)]];
        let mut b = a.clone();
        for i in 0..19 {
            b[0][0].data[i] = 20.0; // 19 large changes: fewer than 20
        }
        b[0][0].data[50] = 10.4;
        assert!((material("gamma", &b, &a) - 0.4).abs() < 1e-6);
        b[0][0].data[19] = 13.0;
        assert!((material("gamma", &b, &a) - 3.0).abs() < 1e-6);
    }

    #[test]
    fn a_local_effect_is_material_on_its_support() {
        // 80 photosites of one small glint lowered by 3 DN in a 640x400 frame pair: the 256th
        // largest change of the 512000 values is 0, the 20th of the 80 changed ones 3 DN.
        let a = vec![vec![Plane::filled(640, 400, 200.0)], vec![Plane::filled(640, 400, 200.0)]];
        let mut b = a.clone();
        for f in 0..2 {
            for i in 0..40 {
                b[f][0].data[1000 + 3 * i] = 197.0;
            }
        }
        assert_eq!(material("gamma", &b, &a), 0.0);
        assert!((material("blooming", &b, &a) - 3.0).abs() < 1e-6);
        // Fewer than 20 changed values are never material, local or not.
        let mut c = a.clone();
        for i in 0..19 {
            c[0][0].data[i] = 150.0;
        }
        assert_eq!(material("blooming", &c, &a), 0.0);
    }

    #[test]
    fn tone_check_replaces_only_by_tone_curve_shapes() {
        use super::super::tone::{LevelPoint, readings, tone_curve};
        let fs = FS as f64;
        let pts = |f: &dyn Fn(f64) -> f64| -> Vec<LevelPoint> {
            (2..240).step_by(2).map(|s| LevelPoint { s: s as f64, m: f(s as f64), se: 0.05, n: 2000 }).collect()
        };
        // A dark level seen through a camera with a slight gain error: the straight line reads it
        // far better than the offset, but both are library shapes the forward selection compared
        // on every pixel, so its `dark_current` stays.
        let p = pts(&|s| 1.01 * s + 3.0);
        let rs = readings(&p, 100_000);
        assert_eq!(rs[0].shape, super::super::tone::Shape::Affine);
        assert!(tone_replacement(&rs, &["dark_current"], &p).is_none());
        // An sRGB-like tone curve taken for a gain and offset is replaced by `gamma` with the
        // least-squares power law of the curve.
        let p = pts(&|s| fs * tone_curve(s / fs, 1.1, 0.02, false));
        let rs = readings(&p, 100_000);
        let r = tone_replacement(&rs, &["gain_offset"], &p).expect("tone curve replaces gain_offset");
        assert_eq!(r.shape.effects(), ["gamma"]);
        assert!((r.gamma - 1.063).abs() < 0.005, "gamma {}", r.gamma);
        // A dark level under a tone curve taken for one gain and offset: dark_current + gamma.
        let p = pts(&|s| fs * tone_curve((s + 2.5) / fs, 0.92, 0.015, true));
        let rs = readings(&p, 100_000);
        let r = tone_replacement(&rs, &["gain_offset"], &p).expect("dark under tone replaces gain_offset");
        assert_eq!(r.shape.effects(), ["dark_current", "gamma"]);
        assert!((r.d - 2.5).abs() < 0.2, "dark {}", r.d);
    }

    /// h31tone: a dark level under a power law, seen on mid-tones only (a lab wall: 60–200 DN),
    /// is read by the level response as the chosen power law extended by a dark level (the local
    /// log-log slope `q·s/(s + d)` rises with the level); a pure power law is not extended, and
    /// neither is a reading that already has its dark level.
    #[test]
    fn tone_extension_adds_a_dark_level_under_the_chosen_power_law() {
        use super::super::tone::{LevelPoint, readings};
        let fs = FS as f64;
        let pts = |f: &dyn Fn(f64) -> f64| -> Vec<LevelPoint> {
            (60..200).step_by(2).map(|s| LevelPoint { s: s as f64, m: f(s as f64), se: 0.1, n: 2000 }).collect()
        };
        let rs = readings(&pts(&|s| fs * ((s + 2.5) / fs).powf(0.96)), 100_000);
        let r = tone_extension(&rs, &["gamma"]).expect("dark level under the power law");
        assert_eq!(r.shape.effects(), ["dark_current", "gamma"]);
        assert!((r.d - 2.5).abs() < 0.5 && (r.gamma - 0.96).abs() < 0.01, "{}", r.describe());
        assert!(tone_extension(&rs, &["dark_current", "gamma"]).is_none());
        let rs = readings(&pts(&|s| fs * (s / fs).powf(0.93)), 100_000);
        assert!(tone_extension(&rs, &["gamma"]).is_none());
    }

    /// h27tone: a dark level under an sRGB curve seen only on levels inside the curve's linear
    /// toe is exactly a gain and offset there; full scale is not seen to move, so gain_offset
    /// (whose own signature that is) gives way to the tone-curve reading. A true gain and
    /// offset seen up to bright levels moves full scale and stands.
    #[test]
    fn gain_offset_stands_only_where_full_scale_moves() {
        use super::super::tone::{LevelPoint, readings, tone_curve};
        let fs = FS as f64;
        let pts = |f: &dyn Fn(f64) -> f64, hi: usize| -> Vec<LevelPoint> {
            (2..hi).step_by(2).map(|s| LevelPoint { s: s as f64, m: f(s as f64), se: 0.3, n: 300 }).collect()
        };
        // Toe of (q 0.88, a 0.05) ends at x 0.35 (89 DN): levels 2..200 DN, the toe and the
        // bend (on the toe alone both read χ² 0 and the tone curve's extra parameter costs
        // ln n in BIC: there gain_offset stays, a limit).
        let dark_tone = |s: f64| fs * tone_curve((s + 2.5) / fs, 0.88, 0.05, true);
        let p = pts(&dark_tone, 200);
        let rs = readings(&p, 100_000);
        let r = tone_replacement(&rs, &["gain_offset"], &p).unwrap_or_else(|| {
            panic!("no moved full scale: {:?}", rs.iter().map(|r| r.describe()).collect::<Vec<_>>())
        });
        assert!(r.shape.effects().contains(&"gamma"), "{}", r.describe());
        let p = pts(&|s| 1.03 * s + 1.5, 240);
        let rs = readings(&p, 100_000);
        assert!(tone_replacement(&rs, &["gain_offset"], &p).is_none(), "a gain of 1.03 up to 240 DN moves full scale");
        // h33photo: a near-linear decoding curve (q 1.3, a 0.22: a linear toe of slope 0.99 up to
        // 0.733 FS) seen on levels inside its toe, the darkest bins (many values, small standard
        // errors) a tenth of a DN low: the straight line reads the response better by far more
        // than 6 in BIC, but the two readings never differ by a material amount where there are
        // data (full scale is beyond them), so the tone curve is reported.
        let toe = |s: f64| fs * tone_curve(s / fs, 1.3, 0.22, false);
        let mut p = pts(&toe, 188);
        for q in p.iter_mut().filter(|q| q.s < 5.0) {
            q.m -= 0.1;
            q.se = 0.03;
        }
        let rs = readings(&p, 100_000);
        let (t, a) = (tone::reading_of(&rs, &["gamma"]).unwrap(), tone::reading_of(&rs, &["gain_offset"]).unwrap());
        assert!(t.bic - a.bic > TONE_GAIN_FS_BIC, "{} / {}", t.describe(), a.describe());
        let r = tone_replacement(&rs, &["gain_offset"], &p).expect("the toe does not show a moved full scale");
        assert_eq!(r.shape.effects(), ["gamma"], "{}", r.describe());
    }

    #[test]
    fn floors_reject_negligible_parameters_only() {
        let mut p = Params::defaults(registry::find("defocus").unwrap().info);
        p.set("sigma_px", 0.2).unwrap();
        assert!(!above_floor(&p));
        p.set("sigma_px", 1.0).unwrap();
        assert!(above_floor(&p));
        let mut g = Params::defaults(registry::find("gain_offset").unwrap().info);
        g.set("gain", 1.002).unwrap();
        g.set("offset_dn", 0.2).unwrap();
        assert!(!above_floor(&g));
        g.set("offset_dn", -2.0).unwrap();
        assert!(above_floor(&g));
        let mut b = Params::defaults(registry::find("blooming").unwrap().info);
        b.set("full_well_fraction", 0.987).unwrap();
        assert!(!above_floor(&b), "a well 1.3 % below full scale is clipping, not overflow");
        b.set("full_well_fraction", 0.94).unwrap();
        assert!(above_floor(&b));
    }

    /// (h28diag) A well 4 DN under the top code of 8-bit data (0.985 FS) is clipping by the
    /// default floor, but charge overflow when the saturated plateau showed it below the top
    /// code (the candidate's ceiling, one ADC step under FS); a well at the top code is not.
    #[test]
    fn well_ceiling_admits_a_plateau_below_the_top_code() {
        let mut p = Params::defaults(registry::find("blooming").unwrap().info);
        p.set("full_well_fraction", 0.985).unwrap();
        let mut c =
            Candidate { name: "blooming", label: "blooming".into(), params: p, fit: vec![], well_ceiling: None };
        assert!(!step_above_floor(&Step::new(&c).unwrap()));
        c.well_ceiling = Some(1.0 - 1.0 / 255.0);
        assert!(step_above_floor(&Step::new(&c).unwrap()));
        assert!(step_above_floor(&Step::new(&c).unwrap().boxed_clone()), "the ceiling survives a clone");
        c.params.set("full_well_fraction", 0.999).unwrap();
        assert!(!step_above_floor(&Step::new(&c).unwrap()), "a well within one ADC step of FS");
    }

    /// Without blooming the forward model's smear counts only samples at the top code: on 10-bit
    /// data (bit-replicated into 16 bits) code 1023 feeds the streak, code 1022 (254.75 DN, a
    /// bright but unsaturated feature) does not, and neither does anything at 0.98·FS.
    #[test]
    fn smear_without_blooming_counts_only_the_top_code() {
        use crate::frame::{Frame, FrameData, PixelFormat};
        let (w, h) = (8usize, 6usize);
        let code16 = |c: u32| ((c << 6) | (c >> 4)) as u16; // 10-bit code → 16-bit
        let mut data = vec![code16(200); w * h];
        data[w + 2] = code16(1023);
        data[3 * w + 2] = code16(1023);
        for y in 0..h {
            data[y * w + 5] = code16(1022);
            data[y * w + 6] = code16(1003); // 0.98·FS
        }
        let f = Frame::from_data(w as u32, h as u32, w, PixelFormat::Mono16, FrameData::U16(data)).unwrap();
        let base = planes_of(&f).remove(0);
        let mut p = Params::defaults(registry::find("smear").unwrap().info);
        p.set("strength", 0.01).unwrap();
        let mut steps = vec![Step::fixed("smear", p).unwrap()];
        let out = apply_steps(&mut steps, &f, 0, 1).unwrap().remove(0);
        let d = |x: usize, y: usize| out.data[y * w + x] - base.data[y * w + x];
        // Two saturated samples in column 2: every unsaturated sample there gains 2 · 0.01 · FS.
        assert!((d(2, 0) - 2.0 * 0.01 * FS).abs() < 0.02, "column 2 gains {}", d(2, 0));
        for y in 0..h {
            assert_eq!(d(5, y), 0.0, "code 1022 is not saturated (row {y})");
            assert_eq!(d(6, y), 0.0, "0.98·FS is not saturated (row {y})");
            assert_eq!(d(0, y), 0.0);
        }
    }

    /// The loss at a few photo-electrons is a proper likelihood: averaged over the values a
    /// camera of known noise gives at a true level (photo-electrons k ~ Poisson(m·gain), read
    /// noise, rounding, clipping at 0; the probabilities summed here directly), it is lowest at
    /// the true level. The Gaussian form without its normalisation ln σ prefers a level about
    /// b/2 DN brighter (it gains by predicting more noise), which over the millions of dark-sky
    /// pixels of a large frame outweighs a real vignetting.
    #[test]
    fn likelihood_at_few_electrons_is_lowest_at_the_true_level() {
        for &(gain, read_sd, m_true) in &[(6.0f64, 1.5f64, 2.0f64), (2.0, 0.5, 3.0), (4.0, 1.0, 1.5)] {
            let mut noise = NoiseModel::prior(1.0);
            noise.a = read_sd * read_sd;
            noise.b = 1.0 / gain;
            noise.c = 0.0;
            let tab = LossTables::new(&noise);
            // P(real = r) of the camera at m_true, r = 0 (clipped) ..= 40.
            let lam = m_true * gain;
            let p_real: Vec<f64> = (0..=40usize)
                .map(|r| {
                    let (lo, hi) = if r == 0 { (f64::NEG_INFINITY, 0.5) } else { (r as f64 - 0.5, r as f64 + 0.5) };
                    let mut pk = (-lam).exp();
                    let mut p = 0.0;
                    for k in 0..200 {
                        let v = k as f64 / gain;
                        p += pk * (stats::norm_cdf((hi - v) / read_sd) - stats::norm_cdf((lo - v) / read_sd));
                        pk *= lam / (k + 1) as f64;
                    }
                    p
                })
                .collect();
            assert!((p_real.iter().sum::<f64>() - 1.0).abs() < 1e-6);
            let v0 = (m_true * 257.0).round() as usize;
            let argmin = |loss: &dyn Fn(f64, f32) -> f64| -> f64 {
                let mut best = (f64::INFINITY, 0.0);
                for v in v0 - 80..=v0 + 80 {
                    let mf = tab.level[v];
                    let e: f64 = p_real.iter().enumerate().map(|(r, &p)| p * loss(r as f64, mf)).sum();
                    if e < best.0 {
                        best = (e, mf as f64);
                    }
                }
                best.1 - m_true
            };
            let exact = argmin(&|r, mf| tab.term(&noise, r, mf, true).0);
            let plain = argmin(&|r, mf| {
                let m = mf as f64;
                if r <= 0.0 { low_term(m, noise.sd(m), 1.0).0 } else { huber((r - m) / noise.sd(m)) }
            });
            // The exact form's residual offset (about 0.02 DN at 6 electrons) comes from its
            // robust cap (the Huber form + ln 2 where that is more probable).
            let what =
                format!("gain {gain}, read {read_sd}, level {m_true}: exact {exact:.4} DN, Gaussian {plain:.4} DN");
            assert!(exact.abs() <= 0.025, "{what}");
            assert!(plain > 0.03 && plain > 3.0 * exact.abs(), "{what}");
        }
    }

    /// The Poisson–Gaussian row sums only the photo-electron counts near each boundary; against the
    /// sum over every count (the form it replaced) it must agree to rounding, for a read noise far
    /// below one electron's step (a first noise estimate with a = 0), near it, and far above it.
    #[test]
    fn pg_row_window_equals_the_sum_over_every_count() {
        for &(a, b, m) in
            &[(0.0f64, 3.4f64, 150.0f64), (0.0, 3.4, 7.0), (2.25, 0.16, 9.0), (0.4, 1.0, 30.0), (1.0, 0.5, 0.0)]
        {
            let mut noise = NoiseModel::prior(1.0);
            noise.a = a;
            noise.b = b;
            noise.c = 0.0;
            let sd = noise.sd(m);
            let r_lo = (m - 4.0 * sd).floor().max(0.0) as usize;
            let r_hi = ((m + 5.0 * sd).ceil() as usize).min(254);
            let got = pg_row(&noise, m, r_lo, r_hi);
            // Reference: every count k of the Poisson, each with its full Phi.
            let lam = m / b;
            let s = (a + noise.c * m * m).max(0.02).sqrt();
            let cdf = |t: f64| {
                let (mut p, mut sum) = ((-lam).exp(), 0.0);
                for k in 0..(lam + 12.0 * lam.sqrt() + 20.0) as usize {
                    sum += p * stats::norm_cdf((t - k as f64 * b) / s);
                    p *= lam / (k + 1) as f64;
                }
                sum
            };
            for (i, r) in (r_lo..=r_hi).enumerate() {
                let p = if r == 0 { cdf(0.5) } else { cdf(r as f64 + 0.5) - cdf(r as f64 - 0.5) };
                let want =
                    -p.max(1e-300).ln() + if r == 0 { 0.0 } else { (1.0 / (2.0 * std::f64::consts::PI).sqrt()).ln() };
                // Where P(r) is above 1e-9 the two agree to 1e-6 in the loss (cancellation in the
                // reference's differences of CDFs near 1 bounds it); further out both are tails.
                if p > 1e-9 {
                    assert!((got[i] - want).abs() < 1e-6, "a {a} b {b} m {m} r {r}: {} vs {want}", got[i]);
                }
            }
        }
    }

    /// 12-bit-like real values near the dark bound: the tabulated interval loss is the per-pixel
    /// formula at the same arguments, bit for bit, and values not in the data are computed directly.
    #[test]
    fn finer_than_8_bit_interval_rows_equal_the_direct_loss() {
        let q = 255.0 / 4095.0;
        let mut noise = NoiseModel::prior(q);
        noise.a = 2.0;
        noise.b = 0.2;
        noise.c = 0.0;
        let mut tab = LossTables::new(&noise);
        // Real values: 12-bit codes scaled to 16 bits (code * 16), as 16-bit PNGs of 12-bit data hold them.
        let mut counts = vec![0u32; LEVELS];
        for code in 0..200usize {
            counts[code * 16] = 1 + (code % 7) as u32;
        }
        tab.add_real_rows(&noise, &counts);
        assert!(!tab.qrows.is_empty());
        let mut hits = 0;
        for code in (3..200usize).step_by(3) {
            let rv = tab.level[code * 16] as f64;
            for v in (0..3000usize).step_by(7) {
                let mf = tab.level[v];
                let (got, _) = tab.term(&noise, rv, mf, true);
                let direct = interval(rv, mf as f64, tab.sd[v], q);
                if tab.interval_at(rv, v).is_some() {
                    hits += 1;
                    let z = (rv - mf as f64) / tab.sd[v];
                    if (rv < 3.0 * tab.sd[v]) && z.abs() <= 3.0 {
                        assert_eq!(got.to_bits(), direct.to_bits(), "code {code} level {v}");
                    }
                }
            }
        }
        assert!(hits > 100, "{hits} table hits");
        // A value the data do not hold (code 5 * 16 + 8) is not in the table.
        assert!(tab.interval_at(tab.level[5 * 16 + 8] as f64, 5 * 16).is_none());
    }

    /// A full photosite reads its clip level with the read noise and ADC step only. On
    /// a 10-bit camera (10 e-/DN, read noise 1.2 DN) whose well sits 2.5 DN under the top code,
    /// the plateau's values are told from a clipped level at the top code by far more than the
    /// shot noise of that level would allow (≈ 5 DN), and a plateau at the top code counts
    /// against a model that puts the well below it.
    #[test]
    fn a_full_photosite_carries_the_read_noise_only() {
        let mut noise = NoiseModel::prior(255.0 / 1023.0);
        noise.a = 1.44;
        noise.b = 0.1;
        noise.c = 0.0;
        let tab = LossTables::new(&noise);
        let read = noise.var(0.0).sqrt();
        let well = 0.99 * FS as f64;
        let (w16, top16) = ((well * 257.0).round() as f32 / 257.0, FS);
        let plateau = (well * 1023.0 / 255.0).round() * 255.0 / 1023.0;
        // Per pixel: the clipped sim at the top code (shot noise of its level) against the well.
        let at_top = tab.term(&noise, plateau, top16, true).0;
        let at_well = term_at_well(&noise, plateau, w16 as f64, read, true).0;
        let with_shot = tab.term(&noise, plateau, w16, true).0;
        assert!(at_top - at_well > 1.0, "top {at_top:.3} well {at_well:.3}");
        assert!(at_top - with_shot < 0.2, "with the shot noise: top {at_top:.3} well {with_shot:.3}");
        // A plateau at the top code: the well below it is unlikely, and more so than with shot noise.
        let clipped = term_at_well(&noise, FS as f64, w16 as f64, read, true).0;
        assert!(clipped > tab.term(&noise, FS as f64, w16, true).0 + 1.0 && clipped > 2.5, "{clipped}");
    }

    #[test]
    fn huber_and_censored_losses_are_continuous_and_increasing() {
        assert!((huber(3.0) - 4.5).abs() < 1e-12 && (huber(3.0 + 1e-9) - 4.5).abs() < 1e-6);
        let mut last = 0.0;
        for i in 0..60 {
            let t = -3.0 + i as f64 * 0.2;
            let v = censored(t, 1.0);
            assert!(v >= last - 1e-12, "t {t}: {v} < {last}");
            last = v;
        }
    }
}
