//! `report.json` (the contract of EFFECTS.md), `fitted.toml`, and `report.md` with residual maps
//! and evidence plots.

use super::fit::{FitMetrics, Fitted, round_sig};
use super::img::{Pair, luma};
use super::locate::Located;
use super::{DiagnoseError, Options, Profile, plot};
use serde::Serialize;
use std::path::Path;

/// One finding of report.json.
#[derive(Debug, Clone, Serialize)]
pub struct Finding {
    pub effect: String,
    pub params: serde_json::Map<String, serde_json::Value>,
    pub loss_before: f64,
    pub loss_after: f64,
    #[serde(rename = "where")]
    pub where_: String,
    pub evidence: String,
    /// Significance of the signature test (one-sided normal z).
    pub z: f64,
    /// Standard errors of the signature estimates.
    pub stderr: serde_json::Map<String, serde_json::Value>,
    /// How the parameters were obtained.
    pub method: String,
    /// Other effects that explained the data about as well when this one was chosen (BIC
    /// difference < [`ALTERNATIVE_BIC`]) and are not in the model: the data do not tell them
    /// apart, so both are listed with their evidence.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub alternatives: Vec<Alternative>,
}

/// A near-equivalent reading of a finding (see [`Finding::alternatives`]).
#[derive(Debug, Clone, Serialize)]
pub struct Alternative {
    pub effect: String,
    pub label: String,
    /// BIC difference to the chosen effect in the round it was chosen (≥ 0).
    pub bic_gap: f64,
    /// Significance of its own loss drop (one-sided normal z).
    pub z: f64,
    pub evidence: String,
}

/// BIC difference below which two readings count as explaining the data equally (Kass and
/// Raftery: "not worth more than a bare mention").
pub const ALTERNATIVE_BIC: f64 = 2.0;

/// Alternatives of the finding `name` from the selection's forward rounds.
fn alternatives(name: &str, sel: &[super::select::Evidence], in_model: &[&str]) -> Vec<Alternative> {
    // Rounds in which `name` won (gap 0).
    let rounds: Vec<usize> = sel
        .iter()
        .filter(|e| e.effect == name && e.round > 0 && e.gap_to_best.is_some_and(|g| g <= 0.0))
        .map(|e| e.round)
        .collect();
    let mut out: Vec<Alternative> = Vec::new();
    for e in sel {
        let Some(gap) = e.gap_to_best else { continue };
        if !rounds.contains(&e.round) || e.effect == name || in_model.contains(&e.effect.as_str()) {
            continue;
        }
        let bic_gap = 2.0 * gap;
        if bic_gap < ALTERNATIVE_BIC && !out.iter().any(|a| a.label == e.label) {
            out.push(Alternative {
                effect: e.effect.clone(),
                label: e.label.clone(),
                bic_gap: round_sig(bic_gap, 3),
                z: round_sig(e.z, 4),
                evidence: format!(
                    "{} explains the data about as well as {name} did when {name} was chosen (loss drop {:.1}, z = {:.1}, BIC difference {:.2} < {ALTERNATIVE_BIC}): the data do not tell them apart",
                    e.label, e.delta, e.z, bic_gap
                ),
            });
        }
    }
    out
}

#[derive(Debug, Clone, Serialize)]
pub struct FitSummary {
    pub before: FitMetrics,
    pub after: FitMetrics,
}

/// One signature test (detected or not), for transparency.
#[derive(Debug, Clone, Serialize)]
pub struct TestRow {
    pub effect: String,
    pub z: f64,
    pub detected: bool,
    pub size: f64,
    pub size_unit: String,
    #[serde(rename = "where")]
    pub where_: String,
    pub evidence: String,
}

impl TestRow {
    /// The report row of a signature test (values rounded for the report).
    pub fn of(s: &super::Signature) -> TestRow {
        TestRow {
            effect: s.effect.to_string(),
            z: round_sig(s.z, 4),
            detected: s.detected,
            size: round_sig(s.size, 5),
            size_unit: s.size_unit.to_string(),
            where_: s.where_.clone(),
            evidence: s.evidence.clone(),
        }
    }
}

/// The whole report.json.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub findings: Vec<Finding>,
    pub fit: FitSummary,
    pub model: String,
    pub mode: String,
    pub pairs: usize,
    /// RMSE of the full fitted model including its (independent) noise; `fit.after.rmse` is the
    /// deterministic part, since no model can predict the real noise pixel by pixel.
    pub rmse_after_with_noise: f64,
    pub tests: Vec<TestRow>,
    /// Every forward-model test of the selection (paired mode).
    pub selection: Vec<super::select::Evidence>,
    pub dropped: Vec<String>,
    pub notes: Vec<String>,
}

fn jnum(v: f64) -> serde_json::Value {
    if v.is_finite() { serde_json::Value::from(round_sig(v, 6)) } else { serde_json::Value::Null }
}

pub fn build(pairs: &[Pair], loc: &Located, fitted: &Fitted, mut notes: Vec<String>, _opts: &Options) -> Report {
    let in_model: Vec<&str> = fitted.effects.iter().map(|e| e.name).collect();
    let findings = fitted
        .effects
        .iter()
        .map(|e| Finding {
            effect: e.name.to_string(),
            params: e.canonical.iter().cloned().collect(),
            loss_before: round_sig(e.loss_before, 6),
            loss_after: round_sig(e.loss_after, 6),
            where_: e.where_.clone(),
            evidence: e.evidence.clone(),
            z: round_sig(e.z, 4),
            stderr: e.stderr.iter().map(|(n, v)| (n.clone(), jnum(*v))).collect(),
            method: e.method.clone(),
            alternatives: {
                let mut a = alternatives(e.name, &fitted.selection_tests, &in_model);
                for (effects, describe, gap) in &e.alternatives {
                    a.push(Alternative {
                        effect: effects.join(" + "),
                        label: format!("level response read as {}", effects.join(" + ")),
                        // NaN: readings of the level-or-position check, not on a common BIC scale
                        // (reported as null; the evidence gives both tests).
                        bic_gap: if gap.is_nan() { f64::NAN } else { round_sig(gap.max(0.0), 3) },
                        z: f64::NAN,
                        evidence: if gap.is_nan() {
                            describe.clone()
                        } else if *gap < 0.0 {
                            format!(
                                "the level response reads it better ({describe}; BIC better by {:.2}) than the effects reported with {}, which the forward model kept on every pixel or which the level-response rules prefer (a gain and offset must show full scale moved): the data do not settle it",
                                -gap, e.name
                            )
                        } else {
                            format!(
                                "the level response reads about as well ({describe}; BIC difference {gap:.2} < {}) as {}: the data do not tell them apart",
                                super::select::TONE_ALTERNATIVE_BIC,
                                e.name
                            )
                        },
                    });
                }
                a
            },
        })
        .collect();
    notes.extend(loc.notes.iter().cloned());
    notes.extend(fitted.notes.iter().cloned());
    Report {
        findings,
        fit: FitSummary { before: rounded(fitted.before), after: rounded(fitted.after) },
        model: "fitted.toml".into(),
        mode: "paired".into(),
        pairs: pairs.len(),
        rmse_after_with_noise: round_sig(fitted.rmse_after_with_noise, 6),
        tests: loc.signatures.iter().map(TestRow::of).collect(),
        selection: fitted.selection_tests.clone(),
        dropped: fitted.dropped.clone(),
        notes,
    }
}

fn rounded(m: FitMetrics) -> FitMetrics {
    FitMetrics { rmse: round_sig(m.rmse, 6), fqi: m.fqi.map(|v| round_sig(v, 6)), hist_corr: round_sig(m.hist_corr, 6) }
}

fn werr(path: &Path, e: impl std::fmt::Display) -> DiagnoseError {
    DiagnoseError::Write { path: path.to_path_buf(), message: e.to_string() }
}

pub fn write_json(rep: &Report, out: &Path) -> Result<(), DiagnoseError> {
    let p = out.join("report.json");
    let s = serde_json::to_string_pretty(rep).map_err(|e| werr(&p, e))?;
    std::fs::write(&p, s + "\n").map_err(|e| werr(&p, e))
}

fn fmt_metrics(m: &FitMetrics) -> String {
    format!(
        "| {:.3} | {} | {:.4} |",
        m.rmse,
        m.fqi.map(|v| format!("{v:.4}")).unwrap_or_else(|| "n/a".into()),
        m.hist_corr
    )
}

/// Write report.json, fitted.toml and (optionally) report.md with its PNGs.
pub fn write(
    rep: &Report,
    pairs: &[Pair],
    loc: &Located,
    fitted: &Fitted,
    out: &Path,
    opts: &Options,
) -> Result<(), DiagnoseError> {
    write_json(rep, out)?;
    let tp = out.join("fitted.toml");
    let mut toml = String::from(
        "# Fault model fitted by `faultcam diagnose`: apply it to sim images with\n# `faultcam apply --faults fitted.toml --in SIM --out OUT`\n",
    );
    toml.push_str(&fitted.config.to_toml());
    std::fs::write(&tp, toml).map_err(|e| werr(&tp, e))?;
    if !opts.write_markdown {
        return Ok(());
    }
    let mut md = String::new();
    md.push_str("# faultcam diagnose report\n\n");
    md.push_str(&format!("{} sim/real pairs (paired mode). Model: [`fitted.toml`](fitted.toml).\n\n", pairs.len()));
    md.push_str("## Findings (most important first)\n\n");
    if rep.findings.is_empty() {
        md.push_str("No significant mismatch found.\n\n");
    } else {
        md.push_str(
            "| effect | parameters | z | loss before | loss after | where | method |\n|---|---|---|---|---|---|---|\n",
        );
        for f in &rep.findings {
            let params: Vec<String> = f.params.iter().map(|(k, v)| format!("{k} = {v}")).collect();
            md.push_str(&format!(
                "| `{}` | {} | {:.1} | {:.4} | {:.4} | {} | {} |\n",
                f.effect,
                params.join(", "),
                f.z,
                f.loss_before,
                f.loss_after,
                f.where_,
                f.method
            ));
        }
        md.push('\n');
        for f in &rep.findings {
            md.push_str(&format!("- **{}**: {}\n", f.effect, f.evidence));
            for a in &f.alternatives {
                md.push_str(&format!("  - or **{}**: {}\n", a.effect, a.evidence));
            }
        }
        md.push('\n');
    }
    md.push_str("## Fit\n\n| | RMSE (DN) | FQI | histogram correlation |\n|---|---|---|---|\n");
    md.push_str(&format!("| sim vs real (before) {}\n", fmt_metrics(&rep.fit.before)));
    md.push_str(&format!("| model vs real (after) {}\n\n", fmt_metrics(&rep.fit.after)));
    md.push_str(&format!(
        "RMSE after is that of the deterministic part of the model; with the model's own noise it is {:.3} DN \
         (two independent noise draws cannot agree pixel by pixel). FQI and histogram correlation use the full \
         model with noise.\n\n",
        rep.rmse_after_with_noise
    ));
    // Residual maps of the first pair.
    if let (Some(p), Some(mp)) = (pairs.first(), fitted.model_planes.first()) {
        let before = luma(&p.real).sub(&luma(&p.sim));
        let after = luma(&p.real).sub(&luma(mp));
        let mut a: Vec<f64> = before.data.iter().map(|v| v.abs() as f64).collect();
        let scale = super::stats::quantile_mut(&mut a, 0.99).max(3.0 * loc.noise.sd(64.0)) as f32;
        let (pb, pa) = (out.join("residual_before.png"), out.join("residual_after.png"));
        plot::residual_map(&before, scale, &pb).map_err(|e| werr(&pb, e))?;
        plot::residual_map(&after, scale, &pa).map_err(|e| werr(&pa, e))?;
        md.push_str(&format!(
            "### Residual maps ({})\n\nreal − sim (left) and real − model (right), blue negative, red positive, saturating at ±{scale:.1} DN.\n\n\
             ![before](residual_before.png) ![after](residual_after.png)\n\n",
            p.name
        ));
    }
    md.push_str("## Evidence profiles\n\n");
    let mut n_plot = 0;
    for s in &loc.signatures {
        let show = s.detected || matches!(s.effect, "gaussian_noise" | "shot_noise");
        if !show {
            continue;
        }
        for (i, prof) in s.profiles.iter().enumerate() {
            let name = format!("plot_{}_{}.png", s.effect, i);
            let path = out.join(&name);
            plot::line_plot(prof, &path).map_err(|e| werr(&path, e))?;
            md.push_str(&profile_caption(prof, &name));
            n_plot += 1;
        }
    }
    if n_plot == 0 {
        md.push_str("No profiles (nothing detected).\n\n");
    }
    if !rep.selection.is_empty() {
        md.push_str(
            "## Forward-model selection\n\nEach candidate is added to the current model and fitted on the library's forward model; \
             ΔL is the drop of the robust loss, D the design effect of the residual (1 = white), z the significance of \
             2ΔL/D on k parameters, BIC whether it pays for its parameters, and 'change' the size of its change of the \
             expected image (DN). The most important significant candidate joins the model each round.\n\n\
             | round | candidate | ΔL | D | k | z | BIC | change (DN) | chosen |\n|---|---|---|---|---|---|---|---|---|\n",
        );
        for t in &rep.selection {
            md.push_str(&format!(
                "| {} | {} | {:.1} | {:.2} | {} | {:.1} | {} | {:.2} | {} |\n",
                t.round,
                t.label,
                t.delta,
                t.design,
                t.k,
                t.z,
                if t.bic { "yes" } else { "no" },
                t.material_dn,
                if t.accepted { "yes" } else { "" }
            ));
        }
        md.push('\n');
    }
    md.push_str("## All signature tests\n\n| effect | z | detected | size | evidence |\n|---|---|---|---|---|\n");
    for t in &rep.tests {
        md.push_str(&format!(
            "| `{}` | {:.1} | {} | {} {} | {} |\n",
            t.effect,
            t.z,
            if t.detected { "yes" } else { "no" },
            t.size,
            t.size_unit,
            t.evidence.replace('|', "/")
        ));
    }
    if !rep.dropped.is_empty() {
        md.push_str("\n## Dropped by the forward-model fit\n\n");
        for d in &rep.dropped {
            md.push_str(&format!("- {d}\n"));
        }
    }
    if !rep.notes.is_empty() {
        md.push_str("\n## Notes\n\n");
        for n in &rep.notes {
            md.push_str(&format!("- {n}\n"));
        }
    }
    let mp = out.join("report.md");
    std::fs::write(&mp, md).map_err(|e| werr(&mp, e))
}

pub fn profile_caption(prof: &Profile, file: &str) -> String {
    let legend: Vec<String> =
        prof.series.iter().enumerate().map(|(i, (l, _))| format!("{} = {}", plot::colour_name(i), l)).collect();
    format!(
        "**{}** — x: {}; y: {}; {}.\n\n![{}]({})\n\n",
        prof.title,
        prof.x_label,
        prof.y_label,
        legend.join(", "),
        prof.title,
        file
    )
}

/// Output of unpaired mode (report plus its own profiles).
pub struct UnpairedReport {
    pub report: Report,
    pub config: crate::config::FaultConfig,
    pub profiles: Vec<Profile>,
    pub lines: Vec<String>,
}

pub fn write_unpaired(rep: &UnpairedReport, out: &Path, _opts: &Options) -> Result<(), DiagnoseError> {
    write_json(&rep.report, out)?;
    let tp = out.join("fitted.toml");
    let mut toml = String::from("# Fault model fitted by `faultcam diagnose --unpaired`\n");
    toml.push_str(&rep.config.to_toml());
    std::fs::write(&tp, toml).map_err(|e| werr(&tp, e))?;
    let mut md = String::from("# faultcam diagnose report (unpaired)\n\n");
    for l in &rep.lines {
        md.push_str(l);
        md.push('\n');
    }
    md.push_str(
        "\n## Findings\n\n| effect | parameters | loss before | loss after | evidence |\n|---|---|---|---|---|\n",
    );
    for f in &rep.report.findings {
        let params: Vec<String> = f.params.iter().map(|(k, v)| format!("{k} = {v}")).collect();
        md.push_str(&format!(
            "| `{}` | {} | {:.4} | {:.4} | {} |\n",
            f.effect,
            params.join(", "),
            f.loss_before,
            f.loss_after,
            f.evidence
        ));
    }
    // Readings the data cannot tell from a finding, with why.
    for f in rep.report.findings.iter().filter(|f| !f.alternatives.is_empty()) {
        md.push_str(&format!("\n- **{}** cannot be told apart here from:\n", f.effect));
        for a in &f.alternatives {
            md.push_str(&format!("  - **{}**: {}\n", a.label, a.evidence));
        }
    }
    md.push_str("\n## Fit (statistics of the sets)\n\n| | RMSE of mean histograms | FQI | histogram correlation |\n|---|---|---|---|\n");
    md.push_str(&format!("| sim vs real (before) {}\n", fmt_metrics(&rep.report.fit.before)));
    md.push_str(&format!("| model vs real (after) {}\n\n", fmt_metrics(&rep.report.fit.after)));
    md.push_str("## Profiles\n\n");
    for (i, prof) in rep.profiles.iter().enumerate() {
        let name = format!("plot_unpaired_{i}.png");
        let path = out.join(&name);
        plot::line_plot(prof, &path).map_err(|e| werr(&path, e))?;
        md.push_str(&profile_caption(prof, &name));
    }
    if !rep.report.notes.is_empty() {
        md.push_str("\n## Notes\n\n");
        for n in &rep.report.notes {
            md.push_str(&format!("- {n}\n"));
        }
    }
    let mp = out.join("report.md");
    std::fs::write(&mp, md).map_err(|e| werr(&mp, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::select::Evidence;

    fn ev(effect: &str, round: usize, gap: Option<f64>) -> Evidence {
        Evidence {
            effect: effect.into(),
            label: effect.into(),
            loss_without: 10.0,
            loss_with: 9.0,
            delta: 100.0,
            design: 1.0,
            k: 1,
            z: 8.0,
            bic: true,
            material_dn: 2.0,
            accepted: gap.is_some_and(|g| g <= 0.0),
            round,
            gap_to_best: gap,
            params: None,
        }
    }

    #[test]
    fn alternatives_are_near_equal_passing_rivals_of_the_winning_round_not_in_the_model() {
        let sel = vec![
            ev("gamma", 1, Some(0.0)),
            ev("gain_offset", 1, Some(0.4)),  // BIC gap 0.8: listed
            ev("vignetting", 1, Some(3.0)),   // BIC gap 6: clearly worse
            ev("stray_light", 1, None),       // did not pass its tests
            ev("dark_current", 2, Some(0.1)), // another round
            ev("defocus", 1, Some(0.2)),      // ends up in the model itself
        ];
        let alts = alternatives("gamma", &sel, &["gamma", "defocus"]);
        let names: Vec<&str> = alts.iter().map(|a| a.effect.as_str()).collect();
        assert_eq!(names, ["gain_offset"]);
        assert!((alts[0].bic_gap - 0.8).abs() < 1e-9);
        assert!(alts[0].evidence.contains("do not tell them apart"));
        // An effect that never won a round has no alternatives.
        assert!(alternatives("vignetting", &sel, &["vignetting"]).is_empty());
    }
}
