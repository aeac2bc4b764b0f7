//! `faultcam eval`: fidelity metrics between paired images, and the blooming validation protocol.

use anyhow::Context;
use clap::Subcommand;
use faultcam::eval::blooming::{self, BloomingConfig, Generated};
use faultcam::eval::pairs;
use faultcam::faults;
use faultcam::metrics::OrbConfig;
use std::path::PathBuf;

/// Arguments of `faultcam eval`.
#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    pub command: EvalCommand,
}

#[derive(Subcommand, Debug)]
pub enum EvalCommand {
    /// Metrics between images of two folders paired by file stem (RMSE, PSNR, SSIM, FQI,
    /// histogram correlation, Bhattacharyya distance, SPI): a table on stdout, JSON on request.
    Pairs(PairsArgs),
    /// The original study's blooming validation protocol: bloom bright generated images, crop
    /// the blooming zones, match them against real blooming crops (FQI, histogram correlation),
    /// accept at thresholds, compare with the same crops before blooming (control).
    Blooming(BloomingArgs),
}

#[derive(clap::Args, Debug)]
pub struct PairsArgs {
    /// First folder (e.g. simulated images).
    #[arg(long)]
    pub a: PathBuf,
    /// Second folder (e.g. real images); files pair by stem (`x.png` with `x.jpg`).
    #[arg(long)]
    pub b: PathBuf,
    /// Write the per-pair and mean metrics as JSON to this file (`-` for stdout instead of the
    /// table).
    #[arg(long)]
    pub json: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct BloomingArgs {
    /// Generated images: a folder, or a source URI such as `synth:?width=330&height=205`.
    #[arg(long)]
    pub generated: String,
    /// Folder of real images with blooming.
    #[arg(long)]
    pub real: PathBuf,
    /// Use only real images whose file name contains this text (repeatable; default: all).
    #[arg(long = "real-include")]
    pub real_include: Vec<String>,
    /// Output folder: report.json, summary.txt, fqi_hist.png, hist_corr_hist.png, grey_hist.png,
    /// crops/.
    #[arg(long)]
    pub out: PathBuf,
    /// Bright level in 8-bit DN for selection and zones.
    #[arg(long, default_value_t = 250.0)]
    pub threshold: f32,
    /// Pixels at or above the threshold needed to select a generated image (and smallest zone).
    #[arg(long, default_value_t = 10)]
    pub min_area: usize,
    /// Smallest crop side in px (zones are grown about their centre to this).
    #[arg(long, default_value_t = 96)]
    pub min_crop: usize,
    /// Acceptance threshold on FQI.
    #[arg(long, default_value_t = 0.80)]
    pub fqi_min: f64,
    /// Acceptance threshold on histogram correlation (-1..=1).
    #[arg(long, default_value_t = 0.90, allow_negative_numbers = true)]
    pub corr_min: f64,
    /// ORB patch size and edge threshold in px (OpenCV default 31; 2..=255).
    #[arg(long, default_value_t = 31, value_parser = clap::value_parser!(i32).range(2..=255))]
    pub orb_patch: i32,
    /// Most generated images to read.
    #[arg(long, default_value_t = 210)]
    pub count: usize,
    /// Seed of the blooming effect's generators.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Blooming parameter `name=value` (repeatable), e.g. `--param spread_px=4`.
    #[arg(long = "param")]
    pub params: Vec<String>,
    /// Fault configuration (TOML, e.g. diagnose's fitted.toml) applied instead of blooming
    /// alone: every effect it enables, in physical order. `--param` is then not accepted.
    #[arg(long)]
    pub faults: Option<std::path::PathBuf>,
    /// Do not write the crops as PNG.
    #[arg(long)]
    pub no_crops: bool,
}

pub fn run(args: Args) -> anyhow::Result<u8> {
    match args.command {
        EvalCommand::Pairs(a) => run_pairs(a),
        EvalCommand::Blooming(a) => run_blooming(a),
    }
}

fn run_pairs(a: PairsArgs) -> anyhow::Result<u8> {
    let report = pairs::evaluate_pairs(&a.a, &a.b)?;
    let json = serde_json::to_string_pretty(&report)?;
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    match &a.json {
        Some(p) if p.as_os_str() == "-" => writeln!(out, "{json}")?,
        Some(p) => {
            std::fs::write(p, &json).with_context(|| format!("writing {}", p.display()))?;
            write!(out, "{}", report.table())?;
        }
        None => write!(out, "{}", report.table())?,
    }
    Ok(if report.pairs.iter().any(|p| p.error.is_some()) { 1 } else { 0 })
}

fn run_blooming(a: BloomingArgs) -> anyhow::Result<u8> {
    let mut params =
        faults::default_params("blooming").context("the blooming validation protocol needs the `blooming` effect")?;
    for kv in &a.params {
        let (k, v) = kv.split_once('=').with_context(|| format!("--param '{kv}': expected name=value"))?;
        match v.parse::<f64>() {
            Ok(x) => params.set(k, x)?,
            Err(_) => match v {
                "true" => params.set(k, 1.0)?,
                "false" => params.set(k, 0.0)?,
                word => params.set_choice(k, word)?,
            },
        }
    }
    let faults = match &a.faults {
        Some(_) if !a.params.is_empty() => anyhow::bail!("--faults and --param: give the parameters in the file"),
        Some(p) => Some(faultcam::config::FaultConfig::load(p)?),
        None => None,
    };
    let cfg = BloomingConfig {
        threshold: a.threshold,
        min_area: a.min_area,
        min_crop: a.min_crop,
        fqi_min: a.fqi_min,
        corr_min: a.corr_min,
        orb: OrbConfig { edge_threshold: a.orb_patch, patch_size: a.orb_patch, ..OrbConfig::default() },
        blooming: Some(params),
        faults,
        seed: a.seed,
        max_generated: a.count,
        real_include: a.real_include,
        save_crops: !a.no_crops,
    };
    let report = blooming::run_protocol(&Generated::parse(&a.generated), &a.real, &a.out, &cfg)?;
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    write!(out, "{}", report.summary())?;
    writeln!(out, "wrote {} (report.json, summary.txt, {})", a.out.display(), report.plots.join(", "))?;
    Ok(0)
}
