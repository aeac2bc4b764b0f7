//! Motion blur of 8-bit frames at a cost independent of the streak length: shear, running sum,
//! unshear.
//!
//! The line PSF of `motion_blur` (length `L`, unit direction `u`) is, up to its 1/8 px
//! quadrature, `P(d) = (1/L) integral over s in [-L/2, L/2] of tent(dx - s ux) tent(dy - s uy)`
//! (the line spread bilinearly). Call the axis along which `u` has its larger component the
//! *major* axis, and lines the image lines across it (rows for a mostly vertical streak, columns
//! for a mostly horizontal one: those are transposed first). Along the major axis the streak moves
//! `m` (|m| <= 1) pixels within a line per line step and spans `2T = L |u_major|` lines. Output
//! line `i` at position `x` is
//!
//!   `out(i, x) = sum_d W(d) J(i + d, x + d m)`,  `W(d) = (1/2T) integral_{-T}^{T} tent(d - t) dt`
//!
//! where `J(j, z)` interpolates line `j` linearly at position `z` (exactly the model's weights
//! along the major axis; across it the model's profile `tent * tent(./m)` is replaced by the two
//! linear interpolations below). With `A(j, k) = J(j, k + j m)` (line `j` shifted by `j m`: the
//! shear), `out(i, x) = sum_d W(d) A(i + d, x - i m)`: for each `k` a sum across lines with fixed
//! weights, kept as a running sum (`2n + 1` full-weight lines plus two partial taps at each end).
//! `x - i m` is not whole: the result is interpolated linearly between `k = floor(x - i m)` and
//! `k + 1` (the unshear). The shifts `j m` and `-i m` are rounded to 1/64 px.
//!
//! Arithmetic is f32 on integer-valued data: `A` is `(64 - f) p0 + f p1` of two bytes (an exact
//! integer <= 16320), the running sums are exact integers (< 2^24), and the remaining operations
//! (end taps, unshear, normalisation, rounding half to even) are the same IEEE operations in the
//! same order on every path: the bytes do not depend on the CPU (scalar, AVX2, AVX-512 copies of
//! one loop) nor on how lines are split over threads (exact sums). Borders are mirrored
//! (half-sample symmetric) per axis like the model's taps.

use super::defocus::mirror;
use rayon::prelude::*;

/// Geometry and weights of one streak.
#[derive(Clone, Debug, PartialEq)]
pub struct StreakPlan {
    /// True: lines are image rows (the streak is at least as vertical as horizontal).
    pub vertical: bool,
    /// Shift within a line per line step (|m| <= 1).
    pub m: f64,
    /// Full-weight taps each side of the centre line.
    pub n: usize,
    /// Weights of the partial taps at distance n + 1 and n + 2 (the full taps weigh 1).
    pub e: [f32; 2],
    /// 1 / (total weight * 64 * 64).
    pub inv: f32,
    /// The model's cross-streak variance (px^2) averaged over the lines with their weights: per
    /// line `d` the discrete variance of `g_m = tent * tent(./m)/|m|` sampled at phase `frac(d m)`.
    pub vbar: f64,
}

/// CDF of the unit tent (triangle on [-1, 1]).
fn tent_cdf(z: f64) -> f64 {
    if z <= -1.0 {
        0.0
    } else if z <= 0.0 {
        0.5 * (1.0 + z) * (1.0 + z)
    } else if z < 1.0 {
        1.0 - 0.5 * (1.0 - z) * (1.0 - z)
    } else {
        1.0
    }
}

/// Discrete variance of the model's cross-streak profile `g_m(z) = integral tent(u) tent(z - m u)
/// du` sampled at the integers around phase `phi` (the bilinear spreading of the line samples).
fn model_cross_variance(m: f64, phi: f64) -> f64 {
    const Q: usize = 256;
    let tent = |z: f64| (1.0 - z.abs()).max(0.0);
    let g = |z: f64| {
        (0..Q).map(|k| -1.0 + (k as f64 + 0.5) * 2.0 / Q as f64).map(|u| tent(u) * tent(z - m * u)).sum::<f64>() * 2.0
            / Q as f64
    };
    let (mut s, mut s2) = (0.0, 0.0);
    for e in -3..=3 {
        let z = e as f64 - phi;
        let v = g(z);
        s += v;
        s2 += v * z * z;
    }
    s2 / s
}

/// Whether a streak at `angle_deg` runs its lines along image rows (at least as vertical as
/// horizontal), see [`StreakPlan::vertical`].
pub fn is_vertical(angle_deg: f64) -> bool {
    let t = angle_deg.to_radians();
    t.sin().abs() >= t.cos().abs()
}

impl StreakPlan {
    /// Plan for a streak of `length` px (>= 2) at `angle_deg` (CCW from +x, y up on screen).
    pub fn new(length: f64, angle_deg: f64) -> StreakPlan {
        let t = angle_deg.to_radians();
        let (ux, uy) = (t.cos(), -t.sin());
        let vertical = is_vertical(angle_deg);
        let (major, minor) = if vertical { (uy, ux) } else { (ux, uy) };
        let m = minor / major;
        let tt = 0.5 * length * major.abs();
        assert!(tt >= 1.0, "streak too short for the running-sum path: {length} px");
        let n = (tt - 1.0).floor() as usize;
        // Relative weight of the line at distance d (1 for |d| <= n, 0 from n + 3).
        let wgt = |d: f64| tent_cdf(d + tt) - tent_cdf(d - tt);
        let e = [wgt(n as f64 + 1.0) as f32, wgt(n as f64 + 2.0) as f32];
        let total = (2 * n + 1) as f64 + 2.0 * (e[0] as f64 + e[1] as f64);
        let mut p = StreakPlan { vertical, m, n, e, inv: (1.0 / (total * 4096.0)) as f32, vbar: 0.0 };
        p.vbar = p
            .line_weights()
            .iter()
            .enumerate()
            .map(|(i, &wd)| wd * model_cross_variance(m, ((i as f64 - n as f64 - 2.0) * m).rem_euclid(1.0)))
            .sum();
        p
    }

    /// Variance (px^2) of the cross-streak weights this path gives output line `i` before the
    /// cross filter: per contributing line the two linear interpolations (shear at `f`, unshear
    /// at `g`) add `f (1 - f) + g (1 - g)`.
    fn path_cross_variance(&self, i: isize) -> f64 {
        let ph = |j: isize| (self.shift_q(j) & 63) as f64 / 64.0;
        let g = ((-self.shift_q(i)) & 63) as f64 / 64.0;
        let n = self.n as isize;
        let w = self.line_weights();
        let f: f64 = (-n - 2..=n + 2).zip(&w).map(|(d, &wd)| wd * ph(i + d) * (1.0 - ph(i + d))).sum();
        f + g * (1.0 - g)
    }

    /// Weight `a` of the cross filter `[a, 1 - 2a, a]` for output line `i`: makes up the
    /// difference to the model's cross-streak variance (`2a`), none if this path is already wider.
    pub fn cross_tap(&self, i: isize) -> f32 {
        ((self.vbar - self.path_cross_variance(i)) / 2.0).clamp(-0.25, 0.25) as f32
    }

    /// The relative tap weights across lines, `-(n + 2)..=n + 2`, normalised (the model the
    /// running sums compute, for tests).
    pub fn line_weights(&self) -> Vec<f64> {
        let n = self.n;
        let total = (2 * n + 1) as f64 + 2.0 * (self.e[0] as f64 + self.e[1] as f64);
        (0..2 * n + 5)
            .map(|i| {
                let d = (i as isize - n as isize - 2).unsigned_abs();
                (if d <= n { 1.0 } else { self.e[d - n - 1] as f64 }) / total
            })
            .collect()
    }

    /// Shift of line `j` (in 1/64 px): `round(64 j m)`.
    fn shift_q(&self, j: isize) -> i64 {
        (64.0 * j as f64 * self.m).round() as i64
    }
}

/// Per-thread scratch of one band of lines.
#[derive(Default)]
struct Slot {
    // running sums R(k) and the lines A(j, k) at j = i - n - 2 .. i - n and i + n + 1, i + n + 2,
    // over the band's range of k (f32, `ch` per position); the B row; a padded source line
    r: Vec<f32>,
    a: [Vec<f32>; 5],
    b: Vec<f32>,
    u: Vec<f32>,
    pad: Vec<u8>,
    // the cross-filter tap of each line of the band
    taps: Vec<f32>,
}

/// Scratch of [`blur_u8`]; grows only (allocation when the frame size or the streak grows).
#[derive(Default)]
pub struct Scratch {
    // allocation: per frame size: the source (rows, or columns transposed) and, for mostly
    // horizontal streaks, the transposed output
    src: Vec<u8>,
    out: Vec<u8>,
    // allocation: per frame size, streak and thread count: one slot per band
    slots: Vec<Slot>,
}

/// Line access: `nl` pixels of `ch` samples per line, lines `stride` bytes apart.
#[derive(Clone, Copy)]
struct Lines<'a> {
    data: &'a [u8],
    stride: usize,
    count: usize,
    nl: usize,
    ch: usize,
}

impl Lines<'_> {
    fn line(&self, j: isize) -> &[u8] {
        let j = mirror(j, self.count);
        &self.data[j * self.stride..j * self.stride + self.nl * self.ch]
    }
}

macro_rules! dispatch {
    ($name:ident, $body:ident, ($($a:ident: $t:ty),*)) => {
        #[inline]
        fn $name(lv: u8, $($a: $t),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
                unsafe fn v512($($a: $t),*) { $body($($a),*) }
                #[target_feature(enable = "avx2")]
                unsafe fn v256($($a: $t),*) { $body($($a),*) }
                if lv >= 2 && super::kit::has_avx512() {
                    // SAFETY: AVX-512 F/BW/VL present (checked).
                    return unsafe { v512($($a),*) };
                }
                if lv >= 1 && super::kit::has_avx2() {
                    // SAFETY: AVX2 present (checked).
                    return unsafe { v256($($a),*) };
                }
            }
            $body($($a),*)
        }
    };
}

/// `a[t] = p[t] (64 - f) + p[t + ch] f` for `t < a.len()`.
#[inline(always)]
fn lerp_k(a: &mut [f32], p: &[u8], ch: usize, f: u8) {
    let (w0, w1) = ((64 - f) as f32, f as f32);
    let p1 = &p[ch..ch + a.len()];
    let p0 = &p[..a.len()];
    for ((a, &x0), &x1) in a.iter_mut().zip(p0).zip(p1) {
        *a = x0 as f32 * w0 + x1 as f32 * w1;
    }
}
dispatch!(lerp_d, lerp_k, (a: &mut [f32], p: &[u8], ch: usize, f: u8));

/// `r[t] += a[t]` (exact: integer values below 2^24).
#[inline(always)]
fn add_k(r: &mut [f32], a: &[f32]) {
    for (r, &a) in r.iter_mut().zip(a) {
        *r += a;
    }
}
dispatch!(add_d, add_k, (r: &mut [f32], a: &[f32]));

/// `r[t] += lead[t] - trail[t]` (exact).
#[inline(always)]
fn slide_k(r: &mut [f32], lead: &[f32], trail: &[f32]) {
    for ((r, &l), &t) in r.iter_mut().zip(lead).zip(trail) {
        *r += l - t;
    }
}
dispatch!(slide_d, slide_k, (r: &mut [f32], lead: &[f32], trail: &[f32]));

/// `b = r + e0 (t1 + l1) + e1 (t2 + l2)`.
#[inline(always)]
fn ends_k(b: &mut [f32], r: &[f32], t1: &[f32], l1: &[f32], t2: &[f32], l2: &[f32], e0: f32, e1: f32) {
    let n = b.len();
    let (r, t1, l1, t2, l2) = (&r[..n], &t1[..n], &l1[..n], &t2[..n], &l2[..n]);
    for i in 0..n {
        b[i] = r[i] + e0 * (t1[i] + l1[i]) + e1 * (t2[i] + l2[i]);
    }
}
dispatch!(ends_d, ends_k, (b: &mut [f32], r: &[f32], t1: &[f32], l1: &[f32], t2: &[f32], l2: &[f32], e0: f32, e1: f32));

/// `u[t] = b[t] (64 - g) + b[t + ch] g` (the unshear), then
/// `out[t] = round_half_even((u[t + ch] (1 - 2a) + (u[t] + u[t + 2 ch]) a) inv)` clamped to 0..=255
/// (the cross filter). `b` and `u` start one position before the output.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn unshear_k(out: &mut [u8], b: &[f32], u: &mut [f32], ch: usize, g: u8, a: f32, inv: f32) {
    let (w0, w1) = ((64 - g) as f32, g as f32);
    let n = out.len();
    let m = n + 2 * ch;
    let (b0, b1, u) = (&b[..m], &b[ch..ch + m], &mut u[..m]);
    for i in 0..m {
        u[i] = b0[i] * w0 + b1[i] * w1;
    }
    let c0 = 1.0 - 2.0 * a;
    let (ul, uc, ur) = (&u[..n], &u[ch..ch + n], &u[2 * ch..2 * ch + n]);
    for i in 0..n {
        let v = ((uc[i] * c0 + (ul[i] + ur[i]) * a) * inv).round_ties_even().clamp(0.0, 255.0);
        // SAFETY: `v` is finite (sums and products of finite values, clamped) and in 0..=255,
        // so the conversion is exact and defined (and vectorises, unlike `as u8`).
        out[i] = unsafe { v.to_int_unchecked::<i32>() } as u8;
    }
}
dispatch!(unshear_d, unshear_k, (out: &mut [u8], b: &[f32], u: &mut [f32], ch: usize, g: u8, a: f32, inv: f32));

/// Output positions (pixels along a line) per column block: the block's running sums and held
/// lines stay in the L1 cache while it runs down the band.
const CHUNK: isize = 256;

/// One band of output lines `i0..i0 + rows` (written to `dst`, lines `dstride` apart), block by
/// block of output positions `k` (line `i` writes pixel `x = k - klo(i)`).
#[allow(clippy::too_many_arguments)]
fn band(
    lv: u8,
    plan: &StreakPlan,
    src: Lines,
    i0: usize,
    rows: usize,
    dst: &mut [u8],
    dstride: usize,
    slot: &mut Slot,
) {
    let (nl, ch) = (src.nl, src.ch);
    let n = plan.n as isize;
    // Line i's output pixel x reads B at k = x + klo(i) and k + 1 (phase g); the cross filter
    // needs one position more on each side.
    let klo = |i: usize| -> (isize, u8) {
        let q = -plan.shift_q(i as isize);
        ((q >> 6) as isize, (q & 63) as u8)
    };
    slot.taps.clear();
    slot.taps.extend((i0..i0 + rows).map(|i| plan.cross_tap(i as isize)));
    let len = (CHUNK as usize + 3) * ch;
    for v in [&mut slot.r, &mut slot.b, &mut slot.u].into_iter().chain(slot.a.iter_mut()) {
        if v.len() < len {
            v.resize(len, 0.0);
        }
    }
    // A(j, k) for k in [k0, k1) into `a` (index (k - base) ch).
    let fill = |a: &mut [f32], pad: &mut Vec<u8>, base: isize, j: isize, k0: isize, k1: isize| {
        let q = plan.shift_q(j);
        let (s, f) = ((q >> 6) as isize, (q & 63) as u8);
        let line = src.line(j);
        let x = |k: isize| (k - base) as usize * ch;
        // Positions whose two pixels are inside the line read it directly; the others go
        // through a mirrored copy.
        let (i0, i1) = ((-s).clamp(k0, k1), (nl as isize - 1 - s).clamp(k0, k1).max((-s).clamp(k0, k1)));
        if i1 > i0 {
            let p = ((i0 + s) as usize) * ch;
            lerp_d(lv, &mut a[x(i0)..x(i1)], &line[p..p + ((i1 - i0) as usize + 1) * ch], ch, f);
        }
        for (e0, e1) in [(k0, i0), (i1, k1)] {
            if e1 > e0 {
                pad.clear();
                for p in e0 + s..e1 + s + 1 {
                    let sp = mirror(p, nl) * ch;
                    pad.extend_from_slice(&line[sp..sp + ch]);
                }
                lerp_d(lv, &mut a[x(e0)..x(e1)], pad, ch, f);
            }
        }
    };
    // Lines held in `a`: slot t holds j = i + off[t].
    let off = [-n - 2, -n - 1, -n, n + 1, n + 2];
    let (ka, kb) = (klo(i0).0, klo(i0 + rows - 1).0);
    let mut c0 = ka.min(kb);
    while c0 < ka.max(kb) + nl as isize {
        let c1 = c0 + CHUNK;
        // State over k in [c0 - 1, c1 + 2), local index (k - base) ch.
        let base = c0 - 1;
        let w = (c1 + 2 - base) as usize * ch;
        let mut started = false;
        for (row, i) in (i0..i0 + rows).enumerate() {
            let (k, g) = klo(i);
            let (o0, o1) = (c0.max(k), c1.min(k + nl as isize));
            if o0 >= o1 {
                if started {
                    break;
                }
                continue;
            }
            let Slot { r, a, b, u, pad, taps } = &mut *slot;
            if !started {
                // Running sums and held lines at line i.
                started = true;
                r[..w].fill(0.0);
                for d in -n..=n {
                    fill(b, pad, base, i as isize + d, base, c1 + 2);
                    add_d(lv, &mut r[..w], &b[..w]);
                }
                for (t, &o) in off.iter().enumerate() {
                    fill(&mut a[t], pad, base, i as isize + o, base, c1 + 2);
                }
            }
            // B over [o0 - 1, o1 + 2), then unshear and cross filter into pixels o0 - k.. o1 - k.
            let (x0, x1) = ((o0 - 1 - base) as usize * ch, (o1 + 2 - base) as usize * ch);
            ends_d(
                lv,
                &mut b[x0..x1],
                &r[x0..x1],
                &a[1][x0..x1],
                &a[3][x0..x1],
                &a[0][x0..x1],
                &a[4][x0..x1],
                plan.e[0],
                plan.e[1],
            );
            let p0 = row * dstride + (o0 - k) as usize * ch;
            let orow = &mut dst[p0..p0 + (o1 - o0) as usize * ch];
            unshear_d(lv, orow, &b[x0..x1], u, ch, g, taps[row], plan.inv);
            if row + 1 == rows {
                break;
            }
            let Slot { r, a, pad, .. } = &mut *slot;
            // Advance to line i + 1.
            slide_d(lv, &mut r[..w], &a[3][..w], &a[2][..w]);
            // Trail: t2 <- t1 <- t0 <- A(i + 1 - n); lead: l1 <- l2 <- A(i + 1 + n + 2).
            a.swap(0, 1);
            a.swap(1, 2);
            fill(&mut a[2], pad, base, i as isize + 1 - n, base, c1 + 2);
            a.swap(3, 4);
            fill(&mut a[4], pad, base, i as isize + 1 + n + 2, base, c1 + 2);
        }
        c0 = c1;
    }
}

/// Pixel transpose: `dst[x * dstride + y * ch + c] = src[y * sstride + x * ch + c]` for
/// `x < w`, `y < h`, in blocks of 16 x 16 pixels (a block's rows stay in cache).
fn transpose(src: &[u8], sstride: usize, w: usize, h: usize, ch: usize, dst: &mut [u8], dstride: usize) {
    match ch {
        1 => transpose_px::<1>(src, sstride, w, h, dst, dstride),
        3 => transpose_px::<3>(src, sstride, w, h, dst, dstride),
        _ => unreachable!("8-bit frames have 1 or 3 channels"),
    }
}

fn transpose_px<const C: usize>(src: &[u8], sstride: usize, w: usize, h: usize, dst: &mut [u8], dstride: usize) {
    const B: usize = 32;
    let used = dst.len().min(dstride * w);
    dst[..used].par_chunks_mut(dstride * B).enumerate().for_each(|(bx, dband)| {
        let x0 = bx * B;
        let xs = B.min(w - x0);
        for y0 in (0..h).step_by(B) {
            let ys = B.min(h - y0);
            let sblock = &src[y0 * sstride + x0 * C..];
            for dx in 0..xs {
                let drow = &mut dband[dx * dstride + y0 * C..dx * dstride + (y0 + ys) * C];
                for (dy, d) in drow.chunks_exact_mut(C).enumerate() {
                    let o = dy * sstride + dx * C;
                    let px: &[u8; C] = sblock[o..o + C].try_into().expect("C bytes");
                    d.copy_from_slice(px);
                }
            }
        }
    });
}

/// Streak blur of an 8-bit frame (`ch` interleaved channels, rows of `stride` bytes) in place.
pub fn blur_u8(d: &mut [u8], stride: usize, w: usize, h: usize, ch: usize, plan: &StreakPlan, sc: &mut Scratch) {
    blur_u8_at(super::boxblur::cpu_level(), d, stride, w, h, ch, plan, sc)
}

/// [`blur_u8`] with the kernels of level `lv` at most (2 AVX-512, 1 AVX2, 0 scalar).
#[allow(clippy::too_many_arguments)]
pub fn blur_u8_at(
    lv: u8,
    d: &mut [u8],
    stride: usize,
    w: usize,
    h: usize,
    ch: usize,
    plan: &StreakPlan,
    sc: &mut Scratch,
) {
    let (count, nl) = if plan.vertical { (h, w) } else { (w, h) };
    let ls = nl * ch;
    if sc.src.len() < count * ls {
        sc.src.resize(count * ls, 0);
    }
    if plan.vertical {
        sc.src[..count * ls]
            .par_chunks_mut(ls)
            .enumerate()
            .for_each(|(y, l)| l.copy_from_slice(&d[y * stride..y * stride + ls]));
    } else {
        transpose(d, stride, w, h, ch, &mut sc.src[..count * ls], ls);
        if sc.out.len() < count * ls {
            sc.out.resize(count * ls, 0);
        }
    }
    let threads = rayon::current_num_threads().max(1);
    let per = count.div_ceil(threads).max(64);
    let nb = count.div_ceil(per);
    if sc.slots.len() < nb {
        sc.slots.resize_with(nb, Slot::default);
    }
    let src = Lines { data: &sc.src, stride: ls, count, nl, ch };
    let (dst, dstride): (&mut [u8], usize) = if plan.vertical { (d, stride) } else { (&mut sc.out[..count * ls], ls) };
    let used = dst.len().min(dstride * count);
    dst[..used].par_chunks_mut(dstride * per).zip(sc.slots.par_iter_mut()).enumerate().for_each(|(b, (out, slot))| {
        let i0 = b * per;
        band(lv, plan, src, i0, per.min(count - i0), out, dstride, slot);
    });
    if !plan.vertical {
        transpose(&sc.out, ls, h, w, ch, d, stride);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_are_the_box_convolved_with_the_tent() {
        for (len, ang) in [(12.0, 0.0), (37.5, 137.0), (100.0, 63.0), (13.0, 45.0)] {
            let p = StreakPlan::new(len, ang);
            let w = p.line_weights();
            let s: f64 = w.iter().sum();
            assert!((s - 1.0).abs() < 1e-6, "{len} {ang}: sum {s}");
            // Variance of the streak along the major axis: box (2T)^2/12 plus the tent's 1/6.
            let t = ang.to_radians();
            let major = if p.vertical { t.sin().abs() } else { t.cos().abs() };
            let tt = 0.5 * len * major;
            let var: f64 = w.iter().enumerate().map(|(i, &v)| v * (i as f64 - p.n as f64 - 2.0).powi(2)).sum();
            let want = (2.0 * tt).powi(2) / 12.0 + 1.0 / 6.0;
            assert!((var - want).abs() < 1e-3 * want, "{len} {ang}: variance {var} vs {want}");
            assert!(p.m.abs() <= 1.0);
        }
    }

    #[test]
    fn every_kernel_level_and_thread_count_gives_the_same_bytes() {
        use crate::frame::{FrameData, PixelFormat};
        for (w, h, format) in [(203u32, 131u32, PixelFormat::Rgb8), (150, 190, PixelFormat::Mono8)] {
            let f = crate::faults::kit::bench_scene(w, h, format, 3).unwrap();
            let ch = format.channels();
            for (len, ang) in [(13.0, 10.0), (40.0, 63.0), (100.0, 137.0), (30.0, 90.0), (25.0, 0.0)] {
                let plan = StreakPlan::new(len, ang);
                let run = |lv: u8, threads: usize| {
                    let mut g = f.clone();
                    let stride = g.stride;
                    let FrameData::U8(d) = &mut g.data else { unreachable!() };
                    rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                        blur_u8_at(lv, d, stride, w as usize, h as usize, ch, &plan, &mut Scratch::default())
                    });
                    g
                };
                let scalar = run(0, 1);
                assert_ne!(scalar, f, "{format} {len}@{ang}: blurred");
                assert_eq!(run(1, 1), scalar, "{format} {len}@{ang}: AVX2 vs scalar");
                assert_eq!(run(2, 1), scalar, "{format} {len}@{ang}: AVX-512 vs scalar");
                assert_eq!(run(2, 3), scalar, "{format} {len}@{ang}: 3 threads vs 1");
            }
        }
    }
}
