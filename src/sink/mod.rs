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

/// URI schemes [`open`] accepts.
pub const SCHEMES: &[&str] = &["files", "null", "gst", "v4l2"];

/// Open a sink by URI: `files:DIR?format=png`, `null:`.
pub fn open(uri: &str) -> Result<Box<dyn Sink>, SinkError> {
    let (scheme, _, _) = crate::source::split_uri(uri);
    match scheme {
        "files" => Ok(Box::new(files::FilesSink::open(uri)?)),
        "null" => Ok(Box::new(null::NullSink::open(uri)?)),
        #[cfg(feature = "gst")]
        "gst" => Ok(Box::new(gst::GstSink::open(uri)?)),
        #[cfg(feature = "v4l2")]
        "v4l2" => Ok(Box::new(v4l2::V4l2Sink::open(uri)?)),
        other => Err(SinkError::BadUri {
            uri: uri.to_string(),
            reason: format!(
                "unknown scheme '{other}:'; accepted: {}",
                SCHEMES.iter().map(|s| format!("{s}:")).collect::<Vec<_>>().join(", ")
            ),
        }),
    }
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
