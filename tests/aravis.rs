//! Aravis source against the in-process fake camera `Fake_1` (the `Fake` interface only: the
//! GigE and USB3 interfaces are disabled, so nothing is sent on the network).
//!
//! The fake camera fills frame `id` with the diagonal ramp `v(x, y) = (x + y + id) mod 255`
//! (8-bit) or `v·256 + 255` (Mono16), at the exposure's scale 1 (10 ms).
#![cfg(feature = "aravis")]

use faultcam::control::Controller;
use faultcam::faults::chain::Chain;
use faultcam::faults::default_params;
use faultcam::frame::{Frame, PixelFormat};
use faultcam::gtlog::GroundTruthLog;
use faultcam::pipeline::{self, PipelineOptions};
use faultcam::sink::Sink;
use faultcam::sink::files::FilesSink;
use faultcam::source::Source;
use faultcam::source::aravis::AravisSource;

/// Offset `c` such that `v(x, y) = (x + y + c) mod 255`, checking every pixel.
fn ramp_offset8(f: &Frame) -> u32 {
    let d = f.as_u8().unwrap();
    let c = d[0] as u32;
    for y in 0..f.height as usize {
        for x in 0..f.width as usize {
            assert_eq!(d[y * f.stride + x] as u32, (x as u32 + y as u32 + c) % 255, "pixel ({x},{y}) of seq {}", f.seq);
        }
    }
    c
}

#[test]
fn fake_camera_streams_in_order_with_its_ramp() {
    let mut s = AravisSource::open("aravis:Fake_1?width=64&height=48&fps=200").unwrap();
    let d = s.describe();
    assert!(d.contains("64x48") && d.contains("Mono8"), "what the camera chose is reported: {d}");
    let mut offsets = Vec::new();
    let mut last_seq = None;
    let mut last_pts = 0;
    while offsets.len() < 8 {
        match s.next_frame() {
            Ok(Some(f)) => {
                assert_eq!((f.width, f.height, f.format, f.stride), (64, 48, PixelFormat::Mono8, 64));
                if let Some(l) = last_seq {
                    assert!(f.seq > l, "seq increases");
                    assert!(f.pts_ns > last_pts, "camera timestamps increase");
                }
                let c = ramp_offset8(&f);
                // The ramp advances with the frame id, and seq counts frame ids.
                if let Some(&(s0, c0)) = offsets.first() {
                    assert_eq!(c, (c0 + (f.seq - s0) as u32) % 255, "content follows the frame id");
                }
                offsets.push((f.seq, c));
                last_seq = Some(f.seq);
                last_pts = f.pts_ns;
                s.recycle(f);
            }
            Ok(None) => panic!("a camera does not end"),
            // A lost frame is reported, never silent; it must not happen often.
            Err(e) if e.recoverable() => eprintln!("skipped: {e}"),
            Err(e) => panic!("{e}"),
        }
    }
}

#[test]
fn fake_camera_mono16_and_settings_read_back() {
    let mut s =
        AravisSource::open("aravis:Fake_1?pixel_format=Mono16&width=32&height=4&fps=150&exposure_us=10000").unwrap();
    let d = s.describe();
    // The camera rounds the rate to its clock (150.02 fps): the value read back is reported.
    assert!(d.contains("Mono16") && d.contains("150.0") && d.contains("exposure 10000 us"), "{d}");
    let f = s.next_frame().unwrap().unwrap();
    assert_eq!(f.format, PixelFormat::Mono16);
    let v = f.as_u16().unwrap();
    let c = (v[0] >> 8) as u32;
    for (x, &p) in v[..32].iter().enumerate() {
        assert_eq!(p as u32, ((x as u32 + c) % 255) * 256 + 255, "x={x}");
    }
}

#[test]
fn errors_are_clear() {
    let e = AravisSource::open("aravis:Fake_1?pixel_format=Nope").err().unwrap().to_string();
    assert!(e.contains("pixel_format=Nope") && e.contains("Mono16"), "lists what the camera offers: {e}");
    let e = AravisSource::open("aravis:Fake_1?colour=red").err().unwrap().to_string();
    assert!(e.contains("colour") && e.contains("exposure_us"), "{e}");
    let e = AravisSource::open("aravis:Fake_42").err().unwrap().to_string();
    assert!(e.contains("Fake_42"), "{e}");
    // One frame per second with a 20 ms timeout: the first pop times out with a clear error.
    let mut s = AravisSource::open("aravis:Fake_1?width=16&height=16&fps=1&timeout_ms=20").unwrap();
    let mut err = None;
    for _ in 0..3 {
        match s.next_frame() {
            Ok(_) => continue,
            Err(e) => {
                err = Some(e);
                break;
            }
        }
    }
    let e = err.expect("a timeout");
    assert!(!e.recoverable());
    assert!(e.to_string().contains("no frame within 20 ms"), "{e}");
}

#[test]
fn fake_camera_through_the_pipeline_into_files() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let source = Box::new(AravisSource::open("aravis:Fake_1?width=40&height=30&fps=200").unwrap());
    let sink: Box<dyn Sink> = Box::new(FilesSink::open(&format!("files:{}", out.display())).unwrap());
    let mut chain = Chain::new(9);
    let mut p = default_params("gain_offset").unwrap();
    p.set("offset_dn", 3.0).unwrap();
    chain.push("gain_offset", p).unwrap();
    let log_path = dir.path().join("gt.jsonl");
    let mut log = GroundTruthLog::create(&log_path).unwrap();
    let opts = PipelineOptions { max_frames: Some(12), realtime_source: true, ..Default::default() };
    let controllers: Vec<Box<dyn Controller>> = Vec::new();
    let summary = pipeline::run(source, sink, chain, controllers, &opts, &mut log).unwrap();
    drop(log);
    assert!(summary.error.is_none(), "{summary}");
    assert_eq!(summary.frames_in, 12);
    assert_eq!(summary.delivered, 12);
    assert_eq!(summary.unaccounted, 0);
    // Every delivered record names its file; each file is the ramp + 3 DN (clipped).
    let text = std::fs::read_to_string(&log_path).unwrap();
    let recs: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .filter(|v: &serde_json::Value| v["record"] == "frame")
        .collect();
    assert_eq!(recs.len(), 12);
    for r in &recs {
        assert_eq!(r["status"], "delivered");
        assert_eq!(r["effects"][0]["name"], "gain_offset");
        let img =
            image::open(r["output"].as_str().map(|o| out.join(std::path::Path::new(o).file_name().unwrap())).unwrap())
                .unwrap()
                .to_luma8();
        let c = img.get_pixel(0, 0)[0] as u32 - 3;
        for (x, y, p) in img.enumerate_pixels() {
            let v = (x + y + c) % 255;
            assert_eq!(p[0] as u32, (v + 3).min(255), "({x},{y}) of seq {}", r["seq"]);
        }
    }
}

#[cfg(feature = "gst")]
#[test]
fn aravissrc_element_reads_the_fake_camera() {
    // Opening our source first enables the Fake interface (and disables GigE/USB3) in this
    // process; GStreamer's aravissrc then finds Fake_1 without any discovery traffic.
    drop(AravisSource::open("aravis:Fake_1?width=16&height=16").unwrap());
    let mut s = faultcam::source::gst::GstSource::open(
        "gst:aravissrc camera-name=Fake_1 num-buffers=4 ! videoconvert ! video/x-raw,format=GRAY8 ! appsink sync=false",
    )
    .unwrap();
    let mut n = 0;
    while let Some(f) = s.next_frame().unwrap() {
        assert_eq!(f.format, PixelFormat::Mono8);
        ramp_offset8(&f);
        n += 1;
    }
    assert_eq!(n, 4);
}
