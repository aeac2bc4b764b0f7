//! faultcam: physically modelled camera faults for hardware-in-the-loop testing of spacecraft
//! vision. See README.md for the pipeline and EFFECTS.md (shared) for the effect vocabulary.

// Numerical kernels index several arrays with one loop variable; iterator zips would hide the
// arithmetic. Forward models take many physical parameters.
#![allow(clippy::needless_range_loop, clippy::too_many_arguments)]

pub mod config;
pub mod control;
pub mod diagnose;
pub mod eval;
pub mod faults;
pub mod frame;
pub mod gtlog;
pub mod limits;
pub mod masks;
pub mod metrics;
pub mod pipeline;
pub mod pose;
pub mod rng;
pub mod schedule;
pub mod sink;
pub mod source;
pub mod sweep;
pub mod trigger;

pub use config::FaultConfig;
pub use faults::chain::{Chain, FrameReport};
pub use faults::{Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
pub use frame::{Frame, FrameData, PixelFormat};
pub use rng::Rng;
