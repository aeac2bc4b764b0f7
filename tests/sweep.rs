//! Pose truth in the ground-truth log and `faultcam sweep` end to end through the real binary:
//! a SUT that answers with the truth scores 0, one that answers nothing fails every frame, one
//! that crashes, hangs or prints garbage is recorded and the sweep goes on, shards merge into
//! the unsharded report byte for byte, and the reference SUT is near exact on clean frames.

#[path = "support/files.rs"]
mod files;
use faultcam::pose::{Pose, rotation_error};
use faultcam::source::Source;
use faultcam::source::synth::SynthSource;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

const FAULTCAM: &str = env!("CARGO_BIN_EXE_faultcam");
const SYNTH: &str = "synth:?width=64&height=48&frames=3&spin_dps=30";

fn run_ok(c: &mut Command) -> String {
    let out = c.output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{err}");
    err
}

fn records(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

fn frames(recs: &[Value]) -> Vec<&Value> {
    recs.iter().filter(|r| r["record"] == "frame").collect()
}

fn pose_of(v: &Value) -> Pose {
    serde_json::from_value(v.clone()).unwrap()
}

/// An example binary of this package, built in the test's profile when missing or stale.
fn example(name: &str) -> PathBuf {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _g = LOCK.lock().unwrap_or_else(|e| e.into_inner());
    let bin_dir = Path::new(FAULTCAM).parent().unwrap();
    let mut c = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    c.args(["build", "--quiet", "--example", name]).current_dir(env!("CARGO_MANIFEST_DIR"));
    if bin_dir.ends_with("release") {
        c.arg("--release");
    }
    assert!(c.status().unwrap().success(), "cargo build --example {name}");
    bin_dir.join("examples").join(name)
}

fn empty_faults(dir: &Path) -> PathBuf {
    let p = dir.join("empty.toml");
    std::fs::write(&p, "seed = 0\n").unwrap();
    p
}

/// A SUT command answering with the truth: `faultcam run` logs the same source, truth_sut
/// turns the log into poses.
fn truth_sut(dir: &Path) -> String {
    format!(
        "test -d {{in_dir}} && '{FAULTCAM}' run --source '{SYNTH}' --sink null: --faults '{}' --log {{cell_dir}}/gt.jsonl >/dev/null 2>&1 \
         && '{}' {{cell_dir}}/gt.jsonl {{out_file}}",
        empty_faults(dir).display(),
        example("truth_sut").display()
    )
}

fn sweep(out: &Path, sut: &str, extra: &[&str]) -> Value {
    let mut c = Command::new(FAULTCAM);
    c.args(["sweep", "--source", SYNTH, "--sut", sut, "--out"]).arg(out).args(extra);
    run_ok(&mut c);
    serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap()
}

#[test]
fn synth_logs_pose_and_camera_per_frame() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("gt.jsonl");
    let mut c = Command::new(FAULTCAM);
    c.args(["run", "--source", SYNTH, "--sink", "null:", "--faults"])
        .arg(empty_faults(dir.path()))
        .arg("--log")
        .arg(&log);
    run_ok(&mut c);
    let recs = records(&log);
    let fr = frames(&recs);
    assert_eq!(fr.len(), 3);
    let mut s = SynthSource::open(SYNTH).unwrap();
    for r in fr {
        s.next_frame().unwrap().unwrap();
        let seq = r["seq"].as_u64().unwrap();
        let (p, want) = (pose_of(&r["pose"]), s.pose_truth(seq));
        assert!(rotation_error(&p.q, &want.q) < 1e-9 && p.t == want.t, "{r}");
        // Unit quaternion; the spin moves the attitude by 30 deg/s / 30 fps = 1 deg per frame.
        assert!((p.q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-12);
        let k = &r["camera"];
        let f = 32.0 / (15f64).to_radians().tan();
        assert!((k["fx"].as_f64().unwrap() - f).abs() < 1e-9 && k["cx"] == 31.5 && k["cy"] == 23.5, "{k}");
    }
    let q0 = pose_of(&frames(&recs)[0]["pose"]).q;
    let q2 = pose_of(&frames(&recs)[2]["pose"]).q;
    assert!((rotation_error(&q0, &q2).to_degrees() - 2.0).abs() < 1e-6);
}

#[test]
fn files_carry_a_poses_file_into_the_log() {
    let dir = files::png_folder(3);
    let poses = dir.path().join("poses.csv");
    std::fs::write(&poses, "filename,qw,qx,qy,qz,x,y,z\nimg_000.png,1,0,0,0,0.5,-0.25,10\nimg_002.png,0,0,0,2,0,0,7\n")
        .unwrap();
    let log = dir.path().join("out/gt.jsonl");
    std::fs::create_dir_all(dir.path().join("out")).unwrap();
    let mut c = Command::new(FAULTCAM);
    c.arg("run")
        .arg("--source")
        .arg(format!("files:{}?poses=poses.csv&fx=100&fy=100&cx=7.5&cy=3.5", dir.path().display()))
        .args(["--sink", "null:", "--faults"])
        .arg(empty_faults(&dir.path().join("out")))
        .arg("--log")
        .arg(&log);
    run_ok(&mut c);
    let recs = records(&log);
    let fr = frames(&recs);
    // The poses file is not an input.
    assert_eq!(
        fr.iter().map(|r| r["input"].as_str().unwrap()).collect::<Vec<_>>(),
        ["img_000.png", "img_001.png", "img_002.png"]
    );
    assert_eq!(pose_of(&fr[0]["pose"]), Pose { q: [1.0, 0.0, 0.0, 0.0], t: [0.5, -0.25, 10.0] });
    assert!(fr[1].get("pose").is_none(), "no line, no pose");
    assert_eq!(pose_of(&fr[2]["pose"]).q, [0.0, 0.0, 0.0, 1.0], "normalised");
    assert_eq!(fr[1]["camera"]["fx"], 100.0);
    // A bad line is named with its file and line.
    std::fs::write(&poses, "img_000.png,1,0,0,0,0,0,10\nimg_001.png,1,0,0\n").unwrap();
    let out = c.output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("poses.csv:2") && err.contains("8 fields"), "{err}");
}

#[test]
fn truth_scores_zero_and_silence_fails_every_frame() {
    let dir = tempfile::tempdir().unwrap();
    let args =
        ["--effects", "defocus,gaussian_noise", "--levels", "2", "--seeds", "1,2", "--pairs", "defocus+gaussian_noise"];
    let r = sweep(&dir.path().join("truth"), &truth_sut(dir.path()), &args);
    let b = &r["baseline"];
    assert_eq!((b["frames"].as_u64(), b["failure_rate"].as_f64()), (Some(6), Some(0.0)), "{b}");
    let curves: Vec<&Value> = r["effects"].as_array().unwrap().iter().chain(r["pairs"].as_array().unwrap()).collect();
    assert_eq!(curves.len(), 3);
    for c in &curves {
        assert!(c["breaking_point"].is_null(), "{c}");
        for l in c["levels"].as_array().unwrap() {
            assert_eq!(l["frames"], 6);
            assert_eq!(l["failure_rate"], 0.0);
            assert!(l["p95_score"].as_f64().unwrap() < 1e-12, "{l}");
        }
        // The baseline's error is 0: the corruption error is undefined.
        assert!(c["ce"].is_null());
    }
    assert_eq!(r["summary"]["incidents"], 0);
    let frames = std::fs::read_to_string(dir.path().join("truth/frames.jsonl")).unwrap();
    assert_eq!(frames.lines().count(), 2 * (1 + 2 + 2 + 2) * 3);
    for p in ["report.md", "plots/defocus.png", "plots/failure_rate.png", "plots/defocus+gaussian_noise.png"] {
        assert!(dir.path().join("truth").join(p).exists(), "{p}");
    }

    // A SUT that answers nothing: every frame fails, the breaking point is the first level.
    let r = sweep(&dir.path().join("silent"), "true {in_dir} {out_file}", &args);
    assert_eq!(r["baseline"]["failure_rate"], 1.0);
    for c in r["effects"].as_array().unwrap() {
        assert_eq!(c["breaking_point"]["level"], 1);
        assert!(c["levels"].as_array().unwrap().iter().all(|l| l["failure_rate"] == 1.0 && l["posed"] == 0));
        // Same error as the baseline at every level: CE = 1.
        assert!((c["ce"].as_f64().unwrap() - 1.0).abs() < 1e-12);
    }
    // The missing output is an incident of every cell.
    assert_eq!(r["summary"]["incidents"], 14);
}

#[test]
fn crashes_hangs_and_garbage_are_recorded_and_the_sweep_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let truth = truth_sut(dir.path());
    // Cell 1 crashes, cell 2 hangs, cell 3 prints garbage (and one good line), the rest answer.
    let sut = format!(
        "case {{cell_dir}} in *cell-00001) kill -SEGV $$;; *cell-00002) sleep 60;; \
         *cell-00003) printf 'nonsense\\nframe_000000.png,1,0,0\\n' > {{out_file}};; *) {truth};; esac"
    );
    let t0 = std::time::Instant::now();
    let r = sweep(&dir.path().join("o"), &sut, &["--effects", "defocus", "--levels", "4", "--timeout-s", "1"]);
    assert!(t0.elapsed().as_secs() < 50, "the hanging SUT was killed at its time-out");
    let inc = r["incidents"].as_array().unwrap();
    let what = |cell: u64| inc.iter().find(|i| i["cell"] == cell).map(|i| i["what"].as_str().unwrap().to_string());
    assert!(what(1).unwrap().contains("killed by signal 11"), "{inc:?}");
    assert!(what(2).unwrap().contains("timeout after 1 s"), "{inc:?}");
    let g = what(3).unwrap();
    assert!(g.contains("2 garbage line(s)") && g.contains("line 1: expected 8 fields"), "{g}");
    assert_eq!(inc.len(), 3);
    let lv = r["effects"][0]["levels"].as_array().unwrap();
    for (i, l) in lv.iter().enumerate() {
        let want = if i < 3 { 1.0 } else { 0.0 };
        assert_eq!(l["failure_rate"], want, "level {}", i + 1);
    }
    assert_eq!(r["effects"][0]["breaking_point"]["level"], 1);
}

#[test]
fn shards_merge_into_the_unsharded_report() {
    let dir = tempfile::tempdir().unwrap();
    // Every frame gets the identity attitude at 25 m: errors differ per frame and fault.
    let sut = "for f in {in_dir}/*.png; do echo \"$(basename $f),1,0,0,0,0,0,25\"; done > {out_file}";
    let args = ["--effects", "defocus,jpeg,gaussian_noise", "--levels", "2", "--seeds", "3,4", "--tolerance", "0.65"];
    let mut a: Vec<&str> = args.to_vec();
    a.extend(["--jobs", "2"]);
    let whole = sweep(&dir.path().join("whole"), sut, &a);
    assert!(whole["baseline"]["median_e_q"].as_f64().unwrap() > 0.1);
    let shards = dir.path().join("shards");
    for k in 0..3 {
        let mut c = Command::new(FAULTCAM);
        c.args(["sweep", "--source", SYNTH, "--sut", sut, "--shard", &format!("{k}/3"), "--out"])
            .arg(&shards)
            .args(args);
        run_ok(&mut c);
    }
    let merged = dir.path().join("merged");
    run_ok(Command::new(FAULTCAM).args(["sweep", "merge", "--out"]).arg(&merged).arg(&shards));
    let read = |d: &Path| std::fs::read(d.join("report.json")).unwrap();
    assert_eq!(read(&dir.path().join("whole")), read(&merged), "merged report == unsharded report");
    assert_eq!(
        std::fs::read(dir.path().join("whole/frames.jsonl")).unwrap(),
        std::fs::read(merged.join("frames.jsonl")).unwrap()
    );
    // A missing shard is named.
    std::fs::remove_file(shards.join("shard-1-of-3.json")).unwrap();
    let out = Command::new(FAULTCAM).args(["sweep", "merge", "--out"]).arg(&merged).arg(&shards).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("cell 1 is missing"), "{err}");
}

#[test]
fn reference_sut_is_near_exact_on_clean_frames() {
    let dir = tempfile::tempdir().unwrap();
    let sut = format!("'{}' {{in_dir}} {{out_file}} {{camera}}", example("ref_sut").display());
    let mut c = Command::new(FAULTCAM);
    c.args(["sweep", "--source", "synth:?width=160&height=120&frames=2&spin_dps=300", "--sut", &sut])
        .args(["--effects", "defocus", "--levels", "1", "--out"])
        .arg(dir.path());
    run_ok(&mut c);
    let r: Value = serde_json::from_slice(&std::fs::read(dir.path().join("report.json")).unwrap()).unwrap();
    let b = &r["baseline"];
    assert_eq!(b["posed"], 2, "{b}");
    assert!(b["p95_e_t"].as_f64().unwrap() < 0.01 && b["p95_e_q"].as_f64().unwrap() < 0.01, "{b}");
    // sigma 20 px on a 160 px frame blurs the spacecraft away from the truth.
    let l = &r["effects"][0]["levels"][0];
    assert!(
        l["failure_rate"].as_f64().unwrap() > 0.0
            || l["median_score"].as_f64().unwrap() > b["p95_score"].as_f64().unwrap(),
        "{l}"
    );
}
