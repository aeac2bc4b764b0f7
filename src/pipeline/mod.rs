//! The streaming pipeline: source thread → fault stage → sink thread.
//!
//! ```text
//!  source thread            fault stage (caller's thread)         sink thread
//!  next_frame ─ pace ─▶ [queue] ─▶ controllers ─ chain ─▶ [queue] ─▶ delay line ─ write ─ log
//!       ▲   └─ drop note (overrun policy `drop`) ─────────────────────────────▲        │
//!       └──────────────────────────── free slots (frame pool) ◀───────────────────────┘
//! ```
//!
//! * **Frame pool.** Frames travel in pooled slots (frame + report + metadata). The sink
//!   thread returns each slot to the source thread, which hands the frame buffer back to the
//!   source ([`Source::recycle`]) before the next `next_frame`, so the steady state allocates
//!   nothing. The pool grows on demand to the number of frames in flight, bounded by the two
//!   queues (`queue_depth` each) and the delay line (`max_delayed_frames`).
//! * **Pacing.** [`Pacing::Fps`] releases frame k at `start + k / fps`, [`Pacing::Timestamps`]
//!   at `start + (pts − first pts)` (a timestamp that goes backwards, as when a recording
//!   loops, continues the timeline one frame interval after the previous frame);
//!   [`Pacing::Free`] reads as fast as the pipeline accepts. Looping itself is the source's
//!   job (`files:DIR?loop=true`).
//! * **Latency.** A frame's *capture* time is when the source produced it: for a paced source
//!   the time it was due (so a replay or pipeline that cannot keep up shows as latency), for a
//!   free-running one the time `next_frame` returned. Latency = sink write finished − capture.
//!   An injected output delay (`frame_delay`, `jitter`: [`FrameReport::delay_ns`]) is part of
//!   the latency but not of the budget check: a frame is *over budget* when
//!   `latency − injected delay > budget`.
//! * **Overrun policy** (what happens to frames that miss `budget_ms`): see [`OverrunPolicy`].
//! * **Accounting.** Every input frame gets exactly one `frame` line in the ground-truth log,
//!   with status `delivered`, `dropped_by_fault`, `dropped_overrun` or `failed` and its
//!   [`Timing`]. A full queue blocks (policies `pass`, `degrade`) or drops the frame with a log
//!   line (`drop`); nothing is lost silently. Skipped input items get `skip` lines, controller
//!   and degrade events `event` lines, and the [`Summary`] a final `summary` line.
//! * **Stop.** Raising [`PipelineOptions::stop`] (SIGINT in `faultcam run`) stops reading;
//!   frames already read are finished and logged, held frames drained, the sink finished.

pub mod degrade;
pub mod pool;
pub mod stats;

pub use stats::{EffectCost, LatencyHistogram, LatencyStats, StopReason, Summary};

use crate::control::{Controller, LogEvent};
use crate::faults::Outcome;
use crate::faults::chain::{Chain, FrameReport};
use crate::frame::{Frame, FrameData};
use crate::gtlog::{FrameRecord, FrameStatus, GroundTruthLog, Timing};
use crate::masks::{MaskOptions, MaskRecord, MaskRecorder, mask_stem};
use crate::sink::{Sink, SinkError};
use crate::source::Source;
use crossbeam_channel::{Receiver, RecvTimeoutError, Select, Sender, TrySendError, bounded};
use degrade::Degrader;
use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use thiserror::Error;

/// What to do with a frame that misses its latency budget.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum OverrunPolicy {
    /// Deliver every frame, late ones late (logged with `over_budget: true`, action `pass`).
    #[default]
    Pass,
    /// Deliver every frame, and while frames miss the budget run a cheaper chain: skip the
    /// most expensive effects, one more per miss, one fewer after a run of on-time frames
    /// (see [`degrade`]). Degraded frames are logged with action `degrade` and list only the
    /// effects that ran.
    Degrade,
    /// Drop frames that cannot make the budget, logged as `dropped_overrun` with the reason:
    /// at capture when the pipeline is full (paced or live sources only), before the chain
    /// when age + the chain's recent cost exceeds the budget, before the sink write when the
    /// frame is already over budget. A frame whose write itself ends over budget is
    /// delivered (it cannot be taken back) and counted late.
    Drop,
}

impl OverrunPolicy {
    pub fn name(self) -> &'static str {
        match self {
            OverrunPolicy::Pass => "pass",
            OverrunPolicy::Degrade => "degrade",
            OverrunPolicy::Drop => "drop",
        }
    }
}

impl std::str::FromStr for OverrunPolicy {
    type Err = PipelineError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "pass" => Ok(OverrunPolicy::Pass),
            "degrade" => Ok(OverrunPolicy::Degrade),
            "drop" => Ok(OverrunPolicy::Drop),
            _ => Err(PipelineError::BadOption {
                option: "overrun",
                value: s.to_string(),
                accepted: "pass, degrade or drop",
            }),
        }
    }
}

/// When the source thread releases frames into the pipeline.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Pacing {
    /// As fast as the pipeline accepts them (live sources pace themselves).
    #[default]
    Free,
    /// At a fixed rate (frames per second).
    Fps(f64),
    /// At the recorded timestamps (`Frame::pts_ns`), relative to the first frame.
    Timestamps,
}

/// Pipeline settings.
#[derive(Debug, Clone)]
pub struct PipelineOptions {
    pub pacing: Pacing,
    /// Capture-to-sink latency budget in ms; `None` = no budget (the policy never acts).
    pub budget_ms: Option<f64>,
    pub overrun: OverrunPolicy,
    /// The source produces frames in real time whether or not the pipeline is ready (camera,
    /// live stream): with the `drop` policy a full pipeline drops at capture. Paced sources
    /// count as real time.
    pub realtime_source: bool,
    /// Capacity of each of the two queues (source→chain, chain→sink), >= 1.
    pub queue_depth: usize,
    /// Most frames held back by injected delays before the sink stops taking new frames.
    pub max_delayed_frames: usize,
    /// Stop after this many input frames.
    pub max_frames: Option<u64>,
    /// Stop reading after this long.
    pub duration: Option<Duration>,
    /// Degrade policy: on-time frames before stepping back up one effect.
    pub degrade_hold_frames: u32,
    /// Raised from outside (SIGINT) to stop cleanly.
    pub stop: Arc<AtomicBool>,
    /// After a stop request, how long to wait for a source blocked in `next_frame`.
    pub stop_grace: Duration,
    /// Print a progress line to stderr this often.
    pub progress_every: Option<Duration>,
    /// Record per-pixel fault masks of every delivered frame and write them to this folder
    /// (see [`crate::masks`]); named in the frame records' `masks` field.
    pub masks: Option<MaskSettings>,
    /// Free-space floor checked before each sink write (`--min-free-mb`, `--low-disk`).
    pub disk_floor: Option<crate::gtlog::DiskFloor>,
}

/// Where and what per-pixel fault masks the pipeline writes.
#[derive(Debug, Clone)]
pub struct MaskSettings {
    pub dir: PathBuf,
    pub opts: MaskOptions,
}

impl Default for PipelineOptions {
    fn default() -> Self {
        PipelineOptions {
            pacing: Pacing::Free,
            budget_ms: None,
            overrun: OverrunPolicy::Pass,
            realtime_source: false,
            queue_depth: 2,
            max_delayed_frames: 64,
            max_frames: None,
            duration: None,
            degrade_hold_frames: 30,
            stop: Arc::new(AtomicBool::new(false)),
            stop_grace: Duration::from_secs(2),
            progress_every: None,
            masks: None,
            disk_floor: None,
        }
    }
}

impl PipelineOptions {
    /// Check ranges; errors name the option and the accepted range.
    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad = |option: &'static str, value: String, accepted: &'static str| {
            Err(PipelineError::BadOption { option, value, accepted })
        };
        if let Pacing::Fps(f) = self.pacing
            && !(f.is_finite() && f > 0.0 && f <= 100_000.0)
        {
            return bad("fps", f.to_string(), "0 < fps <= 100000");
        }
        if let Some(b) = self.budget_ms
            && !(b.is_finite() && b > 0.0)
        {
            return bad("budget_ms", b.to_string(), "a positive number of milliseconds");
        }
        if self.queue_depth == 0 || self.queue_depth > 1024 {
            return bad("queue_depth", self.queue_depth.to_string(), "1..=1024");
        }
        if self.max_delayed_frames == 0 || self.max_delayed_frames > 4096 {
            return bad("max_delayed_frames", self.max_delayed_frames.to_string(), "1..=4096");
        }
        Ok(())
    }
    fn budget_ns(&self) -> Option<u64> {
        self.budget_ms.map(|b| (b * 1e6) as u64)
    }
}

/// Errors that prevent a stream from starting.
#[derive(Debug, Error)]
pub enum PipelineError {
    #[error("pipeline option {option} = {value} is invalid; accepted: {accepted}")]
    BadOption { option: &'static str, value: String, accepted: &'static str },
    #[error("cannot start the source thread: {0}")]
    Thread(#[from] std::io::Error),
}

/// Effects whose `Outcome::Drop` means "held back, released later" rather than lost (see
/// `reorder`): their records count as [`Summary::held`], not as drops.
pub const HOLDING_EFFECTS: &[&str] = &["reorder"];

// ---------------------------------------------------------------------------------------------
// Slots and messages

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SlotState {
    Pending,
    DroppedByFault,
    DroppedOverrun,
    Failed,
}

/// One pooled frame in flight with everything the log needs about it.
struct Slot {
    frame: Frame,
    report: FrameReport,
    item: String,
    has_item: bool,
    /// Pose truth and camera the source reported for the frame.
    truth: crate::pose::Truth,
    capture_ns: u64,
    /// Stream time handed to controllers.
    t_ns: u64,
    state: SlotState,
    reason: Option<&'static str>,
    error: Option<String>,
    level: u32,
    degraded: bool,
    /// `before_frame` was called: controllers get `after_frame`.
    controlled: bool,
    drained: bool,
    chain_ns: u64,
    ready_ns: u64,
    due_ns: u64,
    /// Masks written for this frame (`PipelineOptions::masks`).
    masks: Option<MaskRecord>,
}

fn frame_is_empty(f: &Frame) -> bool {
    match &f.data {
        FrameData::U8(v) => v.capacity() == 0,
        FrameData::U16(v) => v.capacity() == 0,
    }
}

impl Slot {
    fn new() -> Box<Slot> {
        // allocation: once per pool slot (the pool grows to the number of frames in flight)
        Box::new(Slot {
            frame: Frame::empty(),
            report: FrameReport::default(),
            item: String::new(),
            has_item: false,
            truth: crate::pose::Truth::default(),
            capture_ns: 0,
            t_ns: 0,
            state: SlotState::Pending,
            reason: None,
            error: None,
            level: 0,
            degraded: false,
            controlled: false,
            drained: false,
            chain_ns: 0,
            ready_ns: 0,
            due_ns: 0,
            masks: None,
        })
    }
    fn reset(&mut self) {
        self.report.clear();
        self.item.clear();
        self.has_item = false;
        self.truth = crate::pose::Truth::default();
        self.state = SlotState::Pending;
        self.reason = None;
        self.error = None;
        self.level = 0;
        self.degraded = false;
        self.controlled = false;
        self.drained = false;
        self.chain_ns = 0;
        self.ready_ns = 0;
        self.due_ns = 0;
        self.masks = None;
    }
}

/// Fault stage → sink thread.
enum Msg {
    Frame(Box<Slot>),
    Events(Vec<LogEvent>),
}

/// Source thread → sink thread (outside the frame queues, so a full pipeline can still log).
enum Note {
    Dropped { seq: u64, pts_ns: u64, capture_ns: u64, item: Option<String>, truth: crate::pose::Truth },
    Skip { item: String, reason: String },
}

/// Sink thread → fault stage: a frame was handled (for `Controller::after_frame`).
struct Done {
    seq: u64,
    t_ns: u64,
    status: FrameStatus,
}

struct Shared {
    t0: Instant,
    stop: Arc<AtomicBool>,
    /// Internal stop: fatal error or closed sink.
    halt: AtomicBool,
    /// The fault stage gave up waiting for a blocked source.
    abandoned: AtomicBool,
    /// Bit l set: a frame processed at degrade level l missed the budget.
    late_levels: AtomicU64,
    frames_in: AtomicU64,
    skipped: AtomicU64,
}

impl Shared {
    fn now_ns(&self) -> u64 {
        self.t0.elapsed().as_nanos() as u64
    }
    fn stopping(&self) -> bool {
        self.stop.load(Ordering::Relaxed) || self.halt.load(Ordering::Relaxed)
    }
}

// ---------------------------------------------------------------------------------------------
// Source thread

/// Release schedule of the source thread.
struct Pacer {
    pacing: Pacing,
    started: bool,
    start_ns: u64,
    k: u64,
    first_pts: u64,
    prev_rel: u64,
    prev_t: u64,
    offset: u64,
    last_interval: u64,
}

impl Pacer {
    fn new(pacing: Pacing) -> Pacer {
        Pacer {
            pacing,
            started: false,
            start_ns: 0,
            k: 0,
            first_pts: 0,
            prev_rel: 0,
            prev_t: 0,
            offset: 0,
            last_interval: 33_333_333,
        }
    }

    /// (release time since t0, stream time for controllers) of the next frame.
    fn schedule(&mut self, pts_ns: u64, now_ns: u64) -> (u64, u64) {
        if !self.started {
            self.started = true;
            self.start_ns = now_ns;
            self.first_pts = pts_ns;
        }
        let k = self.k;
        self.k += 1;
        match self.pacing {
            Pacing::Free => (now_ns, pts_ns.saturating_sub(self.first_pts)),
            Pacing::Fps(fps) => {
                let t = (k as f64 * 1e9 / fps) as u64;
                (self.start_ns + t, t)
            }
            Pacing::Timestamps => {
                let rel = pts_ns.saturating_sub(self.first_pts);
                if k > 0 && rel < self.prev_rel {
                    // Timestamps went backwards (the recording looped): continue one interval on.
                    self.offset = self.prev_t + self.last_interval - rel;
                } else if k > 0 && rel > self.prev_rel {
                    self.last_interval = rel - self.prev_rel;
                }
                let t = rel + self.offset;
                self.prev_rel = rel;
                self.prev_t = t;
                (self.start_ns + t, t)
            }
        }
    }
}

struct SourceCfg {
    pacing: Pacing,
    max_frames: Option<u64>,
    duration_ns: Option<u64>,
    may_drop: bool,
}

struct SourceEnd {
    reason: Option<StopReason>,
    error: Option<String>,
}

fn source_loop(
    mut source: Box<dyn Source>,
    sh: Arc<Shared>,
    cfg: SourceCfg,
    free_rx: Receiver<Box<Slot>>,
    work_tx: Sender<Box<Slot>>,
    note_tx: Sender<Note>,
) -> SourceEnd {
    let mut shells: Vec<Box<Slot>> = Vec::new(); // allocation: grows once to the pool size
    let mut pacer = Pacer::new(cfg.pacing);
    let mut produced = 0u64;
    let mut end = SourceEnd { reason: None, error: None };
    let take_back = |source: &mut Box<dyn Source>, shells: &mut Vec<Box<Slot>>, mut s: Box<Slot>| {
        let f = std::mem::replace(&mut s.frame, Frame::empty());
        if !frame_is_empty(&f) {
            source.recycle(f);
        }
        shells.push(s);
    };
    loop {
        if sh.stop.load(Ordering::Relaxed) {
            end.reason = Some(StopReason::Signal);
            break;
        }
        if sh.halt.load(Ordering::Relaxed) {
            break;
        }
        if cfg.max_frames.is_some_and(|m| produced >= m) {
            end.reason = Some(StopReason::FrameLimit);
            break;
        }
        if cfg.duration_ns.is_some_and(|d| sh.now_ns() >= d) {
            end.reason = Some(StopReason::Duration);
            break;
        }
        while let Ok(s) = free_rx.try_recv() {
            take_back(&mut source, &mut shells, s);
        }
        let frame = match source.next_frame() {
            Ok(Some(f)) => f,
            Ok(None) => {
                end.reason = Some(StopReason::EndOfStream);
                break;
            }
            Err(e) if e.recoverable() => {
                sh.skipped.fetch_add(1, Ordering::Relaxed);
                let (item, reason) = match e {
                    crate::source::SourceError::BadInput { item, reason } => (item, reason),
                    other => (source.item_name().unwrap_or("?").to_string(), other.to_string()),
                };
                let _ = note_tx.send(Note::Skip { item, reason });
                continue;
            }
            Err(e) => {
                end.reason = Some(StopReason::Error);
                end.error = Some(format!("source: {e}"));
                break;
            }
        };
        let (release_ns, t_ns) = pacer.schedule(frame.pts_ns, sh.now_ns());
        // Wait for the release time in short naps so a stop request is seen promptly.
        let mut stopped = false;
        loop {
            let now = sh.now_ns();
            if now >= release_ns {
                break;
            }
            if sh.stopping() {
                stopped = true;
                break;
            }
            std::thread::sleep(Duration::from_nanos((release_ns - now).min(20_000_000)));
        }
        if stopped {
            // Read but never released (its capture time lies in the future): not an input.
            source.recycle(frame);
            continue;
        }
        let capture_ns = if cfg.pacing == Pacing::Free { sh.now_ns() } else { release_ns };
        let mut slot = match shells.pop() {
            Some(s) => s,
            None => match free_rx.try_recv() {
                Ok(mut s) => {
                    let f = std::mem::replace(&mut s.frame, Frame::empty());
                    if !frame_is_empty(&f) {
                        source.recycle(f);
                    }
                    s
                }
                Err(_) => Slot::new(),
            },
        };
        slot.reset();
        if let Some(name) = source.item_name() {
            slot.item.push_str(name);
            slot.has_item = true;
        }
        slot.truth = source.truth();
        slot.frame = frame;
        slot.capture_ns = capture_ns;
        slot.t_ns = t_ns;
        produced += 1;
        if cfg.may_drop {
            match work_tx.try_send(slot) {
                Ok(()) => {
                    sh.frames_in.fetch_add(1, Ordering::Relaxed);
                }
                Err(TrySendError::Full(s)) => {
                    let note = Note::Dropped {
                        seq: s.frame.seq,
                        pts_ns: s.frame.pts_ns,
                        capture_ns,
                        item: s.has_item.then(|| s.item.clone()),
                        truth: s.truth,
                    };
                    if note_tx.send(note).is_ok() {
                        sh.frames_in.fetch_add(1, Ordering::Relaxed);
                    }
                    take_back(&mut source, &mut shells, s);
                }
                Err(TrySendError::Disconnected(_)) => break,
            }
        } else {
            if work_tx.send(slot).is_err() {
                break;
            }
            sh.frames_in.fetch_add(1, Ordering::Relaxed);
        }
    }
    end
}

// ---------------------------------------------------------------------------------------------
// Fault stage

struct FaultStage<'a> {
    sh: &'a Shared,
    opts: &'a PipelineOptions,
    chain: Chain,
    controllers: Vec<Box<dyn Controller>>,
    degrader: Degrader,
    events: Vec<LogEvent>,
    work_tx: Sender<Msg>,
    done_rx: Option<Receiver<Done>>,
    degraded: u64,
    error: Option<String>,
    last_t: u64,
    /// Per-pixel fault masks (`PipelineOptions::masks`).
    masks: Option<MaskRecorder>,
    /// Frames dropped in a row before the chain on the cost estimate (`drop` policy).
    estimate_drops: u32,
}

/// With the `drop` policy, after this many frames in a row dropped before the chain on the
/// chain's cost estimate, the next frame runs anyway: the estimate is only refreshed by frames
/// that run, so without this probe one slow frame (a warm-up, a busy moment) would make every
/// later frame look too expensive and the stream would drop everything for good.
const PROBE_AFTER_ESTIMATE_DROPS: u32 = 15;

impl FaultStage<'_> {
    fn handle_done(&mut self, d: Done) {
        for c in &mut self.controllers {
            c.after_frame(d.seq, d.t_ns, d.status, &mut self.events);
        }
    }

    fn poll_done(&mut self) {
        while let Some(d) = self.done_rx.as_ref().and_then(|r| r.try_recv().ok()) {
            self.handle_done(d);
        }
    }

    /// Send to the sink thread, serving completions while the queue is full (so the sink,
    /// which may be waiting to report a completion, never deadlocks with us).
    fn send(&mut self, msg: Msg) {
        let mut msg = msg;
        loop {
            match self.work_tx.try_send(msg) {
                Ok(()) => return,
                Err(TrySendError::Disconnected(_)) => return,
                Err(TrySendError::Full(m)) => msg = m,
            }
            let Some(done_rx) = self.done_rx.clone() else {
                let _ = self.work_tx.send(msg);
                return;
            };
            let mut sel = Select::new();
            let si = sel.send(&self.work_tx);
            let ri = sel.recv(&done_rx);
            let op = sel.select();
            if op.index() == si {
                let _ = op.send(&self.work_tx, msg);
                return;
            } else if op.index() == ri {
                match op.recv(&done_rx) {
                    Ok(d) => self.handle_done(d),
                    Err(_) => self.done_rx = None,
                }
            }
        }
    }

    fn flush_events(&mut self) {
        if !self.events.is_empty() {
            let ev = std::mem::take(&mut self.events);
            self.send(Msg::Events(ev));
        }
    }

    fn process(&mut self, mut slot: Box<Slot>) {
        let budget = self.opts.budget_ns();
        let now = self.sh.now_ns();
        let age = now.saturating_sub(slot.capture_ns);
        self.last_t = slot.t_ns;
        if self.sh.halt.load(Ordering::Relaxed) {
            slot.state = SlotState::Failed;
            slot.error = Some(format!(
                "not processed: the stream stopped after an error ({})",
                self.error.as_deref().unwrap_or("sink")
            ));
            slot.ready_ns = now;
            self.send(Msg::Frame(slot));
            return;
        }
        // Overrun feedback from the sink: did a frame processed at >= the current level miss?
        let level = self.degrader.level();
        let late = self.sh.late_levels.swap(0, Ordering::Relaxed);
        let mut missed = level < 64 && (late >> level) != 0;
        if let Some(b) = budget {
            match self.opts.overrun {
                OverrunPolicy::Drop => {
                    let reason = if age > b {
                        Some("overrun: older than the budget before the chain")
                    } else if self.estimate_drops < PROBE_AFTER_ESTIMATE_DROPS
                        && age + self.degrader.chain_estimate_ns(&self.chain) > b
                    {
                        self.estimate_drops += 1;
                        Some("overrun: age + recent chain cost exceed the budget before the chain")
                    } else {
                        None
                    };
                    if let Some(reason) = reason {
                        slot.state = SlotState::DroppedOverrun;
                        slot.reason = Some(reason);
                        slot.ready_ns = now;
                        self.send(Msg::Frame(slot));
                        return;
                    }
                    self.estimate_drops = 0;
                }
                OverrunPolicy::Degrade => missed |= age > b,
                OverrunPolicy::Pass => {}
            }
        }
        let seq = slot.frame.seq;
        let mut level_changed = false;
        if self.opts.overrun == OverrunPolicy::Degrade && budget.is_some() {
            let n_enabled = self.chain.entries().iter().filter(|e| e.enabled).count();
            level_changed = self.degrader.update(missed, n_enabled).is_some();
        }
        for c in &mut self.controllers {
            if let Err(e) = c.before_frame(seq, slot.t_ns, &mut self.chain, &mut self.events) {
                let msg = format!("controller failed before frame {seq}: {e:#}");
                self.events.push(serde_json::json!({"event": "controller_error", "seq": seq, "error": msg}));
                self.error.get_or_insert(msg);
                self.sh.halt.store(true, Ordering::Relaxed);
            }
        }
        slot.controlled = !self.controllers.is_empty();
        self.degrader.disable(&mut self.chain);
        if level_changed {
            let skipped = self.degrader.skipped_names(&self.chain);
            self.events.push(serde_json::json!({
                "event": "overrun_degrade", "seq": seq, "t_ns": slot.t_ns,
                "level": self.degrader.level(), "skipped": skipped,
            }));
        }
        slot.level = self.degrader.level();
        slot.degraded = self.degrader.active();
        if slot.degraded {
            self.degraded += 1;
        }
        let t = Instant::now();
        let result = match self.masks.as_mut() {
            Some(rec) => self.chain.apply_recording(&mut slot.frame, &mut slot.report, rec),
            None => self.chain.apply(&mut slot.frame, &mut slot.report),
        };
        slot.chain_ns = t.elapsed().as_nanos() as u64;
        self.degrader.restore(&mut self.chain);
        match result {
            Ok(Outcome::Keep) => {
                slot.state = SlotState::Pending;
                if let (Some(rec), Some(m)) = (self.masks.as_mut(), self.opts.masks.as_ref()) {
                    // allocation: per frame, only with masks on (PNG/TIFF encoding, file names).
                    let stem = mask_stem(slot.has_item.then_some(slot.item.as_str()), seq);
                    match rec.write(&m.dir, &stem) {
                        Ok(r) => slot.masks = Some(r),
                        Err(e) => slot.error = Some(e.to_string()),
                    }
                }
            }
            Ok(Outcome::Drop) => slot.state = SlotState::DroppedByFault,
            Err(e) => {
                slot.state = SlotState::Failed;
                slot.error = Some(e.to_string());
            }
        }
        slot.ready_ns = self.sh.now_ns();
        self.flush_events();
        self.send(Msg::Frame(slot));
    }

    /// Frames effects still hold at the end (`Chain::drain_next`), passed through the effects
    /// after the one that held them.
    fn drain(&mut self) {
        loop {
            let mut slot = Slot::new(); // allocation: end of stream only
            let Some((frame, result)) = self.chain.drain_next(&mut slot.report) else {
                return;
            };
            slot.capture_ns = self.sh.now_ns();
            slot.t_ns = self.last_t;
            slot.drained = true;
            slot.state = match &result {
                Err(_) => SlotState::Failed,
                Ok(Outcome::Drop) => SlotState::DroppedByFault,
                Ok(Outcome::Keep) => SlotState::Pending,
            };
            slot.error = result.err().map(|e| e.to_string());
            slot.frame = frame;
            slot.ready_ns = self.sh.now_ns();
            self.send(Msg::Frame(slot));
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Sink thread

#[derive(Default)]
struct SinkEnd {
    delivered: u64,
    dropped_by_fault: u64,
    dropped_overrun: u64,
    failed: u64,
    held: u64,
    drained: u64,
    late: u64,
    dropped_low_disk: u64,
    unlogged: u64,
    latency: LatencyHistogram,
    chain: LatencyHistogram,
    write: LatencyHistogram,
    error: Option<String>,
    closed: bool,
}

struct SinkStage<'a> {
    sh: &'a Shared,
    opts: &'a PipelineOptions,
    sink: &'a mut dyn Sink,
    log: &'a mut GroundTruthLog,
    free_tx: Sender<Box<Slot>>,
    done_tx: Sender<Done>,
    out: SinkEnd,
    sink_dead: bool,
    last_due: u64,
    next_progress: Option<Instant>,
}

impl SinkStage<'_> {
    fn fatal(&mut self, msg: String) {
        self.out.error.get_or_insert(msg);
        self.sh.halt.store(true, Ordering::Relaxed);
    }

    fn log_frame(&mut self, rec: &FrameRecord<'_>) {
        if let Err(e) = self.log.frame(rec) {
            self.out.unlogged += 1;
            if self.out.error.is_none() {
                self.fatal(format!("cannot write the ground-truth log: {e}"));
            }
        }
    }

    fn timing(&self, capture_ns: u64, done_ns: u64, injected_ns: u64, action: Option<&'static str>) -> Timing {
        let latency_ns = done_ns.saturating_sub(capture_ns);
        let budget = self.opts.budget_ns();
        Timing {
            capture_ns,
            done_ns,
            latency_ms: latency_ns as f64 / 1e6,
            budget_ms: self.opts.budget_ms.unwrap_or(0.0),
            over_budget: budget.is_some_and(|b| latency_ns.saturating_sub(injected_ns) > b),
            action,
        }
    }

    /// Log a slot in its final state, count it, report it to controllers, recycle it.
    fn record(&mut self, mut slot: Box<Slot>, action: Option<&'static str>) {
        let done_ns = self.sh.now_ns();
        let timing = self.timing(slot.capture_ns, done_ns, slot.report.delay_ns, action);
        let status = match slot.state {
            SlotState::Pending => FrameStatus::Delivered,
            SlotState::DroppedByFault => FrameStatus::DroppedByFault,
            SlotState::DroppedOverrun => FrameStatus::DroppedOverrun,
            SlotState::Failed => FrameStatus::Failed,
        };
        match status {
            FrameStatus::Delivered => self.out.delivered += 1,
            FrameStatus::DroppedByFault if slot.report.dropped_by.is_some_and(|e| HOLDING_EFFECTS.contains(&e)) => {
                self.out.held += 1
            }
            FrameStatus::DroppedByFault => self.out.dropped_by_fault += 1,
            FrameStatus::DroppedOverrun => self.out.dropped_overrun += 1,
            FrameStatus::Failed => self.out.failed += 1,
        }
        if slot.drained {
            self.out.drained += 1;
        }
        if status != FrameStatus::DroppedOverrun && slot.chain_ns > 0 {
            self.out.chain.record(slot.chain_ns);
        }
        let error = slot.error.as_deref().or(slot.reason);
        let output = if status == FrameStatus::Delivered { self.sink.last_output() } else { None };
        let rec = FrameRecord {
            seq: slot.frame.seq,
            pts_ns: slot.frame.pts_ns,
            input: slot.has_item.then_some(slot.item.as_str()),
            pose: slot.truth.pose,
            camera: slot.truth.camera,
            status,
            dropped_by: slot.report.dropped_by,
            effects: if status == FrameStatus::DroppedOverrun { &[] } else { &slot.report.applied },
            output,
            masks: if status == FrameStatus::Delivered { slot.masks.as_ref() } else { None },
            timing: Some(&timing),
            error,
        };
        if let Err(e) = self.log.frame(&rec) {
            self.out.unlogged += 1;
            if self.out.error.is_none() {
                self.out.error = Some(format!("cannot write the ground-truth log: {e}"));
                self.sh.halt.store(true, Ordering::Relaxed);
            }
        }
        if slot.controlled {
            let _ = self.done_tx.send(Done { seq: slot.frame.seq, t_ns: slot.t_ns, status });
        }
        slot.error = None;
        let _ = self.free_tx.try_send(slot);
    }

    /// Write a pending frame (or drop it under the `drop` policy) and record it.
    fn deliver(&mut self, mut slot: Box<Slot>) {
        if self.sink_dead {
            slot.state = SlotState::Failed;
            slot.error = Some(if self.out.closed {
                "not delivered: the sink's consumer closed".to_string()
            } else {
                "not delivered: the sink failed earlier".to_string()
            });
            self.record(slot, None);
            return;
        }
        let injected = slot.report.delay_ns;
        let budget = self.opts.budget_ns();
        let now = self.sh.now_ns();
        if self.opts.overrun == OverrunPolicy::Drop
            && let Some(b) = budget
            && now.saturating_sub(slot.capture_ns).saturating_sub(injected) > b
        {
            slot.state = SlotState::DroppedOverrun;
            slot.reason = Some("overrun: over budget before the sink write");
            self.record(slot, Some("drop"));
            return;
        }
        if let Some(floor) = &self.opts.disk_floor
            && let Some(why) = floor.low()
        {
            slot.state = SlotState::Failed;
            match floor.policy {
                crate::gtlog::LowDiskPolicy::Drop => self.out.dropped_low_disk += 1,
                // Frames still in flight meet the same check and are logged as failed.
                crate::gtlog::LowDiskPolicy::Stop => self.fatal(format!("{why} (policy stop)")),
            }
            slot.error = Some(why);
            self.record(slot, None);
            return;
        }
        let t = Instant::now();
        let name = slot.has_item.then_some(slot.item.as_str());
        let res = self.sink.write_frame(&slot.frame, name);
        let write_ns = t.elapsed().as_nanos() as u64;
        match res {
            Ok(()) => {
                self.out.write.record(write_ns);
                let done = self.sh.now_ns();
                let latency = done.saturating_sub(slot.capture_ns);
                self.out.latency.record(latency);
                let over = budget.is_some_and(|b| latency.saturating_sub(injected) > b);
                if over {
                    self.out.late += 1;
                    self.sh.late_levels.fetch_or(1u64 << slot.level.min(63), Ordering::Relaxed);
                }
                let action = if slot.degraded {
                    Some("degrade")
                } else if over {
                    Some("pass")
                } else {
                    None
                };
                self.record(slot, action);
            }
            Err(e) => {
                self.sink_dead = true;
                if let SinkError::Closed { .. } = e {
                    self.out.closed = true;
                    self.sh.halt.store(true, Ordering::Relaxed);
                } else {
                    self.fatal(format!("sink: {e}"));
                }
                slot.state = SlotState::Failed;
                slot.error = Some(format!("sink: {e}"));
                self.record(slot, None);
            }
        }
    }

    fn note(&mut self, n: Note) {
        match n {
            Note::Dropped { seq, pts_ns, capture_ns, item, truth } => {
                let timing = self.timing(capture_ns, self.sh.now_ns(), 0, Some("drop"));
                let rec = FrameRecord {
                    seq,
                    pts_ns,
                    input: item.as_deref(),
                    pose: truth.pose,
                    camera: truth.camera,
                    status: FrameStatus::DroppedOverrun,
                    dropped_by: None,
                    effects: &[],
                    output: None,
                    masks: None,
                    timing: Some(&timing),
                    error: Some("overrun: pipeline full at capture"),
                };
                self.out.dropped_overrun += 1;
                self.log_frame(&rec);
            }
            Note::Skip { item, reason } => {
                if let Err(e) = self.log.skip(&item, &reason) {
                    self.fatal(format!("cannot write the ground-truth log: {e}"));
                }
            }
        }
    }

    fn progress(&mut self) {
        let (Some(every), Some(next)) = (self.opts.progress_every, self.next_progress) else { return };
        if Instant::now() < next {
            return;
        }
        self.next_progress = Some(next + every);
        let l = self.out.latency.stats();
        eprintln!(
            "faultcam: t={:.0}s in={} out={} dropped={}+{} failed={} latency p50={:.2}ms p99={:.2}ms max={:.2}ms late={}",
            self.sh.t0.elapsed().as_secs_f64(),
            self.sh.frames_in.load(Ordering::Relaxed),
            self.out.delivered,
            self.out.dropped_by_fault,
            self.out.dropped_overrun,
            self.out.failed,
            l.p50_ms,
            l.p99_ms,
            l.max_ms,
            self.out.late,
        );
    }

    fn run(mut self, work_rx: Receiver<Msg>, note_rx: Receiver<Note>) -> SinkEnd {
        // allocation: once per stream
        let mut delayed: VecDeque<Box<Slot>> = VecDeque::with_capacity(self.opts.max_delayed_frames);
        let mut work = Some(work_rx);
        let mut notes = Some(note_rx);
        loop {
            let now = self.sh.now_ns();
            while delayed.front().is_some_and(|s| s.due_ns <= now) {
                if let Some(s) = delayed.pop_front() {
                    self.deliver(s);
                }
            }
            self.progress();
            if work.is_none() && (notes.is_none() || self.sh.abandoned.load(Ordering::Relaxed)) {
                if delayed.is_empty() {
                    break;
                }
                notes = None;
            }
            let wait_ns = delayed.front().map(|s| s.due_ns.saturating_sub(self.sh.now_ns())).unwrap_or(u64::MAX);
            let timeout = Duration::from_nanos(wait_ns.min(100_000_000));
            let take_work = delayed.len() < self.opts.max_delayed_frames;
            let mut sel = Select::new();
            let wi = match (&work, take_work) {
                (Some(w), true) => Some(sel.recv(w)),
                _ => None,
            };
            let ni = notes.as_ref().map(|n| sel.recv(n));
            let Ok(op) = sel.select_timeout(timeout) else { continue };
            let idx = op.index();
            if Some(idx) == wi {
                let Some(w) = work.as_ref() else { continue };
                match op.recv(w) {
                    Ok(Msg::Frame(mut slot)) => {
                        if slot.state != SlotState::Pending {
                            let action = (slot.state == SlotState::DroppedOverrun).then_some("drop");
                            self.record(slot, action);
                        } else if slot.report.delay_ns == 0 && delayed.is_empty() {
                            self.deliver(slot);
                        } else {
                            slot.due_ns = (slot.ready_ns + slot.report.delay_ns).max(self.last_due);
                            self.last_due = slot.due_ns;
                            delayed.push_back(slot);
                        }
                    }
                    Ok(Msg::Events(events)) => {
                        for e in &events {
                            if let Err(err) = self.log.event(e) {
                                self.fatal(format!("cannot write the ground-truth log: {err}"));
                            }
                        }
                    }
                    Err(_) => work = None,
                }
            } else if Some(idx) == ni {
                let Some(n) = notes.as_ref() else { continue };
                match op.recv(n) {
                    Ok(note) => self.note(note),
                    Err(_) => notes = None,
                }
            }
        }
        if !self.sink_dead
            && let Err(e) = self.sink.finish()
        {
            match e {
                SinkError::Closed { .. } => self.out.closed = true,
                e => {
                    self.out.error.get_or_insert(format!("sink finish: {e}"));
                }
            }
        }
        self.out
    }
}

// ---------------------------------------------------------------------------------------------
// Entry point

/// Stream `source` through `chain` into `sink`, calling `controllers` around every frame and
/// writing one ground-truth record per input frame to `log` (plus events, skips and the
/// summary). Returns the [`Summary`]; a source, chain, controller or sink failure ends the
/// stream cleanly (everything read is accounted for) and is reported in `Summary::error`.
pub fn run(
    source: Box<dyn Source>,
    mut sink: Box<dyn Sink>,
    mut chain: Chain,
    controllers: Vec<Box<dyn Controller>>,
    opts: &PipelineOptions,
    log: &mut GroundTruthLog,
) -> Result<Summary, PipelineError> {
    opts.validate()?;
    let mut summary = Summary {
        source: source.describe(),
        sink: sink.describe(),
        budget_ms: opts.budget_ms,
        overrun_policy: opts.overrun.name(),
        ..Default::default()
    };
    let tracked = degrade::instrument(&mut chain);
    let degrader = Degrader::new(tracked, opts.degrade_hold_frames);
    let sh = Arc::new(Shared {
        t0: Instant::now(),
        stop: opts.stop.clone(),
        halt: AtomicBool::new(false),
        abandoned: AtomicBool::new(false),
        late_levels: AtomicU64::new(0),
        frames_in: AtomicU64::new(0),
        skipped: AtomicU64::new(0),
    });
    let q = opts.queue_depth;
    let pool_cap = 2 * q + opts.max_delayed_frames + 8;
    let (src_tx, src_rx) = bounded::<Box<Slot>>(q);
    let (work_tx, work_rx) = bounded::<Msg>(q);
    let (free_tx, free_rx) = bounded::<Box<Slot>>(pool_cap);
    let (note_tx, note_rx) = bounded::<Note>(1024);
    let (done_tx, done_rx) = bounded::<Done>(pool_cap);

    let src_cfg = SourceCfg {
        pacing: opts.pacing,
        max_frames: opts.max_frames,
        duration_ns: opts.duration.map(|d| d.as_nanos() as u64),
        may_drop: opts.overrun == OverrunPolicy::Drop
            && opts.budget_ms.is_some()
            && (opts.realtime_source || opts.pacing != Pacing::Free),
    };
    let sh_src = sh.clone();
    let src_handle = std::thread::Builder::new()
        .name("faultcam-source".into())
        .spawn(move || source_loop(source, sh_src, src_cfg, free_rx, src_tx, note_tx))?;

    let mut stage = FaultStage {
        sh: &sh,
        opts,
        chain,
        controllers,
        degrader,
        events: Vec::new(),
        work_tx,
        done_rx: Some(done_rx),
        degraded: 0,
        error: None,
        last_t: 0,
        masks: opts.masks.as_ref().map(|m| MaskRecorder::new(m.opts)),
        estimate_drops: 0,
    };

    let sink_end = std::thread::scope(|s| {
        let sink_stage = SinkStage {
            sh: &sh,
            opts,
            sink: sink.as_mut(),
            log: &mut *log,
            free_tx,
            done_tx,
            out: SinkEnd::default(),
            sink_dead: false,
            last_due: 0,
            next_progress: opts.progress_every.map(|d| Instant::now() + d),
        };
        let sink_handle = std::thread::Builder::new()
            .name("faultcam-sink".into())
            .spawn_scoped(s, move || sink_stage.run(work_rx, note_rx));
        let sink_handle = match sink_handle {
            Ok(h) => h,
            Err(e) => {
                stage.error = Some(format!("cannot start the sink thread: {e}"));
                sh.halt.store(true, Ordering::Relaxed);
                drop(src_rx);
                return SinkEnd { error: stage.error.clone(), ..Default::default() };
            }
        };
        let mut stop_seen: Option<Instant> = None;
        loop {
            stage.poll_done();
            stage.flush_events();
            match src_rx.recv_timeout(Duration::from_millis(50)) {
                Ok(slot) => stage.process(slot),
                Err(RecvTimeoutError::Disconnected) => break,
                Err(RecvTimeoutError::Timeout) => {
                    if sh.stopping() {
                        let since = *stop_seen.get_or_insert_with(Instant::now);
                        if since.elapsed() > opts.stop_grace {
                            sh.abandoned.store(true, Ordering::Relaxed);
                            break;
                        }
                    }
                }
            }
        }
        drop(src_rx);
        // Held frames are released even after an error: they are inputs and must be accounted.
        stage.drain();
        stage.flush_events();
        // Close the queue to the sink, then serve completions until the sink thread is done.
        let (dummy_tx, _) = bounded::<Msg>(1);
        drop(std::mem::replace(&mut stage.work_tx, dummy_tx));
        while let Some(rx) = stage.done_rx.clone() {
            match rx.recv() {
                Ok(d) => stage.handle_done(d),
                Err(_) => stage.done_rx = None,
            }
        }
        sink_handle
            .join()
            .unwrap_or_else(|_| SinkEnd { error: Some("the sink thread panicked".to_string()), ..Default::default() })
    });

    // The source thread: wait for it, or leave it behind if it is stuck in `next_frame`.
    let src_end = if sh.abandoned.load(Ordering::Relaxed) && !src_handle.is_finished() {
        SourceEnd { reason: Some(StopReason::Signal), error: None }
    } else {
        src_handle.join().unwrap_or(SourceEnd {
            reason: Some(StopReason::Error),
            error: Some("the source thread panicked".to_string()),
        })
    };

    // Late events (after_frame of the last frames, controllers' finish) go to the log now.
    let mut events = std::mem::take(&mut stage.events);
    for c in &mut stage.controllers {
        c.finish(&mut events);
    }
    let mut log_error = None;
    for e in &events {
        if let Err(err) = log.event(e) {
            log_error.get_or_insert(format!("cannot write the ground-truth log: {err}"));
        }
    }

    summary.frames_in = sh.frames_in.load(Ordering::Relaxed);
    summary.skipped_inputs = sh.skipped.load(Ordering::Relaxed);
    summary.delivered = sink_end.delivered;
    summary.dropped_by_fault = sink_end.dropped_by_fault;
    summary.dropped_overrun = sink_end.dropped_overrun;
    summary.dropped = summary.dropped_by_fault + summary.dropped_overrun;
    summary.failed = sink_end.failed;
    summary.dropped_low_disk = sink_end.dropped_low_disk;
    summary.unlogged = sink_end.unlogged;
    summary.held = sink_end.held;
    summary.drained = sink_end.drained;
    summary.unaccounted = summary.frames_in as i64 - summary.accounted() as i64;
    summary.late = sink_end.late;
    summary.budget_misses = sink_end.late + sink_end.dropped_overrun;
    summary.degraded = stage.degraded;
    summary.max_degrade_level = stage.degrader.max_level();
    summary.latency = sink_end.latency.stats();
    summary.chain = sink_end.chain.stats();
    summary.sink_write = sink_end.write.stats();
    summary.wall_s = sh.t0.elapsed().as_secs_f64();
    // What the sink negotiated on its first frame (format, size) is known only now.
    summary.sink = sink.describe();
    if summary.wall_s > 0.0 {
        summary.fps_in = summary.frames_in as f64 / summary.wall_s;
        summary.fps_out = summary.delivered as f64 / summary.wall_s;
    }
    summary.effects = stage
        .degrader
        .tracked()
        .iter()
        .map(|t| EffectCost {
            name: t.name,
            frames: t.cell.calls(),
            mean_ms: t.cell.mean_ns() / 1e6,
            max_ms: t.cell.max_ns() as f64 / 1e6,
        })
        .collect();
    let error = stage.error.take().or(src_end.error).or(sink_end.error).or(log_error);
    summary.stopped_by = if error.is_some() {
        StopReason::Error
    } else if opts.stop.load(Ordering::Relaxed) {
        StopReason::Signal
    } else {
        src_end.reason.unwrap_or(StopReason::EndOfStream)
    };
    summary.error = error;
    if let Err(e) = log.summary(&summary).and_then(|_| log.flush())
        && summary.error.is_none()
    {
        summary.error = Some(format!("cannot write the ground-truth log: {e}"));
        summary.stopped_by = StopReason::Error;
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pacer_fps_and_timestamps() {
        let mut p = Pacer::new(Pacing::Fps(50.0));
        assert_eq!(p.schedule(999, 1000), (1000, 0));
        assert_eq!(p.schedule(0, 5000), (1000 + 20_000_000, 20_000_000));
        let mut p = Pacer::new(Pacing::Timestamps);
        assert_eq!(p.schedule(5_000, 10), (10, 0));
        assert_eq!(p.schedule(15_000, 11), (10 + 10_000, 10_000));
        assert_eq!(p.schedule(35_000, 12), (10 + 30_000, 30_000));
        // Loop: timestamps restart; the timeline continues one interval (20 us) later.
        assert_eq!(p.schedule(5_000, 13), (10 + 50_000, 50_000));
        assert_eq!(p.schedule(15_000, 14), (10 + 60_000, 60_000));
    }

    #[test]
    fn overrun_policy_parses() {
        assert_eq!("drop".parse::<OverrunPolicy>().unwrap(), OverrunPolicy::Drop);
        let e = "late".parse::<OverrunPolicy>().unwrap_err().to_string();
        assert!(e.contains("pass, degrade or drop"), "{e}");
    }

    #[test]
    fn options_are_validated() {
        let o = PipelineOptions { pacing: Pacing::Fps(0.0), ..Default::default() };
        assert!(o.validate().unwrap_err().to_string().contains("fps"));
        let o = PipelineOptions { budget_ms: Some(-1.0), ..Default::default() };
        assert!(o.validate().unwrap_err().to_string().contains("budget_ms"));
        assert!(PipelineOptions::default().validate().is_ok());
    }
}
