//! Evaluation over image sets: paired metrics ([`pairs`], `faultcam eval pairs`) and the original
//! study's blooming validation protocol ([`blooming`], `faultcam eval blooming`).

pub mod blooming;
pub mod pairs;
pub mod plot;
pub mod zones;

use crate::frame::{Frame, FrameData, PixelFormat};
use crate::metrics::{Grey, MetricsError};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Errors of the evaluation commands.
#[derive(Debug, Error)]
pub enum EvalError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: cannot decode image: {message}")]
    Image { path: PathBuf, message: String },
    #[error("{dir}: no images (accepted extensions: {accepted})")]
    NoImages { dir: PathBuf, accepted: String },
    #[error("{context}: {source}")]
    Metrics { context: String, source: MetricsError },
    #[error("generated source '{uri}': {message}")]
    Source { uri: String, message: String },
    #[error("{0}")]
    Fault(#[from] crate::faults::FaultError),
    #[error("{what}")]
    Invalid { what: String },
}

/// File extensions read as images.
pub const IMAGE_EXTENSIONS: &[&str] = &["png", "jpg", "jpeg", "pgm", "ppm", "pnm", "tif", "tiff"];

/// Image files of a folder (not recursive), sorted by file name.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>, EvalError> {
    let rd = std::fs::read_dir(dir).map_err(|source| EvalError::Io { path: dir.to_path_buf(), source })?;
    let mut out = Vec::new();
    for e in rd {
        let e = e.map_err(|source| EvalError::Io { path: dir.to_path_buf(), source })?;
        let p = e.path();
        let ok = p
            .extension()
            .and_then(|x| x.to_str())
            .is_some_and(|x| IMAGE_EXTENSIONS.contains(&x.to_ascii_lowercase().as_str()));
        if ok && p.is_file() {
            out.push(p);
        }
    }
    out.sort();
    Ok(out)
}

/// Decode an image file into a [`Frame`]: 8-bit grey → `Mono8`, 16-bit grey → `Mono16`, colour
/// → `Rgb8` (alpha dropped, 16-bit colour reduced to 8 bits).
pub fn load_frame(path: &Path) -> Result<Frame, EvalError> {
    let img = crate::limits::load_image(path, &crate::limits::ImageLimits::current())
        .map_err(|message| EvalError::Image { path: path.to_path_buf(), message })?;
    let (w, h) = (img.width(), img.height());
    let (format, data) = match img {
        image::DynamicImage::ImageLuma8(b) => (PixelFormat::Mono8, FrameData::U8(b.into_raw())),
        image::DynamicImage::ImageLuma16(b) => (PixelFormat::Mono16, FrameData::U16(b.into_raw())),
        image::DynamicImage::ImageLumaA8(_) => (PixelFormat::Mono8, FrameData::U8(img.to_luma8().into_raw())),
        other => (PixelFormat::Rgb8, FrameData::U8(other.to_rgb8().into_raw())),
    };
    let stride = w as usize * format.channels();
    Frame::from_data(w, h, stride, format, data)
        .map_err(|e| EvalError::Image { path: path.to_path_buf(), message: e.to_string() })
}

/// Write a grey plane as an 8-bit PNG (rounded, clamped).
pub fn save_grey_png(g: &Grey, path: &Path) -> Result<(), EvalError> {
    let buf = image::GrayImage::from_raw(g.width as u32, g.height as u32, g.to_u8())
        .ok_or_else(|| EvalError::Invalid { what: format!("{}: bad grey buffer", path.display()) })?;
    buf.save(path).map_err(|e| EvalError::Image { path: path.to_path_buf(), message: e.to_string() })
}

/// Summary statistics of a score distribution.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Stats {
    pub n: usize,
    pub mean: f64,
    pub median: f64,
    /// Population standard deviation (divides by n).
    pub std: f64,
    pub min: f64,
    pub max: f64,
}

impl Stats {
    /// Statistics of the finite values; `None` if there are none.
    pub fn of(values: &[f64]) -> Option<Stats> {
        let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let n = v.len();
        let mean = v.iter().sum::<f64>() / n as f64;
        let median = if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) };
        let std = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
        Some(Stats { n, mean, median, std, min: v[0], max: v[n - 1] })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_by_hand() {
        let s = Stats::of(&[1.0, 3.0, 2.0, 4.0, f64::NAN]).unwrap();
        assert_eq!((s.n, s.mean, s.median, s.min, s.max), (4, 2.5, 2.5, 1.0, 4.0));
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-12);
        assert_eq!(Stats::of(&[5.0, 1.0, 3.0]).unwrap().median, 3.0);
        assert!(Stats::of(&[]).is_none());
    }
}
