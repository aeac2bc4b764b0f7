//! Feature Quality Index through OpenCV: ORB keypoints and 256-bit descriptors, brute-force
//! Hamming matching with cross-check.

use super::{Fqi, Grey, MetricsError, OrbConfig};
use opencv::core::{DMatch, KeyPoint, Mat, NORM_HAMMING, Vector, no_array};
use opencv::features2d::{BFMatcher, ORB, ORB_ScoreType};
use opencv::prelude::*;

fn cv_err(step: &'static str) -> impl Fn(opencv::Error) -> MetricsError {
    move |e| MetricsError::Opencv { step, message: e.message }
}

/// An owned 8-bit single-channel `Mat` (CV_8UC1, continuous) holding [`Grey::to_u8`]; the
/// conversion from any [`crate::Frame`] (stride, 16-bit scaling, RGB luma) happens in
/// [`Grey::from_frame`].
pub fn grey_to_mat(g: &Grey) -> Result<Mat, MetricsError> {
    let bytes = g.to_u8();
    let rows = i32::try_from(g.height).map_err(|_| MetricsError::Opencv {
        step: "Mat from grey",
        message: format!("height {} does not fit i32", g.height),
    })?;
    let cols = i32::try_from(g.width).map_err(|_| MetricsError::Opencv {
        step: "Mat from grey",
        message: format!("width {} does not fit i32", g.width),
    })?;
    let view = Mat::new_rows_cols_with_data(rows, cols, &bytes).map_err(cv_err("Mat from grey"))?;
    // Deep copy: the Mat must not borrow `bytes`.
    view.try_clone().map_err(cv_err("Mat clone"))
}

/// ORB keypoints and descriptors of one image, reusable against many others.
#[derive(Debug)]
pub struct OrbFeatures {
    /// Number of keypoints that got a descriptor.
    pub keypoints: usize,
    descriptors: Mat,
}

/// Detect ORB keypoints and compute their descriptors.
pub fn orb_features(g: &Grey, cfg: &OrbConfig) -> Result<OrbFeatures, MetricsError> {
    let img = grey_to_mat(g)?;
    let mut orb = ORB::create(
        cfg.nfeatures,
        cfg.scale_factor,
        cfg.nlevels,
        cfg.edge_threshold,
        0,
        2,
        ORB_ScoreType::HARRIS_SCORE,
        cfg.patch_size,
        cfg.fast_threshold,
    )
    .map_err(cv_err("ORB::create"))?;
    let mut kps = Vector::<KeyPoint>::new();
    let mut desc = Mat::default();
    orb.detect_and_compute(&img, &no_array(), &mut kps, &mut desc, false).map_err(cv_err("ORB detect_and_compute"))?;
    let keypoints = if desc.empty() { 0 } else { desc.rows().max(0) as usize };
    Ok(OrbFeatures { keypoints, descriptors: desc })
}

/// FQI between two precomputed feature sets (see [`super::fqi`] for the formula and the
/// no-feature rule).
pub fn fqi_features(a: &OrbFeatures, b: &OrbFeatures) -> Result<Fqi, MetricsError> {
    let mut out = Fqi { value: None, keypoints_a: a.keypoints, keypoints_b: b.keypoints, matches: 0 };
    if a.keypoints == 0 || b.keypoints == 0 {
        return Ok(out);
    }
    let matcher = BFMatcher::new(NORM_HAMMING, true).map_err(cv_err("BFMatcher::new"))?;
    let mut matches = Vector::<DMatch>::new();
    matcher
        .train_match(&a.descriptors, &b.descriptors, &mut matches, &no_array())
        .map_err(cv_err("BFMatcher match"))?;
    out.matches = matches.len();
    let distances: Vec<f32> = matches.iter().map(|m| m.distance).collect();
    out.value = super::fqi_from_distances(&distances);
    Ok(out)
}

impl OrbFeatures {
    /// FQI against another feature set.
    pub fn fqi(&self, other: &OrbFeatures) -> Result<Fqi, MetricsError> {
        fqi_features(self, other)
    }

    /// The 256-bit descriptors as bytes, one per keypoint (for checks and custom matching).
    pub fn descriptors(&self) -> Result<Vec<[u8; 32]>, MetricsError> {
        let mut out = Vec::with_capacity(self.keypoints);
        for r in 0..self.keypoints as i32 {
            let row = self.descriptors.at_row::<u8>(r).map_err(cv_err("descriptor row"))?;
            let mut d = [0u8; 32];
            if row.len() != 32 {
                return Err(MetricsError::Opencv {
                    step: "descriptor row",
                    message: format!("expected 32 bytes, got {}", row.len()),
                });
            }
            d.copy_from_slice(row);
            out.push(d);
        }
        Ok(out)
    }
}
