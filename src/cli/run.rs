//! `faultcam run`: stream frames from a source URI through the fault chain into a sink URI,
//! writing a ground-truth record for every input frame and a summary at the end.
//!
//! The loop here is sequential and untimed ([`sequential_loop`]); the threaded, timed
//! pipeline (`faultcam::pipeline`) replaces it behind the same arguments.

use anyhow::Context;
use faultcam::faults::Outcome;
use faultcam::gtlog::{FrameRecord, FrameStatus, GroundTruthLog};
use faultcam::sink::{self, Sink, SinkError};
use faultcam::source::{self, Source};
use faultcam::{Chain, FaultConfig, FrameReport};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `faultcam run`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Source URI: `files:DIR[?loop=true&fps=30]`, `synth:[?width=..&height=..&frames=..]`.
    #[arg(long)]
    pub source: String,
    /// Sink URI: `files:DIR[?format=png|pgm|jpg|tiff]`, `null:`.
    #[arg(long)]
    pub sink: String,
    /// Fault configuration (TOML; see `faultcam effects`).
    #[arg(long)]
    pub faults: PathBuf,
    /// Ground-truth log (JSON Lines). Default: DIR/groundtruth.jsonl for a `files:DIR` sink,
    /// else ./groundtruth.jsonl.
    #[arg(long)]
    pub log: Option<PathBuf>,
    /// Stop after N input frames (skipped inputs do not count).
    #[arg(long)]
    pub frames: Option<u64>,
    /// Campaign seed (overrides the config's `seed`).
    #[arg(long)]
    pub seed: Option<u64>,
}

/// What happened to the input, counted.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct Counts {
    /// Frames read from the source.
    pub frames_in: u64,
    /// Written to the sink.
    pub delivered: u64,
    /// Dropped by a fault effect.
    pub dropped: u64,
    /// Failed in the chain or the sink.
    pub failed: u64,
    /// Input items the source could not read (corrupt, wrong size, not an image).
    pub skipped: u64,
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

/// Source → chain → sink, one frame at a time, logging every input. Returns the counts and,
/// if the stream stopped on an error, that error (after the frame that hit it was logged).
pub fn sequential_loop(
    source: &mut dyn Source,
    chain: &mut Chain,
    sink: &mut dyn Sink,
    log: &mut GroundTruthLog,
    max_frames: Option<u64>,
) -> (Counts, Option<anyhow::Error>) {
    let mut c = Counts::default();
    let mut report = FrameReport::default();
    let result = (|| -> anyhow::Result<()> {
        while max_frames.is_none_or(|m| c.frames_in < m) {
            let mut frame = match source.next_frame() {
                Ok(Some(f)) => f,
                Ok(None) => break,
                Err(source::SourceError::BadInput { item, reason }) => {
                    c.skipped += 1;
                    eprintln!("faultcam: skip {item}: {reason}");
                    log.skip(&item, &reason)?;
                    continue;
                }
                Err(e) => return Err(e).context("source failed"),
            };
            c.frames_in += 1;
            let (seq, pts_ns) = (frame.seq, frame.pts_ns);
            let input = source.item_name();
            let mut rec_status = FrameStatus::Delivered;
            let mut error: Option<anyhow::Error> = None;
            let mut stop = false;
            match chain.apply(&mut frame, &mut report) {
                Ok(Outcome::Drop) => rec_status = FrameStatus::DroppedByFault,
                Ok(Outcome::Keep) => {
                    // A temporal effect may hand out another frame: keep the name only if it is ours.
                    let name = if frame.seq == seq { input } else { None };
                    match sink.write_frame(&frame, name) {
                        Ok(()) => {}
                        Err(SinkError::Closed { .. }) => {
                            rec_status = FrameStatus::Failed;
                            stop = true;
                        }
                        Err(e) => {
                            rec_status = FrameStatus::Failed;
                            error = Some(anyhow::Error::new(e).context(format!("frame {seq}: sink failed")));
                        }
                    }
                }
                Err(e) => {
                    rec_status = FrameStatus::Failed;
                    error = Some(anyhow::Error::new(e).context(format!("frame {seq}: fault chain failed")));
                }
            }
            let err_text = error.as_ref().map(|e| format!("{e:#}"));
            let mut rec = FrameRecord::from_report(seq, pts_ns, &report);
            rec.input = input;
            rec.status = rec_status;
            rec.output = if rec_status == FrameStatus::Delivered { sink.last_output() } else { None };
            rec.error = if stop { Some("sink closed") } else { err_text.as_deref() };
            log.frame(&rec)?;
            match rec_status {
                FrameStatus::Delivered => c.delivered += 1,
                FrameStatus::DroppedByFault | FrameStatus::DroppedOverrun => c.dropped += 1,
                FrameStatus::Failed => c.failed += 1,
            }
            source.recycle(frame);
            if let Some(e) = error {
                return Err(e);
            }
            if stop {
                break;
            }
        }
        Ok(())
    })();
    (c, result.err())
}

pub fn run(args: Args) -> anyhow::Result<u8> {
    let mut cfg = FaultConfig::load(&args.faults)?;
    if let Some(s) = args.seed {
        cfg.seed = s;
    }
    let mut chain = Chain::from_config(&cfg).with_context(|| format!("{}", args.faults.display()))?;
    let mut src = source::open(&args.source)?;
    let mut snk = sink::open(&args.sink)?;
    let log_path = args.log.clone().unwrap_or_else(|| default_log(&args.sink));
    let mut log = GroundTruthLog::create(&log_path).with_context(|| format!("cannot create {}", log_path.display()))?;
    eprintln!("faultcam: source {}", src.describe());
    eprintln!("faultcam: sink {}", snk.describe());
    log.event(&serde_json::json!({
        "event": "start",
        "source": src.describe(),
        "sink": snk.describe(),
        "faults": args.faults.display().to_string(),
        "seed": cfg.seed,
        "effects": chain.entries().iter().map(|e| e.name()).collect::<Vec<_>>(),
    }))?;
    let t0 = Instant::now();
    let (counts, err) = sequential_loop(src.as_mut(), &mut chain, snk.as_mut(), &mut log, args.frames);
    let finish = snk.finish();
    let wall_s = t0.elapsed().as_secs_f64();
    log.summary(&serde_json::json!({
        "frames_in": counts.frames_in,
        "delivered": counts.delivered,
        "dropped": counts.dropped,
        "failed": counts.failed,
        "skipped": counts.skipped,
        "wall_s": wall_s,
        "error": err.as_ref().map(|e| format!("{e:#}")),
    }))?;
    log.flush()?;
    eprintln!(
        "faultcam: {} frames in, {} out, {} dropped by faults, {} failed, {} inputs skipped ({:.2} s, {:.1} fps); log {}",
        counts.frames_in,
        counts.delivered,
        counts.dropped,
        counts.failed,
        counts.skipped,
        wall_s,
        counts.frames_in as f64 / wall_s.max(1e-9),
        log_path.display()
    );
    if let Some(e) = err {
        return Err(e);
    }
    finish?;
    Ok(0)
}
