//! `v4l2:/dev/videoN` output sink, for a v4l2loopback device (see `hil/v4l2loopback.md`):
//! faulted frames appear as a camera that any V4L2 application (the vision stack under
//! test, GStreamer `v4l2src`, ffplay, a browser) can open.
//!
//! URI: `v4l2:/dev/videoN[?format=GREY|Y16|RGB3|YUYV&fps=30]`.
//!
//! * The output format is set on the first frame (`VIDIOC_S_FMT` on the output queue): by
//!   default the frame's own layout (mono8 → `GREY`, mono16 → `Y16`, rgb8 → `RGB3`, bayer8 →
//!   `GREY`); `format=YUYV` converts for consumers that need YUYV (mono8: U = V = 128; rgb8:
//!   ITU-R BT.601 limited range; mono16: the high byte). What the driver chose is checked:
//!   a different size or fourcc is an error naming both. Later frames must keep the size.
//! * Each frame is written with `write(2)` on the device (v4l2loopback's read/write I/O, as
//!   ffmpeg's v4l2 output does): it is handed to readers at once, with no extra frame of
//!   queueing. Rows are laid out with the driver's `bytesperline` from one buffer allocated
//!   once per stream.

use super::{Sink, SinkError};
use crate::frame::{Frame, FrameData, PixelFormat};
use crate::source::split_uri;
use crate::source::v4l2::parse_fourcc;
use std::io::Write;
use std::mem::ManuallyDrop;
use std::os::fd::FromRawFd;
use v4l::video::Output;
use v4l::{Device, FourCC};

/// `POLLOUT` (Linux).
const POLLOUT: i16 = 0x004;
/// How long a write waits for the device to accept a frame.
const WRITE_TIMEOUT_MS: i32 = 2000;

/// An open output device.
pub struct V4l2Sink {
    uri: String,
    path: String,
    device: Device,
    want: Option<[u8; 4]>,
    fps: Option<u64>,
    shape: Option<(u32, u32, PixelFormat)>,
    fourcc: [u8; 4],
    bytesperline: usize,
    // allocation: once per stream (one frame in the driver's layout)
    buf: Vec<u8>,
    chosen: String,
}

#[inline]
fn clip(v: f32) -> u8 {
    (v + 0.5).clamp(0.0, 255.0) as u8
}

/// BT.601 limited-range Y, U, V of an RGB pixel.
fn yuv601(r: f32, g: f32, b: f32) -> (u8, u8, u8) {
    let y = 16.0 + 0.257 * r + 0.504 * g + 0.098 * b;
    let u = 128.0 - 0.148 * r - 0.291 * g + 0.439 * b;
    let v = 128.0 + 0.439 * r - 0.368 * g - 0.071 * b;
    (clip(y), clip(u), clip(v))
}

/// Write one frame row into a YUYV row (pairs `Y0 U Y1 V`).
pub fn row_to_yuyv(frame: &Frame, y: usize, dst: &mut [u8]) {
    let w = frame.width as usize;
    let c = frame.channels();
    match &frame.data {
        FrameData::U8(d) if frame.format == PixelFormat::Rgb8 => {
            let row = &d[y * frame.stride..y * frame.stride + w * c];
            let mut x = 0;
            while x < w {
                let x1 = (x + 1).min(w - 1);
                let p0 = &row[x * 3..x * 3 + 3];
                let p1 = &row[x1 * 3..x1 * 3 + 3];
                let (y0, u0, v0) = yuv601(p0[0] as f32, p0[1] as f32, p0[2] as f32);
                let (y1, u1, v1) = yuv601(p1[0] as f32, p1[1] as f32, p1[2] as f32);
                let o = x * 2;
                dst[o] = y0;
                dst[o + 1] = (u0 as u16 + u1 as u16).div_ceil(2) as u8;
                if o + 2 < dst.len() {
                    dst[o + 2] = y1;
                }
                if o + 3 < dst.len() {
                    dst[o + 3] = (v0 as u16 + v1 as u16).div_ceil(2) as u8;
                }
                x += 2;
            }
        }
        FrameData::U8(d) => {
            for (x, &v) in d[y * frame.stride..y * frame.stride + w].iter().enumerate() {
                dst[x * 2] = v;
                dst[x * 2 + 1] = 128;
            }
        }
        FrameData::U16(d) => {
            for (x, &v) in d[y * frame.stride..y * frame.stride + w].iter().enumerate() {
                dst[x * 2] = (v >> 8) as u8;
                dst[x * 2 + 1] = 128;
            }
        }
    }
}

impl V4l2Sink {
    pub fn open(uri: &str) -> Result<V4l2Sink, SinkError> {
        let (_, path, opts) = split_uri(uri);
        let bad = |reason: String| SinkError::BadUri { uri: uri.to_string(), reason };
        if path.is_empty() {
            return Err(bad("expected v4l2:/dev/videoN (a v4l2loopback device)".into()));
        }
        let mut o = crate::source::UriOptions::new(opts);
        let want = match o.raw("format") {
            Some(f) => {
                let fc = parse_fourcc(&f).ok_or_else(|| bad(format!("format={f} is not a fourcc such as GREY")))?;
                if !matches!(&fc, b"GREY" | b"Y16 " | b"RGB3" | b"YUYV") {
                    return Err(bad(format!("format={f} is not accepted; expected GREY, Y16, RGB3 or YUYV")));
                }
                Some(fc)
            }
            None => None,
        };
        let fps = o.int("fps", 1, 1000).map_err(bad)?;
        o.finish().map_err(bad)?;
        let failed = |reason: String| SinkError::Failed { uri: uri.to_string(), reason };
        let device = Device::with_path(path).map_err(|e| failed(format!("cannot open {path}: {e}")))?;
        let caps = device.query_caps().map_err(|e| failed(format!("{path}: VIDIOC_QUERYCAP: {e}")))?;
        if !caps.capabilities.contains(v4l::capability::Flags::VIDEO_OUTPUT) {
            return Err(failed(format!(
                "{path} ({}, {}) is not an output device (capabilities {}); use a v4l2loopback device \
                 that no other writer holds (see hil/v4l2loopback.md)",
                caps.card, caps.driver, caps.capabilities
            )));
        }
        Ok(V4l2Sink {
            uri: uri.to_string(),
            path: path.to_string(),
            device,
            want,
            fps,
            shape: None,
            fourcc: *b"GREY",
            bytesperline: 0,
            buf: Vec::new(),
            chosen: format!("{} {}", caps.card, caps.driver),
        })
    }

    fn failed(&self, reason: String) -> SinkError {
        SinkError::Failed { uri: self.uri.clone(), reason }
    }

    fn configure(&mut self, frame: &Frame) -> Result<(), SinkError> {
        let shape = (frame.width, frame.height, frame.format);
        if let Some(s) = self.shape {
            if s != shape {
                return Err(self.failed(format!(
                    "frame {} is {}x{} {}, but the device was set up for {}x{} {}",
                    frame.seq, frame.width, frame.height, frame.format, s.0, s.1, s.2
                )));
            }
            return Ok(());
        }
        let fourcc = self.want.unwrap_or(match frame.format {
            PixelFormat::Mono16 => *b"Y16 ",
            PixelFormat::Rgb8 => *b"RGB3",
            PixelFormat::Mono8 | PixelFormat::Bayer8 => *b"GREY",
        });
        let ok = match &fourcc {
            b"YUYV" => true,
            b"GREY" => matches!(frame.format, PixelFormat::Mono8 | PixelFormat::Bayer8),
            b"Y16 " => frame.format == PixelFormat::Mono16,
            b"RGB3" => frame.format == PixelFormat::Rgb8,
            _ => false,
        };
        if !ok {
            return Err(self.failed(format!(
                "format={} cannot carry {} frames; use YUYV or the frame's own format",
                FourCC::new(&fourcc),
                frame.format
            )));
        }
        let want = v4l::Format::new(frame.width, frame.height, FourCC::new(&fourcc));
        let got = Output::set_format(&self.device, &want).map_err(|e| {
            self.failed(format!("{}: VIDIOC_S_FMT {}x{} {}: {e}", self.path, frame.width, frame.height, want.fourcc))
        })?;
        if got.width != frame.width || got.height != frame.height || got.fourcc.repr != fourcc {
            return Err(self.failed(format!(
                "{}: asked for {}x{} {}, the driver chose {}x{} {}",
                self.path, frame.width, frame.height, want.fourcc, got.width, got.height, got.fourcc
            )));
        }
        if let Some(f) = self.fps {
            let _ = Output::set_params(&self.device, &v4l::video::output::Parameters::with_fps(f as u32));
        }
        let bpp = if &fourcc == b"RGB3" {
            3
        } else if &fourcc == b"GREY" {
            1
        } else {
            2
        };
        self.bytesperline = (got.stride as usize).max(frame.width as usize * bpp);
        let size = (got.size as usize).max(self.bytesperline * frame.height as usize);
        self.buf = vec![0; size];
        self.fourcc = fourcc;
        self.shape = Some(shape);
        self.chosen =
            format!("{}: {}x{} {}, bytesperline {}", self.chosen, got.width, got.height, got.fourcc, self.bytesperline);
        Ok(())
    }

    fn fill(&mut self, frame: &Frame) -> Result<(), SinkError> {
        let bpl = self.bytesperline;
        if &self.fourcc == b"YUYV" {
            for y in 0..frame.height as usize {
                let row = &mut self.buf[y * bpl..y * bpl + frame.width as usize * 2];
                row_to_yuyv(frame, y, row);
            }
            Ok(())
        } else {
            crate::pipeline::pool::copy_rows_out(frame, &mut self.buf, bpl).map_err(|e| self.failed(e.to_string()))
        }
    }
}

impl Sink for V4l2Sink {
    fn describe(&self) -> String {
        format!("{} ({})", self.uri, self.chosen)
    }

    fn write_frame(&mut self, frame: &Frame, _name: Option<&str>) -> Result<(), SinkError> {
        self.configure(frame)?;
        self.fill(frame)?;
        // SAFETY: the fd belongs to `self.device` and stays open; ManuallyDrop keeps the File
        // from closing it.
        let mut file = ManuallyDrop::new(unsafe { std::fs::File::from_raw_fd(self.device.handle().fd()) });
        let mut off = 0;
        while off < self.buf.len() {
            match file.write(&self.buf[off..]) {
                Ok(0) => return Err(SinkError::Closed { uri: self.uri.clone() }),
                Ok(n) => off += n,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    let ready = self
                        .device
                        .handle()
                        .poll(POLLOUT, WRITE_TIMEOUT_MS)
                        .map_err(|e| self.failed(format!("poll: {e}")))?;
                    if ready == 0 {
                        return Err(
                            self.failed(format!("{}: the device took no frame for {WRITE_TIMEOUT_MS} ms", self.path))
                        );
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(self.failed(format!("{}: write: {e}", self.path))),
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yuyv_of_grey_and_rgb() {
        let mut f = Frame::new(3, 1, PixelFormat::Mono8).unwrap();
        f.as_u8_mut().unwrap().copy_from_slice(&[10, 20, 30]);
        let mut row = [0u8; 6];
        row_to_yuyv(&f, 0, &mut row);
        assert_eq!(row, [10, 128, 20, 128, 30, 128]);
        let mut f = Frame::new(2, 1, PixelFormat::Rgb8).unwrap();
        f.as_u8_mut().unwrap().copy_from_slice(&[255, 255, 255, 0, 0, 0]);
        let mut row = [0u8; 4];
        row_to_yuyv(&f, 0, &mut row);
        assert_eq!((row[0], row[2]), (235, 16), "limited-range white and black");
        assert!((row[1] as i32 - 128).abs() <= 1 && (row[3] as i32 - 128).abs() <= 1, "grey has no chroma");
    }

    #[test]
    fn open_errors_name_the_device_and_options() {
        let e = V4l2Sink::open("v4l2:/dev/video-faultcam-none").err().unwrap().to_string();
        assert!(e.contains("/dev/video-faultcam-none"), "{e}");
        let e = V4l2Sink::open("v4l2:/dev/null?format=MJPG").err().unwrap().to_string();
        assert!(e.contains("GREY, Y16, RGB3 or YUYV"), "{e}");
    }
}
