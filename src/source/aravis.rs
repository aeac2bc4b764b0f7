//! `aravis:CAMERA` source: GenICam cameras (GigE Vision, USB3 Vision) through Aravis.
//!
//! URI: `aravis:[CAMERA][?pixel_format=Mono8&exposure_us=5000&fps=30&width=640&height=480&
//! buffers=8&timeout_ms=3000&interfaces=all]`.
//!
//! * `CAMERA` is the Aravis device id (`arv-tool-0.8` lists them, e.g. `Fake_1` or
//!   `Basler-21234567`); empty = the first camera found.
//! * `interfaces`: `fake` (only the in-process fake camera: no network traffic at all), `gige`,
//!   `usb` or `all`. Default: `fake` when the name starts with `Fake_`, else `all`. Any
//!   other choice runs Aravis device discovery, which broadcasts on the network.
//! * Options set the camera before streaming; what the camera actually chose (it may round
//!   exposure, frame rate and region) is read back and reported by `describe()`.
//! * Pixel formats: `Mono8` → mono8; `Mono10`, `Mono12`, `Mono14`, `Mono16` (unpacked,
//!   little-endian 16-bit containers) → mono16, shifted left so the sensor's full scale is
//!   65535; `RGB8` (`RGB8Packed`) → rgb8; 8-bit Bayer (`BayerRG8`, ...) → bayer8.
//! * Streaming uses `buffers` driver buffers allocated once, each pushed back after its
//!   pixels are copied into a pooled frame. `pts_ns` is the camera timestamp; `seq` counts
//!   from the first frame id, so frames the camera or the transport lost leave a gap and are
//!   reported one by one as recoverable errors (logged as `skip` records), as are incomplete
//!   buffers (missing packets).
//! * No frame within `timeout_ms`, or the device's control-lost signal (camera unplugged,
//!   network down), ends the stream with an error naming the camera.

use super::frame_ids::{FrameIds, Placement};
use super::{Source, SourceError, UriOptions, split_uri};
use crate::frame::{Frame, PixelFormat};
use crate::pipeline::pool::{FramePool, copy_rows_into};
use aravis::prelude::*;
use aravis::{Buffer, BufferStatus, Camera, Stream};
use std::collections::VecDeque;
use std::ffi::CString;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Aravis interface ids.
const IFACE_FAKE: &str = "Fake";
const IFACE_GIGE: &str = "GigEVision";
const IFACE_USB: &str = "USB3Vision";

/// A streaming GenICam camera.
/// Longest run of lost frames counted as a gap; a longer jump of the frame counter is a wrap
/// or a reset (see [`FrameIds`]).
const MAX_GAP: u64 = 1024;

pub struct AravisSource {
    uri: String,
    camera: Camera,
    stream: Stream,
    lost: Arc<AtomicBool>,
    timeout_us: u64,
    width: u32,
    height: u32,
    arv_format: aravis::PixelFormat,
    format: PixelFormat,
    /// Left shift applied to 16-bit containers (16 - bit depth).
    shift: u32,
    settings: String,
    pool: FramePool,
    /// Stream numbers from the camera's frame ids (gaps, wraps, resets).
    ids: FrameIds,
    /// Lost frames and counter jumps, reported one per `next_frame` call before `ready`.
    pending: VecDeque<SourceError>,
    ready: Option<Frame>,
    acquiring: bool,
}

fn set_interface(id: &str, on: bool) {
    if let Ok(c) = CString::new(id) {
        // SAFETY: plain C calls with a NUL-terminated string that outlives them.
        unsafe {
            if on {
                aravis_sys::arv_enable_interface(c.as_ptr());
            } else {
                aravis_sys::arv_disable_interface(c.as_ptr());
            }
        }
    }
}

/// Map a GenICam pixel format to a frame format and the left shift for 16-bit containers.
fn map_format(f: aravis::PixelFormat) -> Option<(PixelFormat, u32)> {
    use aravis::PixelFormat as A;
    Some(match f {
        A::MONO_8 => (PixelFormat::Mono8, 0),
        A::MONO_10 => (PixelFormat::Mono16, 6),
        A::MONO_12 => (PixelFormat::Mono16, 4),
        A::MONO_14 => (PixelFormat::Mono16, 2),
        A::MONO_16 => (PixelFormat::Mono16, 0),
        A::RGB_8_PACKED => (PixelFormat::Rgb8, 0),
        A::BAYER_RG_8 | A::BAYER_GR_8 | A::BAYER_GB_8 | A::BAYER_BG_8 => (PixelFormat::Bayer8, 0),
        _ => return None,
    })
}

const ACCEPTED_FORMATS: &str = "Mono8, Mono10, Mono12, Mono14, Mono16, RGB8Packed, BayerRG8/GR8/GB8/BG8";

impl AravisSource {
    pub fn open(uri: &str) -> Result<AravisSource, SourceError> {
        let (_, name, opts) = split_uri(uri);
        let name = name.trim().to_string();
        let bad = |reason: String| SourceError::BadUri { uri: uri.to_string(), reason };
        let mut o = UriOptions::new(opts);
        let pixel_format = o.raw("pixel_format");
        let exposure_us = o.num("exposure_us", 1.0, 1e8).map_err(bad)?;
        let fps = o.num("fps", 0.01, 1e5).map_err(bad)?;
        let width = o.int("width", 1, 65535).map_err(bad)?;
        let height = o.int("height", 1, 65535).map_err(bad)?;
        let buffers = o.int("buffers", 2, 256).map_err(bad)?.unwrap_or(8);
        let timeout_ms = o.int("timeout_ms", 10, 600_000).map_err(bad)?.unwrap_or(3000);
        let default_iface = if name.starts_with("Fake_") { "fake" } else { "all" };
        let interfaces = o.raw("interfaces").unwrap_or_else(|| default_iface.to_string());
        o.finish().map_err(bad)?;

        let (fake, gige, usb) = match interfaces.as_str() {
            "fake" => (true, false, false),
            "gige" => (false, true, false),
            "usb" => (false, false, true),
            "all" => (true, true, true),
            other => return Err(bad(format!("interfaces={other} is not accepted; expected fake, gige, usb or all"))),
        };
        set_interface(IFACE_FAKE, fake);
        set_interface(IFACE_GIGE, gige);
        set_interface(IFACE_USB, usb);

        let fatal = |reason: String| SourceError::Fatal { uri: uri.to_string(), reason };
        let shown = if name.is_empty() { "the first camera".to_string() } else { format!("camera '{name}'") };
        let camera = Camera::new((!name.is_empty()).then_some(name.as_str()))
            .map_err(|e| fatal(format!("cannot open {shown} (interfaces: {interfaces}): {e}")))?;
        let cam_err = |what: &str, e: aravis::glib::Error| fatal(format!("{shown}: {what}: {e}"));

        if let Some(pf) = &pixel_format {
            camera.set_pixel_format_from_string(pf).map_err(|e| {
                let avail = camera
                    .dup_available_pixel_formats_as_strings()
                    .map(|v| v.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", "))
                    .unwrap_or_default();
                fatal(format!("{shown}: cannot set pixel_format={pf}: {e}; the camera offers: {avail}"))
            })?;
        }
        if width.is_some() || height.is_some() {
            let (x, y, w, h) = camera.region().map_err(|e| cam_err("reading the region", e))?;
            let w = width.map(|v| v as i32).unwrap_or(w);
            let h = height.map(|v| v as i32).unwrap_or(h);
            camera.set_region(x, y, w, h).map_err(|e| cam_err("setting the region", e))?;
        }
        if let Some(e_us) = exposure_us {
            camera.set_exposure_time(e_us).map_err(|e| cam_err("setting exposure_us", e))?;
        }
        if let Some(f) = fps {
            camera.set_frame_rate(f).map_err(|e| cam_err("setting fps", e))?;
        }
        let (_, _, w, h) = camera.region().map_err(|e| cam_err("reading the region", e))?;
        let arv_format = camera.pixel_format().map_err(|e| cam_err("reading the pixel format", e))?;
        let fmt_name = camera.pixel_format_as_string().map(|s| s.to_string()).unwrap_or_else(|_| "?".into());
        let (format, shift) = map_format(arv_format).ok_or_else(|| {
            fatal(format!(
                "{shown}: pixel format {fmt_name} is not supported; use pixel_format= one of {ACCEPTED_FORMATS}"
            ))
        })?;
        let exposure = camera.exposure_time().ok();
        let rate = camera.frame_rate().ok();
        let model = camera.model_name().map(|s| s.to_string()).unwrap_or_default();
        let id = camera.device_id().map(|s| s.to_string()).unwrap_or_default();
        let settings = format!(
            "{model} {id}: {w}x{h} {fmt_name} → {format}, exposure {} us, {} fps",
            exposure.map(|v| format!("{v:.0}")).unwrap_or_else(|| "?".into()),
            rate.map(|v| format!("{v:.2}")).unwrap_or_else(|| "?".into())
        );

        // The region is checked against the image limits before the buffer ring is allocated.
        let limits = crate::limits::ImageLimits::current();
        let bpp = (format.channels() * format.bytes_per_sample()) as u64;
        limits
            .check("the camera region", w.max(0) as u32, h.max(0) as u32, bpp)
            .map_err(|e| fatal(format!("{shown}: {e}")))?;
        let payload = camera.payload().map_err(|e| cam_err("reading the payload size", e))?;
        if payload as u64 > limits.max_bytes {
            return Err(fatal(format!(
                "{shown}: payload of {payload} bytes per buffer is over the image limit of {} MB ({})",
                limits.max_bytes >> 20,
                crate::limits::FLAGS_HINT
            )));
        }
        let stream = camera.create_stream().map_err(|e| cam_err("creating the stream", e))?;
        for _ in 0..buffers {
            // allocation: once per stream (the driver's buffer ring)
            stream.push_buffer(Buffer::new_allocate(payload as usize));
        }
        let lost = Arc::new(AtomicBool::new(false));
        if let Some(dev) = camera.device() {
            let l = lost.clone();
            dev.connect_control_lost(move |_| l.store(true, Ordering::Relaxed));
        }
        camera.start_acquisition().map_err(|e| cam_err("starting acquisition", e))?;
        Ok(AravisSource {
            uri: uri.to_string(),
            camera,
            stream,
            lost,
            timeout_us: timeout_ms * 1000,
            width: w as u32,
            height: h as u32,
            arv_format,
            format,
            shift,
            settings,
            pool: FramePool::new(8),
            ids: FrameIds::new(MAX_GAP),
            pending: VecDeque::with_capacity(MAX_GAP as usize + 1),
            ready: None,
            acquiring: true,
        })
    }

    fn fatal(&self, reason: String) -> SourceError {
        SourceError::Fatal { uri: self.uri.clone(), reason }
    }

    /// Copy a completed buffer into a pooled frame.
    fn convert(&mut self, buf: &Buffer) -> Result<Frame, SourceError> {
        let (w, h) = (buf.image_width(), buf.image_height());
        if w <= 0 || h <= 0 {
            return Err(self.fatal(format!("buffer with an empty image ({w}x{h})")));
        }
        let pf = buf.image_pixel_format();
        if pf != self.arv_format {
            return Err(self.fatal(format!("the camera changed its pixel format mid-stream ({pf:?})")));
        }
        let (w, h) = (w as u32, h as u32);
        let (ptr, len) = buf.data();
        if ptr.is_null() {
            return Err(self.fatal("buffer without data".into()));
        }
        // SAFETY: Aravis guarantees `len` readable bytes at `ptr` while we hold `buf`.
        let bytes = unsafe { std::slice::from_raw_parts(ptr as *const u8, len) };
        let row_bytes = w as usize * self.format.channels() * self.format.bytes_per_sample();
        let (pad_x, _) = buf.image_padding();
        let stride = row_bytes + pad_x.max(0) as usize;
        let mut frame = self.pool.take(w, h, self.format).map_err(|e| self.fatal(e.to_string()))?;
        copy_rows_into(&mut frame, bytes, stride).map_err(|e| self.fatal(format!("buffer too short: {e}")))?;
        if self.shift > 0
            && let Some(d) = frame.as_u16_mut()
        {
            let s = self.shift;
            d.iter_mut().for_each(|v| *v = v.checked_shl(s).unwrap_or(u16::MAX));
        }
        frame.pts_ns = buf.timestamp();
        Ok(frame)
    }
}

impl Source for AravisSource {
    fn describe(&self) -> String {
        format!("{} ({}; {}x{})", self.uri, self.settings, self.width, self.height)
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, SourceError> {
        if let Some(e) = self.pending.pop_front() {
            return Err(e);
        }
        if let Some(f) = self.ready.take() {
            return Ok(Some(f));
        }
        if self.lost.load(Ordering::Relaxed) {
            return Err(self.fatal("the camera disappeared (control lost)".into()));
        }
        let Some(buf) = self.stream.timeout_pop_buffer(self.timeout_us) else {
            if self.lost.load(Ordering::Relaxed) {
                return Err(self.fatal("the camera disappeared (control lost)".into()));
            }
            return Err(self.fatal(format!(
                "no frame within {} ms (camera disconnected, stopped or waiting for a trigger?)",
                self.timeout_us / 1000
            )));
        };
        let id = buf.frame_id();
        let status = buf.status();
        let result = if status == BufferStatus::Success { Some(self.convert(&buf)) } else { None };
        self.stream.push_buffer(buf);
        let incomplete = || SourceError::BadInput {
            item: format!("{}: frame id {id}", self.uri),
            reason: format!("incomplete buffer from the camera: {status:?}"),
        };
        // An incomplete buffer's id numbers the stream only if it continues the sequence (a
        // failed buffer may carry id 0).
        if result.is_none() && self.ids.step(id).is_none() {
            return Err(incomplete());
        }
        let seq = match self.ids.place(id) {
            Placement::Next { seq, skipped } => {
                for lost in seq - skipped..seq {
                    self.pending.push_back(SourceError::BadInput {
                        item: format!("{}: frame {lost} (before camera frame id {id})", self.uri),
                        reason: "lost by the camera or the transport (gap in frame ids)".into(),
                    });
                }
                seq
            }
            Placement::Jump { seq, from, to } => {
                self.pending.push_back(SourceError::BadInput {
                    item: format!("{}: frame id {to}", self.uri),
                    reason: format!(
                        "the camera's frame counter jumped from {from} to {to} (wrapped or reset); numbering \
                         goes on, frames lost in the jump (if any) cannot be counted"
                    ),
                });
                seq
            }
        };
        match result {
            None => {
                self.pending.push_back(incomplete());
                Err(self.pending.pop_front().expect("just pushed"))
            }
            Some(Err(e)) => Err(e),
            Some(Ok(mut frame)) => {
                frame.seq = seq;
                match self.pending.pop_front() {
                    None => Ok(Some(frame)),
                    Some(e) => {
                        self.ready = Some(frame);
                        Err(e)
                    }
                }
            }
        }
    }

    fn recycle(&mut self, frame: Frame) {
        self.pool.give(frame);
    }
}

impl Drop for AravisSource {
    fn drop(&mut self) {
        if self.acquiring {
            let _ = self.camera.stop_acquisition();
            self.acquiring = false;
        }
    }
}
