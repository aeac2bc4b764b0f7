//! `faultcam sweep`: run a pose stack under test against every fault at a grid of severities
//! and report where it breaks (see `faultcam::sweep`). `faultcam sweep merge` joins shards.

use anyhow::bail;
use faultcam::sweep::plan::Settings;
use faultcam::sweep::{RunOptions, ShardFile, merge_shards, report, run_cells};
use std::path::{Path, PathBuf};

/// Arguments of `faultcam sweep`.
#[derive(clap::Args, Debug)]
#[command(args_conflicts_with_subcommands = true)]
pub struct Args {
    #[command(subcommand)]
    pub merge: Option<Merge>,
    /// Sweep config (TOML): source, poses, sut, timeout_s, levels, seeds, tolerance, threshold,
    /// effects, campaign, pairs, [[effect]] grids; live: mode = "live", sink, sut_report,
    /// frame_timeout_s, startup_s, fps. Options given here override it.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Batch SUT: a shell command with {in_dir} (images), {out_file} (one pose per image, JSON
    /// Lines {"file","q":[w,x,y,z],"t":[x,y,z]} or CSV file,qw,qx,qy,qz,x,y,z; without it the
    /// SUT's stdout is read) and {camera} (JSON intrinsics fx, fy, cx, cy).
    #[arg(long, value_name = "CMD")]
    pub sut: Option<String>,
    /// Live mode: stream each cell's frames into --sink while the SUT runs; it reports one
    /// JSON line {"seq":N,"q":[w,x,y,z],"t":[x,y,z]} per frame over --sut-report. The SUT
    /// command gets {in_dir}, {camera}, {cell_dir} and {report} (the report address/device).
    #[arg(long)]
    pub live: bool,
    /// Live: sink the SUT reads, files:DIR (default files:{in_dir}, written frame by frame),
    /// gst:appsrc ! ... or v4l2:/dev/videoN (frame seq N stamped (N+1) ms, shown again while
    /// its report is awaited); {in_dir} and {cell_dir} are replaced per cell.
    #[arg(long, value_name = "URI")]
    pub sink: Option<String>,
    /// Live: where poses come back: stdout (default), udp:HOST:PORT (faultcam binds; port 0 =
    /// any free port, passed as {report}) or serial:DEVICE[?baud=N].
    #[arg(long, value_name = "SPEC")]
    pub sut_report: Option<String>,
    /// Live: time-out of one frame's report, seconds (default 5).
    #[arg(long, value_name = "S")]
    pub frame_timeout_s: Option<f64>,
    /// Live: extra time for the first frame's report (SUT start-up), seconds (default 10).
    #[arg(long, value_name = "S")]
    pub startup_s: Option<f64>,
    /// Live: pacing, frames per second: frame N is shown no earlier than N/F s after the
    /// stream's start (still one at a time, after the previous frame's report or time-out).
    #[arg(long, value_name = "F")]
    pub fps: Option<f64>,
    /// Frame source (default: a small synth: scene); files:DIR needs --poses.
    #[arg(long, value_name = "URI")]
    pub source: Option<String>,
    /// Pose truth for a files: source (JSON Lines or SPEED+-style CSV).
    #[arg(long, value_name = "FILE")]
    pub poses: Option<PathBuf>,
    /// Sweep the effects of this fault campaign (its parameters are the base of each grid).
    #[arg(long, value_name = "FILE")]
    pub campaign: Option<PathBuf>,
    /// Effects to sweep, comma-separated (default: every effect that changes pixels).
    #[arg(long, value_delimiter = ',', value_name = "NAMES")]
    pub effects: Option<Vec<String>>,
    /// Pairs of effects swept together at the same level: a+b, comma-separated.
    #[arg(long, value_delimiter = ',', value_name = "A+B")]
    pub pairs: Option<Vec<String>>,
    /// Levels per effect (default 5), spread over the effect's severity range.
    #[arg(long, value_name = "N")]
    pub levels: Option<usize>,
    /// Fault seeds, comma-separated (default 1): every cell runs once per seed.
    #[arg(long, value_delimiter = ',', value_name = "S")]
    pub seeds: Option<Vec<u64>>,
    /// A frame fails above this score (E_t + E_q; default 0.1).
    #[arg(long)]
    pub tolerance: Option<f64>,
    /// Breaking point: the lowest level whose failure rate is at least this (default 0.5).
    #[arg(long)]
    pub threshold: Option<f64>,
    /// Time-out of one SUT run (one cell, live or batch), seconds (default 600).
    #[arg(long, value_name = "S")]
    pub timeout_s: Option<f64>,
    /// Output folder: report.json, report.md, frames.jsonl, plots/ (or the shard file).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Run only shard K of N (0-based K, as `apply --shard`: cells with index % N == K) and write
    /// OUT/shard-K-of-N.json; join with `faultcam sweep merge`.
    #[arg(long, value_name = "K/N")]
    pub shard: Option<String>,
    /// Cells run at the same time (default 1). Results do not depend on it.
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Keep every cell's folder (images, SUT output, stderr) under OUT/work/.
    #[arg(long)]
    pub keep_work: bool,
    /// Print the resolved plan (grids and cells) and exit.
    #[arg(long)]
    pub dry_run: bool,
}

#[derive(clap::Subcommand, Debug)]
pub enum Merge {
    /// Join shard results (files or folders holding shard-*.json) into one report.
    Merge {
        /// Shard files or folders.
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        /// Output folder for the report.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
    },
}

/// Parse a 0-based `K/N` (as `faultcam apply --shard`).
pub fn parse_shard(s: &str) -> Result<(usize, usize), String> {
    let err = || format!("--shard '{s}' is not accepted; expected K/N with 0 <= K < N (0-based, as apply), e.g. 0/4");
    let (k, n) = s.split_once('/').ok_or_else(err)?;
    let (k, n): (usize, usize) = (k.trim().parse().map_err(|_| err())?, n.trim().parse().map_err(|_| err())?);
    if n == 0 || k >= n {
        return Err(err());
    }
    Ok((k, n))
}

fn write_report(out: &Path, plan: &serde_json::Value, cells: &[faultcam::sweep::CellResult]) -> anyhow::Result<()> {
    let r = report::build(plan, cells).map_err(anyhow::Error::msg)?;
    report::write(out, &r, cells).map_err(anyhow::Error::msg)?;
    println!("{}", report::markdown(&r).split("## Curves").next().unwrap_or("").trim_end());
    eprintln!("faultcam sweep: wrote {}", out.join("report.md").display());
    Ok(())
}

pub fn run(args: Args) -> anyhow::Result<u8> {
    if let Some(Merge::Merge { inputs, out }) = &args.merge {
        let (plan, cells) = merge_shards(inputs).map_err(anyhow::Error::msg)?;
        write_report(out, &plan, &cells)?;
        return Ok(0);
    }
    let file = match &args.config {
        Some(p) => Settings::load(p).map_err(anyhow::Error::msg)?,
        None => Settings::default(),
    };
    let mut pairs = Vec::new();
    for p in args.pairs.iter().flatten() {
        let Some((a, b)) = p.split_once('+') else { bail!("--pairs '{p}' is not accepted; expected a+b") };
        pairs.push((a.to_string(), b.to_string()));
    }
    let path_str = |p: &Option<PathBuf>| p.as_ref().map(|p| p.display().to_string());
    let cli = Settings {
        source: args.source.clone(),
        poses: path_str(&args.poses),
        sut: args.sut.clone(),
        timeout_s: args.timeout_s,
        levels: args.levels,
        seeds: args.seeds.clone(),
        tolerance: args.tolerance,
        threshold: args.threshold,
        effects: args.effects.clone(),
        campaign: path_str(&args.campaign),
        grids: Vec::new(),
        pairs,
        live: args.live.then_some(true),
        sink: args.sink.clone(),
        sut_report: args.sut_report.clone(),
        frame_timeout_s: args.frame_timeout_s,
        startup_s: args.startup_s,
        fps: args.fps,
    };
    let mut settings = file.overlay(cli);
    if args.effects.is_some() || args.campaign.is_some() {
        settings.grids.clear();
    }
    if args.effects.is_some() {
        settings.campaign = None;
    }
    let plan = settings.resolve().map_err(anyhow::Error::msg)?;
    // The source must end: a sweep renders it once per cell.
    if plan.source.starts_with("synth:") {
        let c = faultcam::source::synth::SynthConfig::from_uri(&plan.source)?;
        if c.frames == 0 {
            bail!("source {}: frames=0 is endless; give frames=N for a sweep", plan.source);
        }
    } else if plan.source.contains("loop=") {
        bail!("source {}: a looping source never ends; drop loop= for a sweep", plan.source);
    }
    if let Some(l) = &plan.live
        && args.jobs > 1
    {
        // Cells in parallel need a report channel and a sink of their own.
        let own_sink = l.sink.starts_with("files:") && (l.sink.contains("{in_dir}") || l.sink.contains("{cell_dir}"));
        let own_report = match faultcam::sweep::live::ReportSpec::parse(&l.report) {
            Ok(faultcam::sweep::live::ReportSpec::Stdout) => true,
            Ok(faultcam::sweep::live::ReportSpec::Udp(a)) => a.port() == 0,
            _ => false,
        };
        if !(own_sink && own_report) {
            bail!(
                "--jobs {} with a live sweep needs a sink and a report channel per cell (a files: sink under \
                 {{in_dir}} or {{cell_dir}}, and stdout or udp:HOST:0); sink '{}' and sut_report '{}' are \
                 shared: use --jobs 1",
                args.jobs,
                l.sink,
                l.report
            );
        }
    }
    let cells = plan.cells();
    if args.dry_run {
        println!("{}", serde_json::to_string_pretty(&plan)?);
        println!("{} cells", cells.len());
        return Ok(0);
    }
    let Some(out) = args.out.clone() else { bail!("--out DIR is required (the report's folder)") };
    let shard = match &args.shard {
        Some(s) => parse_shard(s).map_err(anyhow::Error::msg)?,
        None => (0, 1),
    };
    let plan_json = serde_json::to_value(&plan)?;
    std::fs::create_dir_all(&out)?;
    let work = out.join("work");
    let opts = RunOptions { keep: args.keep_work, verbose: true };
    let results = run_cells(&plan, shard, args.jobs, &work, &opts);
    if !args.keep_work {
        let _ = std::fs::remove_dir(&work);
    }
    if args.shard.is_some() {
        let path = out.join(format!("shard-{}-of-{}.json", shard.0, shard.1));
        let f = ShardFile { plan: plan_json, shard: [shard.0, shard.1], cells: results };
        std::fs::write(&path, serde_json::to_vec(&f)?)?;
        eprintln!("faultcam sweep: wrote {} ({} cells)", path.display(), f.cells.len());
        return Ok(0);
    }
    write_report(&out, &plan_json, &results)?;
    Ok(0)
}
