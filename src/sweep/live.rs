//! Live mode of the sweep's SUT adapter: per cell, faultcam streams the faulted frames into a
//! sink the SUT reads (`files:` written frame by frame, a `gst:` pipeline, a `v4l2:` loopback
//! device) and the SUT reports one pose per frame, tagged with the frame's sequence number:
//!
//! ```text
//! {"seq":N,"q":[w,x,y,z],"t":[x,y,z]}
//! ```
//!
//! (one JSON line per frame, the [`crate::pose`] convention; `seq` is the frame's `seq` in the
//! ground-truth log: `frame_NNNNNN` in a `files:` sink's names, the buffer's `offset` through a
//! `gst:` sink when no frame is dropped, the buffer timestamp through a `v4l2:` sink (see
//! below); `{"seq":N}` says "no pose in frame N": it fails at once instead of at its time-out)
//! over:
//! - `stdout`: the SUT's standard output;
//! - `udp:HOST:PORT`: datagrams to a socket faultcam binds (loopback; port 0 = any free port,
//!   the SUT gets the address as `{report}`), one or more lines per datagram;
//! - `serial:DEVICE[?baud=N]`: a serial line faultcam opens (default 115200 baud).
//!
//! Frames go one at a time (lockstep): faultcam writes frame N, waits for its report up to the
//! per-frame time-out (`frame_timeout_s`, plus `startup_s` for the first frame), then writes
//! the next (with `fps`, no earlier than N / fps seconds after the stream's start: a camera's
//! frame rate as a floor), so a deterministic SUT gives the same report on every run, and the same as the
//! batch mode with the same poses. The SUT's standard input is a pipe closed at the end of the
//! stream (it may exit then; it is stopped after a grace period otherwise). Per frame, an
//! **incident** is recorded for: no report within the time-out, a garbage line, a report for
//! an unknown seq (not a frame shown in this cell) or a second report for a frame, a report
//! after the frame's time-out, a SUT that ended (crash, exit) before the frame. Frames without
//! a report fail; the sweep goes on. Over UDP or a serial line a SUT command that exits with
//! status 0 mid-stream is taken for a launcher (the SUT runs elsewhere): reports may still come.
//!
//! **`v4l2:` sink (a v4l2loopback device).** The device is the SUT's camera. A frame's seq
//! travels in its V4L2 buffer timestamp: faultcam opens the sink with `stamp=seq`, so frame
//! `seq` is stamped exactly `(seq + 1)` ms ([`seq_stamp_ns`]: `tv_sec = (seq + 1) / 1000`,
//! `tv_usec = ((seq + 1) % 1000) · 1000`; never 0, which v4l2loopback would replace with the
//! queue time), and a reader maps a timestamp back with `seq = round(t / 1 ms) − 1`
//! ([`seq_of_stamp_ns`]). v4l2loopback 0.12.7 gives readers no advancing sequence numbers
//! and restamps every buffer with the current `CLOCK_MONOTONIC` time when a reader requests
//! buffers (`VIDIOC_REQBUFS`): a reader takes only buffers stamped before the time it
//! started opening the device (frame stamps are far below the clock: a cell of S frames needs
//! an uptime above S ms). While it waits for frame N's report, faultcam keeps the device fed
//! like a camera: it writes frame N again, same bytes and stamp, every 1/`fps` s
//! (default [`DEFAULT_REFEED_FPS`]), so a reader that opened late (with `exclusive_caps=1` it can
//! open the device only once the first frame is written), skipped a restamped buffer or missed
//! one still gets it; the reader reports each seq once. A sink that cannot be opened (no such
//! device, held by another writer: retried for [`V4L2_OPEN_RETRY_S`] s) or that refuses the
//! format makes every frame not shown an incident naming the device; a SUT that never reads
//! the device leaves its frames without reports (per-frame time-outs). One cell at a time
//! (`--jobs 1`): the cells share the device.
//!
//! [`sut`] has the SUT side for Rust SUTs (the examples `truth_sut`, `ref_sut` and `pnp_sut` use
//! it): watching a `files:` sink folder or reading a `v4l2:` device, the seq of a frame file or
//! buffer, reporting over stdout or UDP.

use super::{FrameResult, FrameStatus, SutOutcome, shell_quote};
use crate::pose::{Pose, check_pose};
use crossbeam_channel::{Receiver, RecvTimeoutError, Sender, bounded};
use serde::{Deserialize, Serialize};
use std::io::Read;
use std::net::{SocketAddr, UdpSocket};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Default sink of a live sweep: the cell's image folder, written frame by frame.
pub const DEFAULT_SINK: &str = "files:{in_dir}";
/// Default per-frame time-out, seconds.
pub const DEFAULT_FRAME_TIMEOUT_S: f64 = 5.0;
/// Default extra time for the first frame (the SUT starting up), seconds.
pub const DEFAULT_STARTUP_S: f64 = 10.0;
/// Longest report line taken; longer lines are garbage.
pub const MAX_LINE_BYTES: usize = 4096;
/// Sink schemes a live sweep accepts.
pub const SINK_SCHEMES: &[&str] = &["files", "gst", "v4l2"];
/// Rate at which a `v4l2:` sink is fed the awaited frame again when the plan has no `fps`.
pub const DEFAULT_REFEED_FPS: f64 = 30.0;
/// How long a live cell tries to open a `v4l2:` sink that exists but is held (by the previous
/// cell's reader, closing), seconds.
pub const V4L2_OPEN_RETRY_S: f64 = 3.0;
/// Period of the seq stamp: frame `seq` through a `v4l2:` sink is stamped `(seq + 1)` periods.
pub const SEQ_STAMP_PERIOD_NS: u64 = 1_000_000;

/// The V4L2 buffer timestamp of frame `seq` in a live sweep, ns: `(seq + 1)` ms, a whole number
/// of µs (the V4L2 timestamp's resolution), never 0. None when it overflows.
pub fn seq_stamp_ns(seq: u64) -> Option<u64> {
    seq.checked_add(1)?.checked_mul(SEQ_STAMP_PERIOD_NS)
}

/// The seq a buffer timestamp (ns) stands for: the nearest `(seq + 1)` ms; None below 0.5 ms
/// (no frame's stamp).
pub fn seq_of_stamp_ns(ts_ns: u64) -> Option<u64> {
    (ts_ns / SEQ_STAMP_PERIOD_NS + u64::from(ts_ns % SEQ_STAMP_PERIOD_NS >= SEQ_STAMP_PERIOD_NS / 2)).checked_sub(1)
}

/// A live `v4l2:` sink's URI as faultcam opens it: `stamp=seq` added (see the module notes).
pub fn v4l2_sink_uri(uri: &str) -> String {
    crate::source::with_default_option(uri, "stamp", "seq")
}

/// The live settings of a plan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LivePlan {
    /// Sink URI; `{in_dir}` and `{cell_dir}` are replaced by the cell's folders.
    pub sink: String,
    /// Where reports come from: `stdout`, `udp:HOST:PORT`, `serial:DEVICE[?baud=N]`.
    pub report: String,
    /// Time-out of one frame's report, seconds.
    pub frame_timeout_s: f64,
    /// Extra time for the first frame's report (SUT start-up), seconds.
    pub startup_s: f64,
    /// Pacing: frame N (its index in the cell's stream) is shown no earlier than N / fps
    /// seconds after the stream's start (still lockstep: never before frame N-1's report or
    /// time-out). None: as soon as the previous frame is answered.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
}

/// A parsed `report` setting.
#[derive(Debug, Clone, PartialEq)]
pub enum ReportSpec {
    Stdout,
    Udp(SocketAddr),
    Serial { path: String, baud: u32 },
}

const REPORT_FORMS: &str = "stdout, udp:HOST:PORT (e.g. udp:127.0.0.1:5600; port 0 = any free port) or \
                            serial:DEVICE[?baud=N]";

impl ReportSpec {
    pub fn parse(s: &str) -> Result<ReportSpec, String> {
        let bad = |why: &str| format!("sut_report '{s}': {why}; accepted: {REPORT_FORMS}");
        if s == "stdout" {
            return Ok(ReportSpec::Stdout);
        }
        if let Some(a) = s.strip_prefix("udp:") {
            let addr: SocketAddr = a.parse().map_err(|_| bad("not an IP address and port"))?;
            return Ok(ReportSpec::Udp(addr));
        }
        if let Some(rest) = s.strip_prefix("serial:") {
            let (path, opts) = rest.split_once('?').unwrap_or((rest, ""));
            if path.is_empty() {
                return Err(bad("no device"));
            }
            let mut baud = 115_200;
            for kv in opts.split('&').filter(|k| !k.is_empty()) {
                match kv.split_once('=') {
                    Some(("baud", v)) => {
                        baud = v
                            .parse()
                            .ok()
                            .filter(|b| (50..=4_000_000).contains(b))
                            .ok_or_else(|| bad("baud must be an integer in 50..=4000000"))?
                    }
                    _ => return Err(bad(&format!("unknown option '{kv}' (only baud=N)"))),
                }
            }
            return Ok(ReportSpec::Serial { path: path.to_string(), baud });
        }
        Err(bad("unknown form"))
    }
}

/// Check a live sink URI without opening it (a `v4l2:` device may exist only on the rig).
pub fn check_sink(uri: &str) -> Result<(), String> {
    let (scheme, path, _) = crate::source::split_uri(uri);
    let bad = |why: &str| format!("sink '{uri}': {why}");
    if !SINK_SCHEMES.contains(&scheme) {
        return Err(bad(&format!(
            "a live SUT reads the sink; accepted: {}",
            SINK_SCHEMES.iter().map(|s| format!("{s}:")).collect::<Vec<_>>().join(", ")
        )));
    }
    let (_, _, opts) = crate::source::split_uri(uri);
    let opt = |k: &str| opts.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    match scheme {
        "files" if path.is_empty() => Err(bad("expected files:DIR (e.g. files:{in_dir})")),
        "v4l2" if !path.starts_with('/') => Err(bad("expected v4l2:/dev/videoN (a v4l2loopback device)")),
        "v4l2" if opt("stamp").is_some_and(|v| v != "seq") => {
            Err(bad("a live v4l2 sink stamps each frame with its seq (stamp=seq, the default here)"))
        }
        "v4l2" if opt("io") == Some("write") => {
            Err(bad("a live v4l2 sink needs io=mmap (the frame's seq travels in the buffer timestamp)"))
        }
        "v4l2" if !cfg!(feature = "v4l2") => Err(bad("this faultcam was built without V4L2 (feature v4l2)")),
        "gst" if !cfg!(feature = "gst") => Err(bad("this faultcam was built without GStreamer (feature gst)")),
        "gst" if !uri.contains("appsrc") => Err(bad("the pipeline must start with an appsrc")),
        _ => Ok(()),
    }
}

/// Parse one report line: `Ok(None)` for blank lines and `#` comments; `(seq, None)` for
/// `{"seq":N}` (the SUT found no pose in frame N: it fails without waiting for the time-out).
pub fn parse_report_line(line: &str) -> Result<Option<(u64, Option<Pose>)>, String> {
    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    struct L {
        seq: u64,
        q: Option<[f64; 4]>,
        t: Option<[f64; 3]>,
    }
    let line = line.trim().trim_start_matches('\u{feff}');
    if line.is_empty() || line.starts_with('#') {
        return Ok(None);
    }
    let l: L = serde_json::from_str(line)
        .map_err(|e| format!("not a report {{\"seq\":N,\"q\":[w,x,y,z],\"t\":[x,y,z]}}: {e}"))?;
    match (l.q, l.t) {
        (Some(q), Some(t)) => Ok(Some((l.seq, Some(check_pose(&q, &t)?)))),
        (None, None) => Ok(Some((l.seq, None))),
        _ => Err("a report needs both q and t (or neither: no pose)".into()),
    }
}

/// What the report reader hands over.
enum Msg {
    Line(Vec<u8>),
    /// The SUT's stdout closed.
    Eof,
}

/// Splits a byte stream into lines (longer than [`MAX_LINE_BYTES`]: cut and sent as is).
struct Lines {
    buf: Vec<u8>,
}

impl Lines {
    fn push(&mut self, bytes: &[u8], tx: &Sender<Msg>) -> bool {
        for &b in bytes {
            if b == b'\n' {
                if tx.send(Msg::Line(std::mem::take(&mut self.buf))).is_err() {
                    return false;
                }
            } else {
                self.buf.push(b);
                if self.buf.len() > MAX_LINE_BYTES && tx.send(Msg::Line(std::mem::take(&mut self.buf))).is_err() {
                    return false;
                }
            }
        }
        true
    }
}

/// A report channel with its reader thread.
struct Reports {
    rx: Receiver<Msg>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

const POLL: Duration = Duration::from_millis(20);

impl Reports {
    fn spawn(f: impl FnOnce(Sender<Msg>, Arc<AtomicBool>) + Send + 'static, join: bool) -> Result<Reports, String> {
        let (tx, rx) = bounded(1024);
        let stop = Arc::new(AtomicBool::new(false));
        let s = stop.clone();
        let h = std::thread::Builder::new()
            .name("faultcam-sut-reports".into())
            .spawn(move || f(tx, s))
            .map_err(|e| format!("cannot start the report reader: {e}"))?;
        Ok(Reports { rx, stop, thread: join.then_some(h) })
    }

    /// Bind a UDP socket; returns the reader and the bound address.
    fn udp(addr: SocketAddr) -> Result<(Reports, SocketAddr), String> {
        let sock = UdpSocket::bind(addr).map_err(|e| format!("sut_report udp:{addr}: cannot bind: {e}"))?;
        sock.set_read_timeout(Some(POLL)).map_err(|e| format!("sut_report udp:{addr}: {e}"))?;
        let local = sock.local_addr().map_err(|e| format!("sut_report udp:{addr}: {e}"))?;
        let r = Reports::spawn(
            move |tx, stop| {
                let mut buf = vec![0u8; 65536];
                while !stop.load(Ordering::Relaxed) {
                    match sock.recv_from(&mut buf) {
                        Ok((n, _)) => {
                            // A datagram ends its last line.
                            let mut l = Lines { buf: Vec::new() };
                            if !l.push(&buf[..n], &tx) || (!l.buf.is_empty() && tx.send(Msg::Line(l.buf)).is_err()) {
                                return;
                            }
                        }
                        Err(_) => continue,
                    }
                }
            },
            true,
        )?;
        Ok((r, local))
    }

    fn serial(path: &str, baud: u32) -> Result<Reports, String> {
        let mut port = crate::trigger::open_port(path, baud, POLL).map_err(|e| format!("sut_report: {e}"))?;
        // Bytes left over from an earlier cell are not this cell's.
        let _ = port.clear(serialport::ClearBuffer::Input);
        Reports::spawn(
            move |tx, stop| {
                let mut l = Lines { buf: Vec::new() };
                let mut buf = [0u8; 512];
                while !stop.load(Ordering::Relaxed) {
                    match port.read(&mut buf) {
                        Ok(0) => std::thread::sleep(POLL),
                        Ok(n) => {
                            if !l.push(&buf[..n], &tx) {
                                return;
                            }
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                        Err(_) => std::thread::sleep(POLL),
                    }
                }
            },
            true,
        )
    }

    /// Read the SUT's stdout (the thread ends at end of file; not joined, a stray process
    /// may keep the pipe open).
    fn stdout(mut out: std::process::ChildStdout) -> Result<Reports, String> {
        Reports::spawn(
            move |tx, _| {
                let mut l = Lines { buf: Vec::new() };
                let mut buf = [0u8; 4096];
                loop {
                    match out.read(&mut buf) {
                        Ok(0) => break,
                        Ok(n) => {
                            if !l.push(&buf[..n], &tx) {
                                return;
                            }
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                        Err(_) => break,
                    }
                }
                if !l.buf.is_empty() {
                    let _ = tx.send(Msg::Line(std::mem::take(&mut l.buf)));
                }
                let _ = tx.send(Msg::Eof);
            },
            false,
        )
    }
}

impl Drop for Reports {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.thread.take() {
            let _ = h.join();
        }
    }
}

fn exit_text(st: std::process::ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (st.code(), st.signal()) {
        (Some(0), _) => "ok".to_string(),
        (Some(c), _) => format!("exit status {c}"),
        (None, Some(s)) => format!("killed by signal {s}"),
        _ => "ended abnormally".to_string(),
    }
}

fn kill_group(child: &std::process::Child) {
    // SAFETY: kill(2) on the process group created for the child.
    unsafe {
        libc::kill(-(child.id() as i32), libc::SIGKILL);
    }
}

/// The running SUT and what it reported.
struct Session<'a> {
    child: std::process::Child,
    stdin: Option<std::process::ChildStdin>,
    reports: Reports,
    stdout_mode: bool,
    /// The SUT's exit, once seen.
    exited: Option<String>,
    /// No more reports can come (stdout closed, or the SUT crashed).
    gone: bool,
    frames: &'a mut Vec<FrameResult>,
    /// Per frame: answered (with a pose or none).
    poses: Vec<Option<Option<Pose>>>,
    /// Frame index by seq, for frames shown to the SUT.
    shown: std::collections::HashMap<u64, usize>,
    sut: SutOutcome,
}

fn note(f: &mut FrameResult, what: String) {
    match &mut f.incident {
        Some(s) => {
            s.push_str("; ");
            s.push_str(&what);
        }
        None => f.incident = Some(what),
    }
}

impl Session<'_> {
    /// Take one report line while frame `cur` (index) is awaited (or the last one shown).
    fn line(&mut self, bytes: &[u8], cur: Option<usize>) {
        let text = String::from_utf8_lossy(bytes);
        match parse_report_line(&text) {
            Ok(None) => {}
            Err(mut e) => {
                self.sut.garbage_lines += 1;
                e.truncate(160);
                if self.sut.first_garbage.is_none() {
                    self.sut.first_garbage = Some(e.clone());
                }
                if let Some(i) = cur {
                    note(&mut self.frames[i], format!("garbage report line: {e}"));
                }
            }
            Ok(Some((seq, pose))) => match self.shown.get(&seq) {
                Some(&i) if self.poses[i].is_some() => {
                    self.sut.duplicates += 1;
                    note(&mut self.frames[i], format!("second report for seq {seq} (ignored)"));
                }
                Some(&i) if Some(i) == cur => self.poses[i] = Some(pose),
                Some(&i) => {
                    self.sut.late += 1;
                    note(&mut self.frames[i], format!("report for seq {seq} after its time-out (ignored)"));
                }
                None => {
                    self.sut.unknown_files += 1;
                    if let Some(i) = cur {
                        note(&mut self.frames[i], format!("report for unknown seq {seq} (not a frame shown)"));
                    }
                }
            },
        }
    }

    /// See whether the SUT ended; a crash (or any end in stdout mode once its output closed)
    /// means no more reports.
    fn check_exit(&mut self) {
        if self.exited.is_none()
            && let Ok(Some(st)) = self.child.try_wait()
        {
            let t = exit_text(st);
            if t != "ok" {
                // Its helpers may hold the report pipe: stop the whole group.
                kill_group(&self.child);
                if !self.stdout_mode {
                    // Datagrams / bytes already sent are in the buffers: take them first.
                    self.drain(Duration::from_millis(50), None);
                    self.gone = true;
                }
            }
            self.exited = Some(t);
        }
    }

    /// Why no more reports can come: the SUT's exit (waited for a moment: its output closes
    /// as it ends), else its closed output.
    fn why_gone(&mut self) -> String {
        let end = Instant::now() + Duration::from_millis(500);
        while self.exited.is_none() && Instant::now() < end {
            self.check_exit();
            std::thread::sleep(Duration::from_millis(2));
        }
        match self.exited.as_deref() {
            Some("ok") => "exit status 0".into(),
            Some(t) => t.to_string(),
            None => "closed its output".into(),
        }
    }

    /// Take reports for `d` (no frame awaited: `cur` gets the incidents).
    fn drain(&mut self, d: Duration, cur: Option<usize>) {
        let end = Instant::now() + d;
        while let Some(left) = end.checked_duration_since(Instant::now()) {
            match self.reports.rx.recv_timeout(left) {
                Ok(Msg::Line(l)) => self.line(&l, cur),
                Ok(Msg::Eof) => {
                    self.gone = true;
                    return;
                }
                Err(_) => return,
            }
        }
    }

    /// Wait for frame `i`'s report until `deadline`; true when it came. `refeed` is called
    /// every [`POLL`] at most (a `v4l2:` sink shows the frame again when due); its error is an
    /// incident of the frame and ends the re-feeding.
    fn await_frame(
        &mut self,
        i: usize,
        deadline: Instant,
        timeout_s: f64,
        mut refeed: Option<&mut dyn FnMut() -> Result<(), String>>,
    ) -> bool {
        loop {
            if let Some(r) = refeed.as_mut()
                && let Err(e) = r()
            {
                note(&mut self.frames[i], e);
                refeed = None;
            }
            if self.poses[i].is_some() {
                return true;
            }
            if self.gone {
                let why = self.why_gone();
                note(&mut self.frames[i], format!("no report: the SUT ended ({why})"));
                return false;
            }
            let now = Instant::now();
            if now >= deadline {
                note(&mut self.frames[i], format!("no report within {} s", super::report::g(timeout_s)));
                return false;
            }
            match self.reports.rx.recv_timeout((deadline - now).min(POLL)) {
                Ok(Msg::Line(l)) => self.line(&l, Some(i)),
                Ok(Msg::Eof) => self.gone = true,
                Err(RecvTimeoutError::Timeout) => self.check_exit(),
                Err(RecvTimeoutError::Disconnected) => self.gone = true,
            }
        }
    }
}

/// Open a live `v4l2:` sink (with `stamp=seq`): a device that exists but cannot be opened as
/// an output (the previous cell's reader still closing) is tried again for
/// [`V4L2_OPEN_RETRY_S`] s.
fn open_v4l2_sink(uri: &str) -> Result<Box<dyn crate::sink::Sink>, String> {
    let uri = v4l2_sink_uri(uri);
    let path = crate::source::split_uri(&uri).1.to_string();
    let end = Instant::now() + Duration::from_secs_f64(V4L2_OPEN_RETRY_S);
    loop {
        match crate::sink::open(&uri) {
            Ok(s) => return Ok(s),
            Err(_) if Path::new(&path).exists() && Instant::now() < end => {
                std::thread::sleep(Duration::from_millis(50));
            }
            Err(e) => return Err(format!("sink: {e}")),
        }
    }
}

fn next_frame(src: &mut Box<dyn crate::source::Source>) -> Result<Option<crate::frame::Frame>, String> {
    loop {
        match src.next_frame() {
            Ok(f) => return Ok(f),
            Err(e) if e.recoverable() => continue,
            Err(e) => return Err(format!("source: {e}")),
        }
    }
}

/// Run one live cell in `dir`: frames and the SUT's outcome (poses not yet scored: `poses`).
pub(super) fn run(
    plan: &super::plan::Plan,
    live: &LivePlan,
    cell: super::plan::Cell,
    dir: &Path,
    frames: &mut Vec<FrameResult>,
    truths: &mut Vec<crate::pose::Truth>,
) -> Result<(Vec<Option<Pose>>, SutOutcome), String> {
    let in_dir = dir.join("in");
    let mut chain = super::build_chain(plan, cell)?;
    let mut src = crate::source::open(&plan.source).map_err(|e| e.to_string())?;
    let mut report = crate::FrameReport::default();
    let spec = ReportSpec::parse(&live.report)?;
    // The first frame carries the camera the SUT gets as {camera}.
    let mut pending = next_frame(&mut src)?;
    let truth0 = src.truth();
    let cam_path = super::write_camera(dir, truth0.camera)?;
    let (reports, report_arg) = match &spec {
        ReportSpec::Udp(a) => {
            let (r, local) = Reports::udp(*a)?;
            (Some(r), local.to_string())
        }
        ReportSpec::Serial { path, baud } => (Some(Reports::serial(path, *baud)?), path.clone()),
        ReportSpec::Stdout => (None, "-".to_string()),
    };
    let sink_uri =
        live.sink.replace("{in_dir}", &in_dir.display().to_string()).replace("{cell_dir}", &dir.display().to_string());
    let v4l2 = crate::source::split_uri(&sink_uri).0 == "v4l2";
    // A v4l2: sink that cannot be opened fails the frames (incidents naming the device), as a
    // device lost mid-stream would; the SUT still runs (it may be waiting for the device).
    let (mut sink, sink_error) = if v4l2 {
        match open_v4l2_sink(&sink_uri) {
            Ok(s) => (Some(s), None),
            Err(e) => (None, Some(e)),
        }
    } else {
        (Some(crate::sink::open(&sink_uri).map_err(|e| format!("sink: {e}"))?), None)
    };

    use std::os::unix::process::CommandExt;
    let cam = cam_path.as_deref().map(shell_quote).unwrap_or_else(|| "''".into());
    let cmd = plan
        .sut
        .replace("{in_dir}", &shell_quote(&in_dir))
        .replace("{camera}", &cam)
        .replace("{cell_dir}", &shell_quote(dir))
        .replace("{report}", &shell_quote(Path::new(&report_arg)));
    let stdout_mode = spec == ReportSpec::Stdout;
    let open = |n: &str| std::fs::File::create(dir.join(n)).map_err(|e| format!("cannot create {n}: {e}"));
    let mut c = std::process::Command::new("sh");
    c.arg("-c").arg(&cmd).stdin(std::process::Stdio::piped()).stderr(open("sut.stderr")?).process_group(0);
    if stdout_mode {
        c.stdout(std::process::Stdio::piped());
    } else {
        c.stdout(open("sut.stdout")?);
    }
    let mut child = match c.spawn() {
        Ok(ch) => ch,
        Err(e) => {
            let sut = SutOutcome { status: format!("could not start: {e}"), live: true, ..SutOutcome::default() };
            return Ok((Vec::new(), sut));
        }
    };
    let stdin = child.stdin.take();
    let reports = match reports {
        Some(r) => r,
        None => match child.stdout.take().map(Reports::stdout) {
            Some(Ok(r)) => r,
            _ => {
                kill_group(&child);
                let _ = child.wait();
                return Err("cannot read the SUT's stdout".into());
            }
        },
    };
    let mut s = Session {
        child,
        stdin,
        reports,
        stdout_mode,
        exited: None,
        gone: false,
        frames,
        poses: Vec::new(),
        shown: Default::default(),
        sut: SutOutcome { status: "ok".into(), live: true, ..SutOutcome::default() },
    };
    let t0 = Instant::now();
    let cell_deadline = t0 + Duration::from_secs_f64(plan.timeout_s);
    let mut timed_out = false;
    let mut first_shown = true;
    let mut last_shown = None;
    let mut first = true;
    let mut stop_why: Option<String> = sink_error;
    let refeed_every = Duration::from_secs_f64(1.0 / live.fps.unwrap_or(DEFAULT_REFEED_FPS));
    while let Some(mut f) = pending.take() {
        let truth = if first { truth0 } else { src.truth() };
        first = false;
        let name = crate::sink::files::output_name(src.item_name(), f.seq, "png");
        let seq = f.seq;
        let outcome = chain.apply(&mut f, &mut report).map_err(|e| format!("{name}: {e}"))?;
        let i = s.frames.len();
        let status = if outcome == crate::faults::Outcome::Drop {
            FrameStatus::Dropped
        } else if truth.pose.is_some() {
            FrameStatus::NoPose
        } else {
            FrameStatus::NoTruth
        };
        s.frames.push(FrameResult { file: name, status, e_t: None, e_q: None, score: None, incident: None });
        s.poses.push(None);
        truths.push(truth);
        if status != FrameStatus::Dropped {
            if stop_why.is_none() && Instant::now() >= cell_deadline {
                timed_out = true;
                stop_why = Some(format!("the cell's time-out ({} s)", super::report::g(plan.timeout_s)));
            }
            if stop_why.is_none() {
                s.check_exit();
                if s.gone {
                    stop_why = Some(format!("the SUT ended ({})", s.why_gone()));
                }
            }
            if stop_why.is_none()
                && let Some(fps) = live.fps
            {
                // Pacing: frame i no earlier than i / fps after the start (the cell's time-out
                // still holds).
                // Reports taken meanwhile belong to no awaited frame (a report of the previous
                // frame is late now).
                let due = (t0 + Duration::from_secs_f64(i as f64 / fps)).min(cell_deadline);
                while let Some(d) = due.checked_duration_since(Instant::now()) {
                    if s.gone {
                        std::thread::sleep(d.min(POLL));
                    } else {
                        s.drain(d.min(POLL), None);
                    }
                }
            }
            // The frame carries the seq its report must have (a v4l2: sink stamps it).
            f.seq = seq;
            match (&stop_why, sink.as_mut()) {
                (Some(why), _) => note(&mut s.frames[i], format!("not shown: {why}")),
                (None, None) => note(&mut s.frames[i], "not shown: no sink".into()),
                (None, Some(sink)) => match sink.write_frame(&f, src.item_name()) {
                    Ok(()) => {
                        s.shown.insert(seq, i);
                        last_shown = Some(i);
                        let mut wait = live.frame_timeout_s;
                        if first_shown {
                            wait += live.startup_s;
                            first_shown = false;
                        }
                        let deadline = (Instant::now() + Duration::from_secs_f64(wait)).min(cell_deadline);
                        if v4l2 {
                            // Feed the device like a camera while the report is awaited: the
                            // same frame, bytes and stamp again every `refeed_every`.
                            let mut due = Instant::now() + refeed_every;
                            let name = src.item_name();
                            let mut again = || {
                                if Instant::now() < due {
                                    return Ok(());
                                }
                                due += refeed_every;
                                sink.write_frame(&f, name).map_err(|e| format!("sink (frame shown again): {e}"))
                            };
                            s.await_frame(i, deadline, wait, Some(&mut again));
                        } else {
                            s.await_frame(i, deadline, wait, None);
                        }
                    }
                    Err(e) => {
                        let why = format!("sink: {e}");
                        note(&mut s.frames[i], why.clone());
                        stop_why = Some(why);
                    }
                },
            }
        }
        src.recycle(f);
        pending = next_frame(&mut src)?;
    }
    if let Some(Err(e)) = sink.as_mut().map(|s| s.finish())
        && let Some(i) = last_shown
    {
        note(&mut s.frames[i], format!("sink: {e}"));
    }
    // End of stream: close stdin, give the SUT a grace period to finish, then stop it.
    s.stdin = None;
    let grace = Duration::from_secs_f64(live.frame_timeout_s.min(2.0));
    let end = Instant::now() + grace;
    while s.exited.is_none() && Instant::now() < end && !timed_out {
        s.drain(POLL, last_shown);
        s.check_exit();
    }
    if s.exited.is_none() {
        kill_group(&s.child);
    }
    let _ = s.child.wait();
    // The device is closed after its reader: the next cell's writer finds it free sooner.
    drop(sink);
    s.sut.status = match (timed_out, &s.exited) {
        (true, _) => format!("timeout after {} s", super::report::g(plan.timeout_s)),
        (false, Some(t)) if t != "ok" => match &stop_why {
            Some(_) => format!("{t} mid-stream"),
            None => t.clone(),
        },
        _ => "ok".into(),
    };
    Ok((s.poses.into_iter().map(Option::flatten).collect(), s.sut))
}

/// The SUT side of the live protocol, for SUTs written in Rust.
pub mod sut {
    use std::collections::BTreeSet;
    use std::io::Write;
    use std::path::PathBuf;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};

    /// New files in a `files:` sink folder (or a `multifilesink` folder), in name order;
    /// `.tmp` files (being written) are skipped.
    pub struct FolderWatch {
        dir: PathBuf,
        seen: BTreeSet<String>,
    }

    impl FolderWatch {
        pub fn new(dir: impl Into<PathBuf>) -> FolderWatch {
            FolderWatch { dir: dir.into(), seen: BTreeSet::new() }
        }
        /// Paths of the files that appeared since the last call (none while the folder is missing).
        pub fn poll(&mut self) -> Vec<PathBuf> {
            let Ok(rd) = std::fs::read_dir(&self.dir) else { return Vec::new() };
            let mut new: Vec<String> = rd
                .filter_map(|e| e.ok()?.file_name().into_string().ok())
                .filter(|n| !n.ends_with(".tmp") && !self.seen.contains(n))
                .collect();
            new.sort();
            self.seen.extend(new.iter().cloned());
            new.into_iter().map(|n| self.dir.join(n)).collect()
        }
    }

    /// Where a live SUT gets its frames: a `files:` sink folder (or a `multifilesink` folder)
    /// or a `v4l2:` device.
    pub enum Input {
        Folder(FolderWatch),
        #[cfg(feature = "v4l2")]
        Device(Box<DeviceWatch>),
    }

    impl Input {
        /// `v4l2:/dev/videoN[?OPTIONS]` (a v4l2loopback device a live sweep writes; OPTIONS as
        /// the `v4l2:` source's) or a folder.
        pub fn open(spec: &str) -> Result<Input, String> {
            if spec.starts_with("v4l2:") {
                #[cfg(feature = "v4l2")]
                return Ok(Input::Device(Box::new(DeviceWatch::new(spec)?)));
                #[cfg(not(feature = "v4l2"))]
                return Err(format!("{spec}: this faultcam was built without V4L2 (feature v4l2)"));
            }
            Ok(Input::Folder(FolderWatch::new(spec)))
        }

        /// New frames: the seq when known and the image file. A folder: the files that appeared
        /// since the last call, in name order, seq from a `frame_NNNNNN` name (None for other
        /// names); does not wait. A device: at most one frame not reported before (waits up to
        /// [`DEVICE_POLL_MS`] ms), its seq from the buffer timestamp, written as a PNG file
        /// (valid until the next call).
        pub fn poll(&mut self) -> Vec<(Option<u64>, PathBuf)> {
            match self {
                Input::Folder(w) => w
                    .poll()
                    .into_iter()
                    .map(|p| (p.file_name().and_then(|n| n.to_str()).and_then(seq_of_name), p))
                    .collect(),
                #[cfg(feature = "v4l2")]
                Input::Device(d) => d.poll().into_iter().map(|(s, p)| (Some(s), p)).collect(),
            }
        }

        /// At the end of the stream: an error when a device never gave a frame (why it could not
        /// be read).
        pub fn finish(&self) -> Result<(), String> {
            match self {
                Input::Folder(_) => Ok(()),
                #[cfg(feature = "v4l2")]
                Input::Device(d) => d.finish(),
            }
        }

        fn waits(&self) -> bool {
            !matches!(self, Input::Folder(_))
        }
    }

    /// Longest wait of [`Input::poll`] on a device, ms.
    pub const DEVICE_POLL_MS: u64 = 50;

    /// Whether a buffer stamped `ts_ns` carries a frame's seq stamp, for a reader that started
    /// opening the device at `opened_ns` (`CLOCK_MONOTONIC`): v4l2loopback 0.12.7 restamps
    /// every buffer with the current time on a reader's `VIDIOC_REQBUFS`, so a buffer stamped
    /// at or after the open (compared at the timestamp's µs resolution) is no frame's stamp.
    pub fn is_seq_stamp(ts_ns: u64, opened_ns: u64) -> Option<u64> {
        if ts_ns >= opened_ns / 1000 * 1000 {
            return None;
        }
        super::seq_of_stamp_ns(ts_ns)
    }

    /// Frames of a `v4l2:` device a live sweep writes (a v4l2loopback device with the
    /// `stamp=seq` contract, see [`super`]): opened as a capture device once it is one (with
    /// `exclusive_caps=1`, after faultcam has written the first frame; tried every
    /// [`DEVICE_POLL_MS`] ms until then), each seq once.
    #[cfg(feature = "v4l2")]
    pub struct DeviceWatch {
        spec: String,
        uri: String,
        src: Option<crate::source::v4l2::V4l2Source>,
        /// When the current open started (`CLOCK_MONOTONIC`, ns).
        opened_ns: u64,
        next_try: std::time::Instant,
        reported: BTreeSet<u64>,
        scratch: PathBuf,
        last_file: Option<PathBuf>,
        png: Vec<u8>,
        /// Why the device could not be opened or read, last time.
        last_error: Option<String>,
        frames: u64,
    }

    #[cfg(feature = "v4l2")]
    impl DeviceWatch {
        pub fn new(spec: &str) -> Result<DeviceWatch, String> {
            if !crate::source::split_uri(spec).1.starts_with('/') {
                return Err(format!("{spec}: expected v4l2:/dev/videoN"));
            }
            let uri = crate::source::with_default_option(spec, "timeout_ms", &DEVICE_POLL_MS.to_string());
            static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
            let scratch = std::env::temp_dir().join(format!(
                "faultcam-sut-{}-{}",
                std::process::id(),
                N.fetch_add(1, Ordering::Relaxed)
            ));
            std::fs::create_dir_all(&scratch).map_err(|e| format!("{}: {e}", scratch.display()))?;
            Ok(DeviceWatch {
                spec: spec.to_string(),
                uri,
                src: None,
                opened_ns: 0,
                next_try: std::time::Instant::now(),
                reported: BTreeSet::new(),
                scratch,
                last_file: None,
                png: Vec::new(),
                last_error: None,
                frames: 0,
            })
        }

        /// At most one frame not reported before: (seq, PNG file).
        pub fn poll(&mut self) -> Option<(u64, PathBuf)> {
            use crate::source::Source;
            let wait = std::time::Duration::from_millis(DEVICE_POLL_MS);
            if self.src.is_none() {
                if let Some(d) = self.next_try.checked_duration_since(std::time::Instant::now()) {
                    std::thread::sleep(d);
                }
                self.next_try = std::time::Instant::now() + wait;
                self.opened_ns = crate::frame::monotonic_ns();
                match crate::source::v4l2::V4l2Source::open(&self.uri) {
                    Ok(s) => {
                        eprintln!("faultcam sut: reading {}", s.describe());
                        self.src = Some(s);
                    }
                    Err(e) => {
                        self.last_error = Some(e.to_string());
                        return None;
                    }
                }
            }
            let src = self.src.as_mut()?;
            let f = match src.poll_frame() {
                Ok(Some(f)) => f,
                Ok(None) => return None,
                Err(e) if e.recoverable() => return None,
                Err(e) => {
                    // Reopen (the writer restarted, the device was reset).
                    eprintln!("faultcam sut: {e}; opening {} again", self.spec);
                    self.last_error = Some(e.to_string());
                    self.src = None;
                    return None;
                }
            };
            let seq = is_seq_stamp(f.pts_ns, self.opened_ns).filter(|s| !self.reported.contains(s));
            let out = match seq {
                Some(seq) => {
                    if let Some(old) = self.last_file.take() {
                        let _ = std::fs::remove_file(old);
                    }
                    let p = self.scratch.join(format!("frame_{seq:06}.png"));
                    let opts = crate::sink::files::WriteOptions::default();
                    match crate::sink::files::write_image(&p, &f, &opts, &mut self.png) {
                        Ok(()) => {
                            self.reported.insert(seq);
                            self.frames += 1;
                            self.last_file = Some(p.clone());
                            Some((seq, p))
                        }
                        Err(e) => {
                            self.last_error = Some(e);
                            None
                        }
                    }
                }
                None => None,
            };
            src.recycle(f);
            out
        }

        pub fn finish(&self) -> Result<(), String> {
            match (&self.last_error, self.frames) {
                (Some(e), 0) => Err(format!("{}: no frame read: {e}", self.spec)),
                _ => Ok(()),
            }
        }
    }

    #[cfg(feature = "v4l2")]
    impl Drop for DeviceWatch {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.scratch);
        }
    }

    /// The seq of a sink file named `frame_NNNNNN.EXT` (a source without item names).
    pub fn seq_of_name(name: &str) -> Option<u64> {
        let stem = name.rsplit('/').next()?.split('.').next()?;
        stem.strip_prefix("frame_")?.parse().ok()
    }

    /// A flag set when standard input closes (faultcam closes it at the end of the stream).
    pub fn stdin_closed() -> Arc<AtomicBool> {
        let done = Arc::new(AtomicBool::new(false));
        let d = done.clone();
        std::thread::spawn(move || {
            let _ = std::io::copy(&mut std::io::stdin(), &mut std::io::sink());
            d.store(true, Ordering::Relaxed);
        });
        done
    }

    /// Where reports go: stdout (`-`) or UDP (`udp:HOST:PORT` or `HOST:PORT`, what faultcam
    /// passes as `{report}`). For a serial line, redirect stdout to the device.
    pub enum Reporter {
        Stdout(std::io::Stdout),
        Udp(std::net::UdpSocket),
    }

    impl Reporter {
        pub fn open(spec: &str) -> Result<Reporter, String> {
            if spec == "-" || spec == "stdout" {
                return Ok(Reporter::Stdout(std::io::stdout()));
            }
            let addr = spec.strip_prefix("udp:").unwrap_or(spec);
            let s = std::net::UdpSocket::bind("127.0.0.1:0").map_err(|e| format!("udp: {e}"))?;
            s.connect(addr).map_err(|e| format!("udp {addr}: {e}"))?;
            Ok(Reporter::Udp(s))
        }
        /// Report frame `seq`'s pose (`None`: no pose found).
        pub fn send(&mut self, seq: u64, pose: Option<([f64; 4], [f64; 3])>) -> Result<(), String> {
            let line = match pose {
                Some((q, t)) => serde_json::json!({"seq": seq, "q": q, "t": t}),
                None => serde_json::json!({ "seq": seq }),
            }
            .to_string();
            match self {
                Reporter::Stdout(o) => {
                    let mut o = o.lock();
                    writeln!(o, "{line}").and_then(|_| o.flush()).map_err(|e| format!("stdout: {e}"))
                }
                Reporter::Udp(s) => s.send(line.as_bytes()).map(|_| ()).map_err(|e| format!("udp send: {e}")),
            }
        }
    }

    /// A pose estimate: `(q, t)` in the sweep's convention, or `None` (no pose found).
    pub type Estimate = Option<([f64; 4], [f64; 3])>;

    /// Extensions of the images a SUT reads from a sink folder.
    const IMAGE_EXTS: [&str; 7] = ["png", "jpg", "jpeg", "pgm", "ppm", "tif", "tiff"];

    /// The `{camera}` JSON file a sweep passes (`{"fx","fy","cx","cy"}`; an empty path or an
    /// unreadable file: none).
    pub fn camera_json(path: Option<&str>) -> Option<serde_json::Value> {
        let p = path.filter(|s| !s.is_empty())?;
        serde_json::from_slice(&std::fs::read(p).ok()?).ok()
    }

    /// Batch mode: estimate every image of `in_dir` (sorted by name, in parallel) and write one
    /// `{"file":..,"q":..,"t":..}` line per image with a pose to `out_file`.
    pub fn run_batch(
        in_dir: &std::path::Path,
        out_file: &std::path::Path,
        estimate: impl Fn(&std::path::Path) -> Estimate + Sync,
    ) -> Result<(), String> {
        use rayon::prelude::*;
        let rd = std::fs::read_dir(in_dir).map_err(|e| format!("{}: {e}", in_dir.display()))?;
        let mut files: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).collect();
        files.retain(|p| p.extension().and_then(|e| e.to_str()).is_some_and(|e| IMAGE_EXTS.contains(&e)));
        files.sort();
        let poses: Vec<Estimate> = files.par_iter().map(|p| estimate(p)).collect();
        let mut out = String::new();
        for (p, pose) in files.iter().zip(&poses) {
            let Some((q, t)) = pose else { continue };
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            out += &serde_json::json!({"file": name, "q": q, "t": t}).to_string();
            out.push('\n');
        }
        std::fs::write(out_file, out).map_err(|e| format!("{}: {e}", out_file.display()))
    }

    /// Live mode: one report per new frame of `input` to `report` (see [`Reporter::open`]),
    /// until standard input closes. `input` is a folder (each new `frame_NNNNNN` file) or
    /// `v4l2:/dev/videoN` (each frame read from the device, seq from its timestamp, once; see
    /// [`Input`]).
    pub fn run_live(input: &str, report: &str, estimate: impl Fn(&std::path::Path) -> Estimate) -> Result<(), String> {
        let mut out = Reporter::open(report)?;
        let done = stdin_closed();
        let mut input = Input::open(input)?;
        loop {
            let last = done.load(Ordering::Relaxed);
            for (seq, p) in input.poll() {
                let Some(seq) = seq else { continue };
                out.send(seq, estimate(&p))?;
            }
            if last {
                return input.finish();
            }
            if !input.waits() {
                std::thread::sleep(std::time::Duration::from_millis(2));
            }
        }
    }

    /// The command line of an image-based SUT: `NAME IN_DIR OUT_FILE [CAMERA_JSON]` (batch) or
    /// `NAME --live IN_DIR|v4l2:/dev/videoN REPORT [CAMERA_JSON]`; `camera` turns the camera file into what
    /// `estimate` needs. Exit code 2 with a message on a usage or I/O error.
    pub fn main<C: Copy + Sync>(
        name: &str,
        camera: impl Fn(Option<&str>) -> C,
        estimate: impl Fn(&std::path::Path, C) -> Estimate + Sync,
    ) -> std::process::ExitCode {
        let args: Vec<String> = std::env::args().collect();
        let live = args.get(1).map(String::as_str) == Some("--live");
        let result = match (live, args.len()) {
            (true, 4..=5) => {
                let cam = camera(args.get(4).map(String::as_str));
                run_live(&args[2], &args[3], |p| estimate(p, cam))
            }
            (false, 3..=4) => {
                let cam = camera(args.get(3).map(String::as_str));
                run_batch(args[1].as_ref(), args[2].as_ref(), |p| estimate(p, cam))
            }
            _ => Err(format!(
                "usage: {name} IN_DIR OUT_FILE [CAMERA_JSON] | {name} --live IN_DIR|v4l2:/dev/videoN REPORT [CAMERA_JSON]"
            )),
        };
        match result {
            Ok(()) => std::process::ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("{name}: {e}");
                std::process::ExitCode::from(2)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn report_specs_parse_and_errors_name_the_forms() {
        assert_eq!(ReportSpec::parse("stdout").unwrap(), ReportSpec::Stdout);
        assert_eq!(
            ReportSpec::parse("udp:127.0.0.1:5600").unwrap(),
            ReportSpec::Udp("127.0.0.1:5600".parse().unwrap())
        );
        assert_eq!(
            ReportSpec::parse("serial:/dev/ttyUSB0?baud=9600").unwrap(),
            ReportSpec::Serial { path: "/dev/ttyUSB0".into(), baud: 9600 }
        );
        assert_eq!(
            ReportSpec::parse("serial:/dev/ttyS1").unwrap(),
            ReportSpec::Serial { path: "/dev/ttyS1".into(), baud: 115_200 }
        );
        let e = ReportSpec::parse("udp:localhost").unwrap_err();
        assert!(e.contains("udp:HOST:PORT") && e.contains("serial:DEVICE"), "{e}");
        assert!(ReportSpec::parse("serial:/dev/x?baud=0").unwrap_err().contains("50..=4000000"));
        assert!(ReportSpec::parse("tcp:1").is_err());
    }

    #[test]
    fn sinks_are_checked_without_opening() {
        assert!(check_sink("files:{in_dir}").is_ok());
        assert!(check_sink("v4l2:/dev/video42?format=GREY").is_ok());
        assert!(check_sink("null:").unwrap_err().contains("files:, gst:, v4l2:"));
        assert!(check_sink("v4l2:video0").unwrap_err().contains("/dev/videoN"));
    }

    #[test]
    fn seq_stamps_round_trip_through_a_v4l2_timestamp() {
        // Frame seq N is stamped (N + 1) ms: never 0 (v4l2loopback replaces a zero stamp).
        assert_eq!(seq_stamp_ns(0), Some(1_000_000));
        assert_eq!(seq_stamp_ns(41), Some(42_000_000));
        assert_eq!(seq_stamp_ns(u64::MAX), None);
        assert_eq!(seq_stamp_ns(u64::MAX / 1_000_000), None, "(seq + 1) ms overflows u64 ns");
        for seq in (0..5000).chain([999, 1000, 86_399_999, 9_000_000_000]) {
            let ts = seq_stamp_ns(seq).unwrap();
            // Through struct timeval (what VIDIOC_QBUF takes and VIDIOC_DQBUF gives back):
            // whole µs, so nothing is lost.
            let (sec, usec) = (ts / 1_000_000_000, ts % 1_000_000_000 / 1000);
            let back = sec * 1_000_000_000 + usec * 1000;
            assert_eq!(back, ts, "seq {seq}");
            assert_eq!(seq_of_stamp_ns(back), Some(seq), "seq {seq}");
            // A reader's rounding takes anything within half a period (a float-seconds reader,
            // a driver that moves stamps by some µs).
            assert_eq!(seq_of_stamp_ns(back + 499_999), Some(seq), "seq {seq} + 0.499999 ms");
            assert_eq!(seq_of_stamp_ns(back - 500_000), Some(seq), "seq {seq} − 0.5 ms");
            assert_eq!(seq_of_stamp_ns(back + 500_000), Some(seq + 1), "seq {seq} + 0.5 ms is the next");
        }
        assert_eq!(seq_of_stamp_ns(0), None);
        assert_eq!(seq_of_stamp_ns(499_999), None, "below half a period: no frame's stamp");
        // In float seconds (a Python reader: tv_sec + tv_usec / 1e6), rounding recovers seq.
        for seq in [0u64, 7, 12_345, 3_600_000] {
            let secs = seq_stamp_ns(seq).unwrap() as f64 / 1e9;
            assert_eq!(((secs * 1000.0).round() as u64).checked_sub(1), Some(seq));
        }
    }

    #[test]
    fn restamped_buffers_are_no_seq_stamps() {
        // A reader that started opening at 35.0000005 s of uptime: buffers stamped then or
        // later (v4l2loopback restamps at the reader's VIDIOC_REQBUFS, µs resolution) are not
        // frames' stamps; earlier ones are.
        let opened = 35_000_000_500;
        assert_eq!(sut::is_seq_stamp(35_000_000_000, opened), None, "same µs as the open");
        assert_eq!(sut::is_seq_stamp(35_000_017_000, opened), None);
        assert_eq!(sut::is_seq_stamp(seq_stamp_ns(7).unwrap(), opened), Some(7));
        assert_eq!(
            sut::is_seq_stamp(34_999_999_000, opened),
            Some(34_999),
            "just before the open (rounded to 35 000 ms)"
        );
        assert!(crate::frame::monotonic_ns() > 0);
    }

    #[test]
    fn live_v4l2_sinks_get_seq_stamps() {
        assert_eq!(v4l2_sink_uri("v4l2:/dev/video10"), "v4l2:/dev/video10?stamp=seq");
        assert_eq!(v4l2_sink_uri("v4l2:/dev/video10?format=GREY"), "v4l2:/dev/video10?format=GREY&stamp=seq");
        assert_eq!(v4l2_sink_uri("v4l2:/dev/video10?stamp=seq"), "v4l2:/dev/video10?stamp=seq");
        assert!(check_sink("v4l2:/dev/video10?stamp=seq").is_ok());
        assert!(check_sink("v4l2:/dev/video10?stamp=pts").unwrap_err().contains("stamp=seq"));
        assert!(check_sink("v4l2:/dev/video10?io=write").unwrap_err().contains("io=mmap"));
    }

    #[test]
    fn report_lines() {
        let (seq, p) = parse_report_line(r#"{"seq":7,"q":[2,0,0,0],"t":[0,0,10]}"#).unwrap().unwrap();
        let p = p.unwrap();
        assert_eq!((seq, p.q, p.t), (7, [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 10.0]));
        assert_eq!(parse_report_line(r#"{"seq":3}"#).unwrap(), Some((3, None)));
        assert!(parse_report_line(r#"{"seq":3,"t":[0,0,1]}"#).unwrap_err().contains("both q and t"));
        assert!(parse_report_line(r#"{"seq":3,"file":"a.png"}"#).is_err());
        assert_eq!(parse_report_line("  # note").unwrap(), None);
        assert!(parse_report_line(r#"{"seq":-1,"q":[1,0,0,0],"t":[0,0,1]}"#).is_err());
        assert!(parse_report_line(r#"{"seq":1,"q":[0,0,0,0],"t":[0,0,1]}"#).unwrap_err().contains("zero norm"));
        assert!(parse_report_line("frame_000000.png,1,0,0,0,0,0,1").unwrap_err().contains("seq"));
        assert_eq!(sut::seq_of_name("/x/frame_000012.png"), Some(12));
        assert_eq!(sut::seq_of_name("img_3.png"), None);
    }
}
