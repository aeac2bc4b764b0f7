//! Feature-based pose estimator for `faultcam sweep`: OpenCV features and `solvePnPRansac` on
//! the `synth:` spacecraft's fiducials.
//!
//! Usage (the same command-line contract as `ref_sut`):
//! - batch: `pnp_sut IN_DIR OUT_FILE [CAMERA_JSON]` — one JSON line per image of IN_DIR (sorted
//!   by name) it could estimate: `{"file":"frame_000000.png","q":[w,x,y,z],"t":[x,y,z]}`;
//! - live: `pnp_sut --live IN_DIR REPORT [CAMERA_JSON]` — watches IN_DIR (a `files:` sink) and
//!   reports each new `frame_NNNNNN` image as `{"seq":N,"q":..,"t":..}` (`{"seq":N}` when it
//!   finds no pose) to REPORT (`-` stdout, or `udp:HOST:PORT`) until its standard input closes;
//!   IN_DIR may be `v4l2:/dev/videoN` (the live sweep's v4l2loopback sink, read as a camera).
//!
//! Pose convention: faultcam's (`src/pose.rs`): q scalar first, rotation body → camera; camera x
//! right, y down, z forward; metres. CAMERA_JSON (`{"fx","fy","cx","cy"}` in pixels, OpenCV
//! convention, what `faultcam sweep` passes as `{camera}`) gives the intrinsics; without it the
//! synth default is assumed (30° horizontal field of view, principal point at the centre).
//!
//! Method (a 6-degree-of-freedom estimate: nothing assumes the target on the optical axis):
//! 1. **Features.** The spacecraft's fiducials are its five polished fittings (two bus corners,
//!    the payload dome, the two wing tips; body-frame positions from
//!    `SynthSource::glint_points`), which glint as saturated discs. The image (luminance, 8 bit)
//!    minus its median (the dark level of space) is thresholded at 90 % of its maximum;
//!    `cv::connectedComponentsWithStats` gives the blobs; those of a glint's size (area 3 px up
//!    to 2.5·π·(3 r)², r the synth glint radius `max(2, height/400)` px) are the detections,
//!    at their centroids (at most the 8 largest).
//! 2. **Association** (RANSAC over hypotheses): every triple of detections against every
//!    ordered triple of the five model points is solved with `cv::solveP3P` (up to 4 poses
//!    each); a pose is scored by how many model points project within `tol` = max(3, 1.5 r) px
//!    of a distinct detection (then by the RMS reprojection error).
//! 3. **Pose.** For each of the best-scoring distinct hypotheses with 4 or more matched points,
//!    `cv::solvePnPRansac` (AP3P minimal sets, threshold `tol`) on the matched points, then
//!    `cv::solvePnPRefineLM` on its inliers; with 3 matched points the P3P pose stands.
//! 4. **Verification.** The fittings' layout is nearly symmetric (with the dome hidden, a
//!    180° turn maps the four other fittings onto each other), so the point fit alone cannot
//!    tell some hypotheses apart: each candidate is rendered with the spacecraft model
//!    (`SynthSource::render_pose`, at the candidate's attitude and range, shifted by its
//!    lateral offset) and the one whose image correlates best (normalised cross-correlation of
//!    the background-subtracted, box-blurred images) is reported.
//!
//! An image with fewer than 3 detections gets no pose. Faults act on the features: noise and
//! bright additive faults (flare ghosts, hot pixels, bloom) add or move blobs, blur spreads the
//! glints, gain changes move the threshold.

use faultcam::frame::{Frame, FrameData, PixelFormat};
use faultcam::pose::quat_from_matrix;
use faultcam::source::synth::{Pose as SynthPose, SynthConfig, SynthSource};
use faultcam::sweep::live::sut;
use opencv::calib3d;
use opencv::core::{self, Mat, Point2d, Point3d, TermCriteria, Vector};
use opencv::imgproc;
use opencv::prelude::*;
use std::path::Path;

#[path = "support/blur.rs"]
mod blur;
use blur::box_blur;

/// Pinhole intrinsics in pixels (OpenCV convention).
#[derive(Clone, Copy, Debug)]
struct Camera {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

impl Camera {
    /// The synth default for a `w` x `h` image: 30° horizontal field, centred.
    fn synth_default(w: usize, h: usize) -> Camera {
        let f = w as f64 / 2.0 / 15f64.to_radians().tan();
        Camera { fx: f, fy: f, cx: w as f64 / 2.0 - 0.5, cy: h as f64 / 2.0 - 0.5 }
    }

    fn matrix(&self) -> opencv::Result<Mat> {
        Mat::from_slice_2d(&[[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
    }

    fn project(&self, r: &[[f64; 3]; 3], t: &[f64; 3], p: &[f64; 3]) -> Option<(f64, f64)> {
        let c: [f64; 3] = std::array::from_fn(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + t[i]);
        (c[2] > 1e-3).then(|| (self.fx * c[0] / c[2] + self.cx, self.fy * c[1] / c[2] + self.cy))
    }
}

/// A pose hypothesis: rotation body → camera (row-major), translation (m), matched
/// (model index, detection index) pairs and their RMS reprojection error (px).
#[derive(Clone, Debug)]
struct Hypothesis {
    r: [[f64; 3]; 3],
    t: [f64; 3],
    matches: Vec<(usize, usize)>,
    rms: f64,
}

/// Rotation matrix of a Rodrigues vector.
fn rodrigues(v: [f64; 3]) -> [[f64; 3]; 3] {
    let th = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if th < 1e-12 {
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    }
    let k = v.map(|x| x / th);
    let (s, c) = th.sin_cos();
    let kx = [[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]];
    std::array::from_fn(|i| {
        std::array::from_fn(|j| {
            let id = if i == j { 1.0 } else { 0.0 };
            id * c + s * kx[i][j] + (1.0 - c) * k[i] * k[j]
        })
    })
}

/// Rodrigues vector of a rotation matrix (via the quaternion).
fn rodrigues_of(r: &[[f64; 3]; 3]) -> [f64; 3] {
    let q = quat_from_matrix(r);
    let s = (q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if s < 1e-12 {
        return [0.0; 3];
    }
    let th = 2.0 * s.atan2(q[0]);
    [q[1] / s * th, q[2] / s * th, q[3] / s * th]
}

fn mat3(m: &Mat) -> opencv::Result<[f64; 3]> {
    Ok([*m.at::<f64>(0)?, *m.at::<f64>(1)?, *m.at::<f64>(2)?])
}

/// Glint detections: centroids (px, OpenCV convention) of bright blobs of a glint's size.
fn detect(gray: &[u8], w: usize, h: usize, bg: u8) -> opencv::Result<Vec<(f64, f64)>> {
    let maxv = gray.iter().copied().max().unwrap_or(0);
    if maxv as f64 - (bg as f64) < 20.0 {
        return Ok(Vec::new());
    }
    let thr = bg as f64 + 0.9 * (maxv as f64 - bg as f64);
    let mask: Vec<u8> = gray.iter().map(|&v| if v as f64 >= thr { 255 } else { 0 }).collect();
    let mask = Mat::new_rows_cols_with_data(h as i32, w as i32, &mask)?;
    let (mut labels, mut stats, mut cents) = (Mat::default(), Mat::default(), Mat::default());
    let n = imgproc::connected_components_with_stats(&mask, &mut labels, &mut stats, &mut cents, 8, core::CV_32S)?;
    let r = (h as f64 / 400.0).max(2.0);
    let max_area = 2.5 * std::f64::consts::PI * (3.0 * r).powi(2);
    let mut blobs: Vec<(i32, f64, f64)> = Vec::new();
    for i in 1..n {
        let area = *stats.at_2d::<i32>(i, imgproc::CC_STAT_AREA)?;
        if area < 3 || area as f64 > max_area {
            continue;
        }
        blobs.push((area, *cents.at_2d::<f64>(i, 0)?, *cents.at_2d::<f64>(i, 1)?));
    }
    // Largest first; ties by position, so the order never depends on labelling details.
    blobs.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.total_cmp(&b.1)).then(a.2.total_cmp(&b.2)));
    blobs.truncate(8);
    Ok(blobs.into_iter().map(|(_, x, y)| (x, y)).collect())
}

/// Match the projected model points to detections (greedy by distance, each used once).
fn score(
    cam: &Camera,
    model: &[[f64; 3]],
    det: &[(f64, f64)],
    r: &[[f64; 3]; 3],
    t: &[f64; 3],
    tol: f64,
) -> (Vec<(usize, usize)>, f64) {
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (m, p) in model.iter().enumerate() {
        let Some((u, v)) = cam.project(r, t, p) else { continue };
        for (d, &(x, y)) in det.iter().enumerate() {
            let e = ((u - x).powi(2) + (v - y).powi(2)).sqrt();
            if e < tol {
                pairs.push((e, m, d));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let (mut used_m, mut used_d) = (0u32, 0u32);
    let (mut matches, mut ss) = (Vec::new(), 0.0);
    for (e, m, d) in pairs {
        if used_m & (1 << m) == 0 && used_d & (1 << d) == 0 {
            used_m |= 1 << m;
            used_d |= 1 << d;
            matches.push((m, d));
            ss += e * e;
        }
    }
    matches.sort_unstable();
    let rms = if matches.is_empty() { f64::INFINITY } else { (ss / matches.len() as f64).sqrt() };
    (matches, rms)
}

fn p3(p: &[f64; 3]) -> Point3d {
    Point3d::new(p[0], p[1], p[2])
}

/// Step 2: P3P over every detection triple and ordered model triple.
fn hypotheses(cam: &Camera, model: &[[f64; 3]], det: &[(f64, f64)], tol: f64) -> opencv::Result<Vec<Hypothesis>> {
    let k = cam.matrix()?;
    let dist = Mat::default();
    let mut out = Vec::new();
    let n = det.len();
    let mut obj = Vector::<Point3d>::new();
    let mut img = Vector::<Point2d>::new();
    for a in 0..n {
        for b in a + 1..n {
            for c in b + 1..n {
                img.clear();
                for &i in &[a, b, c] {
                    img.push(Point2d::new(det[i].0, det[i].1));
                }
                for ma in 0..model.len() {
                    for mb in 0..model.len() {
                        for mc in 0..model.len() {
                            if ma == mb || mb == mc || ma == mc {
                                continue;
                            }
                            obj.clear();
                            for &m in &[ma, mb, mc] {
                                obj.push(p3(&model[m]));
                            }
                            let (mut rv, mut tv) = (Vector::<Mat>::new(), Vector::<Mat>::new());
                            let ns = calib3d::solve_p3p(&obj, &img, &k, &dist, &mut rv, &mut tv, calib3d::SOLVEPNP_P3P)
                                .unwrap_or(0);
                            for s in 0..ns.max(0) as usize {
                                let (r, t) = (rodrigues(mat3(&rv.get(s)?)?), mat3(&tv.get(s)?)?);
                                if !(0.5..1e5).contains(&t[2])
                                    || t.iter().chain(r.iter().flatten()).any(|v| !v.is_finite())
                                {
                                    continue;
                                }
                                let (matches, rms) = score(cam, model, det, &r, &t, tol);
                                if matches.len() >= 3 {
                                    out.push(Hypothesis { r, t, matches, rms });
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    Ok(out)
}

/// Step 3: solvePnPRansac + solvePnPRefineLM on a hypothesis's matched points (4 or more).
fn refine(
    cam: &Camera,
    model: &[[f64; 3]],
    det: &[(f64, f64)],
    h: &Hypothesis,
    tol: f64,
) -> opencv::Result<Hypothesis> {
    if h.matches.len() < 4 {
        return Ok(h.clone());
    }
    let k = cam.matrix()?;
    let dist = Mat::default();
    let obj: Vector<Point3d> = h.matches.iter().map(|&(m, _)| p3(&model[m])).collect();
    let img: Vector<Point2d> = h.matches.iter().map(|&(_, d)| Point2d::new(det[d].0, det[d].1)).collect();
    let mut rvec = Mat::from_slice(&rodrigues_of(&h.r))?.try_clone()?;
    let mut tvec = Mat::from_slice(&h.t)?.try_clone()?;
    let mut inliers = Vector::<i32>::new();
    let ok = calib3d::solve_pnp_ransac(
        &obj,
        &img,
        &k,
        &dist,
        &mut rvec,
        &mut tvec,
        true,
        100,
        tol as f32,
        0.99,
        &mut inliers,
        calib3d::SOLVEPNP_AP3P,
    )
    .unwrap_or(false);
    if !ok || inliers.len() < 4 {
        return Ok(h.clone());
    }
    let obj_in: Vector<Point3d> = inliers.iter().map(|i| obj.get(i as usize)).collect::<opencv::Result<_>>()?;
    let img_in: Vector<Point2d> = inliers.iter().map(|i| img.get(i as usize)).collect::<opencv::Result<_>>()?;
    let crit = TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 30, 1e-10)?;
    calib3d::solve_pnp_refine_lm(&obj_in, &img_in, &k, &dist, &mut rvec, &mut tvec, crit)?;
    let (r, t) = (rodrigues(mat3(&rvec)?), mat3(&tvec)?);
    if !(0.5..1e5).contains(&t[2]) || t.iter().chain(r.iter().flatten()).any(|v| !v.is_finite()) {
        return Ok(h.clone());
    }
    let (matches, rms) = score(cam, model, det, &r, &t, tol);
    if matches.len() < h.matches.len() {
        return Ok(h.clone());
    }
    Ok(Hypothesis { r, t, matches, rms })
}

/// Rotation angle between two rotation matrices (rad).
fn angle_between(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> f64 {
    // trace(A^T B) = 1 + 2 cos θ
    let tr: f64 = (0..3).map(|i| (0..3).map(|k| a[k][i] * b[k][i]).sum::<f64>()).sum();
    ((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}

/// The synth's (yaw, pitch, roll) of `R = Rz(roll) · Rx(pitch) · Ry(yaw)`, degrees.
fn synth_angles(r: &[[f64; 3]; 3]) -> (f64, f64, f64) {
    let pitch = r[2][1].clamp(-1.0, 1.0).asin();
    let yaw = (-r[2][0]).atan2(r[2][2]);
    let roll = (-r[0][1]).atan2(r[1][1]);
    (yaw.to_degrees(), pitch.to_degrees(), roll.to_degrees())
}

/// Step 4: renders candidates with the spacecraft model and correlates them with the image.
struct Verifier {
    w: usize,
    h: usize,
    cam: Camera,
    obs: Vec<f32>,
    src: SynthSource,
    frame: Frame,
    img: Vec<f32>,
    tmp: Vec<f32>,
}

impl Verifier {
    fn new(full: &[f32], w: usize, h: usize, cam: Camera) -> Verifier {
        let mut obs = full.to_vec();
        let mut tmp = Vec::new();
        box_blur(&mut obs, &mut tmp, w, h, 1);
        // The renderer's field of view from fx (square pixels, centred principal point).
        let fov_deg = 2.0 * (w as f64 / (2.0 * cam.fx)).atan().to_degrees();
        let cfg = SynthConfig {
            width: w as u32,
            height: h as u32,
            format: PixelFormat::Mono8,
            frames: 1,
            spin_dps: 0.0,
            stars: false,
            earth: false,
            fov_deg,
            ..SynthConfig::default()
        };
        Verifier { w, h, cam, obs, src: SynthSource::new(cfg), frame: Frame::empty(), img: Vec::new(), tmp }
    }

    /// Normalised cross-correlation of the candidate's rendering with the image.
    fn ncc(&mut self, hyp: &Hypothesis) -> f64 {
        let (yaw_deg, pitch_deg, roll_deg) = synth_angles(&hyp.r);
        let dist = (hyp.t.iter().map(|v| v * v).sum::<f64>()).sqrt();
        let pose = SynthPose { yaw_deg, pitch_deg, roll_deg, distance_m: dist.clamp(8.0, 1e5) };
        self.src.render_pose(0, &pose, &mut self.frame);
        let FrameData::U8(d) = &self.frame.data else { unreachable!("mono8 renderer") };
        let (w, h) = (self.w, self.h);
        // The renderer puts the target on the axis: shift by the candidate's lateral offset
        // (and the principal point's offset from the centre).
        let dx = (self.cam.fx * hyp.t[0] / hyp.t[2] + self.cam.cx - (w as f64 / 2.0 - 0.5)).round() as i64;
        let dy = (self.cam.fy * hyp.t[1] / hyp.t[2] + self.cam.cy - (h as f64 / 2.0 - 0.5)).round() as i64;
        self.img.clear();
        self.img.resize(w * h, 0.0);
        for y in 0..h as i64 {
            let sy = y - dy;
            if sy < 0 || sy >= h as i64 {
                continue;
            }
            for x in 0..w as i64 {
                let sx = x - dx;
                if sx >= 0 && sx < w as i64 {
                    self.img[(y as usize) * w + x as usize] = d[sy as usize * w + sx as usize] as f32;
                }
            }
        }
        box_blur(&mut self.img, &mut self.tmp, w, h, 1);
        let n = (w * h) as f64;
        let (ma, mb) =
            (self.obs.iter().map(|&v| v as f64).sum::<f64>() / n, self.img.iter().map(|&v| v as f64).sum::<f64>() / n);
        let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
        for (&a, &b) in self.obs.iter().zip(&self.img) {
            let (a, b) = (a as f64 - ma, b as f64 - mb);
            sab += a * b;
            saa += a * a;
            sbb += b * b;
        }
        if saa <= 0.0 || sbb <= 0.0 { -1.0 } else { sab / (saa * sbb).sqrt() }
    }
}

/// Most candidates refined and verified per image.
const MAX_CANDIDATES: usize = 400;

fn estimate(path: &Path, cam: Option<Camera>) -> Option<([f64; 4], [f64; 3])> {
    let img = image::open(path).ok()?.to_luma8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    let cam = cam.unwrap_or_else(|| Camera::synth_default(w, h));
    let gray = img.as_raw();
    let mut sorted = gray.clone();
    sorted.sort_unstable();
    let bg = sorted[sorted.len() / 2];
    let det = detect(gray, w, h, bg).ok()?;
    if det.len() < 3 {
        return None;
    }
    let model = SynthSource::new(SynthConfig { width: 16, height: 16, stars: false, ..SynthConfig::default() })
        .glint_points()
        .to_vec();
    let r_glint = (h as f64 / 400.0).max(2.0);
    let tol = (1.5 * r_glint).max(3.0);
    let mut hyps = hypotheses(&cam, &model, &det, tol).ok()?;
    let best = hyps.iter().map(|h| h.matches.len()).max()?;
    hyps.retain(|h| h.matches.len() == best);
    hyps.sort_by(|a, b| a.rms.total_cmp(&b.rms));
    // Distinct candidates (3° in attitude, 2 % in position apart).
    let mut cands: Vec<Hypothesis> = Vec::new();
    for hyp in hyps {
        let tn = hyp.t.iter().map(|v| v * v).sum::<f64>().sqrt();
        let same = cands.iter().any(|c| {
            let dt = (0..3).map(|i| (c.t[i] - hyp.t[i]).powi(2)).sum::<f64>().sqrt();
            angle_between(&c.r, &hyp.r) < 3f64.to_radians() && dt < 0.02 * tn
        });
        if !same {
            cands.push(hyp);
            if cands.len() == MAX_CANDIDATES {
                break;
            }
        }
    }
    let full: Vec<f32> = gray.iter().map(|&v| (v as f32 - bg as f32).max(0.0)).collect();
    let mut ver = Verifier::new(&full, w, h, cam);
    let mut best: Option<(f64, Hypothesis)> = None;
    for c in &cands {
        // An OpenCV error in the refinement leaves the P3P pose.
        let c = refine(&cam, &model, &det, c, tol).unwrap_or_else(|_| c.clone());
        let s = ver.ncc(&c);
        if best.as_ref().is_none_or(|b| s > b.0) {
            best = Some((s, c));
        }
    }
    let (_, b) = best?;
    Some((quat_from_matrix(&b.r), b.t))
}

/// Intrinsics from a `{camera}` JSON file (empty path or unreadable: none).
fn camera_of(path: Option<&str>) -> Option<Camera> {
    let v = sut::camera_json(path)?;
    let g = |k: &str| v.get(k).and_then(|x| x.as_f64());
    Some(Camera { fx: g("fx")?, fy: g("fy")?, cx: g("cx")?, cy: g("cy")? })
}

fn main() -> std::process::ExitCode {
    // OpenCV's own threads add nothing here (small calls; batch mode is parallel over files).
    let _ = core::set_num_threads(1);
    sut::main("pnp_sut", camera_of, estimate)
}
