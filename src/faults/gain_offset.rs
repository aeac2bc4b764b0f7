//! `gain_offset`: linear transfer error of the readout chain, `v = gain * v + offset_dn`.

use super::kit::lut_u8_row;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, Sample};
use crate::with_image_mut;

pub static INFO: EffectInfo = EffectInfo {
    name: "gain_offset",
    stage: Stage::Readout,
    order: 50,
    summary: "linear gain and offset error of the analogue chain / ADC",
    model: "v' = gain * v + offset_dn * (FS/255), rounded to nearest and clipped to [0, FS]. \
            Exact and deterministic. gain = 1, offset_dn = 0 is the identity.",
    params: &[
        ParamSpec::float("gain", "1", 0.0, 4.0, 1.0, "multiplicative gain (1 = none)"),
        ParamSpec::float("offset_dn", "DN", -255.0, 255.0, 0.0, "additive offset in 8-bit DN (scaled for 16-bit)"),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(GainOffset::default())
}

/// Lookup-table implementation: the table is rebuilt only when parameters or format change.
#[derive(Default)]
pub struct GainOffset {
    lut_key: Option<(u64, u64, bool)>,
    // allocation: once per parameter change (65536 entries for 16-bit, 256 for 8-bit)
    lut8: Vec<u8>,
    lut16: Vec<u16>,
}

fn build<T: Sample>(gain: f64, offset: f64) -> impl Iterator<Item = T> {
    (0..=T::MAX_U32).map(move |v| T::from_f32((gain * v as f64 + offset) as f32))
}

impl Effect for GainOffset {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let gain = p.get("gain");
        let offset = p.get("offset_dn") * frame.format.dn_scale() as f64;
        let wide = frame.as_u16().is_some();
        let key = (gain.to_bits(), offset.to_bits(), wide);
        if self.lut_key != Some(key) {
            if wide {
                self.lut16.clear();
                self.lut16.extend(build::<u16>(gain, offset));
            } else {
                self.lut8.clear();
                self.lut8.extend(build::<u8>(gain, offset));
            }
            self.lut_key = Some(key);
        }
        let (l8, l16) = (&self.lut8, &self.lut16);
        let t8 = <&[u8; 256]>::try_from(&l8[..]).ok();
        with_image_mut!(frame, img => {
            for row in img.rows_mut() {
                match (Sample::bytes_mut(&mut *row), t8) {
                    (Some(bytes), Some(t8)) => lut_u8_row(bytes, t8),
                    (_, _) => {
                        for v in row.iter_mut() {
                            *v = lut_get(l8, l16, *v);
                        }
                    }
                }
            }
        });
        Ok(Outcome::Keep)
    }
}

#[inline(always)]
fn lut_get<T: Sample>(l8: &[u8], l16: &[u16], v: T) -> T {
    let i = v.to_u32() as usize;
    if T::MAX_U32 == 255 { T::from_u32_sat(l8[i] as u32) } else { T::from_u32_sat(l16[i] as u32) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    #[test]
    fn exact_transfer_and_identity() {
        let mut f = Frame::new(256, 1, PixelFormat::Mono8).unwrap();
        for x in 0..256 {
            f.set(x, 0, 0, x as f32);
        }
        let orig = f.clone();
        let mut e = GainOffset::default();
        let mut ctx = EffectCtx::new(0, 0, 0);
        let mut p = Params::defaults(&INFO);
        e.apply(&mut f, &p, &mut ctx).unwrap();
        assert_eq!(f, orig, "gain 1, offset 0 is the identity");
        p.set("gain", 0.5).unwrap();
        p.set("offset_dn", 10.0).unwrap();
        e.apply(&mut f, &p, &mut ctx).unwrap();
        for x in 0..256 {
            let want = (0.5 * x as f64 + 10.0).round().clamp(0.0, 255.0);
            assert_eq!(f.get(x, 0, 0) as f64, want);
        }
        assert!(p.set("gain", 5.0).is_err());
    }

    #[test]
    fn sixteen_bit_offset_is_scaled() {
        let mut f = Frame::new(4, 1, PixelFormat::Mono16).unwrap();
        let mut p = Params::defaults(&INFO);
        p.set("offset_dn", 1.0).unwrap();
        GainOffset::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f.get(0, 0, 0), 257.0);
    }
}
