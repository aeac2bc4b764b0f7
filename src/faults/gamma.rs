//! `gamma`: power-law transfer of the readout/ISP, `v' = FS·(v/FS)^gamma`.

use super::kit::Lut;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::Frame;

pub static INFO: EffectInfo = EffectInfo {
    name: "gamma",
    stage: Stage::Readout,
    order: 60,
    summary: "power-law transfer curve (display gamma / ISP tone curve)",
    model: "v' = FS * (v / FS)^gamma after clipping v to [0, FS], rounded to nearest. FS = 255 (8-bit) or \
            65535 (16-bit); applied to every channel. gamma < 1 brightens mid-tones, gamma > 1 darkens them; \
            0 and FS are fixed points. gamma = 1 is the identity (exact bytes). Exact and deterministic: a \
            lookup table computed in f64, rebuilt only when gamma or the sample width changes.",
    params: &[ParamSpec::float("gamma", "1", 0.1, 10.0, 1.0, "exponent of the transfer curve (1 = none)").log()],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(Gamma::default())
}

#[derive(Default)]
pub struct Gamma {
    lut: Lut,
}

/// The exact transfer in DN (before rounding).
pub fn transfer(v: f64, fs: f64, gamma: f64) -> f64 {
    fs * (v.clamp(0.0, fs) / fs).powf(gamma)
}

impl Effect for Gamma {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let g = p.get("gamma");
        if g == 1.0 {
            return Ok(Outcome::Keep);
        }
        self.lut.ensure((g.to_bits(), 0, 0), frame.as_u16().is_some(), |v, fs| transfer(v, fs, g));
        self.lut.apply(frame);
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn ramp(format: PixelFormat) -> Frame {
        let mut f = Frame::new(256, 2, format).unwrap();
        let s = format.dn_scale();
        for x in 0..256 {
            for c in 0..format.channels() {
                f.set(x, 0, c, x as f32 * s);
                f.set(x, 1, c, (255 - x) as f32 * s);
            }
        }
        f
    }

    #[test]
    fn exact_power_law_and_identity() {
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
            let orig = ramp(format);
            let mut f = orig.clone();
            let mut e = Gamma::default();
            let mut p = Params::defaults(&INFO);
            e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            assert_eq!(f, orig, "gamma 1 is the identity");
            for g in [0.45, 2.2] {
                let mut f = orig.clone();
                p.set("gamma", g).unwrap();
                e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
                let fs = format.full_scale() as f64;
                for x in 0..256 {
                    for c in 0..format.channels() {
                        let want = transfer(orig.get(x, 0, c) as f64, fs, g).round();
                        assert_eq!(f.get(x, 0, c) as f64, want, "{format} gamma {g} at {x}");
                    }
                }
                assert_eq!(f.get(0, 0, 0), 0.0);
                assert_eq!(f.get(255, 0, 0) as f64, fs);
            }
        }
    }

    #[test]
    fn inverse_gammas_round_trip_within_quantisation() {
        let orig = ramp(PixelFormat::Mono16);
        let mut f = orig.clone();
        let mut e = Gamma::default();
        let mut p = Params::defaults(&INFO);
        p.set("gamma", 2.0).unwrap();
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        p.set("gamma", 0.5).unwrap();
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        for x in 1..256 {
            // d(sqrt(v·FS))/dv = 0.5·sqrt(FS/v): one DN of rounding after gamma 2 costs at most that.
            let v = orig.get(x, 0, 0) as f64;
            let tol = 0.5 * (65535.0 / (v * v / 65535.0).max(1.0)).sqrt() + 1.0;
            assert!((f.get(x, 0, 0) as f64 - v).abs() <= tol, "{x}: {} vs {v}", f.get(x, 0, 0));
        }
    }
}
