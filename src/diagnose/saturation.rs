//! Around saturated pixels: `blooming` (plateau below full scale and a halo of spilled charge) and
//! `smear` (column or row offsets proportional to the number of saturated pixels they contain).
//! Lens flare has its own signature ([`super`]`::flare`, ghost plateaus on the source–centre line).

use super::common::{Masks, NoiseModel};
use super::img::{FS, Pair, Plane, SAT_DN};
use super::stats::{self, Wls};
use super::types::{Profile, Signature};

/// Location of `vals` (observations of N(mu, sigma²) rounded to `q` and clipped at 0) with
/// sigma known; returns (mu, variance of mu).
pub fn censored_mean_known_sigma(vals: &[f32], sigma: f64, q: f64) -> (f64, f64) {
    let n = vals.len() as f64;
    let zeros = vals.iter().filter(|&&v| v <= 0.0).count() as f64;
    if zeros == 0.0 {
        let m = vals.iter().map(|&v| v as f64).sum::<f64>() / n;
        return (m, sigma * sigma / n);
    }
    let pos: Vec<f64> = vals.iter().filter(|&&v| v > 0.0).map(|&v| v as f64).collect();
    let half = q / 2.0;
    let nll = |mu: f64| -> f64 {
        let mut s = -zeros * stats::norm_cdf((half - mu) / sigma).max(1e-300).ln();
        for &v in &pos {
            let p = if q > 0.0 {
                stats::norm_cdf((v + half - mu) / sigma) - stats::norm_cdf((v - half - mu) / sigma)
            } else {
                stats::norm_pdf((v - mu) / sigma)
            };
            s -= p.max(1e-300).ln();
        }
        s
    };
    let hi = pos.iter().copied().fold(0.0, f64::max) + 3.0 * sigma;
    let (mu, _) = stats::golden(&mut |m| nll(m), -4.0 * sigma, hi, 40);
    // Fisher information is lower than n/sigma² by the censored fraction.
    let frac_obs = (pos.len() as f64 / n).max(0.1);
    (mu, sigma * sigma / (n * frac_obs))
}

/// Depth (px, chamfer distance to the nearest unsaturated sim pixel) of the saturated "cores"
/// on which the plateau is read when no saturated region has an interior: 1.3 keeps the pixels
/// whose four neighbours are saturated too (a pixel on the rim may be partly covered).
pub const CORE_DEPTH_PX: f32 = 1.3;
/// Largest blur (σ, px, from the defocus signature) at which cores are trusted: a wider PSF
/// mixes the surroundings into a core pixel and lowers it.
pub const CORE_MAX_BLUR_PX: f64 = 0.5;
/// Margin (DN) by which the halo at 1 px must exceed the sim's excess over the well to be read
/// as over-exposure.
pub const OVEREXPOSED_MARGIN_DN: f64 = 3.0;

/// z (binomial, against 1/2) below which the share of the saturated plateau at the top code does
/// not show a well below full scale (see [`blooming`]).
pub const PLATEAU_BELOW_TOP_Z: f64 = 5.0;
/// Smallest z of the smear-free halo at 1 px for its shape to be read (a 5-sigma excess).
pub const SHAPE_MIN_Z: f64 = 5.0;

/// Parameter of the blooming signature (set with `halo_px`, over-exposed sources only): how far
/// (px) the halo reaches beyond the real spill footprint ([`spill_footprint`]), where the mean
/// residual falls below 1 DN.
pub const SPILL_REACH_PARAM: &str = "spill_reach_px";
/// Farthest reach (px) of the halo beyond the real spill footprint that is measured.
const SPILL_REACH_MAX: usize = 30;
/// Frames read for the reach (the first ones with saturated sim pixels).
const SPILL_FRAMES: usize = 3;

/// Lowest real value (DN) counted as a photosite at the well: the plateau less three times its
/// scatter (at least 1 DN).
fn spill_threshold(plateau: f64, plateau_sd: f64) -> f32 {
    (plateau - (3.0 * plateau_sd).max(1.0)) as f32
}

/// The real spill footprint of over-exposed sources in one frame: the sim's saturated pixels and
/// every pixel connected to them (8-neighbourhood) whose real value, in any channel, is at the
/// well (`>= thr`). Physics: a source far over full scale holds far more charge than its
/// photosites can; the excess overflows into the neighbours, fills each to the well and moves
/// on, so the real frame shows a plateau region grown from the source, contiguous with it, whose
/// size is set by the source's total over-exposure, which the clipped sim no longer holds (a
/// star at 20 FS grows a blob several px wide around a core of a few saturated sim pixels).
pub fn spill_footprint(p: &Pair, m: &Masks, thr: f32) -> Vec<bool> {
    grow_footprint(m, p.w(), p.h(), |i| p.real.iter().any(|c| c.data[i] >= thr))
}

/// The sim's saturated pixels grown (8-neighbourhood) through the pixels where `at_well` holds.
fn grow_footprint(m: &Masks, w: usize, h: usize, at_well: impl Fn(usize) -> bool) -> Vec<bool> {
    let mut foot = vec![false; w * h];
    let mut stack: Vec<usize> = Vec::new();
    for (i, f) in foot.iter_mut().enumerate() {
        if m.sat.get(i) {
            *f = true;
            stack.push(i);
        }
    }
    while let Some(i) = stack.pop() {
        let (x, y) = ((i % w) as isize, (i / w) as isize);
        for dy in -1isize..=1 {
            for dx in -1isize..=1 {
                let (xx, yy) = (x + dx, y + dy);
                if xx < 0 || yy < 0 || xx >= w as isize || yy >= h as isize {
                    continue;
                }
                let j = yy as usize * w + xx as usize;
                if !foot[j] && at_well(j) {
                    foot[j] = true;
                    stack.push(j);
                }
            }
        }
    }
    foot
}

/// Column offsets (vertical smear, and any far-field level), then row offsets (horizontal
/// smear) on what the columns leave, of the residual `rr`, read on pixels far (more than
/// [`SHAPE_FAR_PX`]) from the footprint whose distance map is `dist` and from the sim's
/// saturated regions (NaN where a line has fewer than 16 such pixels).
fn line_offsets(rr: &[f32], dist: &[f32], m: &Masks, w: usize, h: usize) -> (Vec<f64>, Vec<f64>) {
    let far = |i: usize| dist[i] > SHAPE_FAR_PX && m.dist_sat.get(i) > SHAPE_FAR_PX;
    let mut col = vec![f64::NAN; w];
    let mut buf = Vec::with_capacity(h.max(w));
    for (x, cv) in col.iter_mut().enumerate() {
        buf.clear();
        buf.extend((0..h).map(|y| y * w + x).filter(|&i| far(i)).map(|i| rr[i] as f64));
        if buf.len() >= 16 {
            *cv = stats::median_mut(&mut buf);
        }
    }
    let mut row = vec![f64::NAN; h];
    for (y, rv) in row.iter_mut().enumerate() {
        buf.clear();
        buf.extend(
            (0..w)
                .map(|x| (x, y * w + x))
                .filter(|&(x, i)| far(i) && col[x].is_finite())
                .map(|(x, i)| rr[i] as f64 - col[x]),
        );
        if buf.len() >= 16 {
            *rv = stats::median_mut(&mut buf);
        }
    }
    (col, row)
}

/// The pixels at rounded distance `1..=dmax` from a footprint (`dist`, its distance transform),
/// away from unsaturated edges, each with its distance bin and its residual `rr` less the line
/// offsets `col`/`row` (see [`line_offsets`]), in pixel order. The samples both the halo's shape
/// and the spill's reach are read on.
fn ring_samples<'a>(
    rr: &'a [f32],
    dist: &'a [f32],
    m: &'a Masks,
    w: usize,
    (col, row): (&'a [f64], &'a [f64]),
    dmax: usize,
) -> impl Iterator<Item = (usize, usize, f64)> + 'a {
    dist.iter().enumerate().filter_map(move |(i, &d)| {
        let (x, y) = (i % w, i / w);
        if !(0.5..=dmax as f32 + 0.49).contains(&d)
            || m.dist_edge_unsat.get(i) < 1.5
            || !col[x].is_finite()
            || !row[y].is_finite()
        {
            return None;
        }
        Some((i, d.round() as usize, rr[i] as f64 - col[x] - row[y]))
    })
}

/// Reach (px) of the over-exposed halo beyond the real spill footprint: the first distance from
/// it at which the mean residual (far level removed) falls below 1 DN, at most
/// [`SPILL_REACH_MAX`]. The spilled charge decays away from the plateau region it filled, not
/// from the sim's few saturated pixels, so the halo is measured from there.
fn spill_reach(pairs: &[Pair], masks: &[Masks], r1: &[Vec<Plane>], thr: f32) -> usize {
    let mut acc = vec![(0.0f64, 0usize); SPILL_REACH_MAX + 1];
    for (k, p) in pairs.iter().enumerate().filter(|(k, _)| masks[*k].sat.any()).take(SPILL_FRAMES) {
        let m = &masks[k];
        let (w, h) = (p.w(), p.h());
        let foot = spill_footprint(p, m, thr);
        let dist = super::img::distance_transform(&foot, w, h);
        for rr in &r1[k] {
            // Smear's column and row offsets (and the far level) come out first: a smear column
            // through the source is no halo, and would carry the reach along it.
            let (col, row) = line_offsets(&rr.data, &dist, m, w, h);
            for (_, b, v) in ring_samples(&rr.data, &dist, m, w, (&col, &row), SPILL_REACH_MAX) {
                acc[b].0 += v;
                acc[b].1 += 1;
            }
        }
    }
    (1..=SPILL_REACH_MAX).find(|&b| acc[b].1 > 10 && acc[b].0 < acc[b].1 as f64).unwrap_or(SPILL_REACH_MAX)
}

/// Pixels of pair `p` that over-exposed sources' spilled charge reaches (None when the blooming
/// signature `bloom` did not find over-exposed sources, i.e. set no `halo_px`): within `halo_px`
/// of the sim's saturated regions, or within the reach ([`SPILL_REACH_PARAM`]) of the real spill
/// footprint ([`spill_footprint`]), the sim's saturated pixels themselves excepted (their
/// plateau is blooming's evidence). No effect applied to the clipped sim can put that charge
/// there, so these pixels are no evidence for any forward-model effect (a wider PSF, a gain, a
/// ghost would each absorb part of the blob), and the signatures read away from them.
pub fn spill_skip(p: &Pair, m: &Masks, bloom: &Signature) -> Option<Vec<bool>> {
    let halo = bloom.param("halo_px")? as f32;
    let plateau = bloom.param("full_well_fraction")? * FS as f64;
    let sd = bloom.param(PLATEAU_SD_PARAM).unwrap_or(1.0);
    let reach = bloom.param(SPILL_REACH_PARAM).map_or(halo, |r| r as f32);
    let foot = spill_footprint(p, m, spill_threshold(plateau, sd));
    let dist = super::img::distance_transform(&foot, p.w(), p.h());
    Some((0..dist.len()).map(|i| !m.sat.get(i) && (m.dist_sat.get(i) <= halo || dist[i] <= reach)).collect())
}

/// Robust scatter (DN, 1.4826 MAD) of the saturated plateau's real values, floored at the read
/// noise and ADC step a photosite at its full well still carries, and the share of the values at
/// the top code.
pub fn plateau_scatter(vals: &[f64], noise: &NoiseModel) -> (f64, f64) {
    if vals.is_empty() {
        return (noise.sd(FS as f64), 1.0);
    }
    let med = stats::median(vals);
    let dev: Vec<f64> = vals.iter().map(|v| (v - med).abs()).collect();
    let mad = 1.4826 * stats::median(&dev);
    let read = (noise.a.max(0.0) + noise.quant * noise.quant / 12.0).sqrt();
    let top = vals.iter().filter(|&&v| v >= SAT_DN as f64).count() as f64 / vals.len() as f64;
    (mad.max(read), top)
}

/// Blooming: plateau level inside saturated regions and the halo around them. The choice
/// `well_basis` says where the plateau was read: `interior` (saturated regions deeper than the
/// blur), `cores` (no interior, no measurable blur: pixels of small saturated regions whose four
/// neighbours are saturated) or `untestable` (neither: the full well is not constrained by the
/// data). The parameter `halo_px` is set when the sources are over-exposed (see below).
pub fn blooming(
    pairs: &[Pair],
    masks: &[Masks],
    q: &[Vec<Plane>],
    r1: &[Vec<Plane>],
    noise: &NoiseModel,
    blur_sigma: f64,
) -> Signature {
    let mut sig = Signature::new("blooming");
    let interior = (3.0 * blur_sigma).max(3.0) as f32 + 1.0;
    let collect = |depth: f32, min_n: usize| {
        let mut per_frame: Vec<(f64, f64, usize)> = Vec::new(); // (deficit, plateau, n)
        let mut all_r: Vec<f64> = Vec::new();
        let mut all_p: Vec<f64> = Vec::new();
        for (k, p) in pairs.iter().enumerate() {
            let m = &masks[k];
            let mut rv = Vec::new();
            let mut pv = Vec::new();
            for c in 0..p.channels() {
                let s = &p.sim[c].data;
                for i in 0..s.len() {
                    if s[i] >= SAT_DN && m.dist_in.get(i) >= depth {
                        rv.push(p.real[c].data[i] as f64);
                        pv.push((q[k][c].data[i] as f64).min(FS as f64));
                    }
                }
            }
            if rv.len() >= min_n {
                let rm = stats::median(&rv);
                let pm = stats::median(&pv);
                per_frame.push((pm - rm, rm, rv.len()));
                all_r.extend(&rv);
                all_p.extend(&pv);
            }
        }
        (per_frame, all_r, all_p)
    };
    let (mut per_frame, mut all_r, mut all_p) = collect(interior, 20);
    let mut basis = "interior";
    if all_r.is_empty() && blur_sigma < CORE_MAX_BLUR_PX {
        // Small saturated regions (glints, stars, reflectors): without a measurable blur, a pixel
        // whose four neighbours are saturated too collects nothing from outside it, so it reads the
        // well as an interior pixel does. A few pixels per frame, at least 20 in all.
        (per_frame, all_r, all_p) = collect(CORE_DEPTH_PX, 3);
        if all_r.len() < 20 {
            all_r.clear();
        }
        basis = "cores";
    }
    if all_r.is_empty() {
        sig.evidence = "no saturated regions with an interior in the sim: the full well cannot be tested (no plateau to read it on)".into();
        sig.choices.push(("well_basis".into(), "untestable".into()));
        return sig;
    }
    sig.choices.push(("well_basis".into(), basis.into()));
    let rm = stats::median(&all_r);
    let pm = stats::median(&all_p);
    let deficit = pm - rm;
    let n = all_r.len() as f64;
    // A photosite at its full well holds a clipped charge: it carries no shot noise, only the
    // read noise and the ADC step. The scatter of the plateau is measured (robustly) and
    // floored at that read noise, instead of taken from the noise model at the plateau's level
    // (which adds the shot noise of a charge that was never read out).
    let (sd_plateau, top_frac) = plateau_scatter(&all_r, noise);
    // SE of the median of the plateau values; across frames when there are several.
    let se_noise = 1.2533 * sd_plateau / n.sqrt();
    let se_frames = if per_frame.len() >= 3 {
        let d: Vec<f64> = per_frame.iter().map(|f| f.0).collect();
        stats::mean_se(&d).1
    } else {
        0.0
    };
    let se = se_noise.max(se_frames).max(0.05);
    // The plateau read in the sensor (before readout gain/offset): W relative to FS.
    sig.z = deficit / se;
    sig.size = deficit;
    sig.size_unit = "DN plateau deficit";
    // Halo: mean residual against distance outside the saturated regions, minus the far level.
    const D: usize = 30;
    let mut acc = vec![(0.0f64, 0usize); D + 1];
    let mut far = Vec::new();
    for (k, p) in pairs.iter().enumerate() {
        let m = &masks[k];
        for c in 0..p.channels() {
            let rr = &r1[k][c].data;
            for i in 0..rr.len() {
                let d = m.dist_sat.get(i);
                if !d.is_finite() || d < 0.5 || m.dist_edge_unsat.get(i) < 1.5 {
                    continue;
                }
                if d <= D as f32 {
                    let b = d.round() as usize;
                    acc[b].0 += rr[i] as f64;
                    acc[b].1 += 1;
                } else if d > 40.0 && far.len() < 200_000 {
                    far.push(rr[i] as f64);
                }
            }
        }
    }
    let far_level = if far.len() > 100 { stats::mean_se(&far).0 } else { 0.0 };
    let xs: Vec<f64> = (1..=D).map(|d| d as f64).collect();
    let prof: Vec<f64> =
        (1..=D).map(|d| if acc[d].1 > 10 { acc[d].0 / acc[d].1 as f64 - far_level } else { f64::NAN }).collect();
    // Spread: first moment of the positive halo (for a Gaussian spill from an edge the mean
    // distance is sigma·sqrt(2/pi)).
    let (mut m0, mut m1) = (0.0, 0.0);
    for (i, &v) in prof.iter().enumerate() {
        if v.is_finite() && v > 0.0 {
            m0 += v;
            m1 += v * (i as f64 + 1.0);
        }
    }
    let spread = if m0 > 0.0 { ((m1 / m0) - 0.5).max(0.3) / (2.0 / std::f64::consts::PI).sqrt() } else { 1.0 };
    // Over-exposure: one pixel's spilled excess cannot raise a neighbour by more than the excess
    // itself. The sim, clipped at FS, holds at most FS - plateau above the well; a halo at 1 px
    // well above that is fed by sources brighter than FS, which no effect applied to the sim can
    // reproduce (blooming_overexposed_mono: 79 DN at 1 px for 20 DN). The halo's extent is then reported (`halo_px`: where it falls below 1 DN) so
    // that the fit leaves that ring out instead of explaining it by something else.
    let sim_excess = (FS as f64 - rm).max(0.0);
    let mut shape_ev = None;
    // Only with charge overflow shown by the plateau itself (a well measurably below FS; not the
    // deficit against the model's prediction, which a gain fitted on the halo may pull down).
    if sim_excess >= 1.0
        && sim_excess / se >= 5.0
        && prof[0].is_finite()
        && prof[0] > sim_excess + OVEREXPOSED_MARGIN_DN
    {
        let r = prof.iter().position(|v| v.is_finite() && *v < 1.0).map(|i| i + 1).unwrap_or(D);
        sig.set_param("halo_px", r as f64);
        let thr = spill_threshold(rm, sd_plateau);
        sig.set_param(SPILL_REACH_PARAM, spill_reach(pairs, masks, r1, thr) as f64);
    }
    // A well below the top code: no saturated photosite reaches the top code. Without one
    // (the well at or above full scale, the plateau only lowered by PRNU, noise or JPEG
    // ringing of clipped samples), a pixel whose expected level is at or above full scale reads
    // the top code at least half of the time. The share of the plateau at the top code, tested
    // against 1/2 (binomial), says whether the data show a well below full scale.
    let flat_z = (0.5 - top_frac) / (0.25 / n).sqrt();
    if flat_z >= PLATEAU_BELOW_TOP_Z && deficit > 0.0 {
        sig.choices.push(("plateau".into(), "below_top_code".into()));
    }
    if let Some((s, z1, ev)) =
        halo_shape_spread(pairs, masks, r1, rm, sd_plateau, noise, sig.param("halo_px").is_some())
    {
        if z1 >= SHAPE_MIN_Z {
            sig.set_param(SHAPE_SPREAD_PARAM, s.clamp(0.3, 8.0));
        }
        shape_ev = Some(ev);
    }
    // The plateau's scatter: what the forward loss takes for a full photosite's value.
    sig.set_param(PLATEAU_SD_PARAM, sd_plateau);
    let fwf = (rm / FS as f64).clamp(0.05, 1.0);
    sig.set_param("full_well_fraction", fwf);
    sig.set_param("spread_px", spread.clamp(0.3, 20.0));
    sig.stderr = vec![("full_well_fraction".into(), se / FS as f64)];
    sig.where_ = format!(
        "{} saturated sim pixels ({basis}) in {} of {} frames and their surroundings",
        all_r.len(),
        per_frame.len(),
        pairs.len()
    );
    sig.evidence = format!(
        "saturated plateau reads {rm:.1} DN where {pm:.1} DN is expected (deficit {deficit:.2} ± {se:.2} DN, z = {:.1}); halo {:.2} DN at 1 px, {:.2} DN at 3 px above the far field",
        sig.z, prof[0], prof[2]
    );
    sig.evidence.push_str(&format!(
        "; plateau scatter {sd_plateau:.2} DN, {:.1} % of it at the top code (z = {flat_z:.1} against the 50 % of a clipped level at or above full scale)",
        100.0 * top_frac
    ));
    if let Some(ev) = shape_ev {
        sig.evidence.push_str(&format!("; {ev}"));
    }
    if let Some(r) = sig.param("halo_px") {
        sig.evidence.push_str(&format!(
            "; the halo exceeds the {sim_excess:.1} DN the clipped sim holds above the well: over-exposed sources (ring to {r:.0} px left out of the fit, spread_px untestable)"
        ));
    }
    sig.profiles.push(Profile {
        title: "blooming: residual against distance from saturated regions".into(),
        x_label: "distance from the saturated region (px)".into(),
        y_label: "mean real - model (DN), far field removed".into(),
        x: xs,
        series: vec![("halo".into(), prof)],
    });
    sig
}

/// Smear: column (vertical) or row (horizontal) offsets against the number of saturated sim
/// pixels in that column/row.
pub fn smear(pairs: &[Pair], masks: &[Masks], r1: &[Vec<Plane>], q: &[Vec<Plane>], noise: &NoiseModel) -> Signature {
    let mut sig = Signature::new("smear");
    let sigma0 = (noise.var(0.0) - noise.quant * noise.quant / 12.0).max(0.01).sqrt();
    let lo = 3.0 * noise.sd(0.0);
    let mut results = Vec::new();
    for vertical in [true, false] {
        let mut betas: Vec<(f64, f64)> = Vec::new();
        let mut prof_x = Vec::new();
        let mut prof_y = Vec::new();
        let mut n_lines_sat = 0usize;
        for (k, p) in pairs.iter().enumerate() {
            let m = &masks[k];
            let (w, h) = (p.w(), p.h());
            let (nl, len) = if vertical { (w, h) } else { (h, w) };
            for c in 0..p.channels() {
                let s = &p.sim[c].data;
                let rr = &r1[k][c].data;
                let real = &p.real[c].data;
                let qq = &q[k][c].data;
                let mut ys = Vec::with_capacity(nl);
                for l in 0..nl {
                    let mut nsat = 0usize;
                    let mut bright = Vec::new();
                    let mut dark = Vec::new();
                    let mut dark_q = 0.0f64;
                    for t in 0..len {
                        let i = if vertical { t * w + l } else { l * w + t };
                        if s[i] >= SAT_DN {
                            nsat += 1;
                        }
                        if m.dist_sat.get(i) <= 12.0 || m.dist_edge.get(i) <= 3.0 {
                            continue;
                        }
                        if s[i] <= 0.25 {
                            dark.push(real[i]);
                            dark_q += qq[i] as f64;
                        } else if qq[i] as f64 >= lo && real[i] < FS {
                            bright.push(rr[i] as f64);
                        }
                    }
                    let mut est = Vec::new();
                    if bright.len() >= 8 {
                        let med = stats::median(&bright);
                        // trimmed mean: mean of values within 4 sigma of the median
                        let sd = noise.sd(128.0);
                        let kept_vals: Vec<f64> =
                            bright.iter().copied().filter(|v| (v - med).abs() <= 4.0 * sd).collect();
                        if kept_vals.len() >= 8 {
                            let m = kept_vals.iter().sum::<f64>() / kept_vals.len() as f64;
                            est.push((m, sd * sd / kept_vals.len() as f64));
                        }
                    }
                    if dark.len() >= 8 {
                        let (mu, v) = censored_mean_known_sigma(&dark, sigma0, noise.quant);
                        // Relative to the model like the bright residuals: remove the mean
                        // predicted additive level of these pixels.
                        est.push((mu - dark_q / dark.len() as f64, v));
                    }
                    if est.is_empty() {
                        continue;
                    }
                    let (m, v) = if est.len() == 2 {
                        let w0 = 1.0 / est[0].1;
                        let w1 = 1.0 / est[1].1;
                        ((est[0].0 * w0 + est[1].0 * w1) / (w0 + w1), 1.0 / (w0 + w1))
                    } else {
                        est[0]
                    };
                    ys.push((l, m, v, nsat, !dark.is_empty()));
                }
                // Per frame/channel regression: level ~ 1 + t + t² + nsat.
                if !ys.iter().any(|y| y.3 > 0) || ys.len() < 10 {
                    continue;
                }
                n_lines_sat += ys.iter().filter(|y| y.3 > 0).count();
                let mut wls = Wls::new(4);
                for &(l, m, v, ns, _) in &ys {
                    let t = 2.0 * l as f64 / (nl.max(2) - 1) as f64 - 1.0;
                    wls.push(&[1.0, t, t * t, ns as f64], m, 1.0 / v.max(1e-6), (l / 4) as u32);
                }
                if let Some(f) = wls.fit() {
                    betas.push((f.beta[3], f.se(3)));
                    if k == 0 && c == 0 {
                        for &(l, m, _, ns, _) in &ys {
                            let t = 2.0 * l as f64 / (nl.max(2) - 1) as f64 - 1.0;
                            prof_x.push(l as f64);
                            prof_y.push(m - f.beta[0] - f.beta[1] * t - f.beta[2] * t * t);
                            let _ = ns;
                        }
                    }
                }
            }
        }
        if betas.is_empty() {
            results.push((vertical, 0.0, f64::INFINITY, 0.0, prof_x, prof_y, 0usize));
            continue;
        }
        let (mut sw, mut sb) = (0.0, 0.0);
        for &(b, se) in &betas {
            let w = 1.0 / (se * se).max(1e-18);
            sw += w;
            sb += w * b;
        }
        let beta = sb / sw;
        let se = (1.0 / sw).sqrt();
        results.push((vertical, beta, se, beta / se, prof_x, prof_y, n_lines_sat));
    }
    let best = results.iter().max_by(|a, b| a.3.total_cmp(&b.3)).cloned();
    let Some((vertical, beta, se, z, px, py, nls)) = best else {
        sig.evidence = "no saturated sim pixels: smear cannot be tested".into();
        return sig;
    };
    if !se.is_finite() {
        sig.evidence = "no saturated sim pixels: smear cannot be tested".into();
        return sig;
    }
    let other = results.iter().find(|r| r.0 != vertical).map(|r| r.3).unwrap_or(0.0);
    sig.z = z;
    sig.size = beta;
    sig.size_unit = "DN per saturated pixel";
    sig.set_param("strength", (beta / FS as f64).max(0.0));
    sig.choices.push(("direction".into(), if vertical { "vertical" } else { "horizontal" }.into()));
    sig.stderr = vec![("strength".into(), se / FS as f64)];
    let dir = if vertical { "columns" } else { "rows" };
    sig.where_ = format!("{nls} {dir} through saturated sim pixels");
    sig.evidence = format!(
        "{dir} gain {beta:.4} ± {se:.4} DN per saturated pixel they contain (z = {z:.1}; the other direction z = {other:.1})"
    );
    let mut sat_counts = Vec::new();
    if let Some(p) = pairs.first() {
        let (w, h) = (p.w(), p.h());
        for &l in &px {
            let l = l as usize;
            let n = if vertical {
                (0..h).filter(|&t| p.sim[0].data[t * w + l] >= SAT_DN).count()
            } else {
                (0..w).filter(|&t| p.sim[0].data[l * w + t] >= SAT_DN).count()
            };
            sat_counts.push(n as f64 * beta);
        }
    }
    sig.profiles.push(Profile {
        title: format!("smear: {dir} level against position (first frame)"),
        x_label: if vertical { "column x (px)".into() } else { "row y (px)".into() },
        y_label: "mean residual away from saturation (DN)".into(),
        x: px,
        series: vec![("measured".into(), py), ("fitted: strength x saturated count".into(), sat_counts)],
    });
    sig
}

/// Name of the blooming signature's parameter holding the spread read on the halo's shape.
pub const SHAPE_SPREAD_PARAM: &str = "spread_shape_px";
/// Signature parameter: robust scatter (DN) of the real saturated plateau (see
/// [`plateau_scatter`]), the noise of a full photosite in the forward loss.
pub const PLATEAU_SD_PARAM: &str = "plateau_sd_dn";
/// Distance bins (px from the real saturated footprint) of the halo-shape reading.
const SHAPE_D: usize = 12;
/// Far field of the halo-shape reading: beyond any plausible spill (px from the footprint).
const SHAPE_FAR_PX: f32 = 40.0;
/// Frames used by the halo-shape reading (the first ones with saturation).
const SHAPE_FRAMES: usize = 3;

/// Spread of the spilled charge read on the SHAPE of the halo, not on its size.
///
/// Physics: blooming spills the charge above the full well into the pixels next to a saturated
/// region, with a fall-off set by the spread (a decay length); how much charge spills is set by
/// the over-exposure, which a clipped sim does not hold. Smear, the near alias, adds a constant
/// to the whole column (or row) of a saturated pixel, above and below the source as far from it
/// as next to it. So: (1) the column and row offsets are read far from every saturated region
/// (beyond blooming's reach) and removed, which takes smear out whatever its strength and
/// whatever footprint feeds it; (2) the distance is measured from the REAL saturated footprint
/// (pixels at the measured plateau; blooming grows it beyond the sim's when over-exposed);
/// (3) the remaining excess against distance is fitted by the footprint spread with a Gaussian
/// of std s (the library model's kernel), with a free amplitude, so that only the fall-off's
/// shape decides s. `over_exposed` (blooming found `halo_px`): the footprint is the plateau grown
/// from the sim's saturated regions however far it reaches ([`grow_footprint`]). Returns (s, z of
/// the halo at 1 px, evidence) or None when the halo is not measurable (no footprint, too few
/// pixels, or no positive halo).
pub fn halo_shape_spread(
    pairs: &[Pair],
    masks: &[Masks],
    r1: &[Vec<Plane>],
    plateau: f64,
    plateau_sd: f64,
    noise: &NoiseModel,
    over_exposed: bool,
) -> Option<(f64, f64, String)> {
    // Per frame and channel: (bins of the near pixels, their corrected residuals, footprint).
    struct Near {
        mask: Plane,
        idx: Vec<(u32, u8)>,
    }
    let mut nears: Vec<Near> = Vec::new();
    let mut acc = vec![(0.0f64, 0usize); SHAPE_D + 1];
    let thr = (plateau - (3.0 * plateau_sd).max(1.0)) as f32;
    let mut used = 0usize;
    for (k, p) in pairs.iter().enumerate() {
        if used >= SHAPE_FRAMES {
            break;
        }
        let m = &masks[k];
        if !m.sat.any() {
            continue;
        }
        used += 1;
        let (w, h) = (p.w(), p.h());
        for c in 0..p.channels() {
            let real = &p.real[c].data;
            let rr = &r1[k][c].data;
            // The real footprint: pixels at the well near the sim's saturated regions and, with
            // over-exposed sources (`halo_px`), the plateau grown from them however far it
            // reaches (their spill fills a region wider than SHAPE_D; the halo falls off from
            // that region's rim, not from inside it).
            let grown = if over_exposed { grow_footprint(m, w, h, |i| real[i] >= thr) } else { Vec::new() };
            let foot: Vec<bool> = (0..w * h)
                .map(|i| {
                    grown.get(i).copied().unwrap_or(false)
                        || m.sat.get(i)
                        || (real[i] >= thr && m.dist_sat.get(i) <= SHAPE_D as f32)
                })
                .collect();
            let dist = super::img::distance_transform(&foot, w, h);
            let (col, row) = line_offsets(rr, &dist, m, w, h);
            let mut idx = Vec::new();
            for (i, b, v) in ring_samples(rr, &dist, m, w, (&col, &row), SHAPE_D) {
                acc[b].0 += v;
                acc[b].1 += 1;
                idx.push((i as u32, b as u8));
            }
            if !idx.is_empty() {
                nears.push(Near { mask: Plane { w, h, data: foot.iter().map(|&f| f as u8 as f32).collect() }, idx });
            }
        }
    }
    if nears.is_empty() || (1..=3).any(|b| acc[b].1 < 30) {
        return None;
    }
    let prof: Vec<f64> = (0..=SHAPE_D).map(|b| if acc[b].1 > 0 { acc[b].0 / acc[b].1 as f64 } else { 0.0 }).collect();
    let sd1 = noise.sd(0.0).max(0.3);
    let z1 = prof[1] / (sd1 / (acc[1].1 as f64).sqrt());
    if prof[1] <= 0.0 {
        return None;
    }
    // Template of the footprint spread by a Gaussian of std s, in the same bins; the amplitude
    // is free (weighted least squares with the bins' pixel counts).
    let template = |s: f64| -> Vec<f64> {
        let mut t = vec![(0.0f64, 0usize); SHAPE_D + 1];
        for nr in &nears {
            let g = nr.mask.gaussian(s as f32);
            for &(i, b) in &nr.idx {
                t[b as usize].0 += g.data[i as usize] as f64;
                t[b as usize].1 += 1;
            }
        }
        t.iter().map(|&(v, n)| if n > 0 { v / n as f64 } else { 0.0 }).collect()
    };
    let cost = |s: f64| -> f64 {
        let t = template(s);
        let (mut stt, mut spt) = (0.0, 0.0);
        for b in 1..=SHAPE_D {
            let wgt = acc[b].1 as f64;
            stt += wgt * t[b] * t[b];
            spt += wgt * prof[b] * t[b];
        }
        if stt <= 0.0 {
            return f64::INFINITY;
        }
        let a = (spt / stt).max(0.0);
        (1..=SHAPE_D).map(|b| acc[b].1 as f64 * (prof[b] - a * t[b]).powi(2)).sum()
    };
    // Log grid over the library's range, then golden refinement around the best node.
    let grid: Vec<f64> = (0..=20).map(|j| 0.3 * (8.0f64 / 0.3).powf(j as f64 / 20.0)).collect();
    let costs: Vec<f64> = grid.iter().map(|&s| cost(s)).collect();
    let (s, _) = stats::golden_around_best(&mut |s| cost(s), &grid, &costs, 12);
    let ev = format!(
        "halo shape (smear's column/row offsets read beyond {SHAPE_FAR_PX:.0} px and removed; distance from the real saturated footprint): {:.2}, {:.2}, {:.2}, {:.2} DN at 1-4 px (z = {z1:.1} at 1 px), fall-off fitted by a Gaussian spread of {s:.2} px with a free amplitude",
        prof[1], prof[2], prof[3], prof[4]
    );
    Some((s, z1, ev))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// (h28diag) A plateau at a full well below the top code carries only the read noise: its
    /// scatter is floored there (not the shot noise of the noise model at that level), and none
    /// of it is at the top code. A level clipped at the top code has half or more there.
    #[test]
    fn plateau_scatter_of_a_full_well_is_the_read_noise() {
        let mut nm = NoiseModel::prior(1.0);
        nm.a = 2.25;
        nm.b = 1.0 / 6.0;
        let flat = vec![251.0; 120];
        let (sd, top) = plateau_scatter(&flat, &nm);
        assert!((sd - (2.25f64 + 1.0 / 12.0).sqrt()).abs() < 1e-9, "sd {sd}");
        assert!(sd < 0.5 * nm.sd(251.0), "read noise only, well under the shot noise at 251 DN");
        assert_eq!(top, 0.0);
        // Noisy values around full scale, clipped at the top code: half or more at the top.
        let clipped: Vec<f64> = (0..200).map(|i| (250.0 + (i % 11) as f64).min(255.0)).collect();
        let (sd_c, top_c) = plateau_scatter(&clipped, &nm);
        assert!(top_c >= 0.5, "top share {top_c}");
        assert!(sd_c >= (2.25f64 + 1.0 / 12.0).sqrt());
    }
    /// The halo's spread is read on its shape, whatever its size and beside smear: a saturated
    /// disc whose excess spills with an exponential kernel (per-axis std 1.68 px; not the
    /// library's Gaussian), once at a small excess and once at a ten times larger one, with a
    /// strong vertical smear (its columns carry more than the halo at 1 px). The reading is the
    /// same for both sizes and near the kernel's std.
    #[test]
    fn halo_shape_spread_reads_the_fall_off_not_the_size_beside_smear() {
        let (w, h) = (200usize, 160usize);
        let disc = |x: usize, y: usize| (x as f64 - 100.0).powi(2) + (y as f64 - 80.0).powi(2) < 64.0;
        // Exponential spill kernel exp(-r / 1.0) (per-axis std about 1.68 px), radius 6.
        let kern: Vec<(isize, isize, f64)> = {
            let mut k = Vec::new();
            for dy in -6isize..=6 {
                for dx in -6isize..=6 {
                    let r = ((dx * dx + dy * dy) as f64).sqrt();
                    if r > 0.0 && r <= 6.0 {
                        k.push((dx, dy, (-r).exp()));
                    }
                }
            }
            let s: f64 = k.iter().map(|t| t.2).sum();
            k.into_iter().map(|(a, b, v)| (a, b, v / s)).collect()
        };
        let read = |excess: f64| {
            let mut sim = Plane::filled(w, h, 40.0);
            let mut real = Plane::filled(w, h, 40.0);
            for y in 0..h {
                for x in 0..w {
                    if disc(x, y) {
                        sim.data[y * w + x] = 255.0;
                        real.data[y * w + x] = 240.0;
                    }
                }
            }
            let mut spill = vec![0.0f64; w * h];
            for y in 0..h {
                for x in 0..w {
                    if disc(x, y) {
                        for &(dx, dy, v) in &kern {
                            let (xx, yy) = ((x as isize + dx) as usize, (y as isize + dy) as usize);
                            if !disc(xx, yy) {
                                spill[yy * w + xx] += excess * v;
                            }
                        }
                    }
                }
            }
            for x in 0..w {
                let n = (0..h).filter(|&y| disc(x, y)).count() as f64;
                for y in 0..h {
                    let i = y * w + x;
                    if !disc(x, y) {
                        // Smear: 0.003 FS per saturated pixel of the column, along the whole column.
                        real.data[i] += (spill[i] + 0.003 * 255.0 * n) as f32;
                        // Deterministic texture-free "noise" (a small checkerboard).
                        real.data[i] += if (x + y) % 2 == 0 { 0.5 } else { -0.5 };
                    }
                }
            }
            let f = super::super::img::frame_from_planes(
                std::slice::from_ref(&sim),
                &crate::frame::Frame::new(w as u32, h as u32, crate::frame::PixelFormat::Mono8).unwrap(),
            );
            let g = super::super::img::frame_from_planes(std::slice::from_ref(&real), &f);
            let r1 = vec![vec![real.sub(&sim)]];
            let masks = vec![Masks::compute(std::slice::from_ref(&sim))];
            let pairs = vec![Pair { name: "0".into(), sim_frame: f, real_frame: g, sim: vec![sim], real: vec![real] }];
            let mut nm = NoiseModel::prior(1.0);
            nm.a = 0.25;
            halo_shape_spread(&pairs, &masks, &r1, 240.0, 0.3, &nm, false).expect("halo measurable").0
        };
        let (small, large) = (read(20.0), read(200.0));
        assert!((1.0..=2.4).contains(&small), "small excess: {small}");
        assert!((small - large).abs() < 0.15 * small, "size-independent: {small} vs {large}");
    }
}
