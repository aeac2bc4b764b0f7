//! `defocus`: isotropic Gaussian blur (defocus / diffraction / soft optics), separable.

use super::kit::{ROWS_PER_TASK, axpy_row, band_rows, bands, mirrored_row_f32, par_bands_with, round_row};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, FrameData, Sample};
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "defocus",
    stage: Stage::Optics,
    order: 40,
    summary: "isotropic Gaussian point-spread function (defocus, soft optics)",
    model: "Convolution with an isotropic Gaussian PSF of standard deviation sigma_px, applied separably \
            (rows, then columns) with the discrete Gaussian kernel T(n) = exp(-s) I_n(s), s = sigma_px^2 \
            (Lindeberg's discrete analogue of the Gaussian: its variance is exactly sigma_px^2 even below one \
            pixel), truncated at |n| <= ceil(4 sigma_px) + 1 and renormalised. Borders are mirrored \
            (half-sample symmetric), which makes the operator conserve the total signal: the image mean is \
            kept up to the final rounding (|error| < 0.5 DN per pixel, zero on average). Channels are \
            blurred independently; computed in f32, rounded to nearest and clipped. sigma_px = 0 is the \
            identity.",
    params: &[ParamSpec::float("sigma_px", "px", 0.0, 20.0, 1.5, "standard deviation of the Gaussian PSF")],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(Defocus::default())
}

/// Discrete Gaussian kernel of variance `sigma^2` (taps -r..=r, normalised), r = ceil(4 sigma) + 1.
/// Computed with Miller's backward recurrence for the modified Bessel functions I_n(s).
pub fn discrete_gaussian(sigma: f64) -> Vec<f32> {
    if sigma <= 0.0 {
        return vec![1.0];
    }
    let s = sigma * sigma;
    let r = (4.0 * sigma).ceil() as usize + 1;
    // Start well above r so the recurrence has converged at n <= r.
    let start = r + 20 + (10.0 * s.sqrt()) as usize + (2.0 * s) as usize;
    let mut vals = vec![0.0f64; start + 2];
    vals[start] = 1e-300;
    for n in (1..=start).rev() {
        vals[n - 1] = vals[n + 1] + (2.0 * n as f64 / s) * vals[n];
        if vals[n - 1] > 1e250 {
            for v in vals.iter_mut() {
                *v *= 1e-250;
            }
        }
    }
    // exp(s) = I_0 + 2 sum_{n>=1} I_n.
    let total = vals[0] + 2.0 * vals[1..].iter().sum::<f64>();
    let half: Vec<f64> = vals[..=r].iter().map(|v| v / total).collect();
    let mut k: Vec<f64> = half[1..].iter().rev().chain(half.iter()).copied().collect();
    let sum: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    k.into_iter().map(|v| v as f32).collect()
}

/// Half-sample symmetric index into [0, n).
#[inline]
pub fn mirror(i: isize, n: usize) -> usize {
    let n2 = 2 * n as isize;
    let m = i.rem_euclid(n2);
    if m >= n as isize { (n2 - 1 - m) as usize } else { m as usize }
}

#[derive(Default)]
pub struct Defocus {
    kernel_key: Option<u64>,
    kernel: Vec<f32>,
    // allocation: once per frame size: f32 copy of the frame after the row pass
    tmp: Vec<f32>,
    // allocation: once per frame size: per band, a mirrored input row (pass 1) and an
    // accumulator row (pass 2)
    pad: Vec<f32>,
    acc: Vec<f32>,
}

/// Row pass: each input row, mirrored at its ends, convolved into `tmp` (packed, w*ch per row).
fn row_pass<T: Sample>(src: &[T], stride: usize, w: usize, ch: usize, k: &[f32], tmp: &mut [f32], pad: &mut [f32]) {
    let r = k.len() / 2;
    let rl = w * ch;
    let padw = (w + 2 * r) * ch;
    tmp.par_chunks_mut(rl * ROWS_PER_TASK).zip(pad.par_chunks_mut(padw)).enumerate().for_each(|(b, (out, pad))| {
        for (i, orow) in out.chunks_mut(rl).enumerate() {
            let y = b * ROWS_PER_TASK + i;
            let irow = &src[y * stride..y * stride + rl];
            mirrored_row_f32(irow, w, ch, r, pad);
            orow.fill(0.0);
            for (j, &kj) in k.iter().enumerate() {
                let src = &pad[j * ch..j * ch + rl];
                axpy_row(orow, kj, src, 0u8);
            }
        }
    });
}

/// Column pass: output row y = sum_j k_j tmp[mirror(y + j - r)].
fn col_pass<T: Sample>(dst: &mut [T], stride: usize, h: usize, rl: usize, k: &[f32], tmp: &[f32], acc: &mut [f32]) {
    let r = k.len() / 2;
    par_bands_with(dst, stride, h, acc, rl, |_, y0, band, acc| {
        for (i, orow) in band_rows(band, stride, rl).enumerate() {
            let y = y0 + i;
            acc.fill(0.0);
            for (j, &kj) in k.iter().enumerate() {
                let sy = mirror(y as isize + j as isize - r as isize, h);
                let src = &tmp[sy * rl..(sy + 1) * rl];
                axpy_row(acc, kj, src, 0u8);
            }
            round_row(orow, acc);
        }
    });
}

impl Effect for Defocus {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let sigma = p.get("sigma_px");
        if sigma == 0.0 {
            return Ok(Outcome::Keep);
        }
        if self.kernel_key != Some(sigma.to_bits()) {
            self.kernel = discrete_gaussian(sigma);
            self.kernel_key = Some(sigma.to_bits());
        }
        let (w, h, ch, stride) = (frame.width as usize, frame.height as usize, frame.channels(), frame.stride);
        let rl = w * ch;
        let r = self.kernel.len() / 2;
        self.tmp.resize(rl * h, 0.0);
        self.pad.resize((w + 2 * r) * ch * bands(h), 0.0);
        self.acc.resize(rl * bands(h), 0.0);
        let k = &self.kernel;
        match &mut frame.data {
            FrameData::U8(d) => {
                row_pass(d, stride, w, ch, k, &mut self.tmp, &mut self.pad);
                col_pass(d, stride, h, rl, k, &self.tmp, &mut self.acc);
            }
            FrameData::U16(d) => {
                row_pass(d, stride, w, ch, k, &mut self.tmp, &mut self.pad);
                col_pass(d, stride, h, rl, k, &self.tmp, &mut self.acc);
            }
        }
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    #[test]
    fn kernel_has_variance_sigma_squared() {
        for sigma in [0.3, 0.7, 1.5, 4.0, 20.0] {
            let k = discrete_gaussian(sigma);
            let r = (k.len() / 2) as f64;
            let sum: f64 = k.iter().map(|&v| v as f64).sum();
            let var: f64 = k.iter().enumerate().map(|(i, &v)| v as f64 * (i as f64 - r).powi(2)).sum();
            assert!((sum - 1.0).abs() < 1e-5, "{sigma}: sum {sum}");
            assert!((var - sigma * sigma).abs() < 1e-3 * sigma * sigma + 1e-5, "{sigma}: var {var}");
            for i in 0..k.len() {
                assert_eq!(k[i], k[k.len() - 1 - i]);
            }
        }
        assert_eq!(discrete_gaussian(0.0), vec![1.0]);
    }

    #[test]
    fn mirror_folds_indices() {
        let got: Vec<usize> = (-4..8).map(|i| mirror(i, 3)).collect();
        assert_eq!(got, vec![2, 2, 1, 0, 0, 1, 2, 2, 1, 0, 0, 1]);
    }

    #[test]
    fn keeps_the_mean_and_spreads_a_dot_by_sigma() {
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
            let orig = crate::faults::kit::bench_scene(96, 80, format, 4).unwrap();
            let mut f = orig.clone();
            let mut p = Params::defaults(&INFO);
            p.set("sigma_px", 2.5).unwrap();
            Defocus::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            let mean = |f: &Frame| f.packed_samples_f32().iter().map(|&v| v as f64).sum::<f64>() / (96.0 * 80.0);
            // Rounding errors are within ±0.5 DN per sample and average out; 0.05 DN is > 10 sigma.
            let (m0, m1) = (mean(&orig), mean(&f));
            assert!((m0 - m1).abs() < 0.05 * format.dn_scale() as f64 + 1e-9, "{format}: {m0} -> {m1}");
            assert_ne!(f, orig);
        }
        // A dot in a 16-bit frame: the second moment of the blurred spot is sigma^2 per axis.
        let mut f = Frame::new(61, 61, PixelFormat::Mono16).unwrap();
        f.set(30, 30, 0, 60000.0);
        let mut p = Params::defaults(&INFO);
        p.set("sigma_px", 3.0).unwrap();
        Defocus::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        let (mut s, mut sxx, mut syy) = (0.0, 0.0, 0.0);
        for y in 0..61 {
            for x in 0..61 {
                let v = f.get(x, y, 0) as f64;
                s += v;
                sxx += v * (x as f64 - 30.0).powi(2);
                syy += v * (y as f64 - 30.0).powi(2);
            }
        }
        assert!((s - 60000.0).abs() < 61.0 * 61.0 * 0.5, "total {s}");
        assert!((sxx / s - 9.0).abs() < 0.1 && (syy / s - 9.0).abs() < 0.1, "{} {}", sxx / s, syy / s);
    }

    #[test]
    fn zero_sigma_identity_thread_independent_and_padded_rows() {
        let orig = crate::faults::kit::bench_scene(130, 150, PixelFormat::Rgb8, 5).unwrap();
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("sigma_px", 0.0).unwrap();
        let mut e = Defocus::default();
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f, orig);
        p.set("sigma_px", 1.2).unwrap();
        let run = |threads, frame: &Frame| {
            let mut f = frame.clone();
            rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                Defocus::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            });
            f
        };
        let one = run(1, &orig);
        assert_eq!(one, run(2, &orig));
        // Same image with padded rows gives the same pixels and keeps the padding.
        let rl = orig.row_len();
        let mut padded = Vec::new();
        for row in orig.as_u8().unwrap().chunks(rl) {
            padded.extend_from_slice(row);
            padded.extend_from_slice(&[7, 7, 7, 7, 7]);
        }
        let pf = Frame::from_data(130, 150, rl + 5, PixelFormat::Rgb8, FrameData::U8(padded)).unwrap();
        let out = run(2, &pf);
        assert_eq!(out.to_packed().as_u8(), one.as_u8());
        assert!(out.as_u8().unwrap().chunks(rl + 5).all(|r| r[rl..] == [7, 7, 7, 7, 7]));
    }
}
