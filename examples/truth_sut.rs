//! A test SUT for `faultcam sweep` that answers with the truth: it reads a ground-truth log
//! (`faultcam run --log`, whose frame records carry `pose`) and writes each frame's pose as the
//! sweep expects it, named as the sweep names frames (`frame_NNNNNN.png`, or the input's stem
//! with `.png`). A sweep of this SUT must score 0 everywhere: it checks the join, not a stack.
//!
//! Usage: `truth_sut LOG OUT_FILE`.

fn main() -> std::process::ExitCode {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 3 {
        eprintln!("usage: truth_sut LOG OUT_FILE");
        return std::process::ExitCode::from(2);
    }
    let text = match std::fs::read_to_string(&args[1]) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("truth_sut: {}: {e}", args[1]);
            return std::process::ExitCode::from(2);
        }
    };
    let mut out = String::new();
    for line in text.lines() {
        let Ok(v) = serde_json::from_str::<serde_json::Value>(line) else { continue };
        if v.get("record").and_then(|r| r.as_str()) != Some("frame") {
            continue;
        }
        let Some(pose) = v.get("pose") else { continue };
        let seq = v.get("seq").and_then(|s| s.as_u64()).unwrap_or(0);
        let file = match v.get("input").and_then(|i| i.as_str()) {
            Some(name) => {
                let stem = std::path::Path::new(name).file_stem().and_then(|s| s.to_str()).unwrap_or(name);
                format!("{stem}.png")
            }
            None => format!("frame_{seq:06}.png"),
        };
        out += &serde_json::json!({"file": file, "q": pose["q"], "t": pose["t"]}).to_string();
        out.push('\n');
    }
    if let Err(e) = std::fs::write(&args[2], out) {
        eprintln!("truth_sut: {}: {e}", args[2]);
        return std::process::ExitCode::from(2);
    }
    std::process::ExitCode::SUCCESS
}
