//! Image helper shared by the example SUTs (`ref_sut`, `pnp_sut`; included with `#[path]`).

/// Separable box blur of radius `r` with clamped windows at the borders (each output is the mean
/// of the samples of its window inside the image); `tmp` is scratch. `r = 0` is the identity.
pub fn box_blur(img: &mut [f32], tmp: &mut Vec<f32>, w: usize, h: usize, r: usize) {
    if r == 0 {
        return;
    }
    tmp.resize(w * h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
            tmp[y * w + x] = img[y * w + a..=y * w + b].iter().sum::<f32>() / (b - a + 1) as f32;
        }
    }
    for y in 0..h {
        let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
        for x in 0..w {
            img[y * w + x] = (a..=b).map(|yy| tmp[yy * w + x]).sum::<f32>() / (b - a + 1) as f32;
        }
    }
}
