//! Motion blur of 8-bit frames at a cost independent of the streak length: shear, running sum,
//! unshear.
//!
//! The line PSF of `motion_blur` (length `L`, unit direction `u`) is, up to its 1/8 px
//! quadrature, `P(d) = (1/L) integral over s in [-L/2, L/2] of tent(dx - s ux) tent(dy - s uy)`
//! (the line spread bilinearly). Call the axis along which `u` has its larger component the
//! *major* axis, and lines the image lines across it (rows for a mostly vertical streak, columns
//! for a mostly horizontal one: read from the frame 8 columns at a time through 8 x 8 register
//! transposes). Along the major axis the streak moves
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
//! Arithmetic is 16-bit unsigned integer (16 lanes per AVX2 register, twice f32's): `A` is
//! `((64 - f) p0 + f p1) 2^q / 64` of two bytes rounded, with `q <= 6` fraction bits chosen per
//! streak so that the running sum of `2n + 1` lines plus the end taps stays below 2^16 (`q = 1`
//! at 100 px, 3 at 25 px: each line's interpolation within 1/4 resp. 1/16 DN); the running sums
//! are exact (wrapping 16-bit adds whose true value fits), the end taps, unshear, cross filter and
//! the final division are multiply-highs (`vpmulhuw`) with 16-bit weights. Every operation is an
//! integer operation, the same on every path: the bytes do not depend on the CPU (scalar, AVX2,
//! AVX-512 copies of one loop) nor on how lines are split over threads (exact sums). Borders are
//! mirrored (half-sample symmetric) per axis like the model's taps.

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
    /// The partial taps' weights in the integer step: `floor(65536 e)` (a multiply-high).
    pub eq: [u16; 2],
    /// Fraction bits of the held lines `A` (`A` = the interpolated line times `2^q`, rounded):
    /// the largest `q <= 6` whose running sum with its end taps fits 16 bits.
    pub q: u32,
    /// The final division by `D` = total integer weight * 2^(q - 1) (the step's `B` per DN):
    /// `out = ((mulhi(v + OFF, dm) - mulhi(OFF, dm)) >> (ds - 1) + 1) >> 1`, `dm = round(2^(16 + ds)
    /// / D)` (the largest `ds` with `dm < 2^16`).
    pub dm: u16,
    /// The shift of the final division (see `dm`), at least 1.
    pub ds: u32,
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
        let eq = e.map(|v| (v as f64 * 65536.0).floor().min(65535.0) as u16);
        // The running sum (2n + 1 lines) plus the end taps, all samples 255: at most 65535.
        let q = (0..=6u32).rev().find(|&q| (2 * n + 5) as u64 * (255 << q) <= 65535).unwrap_or(0);
        let total_q = (2 * n + 1) as f64 + 2.0 * (eq[0] as f64 + eq[1] as f64) / 65536.0;
        let dd = total_q * (1u32 << q) as f64 / 2.0;
        let ds = (1..=15u32).rev().find(|&s| (2f64.powi(16 + s as i32) / dd).round() < 65536.0).unwrap_or(1);
        let dm = (2f64.powi(16 + ds as i32) / dd).round() as u16;
        let mut p = StreakPlan { vertical, m, n, e, eq, q, dm, ds, vbar: 0.0 };
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
    /// difference to the model's cross-streak variance (`2a`), none if this path is already wider;
    /// in 1/65536 (|a| <= 1/4).
    pub fn cross_tap(&self, i: isize) -> i32 {
        (((self.vbar - self.path_cross_variance(i)) / 2.0).clamp(-0.25, 0.25) * 65536.0).round() as i32
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

    /// Shift of line `j` (in 1/64 px): `round(64 j m)` (half away from zero, as `f64::round`,
    /// without its library call: the band loops ask for it per line and block).
    #[inline]
    fn shift_q(&self, j: isize) -> i64 {
        let x = 64.0 * j as f64 * self.m;
        // |x| <= 64 |j| < 2^52: the truncation and the fraction `x - t` are exact.
        let t = x as i64;
        let fr = x - t as f64;
        if fr >= 0.5 {
            t + 1
        } else if fr <= -0.5 {
            t - 1
        } else {
            t
        }
    }
}

/// Per-thread scratch of one band of lines.
#[derive(Default)]
struct Slot {
    // running sums R(k) over the block's range of k (16-bit, `ch` per position); the B row; a
    // padded source line
    r: Vec<u16>,
    b: Vec<u16>,
    // the unshear's interpolated `B` of a line (see `simd::unshear`)
    u: Vec<u16>,
    // allocation: per streak length: a ring of the 2n + 5 lines A(j, k) of the window, j = i - n - 2
    // ..= i + n + 2, line j in slot j mod (2n + 5), each `line` values apart (every source line is
    // interpolated once per block, when it enters the window)
    ring: Vec<u16>,
    pad: Vec<u8>,
    // mostly horizontal streaks: the last output lines (up to `TILE`), a chunk's positions each
    tile: Vec<u8>,
    // mostly horizontal streaks: the band's own source lines read from the frame (see `Strips`)
    strips: Strips,
    // allocation: per frame size and streak: the shift of every line the band reads (see
    // `Shifts`)
    shifts: Vec<i64>,
}

/// [`StreakPlan::shift_q`] of lines `j0..j0 + v.len()`, looked up (the band asks for a line's
/// shift several times per block: its output position, its fill, its group's load).
#[derive(Clone, Copy)]
struct Shifts<'a> {
    v: &'a [i64],
    j0: isize,
}

impl Shifts<'_> {
    #[inline(always)]
    fn q(&self, j: isize) -> i64 {
        self.v[(j - self.j0) as usize]
    }
}

/// Scratch of [`blur_u8`]; grows only (allocation when the frame size or the streak grows).
#[derive(Default)]
pub struct Scratch {
    // allocation: per frame size: the source rows (mostly vertical streaks; mostly horizontal
    // ones read the frame's columns through `Strips` and write their output lines straight into
    // them, see `flush_cols`)
    src: Vec<u8>,
    // allocation: per frame size, streak and thread count: mostly horizontal streaks: each band's
    // side lines (transposed copies of the columns of the other bands and the mirrored edges it
    // reads), then the frame's last rows (see `ColSrc`)
    side: Vec<u8>,
    // allocation: per frame size, streak and thread count: one slot per band
    slots: Vec<Slot>,
    // allocation: per frame size and streak: the cross-filter tap of every line, and the
    // (streak, line count) they are for
    taps: Vec<i32>,
    taps_for: Option<(StreakPlan, usize)>,
    // per band (mostly horizontal streaks): the column ranges of its side lines and their offset
    // in `side`
    sides: Vec<(Span, Span, usize)>,
}

/// A range of columns `[start, end)`.
type Span = (usize, usize);

/// Line access: `nl` pixels of `ch` samples per line, lines `stride` bytes apart.
#[derive(Clone, Copy)]
struct Lines<'a> {
    data: &'a [u8],
    stride: usize,
    count: usize,
    nl: usize,
    ch: usize,
}

impl<'a> Lines<'a> {
    fn line(&self, j: isize) -> &'a [u8] {
        let j = mirror(j, self.count);
        &self.data[j * self.stride..j * self.stride + self.nl * self.ch]
    }
}

/// Mostly horizontal streaks: the source lines (image columns) of one band, read from the frame
/// itself while the bands write their output lines into it (no transposed copy of the frame).
/// A line of the band's own columns `[i0, i0 + rows)` is read from the frame (8 columns at a
/// time, see [`Strips`]) before the band writes its column in the current block of positions;
/// every other line (the neighbour bands' columns and the mirrored lines beyond the frame edges,
/// which other bands or this one overwrite at any time) from `side`, copies taken before any
/// band writes; the frame's last `e` rows from `bottom`, a copy as well (the lines' mirrored
/// tails read back up to `n + 5` rows from the bottom edge, rows a block may already have
/// written).
#[derive(Clone, Copy)]
struct ColSrc<'a> {
    cols: Cols,
    ch: usize,
    i0: usize,
    rows: usize,
    // the columns [l0, l1) then [r0, r1), transposed: `rows * ch` (`Cols::rows`) bytes each
    side: &'a [u8],
    l: (usize, usize),
    r: (usize, usize),
    // rows [cols.rows - e, cols.rows) of the frame, `cols.cols * ch` bytes each
    bottom: &'a [u8],
    e: usize,
}

/// Where [`band`] reads its source lines.
#[derive(Clone, Copy)]
enum Src<'a> {
    /// A copy of the frame's rows (mostly vertical streaks).
    Rows(Lines<'a>),
    /// The frame's columns (mostly horizontal streaks).
    Cols(ColSrc<'a>),
}

impl Src<'_> {
    /// Pixels per line and samples per pixel.
    fn dims(&self) -> (usize, usize) {
        match self {
            Src::Rows(l) => (l.nl, l.ch),
            Src::Cols(c) => (c.cols.rows, c.ch),
        }
    }
}

/// Rows of a group's carry (see [`Strips`]): at least the spread of the 8 lines' whole shifts
/// (at most 8) plus 4.
const CARRY: usize = 16;

/// The band's own source lines of the current block, 8 columns (a group, lines `i0 + 8 g ..`) at
/// a time, transposed from the frame into a small cache when a line of the group is first read
/// in the block: over the rows the block's positions read (`[c0 - 1 + s, c1 + 3 + s)` for
/// shifts `s`, mirrored). Within a block a line is read only before its column is written (the
/// window runs ahead of the output line) and once the window has passed it never again, so the
/// cache holds the window's groups. The rows a block reads that earlier blocks have already
/// written (output line `j` writes rows `[c0 + ceil(shift), c1 + ceil(shift))`, the next block
/// reads from `c1 - 1 + floor(shift)`: at most two rows, and the mirror of those at the top
/// edge) come from the group's carry, the rows `[c1 - 1 + smin, c1 + 3 + smax)` saved from the
/// group's load in the block before.
#[derive(Default)]
struct Strips {
    // allocation: per frame size and streak: `slots` groups of 8 lines of the frame's height
    buf: Vec<u8>,
    // per cache slot: the (group, block) it holds
    tag: Vec<(usize, usize)>,
    // allocation: per frame size and thread count: per group, 8 lines of CARRY pixels
    carry: Vec<u8>,
    // per group: 1 + the block of its last load (0: none this frame)
    carry_b: Vec<usize>,
    slots: usize,
}

impl Strips {
    /// Sizes the cache for a band of `rows` lines of `ls` bytes and a streak of `n` full taps;
    /// forgets every load (a new frame).
    fn reset(&mut self, n: usize, rows: usize, ls: usize, ch: usize) {
        // The window spans 2n + 5 lines: a group is evicted only once all its lines are behind
        // it (`line` asserts that no group is loaded twice in a block).
        self.slots = (2 * n + 12) / 8 + 2;
        if self.buf.len() < self.slots * 8 * ls {
            self.buf.resize(self.slots * 8 * ls, 0);
        }
        self.tag.clear();
        self.tag.resize(self.slots, (usize::MAX, 0));
        let groups = rows.div_ceil(8);
        if self.carry.len() < groups * 8 * CARRY * ch {
            self.carry.resize(groups * 8 * CARRY * ch, 0);
        }
        self.carry_b.clear();
        self.carry_b.resize(groups, 0);
    }

    /// Source line `j` for block `bi` (positions `[c0, c1)`).
    #[allow(clippy::too_many_arguments)]
    fn line<'s, 'a: 's>(
        &'s mut self,
        lv: u8,
        sh: Shifts,
        src: &Src<'a>,
        j: isize,
        bi: usize,
        c0: isize,
        c1: isize,
    ) -> &'s [u8] {
        let cs = match src {
            Src::Rows(l) => return l.line(j),
            Src::Cols(cs) => cs,
        };
        let (h, ch, w) = (cs.cols.rows, cs.ch, cs.cols.cols);
        let ls = h * ch;
        if j < cs.i0 as isize || j >= (cs.i0 + cs.rows) as isize {
            let c = mirror(j, w);
            let t = if (cs.l.0..cs.l.1).contains(&c) {
                c - cs.l.0
            } else {
                assert!((cs.r.0..cs.r.1).contains(&c), "side line {j} (column {c}) not copied");
                cs.l.1 - cs.l.0 + c - cs.r.0
            };
            return &cs.side[t * ls..(t + 1) * ls];
        }
        let jj = j as usize - cs.i0;
        let g = jj / 8;
        let slot = g % self.slots;
        if self.tag[slot] != (g, bi) {
            assert!(self.carry_b[g] != bi + 1, "group {g} loaded twice in block {bi}");
            let carry_valid = bi > 0 && self.carry_b[g] == bi;
            let strip = &mut self.buf[slot * 8 * ls..(slot + 1) * 8 * ls];
            let carry = &mut self.carry[g * 8 * CARRY * ch..(g + 1) * 8 * CARRY * ch];
            load_group(lv, sh, cs, g, c0, c1, strip, carry, carry_valid);
            self.tag[slot] = (g, bi);
            self.carry_b[g] = bi + 1;
        }
        let at = (slot * 8 + jj % 8) * ls;
        &self.buf[at..at + ls]
    }
}

/// Rows ahead of the 8 being transposed whose bytes [`load_group`] asks the cache for (rgb8 40 px
/// at 30 deg: `t8x8_px` 9.3 -> 4.9 % of the bench's samples, 16 and 32 rows alike).
#[cfg(target_arch = "x86_64")]
const LOAD_AHEAD: usize = 32;

/// Loads group `g` of the band's own lines for the block of positions `[c0, c1)` into `strip`
/// (line `t` at `t ls`, pixel `x` at `x ch`, the rows the block reads; see [`Strips`]), the rows
/// earlier blocks wrote from `carry` (when `carry_valid`: saved by this group's load in the block
/// before), then saves the carry for the next block.
#[allow(clippy::too_many_arguments)]
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_variables, unused_mut))]
fn load_group(
    lv: u8,
    sh: Shifts,
    cs: &ColSrc,
    g: usize,
    c0: isize,
    c1: isize,
    strip: &mut [u8],
    carry: &mut [u8],
    carry_valid: bool,
) {
    let (h, ch, w, stride) = (cs.cols.rows, cs.ch, cs.cols.cols, cs.cols.stride);
    let ls = h * ch;
    let j0 = cs.i0 + 8 * g;
    let nc = 8.min(cs.i0 + cs.rows - j0);
    let s = |j: usize| (sh.q(j as isize) >> 6) as isize;
    let (smin, smax) = (j0..j0 + nc).fold((isize::MAX, isize::MIN), |(a, b), j| (a.min(s(j)), b.max(s(j))));
    assert!(smax - smin + 4 <= CARRY as isize);
    // Virtual rows [lo, hi) (before mirroring), the rows [amin, amax) that holds.
    let hh = h as isize;
    let (lo, hi) = (c0 - 1 + smin, c1 + 3 + smax);
    let (amin, amax) = if lo <= -hh || hi >= 2 * hh {
        (0, hh)
    } else {
        let amin = if lo < 0 {
            0
        } else if hi > hh {
            lo.min(2 * hh - hi)
        } else {
            lo
        };
        let amax = if hi > hh {
            hh
        } else if lo < 0 {
            hi.max(-lo)
        } else {
            hi
        };
        (amin.clamp(0, hh), amax.clamp(0, hh))
    };
    let (amin, amax) = (amin as usize, amax as usize);
    assert!(j0 + nc <= w && cs.cols.len >= (h - 1) * stride + w * ch && cs.bottom.len() >= cs.e * w * ch);
    // Rows below h - e from the frame, the others from the copy of the last rows.
    let hb = h - cs.e;
    for (r0, r1, base, ss) in [
        (amin, amax.min(hb), cs.cols.ptr as *const u8, stride),
        (amin.max(hb), amax, cs.bottom.as_ptr().wrapping_sub(hb * w * ch), w * ch),
    ] {
        if r1 <= r0 {
            continue;
        }
        let mut r = r0;
        #[cfg(target_arch = "x86_64")]
        if nc == 8 && lv >= 1 && super::kit::has_avx2() {
            while r + 8 <= r1 {
                // The rows LOAD_AHEAD below first: each row is on another 4 KiB page (rows are
                // `stride` >= 4 KiB apart at 1920 px rgb8), which the hardware prefetchers do
                // not cross.
                for y in (r + LOAD_AHEAD).min(r1)..(r + LOAD_AHEAD + 8).min(r1) {
                    // The cache line of the row's last byte of the 8 columns (its first byte's
                    // line is the last byte's of the group before, loaded 8 lines earlier).
                    let p = base.wrapping_add(y * ss + (j0 + 8) * ch - 1);
                    // SAFETY: a prefetch hint (no effect on values) of a byte of row y < r1 of
                    // columns j0..j0 + 8 (inside the frame resp. the copy, asserted above).
                    unsafe { std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p.cast::<i8>()) };
                }
                // SAFETY: AVX2 present (checked); rows r..r + 8 < h of columns j0..j0 + 8 <= w:
                // inside the frame resp. the copy of its rows from hb (asserted above), and 8
                // strip lines of ls = h ch bytes from pixel r (the wide store's 32 bytes: to
                // pixel r + 10 < r1 <= h). The frame's columns j0.. are this
                // band's, which only this thread writes, and not meanwhile.
                unsafe {
                    let p = base.wrapping_add(r * ss + j0 * ch);
                    let d = strip.as_mut_ptr().add(r * ch);
                    match ch {
                        1 => simd::t8x8_px::<1>(p, ss, d, ls),
                        // The wide store's 8 bytes after the 8 pixels (rows r + 8 ..= r + 10)
                        // when rows below r1 that this loop or the pixel loop below writes
                        // later.
                        _ if r + 11 <= r1 => simd::t8x8_px_wide::<3>(p, ss, d, ls),
                        _ => simd::t8x8_px::<3>(p, ss, d, ls),
                    }
                }
                r += 8;
            }
            if r > r0 && r < r1 {
                // The last rows as a block ending at r1 (overlapping the one before: the same
                // bytes again; no wide store).
                // SAFETY: as above for rows r1 - 8 >= r0 ..r1.
                unsafe {
                    let p = base.wrapping_add((r1 - 8) * ss + j0 * ch);
                    let d = strip.as_mut_ptr().add((r1 - 8) * ch);
                    match ch {
                        1 => simd::t8x8_px::<1>(p, ss, d, ls),
                        _ => simd::t8x8_px::<3>(p, ss, d, ls),
                    }
                }
                r = r1;
            }
        }
        for y in r..r1 {
            for t in 0..nc {
                let d = &mut strip[t * ls + y * ch..t * ls + (y + 1) * ch];
                // SAFETY: pixel (y, j0 + t) inside the frame resp. the copy (asserted above);
                // `d` is in `strip`, which does not overlap either.
                unsafe { copy_px(base.wrapping_add(y * ss + (j0 + t) * ch), d.as_mut_ptr(), ch) };
            }
        }
    }
    let k = (smax - smin + 4) as usize;
    // Virtual rows from v0 inside the frame: one contiguous run per line.
    let inside = |v0: isize| v0 >= 0 && v0 + k as isize <= hh;
    for t in 0..nc {
        let (line, cy) = (&mut strip[t * ls..(t + 1) * ls], &mut carry[t * CARRY * ch..(t + 1) * CARRY * ch]);
        let v0 = c0 - 1 + smin;
        if carry_valid && inside(v0) {
            line[v0 as usize * ch..(v0 as usize + k) * ch].copy_from_slice(&cy[..k * ch]);
        } else if carry_valid {
            for (u, v) in (v0..).take(k).enumerate() {
                let a = mirror(v, h) * ch;
                line[a..a + ch].copy_from_slice(&cy[u * ch..(u + 1) * ch]);
            }
        }
        let v0 = c1 - 1 + smin;
        if inside(v0) {
            cy[..k * ch].copy_from_slice(&line[v0 as usize * ch..(v0 as usize + k) * ch]);
        } else {
            for (u, v) in (v0..).take(k).enumerate() {
                let a = mirror(v, h) * ch;
                cy[u * ch..(u + 1) * ch].copy_from_slice(&line[a..a + ch]);
            }
        }
    }
}

use super::kit::dispatch_levels as dispatch;

/// `a[t] = (p[t] (64 - f) + p[t + ch] f + 2^(5 - q)) >> (6 - q)` for `t < a.len()` (`q <= 6`:
/// the line interpolated at phase `f / 64`, times `2^q`, rounded half up).
#[inline(always)]
fn lerp_k(a: &mut [u16], p: &[u8], ch: usize, f: u8, q: u32) {
    let (w0, w1) = (64 - f as u16, f as u16);
    let (sh, half) = (6 - q, (1u16 << (6 - q)) >> 1);
    let p1 = &p[ch..ch + a.len()];
    let p0 = &p[..a.len()];
    for ((a, &x0), &x1) in a.iter_mut().zip(p0).zip(p1) {
        *a = (x0 as u16 * w0 + x1 as u16 * w1 + half) >> sh;
    }
}
dispatch!(lerp_d, lerp_k, (a: &mut [u16], p: &[u8], ch: usize, f: u8, q: u32));

/// [`lerp_k`]: on the AVX2 kernels (level `lv` = 1) whole vectors through [`simd::lerp256`] (one
/// `vpmaddubsw` per 16 values), the rest (and every level other than 1) through [`lerp_d`];
/// the same integers, so the same bytes.
#[inline]
fn lerp(lv: u8, a: &mut [u16], p: &[u8], ch: usize, f: u8, q: u32) {
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if lv == 1 && super::kit::has_avx2() {
        // SAFETY: AVX2 present (checked).
        done = unsafe { simd::lerp256(a, p, ch, f, q) };
    }
    lerp_d(lv, &mut a[done..], &p[done..], ch, f, q);
}

/// `r[t] += a[t]` (16-bit; the plan's `q` keeps every running sum below 2^16).
#[inline(always)]
fn add_k(r: &mut [u16], a: &[u16]) {
    for (r, &a) in r.iter_mut().zip(a) {
        *r = r.wrapping_add(a);
    }
}
dispatch!(add_d, add_k, (r: &mut [u16], a: &[u16]));

/// `(x e) >> 16` (the high half of the 16-bit product: one `vpmulhuw`).
#[inline(always)]
fn mulhi(x: u16, e: u16) -> u16 {
    ((x as u32 * e as u32) >> 16) as u16
}

/// One line step over the held lines `a0..a4` = `A(i - n - 2)`, `A(i - n - 1)`, `A(i - n)`,
/// `A(i + n + 1)`, `A(i + n + 2)`: `b = (r + mulhi(a1 + a3, e0) + mulhi(a0 + a4, e1) + 1) >> 1`
/// (line `i` with its end taps, halved and rounded: below 2^15; the sum is below 2^16 - 1), then `r += a3 - a2` (the running sum of line `i + 1`; 16-bit wrapping
/// arithmetic, exact as every true value is below 2^16).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn step_k(b: &mut [u16], r: &mut [u16], a0: &[u16], a1: &[u16], a2: &[u16], a3: &[u16], a4: &[u16], e0: u16, e1: u16) {
    let n = b.len();
    let (r, a0, a1, a2, a3, a4) = (&mut r[..n], &a0[..n], &a1[..n], &a2[..n], &a3[..n], &a4[..n]);
    for i in 0..n {
        b[i] = (r[i].wrapping_add(mulhi(a1[i] + a3[i], e0)).wrapping_add(mulhi(a0[i] + a4[i], e1)) + 1) >> 1;
        r[i] = r[i].wrapping_add(a3[i]).wrapping_sub(a2[i]);
    }
}
dispatch!(step_v, step_k, (b: &mut [u16], r: &mut [u16], a0: &[u16], a1: &[u16], a2: &[u16], a3: &[u16], a4: &[u16], e0: u16, e1: u16));

/// [`step_k`] in AVX-512 registers on AVX-512 CPUs (level `lv` >= 2, 32 positions at a time),
/// then in AVX2 registers (level >= 1, 16 at a time), the rest through [`step_v`]: written out
/// because LLVM widens the multiply-highs of this loop to 32-bit lanes (`vpmovzxwd`, seen in
/// [`step_v`]'s AVX-512 copy on the Zen 4); the same 16-bit operations, so the same bytes.
#[allow(clippy::too_many_arguments)]
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
fn step_d(
    lv: u8,
    b: &mut [u16],
    r: &mut [u16],
    a0: &[u16],
    a1: &[u16],
    a2: &[u16],
    a3: &[u16],
    a4: &[u16],
    e0: u16,
    e1: u16,
) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if lv >= 2 && super::kit::has_avx512() {
            // SAFETY: AVX-512 F/BW present (checked).
            done = unsafe { simd::step512(b, r, [a0, a1, a2, a3, a4], e0, e1) };
        }
        if lv >= 1 && super::kit::has_avx2() {
            let t = done;
            // SAFETY: AVX2 present (checked).
            done += unsafe {
                simd::step(&mut b[t..], &mut r[t..], [&a0[t..], &a1[t..], &a2[t..], &a3[t..], &a4[t..]], e0, e1)
            };
        }
    }
    let t = done;
    step_v(lv, &mut b[t..], &mut r[t..], &a0[t..], &a1[t..], &a2[t..], &a3[t..], &a4[t..], e0, e1);
}

/// Offset of the cross filter's result (its sharpening can undershoot by up to half the
/// largest `B`, 2^14).
const OFF: u16 = 1 << 14;

/// `u[t] = mulhi(b[t], 1024 (64 - g)) + mulhi(b[t + ch], 1024 g)` (the unshear; `b[t]` itself
/// when `g = 0`), then `v[t] = OFF + u[t + ch] + s (mulhi(u[t], |a|) + mulhi(u[t + 2 ch], |a|) -
/// mulhi(u[t + ch], 2 |a|))` (the cross filter `[a, 1 - 2a, a]`, `s` the sign of `a`, wrapping 16-bit
/// arithmetic: the true value is in 0..2^16) and `out[t] = v / D` rounded (see
/// [`StreakPlan::dm`]), clamped to 0..=255; in one pass (each `u` computed where it is used). `b`
/// starts one position before the output.
#[inline(always)]
fn unshear_k(out: &mut [u8], b: &[u16], ch: usize, g: u8, a: i32, dm: u16, ds: u32) {
    let n = out.len();
    let (b0, b1, b2, b3) = (&b[..n], &b[ch..ch + n], &b[2 * ch..2 * ch + n], &b[3 * ch..3 * ch + n]);
    let (aa, sm) = (a.unsigned_abs() as u16, if a < 0 { u16::MAX } else { 0 });
    let aa2 = aa << 1;
    let off = mulhi(OFF, dm);
    let cross = |ul: u16, uc: u16, ur: u16| -> u8 {
        let t = mulhi(ul, aa).wrapping_add(mulhi(ur, aa)).wrapping_sub(mulhi(uc, aa2));
        let v = OFF.wrapping_add(uc).wrapping_add((t ^ sm).wrapping_sub(sm));
        (((mulhi(v, dm).saturating_sub(off) >> (ds - 1)) + 1) >> 1).min(255) as u8
    };
    if g == 0 {
        for i in 0..n {
            out[i] = cross(b0[i], b1[i], b2[i]);
        }
    } else {
        let (w0, w1) = ((64 - g as u16) << 10, (g as u16) << 10);
        for i in 0..n {
            let ul = mulhi(b0[i], w0) + mulhi(b1[i], w1);
            let uc = mulhi(b1[i], w0) + mulhi(b2[i], w1);
            let ur = mulhi(b2[i], w0) + mulhi(b3[i], w1);
            out[i] = cross(ul, uc, ur);
        }
    }
}
/// [`unshear_k`] in AVX-512 registers (32 outputs at a time, level `lv` >= 2), then AVX2 (16 at a
/// time, level >= 1; written out because LLVM widens the sums of multiply-highs to 32 bits), the
/// rest scalar; the same 16-bit operations, so the same bytes. `u`: scratch of `b.len()` values
/// (the SIMD versions interpolate each `B` once, see [`simd::unshear`]).
#[allow(clippy::too_many_arguments)]
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
fn unshear_d(lv: u8, out: &mut [u8], b: &[u16], u: &mut [u16], ch: usize, g: u8, a: i32, dm: u16, ds: u32) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if lv >= 2 && super::kit::has_avx512() {
            // SAFETY: AVX-512 F/BW present (checked).
            done = unsafe { simd::unshear512(out, b, u, ch, g, a, dm, ds) };
        }
        if lv >= 1 && super::kit::has_avx2() {
            let t = done;
            // SAFETY: AVX2 present (checked).
            done += unsafe { simd::unshear(&mut out[t..], &b[t..], &mut u[t..], ch, g, a, dm, ds) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = lv;
    unshear_k(&mut out[done..], &b[done..], ch, g, a, dm, ds);
}

/// Output positions (pixels along a line) per column block of `ch`-sample pixels: the block's
/// running sums and its ring of the window's `2n + 5` lines (2 bytes per sample each: 207 KB
/// rgb8 at 100 px, 30 deg) stay in the L2 cache while it runs down the band, and the per-line overhead is spread over many positions (on the Zen 3
/// 384 rgb8 / 512 mono8 positions ran faster than 256; BENCHMARKS.md).
fn chunk(ch: usize) -> isize {
    if ch == 1 { 512 } else { 384 }
}

/// Lines ahead of the newest held line whose bytes [`prefetch`] asks the cache for: the block
/// walks down the lines, one new source line per output line, a stride the hardware
/// prefetchers miss.
const AHEAD: isize = 6;

/// Positions a block's valid range grows by at a time on its lead side (see [`band`]).
const GROUP: isize = 64;

/// Hints the cache to load the bytes of source line `j` that `A(j, k)`, `k` in `[k0, k1)`, reads
/// (no effect on the values).
#[inline]
fn prefetch(plan: &StreakPlan, src: Src, j: isize, k0: isize, k1: isize) {
    // Mostly horizontal streaks read the frame's columns 8 at a time (a stride the prefetchers
    // follow).
    let Src::Rows(src) = src else { return };
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let s = (plan.shift_q(j) >> 6) as isize;
        let line = src.line(j);
        let at = |k: isize| ((k + s).max(0) as usize * src.ch).min(line.len());
        for p in (at(k0)..at(k1 + 1)).step_by(64) {
            // SAFETY: a prefetch hint of an address inside `line` (p < line.len()).
            unsafe { _mm_prefetch::<_MM_HINT_T0>(line.as_ptr().add(p).cast::<i8>()) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (plan, src, j, k0, k1);
}

/// [`mirror`] without its division where `i` is within one line length of the line.
#[inline(always)]
fn mirror_near(i: isize, n: usize) -> usize {
    let ni = n as isize;
    if (0..ni).contains(&i) {
        i as usize
    } else if (-ni..0).contains(&i) {
        (-1 - i) as usize
    } else if (ni..2 * ni).contains(&i) {
        (2 * ni - 1 - i) as usize
    } else {
        mirror(i, n)
    }
}

/// `pad` = the pixels of `C` bytes of `line` (`nl` pixels) at `p0, p0 + 1, ..`, mirrored
/// ([`mirror_near`]): by runs, the pixels inside the line copied at once, those within one line
/// length beyond either edge one by one in reverse order, the rest pixel by pixel.
#[inline(always)]
fn pad_px<const C: usize>(pad: &mut [u8], line: &[u8], p0: isize, nl: usize) {
    let (cnt, ni) = (pad.len() / C, nl as isize);
    let mut t = 0;
    while t < cnt {
        let p = p0 + t as isize;
        // Pixels t..t + run of `pad` from source pixels [s0, s0 + run), reversed or not.
        let (run, s0, rev) = if (0..ni).contains(&p) {
            (((ni - p) as usize).min(cnt - t), p as usize, false)
        } else if (-ni..0).contains(&p) {
            // Pixels p.. mirror to -1 - p, -2 - p, ..: the run of sources ends at -p.
            let run = ((-p) as usize).min(cnt - t);
            (run, (-p) as usize - run, true)
        } else if (ni..2 * ni).contains(&p) {
            // Pixels p.. mirror to 2 nl - 1 - p, ..: the run of sources ends at 2 nl - p.
            let run = ((2 * ni - p) as usize).min(cnt - t);
            (run, (2 * ni - p) as usize - run, true)
        } else {
            (1, mirror_near(p, nl), false)
        };
        let (d, s) = (&mut pad[t * C..(t + run) * C], &line[s0 * C..(s0 + run) * C]);
        if rev {
            for (d, s) in d.chunks_exact_mut(C).zip(s.rchunks_exact(C)) {
                d.copy_from_slice(s);
            }
        } else {
            d.copy_from_slice(s);
        }
        t += run;
    }
}

/// Where [`band`] writes its output lines.
enum Dst<'a> {
    /// Line `row` of the band at `dst[row * stride..]` (a mostly vertical streak: image rows).
    Rows(&'a mut [u8], usize),
    /// A mostly horizontal streak: output line `i` is image column `i`, its pixel `x` image row
    /// `x`; lines go through the slot's tile, [`TILE`] lines at a time (see [`flush_cols`]).
    Cols(Cols),
}

/// The frame as columns: sample `c` of pixel `x` of column `i` at `ptr + x * stride + i * ch + c`
/// (`x < rows`, `i < cols`). Bands write disjoint columns.
#[derive(Clone, Copy)]
struct Cols {
    ptr: *mut u8,
    len: usize,
    stride: usize,
    rows: usize,
    cols: usize,
}

// SAFETY: `Cols` is a view of a frame that `blur_u8_at` borrows mutably for the whole parallel
// section; each band writes only the columns of its own lines, so no two threads write the same
// byte and nobody reads the frame meanwhile.
unsafe impl Send for Cols {}
// SAFETY: as for `Send`.
unsafe impl Sync for Cols {}

/// Values of room after a block's positions (`Slot::r`, `b`, each ring line) and after the tile:
/// the SIMD kernels' last vector (32 16-bit lanes on AVX-512).
const VPAD: usize = 32;

/// `n` rounded up to whole vectors of every SIMD level `lv` allows (a multiple of 32 values, so
/// that no scalar tail is left), on CPUs that run them (AVX2 at least; `n` itself otherwise: the
/// scalar kernels must not compute on values beyond, whose sums may overflow).
fn whole_vectors(lv: u8) -> impl Fn(usize) -> usize {
    #[cfg(target_arch = "x86_64")]
    let simd = lv >= 1 && super::kit::has_avx2();
    #[cfg(not(target_arch = "x86_64"))]
    let simd = {
        let _ = lv;
        false
    };
    move |n| if simd { n.div_ceil(VPAD) * VPAD } else { n }
}

/// Output lines held in a slot's tile before [`flush_cols`] transposes them into the frame.
const TILE: usize = 8;

/// Copies one pixel of `ch` (1 or 3) bytes (a fixed-size copy: no `memmove` call).
///
/// # Safety
/// `ch` bytes readable at `src`, writable at `dst`, not overlapping.
#[inline(always)]
unsafe fn copy_px(src: *const u8, dst: *mut u8, ch: usize) {
    // SAFETY: as documented.
    unsafe {
        match ch {
            1 => *dst = *src,
            3 => std::ptr::copy_nonoverlapping(src, dst, 3),
            _ => std::ptr::copy_nonoverlapping(src, dst, ch),
        }
    }
}

/// Writes the tile's `grp.len()` (<= [`TILE`]) consecutive output lines into frame columns:
/// tile row `t` holds line `grp[t].0` over positions `[grp[t].2, grp[t].3)` of the chunk starting
/// at `c0` (`tl` bytes a row, `ch` per position); position `o` of the line is its pixel `o - k`,
/// `k = grp[t].1`. With [`TILE`] lines and AVX2 (level `lv` >= 1), the pixels all of them hold
/// go 8 x 8 at a time through registers, the rest pixel by pixel (byte copies: the same bytes
/// either way).
#[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut, unused_variables))]
fn flush_cols(lv: u8, cols: Cols, ch: usize, tile: &[u8], tl: usize, c0: isize, grp: &[(usize, isize, isize, isize)]) {
    let Some(&(ifirst, ..)) = grp.first() else { return };
    let ilast = grp[grp.len() - 1].0;
    let (xlo, xhi) =
        grp.iter().fold((isize::MAX, isize::MIN), |(a, b), &(_, k, o0, o1)| (a.min(o0 - k), b.max(o1 - k)));
    assert!(ilast < cols.cols && xlo >= 0 && xhi as usize <= cols.rows && grp.len() <= TILE);
    assert!(cols.len >= (cols.rows - 1) * cols.stride + cols.cols * ch && cols.cols * ch <= cols.stride);
    // Pixels [xs, xv) of every line in registers.
    let (xs, xe) = grp.iter().fold((isize::MIN, isize::MAX), |(a, b), &(_, k, o0, o1)| (a.max(o0 - k), b.min(o1 - k)));
    #[cfg(target_arch = "x86_64")]
    let simd = lv >= 1 && grp.len() == TILE && xe - xs >= 8 && super::kit::has_avx2();
    #[cfg(not(target_arch = "x86_64"))]
    let simd = {
        let _ = lv;
        false
    };
    // All of [xs, xe) through registers (the last block overlaps the one before: the same bytes
    // written twice), when it holds a block.
    let xv = if simd { xe } else { xs };
    #[cfg(target_arch = "x86_64")]
    if simd {
        // Line t's pixel x at `tile[t * tl + (x + k - c0) ch..]`: pixels [xs, xe) are inside its
        // row of the tile (o0 - k <= xs, xe <= o1 - k, and [o0, o1) within [c0, c1)).
        assert!(
            grp.iter().all(|&(_, k, o0, o1)| o0 >= c0 && (o1 - c0) as usize * ch <= tl && o0 - k <= xs && xe <= o1 - k)
        );
        assert!(tile.len() >= TILE * tl);
        let at: [isize; TILE] = std::array::from_fn(|t| t as isize * tl as isize + (grp[t].1 - c0) * ch as isize);
        let last = xe - 8;
        for x in (xs..last).step_by(8).chain([last]) {
            // Pixels x..x + 8 within [xs, xe) of each line: inside its row of `tile` (asserted
            // above).
            let src: [*const u8; TILE] =
                std::array::from_fn(|t| tile.as_ptr().wrapping_offset(at[t] + x * ch as isize));
            // SAFETY: AVX2 present (checked with `simd`); each source row has its 8 pixels
            // inside `tile` (above); the 8 destination rows x..x + 8 < rows have columns
            // ifirst..ifirst + 8 <= cols inside the frame (asserted above), which only this band
            // writes (see `Cols`).
            unsafe {
                let d = cols.ptr.add(x as usize * cols.stride + ifirst * ch);
                match ch {
                    1 => simd::t8x8_rows::<1>(src, d, cols.stride),
                    _ => simd::t8x8_rows::<3>(src, d, cols.stride),
                }
            }
        }
    }
    for (t, &(i, k, o0, o1)) in grp.iter().enumerate() {
        // The line's pixels [o0 - k, o1 - k) outside [xs, xv) (xs <= xv).
        for x in (o0 - k..xs.min(o1 - k)).chain(xv.max(o0 - k)..o1 - k) {
            let at = t * tl + (x + k - c0) as usize * ch;
            let px = &tile[at..at + ch];
            // SAFETY: x < rows, i < cols (asserted above): inside the frame, in this band's
            // column (see `Cols`); `px` is in `tile`, which does not overlap the frame.
            unsafe { copy_px(px.as_ptr(), cols.ptr.add(x as usize * cols.stride + i * ch), ch) };
        }
    }
}

/// One band of output lines `i0..i0 + rows` (written to `dst`: image rows, or image columns
/// through the slot's tile), block by block of output positions `k` (line `i` writes pixel
/// `x = k - klo(i)`).
#[allow(clippy::too_many_arguments)]
fn band(lv: u8, plan: &StreakPlan, src: Src, i0: usize, rows: usize, mut dst: Dst, taps: &[i32], slot: &mut Slot) {
    let (nl, ch) = src.dims();
    let n = plan.n as isize;
    // Line i's output pixel x reads B at k = x + klo(i) and k + 1 (phase g); the cross filter
    // needs one position more on each side.
    // The shifts of lines i0 - n - 2 ..= i0 + rows + n + 2 (the window's lines).
    let mut shifts = std::mem::take(&mut slot.shifts);
    let jlo = i0 as isize - n - 2;
    shifts.clear();
    shifts.extend((jlo..i0 as isize + rows as isize + n + 3).map(|j| plan.shift_q(j)));
    let sh = Shifts { v: &shifts, j0: jlo };
    let klo = |i: usize| -> (isize, u8) {
        let q = -sh.q(i as isize);
        ((q >> 6) as isize, (q & 63) as u8)
    };
    let chunk = chunk(ch);
    // The block's positions, then room for the last whole vector of `step_d` and `unshear_d`
    // (see `whole`).
    let len = (chunk as usize + 3) * ch + VPAD;
    // The running sums, `B` and every ring line start on a 64-byte line (from `ro`, `bo`, `go`
    // values into their buffers; ring lines `lp` values apart), so that the step's vectors, which
    // start at a multiple of VPAD values with SIMD (see `y0`), do not straddle cache lines.
    let lp = len.div_ceil(VPAD) * VPAD;
    for v in [&mut slot.r, &mut slot.b, &mut slot.u] {
        if v.len() < len + VPAD {
            v.resize(len + VPAD, 0);
        }
    }
    // The ring's slots: line j at `(j mod nr) lp`.
    let nr = 2 * n + 5;
    if slot.ring.len() < nr as usize * lp + VPAD {
        slot.ring.resize(nr as usize * lp + VPAD, 0);
    }
    // Values from the buffer's start to its first 64-byte boundary (u16 buffers: even addresses).
    let line_start = |v: &[u16]| (v.as_ptr() as usize).wrapping_neg() % 64 / 2;
    let (ro, bo, go, uo) = (line_start(&slot.r), line_start(&slot.b), line_start(&slot.ring), line_start(&slot.u));
    // The tile from a 64-byte line too (the unshear's stores of a block's inner lines start
    // there).
    let to = (slot.tile.as_ptr() as usize).wrapping_neg() % 64;
    let at = |j: isize| go + j.rem_euclid(nr) as usize * lp;
    let tl = chunk as usize * ch;
    if matches!(dst, Dst::Cols(_)) && slot.tile.len() < TILE * tl + VPAD + 64 {
        slot.tile.resize(TILE * tl + VPAD + 64, 0);
    }
    let whole = whole_vectors(lv);
    if let Src::Cols(_) = src {
        slot.strips.reset(plan.n, rows, nl * ch, ch);
    }
    // A(j, k) for k in [k0, k1) into `a` (index (k - base) ch).
    let fill = |a: &mut [u16], pad: &mut Vec<u8>, base: isize, j: isize, k0: isize, k1: isize, line: &[u8]| {
        let q = sh.q(j);
        let (s, f) = ((q >> 6) as isize, (q & 63) as u8);
        let x = |k: isize| (k - base) as usize * ch;
        // Positions whose two pixels are inside the line read it directly; the others go
        // through a mirrored copy.
        let (i0, i1) = ((-s).clamp(k0, k1), (nl as isize - 1 - s).clamp(k0, k1).max((-s).clamp(k0, k1)));
        if i1 > i0 {
            let p = ((i0 + s) as usize) * ch;
            lerp(lv, &mut a[x(i0)..x(i1)], &line[p..p + ((i1 - i0) as usize + 1) * ch], ch, f, plan.q);
        }
        for (e0, e1) in [(k0, i0), (i1, k1)] {
            if e1 > e0 {
                let cnt = (e1 - e0 + 1) as usize;
                if pad.len() < cnt * ch {
                    pad.resize(cnt * ch, 0);
                }
                match ch {
                    1 => pad_px::<1>(&mut pad[..cnt], line, e0 + s, nl),
                    _ => pad_px::<3>(&mut pad[..cnt * 3], line, e0 + s, nl),
                }
                lerp(lv, &mut a[x(e0)..x(e1)], &pad[..cnt * ch], ch, f, plan.q);
            }
        }
    };
    // The held lines the step reads: j = i + off[t].
    let off = [-n - 2, -n - 1, -n, n + 1, n + 2];
    let (ka, kb) = (klo(i0).0, klo(i0 + rows - 1).0);
    let mut c0 = ka.min(kb);
    let mut bi = 0;
    while c0 < ka.max(kb) + nl as isize {
        let c1 = c0 + chunk;
        // State over k in [c0 - 1, c1 + 2), local index (k - base) ch.
        let base = c0 - 1;
        // Positions [v0, v1) hold valid running sums and lines (`None`: not started). The
        // positions a line needs, [o0 - 1, o1 + 2), move monotonically with the line (by the
        // sign of -m): the lead side is extended GROUP positions at a time, the trailing side is
        // dropped (never needed again), so the block computes only about the positions its
        // lines output (the sheared parallelogram, not its bounding rectangle).
        let mut valid: Option<(isize, isize)> = None;
        // The lines in the tile (mostly horizontal streaks): (i, k, o0, o1).
        let mut grp = [(0usize, 0isize, 0isize, 0isize); TILE];
        let mut glen = 0;
        for (row, i) in (i0..i0 + rows).enumerate() {
            let (k, g) = klo(i);
            let (o0, o1) = (c0.max(k), c1.min(k + nl as isize));
            if o0 >= o1 {
                if valid.is_some() {
                    break;
                }
                continue;
            }
            let (n0, n1) = (o0 - 1, o1 + 2);
            let Slot { r, b, u, pad, tile, ring, strips, .. } = &mut *slot;
            let (r, b, u) = (&mut r[ro..ro + len], &mut b[bo..bo + len], &mut u[uo..uo + len]);
            // Running sums and the window's lines at line i over [g0, g1).
            let mut init = |g0: isize, g1: isize| {
                let (x0, x1) = ((g0 - base) as usize * ch, (g1 - base) as usize * ch);
                r[x0..x1].fill(0);
                for d in -n - 2..=n + 2 {
                    let j = i as isize + d;
                    let line = &mut ring[at(j)..at(j) + len];
                    fill(line, pad, base, j, g0, g1, strips.line(lv, sh, &src, j, bi, c0, c1));
                    if d.abs() <= n {
                        add_d(lv, &mut r[x0..x1], &line[x0..x1]);
                    }
                }
            };
            let (mut v0, mut v1) = match valid {
                None => {
                    let (g0, g1) = if plan.m > 0.0 {
                        ((n0 - GROUP).max(base), n1)
                    } else if plan.m < 0.0 {
                        (n0, (n1 + GROUP).min(c1 + 2))
                    } else {
                        (n0, n1)
                    };
                    init(g0, g1);
                    (g0, g1)
                }
                Some(v) => v,
            };
            if n0 < v0 {
                let g0 = (v0 - GROUP).min(n0).max(base);
                init(g0, v0);
                v0 = g0;
            }
            if n1 > v1 {
                let g1 = (v1 + GROUP).max(n1).min(c1 + 2);
                init(v1, g1);
                v1 = g1;
            }
            if plan.m > 0.0 {
                v1 = v1.min(n1);
            } else if plan.m < 0.0 {
                v0 = v0.max(n0);
            }
            valid = Some((v0, v1));
            let (y0, y1) = ((v0 - base) as usize * ch, (v1 - base) as usize * ch);
            // B over [v0, v1) (used over [o0 - 1, o1 + 2)) and the running sums of line i + 1,
            // then unshear and cross filter into pixels o0 - k.. o1 - k.
            // The step over whole vectors, up to VPAD values beyond y1 (values nobody reads: B
            // beyond v1, and running sums beyond v1, which `init` restarts before they are used).
            // With SIMD the step starts at the multiple of VPAD values at or below y0 (B and
            // running sums of positions below v0: values nobody reads, see above).
            let y0 = y0 / whole(1) * whole(1);
            let y1 = y0 + whole(y1 - y0);
            // Ring slots of lines i - n - 2, .., i - n, i + n + 1, i + n + 2: s0, s0 + 1, s0 + 2,
            // s0 - 2, s0 - 1 modulo 2n + 5 (one division).
            let s0 = (i as isize + off[0]).rem_euclid(nr);
            let [a0, a1, a2, a3, a4] = [0, 1, 2, -2, -1].map(|d| {
                let sl = s0 + d;
                let sl = if sl >= nr {
                    sl - nr
                } else if sl < 0 {
                    sl + nr
                } else {
                    sl
                };
                let o = go + sl as usize * lp;
                &ring[o + y0..o + y1]
            });
            step_d(lv, &mut b[y0..y1], &mut r[y0..y1], a0, a1, a2, a3, a4, plan.eq[0], plan.eq[1]);
            let (x0, x1) = ((n0 - base) as usize * ch, (n1 - base) as usize * ch);
            let bx = &b[x0..x1];
            match &mut dst {
                Dst::Rows(d, stride) => {
                    let p0 = row * *stride + (o0 - k) as usize * ch;
                    unshear_d(lv, &mut d[p0..p0 + (o1 - o0) as usize * ch], bx, u, ch, g, taps[row], plan.dm, plan.ds);
                }
                Dst::Cols(cols) => {
                    // Whole vectors, up to VPAD bytes beyond the line's pixels into the tile's
                    // next row (written after this one) or its padding: bytes `flush_cols` does
                    // not read.
                    let p0 = to + glen * tl + (o0 - c0) as usize * ch;
                    let no = whole((o1 - o0) as usize * ch);
                    let bx = &b[x0..x0 + no + 3 * ch];
                    unshear_d(lv, &mut tile[p0..p0 + no], bx, u, ch, g, taps[row], plan.dm, plan.ds);
                    grp[glen] = (i, k, o0, o1);
                    glen += 1;
                    if glen == TILE {
                        flush_cols(lv, *cols, ch, &tile[to..], tl, c0, &grp);
                        glen = 0;
                    }
                }
            }
            if row + 1 == rows {
                break;
            }
            let Slot { ring, pad, strips, .. } = &mut *slot;
            // Advance to line i + 1: A(i + 1 + n + 2) enters the window in the slot of A(i - n - 2),
            // which leaves it (the other lines are valid over [v0, v1): every line entered over
            // the range then valid, `init` extends all of them, and the range only grows there).
            let j = i as isize + 1 + n + 2;
            fill(&mut ring[at(j)..at(j) + len], pad, base, j, v0, v1, strips.line(lv, sh, &src, j, bi, c0, c1));
            prefetch(plan, src, i as isize + 1 + n + 2 + AHEAD, v0, v1);
        }
        if let Dst::Cols(cols) = &dst {
            flush_cols(lv, *cols, ch, &slot.tile[to..], tl, c0, &grp[..glen]);
        }
        c0 = c1;
        bi += 1;
    }
    slot.shifts = shifts;
}

/// Pixel transpose: `dst[x * dstride + y * ch + c] = src[y * sstride + x * ch + c]` for
/// `x < w`, `y < h`, in blocks of 64 x 64 pixels (a block's rows stay in cache), 8 x 8 pixels at
/// a time in AVX2 registers (level `lv` >= 1), the block edges pixel by pixel.
#[allow(clippy::too_many_arguments)]
fn transpose(lv: u8, src: &[u8], sstride: usize, w: usize, h: usize, ch: usize, dst: &mut [u8], dstride: usize) {
    match ch {
        1 => transpose_px::<1>(lv, src, sstride, w, h, dst, dstride),
        3 => transpose_px::<3>(lv, src, sstride, w, h, dst, dstride),
        _ => unreachable!("8-bit frames have 1 or 3 channels"),
    }
}

#[allow(clippy::too_many_arguments)]
fn transpose_px<const C: usize>(
    lv: u8,
    src: &[u8],
    sstride: usize,
    w: usize,
    h: usize,
    dst: &mut [u8],
    dstride: usize,
) {
    const B: usize = 64;
    let used = dst.len().min(dstride * w);
    #[cfg(target_arch = "x86_64")]
    let simd = lv >= 1 && super::kit::has_avx2();
    #[cfg(not(target_arch = "x86_64"))]
    let simd = {
        let _ = lv;
        false
    };
    dst[..used].par_chunks_mut(dstride * B).enumerate().for_each(|(bx, dband)| {
        let x0 = bx * B;
        let xs = B.min(w - x0);
        for y0 in (0..h).step_by(B) {
            let ys = B.min(h - y0);
            let sblock = &src[y0 * sstride + x0 * C..];
            // The next block's source rows (a stride the hardware prefetchers miss).
            #[cfg(target_arch = "x86_64")]
            for y in y0 + B..(y0 + 2 * B).min(h) {
                use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
                let row = &src[y * sstride + x0 * C..y * sstride + (x0 + xs) * C];
                for p in (0..row.len()).step_by(64).chain([row.len() - 1]) {
                    // SAFETY: a prefetch hint of an address inside `row` (no effect on values).
                    unsafe { _mm_prefetch::<_MM_HINT_T0>(row.as_ptr().add(p).cast::<i8>()) };
                }
            }
            // Pixels (dx, dy) of the block done in registers: dx < xv, dy < yv.
            let (xv, yv) = if simd { (xs / 8 * 8, ys / 8 * 8) } else { (0, 0) };
            #[cfg(target_arch = "x86_64")]
            for dx in (0..xv).step_by(8) {
                for dy in (0..yv).step_by(8) {
                    let s = &sblock[dy * sstride + dx * C..];
                    let d = &mut dband[dx * dstride + (y0 + dy) * C..];
                    assert!(s.len() >= 7 * sstride + 8 * C && d.len() >= 7 * dstride + 8 * C);
                    // SAFETY: AVX2 present (checked with `simd`); 8 rows of 8 pixels readable
                    // at `s + r * sstride` and writable at `d + r * dstride` (asserted).
                    unsafe { simd::t8x8_px::<C>(s.as_ptr(), sstride, d.as_mut_ptr(), dstride) };
                }
            }
            for dx in 0..xs {
                let drow = &mut dband[dx * dstride + y0 * C..dx * dstride + (y0 + ys) * C];
                let from = if dx < xv { yv } else { 0 };
                for (dy, d) in drow.chunks_exact_mut(C).enumerate().skip(from) {
                    let o = dy * sstride + dx * C;
                    let px: &[u8; C] = sblock[o..o + C].try_into().expect("C bytes");
                    d.copy_from_slice(px);
                }
            }
        }
    });
}

#[cfg(target_arch = "x86_64")]
mod simd {
    use super::super::kit::{mulhi_epu16_256 as mulhi, mulhi_epu16_512 as mulhi512};
    use std::arch::x86_64::*;

    /// [`super::lerp_k`] over the first `a.len() / 32 * 32` values (returned), 32 at a time: the
    /// two pixels of each value interleaved (`vpunpck*bw`) and multiplied with the weight pair
    /// `(64 - f, f)` by one `vpmaddubsw` per 16 values (both weights fit a signed byte; the sum,
    /// at most 255 * 64, does not saturate), rounded and shifted as `lerp_k` does.
    ///
    /// # Safety
    /// AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn lerp256(a: &mut [u16], p: &[u8], ch: usize, f: u8, q: u32) -> usize {
        let n = a.len() / 32 * 32;
        assert!(p.len() >= n + ch && f < 64 && q <= 6);
        let w = _mm256_set1_epi16((((f as u16) << 8) | (64 - f as u16)) as i16);
        let half = _mm256_set1_epi16(((1u16 << (6 - q)) >> 1) as i16);
        let cnt = _mm_cvtsi32_si128(6 - q as i32);
        for i in (0..n).step_by(32) {
            // SAFETY: AVX2 (the caller's contract); loads of 32 bytes of `p` below `n + ch <=
            // p.len()`, stores of 32 values of `a` below n (asserted).
            unsafe {
                let x0 = _mm256_loadu_si256(p.as_ptr().add(i).cast::<__m256i>());
                let x1 = _mm256_loadu_si256(p.as_ptr().add(i + ch).cast::<__m256i>());
                // Values 0..8 and 16..24 (lo), 8..16 and 24..32 (hi), each in its lane.
                let lo = _mm256_maddubs_epi16(_mm256_unpacklo_epi8(x0, x1), w);
                let hi = _mm256_maddubs_epi16(_mm256_unpackhi_epi8(x0, x1), w);
                let lo = _mm256_srl_epi16(_mm256_add_epi16(lo, half), cnt);
                let hi = _mm256_srl_epi16(_mm256_add_epi16(hi, half), cnt);
                _mm256_storeu_si256(a.as_mut_ptr().add(i).cast::<__m256i>(), _mm256_permute2x128_si256(lo, hi, 0x20));
                _mm256_storeu_si256(
                    a.as_mut_ptr().add(i + 16).cast::<__m256i>(),
                    _mm256_permute2x128_si256(lo, hi, 0x31),
                );
            }
        }
        n
    }

    /// [`super::step_k`] over the first `b.len() / 16 * 16` positions (returned), 16 at a time.
    ///
    /// # Safety
    /// AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn step(b: &mut [u16], r: &mut [u16], a: [&[u16]; 5], e0: u16, e1: u16) -> usize {
        let n = b.len() / 16 * 16;
        assert!(r.len() >= n && a.iter().all(|v| v.len() >= n));
        let (e0v, e1v, one) = (_mm256_set1_epi16(e0 as i16), _mm256_set1_epi16(e1 as i16), _mm256_set1_epi16(1));
        for i in (0..n).step_by(16) {
            // SAFETY: AVX2 (the caller's contract); every load and store covers 16 values
            // below n of its slice (asserted).
            unsafe {
                let l = |v: &[u16]| _mm256_loadu_si256(v.as_ptr().add(i).cast::<__m256i>());
                let rv = l(r);
                let (x0, x1, x2, x3, x4) = (l(a[0]), l(a[1]), l(a[2]), l(a[3]), l(a[4]));
                let t = _mm256_add_epi16(
                    _mm256_add_epi16(rv, mulhi(_mm256_add_epi16(x1, x3), e0v)),
                    mulhi(_mm256_add_epi16(x0, x4), e1v),
                );
                let bv = _mm256_srli_epi16(_mm256_add_epi16(t, one), 1);
                _mm256_storeu_si256(b.as_mut_ptr().add(i).cast::<__m256i>(), bv);
                let rn = _mm256_sub_epi16(_mm256_add_epi16(rv, x3), x2);
                _mm256_storeu_si256(r.as_mut_ptr().add(i).cast::<__m256i>(), rn);
            }
        }
        n
    }

    /// [`super::step_k`] over the first `b.len() / 32 * 32` positions (returned), 32 at a time.
    ///
    /// # Safety
    /// AVX-512 F/BW.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub unsafe fn step512(b: &mut [u16], r: &mut [u16], a: [&[u16]; 5], e0: u16, e1: u16) -> usize {
        let n = b.len() / 32 * 32;
        assert!(r.len() >= n && a.iter().all(|v| v.len() >= n));
        let (e0v, e1v, one) = (_mm512_set1_epi16(e0 as i16), _mm512_set1_epi16(e1 as i16), _mm512_set1_epi16(1));
        for i in (0..n).step_by(32) {
            // SAFETY: AVX-512 F/BW (the caller's contract); every load and store covers 32
            // values below n of its slice (asserted).
            unsafe {
                let l = |v: &[u16]| _mm512_loadu_si512(v.as_ptr().add(i).cast::<__m512i>());
                let rv = l(r);
                let (x0, x1, x2, x3, x4) = (l(a[0]), l(a[1]), l(a[2]), l(a[3]), l(a[4]));
                let t = _mm512_add_epi16(
                    _mm512_add_epi16(rv, mulhi512(_mm512_add_epi16(x1, x3), e0v)),
                    mulhi512(_mm512_add_epi16(x0, x4), e1v),
                );
                let bv = _mm512_srli_epi16::<1>(_mm512_add_epi16(t, one));
                _mm512_storeu_si512(b.as_mut_ptr().add(i).cast::<__m512i>(), bv);
                let rn = _mm512_sub_epi16(_mm512_add_epi16(rv, x3), x2);
                _mm512_storeu_si512(r.as_mut_ptr().add(i).cast::<__m512i>(), rn);
            }
        }
        n
    }

    /// [`super::unshear_k`] over the first `out.len() / 16 * 16` outputs (returned), 16 at a time:
    /// first `u[t] = mulhi(b[t], w0) + mulhi(b[t + ch], w1)` for `t < n + 2 ch` (the unshear, each
    /// value once: the scalar loop's `ul`, `uc`, `ur` are `u[t]`, `u[t + ch]`, `u[t + 2 ch]`;
    /// the multiply-highs are the loop's bottleneck), then the cross filter and the division
    /// (`b` itself when `g = 0`).
    ///
    /// # Safety
    /// AVX2.
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn unshear(
        out: &mut [u8],
        b: &[u16],
        u: &mut [u16],
        ch: usize,
        g: u8,
        a: i32,
        dm: u16,
        ds: u32,
    ) -> usize {
        let n = out.len() / 16 * 16;
        assert!(b.len() >= n + 3 * ch && u.len() >= n + 2 * ch && ds >= 1);
        if n == 0 {
            return 0;
        }
        let set = |v: u16| _mm256_set1_epi16(v as i16);
        let (w0, w1) = (set((64 - g as u16) << 10), set((g as u16) << 10));
        let m = n + 2 * ch;
        if g != 0 {
            // Whole vectors, the last one ending at m (n >= 16: it overlaps the one before and
            // writes the same values again).
            for i in (0..m).step_by(16).map(|i| i.min(m - 16)) {
                // SAFETY: AVX2 (the caller's contract); loads of 16 values of `b` below
                // `m + ch <= b.len()`, a store of 16 values of `u` below `m <= u.len()`
                // (asserted).
                unsafe {
                    let l = |o: usize| _mm256_loadu_si256(b.as_ptr().add(i + o).cast::<__m256i>());
                    let v = _mm256_add_epi16(mulhi(l(0), w0), mulhi(l(ch), w1));
                    _mm256_storeu_si256(u.as_mut_ptr().add(i).cast::<__m256i>(), v);
                }
            }
        }
        let src: &[u16] = if g == 0 { b } else { u };
        let aa = a.unsigned_abs() as u16;
        let (aa1, aa2, sm) = (set(aa), set(aa << 1), set(if a < 0 { u16::MAX } else { 0 }));
        let (off, offv, dmv, zero) = (set(super::OFF), set(super::mulhi(super::OFF, dm)), set(dm), set(0));
        let cnt = _mm_cvtsi32_si128(ds as i32 - 1);
        // The 16 results from position i before the saturating pack to bytes: `((x >> (ds - 1)) + 1)
        // >> 1` (16-bit wrapping) is `avg(x >> (ds - 1), 0)` except that `avg` gives 2^15 where the
        // sum wraps to 0; both are at most 2^15 and pack to the same byte (2^15 is negative as a
        // signed 16-bit value: 0; 256..2^15 - 1: 255, as the scalar `min(255)`).
        let q = |i: usize| {
            // SAFETY: AVX2 (the caller's contract); every load reads 16 values of `src` below
            // `i + 16 + 2 ch <= m` (`b` or `u`, both at least m long) for `i + 16 <= n`.
            unsafe {
                let l = |o: usize| _mm256_loadu_si256(src.as_ptr().add(i + o).cast::<__m256i>());
                let (ul, uc, ur) = (l(0), l(ch), l(2 * ch));
                let t = _mm256_sub_epi16(_mm256_add_epi16(mulhi(ul, aa1), mulhi(ur, aa1)), mulhi(uc, aa2));
                let v = _mm256_add_epi16(_mm256_add_epi16(off, uc), _mm256_sub_epi16(_mm256_xor_si256(t, sm), sm));
                let q = _mm256_subs_epu16(mulhi(v, dmv), offv);
                _mm256_avg_epu16(_mm256_srl_epi16(q, cnt), zero)
            }
        };
        // 32 outputs at a time (one pack and one 32-byte store), then 16.
        let mut i = 0;
        while i + 32 <= n {
            // SAFETY: AVX2 (the caller's contract); the store writes 32 bytes of `out` below n.
            unsafe {
                let r = _mm256_permute4x64_epi64::<0xd8>(_mm256_packus_epi16(q(i), q(i + 16)));
                _mm256_storeu_si256(out.as_mut_ptr().add(i).cast::<__m256i>(), r);
            }
            i += 32;
        }
        if i < n {
            let q = q(i);
            // SAFETY: AVX2 (the caller's contract); the store writes 16 bytes of `out` below n.
            unsafe {
                let r = _mm_packus_epi16(_mm256_castsi256_si128(q), _mm256_extracti128_si256(q, 1));
                _mm_storeu_si128(out.as_mut_ptr().add(i).cast::<__m128i>(), r);
            }
        }
        n
    }

    /// [`super::unshear_k`] over the first `out.len() / 32 * 32` outputs (returned), 32 at a time
    /// (as [`unshear`]: `u` first).
    ///
    /// # Safety
    /// AVX-512 F/BW.
    #[target_feature(enable = "avx512f,avx512bw")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn unshear512(
        out: &mut [u8],
        b: &[u16],
        u: &mut [u16],
        ch: usize,
        g: u8,
        a: i32,
        dm: u16,
        ds: u32,
    ) -> usize {
        let n = out.len() / 32 * 32;
        assert!(b.len() >= n + 3 * ch && u.len() >= n + 2 * ch && ds >= 1);
        if n == 0 {
            return 0;
        }
        let set = |v: u16| _mm512_set1_epi16(v as i16);
        let (w0, w1) = (set((64 - g as u16) << 10), set((g as u16) << 10));
        let m = n + 2 * ch;
        if g != 0 {
            // Whole vectors, the last one ending at m (n >= 32).
            for i in (0..m).step_by(32).map(|i| i.min(m - 32)) {
                // SAFETY: AVX-512 F/BW (the caller's contract); loads of 32 values of `b` below
                // `m + ch <= b.len()`, a store of 32 values of `u` below `m <= u.len()`
                // (asserted).
                unsafe {
                    let l = |o: usize| _mm512_loadu_si512(b.as_ptr().add(i + o).cast::<__m512i>());
                    let v = _mm512_add_epi16(mulhi512(l(0), w0), mulhi512(l(ch), w1));
                    _mm512_storeu_si512(u.as_mut_ptr().add(i).cast::<__m512i>(), v);
                }
            }
        }
        let src: &[u16] = if g == 0 { b } else { u };
        let aa = a.unsigned_abs() as u16;
        let (aa1, aa2, sm) = (set(aa), set(aa << 1), set(if a < 0 { u16::MAX } else { 0 }));
        let (off, offv, dmv, zero, top) =
            (set(super::OFF), set(super::mulhi(super::OFF, dm)), set(dm), set(0), set(255));
        let cnt = _mm_cvtsi32_si128(ds as i32 - 1);
        for i in (0..n).step_by(32) {
            // SAFETY: AVX-512 F/BW (the caller's contract); every load reads 32 values of `src`
            // below `i + 32 + 2 ch <= m` (`b` or `u`, both at least m long) and the store writes
            // 32 bytes of `out` below n (asserted).
            unsafe {
                let l = |o: usize| _mm512_loadu_si512(src.as_ptr().add(i + o).cast::<__m512i>());
                let (ul, uc, ur) = (l(0), l(ch), l(2 * ch));
                let t = _mm512_sub_epi16(_mm512_add_epi16(mulhi512(ul, aa1), mulhi512(ur, aa1)), mulhi512(uc, aa2));
                let v = _mm512_add_epi16(_mm512_add_epi16(off, uc), _mm512_sub_epi16(_mm512_xor_si512(t, sm), sm));
                let q = _mm512_subs_epu16(mulhi512(v, dmv), offv);
                // `avg(x >> (ds - 1), 0)` as in [`unshear`], then the signed minimum: 2^15 is
                // negative, so 0 (where the wrapping sum gives 0), 256..2^15 - 1 give 255.
                let q = _mm512_min_epi16(_mm512_avg_epu16(_mm512_srl_epi16(q, cnt), zero), top);
                // Every value is 0..=255, kept by the (truncating) narrowing, or -2^15, whose low
                // byte is 0.
                _mm256_storeu_si256(out.as_mut_ptr().add(i).cast::<__m256i>(), _mm512_cvtepi16_epi8(q));
            }
        }
        n
    }

    /// Transposes 8 x 8 pixels of `C` (1 or 3) bytes: `dst[c * ds + r * C + b] = src[r * ss +
    /// c * C + b]`, each pixel widened to a 32-bit lane, an 8 x 8 32-bit transpose (`C` = 3: two
    /// in-lane 4 x 4 ones, see [`t8x8_narrow`]), narrowed back.
    ///
    /// # Safety
    /// AVX2; 8 rows of `8 C` bytes readable at `src + r * ss`, writable at `dst + c * ds`.
    #[target_feature(enable = "avx2")]
    pub unsafe fn t8x8_px<const C: usize>(src: *const u8, ss: usize, dst: *mut u8, ds: usize) {
        // SAFETY: as documented (row r at src + r ss).
        unsafe { t8x8_rows::<C>(std::array::from_fn(|r| src.add(r * ss)), dst, ds) }
    }

    /// [`t8x8_px`] storing each column's 24 bytes (`C` = 3) at once as 32: the 8 bytes after
    /// them (pixels 8, 9 and 10 from `dst + c * ds`) are overwritten with zeros.
    ///
    /// # Safety
    /// AVX2; 8 rows of `8 C` bytes readable at `src + r * ss`; `max(8 C, 32)` bytes writable at
    /// `dst + c * ds`.
    #[target_feature(enable = "avx2")]
    pub unsafe fn t8x8_px_wide<const C: usize>(src: *const u8, ss: usize, dst: *mut u8, ds: usize) {
        // SAFETY: as documented (row r at src + r ss).
        unsafe {
            let cols = t8x8_narrow::<C>(std::array::from_fn(|r| src.add(r * ss)));
            // Dwords 0..3 and 4..7 of each lane's 12 valid bytes, then zeros.
            let pack = _mm256_setr_epi32(0, 1, 2, 4, 5, 6, 3, 7);
            for (c, v) in cols.into_iter().enumerate() {
                let d = dst.add(c * ds);
                if C == 3 {
                    _mm256_storeu_si256(d as *mut __m256i, _mm256_permutevar8x32_epi32(v, pack));
                } else {
                    let (lo, hi) = (_mm256_castsi256_si128(v), _mm256_extracti128_si256(v, 1));
                    _mm_storel_epi64(d as *mut __m128i, _mm_unpacklo_epi32(lo, hi));
                }
            }
        }
    }

    /// [`t8x8_px`] with the 8 source rows at `src[r]`.
    ///
    /// # Safety
    /// AVX2; `8 C` bytes readable at each `src[r]`, writable at `dst + c * ds` for c < 8.
    #[target_feature(enable = "avx2")]
    pub unsafe fn t8x8_rows<const C: usize>(src: [*const u8; 8], dst: *mut u8, ds: usize) {
        // SAFETY: as documented; every store stays within the 8 C bytes of its row.
        unsafe {
            let cols = t8x8_narrow::<C>(src);
            // Dwords 0..3 and 4..7 of each lane's 12 valid bytes first (C = 3).
            let pack = _mm256_setr_epi32(0, 1, 2, 4, 5, 6, 3, 7);
            for (c, v) in cols.into_iter().enumerate() {
                let d = dst.add(c * ds);
                if C == 3 {
                    // The 24 bytes packed, stored as 16 + 8.
                    let v = _mm256_permutevar8x32_epi32(v, pack);
                    _mm_storeu_si128(d as *mut __m128i, _mm256_castsi256_si128(v));
                    _mm_storel_epi64(d.add(16) as *mut __m128i, _mm256_extracti128_si256(v, 1));
                } else {
                    let (lo, hi) = (_mm256_castsi256_si128(v), _mm256_extracti128_si256(v, 1));
                    _mm_storel_epi64(d as *mut __m128i, _mm_unpacklo_epi32(lo, hi));
                }
            }
        }
    }

    /// The 8 x 8 transpose of [`t8x8_rows`] in registers: column `c` (source pixel `c` of each
    /// row) in vector `c`, its pixel `r` at bytes `4 (r % 4) .. + C` of 128-bit lane `r / 4`
    /// (`C` = 3: each lane's bytes 0..12, zeros after; `C` = 1: bytes 0..4 of each lane).
    ///
    /// # Safety
    /// AVX2; `8 C` bytes readable at each `src[r]`.
    #[target_feature(enable = "avx2")]
    unsafe fn t8x8_narrow<const C: usize>(src: [*const u8; 8]) -> [__m256i; 8] {
        // SAFETY: as documented; every load stays within the 8 C bytes of its row.
        unsafe {
            let cols = if C == 3 {
                // Rows r and r + 4 in the two lanes of one register (their pixels 0..4 from bytes
                // 0..12, pixels 4..8 from bytes 12..24 loaded from byte 8), each pixel widened
                // to a 32-bit lane: two in-lane 4 x 4 transposes give the columns, no lane
                // permutes.
                let wa = _mm256_setr_epi8(
                    0, 1, 2, -1, 3, 4, 5, -1, 6, 7, 8, -1, 9, 10, 11, -1, 0, 1, 2, -1, 3, 4, 5, -1, 6, 7, 8, -1, 9, 10,
                    11, -1,
                );
                let wb = _mm256_setr_epi8(
                    4, 5, 6, -1, 7, 8, 9, -1, 10, 11, 12, -1, 13, 14, 15, -1, 4, 5, 6, -1, 7, 8, 9, -1, 10, 11, 12, -1,
                    13, 14, 15, -1,
                );
                let ld = |r: usize, o: usize, w: __m256i| {
                    _mm256_shuffle_epi8(
                        _mm256_set_m128i(
                            _mm_loadu_si128(src[r + 4].add(o) as *const __m128i),
                            _mm_loadu_si128(src[r].add(o) as *const __m128i),
                        ),
                        w,
                    )
                };
                let [c0, c1, c2, c3] =
                    crate::faults::kit::transpose4x4x2_epi32([ld(0, 0, wa), ld(1, 0, wa), ld(2, 0, wa), ld(3, 0, wa)]);
                let [c4, c5, c6, c7] =
                    crate::faults::kit::transpose4x4x2_epi32([ld(0, 8, wb), ld(1, 8, wb), ld(2, 8, wb), ld(3, 8, wb)]);
                [c0, c1, c2, c3, c4, c5, c6, c7]
            } else {
                let ld = |r: usize| _mm256_cvtepu8_epi32(_mm_loadl_epi64(src[r] as *const __m128i));
                crate::faults::kit::transpose8x8_epi32([ld(0), ld(1), ld(2), ld(3), ld(4), ld(5), ld(6), ld(7)])
            };
            let narrow = if C == 3 {
                _mm256_setr_epi8(
                    0, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14, -1, -1, -1, -1, 0, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14, -1,
                    -1, -1, -1,
                )
            } else {
                _mm256_setr_epi8(
                    0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 0, 4, 8, 12, -1, -1, -1, -1, -1, -1,
                    -1, -1, -1, -1, -1, -1,
                )
            };
            cols.map(|v| _mm256_shuffle_epi8(v, narrow))
        }
    }
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
    let threads = rayon::current_num_threads().max(1);
    let per = count.div_ceil(threads).max(64);
    let nb = count.div_ceil(per);
    if sc.slots.len() < nb {
        sc.slots.resize_with(nb, Slot::default);
    }
    if sc.taps_for.as_ref().is_none_or(|(p, c)| p != plan || *c != count) {
        sc.taps.clear();
        sc.taps.extend((0..count).map(|i| plan.cross_tap(i as isize)));
        sc.taps_for = Some((plan.clone(), count));
    }
    let taps = &sc.taps;
    if plan.vertical {
        if sc.src.len() < count * ls {
            if sc.src.capacity() < count * ls {
                // A fresh buffer asks for transparent huge pages before its first touch: the
                // line walk strides across the frame (one 4 KiB page per line), fewer TLB misses
                // with 2 MiB pages (4-9 % on the Zen 3, BENCHMARKS.md).
                let mut v: Vec<u8> = Vec::with_capacity(count * ls);
                #[cfg(target_os = "linux")]
                {
                    let (p, huge) = (v.as_mut_ptr() as usize, 1usize << 21);
                    let (a0, a1) = ((p + huge - 1) & !(huge - 1), (p + count * ls) & !(huge - 1));
                    if a1 > a0 {
                        // SAFETY: advice on whole pages inside the buffer's own allocation (not
                        // yet touched); it changes how the kernel backs them, never their
                        // contents.
                        unsafe { libc::madvise(a0 as *mut libc::c_void, a1 - a0, libc::MADV_HUGEPAGE) };
                    }
                }
                sc.src = v;
            }
            sc.src.resize(count * ls, 0);
        }
        sc.src[..count * ls]
            .par_chunks_mut(ls)
            .enumerate()
            .for_each(|(y, l)| l.copy_from_slice(&d[y * stride..y * stride + ls]));
        let src = Src::Rows(Lines { data: &sc.src, stride: ls, count, nl, ch });
        let used = d.len().min(stride * count);
        d[..used].par_chunks_mut(stride * per).zip(sc.slots.par_iter_mut()).enumerate().for_each(|(b, (out, slot))| {
            let i0 = b * per;
            let rows = per.min(count - i0);
            band(lv, plan, src, i0, rows, Dst::Rows(out, stride), &taps[i0..i0 + rows], slot);
        });
    } else {
        // Output lines are the frame's columns, written by each band (disjoint columns); each
        // band reads its own columns from the frame (see `ColSrc`), the columns of its window
        // beyond them from copies taken first: per band the columns its virtual lines
        // [i0 - n - 2, i0) and [i0 + rows, i0 + rows + n + 2) mirror to (two ranges).
        assert!(d.len() >= (h - 1) * stride + w * ch && w * ch <= stride);
        let n = plan.n as isize;
        let span = |j0: isize, j1: isize| {
            (j0..j1).map(|j| mirror(j, w)).fold((usize::MAX, 0), |(a, b), c| (a.min(c), b.max(c + 1)))
        };
        let mut lines = 0;
        sc.sides.clear();
        for b in 0..nb {
            let (i0, i1) = ((b * per) as isize, ((b + 1) * per).min(count) as isize);
            let (l, r) = (span(i0 - n - 2, i0), span(i1, i1 + n + 2));
            sc.sides.push((l, r, lines * ls));
            lines += l.1 - l.0 + r.1 - r.0;
        }
        let sides = &sc.sides;
        let e = h.min(plan.n + 8);
        let need = lines * ls + e * w * ch;
        if sc.side.len() < need {
            sc.side.resize(need, 0);
        }
        let (side, bottom) = sc.side[..need].split_at_mut(lines * ls);
        let mut rest = &mut *side;
        for &(l, r, _) in sides {
            for (c0, c1) in [l, r] {
                let (dst, tail) = std::mem::take(&mut rest).split_at_mut((c1 - c0) * ls);
                transpose(lv, &d[c0 * ch..], stride, c1 - c0, h, ch, dst, ls);
                rest = tail;
            }
        }
        for (y, row) in bottom.chunks_exact_mut(w * ch).enumerate() {
            let at = (h - e + y) * stride;
            row.copy_from_slice(&d[at..at + w * ch]);
        }
        let (side, bottom) = (&*side, &*bottom);
        let cols = Cols { ptr: d.as_mut_ptr(), len: d.len(), stride, rows: h, cols: w };
        sc.slots[..nb].par_iter_mut().enumerate().for_each(|(b, slot)| {
            let i0 = b * per;
            let rows = per.min(count - i0);
            let (l, r, o) = sides[b];
            let side = &side[o..o + (l.1 - l.0 + r.1 - r.0) * ls];
            let src = Src::Cols(ColSrc { cols, ch, i0, rows, side, l, r, bottom, e });
            band(lv, plan, src, i0, rows, Dst::Cols(cols), &taps[i0..i0 + rows], slot);
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The mostly horizontal path as it was: the whole frame transposed into a copy first, the
    /// lines read from it.
    fn blur_transposed(lv: u8, d: &mut [u8], stride: usize, w: usize, h: usize, ch: usize, plan: &StreakPlan) {
        assert!(!plan.vertical);
        let (count, nl) = (w, h);
        let ls = nl * ch;
        let mut t = vec![0u8; count * ls];
        transpose(lv, d, stride, w, h, ch, &mut t, ls);
        let taps: Vec<i32> = (0..count).map(|i| plan.cross_tap(i as isize)).collect();
        let src = Src::Rows(Lines { data: &t, stride: ls, count, nl, ch });
        let cols = Cols { ptr: d.as_mut_ptr(), len: d.len(), stride, rows: h, cols: w };
        let threads = rayon::current_num_threads().max(1);
        let per = count.div_ceil(threads).max(64);
        let mut slots: Vec<Slot> = (0..count.div_ceil(per)).map(|_| Slot::default()).collect();
        slots.par_iter_mut().enumerate().for_each(|(b, slot)| {
            let i0 = b * per;
            let rows = per.min(count - i0);
            band(lv, plan, src, i0, rows, Dst::Cols(cols), &taps[i0..i0 + rows], slot);
        });
    }

    #[test]
    fn frame_columns_read_in_place_equal_the_transposed_copy() {
        use crate::frame::{FrameData, PixelFormat};
        for (w, h, format) in [
            (203u32, 131u32, PixelFormat::Rgb8),
            (150, 190, PixelFormat::Mono8),
            (700, 300, PixelFormat::Rgb8),
            (600, 650, PixelFormat::Mono8),
            (64, 7, PixelFormat::Rgb8),
            (7, 64, PixelFormat::Mono8),
            (130, 20, PixelFormat::Rgb8),
            (143, 70, PixelFormat::Rgb8),
        ] {
            let f = crate::faults::kit::bench_scene(w, h, format, 3).unwrap();
            let ch = format.channels();
            for (len, ang) in [
                (30.0, 30.0),
                (40.0, 30.0),
                (40.0, 45.0),
                (100.0, 30.0),
                (60.0, 10.0),
                (100.0, 170.0),
                (25.0, 20.0),
                (66.0, 0.0),
                (100.0, 200.0),
                (50.0, 340.0),
            ] {
                let plan = StreakPlan::new(len, ang);
                if plan.vertical {
                    continue;
                }
                for threads in [1, 2, 3] {
                    for lv in [0, 1, 2] {
                        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
                        let (mut a, mut b) = (f.clone(), f.clone());
                        let stride = a.stride;
                        let (FrameData::U8(da), FrameData::U8(db)) = (&mut a.data, &mut b.data) else { unreachable!() };
                        pool.install(|| {
                            blur_u8_at(lv, da, stride, w as usize, h as usize, ch, &plan, &mut Scratch::default());
                            blur_transposed(lv, db, stride, w as usize, h as usize, ch, &plan);
                        });
                        if let Some(p) = da.iter().zip(db.iter()).position(|(x, y)| x != y) {
                            panic!(
                                "{format} {w}x{h} {len}@{ang} lv {lv} {threads} threads: first difference at row {} byte {}",
                                p / stride,
                                p % stride
                            );
                        }
                    }
                }
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn lerp256_equals_the_scalar_lerp() {
        if !crate::faults::kit::has_avx2() {
            return;
        }
        let mut seed = 12345u32;
        let p: Vec<u8> = (0..400)
            .map(|_| {
                seed = seed.wrapping_mul(1664525).wrapping_add(1013904223);
                (seed >> 24) as u8
            })
            .chain([0, 255, 255, 0, 255, 255, 255, 255, 255, 255])
            .collect();
        for ch in [1, 3] {
            for q in 0..=6 {
                for f in 0..64u8 {
                    for (len, off) in [(0, 0), (31, 5), (32, 0), (64, 3), (95, 1), (320, 67), (390, 7)] {
                        let (mut a, mut b) = (vec![0u16; len], vec![0u16; len]);
                        let src = &p[off..off + len + ch];
                        lerp_k(&mut a, src, ch, f, q);
                        // SAFETY: AVX2 present (checked above).
                        let done = unsafe { simd::lerp256(&mut b, src, ch, f, q) };
                        assert_eq!(done, len / 32 * 32);
                        assert_eq!(a[..done], b[..done], "ch {ch} q {q} f {f} len {len}");
                    }
                }
            }
        }
    }

    #[test]
    fn line_shifts_round_as_f64_round() {
        for (len, ang) in [(30.0, 30.0), (40.0, 45.0), (100.0, 170.0), (66.0, 5.0), (40.0, 80.0), (37.5, 135.0)] {
            let p = StreakPlan::new(len, ang);
            for j in -5000isize..5000 {
                assert_eq!(p.shift_q(j), (64.0 * j as f64 * p.m).round() as i64, "{len}@{ang} line {j}");
            }
        }
        // Halves round away from zero.
        let p = StreakPlan { m: 1.0 / 128.0, ..StreakPlan::new(30.0, 30.0) };
        assert_eq!((p.shift_q(1), p.shift_q(-1), p.shift_q(3), p.shift_q(-3)), (1, -1, 2, -2));
    }

    #[test]
    fn mirrored_padding_by_runs_equals_the_mirror_per_pixel() {
        for nl in [1usize, 2, 5, 64] {
            let line: Vec<u8> = (0..3 * nl).map(|v| (v * 37 % 251) as u8).collect();
            for p0 in -3 * nl as isize - 2..3 * nl as isize + 2 {
                for cnt in [1usize, 2, 7, 40, 5 * nl + 3] {
                    let mut pad3 = vec![0u8; 3 * cnt];
                    pad_px::<3>(&mut pad3, &line, p0, nl);
                    let mut pad1 = vec![0u8; cnt];
                    pad_px::<1>(&mut pad1, &line[..nl], p0, nl);
                    for t in 0..cnt {
                        let sp = mirror(p0 + t as isize, nl);
                        assert_eq!(pad3[3 * t..3 * t + 3], line[3 * sp..3 * sp + 3], "{nl} {p0} {cnt} {t}");
                        assert_eq!(pad1[t], line[sp], "{nl} {p0} {cnt} {t}");
                    }
                }
            }
        }
    }

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
    fn unshear_levels_equal_the_scalar_over_the_whole_16_bit_range() {
        // Random `B` over all of 0..2^16 (the wrapping and the rounding's edges: results above
        // 255 and the saturating packs), both signs of the cross tap, ds 1..=4, g = 0 and not.
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        for ch in [1usize, 3] {
            for n in [16usize, 31, 32, 48, 64, 95, 130] {
                for case in 0..24 {
                    let b: Vec<u16> = (0..n + 3 * ch + 40).map(|_| rnd() as u16).collect();
                    let g = if case % 3 == 0 { 0 } else { (rnd() % 64) as u8 };
                    let a = (rnd() % 30000) as i32 * if case % 2 == 0 { 1 } else { -1 };
                    let ds = 1 + (case as u32 % 4);
                    let dm = (4 + rnd() % 65532) as u16;
                    let run = |lv: u8| {
                        let mut out = vec![0u8; n];
                        let mut u = vec![0u16; b.len()];
                        unshear_d(lv, &mut out, &b, &mut u, ch, g, a, dm, ds);
                        out
                    };
                    let want = run(0);
                    for lv in [1, 2] {
                        assert_eq!(run(lv), want, "ch {ch} n {n} g {g} a {a} dm {dm} ds {ds} lv {lv}");
                    }
                }
            }
        }
    }

    #[test]
    fn every_kernel_level_and_thread_count_gives_the_same_bytes() {
        use crate::frame::{FrameData, PixelFormat};
        for (w, h, format) in [(203u32, 131u32, PixelFormat::Rgb8), (150, 190, PixelFormat::Mono8)] {
            let f = crate::faults::kit::bench_scene(w, h, format, 3).unwrap();
            let ch = format.channels();
            for (len, ang) in [
                (13.0, 10.0),
                (40.0, 63.0),
                (100.0, 137.0),
                (30.0, 90.0),
                (25.0, 0.0),
                (25.0, 10.0),
                (61.0, 0.0),
                (100.0, 45.0),
            ] {
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
