//! Invariants across the whole effect library (every effect of EFFECTS.md): identity at zero
//! strength, monotone response to the strength parameter, physical chain order, determinism on
//! 1 and 2 threads, and the channel shift measured by image registration. Per-effect physics
//! (charge conservation, noise statistics, geometry) is tested in each effect's file.

use faultcam::faults::chain::{Chain, FrameReport};
use faultcam::faults::kit::{bench_params, bench_scene};
use faultcam::faults::{EffectCtx, Outcome, Params, Stage, create, default_params, registry};
use faultcam::{Frame, PixelFormat, Rng};

fn params(name: &str, kv: &[(&str, f64)]) -> Params {
    let mut p = default_params(name).unwrap();
    for (k, v) in kv {
        p.set(k, *v).unwrap_or_else(|e| panic!("{name}: {e}"));
    }
    p
}

/// The zero-strength setting of every effect (EFFECTS.md names; model texts state each one).
const IDENTITY: &[(&str, &[(&str, f64)])] = &[
    ("lens_flare", &[("intensity", 0.0)]),
    ("stray_light", &[("amplitude_dn", 0.0)]),
    ("veiling_glare", &[("fraction", 0.0)]),
    ("vignetting", &[("strength", 0.0)]),
    ("defocus", &[("sigma_px", 0.0)]),
    ("motion_blur", &[("length_px", 0.0)]),
    ("channel_shift", &[("dx_r", 0.0), ("dy_r", 0.0), ("dx_b", 0.0), ("dy_b", 0.0)]),
    ("prnu", &[("sigma", 0.0)]),
    ("dark_current", &[("mean_dn", 0.0)]),
    ("hot_pixels", &[("rate", 0.0)]),
    ("cosmic_rays", &[("rate", 0.0)]),
    ("blooming", &[("full_well_fraction", 1.0), ("exposure_gain", 1.0)]),
    ("smear", &[("strength", 0.0)]),
    ("dead_pixels", &[("rate", 0.0)]),
    ("gaussian_noise", &[("sigma_dn", 0.0)]),
    ("row_noise", &[("sigma_dn", 0.0)]),
    ("vertical_glitch", &[("count", 0.0)]),
    ("horizontal_glitch", &[("count", 0.0)]),
    ("gain_offset", &[("gain", 1.0), ("offset_dn", 0.0)]),
    ("gamma", &[("gamma", 1.0)]),
    ("bit_flip", &[("rate", 0.0)]),
    ("frame_freeze", &[("frames", 0.0)]),
    ("frame_drop", &[("p", 0.0)]),
    ("frame_delay", &[("ms", 0.0)]),
    ("jitter", &[("ms", 0.0)]),
    ("reorder", &[("depth", 0.0)]),
];

/// Effects whose identity holds only in part, and why (tested in their own files).
const IDENTITY_EXCEPTIONS: &[(&str, &str)] = &[
    // Infinite gain is the identity; the largest gain (1e6 e-/DN) is exact for 8-bit only.
    ("shot_noise", "8-bit only: gain_e_per_dn = 1e6"),
    // DCT rounding: quality 100 is near, not exactly, the identity (jpeg.rs tests the bound).
    ("jpeg", "no exact identity"),
];

#[test]
fn zero_strength_is_the_identity_for_every_effect() {
    for r in registry::all() {
        let name = r.info.name;
        let set = IDENTITY.iter().find(|(n, _)| *n == name);
        let exception = IDENTITY_EXCEPTIONS.iter().find(|(n, _)| *n == name);
        assert!(set.is_some() ^ exception.is_some(), "{name}: add its zero-strength setting to IDENTITY");
        let (kv, formats): (&[(&str, f64)], &[PixelFormat]) = match (set, name) {
            (Some((_, kv)), _) => (kv, &[PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16]),
            (None, "shot_noise") => (&[("gain_e_per_dn", 1e6)], &[PixelFormat::Mono8, PixelFormat::Rgb8]),
            (None, _) => continue,
        };
        // Start from the visible bench parameters so that only the zero-strength setting matters.
        let mut p = bench_params(name).unwrap();
        for (k, v) in kv {
            p.set(k, *v).unwrap();
        }
        for &format in formats {
            let input = bench_scene(97, 61, format, 2).unwrap();
            let mut e = create(name).unwrap();
            for seq in 0..4 {
                let mut f = input.clone();
                f.seq = seq;
                let mut ctx = EffectCtx::new(3, seq, 1);
                let out = e.apply(&mut f, &p, &mut ctx).unwrap();
                assert_eq!(out, Outcome::Keep, "{name} {format}");
                assert_eq!(ctx.delay_ns, 0, "{name}: no added delay");
                let mut want = input.clone();
                want.seq = seq;
                assert!(f == want, "{name} {format} frame {seq}: zero strength changed the frame");
            }
        }
    }
}

/// Mean absolute difference between two frames (DN).
fn mad(a: &Frame, b: &Frame) -> f64 {
    let (x, y) = (a.packed_samples_f32(), b.packed_samples_f32());
    x.iter().zip(&y).map(|(p, q)| (p - q).abs() as f64).sum::<f64>() / x.len() as f64
}

#[test]
fn the_change_grows_with_the_strength_parameter() {
    // (effect, parameter, three values from weak to strong, extra settings)
    type Case = (&'static str, &'static str, [f64; 3], &'static [(&'static str, f64)]);
    let cases: &[Case] = &[
        ("lens_flare", "intensity", [0.02, 0.08, 0.3], &[]),
        ("stray_light", "amplitude_dn", [5.0, 30.0, 120.0], &[]),
        ("veiling_glare", "fraction", [0.01, 0.05, 0.3], &[]),
        ("vignetting", "strength", [0.1, 0.3, 0.8], &[]),
        ("defocus", "sigma_px", [0.5, 1.5, 4.0], &[]),
        ("motion_blur", "length_px", [2.0, 8.0, 30.0], &[]),
        ("channel_shift", "dx_r", [0.3, 1.0, 4.0], &[]),
        ("prnu", "sigma", [0.005, 0.02, 0.1], &[]),
        ("shot_noise", "gain_e_per_dn", [40.0, 4.0, 0.4], &[]),
        ("dark_current", "mean_dn", [1.0, 5.0, 25.0], &[]),
        ("hot_pixels", "rate", [1e-4, 1e-3, 1e-2], &[]),
        ("cosmic_rays", "rate", [1e-4, 4e-4, 1e-3], &[]),
        ("blooming", "full_well_fraction", [0.98, 0.9, 0.7], &[("exposure_gain", 1.2)]),
        ("smear", "strength", [0.001, 0.005, 0.02], &[("sat_level", 0.9)]),
        ("dead_pixels", "rate", [1e-4, 1e-3, 1e-2], &[]),
        ("gaussian_noise", "sigma_dn", [0.5, 3.0, 15.0], &[]),
        ("row_noise", "sigma_dn", [0.5, 3.0, 15.0], &[]),
        ("vertical_glitch", "count", [1.0, 4.0, 16.0], &[("max_offset_px", 30.0), ("max_band_px", 8.0)]),
        ("horizontal_glitch", "count", [1.0, 4.0, 16.0], &[("max_offset_px", 30.0), ("max_band_px", 8.0)]),
        ("gain_offset", "offset_dn", [1.0, 5.0, 30.0], &[]),
        ("gamma", "gamma", [1.1, 1.5, 3.0], &[]),
        ("jpeg", "quality", [95.0, 60.0, 10.0], &[]),
        ("bit_flip", "rate", [1e-4, 1e-3, 1e-2], &[]),
    ];
    let input = bench_scene(256, 160, PixelFormat::Rgb8, 4).unwrap();
    for (name, param, values, extra) in cases {
        let mut changes = Vec::new();
        for v in values {
            let mut p = params(name, extra);
            p.set(param, *v).unwrap();
            let mut f = input.clone();
            create(name).unwrap().apply(&mut f, &p, &mut EffectCtx::new(5, 0, 0)).unwrap();
            changes.push(mad(&f, &input));
        }
        assert!(changes[0] > 0.0, "{name}: the weakest setting changes the frame");
        assert!(changes[0] < changes[1] && changes[1] < changes[2], "{name}.{param} {values:?}: change {changes:?}");
    }
}

#[test]
fn the_full_chain_runs_in_physical_order() {
    let names: Vec<&str> = registry::all().iter().map(|r| r.info.name).collect();
    // Pushed in a scrambled order, the chain sorts by (stage, order).
    let mut scrambled = names.clone();
    let mut rng = Rng::new(9);
    for i in (1..scrambled.len()).rev() {
        scrambled.swap(i, rng.below(i as u64 + 1) as usize);
    }
    let mut chain = Chain::new(0);
    for n in &scrambled {
        chain.push(n, default_params(n).unwrap()).unwrap();
    }
    let got: Vec<&str> = chain.entries().iter().map(|e| e.name()).collect();
    assert_eq!(
        got,
        [
            // optics: light added by the lens, then focal-plane irradiance shaping, then geometry
            "lens_flare",
            "veiling_glare",
            "stray_light",
            "vignetting",
            "defocus",
            "motion_blur",
            "channel_shift",
            // sensor: photo-response, photon noise, dark and radiation charge, overflow, transfer
            "prnu",
            "shot_noise",
            "dark_current",
            "hot_pixels",
            "cosmic_rays",
            "blooming",
            "smear",
            "dead_pixels",
            // readout: analogue noise, readout glitches, transfer curve
            "gaussian_noise",
            "row_noise",
            "vertical_glitch",
            "horizontal_glitch",
            "gain_offset",
            "gamma",
            // transmission: compression, then errors and stream-level faults
            "jpeg",
            "bit_flip",
            "frame_freeze",
            "frame_drop",
            "frame_delay",
            "jitter",
            "reorder",
        ]
    );
    let stages: Vec<Stage> = chain.entries().iter().map(|e| e.stage()).collect();
    assert!(stages.windows(2).all(|w| w[0] <= w[1]));
    // The config index (part of every generator seed) is the push position, not the sorted one.
    let first = chain.entries().iter().find(|e| e.name() == scrambled[0]).unwrap();
    assert_eq!(first.index, 0);
}

#[test]
fn same_seed_same_bytes_on_one_and_two_threads_for_the_whole_library() {
    for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
        let input = bench_scene(200, 150, format, 6).unwrap();
        let run = |threads: usize| -> Vec<(Outcome, u64, Option<Frame>)> {
            rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                let mut chain = Chain::new(42);
                for r in registry::all() {
                    chain.push(r.info.name, bench_params(r.info.name).unwrap()).unwrap();
                }
                let mut report = FrameReport::default();
                (0..8)
                    .map(|seq| {
                        let mut f = input.clone();
                        f.seq = seq;
                        let out = chain.apply(&mut f, &mut report).unwrap();
                        (out, report.delay_ns, (out == Outcome::Keep).then_some(f))
                    })
                    .collect()
            })
        };
        let one = run(1);
        assert!(
            one.iter()
                .any(|o| o.2.as_ref().is_some_and(|f| f.as_u8() != input.as_u8() || f.as_u16() != input.as_u16()))
        );
        assert!(one == run(2), "{format}: output differs between 1 and 2 threads");
    }
}

/// Sub-pixel translation d that maps `reference` onto `moved` (moved(x) ≈ reference(x − d)),
/// by Lucas–Kanade: Gauss–Newton on the sum of squared differences with bilinear resampling,
/// over the interior (8 px margin).
fn register(reference: &[f64], moved: &[f64], w: usize, h: usize) -> (f64, f64) {
    let sample = |img: &[f64], x: f64, y: f64| -> f64 {
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as usize, y0 as usize);
        let at = |xx: usize, yy: usize| img[yy * w + xx];
        (1.0 - fy) * ((1.0 - fx) * at(x0, y0) + fx * at(x0 + 1, y0))
            + fy * ((1.0 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1))
    };
    let (mut dx, mut dy) = (0.0f64, 0.0f64);
    for _ in 0..30 {
        let (mut a11, mut a12, mut a22, mut b1, mut b2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for y in 8..h - 8 {
            for x in 8..w - 8 {
                let (sx, sy) = (x as f64 - dx, y as f64 - dy);
                let r = moved[y * w + x] - sample(reference, sx, sy);
                // d/d(dx) of reference(x - dx) = -gx.
                let gx = -(sample(reference, sx + 0.5, sy) - sample(reference, sx - 0.5, sy));
                let gy = -(sample(reference, sx, sy + 0.5) - sample(reference, sx, sy - 0.5));
                a11 += gx * gx;
                a12 += gx * gy;
                a22 += gy * gy;
                b1 += gx * r;
                b2 += gy * r;
            }
        }
        let det = a11 * a22 - a12 * a12;
        let (ux, uy) = ((a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det);
        dx += ux;
        dy += uy;
        if ux.abs() + uy.abs() < 1e-6 {
            break;
        }
    }
    (dx, dy)
}

#[test]
fn channel_shift_moves_red_and_blue_by_the_requested_amount_measured_by_registration() {
    // Smooth random texture (band-limited: sum of random sinusoids), identical in R, G and B.
    let (w, h) = (160usize, 120usize);
    let mut rng = Rng::new(12);
    let waves: Vec<(f64, f64, f64, f64)> = (0..12)
        .map(|_| {
            let k = 0.05 + 0.2 * rng.uniform();
            let t = rng.uniform() * std::f64::consts::TAU;
            (k * t.cos(), k * t.sin(), rng.uniform() * std::f64::consts::TAU, 8.0 + 8.0 * rng.uniform())
        })
        .collect();
    let mut input = Frame::new(w as u32, h as u32, PixelFormat::Rgb8).unwrap();
    for y in 0..h {
        for x in 0..w {
            let v = 128.0
                + waves.iter().map(|&(kx, ky, ph, a)| a * (kx * x as f64 + ky * y as f64 + ph).sin()).sum::<f64>();
            for c in 0..3 {
                input.set(x, y, c, v as f32);
            }
        }
    }
    let plane = |f: &Frame, c: usize| -> Vec<f64> {
        (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).map(|(x, y)| f.get(x, y, c) as f64).collect()
    };
    for shift in [[0.37, -0.81, -1.26, 0.55], [2.5, 1.75, -0.2, -3.1]] {
        let mut f = input.clone();
        let p =
            params("channel_shift", &[("dx_r", shift[0]), ("dy_r", shift[1]), ("dx_b", shift[2]), ("dy_b", shift[3])]);
        create("channel_shift").unwrap().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        let g = plane(&f, 1);
        assert_eq!(g, plane(&input, 1), "green is the reference and is untouched");
        let (rx, ry) = register(&g, &plane(&f, 0), w, h);
        let (bx, by) = register(&g, &plane(&f, 2), w, h);
        // +dx moves content right, +dy down. Rounding to whole DN on a texture of ~30 DN
        // contrast limits registration to a few hundredths of a pixel.
        for (got, want, what) in
            [(rx, shift[0], "dx_r"), (ry, shift[1], "dy_r"), (bx, shift[2], "dx_b"), (by, shift[3], "dy_b")]
        {
            assert!((got - want).abs() < 0.03, "{what}: registered {got:.4} px, requested {want} px");
        }
    }
}
