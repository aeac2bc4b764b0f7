//! `faultcam eval` end to end: the real binary on images generated in temporary folders.

mod support_eval;

use assert_cmd::Command;
use serde_json::Value;
use std::path::Path;
use support_eval::*;

fn faultcam() -> Command {
    Command::cargo_bin("faultcam").unwrap()
}

fn gradient(w: usize, h: usize, offset: u8) -> Vec<u8> {
    (0..w * h).map(|i| ((i % w) * 6 + (i / w) * 2) as u8 + offset).collect()
}

#[test]
fn eval_pairs_reports_exact_rmse_psnr_and_unpaired_names() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    // `off`: every pixel 4 DN brighter -> RMSE 4 exactly, PSNR 20 log10(255 / 4) dB.
    save_grey(&a.join("off.png"), 32, 24, gradient(32, 24, 0));
    save_grey(&b.join("off.png"), 32, 24, gradient(32, 24, 4));
    // `same`: identical -> RMSE 0, PSNR infinite (JSON null), SSIM 1.
    save_grey(&a.join("same.png"), 32, 24, gradient(32, 24, 10));
    save_grey(&b.join("same.png"), 32, 24, gradient(32, 24, 10));
    save_grey(&a.join("lonely.png"), 8, 8, vec![0; 64]);
    let out = faultcam()
        .args(["eval", "pairs", "--json", "-", "--a"])
        .arg(&a)
        .arg("--b")
        .arg(&b)
        .assert()
        .success()
        .get_output()
        .stdout
        .clone();
    let v: Value = serde_json::from_slice(&out).unwrap();
    let pairs = v["pairs"].as_array().unwrap();
    assert_eq!(pairs.len(), 2);
    let off = pairs.iter().find(|p| p["name"] == "off").unwrap();
    assert!((off["metrics"]["rmse"].as_f64().unwrap() - 4.0).abs() < 1e-12, "{off}");
    let psnr = 20.0 * (255.0f64 / 4.0).log10();
    assert!((off["metrics"]["psnr"].as_f64().unwrap() - psnr).abs() < 1e-9, "{off}");
    let same = pairs.iter().find(|p| p["name"] == "same").unwrap();
    assert_eq!(same["metrics"]["rmse"], 0.0);
    assert!(same["metrics"]["psnr"].is_null());
    assert!((same["metrics"]["ssim"].as_f64().unwrap() - 1.0).abs() < 1e-12);
    assert_eq!(v["only_in_a"], serde_json::json!(["lonely"]));
    assert_eq!(v["mean"]["pairs"], 2);
    assert!((v["mean"]["rmse"].as_f64().unwrap() - 2.0).abs() < 1e-12);
    // Plain table by default.
    let text = faultcam().args(["eval", "pairs", "--a"]).arg(&a).arg("--b").arg(&b).assert().success();
    let text = String::from_utf8(text.get_output().stdout.clone()).unwrap();
    assert!(text.contains("mean (2)") && text.contains("only in"), "{text}");
}

fn run_blooming(gen_uri: &str, real: &Path, out: &Path, extra: &[&str]) -> (Value, String) {
    let assert = faultcam()
        .args(["eval", "blooming", "--generated", gen_uri, "--real"])
        .arg(real)
        .arg("--out")
        .arg(out)
        .args(["--min-crop", "48", "--orb-patch", "15", "--param", "full_well_fraction=1", "--param"])
        .arg("exposure_gain=3")
        .args(extra)
        .assert()
        .success();
    let stdout = String::from_utf8(assert.get_output().stdout.clone()).unwrap();
    let report: Value = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    (report, stdout)
}

/// Every per-image decision follows the thresholds in the report, and the summary counts them.
fn check_acceptance(r: &Value) -> (u64, u64) {
    let (fmin, cmin) = (r["fqi_min"].as_f64().unwrap(), r["corr_min"].as_f64().unwrap());
    let per = r["per_image"].as_array().unwrap();
    let mut accepted = [0u64, 0];
    for p in per {
        for (k, arm) in ["bloomed", "control"].iter().enumerate() {
            let m = &p[arm];
            let fqi = m["fqi"].as_f64().unwrap_or(0.0);
            let corr = m["hist_corr"].as_f64().unwrap();
            let expected = fqi >= fmin && corr >= cmin;
            assert_eq!(m["accepted"].as_bool().unwrap(), expected, "{arm} {p}");
            accepted[k] += expected as u64;
        }
    }
    for (k, arm) in ["bloomed", "control"].iter().enumerate() {
        let s = &r[arm];
        assert_eq!(s["accepted"].as_u64().unwrap(), accepted[k]);
        assert_eq!(s["total"].as_u64().unwrap(), per.len() as u64);
        let rate = accepted[k] as f64 / per.len() as f64;
        assert!((s["acceptance_rate"].as_f64().unwrap() - rate).abs() < 1e-12);
        for stat in ["fqi", "hist_corr", "matches", "bright_fraction"] {
            for key in ["n", "mean", "median", "std", "min", "max"] {
                assert!(s[stat][key].is_number(), "{arm}.{stat}.{key}");
            }
        }
    }
    (accepted[0], accepted[1])
}

#[test]
fn eval_blooming_runs_the_protocol_end_to_end() {
    let tmp = tempfile::tempdir().unwrap();
    let real = tmp.path().join("real");
    std::fs::create_dir_all(&real).unwrap();
    write_reals(&real, 3, 160, 100);
    let uri = "synth:?width=160&height=100&frames=5&spin_dps=25&distance_m=14&fps=1";

    let out = tmp.path().join("default");
    let (r, stdout) = run_blooming(uri, &real, &out, &[]);
    assert!(stdout.contains("accepted at FQI >= 0.8 and corr >= 0.9"), "{stdout}");
    assert!(stdout.contains("study:   189/210 accepted"), "{stdout}");
    assert!(stdout.starts_with(&std::fs::read_to_string(out.join("summary.txt")).unwrap()), "{stdout}");
    assert_eq!(
        (r["threshold"].as_f64(), r["fqi_min"].as_f64(), r["corr_min"].as_f64()),
        (Some(250.0), Some(0.8), Some(0.9))
    );
    assert_eq!(r["generated_read"], 5);
    assert_eq!(r["per_image"].as_array().unwrap().len(), 5);
    assert_eq!(r["real_used"].as_array().unwrap().len(), 3);
    assert_eq!(r["blooming_params"]["exposure_gain"], 3.0);
    assert_eq!(r["blooming_params"]["mode"], "charge");
    assert_eq!(r["study"]["accepted"], 189);
    check_acceptance(&r);
    for p in ["fqi_hist.png", "hist_corr_hist.png", "grey_hist.png"] {
        let img = image::open(out.join(p)).unwrap();
        assert_eq!((img.width(), img.height()), (720, 400), "{p}");
    }
    assert_eq!(r["plots"].as_array().unwrap().len(), 3);

    // Thresholds everyone passes, and thresholds nobody can pass.
    let (r, _) =
        run_blooming(uri, &real, &tmp.path().join("lax"), &["--fqi-min", "0", "--corr-min", "-1", "--no-crops"]);
    assert_eq!(check_acceptance(&r), (5, 5));
    assert!(!tmp.path().join("lax/crops").exists());
    let (r, _) = run_blooming(uri, &real, &tmp.path().join("strict"), &["--fqi-min", "1.01", "--no-crops"]);
    assert_eq!(check_acceptance(&r), (0, 0));
    // A correlation threshold between the bloomed and control scores splits them.
    let corr: Vec<f64> =
        r["per_image"].as_array().unwrap().iter().map(|p| p["bloomed"]["hist_corr"].as_f64().unwrap()).collect();
    let mid = (corr.iter().cloned().fold(f64::INFINITY, f64::min)
        + corr.iter().cloned().fold(f64::NEG_INFINITY, f64::max))
        / 2.0;
    let (r, _) = run_blooming(
        uri,
        &real,
        &tmp.path().join("mid"),
        &["--fqi-min", "0", "--corr-min", &mid.to_string(), "--no-crops"],
    );
    let (acc, _) = check_acceptance(&r);
    let expected = corr.iter().filter(|&&c| c >= mid).count() as u64;
    assert_eq!(acc, expected);
    assert!(acc > 0 && acc < 5, "corr {corr:?} mid {mid}");
}

#[test]
fn eval_blooming_errors_name_the_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("no-such-folder");
    let a = faultcam()
        .args(["eval", "blooming", "--generated", "synth:?width=64&height=48&frames=1", "--real"])
        .arg(&missing)
        .arg("--out")
        .arg(tmp.path().join("o"))
        .assert()
        .code(2);
    let err = String::from_utf8(a.get_output().stderr.clone()).unwrap();
    assert!(err.contains(&missing.display().to_string()), "{err}");
    let a = faultcam()
        .args([
            "eval",
            "blooming",
            "--generated",
            "synth:?width=64&height=48&frames=1",
            "--param",
            "spread_px=99",
            "--real",
        ])
        .arg(tmp.path())
        .arg("--out")
        .arg(tmp.path().join("o"))
        .assert()
        .code(2);
    let err = String::from_utf8(a.get_output().stderr.clone()).unwrap();
    assert!(err.contains("spread_px") && err.contains("8"), "{err}");
}
