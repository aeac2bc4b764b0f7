//! `faultcam run`: stream frames from a source URI through the fault chain into a sink URI on
//! the threaded pipeline ([`faultcam::pipeline`]): timed replay (`--fps`, `--realtime`), a
//! latency budget with an overrun policy, a campaign timeline from the `--faults` file, serial
//! triggers (`--trigger`) or triggers replayed from a ground-truth log (`--replay-triggers`).
//! Every input frame gets a ground-truth record; SIGINT/SIGTERM stop the stream cleanly and the
//! summary is still written.

use anyhow::Context;
use faultcam::pipeline::{self, OverrunPolicy, Pacing, PipelineOptions, StopReason, Summary};
use faultcam::schedule::{self, Campaign, TriggerOptions};
use faultcam::sink;
use faultcam::source;
use faultcam::{Chain, FaultConfig};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

/// Arguments of `faultcam run`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Source URI: `files:DIR`, `synth:`, `gst:PIPELINE ! appsink`, `aravis:CAMERA`, `v4l2:/dev/videoN`
    /// (options after `?`, see README "Sources and sinks").
    #[arg(long, required_unless_present = "check")]
    pub source: Option<String>,
    /// Sink URI: `files:DIR`, `gst:appsrc ! PIPELINE`, `v4l2:/dev/videoN`, `null:`.
    #[arg(long, required_unless_present = "check")]
    pub sink: Option<String>,
    /// Fault configuration or campaign (TOML: `[[effects]]`, optional `[[events]]`, `[triggers]`).
    #[arg(long)]
    pub faults: PathBuf,
    /// Ground-truth log (JSON Lines). Default: DIR/groundtruth.jsonl for a `files:DIR` sink,
    /// else ./groundtruth.jsonl.
    #[arg(long)]
    pub log: Option<PathBuf>,
    /// Stop after N input frames (skipped inputs do not count).
    #[arg(long)]
    pub frames: Option<u64>,
    /// Stop reading after this long: seconds, or a number with s, m or h (`90`, `90s`, `10m`).
    #[arg(long, value_parser = parse_duration)]
    pub duration: Option<Duration>,
    /// Campaign seed (overrides the config's `seed`).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Release frames at this rate (frames per second), e.g. to replay a folder at camera speed.
    #[arg(long, conflicts_with = "realtime")]
    pub fps: Option<f64>,
    /// Release frames at their recorded timestamps (`pts_ns`), relative to the first frame.
    #[arg(long)]
    pub realtime: bool,
    /// Capture-to-sink latency budget per frame, in milliseconds.
    #[arg(long)]
    pub budget_ms: Option<f64>,
    /// What to do with frames that miss the budget: pass (deliver late), degrade (run a cheaper
    /// chain while frames are late), drop (drop frames that cannot make it).
    #[arg(long, default_value = "pass", value_parser = parse_overrun)]
    pub overrun: OverrunPolicy,
    /// Treat the source as live (it produces frames whether or not the pipeline is ready): with
    /// `--overrun drop` a full pipeline drops at capture. Implied for `aravis:` and `v4l2:`.
    #[arg(long)]
    pub live: bool,
    /// Serial trigger port, `DEVICE[?baud=N]` (default 115200 baud); overrides `[triggers] port`.
    #[arg(long, conflicts_with = "replay_triggers")]
    pub trigger: Option<String>,
    /// Replay the triggers recorded in this ground-truth log at the frames where they took
    /// effect (no serial port): with the same campaign, seed and input the output is identical.
    #[arg(long)]
    pub replay_triggers: Option<PathBuf>,
    /// Worker threads for the effects (rayon). Default: all cores. The output does not depend on it.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Frames queued between stages (source → chain, chain → sink).
    #[arg(long, default_value_t = 2)]
    pub queue: usize,
    /// Print a progress line (counts, latency) every N seconds.
    #[arg(long)]
    pub progress_s: Option<f64>,
    /// Validate the fault configuration and campaign (every problem with its line), then exit.
    #[arg(long)]
    pub check: bool,
    /// Write per-pixel fault masks of every delivered frame into this folder: STEM.labels.png, a
    /// 16-bit PNG where bit k marks the pixels the k-th applied effect of the frame record
    /// changed (see README "Fault masks"); named in each frame record's `masks` field.
    #[arg(long)]
    pub masks: Option<PathBuf>,
    /// With --masks, also write each effect's signed change as a 32-bit float TIFF
    /// (STEM.delta-KK-EFFECT.tiff, in DN).
    #[arg(long, requires = "masks")]
    pub mask_deltas: bool,
    /// Free-space floor in MB for the folders written to (the log's, a `files:` sink's, the
    /// masks'): checked before each frame is written; see --low-disk.
    #[arg(long, value_name = "N")]
    pub min_free_mb: Option<u64>,
    /// Under the --min-free-mb floor: stop (end the run cleanly, with its summary) or drop (do
    /// not write the frame, log it as failed with a `low disk` error, count it, keep going).
    #[arg(long, default_value = "stop", value_parser = parse_low_disk, requires = "min_free_mb")]
    pub low_disk: faultcam::gtlog::LowDiskPolicy,
}

fn parse_low_disk(s: &str) -> Result<faultcam::gtlog::LowDiskPolicy, String> {
    s.parse()
}

fn parse_overrun(s: &str) -> Result<OverrunPolicy, String> {
    s.parse::<OverrunPolicy>().map_err(|e| e.to_string())
}

/// `90`, `90s`, `1.5m`, `2h` → a duration (positive, at most 100 days).
pub fn parse_duration(s: &str) -> Result<Duration, String> {
    let t = s.trim();
    let (num, scale) = match t.char_indices().last() {
        Some((i, 's')) => (&t[..i], 1.0),
        Some((i, 'm')) => (&t[..i], 60.0),
        Some((i, 'h')) => (&t[..i], 3600.0),
        _ => (t, 1.0),
    };
    match num.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 && v * scale <= 8.64e6 => Ok(Duration::from_secs_f64(v * scale)),
        _ => Err(format!(
            "'{s}' is not accepted; accepted: a positive duration up to 100 days, as seconds or with s, m, h (e.g. 90, 90s, 10m, 2h)"
        )),
    }
}

/// `DEVICE[?baud=N]` → (device, baud).
pub fn parse_trigger_port(s: &str) -> anyhow::Result<(String, Option<u32>)> {
    let (dev, query) = match s.split_once('?') {
        Some((d, q)) => (d, q),
        None => (s, ""),
    };
    if dev.is_empty() {
        anyhow::bail!("--trigger '{s}': expected a serial device such as /dev/ttyACM0[?baud=115200]");
    }
    let mut baud = None;
    for kv in query.split('&').filter(|kv| !kv.is_empty()) {
        match kv.split_once('=') {
            Some(("baud", v)) => match v.parse::<u32>() {
                Ok(b) if (50..=4_000_000).contains(&b) => baud = Some(b),
                _ => anyhow::bail!("--trigger '{s}': baud={v} is not accepted; accepted: an integer 50..=4000000"),
            },
            _ => anyhow::bail!("--trigger '{s}': unknown option '{kv}'; accepted: baud"),
        }
    }
    Ok((dev.to_string(), baud))
}

/// Default log path for a sink URI.
pub fn default_log(sink_uri: &str) -> PathBuf {
    let (scheme, body, _) = source::split_uri(sink_uri);
    if scheme == "files" && !body.is_empty() {
        Path::new(body).join("groundtruth.jsonl")
    } else {
        PathBuf::from("groundtruth.jsonl")
    }
}

/// The one-line summary printed at the end.
pub fn summary_line(s: &Summary) -> String {
    let budget = match s.budget_ms {
        Some(b) => format!(
            "; budget {b} ms ({}): {} misses ({} late, {} dropped), {} degraded",
            s.overrun_policy, s.budget_misses, s.late, s.dropped_overrun, s.degraded
        ),
        None => String::new(),
    };
    format!(
        "{} frames in, {} out, {} dropped ({} by faults, {} by overrun), {} failed, {} inputs skipped, {} unaccounted; \
         latency p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms{budget}; {:.1} s, {:.1} fps in; stopped by {}",
        s.frames_in,
        s.delivered,
        s.dropped_by_fault + s.dropped_overrun,
        s.dropped_by_fault,
        s.dropped_overrun,
        s.failed,
        s.skipped_inputs,
        s.unaccounted,
        s.latency.p50_ms,
        s.latency.p99_ms,
        s.latency.max_ms,
        s.wall_s,
        s.fps_in,
        s.stopped_by.name()
    )
}

fn check(args: &Args, cfg: &FaultConfig) -> anyhow::Result<u8> {
    let campaign = Campaign::from_config(cfg)?;
    faultcam::masks::MaskConfig::from_config(cfg).with_context(|| format!("{}", args.faults.display()))?;
    let effects: Vec<String> = cfg.effects.iter().map(|e| e.name.clone()).collect();
    println!(
        "{}: ok: {} effects ({}), {} events, trigger names: {}",
        args.faults.display(),
        effects.len(),
        effects.join(", "),
        campaign.events.len(),
        if campaign.by_name.is_empty() {
            "none".to_string()
        } else {
            campaign.by_name.keys().cloned().collect::<Vec<_>>().join(", ")
        }
    );
    Ok(0)
}

pub fn run(args: Args) -> anyhow::Result<u8> {
    let mut cfg = FaultConfig::load(&args.faults)?;
    if let Some(s) = args.seed {
        cfg.seed = s;
    }
    if args.check {
        return check(&args, &cfg);
    }
    let (Some(source_uri), Some(sink_uri)) = (args.source.as_deref(), args.sink.as_deref()) else {
        anyhow::bail!("--source and --sink are required (unless --check)");
    };
    if let Some(t) = args.threads {
        if !(1..=1024).contains(&t) {
            anyhow::bail!("--threads {t} is out of range; accepted: 1..=1024");
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .thread_name(|i| format!("faultcam-fx-{i}"))
            .build_global()
            .context("cannot start the effect worker threads")?;
    }
    let chain = Chain::from_config(&cfg).with_context(|| format!("{}", args.faults.display()))?;
    let trigger_opts = match &args.trigger {
        Some(t) => {
            let (dev, baud) = parse_trigger_port(t)?;
            TriggerOptions { serial: Some(dev), baud, ..Default::default() }
        }
        None => TriggerOptions { replay: args.replay_triggers.clone(), ..Default::default() },
    };
    // The whole campaign is validated (and the trigger port opened) before the stream starts.
    let controllers = schedule::controllers_from_config(&cfg, &trigger_opts)?;

    let src = source::open(source_uri)?;
    let snk = sink::open(sink_uri)?;
    let (scheme, _, _) = source::split_uri(source_uri);
    let live = args.live || matches!(scheme, "aravis" | "v4l2");
    let pacing = match (args.fps, args.realtime) {
        (Some(f), _) => Pacing::Fps(f),
        (None, true) => Pacing::Timestamps,
        (None, false) => Pacing::Free,
    };
    let log_path = args.log.clone().unwrap_or_else(|| default_log(sink_uri));
    // Masks: --masks DIR, else the config's [masks] section (a relative `dir`, default "masks",
    // is taken relative to the ground-truth log's folder).
    let mask_settings = match &args.masks {
        Some(dir) => Some(pipeline::MaskSettings {
            dir: dir.clone(),
            opts: faultcam::masks::MaskOptions { deltas: args.mask_deltas },
        }),
        None => faultcam::masks::MaskConfig::from_config(&cfg)
            .with_context(|| format!("{}", args.faults.display()))?
            .map(|mc| {
                let dir = mc.dir.unwrap_or_else(|| PathBuf::from("masks"));
                let dir = if dir.is_absolute() { dir } else { log_path.parent().unwrap_or(Path::new("")).join(dir) };
                pipeline::MaskSettings { dir, opts: mc.options }
            }),
    };
    let stop = Arc::new(AtomicBool::new(false));
    // First SIGINT/SIGTERM: stop cleanly (finish the frames in flight, write the summary);
    // a second one while stopping ends the process at once.
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(sig, 130, stop.clone())
            .context("cannot install the signal handler")?;
        signal_hook::flag::register(sig, stop.clone()).context("cannot install the signal handler")?;
    }
    let opts = PipelineOptions {
        pacing,
        budget_ms: args.budget_ms,
        overrun: args.overrun,
        realtime_source: live,
        queue_depth: args.queue,
        max_frames: args.frames,
        duration: args.duration,
        stop,
        progress_every: match args.progress_s {
            Some(p) if p.is_finite() && p > 0.0 => Some(Duration::from_secs_f64(p)),
            Some(p) => anyhow::bail!("--progress-s {p} is not accepted; accepted: a positive number of seconds"),
            None => None,
        },
        masks: mask_settings.clone(),
        disk_floor: match args.min_free_mb {
            Some(n) if n > 1 << 30 => anyhow::bail!("--min-free-mb {n} is not accepted; accepted: 0..=1073741824 (MB)"),
            Some(n) => {
                let mut dirs = vec![
                    log_path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).to_path_buf(),
                ];
                let (scheme, body, _) = source::split_uri(sink_uri);
                if scheme == "files" && !body.is_empty() {
                    dirs.push(PathBuf::from(body));
                }
                if let Some(m) = &mask_settings {
                    dirs.push(m.dir.clone());
                }
                Some(faultcam::gtlog::DiskFloor { min_free_mb: n, dirs, policy: args.low_disk })
            }
            None => None,
        },
        ..Default::default()
    };
    opts.validate()?;
    if let Some(m) = &mask_settings {
        std::fs::create_dir_all(&m.dir)
            .with_context(|| format!("cannot create the masks folder {}", m.dir.display()))?;
    }

    let mut log = faultcam::gtlog::GroundTruthLog::create(&log_path)
        .with_context(|| format!("cannot create {}", log_path.display()))?;
    eprintln!("faultcam: source {}", src.describe());
    eprintln!("faultcam: sink {}", snk.describe());
    let threads = args.threads.unwrap_or_else(rayon::current_num_threads);
    log.event(&serde_json::json!({
        "event": "start",
        "source": src.describe(),
        "sink": snk.describe(),
        "faults": args.faults.display().to_string(),
        "seed": cfg.seed,
        "effects": chain.entries().iter().map(|e| e.name()).collect::<Vec<_>>(),
        "pacing": match pacing {
            Pacing::Free => "free".to_string(),
            Pacing::Fps(f) => format!("fps {f}"),
            Pacing::Timestamps => "timestamps".to_string(),
        },
        "budget_ms": args.budget_ms,
        "overrun": args.overrun.name(),
        "live": live,
        "threads": threads,
        "trigger": args.trigger,
        "replay_triggers": args.replay_triggers.as_ref().map(|p| p.display().to_string()),
        "masks": mask_settings.as_ref().map(|m| m.dir.display().to_string()),
    }))?;
    let summary = pipeline::run(src, snk, chain, controllers, &opts, &mut log)?;
    drop(log);
    eprint!("{summary}");
    eprintln!("faultcam: {}; log {}", summary_line(&summary), log_path.display());
    if let Some(e) = &summary.error {
        anyhow::bail!("{e} (log {})", log_path.display());
    }
    if summary.unaccounted != 0 {
        anyhow::bail!(
            "{} input frames are not accounted for in the log (a bug); log {}",
            summary.unaccounted,
            log_path.display()
        );
    }
    if summary.stopped_by == StopReason::Signal {
        eprintln!("faultcam: stopped by signal; the log and summary are complete");
    }
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_and_trigger_ports_parse() {
        assert_eq!(parse_duration("90").unwrap(), Duration::from_secs(90));
        assert_eq!(parse_duration("1.5m").unwrap(), Duration::from_secs(90));
        assert_eq!(parse_duration("2h").unwrap(), Duration::from_secs(7200));
        assert!(parse_duration("0").unwrap_err().contains("accepted"));
        assert!(parse_duration("ten").is_err());
        assert_eq!(parse_trigger_port("/dev/ttyACM0").unwrap(), ("/dev/ttyACM0".to_string(), None));
        assert_eq!(parse_trigger_port("/dev/pts/3?baud=9600").unwrap(), ("/dev/pts/3".to_string(), Some(9600)));
        let e = parse_trigger_port("/dev/x?baud=7").unwrap_err().to_string();
        assert!(e.contains("baud=7") && e.contains("50..=4000000"), "{e}");
        assert!(parse_trigger_port("/dev/x?parity=odd").unwrap_err().to_string().contains("accepted: baud"));
    }
}
