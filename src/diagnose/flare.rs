//! Lens flare (`lens_flare`) in diagnose: a matched search for ghost plateaus on the line from
//! the brightest source through the image centre.
//!
//! Physics (EFFECTS.md): ghosts are additive plateaus (images of the aperture: a disc or a
//! polygon, with soft edges) centred on the line from the source s through the optical centre
//! c, at points c + t (s − c) whose `t` are fixed by the lens; their levels are proportional to
//! the source, and `intensity` is their mean plateau / FS.
//!
//! The source is the brightest blob of the sim: the 8-connected pixels of luma ≥ 0.95 FS with the
//! largest flux above that level (on a star field the saturated star with the largest saturated
//! area, not the centroid of all bright pixels, which many small saturated stars pull towards the
//! centre). Along the line the residual (real − photometric prediction, channel mean) is scanned
//! with plateau templates: a core disc of radius 0.8 ρ against a ring ρ + 2 .. ρ + 2 + max(4,
//! 0.4 ρ) around it, for ρ from 1.2 % to 6.8 % of the diagonal (steps of about 19 %), one position per pixel of line.
//! Pixels are weighted by the inverse of the noise model's variance at their predicted level
//! (the residual of a bright star weighs little), standardised residuals are clipped at ±5, pixels
//! near saturation (10 px) or next to a sim edge (3 px) are left out, and so are templates whose
//! core and ring see different scene levels (sim means more than 4 DN apart: a residual that
//! follows the scene, e.g. a tone mismatch on a lit panel, is not a ghost). Column and row offsets
//! (smear, row noise) are removed first where a column's or row's median residual differs from
//! zero by more than 6 standard errors. Frames are combined at the same `t` (ghosts move with the
//! source, their `t` does not). The z of each template comes from the noise model, scaled by the
//! robust spread of the same statistic on control lines through the centre at other angles (their
//! part near the centre, which every line shares, left out).
//!
//! Ghosts are picked greedily by z (each above the threshold and above the control lines' largest
//! z, not overlapping one picked before); each ghost's plateau is read again on its inner part
//! (0.6 ρ) against a ring clear of its edge (1.25 ρ + 3 px outwards), at the most significant
//! position within ρ/2 along the line, weighted over the frames. `intensity` = the mean plateau of the ghosts found / FS, `ghosts` = their number.

use super::common::{Masks, NoiseModel};
use super::img::{FS, Pair, Plane, luma};
use super::stats;
use super::types::{Profile, Signature};
use rayon::prelude::*;

/// Signature parameter holding the ghosts' plateau / FS (not a library parameter, so the fit's
/// initial values do not see it; the report's `intensity` is this reading).
pub const PLATEAU_PARAM: &str = "plateau_intensity";
/// Signature parameter holding the number of ghosts found (the report's `ghosts`).
pub const COUNT_PARAM: &str = "ghosts_found";

/// Template radii as shares of the image diagonal.
const RADII: &[f64] = &[0.012, 0.0145, 0.017, 0.02, 0.024, 0.029, 0.034, 0.04, 0.048, 0.057, 0.068];
/// Line parameter range scanned (centre 0, source 1).
const U_MIN: f64 = -1.8;
const U_MAX: f64 = 0.85;
/// Largest difference (DN) of the sim's mean level between a template's core and ring (beyond
/// it a ghost's plateau cannot be told from a residual that follows the scene).
const MAX_SCENE_STEP: f64 = 40.0;
/// Smallest weighted variance (DN²) of the scene level within a template's regions for the
/// scene-proportional residual to be fitted.
const MIN_SCENE_SPREAD: f64 = 4.0;
/// Pixels this close to saturation (px) or to a sim edge are not used.
const SAT_MARGIN: f32 = 10.0;
const EDGE_MARGIN: f32 = 1.5;
/// Shares of a template's core and ring pixels that must be valid: in the scan, and when a ghost's
/// plateau is read (a ghost half over the scene or a masked region is found but not read).
const SCAN_COVER: f64 = 0.4;
const READ_COVER: f64 = 0.7;
/// Clip of standardised residuals.
const CLIP: f32 = 5.0;
/// Control line angles (degrees from the source direction).
const CONTROL_DEG: &[f64] = &[35.0, 70.0, 105.0, 140.0];
/// Practical floor of the plateau (share of FS), as the selection's floor for `intensity`.
pub const MIN_INTENSITY: f64 = 0.003;

/// Brightest source of a frame (luma of the sim): flux-weighted centroid of the 8-connected
/// blob of pixels ≥ 0.95 FS with the largest flux above that level.
pub fn brightest_source(lum: &Plane) -> Option<(f64, f64)> {
    let (w, h) = (lum.w, lum.h);
    let thr = 0.95 * FS;
    let hot = |i: usize| lum.data[i] >= thr;
    let mut seen = vec![false; w * h];
    let mut stack = Vec::new();
    let mut best: Option<(f64, f64, f64)> = None;
    for i0 in 0..w * h {
        if seen[i0] || !hot(i0) {
            continue;
        }
        seen[i0] = true;
        stack.push(i0);
        let (mut f, mut sx, mut sy) = (0.0, 0.0, 0.0);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            let wt = (lum.data[i] - thr) as f64 + 1.0;
            f += wt;
            sx += wt * x as f64;
            sy += wt * y as f64;
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    let j = yy * w + xx;
                    if !seen[j] && hot(j) {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        if best.is_none_or(|b| f > b.0) {
            best = Some((f, sx / f, sy / f));
        }
    }
    best.map(|b| (b.1, b.2))
}

/// Row prefix sums of one frame, per pixel: weight w, w·r (residual), w·s (predicted level),
/// w·s², w·r·s, and the count of valid pixels.
struct Sums {
    w: usize,
    h: usize,
    p: [Vec<f64>; NS],
}

/// Number of prefix-summed quantities.
const NS: usize = 6;

/// Sums over a disc of radius `r` at (`x`, `y`): (Σw, Σwr, Σws, Σws², Σwrs, n).
fn disc(s: &Sums, x: f64, y: f64, r: f64) -> [f64; NS] {
    let mut out = [0.0; NS];
    let y0 = (y - r).ceil().max(0.0) as isize;
    let y1 = (y + r).floor().min(s.h as f64 - 1.0) as isize;
    let st = s.w + 1;
    for yy in y0..=y1 {
        let dy = yy as f64 - y;
        let half = (r * r - dy * dy).max(0.0).sqrt();
        let xa = (x - half).ceil().max(0.0);
        let xb = (x + half).floor().min(s.w as f64 - 1.0);
        if xb < xa {
            continue;
        }
        let (a, b) = (yy as usize * st + xa as usize, yy as usize * st + xb as usize + 1);
        for (o, p) in out.iter_mut().zip(&s.p) {
            *o += p[b] - p[a];
        }
    }
    out
}

/// Plateau excess of a template: (core − ring, its variance) or `None` when fewer than `cover` of
/// the core's or the ring's pixels are valid or its core and ring see scene levels too far apart. A residual proportional
/// to the scene level (a gain or tone mismatch: r = β s) is fitted together with the two levels
/// (weighted least squares of r = m_c [core] + m_r [ring] + β s) when the levels within the
/// template spread enough to tell it; a ghost adds the same to every pixel whatever the scene.
fn template(s: &Sums, x: f64, y: f64, core_r: f64, ring: (f64, f64), cover: f64) -> Option<(f64, f64)> {
    let (ring_in, ring_out) = ring;
    let c = disc(s, x, y, core_r);
    let i = disc(s, x, y, ring_in);
    let o = disc(s, x, y, ring_out);
    let ring: [f64; NS] = std::array::from_fn(|k| o[k] - i[k]);
    let pi = std::f64::consts::PI;
    let (ac, ar) = (pi * core_r * core_r, pi * (ring_out * ring_out - ring_in * ring_in));
    if c[5] < cover * ac || ring[5] < cover * ar || c[0] <= 0.0 || ring[0] <= 0.0 {
        return None;
    }
    let (mc, mr) = (c[2] / c[0], ring[2] / ring[0]);
    if (mc - mr).abs() > MAX_SCENE_STEP {
        return None;
    }
    let simple = (c[1] / c[0] - ring[1] / ring[0], 1.0 / c[0] + 1.0 / ring[0]);
    // Within-region spread of the scene level (weighted sum of squares about each region's mean).
    let spread = (c[3] - c[2] * mc) + (ring[3] - ring[2] * mr);
    if spread <= MIN_SCENE_SPREAD * (c[0] + ring[0]) {
        return Some(simple);
    }
    // Normal equations of (m_c, m_r, β); eliminate m_c and m_r: β = Σ_regions (Σwrs − Σws Σwr/Σw)
    // / spread, then E = (Σwr_c − β Σws_c)/Σw_c − (Σwr_r − β Σws_r)/Σw_r.
    let beta = ((c[4] - c[2] * c[1] / c[0]) + (ring[4] - ring[2] * ring[1] / ring[0])) / spread;
    let e = (c[1] - beta * c[2]) / c[0] - (ring[1] - beta * ring[2]) / ring[0];
    Some((e, simple.1 + (mc - mr).powi(2) / spread))
}

/// Ring of a template of radius `rho`: (inner, outer) radius.
fn ring_of(rho: f64) -> (f64, f64) {
    (rho + 2.0, rho + 2.0 + (0.4 * rho).max(4.0))
}

/// One frame prepared for the scan.
struct FrameScan {
    sums: Sums,
    src: (f64, f64),
}

/// Residual (channel mean) with columns and rows of significant median offset removed,
/// weights and the prefix sums.
fn prepare(
    p: &Pair,
    m: &Masks,
    pred: &[Plane],
    resid: &[Plane],
    noise: &NoiseModel,
    src: (f64, f64),
    spill: Option<&[bool]>,
) -> FrameScan {
    let (w, h) = (p.w(), p.h());
    let nc = resid.len() as f32;
    let mut r = vec![f32::NAN; w * h];
    let mut sd = vec![0f32; w * h];
    let mut lvl = vec![0f32; w * h];
    for i in 0..w * h {
        if m.dist_sat.get(i) <= SAT_MARGIN || m.dist_edge.get(i) <= EDGE_MARGIN || spill.is_some_and(|s| s[i]) {
            continue;
        }
        let mut v = 0.0;
        let mut var = 0.0;
        let mut l = 0.0;
        for c in 0..resid.len() {
            v += resid[c].data[i];
            let q = pred[c].data[i];
            l += q;
            var += noise.var(q as f64) as f32;
        }
        r[i] = v / nc;
        sd[i] = (var.max(1e-6)).sqrt() / nc;
        lvl[i] = l / nc;
    }
    // Column and row offsets (smear, row noise): removed where the median differs from zero by
    // more than 6 standard errors; a ghost covers a minority of any column or row.
    for pass in 0..2 {
        let (nl, len) = if pass == 0 { (w, h) } else { (h, w) };
        let mut vals = Vec::with_capacity(len);
        let mut sds = Vec::with_capacity(len);
        for l in 0..nl {
            vals.clear();
            sds.clear();
            for t in 0..len {
                let i = if pass == 0 { t * w + l } else { l * w + t };
                if r[i].is_finite() {
                    vals.push(r[i] as f64);
                    sds.push(sd[i] as f64);
                }
            }
            if vals.len() < 20 {
                continue;
            }
            let med = stats::median(&vals);
            let se = 1.2533 * stats::median(&sds) / (vals.len() as f64).sqrt();
            if med.abs() > 6.0 * se {
                for t in 0..len {
                    let i = if pass == 0 { t * w + l } else { l * w + t };
                    if r[i].is_finite() {
                        r[i] -= med as f32;
                    }
                }
            }
        }
    }
    FrameScan { sums: prefix_sums(w, h, &r, &sd, &lvl), src }
}

/// Row prefix sums ([`Sums`]) of a residual `r` (NaN = not used) with noise sd `sd` and predicted
/// level `lvl`; standardised residuals are clipped at ±[`CLIP`].
fn prefix_sums(w: usize, h: usize, r: &[f32], sd: &[f32], lvl: &[f32]) -> Sums {
    let st = w + 1;
    let mut p: [Vec<f64>; NS] = std::array::from_fn(|_| vec![0.0; st * h]);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (a, b) = (y * st + x, y * st + x + 1);
            let d = if r[i].is_finite() {
                let s = sd[i] as f64;
                let wt = 1.0 / (s * s);
                let v = (r[i] as f64).clamp(-(CLIP as f64) * s, CLIP as f64 * s);
                let l = lvl[i] as f64;
                [wt, wt * v, wt * l, wt * l * l, wt * v * l, 1.0]
            } else {
                [0.0; NS]
            };
            for (pk, dk) in p.iter_mut().zip(d) {
                pk[b] = pk[a] + dk;
            }
        }
    }
    Sums { w, h, p }
}

/// Excess and variance of one template on one frame at line parameter `u` along the direction
/// rotated by `ang` from the source direction; `core` = share of ρ of the core radius. `None`
/// off the frame or where [`template`] cannot read it.
fn frame_template(
    f: &FrameScan,
    u: f64,
    ang: f64,
    rho: f64,
    core: f64,
    ring: (f64, f64),
    cover: f64,
) -> Option<(f64, f64)> {
    let (w, h) = (f.sums.w, f.sums.h);
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let (vx, vy) = (f.src.0 - cx, f.src.1 - cy);
    let (ca, sa) = (ang.cos(), ang.sin());
    let (dx, dy) = (vx * ca - vy * sa, vx * sa + vy * ca);
    let (x, y) = (cx + u * dx, cy + u * dy);
    if x < 0.0 || y < 0.0 || x > w as f64 - 1.0 || y > h as f64 - 1.0 {
        return None;
    }
    template(&f.sums, x, y, core * rho, ring, cover)
}

/// Inverse-variance combination over frames of one template: the sums (Σ 1/v, Σ e/v), to which
/// the frames are added in pair order ([`Combined::add`]) so that the result has the same bits
/// however the frames were grouped and on however many threads they were read.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Combined {
    sw: f64,
    swe: f64,
}

impl Combined {
    fn add(&mut self, ev: Option<(f64, f64)>) {
        if let Some((e, v)) = ev {
            self.sw += 1.0 / v;
            self.swe += e / v;
        }
    }
    /// Combined excess and its variance, `None` when no frame could read the template.
    fn get(&self) -> Option<(f64, f64)> {
        (self.sw > 0.0).then(|| (self.swe / self.sw, 1.0 / self.sw))
    }
}

/// Frames prepared (prefix sums, [`prepare`]) a few at a time, in parallel within a group, each
/// evaluated by `eval` into one value per query and then dropped; the values are added into `acc`
/// frame by frame in pair order. Only a group's prefix sums (six f64 per pixel and frame) are
/// held at once, not every frame's.
fn stream_frames<F>(
    frames: &[(usize, (f64, f64))],
    prep: &(dyn Fn(usize, (f64, f64)) -> FrameScan + Sync),
    eval: F,
    acc: &mut [Combined],
) where
    F: Fn(&FrameScan) -> Vec<Option<(f64, f64)>> + Sync,
{
    for group in frames.chunks(STREAM_GROUP) {
        let vals: Vec<Vec<Option<(f64, f64)>>> = group.par_iter().map(|&(k, src)| eval(&prep(k, src))).collect();
        for v in vals {
            debug_assert_eq!(v.len(), acc.len());
            for (a, ev) in acc.iter_mut().zip(v) {
                a.add(ev);
            }
        }
    }
}

/// Frames prepared at once by [`stream_frames`] (a fixed number, so that the grouping and with it
/// the result do not depend on the thread count).
const STREAM_GROUP: usize = 4;

/// A ghost found: line parameter, template radius (px), plateau (DN), its standard error, z.
#[derive(Debug, Clone, Copy)]
pub struct Ghost {
    pub u: f64,
    pub rho: f64,
    pub plateau: f64,
    pub se: f64,
    pub z: f64,
}

/// The lens-flare signature (see the module doc). `z_thr` is the detection threshold.
pub fn lens_flare(
    pairs: &[Pair],
    masks: &[Masks],
    pred: &[Vec<Plane>],
    resid: &[Vec<Plane>],
    noise: &NoiseModel,
    z_thr: f64,
    spill: Option<&[Vec<bool>]>,
) -> Signature {
    let mut sig = Signature::new("lens_flare");
    // The forward fit starts from the library's default layout with 3 ghosts; the count found is
    // reported as COUNT_PARAM.
    sig.set_param("ghosts", 3.0);
    sig.set_param("intensity", 0.0);
    // The brightest source of every frame (in parallel; pair order kept), then only off-centre ones.
    let srcs: Vec<Option<(f64, f64)>> = pairs.par_iter().map(|p| brightest_source(&luma(&p.sim))).collect();
    let frames: Vec<(usize, (f64, f64))> = srcs
        .iter()
        .enumerate()
        .filter_map(|(k, s)| s.map(|s| (k, s)))
        .filter(|&(k, src)| {
            let (w, h) = (pairs[k].w(), pairs[k].h());
            let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
            ((src.0 - cx).powi(2) + (src.1 - cy).powi(2)).sqrt() >= 0.05 * w.min(h) as f64
        })
        .collect();
    if frames.is_empty() {
        sig.evidence = "no off-centre bright source (no blob at 95 % of full scale away from the centre): lens flare cannot be tested".into();
        return sig;
    }
    // Over-exposed sources: the region their spilled charge fills (a plateau grown around the
    // source, often as wide as a ghost) is no evidence of a ghost; the scan reads away from it.
    let prep = |k: usize, src: (f64, f64)| {
        let spill = spill.and_then(|s| s.get(k)).filter(|s| !s.is_empty()).map(Vec::as_slice);
        prepare(&pairs[k], &masks[k], &pred[k], &resid[k], noise, src, spill)
    };
    let (w, h) = (pairs[frames[0].0].w(), pairs[frames[0].0].h());
    let diag = ((w * w + h * h) as f64).sqrt();
    let len = frames
        .iter()
        .map(|&(_, src)| ((src.0 - (w as f64 - 1.0) / 2.0).powi(2) + (src.1 - (h as f64 - 1.0) / 2.0).powi(2)).sqrt())
        .sum::<f64>()
        / frames.len() as f64;
    let du = 1.0 / len;
    let us: Vec<f64> = (0..).map(|j| U_MIN + j as f64 * du).take_while(|&u| u <= U_MAX).collect();
    let radii: Vec<f64> = RADII.iter().map(|r| (r * diag).max(3.0)).collect();
    // z of every template on the lines at angles 0 (the main line) and CONTROL_DEG: per angle,
    // per radius, per position; every frame is read once for all of them.
    let angles: Vec<f64> = std::iter::once(0.0).chain(CONTROL_DEG.iter().map(|a| a.to_radians())).collect();
    let (nr, nu) = (radii.len(), us.len());
    let mut acc = vec![Combined::default(); angles.len() * nr * nu];
    let eval_scan = |f: &FrameScan| -> Vec<Option<(f64, f64)>> {
        let mut out = Vec::with_capacity(angles.len() * nr * nu);
        for &ang in &angles {
            for &rho in &radii {
                let ring = ring_of(rho);
                out.extend(us.iter().map(|&u| frame_template(f, u, ang, rho, 0.8, ring, SCAN_COVER)));
            }
        }
        out
    };
    stream_frames(&frames, &prep, eval_scan, &mut acc);
    let scan = |a: usize| -> Vec<Vec<f64>> {
        (0..nr)
            .map(|ri| {
                (0..nu)
                    .map(|j| match acc[(a * nr + ri) * nu + j].get() {
                        Some((e, v)) => e / v.sqrt(),
                        None => f64::NAN,
                    })
                    .collect()
            })
            .collect()
    };
    let main = scan(0);
    // Calibration: the spread of the same statistic on control lines, away from the centre
    // (where every line through the centre meets the same pixels).
    let mut ctrl = Vec::new();
    let mut ctrl_max = f64::NEG_INFINITY;
    for a in 1..angles.len() {
        let z = scan(a);
        for (ri, row) in z.iter().enumerate() {
            let keep = 2.0 * (ring_of(radii[ri]).1) / len;
            for (j, &v) in row.iter().enumerate() {
                if v.is_finite() && us[j].abs() > keep {
                    ctrl.push(v);
                    ctrl_max = ctrl_max.max(v);
                }
            }
        }
    }
    let inflate = if ctrl.len() >= 50 { stats::mad_sigma(&ctrl).max(1.0) } else { 1.0 };
    // Greedy peak picking on the main line.
    let mut peaks: Vec<(f64, usize, usize)> = Vec::new();
    for (ri, row) in main.iter().enumerate() {
        for (j, &v) in row.iter().enumerate() {
            if v.is_finite() && v / inflate >= z_thr {
                peaks.push((v / inflate, ri, j));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut ghosts: Vec<Ghost> = Vec::new();
    // Each ghost must stand above the largest z of the control lines (the scan maximum where no
    // ghost can be) as well as above the threshold.
    let floor = z_thr.max(ctrl_max / inflate);
    // The plateau readings the picking below can ask for: every position within ρ/2 of every
    // peak above the floor, read on all frames in a second pass (only when there is such a peak).
    let reach_of = |rho: f64| (0.5 * rho / (du * len)).round() as isize;
    let read_ring = |rho: f64| (1.25 * rho + 3.0, 1.25 * rho + 3.0 + (0.4 * rho).max(6.0));
    let cands: Vec<(f64, usize, usize)> = peaks.iter().copied().filter(|p| p.0 >= floor).collect();
    let mut offsets = Vec::with_capacity(cands.len() + 1);
    offsets.push(0usize);
    for &(_, ri, _) in &cands {
        offsets.push(offsets.last().copied().unwrap_or(0) + (2 * reach_of(radii[ri]) + 1) as usize);
    }
    let mut reads = vec![Combined::default(); offsets.last().copied().unwrap_or(0)];
    if !reads.is_empty() {
        let n_reads = reads.len();
        let eval_reads = |f: &FrameScan| -> Vec<Option<(f64, f64)>> {
            let mut out = Vec::with_capacity(n_reads);
            for &(_, ri, j) in &cands {
                let (u, rho) = (us[j], radii[ri]);
                let reach = reach_of(rho);
                out.extend((-reach..=reach).map(|d| {
                    let uu = u + d as f64 * du;
                    frame_template(f, uu, 0.0, rho, 0.6, read_ring(rho), READ_COVER)
                }));
            }
            out
        };
        stream_frames(&frames, &prep, eval_reads, &mut reads);
    }
    for (ci, &(z, ri, j)) in cands.iter().enumerate() {
        let (u, rho) = (us[j], radii[ri]);
        if ghosts.iter().any(|g| (g.u - u).abs() * len < g.rho + rho) {
            continue;
        }
        // The plateau on the ghost's inner part (0.6 ρ) against a ring clear of its soft edge
        // (from 1.25 ρ + 3 px: the best template's ring may start just inside the edge), at the
        // position within ρ/2 along the line where it is most significant (the scan's peak can
        // lean away from masked pixels).
        let reach = reach_of(rho);
        let best = (-reach..=reach)
            .zip(&reads[offsets[ci]..offsets[ci + 1]])
            .filter_map(|(d, c)| {
                let uu = u + d as f64 * du;
                c.get().map(|(e, v)| (uu, e, v))
            })
            .max_by(|a, b| (a.1 / a.2.sqrt()).total_cmp(&(b.1 / b.2.sqrt())));
        // A ghost's plateau is significant on its own inner part too (a template that only
        // straddles the edge of a brighter ghost is not).
        if let Some((uu, e, v)) = best
            && e / (v.sqrt() * inflate) >= floor
            && !ghosts.iter().any(|g| (g.u - uu).abs() * len < g.rho + rho)
        {
            ghosts.push(Ghost { u: uu, rho, plateau: e, se: v.sqrt(), z });
        }
    }
    ghosts.sort_by(|a, b| a.u.total_cmp(&b.u));
    // Coverage: stretches of the line (inside the frame) where not even the smallest template can
    // be read (scene edges, saturation) and that no ghost found covers. A ghost could hide there,
    // so the count is only a lower bound when one is at least a smallest ghost's diameter long.
    let inside = |u: f64| {
        frames.iter().any(|&(k, src)| {
            let (fw, fh) = (pairs[k].w(), pairs[k].h());
            let (cx, cy) = ((fw as f64 - 1.0) / 2.0, (fh as f64 - 1.0) / 2.0);
            let (x, y) = (cx + u * (src.0 - cx), cy + u * (src.1 - cy));
            x >= 0.0 && y >= 0.0 && x <= fw as f64 - 1.0 && y <= fh as f64 - 1.0
        })
    };
    let mut gap = 0.0f64;
    let mut run = 0.0f64;
    for (j, &u) in us.iter().enumerate() {
        let covered = ghosts.iter().any(|g| (g.u - u).abs() * len <= g.rho);
        if inside(u) && !main[0][j].is_finite() && !covered {
            run += du * len;
            gap = gap.max(run);
        } else {
            run = 0.0;
        }
    }
    let complete = gap < 2.0 * radii[0];
    let zmax = peaks
        .first()
        .map(|p| p.0)
        .unwrap_or_else(|| main.iter().flatten().copied().filter(|v| v.is_finite()).fold(0.0, f64::max) / inflate);
    sig.z = zmax;
    sig.where_ = format!(
        "along the line from the brightest source through the centre ({} frame(s), source {:.0} px from the centre)",
        frames.len(),
        len
    );
    sig.size_unit = "DN mean ghost plateau";
    let ctrl_note = format!(
        "scan of {} positions x {} template radii ({:.0}-{:.0} px); noise-model z scaled by the control lines' spread {:.2} (their largest z {:.1})",
        us.len(),
        radii.len(),
        radii[0],
        radii[radii.len() - 1],
        inflate,
        ctrl_max / inflate
    );
    if ghosts.is_empty() {
        sig.evidence =
            format!("no ghost plateau above z = {z_thr} on the source–centre line (largest z {zmax:.1}); {ctrl_note}");
    } else {
        let mean = ghosts.iter().map(|g| g.plateau).sum::<f64>() / ghosts.len() as f64;
        let se = (ghosts.iter().map(|g| g.se * g.se).sum::<f64>()).sqrt() / ghosts.len() as f64;
        sig.size = mean;
        if complete {
            sig.set_param(COUNT_PARAM, ghosts.len() as f64);
        }
        sig.set_param("intensity", (mean / FS as f64).clamp(0.0, 1.0));
        sig.set_param(PLATEAU_PARAM, (mean / FS as f64).clamp(0.0, 1.0));
        sig.stderr.push(("intensity".into(), se / FS as f64));
        let list: Vec<String> = ghosts
            .iter()
            .map(|g| {
                format!("t = {:+.2}, radius ~{:.0} px: {:.2} ± {:.2} DN (z = {:.0})", g.u, g.rho, g.plateau, g.se, g.z)
            })
            .collect();
        let count_note = if complete {
            String::new()
        } else {
            format!(
                " (a stretch of {gap:.0} px of the line cannot be read (scene edges or saturation): the count is a lower bound and is not reported)"
            )
        };
        sig.evidence = format!(
            "{} ghost plateau(s) on the source–centre line{count_note}: {}; mean plateau {mean:.2} ± {se:.2} DN = {:.4} FS; {ctrl_note}",
            ghosts.len(),
            list.join("; "),
            mean / FS as f64
        );
    }
    sig.detected = !ghosts.is_empty() && sig.z >= z_thr && sig.size >= MIN_INTENSITY * FS as f64;
    // Profile: the best template's z along the line, and one control line.
    let best_row = |z: &[Vec<f64>]| -> Vec<f64> {
        (0..us.len())
            .map(|j| z.iter().map(|r| r[j]).filter(|v| v.is_finite()).fold(f64::NAN, f64::max) / inflate)
            .collect()
    };
    sig.profiles.push(Profile {
        title: "lens flare: plateau z along the source–centre line (best template radius)".into(),
        x_label: "position along the line (0 = centre, 1 = source)".into(),
        y_label: "z of core minus ring".into(),
        x: us.clone(),
        series: vec![("source–centre line".into(), best_row(&main))],
    });
    sig
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn source_is_the_blob_with_most_flux_not_the_bright_pixels_centroid() {
        // Many small saturated stars on one side, one large saturated star on the other.
        let mut p = Plane::filled(200, 120, 3.0);
        for k in 0..12 {
            let (x, y) = (150 + (k % 4) * 12, 20 + (k / 4) * 30);
            p.data[y * 200 + x] = 255.0;
            p.data[y * 200 + x + 1] = 255.0;
        }
        for y in 36..45 {
            for x in 26..35 {
                p.data[y * 200 + x] = 255.0;
            }
        }
        let (x, y) = brightest_source(&p).expect("source");
        assert!((x - 30.0).abs() < 0.5 && (y - 40.0).abs() < 0.5, "source at ({x}, {y})");
    }

    #[test]
    fn plateau_template_reads_a_disc_and_ignores_flat_noise() {
        // A flat residual with a disc of +2 DN: the template centred on it reads 2 DN; off it, 0.
        let (w, h) = (120usize, 100usize);
        let mut r = vec![0.0f64; w * h];
        for y in 0..h {
            for x in 0..w {
                if ((x as f64 - 60.0).powi(2) + (y as f64 - 50.0).powi(2)).sqrt() <= 12.0 {
                    r[y * w + x] = 2.0;
                }
            }
        }
        let sd = vec![1.0f32; w * h];
        let lvl = vec![3.0f32; w * h];
        let rf: Vec<f32> = r.iter().map(|&v| v as f32).collect();
        let s = prefix_sums(w, h, &rf, &sd, &lvl);
        let (e, v) = template(&s, 60.0, 50.0, 0.6 * 12.0, (16.0, 24.0), 0.7).expect("template");
        assert!((e - 2.0).abs() < 1e-9 && v > 0.0, "plateau {e}");
        let (e, _) = template(&s, 25.0, 25.0, 8.0, (12.0, 16.0), 0.7).expect("template");
        assert!(e.abs() < 1e-9, "off the ghost {e}");
    }

    #[test]
    fn streamed_frames_combine_as_the_whole_set_in_pair_order() {
        // Seven frames (more than a group) with ghosts of different levels: the streamed sums
        // equal the frame-by-frame sums in pair order bit for bit, on 1 and on 2 threads.
        let (w, h) = (90usize, 70usize);
        let scans: Vec<FrameScan> = (0..7)
            .map(|k| {
                let r: Vec<f32> = (0..w * h)
                    .map(|i| {
                        let (x, y) = ((i % w) as f64, (i / w) as f64);
                        let g = if (x - 30.0).hypot(y - 40.0) <= 9.0 { 1.0 + 0.3 * k as f64 } else { 0.0 };
                        (g + 0.1 * ((i * (k + 3)) % 17) as f64 - 0.8) as f32
                    })
                    .collect();
                let sd: Vec<f32> = (0..w * h).map(|i| 1.0 + 0.01 * (i % 7) as f32).collect();
                let lvl = vec![20.0f32; w * h];
                FrameScan { sums: prefix_sums(w, h, &r, &sd, &lvl), src: (70.0 + k as f64, 10.0) }
            })
            .collect();
        let frames: Vec<(usize, (f64, f64))> = scans.iter().enumerate().map(|(k, f)| (k, f.src)).collect();
        let us: Vec<f64> = (0..40).map(|j| -1.5 + 0.06 * j as f64).collect();
        let eval = |f: &FrameScan| -> Vec<Option<(f64, f64)>> {
            us.iter().map(|&u| frame_template(f, u, 0.3, 9.0, 0.8, ring_of(9.0), SCAN_COVER)).collect()
        };
        let mut whole = vec![Combined::default(); us.len()];
        for f in &scans {
            for (a, ev) in whole.iter_mut().zip(eval(f)) {
                a.add(ev);
            }
        }
        assert!(whole.iter().filter(|c| c.get().is_some()).count() > 10, "templates read");
        let copy = |k: usize, _src: (f64, f64)| FrameScan {
            sums: Sums { w: scans[k].sums.w, h: scans[k].sums.h, p: scans[k].sums.p.clone() },
            src: scans[k].src,
        };
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
            let mut acc = vec![Combined::default(); us.len()];
            pool.install(|| stream_frames(&frames, &copy, eval, &mut acc));
            for (a, b) in acc.iter().zip(&whole) {
                assert_eq!((a.sw.to_bits(), a.swe.to_bits()), (b.sw.to_bits(), b.swe.to_bits()), "{threads} thread(s)");
            }
        }
    }

    #[test]
    fn residual_that_follows_the_scene_is_not_a_plateau() {
        // A textured scene with a 2 % gain mismatch (r = 0.02 s, below the ±5 sd clip) and a +2 DN
        // disc: the template
        // reads 2 DN on the disc and 0 off it, whereas core minus ring alone would read the
        // scene's texture too.
        let (w, h) = (120usize, 100usize);
        let lvl: Vec<f32> = (0..w * h)
            .map(|i| (50.0 + 30.0 * ((i % w) as f64 / 3.0).sin() * ((i / w) as f64 / 4.0).cos()) as f32)
            .collect();
        let mut r: Vec<f32> = lvl.iter().map(|&s| 0.02 * s).collect();
        for y in 0..h {
            for x in 0..w {
                if ((x as f64 - 60.0).powi(2) + (y as f64 - 50.0).powi(2)).sqrt() <= 12.0 {
                    r[y * w + x] += 2.0;
                }
            }
        }
        let sd = vec![1.0f32; w * h];
        let s = prefix_sums(w, h, &r, &sd, &lvl);
        let (e, _) = template(&s, 60.0, 50.0, 0.6 * 12.0, (16.0, 24.0), 0.7).expect("template");
        assert!((e - 2.0).abs() < 0.02, "plateau {e}");
        let (e, _) = template(&s, 25.0, 25.0, 8.0, (12.0, 16.0), 0.7).expect("template");
        assert!(e.abs() < 0.02, "off the ghost {e}");
    }
}
