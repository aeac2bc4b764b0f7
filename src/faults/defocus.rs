//! `defocus`: isotropic Gaussian blur (defocus / diffraction / soft optics), separable.

use super::boxblur;
use super::fir16;
use super::kit::{ROWS_PER_TASK, axpy_row, band_rows, bands, mirrored_row_f32, par_bands_with, round_row};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, FrameData, Sample};
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "defocus",
    stage: Stage::Optics,
    order: 40,
    summary: "isotropic Gaussian point-spread function (defocus, soft optics)",
    model: "Convolution with an isotropic Gaussian PSF of standard deviation sigma_px, applied separably \
            (rows, then columns) with the discrete Gaussian kernel T(n) = exp(-s) I_n(s), s = sigma_px^2 \
            (Lindeberg's discrete analogue of the Gaussian: its variance is exactly sigma_px^2 even below one \
            pixel), truncated at |n| <= ceil(4 sigma_px) + 1 and renormalised. Borders are mirrored \
            (half-sample symmetric), which makes the operator conserve the total signal: the image mean is \
            kept up to the final rounding (zero on average). Channels are blurred independently. 8-bit \
            frames, sigma_px < 1.85: 16-bit fixed point (the kernel cut at |n| <= ceil(3 sigma_px + 0.45) and \
            renormalised, samples x 64, weights rounded to multiples of 2^-15 that sum exactly to 1, every \
            product rounded to nearest, the same integer operations on every CPU path): each output is \
            within 1 DN of the exact convolution (tested against an f64 reference on point sources and \
            hard edges; rounding alone accounts for 0.5 DN); cost grows with sigma_px (2 ceil(3 \
            sigma_px + 0.45) + 1 taps per axis). 8-bit frames, sigma_px >= 1.85: a pyramid (the Gaussian has \
            little above a quarter of the sampling rate there): per level, pre-filter with the binomial \
            [1,5,10,10,5,1]/32 and keep every second row and column (the coarse grid on the half-sample \
            points, so the mirrored borders stay half-sample mirrors), the discrete Gaussian of sigma_c \
            on the coarsest grid (the fixed-point FIR above), and per level an upsampler by 2 with the \
            same binomial (weights 5,10,1 / 16 and 1,10,5 / 16); one level below sigma_px 4.5, two \
            below 9.5, three from 9.5; the variances add: sigma_px^2 = 2.5 + 4 sigma_c^2, 12.5 + 16 \
            sigma_c^2 or 52.5 + 64 sigma_c^2. rgb8 runs as three planes (split and merged with byte \
            shuffles). Integer sums in 16-bit lanes with six roundings (pre-filter sums to v x 8 and \
            x 64, the coarse plane to x 16, the upsampler's vertical step to x 16, the last to 8 bits; \
            the rounding offset alternates between S/2 - 1 and S/2 from row to row, so the roundings \
            do not bias the mean), the same integer operations on every CPU path; all the weights sum \
            exactly to 1, so a flat image stays flat and the mean is kept (within 0.02 DN). Against \
            the discrete Gaussian this path is within 3 DN on point sources, hard edges and texture \
            (tested for sigma 1.85-20, even and odd frame sizes: 2.3 DN at sigma 1.85, 1.4 at 2, \
            largest 2.97 DN at sigma 13 and 2.9 at 2.75 (just above the level switches at 4.5 and 9.5 it is \
            2.2): the pre-filter's aliasing and the upsampler's images). 16-bit frames are computed \
            in f32 with the discrete Gaussian, rounded to nearest and clipped (|error| < 0.5 DN + f32 \
            rounding; cost grows with sigma_px). sigma_px = 0 is the identity.",
    params: &[ParamSpec::float("sigma_px", "px", 0.0, 20.0, 1.5, "standard deviation of the Gaussian PSF")],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(Defocus::default())
}

/// Discrete Gaussian kernel of variance `sigma^2` (taps -r..=r, normalised), r = ceil(4 sigma) + 1.
/// Computed with Miller's backward recurrence for the modified Bessel functions I_n(s).
pub fn discrete_gaussian(sigma: f64) -> Vec<f32> {
    discrete_gaussian_f64(sigma).into_iter().map(|v| v as f32).collect()
}

/// [`discrete_gaussian`] in f64.
pub fn discrete_gaussian_f64(sigma: f64) -> Vec<f64> {
    if sigma <= 0.0 {
        return vec![1.0];
    }
    let s = sigma * sigma;
    let r = (4.0 * sigma).ceil() as usize + 1;
    // Start well above r so the recurrence has converged at n <= r.
    let start = r + 20 + (10.0 * s.sqrt()) as usize + (2.0 * s) as usize;
    let mut vals = vec![0.0f64; start + 2];
    vals[start] = 1e-300;
    for n in (1..=start).rev() {
        vals[n - 1] = vals[n + 1] + (2.0 * n as f64 / s) * vals[n];
        if vals[n - 1] > 1e250 {
            for v in vals.iter_mut() {
                *v *= 1e-250;
            }
        }
    }
    // exp(s) = I_0 + 2 sum_{n>=1} I_n.
    let total = vals[0] + 2.0 * vals[1..].iter().sum::<f64>();
    let half: Vec<f64> = vals[..=r].iter().map(|v| v / total).collect();
    let mut k: Vec<f64> = half[1..].iter().rev().chain(half.iter()).copied().collect();
    let sum: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    k
}

/// The 8-bit paths' kernel: the discrete Gaussian `k` of `sigma` cut to |n| <= ceil(3 sigma + 0.45)
/// and renormalised (the weight cut, both tails, is at most 9.9e-4 of the total for sigma < 1.85
/// and 1.06e-3 for the coarse sigmas up to 2.33: at most 0.14 DN on a full-scale edge, against the
/// fixed-point rounding's 0.5 DN). The 0.45 keeps six taps a side up to sigma 1.85, where the
/// pyramid takes over (seven from 5/3 with ceil(3 sigma) + 1: 4.4 ms instead of 3.8 ms rgb8).
fn truncated(k: &[f64], sigma: f64) -> Vec<f64> {
    let r = k.len() / 2;
    let r8 = ((3.0 * sigma + 0.45).ceil() as usize).min(r);
    let mut t = k[r - r8..=r + r8].to_vec();
    let sum: f64 = t.iter().sum();
    t.iter_mut().for_each(|v| *v /= sum);
    t
}

/// Half-sample symmetric index into [0, n).
#[inline]
pub fn mirror(i: isize, n: usize) -> usize {
    let n2 = 2 * n as isize;
    let m = i.rem_euclid(n2);
    if m >= n as isize { (n2 - 1 - m) as usize } else { m as usize }
}

/// 8-bit frames up to this sigma_px use the exact FIR (`fir16`, cost linear in sigma), above it
/// the box cascade (`boxblur`, cost independent of sigma).
pub const FIR_MAX_SIGMA: f64 = 3.0;

/// Stated bound of the box-cascade path against the exact discrete Gaussian (DN, 8-bit), on point
/// sources and hard edges (measured: 3.6 DN just above FIR_MAX_SIGMA, 2 DN at sigma 13-20): the
/// cascade's step-response error on each axis plus the rounding.
pub const BOX_MAX_ERROR_DN: f64 = 4.0;

/// Stated bound of the pyramid path against the exact discrete Gaussian (DN, 8-bit) on point
/// sources, hard edges and texture (measured: 2.3 DN at sigma 1.85, 2.9 at 2.75 and at 13, 2.6
/// at 5.5): the pre-filter's aliasing and the upsampler's images, which the Gaussian attenuates
/// less at a small coarse sigma (just above each level switch), plus the roundings. Below sigma
/// 1.85 the error grows fast (3.0 DN at 1.8, 6.4 at 1.6), so the FIR stays there.
pub const PYR_MAX_ERROR_DN: f64 = 3.0;

/// Largest kernel radius (sigma_px = 20: ceil(80) + 1).
pub(crate) const MAX_R: usize = 81;

#[derive(Default)]
pub struct Defocus {
    kernel_key: Option<u64>,
    kernel: Vec<f32>,
    // allocation: once per sigma: Q15 half kernel (centre first) for 8-bit frames
    q15: Vec<i16>,
    // 8-bit frames with sigma_px > FIR_MAX_SIGMA: the box cascade and its scratch
    boxes: Option<boxblur::BoxPlan>,
    box_scratch: boxblur::Scratch,
    // 8-bit frames with sigma_px >= PYR_MIN_SIGMA: levels, the coarse FIR, scratch
    pyr: Option<(usize, Option<Vec<i16>>)>,
    pyr_scratch: PyrScratch,
    // allocation: when the frame size or the kernel radius grows: 8-bit frames: per band the
    // source rows it does not own, and a ring of row-pass rows, a padded row and an output row
    halo8: Vec<u8>,
    work16: Vec<i16>,
    // allocation: once per frame size: f32 copy of the frame after the row pass
    tmp: Vec<f32>,
    // allocation: once per frame size: per band, a mirrored input row (pass 1) and an
    // accumulator row (pass 2)
    pad: Vec<f32>,
    acc: Vec<f32>,
}

/// Row pass: each input row, mirrored at its ends, convolved into `tmp` (packed, w*ch per row).
fn row_pass<T: Sample>(src: &[T], stride: usize, w: usize, ch: usize, k: &[f32], tmp: &mut [f32], pad: &mut [f32]) {
    let r = k.len() / 2;
    let rl = w * ch;
    let padw = (w + 2 * r) * ch;
    tmp.par_chunks_mut(rl * ROWS_PER_TASK).zip(pad.par_chunks_mut(padw)).enumerate().for_each(|(b, (out, pad))| {
        for (i, orow) in out.chunks_mut(rl).enumerate() {
            let y = b * ROWS_PER_TASK + i;
            let irow = &src[y * stride..y * stride + rl];
            mirrored_row_f32(irow, w, ch, r, pad);
            orow.fill(0.0);
            for (j, &kj) in k.iter().enumerate() {
                let src = &pad[j * ch..j * ch + rl];
                axpy_row(orow, kj, src, 0u8);
            }
        }
    });
}

/// Column pass: output row y = sum_j k_j tmp[mirror(y + j - r)].
fn col_pass<T: Sample>(dst: &mut [T], stride: usize, h: usize, rl: usize, k: &[f32], tmp: &[f32], acc: &mut [f32]) {
    let r = k.len() / 2;
    par_bands_with(dst, stride, h, acc, rl, |_, y0, band, acc| {
        for (i, orow) in band_rows(band, stride, rl).enumerate() {
            let y = y0 + i;
            acc.fill(0.0);
            for (j, &kj) in k.iter().enumerate() {
                let sy = mirror(y as isize + j as isize - r as isize, h);
                let src = &tmp[sy * rl..(sy + 1) * rl];
                axpy_row(acc, kj, src, 0u8);
            }
            round_row(orow, acc);
        }
    });
}

/// Rows per task of the 8-bit blur (at least; `6 r` for wide kernels, so the recomputed halo
/// stays small). Each task filters its rows from the source rows it needs (its own, plus copies of
/// `r` rows on each side, taken before any task writes), so the bytes do not depend on the band
/// size or the thread count.
const BLUR_BAND: usize = 120;

/// Rows `y'` in `[y0 - r, y1 + r)` whose source row `mirror(y')` is not read from the band itself
/// (outside the band, or mirrored at the bottom edge): these are copied to the halo first.
#[inline]
pub(crate) fn from_halo(yv: isize, y0: usize, y1: usize, h: usize) -> bool {
    let s = mirror(yv, h);
    !(s as isize == yv && (y0..y1).contains(&s))
}

/// Pass 1 of the in-place banded blurs (`defocus`'s FIR, `motion_blur`'s FIR): for every band
/// `b` of `rows_per` rows, copies the rows `from_halo` names (reach `r` above and below) from the
/// still unmodified frame `src` (`rl` bytes of each `stride`) into the band's `per_halo` slice
/// of `halo`, in order of the virtual row, so no band reads a row another band overwrites.
#[allow(clippy::too_many_arguments)]
pub(crate) fn fill_band_halos(
    src: &[u8],
    halo: &mut [u8],
    per_halo: usize,
    rows_per: usize,
    h: usize,
    r: usize,
    stride: usize,
    rl: usize,
) {
    halo.par_chunks_mut(per_halo.max(1)).enumerate().for_each(|(b, hb)| {
        let (y0, y1) = (b * rows_per, ((b + 1) * rows_per).min(h));
        let mut j = 0;
        for yv in y0 as isize - r as isize..(y1 + r) as isize {
            if from_halo(yv, y0, y1, h) {
                let s = mirror(yv, h);
                hb[j * rl..(j + 1) * rl].copy_from_slice(&src[s * stride..s * stride + rl]);
                j += 1;
            }
        }
    });
}

/// Q6 (`v * 64`) copy of 8-bit row `src`, mirrored by `r` pixels at both ends, into `pad`.
pub(crate) fn pad_row_q6(src: &[u8], w: usize, ch: usize, r: usize, pad: &mut [i16]) {
    let c = r * ch;
    fir16::u8_to_q6(&mut pad[c..c + w * ch], src);
    for px in (0..r).chain(r + w..w + 2 * r) {
        let sx = mirror(px as isize - r as isize, w);
        for k in 0..ch {
            pad[px * ch + k] = (src[sx * ch + k] as i16) << fir16::SAMPLE_Q;
        }
    }
}

/// 8-bit separable blur, fused: per band of [`BLUR_BAND`] output rows, the row pass fills a ring
/// of `2r + 1` Q6 rows (in cache) that the column pass reads; the result is rounded to 8 bits.
/// `halo` and `work` are scratch (resized here; they only grow).
#[allow(clippy::too_many_arguments)]
fn blur_u8(
    d: &mut [u8],
    stride: usize,
    w: usize,
    h: usize,
    ch: usize,
    q: &[i16],
    halo: &mut Vec<u8>,
    work: &mut Vec<i16>,
) {
    let r = q.len() - 1;
    let rl = w * ch;
    // Ring of 2r + 2 row-pass rows: two output rows per column step (`fir16::sym_fir2`).
    let n = 2 * r + 2;
    let padw = (w + 2 * r) * ch;
    let rows_per = BLUR_BAND.max(6 * r);
    let nb = h.div_ceil(rows_per);
    let per_halo = 3 * r * rl;
    let per_work = n * rl + padw + 2 * rl;
    if halo.len() < per_halo * nb {
        halo.resize(per_halo * nb, 0);
    }
    if work.len() < per_work * nb {
        work.resize(per_work * nb, 0);
    }
    let bounds = |b: usize| (b * rows_per, ((b + 1) * rows_per).min(h));
    // Pass 1: copy the rows each band needs but does not own (the frame is still unmodified).
    fill_band_halos(d, &mut halo[..per_halo * nb], per_halo, rows_per, h, r, stride, rl);
    // Pass 2: the bands.
    let used = d.len().min(stride * h);
    d[..used]
        .par_chunks_mut(stride * rows_per)
        .zip(halo[..per_halo * nb].par_chunks(per_halo.max(1)))
        .zip(work[..per_work * nb].par_chunks_mut(per_work))
        .enumerate()
        .for_each(|(b, ((band, hb), wk))| {
            let (y0, y1) = bounds(b);
            let (ring, rest) = wk.split_at_mut(n * rl);
            let (pad, acc) = rest.split_at_mut(padw);
            let first = y0 as isize - r as isize;
            let slot = |yv: isize| (yv - first) as usize % n;
            let mut j = 0;
            let offs_row: [(usize, usize); MAX_R + 1] =
                std::array::from_fn(|k| if k <= r { (r * ch - k * ch, r * ch + k * ch) } else { (0, 0) });
            // Row pass of virtual row yv into its ring slot.
            let mut produce = |yv: isize, band: &[u8], ring: &mut [i16]| {
                let src = if from_halo(yv, y0, y1, h) {
                    j += 1;
                    &hb[(j - 1) * rl..j * rl]
                } else {
                    let i = yv as usize - y0;
                    &band[i * stride..i * stride + rl]
                };
                pad_row_q6(src, w, ch, r, pad);
                let k = slot(yv);
                fir16::sym_fir(&mut ring[k * rl..(k + 1) * rl], pad, r * ch, &offs_row[..=r], q);
            };
            for yv in first..y0 as isize + r as isize {
                produce(yv, band, ring);
            }
            let mut offs = [(0usize, 0usize); MAX_R + 1];
            let mut rows = [0usize; 2 * MAX_R + 2];
            let mut y = y0;
            while y < y1 {
                let yi = y as isize;
                let i = y - y0;
                produce(yi + r as isize, band, ring);
                if y + 1 < y1 {
                    // Two output rows from 2r + 2 ring rows.
                    produce(yi + 1 + r as isize, band, ring);
                    for (t, o) in rows.iter_mut().enumerate().take(2 * r + 2) {
                        *o = slot(yi - r as isize + t as isize) * rl;
                    }
                    let (a0, a1) = acc.split_at_mut(rl);
                    fir16::sym_fir2(a0, a1, ring, &rows[..2 * r + 2], q);
                    fir16::q6_to_u8(&mut band[i * stride..i * stride + rl], a0);
                    fir16::q6_to_u8(&mut band[(i + 1) * stride..(i + 1) * stride + rl], a1);
                    y += 2;
                    continue;
                }
                for (k, o) in offs.iter_mut().enumerate().take(r + 1) {
                    *o = (slot(yi - k as isize) * rl, slot(yi + k as isize) * rl);
                }
                fir16::sym_fir(&mut acc[..rl], ring, slot(yi) * rl, &offs[..=r], q);
                fir16::q6_to_u8(&mut band[i * stride..i * stride + rl], &acc[..rl]);
                y += 1;
            }
        });
}

// ---------------------------------------------------------------------------------------------
// Pyramid path (8-bit frames, sigma_px >= PYR_MIN_SIGMA): the Gaussian computed on a grid of half
// (a quarter, an eighth of) the resolution. All integer arithmetic in plain Rust (exact on every CPU
// path; the compiler's vectorisation cannot change the values), compiled once more with AVX2
// and with AVX-512 enabled for the CPUs that have them.

/// 8-bit frames from this sigma_px use the pyramid (`pyr_blur_u8`); below it the FIR.
pub const PYR_MIN_SIGMA: f64 = 1.85;
/// From this sigma_px the pyramid has two levels (x4), below it one (x2).
pub const PYR_TWO_LEVELS: f64 = 4.5;
/// From this sigma_px the pyramid has three levels (x8): the coarse Gaussian there has sigma
/// 0.77 coarse px (as at the other switch points, >= 0.7), and the FIR at sigma 20 has 12 taps
/// per axis on 1/64 of the samples instead of 22 on 1/16.
pub const PYR_THREE_LEVELS: f64 = 9.5;
/// Variance (full-resolution px^2, per axis) added by one level's decimating pre-filter and its
/// upsampler: each is the binomial [1,5,10,10,5,1]/32 (variance 5/4).
const LEVEL_VAR: f64 = 2.5;

/// Number of levels and the coarse Gaussian's sigma (in coarse pixels) for `sigma`: the
/// variances add, level l's filters counting 4^(l-1) times theirs: sigma^2 = 2.5 + 4 s^2 with
/// one level, 2.5 (1 + 4) + 16 s^2 with two, 2.5 (1 + 4 + 16) + 64 s^2 with three.
pub fn pyr_split(sigma: f64) -> (usize, f64) {
    let levels = if sigma >= PYR_THREE_LEVELS {
        3
    } else if sigma >= PYR_TWO_LEVELS {
        2
    } else {
        1
    };
    let (fixed, scale) = match levels {
        1 => (LEVEL_VAR, 4.0),
        2 => (LEVEL_VAR * 5.0, 16.0),
        _ => (LEVEL_VAR * 21.0, 64.0),
    };
    (levels, ((sigma * sigma - fixed) / scale).max(0.0).sqrt())
}

/// An i16 Q6 image (`v * 64`) of `w x h` pixels and `ch` channels with `m` pixels of margin on
/// every side (real samples of the mirrored extension, not mirrored again): pixel (x, y) for
/// x, y in -m..w+m.
#[derive(Default)]
pub(crate) struct Plane {
    w: usize,
    h: usize,
    m: usize,
    ch: usize,
    d: Vec<i16>,
}

impl Plane {
    fn set(&mut self, w: usize, h: usize, m: usize, ch: usize) {
        self.set_rows(w, h, m, ch, h + 2 * m);
    }
    /// As [`Plane::set`] with storage for `rows` rows only (a ring: row `jj` in slot `jj % rows`).
    fn set_rows(&mut self, w: usize, h: usize, m: usize, ch: usize, rows: usize) {
        (self.w, self.h, self.m, self.ch) = (w, h, m, ch);
        // Grow only: the planes change size between stages and channels (no refill each time).
        let need = (w + 2 * m) * rows * ch + PLANE_SLACK;
        if self.d.len() < need {
            self.d.resize(need, 0);
        }
    }
    fn rl(&self) -> usize {
        (self.w + 2 * self.m) * self.ch
    }
    /// The rows (without the slack).
    fn rows_mut(&mut self) -> impl Iterator<Item = &mut [i16]> {
        let (rl, n) = (self.rl(), self.h + 2 * self.m);
        self.d[..rl * n].chunks_mut(rl)
    }
    /// Row `jj` counted from the top margin row.
    fn row_mut(&mut self, jj: usize) -> &mut [i16] {
        let rl = self.rl();
        &mut self.d[jj * rl..(jj + 1) * rl]
    }
    fn row(&self, y: isize) -> &[i16] {
        self.row_at((y + self.m as isize) as usize)
    }
    /// Row `jj` of the storage (counted from the top margin row; a ring's slot).
    fn row_at(&self, jj: usize) -> &[i16] {
        &self.d[jj * self.rl()..(jj + 1) * self.rl()]
    }
}

/// Rows of the first level's ring when the pyramid has more levels (each second-level row reads
/// six first-level rows; eight slots, so the rows still needed are never overwritten).
const L1_RING: usize = 8;

/// Rows of the last upsampler's ring (the final upsampler reads three consecutive rows).
const FIN_RING: usize = 4;

/// Samples after the last row of a plane: the FIR runs whole 128-sample chunks past the row ends
/// (those outputs are not used).
const PLANE_SLACK: usize = 256;

/// Scratch of the pyramid path (grows only). allocation: when the frame size or sigma grows.
#[derive(Default)]
pub(crate) struct PyrScratch {
    /// Per channel: the first level, and the plane the final upsampler reads.
    dec: [Plane; 3],
    fin: [Plane; 3],
    /// Per channel: the second level (the first is then a ring of [`L1_RING`] rows).
    l2: [Plane; 3],
    l3: Plane,
    t: Plane,
    row32: Vec<i32>,
    /// Per channel: a ring of horizontal decimation sums (`hdec_q6`).
    h32: [Vec<i32>; 3],
    pad16: Vec<u16>,
    split16: Vec<u16>,
    msrc: Vec<(u32, u32)>,
    f16: Vec<i16>,
    v16: Vec<u16>,
    eo8: Vec<u8>,
}

/// Binomial [1,5,10,10,5,1]: the decimating pre-filter (weights / 32).
#[cfg(test)]
const B5: [i32; 6] = [1, 5, 10, 10, 5, 1];

macro_rules! multiversion {
    ($(#[$m:meta])* fn $name:ident($($a:ident: $t:ty),*) $body:block) => {
        $(#[$m])*
        fn $name($($a: $t),*) {
            #[inline(always)]
            fn imp($($a: $t),*) $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
                unsafe fn v512($($a: $t),*) { imp($($a),*) }
                #[target_feature(enable = "avx2")]
                unsafe fn v256($($a: $t),*) { imp($($a),*) }
                if super::kit::has_avx512() {
                    // SAFETY: the CPU has AVX-512 F/BW/VL (checked).
                    return unsafe { v512($($a),*) };
                }
                if super::kit::has_avx2() {
                    // SAFETY: the CPU has AVX2 (checked).
                    return unsafe { v256($($a),*) };
                }
            }
            imp($($a),*)
        }
    };
}

multiversion! {
    /// `out[i] = (sum_k B5[k] rows[k][i] + rnd) >> 2` for u8 rows (units v * 8, at most 2040: the
    /// decimating horizontal pass then fits 16-bit lanes). `rnd` 1 or 2 (see [`rnd`]).
    fn vsum_u8(out: &mut [u16], r0: &[u8], r1: &[u8], r2: &[u8], r3: &[u8], r4: &[u8], r5: &[u8], rnd: u16) {
        let n = out.len();
        let (r0, r1, r2, r3, r4, r5) = (&r0[..n], &r1[..n], &r2[..n], &r3[..n], &r4[..n], &r5[..n]);
        for i in 0..n {
            let s = (r0[i] as u16 + r5[i] as u16) + 5 * (r1[i] as u16 + r4[i] as u16) + 10 * (r2[i] as u16 + r3[i] as u16);
            out[i] = (s + rnd) >> 2;
        }
    }
}

/// Decimating horizontal pass of one channel in u16 lanes (units v * 8 in, at most 2040):
/// `out[i] = (sum_k B5[k] pad[2i + k] + rnd) >> 2` (Q6; the sum is at most 65280).
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
fn hdec16(out: &mut [i16], pad: &[u16], rnd: u16) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx2() {
        // SAFETY: the CPU has AVX2 (checked).
        done = unsafe { hdec16_avx2(out, pad, rnd) };
    }
    hdec16_plain(&mut out[done..], &pad[2 * done..], rnd);
}

/// [`hdec16`], the portable loop.
fn hdec16_plain(out: &mut [i16], pad: &[u16], rnd: u16) {
    let n = out.len();
    let pad = &pad[..2 * n + 4];
    for i in 0..n {
        let p = &pad[2 * i..2 * i + 6];
        let s = (p[0] + p[5]) + 5 * (p[1] + p[4]) + 10 * (p[2] + p[3]);
        out[i] = ((s + rnd) >> 2) as i16;
    }
}

/// [`hdec16`] on AVX2, 16 outputs per step; returns the outputs done (a multiple of 16). The
/// samples as pixel pairs in 32-bit lanes: `vpmaddwd` with (1, 5), (10, 10) and (5, 1) on the
/// pairs at 2i, 2i + 2 and 2i + 4 gives the six-tap sum of output i exactly (the samples are
/// below 2^15, the sums below 2^16), the same integers as the plain loop (the compiler's code
/// for the stride-2 loop was half as fast on AVX2).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn hdec16_avx2(out: &mut [i16], pad: &[u16], rnd: u16) -> usize {
    use std::arch::x86_64::*;
    let n = out.len() / 16 * 16;
    assert!(pad.len() >= 2 * out.len() + 4);
    // SAFETY: step i reads pad[2i ..= 2i + 35] (2i + 35 <= 2n + 3 < pad.len()) and writes
    // out[i .. i + 16] (i + 16 <= n <= out.len()).
    unsafe {
        let c0 = _mm256_set1_epi32(1 | (5 << 16));
        let c1 = _mm256_set1_epi32(10 | (10 << 16));
        let c2 = _mm256_set1_epi32(5 | (1 << 16));
        let r = _mm256_set1_epi32(rnd as i32);
        let p = pad.as_ptr();
        let sum8 = |q: *const u16| {
            let a = _mm256_madd_epi16(_mm256_loadu_si256(q as *const __m256i), c0);
            let b = _mm256_madd_epi16(_mm256_loadu_si256(q.add(2) as *const __m256i), c1);
            let c = _mm256_madd_epi16(_mm256_loadu_si256(q.add(4) as *const __m256i), c2);
            _mm256_srli_epi32::<2>(_mm256_add_epi32(_mm256_add_epi32(a, b), _mm256_add_epi32(c, r)))
        };
        for i in (0..n).step_by(16) {
            let lo = sum8(p.add(2 * i));
            let hi = sum8(p.add(2 * i + 16));
            let v = _mm256_permute4x64_epi64::<0xD8>(_mm256_packus_epi32(lo, hi));
            _mm256_storeu_si256(out.as_mut_ptr().add(i) as *mut __m256i, v);
        }
    }
    n
}

multiversion! {
    /// Three-channel interleaved u16 row to three rows of `a.len()` samples.
    fn split3_u16(src: &[u16], a: &mut [u16], b: &mut [u16], c: &mut [u16]) {
        let n = a.len();
        let (b, c, src) = (&mut b[..n], &mut c[..n], &src[..3 * n]);
        for i in 0..n {
            a[i] = src[3 * i];
            b[i] = src[3 * i + 1];
            c[i] = src[3 * i + 2];
        }
    }
}

/// Horizontal B5 sums at every second sample of a Q6 row (one channel): `out[i] = sum_k B5[k]
/// row[2i + k]` in i32 (`row` holds at least 2 out.len() + 4 samples). The decimation of the
/// second and third levels runs horizontally first (each input row once, into a ring), then
/// vertically ([`vdec_q6`]): the same integer sums as vertical-first, in the other order.
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
fn hdec_q6(out: &mut [i32], row: &[i16]) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx2() {
        // SAFETY: the CPU has AVX2 (checked).
        done = unsafe { hdec_q6_avx2(out, row) };
    }
    let n = out.len();
    let row = &row[..2 * n + 4];
    for i in done..n {
        let p = &row[2 * i..2 * i + 6];
        out[i] = (p[0] as i32 + p[5] as i32) + 5 * (p[1] as i32 + p[4] as i32) + 10 * (p[2] as i32 + p[3] as i32);
    }
}

/// [`hdec_q6`] on AVX2, 8 outputs per step (`vpmaddwd` on sample pairs, as [`hdec16_avx2`]; the
/// products and sums are exact in i32); returns the outputs done (a multiple of 8).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn hdec_q6_avx2(out: &mut [i32], row: &[i16]) -> usize {
    use std::arch::x86_64::*;
    let n = out.len() / 8 * 8;
    assert!(row.len() >= 2 * out.len() + 4);
    // SAFETY: step i reads row[2i ..= 2i + 19] (2i + 19 <= 2n + 3 < row.len()) and writes
    // out[i .. i + 8] (i + 8 <= n <= out.len()).
    unsafe {
        let c0 = _mm256_set1_epi32(1 | (5 << 16));
        let c1 = _mm256_set1_epi32(10 | (10 << 16));
        let c2 = _mm256_set1_epi32(5 | (1 << 16));
        let p = row.as_ptr();
        for i in (0..n).step_by(8) {
            let q = p.add(2 * i);
            let a = _mm256_madd_epi16(_mm256_loadu_si256(q as *const __m256i), c0);
            let b = _mm256_madd_epi16(_mm256_loadu_si256(q.add(2) as *const __m256i), c1);
            let c = _mm256_madd_epi16(_mm256_loadu_si256(q.add(4) as *const __m256i), c2);
            _mm256_storeu_si256(out.as_mut_ptr().add(i) as *mut __m256i, _mm256_add_epi32(_mm256_add_epi32(a, b), c));
        }
    }
    n
}

multiversion! {
    /// Vertical step of the decimation after [`hdec_q6`]: `out[i] = (sum_k B5[k] rows[k][i] +
    /// 512) >> 10` (units q * 1024 to Q6).
    fn vdec_q6(out: &mut [i16], r0: &[i32], r1: &[i32], r2: &[i32], r3: &[i32], r4: &[i32], r5: &[i32]) {
        let n = out.len();
        let (r0, r1, r2, r3, r4, r5) = (&r0[..n], &r1[..n], &r2[..n], &r3[..n], &r4[..n], &r5[..n]);
        for i in 0..n {
            let s = (r0[i] + r5[i]) + 5 * (r1[i] + r4[i]) + 10 * (r2[i] + r3[i]);
            out[i] = ((s + 512) >> 10) as i16;
        }
    }
}

/// Level 1 from the 8-bit frame, one plane per channel (`outs[c]`): low-res pixel i (at
/// full-res position 2i + 1/2) = the B5 pre-filter over full-res pixels 2i - 2 ..= 2i + 3
/// (mirrored at the frame's borders), for i in -m..ceil(w/2) + m, likewise in y. Vertical sums
/// on the interleaved rows (rounded to v * 8), split per channel, horizontal sums rounded to Q6.
#[allow(clippy::too_many_arguments)]
fn decimate_u8(
    d: &[u8],
    stride: usize,
    w: usize,
    h: usize,
    ch: usize,
    m: usize,
    outs: &mut [Plane],
    ring: Option<usize>,
    pad16: &mut Vec<u16>,
    split16: &mut Vec<u16>,
    msrc: &mut Vec<(u32, u32)>,
    after: &mut dyn FnMut(usize, &[Plane]),
) {
    let (wl, hl) = (w.div_ceil(2), h.div_ceil(2));
    for o in outs.iter_mut() {
        o.set_rows(wl, hl, m, 1, ring.unwrap_or(hl + 2 * m));
    }
    let rl = w * ch;
    let np = 2 * (wl + 2 * m) + 4; // full-res columns -2m-2 ..= 2(wl+m-1)+3
    pad16.resize(np * ch, 0);
    split16.resize(3 * np, 0);
    let x0 = -2 * m as isize - 2;
    let rows = hl + 2 * m;
    let a = (-x0) as usize;
    let inner = (np - a).min(w);
    // The margin columns and the interior column each copies (mirrored), once per call.
    msrc.clear();
    msrc.extend((0..a).chain(a + inner..np).map(|px| (px as u32, mirror(px as isize + x0, w) as u32)));
    for jj in 0..rows {
        let j = jj as isize - m as isize;
        let slot = ring.map_or(jj, |n| jj % n);
        let r = |k: isize| {
            let y = mirror(2 * j - 2 + k, h);
            &d[y * stride..y * stride + rl]
        };
        // Interior columns in place, margins mirrored from them.
        vsum_u8(&mut pad16[a * ch..(a + inner) * ch], r(0), r(1), r(2), r(3), r(4), r(5), rnd(jj, 0));
        for &(px, sx) in msrc.iter() {
            let (px, sx) = (px as usize * ch, (a + sx as usize) * ch);
            pad16.copy_within(sx..sx + ch, px);
        }
        if ch == 1 {
            hdec16(outs[0].row_mut(slot), pad16, rnd(jj, 1));
        } else {
            let (s0, rest) = split16.split_at_mut(np);
            let (s1, s2) = rest.split_at_mut(np);
            split3_u16(pad16, s0, s1, s2);
            for (o, sp) in outs.iter_mut().zip([&*s0, &*s1, &*s2]) {
                hdec16(o.row_mut(slot), sp, rnd(jj, 1));
            }
        }
        after(jj, outs);
    }
}

/// The next level from a Q6 plane (margin `inp.m >= 2 m + 3`): as [`decimate_u8`] on the
/// plane's own samples (its margins are real samples, no mirroring).
fn decimate_q6(inp: &Plane, m: usize, out: &mut Plane, h32: &mut Vec<i32>) {
    let (wl, hl) = (inp.w.div_ceil(2), inp.h.div_ceil(2));
    assert!(inp.m >= 2 * m + 3 && inp.ch == 1);
    out.set(wl, hl, m, 1);
    let n = wl + 2 * m;
    h32.resize(H_RING * n, 0);
    // Input column -2m-2 is at index (inp.m - 2m - 2) of each input row; output row jj reads
    // input rows (counted from the top margin row) 2 jj + s .. 2 jj + s + 5, s = inp.m - 2m - 2.
    let off = inp.m - 2 * m - 2;
    let mut made = off;
    for (jj, orow) in out.rows_mut().enumerate() {
        let i0 = 2 * jj + off;
        while made < i0 + 6 {
            hdec_q6(&mut h32[(made % H_RING) * n..(made % H_RING + 1) * n], &inp.row_at(made)[off..]);
            made += 1;
        }
        let r = |k: usize| &h32[((i0 + k) % H_RING) * n..((i0 + k) % H_RING + 1) * n];
        vdec_q6(orow, r(0), r(1), r(2), r(3), r(4), r(5));
    }
}

/// Rows of the ring of horizontal decimation sums (six read per output row).
const H_RING: usize = 8;

/// Separable discrete-Gaussian FIR (`fir16::sym_fir`, Q15 half kernel `q`) on a plane; the
/// margin shrinks by the radius (`out` gets margin `inp.m - r`). Returns nothing; `t` scratch.
fn fir_plane(inp: &Plane, q: &[i16], t: &mut Plane, out: &mut Plane) {
    let r = q.len() - 1;
    let ch = inp.ch;
    let m2 = inp.m - r;
    // Rows: every row, columns shrink by r. Rows of `t` are `tws` apart (whole chunks of 128,
    // so the FIR has no scalar tail); the extra outputs read the next row or the slack.
    let tw = (inp.w + 2 * m2) * ch;
    let tws = tw.next_multiple_of(128);
    let nrows = inp.h + 2 * inp.m;
    if t.d.len() < tws * nrows + PLANE_SLACK {
        t.d.resize(tws * nrows + PLANE_SLACK, 0);
    }
    let offs: [(usize, usize); MAX_R + 1] =
        std::array::from_fn(|k| if k <= r { ((r - k) * ch, (r + k) * ch) } else { (0, 0) });
    let offs = &offs[..=r];
    let irl = inp.rl();
    debug_assert!(tws - tw < PLANE_SLACK);
    for (y, trow) in t.d.chunks_mut(tws).enumerate().take(nrows) {
        fir16::sym_fir(trow, &inp.d[y * irl..], r * ch, offs, q);
    }
    // Columns: whole chunks of 128 too, each row written past its end (the next row overwrites
    // that; the last row's extra goes to the slack).
    out.set(inp.w, inp.h, m2, ch);
    let orl = out.rl();
    debug_assert_eq!(orl, tw);
    let mut offs = [(0usize, 0usize); MAX_R + 1];
    let rows = inp.h + 2 * m2;
    for y in 0..rows {
        let c = y + r;
        for (k, o) in offs.iter_mut().enumerate().take(r + 1) {
            *o = ((c - k) * tws, (c + k) * tws);
        }
        fir16::sym_fir(&mut out.d[y * orl..y * orl + tws], &t.d, c * tws, &offs[..=r], q);
    }
}

multiversion! {
    /// Vertical step of the upsampler: `out[i] = a * r0[i] + b * r1[i] + c * r2[i]`.
    fn vup(out: &mut [i32], r0: &[i16], r1: &[i16], r2: &[i16], a: i32, b: i32, c: i32) {
        let n = out.len();
        let (r0, r1, r2) = (&r0[..n], &r1[..n], &r2[..n]);
        for i in 0..n {
            out[i] = a * r0[i] as i32 + b * r1[i] as i32 + c * r2[i] as i32;
        }
    }
}

multiversion! {
    /// Horizontal step of the upsampler, even and odd fine pixels apart: for coarse pixel n
    /// (`t` holds n - 1 at `n ch`), fine pixel 2n (weights 5, 10, 1 on n - 1, n, n + 1) into
    /// `e[n ch + c]` and 2n + 1 (1, 10, 5) into `o[n ch + c]`, Q6: `(s + 128) >> 8`.
    fn hup_q6(e: &mut [i16], o: &mut [i16], t: &[i32], ch: usize) {
        let n = e.len();
        let (t0, t1, t2) = (&t[..n], &t[ch..ch + n], &t[2 * ch..2 * ch + n]);
        let o = &mut o[..n];
        for i in 0..n {
            let (a, b, d) = (t0[i], 10 * t1[i] + 128, t2[i]);
            e[i] = ((5 * a + b + d) >> 8) as i16;
            o[i] = ((a + b + 5 * d) >> 8) as i16;
        }
    }
}

/// `out` = pixels of `e` and `o` alternating (`ch` samples each), as many as fit.
fn interleave_px<T: Copy + Default>(out: &mut [T], e: &[T], o: &[T], ch: usize) {
    match ch {
        1 => {
            for ((d, &a), &b) in out.chunks_exact_mut(2).zip(e).zip(o) {
                d[0] = a;
                d[1] = b;
            }
        }
        3 => {
            // Four-sample moves (one load and one store each): the fourth sample is overwritten
            // by the next move; the last pixel pair moves three.
            let n = (out.len() / 6).min(e.len() / 3).min(o.len() / 3);
            for i in 0..n.saturating_sub(1) {
                out[6 * i..6 * i + 4].copy_from_slice(&e[3 * i..3 * i + 4]);
                out[6 * i + 3..6 * i + 7].copy_from_slice(&o[3 * i..3 * i + 4]);
            }
            if n > 0 {
                let i = n - 1;
                out[6 * i..6 * i + 3].copy_from_slice(&e[3 * i..3 * i + 3]);
                out[6 * i + 3..6 * i + 6].copy_from_slice(&o[3 * i..3 * i + 3]);
            }
        }
        _ => {
            for ((d, a), b) in out.chunks_exact_mut(2 * ch).zip(e.chunks_exact(ch)).zip(o.chunks_exact(ch)) {
                d[..ch].copy_from_slice(a);
                d[ch..].copy_from_slice(b);
            }
        }
    }
    // An odd tail pixel (odd widths): the even one only.
    let full = out.len() / (2 * ch) * 2 * ch;
    if full < out.len() {
        let (k, rest) = (full / 2, out.len() - full);
        out[full..].copy_from_slice(&e[k..k + rest]);
    }
}

/// Upsampler weights (/16) of fine row/column `x` on coarse n - 1, n, n + 1 (n = floor(x / 2)):
/// the binomial [1,5,10,10,5,1]/32 at the half-sample offsets, times 2.
fn up_w(x: isize) -> (i32, i32, i32) {
    if x.rem_euclid(2) == 0 { (5, 10, 1) } else { (1, 10, 5) }
}

/// Coarse plane (margin >= 2) to a finer Q6 plane of `w x h` with margin 2 (fine pixels -2..w+2).
fn upsample_q6(c: &Plane, w: usize, h: usize, out: &mut Plane, row32: &mut Vec<i32>, eo: &mut Vec<i16>) {
    let ch = c.ch;
    let m = 2usize;
    out.set(w, h, m, ch);
    // Fine -2 .. 2*ceil((w+2)/2): coarse n from -1; t starts at coarse -2.
    let nc = (w + 2 * m).div_ceil(2) + 2; // coarse pixels -2 .. -2 + nc
    assert!(c.m >= 2 && nc <= c.w + c.m + 2);
    row32.resize(nc * ch, 0);
    eo.resize(2 * (nc - 2) * ch, 0);
    for (yy, orow) in out.rows_mut().enumerate() {
        upsample_q6_row(c, yy as isize - m as isize, orow, row32, eo);
    }
}

/// Fine row `y` of [`upsample_q6`] (margin 2) into `orow`; `row32` and `eo` sized by the caller
/// (`nc ch` and `2 (nc - 2) ch`, nc = (w + 4).div_ceil(2) + 2).
fn upsample_q6_row(c: &Plane, y: isize, orow: &mut [i16], row32: &mut [i32], eo: &mut [i16]) {
    let ch = c.ch;
    let nc = row32.len() / ch;
    let off = (c.m - 2) * ch;
    let np = (nc - 2) * ch;
    let n = y.div_euclid(2);
    let (a, b, d) = up_w(y);
    let r = |k: isize| &c.row(n + k)[off..off + nc * ch];
    vup(row32, r(-1), r(0), r(1), a, b, d);
    // Fine x from -2 (coarse n = -1: t index 1 - 1 = 0 is coarse -2).
    let (e, o) = eo[..2 * np].split_at_mut(np);
    hup_q6(e, o, row32, ch);
    interleave_px(orow, e, o, ch);
}

/// Rounding offset of the 16-bit roundings of row `y`: `rnd` is 1 or 2, alternating with the row
/// (`salt` shifts the pattern between stages); a division by a step S adds S/2 - 2 + rnd (S/2 - 1
/// or S/2) before the shift. Over equally likely remainders r, floor((r + k)/S) - r/S averages
/// k/S - (S - 1)/(2S): round half up (k = S/2) biases every rounding by +1/(2S) of a step, and the
/// six roundings of the 16-bit pyramid added about +0.07 DN to the mean of a 96x80 rgb8 test
/// frame. k = S/2 - 1 and S/2 bias by -1/(2S) and +1/(2S), so alternating them keeps the mean,
/// and every rounding stays within half a step.
#[inline]
fn rnd(y: usize, salt: usize) -> u16 {
    1 + ((y + salt) & 1) as u16
}

/// The final coarse plane from Q6 to Q4 (`(v + 2) >> 2`, values <= 4080), in place: the final
/// upsampler's sums then fit 16-bit lanes (16 x 4080 = 65280).
fn plane_to_q4(c: &mut Plane) {
    let rl = c.rl();
    for (jj, row) in c.rows_mut().enumerate() {
        q6_to_q4(row, rnd(jj, rl.max(1)) as i16);
    }
}

multiversion! {
    /// `v = (v + rnd) >> 2` (Q6 to Q4; the values are not negative).
    fn q6_to_q4(v: &mut [i16], rnd: i16) {
        for x in v.iter_mut() {
            *x = (*x + rnd) >> 2;
        }
    }
}

multiversion! {
    /// Vertical step of the final upsampler in u16 lanes, Q4 in and out:
    /// `(a r0 + b r1 + c r2 + 6 + rnd) >> 4` (a + b + c = 16, so the sum stays below 65536).
    fn vup16(out: &mut [u16], r0: &[i16], r1: &[i16], r2: &[i16], a: u16, b: u16, c: u16, rnd: u16) {
        let n = out.len();
        let (r0, r1, r2) = (&r0[..n], &r1[..n], &r2[..n]);
        for i in 0..n {
            let s = (r0[i] as u16).wrapping_mul(a).wrapping_add((r1[i] as u16).wrapping_mul(b));
            out[i] = s.wrapping_add((r2[i] as u16).wrapping_mul(c)).wrapping_add(6 + rnd) >> 4;
        }
    }
}

multiversion! {
    /// Horizontal step of the final upsampler into bytes (Q4 in): for `v` holding coarse pixel
    /// n - 1 at index n, fine pixel 2n (weights 5, 10, 1 on n - 1, n, n + 1) into `e[n]` and 2n + 1
    /// (1, 10, 5) into `o[n]`, `(s + 126 + rnd) >> 8` (the /16 and Q4 in one rounding; below 65536).
    fn hup16(e: &mut [u8], o: &mut [u8], v: &[u16], rnd: u16) {
        let n = e.len();
        let (t0, t1, t2) = (&v[..n], &v[1..n + 1], &v[2..n + 2]);
        let o = &mut o[..n];
        for i in 0..n {
            let m = t1[i].wrapping_mul(10).wrapping_add(126 + rnd);
            e[i] = (t0[i].wrapping_mul(5).wrapping_add(m).wrapping_add(t2[i]) >> 8).min(255) as u8;
            o[i] = (t0[i].wrapping_add(m).wrapping_add(t2[i].wrapping_mul(5)) >> 8).min(255) as u8;
        }
    }
}

multiversion! {
    /// `out` = bytes of `e` and `o` alternating, as many as fit (an odd last byte from `e`).
    fn zip_u8(out: &mut [u8], e: &[u8], o: &[u8]) {
        let n = out.len() / 2;
        let (e2, o2) = (&e[..n], &o[..n]);
        for (i, d) in out.chunks_exact_mut(2).enumerate() {
            d[0] = e2[i];
            d[1] = o2[i];
        }
        if out.len() % 2 == 1 {
            out[2 * n] = e[n];
        }
    }
}

/// Q4 coarse planes (margin >= 1, one per channel) to the 8-bit frame (`w x h`, fine pixels
/// 0..w), per fine row and channel: the three coarse rows combined vertically (u16, rounded to
/// Q4), then the horizontal step into bytes; rgb8: the three channel rows merged into the frame
/// row (straight from the even and odd pixel rows, `kit::merge_rgb8_eo_row`). `v`, `eo` scratch.
#[allow(clippy::too_many_arguments)]
fn upsample_u8(
    cs: &mut [Plane],
    d: &mut [u8],
    stride: usize,
    w: usize,
    h: usize,
    v: &mut Vec<u16>,
    eo: &mut Vec<u8>,
    ring: Option<usize>,
    produce: &mut dyn FnMut(usize, &mut [Plane]),
) {
    let ch = cs.len();
    // Rows of `cs` (counted from the top margin row) made so far: all of them, or, with a ring,
    // made by `produce` just before they are first read.
    let mut made = if ring.is_some() { 0 } else { usize::MAX };
    let np = w.div_ceil(2); // coarse pixels 0..np give the fine pixels 0..w
    v.resize(np + 2, 0);
    eo.resize(2 * np * ch, 0);
    for y in 0..h {
        let n = (y / 2) as isize;
        let (a, b, e) = up_w(y as isize);
        let drow = &mut d[y * stride..y * stride + w * ch];
        while made <= (n + 1) as usize + cs[0].m {
            produce(made, cs);
            made += 1;
        }
        for (k, c) in cs.iter().enumerate() {
            assert!(c.m >= 1 && c.ch == 1);
            let off = c.m - 1;
            let r = |k: isize| {
                let jj = (n + k + c.m as isize) as usize;
                &c.row_at(ring.map_or(jj, |r| jj % r))[off..off + np + 2]
            };
            vup16(v, r(-1), r(0), r(1), a as u16, b as u16, e as u16, rnd(y, 0));
            let (ev, od) = eo[2 * k * np..2 * (k + 1) * np].split_at_mut(np);
            hup16(ev, od, v, rnd(y, 1));
            if ch == 1 {
                zip_u8(drow, ev, od);
            }
        }
        if ch == 3 {
            // The even and odd pixels of the three channels straight into the frame row.
            let s = |k: usize, p: usize| &eo[(2 * k + p) * np..(2 * k + p + 1) * np];
            super::kit::merge_rgb8_eo_row(drow, [s(0, 0), s(1, 0), s(2, 0)], [s(0, 1), s(1, 1), s(2, 1)], w);
        }
    }
}

/// The pyramid blur of an 8-bit frame (one or three channels, each on its own planes): decimate
/// (one or two levels), the discrete-Gaussian FIR `q` (Q15 half kernel; `None` for none) on the
/// coarsest plane, upsample back.
#[allow(clippy::too_many_arguments)]
pub(crate) fn pyr_blur_u8(
    d: &mut [u8],
    stride: usize,
    w: usize,
    h: usize,
    ch: usize,
    levels: usize,
    q: Option<&[i16]>,
    s: &mut PyrScratch,
) {
    assert!(ch == 1 || ch == 3, "pyramid: one or three channels");
    let r = q.map_or(0, |q| q.len() - 1);
    let PyrScratch { dec, fin, l2, l3, t, row32, h32, pad16, split16, msrc, f16, v16, eo8 } = s;
    // Margins: the coarsest plane r + 2 (the FIR leaves 2 for the upsampler), each finer one
    // what the next decimation reads (2 m + 3); one level: r + 1 (the final upsampler reads 1).
    let mc = r + 2;
    let m1 = match levels {
        1 => r + 1,
        2 => 2 * mc + 3,
        _ => 2 * (2 * mc + 3) + 3,
    };
    if levels == 1 {
        decimate_u8(d, stride, w, h, ch, m1, &mut dec[..ch], None, pad16, split16, msrc, &mut |_, _| {});
        for (dc, fc) in dec.iter_mut().zip(fin.iter_mut()).take(ch) {
            match q {
                Some(q) => fir_plane(dc, q, t, fc),
                None => std::mem::swap(dc, fc),
            }
            plane_to_q4(fc);
        }
        upsample_u8(&mut fin[..ch], d, stride, w, h, v16, eo8, None, &mut |_, _| {});
    } else {
        // The first level streams through a ring of rows: each second-level row is decimated as
        // soon as its six first-level rows are there (the same values as from the whole plane,
        // without writing the first level out to memory and reading it back).
        let (w1, h1) = (w.div_ceil(2), h.div_ceil(2));
        let (w2, h2) = (w1.div_ceil(2), h1.div_ceil(2));
        let m2 = if levels == 2 { mc } else { 2 * mc + 3 };
        for p in l2[..ch].iter_mut() {
            p.set(w2, h2, m2, 1);
        }
        let n2 = w2 + 2 * m2;
        for h in h32[..ch].iter_mut() {
            h.resize(H_RING * n2, 0);
        }
        // Second-level row jj2 reads first-level rows 2 jj2 + 1 ..= 2 jj2 + 6 (m1 = 2 m2 + 3), from
        // first-level column -2 m2 - 2 (index m1 - 2 m2 - 2 = 1): each first-level row's
        // horizontal sums as it comes, the vertical step once its six rows are there.
        let off = m1 - 2 * m2 - 2;
        let rows2 = h2 + 2 * m2;
        let mut next = 0usize;
        decimate_u8(d, stride, w, h, ch, m1, &mut dec[..ch], Some(L1_RING), pad16, split16, msrc, &mut |jj1, l1| {
            let slot = jj1 % H_RING;
            for (p, h) in l1.iter().zip(h32.iter_mut()) {
                hdec_q6(&mut h[slot * n2..(slot + 1) * n2], &p.row_at(jj1 % L1_RING)[off..]);
            }
            while next < rows2 && 2 * next + 6 <= jj1 {
                for (h, o) in h32[..ch].iter().zip(l2.iter_mut()) {
                    let r = |k: usize| &h[((2 * next + 1 + k) % H_RING) * n2..((2 * next + 1 + k) % H_RING + 1) * n2];
                    vdec_q6(o.row_mut(next), r(0), r(1), r(2), r(3), r(4), r(5));
                }
                next += 1;
            }
        });
        debug_assert_eq!(next, rows2);
        // Per channel down to the coarsest level and up to the second (on `dec[c]` or `l2[c]`).
        for (dc, l2) in dec.iter_mut().zip(l2.iter_mut()).take(ch) {
            if levels == 3 {
                decimate_q6(l2, mc, l3, &mut h32[0]);
                let c = if let Some(q) = q {
                    fir_plane(l3, q, t, dc);
                    &*dc
                } else {
                    &*l3
                };
                upsample_q6(c, w2, h2, l2, row32, f16);
            } else if let Some(q) = q {
                fir_plane(l2, q, t, dc);
                std::mem::swap(dc, l2);
            }
        }
        // The second level to the first (Q6, margin 2, rounded to Q4) streams through a ring of
        // rows, made just before the final upsampler reads them (the same values as the whole
        // planes, which are never written out).
        let m = 2;
        for fc in fin[..ch].iter_mut() {
            fc.set_rows(w1, h1, m, 1, FIN_RING);
        }
        let nc = (w1 + 2 * m).div_ceil(2) + 2;
        row32.resize(nc, 0);
        f16.resize(2 * (nc - 2), 0);
        let rl = w1 + 2 * m;
        let l2 = &l2[..ch];
        upsample_u8(&mut fin[..ch], d, stride, w, h, v16, eo8, Some(FIN_RING), &mut |jj, fc| {
            for (c, p) in l2.iter().zip(fc.iter_mut()) {
                let row = p.row_mut(jj % FIN_RING);
                upsample_q6_row(c, jj as isize - m as isize, row, row32, f16);
                q6_to_q4(row, rnd(jj, rl.max(1)) as i16);
            }
        });
    }
}

impl Effect for Defocus {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let sigma = p.get("sigma_px");
        if sigma == 0.0 {
            return Ok(Outcome::Keep);
        }
        if self.kernel_key != Some(sigma.to_bits()) {
            let k = discrete_gaussian_f64(sigma);
            self.q15 = fir16::q15_half_kernel(&truncated(&k, sigma));
            self.kernel = k.into_iter().map(|v| v as f32).collect();
            self.boxes = (sigma > FIR_MAX_SIGMA).then(|| boxblur::BoxPlan::for_sigma(sigma));
            // FAULTCAM_NO_PYR=1: the previous paths (FIR up to 3, box cascade above), for the
            // before/after measurements of this branch.
            self.pyr = (sigma >= PYR_MIN_SIGMA && std::env::var_os("FAULTCAM_NO_PYR").is_none()).then(|| {
                let (levels, sc) = pyr_split(sigma);
                let q = (sc > 0.05).then(|| fir16::q15_half_kernel(&truncated(&discrete_gaussian_f64(sc), sc)));
                (levels, q)
            });
            self.kernel_key = Some(sigma.to_bits());
        }
        let (w, h, ch, stride) = (frame.width as usize, frame.height as usize, frame.channels(), frame.stride);
        let rl = w * ch;
        let r = self.kernel.len() / 2;
        match &mut frame.data {
            FrameData::U8(d) if self.pyr.is_some() => {
                let (levels, q) = self.pyr.as_ref().expect("checked");
                pyr_blur_u8(d, stride, w, h, ch, *levels, q.as_deref(), &mut self.pyr_scratch);
            }
            // 8-bit: Q6 fixed point in 16-bit lanes (see `fir16`).
            FrameData::U8(d) if self.boxes.is_some() && rl >= boxblur::LANES => {
                let plan = self.boxes.as_ref().expect("checked");
                boxblur::blur_u8(d, stride, w, h, ch, plan, &mut self.box_scratch);
            }
            FrameData::U8(d) => {
                blur_u8(d, stride, w, h, ch, &self.q15, &mut self.halo8, &mut self.work16);
            }
            // 16-bit: f32.
            FrameData::U16(d) => {
                self.tmp.resize(rl * h, 0.0);
                self.pad.resize((w + 2 * r) * ch * bands(h), 0.0);
                self.acc.resize(rl * bands(h), 0.0);
                let k = &self.kernel;
                row_pass(d, stride, w, ch, k, &mut self.tmp, &mut self.pad);
                col_pass(d, stride, h, rl, k, &self.tmp, &mut self.acc);
            }
        }
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    #[test]
    fn kernel_has_variance_sigma_squared() {
        for sigma in [0.3, 0.7, 1.5, 4.0, 20.0] {
            let k = discrete_gaussian(sigma);
            let r = (k.len() / 2) as f64;
            let sum: f64 = k.iter().map(|&v| v as f64).sum();
            let var: f64 = k.iter().enumerate().map(|(i, &v)| v as f64 * (i as f64 - r).powi(2)).sum();
            assert!((sum - 1.0).abs() < 1e-5, "{sigma}: sum {sum}");
            assert!((var - sigma * sigma).abs() < 1e-3 * sigma * sigma + 1e-5, "{sigma}: var {var}");
            for i in 0..k.len() {
                assert_eq!(k[i], k[k.len() - 1 - i]);
            }
        }
        assert_eq!(discrete_gaussian(0.0), vec![1.0]);
    }

    /// The exact model in f64: separable convolution with the discrete Gaussian, mirrored borders
    /// (the same f64 reference as the box cascade's, with the Gaussian kernel).
    fn exact_blur(f: &Frame, sigma: f64) -> Vec<f64> {
        let (w, h, ch) = (f.width as usize, f.height as usize, f.channels());
        let src: Vec<f64> = f.packed_samples_f32().into_iter().map(f64::from).collect();
        crate::faults::boxblur::reference_tests::exact(&src, w, h, ch, &discrete_gaussian_f64(sigma))
    }

    /// Largest |error| (DN) and mean error of the 8-bit blur against the exact Gaussian, on a scene
    /// with point sources (stars, a single 255 dot) and hard edges (a saturated square).
    fn errors_against_the_gaussian(format: PixelFormat, sigma: f64) -> (f64, f64) {
        errors_against_the_gaussian_at(format, sigma, 150, 130)
    }

    fn errors_against_the_gaussian_at(format: PixelFormat, sigma: f64, w: u32, h: u32) -> (f64, f64) {
        let mut orig = crate::faults::kit::bench_scene(w, h, format, 7).unwrap();
        for y in 40..70 {
            for x in 90..120 {
                for c in 0..orig.channels() {
                    orig.set(x, y, c, 255.0);
                }
            }
        }
        orig.set(20, 100, 0, 255.0);
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("sigma_px", sigma).unwrap();
        Defocus::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        let exact = exact_blur(&orig, sigma);
        let got = f.packed_samples_f32();
        let (mut worst, mut bias) = (0.0f64, 0.0f64);
        for (&g, &e) in got.iter().zip(&exact) {
            worst = worst.max((g as f64 - e).abs());
            bias += (g as f64 - e) / got.len() as f64;
        }
        (worst, bias)
    }

    #[test]
    fn eight_bit_fixed_point_is_within_one_dn_of_the_exact_gaussian() {
        for format in [PixelFormat::Rgb8, PixelFormat::Mono8] {
            for sigma in [0.3, 0.8, 1.5, 1.8, 1.84] {
                assert!(sigma < PYR_MIN_SIGMA);
                let (worst, bias) = errors_against_the_gaussian(format, sigma);
                // Rounding alone gives up to 0.5 DN; the fixed point adds < 0.5 DN, unbiased.
                assert!(worst < 1.0, "{format} sigma {sigma}: max |error| {worst} DN");
                assert!(bias.abs() < 0.05, "{format} sigma {sigma}: mean error {bias} DN");
            }
        }
    }

    /// The pyramid path against the exact discrete Gaussian, one level (2.5-4.49) and two (4.5
    /// up), even and odd frame sizes: within PYR_MAX_ERROR_DN (the box cascade it replaces was
    /// 3.6 DN just above sigma 3), the mean kept.
    #[test]
    fn pyramid_is_within_the_stated_bound_of_the_exact_gaussian() {
        for format in [PixelFormat::Rgb8, PixelFormat::Mono8] {
            for (w, h) in [(150, 130), (151, 131)] {
                for sigma in [
                    1.85, 1.9, 2.0, 2.25, 2.5, 2.75, 3.0, 3.5, 4.0, 4.49, 4.5, 5.0, 5.5, 6.5, 8.0, 9.49, 9.5, 10.0,
                    11.0, 13.0, 16.0, 20.0,
                ] {
                    assert!(sigma >= PYR_MIN_SIGMA);
                    let (worst, bias) = errors_against_the_gaussian_at(format, sigma, w, h);
                    eprintln!(
                        "{format} {w}x{h} sigma {sigma} {:?}: max |error| {worst:.3} DN, mean {bias:.4}",
                        pyr_split(sigma)
                    );
                    assert!(worst <= PYR_MAX_ERROR_DN, "{format} {w}x{h} sigma {sigma}: max |error| {worst} DN");
                    // Flux: the mean is kept up to rounding.
                    assert!(bias.abs() < 0.05, "{format} {w}x{h} sigma {sigma}: mean error {bias} DN");
                }
            }
        }
    }

    /// The split of the variance: the levels' filters plus the coarse Gaussian give sigma^2.
    #[test]
    fn pyramid_split_adds_up_to_sigma_squared() {
        for sigma in [2.5, 3.0, 4.49, 4.5, 8.0, 9.49, 9.5, 20.0] {
            let (levels, sc) = pyr_split(sigma);
            let var = match levels {
                1 => 2.5 + 4.0 * sc * sc,
                2 => 12.5 + 16.0 * sc * sc,
                _ => 52.5 + 64.0 * sc * sc,
            };
            assert!((var - sigma * sigma).abs() < 1e-9, "{sigma}: {levels} {sc}");
            assert!(sc > 0.6, "{sigma}: coarse sigma {sc}");
        }
    }

    /// Tiny and odd frames through every 8-bit path (FIR, one, two and three levels): no panic, a
    /// flat frame stays exactly flat (every weight sum is exactly one), and a dot keeps its total
    /// within the rounding.
    #[test]
    fn tiny_frames_stay_flat_and_keep_a_dot() {
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8] {
            for (w, h) in [(1u32, 1u32), (2, 1), (1, 5), (3, 2), (17, 3), (5, 40)] {
                for sigma in [1.2, 1.85, 3.0, 6.0, 13.0, 20.0] {
                    let mut p = Params::defaults(&INFO);
                    p.set("sigma_px", sigma).unwrap();
                    let mut f = Frame::new(w, h, format).unwrap();
                    for y in 0..h as usize {
                        for x in 0..w as usize {
                            for c in 0..f.channels() {
                                f.set(x, y, c, 77.0);
                            }
                        }
                    }
                    let flat = f.clone();
                    Defocus::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                    assert_eq!(f, flat, "{format} {w}x{h} sigma {sigma}");
                    let mut d = Frame::new(w, h, format).unwrap();
                    d.set(w as usize / 2, h as usize / 2, 0, 255.0);
                    Defocus::default().apply(&mut d, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                    let total: f64 = d.packed_samples_f32().iter().map(|&v| v as f64).sum();
                    // Each output sample rounds by at most 0.5 DN.
                    let n = (w * h) as f64;
                    assert!((total - 255.0).abs() <= 0.5 * n + 1e-9, "{format} {w}x{h} sigma {sigma}: total {total}");
                }
            }
        }
    }

    /// [`decimate_q6`] as the plain double sum per output sample (no rings, no vectors).
    fn decimate_plain(inp: &Plane, m: usize, out: &mut Plane) {
        out.set(inp.w.div_ceil(2), inp.h.div_ceil(2), m, 1);
        let off = inp.m - 2 * m - 2;
        let n = out.rl();
        for jj in 0..out.h + 2 * m {
            for i in 0..n {
                let mut sum = 0i32;
                for (k, bk) in B5.iter().enumerate() {
                    let row = inp.row_at(2 * jj + off + k);
                    sum += bk * (0..6).map(|k2| B5[k2] * row[off + 2 * i + k2] as i32).sum::<i32>();
                }
                out.row_mut(jj)[i] = ((sum + 512) >> 10) as i16;
            }
        }
    }

    /// The pyramid of whole planes (every level written out and read back, the stages one after
    /// the other: the structure before the rings; the decimation of levels 2 and 3 as plain
    /// sums, the other stages from the same row kernels).
    fn pyr_whole_planes(d: &mut [u8], stride: usize, w: usize, h: usize, ch: usize, sigma: f64) {
        let (levels, sc) = pyr_split(sigma);
        let q = (sc > 0.05).then(|| fir16::q15_half_kernel(&truncated(&discrete_gaussian_f64(sc), sc)));
        let q = q.as_deref();
        let mc = q.map_or(0, |q| q.len() - 1) + 2;
        // Margin of level k (1-based): the coarsest mc (mc - 1 alone: the final upsampler reads
        // one), each finer one what the next decimation reads.
        let mut ms = vec![mc; levels];
        if levels == 1 {
            ms[0] = mc - 1;
        }
        for k in (0..levels - 1).rev() {
            ms[k] = 2 * ms[k + 1] + 3;
        }
        let mut s = PyrScratch::default();
        let PyrScratch { dec, fin, l2, t, row32, pad16, split16, msrc, f16, v16, eo8, .. } = &mut s;
        decimate_u8(d, stride, w, h, ch, ms[0], &mut dec[..ch], None, pad16, split16, msrc, &mut |_, _| {});
        let (w1, h1) = (w.div_ceil(2), h.div_ceil(2));
        for c in 0..ch {
            let mut top = std::mem::take(&mut dec[c]);
            let mut sizes = vec![(w1, h1)];
            for l in 1..levels {
                let mut next = Plane::default();
                decimate_plain(&top, ms[l], &mut next);
                sizes.push((next.w, next.h));
                top = next;
            }
            if let Some(q) = q {
                let mut out = Plane::default();
                fir_plane(&top, q, t, &mut out);
                top = out;
            }
            for &(wl, hl) in sizes[..levels - 1].iter().rev() {
                upsample_q6(&top, wl, hl, &mut l2[0], row32, f16);
                std::mem::swap(&mut top, &mut l2[0]);
            }
            plane_to_q4(&mut top);
            fin[c] = top;
        }
        upsample_u8(&mut fin[..ch], d, stride, w, h, v16, eo8, None, &mut |_, _| {});
    }

    /// The streamed pyramid (rings of rows through the levels) gives the bytes of the pyramid
    /// of whole planes: one, two and three levels, rgb8 and mono8, even, odd and tiny frames.
    #[test]
    fn streamed_pyramid_equals_the_whole_planes() {
        for format in [PixelFormat::Rgb8, PixelFormat::Mono8] {
            for (w, h) in [(150u32, 130u32), (151, 131), (67, 9), (5, 40), (1, 1), (2, 3)] {
                let orig = crate::faults::kit::bench_scene(w, h, format, 11).unwrap();
                for sigma in [1.85, 3.0, 4.5, 6.0, 9.5, 13.0, 20.0] {
                    let mut a = orig.clone();
                    let mut p = Params::defaults(&INFO);
                    p.set("sigma_px", sigma).unwrap();
                    Defocus::default().apply(&mut a, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                    let mut b = orig.clone();
                    let (stride, ch) = (b.stride, b.channels());
                    let FrameData::U8(d) = &mut b.data else { panic!("8-bit") };
                    pyr_whole_planes(d, stride, w as usize, h as usize, ch, sigma);
                    assert_eq!(a, b, "{format} {w}x{h} sigma {sigma}");
                }
            }
        }
    }

    /// The AVX2 row kernels of the decimation (pixel pairs through `vpmaddwd`) against the
    /// plain B5 sums, every length up to 70 (the vector steps and their tails).
    #[test]
    fn decimation_kernels_equal_the_plain_sums() {
        let mut x = 12345u32;
        let mut next = |max: u32| {
            x = x.wrapping_mul(1664525).wrapping_add(1013904223);
            (x >> 8) % (max + 1)
        };
        for n in 0..70 {
            let pad: Vec<u16> = (0..2 * n + 4).map(|_| next(2040) as u16).collect();
            for rnd in [1u16, 2] {
                let mut got = vec![0i16; n];
                hdec16(&mut got, &pad, rnd);
                let want: Vec<i16> = (0..n)
                    .map(|i| (((0..6).map(|k| B5[k] * pad[2 * i + k] as i32).sum::<i32>() + rnd as i32) >> 2) as i16)
                    .collect();
                assert_eq!(got, want, "hdec16 n {n}");
            }
            let row: Vec<i16> = (0..2 * n + 4).map(|_| next(16320) as i16).collect();
            let mut got = vec![0i32; n];
            hdec_q6(&mut got, &row);
            let want: Vec<i32> = (0..n).map(|i| (0..6).map(|k| B5[k] * row[2 * i + k] as i32).sum()).collect();
            assert_eq!(got, want, "hdec_q6 n {n}");
        }
    }

    #[test]
    fn mirror_folds_indices() {
        let got: Vec<usize> = (-4..8).map(|i| mirror(i, 3)).collect();
        assert_eq!(got, vec![2, 2, 1, 0, 0, 1, 2, 2, 1, 0, 0, 1]);
    }

    #[test]
    fn keeps_the_mean_and_spreads_a_dot_by_sigma() {
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
            let orig = crate::faults::kit::bench_scene(96, 80, format, 4).unwrap();
            let mut f = orig.clone();
            let mut p = Params::defaults(&INFO);
            p.set("sigma_px", 2.5).unwrap();
            Defocus::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            let mean = |f: &Frame| f.packed_samples_f32().iter().map(|&v| v as f64).sum::<f64>() / (96.0 * 80.0);
            // Rounding errors are within ±0.5 DN per sample and average out; 0.05 DN is > 10 sigma.
            let (m0, m1) = (mean(&orig), mean(&f));
            assert!((m0 - m1).abs() < 0.05 * format.dn_scale() as f64 + 1e-9, "{format}: {m0} -> {m1}");
            assert_ne!(f, orig);
        }
        // A dot in a 16-bit frame: the second moment of the blurred spot is sigma^2 per axis.
        let mut f = Frame::new(61, 61, PixelFormat::Mono16).unwrap();
        f.set(30, 30, 0, 60000.0);
        let mut p = Params::defaults(&INFO);
        p.set("sigma_px", 3.0).unwrap();
        Defocus::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        let (mut s, mut sxx, mut syy) = (0.0, 0.0, 0.0);
        for y in 0..61 {
            for x in 0..61 {
                let v = f.get(x, y, 0) as f64;
                s += v;
                sxx += v * (x as f64 - 30.0).powi(2);
                syy += v * (y as f64 - 30.0).powi(2);
            }
        }
        assert!((s - 60000.0).abs() < 61.0 * 61.0 * 0.5, "total {s}");
        assert!((sxx / s - 9.0).abs() < 0.1 && (syy / s - 9.0).abs() < 0.1, "{} {}", sxx / s, syy / s);
    }

    #[test]
    fn zero_sigma_identity_thread_independent_and_padded_rows() {
        let orig = crate::faults::kit::bench_scene(130, 150, PixelFormat::Rgb8, 5).unwrap();
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("sigma_px", 0.0).unwrap();
        let mut e = Defocus::default();
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f, orig);
        // The FIR (1.2) and the pyramid (3.0 one level, 6.0 and 20.0 two; 150 rows, 3 threads).
        for sigma in [1.2, 3.0, 6.0, 20.0] {
            p.set("sigma_px", sigma).unwrap();
            let run = |threads, frame: &Frame| {
                let mut f = frame.clone();
                rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                    Defocus::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                });
                f
            };
            let one = run(1, &orig);
            assert_eq!(one, run(2, &orig), "sigma {sigma}");
            assert_eq!(one, run(3, &orig), "sigma {sigma}");
            // Same image with padded rows gives the same pixels and keeps the padding.
            let rl = orig.row_len();
            let mut padded = Vec::new();
            for row in orig.as_u8().unwrap().chunks(rl) {
                padded.extend_from_slice(row);
                padded.extend_from_slice(&[7, 7, 7, 7, 7]);
            }
            let pf = Frame::from_data(130, 150, rl + 5, PixelFormat::Rgb8, FrameData::U8(padded)).unwrap();
            let out = run(2, &pf);
            assert_eq!(out.to_packed().as_u8(), one.as_u8(), "sigma {sigma}");
            assert!(out.as_u8().unwrap().chunks(rl + 5).all(|r| r[rl..] == [7, 7, 7, 7, 7]));
        }
    }
}
