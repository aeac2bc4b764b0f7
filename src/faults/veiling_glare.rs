//! `veiling_glare`: scene-dependent veiling glare, the image convolved with a wide-angle
//! power-law (Moffat) point-spread function.
//!
//! Scattering in the optics (dust, surface roughness, internal reflections) spreads a small share
//! of every source's light over a wide, slowly falling halo: a bright target lifts the dark sky
//! around it, most near the target and in proportion to its flux. Unlike `stray_light` (a lobe
//! from a source outside the frame, independent of the scene), `dark_current` (thermal, present
//! in dark frames) or a black-level offset (`gain_offset`, uniform), this signal follows the
//! scene.
//!
//! Speed: the halo is smooth, so it is computed on a coarse grid of at most [`GRID`] cells on the
//! long side (cell flux = exact integer sum of the samples), convolved there with the
//! cell-integrated PSF (a direct sum over all cells: the kernel covers the whole frame, so no
//! truncation inside the frame), and interpolated back bilinearly from the cell centres. Every
//! output cell and pixel is computed independently in a fixed order: same bytes on any thread
//! count.

use super::kit::{accumulate_u32_row, add_lerp_runs_row, band_rows, bands, par_bands_with};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, Sample};
use crate::with_image_mut;
use rayon::prelude::*;
use std::sync::{Arc, Mutex};

pub static INFO: EffectInfo = EffectInfo {
    name: "veiling_glare",
    stage: Stage::Optics,
    order: 15,
    summary: "scene-dependent veiling glare: the image convolved with a wide power-law (Moffat) PSF",
    model: "v' = min(v + round(fraction * (P * v)), FS) per channel, with * the 2-D convolution and P the \
            Moffat PSF P(r) = (slope - 1) / (pi core_px^2) * (1 + r^2 / core_px^2)^(-slope) (r in px, \
            integral 1 over the plane; the tail falls as r^(-2 slope)). Additive: the direct image is kept \
            and `fraction` of each pixel's signal (DN, taken as linear) is added as a halo, so the glare \
            added to the frame is fraction x the scene's total signal, less what falls outside the frame \
            (for a source at the centre of a W x H frame at least 1 - (1 + (min(W, H)/2)^2 / core_px^2)^(1 - \
            slope) of it lands inside). The halo is strongest next to bright sources and scales with their \
            flux; clipped sources add glare for their clipped signal only. Computed on a grid of at most \
            48 cells on the long side (cell side b = ceil(max(W, H) / 48) px): cell sums, direct \
            convolution with the cell-integrated PSF over the whole frame, bilinear interpolation back \
            from the cell centres, so structure finer than about b is smoothed (the PSF core inside \
            one cell is spread over it). Glare from sources outside the field is `stray_light`. \
            fraction = 0 is the identity.",
    params: &[
        ParamSpec::float("fraction", "fraction", 0.0, 0.5, 0.02, "share of the signal scattered into the halo"),
        ParamSpec::float("core_px", "px", 1.0, 2000.0, 20.0, "Moffat core radius r0 of the PSF").log().extra(),
        ParamSpec::float("slope", "1", 1.05, 4.0, 1.5, "Moffat index beta: the tail falls as r^(-2 beta)").extra(),
    ],
    formats: ALL_FORMATS,
};

/// Most cells of the coarse grid on the long side of the frame.
pub const GRID: usize = 48;

pub fn create() -> Box<dyn Effect> {
    Box::new(VeilingGlare::default())
}

/// Moffat PSF density at radius² `r2` (px²): `(β-1)/(π r0²) (1 + r²/r0²)^-β`, integral 1.
pub fn moffat(r2: f64, core_px: f64, slope: f64) -> f64 {
    (slope - 1.0) / (std::f64::consts::PI * core_px * core_px) * (1.0 + r2 / (core_px * core_px)).powf(-slope)
}

/// Share of the PSF's flux within radius `r` px: `1 - (1 + r²/r0²)^(1-β)`.
pub fn enclosed(r: f64, core_px: f64, slope: f64) -> f64 {
    1.0 - (1.0 + r * r / (core_px * core_px)).powf(1.0 - slope)
}

/// Geometry of the coarse grid for a frame: cell side `b` px, `gw` x `gh` cells.
pub fn grid(w: usize, h: usize) -> (usize, usize, usize) {
    let b = w.max(h).div_ceil(GRID).max(1);
    (b, w.div_ceil(b), h.div_ceil(b))
}

/// Cell-integrated PSF for cell offsets `dx` in `-(gw-1)..=gw-1`, `dy` in `-(gh-1)..=gh-1`
/// (row-major, `(2gw-1) x (2gh-1)`): midpoint rule on 8 x 8 sub-cells (32 x 32 next to the
/// centre); the central cell takes the analytic share of a disc of the same area.
pub fn kernel(b: usize, gw: usize, gh: usize, core_px: f64, slope: f64) -> Vec<f32> {
    let (kw, kh) = (2 * gw - 1, 2 * gh - 1);
    let bf = b as f64;
    let mut k = vec![0f32; kw * kh];
    // Every cell is computed on its own (rows in parallel): the values do not depend on threads.
    k.par_chunks_mut(kw).enumerate().for_each(|(j, row)| {
        let dy = j as f64 - (gh - 1) as f64;
        for i in 0..kw {
            let dx = i as f64 - (gw - 1) as f64;
            let v = if dx == 0.0 && dy == 0.0 {
                enclosed(bf / std::f64::consts::PI.sqrt(), core_px, slope)
            } else {
                let n = if dx.abs() <= 1.0 && dy.abs() <= 1.0 { 32 } else { 8 };
                let s = bf / n as f64;
                let mut acc = 0.0;
                for sy in 0..n {
                    let y = dy * bf - bf / 2.0 + (sy as f64 + 0.5) * s;
                    for sx in 0..n {
                        let x = dx * bf - bf / 2.0 + (sx as f64 + 0.5) * s;
                        acc += moffat(x * x + y * y, core_px, slope);
                    }
                }
                acc * s * s
            };
            row[i] = v as f32;
        }
    });
    k
}

/// Kernels built recently, shared by every instance: `faultcam diagnose` fits the effect through
/// many fresh instances and its searches revisit the same core sizes. Keyed by the exact
/// arguments of [`kernel`], so a hit is the very kernel [`kernel`] returns.
type KernelKey = (usize, usize, usize, u64, u64);
static KERNEL_CACHE: Mutex<Vec<(KernelKey, Arc<[f32]>)>> = Mutex::new(Vec::new());
/// Kernels kept (at most 95 x 95 cells each: 36 KB).
const KERNEL_CACHE_LEN: usize = 32;

/// [`kernel`] through the shared cache (most recently used last; the oldest is dropped).
pub fn kernel_shared(b: usize, gw: usize, gh: usize, core_px: f64, slope: f64) -> Arc<[f32]> {
    let key = (b, gw, gh, core_px.to_bits(), slope.to_bits());
    {
        let mut cache = KERNEL_CACHE.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(pos) = cache.iter().position(|(k, _)| *k == key) {
            let hit = cache.remove(pos);
            let k = hit.1.clone();
            cache.push(hit);
            return k;
        }
    }
    // Built outside the lock (another thread may build the same kernel meanwhile: same values).
    let k: Arc<[f32]> = kernel(b, gw, gh, core_px, slope).into();
    let mut cache = KERNEL_CACHE.lock().unwrap_or_else(|e| e.into_inner());
    if !cache.iter().any(|(c, _)| *c == key) {
        if cache.len() >= KERNEL_CACHE_LEN {
            cache.remove(0);
        }
        cache.push((key, k.clone()));
    }
    k
}

#[derive(Default)]
pub struct VeilingGlare {
    key: Option<(usize, usize, usize, [u64; 2])>,
    // allocation: once per (size, shape parameters)
    kern: Arc<[f32]>,
    // allocation: once per frame size
    /// Cell sums (`[cell row][channel][cell column]`), their values as f32 planar per channel
    /// (`ch` planes of `gw x gh`), and whether a cell row of a channel is all 0.
    sums: Vec<u64>,
    cells: Vec<f32>,
    row_nonzero: Vec<bool>,
    /// Glare density per pixel at the cell centres (DN), planar per channel.
    glare: Vec<f32>,
    /// The columns as runs between cell centres: (first column, end column, left cell), and
    /// each column's weight of the right cell, once per sample (`w x ch`), contiguous.
    runs: Vec<(u32, u32, u32)>,
    tx: Vec<f32>,
    /// Per band: one interpolated cell row (gw x ch, channels interleaved).
    scratch: Vec<f32>,
}

/// Sum of `a[i] * b[i]` in a fixed order (8 partial sums, then combined): vectorises, and the
/// result does not depend on threads.
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..8 {
            acc[l] += x[l] * y[l];
        }
    }
    let mut s = ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

impl VeilingGlare {
    fn prepare(&mut self, w: usize, h: usize, ch: usize, core: f64, slope: f64) {
        let key = (w, h, ch, [core.to_bits(), slope.to_bits()]);
        if self.key == Some(key) {
            return;
        }
        let (b, gw, gh) = grid(w, h);
        self.kern = kernel_shared(b, gw, gh, core, slope);
        self.sums = vec![0; gw * gh * ch];
        self.cells = vec![0.0; gw * gh * ch];
        self.row_nonzero = vec![false; gh * ch];
        self.glare = vec![0.0; gw * gh * ch];
        self.tx.clear();
        self.runs.clear();
        for x in 0..w {
            let (c0, tx) = interp(x, b, gw);
            self.tx.extend(std::iter::repeat_n(tx, ch));
            match self.runs.last_mut() {
                Some(r) if r.2 == c0 => r.1 = x as u32 + 1,
                _ => self.runs.push((x as u32, x as u32 + 1, c0)),
            }
        }
        self.scratch = vec![0.0; gw * ch * bands(h)];
        self.key = Some(key);
    }
}

/// Bilinear position of pixel `x` between cell centres: (left cell, weight of the right cell).
fn interp(x: usize, b: usize, n: usize) -> (u32, f32) {
    let u = ((x as f64 + 0.5) / b as f64 - 0.5).clamp(0.0, (n - 1) as f64);
    let i0 = (u.floor() as usize).min(n.saturating_sub(2));
    (i0 as u32, (u - i0 as f64) as f32)
}

/// Samples per block of [`cell_sums`]: column sums of a block of a cell row are kept on the stack.
const SUM_BLOCK: usize = 1536;

/// Cell sums of the frame, `[cell row][channel][cell column]`. Parallel over cell rows; each
/// cell row is summed in blocks of columns: the rows' samples are added column by column into
/// u32 column sums (vectorised), which are then added up per cell and channel (exact integer
/// sums: the values do not depend on the order).
fn cell_sums<T: Sample>(data: &[T], stride: usize, w: usize, h: usize, ch: usize, b: usize, sums: &mut [u64]) {
    let (gw, gh) = (w.div_ceil(b), h.div_ceil(b));
    sums[..gw * gh * ch].par_chunks_mut(gw * ch).enumerate().for_each(|(cy, row)| {
        row.fill(0);
        let (y0, y1) = (cy * b, ((cy + 1) * b).min(h));
        let mut col = [0u32; SUM_BLOCK];
        let mut x = 0;
        while x < w {
            let xe = (x + SUM_BLOCK / ch).min(w);
            let acc = &mut col[..(xe - x) * ch];
            acc.fill(0);
            // A column's sum over a cell row fits a u32 (b < 65536 px of at most 65535).
            for y in y0..y1 {
                accumulate_u32_row(acc, &data[y * stride + x * ch..][..(xe - x) * ch]);
            }
            let mut px = x;
            while px < xe {
                let cx = px / b;
                let pe = ((cx + 1) * b).min(xe);
                for c in 0..ch {
                    let s: u64 = acc[(px - x) * ch + c..(pe - x) * ch].iter().step_by(ch).map(|&v| v as u64).sum();
                    row[c * gw + cx] += s;
                }
                px = pe;
            }
            x = xe;
        }
    });
}

fn add_glare<T: Sample>(
    data: &mut [T],
    stride: usize,
    (w, h, ch, b, gw): (usize, usize, usize, usize, usize),
    glare: &[f32],
    (runs, tx): (&[(u32, u32, u32)], &[f32]),
    scratch: &mut [f32],
) {
    let gh = h.div_ceil(b);
    let plane = gw * gh;
    par_bands_with(data, stride, h, scratch, gw * ch, |_, y0, band, cellrow| {
        for (i, row) in band_rows(band, stride, w * ch).enumerate() {
            let (r0, ty) = interp(y0 + i, b, gh);
            let r1 = (r0 as usize + 1).min(gh - 1);
            for c in 0..ch {
                let a = &glare[c * plane + r0 as usize * gw..][..gw];
                let z = &glare[c * plane + r1 * gw..][..gw];
                for (o, (p, q)) in cellrow.iter_mut().skip(c).step_by(ch).zip(a.iter().zip(z)) {
                    *o = p + ty * (q - p);
                }
            }
            // The row's glare, p + tx (q - p) between the two nearest cell centres, run by run
            // (p and q - p are the same for every column of a run), added to the samples as it
            // is computed. v is whole, so rounding v + g rounds the glare half up (as sample
            // rounding does).
            add_lerp_runs_row(row, tx, runs, cellrow, ch);
        }
    });
}

/// Output cell row `oy` of one channel of the grid convolution: `out[ox] = scale * sum over the
/// nonzero input rows iy (in order) of dot(cells row iy, K(iy - oy, . - ox))`, each dot as
/// [`dot`] computes it. On AVX2 CPUs four outputs at a time ([`conv4_avx2`]: their dots
/// interleaved, each in its own fixed order, so the same values), the rest one at a time.
fn conv_row(out: &mut [f32], cells: &[f32], kern: &[f32], nz: &[bool], oy: usize, scale: f32) {
    let (gw, gh) = (out.len(), nz.len());
    let kw = 2 * gw - 1;
    #[allow(unused_mut)]
    let mut ox = 0;
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        ox = unsafe { conv4_avx2(out, cells, kern, nz, oy, scale) };
    }
    for (ox, o) in out.iter_mut().enumerate().skip(ox) {
        let mut acc = 0f32;
        for iy in 0..gh {
            if !nz[iy] {
                continue;
            }
            // K(o - i) for ix = 0..gw: the PSF is symmetric, so K(o - i) = K(i - o), a
            // contiguous run of the kernel row dy = iy - oy from dx = -ox.
            let krow = &kern[(iy + gh - 1 - oy) * kw + (gw - 1 - ox)..][..gw];
            acc += dot(&cells[iy * gw..][..gw], krow);
        }
        *o = acc * scale;
    }
}

/// The four-output groups of [`conv_row`] on AVX2 (returns the outputs done, a multiple of 4):
/// lane l of output j's register is [`dot`]'s partial sum l; the partial sums are combined as
/// `((l0 + l4) + (l1 + l5)) + ((l2 + l6) + (l3 + l7))` (two `hadd`s pair them so), then the
/// remainder products are added in order, then the dot to the output's sum: [`dot`]'s values.
///
/// # Safety
/// AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn conv4_avx2(out: &mut [f32], cells: &[f32], kern: &[f32], nz: &[bool], oy: usize, scale: f32) -> usize {
    use std::arch::x86_64::*;
    let (gw, gh) = (out.len(), nz.len());
    let kw = 2 * gw - 1;
    let n8 = gw / 8 * 8;
    let mut ox = 0;
    while ox + 4 <= gw {
        let mut acc = _mm_setzero_ps();
        for iy in 0..gh {
            if !nz[iy] {
                continue;
            }
            let a = &cells[iy * gw..][..gw];
            let base = (iy + gh - 1 - oy) * kw + (gw - 1 - ox);
            // Rows base - j .. base - j + gw lie inside the kernel (base >= 3: ox + 4 <= gw).
            let k = &kern[base - 3..base + gw];
            let mut v = [_mm256_setzero_ps(); 4];
            let mut i = 0;
            while i < n8 {
                // SAFETY: i + 8 <= gw: inside a (gw long) and k (gw + 3 long, row j at 3 - j).
                unsafe {
                    let x = _mm256_loadu_ps(a.as_ptr().add(i));
                    for (j, vj) in v.iter_mut().enumerate() {
                        let y = _mm256_loadu_ps(k.as_ptr().add(3 - j + i));
                        *vj = _mm256_add_ps(*vj, _mm256_mul_ps(x, y));
                    }
                }
                i += 8;
            }
            let e = v.map(|r| _mm_add_ps(_mm256_castps256_ps128(r), _mm256_extractf128_ps(r, 1)));
            let mut s = _mm_hadd_ps(_mm_hadd_ps(e[0], e[1]), _mm_hadd_ps(e[2], e[3]));
            for i in n8..gw {
                let y = _mm_setr_ps(k[3 + i], k[2 + i], k[1 + i], k[i]);
                s = _mm_add_ps(s, _mm_mul_ps(_mm_set1_ps(a[i]), y));
            }
            acc = _mm_add_ps(acc, s);
        }
        let r = _mm_mul_ps(acc, _mm_set1_ps(scale));
        // SAFETY: ox + 4 <= gw = out.len().
        unsafe { _mm_storeu_ps(out.as_mut_ptr().add(ox), r) };
        ox += 4;
    }
    ox
}

impl Effect for VeilingGlare {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let f = p.get("fraction");
        if f == 0.0 {
            return Ok(Outcome::Keep);
        }
        let (w, h, ch, stride) = (frame.width as usize, frame.height as usize, frame.channels(), frame.stride);
        self.prepare(w, h, ch, p.get("core_px"), p.get("slope"));
        let (b, gw, gh) = grid(w, h);
        with_image_mut!(frame, img => cell_sums(img.data, stride, w, h, ch, b, &mut self.sums));
        // Cell fluxes as f32 (relative error 6e-8: far below one DN of glare), and which cell
        // rows carry any signal (dark sky rows are skipped in the convolution).
        let plane = gw * gh;
        for c in 0..ch {
            for cy in 0..gh {
                let src = &self.sums[(cy * ch + c) * gw..][..gw];
                for (cell, &s) in self.cells[c * plane + cy * gw..][..gw].iter_mut().zip(src) {
                    *cell = s as f32;
                }
                self.row_nonzero[c * gh + cy] = src.iter().any(|&s| s != 0);
            }
        }
        // Glare density at each cell centre: fraction / b² * sum_i S_i K(o - i). Parallel over
        // output cell rows; each output is a fixed-order sum.
        let scale = (f / (b * b) as f64) as f32;
        let (kern, cells, nz) = (&self.kern, &self.cells, &self.row_nonzero);
        self.glare.par_chunks_mut(gw).enumerate().for_each(|(k, out)| {
            let (c, oy) = (k / gh, k % gh);
            conv_row(out, &cells[c * plane..][..plane], kern, &nz[c * gh..][..gh], oy, scale);
        });
        let (glare, scratch) = (&self.glare, &mut self.scratch);
        let cols = (&self.runs[..], &self.tx[..]);
        with_image_mut!(frame, img => add_glare(img.data, stride, (w, h, ch, b, gw), glare, cols, scratch));
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn apply(f: &mut Frame, fraction: f64, core: f64, slope: f64) {
        let mut p = Params::defaults(&INFO);
        p.set("fraction", fraction).unwrap();
        p.set("core_px", core).unwrap();
        p.set("slope", slope).unwrap();
        VeilingGlare::default().apply(f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
    }

    /// The grid convolution's kernels (AVX2 four-output groups, the rest one at a time) give
    /// every output exactly the value of the one-at-a-time [`dot`] sum, on odd grid sizes
    /// (partial 8-lane chunks, groups of four with a tail) and with skipped (all-zero) rows.
    #[test]
    fn conv_rows_equal_the_one_at_a_time_sums() {
        let mut rng = crate::rng::Rng::new(11);
        for (gw, gh) in
            [(1usize, 1usize), (3, 2), (4, 5), (7, 3), (8, 8), (9, 4), (13, 7), (17, 11), (48, 30), (48, 27)]
        {
            let kern = kernel(7, gw, gh, 9.0, 1.7);
            let cells: Vec<f32> = (0..gw * gh).map(|_| rng.uniform_f32() * 4000.0).collect();
            let nz: Vec<bool> = (0..gh).map(|i| i % 3 != 1).collect();
            let kw = 2 * gw - 1;
            for oy in 0..gh {
                let mut got = vec![0f32; gw];
                conv_row(&mut got, &cells, &kern, &nz, oy, 0.37);
                for (ox, &g) in got.iter().enumerate() {
                    let mut acc = 0f32;
                    for iy in (0..gh).filter(|&iy| nz[iy]) {
                        acc += dot(&cells[iy * gw..][..gw], &kern[(iy + gh - 1 - oy) * kw + (gw - 1 - ox)..][..gw]);
                    }
                    assert_eq!((acc * 0.37).to_bits(), g.to_bits(), "gw {gw} gh {gh} oy {oy} ox {ox}");
                }
            }
        }
    }

    /// The shared kernel is the kernel: a miss builds it, a hit returns the same allocation, and
    /// arguments that differ in any bit get their own kernel (the cache is keyed exactly).
    #[test]
    fn shared_kernels_are_the_kernels_of_their_exact_arguments() {
        let (b, gw, gh) = grid(200, 120);
        let core = 17.123456789;
        let a = kernel_shared(b, gw, gh, core, 1.7);
        assert_eq!(&a[..], &kernel(b, gw, gh, core, 1.7)[..]);
        let again = kernel_shared(b, gw, gh, core, 1.7);
        assert!(Arc::ptr_eq(&a, &again), "a hit returns the cached kernel");
        let next = f64::from_bits(core.to_bits() + 1);
        let c = kernel_shared(b, gw, gh, next, 1.7);
        assert!(!Arc::ptr_eq(&a, &c));
        assert_eq!(&c[..], &kernel(b, gw, gh, next, 1.7)[..]);
        // More kernels than the cache keeps: every one is still its own kernel.
        for i in 0..(KERNEL_CACHE_LEN + 3) {
            let core = 5.0 + i as f64;
            assert_eq!(&kernel_shared(b, gw, gh, core, 2.0)[..], &kernel(b, gw, gh, core, 2.0)[..]);
        }
        assert!(KERNEL_CACHE.lock().unwrap().len() <= KERNEL_CACHE_LEN);
    }

    /// A square `side` px source of `value` at (cx, cy) on a black Mono16 frame.
    fn source(w: u32, h: u32, cx: usize, cy: usize, side: usize, value: f32) -> Frame {
        let mut f = Frame::new(w, h, PixelFormat::Mono16).unwrap();
        for y in cy - side / 2..cy - side / 2 + side {
            for x in cx - side / 2..cx - side / 2 + side {
                f.set(x, y, 0, value);
            }
        }
        f
    }

    fn added(a: &Frame, b: &Frame) -> Vec<f64> {
        a.packed_samples_f32().iter().zip(b.packed_samples_f32()).map(|(x, y)| (x - y) as f64).collect()
    }

    #[test]
    fn the_psf_integrates_to_one() {
        // Kernel over a grid much larger than the PSF: the sum is the enclosed share of the
        // largest inscribed disc or more, and at most 1 (+1 %: the midpoint rule next to the
        // PSF's core and the disc standing in for the central square).
        for (core, slope) in [(3.0, 2.5), (10.0, 1.5), (2.0, 1.2)] {
            let k = kernel(4, 80, 80, core, slope);
            let s: f64 = k.iter().map(|&v| v as f64).sum();
            assert!(s <= 1.01 && s >= enclosed(316.0, core, slope) - 0.01, "core {core} slope {slope}: sum {s}");
        }
    }

    #[test]
    fn zero_fraction_is_identity_and_glare_only_adds() {
        let orig = crate::faults::kit::bench_scene(96, 64, PixelFormat::Rgb8, 3).unwrap();
        let mut f = orig.clone();
        apply(&mut f, 0.0, 20.0, 1.5);
        assert_eq!(f, orig);
        apply(&mut f, 0.1, 20.0, 1.5);
        assert!(f.as_u8().unwrap().iter().zip(orig.as_u8().unwrap()).all(|(a, b)| a >= b));
        assert_ne!(f, orig);
    }

    #[test]
    fn added_glare_is_the_fraction_of_the_flux_that_lands_in_the_frame() {
        // A 16 x 16 px source at the centre of a 384 x 384 frame. Whatever the PSF, the added
        // signal lies between fraction x flux x (share of the PSF inside the inscribed disc) and
        // fraction x flux (all of it); with a steep tail both bounds are within 0.1 % of
        // fraction x flux. Tolerance 2 %: the coarse-grid kernel (midpoint rule), bilinear
        // interpolation and whole-DN rounding.
        let (w, h) = (384u32, 384u32);
        let orig = source(w, h, 192, 192, 16, 60000.0);
        let flux: f64 = orig.packed_samples_f32().iter().map(|&v| v as f64).sum();
        for (fraction, core, slope) in [(0.1, 6.0, 2.5), (0.05, 10.0, 1.5), (0.2, 30.0, 1.2)] {
            let mut f = orig.clone();
            apply(&mut f, fraction, core, slope);
            let got: f64 = added(&f, &orig).iter().sum();
            let lo = fraction * flux * enclosed(184.0, core, slope);
            let hi = fraction * flux;
            assert!(
                got >= lo * 0.98 && got <= hi * 1.02,
                "fraction {fraction} core {core} slope {slope}: {got} not in [{lo}, {hi}]"
            );
        }
    }

    #[test]
    fn radial_profile_follows_the_psf_around_a_point_source() {
        // Mean added signal on 4 px wide rings around a small source against fraction x flux x
        // PSF density at that radius: within 12 % plus 0.5 DN (each pixel's glare is rounded to
        // whole DN, so rings where the glare is a few DN carry up to half a DN of bias).
        let (w, h) = (480u32, 480u32);
        let (cx, cy) = (240usize, 240usize);
        let orig = source(w, h, cx, cy, 8, 65000.0);
        let flux = 64.0 * 65000.0;
        for (core, slope) in [(20.0, 1.5), (40.0, 2.0), (8.0, 1.2)] {
            let mut f = orig.clone();
            apply(&mut f, 0.5, core, slope);
            let d = added(&f, &orig);
            let ring = |r: f64| -> f64 {
                let (mut s, mut n) = (0.0, 0.0);
                for y in 0..h as usize {
                    for x in 0..w as usize {
                        let rr = ((x as f64 - cx as f64 + 0.5).powi(2) + (y as f64 - cy as f64 + 0.5).powi(2)).sqrt();
                        if (rr - r).abs() < 2.0 {
                            s += d[y * w as usize + x];
                            n += 1.0;
                        }
                    }
                }
                s / n
            };
            // From 4.5 cells (b = 10 px) out: closer in, the cell-integrated core is smoothed.
            for r in [45.0, 60.0, 90.0, 130.0, 180.0, 230.0] {
                let want = 0.5 * flux * moffat(r * r, core, slope);
                let got = ring(r);
                assert!(
                    (got - want).abs() <= 0.12 * want + 0.5,
                    "core {core} slope {slope} r {r}: ring {got:.3} DN, PSF {want:.3} DN"
                );
            }
        }
    }

    #[test]
    fn glare_grows_with_the_fraction_and_with_the_source_flux() {
        let orig = source(200, 160, 100, 80, 10, 30000.0);
        let brighter = source(200, 160, 100, 80, 10, 60000.0);
        let mut last = 0.0;
        // Whole-DN rounding makes faint glare nonlinear: the flux check uses glare of many DN.
        for fraction in [0.01, 0.05, 0.2, 0.5] {
            let mut f = orig.clone();
            apply(&mut f, fraction, 20.0, 1.5);
            let s: f64 = added(&f, &orig).iter().sum();
            assert!(s > last, "fraction {fraction}: {s} after {last}");
            last = s;
            let mut g = brighter.clone();
            apply(&mut g, fraction, 20.0, 1.5);
            let t: f64 = added(&g, &brighter).iter().sum();
            if fraction >= 0.2 {
                assert!((t / s - 2.0).abs() < 0.03, "glare is linear in the flux: {t} vs 2 x {s}");
            }
        }
    }

    #[test]
    fn same_bytes_on_one_and_two_threads() {
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
            let orig = crate::faults::kit::bench_scene(301, 187, format, 5).unwrap();
            let run = |t: usize| {
                rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap().install(|| {
                    let mut f = orig.clone();
                    apply(&mut f, 0.05, 15.0, 1.6);
                    f
                })
            };
            let one = run(1);
            assert_ne!(one, orig);
            assert!(one == run(2), "{format}");
        }
    }
}
