//! Write the diagnosis corpus (issue 7, part 6) to a folder: `<dir>/<case>/{sim,real}/frame_NN.png`
//! and `<dir>/<case>/truth.json`.
//!
//! `cargo run --example make_corpus -- OUT_DIR [--size WxH] [--frames N] [CASE ...]` (all cases
//! when none is named; `--size`/`--frames` render the same cases at another size and frame count,
//! e.g. 640x400 for timing `faultcam diagnose`).
//! The scene renderer and the camera model live in `tests/support/realcam.rs`.

#[path = "../tests/support/realcam.rs"]
mod realcam;

fn main() -> std::process::ExitCode {
    let mut args = std::env::args().skip(1);
    const USAGE: &str = "usage: make_corpus OUT_DIR [--size WxH] [--frames N] [CASE ...]";
    let Some(out) = args.next() else {
        eprintln!("{USAGE}");
        return std::process::ExitCode::from(2);
    };
    // An option in the place of OUT_DIR (e.g. `--help`) is not a directory to write a corpus to.
    if out.starts_with('-') {
        eprintln!("{USAGE}");
        return std::process::ExitCode::from(if out == "--help" || out == "-h" { 0 } else { 2 });
    }
    let mut wanted: Vec<String> = Vec::new();
    let mut size: Option<(usize, usize)> = None;
    let mut frames: Option<usize> = None;
    while let Some(a) = args.next() {
        match a.as_str() {
            "--size" => size = args.next().and_then(|v| realcam::parse_size(&v)),
            "--frames" => frames = args.next().and_then(|v| v.parse().ok()),
            _ if a.starts_with('-') => {
                eprintln!("make_corpus: unknown option {a}\n{USAGE}");
                return std::process::ExitCode::from(2);
            }
            _ => wanted.push(a),
        }
    }
    let out = std::path::PathBuf::from(out);
    let cases: Vec<_> = realcam::corpus()
        .into_iter()
        .chain(realcam::unpaired_corpus())
        .filter(|c| wanted.is_empty() || wanted.contains(&c.name))
        .map(|c| realcam::resized(c, size, frames))
        .collect();
    if cases.is_empty() {
        let names: Vec<String> = realcam::corpus().into_iter().map(|c| c.name).collect();
        eprintln!("no such case; known: {}", names.join(", "));
        return std::process::ExitCode::from(2);
    }
    for c in &cases {
        if let Err(e) = c.write(&out.join(&c.name)) {
            eprintln!("make_corpus: {e}");
            return std::process::ExitCode::from(1);
        }
        let hidden: Vec<&str> = c.hidden.iter().map(|h| h.name()).collect();
        println!(
            "{:24} {:5} {}",
            c.name,
            c.fmt.name(),
            if hidden.is_empty() { "(noise only)".into() } else { hidden.join(", ") }
        );
    }
    std::process::ExitCode::SUCCESS
}
