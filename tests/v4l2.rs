//! V4L2 source and sink against a real v4l2loopback device. The machine must name the device:
//!
//! ```sh
//! sudo modprobe v4l2loopback devices=1 video_nr=10 card_label=faultcam exclusive_caps=1 max_buffers=4
//! FAULTCAM_V4L2_DEVICE=/dev/video10 cargo test --test v4l2 -- --test-threads=1 --nocapture
//! ```
//!
//! Without `FAULTCAM_V4L2_DEVICE` every test prints why it is skipped and passes (kernels
//! without V4L2, CI containers). See `hil/v4l2loopback.md` for the rig set-up.
#![cfg(feature = "v4l2")]

use faultcam::frame::{Frame, PixelFormat};
use faultcam::sink::Sink;
use faultcam::sink::v4l2::V4l2Sink;
use faultcam::source::Source;
use faultcam::source::v4l2::V4l2Source;
use std::sync::Mutex;
use std::sync::mpsc;
use std::time::Duration;

const FAULTCAM: &str = env!("CARGO_BIN_EXE_faultcam");
/// One device: the tests take turns.
static DEVICE: Mutex<()> = Mutex::new(());

fn device(test: &str) -> Option<String> {
    match std::env::var("FAULTCAM_V4L2_DEVICE") {
        Ok(d) if !d.is_empty() => Some(d),
        _ => {
            eprintln!(
                "skipped {test}: set FAULTCAM_V4L2_DEVICE=/dev/videoN (a v4l2loopback device, see \
                 hil/v4l2loopback.md) to run the V4L2 device tests"
            );
            None
        }
    }
}

/// A frame whose every pixel encodes `k`: v = (x + 3y + 17k) mod 256.
fn pattern(k: u64, w: u32, h: u32) -> Frame {
    let mut f = Frame::new(w, h, PixelFormat::Mono8).unwrap();
    f.seq = k;
    f.pts_ns = k * 33_333_333;
    let stride = f.stride;
    for (y, row) in f.as_u8_mut().unwrap().chunks_exact_mut(stride).enumerate() {
        for (x, v) in row.iter_mut().enumerate() {
            *v = ((x + 3 * y + 17 * k as usize) % 256) as u8;
        }
    }
    f
}

/// Which pattern `k` (if any) a captured frame is.
fn which(f: &Frame, candidates: std::ops::Range<u64>) -> Option<u64> {
    candidates.into_iter().find(|&k| {
        let p = pattern(k, f.width, f.height);
        p.as_u8().unwrap() == f.as_u8().unwrap()
    })
}

/// A reader thread: captures from `uri` until `n` frames or an error, sending each.
fn reader(uri: String, n: usize) -> (mpsc::Receiver<Frame>, std::thread::JoinHandle<Result<(), String>>) {
    let (tx, rx) = mpsc::channel();
    let h = std::thread::spawn(move || {
        let mut src = V4l2Source::open(&uri).map_err(|e| e.to_string())?;
        eprintln!("reader: {}", src.describe());
        for _ in 0..n {
            match src.next_frame() {
                Ok(Some(f)) => {
                    if tx.send(f).is_err() {
                        break;
                    }
                }
                Ok(None) => break,
                Err(e) if e.recoverable() => eprintln!("reader: skipped {e}"),
                Err(e) => return Err(e.to_string()),
            }
        }
        Ok(())
    });
    (rx, h)
}

#[test]
fn loopback_round_trip_mmap_and_write_io() {
    let Some(dev) = device("loopback_round_trip_mmap_and_write_io") else { return };
    let _turn = DEVICE.lock().unwrap_or_else(|e| e.into_inner());
    let (w, h) = (64u32, 48u32);
    for io in ["mmap", "write"] {
        let mut sink = V4l2Sink::open(&format!("v4l2:{dev}?io={io}&fps=30")).unwrap();
        // The first frame negotiates the format; with exclusive_caps=1 the device becomes a
        // capture device only now.
        sink.write_frame(&pattern(0, w, h), None).unwrap();
        let d = sink.describe();
        assert!(d.contains("driver chose 64x48 GREY") && d.contains(&format!("io {io}")), "{d}");
        let (rx, handle) = reader(format!("v4l2:{dev}?format=GREY&timeout_ms=3000"), 1000);
        // Lockstep: write frame k, read until frame k arrives (a reader may first see an older one).
        let n = 20u64;
        for k in 1..=n {
            sink.write_frame(&pattern(k, w, h), None).unwrap();
            loop {
                let f = rx.recv_timeout(Duration::from_secs(5)).unwrap_or_else(|e| panic!("io={io} frame {k}: {e}"));
                assert_eq!((f.width, f.height, f.format), (w, h, PixelFormat::Mono8));
                let got =
                    which(&f, 0..n + 1).unwrap_or_else(|| panic!("io={io}: a captured frame is no written frame"));
                assert!(got <= k, "io={io}: frame {got} before it was written ({k})");
                if got == k {
                    break;
                }
            }
        }
        drop(sink);
        drop(rx);
        // The reader ends with a timeout error once the writer is gone, or on its own.
        let _ = handle.join();
    }
}

#[test]
fn faultcam_run_streams_into_and_out_of_the_loopback_device() {
    let Some(dev) = device("faultcam_run_streams_into_and_out_of_the_loopback_device") else { return };
    let _turn = DEVICE.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("f.toml");
    std::fs::write(&cfg, "[[effects]]\nname = \"gain_offset\"\noffset_dn = 0\n").unwrap();

    // 1. faultcam writes 30 frames into the device (v4l2 sink); the log accounts for them.
    let log = dir.path().join("out.jsonl");
    let out = std::process::Command::new(FAULTCAM)
        .args(["run", "--source", "synth:?width=64&height=48&frames=30", "--fps", "30"])
        .arg("--sink")
        .arg(format!("v4l2:{dev}"))
        .arg("--faults")
        .arg(&cfg)
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let summary: serde_json::Value =
        serde_json::from_str(std::fs::read_to_string(&log).unwrap().lines().last().unwrap()).unwrap();
    assert_eq!((summary["delivered"].as_u64(), summary["unaccounted"].as_i64()), (Some(30), Some(0)), "{err}");
    assert!(summary["sink"].as_str().unwrap().contains("driver chose 64x48 GREY"), "{summary}");

    // 2. faultcam captures from the device (v4l2 source) while this test writes patterns.
    let writer_dev = dev.clone();
    let (stop_tx, stop_rx) = mpsc::channel::<()>();
    let writer = std::thread::spawn(move || {
        let mut sink = V4l2Sink::open(&format!("v4l2:{writer_dev}")).unwrap();
        let mut k = 0;
        while stop_rx.try_recv().is_err() && k < 250 {
            sink.write_frame(&pattern(k, 64, 48), None).unwrap();
            k += 1;
            std::thread::sleep(Duration::from_millis(20));
        }
        k
    });
    std::thread::sleep(Duration::from_millis(200));
    let frames = dir.path().join("frames");
    let out = std::process::Command::new(FAULTCAM)
        .args(["run", "--source", &format!("v4l2:{dev}?format=GREY"), "--frames", "10", "--sink"])
        .arg(format!("files:{}", frames.display()))
        .arg("--faults")
        .arg(&cfg)
        .output()
        .unwrap();
    let _ = stop_tx.send(());
    let written = writer.join().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("64x48 GREY"), "the negotiated format is reported: {err}");
    let mut last = None;
    let mut names: Vec<_> = std::fs::read_dir(&frames)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    names.sort();
    assert_eq!(names.len(), 10);
    for p in names {
        let img = image::open(&p).unwrap().to_luma8();
        let mut f = Frame::new(64, 48, PixelFormat::Mono8).unwrap();
        f.as_u8_mut().unwrap().copy_from_slice(img.as_raw());
        let k = which(&f, 0..written).unwrap_or_else(|| panic!("{} is no written frame", p.display()));
        assert!(last.is_none_or(|l| k > l), "order kept");
        last = Some(k);
    }
}
