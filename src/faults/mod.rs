//! The effect vocabulary (see EFFECTS.md): one [`Effect`] implementation per file, registered in
//! [`registry`], applied in physical order by [`chain::Chain`].
//!
//! An effect declares static metadata ([`EffectInfo`]: stage, parameters with units and bounds,
//! model text) and implements [`Effect::apply`]. The same `apply` is the deterministic forward
//! model that `diagnose` fits: given the same frame, parameters and generator it produces the
//! same bytes.

pub mod chain;
/// Helpers of the physics library: row bands, random lanes, sparse sampling, bench scene.
pub mod fir16;
pub mod kit;
/// Table-driven per-sample noise kernel (scalar reference + AVX2).
pub mod noise;
pub mod registry;
pub mod util;

// Optics
pub mod boxblur;
pub mod channel_shift;
pub mod defocus;
pub mod lens_flare;
pub mod motion_blur;
pub mod stray_light;
pub mod streak;
pub mod veiling_glare;
pub mod vignetting;
// Sensor
pub mod blooming;
pub mod dark_current;
pub mod hot_pixels;
pub mod prnu;
pub mod shot_noise;
pub mod smear;
// Readout
pub mod gain_offset;
pub mod gamma;
pub mod gaussian_noise;
/// `vertical_glitch` and `horizontal_glitch`.
pub mod glitch;
pub mod row_noise;
// Transmission
pub mod jpeg;
/// `cosmic_rays`, `bit_flip`, `dead_pixels`.
pub mod radiation;
/// `frame_drop`, `frame_freeze`, `frame_delay`, `jitter`, `reorder`.
pub mod temporal;

use crate::frame::{Frame, PixelFormat};
use crate::rng::Rng;
use thiserror::Error;

/// Physical stage of the signal chain. The chain applies stages in this order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    /// On the irradiance image, before the sensor.
    Optics,
    /// Charge in the pixels (electrons), before conversion.
    Sensor,
    /// Readout electronics and ADC.
    Readout,
    /// Compression, transport and stream-level effects.
    Transmission,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Stage::Optics => "optics",
            Stage::Sensor => "sensor",
            Stage::Readout => "readout",
            Stage::Transmission => "transmission",
        }
    }
}

/// Value type of a parameter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ParamKind {
    Float,
    /// Integer-valued (stored as f64, validated to be whole).
    Int,
    /// 0 or 1 (TOML `true`/`false`).
    Bool,
    /// One of the listed words; stored as the index.
    Choice(&'static [&'static str]),
}

/// How a fitter should search the parameter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Scale {
    Linear,
    /// Positive, searched in log space.
    Log,
}

/// One parameter: name, unit, accepted range, default and meaning.
#[derive(Debug, Clone, Copy)]
pub struct ParamSpec {
    pub name: &'static str,
    /// Unit, e.g. `px`, `DN`, `deg`, `fraction`, `e-/DN`, `1`.
    pub unit: &'static str,
    pub min: f64,
    pub max: f64,
    pub default: f64,
    pub kind: ParamKind,
    pub scale: Scale,
    /// Canonical parameter from EFFECTS.md (fitted by `diagnose`), as opposed to an extra.
    pub canonical: bool,
    pub doc: &'static str,
}

impl ParamSpec {
    /// A canonical float parameter with linear scale.
    pub const fn float(
        name: &'static str,
        unit: &'static str,
        min: f64,
        max: f64,
        default: f64,
        doc: &'static str,
    ) -> ParamSpec {
        ParamSpec { name, unit, min, max, default, kind: ParamKind::Float, scale: Scale::Linear, canonical: true, doc }
    }
    /// A canonical integer parameter.
    pub const fn int(
        name: &'static str,
        unit: &'static str,
        min: f64,
        max: f64,
        default: f64,
        doc: &'static str,
    ) -> ParamSpec {
        ParamSpec { name, unit, min, max, default, kind: ParamKind::Int, scale: Scale::Linear, canonical: true, doc }
    }
    /// A boolean parameter (extra, not fitted).
    pub const fn flag(name: &'static str, default: bool, doc: &'static str) -> ParamSpec {
        ParamSpec {
            name,
            unit: "bool",
            min: 0.0,
            max: 1.0,
            default: if default { 1.0 } else { 0.0 },
            kind: ParamKind::Bool,
            scale: Scale::Linear,
            canonical: false,
            doc,
        }
    }
    /// A choice parameter; `default` is the index into `choices`.
    pub const fn choice(
        name: &'static str,
        choices: &'static [&'static str],
        default: usize,
        canonical: bool,
        doc: &'static str,
    ) -> ParamSpec {
        ParamSpec {
            name,
            unit: "choice",
            min: 0.0,
            max: (choices.len() - 1) as f64,
            default: default as f64,
            kind: ParamKind::Choice(choices),
            scale: Scale::Linear,
            canonical,
            doc,
        }
    }
    /// Same parameter searched in log space.
    pub const fn log(mut self) -> ParamSpec {
        self.scale = Scale::Log;
        self
    }
    /// Mark as an extra (non-canonical) parameter.
    pub const fn extra(mut self) -> ParamSpec {
        self.canonical = false;
        self
    }

    /// Human-readable accepted range, e.g. `0.1..=20 px` or `one of vertical, horizontal`.
    pub fn range_text(&self) -> String {
        match self.kind {
            ParamKind::Choice(c) => format!("one of {}", c.join(", ")),
            ParamKind::Bool => "true or false".to_string(),
            ParamKind::Int => format!("integer {}..={} {}", self.min, self.max, self.unit),
            ParamKind::Float => format!("{}..={} {}", self.min, self.max, self.unit),
        }
    }

    /// Validate a numeric value for this parameter.
    pub fn check(&self, effect: &'static str, value: f64) -> Result<f64, FaultError> {
        let bad = !value.is_finite()
            || value < self.min
            || value > self.max
            || (matches!(self.kind, ParamKind::Int | ParamKind::Bool | ParamKind::Choice(_)) && value.fract() != 0.0);
        if bad {
            return Err(FaultError::ParamOutOfRange { effect, param: self.name, value, accepted: self.range_text() });
        }
        Ok(value)
    }
}

/// Static description of an effect.
#[derive(Debug)]
pub struct EffectInfo {
    /// Name as in EFFECTS.md.
    pub name: &'static str,
    pub stage: Stage,
    /// Position within the stage (smaller first); the physical order inside a stage.
    pub order: u16,
    /// One line.
    pub summary: &'static str,
    /// The forward model, units and sign conventions (printed by `faultcam effects`).
    pub model: &'static str,
    pub params: &'static [ParamSpec],
    /// Formats the effect accepts.
    pub formats: &'static [PixelFormat],
}

/// Formats most image effects accept.
pub const ALL_FORMATS: &[PixelFormat] = &[PixelFormat::Mono8, PixelFormat::Mono16, PixelFormat::Rgb8];

impl EffectInfo {
    pub fn param(&self, name: &str) -> Option<(usize, &'static ParamSpec)> {
        self.params.iter().enumerate().find(|(_, p)| p.name == name)
    }
    pub fn accepts(&self, f: PixelFormat) -> bool {
        self.formats.contains(&f)
    }
}

/// Most parameters any effect has.
pub const MAX_PARAMS: usize = 16;

/// Resolved parameter values of one effect (fixed-size, `Copy`: no allocation per frame).
#[derive(Clone, Copy)]
pub struct Params {
    info: &'static EffectInfo,
    values: [f64; MAX_PARAMS],
}

impl std::fmt::Debug for Params {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut m = f.debug_map();
        for (s, v) in self.iter() {
            m.entry(&s.name, &v);
        }
        m.finish()
    }
}

impl PartialEq for Params {
    fn eq(&self, other: &Self) -> bool {
        self.info.name == other.info.name && self.values == other.values
    }
}

impl Params {
    /// All parameters at their defaults.
    pub fn defaults(info: &'static EffectInfo) -> Params {
        debug_assert!(info.params.len() <= MAX_PARAMS);
        let mut values = [0.0; MAX_PARAMS];
        for (v, p) in values.iter_mut().zip(info.params) {
            *v = p.default;
        }
        Params { info, values }
    }
    pub fn info(&self) -> &'static EffectInfo {
        self.info
    }
    /// Value by name. Unknown names read as NaN (and trip a debug assertion).
    pub fn get(&self, name: &str) -> f64 {
        match self.info.param(name) {
            Some((i, _)) => self.values[i],
            None => {
                debug_assert!(false, "{}: no parameter {name}", self.info.name);
                f64::NAN
            }
        }
    }
    /// Value by index into `info.params`.
    pub fn at(&self, i: usize) -> f64 {
        self.values[i]
    }
    pub fn get_bool(&self, name: &str) -> bool {
        self.get(name) != 0.0
    }
    /// Word of a choice parameter.
    pub fn choice(&self, name: &str) -> &'static str {
        match self.info.param(name) {
            Some((i, ParamSpec { kind: ParamKind::Choice(c), .. })) => {
                c.get(self.values[i] as usize).copied().unwrap_or("")
            }
            _ => "",
        }
    }
    /// Set a numeric value, validated against the parameter's range.
    pub fn set(&mut self, name: &str, value: f64) -> Result<(), FaultError> {
        let (i, spec) = self.info.param(name).ok_or_else(|| self.unknown(name))?;
        self.values[i] = spec.check(self.info.name, value)?;
        Ok(())
    }
    /// Set a choice parameter by word.
    pub fn set_choice(&mut self, name: &str, word: &str) -> Result<(), FaultError> {
        let (i, spec) = self.info.param(name).ok_or_else(|| self.unknown(name))?;
        match spec.kind {
            ParamKind::Choice(c) => match c.iter().position(|w| *w == word) {
                Some(k) => {
                    self.values[i] = k as f64;
                    Ok(())
                }
                None => Err(FaultError::BadChoice {
                    effect: self.info.name,
                    param: spec.name,
                    got: word.to_string(),
                    accepted: spec.range_text(),
                }),
            },
            _ => Err(FaultError::BadChoice {
                effect: self.info.name,
                param: spec.name,
                got: word.to_string(),
                accepted: spec.range_text(),
            }),
        }
    }
    fn unknown(&self, name: &str) -> FaultError {
        FaultError::UnknownParam {
            effect: self.info.name,
            param: name.to_string(),
            accepted: self.info.params.iter().map(|p| p.name).collect::<Vec<_>>().join(", "),
        }
    }
    /// (spec, value) pairs in declaration order.
    pub fn iter(&self) -> impl Iterator<Item = (&'static ParamSpec, f64)> + '_ {
        self.info.params.iter().zip(self.values.iter().copied())
    }
}

impl serde::Serialize for Params {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut m = s.serialize_map(Some(self.info.params.len()))?;
        for (spec, v) in self.iter() {
            match spec.kind {
                ParamKind::Choice(c) => m.serialize_entry(spec.name, c.get(v as usize).copied().unwrap_or(""))?,
                ParamKind::Bool => m.serialize_entry(spec.name, &(v != 0.0))?,
                ParamKind::Int => m.serialize_entry(spec.name, &(v as i64))?,
                ParamKind::Float => m.serialize_entry(spec.name, &v)?,
            }
        }
        m.end()
    }
}

/// What happens to the frame after an effect.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// The frame continues down the chain.
    Keep,
    /// The frame is dropped (e.g. `frame_drop`); later effects are not applied.
    Drop,
}

/// Per-call context handed to [`Effect::apply`].
#[derive(Debug, Clone)]
pub struct EffectCtx {
    /// Per-frame, per-effect generator (derive children per row/band for parallel work).
    pub rng: Rng,
    /// Seed for fixed patterns (same on every frame): use `Rng::new(pattern_seed)`.
    pub pattern_seed: u64,
    /// Frame sequence number.
    pub seq: u64,
    /// Extra output delay requested by temporal effects (ns), summed over the chain.
    pub delay_ns: u64,
}

impl EffectCtx {
    pub fn new(campaign_seed: u64, seq: u64, effect_index: usize) -> EffectCtx {
        EffectCtx {
            rng: Rng::for_frame(campaign_seed, seq, effect_index as u64),
            pattern_seed: Rng::for_pattern(campaign_seed, effect_index as u64).seed(),
            seq,
            delay_ns: 0,
        }
    }
}

/// A physical effect. Implementations keep any per-stream state (cached kernels, fixed
/// patterns, scratch buffers) in `self`, so steady-state application does not allocate.
pub trait Effect: Send {
    fn info(&self) -> &'static EffectInfo;
    /// Apply in place with the given (validated) parameters.
    fn apply(&mut self, frame: &mut Frame, params: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError>;
    /// At the end of the stream: give back a frame the effect still holds (e.g. `reorder`'s
    /// buffer), one per call, `None` when empty. The chain passes drained frames through the
    /// effects after this one, so no input frame is lost.
    fn drain(&mut self) -> Option<Frame> {
        None
    }
}

/// Errors of effects and their parameters.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum FaultError {
    #[error("unknown effect '{name}'; known effects: {known}")]
    UnknownEffect { name: String, known: String },
    #[error("{effect}: unknown parameter '{param}'; accepted parameters: {accepted}")]
    UnknownParam { effect: &'static str, param: String, accepted: String },
    #[error("{effect}.{param} = {value} is out of range; accepted: {accepted}")]
    ParamOutOfRange { effect: &'static str, param: &'static str, value: f64, accepted: String },
    #[error("{effect}.{param} = '{got}' is not accepted; accepted: {accepted}")]
    BadChoice { effect: &'static str, param: &'static str, got: String, accepted: String },
    #[error("{effect} does not support pixel format {format}; supported: {supported}")]
    UnsupportedFormat { effect: &'static str, format: PixelFormat, supported: String },
    #[error("{effect}: {reason}")]
    Failed { effect: &'static str, reason: String },
}

/// Error for a format the effect does not handle.
pub fn unsupported(info: &'static EffectInfo, format: PixelFormat) -> FaultError {
    FaultError::UnsupportedFormat {
        effect: info.name,
        format,
        supported: info.formats.iter().map(|f| f.name()).collect::<Vec<_>>().join(", "),
    }
}

/// Create an effect by name.
pub fn create(name: &str) -> Result<Box<dyn Effect>, FaultError> {
    registry::find(name).map(|r| (r.create)()).ok_or_else(|| FaultError::UnknownEffect {
        name: name.to_string(),
        known: registry::all().iter().map(|r| r.info.name).collect::<Vec<_>>().join(", "),
    })
}

/// Apply one effect once to a frame (the forward model, for tests and fitting).
pub fn apply_once(name: &str, frame: &mut Frame, params: &Params, seed: u64) -> Result<Outcome, FaultError> {
    let mut e = create(name)?;
    let mut ctx = EffectCtx::new(seed, frame.seq, 0);
    e.apply(frame, params, &mut ctx)
}

/// Default parameters of a named effect.
pub fn default_params(name: &str) -> Result<Params, FaultError> {
    create(name).map(|e| Params::defaults(e.info()))
}
