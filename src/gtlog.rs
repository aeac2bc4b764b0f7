//! Ground-truth log: JSON Lines, one record per input frame (whatever happened to it) plus
//! event records (timeline, triggers, skipped inputs, summary).

use crate::faults::chain::{AppliedEffect, FrameReport};
use serde::Serialize;
use std::fs::File;
use std::io::{BufWriter, Write};
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

/// JSON Lines writer. Every line has a `record` field: `frame`, `event`, `skip` or `summary`.
pub struct GroundTruthLog {
    out: Box<dyn Write + Send>,
}

impl GroundTruthLog {
    pub fn create(path: &Path) -> std::io::Result<GroundTruthLog> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        Ok(GroundTruthLog { out: Box::new(BufWriter::new(File::create(path)?)) })
    }
    /// A log into any writer (tests, stdout).
    pub fn to_writer(w: Box<dyn Write + Send>) -> GroundTruthLog {
        GroundTruthLog { out: w }
    }
    fn line<T: Serialize>(&mut self, record: &'static str, body: &T) -> std::io::Result<()> {
        serde_json::to_writer(&mut self.out, &Tagged { record, body })?;
        self.out.write_all(b"\n")
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
    pub fn summary<T: Serialize>(&mut self, s: &T) -> std::io::Result<()> {
        self.line("summary", s)
    }
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}
