//! `faultcam run` end to end through the real binary: GStreamer videotestsrc → faultcam → a
//! GStreamer appsrc/filesink pipeline, the Aravis fake camera → faultcam → files, timed replay
//! of folders, the overrun policy, SIGINT, and every example campaign. Frame counts, order,
//! content (against the chain applied in-process) and the ground-truth log are checked.

#[path = "support/files.rs"]
mod files;
#[path = "support/logs.rs"]
mod logs;
use faultcam::faults::chain::{Chain, FrameReport};
use faultcam::{FaultConfig, Outcome};
use files::png_folder;
use logs::{frames, records, run_ok as ok};
use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};

const FAULTCAM: &str = env!("CARGO_BIN_EXE_faultcam");

const NOISE: &str = "seed = 5\n\n[[effects]]\nname = \"gaussian_noise\"\nsigma_dn = 5.0\n\n\
                     [[effects]]\nname = \"gain_offset\"\ngain = 1.1\noffset_dn = 3\n";

fn faultcam() -> Command {
    let mut c = Command::new(FAULTCAM);
    c.arg("run");
    c
}

fn summary(recs: &[Value]) -> &Value {
    recs.iter().find(|r| r["record"] == "summary").expect("a summary record")
}

fn write_cfg(dir: &Path, text: &str) -> std::path::PathBuf {
    let p = dir.join("faults.toml");
    std::fs::write(&p, text).unwrap();
    p
}

#[cfg(feature = "gst")]
#[test]
fn videotestsrc_through_faultcam_into_an_appsrc_filesink_pipeline() {
    use faultcam::source::Source;
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_cfg(dir.path(), NOISE);
    // 102 px GRAY8 rows are padded to 104 bytes on both sides of faultcam.
    let (w, h, n) = (102usize, 75usize, 24usize);
    let src = format!(
        "gst:videotestsrc num-buffers={n} pattern=ball ! video/x-raw,format=GRAY8,width={w},height={h},framerate=30/1 \
         ! appsink sync=false"
    );
    let raw = dir.path().join("out.raw");
    let log = dir.path().join("gt.jsonl");
    let err = ok(faultcam()
        .args(["--source", &src, "--sink"])
        .arg(format!("gst:appsrc ! queue ! filesink location={}", raw.display()))
        .arg("--faults")
        .arg(&cfg)
        .arg("--log")
        .arg(&log));
    assert!(err.contains("negotiated video/x-raw") && err.contains("GRAY8"), "caps are reported: {err}");

    // Reference: the same pipeline read in-process through the same chain.
    let fcfg = FaultConfig::load(&cfg).unwrap();
    let mut chain = Chain::from_config(&fcfg).unwrap();
    let mut reference = faultcam::source::gst::GstSource::open(&src).unwrap();
    let mut report = FrameReport::default();
    let bytes = std::fs::read(&raw).unwrap();
    let stride = w.div_ceil(4) * 4;
    assert_eq!(bytes.len(), n * stride * h, "{n} frames of {stride}x{h} bytes");
    for (i, out) in bytes.chunks_exact(stride * h).enumerate() {
        let mut want = reference.next_frame().unwrap().unwrap();
        assert_eq!(chain.apply(&mut want, &mut report).unwrap(), Outcome::Keep);
        let want = want.as_u8().unwrap();
        for y in 0..h {
            assert!(out[y * stride..y * stride + w] == want[y * w..(y + 1) * w], "frame {i} row {y} differs");
        }
    }
    assert!(reference.next_frame().unwrap().is_none());
    let recs = records(&log);
    let f = frames(&recs);
    assert_eq!(f.len(), n);
    for (i, r) in f.iter().enumerate() {
        assert_eq!((r["seq"].as_u64(), r["status"].as_str()), (Some(i as u64), Some("delivered")));
        let pts = r["pts_ns"].as_u64().unwrap() as f64;
        assert!((pts - i as f64 * 1e9 / 30.0).abs() <= 1.0, "GStreamer timestamps: {pts}");
        assert!(r["timing"]["latency_ms"].as_f64().unwrap() >= 0.0);
    }
    let s = summary(&recs);
    assert_eq!(
        (s["frames_in"].as_u64(), s["delivered"].as_u64(), s["unaccounted"].as_i64()),
        (Some(24), Some(24), Some(0))
    );
    assert_eq!(s["stopped_by"], "end_of_stream");
}

#[cfg(feature = "gst")]
#[test]
fn gst_errors_are_clear_and_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_cfg(dir.path(), NOISE);
    let run = |src: &str, sink: &str| {
        let o = faultcam().args(["--source", src, "--sink", sink, "--faults"]).arg(&cfg).output().unwrap();
        assert_eq!(o.status.code(), Some(2));
        String::from_utf8(o.stderr).unwrap()
    };
    let e = run("gst:videotestsrc num-buffers=2 ! fakesink", "null:");
    assert!(e.contains("must end in an appsink"), "{e}");
    let e = run("synth:?frames=2", "gst:videotestsrc ! fakesink");
    assert!(e.contains("must start with an appsrc"), "{e}");
    let e = run("gst:nosuchelement ! appsink", "null:");
    assert!(e.contains("nosuchelement"), "{e}");
    // A bus error in the middle of the stream ends it with the element named; what was read is logged.
    let log = dir.path().join("gt.jsonl");
    let o = faultcam()
        .args(["--source", "synth:?width=32&height=16&frames=5", "--sink"])
        .arg(format!("gst:appsrc ! filesink location={}/no/such/dir/x.raw", dir.path().display()))
        .arg("--faults")
        .arg(&cfg)
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    let e = String::from_utf8(o.stderr).unwrap();
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("filesink") && e.contains("no/such/dir"), "{e}");
}

#[cfg(feature = "aravis")]
#[test]
fn fake_camera_through_faultcam_into_files() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_cfg(dir.path(), "[[effects]]\nname = \"gain_offset\"\noffset_dn = 3\n");
    let out = dir.path().join("out");
    let err = ok(faultcam()
        .args(["--source", "aravis:Fake_1?width=48&height=32&fps=100", "--frames", "10", "--sink"])
        .arg(format!("files:{}", out.display()))
        .arg("--faults")
        .arg(&cfg));
    assert!(err.contains("48x32") && err.contains("Mono8"), "what the camera chose is reported: {err}");
    let recs = records(&out.join("groundtruth.jsonl"));
    let f = frames(&recs);
    assert_eq!(f.len(), 10);
    let mut last_seq = None;
    for r in &f {
        assert_eq!(r["status"], "delivered");
        let seq = r["seq"].as_u64().unwrap();
        assert!(last_seq.is_none_or(|l| seq > l), "camera order kept");
        last_seq = Some(seq);
        // The fake camera's ramp (x + y + id) mod 255, plus 3 DN.
        let img = image::open(out.join(format!("frame_{seq:06}.png"))).unwrap().to_luma8();
        assert_eq!(img.dimensions(), (48, 32));
        let c = img.get_pixel(0, 0)[0] as u32 - 3;
        for (x, y, p) in img.enumerate_pixels() {
            assert_eq!(p[0] as u32, ((x + y + c) % 255 + 3).min(255), "({x},{y}) of frame {seq}");
        }
    }
    // Frames the camera lost (if any) are skip records, never silent.
    let s = summary(&recs);
    assert_eq!((s["frames_in"].as_u64(), s["unaccounted"].as_i64()), (Some(10), Some(0)));
    assert_eq!(s["skipped"].as_u64().unwrap() as usize, recs.iter().filter(|r| r["record"] == "skip").count());
}

#[test]
fn folders_replay_at_fps_or_at_their_timestamps_and_loop() {
    let inp = png_folder(3);
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_cfg(dir.path(), NOISE);
    let log = dir.path().join("gt.jsonl");
    // --fps 50: frame k is captured (released) at k·20 ms; the folder loops.
    ok(faultcam()
        .args(["--source", &format!("files:{}?loop=true", inp.path().display())])
        .args(["--sink", "null:", "--fps", "50", "--frames", "7", "--log"])
        .arg(&log)
        .arg("--faults")
        .arg(&cfg));
    let recs = records(&log);
    let f = frames(&recs);
    let names: Vec<&str> = f.iter().map(|r| r["input"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        ["img_000.png", "img_001.png", "img_002.png", "img_000.png", "img_001.png", "img_002.png", "img_000.png"]
    );
    let cap: Vec<u64> = f.iter().map(|r| r["timing"]["capture_ns"].as_u64().unwrap()).collect();
    for (k, c) in cap.iter().enumerate() {
        assert_eq!(c - cap[0], k as u64 * 20_000_000, "release schedule");
    }
    assert_eq!(summary(&recs)["stopped_by"], "frame_limit");
    // --realtime with recorded timestamps: releases follow the recorded intervals.
    let ts = dir.path().join("ts.txt");
    std::fs::write(&ts, "img_000.png 1000000000\nimg_001.png 1010000000\nimg_002.png 1050000000\n").unwrap();
    ok(faultcam()
        .args(["--source", &format!("files:{}?timestamps={}", inp.path().display(), ts.display())])
        .args(["--sink", "null:", "--realtime", "--log"])
        .arg(&log)
        .arg("--faults")
        .arg(&cfg));
    let recs = records(&log);
    let cap: Vec<u64> = frames(&recs).iter().map(|r| r["timing"]["capture_ns"].as_u64().unwrap()).collect();
    assert_eq!(cap.iter().map(|c| c - cap[0]).collect::<Vec<_>>(), [0, 10_000_000, 50_000_000]);
}

#[test]
fn overrun_drop_through_the_binary_accounts_for_every_frame() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_cfg(dir.path(), "[[effects]]\nname = \"defocus\"\nsigma_px = 2.0\n");
    let log = dir.path().join("gt.jsonl");
    // A 1 µs budget cannot be met at 200 fps: frames are dropped, each with a record.
    let err = ok(faultcam()
        .args(["--source", "synth:?width=96&height=64&frames=40", "--sink", "null:", "--fps", "200"])
        .args(["--budget-ms", "0.001", "--overrun", "drop", "--log"])
        .arg(&log)
        .arg("--faults")
        .arg(&cfg));
    let recs = records(&log);
    let s = summary(&recs);
    let dropped = s["dropped_overrun"].as_u64().unwrap();
    assert!(dropped > 0, "{err}");
    assert_eq!(s["delivered"].as_u64().unwrap() + dropped, 40);
    assert_eq!(frames(&recs).iter().filter(|r| r["status"] == "dropped_overrun").count() as u64, dropped);
    assert_eq!(s["unaccounted"], 0);
    // The printed summary line: counts, why frames were dropped, latency quantiles, misses.
    let line = err.lines().find(|l| l.starts_with("faultcam: 40 frames in")).unwrap_or_else(|| panic!("{err}"));
    for part in ["out", &format!("{dropped} by overrun"), "inputs skipped", "p50", "p99", "max", "misses"] {
        assert!(line.contains(part), "'{part}' missing: {line}");
    }
    // Bad options name the option and the accepted values.
    let o = faultcam()
        .args(["--source", "synth:?frames=1", "--sink", "null:", "--overrun", "late", "--faults"])
        .arg(&cfg)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("pass, degrade or drop"));
    let o = faultcam()
        .args(["--source", "synth:?frames=1", "--sink", "null:", "--budget-ms=-3", "--faults"])
        .arg(&cfg)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("budget_ms"));
}

#[test]
fn sigint_stops_an_endless_stream_and_the_summary_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_cfg(dir.path(), NOISE);
    let log = dir.path().join("gt.jsonl");
    let mut child = faultcam()
        .args(["--source", "synth:?width=64&height=48&frames=0", "--sink", "null:", "--fps", "100", "--log"])
        .arg(&log)
        .arg("--faults")
        .arg(&cfg)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The handlers are installed before the source and sink are reported.
    let mut err = BufReader::new(child.stderr.take().unwrap());
    let mut line = String::new();
    while !line.starts_with("faultcam: sink") {
        line.clear();
        assert!(err.read_line(&mut line).unwrap() > 0, "faultcam ended early");
    }
    std::thread::sleep(std::time::Duration::from_millis(300));
    let st = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(st.success());
    let status = child.wait().unwrap();
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut err, &mut rest).unwrap();
    assert!(status.success(), "{rest}");
    assert!(rest.contains("stopped by signal"), "{rest}");
    let recs = records(&log);
    let s = summary(&recs);
    assert_eq!(s["stopped_by"], "signal");
    let n = s["frames_in"].as_u64().unwrap();
    assert!(n > 0);
    assert_eq!(frames(&recs).len() as u64, n, "every frame read has its record");
    assert_eq!(s["unaccounted"], 0);
}

#[test]
fn every_example_campaign_runs() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    for e in std::fs::read_dir(root.join("hil/campaigns")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_none_or(|x| x != "toml") {
            continue;
        }
        let log = dir.path().join("gt.jsonl");
        let err = ok(faultcam()
            .args(["--source", "synth:?width=64&height=48&frames=12&format=rgb8", "--sink", "null:", "--log"])
            .arg(&log)
            .arg("--faults")
            .arg(&p));
        let recs = records(&log);
        assert_eq!(summary(&recs)["delivered"], 12, "{}: {err}", p.display());
        let o = Command::new(FAULTCAM).args(["run", "--check", "--faults"]).arg(&p).output().unwrap();
        assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains(": ok:"), "{}", p.display());
    }
}

/// `--masks` on a stream: every delivered frame gets a 16-bit label PNG named in its record,
/// and the labels are exact: `gain_offset` with offset 3 DN changes every pixel
/// that is not already at full scale; `hot_pixels` (sensor stage, so applied first) change only a
/// fixed, small set of pixels.
#[test]
fn masks_are_written_for_every_delivered_frame_and_are_exact() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_cfg(
        dir.path(),
        "seed = 9\n[[effects]]\nname = \"gain_offset\"\noffset_dn = 3\n\n[[effects]]\nname = \"hot_pixels\"\nrate = 0.001\n",
    );
    let (clean_dir, out_dir, masks) = (dir.path().join("clean"), dir.path().join("out"), dir.path().join("masks"));
    let src = "synth:?width=96&height=64&frames=4&seed=3";
    let none = write_cfg_named(dir.path(), "none.toml", "seed = 0\n");
    ok(faultcam()
        .args(["--source", src, "--sink"])
        .arg(format!("files:{}", clean_dir.display()))
        .arg("--faults")
        .arg(&none));
    let log = dir.path().join("gt.jsonl");
    ok(faultcam()
        .args(["--source", src, "--sink"])
        .arg(format!("files:{}", out_dir.display()))
        .arg("--faults")
        .arg(&cfg)
        .arg("--log")
        .arg(&log)
        .arg("--masks")
        .arg(&masks));
    let recs = records(&log);
    let fr = frames(&recs);
    assert_eq!(fr.len(), 4);
    let mut hot_sets = Vec::new();
    for r in fr {
        let m = &r["masks"];
        assert_eq!(m["bits"], serde_json::json!(["hot_pixels", "gain_offset"]), "bits in application order");
        let bits: Vec<&str> = m["bits"].as_array().unwrap().iter().map(|b| b.as_str().unwrap()).collect();
        let (kg, kh) = (
            bits.iter().position(|b| *b == "gain_offset").unwrap(),
            bits.iter().position(|b| *b == "hot_pixels").unwrap(),
        );
        let labels = image::open(m["labels"].as_str().unwrap()).unwrap().to_luma16();
        let seq = r["seq"].as_u64().unwrap();
        let clean = image::open(clean_dir.join(format!("frame_{seq:06}.png"))).unwrap().to_luma8();
        let out = image::open(out_dir.join(format!("frame_{seq:06}.png"))).unwrap().to_luma8();
        let mut hot = Vec::new();
        for (x, y, l) in labels.enumerate_pixels() {
            let l = l.0[0];
            let (c, o) = (clean.get_pixel(x, y).0[0], out.get_pixel(x, y).0[0]);
            assert_eq!(l == 0, c == o, "({x},{y}): label {l:#b}, clean {c}, out {o}: unchanged pixels have label 0");
            if l & (1 << kh) != 0 {
                hot.push((x, y));
            }
            // Hot pixels come first (sensor), gain_offset after (readout).
            let after_hot = if l & (1 << kh) != 0 { None } else { Some(c) };
            if let Some(v) = after_hot {
                assert_eq!(l & (1 << kg) != 0, v < 255, "({x},{y}) value {v}: gain_offset bit");
            }
        }
        assert!(!hot.is_empty() && hot.len() < 64 * 96 / 100, "a few hot pixels: {}", hot.len());
        assert_eq!(m["changed_px"][kh].as_u64().unwrap(), hot.len() as u64);
        hot_sets.push(hot);
    }
    // Hot pixels are a fixed pattern: the same pixels on every frame.
    assert!(hot_sets.windows(2).all(|w| w[0] == w[1]));
}

fn write_cfg_named(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn masks_section_of_the_config_enables_masks_next_to_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_cfg(
        dir.path(),
        "seed = 2\n[[effects]]\nname = \"hot_pixels\"\nrate = 0.002\n\n[masks]\ndeltas = true\ndir = \"m\"\n",
    );
    let log = dir.path().join("run").join("gt.jsonl");
    std::fs::create_dir_all(log.parent().unwrap()).unwrap();
    ok(faultcam()
        .args(["--source", "synth:?width=64&height=48&frames=3&seed=1", "--sink", "null:", "--faults"])
        .arg(&cfg)
        .arg("--log")
        .arg(&log));
    let recs = records(&log);
    let fr = frames(&recs);
    assert_eq!(fr.len(), 3);
    for r in fr {
        let labels = Path::new(r["masks"]["labels"].as_str().unwrap()).to_path_buf();
        assert!(labels.starts_with(dir.path().join("run").join("m")), "{}", labels.display());
        assert!(labels.exists());
        let d = r["masks"]["deltas"].as_array().unwrap();
        assert_eq!(d.len(), 1, "hot_pixels delta image");
        assert!(Path::new(d[0]["path"].as_str().unwrap()).exists());
    }
    // A bad key in [masks] is an error naming it, at --check and at run time.
    let bad = write_cfg_named(dir.path(), "bad.toml", "[masks]\ndelta = true\n");
    let out = faultcam().args(["--check", "--faults"]).arg(&bad).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("[masks].delta") && err.contains("accepted: enabled, deltas, dir"), "{err}");
}
