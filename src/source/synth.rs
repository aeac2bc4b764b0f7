//! `synth:` source: a procedural spacecraft scene, so demos and tests need no camera or data.
//!
//! URI: `synth:?width=640&height=480&format=mono8&frames=100&fps=30&yaw=35&pitch=20&roll=10&
//! distance_m=25&spin_dps=3&earth=false&stars=true&seed=0&fov_deg=30&glint_px=0`.
//!
//! The scene (camera frame: x right, y down, z along the optical axis, metres):
//! - **Space**: black (0 DN) with optional faint stars (single pixels, 5–60 DN in 8-bit scale).
//! - **Spacecraft** at `distance_m` on the optical axis: a 1.6 × 2.0 × 1.6 m bus (gold MLI on four
//!   faces with a fine crinkle pattern, white radiators front and back, aluminium edge frames),
//!   a 0.45 m radius payload cylinder on top, and two 4.0 × 1.4 m solar wings with a 10 × 4 cell
//!   grid (dark blue cells, silver gaps and frame; the backs are grey). Faces are flat,
//!   Lambertian (`L = albedo · (ambient + E · max(0, n·s))`, `E = 0.95`, `ambient = 0.03`, in
//!   units of full scale) plus a per-face Phong specular lobe on the cell cover glass; no cast
//!   shadows. The sun direction `s` is fixed: upper left, from behind the camera.
//! - **Glints**: five small polished fittings (bus corners, payload dome, wing tips) reflect the
//!   sun as saturated discs of radius `glint_px` (default `max(2, height/400)` px) with a
//!   Gaussian halo; a sphere shows its specular point from any direction, so visible fittings
//!   always glint (occlusion by a z-buffer).
//! - **Earth limb** (`earth=true`): a bright disc below a curved horizon with cloud texture, a
//!   blue haze inside the limb and an exponential atmosphere glow above it.
//!
//! Pose: attitude `R = Rz(roll) · Rx(pitch) · Ry(yaw)` (degrees), with `yaw(t) = yaw + spin_dps ·
//! t`, `t = seq / fps`; see [`SynthSource::pose`]. Pixel values are linear in radiance, full
//! scale = 1.0. Deterministic: the same options give the same bytes. The static background is
//! rendered once; each frame copies it and rasterises the model's convex faces with a z-buffer
//! (about 1–3 ms at 1920x1200 mono8 in release on one core).

use super::{Source, SourceError, UriOptions, split_uri};
use crate::frame::{Frame, FrameData, PixelFormat, Sample};
use crate::rng::{Rng, mix_seed};

/// Frames kept for reuse by [`SynthSource::recycle`].
const POOL_SIZE: usize = 4;

type V3 = [f64; 3];

fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale(a: V3, k: f64) -> V3 {
    [a[0] * k, a[1] * k, a[2] * k]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn norm(a: V3) -> V3 {
    let l = dot(a, a).sqrt();
    if l > 0.0 { scale(a, 1.0 / l) } else { a }
}

/// 3x3 rotation, row-major.
type M3 = [[f64; 3]; 3];

fn mul_mv(m: &M3, v: V3) -> V3 {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}
fn mul_mm(a: &M3, b: &M3) -> M3 {
    let mut r = [[0.0; 3]; 3];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    r
}

/// Settings of the scene (all URI options).
#[derive(Debug, Clone, PartialEq)]
pub struct SynthConfig {
    pub width: u32,
    pub height: u32,
    pub format: PixelFormat,
    /// Number of frames; 0 = endless.
    pub frames: u64,
    pub fps: f64,
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    pub roll_deg: f64,
    pub distance_m: f64,
    /// Yaw rate in degrees per second of stream time.
    pub spin_dps: f64,
    pub earth: bool,
    pub stars: bool,
    pub seed: u64,
    /// Horizontal field of view.
    pub fov_deg: f64,
    /// Radius of the saturated glint cores; 0 = `max(2, height / 400)`.
    pub glint_px: f64,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            width: 640,
            height: 480,
            format: PixelFormat::Mono8,
            frames: 100,
            fps: 30.0,
            yaw_deg: 35.0,
            pitch_deg: 20.0,
            roll_deg: 10.0,
            distance_m: 25.0,
            spin_dps: 3.0,
            earth: false,
            stars: true,
            seed: 0,
            fov_deg: 30.0,
            glint_px: 0.0,
        }
    }
}

impl SynthConfig {
    /// Read the options of a `synth:?...` URI.
    pub fn from_uri(uri: &str) -> Result<SynthConfig, SourceError> {
        let (_, body, opts) = split_uri(uri);
        let bad = |reason: String| SourceError::BadUri { uri: uri.to_string(), reason };
        if !body.is_empty() {
            return Err(bad(format!("unexpected '{body}'; options go after '?', e.g. synth:?width=640&height=480")));
        }
        let mut c = SynthConfig::default();
        let mut o = UriOptions::new(opts);
        c.width = o.int("width", 16, 16384).map_err(bad)?.map_or(c.width, |v| v as u32);
        c.height = o.int("height", 16, 16384).map_err(bad)?.map_or(c.height, |v| v as u32);
        if let Some(f) = o.raw("format") {
            c.format = match PixelFormat::parse(&f) {
                Some(p @ (PixelFormat::Mono8 | PixelFormat::Mono16 | PixelFormat::Rgb8)) => p,
                _ => return Err(bad(format!("option format={f} is not accepted; expected mono8, mono16 or rgb8"))),
            };
        }
        c.frames = o.int("frames", 0, u64::MAX).map_err(bad)?.unwrap_or(c.frames);
        c.fps = o.num("fps", 1e-3, 1e6).map_err(bad)?.unwrap_or(c.fps);
        c.yaw_deg = o.num("yaw", -360.0, 360.0).map_err(bad)?.unwrap_or(c.yaw_deg);
        c.pitch_deg = o.num("pitch", -360.0, 360.0).map_err(bad)?.unwrap_or(c.pitch_deg);
        c.roll_deg = o.num("roll", -360.0, 360.0).map_err(bad)?.unwrap_or(c.roll_deg);
        c.distance_m = o.num("distance_m", 8.0, 1e5).map_err(bad)?.unwrap_or(c.distance_m);
        c.spin_dps = o.num("spin_dps", -360.0, 360.0).map_err(bad)?.unwrap_or(c.spin_dps);
        c.earth = o.flag("earth").map_err(bad)?.unwrap_or(c.earth);
        c.stars = o.flag("stars").map_err(bad)?.unwrap_or(c.stars);
        c.seed = o.int("seed", 0, u64::MAX).map_err(bad)?.unwrap_or(c.seed);
        c.fov_deg = o.num("fov_deg", 1.0, 150.0).map_err(bad)?.unwrap_or(c.fov_deg);
        c.glint_px = o.num("glint_px", 0.0, 100.0).map_err(bad)?.unwrap_or(c.glint_px);
        o.finish().map_err(bad)?;
        Ok(c)
    }

    fn glint_radius(&self) -> f64 {
        if self.glint_px > 0.0 { self.glint_px } else { (self.height as f64 / 400.0).max(2.0) }
    }
}

/// Attitude and range of the spacecraft for one frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Pose {
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    pub roll_deg: f64,
    pub distance_m: f64,
}

impl Pose {
    /// Body-to-camera rotation `Rz(roll) · Rx(pitch) · Ry(yaw)`.
    pub fn rotation(&self) -> [[f64; 3]; 3] {
        let (sy, cy) = self.yaw_deg.to_radians().sin_cos();
        let (sp, cp) = self.pitch_deg.to_radians().sin_cos();
        let (sr, cr) = self.roll_deg.to_radians().sin_cos();
        let ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]];
        let rx = [[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]];
        let rz = [[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]];
        mul_mm(&rz, &mul_mm(&rx, &ry))
    }
}

/// Direction to the sun in the camera frame (unit): upper left, from behind the camera.
pub const SUN_DIR: V3 = [-0.48, -0.56, -0.675];
const SUN_E: f64 = 0.95;
const AMBIENT: f64 = 0.03;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Material {
    /// Gold multi-layer insulation with crinkle, aluminium edge frame.
    Mli,
    /// White radiator with edge frame.
    Radiator,
    /// Silver, plain.
    Silver,
    /// Solar cells with silver gaps and frame (back: grey).
    Panel,
}

/// Most vertices a face has (the payload cap).
const MAX_VERTS: usize = 16;

/// Colour variants per material: index 0 = edge/gap, 1..=4 = surface (crinkle levels).
const N_VARIANTS: usize = 5;

struct Face {
    /// Convex polygon, model frame.
    verts: Vec<V3>,
    /// Outward normal, model frame.
    normal: V3,
    /// Panels are seen from both sides; closed solids are back-face culled.
    two_sided: bool,
    mat: Material,
    /// Texture frame: origin, unit axes, extent in metres.
    origin: V3,
    eu: V3,
    ev: V3,
    size: (f64, f64),
}

fn quad(origin: V3, eu: V3, ev: V3, su: f64, sv: f64, normal: V3, mat: Material, two_sided: bool) -> Face {
    let verts = vec![
        origin,
        add(origin, scale(eu, su)),
        add(add(origin, scale(eu, su)), scale(ev, sv)),
        add(origin, scale(ev, sv)),
    ];
    Face { verts, normal, two_sided, mat, origin, eu, ev, size: (su, sv) }
}

/// The spacecraft model in its body frame (metres).
fn build_model() -> (Vec<Face>, Vec<V3>) {
    let mut faces = Vec::new();
    let (hx, hy, hz) = (0.8, 1.0, 0.8);
    // Bus: six faces. (axis, sign, material)
    let box_faces: [(usize, f64, Material); 6] = [
        (0, 1.0, Material::Mli),
        (0, -1.0, Material::Mli),
        (1, 1.0, Material::Mli),
        (1, -1.0, Material::Mli),
        (2, 1.0, Material::Radiator),
        (2, -1.0, Material::Radiator),
    ];
    let half = [hx, hy, hz];
    for (axis, sign, mat) in box_faces {
        let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
        let mut n = [0.0; 3];
        n[axis] = sign;
        let mut origin = [0.0; 3];
        origin[axis] = sign * half[axis];
        origin[a] = -half[a];
        origin[b] = -half[b];
        let mut eu = [0.0; 3];
        eu[a] = 1.0;
        let mut ev = [0.0; 3];
        ev[b] = 1.0;
        faces.push(quad(origin, eu, ev, 2.0 * half[a], 2.0 * half[b], n, mat, false));
    }
    // Payload cylinder on top (-y): 16 side facets and a cap.
    let (r, y0, y1, sides) = (0.45, -hy, -hy - 0.7, 16);
    let ring = |y: f64| -> Vec<V3> {
        (0..sides)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / sides as f64;
                [r * a.cos(), y, r * a.sin()]
            })
            .collect()
    };
    let (lo, hi) = (ring(y0), ring(y1));
    for i in 0..sides {
        let j = (i + 1) % sides;
        let verts = vec![lo[i], lo[j], hi[j], hi[i]];
        let mid = add(lo[i], lo[j]);
        let normal = norm([mid[0], 0.0, mid[2]]);
        let eu = norm(sub(lo[j], lo[i]));
        faces.push(Face {
            origin: lo[i],
            eu,
            ev: [0.0, -1.0, 0.0],
            size: (dot(sub(lo[j], lo[i]), eu), y0 - y1),
            verts,
            normal,
            two_sided: false,
            mat: Material::Silver,
        });
    }
    faces.push(Face {
        verts: hi.clone(),
        normal: [0.0, -1.0, 0.0],
        two_sided: false,
        mat: Material::Silver,
        origin: [-r, y1, -r],
        eu: [1.0, 0.0, 0.0],
        ev: [0.0, 0.0, 1.0],
        size: (2.0 * r, 2.0 * r),
    });
    // Yokes (thin plates) and solar wings along ±x, facing -z (the camera at zero pose).
    let (x0, x1, wy) = (1.2, 5.2, 0.7);
    for sign in [1.0, -1.0] {
        let ox = if sign > 0.0 { x0 } else { -x1 };
        faces.push(quad(
            [ox, -wy, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            x1 - x0,
            2.0 * wy,
            [0.0, 0.0, -1.0],
            Material::Panel,
            true,
        ));
        let yx = if sign > 0.0 { hx } else { -x0 };
        faces.push(quad(
            [yx, -0.06, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            x0 - hx,
            0.12,
            [0.0, 0.0, -1.0],
            Material::Silver,
            true,
        ));
    }
    // Polished fittings that glint: two bus corners, the payload dome, the wing tips.
    let glints = vec![
        [hx + 0.02, hy + 0.02, -hz - 0.02],
        [-hx - 0.02, -hy - 0.02, hz + 0.02],
        [0.0, y1 - 0.05, 0.0],
        [x1 + 0.03, -wy - 0.03, 0.0],
        [-x1 - 0.03, wy + 0.03, 0.0],
    ];
    (faces, glints)
}

fn albedo(mat: Material, back: bool) -> ([f64; 3], [f64; 3]) {
    // (surface, edge/gap)
    let alu = [0.72, 0.72, 0.74];
    match (mat, back) {
        (Material::Mli, _) => ([0.85, 0.64, 0.28], alu),
        (Material::Radiator, _) => ([0.9, 0.9, 0.88], alu),
        (Material::Silver, _) => ([0.7, 0.7, 0.72], alu),
        (Material::Panel, false) => ([0.05, 0.08, 0.26], [0.55, 0.56, 0.6]),
        (Material::Panel, true) => ([0.33, 0.33, 0.35], [0.5, 0.5, 0.52]),
    }
}

/// Lattice hash in [0, 1).
fn hash01(seed: u64, x: i64, y: i64, k: u64) -> f64 {
    (mix_seed(&[seed, x as u64, y as u64, k]) >> 11) as f64 / (1u64 << 53) as f64
}

/// Fractal value noise in [0, 1).
fn fbm(seed: u64, x: f64, y: f64, octaves: u32) -> f64 {
    let (mut sum, mut amp, mut freq, mut norm_) = (0.0, 1.0, 1.0, 0.0);
    for o in 0..octaves {
        let (fx, fy) = (x * freq, y * freq);
        let (ix, iy) = (fx.floor(), fy.floor());
        let (tx, ty) = (fx - ix, fy - iy);
        let (sx, sy) = (tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty));
        let (ix, iy) = (ix as i64, iy as i64);
        let h = |dx, dy| hash01(seed, ix + dx, iy + dy, o as u64);
        let a = h(0, 0) + (h(1, 0) - h(0, 0)) * sx;
        let b = h(0, 1) + (h(1, 1) - h(0, 1)) * sx;
        sum += amp * (a + (b - a) * sy);
        norm_ += amp;
        amp *= 0.5;
        freq *= 2.0;
    }
    sum / norm_
}

/// Static background in linear RGB (full scale 1.0), row-major.
fn background(c: &SynthConfig) -> Vec<[f32; 3]> {
    let (w, h) = (c.width as usize, c.height as usize);
    // allocation: once per stream
    let mut bg = vec![[0.0f32; 3]; w * h];
    let (wf, hf) = (w as f64, h as f64);
    let re = 2.5 * wf;
    let (ecx, ecy) = (0.35 * wf, 0.72 * hf + re);
    let glow_len = 0.012 * hf;
    let cloud_scale = hf / 6.0;
    let seed = mix_seed(&[c.seed, 0xEA27]);
    if c.earth {
        for y in 0..h {
            for x in 0..w {
                let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                let r = ((px - ecx).powi(2) + (py - ecy).powi(2)).sqrt();
                let v = if r < re {
                    let depth = re - r;
                    let n = fbm(seed, px / cloud_scale, py / cloud_scale * 3.0, 4);
                    let cloud = ((n - 0.5) / 0.15).clamp(0.0, 1.0);
                    let ground = [0.06, 0.12, 0.28];
                    let haze = 0.25 * (-depth / (3.0 * glow_len)).exp();
                    let mut v = [0.0; 3];
                    for k in 0..3 {
                        v[k] = ground[k] * (1.0 - cloud) + 0.78 * cloud + haze * [0.5, 0.7, 1.0][k];
                    }
                    v
                } else {
                    let g = 0.45 * (-(r - re) / glow_len).exp();
                    [0.4 * g, 0.6 * g, g]
                };
                bg[y * w + x] = [v[0] as f32, v[1] as f32, v[2] as f32];
            }
        }
    }
    if c.stars {
        let mut rng = Rng::new(mix_seed(&[c.seed, 0x57A2]));
        let count = (w * h / 3000).max(1);
        for _ in 0..count {
            let (x, y) = (rng.below(w as u64) as usize, rng.below(h as u64) as usize);
            let b = 0.02 + 0.22 * rng.uniform().powi(3);
            let tint = 0.85 + 0.3 * rng.uniform();
            if c.earth {
                let r = ((x as f64 + 0.5 - ecx).powi(2) + (y as f64 + 0.5 - ecy).powi(2)).sqrt();
                if r < re + 8.0 * glow_len {
                    continue;
                }
            }
            let px = &mut bg[y * w + x];
            *px = [(b * tint) as f32, b as f32, (b / tint) as f32];
        }
    }
    bg
}

/// Convert linear RGB to samples of the format (mono: Rec. 709 luminance).
fn to_samples<T: Sample>(v: [f64; 3], channels: usize) -> [T; 3] {
    if channels == 1 {
        let l = 0.2126 * v[0] + 0.7152 * v[1] + 0.0722 * v[2];
        let s = T::from_f32((l * T::MAX_F32 as f64) as f32);
        [s; 3]
    } else {
        [0, 1, 2].map(|k| T::from_f32((v[k] * T::MAX_F32 as f64) as f32))
    }
}

/// A face prepared for one frame: screen polygon and per-pixel coefficients (pixel centre u, v).
struct Prepared {
    pts: [(f32, f32); MAX_VERTS],
    npts: usize,
    /// 1/z = a·u + b·v + c.
    invz: [f32; 3],
    /// texture u = z·(au·u + bu·v + cu) − du (same for v).
    tu: [f32; 4],
    tv: [f32; 4],
    size: (f32, f32),
    mat: Material,
    variant: usize,
}

/// The `synth:` source.
pub struct SynthSource {
    cfg: SynthConfig,
    faces: Vec<Face>,
    glints: Vec<V3>,
    glint_scr: Vec<(f64, f64, f32)>,
    bg8: Vec<u8>,
    bg16: Vec<u16>,
    /// Inverse depth per pixel (0 = nothing drawn).
    zbuf: Vec<f32>,
    prepared: Vec<Prepared>,
    /// Colour variants per prepared face, as samples.
    colours8: Vec<[[u8; 3]; N_VARIANTS]>,
    colours16: Vec<[[u16; 3]; N_VARIANTS]>,
    seq: u64,
    pool: Vec<Frame>,
}

impl SynthSource {
    pub fn open(uri: &str) -> Result<SynthSource, SourceError> {
        let cfg = SynthConfig::from_uri(uri)?;
        let f = cfg.format;
        crate::limits::ImageLimits::current()
            .check("the requested size", cfg.width, cfg.height, (f.channels() * f.bytes_per_sample()) as u64)
            .map_err(|reason| SourceError::BadUri { uri: uri.to_string(), reason })?;
        Ok(SynthSource::new(cfg))
    }

    pub fn new(cfg: SynthConfig) -> SynthSource {
        let (faces, glints) = build_model();
        let bg = background(&cfg);
        let ch = cfg.format.channels();
        let mut bg8 = Vec::new();
        let mut bg16 = Vec::new();
        for v in &bg {
            let v = [v[0] as f64, v[1] as f64, v[2] as f64];
            if cfg.format == PixelFormat::Mono16 {
                bg16.push(to_samples::<u16>(v, 1)[0]);
            } else {
                bg8.extend_from_slice(&to_samples::<u8>(v, ch)[..ch]);
            }
        }
        let n = cfg.width as usize * cfg.height as usize;
        SynthSource {
            cfg,
            faces,
            glints,
            glint_scr: Vec::new(),
            bg8,
            bg16,
            zbuf: vec![0.0; n],
            prepared: Vec::new(),
            colours8: Vec::new(),
            colours16: Vec::new(),
            seq: 0,
            pool: Vec::new(),
        }
    }

    pub fn config(&self) -> &SynthConfig {
        &self.cfg
    }

    /// Pose of frame `seq`: the configured attitude, yaw advancing at `spin_dps`.
    pub fn pose(&self, seq: u64) -> Pose {
        let t = seq as f64 / self.cfg.fps;
        let yaw = (self.cfg.yaw_deg + self.cfg.spin_dps * t).rem_euclid(360.0);
        Pose {
            yaw_deg: yaw,
            pitch_deg: self.cfg.pitch_deg,
            roll_deg: self.cfg.roll_deg,
            distance_m: self.cfg.distance_m,
        }
    }

    /// Focal length in pixels.
    pub fn focal_px(&self) -> f64 {
        self.cfg.width as f64 / 2.0 / (self.cfg.fov_deg.to_radians() / 2.0).tan()
    }

    /// Camera intrinsics (OpenCV convention, see [`crate::pose`]): square pixels, principal
    /// point at the image centre.
    pub fn intrinsics(&self) -> crate::pose::Intrinsics {
        let f = self.focal_px();
        crate::pose::Intrinsics {
            fx: f,
            fy: f,
            cx: self.cfg.width as f64 / 2.0 - 0.5,
            cy: self.cfg.height as f64 / 2.0 - 0.5,
        }
    }

    /// Pose truth of frame `seq` in the [`crate::pose`] convention: `q` of `R = Rz(roll) ·
    /// Rx(pitch) · Ry(yaw)` (body → camera, scalar first), `t = [0, 0, distance_m]`.
    pub fn pose_truth(&self, seq: u64) -> crate::pose::Pose {
        let p = self.pose(seq);
        crate::pose::Pose { q: crate::pose::quat_from_matrix(&p.rotation()), t: [0.0, 0.0, p.distance_m] }
    }

    /// Pixel position of a body-frame point at `pose` (None when behind the camera).
    pub fn project(&self, pose: &Pose, p: V3) -> Option<(f64, f64)> {
        let q = add(mul_mv(&pose.rotation(), p), [0.0, 0.0, pose.distance_m]);
        let f = self.focal_px();
        (q[2] > 1e-3)
            .then(|| (self.cfg.width as f64 / 2.0 + f * q[0] / q[2], self.cfg.height as f64 / 2.0 + f * q[1] / q[2]))
    }

    /// Body-frame positions of the glinting fittings.
    pub fn glint_points(&self) -> &[V3] {
        &self.glints
    }

    /// Render frame `seq` into `frame` (reusing its buffer).
    pub fn render_into(&mut self, seq: u64, frame: &mut Frame) {
        let pose = self.pose(seq);
        self.render_pose(seq, &pose, frame);
    }

    /// Render the scene at an explicit `pose` into `frame` (labelled `seq`): what
    /// [`SynthSource::render_into`] draws for the frame whose pose this is. Model-based pose
    /// estimators (the reference SUT) use it to render hypotheses.
    pub fn render_pose(&mut self, seq: u64, pose: &Pose, frame: &mut Frame) {
        let pose = *pose;
        let bbox = self.prepare(&pose);
        self.glint_screen(&pose);
        let c = &self.cfg;
        let ch = c.format.channels();
        let n = c.width as usize * c.height as usize * ch;
        frame.seq = seq;
        frame.pts_ns = (seq as f64 * 1e9 / c.fps).round() as u64;
        frame.width = c.width;
        frame.height = c.height;
        frame.stride = c.width as usize * ch;
        frame.format = c.format;
        let glints = &self.glint_scr;
        let wide = c.format == PixelFormat::Mono16;
        match &mut frame.data {
            FrameData::U16(d) if wide => d.resize(n, 0),
            FrameData::U8(d) if !wide => d.resize(n, 0),
            // allocation: only when a recycled frame had the other sample type
            data => *data = if wide { FrameData::U16(vec![0; n]) } else { FrameData::U8(vec![0; n]) },
        }
        let (w, h) = (c.width as usize, c.height as usize);
        let r = c.glint_radius();
        match &mut frame.data {
            FrameData::U8(d) => {
                d.copy_from_slice(&self.bg8);
                raster(d, w, h, ch, &self.prepared, &self.colours8, &mut self.zbuf, bbox);
                draw_glints(d, w, h, ch, glints, &self.zbuf, r);
            }
            FrameData::U16(d) => {
                d.copy_from_slice(&self.bg16);
                raster(d, w, h, ch, &self.prepared, &self.colours16, &mut self.zbuf, bbox);
                draw_glints(d, w, h, ch, glints, &self.zbuf, r);
            }
        }
    }

    /// Transform, cull, shade and set up every face; returns the pixel bbox of the model.
    fn prepare(&mut self, pose: &Pose) -> (usize, usize, usize, usize) {
        let rot = pose.rotation();
        let t = [0.0, 0.0, pose.distance_m];
        let f = self.focal_px();
        let (cx, cy) = (self.cfg.width as f64 / 2.0, self.cfg.height as f64 / 2.0);
        let ch = self.cfg.format.channels();
        let s = norm(SUN_DIR);
        self.prepared.clear();
        self.colours8.clear();
        self.colours16.clear();
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for face in &self.faces {
            let nv = face.verts.len().min(MAX_VERTS);
            let mut vbuf = [[0.0; 3]; MAX_VERTS];
            for (o, v) in vbuf.iter_mut().zip(&face.verts) {
                *o = add(mul_mv(&rot, *v), t);
            }
            let verts = &vbuf[..nv];
            if verts.iter().any(|v| v[2] < 0.05) {
                continue;
            }
            let mut nrm = mul_mv(&rot, face.normal);
            let facing = dot(nrm, verts[0]) < 0.0;
            if !facing && !face.two_sided {
                continue;
            }
            let back = !facing;
            if back {
                nrm = scale(nrm, -1.0);
            }
            let d = dot(nrm, verts[0]);
            if d.abs() < 1e-6 {
                continue;
            }
            // Shading (constant over the face).
            let ns = dot(nrm, s).max(0.0);
            let centre = scale(verts.iter().fold([0.0; 3], |a, v| add(a, *v)), 1.0 / verts.len() as f64);
            let spec = if face.mat == Material::Panel && !back && ns > 0.0 {
                let refl = sub(scale(nrm, 2.0 * dot(nrm, s)), s);
                let view = norm(scale(centre, -1.0));
                3.0 * dot(refl, view).max(0.0).powi(200)
            } else {
                0.0
            };
            let (surf, edge) = albedo(face.mat, back);
            let lit = AMBIENT + SUN_E * ns;
            let mut variants = [[0.0f64; 3]; N_VARIANTS];
            for k in 0..3 {
                variants[0][k] = edge[k] * lit + spec;
                for (i, crinkle) in [0.86, 0.95, 1.04, 1.13].iter().enumerate() {
                    let c = if face.mat == Material::Mli { *crinkle } else { 1.0 };
                    variants[i + 1][k] = surf[k] * lit * c + spec;
                }
            }
            if self.cfg.format == PixelFormat::Mono16 {
                self.colours16.push(variants.map(|v| to_samples::<u16>(v, 1)));
            } else {
                self.colours8.push(variants.map(|v| to_samples::<u8>(v, ch)));
            }
            // Screen polygon and per-pixel coefficients.
            let mut pts = [(0.0f32, 0.0f32); MAX_VERTS];
            for (p, v) in pts.iter_mut().zip(verts) {
                *p = ((cx + f * v[0] / v[2]) as f32, (cy + f * v[1] / v[2]) as f32);
            }
            for p in &pts[..nv] {
                x0 = x0.min(p.0 as f64);
                x1 = x1.max(p.0 as f64);
                y0 = y0.min(p.1 as f64);
                y1 = y1.max(p.1 as f64);
            }
            // r(u, v) = ((u - cx)/f, (v - cy)/f, 1); q·r = (qx/f) u + (qy/f) v + (qz - qx cx/f - qy cy/f).
            let lin = |q: V3| [q[0] / f, q[1] / f, q[2] - q[0] * cx / f - q[1] * cy / f];
            let ni = lin(nrm);
            let invz = [(ni[0] / d) as f32, (ni[1] / d) as f32, (ni[2] / d) as f32];
            let eu = mul_mv(&rot, face.eu);
            let ev = mul_mv(&rot, face.ev);
            let o = add(mul_mv(&rot, face.origin), t);
            let (lu, lv) = (lin(eu), lin(ev));
            let tu = [lu[0] as f32, lu[1] as f32, lu[2] as f32, dot(eu, o) as f32];
            let tv = [lv[0] as f32, lv[1] as f32, lv[2] as f32, dot(ev, o) as f32];
            let variant = self.prepared.len();
            self.prepared.push(Prepared {
                pts,
                npts: nv,
                invz,
                tu,
                tv,
                size: (face.size.0 as f32, face.size.1 as f32),
                mat: face.mat,
                variant,
            });
        }
        let (w, h) = (self.cfg.width as f64, self.cfg.height as f64);
        let clampx = |v: f64| v.clamp(0.0, w) as usize;
        let clampy = |v: f64| v.clamp(0.0, h) as usize;
        if x0 > x1 {
            return (0, 0, 0, 0);
        }
        (clampx(x0.floor() - 1.0), clampy(y0.floor() - 1.0), clampx(x1.ceil() + 1.0), clampy(y1.ceil() + 1.0))
    }

    /// Screen position and inverse depth of the glints in front of the camera, into `self.glint_scr`.
    fn glint_screen(&mut self, pose: &Pose) {
        let rot = pose.rotation();
        let f = self.focal_px();
        let (cx, cy) = (self.cfg.width as f64 / 2.0, self.cfg.height as f64 / 2.0);
        self.glint_scr.clear();
        for g in &self.glints {
            let q = add(mul_mv(&rot, *g), [0.0, 0.0, pose.distance_m]);
            if q[2] > 0.05 {
                self.glint_scr.push((cx + f * q[0] / q[2], cy + f * q[1] / q[2], (1.0 / q[2]) as f32));
            }
        }
    }
}

/// Rasterise the prepared faces with a z-buffer of inverse depth.
#[allow(clippy::too_many_arguments)]
fn raster<T: Sample>(
    data: &mut [T],
    w: usize,
    h: usize,
    ch: usize,
    faces: &[Prepared],
    colours: &[[[T; 3]; N_VARIANTS]],
    zbuf: &mut [f32],
    bbox: (usize, usize, usize, usize),
) {
    let (bx0, by0, bx1, by1) = bbox;
    for y in by0..by1 {
        zbuf[y * w + bx0..y * w + bx1].fill(0.0);
    }
    for face in faces {
        let cols = &colours[face.variant];
        let pts = &face.pts[..face.npts];
        let (ymin, ymax) = pts.iter().fold((f32::MAX, f32::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let ystart = ((ymin - 0.5).ceil().max(0.0)) as usize;
        let yend = ((ymax - 0.5).floor()).min(h as f32 - 1.0);
        if yend < 0.0 {
            continue;
        }
        let yend = yend as usize;
        let edge = 0.04f32;
        let (su, sv) = face.size;
        for y in ystart..=yend {
            let yc = y as f32 + 0.5;
            let (mut xl, mut xr) = (f32::MAX, f32::MIN);
            let n = pts.len();
            for i in 0..n {
                let (p, q) = (pts[i], pts[(i + 1) % n]);
                if (p.1 <= yc && q.1 > yc) || (q.1 <= yc && p.1 > yc) {
                    let x = p.0 + (yc - p.1) * (q.0 - p.0) / (q.1 - p.1);
                    xl = xl.min(x);
                    xr = xr.max(x);
                }
            }
            if xl > xr {
                continue;
            }
            let xs = (xl - 0.5).ceil().max(0.0) as usize;
            let xe = (xr - 0.5).floor().min(w as f32 - 1.0);
            if xe < 0.0 {
                continue;
            }
            let xe = xe as usize;
            let row = y * w;
            let rz = face.invz[1] * yc + face.invz[2];
            let ru = face.tu[1] * yc + face.tu[2];
            let rv = face.tv[1] * yc + face.tv[2];
            for x in xs..=xe {
                let xc = x as f32 + 0.5;
                let iz = face.invz[0] * xc + rz;
                let zb = &mut zbuf[row + x];
                if iz < *zb {
                    continue;
                }
                *zb = iz;
                let z = 1.0 / iz;
                let u = z * (face.tu[0] * xc + ru) - face.tu[3];
                let v = z * (face.tv[0] * xc + rv) - face.tv[3];
                let on_edge = u < edge || v < edge || u > su - edge || v > sv - edge;
                let k = match face.mat {
                    Material::Silver => 1,
                    _ if on_edge => 0,
                    Material::Panel => {
                        // 10 x 4 cells; gaps are 6 % of a cell.
                        let (fu, fv) = ((u / su * 10.0).fract(), (v / sv * 4.0).fract());
                        if fu < 0.06 || fv < 0.06 { 0 } else { 1 }
                    }
                    Material::Mli => {
                        let (iu, iv) = ((u / 0.11) as u32, (v / 0.11) as u32);
                        1 + (iu.wrapping_mul(0x9E37_79B1) ^ iv.wrapping_mul(0x85EB_CA77)).rotate_left(7) as usize % 4
                    }
                    Material::Radiator => 1,
                };
                let px = (row + x) * ch;
                data[px..px + ch].copy_from_slice(&cols[k][..ch]);
            }
        }
    }
}

/// Saturated discs of radius `r` px with a Gaussian halo, where the fitting is not hidden.
fn draw_glints<T: Sample>(
    data: &mut [T],
    w: usize,
    h: usize,
    ch: usize,
    glints: &[(f64, f64, f32)],
    zbuf: &[f32],
    r: f64,
) {
    let reach = r * 4.0;
    for &(gx, gy, iz) in glints {
        if gx < -reach || gy < -reach || gx > w as f64 + reach || gy > h as f64 + reach {
            continue;
        }
        // Hidden when a surface at the centre pixel is nearer by more than 0.15 m.
        let (px, py) = (gx.floor(), gy.floor());
        if px >= 0.0 && py >= 0.0 && (px as usize) < w && (py as usize) < h {
            let zb = zbuf[py as usize * w + px as usize];
            if zb > 0.0 && 1.0 / zb < 1.0 / iz - 0.15 {
                continue;
            }
        }
        let x0 = (gx - reach).floor().max(0.0) as usize;
        let x1 = ((gx + reach).ceil().max(0.0) as usize).min(w);
        let y0 = (gy - reach).floor().max(0.0) as usize;
        let y1 = ((gy + reach).ceil().max(0.0) as usize).min(h);
        for y in y0..y1 {
            for x in x0..x1 {
                let d = ((x as f64 + 0.5 - gx).powi(2) + (y as f64 + 0.5 - gy).powi(2)).sqrt();
                let add = if d <= r { 1.0 } else { 0.5 * (-(d - r).powi(2) / (2.0 * r * r)).exp() };
                let i = (y * w + x) * ch;
                for s in &mut data[i..i + ch] {
                    *s = T::from_f32(s.to_f32() + add as f32 * T::MAX_F32);
                }
            }
        }
    }
}

impl Source for SynthSource {
    fn describe(&self) -> String {
        let c = &self.cfg;
        format!(
            "synth: {}x{} {} spacecraft scene ({} frames, {} fps, yaw {} pitch {} roll {} deg, {} m, spin {} deg/s, earth {}, stars {}, seed {})",
            c.width,
            c.height,
            c.format,
            if c.frames == 0 { "endless".to_string() } else { c.frames.to_string() },
            c.fps,
            c.yaw_deg,
            c.pitch_deg,
            c.roll_deg,
            c.distance_m,
            c.spin_dps,
            c.earth,
            c.stars,
            c.seed
        )
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, SourceError> {
        if self.cfg.frames != 0 && self.seq >= self.cfg.frames {
            return Ok(None);
        }
        let mut frame = self.pool.pop().unwrap_or_else(|| {
            // allocation: until the pool holds recycled frames
            Frame { format: self.cfg.format, ..Frame::empty() }
        });
        self.render_into(self.seq, &mut frame);
        self.seq += 1;
        Ok(Some(frame))
    }

    fn truth(&self) -> crate::pose::Truth {
        match self.seq.checked_sub(1) {
            Some(last) => crate::pose::Truth { pose: Some(self.pose_truth(last)), camera: Some(self.intrinsics()) },
            None => crate::pose::Truth::default(),
        }
    }

    fn recycle(&mut self, frame: Frame) {
        if self.pool.len() < POOL_SIZE {
            self.pool.push(frame);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_are_validated() {
        let e = SynthSource::open("synth:?width=4").err().unwrap().to_string();
        assert!(e.contains("width=4") && e.contains("16..=16384"), "{e}");
        let e = SynthSource::open("synth:?colour=red").err().unwrap().to_string();
        assert!(e.contains("unknown option 'colour'") && e.contains("width"), "{e}");
        let e = SynthSource::open("synth:?format=bayer8").err().unwrap().to_string();
        assert!(e.contains("mono8, mono16 or rgb8"), "{e}");
    }

    #[test]
    fn pose_advances_at_spin_rate() {
        let s = SynthSource::open("synth:?width=32&height=32&fps=10&spin_dps=5&yaw=0").unwrap();
        assert_eq!(s.pose(0).yaw_deg, 0.0);
        assert!((s.pose(20).yaw_deg - 10.0).abs() < 1e-9);
    }

    #[test]
    fn pose_truth_reprojects_the_glints() {
        // The logged q, t and intrinsics reproduce the renderer's projection of the model.
        let mut s = SynthSource::open("synth:?width=160&height=120&frames=3&spin_dps=40&fps=2").unwrap();
        for seq in 0..3 {
            s.next_frame().unwrap().unwrap();
            let truth = s.truth();
            let (pose, k) = (truth.pose.unwrap(), truth.camera.unwrap());
            let r = crate::pose::matrix_from_quat(pose.q);
            for g in s.glint_points().to_vec() {
                let c = add(mul_mv(&r, g), pose.t);
                let (u, v) = (k.fx * c[0] / c[2] + k.cx, k.fy * c[1] / c[2] + k.cy);
                let (pu, pv) = s.project(&s.pose(seq), g).unwrap();
                // project() is in corner-origin coordinates (pixel centres at +0.5).
                assert!((u + 0.5 - pu).abs() < 1e-9 && (v + 0.5 - pv).abs() < 1e-9, "{seq}: {u},{v} vs {pu},{pv}");
            }
        }
    }

    #[test]
    fn rotation_is_orthonormal() {
        let p = Pose { yaw_deg: 31.0, pitch_deg: -12.0, roll_deg: 77.0, distance_m: 20.0 };
        let r = p.rotation();
        for i in 0..3 {
            for j in 0..3 {
                let d: f64 = (0..3).map(|k| r[i][k] * r[j][k]).sum();
                assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
    }
}
