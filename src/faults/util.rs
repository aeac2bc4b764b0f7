//! Helpers shared by effects.

/// Rows per rayon task for per-row parallel loops: large enough to amortise scheduling
/// (~1/20 of a 1200-row frame), small enough to balance two to eight cores.
pub const ROWS_PER_TASK: usize = 64;

/// Normalised 1-D Gaussian kernel of standard deviation `sigma` (px), radius ceil(3 sigma).
/// `sigma <= 0` gives the identity kernel `[1.0]`.
pub fn gaussian_kernel(sigma: f32) -> Vec<f32> {
    if sigma <= 0.0 {
        return vec![1.0];
    }
    let r = (3.0 * sigma).ceil() as i32;
    let mut k: Vec<f32> = (-r..=r).map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp()).collect();
    let s: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k
}

#[cfg(test)]
mod tests {
    #[test]
    fn gaussian_kernel_is_normalised_and_symmetric() {
        let k = super::gaussian_kernel(1.5);
        assert_eq!(k.len(), 11);
        assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        for i in 0..k.len() {
            assert_eq!(k[i], k[k.len() - 1 - i]);
        }
        assert_eq!(super::gaussian_kernel(0.0), vec![1.0]);
    }
}
