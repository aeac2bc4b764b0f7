//! `faultcam bench`: per-frame latency (p50/p99/max) of a fault chain and of each of its effects,
//! or of single effects, on a seeded synthetic scene.
//!
//! Every measured frame is a fresh copy of the same scene (copied outside the timed region) with
//! `seq` = frame number, so stochastic effects draw new numbers each frame as in a stream. The
//! chain is timed as a whole (`chain` row) and, through a chain observer, effect by effect inside
//! it (each effect sees the output of the previous ones). Wall-clock times are per frame; with one
//! thread the CPU time of the worker thread is shown too (`cpu p50`), which other processes on the
//! machine do not inflate. `digest` is an FNV-1a hash of every output frame: the same for any
//! `--threads` (determinism check).

use anyhow::{Context, bail};
use faultcam::faults::chain::{Chain, ChainObserver, FrameReport};
use faultcam::faults::kit::{Scene, bench_params};
use faultcam::faults::{Outcome, registry};
use faultcam::frame::{Frame, FrameData, PixelFormat};
use faultcam::{FaultConfig, Params};
use std::path::PathBuf;
use std::time::Instant;

/// Arguments of `faultcam bench`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Fault configuration to time (the chain and each of its effects).
    #[arg(long, value_name = "FILE")]
    pub faults: Option<PathBuf>,
    /// Time this effect alone (repeatable), with the visible bench parameters
    /// (`faults::kit::bench_params`) unless `--set` changes them.
    #[arg(long, value_name = "NAME")]
    pub effect: Vec<String>,
    /// Time every registered effect alone.
    #[arg(long)]
    pub all_effects: bool,
    /// Parameter of a single effect, `NAME.PARAM=VALUE` (repeatable), e.g. `jpeg.quality=90`.
    #[arg(long = "set", value_name = "NAME.PARAM=VALUE")]
    pub set: Vec<String>,
    /// Frame size(s), WxH (repeatable or comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "1920x1200")]
    pub size: Vec<String>,
    /// Pixel format(s): mono8, rgb8, mono16 (repeatable or comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "rgb8")]
    pub format: Vec<String>,
    /// Worker thread count(s) (repeatable or comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "1")]
    pub threads: Vec<usize>,
    /// Input scene: spacecraft (the `synth:` source's procedural spacecraft, small saturated
    /// glints: representative), stress (a large bright body that overflows the well over wide
    /// areas when over-exposed) or ramp (diagonal ramps: bands of saturation across every tile,
    /// blooming's worst case).
    #[arg(long, default_value = "spacecraft")]
    pub scene: String,
    /// Measured frames per case.
    #[arg(long, default_value_t = 60)]
    pub frames: usize,
    /// Unmeasured frames first (caches, lookup tables, buffers).
    #[arg(long, default_value_t = 3)]
    pub warmup: usize,
    /// Print a Markdown table (for BENCHMARKS.md).
    #[arg(long)]
    pub markdown: bool,
}

/// CPU time of the calling thread (ns): `clock_gettime(CLOCK_THREAD_CPUTIME_ID)`, exact to the
/// nanosecond and not inflated by other processes competing for the cores; 0 where unavailable.
fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec; the call only writes into it.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return 0;
    }
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

fn parse_size(s: &str) -> anyhow::Result<(u32, u32)> {
    let (w, h) = s.split_once(['x', 'X']).with_context(|| format!("--size {s}: expected WxH, e.g. 1920x1200"))?;
    let (w, h): (u32, u32) = (
        w.parse().with_context(|| format!("--size {s}: bad width"))?,
        h.parse().with_context(|| format!("--size {s}: bad height"))?,
    );
    if !(8..=16384).contains(&w) || !(8..=16384).contains(&h) {
        bail!("--size {s}: width and height must be 8..=16384");
    }
    Ok((w, h))
}

/// Latencies of one row, in ms.
#[derive(Default)]
struct Series {
    wall: Vec<f64>,
    cpu: Vec<f64>,
}

fn pct(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
    sorted[i]
}

struct Row {
    name: String,
    stage: &'static str,
    p50: f64,
    p99: f64,
    max: f64,
    cpu50: Option<f64>,
    mpx_s: f64,
    digest: Option<u64>,
}

impl Series {
    fn row(mut self, name: String, stage: &'static str, pixels: usize, digest: Option<u64>, cpu: bool) -> Row {
        self.wall.sort_by(f64::total_cmp);
        self.cpu.sort_by(f64::total_cmp);
        let p50 = pct(&self.wall, 0.5);
        Row {
            name,
            stage,
            p50,
            p99: pct(&self.wall, 0.99),
            max: self.wall.last().copied().unwrap_or(f64::NAN),
            cpu50: cpu.then(|| pct(&self.cpu, 0.5)),
            mpx_s: pixels as f64 / p50 / 1e3,
            digest,
        }
    }
}

/// FNV-1a over the frame's samples (little-endian bytes for 16-bit).
fn fnv(mut h: u64, f: &Frame) -> u64 {
    let mut eat = |b: u8| {
        h ^= b as u64;
        h = h.wrapping_mul(0x100_0000_01b3);
    };
    let n = f.row_len();
    match &f.data {
        FrameData::U8(d) => d.chunks(f.stride).take(f.height as usize).flat_map(|r| &r[..n]).for_each(|&b| eat(b)),
        FrameData::U16(d) => d
            .chunks(f.stride)
            .take(f.height as usize)
            .flat_map(|r| &r[..n])
            .for_each(|v| v.to_le_bytes().into_iter().for_each(&mut eat)),
    }
    h
}

const FNV_INIT: u64 = 0xcbf2_9ce4_8422_2325;

/// Per-effect wall and CPU time inside the chain.
struct Timer {
    t0: Instant,
    c0: u64,
    cpu: bool,
    /// (wall ms, cpu ms) of the effects applied to the current frame, by position.
    cur: Vec<(f64, f64)>,
}

impl ChainObserver for Timer {
    fn before_effect(&mut self, _k: usize, _name: &'static str, _frame: &Frame) {
        if self.cpu {
            self.c0 = thread_cpu_ns();
        }
        self.t0 = Instant::now();
    }
    fn after_effect(&mut self, k: usize, _name: &'static str, _frame: &Frame, _o: Outcome) {
        let wall = self.t0.elapsed().as_secs_f64() * 1e3;
        let cpu = if self.cpu { (thread_cpu_ns().saturating_sub(self.c0)) as f64 * 1e-6 } else { 0.0 };
        if self.cur.len() <= k {
            self.cur.resize(k + 1, (0.0, 0.0));
        }
        self.cur[k] = (wall, cpu);
    }
}

/// Time a chain: the whole chain per frame, and each effect inside it.
fn time_chain(
    chain: &mut Chain,
    input: &Frame,
    a: &Args,
    threads: usize,
    per_effect: bool,
) -> anyhow::Result<Vec<Row>> {
    let cpu = threads == 1;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().context("cannot start worker threads")?;
    let names: Vec<(&'static str, &'static str)> =
        chain.entries().iter().filter(|e| e.enabled).map(|e| (e.name(), e.stage().name())).collect();
    pool.install(|| -> anyhow::Result<Vec<Row>> {
        let mut f = input.clone();
        let mut report = FrameReport::default();
        let mut total = Series::default();
        let mut each: Vec<Series> = names.iter().map(|_| Series::default()).collect();
        let mut timer = Timer { t0: Instant::now(), c0: 0, cpu, cur: Vec::with_capacity(names.len()) };
        let mut digest = FNV_INIT;
        for i in 0..a.warmup + a.frames {
            f.copy_from(input);
            f.seq = i as u64;
            timer.cur.clear();
            let (t0, c0) = (Instant::now(), if cpu { thread_cpu_ns() } else { 0 });
            let out = if per_effect {
                chain.apply_observed(&mut f, &mut report, &mut timer)?
            } else {
                chain.apply(&mut f, &mut report)?
            };
            let wall = t0.elapsed().as_secs_f64() * 1e3;
            let cpu_ms = if cpu { thread_cpu_ns().saturating_sub(c0) as f64 * 1e-6 } else { 0.0 };
            if i < a.warmup {
                continue;
            }
            total.wall.push(wall);
            total.cpu.push(cpu_ms);
            for (k, &(w, c)) in timer.cur.iter().enumerate() {
                each[k].wall.push(w);
                each[k].cpu.push(c);
            }
            if out == Outcome::Keep {
                digest = fnv(digest, &f);
            }
        }
        let px = input.pixels();
        let mut rows: Vec<Row> = Vec::new();
        if per_effect {
            for ((name, stage), s) in names.iter().zip(each) {
                rows.push(s.row(name.to_string(), stage, px, None, cpu));
            }
        }
        rows.push(total.row(
            if per_effect { "chain".into() } else { names.first().map_or("-", |n| n.0).into() },
            if per_effect { "all" } else { names.first().map_or("-", |n| n.1) },
            px,
            Some(digest),
            cpu,
        ));
        Ok(rows)
    })
}

fn single_params(name: &str, sets: &[String]) -> anyhow::Result<Params> {
    let mut p = bench_params(name)?;
    for s in sets {
        let (lhs, value) = s.split_once('=').with_context(|| format!("--set {s}: expected NAME.PARAM=VALUE"))?;
        let (effect, param) = lhs.split_once('.').with_context(|| format!("--set {s}: expected NAME.PARAM=VALUE"))?;
        if effect != name {
            continue;
        }
        // A choice word first (some are numbers, e.g. jpeg.chroma=444), else a number.
        if p.set_choice(param, value).is_err() {
            match value.parse::<f64>() {
                Ok(v) => p.set(param, v)?,
                Err(_) => p.set_choice(param, value)?,
            }
        }
    }
    Ok(p)
}

pub fn run(a: Args) -> anyhow::Result<u8> {
    let mut singles: Vec<String> = a.effect.clone();
    if a.all_effects {
        singles.extend(registry::all().iter().map(|r| r.info.name.to_string()));
    }
    if a.faults.is_none() && singles.is_empty() {
        bail!("nothing to time: give --faults FILE, --effect NAME or --all-effects");
    }
    for s in &a.set {
        let name = s.split('.').next().unwrap_or("");
        if !singles.iter().any(|e| e == name) {
            bail!("--set {s}: {name} is not one of the --effect effects (configs set parameters in the file)");
        }
    }
    if a.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let cfg = a.faults.as_deref().map(FaultConfig::load).transpose()?;
    let sizes: Vec<(u32, u32)> = a.size.iter().map(|s| parse_size(s)).collect::<anyhow::Result<_>>()?;
    let formats: Vec<PixelFormat> = a
        .format
        .iter()
        .map(|s| match PixelFormat::parse(s) {
            Some(f @ (PixelFormat::Mono8 | PixelFormat::Mono16 | PixelFormat::Rgb8)) => Ok(f),
            _ => Err(anyhow::anyhow!("--format {s} is not accepted; expected mono8, rgb8 or mono16")),
        })
        .collect::<anyhow::Result<_>>()?;
    if a.threads.contains(&0) {
        bail!("--threads must be at least 1");
    }
    let scene = Scene::parse(&a.scene)
        .with_context(|| format!("--scene {} is not accepted; expected spacecraft, stress or ramp", a.scene))?;
    let host = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!(
        "faultcam bench: {} scene, {} measured frames (+{} warm-up) per case; wall ms per frame; {} cores on this host{}",
        scene.name(),
        a.frames,
        a.warmup,
        host,
        std::fs::read_to_string("/proc/loadavg")
            .ok()
            .map(|l| format!(", load average {}", l.split_whitespace().take(3).collect::<Vec<_>>().join(" ")))
            .unwrap_or_default()
    );
    // Every number names its CPU and the kernel set that ran (FAULTCAM_NO_AVX512 /
    // FAULTCAM_NO_SIMD switch the faster ones off).
    println!("CPU: {}; kernels: {}", faultcam::faults::kit::cpu_model(), faultcam::faults::kit::kernel_set());
    if a.markdown {
        println!(
            "\n| case | effect | stage | size | format | threads | p50 ms | p99 ms | max ms | cpu p50 ms | Mpx/s | digest |"
        );
        println!("|---|---|---|---|---|---|---:|---:|---:|---:|---:|---|");
    }
    for &(w, h) in &sizes {
        for &format in &formats {
            let input = scene.render(w, h, format)?;
            for &threads in &a.threads {
                let mut cases: Vec<(String, Vec<Row>)> = Vec::new();
                if let (Some(cfg), Some(path)) = (&cfg, &a.faults) {
                    let mut chain = Chain::from_config(cfg).with_context(|| path.display().to_string())?;
                    cases.push((path.display().to_string(), time_chain(&mut chain, &input, &a, threads, true)?));
                }
                for name in &singles {
                    let mut chain = Chain::new(1);
                    chain.push(name, single_params(name, &a.set)?)?;
                    cases.push(("single".into(), time_chain(&mut chain, &input, &a, threads, false)?));
                }
                print_cases(&cases, w, h, format, threads, a.markdown);
            }
        }
    }
    Ok(0)
}

fn print_cases(cases: &[(String, Vec<Row>)], w: u32, h: u32, format: PixelFormat, threads: usize, md: bool) {
    let f3 = |v: f64| if v.is_finite() { format!("{v:.3}") } else { "-".into() };
    if !md {
        println!("\n{w}x{h} {format}, {threads} thread(s)");
        println!(
            "  {:<40} {:<12} {:>9} {:>9} {:>9} {:>10} {:>9}  digest",
            "effect", "stage", "p50 ms", "p99 ms", "max ms", "cpu p50", "Mpx/s"
        );
    }
    for (case, rows) in cases {
        for r in rows {
            let name = if r.name == "chain" { format!("chain ({case})") } else { r.name.clone() };
            let digest = r.digest.map(|d| format!("{d:016x}")).unwrap_or_default();
            let cpu = r.cpu50.map(f3).unwrap_or_else(|| "-".into());
            if md {
                println!(
                    "| {case} | {} | {} | {w}x{h} | {format} | {threads} | {} | {} | {} | {cpu} | {:.0} | {digest} |",
                    if r.name == "chain" { "**chain**".to_string() } else { r.name.clone() },
                    r.stage,
                    f3(r.p50),
                    f3(r.p99),
                    f3(r.max),
                    r.mpx_s
                );
            } else {
                println!(
                    "  {:<40} {:<12} {:>9} {:>9} {:>9} {:>10} {:>9.0}  {digest}",
                    name,
                    r.stage,
                    f3(r.p50),
                    f3(r.p99),
                    f3(r.max),
                    cpu,
                    r.mpx_s
                );
            }
        }
    }
}
