//! `lens_flare`: ghost images of a bright source, produced by reflections between lens
//! surfaces. Each ghost is an out-of-focus image of the aperture stop (a disc, or a polygon for a
//! bladed iris) centred on the line from the source through the optical centre.

use super::kit::{max_of_row, multiversion};
use super::util::ROWS_PER_TASK;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, ImageMut, ImageRef, Sample};
use crate::rng::Rng;
use crate::{with_image_mut, with_image_ref};
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "lens_flare",
    stage: Stage::Optics,
    order: 10,
    summary: "additive aperture-shaped ghosts along the line from the brightest source through the image centre",
    model: "Source: the brightest blob, i.e. the 8-connected set of pixels whose brightest channel is >= threshold*FS \
            with the largest flux above threshold; its flux-weighted centroid s (or the fixed source_x/source_y). \
            No pixel above threshold: identity. Centre c = ((W-1)/2, (H-1)/2). Ghost k (k = 0..ghosts) is centred \
            at c + t_k (s - c) with t_k = 0.7 - 2 (k + 0.5 + 0.5 j_k) / ghosts, j_k in [-0.5, 0.5): from near the \
            source (t = 0.7) through the centre to beyond the mirror point (t < -1). Radius r_k = size * diagonal * \
            a_k, a_k in [0.5, 1.5); shape: disc (aperture_blades = 0) or regular polygon with that many sides \
            (3..12, circumradius r_k, fixed rotation); soft edge of width max(1 px, 0.12 r_k) (smoothstep). \
            Plateau level L_k = intensity * FS * b_k / mean(b), b_k in [0.5, 1.5): the ghosts' mean plateau is \
            exactly intensity * FS. j_k, a_k, b_k and the rotations are a fixed pattern of the lens (same every \
            frame). Colour: per-channel gains with mean 1 (tint: white, green, purple, amber coatings, or rainbow \
            = a different hue per ghost); Mono formats use gain 1. Rendering with coverage a(x,y) in [0,1]: \
            v' = v * (1 - a (1 - transparency)) + a * L_k * gain_c, rounded and clipped to [0, FS]; \
            transparency = 1 (default) is the physical additive ghost, < 1 is the study's alpha-blend look where \
            ghosts also hide the scene. ghosts = 0 or intensity = 0 is the identity. Work is limited to each \
            ghost's bounding box.",
    params: &[
        ParamSpec::int("ghosts", "1", 0.0, 16.0, 5.0, "number of ghosts"),
        ParamSpec::float("intensity", "fraction of FS", 0.0, 1.0, 0.08, "mean plateau level of the ghosts / FS"),
        ParamSpec::float("size", "fraction of diagonal", 0.005, 0.3, 0.04, "mean ghost radius / image diagonal")
            .extra(),
        ParamSpec::choice(
            "tint",
            &["rainbow", "white", "green", "purple", "amber"],
            0,
            false,
            "ghost colour (anti-reflection coating); rainbow = one hue per ghost",
        ),
        ParamSpec::float(
            "transparency",
            "1",
            0.0,
            1.0,
            1.0,
            "1 = additive (physical); < 1 = ghosts also attenuate the scene behind them",
        )
        .extra(),
        ParamSpec::int("aperture_blades", "1", 0.0, 12.0, 6.0, "0 = round aperture, 3..12 = polygon sides").extra(),
        ParamSpec::float("threshold", "fraction of FS", 0.5, 1.0, 0.95, "source detection level").extra(),
        ParamSpec::float("source_x", "px", -1.0, 65535.0, -1.0, "fixed source x (px); -1 = detect").extra(),
        ParamSpec::float("source_y", "px", -1.0, 65535.0, -1.0, "fixed source y (px); -1 = detect").extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(LensFlare::default())
}

/// Most ghosts (the parameter's upper bound).
pub const MAX_GHOSTS: usize = 16;

/// One ghost as rendered.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Ghost {
    pub cx: f32,
    pub cy: f32,
    /// Circumradius (px).
    pub radius: f32,
    /// Soft edge width (px).
    pub edge: f32,
    /// Plateau in DN per channel (R, G, B; Mono uses [0]).
    pub level: [f32; 3],
    /// Polygon sides (0 = disc) and rotation (rad).
    pub blades: u32,
    pub rotation: f32,
    /// Parameter along the source–centre line.
    pub t: f32,
}

/// Ghost layout for a source at `s` (px) in a `w` x `h` frame. Fills `out` (at most
/// [`MAX_GHOSTS`]); `pattern_seed` fixes the lens.
#[allow(clippy::too_many_arguments)]
pub fn layout(
    p: &Params,
    pattern_seed: u64,
    w: usize,
    h: usize,
    channels: usize,
    fs: f32,
    s: (f32, f32),
    out: &mut [Ghost; MAX_GHOSTS],
) -> usize {
    let n = (p.get("ghosts") as usize).min(MAX_GHOSTS);
    let (cx, cy) = ((w as f32 - 1.0) / 2.0, (h as f32 - 1.0) / 2.0);
    let diag = ((w * w + h * h) as f32).sqrt();
    let blades = p.get("aperture_blades") as u32;
    let mut r = Rng::new(pattern_seed);
    let mut b = [0f32; MAX_GHOSTS];
    for (k, g) in out.iter_mut().enumerate().take(n) {
        let j = r.uniform_f32() - 0.5;
        let a = 0.5 + r.uniform_f32();
        b[k] = 0.5 + r.uniform_f32();
        let rotation = r.uniform_f32() * std::f32::consts::TAU;
        let t = 0.7 - 2.0 * (k as f32 + 0.5 + 0.5 * j) / n as f32;
        let radius = p.get("size") as f32 * diag * a;
        *g = Ghost {
            cx: cx + t * (s.0 - cx),
            cy: cy + t * (s.1 - cy),
            radius,
            edge: (0.12 * radius).max(1.0),
            level: [0.0; 3],
            blades,
            rotation,
            t,
        };
    }
    let mean_b = b[..n].iter().sum::<f32>() / n.max(1) as f32;
    let base = p.get("intensity") as f32 * fs;
    for (k, g) in out.iter_mut().enumerate().take(n) {
        let gains = if channels == 3 { tint(p.choice("tint"), k, n) } else { [1.0; 3] };
        g.level = gains.map(|c| base * b[k] / mean_b * c);
    }
    n
}

/// Per-channel gains with mean 1.
fn tint(name: &str, k: usize, n: usize) -> [f32; 3] {
    let raw = match name {
        "white" => [1.0, 1.0, 1.0],
        "green" => [0.6, 1.4, 0.8],
        "purple" => [1.2, 0.5, 1.3],
        "amber" => [1.5, 1.0, 0.5],
        _ => {
            // Hue k/n at saturation 0.5.
            let h = 6.0 * k as f32 / n.max(1) as f32;
            let f = |o: f32| {
                let x = ((h + o) % 6.0 - 3.0).abs() - 1.0;
                1.0 - 0.5 * (1.0 - x.clamp(0.0, 1.0))
            };
            [f(0.0), f(4.0), f(2.0)]
        }
    };
    let m = (raw[0] + raw[1] + raw[2]) / 3.0;
    raw.map(|v| v / m)
}

/// Scratch for source detection.
#[derive(Default)]
pub struct LensFlare {
    // allocation: once per stream (one bit per pixel) and the flood-fill stack
    visited: Vec<u64>,
    stack: Vec<u32>,
    rows: Vec<bool>,
    ghosts: [Ghost; MAX_GHOSTS],
    // allocation: once per frame size: per band, three rows of floats for rendering
    render_scratch: Vec<f32>,
}

/// Brightest blob: centroid and flux above threshold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Source {
    pub x: f32,
    pub y: f32,
    pub flux: f64,
}

impl LensFlare {
    /// Find the brightest blob (see the model text). `None` when no pixel reaches `thr`.
    pub fn find_source(&mut self, frame: &Frame, thr: u32) -> Option<Source> {
        let (w, h) = (frame.width as usize, frame.height as usize);
        self.visited.clear();
        self.visited.resize((w * h).div_ceil(64), 0);
        self.rows.clear();
        self.rows.resize(h, false);
        let (visited, stack, rows) = (&mut self.visited, &mut self.stack, &mut self.rows);
        with_image_ref!(frame, img => find_source(&img, thr, visited, stack, rows))
    }
}

fn brightest<T: Sample>(px: &[T]) -> u32 {
    px.iter().fold(0u32, |m, v| m.max(v.to_u32()))
}

fn find_source<T: Sample>(
    img: &ImageRef<'_, T>,
    thr: u32,
    visited: &mut [u64],
    stack: &mut Vec<u32>,
    rows: &mut [bool],
) -> Option<Source> {
    let (w, h, ch) = (img.width, img.height, img.channels);
    let thr_t = T::from_u32_sat(thr);
    // Rows that hold any sample >= thr (vectorisable max per row, in parallel).
    rows.par_iter_mut().enumerate().for_each(|(y, r)| *r = max_of_row(img.row(y)) >= thr_t);
    let mut best: Option<Source> = None;
    for y0 in (0..h).filter(|&y| rows[y]) {
        let row = img.row(y0);
        for x0 in 0..w {
            let i0 = y0 * w + x0;
            if brightest(&row[x0 * ch..x0 * ch + ch]) < thr || visited[i0 / 64] >> (i0 % 64) & 1 == 1 {
                continue;
            }
            // Flood fill (8-connected) from (x0, y0).
            let (mut f, mut fx, mut fy) = (0f64, 0f64, 0f64);
            visited[i0 / 64] |= 1 << (i0 % 64);
            stack.clear();
            stack.push(i0 as u32);
            while let Some(i) = stack.pop() {
                let (x, y) = (i as usize % w, i as usize / w);
                let wgt = (brightest(&img.row(y)[x * ch..x * ch + ch]) - thr + 1) as f64;
                f += wgt;
                fx += wgt * x as f64;
                fy += wgt * y as f64;
                for ny in y.saturating_sub(1)..(y + 2).min(h) {
                    let r = img.row(ny);
                    for nx in x.saturating_sub(1)..(x + 2).min(w) {
                        let j = ny * w + nx;
                        if visited[j / 64] >> (j % 64) & 1 == 0 && brightest(&r[nx * ch..nx * ch + ch]) >= thr {
                            visited[j / 64] |= 1 << (j % 64);
                            stack.push(j as u32);
                        }
                    }
                }
            }
            if best.is_none_or(|b| f > b.flux) {
                best = Some(Source { x: (fx / f) as f32, y: (fy / f) as f32, flux: f });
            }
        }
    }
    best
}

impl Effect for LensFlare {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let blades = p.get("aperture_blades");
        if blades == 1.0 || blades == 2.0 {
            return Err(FaultError::ParamOutOfRange {
                effect: INFO.name,
                param: "aperture_blades",
                value: blades,
                accepted: "0 (round aperture) or integer 3..=12".to_string(),
            });
        }
        if p.get("ghosts") < 1.0 || p.get("intensity") <= 0.0 {
            return Ok(Outcome::Keep);
        }
        let fs = frame.format.full_scale();
        let (w, h) = (frame.width as usize, frame.height as usize);
        let (sx, sy) = (p.get("source_x"), p.get("source_y"));
        let s = if sx >= 0.0 && sy >= 0.0 {
            (sx as f32, sy as f32)
        } else {
            let thr = (p.get("threshold") * fs as f64).ceil() as u32;
            match self.find_source(frame, thr) {
                Some(src) => (src.x, src.y),
                None => return Ok(Outcome::Keep),
            }
        };
        let n = layout(p, ctx.pattern_seed, w, h, frame.channels(), fs, s, &mut self.ghosts);
        let opacity = 1.0 - p.get("transparency") as f32;
        self.render_scratch.resize(3 * w * frame.channels() * super::kit::bands(h), 0.0);
        let (ghosts, scratch) = (&self.ghosts[..n], &mut self.render_scratch);
        with_image_mut!(frame, img => render(&mut img, ghosts, opacity, scratch));
        Ok(Outcome::Keep)
    }
}

multiversion! {
    /// Distance measure of the pixels x0, x0 + 1, ... of a row at `dy` from the ghost centre:
    /// Euclidean (disc, no normals) or, for a polygon, the largest projection on an edge normal
    /// (normals pre-divided by cos(pi/n), so the boundary sits at d = circumradius).
    fn distance_row<T: Copy>(d: &mut [f32], x0: usize, cx: f32, dy: f32, normals: &[(f32, f32)], _t: T) {
        // Pixel columns as i32 -> f32 (exact below 2^24; converts in vector registers).
        let x0 = x0 as i32;
        if normals.is_empty() {
            for (k, v) in (0i32..).zip(d.iter_mut()) {
                let dx = (x0 + k) as f32 - cx;
                *v = (dx * dx + dy * dy).sqrt();
            }
            return;
        }
        d.fill(f32::MIN);
        for &(nx, ny) in normals {
            let base = dy * ny;
            for (k, v) in (0i32..).zip(d.iter_mut()) {
                let dx = (x0 + k) as f32 - cx;
                *v = v.max(dx * nx + base);
            }
        }
    }
}

multiversion! {
    /// Smoothstep coverage of one row segment: `d` holds the distance measure (disc: Euclidean;
    /// polygon: largest normal projection) and becomes the coverage.
    fn coverage_row<T: Copy>(d: &mut [f32], radius: f32, edge: f32, _t: T) {
        for v in d.iter_mut() {
            let s = ((radius - *v) / edge + 0.5).clamp(0.0, 1.0);
            *v = s * s * (3.0 - 2.0 * s);
        }
    }
}

multiversion! {
    /// `v = round(v * (1 - a * opacity) + a * level)` per sample (a, level expanded per sample).
    fn blend_row<T: Sample>(row: &mut [T], a: &[f32], level: &[f32], opacity: f32) {
        for ((v, &a), &l) in row.iter_mut().zip(a).zip(level) {
            *v = T::from_f32(v.to_f32() * (1.0 - a * opacity) + a * l);
        }
    }
}

/// Render the ghosts. Per row of a ghost's bounding box: the distance measure of every pixel
/// (vectorised over x), its smoothstep coverage, then the blend over the samples (coverage and
/// level expanded per sample). Pixels with zero coverage blend to themselves.
fn render<T: Sample>(img: &mut ImageMut<'_, T>, ghosts: &[Ghost], opacity: f32, scratch: &mut [f32]) {
    let (stride, row_len, w, h, ch) = (img.stride, img.row_len(), img.width, img.height, img.channels);
    let used = stride * (h - 1) + row_len;
    let per_band = 3 * w * ch;
    img.data[..used].par_chunks_mut(stride * ROWS_PER_TASK).zip(scratch.par_chunks_mut(per_band)).enumerate().for_each(
        |(band, (chunk, scratch))| {
            let (dist, rest) = scratch.split_at_mut(w * ch);
            let (aexp, lexp) = rest.split_at_mut(w * ch);
            let y_band = band * ROWS_PER_TASK;
            for g in ghosts {
                let reach = g.radius + g.edge;
                let y0 = (g.cy - reach).floor().max(y_band as f32) as usize;
                let y1 = ((g.cy + reach).ceil() + 1.0).min((y_band + ROWS_PER_TASK).min(h) as f32);
                let x0 = (g.cx - reach).floor().max(0.0) as usize;
                let x1 = ((g.cx + reach).ceil() + 1.0).min(w as f32);
                if y1 <= y0 as f32 || x1 <= x0 as f32 {
                    continue;
                }
                let (y1, x1) = (y1 as usize, x1 as usize);
                let nx = x1 - x0;
                let mut normals = [(0f32, 0f32); 12];
                let nb = if g.blades >= 3 { g.blades as usize } else { 0 };
                let inv_cos = 1.0 / (std::f32::consts::PI / nb.max(1) as f32).cos();
                for (i, nrm) in normals.iter_mut().enumerate().take(nb) {
                    let a = g.rotation + (2 * i + 1) as f32 * std::f32::consts::PI / nb as f32;
                    *nrm = (a.cos() * inv_cos, a.sin() * inv_cos);
                }
                if ch == 1 {
                    // One channel: the coverage is the per-sample weight, the level is constant.
                    lexp[..nx].fill(g.level[0]);
                }
                for y in y0..y1 {
                    let dy = y as f32 - g.cy;
                    let d = &mut dist[..nx];
                    distance_row(d, x0, g.cx, dy, &normals[..nb], 0u8);
                    coverage_row(d, g.radius, g.edge, 0u8);
                    if ch == 1 {
                        let row = &mut chunk[(y - y_band) * stride + x0..][..nx];
                        blend_row(row, d, &lexp[..nx], opacity);
                        continue;
                    }
                    let (ae, le) = (&mut aexp[..nx * ch], &mut lexp[..nx * ch]);
                    for ((a, l), &cov) in ae.chunks_exact_mut(ch).zip(le.chunks_exact_mut(ch)).zip(d.iter()) {
                        a.fill(cov);
                        for (c, lv) in l.iter_mut().enumerate() {
                            *lv = g.level[c];
                        }
                    }
                    let row = &mut chunk[(y - y_band) * stride + x0 * ch..][..nx * ch];
                    blend_row(row, ae, le, opacity);
                }
            }
        },
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn params(kv: &[(&str, f64)]) -> Params {
        let mut p = Params::defaults(&INFO);
        for (k, v) in kv {
            p.set(k, *v).unwrap();
        }
        p
    }

    /// Black frame with a saturated 3x3 spot centred on (sx, sy).
    fn spot_frame(fmt: PixelFormat, sx: usize, sy: usize) -> Frame {
        let mut f = Frame::new(256, 192, fmt).unwrap();
        for y in sy - 1..=sy + 1 {
            for x in sx - 1..=sx + 1 {
                for c in 0..fmt.channels() {
                    f.set(x, y, c, fmt.full_scale());
                }
            }
        }
        f
    }

    /// Connected components (4-connected) of pixels where `mask` is true: (centroid, pixels).
    fn components(w: usize, h: usize, mask: &[bool]) -> Vec<((f64, f64), Vec<usize>)> {
        let mut seen = vec![false; w * h];
        let mut out = Vec::new();
        for i in 0..w * h {
            if !mask[i] || seen[i] {
                continue;
            }
            let mut st = vec![i];
            seen[i] = true;
            let mut px = Vec::new();
            while let Some(j) = st.pop() {
                px.push(j);
                let (x, y) = (j % w, j / w);
                let mut nb = vec![];
                if x > 0 {
                    nb.push(j - 1);
                }
                if x + 1 < w {
                    nb.push(j + 1);
                }
                if y > 0 {
                    nb.push(j - w);
                }
                if y + 1 < h {
                    nb.push(j + w);
                }
                for k in nb {
                    if mask[k] && !seen[k] {
                        seen[k] = true;
                        st.push(k);
                    }
                }
            }
            let n = px.len() as f64;
            let cx = px.iter().map(|&j| (j % w) as f64).sum::<f64>() / n;
            let cy = px.iter().map(|&j| (j / w) as f64).sum::<f64>() / n;
            out.push(((cx, cy), px));
        }
        out
    }

    #[test]
    fn ghosts_lie_on_the_source_centre_line_with_the_requested_mean_plateau() {
        for blades in [0.0, 6.0] {
            let (sx, sy) = (200usize, 40usize);
            let orig = spot_frame(PixelFormat::Mono8, sx, sy);
            let mut f = orig.clone();
            let p = params(&[
                ("ghosts", 4.0),
                ("intensity", 0.3),
                ("size", 0.015),
                ("aperture_blades", blades),
                ("tint", 1.0),
            ]);
            LensFlare::default().apply(&mut f, &p, &mut EffectCtx::new(3, 0, 0)).unwrap();
            let (w, h) = (256usize, 192usize);
            let changed: Vec<bool> = (0..w * h).map(|i| f.get(i % w, i / w, 0) != orig.get(i % w, i / w, 0)).collect();
            let comps = components(w, h, &changed);
            assert_eq!(comps.len(), 4, "four separate ghosts");
            let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
            let (ux, uy) = (sx as f64 - cx, sy as f64 - cy);
            let norm = (ux * ux + uy * uy).sqrt();
            let mut plateau = 0.0;
            for ((gx, gy), px) in &comps {
                // Perpendicular distance of the measured ghost centroid from the source–centre line.
                let dist = ((gx - cx) * uy - (gy - cy) * ux).abs() / norm;
                assert!(dist < 0.5, "blades {blades}: ghost at ({gx:.2}, {gy:.2}) is {dist:.3} px off the line");
                plateau += px.iter().map(|&j| f.get(j % w, j / w, 0) as f64).fold(0.0, f64::max);
            }
            // Mean plateau = intensity * FS = 76.5 DN, up to rounding of each plateau (0.5 DN).
            let mean = plateau / comps.len() as f64;
            assert!((mean - 76.5).abs() <= 0.5, "mean plateau {mean}");
        }
    }

    /// Scalar reference: coverage in [0, 1] of ghost `g` at pixel centre (x, y).
    fn coverage(g: &Ghost, normals: &[(f32, f32)], x: f32, y: f32) -> f32 {
        let (dx, dy) = (x - g.cx, y - g.cy);
        let d = if normals.is_empty() {
            (dx * dx + dy * dy).sqrt()
        } else {
            // Polygon "radius": largest projection on an edge normal, divided by cos(pi/n), so the
            // boundary sits at d = circumradius.
            normals.iter().fold(f32::MIN, |m, &(nx, ny)| m.max(dx * nx + dy * ny))
        };
        let s = ((g.radius - d) / g.edge + 0.5).clamp(0.0, 1.0);
        s * s * (3.0 - 2.0 * s)
    }

    #[test]
    fn row_renderer_equals_the_per_pixel_reference() {
        for (fmt, blades, opacity) in
            [(PixelFormat::Rgb8, 6u32, 0.0f32), (PixelFormat::Mono16, 0, 0.4), (PixelFormat::Mono8, 5, 1.0)]
        {
            let (w, h) = (150usize, 140usize);
            let mut orig = spot_frame(fmt, 20, 30);
            if let Some(d) = orig.as_u8_mut() {
                d.iter_mut().enumerate().for_each(|(i, v)| *v = v.saturating_add((i % 97) as u8));
            }
            let ghosts: Vec<Ghost> = (0..4)
                .map(|k| Ghost {
                    cx: 20.0 + 31.3 * k as f32,
                    cy: 100.0 - 17.1 * k as f32,
                    radius: 9.0 + 5.0 * k as f32,
                    edge: 2.0,
                    level: [40.0 * fmt.dn_scale(), 70.0 * fmt.dn_scale(), 20.0 * fmt.dn_scale()],
                    blades,
                    rotation: 0.3 * k as f32,
                    t: 0.0,
                })
                .collect();
            let mut f = orig.clone();
            let mut scratch = vec![0f32; 3 * w * fmt.channels() * crate::faults::kit::bands(h)];
            with_image_mut!(f, img => render(&mut img, &ghosts, opacity, &mut scratch));
            let mut want = orig.clone();
            for g in &ghosts {
                let mut normals = [(0f32, 0f32); 12];
                let nb = if g.blades >= 3 { g.blades as usize } else { 0 };
                let inv_cos = 1.0 / (std::f32::consts::PI / nb.max(1) as f32).cos();
                for (i, nrm) in normals.iter_mut().enumerate().take(nb) {
                    let a = g.rotation + (2 * i + 1) as f32 * std::f32::consts::PI / nb as f32;
                    *nrm = (a.cos() * inv_cos, a.sin() * inv_cos);
                }
                for y in 0..h {
                    for x in 0..w {
                        let a = coverage(g, &normals[..nb], x as f32, y as f32);
                        if a > 0.0 {
                            for c in 0..fmt.channels() {
                                let v = want.get(x, y, c);
                                want.set(x, y, c, v * (1.0 - a * opacity) + a * g.level[c]);
                            }
                        }
                    }
                }
            }
            assert!(f == want, "{fmt}: row renderer differs from the per-pixel reference");
        }
    }

    #[test]
    fn source_is_the_brightest_blob_centroid() {
        let mut f = spot_frame(PixelFormat::Rgb8, 60, 50);
        // A bigger saturated blob elsewhere wins.
        for y in 120..126 {
            for x in 30..35 {
                for c in 0..3 {
                    f.set(x, y, c, 255.0);
                }
            }
        }
        let s = LensFlare::default().find_source(&f, 243).unwrap();
        assert!((s.x - 32.0).abs() < 1e-4 && (s.y - 122.5).abs() < 1e-4, "{s:?}");
        assert!(LensFlare::default().find_source(&Frame::new(10, 10, PixelFormat::Mono16).unwrap(), 60000).is_none());
    }

    #[test]
    fn identity_without_source_ghosts_or_intensity() {
        let mut f = Frame::new(64, 48, PixelFormat::Rgb8).unwrap();
        f.as_u8_mut().unwrap().iter_mut().enumerate().for_each(|(i, v)| *v = (i % 200) as u8);
        let orig = f.clone();
        LensFlare::default().apply(&mut f, &params(&[]), &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f, orig, "no pixel above threshold");
        let mut g = spot_frame(PixelFormat::Mono16, 40, 40);
        let og = g.clone();
        for kv in [[("ghosts", 0.0)], [("intensity", 0.0)]] {
            LensFlare::default().apply(&mut g, &params(&kv), &mut EffectCtx::new(0, 0, 0)).unwrap();
            assert_eq!(g, og);
        }
        let e = LensFlare::default().apply(&mut g, &params(&[("aperture_blades", 2.0)]), &mut EffectCtx::new(0, 0, 0));
        assert!(e.unwrap_err().to_string().contains("aperture_blades"));
    }

    #[test]
    fn ghosts_are_a_fixed_pattern_and_tint_keeps_mean_level() {
        let p = params(&[("ghosts", 6.0), ("intensity", 0.2)]);
        let mut a = [Ghost::default(); MAX_GHOSTS];
        let mut b = [Ghost::default(); MAX_GHOSTS];
        layout(&p, 5, 320, 240, 3, 255.0, (300.0, 20.0), &mut a);
        layout(&p, 5, 320, 240, 3, 255.0, (300.0, 20.0), &mut b);
        assert_eq!(a, b);
        let mean: f32 = a[..6].iter().map(|g| g.level.iter().sum::<f32>() / 3.0).sum::<f32>() / 6.0;
        assert!((mean - 51.0).abs() < 1e-3, "mean plateau over ghosts and channels {mean}");
        assert!(a[..6].iter().any(|g| g.t < -1.0) && a[..6].iter().all(|g| g.t < 1.0));
    }
}
