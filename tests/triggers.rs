//! Serial triggers end to end: the real `faultcam run` binary streams frames while a scripted
//! rig on the other end of a real pseudo-terminal pair (`TTYPort::pair`) sends commands,
//! garbage and partial lines. The test checks the acknowledgements (frame seq and stream time
//! at which each change took effect), the NAKs, which frames carry the fault (log and pixels),
//! that the stream never stops, and that replaying the recorded triggers from the ground-truth
//! log reproduces the output bytes exactly.

#[path = "support/files.rs"]
mod files;
use files::pngs;
use serde_json::Value;
use serialport::{SerialPort, TTYPort};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const FAULTCAM: &str = env!("CARGO_BIN_EXE_faultcam");

/// Frames of the rig test, at 25 fps (40 ms per frame: stream time = seq · 40 ms).
const FRAMES: u64 = 80;
const FRAME_NS: u64 = 40_000_000;

const CAMPAIGN: &str = r#"seed = 21

[[effects]]
name = "gain_offset"          # driven by the trigger only
offset_dn = 40

[[effects]]
name = "gaussian_noise"       # always on: the replay must reproduce the noise too
sigma_dn = 3.0
enabled = true

[[events]]
name = "glare"
effect = "gain_offset"
trigger = "flash"
duration_s = 0.2              # 5 frames at 25 fps
"#;

fn source() -> String {
    format!("synth:?width=64&height=48&fps=25&frames={FRAMES}")
}

fn faultcam_run(campaign: &Path, out: &Path, extra: &[&str]) -> Command {
    let mut c = Command::new(FAULTCAM);
    c.args(["run", "--source", &source(), "--sink"])
        .arg(format!("files:{}", out.display()))
        .arg("--faults")
        .arg(campaign)
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    c
}

fn log_of(out: &Path) -> Vec<Value> {
    std::fs::read_to_string(out.join("groundtruth.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The rig's end of the link: writes commands, reads reply lines.
struct Rig {
    port: TTYPort,
    buf: Vec<u8>,
    replies: Vec<String>,
}

impl Rig {
    fn send(&mut self, bytes: &[u8]) {
        self.port.write_all(bytes).unwrap();
        self.port.flush().unwrap();
    }

    /// Read replies until one satisfies `want`, or the process `child` ends, or 15 s pass
    /// (a guard against hanging, not a timing assertion).
    fn wait_for(&mut self, child: &mut Child, want: impl Fn(&str) -> bool) -> Option<String> {
        let t0 = Instant::now();
        loop {
            if let Some(r) = self.replies.iter().find(|r| want(r)) {
                return Some(r.clone());
            }
            if t0.elapsed() > Duration::from_secs(15) || child.try_wait().unwrap().is_some() {
                self.read_some();
                return self.replies.iter().find(|r| want(r)).cloned();
            }
            self.read_some();
        }
    }

    fn read_some(&mut self) {
        let mut b = [0u8; 256];
        match self.port.read(&mut b) {
            Ok(n) => self.buf.extend_from_slice(&b[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => panic!("rig read: {e}"),
        }
        while let Some(i) = self.buf.iter().position(|&c| c == b'\n') {
            let line: Vec<u8> = self.buf.drain(..=i).collect();
            self.replies.push(String::from_utf8_lossy(&line).trim_end().to_string());
        }
    }
}

/// `ACK <cmd> frame=<f> t_ns=<t>` → (f, t).
fn ack_frame(reply: &str) -> (u64, u64) {
    let mut f = None;
    let mut t = None;
    for w in reply.split_whitespace() {
        if let Some(v) = w.strip_prefix("frame=") {
            f = v.parse().ok();
        }
        if let Some(v) = w.strip_prefix("t_ns=") {
            t = v.parse().ok();
        }
    }
    (f.unwrap(), t.unwrap())
}

fn effects_of(frame: &Value) -> Vec<&str> {
    frame["effects"].as_array().unwrap().iter().map(|e| e["name"].as_str().unwrap()).collect()
}

#[test]
fn rig_triggers_over_a_pty_while_frames_flow_and_the_log_replays_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = dir.path().join("campaign.toml");
    std::fs::write(&campaign, CAMPAIGN).unwrap();
    let (mut master, slave) = TTYPort::pair().unwrap();
    master.set_timeout(Duration::from_millis(50)).unwrap();
    // The test keeps the slave end open (never reads it) so the link stays up; faultcam opens
    // the same device by its path.
    let tty = slave.name().unwrap();

    // --- Live run at 25 fps with the rig on the pty.
    let live = dir.path().join("live");
    let mut child =
        faultcam_run(&campaign, &live, &["--fps", "25", "--trigger", &format!("{tty}?baud=115200")]).spawn().unwrap();
    let mut rig = Rig { port: master, buf: Vec::new(), replies: Vec::new() };
    // Handshake: PING until acknowledged (the stream is running once PING is applied to a frame).
    let t0 = Instant::now();
    let ping = loop {
        rig.send(b"1 PING\n");
        if let Some(r) = rig.wait_for(&mut child, |r| r.starts_with("ACK 1 ")) {
            break r;
        }
        assert!(t0.elapsed() < Duration::from_secs(30) && child.try_wait().unwrap().is_none(), "no ACK to PING");
    };
    let (ping_frame, ping_t) = ack_frame(&ping);
    assert_eq!(ping_t, ping_frame * FRAME_NS, "ack carries the frame's stream time");

    rig.send(b"2 START flash\r\n");
    let start = rig.wait_for(&mut child, |r| r.starts_with("ACK 2 ")).expect("START acknowledged");
    let (s, s_t) = ack_frame(&start);
    assert!(s > ping_frame && s + 5 < FRAMES, "START took effect mid-stream at frame {s}");
    assert_eq!(s_t, s * FRAME_NS);

    // Garbage, unknown commands, out-of-range values, invalid UTF-8 and a partial line: each
    // gets a NAK with a reason; the stream goes on.
    rig.send(b"hello\n");
    rig.send(b"3 FIRE flash\n");
    rig.send(b"4 SET gain_offset.offset_dn 300\n");
    rig.send(b"5 START fl\xffash\n");
    rig.send(b"6 STA");
    let nak_garbage = rig.wait_for(&mut child, |r| r.starts_with("NAK - expected")).expect("NAK for garbage");
    assert!(nak_garbage.contains("sequence number"), "{nak_garbage}");
    let nak3 = rig.wait_for(&mut child, |r| r.starts_with("NAK 3 ")).expect("NAK 3");
    assert!(nak3.contains("unknown command 'FIRE'") && nak3.contains("START, STOP"), "{nak3}");
    let nak4 = rig.wait_for(&mut child, |r| r.starts_with("NAK 4 ")).expect("NAK 4");
    assert!(nak4.contains("out of range") && nak4.contains("-255..=255"), "{nak4}");
    let nak5 = rig.wait_for(&mut child, |r| r.starts_with("NAK 5 ")).expect("NAK 5");
    assert!(nak5.contains("invalid UTF-8 at byte 10"), "{nak5}");
    let partial = rig.wait_for(&mut child, |r| r.contains("partial line")).expect("NAK for the partial line");
    assert!(partial.starts_with("NAK - partial line: no terminator within 500 ms"), "{partial}");
    // Still streaming: a MARK after all that is applied to a later frame.
    rig.send(b"7 MARK after the garbage\n");
    let mark = rig.wait_for(&mut child, |r| r.starts_with("ACK 7 ")).expect("MARK acknowledged");
    let (m, _) = ack_frame(&mark);
    assert!(m >= s, "{mark}");
    let status = child.wait().unwrap();
    let mut err = String::new();
    child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
    assert!(status.success(), "{err}");
    drop(slave);

    // The log: every frame delivered, the fault on exactly the 5 frames from the ACKed one.
    let log = log_of(&live);
    let frames: Vec<&Value> = log.iter().filter(|r| r["record"] == "frame").collect();
    assert_eq!(frames.len() as u64, FRAMES, "{err}");
    let faulted: Vec<u64> =
        frames.iter().filter(|f| effects_of(f).contains(&"gain_offset")).map(|f| f["seq"].as_u64().unwrap()).collect();
    assert_eq!(faulted, (s..s + 5).collect::<Vec<u64>>(), "{err}");
    assert!(frames.iter().all(|f| f["status"] == "delivered" && effects_of(f).contains(&"gaussian_noise")));
    let events: Vec<&Value> = log.iter().filter(|r| r["record"] == "event").collect();
    let find = |kind: &str, cmd_seq: u64| {
        events
            .iter()
            .find(|e| e["event"] == kind && e["cmd_seq"] == cmd_seq)
            .copied()
            .unwrap_or_else(|| panic!("no {kind} event for command {cmd_seq}"))
    };
    let trig = find("trigger", 2);
    assert_eq!((trig["seq"].as_u64(), trig["command"].as_str()), (Some(s), Some("START flash")));
    assert_eq!(find("ack", 2)["reply"], start.as_str());
    assert_eq!(find("ack", 2)["t_ns"], s * FRAME_NS);
    for c in [3, 4, 5] {
        assert!(find("nak", c)["reason"].is_string());
    }
    assert!(events.iter().any(|e| e["event"] == "nak" && e["raw"] == "hello"));
    assert!(events.iter().any(|e| e["event"] == "event_start" && e["seq"] == s && e["cause"] == "trigger"));
    assert!(events.iter().any(|e| e["event"] == "event_stop" && e["seq"] == s + 5 && e["reason"] == "duration"));
    assert_eq!(find("mark", 7)["label"], "after the garbage");
    let summary = log.iter().find(|r| r["record"] == "summary").unwrap();
    assert_eq!((summary["frames_in"].as_u64(), summary["unaccounted"].as_i64()), (Some(FRAMES), Some(0)));

    // --- Replay: the same campaign, seed and input with the recorded triggers, unpaced (as fast
    // as possible) and on one effect thread: the same bytes, frame for frame.
    let replay = dir.path().join("replay");
    let live_log = live.join("groundtruth.jsonl");
    let live_log_copy: PathBuf = dir.path().join("live.jsonl");
    std::fs::copy(&live_log, &live_log_copy).unwrap();
    let out = faultcam_run(&campaign, &replay, &["--replay-triggers"])
        .arg(&live_log_copy)
        .args(["--threads", "1"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (a, b) = (pngs(&live), pngs(&replay));
    assert_eq!(a.len() as u64, FRAMES);
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (name, bytes) in &a {
        assert!(bytes == &b[name], "{name} differs between the live run and its replay");
    }
    let rlog = log_of(&replay);
    assert!(rlog.iter().any(|e| e["event"] == "trigger" && e["seq"] == s && e["replayed"] == true));

    // --- Without the trigger the fault is absent: exactly the 5 triggered frames differ.
    let plain = dir.path().join("plain");
    let out = faultcam_run(&campaign, &plain, &[]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let c = pngs(&plain);
    let differ: Vec<u64> = a
        .iter()
        .filter(|(name, bytes)| c[*name] != **bytes)
        .map(|(name, _)| name.trim_start_matches("frame_").trim_end_matches(".png").parse().unwrap())
        .collect();
    assert_eq!(differ, (s..s + 5).collect::<Vec<u64>>());
}

#[test]
fn trigger_options_are_checked_before_the_stream_starts() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = dir.path().join("campaign.toml");
    std::fs::write(&campaign, CAMPAIGN).unwrap();
    let out = dir.path().join("out");
    let run = |extra: &[&str]| {
        let o = faultcam_run(&campaign, &out, extra).output().unwrap();
        assert_eq!(o.status.code(), Some(2));
        String::from_utf8(o.stderr).unwrap()
    };
    let e = run(&["--trigger", "/dev/faultcam-no-such-tty"]);
    assert!(e.contains("/dev/faultcam-no-such-tty") && e.contains("cannot open"), "{e}");
    let e = run(&["--trigger", "/dev/ttyS0?baud=7"]);
    assert!(e.contains("baud=7") && e.contains("50..=4000000"), "{e}");
    // A log from another campaign does not fit: named with its line.
    let other = dir.path().join("other.jsonl");
    std::fs::write(&other, "{\"record\":\"event\",\"event\":\"trigger\",\"seq\":3,\"command\":\"START storm\"}\n")
        .unwrap();
    let e = run(&["--replay-triggers", other.to_str().unwrap()]);
    assert!(e.contains("other.jsonl:1") && e.contains("unknown event or trigger 'storm'"), "{e}");
    assert!(!out.join("groundtruth.jsonl").exists(), "nothing ran");
}
