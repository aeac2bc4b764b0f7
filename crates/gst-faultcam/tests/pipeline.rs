//! The `faultcam` element in real pipelines: `videotestsrc ! faultcam ! appsink` compared byte
//! for byte with `faultcam apply` on the same frames, the campaign timeline on frame indices,
//! the per-buffer messages, the ground-truth log and masks, dropped frames, and the plugin
//! loaded from its shared library by `gst-launch-1.0` / `gst-inspect-1.0` (GST_PLUGIN_PATH).

use gst::prelude::*;
use gst_video::prelude::*;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Once;

fn init() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        gst::init().unwrap();
        gstfaultcam::register(None).unwrap();
    });
}

/// target/debug (or the profile's folder): the test runs from target/<profile>/deps.
fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    exe.parent().and_then(Path::parent).unwrap().to_path_buf()
}

/// The `faultcam` CLI of the same build (built by `cargo test` at the root; else built here).
fn faultcam_bin() -> PathBuf {
    let bin = profile_dir().join("faultcam");
    if !bin.exists() {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../Cargo.toml");
        let st = Command::new(cargo)
            .args(["build", "--bin", "faultcam", "--manifest-path"])
            .arg(&manifest)
            .status()
            .expect("run cargo build --bin faultcam");
        assert!(st.success(), "cargo build --bin faultcam failed");
    }
    assert!(bin.exists(), "{} missing", bin.display());
    bin
}

#[derive(Debug)]
struct Run {
    /// Packed samples of every buffer that reached the appsink (padding removed).
    frames: Vec<Vec<u8>>,
    pts: Vec<Option<u64>>,
    /// `faultcam-frame` messages in bus order.
    messages: Vec<gst::Structure>,
}

impl Run {
    /// Keep a sample's samples packed (row padding removed) and its PTS.
    fn push(&mut self, sample: &gst::Sample) {
        let info = gst_video::VideoInfo::from_caps(sample.caps().unwrap()).unwrap();
        let buf = sample.buffer().unwrap();
        let vf = gst_video::VideoFrameRef::from_buffer_ref_readable(buf, &info).unwrap();
        let row = info.width() as usize * info.format_info().pixel_stride()[0] as usize;
        let stride = vf.plane_stride()[0] as usize;
        let data = vf.plane_data(0).unwrap();
        let mut packed = Vec::new();
        for y in 0..info.height() as usize {
            packed.extend_from_slice(&data[y * stride..y * stride + row]);
        }
        self.frames.push(packed);
        self.pts.push(buf.pts().map(|p| p.nseconds()));
    }
}

/// Run `desc` (which ends in `appsink name=out`) to EOS.
fn run(desc: &str) -> Result<Run, String> {
    init();
    let pipeline = gst::parse::launch(desc).map_err(|e| e.to_string())?.downcast::<gst::Pipeline>().unwrap();
    let sink = pipeline.by_name("out").unwrap().downcast::<gst_app::AppSink>().unwrap();
    sink.set_property("sync", false);
    let bus = pipeline.bus().unwrap();
    if let Err(e) = pipeline.set_state(gst::State::Playing) {
        let why = bus.pop_filtered(&[gst::MessageType::Error]).and_then(|m| match m.view() {
            gst::MessageView::Error(e) => Some(format!("{} ({:?})", e.error(), e.debug())),
            _ => None,
        });
        pipeline.set_state(gst::State::Null).unwrap();
        return Err(format!("cannot start: {e}: {}", why.unwrap_or_default()));
    }
    let mut out = Run { frames: Vec::new(), pts: Vec::new(), messages: Vec::new() };
    let mut error = None;
    loop {
        if let Some(sample) = sink.try_pull_sample(gst::ClockTime::from_mseconds(50)) {
            out.push(&sample);
        }
        let mut eos = false;
        while let Some(msg) = bus.pop() {
            match msg.view() {
                gst::MessageView::Element(e) => {
                    if let Some(s) = e.structure().filter(|s| s.name() == gstfaultcam::MESSAGE_NAME) {
                        out.messages.push(s.to_owned());
                    }
                }
                gst::MessageView::Eos(_) => eos = true,
                gst::MessageView::Error(e) => {
                    error = Some(format!("{} ({:?})", e.error(), e.debug()));
                    eos = true;
                }
                _ => {}
            }
        }
        if eos {
            break;
        }
    }
    // Samples still queued in the appsink after EOS.
    while let Some(sample) = sink.try_pull_sample(gst::ClockTime::ZERO) {
        out.push(&sample);
    }
    pipeline.set_state(gst::State::Null).unwrap();
    match error {
        Some(e) => Err(e),
        None => Ok(out),
    }
}

/// PGM/PPM (P5/P6) writer and reader for the `faultcam apply` round trip (16-bit big-endian).
fn write_pnm(path: &Path, w: usize, h: usize, format: &str, packed: &[u8]) {
    let (magic, max) = match format {
        "RGB" => ("P6", 255),
        "GRAY16_LE" => ("P5", 65535),
        _ => ("P5", 255),
    };
    let mut bytes = format!("{magic}\n{w} {h}\n{max}\n").into_bytes();
    if format == "GRAY16_LE" {
        bytes.extend(packed.chunks_exact(2).flat_map(|c| [c[1], c[0]]));
    } else {
        bytes.extend_from_slice(packed);
    }
    std::fs::write(path, bytes).unwrap();
}

fn read_pnm(path: &Path, format: &str) -> Vec<u8> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    // Three header tokens after the magic, then one whitespace byte.
    let mut fields = 0;
    let mut i = 2;
    while fields < 3 {
        while bytes[i].is_ascii_whitespace() {
            i += 1;
        }
        while !bytes[i].is_ascii_whitespace() {
            i += 1;
        }
        fields += 1;
    }
    let body = &bytes[i + 1..];
    if format == "GRAY16_LE" { body.chunks_exact(2).flat_map(|c| [c[1], c[0]]).collect() } else { body.to_vec() }
}

const W: usize = 96;
const H: usize = 64;
const N: usize = 6;

/// Effects of every stage that work on grey and RGB, 8 and 16 bit; the config's seed (3) is
/// overridden by the `seed` property / `--seed` (11).
const CONFIG: &str = r#"
seed = 3

[[effects]]
name = "vignetting"
strength = 0.4

[[effects]]
name = "defocus"
sigma_px = 1.3

[[effects]]
name = "shot_noise"
gain_e_per_dn = 2.0

[[effects]]
name = "hot_pixels"
rate = 0.002

[[effects]]
name = "gaussian_noise"
sigma_dn = 3.0

[[effects]]
name = "row_noise"
sigma_dn = 1.5

[[effects]]
name = "gain_offset"
gain = 1.1
offset_dn = 4.0

[[effects]]
name = "bit_flip"
rate = 0.0005
"#;

fn caps(format: &str) -> String {
    format!("video/x-raw,format={format},width={W},height={H},framerate=30/1")
}

#[test]
fn same_bytes_as_faultcam_apply_for_gray8_gray16_and_rgb() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("faults.toml");
    std::fs::write(&cfg, CONFIG).unwrap();
    let bin = faultcam_bin();
    for format in ["GRAY8", "GRAY16_LE", "RGB"] {
        let src = format!("videotestsrc pattern=ball num-buffers={N} ! {}", caps(format));
        let input = run(&format!("{src} ! appsink name=out")).unwrap();
        assert_eq!(input.frames.len(), N, "{format}: input frames");
        let out = run(&format!("{src} ! faultcam config={} seed=11 ! appsink name=out", cfg.display())).unwrap();
        assert_eq!(out.frames.len(), N, "{format}: every frame delivered");

        let in_dir = dir.path().join(format!("in-{format}"));
        let out_dir = dir.path().join(format!("out-{format}"));
        std::fs::create_dir_all(&in_dir).unwrap();
        for (i, f) in input.frames.iter().enumerate() {
            write_pnm(&in_dir.join(format!("f{i:03}.pnm")), W, H, format, f);
        }
        let st = Command::new(&bin)
            .args(["apply", "--in"])
            .arg(&in_dir)
            .arg("--out")
            .arg(&out_dir)
            .arg("--faults")
            .arg(&cfg)
            .args(["--seed", "11", "--format", "pgm", "--threads", "1"])
            .output()
            .unwrap();
        assert!(st.status.success(), "faultcam apply: {}", String::from_utf8_lossy(&st.stderr));
        let ext = if format == "RGB" { "ppm" } else { "pgm" };
        for i in 0..N {
            let want = read_pnm(&out_dir.join(format!("f{i:03}.{ext}")), format);
            assert_eq!(want.len(), out.frames[i].len(), "{format} frame {i}: size");
            let diff = want.iter().zip(&out.frames[i]).filter(|(a, b)| a != b).count();
            assert_eq!(diff, 0, "{format} frame {i}: {diff} bytes differ from faultcam apply");
            // The faults did something (a chain that changed nothing would also compare equal).
            let changed = input.frames[i].iter().zip(&out.frames[i]).filter(|(a, b)| a != b).count();
            assert!(changed > want.len() / 4, "{format} frame {i}: only {changed} bytes changed");
        }
        // One message per buffer, in order, naming the effects in physical order.
        assert_eq!(out.messages.len(), N);
        for (i, m) in out.messages.iter().enumerate() {
            assert_eq!(m.get::<u64>("seq").unwrap(), i as u64);
            assert_eq!(m.get::<&str>("status").unwrap(), "delivered");
            assert_eq!(
                m.get::<&str>("effects").unwrap(),
                "vignetting,defocus,shot_noise,hot_pixels,gaussian_noise,row_noise,gain_offset,bit_flip"
            );
            let rec: serde_json::Value = serde_json::from_str(m.get::<&str>("record").unwrap()).unwrap();
            assert_eq!(rec["seq"], i as u64);
            assert_eq!(rec["effects"].as_array().unwrap().len(), 8);
        }
    }
}

#[test]
fn bgr_gives_the_rgb_bytes_with_channels_swapped() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("faults.toml");
    // channel_shift moves R and B differently: a BGR stream handled as RGB would fail this.
    std::fs::write(&cfg, format!("{CONFIG}\n[[effects]]\nname = \"channel_shift\"\ndx_r = 1.5\ndy_b = -1.0\n"))
        .unwrap();
    let swap = |f: &[u8]| f.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]).collect::<Vec<u8>>();
    let rgb_in =
        run(&format!("videotestsrc pattern=smpte num-buffers=3 ! {} ! appsink name=out", caps("RGB"))).unwrap();
    let bgr_in =
        run(&format!("videotestsrc pattern=smpte num-buffers=3 ! {} ! appsink name=out", caps("BGR"))).unwrap();
    assert_eq!(swap(&bgr_in.frames[0]), rgb_in.frames[0], "videotestsrc BGR is RGB swapped");
    let f = |fmt: &str| {
        run(&format!(
            "videotestsrc pattern=smpte num-buffers=3 ! {} ! faultcam config={} ! appsink name=out",
            caps(fmt),
            cfg.display()
        ))
        .unwrap()
    };
    let (rgb, bgr) = (f("RGB"), f("BGR"));
    assert_eq!(rgb.frames.len(), 3);
    for i in 0..3 {
        assert_ne!(rgb.frames[i], rgb_in.frames[i]);
        assert!(swap(&bgr.frames[i]) == rgb.frames[i], "frame {i}: BGR output is not the RGB output swapped");
    }
}

#[test]
fn timeline_by_frame_index_log_and_masks() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("campaign.toml");
    std::fs::write(
        &cfg,
        r#"
seed = 5

[[effects]]
name = "gaussian_noise"
sigma_dn = 2.0

[[effects]]
name = "gain_offset"

[[events]]
name = "dim"
effect = "gain_offset"
at_frame = 2
duration_frames = 3
[events.params]
gain = 0.5
"#,
    )
    .unwrap();
    let log = dir.path().join("gt.jsonl");
    let masks = dir.path().join("masks");
    let out = run(&format!(
        "videotestsrc pattern=white num-buffers=7 ! {} ! faultcam config={} log={} masks={} ! appsink name=out",
        caps("GRAY8"),
        cfg.display(),
        log.display(),
        masks.display()
    ))
    .unwrap();
    assert_eq!(out.frames.len(), 7);
    let mean = |f: &[u8]| f.iter().map(|&v| v as f64).sum::<f64>() / f.len() as f64;
    // videotestsrc's white in GRAY8 (235, video range) with noise, halved during the event.
    let white = mean(&out.frames[0]);
    assert!((white - 235.0).abs() < 2.0, "white {white}");
    for (i, m) in out.messages.iter().enumerate() {
        let active = (2..5).contains(&i);
        let effects = m.get::<&str>("effects").unwrap();
        assert_eq!(effects.contains("gain_offset"), active, "frame {i}: {effects}");
        let mu = mean(&out.frames[i]);
        let want = if active { white / 2.0 } else { white };
        assert!((mu - want).abs() < 1.0, "frame {i}: mean {mu}, expected {want}");
        assert!(masks.join(format!("frame_{i:06}.labels.png")).exists(), "frame {i}: mask");
    }
    let text = std::fs::read_to_string(&log).unwrap();
    let lines: Vec<serde_json::Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let frames: Vec<_> = lines.iter().filter(|l| l["record"] == "frame").collect();
    assert_eq!(frames.len(), 7);
    assert_eq!(frames[3]["effects"][1]["name"], "gain_offset");
    assert_eq!(frames[3]["effects"][1]["params"]["gain"], 0.5);
    assert!(frames[3]["masks"].is_object(), "{}", frames[3]);
    assert!(lines.iter().any(|l| l["record"] == "event" && l["event"] == "event_start"), "{text}");
    assert_eq!(lines.last().unwrap()["record"], "summary");
    assert_eq!(lines.last().unwrap()["delivered"], 7);
}

#[test]
fn dropped_frames_leave_the_stream_and_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("drop.toml");
    std::fs::write(&cfg, "seed = 9\n[[effects]]\nname = \"frame_drop\"\np = 0.5\n").unwrap();
    let out = run(&format!(
        "videotestsrc num-buffers=40 ! {} ! faultcam config={} ! appsink name=out",
        caps("GRAY8"),
        cfg.display()
    ))
    .unwrap();
    assert_eq!(out.messages.len(), 40);
    let dropped: Vec<u64> = out
        .messages
        .iter()
        .filter(|m| m.get::<&str>("status").unwrap() == "dropped_by_fault")
        .map(|m| m.get::<u64>("seq").unwrap())
        .collect();
    assert!(!dropped.is_empty() && dropped.len() < 40, "{dropped:?}");
    assert_eq!(out.frames.len() + dropped.len(), 40);
    for m in out.messages.iter().filter(|m| m.get::<&str>("status").unwrap() == "dropped_by_fault") {
        assert_eq!(m.get::<&str>("dropped-by").unwrap(), "frame_drop");
    }
    // The delivered buffers keep their timestamps: the dropped ones are the gaps.
    let kept: Vec<u64> = out.pts.iter().map(|p| p.unwrap() / 33_333_333).collect();
    assert!(kept.iter().all(|k| !dropped.contains(k)), "{kept:?} vs {dropped:?}");
}

#[test]
fn errors_name_the_property_and_the_file() {
    let e = run(&format!("videotestsrc num-buffers=2 ! {} ! faultcam ! appsink name=out", caps("GRAY8"))).unwrap_err();
    assert!(e.contains("config"), "{e}");
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("bad.toml");
    std::fs::write(&cfg, "[[effects]]\nname = \"gaussian_noise\"\nsigma_dn = -4\n").unwrap();
    let e = run(&format!(
        "videotestsrc num-buffers=2 ! {} ! faultcam config={} ! appsink name=out",
        caps("GRAY8"),
        cfg.display()
    ))
    .unwrap_err();
    assert!(e.contains("bad.toml:3") && e.contains("sigma_dn"), "{e}");
    // Formats the chain does not take are refused at negotiation.
    let e = run(&format!(
        "videotestsrc num-buffers=2 ! video/x-raw,format=I420,width=64,height=48 ! faultcam config={} ! appsink name=out",
        cfg.display()
    ));
    assert!(e.is_err());
}

/// The shared library as GStreamer loads it: gst-inspect-1.0 and gst-launch-1.0 with
/// GST_PLUGIN_PATH pointing at the build folder (a private registry, so no stale cache).
#[test]
fn gst_launch_and_gst_inspect_load_the_plugin() {
    // The cdylib built with this test is in deps/ (cargo uplifts it to target/<profile>/ only when
    // the plugin is built on its own): copy it into a folder of its own for GST_PLUGIN_PATH.
    let built = profile_dir().join("deps/libgstfaultcam.so");
    assert!(built.exists(), "{} missing", built.display());
    let dir = tempfile::tempdir().unwrap();
    let plugin_dir = dir.path().join("plugins");
    std::fs::create_dir_all(&plugin_dir).unwrap();
    std::fs::copy(&built, plugin_dir.join("libgstfaultcam.so")).unwrap();
    let env = |c: &mut Command| {
        c.env("GST_PLUGIN_PATH", &plugin_dir).env("GST_REGISTRY", dir.path().join("registry.bin"));
    };
    let mut inspect = Command::new("gst-inspect-1.0");
    inspect.arg("faultcam");
    env(&mut inspect);
    let o = inspect.output().expect("gst-inspect-1.0 (gstreamer1.0-tools)");
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{text}{}", String::from_utf8_lossy(&o.stderr));
    for want in ["GRAY16_LE", "config", "seed", "log", "masks", "trigger", "post-messages"] {
        assert!(text.contains(want), "gst-inspect-1.0 faultcam lacks {want}:\n{text}");
    }
    let cfg = dir.path().join("f.toml");
    std::fs::write(&cfg, "[[effects]]\nname = \"gaussian_noise\"\nsigma_dn = 2\n").unwrap();
    let log = dir.path().join("gt.jsonl");
    let mut launch = Command::new("gst-launch-1.0");
    launch.arg("-q").args(
        format!(
            "videotestsrc num-buffers=4 ! video/x-raw,format=GRAY16_LE,width=64,height=48 ! faultcam config={} seed=2 log={} ! fakesink",
            cfg.display(),
            log.display()
        )
        .split(' '),
    );
    env(&mut launch);
    let o = launch.output().unwrap();
    assert!(o.status.success(), "gst-launch-1.0: {}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(text.lines().filter(|l| l.contains(r#""record":"frame""#)).count(), 4, "{text}");
    assert!(text.lines().next().unwrap().contains(r#""seed":2"#), "{text}");
}

#[test]
fn timeline_by_pts_runs_on_stream_time() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("campaign.toml");
    std::fs::write(
        &cfg,
        "[[effects]]\nname = \"gain_offset\"\n\n[[events]]\nname = \"dim\"\neffect = \"gain_offset\"\n\
         at_s = 0.25\nduration_s = 0.2\n[events.params]\ngain = 0.5\n",
    )
    .unwrap();
    // 10 frames/s: stream times 0, 0.1, ... 0.7 s; the event covers t in [0.25, 0.45).
    let out = run(&format!(
        "videotestsrc num-buffers=8 ! video/x-raw,format=GRAY8,width=32,height=16,framerate=10/1 ! \
         faultcam config={} ! appsink name=out",
        cfg.display()
    ))
    .unwrap();
    let active: Vec<u64> = out
        .messages
        .iter()
        .filter(|m| m.get::<&str>("effects").unwrap().contains("gain_offset"))
        .map(|m| m.get::<u64>("stream-time").unwrap() / 100_000_000)
        .collect();
    assert_eq!(active, [3, 4]);
}

/// The `trigger` property: a rig on a real pseudo-terminal pair sends `1 PING`, and once that is
/// acknowledged (frames flow) `2 START flash`, while a live source streams; the element acknowledges it and the triggered event holds from one frame to
/// the end of the stream (frames before it untouched).
#[test]
fn serial_trigger_property_starts_an_event_mid_stream() {
    use std::io::{Read, Write};
    let (mut rig, dut) = serialport::TTYPort::pair().expect("pseudo-terminal pair");
    let dut_path = serialport::SerialPort::name(&dut).expect("pty name");
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("campaign.toml");
    std::fs::write(
        &cfg,
        r#"
seed = 3

[[effects]]
name = "gain_offset"          # driven by the event only
offset_dn = 40

[[events]]
name = "lift"
effect = "gain_offset"
trigger = "flash"
duration_s = 100.0

[triggers]
armed = true
"#,
    )
    .unwrap();
    // The rig waits for the stream (PING is acknowledged once frames flow), then fires.
    let rig_thread = std::thread::spawn(move || {
        serialport::SerialPort::set_timeout(&mut rig, std::time::Duration::from_millis(100)).unwrap();
        let mut reply = Vec::new();
        let read_line = |reply: &mut Vec<u8>, rig: &mut serialport::TTYPort| {
            let t0 = std::time::Instant::now();
            let lines = reply.iter().filter(|&&b| b == b'\n').count();
            while t0.elapsed() < std::time::Duration::from_secs(20)
                && reply.iter().filter(|&&b| b == b'\n').count() == lines
            {
                let mut buf = [0u8; 256];
                if let Ok(n) = rig.read(&mut buf) {
                    reply.extend_from_slice(&buf[..n]);
                }
            }
        };
        rig.write_all(b"1 PING\n").unwrap();
        read_line(&mut reply, &mut rig);
        rig.write_all(b"2 START flash\n").unwrap();
        read_line(&mut reply, &mut rig);
        String::from_utf8_lossy(&reply).into_owned()
    });
    let out = run(&format!(
        "videotestsrc pattern=black is-live=true num-buffers=90 ! video/x-raw,format=GRAY8,width=96,height=64,framerate=30/1 ! faultcam config={} trigger={} ! appsink name=out",
        cfg.display(),
        dut_path
    ))
    .unwrap();
    let reply = rig_thread.join().unwrap();
    drop(dut);
    assert!(reply.matches("ACK").count() == 2 && !reply.contains("NAK"), "rig got: {reply:?}");
    assert_eq!(out.messages.len(), 90);
    let on: Vec<bool> =
        out.messages.iter().map(|m| m.get::<&str>("effects").unwrap().contains("gain_offset")).collect();
    let first = on.iter().position(|&b| b).expect("the trigger never took effect");
    assert!(first > 0, "the event was on before the trigger was sent");
    assert!(on[first..].iter().all(|&b| b), "the event must hold to the end: {on:?}");
    let mean = |f: &[u8]| f.iter().map(|&v| v as f64).sum::<f64>() / f.len() as f64;
    // videotestsrc's black in GRAY8 is 16 (video range); lifted by 40 DN while the event runs.
    assert!((mean(&out.frames[first - 1]) - 16.0).abs() < 1.0);
    assert!((mean(&out.frames[first]) - 56.0).abs() < 1.0);
}

#[test]
fn frames_held_by_reorder_are_pushed_at_eos_and_every_buffer_is_accounted_for() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("reorder.toml");
    std::fs::write(&cfg, "seed = 4\n[[effects]]\nname = \"reorder\"\ndepth = 3\n").unwrap();
    let log = dir.path().join("gt.jsonl");
    // A moving ball: every buffer differs, so each output can be matched to its input.
    let src = format!("videotestsrc pattern=ball num-buffers=12 ! {}", caps("GRAY8"));
    let inputs = run(&format!("{src} ! appsink name=out")).unwrap();
    let out =
        run(&format!("{src} ! faultcam config={} log={} ! appsink name=out", cfg.display(), log.display())).unwrap();
    // Nothing lost: all 12 buffers come out (3 of them at EOS), each input exactly once.
    assert_eq!(out.frames.len(), 12, "{} buffers out", out.frames.len());
    let mut seen = vec![0; 12];
    for f in &out.frames {
        let k = inputs.frames.iter().position(|i| i == f).expect("an output that is no input");
        seen[k] += 1;
    }
    assert_eq!(seen, vec![1; 12], "each input once");
    assert_ne!(out.frames, inputs.frames, "reorder changed the order");
    // The buffers keep the stream's time slots: the 9 in-stream outputs those of inputs 3..12
    // (the first 3 were held), the 3 released at EOS the next 3 slots after the last buffer.
    let got: Vec<u64> = out.pts.iter().map(|p| p.unwrap()).collect();
    let inp: Vec<u64> = inputs.pts.iter().map(|p| p.unwrap()).collect();
    assert_eq!(got[..9], inp[3..12]);
    let period = (inp[11] - inp[0]) as f64 / 11.0;
    for (k, &p) in got[9..].iter().enumerate() {
        let want = inp[11] as f64 + (k + 1) as f64 * period;
        assert!((p as f64 - want).abs() < 10.0, "released {k}: pts {p}, want {want}");
    }
    // 12 hold/pass messages + 3 drained at EOS.
    assert_eq!(out.messages.len(), 15);
    let held = out.messages.iter().filter(|m| m.get::<&str>("dropped-by").ok() == Some("reorder")).count();
    assert_eq!(held, 3);
    // The log is complete and accounts for every buffer (`faultcam log check`).
    let text = std::fs::read_to_string(&log).unwrap();
    let summary: serde_json::Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    assert_eq!(summary["record"], "summary", "{text}");
    assert_eq!((summary["frames_in"].as_u64(), summary["delivered"].as_u64()), (Some(12), Some(12)), "{summary}");
    assert_eq!((summary["held"].as_u64(), summary["drained"].as_u64()), (Some(3), Some(3)), "{summary}");
    let check = std::process::Command::new(faultcam_bin()).args(["log", "check"]).arg(&log).output().unwrap();
    assert!(
        check.status.success(),
        "{}{}",
        String::from_utf8_lossy(&check.stdout),
        String::from_utf8_lossy(&check.stderr)
    );
}
