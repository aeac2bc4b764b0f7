//! `faultcam apply`: apply a fault config to every image of a folder (batch, shardable).
//!
//! - Inputs are the folder's files sorted by name; a file's `seq` is its index in that full
//!   listing, so the per-frame generators (seeded by campaign seed, seq and effect index) are
//!   the same whether the folder is processed at once or in shards.
//! - `--shard K/N` (0-based: K = 0..N-1, e.g. a Kubernetes indexed job's completion index or
//!   `$SLURM_ARRAY_TASK_ID` with `--array=0-(N-1)`) processes the files whose index mod N == K.
//!   The union of the N shards' outputs equals the unsharded output byte for byte. Effects with
//!   state across frames (frame_freeze, frame_delay, reorder, ...) see only their shard's frames.
//! - `--threads N`: images are decoded and encoded N at a time and effects use N threads
//!   internally; the chain itself sees the frames in file order, so the output bytes do not
//!   depend on N.
//! - `--masks` (`--mask-deltas`): per-pixel fault masks of every written frame in OUT/masks/
//!   (see `faultcam::masks`), named in the frame records' `masks` field. The chain runs serially
//!   anyway; masks are written right after each frame's pass so one recorder serves the run.
//! - Outputs keep the input file name with the output format's extension. Corrupt files, files
//!   that are not images and files whose size or pixel format differs from the first readable
//!   file of the full listing are logged as `skip` records and left out.

use anyhow::{Context, bail};
use faultcam::faults::Outcome;
use faultcam::frame::{Frame, PixelFormat};
use faultcam::gtlog::{DiskFloor, FrameRecord, FrameStatus, GroundTruthLog, LowDiskPolicy};
use faultcam::masks::{MaskOptions, MaskRecord, MaskRecorder, mask_stem};
use faultcam::sink::files::{ImageFormat, WriteOptions, output_name, write_image};
use faultcam::source::SourceError;
use faultcam::source::files::{self, Item, Shape};
use faultcam::{Chain, FaultConfig, FrameReport};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `faultcam apply`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Input folder (PNG, JPEG, PGM/PPM, TIFF; 8/16-bit grey or RGB).
    #[arg(long = "in", value_name = "DIR")]
    pub input: PathBuf,
    /// Output folder (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Fault configuration (TOML; see `faultcam effects`).
    #[arg(long, value_name = "FILE")]
    pub faults: PathBuf,
    /// Campaign seed (overrides the config's `seed`).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Process only shard K of N (0-based K: 0..N-1): the files whose index mod N == K.
    #[arg(long, value_name = "K/N")]
    pub shard: Option<String>,
    /// Worker threads (default: all cores). The output does not depend on it.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Ground-truth log. Default: OUT/groundtruth.jsonl, or OUT/groundtruth.shard-K-of-N.jsonl.
    #[arg(long, value_name = "FILE")]
    pub log: Option<PathBuf>,
    /// Output image format: png (default, 8/16-bit), pgm (PGM/PPM), tiff, jpg (8-bit only).
    #[arg(long, default_value = "png")]
    pub format: String,
    /// JPEG quality for --format jpg (1..=100).
    #[arg(long, default_value_t = 95, value_parser = clap::value_parser!(u8).range(1..=100))]
    pub quality: u8,
    /// Write per-pixel fault masks to OUT/masks/: STEM.labels.png, a 16-bit PNG where bit k marks
    /// the pixels the k-th applied effect changed (the frame record's `effects[k]`).
    #[arg(long)]
    pub masks: bool,
    /// With the masks, write per-effect signed changes as 32-bit float TIFF
    /// (OUT/masks/STEM.delta-KK-EFFECT.tiff, in DN); implies --masks.
    #[arg(long)]
    pub mask_deltas: bool,
    /// Free-space floor in MB for the output and log folders, checked before each batch is
    /// written; see --low-disk.
    #[arg(long, value_name = "N")]
    pub min_free_mb: Option<u64>,
    /// Under the --min-free-mb floor: stop (end cleanly with the summary) or drop (do not write
    /// the images, log them as failed with a `low disk` error, count them, keep going).
    #[arg(long, default_value = "stop", value_parser = parse_low_disk, requires = "min_free_mb")]
    pub low_disk: LowDiskPolicy,
}

fn parse_low_disk(s: &str) -> Result<LowDiskPolicy, String> {
    s.parse()
}

/// Per-slot work of one batch.
struct Slot {
    frame: Frame,
    scratch: Vec<u8>,
    /// Index into the listing.
    index: usize,
    decoded: Result<Shape, SourceError>,
    outcome: Option<Outcome>,
    /// Output path once written, or the error.
    written: Option<Result<PathBuf, String>>,
    report: FrameReport,
    chain_error: Option<String>,
    /// Masks written for this frame (with --masks).
    masks: Option<Result<MaskRecord, String>>,
}

impl Slot {
    fn new() -> Slot {
        Slot {
            frame: Frame::empty(),
            scratch: Vec::new(),
            index: 0,
            decoded: Ok(Shape { width: 0, height: 0, format: PixelFormat::Mono8 }),
            outcome: None,
            written: None,
            report: FrameReport::default(),
            chain_error: None,
            masks: None,
        }
    }
}

fn same_dir(a: &Path, b: &Path) -> bool {
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

pub fn run(args: Args) -> anyhow::Result<u8> {
    let mut cfg = FaultConfig::load(&args.faults)?;
    if let Some(s) = args.seed {
        cfg.seed = s;
    }
    let mut chain = Chain::from_config(&cfg).with_context(|| format!("{}", args.faults.display()))?;
    let shard = args.shard.as_deref().map(files::parse_shard).transpose().map_err(anyhow::Error::msg)?;
    let format = ImageFormat::parse(&args.format)
        .with_context(|| format!("--format {} is not accepted; expected png, pgm, tiff or jpg", args.format))?;
    let wopts = WriteOptions { format, quality: args.quality, ..WriteOptions::default() };
    let threads = args.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())).max(1);

    if !args.input.is_dir() {
        bail!("--in {}: not a folder", args.input.display());
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    if same_dir(&args.input, &args.out) {
        bail!("--out {} is the input folder; choose another folder so inputs are not overwritten", args.out.display());
    }
    let items = files::list(&args.input)?;
    let reference = files::reference_shape(&items);
    let out_fmt = reference.map_or(PixelFormat::Mono8, |s| s.format);
    let ext = format.extension(out_fmt);
    // Two inputs must not map to the same output file (checked on the full listing, so every
    // shard agrees).
    let mut names: Vec<(String, &str)> =
        items.iter().filter(|i| i.is_image()).map(|i| (output_name(Some(&i.name), 0, ext), i.name.as_str())).collect();
    names.sort();
    if let Some(w) = names.windows(2).find(|w| w[0].0 == w[1].0) {
        bail!("inputs {} and {} would both be written to {}; rename one", w[0].1, w[1].1, w[0].0);
    }
    let indices: Vec<usize> = match shard {
        Some((k, n)) => (0..items.len()).filter(|i| *i as u64 % n == k).collect(),
        None => (0..items.len()).collect(),
    };
    let log_path = args.log.clone().unwrap_or_else(|| match shard {
        Some((k, n)) => args.out.join(format!("groundtruth.shard-{k}-of-{n}.jsonl")),
        None => args.out.join("groundtruth.jsonl"),
    });
    let mut log = GroundTruthLog::create(&log_path).with_context(|| format!("cannot create {}", log_path.display()))?;
    let floor = match args.min_free_mb {
        Some(n) if n > 1 << 30 => bail!("--min-free-mb {n} is not accepted; accepted: 0..=1073741824 (MB)"),
        Some(n) => {
            let log_dir = log_path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
            Some(DiskFloor {
                min_free_mb: n,
                dirs: vec![args.out.clone(), log_dir.to_path_buf()],
                policy: args.low_disk,
            })
        }
        None => None,
    };
    log.event(&serde_json::json!({
        "event": "start",
        "input": args.input.display().to_string(),
        "output": args.out.display().to_string(),
        "faults": args.faults.display().to_string(),
        "seed": cfg.seed,
        "shard": shard.map(|(k, n)| format!("{k}/{n}")),
        "files": items.len(),
        "reference": reference.map(|s| s.to_string()),
        "effects": chain.entries().iter().map(|e| e.name()).collect::<Vec<_>>(),
        "masks": (args.masks || args.mask_deltas).then(|| args.out.join("masks").display().to_string()),
    }))?;

    let mask_dir = args.out.join("masks");
    // allocation: once per run (buffers sized on the first frame)
    let mut recorder =
        (args.masks || args.mask_deltas).then(|| MaskRecorder::new(MaskOptions { deltas: args.mask_deltas }));

    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().context("cannot start worker threads")?;
    let bar = if std::io::stderr().is_terminal() {
        let b = ProgressBar::new(indices.len() as u64);
        b.set_style(
            ProgressStyle::with_template("{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} {per_sec} eta {eta}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        b
    } else {
        ProgressBar::hidden()
    };

    let t0 = Instant::now();
    let batch = (2 * threads).max(2);
    // allocation: one slot (frame and scratch buffers) per batch position, reused
    let mut slots: Vec<Slot> = (0..batch).map(|_| Slot::new()).collect();
    let (mut delivered, mut dropped, mut failed, mut skipped) = (0u64, 0u64, 0u64, 0u64);
    let mut dropped_low_disk = 0u64;
    let mut unlogged = 0u64;
    // A log write that failed (full disk): the run stops and only the summary is attempted.
    let mut log_error: Option<String> = None;
    let mut first_error: Option<String> = None;
    'batches: for chunk in indices.chunks(batch) {
        let slots = &mut slots[..chunk.len()];
        for (s, &i) in slots.iter_mut().zip(chunk) {
            s.index = i;
            s.outcome = None;
            s.written = None;
            s.chain_error = None;
            s.masks = None;
        }
        // 1. Decode in parallel.
        pool.install(|| {
            slots.par_iter_mut().for_each(|s| {
                s.decoded = files::decode_into(&items[s.index], reference, &mut s.frame, &mut s.scratch);
            })
        });
        // 2. The chain, in file order (effects parallelise inside).
        pool.install(|| {
            for s in slots.iter_mut() {
                if s.decoded.is_err() {
                    continue;
                }
                s.frame.seq = s.index as u64;
                s.frame.pts_ns = 0;
                let result = match recorder.as_mut() {
                    Some(rec) => chain.apply_recording(&mut s.frame, &mut s.report, rec),
                    None => chain.apply(&mut s.frame, &mut s.report),
                };
                match result {
                    Ok(o) => s.outcome = Some(o),
                    Err(e) => s.chain_error = Some(e.to_string()),
                }
                // Masks describe this pass of the chain: write them before the next frame's.
                if let (Some(rec), Some(Outcome::Keep)) = (recorder.as_mut(), s.outcome) {
                    let seq = s.frame.seq;
                    let stem = mask_stem(items.get(seq as usize).map(|i| i.name.as_str()), seq);
                    s.masks = Some(rec.write(&mask_dir, &stem).map_err(|e| e.to_string()));
                }
            }
        });
        // 3. Encode in parallel (unless free space is under the floor).
        let low = floor.as_ref().and_then(|f| f.low());
        if let Some(why) = &low {
            for s in slots.iter_mut().filter(|s| s.outcome == Some(Outcome::Keep)) {
                s.written = Some(Err(why.clone()));
                s.outcome = None;
            }
        }
        let out_dir = &args.out;
        pool.install(|| {
            slots.par_iter_mut().filter(|s| s.outcome == Some(Outcome::Keep)).for_each(|s| {
                // A temporal effect may hand out another input's frame: name by the frame's seq.
                let seq = s.frame.seq;
                let name = items.get(seq as usize).map(|i| i.name.as_str());
                let path = out_dir.join(output_name(name, seq, format.extension(s.frame.format)));
                s.written = Some(write_image(&path, &s.frame, &wopts, &mut s.scratch).map(|_| path));
            })
        });
        // 4. Log in file order.
        for s in slots.iter() {
            let item: &Item = &items[s.index];
            if let Err(e) = &s.decoded {
                let reason = match e {
                    SourceError::BadInput { reason, .. } => reason.clone(),
                    other => other.to_string(),
                };
                eprintln!("faultcam: skip {}: {reason}", item.path.display());
                if let Err(e) = log.skip(&item.path.display().to_string(), &reason) {
                    log_error.get_or_insert(format!("cannot write the ground-truth log {}: {e}", log_path.display()));
                }
                skipped += 1;
                bar.inc(1);
                continue;
            }
            let mut rec = FrameRecord::from_report(s.index as u64, 0, &s.report);
            rec.input = Some(&item.name);
            let out_text;
            let err_text;
            if let Some(Ok(m)) = &s.masks {
                rec.masks = Some(m);
            }
            match (&s.chain_error, &s.written) {
                (Some(e), _) => {
                    rec.status = FrameStatus::Failed;
                    rec.error = Some(e);
                }
                (None, Some(Ok(p))) => {
                    out_text = p.display().to_string();
                    rec.output = Some(&out_text);
                    if let Some(Err(e)) = &s.masks {
                        rec.status = FrameStatus::Failed;
                        rec.error = Some(e);
                    }
                }
                (None, Some(Err(e))) => {
                    rec.status = FrameStatus::Failed;
                    err_text = e.clone();
                    rec.error = Some(&err_text);
                }
                (None, None) => {} // dropped by a fault: status set by from_report
            }
            if let Err(e) = log.frame(&rec) {
                unlogged += 1;
                log_error.get_or_insert(format!("cannot write the ground-truth log {}: {e}", log_path.display()));
            }
            match rec.status {
                FrameStatus::Delivered => delivered += 1,
                FrameStatus::Failed
                    if args.low_disk == LowDiskPolicy::Drop && rec.error.is_some_and(|e| e.starts_with("low disk")) =>
                {
                    failed += 1;
                    dropped_low_disk += 1;
                }
                FrameStatus::Failed => {
                    failed += 1;
                    first_error.get_or_insert_with(|| format!("{}: {}", item.path.display(), rec.error.unwrap_or("")));
                }
                _ => dropped += 1,
            }
            bar.inc(1);
        }
        if first_error.is_some() || log_error.is_some() {
            break 'batches;
        }
    }
    bar.finish_and_clear();
    let wall_s = t0.elapsed().as_secs_f64();
    let error = log_error.clone().or(first_error.clone());
    let summary_written = log
        .summary(&serde_json::json!({
            "frames_in": delivered + dropped + failed,
            "delivered": delivered,
            "dropped": dropped,
            "failed": failed,
            "dropped_low_disk": dropped_low_disk,
            "unlogged": unlogged,
            "skipped": skipped,
            "unaccounted": 0,
            "wall_s": wall_s,
            "threads": threads,
            "stopped_by": if error.is_some() { "error" } else { "end of input" },
            "error": error,
        }))
        .and_then(|_| log.flush());
    if let Err(e) = summary_written {
        eprintln!("faultcam: the summary could not be written to {}: {e}", log_path.display());
    }
    eprintln!(
        "faultcam: {} files{}: {delivered} written, {dropped} dropped by faults, {failed} failed, {skipped} skipped \
         ({wall_s:.2} s, {threads} threads); log {}",
        indices.len(),
        shard.map(|(k, n)| format!(" (shard {k}/{n})")).unwrap_or_default(),
        log_path.display()
    );
    if dropped_low_disk > 0 {
        eprintln!(
            "faultcam: {dropped_low_disk} images not written: free space under --min-free-mb (counted as failed)"
        );
    }
    if let Some(e) = log_error {
        bail!("{e}");
    }
    if let Some(e) = first_error {
        bail!("stopped at the first failure: {e}");
    }
    Ok(0)
}
