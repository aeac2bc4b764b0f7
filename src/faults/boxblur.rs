//! Gaussian blur of 8-bit frames at a cost independent of sigma: a cascade of `K` = 4 box
//! filters per axis (running sums), in 16-bit integer lanes.
//!
//! Each axis convolves with `B = box(w1) * box(w2) * box(w3) * box(w4)` (widths chosen once per
//! sigma to minimise the largest step-response difference to the discrete Gaussian, see
//! [`BoxPlan::for_sigma`]); 2D is `B(x) B(y)`, mirrored borders (half-sample symmetric).
//! Samples are held as `v * S` in `u16` (`S` as large as the widest box allows: the window sum of
//! a box must stay below 2^16). A stage keeps a running window sum (wrapping `u16` arithmetic,
//! exact because the true sum is < 2^16) and outputs `round(sum / w)` exactly (rounded half up,
//! computed with a reciprocal multiply and one correction step). Every path (AVX-512, AVX2,
//! scalar) runs the same integer operations on the same values: the bytes do not depend on the
//! CPU, and each column strip / row band is computed whole, so not on the thread count either.
//!
//! Data flow: pass 1 runs the cascade down columns (strips of [`LANES`] byte columns, all rows,
//! into a strip-major `u16` buffer); pass 2 transposes bands of [`LANES`] rows (8 x 8 blocks),
//! runs the cascade along each channel of the rows, transposes back and stores bytes.

use super::defocus::mirror;
use rayon::prelude::*;

/// Lanes (columns in pass 1, rows in pass 2) processed together.
pub const LANES: usize = 64;
type Lane = [u16; LANES];

/// Number of boxes per axis.
pub const K: usize = 4;

/// Widths and fixed-point scale of a box cascade.
#[derive(Clone, Debug, PartialEq)]
pub struct BoxPlan {
    /// Box widths (>= 1; the sum of `w - 1` is even, so the cascade is centred).
    pub widths: [usize; K],
    /// Samples are held as `v * scale`.
    pub scale: u16,
    /// Half support of the cascade: `sum(w - 1) / 2`.
    pub radius: usize,
}

/// Exact 1D kernel of a box cascade (taps `-radius..=radius`).
pub fn cascade_kernel(widths: &[usize]) -> Vec<f64> {
    let mut k = vec![1.0f64];
    for &w in widths {
        let mut o = vec![0.0; k.len() + w - 1];
        for (i, &a) in k.iter().enumerate() {
            for v in &mut o[i..i + w] {
                *v += a / w as f64;
            }
        }
        k = o;
    }
    k
}

/// Largest |difference| of the cumulative sums of two centred odd-length kernels (the
/// step-response error, as a fraction of the step).
pub fn step_error(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().max(b.len());
    let (pa, pb) = ((n - a.len()) / 2, (n - b.len()) / 2);
    let (mut ca, mut cb, mut worst) = (0.0f64, 0.0f64, 0.0f64);
    for i in 0..n {
        ca += if i >= pa && i - pa < a.len() { a[i - pa] } else { 0.0 };
        cb += if i >= pb && i - pb < b.len() { b[i - pb] } else { 0.0 };
        worst = worst.max((ca - cb).abs());
    }
    worst
}

impl BoxPlan {
    /// The cascade closest to the discrete Gaussian of standard deviation `sigma` (> 0): among
    /// the widths around `sqrt(12 sigma^2 / K + 1)` (each box has variance (w^2 - 1) / 12), the set
    /// with the smallest step-response error.
    pub fn for_sigma(sigma: f64) -> BoxPlan {
        let g = super::defocus::discrete_gaussian_f64(sigma);
        let wc = (12.0 * sigma * sigma / K as f64 + 1.0).sqrt().round() as usize;
        let (lo, hi) = (wc.saturating_sub(3).max(1), wc + 3);
        let mut best: Option<(f64, [usize; K])> = None;
        let mut ws = [lo; K];
        loop {
            if ws.iter().map(|w| w - 1).sum::<usize>() % 2 == 0 {
                let e = step_error(&cascade_kernel(&ws), &g);
                if best.is_none_or(|(b, _)| e < b) {
                    best = Some((e, ws));
                }
            }
            // Next non-decreasing tuple in [lo, hi]^K.
            let Some(i) = (0..K).rev().find(|&i| ws[i] < hi) else { break };
            let v = ws[i] + 1;
            ws[i..].iter_mut().for_each(|w| *w = v);
        }
        BoxPlan::new(best.expect("one candidate").1)
    }

    /// Plan for given widths.
    pub fn new(widths: [usize; K]) -> BoxPlan {
        let wmax = *widths.iter().max().unwrap();
        assert!(widths.iter().map(|w| w - 1).sum::<usize>() % 2 == 0, "box cascade must be centred");
        // Window sum of the widest box, plus half a box for the rounding, below 2^16.
        // Odd, so that the final rounding to whole DN never meets a tie (round half up would
        // bias the mean by 0.5 / scale DN).
        let scale = ((65535 - wmax / 2) / (255 * wmax)).min(127) as u16;
        let scale = if scale.is_multiple_of(2) { scale - 1 } else { scale };
        assert!(scale >= 1, "box width {wmax} too large for 16-bit lanes");
        BoxPlan { widths, scale, radius: widths.iter().map(|w| w - 1).sum::<usize>() / 2 }
    }

    fn stages(&self) -> impl Iterator<Item = usize> + '_ {
        self.widths.iter().copied().filter(|&w| w > 1)
    }

    /// Lanes of state one line needs (rings and accumulators).
    fn state_lanes(&self) -> usize {
        self.stages().map(|w| w + 1).sum::<usize>()
    }
}

/// Division of `a < 2^16` by `w` (2..=255), rounded half up, as the lanes compute it.
#[inline(always)]
fn div_round(a: u16, w: u16, m: u16) -> u16 {
    let a = a.wrapping_add(w / 2);
    // q = floor(a * floor(2^16 / w) / 2^16) is floor(a / w) or one less.
    let q = ((a as u32 * m as u32) >> 16) as u16;
    let r = a.wrapping_sub(q.wrapping_mul(w));
    q + (r >= w) as u16
}

/// One stage on 64 lanes: `acc += v - slot; slot = v; v = round(acc / w)` ([`div_round`]).
#[inline(always)]
fn stage<const LV: u8>(acc: &mut Lane, slot: &mut Lane, v: &mut Lane, w: u16, m: u16) {
    #[cfg(target_arch = "x86_64")]
    {
        if LV == 2 {
            // SAFETY: LV == 2 only inside functions compiled with AVX-512 F/BW/VL, called after
            // the runtime check.
            return unsafe { simd::stage512(acc, slot, v, w, m) };
        }
        if LV == 1 {
            // SAFETY: as above, AVX2.
            return unsafe { simd::stage256(acc, slot, v, w, m) };
        }
    }
    for l in 0..LANES {
        acc[l] = acc[l].wrapping_add(v[l]).wrapping_sub(slot[l]);
        slot[l] = v[l];
        v[l] = div_round(acc[l], w, m);
    }
}

/// `v = round(v / s)` on 64 lanes (the same operations as [`stage`], on a zero window).
#[inline(always)]
fn descale<const LV: u8>(v: &mut Lane, s: u16) {
    if s > 1 {
        let (mut acc, mut slot) = ([0u16; LANES], [0u16; LANES]);
        stage::<LV>(&mut acc, &mut slot, v, s, (65536 / s as u32) as u16);
    }
}

/// Position in a line: per stage its ring slot for the current input and whether it is active
/// (has inputs yet) and full (outputs a value). The same for every strip or channel at the same
/// virtual index, so it is advanced once per index.
#[derive(Clone, Copy)]
struct Cursor {
    n: usize,
    w: [usize; K],
    m: [u16; K],
    lag: [usize; K],
    pos: [usize; K],
    i: usize,
}

impl Cursor {
    fn new(plan: &BoxPlan) -> Cursor {
        let mut c = Cursor { n: 0, w: [1; K], m: [0; K], lag: [0; K], pos: [0; K], i: 0 };
        let mut lag = 0;
        for w in plan.stages() {
            c.w[c.n] = w;
            c.m[c.n] = (65536 / w) as u16;
            c.lag[c.n] = lag;
            lag += w - 1;
            c.n += 1;
        }
        c
    }

    /// Move to the next virtual index.
    #[inline(always)]
    fn advance(&mut self) {
        for k in 0..self.n {
            if self.i >= self.lag[k] {
                self.pos[k] += 1;
                if self.pos[k] == self.w[k] {
                    self.pos[k] = 0;
                }
            }
        }
        self.i += 1;
    }
}

/// Push input `v` (virtual sample `cur.i` of the line) through the stages (each starts once the
/// one before has a full window); true, with `v` the cascade's output `i - 2 radius`, once
/// every stage has a full window. `state` holds per stage a ring of `w` lanes and the window sum.
#[inline(always)]
fn push_all<const LV: u8>(cur: &Cursor, state: &mut [Lane], v: &mut Lane) -> bool {
    let mut off = 0;
    for k in 0..cur.n {
        let w = cur.w[k];
        if cur.i < cur.lag[k] {
            return false;
        }
        let (ring, rest) = state[off..].split_at_mut(w);
        stage::<LV>(&mut rest[0], &mut ring[cur.pos[k]], v, w as u16, cur.m[k]);
        if cur.i - cur.lag[k] + 1 < w {
            return false;
        }
        off += w + 1;
    }
    true
}

/// Strips per column block of pass 1 (rows are read 512 bytes at a time).
const STRIPS_PER_BLOCK: usize = 8;

/// Pass 1 over a block of strips (strip `s0 + k` starts at byte column `min((s0 + k) LANES,
/// rl - LANES)`): all rows, into `out` (`h` lanes per strip).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn column_block<const LV: u8>(
    plan: &BoxPlan,
    src: &[u8],
    stride: usize,
    rl: usize,
    h: usize,
    s0: usize,
    out: &mut [Lane],
    state: &mut [Lane],
) {
    let sl = plan.state_lanes();
    let nst = out.len() / h;
    let sc = plan.scale;
    let r = plan.radius as isize;
    let r2 = 2 * plan.radius;
    state.iter_mut().for_each(|l| *l = [0; LANES]);
    let mut v = [0u16; LANES];
    let mut cur = Cursor::new(plan);
    for i in 0..h + r2 {
        let y = mirror(i as isize - r, h);
        // The rows are a page apart: prefetch the block's bytes of a row a few steps ahead (the
        // hardware prefetchers do not follow such strides). No effect on the values.
        #[cfg(target_arch = "x86_64")]
        {
            let yp = mirror(i as isize + 6 - r, h);
            for k in 0..nst {
                let j0 = ((s0 + k) * LANES).min(rl - LANES);
                // SAFETY: a prefetch hint of an address inside `src` (no access is made).
                unsafe {
                    use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
                    _mm_prefetch::<_MM_HINT_T0>(src.as_ptr().add(yp * stride + j0) as *const i8);
                }
            }
        }
        for k in 0..nst {
            let j0 = ((s0 + k) * LANES).min(rl - LANES);
            let row: &[u8; LANES] = src[y * stride + j0..y * stride + j0 + LANES].try_into().unwrap();
            for l in 0..LANES {
                v[l] = row[l] as u16 * sc;
            }
            if push_all::<LV>(&cur, &mut state[k * sl..(k + 1) * sl], &mut v) {
                out[k * h + i - r2] = v;
            }
        }
        cur.advance();
    }
}

/// Pass 2 over one band: `bt` holds the band transposed (`bt[j]` = byte column `j` of the
/// band's rows, scaled); the cascade runs along each channel; `ot[j]` receives the 8-bit
/// results (in `u16` lanes).
#[inline(always)]
fn row_band<const LV: u8>(plan: &BoxPlan, w: usize, ch: usize, bt: &[Lane], ot: &mut [Lane], state: &mut [Lane]) {
    let s = plan.scale;
    let r = plan.radius as isize;
    let r2 = 2 * plan.radius;
    for c in 0..ch {
        state.iter_mut().for_each(|l| *l = [0; LANES]);
        let mut cur = Cursor::new(plan);
        for i in 0..w + r2 {
            let mut v = bt[mirror(i as isize - r, w) * ch + c];
            if push_all::<LV>(&cur, state, &mut v) {
                descale::<LV>(&mut v, s);
                ot[(i - r2) * ch + c] = v;
            }
            cur.advance();
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod simd {
    use super::{LANES, Lane};
    use std::arch::x86_64::*;

    /// 8 x 8 `u16` transpose, SSE2: returns the 8 columns of the rows at `src + r * ss`.
    #[inline(always)]
    unsafe fn cols8(src: *const u16, ss: usize) -> [__m128i; 8] {
        // SAFETY: the caller guarantees 8 readable rows of 8 u16.
        unsafe {
            let ld = |r: usize| _mm_loadu_si128(src.add(r * ss) as *const __m128i);
            let (r0, r1, r2, r3, r4, r5, r6, r7) = (ld(0), ld(1), ld(2), ld(3), ld(4), ld(5), ld(6), ld(7));
            let a0 = _mm_unpacklo_epi16(r0, r1);
            let a1 = _mm_unpackhi_epi16(r0, r1);
            let a2 = _mm_unpacklo_epi16(r2, r3);
            let a3 = _mm_unpackhi_epi16(r2, r3);
            let a4 = _mm_unpacklo_epi16(r4, r5);
            let a5 = _mm_unpackhi_epi16(r4, r5);
            let a6 = _mm_unpacklo_epi16(r6, r7);
            let a7 = _mm_unpackhi_epi16(r6, r7);
            let b0 = _mm_unpacklo_epi32(a0, a2);
            let b1 = _mm_unpackhi_epi32(a0, a2);
            let b2 = _mm_unpacklo_epi32(a1, a3);
            let b3 = _mm_unpackhi_epi32(a1, a3);
            let b4 = _mm_unpacklo_epi32(a4, a6);
            let b5 = _mm_unpackhi_epi32(a4, a6);
            let b6 = _mm_unpacklo_epi32(a5, a7);
            let b7 = _mm_unpackhi_epi32(a5, a7);
            [
                _mm_unpacklo_epi64(b0, b4),
                _mm_unpackhi_epi64(b0, b4),
                _mm_unpacklo_epi64(b1, b5),
                _mm_unpackhi_epi64(b1, b5),
                _mm_unpacklo_epi64(b2, b6),
                _mm_unpackhi_epi64(b2, b6),
                _mm_unpacklo_epi64(b3, b7),
                _mm_unpackhi_epi64(b3, b7),
            ]
        }
    }

    /// `dst[c * ds + r] = src[r * ss + c]`, r, c < 8.
    ///
    /// # Safety
    /// 8 rows of 8 `u16` readable at `src + r * ss`, writable at `dst + c * ds`.
    pub unsafe fn t8x8(src: *const u16, ss: usize, dst: *mut u16, ds: usize) {
        // SAFETY: as documented.
        unsafe {
            for (c, v) in cols8(src, ss).into_iter().enumerate() {
                _mm_storeu_si128(dst.add(c * ds) as *mut __m128i, v);
            }
        }
    }

    /// Like [`t8x8`], each value (<= 255) stored as a byte: `dst[c * ds + r] = src[r * ss + c]`.
    ///
    /// # Safety
    /// 8 rows of 8 `u16` readable at `src + r * ss`, 8 bytes writable at `dst + c * ds`.
    pub unsafe fn t8x8_u8(src: *const u16, ss: usize, dst: *mut u8, ds: usize) {
        // SAFETY: as documented.
        unsafe {
            let c = cols8(src, ss);
            for k in 0..4 {
                let p = _mm_packus_epi16(c[2 * k], c[2 * k + 1]);
                _mm_storel_epi64(dst.add(2 * k * ds) as *mut __m128i, p);
                _mm_storel_epi64(dst.add((2 * k + 1) * ds) as *mut __m128i, _mm_srli_si128(p, 8));
            }
        }
    }

    #[inline]
    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
    pub unsafe fn stage512(acc: &mut Lane, slot: &mut Lane, v: &mut Lane, w: u16, m: u16) {
        let (wv, mv, hv, one) = (
            _mm512_set1_epi16(w as i16),
            _mm512_set1_epi16(m as i16),
            _mm512_set1_epi16((w / 2) as i16),
            _mm512_set1_epi16(1),
        );
        for k in 0..LANES / 32 {
            // SAFETY: 32 u16 at offset 32k of 64-lane arrays.
            unsafe {
                let pa = acc.as_mut_ptr().add(32 * k) as *mut __m512i;
                let ps = slot.as_mut_ptr().add(32 * k) as *mut __m512i;
                let pv = v.as_mut_ptr().add(32 * k) as *mut __m512i;
                let x = _mm512_loadu_si512(pv as *const __m512i);
                let a = _mm512_sub_epi16(
                    _mm512_add_epi16(_mm512_loadu_si512(pa as *const __m512i), x),
                    _mm512_loadu_si512(ps as *const __m512i),
                );
                _mm512_storeu_si512(pa, a);
                _mm512_storeu_si512(ps, x);
                let t = _mm512_add_epi16(a, hv);
                let q = _mm512_mulhi_epu16(t, mv);
                let rem = _mm512_sub_epi16(t, _mm512_mullo_epi16(q, wv));
                let ge = _mm512_cmpge_epu16_mask(rem, wv);
                _mm512_storeu_si512(pv, _mm512_mask_add_epi16(q, ge, q, one));
            }
        }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    pub unsafe fn stage256(acc: &mut Lane, slot: &mut Lane, v: &mut Lane, w: u16, m: u16) {
        let (wv, mv, hv) =
            (_mm256_set1_epi16(w as i16), _mm256_set1_epi16(m as i16), _mm256_set1_epi16((w / 2) as i16));
        for k in 0..LANES / 16 {
            // SAFETY: 16 u16 at offset 16k of 64-lane arrays.
            unsafe {
                let pa = acc.as_mut_ptr().add(16 * k) as *mut __m256i;
                let ps = slot.as_mut_ptr().add(16 * k) as *mut __m256i;
                let pv = v.as_mut_ptr().add(16 * k) as *mut __m256i;
                let x = _mm256_loadu_si256(pv);
                let a = _mm256_sub_epi16(_mm256_add_epi16(_mm256_loadu_si256(pa), x), _mm256_loadu_si256(ps));
                _mm256_storeu_si256(pa, a);
                _mm256_storeu_si256(ps, x);
                let t = _mm256_add_epi16(a, hv);
                let q = _mm256_mulhi_epu16(t, mv);
                let rem = _mm256_sub_epi16(t, _mm256_mullo_epi16(q, wv));
                // rem >= w (unsigned) <=> max(rem, w) == rem: all ones, i.e. -1.
                let ge = _mm256_cmpeq_epi16(_mm256_max_epu16(rem, wv), rem);
                _mm256_storeu_si256(pv, _mm256_sub_epi16(q, ge));
            }
        }
    }
}

/// The kernel level this CPU runs: 2 = AVX-512 (F/BW/VL), 1 = AVX2, 0 = scalar (after
/// `FAULTCAM_NO_AVX512` / `FAULTCAM_NO_SIMD`).
pub fn cpu_level() -> u8 {
    #[cfg(target_arch = "x86_64")]
    {
        if super::kit::has_avx512() {
            return 2;
        }
        if super::kit::has_avx2() {
            return 1;
        }
    }
    0
}

macro_rules! dispatch {
    ($name:ident, $body:ident, ($($a:ident: $t:ty),*)) => {
        fn $name(lv: u8, $($a: $t),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
                unsafe fn v512($($a: $t),*) { $body::<2>($($a),*) }
                #[target_feature(enable = "avx2")]
                unsafe fn v256($($a: $t),*) { $body::<1>($($a),*) }
                if lv >= 2 && super::kit::has_avx512() {
                    // SAFETY: AVX-512 F/BW/VL present (checked).
                    return unsafe { v512($($a),*) };
                }
                if lv >= 1 && super::kit::has_avx2() {
                    // SAFETY: AVX2 present (checked).
                    return unsafe { v256($($a),*) };
                }
            }
            $body::<0>($($a),*)
        }
    };
}

dispatch!(column_block_d, column_block, (plan: &BoxPlan, src: &[u8], stride: usize, rl: usize, h: usize, s0: usize, out: &mut [Lane], state: &mut [Lane]));
dispatch!(row_band_d, row_band, (plan: &BoxPlan, w: usize, ch: usize, bt: &[Lane], ot: &mut [Lane], state: &mut [Lane]));

/// `dst[j][l] = src[l][j]` for `l < src.len()` (<= LANES) and `j < LANES`.
fn transpose_in(lv: u8, src: &[Lane], dst: &mut [Lane]) {
    let rows = src.len();
    let full = rows / 8 * 8;
    #[cfg(target_arch = "x86_64")]
    if lv > 0 {
        for lb in (0..full).step_by(8) {
            for jb in (0..LANES).step_by(8) {
                let s = &src[lb..lb + 8];
                // SAFETY: 8 rows of LANES u16 from s[..][jb..], 8 rows of LANES u16 into
                // dst[jb..jb + 8][lb..]; both in bounds (lb + 8 <= rows, jb + 8 <= LANES).
                unsafe {
                    simd::t8x8(
                        s.as_ptr().cast::<u16>().add(jb),
                        LANES,
                        dst.as_mut_ptr().add(jb).cast::<u16>().add(lb),
                        LANES,
                    )
                };
            }
        }
        for l in full..rows {
            for j in 0..LANES {
                dst[j][l] = src[l][j];
            }
        }
        return;
    }
    for (l, row) in src.iter().enumerate() {
        for j in 0..LANES {
            dst[j][l] = row[j];
        }
    }
}

/// `band[l * stride + j] = ot[j][l]` (as bytes, values <= 255) for `l < rows`, `j < ot.len()`.
fn transpose_out(lv: u8, ot: &[Lane], band: &mut [u8], stride: usize, rows: usize) {
    let rl = ot.len();
    let (fr, fj) = (rows / 8 * 8, rl / 8 * 8);
    #[cfg(target_arch = "x86_64")]
    if lv > 0 {
        for lb in (0..fr).step_by(8) {
            assert!(band.len() >= (lb + 7) * stride + rl);
            for jb in (0..fj).step_by(8) {
                // SAFETY: reads ot[jb..jb + 8][lb..lb + 8] (in bounds), writes 8 bytes at
                // band[(lb + r) * stride + jb..] for r < 8 (asserted above).
                unsafe {
                    simd::t8x8_u8(
                        ot.as_ptr().add(jb).cast::<u16>().add(lb),
                        LANES,
                        band.as_mut_ptr().add(lb * stride + jb),
                        stride,
                    )
                };
            }
            for l in lb..lb + 8 {
                for j in fj..rl {
                    band[l * stride + j] = ot[j][l] as u8;
                }
            }
        }
        for l in fr..rows {
            for j in 0..rl {
                band[l * stride + j] = ot[j][l] as u8;
            }
        }
        return;
    }
    for l in 0..rows {
        for j in 0..rl {
            band[l * stride + j] = ot[j][l] as u8;
        }
    }
}

/// Scratch of [`blur_u8`]; grows only (allocation when the frame size or the widths grow).
#[derive(Default)]
pub struct Scratch {
    // allocation: per frame size: pass-1 output, strip-major (strip, row, lane)
    cols: Vec<Lane>,
    // allocation: per frame size and thread count: per band slot the transposed band (input and
    // output) and the line state
    bands: Vec<Lane>,
    // allocation: per width change: per strip the line state
    state: Vec<Lane>,
}

/// Separable box-cascade blur of an 8-bit frame (`ch` interleaved channels, rows of `stride`
/// bytes) in place. Needs `w * ch >= LANES`.
pub fn blur_u8(d: &mut [u8], stride: usize, w: usize, h: usize, ch: usize, plan: &BoxPlan, sc: &mut Scratch) {
    // The AVX2 kernels: on the AVX-512 machine measured (Zen 4, whose 512-bit units are two
    // 256-bit halves) they are faster than the AVX-512 ones; the bytes are the same.
    blur_u8_at(cpu_level().min(1), d, stride, w, h, ch, plan, sc)
}

/// [`blur_u8`] with the kernels of level `lv` at most (see [`cpu_level`]; tests compare them).
#[allow(clippy::too_many_arguments)]
pub fn blur_u8_at(
    lv: u8,
    d: &mut [u8],
    stride: usize,
    w: usize,
    h: usize,
    ch: usize,
    plan: &BoxPlan,
    sc: &mut Scratch,
) {
    let rl = w * ch;
    assert!(rl >= LANES, "box blur needs rows of at least {LANES} samples");
    let ns = rl.div_ceil(LANES);
    let sl = plan.state_lanes();
    if sc.cols.len() < ns * h {
        sc.cols.resize(ns * h, [0; LANES]);
    }
    let nblk = ns.div_ceil(STRIPS_PER_BLOCK);
    if sc.state.len() < nblk * STRIPS_PER_BLOCK * sl {
        sc.state.resize(nblk * STRIPS_PER_BLOCK * sl, [0; LANES]);
    }
    // Pass 1: columns, in blocks of strips. The last strip overlaps the previous one (same
    // values for the shared columns).
    {
        let src: &[u8] = d;
        sc.cols[..ns * h]
            .par_chunks_mut(h * STRIPS_PER_BLOCK)
            .zip(sc.state.par_chunks_mut(STRIPS_PER_BLOCK * sl))
            .enumerate()
            .for_each(|(b, (out, state))| {
                column_block_d(lv, plan, src, stride, rl, h, b * STRIPS_PER_BLOCK, out, state);
            });
    }
    // Pass 2: bands of LANES rows, in groups of as many bands as there are threads (one
    // scratch slot each).
    let rl8 = rl.div_ceil(8) * 8;
    let per = 2 * rl8 + sl;
    let slots = rayon::current_num_threads().max(1);
    if sc.bands.len() < slots * per {
        sc.bands.resize(slots * per, [0; LANES]);
    }
    let nb = h.div_ceil(LANES);
    let cols = &sc.cols;
    let used = d.len().min(stride * h);
    let mut b0 = 0;
    while b0 < nb {
        let n = slots.min(nb - b0);
        d[..used]
            .par_chunks_mut(stride * LANES)
            .skip(b0)
            .take(n)
            .zip(sc.bands.par_chunks_mut(per).take(n))
            .enumerate()
            .for_each(|(k, (band, slot))| {
                let y0 = (b0 + k) * LANES;
                let rows = LANES.min(h - y0);
                let (bt, rest) = slot.split_at_mut(rl8);
                let (ot, state) = rest.split_at_mut(rl8);
                // Transpose: bt[j][l] = cols[strip(j)][y0 + l][j - j0].
                for s in 0..ns {
                    let j0 = (s * LANES).min(rl - LANES);
                    let strip = &cols[s * h + y0..s * h + y0 + rows];
                    transpose_in(lv, strip, &mut bt[j0..j0 + LANES]);
                }
                row_band_d(lv, plan, w, ch, &bt[..rl], &mut ot[..rl], state);
                // Transpose back and store bytes.
                transpose_out(lv, &ot[..rl], band, stride, rows);
            });
        b0 += n;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn division_is_exact_rounding() {
        for w in 2u16..=255 {
            let m = (65536 / w as u32) as u16;
            for a in (0u32..65536 - w as u32 / 2).step_by(7).chain([65535 - w as u32 / 2]) {
                let want = (a + w as u32 / 2) / w as u32;
                assert_eq!(div_round(a as u16, w, m) as u32, want, "{a} / {w}");
            }
        }
    }

    #[test]
    fn transposes_move_every_value() {
        for rows in [1usize, 7, 8, 13, 64] {
            let src: Vec<Lane> = (0..rows).map(|l| std::array::from_fn(|j| (l * 64 + j) as u16)).collect();
            let mut dst = vec![[0u16; LANES]; LANES];
            transpose_in(cpu_level(), &src, &mut dst);
            for l in 0..rows {
                for j in 0..LANES {
                    assert_eq!(dst[j][l], src[l][j]);
                }
            }
            for rl in [64usize, 70, 203] {
                let ot: Vec<Lane> = (0..rl).map(|j| std::array::from_fn(|l| ((j * 7 + l * 3) % 256) as u16)).collect();
                let stride = rl + 3;
                let mut band = vec![9u8; stride * rows];
                transpose_out(cpu_level(), &ot, &mut band, stride, rows);
                for l in 0..rows {
                    for j in 0..rl {
                        assert_eq!(band[l * stride + j] as u16, ot[j][l]);
                    }
                    assert_eq!(band[l * stride + rl..l * stride + stride], [9, 9, 9]);
                }
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod reference_tests {
    use super::*;
    use crate::frame::{Frame, FrameData, PixelFormat};

    /// The exact model in f64: separable convolution with the cascade kernel, mirrored borders.
    pub(crate) fn exact(src: &[f64], w: usize, h: usize, ch: usize, k: &[f64]) -> Vec<f64> {
        let r = (k.len() / 2) as isize;
        let mut rows = vec![0.0f64; w * h * ch];
        for y in 0..h {
            for x in 0..w {
                for c in 0..ch {
                    rows[(y * w + x) * ch + c] =
                        (-r..=r).map(|j| k[(j + r) as usize] * src[(y * w + mirror(x as isize + j, w)) * ch + c]).sum();
                }
            }
        }
        let mut out = vec![0.0f64; w * h * ch];
        for y in 0..h {
            for x in 0..w {
                for c in 0..ch {
                    out[(y * w + x) * ch + c] = (-r..=r)
                        .map(|j| k[(j + r) as usize] * rows[(mirror(y as isize + j, h) * w + x) * ch + c])
                        .sum();
                }
            }
        }
        out
    }

    #[test]
    fn cascade_is_within_one_dn_of_its_exact_kernel() {
        for (w, h, format) in [(150usize, 130usize, PixelFormat::Rgb8), (97, 70, PixelFormat::Mono8)] {
            let mut f = crate::faults::kit::bench_scene(w as u32, h as u32, format, 7).unwrap();
            for y in 40..60 {
                for x in 50..70 {
                    for c in 0..f.channels() {
                        f.set(x, y, c, 255.0);
                    }
                }
            }
            let ch = f.channels();
            let src: Vec<f64> = f.packed_samples_f32().iter().map(|&v| v as f64).collect();
            for widths in
                [[2, 2, 3, 3], [5, 5, 5, 5], [1, 3, 3, 3], [34, 34, 34, 34], [9, 13, 13, 13], [20, 20, 23, 25]]
            {
                let plan = BoxPlan::new(widths);
                let want = exact(&src, w, h, ch, &cascade_kernel(&widths));
                let mut g = f.clone();
                let stride = g.stride;
                let FrameData::U8(d) = &mut g.data else { unreachable!() };
                blur_u8(d, stride, w, h, ch, &plan, &mut Scratch::default());
                let got = g.packed_samples_f32();
                let (mut worst, mut bias) = (0.0f64, 0.0f64);
                for (&a, &b) in got.iter().zip(&want) {
                    worst = worst.max((a as f64 - b).abs());
                    bias += (a as f64 - b) / want.len() as f64;
                }
                assert!(worst < 1.0, "{format} {widths:?}: max |error| {worst}");
                assert!(bias.abs() < 0.05, "{format} {widths:?}: mean error {bias}");
            }
        }
        let _ = Frame::new(1, 1, PixelFormat::Mono8);
    }

    #[test]
    fn scalar_avx2_and_avx512_levels_give_the_same_bytes() {
        for (w, h, format) in
            [(203usize, 131usize, PixelFormat::Rgb8), (333, 70, PixelFormat::Mono8), (64, 9, PixelFormat::Mono8)]
        {
            let f = crate::faults::kit::bench_scene(w as u32, h as u32, format, 3).unwrap();
            for sigma in [2.1, 3.0, 8.0, 20.0] {
                let plan = BoxPlan::for_sigma(sigma);
                let run = |lv: u8| {
                    let mut g = f.clone();
                    let stride = g.stride;
                    let FrameData::U8(d) = &mut g.data else { unreachable!() };
                    blur_u8_at(lv, d, stride, w, h, format.channels(), &plan, &mut Scratch::default());
                    g
                };
                let scalar = run(0);
                assert_ne!(scalar, f, "{format} sigma {sigma}: blurred");
                assert_eq!(run(1), scalar, "{format} sigma {sigma}: AVX2 vs scalar");
                assert_eq!(run(2), scalar, "{format} sigma {sigma}: AVX-512 vs scalar");
            }
        }
    }
}
