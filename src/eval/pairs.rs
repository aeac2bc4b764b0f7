//! Metrics between two folders of images paired by file stem (`faultcam eval pairs`).

use super::{EvalError, list_images, load_frame};
use crate::metrics::{self, Grey, Metrics};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Metrics of one pair, or why it could not be compared.
#[derive(Debug, Clone, serde::Serialize)]
pub struct PairResult {
    /// Common file stem.
    pub name: String,
    pub a: PathBuf,
    pub b: PathBuf,
    pub width: usize,
    pub height: usize,
    pub metrics: Option<Metrics>,
    pub error: Option<String>,
}

/// Means over the pairs that were compared. PSNR averages the finite values only (identical
/// pairs have infinite PSNR) and FQI the pairs that have one (no-feature rule).
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct MeanMetrics {
    pub pairs: usize,
    pub rmse: f64,
    pub psnr: Option<f64>,
    pub psnr_pairs: usize,
    pub ssim: f64,
    pub fqi: Option<f64>,
    pub fqi_pairs: usize,
    pub hist_corr: f64,
    pub bhattacharyya: f64,
    pub spi: f64,
}

/// Result of [`evaluate_pairs`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct PairsReport {
    pub a_dir: PathBuf,
    pub b_dir: PathBuf,
    pub pairs: Vec<PairResult>,
    /// Stems present in only one folder (not compared).
    pub only_in_a: Vec<String>,
    pub only_in_b: Vec<String>,
    pub mean: MeanMetrics,
}

fn by_stem(files: Vec<PathBuf>) -> BTreeMap<String, PathBuf> {
    let mut m = BTreeMap::new();
    for p in files {
        let stem = p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        // Sorted input: the first of `x.png`, `x.tif` wins, deterministically.
        m.entry(stem).or_insert(p);
    }
    m
}

fn compare_files(a: &Path, b: &Path) -> Result<(usize, usize, Metrics), EvalError> {
    let ga = Grey::from_frame(&load_frame(a)?);
    let gb = Grey::from_frame(&load_frame(b)?);
    let m = metrics::compare(&ga, &gb)
        .map_err(|source| EvalError::Metrics { context: format!("{} vs {}", a.display(), b.display()), source })?;
    Ok((ga.width, ga.height, m))
}

/// Compare every pair of images with the same file stem in `a_dir` and `b_dir` (e.g.
/// `img01.png` with `img01.jpg`). A pair that cannot be read or differs in size is reported
/// with its error and left out of the means; it does not stop the others.
pub fn evaluate_pairs(a_dir: &Path, b_dir: &Path) -> Result<PairsReport, EvalError> {
    let a = by_stem(list_images(a_dir)?);
    let b = by_stem(list_images(b_dir)?);
    let accepted = super::IMAGE_EXTENSIONS.join(", ");
    if a.is_empty() {
        return Err(EvalError::NoImages { dir: a_dir.to_path_buf(), accepted });
    }
    if b.is_empty() {
        return Err(EvalError::NoImages { dir: b_dir.to_path_buf(), accepted });
    }
    let only_in_a: Vec<String> = a.keys().filter(|k| !b.contains_key(*k)).cloned().collect();
    let only_in_b: Vec<String> = b.keys().filter(|k| !a.contains_key(*k)).cloned().collect();
    let jobs: Vec<(String, PathBuf, PathBuf)> =
        a.iter().filter_map(|(k, pa)| b.get(k).map(|pb| (k.clone(), pa.clone(), pb.clone()))).collect();
    if jobs.is_empty() {
        return Err(EvalError::Invalid {
            what: format!("no file stem is common to {} and {}", a_dir.display(), b_dir.display()),
        });
    }
    let pairs: Vec<PairResult> = jobs
        .into_par_iter()
        .map(|(name, pa, pb)| match compare_files(&pa, &pb) {
            Ok((width, height, m)) => PairResult { name, a: pa, b: pb, width, height, metrics: Some(m), error: None },
            Err(e) => PairResult { name, a: pa, b: pb, width: 0, height: 0, metrics: None, error: Some(e.to_string()) },
        })
        .collect();
    let mean = mean_metrics(pairs.iter().filter_map(|p| p.metrics.as_ref()));
    Ok(PairsReport { a_dir: a_dir.to_path_buf(), b_dir: b_dir.to_path_buf(), pairs, only_in_a, only_in_b, mean })
}

/// Means of a set of metric results (see [`MeanMetrics`]).
pub fn mean_metrics<'a>(ms: impl Iterator<Item = &'a Metrics>) -> MeanMetrics {
    let mut s = MeanMetrics::default();
    let (mut psnr, mut fqi) = (0.0, 0.0);
    for m in ms {
        s.pairs += 1;
        s.rmse += m.rmse;
        s.ssim += m.ssim;
        s.hist_corr += m.hist_corr;
        s.bhattacharyya += m.bhattacharyya;
        s.spi += m.spi;
        if m.psnr.is_finite() {
            psnr += m.psnr;
            s.psnr_pairs += 1;
        }
        if let Some(f) = m.fqi {
            fqi += f;
            s.fqi_pairs += 1;
        }
    }
    if s.pairs > 0 {
        let n = s.pairs as f64;
        s.rmse /= n;
        s.ssim /= n;
        s.hist_corr /= n;
        s.bhattacharyya /= n;
        s.spi /= n;
    }
    s.psnr = (s.psnr_pairs > 0).then(|| psnr / s.psnr_pairs as f64);
    s.fqi = (s.fqi_pairs > 0).then(|| fqi / s.fqi_pairs as f64);
    s
}

fn opt(v: Option<f64>, prec: usize) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.prec$}"),
        Some(_) => "inf".to_string(),
        None => "-".to_string(),
    }
}

impl PairsReport {
    /// Plain-text table: one line per pair, then the means.
    pub fn table(&self) -> String {
        let w = self.pairs.iter().map(|p| p.name.len()).max().unwrap_or(4).clamp(4, 40);
        let mut s = format!(
            "{:<w$}  {:>8} {:>8} {:>7} {:>7} {:>9} {:>7} {:>7}\n",
            "pair", "rmse_dn", "psnr_db", "ssim", "fqi", "hist_corr", "bhatt", "spi"
        );
        for p in &self.pairs {
            match (&p.metrics, &p.error) {
                (Some(m), _) => {
                    s += &format!(
                        "{:<w$}  {:>8.3} {:>8} {:>7.4} {:>7} {:>9.4} {:>7.4} {:>7.4}\n",
                        p.name,
                        m.rmse,
                        opt(Some(m.psnr), 2),
                        m.ssim,
                        opt(m.fqi, 4),
                        m.hist_corr,
                        m.bhattacharyya,
                        m.spi
                    )
                }
                (None, e) => s += &format!("{:<w$}  error: {}\n", p.name, e.as_deref().unwrap_or("?")),
            }
        }
        let m = &self.mean;
        s += &format!(
            "{:<w$}  {:>8.3} {:>8} {:>7.4} {:>7} {:>9.4} {:>7.4} {:>7.4}\n",
            format!("mean ({})", m.pairs),
            m.rmse,
            opt(m.psnr, 2),
            m.ssim,
            opt(m.fqi, 4),
            m.hist_corr,
            m.bhattacharyya,
            m.spi
        );
        if !self.only_in_a.is_empty() {
            s += &format!("only in {}: {}\n", self.a_dir.display(), self.only_in_a.join(", "));
        }
        if !self.only_in_b.is_empty() {
            s += &format!("only in {}: {}\n", self.b_dir.display(), self.only_in_b.join(", "));
        }
        s
    }
}
