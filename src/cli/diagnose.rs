//! `faultcam diagnose`: find the physics a simulation left out, fit it, and report.

use faultcam::diagnose::{self, Options};
use std::path::PathBuf;

/// Arguments of `faultcam diagnose`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Folder of simulated images (paired with REAL by file name).
    #[arg(long)]
    pub sim: PathBuf,
    /// Folder of real images.
    #[arg(long)]
    pub real: PathBuf,
    /// Output folder (report.json, fitted.toml, report.md, plots).
    #[arg(long)]
    pub out: PathBuf,
    /// Sim and real show different scenes: compare statistics instead of pixels.
    #[arg(long)]
    pub unpaired: bool,
    /// Significance (one-sided normal z) a signature needs to become a finding.
    #[arg(long, default_value_t = 6.0)]
    pub z_threshold: f64,
    /// Largest number of pairs used by the joint forward-model fit.
    #[arg(long, default_value_t = 4)]
    pub fit_frames: usize,
    /// Seed of the forward models (and of fitted.toml).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Do not write report.md and its plots.
    #[arg(long)]
    pub no_markdown: bool,
    /// Print the report JSON to stdout as well.
    #[arg(long)]
    pub print: bool,
}

pub fn run(args: Args) -> anyhow::Result<u8> {
    let opts = Options {
        unpaired: args.unpaired,
        z_threshold: args.z_threshold,
        fit_frames: args.fit_frames,
        seed: args.seed,
        write_markdown: !args.no_markdown,
    };
    let t0 = std::time::Instant::now();
    let rep = diagnose::diagnose_dirs(&args.sim, &args.real, &args.out, &opts)?;
    if args.print {
        println!("{}", serde_json::to_string_pretty(&rep)?);
    }
    eprintln!(
        "faultcam diagnose: {} finding(s) [{}] in {:.1} s; report in {}",
        rep.findings.len(),
        rep.findings.iter().map(|f| f.effect.as_str()).collect::<Vec<_>>().join(", "),
        t0.elapsed().as_secs_f64(),
        args.out.join("report.json").display()
    );
    Ok(0)
}
