//! Frames: the unit that flows from a source through the fault chain to a sink.
//!
//! Samples are stored row by row with a stride counted in *samples* (not bytes), so 16-bit
//! data never has alignment problems. Rows may carry padding (`stride > width * channels`),
//! as GStreamer and V4L2 buffers do; every accessor slices the padding off.

use thiserror::Error;

/// Pixel layouts faultcam understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum PixelFormat {
    /// 8-bit grey.
    Mono8,
    /// 16-bit grey (full scale 65535).
    Mono16,
    /// 8-bit interleaved R, G, B.
    Rgb8,
    /// 8-bit raw Bayer mosaic, passed through as one plane.
    Bayer8,
}

impl PixelFormat {
    /// Samples per pixel.
    pub fn channels(self) -> usize {
        match self {
            PixelFormat::Rgb8 => 3,
            _ => 1,
        }
    }
    /// Bytes per sample.
    pub fn bytes_per_sample(self) -> usize {
        match self {
            PixelFormat::Mono16 => 2,
            _ => 1,
        }
    }
    /// Full scale FS in DN.
    pub fn full_scale(self) -> f32 {
        match self {
            PixelFormat::Mono16 => 65535.0,
            _ => 255.0,
        }
    }
    /// Factor that turns a parameter given in 8-bit DN into DN of this format.
    pub fn dn_scale(self) -> f32 {
        self.full_scale() / 255.0
    }
    /// Canonical lower-case name (`mono8`, `mono16`, `rgb8`, `bayer8`).
    pub fn name(self) -> &'static str {
        match self {
            PixelFormat::Mono8 => "mono8",
            PixelFormat::Mono16 => "mono16",
            PixelFormat::Rgb8 => "rgb8",
            PixelFormat::Bayer8 => "bayer8",
        }
    }
    /// Parse a canonical name (case-insensitive).
    pub fn parse(s: &str) -> Option<PixelFormat> {
        match s.to_ascii_lowercase().as_str() {
            "mono8" | "gray8" | "gray" => Some(PixelFormat::Mono8),
            "mono16" | "gray16" => Some(PixelFormat::Mono16),
            "rgb8" | "rgb" => Some(PixelFormat::Rgb8),
            "bayer8" => Some(PixelFormat::Bayer8),
            _ => None,
        }
    }
}

impl std::fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Sample storage: 8-bit formats use `U8`, `Mono16` uses `U16`.
#[derive(Debug, Clone, PartialEq)]
pub enum FrameData {
    U8(Vec<u8>),
    U16(Vec<u16>),
}

/// Errors constructing or reshaping frames.
#[derive(Debug, Error, PartialEq)]
pub enum FrameError {
    #[error("frame size {width}x{height} overflows (stride {stride} samples)")]
    Overflow { width: u32, height: u32, stride: usize },
    #[error("frame buffer too small: expected at least {expected} samples, got {got}")]
    BufferTooSmall { expected: usize, got: usize },
    #[error("stride {stride} samples is smaller than a row ({row} samples = width x channels)")]
    StrideTooSmall { stride: usize, row: usize },
    #[error("sample storage does not match format {format}: expected {expected}-bit samples")]
    StorageMismatch { format: PixelFormat, expected: u32 },
    #[error("frame is empty ({width}x{height}); width and height must be at least 1")]
    Empty { width: u32, height: u32 },
}

/// `CLOCK_MONOTONIC` now, ns: the clock of V4L2 buffer timestamps (a `v4l2:` camera's pts, the
/// stamps a `v4l2:` sink queues).
pub fn monotonic_ns() -> u64 {
    // SAFETY: all-zero is a valid timespec; clock_gettime fills it.
    let mut t: libc::timespec = unsafe { std::mem::zeroed() };
    // SAFETY: `t` outlives the call; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut t) };
    t.tv_sec as u64 * 1_000_000_000 + t.tv_nsec as u64
}

/// One image with its stream metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Input sequence number (0-based, as delivered by the source).
    pub seq: u64,
    /// Presentation timestamp in nanoseconds (capture time where the source knows it).
    pub pts_ns: u64,
    pub width: u32,
    pub height: u32,
    /// Row pitch in samples (>= width * channels).
    pub stride: usize,
    pub format: PixelFormat,
    pub data: FrameData,
}

/// A sample type: `u8` or `u16`.
pub trait Sample: Copy + Send + Sync + Default + PartialOrd + 'static {
    /// Largest representable value.
    const MAX_F32: f32;
    const MAX_U32: u32;
    fn to_f32(self) -> f32;
    fn to_u32(self) -> u32;
    /// Round to nearest and clamp to [0, MAX].
    fn from_f32(v: f32) -> Self;
    /// Saturating conversion.
    fn from_u32_sat(v: u32) -> Self;
    /// The samples as bytes, when they are bytes (8-bit kernels).
    fn bytes(s: &[Self]) -> Option<&[u8]> {
        let _ = s;
        None
    }
    /// The samples as mutable bytes, when they are bytes (8-bit kernels).
    fn bytes_mut(s: &mut [Self]) -> Option<&mut [u8]> {
        let _ = s;
        None
    }
}

impl Sample for u8 {
    const MAX_F32: f32 = 255.0;
    const MAX_U32: u32 = 255;
    fn bytes(s: &[u8]) -> Option<&[u8]> {
        Some(s)
    }
    fn bytes_mut(s: &mut [u8]) -> Option<&mut [u8]> {
        Some(s)
    }
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self as f32
    }
    #[inline(always)]
    fn to_u32(self) -> u32 {
        self as u32
    }
    #[inline(always)]
    // `max`/`min` rather than `clamp`: they map NaN to a bound (clamp would keep NaN).
    #[allow(clippy::manual_clamp)]
    fn from_f32(v: f32) -> Self {
        // Round half up and clip: the same results as the saturating `(v + 0.5) as u8` (NaN gives
        // 0: `max` ignores NaN), written so that the range is explicit and loops vectorise.
        let x = (v + 0.5).max(0.0).min(255.0);
        // SAFETY: x is finite and in [0, 255] (NaN became 0 above), so it fits an i32.
        unsafe { x.to_int_unchecked::<i32>() as u8 }
    }
    #[inline(always)]
    fn from_u32_sat(v: u32) -> Self {
        v.min(255) as u8
    }
}

impl Sample for u16 {
    const MAX_F32: f32 = 65535.0;
    const MAX_U32: u32 = 65535;
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self as f32
    }
    #[inline(always)]
    fn to_u32(self) -> u32 {
        self as u32
    }
    #[inline(always)]
    #[allow(clippy::manual_clamp)] // NaN-safe, see u8
    fn from_f32(v: f32) -> Self {
        let x = (v + 0.5).max(0.0).min(65535.0);
        // SAFETY: x is finite and in [0, 65535] (NaN became 0 above), so it fits an i32.
        unsafe { x.to_int_unchecked::<i32>() as u16 }
    }
    #[inline(always)]
    fn from_u32_sat(v: u32) -> Self {
        v.min(65535) as u16
    }
}

/// Mutable strided view of a frame's samples.
#[derive(Debug)]
pub struct ImageMut<'a, T> {
    pub data: &'a mut [T],
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    /// Row pitch in samples.
    pub stride: usize,
}

/// Shared strided view of a frame's samples.
#[derive(Debug, Clone, Copy)]
pub struct ImageRef<'a, T> {
    pub data: &'a [T],
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub stride: usize,
}

impl<'a, T: Sample> ImageMut<'a, T> {
    /// Samples in one row without padding.
    pub fn row_len(&self) -> usize {
        self.width * self.channels
    }
    pub fn row(&self, y: usize) -> &[T] {
        let s = y * self.stride;
        &self.data[s..s + self.row_len()]
    }
    pub fn row_mut(&mut self, y: usize) -> &mut [T] {
        let s = y * self.stride;
        let n = self.row_len();
        &mut self.data[s..s + n]
    }
    /// Rows without padding, mutable (for `rayon::par_chunks` style use the raw `data` with `stride`).
    pub fn rows_mut(&mut self) -> impl Iterator<Item = &mut [T]> {
        let n = self.row_len();
        self.data.chunks_mut(self.stride).take(self.height).map(move |r| &mut r[..n])
    }
    pub fn as_ref(&self) -> ImageRef<'_, T> {
        ImageRef {
            data: self.data,
            width: self.width,
            height: self.height,
            channels: self.channels,
            stride: self.stride,
        }
    }
}

impl<'a, T: Sample> ImageRef<'a, T> {
    pub fn row_len(&self) -> usize {
        self.width * self.channels
    }
    pub fn row(&self, y: usize) -> &'a [T] {
        let s = y * self.stride;
        &self.data[s..s + self.row_len()]
    }
    pub fn rows(&self) -> impl Iterator<Item = &'a [T]> + '_ {
        let n = self.row_len();
        self.data.chunks(self.stride).take(self.height).map(move |r| &r[..n])
    }
}

/// Either sample type, mutable.
pub enum AnyImageMut<'a> {
    U8(ImageMut<'a, u8>),
    U16(ImageMut<'a, u16>),
}

/// Either sample type, shared.
pub enum AnyImageRef<'a> {
    U8(ImageRef<'a, u8>),
    U16(ImageRef<'a, u16>),
}

/// Run a generic body on the frame's samples whatever their type:
/// `with_image_mut!(frame, img => my_generic_fn(&mut img, ...))`.
#[macro_export]
macro_rules! with_image_mut {
    ($frame:expr, $img:ident => $body:expr) => {
        match $frame.image_mut() {
            #[allow(unused_mut)]
            $crate::frame::AnyImageMut::U8(mut $img) => $body,
            #[allow(unused_mut)]
            $crate::frame::AnyImageMut::U16(mut $img) => $body,
        }
    };
}

/// Shared-view counterpart of [`with_image_mut!`].
#[macro_export]
macro_rules! with_image_ref {
    ($frame:expr, $img:ident => $body:expr) => {
        match $frame.image_ref() {
            $crate::frame::AnyImageRef::U8($img) => $body,
            $crate::frame::AnyImageRef::U16($img) => $body,
        }
    };
}

impl Frame {
    /// A zero-filled, tightly packed frame.
    pub fn new(width: u32, height: u32, format: PixelFormat) -> Result<Frame, FrameError> {
        if width == 0 || height == 0 {
            return Err(FrameError::Empty { width, height });
        }
        let stride =
            (width as usize).checked_mul(format.channels()).ok_or(FrameError::Overflow { width, height, stride: 0 })?;
        let len = stride.checked_mul(height as usize).ok_or(FrameError::Overflow { width, height, stride })?;
        let data = match format {
            PixelFormat::Mono16 => FrameData::U16(vec![0; len]),
            _ => FrameData::U8(vec![0; len]),
        };
        Ok(Frame { seq: 0, pts_ns: 0, width, height, stride, format, data })
    }

    /// A frame with no pixels (0x0 mono8): a slot a source or decoder fills and reshapes.
    pub fn empty() -> Frame {
        Frame {
            seq: 0,
            pts_ns: 0,
            width: 0,
            height: 0,
            stride: 0,
            format: PixelFormat::Mono8,
            data: FrameData::U8(Vec::new()),
        }
    }

    /// Wrap existing samples, validating sizes.
    pub fn from_data(
        width: u32,
        height: u32,
        stride: usize,
        format: PixelFormat,
        data: FrameData,
    ) -> Result<Frame, FrameError> {
        if width == 0 || height == 0 {
            return Err(FrameError::Empty { width, height });
        }
        let row =
            (width as usize).checked_mul(format.channels()).ok_or(FrameError::Overflow { width, height, stride })?;
        if stride < row {
            return Err(FrameError::StrideTooSmall { stride, row });
        }
        let expected = stride
            .checked_mul(height as usize - 1)
            .and_then(|v| v.checked_add(row))
            .ok_or(FrameError::Overflow { width, height, stride })?;
        let got = match (&data, format) {
            (FrameData::U16(d), PixelFormat::Mono16) => d.len(),
            (FrameData::U8(d), f) if f != PixelFormat::Mono16 => d.len(),
            _ => {
                return Err(FrameError::StorageMismatch {
                    format,
                    expected: if format == PixelFormat::Mono16 { 16 } else { 8 },
                });
            }
        };
        if got < expected {
            return Err(FrameError::BufferTooSmall { expected, got });
        }
        Ok(Frame { seq: 0, pts_ns: 0, width, height, stride, format, data })
    }

    pub fn channels(&self) -> usize {
        self.format.channels()
    }
    pub fn full_scale(&self) -> f32 {
        self.format.full_scale()
    }
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
    /// Row length in samples, without padding.
    pub fn row_len(&self) -> usize {
        self.width as usize * self.channels()
    }

    pub fn image_mut(&mut self) -> AnyImageMut<'_> {
        let (width, height, channels, stride) =
            (self.width as usize, self.height as usize, self.channels(), self.stride);
        match &mut self.data {
            FrameData::U8(d) => AnyImageMut::U8(ImageMut { data: d, width, height, channels, stride }),
            FrameData::U16(d) => AnyImageMut::U16(ImageMut { data: d, width, height, channels, stride }),
        }
    }

    pub fn image_ref(&self) -> AnyImageRef<'_> {
        let (width, height, channels, stride) =
            (self.width as usize, self.height as usize, self.channels(), self.stride);
        match &self.data {
            FrameData::U8(d) => AnyImageRef::U8(ImageRef { data: d, width, height, channels, stride }),
            FrameData::U16(d) => AnyImageRef::U16(ImageRef { data: d, width, height, channels, stride }),
        }
    }

    /// 8-bit samples, if this is an 8-bit format.
    pub fn as_u8(&self) -> Option<&[u8]> {
        match &self.data {
            FrameData::U8(d) => Some(d),
            FrameData::U16(_) => None,
        }
    }
    pub fn as_u8_mut(&mut self) -> Option<&mut [u8]> {
        match &mut self.data {
            FrameData::U8(d) => Some(d),
            FrameData::U16(_) => None,
        }
    }
    pub fn as_u16(&self) -> Option<&[u16]> {
        match &self.data {
            FrameData::U16(d) => Some(d),
            FrameData::U8(_) => None,
        }
    }
    pub fn as_u16_mut(&mut self) -> Option<&mut [u16]> {
        match &mut self.data {
            FrameData::U16(d) => Some(d),
            FrameData::U8(_) => None,
        }
    }

    /// Sample at (x, y, channel) as f32 DN (for tests and diagnostics; not for hot loops).
    pub fn get(&self, x: usize, y: usize, c: usize) -> f32 {
        let i = y * self.stride + x * self.channels() + c;
        match &self.data {
            FrameData::U8(d) => d[i] as f32,
            FrameData::U16(d) => d[i] as f32,
        }
    }

    /// Set sample at (x, y, channel), rounding and clamping (for tests and scene generation).
    pub fn set(&mut self, x: usize, y: usize, c: usize, v: f32) {
        let i = y * self.stride + x * self.channels() + c;
        match &mut self.data {
            FrameData::U8(d) => d[i] = u8::from_f32(v),
            FrameData::U16(d) => d[i] = u16::from_f32(v),
        }
    }

    /// Packed copy of the samples (no padding), row-major.
    pub fn packed_samples_f32(&self) -> Vec<f32> {
        let mut out = Vec::with_capacity(self.pixels() * self.channels());
        with_image_ref!(self, img => {
            for r in img.rows() {
                out.extend(r.iter().map(|v| v.to_f32()));
            }
        });
        out
    }

    /// Copy content and metadata from `other` into `self`, reusing `self`'s allocation when it is
    /// large enough (frame pools use this to avoid per-frame allocation).
    pub fn copy_from(&mut self, other: &Frame) {
        self.seq = other.seq;
        self.pts_ns = other.pts_ns;
        self.width = other.width;
        self.height = other.height;
        self.stride = other.stride;
        self.format = other.format;
        match (&mut self.data, &other.data) {
            (FrameData::U8(a), FrameData::U8(b)) => {
                a.clear();
                a.extend_from_slice(b);
            }
            (FrameData::U16(a), FrameData::U16(b)) => {
                a.clear();
                a.extend_from_slice(b);
            }
            (a, b) => *a = b.clone(),
        }
    }

    /// Same content, tightly packed (stride = width * channels).
    pub fn to_packed(&self) -> Frame {
        if self.stride == self.row_len() {
            return self.clone();
        }
        let n = self.row_len();
        let data = match &self.data {
            FrameData::U8(d) => {
                FrameData::U8(d.chunks(self.stride).take(self.height as usize).flat_map(|r| &r[..n]).copied().collect())
            }
            FrameData::U16(d) => FrameData::U16(
                d.chunks(self.stride).take(self.height as usize).flat_map(|r| &r[..n]).copied().collect(),
            ),
        };
        Frame {
            seq: self.seq,
            pts_ns: self.pts_ns,
            width: self.width,
            height: self.height,
            stride: n,
            format: self.format,
            data,
        }
    }
}

impl Clone for AnyImageRef<'_> {
    fn clone(&self) -> Self {
        match self {
            AnyImageRef::U8(i) => AnyImageRef::U8(*i),
            AnyImageRef::U16(i) => AnyImageRef::U16(*i),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn from_data_validates_sizes() {
        assert!(matches!(
            Frame::from_data(4, 2, 3, PixelFormat::Mono8, FrameData::U8(vec![0; 8])),
            Err(FrameError::StrideTooSmall { stride: 3, row: 4 })
        ));
        assert!(matches!(
            Frame::from_data(4, 2, 5, PixelFormat::Mono8, FrameData::U8(vec![0; 8])),
            Err(FrameError::BufferTooSmall { expected: 9, got: 8 })
        ));
        assert!(Frame::from_data(4, 2, 5, PixelFormat::Mono8, FrameData::U8(vec![0; 9])).is_ok());
        assert!(matches!(
            Frame::from_data(4, 2, 4, PixelFormat::Mono16, FrameData::U8(vec![0; 8])),
            Err(FrameError::StorageMismatch { .. })
        ));
    }

    #[test]
    fn from_f32_rounds_half_up_and_saturates_like_as() {
        let mut vals = vec![f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1e9, 1e9, -0.5, -0.49, 0.49, 0.5];
        vals.extend((0..300_000).map(|i| -10.0 + i as f32 * 0.2501));
        for v in vals {
            assert_eq!(u8::from_f32(v), (v + 0.5) as u8, "{v}");
            assert_eq!(u16::from_f32(v), (v + 0.5) as u16, "{v}");
            assert_eq!(u16::from_f32(v * 300.0), (v * 300.0 + 0.5) as u16, "{v}");
        }
    }

    #[test]
    fn packed_drops_padding() {
        let mut f = Frame::from_data(2, 2, 3, PixelFormat::Mono8, FrameData::U8(vec![1, 2, 99, 3, 4, 99])).unwrap();
        f.seq = 7;
        let p = f.to_packed();
        assert_eq!(p.as_u8().unwrap(), &[1, 2, 3, 4]);
        assert_eq!(p.seq, 7);
        assert_eq!(p.stride, 2);
    }
}
