//! Building blocks of the physics library (helper "physlib"): parallel row bands with
//! thread-count-independent randomness, a multi-lane random generator for per-sample noise,
//! sparse Bernoulli sampling, fixed-point gain maps, benchmark parameters and scenes.
//!
//! Determinism: work is split into bands of [`ROWS_PER_TASK`] rows whatever the thread count;
//! band `k` draws from `ctx.rng.derive(k)`, so the bytes never depend on how rayon schedules.

use crate::frame::{Frame, PixelFormat, Sample};
use crate::rng::Rng;
use rayon::prelude::*;

/// `RGB8_SPLIT[c][k]`: `pshufb` indices taking channel `c` of 16 interleaved RGB pixels from
/// 16-byte part `k` of their 48 bytes (0x80: not in this part); OR-ing the three shuffled parts
/// gives the channel's 16 samples in order (channel_shift's R/B split, blooming's tile loads).
#[cfg(target_arch = "x86_64")]
pub(crate) const RGB8_SPLIT: [[[u8; 16]; 3]; 3] = {
    let mut t = [[[0x80u8; 16]; 3]; 3];
    let mut c = 0;
    while c < 3 {
        let mut p = 0;
        while p < 16 {
            let pos = 3 * p + c;
            t[c][pos / 16][p] = (pos % 16) as u8;
            p += 1;
        }
        c += 1;
    }
    t
};

pub use super::util::ROWS_PER_TASK;

/// `RGB8_MERGE[k][c]`: `pshufb` indices putting channel `c`'s sample of pixel (16k + j) / 3 at byte
/// j of 16-byte part `k` of 48 interleaved RGB bytes (0x80 where byte j is another channel's);
/// OR-ing the three shuffled channel registers gives part `k` (the inverse of [`RGB8_SPLIT`]).
#[cfg(target_arch = "x86_64")]
pub(crate) const RGB8_MERGE: [[[u8; 16]; 3]; 3] = {
    let mut t = [[[0x80u8; 16]; 3]; 3];
    let mut k = 0;
    while k < 3 {
        let mut j = 0;
        while j < 16 {
            let pos = 16 * k + j;
            t[k][pos % 3][j] = (pos / 3) as u8;
            j += 1;
        }
        k += 1;
    }
    t
};

/// Split an interleaved RGB8 row (`3 n` bytes) into three planar rows of `n` bytes. A permutation
/// of bytes: the same result on every path (16-pixel `pshufb` steps on AVX2 CPUs).
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
pub fn split_rgb8_row(src: &[u8], r: &mut [u8], g: &mut [u8], b: &mut [u8]) {
    let n = r.len();
    assert!(g.len() == n && b.len() == n && src.len() >= 3 * n);
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: AVX2 present (checked); the lengths are asserted above.
        done = unsafe { rgb8_simd::split(src, r, g, b) };
    }
    for i in done..n {
        (r[i], g[i], b[i]) = (src[3 * i], src[3 * i + 1], src[3 * i + 2]);
    }
}

/// Interleave three planar rows of `n` bytes into an RGB8 row (`3 n` bytes): the inverse of
/// [`split_rgb8_row`], the same result on every path.
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
pub fn merge_rgb8_row(dst: &mut [u8], r: &[u8], g: &[u8], b: &[u8]) {
    let n = r.len();
    assert!(g.len() == n && b.len() == n && dst.len() >= 3 * n);
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: AVX2 present (checked); the lengths are asserted above.
        done = unsafe { rgb8_simd::merge(dst, r, g, b) };
    }
    for i in done..n {
        (dst[3 * i], dst[3 * i + 1], dst[3 * i + 2]) = (r[i], g[i], b[i]);
    }
}

/// Interleave the even and the odd pixels of three channels into an RGB8 row of `w` pixels:
/// pixel 2i of channel c is `e[c][i]`, pixel 2i + 1 is `o[c][i]` (an odd last pixel from `e`).
/// [`merge_rgb8_row`] of the rows that zipping `e` and `o` would give, without those rows; a
/// permutation of bytes, the same result on every path.
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
pub fn merge_rgb8_eo_row(dst: &mut [u8], e: [&[u8]; 3], o: [&[u8]; 3], w: usize) {
    let pairs = w / 2;
    assert!(dst.len() >= 3 * w && e.iter().all(|x| x.len() >= w.div_ceil(2)) && o.iter().all(|x| x.len() >= pairs));
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: AVX2 present (checked); the lengths are asserted above.
        done = unsafe { rgb8_simd::merge_eo(dst, e, o, pairs) };
    }
    for i in done..pairs {
        for c in 0..3 {
            dst[6 * i + c] = e[c][i];
            dst[6 * i + 3 + c] = o[c][i];
        }
    }
    if w % 2 == 1 {
        for c in 0..3 {
            dst[6 * pairs + c] = e[c][pairs];
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod rgb8_simd {
    use super::{RGB8_MERGE, RGB8_SPLIT};
    use std::arch::x86_64::*;

    /// 16 pixels per step; returns the pixels done (a multiple of 16).
    #[target_feature(enable = "avx2")]
    pub unsafe fn split(src: &[u8], r: &mut [u8], g: &mut [u8], b: &mut [u8]) -> usize {
        let n = r.len() / 16 * 16;
        // SAFETY: table loads of 16 bytes from [[u8; 16]; 3] rows; pixel blocks read bytes
        // 48 i .. 48 i + 48 <= 3 n of `src` and write 16 i .. 16 i + 16 <= n of each plane.
        unsafe {
            let t = |c: usize, k: usize| _mm_loadu_si128(RGB8_SPLIT[c][k].as_ptr() as *const __m128i);
            let m = [[t(0, 0), t(0, 1), t(0, 2)], [t(1, 0), t(1, 1), t(1, 2)], [t(2, 0), t(2, 1), t(2, 2)]];
            let outs = [r.as_mut_ptr(), g.as_mut_ptr(), b.as_mut_ptr()];
            for i in (0..n).step_by(16) {
                let p = src.as_ptr().add(3 * i) as *const __m128i;
                let (a0, a1, a2) = (_mm_loadu_si128(p), _mm_loadu_si128(p.add(1)), _mm_loadu_si128(p.add(2)));
                for c in 0..3 {
                    let v = _mm_or_si128(
                        _mm_or_si128(_mm_shuffle_epi8(a0, m[c][0]), _mm_shuffle_epi8(a1, m[c][1])),
                        _mm_shuffle_epi8(a2, m[c][2]),
                    );
                    _mm_storeu_si128(outs[c].add(i) as *mut __m128i, v);
                }
            }
        }
        n
    }

    /// 16 pixel pairs per step (`e` and `o` zipped in registers, then merged as in [`merge`]);
    /// returns the pairs done (a multiple of 16).
    #[target_feature(enable = "avx2")]
    pub unsafe fn merge_eo(dst: &mut [u8], e: [&[u8]; 3], o: [&[u8]; 3], pairs: usize) -> usize {
        let n = pairs / 16 * 16;
        // SAFETY: reads 16 i .. 16 i + 16 <= n <= pairs of each of `e` and `o`, writes 96 i
        // .. 96 i + 96 <= 6 n <= 6 pairs <= 3 w of `dst` (the caller's asserts).
        unsafe {
            let t = |k: usize, c: usize| _mm_loadu_si128(RGB8_MERGE[k][c].as_ptr() as *const __m128i);
            let m = [[t(0, 0), t(0, 1), t(0, 2)], [t(1, 0), t(1, 1), t(1, 2)], [t(2, 0), t(2, 1), t(2, 2)]];
            for i in (0..n).step_by(16) {
                let ev = [0, 1, 2].map(|c| _mm_loadu_si128(e[c].as_ptr().add(i) as *const __m128i));
                let ov = [0, 1, 2].map(|c| _mm_loadu_si128(o[c].as_ptr().add(i) as *const __m128i));
                let lo = [0, 1, 2].map(|c| _mm_unpacklo_epi8(ev[c], ov[c]));
                let hi = [0, 1, 2].map(|c| _mm_unpackhi_epi8(ev[c], ov[c]));
                let q = dst.as_mut_ptr().add(6 * i) as *mut __m128i;
                for (h, v) in [lo, hi].iter().enumerate() {
                    for k in 0..3 {
                        let x = _mm_or_si128(
                            _mm_or_si128(_mm_shuffle_epi8(v[0], m[k][0]), _mm_shuffle_epi8(v[1], m[k][1])),
                            _mm_shuffle_epi8(v[2], m[k][2]),
                        );
                        _mm_storeu_si128(q.add(3 * h + k), x);
                    }
                }
            }
        }
        n
    }

    /// 16 pixels per step; returns the pixels done (a multiple of 16).
    #[target_feature(enable = "avx2")]
    pub unsafe fn merge(dst: &mut [u8], r: &[u8], g: &[u8], b: &[u8]) -> usize {
        let n = r.len() / 16 * 16;
        // SAFETY: as in `split`, reads 16 i .. 16 i + 16 <= n of each plane, writes 48 i ..
        // 48 i + 48 <= 3 n of `dst`.
        unsafe {
            let t = |k: usize, c: usize| _mm_loadu_si128(RGB8_MERGE[k][c].as_ptr() as *const __m128i);
            let m = [[t(0, 0), t(0, 1), t(0, 2)], [t(1, 0), t(1, 1), t(1, 2)], [t(2, 0), t(2, 1), t(2, 2)]];
            let ins = [r.as_ptr(), g.as_ptr(), b.as_ptr()];
            for i in (0..n).step_by(16) {
                let v = [0, 1, 2].map(|c| _mm_loadu_si128(ins[c].add(i) as *const __m128i));
                let q = dst.as_mut_ptr().add(3 * i) as *mut __m128i;
                for k in 0..3 {
                    let o = _mm_or_si128(
                        _mm_or_si128(_mm_shuffle_epi8(v[0], m[k][0]), _mm_shuffle_epi8(v[1], m[k][1])),
                        _mm_shuffle_epi8(v[2], m[k][2]),
                    );
                    _mm_storeu_si128(q.add(k), o);
                }
            }
        }
        n
    }
}

/// Run `f(band, first_row, rows)` over bands of [`ROWS_PER_TASK`] rows in parallel. `rows` is the
/// band's slice of `data` (rows of `stride` samples; the last row of the frame may be shorter
/// than `stride` but is at least one row long). No allocation.
pub fn par_bands<T: Send>(data: &mut [T], stride: usize, height: usize, f: impl Fn(usize, usize, &mut [T]) + Sync) {
    let used = used_len(data.len(), stride, height);
    data[..used].par_chunks_mut(stride * ROWS_PER_TASK).enumerate().for_each(|(k, band)| f(k, k * ROWS_PER_TASK, band));
}

/// Like [`par_bands`], with a second per-band slice (scratch) handed to each band: `scratch`
/// is split into chunks of `per_band` elements, one per band (it must hold `bands(height)` chunks).
pub fn par_bands_with<T: Send, S: Send>(
    data: &mut [T],
    stride: usize,
    height: usize,
    scratch: &mut [S],
    per_band: usize,
    f: impl Fn(usize, usize, &mut [T], &mut [S]) + Sync,
) {
    let used = used_len(data.len(), stride, height);
    debug_assert!(scratch.len() >= per_band * bands(height), "scratch for every band");
    data[..used]
        .par_chunks_mut(stride * ROWS_PER_TASK)
        .zip(scratch.par_chunks_mut(per_band.max(1)))
        .enumerate()
        .for_each(|(k, (band, s))| f(k, k * ROWS_PER_TASK, band, s));
}

/// Number of bands for a frame height.
pub fn bands(height: usize) -> usize {
    height.div_ceil(ROWS_PER_TASK)
}

fn used_len(len: usize, stride: usize, height: usize) -> usize {
    len.min(stride * height)
}

/// Rows of a band (each without padding).
pub fn band_rows<T>(band: &mut [T], stride: usize, row_len: usize) -> impl Iterator<Item = &mut [T]> {
    band.chunks_mut(stride).map(move |r| &mut r[..row_len])
}

/// Compile a row kernel twice: as is (the portable reference) and with AVX2 enabled, and call the
/// AVX2 copy when the CPU has it. The copies run the same IEEE/integer operations in the same
/// order (no fast-math, no FMA contraction), so they give the same bytes; AVX2 only lets the
/// compiler use wider vectors.
macro_rules! multiversion {
    ($(#[$m:meta])* $vis:vis fn $name:ident<$T:ident: $B:path>($($a:ident: $t:ty),* $(,)?) $(-> $R:ty)? $body:block) => {
        $(#[$m])*
        $vis fn $name<$T: $B>($($a: $t),*) $(-> $R)? {
            #[inline(always)]
            fn generic<$T: $B>($($a: $t),*) $(-> $R)? $body
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            unsafe fn avx2<$T: $B>($($a: $t),*) $(-> $R)? {
                generic($($a),*)
            }
            #[cfg(target_arch = "x86_64")]
            if $crate::faults::kit::has_avx2() {
                // SAFETY: the CPU supports AVX2 (checked just above).
                return unsafe { avx2($($a),*) };
            }
            generic($($a),*)
        }
    };
}

pub(crate) use multiversion;

/// `fn $name(lv: u8, args..)` calling the kernel `$body(args..)` (`#[inline(always)]`) compiled
/// with AVX-512 F/BW/VL when `lv >= 2` and the CPU has them, with AVX2 when `lv >= 1` and the CPU
/// has it, else as is (`lv`: `boxblur::cpu_level()`, lowered by `FAULTCAM_NO_AVX512` /
/// `FAULTCAM_NO_SIMD`). The copies run the same integer operations, so they give the same bytes.
macro_rules! dispatch_levels {
    ($name:ident, $body:ident, ($($a:ident: $t:ty),*)) => {
        #[inline]
        #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
        fn $name(lv: u8, $($a: $t),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
                unsafe fn v512($($a: $t),*) { $body($($a),*) }
                #[target_feature(enable = "avx2")]
                unsafe fn v256($($a: $t),*) { $body($($a),*) }
                if lv >= 2 && $crate::faults::kit::has_avx512() {
                    // SAFETY: AVX-512 F/BW/VL present (checked).
                    return unsafe { v512($($a),*) };
                }
                if lv >= 1 && $crate::faults::kit::has_avx2() {
                    // SAFETY: AVX2 present (checked).
                    return unsafe { v256($($a),*) };
                }
            }
            $body($($a),*)
        }
    };
}

pub(crate) use dispatch_levels;

/// `_mm256_mulhi_epu16` pinned as one `vpmulhuw` (LLVM otherwise rewrites some multiply-highs
/// into a widening 32-bit sequence, about 2x slower).
///
/// # Safety
/// AVX2 (a safe function in `#[target_feature]` code that has it).
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
pub fn mulhi_epu16_256(a: std::arch::x86_64::__m256i, b: std::arch::x86_64::__m256i) -> std::arch::x86_64::__m256i {
    let r: std::arch::x86_64::__m256i;
    // SAFETY: AVX2 (this function's feature); a register-only instruction without memory access
    // or flags.
    unsafe {
        std::arch::asm!("vpmulhuw {r}, {a}, {b}", r = lateout(ymm_reg) r, a = in(ymm_reg) a, b = in(ymm_reg) b,
            options(pure, nomem, nostack, preserves_flags));
    }
    r
}

/// `_mm512_mulhi_epu16` pinned as one `vpmulhuw` (see [`mulhi_epu16_256`]).
///
/// # Safety
/// AVX-512 BW (a safe function in `#[target_feature]` code that has it).
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx512f,avx512bw")]
pub fn mulhi_epu16_512(a: std::arch::x86_64::__m512i, b: std::arch::x86_64::__m512i) -> std::arch::x86_64::__m512i {
    let r: std::arch::x86_64::__m512i;
    // SAFETY: AVX-512 BW (this function's feature); a register-only instruction without memory
    // access or flags.
    unsafe {
        std::arch::asm!("vpmulhuw {r}, {a}, {b}", r = lateout(zmm_reg) r, a = in(zmm_reg) a, b = in(zmm_reg) b,
            options(pure, nomem, nostack, preserves_flags));
    }
    r
}

/// Whether `FAULTCAM_NO_SIMD` is set: every kernel then runs its portable scalar reference (to
/// time it, or to test that it gives the SIMD versions' bytes on the same machine).
pub fn no_simd() -> bool {
    use std::sync::OnceLock;
    static NO: OnceLock<bool> = OnceLock::new();
    *NO.get_or_init(|| std::env::var_os("FAULTCAM_NO_SIMD").is_some())
}

/// Whether the AVX2 kernels can run, unless `FAULTCAM_NO_SIMD` is set.
#[cfg(target_arch = "x86_64")]
pub fn has_avx2() -> bool {
    use std::sync::OnceLock;
    static HAS: OnceLock<bool> = OnceLock::new();
    *HAS.get_or_init(|| !no_simd() && std::arch::is_x86_feature_detected!("avx2"))
}

/// Whether the AVX-512 kernels can run (F, BW and VL), unless `FAULTCAM_NO_AVX512` or
/// `FAULTCAM_NO_SIMD` is set (to time or test the AVX2 and scalar versions on the same machine).
#[cfg(target_arch = "x86_64")]
pub fn has_avx512() -> bool {
    use std::sync::OnceLock;
    static HAS: OnceLock<bool> = OnceLock::new();
    *HAS.get_or_init(|| {
        std::env::var_os("FAULTCAM_NO_AVX512").is_none()
            && has_avx2()
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vl")
    })
}

/// [`has_avx512`] and VBMI (byte permutes).
#[cfg(target_arch = "x86_64")]
pub fn has_avx512_vbmi() -> bool {
    use std::sync::OnceLock;
    static HAS: OnceLock<bool> = OnceLock::new();
    *HAS.get_or_init(|| has_avx512() && std::arch::is_x86_feature_detected!("avx512vbmi"))
}

/// Transposes 8 x 8 32-bit lanes held in eight AVX2 registers (row `i` of the result is lane `i`
/// of every input row): unpacks and lane permutes only, no gathers.
///
/// # Safety
/// AVX2: call only from code compiled with (or checked for) AVX2; inlined into its caller.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub unsafe fn transpose8x8_epi32(r: [std::arch::x86_64::__m256i; 8]) -> [std::arch::x86_64::__m256i; 8] {
    use std::arch::x86_64::*;
    // SAFETY: register-only AVX2 operations; the caller guarantees AVX2.
    unsafe {
        let t0 = _mm256_unpacklo_epi32(r[0], r[1]);
        let t1 = _mm256_unpackhi_epi32(r[0], r[1]);
        let t2 = _mm256_unpacklo_epi32(r[2], r[3]);
        let t3 = _mm256_unpackhi_epi32(r[2], r[3]);
        let t4 = _mm256_unpacklo_epi32(r[4], r[5]);
        let t5 = _mm256_unpackhi_epi32(r[4], r[5]);
        let t6 = _mm256_unpacklo_epi32(r[6], r[7]);
        let t7 = _mm256_unpackhi_epi32(r[6], r[7]);
        let u0 = _mm256_unpacklo_epi64(t0, t2);
        let u1 = _mm256_unpackhi_epi64(t0, t2);
        let u2 = _mm256_unpacklo_epi64(t1, t3);
        let u3 = _mm256_unpackhi_epi64(t1, t3);
        let u4 = _mm256_unpacklo_epi64(t4, t6);
        let u5 = _mm256_unpackhi_epi64(t4, t6);
        let u6 = _mm256_unpacklo_epi64(t5, t7);
        let u7 = _mm256_unpackhi_epi64(t5, t7);
        [
            _mm256_permute2x128_si256(u0, u4, 0x20),
            _mm256_permute2x128_si256(u1, u5, 0x20),
            _mm256_permute2x128_si256(u2, u6, 0x20),
            _mm256_permute2x128_si256(u3, u7, 0x20),
            _mm256_permute2x128_si256(u0, u4, 0x31),
            _mm256_permute2x128_si256(u1, u5, 0x31),
            _mm256_permute2x128_si256(u2, u6, 0x31),
            _mm256_permute2x128_si256(u3, u7, 0x31),
        ]
    }
}

/// Transposes, within each 128-bit lane, the 4 x 4 32-bit lanes of four AVX2 registers (dword
/// `c` of lane `l` of result `i` is dword `i` of lane `l` of input `c`): 8 in-lane unpacks, no
/// lane permutes. Two 4 x 4 transposes at once; an 8 x 8 transpose when the inputs hold rows `r`
/// and `r + 4` in their two lanes.
///
/// # Safety
/// AVX2: call only from code compiled with (or checked for) AVX2; inlined into its caller.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub unsafe fn transpose4x4x2_epi32(r: [std::arch::x86_64::__m256i; 4]) -> [std::arch::x86_64::__m256i; 4] {
    use std::arch::x86_64::*;
    // SAFETY: register-only AVX2 operations; the caller guarantees AVX2.
    unsafe {
        let t0 = _mm256_unpacklo_epi32(r[0], r[1]);
        let t1 = _mm256_unpackhi_epi32(r[0], r[1]);
        let t2 = _mm256_unpacklo_epi32(r[2], r[3]);
        let t3 = _mm256_unpackhi_epi32(r[2], r[3]);
        [
            _mm256_unpacklo_epi64(t0, t2),
            _mm256_unpackhi_epi64(t0, t2),
            _mm256_unpacklo_epi64(t1, t3),
            _mm256_unpackhi_epi64(t1, t3),
        ]
    }
}

/// The kernel set the hot loops run on this CPU, as `faultcam bench` reports it: "AVX-512
/// (VBMI)", "AVX-512", "AVX2" or "scalar" (after `FAULTCAM_NO_AVX512` / `FAULTCAM_NO_SIMD`).
pub fn kernel_set() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        if has_avx512_vbmi() {
            return "AVX-512 (F/BW/VL/VBMI)";
        }
        if has_avx512() {
            return "AVX-512 (F/BW/VL)";
        }
        if has_avx2() {
            return "AVX2";
        }
    }
    "scalar"
}

/// The CPU model: `model name` of /proc/cpuinfo, with the x86 family/model numbers (a VM may
/// show only "AMD EPYC"; family 25 = Zen 3/4, 23 = Zen 1/2), else the architecture.
pub fn cpu_model() -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let field = |key: &str| {
        info.lines()
            .find(|l| l.split(':').next().is_some_and(|k| k.trim() == key))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string())
            .filter(|v| !v.is_empty())
    };
    let name = field("model name")
        .or_else(|| field("Hardware"))
        .or_else(|| field("CPU part").map(|p| format!("CPU part {p}")));
    match (name, field("cpu family"), field("model")) {
        (Some(n), Some(f), Some(m)) => format!("{n} (family {f}, model {m})"),
        (Some(n), _, _) => n,
        _ => std::env::consts::ARCH.to_string(),
    }
}

/// `v = lut[v]` for every byte of `row`.
pub fn lut_u8_row(row: &mut [u8], lut: &[u8; 256]) {
    #[cfg(target_arch = "x86_64")]
    if has_avx512_vbmi() {
        // SAFETY: the CPU supports AVX-512 F/BW/VL/VBMI (checked just above).
        unsafe { simd512::lut_u8_row(row, lut) };
        return;
    }
    for v in row.iter_mut() {
        *v = lut[*v as usize];
    }
}

/// Bit i of `out` (64 per word, least significant first) = `row[i] >= thr`; `out` needs
/// `row.len().div_ceil(64)` words.
pub fn ge_mask_u8(row: &[u8], thr: u8, out: &mut [u64]) {
    #[cfg(target_arch = "x86_64")]
    if has_avx512() {
        // SAFETY: the CPU supports AVX-512 F/BW/VL (checked just above).
        unsafe { simd512::ge_mask_u8(row, thr, out) };
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { ge_mask_u8_avx2(row, thr, out) };
        return;
    }
    ge_mask_u8_scalar(row, thr, out)
}

/// AVX2 version of [`ge_mask_u8`]: whole 64-byte words by `movemask`, the tail by the reference.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn ge_mask_u8_avx2(row: &[u8], thr: u8, out: &mut [u64]) {
    use std::arch::x86_64::*;
    let t = _mm256_set1_epi8(thr as i8);
    let full = row.len() / 64;
    for (k, o) in out.iter_mut().enumerate().take(full) {
        // SAFETY: bytes 64k .. 64k + 64 are inside the row (k < row.len() / 64).
        let bits = |off: usize| unsafe {
            let v = _mm256_loadu_si256(row.as_ptr().add(64 * k + off) as *const __m256i);
            // v >= thr  <=>  max(v, thr) == v (unsigned).
            _mm256_movemask_epi8(_mm256_cmpeq_epi8(_mm256_max_epu8(v, t), v)) as u32 as u64
        };
        *o = bits(0) | bits(32) << 32;
    }
    if full < out.len() {
        ge_mask_u8_scalar(&row[64 * full..], thr, &mut out[full..]);
    }
}

/// Scalar reference of [`ge_mask_u8`].
pub fn ge_mask_u8_scalar(row: &[u8], thr: u8, out: &mut [u64]) {
    for (o, chunk) in out.iter_mut().zip(row.chunks(64)) {
        *o = chunk.iter().enumerate().fold(0u64, |m, (k, &v)| m | ((v >= thr) as u64) << k);
    }
}

/// Bit j of `RGB_CHANNEL_BITS[r][c]` is set when sample `r + j` of an interleaved RGB row,
/// counted from a pixel boundary, belongs to channel c: the channel masks of a 64-sample word
/// that starts r (mod 3) samples after a pixel boundary (64 = 1 mod 3, so word k of a row
/// starts k mod 3 samples after one).
pub const RGB_CHANNEL_BITS: [[u64; 3]; 3] = {
    let mut t = [[0u64; 3]; 3];
    let mut r = 0;
    while r < 3 {
        let mut j = 0;
        while j < 64 {
            t[r][(r + j) % 3] |= 1 << j;
            j += 1;
        }
        r += 1;
    }
    t
};

#[cfg(target_arch = "x86_64")]
mod simd512 {
    use std::arch::x86_64::*;

    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub unsafe fn lut_u8_row(row: &mut [u8], lut: &[u8; 256]) {
        // SAFETY (whole function): 64-byte loads from the 256-byte table; row accesses are
        // masked to the row's length.
        unsafe {
            let t = lut.as_ptr() as *const __m512i;
            let (t0, t1, t2, t3) = (
                _mm512_loadu_si512(t),
                _mm512_loadu_si512(t.add(1)),
                _mm512_loadu_si512(t.add(2)),
                _mm512_loadu_si512(t.add(3)),
            );
            let mut i = 0;
            while i < row.len() {
                let n = (row.len() - i).min(64);
                let m: __mmask64 = if n == 64 { !0 } else { (1u64 << n) - 1 };
                let p = row.as_mut_ptr().add(i);
                let v = _mm512_maskz_loadu_epi8(m, p as *const i8);
                let lo = _mm512_permutex2var_epi8(t0, v, t1);
                let hi = _mm512_permutex2var_epi8(t2, v, t3);
                let r = _mm512_mask_blend_epi8(_mm512_movepi8_mask(v), lo, hi);
                _mm512_mask_storeu_epi8(p as *mut i8, m, r);
                i += 64;
            }
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,avx512vl")]
    pub unsafe fn ge_mask_u8(row: &[u8], thr: u8, out: &mut [u64]) {
        let t = _mm512_set1_epi8(thr as i8);
        for (k, o) in out.iter_mut().enumerate().take(row.len().div_ceil(64)) {
            let i = k * 64;
            let n = (row.len() - i).min(64);
            let m: __mmask64 = if n == 64 { !0 } else { (1u64 << n) - 1 };
            // SAFETY: the load is masked to the row's length.
            let v = unsafe { _mm512_maskz_loadu_epi8(m, row.as_ptr().add(i) as *const i8) };
            *o = _mm512_mask_cmpge_epu8_mask(m, v, t);
        }
    }
}

multiversion! {
    /// `v = round(v * g)` (f32, half up, clipped to the sample range) with one gain per sample.
    pub fn mul_round_row<T: Sample>(row: &mut [T], gains: &[f32]) {
        for (v, &g) in row.iter_mut().zip(gains) {
            *v = T::from_f32(v.to_f32() * g);
        }
    }
}

multiversion! {
    /// `out += a * x` element by element (f32, no fused multiply-add: the same rounding on every
    /// path).
    pub fn axpy_row<T: Copy>(out: &mut [f32], a: f32, x: &[f32], _t: T) {
        for (o, &v) in out.iter_mut().zip(x) {
            *o += a * v;
        }
    }
}

multiversion! {
    /// `out = x as f32` element by element.
    pub fn to_f32_row<T: Sample>(out: &mut [f32], x: &[T]) {
        for (o, &v) in out.iter_mut().zip(x) {
            *o = v.to_f32();
        }
    }
}

/// Row `irow` (`w` pixels of `ch` samples) as f32 into `pad`, mirrored (half-sample symmetric) by
/// `r` pixels at both ends: `pad` holds `(w + 2r) * ch` samples, pixel p of `pad` is pixel
/// mirror(p - r) of the row. The interior is converted in one vectorised call.
pub fn mirrored_row_f32<T: Sample>(irow: &[T], w: usize, ch: usize, r: usize, pad: &mut [f32]) {
    to_f32_row(&mut pad[r * ch..(r + w) * ch], &irow[..w * ch]);
    let n2 = 2 * w as isize;
    let mirror = |i: isize| {
        let m = i.rem_euclid(n2);
        if m >= w as isize { (n2 - 1 - m) as usize } else { m as usize }
    };
    for px in (0..r).chain(r + w..w + 2 * r) {
        let sx = mirror(px as isize - r as isize);
        for c in 0..ch {
            pad[px * ch + c] = irow[sx * ch + c].to_f32();
        }
    }
}

multiversion! {
    /// `out = round(acc)`, clipped to the sample range.
    pub fn round_row<T: Sample>(out: &mut [T], acc: &[f32]) {
        for (o, &a) in out.iter_mut().zip(acc) {
            *o = T::from_f32(a);
        }
    }
}

multiversion! {
    /// Largest sample of a row (`T::default()` for an empty row).
    pub fn max_of_row<T: Sample>(row: &[T]) -> T {
        row.iter().fold(T::default(), |m, &v| if v > m { v } else { m })
    }
}

multiversion! {
    /// `v = min((v * gq + 2^15) >> 16, MAX)`: a gain in Q16 fixed point, rounded half up.
    pub fn scale_q16_row<T: Sample>(row: &mut [T], gq: u32) {
        if T::MAX_U32 == 255 && gq < 1 << 24 {
            // 8-bit: the product fits in u32, which vectorises.
            for v in row.iter_mut() {
                *v = T::from_u32_sat((v.to_u32() * gq + 32768) >> 16);
            }
        } else {
            for v in row.iter_mut() {
                let p = (v.to_u32() as u64 * gq as u64 + 32768) >> 16;
                *v = T::from_u32_sat(p.min(T::MAX_U32 as u64) as u32);
            }
        }
    }
}

/// [`scale_q16_row`] on bytes: `v = min((v * gq + 2^15) >> 16, 255)`. With AVX2 and gq < 2^24
/// the product is split for 16-bit lanes (see [`scale_q16_u8_avx2`]), 32 bytes per step instead
/// of 8 in 32-bit lanes; the same values.
pub fn scale_q16_u8(row: &mut [u8], gq: u32) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() && gq < 1 << 24 {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { scale_q16_u8_avx2(row, gq) };
        return;
    }
    scale_q16_row(row, gq)
}

/// AVX2 version of [`scale_q16_u8`] (gq < 2^24). With gq = a * 2^16 + b (a < 256, b < 2^16) and
/// v * b = hi * 2^16 + lo: `(v * gq + 2^15) >> 16 = v * a + hi + (lo >> 15)`, at most
/// 255 * 255 + 255 < 2^16, so every term fits a 16-bit lane (`vpmullw`, `vpmulhuw`); then the
/// minimum with 255 and an unsigned pack. The tail runs the reference.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn scale_q16_u8_avx2(row: &mut [u8], gq: u32) {
    use std::arch::x86_64::*;
    let (a, b) = (_mm256_set1_epi16((gq >> 16) as i16), _mm256_set1_epi16((gq & 0xffff) as u16 as i16));
    let (zero, max) = (_mm256_setzero_si256(), _mm256_set1_epi16(255));
    let scale = |v: __m256i| {
        let (hi, lo) = (_mm256_mulhi_epu16(v, b), _mm256_mullo_epi16(v, b));
        let r = _mm256_add_epi16(_mm256_add_epi16(_mm256_mullo_epi16(v, a), hi), _mm256_srli_epi16(lo, 15));
        _mm256_min_epu16(r, max)
    };
    let full = row.len() / 32;
    for k in 0..full {
        // SAFETY: bytes 32k .. 32k + 32 are inside the row (k < row.len() / 32).
        unsafe {
            let p = row.as_mut_ptr().add(32 * k) as *mut __m256i;
            let v = _mm256_loadu_si256(p);
            // Unpack and pack both work within 128-bit lanes, so the bytes come back in order.
            let (l, h) = (scale(_mm256_unpacklo_epi8(v, zero)), scale(_mm256_unpackhi_epi8(v, zero)));
            _mm256_storeu_si256(p, _mm256_packus_epi16(l, h));
        }
    }
    scale_q16_row(&mut row[32 * full..], gq);
}

multiversion! {
    /// `v = min(v + a, MAX)` with one addend per sample.
    pub fn add_sat_row<T: Sample>(row: &mut [T], add: &[u32]) {
        for (v, &a) in row.iter_mut().zip(add) {
            *v = T::from_u32_sat(v.to_u32().saturating_add(a));
        }
    }
}

/// Four interleaved xoshiro256++ streams stepped together: the same algorithm as [`Rng`], laid
/// out so the compiler can keep the four states in vector registers. Each lane is seeded from
/// `parent.derive(lane)`, so the stream is a pure function of the parent's seed.
#[derive(Clone, Debug)]
pub struct RngLanes {
    s: [[u64; 4]; 4],
}

impl RngLanes {
    pub fn new(parent: &Rng) -> RngLanes {
        let mut s = [[0u64; 4]; 4];
        for lane in 0..4 {
            let mut child = parent.derive(lane as u64);
            // Burn-in is unnecessary (SplitMix seeding); take the state through the public stream.
            let st = [child.next_u64(), child.next_u64(), child.next_u64(), child.next_u64()];
            for j in 0..4 {
                s[j][lane] = st[j] | if j == 0 { 1 } else { 0 };
            }
        }
        RngLanes { s }
    }

    /// The state, `[word][lane]` (for SIMD kernels that step the lanes in registers).
    #[cfg(target_arch = "x86_64")]
    pub(crate) fn state_mut(&mut self) -> &mut [[u64; 4]; 4] {
        &mut self.s
    }

    /// Four 64-bit outputs.
    #[inline(always)]
    pub fn next4(&mut self) -> [u64; 4] {
        let [s0, s1, s2, s3] = &mut self.s;
        let mut out = [0u64; 4];
        for l in 0..4 {
            out[l] = s0[l].wrapping_add(s3[l]).rotate_left(23).wrapping_add(s0[l]);
            let t = s1[l] << 17;
            s2[l] ^= s0[l];
            s3[l] ^= s1[l];
            s1[l] ^= s2[l];
            s0[l] ^= s3[l];
            s2[l] ^= t;
            s3[l] = s3[l].rotate_left(45);
        }
        out
    }

    /// Fill `out` with uniform 32-bit words.
    #[inline]
    pub fn fill_u32(&mut self, out: &mut [u32]) {
        let mut chunks = out.chunks_exact_mut(8);
        for c in &mut chunks {
            let r = self.next4();
            for l in 0..4 {
                c[2 * l] = r[l] as u32;
                c[2 * l + 1] = (r[l] >> 32) as u32;
            }
        }
        let rest = chunks.into_remainder();
        if !rest.is_empty() {
            let r = self.next4();
            for (i, v) in rest.iter_mut().enumerate() {
                *v = (r[i / 2] >> (32 * (i % 2))) as u32;
            }
        }
    }
}

/// Visit the indices `i < n` of a Bernoulli(p) process (each index independently with
/// probability `p`) by geometric skipping: one uniform draw per selected index, so sparse
/// faults cost O(p·n). Exact in distribution up to f64 resolution.
pub fn for_each_bernoulli(rng: &mut Rng, n: usize, p: f64, mut f: impl FnMut(usize, &mut Rng)) {
    if p <= 0.0 || n == 0 {
        return;
    }
    if p >= 1.0 {
        for i in 0..n {
            f(i, rng);
        }
        return;
    }
    let ln_q = (-p).ln_1p(); // ln(1 - p) < 0
    let mut i = 0usize;
    loop {
        // Number of failures before the next success: floor(ln(U) / ln(1 - p)), U in (0, 1].
        let u = 1.0 - rng.uniform();
        let skip = (u.ln() / ln_q).floor();
        if !skip.is_finite() || skip >= (n - i) as f64 {
            return;
        }
        i += skip as usize;
        f(i, rng);
        i += 1;
        if i >= n {
            return;
        }
    }
}

/// Fixed-point gain maps: `Q` fractional bits. `apply_gain_q` computes round(v·g) with the
/// gain stored as round(g·2^Q) in a `u32`, saturating at the sample maximum.
pub const GAIN_Q: u32 = 16;

/// Gain → fixed point (clamped to [0, 65535.99]).
#[inline]
pub fn gain_to_q(g: f64) -> u32 {
    (g.clamp(0.0, 65535.0) * (1u64 << GAIN_Q) as f64).round() as u32
}

/// round(v · g) with `g` in Q16, saturating. Exact for 8-bit samples and gains that are
/// multiples of 2^-16; for 16-bit samples the product is formed in 64 bits.
#[inline(always)]
pub fn mul_gain_q<T: Sample>(v: T, gq: u32) -> T {
    let p = v.to_u32() as u64 * gq as u64 + (1u64 << (GAIN_Q - 1));
    T::from_u32_sat((p >> GAIN_Q).min(u32::MAX as u64) as u32)
}

/// Point-wise lookup tables for both sample widths, rebuilt only when their key changes.
#[derive(Default, Debug)]
pub struct Lut {
    key: Option<(u64, u64, u64, bool)>,
    // allocation: once per parameter change
    pub t8: Vec<u8>,
    pub t16: Vec<u16>,
}

impl Lut {
    /// Make sure the table for `key` and the frame's sample width exists; `f(v, fs)` maps a
    /// sample value to the output value in DN (rounded and clamped here).
    pub fn ensure(&mut self, key: (u64, u64, u64), wide: bool, f: impl Fn(f64, f64) -> f64) {
        let full = (key.0, key.1, key.2, wide);
        if self.key == Some(full) {
            return;
        }
        if wide {
            self.t16.clear();
            self.t16.extend((0..=65535u32).map(|v| f(v as f64, 65535.0).round().clamp(0.0, 65535.0) as u16));
        } else {
            self.t8.clear();
            self.t8.extend((0..=255u32).map(|v| f(v as f64, 255.0).round().clamp(0.0, 255.0) as u8));
        }
        self.key = Some(full);
    }

    /// Apply the table to every sample of the frame (parallel over row bands).
    pub fn apply(&self, frame: &mut Frame) {
        let (stride, height, row_len) = (frame.stride, frame.height as usize, frame.row_len());
        match &mut frame.data {
            crate::frame::FrameData::U8(d) => {
                let Ok(t) = <&[u8; 256]>::try_from(&self.t8[..]) else { return };
                par_bands(d, stride, height, |_, _, band| {
                    for row in band_rows(band, stride, row_len) {
                        lut_u8_row(row, t);
                    }
                });
            }
            crate::frame::FrameData::U16(d) => {
                let Ok(t) = <&[u16; 65536]>::try_from(&self.t16[..]) else { return };
                par_bands(d, stride, height, |_, _, band| {
                    for row in band_rows(band, stride, row_len) {
                        for v in row.iter_mut() {
                            *v = t[*v as usize];
                        }
                    }
                });
            }
        }
    }
}

/// A fixed sparse pixel pattern (hot pixels, dead pixels) that is *nested* in its rate: the
/// candidates are drawn once per (pixel count, seed) at the parameter's maximum rate, each with
/// a uniform key in [0, max_rate); the pattern for rate r is the candidates with key < r. So
/// every pixel is in the pattern independently with probability r, and raising r only adds
/// pixels (a fitter sees a monotone, continuous response).
#[derive(Default, Debug)]
pub struct SparsePattern {
    cand_key: Option<(usize, u64, u64)>,
    // allocation: once per (size, seed): about max_rate · pixels entries
    cand: Vec<(u32, f64)>,
    active_key: Option<u64>,
    // allocation: once per rate change
    active: Vec<u32>,
}

impl SparsePattern {
    /// Pixel indices (y·width + x, increasing) of the pattern.
    pub fn ensure(&mut self, pixels: usize, seed: u64, max_rate: f64, rate: f64) -> &[u32] {
        let ck = (pixels, seed, max_rate.to_bits());
        if self.cand_key != Some(ck) {
            self.cand.clear();
            let mut rng = Rng::new(seed);
            let cand = &mut self.cand;
            for_each_bernoulli(&mut rng, pixels.min(u32::MAX as usize), max_rate, |i, r| {
                cand.push((i as u32, r.uniform() * max_rate));
            });
            self.cand_key = Some(ck);
            self.active_key = None;
        }
        if self.active_key != Some(rate.to_bits()) {
            self.active.clear();
            self.active.extend(self.cand.iter().filter(|c| c.1 < rate).map(|c| c.0));
            self.active_key = Some(rate.to_bits());
        }
        &self.active
    }
}

/// Visible, study-like parameters of an effect for benchmarks and whole-library tests: every
/// effect does real work (no identity settings), at strengths like `hil/campaigns/original8.toml`.
/// Effects not listed take their defaults (which are already active).
pub fn bench_params(name: &str) -> Result<super::Params, super::FaultError> {
    let mut p = super::default_params(name)?;
    let set: &[(&str, f64)] = match name {
        "lens_flare" => &[("ghosts", 5.0), ("intensity", 0.08)],
        "motion_blur" => &[("length_px", 10.0), ("angle_deg", 30.0)],
        "channel_shift" => &[("dx_r", 1.3), ("dy_r", -0.6), ("dx_b", -1.1), ("dy_b", 0.8)],
        "dark_current" => &[("mean_dn", 3.0), ("hot_pixel_rate", 5e-4)],
        "blooming" => &[("full_well_fraction", 0.95), ("spread_px", 2.0), ("exposure_gain", 1.2)],
        "smear" => &[("strength", 0.002), ("sat_level", 0.95)],
        "gaussian_noise" => &[("sigma_dn", 3.0)],
        "vertical_glitch" | "horizontal_glitch" => &[("count", 2.0), ("max_offset_px", 24.0)],
        "gain_offset" => &[("gain", 1.2), ("offset_dn", 4.0)],
        "gamma" => &[("gamma", 2.2)],
        "jpeg" => &[("quality", 75.0)],
        "cosmic_rays" => &[("rate", 2e-5), ("track_len_px", 8.0)],
        "bit_flip" => &[("rate", 1e-5)],
        "dead_pixels" => &[("rate", 1e-4)],
        _ => &[],
    };
    for (k, v) in set {
        p.set(k, *v)?;
    }
    Ok(p)
}

/// Input scenes for benchmarks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scene {
    /// The procedural spacecraft of the `synth:` source (default pose, seed 0): dark sky, lit
    /// bus and solar wings, a few small saturated glints. The representative case.
    Spacecraft,
    /// [`bench_scene`]: a large bright textured body that overflows the full well over wide areas
    /// when over-exposed (a stress case for blooming).
    Stress,
    /// Diagonal ramps, `v = (x + y) mod 256` (x 257 for 16-bit; RGB channels shifted by 85):
    /// bands of saturation across every part of the frame (about a fifth of the samples over
    /// the original chain's blooming well): the worst case for blooming's sparse tiles, the
    /// frames `scripts/soak/feeder.py` falls back to.
    Ramp,
}

impl Scene {
    pub fn parse(s: &str) -> Option<Scene> {
        match s {
            "spacecraft" | "synth" => Some(Scene::Spacecraft),
            "stress" | "bench" => Some(Scene::Stress),
            "ramp" => Some(Scene::Ramp),
            _ => None,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Scene::Spacecraft => "spacecraft",
            Scene::Stress => "stress",
            Scene::Ramp => "ramp",
        }
    }
    /// Render the scene (deterministic in size and format).
    pub fn render(self, width: u32, height: u32, format: PixelFormat) -> Result<Frame, crate::frame::FrameError> {
        match self {
            Scene::Stress => bench_scene(width, height, format, 1),
            Scene::Ramp => {
                let mut f = Frame::new(width, height, format)?;
                let ch = format.channels();
                for y in 0..height as usize {
                    for x in 0..width as usize {
                        for c in 0..ch {
                            f.set(x, y, c, ((x + y + 85 * c) % 256) as f32 * format.full_scale() / 255.0);
                        }
                    }
                }
                Ok(f)
            }
            // The synth source needs at least 16x16 pixels.
            Scene::Spacecraft if width < 16 || height < 16 => bench_scene(width, height, format, 1),
            Scene::Spacecraft => {
                let mut f = Frame::new(width, height, format)?;
                let cfg = crate::source::synth::SynthConfig { width, height, format, ..Default::default() };
                crate::source::synth::SynthSource::new(cfg).render_into(0, &mut f);
                f.seq = 0;
                f.pts_ns = 0;
                Ok(f)
            }
        }
    }
}

/// A seeded synthetic test scene for benchmarks and tests: a dark sky gradient with a lit
/// spacecraft-like body (textured), a few saturated specular spots (value FS) and a row of
/// stars. Deterministic in (size, format, seed).
pub fn bench_scene(width: u32, height: u32, format: PixelFormat, seed: u64) -> Result<Frame, crate::frame::FrameError> {
    let mut f = Frame::new(width, height, format)?;
    let fs = format.full_scale();
    let (w, h) = (width as f32, height as f32);
    let ch = format.channels();
    let mut rng = Rng::new(seed);
    // Saturated spots: (x, y, radius) in pixels.
    let spots: Vec<(f32, f32, f32)> = (0..6)
        .map(|_| {
            (
                (0.25 + 0.5 * rng.uniform_f32()) * w,
                (0.25 + 0.5 * rng.uniform_f32()) * h,
                (2.0 + 6.0 * rng.uniform_f32()) * (w / 1280.0).max(0.25),
            )
        })
        .collect();
    let stars: Vec<(usize, usize)> =
        (0..64).map(|_| (rng.below(width as u64) as usize, rng.below(height as u64) as usize)).collect();
    let tint = [1.0f32, 0.92, 0.8];
    let (cx, cy, rx, ry) = (0.5 * w, 0.55 * h, 0.3 * w, 0.2 * h);
    let texture_seed = rng.next_u64();
    crate::with_image_mut!(f, img => {
        for y in 0..img.height {
            let mut trng = Rng::new(texture_seed).derive(y as u64);
            let row = img.row_mut(y);
            for x in 0..(width as usize) {
                let (xf, yf) = (x as f32, y as f32);
                let mut v = 0.04 + 0.04 * yf / h;
                let (dx, dy) = ((xf - cx) / rx, (yf - cy) / ry);
                let d2 = dx * dx + dy * dy;
                if d2 < 1.0 {
                    // Lit body, brighter towards the upper left, with panel texture.
                    let panel = if ((x / 24) + (y / 24)) % 2 == 0 { 0.08 } else { 0.0 };
                    v = 0.35 + 0.3 * (1.0 - d2) - 0.15 * dx - 0.1 * dy + panel + 0.03 * trng.uniform_f32();
                }
                for &(sx, sy, r) in &spots {
                    let q = ((xf - sx) * (xf - sx) + (yf - sy) * (yf - sy)) / (r * r);
                    if q < 1.0 {
                        v = 1.5; // saturated
                    } else if q < 4.0 {
                        v = v.max(1.0 - 0.3 * (q - 1.0));
                    }
                }
                for c in 0..ch {
                    row[x * ch + c] = Sample::from_f32(v.min(1.0) * fs * if v >= 1.0 { 1.0 } else { tint[c % 3] });
                }
            }
        }
        for &(x, y) in &stars {
            for c in 0..ch {
                img.row_mut(y)[x * ch + c] = Sample::from_f32(0.8 * fs);
            }
        }
    });
    Ok(f)
}

#[cfg(test)]
mod tests {

    /// The even/odd merge against its definition, every width up to 100 (the 32-pixel vector
    /// steps, their tails, odd widths).
    #[test]
    fn merge_rgb8_eo_row_interleaves_even_and_odd_pixels() {
        for w in 0..100usize {
            let np = w.div_ceil(2);
            let e: Vec<Vec<u8>> = (0..3).map(|c| (0..np).map(|i| (7 * i + 50 * c) as u8).collect()).collect();
            let o: Vec<Vec<u8>> = (0..3).map(|c| (0..np).map(|i| (3 * i + 50 * c + 200) as u8).collect()).collect();
            let mut got = vec![0u8; 3 * w + 5];
            merge_rgb8_eo_row(&mut got, [&e[0], &e[1], &e[2]], [&o[0], &o[1], &o[2]], w);
            let mut want = vec![0u8; 3 * w + 5];
            for x in 0..w {
                for c in 0..3 {
                    want[3 * x + c] = if x % 2 == 0 { e[c][x / 2] } else { o[c][x / 2] };
                }
            }
            assert_eq!(got, want, "w {w}");
        }
    }
    use super::*;

    #[test]
    fn rgb8_split_and_merge_equal_the_plain_loops() {
        let mut r = Rng::new(11);
        for n in [0usize, 1, 15, 16, 17, 47, 48, 100, 333] {
            let src: Vec<u8> = (0..3 * n).map(|_| r.below(256) as u8).collect();
            let (mut a, mut b, mut c) = (vec![0u8; n], vec![0u8; n], vec![0u8; n]);
            split_rgb8_row(&src, &mut a, &mut b, &mut c);
            for i in 0..n {
                assert_eq!((a[i], b[i], c[i]), (src[3 * i], src[3 * i + 1], src[3 * i + 2]), "{n} px, pixel {i}");
            }
            let mut back = vec![0u8; 3 * n];
            merge_rgb8_row(&mut back, &a, &b, &c);
            assert_eq!(back, src, "{n} px");
        }
    }

    #[test]
    fn byte_lookup_and_threshold_masks_equal_their_references() {
        let mut r = Rng::new(5);
        let lut: [u8; 256] = std::array::from_fn(|v| ((v * 37 + 11) % 256) as u8);
        for n in [0usize, 1, 63, 64, 65, 127, 200, 1920, 5761] {
            let row: Vec<u8> = (0..n).map(|_| r.below(256) as u8).collect();
            let mut a = row.clone();
            lut_u8_row(&mut a, &lut);
            assert!(a.iter().zip(&row).all(|(&o, &v)| o == lut[v as usize]), "lut, {n} bytes");
            for thr in [0u8, 1, 128, 202, 255] {
                let words = n.div_ceil(64);
                let (mut fast, mut slow) = (vec![!0u64; words], vec![!0u64; words]);
                ge_mask_u8(&row, thr, &mut fast);
                ge_mask_u8_scalar(&row, thr, &mut slow);
                assert_eq!(fast, slow, "mask, {n} bytes, thr {thr}");
                for i in 0..n {
                    assert_eq!(fast[i / 64] >> (i % 64) & 1 == 1, row[i] >= thr);
                }
            }
        }
        // Byte Q16 gains (AVX2 16-bit lanes) equal the reference for every byte and length.
        let all: Vec<u8> = (0..=255u8).chain((0..300).map(|_| r.below(256) as u8)).collect();
        for gq in [0u32, 1, 32768, 65536, 78643, 98304, 131072, 1 << 20, (1 << 24) - 1, 1 << 24, 1 << 30] {
            for n in [0usize, 5, 31, 32, 33, 95, all.len()] {
                let mut fast = all[..n].to_vec();
                scale_q16_u8(&mut fast, gq);
                let want: Vec<u8> =
                    all[..n].iter().map(|&v| ((v as u64 * gq as u64 + 32768) >> 16).min(255) as u8).collect();
                assert_eq!(fast, want, "gq {gq}, {n} bytes");
            }
        }
        // Channel masks: every bit in exactly one channel; word 1 of a row starts at sample 64,
        // which is channel 1.
        for r in 0..3 {
            assert_eq!(RGB_CHANNEL_BITS[r].iter().fold(0, |a, m| a | m), u64::MAX);
            assert_eq!(RGB_CHANNEL_BITS[r][0] & RGB_CHANNEL_BITS[r][1], 0);
            assert_eq!(RGB_CHANNEL_BITS[r][r] & 1, 1);
        }
    }

    #[test]
    fn lanes_are_reproducible_and_uniform() {
        let p = Rng::new(3);
        let mut a = RngLanes::new(&p);
        let mut b = RngLanes::new(&p);
        let mut va = vec![0u32; 1003];
        let mut vb = vec![0u32; 1003];
        a.fill_u32(&mut va);
        b.fill_u32(&mut vb);
        assert_eq!(va, vb);
        let mut big = vec![0u32; 200_000];
        a.fill_u32(&mut big);
        let mean = big.iter().map(|&v| v as f64 / 4294967296.0).sum::<f64>() / big.len() as f64;
        // Uniform mean 0.5, std 0.2887/sqrt(n) = 6.5e-4; 5 sigma.
        assert!((mean - 0.5).abs() < 3.3e-3, "{mean}");
        // Every bit is set about half of the time (binomial std 112; 6 sigma).
        for bit in 0..32 {
            let ones = big.iter().filter(|&&v| v >> bit & 1 == 1).count() as f64;
            assert!((ones - 100_000.0).abs() < 672.0, "bit {bit}: {ones}");
        }
    }

    #[test]
    fn bernoulli_skipping_has_binomial_count() {
        let mut rng = Rng::new(11);
        let n = 1_000_000;
        for &p in &[1e-4, 0.01, 0.3] {
            let mut count = 0usize;
            let mut last = None;
            for_each_bernoulli(&mut rng, n, p, |i, _| {
                assert!(i < n && last.is_none_or(|l| i > l));
                last = Some(i);
                count += 1;
            });
            let sd = (n as f64 * p * (1.0 - p)).sqrt();
            assert!((count as f64 - n as f64 * p).abs() < 5.0 * sd, "p {p}: {count}");
        }
        let mut count = 0;
        for_each_bernoulli(&mut rng, 10, 1.0, |_, _| count += 1);
        assert_eq!(count, 10);
    }

    #[test]
    fn fixed_point_gain_rounds_like_floats() {
        for v in 0..=255u8 {
            for &g in &[0.0, 0.5, 0.75, 1.0, 1.3, 2.0] {
                let want = (v as f64 * g).round().min(255.0) as u8;
                assert_eq!(mul_gain_q(v, gain_to_q(g)), want, "{v} * {g}");
            }
        }
        assert_eq!(mul_gain_q(65535u16, gain_to_q(2.0)), 65535);
    }
}

multiversion! {
    /// `acc[i] += x[i]` (exact integer sums: the same values on every path; the caller keeps
    /// them within u32).
    pub fn accumulate_u32_row<T: Sample>(acc: &mut [u32], x: &[T]) {
        for (a, &v) in acc.iter_mut().zip(x) {
            *a += v.to_u32();
        }
    }
}

/// Length of the repeating addend pattern of [`add_lerp_runs_row`]: a multiple of 1 and 3
/// (the channel counts) and of the AVX2 f32 lane count.
const LERP_PATTERN: usize = 24;

/// Scalar reference of [`add_lerp_runs_row`] for any channel count.
#[inline(always)]
fn lerp_runs_any<T: Sample>(row: &mut [T], t: &[f32], runs: &[(u32, u32, u32)], cells: &[f32], ch: usize) {
    let gw = cells.len() / ch;
    for &(x0, x1, c0) in runs {
        let (x0, x1, c0) = (x0 as usize, x1 as usize, c0 as usize);
        let c1 = (c0 + 1).min(gw - 1);
        for x in x0..x1 {
            for c in 0..ch {
                let (p, q) = (cells[c0 * ch + c], cells[c1 * ch + c]);
                let v = &mut row[x * ch + c];
                *v = T::from_f32(v.to_f32() + (p + t[x * ch + c] * (q - p)));
            }
        }
    }
}

/// [`add_lerp_runs_row`] for `CH` channels: each run's `p` and `d` as a pattern of
/// [`LERP_PATTERN`] samples (built in registers), the samples in steps of the pattern.
#[inline(always)]
fn lerp_runs_ch<T: Sample, const CH: usize>(row: &mut [T], t: &[f32], runs: &[(u32, u32, u32)], cells: &[f32]) {
    let gw = cells.len() / CH;
    for &(x0, x1, c0) in runs {
        let (x0, x1, c0) = (x0 as usize, x1 as usize, c0 as usize);
        let c1 = (c0 + 1).min(gw - 1);
        let pc: [f32; CH] = std::array::from_fn(|c| cells[c0 * CH + c]);
        let dc: [f32; CH] = std::array::from_fn(|c| cells[c1 * CH + c] - pc[c]);
        let p: [f32; LERP_PATTERN] = std::array::from_fn(|k| pc[k % CH]);
        let d: [f32; LERP_PATTERN] = std::array::from_fn(|k| dc[k % CH]);
        let (r, tt) = (&mut row[x0 * CH..x1 * CH], &t[x0 * CH..x1 * CH]);
        let mut rc = r.chunks_exact_mut(LERP_PATTERN);
        let mut tc = tt.chunks_exact(LERP_PATTERN);
        for (r, tt) in (&mut rc).zip(&mut tc) {
            for k in 0..LERP_PATTERN {
                r[k] = T::from_f32(r[k].to_f32() + (p[k] + tt[k] * d[k]));
            }
        }
        for (((v, &tt), &pp), &dd) in rc.into_remainder().iter_mut().zip(tc.remainder()).zip(&p).zip(&d) {
            *v = T::from_f32(v.to_f32() + (pp + tt * dd));
        }
    }
}

multiversion! {
    /// Adds to a row of `ch`-channel pixels the linear interpolation between cell values, run by
    /// run: for each run `(x0, x1, c0)` (pixels `x0..x1`, left cell `c0`, right cell
    /// `c1 = min(c0 + 1, gw - 1)`) and channel c, `v = round(v + (p + t * (q - p)))` with
    /// `p = cells[c0 ch + c]`, `q = cells[c1 ch + c]` (cells interleaved, `gw x ch`) and `t` the
    /// sample's weight (`t[x ch + c]`). f32, a multiply then an add (no fused multiply-add);
    /// rounded half up and clipped to the sample range (`Sample::from_f32`): the same values on every path, without
    /// writing the addends out.
    pub fn add_lerp_runs_row<T: Sample>(row: &mut [T], t: &[f32], runs: &[(u32, u32, u32)], cells: &[f32], ch: usize) {
        #[cfg(target_arch = "x86_64")]
        if ch == 3
            && has_avx2()
            && let Some(r) = T::bytes_mut(row)
        {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { lerp_runs_rgb8_avx2(r, t, runs, cells) };
            return;
        }
        match ch {
            1 => lerp_runs_ch::<T, 1>(row, t, runs, cells),
            3 => lerp_runs_ch::<T, 3>(row, t, runs, cells),
            _ => lerp_runs_any(row, t, runs, cells, ch),
        }
    }
}

/// [`add_lerp_runs_row`] for RGB8 on AVX2: each run's `p` and `d` as three 8-lane patterns
/// (channel pattern 0 1 2 0 1 2 0 1, then 2 0 1 .., 1 2 0 ..) permuted in registers, 24 samples
/// a step; the same f32 operations in the same order as [`lerp_runs_any`] (a multiply then an
/// add, `max` giving 0 for NaN as `from_f32` does).
///
/// # Safety
/// AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn lerp_runs_rgb8_avx2(row: &mut [u8], t: &[f32], runs: &[(u32, u32, u32)], cells: &[f32]) {
    use std::arch::x86_64::*;
    let gw = cells.len() / 3;
    let (zero, half, top) = (_mm256_setzero_ps(), _mm256_set1_ps(0.5), _mm256_set1_ps(255.0));
    let idx = [
        _mm256_setr_epi32(0, 1, 2, 0, 1, 2, 0, 1),
        _mm256_setr_epi32(2, 0, 1, 2, 0, 1, 2, 0),
        _mm256_setr_epi32(1, 2, 0, 1, 2, 0, 1, 2),
    ];
    for &(x0, x1, c0) in runs {
        let (x0, x1, c0) = (x0 as usize, x1 as usize, c0 as usize);
        let c1 = (c0 + 1).min(gw - 1);
        let pc = [cells[c0 * 3], cells[c0 * 3 + 1], cells[c0 * 3 + 2]];
        let dc = [cells[c1 * 3] - pc[0], cells[c1 * 3 + 1] - pc[1], cells[c1 * 3 + 2] - pc[2]];
        let pv = _mm256_setr_ps(pc[0], pc[1], pc[2], 0.0, 0.0, 0.0, 0.0, 0.0);
        let dv = _mm256_setr_ps(dc[0], dc[1], dc[2], 0.0, 0.0, 0.0, 0.0, 0.0);
        let p = idx.map(|i| _mm256_permutevar8x32_ps(pv, i));
        let d = idx.map(|i| _mm256_permutevar8x32_ps(dv, i));
        let (r, tt) = (&mut row[x0 * 3..x1 * 3], &t[x0 * 3..x1 * 3]);
        let n = r.len();
        let mut i = 0;
        while i + 24 <= n {
            for j in 0..3 {
                let k = i + 8 * j;
                // SAFETY: k + 8 <= n: 8-byte and 8-float accesses inside the run's slices.
                unsafe {
                    let rp = r.as_mut_ptr().add(k);
                    let v = _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_loadl_epi64(rp as *const __m128i)));
                    let g = _mm256_add_ps(p[j], _mm256_mul_ps(_mm256_loadu_ps(tt.as_ptr().add(k)), d[j]));
                    let x = _mm256_min_ps(_mm256_max_ps(_mm256_add_ps(_mm256_add_ps(v, g), half), zero), top);
                    let q = _mm256_cvttps_epi32(x);
                    let w = _mm_packus_epi32(_mm256_castsi256_si128(q), _mm256_extracti128_si256(q, 1));
                    _mm_storel_epi64(rp as *mut __m128i, _mm_packus_epi16(w, w));
                }
            }
            i += 24;
        }
        // i is a multiple of 3: sample k is channel k % 3.
        for k in i..n {
            let c = k % 3;
            r[k] = u8::from_f32(r[k] as f32 + (pc[c] + tt[k] * dc[c]));
        }
    }
}

#[cfg(test)]
mod lerp_tests {
    use super::*;

    /// The dispatched kernels (RGB8 AVX2, the per-channel-count patterns) against the scalar
    /// reference on odd widths and run lengths, u8 and u16, 1 and 3 channels.
    #[test]
    fn lerp_runs_kernels_match_the_scalar_reference() {
        let mut rng = Rng::new(7);
        for ch in [1usize, 3] {
            for w in [1usize, 2, 7, 8, 23, 24, 25, 41, 97, 333] {
                for b in [1usize, 3, 8, 9, 40] {
                    let gw = w.div_ceil(b);
                    let cells: Vec<f32> = (0..gw * ch).map(|_| rng.uniform_f32() * 300.0 - 20.0).collect();
                    let t: Vec<f32> = (0..w * ch).map(|_| rng.uniform_f32()).collect();
                    let mut runs: Vec<(u32, u32, u32)> = Vec::new();
                    for x in 0..w {
                        let c0 = ((x / b) as u32).min(gw.saturating_sub(2) as u32);
                        match runs.last_mut() {
                            Some(r) if r.2 == c0 => r.1 = x as u32 + 1,
                            _ => runs.push((x as u32, x as u32 + 1, c0)),
                        }
                    }
                    let row8: Vec<u8> = (0..w * ch).map(|_| (rng.next_u64() & 255) as u8).collect();
                    let (mut a, mut e) = (row8.clone(), row8.clone());
                    add_lerp_runs_row(&mut a, &t, &runs, &cells, ch);
                    lerp_runs_any(&mut e, &t, &runs, &cells, ch);
                    assert_eq!(a, e, "u8 ch {ch} w {w} b {b}");
                    let row16: Vec<u16> = row8.iter().map(|&v| v as u16 * 257).collect();
                    let cells16: Vec<f32> = cells.iter().map(|v| v * 300.0).collect();
                    let (mut a, mut e) = (row16.clone(), row16.clone());
                    add_lerp_runs_row(&mut a, &t, &runs, &cells16, ch);
                    lerp_runs_any(&mut e, &t, &runs, &cells16, ch);
                    assert_eq!(a, e, "u16 ch {ch} w {w} b {b}");
                }
            }
        }
    }

    #[test]
    fn accumulate_u32_row_adds_every_sample() {
        for n in [0usize, 1, 7, 31, 33, 100] {
            let x: Vec<u8> = (0..n).map(|i| (i * 37 % 256) as u8).collect();
            let mut acc: Vec<u32> = (0..n as u32).collect();
            accumulate_u32_row(&mut acc, &x);
            assert!(acc.iter().enumerate().all(|(i, &a)| a == i as u32 + x[i] as u32));
        }
    }
}
