//! Table-driven per-sample noise: the kernel behind `gaussian_noise` and `dark_current`.
//!
//! Each sample takes one 16-bit uniform from [`RngLanes`] (sample j of a group of 16 uses bits
//! 16·(j mod 4) .. of output j / 4 of one `next4` step), keeps its low `bits` bits as an index
//! into a table of integer DN offsets, and becomes `clip(v + table[index], 0, MAX)`. A table
//! entry [`RESOLVE`] marks an index whose offset is not a single value (a distribution tail or a
//! bucket that straddles a CDF step): the caller's `resolve(index)` draws it exactly, in sample
//! order, from its own generator.
//!
//! [`add_table_noise`] dispatches to the fastest exact version the CPU has; the scalar reference
//! below defines the bytes and the tests check that every version agrees:
//! - AVX-512, 8-bit samples, for tables with the two-level form of [`TwoLevel`] (the monotone
//!   inverse-CDF tables of both effects have it): the offset is computed in registers, with no
//!   memory lookups, from 64-entry byte tables (`vpermb`, VBMI, 64 samples per step) when every
//!   offset fits a byte, else from 64-entry word tables (`vpermi2w`, 32 samples per step);
//! - AVX2, 8-bit samples, for tables whose two-level form has the byte form: the same
//!   computation with no memory lookups and no gathers, from 16-entry quarters of the 64-entry
//!   byte tables (`vpshufb`, two `vpblendvb` on the coarse index's bits 4 and 5), 32 samples per
//!   step; gathers are microcoded and slow on many AMD cores (Zen 2/3), so no AVX2 kernel uses
//!   them. When every simple bucket steps by the same amount and resolves at most the entry
//!   before its step (`StepForm`, both effects' tables at usual settings) two such lookups
//!   replace the four;
//! - AVX2, other tables and 16-bit samples: xoshiro256++ lanes in registers, table entries by
//!   scalar loads.

use super::kit::RngLanes;
#[cfg(target_arch = "x86_64")]
use super::kit::{has_avx2, has_avx512, has_avx512_vbmi};
use crate::frame::Sample;

/// Table entry meaning "ask `resolve`".
pub const RESOLVE: i32 = i32::MIN;

/// Coarse index bits of the two-level form (64 coarse buckets: one `vpermi2w` table).
const COARSE_BITS: u32 = 6;
/// Most coarse buckets that may need an exact 64-entry table.
const MAX_EXACT: usize = 4;
/// Largest offset magnitude of the two-level form (16-bit lanes, headroom for v + offset).
const MAX_FAST_OFFSET: i32 = 16384;
/// Word-table entry for "resolve" in an exact bucket table.
const EXACT_RESOLVE: i16 = i16::MIN;
/// "Never" for thresholds and resolve positions (fine indices are below 2^10).
const NEVER: u16 = u16::MAX;

/// The two-level form of a table with `bits` = 12: index i = 64·c + f (coarse c, fine f).
/// Coarse bucket c is either *simple*, `table[i] = base[c] + (f >= thr[c] ? delta[c] : 0)`
/// with at most one entry to resolve (at `f == res[c]`), or one of at most [`MAX_EXACT`]
/// *exact* buckets with its own 64-entry word table ([`EXACT_RESOLVE`] marking entries to
/// resolve). [`TwoLevel::compile`] builds it only when it reproduces every entry.
#[derive(Clone, Debug, PartialEq)]
pub struct TwoLevel {
    base: [i16; 64],
    thr: [u16; 64],
    delta: [i16; 64],
    res: [u16; 64],
    exact_c: [u16; MAX_EXACT],
    exact: [[i16; 64]; MAX_EXACT],
    n_exact: usize,
    /// The same form in bytes, when every offset fits in [-127, 127] (64 samples per step with
    /// single-register byte permutes).
    bytes: Option<ByteForm>,
}

/// [`TwoLevel`] with byte entries: `thr` 64 and `res` 255 mean "never", exact-bucket entries
/// [`BYTE_RESOLVE`] mean "resolve".
#[derive(Clone, Debug, PartialEq)]
struct ByteForm {
    base: [i8; 64],
    thr: [u8; 64],
    delta: [i8; 64],
    res: [u8; 64],
    exact_c: [u8; MAX_EXACT],
    exact: [[i8; 64]; MAX_EXACT],
    /// The same form with two coarse tables instead of four, when it has one.
    step: Option<StepForm>,
}

/// [`ByteForm`] in two coarse lookups instead of four, for tables whose simple buckets all step
/// by the same `delta` (or not at all) and resolve, if anything, the entry just before the step
/// (the monotone inverse-CDF tables of both effects at usual settings). `thr[c]` holds the step
/// position (0..=64, 64 never) in bits 0..6 and "resolve the entry at f = thr - 1" in bit 7;
/// entry f of simple bucket c is `base[c] + (f >= thr ? delta : 0)` in wrapping byte
/// arithmetic. The exact buckets are the byte form's.
#[derive(Clone, Debug, PartialEq)]
struct StepForm {
    base: [i8; 64],
    thr: [u8; 64],
    delta: i8,
    /// Some bucket has an entry to resolve (bit 7 of some `thr`).
    any_res: bool,
}

/// Bit 7 of a [`StepForm`] threshold: the entry at `thr - 1` is resolved.
const STEP_RES: u8 = 0x80;

impl StepForm {
    /// The step form of `b` (with `n_exact` exact buckets), checked against every entry of
    /// `table`.
    fn of(b: &ByteForm, n_exact: usize, table: &[i32]) -> Option<StepForm> {
        let exact = |c: usize| b.exact_c[..n_exact].contains(&(c as u8));
        let mut delta = 0i8;
        for c in (0..64).filter(|&c| !exact(c) && b.thr[c] < 64) {
            if delta == 0 {
                delta = b.delta[c];
            } else if b.delta[c] != delta {
                return None;
            }
        }
        let mut s = StepForm { base: [0; 64], thr: [64; 64], delta, any_res: false };
        for c in (0..64).filter(|&c| !exact(c)) {
            let (base, thr, res) = match (b.thr[c], b.res[c]) {
                (t, 255) => (b.base[c], t, false),
                (t, r) if r < 64 && r + 1 == t => (b.base[c], t, true),
                // No step, the first entry resolved: a step of `delta` at 1 from base - delta
                // (wrapping: the entries from f = 1 on are base again).
                (64, 0) => (b.base[c].wrapping_sub(delta), 1, true),
                _ => return None,
            };
            s.base[c] = base;
            s.thr[c] = thr | if res { STEP_RES } else { 0 };
            s.any_res |= res;
        }
        // Belt and braces: the form must give back every entry.
        (0..table.len()).all(|i| s.lookup(b, n_exact, i) == table[i]).then_some(s)
    }

    /// The entry of index `i` as the registers compute it (RESOLVE for entries to resolve).
    fn lookup(&self, b: &ByteForm, n_exact: usize, i: usize) -> i32 {
        let (c, f) = (i >> COARSE_BITS, (i & 63) as u8);
        if let Some(k) = b.exact_c[..n_exact].iter().position(|&e| e as usize == c) {
            let q = b.exact[k][f as usize];
            return if q == BYTE_RESOLVE { RESOLVE } else { q as i32 };
        }
        let thr = self.thr[c] & !STEP_RES;
        if self.thr[c] & STEP_RES != 0 && f + 1 == thr {
            return RESOLVE;
        }
        self.base[c].wrapping_add(if f >= thr { self.delta } else { 0 }) as i32
    }
}

/// Byte-form entry for "resolve" in an exact bucket table.
const BYTE_RESOLVE: i8 = i8::MIN;

impl ByteForm {
    fn of(t: &TwoLevel) -> Option<ByteForm> {
        let byte = |v: i32| i8::try_from(v).ok().filter(|&b| b != BYTE_RESOLVE);
        let mut b = ByteForm {
            base: [0; 64],
            thr: [64; 64],
            delta: [0; 64],
            res: [255; 64],
            exact_c: [255; MAX_EXACT],
            exact: [[0; 64]; MAX_EXACT],
            step: None,
        };
        for c in 0..64 {
            let (base, delta) = (t.base[c] as i32, t.delta[c] as i32);
            b.base[c] = byte(base)?;
            b.delta[c] = byte(delta)?;
            byte(base + delta)?;
            b.thr[c] = t.thr[c].min(64) as u8;
            b.res[c] = if t.res[c] == NEVER { 255 } else { t.res[c] as u8 };
        }
        for k in 0..t.n_exact {
            b.exact_c[k] = t.exact_c[k] as u8;
            for (o, &q) in b.exact[k].iter_mut().zip(&t.exact[k]) {
                *o = if q == EXACT_RESOLVE { BYTE_RESOLVE } else { byte(q as i32)? };
            }
        }
        Some(b)
    }
}

impl TwoLevel {
    /// The two-level form of `table` (`1 << bits` entries), if it has one.
    pub fn compile(table: &[i32], bits: u32) -> Option<TwoLevel> {
        if bits != 2 * COARSE_BITS || table.len() != 1 << bits {
            return None;
        }
        let fine = 1usize << (bits - COARSE_BITS);
        let mut t = TwoLevel {
            base: [0; 64],
            thr: [NEVER; 64],
            delta: [0; 64],
            res: [NEVER; 64],
            exact_c: [NEVER; MAX_EXACT],
            exact: [[0; 64]; MAX_EXACT],
            n_exact: 0,
            bytes: None,
        };
        for (c, bucket) in table.chunks(fine).enumerate() {
            if bucket.iter().any(|&q| q != RESOLVE && !(-MAX_FAST_OFFSET..=MAX_FAST_OFFSET).contains(&q)) {
                return None;
            }
            if !t.simple(c, bucket) {
                if t.n_exact == MAX_EXACT {
                    return None;
                }
                let k = t.n_exact;
                t.exact_c[k] = c as u16;
                for (e, &q) in t.exact[k].iter_mut().zip(bucket) {
                    *e = if q == RESOLVE { EXACT_RESOLVE } else { q as i16 };
                }
                t.n_exact += 1;
            }
        }
        // Belt and braces: the form must give back every entry.
        if !(0..table.len()).all(|i| t.lookup(i) == table[i]) {
            return None;
        }
        t.bytes = ByteForm::of(&t);
        if let Some(b) = &mut t.bytes {
            b.step = StepForm::of(b, t.n_exact, table);
        }
        Some(t)
    }

    /// Fill the simple description of bucket `c`; false when it has none.
    fn simple(&mut self, c: usize, bucket: &[i32]) -> bool {
        let resolve: Vec<usize> = (0..bucket.len()).filter(|&f| bucket[f] == RESOLVE).collect();
        if resolve.len() > 1 {
            return false;
        }
        let vals: Vec<(usize, i32)> = bucket.iter().copied().enumerate().filter(|&(_, q)| q != RESOLVE).collect();
        let Some(&(_, first)) = vals.first() else { return false };
        // At most one change of value, at `thr`.
        let mut thr = None;
        let mut second = first;
        for &(f, q) in &vals {
            if q != second {
                if thr.is_some() {
                    return false;
                }
                thr = Some(f);
                second = q;
            }
        }
        self.base[c] = first as i16;
        self.thr[c] = thr.map_or(NEVER, |f| f as u16);
        self.delta[c] = (second - first) as i16;
        self.res[c] = resolve.first().map_or(NEVER, |&f| f as u16);
        true
    }

    /// The entry of index `i` as the registers compute it (RESOLVE for entries to resolve).
    fn lookup(&self, i: usize) -> i32 {
        let (c, f) = (i >> COARSE_BITS, (i & 63) as u16);
        if let Some(k) = self.exact_c[..self.n_exact].iter().position(|&e| e as usize == c) {
            let q = self.exact[k][f as usize];
            return if q == EXACT_RESOLVE { RESOLVE } else { q as i32 };
        }
        if f == self.res[c] {
            return RESOLVE;
        }
        self.base[c] as i32 + if f >= self.thr[c] { self.delta[c] as i32 } else { 0 }
    }

    /// Number of coarse buckets that need an exact table.
    pub fn exact_buckets(&self) -> usize {
        self.n_exact
    }

    /// Whether the byte form exists (every offset in [-127, 127]).
    pub fn has_bytes(&self) -> bool {
        self.bytes.is_some()
    }

    /// Whether the byte form has the two-lookup step form (uniform steps).
    pub fn has_step_form(&self) -> bool {
        self.bytes.as_ref().is_some_and(|b| b.step.is_some())
    }
}

/// A noise table (`1 << bits` integer DN offsets, [`RESOLVE`] entries) with its two-level
/// form, built once per parameter change.
#[derive(Default)]
pub struct NoiseTable {
    // allocation: once per parameter change
    entries: Vec<i32>,
    bits: u32,
    two_level: Option<Box<TwoLevel>>,
}

impl NoiseTable {
    /// Rebuild from `1 << bits` entries (`bits <= 16`).
    pub fn rebuild(&mut self, bits: u32, entries: impl IntoIterator<Item = i32>) {
        self.entries.clear();
        self.entries.extend(entries);
        self.bits = bits;
        assert!(
            bits <= 16 && self.entries.len() == 1 << bits,
            "noise table: {} entries for {bits} bits",
            self.entries.len()
        );
        self.two_level = TwoLevel::compile(&self.entries, bits).map(Box::new);
    }
    /// The entries.
    pub fn entries(&self) -> &[i32] {
        &self.entries
    }
    /// Index bits.
    pub fn bits(&self) -> u32 {
        self.bits
    }
    /// The two-level form, when the table has one.
    pub fn two_level(&self) -> Option<&TwoLevel> {
        self.two_level.as_deref()
    }
}

/// Add table noise to `row` (see the module documentation).
pub fn add_table_noise<T: Sample>(
    row: &mut [T],
    lanes: &mut RngLanes,
    table: &NoiseTable,
    resolve: &mut dyn FnMut(usize) -> i32,
) {
    let bits = table.bits;
    let entries = &table.entries[..];
    if entries.len() != 1 << bits || bits > 16 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    {
        if let Some(t) = table.two_level.as_deref()
            && has_avx2()
            && let Some(bytes) = T::bytes_mut(row)
        {
            match &t.bytes {
                // SAFETY: the CPU supports AVX-512 F/BW/VL/VBMI (checked).
                Some(b) if has_avx512_vbmi() => unsafe {
                    avx512::add_byte_form(bytes, lanes, b, t.n_exact, entries, bits, resolve)
                },
                // SAFETY: the CPU supports AVX-512 F/BW/VL (checked just above).
                _ if has_avx512() => unsafe { avx512::add_two_level(bytes, lanes, t, entries, bits, resolve) },
                // SAFETY: the CPU supports AVX2 (checked above).
                Some(b) => unsafe {
                    match &b.step {
                        Some(st) => avx2::add_step_form(bytes, lanes, st, b, t.n_exact, entries, bits, resolve),
                        None => avx2::add_byte_form(bytes, lanes, b, t.n_exact, entries, bits, resolve),
                    }
                },
                // SAFETY: the CPU supports AVX2 (checked above); the table length was checked.
                None => unsafe { avx2::add_table_noise(bytes, lanes, entries, bits, resolve) },
            }
            return;
        }
        if has_avx2() {
            // SAFETY: the CPU supports AVX2 (checked just above); the table length was checked.
            unsafe { avx2::add_table_noise(row, lanes, entries, bits, resolve) };
            return;
        }
    }
    add_table_noise_scalar(row, lanes, entries, bits, resolve)
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

/// 8-bit samples still to resolve (position in the row, table index), in sample order; fixed
/// capacity (no allocation). Used by the two-level SIMD kernels.
#[cfg(target_arch = "x86_64")]
struct Lanes {
    pos: [u32; 64],
    idx: [u16; 64],
    len: usize,
}

#[cfg(target_arch = "x86_64")]
impl Lanes {
    fn new() -> Lanes {
        Lanes { pos: [0; 64], idx: [0; 64], len: 0 }
    }

    /// List the lanes set in `mask`, in order: sample `base + j`, table index `ix[j]`'s low
    /// 12 bits (resolving the list first when it is full).
    #[inline]
    fn push_mask(
        &mut self,
        mut mask: u64,
        base: usize,
        ix: &[u16],
        row: &mut [u8],
        resolve: &mut dyn FnMut(usize) -> i32,
    ) {
        while mask != 0 {
            let j = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            if self.len == self.pos.len() {
                self.flush(row, resolve);
            }
            self.pos[self.len] = (base + j) as u32;
            self.idx[self.len] = ix[j] & 0x0fff;
            self.len += 1;
        }
    }

    /// Resolve the listed samples in order (they still hold their input value).
    #[cold]
    fn flush(&mut self, row: &mut [u8], resolve: &mut dyn FnMut(usize) -> i32) {
        for (&p, &i) in self.pos[..self.len].iter().zip(&self.idx[..self.len]) {
            let v = &mut row[p as usize];
            *v = (*v as i32).saturating_add(resolve(i as usize)).clamp(0, 255) as u8;
        }
        self.len = 0;
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::{BYTE_RESOLVE, ByteForm, Lanes, MAX_EXACT, RESOLVE, RngLanes, Sample, StepForm};
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

    /// `table[idx[j]]` for the eight lanes, by eight scalar loads instead of `vpgatherdd`
    /// (microcoded and slow on many AMD cores, and on Intel cores with the GDS mitigation).
    ///
    /// # Safety
    /// AVX2 context; every lane of `idx` is a valid index of `table`.
    #[inline(always)]
    pub(crate) unsafe fn lookup8(table: &[i32], idx: __m256i) -> __m256i {
        let mut ix = [0u32; 8];
        // SAFETY: eight u32 = 32 bytes; unaligned store. The caller guarantees the indices.
        unsafe {
            _mm256_storeu_si256(ix.as_mut_ptr() as *mut __m256i, idx);
            debug_assert!(ix.iter().all(|&i| (i as usize) < table.len()));
            let t = |j: usize| *table.get_unchecked(ix[j] as usize);
            _mm256_setr_epi32(t(0), t(1), t(2), t(3), t(4), t(5), t(6), t(7))
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
            let (mut q_lo, mut q_hi) = unsafe { (lookup8(table, i_lo), lookup8(table, i_hi)) };
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

    /// A 64-entry byte table as four 16-entry quarters, each repeated in both 128-bit halves
    /// (the operands of `vpshufb`).
    #[inline(always)]
    fn quarters<E>(t: &[E; 64]) -> [__m256i; 4] {
        assert_eq!(size_of::<E>(), 1);
        // SAFETY: 64 one-byte entries; 16-byte unaligned loads (AVX2 context only).
        std::array::from_fn(|q| unsafe {
            _mm256_broadcastsi128_si256(_mm_loadu_si128((t.as_ptr() as *const u8).add(16 * q) as *const __m128i))
        })
    }

    /// Fine (bits 0..5) and coarse (bits 6..11) index of 32 samples (16-bit elements, samples
    /// 0..16 in `r0`, 16..32 in `r1`) as bytes; `packus` interleaves the 128-bit halves: byte
    /// order s0-7, s16-23, s8-15, s24-31.
    #[inline(always)]
    fn fine_coarse(r0: __m256i, r1: __m256i) -> (__m256i, __m256i) {
        // SAFETY: AVX2 context only (inlined into the AVX2 byte-form kernels).
        unsafe {
            let m3f = _mm256_set1_epi16(0x3f);
            let f = _mm256_packus_epi16(_mm256_and_si256(r0, m3f), _mm256_and_si256(r1, m3f));
            let c = _mm256_packus_epi16(
                _mm256_and_si256(_mm256_srli_epi16::<6>(r0), m3f),
                _mm256_and_si256(_mm256_srli_epi16::<6>(r1), m3f),
            );
            (f, c)
        }
    }

    /// Bit 4 and bit 5 of every byte of `i` moved to bit 7 (the `vpblendvb` selectors of
    /// [`lookup64`]).
    #[inline(always)]
    fn selectors(i: __m256i) -> (__m256i, __m256i) {
        // SAFETY: AVX2 context only. The 16-bit shifts move no set bit across a byte's bit 7
        // that matters: only bit 7 of each byte is read.
        unsafe { (_mm256_slli_epi16::<3>(i), _mm256_slli_epi16::<2>(i)) }
    }

    /// `t[i]` for every byte `i` in 0..64: four in-register `vpshufb` lookups (low four bits)
    /// and two blends on bits 4 and 5. No memory access.
    #[inline(always)]
    fn lookup64(t: &[__m256i; 4], i: __m256i, (s4, s5): (__m256i, __m256i)) -> __m256i {
        // SAFETY: AVX2 context only; bytes of `i` are below 64 (bit 7 clear: no zeroing).
        unsafe {
            let a = _mm256_blendv_epi8(_mm256_shuffle_epi8(t[0], i), _mm256_shuffle_epi8(t[1], i), s4);
            let b = _mm256_blendv_epi8(_mm256_shuffle_epi8(t[2], i), _mm256_shuffle_epi8(t[3], i), s4);
            _mm256_blendv_epi8(a, b, s5)
        }
    }

    /// [`super::add_table_noise`] for 8-bit samples and a table with the byte form of its
    /// two-level form (`bits` = 12), with AVX2 and no gathers: 32 samples per step, each offset
    /// computed from in-register byte shuffles (`vpshufb` over 16-entry quarters of the 64-entry
    /// coarse tables), a compare for the step and saturating byte arithmetic. The same bytes as
    /// the reference (and as the AVX-512 `add_byte_form`).
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn add_byte_form(
        row: &mut [u8],
        lanes: &mut RngLanes,
        t: &ByteForm,
        n_exact: usize,
        entries: &[i32],
        bits: u32,
        resolve: &mut dyn FnMut(usize) -> i32,
    ) {
        debug_assert_eq!(bits, 12);
        let mut s = load_state(lanes);
        let (base, thr, delta, res) = (quarters(&t.base), quarters(&t.thr), quarters(&t.delta), quarters(&t.res));
        let n_exact = n_exact.min(MAX_EXACT);
        let exact: [(__m256i, [__m256i; 4]); MAX_EXACT] =
            std::array::from_fn(|k| (_mm256_set1_epi8(t.exact_c[k] as i8), quarters(&t.exact[k])));
        let sentinel = _mm256_set1_epi8(BYTE_RESOLVE);
        let zero = _mm256_setzero_si256();
        let mut pending = Lanes::new();
        let n32 = row.len() / 32 * 32;
        for bi in 0..n32 / 32 {
            // Samples 0..16 in r0, 16..32 in r1 (16-bit elements, the scalar order).
            let (r0, r1) = (next4(&mut s), next4(&mut s));
            let (f, c) = fine_coarse(r0, r1);
            let sc = selectors(c);
            let mut val = lookup64(&base, c, sc);
            // f >= thr[c] (unsigned): max(f, thr) == f; thr 64 never.
            let thr_c = lookup64(&thr, c, sc);
            let step = _mm256_cmpeq_epi8(_mm256_max_epu8(f, thr_c), f);
            val = _mm256_add_epi8(val, _mm256_and_si256(step, lookup64(&delta, c, sc)));
            let mut m_res = _mm256_cmpeq_epi8(f, lookup64(&res, c, sc));
            if n_exact > 0 {
                let sf = selectors(f);
                for (ec, tab) in &exact[..n_exact] {
                    let mk = _mm256_cmpeq_epi8(c, *ec);
                    val = _mm256_blendv_epi8(val, lookup64(tab, f, sf), mk);
                }
            }
            m_res = _mm256_or_si256(m_res, _mm256_cmpeq_epi8(val, sentinel));
            // Back to sample order.
            let mut val = _mm256_permute4x64_epi64::<0b11_01_10_00>(val);
            let m_res = _mm256_permute4x64_epi64::<0b11_01_10_00>(m_res);
            let bits_res = _mm256_movemask_epi8(m_res) as u32;
            if bits_res != 0 {
                // Lanes to resolve: left unchanged now (offset 0), resolved in sample order
                // after the loop (or when the list is full), from the sample itself.
                let mut ix = [0u16; 32];
                // SAFETY: 32 u16 = 64 bytes; unaligned stores.
                unsafe {
                    _mm256_storeu_si256(ix.as_mut_ptr() as *mut __m256i, r0);
                    _mm256_storeu_si256(ix.as_mut_ptr().add(16) as *mut __m256i, r1);
                }
                pending.push_mask(bits_res as u64, bi * 32, &ix, row, resolve);
                val = _mm256_andnot_si256(m_res, val);
            }
            // SAFETY: 32 bytes at 32·bi lie inside the row (bi < n32 / 32); unaligned access.
            unsafe {
                let p = row.as_mut_ptr().add(bi * 32) as *mut __m256i;
                let v = _mm256_loadu_si256(p);
                // v + val clipped to [0, 255] (|val| <= 127): add the positive part, subtract
                // the negative one, both saturating.
                let pos = _mm256_max_epi8(val, zero);
                let neg = _mm256_sub_epi8(pos, val);
                _mm256_storeu_si256(p, _mm256_subs_epu8(_mm256_adds_epu8(v, pos), neg));
            }
        }
        pending.flush(row, resolve);
        store_state(lanes, &s);
        if n32 < row.len() {
            super::add_table_noise_scalar(&mut row[n32..], lanes, entries, bits, resolve);
        }
    }

    /// [`add_byte_form`] for a table with the step form: two coarse lookups (base, and the step
    /// position with its resolve flag) instead of four, specialised on the number of exact
    /// buckets and on whether any simple bucket resolves. The same bytes.
    ///
    /// # Safety
    /// The CPU supports AVX2; `n_exact` is the byte form's.
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn add_step_form(
        row: &mut [u8],
        lanes: &mut RngLanes,
        st: &StepForm,
        b: &ByteForm,
        n_exact: usize,
        entries: &[i32],
        bits: u32,
        resolve: &mut dyn FnMut(usize) -> i32,
    ) {
        // SAFETY (every arm): the caller guarantees AVX2.
        unsafe {
            match (n_exact, st.any_res) {
                (0, false) => step_form::<0, false>(row, lanes, st, b, entries, bits, resolve),
                (0, true) => step_form::<0, true>(row, lanes, st, b, entries, bits, resolve),
                (1, false) => step_form::<1, false>(row, lanes, st, b, entries, bits, resolve),
                (1, true) => step_form::<1, true>(row, lanes, st, b, entries, bits, resolve),
                (2, false) => step_form::<2, false>(row, lanes, st, b, entries, bits, resolve),
                (2, true) => step_form::<2, true>(row, lanes, st, b, entries, bits, resolve),
                (3, false) => step_form::<3, false>(row, lanes, st, b, entries, bits, resolve),
                (3, true) => step_form::<3, true>(row, lanes, st, b, entries, bits, resolve),
                (4, false) => step_form::<4, false>(row, lanes, st, b, entries, bits, resolve),
                (4, true) => step_form::<4, true>(row, lanes, st, b, entries, bits, resolve),
                _ => add_byte_form(row, lanes, b, n_exact, entries, bits, resolve),
            }
        }
    }

    /// [`add_step_form`] with `N` exact buckets; `RES`: some simple bucket resolves an entry.
    #[target_feature(enable = "avx2")]
    unsafe fn step_form<const N: usize, const RES: bool>(
        row: &mut [u8],
        lanes: &mut RngLanes,
        st: &StepForm,
        b: &ByteForm,
        entries: &[i32],
        bits: u32,
        resolve: &mut dyn FnMut(usize) -> i32,
    ) {
        debug_assert_eq!(bits, 12);
        let mut s = load_state(lanes);
        let (base, thr) = (quarters(&st.base), quarters(&st.thr));
        let exact: [(__m256i, [__m256i; 4]); N] =
            std::array::from_fn(|k| (_mm256_set1_epi8(b.exact_c[k] as i8), quarters(&b.exact[k])));
        let delta = _mm256_set1_epi8(st.delta);
        let (one, low7, flag) = (_mm256_set1_epi8(1), _mm256_set1_epi8(0x7f), _mm256_set1_epi8(-128));
        let sentinel = _mm256_set1_epi8(BYTE_RESOLVE);
        let zero = _mm256_setzero_si256();
        let mut pending = Lanes::new();
        // With entries to resolve in simple buckets (about one step in eight has a lane to
        // resolve for the Poisson tables), the steps are recorded without a branch instead.
        let mut rec = Records::new();
        let n32 = row.len() / 32 * 32;
        for bi in 0..n32 / 32 {
            // Samples 0..16 in r0, 16..32 in r1 (16-bit elements, the scalar order).
            let (r0, r1) = (next4(&mut s), next4(&mut s));
            let (f, c) = fine_coarse(r0, r1);
            let sc = selectors(c);
            let t = lookup64(&thr, c, sc);
            // f >= thr <=> f + 1 > thr, signed bytes (both in 0..=64 without the flag bit).
            let f1 = _mm256_add_epi8(f, one);
            let (step, mut m_res) = if RES {
                let step = _mm256_cmpgt_epi8(f1, _mm256_and_si256(t, low7));
                // Flag set and f + 1 == thr.
                (step, _mm256_cmpeq_epi8(_mm256_or_si256(f1, flag), t))
            } else {
                (_mm256_cmpgt_epi8(f1, t), zero)
            };
            let mut val = _mm256_add_epi8(lookup64(&base, c, sc), _mm256_and_si256(step, delta));
            if N > 0 {
                let sf = selectors(f);
                for (ec, tab) in &exact {
                    let mk = _mm256_cmpeq_epi8(c, *ec);
                    val = _mm256_blendv_epi8(val, lookup64(tab, f, sf), mk);
                }
                m_res = _mm256_or_si256(m_res, _mm256_cmpeq_epi8(val, sentinel));
            }
            if RES {
                // Lanes to resolve: left unchanged now (offset 0); this step is recorded (kept
                // when some lane resolves) and resolved in sample order when the list is full
                // or after the loop, from the sample itself.
                let packed = _mm256_movemask_epi8(m_res) as u32;
                let k = rec.len;
                rec.mask[k] = packed;
                rec.at[k] = bi as u32;
                // SAFETY: 32 u16 = 64 bytes; unaligned stores.
                unsafe {
                    _mm256_storeu_si256(rec.ix[k].as_mut_ptr() as *mut __m256i, r0);
                    _mm256_storeu_si256(rec.ix[k].as_mut_ptr().add(16) as *mut __m256i, r1);
                }
                rec.len = k + (packed != 0) as usize;
                if rec.len == RECORDS {
                    rec.flush(row, resolve);
                }
                val = _mm256_andnot_si256(m_res, val);
            } else if N > 0 {
                let packed = _mm256_movemask_epi8(m_res) as u32;
                if packed != 0 {
                    // Lanes to resolve: left unchanged now (offset 0), resolved in sample order
                    // after the loop (or when the list is full), from the sample itself. The
                    // mask's bytes 8..16 and 16..24 swap back to sample order.
                    let in_order =
                        (packed & 0xff00_00ff) | ((packed & 0x0000_ff00) << 8) | ((packed & 0x00ff_0000) >> 8);
                    let mut ix = [0u16; 32];
                    // SAFETY: 32 u16 = 64 bytes; unaligned stores.
                    unsafe {
                        _mm256_storeu_si256(ix.as_mut_ptr() as *mut __m256i, r0);
                        _mm256_storeu_si256(ix.as_mut_ptr().add(16) as *mut __m256i, r1);
                    }
                    pending.push_mask(in_order as u64, bi * 32, &ix, row, resolve);
                    val = _mm256_andnot_si256(m_res, val);
                }
            }
            // Back to sample order.
            let val = _mm256_permute4x64_epi64::<0b11_01_10_00>(val);
            // SAFETY: 32 bytes at 32·bi lie inside the row (bi < n32 / 32); unaligned access.
            unsafe {
                let p = row.as_mut_ptr().add(bi * 32) as *mut __m256i;
                let v = _mm256_loadu_si256(p);
                // v + val clipped to [0, 255] (|val| <= 127): add the positive part, subtract
                // the negative one, both saturating.
                // v + val clipped to [0, 255] (|val| <= 127): v - 128 as a signed byte, a signed
                // saturating add, + 128 back.
                _mm256_storeu_si256(p, _mm256_xor_si256(_mm256_adds_epi8(_mm256_xor_si256(v, flag), val), flag));
            }
        }
        rec.flush(row, resolve);
        pending.flush(row, resolve);
        store_state(lanes, &s);
        if n32 < row.len() {
            super::add_table_noise_scalar(&mut row[n32..], lanes, entries, bits, resolve);
        }
    }

    /// Steps recorded by [`step_form`] with `RES`.
    const RECORDS: usize = 16;

    /// Steps of 32 samples with lanes to resolve (fixed capacity, no allocation): the sample
    /// indices, the `packus`-order lane mask and the step number.
    struct Records {
        ix: [[u16; 32]; RECORDS],
        mask: [u32; RECORDS],
        at: [u32; RECORDS],
        len: usize,
    }

    impl Records {
        fn new() -> Records {
            Records { ix: [[0; 32]; RECORDS], mask: [0; RECORDS], at: [0; RECORDS], len: 0 }
        }

        /// Resolve the recorded lanes in sample order (they still hold their input value).
        #[inline(never)]
        fn flush(&mut self, row: &mut [u8], resolve: &mut dyn FnMut(usize) -> i32) {
            for k in 0..self.len {
                let packed = self.mask[k];
                // Bytes 8..16 and 16..24 of the mask swap back to sample order.
                let mut m = (packed & 0xff00_00ff) | ((packed & 0x0000_ff00) << 8) | ((packed & 0x00ff_0000) >> 8);
                let base = self.at[k] as usize * 32;
                while m != 0 {
                    let j = m.trailing_zeros() as usize;
                    m &= m - 1;
                    let v = &mut row[base + j];
                    *v = (*v as i32).saturating_add(resolve((self.ix[k][j] & 0x0fff) as usize)).clamp(0, 255) as u8;
                }
            }
            self.len = 0;
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

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::avx2::{load_state, store_state};
    use super::{BYTE_RESOLVE, ByteForm, EXACT_RESOLVE, Lanes, MAX_EXACT, RngLanes, TwoLevel};
    use std::arch::x86_64::*;

    /// One xoshiro256++ step of the four lanes (as `RngLanes::next4`), with AVX-512VL rotates.
    #[inline(always)]
    fn next4(s: &mut [__m256i; 4]) -> __m256i {
        // SAFETY: only inlined into `add_two_level`, which enables AVX-512 F/VL.
        unsafe {
            let out = _mm256_add_epi64(_mm256_rol_epi64::<23>(_mm256_add_epi64(s[0], s[3])), s[0]);
            let t = _mm256_slli_epi64::<17>(s[1]);
            s[2] = _mm256_xor_si256(s[2], s[0]);
            s[3] = _mm256_xor_si256(s[3], s[1]);
            s[1] = _mm256_xor_si256(s[1], s[2]);
            s[0] = _mm256_xor_si256(s[0], s[3]);
            s[2] = _mm256_xor_si256(s[2], t);
            s[3] = _mm256_rol_epi64::<45>(s[3]);
            out
        }
    }

    /// A 64-entry word table as two registers (the operands of `vpermi2w`).
    #[inline(always)]
    fn pair<E>(t: &[E; 64]) -> (__m512i, __m512i) {
        assert_eq!(size_of::<E>(), 2);
        // SAFETY: 64 two-byte entries = 128 bytes; unaligned loads (AVX-512F context only).
        unsafe {
            let p = t.as_ptr() as *const __m512i;
            (_mm512_loadu_si512(p), _mm512_loadu_si512(p.add(1)))
        }
    }

    /// [`super::add_table_noise`] for 8-bit samples and a table with a two-level form
    /// (`bits` = 12): 32 samples per step, offsets computed in registers.
    #[target_feature(enable = "avx512f,avx512bw,avx512vl")]
    pub unsafe fn add_two_level(
        row: &mut [u8],
        lanes: &mut RngLanes,
        t: &TwoLevel,
        entries: &[i32],
        bits: u32,
        resolve: &mut dyn FnMut(usize) -> i32,
    ) {
        debug_assert_eq!(bits, 12);
        let mut s = load_state(lanes);
        let (base_lo, base_hi) = pair(&t.base);
        let (thr_lo, thr_hi) = pair(&t.thr);
        let (delta_lo, delta_hi) = pair(&t.delta);
        let (res_lo, res_hi) = pair(&t.res);
        let n_exact = t.n_exact.min(MAX_EXACT);
        let exact: [(__m512i, __m512i, __m512i); MAX_EXACT] = std::array::from_fn(|k| {
            let (lo, hi) = pair(&t.exact[k]);
            (_mm512_set1_epi16(t.exact_c[k] as i16), lo, hi)
        });
        let idx_mask = _mm512_set1_epi16(0x0fff);
        let fine_mask = _mm512_set1_epi16(0x003f);
        let sentinel = _mm512_set1_epi16(EXACT_RESOLVE);
        let zero = _mm512_setzero_si512();
        let mut pending = Lanes::new();
        let n32 = row.len() / 32 * 32;
        for bi in 0..n32 / 32 {
            let r0 = next4(&mut s);
            let r1 = next4(&mut s);
            // Sample j of the 32 is 16-bit element j (the scalar order: r0 then r1).
            let u = _mm512_inserti64x4::<1>(_mm512_castsi256_si512(r0), r1);
            let idx = _mm512_and_si512(u, idx_mask);
            let c = _mm512_srli_epi16::<6>(idx);
            let f = _mm512_and_si512(idx, fine_mask);
            let mut val = _mm512_permutex2var_epi16(base_lo, c, base_hi);
            let step = _mm512_cmpge_epu16_mask(f, _mm512_permutex2var_epi16(thr_lo, c, thr_hi));
            val = _mm512_mask_add_epi16(val, step, val, _mm512_permutex2var_epi16(delta_lo, c, delta_hi));
            let mut m_res = _mm512_cmpeq_epi16_mask(f, _mm512_permutex2var_epi16(res_lo, c, res_hi));
            for &(ec, lo, hi) in &exact[..n_exact] {
                let mk = _mm512_cmpeq_epi16_mask(c, ec);
                val = _mm512_mask_mov_epi16(val, mk, _mm512_permutex2var_epi16(lo, f, hi));
            }
            m_res |= _mm512_cmpeq_epi16_mask(val, sentinel);
            if m_res != 0 {
                // Lanes to resolve: left unchanged now (offset 0), resolved in sample order
                // after the loop (or when the list is full), from the sample itself.
                let mut ix = [0u16; 32];
                // SAFETY: 32 u16 = 64 bytes; unaligned store.
                unsafe { _mm512_storeu_si512(ix.as_mut_ptr() as *mut __m512i, idx) };
                pending.push_mask(m_res as u64, bi * 32, &ix, row, resolve);
                val = _mm512_maskz_mov_epi16(!m_res, val);
            }
            // SAFETY: 32 bytes at 32·bi lie inside the row (bi < n32 / 32); unaligned access.
            unsafe {
                let p = row.as_mut_ptr().add(bi * 32) as *mut __m256i;
                let v = _mm512_cvtepu8_epi16(_mm256_loadu_si256(p));
                // |val| <= 16384: no saturation; clip to [0, 255] as the reference.
                let sum = _mm512_max_epi16(_mm512_adds_epi16(v, val), zero);
                _mm256_storeu_si256(p, _mm512_cvtusepi16_epi8(sum));
            }
        }
        pending.flush(row, resolve);
        store_state(lanes, &s);
        if n32 < row.len() {
            super::add_table_noise_scalar(&mut row[n32..], lanes, entries, bits, resolve);
        }
    }
    /// A 64-entry byte table as one register (the operand of `vpermb`).
    #[inline(always)]
    fn table8<E>(t: &[E; 64]) -> __m512i {
        assert_eq!(size_of::<E>(), 1);
        // SAFETY: 64 one-byte entries; unaligned load (AVX-512F context only).
        unsafe { _mm512_loadu_si512(t.as_ptr() as *const __m512i) }
    }

    /// Even bytes (the low byte of each 16-bit element) of `a` then `b`, in order.
    const fn byte_select(high: bool) -> [u8; 64] {
        let mut t = [0u8; 64];
        let mut j = 0;
        while j < 64 {
            t[j] = (2 * j + high as usize) as u8;
            j += 1;
        }
        t
    }
    const LOW_BYTES: [u8; 64] = byte_select(false);
    const HIGH_BYTES: [u8; 64] = byte_select(true);

    /// [`add_two_level`] with the byte form: 64 samples per step, offsets from single-register
    /// byte permutes, saturating byte arithmetic.
    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub unsafe fn add_byte_form(
        row: &mut [u8],
        lanes: &mut RngLanes,
        t: &ByteForm,
        n_exact: usize,
        entries: &[i32],
        bits: u32,
        resolve: &mut dyn FnMut(usize) -> i32,
    ) {
        debug_assert_eq!(bits, 12);
        let mut s = load_state(lanes);
        let (base, thr, delta, res) = (table8(&t.base), table8(&t.thr), table8(&t.delta), table8(&t.res));
        let n_exact = n_exact.min(MAX_EXACT);
        let exact: [(__m512i, __m512i); MAX_EXACT] =
            std::array::from_fn(|k| (_mm512_set1_epi8(t.exact_c[k] as i8), table8(&t.exact[k])));
        let (lo_sel, hi_sel) = (table8(&LOW_BYTES), table8(&HIGH_BYTES));
        let (m03, m3c, m3f) = (_mm512_set1_epi8(0x03), _mm512_set1_epi8(0x3c), _mm512_set1_epi8(0x3f));
        let sentinel = _mm512_set1_epi8(BYTE_RESOLVE);
        let zero = _mm512_setzero_si512();
        let mut pending = Lanes::new();
        let n64 = row.len() / 64 * 64;
        for bi in 0..n64 / 64 {
            // Samples 0..32 in u0, 32..64 in u1 (16-bit elements, the scalar order).
            let u0 = _mm512_inserti64x4::<1>(_mm512_castsi256_si512(next4(&mut s)), next4(&mut s));
            let u1 = _mm512_inserti64x4::<1>(_mm512_castsi256_si512(next4(&mut s)), next4(&mut s));
            // Index bits 0..5 (fine) and 6..11 (coarse) of each sample, as bytes in order.
            let lo = _mm512_permutex2var_epi8(u0, lo_sel, u1);
            let hi = _mm512_permutex2var_epi8(u0, hi_sel, u1);
            let f = _mm512_and_si512(lo, m3f);
            let c = _mm512_or_si512(
                _mm512_and_si512(_mm512_srli_epi16::<6>(lo), m03),
                _mm512_and_si512(_mm512_slli_epi16::<2>(hi), m3c),
            );
            let mut val = _mm512_permutexvar_epi8(c, base);
            let step = _mm512_cmpge_epu8_mask(f, _mm512_permutexvar_epi8(c, thr));
            val = _mm512_mask_add_epi8(val, step, val, _mm512_permutexvar_epi8(c, delta));
            let mut m_res = _mm512_cmpeq_epi8_mask(f, _mm512_permutexvar_epi8(c, res));
            for &(ec, tab) in &exact[..n_exact] {
                let mk = _mm512_cmpeq_epi8_mask(c, ec);
                val = _mm512_mask_mov_epi8(val, mk, _mm512_permutexvar_epi8(f, tab));
            }
            m_res |= _mm512_cmpeq_epi8_mask(val, sentinel);
            if m_res != 0 {
                // Lanes to resolve: left unchanged now (offset 0), resolved in sample order
                // after the loop (or when the list is full), from the sample itself.
                let mut ix = [0u16; 64];
                // SAFETY: 64 u16 = 128 bytes; unaligned stores.
                unsafe {
                    _mm512_storeu_si512(ix.as_mut_ptr() as *mut __m512i, u0);
                    _mm512_storeu_si512(ix.as_mut_ptr().add(32) as *mut __m512i, u1);
                }
                pending.push_mask(m_res, bi * 64, &ix, row, resolve);
                val = _mm512_maskz_mov_epi8(!m_res, val);
            }
            // SAFETY: 64 bytes at 64·bi lie inside the row (bi < n64 / 64); unaligned access.
            unsafe {
                let p = row.as_mut_ptr().add(bi * 64) as *mut __m512i;
                let v = _mm512_loadu_si512(p);
                // v + val clipped to [0, 255]: add the positive part, subtract the negative one.
                let pos = _mm512_max_epi8(val, zero);
                let neg = _mm512_sub_epi8(pos, val);
                _mm512_storeu_si512(p, _mm512_subs_epu8(_mm512_adds_epu8(v, pos), neg));
            }
        }
        pending.flush(row, resolve);
        store_state(lanes, &s);
        if n64 < row.len() {
            super::add_table_noise_scalar(&mut row[n64..], lanes, entries, bits, resolve);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// The dispatched kernel (whatever this CPU runs) against the scalar reference on rows of
    /// every length class, with the resolve calls in the same order.
    /// A noise kernel under test: row, lanes, table, resolve.
    type Kernel<'a, T> = dyn Fn(&mut [T], &mut RngLanes, &NoiseTable, &mut dyn FnMut(usize) -> i32) + 'a;

    fn compare<T: Sample + std::fmt::Debug + PartialEq>(table: &NoiseTable, max: u32, r: &mut Rng) {
        compare_kernel::<T>(table, max, r, &|row, lanes, t, res| add_table_noise(row, lanes, t, res));
        // The gather-free AVX2 kernel directly, whatever faster kernel this CPU also has.
        #[cfg(target_arch = "x86_64")]
        if has_avx2()
            && T::MAX_U32 == 255
            && let Some(tl) = table.two_level()
            && let Some(b) = &tl.bytes
        {
            compare_kernel::<T>(table, max, r, &|row, lanes, t, res| {
                let bytes = T::bytes_mut(row).expect("8-bit rows only");
                // SAFETY: the CPU supports AVX2 (checked above).
                unsafe { avx2::add_byte_form(bytes, lanes, b, tl.n_exact, t.entries(), t.bits(), res) }
            });
            // And the two-lookup kernel of the step form, when the table has one.
            if let Some(st) = &b.step {
                compare_kernel::<T>(table, max, r, &|row, lanes, t, res| {
                    let bytes = T::bytes_mut(row).expect("8-bit rows only");
                    // SAFETY: the CPU supports AVX2 (checked above); `n_exact` is the form's.
                    unsafe { avx2::add_step_form(bytes, lanes, st, b, tl.n_exact, t.entries(), t.bits(), res) }
                });
            }
        }
    }

    /// `kernel` against the scalar reference on rows of every length class, with the resolve
    /// calls in the same order.
    fn compare_kernel<T: Sample + std::fmt::Debug + PartialEq>(
        table: &NoiseTable,
        max: u32,
        r: &mut Rng,
        kernel: &Kernel<'_, T>,
    ) {
        let bits = table.bits();
        for n in [0usize, 1, 15, 16, 17, 31, 32, 33, 63, 64, 65, 100, 1921, 5760] {
            let row: Vec<T> = (0..n).map(|_| T::from_u32_sat(r.below(max as u64 + 1) as u32)).collect();
            let seed = Rng::new(n as u64 + bits as u64);
            let (mut a, mut b) = (row.clone(), row.clone());
            let (mut la, mut lb) = (RngLanes::new(&seed), RngLanes::new(&seed));
            let (mut ra, mut rb) = (Rng::new(9), Rng::new(9));
            let (mut ca, mut cb) = (Vec::new(), Vec::new());
            add_table_noise_scalar(&mut a, &mut la, table.entries(), bits, &mut |i| {
                ca.push(i);
                ra.below(41) as i32 - 20
            });
            kernel(&mut b, &mut lb, table, &mut |i| {
                cb.push(i);
                rb.below(41) as i32 - 20
            });
            assert_eq!(a, b, "bits {bits}, {n} samples");
            assert_eq!(ca, cb, "resolve calls in the same order");
            // Both continue the same stream.
            assert_eq!(la.next4(), lb.next4());
        }
    }

    fn check<T: Sample + std::fmt::Debug + PartialEq>(max: u32) {
        let mut r = Rng::new(3);
        // Sparse entries to resolve (the usual case) and dense ones (many pending chunks per row,
        // so the fix-up list fills and flushes mid-row).
        for (bits, every) in [(12u32, 997usize), (16, 997), (12, 7)] {
            // Offsets of either sign and size (clipping at both ends), some entries to resolve.
            let entries: Vec<i32> = (0..1usize << bits)
                .map(|i| {
                    if i % every == 5 { RESOLVE } else { (r.below(2 * max as u64 + 1) as i64 - max as i64) as i32 / 3 }
                })
                .collect();
            let mut table = NoiseTable::default();
            table.rebuild(bits, entries);
            assert!(table.two_level().is_none(), "a random table has no two-level form");
            compare::<T>(&table, max, &mut r);
        }
    }

    #[test]
    fn fast_path_equals_the_scalar_reference() {
        check::<u8>(255);
        check::<u16>(65535);
    }

    /// The tables of `gaussian_noise` and `dark_current` at typical settings have the two-level
    /// form (so the AVX-512 kernel runs them), and every kernel gives the reference's bytes.
    #[test]
    fn two_level_form_is_exact_for_the_effect_tables() {
        let mut r = Rng::new(11);
        let normal = crate::faults::gaussian_noise::conditional_mean_table();
        // Up to sigma 7 DN the form exists; at 20 DN the tails step too often (AVX2 gathers).
        // The gaussian_noise table (outer buckets resolved) of `entry(conditional mean)`.
        let table = |entry: &dyn Fn(f64) -> i32| {
            let mut t = NoiseTable::default();
            let last = normal.len() - 1;
            t.rebuild(
                12,
                normal.iter().enumerate().map(|(i, &m)| if i == 0 || i == last { RESOLVE } else { entry(m) }),
            );
            t
        };
        for sigma in [0.3, 1.0, 3.0, 4.0, 5.0, 6.0, 7.0, 20.0] {
            let t = table(&|m| (sigma * m + 0.5).floor() as i32);
            // The chain's setting (original8.toml) has the two-lookup step form.
            if sigma == 3.0 {
                assert!(t.two_level().is_some_and(|tl| tl.has_step_form()), "gaussian sigma 3: no step form");
            }
            match t.two_level() {
                Some(tl) => assert!(sigma <= 7.0 && tl.exact_buckets() <= MAX_EXACT && tl.has_bytes()),
                None => assert!(sigma > 7.0, "gaussian sigma {sigma}: no two-level form"),
            }
            compare::<u8>(&t, 255, &mut r);
            compare::<u16>(&t, 65535, &mut r);
        }
        let mut poisson = crate::faults::dark_current::PoissonTable::default();
        for (lambda, dn_per_e) in [(0.5, 1.0), (4.95, 1.0), (10.0, 1.0), (5.0, 2.5), (20.0, 0.4)] {
            poisson.prepare(lambda, dn_per_e);
            let t = poisson.noise_table();
            if t.bits() == 12 {
                assert!(t.two_level().is_some(), "poisson lambda {lambda}: no two-level form");
            }
            // The chain's setting (original8.toml: lambda = 4.95 e-, 1 DN per e-).
            if dn_per_e == 1.0 && lambda < 5.0 && lambda > 4.9 {
                assert!(t.two_level().is_some_and(|tl| tl.has_step_form()), "poisson {lambda}: no step form");
            }
            compare::<u8>(t, 255, &mut r);
        }
        // Offsets beyond a byte: the two-level form without its byte form (16-bit lanes).
        for shift in [-200, 150] {
            let t = table(&|m| shift + (2.0 * m + 0.5).floor() as i32);
            let tl = t.two_level().expect("two-level form");
            assert!(!tl.has_bytes());
            compare::<u8>(&t, 255, &mut r);
        }
        // Every entry of the form is checked when it is built; a table whose buckets change value
        // more than once (and too often to be exact buckets) has none.
        let zigzag: Vec<i32> = (0..4096).map(|i: i32| i % 3).collect();
        assert!(TwoLevel::compile(&zigzag, 12).is_none());
        // Monotone with many steps per bucket in the middle: none either.
        let steep: Vec<i32> = (0..4096).map(|i: i32| i / 8).collect();
        assert!(TwoLevel::compile(&steep, 12).is_none());
    }

    /// A two-level byte-form table with every feature: steps, an entry to resolve in every
    /// other bucket (dense: the fix-up list fills and flushes mid-row), three exact buckets with
    /// entries to resolve, offsets of both signs up to the byte limit.
    #[test]
    fn two_level_kernels_with_dense_resolves_and_exact_buckets() {
        let entries: Vec<i32> = (0..4096usize)
            .map(|i| {
                let (c, f) = (i / 64, i % 64);
                if [3, 17, 40].contains(&c) {
                    return if f % 9 == 4 { RESOLVE } else { (f as i32 * 37 % 255) - 127 };
                }
                if c % 2 == 0 && f == (c * 7) % 64 {
                    return RESOLVE;
                }
                let base = 4 * c as i32 - 127;
                if f >= (c * 5) % 64 { (base + 3).min(127) } else { base }
            })
            .collect();
        let mut table = NoiseTable::default();
        table.rebuild(12, entries);
        let tl = table.two_level().expect("two-level form");
        assert_eq!(tl.exact_buckets(), 3);
        assert!(tl.has_bytes());
        let mut r = Rng::new(5);
        compare::<u8>(&table, 255, &mut r);
        compare::<u16>(&table, 65535, &mut r);
    }

    /// A table with the step form and every case of it: steps of 2 at every position, the entry
    /// before the step resolved in every third bucket (dense: the fix-up list fills mid-row),
    /// buckets without a step resolving their first entry (base - delta wraps in one of them) or
    /// their last one, offsets of both signs up to the byte limit, and 0 to 4 exact buckets.
    #[test]
    fn step_form_kernel_with_dense_resolves_and_exact_buckets() {
        let mut r = Rng::new(13);
        for n_exact in 0..=MAX_EXACT {
            let exact_c = &[3usize, 17, 40, 62][..n_exact];
            let entries: Vec<i32> = (0..4096usize)
                .map(|i| {
                    let (c, f) = (i / 64, i % 64);
                    if exact_c.contains(&c) {
                        return if f % 9 == 4 { RESOLVE } else { (f as i32 * 37 % 255) - 127 };
                    }
                    let base = if c == 57 { -127 } else { 4 * (c as i32 % 32) - 64 };
                    match c % 8 {
                        1 => return if f == 0 { RESOLVE } else { base },
                        5 => return if f == 63 { RESOLVE } else { base },
                        _ => {}
                    }
                    let thr = 1 + (c * 5) % 63;
                    if c % 3 == 0 && f + 1 == thr {
                        RESOLVE
                    } else if f >= thr {
                        base + 2
                    } else {
                        base
                    }
                })
                .collect();
            let mut table = NoiseTable::default();
            table.rebuild(12, entries);
            let tl = table.two_level().expect("two-level form");
            assert_eq!(tl.exact_buckets(), n_exact);
            assert!(tl.has_step_form(), "{n_exact} exact buckets: no step form");
            compare::<u8>(&table, 255, &mut r);
        }
        // Steps of different sizes: no step form (the four-lookup kernel runs).
        let uneven: Vec<i32> =
            (0..4096i32).map(|i| if i % 64 >= 32 { i / 64 * (1 + i / 2048) + 1 } else { 0 }).collect();
        let mut table = NoiseTable::default();
        table.rebuild(12, uneven);
        let tl = table.two_level().expect("two-level form");
        assert!(tl.has_bytes() && !tl.has_step_form());
        compare::<u8>(&table, 255, &mut r);
    }

    #[test]
    fn offsets_come_from_the_table_with_clipping() {
        // A table with one value: every sample moves by it, clipped.
        let mut table = NoiseTable::default();
        table.rebuild(12, vec![7i32; 1 << 12]);
        assert!(table.two_level().is_some());
        let mut row: Vec<u8> = (0..=255).collect();
        add_table_noise(&mut row, &mut RngLanes::new(&Rng::new(1)), &table, &mut |_| 0);
        for (v, out) in (0..=255u32).zip(&row) {
            assert_eq!(*out as u32, (v + 7).min(255));
        }
    }
}
