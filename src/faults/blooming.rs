//! `blooming`: charge beyond a pixel's full well overflows into its neighbours.
//!
//! Charge model: the excess above the full well W is diffused with a Gaussian kernel, the
//! pixels that now exceed W overflow again, for at most 4 rounds and only while a round removes
//! at least 20 % of the remaining excess; what is left then fills the nearest pixels with room,
//! breadth-first from each saturated region's border (see `INFO.model`). EFFECTS.md defines the
//! diffusion as repeated until nothing exceeds W: the two differ where a large region sits just
//! over the well (the diffusion stalls and the fill puts the excess into the region's 1 px rim;
//! README "Known weaknesses"). The work is
//! sparse: the frame is cut into 32x32 tiles and only tiles reached by overflowing charge are
//! loaded into a floating-point pool; everything else is never touched (or, with an exposure
//! gain, only rescaled).

use super::kit::{RGB_CHANNEL_BITS, ge_mask_u8, lut_u8_row, max_of_row, multiversion, scale_q16_row, scale_q16_u8};
use super::util::gaussian_kernel;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, ImageMut, ImageRef, Sample};
use crate::with_image_mut;
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "blooming",
    stage: Stage::Sensor,
    order: 60,
    summary: "charge above the full well overflows into neighbouring pixels (charge conserving)",
    model: "Signal s = v * exposure_gain (DN; exposure_gain models a longer exposure so that 8-bit inputs can \
            overflow), full well W = full_well_fraction * FS. mode = charge: every sample with s > W keeps W \
            and its excess s - W is spread with a normalised Gaussian kernel of std spread_px (isotropic; \
            axis = vertical or horizontal restricts the spread to the column or row, the CCD variant where \
            charge overflows along the transfer channel); pixels pushed above W overflow again; repeated \
            for at most 4 rounds, and only while a round reduces the remaining excess by at least 20 % (the \
            halo); the excess still left (charge that landed back inside a saturated region, which is \
            full) then fills the nearest pixels with room, breadth-first (4-neighbours) \
            from each saturated region's border, which conserves charge exactly. Charge is conserved \
            except what the kernel carries out of the frame (lost, as on a real sensor) or what cannot fit \
            because the frame is full. Saturated pixels read W (rounded to nearest DN), never FS. Rgb8: each \
            channel on its own. Output rounded half up and clipped. With exposure_gain = 1 and no sample \
            above W (e.g. full_well_fraction = 1) the effect is the identity. mode = glow: the study's \
            visual rendering, not charge conserving: samples with s >= W emit a halo glow_strength * FS * \
            min(1, (mask * G) / G(0)) (G: the Gaussian of std spread_px, so one saturated pixel glows with the full \
            amplitude and large regions do not pile up) and a vertical streak of peak glow_strength * FS / 2 decaying as \
            exp(-|dy| / streak_px); glow_strength = 0 is the identity.",
    params: &[
        ParamSpec::float("full_well_fraction", "fraction of FS", 0.05, 1.0, 0.9, "full well W / FS"),
        ParamSpec::float("spread_px", "px", 0.3, 8.0, 1.5, "std of the Gaussian overflow kernel (px)"),
        ParamSpec::choice(
            "mode",
            &["charge", "glow"],
            0,
            false,
            "charge = conserving overflow; glow = the study's halo-and-streak rendering",
        ),
        ParamSpec::choice(
            "axis",
            &["isotropic", "vertical", "horizontal"],
            0,
            false,
            "overflow direction: isotropic, or along columns / rows (CCD)",
        ),
        ParamSpec::float("exposure_gain", "1", 0.1, 100.0, 1.0, "signal multiplier before the well").log().extra(),
        ParamSpec::float("glow_strength", "fraction of FS", 0.0, 1.0, 0.5, "glow mode: halo amplitude / FS").extra(),
        ParamSpec::float("streak_px", "px", 0.0, 4000.0, 40.0, "glow mode: decay length of the streak (px)").extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(Blooming::default())
}

/// Tile edge (px). The kernel radius (3 * 8 px) must not exceed it.
pub const TILE: usize = 32;
const TT: usize = TILE * TILE;
const NONE: u32 = u32::MAX;
/// Rounds of Gaussian diffusion before the breadth-first fill. Diffusion shapes the halo around
/// a saturated region; charge that lands back inside the region (which is full) would bounce for
/// many rounds (the excess of a saturated disc falls only ~15 % per round), so after this many
/// rounds the remainder fills the nearest pixels with room directly.
pub const DIFFUSION_ROUNDS: usize = 4;
/// Diffusion continues only while a round reduces the excess left over by at least 20 %
/// (the excess of a small glint falls ~25-30 % per round; inside a large saturated region a few
/// percent).
pub const STALL_RATIO: f64 = 0.8;

/// Sparse tiled state of one channel, kept across frames (no per-frame allocation once the
/// pool has grown).
#[derive(Default)]
pub struct Blooming {
    ntx: usize,
    nty: usize,
    // allocation: once per stream (tile table, pool growing to the largest active area)
    slot: Vec<u32>,
    active: Vec<u32>,
    cur: Vec<f32>,
    acc: Vec<f32>,
    exc: Vec<f32>,
    stamp: Vec<u32>,
    /// Last fill generation written into `stamp` (kept across calls).
    generation: u32,
    has_exc: Vec<bool>,
    hbuf: Vec<f32>,
    lbuf: Vec<f32>,
    /// Breadth-first fill: (x, y, pool index).
    queue: Vec<(u32, u32, u32)>,
    frontier: Vec<(u32, u32, u32)>,
    streaks: Vec<(u32, u32, u32)>,
    /// Streaks of every channel: (channel, column, first row, end row), added at the end.
    streak_list: Vec<(u32, u32, u32, u32)>,
    // allocation: once per frame size: per (tile, channel) "holds a sample over W"
    tile_flags: Vec<bool>,
    // allocation: once per gain and sample width: round(v * exposure_gain)
    lut: Vec<u32>,
    /// `lut` as bytes, for 8-bit samples only (256 entries; empty for 16-bit).
    lut8: Vec<u8>,
    lut_gain: Option<u32>,
    /// The gain in Q16 when `(v * g + 2^15) >> 16` equals the table for every v.
    fixed_gain: Option<u32>,
    streak_buf: Vec<f32>,
    // allocation: once per stream (one flag per pool slot, list of slots fed this round)
    touched: Vec<bool>,
    touched_list: Vec<u32>,
    kernel_key: Option<(u64, u8)>,
    kh: Vec<f32>,
    kv: Vec<f32>,
    /// Charge (DN) lost out of the frame on the last call, summed over channels.
    lost: f64,
    /// Diffusion rounds used on the last call (largest over channels).
    rounds: usize,
    /// Charge (DN) placed by the breadth-first fill on the last call (kept or lost).
    fallback_dn: f64,
    /// One worker per channel (each with its own pool); allocated once per channel count.
    chans: Vec<Blooming>,
    /// Worker: whether its channel had a flagged tile on the last call.
    ran: bool,
}

/// What one channel pass needs to read the frame.
struct View<'a, T> {
    img: ImageRef<'a, T>,
    c: usize,
    gain: f32,
    well: f32,
    /// Glow mode: amplitude emitted by saturated samples.
    glow: Option<f32>,
}

impl<T: Sample> View<'_, T> {
    #[inline]
    fn signal(&self, x: usize, y: usize) -> f32 {
        self.img.data[y * self.img.stride + x * self.img.channels + self.c].to_f32() * self.gain
    }
}

impl Blooming {
    /// Charge lost out of the frame on the last call (DN).
    pub fn lost_dn(&self) -> f64 {
        self.lost
    }
    /// Diffusion rounds used on the last call.
    pub fn rounds(&self) -> usize {
        self.rounds
    }
    /// Excess charge (DN) that was left after the diffusion rounds and placed by the
    /// breadth-first fill on the last call.
    pub fn fallback_dn(&self) -> f64 {
        self.fallback_dn
    }

    fn reset(&mut self, w: usize, h: usize) {
        self.ntx = w.div_ceil(TILE);
        self.nty = h.div_ceil(TILE);
        let n = self.ntx * self.nty;
        self.slot.clear();
        self.slot.resize(n, NONE);
        self.active.clear();
        self.has_exc.clear();
        self.touched.clear();
        self.touched_list.clear();
        self.streaks.clear();
        // Reserve (address space only: pages are touched as tiles are used) for every tile, so a
        // frame with more saturated tiles than any before does not reallocate mid-stream.
        let px = n * TT;
        for v in [&mut self.cur, &mut self.acc, &mut self.exc] {
            v.reserve(px.saturating_sub(v.len()));
        }
        self.stamp.reserve(px.saturating_sub(self.stamp.len()));
        for v in [&mut self.active, &mut self.touched_list] {
            v.reserve(n.saturating_sub(v.len()));
        }
        self.has_exc.reserve(n.saturating_sub(self.has_exc.len()));
        self.touched.reserve(n.saturating_sub(self.touched.len()));
        for q in [&mut self.queue, &mut self.frontier] {
            q.reserve(px.saturating_sub(q.len()));
        }
    }

    /// Slot of tile `tid`, loading it from the frame on first use.
    fn activate<T: Sample>(&mut self, tid: usize, v: &View<'_, T>) -> usize {
        let s = self.slot[tid];
        if s != NONE {
            return s as usize;
        }
        let s = self.active.len();
        self.slot[tid] = s as u32;
        self.active.push(tid as u32);
        self.has_exc.push(false);
        self.touched.push(false);
        if self.cur.len() < (s + 1) * TT {
            let n = (s + 1) * TT;
            self.cur.resize(n, 0.0);
            self.acc.resize(n, 0.0);
            self.exc.resize(n, 0.0);
            self.stamp.resize(n, 0);
        }
        let (tx, ty) = (tid % self.ntx, tid / self.ntx);
        let (w, h, ch) = (v.img.width, v.img.height, v.img.channels);
        let r = s * TT..(s + 1) * TT;
        // `acc` is all zero outside a round (every slot that receives charge is merged, which
        // clears it) and `stamp` holds only generations of earlier fills (see `fallback`), so
        // neither needs clearing; `cur` and `exc` are overwritten below except outside the frame
        // in a border tile.
        debug_assert!(self.acc[r.clone()].iter().all(|&a| a == 0.0));
        let (x0, xn) = (tx * TILE, TILE.min(w - tx * TILE));
        if xn < TILE || h - ty * TILE < TILE {
            self.cur[r.clone()].fill(0.0);
            self.exc[r].fill(0.0);
        }
        let mut any = false;
        let mut sig = [T::default(); TILE];
        for ly in 0..TILE.min(h - ty * TILE) {
            let row = &v.img.row(ty * TILE + ly)[x0 * ch..(x0 + xn) * ch];
            let base = s * TT + ly * TILE;
            let (cur, exc) = (&mut self.cur[base..base + xn], &mut self.exc[base..base + xn]);
            if ch == 1 {
                // One channel: the samples are contiguous, converted in vectors with the rest.
                load_span(row, v.gain, v.well, v.glow.is_some(), cur, exc, &mut any);
                continue;
            }
            // Gather the channel (8-bit RGB: byte shuffles; else scalar), then the arithmetic in
            // vectors.
            if ch == 3
                && let (Some(src), Some(dst)) = (T::bytes(row), T::bytes_mut(&mut sig[..xn]))
            {
                gather_rgb8(src, v.c, dst);
            } else {
                for (o, px) in sig[..xn].iter_mut().zip(row.chunks_exact(ch)) {
                    *o = px[v.c];
                }
            }
            load_span(&sig[..xn], v.gain, v.well, v.glow.is_some(), cur, exc, &mut any);
        }
        self.has_exc[s] = any;
        s
    }

    /// Slot and in-tile index of pixel (x, y), loading its tile if needed.
    #[inline]
    fn index<T: Sample>(&mut self, x: usize, y: usize, v: &View<'_, T>) -> usize {
        let tid = (y / TILE) * self.ntx + x / TILE;
        let s = self.activate(tid, v);
        s * TT + (y % TILE) * TILE + x % TILE
    }

    /// Spread the excess of slot `s` into `acc` of the tiles around it (the kernel radius is at
    /// most one tile, so only the 3x3 tiles around it are reached; each is resolved once and fed
    /// row by row). Returns the charge that left the frame.
    fn scatter<T: Sample>(&mut self, s: usize, v: &View<'_, T>) -> f64 {
        let (rh, rv) = (self.kh.len() / 2, self.kv.len() / 2);
        let (lw, lh) = (TILE + 2 * rh, TILE + 2 * rv);
        // Only the rows of the tile that hold excess (and the rows the vertical kernel reaches
        // from them) can be non-zero: just those are cleared, spread and distributed. Zero rows
        // add nothing anywhere, so the result is the same as for the whole tile.
        let exc = &self.exc[s * TT..(s + 1) * TT];
        let nonzero = |ly: &usize| exc[ly * TILE..(ly + 1) * TILE].iter().any(|&e| e != 0.0);
        let (Some(y0), Some(y1)) = ((0..TILE).find(nonzero), (0..TILE).rev().find(nonzero)) else {
            self.has_exc[s] = false;
            return 0.0;
        };
        self.hbuf.resize(TILE * lw, 0.0);
        self.hbuf[y0 * lw..(y1 + 1) * lw].fill(0.0);
        self.lbuf.resize(lh * lw, 0.0);
        let (l0, l1) = (y0, y1 + 2 * rv + 1);
        self.lbuf[l0 * lw..l1 * lw].fill(0.0);
        scatter_passes(exc, &self.kh, &self.kv, &mut self.hbuf, &mut self.lbuf, lw, y0, y1 + 1, 0u8);
        self.exc[s * TT..(s + 1) * TT].iter_mut().for_each(|e| *e = 0.0);
        self.has_exc[s] = false;
        let tid = self.active[s] as usize;
        let (tx, ty) = ((tid % self.ntx) as isize, (tid / self.ntx) as isize);
        let (w, h) = (v.img.width as isize, v.img.height as isize);
        let t = TILE as isize;
        // lbuf pixel (lx, ly) is frame pixel (tx*T + lx - rh, ty*T + ly - rv).
        let (ox, oy) = (tx * t - rh as isize, ty * t - rv as isize);
        let mut lost = 0f64;
        // Taken out of `self` while tiles are activated (put back below: no allocation).
        let lbuf = std::mem::take(&mut self.lbuf);
        for dty in -1..=1isize {
            let nty = ty + dty;
            // Rows of lbuf that fall in tile row nty (and may be non-zero).
            let (y_lo, y_hi) = ((nty * t).max(oy + l0 as isize), ((nty + 1) * t).min(oy + l1 as isize));
            if y_lo >= y_hi {
                continue;
            }
            for dtx in -1..=1isize {
                let ntx = tx + dtx;
                let (x_lo, x_hi) = ((ntx * t).max(ox), ((ntx + 1) * t).min(ox + lw as isize));
                if x_lo >= x_hi {
                    continue;
                }
                // Part inside the frame.
                let (fx_hi, fy_hi) = (x_hi.min(w), y_hi.min(h));
                let inside_tile = ntx >= 0 && nty >= 0 && ntx * t < w && nty * t < h;
                let mut slot: Option<usize> = None;
                for y in y_lo..y_hi {
                    let row = &lbuf[((y - oy) as usize) * lw..][..lw];
                    let seg = &row[(x_lo - ox) as usize..(x_hi - ox) as usize];
                    if !inside_tile || y >= fy_hi || y < 0 {
                        lost += seg.iter().map(|&q| q as f64).sum::<f64>();
                        continue;
                    }
                    let split = (fx_hi - x_lo).max(0) as usize;
                    let (keep, out) = seg.split_at(split.min(seg.len()));
                    if !out.is_empty() {
                        lost += out.iter().map(|&q| q as f64).sum::<f64>();
                    }
                    if keep.iter().all(|&q| q == 0.0) {
                        continue;
                    }
                    let sl = match slot {
                        Some(sl) => sl,
                        None => {
                            let sl = self.activate((nty as usize) * self.ntx + ntx as usize, v);
                            if !self.touched[sl] {
                                self.touched[sl] = true;
                                self.touched_list.push(sl as u32);
                            }
                            slot = Some(sl);
                            sl
                        }
                    };
                    let base = sl * TT + ((y - nty * t) as usize) * TILE + (x_lo - ntx * t) as usize;
                    for (a, &q) in self.acc[base..base + keep.len()].iter_mut().zip(keep) {
                        *a += q;
                    }
                }
            }
        }
        self.lbuf = lbuf;
        lost
    }

    /// Charge mode on one channel: up to [`DIFFUSION_ROUNDS`] rounds of Gaussian diffusion of
    /// the excess, then the exact breadth-first fill of what remains. Returns (lost charge,
    /// rounds).
    fn charge<T: Sample>(&mut self, v: &View<'_, T>, vertical_only: bool, horizontal_only: bool) -> (f64, usize) {
        let mut lost = 0.0;
        let mut rounds = 0;
        let excess = |b: &Self| -> f64 {
            (0..b.active.len()).filter(|&s| b.has_exc[s]).map(|s| sum_tile(&b.exc[s * TT..(s + 1) * TT])).sum()
        };
        let mut before = excess(self);
        while rounds < DIFFUSION_ROUNDS && before > 0.0 {
            let n = self.active.len();
            rounds += 1;
            for s in 0..n {
                if self.has_exc[s] {
                    lost += self.scatter(s, v);
                }
            }
            // Only the tiles that received charge can change.
            let mut after = 0f64;
            for i in 0..self.touched_list.len() {
                let s = self.touched_list[i] as usize;
                self.touched[s] = false;
                let r = s * TT..(s + 1) * TT;
                let tile = merge_tile(&mut self.cur[r.clone()], &mut self.acc[r.clone()], &mut self.exc[r], v.well);
                self.has_exc[s] |= tile > 0.0;
                after += tile as f64;
            }
            self.touched_list.clear();
            // Diffusion that no longer makes progress (the excess landed back inside a large
            // saturated region) hands over to the fill.
            if after > STALL_RATIO * before {
                break;
            }
            before = after;
        }
        let n = self.active.len();
        self.fallback_dn +=
            (0..n).filter(|&s| self.has_exc[s]).map(|s| sum_tile(&self.exc[s * TT..(s + 1) * TT])).sum::<f64>();
        lost += self.fallback(v, vertical_only, horizontal_only);
        (lost, rounds)
    }

    /// Move every remaining excess to the nearest pixels with room (breadth-first from each
    /// saturated region). Exact conservation; returns what did not fit in the frame.
    fn fallback<T: Sample>(&mut self, v: &View<'_, T>, vertical_only: bool, horizontal_only: bool) -> f64 {
        let axes = (vertical_only, horizontal_only);
        let mut lost = 0.0;
        // Generations increase across calls, so stamps left by earlier frames never match; on
        // wrap-around the stamps are cleared once.
        let mut generation = self.generation;
        let mut s = 0;
        while s < self.active.len() {
            if !self.has_exc[s] {
                s += 1;
                continue;
            }
            let tid = self.active[s] as usize;
            let mut li = 0;
            while li < TT {
                // Seeds in index order; eight samples without excess are skipped at once (no seed
                // among them, and nothing changes them before the scan moves past).
                if li % 8 == 0 && self.exc[s * TT + li..][..8].iter().all(|&e| e <= 0.0) {
                    li += 8;
                    continue;
                }
                if self.exc[s * TT + li] <= 0.0 {
                    li += 1;
                    continue;
                }
                if generation == u32::MAX {
                    self.stamp.iter_mut().for_each(|t| *t = 0);
                    generation = 0;
                }
                generation += 1;
                let x0 = (tid % self.ntx) * TILE + li % TILE;
                let y0 = (tid / self.ntx) * TILE + li / TILE;
                let mut pool = 0f64;
                self.queue.clear();
                self.frontier.clear();
                let seed = s * TT + li;
                self.stamp[seed] = generation;
                self.queue.push((x0 as u32, y0 as u32, seed as u32));
                let mut nb = [(0u32, 0u32, 0u32); 4];
                // Pass A: the saturated region around the seed, pooling its excess.
                let mut head = 0;
                while head < self.queue.len() {
                    let (x, y, i) = self.queue[head];
                    head += 1;
                    let i = i as usize;
                    pool += self.exc[i] as f64;
                    self.exc[i] = 0.0;
                    let k = self.neighbours_of(x as usize, y as usize, i, axes, v, &mut nb);
                    for &(nx, ny, j) in &nb[..k] {
                        let j = j as usize;
                        if self.stamp[j] == generation {
                            continue;
                        }
                        self.stamp[j] = generation;
                        if self.cur[j] >= v.well {
                            self.queue.push((nx, ny, j as u32));
                        } else {
                            self.frontier.push((nx, ny, j as u32));
                        }
                    }
                }
                // Pass B: fill outward from the region's border, nearest first.
                std::mem::swap(&mut self.queue, &mut self.frontier);
                let mut head = 0;
                while head < self.queue.len() && pool > 0.0 {
                    let (x, y, i) = self.queue[head];
                    head += 1;
                    let i = i as usize;
                    pool += self.exc[i] as f64;
                    self.exc[i] = 0.0;
                    let take = ((v.well - self.cur[i]) as f64).clamp(0.0, pool);
                    self.cur[i] = (self.cur[i] + take as f32).min(v.well);
                    pool -= take;
                    if pool <= 0.0 {
                        break;
                    }
                    let k = self.neighbours_of(x as usize, y as usize, i, axes, v, &mut nb);
                    for &(nx, ny, j) in &nb[..k] {
                        if self.stamp[j as usize] != generation {
                            self.stamp[j as usize] = generation;
                            self.queue.push((nx, ny, j));
                        }
                    }
                }
                lost += pool.max(0.0);
                li += 1;
            }
            self.has_exc[s] = false;
            s += 1;
        }
        self.generation = generation;
        lost
    }

    /// The 4-neighbours of pixel (x, y) (pool index `i`) inside the frame, optionally restricted
    /// to one axis (`axes` = (vertical only, horizontal only)), in the order left, right, up,
    /// down, with their pool indices (inside the tile by offset, across a tile edge through the
    /// tile table, loading the tile if needed); returns how many.
    #[inline(always)]
    fn neighbours_of<T: Sample>(
        &mut self,
        x: usize,
        y: usize,
        i: usize,
        axes: (bool, bool),
        v: &View<'_, T>,
        out: &mut [(u32, u32, u32); 4],
    ) -> usize {
        let (w, h) = (v.img.width, v.img.height);
        let mut k = 0;
        let mut put = |nx: usize, ny: usize, j: usize| {
            out[k] = (nx as u32, ny as u32, j as u32);
            k += 1;
        };
        if !axes.0 {
            if x > 0 {
                put(x - 1, y, if !x.is_multiple_of(TILE) { i - 1 } else { self.index(x - 1, y, v) });
            }
            if x + 1 < w {
                put(x + 1, y, if !(x + 1).is_multiple_of(TILE) { i + 1 } else { self.index(x + 1, y, v) });
            }
        }
        if !axes.1 {
            if y > 0 {
                put(x, y - 1, if !y.is_multiple_of(TILE) { i - TILE } else { self.index(x, y - 1, v) });
            }
            if y + 1 < h {
                put(x, y + 1, if !(y + 1).is_multiple_of(TILE) { i + TILE } else { self.index(x, y + 1, v) });
            }
        }
        k
    }

    /// Glow mode on one channel: halo (one scatter, no well) and streak profiles.
    fn glow<T: Sample>(&mut self, v: &View<'_, T>, streak_px: f32, amp: f32) {
        // Streak columns: every column holding a saturated sample in a flagged tile.
        self.streaks.clear();
        let (w, h) = (v.img.width, v.img.height);
        let n = self.active.len();
        for s in 0..n {
            let tid = self.active[s] as usize;
            let (tx, ty) = (tid % self.ntx, tid / self.ntx);
            for lx in 0..TILE.min(w - tx * TILE) {
                let col = (0..TILE.min(h - ty * TILE)).filter(|&ly| self.exc[s * TT + ly * TILE + lx] > 0.0);
                let (mut lo, mut hi) = (u32::MAX, 0);
                for ly in col {
                    lo = lo.min((ty * TILE + ly) as u32);
                    hi = hi.max((ty * TILE + ly) as u32);
                }
                if lo <= hi {
                    self.streaks.push(((tx * TILE + lx) as u32, lo, hi));
                }
            }
        }
        self.streaks.sort_unstable();
        // Merge entries of the same column (from vertically adjacent tiles).
        self.streaks.dedup_by(|b, a| {
            if a.0 == b.0 {
                a.1 = a.1.min(b.1);
                a.2 = a.2.max(b.2);
                true
            } else {
                false
            }
        });
        if streak_px > 0.0 {
            let decay = (-1.0 / streak_px).exp();
            let reach = (8.0 * streak_px).ceil() as u32;
            for k in 0..self.streaks.len() {
                let (x, lo, hi) = self.streaks[k];
                let (y0, y1) = (lo.saturating_sub(reach) as usize, ((hi + reach + 1) as usize).min(h));
                let start = self.streak_buf.len();
                self.streak_buf.resize(start + (y1 - y0), 0.0);
                let buf = &mut self.streak_buf[start..];
                let mut m = 0f32;
                for (y, b) in (y0..y1).zip(buf.iter_mut()) {
                    m = if v.signal(x as usize, y) >= v.well { 1.0 } else { m * decay };
                    *b = m;
                }
                m = 0.0;
                for (y, b) in (y0..y1).zip(buf.iter_mut()).rev() {
                    m = if v.signal(x as usize, y) >= v.well { 1.0 } else { m * decay };
                    *b = b.max(m) * 0.5 * amp;
                }
                self.streaks[k] = (x, y0 as u32, y1 as u32);
            }
        } else {
            self.streaks.clear();
        }
        for s in 0..n {
            if self.has_exc[s] {
                self.scatter(s, v);
            }
        }
        for &t in &self.touched_list {
            self.touched[t as usize] = false;
        }
        self.touched_list.clear();
        // Halo = amp * min(1, blurred mask / kernel peak): a single saturated pixel glows with
        // the full amplitude at its centre, large regions do not pile up beyond it.
        let peak = self.kh[self.kh.len() / 2] * self.kv[self.kv.len() / 2];
        for s in 0..self.active.len() {
            let r = s * TT..(s + 1) * TT;
            for (c, a) in self.cur[r.clone()].iter_mut().zip(&mut self.acc[r]) {
                *c += amp * (*a / peak).min(1.0);
                *a = 0.0;
            }
        }
    }
}

multiversion! {
    /// Separable spread of one tile's excess (`TILE` x `TILE`) into `lbuf` ((TILE + 2 rv) rows of
    /// `lw` = TILE + 2 rh): horizontal kernel into `hbuf`, then the vertical kernel.
    /// Only rows `y0..y1` of `exc` are read (the others must be zero); the matching rows of
    /// `hbuf` and rows `y0..y1 + kv.len() - 1` of `lbuf` must be zero on entry.
    fn scatter_passes<T: Copy>(
        exc: &[f32],
        kh: &[f32],
        kv: &[f32],
        hbuf: &mut [f32],
        lbuf: &mut [f32],
        lw: usize,
        y0: usize,
        y1: usize,
        _t: T,
    ) {
        for ly in y0..y1 {
            let e_row = &exc[ly * TILE..][..TILE];
            if e_row.iter().all(|&e| e == 0.0) {
                continue;
            }
            let h_row = &mut hbuf[ly * lw..][..lw];
            // Tap by tap over the whole row (vectorises): h[lx + j] += kh[j] * e[lx].
            for (j, &k) in kh.iter().enumerate() {
                for (o, &e) in h_row[j..j + TILE].iter_mut().zip(e_row) {
                    *o += e * k;
                }
            }
        }
        for ly in y0..y1 {
            let h_row = &hbuf[ly * lw..][..lw];
            if h_row.iter().all(|&x| x == 0.0) {
                continue;
            }
            for (k, &kw) in kv.iter().enumerate() {
                let l_row = &mut lbuf[(ly + k) * lw..][..lw];
                for (o, &hv) in l_row.iter_mut().zip(h_row) {
                    *o += hv * kw;
                }
            }
        }
    }
}

multiversion! {
    /// `row[lx * ch] = round(src[lx])` (the frame's rounding and clipping) for every lx.
    fn store_channel<T: Sample>(row: &mut [T], src: &[f32], ch: usize) {
        if ch == 1 {
            for (o, &v) in row.iter_mut().zip(src) {
                *o = T::from_f32(v);
            }
        } else {
            // Convert in vectors, then store with the stride.
            let mut tmp = [T::default(); TILE];
            for (src, row) in src.chunks(TILE).zip(row.chunks_mut(TILE * ch)) {
                let tmp = &mut tmp[..src.len()];
                for (o, &v) in tmp.iter_mut().zip(src) {
                    *o = T::from_f32(v);
                }
                for (o, &t) in row.iter_mut().step_by(ch).zip(tmp.iter()) {
                    *o = t;
                }
            }
        }
    }
}

multiversion! {
    /// Sum of f32 values in f64 with four interleaved partial sums (the order is fixed, so the
    /// result is the same on every run; it vectorises).
    fn sum_f64<T: Copy>(v: &[f32], out: &mut f64, _t: T) {
        let mut part = [0f64; 4];
        let mut it = v.chunks_exact(4);
        for q in &mut it {
            for k in 0..4 {
                part[k] += q[k] as f64;
            }
        }
        let tail: f64 = it.remainder().iter().map(|&e| e as f64).sum();
        *out = (part[0] + part[1]) + (part[2] + part[3]) + tail;
    }
}

/// [`sum_f64`] as a function.
#[inline]
fn sum_tile(v: &[f32]) -> f64 {
    let mut out = 0.0;
    sum_f64(v, &mut out, 0u8);
    out
}

multiversion! {
    fn merge_tile_mv<T: Copy>(cur: &mut [f32], acc: &mut [f32], exc: &mut [f32], well: f32, out: &mut f32, _t: T) {
        let mut part = [0f32; 8];
        for ((c8, a8), e8) in cur.chunks_exact_mut(8).zip(acc.chunks_exact_mut(8)).zip(exc.chunks_exact_mut(8)) {
            for k in 0..8 {
                let sum = c8[k] + a8[k];
                let over = (sum - well).max(0.0);
                a8[k] = 0.0;
                e8[k] += over;
                c8[k] = sum.min(well);
                part[k] += over;
            }
        }
        *out = part.iter().sum();
    }
}

multiversion! {
    /// Load samples `src` of a tile row with the exposure gain: charge mode `cur = min(s, W)`,
    /// `exc = max(s - W, 0)`; glow mode `cur = s`, `exc = [s >= W]` (s = src * gain). Sets `any`
    /// when some `exc` is positive.
    fn load_span<T: Sample>(
        src: &[T],
        gain: f32,
        well: f32,
        glow: bool,
        cur: &mut [f32],
        exc: &mut [f32],
        any: &mut bool,
    ) {
        let mut flag = 0u32;
        if glow {
            for ((c, e), &x) in cur.iter_mut().zip(exc.iter_mut()).zip(src) {
                let sig = x.to_f32() * gain;
                *c = sig;
                *e = if sig >= well { 1.0 } else { 0.0 };
                flag |= (sig >= well) as u32;
            }
        } else {
            for ((c, e), &x) in cur.iter_mut().zip(exc.iter_mut()).zip(src) {
                let sig = x.to_f32() * gain;
                *c = sig.min(well);
                let over = (sig - well).max(0.0);
                *e = over;
                flag |= (over > 0.0) as u32;
            }
        }
        *any |= flag != 0;
    }
}

multiversion! {
    /// Maximum of each `seg`-sample segment of `row` into `out` (one per segment, the last one
    /// possibly shorter).
    fn segment_max<T: Sample>(row: &[T], seg: usize, out: &mut [T]) {
        for (o, s) in out.iter_mut().zip(row.chunks(seg)) {
            *o = s.iter().fold(T::default(), |m, &v| if v > m { v } else { m });
        }
    }
}

/// Channel `c` of the first `out.len()` pixels of an interleaved 3-channel byte row into `out`
/// (a full tile row: 16-byte shuffles with AVX2; otherwise scalar).
fn gather_rgb8(row: &[u8], c: usize, out: &mut [u8]) {
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx2() && c < 3 && out.len() == TILE && row.len() >= 3 * TILE {
        // SAFETY: the CPU supports AVX2 (checked just above), and the lengths were checked.
        unsafe { gather_rgb8_avx2(row, c, out) };
        return;
    }
    for (o, px) in out.iter_mut().zip(row.chunks_exact(3)) {
        *o = px[c];
    }
}

/// AVX2 (SSSE3 shuffles) version of [`gather_rgb8`] for a full tile row.
/// # Safety
/// AVX2; `c < 3`, `out.len() == TILE` and `row.len() >= 3 * TILE`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn gather_rgb8_avx2(row: &[u8], c: usize, out: &mut [u8]) {
    use std::arch::x86_64::*;
    // SAFETY: 16-byte loads from the 48-entry split table of channel c < 3; the blocks read bytes
    // 0 .. 96 = 3 * TILE of the row and write bytes 0 .. 32 = TILE of `out` (the caller's bounds).
    unsafe {
        let m = super::kit::RGB8_SPLIT[c].as_ptr() as *const __m128i;
        let (m0, m1, m2) = (_mm_loadu_si128(m), _mm_loadu_si128(m.add(1)), _mm_loadu_si128(m.add(2)));
        for blk in 0..TILE / 16 {
            let p = row.as_ptr().add(48 * blk) as *const __m128i;
            let a = _mm_shuffle_epi8(_mm_loadu_si128(p), m0);
            let b = _mm_shuffle_epi8(_mm_loadu_si128(p.add(1)), m1);
            let d = _mm_shuffle_epi8(_mm_loadu_si128(p.add(2)), m2);
            _mm_storeu_si128(out.as_mut_ptr().add(16 * blk) as *mut __m128i, _mm_or_si128(_mm_or_si128(a, b), d));
        }
    }
}

/// Flag (tile, channel) pairs of one row from its comparison bits (`bits`: sample i of the row
/// is bit i; `flags`: `ch` entries per tile).
fn flag_tiles_from_bits(bits: &[u64], w: usize, ch: usize, flags: &mut [bool]) {
    let span = TILE * ch;
    let len = w * ch;
    // Only the words holding a set bit matter; each covers at most three tiles' samples.
    for (k, &word) in bits.iter().enumerate() {
        if word == 0 {
            continue;
        }
        let (w0, w1) = (k * 64, (k * 64 + 64).min(len));
        let mut tx = w0 / span;
        while tx * span < w1 {
            // Bits of this word inside tile tx.
            let (a, b) = ((tx * span).max(w0), ((tx + 1) * span).min(w1));
            let part = (word >> (a - w0)) & if b - a >= 64 { u64::MAX } else { (1u64 << (b - a)) - 1 };
            if part != 0 {
                let f = &mut flags[tx * ch..(tx + 1) * ch];
                match ch {
                    1 => f[0] = true,
                    3 => {
                        // Bit 0 of `part` is sample a, whose channel is (a - tile start) % 3.
                        let r = (a - tx * span) % 3;
                        for (c, fc) in f.iter_mut().enumerate() {
                            *fc |= part & RGB_CHANNEL_BITS[r][c] != 0;
                        }
                    }
                    _ => {
                        for j in 0..b - a {
                            if part >> j & 1 != 0 {
                                f[(a + j - tx * span) % ch] = true;
                            }
                        }
                    }
                }
            }
            tx += 1;
        }
    }
}

/// Add the received charge `acc` to `cur`, move what exceeds the well into `exc`, clear `acc`;
/// returns the new excess of the tile. Branch-free with eight partial sums, so it vectorises;
/// the same values as "if c > W { e += c - W; c = W }".
#[inline]
fn merge_tile(cur: &mut [f32], acc: &mut [f32], exc: &mut [f32], well: f32) -> f32 {
    let mut out = 0.0;
    merge_tile_mv(cur, acc, exc, well, &mut out, 0u8);
    out
}

impl Effect for Blooming {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let fs = frame.format.full_scale();
        let well = (p.get("full_well_fraction") as f32) * fs;
        let gain = p.get("exposure_gain") as f32;
        let glow = p.choice("mode") == "glow";
        let axis = p.choice("axis");
        let (vertical_only, horizontal_only) = (axis == "vertical" && !glow, axis == "horizontal" && !glow);
        let glow_amp = p.get("glow_strength") as f32 * fs;
        self.lost = 0.0;
        self.fallback_dn = 0.0;
        self.rounds = 0;
        if glow && glow_amp <= 0.0 && gain == 1.0 {
            return Ok(Outcome::Keep);
        }
        let key = (p.get("spread_px").to_bits(), (vertical_only as u8) | (horizontal_only as u8) << 1);
        if self.kernel_key != Some(key) {
            let k = gaussian_kernel(p.get("spread_px") as f32);
            self.kh = if vertical_only { vec![1.0] } else { k.clone() };
            self.kv = if horizontal_only { vec![1.0] } else { k };
            self.kernel_key = Some(key);
        }
        let streak_px = p.get("streak_px") as f32;
        let opts = Opts { well, gain, glow: glow.then_some(glow_amp), vertical_only, horizontal_only, streak_px };
        with_image_mut!(frame, img => self.process(&mut img, &opts));
        Ok(Outcome::Keep)
    }
}

struct Opts {
    well: f32,
    gain: f32,
    glow: Option<f32>,
    vertical_only: bool,
    horizontal_only: bool,
    streak_px: f32,
}

impl Blooming {
    fn process<T: Sample>(&mut self, img: &mut ImageMut<'_, T>, o: &Opts) {
        let (w, h, ch) = (img.width, img.height, img.channels);
        let (ntx, nty) = (w.div_ceil(TILE), h.div_ceil(TILE));
        let ntiles = ntx * nty;
        self.streak_list.clear();
        self.streak_buf.clear();
        // Smallest sample value over the threshold (glow: s >= W, charge: s > W, s = v * gain in
        // f32 exactly as the tiles compute it), so tiles are flagged by integer comparison.
        let over = |v: u32| {
            let s = v as f32 * o.gain;
            if o.glow.is_some() { s >= o.well } else { s > o.well }
        };
        let guess = ((o.well / o.gain).floor().max(0.0) as u32).min(T::MAX_U32);
        let mut thr = guess.saturating_sub(2);
        while thr <= T::MAX_U32 && !over(thr) {
            thr += 1;
        }
        // Per tile and channel: does it hold a sample >= thr? One pass for all channels.
        self.tile_flags.clear();
        self.tile_flags.resize(ntiles * ch, false);
        if thr <= T::MAX_U32 {
            let view = img.as_ref();
            let thr_t = T::from_u32_sat(thr);
            self.tile_flags.par_chunks_mut(ntx * ch).enumerate().for_each(|(ty, flags)| {
                let mut maxes = [T::default(); 512];
                // 8-bit: one comparison bit per sample (a row of up to 32768 samples).
                let mut bits = [0u64; 512];
                for y in ty * TILE..((ty + 1) * TILE).min(h) {
                    let row = view.row(y);
                    if let Some(bytes) = T::bytes(row).filter(|b| b.len() <= 512 * 64) {
                        let bits = &mut bits[..bytes.len().div_ceil(64)];
                        ge_mask_u8(bytes, thr as u8, bits);
                        flag_tiles_from_bits(bits, w, ch, flags);
                        continue;
                    }
                    // Per-tile maxima of the row in one vectorised call: most tiles are rejected.
                    let maxes = &mut maxes[..ntx.min(512)];
                    segment_max(row, TILE * ch, maxes);
                    for (tx, f) in flags.chunks_exact_mut(ch).enumerate() {
                        let seg = &row[tx * TILE * ch..((tx + 1) * TILE).min(w) * ch];
                        let m = if tx < maxes.len() { maxes[tx] } else { max_of_row(seg) };
                        if m < thr_t {
                            continue;
                        }
                        if ch == 1 {
                            f[0] = true;
                        } else {
                            for (c, fc) in f.iter_mut().enumerate() {
                                *fc |= seg.iter().skip(c).step_by(ch).any(|&v| v >= thr_t);
                            }
                        }
                    }
                }
            });
        }
        // One worker (its own pool) per channel; the channels are independent, so they run in
        // parallel and their results are combined in channel order (the same bytes and totals on
        // any thread count).
        if self.chans.len() < ch {
            self.chans.resize_with(ch, Blooming::default);
        }
        for b in &mut self.chans[..ch] {
            if b.kernel_key != self.kernel_key {
                b.kh.clone_from(&self.kh);
                b.kv.clone_from(&self.kv);
                b.kernel_key = self.kernel_key;
            }
        }
        let (flags, view) = (&self.tile_flags, img.as_ref());
        self.chans[..ch].par_iter_mut().enumerate().for_each(|(c, b)| b.run_channel(view, c, flags, o));
        // The tile pass read the frame; now every sample is rescaled by the exposure gain and the
        // samples of the tiles the pass worked on are then overwritten with its results.
        if o.gain != 1.0 {
            self.rescale(img, o.gain);
        }
        for c in 0..ch {
            let b = &mut self.chans[c];
            if !b.ran {
                continue;
            }
            self.lost += b.lost;
            self.rounds = self.rounds.max(b.rounds);
            self.fallback_dn += b.fallback_dn;
            b.write_back(img, c, &mut self.streak_list, &mut self.streak_buf);
        }
        // Streaks (glow mode) were collected per channel into `streak_list`.
        let (stride, mut off) = (img.stride, 0);
        for &(c, x, y0, y1) in &self.streak_list {
            for y in y0 as usize..y1 as usize {
                let v = &mut img.data[y * stride + x as usize * ch + c as usize];
                *v = T::from_f32(v.to_f32() + self.streak_buf[off]);
                off += 1;
            }
        }
    }

    /// Channel worker: load the flagged tiles of channel `c` and run the charge or glow pass
    /// (results in `ran`, `lost`, `rounds`, `fallback_dn`, the pool, `streaks`, `streak_buf`).
    fn run_channel<T: Sample>(&mut self, view: ImageRef<'_, T>, c: usize, flags: &[bool], o: &Opts) {
        self.ran = false;
        self.lost = 0.0;
        self.rounds = 0;
        self.fallback_dn = 0.0;
        self.streaks.clear();
        self.streak_buf.clear();
        let (w, h, ch) = (view.width, view.height, view.channels);
        let ntiles = w.div_ceil(TILE) * h.div_ceil(TILE);
        if !(0..ntiles).any(|t| flags[t * ch + c]) {
            return;
        }
        self.ran = true;
        self.reset(w, h);
        let v = View { img: view, c, gain: o.gain, well: o.well, glow: o.glow };
        for tid in 0..ntiles {
            if flags[tid * ch + c] {
                self.activate(tid, &v);
            }
        }
        match o.glow {
            None => {
                let (lost, rounds) = self.charge(&v, o.vertical_only, o.horizontal_only);
                self.lost = lost;
                self.rounds = rounds;
            }
            Some(amp) => self.glow(&v, o.streak_px, amp),
        }
    }

    /// Write channel `c` of the worker's active tiles into the frame and hand its glow streaks
    /// to `streak_list` / `streak_buf`.
    fn write_back<T: Sample>(
        &mut self,
        img: &mut ImageMut<'_, T>,
        c: usize,
        streak_list: &mut Vec<(u32, u32, u32, u32)>,
        streak_buf: &mut Vec<f32>,
    ) {
        let (w, h, ch, stride) = (img.width, img.height, img.channels, img.stride);
        for s in 0..self.active.len() {
            let tid = self.active[s] as usize;
            let (tx, ty) = (tid % self.ntx, tid / self.ntx);
            for ly in 0..TILE.min(h - ty * TILE) {
                let y = ty * TILE + ly;
                let src = &self.cur[s * TT + ly * TILE..][..TILE.min(w - tx * TILE)];
                let row = &mut img.data[y * stride + tx * TILE * ch..][..src.len() * ch];
                store_channel(&mut row[c..], src, ch);
            }
        }
        // Glow streaks of this channel: kept for the end (the rescale pass runs first).
        for &(x, y0, y1) in &self.streaks {
            streak_list.push((c as u32, x, y0, y1));
        }
        self.streaks.clear();
        streak_buf.extend_from_slice(&self.streak_buf);
    }

    /// Rescale every sample by the exposure gain, `v' = round_half_up(v * gain)` in f32 as the
    /// tiles compute it, through a lookup table (8-bit: byte table lookups; 16-bit: a Q16
    /// multiply when it reproduces the table).
    fn rescale<T: Sample>(&mut self, img: &mut ImageMut<'_, T>, gain: f32) {
        let n = T::MAX_U32 as usize + 1;
        if self.lut_gain != Some(gain.to_bits()) || self.lut.len() != n {
            self.lut.clear();
            self.lut.extend((0..n as u32).map(|v| T::from_f32(v as f32 * gain).to_u32()));
            self.lut_gain = Some(gain.to_bits());
            // Fast path: a Q16 fixed-point multiply, used only when it reproduces the table
            // (the reference) for every sample value.
            let gq = (gain as f64 * 65536.0).round() as u64;
            let fixed = |v: u64| ((v * gq + 32768) >> 16).min(T::MAX_U32 as u64) as u32;
            self.fixed_gain = self.lut.iter().enumerate().all(|(v, &l)| fixed(v as u64) == l).then_some(gq as u32);
            self.lut8.clear();
            if n == 256 {
                self.lut8.extend(self.lut.iter().map(|&l| l as u8));
            }
        }
        let (fixed, lut) = (self.fixed_gain, &self.lut);
        let lut8 = <&[u8; 256]>::try_from(self.lut8.as_slice()).ok();
        // Byte table lookups when the CPU permutes bytes, else the vectorised Q16 multiply.
        #[cfg(target_arch = "x86_64")]
        let has_vbmi = super::kit::has_avx512_vbmi();
        #[cfg(not(target_arch = "x86_64"))]
        let has_vbmi = false;
        let (w, h, ch, stride) = (img.width, img.height, img.channels, img.stride);
        let used = stride * (h - 1) + w * ch;
        img.data[..used].par_chunks_mut(stride * TILE).for_each(|chunk| {
            for row in chunk.chunks_mut(stride) {
                let row = &mut row[..w * ch];
                if let (Some(bytes), Some(lut8)) = (T::bytes_mut(row), lut8)
                    && (has_vbmi || fixed.is_none())
                {
                    lut_u8_row(bytes, lut8);
                    continue;
                }
                match fixed {
                    // 8-bit without byte permutes: the multiply in 16-bit lanes.
                    Some(gq) if T::bytes(row).is_some() => {
                        if let Some(bytes) = T::bytes_mut(row) {
                            scale_q16_u8(bytes, gq);
                        }
                    }
                    Some(gq) => scale_q16_row(row, gq),
                    None => {
                        for v in row.iter_mut() {
                            *v = T::from_u32_sat(lut[v.to_u32() as usize]);
                        }
                    }
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;
    use crate::rng::Rng;

    fn params(kv: &[(&str, f64)]) -> Params {
        let mut p = Params::defaults(&INFO);
        for (k, v) in kv {
            p.set(k, *v).unwrap();
        }
        p
    }

    /// Textured background (10..40% FS) with bright rectangles well inside the frame.
    fn scene(fmt: PixelFormat, w: u32, h: u32, spots: &[(usize, usize, usize, usize)]) -> Frame {
        let mut f = Frame::new(w, h, fmt).unwrap();
        let fs = fmt.full_scale();
        let mut r = Rng::new(4);
        for y in 0..h as usize {
            for x in 0..w as usize {
                for c in 0..fmt.channels() {
                    f.set(x, y, c, (0.1 + 0.3 * r.uniform_f32()) * fs);
                }
            }
        }
        for &(x0, y0, sw, sh) in spots {
            for y in y0..y0 + sh {
                for x in x0..x0 + sw {
                    for c in 0..fmt.channels() {
                        f.set(x, y, c, fs);
                    }
                }
            }
        }
        f
    }

    fn sum(f: &Frame) -> f64 {
        f.packed_samples_f32().iter().map(|&v| v as f64).sum()
    }

    fn run(f: &mut Frame, p: &Params) -> Blooming {
        let mut b = Blooming::default();
        b.apply(f, p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        b
    }

    /// Conservation, well level and saturated pixels reading W on an interior scene.
    fn check_charge(fmt: PixelFormat, kv: &[(&str, f64)], spots: &[(usize, usize, usize, usize)]) -> Blooming {
        let orig = scene(fmt, 160, 128, spots);
        let mut f = orig.clone();
        let p = params(kv);
        let b = run(&mut f, &p);
        let fs = fmt.full_scale() as f64;
        let well = p.get("full_well_fraction") * fs;
        let gain = p.get("exposure_gain");
        let w_read = (well + 0.5).floor() as f32;
        let mut changed = 0usize;
        let mut excess_px = 0;
        let (a, o) = (f.packed_samples_f32(), orig.packed_samples_f32());
        for (&out, &inp) in a.iter().zip(&o) {
            assert!(out <= w_read, "{fmt}: {out} above the well {well}");
            if inp as f64 * gain > well {
                assert_eq!(out, w_read, "{fmt}: a pixel with excess reads W");
                excess_px += 1;
            }
            if (out as f64 - inp as f64 * gain).abs() > 1e-9 {
                changed += 1;
            }
        }
        assert!(excess_px > 0);
        // Conservation: each changed sample carries at most 0.5 DN of rounding, plus f32
        // accumulation error (1e-6 relative); nothing left the frame.
        let want = sum(&orig) * gain;
        let got = sum(&f);
        assert!(b.lost_dn() < 1e-3 * fs, "lost {}", b.lost_dn());
        let bound = 0.5 * changed as f64 + 1e-6 * want;
        assert!((got - want).abs() <= bound, "{fmt}: sum {got} vs {want} (bound {bound}, {changed} changed)");
        b
    }

    #[test]
    fn charge_is_conserved_and_saturated_pixels_read_the_well() {
        for fmt in [PixelFormat::Mono8, PixelFormat::Mono16, PixelFormat::Rgb8] {
            check_charge(fmt, &[("full_well_fraction", 0.8), ("spread_px", 1.5)], &[(40, 40, 6, 4), (100, 70, 3, 3)]);
        }
    }

    /// The 8-bit tile flags from comparison bits equal "some sample of the channel in the tile's
    /// columns is >= thr".
    #[test]
    fn tile_flags_from_bits_match_a_direct_scan() {
        let mut r = Rng::new(8);
        for (w, ch) in [(1000usize, 3usize), (1000, 1), (64, 3), (33, 1), (97, 3), (50, 2)] {
            for density in [0u64, 1, 20, 500] {
                let row: Vec<u8> =
                    (0..w * ch).map(|_| if r.below(1000) < density { 230 } else { r.below(200) as u8 }).collect();
                let thr = 202u8;
                let ntx = w.div_ceil(TILE);
                let mut bits = vec![0u64; (w * ch).div_ceil(64)];
                crate::faults::kit::ge_mask_u8(&row, thr, &mut bits);
                let mut got = vec![false; ntx * ch];
                flag_tiles_from_bits(&bits, w, ch, &mut got);
                let want: Vec<bool> = (0..ntx * ch)
                    .map(|k| {
                        let (tx, c) = (k / ch, k % ch);
                        (tx * TILE..((tx + 1) * TILE).min(w)).any(|x| row[x * ch + c] >= thr)
                    })
                    .collect();
                assert_eq!(got, want, "w {w}, ch {ch}, density {density}");
            }
        }
    }

    #[test]
    fn rgb8_channel_gather_equals_a_strided_copy() {
        let row: Vec<u8> = (0..3 * TILE + 7).map(|i| (i * 7 + 3) as u8).collect();
        for c in 0..3 {
            for n in [TILE, 5, 31] {
                let mut got = vec![0u8; n];
                gather_rgb8(&row, c, &mut got);
                let want: Vec<u8> = (0..n).map(|x| row[3 * x + c]).collect();
                assert_eq!(got, want, "channel {c}, {n} pixels");
            }
        }
    }

    #[test]
    fn state_kept_across_frames_does_not_change_the_output() {
        // The pool keeps stale values between frames (acc, stamps of earlier fills): a reused
        // instance, one whose fill generation is about to wrap around, and a fresh one give the
        // same bytes, frame after frame, with different saturated regions per frame.
        let p = params(&[("full_well_fraction", 0.6), ("spread_px", 0.5), ("exposure_gain", 1.4)]);
        let frames: Vec<Frame> = [(60, 45, 30, 30), (10, 100, 20, 20), (90, 5, 40, 12)]
            .iter()
            .map(|&spot| scene(PixelFormat::Mono16, 160, 128, &[spot]))
            .collect();
        let mut reused = Blooming::default();
        // (Mono: channel 0's worker does the fill.)
        let mut wrapping =
            Blooming { chans: vec![Blooming { generation: u32::MAX - 3, ..Default::default() }], ..Default::default() };
        for _ in 0..2 {
            for f in &frames {
                let mut fresh_out = f.clone();
                let fresh = run(&mut fresh_out, &p);
                assert!(fresh.fallback_dn() > 0.0, "the fill runs (it uses the stamps)");
                for b in [&mut reused, &mut wrapping] {
                    let mut out = f.clone();
                    b.apply(&mut out, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                    assert!(out == fresh_out, "reused state changed the output");
                }
            }
        }
        assert!(wrapping.chans[0].generation < u32::MAX - 3, "the generation wrapped around");
    }

    #[test]
    fn large_overflow_uses_fallback_and_still_conserves() {
        // 30x30 block at 1.4 FS (background stays below W) with a small kernel: the excess needs a region
        // far larger than the kernel; the fallback finishes the job exactly.
        let b = check_charge(
            PixelFormat::Mono16,
            &[("full_well_fraction", 0.6), ("spread_px", 0.5), ("exposure_gain", 1.4)],
            &[(60, 45, 30, 30)],
        );
        // Inside the 30x30 block the diffused excess lands back on full pixels: diffusion stalls
        // after the first round and the breadth-first fill places the rest.
        assert!(b.rounds() < DIFFUSION_ROUNDS, "rounds {}", b.rounds());
        assert!(b.fallback_dn() > 1000.0, "the breadth-first fill placed the rest: {}", b.fallback_dn());
        // A small spot: every round makes progress, all rounds run.
        let small =
            check_charge(PixelFormat::Mono16, &[("full_well_fraction", 0.8), ("spread_px", 1.5)], &[(60, 45, 3, 3)]);
        assert_eq!(small.rounds(), DIFFUSION_ROUNDS);
        for axis in [1.0, 2.0] {
            check_charge(
                PixelFormat::Mono8,
                &[("full_well_fraction", 0.9), ("spread_px", 2.0), ("axis", axis), ("exposure_gain", 1.5)],
                &[(70, 60, 4, 4)],
            );
        }
    }

    #[test]
    fn vertical_axis_keeps_charge_in_its_columns() {
        // Background * 1.3 stays below W = 178.5; only the 3x5 spot (columns 40..43) overflows.
        let orig = scene(PixelFormat::Mono8, 96, 96, &[(40, 44, 3, 5)]);
        let mut f = orig.clone();
        run(&mut f, &params(&[("full_well_fraction", 0.7), ("axis", 1.0), ("exposure_gain", 1.3)]));
        let mut moved = 0;
        for y in 0..96 {
            for x in 0..96 {
                let scaled = (orig.get(x, y, 0) * 1.3 + 0.5).floor();
                if !(40..43).contains(&x) {
                    assert_eq!(f.get(x, y, 0), scaled, "x {x} y {y}: outside the spot's columns");
                } else if !(44..49).contains(&y) && f.get(x, y, 0) != scaled {
                    moved += 1;
                }
            }
        }
        assert!(moved >= 6, "charge moved along the columns ({moved} samples)");
    }

    #[test]
    fn zero_excess_is_identity_and_glow_brightens_around_glints() {
        let orig = scene(PixelFormat::Rgb8, 100, 80, &[(50, 40, 3, 3)]);
        let mut f = orig.clone();
        run(&mut f, &params(&[("full_well_fraction", 1.0)]));
        assert_eq!(f, orig, "W = FS: nothing can exceed the well");
        let plain = scene(PixelFormat::Mono8, 100, 80, &[]);
        let mut g = plain.clone();
        run(&mut g, &params(&[("full_well_fraction", 0.5)]));
        assert_eq!(g, plain, "no sample above W");

        let mut f = orig.clone();
        run(&mut f, &params(&[("mode", 1.0), ("full_well_fraction", 0.95), ("spread_px", 3.0), ("streak_px", 20.0)]));
        // Halo next to the glint, streak far above it in the same column, nothing far to the side.
        assert!(f.get(48, 41, 0) > orig.get(48, 41, 0) + 20.0);
        assert!(f.get(51, 10, 1) > orig.get(51, 10, 1) + 5.0);
        assert_eq!(f.get(10, 10, 2), orig.get(10, 10, 2));
    }

    #[test]
    fn charge_at_the_border_is_lost_not_created() {
        let orig = scene(PixelFormat::Mono8, 64, 64, &[(0, 0, 4, 4)]);
        let mut f = orig.clone();
        let b = run(&mut f, &params(&[("full_well_fraction", 0.7), ("spread_px", 2.0)]));
        assert!(b.lost_dn() > 1.0, "the kernel carries charge out of the frame");
        let changed = f.packed_samples_f32().iter().zip(orig.packed_samples_f32()).filter(|(a, b)| *a != b).count();
        // Kept + lost = initial, up to rounding.
        let bound = 0.5 * changed as f64 + 1e-3;
        assert!((sum(&f) + b.lost_dn() - sum(&orig)).abs() <= bound);
    }
}
