//! `null:` sink: discards frames (benchmarks, soak tests, dry runs). Counts what it got.

use super::{Sink, SinkError};
use crate::frame::Frame;

/// The `null:` sink.
#[derive(Debug, Default)]
pub struct NullSink {
    frames: u64,
}

impl NullSink {
    pub fn open(uri: &str) -> Result<NullSink, SinkError> {
        let (_, body, opts) = crate::source::split_uri(uri);
        if !body.is_empty() || !opts.is_empty() {
            return Err(SinkError::BadUri { uri: uri.to_string(), reason: "null: takes no path or options".into() });
        }
        Ok(NullSink::default())
    }
    /// Frames received so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }
}

impl Sink for NullSink {
    fn describe(&self) -> String {
        "null: (frames are discarded)".to_string()
    }
    fn write_frame(&mut self, _frame: &Frame, _name: Option<&str>) -> Result<(), SinkError> {
        self.frames += 1;
        Ok(())
    }
}
