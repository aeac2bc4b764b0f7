//! Metrics against hand-computed values and against OpenCV's own implementations.

use faultcam::frame::{Frame, FrameData, PixelFormat};
use faultcam::metrics::{self, Grey, MetricsError};
use faultcam::rng::Rng;
use opencv::prelude::*;

/// A scene with corners for ORB: random grey rectangles on a mid-grey background.
fn rect_scene(w: usize, h: usize, seed: u64) -> Grey {
    let mut rng = Rng::new(seed);
    let mut d = vec![90.0f32; w * h];
    for _ in 0..40 {
        let (rw, rh) = (4 + rng.below(w as u64 / 5) as usize, 4 + rng.below(h as u64 / 5) as usize);
        let (x0, y0) = (rng.below((w - rw) as u64) as usize, rng.below((h - rh) as u64) as usize);
        let v = rng.below(256) as f32;
        for y in y0..y0 + rh {
            d[y * w + x0..y * w + x0 + rw].fill(v);
        }
    }
    Grey::new(w, h, d).unwrap()
}

fn with_noise(g: &Grey, sigma: f64, seed: u64) -> Grey {
    let mut rng = Rng::new(seed);
    Grey::new(
        g.width,
        g.height,
        g.data.iter().map(|&v| (v as f64 + sigma * rng.normal()).clamp(0.0, 255.0) as f32).collect(),
    )
    .unwrap()
}

#[test]
fn fqi_is_one_for_identical_images_and_undefined_without_features() {
    let a = rect_scene(160, 120, 1);
    let f = metrics::fqi_with(&a, &a, &Default::default()).unwrap();
    assert!(f.keypoints_a > 20, "too few keypoints for the test to mean anything: {f:?}");
    assert_eq!(f.value, Some(1.0));
    assert_eq!(f.matches, f.keypoints_a, "cross-check on identical descriptors matches every keypoint");
    // A flat image has no corner: no keypoint, FQI undefined (None), never a made-up number.
    let flat = Grey::new(160, 120, vec![128.0; 160 * 120]).unwrap();
    let f = metrics::fqi_with(&a, &flat, &Default::default()).unwrap();
    assert_eq!((f.value, f.keypoints_b, f.matches), (None, 0, 0));
    assert_eq!(metrics::fqi(&flat, &flat).unwrap(), None);
}

#[test]
fn fqi_falls_with_noise_and_is_lowest_for_unrelated_images() {
    let a = rect_scene(160, 120, 2);
    let mild = metrics::fqi(&a, &with_noise(&a, 3.0, 9)).unwrap().unwrap();
    let strong = metrics::fqi(&a, &with_noise(&a, 25.0, 9)).unwrap().unwrap();
    let other = metrics::fqi(&a, &rect_scene(160, 120, 77)).unwrap().unwrap();
    assert!(mild < 1.0 && mild > strong && strong > other, "mild {mild} strong {strong} unrelated {other}");
    // Unrelated 256-bit descriptors differ in about half their bits; cross-checked best matches
    // are closer than that, but far from identical.
    assert!(other > 0.5 && other < 0.85, "unrelated {other}");
}

/// Cross-checked brute-force Hamming matching written out in Rust, on OpenCV's descriptors:
/// the FQI must equal 1 - mean distance / 256 of the mutual nearest neighbours.
#[test]
fn fqi_equals_mutual_nearest_neighbour_hamming_mean() {
    let a = rect_scene(160, 120, 3);
    let b = with_noise(&a, 12.0, 4);
    let cfg = metrics::OrbConfig::default();
    let (fa, fb) = (metrics::orb_features(&a, &cfg).unwrap(), metrics::orb_features(&b, &cfg).unwrap());
    let (da, db) = (fa.descriptors().unwrap(), fb.descriptors().unwrap());
    let ham = |x: &[u8; 32], y: &[u8; 32]| x.iter().zip(y).map(|(p, q)| (p ^ q).count_ones()).sum::<u32>();
    let nearest = |x: &[u8; 32], set: &[[u8; 32]]| (0..set.len()).min_by_key(|&j| (ham(x, &set[j]), j)).unwrap();
    let mut dists = Vec::new();
    for (i, x) in da.iter().enumerate() {
        let j = nearest(x, &db);
        if nearest(&db[j], &da) == i {
            dists.push(ham(x, &db[j]) as f32);
        }
    }
    let expected = metrics::fqi_from_distances(&dists).unwrap();
    let got = fa.fqi(&fb).unwrap();
    assert_eq!(got.matches, dists.len());
    assert!((got.value.unwrap() - expected).abs() < 1e-9, "opencv {got:?} vs rust {expected}");
    assert!(expected < 1.0);
}

/// Frames reach OpenCV through `Grey`: padding skipped, 16-bit scaled by 1/257, RGB to luma.
#[test]
fn frame_conversion_to_opencv_handles_stride_depth_and_colour() {
    let g = rect_scene(160, 120, 5);
    let bytes = g.to_u8();
    let (w, h) = (160usize, 120usize);
    // Mono8 with 7 samples of padding per row, padding filled with garbage.
    let stride = w + 7;
    let mut padded = vec![255u8; stride * h];
    for y in 0..h {
        padded[y * stride..y * stride + w].copy_from_slice(&bytes[y * w..(y + 1) * w]);
    }
    let f8 = Frame::from_data(w as u32, h as u32, stride, PixelFormat::Mono8, FrameData::U8(padded)).unwrap();
    let f16 = Frame::from_data(
        w as u32,
        h as u32,
        w,
        PixelFormat::Mono16,
        FrameData::U16(bytes.iter().map(|&v| v as u16 * 257).collect()),
    )
    .unwrap();
    let frgb = Frame::from_data(
        w as u32,
        h as u32,
        3 * w,
        PixelFormat::Rgb8,
        FrameData::U8(bytes.iter().flat_map(|&v| [v, v, v]).collect()),
    )
    .unwrap();
    for f in [&f8, &f16, &frgb] {
        let gg = Grey::from_frame(f);
        assert_eq!(gg.to_u8(), bytes, "{}", f.format);
        let mat = metrics::grey_to_mat(&gg).unwrap();
        assert_eq!((mat.cols(), mat.rows(), mat.typ()), (w as i32, h as i32, opencv::core::CV_8UC1));
        assert_eq!(mat.data_bytes().unwrap(), &bytes[..]);
        assert_eq!(metrics::fqi(&g, &gg).unwrap(), Some(1.0));
    }
}

fn hist_mat(h: &[f64; 256]) -> opencv::core::Mat {
    let v: Vec<f32> = h.iter().map(|&x| x as f32).collect();
    opencv::core::Mat::from_slice(&v).unwrap().try_clone().unwrap()
}

#[test]
fn histogram_comparisons_match_opencv_compare_hist() {
    use opencv::imgproc::{HISTCMP_BHATTACHARYYA, HISTCMP_CORREL, compare_hist};
    let scenes = [rect_scene(64, 48, 10), rect_scene(64, 48, 11), with_noise(&rect_scene(64, 48, 10), 20.0, 3)];
    for a in &scenes {
        for b in &scenes {
            let (ha, hb) = (metrics::histogram(a), metrics::histogram(b));
            let (ma, mb) = (hist_mat(&ha), hist_mat(&hb));
            let cv_corr = compare_hist(&ma, &mb, HISTCMP_CORREL).unwrap();
            let cv_bh = compare_hist(&ma, &mb, HISTCMP_BHATTACHARYYA).unwrap();
            // OpenCV works on the f32 copies: agreement to f32 precision.
            assert!((metrics::hist_correlation(a, b) - cv_corr).abs() < 1e-5, "corr {cv_corr}");
            assert!((metrics::bhattacharyya(a, b) - cv_bh).abs() < 1e-4, "bhatt {cv_bh}");
        }
    }
    // And OpenCV's calcHist gives the same normalised histogram.
    let g = &scenes[2];
    let bytes = g.to_u8();
    let m = opencv::core::Mat::new_rows_cols_with_data(g.height as i32, g.width as i32, &bytes).unwrap();
    let mut imgs = opencv::core::Vector::<opencv::core::Mat>::new();
    imgs.push(m.try_clone().unwrap());
    let mut hist = opencv::core::Mat::default();
    opencv::imgproc::calc_hist(
        &imgs,
        &opencv::core::Vector::from_slice(&[0]),
        &opencv::core::no_array(),
        &mut hist,
        &opencv::core::Vector::from_slice(&[256]),
        &opencv::core::Vector::from_slice(&[0.0f32, 256.0]),
        false,
    )
    .unwrap();
    let ours = metrics::histogram(g);
    for (k, o) in ours.iter().enumerate() {
        let c = *hist.at::<f32>(k as i32).unwrap() as f64 / bytes.len() as f64;
        assert!((c - o).abs() < 1e-12, "bin {k}");
    }
}

#[test]
fn otsu_matches_opencv_threshold() {
    use opencv::imgproc::{THRESH_BINARY, THRESH_OTSU, threshold};
    let mut rng = Rng::new(42);
    for case in 0..12u64 {
        // Bimodal noisy images with random modes, weights and widths, plus plain scenes.
        let (w, h) = (64usize, 48usize);
        let g = if case < 8 {
            let (m0, m1) = (rng.range(10.0, 120.0), rng.range(130.0, 250.0));
            let p = rng.range(0.1, 0.9);
            let s = rng.range(2.0, 25.0);
            Grey::new(
                w,
                h,
                (0..w * h)
                    .map(|_| {
                        let m = if rng.bernoulli(p) { m0 } else { m1 };
                        (m + s * rng.normal()).clamp(0.0, 255.0) as f32
                    })
                    .collect(),
            )
            .unwrap()
        } else {
            rect_scene(w, h, case)
        };
        let bytes = g.to_u8();
        let src = opencv::core::Mat::new_rows_cols_with_data(h as i32, w as i32, &bytes).unwrap();
        let mut dst = opencv::core::Mat::default();
        let t = threshold(&src, &mut dst, 0.0, 255.0, THRESH_BINARY | THRESH_OTSU).unwrap();
        assert_eq!(metrics::otsu_threshold(&g) as f64, t, "case {case}");
    }
}

#[test]
fn compare_reports_every_metric_and_rejects_size_mismatch() {
    let a = rect_scene(160, 120, 6);
    let m = metrics::compare(&a, &a).unwrap();
    assert_eq!((m.rmse, m.psnr, m.fqi, m.spi), (0.0, f64::INFINITY, Some(1.0), 1.0));
    assert!((m.ssim - 1.0).abs() < 1e-12 && (m.hist_corr - 1.0).abs() < 1e-12 && m.bhattacharyya < 1e-6);
    let b = with_noise(&a, 8.0, 1);
    let m = metrics::compare(&a, &b).unwrap();
    // Clipping at 0/255 shrinks the error a little below sigma: stated bound 8 +- 1 DN.
    assert!((m.rmse - 8.0).abs() < 1.0, "{m:?}");
    assert!(m.ssim < 0.95 && m.ssim > 0.2, "{m:?}");
    let c = rect_scene(120, 160, 6);
    assert!(matches!(metrics::compare(&a, &c), Err(MetricsError::SizeMismatch { .. })));
}
