//! A real full disk: a small tmpfs is mounted (needs root with CAP_SYS_ADMIN, as CI runs; the
//! tests print SKIP and pass without it) and `run`/`apply` fill it. The ground-truth log must
//! stay parseable to its last complete record, end with a summary that says how the run ended,
//! and account for every input frame (`faultcam log check` passes).

use std::path::{Path, PathBuf};
use std::process::Command;

fn bin() -> PathBuf {
    assert_cmd::cargo::cargo_bin("faultcam")
}

/// A mounted tmpfs, unmounted on drop.
struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    fn mount(size: &str) -> Option<Tmpfs> {
        let dir = tempfile::tempdir().unwrap();
        let ok = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .status()
            .is_ok_and(|s| s.success());
        if !ok {
            eprintln!(
                "SKIP: cannot mount a {size} tmpfs (needs root with CAP_SYS_ADMIN); the full-disk test did not run"
            );
            return None;
        }
        Some(Tmpfs { dir })
    }
    fn path(&self) -> &Path {
        self.dir.path()
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(self.dir.path()).status();
    }
}

/// Input frames per test: 24 incompressible PNGs of ~66 KB (1.6 MB) overflow the 1 MB tmpfs
/// and the 1 MB above a 2 MB floor on the 3 MB one (12 of them, 0.8 MB, did not).
const N_FRAMES: usize = 24;

/// `n` incompressible 256x256 grey PNGs (~66 KB each).
fn noise_folder(n: usize) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let mut z = 0x9E37_79B9_7F4A_7C15u64;
    for i in 0..n {
        let img = image::GrayImage::from_fn(256, 256, |_, _| {
            z ^= z << 13;
            z ^= z >> 7;
            z ^= z << 17;
            image::Luma([(z >> 24) as u8])
        });
        img.save(dir.path().join(format!("img_{i:03}.png"))).unwrap();
    }
    dir
}

const CFG: &str = "seed = 1\n\n[[effects]]\nname = \"gain_offset\"\ngain = 1.0\n";

fn faults(dir: &Path) -> PathBuf {
    let p = dir.join("f.toml");
    std::fs::write(&p, CFG).unwrap();
    p
}

/// `faultcam log check` on the log: (exit code, stdout).
fn log_check(log: &Path) -> (i32, String) {
    let o = Command::new(bin()).args(["log", "check"]).arg(log).output().unwrap();
    (o.status.code().unwrap_or(-1), String::from_utf8_lossy(&o.stdout).into_owned())
}

fn summary_of(log: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(log).unwrap();
    let last = text.lines().last().unwrap();
    let v: serde_json::Value = serde_json::from_str(last).unwrap();
    assert_eq!(v["record"], "summary", "{last}");
    v
}

#[test]
fn run_onto_a_full_disk_keeps_a_valid_log_with_its_summary() {
    let Some(fs) = Tmpfs::mount("1m") else { return };
    let input = noise_folder(N_FRAMES);
    let work = tempfile::tempdir().unwrap();
    let log = fs.path().join("gt.jsonl");
    let out = Command::new(bin())
        .args(["run", "--source", &format!("files:{}", input.path().display())])
        .args(["--sink", &format!("files:{}", fs.path().join("out").display())])
        .arg("--faults")
        .arg(faults(work.path()))
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("No space left on device"), "{stderr}");
    let s = summary_of(&log);
    assert_eq!(s["stopped_by"], "error", "{s}");
    // The run stops at the error: the frames read so far are delivered or failed, none lost.
    let delivered = s["delivered"].as_u64().unwrap();
    let frames_in = s["frames_in"].as_u64().unwrap();
    assert!(delivered > 0 && delivered < frames_in && frames_in <= N_FRAMES as u64, "{s}");
    assert_eq!(delivered + s["failed"].as_u64().unwrap(), frames_in, "{s}");
    assert_eq!(s["unaccounted"], 0, "{s}");
    let (code, report) = log_check(&log);
    assert_eq!(code, 0, "{report}");
    assert!(report.contains("summary") && report.contains("ok"), "{report}");
}

#[test]
fn a_log_that_fills_the_disk_ends_at_a_whole_record_and_still_has_its_summary() {
    let Some(fs) = Tmpfs::mount("256k") else { return };
    let work = tempfile::tempdir().unwrap();
    let log = fs.path().join("gt.jsonl");
    // Only the log writes to the tmpfs: ~300-byte records fill 256 KB after ~800 frames.
    let out = Command::new(bin())
        .args(["run", "--source", "synth:?width=16&height=16&frames=5000", "--sink", "null:"])
        .arg("--faults")
        .arg(faults(work.path()))
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("cannot write the ground-truth log"), "{stderr}");
    let bytes = std::fs::read(&log).unwrap();
    assert_eq!(bytes.last(), Some(&b'\n'), "the log ends with a whole record");
    let s = summary_of(&log);
    assert_eq!(s["stopped_by"], "error", "{s}");
    assert!(s["error"].as_str().unwrap().contains("ground-truth log"), "{s}");
    let (code, report) = log_check(&log);
    assert_eq!(code, 0, "{report}");
}

#[test]
fn a_free_space_floor_stops_or_drops_before_the_disk_is_full() {
    let Some(fs) = Tmpfs::mount("3m") else { return };
    let input = noise_folder(N_FRAMES);
    let work = tempfile::tempdir().unwrap();
    for (policy, expect_ok) in [("drop", true), ("stop", false)] {
        let out_dir = fs.path().join(format!("out-{policy}"));
        let log = fs.path().join(format!("gt-{policy}.jsonl"));
        let out = Command::new(bin())
            .args(["run", "--source", &format!("files:{}", input.path().display())])
            .args(["--sink", &format!("files:{}", out_dir.display())])
            .arg("--faults")
            .arg(faults(work.path()))
            .arg("--log")
            .arg(&log)
            .args(["--min-free-mb", "2", "--low-disk", policy])
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code() == Some(0), expect_ok, "{policy}: {stderr}");
        assert!(!stderr.contains("No space left"), "{policy}: the floor acts first: {stderr}");
        let s = summary_of(&log);
        let failed = s["failed"].as_u64().unwrap();
        assert!(s["delivered"].as_u64().unwrap() > 0 && failed > 0, "{policy}: {s}");
        if policy == "drop" {
            assert_eq!(s["dropped_low_disk"].as_u64().unwrap(), failed, "{s}");
            assert_eq!(s["frames_in"], N_FRAMES as u64, "{s}");
        } else {
            assert!(s["error"].as_str().unwrap().contains("--min-free-mb 2"), "{s}");
        }
        let text = std::fs::read_to_string(&log).unwrap();
        assert!(text.contains("low disk:"), "{text}");
        let (code, report) = log_check(&log);
        assert_eq!(code, 0, "{policy}: {report}");
        // Free the space for the next policy.
        std::fs::remove_dir_all(&out_dir).unwrap();
    }
}

#[test]
fn apply_onto_a_full_disk_keeps_a_valid_log_with_its_summary() {
    let Some(fs) = Tmpfs::mount("1m") else { return };
    let input = noise_folder(N_FRAMES);
    let out_dir = fs.path().join("out");
    let work = tempfile::tempdir().unwrap();
    let out = Command::new(bin())
        .args(["apply", "--threads", "1", "--in"])
        .arg(input.path())
        .arg("--out")
        .arg(&out_dir)
        .arg("--faults")
        .arg(faults(work.path()))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(0), "{stderr}");
    let log = out_dir.join("groundtruth.jsonl");
    let s = summary_of(&log);
    assert!(s["error"].as_str().unwrap().contains("No space left"), "{s}");
    let (code, report) = log_check(&log);
    assert_eq!(code, 0, "{report}");
}
