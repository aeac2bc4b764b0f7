//! `hot_pixels`: a fixed fraction of pixels with a large constant dark offset.

use super::kit::SparsePattern;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, Sample};
use crate::with_image_mut;

pub static INFO: EffectInfo = EffectInfo {
    name: "hot_pixels",
    stage: Stage::Sensor,
    order: 40,
    summary: "fixed fraction of pixels with a large constant offset (defective, high-leakage pixels)",
    model: "Each pixel is hot independently with probability `rate` (a fixed pattern for the recording, \
            drawn from Rng::new(pattern_seed); the pattern is nested: raising `rate` only adds pixels). \
            A hot pixel reads v' = min(v + offset_dn * FS/255, FS) on every channel. rate = 0 or \
            offset_dn = 0 is the identity. Typical CMOS sensors: rate 1e-5..1e-3 (grows with radiation dose).",
    params: &[
        ParamSpec::float("rate", "fraction", 0.0, 0.01, 1e-4, "fraction of pixels that are hot").log(),
        ParamSpec::float("offset_dn", "DN", 0.0, 255.0, 150.0, "offset of a hot pixel, 8-bit DN").extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(HotPixels::default())
}

#[derive(Default)]
pub struct HotPixels {
    pattern: SparsePattern,
}

impl HotPixels {
    /// Pixel indices (y·width + x) of the hot pixels for a sensor size, seed and rate.
    pub fn pattern(&mut self, width: u32, height: u32, seed: u64, rate: f64) -> &[u32] {
        self.pattern.ensure(width as usize * height as usize, seed, INFO.params[0].max, rate)
    }
}

impl Effect for HotPixels {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let rate = p.get("rate");
        let offset = p.get("offset_dn") as f32 * frame.format.dn_scale();
        if rate == 0.0 || offset == 0.0 {
            return Ok(Outcome::Keep);
        }
        let (w, stride, ch) = (frame.width as usize, frame.stride, frame.channels());
        let hot = self.pattern(frame.width, frame.height, ctx.pattern_seed, rate);
        with_image_mut!(frame, img => {
            let off = offset.round() as u32;
            for &i in hot {
                let (x, y) = (i as usize % w, i as usize / w);
                let s = y * stride + x * ch;
                for v in &mut img.data[s..s + ch] {
                    *v = Sample::from_u32_sat(v.to_u32() + off);
                }
            }
        });
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    #[test]
    fn rate_within_binomial_bounds_fixed_and_nested() {
        let (w, h) = (400u32, 300u32);
        let n = (w * h) as f64;
        let mut e = HotPixels::default();
        let mut p = Params::defaults(&INFO);
        let mut prev: Vec<usize> = Vec::new();
        for rate in [1e-3, 5e-3, 1e-2] {
            p.set("rate", rate).unwrap();
            let mut f = Frame::new(w, h, PixelFormat::Rgb8).unwrap();
            e.apply(&mut f, &p, &mut EffectCtx::new(4, 0, 2)).unwrap();
            let hot: Vec<usize> =
                (0..w as usize * h as usize).filter(|&i| f.get(i % w as usize, i / w as usize, 0) != 0.0).collect();
            for &i in &hot {
                for c in 0..3 {
                    assert_eq!(f.get(i % w as usize, i / w as usize, c), 150.0);
                }
            }
            let sd = (n * rate * (1.0 - rate)).sqrt();
            assert!((hot.len() as f64 - n * rate).abs() < 5.0 * sd, "rate {rate}: {}", hot.len());
            assert!(prev.iter().all(|i| hot.binary_search(i).is_ok()), "nested in rate");
            // Same pattern on another frame.
            let mut g = Frame::new(w, h, PixelFormat::Rgb8).unwrap();
            e.apply(&mut g, &p, &mut EffectCtx::new(4, 7, 2)).unwrap();
            assert_eq!(f, g);
            prev = hot;
        }
    }

    #[test]
    fn saturates_and_zero_rate_is_identity() {
        let mut f = Frame::new(64, 64, PixelFormat::Mono16).unwrap();
        f.as_u16_mut().unwrap().fill(65000);
        let orig = f.clone();
        let mut p = Params::defaults(&INFO);
        p.set("rate", 0.0).unwrap();
        let mut e = HotPixels::default();
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f, orig);
        p.set("rate", 0.01).unwrap();
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert!(f.as_u16().unwrap().iter().all(|&v| v == 65000 || v == 65535));
        assert!(f.as_u16().unwrap().contains(&65535));
    }
}
