//! Fidelity metrics between two images (simulated vs real, before vs after a fault).
//!
//! Every metric works on a [`Grey`] plane: one channel of `f32` samples in **8-bit DN**
//! (0..=255), whatever the source format, so that numbers are comparable across formats:
//!
//! * `Mono8`, `Bayer8`: the samples as they are (a Bayer mosaic is treated as grey);
//! * `Mono16`: `v / 257` (65535 → 255 exactly);
//! * `Rgb8`: luma `0.299 R + 0.587 G + 0.114 B` (ITU-R BT.601, the weights of OpenCV's
//!   `cvtColor(RGB2GRAY)`).
//!
//! Metrics that need integer grey levels (histograms, Otsu, ORB) round to the nearest level and
//! clamp to 0..=255 ([`Grey::to_u8`]).
//!
//! | metric | function | formula | range, best |
//! |---|---|---|---|
//! | RMSE | [`rmse`] | `sqrt(mean((a - b)^2))` in 8-bit DN | 0..=255, 0 |
//! | PSNR | [`psnr`] | `20 log10(255 / RMSE)` dB; `+inf` when identical | 0.., high |
//! | SSIM | [`ssim`] | Wang et al. 2004, Gaussian window (11x11, sigma 1.5), `K1 = 0.01`, `K2 = 0.03`, `L = 255`; mean over the valid windows | -1..=1, 1 |
//! | histogram correlation | [`hist_correlation`] | OpenCV `HISTCMP_CORREL` on 256-bin normalised grey histograms | -1..=1, 1 |
//! | Bhattacharyya distance | [`bhattacharyya`] | OpenCV `HISTCMP_BHATTACHARYYA`: `sqrt(1 - sum sqrt(h1 h2))` for normalised histograms | 0..=1, 0 |
//! | SPI | [`spi`] | IoU of the Otsu shadow masks (pixels at or below each image's Otsu threshold) | 0..=1, 1 |
//! | FQI | [`fqi`] | ORB descriptors, brute-force Hamming matching with cross-check, `1 - mean(Hamming) / 256` | 0..=1, 1 |
//!
//! FQI needs OpenCV (cargo feature `opencv`, on by default); without it [`fqi`] returns
//! [`MetricsError::OpencvUnavailable`] and everything else works.

mod hist;
#[cfg(feature = "opencv")]
mod orb;
mod ssim;

pub use hist::{bhattacharyya, bhattacharyya_hist, hist_correlation, hist_correlation_hist, histogram, otsu_threshold};
pub use hist::{shadow_mask, spi};
#[cfg(feature = "opencv")]
pub use orb::{OrbFeatures, grey_to_mat, orb_features};
pub use ssim::{ssim, ssim_with};

use crate::frame::{Frame, ImageRef, PixelFormat, Sample};
use crate::with_image_ref;
use thiserror::Error;

/// Errors of the metrics.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum MetricsError {
    #[error("image sizes differ: {a_width}x{a_height} vs {b_width}x{b_height}; this metric compares pixel by pixel")]
    SizeMismatch { a_width: usize, a_height: usize, b_width: usize, b_height: usize },
    #[error("grey buffer of {width}x{height} needs {expected} samples, got {got}")]
    BadBuffer { width: usize, height: usize, expected: usize, got: usize },
    #[error("image is empty ({width}x{height}); width and height must be at least 1")]
    Empty { width: usize, height: usize },
    #[error("FQI needs OpenCV: build faultcam with the cargo feature `opencv` (on by default)")]
    OpencvUnavailable,
    #[error("OpenCV failed in {step}: {message}")]
    Opencv { step: &'static str, message: String },
}

/// One grey plane in 8-bit DN (0..=255 as `f32`), packed row-major (no padding).
#[derive(Debug, Clone, PartialEq)]
pub struct Grey {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

/// BT.601 luma weights (R, G, B), as OpenCV's `RGB2GRAY`.
pub const LUMA_BT601: [f32; 3] = [0.299, 0.587, 0.114];

fn grey_rows<T: Sample>(img: &ImageRef<'_, T>, format: PixelFormat, out: &mut Vec<f32>) {
    // 1 for 8-bit, 257 for 16-bit: a division keeps multiples of 257 exact.
    let div = T::MAX_F32 / 255.0;
    for row in img.rows() {
        if format == PixelFormat::Rgb8 {
            out.extend(row.chunks_exact(3).map(|p| {
                (LUMA_BT601[0] * p[0].to_f32() + LUMA_BT601[1] * p[1].to_f32() + LUMA_BT601[2] * p[2].to_f32()) / div
            }));
        } else {
            out.extend(row.iter().map(|v| v.to_f32() / div));
        }
    }
}

impl Grey {
    /// Wrap packed samples in 8-bit DN.
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Result<Grey, MetricsError> {
        if width == 0 || height == 0 {
            return Err(MetricsError::Empty { width, height });
        }
        let expected = width.saturating_mul(height);
        if data.len() != expected {
            return Err(MetricsError::BadBuffer { width, height, expected, got: data.len() });
        }
        Ok(Grey { width, height, data })
    }

    /// From packed 8-bit samples.
    pub fn from_u8(width: usize, height: usize, data: &[u8]) -> Result<Grey, MetricsError> {
        Grey::new(width, height, data.iter().map(|&v| v as f32).collect())
    }

    /// Grey plane of a frame (see the module documentation for the conversion). Honours the
    /// stride (padding is skipped).
    pub fn from_frame(frame: &Frame) -> Grey {
        let mut data = Vec::with_capacity(frame.pixels());
        let format = frame.format;
        with_image_ref!(frame, img => grey_rows(&img, format, &mut data));
        Grey { width: frame.width as usize, height: frame.height as usize, data }
    }

    /// Integer grey levels: round to nearest, clamp to 0..=255.
    pub fn to_u8(&self) -> Vec<u8> {
        self.data.iter().map(|&v| u8::from_f32(v)).collect()
    }

    /// `Mono8` frame of [`Grey::to_u8`].
    pub fn to_frame(&self) -> Frame {
        Frame {
            seq: 0,
            pts_ns: 0,
            width: self.width as u32,
            height: self.height as u32,
            stride: self.width,
            format: PixelFormat::Mono8,
            data: crate::frame::FrameData::U8(self.to_u8()),
        }
    }

    pub fn get(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Sub-image `[x0, x0 + w) x [y0, y0 + h)`, clipped to the image. `None` if the clipped
    /// rectangle is empty.
    pub fn crop(&self, x0: usize, y0: usize, w: usize, h: usize) -> Option<Grey> {
        let x1 = x0.saturating_add(w).min(self.width);
        let y1 = y0.saturating_add(h).min(self.height);
        if x0 >= x1 || y0 >= y1 {
            return None;
        }
        let mut data = Vec::with_capacity((x1 - x0) * (y1 - y0));
        for y in y0..y1 {
            data.extend_from_slice(&self.data[y * self.width + x0..y * self.width + x1]);
        }
        Some(Grey { width: x1 - x0, height: y1 - y0, data })
    }

    /// Centred `w` x `h` sub-image (`w`, `h` clipped to the image size).
    pub fn centre_crop(&self, w: usize, h: usize) -> Grey {
        let (w, h) = (w.clamp(1, self.width), h.clamp(1, self.height));
        let (x0, y0) = ((self.width - w) / 2, (self.height - h) / 2);
        // Cannot be empty: 1 <= w <= width, 1 <= h <= height.
        self.crop(x0, y0, w, h).unwrap_or_else(|| self.clone())
    }
}

fn same_size(a: &Grey, b: &Grey) -> Result<(), MetricsError> {
    if a.width != b.width || a.height != b.height || a.data.len() != b.data.len() {
        return Err(MetricsError::SizeMismatch {
            a_width: a.width,
            a_height: a.height,
            b_width: b.width,
            b_height: b.height,
        });
    }
    Ok(())
}

/// Root-mean-square difference in 8-bit DN: `sqrt(1/N sum (a_i - b_i)^2)`.
pub fn rmse(a: &Grey, b: &Grey) -> Result<f64, MetricsError> {
    same_size(a, b)?;
    let sse: f64 = a.data.iter().zip(&b.data).map(|(&x, &y)| ((x - y) as f64).powi(2)).sum();
    Ok((sse / a.data.len() as f64).sqrt())
}

/// Peak signal-to-noise ratio in dB with peak 255: `20 log10(255 / RMSE)`; `f64::INFINITY` for
/// identical images (serialised as `null` in JSON).
pub fn psnr(a: &Grey, b: &Grey) -> Result<f64, MetricsError> {
    Ok(psnr_from_rmse(rmse(a, b)?))
}

/// PSNR (dB, peak 255) from an RMSE in 8-bit DN.
pub fn psnr_from_rmse(rmse: f64) -> f64 {
    if rmse <= 0.0 { f64::INFINITY } else { 20.0 * (255.0 / rmse).log10() }
}

/// Feature Quality Index between two images with OpenCV's default ORB settings:
/// `1 - mean(Hamming distance) / 256` over the cross-checked brute-force matches of the 256-bit
/// ORB descriptors.
///
/// **No-feature rule:** `Ok(None)` when either image yields no ORB keypoint or no match
/// survives the cross-check: the images share no comparable structure, so there is no
/// quality to report. Callers that need a number (acceptance tests) count `None` as a failure;
/// [`Metrics::fqi`] keeps the `None`. The images need not have the same size.
pub fn fqi(a: &Grey, b: &Grey) -> Result<Option<f64>, MetricsError> {
    Ok(fqi_with(a, b, &OrbConfig::default())?.value)
}

/// FQI from the Hamming distances (bits) of the matched descriptor pairs:
/// `1 - mean(d) / 256`; `None` for no match.
pub fn fqi_from_distances(distances: &[f32]) -> Option<f64> {
    if distances.is_empty() {
        return None;
    }
    let mean = distances.iter().map(|&d| d as f64).sum::<f64>() / distances.len() as f64;
    Some(1.0 - mean / 256.0)
}

/// ORB settings (defaults are OpenCV's `ORB::create()` defaults).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct OrbConfig {
    pub nfeatures: i32,
    pub scale_factor: f32,
    pub nlevels: i32,
    /// Border (px) where no keypoint is detected; should be about `patch_size`.
    pub edge_threshold: i32,
    /// Size (px) of the patch the descriptor samples.
    pub patch_size: i32,
    pub fast_threshold: i32,
}

impl Default for OrbConfig {
    fn default() -> Self {
        OrbConfig {
            nfeatures: 500,
            scale_factor: 1.2,
            nlevels: 8,
            edge_threshold: 31,
            patch_size: 31,
            fast_threshold: 20,
        }
    }
}

/// FQI with its evidence.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Fqi {
    /// `1 - mean Hamming / 256`, `None` by the no-feature rule of [`fqi`].
    pub value: Option<f64>,
    pub keypoints_a: usize,
    pub keypoints_b: usize,
    /// Cross-checked matches.
    pub matches: usize,
}

/// [`fqi`] with explicit ORB settings, returning the keypoint and match counts too.
pub fn fqi_with(a: &Grey, b: &Grey, cfg: &OrbConfig) -> Result<Fqi, MetricsError> {
    #[cfg(feature = "opencv")]
    {
        let fa = orb::orb_features(a, cfg)?;
        let fb = orb::orb_features(b, cfg)?;
        orb::fqi_features(&fa, &fb)
    }
    #[cfg(not(feature = "opencv"))]
    {
        let _ = (a, b, cfg);
        Err(MetricsError::OpencvUnavailable)
    }
}

/// All metrics between two same-size images.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Metrics {
    /// 8-bit DN.
    pub rmse: f64,
    /// dB; infinite (JSON `null`) for identical images.
    pub psnr: f64,
    pub ssim: f64,
    /// `None` by the no-feature rule, or when built without OpenCV.
    pub fqi: Option<f64>,
    pub hist_corr: f64,
    pub bhattacharyya: f64,
    pub spi: f64,
}

/// Every metric between `a` and `b` (same size). FQI is `None` when OpenCV is not built in.
pub fn compare(a: &Grey, b: &Grey) -> Result<Metrics, MetricsError> {
    let rmse = rmse(a, b)?;
    let fqi = match fqi(a, b) {
        Ok(v) => v,
        Err(MetricsError::OpencvUnavailable) => None,
        Err(e) => return Err(e),
    };
    Ok(Metrics {
        rmse,
        psnr: psnr_from_rmse(rmse),
        ssim: ssim(a, b)?,
        fqi,
        hist_corr: hist_correlation(a, b),
        bhattacharyya: bhattacharyya(a, b),
        spi: spi(a, b)?,
    })
}

/// [`compare`] on frames (converted with [`Grey::from_frame`]).
pub fn compare_frames(a: &Frame, b: &Frame) -> Result<Metrics, MetricsError> {
    compare(&Grey::from_frame(a), &Grey::from_frame(b))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::FrameData;

    #[test]
    fn grey_from_frame_scales_and_skips_padding() {
        // 2x2 Mono16 with one padding sample per row.
        let f = Frame::from_data(2, 2, 3, PixelFormat::Mono16, FrameData::U16(vec![0, 257, 9999, 65535, 2570, 9999]))
            .unwrap();
        let g = Grey::from_frame(&f);
        assert_eq!(g.data, vec![0.0, 1.0, 255.0, 10.0]);
        let rgb = Frame::from_data(1, 1, 3, PixelFormat::Rgb8, FrameData::U8(vec![100, 100, 100])).unwrap();
        assert!((Grey::from_frame(&rgb).data[0] - 100.0).abs() < 1e-4);
        let red = Frame::from_data(1, 1, 3, PixelFormat::Rgb8, FrameData::U8(vec![255, 0, 0])).unwrap();
        assert!((Grey::from_frame(&red).data[0] - 76.245).abs() < 1e-3);
    }

    #[test]
    fn rmse_and_psnr_by_hand() {
        // 4x4: four pixels differ by 4 DN -> MSE = 4 * 16 / 16 = 4, RMSE = 2.
        let a = Grey::new(4, 4, vec![0.0; 16]).unwrap();
        let mut d = vec![0.0; 16];
        for i in [0, 5, 10, 15] {
            d[i] = 4.0;
        }
        let b = Grey::new(4, 4, d).unwrap();
        assert!((rmse(&a, &b).unwrap() - 2.0).abs() < 1e-12);
        assert!((psnr(&a, &b).unwrap() - 20.0 * (127.5f64).log10()).abs() < 1e-9);
        assert_eq!(psnr(&a, &a).unwrap(), f64::INFINITY);
        let c = Grey::new(2, 8, vec![0.0; 16]).unwrap();
        assert!(matches!(rmse(&a, &c), Err(MetricsError::SizeMismatch { .. })));
    }

    #[test]
    fn fqi_formula_by_hand() {
        // Mean distance 32 bits of 256 -> 0.875; identical descriptors -> 1; no match -> None.
        assert_eq!(fqi_from_distances(&[0.0, 32.0, 64.0]), Some(0.875));
        assert_eq!(fqi_from_distances(&[0.0; 5]), Some(1.0));
        assert_eq!(fqi_from_distances(&[256.0]), Some(0.0));
        assert_eq!(fqi_from_distances(&[]), None);
    }

    #[test]
    fn crops() {
        let g = Grey::new(4, 3, (0..12).map(|v| v as f32).collect()).unwrap();
        let c = g.crop(1, 1, 2, 5).unwrap();
        assert_eq!((c.width, c.height), (2, 2));
        assert_eq!(c.data, vec![5.0, 6.0, 9.0, 10.0]);
        assert!(g.crop(4, 0, 1, 1).is_none());
        let cc = g.centre_crop(2, 1);
        assert_eq!(cc.data, vec![5.0, 6.0]);
    }
}
