//! `v4l2:/dev/videoN` output sink, for a v4l2loopback device (see `hil/v4l2loopback.md`):
//! faulted frames appear as a camera that any V4L2 application (the vision stack under
//! test, GStreamer `v4l2src`, ffplay, a browser) can open.
//!
//! URI: `v4l2:/dev/videoN[?format=GREY|Y16|RGB3|YUYV&fps=30&io=mmap|write&buffers=4&timeout_ms=2000&
//! stamp=pts|seq]`.
//!
//! * The output format is negotiated on the first frame (`VIDIOC_S_FMT` on the output queue):
//!   by default the frame's own layout (mono8 → `GREY`, mono16 → `Y16`, rgb8 → `RGB3`,
//!   bayer8 → `GREY`); `format=YUYV` converts for consumers that need YUYV (mono8: U = V =
//!   128; rgb8: ITU-R BT.601 limited range; mono16: the high byte). What the driver chose
//!   (size, fourcc, `bytesperline`, `sizeimage`, buffer count) is read back and reported by
//!   `describe()`; a different size or fourcc is an error naming both. Later frames must keep
//!   the size.
//! * `io=mmap` (default): streaming I/O. `buffers` driver buffers are requested
//!   (`VIDIOC_REQBUFS`, `V4L2_MEMORY_MMAP`; v4l2loopback grants at most its `max_buffers`) and
//!   mapped once; each frame is written straight into a free buffer in the driver's layout and
//!   queued (`VIDIOC_QBUF`) at once, stamped with the frame's `pts_ns` moved onto
//!   `CLOCK_MONOTONIC` (the clock V4L2 readers assume): the first frame is stamped with the
//!   time it is queued and later ones keep their pts spacing, never later than the time they
//!   are queued (a frame written earlier than its pts is stamped with its queue time, and the
//!   later ones keep the spacing from there; readers such as GStreamer's v4l2src distrust
//!   timestamps in the future), unless the pts already are
//!   monotonic-clock times (within 10 s of now, as from a live `v4l2:` camera), which pass
//!   unchanged (a pts under 1 s is always taken as a stream origin). (A zero timestamp would be replaced by v4l2loopback with the queue time, so a
//!   stream starting at pts 0 would read back non-monotone.) With `stamp=seq` (what a live
//!   `faultcam sweep` uses) the timestamp is instead the frame's identity: exactly
//!   `(seq + 1)` ms ([`crate::sweep::live::seq_stamp_ns`]; a reader recovers `seq` with
//!   [`crate::sweep::live::seq_of_stamp_ns`]), the same for every write of the same frame;
//!   it needs `io=mmap` (with `write(2)` the driver stamps the buffer itself). Buffers the
//!   driver has consumed come back with `VIDIOC_DQBUF` (waiting up to `timeout_ms` when all
//!   are queued). Streaming starts (`VIDIOC_STREAMON`) with the first frame.
//! * `io=write`: each frame is written with `write(2)` (v4l2loopback's read/write I/O, as
//!   ffmpeg's v4l2 output does) from one buffer allocated once per stream.
//! * Either way a frame is handed to readers when `write_frame` returns: no extra frame of
//!   queueing inside faultcam, and no allocation per frame.
//! * v4l2loopback (0.12.7, Debian 12) quirks worked around: with `io=mmap` the buffers are
//!   filled in turn instead of in the order output `VIDIOC_DQBUF` returns them (it returns the
//!   buffer queued last, so every frame would go into one buffer and GStreamer's `v4l2src`
//!   fails with "buffer N was not queued"); with `io=write` the sink also calls
//!   `VIDIOC_STREAMON`, without which the device is left neither output nor capture after the
//!   writer closes. The reader-side quirks (a reader's `VIDIOC_REQBUFS` restamps every buffer,
//!   so the first buffer a late reader gets carries its start time) are in
//!   `hil/v4l2loopback.md`.

use super::{Sink, SinkError};
use crate::frame::{Frame, FrameData, PixelFormat};
use crate::source::split_uri;
use crate::source::v4l2::parse_fourcc;
use std::io::Write;
use std::mem::ManuallyDrop;
use std::os::fd::FromRawFd;
use std::sync::Arc;
use v4l::device::Handle;
use v4l::video::Output;
use v4l::{Device, FourCC};

/// `POLLOUT` (Linux).
const POLLOUT: i16 = 0x004;

/// Output I/O method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Io {
    Mmap,
    Write,
}

/// One driver buffer mapped into this process.
struct Mapped {
    ptr: *mut std::ffi::c_void,
    len: usize,
}

/// Streaming output over mapped driver buffers.
struct MmapOut {
    handle: Arc<Handle>,
    bufs: Vec<Mapped>,
    /// Buffers `0..fresh` have been queued at least once; the others are free to fill.
    fresh: usize,
    /// v4l2loopback: fill the buffers in turn (see `acquire`); the next one to fill.
    in_turn: Option<usize>,
    streaming: bool,
    /// Added to `pts_ns` to get a `CLOCK_MONOTONIC` timestamp; set on the first frame.
    ts_offset: Option<i128>,
}

/// What a queued buffer's timestamp says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stamp {
    /// The frame's pts on `CLOCK_MONOTONIC` (see the module notes).
    Pts,
    /// The frame's seq: `(seq + 1)` ms exactly (the live sweep's contract).
    Seq,
}

// SAFETY: the mappings belong to this value alone (no other reference to them exists), and the
// device handle they come from is kept alive by `handle`; moving them to another thread is fine.
unsafe impl Send for MmapOut {}

fn v4l2_buffer(index: u32) -> v4l::v4l_sys::v4l2_buffer {
    // SAFETY: v4l2_buffer is a plain C struct for which all-zero bytes are a valid value.
    let mut b: v4l::v4l_sys::v4l2_buffer = unsafe { std::mem::zeroed() };
    b.index = index;
    b.type_ = v4l::buffer::Type::VideoOutput as u32;
    b.memory = v4l::memory::Memory::Mmap as u32;
    b
}

impl MmapOut {
    /// Request `count` buffers and map them.
    fn new(device: &Device, count: u32, in_turn: bool) -> std::io::Result<MmapOut> {
        let handle = device.handle();
        let fd = handle.fd();
        // SAFETY: all-zero is a valid v4l2_requestbuffers.
        let mut req: v4l::v4l_sys::v4l2_requestbuffers = unsafe { std::mem::zeroed() };
        req.count = count;
        req.type_ = v4l::buffer::Type::VideoOutput as u32;
        req.memory = v4l::memory::Memory::Mmap as u32;
        // SAFETY: VIDIOC_REQBUFS takes a pointer to a v4l2_requestbuffers that outlives the call.
        unsafe {
            v4l::v4l2::ioctl(fd, v4l::v4l2::vidioc::VIDIOC_REQBUFS, &mut req as *mut _ as *mut std::ffi::c_void)?
        };
        if req.count == 0 {
            return Err(std::io::Error::other("the driver granted no buffers"));
        }
        let mut out = MmapOut {
            handle,
            bufs: Vec::with_capacity(req.count as usize),
            fresh: 0,
            in_turn: in_turn.then_some(0),
            streaming: false,
            ts_offset: None,
        };
        for index in 0..req.count {
            let mut b = v4l2_buffer(index);
            // SAFETY: VIDIOC_QUERYBUF fills the v4l2_buffer it is given; then the buffer is
            // mapped at the offset the driver reported, with the length it reported.
            unsafe {
                v4l::v4l2::ioctl(fd, v4l::v4l2::vidioc::VIDIOC_QUERYBUF, &mut b as *mut _ as *mut std::ffi::c_void)?;
                let ptr = v4l::v4l2::mmap(
                    std::ptr::null_mut(),
                    b.length as usize,
                    libc::PROT_READ | libc::PROT_WRITE,
                    libc::MAP_SHARED,
                    fd,
                    b.m.offset as libc::off_t,
                )?;
                out.bufs.push(Mapped { ptr, len: b.length as usize });
            }
        }
        Ok(out)
    }

    /// A buffer the application may fill: a never-queued one, else one the driver gives back.
    ///
    /// v4l2loopback (0.12.7) answers an output `VIDIOC_DQBUF` with the buffer queued *last*, so a
    /// writer that fills what it gets back writes every frame into one buffer: the one readers
    /// were just handed (torn frames), and a reader's `VIDIOC_DQBUF` returns that same index
    /// again and again — GStreamer's v4l2src stops with "buffer N was not queued, this indicate
    /// a driver bug" / "Failed to allocate a buffer". For v4l2loopback the buffer is still
    /// dequeued (the protocol), but the buffers are filled in turn, as its own `write(2)` path
    /// does (it hands no buffer to anyone: a queued output buffer is consumed at once).
    fn acquire(&mut self, timeout_ms: i32) -> std::io::Result<usize> {
        if self.fresh < self.bufs.len() {
            self.fresh += 1;
            return Ok(self.fresh - 1);
        }
        if self.handle.poll(POLLOUT, timeout_ms)? == 0 {
            return Err(std::io::Error::new(std::io::ErrorKind::TimedOut, "no buffer came back"));
        }
        let mut b = v4l2_buffer(0);
        // SAFETY: VIDIOC_DQBUF fills the v4l2_buffer it is given.
        unsafe {
            v4l::v4l2::ioctl(
                self.handle.fd(),
                v4l::v4l2::vidioc::VIDIOC_DQBUF,
                &mut b as *mut _ as *mut std::ffi::c_void,
            )?
        };
        let i = b.index as usize;
        if i >= self.bufs.len() {
            return Err(std::io::Error::other(format!("the driver returned buffer {i} of {}", self.bufs.len())));
        }
        if let Some(next) = self.in_turn.as_mut() {
            let i = *next;
            *next = (i + 1) % self.bufs.len();
            return Ok(i);
        }
        Ok(i)
    }

    fn buffer(&mut self, i: usize) -> &mut [u8] {
        let m = &self.bufs[i];
        // SAFETY: the mapping is `len` bytes, readable and writable, alive until Drop, and only
        // reachable through `&mut self`.
        unsafe { std::slice::from_raw_parts_mut(m.ptr as *mut u8, m.len) }
    }

    /// The `CLOCK_MONOTONIC` timestamp of a frame with `pts_ns` (see the module notes).
    fn pts_stamp(&mut self, pts_ns: u64) -> u64 {
        let now = crate::frame::monotonic_ns() as i128;
        let offset = match self.ts_offset {
            // pts that are monotonic-clock times already (a live camera) pass unchanged.
            Some(0) => 0,
            // Never a time after the frame is queued: a reader takes a timestamp in the future
            // for a broken clock (GStreamer's v4l2src then ignores the driver timestamps and
            // stamps buffers itself from then on, a jump in its pts). The offset only shrinks,
            // when a frame comes earlier than its pts say (the first frame was slow, or frames
            // are written faster than their pts); the stamps stay monotone.
            Some(o) => o.min(now - pts_ns as i128),
            None => {
                // A pts under 1 s is a stream's own origin (synth and files start at 0), not a
                // monotonic-clock time, even on a machine that booted less than 10 s ago.
                let live = pts_ns >= 1_000_000_000 && (now - pts_ns as i128).abs() < 10_000_000_000;
                if live { 0 } else { now - pts_ns as i128 }
            }
        };
        self.ts_offset = Some(offset);
        // Never 0 (v4l2loopback would stamp it itself) and never before the clock's origin.
        (pts_ns as i128 + offset).max(1000) as u64
    }

    /// Hand buffer `i` (with `bytesused` bytes of frame) to the driver, stamped `ts` ns (µs
    /// resolution); start streaming.
    fn queue(&mut self, i: usize, bytesused: usize, ts: u64) -> std::io::Result<()> {
        let mut b = v4l2_buffer(i as u32);
        b.bytesused = bytesused as u32;
        b.field = v4l::v4l_sys::v4l2_field_V4L2_FIELD_NONE;
        b.timestamp.tv_sec = (ts / 1_000_000_000) as _;
        b.timestamp.tv_usec = ((ts % 1_000_000_000) / 1000) as _;
        let fd = self.handle.fd();
        // SAFETY: VIDIOC_QBUF reads the v4l2_buffer it is given.
        unsafe { v4l::v4l2::ioctl(fd, v4l::v4l2::vidioc::VIDIOC_QBUF, &mut b as *mut _ as *mut std::ffi::c_void)? };
        if !self.streaming {
            let mut typ = v4l::buffer::Type::VideoOutput as u32;
            // SAFETY: VIDIOC_STREAMON reads the buffer type it is given.
            unsafe {
                v4l::v4l2::ioctl(fd, v4l::v4l2::vidioc::VIDIOC_STREAMON, &mut typ as *mut _ as *mut std::ffi::c_void)?
            };
            self.streaming = true;
        }
        Ok(())
    }
}

impl Drop for MmapOut {
    fn drop(&mut self) {
        let fd = self.handle.fd();
        if self.streaming {
            let mut typ = v4l::buffer::Type::VideoOutput as u32;
            // SAFETY: as in `queue`; errors are ignored (never panic in Drop).
            let _ = unsafe {
                v4l::v4l2::ioctl(fd, v4l::v4l2::vidioc::VIDIOC_STREAMOFF, &mut typ as *mut _ as *mut std::ffi::c_void)
            };
        }
        for m in self.bufs.drain(..) {
            // SAFETY: each mapping was made by `new` with this length and is unmapped once.
            let _ = unsafe { v4l::v4l2::munmap(m.ptr, m.len) };
        }
        // SAFETY: all-zero is a valid v4l2_requestbuffers; count 0 frees the driver's buffers.
        let mut req: v4l::v4l_sys::v4l2_requestbuffers = unsafe { std::mem::zeroed() };
        req.type_ = v4l::buffer::Type::VideoOutput as u32;
        req.memory = v4l::memory::Memory::Mmap as u32;
        // SAFETY: as in `new`.
        let _ = unsafe {
            v4l::v4l2::ioctl(fd, v4l::v4l2::vidioc::VIDIOC_REQBUFS, &mut req as *mut _ as *mut std::ffi::c_void)
        };
    }
}

/// An open output device.
pub struct V4l2Sink {
    uri: String,
    path: String,
    // Declared before `device`: buffers are released before the device is closed.
    mmap: Option<MmapOut>,
    device: Device,
    want: Option<[u8; 4]>,
    fps: Option<u64>,
    io: Io,
    stamp: Stamp,
    /// The driver is v4l2loopback (its quirks are worked around, see `MmapOut::acquire`).
    loopback: bool,
    buffers: u32,
    timeout_ms: i32,
    shape: Option<(u32, u32, PixelFormat)>,
    fourcc: [u8; 4],
    bytesperline: usize,
    /// Bytes of one frame in the driver's layout (`sizeimage`).
    frame_bytes: usize,
    // allocation: once per stream (io=write: one frame in the driver's layout)
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
        let io = match o.raw("io").as_deref() {
            None | Some("mmap") => Io::Mmap,
            Some("write") => Io::Write,
            Some(v) => return Err(bad(format!("io={v} is not accepted; expected mmap or write"))),
        };
        let buffers = o.int("buffers", 2, 32).map_err(bad)?.unwrap_or(4) as u32;
        let timeout_ms = o.int("timeout_ms", 10, 600_000).map_err(bad)?.unwrap_or(2000) as i32;
        let stamp = match o.raw("stamp").as_deref() {
            None | Some("pts") => Stamp::Pts,
            Some("seq") if io == Io::Mmap => Stamp::Seq,
            Some("seq") => {
                return Err(bad("stamp=seq needs io=mmap (with write(2) the driver stamps buffers itself)".into()));
            }
            Some(v) => return Err(bad(format!("stamp={v} is not accepted; expected pts or seq"))),
        };
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
        if io == Io::Mmap && !caps.capabilities.contains(v4l::capability::Flags::STREAMING) {
            return Err(failed(format!("{path} ({}) does not support streaming I/O; use io=write", caps.card)));
        }
        Ok(V4l2Sink {
            uri: uri.to_string(),
            path: path.to_string(),
            mmap: None,
            device,
            want,
            fps,
            io,
            stamp,
            loopback: caps.driver == "v4l2 loopback",
            buffers,
            timeout_ms,
            shape: None,
            fourcc: *b"GREY",
            bytesperline: 0,
            frame_bytes: 0,
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
        self.frame_bytes = (got.size as usize).max(self.bytesperline * frame.height as usize);
        let io = match self.io {
            Io::Mmap => {
                let m = MmapOut::new(&self.device, self.buffers, self.loopback).map_err(|e| {
                    self.failed(format!(
                        "{}: cannot map {} output buffers: {e} (try io=write)",
                        self.path, self.buffers
                    ))
                })?;
                if let Some(small) = m.bufs.iter().find(|b| b.len < self.frame_bytes) {
                    return Err(self.failed(format!(
                        "{}: a driver buffer has {} bytes, a frame needs {}",
                        self.path, small.len, self.frame_bytes
                    )));
                }
                let io = format!("mmap, {} buffers", m.bufs.len());
                self.mmap = Some(m);
                io
            }
            Io::Write => {
                self.buf = vec![0; self.frame_bytes];
                if self.loopback {
                    // v4l2loopback 0.12.7 takes an opener for its writer only on
                    // VIDIOC_STREAMON; a write(2)-only writer leaves the device, once closed,
                    // neither an output nor a capture device until the module is reloaded.
                    let mut typ = v4l::buffer::Type::VideoOutput as u32;
                    // SAFETY: VIDIOC_STREAMON reads the buffer type it is given. An error is
                    // harmless here (write(2) works without it).
                    let _ = unsafe {
                        v4l::v4l2::ioctl(
                            self.device.handle().fd(),
                            v4l::v4l2::vidioc::VIDIOC_STREAMON,
                            &mut typ as *mut _ as *mut std::ffi::c_void,
                        )
                    };
                }
                "write".to_string()
            }
        };
        self.fourcc = fourcc;
        self.shape = Some(shape);
        let stamps = if self.stamp == Stamp::Seq { ", timestamps (seq + 1) ms" } else { "" };
        self.chosen = format!(
            "{}: driver chose {}x{} {}, bytesperline {}, sizeimage {}, io {io}{stamps}",
            self.chosen, got.width, got.height, got.fourcc, self.bytesperline, got.size
        );
        Ok(())
    }
}

/// Lay `frame` out in `dst` as `fourcc` rows of `bpl` bytes.
fn fill(frame: &Frame, fourcc: &[u8; 4], bpl: usize, dst: &mut [u8]) -> Result<(), String> {
    if fourcc == b"YUYV" {
        let row = frame.width as usize * 2;
        for y in 0..frame.height as usize {
            let d = dst.get_mut(y * bpl..y * bpl + row).ok_or("driver buffer too small")?;
            row_to_yuyv(frame, y, d);
        }
        Ok(())
    } else {
        crate::pipeline::pool::copy_rows_out(frame, dst, bpl).map_err(|e| e.to_string())
    }
}

impl Sink for V4l2Sink {
    fn describe(&self) -> String {
        format!("{} ({})", self.uri, self.chosen)
    }

    fn write_frame(&mut self, frame: &Frame, _name: Option<&str>) -> Result<(), SinkError> {
        self.configure(frame)?;
        let (fourcc, bpl, n) = (self.fourcc, self.bytesperline, self.frame_bytes);
        if let Some(m) = self.mmap.as_mut() {
            let i = match m.acquire(self.timeout_ms) {
                Ok(i) => i,
                Err(e) => {
                    return Err(SinkError::Failed {
                        uri: self.uri.clone(),
                        reason: format!("{}: VIDIOC_DQBUF: {e} (timeout {} ms)", self.path, self.timeout_ms),
                    });
                }
            };
            let ts = match self.stamp {
                Stamp::Pts => Some(m.pts_stamp(frame.pts_ns)),
                Stamp::Seq => crate::sweep::live::seq_stamp_ns(frame.seq),
            };
            let r = match ts {
                Some(ts) => fill(frame, &fourcc, bpl, &mut m.buffer(i)[..n])
                    .and_then(|()| m.queue(i, n, ts).map_err(|e| format!("VIDIOC_QBUF: {e}"))),
                None => Err(format!("frame {}: seq too large for a timestamp (stamp=seq)", frame.seq)),
            };
            return r.map_err(|e| SinkError::Failed { uri: self.uri.clone(), reason: format!("{}: {e}", self.path) });
        }
        fill(frame, &fourcc, bpl, &mut self.buf).map_err(|e| self.failed(e))?;
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
                        .poll(POLLOUT, self.timeout_ms)
                        .map_err(|e| self.failed(format!("poll: {e}")))?;
                    if ready == 0 {
                        return Err(
                            self.failed(format!("{}: the device took no frame for {} ms", self.path, self.timeout_ms))
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
        let e = V4l2Sink::open("v4l2:/dev/null?io=userptr").err().unwrap().to_string();
        assert!(e.contains("io=userptr") && e.contains("mmap or write"), "{e}");
        let e = V4l2Sink::open("v4l2:/dev/null?io=write&stamp=seq").err().unwrap().to_string();
        assert!(e.contains("stamp=seq needs io=mmap"), "{e}");
        let e = V4l2Sink::open("v4l2:/dev/null?stamp=now").err().unwrap().to_string();
        assert!(e.contains("stamp=now") && e.contains("pts or seq"), "{e}");
        let e = V4l2Sink::open("v4l2:/dev/null?buffers=1").err().unwrap().to_string();
        assert!(e.contains("buffers") && e.contains("2..=32"), "{e}");
        // /dev/null is no V4L2 device: the error names it.
        let e = V4l2Sink::open("v4l2:/dev/null").err().unwrap().to_string();
        assert!(e.contains("/dev/null") && e.contains("VIDIOC_QUERYCAP"), "{e}");
    }
}
