//! Ground-truth log: JSON Lines, one record per input frame (whatever happened to it) plus
//! event records (timeline, triggers, skipped inputs, summary).

use crate::faults::chain::{AppliedEffect, FrameReport};
use serde::Serialize;
use std::fs::File;
use std::io::Write;
use std::path::Path;

/// What became of an input frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameStatus {
    /// Written to the sink.
    Delivered,
    /// Dropped by a fault effect (`dropped_by` names it).
    DroppedByFault,
    /// Dropped by the overrun policy.
    DroppedOverrun,
    /// Could not be processed (error in `error`).
    Failed,
}

/// Per-frame timing (ns since the stream started, and capture-to-sink latency).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Timing {
    pub capture_ns: u64,
    pub done_ns: u64,
    pub latency_ms: f64,
    pub budget_ms: f64,
    pub over_budget: bool,
    /// Overrun policy action taken, if any ("pass", "degrade", "drop").
    #[serde(skip_serializing_if = "Option::is_none")]
    pub action: Option<&'static str>,
}

/// Mask outputs of a frame (see [`crate::masks`]).
pub use crate::masks::{DeltaFile, MaskRecord};

/// One frame's line.
#[derive(Debug, Serialize)]
pub struct FrameRecord<'a> {
    pub seq: u64,
    pub pts_ns: u64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub input: Option<&'a str>,
    /// Target pose in the camera frame when the source knows it (`synth:`, `files:` with
    /// `poses=`): `{"q":[w,x,y,z],"t":[x,y,z]}`, q scalar first, rotation target → camera,
    /// camera x right, y down, z forward, metres (see [`crate::pose`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pose: Option<crate::pose::Pose>,
    /// Camera intrinsics `{"fx","fy","cx","cy"}` in pixels (OpenCV convention).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<crate::pose::Intrinsics>,
    pub status: FrameStatus,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dropped_by: Option<&'a str>,
    pub effects: &'a [AppliedEffect],
    #[serde(skip_serializing_if = "Option::is_none")]
    pub output: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub masks: Option<&'a MaskRecord>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub timing: Option<&'a Timing>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<&'a str>,
}

impl<'a> FrameRecord<'a> {
    /// Record for a frame that went through the chain.
    pub fn from_report(seq: u64, pts_ns: u64, report: &'a FrameReport) -> FrameRecord<'a> {
        FrameRecord {
            seq,
            pts_ns,
            input: None,
            pose: None,
            camera: None,
            status: if report.dropped_by.is_some() { FrameStatus::DroppedByFault } else { FrameStatus::Delivered },
            dropped_by: report.dropped_by,
            effects: &report.applied,
            output: None,
            masks: None,
            timing: None,
            error: None,
        }
    }
}

#[derive(Serialize)]
struct Tagged<'a, T: Serialize> {
    record: &'static str,
    #[serde(flatten)]
    body: &'a T,
}

/// Bytes kept preallocated past the end of a log file (Linux `fallocate` with
/// `FALLOC_FL_KEEP_SIZE`) so the last records and the summary can still be written when the
/// disk fills up.
pub const SUMMARY_RESERVE: u64 = 64 * 1024;
/// Part of the reserve only the summary may use.
pub const SUMMARY_KEEP: u64 = 16 * 1024;

enum Out {
    File(File),
    Writer(Box<dyn Write + Send>),
}

/// JSON Lines writer. Every line has a `record` field: `frame`, `event`, `skip` or `summary`.
///
/// Records are written whole or not at all: each is serialised into a reused buffer and written
/// with one `write_all`; when that fails (a full disk: `ENOSPC`) the file is truncated back to
/// the end of the last complete record, so the log always parses to its last record. A file
/// log keeps [`SUMMARY_RESERVE`] bytes allocated past its end: when the disk cannot renew that
/// reserve any more, records go on into what is left of it down to [`SUMMARY_KEEP`] bytes,
/// then are refused (an error naming the cause) and the summary goes into the rest. After a failed write only the summary is still attempted. The
/// reserve is released when the log is dropped.
pub struct GroundTruthLog {
    out: Out,
    /// Reused serialisation buffer (no per-record allocation once it has grown).
    buf: Vec<u8>,
    /// Bytes of complete records in the file.
    committed: u64,
    /// Records written.
    records: u64,
    /// Set once a record could not be written (or the reserve could not be kept).
    broken: Option<String>,
    /// True once the file has had a reserve allocated past its end.
    reserved: bool,
    /// File offset up to which space is allocated (0 without a reserve).
    reserved_end: u64,
}

impl GroundTruthLog {
    pub fn create(path: &Path) -> std::io::Result<GroundTruthLog> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let mut log = GroundTruthLog::new(Out::File(File::create(path)?));
        log.keep_reserve();
        Ok(log)
    }
    /// A log into any writer (tests, stdout): records whole, but no truncation or reserve.
    pub fn to_writer(w: Box<dyn Write + Send>) -> GroundTruthLog {
        GroundTruthLog::new(Out::Writer(w))
    }
    fn new(out: Out) -> GroundTruthLog {
        // allocation: once per log
        GroundTruthLog {
            out,
            buf: Vec::with_capacity(4096),
            committed: 0,
            records: 0,
            broken: None,
            reserved: false,
            reserved_end: 0,
        }
    }

    /// Records written so far.
    pub fn records(&self) -> u64 {
        self.records
    }
    /// Bytes of complete records written so far.
    pub fn bytes(&self) -> u64 {
        self.committed
    }
    /// Why records are refused, once they are.
    pub fn broken(&self) -> Option<&str> {
        self.broken.as_deref()
    }

    /// Allocate [`SUMMARY_RESERVE`] bytes past the last complete record (keeping the size).
    /// Returns false when the file system has no room for it (`ENOSPC`); file systems without
    /// `fallocate` simply get no reserve.
    fn keep_reserve(&mut self) -> bool {
        let Out::File(f) = &self.out else { return true };
        use std::os::fd::AsRawFd;
        // SAFETY: fallocate on a file descriptor we own; no memory is passed.
        let r = unsafe {
            libc::fallocate(f.as_raw_fd(), libc::FALLOC_FL_KEEP_SIZE, self.committed as i64, SUMMARY_RESERVE as i64)
        };
        if r == 0 {
            self.reserved = true;
            self.reserved_end = self.committed + SUMMARY_RESERVE;
            return true;
        }
        let e = std::io::Error::last_os_error();
        e.raw_os_error() != Some(libc::ENOSPC)
    }

    fn line<T: Serialize>(&mut self, record: &'static str, body: &T) -> std::io::Result<()> {
        let summary = record == "summary";
        if let Some(why) = &self.broken
            && !summary
        {
            return Err(std::io::Error::other(format!("record refused: {why}")));
        }
        self.buf.clear();
        serde_json::to_writer(&mut self.buf, &Tagged { record, body })?;
        self.buf.push(b'\n');
        let res = match &mut self.out {
            Out::File(f) => f.write_all(&self.buf),
            Out::Writer(w) => w.write_all(&self.buf),
        };
        if let Err(e) = res {
            // Cut the partial record off: the log ends at its last complete record.
            if let Out::File(f) = &mut self.out {
                use std::io::{Seek, SeekFrom};
                let _ = f.set_len(self.committed).and_then(|_| f.seek(SeekFrom::Start(self.committed)));
            }
            let why = format!("{e}; the log ends at its last complete record ({} records)", self.records);
            self.broken.get_or_insert(why.clone());
            return Err(std::io::Error::new(e.kind(), why));
        }
        self.committed += self.buf.len() as u64;
        self.records += 1;
        if !summary && !self.keep_reserve() && self.reserved_end.saturating_sub(self.committed) < SUMMARY_KEEP {
            let why = format!(
                "No space left on device for the log's {} KiB summary reserve; the log ends at record {} ({} bytes) \
                 and keeps the reserve for the summary",
                SUMMARY_RESERVE / 1024,
                self.records,
                self.committed
            );
            self.broken.get_or_insert(why);
        }
        Ok(())
    }
    pub fn frame(&mut self, r: &FrameRecord<'_>) -> std::io::Result<()> {
        self.line("frame", r)
    }
    /// Timeline/trigger/ack events.
    pub fn event<T: Serialize>(&mut self, e: &T) -> std::io::Result<()> {
        self.line("event", e)
    }
    /// An input item that was skipped (corrupt file, wrong size) with the reason.
    pub fn skip(&mut self, item: &str, reason: &str) -> std::io::Result<()> {
        #[derive(Serialize)]
        struct Skip<'a> {
            item: &'a str,
            reason: &'a str,
        }
        self.line("skip", &Skip { item, reason })
    }
    /// The summary record: attempted even after a failed write (into the reserve).
    pub fn summary<T: Serialize>(&mut self, s: &T) -> std::io::Result<()> {
        self.line("summary", s)
    }
    pub fn flush(&mut self) -> std::io::Result<()> {
        match &mut self.out {
            Out::File(f) => f.flush(),
            Out::Writer(w) => w.flush(),
        }
    }
}

impl Drop for GroundTruthLog {
    fn drop(&mut self) {
        // Release the reserve: the file ends at its last complete record.
        if let Out::File(f) = &mut self.out
            && self.reserved
        {
            use std::os::fd::AsRawFd;
            // SAFETY: fallocate on a file descriptor we own; no memory is passed.
            unsafe {
                libc::fallocate(
                    f.as_raw_fd(),
                    libc::FALLOC_FL_PUNCH_HOLE | libc::FALLOC_FL_KEEP_SIZE,
                    self.committed as i64,
                    SUMMARY_RESERVE as i64,
                );
            }
            let _ = f.set_len(self.committed);
        }
    }
}

/// What to do when free space falls under the floor (`--low-disk`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LowDiskPolicy {
    /// Stop the run cleanly (the summary is written, the run ends with an error).
    #[default]
    Stop,
    /// Do not write the frame; log it as `failed` with a `low disk` error, count it
    /// (`dropped_low_disk`) and keep going.
    Drop,
}

impl std::str::FromStr for LowDiskPolicy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "stop" => Ok(LowDiskPolicy::Stop),
            "drop" => Ok(LowDiskPolicy::Drop),
            _ => Err(format!("--low-disk '{s}' is not accepted; accepted: stop or drop")),
        }
    }
}

/// A free-space floor (`--min-free-mb N`) over the folders a run writes to (the log's and the
/// sink's): checked with `statvfs` before each frame is written (space available to an
/// unprivileged user, `f_bavail · f_frsize`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiskFloor {
    pub min_free_mb: u64,
    pub dirs: Vec<std::path::PathBuf>,
    pub policy: LowDiskPolicy,
}

/// Bytes available to unprivileged users on the file system holding `dir`.
pub fn free_bytes(dir: &Path) -> std::io::Result<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).map_err(std::io::Error::other)?;
    // SAFETY: statvfs with a NUL-terminated path and a zeroed out-struct we own.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::statvfs(c.as_ptr(), &mut st) } != 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(st.f_bavail as u64 * st.f_frsize as u64)
}

impl DiskFloor {
    /// `Some(reason)` when a folder has less than the floor free (or cannot be checked).
    pub fn low(&self) -> Option<String> {
        for d in &self.dirs {
            match free_bytes(d) {
                Ok(b) if b >= self.min_free_mb << 20 => {}
                Ok(b) => {
                    return Some(format!(
                        "low disk: {} has {:.1} MB free, under --min-free-mb {}",
                        d.display(),
                        b as f64 / 1048576.0,
                        self.min_free_mb
                    ));
                }
                Err(e) => return Some(format!("low disk: cannot check the free space of {}: {e}", d.display())),
            }
        }
        None
    }
}

/// What `faultcam log check` found in a ground-truth log.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct LogCheck {
    /// Complete, parseable records.
    pub records: u64,
    pub frames: u64,
    pub events: u64,
    pub skips: u64,
    pub summary: bool,
    /// The summary's `stopped_by` and `error`, when there is one.
    pub stopped_by: Option<String>,
    pub error: Option<String>,
    /// Frame records per status: delivered, dropped_by_fault (less held), dropped_overrun, failed.
    pub counts: [u64; 4],
    /// Everything wrong, each naming the line.
    pub problems: Vec<String>,
    /// Frame records the summary declares could not be written (a full disk).
    pub unlogged: u64,
}

impl LogCheck {
    pub fn ok(&self) -> bool {
        self.problems.is_empty()
    }
}

/// Validate a ground-truth log: every line a JSON object with a known `record`, no partial last
/// line (a truncated write), exactly one summary and it last, and every input frame accounted
/// for (summary: `frames_in = delivered + dropped_by_fault + dropped_overrun + failed`, and the
/// frame records agree with the summary's counts). Works on `run` and `apply` logs.
pub fn check_log(bytes: &[u8]) -> LogCheck {
    let mut c = LogCheck::default();
    let mut summary: Option<serde_json::Value> = None;
    let mut held = 0u64;
    let complete = match bytes.iter().rposition(|&b| b == b'\n') {
        Some(i) => &bytes[..=i],
        None => &bytes[..0],
    };
    let n_complete = complete.iter().filter(|&&b| b == b'\n').count();
    if complete.len() < bytes.len() {
        c.problems.push(format!(
            "truncated: line {} is a partial record ({} bytes without a newline; a write was cut off)",
            n_complete + 1,
            bytes.len() - complete.len()
        ));
    }
    for (i, line) in complete.split(|&b| b == b'\n').take(n_complete).enumerate() {
        let ln = i + 1;
        let v: serde_json::Value = match serde_json::from_slice(line) {
            Ok(v) => v,
            Err(e) => {
                c.problems.push(format!("line {ln}: not a valid JSON record: {e}"));
                continue;
            }
        };
        let Some(kind) = v.get("record").and_then(|r| r.as_str()) else {
            c.problems.push(format!("line {ln}: no \"record\" field (accepted: frame, event, skip, summary)"));
            continue;
        };
        if summary.is_some() {
            c.problems.push(format!("line {ln}: a {kind} record after the summary"));
        }
        c.records += 1;
        match kind {
            "frame" => {
                c.frames += 1;
                let status = v.get("status").and_then(|s| s.as_str()).unwrap_or("");
                match status {
                    "delivered" => c.counts[0] += 1,
                    "dropped_by_fault" if v.get("dropped_by").and_then(|d| d.as_str()).is_some_and(|d| d == "reorder") => {
                        held += 1
                    }
                    "dropped_by_fault" => c.counts[1] += 1,
                    "dropped_overrun" => c.counts[2] += 1,
                    "failed" => c.counts[3] += 1,
                    other => c.problems.push(format!(
                        "line {ln}: frame status '{other}' is not one of delivered, dropped_by_fault, dropped_overrun, failed"
                    )),
                }
            }
            "event" => c.events += 1,
            "skip" => c.skips += 1,
            "summary" => {
                if c.summary {
                    c.problems.push(format!("line {ln}: a second summary"));
                }
                c.summary = true;
                summary = Some(v);
            }
            other => {
                c.problems.push(format!("line {ln}: unknown record '{other}' (accepted: frame, event, skip, summary)"))
            }
        }
    }
    let Some(s) = summary else {
        c.problems.push(
            "no summary record: the run did not finish its log (killed, or the disk filled before the summary)".into(),
        );
        return c;
    };
    let num = |k: &str| s.get(k).and_then(|v| v.as_u64());
    c.stopped_by = s.get("stopped_by").and_then(|v| v.as_str()).map(str::to_string);
    c.error = s.get("error").and_then(|v| v.as_str()).map(str::to_string);
    // `run` logs count drops by cause; `apply` logs have one `dropped` (all by faults).
    let (dbf, dov) = match (num("dropped_by_fault"), num("dropped_overrun")) {
        (Some(a), Some(b)) => (Some(a), Some(b)),
        _ => (num("dropped"), Some(0)),
    };
    let fields =
        [("frames_in", num("frames_in")), ("delivered", num("delivered")), ("dropped", dbf), ("failed", num("failed"))];
    if let Some((k, _)) = fields.iter().find(|(_, v)| v.is_none()) {
        c.problems.push(format!("summary: no '{k}' count"));
        return c;
    }
    let [inn, del, dbf, fail] = fields.map(|(_, v)| v.unwrap_or(0));
    let dov = dov.unwrap_or(0);
    let sum = del + dbf + dov + fail;
    if inn != sum {
        c.problems.push(format!(
            "unaccounted frames: in {inn} != delivered {del} + dropped by fault {dbf} + dropped by overrun {dov} + failed {fail} = {sum}"
        ));
    }
    if let Some(u) = s.get("unaccounted").and_then(|v| v.as_i64())
        && u != 0
    {
        c.problems.push(format!("summary: {u} unaccounted frames"));
    }
    // Frames whose record could not be written (a full disk) are declared by the summary.
    let unlogged = num("unlogged").unwrap_or(0);
    c.unlogged = unlogged;
    let logged_total = c.counts.iter().sum::<u64>();
    let short = sum.saturating_sub(logged_total);
    for (name, logged, summed) in [
        ("delivered", c.counts[0], del),
        ("dropped by fault", c.counts[1], dbf),
        ("dropped by overrun", c.counts[2], dov),
        ("failed", c.counts[3], fail),
    ] {
        if logged > summed || (logged < summed && unlogged == 0) {
            c.problems.push(format!("{name}: {logged} frame records but the summary says {summed}"));
        }
    }
    if unlogged > 0 && short != unlogged {
        c.problems.push(format!("the summary declares {unlogged} unlogged frame records but {short} are missing"));
    }
    if let Some(h) = num("held")
        && h != held
    {
        c.problems.push(format!("held by effects: {held} records but the summary says {h}"));
    }
    if let Some(k) = num("skipped")
        && k != c.skips
    {
        c.problems.push(format!("skipped inputs: {} skip records but the summary says {k}", c.skips));
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ev(i: u64) -> serde_json::Value {
        serde_json::json!({ "event": "tick", "i": i, "pad": "x".repeat(100) })
    }

    #[test]
    fn a_file_log_is_whole_lines_and_releases_its_reserve() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("gt.jsonl");
        let mut log = GroundTruthLog::create(&path).unwrap();
        for i in 0..50 {
            log.event(&ev(i)).unwrap();
        }
        log.summary(&serde_json::json!({"frames_in": 0, "delivered": 0, "dropped": 0, "failed": 0})).unwrap();
        let bytes = log.bytes();
        drop(log);
        let text = std::fs::read(&path).unwrap();
        assert_eq!(text.len() as u64, bytes, "size is the records, not the reserve");
        let c = check_log(&text);
        assert!(c.ok(), "{:?}", c.problems);
        assert_eq!((c.records, c.events, c.summary), (51, 50, true));
    }

    #[test]
    fn dev_full_gives_named_errors_not_partial_records() {
        // /dev/full: every write fails with ENOSPC (the always-full disk).
        let mut log = GroundTruthLog::create(Path::new("/dev/full")).unwrap();
        let e = log.event(&ev(0)).unwrap_err().to_string();
        assert!(e.contains("No space left") && e.contains("last complete record (0 records)"), "{e}");
        assert!(log.broken().is_some());
        // Later records are refused; the summary is still attempted (and fails here).
        assert!(log.event(&ev(1)).unwrap_err().to_string().contains("record refused"));
        assert!(log.summary(&ev(2)).unwrap_err().to_string().contains("No space left"));
        assert_eq!(log.records(), 0);
    }

    fn frame(seq: u64, status: &str) -> String {
        format!("{{\"record\":\"frame\",\"seq\":{seq},\"pts_ns\":0,\"status\":\"{status}\",\"effects\":[]}}\n")
    }

    #[test]
    fn check_reports_truncation_missing_summary_and_unaccounted_frames() {
        let mut good = String::new();
        good += &frame(0, "delivered");
        good += &frame(1, "dropped_by_fault");
        good += &frame(2, "failed");
        good += "{\"record\":\"skip\",\"item\":\"x.png\",\"reason\":\"corrupt\"}\n";
        let summary = |inn: u64, extra: &str| {
            format!(
                "{{\"record\":\"summary\",\"stopped_by\":\"end_of_stream\",\"frames_in\":{inn},\"delivered\":1,\
                 \"dropped_by_fault\":1,\"dropped_overrun\":0,\"failed\":1,\"held\":0,\"skipped\":1{extra}}}\n"
            )
        };
        let ok = good.clone() + &summary(3, "");
        let c = check_log(ok.as_bytes());
        assert!(c.ok(), "{:?}", c.problems);
        assert_eq!((c.frames, c.skips, c.counts), (3, 1, [1, 1, 0, 1]));

        // A partial last record (a write cut off) and no summary.
        let cut = good.clone() + "{\"record\":\"frame\",\"seq\":3,\"sta";
        let c = check_log(cut.as_bytes());
        assert!(c.problems.iter().any(|p| p.contains("truncated: line 5")), "{:?}", c.problems);
        assert!(c.problems.iter().any(|p| p.contains("no summary")), "{:?}", c.problems);

        // The summary claims 4 in: one frame unaccounted.
        let c = check_log((good.clone() + &summary(4, "")).as_bytes());
        assert!(c.problems.iter().any(|p| p.contains("unaccounted frames: in 4")), "{:?}", c.problems);

        // Records missing without an `unlogged` declaration, then with the right one.
        let short =
            frame(0, "delivered") + &frame(2, "failed") + "{\"record\":\"skip\",\"item\":\"x\",\"reason\":\"r\"}\n";
        let c = check_log((short.clone() + &summary(3, "")).as_bytes());
        assert!(c.problems.iter().any(|p| p.contains("dropped by fault: 0 frame records")), "{:?}", c.problems);
        let c = check_log((short + &summary(3, ",\"unlogged\":1")).as_bytes());
        assert!(c.ok(), "{:?}", c.problems);

        // Garbage lines and records after the summary are named by line.
        let bad = ok.clone() + "not json\n" + &frame(9, "delivered");
        let c = check_log(bad.as_bytes());
        assert!(c.problems.iter().any(|p| p.starts_with("line 6: not a valid JSON")), "{:?}", c.problems);
        assert!(c.problems.iter().any(|p| p.contains("line 7: a frame record after the summary")), "{:?}", c.problems);
    }

    #[test]
    fn low_disk_policy_parses() {
        assert_eq!("drop".parse::<LowDiskPolicy>(), Ok(LowDiskPolicy::Drop));
        assert!("later".parse::<LowDiskPolicy>().unwrap_err().contains("stop or drop"));
        let f = DiskFloor { min_free_mb: 0, dirs: vec![std::env::temp_dir()], policy: LowDiskPolicy::Stop };
        assert_eq!(f.low(), None);
        let f = DiskFloor { min_free_mb: 1 << 40, ..f };
        assert!(f.low().unwrap().contains("under --min-free-mb"));
    }
}
