//! `faultcam diagnose` through the real binary: the report contract of EFFECTS.md (report.json
//! fields, fitted.toml usable by `faultcam apply` as it is, report.md with residual maps and
//! plots), unpaired mode, and errors that name the file concerned. Diagnosis accuracy on concealed
//! effects is tested in `diagnose_corpus.rs` with an independent forward model; here the "real"
//! frames are made with the library itself (strong vignetting and noise) only to exercise the
//! command end to end.

use assert_cmd::Command;
use faultcam::sink::{Sink, files::FilesSink};
use faultcam::source::Source;
use faultcam::source::synth::SynthSource;
use std::path::Path;

fn faultcam() -> Command {
    Command::cargo_bin("faultcam").expect("faultcam binary")
}

fn make_inputs(dir: &Path, n: usize) {
    let mut src = SynthSource::open(&format!("synth:?width=128&height=96&frames={n}&spin_dps=20&earth=true"))
        .expect("synth source");
    let mut sink = FilesSink::open(&format!("files:{}", dir.display())).expect("files sink");
    let mut i = 0;
    while let Some(f) = src.next_frame().expect("frame") {
        sink.write_frame(&f, Some(&format!("img_{i:03}.png"))).expect("write");
        i += 1;
    }
}

fn write(path: &Path, text: &str) {
    std::fs::write(path, text).expect("write file");
}

#[test]
fn diagnose_writes_the_report_contract_and_an_applicable_model() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (sim, real, out, applied) =
        (tmp.path().join("sim"), tmp.path().join("real"), tmp.path().join("out"), tmp.path().join("applied"));
    make_inputs(&sim, 3);
    let cfg = tmp.path().join("camera.toml");
    write(
        &cfg,
        "seed = 3\n[[effects]]\nname = \"vignetting\"\nstrength = 0.3\n\n[[effects]]\nname = \"gaussian_noise\"\nsigma_dn = 2.0\n",
    );
    faultcam().args(["apply", "--in"]).arg(&sim).arg("--out").arg(&real).arg("--faults").arg(&cfg).assert().success();
    faultcam().args(["diagnose", "--sim"]).arg(&sim).arg("--real").arg(&real).arg("--out").arg(&out).assert().success();
    let rep: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).expect("report.json")).expect("json");
    assert_eq!(rep["model"], "fitted.toml");
    for phase in ["before", "after"] {
        for k in ["rmse", "fqi", "hist_corr"] {
            assert!(rep["fit"][phase].get(k).is_some(), "fit.{phase}.{k} missing: {}", rep["fit"]);
        }
    }
    let findings = rep["findings"].as_array().expect("findings");
    for f in findings {
        for k in ["effect", "params", "loss_before", "loss_after", "where", "evidence"] {
            assert!(f.get(k).is_some(), "finding without {k}: {f}");
        }
    }
    let names: Vec<&str> = findings.iter().filter_map(|f| f["effect"].as_str()).collect();
    assert!(names.contains(&"vignetting"), "30 % vignetting not found: {names:?}");
    assert!(names.contains(&"gaussian_noise"), "2 DN read noise not found: {names:?}");
    let v = findings.iter().find(|f| f["effect"] == "vignetting").expect("vignetting");
    let s = v["params"]["strength"].as_f64().expect("strength");
    assert!((s - 0.3).abs() < 0.05, "vignetting strength {s}");
    // The deterministic model is closer to real than the sim was.
    let (b, a) =
        (rep["fit"]["before"]["rmse"].as_f64().expect("rmse"), rep["fit"]["after"]["rmse"].as_f64().expect("rmse"));
    assert!(a < b, "rmse {b} -> {a}");
    // fitted.toml is accepted by apply as it is.
    faultcam()
        .args(["apply", "--in"])
        .arg(&sim)
        .arg("--out")
        .arg(&applied)
        .arg("--faults")
        .arg(out.join("fitted.toml"))
        .assert()
        .success();
    assert_eq!(
        std::fs::read_dir(&applied)
            .expect("applied")
            .filter(|e| e.as_ref().is_ok_and(|e| e.path().extension().is_some_and(|x| x == "png")))
            .count(),
        3
    );
    let md = std::fs::read_to_string(out.join("report.md")).expect("report.md");
    assert!(md.contains("residual_before.png") && md.contains("residual_after.png"));
    assert!(out.join("residual_before.png").is_file() && out.join("residual_after.png").is_file());
    assert!(md.contains("Forward-model selection"));
}

/// `faultcam diagnose --unpaired` on two folders; the parsed report.json.
fn diagnose_unpaired(sim: &Path, real: &Path, out: &Path) -> serde_json::Value {
    faultcam()
        .args(["diagnose", "--unpaired", "--sim"])
        .arg(sim)
        .arg("--real")
        .arg(real)
        .arg("--out")
        .arg(out)
        .assert()
        .success();
    serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).expect("report.json")).expect("json")
}

#[test]
fn diagnose_unpaired_writes_a_report() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (sim, real, out) = (tmp.path().join("sim"), tmp.path().join("real"), tmp.path().join("out"));
    make_inputs(&sim, 2);
    make_inputs(&real, 2);
    let rep = diagnose_unpaired(&sim, &real, &out);
    assert_eq!(rep["mode"], "unpaired");
    // Identical sets: nothing to find.
    assert_eq!(rep["findings"].as_array().expect("findings").len(), 0, "{}", rep["findings"]);
    assert!(out.join("fitted.toml").is_file() && out.join("report.md").is_file());
}

#[test]
fn diagnose_errors_name_the_folder() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let missing = tmp.path().join("no_such_folder");
    let sim = tmp.path().join("sim");
    make_inputs(&sim, 1);
    let out = faultcam()
        .args(["diagnose", "--sim"])
        .arg(&sim)
        .arg("--real")
        .arg(&missing)
        .arg("--out")
        .arg(tmp.path().join("out"))
        .assert()
        .code(2)
        .get_output()
        .clone();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no_such_folder"), "{err}");
    // No common file names: the message says how pairs are made.
    let other = tmp.path().join("other");
    std::fs::create_dir_all(&other).expect("mkdir");
    std::fs::copy(sim.join("img_000.png"), other.join("different.png")).expect("copy");
    let out = faultcam()
        .args(["diagnose", "--sim"])
        .arg(&sim)
        .arg("--real")
        .arg(&other)
        .arg("--out")
        .arg(tmp.path().join("out2"))
        .assert()
        .code(2)
        .get_output()
        .clone();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("paired by file name"), "{err}");
}

/// A rendered black sky (0 DN in every dark pixel) carries no information on its level or noise:
/// unpaired against frames whose sky sits at 12 DN with noise, the sim's dark level reads 0 DN
/// (not a censored fit that runs to -100 or -253 DN, which made a 255 DN "dark current" on the
/// blooming validation) and the dark level found is the real's 12 DN. The real frames
/// are the synthetic ones plus a level and Gaussian noise drawn here (xorshift, Box-Muller), not
/// through the library.
#[test]
fn diagnose_unpaired_reads_a_black_sim_sky_as_zero() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (sim, real, out) = (tmp.path().join("sim"), tmp.path().join("real"), tmp.path().join("out"));
    let write_set = |dir: &Path, yaw: f64, lift: Option<(f64, f64)>| {
        let mut src =
            SynthSource::open(&format!("synth:?width=160&height=120&frames=4&spin_dps=20&earth=false&yaw={yaw}"))
                .expect("synth source");
        let mut sink = FilesSink::open(&format!("files:{}", dir.display())).expect("files sink");
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut uniform = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let mut i = 0;
        while let Some(mut f) = src.next_frame().expect("frame") {
            if let Some((level, sd)) = lift {
                for v in f.as_u8_mut().expect("8-bit frame") {
                    let g = (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos();
                    *v = (*v as f64 + level + sd * g).round().clamp(0.0, 255.0) as u8;
                }
            }
            sink.write_frame(&f, Some(&format!("img_{i:03}.png"))).expect("write");
            i += 1;
        }
    };
    write_set(&sim, 0.0, None);
    write_set(&real, 140.0, Some((12.0, 2.0)));
    let rep = diagnose_unpaired(&sim, &real, &out);
    let dark = rep["findings"]
        .as_array()
        .expect("findings")
        .iter()
        .find(|f| f["effect"] == "dark_current")
        .unwrap_or_else(|| panic!("no dark_current finding: {}", rep["findings"]));
    let mean = dark["params"]["mean_dn"].as_f64().expect("mean_dn");
    assert!((mean - 12.0).abs() <= 1.5, "dark level {mean} DN, expected about 12: {dark}");
    // Unpaired, a uniform level is also a black-level offset or light from outside the frame:
    // the report lists both readings with why the data cannot tell them apart.
    let alts: Vec<&str> =
        dark["alternatives"].as_array().expect("alternatives").iter().filter_map(|a| a["effect"].as_str()).collect();
    assert_eq!(alts, ["gain_offset", "stray_light"], "{dark}");
    assert!(dark["alternatives"][0]["evidence"].as_str().is_some_and(|e| e.contains("dark frames")), "{dark}");
    // The sim's own level, as the dark test reports it ("... DN, sim X DN (gap ..."): 0 DN, not
    // a censored fit run far below it.
    let ev = rep["tests"]
        .as_array()
        .expect("tests")
        .iter()
        .find(|t| t["effect"] == "dark_current")
        .and_then(|t| t["evidence"].as_str())
        .expect("dark_current test")
        .to_string();
    let sim_level: f64 = ev
        .split("sim ")
        .nth(1)
        .and_then(|r| r.split(" DN").next())
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no sim level in {ev:?}"));
    assert!(sim_level.abs() <= 0.5, "sim dark level {sim_level} DN for a black sky: {ev}");
}
