//! No allocation per frame in steady state: a counting global allocator around the full effect
//! chain (every registered effect, i.e. everything that can be in a stream) and around mask
//! recording, for Mono8, Rgb8 and Mono16 frames.
//!
//! `harness = false` (see Cargo.toml): a plain `main`, so no test-harness thread allocates while
//! we count. The chain runs inside a rayon pool (`install`), as a stream's fault stage does:
//! parallel work spawned from a pool thread reuses the workers' deques. (Parallel work started
//! from a thread outside any pool goes through rayon's global injector, which allocates a queue
//! block every 63 submissions; that is measured and reported below, not asserted.)

use faultcam::faults::chain::{Chain, FrameReport};
use faultcam::faults::kit::{bench_params, bench_scene};
use faultcam::faults::registry;
use faultcam::masks::{MaskOptions, MaskRecorder};
use faultcam::{Frame, PixelFormat};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

struct Counting;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

// SAFETY: forwards every call to the system allocator unchanged; only counts.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Relaxed);
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Relaxed);
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Relaxed);
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

const WARMUP: u64 = 12;
const MEASURED: u64 = 40;

/// Every registered effect with its visible bench parameters, in one chain.
fn full_chain() -> Chain {
    let mut chain = Chain::new(7);
    for r in registry::all() {
        chain.push(r.info.name, bench_params(r.info.name).expect("bench params")).expect("push");
    }
    chain
}

/// Run `frames` frames through the chain (seq continuing from `first`); return the number of
/// allocations during the last `MEASURED` of them.
fn run(chain: &mut Chain, input: &Frame, rec: Option<&mut MaskRecorder>, first: u64) -> u64 {
    let mut f = input.clone();
    let mut report = FrameReport::default();
    let mut rec = rec;
    let mut before = 0;
    for i in 0..WARMUP + MEASURED {
        if i == WARMUP {
            before = ALLOCATIONS.load(Relaxed);
        }
        f.copy_from(input);
        f.seq = first + i;
        let r = match rec.as_deref_mut() {
            Some(rec) => chain.apply_recording(&mut f, &mut report, rec),
            None => chain.apply(&mut f, &mut report),
        };
        if let Err(e) = r {
            eprintln!("alloc: chain failed: {e}");
            std::process::exit(1);
        }
    }
    ALLOCATIONS.load(Relaxed) - before
}

/// Allocations inside each effect (diagnostics on failure).
struct PerEffect {
    start: u64,
    counts: Vec<u64>,
    names: Vec<&'static str>,
}

impl faultcam::faults::chain::ChainObserver for PerEffect {
    fn before_effect(&mut self, _k: usize, _name: &'static str, _frame: &Frame) {
        self.start = ALLOCATIONS.load(Relaxed);
    }
    fn after_effect(&mut self, k: usize, name: &'static str, _frame: &Frame, _o: faultcam::faults::Outcome) {
        self.counts[k] += ALLOCATIONS.load(Relaxed) - self.start;
        self.names[k] = name;
    }
}

/// A rayon pool of `threads` workers, every one of them started and idle: a worker's start-up
/// allocates (its stack, thread-locals), which must not land in a short case's measured frames.
fn started_pool(threads: usize) -> rayon::ThreadPool {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
    pool.broadcast(|_| ());
    pool
}

fn main() {
    // The counter sees allocations (so a zero below means something).
    let before = ALLOCATIONS.load(Relaxed);
    let probe = std::hint::black_box(vec![7u8; 100]);
    if ALLOCATIONS.load(Relaxed) == before || probe.len() != 100 {
        eprintln!("alloc: FAILED: the counting allocator did not count an allocation");
        std::process::exit(1);
    }
    drop(probe);
    let mut failures = Vec::new();
    let names: Vec<&str> = registry::all().iter().map(|r| r.info.name).collect();
    println!("alloc: {} effects in the chain: {}", names.len(), names.join(", "));
    // Both pools live until the end: a dropped pool's workers exit on their own time, and a
    // thread's exit allocates (crossbeam-epoch hands its leftover garbage to the global queue), so
    // a pool dropped between cases could put allocations into the next case's measured frames
    // (seen under load: 1-2 allocations in the first blur case after the chain's pools).
    let pools: Vec<(usize, rayon::ThreadPool)> = [1usize, 2].into_iter().map(|t| (t, started_pool(t))).collect();
    for (threads, pool) in &pools {
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
            let input = bench_scene(320, 240, format, 3).expect("scene");
            let (plain, recorded) = pool.install(|| {
                let mut chain = full_chain();
                let plain = run(&mut chain, &input, None, 0);
                let mut rec = MaskRecorder::new(MaskOptions { deltas: true });
                let mut chain = full_chain();
                let recorded = run(&mut chain, &input, Some(&mut rec), 0);
                (plain, recorded)
            });
            println!(
                "alloc: {format}, {threads} thread(s): {plain} allocations in {MEASURED} frames after {WARMUP} warm-up \
                 frames; with mask recording (labels + deltas): {recorded}"
            );
            if plain != 0 || recorded != 0 {
                failures.push(format!("{format}/{threads} threads: {plain} (plain), {recorded} (masks)"));
            }
        }
    }
    // The blurs' other 8-bit paths (the chain above runs motion_blur's FIR at 10 px 30 deg and
    // defocus at its bench sigma): motion_blur's row box (along x), its running sums on rows (mostly
    // vertical) and on frame columns (mostly horizontal), defocus's pyramid, at a frame size whose
    // rows are not a whole number of registers.
    for (threads, pool) in &pools {
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8] {
            let input = bench_scene(333, 203, format, 3).expect("scene");
            let cases: [(&str, &[(&str, f64)]); 4] = [
                ("motion_blur", &[("length_px", 66.0), ("angle_deg", 0.0)]),
                ("motion_blur", &[("length_px", 40.0), ("angle_deg", 80.0)]),
                ("motion_blur", &[("length_px", 40.0), ("angle_deg", 30.0)]),
                ("defocus", &[("sigma_px", 9.5)]),
            ];
            for (effect, set) in cases {
                let got = pool.install(|| {
                    let mut chain = Chain::new(7);
                    let mut p = bench_params(effect).expect("bench params");
                    for &(k, v) in set {
                        p.set(k, v).expect("in range");
                    }
                    chain.push(effect, p).expect("push");
                    run(&mut chain, &input, None, 0)
                });
                println!(
                    "alloc: {effect} {set:?}, {format}, {threads} thread(s): {got} allocations in {MEASURED} frames"
                );
                if got != 0 {
                    failures.push(format!("{effect} {set:?} {format}/{threads} threads: {got}"));
                }
            }
        }
    }
    // Informational: the same chain driven from a thread outside any rayon pool.
    let input = bench_scene(320, 240, PixelFormat::Rgb8, 3).expect("scene");
    let mut chain = full_chain();
    let outside = run(&mut chain, &input, None, 0);
    println!(
        "alloc: (info) Rgb8 chain called from outside a rayon pool: {outside} allocations in {MEASURED} frames \
         (rayon's global injector queue blocks)"
    );
    if !failures.is_empty() {
        // Name the culprits: allocations inside each effect of the chain.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().expect("pool");
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
            pool.install(|| {
                let input = bench_scene(320, 240, format, 3).expect("scene");
                let mut chain = full_chain();
                let mut obs = PerEffect { start: 0, counts: vec![0; names.len()], names: vec![""; names.len()] };
                let mut report = FrameReport::default();
                let mut f = input.clone();
                for i in 0..WARMUP + MEASURED {
                    f.copy_from(&input);
                    f.seq = i;
                    if i == WARMUP {
                        obs.counts.iter_mut().for_each(|c| *c = 0);
                    }
                    let _ = chain.apply_observed(&mut f, &mut report, &mut obs);
                }
                for (n, c) in obs.names.iter().zip(&obs.counts) {
                    if *c > 0 {
                        eprintln!("alloc: {format}: {c} allocations in {n} over {MEASURED} frames");
                    }
                }
            });
        }
        eprintln!("alloc: FAILED: allocations per frame in steady state: {}", failures.join("; "));
        std::process::exit(1);
    }
    println!("alloc: ok, no allocation per frame in steady state");
}
