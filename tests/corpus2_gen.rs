//! The held-out corpus generator (tools/corpus2/gen.py, issue 13) stays deterministic and keeps
//! every hidden effect at or below the camera noise: `gen.py --check` writes two cases twice and
//! compares the bytes, and measures each hidden effect's noise-free RMS change against the RMS
//! per-pixel noise on every case. It needs `python3`; the script makes its own virtual
//! environment under target/venv-corpus2 with numpy and Pillow on first use (pip).

use std::process::Command;

#[test]
fn corpus2_generator_is_deterministic_and_below_the_noise() {
    let root = env!("CARGO_MANIFEST_DIR");
    let out = Command::new("python3")
        .arg(format!("{root}/tools/corpus2/gen.py"))
        .arg("--check")
        .current_dir(root)
        .output()
        .expect("python3 runs (needed by tools/corpus2/gen.py --check)");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "gen.py --check failed ({}):\n{stdout}\n{stderr}", out.status);
    assert!(stdout.contains("gen.py --check ok"), "no verdict line:\n{stdout}");
    // Every effect case was measured (24 effect cases, 29 hidden effects), none too strong.
    let measured = stdout.lines().filter(|l| l.contains(" vs noise ")).count();
    assert!(measured >= 29, "only {measured} hidden effects measured:\n{stdout}");
    assert!(!stdout.contains("TOO STRONG"), "{stdout}");
}
