//! Criterion benchmarks: one group per effect (every registered effect, with the visible
//! parameters of `faults::kit::bench_params`) and one for the eight-fault chain of the original
//! study (`hil/campaigns/original8.toml`), at 1280x720, 1920x1200 and 3840x2160, Mono8 and Rgb8,
//! on a seeded synthetic scene (the `synth:` spacecraft, as `faultcam bench`;
//! `FAULTCAM_BENCH_SCENE=stress` for the over-exposed stress scene); throughput in pixels.
//!
//! `cargo bench --bench effects` measures all sizes. Effects run inside a rayon pool of
//! `FAULTCAM_BENCH_THREADS` threads (default 1: one core). Each iteration is one frame with a new
//! `seq` (new noise); the copy of the input into the frame is not timed.
//! Under `cargo test` (test mode: no `--bench` argument) each benchmark runs once on a small
//! frame (160x100) so CI stays fast; `FAULTCAM_BENCH_FULL=1` runs the full sizes there too.
//! `FAULTCAM_BENCH_SIZES=1920x1200,...` overrides the sizes in either mode.
//! Latency percentiles per frame (p50/p99/max): `faultcam bench` (see BENCHMARKS.md).

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use faultcam::faults::chain::{Chain, FrameReport};
use faultcam::faults::kit::{Scene, bench_params};
use faultcam::faults::{EffectCtx, create, registry};
use faultcam::{FaultConfig, Frame, PixelFormat};
use std::time::{Duration, Instant};

const FULL_SIZES: &[(u32, u32)] = &[(1280, 720), (1920, 1200), (3840, 2160)];
const TEST_SIZES: &[(u32, u32)] = &[(160, 100)];
const FORMATS: &[PixelFormat] = &[PixelFormat::Mono8, PixelFormat::Rgb8];

fn sizes() -> Vec<(u32, u32)> {
    if let Ok(s) = std::env::var("FAULTCAM_BENCH_SIZES") {
        return s
            .split(',')
            .filter_map(|t| t.split_once('x'))
            .filter_map(|(w, h)| Some((w.trim().parse().ok()?, h.trim().parse().ok()?)))
            .collect();
    }
    let benchmarking = std::env::args().any(|a| a == "--bench");
    if benchmarking || std::env::var_os("FAULTCAM_BENCH_FULL").is_some() {
        FULL_SIZES.to_vec()
    } else {
        TEST_SIZES.to_vec()
    }
}

fn scene() -> Scene {
    std::env::var("FAULTCAM_BENCH_SCENE").ok().and_then(|s| Scene::parse(&s)).unwrap_or(Scene::Spacecraft)
}

fn pool() -> rayon::ThreadPool {
    let n = std::env::var("FAULTCAM_BENCH_THREADS").ok().and_then(|s| s.parse().ok()).unwrap_or(1);
    rayon::ThreadPoolBuilder::new().num_threads(n).build().expect("rayon pool")
}

fn configure(group: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>) {
    group.sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(2));
}

fn effects(c: &mut Criterion) {
    let pool = pool();
    let sizes = sizes();
    let inputs: Vec<Frame> = sizes
        .iter()
        .flat_map(|&(w, h)| FORMATS.iter().map(move |&f| scene().render(w, h, f).expect("scene")))
        .collect();
    for r in registry::all() {
        let name = r.info.name;
        let params = bench_params(name).expect("bench params");
        let mut group = c.benchmark_group(name);
        configure(&mut group);
        for input in &inputs {
            let id = BenchmarkId::new(input.format.name(), format!("{}x{}", input.width, input.height));
            group.throughput(Throughput::Elements(input.pixels() as u64));
            let mut effect = create(name).expect("registered");
            let mut frame = input.clone();
            let mut seq = 0u64;
            group.bench_function(id, |b| {
                b.iter_custom(|iters| {
                    pool.install(|| {
                        let mut total = Duration::ZERO;
                        for _ in 0..iters {
                            frame.copy_from(input);
                            frame.seq = seq;
                            seq += 1;
                            let mut ctx = EffectCtx::new(1, frame.seq, 0);
                            let t = Instant::now();
                            let out = effect.apply(&mut frame, &params, &mut ctx).expect("effect");
                            total += t.elapsed();
                            std::hint::black_box(out);
                        }
                        total
                    })
                })
            });
        }
        group.finish();
    }
}

fn chain_original8(c: &mut Criterion) {
    let pool = pool();
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("hil/campaigns/original8.toml");
    let cfg = FaultConfig::load(&path).expect("hil/campaigns/original8.toml");
    let mut group = c.benchmark_group("chain_original8");
    configure(&mut group);
    for (w, h) in sizes() {
        for &format in FORMATS {
            let input = scene().render(w, h, format).expect("scene");
            let mut chain = Chain::from_config(&cfg).expect("chain");
            let mut frame = input.clone();
            let mut report = FrameReport::default();
            let mut seq = 0u64;
            group.throughput(Throughput::Elements(input.pixels() as u64));
            group.bench_function(BenchmarkId::new(format.name(), format!("{w}x{h}")), |b| {
                b.iter_custom(|iters| {
                    pool.install(|| {
                        let mut total = Duration::ZERO;
                        for _ in 0..iters {
                            frame.copy_from(&input);
                            frame.seq = seq;
                            seq += 1;
                            let t = Instant::now();
                            let out = chain.apply(&mut frame, &mut report).expect("chain");
                            total += t.elapsed();
                            std::hint::black_box(out);
                        }
                        total
                    })
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, effects, chain_original8);
criterion_main!(benches);
