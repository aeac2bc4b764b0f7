//! `vignetting`: radial fall-off of the irradiance towards the image corners.

use super::kit::{band_rows, bands, mul_round_row, par_bands_with};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, Sample};
use crate::with_image_mut;
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "vignetting",
    stage: Stage::Optics,
    order: 30,
    summary: "smooth radial multiplicative fall-off: gain 1 at the centre, 1 - strength at the corners",
    model: "v' = round(v * g(rho)), rho = r / r_c, r = distance of the pixel centre from the image centre \
            ((W-1)/2, (H-1)/2), r_c = that distance for a corner pixel. g(rho) = 1 - strength * q(rho) with \
            the natural cos^4 law normalised to the corner: q(rho) = (1 - c(rho)) / (1 - c(1)), \
            c(rho) = cos^4(atan(rho * tan(field_deg))) = (1 + rho^2 tan^2(field_deg))^-2, where field_deg is \
            the half-diagonal field angle (shape only; small angles approach a parabola q = rho^2). \
            q(0) = 0 and q(1) = 1, so the gain is exactly 1 at the centre and exactly 1 - strength at the \
            corner pixels, and strictly decreasing in rho. All channels share the gain. strength = 0 is the \
            identity.",
    params: &[
        ParamSpec::float("strength", "fraction", 0.0, 1.0, 0.3, "irradiance loss at the corners (0.3 = 30 %)"),
        ParamSpec::float("field_deg", "deg", 1.0, 80.0, 35.0, "half-diagonal field angle of the cos^4 shape").extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(Vignetting::default())
}

/// Gain at normalised radius `rho` (1 = corner).
pub fn gain(rho: f64, strength: f64, field_deg: f64) -> f64 {
    let t2 = field_deg.to_radians().tan().powi(2);
    let c = |r: f64| (1.0 + r * r * t2).powi(-2);
    1.0 - strength * (1.0 - c(rho)) / (1.0 - c(1.0))
}

#[derive(Default)]
pub struct Vignetting {
    key: Option<(u32, u32, u64, u64)>,
    // allocation: once per (size, parameters): gains of the upper half of the rows (the lower
    // half mirrors them), one f32 per pixel
    map: Vec<f32>,
    // allocation: once per frame size: per band, one row of per-sample gains
    rows: Vec<f32>,
}

impl Vignetting {
    fn ensure(&mut self, w: u32, h: u32, strength: f64, field: f64) {
        let key = (w, h, strength.to_bits(), field.to_bits());
        if self.key == Some(key) {
            return;
        }
        let (wu, hh) = (w as usize, (h as usize).div_ceil(2));
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let rc = (cx * cx + cy * cy).sqrt().max(f64::MIN_POSITIVE);
        self.map.clear();
        self.map.resize(wu * hh, 1.0);
        self.map.par_chunks_mut(wu).enumerate().for_each(|(y, row)| {
            let dy = y as f64 - cy;
            for (x, g) in row.iter_mut().enumerate() {
                let dx = x as f64 - cx;
                let rho = ((dx * dx + dy * dy).sqrt() / rc).min(1.0);
                *g = gain(rho, strength, field) as f32;
            }
        });
        self.key = Some(key);
    }
}

fn apply_map<T: Sample, const CH: usize>(
    data: &mut [T],
    stride: usize,
    h: usize,
    w: usize,
    map: &[f32],
    rows: &mut [f32],
) {
    par_bands_with(data, stride, h, rows, w * CH, |_, y0, band, gx| {
        for (i, row) in band_rows(band, stride, w * CH).enumerate() {
            let y = y0 + i;
            let my = y.min(h - 1 - y);
            let grow = &map[my * w..(my + 1) * w];
            // One gain per sample (channels share the pixel's gain), then a flat loop that
            // vectorises: v' = round(v * g).
            let gain: &[f32] = if CH == 1 {
                grow
            } else {
                for (e, &g) in gx.chunks_exact_mut(CH).zip(grow) {
                    e.fill(g);
                }
                gx
            };
            mul_round_row(row, gain);
        }
    });
}

impl Effect for Vignetting {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let strength = p.get("strength");
        if strength == 0.0 {
            return Ok(Outcome::Keep);
        }
        self.ensure(frame.width, frame.height, strength, p.get("field_deg"));
        let (w, h, stride, ch) = (frame.width as usize, frame.height as usize, frame.stride, frame.channels());
        self.rows.resize(w * ch * bands(h), 0.0);
        let (map, rows) = (&self.map, &mut self.rows);
        with_image_mut!(frame, img => match ch {
            3 => apply_map::<_, 3>(img.data, stride, h, w, map, rows),
            _ => apply_map::<_, 1>(img.data, stride, h, w, map, rows),
        });
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn flat(w: u32, h: u32, format: PixelFormat, v: f32) -> Frame {
        let mut f = Frame::new(w, h, format).unwrap();
        for y in 0..h as usize {
            for x in 0..w as usize {
                for c in 0..format.channels() {
                    f.set(x, y, c, v);
                }
            }
        }
        f
    }

    #[test]
    fn centre_one_corners_one_minus_strength_monotone() {
        for (w, h) in [(101u32, 61u32), (128, 96)] {
            for format in [PixelFormat::Mono16, PixelFormat::Rgb8] {
                let v0 = 0.8 * format.full_scale();
                let s = 0.37;
                let mut f = flat(w, h, format, v0);
                let mut p = Params::defaults(&INFO);
                p.set("strength", s).unwrap();
                Vignetting::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                let corner = (v0 as f64 * (1.0 - s)).round() as f32;
                for (x, y) in [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1)] {
                    assert_eq!(f.get(x as usize, y as usize, 0), corner, "{format} corner ({x},{y})");
                }
                if w % 2 == 1 && h % 2 == 1 {
                    assert_eq!(f.get(w as usize / 2, h as usize / 2, 0), v0, "centre gain is 1");
                }
                // Monotone: sort pixels by radius, values never increase.
                let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
                let mut px: Vec<(f64, f32)> = (0..h as usize)
                    .flat_map(|y| (0..w as usize).map(move |x| (x, y)))
                    .map(|(x, y)| (((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)).sqrt(), f.get(x, y, 0)))
                    .collect();
                px.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap());
                for pair in px.windows(2) {
                    assert!(pair[1].1 <= pair[0].1, "not monotone at r={}: {:?}", pair[1].0, pair);
                }
                for y in 0..h as usize {
                    for x in 0..w as usize {
                        for c in 1..format.channels() {
                            assert_eq!(f.get(x, y, c), f.get(x, y, 0));
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn gain_function_endpoints_and_identity() {
        for field in [1.0, 35.0, 80.0] {
            assert!((gain(0.0, 0.4, field) - 1.0).abs() < 1e-12);
            assert!((gain(1.0, 0.4, field) - 0.6).abs() < 1e-12);
            let mut last = 1.0;
            for i in 1..=100 {
                let g = gain(i as f64 / 100.0, 0.4, field);
                assert!(g < last);
                last = g;
            }
        }
        let orig = crate::faults::kit::bench_scene(64, 48, PixelFormat::Mono8, 1).unwrap();
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("strength", 0.0).unwrap();
        Vignetting::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f, orig);
    }
}
