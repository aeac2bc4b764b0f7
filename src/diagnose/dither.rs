//! The per-value kernels of the dithered JPEG step (`select::Step::dithered_jpeg`): one noisy
//! copy of a 16-bit work plane, and the interleaving of three planes into an RGB frame and back.
//!
//! A dithered JPEG step runs these on every value of the fitted frames three times per
//! evaluation, which made them a quarter of a JPEG case's CPU in scalar code. The AVX2 form runs
//! the very same IEEE double operations in the same order (a division by 257, a product, a sum, a
//! product, a clamp, a truncation and a comparison; no fused multiply-add), so every path gives
//! the same bits (tested against the scalar form below).

/// `x.round().clamp(0, 65535) as u16`, exactly (round half away from zero), without the libm
/// call `f64::round` costs on the baseline x86-64 target.
#[inline]
pub fn round_clamp_u16(x: f64) -> u16 {
    // Branch-free: the fraction's test is a coin flip for noisy values, so a branch on it is
    // mispredicted half of the time. NaN converts to 0, as `NaN as u16` does.
    let y = x.clamp(0.0, 65535.0);
    let i = y as u32;
    // y - i is exact for 0 <= y <= 65535.
    (i + (y - i as f64 >= 0.5) as u32).min(65535) as u16
}

/// One dithered copy of a work plane: `out[i] = round_clamp_u16((m + sd[src[i]] * g[i]) * 257)`
/// with `m = src[i] / 257` (the value in 8-bit DN), for the common length of the slices.
/// `sd` is the dither sigma (DN) of each 16-bit level, `g` standard normal draws.
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
pub fn add_noise(out: &mut [u16], src: &[u16], g: &[f64], sd: &[f64; 65536]) {
    let n = out.len().min(src.len()).min(g.len());
    let (out, src, g) = (&mut out[..n], &src[..n], &g[..n]);
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if crate::faults::kit::has_avx2() {
        // SAFETY: AVX2 present (checked); the three slices hold n values.
        done = unsafe { simd::add_noise_avx2(out, src, g, sd) };
    }
    add_noise_scalar(&mut out[done..], &src[done..], &g[done..], sd);
}

fn add_noise_scalar(out: &mut [u16], src: &[u16], g: &[f64], sd: &[f64; 65536]) {
    for ((v, &s), &g) in out.iter_mut().zip(src).zip(g) {
        let m = s as f64 / 257.0;
        *v = round_clamp_u16((m + sd[s as usize] * g) * 257.0);
    }
}

/// Interleave three 16-bit planes (8-bit DN x 257) into RGB bytes, each rounded to 8 bits:
/// `rgb[3i + c] = round(planes[c][i] / 257)` (exact: no ties, the remainder is an integer).
pub fn interleave_rgb8(rgb: &mut [u8], r: &[u16], g: &[u16], b: &[u16]) {
    let to8 = |d: u16| ((d as u32 + 128) / 257) as u8;
    for (((px, &r), &g), &b) in rgb.chunks_exact_mut(3).zip(r).zip(g).zip(b) {
        px[0] = to8(r);
        px[1] = to8(g);
        px[2] = to8(b);
    }
}

/// The inverse of [`interleave_rgb8`] on 8-bit data: `planes[c][i] = rgb[3i + c] * 257`.
pub fn split_rgb8(rgb: &[u8], r: &mut [u16], g: &mut [u16], b: &mut [u16]) {
    for (((px, r), g), b) in rgb.chunks_exact(3).zip(r.iter_mut()).zip(g.iter_mut()).zip(b.iter_mut()) {
        *r = px[0] as u16 * 257;
        *g = px[1] as u16 * 257;
        *b = px[2] as u16 * 257;
    }
}

#[cfg(target_arch = "x86_64")]
mod simd {
    use std::arch::x86_64::*;

    /// Whole groups of 4 values; returns how many were written.
    #[target_feature(enable = "avx2")]
    pub unsafe fn add_noise_avx2(out: &mut [u16], src: &[u16], g: &[f64], sd: &[f64; 65536]) -> usize {
        let n = out.len() / 4 * 4;
        let c257 = _mm256_set1_pd(257.0);
        let zero = _mm256_setzero_pd();
        let top = _mm256_set1_pd(65535.0);
        let half = _mm256_set1_pd(0.5);
        let one = _mm256_set1_pd(1.0);
        let mut i = 0;
        while i < n {
            let s = [src[i], src[i + 1], src[i + 2], src[i + 3]];
            // SAFETY (block): i + 4 <= n <= len of every slice; the table lookups are by u16.
            unsafe {
                let sv = _mm256_set_pd(s[3] as f64, s[2] as f64, s[1] as f64, s[0] as f64);
                let sdv = _mm256_set_pd(sd[s[3] as usize], sd[s[2] as usize], sd[s[1] as usize], sd[s[0] as usize]);
                let gv = _mm256_loadu_pd(g.as_ptr().add(i));
                let m = _mm256_div_pd(sv, c257);
                let x = _mm256_mul_pd(_mm256_add_pd(m, _mm256_mul_pd(sdv, gv)), c257);
                // clamp: NaN becomes 0 here (max returns its second operand), as the scalar
                // form's NaN converts to 0.
                let y = _mm256_min_pd(_mm256_max_pd(x, zero), top);
                let t = _mm256_round_pd(y, _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC);
                let up = _mm256_and_pd(_mm256_cmp_pd(_mm256_sub_pd(y, t), half, _CMP_GE_OQ), one);
                let r = _mm256_min_pd(_mm256_add_pd(t, up), top);
                let r32 = _mm256_cvttpd_epi32(r);
                let r16 = _mm_packus_epi32(r32, r32);
                _mm_storel_epi64(out.as_mut_ptr().add(i) as *mut __m128i, r16);
            }
            i += 4;
        }
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The AVX2 form gives the scalar form's bits, including ties at half a level, values
    /// clamped at both ends and a NaN sigma.
    #[test]
    fn add_noise_is_the_same_on_every_path() {
        let mut sd = Box::new([0.0f64; 65536]);
        for (v, s) in sd.iter_mut().enumerate() {
            *s = 0.3 + (v as f64 / 65535.0) * 4.0;
        }
        sd[7] = f64::NAN;
        let n = 4099;
        let mut state = 0x9e3779b97f4a7c15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut src: Vec<u16> = (0..n).map(|_| (next() % 65536) as u16).collect();
        let mut g: Vec<f64> = (0..n).map(|_| ((next() % 20001) as f64 - 10000.0) / 2500.0).collect();
        // Edge values: zero and top codes, a NaN sigma, huge draws both ways, exact ties.
        src[..6].copy_from_slice(&[0, 65535, 7, 257, 514, 1000]);
        g[..6].copy_from_slice(&[-3.0, 3.0, 1.0, 1e9, -1e9, 0.0]);
        for i in 6..40 {
            // Near half a level (even i) and no noise at all (odd i).
            g[i] = if i % 2 == 0 { 0.5 / 257.0 / sd[src[i] as usize] } else { 0.0 };
        }
        let mut simd = vec![0u16; n];
        let mut scalar = vec![0u16; n];
        add_noise(&mut simd, &src, &g, &sd);
        add_noise_scalar(&mut scalar, &src, &g, &sd);
        assert_eq!(simd, scalar);
        // And the result is the documented formula.
        for i in 0..n {
            let want = round_clamp_u16((src[i] as f64 / 257.0 + sd[src[i] as usize] * g[i]) * 257.0);
            assert_eq!(scalar[i], want, "value {i}");
        }
        assert_eq!(scalar[0], 0);
        assert_eq!(scalar[1], 65535);
        assert_eq!(scalar[2], 0, "a NaN sigma gives 0, as a NaN cast does");
    }

    #[test]
    fn rgb_interleave_round_trips_8_bit_planes() {
        let n = 37;
        let r: Vec<u16> = (0..n).map(|i| (i * 7 % 256) as u16 * 257).collect();
        let g: Vec<u16> = (0..n).map(|i| (i * 3 % 255) as u16 * 257 + 100).collect();
        let b: Vec<u16> = (0..n).map(|i| (i as u16 * 257).saturating_sub(128)).collect();
        let mut rgb = vec![0u8; 3 * n];
        interleave_rgb8(&mut rgb, &r, &g, &b);
        for i in 0..n {
            assert_eq!(rgb[3 * i], (r[i] / 257) as u8);
            // 100 / 257 < 1/2: rounds down; 257 i - 128 rounds to i (half up).
            assert_eq!(rgb[3 * i + 1], (g[i] / 257) as u8);
            assert_eq!(rgb[3 * i + 2], i as u8);
        }
        let (mut r2, mut g2, mut b2) = (vec![0u16; n], vec![0u16; n], vec![0u16; n]);
        split_rgb8(&rgb, &mut r2, &mut g2, &mut b2);
        assert_eq!(r2, r);
        assert!(g2.iter().zip(&g).all(|(a, b)| *a == b - 100));
        assert!(b2.iter().enumerate().all(|(i, &v)| v == i as u16 * 257));
    }
}
