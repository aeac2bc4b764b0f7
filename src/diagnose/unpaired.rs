//! Unpaired mode (`--unpaired`): sim and real show different scenes, so statistics are compared
//! instead of pixels.

use super::report::{FitSummary, Report, UnpairedReport};
use super::{DiagnoseError, Options};
use crate::frame::Frame;

pub fn run(
    sims: &[(String, Frame)],
    reals: &[(String, Frame)],
    _opts: &Options,
) -> Result<UnpairedReport, DiagnoseError> {
    let report = Report {
        findings: Vec::new(),
        fit: FitSummary { before: Default::default(), after: Default::default() },
        model: "fitted.toml".into(),
        mode: "unpaired".into(),
        pairs: sims.len().min(reals.len()),
        rmse_after_with_noise: f64::NAN,
        tests: Vec::new(),
        selection: Vec::new(),
        dropped: Vec::new(),
        notes: vec!["unpaired mode not implemented yet".into()],
    };
    Ok(UnpairedReport {
        report,
        config: crate::config::FaultConfig::from_effects(1, Vec::new()),
        profiles: Vec::new(),
        lines: Vec::new(),
    })
}
