//! Unpaired mode (`--unpaired`): sim and real show different scenes (different poses, objects,
//! backgrounds), so pixels cannot be compared; statistics that describe the *camera* rather than
//! the scene are compared instead, and the effects that close the gap are fitted by moment
//! matching through the library's forward models (the sim set is pushed through the candidate
//! model and the same statistic re-measured).
//!
//! | statistic (per image, pooled per set) | effect |
//! |---|---|
//! | noise floor: low quantile of 8x8-block variances of the 5-point high-pass, per level | `gaussian_noise`, `shot_noise` |
//! | edge spread: second moment of the gradient profile across strong isolated edges | `defocus` |
//! | mean level against distance from saturated regions, and the saturated fraction | `blooming` (with its exposure gain) |
//! | level of the darkest region (interval-censored fit, so clipped noise does not bias it) | `dark_current` |
//! | dark-background level of each column/row against its saturated pixels | `smear` |
//! | registration of the red and blue planes against green at edges | `channel_shift` |
//! | isolated outliers above their 3x3 median | `hot_pixels` |
//! | covariance of row means between even and odd columns | `row_noise` |
//! | DCT quantisation lattice of the real images | `jpeg` |
//!
//! Significance: every gap (real minus sim) gets a standard error by bootstrapping the images
//! of both sets, so the scatter between scenes counts against it; a finding needs `z` above the
//! threshold and a material size. Tone (gain, gamma), vignetting and stray light are not
//! identifiable from different scenes and are not fitted here (the histograms are still
//! compared in `fit`).

use super::common::{NoiseBin, NoiseModel};
use super::fit::{FitMetrics, canonical_of, mean_metrics, round_sig};
use super::img::{FS, Plane, SAT_DN, distance_transform, luma, planes_of};
use super::report::{Alternative, Finding, FitSummary, Report, TestRow, UnpairedReport};
use super::{DiagnoseError, Options, Profile, Signature, jpeg, stats};
use crate::config::FaultConfig;
use crate::faults::{Params, registry};
use crate::frame::{Frame, FrameData, PixelFormat};
use crate::rng::Rng;

/// Halo profile length (px).
const HALO: usize = 24;
/// Level bins of the noise floor (DN).
const NBIN: f64 = 16.0;
/// Bootstrap replicates over images.
const BOOT: usize = 60;

/// Per-image measurements.
#[derive(Debug, Clone, Default)]
struct ImStats {
    /// (level, variance of the high-pass) per 8x8 block.
    blocks: Vec<(f32, f32)>,
    /// Second moments (px²) of gradient profiles across edges.
    widths: Vec<f32>,
    halo_sum: Vec<f64>,
    halo_n: Vec<f64>,
    far: (f64, f64),
    sat: usize,
    pixels: usize,
    /// Level of the darkest region (censored fit) and its noise variance.
    dark: Option<f64>,
    dark_var: Option<f64>,
    /// Smear regressions: (beta DN per saturated pixel, se) for columns and rows.
    smear: [Option<(f64, f64)>; 2],
    /// Shifts of red and blue against green (dx_r, dy_r, dx_b, dy_b).
    shift: Option<[f64; 4]>,
    /// Hot-pixel candidates and eligible pixels.
    hot: (f64, f64),
    hot_excess: Vec<f64>,
    /// Row-noise products (sum, count).
    row: (f64, f64),
}

/// One image ready for measurement.
struct Image {
    frame: Frame,
}

impl Image {
    fn planes(&self) -> Vec<Plane> {
        planes_of(&self.frame)
    }
}

/// Frame converted to Mono8 luma (when the sets differ in channels).
fn to_mono(f: &Frame) -> Frame {
    let g = luma(&planes_of(f));
    let data: Vec<u8> = g.data.iter().map(|v| v.round().clamp(0.0, 255.0) as u8).collect();
    Frame::from_data(f.width, f.height, f.width as usize, PixelFormat::Mono8, FrameData::U8(data))
        .unwrap_or_else(|_| f.clone())
}

/// Measure one image. `noise_sd` is a rough noise scale for thresholds.
fn measure(planes: &[Plane], noise_sd: f64) -> ImStats {
    let (w, h) = (planes[0].w, planes[0].h);
    let grey = luma(planes);
    let mut st =
        ImStats { pixels: w * h, halo_sum: vec![0.0; HALO + 1], halo_n: vec![0.0; HALO + 1], ..Default::default() };
    let sat: Vec<bool> = (0..w * h).map(|i| planes.iter().any(|p| p.data[i] >= SAT_DN)).collect();
    st.sat = sat.iter().filter(|&&s| s).count();
    let dist = distance_transform(&sat, w, h);
    // ---- noise floor: 8x8 blocks of the 5-point high-pass, every channel ----
    for p in planes {
        for by in 0..(h.saturating_sub(2)) / 8 {
            for bx in 0..(w.saturating_sub(2)) / 8 {
                let mut v = Vec::with_capacity(64);
                let mut lvl = 0.0;
                for y in by * 8 + 1..by * 8 + 9 {
                    for x in bx * 8 + 1..bx * 8 + 9 {
                        let i = y * w + x;
                        let nb = [i, i - 1, i + 1, i - w, i + w];
                        if nb.iter().any(|&j| p.data[j] <= 0.0 || p.data[j] >= FS) || dist[i] <= 3.0 {
                            continue;
                        }
                        let d = &p.data;
                        v.push((d[i] - 0.25 * (d[i - 1] + d[i + 1] + d[i - w] + d[i + w])) as f64);
                        lvl += d[i] as f64;
                    }
                }
                if v.len() >= 48 {
                    let n = v.len() as f64;
                    let m = v.iter().sum::<f64>() / n;
                    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
                    st.blocks.push(((lvl / n) as f32, var as f32));
                }
            }
        }
    }
    // ---- edge spread ----
    let gx = |x: usize, y: usize| 0.5 * (grey.at(x + 1, y) - grey.at(x - 1, y));
    let gy = |x: usize, y: usize| 0.5 * (grey.at(x, y + 1) - grey.at(x, y - 1));
    let mut gm = Plane::new(w, h);
    for y in 1..h.saturating_sub(1) {
        for x in 1..w - 1 {
            gm.data[y * w + x] = (gx(x, y).powi(2) + gy(x, y).powi(2)).sqrt();
        }
    }
    let tg = (6.0 * noise_sd).max(12.0) as f32;
    let step = ((w * h) / 200_000).max(1);
    for y in (6..h.saturating_sub(6)).step_by(step) {
        for x in 6..w.saturating_sub(6) {
            let i = y * w + x;
            let g0 = gm.data[i];
            if g0 < tg || dist[i] <= 5.0 {
                continue;
            }
            let (nx, ny) = (gx(x, y) / g0, gy(x, y) / g0);
            let at = |t: f32| gm.bilinear(x as f32 + t * nx, y as f32 + t * ny);
            if at(1.0) > g0 || at(-1.0) > g0 {
                continue; // not the maximum across the edge
            }
            // Step height across the edge and the peak gradient: a step of height c blurred to
            // a Gaussian edge of std s has a peak gradient c / (s sqrt(2π)).
            let iv = |t: f32| grey.bilinear(x as f32 + t * nx, y as f32 + t * ny);
            let prof: Vec<f32> = (-3..=3).map(|t| iv(t as f32)).collect();
            let contrast = prof[6] - prof[0];
            if contrast < 3.0 * tg {
                continue;
            }
            // Monotone across the edge (a step, not a thin line or a corner).
            if prof.windows(2).any(|p| p[1] < p[0] - 0.1 * contrast) {
                continue;
            }
            let s = contrast / (g0 * (2.0 * std::f32::consts::PI).sqrt());
            st.widths.push(s * s);
        }
    }
    // ---- halo around saturated regions ----
    if st.sat >= 10 {
        for i in 0..w * h {
            let d = dist[i];
            if sat[i] || !d.is_finite() {
                continue;
            }
            let v = grey.data[i] as f64;
            let b = d.round() as usize;
            if (1..=HALO).contains(&b) {
                st.halo_sum[b] += v;
                st.halo_n[b] += 1.0;
            } else if (28.0..=44.0).contains(&d) {
                st.far.0 += v;
                st.far.1 += 1.0;
            }
        }
    }
    // ---- darkest region: censored fit of the pixels whose 15x15 mean is in the lowest 20 % (a
    // wide mean, so that the selection does not pick the low tail of the noise) ----
    let sm = grey.box_mean(2);
    let wide = grey.box_mean(7);
    let mut sv: Vec<f64> = wide.data.iter().map(|&v| v as f64).collect();
    let p20 = stats::quantile_mut(&mut sv, 0.20);
    let sel = p20 + 2.0 * noise_sd / 15.0 + 0.5;
    let dark_px: Vec<usize> = (0..w * h).filter(|&i| (wide.data[i] as f64) <= sel && dist[i] > 8.0).collect();
    let dark_thr = sel + 2.0 * noise_sd + 1.0;
    if p20 < 40.0 && dark_px.len() >= 200 {
        // Per channel (the noise of one sample, like the high-pass bins), then averaged. A
        // region clipped at 0 DN almost everywhere (a rendered black sky) identifies neither
        // level nor noise — the censored likelihood keeps growing as the level falls — so its
        // level is taken as 0 DN (the largest the data allow) and its noise as unknown.
        let fits: Vec<(f64, Option<f64>)> = planes
            .iter()
            .filter_map(|p| {
                let lit = dark_px.iter().filter(|&&i| p.data[i] > 0.0).count();
                if (lit as f64) < 0.01 * dark_px.len() as f64 {
                    return Some((0.0, None));
                }
                let obs: Vec<(f32, f32)> = dark_px.iter().map(|&i| (0.0, p.data[i])).collect();
                super::noise::censored_offset_fit(&obs, 1.0).map(|(mu, sigma, _, _)| (mu, Some(sigma * sigma)))
            })
            .collect();
        if !fits.is_empty() {
            let n = fits.len() as f64;
            st.dark = Some(fits.iter().map(|f| f.0).sum::<f64>() / n);
            st.dark_var = fits.iter().map(|f| f.1).sum::<Option<f64>>().map(|v| v / n);
        }
    }
    // ---- smear: background level of each column / row against its saturated pixels: the
    // median of the line's pixels away from saturation and not far above the dark level (the
    // median, so that dark parts of the object crossing the line do not count; the headroom, so
    // that the smear itself does).
    let head = dark_thr + 40.0;
    if st.sat > 0 && st.dark.is_some() {
        for (dir, vertical) in [true, false].iter().enumerate() {
            let (nl, len) = if *vertical { (w, h) } else { (h, w) };
            let mut wls = stats::Wls::new(4);
            let mut any_sat = false;
            for l in 0..nl {
                let mut nsat = 0usize;
                let mut vals = Vec::new();
                for t in 0..len {
                    let i = if *vertical { t * w + l } else { l * w + t };
                    if sat[i] {
                        nsat += 1;
                    } else if dist[i] > 20.0 && (sm.data[i] as f64) <= head {
                        vals.push(grey.data[i] as f64);
                    }
                }
                if vals.len() < 10 {
                    continue;
                }
                any_sat |= nsat > 0;
                let m = stats::median(&vals);
                let tt = 2.0 * l as f64 / (nl.max(2) - 1) as f64 - 1.0;
                let var = (noise_sd * noise_sd).max(0.1) / vals.len() as f64;
                wls.push(&[1.0, tt, tt * tt, nsat as f64], m, 1.0 / var, (l / 4) as u32);
            }
            if any_sat && let Some(f) = wls.fit() {
                st.smear[dir] = Some((f.beta[3], f.se(3)));
            }
        }
    }
    // ---- channel registration ----
    if planes.len() == 3 {
        let pts: Vec<usize> = (0..w * h)
            .filter(|&i| {
                let (x, y) = (i % w, i / w);
                x >= 4 && y >= 4 && x + 4 < w && y + 4 < h && gm.data[i] >= tg && dist[i] > 4.0
            })
            .step_by(((w * h) / 40_000).max(1))
            .collect();
        if pts.len() >= 200 {
            let g = &planes[1];
            let mut out = [0.0; 4];
            for (ci, c) in [0usize, 2].iter().enumerate() {
                let tgt = &planes[*c];
                let loss = |d: &[f64]| -> f64 {
                    // C(x) ≈ a G(x - d) + b with a, b by least squares.
                    let (mut sx, mut sy, mut sxx, mut sxy, mut n) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    let vals: Vec<(f64, f64)> = pts
                        .iter()
                        .map(|&i| {
                            let (x, y) = ((i % w) as f32, (i / w) as f32);
                            (g.bilinear(x - d[0] as f32, y - d[1] as f32) as f64, tgt.data[i] as f64)
                        })
                        .collect();
                    for &(a, b) in &vals {
                        sx += a;
                        sy += b;
                        sxx += a * a;
                        sxy += a * b;
                        n += 1.0;
                    }
                    let den = (n * sxx - sx * sx).max(1e-9);
                    let al = (n * sxy - sx * sy) / den;
                    let be = (sy - al * sx) / n;
                    vals.iter().map(|&(a, b)| (b - al * a - be).powi(2)).sum::<f64>()
                };
                let best = stats::nelder_mead(&loss, &[0.0, 0.0], &[0.4, 0.4], 120, 1e-10);
                out[ci * 2] = best[0].clamp(-4.0, 4.0);
                out[ci * 2 + 1] = best[1].clamp(-4.0, 4.0);
            }
            st.shift = Some(out);
        }
    }
    // ---- hot pixels: isolated outliers above the 3x3 median ----
    let thr = (8.0 * noise_sd).max(25.0) as f32;
    for p in planes {
        for y in 1..h.saturating_sub(1) {
            for x in 1..w - 1 {
                let i = y * w + x;
                if dist[i] <= 3.0 {
                    continue;
                }
                let mut nb = [0f32; 8];
                for (slot, (dx, dy)) in
                    nb.iter_mut().zip([(-1isize, -1isize), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)])
                {
                    *slot = p.at_clamped(x as isize + dx, y as isize + dy);
                }
                nb.sort_by(|a, b| a.total_cmp(b));
                let med = 0.5 * (nb[3] + nb[4]);
                if med > 200.0 {
                    continue;
                }
                st.hot.1 += 1.0;
                let spread = nb[6] - nb[1];
                if p.data[i] - med >= thr && spread < 0.5 * thr {
                    st.hot.0 += 1.0;
                    st.hot_excess.push((p.data[i] - med) as f64);
                }
            }
        }
    }
    // ---- row noise: split-half covariance of row means over the dark background ----
    let mut me = vec![f64::NAN; h];
    let mut mo = vec![f64::NAN; h];
    for y in 0..h {
        let (mut se, mut ne, mut so, mut no) = (0.0, 0.0, 0.0, 0.0);
        for x in 0..w {
            let i = y * w + x;
            if dist[i] <= 8.0 || (sm.data[i] as f64) > dark_thr + 8.0 || grey.data[i] >= FS {
                continue;
            }
            if x % 2 == 0 {
                se += grey.data[i] as f64;
                ne += 1.0;
            } else {
                so += grey.data[i] as f64;
                no += 1.0;
            }
        }
        if ne >= 16.0 && no >= 16.0 {
            me[y] = se / ne;
            mo[y] = so / no;
        }
    }
    for y in 1..h.saturating_sub(1) {
        let a = me[y + 1] - 2.0 * me[y] + me[y - 1];
        let b = mo[y + 1] - 2.0 * mo[y] + mo[y - 1];
        if a.is_finite() && b.is_finite() {
            st.row.0 += a * b / 6.0;
            st.row.1 += 1.0;
        }
    }
    st
}

/// Statistics of a set of images (a bootstrap sample of them).
#[derive(Debug, Clone, Default)]
struct SetStats {
    /// (level, floor variance, blocks, homogeneity q10/q50 of the block variances).
    noise: Vec<(f64, f64, usize, f64)>,
    /// Noise of the darkest region: (level, variance, images).
    dark_noise: Option<(f64, f64, usize)>,
    width: Option<f64>,
    halo: Vec<f64>,
    sat_frac: f64,
    dark: Option<f64>,
    smear: [Option<f64>; 2],
    shift: Option<[f64; 4]>,
    hot_rate: f64,
    row: Option<f64>,
}

/// Quantile of chi²_ν/ν used to turn the low quantile of block variances into a variance.
fn chi2_quantile_factor(q: f64, nu: f64) -> f64 {
    // Wilson–Hilferty: chi²_ν/ν ≈ (1 - 2/(9ν) + z sqrt(2/(9ν)))³.
    let z = -inv_norm(1.0 - q);
    let h = 2.0 / (9.0 * nu);
    (1.0 - h + z * h.sqrt()).powi(3)
}

fn inv_norm(p: f64) -> f64 {
    crate::faults::gaussian_noise::inverse_normal_cdf(p)
}

fn combine(items: &[&ImStats]) -> SetStats {
    let mut s = SetStats::default();
    // Noise floor per level bin.
    let nb = (FS as f64 / NBIN).ceil() as usize;
    let mut bins: Vec<Vec<f64>> = vec![Vec::new(); nb];
    for it in items {
        for &(l, v) in &it.blocks {
            bins[((l as f64 / NBIN) as usize).min(nb - 1)].push(v as f64);
        }
    }
    let f10 = chi2_quantile_factor(0.1, 50.0);
    for (b, v) in bins.iter_mut().enumerate() {
        if v.len() < 20 {
            continue;
        }
        let q = stats::quantile_mut(v, 0.1);
        let q50 = stats::quantile_mut(v, 0.5);
        let homog = if q50 > 0.0 { q / q50 } else { 1.0 };
        s.noise.push(((b as f64 + 0.5) * NBIN, (q / f10 / 1.25 - 1.0 / 12.0).max(0.0), v.len(), homog));
    }
    // The darkest region's censored fit replaces the lowest bin (clipping biases the high-pass).
    let dv: Vec<(f64, f64)> = items.iter().filter_map(|it| it.dark.zip(it.dark_var)).collect();
    if !dv.is_empty() {
        let lvl = stats::median(&dv.iter().map(|d| d.0).collect::<Vec<_>>());
        let var = stats::median(&dv.iter().map(|d| d.1).collect::<Vec<_>>());
        s.noise.retain(|b| b.0 > NBIN);
        s.dark_noise = Some((lvl.max(0.0), var, dv.len()));
    }
    let mut widths: Vec<f64> = items.iter().flat_map(|it| it.widths.iter().map(|&v| v as f64)).collect();
    if widths.len() >= 30 {
        s.width = Some(stats::median_mut(&mut widths));
    }
    let (mut fs, mut fnn) = (0.0, 0.0);
    let mut hs = [0.0; HALO + 1];
    let mut hn = [0.0; HALO + 1];
    for it in items {
        fs += it.far.0;
        fnn += it.far.1;
        for d in 1..=HALO {
            hs[d] += it.halo_sum[d];
            hn[d] += it.halo_n[d];
        }
    }
    if fnn > 50.0 {
        let far = fs / fnn;
        s.halo = (1..=HALO).map(|d| if hn[d] > 5.0 { hs[d] / hn[d] - far } else { f64::NAN }).collect();
    }
    let px: usize = items.iter().map(|it| it.pixels).sum();
    s.sat_frac = items.iter().map(|it| it.sat).sum::<usize>() as f64 / px.max(1) as f64;
    let darks: Vec<f64> = items.iter().filter_map(|it| it.dark).collect();
    if !darks.is_empty() {
        s.dark = Some(stats::median(&darks));
    }
    for d in 0..2 {
        let (mut sw, mut sb) = (0.0, 0.0);
        for it in items {
            if let Some((b, se)) = it.smear[d] {
                let w = 1.0 / (se * se).max(1e-9);
                sw += w;
                sb += w * b;
            }
        }
        if sw > 0.0 {
            s.smear[d] = Some(sb / sw);
        }
    }
    let shifts: Vec<[f64; 4]> = items.iter().filter_map(|it| it.shift).collect();
    if !shifts.is_empty() {
        let mut o = [0.0; 4];
        for (k, v) in o.iter_mut().enumerate() {
            *v = stats::median(&shifts.iter().map(|s| s[k]).collect::<Vec<_>>());
        }
        s.shift = Some(o);
    }
    let (hc, he) = items.iter().fold((0.0, 0.0), |a, it| (a.0 + it.hot.0, a.1 + it.hot.1));
    s.hot_rate = if he > 0.0 { hc / he } else { 0.0 };
    let (rs, rn) = items.iter().fold((0.0, 0.0), |a, it| (a.0 + it.row.0, a.1 + it.row.1));
    if rn >= 30.0 {
        s.row = Some(rs / rn);
    }
    s
}

/// Noise gap (real - sim) fitted as a + b L; returns (a, b, slope identified). Level bins count
/// only where the sim has flat blocks at that level (its floor at most 30 % of the real's), so
/// that scene texture, which differs between the sets, is not read as noise; the darkest
/// regions count through their censored fits.
fn noise_gap(r: &SetStats, s: &SetStats) -> Option<(f64, f64, bool)> {
    let mut pts: Vec<(f64, f64, f64)> = Vec::new();
    if let (Some(rd), Some(sd)) = (r.dark_noise, s.dark_noise) {
        pts.push((rd.0, rd.1 - sd.1, 2000.0 * rd.2 as f64 / (rd.1 * rd.1).max(0.01)));
    }
    for &(l, v, n, homog) in &r.noise {
        let Some(sv) = s.noise.iter().find(|b| (b.0 - l).abs() < 1e-9).map(|b| b.1) else { continue };
        // Usable: the sim is flat there, and the real's blocks at this level look like noise
        // (their variances are as homogeneous as chi-square scatter allows; texture spreads
        // them: for 50 degrees of freedom q10/q50 ≈ 0.75).
        if sv > 0.3 * v + 0.1 || homog < 0.55 {
            continue;
        }
        pts.push((l, v - sv, n as f64 / (v * v).max(0.01)));
    }
    if pts.is_empty() {
        return None;
    }
    let lo = pts.iter().map(|p| p.0).fold(f64::INFINITY, f64::min);
    let hi = pts.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
    let ident = hi - lo >= 48.0 && pts.len() >= 3;
    if ident {
        let mut w = stats::Wls::new(2);
        for (i, p) in pts.iter().enumerate() {
            w.push(&[1.0, p.0], p.1, p.2, i as u32);
        }
        if let Some(f) = w.fit()
            && f.beta[1] >= 0.0
        {
            return Some((f.beta[0], f.beta[1], true));
        }
    }
    let sw: f64 = pts.iter().map(|p| p.2).sum();
    Some((pts.iter().map(|p| p.1 * p.2).sum::<f64>() / sw.max(1e-12), 0.0, false))
}

/// A scalar gap with its bootstrap standard error.
#[derive(Debug, Clone, Copy)]
struct Gap {
    value: f64,
    se: f64,
}

impl Gap {
    fn z(&self) -> f64 {
        if self.se > 0.0 { self.value / self.se } else { 0.0 }
    }
}

fn boot_se(vals: &[f64]) -> f64 {
    let v: Vec<f64> = vals.iter().copied().filter(|x| x.is_finite()).collect();
    if v.len() < 5 {
        return f64::INFINITY;
    }
    let (m, _) = stats::mean_se(&v);
    (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

/// Every gap statistic between a real and a sim set summary.
fn gaps(r: &SetStats, s: &SetStats) -> Vec<(&'static str, f64)> {
    let mut out = Vec::new();
    if let Some((a, b, _)) = noise_gap(r, s) {
        out.push(("noise_a", a));
        out.push(("noise_b", b));
    }
    if let (Some(a), Some(b)) = (r.width, s.width) {
        out.push(("width", a - b));
    }
    if !r.halo.is_empty() && !s.halo.is_empty() {
        let m = |h: &[f64]| h[..4].iter().copied().filter(|v| v.is_finite()).sum::<f64>() / 4.0;
        out.push(("halo", m(&r.halo) - m(&s.halo)));
    }
    out.push(("sat_frac", r.sat_frac - s.sat_frac));
    if let (Some(a), Some(b)) = (r.dark, s.dark) {
        out.push(("dark", a - b));
    }
    for (d, name) in [(0usize, "smear_v"), (1, "smear_h")] {
        if let (Some(a), Some(b)) = (r.smear[d], s.smear[d]) {
            out.push((name, a - b));
        }
    }
    if let (Some(a), Some(b)) = (r.shift, s.shift) {
        for (k, name) in ["dx_r", "dy_r", "dx_b", "dy_b"].iter().enumerate() {
            out.push((name, a[k] - b[k]));
        }
    }
    out.push(("hot", r.hot_rate - s.hot_rate));
    if let (Some(a), Some(b)) = (r.row, s.row) {
        out.push(("row", a - b));
    }
    out
}

/// Gaps with bootstrap standard errors (resampling the images of both sets).
fn gaps_with_se(real: &[ImStats], sim: &[ImStats], seed: u64) -> Vec<(&'static str, Gap)> {
    let rr: Vec<&ImStats> = real.iter().collect();
    let ss: Vec<&ImStats> = sim.iter().collect();
    let point = gaps(&combine(&rr), &combine(&ss));
    let mut rng = Rng::new(seed ^ 0xb00f);
    let mut reps: Vec<Vec<(&'static str, f64)>> = Vec::new();
    for _ in 0..BOOT {
        let rb: Vec<&ImStats> =
            (0..real.len()).map(|_| &real[(rng.uniform() * real.len() as f64) as usize % real.len()]).collect();
        let sb: Vec<&ImStats> =
            (0..sim.len()).map(|_| &sim[(rng.uniform() * sim.len() as f64) as usize % sim.len()]).collect();
        reps.push(gaps(&combine(&rb), &combine(&sb)));
    }
    // Counting statistics: a Poisson floor on the standard error (few images, few counts).
    let (rc, re) = real.iter().fold((0.0, 0.0), |a, it| (a.0 + it.hot.0, a.1 + it.hot.1));
    let (sc, se_) = sim.iter().fold((0.0, 0.0), |a, it| (a.0 + it.hot.0, a.1 + it.hot.1));
    let hot_floor = ((rc.max(1.0) / (re * re).max(1.0)) + (sc.max(1.0) / (se_ * se_).max(1.0))).sqrt();
    point
        .into_iter()
        .map(|(n, v)| {
            let vals: Vec<f64> = reps.iter().filter_map(|r| r.iter().find(|x| x.0 == n).map(|x| x.1)).collect();
            let mut se = boot_se(&vals);
            if n == "hot" {
                se = se.max(hot_floor);
            }
            (n, Gap { value: v, se })
        })
        .collect()
}

fn gap_of(g: &[(&'static str, Gap)], name: &str) -> Option<Gap> {
    g.iter().find(|x| x.0 == name).map(|x| x.1)
}

/// Push frames through a fitted config (with its noise, seeded).
fn apply_all(cfg: &FaultConfig, frames: &[Frame]) -> Result<Vec<Frame>, DiagnoseError> {
    let mut chain = crate::faults::chain::Chain::from_config(cfg)?;
    let mut rep = crate::faults::chain::FrameReport::default();
    let mut out = Vec::with_capacity(frames.len());
    for (k, f) in frames.iter().enumerate() {
        let mut g = f.clone();
        g.seq = k as u64;
        chain.apply(&mut g, &mut rep)?;
        out.push(g);
    }
    Ok(out)
}

fn measure_frames(frames: &[Frame], noise_sd: f64) -> Vec<ImStats> {
    frames.iter().map(|f| measure(&planes_of(f), noise_sd)).collect()
}

fn params_of(name: &str, vals: &[(&str, f64)]) -> Option<Params> {
    let reg = registry::find(name)?;
    let mut p = Params::defaults(reg.info);
    for (n, v) in vals {
        if let Some((_, spec)) = reg.info.param(n) {
            let _ = p.set(n, v.clamp(spec.min, spec.max));
        }
    }
    Some(p)
}

/// A finding for `sig` with the parameters `vals` of the library effect `name` (see
/// [`params_of`]).
fn finding(sig: &Signature, name: &str, vals: &[(&str, f64)], stat: &'static str, method: &str) -> Option<UFinding> {
    params_of(name, vals).map(|params| UFinding {
        sig: sig.clone(),
        params,
        stat,
        method: method.into(),
        alternatives: Vec::new(),
    })
}

/// One unpaired finding before it goes into the report.
struct UFinding {
    sig: Signature,
    params: Params,
    /// Name of the gap statistic that measures it (for loss before/after).
    stat: &'static str,
    method: String,
    /// Readings the unpaired data cannot tell from this one (same signature).
    alternatives: Vec<Alternative>,
}

fn pooled_hist(frames: &[Frame]) -> Vec<f64> {
    let mut h = vec![0.0; 256];
    for f in frames {
        let g = crate::metrics::Grey::from_frame(f);
        for (a, b) in h.iter_mut().zip(crate::metrics::histogram(&g).iter()) {
            *a += b / frames.len() as f64;
        }
    }
    h
}

fn quantiles(h: &[f64]) -> Vec<f64> {
    let mut out = Vec::new();
    let mut cum = 0.0;
    let mut k = 0;
    for q in 1..100 {
        let t = q as f64 / 100.0;
        while k < h.len() && cum + h[k] < t {
            cum += h[k];
            k += 1;
        }
        out.push(k.min(255) as f64);
    }
    out
}

/// Set-level metrics: RMS difference of the pooled quantile functions (DN), correlation of the
/// pooled histograms, and the mean FQI of sim i against real i (mod the real count).
fn set_metrics(model: &[Frame], real: &[Frame]) -> FitMetrics {
    let (hm, hr) = (pooled_hist(model), pooled_hist(real));
    let (qm, qr) = (quantiles(&hm), quantiles(&hr));
    let rmse = (qm.iter().zip(&qr).map(|(a, b)| (a - b).powi(2)).sum::<f64>() / qm.len() as f64).sqrt();
    let mut fq = Vec::new();
    for (i, m) in model.iter().enumerate() {
        let r = &real[i % real.len()];
        let v = super::fit::metrics_of(m, r);
        fq.push(v);
    }
    let f = mean_metrics(&fq);
    FitMetrics { rmse, fqi: f.fqi, hist_corr: crate::metrics::hist_correlation_hist(&hm, &hr) }
}

/// RMS difference of the pooled quantile functions over the darker (q1–q49) and the brighter
/// (q50–q99) half of the levels, DN.
fn quantile_halves(model: &[Frame], real: &[Frame]) -> (f64, f64) {
    let (qm, qr) = (quantiles(&pooled_hist(model)), quantiles(&pooled_hist(real)));
    let rms = |r: std::ops::Range<usize>| {
        let n = r.len() as f64;
        (r.map(|i| (qm[i] - qr[i]).powi(2)).sum::<f64>() / n).sqrt()
    };
    (rms(0..49), rms(49..qm.len()))
}

/// When a fit statistic is worse after the fit than before, a note naming it and saying why, as
/// far as the quantile functions tell: which half of the levels the fitted model brought closer
/// and which it moved apart. `halves_*`: [`quantile_halves`] before and after.
fn worse_note(before: &FitMetrics, after: &FitMetrics, hb: (f64, f64), ha: (f64, f64)) -> Option<String> {
    let mut worse = Vec::new();
    if after.rmse > before.rmse + 1e-9 {
        worse.push(format!("quantile RMSE {:.1} → {:.1} DN", before.rmse, after.rmse));
    }
    if after.hist_corr < before.hist_corr - 1e-9 {
        worse.push(format!("histogram correlation {:.3} → {:.3}", before.hist_corr, after.hist_corr));
    }
    if let (Some(b), Some(a)) = (before.fqi, after.fqi)
        && a < b - 1e-9
    {
        worse.push(format!("FQI {b:.3} → {a:.3}"));
    }
    if worse.is_empty() {
        return None;
    }
    let half = |name: &str, b: f64, a: f64| {
        format!("{name} {} (RMS {b:.1} → {a:.1} DN)", if a < b { "closer" } else { "further apart" })
    };
    let why = if (ha.0 < hb.0) != (ha.1 < hb.1) {
        " The fitted camera effects move every level of the sims alike, but the two sets differ in scene content \
         (different scenes, unpaired), so one half of the levels gets closer while the other moves apart: \
         no camera effect of the model explains that difference."
    } else {
        ""
    };
    Some(format!(
        "worse after the fit: {}; pooled quantiles: {}, {}.{why}",
        worse.join(", "),
        half("darker half (q1–q49)", hb.0, ha.0),
        half("brighter half (q50–q99)", hb.1, ha.1),
    ))
}

/// A uniform additive level in the darkest regions has three physical readings that unpaired
/// images without dark frames cannot tell apart: a thermal level (`dark_current`, the one
/// reported), an electronic black-level offset (`gain_offset.offset_dn`) and uniform light from
/// a source outside the frame (`stray_light`). In-frame veiling glare is tested on its own
/// (`glare` = its test's z and whether it was found).
fn uniform_level_alternatives(level: f64, z: f64, glare: (f64, bool)) -> Vec<Alternative> {
    let glare_text = if glare.0.is_finite() {
        format!(
            "in-frame veiling glare was tested on its own (z = {:.1}, {}), so the level left is the part no source inside the frame predicts",
            glare.0,
            if glare.1 { "fitted before this level" } else { "not established" }
        )
    } else {
        "in-frame veiling glare could not be tested".into()
    };
    let alt = |effect: &str, label: String, what: &str| Alternative {
        effect: effect.into(),
        label,
        bic_gap: 0.0,
        z: round_sig(z, 4),
        evidence: format!(
            "{what} adds the same uniform {level:.1} DN over the darkest regions: without dark frames (or pairs of \
             the same scene) a thermal level cannot be told from it; {glare_text}"
        ),
    };
    vec![
        alt("gain_offset", format!("gain_offset.offset_dn = {level:.1}"), "an electronic black-level offset"),
        alt(
            "stray_light",
            "stray_light (uniform, from outside the frame)".into(),
            "light scattered from a source outside the frame",
        ),
    ]
}

/// Unpaired diagnosis.
pub fn run(
    sims: &[(String, Frame)],
    reals: &[(String, Frame)],
    opts: &Options,
) -> Result<UnpairedReport, DiagnoseError> {
    // Bootstrap standard errors from a handful of images are rough: keep a margin.
    let z_thr = (opts.z_threshold - 1.0).max(3.0);
    let mut notes = vec![
        "unpaired mode: sim and real show different scenes; statistics of the camera are compared, with standard errors from bootstrapping the images of both sets".to_string(),
    ];
    let same_channels = sims.iter().chain(reals).all(|(_, f)| f.channels() == sims[0].1.channels());
    let conv = |f: &Frame| -> Frame {
        let f = if f.format == PixelFormat::Mono16 {
            // Analysed in 8-bit DN like everything else.
            let p = planes_of(f);
            super::img::frame_from_planes(
                &p,
                &Frame::new(f.width, f.height, PixelFormat::Mono8).unwrap_or_else(|_| f.clone()),
            )
        } else {
            f.clone()
        };
        if same_channels { f } else { to_mono(&f) }
    };
    if !same_channels {
        notes.push("sim and real differ in channels: both analysed as grey (luma)".into());
    }
    let sim_frames: Vec<Frame> = sims.iter().map(|(_, f)| conv(f)).collect();
    let real_frames: Vec<Frame> = reals.iter().map(|(_, f)| conv(f)).collect();
    let sims_img: Vec<Image> = sim_frames.iter().map(|f| Image { frame: f.clone() }).collect();
    let reals_img: Vec<Image> = real_frames.iter().map(|f| Image { frame: f.clone() }).collect();
    // A rough noise scale for the thresholds: median high-pass MAD of the real images.
    let noise_sd = {
        let v: Vec<f64> = reals_img
            .iter()
            .map(|im| {
                let g = luma(&im.planes());
                let (w, h) = (g.w, g.h);
                let mut d = Vec::new();
                for y in (1..h.saturating_sub(1)).step_by(2) {
                    for x in 1..w - 1 {
                        let i = y * w + x;
                        d.push(
                            (g.data[i] - 0.25 * (g.data[i - 1] + g.data[i + 1] + g.data[i - w] + g.data[i + w])) as f64,
                        );
                    }
                }
                stats::mad_sigma(&d) / 1.118
            })
            .collect();
        stats::median(&v).max(0.5)
    };
    let real_st: Vec<ImStats> = reals_img.iter().map(|im| measure(&im.planes(), noise_sd)).collect();
    let sim_st: Vec<ImStats> = sims_img.iter().map(|im| measure(&im.planes(), noise_sd)).collect();
    let g0 = gaps_with_se(&real_st, &sim_st, opts.seed);
    let rr: Vec<&ImStats> = real_st.iter().collect();
    let ss: Vec<&ImStats> = sim_st.iter().collect();
    let (rset, sset) = (combine(&rr), combine(&ss));
    let like = &real_frames[0];
    let mut found: Vec<UFinding> = Vec::new();
    let mut tests: Vec<Signature> = Vec::new();
    // ---- camera noise ----
    let mut noise_model: Option<NoiseModel> = None;
    if let (Some(a), Some(b)) = (gap_of(&g0, "noise_a"), gap_of(&g0, "noise_b")) {
        let ident = noise_gap(&rset, &sset).map(|x| x.2).unwrap_or(false);
        let mut nm = NoiseModel::prior(1.0);
        nm.a = a.value.max(0.0);
        nm.se_a = a.se;
        nm.b = if ident { b.value.max(0.0) } else { 0.0 };
        nm.se_b = b.se;
        nm.bins = rset.noise.iter().map(|&(l, v, n, _)| NoiseBin { level: l, var: v, n }).collect();
        nm.fit_range =
            (rset.noise.first().map(|b| b.0).unwrap_or(0.0), rset.noise.last().map(|b| b.0).unwrap_or(FS as f64));
        nm.slope_identified = ident;
        let (mut gn, mut sn) = super::locate::camera_noise(&nm, z_thr);
        gn.where_ = "flat blocks of the real images (noise floor above the sim's)".into();
        gn.evidence = format!(
            "noise floor of real minus sim: {:.3} ± {:.3} DN² at zero signal ({} level bins; sim floor {:.3} DN²)",
            a.value,
            a.se,
            rset.noise.len(),
            sset.noise.first().map(|b| b.1).unwrap_or(0.0)
        );
        sn.evidence = format!(
            "noise floor slope real minus sim: {:.4} ± {:.4} DN²/DN{}",
            b.value,
            b.se,
            if ident { "" } else { " (levels too narrow: slope not identified)" }
        );
        gn.z = a.z();
        sn.z = if ident { b.z() } else { 0.0 };
        gn.detected = gn.z > z_thr && nm.a.sqrt() >= 0.3;
        sn.detected = sn.z > z_thr && nm.b > 1e-3;
        for s in [gn, sn] {
            if s.detected
                && let Some((p, method, _, _)) = super::moments::calibrate(&s, &nm, 0.0, like, opts.seed)
            {
                found.push(UFinding {
                    sig: s.clone(),
                    params: p,
                    stat: if s.effect == "gaussian_noise" { "noise_a" } else { "noise_b" },
                    method,
                    alternatives: Vec::new(),
                });
            }
            tests.push(s);
        }
        noise_model = Some(nm);
    } else {
        let mut gn = Signature::new("gaussian_noise");
        gn.evidence = "noise floor at zero signal not measurable in one of the sets (no noise level bins, e.g. a \
                       rendered black sky clipped at 0 DN in every dark pixel): camera noise not compared"
            .into();
        tests.push(gn);
    }
    let noise_cfg = |found: &[UFinding]| -> Vec<Params> {
        found.iter().filter(|f| matches!(f.sig.effect, "gaussian_noise" | "shot_noise")).map(|f| f.params).collect()
    };
    // ---- edge spread → defocus ----
    let mut def = Signature::new("defocus");
    if let Some(gw) = gap_of(&g0, "width") {
        def.z = gw.z();
        def.size = gw.value;
        def.size_unit = "px² edge spread (real - sim)";
        def.where_ = format!(
            "strong isolated edges ({} real, {} sim)",
            rr.iter().map(|s| s.widths.len()).sum::<usize>(),
            ss.iter().map(|s| s.widths.len()).sum::<usize>()
        );
        def.evidence = format!(
            "median second moment of the gradient profile across edges: real {:.3} px², sim {:.3} px² (gap {:.3} ± {:.3}, z = {:.1})",
            rset.width.unwrap_or(f64::NAN),
            sset.width.unwrap_or(f64::NAN),
            gw.value,
            gw.se,
            def.z
        );
        def.detected = def.z > z_thr && gw.value > 0.05;
        if def.detected {
            // Moment matching: defocus (with the fitted camera noise) on the sims until the
            // median edge spread equals the real one.
            let target = rset.width.unwrap_or(0.0);
            let base = noise_cfg(&found);
            let mut eval = |sigma: f64| -> f64 {
                let mut ps = base.clone();
                if let Some(p) = params_of("defocus", &[("sigma_px", sigma)]) {
                    ps.push(p);
                }
                let cfg = FaultConfig::from_effects(opts.seed, ps);
                match apply_all(&cfg, &sim_frames) {
                    Ok(fr) => {
                        let st = measure_frames(&fr, noise_sd);
                        let refs: Vec<&ImStats> = st.iter().collect();
                        combine(&refs).width.map(|w| (w - target).powi(2)).unwrap_or(f64::INFINITY)
                    }
                    Err(_) => f64::INFINITY,
                }
            };
            let hi = (3.0 * gw.value.max(0.05).sqrt()).clamp(1.0, 8.0);
            let (sig_px, _) = stats::golden(&mut eval, 0.0, hi, 14);
            def.set_param("sigma_px", sig_px);
            found.extend(finding(
                &def,
                "defocus",
                &[("sigma_px", sig_px)],
                "width",
                "moment matching: median edge spread of the sims through the library defocus (with the fitted noise)",
            ));
        }
    } else {
        def.evidence = "too few strong isolated edges in one of the sets".into();
    }
    tests.push(def);
    // ---- veiling glare (before blooming and the dark level: glare lifts the sky next to bright
    // sources and the dark regions too) ----
    let mut g_halo = g0.clone();
    let mut glare_p: Option<Params> = None;
    let mut dark_gap = gap_of(&g0, "dark");
    let mut after_glare = "";
    let glare_test: (f64, bool);
    {
        let base = noise_cfg(&found);
        let mut apply = |p: Params| {
            let mut ps = base.clone();
            ps.push(p);
            apply_all(&FaultConfig::from_effects(opts.seed, ps), &sim_frames)
        };
        let gl = super::glare::unpaired(&real_frames, &sim_frames, z_thr, noise_sd, opts.seed, &mut apply)?;
        if let Some(p) = gl.params {
            // The dark level and the halo left once the sims carry the fitted glare: only
            // what is left is uniform, or blooming.
            let st = measure_frames(&apply(p)?, noise_sd);
            let g = gaps_with_se(&real_st, &st, opts.seed ^ 2);
            dark_gap = gap_of(&g, "dark");
            after_glare = " after the fitted veiling glare";
            g_halo = g;
            glare_p = Some(p);
            found.push(UFinding {
                sig: gl.sig.clone(),
                params: p,
                stat: "",
                method: gl.method,
                alternatives: Vec::new(),
            });
        }
        glare_test = (gl.sig.z, gl.sig.detected);
        tests.push(gl.sig);
    }
    // ---- halo and saturation → blooming ----
    let mut bl = Signature::new("blooming");
    match (gap_of(&g_halo, "halo"), gap_of(&g_halo, "sat_frac")) {
        (Some(gh), Some(gs)) => {
            bl.z = gh.z();
            bl.size = gh.value;
            bl.size_unit = "DN mean excess at 1-4 px from saturation (real - sim)";
            bl.where_ = "around saturated regions".into();
            bl.evidence = format!(
                "mean level 1-4 px from saturated regions above the level at 28-44 px: real exceeds sim by {:.2} ± {:.2} DN (z = {:.1}); saturated fraction real {:.4} vs sim {:.4}",
                gh.value, gh.se, bl.z, rset.sat_frac, sset.sat_frac
            );
            if glare_p.is_some() {
                bl.evidence.push_str(" (sims through the fitted veiling glare)");
            }
            bl.detected = bl.z > z_thr && gh.value > 1.0;
            if bl.detected {
                // Fit exposure gain and spread so the sims' halo and saturated fraction match.
                let target_h = rset.halo.clone();
                let target_s = rset.sat_frac;
                let se_h = gh.se.max(0.5);
                let se_s = gs.se.max(1e-4);
                let base: Vec<Params> = noise_cfg(&found).into_iter().chain(glare_p).collect();
                let eval2 = |g: f64, sp: f64| -> f64 {
                    let mut ps = base.clone();
                    if let Some(p) =
                        params_of("blooming", &[("full_well_fraction", 1.0), ("spread_px", sp), ("exposure_gain", g)])
                    {
                        ps.push(p);
                    }
                    let cfg = FaultConfig::from_effects(opts.seed, ps);
                    match apply_all(&cfg, &sim_frames) {
                        Ok(fr) => {
                            let st = measure_frames(&fr, noise_sd);
                            let refs: Vec<&ImStats> = st.iter().collect();
                            let c = combine(&refs);
                            if c.halo.is_empty() {
                                return 1e12;
                            }
                            let mut l = 0.0;
                            for (a, b) in c.halo.iter().zip(&target_h).take(12) {
                                if a.is_finite() && b.is_finite() {
                                    l += ((a - b) / se_h).powi(2);
                                }
                            }
                            l + ((c.sat_frac - target_s) / se_s).powi(2)
                        }
                        Err(_) => f64::INFINITY,
                    }
                };
                let (mut g, mut sp) = (1.0f64, 1.5f64);
                for _ in 0..2 {
                    let (lg, _) = stats::golden(&mut |u| eval2(u.exp(), sp), 0.0, (6.0f64).ln(), 10);
                    g = lg.exp();
                    let (s2, _) = stats::golden(&mut |s| eval2(g, s), 0.3, 8.0, 10);
                    sp = s2;
                }
                bl.set_param("full_well_fraction", 1.0);
                bl.set_param("spread_px", sp);
                bl.set_param("exposure_gain", g);
                found.extend(finding(
                    &bl,
                    "blooming",
                    &[("full_well_fraction", 1.0), ("spread_px", sp), ("exposure_gain", g)],
                    "halo",
                    "moment matching: halo profile and saturated fraction of the sims through the library blooming (exposure gain, spread)",
                ));
            }
        }
        _ => bl.evidence = "no saturated regions in one of the sets: blooming cannot be compared".into(),
    }
    tests.push(bl);
    // ---- dark level ----
    let mut dk = Signature::new("dark_current");
    if let Some(gd) = dark_gap {
        dk.z = gd.z();
        dk.size = gd.value;
        dk.size_unit = "DN";
        dk.where_ = "darkest 10 % of each image".into();
        dk.evidence = format!(
            "censored level of the darkest regions: real {:.2} DN, sim {:.2} DN (gap{after_glare} {:.2} ± {:.2}, z = {:.1})",
            rset.dark.unwrap_or(f64::NAN),
            sset.dark.unwrap_or(f64::NAN),
            gd.value,
            gd.se,
            dk.z
        );
        dk.detected = dk.z > z_thr && gd.value >= 1.0;
        if dk.detected {
            let gain = found
                .iter()
                .find(|f| f.sig.effect == "shot_noise")
                .map(|f| f.params.get("gain_e_per_dn"))
                .unwrap_or(1e3);
            dk.set_param("mean_dn", gd.value);
            found.extend(
                finding(
                    &dk,
                    "dark_current",
                    &[("mean_dn", gd.value), ("hot_pixel_rate", 0.0), ("gain_e_per_dn", gain)],
                    "dark",
                    "level difference of the darkest regions (censored fits)",
                )
                .map(|mut f| {
                    f.alternatives = uniform_level_alternatives(gd.value, dk.z, glare_test);
                    f
                }),
            );
        }
    } else {
        dk.evidence = "no dark region (10 % of the pixels below 40 DN) in one of the sets".into();
    }
    tests.push(dk);
    // ---- smear ----
    let mut sm = Signature::new("smear");
    let sv = gap_of(&g0, "smear_v");
    let sh = gap_of(&g0, "smear_h");
    let best = [(sv, "vertical"), (sh, "horizontal")]
        .into_iter()
        .filter_map(|(g, d)| g.map(|g| (g, d)))
        .max_by(|a, b| a.0.z().total_cmp(&b.0.z()));
    if let Some((g, dir)) = best {
        sm.z = g.z();
        sm.size = g.value;
        sm.size_unit = "DN per saturated pixel";
        sm.where_ = format!(
            "dark background of {} through saturated pixels",
            if dir == "vertical" { "columns" } else { "rows" }
        );
        sm.evidence = format!(
            "dark-background level rises by {:.3} ± {:.3} DN per saturated pixel of the line more in real than in sim (z = {:.1})",
            g.value, g.se, sm.z
        );
        sm.detected = sm.z > z_thr && g.value / FS as f64 >= 5e-4;
        if sm.detected {
            sm.set_param("strength", g.value / FS as f64);
            sm.choices.push(("direction".into(), dir.into()));
            if let Some(mut p) = params_of("smear", &[("strength", g.value / FS as f64)]) {
                let _ = p.set_choice("direction", dir);
                found.push(UFinding {
                    sig: sm.clone(),
                    params: p,
                    stat: if dir == "vertical" { "smear_v" } else { "smear_h" },
                    method: "regression of line levels on saturated counts (real minus sim)".into(),
                    alternatives: Vec::new(),
                });
            }
        }
    } else {
        sm.evidence = "no saturated pixels with dark background: smear cannot be compared".into();
    }
    tests.push(sm);
    // ---- channel shift ----
    let mut cs = Signature::new("channel_shift");
    let comps: Vec<Option<Gap>> = ["dx_r", "dy_r", "dx_b", "dy_b"].iter().map(|n| gap_of(&g0, n)).collect();
    if comps.iter().all(|c| c.is_some()) {
        let c: Vec<Gap> = comps.into_iter().flatten().collect();
        let chi: f64 = c.iter().map(|g| g.z().powi(2)).sum();
        cs.z = stats::chi2_to_z(chi, 4.0);
        cs.size = c.iter().fold(0.0f64, |m, g| m.max(g.value.abs()));
        cs.size_unit = "px (largest component)";
        cs.where_ = "edges; red and blue planes against green".into();
        cs.evidence = format!(
            "registration real minus sim: R {:+.2},{:+.2} px, B {:+.2},{:+.2} px (chi2 = {chi:.1} on 4 df, z = {:.1})",
            c[0].value, c[1].value, c[2].value, c[3].value, cs.z
        );
        cs.detected = cs.z > z_thr && cs.size >= 0.15;
        if cs.detected {
            let vals: Vec<(&str, f64)> =
                ["dx_r", "dy_r", "dx_b", "dy_b"].iter().zip(&c).map(|(n, g)| (*n, g.value)).collect();
            for (n, v) in &vals {
                cs.set_param(n, *v);
            }
            found.extend(finding(
                &cs,
                "channel_shift",
                &vals,
                "dx_r",
                "edge registration of the planes (real minus sim)",
            ));
        }
    } else {
        cs.evidence = "not colour, or too few edges: channel shift cannot be compared".into();
    }
    tests.push(cs);
    // ---- hot pixels ----
    let mut hp = Signature::new("hot_pixels");
    if let Some(g) = gap_of(&g0, "hot") {
        hp.z = g.z();
        hp.size = g.value;
        hp.size_unit = "fraction of pixels";
        hp.where_ = "isolated outliers above their 3x3 median".into();
        let ex: Vec<f64> = real_st.iter().flat_map(|s| s.hot_excess.iter().copied()).collect();
        let excess = if ex.is_empty() { 0.0 } else { stats::median(&ex) };
        hp.evidence = format!(
            "isolated outlier rate real {:.2e} vs sim {:.2e} (gap z = {:.1}; median excess {excess:.0} DN)",
            rset.hot_rate, sset.hot_rate, hp.z
        );
        hp.detected = hp.z > z_thr && g.value > 2e-5;
        if hp.detected {
            hp.set_param("rate", g.value);
            hp.set_param("offset_dn", excess);
            found.extend(finding(
                &hp,
                "hot_pixels",
                &[("rate", g.value), ("offset_dn", excess)],
                "hot",
                "outlier rate difference",
            ));
        }
    }
    tests.push(hp);
    // ---- row noise ----
    let mut rn = Signature::new("row_noise");
    if let Some(g) = gap_of(&g0, "row") {
        rn.z = g.z();
        rn.size = g.value.max(0.0).sqrt();
        rn.size_unit = "DN row offset sigma";
        rn.where_ = "rows of the dark background".into();
        rn.evidence = format!(
            "row-offset variance shared by even and odd columns: real minus sim {:.4} ± {:.4} DN² (z = {:.1})",
            g.value, g.se, rn.z
        );
        rn.detected = rn.z > z_thr && rn.size >= 0.2;
        if rn.detected {
            rn.set_param("sigma_dn", rn.size);
            found.extend(finding(
                &rn,
                "row_noise",
                &[("sigma_dn", rn.size)],
                "row",
                "split-half covariance of row means (real minus sim)",
            ));
        }
    } else {
        rn.evidence = "no dark background rows in one of the sets".into();
    }
    tests.push(rn);
    // ---- JPEG ----
    let rp: Vec<Vec<Plane>> = real_frames.iter().map(planes_of).collect();
    let sp: Vec<Vec<Plane>> = sim_frames.iter().map(planes_of).collect();
    let rref: Vec<&[Plane]> = rp.iter().map(|v| v.as_slice()).collect();
    let sref: Vec<&[Plane]> = sp.iter().map(|v| v.as_slice()).collect();
    let mut jp = jpeg::test_planes(&rref, &sref);
    jp.detected = jp.z > z_thr.max(8.0) && jp.param("quality").unwrap_or(100.0) < 98.0;
    if jp.detected {
        let q = jp.param("quality").unwrap_or(90.0).round();
        found.extend(finding(
            &jp,
            "jpeg",
            &[("quality", q)],
            "",
            "quality from the DCT quantisation lattice (libjpeg tables)",
        ));
    }
    tests.push(jp);
    // ---- the fitted model and the gaps after ----
    let cfg_params: Vec<Params> = found.iter().map(|f| f.params).collect();
    let mut config = FaultConfig::from_effects(opts.seed, cfg_params);
    config.origin = "fitted by faultcam diagnose --unpaired".into();
    let model_frames = apply_all(&config, &sim_frames)?;
    let model_st = measure_frames(&model_frames, noise_sd);
    let g1 = gaps_with_se(&real_st, &model_st, opts.seed ^ 1);
    let ms: Vec<&ImStats> = model_st.iter().collect();
    let mset = combine(&ms);
    let mut findings = Vec::new();
    for f in &found {
        let (lb, la) = match (gap_of(&g0, f.stat), gap_of(&g1, f.stat)) {
            (Some(b), Some(a)) => (b.z().powi(2), (a.value / b.se.max(1e-12)).powi(2)),
            _ => (f.sig.z.max(0.0).powi(2), f64::NAN),
        };
        findings.push(Finding {
            effect: f.sig.effect.to_string(),
            params: canonical_of(&f.params).into_iter().collect(),
            loss_before: round_sig(lb, 6),
            loss_after: round_sig(la, 6),
            where_: f.sig.where_.clone(),
            evidence: f.sig.evidence.clone(),
            z: round_sig(f.sig.z, 4),
            stderr: f.sig.stderr.iter().map(|(n, v)| (n.clone(), serde_json::Value::from(round_sig(*v, 4)))).collect(),
            method: f.method.clone(),
            alternatives: f.alternatives.clone(),
        });
    }
    // Most significant first.
    findings.sort_by(|a, b| b.z.total_cmp(&a.z));
    let before = set_metrics(&sim_frames, &real_frames);
    let after = set_metrics(&model_frames, &real_frames);
    if let Some(n) = worse_note(
        &before,
        &after,
        quantile_halves(&sim_frames, &real_frames),
        quantile_halves(&model_frames, &real_frames),
    ) {
        notes.push(n);
    }
    let report = Report {
        findings,
        fit: FitSummary { before: rounded(before), after: rounded(after) },
        model: "fitted.toml".into(),
        mode: "unpaired".into(),
        pairs: sims.len().min(reals.len()),
        rmse_after_with_noise: round_sig(after.rmse, 6),
        tests: tests.iter().map(TestRow::of).collect(),
        selection: Vec::new(),
        dropped: Vec::new(),
        notes: {
            notes.push(format!(
                "{} sim and {} real images; rough noise scale {:.2} DN; not fitted unpaired: gain, gamma, vignetting, stray light, motion blur, lens flare (scene-dependent)",
                sims.len(),
                reals.len(),
                noise_sd
            ));
            notes.push("fit.rmse here is the RMS difference of the pooled quantile functions (DN); fit.fqi the mean FQI of sim i against real i".into());
            notes
        },
    };
    let profiles = profiles(&rset, &sset, &mset, &real_frames, &sim_frames, &model_frames, noise_model.as_ref());
    let lines = vec![format!(
        "{} sim images vs {} real images (different scenes). Model: [`fitted.toml`](fitted.toml).",
        sims.len(),
        reals.len()
    )];
    Ok(UnpairedReport { report, config, profiles, lines })
}

fn rounded(m: FitMetrics) -> FitMetrics {
    FitMetrics { rmse: round_sig(m.rmse, 6), fqi: m.fqi.map(|v| round_sig(v, 6)), hist_corr: round_sig(m.hist_corr, 6) }
}

#[allow(clippy::too_many_arguments)]
fn profiles(
    r: &SetStats,
    s: &SetStats,
    m: &SetStats,
    real: &[Frame],
    sim: &[Frame],
    model: &[Frame],
    _noise: Option<&NoiseModel>,
) -> Vec<Profile> {
    let mut out = Vec::new();
    // Noise floors.
    let levels: Vec<f64> = (0..16).map(|b| (b as f64 + 0.5) * NBIN).collect();
    let floor = |st: &SetStats| -> Vec<f64> {
        levels
            .iter()
            .map(|l| st.noise.iter().find(|b| (b.0 - l).abs() < 1e-9).map(|b| b.1).unwrap_or(f64::NAN))
            .collect()
    };
    out.push(Profile {
        title: "noise floor against level".into(),
        x_label: "block mean level (DN)".into(),
        y_label: "noise variance floor (DN²)".into(),
        x: levels.clone(),
        series: vec![("real".into(), floor(r)), ("sim".into(), floor(s)), ("sim through the model".into(), floor(m))],
    });
    if !r.halo.is_empty() {
        let x: Vec<f64> = (1..=HALO).map(|d| d as f64).collect();
        let pad = |h: &[f64]| if h.is_empty() { vec![f64::NAN; HALO] } else { h.to_vec() };
        out.push(Profile {
            title: "halo: mean level against distance from saturated regions".into(),
            x_label: "distance from the saturated region (px)".into(),
            y_label: "mean level minus the level at 28-44 px (DN)".into(),
            x,
            series: vec![
                ("real".into(), pad(&r.halo)),
                ("sim".into(), pad(&s.halo)),
                ("sim through the model".into(), pad(&m.halo)),
            ],
        });
    }
    let x: Vec<f64> = (0..256).map(|v| v as f64).collect();
    out.push(Profile {
        title: "pooled grey histograms".into(),
        x_label: "grey level (DN)".into(),
        y_label: "fraction of pixels".into(),
        x,
        series: vec![
            ("real".into(), pooled_hist(real)),
            ("sim".into(), pooled_hist(sim)),
            ("sim through the model".into(), pooled_hist(model)),
        ],
    });
    out
}

#[cfg(test)]
mod note_tests {
    use super::*;

    fn m(rmse: f64, hist_corr: f64, fqi: f64) -> FitMetrics {
        FitMetrics { rmse, fqi: Some(fqi), hist_corr }
    }

    #[test]
    fn a_statistic_worse_after_the_fit_is_named_with_the_half_that_moved_apart() {
        // Darker half closer, brighter half further: the RMSE got worse, the correlation better.
        let n = worse_note(&m(52.2, -0.01, 0.765), &m(63.6, 0.68, 0.764), (40.0, 60.0), (5.0, 90.0))
            .expect("a note when the RMSE is worse");
        assert!(n.contains("quantile RMSE 52.2 → 63.6 DN"), "{n}");
        assert!(n.contains("FQI 0.765 → 0.764"), "{n}");
        assert!(!n.contains("histogram correlation"), "{n}");
        assert!(n.contains("darker half (q1–q49) closer (RMS 40.0 → 5.0 DN)"), "{n}");
        assert!(n.contains("brighter half (q50–q99) further apart (RMS 60.0 → 90.0 DN)"), "{n}");
        assert!(n.contains("scene content"), "{n}");
        // Everything better: no note.
        assert!(worse_note(&m(52.2, 0.1, 0.70), &m(12.0, 0.9, 0.71), (40.0, 60.0), (5.0, 8.0)).is_none());
        // Worse in both halves: named, but not blamed on the scenes.
        let n = worse_note(&m(10.0, 0.9, 0.8), &m(20.0, 0.9, 0.8), (5.0, 5.0), (9.0, 9.0)).expect("note");
        assert!(!n.contains("scene content"), "{n}");
    }

    #[test]
    fn a_uniform_level_lists_the_readings_unpaired_data_cannot_tell_apart() {
        let a = uniform_level_alternatives(32.0, 9.5, (2.3, false));
        let effects: Vec<&str> = a.iter().map(|a| a.effect.as_str()).collect();
        assert_eq!(effects, ["gain_offset", "stray_light"]);
        for x in &a {
            assert!(x.evidence.contains("32.0 DN") && x.evidence.contains("dark frames"), "{}", x.evidence);
            assert!(x.evidence.contains("z = 2.3, not established"), "{}", x.evidence);
            assert_eq!(x.bic_gap, 0.0);
        }
    }
}
