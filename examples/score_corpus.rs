//! Score `faultcam diagnose` on the diagnosis corpus and print a markdown table.
//!
//! `cargo build --bin faultcam && cargo run --example score_corpus -- [--faultcam PATH]
//!  [--keep DIR] [--out FILE.md] [--size WxH] [--frames N] [CASE ...]`
//!
//! `--faultcam` defaults to the `faultcam` binary next to this example's build directory;
//! `--keep` keeps the generated corpus and the diagnose outputs (default: a temporary folder).
//! The pass/fail thresholds are asserted by `tests/diagnose_corpus.rs`; this tool only reports.

#[path = "../tests/support/realcam.rs"]
mod realcam;
#[path = "../tests/support/realcam_score.rs"]
mod realcam_score;

use std::path::PathBuf;

fn main() -> std::process::ExitCode {
    let mut faultcam: Option<PathBuf> = None;
    let mut keep: Option<PathBuf> = None;
    let mut out: Option<PathBuf> = None;
    let mut wanted = Vec::new();
    let mut size: Option<(usize, usize)> = None;
    let mut frames: Option<usize> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--faultcam" => faultcam = args.next().map(PathBuf::from),
            "--keep" => keep = args.next().map(PathBuf::from),
            "--out" => out = args.next().map(PathBuf::from),
            "--size" => size = args.next().and_then(|v| realcam::parse_size(&v)),
            "--frames" => frames = args.next().and_then(|v| v.parse().ok()),
            _ => wanted.push(a),
        }
    }
    let faultcam = faultcam.unwrap_or_else(|| {
        // target/<profile>/examples/score_corpus → target/<profile>/faultcam
        let exe = std::env::current_exe().unwrap_or_default();
        exe.parent().and_then(|p| p.parent()).map(|p| p.join("faultcam")).unwrap_or_default()
    });
    if !faultcam.is_file() {
        eprintln!("score_corpus: no faultcam binary at {} (build it or pass --faultcam)", faultcam.display());
        return std::process::ExitCode::from(2);
    }
    let tmp;
    let root = match keep {
        Some(k) => k,
        None => {
            tmp = match tempfile::tempdir() {
                Ok(t) => t,
                Err(e) => {
                    eprintln!("score_corpus: tempdir: {e}");
                    return std::process::ExitCode::from(1);
                }
            };
            tmp.path().to_path_buf()
        }
    };
    let cases: Vec<_> = realcam::corpus()
        .into_iter()
        .chain(realcam::unpaired_corpus())
        .filter(|c| wanted.is_empty() || wanted.contains(&c.name))
        .map(|c| realcam::resized(c, size, frames))
        .collect();
    let mut scores = Vec::new();
    for c in &cases {
        let s = realcam_score::run_case(c, &root, &faultcam);
        eprintln!(
            "{:24} reported [{}] missed [{}] false [{}] {:.1} s{}",
            s.name,
            s.reported.join(", "),
            s.missed.join(", "),
            s.false_discoveries.join(", "),
            s.diagnose_s,
            s.error.as_deref().map(|e| format!(" ERROR {e}")).unwrap_or_default()
        );
        scores.push(s);
    }
    let table = realcam_score::markdown(&scores);
    println!("{table}");
    if let Some(o) = out
        && let Err(e) = std::fs::write(&o, &table)
    {
        eprintln!("score_corpus: {}: {e}", o.display());
        return std::process::ExitCode::from(1);
    }
    std::process::ExitCode::SUCCESS
}
