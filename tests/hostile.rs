//! Hostile inputs: decompression bombs (headers claiming 100000x100000 over ~100 bytes) are
//! rejected from the header, named with the limit and the flag, skipped while the batch goes
//! on, and the process's peak memory stays small (a memory bound, measured with wait4's
//! ru_maxrss of the child, not a timing).

#[path = "support/bombs.rs"]
mod bombs;
#[path = "support/files.rs"]
mod files;

use std::path::Path;
use std::process::Command;

/// Peak resident memory allowed for a run over the bombs, in MB (the bombs claim 4 to 10 GB).
const PEAK_MB: u64 = 300;

fn bin() -> std::path::PathBuf {
    assert_cmd::cargo::cargo_bin("faultcam")
}

/// Run the binary, returning (exit code, stderr then stdout, peak RSS in MB) measured for this
/// child only (`eval pairs` names a failed pair in its table on stdout).
// The child is reaped by `wait4` (which also gives its peak RSS), not by `Child::wait`.
#[allow(clippy::zombie_processes)]
fn run_measured(args: &[&str], dir: &Path) -> (i32, String, u64) {
    let err_path = dir.join("stderr.txt");
    let out_path = dir.join("stdout.txt");
    let child = Command::new(bin())
        .args(args)
        .stdout(std::fs::File::create(&out_path).unwrap())
        .stderr(std::fs::File::create(&err_path).unwrap())
        .spawn()
        .unwrap();
    let pid = child.id() as libc::pid_t;
    let mut status = 0;
    // SAFETY: plain wait4 on our own child with valid out-pointers.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut ru) };
    assert_eq!(r, pid, "wait4");
    let code = if libc::WIFEXITED(status) { libc::WEXITSTATUS(status) } else { -1 };
    let output = std::fs::read_to_string(&err_path).unwrap() + &std::fs::read_to_string(&out_path).unwrap();
    (code, output, ru.ru_maxrss as u64 / 1024)
}

fn bomb_folder() -> tempfile::TempDir {
    let dir = files::png_folder(3);
    for (name, bytes) in bombs::all() {
        assert!(bytes.len() < 1000, "{name}: {} bytes", bytes.len());
        std::fs::write(dir.path().join(name), bytes).unwrap();
    }
    dir
}

const CFG: &str = "seed = 1\n\n[[effects]]\nname = \"gain_offset\"\ngain = 1.5\n";

fn assert_named(stderr: &str, name: &str, claimed: &str) {
    let line = stderr.lines().find(|l| l.contains(name)).unwrap_or_else(|| panic!("{name} not named:\n{stderr}"));
    assert!(line.contains(claimed) && line.contains("16384x16384") && line.contains("--max-image-dims"), "{line}");
}

#[test]
fn apply_skips_every_bomb_with_bounded_memory() {
    let input = bomb_folder();
    let work = tempfile::tempdir().unwrap();
    let cfg = work.path().join("f.toml");
    std::fs::write(&cfg, CFG).unwrap();
    let out = work.path().join("out");
    let (code, stderr, peak_mb) = run_measured(
        &[
            "apply",
            "--in",
            input.path().to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--faults",
            cfg.to_str().unwrap(),
        ],
        work.path(),
    );
    assert_eq!(code, 0, "{stderr}");
    for (name, claimed) in [
        ("0-bomb-png.png", "100000x100000"),
        ("0-bomb-tiff.tiff", "100000x100000"),
        ("0-bomb-pgm.pgm", "100000x100000"),
        ("0-bomb-jpg.jpg", "65535x65535"),
    ] {
        assert_named(&stderr, name, claimed);
    }
    // The batch went on: the three real images are written, the four bombs are skip records.
    assert_eq!(files::pngs(&out).len(), 3, "{stderr}");
    let log = std::fs::read_to_string(out.join("groundtruth.jsonl")).unwrap();
    let skips: Vec<&str> = log.lines().filter(|l| l.contains("\"record\":\"skip\"")).collect();
    assert_eq!(skips.len(), 4, "{log}");
    assert!(skips.iter().all(|l| l.contains("over the image limit")), "{log}");
    assert!(peak_mb < PEAK_MB, "peak RSS {peak_mb} MB for 4 bombs (limit {PEAK_MB} MB)");
}

#[test]
fn run_from_files_skips_bombs_with_bounded_memory() {
    let input = bomb_folder();
    let work = tempfile::tempdir().unwrap();
    let cfg = work.path().join("f.toml");
    std::fs::write(&cfg, CFG).unwrap();
    let log = work.path().join("gt.jsonl");
    let src = format!("files:{}", input.path().display());
    let (code, stderr, peak_mb) = run_measured(
        &[
            "run",
            "--source",
            &src,
            "--sink",
            "null:",
            "--faults",
            cfg.to_str().unwrap(),
            "--log",
            log.to_str().unwrap(),
        ],
        work.path(),
    );
    assert_eq!(code, 0, "{stderr}");
    assert!(stderr.contains("3 frames in, 3 out") && stderr.contains("4 inputs skipped"), "{stderr}");
    let text = std::fs::read_to_string(&log).unwrap();
    for name in ["0-bomb-png.png", "0-bomb-tiff.tiff", "0-bomb-pgm.pgm", "0-bomb-jpg.jpg"] {
        let rec = text.lines().find(|l| l.contains(name)).unwrap_or_else(|| panic!("{name} not logged:\n{text}"));
        assert!(rec.contains("\"record\":\"skip\"") && rec.contains("--max-image-dims"), "{rec}");
    }
    assert!(peak_mb < PEAK_MB, "peak RSS {peak_mb} MB (limit {PEAK_MB} MB)");
}

#[test]
fn the_flags_change_the_limits() {
    // 16x8 images against a 8x8 cap: every input is over the limit, named with the new limit.
    let input = files::png_folder(2);
    let work = tempfile::tempdir().unwrap();
    let cfg = work.path().join("f.toml");
    std::fs::write(&cfg, CFG).unwrap();
    let out = work.path().join("out");
    let (code, stderr, _) = run_measured(
        &[
            "--max-image-dims",
            "8x8",
            "apply",
            "--in",
            input.path().to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--faults",
            cfg.to_str().unwrap(),
        ],
        work.path(),
    );
    assert_eq!(code, 0, "{stderr}");
    assert!(stderr.contains("img_000.png") && stderr.contains("16x8") && stderr.contains("8x8 pixels"), "{stderr}");
    assert!(files::pngs(&out).is_empty());
    // A memory cap alone: 16x8 grey is 128 bytes, under 1 MB: accepted.
    let out2 = work.path().join("out2");
    let (code, stderr, _) = run_measured(
        &[
            "apply",
            "--max-image-mb",
            "1",
            "--in",
            input.path().to_str().unwrap(),
            "--out",
            out2.to_str().unwrap(),
            "--faults",
            cfg.to_str().unwrap(),
        ],
        work.path(),
    );
    assert_eq!(code, 0, "{stderr}");
    assert_eq!(files::pngs(&out2).len(), 2);
    // Bad values are named with the accepted range.
    let (code, stderr, _) = run_measured(&["--max-image-dims", "0x7", "effects"], work.path());
    assert_eq!(code, 2);
    assert!(stderr.contains("--max-image-dims '0x7'") && stderr.contains("1..=1048576"), "{stderr}");
}

#[test]
fn eval_and_diagnose_name_the_bomb() {
    let work = tempfile::tempdir().unwrap();
    let (a, b) = (work.path().join("a"), work.path().join("b"));
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    std::fs::write(a.join("x.png"), bombs::png(100_000, 100_000)).unwrap();
    std::fs::write(b.join("x.png"), bombs::png(100_000, 100_000)).unwrap();
    let (code, stderr, peak_mb) =
        run_measured(&["eval", "pairs", "--a", a.to_str().unwrap(), "--b", b.to_str().unwrap()], work.path());
    assert_ne!(code, 0);
    assert!(
        stderr.contains("x.png") && stderr.contains("100000x100000") && stderr.contains("--max-image-dims"),
        "{stderr}"
    );
    assert!(peak_mb < PEAK_MB, "peak RSS {peak_mb} MB");
}

#[cfg(feature = "gst")]
#[test]
fn gstreamer_caps_over_the_limit_stop_with_a_clear_error() {
    let work = tempfile::tempdir().unwrap();
    let cfg = work.path().join("f.toml");
    std::fs::write(&cfg, CFG).unwrap();
    let src = "gst:videotestsrc num-buffers=2 ! video/x-raw,format=GRAY8,width=320,height=240 ! appsink";
    let log = work.path().join("gt.jsonl");
    let (code, stderr, _) = run_measured(
        &[
            "--max-image-dims",
            "64x64",
            "run",
            "--source",
            src,
            "--sink",
            "null:",
            "--faults",
            cfg.to_str().unwrap(),
            "--log",
            log.to_str().unwrap(),
        ],
        work.path(),
    );
    assert_ne!(code, 0, "{stderr}");
    assert!(stderr.contains("negotiated caps") && stderr.contains("320x240") && stderr.contains("64x64"), "{stderr}");
}
