//! Frame sources, named by URI: `files:DIR`, `synth:`, `gst:PIPELINE`, `v4l2:/dev/videoN`,
//! `aravis:CAMERA`. Each implementation lives in its own file.

#[cfg(feature = "aravis")]
pub mod aravis;
pub mod files;
#[cfg(feature = "gst")]
pub mod gst;
pub mod synth;
#[cfg(feature = "v4l2")]
pub mod v4l2;

use crate::frame::Frame;
use thiserror::Error;

/// Errors of sources.
#[derive(Debug, Error)]
pub enum SourceError {
    /// One input item is bad (corrupt file, wrong size): log it, skip it, keep going.
    #[error("{item}: {reason}")]
    BadInput { item: String, reason: String },
    /// The source cannot continue.
    #[error("{uri}: {reason}")]
    Fatal { uri: String, reason: String },
    /// The URI or its options are wrong.
    #[error("bad source '{uri}': {reason}")]
    BadUri { uri: String, reason: String },
}

impl SourceError {
    /// True when the stream can continue after this error (the item is skipped).
    pub fn recoverable(&self) -> bool {
        matches!(self, SourceError::BadInput { .. })
    }
}

/// A stream of frames.
pub trait Source: Send {
    /// What was opened and the negotiated format (reported, not assumed).
    fn describe(&self) -> String;
    /// Next frame, `Ok(None)` at the end of the stream. A recoverable error skips one item;
    /// call again to continue.
    fn next_frame(&mut self) -> Result<Option<Frame>, SourceError>;
    /// Name of the input item the last frame came from (file name), if any.
    fn item_name(&self) -> Option<&str> {
        None
    }
    /// Give a frame back so its buffer can be reused (frame pool). Default: drop it.
    fn recycle(&mut self, _frame: Frame) {}
}

/// Split `scheme:rest?k=v&k2=v2` into scheme, rest and options.
pub fn split_uri(uri: &str) -> (&str, &str, Vec<(String, String)>) {
    let (scheme, rest) = uri.split_once(':').unwrap_or((uri, ""));
    let (body, query) = match rest.rsplit_once('?') {
        Some((b, q)) if !q.contains(' ') && q.contains('=') => (b, q),
        _ => (rest, ""),
    };
    let opts = query
        .split('&')
        .filter(|s| !s.is_empty())
        .map(|kv| {
            let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
            (k.to_string(), v.to_string())
        })
        .collect();
    (scheme, body, opts)
}

#[cfg(test)]
mod tests {
    #[test]
    fn split_uri_parts() {
        let (s, r, o) = super::split_uri("synth:?width=64&height=32");
        assert_eq!((s, r), ("synth", ""));
        assert_eq!(o, vec![("width".into(), "64".into()), ("height".into(), "32".into())]);
        let (s, r, o) = super::split_uri("gst:videotestsrc num-buffers=3 ! appsink");
        assert_eq!((s, r), ("gst", "videotestsrc num-buffers=3 ! appsink"));
        assert!(o.is_empty());
    }
}
