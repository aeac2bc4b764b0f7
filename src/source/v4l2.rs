//! `v4l2:/dev/videoN` capture source (Video4Linux2, mmap streaming, `v4l` crate).
//!
//! URI: `v4l2:/dev/videoN[?format=GREY|Y16|RGB3|YUYV&width=640&height=480&fps=30&buffers=4&
//! timeout_ms=2000&yuyv=mono8|rgb8]`.
//!
//! * Format negotiation: the requested fourcc/size (or, if none is given, the driver's current
//!   format when faultcam can use it, else the first of GREY, Y16, RGB3, YUYV the driver takes)
//!   is set with `VIDIOC_S_FMT`, and what the driver *chose* (it may change size or format) is
//!   read back and reported by `describe()`; frames follow the chosen format. An explicit
//!   `format=` the driver answers with another fourcc is an error naming both.
//! * Pixel formats: `GREY` → mono8, `Y16` (little-endian) → mono16, `RGB3` → rgb8, 8-bit Bayer
//!   (`BA81`, `GBRG`, `GRBG`, `RGGB`) → bayer8, `YUYV` → mono8 (the Y samples, exact) or, with
//!   `yuyv=rgb8`, rgb8 by ITU-R BT.601 limited range (`R = 1.164(Y−16) + 1.596(V−128)`, `G =
//!   1.164(Y−16) − 0.392(U−128) − 0.813(V−128)`, `B = 1.164(Y−16) + 2.017(U−128)`, rounded and
//!   clipped; U, V shared by the pixel pair).
//! * Rows are read with the driver's `bytesperline` (padding is dropped). `pts_ns` is the
//!   driver timestamp; `seq` counts from the first buffer's sequence number, so frames the
//!   driver dropped leave a gap and are reported one by one as recoverable errors (logged as
//!   `skip` records), as are buffers flagged `ERROR` or shorter than a frame. A driver whose
//!   sequence numbers do not advance (v4l2loopback 0.12.7 leaves them at 0 when the writer uses
//!   streaming I/O) gets consecutive numbers instead (no gaps can be seen then).
//! * No buffer within `timeout_ms` ends the stream with an error naming the device.

use super::{Source, SourceError, UriOptions, split_uri};
use crate::frame::{Frame, PixelFormat};
use crate::pipeline::pool::{FramePool, copy_rows_into};
use std::collections::VecDeque;
use std::time::Duration;
use v4l::buffer::Type;
use v4l::io::mmap::Stream as MmapStream;
use v4l::io::traits::{CaptureStream, Stream as _};
use v4l::video::Capture;
use v4l::{Device, Format, FourCC};

/// How a V4L2 fourcc maps to frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    Grey,
    Y16,
    Rgb3,
    Bayer8,
    /// YUYV 4:2:2 converted to mono8 (Y only) or rgb8 (BT.601).
    Yuyv(PixelFormat),
}

impl Layout {
    pub fn from_fourcc(f: &[u8; 4], yuyv: PixelFormat) -> Option<Layout> {
        Some(match f {
            b"GREY" => Layout::Grey,
            b"Y16 " => Layout::Y16,
            b"RGB3" => Layout::Rgb3,
            b"BA81" | b"GBRG" | b"GRBG" | b"RGGB" => Layout::Bayer8,
            b"YUYV" => Layout::Yuyv(yuyv),
            _ => return None,
        })
    }
    pub fn pixel_format(self) -> PixelFormat {
        match self {
            Layout::Grey => PixelFormat::Mono8,
            Layout::Y16 => PixelFormat::Mono16,
            Layout::Rgb3 => PixelFormat::Rgb8,
            Layout::Bayer8 => PixelFormat::Bayer8,
            Layout::Yuyv(p) => p,
        }
    }
    /// Bytes per pixel in the V4L2 buffer.
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            Layout::Grey | Layout::Bayer8 => 1,
            Layout::Y16 | Layout::Yuyv(_) => 2,
            Layout::Rgb3 => 3,
        }
    }
}

/// Parse a fourcc option (`GREY`, `Y16`, ...), padding short codes with spaces.
pub fn parse_fourcc(s: &str) -> Option<[u8; 4]> {
    let b = s.as_bytes();
    if b.is_empty() || b.len() > 4 || !b.iter().all(|c| c.is_ascii_graphic()) {
        return None;
    }
    let mut f = [b' '; 4];
    f[..b.len()].copy_from_slice(b);
    Some(f)
}

#[inline]
fn clip(v: f32) -> u8 {
    (v + 0.5).clamp(0.0, 255.0) as u8
}

/// One YUYV row (`Y0 U Y1 V` per pixel pair) into mono8 (Y) or rgb8 (BT.601 limited range).
pub fn yuyv_row(src: &[u8], width: usize, out: PixelFormat, dst: &mut [u8]) {
    match out {
        PixelFormat::Rgb8 => {
            for x in 0..width {
                let pair = (x / 2) * 4;
                let y = src[x * 2] as f32 - 16.0;
                let u = src[pair + 1] as f32 - 128.0;
                let v = src[pair + 3] as f32 - 128.0;
                let o = &mut dst[x * 3..x * 3 + 3];
                o[0] = clip(1.164 * y + 1.596 * v);
                o[1] = clip(1.164 * y - 0.392 * u - 0.813 * v);
                o[2] = clip(1.164 * y + 2.017 * u);
            }
        }
        _ => {
            for (x, d) in dst[..width].iter_mut().enumerate() {
                *d = src[x * 2];
            }
        }
    }
}

/// Longest run of frames the driver may drop that is counted as a gap; a longer jump of its
/// sequence number (a writer that restarted, a reset counter) continues the numbering instead
/// of being read as billions of dropped frames.
const MAX_GAP: u64 = 1024;

/// A frame's number from the driver's sequence number `raw` (relative to the first buffer's):
/// the driver's steps while it advances by 1..=`MAX_GAP + 1` (a step of k leaves a gap of k - 1
/// frames the driver dropped), else `next`, the number after the last frame's (a driver whose
/// sequence numbers stay put, go back or jump far).
fn frame_seq(last_raw: Option<u64>, raw: u64, next: u64) -> u64 {
    match last_raw.map(|l| raw.wrapping_sub(l)) {
        Some(step) if (1..=MAX_GAP + 1).contains(&step) => next + step - 1,
        _ => next,
    }
}

/// An open, streaming capture device.
pub struct V4l2Source {
    uri: String,
    path: String,
    // Declared before `device`: the stream is stopped and unmapped first.
    stream: Option<MmapStream<'static>>,
    device: Device,
    layout: Layout,
    width: u32,
    height: u32,
    bytesperline: usize,
    chosen: String,
    pool: FramePool,
    first_seq: Option<u32>,
    /// The last buffer's driver sequence number, relative to the first.
    last_raw: Option<u64>,
    next: u64,
    gaps: VecDeque<u64>,
    ready: Option<Frame>,
}

impl V4l2Source {
    pub fn open(uri: &str) -> Result<V4l2Source, SourceError> {
        let (_, path, opts) = split_uri(uri);
        let bad = |reason: String| SourceError::BadUri { uri: uri.to_string(), reason };
        if path.is_empty() {
            return Err(bad("expected v4l2:/dev/videoN".into()));
        }
        let mut o = UriOptions::new(opts);
        let fourcc = match o.raw("format") {
            Some(f) => Some(parse_fourcc(&f).ok_or_else(|| bad(format!("format={f} is not a fourcc such as GREY")))?),
            None => None,
        };
        let width = o.int("width", 1, 16384).map_err(bad)?;
        let height = o.int("height", 1, 16384).map_err(bad)?;
        let fps = o.int("fps", 1, 1000).map_err(bad)?;
        let buffers = o.int("buffers", 2, 32).map_err(bad)?.unwrap_or(4);
        let timeout_ms = o.int("timeout_ms", 10, 600_000).map_err(bad)?.unwrap_or(2000);
        let yuyv = match o.raw("yuyv").as_deref() {
            None | Some("mono8") => PixelFormat::Mono8,
            Some("rgb8") => PixelFormat::Rgb8,
            Some(v) => return Err(bad(format!("yuyv={v} is not accepted; expected mono8 or rgb8"))),
        };
        o.finish().map_err(bad)?;

        let fatal = |reason: String| SourceError::Fatal { uri: uri.to_string(), reason };
        let device = Device::with_path(path).map_err(|e| fatal(format!("cannot open {path}: {e}")))?;
        let caps = device.query_caps().map_err(|e| fatal(format!("{path}: VIDIOC_QUERYCAP: {e}")))?;
        let flags = caps.capabilities;
        if !flags.contains(v4l::capability::Flags::VIDEO_CAPTURE) {
            return Err(fatal(format!(
                "{path} ({}, {}) is not a capture device (capabilities {flags}); a v4l2loopback device \
                 with exclusive_caps=1 becomes capturable once a writer has opened it",
                caps.card, caps.driver
            )));
        }
        if !flags.contains(v4l::capability::Flags::STREAMING) {
            return Err(fatal(format!("{path} ({}) does not support streaming I/O", caps.card)));
        }
        let current = device.format().map_err(|e| fatal(format!("{path}: VIDIOC_G_FMT: {e}")))?;
        let usable = |f: &[u8; 4]| Layout::from_fourcc(f, yuyv).is_some();
        let candidates: Vec<[u8; 4]> = match fourcc {
            Some(f) => vec![f],
            None if usable(&current.fourcc.repr) => vec![current.fourcc.repr],
            None => vec![*b"GREY", *b"Y16 ", *b"RGB3", *b"YUYV"],
        };
        let mut chosen: Option<Format> = None;
        let mut tried = Vec::new();
        for f in candidates {
            let mut want = current;
            want.fourcc = FourCC::new(&f);
            if let Some(w) = width {
                want.width = w as u32;
            }
            if let Some(h) = height {
                want.height = h as u32;
            }
            match device.set_format(&want) {
                // An explicit `format=` must be what the driver chose (it answers a fourcc it
                // does not have with one of its own).
                Ok(got) if fourcc.is_some() && got.fourcc.repr != f => {
                    tried.push(format!("{} (driver chose {})", FourCC::new(&f), got.fourcc))
                }
                Ok(got) if usable(&got.fourcc.repr) => {
                    chosen = Some(got);
                    break;
                }
                Ok(got) => tried.push(format!("{} (driver chose {})", FourCC::new(&f), got.fourcc)),
                Err(e) => tried.push(format!("{} ({e})", FourCC::new(&f))),
            }
        }
        let fmt = chosen.ok_or_else(|| {
            fatal(format!(
                "{path}: no usable pixel format; tried {}; faultcam reads GREY, Y16, RGB3, YUYV, 8-bit Bayer",
                tried.join(", ")
            ))
        })?;
        let layout = Layout::from_fourcc(&fmt.fourcc.repr, yuyv)
            .ok_or_else(|| fatal(format!("{path}: unusable format {}", fmt.fourcc)))?;
        if let Some(f) = fps {
            // Not every driver supports frame intervals; what it chose is read back below.
            let _ = device.set_params(&v4l::video::capture::Parameters::with_fps(f as u32));
        }
        let rate = device
            .params()
            .ok()
            .filter(|p| p.interval.numerator > 0)
            .map(|p| format!(", {:.2} fps", p.interval.denominator as f64 / p.interval.numerator as f64))
            .unwrap_or_default();
        // The negotiated size is checked against the image limits before buffers are mapped.
        let pf = layout.pixel_format();
        crate::limits::ImageLimits::current()
            .check("the negotiated format", fmt.width, fmt.height, (pf.channels() * pf.bytes_per_sample()) as u64)
            .map_err(|e| fatal(format!("{path}: {e}")))?;
        let min_stride = fmt.width as usize * layout.bytes_per_pixel();
        let bytesperline = (fmt.stride as usize).max(min_stride);
        let note = match (width, height) {
            (Some(w), _) if w as u32 != fmt.width => " (driver changed the width)",
            (_, Some(h)) if h as u32 != fmt.height => " (driver changed the height)",
            _ => "",
        };
        let chosen = format!(
            "{} {}: {}x{} {} → {}, bytesperline {bytesperline}{rate}{note}",
            caps.card,
            caps.driver,
            fmt.width,
            fmt.height,
            fmt.fourcc,
            layout.pixel_format()
        );
        let mut stream = MmapStream::with_buffers(&device, Type::VideoCapture, buffers as u32)
            .map_err(|e| fatal(format!("{path}: cannot map {buffers} buffers: {e}")))?;
        stream.set_timeout(Duration::from_millis(timeout_ms));
        Ok(V4l2Source {
            uri: uri.to_string(),
            path: path.to_string(),
            stream: Some(stream),
            device,
            layout,
            width: fmt.width,
            height: fmt.height,
            bytesperline,
            chosen,
            pool: FramePool::new(8),
            first_seq: None,
            last_raw: None,
            next: 0,
            gaps: VecDeque::new(),
            ready: None,
        })
    }

    fn fatal(&self, reason: String) -> SourceError {
        SourceError::Fatal { uri: self.uri.clone(), reason }
    }

    /// The device this source streams from (for controls).
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The next frame, or `Ok(None)` when none came within `timeout_ms` (the stream stays
    /// usable: call again). Errors as [`Source::next_frame`]'s.
    pub fn poll_frame(&mut self) -> Result<Option<Frame>, SourceError> {
        self.read(true)
    }

    /// [`Source::next_frame`]; with `poll`, no buffer within the timeout is `Ok(None)` instead
    /// of an error ending the stream.
    fn read(&mut self, poll: bool) -> Result<Option<Frame>, SourceError> {
        if let Some(seq) = self.gaps.pop_front() {
            return Err(SourceError::BadInput {
                item: format!("{} frame {seq}", self.path),
                reason: "dropped by the driver (gap in buffer sequence numbers)".into(),
            });
        }
        if let Some(f) = self.ready.take() {
            return Ok(Some(f));
        }
        let (w, h) = (self.width, self.height);
        let pf = self.layout.pixel_format();
        let mut frame = self.pool.take(w, h, pf).map_err(|e| self.fatal(e.to_string()))?;
        let Some(stream) = self.stream.as_mut() else {
            return Err(SourceError::Fatal { uri: self.uri.clone(), reason: "stream closed".into() });
        };
        let (buf, meta) = match CaptureStream::next(stream) {
            Ok(x) => x,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut && poll => {
                self.pool.give(frame);
                return Ok(None);
            }
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {
                return Err(SourceError::Fatal {
                    uri: self.uri.clone(),
                    reason: format!("{}: no frame within the timeout (device stopped or unplugged?)", self.path),
                });
            }
            Err(e) => {
                return Err(SourceError::Fatal {
                    uri: self.uri.clone(),
                    reason: format!("{}: VIDIOC_DQBUF: {e}", self.path),
                });
            }
        };
        let first = *self.first_seq.get_or_insert(meta.sequence);
        // A driver whose sequence numbers do not advance (v4l2loopback 0.12 leaves them at 0 for
        // a streaming-I/O writer) gets consecutive numbers: without them every frame would be
        // frame 0 (a `files:` sink then writes one file, over and over).
        let raw = meta.sequence.wrapping_sub(first) as u64;
        let seq = frame_seq(self.last_raw, raw, self.next);
        self.last_raw = Some(raw);
        let pts_ns = meta.timestamp.sec.max(0) as u64 * 1_000_000_000 + meta.timestamp.usec.max(0) as u64 * 1000;
        let need = self.bytesperline * (h as usize - 1) + w as usize * self.layout.bytes_per_pixel();
        let used = if meta.bytesused == 0 { buf.len() } else { (meta.bytesused as usize).min(buf.len()) };
        let problem = if meta.flags.contains(v4l::buffer::Flags::ERROR) {
            Some("buffer flagged ERROR by the driver".to_string())
        } else if used < need {
            Some(format!("short buffer: {used} bytes, a frame needs {need}"))
        } else {
            None
        };
        if problem.is_none() {
            match self.layout {
                Layout::Yuyv(out) => {
                    let row = frame.row_len();
                    let stride = frame.stride;
                    if let Some(d) = frame.as_u8_mut() {
                        for y in 0..h as usize {
                            let src = &buf[y * self.bytesperline..];
                            yuyv_row(src, w as usize, out, &mut d[y * stride..y * stride + row]);
                        }
                    }
                }
                _ => {
                    if let Err(e) = copy_rows_into(&mut frame, &buf[..used], self.bytesperline) {
                        return Err(SourceError::Fatal { uri: self.uri.clone(), reason: e.to_string() });
                    }
                }
            }
        }
        if seq > self.next {
            for missing in self.next..seq {
                self.gaps.push_back(missing);
            }
        }
        self.next = self.next.max(seq + 1);
        if let Some(reason) = problem {
            self.pool.give(frame);
            return Err(SourceError::BadInput { item: format!("{} frame {seq}", self.path), reason });
        }
        frame.seq = seq;
        frame.pts_ns = pts_ns;
        if self.gaps.is_empty() {
            Ok(Some(frame))
        } else {
            self.ready = Some(frame);
            self.read(poll)
        }
    }
}

impl Source for V4l2Source {
    fn describe(&self) -> String {
        format!("{} ({})", self.uri, self.chosen)
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, SourceError> {
        self.read(false)
    }

    fn recycle(&mut self, frame: Frame) {
        self.pool.give(frame);
    }
}

impl Drop for V4l2Source {
    fn drop(&mut self) {
        if let Some(mut s) = self.stream.take() {
            // The v4l stream panics in its Drop if STREAMOFF fails; stop it here and, should
            // that fail, leak it rather than panic.
            if s.stop().is_err() {
                std::mem::forget(s);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fourccs_map_to_frame_formats() {
        assert_eq!(parse_fourcc("Y16"), Some(*b"Y16 "));
        assert_eq!(parse_fourcc("GREY"), Some(*b"GREY"));
        assert_eq!(parse_fourcc("TOOLONG"), None);
        assert_eq!(
            Layout::from_fourcc(b"Y16 ", PixelFormat::Mono8).map(Layout::pixel_format),
            Some(PixelFormat::Mono16)
        );
        assert_eq!(Layout::from_fourcc(b"YUYV", PixelFormat::Rgb8).map(Layout::pixel_format), Some(PixelFormat::Rgb8));
        assert_eq!(Layout::from_fourcc(b"MJPG", PixelFormat::Mono8), None);
    }

    #[test]
    fn yuyv_conversion_bt601() {
        // Two pixel pairs: black/white grey (U=V=128), then saturated red-ish chroma.
        let src = [16u8, 128, 235, 128, 81, 90, 81, 240];
        let mut mono = [0u8; 4];
        yuyv_row(&src, 4, PixelFormat::Mono8, &mut mono);
        assert_eq!(mono, [16, 235, 81, 81], "mono8 is the Y samples, exact");
        let mut rgb = [0u8; 12];
        yuyv_row(&src, 4, PixelFormat::Rgb8, &mut rgb);
        assert_eq!(&rgb[..6], &[0, 0, 0, 255, 255, 255], "limited-range black and white");
        // BT.601 red (R=255,G=0,B=0) is Y=81, U=90, V=240: back to ~red within rounding.
        assert!(rgb[6] >= 250 && rgb[7] <= 3 && rgb[8] <= 3, "{:?}", &rgb[6..9]);
    }

    #[test]
    fn frame_numbers_follow_the_driver_or_count_when_it_is_stuck() {
        let run = |raws: &[u64]| {
            let (mut last, mut next, mut out) = (None, 0, Vec::new());
            for &r in raws {
                let s = frame_seq(last, r, next);
                last = Some(r);
                next = next.max(s + 1);
                out.push(s);
            }
            out
        };
        assert_eq!(run(&[0, 1, 2, 5, 6]), [0, 1, 2, 5, 6], "an advancing driver's numbers, gaps kept");
        assert_eq!(run(&[0, 0, 0, 0]), [0, 1, 2, 3], "v4l2loopback 0.12.7 (mmap writer): all 0");
        assert_eq!(run(&[0, 1, 2, 1, 2, 3]), [0, 1, 2, 3, 4, 5], "a sequence that goes back");
        // A sequence number far behind the first one (a restarted writer: u32 differences wrap
        // to ~4e9) or far ahead is a jump, not billions of dropped frames; gaps resume after it.
        let far = u32::MAX as u64 - 95;
        assert_eq!(run(&[0, 1, far, far + 1, far + 3]), [0, 1, 2, 3, 5], "a restarted writer");
        assert_eq!(run(&[0, 1, 1 + MAX_GAP + 2, 1 + MAX_GAP + 3]), [0, 1, 2, 3], "a jump past the largest gap");
        assert_eq!(run(&[0, 1 + MAX_GAP]), [0, 1 + MAX_GAP], "the largest gap (MAX_GAP frames) is counted");
    }

    #[test]
    fn missing_device_is_a_clear_error() {
        let e = V4l2Source::open("v4l2:/dev/video-faultcam-none").err().unwrap().to_string();
        assert!(e.contains("/dev/video-faultcam-none"), "{e}");
        let e = V4l2Source::open("v4l2:/dev/video0?colour=1").err().unwrap().to_string();
        assert!(e.contains("colour") && e.contains("format"), "{e}");
    }
}
