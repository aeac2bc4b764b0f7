//! `stray_light`: smooth additive veiling glare from a bright source outside the field of view.

use super::kit::{add_sat_row, band_rows, par_bands_with};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, Sample};
use crate::with_image_mut;

pub static INFO: EffectInfo = EffectInfo {
    name: "stray_light",
    stage: Stage::Optics,
    order: 20,
    summary: "smooth additive glare lobe from an off-axis bright source (Sun, Earth limb)",
    model: "v' = min(v + round(a(x, y)), FS), a = amplitude_dn * FS/255 * L(x, y) / max_frame(L), with the \
            Gaussian lobe L = exp(-|p - s|^2 / (2 w^2)) of a source at s = c + distance * R * (cos t, -sin t): \
            c the image centre, R the half-diagonal, t = angle_deg counter-clockwise from +x as displayed \
            (y up on screen, so +90 deg is above the frame), w = width * R. The lobe is normalised by its \
            maximum inside the frame, so amplitude_dn is exactly the largest added signal (reached at the \
            frame point nearest the source). distance < 1 puts the source inside the field. The field is \
            separable (L = Lx(x) Ly(y)), so it costs one multiply per pixel. All channels get the same \
            signal (grey glare). amplitude_dn = 0 is the identity.",
    params: &[
        ParamSpec::float("amplitude_dn", "DN", 0.0, 255.0, 30.0, "maximum added signal inside the frame, 8-bit DN"),
        ParamSpec::float("angle_deg", "deg", 0.0, 360.0, 45.0, "direction of the source from the centre, CCW").extra(),
        ParamSpec::float("distance", "half-diagonals", 0.0, 5.0, 1.3, "source distance from the centre").extra(),
        ParamSpec::float("width", "half-diagonals", 0.05, 5.0, 0.8, "lobe standard deviation").extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(StrayLight::default())
}

#[derive(Default)]
pub struct StrayLight {
    key: Option<(u32, u32, [u64; 4])>,
    // allocation: once per (size, parameters)
    lx: Vec<f32>,
    ly: Vec<f32>,
    // allocation: once per frame size: one row of addends (per sample) per band
    scratch: Vec<u32>,
}

/// The separable lobe factors (Lx per column, Ly per row), scaled so that max(Lx)·max(Ly) =
/// amplitude (in DN of the frame).
pub fn lobe(w: u32, h: u32, amplitude: f64, angle_deg: f64, distance: f64, width: f64) -> (Vec<f32>, Vec<f32>) {
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let r = (cx * cx + cy * cy).sqrt().max(0.5);
    let t = angle_deg.to_radians();
    let (sx, sy) = (cx + distance * r * t.cos(), cy - distance * r * t.sin());
    let sig = width * r;
    let g = |d: f64| (-(d * d) / (2.0 * sig * sig)).exp();
    let lx: Vec<f64> = (0..w).map(|x| g(x as f64 - sx)).collect();
    let ly: Vec<f64> = (0..h).map(|y| g(y as f64 - sy)).collect();
    let mx = lx.iter().cloned().fold(f64::MIN_POSITIVE, f64::max);
    let my = ly.iter().cloned().fold(f64::MIN_POSITIVE, f64::max);
    let ax = amplitude.sqrt();
    (lx.iter().map(|v| (ax * v / mx) as f32).collect(), ly.iter().map(|v| (ax * v / my) as f32).collect())
}

fn add_field<T: Sample, const CH: usize>(
    data: &mut [T],
    stride: usize,
    h: usize,
    lx: &[f32],
    ly: &[f32],
    scratch: &mut [u32],
) {
    let w = lx.len();
    par_bands_with(data, stride, h, scratch, w * CH, |_, y0, band, add| {
        for (i, row) in band_rows(band, stride, w * CH).enumerate() {
            let fy = ly[y0 + i];
            // Per-sample addends (all channels of a pixel get the same), then a flat loop.
            for (a, &fx) in add.chunks_exact_mut(CH).zip(lx) {
                // fx * fy is in [0, amplitude]: round half up as u16 sample rounding does.
                a.fill(u16::from_f32(fx * fy) as u32);
            }
            add_sat_row(row, add);
        }
    });
}

impl Effect for StrayLight {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let amp = p.get("amplitude_dn") * frame.format.dn_scale() as f64;
        if amp == 0.0 {
            return Ok(Outcome::Keep);
        }
        let (w, h) = (frame.width, frame.height);
        let pk = [amp.to_bits(), p.get("angle_deg").to_bits(), p.get("distance").to_bits(), p.get("width").to_bits()];
        if self.key != Some((w, h, pk)) {
            let (lx, ly) = lobe(w, h, amp, p.get("angle_deg"), p.get("distance"), p.get("width"));
            self.lx = lx;
            self.ly = ly;
            self.key = Some((w, h, pk));
        }
        self.scratch.resize(w as usize * frame.channels() * super::kit::bands(h as usize), 0);
        let (stride, ch) = (frame.stride, frame.channels());
        let (lx, ly, scratch) = (&self.lx, &self.ly, &mut self.scratch);
        with_image_mut!(frame, img => match ch {
            3 => add_field::<_, 3>(img.data, stride, h as usize, lx, ly, scratch),
            _ => add_field::<_, 1>(img.data, stride, h as usize, lx, ly, scratch),
        });
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    #[test]
    fn maximum_is_amplitude_at_the_side_of_the_source_and_field_is_smooth() {
        let (w, h) = (160u32, 120u32);
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
            let mut f = Frame::new(w, h, format).unwrap();
            let mut p = Params::defaults(&INFO);
            p.set("amplitude_dn", 50.0).unwrap();
            p.set("angle_deg", 90.0).unwrap(); // source above the frame
            StrayLight::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            let s = format.dn_scale();
            let max = (0..h as usize)
                .flat_map(|y| (0..w as usize).map(move |x| (x, y)))
                .map(|(x, y)| f.get(x, y, 0))
                .fold(0.0f32, f32::max);
            assert_eq!(max, (50.0 * s).round(), "{format}");
            // Brightest at the top (y = 0 is the top row on screen), decreasing downwards.
            for y in 1..h as usize {
                assert!(f.get(80, y, 0) <= f.get(80, y - 1, 0));
            }
            assert!(f.get(80, 0, 0) > 2.0 * f.get(80, h as usize - 1, 0));
            // Low spatial frequency: neighbouring pixels differ by little.
            for y in 0..h as usize {
                for x in 1..w as usize {
                    assert!((f.get(x, y, 0) - f.get(x - 1, y, 0)).abs() <= 1.0 + 0.02 * 50.0 * s);
                }
            }
        }
    }

    #[test]
    fn zero_amplitude_is_identity_and_saturates() {
        let orig = crate::faults::kit::bench_scene(64, 48, PixelFormat::Rgb8, 2).unwrap();
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("amplitude_dn", 0.0).unwrap();
        let mut e = StrayLight::default();
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f, orig);
        p.set("amplitude_dn", 255.0).unwrap();
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert!(f.as_u8().unwrap().iter().zip(orig.as_u8().unwrap()).all(|(a, b)| a >= b));
    }
}
