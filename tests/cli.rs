//! CLI tests: the real `faultcam` binary on inputs generated in temporary folders.

#[path = "support/files.rs"]
mod files;
use assert_cmd::Command;
use faultcam::faults::registry;
use faultcam::sink::{Sink, files::FilesSink};
use faultcam::source::Source;
use faultcam::source::synth::SynthSource;
use files::pngs;
use std::path::Path;

fn faultcam() -> Command {
    Command::cargo_bin("faultcam").unwrap()
}

/// Write `n` synthetic frames (PNG) named img_000.png, ... into `dir`.
fn make_inputs(dir: &Path, n: usize, opts: &str) {
    let mut src = SynthSource::open(&format!("synth:?width=96&height=64&frames={n}&spin_dps=20&{opts}")).unwrap();
    let mut sink = FilesSink::open(&format!("files:{}", dir.display())).unwrap();
    let mut i = 0;
    while let Some(f) = src.next_frame().unwrap() {
        sink.write_frame(&f, Some(&format!("img_{i:03}.png"))).unwrap();
        i += 1;
    }
}

fn log_records(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

fn count(records: &[serde_json::Value], kind: &str) -> usize {
    records.iter().filter(|r| r["record"] == kind).count()
}

const NOISE: &str = "seed = 3\n\n[[effects]]\nname = \"gaussian_noise\"\nsigma_dn = 6.0\n\n[[effects]]\nname = \"gain_offset\"\ngain = 1.2\noffset_dn = 4\n";

#[test]
fn effects_lists_every_registered_effect_with_units() {
    let out = faultcam().arg("effects").assert().success().get_output().stdout.clone();
    let text = String::from_utf8(out).unwrap();
    for r in registry::all() {
        assert!(text.contains(&format!("{} [{} stage", r.info.name, r.info.stage.name())), "{} missing", r.info.name);
        for p in r.info.params {
            assert!(
                text.contains(&p.name.to_string()) && text.contains(&format!("[{}]", p.unit)),
                "{}.{}",
                r.info.name,
                p.name
            );
            assert!(text.contains(&p.range_text()), "{}.{} range", r.info.name, p.name);
        }
    }
    let out = faultcam().args(["effects", "--json"]).assert().success().get_output().stdout.clone();
    let v: serde_json::Value = serde_json::from_slice(&out).unwrap();
    let arr = v.as_array().unwrap();
    assert_eq!(arr.len(), registry::all().len());
    for (e, r) in arr.iter().zip(registry::all()) {
        assert_eq!(e["name"], r.info.name);
        assert_eq!(e["params"].as_array().unwrap().len(), r.info.params.len());
        for (p, s) in e["params"].as_array().unwrap().iter().zip(r.info.params) {
            assert_eq!(p["unit"], s.unit);
            assert_eq!(p["min"], s.min);
            assert_eq!(p["max"], s.max);
        }
    }
    let out = faultcam().args(["effects", "--name", "gain_offset"]).assert().success().get_output().stdout.clone();
    let text = String::from_utf8(out).unwrap();
    assert!(
        text.starts_with("gain_offset [readout stage") && text.contains("offset_dn  [DN]  -255..=255 DN"),
        "{text}"
    );
    let err = faultcam().args(["effects", "--name", "nope"]).assert().code(2).get_output().stderr.clone();
    let err = String::from_utf8(err).unwrap();
    assert!(err.contains("known effects: lens_flare,") && err.contains("gain_offset"), "{err}");
}

#[test]
fn bad_faults_file_exits_2_naming_file_line_parameter_and_range() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("bad.toml");
    std::fs::write(&cfg, "seed = 1\n\n[[effects]]\nname = \"gain_offset\"\ngain = 9.0\n").unwrap();
    let inp = dir.path().join("in");
    std::fs::create_dir(&inp).unwrap();
    make_inputs(&inp, 1, "");
    let out = faultcam()
        .args(["apply", "--in"])
        .arg(&inp)
        .arg("--out")
        .arg(dir.path().join("out"))
        .arg("--faults")
        .arg(&cfg)
        .assert()
        .code(2)
        .get_output()
        .stderr
        .clone();
    let err = String::from_utf8(out).unwrap();
    assert!(err.contains(&format!("{}:5:", cfg.display())), "{err}");
    assert!(err.contains("gain_offset.gain") && err.contains("0..=4"), "{err}");
    // The same for `run`.
    let out = faultcam()
        .args(["run", "--source", "synth:?frames=1", "--sink", "null:", "--faults"])
        .arg(&cfg)
        .assert()
        .code(2)
        .get_output()
        .stderr
        .clone();
    assert!(String::from_utf8(out).unwrap().contains("bad.toml:5:"));
    // A bad URI is exit 2 too.
    faultcam().args(["run", "--source", "synth:?width=2", "--sink", "null:", "--faults"]).arg(&cfg).assert().code(2);
}

#[test]
fn run_synth_to_files_writes_n_frames_and_n_records() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("f.toml");
    std::fs::write(&cfg, NOISE).unwrap();
    let out = dir.path().join("frames");
    let log = dir.path().join("gt.jsonl");
    faultcam()
        .args(["run", "--source", "synth:?width=96&height=64&frames=5", "--sink"])
        .arg(format!("files:{}", out.display()))
        .arg("--faults")
        .arg(&cfg)
        .arg("--log")
        .arg(&log)
        .assert()
        .success();
    let imgs = pngs(&out);
    assert_eq!(
        imgs.keys().cloned().collect::<Vec<_>>(),
        (0..5).map(|i| format!("frame_{i:06}.png")).collect::<Vec<_>>()
    );
    let recs = log_records(&log);
    assert_eq!(count(&recs, "frame"), 5);
    let frames: Vec<_> = recs.iter().filter(|r| r["record"] == "frame").collect();
    for (i, r) in frames.iter().enumerate() {
        assert_eq!(r["seq"], i as u64);
        assert_eq!(r["status"], "delivered");
        assert!(r["output"].as_str().unwrap().ends_with(&format!("frame_{i:06}.png")));
        let effects = r["effects"].as_array().unwrap();
        // Physical order: gaussian_noise (readout, order 10) before gain_offset (readout, order 50).
        assert_eq!(
            effects.iter().map(|e| e["name"].as_str().unwrap()).collect::<Vec<_>>(),
            ["gaussian_noise", "gain_offset"]
        );
        assert_eq!(effects[0]["params"]["sigma_dn"], 6.0);
    }
    let summary = recs.iter().find(|r| r["record"] == "summary").unwrap();
    assert_eq!((summary["frames_in"].as_u64(), summary["delivered"].as_u64()), (Some(5), Some(5)));
    // --frames limits the input; default log goes next to a files: sink.
    let out2 = dir.path().join("frames2");
    faultcam()
        .args(["run", "--source", "synth:?width=64&height=48&frames=0", "--frames", "3", "--sink"])
        .arg(format!("files:{}", out2.display()))
        .arg("--faults")
        .arg(&cfg)
        .assert()
        .success();
    assert_eq!(pngs(&out2).len(), 3);
    assert_eq!(count(&log_records(&out2.join("groundtruth.jsonl")), "frame"), 3);
}

#[test]
fn run_files_logs_skipped_inputs_and_keeps_names() {
    let dir = tempfile::tempdir().unwrap();
    let inp = dir.path().join("in");
    std::fs::create_dir(&inp).unwrap();
    make_inputs(&inp, 3, "");
    std::fs::write(inp.join("img_001.png"), b"broken").unwrap();
    let cfg = dir.path().join("f.toml");
    std::fs::write(&cfg, NOISE).unwrap();
    let out = dir.path().join("out");
    faultcam()
        .args(["run", "--source"])
        .arg(format!("files:{}", inp.display()))
        .arg("--sink")
        .arg(format!("files:{}", out.display()))
        .arg("--faults")
        .arg(&cfg)
        .assert()
        .success();
    assert_eq!(pngs(&out).keys().cloned().collect::<Vec<_>>(), ["img_000.png", "img_002.png"]);
    let recs = log_records(&out.join("groundtruth.jsonl"));
    assert_eq!(count(&recs, "frame"), 2);
    let skip = recs.iter().find(|r| r["record"] == "skip").unwrap();
    assert!(skip["item"].as_str().unwrap().ends_with("img_001.png"));
    let summary = recs.iter().find(|r| r["record"] == "summary").unwrap();
    assert_eq!(summary["skipped"], 1);
}

fn apply(inp: &Path, out: &Path, cfg: &Path, extra: &[&str]) {
    faultcam()
        .args(["apply", "--in"])
        .arg(inp)
        .arg("--out")
        .arg(out)
        .arg("--faults")
        .arg(cfg)
        .args(extra)
        .assert()
        .success();
}

#[test]
fn apply_shards_reproduce_the_unsharded_output_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let inp = dir.path().join("in");
    std::fs::create_dir(&inp).unwrap();
    make_inputs(&inp, 10, "");
    // A corrupt and a wrong-size file: skipped (and logged) by whichever shard owns them.
    std::fs::write(inp.join("img_004.png"), b"\x89PNG\r\n\x1a\ntruncated").unwrap();
    let mut small = SynthSource::open("synth:?width=32&height=32&frames=1").unwrap();
    FilesSink::open(&format!("files:{}", inp.display()))
        .unwrap()
        .write_frame(&small.next_frame().unwrap().unwrap(), Some("img_007.png"))
        .unwrap();
    let cfg = dir.path().join("f.toml");
    std::fs::write(&cfg, NOISE).unwrap();

    let whole = dir.path().join("whole");
    apply(&inp, &whole, &cfg, &["--threads", "2"]);
    let expected = pngs(&whole);
    assert_eq!(expected.len(), 8, "10 inputs, one corrupt, one wrong size: {:?}", expected.keys());
    assert!(!expected.contains_key("img_004.png") && !expected.contains_key("img_007.png"));
    let recs = log_records(&whole.join("groundtruth.jsonl"));
    assert_eq!((count(&recs, "frame"), count(&recs, "skip")), (8, 2));
    let skips: Vec<String> = recs.iter().filter(|r| r["record"] == "skip").map(|r| r["reason"].to_string()).collect();
    assert!(skips[1].contains("expected 96x64 mono8, got 32x32 mono8"), "{skips:?}");
    // Input names are kept and seq is the index in the listing.
    let r5 = recs.iter().find(|r| r["record"] == "frame" && r["input"] == "img_005.png").unwrap();
    assert_eq!(r5["seq"], 5);

    let sharded = dir.path().join("sharded");
    let mut frames = 0;
    for k in 0..3 {
        apply(&inp, &sharded, &cfg, &["--threads", "1", "--shard", &format!("{k}/3")]);
        let log = sharded.join(format!("groundtruth.shard-{k}-of-3.jsonl"));
        frames += count(&log_records(&log), "frame");
    }
    assert_eq!(frames, 8);
    let got = pngs(&sharded);
    assert_eq!(got.keys().collect::<Vec<_>>(), expected.keys().collect::<Vec<_>>());
    for (name, bytes) in &expected {
        assert!(got[name] == *bytes, "{name}: sharded output differs from the unsharded one");
    }
    // The faults did something: outputs differ from inputs.
    assert_ne!(std::fs::read(inp.join("img_000.png")).unwrap(), expected["img_000.png"]);
}

#[test]
fn apply_same_seed_same_bytes_on_1_and_2_threads_and_seed_matters() {
    let dir = tempfile::tempdir().unwrap();
    let inp = dir.path().join("in");
    std::fs::create_dir(&inp).unwrap();
    make_inputs(&inp, 5, "format=rgb8");
    let cfg = dir.path().join("f.toml");
    std::fs::write(&cfg, NOISE).unwrap();
    let (a, b, c) = (dir.path().join("a"), dir.path().join("b"), dir.path().join("c"));
    apply(&inp, &a, &cfg, &["--threads", "1", "--seed", "11"]);
    apply(&inp, &b, &cfg, &["--threads", "2", "--seed", "11"]);
    apply(&inp, &c, &cfg, &["--threads", "2", "--seed", "12"]);
    let (ia, ib, ic) = (pngs(&a), pngs(&b), pngs(&c));
    assert_eq!(ia.len(), 5);
    assert!(ia == ib, "--threads 1 and --threads 2 differ");
    for (name, bytes) in &ia {
        assert!(ic[name] != *bytes, "{name}: a different seed gave the same bytes");
    }
    // The log records the seed of every effect's generator.
    let recs = log_records(&a.join("groundtruth.jsonl"));
    let start = recs.iter().find(|r| r["record"] == "event").unwrap();
    assert_eq!(start["seed"], 11);
}

#[test]
fn apply_refuses_to_overwrite_its_input() {
    let dir = tempfile::tempdir().unwrap();
    let inp = dir.path().join("in");
    std::fs::create_dir(&inp).unwrap();
    make_inputs(&inp, 1, "");
    let cfg = dir.path().join("f.toml");
    std::fs::write(&cfg, NOISE).unwrap();
    let err = faultcam()
        .args(["apply", "--in"])
        .arg(&inp)
        .arg("--out")
        .arg(&inp)
        .arg("--faults")
        .arg(&cfg)
        .assert()
        .code(2)
        .get_output()
        .stderr
        .clone();
    assert!(String::from_utf8(err).unwrap().contains("input folder"));
    faultcam()
        .args(["apply", "--in"])
        .arg(&inp)
        .arg("--out")
        .arg(dir.path().join("o"))
        .arg("--faults")
        .arg(&cfg)
        .args(["--shard", "3/3"])
        .assert()
        .code(2);
}

const SPARSE: &str = "seed = 5\n\n[[effects]]\nname = \"hot_pixels\"\nrate = 0.003\n\n[[effects]]\nname = \"vertical_glitch\"\ncount = 2\nmax_offset_px = 7\n";

#[test]
fn apply_masks_label_exactly_the_changed_pixels_and_name_the_files_in_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let inp = dir.path().join("in");
    std::fs::create_dir(&inp).unwrap();
    make_inputs(&inp, 3, "");
    let cfg = dir.path().join("f.toml");
    std::fs::write(&cfg, SPARSE).unwrap();
    let plain = dir.path().join("plain");
    apply(&inp, &plain, &cfg, &["--threads", "2"]);
    let out = dir.path().join("out");
    apply(&inp, &out, &cfg, &["--threads", "2", "--mask-deltas"]);
    assert_eq!(pngs(&plain), pngs(&out), "masks do not change the output");
    let recs = log_records(&out.join("groundtruth.jsonl"));
    let frames: Vec<_> = recs.iter().filter(|r| r["record"] == "frame").collect();
    assert_eq!(frames.len(), 3);
    for r in frames {
        let m = &r["masks"];
        let names: Vec<_> = r["effects"].as_array().unwrap().iter().map(|e| e["name"].clone()).collect();
        assert_eq!(m["bits"].as_array().unwrap(), &names, "bit k = effects[k]");
        let labels = image::open(m["labels"].as_str().unwrap()).unwrap().into_luma16();
        let input = image::open(inp.join(r["input"].as_str().unwrap())).unwrap().into_luma8();
        let output = image::open(r["output"].as_str().unwrap()).unwrap().into_luma8();
        let mut labelled = 0;
        for (x, y, l) in labels.enumerate_pixels() {
            let changed = input.get_pixel(x, y) != output.get_pixel(x, y);
            if changed {
                assert_ne!(l.0[0], 0, "a changed pixel is labelled ({x},{y})");
            }
            if l.0[0] == 0 {
                assert!(!changed);
            } else {
                labelled += 1;
            }
            assert!(l.0[0] < 4, "two effects: bits 0 and 1 only");
        }
        assert!(labelled > 0);
        for d in m["deltas"].as_array().unwrap() {
            assert!(Path::new(d["path"].as_str().unwrap()).exists());
        }
        assert!(m["deltas"].as_array().unwrap().iter().any(|d| d["effect"] == "hot_pixels"));
    }
}

#[test]
fn unknown_effect_error_is_printed_once() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("x.toml");
    std::fs::write(&cfg, "[[effects]]\nname = \"jpegg\"\n").unwrap();
    let inp = dir.path().join("in");
    std::fs::create_dir(&inp).unwrap();
    let out = faultcam()
        .args(["apply", "--in"])
        .arg(&inp)
        .arg("--out")
        .arg(dir.path().join("out"))
        .arg("--faults")
        .arg(&cfg)
        .assert()
        .code(2)
        .get_output()
        .stderr
        .clone();
    let err = String::from_utf8(out).unwrap();
    assert_eq!(err.matches("unknown effect 'jpegg'").count(), 1, "{err}");
    assert!(err.contains("x.toml:1:") && err.contains("jpeg"), "{err}");
}

#[test]
fn bench_prints_latency_percentiles_and_the_same_digest_on_one_and_two_threads() {
    let out = faultcam()
        .args(["bench", "--faults", "hil/campaigns/original8.toml", "--effect", "gamma", "--set", "gamma.gamma=0.5"])
        .args(["--size", "96x64", "--format", "mono8,rgb8", "--threads", "1,2", "--frames", "4", "--warmup", "1"])
        .assert()
        .success()
        .get_output()
        .stdout
        .clone();
    let text = String::from_utf8(out).unwrap();
    assert!(text.contains("p50 ms") && text.contains("p99 ms") && text.contains("max ms"), "{text}");
    // Digest of the chain's output frames: one per (format, threads); equal across thread counts.
    let digests = |fmt: &str| -> Vec<String> {
        let mut cur = String::new();
        let mut out = Vec::new();
        for line in text.lines() {
            if line.starts_with("96x64") {
                cur = line.to_string();
            } else if line.trim_start().starts_with("chain (") && cur.contains(fmt) {
                out.push(line.split_whitespace().last().unwrap().to_string());
            }
        }
        out
    };
    for fmt in ["mono8", "rgb8"] {
        let d = digests(fmt);
        assert_eq!(d.len(), 2, "{fmt}: {text}");
        assert_eq!(d[0], d[1], "{fmt}: output differs between 1 and 2 threads");
        assert_eq!(d[0].len(), 16);
    }
    assert!(text.lines().any(|l| l.trim_start().starts_with("lens_flare")), "per-effect rows");
    let md = faultcam()
        .args(["bench", "--effect", "vignetting", "--size", "64x48", "--frames", "2", "--markdown"])
        .assert()
        .success()
        .get_output()
        .stdout
        .clone();
    let md = String::from_utf8(md).unwrap();
    assert!(
        md.contains("| case | effect |") && md.contains("| single | vignetting | optics | 64x48 | rgb8 | 1 |"),
        "{md}"
    );
    faultcam().args(["bench", "--size", "64x48"]).assert().code(2);
    faultcam().args(["bench", "--effect", "nope"]).assert().code(2);
}

/// `faultcam bench ARGS` with the kernel set `env` names (`FAULTCAM_NO_AVX512`,
/// `FAULTCAM_NO_SIMD`, or `None`: the fastest this CPU has); its standard output.
fn bench_on_kernels(env: Option<&str>, args: &[&str]) -> String {
    let mut cmd = faultcam();
    cmd.env_remove("FAULTCAM_NO_AVX512").env_remove("FAULTCAM_NO_SIMD");
    if let Some(var) = env {
        cmd.env(var, "1");
    }
    let out = cmd.arg("bench").args(args).assert().success().get_output().stdout.clone();
    String::from_utf8(out).unwrap()
}

/// The rows of a `faultcam bench` output that end in an output digest: (first word, digest).
fn bench_digests(text: &str) -> Vec<(String, String)> {
    text.lines()
        .filter_map(|l| {
            let d = l.split_whitespace().last()?;
            (d.len() == 16 && d.bytes().all(|b| b.is_ascii_hexdigit()))
                .then(|| (l.split_whitespace().next().unwrap().to_string(), d.to_string()))
        })
        .collect()
}

/// Every kernel set gives the same bytes: the chain and every effect alone, in each format, with
/// the fastest kernels this CPU has, with `FAULTCAM_NO_AVX512` (AVX2 on an AVX-512 machine) and
/// with `FAULTCAM_NO_SIMD` (the scalar references), compared digest by digest. The frame size is
/// odd so every SIMD tail runs too. `faultcam bench` names the kernel set it ran.
#[test]
fn scalar_avx2_and_avx512_kernels_give_the_same_bytes() {
    let run = |env: Option<&str>| -> (String, Vec<String>) {
        let args = [
            ["--faults", "hil/campaigns/original8.toml", "--all-effects"].as_slice(),
            &["--size", "333x203", "--format", "mono8,rgb8,mono16"],
            &["--frames", "2", "--warmup", "0", "--scene", "stress"],
        ];
        let text = bench_on_kernels(env, &args.concat());
        let kernels = text.lines().find(|l| l.starts_with("CPU: ")).expect("CPU line").to_string();
        let rows = bench_digests(&text).into_iter().map(|(name, d)| format!("{name} {d}")).collect();
        (kernels, rows)
    };
    let (fast_k, fast) = run(None);
    let (avx2_k, avx2) = run(Some("FAULTCAM_NO_AVX512"));
    let (scalar_k, scalar) = run(Some("FAULTCAM_NO_SIMD"));
    assert!(scalar_k.ends_with("kernels: scalar"), "{scalar_k}");
    assert!(!avx2_k.contains("AVX-512"), "{avx2_k}");
    assert!(fast_k.contains(" kernels: ") && !fast_k.contains("CPU: ;"), "{fast_k}");
    // Chain and every effect, three formats, one frame size.
    assert!(fast.len() > 3 * registry::all().len(), "{fast:?}");
    assert_eq!(fast, avx2, "{fast_k} vs {avx2_k}");
    assert_eq!(fast, scalar, "{fast_k} vs {scalar_k}");
}

/// Blooming where saturation covers every tile (`--scene ramp`: diagonal ramps, about a fifth
/// of the samples over the well, the breadth-first fill busy across the frame): the same bytes
/// with the fastest kernels, `FAULTCAM_NO_AVX512` and `FAULTCAM_NO_SIMD`, on 1 and 2 threads.
#[test]
fn blooming_on_dense_saturation_gives_the_same_bytes_on_every_path_and_thread_count() {
    let digests = |env: Option<&str>| -> Vec<String> {
        let args = [
            ["--effect", "blooming", "--set", "blooming.full_well_fraction=0.95"].as_slice(),
            &["--set", "blooming.exposure_gain=1.2", "--set", "blooming.spread_px=2", "--scene", "ramp"],
            &["--size", "333x203", "--format", "mono8,rgb8,mono16", "--threads", "1,2"],
            &["--frames", "2", "--warmup", "0"],
        ];
        let text = bench_on_kernels(env, &args.concat());
        bench_digests(&text).into_iter().filter(|(name, _)| name == "blooming").map(|(_, d)| d).collect()
    };
    let fast = digests(None);
    // 3 formats x 2 thread counts, each with a digest; the formats differ.
    assert_eq!(fast.len(), 6, "{fast:?}");
    assert!(fast.iter().all(|d| d.len() == 16 && d.bytes().all(|b| b.is_ascii_hexdigit())), "{fast:?}");
    assert!(fast[0] == fast[1] && fast[0] != fast[2], "{fast:?}");
    assert_eq!(fast, digests(Some("FAULTCAM_NO_AVX512")));
    assert_eq!(fast, digests(Some("FAULTCAM_NO_SIMD")));
}

/// The blurs at strengths that take the sigma-independent paths (defocus box cascade) and the
/// FIR paths: the same bytes with the fastest kernels, `FAULTCAM_NO_AVX512` and `FAULTCAM_NO_SIMD`.
#[test]
fn blur_kernels_give_the_same_bytes_on_every_path() {
    let cases: &[&[&str]] = &[
        &["--effect", "defocus", "--set", "defocus.sigma_px=4"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=20"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=0.7"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=2.5"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=8"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=3"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=4.5"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=1.8"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=1.85"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=9.5"],
        &["--effect", "defocus", "--set", "defocus.sigma_px=13"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=30", "--set", "motion_blur.angle_deg=30"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=100", "--set", "motion_blur.angle_deg=137"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=0.7", "--set", "motion_blur.angle_deg=0"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=25", "--set", "motion_blur.angle_deg=80"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=61", "--set", "motion_blur.angle_deg=10"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=60", "--set", "motion_blur.angle_deg=100"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=40", "--set", "motion_blur.angle_deg=30"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=90", "--set", "motion_blur.angle_deg=0"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=30", "--set", "motion_blur.angle_deg=170"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=24.5", "--set", "motion_blur.angle_deg=90"],
        // The 8-bit FIR: the column kernel (oblique and vertical streaks), the row kernel (0 deg).
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=10", "--set", "motion_blur.angle_deg=30"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=24", "--set", "motion_blur.angle_deg=100"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=23", "--set", "motion_blur.angle_deg=145"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=12", "--set", "motion_blur.angle_deg=0"],
        // The row box (exactly along x, longer than 28 px): 90 px at 0 deg above, and these.
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=29", "--set", "motion_blur.angle_deg=180"],
        &["--effect", "motion_blur", "--set", "motion_blur.length_px=66", "--set", "motion_blur.angle_deg=0"],
    ];
    for case in cases {
        let run = |env: Option<&str>| -> Vec<String> {
            let size = ["--size", "333x203", "--format", "mono8,rgb8", "--frames", "1", "--warmup", "0"];
            let text = bench_on_kernels(env, &[*case, &size, &["--scene", "stress"]].concat());
            bench_digests(&text).into_iter().map(|(_, d)| d).collect()
        };
        let fast = run(None);
        assert_eq!(fast.len(), 2, "{case:?}: {fast:?}");
        assert_eq!(fast, run(Some("FAULTCAM_NO_AVX512")), "{case:?}");
        assert_eq!(fast, run(Some("FAULTCAM_NO_SIMD")), "{case:?}");
    }
}
