//! A test SUT for `faultcam sweep` that answers with the truth: it reads a ground-truth log
//! (`faultcam run --log`, whose frame records carry `pose`) and gives each frame's pose as the
//! sweep expects it. A sweep of this SUT must score 0 everywhere: it checks the join, not a
//! stack.
//!
//! Usage:
//! - batch: `truth_sut LOG OUT_FILE`: one line `{"file":..,"q":..,"t":..}` per frame, named
//!   as the sweep names frames (`frame_NNNNNN.png`, or the input's stem with `.png`);
//! - live: `truth_sut --live LOG INPUT [REPORT]`: INPUT is a folder (a `files:` sink, or a
//!   GStreamer `multifilesink location=DIR/frame_%06d.png`), watched for new image files, or
//!   `v4l2:/dev/videoN` (a live sweep's v4l2loopback sink), read as a camera (each frame's seq
//!   from its buffer timestamp, each seq once). It reports `{"seq":N,"q":..,"t":..}` per frame,
//!   N the seq the frame's name has in the log (or the device's seq), to REPORT:
//!   `udp:HOST:PORT` (one datagram per report) or `-`/absent (stdout). It exits when its
//!   standard input closes (faultcam closes it at the end of the stream). For each frame it
//!   reports it prints `truth_sut: seq N WxH COLOUR pixels HASH` on stderr (FNV-1a 64 of the
//!   decoded pixels): what it was shown, for tests comparing sinks.

use serde_json::Value;
use std::collections::BTreeMap;
use std::process::ExitCode;
use std::sync::atomic::Ordering;

/// Frame records of the log: (sweep name, seq, pose).
fn read_log(path: &str) -> Result<Vec<(String, u64, Value)>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))?;
    let mut out = Vec::new();
    for line in text.lines() {
        let Ok(v) = serde_json::from_str::<Value>(line) else { continue };
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
        out.push((file, seq, pose.clone()));
    }
    Ok(out)
}

fn batch(log: &str, out_file: &str) -> Result<(), String> {
    let mut out = String::new();
    for (file, _, pose) in read_log(log)? {
        out += &serde_json::json!({"file": file, "q": pose["q"], "t": pose["t"]}).to_string();
        out.push('\n');
    }
    std::fs::write(out_file, out).map_err(|e| format!("{out_file}: {e}"))
}

/// `WxH COLOUR pixels HASH` of an image file: FNV-1a 64 of its decoded samples.
fn pixels_digest(path: &std::path::Path) -> String {
    match image::open(path) {
        Ok(img) => {
            let h = img
                .as_bytes()
                .iter()
                .fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3));
            format!("{}x{} {:?} pixels {h:016x}", img.width(), img.height(), img.color())
        }
        Err(e) => format!("unreadable: {e}"),
    }
}

fn live(log: &str, input: &str, report: Option<&str>) -> Result<(), String> {
    use faultcam::sweep::live::sut::{Input, Reporter, stdin_closed};
    let frames = read_log(log)?;
    let by_seq: BTreeMap<u64, Value> = frames.iter().map(|(_, s, p)| (*s, p.clone())).collect();
    let by_name: BTreeMap<String, (u64, Value)> = frames.into_iter().map(|(f, s, p)| (f, (s, p))).collect();
    let mut out = Reporter::open(report.unwrap_or("-"))?;
    let done = stdin_closed();
    let mut input = Input::open(input)?;
    loop {
        let last = done.load(Ordering::Relaxed);
        for (seq, path) in input.poll() {
            // The sweep names frames with .png; a sink may write another image format. A frame
            // read from a device has its seq (and a frame_NNNNNN name).
            let Some(stem) = path.file_stem().and_then(|s| s.to_str()) else { continue };
            let hit = match by_name.get(&format!("{stem}.png")) {
                Some((s, p)) => Some((*s, p)),
                None => seq.and_then(|s| Some((s, by_seq.get(&s)?))),
            };
            if let Some((seq, pose)) = hit {
                eprintln!("truth_sut: seq {seq} {}", pixels_digest(&path));
                let (q, t) = serde_json::from_value(serde_json::json!([pose["q"], pose["t"]]))
                    .map_err(|e| format!("{log}: pose of seq {seq}: {e}"))?;
                out.send(seq, Some((q, t)))?;
            }
        }
        if last {
            return input.finish();
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().collect();
    let r = match args.get(1).map(String::as_str) {
        Some("--live") if (4..=5).contains(&args.len()) => live(&args[2], &args[3], args.get(4).map(String::as_str)),
        Some(_) if args.len() == 3 => batch(&args[1], &args[2]),
        _ => {
            eprintln!("usage: truth_sut LOG OUT_FILE | truth_sut --live LOG DIR|v4l2:/dev/videoN [udp:HOST:PORT|-]");
            return ExitCode::from(2);
        }
    };
    match r {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("truth_sut: {e}");
            ExitCode::from(2)
        }
    }
}
