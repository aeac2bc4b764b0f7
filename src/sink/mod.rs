//! Frame sinks, named by URI: `files:DIR`, `gst:PIPELINE`, `v4l2:/dev/videoN`, `null:`.

pub mod files;
#[cfg(feature = "gst")]
pub mod gst;
pub mod null;
#[cfg(feature = "v4l2")]
pub mod v4l2;

use crate::frame::Frame;
use thiserror::Error;

/// Errors of sinks.
#[derive(Debug, Error)]
pub enum SinkError {
    #[error("{uri}: {reason}")]
    Failed { uri: String, reason: String },
    #[error("bad sink '{uri}': {reason}")]
    BadUri { uri: String, reason: String },
    /// The consumer went away (closed pipe, EOS downstream): stop quietly.
    #[error("{uri}: consumer closed")]
    Closed { uri: String },
}

/// Where faulted frames go.
pub trait Sink: Send {
    fn describe(&self) -> String;
    /// Write one frame. `name` is the input item name when known (files keep names).
    fn write_frame(&mut self, frame: &Frame, name: Option<&str>) -> Result<(), SinkError>;
    /// Name of the last written output (file path), for the ground-truth log.
    fn last_output(&self) -> Option<&str> {
        None
    }
    /// Flush and close (EOS for pipelines).
    fn finish(&mut self) -> Result<(), SinkError> {
        Ok(())
    }
}
