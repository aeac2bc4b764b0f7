//! The original study's blooming validation protocol (`faultcam eval blooming`).
//!
//! Question: does the `blooming` effect make the bright zones of generated (simulated) images look
//! like the blooming zones of real camera images? Protocol:
//!
//! 1. **Select** generated images with a bright region: at least `min_area` pixels at or above
//!    `threshold` (250 in 8-bit DN), measured before blooming.
//! 2. **Apply blooming** (`faults::create("blooming")`, the effect's defaults unless parameters
//!    are given; generator seeded from `seed` and the image's index in the input order).
//! 3. **Crop** the bounding box of the brightest blooming zone: the largest (most pixels)
//!    8-connected region at or above the threshold in every real image, and at or above the
//!    zone level in every bloomed generated image ([`zones::zone_level`]: the threshold, or
//!    just below the image's own saturation plateau when the full well reads lower). Its box equals the bounding box of the region's
//!    outer contour (OpenCV `findContours(RETR_EXTERNAL)` + `boundingRect`; a test checks
//!    this). Boxes smaller than `min_crop` are grown about their centre to `min_crop` px (inside
//!    the image) so that ORB has room for its patch (`min_crop = 0` keeps the bare boxes). The
//!    *control* crop is the same box in the generated image before blooming.
//! 4. **Centre-crop** every crop to the common shape: the smallest width and the smallest height
//!    over all bloomed and real crops.
//! 5. **Score** each generated crop against every real crop: FQI (ORB, see
//!    [`crate::metrics::fqi`]) and histogram correlation ([`crate::metrics::hist_correlation`]).
//!    An undefined FQI (no keypoints or no match) scores 0. The **best match** is the real crop
//!    with the largest `FQI + correlation` (first in file-name order on ties); its two scores
//!    are the image's scores.
//! 6. **Accept** an image when `FQI >= fqi_min` (0.80) and `correlation >= corr_min` (0.90)
//!    ([`accept`]); report the acceptance rate and the score distributions (mean, median,
//!    population std, min, max), the number of descriptor matches behind each FQI, and the
//!    *bright fraction* of the crops (share of the crop at or above its zone level: how much of
//!    it blooming saturated).
//! 7. **Control**: steps 5-6 on the control crops (same boxes, before blooming).
//!
//! Outputs in the output folder: `report.json` (everything, per image), `summary.txt`, the PNG
//! plots `fqi_hist.png`, `hist_corr_hist.png` (bloomed vs control distributions with the
//! threshold marked) and `grey_hist.png` (mean grey histograms of real, bloomed and control
//! crops), and `crops/` (every crop as PNG) unless disabled.

use super::zones::{self, Zone};
use super::{EvalError, Stats, list_images, load_frame, plot, save_grey_png};
use crate::faults::{self, EffectCtx, Params};
use crate::frame::Frame;
use crate::metrics::{self, Grey, OrbConfig};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Where generated images come from.
#[derive(Debug, Clone)]
pub enum Generated {
    /// A folder of images.
    Dir(PathBuf),
    /// A source URI (`synth:?...`, `files:DIR`), read until its end or `max_generated` frames.
    Uri(String),
}

impl Generated {
    /// `synth:...`/`files:...`/any `scheme:` with a known scheme is a URI, anything else a folder.
    pub fn parse(s: &str) -> Generated {
        let scheme = s.split_once(':').map(|(a, _)| a).unwrap_or("");
        if crate::source::SCHEMES.contains(&scheme) { Generated::Uri(s.to_string()) } else { Generated::Dir(s.into()) }
    }
}

/// Settings of the protocol.
#[derive(Debug, Clone)]
pub struct BloomingConfig {
    /// Bright level (8-bit DN) for selection and zones.
    pub threshold: f32,
    /// Pixels at or above the threshold a generated image needs to be selected, and smallest
    /// zone kept.
    pub min_area: usize,
    /// Smallest crop side (px) before centre-cropping to the common shape.
    pub min_crop: usize,
    pub fqi_min: f64,
    pub corr_min: f64,
    pub orb: OrbConfig,
    /// Parameters of the `blooming` effect.
    pub blooming: Option<Params>,
    /// A whole fault configuration (e.g. diagnose's `fitted.toml`) applied in step 2 instead of
    /// blooming alone: every effect it enables, in physical order; the control is the image
    /// before it.
    pub faults: Option<crate::config::FaultConfig>,
    /// Seed of the effect generators (per image: derived from seed and image index).
    pub seed: u64,
    /// Most generated images read (a source may be endless).
    pub max_generated: usize,
    /// Real images are used only if their file name contains one of these (all if empty).
    pub real_include: Vec<String>,
    /// Write the crops as PNG under `out/crops`.
    pub save_crops: bool,
}

impl Default for BloomingConfig {
    fn default() -> Self {
        BloomingConfig {
            threshold: 250.0,
            min_area: 10,
            min_crop: 96,
            fqi_min: 0.80,
            corr_min: 0.90,
            orb: OrbConfig::default(),
            blooming: None,
            faults: None,
            seed: 1,
            max_generated: 210,
            real_include: Vec::new(),
            save_crops: true,
        }
    }
}

/// A crop that took part in the comparison.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CropInfo {
    pub name: String,
    /// Level (8-bit DN) the zone was cut at (the threshold, or [`zones::zone_level`] for
    /// bloomed images).
    pub level: f32,
    /// Zone found (before growing to `min_crop`).
    pub zone: Zone,
    /// Box cropped (after growing), before the common centre crop.
    pub crop: Zone,
    /// Fraction of the final (common-shape) crop at or above `level`.
    pub bright_fraction: f64,
}

/// Scores of one generated crop against its best real match.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MatchScore {
    pub best_real: String,
    /// `None` by the no-feature rule (scored as 0).
    pub fqi: Option<f64>,
    pub hist_corr: f64,
    /// ORB keypoints of the generated crop.
    pub keypoints: usize,
    /// ORB keypoints of the best real crop.
    pub keypoints_real: usize,
    /// Cross-checked descriptor matches the FQI averages over.
    pub matches: usize,
    /// `FQI >= fqi_min` and `hist_corr >= corr_min` (undefined FQI counts as 0).
    pub accepted: bool,
}

/// Per generated image.
#[derive(Debug, Clone, serde::Serialize)]
pub struct GeneratedResult {
    #[serde(flatten)]
    pub crop: CropInfo,
    pub bloomed: MatchScore,
    pub control: MatchScore,
}

/// Acceptance and score distributions of one arm (bloomed or control).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ArmSummary {
    pub accepted: usize,
    pub total: usize,
    pub acceptance_rate: f64,
    /// Best-match FQI, undefined FQI counted as 0.
    pub fqi: Option<Stats>,
    /// Best-match FQI over the images where it is defined (`None` if it never is).
    pub fqi_defined: Option<Stats>,
    pub fqi_undefined: usize,
    pub hist_corr: Option<Stats>,
    /// Cross-checked matches behind each best-match FQI.
    pub matches: Option<Stats>,
    /// Fraction of each crop at or above its zone level (how much of the crop is saturated).
    pub bright_fraction: Option<Stats>,
    /// How often each real crop was the best match.
    pub best_real_counts: std::collections::BTreeMap<String, usize>,
    /// Per real crop: how many generated crops are accepted against that crop alone (so that
    /// one real image cannot carry the result).
    pub accepted_per_real: std::collections::BTreeMap<String, usize>,
}

/// The original study's published numbers, for side-by-side reporting.
#[derive(Debug, Clone, serde::Serialize)]
pub struct StudyNumbers {
    pub accepted: usize,
    pub total: usize,
    pub mean_fqi: f64,
    pub mean_hist_corr: f64,
    pub control_mean_fqi: f64,
    pub control_mean_hist_corr: f64,
}

pub const STUDY: StudyNumbers = StudyNumbers {
    accepted: 189,
    total: 210,
    mean_fqi: 0.908,
    mean_hist_corr: 0.996,
    control_mean_fqi: 0.846,
    control_mean_hist_corr: 0.054,
};

/// Everything `report.json` holds.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BloomingReport {
    pub generated_source: String,
    pub real_dir: PathBuf,
    pub threshold: f32,
    pub min_area: usize,
    pub min_crop: usize,
    pub fqi_min: f64,
    pub corr_min: f64,
    pub orb: OrbConfig,
    pub blooming_params: serde_json::Value,
    pub seed: u64,
    pub generated_read: usize,
    /// Generated images skipped, with the reason (no bright region, unreadable, ...).
    pub generated_skipped: Vec<(String, String)>,
    pub real_used: Vec<CropInfo>,
    pub real_skipped: Vec<(String, String)>,
    /// Fraction of each real crop at or above its zone level.
    pub real_bright_fraction: Option<Stats>,
    /// Common crop shape (width, height) px.
    pub crop_shape: (usize, usize),
    pub bloomed: ArmSummary,
    pub control: ArmSummary,
    pub study: StudyNumbers,
    pub per_image: Vec<GeneratedResult>,
    pub plots: Vec<String>,
}

struct GenCrop {
    info: CropInfo,
    bloomed: Grey,
    control: Grey,
    /// Zone level of the image before blooming (for the control's bright fraction).
    control_level: f32,
}

/// Fraction of `g` at or above `level`.
fn fraction_at_or_above(g: &Grey, level: f32) -> f64 {
    zones::count_at_or_above(g, level) as f64 / g.data.len().max(1) as f64
}

/// Run the protocol and write `report.json`, the plots and (optionally) the crops into `out`.
pub fn run_protocol(
    generated: &Generated,
    real_dir: &Path,
    out: &Path,
    cfg: &BloomingConfig,
) -> Result<BloomingReport, EvalError> {
    std::fs::create_dir_all(out).map_err(|source| EvalError::Io { path: out.to_path_buf(), source })?;
    let params = match cfg.blooming {
        Some(p) => p,
        None => faults::default_params("blooming")?,
    };
    // Fails early, naming the known effects, if `blooming` is not registered.
    let mut effect = faults::create("blooming")?;
    let mut chain = match &cfg.faults {
        Some(fc) => Some(crate::faults::chain::Chain::from_config(fc)?),
        None => None,
    };
    let mut chain_report = crate::faults::chain::FrameReport::default();

    // Generated: select, bloom, crop.
    let mut skipped = Vec::new();
    let mut gens = Vec::new();
    let mut read = 0usize;
    let mut handle = |name: String, mut frame: Frame, skipped: &mut Vec<(String, String)>| -> Result<(), EvalError> {
        let index = read as u64;
        read += 1;
        let before = Grey::from_frame(&frame);
        let bright = zones::count_at_or_above(&before, cfg.threshold);
        if bright < cfg.min_area {
            skipped.push((name, format!("{bright} px >= {} (needs {})", cfg.threshold, cfg.min_area)));
            return Ok(());
        }
        frame.seq = index;
        if let Some(chain) = chain.as_mut() {
            if chain.apply(&mut frame, &mut chain_report)? != faults::Outcome::Keep {
                skipped.push((name, "dropped by the fault configuration".to_string()));
                return Ok(());
            }
        } else {
            if !effect.info().accepts(frame.format) {
                frame = before.to_frame();
                frame.seq = index;
            }
            let mut ctx = EffectCtx::new(cfg.seed, index, 0);
            effect.apply(&mut frame, &params, &mut ctx)?;
        }
        let after = Grey::from_frame(&frame);
        let level = zones::zone_level(&after, cfg.threshold);
        let Some(zone) = zones::blooming_zone(&after, level, cfg.min_area) else {
            skipped.push((name, "no blooming zone after blooming".to_string()));
            return Ok(());
        };
        let crop = zone.expanded(cfg.min_crop, cfg.min_crop, after.width, after.height);
        let cut = |g: &Grey| g.crop(crop.x0, crop.y0, crop.width(), crop.height());
        if let (Some(bloomed), Some(control)) = (cut(&after), cut(&before)) {
            // Selected above: the image before blooming reaches the threshold.
            let control_level = cfg.threshold;
            let info = CropInfo { name, level, zone, crop, bright_fraction: 0.0 };
            gens.push(GenCrop { info, bloomed, control, control_level });
        }
        Ok(())
    };
    let source_name = match generated {
        Generated::Dir(d) => {
            for p in list_images(d)?.into_iter().take(cfg.max_generated) {
                let name = file_name(&p);
                match load_frame(&p) {
                    Ok(f) => handle(name, f, &mut skipped)?,
                    Err(e) => skipped.push((name, e.to_string())),
                }
            }
            d.display().to_string()
        }
        Generated::Uri(uri) => {
            let err = |e: crate::source::SourceError| EvalError::Source { uri: uri.clone(), message: e.to_string() };
            let mut src = crate::source::open(uri).map_err(err)?;
            let mut n = 0usize;
            while n < cfg.max_generated {
                match src.next_frame() {
                    Ok(Some(f)) => {
                        let name = src.item_name().map(str::to_string).unwrap_or_else(|| format!("frame{n:06}"));
                        handle(name, f, &mut skipped)?;
                    }
                    Ok(None) => break,
                    Err(e) if e.recoverable() => skipped.push((format!("item{n:06}"), e.to_string())),
                    Err(e) => return Err(err(e)),
                }
                n += 1;
            }
            uri.clone()
        }
    };

    // Real crops.
    let mut real_skipped = Vec::new();
    let mut reals: Vec<(CropInfo, Grey)> = Vec::new();
    let mut real_listed = 0usize;
    for p in list_images(real_dir)? {
        let name = file_name(&p);
        if !cfg.real_include.is_empty() && !cfg.real_include.iter().any(|s| name.contains(s.as_str())) {
            continue;
        }
        real_listed += 1;
        let g = match load_frame(&p) {
            Ok(f) => Grey::from_frame(&f),
            Err(e) => {
                real_skipped.push((name, e.to_string()));
                continue;
            }
        };
        let level = cfg.threshold;
        let Some(zone) = zones::blooming_zone(&g, level, cfg.min_area) else {
            real_skipped.push((name, format!("no zone of {} px at or above {}", cfg.min_area, cfg.threshold)));
            continue;
        };
        let crop = zone.expanded(cfg.min_crop, cfg.min_crop, g.width, g.height);
        if let Some(c) = g.crop(crop.x0, crop.y0, crop.width(), crop.height()) {
            reals.push((CropInfo { name, level, zone, crop, bright_fraction: 0.0 }, c));
        }
    }
    if real_listed == 0 {
        return Err(EvalError::NoImages {
            dir: real_dir.to_path_buf(),
            accepted: if cfg.real_include.is_empty() {
                super::IMAGE_EXTENSIONS.join(", ")
            } else {
                format!(
                    "{} with a name containing {}",
                    super::IMAGE_EXTENSIONS.join(", "),
                    cfg.real_include.iter().map(|s| format!("'{s}'")).collect::<Vec<_>>().join(" or ")
                )
            },
        });
    }
    if reals.is_empty() {
        return Err(EvalError::Invalid {
            what: format!(
                "{}: no real image with a blooming zone (>= {} px at or above {}); skipped: {}",
                real_dir.display(),
                cfg.min_area,
                cfg.threshold,
                real_skipped.iter().map(|(n, r)| format!("{n} ({r})")).collect::<Vec<_>>().join("; ")
            ),
        });
    }
    if gens.is_empty() {
        return Err(EvalError::Invalid {
            what: format!(
                "{source_name}: no generated image with >= {} px at or above {} ({read} read)",
                cfg.min_area, cfg.threshold
            ),
        });
    }

    // Common shape.
    let cw = gens.iter().map(|g| g.bloomed.width).chain(reals.iter().map(|r| r.1.width)).min().unwrap_or(1);
    let ch = gens.iter().map(|g| g.bloomed.height).chain(reals.iter().map(|r| r.1.height)).min().unwrap_or(1);
    for g in gens.iter_mut() {
        g.bloomed = g.bloomed.centre_crop(cw, ch);
        g.control = g.control.centre_crop(cw, ch);
        g.info.bright_fraction = fraction_at_or_above(&g.bloomed, g.info.level);
    }
    for r in reals.iter_mut() {
        r.1 = r.1.centre_crop(cw, ch);
        r.0.bright_fraction = fraction_at_or_above(&r.1, r.0.level);
    }
    let control_fraction: Vec<f64> = gens.iter().map(|g| fraction_at_or_above(&g.control, g.control_level)).collect();
    if cfg.save_crops {
        let dir = out.join("crops");
        std::fs::create_dir_all(&dir).map_err(|source| EvalError::Io { path: dir.clone(), source })?;
        for g in &gens {
            let stem = stem_of(&g.info.name);
            save_grey_png(&g.bloomed, &dir.join(format!("gen_{stem}_bloomed.png")))?;
            save_grey_png(&g.control, &dir.join(format!("gen_{stem}_control.png")))?;
        }
        for r in &reals {
            save_grey_png(&r.1, &dir.join(format!("real_{}.png", stem_of(&r.0.name))))?;
        }
    }

    // Scores.
    let real_scores = score_set(reals.iter().map(|r| &r.1), &cfg.orb)?;
    let bloomed = score_set(gens.iter().map(|g| &g.bloomed), &cfg.orb)?;
    let control = score_set(gens.iter().map(|g| &g.control), &cfg.orb)?;
    let per_image: Vec<GeneratedResult> = gens
        .iter()
        .enumerate()
        .map(|(i, g)| -> Result<GeneratedResult, EvalError> {
            Ok(GeneratedResult {
                crop: g.info.clone(),
                bloomed: best_match(&bloomed[i], &real_scores, &reals, cfg)?,
                control: best_match(&control[i], &real_scores, &reals, cfg)?,
            })
        })
        .collect::<Result<_, _>>()?;
    let bloomed_fraction: Vec<f64> = gens.iter().map(|g| g.info.bright_fraction).collect();
    let mut bloomed_sum = summarise(per_image.iter().map(|r| &r.bloomed), &bloomed_fraction);
    let mut control_sum = summarise(per_image.iter().map(|r| &r.control), &control_fraction);
    for (k, (info, _)) in reals.iter().enumerate() {
        let count = |arm: &[Scored]| -> Result<usize, EvalError> {
            let mut n = 0;
            for g in arm {
                n += usize::from(pair_score(g, &real_scores[k], &info.name, cfg)?.accepted);
            }
            Ok(n)
        };
        bloomed_sum.accepted_per_real.insert(info.name.clone(), count(&bloomed)?);
        control_sum.accepted_per_real.insert(info.name.clone(), count(&control)?);
    }
    let real_fraction: Vec<f64> = reals.iter().map(|r| r.0.bright_fraction).collect();

    // Plots.
    let mut plots = Vec::new();
    let fq = |f: fn(&GeneratedResult) -> &MatchScore| -> Vec<f64> {
        per_image.iter().map(|r| f(r).fqi.unwrap_or(0.0)).collect()
    };
    let hc =
        |f: fn(&GeneratedResult) -> &MatchScore| -> Vec<f64> { per_image.iter().map(|r| f(r).hist_corr).collect() };
    let (fb, fc) =
        (plot::bin_counts(&fq(|r| &r.bloomed), 25, 0.0, 1.0), plot::bin_counts(&fq(|r| &r.control), 25, 0.0, 1.0));
    plot::BarPlot {
        title: "FQI of best real match (count)",
        x_label: "FQI",
        x_range: (0.0, 1.0),
        series: vec![
            plot::Series { label: "bloomed", colour: [214, 96, 20], values: &fb },
            plot::Series { label: "control", colour: [60, 110, 200], values: &fc },
        ],
        marker: Some(cfg.fqi_min),
    }
    .save(&out.join("fqi_hist.png"))?;
    plots.push("fqi_hist.png".to_string());
    let (hb, hcc) =
        (plot::bin_counts(&hc(|r| &r.bloomed), 40, -1.0, 1.0), plot::bin_counts(&hc(|r| &r.control), 40, -1.0, 1.0));
    plot::BarPlot {
        title: "histogram correlation of best real match (count)",
        x_label: "correlation",
        x_range: (-1.0, 1.0),
        series: vec![
            plot::Series { label: "bloomed", colour: [214, 96, 20], values: &hb },
            plot::Series { label: "control", colour: [60, 110, 200], values: &hcc },
        ],
        marker: Some(cfg.corr_min),
    }
    .save(&out.join("hist_corr_hist.png"))?;
    plots.push("hist_corr_hist.png".to_string());
    let grey_mean = |gs: &mut dyn Iterator<Item = &Grey>| -> Vec<f64> {
        let mut acc = vec![0.0; 32];
        let mut n = 0.0;
        for g in gs {
            for (i, v) in metrics::histogram(g).iter().enumerate() {
                acc[i / 8] += v;
            }
            n += 1.0;
        }
        acc.iter().map(|v| v / f64::max(n, 1.0)).collect()
    };
    let (gr, gb, gc) = (
        grey_mean(&mut reals.iter().map(|r| &r.1)),
        grey_mean(&mut gens.iter().map(|g| &g.bloomed)),
        grey_mean(&mut gens.iter().map(|g| &g.control)),
    );
    plot::BarPlot {
        title: "mean grey histogram of the crops (fraction, 8 levels per bin)",
        x_label: "grey level (8-bit DN)",
        x_range: (0.0, 256.0),
        series: vec![
            plot::Series { label: "real", colour: [40, 40, 40], values: &gr },
            plot::Series { label: "bloomed", colour: [214, 96, 20], values: &gb },
            plot::Series { label: "control", colour: [60, 110, 200], values: &gc },
        ],
        marker: Some(cfg.threshold as f64),
    }
    .save(&out.join("grey_hist.png"))?;
    plots.push("grey_hist.png".to_string());

    let report = BloomingReport {
        generated_source: source_name,
        real_dir: real_dir.to_path_buf(),
        threshold: cfg.threshold,
        min_area: cfg.min_area,
        min_crop: cfg.min_crop,
        fqi_min: cfg.fqi_min,
        corr_min: cfg.corr_min,
        orb: cfg.orb,
        blooming_params: match &cfg.faults {
            Some(fc) => serde_json::Value::String(format!("fault configuration {}: {}", fc.origin, fc.to_toml())),
            None => serde_json::to_value(params).unwrap_or(serde_json::Value::Null),
        },
        seed: cfg.seed,
        generated_read: read,
        generated_skipped: skipped,
        real_used: reals.iter().map(|r| r.0.clone()).collect(),
        real_skipped,
        real_bright_fraction: Stats::of(&real_fraction),
        crop_shape: (cw, ch),
        bloomed: bloomed_sum,
        control: control_sum,
        study: STUDY,
        per_image,
        plots,
    };
    let path = out.join("report.json");
    let text = serde_json::to_string_pretty(&report)
        .map_err(|e| EvalError::Invalid { what: format!("{}: cannot serialise: {e}", path.display()) })?;
    std::fs::write(&path, text).map_err(|source| EvalError::Io { path, source })?;
    let path = out.join("summary.txt");
    std::fs::write(&path, report.summary()).map_err(|source| EvalError::Io { path, source })?;
    Ok(report)
}

fn file_name(p: &Path) -> String {
    p.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
}

fn stem_of(name: &str) -> String {
    Path::new(name).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| name.to_string())
}

/// Per crop: its grey histogram and, with OpenCV, its ORB features.
struct Scored {
    hist: [f64; 256],
    #[cfg(feature = "opencv")]
    orb: metrics::OrbFeatures,
}

fn score_set<'a>(crops: impl Iterator<Item = &'a Grey>, orb: &OrbConfig) -> Result<Vec<Scored>, EvalError> {
    let crops: Vec<&Grey> = crops.collect();
    crops
        .par_iter()
        .map(|g| -> Result<Scored, EvalError> {
            #[cfg(not(feature = "opencv"))]
            let _ = orb;
            Ok(Scored {
                hist: metrics::histogram(g),
                #[cfg(feature = "opencv")]
                orb: metrics::orb_features(g, orb)
                    .map_err(|source| EvalError::Metrics { context: "ORB on a crop".to_string(), source })?,
            })
        })
        .collect()
}

fn best_match(
    g: &Scored,
    reals: &[Scored],
    real_info: &[(CropInfo, Grey)],
    cfg: &BloomingConfig,
) -> Result<MatchScore, EvalError> {
    let mut best: Option<(f64, MatchScore)> = None;
    for (r, info) in reals.iter().zip(real_info) {
        let m = pair_score(g, r, &info.0.name, cfg)?;
        let score = m.fqi.unwrap_or(0.0) + m.hist_corr;
        // Strictly greater: the first real crop (in file-name order) wins ties.
        if best.as_ref().is_none_or(|(s, _)| score > *s) {
            best = Some((score, m));
        }
    }
    best.map(|b| b.1).ok_or_else(|| EvalError::Invalid { what: "no real crop to compare with".to_string() })
}

/// Scores of a generated crop against one real crop.
fn pair_score(g: &Scored, r: &Scored, real_name: &str, cfg: &BloomingConfig) -> Result<MatchScore, EvalError> {
    #[cfg(feature = "opencv")]
    let f = g.orb.fqi(&r.orb).map_err(|source| EvalError::Metrics { context: real_name.to_string(), source })?;
    #[cfg(not(feature = "opencv"))]
    let f = metrics::Fqi { value: None, keypoints_a: 0, keypoints_b: 0, matches: 0 };
    let corr = metrics::hist_correlation_hist(&g.hist, &r.hist);
    Ok(MatchScore {
        best_real: real_name.to_string(),
        fqi: f.value,
        hist_corr: corr,
        keypoints: f.keypoints_a,
        keypoints_real: f.keypoints_b,
        matches: f.matches,
        accepted: accept(f.value, corr, cfg.fqi_min, cfg.corr_min),
    })
}

/// Acceptance rule of the protocol: `FQI >= fqi_min` and `corr >= corr_min`; an undefined FQI
/// (no keypoints or no match) is scored 0.
pub fn accept(fqi: Option<f64>, corr: f64, fqi_min: f64, corr_min: f64) -> bool {
    fqi.unwrap_or(0.0) >= fqi_min && corr >= corr_min
}

fn summarise<'a>(scores: impl Iterator<Item = &'a MatchScore>, bright_fraction: &[f64]) -> ArmSummary {
    let scores: Vec<&MatchScore> = scores.collect();
    let total = scores.len();
    let accepted = scores.iter().filter(|s| s.accepted).count();
    let fqi: Vec<f64> = scores.iter().map(|s| s.fqi.unwrap_or(0.0)).collect();
    let corr: Vec<f64> = scores.iter().map(|s| s.hist_corr).collect();
    ArmSummary {
        accepted,
        total,
        acceptance_rate: if total > 0 { accepted as f64 / total as f64 } else { 0.0 },
        fqi: Stats::of(&fqi),
        fqi_defined: Stats::of(&scores.iter().filter_map(|s| s.fqi).collect::<Vec<_>>()),
        fqi_undefined: scores.iter().filter(|s| s.fqi.is_none()).count(),
        hist_corr: Stats::of(&corr),
        matches: Stats::of(&scores.iter().map(|s| s.matches as f64).collect::<Vec<_>>()),
        bright_fraction: Stats::of(bright_fraction),
        best_real_counts: scores.iter().fold(Default::default(), |mut m, s| {
            *m.entry(s.best_real.clone()).or_insert(0) += 1;
            m
        }),
        accepted_per_real: Default::default(),
    }
}

impl BloomingReport {
    /// Plain-text summary next to the study's numbers (also written as `summary.txt`).
    pub fn summary(&self) -> String {
        let st = |s: &Option<Stats>| {
            s.map(|s| format!("{:.3}/{:.3}/{:.3}/{:.3}", s.mean, s.median, s.std, s.min))
                .unwrap_or_else(|| "-".to_string())
        };
        let arm = |a: &ArmSummary| {
            format!(
                "{:>4}/{:<4} ({:5.1}%)  FQI {}  corr {}  (FQI undefined: {}; defined mean {}; matches mean {:.1}; bright fraction mean {:.2})",
                a.accepted,
                a.total,
                100.0 * a.acceptance_rate,
                st(&a.fqi),
                st(&a.hist_corr),
                a.fqi_undefined,
                a.fqi_defined.map_or_else(|| "-".to_string(), |m| format!("{:.3}", m.mean)),
                a.matches.map_or(0.0, |m| m.mean),
                a.bright_fraction.map_or(0.0, |m| m.mean),
            )
        };
        let best = |a: &ArmSummary| {
            let mut v: Vec<(&String, &usize)> = a.best_real_counts.iter().collect();
            v.sort_by(|x, y| y.1.cmp(x.1).then(x.0.cmp(y.0)));
            v.iter().map(|(n, c)| format!("{n} {c}")).collect::<Vec<_>>().join(", ")
        };
        let per_real = |a: &ArmSummary| {
            a.accepted_per_real.iter().map(|(n, c)| format!("{n} {c}/{}", a.total)).collect::<Vec<_>>().join(", ")
        };
        let s = &self.study;
        format!(
            "generated read {}, selected {}, real crops {} ({} skipped), crop {}x{} px, ORB patch {} px\n\
             blooming {}\n\
             accepted at FQI >= {} and corr >= {}; scores mean/median/std/min\n\
             bloomed: {}\ncontrol: {}\n\
             real crops: bright fraction mean {:.2}\n\
             best matches (bloomed): {}\n\
             best matches (control): {}\n\
             accepted against each real crop alone (bloomed): {}\n\
             accepted against each real crop alone (control): {}\n\
             study:   {}/{} accepted, mean FQI {}, mean corr {}; control mean FQI {}, mean corr {}\n",
            self.generated_read,
            self.bloomed.total,
            self.real_used.len(),
            self.real_skipped.len(),
            self.crop_shape.0,
            self.crop_shape.1,
            self.orb.patch_size,
            self.blooming_params,
            self.fqi_min,
            self.corr_min,
            arm(&self.bloomed),
            arm(&self.control),
            self.real_bright_fraction.map_or(0.0, |m| m.mean),
            best(&self.bloomed),
            best(&self.control),
            per_real(&self.bloomed),
            per_real(&self.control),
            s.accepted,
            s.total,
            s.mean_fqi,
            s.mean_hist_corr,
            s.control_mean_fqi,
            s.control_mean_hist_corr
        )
    }
}
