//! Fixed patterns and noise structure: `prnu` (covariance of the relative high-passed residual
//! between frames), `hot_pixels` (isolated outliers that recur at the same place) and
//! `row_noise` (split-half covariance of row offsets).
//!
//! All three use the same trick to get an honest null: two measurements that share the effect
//! but not the noise (two frames for a fixed pattern, even and odd columns for a row offset).
//! Their covariance is zero without the effect whatever the noise model is, so no noise
//! calibration can fake a detection.

use super::common::{Masks, NoiseModel, RowOffsets};
use super::img::{FS, Pair, Plane};
use super::stats::{self, Wls};
use super::types::{Profile, Signature};

/// Relative change of the model level between two frames above which a textured pixel counts
/// as showing other scene content (see [`prnu`]).
pub const MOVED_FRACTION: f64 = 0.1;

/// PRNU by cross-frame covariance of the relative high-passed residual, on bright pixels that
/// are flat in both frames or whose scene content differs between them. Returns the signature
/// and the variance coefficient c = sigma² (0 when not detected) for the noise model.
pub fn prnu(
    pairs: &[Pair],
    masks: &[Masks],
    quiet: &[Vec<bool>],
    base: &[Vec<Plane>],
    noise: &NoiseModel,
    hot: &[Vec<bool>],
) -> (Signature, f64) {
    let mut sig = Signature::new("prnu");
    if pairs.len() < 2 {
        sig.evidence = "a single frame: a fixed pattern cannot be told from noise".into();
        return (sig, 0.0);
    }
    // Per frame: the relative high-passed residual u = hp(real - base) / base where usable.
    let us: Vec<Vec<Vec<f32>>> = pairs
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let (w, h) = (p.w(), p.h());
            (0..p.channels())
                .map(|c| {
                    let (s, r) = (&base[k][c].data, &p.real[c].data);
                    let mut u = vec![f32::NAN; w * h];
                    for y in 1..h.saturating_sub(1) {
                        for x in 1..w - 1 {
                            let i = y * w + x;
                            let cross = [i, i - 1, i + 1, i - w, i + w];
                            if masks[k].dist_sat.get(i) <= 3.0
                                || s[i] < 30.0
                                || cross.iter().any(|&j| hot[k][j] || r[j] <= 0.0 || r[j] >= FS)
                            {
                                continue;
                            }
                            let d = |j: usize| r[j] - s[j];
                            let hp5 = d(i) - 0.25 * (d(i - 1) + d(i + 1) + d(i - w) + d(i + w));
                            u[i] = hp5 / s[i];
                        }
                    }
                    u
                })
                .collect()
        })
        .collect();
    let mut wls = Wls::new(2);
    let mut npairs = 0;
    let mut nprod = 0usize;
    let max_pairs = 45;
    'outer: for a in 0..pairs.len() {
        for b in a + 1..pairs.len() {
            if npairs >= max_pairs {
                break 'outer;
            }
            let (pa, pb) = (&pairs[a], &pairs[b]);
            if pa.w() != pb.w() || pa.h() != pb.h() || pa.channels() != pb.channels() {
                continue;
            }
            npairs += 1;
            let w = pa.w();
            for c in 0..pa.channels() {
                let (sa, sb) = (&base[a][c].data, &base[b][c].data);
                let (ua, ub) = (&us[a][c], &us[b][c]);
                for i in 0..ua.len() {
                    let (u1, u2) = (ua[i] as f64, ub[i] as f64);
                    if !(u1.is_finite() && u2.is_finite()) {
                        continue;
                    }
                    let (s1, s2) = (sa[i] as f64, sb[i] as f64);
                    // A pixel flat in both frames, or one where the scene moved between the two
                    // frames (its level changed by MOVED_FRACTION or more): PRNU stays with the
                    // photosite, while a misfit of the model follows the scene's texture, so on
                    // textured pixels only products of different scene content keep the honest
                    // null. A static scene falls back to the flat pixels.
                    let flat = quiet[a][i] && quiet[b][i];
                    if !flat && (s1 - s2).abs() < MOVED_FRACTION * s1.max(s2) {
                        continue;
                    }
                    let v1 = 1.25 * noise.var(s1) / (s1 * s1);
                    let v2 = 1.25 * noise.var(s2) / (s2 * s2);
                    if u1.abs() > 8.0 * v1.sqrt() + 0.3 || u2.abs() > 8.0 * v2.sqrt() + 0.3 {
                        continue;
                    }
                    // E[u1 u2] = 1.25 sigma_p² + 1.25 d² / (s1 s2) (d: additive fixed pattern)
                    let cl = (npairs as u32) * 100_000 + (c * 10_000 + (i / w) / 16) as u32;
                    wls.push(&[1.25, 1.25 / (s1 * s2)], u1 * u2, 1.0 / (v1 * v2), cl);
                    nprod += 1;
                }
            }
        }
    }
    let Some(f) = wls.fit() else {
        sig.evidence = format!("too few bright pixels shared by two frames ({nprod})");
        return (sig, 0.0);
    };
    let s2 = f.beta[0];
    let se = f.se(0);
    let sd = s2.max(0.0).sqrt();
    sig.z = s2 / se;
    sig.size = sd;
    sig.size_unit = "relative gain sigma";
    sig.set_param("sigma", sd);
    sig.stderr = vec![("sigma".into(), se / (2.0 * sd.max(1e-3)))];
    sig.where_ = format!(
        "bright pixels flat in both frames or where the scene moved between them, {npairs} frame pairs ({nprod} pixel products)"
    );
    sig.evidence = format!(
        "relative residual correlates between frames: sigma² = {s2:.3e} ± {se:.1e} (z = {:.1}), additive fixed pattern {:.3} DN²",
        sig.z, f.beta[1]
    );
    let c = if sig.z > 4.0 { s2.max(0.0) } else { 0.0 };
    (sig, c)
}

/// Hot pixels: isolated positive outliers far above the noise, recurring in several frames.
/// Returns the signature, the per-frame outlier masks (to exclude them elsewhere), and the mean
/// excess of the hot pixels (DN).
pub fn hot_pixels(
    pairs: &[Pair],
    masks: &[Masks],
    quiet: &[Vec<bool>],
    q: &[Vec<Plane>],
    noise: &NoiseModel,
) -> (Signature, Vec<Vec<bool>>, f64) {
    let mut sig = Signature::new("hot_pixels");
    let mut cand: Vec<Vec<bool>> = Vec::new();
    let mut eligible: Vec<Vec<bool>> = Vec::new();
    let mut excess = Vec::new();
    for (k, p) in pairs.iter().enumerate() {
        let m = &masks[k];
        let (w, h) = (p.w(), p.h());
        let mut cm = vec![false; w * h];
        let mut el = vec![false; w * h];
        let z = |c: usize, i: usize| -> f64 {
            let qv = q[k][c].data[i] as f64;
            (p.real[c].data[i] as f64 - qv) / noise.sd(qv)
        };
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let i = y * w + x;
                if !quiet[k][i] || m.dist_sat.get(i) <= 3.0 || m.dist_edge.get(i) <= 2.0 {
                    continue;
                }
                el[i] = true;
                for c in 0..p.channels() {
                    let zc = z(c, i);
                    if zc < 7.0 || (p.real[c].data[i] as f64 - q[k][c].data[i] as f64) < 6.0 {
                        continue;
                    }
                    // isolated: the 8 neighbours are ordinary
                    let mut iso = true;
                    for (dx, dy) in [(-1isize, -1isize), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)] {
                        let j = ((y as isize + dy) as usize) * w + (x as isize + dx) as usize;
                        if z(c, j) > 4.0 {
                            iso = false;
                            break;
                        }
                    }
                    if iso {
                        cm[i] = true;
                        excess.push(p.real[c].data[i] as f64 - q[k][c].data[i] as f64);
                    }
                }
            }
        }
        cand.push(cm);
        eligible.push(el);
    }
    let n = pairs.len();
    let same_size = pairs.iter().all(|p| p.w() == pairs[0].w() && p.h() == pairs[0].h());
    let npix = pairs[0].w() * pairs[0].h();
    let (count, elig, recurrence) = if n >= 2 && same_size {
        let mut count = 0usize;
        let mut elig = 0usize;
        for i in 0..npix {
            let ne = (0..n).filter(|&k| eligible[k][i]).count();
            if ne >= 2 {
                elig += 1;
                let nc = (0..n).filter(|&k| cand[k][i]).count();
                if nc >= 2 && nc * 2 >= ne {
                    count += 1;
                }
            }
        }
        (count, elig, true)
    } else {
        let count: usize = cand.iter().map(|c| c.iter().filter(|&&b| b).count()).sum();
        let elig: usize = eligible.iter().map(|c| c.iter().filter(|&&b| b).count()).sum();
        (count, elig, false)
    };
    // Expected false candidates: Gaussian tail beyond 7 sigma with a large safety factor for
    // non-Gaussian tails; with recurrence, the square of a per-frame rate.
    let chans = pairs[0].channels() as f64;
    let p1 = 1e-9 * chans;
    let lambda0 = if recurrence { elig as f64 * (p1 * 1e3).powi(2) * n as f64 } else { elig as f64 * p1 * 100.0 };
    let min_count = if recurrence { 3.0 } else { 10.0 };
    sig.z = if (count as f64) < min_count { 0.0 } else { (count as f64 - lambda0) / (lambda0 + 1.0).sqrt() };
    let rate = if elig > 0 { count as f64 / elig as f64 } else { 0.0 };
    let mean_excess = if excess.is_empty() { 0.0 } else { stats::median(&excess) };
    sig.size = rate;
    sig.size_unit = "fraction of pixels";
    sig.set_param("rate", rate);
    sig.set_param("offset_dn", mean_excess);
    sig.stderr = vec![("rate".into(), (count as f64).sqrt().max(1.0) / elig.max(1) as f64)];
    sig.where_ = format!("{count} isolated pixels{}", if recurrence { " recurring across frames" } else { "" });
    sig.evidence = format!(
        "{count} of {elig} eligible pixels are isolated outliers above 7 sigma{} (median excess {mean_excess:.1} DN; expected by chance {lambda0:.2})",
        if recurrence { " in at least two frames" } else { "" }
    );
    (sig, cand, mean_excess)
}

/// Across-frame products for [`row_noise`]: for each channel and row, over the frames that see
/// it (enough quiet lit pixels in even and odd columns; at least two), the deviation of each
/// frame's row mean from the mean over those frames, less the frame's own mean and linear trend
/// over y; the product of the even- and odd-column deviations, times K/(K−1) for the K frames
/// seeing that row, has expectation sigma² (the offsets are independent between frames, pixel
/// noise between columns). Cluster = (channel, block of 8 rows), all frames together.
/// `None` with fewer than two frames or frames of different heights.
fn across_frames(means: &[Vec<(Vec<f64>, Vec<f64>)>]) -> Option<Vec<(f64, usize)>> {
    let nk = means.len();
    if nk < 2 {
        return None;
    }
    let nc = means[0].len();
    let h = means[0].first()?.0.len();
    if means.iter().any(|m| m.len() != nc || m.iter().any(|(e, o)| e.len() != h || o.len() != h)) {
        return None;
    }
    let mut out = Vec::new();
    for c in 0..nc {
        let seen = |k: usize, y: usize| means[k][c].0[y].is_finite() && means[k][c].1[y].is_finite();
        // Per row: number of frames seeing it and the mean over them (even, odd).
        let row_mean: Vec<Option<(f64, f64, f64)>> = (0..h)
            .map(|y| {
                let ks: Vec<usize> = (0..nk).filter(|&k| seen(k, y)).collect();
                if ks.len() < 2 {
                    return None;
                }
                let n = ks.len() as f64;
                let e = ks.iter().map(|&k| means[k][c].0[y]).sum::<f64>() / n;
                let o = ks.iter().map(|&k| means[k][c].1[y]).sum::<f64>() / n;
                Some((n, e, o))
            })
            .collect();
        for k in 0..nk {
            let rows: Vec<(usize, f64, f64, f64)> = (0..h)
                .filter(|&y| seen(k, y))
                .filter_map(|y| {
                    row_mean[y].map(|(n, e, o)| (y, n / (n - 1.0), means[k][c].0[y] - e, means[k][c].1[y] - o))
                })
                .collect();
            if rows.len() < 16 {
                continue;
            }
            // The frame's least-squares line over y (mean and slope), per column half.
            let n = rows.len() as f64;
            let ym = rows.iter().map(|r| r.0 as f64).sum::<f64>() / n;
            let syy = rows.iter().map(|r| (r.0 as f64 - ym).powi(2)).sum::<f64>().max(1e-9);
            let line = |d: fn(&(usize, f64, f64, f64)) -> f64| {
                let a = rows.iter().map(d).sum::<f64>() / n;
                let b = rows.iter().map(|r| (r.0 as f64 - ym) * d(r)).sum::<f64>() / syy;
                (a, b)
            };
            let (ae, be) = line(|r| r.2);
            let (ao, bo) = line(|r| r.3);
            for &(y, f, de, dd) in &rows {
                let t = y as f64 - ym;
                out.push(((de - ae - be * t) * (dd - ao - bo * t) * f, c * (h / 8 + 1) + y / 8));
            }
        }
    }
    Some(out)
}

/// Row-to-row fluctuation of the residual (median of each row, less a running median over nine
/// rows), per frame and channel.
pub fn row_offsets(pairs: &[Pair], masks: &[Masks], resid: &[Vec<Plane>], hot: &[Vec<bool>]) -> RowOffsets {
    pairs
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let (w, h) = (p.w(), p.h());
            (0..p.channels())
                .map(|c| {
                    let rr = &resid[k][c].data;
                    let real = &p.real[c].data;
                    let med: Vec<f64> = (0..h)
                        .map(|y| {
                            let v: Vec<f64> = (0..w)
                                .map(|x| y * w + x)
                                .filter(|&i| {
                                    real[i] > 0.0 && real[i] < FS && !hot[k][i] && masks[k].dist_sat.get(i) > 3.0
                                })
                                .map(|i| rr[i] as f64)
                                .collect();
                            if v.len() >= 8 { stats::median(&v) } else { f64::NAN }
                        })
                        .collect();
                    (0..h)
                        .map(|y| {
                            if !med[y].is_finite() {
                                return 0.0;
                            }
                            let win: Vec<f64> = (y.saturating_sub(4)..(y + 5).min(h))
                                .map(|j| med[j])
                                .filter(|v| v.is_finite())
                                .collect();
                            (med[y] - stats::median(&win)) as f32
                        })
                        .collect()
                })
                .collect()
        })
        .collect()
}

/// Row noise by split-half covariance of row means (even vs odd columns, so pixel noise cancels).
///
/// Row noise is new every frame (EFFECTS.md), so with two or more frames the offsets are measured
/// against the mean over frames of each row: whatever does not change between frames (the scene,
/// a static model mismatch) cancels whatever its spatial frequency, and the RMS offset is found
/// whatever the offsets' spectrum along y — white, or 1/f with most of its power in slow drifts
/// over the frame. Each frame's mean and linear trend over y are removed first (a frame-wide
/// flicker or gradient change is not row noise). With one frame the second difference of row
/// means along y is used (white offsets only: it sees little of a 1/f spectrum).
pub fn row_noise(
    pairs: &[Pair],
    masks: &[Masks],
    quiet: &[Vec<bool>],
    r1: &[Vec<Plane>],
    q: &[Vec<Plane>],
    noise: &NoiseModel,
) -> Signature {
    let mut sig = Signature::new("row_noise");
    // (product, cluster): clusters of 8 consecutive rows, since neighbouring second differences
    // share rows.
    let mut prods: Vec<(f64, usize)> = Vec::new();
    let mut n_cluster = 0usize;
    let mut prof = Vec::new();
    // Row means per (frame, channel), for the across-frame estimator.
    let mut means: Vec<Vec<(Vec<f64>, Vec<f64>)>> = Vec::new();
    for (k, p) in pairs.iter().enumerate() {
        means.push(Vec::new());
        let m = &masks[k];
        let (w, h) = (p.w(), p.h());
        for c in 0..p.channels() {
            let rr = &r1[k][c].data;
            let qq = &q[k][c].data;
            let mut me = vec![f64::NAN; h];
            let mut mo = vec![f64::NAN; h];
            for y in 0..h {
                let (mut se, mut ne, mut so, mut no) = (0.0, 0usize, 0.0, 0usize);
                for x in 0..w {
                    let i = y * w + x;
                    if !quiet[k][i] || m.dist_sat.get(i) <= 6.0 {
                        continue;
                    }
                    let qv = qq[i] as f64;
                    // Dark pixels count too: clipping at 0 shrinks the offsets (on a mostly
                    // black sky the size comes out ~10 % low) but cannot create a covariance
                    // between even and odd columns; leaving them out leaves too few rows.
                    if p.real[c].data[i] >= FS {
                        continue;
                    }
                    let v = rr[i] as f64;
                    if v.abs() > 6.0 * noise.sd(qv) {
                        continue;
                    }
                    if x % 2 == 0 {
                        se += v;
                        ne += 1;
                    } else {
                        so += v;
                        no += 1;
                    }
                }
                if ne >= 8 && no >= 8 {
                    me[y] = se / ne as f64;
                    mo[y] = so / no as f64;
                }
            }
            for y in 1..h.saturating_sub(1) {
                let d2 = |m: &[f64]| m[y + 1] - 2.0 * m[y] + m[y - 1];
                let (a, b) = (d2(&me), d2(&mo));
                if a.is_finite() && b.is_finite() {
                    prods.push((a * b, n_cluster + y / 8));
                    if k == 0 && c == 0 {
                        prof.push((y as f64, 0.5 * (me[y] + mo[y]), me[y], mo[y]));
                    }
                }
            }
            n_cluster += h / 8 + 1;
            means[k].push((me, mo));
        }
    }
    let temporal = across_frames(&means);
    let (prods, scale, how) = match temporal {
        Some(t) if t.len() >= 30 => (t, 1.0, "across frames"),
        _ => (prods, 1.0 / 6.0, "second difference along y"),
    };
    if prods.len() < 30 {
        sig.evidence = format!("too few rows with quiet unclipped pixels ({})", prods.len());
        return sig;
    }
    // Winsorise the products at the 1 % tails (rows crossing structures).
    let mut sorted: Vec<f64> = prods.iter().map(|p| p.0).collect();
    let lo_q = stats::quantile_mut(&mut sorted, 0.01);
    let hi_q = stats::quantile_mut(&mut sorted, 0.99);
    let n = prods.len() as f64;
    let m = prods.iter().map(|p| p.0.clamp(lo_q, hi_q)).sum::<f64>() / n;
    // Cluster-robust standard error of the mean.
    // Sorted by cluster, so that the sum of squares is the same bits on every run.
    let mut cs: std::collections::BTreeMap<usize, f64> = std::collections::BTreeMap::new();
    for &(v, cl) in &prods {
        *cs.entry(cl).or_insert(0.0) += v.clamp(lo_q, hi_q) - m;
    }
    let g = cs.len() as f64;
    let se = (cs.values().map(|s| s * s).sum::<f64>() * g / (g - 1.0).max(1.0)).sqrt() / n;
    let s2 = m * scale;
    let se2 = se * scale;
    let sd = s2.max(0.0).sqrt();
    sig.z = s2 / se2;
    sig.size = sd;
    sig.size_unit = "DN row offset sigma";
    sig.set_param("sigma_dn", sd);
    sig.stderr = vec![("sigma_dn".into(), se2 / (2.0 * sd.max(0.05)))];
    sig.where_ = format!("{} row products ({how}) in all frames", prods.len());
    sig.evidence = format!(
        "row offsets shared by even and odd columns ({how}): sigma² = {s2:.4} ± {se2:.4} DN² (z = {:.1})",
        sig.z
    );
    sig.profiles.push(Profile {
        title: "row noise: row means of the residual, even vs odd columns (first frame)".into(),
        x_label: "row y (px)".into(),
        y_label: "row mean residual (DN)".into(),
        x: prof.iter().map(|p| p.0).collect(),
        series: vec![
            ("even columns".into(), prof.iter().map(|p| p.2).collect()),
            ("odd columns".into(), prof.iter().map(|p| p.3).collect()),
        ],
    });
    sig
}
