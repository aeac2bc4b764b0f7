//! Fuzzing in the normal test suite (proptest, arbitrary bytes and mutated seeds), a bounded
//! number of cases so this file runs in well under a minute:
//!
//! - the campaign/timeline TOML parser (`FaultConfig::parse`, `Campaign::from_config`,
//!   `Chain::from_config`, `MaskConfig::from_config`),
//! - the serial trigger line protocol (`LineAssembler`, `parse_line`),
//! - the image decoders through the `files:` source (PNG, JPEG, PNM, TIFF),
//! - the source and sink URI parsers (`files:`, `synth:`, `null:`, unknown schemes),
//! - the ground-truth log checker (`check_log`).
//!
//! Properties: no panic; errors name the input (file and line, the file path, the URI);
//! allocations bounded (a counting global allocator: no single allocation over twice the
//! image byte limit while decoding). Seeds in `tests/fuzz_corpus/<target>/` are replayed
//! every run and also used as the starting points of mutations. The RNG seed is fixed (set
//! `PROPTEST_RNG_SEED` to explore others; `FUZZ_CASES_SCALE=N` multiplies the case counts).

use faultcam::limits::ImageLimits;
use faultcam::source;
use faultcam::trigger::{LineAssembler, RawLine, parse_line};
use faultcam::{Chain, FaultConfig};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed, TestRunner};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

#[path = "support/bombs.rs"]
mod bombs;

// ---------------------------------------------------------------------------------------------
// Allocation bound

struct Counting;
/// Largest single allocation (bytes) while `WATCH` is on.
static LARGEST: AtomicUsize = AtomicUsize::new(0);
static WATCH: AtomicBool = AtomicBool::new(false);

fn note(size: usize) {
    if WATCH.load(Ordering::Relaxed) {
        LARGEST.fetch_max(size, Ordering::Relaxed);
    }
}

// SAFETY: forwards to the system allocator; only records sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        note(l.size());
        unsafe { System.alloc(l) }
    }
    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        note(l.size());
        unsafe { System.alloc_zeroed(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        note(new);
        unsafe { System.realloc(p, l, new) }
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Image limits for this process: small, so a mutated header cannot ask for much.
const FUZZ_LIMITS: ImageLimits = ImageLimits { max_width: 1024, max_height: 1024, max_bytes: 4 << 20 };

// ---------------------------------------------------------------------------------------------
// Helpers

fn corpus(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_corpus").join(target);
    let mut v: Vec<(PathBuf, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .map(|p| {
            let b = std::fs::read(&p).unwrap();
            (p, b)
        })
        .collect();
    v.sort();
    assert!(!v.is_empty(), "{}: no seeds", dir.display());
    v
}

fn runner(cases: u32) -> TestRunner {
    let scale: u32 = std::env::var("FUZZ_CASES_SCALE").ok().and_then(|s| s.parse().ok()).unwrap_or(1);
    let mut cfg = Config { cases: cases * scale.max(1), failure_persistence: None, ..Config::default() };
    if cfg.rng_seed == RngSeed::Random {
        cfg.rng_seed = RngSeed::Fixed(0xFA17_CA11);
    }
    TestRunner::new(cfg)
}

/// Arbitrary bytes, or a seed with a few random edits (replace, insert, delete, truncate).
fn input(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    let edits = prop::collection::vec((0u8..4, any::<usize>(), any::<u8>()), 1..8);
    prop_oneof![
        prop::collection::vec(any::<u8>(), 0..512),
        (prop::sample::select(seeds), edits).prop_map(|(mut s, edits)| {
            for (kind, at, b) in edits {
                let i = if s.is_empty() { 0 } else { at % s.len() };
                match kind {
                    0 if !s.is_empty() => s[i] = b,
                    1 => s.insert(i.min(s.len()), b),
                    2 if !s.is_empty() => {
                        s.remove(i);
                    }
                    3 => s.truncate(i),
                    _ => {}
                }
            }
            s
        }),
    ]
}

// ---------------------------------------------------------------------------------------------
// Campaign / timeline TOML

fn campaign_case(bytes: &[u8]) -> Result<(), TestCaseError> {
    let text = String::from_utf8_lossy(bytes);
    let cfg = match FaultConfig::parse(&text, "fuzz.toml") {
        Ok(c) => c,
        Err(e) => {
            let m = e.to_string();
            prop_assert!(m.starts_with("fuzz.toml:"), "config error does not name the file: {m}");
            return Ok(());
        }
    };
    if let Err(e) = faultcam::schedule::Campaign::from_config(&cfg) {
        prop_assert!(!e.to_string().is_empty());
    }
    if let Err(e) = Chain::from_config(&cfg) {
        prop_assert!(!e.to_string().is_empty());
    }
    let _ = faultcam::masks::MaskConfig::from_config(&cfg);
    Ok(())
}

#[test]
fn campaign_parser_never_panics_and_names_the_file() {
    let seeds = corpus("campaign");
    for (p, b) in &seeds {
        campaign_case(b).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        // The checked-in campaigns are valid.
        let text = std::str::from_utf8(b).unwrap();
        let cfg = FaultConfig::parse(text, "seed.toml").unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        faultcam::schedule::Campaign::from_config(&cfg).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    }
    let strat = input(seeds.into_iter().map(|(_, b)| b).collect());
    runner(400).run(&strat, |b| campaign_case(&b)).unwrap();
}

// ---------------------------------------------------------------------------------------------
// Serial trigger protocol

fn catalog() -> faultcam::trigger::Catalog {
    let text = include_str!("fuzz_corpus/campaign/triggered-blooming.toml");
    let cfg = FaultConfig::parse(text, "triggered-blooming.toml").unwrap();
    faultcam::schedule::Campaign::from_config(&cfg).unwrap().catalog()
}

const MAX_LINE: usize = 128;

fn trigger_case(cat: &faultcam::trigger::Catalog, bytes: &[u8], chunk: usize) -> Result<(), TestCaseError> {
    let mut asm = LineAssembler::new(MAX_LINE, Duration::from_millis(50));
    let mut lines = Vec::new();
    let t0 = Instant::now();
    for (i, c) in bytes.chunks(chunk.max(1)).enumerate() {
        asm.push(c, t0 + Duration::from_millis(i as u64), &mut lines);
    }
    asm.check_timeout(t0 + Duration::from_secs(1), &mut lines);
    for l in &lines {
        let (RawLine::Line(b) | RawLine::TooLong(b) | RawLine::Partial(b)) = l;
        prop_assert!(b.len() <= MAX_LINE, "line of {} bytes over the {MAX_LINE} limit", b.len());
        prop_assert!(!b.contains(&b'\n') && !b.contains(&b'\r'));
        if let RawLine::Line(b) = l {
            prop_assert!(!b.is_empty());
            match parse_line(b, cat) {
                Ok((_, cmd)) => {
                    // A parsed command prints back as protocol text that parses to itself.
                    let again = format!("1 {}", cmd.text(cat));
                    let (_, cmd2) = parse_line(again.as_bytes(), cat)
                        .map_err(|(_, e)| TestCaseError::fail(format!("'{again}' does not parse back: {e}")))?;
                    prop_assert_eq!(cmd2.text(cat), cmd.text(cat));
                }
                Err((_, msg)) => {
                    prop_assert!(!msg.is_empty());
                    prop_assert!(!msg.contains('\n') && !msg.contains('\r'), "NAK text must be one line: {msg:?}");
                }
            }
        }
    }
    Ok(())
}

#[test]
fn trigger_protocol_never_panics_and_naks_on_one_line() {
    let cat = catalog();
    let seeds = corpus("trigger");
    for (p, b) in &seeds {
        for chunk in [1, 7, 4096] {
            trigger_case(&cat, b, chunk).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        }
    }
    let strat = (input(seeds.into_iter().map(|(_, b)| b).collect()), 1usize..64);
    runner(2000).run(&strat, |(b, chunk)| trigger_case(&cat, &b, chunk)).unwrap();
}

// ---------------------------------------------------------------------------------------------
// Image decoders through the `files:` source

const EXTS: &[&str] = &["png", "jpg", "tiff", "pgm"];

fn image_case(dir: &Path, bytes: &[u8], ext: &str) -> Result<(), TestCaseError> {
    let name = format!("in.{ext}");
    let path = dir.join(&name);
    std::fs::write(&path, bytes).unwrap();
    LARGEST.store(0, Ordering::Relaxed);
    WATCH.store(true, Ordering::Relaxed);
    let res = (|| {
        let mut src = source::open(&format!("files:{}", dir.display()))?;
        src.next_frame()
    })();
    WATCH.store(false, Ordering::Relaxed);
    let largest = LARGEST.load(Ordering::Relaxed) as u64;
    std::fs::remove_file(&path).unwrap();
    prop_assert!(
        largest <= 2 * FUZZ_LIMITS.max_bytes,
        "{name}: an allocation of {largest} bytes while decoding (limit {} bytes)",
        FUZZ_LIMITS.max_bytes
    );
    match res {
        Ok(Some(f)) => {
            prop_assert!(f.width <= FUZZ_LIMITS.max_width && f.height <= FUZZ_LIMITS.max_height);
            let samples = match &f.data {
                faultcam::frame::FrameData::U8(v) => v.len(),
                faultcam::frame::FrameData::U16(v) => v.len(),
            };
            prop_assert!(samples >= f.width as usize * f.height as usize * f.format.channels());
        }
        Ok(None) => prop_assert!(false, "one file gave no frame and no error"),
        Err(e) => {
            let m = e.to_string();
            prop_assert!(e.recoverable(), "{m}");
            prop_assert!(m.contains(&name), "error does not name the file: {m}");
        }
    }
    Ok(())
}

#[test]
fn image_decoders_never_panic_and_stay_within_the_limits() {
    FUZZ_LIMITS.set_current();
    let dir = tempfile::tempdir().unwrap();
    let mut seeds = corpus("images");
    for (name, b) in bombs::all() {
        seeds.push((PathBuf::from(name), b));
    }
    for (p, b) in &seeds {
        for ext in EXTS {
            image_case(dir.path(), b, ext).unwrap_or_else(|e| panic!("{} as .{ext}: {e}", p.display()));
        }
    }
    let strat = (input(seeds.into_iter().map(|(_, b)| b).collect()), prop::sample::select(EXTS));
    runner(300).run(&strat, |(b, ext)| image_case(dir.path(), &b, ext)).unwrap();
}

// ---------------------------------------------------------------------------------------------
// Source and sink URIs

/// Schemes that would touch devices, cameras or launch pipelines are not fuzzed here.
fn safe(uri: &str) -> bool {
    let (scheme, _, _) = source::split_uri(uri);
    !matches!(scheme, "gst" | "aravis" | "v4l2") || uri.starts_with("v4l2:/dev/video-faultcam-none")
}

fn uri_case(dir: &Path, raw: &[u8]) -> Result<(), TestCaseError> {
    let text = String::from_utf8_lossy(raw).replace("DIR", &dir.display().to_string());
    let (as_sink, uri) = match text.strip_prefix("sink-") {
        Some(u) => (true, u.to_string()),
        None => (false, text),
    };
    if !safe(&uri) {
        return Ok(());
    }
    if as_sink {
        if let Err(e) = faultcam::sink::open(&uri) {
            prop_assert!(!e.to_string().is_empty());
        }
    } else {
        match source::open(&uri) {
            Ok(mut s) => {
                let _ = s.describe();
                let _ = s.next_frame();
            }
            Err(e) => {
                let m = e.to_string();
                prop_assert!(
                    m.contains(uri.as_str()) || m.contains(dir.to_str().unwrap()),
                    "error does not name the URI: {m}"
                );
            }
        }
    }
    Ok(())
}

#[test]
fn uri_parsers_never_panic_and_name_the_uri() {
    FUZZ_LIMITS.set_current();
    // DIR is a folder inside the temporary one, so a mutated sink URI such as `files:DIR?fora`
    // (a folder named `d?fora`) is created inside it and removed with it.
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("d");
    std::fs::create_dir(&dir).unwrap();
    let img = image::GrayImage::from_fn(8, 8, |x, y| image::Luma([(x * 9 + y) as u8]));
    img.save(dir.join("a.png")).unwrap();
    let seeds = corpus("uri");
    for (p, b) in &seeds {
        uri_case(&dir, b).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    }
    let mut seeds: Vec<Vec<u8>> = seeds.into_iter().map(|(_, b)| b).collect();
    // Keys every parser knows, so mutations reach the value checks.
    for k in ["loop", "fps", "shard", "timestamps", "width", "height", "format", "frames", "quality", "seed"] {
        seeds.push(format!("synth:?{k}=1").into_bytes());
        seeds.push(format!("files:DIR?{k}=2").into_bytes());
    }
    runner(600).run(&input(seeds), |b| uri_case(&dir, &b)).unwrap();
}

// ---------------------------------------------------------------------------------------------
// Ground-truth log checker

#[test]
fn log_checker_never_panics() {
    let seeds = corpus("log");
    for (p, b) in &seeds {
        let c = faultcam::gtlog::check_log(b);
        let name = p.file_name().unwrap().to_string_lossy();
        // Seeds named ok-* are valid logs; the others each have a problem.
        assert_eq!(c.ok(), name.starts_with("ok-"), "{name}: {:?}", c.problems);
    }
    let strat = input(seeds.into_iter().map(|(_, b)| b).collect());
    runner(500)
        .run(&strat, |b| {
            let c = faultcam::gtlog::check_log(&b);
            prop_assert!(c.ok() || c.problems.iter().all(|p| !p.is_empty()));
            Ok(())
        })
        .unwrap();
}

/// Regenerate the image seeds (`cargo test --test fuzz -- --ignored write_image_seeds`).
#[test]
#[ignore]
fn write_image_seeds() {
    use faultcam::frame::{Frame, PixelFormat};
    use faultcam::sink::Sink;
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_corpus/images");
    std::fs::create_dir_all(&out).unwrap();
    for (fmt, pf) in [
        ("png", PixelFormat::Mono8),
        ("png", PixelFormat::Mono16),
        ("png", PixelFormat::Rgb8),
        ("pgm", PixelFormat::Mono8),
        ("pgm", PixelFormat::Rgb8),
        ("tiff", PixelFormat::Mono16),
        ("tiff", PixelFormat::Rgb8),
        ("jpg", PixelFormat::Mono8),
        ("jpg", PixelFormat::Rgb8),
    ] {
        let mut f = Frame::new(12, 9, pf).unwrap();
        for y in 0..9 {
            for x in 0..12 {
                for c in 0..pf.channels() {
                    f.set(x, y, c, ((x * 20 + y * 7 + c * 60) % 256) as f32);
                }
            }
        }
        let tmp = tempfile::tempdir().unwrap();
        let mut s =
            faultcam::sink::files::FilesSink::open(&format!("files:{}?format={fmt}", tmp.path().display())).unwrap();
        s.write_frame(&f, Some("x")).unwrap();
        s.finish().unwrap();
        for e in std::fs::read_dir(tmp.path()).unwrap() {
            let p = e.unwrap().path();
            let ext = p.extension().unwrap().to_string_lossy().into_owned();
            std::fs::copy(&p, out.join(format!("small-{pf}.{ext}"))).unwrap();
        }
    }
    for (name, b) in bombs::all() {
        std::fs::write(out.join(name.replace("0-bomb", "bomb")), b).unwrap();
    }
}
