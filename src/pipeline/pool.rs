//! A small frame pool for sources: frames given back with [`crate::source::Source::recycle`]
//! are reshaped and refilled instead of allocating a new buffer per frame.

use crate::frame::{Frame, FrameData, FrameError, PixelFormat};

/// Frames waiting to be reused.
#[derive(Debug, Default)]
pub struct FramePool {
    frames: Vec<Frame>,
    cap: usize,
}

impl FramePool {
    /// A pool that keeps at most `cap` spare frames.
    pub fn new(cap: usize) -> FramePool {
        // allocation: once per stream
        FramePool { frames: Vec::with_capacity(cap), cap }
    }

    /// Keep a frame for reuse (dropped when the pool is full).
    pub fn give(&mut self, frame: Frame) {
        if self.frames.len() < self.cap {
            self.frames.push(frame);
        }
    }

    /// A tightly packed frame of this size and format, reusing a spare buffer when there is
    /// one (no allocation once the pool holds buffers of the stream's size). The samples are
    /// left as they were: the caller overwrites every row.
    pub fn take(&mut self, width: u32, height: u32, format: PixelFormat) -> Result<Frame, FrameError> {
        if width == 0 || height == 0 {
            return Err(FrameError::Empty { width, height });
        }
        let stride =
            (width as usize).checked_mul(format.channels()).ok_or(FrameError::Overflow { width, height, stride: 0 })?;
        let len = stride.checked_mul(height as usize).ok_or(FrameError::Overflow { width, height, stride })?;
        let mut f = match self.frames.pop() {
            Some(f) => f,
            None => Frame::new(width, height, format)?,
        };
        match (&mut f.data, format) {
            (FrameData::U16(v), PixelFormat::Mono16) => v.resize(len, 0),
            (FrameData::U8(v), fmt) if fmt != PixelFormat::Mono16 => v.resize(len, 0),
            (d, PixelFormat::Mono16) => *d = FrameData::U16(vec![0; len]),
            (d, _) => *d = FrameData::U8(vec![0; len]),
        }
        f.width = width;
        f.height = height;
        f.stride = stride;
        f.format = format;
        Ok(f)
    }
}

/// Copy `height` rows of `row_bytes` bytes from `src` (row pitch `src_stride` bytes) into the
/// packed frame `dst`. 16-bit frames take little-endian byte pairs.
pub fn copy_rows_into(dst: &mut Frame, src: &[u8], src_stride: usize) -> Result<(), FrameError> {
    let h = dst.height as usize;
    let row = dst.row_len();
    let bps = dst.format.bytes_per_sample();
    let row_bytes = row * bps;
    let need = if h == 0 { 0 } else { src_stride * (h - 1) + row_bytes };
    if src.len() < need || src_stride < row_bytes {
        return Err(FrameError::BufferTooSmall { expected: need, got: src.len() });
    }
    let stride = dst.stride;
    match &mut dst.data {
        FrameData::U8(d) => {
            for (y, out) in d.chunks_exact_mut(stride).take(h).enumerate() {
                let s = &src[y * src_stride..y * src_stride + row_bytes];
                out[..row].copy_from_slice(s);
            }
        }
        FrameData::U16(d) => {
            for (y, out) in d.chunks_exact_mut(stride).take(h).enumerate() {
                let s = &src[y * src_stride..y * src_stride + row_bytes];
                for (o, b) in out[..row].iter_mut().zip(s.chunks_exact(2)) {
                    *o = u16::from_le_bytes([b[0], b[1]]);
                }
            }
        }
    }
    Ok(())
}

/// Copy the frame's rows into `dst` (row pitch `dst_stride` bytes); 16-bit samples are
/// written little-endian.
pub fn copy_rows_out(src: &Frame, dst: &mut [u8], dst_stride: usize) -> Result<(), FrameError> {
    let h = src.height as usize;
    let row = src.row_len();
    let row_bytes = row * src.format.bytes_per_sample();
    let need = if h == 0 { 0 } else { dst_stride * (h - 1) + row_bytes };
    if dst.len() < need || dst_stride < row_bytes {
        return Err(FrameError::BufferTooSmall { expected: need, got: dst.len() });
    }
    match &src.data {
        FrameData::U8(d) => {
            for (y, r) in d.chunks(src.stride).take(h).enumerate() {
                dst[y * dst_stride..y * dst_stride + row_bytes].copy_from_slice(&r[..row]);
            }
        }
        FrameData::U16(d) => {
            for (y, r) in d.chunks(src.stride).take(h).enumerate() {
                let out = &mut dst[y * dst_stride..y * dst_stride + row_bytes];
                for (o, v) in out.chunks_exact_mut(2).zip(&r[..row]) {
                    o.copy_from_slice(&v.to_le_bytes());
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pool_reuses_and_reshapes() {
        let mut p = FramePool::new(2);
        let f = p.take(4, 3, PixelFormat::Mono8).unwrap();
        let ptr = f.as_u8().unwrap().as_ptr();
        p.give(f);
        let f = p.take(2, 3, PixelFormat::Mono8).unwrap();
        assert_eq!(f.as_u8().unwrap().as_ptr(), ptr, "buffer reused");
        assert_eq!((f.width, f.height, f.stride, f.as_u8().unwrap().len()), (2, 3, 2, 6));
        p.give(f);
        let f = p.take(2, 2, PixelFormat::Mono16).unwrap();
        assert_eq!(f.as_u16().unwrap().len(), 4);
    }

    #[test]
    fn rows_round_trip_with_padding() {
        let mut f = Frame::new(3, 2, PixelFormat::Mono16).unwrap();
        let src: Vec<u8> = vec![1, 0, 2, 0, 3, 1, 99, 99, 4, 0, 5, 0, 6, 2, 99, 99];
        copy_rows_into(&mut f, &src, 8).unwrap();
        assert_eq!(f.as_u16().unwrap(), &[1, 2, 259, 4, 5, 518]);
        let mut out = vec![0u8; 16];
        copy_rows_out(&f, &mut out, 8).unwrap();
        assert_eq!(&out[..6], &src[..6]);
        assert_eq!(&out[8..14], &src[8..14]);
        assert!(copy_rows_into(&mut f, &src[..10], 8).is_err());
    }
}
