//! Veiling glare (`veiling_glare`) in diagnose: telling it from a uniform level (black-level
//! offset, or dark current when no dark frames are given) by its signature, and fitting it.
//!
//! Signature: glare is the scene convolved with a wide PSF, so the level of the *sky* of an
//! image rises where the glare that the image's own lit scene predicts is high: next to bright
//! sources, and more in images with more total flux. A uniform level lifts every sky cell alike.
//! Sky cells (on the coarse grid of [`crate::faults::veiling_glare::grid`]) are the flat,
//! unsaturated cells with no lit-scene pixel within one cell side: a pixel is lit scene when it
//! stands above the frame's background by a share of its dynamic range (see `scene_mask`), so
//! the target, the Earth and their blurred edges — scene albedo, which in earlier versions
//! passed as "background" and dominated the regression — are left out. The sources of the
//! predicted glare are the lit-scene pixels less the background (a uniform level is no source).
//! Per set, the sky levels (trimmed means) are regressed on the predicted glare `G = P * I`
//! (unit fraction): `level = c + f G`. Glare is `f` > 0 (real above sim); the intercept `c` is
//! the uniform part. Standard errors bootstrap the images, so the scatter between scenes counts
//! against `f`.
//!
//! Fit: the PSF shape (core radius, Moffat index) is the one of [`SHAPES`] whose pooled
//! regression explains the real sky levels best (largest R²); the fraction is fitted by moment
//! matching: the sims are pushed through the library's `veiling_glare` until their slope
//! equals the real one.

use super::img::{Plane, luma, planes_of};
use super::stats;
use super::types::{DiagnoseError, Signature};
use crate::faults::veiling_glare::{grid, kernel_shared};
use crate::faults::{Params, default_params};
use crate::frame::Frame;
use crate::rng::Rng;

/// PSF shapes tried: (core radius as a share of the frame's long side, Moffat index). Indices
/// below 1.5 are left out: outside the core the sky only sees the tail `f r0^(2β-2) r^(-2β)`,
/// and a flatter tail with a smaller core explains it as well (the regression cannot tell them
/// apart) while putting most of the scattered flux outside any frame.
pub const SHAPES: &[(f64, f64)] = &[
    (0.01, 1.5),
    (0.02, 1.5),
    (0.035, 1.5),
    (0.055, 1.5),
    (0.08, 1.5),
    (0.12, 1.5),
    (0.18, 1.5),
    (0.01, 2.0),
    (0.02, 2.0),
    (0.035, 2.0),
    (0.055, 2.0),
    (0.08, 2.0),
    (0.12, 2.0),
    (0.18, 2.0),
    (0.035, 2.5),
    (0.055, 2.5),
    (0.08, 2.5),
    (0.12, 2.5),
    (0.18, 2.5),
];
/// Share of a sky cell's samples trimmed at each end before its level is averaged (a star or
/// a hot pixel does not move the level; the mean of the rest is not quantised to whole DN).
const TRIM: f64 = 0.2;
/// Saturation level (8-bit DN): cells reaching it are sources, not background.
const SAT: f32 = 250.0;
/// Bootstrap replicates over images.
const BOOT: usize = 60;
/// Quantile of a frame taken as its background (sky) level, and as its bright level.
const BG_Q: f64 = 0.05;
const BRIGHT_Q: f64 = 0.995;
/// Share of the way from the background to the bright level above which a pixel belongs to
/// the lit scene (target, Earth), not the sky.
const SCENE_SHARE: f64 = 0.15;

/// Lit-scene mask of a frame as an integral image (`(w+1) x (h+1)` counts of scene pixels), the
/// frame's background level and the threshold (DN). A pixel is scene when it is above
/// `bg + max(2 flat_dn, SCENE_SHARE (bright − bg))`, `bg` and `bright` the frame's [`BG_Q`] and
/// [`BRIGHT_Q`] quantiles: lit surfaces stand far above the sky, while the glare next to them is
/// a few percent of their level (up to a quarter for the largest fraction the effect allows,
/// which then only widens the mask).
fn scene_mask(p: &Plane, flat_dn: f64) -> (Vec<u32>, f64, f64) {
    let (w, h) = (p.w, p.h);
    let mut v: Vec<f64> = p.data.iter().map(|&x| x as f64).collect();
    let bg = stats::quantile_mut(&mut v, BG_Q);
    let bright = stats::quantile_mut(&mut v, BRIGHT_Q);
    let thr = bg + (2.0 * flat_dn).max(SCENE_SHARE * (bright - bg));
    let mut ii = vec![0u32; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0u32;
        for x in 0..w {
            row += (p.data[y * w + x] as f64 > thr) as u32;
            ii[(y + 1) * (w + 1) + x + 1] = ii[y * (w + 1) + x + 1] + row;
        }
    }
    (ii, bg, thr)
}

/// Scene pixels in the box `[x0, x1) x [y0, y1)` (clamped to the frame) of an integral image.
fn count_in(ii: &[u32], w: usize, h: usize, x0: isize, y0: isize, x1: isize, y1: isize) -> u32 {
    let cl = |v: isize, m: usize| v.clamp(0, m as isize) as usize;
    let (x0, x1, y0, y1) = (cl(x0, w), cl(x1, w), cl(y0, h), cl(y1, h));
    let s = w + 1;
    ii[y1 * s + x1] + ii[y0 * s + x0] - ii[y0 * s + x1] - ii[y1 * s + x0]
}

/// Background cells of one image: (predicted glare at unit fraction, floor), both in DN.
pub fn background_cells(p: &Plane, core_share: f64, slope: f64, flat_dn: f64) -> Vec<(f64, f64)> {
    cells_against(p, p, core_share, slope, flat_dn)
}

/// Sky cells of the scene `p`: whole cells with no lit-scene pixel (see [`scene_mask`]) within
/// one cell side of them — the lit target, the Earth and their blurred edges are scene albedo,
/// not glare — no saturated pixel, and flat (10–90 % spread within `flat_dn`). Returns per sky
/// cell (glare that the lit scene of `p` — its pixels above the threshold, less the background —
/// predicts there at unit fraction, trimmed mean of `floor_of` in the
/// cell), both in DN.
pub fn cells_against(p: &Plane, floor_of: &Plane, core_share: f64, slope: f64, flat_dn: f64) -> Vec<(f64, f64)> {
    let (w, h) = (p.w, p.h);
    let (b, gw, gh) = grid(w, h);
    let core = (core_share * w.max(h) as f64).max(1.0);
    let k = kernel_shared(b, gw, gh, core, slope);
    let kw = 2 * gw - 1;
    let (mask, bg, thr) = scene_mask(p, flat_dn);
    let m = b as isize;
    let mut sums = vec![0f64; gw * gh];
    let mut floor = vec![f64::NAN; gw * gh];
    let mut vals = Vec::with_capacity(b * b);
    for cy in 0..gh {
        for cx in 0..gw {
            vals.clear();
            for y in cy * b..((cy + 1) * b).min(h) {
                for x in cx * b..((cx + 1) * b).min(w) {
                    vals.push(p.data[y * w + x] as f64);
                }
            }
            // The glare sources: the lit scene above the background. The sky itself is left out,
            // so a uniform level (offset, dark current) predicts no glare, and a sky cell's own
            // noise and glare do not enter its own prediction.
            sums[cy * gw + cx] = vals.iter().filter(|&&v| v > thr).map(|&v| v - bg).sum();
            let (x0, y0) = ((cx * b) as isize, (cy * b) as isize);
            let sky = count_in(&mask, w, h, x0 - m, y0 - m, x0 + 2 * m, y0 + 2 * m) == 0;
            // Whole sky cells only, without saturated pixels, flat (spread within `flat_dn`).
            if sky && vals.len() == b * b && vals.iter().all(|&v| v < SAT as f64) {
                let hi = stats::quantile_mut(&mut vals, 0.9);
                if hi - stats::quantile_mut(&mut vals, 0.1) <= flat_dn {
                    if !std::ptr::eq(p, floor_of) {
                        vals.clear();
                        for y in cy * b..(cy + 1) * b {
                            vals.extend(floor_of.data[y * w + cx * b..y * w + (cx + 1) * b].iter().map(|&v| v as f64));
                        }
                    }
                    floor[cy * gw + cx] = stats::trimmed_mean_mut(&mut vals, TRIM);
                }
            }
        }
    }
    let mut out = Vec::new();
    for oy in 0..gh {
        for ox in 0..gw {
            let f = floor[oy * gw + ox];
            if !f.is_finite() {
                continue;
            }
            let mut g = 0.0;
            for iy in 0..gh {
                let krow = &k[(iy + gh - 1 - oy) * kw + (gw - 1 - ox)..][..gw];
                for (s, kv) in sums[iy * gw..(iy + 1) * gw].iter().zip(krow) {
                    g += s * *kv as f64;
                }
            }
            out.push((g / (b * b) as f64, f));
        }
    }
    out
}

/// Pooled least squares `floor = c + f G` over the cells of some images: (f, c, R², mean G).
pub fn regress(cells: &[&[(f64, f64)]]) -> Option<(f64, f64, f64, f64)> {
    let (mut n, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for c in cells {
        for &(x, y) in c.iter() {
            n += 1.0;
            sx += x;
            sy += y;
        }
    }
    if n < 10.0 {
        return None;
    }
    let (mx, my) = (sx / n, sy / n);
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for c in cells {
        for &(x, y) in c.iter() {
            sxx += (x - mx) * (x - mx);
            sxy += (x - mx) * (y - my);
            syy += (y - my) * (y - my);
        }
    }
    if sxx <= 1e-12 {
        return None;
    }
    let f = sxy / sxx;
    let r2 = if syy > 0.0 { (sxy * sxy / (sxx * syy)).clamp(0.0, 1.0) } else { 0.0 };
    Some((f, my - f * mx, r2, mx))
}

fn refs(v: &[Vec<(f64, f64)>]) -> Vec<&[(f64, f64)]> {
    v.iter().map(|c| c.as_slice()).collect()
}

fn pick<'a>(v: &'a [Vec<(f64, f64)>], rng: &mut Rng) -> Vec<&'a [(f64, f64)]> {
    (0..v.len()).map(|_| v[(rng.uniform() * v.len() as f64) as usize % v.len()].as_slice()).collect()
}

/// Slope gap (real minus sim) with a bootstrap standard error over the images of both sets.
fn slope_gap(real: &[Vec<(f64, f64)>], sim: &[Vec<(f64, f64)>], seed: u64) -> Option<(f64, f64)> {
    let fr = regress(&refs(real))?.0;
    let fs = regress(&refs(sim)).map(|r| r.0).unwrap_or(0.0);
    let mut rng = Rng::new(seed ^ 0x61a2e);
    let mut reps = Vec::new();
    for _ in 0..BOOT {
        let (a, b) = (pick(real, &mut rng), pick(sim, &mut rng));
        if let Some(r) = regress(&a) {
            reps.push(r.0 - regress(&b).map(|r| r.0).unwrap_or(0.0));
        }
    }
    if reps.len() < 10 {
        return None;
    }
    let (m, _) = stats::mean_se(&reps);
    let se = (reps.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (reps.len() - 1) as f64).sqrt();
    Some((fr - fs, se))
}

/// Cells of every frame for one shape.
fn cells_of(frames: &[Frame], shape: (f64, f64), flat_dn: f64) -> Vec<Vec<(f64, f64)>> {
    frames.iter().map(|f| background_cells(&luma(&planes_of(f)), shape.0, shape.1, flat_dn)).collect()
}

/// What the glare test found.
pub struct GlareResult {
    pub sig: Signature,
    /// The fitted effect when detected.
    pub params: Option<Params>,
    pub method: String,
}

/// The unpaired glare test and fit. `apply` pushes frames through a config of the given
/// effects (the caller's fitted noise plus the candidate glare).
pub fn unpaired(
    real: &[Frame],
    sim: &[Frame],
    z_thr: f64,
    noise_sd: f64,
    seed: u64,
    apply: &mut dyn FnMut(Params) -> Result<Vec<Frame>, DiagnoseError>,
) -> Result<GlareResult, DiagnoseError> {
    /// Per image, the flat cells as `cells_of` returns them.
    type CellsPerImage = Vec<Vec<(f64, f64)>>;
    let mut sig = Signature::new("veiling_glare");
    sig.where_ =
        "flat sky cells of the real images (away from the lit scene), against the glare their own scenes predict"
            .into();
    let flat_dn = (6.0 * noise_sd).max(8.0);
    // Shape: the one that explains the real sky levels best.
    let mut best: Option<(f64, (f64, f64), CellsPerImage)> = None;
    for &shape in SHAPES {
        let rc = cells_of(real, shape, flat_dn);
        let refs: Vec<&[(f64, f64)]> = rc.iter().map(|c| c.as_slice()).collect();
        if let Some((_, _, r2, _)) = regress(&refs)
            && best.as_ref().is_none_or(|b| r2 > b.0)
        {
            best = Some((r2, shape, rc));
        }
    }
    let none = |sig: Signature| Ok(GlareResult { sig, params: None, method: String::new() });
    let Some((r2, shape, rc)) = best else {
        sig.evidence = "too few flat sky cells in the real images to regress their level on the scene".into();
        return none(sig);
    };
    let sc = cells_of(sim, shape, flat_dn);
    let Some((fr, cr, _, _)) = regress(&refs(&rc)) else { return none(sig) };
    let sfit = regress(&refs(&sc));
    let Some((gap, se)) = slope_gap(&rc, &sc, seed) else {
        sig.evidence = "too few images with sky cells for a bootstrap".into();
        return none(sig);
    };
    sig.z = if se > 0.0 { gap / se } else { 0.0 };
    // Size: the glare on the sky next to the sources (95th percentile of the predicted glare
    // over the real sky cells); the mean over the sky is diluted by the far, dark cells.
    let mut gs: Vec<f64> = rc.iter().flatten().map(|c| c.0).collect();
    let g95 = stats::quantile_mut(&mut gs, 0.95);
    sig.size = gap * g95;
    sig.size_unit = "DN glare on the sky next to the sources (fraction gap x 95th percentile of the predicted glare)";
    let (core_share, slope) = shape;
    let (fs, cs) = sfit.map(|s| (s.0, s.1)).unwrap_or((0.0, f64::NAN));
    sig.evidence = format!(
        "sky level = c + f x (lit scene * PSF) over {} real and {} sim sky cells: real f = {:.4} (c = {:.1} DN, R² = {:.2}), \
         sim f = {:.4} (c = {:.1} DN); gap {:.4} ± {:.4} (z = {:.1}); the floor follows the scene's flux and the distance to \
         bright sources (a uniform offset or dark current would give f = 0 and only raise c); PSF shape of best R²: \
         core {:.0} % of the long side, Moffat index {}",
        rc.iter().map(Vec::len).sum::<usize>(),
        sc.iter().map(Vec::len).sum::<usize>(),
        fr,
        cr,
        r2,
        fs,
        cs,
        gap,
        se,
        sig.z,
        100.0 * core_share,
        slope
    );
    sig.stderr.push(("fraction".into(), se));
    sig.detected = sig.z > z_thr && gap > 0.0 && sig.size >= 1.0;
    if !sig.detected {
        return none(sig);
    }
    // Moment matching of the fraction through the library effect.
    let long = real.iter().map(|f| f.width.max(f.height)).max().unwrap_or(1) as f64;
    let make = |fraction: f64| -> Option<Params> {
        let mut p = default_params("veiling_glare").ok()?;
        p.set("fraction", fraction.clamp(0.0, 0.5)).ok()?;
        p.set("core_px", (core_share * long).clamp(1.0, 2000.0)).ok()?;
        p.set("slope", slope).ok()?;
        Some(p)
    };
    let mut eval = |fraction: f64| -> f64 {
        let Some(p) = make(fraction) else { return f64::INFINITY };
        match apply(p) {
            Ok(fr_) => {
                let c = cells_of(&fr_, shape, flat_dn);
                regress(&refs(&c)).map(|r| (r.0 - fr).powi(2)).unwrap_or(f64::INFINITY)
            }
            Err(_) => f64::INFINITY,
        }
    };
    let hi = (3.0 * gap).clamp(1e-3, 0.5);
    let (fraction, _) = stats::golden(&mut eval, 0.0, hi, 14);
    sig.set_param("fraction", fraction);
    sig.set_param("core_px", core_share * long);
    sig.set_param("slope", slope);
    Ok(GlareResult {
        params: make(fraction),
        sig,
        method: "regression of sky levels on the lit scene convolved with the PSF (shape of best R²), fraction by \
                 moment matching through the library veiling_glare"
            .into(),
    })
}

/// Paired initial values: the residual level (real − sim) of the sky cells regressed on
/// the glare the sim's scene predicts, for every shape of [`SHAPES`]; the shape of best R².
/// Returns (fraction, core_px, slope, R²) when the slope is positive.
pub fn paired_init(pairs: &[super::img::Pair]) -> Option<(f64, f64, f64, f64)> {
    let mut best: Option<(f64, f64, f64, f64)> = None;
    for &(core_share, slope) in SHAPES {
        let mut all = Vec::new();
        let mut long = 1usize;
        for p in pairs.iter().take(4) {
            let (s, r) = (luma(&p.sim), luma(&p.real));
            long = long.max(s.w.max(s.h));
            all.push(cells_against(&s, &r.sub(&s), core_share, slope, 8.0));
        }
        let refs: Vec<&[(f64, f64)]> = all.iter().map(|c| c.as_slice()).collect();
        if let Some((f, _, r2, _)) = regress(&refs)
            && f > 0.0
            && best.is_none_or(|b| r2 > b.3)
        {
            best = Some((f, core_share * long as f64, slope, r2));
        }
    }
    best
}
