//! `prnu`: photo-response non-uniformity, a fixed per-pixel gain pattern.

use super::kit::{band_rows, bands, mul_round_row, par_bands_with};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, Sample};
use crate::rng::Rng;
use crate::with_image_mut;
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "prnu",
    stage: Stage::Sensor,
    order: 10,
    summary: "photo-response non-uniformity: fixed per-pixel gain pattern",
    model: "v' = round(v * max(0, 1 + sigma * n(x, y))), n ~ N(0, 1) independent per pixel, clipped to [0, FS]. \
            The pattern n is fixed for a recording: drawn from Rng::new(pattern_seed) (row y from its child \
            derive(y)), cached per (size, seed) and identical on every frame; it does not depend on sigma, so \
            the response is continuous in sigma. All channels of an Rgb8 pixel share the gain. sigma is the \
            relative standard deviation of the pixel gains (EMVA 1288 PRNU); typical sensors 0.005..0.02. \
            sigma = 0 is the identity.",
    params: &[ParamSpec::float("sigma", "1", 0.0, 0.2, 0.01, "relative std of the per-pixel gain (0.01 = 1 %)").log()],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(Prnu::default())
}

#[derive(Default)]
pub struct Prnu {
    key: Option<(u32, u32, u64)>,
    // allocation: once per (size, seed): one f32 per pixel
    z: Vec<f32>,
    // allocation: once per frame size: per band, one row of per-sample gains
    rows: Vec<f32>,
}

impl Prnu {
    /// The standard-normal pattern n(x, y) of a `width`×`height` sensor with this pattern seed,
    /// row-major (for tests and diagnosis).
    pub fn pattern(&mut self, width: u32, height: u32, seed: u64) -> &[f32] {
        if self.key != Some((width, height, seed)) {
            let w = width as usize;
            self.z.clear();
            self.z.resize(w * height as usize, 0.0);
            let base = Rng::new(seed);
            self.z.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                let mut r = base.derive(y as u64);
                for v in row.iter_mut() {
                    *v = r.normal() as f32;
                }
            });
            self.key = Some((width, height, seed));
        }
        &self.z
    }
}

fn apply_gain<T: Sample, const CH: usize>(
    data: &mut [T],
    stride: usize,
    height: usize,
    width: usize,
    z: &[f32],
    sigma: f32,
    rows: &mut [f32],
) {
    par_bands_with(data, stride, height, rows, width * CH, |_, y0, band, gains| {
        for (i, row) in band_rows(band, stride, width * CH).enumerate() {
            let zrow = &z[(y0 + i) * width..(y0 + i + 1) * width];
            // Per-sample gains (channels share the pixel's), then a flat loop that vectorises.
            for (e, &n) in gains.chunks_exact_mut(CH).zip(zrow) {
                e.fill((1.0 + sigma * n).max(0.0));
            }
            mul_round_row(row, gains);
        }
    });
}

impl Effect for Prnu {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let sigma = p.get("sigma") as f32;
        if sigma == 0.0 {
            return Ok(Outcome::Keep);
        }
        let (w, h, stride, ch) = (frame.width, frame.height, frame.stride, frame.channels());
        self.pattern(w, h, ctx.pattern_seed);
        let (w, h) = (w as usize, h as usize);
        self.rows.resize(w * ch * bands(h), 0.0);
        let (z, rows) = (&self.z, &mut self.rows);
        with_image_mut!(frame, img => match ch {
            3 => apply_gain::<_, 3>(img.data, stride, h, w, z, sigma, rows),
            _ => apply_gain::<_, 1>(img.data, stride, h, w, z, sigma, rows),
        });
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn flat(format: PixelFormat, v: f32) -> Frame {
        let mut f = Frame::new(256, 256, format).unwrap();
        for y in 0..256 {
            for x in 0..256 {
                for c in 0..format.channels() {
                    f.set(x, y, c, v);
                }
            }
        }
        f
    }

    #[test]
    fn same_pattern_every_frame_with_relative_std_sigma() {
        let sigma = 0.02;
        let mut p = Params::defaults(&INFO);
        p.set("sigma", sigma).unwrap();
        let mut e = Prnu::default();
        let orig = flat(PixelFormat::Mono16, 40000.0);
        let mut a = orig.clone();
        let mut b = orig.clone();
        // Two frames: different per-frame generators, same pattern seed (same effect index).
        e.apply(&mut a, &p, &mut EffectCtx::new(9, 0, 1)).unwrap();
        e.apply(&mut b, &p, &mut EffectCtx::new(9, 1, 1)).unwrap();
        assert_eq!(a, b, "fixed pattern");
        let rel: Vec<f64> = a.as_u16().unwrap().iter().map(|&v| v as f64 / 40000.0 - 1.0).collect();
        let n = rel.len() as f64;
        let m = rel.iter().sum::<f64>() / n;
        let sd = (rel.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (n - 1.0)).sqrt();
        // 65536 pixels: std of the mean sigma/256, relative SE of the std 1/sqrt(2n) = 0.28 %;
        // 16-bit rounding adds (1/40000)^2/12, negligible. 5-sigma bounds.
        assert!(m.abs() < 5.0 * sigma / 256.0, "mean gain error {m}");
        assert!((sd - sigma).abs() < 5.0 * sigma / (2.0 * n).sqrt(), "std {sd}");
        // A different campaign seed gives a different pattern.
        let mut c = orig.clone();
        Prnu::default().apply(&mut c, &p, &mut EffectCtx::new(10, 0, 1)).unwrap();
        assert_ne!(a, c);
    }

    #[test]
    fn rgb_pixels_share_gain_and_zero_sigma_is_identity() {
        let orig = flat(PixelFormat::Rgb8, 200.0);
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("sigma", 0.0).unwrap();
        let mut e = Prnu::default();
        e.apply(&mut f, &p, &mut EffectCtx::new(1, 0, 0)).unwrap();
        assert_eq!(f, orig);
        p.set("sigma", 0.05).unwrap();
        e.apply(&mut f, &p, &mut EffectCtx::new(1, 0, 0)).unwrap();
        let z = e.pattern(256, 256, EffectCtx::new(1, 0, 0).pattern_seed).to_vec();
        for y in 0..256 {
            for x in 0..256 {
                let want = (200.0 * (1.0 + 0.05 * z[y * 256 + x])).round().clamp(0.0, 255.0);
                for c in 0..3 {
                    assert_eq!(f.get(x, y, c), want);
                }
            }
        }
    }
}
