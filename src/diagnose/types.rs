//! Shared vocabulary of the diagnosis: its errors and options, the outcome of a signature test
//! ([`Signature`], with its evidence curves [`Profile`]) and the progress line. Depends on no
//! other module of `diagnose` (see the dependency rule in the module doc of `diagnose`).

use crate::faults::FaultError;
use std::path::PathBuf;
use thiserror::Error;

/// Errors of diagnosis (each names the file concerned).
#[derive(Debug, Error)]
pub enum DiagnoseError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: cannot decode image: {message}")]
    Decode { path: PathBuf, message: String },
    #[error("{name}: sim is {sim} but real ({real_path}) is {real}; pairs must have the same size and channels")]
    SizeMismatch { name: String, sim: String, real: String, real_path: PathBuf },
    #[error("no pairs: no file name of {sim} is also in {real} (images are paired by file name)")]
    NoPairs { sim: PathBuf, real: PathBuf },
    #[error("{dir}: no images (accepted: png, jpg, tif, pgm, ppm)")]
    NoImages { dir: PathBuf },
    #[error("{path}: cannot write: {message}")]
    Write { path: PathBuf, message: String },
    #[error(transparent)]
    Fault(#[from] FaultError),
}

/// Options of a diagnosis run.
#[derive(Debug, Clone)]
pub struct Options {
    /// Sim and real show different scenes: compare statistics.
    pub unpaired: bool,
    /// Significance (one-sided normal z) a signature must reach to become a candidate.
    pub z_threshold: f64,
    /// Largest number of pairs used by the joint forward-model fit (all pairs are used by the
    /// signature tests).
    pub fit_frames: usize,
    /// Seed of the forward models' generators.
    pub seed: u64,
    /// Write report.md with plots and residual maps.
    pub write_markdown: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options { unpaired: false, z_threshold: 6.0, fit_frames: 4, seed: 1, write_markdown: true }
    }
}

/// A curve that gave evidence (plotted in report.md).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Profile {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub x: Vec<f64>,
    /// (label, values); values may be NaN where there is no data.
    pub series: Vec<(String, Vec<f64>)>,
}

/// Outcome of one signature test.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Signature {
    /// Effect name from EFFECTS.md.
    pub effect: &'static str,
    /// Significance as a one-sided normal z (large = strong evidence against "absent").
    pub z: f64,
    /// Passed the significance test and the minimum effect size.
    pub detected: bool,
    /// Initial canonical parameter estimates from the signature (before the forward-model fit).
    pub params: Vec<(String, f64)>,
    /// Choice parameters (e.g. smear direction).
    pub choices: Vec<(String, String)>,
    /// Standard errors of the estimates, where known.
    pub stderr: Vec<(String, f64)>,
    /// Effect size in the unit of `size_unit`, for ranking and the practical threshold.
    pub size: f64,
    pub size_unit: &'static str,
    #[serde(rename = "where")]
    pub where_: String,
    pub evidence: String,
    #[serde(skip)]
    pub profiles: Vec<Profile>,
}

impl Signature {
    pub fn new(effect: &'static str) -> Signature {
        Signature {
            effect,
            z: 0.0,
            detected: false,
            params: Vec::new(),
            choices: Vec::new(),
            stderr: Vec::new(),
            size: 0.0,
            size_unit: "",
            where_: String::new(),
            evidence: String::new(),
            profiles: Vec::new(),
        }
    }
    pub fn param(&self, name: &str) -> Option<f64> {
        self.params.iter().find(|(n, _)| n == name).map(|(_, v)| *v)
    }
    pub fn set_param(&mut self, name: &str, v: f64) {
        if let Some(p) = self.params.iter_mut().find(|(n, _)| n == name) {
            p.1 = v;
        } else {
            self.params.push((name.to_string(), v));
        }
    }
}

/// Progress of a diagnosis on stderr (`faultcam diagnose: <stage> at <s> s`), seconds since the
/// first call of the process. Set `FAULTCAM_DIAG_QUIET` to silence it; set `FAULTCAM_DIAG_MEM`
/// to append the process's resident memory now and at its peak so far (`VmRSS`, `VmHWM` of
/// /proc/self/status, Linux only).
pub fn progress(stage: &str) {
    static START: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    let t0 = *START.get_or_init(std::time::Instant::now);
    if std::env::var_os("FAULTCAM_DIAG_QUIET").is_none() {
        let mem = if std::env::var_os("FAULTCAM_DIAG_MEM").is_some() { memory_status() } else { String::new() };
        eprintln!("faultcam diagnose: {stage} at {:.1} s{mem}", t0.elapsed().as_secs_f64());
    }
}

/// `" (RSS <a> MB, peak <b> MB)"` from /proc/self/status, empty where it cannot be read.
fn memory_status() -> String {
    let Ok(status) = std::fs::read_to_string("/proc/self/status") else {
        return String::new();
    };
    let kb = |key: &str| -> Option<f64> {
        let line = status.lines().find(|l| l.starts_with(key))?;
        line[key.len()..].trim().trim_end_matches("kB").trim().parse::<f64>().ok()
    };
    match (kb("VmRSS:"), kb("VmHWM:")) {
        (Some(rss), Some(hwm)) => format!(" (RSS {:.0} MB, peak {:.0} MB)", rss / 1024.0, hwm / 1024.0),
        _ => String::new(),
    }
}
