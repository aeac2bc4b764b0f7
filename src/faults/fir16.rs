//! Symmetric FIR filters on 16-bit fixed-point rows, for the blurs of 8-bit frames (`defocus`).
//!
//! Samples are held as `v * 2^6` in `i16` (Q6: 8-bit values up to 16320, so the sum of two
//! samples fits) and weights as `round(w * 2^15)` (Q15, renormalised to sum exactly 2^15). One
//! output is `sum_k mulhrs(x_-k + x_+k, q_k)` with `mulhrs(a, b) = (a * b + 2^14) >> 15` (the
//! `vpmulhrsw` instruction: each product rounded to nearest), so every path (AVX-512 BW, AVX2,
//! scalar) runs the same integer operations and gives the same bits. Error of one output against
//! the exact weighted sum: at most 1/128 DN per tap pair from the product rounding, plus the
//! weights' rounding (|dw| < 2^-15 each, total weight exactly 1).

/// Fractional bits of a sample (`v * 2^6`).
pub const SAMPLE_Q: u32 = 6;

/// Q15 weights of a symmetric kernel of odd length `2r + 1`: `q[0]` is the centre tap, `q[k]`
/// the taps at ±k. Rounded with the largest-remainder rule so that `q[0] + 2 sum q[k] = 2^15`
/// exactly (the filter keeps the mean); every pair weight is within 2^-15 of the exact one, the
/// centre within 2 * 2^-15.
pub fn q15_half_kernel(k: &[f64]) -> Vec<i16> {
    q15_pairs(&k[k.len() / 2..])
}

/// Q15 weights of a point-symmetric kernel given as `half[0]` (the centre tap) and `half[j]`
/// (the weight of each tap of pair j): rounded as in [`q15_half_kernel`] so that
/// `q[0] + 2 sum q[j] = 2^15` (the exact weights must sum to 1).
pub fn q15_pairs(half: &[f64]) -> Vec<i16> {
    let r = half.len() - 1;
    let total = 32768i64;
    // Units: the centre counts once, every other tap twice (its mirror shares the weight).
    let want: Vec<f64> = half.iter().map(|w| w * total as f64).collect();
    let mut q: Vec<i64> = want.iter().map(|w| w.floor() as i64).collect();
    let mut sum: i64 = q[0] + 2 * q[1..].iter().sum::<i64>();
    // Hand out the remaining units by largest remainder: the centre takes single units, a pair
    // takes two. Order: remainders descending, then index ascending (deterministic).
    let mut order: Vec<usize> = (0..=r).collect();
    order.sort_by(|&a, &b| {
        let (ra, rb) = (want[a] - want[a].floor(), want[b] - want[b].floor());
        rb.partial_cmp(&ra).unwrap_or(std::cmp::Ordering::Equal).then(a.cmp(&b))
    });
    for &j in &order {
        let step = if j == 0 { 1 } else { 2 };
        if sum + step <= total {
            q[j] += 1;
            sum += step;
        }
        if sum == total {
            break;
        }
    }
    // A last odd unit that no pair could take goes to the centre.
    q[0] += total - sum;
    sum = total;
    debug_assert_eq!(sum, total);
    q.into_iter().map(|v| v.clamp(0, i16::MAX as i64) as i16).collect()
}

/// `(a * b + 2^14) >> 15`, the rounding high product of `vpmulhrsw`.
#[inline(always)]
pub fn mulhrs(a: i16, b: i16) -> i16 {
    ((a as i32 * b as i32 + 0x4000) >> 15) as i16
}

/// `out[i] = mulhrs(base[center + i], q[0]) + sum_{k>=1} mulhrs(base[offs[k].0 + i] +
/// base[offs[k].1 + i], q[k])` (wrapping i16 adds; the caller keeps the sums in range).
/// `offs[0]` is not used. Panics if a read would leave `base`.
pub fn sym_fir(out: &mut [i16], base: &[i16], center: usize, offs: &[(usize, usize)], q: &[i16]) {
    let n = out.len();
    assert!(offs.len() == q.len() && !q.is_empty());
    assert!(center + n <= base.len(), "fir: centre row inside the buffer");
    for &(a, b) in &offs[1..] {
        assert!(a + n <= base.len() && b + n <= base.len(), "fir: taps inside the buffer");
    }
    #[cfg(target_arch = "x86_64")]
    {
        if super::kit::has_avx512() {
            // SAFETY: AVX-512 F/BW present (checked); reads are in bounds (asserted above).
            let done = unsafe { simd::fir_avx512(out, base, center, offs, q) };
            return fir_scalar(&mut out[done..], base, center + done, offs, q, done);
        }
        if super::kit::has_avx2() {
            // SAFETY: AVX2 present (checked); reads are in bounds (asserted above).
            let done = unsafe { simd::fir_avx2(out, base, center, offs, q) };
            return fir_scalar(&mut out[done..], base, center + done, offs, q, done);
        }
    }
    fir_scalar(out, base, center, offs, q, 0)
}

/// Two outputs of the same filter on consecutive centre rows, sharing the loads: `rows[t]` is
/// the offset in `base` of row `t - r` relative to the first centre (`t = 0..2r + 2`, `r + 1 =
/// q.len()`), `out0` is [`sym_fir`] centred on `rows[r]`, `out1` centred on `rows[r + 1]`. The
/// same integer operations in the same order as [`sym_fir`], so the same values; each row is
/// loaded once for both outputs (half the loads of two [`sym_fir`] calls).
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
pub fn sym_fir2(out0: &mut [i16], out1: &mut [i16], base: &[i16], rows: &[usize], q: &[i16]) {
    let n = out0.len();
    let r = q.len() - 1;
    assert!(out1.len() == n && rows.len() == 2 * r + 2 && !q.is_empty() && r <= super::defocus::MAX_R);
    for &o in rows {
        assert!(o + n <= base.len(), "fir: rows inside the buffer");
    }
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx2() {
        // SAFETY: AVX2 present (checked); reads are in bounds (asserted above).
        done = unsafe { simd::fir2_avx2(out0, out1, base, rows, q) };
    }
    if done < n {
        // The tail (fewer than 32 outputs) in scalar code; its tap offsets only built then.
        let offs = |c: usize| -> [(usize, usize); 2 * (super::defocus::MAX_R + 1)] {
            std::array::from_fn(|k| if k <= r && k > 0 { (rows[c - k], rows[c + k]) } else { (0, 0) })
        };
        let (o0, o1) = (offs(r), offs(r + 1));
        fir_scalar(&mut out0[done..], base, rows[r] + done, &o0[..=r], q, done);
        fir_scalar(&mut out1[done..], base, rows[r + 1] + done, &o1[..=r], q, done);
    }
}

/// [`sym_fir`] followed by [`q6_to_u8`] in one pass: `out[i]` = the filter's Q6 sum rounded to
/// a byte (round half up, clamped to 0..=255), converted in registers instead of through a Q6
/// row (the same integer operations, so the same bytes as the two calls). Panics if a read
/// would leave `base`.
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
pub fn sym_fir_u8(out: &mut [u8], base: &[i16], center: usize, offs: &[(usize, usize)], q: &[i16]) {
    let n = out.len();
    assert!(offs.len() == q.len() && !q.is_empty());
    assert!(center + n <= base.len(), "fir: centre row inside the buffer");
    for &(a, b) in &offs[1..] {
        assert!(a + n <= base.len() && b + n <= base.len(), "fir: taps inside the buffer");
    }
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if super::kit::has_avx512() {
            // SAFETY: AVX-512 F/BW present (checked); reads are in bounds (asserted above).
            done = unsafe { simd::fir_u8_avx512(out, base, center, offs, q) };
        } else if super::kit::has_avx2() {
            // SAFETY: AVX2 present (checked); reads are in bounds (asserted above).
            done = unsafe { simd::fir_u8_avx2(out, base, center, offs, q) };
        }
    }
    // The tail (fewer than one chunk) through a Q6 buffer on the stack.
    let mut acc = [0i16; 128];
    for (k, o) in out[done..].chunks_mut(128).enumerate() {
        let skip = done + k * 128;
        let a = &mut acc[..o.len()];
        fir_scalar(a, base, center + skip, offs, q, skip);
        for (o, &a) in o.iter_mut().zip(a.iter()) {
            *o = ((a.max(0) as i32 + 32) >> SAMPLE_Q).min(255) as u8;
        }
    }
}

/// One column of point-symmetric tap pairs for [`sym_fir_cols_u8`]: the taps at `(dx, dy)` and
/// `(-dx, -dy)` for `dy` in `dy0..=dy1`, `dx >= 0` (for `dx = 0`, `dy0 >= 1`), with the Q15
/// weights `wq[w0..=w0 + dy1 - dy0]` (0 for a gap: `mulhrs(_, 0) = 0`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TapCol {
    /// `dx` (pixels, `>= 0`).
    pub dx: usize,
    pub dy0: i32,
    pub dy1: i32,
    pub w0: usize,
}

impl TapCol {
    /// Pairs in the column.
    pub fn len(&self) -> usize {
        (self.dy1 - self.dy0) as usize + 1
    }

    /// Whether the column has no pairs (never: `dy0 <= dy1`).
    pub fn is_empty(&self) -> bool {
        self.dy1 < self.dy0
    }
}

/// Most output rows [`sym_fir_cols_u8`] processes together.
pub const MAX_COL_ROWS: usize = 8;

/// Output rows [`sym_fir_cols_u8`] should get per call on this CPU: 8 on AVX-512 (32 zmm
/// registers hold the 8 sums, the weights and a column's source vectors, so each source vector
/// and weight serves twice the rows), 4 on AVX2 (16 ymm registers: 8 rows spill) and without SIMD.
/// Measured on the Zen 4, rgb8 24 px at 30 deg: AVX-512 4 rows 5.7 ms, 8 rows 5.0 ms; AVX2 4 rows
/// 6.2 ms, 8 rows 7.9 ms.
pub fn col_rows() -> usize {
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx512() {
        return 8;
    }
    4
}

/// Longest [`TapCol`] [`sym_fir_cols_u8`] takes as a strided run (two offsets, fully unrolled
/// code); longer columns take one offset per source row and a loop that rotates the source
/// vectors through registers (two loads per pair for all `R` rows).
pub const MAX_COL_PAIRS: usize = 4;

/// Source rows a column of `k` pairs reads per side for `rows` output rows (one run of
/// consecutive rows, see [`sym_fir_cols_u8`]).
pub fn col_run(k: usize, rows: usize) -> usize {
    k + rows - 1
}

/// Offsets [`sym_fir_cols_u8`] takes for a column of `k` pairs and `rows` output rows: 2 (the
/// first rows of its two runs) up to [`MAX_COL_PAIRS`] pairs, else one per source row,
/// `2 col_run(k, rows)`.
pub fn col_offs(k: usize, rows: usize) -> usize {
    if k <= MAX_COL_PAIRS { 2 } else { 2 * col_run(k, rows) }
}

/// A 2D point-symmetric FIR ([`sym_fir`]'s sums: the centre `mulhrs(x, q0)` plus, per tap pair,
/// `mulhrs(x_lo + x_hi, w)`, wrapping 16-bit adds, rounded to bytes as [`q6_to_u8`]) for
/// `R = outs.len()` (4 or 8, see [`col_rows`]) consecutive output rows `y + j` at once, the tap
/// pairs grouped by columns ([`TapCol`]): within a column the source rows of `dy` and `dy + 1`
/// serve neighbouring output rows, so each source vector is loaded once for all of them (a
/// column of `k` pairs costs `2 (k + R - 1)` loads instead of `2 k R`). `centre[j]` is the
/// offset in `base` of output row `j`'s centre sample 0. A column of `k` pairs reads the runs of
/// [`col_run`]`(k, R)` source rows `lo[m]` (sample 0 of row `y - dy1 + m`, shifted by `-dx`
/// pixels) and `hi[m]` (row `y + dy0 + m`, shifted by `+dx`): pair `dy0 + s` of output row `j`
/// is `lo[k - 1 + j - s] + hi[j + s]`. Per column, in order, `offs` holds [`col_offs`]`(k, R)`
/// offsets: for `k <= MAX_COL_PAIRS` `lo[0]` and `hi[0]`, the runs' rows `stride` samples
/// apart (the caller keeps each run contiguous); for longer columns every `lo[m]`, then every
/// `hi[m]`. The same integer values as [`sym_fir`] and [`q6_to_u8`] per row (every pair's sum
/// and product is the same; the sums of the products are wrapping, so their order does not
/// matter). Panics if a read would leave `base`. The bytes of the (at most `R`) rows in
/// `prefetch` are only prefetched into the cache, spread over the call (the caller's next
/// rows: their loads then overlap this call's arithmetic instead of stalling the next fill).
#[allow(clippy::too_many_arguments)]
pub fn sym_fir_cols_u8(
    outs: &mut [&mut [u8]],
    base: &[i16],
    stride: usize,
    centre: &[usize],
    cols: &[TapCol],
    offs: &[usize],
    q0: i16,
    wq: &[i16],
    prefetch: &[&[u8]],
) {
    let rows = outs.len();
    assert!(rows == 4 || rows == 8, "fir: 4 or 8 output rows");
    assert!(prefetch.len() <= rows);
    assert_eq!(centre.len(), rows);
    let n = outs[0].len();
    assert!(outs.iter().all(|o| o.len() == n));
    assert!(centre.iter().all(|&o| o + n <= base.len()), "fir: rows inside the buffer");
    assert_eq!(offs.len(), cols.iter().map(|c| col_offs(c.len(), rows)).sum::<usize>());
    let mut p = 0;
    for c in cols {
        assert!(c.dy0 <= c.dy1 && c.w0 + c.len() <= wq.len());
        let m = col_offs(c.len(), rows);
        let o = &offs[p..p + m];
        let last = if m == 2 { (col_run(c.len(), rows) - 1) * stride + n } else { n };
        assert!(o.iter().all(|&o| o + last <= base.len()), "fir: rows inside the buffer");
        p += m;
    }
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if super::kit::has_avx512() {
            // SAFETY: AVX-512 F/BW present (checked); reads are in bounds, `offs` holds
            // col_offs(k, rows) offsets per column and every column's weights lie inside `wq`
            // (asserted above).
            done = unsafe {
                if rows == 8 {
                    simd::cols_avx512::<8>(outs, base, stride, centre, cols, offs, q0, wq, prefetch)
                } else {
                    simd::cols_avx512::<4>(outs, base, stride, centre, cols, offs, q0, wq, prefetch)
                }
            };
        } else if super::kit::has_avx2() {
            // SAFETY: AVX2 present (checked); as above.
            done = unsafe {
                if rows == 8 {
                    simd::cols_avx2::<8>(outs, base, stride, centre, cols, offs, q0, wq, prefetch)
                } else {
                    simd::cols_avx2::<4>(outs, base, stride, centre, cols, offs, q0, wq, prefetch)
                }
            };
        }
    }
    fir_cols_scalar(outs, base, stride, centre, cols, offs, q0, wq, done);
}

/// Scalar reference of [`sym_fir_cols_u8`] (outputs from `skip` on).
#[allow(clippy::too_many_arguments)]
fn fir_cols_scalar(
    outs: &mut [&mut [u8]],
    base: &[i16],
    stride: usize,
    centre: &[usize],
    cols: &[TapCol],
    offs: &[usize],
    q0: i16,
    wq: &[i16],
    skip: usize,
) {
    let rows = outs.len();
    for (j, out) in outs.iter_mut().enumerate() {
        for (i, o) in out[skip..].iter_mut().enumerate() {
            let x = skip + i;
            let mut acc = mulhrs(base[centre[j] + x], q0);
            let mut p = 0;
            for c in cols {
                let (k, m) = (c.len(), col_offs(c.len(), rows));
                let o = &offs[p..p + m];
                // Row t of the column's lo and hi runs.
                let lo = |t: usize| if m == 2 { o[0] + t * stride } else { o[t] };
                let hi = |t: usize| if m == 2 { o[1] + t * stride } else { o[m / 2 + t] };
                for s in 0..k {
                    let v = base[lo(k - 1 + j - s) + x].wrapping_add(base[hi(j + s) + x]);
                    acc = acc.wrapping_add(mulhrs(v, wq[c.w0 + s]));
                }
                p += m;
            }
            *o = ((acc.max(0) as i32 + 32) >> SAMPLE_Q).min(255) as u8;
        }
    }
}

/// Source rows [`sym_fir_cols4_u8`] reads per side for a column of `k` pairs: `k + 3`.
pub fn col_loads4(k: usize) -> usize {
    k + 3
}

/// [`sym_fir_cols_u8`] for 4 output rows with one offset per source row in main's (stop 41)
/// layout, for the 4-row (AVX2) kernel when most pairs lie in columns longer than
/// [`MAX_COL_PAIRS`] (steep streaks): every column rotates its source vectors through
/// registers, with no per-call or per-column set-up beyond main's (`sym_fir_cols_u8` on such
/// streaks ran 7-10 % slower on the AVX2 kernels at 60-80 deg, mono8, for reasons not found;
/// this is stop 41's kernel unchanged). Per column, in order, `offs` holds
/// [`col_loads4`]`(k)` offsets `lo[m]` (sample 0 of source row `y + 3 - dy0 - m`, shifted by
/// `-dx` pixels) and as many `hi[m]` (row `y + dy0 + m`, shifted by `+dx`): pair `dy0 + s` of
/// output row `j` is `lo[3 - j + s] + hi[j + s]`. The same bytes as [`sym_fir_cols_u8`].
/// Panics if a read would leave `base`.
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
pub fn sym_fir_cols4_u8(
    outs: [&mut [u8]; 4],
    base: &[i16],
    centre: [usize; 4],
    cols: &[TapCol],
    offs: &[usize],
    q0: i16,
    wq: &[i16],
) {
    let n = outs[0].len();
    assert!(outs.iter().all(|o| o.len() == n));
    assert!(centre.iter().chain(offs).all(|&o| o + n <= base.len()), "fir: rows inside the buffer");
    assert_eq!(offs.len(), cols.iter().map(|c| 2 * col_loads4(c.len())).sum::<usize>());
    assert!(cols.iter().all(|c| c.dy0 <= c.dy1 && c.w0 + c.len() <= wq.len()));
    let [o0, o1, o2, o3] = outs;
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx2() {
        // SAFETY: AVX2 present (checked); reads are in bounds (asserted above).
        done =
            unsafe { simd::fir_cols4_avx2([&mut *o0, &mut *o1, &mut *o2, &mut *o3], base, centre, cols, offs, q0, wq) };
    }
    let outs = [&mut o0[done..], &mut o1[done..], &mut o2[done..], &mut o3[done..]];
    fir_cols4_scalar(outs, base, centre, cols, offs, q0, wq, done);
}

/// Scalar reference of [`sym_fir_cols4_u8`] (outputs from `skip` on).
#[allow(clippy::too_many_arguments)]
fn fir_cols4_scalar(
    outs: [&mut [u8]; 4],
    base: &[i16],
    centre: [usize; 4],
    cols: &[TapCol],
    offs: &[usize],
    q0: i16,
    wq: &[i16],
    skip: usize,
) {
    for (j, out) in outs.into_iter().enumerate() {
        for (i, o) in out.iter_mut().enumerate() {
            let x = skip + i;
            let mut acc = mulhrs(base[centre[j] + x], q0);
            let mut p = 0;
            for c in cols {
                let m = col_loads4(c.len());
                let (lo, hi) = (&offs[p..p + m], &offs[p + m..p + 2 * m]);
                for s in 0..c.len() {
                    let v = base[lo[3 - j + s] + x].wrapping_add(base[hi[j + s] + x]);
                    acc = acc.wrapping_add(mulhrs(v, wq[c.w0 + s]));
                }
                p += 2 * m;
            }
            *o = ((acc.max(0) as i32 + 32) >> SAMPLE_Q).min(255) as u8;
        }
    }
}

/// Scalar reference of [`sym_fir`] (outputs from `skip` on: tap offsets are shifted by it).
fn fir_scalar(out: &mut [i16], base: &[i16], center: usize, offs: &[(usize, usize)], q: &[i16], skip: usize) {
    for (i, o) in out.iter_mut().enumerate() {
        let mut acc = mulhrs(base[center + i], q[0]);
        for k in 1..q.len() {
            let (a, b) = (offs[k].0 + skip + i, offs[k].1 + skip + i);
            acc = acc.wrapping_add(mulhrs(base[a].wrapping_add(base[b]), q[k]));
        }
        *o = acc;
    }
}

/// `out[i] = clamp(round(acc[i] / 2^6), 0, 255)` (round half up).
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
pub fn q6_to_u8(out: &mut [u8], acc: &[i16]) {
    let n = out.len().min(acc.len());
    let (out, acc) = (&mut out[..n], &acc[..n]);
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx2() {
        // SAFETY: AVX2 present (checked); both slices hold n values.
        done = unsafe { simd::q6_to_u8_avx2(out, acc) };
    }
    for (o, &a) in out[done..].iter_mut().zip(&acc[done..]) {
        *o = ((a.max(0) as i32 + 32) >> SAMPLE_Q).min(255) as u8;
    }
}

/// `out[i] = src[i] << 6` (8-bit samples to Q6), the first `min(len)` values.
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
pub fn u8_to_q6(out: &mut [i16], src: &[u8]) {
    let n = out.len().min(src.len());
    let (out, src) = (&mut out[..n], &src[..n]);
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx2() {
        // SAFETY: AVX2 present (checked); both slices hold n values.
        done = unsafe { simd::u8_to_q6_avx2(out, src) };
    }
    for (p, &v) in out[done..].iter_mut().zip(&src[done..]) {
        *p = (v as i16) << SAMPLE_Q;
    }
}

#[cfg(target_arch = "x86_64")]
mod simd {
    use super::mulhrs;
    use std::arch::x86_64::*;

    /// The point-symmetric FIR's Q6 sums of 64 outputs from `c` (`bp + c`, pairs at `offs[k] + i`,
    /// centre weight `q[0]`): one `vpmulhrsw` per tap pair and register, wrapping 16-bit adds.
    /// Shared by [`fir_avx2`] (stores the sums) and [`fir_u8_avx2`] (rounds them to bytes).
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn sums64_avx2(bp: *const i16, c: usize, offs: &[(usize, usize)], q: &[i16], i: usize) -> [__m256i; 4] {
        // SAFETY (block): the caller's bounds: c + 64 and offs[k] + i + 64 lie within the base.
        unsafe {
            let ld = |p: usize| _mm256_loadu_si256(bp.add(p) as *const __m256i);
            let q0 = _mm256_set1_epi16(q[0]);
            let mut a = [0, 16, 32, 48].map(|o| _mm256_mulhrs_epi16(ld(c + o), q0));
            for k in 1..q.len() {
                let qk = _mm256_set1_epi16(q[k]);
                let (lo, hi) = (offs[k].0 + i, offs[k].1 + i);
                for (j, aj) in a.iter_mut().enumerate() {
                    let o = 16 * j;
                    *aj = _mm256_add_epi16(*aj, _mm256_mulhrs_epi16(_mm256_add_epi16(ld(lo + o), ld(hi + o)), qk));
                }
            }
            a
        }
    }

    /// [`sums64_avx2`] in four zmm registers: the sums of 128 outputs, for [`fir_avx512`] and
    /// [`fir_u8_avx512`].
    #[target_feature(enable = "avx512f,avx512bw")]
    #[inline]
    unsafe fn sums128_avx512(bp: *const i16, c: usize, offs: &[(usize, usize)], q: &[i16], i: usize) -> [__m512i; 4] {
        // SAFETY (block): the caller's bounds: c + 128 and offs[k] + i + 128 lie within the base.
        unsafe {
            let ld = |p: usize| _mm512_loadu_si512(bp.add(p) as *const __m512i);
            let q0 = _mm512_set1_epi16(q[0]);
            let mut a = [0, 32, 64, 96].map(|o| _mm512_mulhrs_epi16(ld(c + o), q0));
            for k in 1..q.len() {
                let qk = _mm512_set1_epi16(q[k]);
                let (lo, hi) = (offs[k].0 + i, offs[k].1 + i);
                for (j, aj) in a.iter_mut().enumerate() {
                    let o = 32 * j;
                    *aj = _mm512_add_epi16(*aj, _mm512_mulhrs_epi16(_mm512_add_epi16(ld(lo + o), ld(hi + o)), qk));
                }
            }
            a
        }
    }

    /// Whole chunks of 64 outputs; returns how many outputs were written.
    #[target_feature(enable = "avx2")]
    pub unsafe fn fir_avx2(out: &mut [i16], base: &[i16], center: usize, offs: &[(usize, usize)], q: &[i16]) -> usize {
        let n = out.len() / 64 * 64;
        let bp = base.as_ptr();
        let mut i = 0;
        while i < n {
            // SAFETY (block): offsets + i + 64 <= offsets + n <= base.len() (checked by the caller).
            unsafe {
                let [a0, a1, a2, a3] = sums64_avx2(bp, center + i, offs, q, i);
                let op = out.as_mut_ptr().add(i) as *mut __m256i;
                _mm256_storeu_si256(op, a0);
                _mm256_storeu_si256(op.add(1), a1);
                _mm256_storeu_si256(op.add(2), a2);
                _mm256_storeu_si256(op.add(3), a3);
            }
            i += 64;
        }
        let _ = mulhrs;
        n
    }

    /// [`super::q6_to_u8`] on whole chunks of 32 values (`out.len() == acc.len()`): `(a + 32) >> 6`
    /// with a saturating add, then `vpackuswb` clamps to 0..=255, which equals the scalar form
    /// for every i16 (a saturated sum is >= 32735, far above 255 * 64). Returns the count done.
    #[target_feature(enable = "avx2")]
    pub unsafe fn q6_to_u8_avx2(out: &mut [u8], acc: &[i16]) -> usize {
        let n = out.len().min(acc.len()) / 32 * 32;
        let half = _mm256_set1_epi16(32);
        let mut i = 0;
        while i < n {
            // SAFETY (block): i + 32 <= n <= both lengths.
            unsafe {
                let a = _mm256_loadu_si256(acc.as_ptr().add(i) as *const __m256i);
                let b = _mm256_loadu_si256(acc.as_ptr().add(i + 16) as *const __m256i);
                let a = _mm256_srai_epi16::<6>(_mm256_adds_epi16(a, half));
                let b = _mm256_srai_epi16::<6>(_mm256_adds_epi16(b, half));
                let p = _mm256_permute4x64_epi64::<0xD8>(_mm256_packus_epi16(a, b));
                _mm256_storeu_si256(out.as_mut_ptr().add(i) as *mut __m256i, p);
            }
            i += 32;
        }
        n
    }

    /// [`super::u8_to_q6`] on whole chunks of 16 values; returns the count done.
    #[target_feature(enable = "avx2")]
    pub unsafe fn u8_to_q6_avx2(out: &mut [i16], src: &[u8]) -> usize {
        let n = out.len().min(src.len()) / 16 * 16;
        let mut i = 0;
        while i < n {
            // SAFETY (block): i + 16 <= n <= both lengths.
            unsafe {
                let v = _mm256_cvtepu8_epi16(_mm_loadu_si128(src.as_ptr().add(i) as *const __m128i));
                _mm256_storeu_si256(out.as_mut_ptr().add(i) as *mut __m256i, _mm256_slli_epi16::<6>(v));
            }
            i += 16;
        }
        n
    }

    /// [`super::sym_fir2`] on whole chunks of 32 outputs; returns how many were written. The
    /// row addresses and the broadcast weights are set up once per call, and the tap loop is
    /// unrolled by two so the rows loaded for one tap serve the next without register copies
    /// (the loop was bound by its scalar bookkeeping: index loads, bounds checks, moves).
    #[target_feature(enable = "avx2")]
    pub unsafe fn fir2_avx2(out0: &mut [i16], out1: &mut [i16], base: &[i16], rows: &[usize], q: &[i16]) -> usize {
        let n = out0.len() / 32 * 32;
        let r = q.len() - 1;
        if n == 0 {
            return 0;
        }
        const M: usize = super::super::defocus::MAX_R;
        assert!(r <= M && rows.len() == 2 * r + 2 && out1.len() >= n);
        let bp = base.as_ptr();
        // Row t's first sample (offsets inside `base`, checked by the caller).
        let mut rp = [bp; 2 * M + 2];
        for (p, &o) in rp.iter_mut().zip(rows) {
            // SAFETY: o + n <= base.len() (checked by the caller).
            *p = unsafe { bp.add(o) };
        }
        let mut qv = [_mm256_setzero_si256(); M + 1];
        for (v, &w) in qv.iter_mut().zip(q) {
            *v = _mm256_set1_epi16(w);
        }
        let mut i = 0;
        while i < n {
            // SAFETY (block): t < 2r + 2 = rows.len() and k <= r index rp and qv in bounds;
            // rows[t] + i + 32 <= rows[t] + n <= base.len() (checked by the caller); out0 and
            // out1 hold n >= i + 32 values.
            unsafe {
                let ld = |t: usize, o: usize| _mm256_loadu_si256(rp.get_unchecked(t).add(i + o) as *const __m256i);
                let q0 = *qv.get_unchecked(0);
                let (x0a, x0b) = (ld(r, 0), ld(r, 16));
                let (x1a, x1b) = (ld(r + 1, 0), ld(r + 1, 16));
                let mut a0a = _mm256_mulhrs_epi16(x0a, q0);
                let mut a0b = _mm256_mulhrs_epi16(x0b, q0);
                let mut a1a = _mm256_mulhrs_epi16(x1a, q0);
                let mut a1b = _mm256_mulhrs_epi16(x1b, q0);
                // Tap pair k: out0 += (row r - k) + (row r + k), out1 += (row r + 1 - k) + (row
                // r + 1 + k); `p*` hold the rows r + 1 - k (low) and r + k (high) of the step
                // before, `n*` the rows loaded in this step.
                macro_rules! step {
                    ($k:expr, $pla:ident, $plb:ident, $pha:ident, $phb:ident, $nla:ident, $nlb:ident, $nha:ident, $nhb:ident) => {
                        let qk = *qv.get_unchecked($k);
                        $nla = ld(r - $k, 0);
                        $nlb = ld(r - $k, 16);
                        $nha = ld(r + 1 + $k, 0);
                        $nhb = ld(r + 1 + $k, 16);
                        a0a = _mm256_add_epi16(a0a, _mm256_mulhrs_epi16(_mm256_add_epi16($nla, $pha), qk));
                        a0b = _mm256_add_epi16(a0b, _mm256_mulhrs_epi16(_mm256_add_epi16($nlb, $phb), qk));
                        a1a = _mm256_add_epi16(a1a, _mm256_mulhrs_epi16(_mm256_add_epi16($pla, $nha), qk));
                        a1b = _mm256_add_epi16(a1b, _mm256_mulhrs_epi16(_mm256_add_epi16($plb, $nhb), qk));
                    };
                }
                let (mut pla, mut plb, mut pha, mut phb) = (x0a, x0b, x1a, x1b);
                let (mut la, mut lb, mut ha, mut hb);
                let mut k = 1;
                while k < r {
                    step!(k, pla, plb, pha, phb, la, lb, ha, hb);
                    step!(k + 1, la, lb, ha, hb, pla, plb, pha, phb);
                    k += 2;
                }
                if k == r {
                    step!(k, pla, plb, pha, phb, la, lb, ha, hb);
                    let _ = (la, lb, ha, hb);
                }
                let p0 = out0.as_mut_ptr().add(i) as *mut __m256i;
                let p1 = out1.as_mut_ptr().add(i) as *mut __m256i;
                _mm256_storeu_si256(p0, a0a);
                _mm256_storeu_si256(p0.add(1), a0b);
                _mm256_storeu_si256(p1, a1a);
                _mm256_storeu_si256(p1.add(1), a1b);
            }
            i += 32;
        }
        n
    }

    /// [`super::sym_fir_u8`] on whole chunks of 64 outputs: [`fir_avx2`]'s sums, then
    /// [`q6_to_u8_avx2`]'s conversion in registers. Returns how many outputs were written.
    #[target_feature(enable = "avx2")]
    pub unsafe fn fir_u8_avx2(
        out: &mut [u8],
        base: &[i16],
        center: usize,
        offs: &[(usize, usize)],
        q: &[i16],
    ) -> usize {
        let n = out.len() / 64 * 64;
        let bp = base.as_ptr();
        let half = _mm256_set1_epi16(32);
        let mut i = 0;
        while i < n {
            // SAFETY (block): offsets + i + 64 <= offsets + n <= base.len() (checked by the
            // caller); out holds n >= i + 64 bytes.
            unsafe {
                let [a0, a1, a2, a3] = sums64_avx2(bp, center + i, offs, q, i);
                let cv = |a: __m256i| _mm256_srai_epi16::<6>(_mm256_adds_epi16(a, half));
                let p0 = _mm256_permute4x64_epi64::<0xD8>(_mm256_packus_epi16(cv(a0), cv(a1)));
                let p1 = _mm256_permute4x64_epi64::<0xD8>(_mm256_packus_epi16(cv(a2), cv(a3)));
                let op = out.as_mut_ptr().add(i) as *mut __m256i;
                _mm256_storeu_si256(op, p0);
                _mm256_storeu_si256(op.add(1), p1);
            }
            i += 64;
        }
        n
    }

    /// [`super::sym_fir_u8`] on whole chunks of 128 outputs: [`fir_avx512`]'s sums, then the
    /// byte conversion in registers (`(a + 32) >> 6` with a saturating add, negatives to 0,
    /// then an unsigned saturating narrow: [`super::q6_to_u8`]'s values). Returns the count.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub unsafe fn fir_u8_avx512(
        out: &mut [u8],
        base: &[i16],
        center: usize,
        offs: &[(usize, usize)],
        q: &[i16],
    ) -> usize {
        let n = out.len() / 128 * 128;
        let bp = base.as_ptr();
        let half = _mm512_set1_epi16(32);
        let zero = _mm512_setzero_si512();
        let mut i = 0;
        while i < n {
            // SAFETY (block): offsets + i + 128 <= offsets + n <= base.len() (checked by the
            // caller); out holds n >= i + 128 bytes.
            unsafe {
                let [a0, a1, a2, a3] = sums128_avx512(bp, center + i, offs, q, i);
                let cv = |a: __m512i| {
                    _mm512_cvtusepi16_epi8(_mm512_max_epi16(_mm512_srai_epi16::<6>(_mm512_adds_epi16(a, half)), zero))
                };
                let op = out.as_mut_ptr().add(i) as *mut __m256i;
                _mm256_storeu_si256(op, cv(a0));
                _mm256_storeu_si256(op.add(1), cv(a1));
                _mm256_storeu_si256(op.add(2), cv(a2));
                _mm256_storeu_si256(op.add(3), cv(a3));
            }
            i += 128;
        }
        n
    }

    /// [`super::sym_fir_cols4_u8`] on whole chunks of 16 outputs per row (one register per
    /// output row; a column's source vectors rotate through registers); returns the count.
    #[target_feature(enable = "avx2")]
    pub unsafe fn fir_cols4_avx2(
        mut outs: [&mut [u8]; 4],
        base: &[i16],
        centre: [usize; 4],
        cols: &[super::TapCol],
        offs: &[usize],
        q0: i16,
        wq: &[i16],
    ) -> usize {
        let n = outs[0].len() / 16 * 16;
        let bp = base.as_ptr();
        let q0v = _mm256_set1_epi16(q0);
        let half = _mm256_set1_epi16(32);
        let mut i = 0;
        while i < n {
            // SAFETY (block): every offset in `centre` and `offs` plus i + 16 is at most
            // base.len() and every weight index is inside `wq` (asserted by the caller); each
            // output holds n >= i + 16 bytes.
            unsafe {
                let ld = |p: usize| _mm256_loadu_si256(bp.add(p + i) as *const __m256i);
                let mut a0 = _mm256_mulhrs_epi16(ld(centre[0]), q0v);
                let mut a1 = _mm256_mulhrs_epi16(ld(centre[1]), q0v);
                let mut a2 = _mm256_mulhrs_epi16(ld(centre[2]), q0v);
                let mut a3 = _mm256_mulhrs_epi16(ld(centre[3]), q0v);
                let mut p = offs.as_ptr();
                for c in cols {
                    let k = c.len();
                    let m = super::col_loads4(k);
                    let (lo, hi) = (p, p.add(m));
                    let (mut l3, mut l2, mut l1, mut l0) = (ld(*lo), ld(*lo.add(1)), ld(*lo.add(2)), ld(*lo.add(3)));
                    let (mut h0, mut h1, mut h2, mut h3) = (ld(*hi), ld(*hi.add(1)), ld(*hi.add(2)), ld(*hi.add(3)));
                    let w = wq.as_ptr().add(c.w0);
                    let mut s = 0;
                    loop {
                        let wv = _mm256_set1_epi16(*w.add(s));
                        a0 = _mm256_add_epi16(a0, _mm256_mulhrs_epi16(_mm256_add_epi16(l0, h0), wv));
                        a1 = _mm256_add_epi16(a1, _mm256_mulhrs_epi16(_mm256_add_epi16(l1, h1), wv));
                        a2 = _mm256_add_epi16(a2, _mm256_mulhrs_epi16(_mm256_add_epi16(l2, h2), wv));
                        a3 = _mm256_add_epi16(a3, _mm256_mulhrs_epi16(_mm256_add_epi16(l3, h3), wv));
                        s += 1;
                        if s == k {
                            break;
                        }
                        (l3, l2, l1, l0) = (l2, l1, l0, ld(*lo.add(3 + s)));
                        (h0, h1, h2, h3) = (h1, h2, h3, ld(*hi.add(3 + s)));
                    }
                    p = p.add(2 * m);
                }
                for (o, a) in outs.iter_mut().zip([a0, a1, a2, a3]) {
                    let v = _mm256_srai_epi16::<6>(_mm256_adds_epi16(a, half));
                    let v = _mm256_permute4x64_epi64::<0xD8>(_mm256_packus_epi16(v, v));
                    _mm_storeu_si128(o.as_mut_ptr().add(i) as *mut __m128i, _mm256_castsi256_si128(v));
                }
            }
            i += 16;
        }
        n
    }

    /// One column of `$k` tap pairs for `R` output rows (see [`super::sym_fir_cols_u8`]):
    /// `a[j] += mulhrs(lo[(k - 1 + j - s) stride] + hi[(j + s) stride], w[s])` for `s < $k`,
    /// fully unrolled; each source vector is loaded once (repeated loads of one address merge)
    /// and each weight is a register broadcast once per call.
    macro_rules! col_block {
        ($k:literal, $a:ident, $ld:ident, $lo:expr, $hi:expr, $st:expr, $w:expr, $add:ident, $mul:ident, $bc:ident) => {{
            let (lo, hi, st, w) = ($lo, $hi, $st, $w);
            for s in 0..$k {
                let wv = $bc(w.add(s));
                for j in 0..R {
                    let v = $add($ld(lo + ($k - 1 + j - s) * st), $ld(hi + (j + s) * st));
                    $a[j] = $add($a[j], $mul(v, wv));
                }
            }
        }};
    }

    /// One column of `k > MAX_COL_PAIRS` pairs for `R` output rows from per-row offsets (`lo`,
    /// `hi`: [`super::col_run`]`(k, R)` each): the `R` source vectors of each side rotate through
    /// registers, one new load per side and pair.
    macro_rules! col_rot {
        ($a:ident, $ld:ident, $lo:expr, $hi:expr, $k:expr, $w:expr, $add:ident, $mul:ident, $bc:ident) => {{
            let (lo_at, hi_at, k, w) = ($lo, $hi, $k, $w);
            let mut l: [_; R] = std::array::from_fn(|j| $ld(lo_at(k - 1 + j)));
            let mut h: [_; R] = std::array::from_fn(|j| $ld(hi_at(j)));
            let mut s = 0;
            loop {
                let wv = $bc(w.add(s));
                for j in 0..R {
                    $a[j] = $add($a[j], $mul($add(l[j], h[j]), wv));
                }
                s += 1;
                if s == k {
                    break;
                }
                let (nl, nh) = ($ld(lo_at(k - 1 - s)), $ld(hi_at(R - 1 + s)));
                l = std::array::from_fn(|j| if j == 0 { nl } else { l[j - 1] });
                h = std::array::from_fn(|j| if j + 1 == R { nh } else { h[j + 1] });
            }
        }};
    }

    /// The sums of one chunk of `R` output rows over every column: up to `MAX_COL_PAIRS` pairs
    /// its unrolled [`col_block`] picked by its length, longer ones [`col_rot`].
    macro_rules! cols_sums {
        ($a:ident, $ld:ident, $cols:expr, $offs:expr, $st:expr, $wv:expr, $add:ident, $mul:ident, $bc:ident) => {{
            let mut p = $offs;
            for c in $cols {
                let w = $wv.add(c.w0);
                let k = c.len();
                if k > super::MAX_COL_PAIRS {
                    let m = super::col_run(k, R);
                    col_rot!($a, $ld, |t: usize| *p.add(t), |t: usize| *p.add(m + t), k, w, $add, $mul, $bc);
                    p = p.add(2 * m);
                    continue;
                }
                let (lo, hi) = (*p, *p.add(1));
                match k {
                    1 => col_block!(1, $a, $ld, lo, hi, $st, w, $add, $mul, $bc),
                    2 => col_block!(2, $a, $ld, lo, hi, $st, w, $add, $mul, $bc),
                    3 => col_block!(3, $a, $ld, lo, hi, $st, w, $add, $mul, $bc),
                    _ => col_block!(4, $a, $ld, lo, hi, $st, w, $add, $mul, $bc),
                }
                p = p.add(2);
            }
        }};
    }

    /// [`super::sym_fir_cols_u8`] for `R` output rows on whole chunks of 16 outputs per row (one
    /// register per output row). Returns the count done.
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn cols_avx2<const R: usize>(
        outs: &mut [&mut [u8]],
        base: &[i16],
        stride: usize,
        centre: &[usize],
        cols: &[super::TapCol],
        offs: &[usize],
        q0: i16,
        wq: &[i16],
        prefetch: &[&[u8]],
    ) -> usize {
        let n = outs[0].len() / 16 * 16;
        let bp = base.as_ptr();
        // SAFETY: the callers read weights inside `wq`.
        let bc = |p: *const i16| _mm256_set1_epi16(unsafe { *p });
        let q0v = _mm256_set1_epi16(q0);
        let half = _mm256_set1_epi16(32);
        let add = |a, b| _mm256_add_epi16(a, b);
        let mul = |a, b| _mm256_mulhrs_epi16(a, b);
        let mut i = 0;
        while i < n {
            // SAFETY (block): every offset in `centre` and `offs` plus i + 16 is at most
            // base.len(), every weight index is inside `wq` (asserted by the caller); each
            // output holds n >= i + 16 bytes.
            unsafe {
                let ld = |p: usize| _mm256_loadu_si256(bp.add(p + i) as *const __m256i);
                let mut a: [__m256i; R] = std::array::from_fn(|j| _mm256_mulhrs_epi16(ld(centre[j]), q0v));
                cols_sums!(a, ld, cols, offs.as_ptr(), stride, wq.as_ptr(), add, mul, bc);
                for (o, a) in outs.iter_mut().zip(a) {
                    let v = _mm256_srai_epi16::<6>(_mm256_adds_epi16(a, half));
                    let v = _mm256_permute4x64_epi64::<0xD8>(_mm256_packus_epi16(v, v));
                    _mm_storeu_si128(o.as_mut_ptr().add(i) as *mut __m128i, _mm256_castsi256_si128(v));
                }
            }
            prefetch_rows(prefetch, i, 16);
            i += 16;
        }
        n
    }

    /// Prefetches the cache lines of `rows` that hold bytes `i..i + step` (the first byte of
    /// each line once).
    #[inline(always)]
    fn prefetch_rows(rows: &[&[u8]], i: usize, step: usize) {
        if i % 64 < step {
            for r in rows {
                if let Some(b) = r.get(i - i % 64) {
                    // SAFETY: a prefetch reads nothing observable; the address is inside `r`.
                    unsafe { _mm_prefetch::<_MM_HINT_T0>(b as *const u8 as *const i8) };
                }
            }
        }
    }

    /// [`cols_avx2`] with 32 outputs per register.
    #[target_feature(enable = "avx512f,avx512bw")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn cols_avx512<const R: usize>(
        outs: &mut [&mut [u8]],
        base: &[i16],
        stride: usize,
        centre: &[usize],
        cols: &[super::TapCol],
        offs: &[usize],
        q0: i16,
        wq: &[i16],
        prefetch: &[&[u8]],
    ) -> usize {
        let n = outs[0].len() / 32 * 32;
        let bp = base.as_ptr();
        // SAFETY: the callers read weights inside `wq`.
        let bc = |p: *const i16| _mm512_set1_epi16(unsafe { *p });
        let q0v = _mm512_set1_epi16(q0);
        let (half, zero) = (_mm512_set1_epi16(32), _mm512_setzero_si512());
        let add = |a, b| _mm512_add_epi16(a, b);
        let mul = |a, b| _mm512_mulhrs_epi16(a, b);
        let mut i = 0;
        while i < n {
            // SAFETY (block): as in `cols_avx2`, with i + 32.
            unsafe {
                let ld = |p: usize| _mm512_loadu_si512(bp.add(p + i) as *const __m512i);
                let mut a: [__m512i; R] = std::array::from_fn(|j| _mm512_mulhrs_epi16(ld(centre[j]), q0v));
                cols_sums!(a, ld, cols, offs.as_ptr(), stride, wq.as_ptr(), add, mul, bc);
                for (o, a) in outs.iter_mut().zip(a) {
                    let v = _mm512_max_epi16(_mm512_srai_epi16::<6>(_mm512_adds_epi16(a, half)), zero);
                    _mm256_storeu_si256(o.as_mut_ptr().add(i) as *mut __m256i, _mm512_cvtusepi16_epi8(v));
                }
            }
            prefetch_rows(prefetch, i, 32);
            i += 32;
        }
        n
    }

    /// Whole chunks of 128 outputs; returns how many outputs were written.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub unsafe fn fir_avx512(
        out: &mut [i16],
        base: &[i16],
        center: usize,
        offs: &[(usize, usize)],
        q: &[i16],
    ) -> usize {
        let n = out.len() / 128 * 128;
        let bp = base.as_ptr();
        let mut i = 0;
        while i < n {
            // SAFETY (block): offsets + i + 128 <= offsets + n <= base.len() (checked by the caller).
            unsafe {
                let [a0, a1, a2, a3] = sums128_avx512(bp, center + i, offs, q, i);
                let op = out.as_mut_ptr().add(i) as *mut __m512i;
                _mm512_storeu_si512(op, a0);
                _mm512_storeu_si512(op.add(1), a1);
                _mm512_storeu_si512(op.add(2), a2);
                _mm512_storeu_si512(op.add(3), a3);
            }
            i += 128;
        }
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn weights_sum_to_one_and_round_to_the_nearest_unit() {
        for sigma in [0.05, 0.3, 1.5, 4.0, 20.0] {
            let k: Vec<f64> = crate::faults::defocus::discrete_gaussian_f64(sigma);
            let q = q15_half_kernel(&k);
            let r = k.len() / 2;
            assert_eq!(q[0] as i64 + 2 * q[1..].iter().map(|&v| v as i64).sum::<i64>(), 32768, "{sigma}");
            assert!((q[0] as f64 - k[r] * 32768.0).abs() < 2.0, "{sigma}: centre");
            for j in 1..=r {
                assert!((q[j] as f64 - k[r + j] * 32768.0).abs() < 1.0, "{sigma}: tap {j}");
            }
        }
    }

    #[test]
    fn simd_paths_equal_the_scalar_reference() {
        let mut rng = Rng::new(9);
        let base: Vec<i16> = (0..3000).map(|_| rng.below(16321) as i16).collect();
        let q: Vec<i16> = vec![9000, 7000, 3000, 500, 884];
        for n in [0usize, 1, 63, 64, 65, 127, 128, 129, 700, 2000] {
            let offs: Vec<(usize, usize)> = vec![(0, 0), (40, 60), (30, 70), (10, 90), (0, 100)];
            let mut fast = vec![0i16; n];
            let mut slow = vec![0i16; n];
            sym_fir(&mut fast, &base, 50, &offs, &q);
            fir_scalar(&mut slow, &base, 50, &offs, &q, 0);
            assert_eq!(fast, slow, "{n}");
        }
        // Two centres at once: the same values as two single calls (even and odd r, r = 0).
        for r in [4usize, 3, 1, 0] {
            let q = &q[..=r];
            for n in [0usize, 1, 31, 32, 33, 95, 700] {
                let rows: Vec<usize> = (0..2 * r + 2).map(|t| (t * 211) % 2000).collect();
                let (mut f0, mut f1) = (vec![0i16; n], vec![0i16; n]);
                sym_fir2(&mut f0, &mut f1, &base, &rows, q);
                for (c, f) in [(r, &f0), (r + 1, &f1)] {
                    let offs: Vec<(usize, usize)> = (0..=r).map(|k| (rows[c - k], rows[c + k])).collect();
                    let mut slow = vec![0i16; n];
                    fir_scalar(&mut slow, &base, rows[c], &offs, q, 0);
                    assert_eq!(*f, slow, "r {r} n {n} centre {c}");
                }
            }
        }
        // The column kernel: the same bytes as sym_fir + q6_to_u8 row by row, over columns with
        // negative and positive dy, a gap (weight 0), dx = 0, at lengths around the chunk sizes.
        // Unrolled columns of 1 to 4 pairs (one dx cut into four columns) and rotated ones of 5
        // (the shortest), 7 and 9 pairs, 4 and 8 output rows.
        let (pw, ch) = (700usize, 3usize);
        let cols = [
            TapCol { dx: 0, dy0: 1, dy1: 3, w0: 0 },
            TapCol { dx: 1, dy0: -2, dy1: 1, w0: 3 },
            TapCol { dx: 4, dy0: 2, dy1: 2, w0: 7 },
            TapCol { dx: 2, dy0: -4, dy1: -4, w0: 8 },
            TapCol { dx: 2, dy0: -3, dy1: -1, w0: 9 },
            TapCol { dx: 2, dy0: 0, dy1: 2, w0: 12 },
            TapCol { dx: 2, dy0: 3, dy1: 5, w0: 15 },
            TapCol { dx: 3, dy0: -2, dy1: 1, w0: 18 },
            TapCol { dx: 5, dy0: -3, dy1: 3, w0: 22 },
            TapCol { dx: 6, dy0: -4, dy1: 4, w0: 29 },
            TapCol { dx: 7, dy0: 0, dy1: 4, w0: 38 },
        ];
        let mut wq = vec![
            2100, 1300, 700, 900, 0, 2500, 1200, 400, 300, 50, 800, 0, 120, 640, 90, 1000, 20, 260, 310, 0, 450, 700,
        ];
        // The rotated columns: 21 small weights (one gap), sum 2100.
        wq.extend((0..21).map(|s| if s == 10 { 0 } else { 5 + 10 * s as i16 }));
        assert_eq!(wq.len(), 43);
        let q0 = 32768 - 2 * wq.iter().map(|&v| v as i32).sum::<i32>();
        assert!(q0 > 0);
        let base: Vec<i16> = (0..pw * 30).map(|_| rng.below(16321) as i16).collect();
        // (dx, dy) pairs and their weights for sym_fir.
        let mut pairs = vec![((0isize, 0isize), q0 as i16)];
        for c in &cols {
            for (s, dy) in (c.dy0..=c.dy1).enumerate() {
                pairs.push(((c.dx as isize, dy as isize), wq[c.w0 + s]));
            }
        }
        for (nrows, n) in
            [4usize, 8].into_iter().flat_map(|r| [0usize, 1, 15, 16, 17, 31, 32, 33, 100, 600].map(|n| (r, n)))
        {
            let c0 = 10 * pw + 5 * ch;
            let mut rows: Vec<Vec<u8>> = vec![vec![0u8; n]; nrows];
            // Sample 0 of row y + t (t from -10), shifted by dx pixels; per column lo (row
            // -dy1, -dx) and hi (row dy0, +dx): two offsets, or for the rotated columns every
            // row of the two runs.
            let at = |t: isize, dx: isize| (c0 as isize + t * pw as isize + dx * ch as isize) as usize;
            let mut offs = Vec::new();
            for c in &cols {
                let (dx, m) = (c.dx as isize, col_offs(c.len(), nrows));
                offs.extend((0..m / 2).map(|t| at(t as isize - c.dy1 as isize, -dx)));
                offs.extend((0..m / 2).map(|t| at(c.dy0 as isize + t as isize, dx)));
            }
            let centre: Vec<usize> = (0..nrows).map(|j| at(j as isize, 0)).collect();
            let mut outs: Vec<&mut [u8]> = rows.iter_mut().map(|r| &mut r[..]).collect();
            // Prefetched rows (their bytes are not read): one shorter than the outputs.
            let spare = vec![7u8; 2 * n + 64];
            let pf: Vec<&[u8]> = (0..nrows).map(|j| if j == 1 { &spare[..n / 2] } else { &spare[j..j + n] }).collect();
            sym_fir_cols_u8(&mut outs, &base, pw, &centre, &cols, &offs, q0 as i16, &wq, &pf);
            if nrows == 4 {
                // Stop 41's 4-row kernel (every column rotated): lo[m] row 3 - dy0 - m (-dx),
                // hi[m] row dy0 + m (+dx); the same bytes.
                let mut offs4 = Vec::new();
                for c in &cols {
                    let (dx, dy0, m) = (c.dx as isize, c.dy0 as isize, col_loads4(c.len()) as isize);
                    offs4.extend((0..m).map(|t| at(3 - dy0 - t, -dx)));
                    offs4.extend((0..m).map(|t| at(dy0 + t, dx)));
                }
                let mut rows4: Vec<Vec<u8>> = vec![vec![0u8; n]; 4];
                let [o0, o1, o2, o3] = &mut rows4[..] else { unreachable!() };
                let c4: [usize; 4] = std::array::from_fn(|j| centre[j]);
                sym_fir_cols4_u8([o0, o1, o2, o3], &base, c4, &cols, &offs4, q0 as i16, &wq);
                assert_eq!(rows4, rows, "4-row rotated kernel, n {n}");
            }
            for (j, got) in rows.iter().enumerate() {
                let cj = c0 + j * pw;
                let at = |dx: isize, dy: isize| (cj as isize + dy * pw as isize + dx * ch as isize) as usize;
                let offs: Vec<(usize, usize)> = pairs.iter().map(|&((dx, dy), _)| (at(-dx, -dy), at(dx, dy))).collect();
                let q: Vec<i16> = pairs.iter().map(|p| p.1).collect();
                let mut acc = vec![0i16; n];
                sym_fir(&mut acc, &base, cj, &offs, &q);
                let mut want = vec![0u8; n];
                q6_to_u8(&mut want, &acc);
                assert_eq!(*got, want, "column kernel, {nrows} rows, n {n}, row {j}");
                let mut fused = vec![0u8; n];
                sym_fir_u8(&mut fused, &base, cj, &offs, &q);
                assert_eq!(fused, want, "sym_fir_u8, n {n}, row {j}");
            }
        }
        // The conversions: every i16 and every byte, at lengths around the chunk sizes.
        let all: Vec<i16> = (i16::MIN..=i16::MAX).collect();
        let mut fast = vec![0u8; all.len()];
        q6_to_u8(&mut fast, &all);
        for (&a, &f) in all.iter().zip(&fast) {
            assert_eq!(f, ((a.max(0) as i32 + 32) >> SAMPLE_Q).min(255) as u8, "{a}");
        }
        for n in [0usize, 1, 15, 16, 17, 31, 32, 33, 300] {
            let src: Vec<u8> = (0..n).map(|i| (i * 37 % 256) as u8).collect();
            let mut q6 = vec![0i16; n];
            u8_to_q6(&mut q6, &src);
            assert!(q6.iter().zip(&src).all(|(&p, &v)| p == (v as i16) << SAMPLE_Q), "{n}");
            let mut back = vec![0u8; n];
            q6_to_u8(&mut back, &q6);
            assert_eq!(back, src, "{n}");
        }
        // mulhrs is round-to-nearest (ties up) of a * b / 2^15.
        for &(a, b) in &[(16320i16, 32767i16), (1, 16384), (3, 16384), (-5, 9000), (32640, 1)] {
            let exact = a as f64 * b as f64 / 32768.0;
            assert_eq!(mulhrs(a, b) as f64, (exact + 0.5).floor(), "{a} {b}");
        }
    }
}
