//! Frame sources, named by URI: `files:DIR`, `synth:`, `gst:PIPELINE`, `v4l2:/dev/videoN`,
//! `aravis:CAMERA`. Each implementation lives in its own file.

#[cfg(feature = "aravis")]
pub mod aravis;
pub mod files;
pub mod frame_ids;
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
    /// Pose truth and camera intrinsics of the last frame, when the source knows them
    /// (`synth:` always, `files:` with `poses=FILE`). Convention: [`crate::pose`].
    fn truth(&self) -> crate::pose::Truth {
        crate::pose::Truth::default()
    }
    /// Give a frame back so its buffer can be reused (frame pool). Default: drop it.
    fn recycle(&mut self, _frame: Frame) {}
}

/// URI schemes [`open`] accepts.
pub const SCHEMES: &[&str] = &["files", "synth", "gst", "v4l2", "aravis"];

/// Open a source by URI: `files:DIR?loop=true&fps=30`, `synth:?width=640&height=480`.
/// Every implementation reports what it opened (and the negotiated format) in `describe()`.
pub fn open(uri: &str) -> Result<Box<dyn Source>, SourceError> {
    let (scheme, _, _) = split_uri(uri);
    match scheme {
        "files" => Ok(Box::new(files::FilesSource::open(uri)?)),
        "synth" => Ok(Box::new(synth::SynthSource::open(uri)?)),
        #[cfg(feature = "gst")]
        "gst" => Ok(Box::new(gst::GstSource::open(uri)?)),
        #[cfg(feature = "aravis")]
        "aravis" => Ok(Box::new(aravis::AravisSource::open(uri)?)),
        #[cfg(feature = "v4l2")]
        "v4l2" => Ok(Box::new(v4l2::V4l2Source::open(uri)?)),
        other => Err(SourceError::BadUri {
            uri: uri.to_string(),
            reason: format!(
                "unknown scheme '{other}:'; accepted: {}",
                SCHEMES.iter().map(|s| format!("{s}:")).collect::<Vec<_>>().join(", ")
            ),
        }),
    }
}

/// Typed access to the `?k=v&...` options of a URI. Each getter marks its key as used;
/// [`UriOptions::finish`] rejects keys nobody asked for, naming the accepted ones. Errors are
/// plain messages: sources wrap them in [`SourceError::BadUri`], sinks in `SinkError::BadUri`.
#[derive(Debug, Clone)]
pub struct UriOptions {
    opts: Vec<(String, String)>,
    used: Vec<bool>,
    accepted: Vec<&'static str>,
}

impl UriOptions {
    pub fn new(opts: Vec<(String, String)>) -> UriOptions {
        let used = vec![false; opts.len()];
        UriOptions { opts, used, accepted: Vec::new() }
    }

    /// Raw value of `key` (the last one wins when repeated).
    pub fn raw(&mut self, key: &'static str) -> Option<String> {
        self.accepted.push(key);
        let mut found = None;
        for (i, (k, v)) in self.opts.iter().enumerate() {
            if k == key {
                self.used[i] = true;
                found = Some(v.clone());
            }
        }
        found
    }

    /// Parsed value of `key`; `expected` describes the accepted values for the error message.
    pub fn get<T: std::str::FromStr>(&mut self, key: &'static str, expected: &str) -> Result<Option<T>, String> {
        match self.raw(key) {
            None => Ok(None),
            Some(v) => {
                v.parse::<T>().map(Some).map_err(|_| format!("option {key}={v} is not accepted; expected {expected}"))
            }
        }
    }

    /// A number in `lo..=hi`.
    pub fn num(&mut self, key: &'static str, lo: f64, hi: f64) -> Result<Option<f64>, String> {
        let expected = format!("a number in {lo}..={hi}");
        match self.get::<f64>(key, &expected)? {
            Some(v) if !(lo..=hi).contains(&v) => Err(format!("option {key}={v} is out of range; expected {expected}")),
            other => Ok(other),
        }
    }

    /// An integer in `lo..=hi`.
    pub fn int(&mut self, key: &'static str, lo: u64, hi: u64) -> Result<Option<u64>, String> {
        let expected = format!("an integer in {lo}..={hi}");
        match self.get::<u64>(key, &expected)? {
            Some(v) if !(lo..=hi).contains(&v) => Err(format!("option {key}={v} is out of range; expected {expected}")),
            other => Ok(other),
        }
    }

    /// `true`/`false` (also `1`/`0`, `yes`/`no`; a bare `key` means true).
    pub fn flag(&mut self, key: &'static str) -> Result<Option<bool>, String> {
        match self.raw(key).as_deref() {
            None => Ok(None),
            Some("" | "true" | "1" | "yes" | "on") => Ok(Some(true)),
            Some("false" | "0" | "no" | "off") => Ok(Some(false)),
            Some(v) => Err(format!("option {key}={v} is not accepted; expected true or false")),
        }
    }

    /// Error on any option no getter asked for.
    pub fn finish(&self) -> Result<(), String> {
        match self.opts.iter().zip(&self.used).find(|(_, u)| !**u) {
            None => Ok(()),
            Some(((k, _), _)) => Err(format!("unknown option '{k}'; accepted: {}", self.accepted.join(", "))),
        }
    }
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

/// `uri` with the option `key=value` added unless it already sets `key`.
pub fn with_default_option(uri: &str, key: &str, value: &str) -> String {
    let (_, _, opts) = split_uri(uri);
    if opts.iter().any(|(k, _)| k == key) {
        uri.to_string()
    } else {
        format!("{uri}{}{key}={value}", if opts.is_empty() { "?" } else { "&" })
    }
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
