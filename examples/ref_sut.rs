//! Reference pose estimator for `faultcam sweep`: a batch SUT for the `synth:` spacecraft.
//!
//! Usage: `ref_sut IN_DIR OUT_FILE [CAMERA_JSON]` — reads every image of IN_DIR (sorted by
//! name), estimates the spacecraft's pose in each and writes one JSON line per image it could
//! estimate: `{"file":"frame_000000.png","q":[w,x,y,z],"t":[x,y,z]}` (faultcam's pose
//! convention: q scalar first, rotation body → camera; camera x right, y down, z forward; m).
//!
//! Live: `ref_sut --live IN_DIR REPORT [CAMERA_JSON]` — watches IN_DIR (a `files:` sink) and
//! reports each new `frame_NNNNNN` image as `{"seq":N,"q":..,"t":..}` (`{"seq":N}` when it
//! finds no pose) to REPORT (`-` stdout, or `udp:HOST:PORT` / `HOST:PORT`) until its standard
//! input closes: `faultcam sweep --live --sut 'ref_sut --live {in_dir} - {camera}'`. IN_DIR
//! may be `v4l2:/dev/videoN` instead: the live sweep's v4l2loopback sink, read as a camera (the
//! seq from each buffer's timestamp, see `faultcam::sweep::live`).
//! CAMERA_JSON (`{"fx","fy","cx","cy"}`, what `faultcam sweep` passes as `{camera}`) gives the
//! focal length; without it the synth default (30° horizontal field of view) is assumed.
//!
//! Method: model-based render-and-compare. The estimator knows the spacecraft's 3-D model (it
//! renders hypotheses with `faultcam::source::synth`, the same model and lighting) and that the
//! target is centred on the optical axis, as `synth:` renders it: it estimates attitude and
//! range (4 degrees of freedom), `t = [0, 0, range]`.
//! 1. The image's median (the dark level of space) is subtracted; the image is reduced by area
//!    averaging to about 160 px wide and box-blurred.
//! 2. Coarse search: yaw and roll every 30°, pitch every 30° in −90..=90 (1008 attitudes); for
//!    each, the range follows from the silhouette area (area ∝ 1/range²: render at 25 m, count
//!    pixels above 8 DN against those of the blurred image, scale), then the hypothesis is rendered at that range and scored by the
//!    sum of squared differences to the observed image.
//! 3. The six best hypotheses are refined by Nelder–Mead over (yaw, pitch, roll, ln range) at the
//!    reduced size, the best of them again at full size (blur radius 1).
//!
//! An image with no blurred pixel 8 DN above its median gets no pose. Clean `synth:` frames come out within a
//! fraction of a degree and of a per cent of range; faults move the optimum (noise, blur) or
//! break the silhouette (glare, glitches), which is what a sweep measures.

use faultcam::frame::{Frame, FrameData, PixelFormat};
use faultcam::pose::quat_from_matrix;
use faultcam::source::synth::{Pose, SynthConfig, SynthSource};
use faultcam::sweep::live::sut;
use std::path::Path;

#[path = "support/blur.rs"]
mod blur;
use blur::box_blur;

const FG_DN: f32 = 8.0;

/// One resolution: the observed image (blurred) and a renderer of the same size and field.
struct Level {
    w: usize,
    h: usize,
    blur: usize,
    obs: Vec<f32>,
    src: SynthSource,
    frame: Frame,
    tmp: Vec<f32>,
    tmp2: Vec<f32>,
}

impl Level {
    fn new(full: &[f32], fw: usize, fh: usize, k: usize, fov_deg: f64, blur: usize) -> Level {
        let (w, h) = (fw / k, fh / k);
        let mut obs = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut s = 0.0;
                for dy in 0..k {
                    for dx in 0..k {
                        s += full[(y * k + dy) * fw + x * k + dx];
                    }
                }
                obs[y * w + x] = s / (k * k) as f32;
            }
        }
        let mut tmp = Vec::new();
        box_blur(&mut obs, &mut tmp, w, h, blur);
        let cfg = SynthConfig {
            width: w as u32,
            height: h as u32,
            format: PixelFormat::Mono8,
            frames: 1,
            spin_dps: 0.0,
            stars: false,
            earth: false,
            fov_deg,
            glint_px: ((fh as f64 / 400.0).max(2.0) / k as f64).max(0.3),
            ..SynthConfig::default()
        };
        let frame = Frame::empty();
        Level { w, h, blur, obs, src: SynthSource::new(cfg), frame, tmp, tmp2: Vec::new() }
    }

    fn render(&mut self, p: &Pose) {
        self.src.render_pose(0, p, &mut self.frame);
        let FrameData::U8(d) = &self.frame.data else { unreachable!("mono8 renderer") };
        self.tmp2.clear();
        self.tmp2.extend(d.iter().map(|&v| v as f32));
    }

    fn area(&mut self, p: &Pose) -> usize {
        self.render(p);
        self.tmp2.iter().filter(|&&v| v > FG_DN).count()
    }

    fn cost(&mut self, p: &Pose) -> f64 {
        self.render(p);
        box_blur(&mut self.tmp2, &mut self.tmp, self.w, self.h, self.blur);
        self.obs.iter().zip(&self.tmp2).map(|(a, b)| ((a - b) as f64).powi(2)).sum()
    }
}

fn pose_of(x: &[f64; 4]) -> Pose {
    Pose { yaw_deg: x[0], pitch_deg: x[1], roll_deg: x[2], distance_m: x[3].exp().clamp(8.0, 1e5) }
}

/// Nelder–Mead minimisation from `x0` with initial steps `step`, `iters` iterations.
fn nelder_mead(f: &mut dyn FnMut(&[f64; 4]) -> f64, x0: [f64; 4], step: [f64; 4], iters: usize) -> ([f64; 4], f64) {
    let mut pts: Vec<([f64; 4], f64)> = Vec::with_capacity(5);
    pts.push((x0, f(&x0)));
    for i in 0..4 {
        let mut x = x0;
        x[i] += step[i];
        pts.push((x, f(&x)));
    }
    for _ in 0..iters {
        pts.sort_by(|a, b| a.1.total_cmp(&b.1));
        let mut c = [0.0; 4];
        for p in &pts[..4] {
            for (ci, v) in c.iter_mut().zip(&p.0) {
                *ci += v / 4.0;
            }
        }
        let worst = pts[4];
        let along = |t: f64| -> [f64; 4] { std::array::from_fn(|i| c[i] + t * (worst.0[i] - c[i])) };
        let xr = along(-1.0);
        let fr = f(&xr);
        if fr < pts[0].1 {
            let xe = along(-2.0);
            let fe = f(&xe);
            pts[4] = if fe < fr { (xe, fe) } else { (xr, fr) };
        } else if fr < pts[3].1 {
            pts[4] = (xr, fr);
        } else {
            let xc = if fr < worst.1 { along(-0.5) } else { along(0.5) };
            let fc = f(&xc);
            if fc < worst.1.min(fr) {
                pts[4] = (xc, fc);
            } else {
                let best = pts[0].0;
                for p in pts.iter_mut().skip(1) {
                    p.0 = std::array::from_fn(|i| best[i] + 0.5 * (p.0[i] - best[i]));
                    p.1 = f(&p.0);
                }
            }
        }
    }
    pts.sort_by(|a, b| a.1.total_cmp(&b.1));
    pts[0]
}

/// Largest k <= `w / 120` dividing both sides (1 for small images).
fn reduction(w: usize, h: usize) -> usize {
    (1..=(w / 120).max(1)).rev().find(|k| w.is_multiple_of(*k) && h.is_multiple_of(*k)).unwrap_or(1)
}

fn estimate(path: &Path, fov_deg: f64) -> Option<Pose> {
    let img = image::open(path).ok()?.to_luma8();
    let (fw, fh) = (img.width() as usize, img.height() as usize);
    // Background subtraction: most of the frame is space, so its median is the dark level
    // (offsets, dark current, stray light); the renderer's space is 0.
    let mut sorted = img.as_raw().clone();
    sorted.sort_unstable();
    let bg = sorted[sorted.len() / 2] as f32;
    let full: Vec<f32> = img.as_raw().iter().map(|&v| v as f32 - bg).collect();
    let k = reduction(fw, fh);
    let mut lo = Level::new(&full, fw, fh, k, fov_deg, 2);
    // Silhouette area on the blurred, reduced image (noise averages out).
    let raw_area = lo.obs.iter().filter(|&&v| v > FG_DN).count();
    if raw_area == 0 {
        return None;
    }
    // Coarse search over attitude; range from the silhouette area.
    let mut cands: Vec<([f64; 4], f64)> = Vec::new();
    for yaw in (0..360).step_by(30) {
        for pitch in (-90..=90).step_by(30) {
            for roll in (0..360).step_by(30) {
                let (y, p, r) = (yaw as f64, pitch as f64, roll as f64);
                let a = lo.area(&Pose { yaw_deg: y, pitch_deg: p, roll_deg: r, distance_m: 25.0 });
                if a == 0 {
                    continue;
                }
                let d = (25.0 * (a as f64 / raw_area as f64).sqrt()).clamp(8.0, 1e5);
                let x = [y, p, r, d.ln()];
                let c = lo.cost(&pose_of(&x));
                cands.push((x, c));
            }
        }
    }
    cands.sort_by(|a, b| a.1.total_cmp(&b.1));
    let mut best: Option<([f64; 4], f64)> = None;
    for (x0, _) in cands.iter().take(6) {
        let r = nelder_mead(&mut |x| lo.cost(&pose_of(x)), *x0, [12.0, 12.0, 12.0, 0.08], 120);
        if best.is_none_or(|b| r.1 < b.1) {
            best = Some(r);
        }
    }
    let (x, _) = best?;
    let mut hi = Level::new(&full, fw, fh, 1, fov_deg, 1);
    let (x, _) = nelder_mead(&mut |x| hi.cost(&pose_of(x)), x, [2.0, 2.0, 2.0, 0.02], 150);
    Some(pose_of(&x))
}

/// The camera's fx from a `{camera}` JSON file (empty path or unreadable: none).
fn camera_fx(path: Option<&str>) -> Option<f64> {
    sut::camera_json(path)?.get("fx")?.as_f64()
}

/// Estimate one image: field of view from fx and the image width (synth default without fx).
fn estimate_file(p: &Path, fx: Option<f64>) -> Option<Pose> {
    let w = image::image_dimensions(p).ok()?.0 as f64;
    let fov = fx.map(|f| 2.0 * (w / (2.0 * f)).atan().to_degrees()).unwrap_or(30.0);
    estimate(p, fov)
}

fn main() -> std::process::ExitCode {
    sut::main("ref_sut", camera_fx, |p, fx| {
        estimate_file(p, fx).map(|pose| (quat_from_matrix(&pose.rotation()), [0.0, 0.0, pose.distance_m]))
    })
}
