//! Subcommands of the `faultcam` binary.

pub mod apply;
pub mod bench;
pub mod diagnose;
pub mod effects;
pub mod eval;
pub mod log;
pub mod run;
pub mod sweep;
