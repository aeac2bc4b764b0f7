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
    /// Per stage (widths > 1, in order) the rounded division by its width.
    divs: [Div; K],
    /// The last stage of the second axis: division by `w * scale` (straight to whole DN).
    last_dn: Div,
}

/// Rounded division of a window sum `a` by a constant `d` (2..=256) with one 16-bit multiply:
/// `round(a / d) = floor((a + d/2) / d) = mulhi(a + add, m) >> sh`, where `m` is either
/// `ceil(2^(16+sh) / d)` (`add = d/2`) or `floor(2^(16+sh) / d)` with the increment folded into
/// `add = d/2 + 1` (Robison's N-bit division by an N-bit multiply-add: for every divisor one of
/// the two is exact), `2^sh < d`. Chosen, and checked exhaustively, for every `a` up to the
/// stage's largest window sum when the plan is made.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Div {
    add: u16,
    m: u16,
    sh: u32,
}

impl Div {
    /// The exact division by `d` for every `a <= amax`, if one of the two forms is.
    fn exact(d: u32, amax: u32) -> Option<Div> {
        assert!((2..=256).contains(&d));
        let sh = 15 - ((d - 1) as u16).leading_zeros();
        let p = 1u64 << (16 + sh);
        let up = p.div_ceil(d as u64);
        let down = p / d as u64;
        let check = |div: Div| {
            (amax + div.add as u32 <= 65535 && (0..=amax).all(|a| div.apply(a as u16) as u32 == (a + d / 2) / d))
                .then_some(div)
        };
        let h = (d / 2) as u16;
        (up < 65536)
            .then(|| check(Div { add: h, m: up as u16, sh }))
            .flatten()
            .or_else(|| check(Div { add: h + 1, m: down as u16, sh }))
    }

    #[inline(always)]
    fn apply(self, a: u16) -> u16 {
        ((a.wrapping_add(self.add) as u32 * self.m as u32) >> (16 + self.sh)) as u16
    }
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
        // Window sum of the widest box, plus half a box for the rounding, below 2^16. Odd: the
        // second axis's last stage divides by `w scale` at once, which for an odd scale equals
        // rounding to a box average first and then to whole DN (no half-way value is crossed),
        // and keeps the rounding to whole DN free of ties; then every divisor is <= 256.
        let scale = ((65535 - wmax / 2) / (255 * wmax)).min(127) as u16;
        let mut scale = if scale.is_multiple_of(2) { scale - 1 } else { scale };
        let stages: Vec<usize> = widths.iter().copied().filter(|&w| w > 1).collect();
        // Every division exact over its stage's range (window sums up to 255 scale w); a lower
        // (odd) scale if not (none of the plans for sigma in (3, 20] needs it).
        loop {
            assert!(scale >= 1, "box width {wmax} too large for 16-bit lanes");
            let s = scale as u32;
            let divs: Option<Vec<Div>> = stages.iter().map(|&w| Div::exact(w as u32, 255 * s * w as u32)).collect();
            let last = stages.last().map_or(1, |&w| w as u32);
            let last_dn = if last * s >= 2 { Div::exact(last * s, 255 * s * last) } else { None };
            if let (Some(divs), Some(last_dn)) = (divs, last_dn) {
                let mut d = [Div { add: 0, m: 0, sh: 0 }; K];
                d[..divs.len()].copy_from_slice(&divs);
                let radius = widths.iter().map(|w| w - 1).sum::<usize>() / 2;
                return BoxPlan { widths, scale, radius, divs: d, last_dn };
            }
            scale = scale.saturating_sub(2);
        }
    }

    fn stages(&self) -> impl Iterator<Item = usize> + '_ {
        self.widths.iter().copied().filter(|&w| w > 1)
    }

    /// Lanes of state one line needs (rings and accumulators).
    fn state_lanes(&self) -> usize {
        self.stages().map(|w| w + 1).sum::<usize>()
    }
}

/// One stage on 64 lanes: `acc += v - slot; slot = v; v = round(acc / d)` ([`Div`]).
#[inline(always)]
fn stage<const LV: u8>(acc: &mut Lane, slot: &mut Lane, v: &mut Lane, div: Div) {
    #[cfg(target_arch = "x86_64")]
    {
        if LV == 2 {
            // SAFETY: LV == 2 only inside functions compiled with AVX-512 F/BW/VL, called after
            // the runtime check.
            return unsafe { simd::stage512(acc, slot, v, div.add, div.m, div.sh) };
        }
        if LV == 1 {
            // SAFETY: as above, AVX2.
            return unsafe { simd::stage256(acc, slot, v, div.add, div.m, div.sh) };
        }
    }
    for l in 0..LANES {
        acc[l] = acc[l].wrapping_add(v[l]).wrapping_sub(slot[l]);
        slot[l] = v[l];
        v[l] = div.apply(acc[l]);
    }
}

/// Position in a line: per stage its ring slot for the current input and whether it is active
/// (has inputs yet) and full (outputs a value). The same for every strip or channel at the same
/// virtual index, so it is advanced once per index.
#[derive(Clone, Copy)]
struct Cursor {
    n: usize,
    w: [usize; K],
    // per stage the division of the window sum
    div: [Div; K],
    lag: [usize; K],
    pos: [usize; K],
    i: usize,
}

impl Cursor {
    fn new(plan: &BoxPlan) -> Cursor {
        let mut c = Cursor { n: 0, w: [1; K], div: plan.divs, lag: [0; K], pos: [0; K], i: 0 };
        let mut lag = 0;
        for w in plan.stages() {
            c.w[c.n] = w;
            c.lag[c.n] = lag;
            lag += w - 1;
            c.n += 1;
        }
        c
    }

    /// The last stage divides by `w * scale` instead of `w`: its output is the 8-bit result
    /// (one rounding instead of a box average and a second rounding to whole DN).
    fn to_dn(mut self, plan: &BoxPlan) -> Cursor {
        self.div[self.n - 1] = plan.last_dn;
        self
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
        stage::<LV>(&mut rest[0], &mut ring[cur.pos[k]], v, cur.div[k]);
        if cur.i - cur.lag[k] + 1 < w {
            return false;
        }
        off += w + 1;
    }
    true
}

/// Vertical cascade of one strip (byte columns `j0..j0 + LANES`) over virtual rows `i0..i1`
/// (relative to the super-band's start `y_start`: virtual row `i` reads source row
/// `mirror(y_start + i - radius)`); outputs (relative row `i - 2 radius`, from `o0` on) go to
/// `blk[row - o0]`. `row_of(k)` gives source row `y_start - radius + k`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn strip_rows<'a, const LV: u8>(
    plan: &BoxPlan,
    row_of: &impl Fn(usize) -> &'a [u8],
    j0: usize,
    cur: &mut Cursor,
    i1: usize,
    o0: usize,
    blk: &mut [Lane],
    state: &mut [Lane],
) {
    let sc = plan.scale;
    let r2 = 2 * plan.radius;
    let mut v = [0u16; LANES];
    while cur.i < i1 {
        // The rows are a page apart: prefetch this strip's bytes a few rows ahead (the hardware
        // prefetchers do not follow such strides). No effect on the values.
        #[cfg(target_arch = "x86_64")]
        if cur.i + 6 < i1 {
            // SAFETY: a prefetch hint of an address inside a row slice (no access is made).
            unsafe {
                use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
                _mm_prefetch::<_MM_HINT_T0>(row_of(cur.i + 6).as_ptr().add(j0) as *const i8);
            }
        }
        let row: &[u8; LANES] = row_of(cur.i)[j0..j0 + LANES].try_into().unwrap();
        for l in 0..LANES {
            v[l] = row[l] as u16 * sc;
        }
        if push_all::<LV>(cur, state, &mut v) {
            blk[cur.i - r2 - o0] = v;
        }
        cur.advance();
    }
}

/// Write byte columns `jb..jb + n` (n <= 8) of `rows` rows from `ring[k][l]` (column `jb + k`,
/// row `l`, values <= 255) into `band` (rows of `stride` bytes).
#[inline(always)]
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
fn flush8(lv: u8, ring: &[Lane], band: &mut [u8], stride: usize, rows: usize, jb: usize, n: usize) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if lv > 0 && n == 8 {
        done = rows / 8 * 8;
        if done > 0 {
            assert!(ring.len() >= 8 && band.len() >= (done - 1) * stride + jb + 8);
        }
        for lb in (0..done).step_by(8) {
            // SAFETY: reads ring[0..8][lb..lb + 8] (in bounds), writes 8 bytes at
            // band[(lb + r) * stride + jb..] for r < 8 (asserted above).
            unsafe {
                simd::t8x8_u8(
                    ring.as_ptr().cast::<u16>().add(lb),
                    LANES,
                    band.as_mut_ptr().add(lb * stride + jb),
                    stride,
                )
            };
        }
    }
    for l in done..rows {
        for k in 0..n {
            band[l * stride + jb + k] = ring[k][l] as u8;
        }
    }
}

/// Per-thread scratch of one super-band, in lanes: vertical state of every strip, horizontal
/// state of every channel, a vertical output block, the transposed band, the output ring.
fn slot_lanes(ns: usize, sl: usize, ch: usize, rl8: usize) -> usize {
    ns * sl + ch * sl + LANES + rl8 + 8
}

/// One super-band: output rows `y_start..y_end` (`sb` holds them, `stride` bytes each; `halo`
/// the `radius` source rows above and the `radius` below it, copied before any band was
/// written). Per band of [`LANES`] rows: the vertical cascade of every strip continues (state
/// kept across bands), each 64 x 64 block is transposed into `bt`, the horizontal cascade runs
/// along the band's pixels (all channels in one pass) and every 8 finished byte columns are
/// transposed back into the frame.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn super_band<const LV: u8>(
    plan: &BoxPlan,
    w: usize,
    ch: usize,
    stride: usize,
    y_start: usize,
    y_end: usize,
    sb: &mut [u8],
    halo: &[u8],
    scratch: &mut [Lane],
) {
    let rl = w * ch;
    let ns = rl.div_ceil(LANES);
    let sl = plan.state_lanes();
    let r = plan.radius;
    let r2 = 2 * r;
    let rl8 = rl.div_ceil(8) * 8;
    let (vstate, rest) = scratch.split_at_mut(ns * sl);
    let (hstate, rest) = rest.split_at_mut(ch * sl);
    let (blk, rest) = rest.split_at_mut(LANES);
    let (bt, ring) = rest.split_at_mut(rl8);
    vstate.iter_mut().for_each(|l| *l = [0; LANES]);
    let mut vcur = Cursor::new(plan);
    let mut y0 = y_start;
    while y0 < y_end {
        let rows = LANES.min(y_end - y0);
        // Relative virtual rows of this band: outputs o0..o0 + rows need inputs up to
        // o0 + rows + r2.
        let o0 = y0 - y_start;
        let i1 = o0 + rows + r2;
        {
            let src: &[u8] = sb;
            let row_of = |k: usize| -> &[u8] {
                let yv = y_start + k; // = source row + r
                if yv < y_start + r {
                    &halo[k * rl..(k + 1) * rl]
                } else if yv < y_end + r {
                    let y = yv - r - y_start;
                    &src[y * stride..y * stride + rl]
                } else {
                    let j = r + (yv - r - y_end);
                    &halo[j * rl..(j + 1) * rl]
                }
            };
            let cur0 = vcur;
            for s in 0..ns {
                let j0 = (s * LANES).min(rl - LANES);
                vcur = cur0;
                strip_rows::<LV>(plan, &row_of, j0, &mut vcur, i1, o0, blk, &mut vstate[s * sl..(s + 1) * sl]);
                transpose_in(LV, &blk[..rows], &mut bt[j0..j0 + LANES]);
            }
        }
        // Horizontal cascade, all channels, with the output written 8 columns at a time.
        let band = &mut sb[o0 * stride..];
        hstate.iter_mut().for_each(|l| *l = [0; LANES]);
        let mut cur = Cursor::new(plan).to_dn(plan);
        for i in 0..w + r2 {
            let x = mirror(i as isize - r as isize, w);
            for c in 0..ch {
                let mut v = bt[x * ch + c];
                if push_all::<LV>(&cur, &mut hstate[c * sl..(c + 1) * sl], &mut v) {
                    let j = (i - r2) * ch + c;
                    ring[j % 8] = v;
                    if j % 8 == 7 {
                        flush8(LV, ring, band, stride, rows, j - 7, 8);
                    }
                }
            }
            cur.advance();
        }
        if !rl.is_multiple_of(8) {
            flush8(LV, ring, band, stride, rows, rl / 8 * 8, rl % 8);
        }
        y0 += rows;
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
    pub unsafe fn stage512(acc: &mut Lane, slot: &mut Lane, v: &mut Lane, add: u16, m: u16, sh: u32) {
        let (av, mv, shv) = (_mm512_set1_epi16(add as i16), _mm512_set1_epi16(m as i16), _mm_cvtsi32_si128(sh as i32));
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
                let q = _mm512_mulhi_epu16(_mm512_add_epi16(a, av), mv);
                _mm512_storeu_si512(pv, _mm512_srl_epi16(q, shv));
            }
        }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    pub unsafe fn stage256(acc: &mut Lane, slot: &mut Lane, v: &mut Lane, add: u16, m: u16, sh: u32) {
        let (av, mv, shv) = (_mm256_set1_epi16(add as i16), _mm256_set1_epi16(m as i16), _mm_cvtsi32_si128(sh as i32));
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
                let q = _mm256_mulhi_epu16(_mm256_add_epi16(a, av), mv);
                _mm256_storeu_si256(pv, _mm256_srl_epi16(q, shv));
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
        #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
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

dispatch!(super_band_d, super_band, (plan: &BoxPlan, w: usize, ch: usize, stride: usize, y_start: usize, y_end: usize, sb: &mut [u8], halo: &[u8], scratch: &mut [Lane]));

/// `dst[j][l] = src[l][j]` for `l < src.len()` (<= LANES) and `j < LANES`.
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
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

/// Scratch of [`blur_u8`]; grows only (allocation when the frame size, the widths or the
/// thread count grow).
#[derive(Default)]
pub struct Scratch {
    // allocation: per frame size and thread count: per super-band the source rows it reads but
    // does not own (copied before any is written)
    halo: Vec<u8>,
    // allocation: per frame size, widths and thread count: per super-band the line states, a
    // block, the transposed band and the output ring (see `slot_lanes`)
    slots: Vec<Lane>,
}

/// Separable box-cascade blur of an 8-bit frame (`ch` interleaved channels, rows of `stride`
/// bytes) in place. Needs `w * ch >= LANES`.
pub fn blur_u8(d: &mut [u8], stride: usize, w: usize, h: usize, ch: usize, plan: &BoxPlan, sc: &mut Scratch) {
    // The AVX2 kernels: on the AVX-512 machine measured (Zen 4, whose 512-bit units are two
    // 256-bit halves) they are faster than the AVX-512 ones; the bytes are the same.
    blur_u8_at(cpu_level().min(1), d, stride, w, h, ch, plan, sc)
}

/// [`blur_u8`] with the kernels of level `lv` at most (see [`cpu_level`]; tests compare them).
///
/// The rows are cut into one super-band per thread (whole bands of [`LANES`] rows). Every box
/// average is the exact rounded mean of its window (the running sums are exact), so a
/// super-band that starts its cascades `2 radius` rows early gives the same values as one pass
/// over the whole frame: the bytes do not depend on the thread count.
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
    let rl8 = rl.div_ceil(8) * 8;
    let r = plan.radius;
    let nb = h.div_ceil(LANES);
    // Super-bands of `bps` whole bands, one per thread.
    let bps = nb.max(1).div_ceil(rayon::current_num_threads().max(1));
    let nsb = nb.max(1).div_ceil(bps);
    let per = slot_lanes(ns, sl, ch, rl8);
    if sc.slots.len() < nsb * per {
        sc.slots.resize(nsb * per, [0; LANES]);
    }
    let per_halo = (2 * r * rl).max(1);
    if sc.halo.len() < nsb * per_halo {
        sc.halo.resize(nsb * per_halo, 0);
    }
    let bounds = |k: usize| (k * bps * LANES, ((k + 1) * bps * LANES).min(h));
    // The rows each super-band reads but does not own (r above, r below, mirrored at the frame's
    // edges), copied while the frame is still unmodified.
    {
        let src: &[u8] = d;
        sc.halo[..nsb * per_halo].par_chunks_mut(per_halo).enumerate().for_each(|(k, hb)| {
            let (y0, y1) = bounds(k);
            let rows = (y0 as isize - r as isize..y0 as isize).chain(y1 as isize..(y1 + r) as isize);
            for (j, yv) in rows.enumerate() {
                let s = mirror(yv, h);
                hb[j * rl..(j + 1) * rl].copy_from_slice(&src[s * stride..s * stride + rl]);
            }
        });
    }
    let used = d.len().min(stride * h);
    d[..used]
        .par_chunks_mut(stride * LANES * bps)
        .enumerate()
        .zip(sc.halo[..nsb * per_halo].par_chunks(per_halo))
        .zip(sc.slots[..nsb * per].par_chunks_mut(per))
        .for_each(|(((k, sb), hb), slot)| {
            let (y0, y1) = bounds(k);
            super_band_d(lv, plan, w, ch, stride, y0, y1, sb, hb, slot);
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn division_is_exact_rounding() {
        // Every divisor a plan can use, over the whole 16-bit range it allows.
        for d in 2u32..=256 {
            let amax = 65535 - d / 2 - 1;
            let div = Div::exact(d, amax).unwrap_or_else(|| panic!("no exact division by {d}"));
            for a in (0..=amax).step_by(3).chain([amax]) {
                assert_eq!(div.apply(a as u16) as u32, (a + d / 2) / d, "{a} / {d}");
            }
        }
        // Plans for every sigma of the box path keep the scale of the exact reference (the
        // largest odd one that fits), so their bytes are those of an exact rounded division.
        for i in 0..=170 {
            let sigma = 3.0 + 0.1 * i as f64 + 0.01;
            let plan = BoxPlan::for_sigma(sigma);
            let wmax = *plan.widths.iter().max().unwrap();
            let s = ((65535 - wmax / 2) / (255 * wmax)).min(127) as u16;
            assert_eq!(plan.scale, if s.is_multiple_of(2) { s - 1 } else { s }, "sigma {sigma}: {plan:?}");
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
                for jb in (0..rl).step_by(8) {
                    let n = 8.min(rl - jb);
                    flush8(cpu_level(), &ot[jb..jb + n], &mut band, stride, rows, jb, n);
                }
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

    /// The integer cascade written plainly, whole lines at a time: each line mirrored by
    /// `radius`, then per stage the rounded (half up) mean of every full window; samples times
    /// `scale`, and the last stage of the second axis divides by `w * scale` (straight to DN).
    fn plain_integer_cascade(src: &[u8], w: usize, h: usize, ch: usize, plan: &BoxPlan) -> Vec<u8> {
        let r = plan.radius as isize;
        let s = plan.scale as u32;
        let stages: Vec<u32> = plan.widths.iter().filter(|&&w| w > 1).map(|&w| w as u32).collect();
        let line = |vals: &dyn Fn(usize) -> u32, n: usize, to_dn: bool| -> Vec<u32> {
            let mut l: Vec<u32> = (-r..n as isize + r).map(|i| vals(mirror(i, n))).collect();
            for (k, &bw) in stages.iter().enumerate() {
                let d = if to_dn && k + 1 == stages.len() { bw * s } else { bw };
                l = l.windows(bw as usize).map(|win| (win.iter().sum::<u32>() + d / 2) / d).collect();
            }
            l
        };
        let rl = w * ch;
        let mut cols = vec![0u32; rl * h];
        for j in 0..rl {
            let out = line(&|y| src[y * rl + j] as u32 * s, h, false);
            for y in 0..h {
                cols[y * rl + j] = out[y];
            }
        }
        let mut dst = vec![0u8; rl * h];
        for y in 0..h {
            for c in 0..ch {
                let out = line(&|x| cols[y * rl + x * ch + c], w, true);
                for x in 0..w {
                    dst[y * rl + x * ch + c] = out[x] as u8;
                }
            }
        }
        dst
    }

    #[test]
    fn same_bytes_as_the_plain_integer_cascade_on_any_thread_count() {
        for (w, h, format) in [
            (203usize, 131usize, PixelFormat::Rgb8),
            (97, 200, PixelFormat::Mono8),
            (64, 9, PixelFormat::Mono8),
            (70, 330, PixelFormat::Rgb8),
        ] {
            let f = crate::faults::kit::bench_scene(w as u32, h as u32, format, 5).unwrap();
            let ch = format.channels();
            for sigma in [3.2, 9.0, 20.0] {
                let plan = BoxPlan::for_sigma(sigma);
                let want = plain_integer_cascade(f.to_packed().as_u8().unwrap(), w, h, ch, &plan);
                for threads in [1, 2, 3, 5] {
                    for lv in [0, cpu_level().min(1), cpu_level()] {
                        let mut g = f.clone();
                        let stride = g.stride;
                        let FrameData::U8(d) = &mut g.data else { unreachable!() };
                        rayon::ThreadPoolBuilder::new()
                            .num_threads(threads)
                            .build()
                            .unwrap()
                            .install(|| blur_u8_at(lv, d, stride, w, h, ch, &plan, &mut Scratch::default()));
                        let got = g.to_packed();
                        assert!(
                            got.as_u8().unwrap() == want.as_slice(),
                            "{format} {w}x{h} sigma {sigma}, {threads} threads, level {lv}"
                        );
                    }
                }
            }
        }
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
