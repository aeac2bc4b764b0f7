//! `motion_blur`: linear motion during the exposure, a normalised line PSF.

use super::defocus::{fill_band_halos, from_halo, mirror};
use super::fir16;
use super::kit::{axpy_row, band_rows, bands, mirrored_row_f32, par_bands_with, round_row};
use super::streak;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, FrameData, Sample};
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "motion_blur",
    stage: Stage::Optics,
    order: 50,
    summary: "linear motion blur: convolution with a normalised line of given length and direction",
    model: "Convolution with a line PSF of length length_px centred on the pixel (the image moved uniformly \
            by length_px during the exposure; centring keeps the centroid). Direction angle_deg is measured \
            counter-clockwise from +x as displayed (y up on screen), modulo 180: 0 = horizontal streak, \
            +45 = streak rising to the right on screen, i.e. towards -y in image rows, 90 = vertical. The \
            line is sampled every 1/8 px (trapezoid weights) and each sample is spread bilinearly over its \
            four nearest pixels (sub-pixel accurate, anti-aliased), then normalised to sum 1. Borders are \
            mirrored. Channels are blurred independently. 8-bit frames, short streaks: 16-bit fixed \
            point (samples x 64, the point-symmetric tap pairs' weights rounded to multiples of 2^-15 \
            that sum exactly to 1, every product rounded to nearest, the same integer operations on \
            every CPU path): each output is within 1 DN of the exact convolution (tested against an f64 \
            reference for lengths 0.7-58 px); cost grows with length_px (about 1.5 taps per px). \
            8-bit frames, length_px > 24 for mostly vertical streaks (|sin angle| >= |cos angle|), \
            and for mostly horizontal ones where that FIR would need more than 34 point-symmetric tap \
            pairs (from 28.5 px at 10 deg, 24.5 px at 30 deg, 31.5 px at 45 deg; not exactly along x): \
            cost independent of \
            the length: the lines across the \
            streak's major axis are sheared (linear interpolation, shifts rounded to 1/64 px) so the \
            streak runs straight across them, a running sum across lines applies the model's exact \
            weights along the major axis (a box of 2T = length x |major component| lines convolved \
            with the tent), the result is unsheared (linear interpolation) and a 3-tap filter along \
            the lines matches, per output line, the model's cross-streak variance (sharpening where \
            the two interpolations are wider). 16-bit integer arithmetic: the interpolated lines \
            with q fraction bits (q = 1 at 100 px, 3 at 25 px: each within 2^-(q+1) DN), exact \
            running sums, the end taps, unshear, cross filter and normalisation as 16-bit \
            multiply-highs; the same integer operations on every CPU path and thread count. Against \
            the model it is within 10 DN on hard edges and point sources from 24 px, 6 DN from 37.5 \
            px, 3.5 DN at 100 px, 0.55 DN for axis-aligned streaks (the final rounding plus the 16-bit \
            truncations), mean within 0.05 DN (tested). 8-bit frames, streaks exactly along x (0 or \
            180 deg) longer than 28 px: the model's PSF is then one row, 2n + 1 equal weights (n = \
            floor(length_px / 2 - 1)) and two end-tap pairs; an exact 16-bit box sum (the difference of two \
            prefix sums of the row, or windows of 1, 2, 4, .. px added by doubling on the scalar \
            path: the same values, cost about independent of the length) plus the end taps \
            and the normalisation as 16-bit multiply-highs, the same integer operations on every \
            CPU path: within 0.55 DN of the model (tested). 16-bit frames in f32 with \
            the model's taps, rounded and clipped (cost grows with length_px). length_px = 0 is the \
            identity.",
    params: &[
        ParamSpec::float("length_px", "px", 0.0, 100.0, 10.0, "length of the motion streak"),
        ParamSpec::float("angle_deg", "deg", 0.0, 180.0, 0.0, "direction, CCW from +x with y up, modulo 180"),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(MotionBlur::default())
}

/// Taps (dx, dy, weight) of the line PSF in image coordinates (y down), weights sum to 1.
pub fn line_taps(length: f64, angle_deg: f64) -> Vec<(i32, i32, f32)> {
    if length <= 0.0 {
        return vec![(0, 0, 1.0)];
    }
    let r = (length / 2.0).ceil() as i32 + 1;
    let side = (2 * r + 1) as usize;
    let mut grid = vec![0.0f64; side * side];
    let t = angle_deg.to_radians();
    let (ux, uy) = (t.cos(), -t.sin());
    let n = (8.0 * length).ceil() as usize + 1;
    for i in 0..n {
        let s = -length / 2.0 + length * i as f64 / (n - 1) as f64;
        let wt = if i == 0 || i == n - 1 { 0.5 } else { 1.0 };
        let (x, y) = (s * ux + r as f64, s * uy + r as f64);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as usize, y0 as usize);
        grid[y0 * side + x0] += wt * (1.0 - fx) * (1.0 - fy);
        grid[y0 * side + x0 + 1] += wt * fx * (1.0 - fy);
        grid[(y0 + 1) * side + x0] += wt * (1.0 - fx) * fy;
        grid[(y0 + 1) * side + x0 + 1] += wt * fx * fy;
    }
    let total: f64 = grid.iter().sum();
    let mut taps = Vec::new();
    for (i, &g) in grid.iter().enumerate() {
        if g > 1e-9 * total {
            taps.push(((i % side) as i32 - r, (i / side) as i32 - r, (g / total) as f32));
        }
    }
    taps
}

/// Most point-symmetric tap pairs (the centre tap included) of a streak that 8-bit frames run
/// as the exact FIR (`fir16`, cost about linear in the pair count: about 0.10-0.13 ms per pair on
/// rgb8 1920x1200 with the AVX-512 kernels, 0.15-0.19 with the AVX2 ones, on a Zen 4 at stop 42):
/// 13 for mostly vertical streaks (every one longer than 24 px runs the running sums, which cost
/// less than a 14-pair FIR there), 34 for mostly horizontal ones, set where the two paths cost
/// the same when those running sums still transposed the whole frame. Since stop 42 they cost
/// less from about 27 pairs on (BENCHMARKS.md "Stop 42 motion_blur"); the switch stays, because
/// moving it would change those streaks' bytes and take them from the FIR's 1 DN to the running
/// sums' 10 DN of the model, still above 4 ms.
pub fn fir_max_pairs(angle_deg: f64) -> usize {
    if streak::is_vertical(angle_deg) { 13 } else { 34 }
}

/// Whether 8-bit frames run the running-sum path (`streak`, cost independent of the length)
/// rather than the exact FIR: streaks longer than 24 px (the running sums' error bound) whose
/// FIR would need more than [`fir_max_pairs`] tap pairs (every mostly vertical one; mostly
/// horizontal ones from 28.5 px at 10 deg, 24.5 px at 30 deg, 31.5 px at 45 deg).
/// Streaks exactly along x run [`RowBox`] instead (see [`runs_row_box`]).
pub fn runs_streak(length: f64, angle_deg: f64) -> bool {
    length > 24.0 && runs_streak_with(length, angle_deg, &line_taps(length, angle_deg))
}

/// [`runs_streak`] with the streak's [`line_taps`] already at hand.
fn runs_streak_with(length: f64, angle_deg: f64, taps: &[(i32, i32, f32)]) -> bool {
    length > 24.0 && taps.len() / 2 + 1 > fir_max_pairs(angle_deg) && RowBox::new(length, angle_deg, taps).is_none()
}

/// Stated bound of the running-sum path against the model (DN, 8-bit) on point sources, hard
/// edges and a textured scene, by length (the model text quotes it).
pub fn streak_max_error_dn(length: f64, angle_deg: f64) -> f64 {
    if !runs_streak(length, angle_deg) {
        1.0 // the FIR
    } else if angle_deg.rem_euclid(90.0) == 0.0 {
        0.55 // the final rounding, plus the 16-bit truncations (end taps, halving, division)
    } else if length < 20.0 {
        14.0
    } else if length < 37.5 {
        10.0
    } else if length < 100.0 {
        6.0
    } else {
        3.5
    }
}

#[derive(Default)]
pub struct MotionBlur {
    key: Option<(u64, u64)>,
    // 8-bit frames when `runs_streak`: the running-sum plan and its scratch
    streak: Option<streak::StreakPlan>,
    streak_scratch: streak::Scratch,
    // 8-bit frames, streaks exactly along x: the box plan and its per-band scratch (allocation:
    // once per frame size and length)
    row_box: Option<RowBox>,
    row_box_scratch: Vec<u16>,
    taps: Vec<(i32, i32, f32)>,
    radius: usize,
    // allocation: once per parameter change: 8-bit frames: the centre tap and one tap (dx, dy)
    // of each point-symmetric pair (dy > 0, or dy = 0 and dx > 0), and their Q15 weights
    pairs: Vec<(i32, i32)>,
    q15: Vec<i16>,
    // the same pairs grouped by columns for `fir16::sym_fir_cols_u8` / `sym_fir_cols4_u8`, and
    // their weights
    cols: Vec<fir16::TapCol>,
    wq: Vec<i16>,
    // allocation: once per frame size, streak and thread count: 8-bit frames: per band the rows
    // it reads from the unmodified frame, its ring of 2r + R mirrored Q6 rows (R = 8 output rows
    // per column-kernel call on AVX-512, else 4) plus the repeated first rows that keep the short
    // columns' runs contiguous (`convolve_q6`), and its tap offsets (per pair, and per column of
    // pairs)
    halo: Vec<u8>,
    ring16: Vec<i16>,
    offs: Vec<(usize, usize)>,
    coffs: Vec<usize>,
    // allocation: once per frame size: mirrored f32 copy of the frame with a border of `radius`
    padded: Vec<f32>,
    // allocation: once per frame size: one accumulator row per band
    acc: Vec<f32>,
}

fn build_padded<T: Sample>(src: &[T], stride: usize, w: usize, h: usize, ch: usize, r: usize, padded: &mut [f32]) {
    let pw = (w + 2 * r) * ch;
    padded.par_chunks_mut(pw).enumerate().for_each(|(py, prow)| {
        let sy = mirror(py as isize - r as isize, h);
        let irow = &src[sy * stride..sy * stride + w * ch];
        mirrored_row_f32(irow, w, ch, r, prow);
    });
}

#[allow(clippy::too_many_arguments)]
fn convolve<T: Sample>(
    dst: &mut [T],
    stride: usize,
    w: usize,
    h: usize,
    ch: usize,
    r: usize,
    taps: &[(i32, i32, f32)],
    padded: &[f32],
    acc: &mut [f32],
) {
    let rl = w * ch;
    let pw = (w + 2 * r) * ch;
    par_bands_with(dst, stride, h, acc, rl, |_, y0, band, acc| {
        for (i, orow) in band_rows(band, stride, rl).enumerate() {
            let y = y0 + i;
            acc.fill(0.0);
            for &(dx, dy, wt) in taps {
                let py = (y as isize + r as isize + dy as isize) as usize;
                let off = py * pw + (r as isize + dx as isize) as usize * ch;
                axpy_row(acc, wt, &padded[off..off + rl], 0u8);
            }
            round_row(orow, acc);
        }
    });
}

/// Split point-symmetric taps into the centre weight and one representative per pair.
fn pair_up(taps: &[(i32, i32, f32)]) -> (Vec<(i32, i32)>, Vec<f64>) {
    let mut pairs = vec![(0, 0)];
    let mut half = vec![0.0f64];
    for &(dx, dy, w) in taps {
        if (dx, dy) == (0, 0) {
            half[0] = w as f64;
        } else if dy > 0 || (dy == 0 && dx > 0) {
            // The mirror tap has the same weight up to f32 rounding: take the mean.
            let m = taps.iter().find(|t| t.0 == -dx && t.1 == -dy).map_or(w, |t| t.2);
            pairs.push((dx, dy));
            half.push(0.5 * (w as f64 + m as f64));
        }
    }
    let s = half[0] + 2.0 * half[1..].iter().sum::<f64>();
    half.iter_mut().for_each(|v| *v /= s);
    (pairs, half)
}

/// The tap pairs (`pairs[k]`, weight `q[k]`, `k >= 1`; `pairs[0]` is the centre) grouped into
/// columns for `fir16::sym_fir_cols_u8`: each pair as `(dx, dy)` with `dx >
/// 0`, or `dx = 0` and `dy > 0`; per `dx` the range of `dy` with the weights (0 in gaps).
fn tap_cols(pairs: &[(i32, i32)], q: &[i16]) -> (Vec<fir16::TapCol>, Vec<i16>) {
    let norm: Vec<(i32, i32, i16)> = pairs[1..]
        .iter()
        .zip(&q[1..])
        .map(|(&(dx, dy), &w)| if dx < 0 || (dx == 0 && dy < 0) { (-dx, -dy, w) } else { (dx, dy, w) })
        .collect();
    let mut dxs: Vec<i32> = norm.iter().map(|t| t.0).collect();
    dxs.sort_unstable();
    dxs.dedup();
    let (mut cols, mut wq) = (Vec::new(), Vec::new());
    for dx in dxs {
        let dys = norm.iter().filter(|t| t.0 == dx).map(|t| t.1);
        let (dy0, dy1) = (dys.clone().min().unwrap_or(0), dys.max().unwrap_or(0));
        let w0 = wq.len();
        wq.extend((dy0..=dy1).map(|dy| norm.iter().find(|t| t.0 == dx && t.1 == dy).map_or(0, |t| t.2)));
        // One column per dx, however long: the kernel takes columns of up to
        // `fir16::MAX_COL_PAIRS` pairs fully unrolled, longer ones in a loop that loads each
        // source row once for all its rows (cut into pieces, every piece would load `rr - 1`
        // rows more per side: 4-10 % slower at 60-80 deg on AVX-512, measured at stop 41).
        cols.push(fir16::TapCol { dx: dx as usize, dy0, dy1, w0 });
    }
    // Longest columns first: the kernel picks its unrolled code by the column's length, and runs
    // of equal lengths keep that choice predictable (the sums' order does not change the bytes).
    // Stop 41's rotated kernel keeps its dx order (as timed against main).
    if !rotated_cols(&cols, fir16::col_rows()) {
        cols.sort_by_key(|c| std::cmp::Reverse(c.len()));
    }
    (cols, wq)
}

/// Whether [`convolve_q6`] runs `fir16::sym_fir_cols4_u8` (every column rotated, stop 41's
/// kernel) instead of `fir16::sym_fir_cols_u8`: on 4 rows (AVX2, and without SIMD) when the columns
/// longer than `fir16::MAX_COL_PAIRS` hold at least half the pairs (streaks steeper than about
/// 50 deg). There `sym_fir_cols_u8` was 7-10 % slower (mono8 16-24 px at 60 and 80 deg, stop 42;
/// its gains at 5-45 deg come from the short columns it unrolls).
fn rotated_cols(cols: &[fir16::TapCol], rows: usize) -> bool {
    let long = cols.iter().map(|c| c.len()).filter(|&k| k > fir16::MAX_COL_PAIRS).sum::<usize>();
    rows == 4 && 2 * long >= cols.iter().map(|c| c.len()).sum::<usize>()
}

/// Whether the column kernel (`fir16::sym_fir_cols_u8`) runs an 8-bit FIR: when it loads at
/// most 3/4 of the source vectors the row kernel (`fir16::sym_fir_u8`, two loads per pair and
/// row, four independent sums per row) does for `rows` rows. Streaks near the horizontal have
/// one pair per column (no sharing between rows) and keep the row kernel.
fn cols_pay(npairs: usize, cols: &[fir16::TapCol], rows: usize) -> bool {
    let by_cols = rows + cols.iter().map(|c| 2 * fir16::col_run(c.len(), rows)).sum::<usize>();
    let by_rows = rows * (2 * npairs.saturating_sub(1) + 1);
    4 * by_cols <= 3 * by_rows
}

/// 8-bit convolution in place: output row y is the FIR (`fir16::sym_fir_u8`) over the mirrored
/// Q6 rows y - r ..= y + r, held in a ring of `2r + 1` rows per band (in cache) instead of a Q6
/// copy of the whole frame, and rounded to bytes in registers. The rows a band needs but does not
/// own (or reads mirrored) are copied from the unmodified frame first. Every output is the same
/// FIR over the same samples, so the bytes do not depend on the band split (one band per
/// thread). `halo` and `ring` are scratch (they only grow).
#[allow(clippy::too_many_arguments)]
fn convolve_q6(
    d: &mut [u8],
    stride: usize,
    w: usize,
    h: usize,
    ch: usize,
    r: usize,
    pairs: &[(i32, i32)],
    q: &[i16],
    cols: &[fir16::TapCol],
    wq: &[i16],
    halo: &mut Vec<u8>,
    ring: &mut Vec<i16>,
    offs: &mut Vec<(usize, usize)>,
    coffs: &mut Vec<usize>,
) {
    let rl = w * ch;
    let pw = (w + 2 * r) * ch;
    // Output rows per column-kernel call (the ring holds R more rows than the taps reach).
    let rr = fir16::col_rows();
    let n = 2 * r + rr;
    // Ring slots n..n + ext repeat slots 0..ext, so that the run of `fir16::col_run(k, rr)`
    // consecutive ring rows a column of k <= MAX_COL_PAIRS pairs reads is contiguous (at stride
    // pw); longer columns take one offset per row.
    let short = cols.iter().map(|c| c.len()).filter(|&k| k <= fir16::MAX_COL_PAIRS).max();
    let four = rotated_cols(cols, rr);
    let ext = if four { 0 } else { short.map_or(0, |k| fir16::col_run(k, rr) - 1) };
    let threads = rayon::current_num_threads().max(1);
    let per = h.div_ceil(threads).max(16);
    let nb = h.div_ceil(per);
    let (per_halo, per_ring) = (2 * r * rl, (n + ext) * pw);
    if halo.len() < per_halo * nb {
        halo.resize(per_halo * nb, 0);
    }
    if ring.len() < per_ring * nb {
        ring.resize(per_ring * nb, 0);
    }
    if offs.len() < pairs.len() * nb {
        offs.resize(pairs.len() * nb, (0, 0));
    }
    let nco = if four {
        cols.iter().map(|c| 2 * fir16::col_loads4(c.len())).sum::<usize>().max(1)
    } else {
        cols.iter().map(|c| fir16::col_offs(c.len(), rr)).sum::<usize>().max(1)
    };
    if coffs.len() < nco * nb {
        coffs.resize(nco * nb, 0);
    }
    let bounds = |b: usize| (b * per, ((b + 1) * per).min(h));
    let use_cols = cols_pay(pairs.len(), cols, rr);
    // Pass 1: the rows each band reads from the unmodified frame (at most r above and r below).
    fill_band_halos(d, &mut halo[..per_halo * nb], per_halo, per, h, r, stride, rl);
    // Pass 2: the bands, each walking down its rows with its ring.
    let used = d.len().min(stride * h);
    d[..used]
        .par_chunks_mut(stride * per)
        .zip(halo[..per_halo * nb].par_chunks(per_halo.max(1)))
        .zip(ring[..per_ring * nb].par_chunks_mut(per_ring))
        .zip(offs[..pairs.len() * nb].par_chunks_mut(pairs.len()))
        .zip(coffs[..nco * nb].par_chunks_mut(nco))
        .enumerate()
        .for_each(|(b, ((((band, hb), ring), offs), coffs))| {
            let (y0, y1) = bounds(b);
            let first = y0 as isize - r as isize;
            let slot = |yv: isize| (yv - first) as usize % n;
            let mut j = 0;
            // Mirrored Q6 copy of virtual row yv into its ring slot.
            let mut produce = |yv: isize, band: &[u8], ring: &mut [i16]| {
                let src = if from_halo(yv, y0, y1, h) {
                    j += 1;
                    &hb[(j - 1) * rl..j * rl]
                } else {
                    let i = yv as usize - y0;
                    &band[i * stride..i * stride + rl]
                };
                let k = slot(yv);
                super::defocus::pad_row_q6(src, w, ch, r, &mut ring[k * pw..(k + 1) * pw]);
                if k < ext && use_cols {
                    ring.copy_within(k * pw..(k + 1) * pw, (n + k) * pw);
                }
            };
            for yv in first..y0 as isize + r as isize {
                produce(yv, band, ring);
            }
            let mut y = y0;
            // 4 output rows at a time, every column rotated (stop 41's kernel and layout).
            while four && use_cols && y + 4 <= y1 {
                let yi = y as isize;
                for t in 0..4 {
                    produce(yi + (r + t) as isize, band, ring);
                }
                // Sample 0 of virtual row yv, shifted by dx pixels.
                let at = |yv: isize, dx: isize| slot(yv) * pw + (r as isize + dx) as usize * ch;
                let mut p = 0;
                for c in cols {
                    let (m, dx) = (fir16::col_loads4(c.len()), c.dx as isize);
                    for t in 0..m as isize {
                        coffs[p + t as usize] = at(yi + 3 - c.dy0 as isize - t, -dx);
                        coffs[p + m + t as usize] = at(yi + c.dy0 as isize + t, dx);
                    }
                    p += 2 * m;
                }
                let centre: [usize; 4] = std::array::from_fn(|j| at(yi + j as isize, 0));
                let i = y - y0;
                let mut it = band[i * stride..].chunks_mut(stride).map(|row| &mut row[..rl]);
                let outs: [&mut [u8]; 4] = std::array::from_fn(|_| it.next().expect("4 rows in the band"));
                fir16::sym_fir_cols4_u8(outs, ring, centre, cols, &coffs[..p], q[0], wq);
                y += 4;
            }
            // rr output rows at a time, their source rows loaded once per column of taps.
            while !four && use_cols && y + rr <= y1 {
                let yi = y as isize;
                for t in 0..rr {
                    produce(yi + (r + t) as isize, band, ring);
                }
                // Sample 0 of virtual row yv, shifted by dx pixels.
                let at = |yv: isize, dx: isize| slot(yv) * pw + (r as isize + dx) as usize * ch;
                // Per column the first rows of its two runs (contiguous: see `ext`), or for
                // longer columns every row of them.
                let mut p = 0;
                for c in cols {
                    let (dx, k) = (c.dx as isize, c.len());
                    let m = fir16::col_offs(k, rr);
                    let (lo, hi) = (yi - c.dy1 as isize, yi + c.dy0 as isize);
                    for t in 0..m / 2 {
                        coffs[p + t] = at(lo + t as isize, -dx);
                        coffs[p + m / 2 + t] = at(hi + t as isize, dx);
                    }
                    p += m;
                }
                let centre: [usize; fir16::MAX_COL_ROWS] = std::array::from_fn(|j| at(yi + j as isize, 0));
                let i = y - y0;
                let (done, rest) = band.split_at_mut(((i + rr) * stride).min(band.len()));
                let mut it = done[i * stride..].chunks_mut(stride).map(|row| &mut row[..rl]);
                let mut outs: [&mut [u8]; fir16::MAX_COL_ROWS] =
                    std::array::from_fn(|j| if j < rr { it.next().expect("rr rows in the band") } else { &mut [] });
                // The band rows the next call's fill reads (virtual rows y + rr + r + t), if
                // they are in the band and not mirrored.
                let mut pf: [&[u8]; fir16::MAX_COL_ROWS] = [&[]; fir16::MAX_COL_ROWS];
                let mut npf = 0;
                for t in 0..rr {
                    let yv = yi + (2 * rr + r + t) as isize - rr as isize;
                    if !from_halo(yv, y0, y1, h) {
                        let k = (yv as usize - y0 - i - rr) * stride;
                        pf[npf] = &rest[k..k + rl];
                        npf += 1;
                    }
                }
                fir16::sym_fir_cols_u8(
                    &mut outs[..rr],
                    ring,
                    pw,
                    &centre[..rr],
                    cols,
                    &coffs[..p],
                    q[0],
                    wq,
                    &pf[..npf],
                );
                y += rr;
            }
            for y in y..y1 {
                let yi = y as isize;
                produce(yi + r as isize, band, ring);
                // Tap (dx, dy) of output row y: ring row y + dy, pixel x + dx (+ r of padding).
                let at = |dx: i32, dy: i32| slot(yi + dy as isize) * pw + (r as isize + dx as isize) as usize * ch;
                for (o, &(dx, dy)) in offs.iter_mut().zip(pairs) {
                    *o = (at(-dx, -dy), at(dx, dy));
                }
                let i = y - y0;
                fir16::sym_fir_u8(&mut band[i * stride..i * stride + rl], ring, at(0, 0), offs, q);
            }
        });
}

/// 8-bit streaks exactly along x longer than this run [`RowBox`] (cost independent of the
/// length, 3.7-4.3 ms rgb8 1920x1200 on the loaded Zen 4 from 26 to 66 px); up to it the exact
/// FIR's row kernel costs no more than that on the AVX2 kernels (the two about equal at 29 px,
/// 4.3-4.4 ms; BENCHMARKS.md "Stop 40 motion_blur"), and the shorter streaks keep their bytes.
pub const ROW_BOX_MIN_PX: f64 = 28.0;

/// Whether an 8-bit frame runs [`RowBox`] (a box sum with the model's weights, within 0.55 DN):
/// streaks exactly along x (0 or 180 deg) longer than [`ROW_BOX_MIN_PX`].
pub fn runs_row_box(length: f64, angle_deg: f64) -> bool {
    RowBox::new(length, angle_deg, &line_taps(length, angle_deg)).is_some()
}

/// 8-bit streaks exactly along x (`angle_deg` 0 or 180) longer than [`ROW_BOX_MIN_PX`]: the
/// model's PSF is then one row (the line's samples have no y component, so the bilinear
/// spreading stays in the row): `2n + 1` equal interior weights (`n = floor(length / 2 - 1)`,
/// every pixel whose tent lies inside the line) and the end taps at `|dx| = n + 1, n + 2` (the
/// line's ends spread over their two nearest pixels), nothing further out. A box of `2n + 1`
/// pixels (a sum that costs the same at any length) plus two tap pairs gives the model's
/// weights.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowBox {
    /// Full-weight taps each side of the centre.
    n: usize,
    /// Fraction bits of the sum `B` (see `row_box_k`): the largest `q <= 6` with `(2n + 5) 255
    /// 2^q < 2^16`.
    q: u32,
    /// The end taps' weights relative to an interior one, times `2^(9 + q)` (rounded; applied as
    /// `mulhi(e << 7, w)` = `e w / 2^9`).
    w: [u16; 2],
    /// The final division by `D` = the `B` of a flat 1 DN row: `out = ((mulhi(B, dm) >> (ds - 1))
    /// + 1) >> 1`, `dm = round(2^(16 + ds) / D)` (the largest `ds` with `dm < 2^16`).
    dm: u16,
    ds: u32,
}

impl RowBox {
    /// The plan for the streak's [`line_taps`] `taps`, or `None` when it is not a row of that
    /// shape (not along x, not longer than [`ROW_BOX_MIN_PX`], or longer than the 16-bit sums
    /// hold).
    fn new(length: f64, angle_deg: f64, taps: &[(i32, i32, f32)]) -> Option<RowBox> {
        if angle_deg.rem_euclid(180.0) != 0.0 || length <= ROW_BOX_MIN_PX {
            return None;
        }
        let n = (length / 2.0 - 1.0).floor() as usize;
        let k = 2 * n + 1;
        // The sums with the end taps: (2n + 5) 255 2^q < 2^16.
        let q = (0..=6u32).rev().find(|&q| (k + 4) * (255 << q) <= u16::MAX as usize)?;
        if taps.iter().any(|t| t.1 != 0 || t.0.unsigned_abs() as usize > n + 2) {
            return None;
        }
        let sum_at = |lo: usize, hi: usize| -> f64 {
            taps.iter().filter(|t| (lo..=hi).contains(&(t.0.unsigned_abs() as usize))).map(|t| t.2 as f64).sum()
        };
        let interior = sum_at(0, n) / k as f64;
        // The interior weights are equal (each pixel's tent lies wholly inside the line) up to
        // the 1/8 px quadrature when the sample spacing length / ceil(8 length) is not 1/8 (a
        // relative 1.3e-4 at 99.9 px) and the f32 rounding of the taps: their mean stands for them
        // if that moves an output by at most 0.02 DN (part of the 0.55 DN bound), else the FIR or
        // the running sums run.
        let total: f64 = taps.iter().map(|t| t.2 as f64).sum();
        let spread: f64 =
            taps.iter().filter(|t| t.0.unsigned_abs() as usize <= n).map(|t| (t.2 as f64 - interior).abs()).sum();
        if 255.0 * spread / total > 0.02 {
            return None;
        }
        let rel = |d: usize| sum_at(d, d) / 2.0 / interior;
        let w = [rel(n + 1), rel(n + 2)].map(|r| (r * 2f64.powi(9 + q as i32)).round().min(65535.0) as u16);
        let dd = (k << q) as f64 + 2.0 * (w[0] as f64 + w[1] as f64) / 512.0;
        let ds = (1..=15u32).rev().find(|&s| (2f64.powi(16 + s as i32) / dd).round() < 65536.0).unwrap_or(1);
        let dm = (2f64.powi(16 + ds as i32) / dd).round() as u16;
        Some(RowBox { n, q, w, dm, ds })
    }
}

/// Output samples per segment of a row in [`row_box_k`]: the segment's three rows of window sums
/// (plus the padded row) stay in the L1 cache (about 26 KB at 100 px rgb8).
const ROW_BOX_SEG: usize = 2048;

/// Per-band scratch of [`row_box`] (u16s): the padded row, its prefix sums and three segments of
/// window sums.
fn row_box_scratch(w: usize, ch: usize, n: usize) -> usize {
    2 * (w + 2 * (n + 2)) * ch + 3 * (ROW_BOX_SEG + (2 * n + 4) * ch)
}

/// `(x e) >> 16` (the high half of the 16-bit product: one `vpmulhuw`).
#[inline(always)]
fn mulhi(x: u16, e: u16) -> u16 {
    ((x as u32 * e as u32) >> 16) as u16
}

/// The last stage's constants of a [`RowBox`], `[sq, w1, w2, dm, sd]`: the shifts by `q` and
/// `ds - 1` as multiplications (vpmullw, vpmulhuw: the compiler keeps them in 16-bit lanes),
/// `x << q = x sq`, `x >> (ds - 1) = mulhi(x, sd)` (`sd = 2^(17 - ds)`, 2 <= ds <= 16), and the
/// end-tap weights and the division's multiplier.
fn row_box_consts(plan: RowBox) -> [u16; 5] {
    debug_assert!((2..=16).contains(&plan.ds));
    [1u16 << plan.q, plan.w[0], plan.w[1], plan.dm, 1u16 << (17 - plan.ds)]
}

/// The last stage of [`row_box_k`] for one sample: the box sum `sum` and the end-tap pairs' sums
/// `e1`, `e2` to a byte (`k` = [`row_box_consts`]); [`rb_simd`]'s `body256` / `body512` run the
/// same operations.
#[inline(always)]
fn row_box_out(sum: u16, e1: u16, e2: u16, k: [u16; 5]) -> u8 {
    let [sq, w1, w2, dm, sd] = k;
    let b = sum * sq + mulhi(e1 << 7, w1) + mulhi(e2 << 7, w2);
    ((mulhi(mulhi(b, dm), sd) + 1) >> 1).min(255) as u8
}

/// The end taps of the row box's `wc` outputs in the padded row `p`: `[l1, r1, l2, r2]`, the pixels
/// at `|dx| = n + 1` (left, right) and `n + 2` (output x: padded pixels x + 1, x + 2n + 3 and x,
/// x + 2n + 4).
fn row_box_end_taps(p: &[u16], n: usize, ch: usize, wc: usize) -> [&[u16]; 4] {
    let at = |px: usize| &p[px * ch..px * ch + wc];
    [at(1), at(2 * n + 3), at(0), at(2 * n + 4)]
}

/// One row of [`row_box`] in place (`row`, `w` pixels of `ch` samples, copied whole into the
/// padded row first); `s` is the scratch of [`row_box_scratch`] u16s. Segment by segment of
/// [`ROW_BOX_SEG`] output samples: the box sum `S` of `k = 2n + 1` pixels by doubling, windows of
/// 1, 2, 4, .. pixels (`cur[i] + cur[i + width]`), the ones in `k`'s binary digits added up on
/// the way (exact 16-bit sums: `k 255 < 2^16`); then per sample `B = S 2^q + mulhi(e1 << 7, w1)
/// + mulhi(e2 << 7, w2)` (`e1`, `e2` the sums of the two end-tap pairs) and the division by `D`
/// (see [`RowBox`]). With AVX2 / AVX-512 (level `lv` >= 1) `S` is instead the difference of
/// two prefix sums of the padded row (`pre[t] = p[t] + pre[t - ch]`, wrapping 16-bit: the
/// difference is exact because `S` fits), scanned in registers, and the last stage runs there too
/// ([`rb_simd`]). Integer operations only: the same bytes on every path and segment split.
#[inline(always)]
fn row_box_k(lv: u8, row: &mut [u8], w: usize, ch: usize, plan: RowBox, s: &mut [u16]) {
    let rr = plan.n + 2;
    let np = (w + 2 * rr) * ch;
    let (p, s) = s.split_at_mut(np);
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_variables))]
    let (pre, s) = s.split_at_mut(np);
    let halo = (2 * rr) * ch;
    let sl = ROW_BOX_SEG + halo;
    let (c0, s) = s.split_at_mut(sl);
    let (c1, acc) = s.split_at_mut(sl);
    let acc = &mut acc[..sl];
    let src = &*row;
    // The row mirrored (half-sample symmetric) by rr pixels a side, as u16.
    for (d, &v) in p[rr * ch..(rr + w) * ch].iter_mut().zip(&src[..w * ch]) {
        *d = v as u16;
    }
    for px in (0..rr).chain(rr + w..w + 2 * rr) {
        let sx = if px < rr && rr <= w {
            rr - 1 - px
        } else if px >= rr + w && rr <= w {
            2 * w + rr - 1 - px
        } else {
            mirror(px as isize - rr as isize, w)
        };
        for c in 0..ch {
            p[px * ch + c] = src[sx * ch + c] as u16;
        }
    }
    let wc = w * ch;
    // With AVX2 / AVX-512: `S` as the difference of two prefix sums of the row (wrapping 16-bit:
    // exact, as `S` itself fits), the prefix sum computed in registers; the same values as the
    // doubling windows below.
    #[cfg(target_arch = "x86_64")]
    if lv >= 1 && super::kit::has_avx2() {
        let k = row_box_consts(plan);
        let avx512 = lv >= 2 && super::kit::has_avx512();
        // SAFETY: AVX-512 F/BW resp. AVX2 present (checked).
        let done = unsafe { if avx512 { rb_simd::prefix512(pre, p, ch) } else { rb_simd::prefix256(pre, p, ch) } };
        for t in done..np {
            pre[t] = p[t].wrapping_add(if t >= ch { pre[t - ch] } else { 0 });
        }
        let n2 = 2 * plan.n;
        let (s1, s0) = (&pre[(n2 + 2) * ch..(n2 + 2) * ch + wc], &pre[ch..ch + wc]);
        let e = row_box_end_taps(p, plan.n, ch, wc);
        let [l1, r1, l2, r2] = e;
        let out = &mut row[..wc];
        // SAFETY: as above.
        let done =
            unsafe { if avx512 { rb_simd::body512(out, s0, s1, e, k) } else { rb_simd::body256(out, s0, s1, e, k) } };
        for t in done..wc {
            out[t] = row_box_out(s1[t].wrapping_sub(s0[t]), l1[t] + r1[t], l2[t] + r2[t], k);
        }
        return;
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = lv;
    let mut s0 = 0;
    while s0 < wc {
        let s1 = (s0 + ROW_BOX_SEG).min(wc);
        row_box_seg(&mut row[s0..s1], &p[s0..s1 + halo], ch, plan, c0, c1, acc);
        s0 = s1;
    }
}

/// The outputs `out` of [`row_box_k`] from the padded samples `p` (`out.len() + (2n + 4) ch`
/// of them); `c0`, `c1`, `acc` scratch of at least `p.len()`.
#[inline(always)]
fn row_box_seg(out: &mut [u8], p: &[u16], ch: usize, plan: RowBox, c0: &mut [u16], c1: &mut [u16], acc: &mut [u16]) {
    let np = p.len();
    let k = 2 * plan.n + 1;
    let top = usize::BITS - 1 - k.leading_zeros();
    // Level b: cur[i] = the sum of the cw = 2^b pixels from i (p, then c0 and c1 in turn);
    // acc[i] = the sum of the aw pixels from i (aw = k's digits below b). Only acc[..out.len() +
    // 2 ch] is used, which every level's next window covers (2 cw - 1 <= 2n).
    let (mut cw, mut aw) = (1usize, 0usize);
    for b in 0..top {
        let (rd, wr): (&[u16], &mut [u16]) = match b {
            0 => (p, &mut *c0),
            _ if b % 2 == 1 => (&*c0, &mut *c1),
            _ => (&*c1, &mut *c0),
        };
        let m = np - (2 * cw - 1) * ch;
        let (lo, hi) = (&rd[..m], &rd[cw * ch..cw * ch + m]);
        if k >> b & 1 == 1 {
            if aw == 0 {
                acc[..m].copy_from_slice(lo);
            } else {
                for (a, &c) in acc[..m].iter_mut().zip(&rd[aw * ch..aw * ch + m]) {
                    *a += c;
                }
            }
            aw += cw;
        }
        for ((d, &x), &y) in wr[..m].iter_mut().zip(lo).zip(hi) {
            *d = x + y;
        }
        cw *= 2;
    }
    let cur: &[u16] = match top {
        0 => p,
        _ if top % 2 == 1 => c0,
        _ => c1,
    };
    // Output x: centre at padded x + rr, box from x + 2, end taps at x + 1, x + 2n + 3 (|dx| =
    // n + 1) and x, x + 2n + 4 (|dx| = n + 2), in pixels.
    let wc = out.len();
    let (at, bt) = (&acc[2 * ch..2 * ch + wc], &cur[(2 + aw) * ch..(2 + aw) * ch + wc]);
    let [l1, r1, l2, r2] = row_box_end_taps(p, plan.n, ch, wc);
    let k = row_box_consts(plan);
    if aw == 0 {
        for t in 0..wc {
            out[t] = row_box_out(bt[t], l1[t] + r1[t], l2[t] + r2[t], k);
        }
    } else {
        for t in 0..wc {
            out[t] = row_box_out(at[t] + bt[t], l1[t] + r1[t], l2[t] + r2[t], k);
        }
    }
}

/// [`row_box_k`] in AVX2 / AVX-512 registers: the row's prefix sums, and the last stage (end taps,
/// division, bytes) with `vpmulhuw` pinned (the compiler's own vectorisation of that stage widens
/// the multiply-highs to 32-bit lanes). The same wrapping 16-bit operations as the scalar code.
#[cfg(target_arch = "x86_64")]
mod rb_simd {
    use super::super::kit::{mulhi_epu16_256 as mulhi, mulhi_epu16_512 as mulhi512};
    use std::arch::x86_64::*;

    /// `pre[t] = p[t] + pre[t - ch]` (wrapping; `pre[t] = p[t]` for `t < ch`) for `t <
    /// p.len() / 32 * 32` (returned), `ch` 1 or 3: each vector scanned in registers (lanes
    /// shifted by `ch`, `2 ch`, `4 ch`, .. and added), then the previous vector's last sum of
    /// each channel added.
    ///
    /// # Safety
    /// AVX-512 F/BW.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub unsafe fn prefix512(pre: &mut [u16], p: &[u16], ch: usize) -> usize {
        let n = p.len() / 32 * 32;
        assert!(pre.len() >= n && (ch == 1 || ch == 3));
        // The index vectors in registers, from the lane numbers (this runs per row: no
        // allocation, and no lane-by-lane construction, which costs 0.2 ms per mono8 frame once
        // the compiler stops inlining this function into its caller).
        const IOTA: [i16; 32] = {
            let mut v = [0i16; 32];
            let mut i = 0;
            while i < 32 {
                v[i] = i as i16;
                i += 1;
            }
            v
        };
        // SAFETY: 32 i16s are 64 bytes.
        let iota = unsafe { _mm512_loadu_si512(IOTA.as_ptr().cast::<__m512i>()) };
        let zero = _mm512_setzero_si512();
        // A fixed array of the shift steps, 5 for ch 1, 4 for ch 3: lane i takes lane max(i - s, 0).
        let shifts: [i16; 5] = if ch == 1 { [1, 2, 4, 8, 16] } else { [3, 6, 12, 24, 0] };
        let steps = shifts.map(|s| {
            ((u32::MAX << s) as __mmask32, _mm512_max_epi16(_mm512_sub_epi16(iota, _mm512_set1_epi16(s)), zero))
        });
        let steps = &steps[..if ch == 1 { 5 } else { 4 }];
        // The last sum of each channel: lane 31 for ch 1, lanes 29 + i % 3 for ch 3 (i % 3 = i -
        // 3 floor(i / 3), floor(i / 3) as a multiply-high by ceil(2^16 / 3) = 21846, exact for i < 32).
        let cidx = if ch == 1 {
            _mm512_set1_epi16(31)
        } else {
            let third = _mm512_mulhi_epu16(iota, _mm512_set1_epi16(21846));
            let rem = _mm512_sub_epi16(iota, _mm512_mullo_epi16(third, _mm512_set1_epi16(3)));
            _mm512_add_epi16(rem, _mm512_set1_epi16(29))
        };
        let mut carry = _mm512_setzero_si512();
        for i in (0..n).step_by(32) {
            // SAFETY: AVX-512 F/BW (the caller's contract); the load and the store cover 32
            // values below n of their slices (asserted).
            unsafe {
                let mut x = _mm512_loadu_si512(p.as_ptr().add(i).cast::<__m512i>());
                for &(m, idx) in steps {
                    x = _mm512_add_epi16(x, _mm512_maskz_permutexvar_epi16(m, idx, x));
                }
                x = _mm512_add_epi16(x, carry);
                _mm512_storeu_si512(pre.as_mut_ptr().add(i).cast::<__m512i>(), x);
                carry = _mm512_permutexvar_epi16(cidx, x);
            }
        }
        n
    }

    /// [`prefix512`] 16 lanes at a time (returns `p.len() / 16 * 16`).
    ///
    /// # Safety
    /// AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn prefix256(pre: &mut [u16], p: &[u16], ch: usize) -> usize {
        let n = p.len() / 16 * 16;
        assert!(pre.len() >= n && (ch == 1 || ch == 3));
        // x shifted up by S lanes (zeros in), S < 16: `lo` = [0, low half of x]; S < 8 takes the
        // top S lanes of `lo`'s half below each half of x (`vpalignr` by 16 - 2 S bytes).
        macro_rules! up {
            ($x:expr, 8) => {{
                let x = $x;
                _mm256_permute2x128_si256::<0x08>(x, x)
            }};
            ($x:expr, 12) => {{
                let x = $x;
                _mm256_slli_si256::<8>(_mm256_permute2x128_si256::<0x08>(x, x))
            }};
            ($x:expr, $s:literal) => {{
                let x = $x;
                _mm256_alignr_epi8::<{ 16 - 2 * $s }>(x, _mm256_permute2x128_si256::<0x08>(x, x))
            }};
        }
        // The previous vector's last sum per channel into every lane of that channel: lane i
        // takes lane 15 (ch 1) or 13 + i mod 3 (ch 3), all in the high half.
        let word = |w: [i8; 16]| -> __m256i {
            let b: [i8; 32] = std::array::from_fn(|i| 2 * w[i / 2] + (i % 2) as i8);
            // SAFETY: 32 bytes.
            unsafe { _mm256_loadu_si256(b.as_ptr().cast::<__m256i>()) }
        };
        let cpat = if ch == 1 {
            word([7; 16])
        } else {
            // High-half words (lane - 8) per 128-bit half: lanes 0-7 then 8-15.
            word(std::array::from_fn(|i| 5 + (i % 3) as i8))
        };
        let mut carry = _mm256_setzero_si256();
        for i in (0..n).step_by(16) {
            // SAFETY: AVX2 (the caller's contract); the load and the store cover 16 values
            // below n of their slices (asserted).
            unsafe {
                let mut x = _mm256_loadu_si256(p.as_ptr().add(i).cast::<__m256i>());
                if ch == 1 {
                    x = _mm256_add_epi16(x, up!(x, 1));
                    x = _mm256_add_epi16(x, up!(x, 2));
                    x = _mm256_add_epi16(x, up!(x, 4));
                    x = _mm256_add_epi16(x, up!(x, 8));
                } else {
                    x = _mm256_add_epi16(x, up!(x, 3));
                    x = _mm256_add_epi16(x, up!(x, 6));
                    x = _mm256_add_epi16(x, up!(x, 12));
                }
                x = _mm256_add_epi16(x, carry);
                _mm256_storeu_si256(pre.as_mut_ptr().add(i).cast::<__m256i>(), x);
                let hi = _mm256_permute2x128_si256::<0x11>(x, x);
                carry = _mm256_shuffle_epi8(hi, cpat);
            }
        }
        n
    }

    /// `out[t] = row_box_out(s1[t] - s0[t], l1[t] + r1[t], l2[t] + r2[t], k)` with `e = [l1, r1,
    /// l2, r2]` ([`super::row_box_out`]: `b = sum sq + mulhi(e1 << 7, w1) + mulhi(e2 << 7, w2)`,
    /// `out = min((mulhi(mulhi(b, dm), sd) + 1) >> 1, 255)`), for `t < out.len() / 16 * 16`
    /// (returned).
    ///
    /// # Safety
    /// AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn body256(out: &mut [u8], s0: &[u16], s1: &[u16], e: [&[u16]; 4], k: [u16; 5]) -> usize {
        let n = out.len() / 16 * 16;
        assert!(s0.len() >= n && s1.len() >= n && e.iter().all(|v| v.len() >= n));
        let [sq, w1, w2, dm, sd] = k.map(|v| _mm256_set1_epi16(v as i16));
        let (one, max) = (_mm256_set1_epi16(1), _mm256_set1_epi16(255));
        for i in (0..n).step_by(16) {
            // SAFETY: AVX2 (the caller's contract); every load covers 16 values below n of its
            // slice and the store 16 bytes below n of `out` (asserted).
            unsafe {
                let l = |v: &[u16]| _mm256_loadu_si256(v.as_ptr().add(i).cast::<__m256i>());
                let sum = _mm256_sub_epi16(l(s1), l(s0));
                let e1 = _mm256_slli_epi16::<7>(_mm256_add_epi16(l(e[0]), l(e[1])));
                let e2 = _mm256_slli_epi16::<7>(_mm256_add_epi16(l(e[2]), l(e[3])));
                let b = _mm256_add_epi16(_mm256_add_epi16(_mm256_mullo_epi16(sum, sq), mulhi(e1, w1)), mulhi(e2, w2));
                let o = _mm256_srli_epi16::<1>(_mm256_add_epi16(mulhi(mulhi(b, dm), sd), one));
                let o = _mm256_min_epu16(o, max);
                let p = _mm256_permute4x64_epi64::<0b1000>(_mm256_packus_epi16(o, o));
                _mm_storeu_si128(out.as_mut_ptr().add(i).cast::<__m128i>(), _mm256_castsi256_si128(p));
            }
        }
        n
    }

    /// [`body256`] 32 at a time (returns `out.len() / 32 * 32`).
    ///
    /// # Safety
    /// AVX-512 F/BW.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub unsafe fn body512(out: &mut [u8], s0: &[u16], s1: &[u16], e: [&[u16]; 4], k: [u16; 5]) -> usize {
        let n = out.len() / 32 * 32;
        assert!(s0.len() >= n && s1.len() >= n && e.iter().all(|v| v.len() >= n));
        let [sq, w1, w2, dm, sd] = k.map(|v| _mm512_set1_epi16(v as i16));
        let one = _mm512_set1_epi16(1);
        for i in (0..n).step_by(32) {
            // SAFETY: AVX-512 F/BW (the caller's contract); every load covers 32 values below n
            // of its slice and the store 32 bytes below n of `out` (asserted).
            unsafe {
                let l = |v: &[u16]| _mm512_loadu_si512(v.as_ptr().add(i).cast::<__m512i>());
                let sum = _mm512_sub_epi16(l(s1), l(s0));
                let e1 = _mm512_slli_epi16::<7>(_mm512_add_epi16(l(e[0]), l(e[1])));
                let e2 = _mm512_slli_epi16::<7>(_mm512_add_epi16(l(e[2]), l(e[3])));
                let b =
                    _mm512_add_epi16(_mm512_add_epi16(_mm512_mullo_epi16(sum, sq), mulhi512(e1, w1)), mulhi512(e2, w2));
                let o = _mm512_srli_epi16::<1>(_mm512_add_epi16(mulhi512(mulhi512(b, dm), sd), one));
                // Unsigned saturation to bytes: `min(o, 255)`.
                _mm256_storeu_si256(out.as_mut_ptr().add(i).cast::<__m256i>(), _mm512_cvtusepi16_epi8(o));
            }
        }
        n
    }
}

super::kit::dispatch_levels!(row_box_row, row_box_k, (lvk: u8, row: &mut [u8], w: usize, ch: usize, plan: RowBox, s: &mut [u16]));

/// [`RowBox`] streaks of 8-bit frames in place, row by row (each row reads only itself: the
/// bytes do not depend on the band split), with the kernels of level `lv` at most (2 AVX-512, 1
/// AVX2, 0 scalar: the same bytes). `scratch` grows only.
#[allow(clippy::too_many_arguments)]
fn row_box(lv: u8, d: &mut [u8], stride: usize, w: usize, h: usize, ch: usize, plan: RowBox, scratch: &mut Vec<u16>) {
    let per = row_box_scratch(w, ch, plan.n);
    if scratch.len() < per * bands(h) {
        scratch.resize(per * bands(h), 0);
    }
    let rl = w * ch;
    par_bands_with(d, stride, h, &mut scratch[..per * bands(h)], per, |_, _, band, s| {
        for row in band_rows(band, stride, rl) {
            row_box_row(lv, lv, row, w, ch, plan, s);
        }
    });
}

impl Effect for MotionBlur {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let (len, ang) = (p.get("length_px"), p.get("angle_deg"));
        if len == 0.0 {
            return Ok(Outcome::Keep);
        }
        if self.key != Some((len.to_bits(), ang.to_bits())) {
            self.taps = line_taps(len, ang);
            self.radius =
                self.taps.iter().map(|t| t.0.unsigned_abs().max(t.1.unsigned_abs())).max().unwrap_or(0) as usize;
            let (pairs, half) = pair_up(&self.taps);
            self.q15 = fir16::q15_pairs(&half);
            self.pairs = pairs;
            (self.cols, self.wq) = tap_cols(&self.pairs, &self.q15);
            self.row_box = RowBox::new(len, ang, &self.taps);
            self.streak = runs_streak_with(len, ang, &self.taps).then(|| streak::StreakPlan::new(len, ang));
            self.key = Some((len.to_bits(), ang.to_bits()));
        }
        let (w, h, ch, stride, r) =
            (frame.width as usize, frame.height as usize, frame.channels(), frame.stride, self.radius);
        let taps = &self.taps;
        match &mut frame.data {
            FrameData::U8(d) if self.row_box.is_some() => {
                let plan = self.row_box.expect("checked");
                row_box(super::boxblur::cpu_level(), d, stride, w, h, ch, plan, &mut self.row_box_scratch);
            }
            // 8-bit: Q6 fixed point in 16-bit lanes (see `fir16`).
            FrameData::U8(d) if self.streak.is_some() => {
                let plan = self.streak.as_ref().expect("checked");
                streak::blur_u8(d, stride, w, h, ch, plan, &mut self.streak_scratch);
            }
            FrameData::U8(d) => {
                convolve_q6(
                    d,
                    stride,
                    w,
                    h,
                    ch,
                    r,
                    &self.pairs,
                    &self.q15,
                    &self.cols,
                    &self.wq,
                    &mut self.halo,
                    &mut self.ring16,
                    &mut self.offs,
                    &mut self.coffs,
                );
            }
            FrameData::U16(d) => {
                self.padded.resize((w + 2 * r) * ch * (h + 2 * r), 0.0);
                self.acc.resize(w * ch * bands(h), 0.0);
                build_padded(d, stride, w, h, ch, r, &mut self.padded);
                convolve(d, stride, w, h, ch, r, taps, &self.padded, &mut self.acc);
            }
        }
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    /// Orientation (deg, CCW from +x with y up, in [0, 180)) and second moments of a spot.
    fn orientation(f: &Frame) -> (f64, f64, f64) {
        let (w, h) = (f.width as usize, f.height as usize);
        let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for y in 0..h {
            for x in 0..w {
                let v = f.get(x, y, 0) as f64;
                s += v;
                sx += v * x as f64;
                sy += v * y as f64;
            }
        }
        let (mx, my) = (sx / s, sy / s);
        let (mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0);
        for y in 0..h {
            for x in 0..w {
                let v = f.get(x, y, 0) as f64;
                let (dx, dy) = (x as f64 - mx, -(y as f64 - my)); // y up
                xx += v * dx * dx;
                yy += v * dy * dy;
                xy += v * dx * dy;
            }
        }
        let ang = 0.5 * (2.0 * xy).atan2(xx - yy);
        let major = 0.5 * (xx + yy) / s + (0.25 * ((xx - yy) / s).powi(2) + (xy / s).powi(2)).sqrt();
        (ang.to_degrees().rem_euclid(180.0), major, s)
    }

    #[test]
    fn direction_and_length_measured_from_a_blurred_dot() {
        for &angle in &[0.0, 30.0, 45.0, 90.0, 120.0, 165.0] {
            let mut f = Frame::new(81, 81, PixelFormat::Mono16).unwrap();
            f.set(40, 40, 0, 65535.0);
            let mut p = Params::defaults(&INFO);
            p.set("length_px", 24.0).unwrap();
            p.set("angle_deg", angle).unwrap();
            MotionBlur::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            let (got, major, total) = orientation(&f);
            let d = (got - angle).rem_euclid(180.0);
            assert!(d.min(180.0 - d) < 1.0, "angle {angle}: measured {got}");
            // A uniform line of length L has variance L^2/12 along it (48 for L = 24) plus the
            // bilinear spreading (< 1/6 px^2 per axis).
            assert!((major - 48.0).abs() < 1.0, "angle {angle}: variance {major}");
            assert!((total - 65535.0).abs() < 81.0 * 0.5 + 1.0, "conserved: {total}");
        }
        // +45 deg: the streak rises to the right on screen, i.e. its right end is in a smaller row.
        let mut f = Frame::new(41, 41, PixelFormat::Mono8).unwrap();
        f.set(20, 20, 0, 255.0);
        let mut p = Params::defaults(&INFO);
        p.set("length_px", 16.0).unwrap();
        p.set("angle_deg", 45.0).unwrap();
        MotionBlur::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert!(f.get(25, 15, 0) > 0.0 && f.get(15, 25, 0) > 0.0);
        assert_eq!(f.get(25, 25, 0), 0.0);
    }

    #[test]
    fn eight_bit_fixed_point_is_within_one_dn_of_the_exact_line_psf() {
        let mut orig = crate::faults::kit::bench_scene(140, 120, PixelFormat::Rgb8, 2).unwrap();
        for y in 30..60 {
            for x in 70..100 {
                for c in 0..3 {
                    orig.set(x, y, c, 255.0);
                }
            }
        }
        orig.set(30, 90, 1, 255.0);
        let (w, h) = (140usize, 120usize);
        let src = orig.packed_samples_f32();
        for &(len, ang) in &[
            (0.7, 20.0),
            (5.0, 0.0),
            (10.0, 30.0),
            (24.0, 90.0),
            (24.0, 30.0),
            (24.0, 0.0),
            (28.0, 10.0),
            (28.0, 180.0),
        ] {
            assert!(!runs_streak(len, ang) && !runs_row_box(len, ang), "{len} px at {ang} deg runs the FIR");
            let mut f = orig.clone();
            let mut p = Params::defaults(&INFO);
            p.set("length_px", len).unwrap();
            p.set("angle_deg", ang).unwrap();
            MotionBlur::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            let got = f.packed_samples_f32();
            // The exact model: the normalised tap weights in f64, mirrored borders.
            let taps = line_taps(len, ang);
            let total: f64 = taps.iter().map(|t| t.2 as f64).sum();
            let mut worst = 0.0f64;
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3 {
                        let e: f64 = taps
                            .iter()
                            .map(|&(dx, dy, wt)| {
                                let sx = mirror(x as isize + dx as isize, w);
                                let sy = mirror(y as isize + dy as isize, h);
                                wt as f64 / total * src[(sy * w + sx) * 3 + c] as f64
                            })
                            .sum();
                        worst = worst.max((got[(y * w + x) * 3 + c] as f64 - e).abs());
                    }
                }
            }
            assert!(worst < 1.0, "length {len} angle {ang}: max |error| {worst} DN");
        }
    }

    /// The 8-bit FIR as it ran before the ring and the column kernel: a mirrored Q6 copy of the
    /// whole frame, `fir16::sym_fir` per row, `fir16::q6_to_u8`.
    fn fir_reference(f: &Frame, len: f64, ang: f64) -> Frame {
        let (w, h, ch) = (f.width as usize, f.height as usize, f.channels());
        let taps = line_taps(len, ang);
        let r = taps.iter().map(|t| t.0.unsigned_abs().max(t.1.unsigned_abs())).max().unwrap() as usize;
        let (pairs, half) = pair_up(&taps);
        let q = fir16::q15_pairs(&half);
        let pw = (w + 2 * r) * ch;
        let mut padded = vec![0i16; pw * (h + 2 * r)];
        let FrameData::U8(src) = &f.data else { unreachable!() };
        for (py, prow) in padded.chunks_mut(pw).enumerate() {
            let sy = mirror(py as isize - r as isize, h);
            crate::faults::defocus::pad_row_q6(&src[sy * f.stride..sy * f.stride + w * ch], w, ch, r, prow);
        }
        let at = |dx: i32, dy: i32| (r as isize + dy as isize) as usize * pw + (r as isize + dx as isize) as usize * ch;
        let offs: Vec<(usize, usize)> = pairs.iter().map(|&(dx, dy)| (at(-dx, -dy), at(dx, dy))).collect();
        let mut out = f.clone();
        let stride = out.stride;
        let FrameData::U8(d) = &mut out.data else { unreachable!() };
        let mut acc = vec![0i16; w * ch];
        for y in 0..h {
            fir16::sym_fir(&mut acc, &padded[y * pw..], at(0, 0), &offs, &q);
            fir16::q6_to_u8(&mut d[y * stride..y * stride + w * ch], &acc);
        }
        out
    }

    #[test]
    fn eight_bit_fir_ring_and_column_kernel_equal_the_whole_frame_fir() {
        // Oblique, vertical and horizontal streaks (column and row kernels), frames shorter
        // than the taps, band and group tails (heights not multiples of 4), 1 to 3 threads.
        for (w, h, format) in
            [(203u32, 131u32, PixelFormat::Rgb8), (150, 97, PixelFormat::Mono8), (37, 9, PixelFormat::Rgb8)]
        {
            let f = crate::faults::kit::bench_scene(w, h, format, 4).unwrap();
            for (len, ang) in
                [(10.0, 30.0), (24.0, 100.0), (23.0, 145.0), (12.0, 0.0), (3.0, 60.0), (24.0, 5.0), (0.7, 20.0)]
            {
                assert!(!runs_streak(len, ang));
                let want = fir_reference(&f, len, ang);
                for threads in [1, 2, 3] {
                    let mut g = f.clone();
                    let mut p = Params::defaults(&INFO);
                    p.set("length_px", len).unwrap();
                    p.set("angle_deg", ang).unwrap();
                    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                        MotionBlur::default().apply(&mut g, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                    });
                    assert!(g == want, "{format} {w}x{h} {len} px at {ang} deg, {threads} threads");
                }
            }
        }
    }

    #[test]
    fn taps_are_normalised_symmetric_and_zero_length_is_identity() {
        for &(l, a) in &[(0.5, 10.0), (7.3, 33.0), (40.0, 90.0)] {
            let taps = line_taps(l, a);
            let s: f32 = taps.iter().map(|t| t.2).sum();
            assert!((s - 1.0).abs() < 1e-5);
            for &(dx, dy, w) in &taps {
                let m = taps.iter().find(|t| t.0 == -dx && t.1 == -dy).expect("point symmetric");
                assert!((m.2 - w).abs() < 1e-6);
            }
        }
        let orig = crate::faults::kit::bench_scene(64, 48, PixelFormat::Rgb8, 3).unwrap();
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("length_px", 0.0).unwrap();
        MotionBlur::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f, orig);
        p.set("length_px", 9.0).unwrap();
        p.set("angle_deg", 60.0).unwrap();
        let run = |threads| {
            let mut g = orig.clone();
            rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                MotionBlur::default().apply(&mut g, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            });
            g
        };
        assert_eq!(run(1), run(2));
    }
}

#[cfg(test)]
mod rotated_cols_tests {
    use super::*;

    /// The columns of a streak's tap pairs, as `MotionBlur::apply` builds them.
    fn cols_of(len: f64, ang: f64) -> Vec<fir16::TapCol> {
        let (pairs, half) = pair_up(&line_taps(len, ang));
        tap_cols(&pairs, &fir16::q15_pairs(&half)).0
    }

    #[test]
    fn steep_streaks_rotate_every_column_on_four_rows() {
        for (len, ang, steep) in [
            (16.0, 60.0, true),
            (20.0, 60.0, true),
            (24.0, 60.0, true),
            (20.0, 80.0, true),
            (24.0, 80.0, true),
            (24.0, 100.0, true),
            (24.0, 30.0, false),
            (24.0, 45.0, false),
            (10.0, 30.0, false),
            (30.0, 5.0, false),
        ] {
            let cols = cols_of(len, ang);
            assert_eq!(rotated_cols(&cols, 4), steep, "{len} px at {ang} deg");
            assert!(!rotated_cols(&cols, 8), "8 rows (AVX-512) keep sym_fir_cols_u8");
        }
    }
}

#[cfg(test)]
mod streak_tests {
    use super::*;
    use crate::frame::PixelFormat;

    /// The model in f64: the normalised taps of [`line_taps`], mirrored borders.
    fn model(src: &[f64], w: usize, h: usize, ch: usize, len: f64, ang: f64) -> Vec<f64> {
        let taps = line_taps(len, ang);
        let total: f64 = taps.iter().map(|t| t.2 as f64).sum();
        let mut out = vec![0.0; w * h * ch];
        for y in 0..h {
            for x in 0..w {
                for c in 0..ch {
                    out[(y * w + x) * ch + c] = taps
                        .iter()
                        .map(|&(dx, dy, wt)| {
                            let sx = mirror(x as isize + dx as isize, w);
                            let sy = mirror(y as isize + dy as isize, h);
                            wt as f64 / total * src[(sy * w + sx) * ch + c]
                        })
                        .sum();
                }
            }
        }
        out
    }

    fn blur(f: &Frame, len: f64, ang: f64) -> Frame {
        let mut g = f.clone();
        let mut p = Params::defaults(&INFO);
        p.set("length_px", len).unwrap();
        p.set("angle_deg", ang).unwrap();
        MotionBlur::default().apply(&mut g, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        g
    }

    /// Point sources, hard edges (vertical, horizontal, diagonal) and texture, rgb8 and mono8.
    fn scenes() -> Vec<Frame> {
        let mut out = Vec::new();
        for (w, h, format) in [(181u32, 163u32, PixelFormat::Rgb8), (150, 170, PixelFormat::Mono8)] {
            let mut f = crate::faults::kit::bench_scene(w, h, format, 5).unwrap();
            let ch = f.channels();
            for y in 0..h as usize {
                for x in 0..w as usize {
                    let v = if x > 120 && y > 20 && y < 60 {
                        255.0
                    } else if x < 40 && y > 100 {
                        if x + y > 120 { 255.0 } else { 0.0 }
                    } else if (60..100).contains(&x) && y > 110 {
                        0.0
                    } else {
                        continue;
                    };
                    for c in 0..ch {
                        f.set(x, y, c, v);
                    }
                }
            }
            for (x, y) in [(90usize, 80usize), (20, 20), (130, 140), (5, 90)] {
                for c in 0..ch {
                    f.set(x, y, c, 255.0);
                }
            }
            out.push(f);
        }
        out
    }

    /// Streaks exactly along x longer than 28 px: the row box (exact 16-bit sums with the model's
    /// weights, the end taps and the division as multiply-highs) is within 0.55 DN of the model
    /// (the final rounding 0.5 plus the truncations: two end-tap products, the division's
    /// product and reciprocal, about 0.03 DN), keeps the mean, and does not depend on the thread
    /// count; frames narrower than the streak (mirrored more than once) included.
    #[test]
    fn row_box_is_within_the_stated_bound_of_the_model() {
        assert!(!runs_row_box(28.0, 0.0) && !runs_row_box(30.0, 0.5) && !runs_row_box(30.0, 90.0));
        let mut frames = scenes();
        frames.push(crate::faults::kit::bench_scene(37, 9, PixelFormat::Rgb8, 4).unwrap());
        let mut report = Vec::new();
        for f in frames {
            let (w, h, ch) = (f.width as usize, f.height as usize, f.channels());
            let src: Vec<f64> = f.packed_samples_f32().iter().map(|&v| v as f64).collect();
            for (len, ang) in [
                (28.5, 0.0),
                (29.0, 180.0),
                (30.0, 0.0),
                (37.3, 0.0),
                (40.0, 180.0),
                (66.0, 0.0),
                (99.9, 0.0),
                (100.0, 180.0),
            ] {
                assert!(runs_row_box(len, ang) && !runs_streak(len, ang), "{len} px at {ang} deg runs the row box");
                let got = blur(&f, len, ang);
                let g = got.packed_samples_f32();
                let want = model(&src, w, h, ch, len, ang);
                let worst = g.iter().zip(&want).map(|(&a, &b)| (a as f64 - b).abs()).fold(0.0, f64::max);
                let mean = g.iter().map(|&v| v as f64).sum::<f64>() / g.len() as f64;
                let mean0 = want.iter().sum::<f64>() / want.len() as f64;
                report.push(format!("{} {w}x{h} {len}@{ang}: max {worst:.3} DN, mean {:+.4}", f.format, mean - mean0));
                assert!(worst <= 0.55, "{} {w}x{h}: {len} px @ {ang}: max |error| {worst} DN", f.format);
                // The mean on the scenes (the 37 x 9 frame has 27 rows' worth of independent
                // roundings: a streak longer than the row gives every pixel of a row almost the same value).
                if w > 100 {
                    assert!((mean - mean0).abs() < 0.05, "{}: {len} px @ {ang}: mean {}", f.format, mean - mean0);
                }
                for threads in [2, 3] {
                    let mut g2 = f.clone();
                    let mut p = Params::defaults(&INFO);
                    p.set("length_px", len).unwrap();
                    p.set("angle_deg", ang).unwrap();
                    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                        MotionBlur::default().apply(&mut g2, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                    });
                    assert!(g2 == got, "{} {w}x{h} {len} px at {ang} deg, {threads} threads", f.format);
                }
            }
        }
        eprintln!("{}", report.join("\n"));
    }

    /// The row box's AVX-512, AVX2 and scalar kernels give the same bytes (segments with and
    /// without the odd window `acc`, rows shorter than a register and than the streak).
    #[test]
    fn row_box_kernels_give_the_same_bytes() {
        let mut frames = scenes();
        frames.push(crate::faults::kit::bench_scene(37, 9, PixelFormat::Rgb8, 4).unwrap());
        frames.push(crate::faults::kit::bench_scene(2111, 5, PixelFormat::Mono8, 4).unwrap());
        for f in frames {
            let (w, h, ch) = (f.width as usize, f.height as usize, f.channels());
            for len in [28.5, 30.0, 37.3, 66.0, 100.0] {
                let taps = line_taps(len, 0.0);
                let plan = RowBox::new(len, 0.0, &taps).expect("a row box");
                let outs: Vec<Frame> = [0u8, 1, 2]
                    .iter()
                    .map(|&lv| {
                        let mut g = f.clone();
                        let stride = g.stride;
                        let FrameData::U8(d) = &mut g.data else { panic!("8-bit") };
                        row_box(lv, d, stride, w, h, ch, plan, &mut Vec::new());
                        g
                    })
                    .collect();
                assert!(outs[1] == outs[0] && outs[2] == outs[0], "{} {w}x{h}: {len} px", f.format);
                assert!(outs[0] != f, "{} {w}x{h}: {len} px blurs", f.format);
            }
        }
    }

    #[test]
    fn running_sum_streak_is_within_the_stated_bound_of_the_model() {
        let mut report = Vec::new();
        for f in scenes() {
            let (w, h, ch) = (f.width as usize, f.height as usize, f.channels());
            let src: Vec<f64> = f.packed_samples_f32().iter().map(|&v| v as f64).collect();
            let cases = if std::env::var_os("STREAK_SWEEP").is_some() {
                let mut v = Vec::new();
                for len in [12.5, 16.0, 25.0, 37.5, 50.0, 61.0, 75.0, 100.0] {
                    for ang in [0.0, 10.0, 22.5, 30.0, 45.0, 60.0, 80.0, 100.0, 137.0, 170.0] {
                        v.push((len, ang));
                    }
                }
                v
            } else {
                vec![
                    (12.5, 0.0),
                    (13.0, 30.0),
                    (20.0, 45.0),
                    (30.0, 63.0),
                    (37.5, 137.0),
                    (40.0, 30.0),
                    (64.0, 90.0),
                    (100.0, 170.0),
                    (100.0, 100.0),
                ]
            };
            for &(len, ang) in &cases {
                let got = blur(&f, len, ang).packed_samples_f32();
                let want = model(&src, w, h, ch, len, ang);
                let (wi, worst) = got
                    .iter()
                    .zip(&want)
                    .map(|(&a, &b)| (a as f64 - b).abs())
                    .enumerate()
                    .fold((0, 0.0), |a, (i, e)| if e > a.1 { (i, e) } else { a });
                let px = wi / ch;
                let at = format!("worst at ({}, {}) c {}: {} vs {:.2}", px % w, px / w, wi % ch, got[wi], want[wi]);
                let mean = got.iter().map(|&v| v as f64).sum::<f64>() / got.len() as f64;
                let mean0 = want.iter().sum::<f64>() / want.len() as f64;
                report.push(format!("{} {len}@{ang}: max {worst:.2} DN ({at}), mean {:+.3}", f.format, mean - mean0));
                assert!(
                    worst <= streak_max_error_dn(len, ang) + 1e-9,
                    "{}: {len} px @ {ang}: max |error| {worst} DN",
                    f.format
                );
                assert!((mean - mean0).abs() < 0.05, "{}: {len} px @ {ang}: mean {}", f.format, mean - mean0);
            }
        }
        eprintln!("{}", report.join("\n"));
    }
}
