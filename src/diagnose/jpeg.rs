//! JPEG: the quantisation lattice of the block DCT.
//!
//! A JPEG round trip leaves every 8x8 block's DCT coefficients (on the block grid that starts
//! at pixel 0) close to integer multiples of the quantisation table step Q(u,v); between the
//! multiples only the pixel rounding error remains (DCT-domain sd ≈ 0.29). The statistic per
//! step is `C(Q) = mean cos(2π F / Q)` over coefficients with |F| >= Q/2 (the zero bin says
//! nothing: smooth regions have small coefficients with or without JPEG). The same statistic on
//! a grid shifted by (4, 4) is the control: the lattice exists only on the true grid. The quality
//! is the libjpeg quality whose scaled standard luminance table maximises the aligned score.

use super::img::{Pair, Plane, SAT_DN};
use super::types::{Profile, Signature};
use rayon::prelude::*;

/// The standard JPEG luminance quantisation table (ITU T.81 Annex K), natural order.
pub const STD_LUMA: [u16; 64] = [
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57, 69, 56, 14, 17, 22, 29, 51,
    87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92, 49, 64, 78, 87, 103, 121, 120, 101,
    72, 92, 95, 98, 112, 100, 103, 99,
];

/// libjpeg's table for a quality 1..=100 (`jpeg_quality_scaling`, baseline clamp to 1..=255).
pub fn luma_table(quality: u32) -> [u16; 64] {
    let q = quality.clamp(1, 100);
    let scale = if q < 50 { 5000 / q } else { 200 - 2 * q };
    let mut t = [0u16; 64];
    for (o, &b) in t.iter_mut().zip(STD_LUMA.iter()) {
        *o = ((b as u32 * scale + 50) / 100).clamp(1, 255) as u16;
    }
    t
}

/// Orthonormal 8x8 DCT-II (the JPEG FDCT) of a block given row-major, level-shifted.
fn dct8(block: &[f64; 64], cos: &[[f64; 8]; 8], out: &mut [f64; 64]) {
    let mut tmp = [0.0; 64];
    for y in 0..8 {
        for u in 0..8 {
            let mut s = 0.0;
            for x in 0..8 {
                s += block[y * 8 + x] * cos[u][x];
            }
            tmp[y * 8 + u] = s;
        }
    }
    for v in 0..8 {
        for u in 0..8 {
            let mut s = 0.0;
            for y in 0..8 {
                s += tmp[y * 8 + u] * cos[v][y];
            }
            out[v * 8 + u] = s;
        }
    }
}

fn cos_table() -> [[f64; 8]; 8] {
    let mut c = [[0.0; 8]; 8];
    for (u, row) in c.iter_mut().enumerate() {
        let cu = if u == 0 { (0.125f64).sqrt() } else { 0.5 };
        for (x, v) in row.iter_mut().enumerate() {
            *v = cu * (((2 * x + 1) as f64 * u as f64 * std::f64::consts::PI) / 16.0).cos();
        }
    }
    c
}

/// Histograms of DCT coefficients per frequency (bins of 1/16) for one grid offset.
struct CoefHist {
    /// Per frequency: (bin, count), sorted by bin (the scores sum over the bins in that order, so
    /// they are the same bits on every run; a hash map's order changes from run to run).
    bins: Vec<Vec<(i32, u32)>>,
}

const RES: f64 = 16.0;

fn coefficient_hist(images: &[&[Plane]], off: (usize, usize)) -> CoefHist {
    let cos = cos_table();
    // Each image's counts on its own (in parallel), then added up: counts are integers, so the
    // histogram is the same whatever the order.
    let per_image: Vec<Vec<std::collections::HashMap<i32, u32>>> = images
        .par_iter()
        .map(|planes| {
            let mut bins: Vec<std::collections::HashMap<i32, u32>> = vec![Default::default(); 64];
            let mut block = [0.0; 64];
            let mut out = [0.0; 64];
            let (w, h) = (planes[0].w, planes[0].h);
            let y_plane: Vec<f32> = if planes.len() == 3 {
                (0..w * h)
                    .map(|i| 0.299 * planes[0].data[i] + 0.587 * planes[1].data[i] + 0.114 * planes[2].data[i])
                    .collect()
            } else {
                planes[0].data.clone()
            };
            let mut by = off.1;
            while by + 8 <= h {
                let mut bx = off.0;
                while bx + 8 <= w {
                    let mut sat = false;
                    for y in 0..8 {
                        for x in 0..8 {
                            let v = y_plane[(by + y) * w + bx + x] as f64;
                            if v >= SAT_DN as f64 {
                                sat = true;
                            }
                            block[y * 8 + x] = v - 128.0;
                        }
                    }
                    if !sat {
                        dct8(&block, &cos, &mut out);
                        for f in 1..64 {
                            *bins[f].entry((out[f] * RES).round() as i32).or_insert(0) += 1;
                        }
                    }
                    bx += 8;
                }
                by += 8;
            }
            bins
        })
        .collect();
    let mut bins: Vec<std::collections::HashMap<i32, u32>> = vec![Default::default(); 64];
    for image in per_image {
        for (f, m) in image.into_iter().enumerate() {
            for (key, count) in m {
                *bins[f].entry(key).or_insert(0) += count;
            }
        }
    }
    let bins = bins
        .into_iter()
        .map(|m| {
            let mut v: Vec<(i32, u32)> = m.into_iter().collect();
            v.sort_unstable();
            v
        })
        .collect();
    CoefHist { bins }
}

/// Score C(Q) for frequency f: (sum cos, count) over |F| >= Q/2.
fn score(h: &CoefHist, f: usize, q: f64) -> (f64, f64) {
    let mut s = 0.0;
    let mut n = 0.0;
    for &(b, c) in &h.bins[f] {
        let v = b as f64 / RES;
        if v.abs() >= q / 2.0 {
            s += c as f64 * (2.0 * std::f64::consts::PI * v / q).cos();
            n += c as f64;
        }
    }
    (s, n)
}

/// Table score: weighted mean of C over the frequencies with enough non-zero coefficients.
fn table_score(
    h: &CoefHist,
    table: &[u16; 64],
    cache: &mut std::collections::HashMap<(usize, u16), (f64, f64)>,
) -> (f64, f64) {
    let (mut s, mut n) = (0.0, 0.0);
    for f in 1..64 {
        let q = table[f];
        if q < 2 {
            continue;
        }
        let (a, b) = *cache.entry((f, q)).or_insert_with(|| score(h, f, q as f64));
        if b >= 20.0 {
            s += a;
            n += b;
        }
    }
    if n > 0.0 { (s / n, n) } else { (0.0, 0.0) }
}

pub fn test(pairs: &[Pair]) -> Signature {
    if pairs.iter().any(|p| p.real_frame.format == crate::frame::PixelFormat::Mono16) {
        let mut sig = Signature::new("jpeg");
        sig.evidence = "16-bit data: JPEG (8-bit) not applicable".into();
        return sig;
    }
    let reals: Vec<&[Plane]> = pairs.iter().map(|p| p.real.as_slice()).collect();
    let sims: Vec<&[Plane]> = pairs.iter().map(|p| p.sim.as_slice()).collect();
    test_planes(&reals, &sims)
}

/// The lattice test on sets of images (real: tested; sim: a lattice already there is not
/// evidence about the real camera).
pub fn test_planes(reals: &[&[Plane]], sims: &[&[Plane]]) -> Signature {
    let mut sig = Signature::new("jpeg");
    let aligned = coefficient_hist(reals, (0, 0));
    let shifted = coefficient_hist(reals, (4, 4));
    let sim_al = coefficient_hist(sims, (0, 0));
    let (mut ca, mut cs, mut csim) = (Default::default(), Default::default(), Default::default());
    let mut best = (0u32, f64::NEG_INFINITY, 0.0, 0.0, 0.0);
    let mut curve_a = Vec::new();
    let mut curve_s = Vec::new();
    for q in 5..=100u32 {
        let t = luma_table(q);
        let (sa, n) = table_score(&aligned, &t, &mut ca);
        let (ss, _) = table_score(&shifted, &t, &mut cs);
        curve_a.push(sa);
        curve_s.push(ss);
        if n > 0.0 && sa - ss > best.1 {
            let (sim_s, _) = table_score(&sim_al, &t, &mut csim);
            best = (q, sa - ss, n, sa, sim_s);
        }
    }
    let (q, diff, n, sa, sim_s) = best;
    if n <= 0.0 {
        sig.evidence = "no usable 8x8 blocks".into();
        return sig;
    }
    // Under no lattice each cosine has variance ~1/2: SE of the difference of two means.
    // The best of ~96 qualities is selected, so the threshold stays high.
    let se = (1.0 / n).sqrt();
    sig.z = diff / se;
    // A lattice already present in the sim is not evidence about the real camera.
    if sim_s > 0.5 * sa {
        sig.z = sig.z.min(0.0);
    }
    sig.size = diff;
    sig.size_unit = "lattice score (aligned - shifted grid)";
    sig.set_param("quality", q as f64);
    sig.where_ = "8x8 block grid from the top-left corner".into();
    sig.evidence = format!(
        "DCT coefficients of real sit on the quality-{q} lattice: score {sa:.3} on the JPEG grid vs {:.3} on a shifted grid (z = {:.1}, sim {sim_s:.3})",
        sa - diff,
        sig.z
    );
    sig.profiles.push(Profile {
        title: "jpeg: DCT lattice score against libjpeg quality".into(),
        x_label: "quality".into(),
        y_label: "mean cos(2π F / Q) over non-zero coefficients".into(),
        x: (5..=100).map(|q| q as f64).collect(),
        series: vec![("8x8 grid at (0,0)".into(), curve_a), ("grid shifted by (4,4)".into(), curve_s)],
    });
    sig
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_follow_libjpeg_scaling() {
        assert_eq!(luma_table(50), STD_LUMA);
        assert!(luma_table(100).iter().all(|&v| v == 1));
        assert_eq!(luma_table(75)[0], 8);
        assert_eq!(luma_table(10)[0], 80);
    }

    #[test]
    fn dct_is_orthonormal() {
        let cos = cos_table();
        let mut b = [0.0; 64];
        b[9] = 1.0;
        let mut o = [0.0; 64];
        dct8(&b, &cos, &mut o);
        let e: f64 = o.iter().map(|v| v * v).sum();
        assert!((e - 1.0).abs() < 1e-9);
    }
}
