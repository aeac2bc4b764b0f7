//! Library tests of the `files:` and `synth:` sources and the `files:`/`null:` sinks, on real
//! files written to temporary folders.

use faultcam::frame::{Frame, FrameData, PixelFormat};
use faultcam::sink::{self, Sink, files::FilesSink};
use faultcam::source::files::FilesSource;
use faultcam::source::synth::{SynthConfig, SynthSource};
use faultcam::source::{self, Source, SourceError};
use std::path::Path;

/// A frame with a ramp plus a checker pattern (every sample value distinct enough to catch
/// channel swaps, row flips and 16-bit truncation).
fn pattern(w: u32, h: u32, format: PixelFormat) -> Frame {
    let mut f = Frame::new(w, h, format).unwrap();
    let c = format.channels();
    for y in 0..h as usize {
        for x in 0..w as usize {
            for k in 0..c {
                let v = match format {
                    PixelFormat::Mono16 => ((x * 997 + y * 131 + 7) % 65536) as f32,
                    _ => ((x * 7 + y * 13 + k * 50 + ((x / 4 + y / 4) % 2) * 90) % 256) as f32,
                };
                f.set(x, y, k, v);
            }
        }
    }
    f
}

fn write_with(dir: &Path, format: &str, name: &str, frame: &Frame) {
    let mut s = FilesSink::open(&format!("files:{}?format={format}", dir.display())).unwrap();
    s.write_frame(frame, Some(name)).unwrap();
}

fn read_all(uri: &str) -> (Vec<Frame>, Vec<String>, Vec<SourceError>) {
    let mut src = source::open(uri).unwrap();
    let (mut frames, mut names, mut errors) = (Vec::new(), Vec::new(), Vec::new());
    loop {
        match src.next_frame() {
            Ok(Some(f)) => {
                names.push(src.item_name().unwrap().to_string());
                frames.push(f);
            }
            Ok(None) => break,
            Err(e) => {
                assert!(e.recoverable(), "{e}");
                errors.push(e);
            }
        }
    }
    (frames, names, errors)
}

#[test]
fn lossless_round_trip_every_format_and_depth() {
    for (fmt, ext) in [("png", "png"), ("pgm", "pgm"), ("tiff", "tiff")] {
        for pf in [PixelFormat::Mono8, PixelFormat::Mono16, PixelFormat::Rgb8] {
            let dir = tempfile::tempdir().unwrap();
            let orig = pattern(37, 23, pf);
            write_with(dir.path(), fmt, "img.x", &orig);
            let want_ext = if fmt == "pgm" && pf == PixelFormat::Rgb8 { "ppm" } else { ext };
            assert!(dir.path().join(format!("img.{want_ext}")).exists(), "{fmt} {pf}");
            let (frames, names, errors) = read_all(&format!("files:{}", dir.path().display()));
            assert!(errors.is_empty(), "{fmt} {pf}: {errors:?}");
            assert_eq!(names, vec![format!("img.{want_ext}")]);
            let got = &frames[0];
            assert_eq!((got.width, got.height, got.format), (37, 23, pf), "{fmt}");
            assert_eq!(got.data, orig.data, "{fmt} {pf}: samples differ after the round trip");
        }
    }
}

#[test]
fn jpeg_round_trip_is_close() {
    for pf in [PixelFormat::Mono8, PixelFormat::Rgb8] {
        let dir = tempfile::tempdir().unwrap();
        // Smooth content: JPEG at quality 95 keeps it within a few DN.
        let mut orig = Frame::new(64, 48, pf).unwrap();
        for y in 0..48 {
            for x in 0..64 {
                for k in 0..pf.channels() {
                    orig.set(x, y, k, (x * 3 + y + k * 20) as f32);
                }
            }
        }
        let mut s = FilesSink::open(&format!("files:{}?format=jpg&quality=95", dir.path().display())).unwrap();
        s.write_frame(&orig, None).unwrap();
        assert!(s.last_output().unwrap().ends_with("frame_000000.jpg"));
        let (frames, _, errors) = read_all(&format!("files:{}", dir.path().display()));
        assert!(errors.is_empty());
        let got = &frames[0];
        assert_eq!((got.width, got.height, got.format), (64, 48, pf));
        let a = orig.packed_samples_f32();
        let b = got.packed_samples_f32();
        let mae = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).sum::<f32>() / a.len() as f32;
        assert!(mae < 2.0, "{pf}: mean abs error {mae} DN after JPEG q95");
    }
    let dir = tempfile::tempdir().unwrap();
    let mut s = FilesSink::open(&format!("files:{}?format=jpg", dir.path().display())).unwrap();
    let e = s.write_frame(&Frame::new(8, 8, PixelFormat::Mono16).unwrap(), None).unwrap_err().to_string();
    assert!(e.contains("16-bit"), "{e}");
}

#[test]
fn alpha_is_dropped_and_16bit_png_is_read_as_mono16() {
    let dir = tempfile::tempdir().unwrap();
    let rgba = image::RgbaImage::from_fn(5, 4, |x, y| image::Rgba([x as u8 * 10, y as u8 * 20, 200, 7]));
    rgba.save(dir.path().join("a_rgba.png")).unwrap();
    let la = image::GrayAlphaImage::from_fn(5, 4, |x, y| image::LumaA([(x + y) as u8 * 9, 100]));
    la.save(dir.path().join("b_la.png")).unwrap();
    let l16 = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(5, 4, |x, y| {
        image::Luma([x as u16 * 10000 + y as u16])
    });
    l16.save(dir.path().join("c_l16.png")).unwrap();

    // Each file has a different pixel format: read them one at a time.
    for (name, pf) in
        [("a_rgba.png", PixelFormat::Rgb8), ("b_la.png", PixelFormat::Mono8), ("c_l16.png", PixelFormat::Mono16)]
    {
        let sub = tempfile::tempdir().unwrap();
        std::fs::copy(dir.path().join(name), sub.path().join(name)).unwrap();
        let (frames, _, errors) = read_all(&format!("files:{}", sub.path().display()));
        assert!(errors.is_empty(), "{errors:?}");
        let f = &frames[0];
        assert_eq!(f.format, pf, "{name}");
        assert_eq!(
            f.get(3, 2, 0),
            match name {
                "a_rgba.png" => 30.0,
                "b_la.png" => 45.0,
                _ => 30002.0,
            }
        );
        if pf == PixelFormat::Rgb8 {
            assert_eq!((f.get(3, 2, 1), f.get(3, 2, 2)), (40.0, 200.0));
        }
    }
}

#[test]
fn corrupt_mismatched_and_non_image_files_are_reported_and_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let good = pattern(64, 48, PixelFormat::Mono8);
    write_with(dir.path(), "png", "a", &good);
    std::fs::write(dir.path().join("b.png"), b"\x89PNG\r\n\x1a\nthis is not a png").unwrap();
    write_with(dir.path(), "png", "c", &pattern(32, 32, PixelFormat::Mono8));
    write_with(dir.path(), "png", "d", &good);
    write_with(dir.path(), "png", "e", &pattern(64, 48, PixelFormat::Rgb8));
    std::fs::write(dir.path().join("f.txt"), "notes").unwrap();
    std::fs::write(dir.path().join(".hidden"), "ignored").unwrap();

    let (frames, names, errors) = read_all(&format!("files:{}", dir.path().display()));
    assert_eq!(names, vec!["a.png", "d.png"]);
    // seq is the index in the sorted listing: the skipped b and c leave a gap.
    assert_eq!(frames.iter().map(|f| f.seq).collect::<Vec<_>>(), vec![0, 3]);
    assert_eq!(frames[1].data, good.data);
    let msgs: Vec<String> = errors.iter().map(|e| e.to_string()).collect();
    assert_eq!(msgs.len(), 4, "{msgs:?}");
    assert!(msgs[0].contains("b.png") && msgs[0].contains("corrupt"), "{}", msgs[0]);
    assert!(msgs[1].contains("c.png") && msgs[1].contains("expected 64x48 mono8, got 32x32 mono8"), "{}", msgs[1]);
    assert!(msgs[2].contains("e.png") && msgs[2].contains("expected 64x48 mono8, got 64x48 rgb8"), "{}", msgs[2]);
    assert!(msgs[3].contains("f.txt") && msgs[3].contains("not an image"), "{}", msgs[3]);
}

#[test]
fn reference_is_the_first_readable_file_even_when_corrupt_files_come_first() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("0.png"), b"garbage").unwrap();
    write_with(dir.path(), "png", "1", &pattern(20, 10, PixelFormat::Mono8));
    write_with(dir.path(), "png", "2", &pattern(10, 20, PixelFormat::Mono8));
    let (frames, names, errors) = read_all(&format!("files:{}", dir.path().display()));
    assert_eq!(names, vec!["1.png"]);
    assert_eq!(frames[0].seq, 1);
    assert_eq!(errors.len(), 2);
    let src = FilesSource::open(&format!("files:{}", dir.path().display())).unwrap();
    assert!(src.describe().contains("20x10 mono8"), "{}", src.describe());
}

#[test]
fn loop_fps_timestamps_and_shard() {
    let dir = tempfile::tempdir().unwrap();
    for n in ["a", "b", "c"] {
        write_with(dir.path(), "png", n, &pattern(8, 8, PixelFormat::Mono8));
    }
    let d = dir.path().display();
    let mut src = source::open(&format!("files:{d}?loop=true&fps=10")).unwrap();
    let got: Vec<(u64, u64)> = (0..7).map(|_| src.next_frame().unwrap().map(|f| (f.seq, f.pts_ns)).unwrap()).collect();
    assert_eq!(got, (0..7).map(|i| (i, i * 100_000_000)).collect::<Vec<_>>());

    let ts = dir.path().join("times.txt");
    std::fs::write(&ts, "# name pts_ns\na.png 1000\nb.png 1500\nc.png 3000\n").unwrap();
    let mut src = source::open(&format!("files:{d}?timestamps={}&loop=true", ts.display())).unwrap();
    let got: Vec<u64> = (0..4).map(|_| src.next_frame().unwrap().unwrap().pts_ns).collect();
    // The timestamps file in the folder is not an input; a loop lasts span + mean interval (3000).
    assert_eq!(got, vec![1000, 1500, 3000, 4000]);

    let (frames, names, _) = read_all(&format!("files:{d}?shard=1/2"));
    assert_eq!(names, vec!["b.png"]);
    assert_eq!(frames[0].seq, 1);

    std::fs::write(&ts, "a.png 1\n").unwrap();
    let e = source::open(&format!("files:{d}?timestamps={}", ts.display())).err().unwrap().to_string();
    assert!(e.contains("no entry for b.png"), "{e}");
}

#[test]
fn recycled_frames_are_reused() {
    let dir = tempfile::tempdir().unwrap();
    for n in ["a", "b"] {
        write_with(dir.path(), "png", n, &pattern(16, 16, PixelFormat::Mono8));
    }
    let mut src = source::open(&format!("files:{}", dir.path().display())).unwrap();
    let f = src.next_frame().unwrap().unwrap();
    let ptr = f.as_u8().unwrap().as_ptr();
    src.recycle(f);
    let g = src.next_frame().unwrap().unwrap();
    assert_eq!(g.as_u8().unwrap().as_ptr(), ptr, "the recycled buffer was not reused");
}

#[test]
fn uri_errors_name_the_accepted_values() {
    let e = source::open("webcam:0").err().unwrap().to_string();
    assert!(e.contains("unknown scheme 'webcam:'") && e.contains("files:") && e.contains("synth:"), "{e}");
    let e = sink::open("ftp:x").err().unwrap().to_string();
    assert!(e.contains("files:") && e.contains("null:"), "{e}");
    let e = source::open("files:/definitely/not/here").err().unwrap().to_string();
    assert!(e.contains("not a folder"), "{e}");
    let dir = tempfile::tempdir().unwrap();
    let e = source::open(&format!("files:{}?lop=true", dir.path().display())).err().unwrap().to_string();
    assert!(e.contains("unknown option 'lop'") && e.contains("loop"), "{e}");
    let e = sink::open(&format!("files:{}?format=bmp", dir.path().display())).err().unwrap().to_string();
    assert!(e.contains("png, pgm, jpg or tiff"), "{e}");
    let mut n = sink::open("null:").unwrap();
    n.write_frame(&Frame::new(4, 4, PixelFormat::Mono8).unwrap(), None).unwrap();
    assert!(n.last_output().is_none());
}

fn synth(opts: &str) -> SynthSource {
    SynthSource::open(&format!("synth:?{opts}")).unwrap()
}

#[test]
fn synth_is_deterministic_and_animated() {
    let mut a = synth("width=160&height=120&frames=3&seed=5");
    let mut b = synth("width=160&height=120&frames=3&seed=5");
    let fa: Vec<Frame> = std::iter::from_fn(|| a.next_frame().unwrap()).collect();
    let fb: Vec<Frame> = std::iter::from_fn(|| b.next_frame().unwrap()).collect();
    assert_eq!(fa.len(), 3);
    assert_eq!(fa, fb, "same options must give the same bytes");
    assert_ne!(fa[0].data, fa[2].data, "the spacecraft spins: frames differ");
    assert_eq!(fa[2].pts_ns, 2 * 1_000_000_000 / 30 + 1); // round(2/30 s) in ns
    let mut c = synth("width=160&height=120&frames=3&seed=6");
    assert_ne!(c.next_frame().unwrap().unwrap().data, fa[0].data, "the seed changes the star field");
    // frames=0 is endless.
    let mut e = synth("width=32&height=32&frames=0&spin_dps=0");
    for _ in 0..200 {
        assert!(e.next_frame().unwrap().is_some());
    }
}

/// Fraction of samples at or below `v`, and count at full scale.
fn stats(f: &Frame) -> (f64, usize, usize) {
    let s = f.packed_samples_f32();
    let fs = f.full_scale();
    let dark = s.iter().filter(|v| **v <= 0.02 * fs).count() as f64 / s.len() as f64;
    let sat = s.iter().filter(|v| **v >= fs).count();
    let mid = s.iter().filter(|v| **v > 0.1 * fs && **v < 0.9 * fs).count();
    (dark, sat, mid)
}

#[test]
fn synth_has_dark_space_saturated_glints_and_a_lit_body() {
    for format in ["mono8", "mono16", "rgb8"] {
        let mut s = synth(&format!("width=320&height=240&format={format}&frames=1"));
        let f = s.next_frame().unwrap().unwrap();
        assert_eq!(f.format, PixelFormat::parse(format).unwrap());
        let (dark, sat, mid) = stats(&f);
        // Space dominates: most of the frame is within 2 % of black.
        assert!(dark > 0.5, "{format}: only {dark:.2} of the samples are dark");
        // Glints: cores of radius 2 px (≈13 px each), at least two fittings visible.
        let ch = f.channels();
        assert!(sat >= 2 * 12 * ch, "{format}: only {sat} samples at full scale");
        // The lit body and panels fill a real part of the frame with mid-level values.
        assert!(mid as f64 / (f.pixels() * ch) as f64 > 0.03, "{format}: body too small ({mid} mid samples)");
        // Saturated samples sit at the projected fittings.
        let pose = s.pose(0);
        let on_glint = s
            .glint_points()
            .iter()
            .filter_map(|p| s.project(&pose, *p))
            .filter(|&(x, y)| x >= 0.0 && y >= 0.0 && x < 320.0 && y < 240.0)
            .filter(|&(x, y)| f.get(x as usize, y as usize, 0) >= f.full_scale())
            .count();
        assert!(on_glint >= 2, "{format}: {on_glint} fittings glint at their projected position");
    }
}

#[test]
fn synth_earth_limb_is_bright_below_the_horizon() {
    let mut s = synth("width=200&height=150&frames=1&earth=true&stars=false");
    let f = s.next_frame().unwrap().unwrap();
    let mean = |y0: usize, y1: usize| {
        let mut sum = 0.0;
        for y in y0..y1 {
            for x in 0..20 {
                sum += f.get(x, y, 0);
            }
        }
        sum / ((y1 - y0) * 20) as f32
    };
    // Left edge, away from the spacecraft: space at the top, Earth at the bottom.
    let (top, bottom) = (mean(0, 20), mean(140, 150));
    assert!(top < 3.0, "space above the limb: {top}");
    assert!(bottom > 20.0, "the Earth below the limb: {bottom}");
    let mut no = synth("width=200&height=150&frames=1&earth=false&stars=false");
    let g = no.next_frame().unwrap().unwrap();
    assert_eq!(g.get(5, 145, 0), 0.0);
}

#[test]
fn synth_options_are_reported() {
    let s = synth("width=64&height=48&format=rgb8&frames=7&earth=true");
    let d = s.describe();
    assert!(d.contains("64x48 rgb8") && d.contains("7 frames") && d.contains("earth true"), "{d}");
    let c = SynthConfig { width: 64, height: 48, ..SynthConfig::default() };
    assert_eq!(SynthSource::new(c).config().height, 48);
}

#[test]
fn files_sink_keeps_input_names_and_writes_16bit() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = sink::open(&format!("files:{}/out", dir.path().display())).unwrap();
    let mut f =
        Frame::from_data(3, 2, 4, PixelFormat::Mono16, FrameData::U16(vec![1, 2, 3, 9, 65535, 0, 7, 9])).unwrap();
    f.seq = 12;
    s.write_frame(&f, Some("shot_12.jpg")).unwrap();
    let out = s.last_output().unwrap().to_string();
    assert!(out.ends_with("out/shot_12.png"), "{out}");
    let img = image::open(&out).unwrap().into_luma16();
    // Row padding (stride 4) is dropped.
    assert_eq!(img.as_raw(), &vec![1, 2, 3, 65535, 0, 7]);
    s.write_frame(&f, None).unwrap();
    assert!(s.last_output().unwrap().ends_with("frame_000012.png"));
    // No temporary files remain.
    let left: Vec<_> = std::fs::read_dir(dir.path().join("out")).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(left.len(), 2, "{left:?}");
}
