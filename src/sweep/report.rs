//! Sweep statistics and reports (report.json, report.md, PNG plots).
//!
//! Per group of cells (the baseline; an effect or a pair at one level), frames pooled over
//! seeds, scored frames only (not dropped by a fault, truth known):
//! - `failure_rate` = (frames without a pose + frames with score > tolerance) / frames;
//! - median and p95 (nearest rank) of `E_t`, `E_q` (rad) and score over the posed frames;
//! - `mean_error` = mean over the frames of `min(score, 1 + π)`, a frame without a pose
//!   counting `1 + π` (the score of a pose 100 % off in range and 180° off in attitude).
//!
//! Per effect: the **breaking point** is the lowest level whose failure rate is at least
//! `threshold` (none when no level reaches it); `ce` (corruption error, as ImageNet-C's CE
//! with the clean baseline as the reference) = `Σ_levels mean_error / (levels ·
//! mean_error(baseline))`, undefined (null) when the baseline's mean error is 0; `mce` is the
//! mean of the defined `ce` over effects. `relative_failure` = mean failure rate over the
//! levels − the baseline's.

use super::{CellResult, FrameStatus};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Error a frame without a pose counts in `mean_error` (and the cap of a frame's score).
pub const ERROR_CAP: f64 = 1.0 + std::f64::consts::PI;

/// The parts of a plan the report needs (read back from its JSON, so sharded and unsharded
/// runs build the report from the same data).
#[derive(Debug, Clone, Deserialize)]
pub struct PlanView {
    pub seeds: Vec<u64>,
    pub tolerance: f64,
    pub threshold: f64,
    pub effects: Vec<EffectView>,
    pub pairs: Vec<(usize, usize)>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct EffectView {
    pub name: String,
    pub param: String,
    pub values: Vec<f64>,
}

impl PlanView {
    pub fn from_value(v: &serde_json::Value) -> Result<PlanView, String> {
        serde_json::from_value(v.clone()).map_err(|e| format!("not a sweep plan: {e}"))
    }
    pub fn cell_count(&self) -> usize {
        let levels: usize = self.effects.iter().map(|e| e.values.len()).sum();
        let pairs: usize = self.pairs.iter().map(|(a, _)| self.effects[*a].values.len()).sum();
        (1 + levels + pairs) * self.seeds.len()
    }
}

/// Statistics of a group of frames.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Stats {
    /// Frames scored (shown to the SUT, truth known).
    pub frames: usize,
    pub posed: usize,
    pub failures: usize,
    pub failure_rate: Option<f64>,
    pub mean_error: Option<f64>,
    pub median_e_t: Option<f64>,
    pub p95_e_t: Option<f64>,
    pub median_e_q: Option<f64>,
    pub p95_e_q: Option<f64>,
    pub median_score: Option<f64>,
    pub p95_score: Option<f64>,
    /// Frames a fault dropped (not scored).
    pub dropped: usize,
}

/// Nearest-rank percentile of sorted values.
fn pct(sorted: &[f64], p: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let r = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    Some(sorted[r - 1])
}

/// Median (mean of the two middle values for an even count).
fn median(sorted: &[f64]) -> Option<f64> {
    let n = sorted.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(sorted[n / 2]),
        _ => Some(0.5 * (sorted[n / 2 - 1] + sorted[n / 2])),
    }
}

pub fn stats<'a>(cells: impl Iterator<Item = &'a CellResult>, tolerance: f64) -> Stats {
    let (mut et, mut eq, mut sc) = (Vec::new(), Vec::new(), Vec::new());
    let (mut frames, mut failures, mut dropped, mut err_sum) = (0, 0, 0, 0.0);
    for f in cells.flat_map(|c| &c.frames) {
        match f.status {
            FrameStatus::Dropped => dropped += 1,
            FrameStatus::NoTruth => {}
            FrameStatus::NoPose => {
                frames += 1;
                failures += 1;
                err_sum += ERROR_CAP;
            }
            FrameStatus::Posed => {
                frames += 1;
                let (t, q, s) = (f.e_t.unwrap_or(f64::NAN), f.e_q.unwrap_or(f64::NAN), f.score.unwrap_or(f64::NAN));
                // NaN (a SUT's degenerate pose) fails and counts the cap.
                if s.is_nan() || s > tolerance {
                    failures += 1;
                }
                err_sum += if s.is_nan() { ERROR_CAP } else { s.min(ERROR_CAP) };
                et.push(if t.is_nan() { f64::INFINITY } else { t });
                eq.push(if q.is_nan() { f64::INFINITY } else { q });
                sc.push(if s.is_nan() { f64::INFINITY } else { s });
            }
        }
    }
    for v in [&mut et, &mut eq, &mut sc] {
        v.sort_by(f64::total_cmp);
    }
    let fin = |x: Option<f64>| x.filter(|v| v.is_finite());
    Stats {
        frames,
        posed: sc.len(),
        failures,
        failure_rate: (frames > 0).then(|| failures as f64 / frames as f64),
        mean_error: (frames > 0).then(|| err_sum / frames as f64),
        median_e_t: fin(median(&et)),
        p95_e_t: fin(pct(&et, 0.95)),
        median_e_q: fin(median(&eq)),
        p95_e_q: fin(pct(&eq, 0.95)),
        median_score: fin(median(&sc)),
        p95_score: fin(pct(&sc, 0.95)),
        dropped,
    }
}

/// The lowest level (1-based) whose failure rate reaches the threshold, with its value.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BreakingPoint {
    pub level: usize,
    pub value: f64,
}

/// Curves of one effect (or pair) over its levels.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Curve {
    pub name: String,
    /// Swept parameter (for pairs: `a.param+b.param`).
    pub param: String,
    /// Parameter value per level (for pairs: the first effect's).
    pub values: Vec<f64>,
    pub levels: Vec<Stats>,
    pub breaking_point: Option<BreakingPoint>,
    pub ce: Option<f64>,
    pub mean_failure_rate: Option<f64>,
    pub relative_failure: Option<f64>,
}

/// A cell where the SUT misbehaved or the cell could not run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Incident {
    pub cell: usize,
    pub label: String,
    pub seed: u64,
    /// Live mode: the frame (file name) whose report went wrong; none for the cell's own.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame: Option<String>,
    pub what: String,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    pub cells: usize,
    pub frames_scored: usize,
    /// Mean of the effects' `ce` (null when none is defined).
    pub mce: Option<f64>,
    /// Mean failure rate over every effect level.
    pub mean_failure_rate: Option<f64>,
    pub incidents: usize,
}

/// The whole report (report.json).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    pub plan: serde_json::Value,
    pub baseline: Stats,
    pub effects: Vec<Curve>,
    pub pairs: Vec<Curve>,
    pub summary: Summary,
    pub incidents: Vec<Incident>,
}

fn mean(v: impl Iterator<Item = f64>) -> Option<f64> {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    (n > 0).then(|| s / n as f64)
}

/// Build the report from all cells of a sweep (in cell order).
pub fn build(plan_json: &serde_json::Value, cells: &[CellResult]) -> Result<Report, String> {
    let plan = PlanView::from_value(plan_json)?;
    let tol = plan.tolerance;
    use super::plan::CellKind;
    let baseline = stats(cells.iter().filter(|c| c.cell.kind == CellKind::Baseline), tol);
    let curve = |name: String, param: String, values: Vec<f64>, sel: &dyn Fn(CellKind) -> Option<usize>| {
        let n = values.len();
        let levels: Vec<Stats> =
            (1..=n).map(|l| stats(cells.iter().filter(|c| sel(c.cell.kind) == Some(l)), tol)).collect();
        let breaking_point = levels
            .iter()
            .position(|s| s.failure_rate.is_some_and(|r| r >= plan.threshold))
            .map(|i| BreakingPoint { level: i + 1, value: values[i] });
        let ce = match baseline.mean_error {
            Some(b) if b > 0.0 => {
                let s: Option<f64> = levels.iter().map(|l| l.mean_error).sum();
                s.map(|s| s / (n as f64 * b))
            }
            _ => None,
        };
        let mean_failure_rate = mean(levels.iter().filter_map(|l| l.failure_rate));
        let relative_failure = mean_failure_rate.zip(baseline.failure_rate).map(|(m, b)| m - b);
        Curve { name, param, values, levels, breaking_point, ce, mean_failure_rate, relative_failure }
    };
    let effects: Vec<Curve> = plan
        .effects
        .iter()
        .enumerate()
        .map(|(i, e)| {
            let sel = move |k: CellKind| match k {
                CellKind::Effect { effect, level } if effect == i => Some(level),
                _ => None,
            };
            curve(e.name.clone(), e.param.clone(), e.values.clone(), &sel)
        })
        .collect();
    let pairs: Vec<Curve> = plan
        .pairs
        .iter()
        .enumerate()
        .map(|(i, (a, b))| {
            let (ea, eb) = (&plan.effects[*a], &plan.effects[*b]);
            let sel = move |k: CellKind| match k {
                CellKind::Pair { pair, level } if pair == i => Some(level),
                _ => None,
            };
            curve(format!("{}+{}", ea.name, eb.name), format!("{}+{}", ea.param, eb.param), ea.values.clone(), &sel)
        })
        .collect();
    let mut incidents = Vec::new();
    for c in cells {
        let what = match (&c.error, &c.sut) {
            (Some(e), _) => Some(format!("cell not run: {e}")),
            (None, Some(s)) if s.incident() => {
                let mut w = vec![format!("sut {}", s.status)];
                if s.no_output {
                    w.push("no output file".into());
                }
                if s.garbage_lines > 0 {
                    w.push(format!(
                        "{} garbage line(s), first {}",
                        s.garbage_lines,
                        s.first_garbage.as_deref().unwrap_or("")
                    ));
                }
                if s.unknown_files > 0 {
                    w.push(format!("{} pose(s) for unknown files", s.unknown_files));
                }
                if s.duplicates > 0 {
                    w.push(format!("{} duplicate pose(s)", s.duplicates));
                }
                Some(w.join("; "))
            }
            _ => None,
        };
        let mut add = |frame: Option<&str>, what: String| {
            let frame = frame.map(str::to_string);
            incidents.push(Incident { cell: c.cell.index, label: c.label.clone(), seed: c.cell.seed, frame, what });
        };
        if let Some(what) = what {
            add(None, what);
        }
        for f in &c.frames {
            if let Some(what) = &f.incident {
                add(Some(&f.file), what.clone());
            }
        }
    }
    let summary = Summary {
        cells: cells.len(),
        frames_scored: cells
            .iter()
            .flat_map(|c| &c.frames)
            .filter(|f| matches!(f.status, FrameStatus::Posed | FrameStatus::NoPose))
            .count(),
        mce: mean(effects.iter().filter_map(|c| c.ce)),
        mean_failure_rate: mean(effects.iter().flat_map(|c| c.levels.iter().filter_map(|l| l.failure_rate))),
        incidents: incidents.len(),
    };
    Ok(Report { plan: plan_json.clone(), baseline, effects, pairs, summary, incidents })
}

fn f(v: Option<f64>) -> String {
    match v {
        None => "–".into(),
        Some(0.0) => "0".into(),
        Some(x) if x.abs() >= 1000.0 || x.abs() < 1e-3 => format!("{x:.2e}"),
        Some(x) => format!("{x:.3}"),
    }
}

pub(crate) fn g(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s.is_empty() || s == "-0" { "0".into() } else { s.to_string() }
}

/// report.md: breaking points, summary, curves per effect, incidents.
pub fn markdown(r: &Report) -> String {
    let p = PlanView::from_value(&r.plan).ok();
    let mut s = String::from("# Robustness sweep\n\n");
    if let Some(p) = &p {
        s += &format!(
            "Source `{}`, SUT `{}`; seeds {:?}; a frame fails without a pose or with score > {}; \
             breaking point = lowest level with failure rate ≥ {}.\n\n",
            r.plan.get("source").and_then(|v| v.as_str()).unwrap_or(""),
            r.plan.get("sut").and_then(|v| v.as_str()).unwrap_or(""),
            p.seeds,
            g(p.tolerance),
            g(p.threshold)
        );
        if let Some(l) = r.plan.get("live") {
            let t = |k: &str| l.get(k).and_then(|v| v.as_str()).unwrap_or("").to_string();
            let n = |k: &str| l.get(k).and_then(|v| v.as_f64()).map(g).unwrap_or_default();
            let pacing = match l.get("fps").and_then(|v| v.as_f64()) {
                Some(f) => format!(", paced at {} frames/s", g(f)),
                None => String::new(),
            };
            s += &format!(
                "Live: frames streamed into `{}`, poses reported over `{}`, {} s per frame (+ {} s start-up){pacing}.\n\n",
                t("sink"),
                t("report"),
                n("frame_timeout_s"),
                n("startup_s")
            );
        }
    }
    let b = &r.baseline;
    s += &format!(
        "Baseline (no fault): {} frames, failure rate {}, median score {}, p95 score {}, mean error {}.\n\n",
        b.frames,
        f(b.failure_rate),
        f(b.median_score),
        f(b.p95_score),
        f(b.mean_error)
    );
    s += &format!(
        "Summary: mCE {} (mean over effects of Σ mean error / (levels · baseline mean error)), \
         mean failure rate {}, {} cells, {} frames scored, {} incident(s).\n\n",
        f(r.summary.mce),
        f(r.summary.mean_failure_rate),
        r.summary.cells,
        r.summary.frames_scored,
        r.summary.incidents
    );
    s += "## Breaking points\n\n| effect | parameter | breaking level | value | mean failure rate | CE |\n|---|---|---|---|---|---|\n";
    for c in r.effects.iter().chain(&r.pairs) {
        let (lvl, val) = match &c.breaking_point {
            Some(bp) => (format!("{} of {}", bp.level, c.values.len()), g(bp.value)),
            None => (format!("none of {}", c.values.len()), "–".into()),
        };
        s += &format!("| {} | {} | {lvl} | {val} | {} | {} |\n", c.name, c.param, f(c.mean_failure_rate), f(c.ce));
    }
    s += "\n## Curves\n\n";
    for c in r.effects.iter().chain(&r.pairs) {
        s += &format!("### {}\n\n![{}](plots/{}.png)\n\n", c.name, c.name, c.name);
        s += &format!(
            "| level | {} | frames | failure rate | median E_t | p95 E_t | median E_q (rad) | p95 E_q | median score | p95 score |\n\
             |---|---|---|---|---|---|---|---|---|---|\n",
            c.param
        );
        s += &format!(
            "| 0 (baseline) | – | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            b.frames,
            f(b.failure_rate),
            f(b.median_e_t),
            f(b.p95_e_t),
            f(b.median_e_q),
            f(b.p95_e_q),
            f(b.median_score),
            f(b.p95_score)
        );
        for (i, l) in c.levels.iter().enumerate() {
            s += &format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
                i + 1,
                g(c.values[i]),
                l.frames,
                f(l.failure_rate),
                f(l.median_e_t),
                f(l.p95_e_t),
                f(l.median_e_q),
                f(l.p95_e_q),
                f(l.median_score),
                f(l.p95_score)
            );
        }
        s += "\n";
    }
    if !r.incidents.is_empty() {
        s += "## Incidents\n\n| cell | fault | seed | frame | what |\n|---|---|---|---|---|\n";
        for i in &r.incidents {
            s += &format!(
                "| {} | {} | {} | {} | {} |\n",
                i.cell,
                i.label,
                i.seed,
                i.frame.as_deref().unwrap_or("–"),
                i.what.replace('|', "\\|")
            );
        }
    }
    s
}

/// Write report.json, report.md, frames.jsonl and plots/ into `out`.
pub fn write(out: &Path, r: &Report, cells: &[CellResult]) -> Result<(), String> {
    std::fs::create_dir_all(out.join("plots")).map_err(|e| format!("cannot create {}: {e}", out.display()))?;
    let w = |name: &str, bytes: &[u8]| {
        std::fs::write(out.join(name), bytes).map_err(|e| format!("cannot write {}: {e}", out.join(name).display()))
    };
    let mut json = serde_json::to_vec_pretty(r).map_err(|e| e.to_string())?;
    json.push(b'\n');
    w("report.json", &json)?;
    w("report.md", markdown(r).as_bytes())?;
    let mut lines = Vec::new();
    for c in cells {
        for fr in &c.frames {
            let v = serde_json::json!({"cell": c.cell.index, "fault": c.label, "seed": c.cell.seed, "frame": fr});
            lines.extend(serde_json::to_vec(&v).map_err(|e| e.to_string())?);
            lines.push(b'\n');
        }
    }
    w("frames.jsonl", &lines)?;
    super::plot::write_plots(&out.join("plots"), r)
}
