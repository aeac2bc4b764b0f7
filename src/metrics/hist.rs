//! Grey-level histograms, their comparison (OpenCV `compareHist` formulas), Otsu's threshold and
//! the Shadow Preservation Index.

use super::{Grey, MetricsError, same_size};

/// Number of histogram bins: one per 8-bit grey level.
pub const BINS: usize = 256;

/// Normalised grey histogram: 256 bins, bin `k` counts pixels whose rounded 8-bit level is `k`
/// (OpenCV `calcHist` with `histSize = 256`, `ranges = [0, 256)` on the 8-bit image), divided by
/// the pixel count so the bins sum to 1.
pub fn histogram(g: &Grey) -> [f64; BINS] {
    let mut h = [0f64; BINS];
    for v in g.to_u8() {
        h[v as usize] += 1.0;
    }
    let n = g.data.len().max(1) as f64;
    h.iter_mut().for_each(|v| *v /= n);
    h
}

/// Histogram correlation of the grey histograms of two images (any sizes), see
/// [`hist_correlation_hist`].
pub fn hist_correlation(a: &Grey, b: &Grey) -> f64 {
    hist_correlation_hist(&histogram(a), &histogram(b))
}

/// OpenCV `HISTCMP_CORREL`: `d = sum (H1 - m1)(H2 - m2) / sqrt(sum (H1 - m1)^2 sum (H2 - m2)^2)`
/// with `mk` the mean bin value. In `-1..=1`, 1 for proportional histograms. When a histogram
/// is flat (zero variance) OpenCV returns 1 and so does this.
pub fn hist_correlation_hist(h1: &[f64], h2: &[f64]) -> f64 {
    let n = h1.len().min(h2.len());
    if n == 0 {
        return 1.0;
    }
    let (mut s1, mut s2, mut s11, mut s22, mut s12) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (&a, &b) in h1.iter().zip(h2) {
        s1 += a;
        s2 += b;
        s11 += a * a;
        s22 += b * b;
        s12 += a * b;
    }
    let scale = 1.0 / n as f64;
    let num = s12 - s1 * s2 * scale;
    let denom2 = (s11 - s1 * s1 * scale) * (s22 - s2 * s2 * scale);
    if denom2.abs() > f64::EPSILON { num / denom2.sqrt() } else { 1.0 }
}

/// Bhattacharyya distance of the grey histograms of two images (any sizes), see
/// [`bhattacharyya_hist`].
pub fn bhattacharyya(a: &Grey, b: &Grey) -> f64 {
    bhattacharyya_hist(&histogram(a), &histogram(b))
}

/// OpenCV `HISTCMP_BHATTACHARYYA` (Hellinger distance):
/// `d = sqrt(1 - sum sqrt(H1 H2) / sqrt(sum H1 * sum H2))`, which for normalised histograms is
/// `sqrt(1 - sum sqrt(h1 h2))`. In `0..=1`: 0 for identical, 1 for disjoint histograms.
pub fn bhattacharyya_hist(h1: &[f64], h2: &[f64]) -> f64 {
    let (mut s1, mut s2, mut bc) = (0.0, 0.0, 0.0);
    for (&a, &b) in h1.iter().zip(h2) {
        s1 += a;
        s2 += b;
        bc += (a * b).sqrt();
    }
    let p = s1 * s2;
    let k = if p.abs() > f32::EPSILON as f64 { 1.0 / p.sqrt() } else { 1.0 };
    (1.0 - bc * k).max(0.0).sqrt()
}

/// Otsu's threshold on the 8-bit grey levels: the level `t` maximising the between-class
/// variance `q0 q1 (mu0 - mu1)^2` of the classes `v <= t` and `v > t`; the first maximum wins
/// (OpenCV `threshold(THRESH_OTSU)` returns the same `t`). A constant image has no split and
/// gives 0.
pub fn otsu_threshold(g: &Grey) -> u8 {
    let h = histogram(g);
    otsu_from_hist(&h)
}

fn otsu_from_hist(h: &[f64; BINS]) -> u8 {
    // Same recurrence as OpenCV's getThreshVal_Otsu_8u.
    let mu: f64 = h.iter().enumerate().map(|(i, p)| i as f64 * p).sum();
    let (mut q1, mut mu1, mut best, mut best_t) = (0.0f64, 0.0f64, 0.0f64, 0u8);
    let eps = f32::EPSILON as f64;
    for (i, &p) in h.iter().enumerate() {
        mu1 *= q1;
        q1 += p;
        let q2 = 1.0 - q1;
        if q1.min(q2) < eps || q1.max(q2) > 1.0 - eps {
            continue;
        }
        mu1 = (mu1 + i as f64 * p) / q1;
        let mu2 = (mu - q1 * mu1) / q2;
        let sigma = q1 * q2 * (mu1 - mu2) * (mu1 - mu2);
        if sigma > best {
            best = sigma;
            best_t = i as u8;
        }
    }
    best_t
}

/// Shadow mask: `true` where the rounded grey level is at or below the image's own Otsu
/// threshold (the dark class of Otsu's split).
pub fn shadow_mask(g: &Grey) -> Vec<bool> {
    let t = otsu_threshold(g);
    g.to_u8().into_iter().map(|v| v <= t).collect()
}

/// Shadow Preservation Index: intersection over union (Jaccard index) of the two images' Otsu
/// shadow masks ([`shadow_mask`]): `|S_a ∩ S_b| / |S_a ∪ S_b|`.
///
/// Meaning (as in the original study's use): 1 when every pixel that is shadow (dark class) in
/// one image is shadow in the other, i.e. the fault or the simulation kept the shadow geometry
/// a vision pipeline relies on; it falls as shadows are filled in (glare, blooming, offsets) or
/// new dark regions appear. Each image is thresholded at its own Otsu level, so a global gain
/// or offset that keeps the shadow geometry does not lower SPI. IoU rather than Dice: it
/// penalises mismatches more (Dice = 2 IoU / (1 + IoU)). Two images without any shadow
/// (both masks empty) score 1.
pub fn spi(a: &Grey, b: &Grey) -> Result<f64, MetricsError> {
    same_size(a, b)?;
    let (ma, mb) = (shadow_mask(a), shadow_mask(b));
    let (mut inter, mut union) = (0usize, 0usize);
    for (&x, &y) in ma.iter().zip(&mb) {
        inter += (x && y) as usize;
        union += (x || y) as usize;
    }
    Ok(if union == 0 { 1.0 } else { inter as f64 / union as f64 })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn g4(v: &[u8]) -> Grey {
        Grey::from_u8(4, 4, v).unwrap()
    }

    #[test]
    fn histogram_of_a_4x4_image() {
        let mut v = [0u8; 16];
        v[..4].fill(10);
        v[4..].fill(200);
        let h = histogram(&g4(&v));
        assert_eq!(h[10], 0.25);
        assert_eq!(h[200], 0.75);
        assert!((h.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        // Rounding: 10.49 -> 10, 10.5 -> 11.
        let g = Grey::new(2, 1, vec![10.49, 10.5]).unwrap();
        let h = histogram(&g);
        assert_eq!((h[10], h[11]), (0.5, 0.5));
    }

    #[test]
    fn correlation_and_bhattacharyya_by_hand() {
        // a: half 0, half 255; b: all 0.
        let mut va = [0u8; 16];
        va[8..].fill(255);
        let (a, b) = (g4(&va), g4(&[0; 16]));
        // sum sqrt(h1 h2) = sqrt(0.5) -> d = sqrt(1 - 1/sqrt 2).
        let d = bhattacharyya(&a, &b);
        assert!((d - (1.0 - 0.5f64.sqrt()).sqrt()).abs() < 1e-12, "{d}");
        // m = 1/256; num = 0.5 - 1/256; var_a = 0.5 - 1/256; var_b = 1 - 1/256
        // -> corr = sqrt(127/255).
        let c = hist_correlation(&a, &b);
        assert!((c - (127.0f64 / 255.0).sqrt()).abs() < 1e-12, "{c}");
        assert!((hist_correlation(&a, &a) - 1.0).abs() < 1e-12);
        assert!(bhattacharyya(&a, &a).abs() < 1e-7);
        // Disjoint histograms: Bhattacharyya 1.
        assert!((bhattacharyya(&g4(&[0; 16]), &g4(&[255; 16])) - 1.0).abs() < 1e-12);
        // Different sizes are fine for histogram metrics.
        let big = Grey::from_u8(8, 2, &va).unwrap();
        assert!((hist_correlation(&a, &big) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn three_level_histograms_by_hand() {
        // a: 8 px at 10, 8 at 20 -> h_a = {10: 1/2, 20: 1/2}.
        // b: 4 px at 10, 4 at 20, 8 at 30 -> h_b = {10: 1/4, 20: 1/4, 30: 1/2}.
        let mut va = [10u8; 16];
        va[8..].fill(20);
        let mut vb = [10u8; 16];
        vb[4..8].fill(20);
        vb[8..].fill(30);
        let (a, b) = (g4(&va), g4(&vb));
        // Bhattacharyya: sum sqrt(h_a h_b) = 2 sqrt(1/8) = 1/sqrt 2 -> d = sqrt(1 - 1/sqrt 2).
        let d = bhattacharyya(&a, &b);
        assert!((d - (1.0 - 0.5f64.sqrt()).sqrt()).abs() < 1e-12, "{d}");
        assert!((d - 0.541_196).abs() < 1e-6);
        // Correlation over 256 bins, mean bin 1/256:
        // num = sum h_a h_b - 1/256 = 1/4 - 1/256 = 63/256,
        // var_a = 1/2 - 1/256 = 127/256, var_b = 3/8 - 1/256 = 95/256 -> 63 / sqrt(127 * 95).
        let c = hist_correlation(&a, &b);
        assert!((c - 63.0 / (127.0f64 * 95.0).sqrt()).abs() < 1e-12, "{c}");
        assert!((c - 0.573_557).abs() < 1e-6);
        // Symmetric.
        assert_eq!(hist_correlation(&b, &a), c);
        assert!((bhattacharyya(&b, &a) - d).abs() < 1e-15);
    }

    #[test]
    fn otsu_on_bimodal_image() {
        // 8 pixels at 10 and 8 at 200: every t in 10..200 splits the modes equally well;
        // the first maximum is t = 10.
        let mut v = [10u8; 16];
        v[8..].fill(200);
        assert_eq!(otsu_threshold(&g4(&v)), 10);
        // Three levels 20 (6 px), 30 (2 px), 220 (8 px): the split between 30 and 220 wins.
        let mut v = [20u8; 16];
        v[6..8].fill(30);
        v[8..].fill(220);
        assert_eq!(otsu_threshold(&g4(&v)), 30);
        assert_eq!(otsu_threshold(&g4(&[77; 16])), 0);
    }

    #[test]
    fn spi_by_hand() {
        // a: left half dark; b: left quarter dark. IoU = 4 / 8.
        let mut va = [200u8; 16];
        let mut vb = [200u8; 16];
        for y in 0..4 {
            va[y * 4] = 10;
            va[y * 4 + 1] = 10;
            vb[y * 4] = 10;
        }
        let (a, b) = (g4(&va), g4(&vb));
        assert!((spi(&a, &a).unwrap() - 1.0).abs() < 1e-12);
        assert!((spi(&a, &b).unwrap() - 0.5).abs() < 1e-12);
        // A global offset keeps the geometry: SPI 1.
        let shifted = g4(&va.map(|v| v + 40));
        assert!((spi(&a, &shifted).unwrap() - 1.0).abs() < 1e-12);
        // Glare lifts part of a shadow. a: 20 (6 px), 30 (2 px), 220 (8 px): Otsu 30, shadow = 8 px.
        // b: the two 30 px become 200. Between-class variance q0 q1 (mu0 - mu1)^2 of b:
        // t = 20: (6/16)(10/16)(20 - 216)^2 = 9003.75; t = 200: (8/16)(8/16)(65 - 220)^2 =
        // 6006.25 -> Otsu 20, shadow = the 6 px at 20, inside a's. SPI = 6 / 8.
        let mut va = [20u8; 16];
        va[6..8].fill(30);
        va[8..].fill(220);
        let mut vb = va;
        vb[6..8].fill(200);
        let (a, b) = (g4(&va), g4(&vb));
        assert_eq!((otsu_threshold(&a), otsu_threshold(&b)), (30, 20));
        assert_eq!(shadow_mask(&b).iter().filter(|&&m| m).count(), 6);
        assert!((spi(&a, &b).unwrap() - 0.75).abs() < 1e-12);
        // Constant images: Otsu 0, masks empty or full; both constant 77 -> both empty -> 1.
        assert_eq!(spi(&g4(&[77; 16]), &g4(&[77; 16])).unwrap(), 1.0);
    }
}
