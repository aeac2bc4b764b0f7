//! Structural similarity (Wang, Bovik, Sheikh, Simoncelli, IEEE TIP 13(4), 2004).
//!
//! For every window position (Gaussian weights `w`, 11x11, sigma 1.5, normalised to sum 1):
//!
//! ```text
//! mu_a = sum w a,  sigma_a^2 = sum w a^2 - mu_a^2,  sigma_ab = sum w a b - mu_a mu_b
//! SSIM = (2 mu_a mu_b + C1)(2 sigma_ab + C2) / ((mu_a^2 + mu_b^2 + C1)(sigma_a^2 + sigma_b^2 + C2))
//! C1 = (0.01 L)^2, C2 = (0.03 L)^2, L = 255
//! ```
//!
//! and the index is the mean over the windows that lie fully inside the image (the "valid"
//! region of the reference MATLAB `ssim_index`). Images smaller than the window use the largest
//! odd window that fits (same sigma, truncated and renormalised).

use super::{Grey, MetricsError, same_size};

/// Window side (px) of Wang et al.
pub const WINDOW: usize = 11;
/// Gaussian sigma (px) of the window.
pub const SIGMA: f64 = 1.5;
/// Dynamic range L in 8-bit DN.
pub const L: f64 = 255.0;
pub const K1: f64 = 0.01;
pub const K2: f64 = 0.03;

/// Mean SSIM with the standard window (11x11 Gaussian, sigma 1.5).
pub fn ssim(a: &Grey, b: &Grey) -> Result<f64, MetricsError> {
    ssim_with(a, b, WINDOW, SIGMA)
}

fn kernel(side: usize, sigma: f64) -> Vec<f64> {
    let r = (side / 2) as f64;
    let mut k: Vec<f64> = (0..side).map(|i| (-(i as f64 - r).powi(2) / (2.0 * sigma * sigma)).exp()).collect();
    let s: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k
}

/// "Valid" separable correlation of a `w x h` plane with `k` along x then y.
fn filter_valid(src: &[f64], w: usize, h: usize, k: &[f64], tmp: &mut Vec<f64>, out: &mut Vec<f64>) {
    let n = k.len();
    let (ow, oh) = (w + 1 - n, h + 1 - n);
    tmp.clear();
    for y in 0..h {
        let row = &src[y * w..(y + 1) * w];
        tmp.extend((0..ow).map(|x| row[x..x + n].iter().zip(k).map(|(v, kk)| v * kk).sum::<f64>()));
    }
    out.clear();
    for y in 0..oh {
        out.extend((0..ow).map(|x| (0..n).map(|j| tmp[(y + j) * ow + x] * k[j]).sum::<f64>()));
    }
}

/// Mean SSIM with a `side x side` Gaussian window of std `sigma` px (`side` odd, shrunk to fit
/// small images).
pub fn ssim_with(a: &Grey, b: &Grey, side: usize, sigma: f64) -> Result<f64, MetricsError> {
    same_size(a, b)?;
    let (w, h) = (a.width, a.height);
    let mut side = side.min(w).min(h).max(1);
    if side % 2 == 0 {
        side -= 1;
    }
    let k = kernel(side, sigma);
    let c1 = (K1 * L).powi(2);
    let c2 = (K2 * L).powi(2);
    let pa: Vec<f64> = a.data.iter().map(|&v| v as f64).collect();
    let pb: Vec<f64> = b.data.iter().map(|&v| v as f64).collect();
    let (mut tmp, mut ma, mut mb, mut saa, mut sbb, mut sab) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    filter_valid(&pa, w, h, &k, &mut tmp, &mut ma);
    filter_valid(&pb, w, h, &k, &mut tmp, &mut mb);
    let sq: Vec<f64> = pa.iter().map(|v| v * v).collect();
    filter_valid(&sq, w, h, &k, &mut tmp, &mut saa);
    let sq: Vec<f64> = pb.iter().map(|v| v * v).collect();
    filter_valid(&sq, w, h, &k, &mut tmp, &mut sbb);
    let sq: Vec<f64> = pa.iter().zip(&pb).map(|(x, y)| x * y).collect();
    filter_valid(&sq, w, h, &k, &mut tmp, &mut sab);
    let mut total = 0.0;
    for i in 0..ma.len() {
        let (mx, my) = (ma[i], mb[i]);
        let vx = saa[i] - mx * mx;
        let vy = sbb[i] - my * my;
        let cxy = sab[i] - mx * my;
        total += (2.0 * mx * my + c1) * (2.0 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2));
    }
    Ok(total / ma.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(w: usize, h: usize) -> Grey {
        Grey::new(w, h, (0..w * h).map(|i| (((i * 37) % 101) as f32) + 50.0).collect()).unwrap()
    }

    #[test]
    fn identical_images_score_one() {
        let a = pattern(24, 20);
        assert!((ssim(&a, &a).unwrap() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn constant_offset_has_the_closed_form_value() {
        // Constant images 100 and 110: variances and covariance vanish, so
        // SSIM = (2*100*110 + C1) / (100^2 + 110^2 + C1) with C1 = 2.55^2 = 6.5025.
        let a = Grey::new(16, 16, vec![100.0; 256]).unwrap();
        let b = Grey::new(16, 16, vec![110.0; 256]).unwrap();
        let expected = (22000.0 + 6.5025) / (22100.0 + 6.5025);
        assert!((ssim(&a, &b).unwrap() - expected).abs() < 1e-9);
        // A textured image plus an offset keeps the structure term at exactly 1; the luminance
        // term depends on the local means, and lies between the values at the extreme means.
        let t = pattern(20, 20);
        let t2 = Grey::new(20, 20, t.data.iter().map(|v| v + 10.0).collect()).unwrap();
        let s = ssim(&t, &t2).unwrap();
        let lum = |m: f64| (2.0 * m * (m + 10.0) + 6.5025) / (m * m + (m + 10.0).powi(2) + 6.5025);
        assert!(s > lum(50.0) && s < lum(150.0), "{s}");
        assert!(s < 1.0);
    }

    #[test]
    fn negated_structure_scores_below_zero() {
        let a = pattern(16, 16);
        let b = Grey::new(16, 16, a.data.iter().map(|v| 200.0 - v).collect()).unwrap();
        assert!(ssim(&a, &b).unwrap() < 0.0);
    }

    #[test]
    fn small_images_shrink_the_window() {
        let a = Grey::new(4, 4, vec![100.0; 16]).unwrap();
        let b = Grey::new(4, 4, vec![110.0; 16]).unwrap();
        let expected = (22000.0 + 6.5025) / (22100.0 + 6.5025);
        assert!((ssim(&a, &b).unwrap() - expected).abs() < 1e-9);
    }
}
