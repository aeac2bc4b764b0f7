//! Moment matching of stochastic effects through the library's forward models.
//!
//! The signature stage measured a statistic on the real images (variance intercept and slope,
//! cross-frame PRNU covariance, row-offset variance, hot-pixel rate, JPEG lattice). Here the
//! library effect is applied to a synthetic probe frame of the real data's format with a trial
//! parameter, the same statistic is measured on the output, and the parameter is corrected until
//! the two agree. This calibrates the reported parameters to the library's exact conventions
//! (rounding, 8-bit DN units, clipping) without re-deriving them.
//!
//! `loss_before`/`loss_after` of these findings is the squared standardised mismatch of the
//! statistic without the effect and with the fitted effect.

use super::common::NoiseModel;
use super::img::{FS, planes_of};
use super::types::Signature;
use crate::faults::{self, EffectCtx, Params, registry};
use crate::frame::{Frame, PixelFormat};

const PW: u32 = 256;
const PH: u32 = 256;

/// Probe frame of constant level (8-bit DN) in the format of `like`.
fn flat(like: &Frame, level: f32) -> Frame {
    flat_sized(like, level, PW, PH)
}

/// A flat probe frame of `w` x `h` pixels in `like`'s format (Bayer as mono).
fn flat_sized(like: &Frame, level: f32, w: u32, h: u32) -> Frame {
    let fmt = match like.format {
        PixelFormat::Bayer8 => PixelFormat::Mono8,
        f => f,
    };
    let mut f = Frame::new(w, h, fmt).unwrap_or_else(|_| like.clone());
    let scale = f.full_scale() / FS;
    for y in 0..f.height as usize {
        for x in 0..f.width as usize {
            for c in 0..f.channels() {
                f.set(x, y, c, level * scale);
            }
        }
    }
    f
}

fn apply(name: &str, p: &Params, f: &Frame, seed: u64, seq: u64) -> Option<Frame> {
    let mut e = faults::create(name).ok()?;
    let mut out = f.clone();
    out.seq = seq;
    let mut ctx = EffectCtx::new(seed, seq, 0);
    e.apply(&mut out, p, &mut ctx).ok()?;
    Some(out)
}

/// Variance (8-bit DN²) of the first channel of a frame.
fn var_of(f: &Frame) -> (f64, f64) {
    let p = &planes_of(f)[0];
    let n = p.data.len() as f64;
    let m = p.data.iter().map(|&v| v as f64).sum::<f64>() / n;
    let v = p.data.iter().map(|&v| (v as f64 - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, v)
}

/// Calibrated parameters, method text, loss before and after. `dark_var` is the variance
/// (DN²) the fitted dark current's own shot noise adds, which the read noise must not repeat.
pub fn calibrate(
    sig: &Signature,
    noise: &NoiseModel,
    dark_var: f64,
    like: &Frame,
    seed: u64,
) -> Option<(Params, String, f64, f64)> {
    let reg = registry::find(sig.effect)?;
    let mut p = super::common::params_from_signature(sig)?;
    let bins_loss = |a: f64, b: f64| -> f64 {
        // mean squared standardised mismatch of the binned variance curve
        let mut s = 0.0;
        let mut n = 0.0;
        for bin in &noise.bins {
            let (l, v, cnt) = (bin.level, bin.var, bin.n);
            if l < noise.fit_range.0 || l > noise.fit_range.1 {
                continue;
            }
            let m = a + b * l + noise.c * l * l;
            let se = v.max(0.05) * (2.0 / cnt.max(2) as f64).sqrt();
            s += ((v - m) / se).powi(2);
            n += 1.0;
        }
        if n > 0.0 { s / n } else { f64::NAN }
    };
    let q12 = noise.quant * noise.quant / 12.0;
    match sig.effect {
        "gaussian_noise" => {
            // Observed variance at zero signal, quantisation included, less the dark shot noise.
            let target = (noise.a - dark_var).max(0.0) + q12;
            let mut s = p.get("sigma_dn");
            for _ in 0..3 {
                let _ = p.set("sigma_dn", s.clamp(0.0, 64.0));
                let out = apply(reg.info.name, &p, &flat(like, 128.0), seed, 0)?;
                let (_, v) = var_of(&out);
                s = (s * s + (target - v)).max(0.0).sqrt();
            }
            let _ = p.set("sigma_dn", s.clamp(0.0, 64.0));
            let before = bins_loss(0.0, noise.b);
            let after = bins_loss(noise.a, noise.b);
            Some((p, "moment matching: variance at zero signal, through the library model".into(), before, after))
        }
        "shot_noise" => {
            let target = noise.b;
            let mut g = p.get("gain_e_per_dn");
            for _ in 0..3 {
                let _ = p.set("gain_e_per_dn", g.clamp(0.01, 1e6));
                let lo = apply(reg.info.name, &p, &flat(like, 48.0), seed, 1)?;
                let hi = apply(reg.info.name, &p, &flat(like, 176.0), seed, 2)?;
                let slope = (var_of(&hi).1 - var_of(&lo).1) / 128.0;
                if slope <= 0.0 || target <= 0.0 {
                    break;
                }
                g *= slope / target;
            }
            let _ = p.set("gain_e_per_dn", g.clamp(0.01, 1e6));
            let before = bins_loss(noise.a, 0.0);
            let after = bins_loss(noise.a, noise.b);
            Some((p, "moment matching: variance slope against signal, through the library model".into(), before, after))
        }
        "prnu" => {
            let target = sig.param("sigma").unwrap_or(0.0);
            let mut s = target;
            for _ in 0..3 {
                let _ = p.set("sigma", s.clamp(1e-6, 0.2));
                let out = apply(reg.info.name, &p, &flat(like, 200.0), seed, 0)?;
                let (m, v) = var_of(&out);
                let rel = ((v - q12) / (m * m)).max(0.0).sqrt();
                if rel <= 0.0 {
                    break;
                }
                s *= target / rel;
            }
            let _ = p.set("sigma", s.clamp(1e-6, 0.2));
            let se = sig.stderr.first().map(|x| x.1).unwrap_or(1.0).max(1e-9);
            Some((
                p,
                "moment matching: cross-frame covariance of the relative residual".into(),
                (target / se).powi(2),
                0.0,
            ))
        }
        "row_noise" => {
            let target_var = sig.param("sigma_dn").unwrap_or(0.0).powi(2);
            let mut s = target_var.sqrt();
            for _ in 0..3 {
                let _ = p.set("sigma_dn", s.clamp(0.0, 50.0));
                // A tall narrow probe: the variance of 16384 drawn row offsets is within ~1 % of
                // the model's, so the match does not inherit one seed's sampling error.
                let out = apply(reg.info.name, &p, &flat_sized(like, 128.0, 16, 16384), seed, 0)?;
                let pl = &planes_of(&out)[0];
                let rows: Vec<f64> = (0..pl.h)
                    .map(|y| pl.data[y * pl.w..(y + 1) * pl.w].iter().map(|&v| v as f64).sum::<f64>() / pl.w as f64)
                    .collect();
                let (m, _) = super::stats::mean_se(&rows);
                let v = rows.iter().map(|r| (r - m).powi(2)).sum::<f64>() / (rows.len() - 1) as f64;
                s = (s * s + (target_var - v)).max(0.0).sqrt();
            }
            let _ = p.set("sigma_dn", s.clamp(0.0, 50.0));
            Some((p, "moment matching: split-half covariance of row means".into(), sig.z.max(0.0).powi(2), 0.0))
        }
        "hot_pixels" => {
            if let Some(ex) = sig.param("offset_dn") {
                let _ = p.set("offset_dn", ex.clamp(0.0, 255.0));
            }
            Some((
                p,
                "hot-pixel rate counted directly (recurring isolated outliers)".into(),
                sig.z.max(0.0).powi(2),
                0.0,
            ))
        }
        "jpeg" => {
            Some((p, "quality from the DCT quantisation lattice (libjpeg tables)".into(), sig.z.max(0.0).powi(2), 0.0))
        }
        _ => Some((p, "signature estimate".into(), sig.z.max(0.0).powi(2), 0.0)),
    }
}

/// Calibrate a fitted dark-current mean (an offset in the pixel fit) to the library model: the
/// library may add its mean through Poisson electrons with rounding and clipping.
pub fn calibrate_dark_mean(p: &mut Params, like: &Frame, seed: u64) {
    let Some(reg) = registry::find("dark_current") else { return };
    let target = p.get("mean_dn");
    let mut m = target;
    let mut probe = *p;
    let _ = probe.set("hot_pixel_rate", 0.0);
    for _ in 0..3 {
        let _ = probe.set("mean_dn", m.max(0.0));
        let Some(out) = apply(reg.info.name, &probe, &flat(like, 60.0), seed, 0) else { return };
        let (mean, _) = var_of(&out);
        let got = mean - 60.0;
        if got <= 0.0 {
            return;
        }
        m *= target / got;
    }
    let _ = p.set("mean_dn", m.max(0.0));
}
