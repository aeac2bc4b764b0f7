//! `row_noise`: row-correlated read noise (banding), a fresh offset per row and frame.

use super::kit::{band_rows, par_bands};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, FrameData};

pub static INFO: EffectInfo = EffectInfo {
    name: "row_noise",
    stage: Stage::Readout,
    order: 20,
    summary: "per-row offset noise (horizontal banding), new every frame",
    model: "Row y of every frame gets an additive offset o_y = sigma_dn * (FS/255) * n_y, n_y ~ N(0, 1) \
            independent per row and frame (row y draws from the frame generator's child derive(y), so the \
            result does not depend on the thread count). All channels of a row share the offset. Output \
            v' = clip(v + round(o_y), 0, FS), which equals round(v + o_y) for integer v: the ADC quantises \
            the offset signal. The standard deviation of the row means is sqrt(sigma_dn^2 + 1/12) in 8-bit \
            DN away from clipping (the 1/12 is the quantisation). sigma_dn = 0 is the identity.",
    params: &[ParamSpec::float("sigma_dn", "DN", 0.0, 50.0, 2.0, "standard deviation of the row offset, 8-bit DN")],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(RowNoise)
}

pub struct RowNoise;

/// Offset of row `y` in DN of the frame's format (before rounding).
pub fn row_offset(ctx_rng: &crate::rng::Rng, y: usize, sigma: f64) -> f64 {
    sigma * ctx_rng.derive(y as u64).normal()
}

impl Effect for RowNoise {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let sigma = p.get("sigma_dn") * frame.format.dn_scale() as f64;
        if sigma == 0.0 {
            return Ok(Outcome::Keep);
        }
        let (stride, height, row_len) = (frame.stride, frame.height as usize, frame.row_len());
        let rng = &ctx.rng;
        match &mut frame.data {
            FrameData::U8(d) => par_bands(d, stride, height, |_, y0, band| {
                for (i, row) in band_rows(band, stride, row_len).enumerate() {
                    let o = row_offset(rng, y0 + i, sigma).round().clamp(-255.0, 255.0) as i16;
                    if o != 0 {
                        for v in row.iter_mut() {
                            *v = (*v as i16 + o).clamp(0, 255) as u8;
                        }
                    }
                }
            }),
            FrameData::U16(d) => par_bands(d, stride, height, |_, y0, band| {
                for (i, row) in band_rows(band, stride, row_len).enumerate() {
                    let o = row_offset(rng, y0 + i, sigma).round().clamp(-65535.0, 65535.0) as i32;
                    if o != 0 {
                        for v in row.iter_mut() {
                            *v = (*v as i32 + o).clamp(0, 65535) as u16;
                        }
                    }
                }
            }),
        }
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn grey(w: u32, h: u32, format: PixelFormat, v: f32) -> Frame {
        let mut f = Frame::new(w, h, format).unwrap();
        with_fill(&mut f, v);
        f
    }
    fn with_fill(f: &mut Frame, v: f32) {
        for y in 0..f.height as usize {
            for x in 0..f.width as usize {
                for c in 0..f.channels() {
                    f.set(x, y, c, v);
                }
            }
        }
    }

    #[test]
    fn row_means_have_std_sigma_and_rows_are_flat() {
        let sigma = 4.0;
        let mut f = grey(16, 4000, PixelFormat::Rgb8, 128.0);
        let mut p = Params::defaults(&INFO);
        p.set("sigma_dn", sigma).unwrap();
        RowNoise.apply(&mut f, &p, &mut EffectCtx::new(1, 0, 0)).unwrap();
        let mut means = Vec::new();
        for y in 0..4000 {
            let first = f.get(0, y, 0);
            for x in 0..16 {
                for c in 0..3 {
                    assert_eq!(f.get(x, y, c), first, "a row shares one offset");
                }
            }
            means.push(first as f64 - 128.0);
        }
        let n = means.len() as f64;
        let m = means.iter().sum::<f64>() / n;
        let sd = (means.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (n - 1.0)).sqrt();
        let want = (sigma * sigma + 1.0 / 12.0).sqrt();
        // Relative standard error of a sample std is 1/sqrt(2n) = 1.1%; allow 5 of them.
        assert!((sd - want).abs() < 5.0 * want / (2.0 * n).sqrt(), "std {sd}, want {want}");
        assert!(m.abs() < 5.0 * want / n.sqrt(), "mean {m}");
    }

    #[test]
    fn zero_sigma_is_identity_and_thread_count_does_not_matter() {
        let orig = crate::faults::kit::bench_scene(200, 300, PixelFormat::Mono16, 3).unwrap();
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("sigma_dn", 0.0).unwrap();
        RowNoise.apply(&mut f, &p, &mut EffectCtx::new(1, 0, 0)).unwrap();
        assert_eq!(f, orig);
        p.set("sigma_dn", 3.0).unwrap();
        let run = |threads| {
            let mut f = orig.clone();
            rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                RowNoise.apply(&mut f, &p, &mut EffectCtx::new(1, 5, 2)).unwrap();
            });
            f
        };
        let one = run(1);
        assert_eq!(one, run(2));
        assert_ne!(one, orig);
    }
}
