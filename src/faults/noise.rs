//! Table-driven per-sample noise: the kernel behind `gaussian_noise` and `dark_current`.
//!
//! Each sample takes one 16-bit uniform from [`RngLanes`] (sample j of a group of 16 uses bits
//! 16·(j mod 4) .. of output j / 4 of one `next4` step), keeps its low `bits` bits as an index
//! into a table of integer DN offsets, and becomes `clip(v + table[index], 0, MAX)`. A table
//! entry [`RESOLVE`] marks an index whose offset is not a single value (a distribution tail or a
//! bucket that straddles a CDF step): the caller's `resolve(index)` draws it exactly, in sample
//! order, from its own generator.
//!
//! [`add_table_noise`] dispatches to an AVX2 version (eight-lane xoshiro256++ state in registers,
//! gathered table lookups) when the CPU has it; the scalar reference below defines the bytes and
//! the tests check that both agree.

use super::kit::RngLanes;
use crate::frame::Sample;

/// Table entry meaning "ask `resolve`".
pub const RESOLVE: i32 = i32::MIN;

/// Add table noise to `row` (see the module documentation). `table.len()` must be `1 << bits`,
/// `bits <= 16`.
pub fn add_table_noise<T: Sample>(
    row: &mut [T],
    lanes: &mut RngLanes,
    table: &[i32],
    bits: u32,
    resolve: &mut dyn FnMut(usize) -> i32,
) {
    if table.len() != 1 << bits || bits > 16 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above); the table length was checked.
        unsafe { avx2::add_table_noise(row, lanes, table, bits, resolve) };
        return;
    }
    add_table_noise_scalar(row, lanes, table, bits, resolve)
}

/// Scalar reference of [`add_table_noise`].
pub fn add_table_noise_scalar<T: Sample>(
    row: &mut [T],
    lanes: &mut RngLanes,
    table: &[i32],
    bits: u32,
    resolve: &mut dyn FnMut(usize) -> i32,
) {
    let mask = (1usize << bits) - 1;
    let max = T::MAX_U32 as i32;
    for chunk in row.chunks_mut(16) {
        let r = lanes.next4();
        for (j, v) in chunk.iter_mut().enumerate() {
            let idx = (r[j / 4] >> (16 * (j % 4))) as usize & mask;
            let mut q = table[idx];
            if q == RESOLVE {
                q = resolve(idx);
            }
            *v = T::from_u32_sat((v.to_u32() as i32).saturating_add(q).clamp(0, max) as u32);
        }
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::{RESOLVE, RngLanes, Sample};
    use std::arch::x86_64::*;

    #[inline(always)]
    fn rotl(x: __m256i, k: i32) -> __m256i {
        // SAFETY (and below): only inlined into `add_table_noise`, which enables AVX2.
        unsafe {
            _mm256_or_si256(_mm256_sll_epi64(x, _mm_cvtsi32_si128(k)), _mm256_srl_epi64(x, _mm_cvtsi32_si128(64 - k)))
        }
    }

    /// One xoshiro256++ step of the four lanes (the same arithmetic as `RngLanes::next4`).
    /// Only inline into functions with AVX2 enabled.
    #[inline(always)]
    pub(crate) fn next4(s: &mut [__m256i; 4]) -> __m256i {
        unsafe {
            let out = _mm256_add_epi64(rotl(_mm256_add_epi64(s[0], s[3]), 23), s[0]);
            let t = _mm256_slli_epi64(s[1], 17);
            s[2] = _mm256_xor_si256(s[2], s[0]);
            s[3] = _mm256_xor_si256(s[3], s[1]);
            s[1] = _mm256_xor_si256(s[1], s[2]);
            s[0] = _mm256_xor_si256(s[0], s[3]);
            s[2] = _mm256_xor_si256(s[2], t);
            s[3] = rotl(s[3], 45);
            out
        }
    }

    /// Load the lanes' state into registers (AVX2 context only).
    #[inline(always)]
    pub(crate) fn load_state(lanes: &mut RngLanes) -> [__m256i; 4] {
        let st = lanes.state_mut();
        // SAFETY: four [u64; 4] arrays of 32 bytes; unaligned loads.
        std::array::from_fn(|j| unsafe { _mm256_loadu_si256(st[j].as_ptr() as *const __m256i) })
    }

    /// Store the registers back into the lanes' state (AVX2 context only).
    #[inline(always)]
    pub(crate) fn store_state(lanes: &mut RngLanes, s: &[__m256i; 4]) {
        let st = lanes.state_mut();
        for j in 0..4 {
            // SAFETY: as in `load_state`.
            unsafe { _mm256_storeu_si256(st[j].as_mut_ptr() as *mut __m256i, s[j]) };
        }
    }

    #[target_feature(enable = "avx2")]
    pub unsafe fn add_table_noise<T: Sample>(
        row: &mut [T],
        lanes: &mut RngLanes,
        table: &[i32],
        bits: u32,
        resolve: &mut dyn FnMut(usize) -> i32,
    ) {
        let mut s = load_state(lanes);
        let mask = _mm256_set1_epi32(((1u32 << bits) - 1) as i32);
        let marker = _mm256_set1_epi32(RESOLVE);
        let (zero, max) = (_mm256_setzero_si256(), _mm256_set1_epi32(T::MAX_U32 as i32));
        let wide = T::MAX_U32 > 255;
        // Chunks holding lanes to resolve are written with offset 0 there and fixed up after the
        // loop, in sample order (so the hot loop has no call and keeps its registers).
        let mut pending = Pending::new();
        let n16 = row.len() / 16 * 16;
        for ci in 0..n16 / 16 {
            let r = next4(&mut s);
            let i_lo = _mm256_and_si256(_mm256_cvtepu16_epi32(_mm256_castsi256_si128(r)), mask);
            let i_hi = _mm256_and_si256(_mm256_cvtepu16_epi32(_mm256_extracti128_si256(r, 1)), mask);
            // SAFETY: every index is masked to `bits` bits and the table holds 1 << bits entries.
            let (mut q_lo, mut q_hi) = unsafe {
                (_mm256_i32gather_epi32::<4>(table.as_ptr(), i_lo), _mm256_i32gather_epi32::<4>(table.as_ptr(), i_hi))
            };
            let (m_lo, m_hi) = (_mm256_cmpeq_epi32(q_lo, marker), _mm256_cmpeq_epi32(q_hi, marker));
            if _mm256_movemask_epi8(_mm256_or_si256(m_lo, m_hi)) != 0 {
                if pending.full() {
                    pending.flush(row, resolve);
                }
                let mut e = PendingChunk { chunk: ci, orig: [0; 16], idx: [0; 16], q: [0; 16] };
                for (o, v) in e.orig.iter_mut().zip(&row[ci * 16..ci * 16 + 16]) {
                    *o = v.to_u32() as i32;
                }
                // SAFETY: eight i32 per half; unaligned stores.
                unsafe {
                    _mm256_storeu_si256(e.q.as_mut_ptr() as *mut __m256i, q_lo);
                    _mm256_storeu_si256(e.q.as_mut_ptr().add(8) as *mut __m256i, q_hi);
                    _mm256_storeu_si256(e.idx.as_mut_ptr() as *mut __m256i, i_lo);
                    _mm256_storeu_si256(e.idx.as_mut_ptr().add(8) as *mut __m256i, i_hi);
                }
                pending.push(e);
                q_lo = _mm256_andnot_si256(m_lo, q_lo);
                q_hi = _mm256_andnot_si256(m_hi, q_hi);
            }
            let chunk = &mut row[ci * 16..ci * 16 + 16];
            // SAFETY: `chunk` holds 16 samples of T (u8 or u16); unaligned loads and stores.
            unsafe {
                let p = chunk.as_mut_ptr();
                let (v_lo, v_hi) = if wide {
                    let v = _mm256_loadu_si256(p as *const __m256i);
                    (
                        _mm256_cvtepu16_epi32(_mm256_castsi256_si128(v)),
                        _mm256_cvtepu16_epi32(_mm256_extracti128_si256(v, 1)),
                    )
                } else {
                    let v = _mm_loadu_si128(p as *const __m128i);
                    (_mm256_cvtepu8_epi32(v), _mm256_cvtepu8_epi32(_mm_srli_si128(v, 8)))
                };
                // Saturating add (as the reference's saturating_add), then clip to [0, MAX].
                let a_lo = _mm256_min_epi32(_mm256_max_epi32(sat_add(v_lo, q_lo), zero), max);
                let a_hi = _mm256_min_epi32(_mm256_max_epi32(sat_add(v_hi, q_hi), zero), max);
                // Values are in [0, MAX]: pack without further saturation effects.
                let p16 = _mm256_permute4x64_epi64(_mm256_packus_epi32(a_lo, a_hi), 0b11_01_10_00);
                if wide {
                    _mm256_storeu_si256(p as *mut __m256i, p16);
                } else {
                    let p8 = _mm256_packus_epi16(p16, p16);
                    let bytes = _mm256_permute4x64_epi64(p8, 0b11_01_10_00);
                    _mm_storeu_si128(p as *mut __m128i, _mm256_castsi256_si128(bytes));
                }
            }
        }
        pending.flush(row, resolve);
        store_state(lanes, &s);
        if n16 < row.len() {
            super::add_table_noise_scalar(&mut row[n16..], lanes, table, bits, resolve);
        }
    }

    /// A chunk of 16 samples with lanes still to resolve: original samples, indices, offsets.
    #[derive(Clone, Copy)]
    struct PendingChunk {
        chunk: usize,
        orig: [i32; 16],
        idx: [i32; 16],
        q: [i32; 16],
    }

    /// Fixed-capacity list (no allocation) of chunks to fix up, in row order.
    struct Pending {
        items: [PendingChunk; 32],
        len: usize,
    }

    impl Pending {
        fn new() -> Pending {
            Pending { items: [PendingChunk { chunk: 0, orig: [0; 16], idx: [0; 16], q: [0; 16] }; 32], len: 0 }
        }
        fn full(&self) -> bool {
            self.len == self.items.len()
        }
        fn push(&mut self, e: PendingChunk) {
            self.items[self.len] = e;
            self.len += 1;
        }
        /// Resolve the marked lanes in sample order and rewrite those samples.
        #[cold]
        fn flush<T: Sample>(&mut self, row: &mut [T], resolve: &mut dyn FnMut(usize) -> i32) {
            let max = T::MAX_U32 as i32;
            for e in &self.items[..self.len] {
                for j in 0..16 {
                    if e.q[j] == RESOLVE {
                        let q = resolve(e.idx[j] as usize);
                        row[e.chunk * 16 + j] = T::from_u32_sat(e.orig[j].saturating_add(q).clamp(0, max) as u32);
                    }
                }
            }
            self.len = 0;
        }
    }

    /// a + b with i32 saturation (v >= 0, so only overflow towards +inf is possible).
    #[inline(always)]
    fn sat_add(v: __m256i, q: __m256i) -> __m256i {
        unsafe {
            let s = _mm256_add_epi32(v, q);
            // Overflow when q > 0 and the sum is negative.
            let ovf = _mm256_and_si256(
                _mm256_cmpgt_epi32(q, _mm256_setzero_si256()),
                _mm256_cmpgt_epi32(_mm256_setzero_si256(), s),
            );
            _mm256_blendv_epi8(s, _mm256_set1_epi32(i32::MAX), ovf)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn check<T: Sample + std::fmt::Debug + PartialEq>(max: u32) {
        let mut r = Rng::new(3);
        // Sparse entries to resolve (the usual case) and dense ones (many pending chunks per row,
        // so the fix-up list fills and flushes mid-row).
        for (bits, every) in [(12u32, 997usize), (16, 997), (12, 7)] {
            // Offsets of either sign and size (clipping at both ends), some entries to resolve.
            let table: Vec<i32> = (0..1usize << bits)
                .map(|i| {
                    if i % every == 5 { RESOLVE } else { (r.below(2 * max as u64 + 1) as i64 - max as i64) as i32 / 3 }
                })
                .collect();
            for n in [0usize, 1, 15, 16, 17, 100, 1921] {
                let row: Vec<T> = (0..n).map(|_| T::from_u32_sat(r.below(max as u64 + 1) as u32)).collect();
                let seed = Rng::new(n as u64 + bits as u64);
                let (mut a, mut b) = (row.clone(), row.clone());
                let (mut la, mut lb) = (RngLanes::new(&seed), RngLanes::new(&seed));
                let (mut ra, mut rb) = (Rng::new(9), Rng::new(9));
                let (mut ca, mut cb) = (Vec::new(), Vec::new());
                add_table_noise_scalar(&mut a, &mut la, &table, bits, &mut |i| {
                    ca.push(i);
                    ra.below(41) as i32 - 20
                });
                add_table_noise(&mut b, &mut lb, &table, bits, &mut |i| {
                    cb.push(i);
                    rb.below(41) as i32 - 20
                });
                assert_eq!(a, b, "bits {bits}, {n} samples");
                assert_eq!(ca, cb, "resolve calls in the same order");
                // Both continue the same stream.
                assert_eq!(la.next4(), lb.next4());
            }
        }
    }

    #[test]
    fn fast_path_equals_the_scalar_reference() {
        check::<u8>(255);
        check::<u16>(65535);
    }

    #[test]
    fn offsets_come_from_the_table_with_clipping() {
        // A table with one value: every sample moves by it, clipped.
        let table = vec![7i32; 1 << 12];
        let mut row: Vec<u8> = (0..=255).collect();
        add_table_noise(&mut row, &mut RngLanes::new(&Rng::new(1)), &table, 12, &mut |_| 0);
        for (v, out) in (0..=255u32).zip(&row) {
            assert_eq!(*out as u32, (v + 7).min(255));
        }
    }
}
