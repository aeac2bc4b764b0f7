//! The evaluation library: bright zones against OpenCV's contours, and the blooming validation
//! protocol on generated images in temporary folders.

#![cfg(feature = "opencv")]

mod support_eval;

use faultcam::eval::blooming::{self, BloomingConfig, Generated};
use faultcam::eval::zones;
use faultcam::faults;
use faultcam::metrics::Grey;
use faultcam::rng::Rng;
use opencv::core::{Mat, Point, Vector};
use opencv::prelude::*;
use support_eval::*;

/// Random filled discs and rectangles at 250..=255 on a background below 250, some touching
/// the image border, some merging into one region.
fn blob_image(w: usize, h: usize, seed: u64) -> Grey {
    let mut rng = Rng::new(seed);
    let mut d: Vec<f32> = (0..w * h).map(|_| rng.range(0.0, 249.0) as f32).collect();
    for _ in 0..12 {
        let v = rng.range(250.0, 255.0) as f32;
        let (cx, cy) = (rng.range(-3.0, w as f64 + 3.0), rng.range(-3.0, h as f64 + 3.0));
        let r = rng.range(0.5, 6.0);
        let disc = rng.bernoulli(0.5);
        for y in 0..h {
            for x in 0..w {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                let inside = if disc { dx * dx + dy * dy <= r * r } else { dx.abs() <= r && dy.abs() <= 0.6 * r };
                if inside {
                    d[y * w + x] = v;
                }
            }
        }
    }
    Grey::new(w, h, d).unwrap()
}

/// Bounding boxes of OpenCV's outer contours of `g >= level`, as (x0, y0, x1, y1).
fn opencv_boxes(g: &Grey, level: f32) -> Vec<(usize, usize, usize, usize)> {
    let mask: Vec<u8> = g.data.iter().map(|&v| if v >= level { 255 } else { 0 }).collect();
    let m = Mat::new_rows_cols_with_data(g.height as i32, g.width as i32, &mask).unwrap().try_clone().unwrap();
    let mut contours = Vector::<Vector<Point>>::new();
    opencv::imgproc::find_contours(
        &m,
        &mut contours,
        opencv::imgproc::RETR_EXTERNAL,
        opencv::imgproc::CHAIN_APPROX_NONE,
        Point::new(0, 0),
    )
    .unwrap();
    let mut boxes: Vec<_> = contours
        .iter()
        .map(|c| {
            let r = opencv::imgproc::bounding_rect(&c).unwrap();
            (r.x as usize, r.y as usize, (r.x + r.width) as usize, (r.y + r.height) as usize)
        })
        .collect();
    boxes.sort();
    boxes
}

#[test]
fn bright_zone_boxes_equal_opencv_contour_bounding_boxes() {
    let mut compared = 0;
    for seed in 0..16 {
        let g = blob_image(64, 48, seed);
        let mut ours: Vec<_> = zones::bright_zones(&g, 250.0, 1).iter().map(|z| (z.x0, z.y0, z.x1, z.y1)).collect();
        ours.sort();
        let cv = opencv_boxes(&g, 250.0);
        assert!(!cv.is_empty(), "seed {seed}: no blob drawn");
        assert_eq!(ours, cv, "seed {seed}");
        compared += cv.len();
    }
    assert!(compared > 50, "too few zones compared: {compared}");
}

fn config() -> BloomingConfig {
    let mut p = faults::default_params("blooming").unwrap();
    p.set("full_well_fraction", 1.0).unwrap();
    p.set("exposure_gain", 3.0).unwrap();
    BloomingConfig {
        min_crop: 48,
        orb: faultcam::metrics::OrbConfig { patch_size: 15, edge_threshold: 15, ..Default::default() },
        blooming: Some(p),
        max_generated: 50,
        ..BloomingConfig::default()
    }
}

#[test]
fn protocol_selects_crops_scores_and_is_deterministic() {
    let tmp = tempfile::tempdir().unwrap();
    let (gen_dir, real_dir) = (tmp.path().join("gen"), tmp.path().join("real"));
    std::fs::create_dir_all(&gen_dir).unwrap();
    std::fs::create_dir_all(&real_dir).unwrap();
    write_synth(&gen_dir, 4, 160, 100);
    // Not selected: 9 px at 250 (needs 10); selected: 10 px at 250 (exactly the threshold).
    let mut few = vec![20u8; 160 * 100];
    few[5000..5009].fill(250);
    save_grey(&gen_dir.join("gen_few.png"), 160, 100, few.clone());
    few[5009] = 250;
    save_grey(&gen_dir.join("gen_just.png"), 160, 100, few);
    write_reals(&real_dir, 3, 160, 100);
    // A real image with nothing at 250 is skipped with its reason.
    save_grey(&real_dir.join("real_dark.png"), 160, 100, vec![40; 160 * 100]);

    let cfg = config();
    let out1 = tmp.path().join("out1");
    let r = blooming::run_protocol(&Generated::Dir(gen_dir.clone()), &real_dir, &out1, &cfg).unwrap();
    assert_eq!(r.generated_read, 6);
    let skipped: Vec<&str> = r.generated_skipped.iter().map(|s| s.0.as_str()).collect();
    assert_eq!(skipped, ["gen_few.png"], "{:?}", r.generated_skipped);
    assert!(r.generated_skipped[0].1.contains("9 px"), "{:?}", r.generated_skipped);
    assert_eq!(r.per_image.len(), 5);
    assert_eq!(r.real_used.len(), 3);
    assert_eq!(r.real_skipped.len(), 1);
    assert_eq!(r.real_skipped[0].0, "real_dark.png");
    // Common shape: the smallest crop side (here the 48 px floor or a larger zone).
    let all = r.per_image.iter().map(|p| &p.crop).chain(&r.real_used);
    let (cw, ch) = all.fold((usize::MAX, usize::MAX), |(w, h), c| (w.min(c.crop.width()), h.min(c.crop.height())));
    assert_eq!(r.crop_shape, (cw, ch));
    assert!(cw >= 48 && ch >= 48, "{:?}", r.crop_shape);
    for p in &r.per_image {
        let c = &p.crop;
        assert!(c.crop.x0 <= c.zone.x0 && c.crop.x1 >= c.zone.x1 && c.crop.y0 <= c.zone.y0 && c.crop.y1 >= c.zone.y1);
        for m in [&p.bloomed, &p.control] {
            assert_eq!(m.accepted, blooming::accept(m.fqi, m.hist_corr, cfg.fqi_min, cfg.corr_min));
            assert!(m.hist_corr <= 1.0 + 1e-12 && m.hist_corr >= -1.0 - 1e-12);
            assert_eq!(m.fqi.is_some(), m.matches > 0, "{m:?}");
        }
    }
    // Blooming at three times the exposure with the full well at full scale spreads the
    // saturation of the synthetic glints: the bloomed crops are brighter than the controls.
    let synth: Vec<_> = r.per_image.iter().filter(|p| p.crop.name.starts_with("gen_0")).collect();
    assert_eq!(synth.len(), 4);
    let (b, c) = (r.bloomed.bright_fraction.unwrap(), r.control.bright_fraction.unwrap());
    assert!(b.mean > 2.0 * c.mean, "bloomed {b:?} control {c:?}");
    // Summary counts.
    for arm in [&r.bloomed, &r.control] {
        assert_eq!(arm.total, 5);
        assert!((arm.acceptance_rate - arm.accepted as f64 / 5.0).abs() < 1e-12);
        assert_eq!(arm.fqi.unwrap().n, 5);
    }
    // Files.
    for f in ["report.json", "summary.txt", "fqi_hist.png", "hist_corr_hist.png", "grey_hist.png"] {
        assert!(out1.join(f).is_file(), "{f}");
    }
    let crops = std::fs::read_dir(out1.join("crops")).unwrap().count();
    assert_eq!(crops, 2 * 5 + 3);
    let crop = image::open(out1.join("crops/gen_gen_000_bloomed.png")).unwrap();
    assert_eq!((crop.width() as usize, crop.height() as usize), r.crop_shape);

    // Same inputs and seed: identical per-image results.
    let out2 = tmp.path().join("out2");
    let r2 = blooming::run_protocol(&Generated::Dir(gen_dir), &real_dir, &out2, &cfg).unwrap();
    assert_eq!(serde_json::to_string(&r.per_image).unwrap(), serde_json::to_string(&r2.per_image).unwrap());
}

#[test]
fn protocol_reads_a_source_uri_and_names_what_is_missing() {
    let tmp = tempfile::tempdir().unwrap();
    let real_dir = tmp.path().join("real");
    std::fs::create_dir_all(&real_dir).unwrap();
    write_reals(&real_dir, 2, 120, 80);
    let cfg = BloomingConfig { max_generated: 3, ..config() };
    let g = Generated::parse("synth:?width=120&height=80&frames=0&spin_dps=30");
    assert!(matches!(g, Generated::Uri(_)));
    // Endless source: stops at max_generated.
    let r = blooming::run_protocol(&g, &real_dir, &tmp.path().join("o"), &cfg).unwrap();
    assert_eq!(r.generated_read, 3);

    // No real image passes the name filter: the error names the folder and the filter.
    let cfg2 = BloomingConfig { real_include: vec!["sunlamp".into()], ..cfg.clone() };
    let e = blooming::run_protocol(&g, &real_dir, &tmp.path().join("o2"), &cfg2).unwrap_err().to_string();
    assert!(e.contains(&real_dir.display().to_string()) && e.contains("'sunlamp'"), "{e}");
    // No generated image bright enough.
    let dark = tmp.path().join("dark");
    std::fs::create_dir_all(&dark).unwrap();
    save_grey(&dark.join("a.png"), 64, 64, vec![100; 64 * 64]);
    let e = blooming::run_protocol(&Generated::Dir(dark.clone()), &real_dir, &tmp.path().join("o3"), &cfg)
        .unwrap_err()
        .to_string();
    assert!(e.contains(&dark.display().to_string()) && e.contains("250"), "{e}");
}
