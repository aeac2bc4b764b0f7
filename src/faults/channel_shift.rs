//! `channel_shift`: lateral chromatic misregistration. The red and blue planes are translated
//! relative to green by sub-pixel amounts (lateral colour of the optics, or a misaligned
//! three-chip / filter-wheel camera).

use super::kit::{bands, multiversion};
use super::util::ROWS_PER_TASK;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, PixelFormat};
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "channel_shift",
    stage: Stage::Optics,
    order: 60,
    summary: "red and blue planes translated relative to green by sub-pixel amounts",
    model: "out_R(x, y) = in_R(x - dx_r, y - dy_r), out_B(x, y) = in_B(x - dx_b, y - dy_b), green unchanged; \
            +dx moves the content right, +dy moves it down (px). Sub-pixel positions are interpolated \
            bilinearly with weights quantised to 1/256 px (shift error <= 0.002 px; bilinear interpolation \
            keeps the plane's intensity centroid exactly at the requested shift, with a slight blur of \
            fractional shifts); samples outside the frame repeat the nearest edge pixel. Rounded to \
            nearest DN. Mono formats have no colour planes: the effect is the identity there. All shifts 0 is \
            the identity. Range +-64 px.",
    params: &[
        ParamSpec::float("dx_r", "px", -64.0, 64.0, 0.0, "red plane shift to the right (px)"),
        ParamSpec::float("dy_r", "px", -64.0, 64.0, 0.0, "red plane shift downward (px)"),
        ParamSpec::float("dx_b", "px", -64.0, 64.0, 0.0, "blue plane shift to the right (px)"),
        ParamSpec::float("dy_b", "px", -64.0, 64.0, 0.0, "blue plane shift downward (px)"),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(ChannelShift::default())
}

/// Scratch copies of the red and blue planes.
#[derive(Default)]
pub struct ChannelShift {
    // allocation: once per stream (two w x h planes)
    planes: Vec<u8>,
    // allocation: once per frame size: one shifted row per band
    rows: Vec<u8>,
}

/// Integer part and 8-bit fractional weight of a source offset `-d`:
/// source coordinate = x + i + f/256, f in 0..256.
#[derive(Debug, Clone, Copy)]
struct Tap {
    i: i64,
    f: u32,
}

fn tap(shift: f64) -> Tap {
    let q = (-shift * 256.0).round() as i64;
    Tap { i: q.div_euclid(256), f: q.rem_euclid(256) as u32 }
}

impl Effect for ChannelShift {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if frame.format != PixelFormat::Rgb8 {
            return Ok(Outcome::Keep);
        }
        let shifts = [(0usize, p.get("dx_r"), p.get("dy_r")), (2usize, p.get("dx_b"), p.get("dy_b"))];
        let active = shifts.map(|(c, dx, dy)| {
            let (tx, ty) = (tap(dx), tap(dy));
            (tx.i != 0 || tx.f != 0 || ty.i != 0 || ty.f != 0).then_some((c, tx, ty))
        });
        if active.iter().all(Option::is_none) {
            return Ok(Outcome::Keep);
        }
        let (w, h, stride) = (frame.width as usize, frame.height as usize, frame.stride);
        let row_len = w * 3;
        let Some(data) = frame.as_u8_mut() else {
            return Ok(Outcome::Keep);
        };
        self.planes.resize(2 * w * h, 0);
        // De-interleave R and B.
        let used = stride * (h - 1) + row_len;
        let (pr, pb) = self.planes.split_at_mut(w * h);
        data[..used].par_chunks(stride).zip(pr.par_chunks_mut(w).zip(pb.par_chunks_mut(w))).for_each(
            |(row, (r, b))| {
                split_rb(&row[..row_len], r, b);
            },
        );
        let planes = &self.planes;
        let active = &active;
        self.rows.resize(w * bands(h), 0);
        data[..used].par_chunks_mut(stride * ROWS_PER_TASK).zip(self.rows.par_chunks_mut(w)).enumerate().for_each(
            |(band, (chunk, buf))| {
                for (k, row) in chunk.chunks_mut(stride).enumerate() {
                    let y = band * ROWS_PER_TASK + k;
                    for &(c, tx, ty) in active.iter().flatten() {
                        let plane = &planes[if c == 0 { 0 } else { w * h }..][..w * h];
                        shift_row(buf, plane, w, h, y, tx, ty);
                        put_channel(&mut row[..row_len], buf, c);
                    }
                }
            },
        );
        Ok(Outcome::Keep)
    }
}

/// De-interleave the red and blue samples of an RGB row (AVX-512 VBMI byte permutes for 64
/// pixels at a time when the CPU has them).
fn split_rb(rgb: &[u8], r: &mut [u8], b: &mut [u8]) {
    #[cfg(target_arch = "x86_64")]
    let done = if super::kit::has_avx512_vbmi() {
        // SAFETY: the CPU supports AVX-512 F/BW/VL/VBMI (checked just above).
        unsafe { vbmi::split_rb(rgb, r, b) }
    } else if super::kit::has_avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { ssse3::split_rb(rgb, r, b) }
    } else {
        0
    };
    #[cfg(not(target_arch = "x86_64"))]
    let done = 0;
    split_rb_mv(&rgb[3 * done..], &mut r[done..], &mut b[done..], 0u8);
}

/// Write `plane` into channel `c` of an RGB row (AVX-512 VBMI when the CPU has it).
fn put_channel(rgb: &mut [u8], plane: &[u8], c: usize) {
    #[cfg(target_arch = "x86_64")]
    let done = if super::kit::has_avx512_vbmi() {
        // SAFETY: the CPU supports AVX-512 F/BW/VL/VBMI (checked just above).
        unsafe { vbmi::put_channel(rgb, plane, c) }
    } else if super::kit::has_avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { ssse3::put_channel(rgb, plane, c) }
    } else {
        0
    };
    #[cfg(not(target_arch = "x86_64"))]
    let done = 0;
    put_channel_mv(&mut rgb[3 * done..], &plane[done..], c, 0u8);
}

#[cfg(target_arch = "x86_64")]
mod vbmi {
    use crate::faults::kit::RGB_CHANNEL_BITS;
    use std::arch::x86_64::*;

    /// Byte j of `PIXEL[k]`: the plane index (pixel) of byte 64k + j of 64 RGB pixels.
    const PIXEL: [[u8; 64]; 3] = {
        let mut t = [[0u8; 64]; 3];
        let mut k = 0;
        while k < 3 {
            let mut j = 0;
            while j < 64 {
                t[k][j] = ((64 * k + j) / 3) as u8;
                j += 1;
            }
            k += 1;
        }
        t
    };

    /// Byte p: the position of channel c of pixel p in 192 bytes, as `vpermi2b` indices into
    /// bytes 0..128 (`lo`) and 64..192 (`hi`, offset by 64).
    const fn gather_idx(c: usize, hi: bool) -> [u8; 64] {
        let mut t = [0u8; 64];
        let mut p = 0;
        while p < 64 {
            let pos = 3 * p + c;
            t[p] = if hi { (pos.saturating_sub(64) & 127) as u8 } else { (pos & 127) as u8 };
            p += 1;
        }
        t
    }
    const R_LO: [u8; 64] = gather_idx(0, false);
    const R_HI: [u8; 64] = gather_idx(0, true);
    const B_LO: [u8; 64] = gather_idx(2, false);
    const B_HI: [u8; 64] = gather_idx(2, true);

    #[inline(always)]
    fn load(a: &[u8; 64]) -> __m512i {
        // SAFETY: 64 bytes; unaligned load (AVX-512F context only).
        unsafe { _mm512_loadu_si512(a.as_ptr() as *const __m512i) }
    }

    /// Pixels taken from bytes >= 128 (3p + c >= 128).
    const fn upper(c: usize) -> u64 {
        let mut m = 0u64;
        let mut p = 0;
        while p < 64 {
            if 3 * p + c >= 128 {
                m |= 1 << p;
            }
            p += 1;
        }
        m
    }

    /// Split whole groups of 64 pixels; returns the pixels done.
    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub unsafe fn split_rb(rgb: &[u8], r: &mut [u8], b: &mut [u8]) -> usize {
        let n = (rgb.len() / 3).min(r.len()).min(b.len()) / 64 * 64;
        let (rl, rh, bl, bh) = (load(&R_LO), load(&R_HI), load(&B_LO), load(&B_HI));
        for i in (0..n).step_by(64) {
            // SAFETY: bytes 3i .. 3i + 192 of `rgb` and i .. i + 64 of `r`, `b` exist (i + 64 <= n).
            unsafe {
                let p = rgb.as_ptr().add(3 * i) as *const __m512i;
                let (x0, x1, x2) = (_mm512_loadu_si512(p), _mm512_loadu_si512(p.add(1)), _mm512_loadu_si512(p.add(2)));
                let rv = _mm512_mask_blend_epi8(
                    upper(0),
                    _mm512_permutex2var_epi8(x0, rl, x1),
                    _mm512_permutex2var_epi8(x1, rh, x2),
                );
                let bv = _mm512_mask_blend_epi8(
                    upper(2),
                    _mm512_permutex2var_epi8(x0, bl, x1),
                    _mm512_permutex2var_epi8(x1, bh, x2),
                );
                _mm512_storeu_si512(r.as_mut_ptr().add(i) as *mut __m512i, rv);
                _mm512_storeu_si512(b.as_mut_ptr().add(i) as *mut __m512i, bv);
            }
        }
        n
    }

    /// Put whole groups of 64 pixels; returns the pixels done.
    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub unsafe fn put_channel(rgb: &mut [u8], plane: &[u8], c: usize) -> usize {
        let n = (rgb.len() / 3).min(plane.len()) / 64 * 64;
        if c > 2 {
            return 0;
        }
        let idx = [load(&PIXEL[0]), load(&PIXEL[1]), load(&PIXEL[2])];
        // Register k holds bytes 64k.., which start k samples (mod 3) after a pixel boundary.
        let masks = [RGB_CHANNEL_BITS[0][c], RGB_CHANNEL_BITS[1][c], RGB_CHANNEL_BITS[2][c]];
        for i in (0..n).step_by(64) {
            // SAFETY: bytes i .. i + 64 of `plane` and 3i .. 3i + 192 of `rgb` exist.
            unsafe {
                let v = _mm512_loadu_si512(plane.as_ptr().add(i) as *const __m512i);
                let p = rgb.as_mut_ptr().add(3 * i) as *mut __m512i;
                for k in 0..3 {
                    let spread = _mm512_permutexvar_epi8(idx[k], v);
                    _mm512_mask_storeu_epi8(p.add(k) as *mut i8, masks[k], spread);
                }
            }
        }
        n
    }
}

/// The same de-interleave and channel write with 16-byte byte shuffles (`pshufb`, in an AVX2
/// context): 16 pixels (48 bytes) per step, for CPUs without AVX-512 VBMI.
#[cfg(target_arch = "x86_64")]
mod ssse3 {
    use std::arch::x86_64::*;

    use crate::faults::kit::RGB8_SPLIT as SPLIT;

    /// `SPREAD[k]`: `pshufb` indices putting pixel (16k + j) / 3 of a 16-pixel plane chunk at
    /// byte j of 16-byte part k of its 48 RGB bytes; `CHANNEL[c][k]`: 0xff at the bytes of
    /// channel c there.
    const SPREAD: [[u8; 16]; 3] = {
        let mut t = [[0u8; 16]; 3];
        let mut k = 0;
        while k < 3 {
            let mut j = 0;
            while j < 16 {
                t[k][j] = ((16 * k + j) / 3) as u8;
                j += 1;
            }
            k += 1;
        }
        t
    };
    const CHANNEL: [[[u8; 16]; 3]; 3] = {
        let mut t = [[[0u8; 16]; 3]; 3];
        let mut c = 0;
        while c < 3 {
            let mut k = 0;
            while k < 3 {
                let mut j = 0;
                while j < 16 {
                    if (16 * k + j) % 3 == c {
                        t[c][k][j] = 0xff;
                    }
                    j += 1;
                }
                k += 1;
            }
            c += 1;
        }
        t
    };

    #[inline(always)]
    fn load(a: &[u8; 16]) -> __m128i {
        // SAFETY: 16 bytes; unaligned load.
        unsafe { _mm_loadu_si128(a.as_ptr() as *const __m128i) }
    }

    /// Split whole groups of 16 pixels; returns the pixels done.
    #[target_feature(enable = "avx2")]
    pub unsafe fn split_rb(rgb: &[u8], r: &mut [u8], b: &mut [u8]) -> usize {
        let n = (rgb.len() / 3).min(r.len()).min(b.len()) / 16 * 16;
        let rs = [load(&SPLIT[0][0]), load(&SPLIT[0][1]), load(&SPLIT[0][2])];
        let bs = [load(&SPLIT[2][0]), load(&SPLIT[2][1]), load(&SPLIT[2][2])];
        for i in (0..n).step_by(16) {
            // SAFETY: bytes 3i .. 3i + 48 of `rgb` and i .. i + 16 of `r`, `b` exist (i + 16 <= n).
            unsafe {
                let p = rgb.as_ptr().add(3 * i) as *const __m128i;
                let x = [_mm_loadu_si128(p), _mm_loadu_si128(p.add(1)), _mm_loadu_si128(p.add(2))];
                let pick = |s: &[__m128i; 3]| {
                    _mm_or_si128(
                        _mm_or_si128(_mm_shuffle_epi8(x[0], s[0]), _mm_shuffle_epi8(x[1], s[1])),
                        _mm_shuffle_epi8(x[2], s[2]),
                    )
                };
                _mm_storeu_si128(r.as_mut_ptr().add(i) as *mut __m128i, pick(&rs));
                _mm_storeu_si128(b.as_mut_ptr().add(i) as *mut __m128i, pick(&bs));
            }
        }
        n
    }

    /// [`super::bilinear_row`] for whole groups of 32 pixels in 16-bit lanes; returns the pixels
    /// done. The same integers: the horizontal sums `wx0·p + wx1·q` (at most 256·255) are exact in
    /// u16; the vertical step `wy0·top + wy1·bot` runs in `vpmaddwd` on the sums offset by -2^15
    /// (signed 16-bit), which takes 2^15·(wy0 + wy1) = 2^23 off the 32-bit total: added back with
    /// the rounding constant before the shift.
    #[target_feature(enable = "avx2")]
    pub unsafe fn bilinear_row(out: &mut [u8], a: &[u8], b: &[u8], wx0: u32, wy0: u32) -> usize {
        let n = out.len().min(a.len().saturating_sub(1)).min(b.len().saturating_sub(1)) / 32 * 32;
        debug_assert!(wx0 <= 256 && wy0 <= 256);
        let (wx0v, wx1v) = (_mm256_set1_epi16(wx0 as i16), _mm256_set1_epi16((256 - wx0) as i16));
        let wy = _mm256_set1_epi32((((256 - wy0) << 16) | wy0) as i32);
        let flip = _mm256_set1_epi16(i16::MIN);
        let round = _mm256_set1_epi32((1 << 23) + (1 << 15));
        let half = |x: usize| {
            // SAFETY: AVX2 context; bytes x .. x + 17 of `a` and `b` exist (x + 16 <= n < len).
            unsafe {
                let ld =
                    |s: &[u8], o: usize| _mm256_cvtepu8_epi16(_mm_loadu_si128(s.as_ptr().add(o) as *const __m128i));
                let top = _mm256_add_epi16(_mm256_mullo_epi16(ld(a, x), wx0v), _mm256_mullo_epi16(ld(a, x + 1), wx1v));
                let bot = _mm256_add_epi16(_mm256_mullo_epi16(ld(b, x), wx0v), _mm256_mullo_epi16(ld(b, x + 1), wx1v));
                let (t, u) = (_mm256_xor_si256(top, flip), _mm256_xor_si256(bot, flip));
                let lo = _mm256_srli_epi32::<16>(_mm256_add_epi32(
                    _mm256_madd_epi16(_mm256_unpacklo_epi16(t, u), wy),
                    round,
                ));
                let hi = _mm256_srli_epi32::<16>(_mm256_add_epi32(
                    _mm256_madd_epi16(_mm256_unpackhi_epi16(t, u), wy),
                    round,
                ));
                // In-lane unpack and pack undo each other: pixels x .. x + 16 in order.
                _mm256_packus_epi32(lo, hi)
            }
        };
        for x in (0..n).step_by(32) {
            let bytes = _mm256_packus_epi16(half(x), half(x + 16));
            // SAFETY: bytes x .. x + 32 of `out` exist (x + 32 <= n).
            unsafe {
                _mm256_storeu_si256(
                    out.as_mut_ptr().add(x) as *mut __m256i,
                    _mm256_permute4x64_epi64::<0b11_01_10_00>(bytes),
                )
            };
        }
        n
    }

    /// Put whole groups of 16 pixels; returns the pixels done.
    #[target_feature(enable = "avx2")]
    pub unsafe fn put_channel(rgb: &mut [u8], plane: &[u8], c: usize) -> usize {
        let n = (rgb.len() / 3).min(plane.len()) / 16 * 16;
        if c > 2 {
            return 0;
        }
        let spread = [load(&SPREAD[0]), load(&SPREAD[1]), load(&SPREAD[2])];
        let mask = [load(&CHANNEL[c][0]), load(&CHANNEL[c][1]), load(&CHANNEL[c][2])];
        for i in (0..n).step_by(16) {
            // SAFETY: bytes i .. i + 16 of `plane` and 3i .. 3i + 48 of `rgb` exist.
            unsafe {
                let v = _mm_loadu_si128(plane.as_ptr().add(i) as *const __m128i);
                let p = rgb.as_mut_ptr().add(3 * i) as *mut __m128i;
                for k in 0..3 {
                    let old = _mm_loadu_si128(p.add(k));
                    _mm_storeu_si128(p.add(k), _mm_blendv_epi8(old, _mm_shuffle_epi8(v, spread[k]), mask[k]));
                }
            }
        }
        n
    }
}

multiversion! {
    /// De-interleave the red and blue samples of an RGB row.
    fn split_rb_mv<T: Copy>(rgb: &[u8], r: &mut [u8], b: &mut [u8], _t: T) {
        for ((px, r), b) in rgb.chunks_exact(3).zip(r.iter_mut()).zip(b.iter_mut()) {
            *r = px[0];
            *b = px[2];
        }
    }
}

multiversion! {
    /// Write `plane` into channel `c` of an RGB row.
    fn put_channel_mv<T: Copy>(rgb: &mut [u8], plane: &[u8], c: usize, _t: T) {
        for (px, &v) in rgb.chunks_exact_mut(3).zip(plane) {
            px[c] = v;
        }
    }
}

multiversion! {
    /// Bilinear interpolation of the interior: out[x] from a[x], a[x+1], b[x], b[x+1] with
    /// weights in 1/256 (wx1 = 256 - wx0, wy1 = 256 - wy0), rounded half up.
    fn bilinear_row<T: Copy>(out: &mut [u8], a: &[u8], b: &[u8], wx0: u32, wy0: u32, _t: T) {
        let (wx1, wy1) = (256 - wx0, 256 - wy0);
        let n = out.len();
        let (a0, a1, b0, b1) = (&a[..n], &a[1..n + 1], &b[..n], &b[1..n + 1]);
        for ((((o, &p), &q), &r), &s) in out.iter_mut().zip(a0).zip(a1).zip(b0).zip(b1) {
            let top = wx0 * p as u32 + wx1 * q as u32;
            let bot = wx0 * r as u32 + wx1 * s as u32;
            *o = ((wy0 * top + wy1 * bot + 32768) >> 16) as u8;
        }
    }
}

/// Output row `y` of a plane shifted by (tx, ty), sampled at (x + tx, y + ty), into `out`
/// (`w` samples).
fn shift_row(out: &mut [u8], plane: &[u8], w: usize, h: usize, y: usize, tx: Tap, ty: Tap) {
    let clampy = |v: i64| v.clamp(0, h as i64 - 1) as usize;
    let y0 = clampy(y as i64 + ty.i);
    let y1 = clampy(y as i64 + ty.i + 1);
    let (r0, r1) = (&plane[y0 * w..y0 * w + w], &plane[y1 * w..y1 * w + w]);
    let (wy1, wy0) = (ty.f, 256 - ty.f);
    let (wx1, wx0) = (tx.f, 256 - tx.f);
    let sample = |x0: usize, x1: usize| -> u8 {
        let top = wx0 * r0[x0] as u32 + wx1 * r0[x1] as u32;
        let bot = wx0 * r1[x0] as u32 + wx1 * r1[x1] as u32;
        ((wy0 * top + wy1 * bot + 32768) >> 16) as u8
    };
    // Interior: x + tx.i and x + tx.i + 1 both inside [0, w).
    let lo = (-tx.i).clamp(0, w as i64) as usize;
    let hi = (w as i64 - 1 - tx.i).clamp(lo as i64, w as i64) as usize;
    let clampx = |v: i64| v.clamp(0, w as i64 - 1) as usize;
    for x in (0..lo).chain(hi..w) {
        let xs = x as i64 + tx.i;
        out[x] = sample(clampx(xs), clampx(xs + 1));
    }
    if hi > lo {
        let s0 = (lo as i64 + tx.i) as usize;
        let (out, a, b) = (&mut out[lo..hi], &r0[s0..s0 + (hi - lo) + 1], &r1[s0..s0 + (hi - lo) + 1]);
        #[cfg(target_arch = "x86_64")]
        let done = if super::kit::has_avx2() {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { ssse3::bilinear_row(out, a, b, wx0, wy0) }
        } else {
            0
        };
        #[cfg(not(target_arch = "x86_64"))]
        let done = 0;
        bilinear_row(&mut out[done..], &a[done..], &b[done..], wx0, wy0, 0u8);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Gaussian spot (sigma 3 px, amplitude 200 DN) on a 10 DN background in every channel.
    fn spot(w: u32, h: u32, cx: f32, cy: f32) -> Frame {
        let mut f = Frame::new(w, h, PixelFormat::Rgb8).unwrap();
        for y in 0..h as usize {
            for x in 0..w as usize {
                let d2 = (x as f32 - cx).powi(2) + (y as f32 - cy).powi(2);
                for c in 0..3 {
                    f.set(x, y, c, 10.0 + 200.0 * (-d2 / 18.0).exp());
                }
            }
        }
        f
    }

    /// Background-subtracted intensity centroid of channel c.
    fn centroid(f: &Frame, c: usize) -> (f64, f64) {
        let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for y in 0..f.height as usize {
            for x in 0..f.width as usize {
                let v = (f.get(x, y, c) as f64 - 10.0).max(0.0);
                s += v;
                sx += v * x as f64;
                sy += v * y as f64;
            }
        }
        (sx / s, sy / s)
    }

    fn run(f: &mut Frame, s: [f64; 4]) {
        let mut p = Params::defaults(&INFO);
        for (k, v) in ["dx_r", "dy_r", "dx_b", "dy_b"].iter().zip(s) {
            p.set(k, v).unwrap();
        }
        ChannelShift::default().apply(f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
    }

    #[test]
    fn measured_shift_matches_request_within_0_05_px() {
        for s in [[1.37, -0.62, -2.25, 0.8], [0.5, 0.5, -0.5, -0.5], [-7.9, 3.3, 4.04, -6.75]] {
            let mut f = spot(96, 80, 47.3, 38.6);
            run(&mut f, s);
            let g = centroid(&f, 1);
            let r = centroid(&f, 0);
            let b = centroid(&f, 2);
            // Green is untouched: its centroid is the spot's.
            assert!((g.0 - 47.3).abs() < 0.02 && (g.1 - 38.6).abs() < 0.02, "green {g:?}");
            for (got, want) in [(r.0 - g.0, s[0]), (r.1 - g.1, s[1]), (b.0 - g.0, s[2]), (b.1 - g.1, s[3])] {
                assert!((got - want).abs() < 0.05, "shift {s:?}: measured {got} want {want}");
            }
        }
    }

    #[test]
    fn integer_shift_is_an_exact_translation_and_green_is_untouched() {
        let mut f = Frame::new(40, 30, PixelFormat::Rgb8).unwrap();
        let mut r = crate::rng::Rng::new(3);
        f.as_u8_mut().unwrap().iter_mut().for_each(|v| *v = r.below(256) as u8);
        let orig = f.clone();
        run(&mut f, [3.0, -2.0, -1.0, 4.0]);
        for y in 0..30usize {
            for x in 0..40usize {
                let cl = |v: i64, n: usize| v.clamp(0, n as i64 - 1) as usize;
                assert_eq!(f.get(x, y, 0), orig.get(cl(x as i64 - 3, 40), cl(y as i64 + 2, 30), 0));
                assert_eq!(f.get(x, y, 1), orig.get(x, y, 1));
                assert_eq!(f.get(x, y, 2), orig.get(cl(x as i64 + 1, 40), cl(y as i64 - 4, 30), 2));
            }
        }
    }

    #[test]
    fn channel_split_and_put_equal_their_references() {
        let mut r = crate::rng::Rng::new(4);
        for n in [0usize, 1, 15, 16, 17, 47, 63, 64, 65, 200, 1920] {
            let rgb: Vec<u8> = (0..3 * n).map(|_| r.below(256) as u8).collect();
            let (mut pr, mut pb) = (vec![0u8; n], vec![0u8; n]);
            split_rb(&rgb, &mut pr, &mut pb);
            assert!((0..n).all(|i| pr[i] == rgb[3 * i] && pb[i] == rgb[3 * i + 2]), "split, {n} px");
            // The 16-pixel shuffle versions directly, whatever this CPU dispatches to.
            #[cfg(target_arch = "x86_64")]
            if crate::faults::kit::has_avx2() {
                let (mut sr, mut sb) = (vec![0u8; n], vec![0u8; n]);
                // SAFETY: the CPU supports AVX2 (checked just above).
                let done = unsafe { ssse3::split_rb(&rgb, &mut sr, &mut sb) };
                assert_eq!(done, n / 16 * 16);
                assert_eq!((&sr[..done], &sb[..done]), (&pr[..done], &pb[..done]), "shuffle split, {n} px");
                for c in 0..3 {
                    let (mut out, mut want) = (rgb.clone(), rgb.clone());
                    // SAFETY: as above.
                    let done = unsafe { ssse3::put_channel(&mut out, &pb, c) };
                    put_channel_mv(&mut want[..3 * done], &pb[..done], c, 0u8);
                    assert_eq!(out, want, "shuffle put channel {c}, {n} px");
                }
            }
            for c in 0..3 {
                let mut out = rgb.clone();
                put_channel(&mut out, &pr, c);
                for i in 0..3 * n {
                    let want = if i % 3 == c { pr[i / 3] } else { rgb[i] };
                    assert_eq!(out[i], want, "put channel {c}, {n} px, byte {i}");
                }
            }
        }
    }

    #[test]
    fn bilinear_kernel_equals_its_reference_for_every_weight() {
        // Every (wx0, wy0) in 1..=256 x 0..=256 (wx0 = 256 - f: never 0), random rows plus the
        // extremes (all 255: the largest sums), lengths around the 32-pixel step.
        #[cfg(target_arch = "x86_64")]
        if crate::faults::kit::has_avx2() {
            let mut r = crate::rng::Rng::new(9);
            let rows: Vec<(Vec<u8>, Vec<u8>)> = (0..3)
                .map(|k| match k {
                    0 => (vec![255u8; 100], vec![255u8; 100]),
                    1 => (vec![255u8; 100], vec![0u8; 100]),
                    _ => {
                        ((0..100).map(|_| r.below(256) as u8).collect(), (0..100).map(|_| r.below(256) as u8).collect())
                    }
                })
                .collect();
            for wx0 in 1..=256u32 {
                for wy0 in 0..=256u32 {
                    for (a, b) in &rows {
                        let n = [31usize, 32, 64, 99][(wx0 + wy0) as usize % 4];
                        let (mut got, mut want) = (vec![0u8; n], vec![0u8; n]);
                        bilinear_row(&mut want, &a[..n + 1], &b[..n + 1], wx0, wy0, 0u8);
                        // SAFETY: the CPU supports AVX2 (checked above).
                        let done = unsafe { ssse3::bilinear_row(&mut got, &a[..n + 1], &b[..n + 1], wx0, wy0) };
                        assert_eq!(done, n / 32 * 32);
                        assert_eq!(&got[..done], &want[..done], "wx0 {wx0} wy0 {wy0} n {n}");
                    }
                }
            }
        }
    }

    #[test]
    fn zero_shift_and_mono_are_identity() {
        let mut f = spot(30, 20, 10.0, 10.0);
        let orig = f.clone();
        run(&mut f, [0.0; 4]);
        assert_eq!(f, orig);
        let mut m = Frame::new(30, 20, PixelFormat::Mono8).unwrap();
        m.as_u8_mut().unwrap().fill(9);
        let mo = m.clone();
        run(&mut m, [1.5, 1.0, 2.0, 3.0]);
        assert_eq!(m, mo);
    }
}
