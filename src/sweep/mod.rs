//! Robustness sweeps: run a pose stack under test (SUT) against every fault at a grid of
//! severities, join its poses with the truth and find where it breaks.
//!
//! A sweep is a list of independent **cells** ([`plan::Plan::cells`]): the clean baseline, each
//! effect at each level, optional pairs of effects at the same level, each with every seed.
//! A cell renders the source's frames (same frames in every cell), applies its faults (chain
//! seeded by the cell's seed), writes them as PNG into a folder and runs the batch SUT:
//! `sh -c 'CMD'` with `{in_dir}` (the images), `{out_file}` (where the SUT writes one pose per
//! image; without the placeholder its stdout is read) and `{camera}` (a JSON file with the
//! intrinsics `{"fx","fy","cx","cy"}` when the source knows them) and `{cell_dir}` (a scratch
//! folder of the cell) replaced by quoted paths; it runs in faultcam's working directory.
//! Output lines: JSON `{"file":"frame_000000.png","q":[w,x,y,z],"t":[x,y,z]}` or CSV
//! `file,qw,qx,qy,qz,x,y,z`, the [`crate::pose`] convention. The SUT runs in its own process
//! group with a time-out (the whole group is killed); a crash, a time-out or garbage lines are
//! recorded for the cell (frames without a pose fail) and the sweep goes on.
//!
//! Per frame: `E_t`, `E_q`, score = `E_t + E_q` ([`crate::pose`]); a frame **fails** when it
//! has no pose or its score is above `tolerance`. Frames a fault dropped, or without truth, are
//! not scored. See [`report`] for the statistics, the breaking point and the summary index.

pub mod live;
pub mod plan;
pub mod plot;
pub mod report;

use crate::faults::Outcome;
use crate::pose::{Truth, parse_pose_line, rotation_error, translation_error};
use crate::sink::files::{WriteOptions, output_name, write_image};
use plan::{Cell, Plan};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// What became of one frame of a cell.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameStatus {
    /// The SUT gave a pose (errors computed).
    Posed,
    /// The SUT gave no (valid) pose for the image: a failure.
    NoPose,
    /// A fault dropped the frame: not shown to the SUT, not scored.
    Dropped,
    /// The source has no pose truth for the frame: not scored.
    NoTruth,
}

/// One frame's result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameResult {
    pub file: String,
    pub status: FrameStatus,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub e_t: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub e_q: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score: Option<f64>,
    /// Live mode: what went wrong with this frame's report (time-out, garbage, unknown or
    /// duplicate seq, late report, SUT ended), `; `-joined.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub incident: Option<String>,
}

/// How the SUT run of a cell went (no paths or times: the same sweep gives the same record).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SutOutcome {
    /// `ok`, `exit status N`, `killed by signal N`, `timeout after S s`, `could not start: ..`.
    pub status: String,
    /// The output file was missing.
    pub no_output: bool,
    /// Output lines that are neither a pose nor blank/comment/header.
    pub garbage_lines: usize,
    /// The first of them: `line N: why`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_garbage: Option<String>,
    /// Poses for files that are not in the cell, and second poses for the same file (ignored).
    /// (Live: reports for an unknown seq.)
    pub unknown_files: usize,
    pub duplicates: usize,
    /// Live: reports that came after their frame's time-out (ignored).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub late: usize,
    /// A live run: garbage, unknown, duplicate and late reports are incidents of their frames
    /// ([`FrameResult::incident`]), the cell's own incident is only the SUT's status.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub live: bool,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

impl SutOutcome {
    /// True when something went wrong with the cell's SUT run (reported as an incident).
    pub fn incident(&self) -> bool {
        if self.live {
            return self.status != "ok";
        }
        self.status != "ok" || self.no_output || self.garbage_lines > 0 || self.unknown_files > 0 || self.duplicates > 0
    }
}

/// The result of one cell.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CellResult {
    pub cell: Cell,
    pub label: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sut: Option<SutOutcome>,
    /// The cell could not be prepared (source or fault error): no frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    pub frames: Vec<FrameResult>,
}

/// A shard's results (or all of them), as written to `shard-K-of-N.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ShardFile {
    /// The resolved plan (merge checks every shard has the same one).
    pub plan: serde_json::Value,
    /// 1-based K and N.
    pub shard: [usize; 2],
    pub cells: Vec<CellResult>,
}

/// Quote a path for `sh`.
pub fn shell_quote(p: &Path) -> String {
    format!("'{}'", p.display().to_string().replace('\'', "'\\''"))
}

/// Raw result of running the SUT once.
struct SutRun {
    status: String,
    output: Option<Vec<u8>>,
}

/// Run the SUT command for a cell folder; kills its process group on time-out.
fn run_sut(template: &str, dir: &Path, in_dir: &Path, camera: Option<&Path>, timeout: Duration) -> SutRun {
    use std::os::unix::process::{CommandExt, ExitStatusExt};
    let out_file = dir.join("poses.out");
    let stdout_file = dir.join("sut.stdout");
    let cam = camera.map(shell_quote).unwrap_or_else(|| "''".into());
    let cmd = template
        .replace("{in_dir}", &shell_quote(in_dir))
        .replace("{out_file}", &shell_quote(&out_file))
        .replace("{camera}", &cam)
        .replace("{cell_dir}", &shell_quote(dir));
    let to_stdout = !template.contains("{out_file}");
    let files =
        std::fs::File::create(&stdout_file).and_then(|o| Ok((o, std::fs::File::create(dir.join("sut.stderr"))?)));
    let (so, se) = match files {
        Ok(f) => f,
        Err(e) => return SutRun { status: format!("could not start: {e}"), output: None },
    };
    let child = std::process::Command::new("sh")
        .arg("-c")
        .arg(&cmd)
        .stdin(std::process::Stdio::null())
        .stdout(so)
        .stderr(se)
        .process_group(0)
        .spawn();
    let mut child = match child {
        Ok(c) => c,
        Err(e) => return SutRun { status: format!("could not start: {e}"), output: None },
    };
    let t0 = Instant::now();
    let mut nap = Duration::from_millis(2);
    let status = loop {
        match child.try_wait() {
            Ok(Some(st)) => {
                break match (st.code(), st.signal()) {
                    (Some(0), _) => "ok".to_string(),
                    (Some(c), _) => format!("exit status {c}"),
                    (None, Some(s)) => format!("killed by signal {s}"),
                    _ => "ended abnormally".to_string(),
                };
            }
            Ok(None) if t0.elapsed() >= timeout => {
                // SAFETY: kill(2) on the process group we created for the child.
                unsafe {
                    libc::kill(-(child.id() as i32), libc::SIGKILL);
                }
                let _ = child.wait();
                break format!("timeout after {} s", timeout.as_secs_f64());
            }
            Ok(None) => {
                std::thread::sleep(nap.min(timeout.saturating_sub(t0.elapsed())));
                nap = (nap * 2).min(Duration::from_millis(50));
            }
            Err(e) => break format!("could not wait: {e}"),
        }
    };
    let output = std::fs::read(if to_stdout { &stdout_file } else { &out_file }).ok();
    SutRun { status, output }
}

/// Parse SUT output into poses by file name, counting garbage, unknown and duplicate lines.
fn parse_output(
    bytes: &[u8],
    known: &BTreeMap<String, usize>,
    sut: &mut SutOutcome,
) -> BTreeMap<String, crate::pose::Pose> {
    let text = String::from_utf8_lossy(bytes);
    let mut poses = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        match parse_pose_line(line) {
            Ok(None) => {}
            Ok(Some(p)) => {
                if !known.contains_key(&p.file) {
                    sut.unknown_files += 1;
                } else {
                    match poses.entry(p.file) {
                        std::collections::btree_map::Entry::Occupied(_) => sut.duplicates += 1,
                        std::collections::btree_map::Entry::Vacant(v) => {
                            v.insert(p.pose);
                        }
                    }
                }
            }
            Err(e) => {
                sut.garbage_lines += 1;
                if sut.first_garbage.is_none() {
                    let mut e = e;
                    e.truncate(160);
                    sut.first_garbage = Some(format!("line {}: {e}", i + 1));
                }
            }
        }
    }
    poses
}

/// Options of a run that do not change results.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Keep each cell's folder (images, SUT output and stderr) under `work`.
    pub keep: bool,
    /// Print one line per cell to stderr.
    pub verbose: bool,
}

/// Run one cell in `work/cell-NNNNN`.
pub fn run_cell(plan: &Plan, cell: Cell, work: &Path, opts: &RunOptions) -> CellResult {
    let label = plan.label(cell.kind);
    let dir = work.join(format!("cell-{:05}", cell.index));
    let mut res = CellResult { cell, label, sut: None, error: None, frames: Vec::new() };
    let t0 = Instant::now();
    match prepare_and_run(plan, cell, &dir) {
        Ok((frames, sut)) => {
            res.frames = frames;
            res.sut = Some(sut);
        }
        Err(e) => res.error = Some(e),
    }
    if !opts.keep {
        let _ = std::fs::remove_dir_all(&dir);
    }
    if opts.verbose {
        let posed = res.frames.iter().filter(|f| f.status == FrameStatus::Posed).count();
        let st = res.sut.as_ref().map(|s| s.status.as_str()).or(res.error.as_deref()).unwrap_or("");
        eprintln!(
            "faultcam sweep: cell {} {} seed {}: {} frames, {posed} posed, sut {st} ({:.1} s)",
            cell.index,
            res.label,
            cell.seed,
            res.frames.len(),
            t0.elapsed().as_secs_f64()
        );
    }
    res
}

/// The cell's fault chain, seeded by the cell's seed.
fn build_chain(plan: &Plan, cell: Cell) -> Result<crate::Chain, String> {
    let mut chain = crate::Chain::new(cell.seed);
    for p in plan.chain_params(cell.kind)? {
        chain.push(p.info().name, p).map_err(|e| e.to_string())?;
    }
    Ok(chain)
}

/// Write `camera.json` (the SUT's `{camera}`) into the cell folder when the intrinsics are known.
fn write_camera(dir: &Path, camera: Option<crate::pose::Intrinsics>) -> Result<Option<PathBuf>, String> {
    match camera {
        Some(k) => {
            let p = dir.join("camera.json");
            std::fs::write(&p, serde_json::to_vec(&k).unwrap_or_default())
                .map_err(|e| format!("cannot write {}: {e}", p.display()))?;
            Ok(Some(p))
        }
        None => Ok(None),
    }
}

fn prepare_and_run(plan: &Plan, cell: Cell, dir: &Path) -> Result<(Vec<FrameResult>, SutOutcome), String> {
    let in_dir = dir.join("in");
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(&in_dir).map_err(|e| format!("cannot create {}: {e}", in_dir.display()))?;
    let mut frames: Vec<FrameResult> = Vec::new();
    let mut truths: Vec<Truth> = Vec::new();
    let (poses, sut) = match &plan.live {
        Some(live) => live::run(plan, live, cell, dir, &mut frames, &mut truths)?,
        None => run_batch(plan, cell, dir, &mut frames, &mut truths)?,
    };
    for ((f, truth), est) in frames.iter_mut().zip(&truths).zip(&poses) {
        if f.status != FrameStatus::NoPose {
            continue;
        }
        let (Some(est), Some(t)) = (est, truth.pose) else { continue };
        let (e_t, e_q) = (translation_error(&est.t, &t.t), rotation_error(&est.q, &t.q));
        f.status = FrameStatus::Posed;
        f.e_t = Some(e_t);
        f.e_q = Some(e_q);
        f.score = Some(e_t + e_q);
    }
    Ok((frames, sut))
}

/// Batch: write every frame into `in/`, run the SUT once, read its poses (by frame index).
fn run_batch(
    plan: &Plan,
    cell: Cell,
    dir: &Path,
    frames: &mut Vec<FrameResult>,
    truths: &mut Vec<Truth>,
) -> Result<(Vec<Option<crate::pose::Pose>>, SutOutcome), String> {
    let in_dir = dir.join("in");
    let mut chain = build_chain(plan, cell)?;
    let mut src = crate::source::open(&plan.source).map_err(|e| e.to_string())?;
    let mut report = crate::FrameReport::default();
    let mut scratch = Vec::new();
    let wopts = WriteOptions::default();
    let mut camera = None;
    loop {
        let mut f = match src.next_frame() {
            Ok(Some(f)) => f,
            Ok(None) => break,
            Err(e) if e.recoverable() => continue,
            Err(e) => return Err(format!("source: {e}")),
        };
        let truth = src.truth();
        camera = camera.or(truth.camera);
        let name = output_name(src.item_name(), f.seq, "png");
        let outcome = chain.apply(&mut f, &mut report).map_err(|e| format!("{name}: {e}"))?;
        let status = if outcome == Outcome::Drop {
            FrameStatus::Dropped
        } else {
            write_image(&in_dir.join(&name), &f, &wopts, &mut scratch)?;
            if truth.pose.is_some() { FrameStatus::NoPose } else { FrameStatus::NoTruth }
        };
        src.recycle(f);
        frames.push(FrameResult { file: name, status, e_t: None, e_q: None, score: None, incident: None });
        truths.push(truth);
    }
    let cam_path = write_camera(dir, camera)?;
    let run = run_sut(&plan.sut, dir, &in_dir, cam_path.as_deref(), Duration::from_secs_f64(plan.timeout_s));
    let mut sut = SutOutcome { status: run.status, no_output: run.output.is_none(), ..SutOutcome::default() };
    let known: BTreeMap<String, usize> = frames
        .iter()
        .enumerate()
        .filter(|(_, f)| f.status != FrameStatus::Dropped)
        .map(|(i, f)| (f.file.clone(), i))
        .collect();
    let by_file = parse_output(run.output.as_deref().unwrap_or(&[]), &known, &mut sut);
    let poses = frames.iter().map(|f| by_file.get(&f.file).copied()).collect();
    Ok((poses, sut))
}

/// Run the cells whose index % n == k (0-based `shard`), `jobs` at a time; results in cell
/// order, identical whatever `jobs` is.
pub fn run_cells(plan: &Plan, shard: (usize, usize), jobs: usize, work: &Path, opts: &RunOptions) -> Vec<CellResult> {
    let (k, n) = shard;
    let cells: Vec<Cell> = plan.cells().into_iter().filter(|c| c.index % n == k).collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let results = std::sync::Mutex::new(Vec::with_capacity(cells.len()));
    std::thread::scope(|s| {
        for _ in 0..jobs.max(1).min(cells.len().max(1)) {
            s.spawn(|| {
                loop {
                    let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let Some(c) = cells.get(i) else { break };
                    let r = run_cell(plan, *c, work, opts);
                    results.lock().unwrap_or_else(|e| e.into_inner()).push(r);
                }
            });
        }
    });
    let mut r = results.into_inner().unwrap_or_else(|e| e.into_inner());
    r.sort_by_key(|c| c.cell.index);
    r
}

/// Read shard files (or folders holding `shard-*.json`) and join them: every shard must carry
/// the same plan and every cell must appear exactly once.
pub fn merge_shards(paths: &[PathBuf]) -> Result<(serde_json::Value, Vec<CellResult>), String> {
    let mut files = Vec::new();
    for p in paths {
        if p.is_dir() {
            let rd = std::fs::read_dir(p).map_err(|e| format!("{}: {e}", p.display()))?;
            let mut found: Vec<PathBuf> = rd
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    let n = f.file_name().and_then(|n| n.to_str()).unwrap_or("");
                    n.starts_with("shard-") && n.ends_with(".json")
                })
                .collect();
            if found.is_empty() {
                return Err(format!("{}: no shard-*.json files", p.display()));
            }
            found.sort();
            files.extend(found);
        } else {
            files.push(p.clone());
        }
    }
    let mut plan: Option<(serde_json::Value, PathBuf)> = None;
    let mut cells: Vec<CellResult> = Vec::new();
    for f in &files {
        let text = std::fs::read(f).map_err(|e| format!("{}: {e}", f.display()))?;
        let s: ShardFile =
            serde_json::from_slice(&text).map_err(|e| format!("{}: not a sweep shard file: {e}", f.display()))?;
        match &plan {
            None => plan = Some((s.plan, f.clone())),
            Some((p, first)) if *p != s.plan => {
                return Err(format!(
                    "{} is from a different sweep than {} (the plans differ: source, SUT, grids, seeds or tolerances)",
                    f.display(),
                    first.display()
                ));
            }
            _ => {}
        }
        cells.extend(s.cells);
    }
    let (plan, _) = plan.ok_or("no shard files given")?;
    cells.sort_by_key(|c| c.cell.index);
    let expected = report::PlanView::from_value(&plan)?.cell_count();
    for (i, c) in cells.iter().enumerate() {
        if c.cell.index != i {
            return Err(if c.cell.index < i {
                format!("cell {} appears in more than one shard file", c.cell.index)
            } else {
                format!("cell {i} is missing: no shard file has it (a shard did not finish?)")
            });
        }
    }
    if cells.len() != expected {
        return Err(format!("{} of {expected} cells present: shard files are missing", cells.len()));
    }
    Ok((plan, cells))
}
