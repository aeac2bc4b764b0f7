//! Scoring harness for the diagnosis corpus: writes a case with `realcam`, runs the real
//! `faultcam diagnose` binary on it as a black box, parses `report.json`, checks `fitted.toml`
//! with `faultcam apply`, and scores detection, false discoveries, parameter error and fit.
#![allow(dead_code)]

use crate::realcam::{Case, FS, FixedPattern, Hidden, Img, Prng, expose};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// Effects every camera has: never counted as false discoveries, but their parameters are scored.
pub const CAMERA_NOISE: [&str; 2] = ["shot_noise", "gaussian_noise"];

/// Tolerance on a parameter: pass if |reported − truth| ≤ max(abs, rel·|truth|).
#[derive(Clone, Copy, Debug)]
pub struct Tol {
    pub abs: f64,
    pub rel: f64,
}

/// Stated tolerances per (effect, parameter). Listed, with the reasoning, in README "Tolerances" (under
/// "Concealed-effect corpus (the first corpus)").
pub fn tolerance(effect: &str, param: &str) -> Tol {
    match (effect, param) {
        ("vignetting", "strength") => Tol { abs: 0.03, rel: 0.0 },
        ("defocus", "sigma_px") => Tol { abs: 0.15, rel: 0.30 },
        ("dark_current", "mean_dn") => Tol { abs: 1.0, rel: 0.0 },
        ("dark_current", "hot_pixel_rate") => Tol { abs: 1.5e-4, rel: 0.5 },
        ("channel_shift", _) => Tol { abs: 0.25, rel: 0.0 },
        ("smear", "strength") => Tol { abs: 0.0005, rel: 0.30 },
        ("prnu", "sigma") => Tol { abs: 0.004, rel: 0.35 },
        ("stray_light", "amplitude_dn") => Tol { abs: 1.5, rel: 0.35 },
        ("veiling_glare", "fraction") => Tol { abs: 0.01, rel: 0.5 },
        ("row_noise", "sigma_dn") => Tol { abs: 0.2, rel: 0.30 },
        ("gamma", "gamma") => Tol { abs: 0.03, rel: 0.0 },
        ("jpeg", "quality") => Tol { abs: 10.0, rel: 0.0 },
        ("motion_blur", "length_px") => Tol { abs: 0.75, rel: 0.25 },
        ("motion_blur", "angle_deg") => Tol { abs: 15.0, rel: 0.0 },
        ("blooming", "full_well_fraction") => Tol { abs: 0.03, rel: 0.0 },
        ("blooming", "spread_px") => Tol { abs: 0.5, rel: 0.5 },
        ("hot_pixels", "rate") => Tol { abs: 1e-4, rel: 0.5 },
        ("gain_offset", "gain") => Tol { abs: 0.02, rel: 0.0 },
        ("gain_offset", "offset_dn") => Tol { abs: 1.0, rel: 0.0 },
        ("shot_noise", "gain_e_per_dn") => Tol { abs: 0.0, rel: 0.25 },
        ("gaussian_noise", "sigma_dn") => Tol { abs: 0.4, rel: 0.0 },
        _ => Tol { abs: 0.0, rel: 0.3 },
    }
}

/// Effects whose hidden presence changes 16x16 block means, so `apply` with the fitted model must
/// bring the sim's block means closer to the real ones.
pub fn changes_block_means(effect: &str) -> bool {
    matches!(effect, "vignetting" | "dark_current" | "stray_light" | "gamma" | "gain_offset")
}

/// Error of a reported parameter against the truth (angles modulo 180 degrees).
pub fn param_error(effect: &str, param: &str, reported: f64, truth: f64) -> f64 {
    if effect == "motion_blur" && param == "angle_deg" {
        let d = (reported - truth).rem_euclid(180.0);
        d.min(180.0 - d)
    } else {
        (reported - truth).abs()
    }
}

#[derive(Clone, Debug)]
pub struct ParamScore {
    pub effect: String,
    pub param: String,
    pub truth: f64,
    pub reported: Option<f64>,
    pub pass: bool,
}

impl ParamScore {
    pub fn err(&self) -> Option<f64> {
        self.reported.map(|r| r - self.truth)
    }
}

#[derive(Clone, Debug, Default)]
pub struct CaseScore {
    pub name: String,
    pub negative: bool,
    /// Unpaired case (sim and real show different scenes; `--unpaired`).
    pub unpaired: bool,
    pub hidden: Vec<String>,
    /// Effect names in report order.
    pub reported: Vec<String>,
    pub detected: Vec<String>,
    pub missed: Vec<String>,
    pub false_discoveries: Vec<String>,
    /// Direction of smear etc. that disagree with the truth.
    pub choice_errors: Vec<String>,
    pub params: Vec<ParamScore>,
    pub noise_params: Vec<ParamScore>,
    pub rmse_before: f64,
    pub rmse_after: f64,
    pub apply_ok: bool,
    pub apply_msg: String,
    pub block_before: f64,
    pub block_after: f64,
    pub diagnose_s: f64,
    /// Hard failure (diagnose crashed, no report, unparsable report).
    pub error: Option<String>,
}

impl CaseScore {
    pub fn fit_improved(&self) -> bool {
        self.rmse_after < self.rmse_before
    }
    pub fn needs_block_improvement(&self) -> bool {
        !self.unpaired && self.hidden.iter().any(|e| changes_block_means(e))
    }
}

fn num(v: &serde_json::Value) -> Option<f64> {
    v.as_f64().or_else(|| v.as_str().and_then(|s| s.parse().ok()))
}

fn run(cmd: &mut Command) -> Result<std::process::Output, String> {
    let out = cmd.output().map_err(|e| format!("spawn {cmd:?}: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "{:?} exited {}: {}",
            cmd.get_args().collect::<Vec<_>>(),
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    Ok(out)
}

fn list_pngs(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x.eq_ignore_ascii_case("png")))
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

fn block_means(img: &Img, b: usize) -> Vec<f64> {
    let mut out = Vec::new();
    for by in 0..img.h / b {
        for bx in 0..img.w / b {
            for ch in 0..img.c {
                let mut s = 0.0;
                for y in by * b..(by + 1) * b {
                    for x in bx * b..(bx + 1) * b {
                        s += img.at(x, y, ch);
                    }
                }
                out.push(s / (b * b) as f64);
            }
        }
    }
    out
}

fn rms_diff(a: &[f64], b: &[f64]) -> f64 {
    (a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len().max(1) as f64).sqrt()
}

/// RMS over a folder pair of the difference of 16x16 block means.
fn block_rmse(a_dir: &Path, b_dir: &Path) -> Result<f64, String> {
    let a = list_pngs(a_dir);
    let b = list_pngs(b_dir);
    if a.is_empty() || a.len() != b.len() {
        return Err(format!("{} has {} images, {} has {}", a_dir.display(), a.len(), b_dir.display(), b.len()));
    }
    let mut acc = 0.0;
    for (pa, pb) in a.iter().zip(&b) {
        let (ia, ib) = (Img::load_png(pa)?, Img::load_png(pb)?);
        if (ia.w, ia.h, ia.c) != (ib.w, ib.h, ib.c) {
            return Err(format!("{} and {} differ in size or channels", pa.display(), pb.display()));
        }
        acc += rms_diff(&block_means(&ia, 16), &block_means(&ib, 16)).powi(2);
    }
    Ok((acc / a.len() as f64).sqrt())
}

/// Score a parsed report against the truth of `case`.
pub fn score_report(case: &Case, report: &serde_json::Value) -> CaseScore {
    let mut s = CaseScore {
        name: case.name.clone(),
        negative: case.is_negative_control(),
        unpaired: case.is_unpaired(),
        hidden: case.hidden.iter().map(|h| h.name().to_string()).collect(),
        ..Default::default()
    };
    let findings = report.get("findings").and_then(|f| f.as_array()).cloned().unwrap_or_default();
    let find = |name: &str| findings.iter().find(|f| f.get("effect").and_then(|e| e.as_str()) == Some(name));
    for f in &findings {
        if let Some(e) = f.get("effect").and_then(|e| e.as_str()) {
            s.reported.push(e.to_string());
        }
    }
    for e in &s.reported {
        if !s.hidden.contains(e) && !CAMERA_NOISE.contains(&e.as_str()) && !s.false_discoveries.contains(e) {
            s.false_discoveries.push(e.clone());
        }
    }
    for hd in &case.hidden {
        let name = hd.name();
        match find(name) {
            None => s.missed.push(name.into()),
            Some(f) => {
                s.detected.push(name.into());
                let params = f.get("params");
                for (p, truth) in hd.canonical() {
                    let reported = params.and_then(|ps| ps.get(p)).and_then(num);
                    let tol = tolerance(name, p);
                    let pass =
                        reported.is_some_and(|r| param_error(name, p, r, truth) <= tol.abs.max(tol.rel * truth.abs()));
                    s.params.push(ParamScore { effect: name.into(), param: p.into(), truth, reported, pass });
                }
                for (p, truth) in hd.canonical_choices() {
                    let got = params.and_then(|ps| ps.get(p)).and_then(|v| v.as_str()).unwrap_or("");
                    if got != truth {
                        s.choice_errors.push(format!("{name}.{p}: truth {truth}, reported {got:?}"));
                    }
                }
            }
        }
    }
    let noise_truth = [
        ("shot_noise", "gain_e_per_dn", case.camera.gain_e_per_dn),
        ("gaussian_noise", "sigma_dn", case.camera.read_sigma_dn),
    ];
    for (e, p, truth) in noise_truth {
        let reported = find(e).and_then(|f| f.get("params")).and_then(|ps| ps.get(p)).and_then(num);
        let tol = tolerance(e, p);
        let pass = reported.is_some_and(|r| (r - truth).abs() <= tol.abs.max(tol.rel * truth.abs()));
        s.noise_params.push(ParamScore { effect: e.into(), param: p.into(), truth, reported, pass });
    }
    let rmse = |k: &str| report.pointer(&format!("/fit/{k}/rmse")).and_then(num).unwrap_or(f64::NAN);
    s.rmse_before = rmse("before");
    s.rmse_after = rmse("after");
    s
}

/// Generate `case` under `root/<name>`, run `faultcam diagnose` and `faultcam apply`, and score.
pub fn run_case(case: &Case, root: &Path, faultcam: &Path) -> CaseScore {
    let dir = root.join(&case.name);
    let fail = |msg: String| CaseScore {
        name: case.name.clone(),
        negative: case.is_negative_control(),
        unpaired: case.is_unpaired(),
        hidden: case.hidden.iter().map(|h| h.name().to_string()).collect(),
        missed: case.hidden.iter().map(|h| h.name().to_string()).collect(),
        rmse_before: f64::NAN,
        rmse_after: f64::NAN,
        error: Some(msg),
        ..Default::default()
    };
    if let Err(e) = case.write(&dir) {
        return fail(format!("writing the case: {e}"));
    }
    let out = dir.join("diag");
    let t0 = Instant::now();
    let mut cmd = Command::new(faultcam);
    cmd.arg("diagnose");
    if case.is_unpaired() {
        cmd.arg("--unpaired");
    }
    let res = run(cmd.arg("--sim").arg(dir.join("sim")).arg("--real").arg(dir.join("real")).arg("--out").arg(&out));
    let secs = t0.elapsed().as_secs_f64();
    if let Err(e) = res {
        let mut s = fail(e);
        s.diagnose_s = secs;
        return s;
    }
    let text = match std::fs::read_to_string(out.join("report.json")) {
        Ok(t) => t,
        Err(e) => return fail(format!("{}: {e}", out.join("report.json").display())),
    };
    let report: serde_json::Value = match serde_json::from_str(&text) {
        Ok(v) => v,
        Err(e) => return fail(format!("report.json does not parse: {e}")),
    };
    let mut s = score_report(case, &report);
    s.diagnose_s = secs;
    // fitted.toml must be accepted by `faultcam apply` as it is, on the sim folder.
    let applied = dir.join("applied");
    let fitted = out.join("fitted.toml");
    match run(Command::new(faultcam)
        .arg("apply")
        .arg("--in")
        .arg(dir.join("sim"))
        .arg("--out")
        .arg(&applied)
        .arg("--faults")
        .arg(&fitted))
    {
        Ok(_) => {
            let n_in = list_pngs(&dir.join("sim")).len();
            let n_out = list_pngs(&applied).len();
            if n_out != n_in {
                s.apply_msg = format!("apply wrote {n_out} PNGs for {n_in} inputs");
            } else {
                s.apply_ok = true;
                match (block_rmse(&dir.join("sim"), &dir.join("real")), block_rmse(&applied, &dir.join("real"))) {
                    (Ok(b), Ok(a)) => {
                        s.block_before = b;
                        s.block_after = a;
                    }
                    (Err(e), _) | (_, Err(e)) => {
                        s.apply_ok = false;
                        s.apply_msg = e;
                    }
                }
            }
        }
        Err(e) => s.apply_msg = e,
    }
    s
}

/// Size of the hidden signal against the noise for a case, measured on frame 0: RMS and max |Δ|
/// of the noise-free real-minus-sim difference, and the RMS camera noise over the same image.
pub fn effect_visibility(case: &Case) -> (f64, f64, f64) {
    let sim = case.sim_frame(0);
    // Noise-free exposure: enormous gain (no shot noise), no read noise, no per-frame row noise.
    let cam = crate::realcam::Camera { gain_e_per_dn: 1e9, read_sigma_dn: 0.0, adc_bits: case.camera.adc_bits };
    let hidden: Vec<Hidden> = case
        .hidden
        .iter()
        .filter(|h| !matches!(h, Hidden::RowNoise { .. } | Hidden::RowNoise1f { .. }))
        .cloned()
        .collect();
    let fp = FixedPattern::new(case.w, case.h, case.fmt.channels(), &hidden, case.seed);
    let clean = expose(&sim, &cam, &hidden, &fp, &mut Prng::new(1));
    let d: Vec<f64> = clean.v.iter().zip(&sim.v).map(|(a, b)| a - b).collect();
    let rms = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
    let mx = d.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let mut row = 0.0;
    for h in &case.hidden {
        if let Hidden::RowNoise { sigma_dn } | Hidden::RowNoise1f { sigma_dn } = h {
            row = *sigma_dn;
        }
    }
    // Quantisation step of the case's ADC (DN of an 8-bit image).
    let quant = FS / ((1u32 << case.camera.adc_bits) - 1) as f64;
    let noise_var = sim
        .v
        .iter()
        .filter(|&&v| v < FS)
        .map(|&v| v / case.camera.gain_e_per_dn + case.camera.read_sigma_dn.powi(2) + quant * quant / 12.0)
        .sum::<f64>()
        / sim.v.len() as f64;
    ((rms * rms + row * row).sqrt(), mx.max(row), noise_var.sqrt())
}

/// Aggregate numbers over scored cases.
#[derive(Clone, Debug, Default)]
pub struct Summary {
    pub cases: usize,
    pub negatives: usize,
    pub hidden: usize,
    pub detected: usize,
    pub fd_total: usize,
    pub fd_negatives: usize,
    pub params: usize,
    pub params_pass: usize,
    pub noise_params: usize,
    pub noise_params_pass: usize,
    pub effect_cases: usize,
    pub fit_improved: usize,
    pub apply_ok: usize,
    pub block_cases: usize,
    pub block_improved: usize,
    pub errors: usize,
    pub choice_errors: usize,
    pub diagnose_s: f64,
    pub paired_effect_cases: usize,
}

pub fn summarise(scores: &[CaseScore]) -> Summary {
    let mut m = Summary { cases: scores.len(), ..Default::default() };
    for s in scores {
        m.negatives += s.negative as usize;
        m.hidden += s.hidden.len();
        m.detected += s.detected.len();
        m.fd_total += s.false_discoveries.len();
        if s.negative {
            m.fd_negatives += s.false_discoveries.len();
        } else {
            m.effect_cases += 1;
            if !s.unpaired {
                m.paired_effect_cases += 1;
                m.fit_improved += s.fit_improved() as usize;
            }
        }
        m.params += s.params.len();
        m.params_pass += s.params.iter().filter(|p| p.pass).count();
        m.noise_params += s.noise_params.len();
        m.noise_params_pass += s.noise_params.iter().filter(|p| p.pass).count();
        m.apply_ok += s.apply_ok as usize;
        if s.needs_block_improvement() {
            m.block_cases += 1;
            m.block_improved += (s.apply_ok && s.block_after < s.block_before) as usize;
        }
        m.errors += s.error.is_some() as usize;
        m.choice_errors += s.choice_errors.len();
        m.diagnose_s += s.diagnose_s;
    }
    m
}

fn fmt_param(p: &ParamScore) -> String {
    let got = p.reported.map(|r| format!("{r:.4}")).unwrap_or_else(|| "—".into());
    format!("{}.{} {:.4}→{}{}", p.effect, p.param, p.truth, got, if p.pass { "" } else { " ✗" })
}

/// Three significant digits.
fn sig3(v: f64) -> String {
    if !v.is_finite() {
        "—".into()
    } else if v == 0.0 {
        "0".into()
    } else if v.abs() >= 0.01 {
        format!("{v:.3}")
    } else {
        format!("{v:.2e}")
    }
}

/// Per effect: cases hiding it, detections, and the median absolute error of each canonical
/// parameter of the detected ones (with the number within tolerance).
pub fn per_effect(scores: &[CaseScore]) -> String {
    let mut effects: Vec<String> = Vec::new();
    for s in scores {
        for h in &s.hidden {
            if !effects.contains(h) {
                effects.push(h.clone());
            }
        }
    }
    let mut t = String::from(
        "| effect | cases | detected | parameter: median abs. error (within tolerance) |\n|---|---|---|---|\n",
    );
    for e in &effects {
        let cases = scores.iter().filter(|s| s.hidden.contains(e)).count();
        let det = scores.iter().filter(|s| s.detected.contains(e)).count();
        let mut names: Vec<String> = Vec::new();
        for s in scores {
            for p in s.params.iter().filter(|p| &p.effect == e) {
                if !names.contains(&p.param) {
                    names.push(p.param.clone());
                }
            }
        }
        let mut cols = Vec::new();
        for n in &names {
            let ps: Vec<&ParamScore> =
                scores.iter().flat_map(|s| s.params.iter()).filter(|p| &p.effect == e && &p.param == n).collect();
            let mut errs: Vec<f64> =
                ps.iter().filter_map(|p| p.reported.map(|r| param_error(e, n, r, p.truth))).collect();
            errs.sort_by(|a, b| a.total_cmp(b));
            let med = if errs.is_empty() { f64::NAN } else { errs[errs.len() / 2] };
            cols.push(format!("{n}: {} ({}/{})", sig3(med), ps.iter().filter(|p| p.pass).count(), ps.len()));
        }
        t.push_str(&format!("| {e} | {cases} | {det} | {} |\n", cols.join("; ")));
    }
    t
}

/// Markdown table, one row per case, plus the summary lines.
pub fn markdown(scores: &[CaseScore]) -> String {
    let mut t = per_effect(scores);
    t.push('\n');
    t.push_str("| case | hidden | reported (order) | missed | false disc. | params truth→fit | noise truth→fit | rmse before→after | apply / block-mean rmse | s |\n");
    t.push_str("|---|---|---|---|---|---|---|---|---|---|\n");
    for s in scores {
        let params = s.params.iter().map(fmt_param).collect::<Vec<_>>().join("<br>");
        let noise = s.noise_params.iter().map(fmt_param).collect::<Vec<_>>().join("<br>");
        let apply = if s.apply_ok {
            format!("ok {:.2}→{:.2}", s.block_before, s.block_after)
        } else if s.error.is_some() {
            "—".into()
        } else {
            format!("FAILED: {}", s.apply_msg.chars().take(120).collect::<String>())
        };
        let reported = match &s.error {
            Some(e) => format!("ERROR: {}", e.chars().take(160).collect::<String>().replace('|', "/")),
            None => s.reported.join(", "),
        };
        let mut choice = String::new();
        for c in &s.choice_errors {
            choice.push_str(&format!("<br>✗ {c}"));
        }
        t.push_str(&format!(
            "| {} | {} | {} | {} | {} | {}{} | {} | {:.3}→{:.3} | {} | {:.1} |\n",
            s.name,
            if s.hidden.is_empty() { "(none)".into() } else { s.hidden.join(", ") },
            reported,
            s.missed.join(", "),
            s.false_discoveries.join(", "),
            params,
            choice,
            noise,
            s.rmse_before,
            s.rmse_after,
            apply,
            s.diagnose_s
        ));
    }
    let m = summarise(scores);
    t.push_str(&format!(
        "\nCases {} ({} negative controls). Detection {}/{} hidden effects. False discoveries: {} in total, {} on negative controls. \
         Parameters within tolerance: {}/{} (detected effects); camera noise parameters within tolerance: {}/{}. \
         Fit rmse improved on {}/{} paired effect cases. fitted.toml accepted by apply: {}/{}; block means closer after apply: {}/{} low-frequency cases. \
         Errors: {}. Diagnose time: {:.0} s total.\n",
        m.cases,
        m.negatives,
        m.detected,
        m.hidden,
        m.fd_total,
        m.fd_negatives,
        m.params_pass,
        m.params,
        m.noise_params_pass,
        m.noise_params,
        m.fit_improved,
        m.paired_effect_cases,
        m.apply_ok,
        m.cases,
        m.block_improved,
        m.block_cases,
        m.errors,
        m.diagnose_s
    ));
    t
}
