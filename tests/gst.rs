//! GStreamer source and sink against real pipelines (videotestsrc, encoders, filesink,
//! multifilesink, decodebin), driven to EOS. Small frames, `num-buffers`, `sync=false`.
#![cfg(feature = "gst")]

use faultcam::frame::{Frame, PixelFormat};
use faultcam::sink::Sink;
use faultcam::sink::gst::GstSink;
use faultcam::source::Source;
use faultcam::source::gst::GstSource;
use std::path::Path;
use std::process::Command;

fn read_all(src: &mut GstSource) -> Vec<Frame> {
    let mut v = Vec::new();
    while let Some(f) = src.next_frame().expect("frame") {
        v.push(f);
    }
    v
}

/// A raw dump of the same videotestsrc frame as GStreamer lays it out (padded rows).
fn raw_dump(caps: &str, path: &Path) -> Vec<u8> {
    let status = Command::new("gst-launch-1.0")
        .args(["-q", "videotestsrc", "num-buffers=1", "pattern=zone-plate", "kx2=20", "ky2=20", "kt=1", "!"])
        .arg(caps)
        .args(["!", "filesink"])
        .arg(format!("location={}", path.display()))
        .status()
        .expect("gst-launch-1.0 runs");
    assert!(status.success());
    std::fs::read(path).unwrap()
}

#[test]
fn videotestsrc_frames_count_order_timestamps() {
    let mut src = GstSource::open(
        "gst:videotestsrc num-buffers=30 ! video/x-raw,format=GRAY8,width=320,height=240,framerate=30/1 ! appsink sync=false",
    )
    .unwrap();
    let d = src.describe();
    assert!(d.contains("GRAY8") && d.contains("320"), "negotiated caps reported: {d}");
    let frames = read_all(&mut src);
    assert_eq!(frames.len(), 30);
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(f.seq, i as u64);
        assert_eq!((f.width, f.height, f.format, f.stride), (320, 240, PixelFormat::Mono8, 320));
        // 30 fps: pts = i / 30 s (GStreamer rounds to the nanosecond).
        let expect = i as f64 * 1e9 / 30.0;
        assert!((f.pts_ns as f64 - expect).abs() <= 1.0, "pts {} vs {expect}", f.pts_ns);
    }
    // EOS is sticky.
    assert!(src.next_frame().unwrap().is_none());
}

#[test]
fn padded_rows_are_unpadded_exactly() {
    let dir = tempfile::tempdir().unwrap();
    // GRAY8 rows of 321 px are padded to 324 bytes; RGB rows of 101 px (303 bytes) to 304.
    for (fmt, w, bpp, pf) in [("GRAY8", 321usize, 1usize, PixelFormat::Mono8), ("RGB", 101, 3, PixelFormat::Rgb8)] {
        let h = 9usize;
        let caps = format!("video/x-raw,format={fmt},width={w},height={h}");
        let raw = raw_dump(&caps, &dir.path().join("raw"));
        let gst_stride = (w * bpp).div_ceil(4) * 4;
        assert_eq!(raw.len(), gst_stride * h, "GStreamer pads rows to 4 bytes");
        let mut src = GstSource::open(&format!(
            "gst:videotestsrc num-buffers=1 pattern=zone-plate kx2=20 ky2=20 kt=1 ! {caps} ! appsink sync=false"
        ))
        .unwrap();
        let f = src.next_frame().unwrap().unwrap();
        assert_eq!((f.format, f.stride), (pf, w * bpp));
        let data = f.as_u8().unwrap();
        for y in 0..h {
            assert_eq!(
                &data[y * w * bpp..(y + 1) * w * bpp],
                &raw[y * gst_stride..y * gst_stride + w * bpp],
                "row {y}"
            );
        }
    }
}

#[test]
fn gray16_is_little_endian_samples() {
    let dir = tempfile::tempdir().unwrap();
    let caps = "video/x-raw,format=GRAY16_LE,width=10,height=4";
    let raw = raw_dump(caps, &dir.path().join("raw16"));
    let mut src = GstSource::open(&format!(
        "gst:videotestsrc num-buffers=1 pattern=zone-plate kx2=20 ky2=20 kt=1 ! {caps} ! appsink sync=false"
    ))
    .unwrap();
    let f = src.next_frame().unwrap().unwrap();
    assert_eq!(f.format, PixelFormat::Mono16);
    let want: Vec<u16> = raw.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect();
    assert_eq!(f.as_u16().unwrap(), &want[..]);
    assert!(want.iter().any(|&v| v > 255), "real 16-bit content");
}

#[test]
fn errors_name_the_problem() {
    let e = GstSource::open("gst:nosuchelement ! appsink").err().unwrap().to_string();
    assert!(e.contains("nosuchelement"), "{e}");
    let e = GstSource::open("gst:videotestsrc num-buffers=1 ! fakesink").err().unwrap().to_string();
    assert!(e.contains("appsink"), "{e}");
    // I420 cannot reach an appsink that accepts only GRAY8/GRAY16_LE/RGB: not negotiated.
    let e = GstSource::open("gst:videotestsrc num-buffers=2 ! video/x-raw,format=I420 ! appsink")
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(e.contains("element") && e.to_lowercase().contains("negotiat"), "{e}");
    let e = GstSink::open("gst:videotestsrc ! fakesink").err().unwrap().to_string();
    assert!(e.contains("appsrc"), "{e}");
}

fn ramp(seq: u64, w: u32, h: u32, format: PixelFormat) -> Frame {
    let mut f = Frame::new(w, h, format).unwrap();
    f.seq = seq;
    f.pts_ns = seq * 40_000_000;
    let c = format.channels();
    match format {
        PixelFormat::Mono16 => {
            for (i, v) in f.as_u16_mut().unwrap().iter_mut().enumerate() {
                *v = ((i as u64 * 263 + seq * 1000) % 65536) as u16;
            }
        }
        _ => {
            for (i, v) in f.as_u8_mut().unwrap().iter_mut().enumerate() {
                let (x, y) = ((i / c) as u32 % w, (i / c) as u32 / w);
                *v = ((x * 3 + y * 5 + seq as u32 * 7 + (i % c) as u32 * 50) % 256) as u8;
            }
        }
    }
    f
}

#[test]
fn sink_png_round_trip_is_exact() {
    // appsrc → pngenc → multifilesink, read back with the image crate: lossless, all formats.
    for format in [PixelFormat::Mono8, PixelFormat::Mono16, PixelFormat::Rgb8] {
        let dir = tempfile::tempdir().unwrap();
        let pattern = dir.path().join("f%03d.png");
        // pngenc takes GRAY16 big-endian; without the caps filter videoconvert would pick
        // (dithered) GRAY8 for Mono16.
        let caps = if format == PixelFormat::Mono16 { "video/x-raw,format=GRAY16_BE ! " } else { "" };
        let mut sink = GstSink::open(&format!(
            "gst:appsrc ! videoconvert ! {caps}pngenc ! multifilesink location={}",
            pattern.display()
        ))
        .unwrap();
        let frames: Vec<Frame> = (0..4).map(|s| ramp(s, 37, 11, format)).collect();
        for f in &frames {
            sink.write_frame(f, None).unwrap();
        }
        sink.finish().unwrap();
        for f in &frames {
            let img = image::open(dir.path().join(format!("f{:03}.png", f.seq))).unwrap();
            match format {
                PixelFormat::Mono8 => assert_eq!(img.to_luma8().as_raw(), f.as_u8().unwrap()),
                PixelFormat::Rgb8 => assert_eq!(img.to_rgb8().as_raw(), f.as_u8().unwrap()),
                _ => assert_eq!(img.to_luma16().as_raw(), f.as_u16().unwrap()),
            }
        }
    }
}

#[test]
fn sink_vp8_webm_then_decode_with_source() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.webm");
    let mut sink = GstSink::open(&format!(
        "gst:appsrc ! videoconvert ! vp8enc deadline=1 ! webmmux ! filesink location={}",
        out.display()
    ))
    .unwrap();
    // Smooth content so a lossy codec keeps it close.
    let mut frames = Vec::new();
    for s in 0..12u64 {
        let mut f = Frame::new(64, 48, PixelFormat::Mono8).unwrap();
        f.seq = s;
        f.pts_ns = s * 40_000_000;
        for (i, v) in f.as_u8_mut().unwrap().iter_mut().enumerate() {
            *v = (40 + (i % 64) * 2 + (i / 64)) as u8;
        }
        frames.push(f);
    }
    for f in &frames {
        sink.write_frame(f, None).unwrap();
    }
    sink.finish().unwrap();
    assert!(std::fs::metadata(&out).unwrap().len() > 100);
    let mut src = GstSource::open(&format!(
        "gst:filesrc location={} ! decodebin ! videoconvert ! video/x-raw,format=GRAY8 ! appsink sync=false",
        out.display()
    ))
    .unwrap();
    let back = read_all(&mut src);
    assert_eq!(back.len(), frames.len(), "every frame encoded and decoded");
    for (a, b) in frames.iter().zip(&back) {
        assert_eq!((b.width, b.height), (64, 48));
        assert_eq!(a.pts_ns, b.pts_ns, "timestamps survive the container");
        let mad: f64 =
            a.as_u8().unwrap().iter().zip(b.as_u8().unwrap()).map(|(&x, &y)| (x as f64 - y as f64).abs()).sum::<f64>()
                / a.pixels() as f64;
        assert!(mad < 6.0, "mean abs difference {mad} DN after VP8");
    }
}

#[test]
fn sink_rejects_a_size_change_and_reports_pipeline_errors() {
    let mut sink = GstSink::open("gst:appsrc ! videoconvert ! fakesink sync=false").unwrap();
    sink.write_frame(&ramp(0, 16, 8, PixelFormat::Mono8), None).unwrap();
    let e = sink.write_frame(&ramp(1, 17, 8, PixelFormat::Mono8), None).unwrap_err().to_string();
    assert!(e.contains("16x8") && e.contains("17x8"), "{e}");
    sink.finish().unwrap();

    // The downstream caps filter wants another size: negotiation fails, and the error names
    // the element.
    let mut sink = GstSink::open("gst:appsrc ! video/x-raw,width=99 ! fakesink").unwrap();
    let mut err = None;
    for s in 0..5 {
        if let Err(e) = sink.write_frame(&ramp(s, 16, 8, PixelFormat::Mono8), None) {
            err = Some(e.to_string());
            break;
        }
    }
    let err = err.or_else(|| sink.finish().err().map(|e| e.to_string())).expect("an error");
    assert!(err.contains("element"), "{err}");
}

#[test]
fn a_pipeline_error_mid_stream_keeps_the_frames_made_before_it() {
    // 30 PNG files, the 21st with a corrupted image chunk: pngdec fails there and the error
    // stops the pipeline. The 20 frames decoded before it (some still queued in the appsink
    // when the error arrives) are all delivered, in order, then the error names an element.
    let dir = tempfile::tempdir().unwrap();
    let status = Command::new("gst-launch-1.0")
        .args(["-q", "videotestsrc", "num-buffers=30", "pattern=ball", "!"])
        .args(["video/x-raw,format=GRAY8,width=96,height=64", "!", "pngenc", "!", "multifilesink"])
        .arg(format!("location={}/f%04d.png", dir.path().display()))
        .status()
        .expect("gst-launch-1.0 runs");
    assert!(status.success());
    let bad = dir.path().join("f0020.png");
    let mut png = std::fs::read(&bad).unwrap();
    let idat = png.windows(4).position(|w| w == b"IDAT").expect("an IDAT chunk");
    let end = (idat + 200).min(png.len() - 12);
    for b in &mut png[idat + 8..end] {
        *b ^= 0x5a;
    }
    std::fs::write(&bad, png).unwrap();
    let mut src = GstSource::open(&format!(
        "gst:multifilesrc location={}/f%04d.png index=0 stop-index=29 caps=image/png ! pngdec ! videoconvert ! \
         appsink sync=false",
        dir.path().display()
    ))
    .unwrap();
    let mut seqs = Vec::new();
    let err = loop {
        match src.next_frame() {
            Ok(Some(f)) => {
                seqs.push(f.seq);
                src.recycle(f);
            }
            Ok(None) => panic!("the stream ended without the error after {} frames", seqs.len()),
            Err(e) => break e.to_string(),
        }
    };
    assert_eq!(seqs, (0..20).collect::<Vec<u64>>(), "every frame before the corrupt file, in order");
    assert!(err.contains("element"), "{err}");
    assert!(src.next_frame().unwrap().is_none(), "after the error the stream has ended");
}
