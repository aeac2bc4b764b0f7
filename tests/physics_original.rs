//! Integration tests across the eight faults of the original study: physical chain order,
//! determinism on 1 and 2 threads, and a timing loop (ignored by default):
//! `cargo test --release --test physics_original -- --ignored --nocapture`.

use faultcam::faults::{EffectCtx, create, default_params, registry};
use faultcam::{Frame, PixelFormat, Rng};
use std::time::Instant;

/// The effects this file covers, with visible, study-like parameters.
fn study_effects() -> Vec<(&'static str, Vec<(&'static str, f64)>)> {
    vec![
        ("lens_flare", vec![("ghosts", 5.0), ("intensity", 0.08)]),
        ("channel_shift", vec![("dx_r", 1.3), ("dy_r", -0.6), ("dx_b", -1.1), ("dy_b", 0.8)]),
        ("dark_current", vec![("mean_dn", 3.0), ("hot_pixel_rate", 5e-4)]),
        ("blooming", vec![("full_well_fraction", 0.85), ("spread_px", 2.0), ("exposure_gain", 1.0)]),
        ("gaussian_noise", vec![("sigma_dn", 3.0)]),
        ("vertical_glitch", vec![("count", 3.0), ("max_offset_px", 24.0)]),
        ("horizontal_glitch", vec![("count", 3.0), ("max_offset_px", 24.0)]),
        ("smear", vec![("strength", 0.004), ("sat_level", 0.85)]),
        ("jpeg", vec![("quality", 75.0)]),
    ]
}

fn registered(name: &str) -> bool {
    registry::find(name).is_some()
}

/// A natural-looking test scene: smooth gradients, texture, dark background and a few
/// saturated glints (like the synthetic spacecraft scene).
fn scene(w: u32, h: u32, fmt: PixelFormat, seed: u64) -> Frame {
    let mut f = Frame::new(w, h, fmt).unwrap();
    let fs = fmt.full_scale();
    let mut r = Rng::new(seed);
    let (cx, cy) = (w as f32 * 0.45, h as f32 * 0.55);
    let rad = w.min(h) as f32 * 0.3;
    let glints: Vec<(f32, f32)> =
        (0..6).map(|_| (r.range(0.1, 0.9) as f32 * w as f32, r.range(0.1, 0.9) as f32 * h as f32)).collect();
    for y in 0..h as usize {
        for x in 0..w as usize {
            let (dx, dy) = (x as f32 - cx, y as f32 - cy);
            let d = (dx * dx + dy * dy).sqrt();
            let body = if d < rad { 0.35 + 0.25 * (dx / rad) + 0.05 * ((x / 7 + y / 5) % 2) as f32 } else { 0.02 };
            for c in 0..fmt.channels() {
                let mut v = body * (1.0 - 0.1 * c as f32) + 0.02 * r.uniform_f32();
                for &(gx, gy) in &glints {
                    let g2 = (x as f32 - gx).powi(2) + (y as f32 - gy).powi(2);
                    v += 1.5 * (-g2 / 8.0).exp();
                }
                f.set(x, y, c, v.min(1.0) * fs);
            }
        }
    }
    f
}

fn params(name: &str, kv: &[(&str, f64)]) -> faultcam::Params {
    let mut p = default_params(name).unwrap();
    for (k, v) in kv {
        p.set(k, *v).unwrap();
    }
    p
}

#[test]
fn chain_applies_the_study_effects_in_physical_order() {
    let mut chain = faultcam::Chain::new(1);
    // Push in reverse physical order: the chain must re-sort.
    let mut effects = study_effects();
    effects.retain(|(n, _)| registered(n));
    for (name, kv) in effects.iter().rev() {
        chain.push(name, params(name, kv)).unwrap();
    }
    let keys: Vec<_> = chain.entries().iter().map(|e| (e.stage(), e.effect.info().order)).collect();
    let mut sorted = keys.clone();
    sorted.sort();
    assert_eq!(keys, sorted);
    let names: Vec<_> = chain.entries().iter().map(|e| e.name()).collect();
    let pos = |n: &str| names.iter().position(|m| *m == n);
    for (a, b) in [
        ("lens_flare", "channel_shift"),
        ("channel_shift", "dark_current"),
        ("dark_current", "blooming"),
        ("blooming", "smear"),
        ("smear", "gaussian_noise"),
        ("gaussian_noise", "vertical_glitch"),
        ("vertical_glitch", "horizontal_glitch"),
        ("horizontal_glitch", "jpeg"),
    ] {
        if let (Some(i), Some(j)) = (pos(a), pos(b)) {
            assert!(i < j, "{a} must run before {b}: {names:?}");
        }
    }
}

#[test]
fn same_seed_gives_identical_bytes_on_one_and_two_threads() {
    for fmt in [PixelFormat::Mono8, PixelFormat::Mono16, PixelFormat::Rgb8] {
        let input = scene(320, 200, fmt, 3);
        let run = |threads: usize| -> Frame {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let mut chain = faultcam::Chain::new(42);
                for (name, kv) in study_effects().iter().filter(|(n, _)| registered(n)) {
                    chain.push(name, params(name, kv)).unwrap();
                }
                let mut f = input.clone();
                f.seq = 17;
                let mut report = faultcam::FrameReport::default();
                chain.apply(&mut f, &mut report).unwrap();
                f
            })
        };
        let one = run(1);
        let two = run(2);
        assert_ne!(one, input, "{fmt}: the chain changed the frame");
        assert_eq!(one, two, "{fmt}: output differs between 1 and 2 threads");
    }
}

/// CPU time of the calling thread in ns (Linux `/proc/thread-self/schedstat`, first field), so
/// timings are not inflated by other processes competing for the cores; 0 where unavailable.
fn thread_cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
        .unwrap_or(0)
}

/// Median time per effect and for the whole chain at 1920x1200, on one rayon thread.
#[test]
#[ignore]
fn timing_1920x1200_one_core() {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    pool.install(|| {
        for fmt in [PixelFormat::Mono8, PixelFormat::Rgb8] {
            let input = scene(1920, 1200, fmt, 1);
            let mut total = 0.0;
            for (name, kv) in study_effects().iter().filter(|(n, _)| registered(n)) {
                let mut e = create(name).unwrap();
                let p = params(name, kv);
                let mut f = input.clone();
                let mut times = Vec::new();
                for i in 0..15u64 {
                    f.copy_from(&input);
                    f.seq = i;
                    let mut ctx = EffectCtx::new(1, i, 0);
                    let (t, c) = (Instant::now(), thread_cpu_ns());
                    e.apply(&mut f, &p, &mut ctx).unwrap();
                    times.push(((thread_cpu_ns() - c) as f64 * 1e-6, t.elapsed().as_secs_f64() * 1e3));
                }
                times.sort_by(|a, b| a.0.total_cmp(&b.0));
                let (med, wall) = times[times.len() / 2];
                total += med;
                println!("{fmt} {name:18} median cpu {med:7.3} ms (wall {wall:7.3} ms)  min cpu {:7.3} ms", times[0].0);
            }
            let mut chain = faultcam::Chain::new(1);
            for (name, kv) in study_effects().iter().filter(|(n, _)| registered(n)) {
                chain.push(name, params(name, kv)).unwrap();
            }
            let mut report = faultcam::FrameReport::default();
            let mut f = input.clone();
            let mut times = Vec::new();
            for i in 0..15u64 {
                f.copy_from(&input);
                f.seq = i;
                let (t, c) = (Instant::now(), thread_cpu_ns());
                chain.apply(&mut f, &mut report).unwrap();
                times.push(((thread_cpu_ns() - c) as f64 * 1e-6, t.elapsed().as_secs_f64() * 1e3));
            }
            times.sort_by(|a, b| a.0.total_cmp(&b.0));
            let (med, wall) = times[times.len() / 2];
            println!("{fmt} chain median cpu {med:.3} ms (wall {wall:.3} ms; sum of effect medians {total:.3} ms)");
        }
    });
}
