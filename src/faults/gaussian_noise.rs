//! `gaussian_noise`: additive zero-mean Gaussian read noise of the readout chain.
//!
//! Fast sampler: a 4096-bucket inverse-CDF table whose entries are the *conditional means* of
//! the standard normal inside each probability bucket (so the table has zero mean and the
//! variance lost inside the buckets is below 1e-5), with the two extreme buckets (|z| > 3.35,
//! probability 1/2048) sampled exactly by the inverse CDF. Each sample takes a 16-bit uniform from
//! the band's [`RngLanes`] and uses its low 12 bits (see [`super::noise`], which also has the
//! AVX2 path). The noise is pre-quantised: for an integer input v, `round_half_up(v + n)` equals
//! `v + floor(n + 0.5)`, so the table holds integer DN offsets.

use super::kit::RngLanes;
use super::noise::{NoiseTable, RESOLVE, add_table_noise};
use super::util::ROWS_PER_TASK;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, Sample};
use crate::rng::Rng;
use crate::with_image_mut;
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "gaussian_noise",
    stage: Stage::Readout,
    order: 10,
    summary: "additive zero-mean Gaussian read noise (amplifier and ADC noise)",
    model: "v' = clip(v + n), n ~ N(0, sigma^2) independent per sample and per frame, sigma = sigma_dn * FS/255 \
            (sigma_dn is given in 8-bit DN and scaled for 16-bit). The result is rounded to the nearest DN \
            (half up) and clipped to [0, FS], so the measured variance of an unclipped flat field is \
            sigma^2 + 1/12 DN^2 (quantisation, Sheppard). Normal deviates come from a 4096-bucket table of \
            conditional means (variance 1 - <1e-5) with exact inverse-CDF sampling of the outer buckets \
            (|z| > 3.35). Rgb8: independent noise per channel. sigma_dn = 0 is the identity. Range 0..=64 DN.",
    params: &[ParamSpec::float(
        "sigma_dn",
        "DN",
        0.0,
        64.0,
        2.0,
        "standard deviation of the read noise in 8-bit DN (scaled by FS/255 for 16-bit)",
    )],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(GaussianNoise::default())
}

/// Bits of uniform randomness per deviate.
pub const TABLE_BITS: u32 = 12;
/// Buckets in the normal table.
pub const TABLE_SIZE: usize = 1 << TABLE_BITS;

/// Standard normal density.
#[inline]
pub fn normal_pdf(z: f64) -> f64 {
    (-0.5 * z * z).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// Inverse of the standard normal CDF (Wichura 1988, algorithm AS 241 PPND16; relative error
/// about 1e-16). `p` outside (0, 1) gives ±infinity.
#[allow(clippy::inconsistent_digit_grouping, clippy::excessive_precision)]
pub fn inverse_normal_cdf(p: f64) -> f64 {
    if p <= 0.0 {
        return f64::NEG_INFINITY;
    }
    if p >= 1.0 {
        return f64::INFINITY;
    }
    let q = p - 0.5;
    if q.abs() <= 0.425 {
        let r = 0.180625 - q * q;
        let num = ((((((r * 2509.080_928_730_122_7 + 33430.575_583_588_13) * r + 67265.770_927_008_7) * r
            + 45921.953_931_549_87)
            * r
            + 13731.693_765_509_461)
            * r
            + 1971.590_950_306_551_3)
            * r
            + 133.141_667_891_784_38)
            * r
            + 3.387_132_872_796_366_5;
        let den = ((((((r * 5226.495_278_852_546 + 28729.085_735_721_943) * r + 39307.895_800_092_71) * r
            + 21213.794_301_586_597)
            * r
            + 5394.196_021_424_751)
            * r
            + 687.187_007_492_057_9)
            * r
            + 42.313_330_701_600_91)
            * r
            + 1.0;
        return q * num / den;
    }
    let mut r = if q < 0.0 { p } else { 1.0 - p };
    r = (-r.ln()).sqrt();
    let val = if r <= 5.0 {
        let r = r - 1.6;
        let num = ((((((r * 7.745_450_142_783_414e-4 + 0.022_723_844_989_269_184) * r + 0.241_780_725_177_450_6)
            * r
            + 1.270_458_252_452_368_4)
            * r
            + 3.647_848_324_763_204_5)
            * r
            + 5.769_497_221_460_691)
            * r
            + 4.630_337_846_156_545)
            * r
            + 1.423_437_110_749_683_5;
        let den = ((((((r * 1.050_750_071_644_416_8e-9 + 5.475_938_084_995_345e-4) * r + 0.015_198_666_563_616_457)
            * r
            + 0.148_103_976_427_480_08)
            * r
            + 0.689_767_334_985_1)
            * r
            + 1.676_384_830_183_803_8)
            * r
            + 2.053_191_626_637_758_8)
            * r
            + 1.0;
        num / den
    } else {
        let r = r - 5.0;
        let num =
            ((((((r * 2.010_334_399_292_288e-7 + 2.711_555_568_743_487_6e-5) * r + 0.001_242_660_947_388_078_4) * r
                + 0.026_532_189_526_576_124)
                * r
                + 0.296_560_571_828_504_9)
                * r
                + 1.784_826_539_917_291_3)
                * r
                + 5.463_784_911_164_114)
                * r
                + 6.657_904_643_501_103;
        let den =
            ((((((r * 2.044_263_103_389_939_7e-15 + 1.421_511_758_316_446e-7) * r + 1.846_318_317_510_054_8e-5) * r
                + 7.868_691_311_456_133e-4)
                * r
                + 0.014_875_361_290_850_615)
                * r
                + 0.136_929_880_922_735_8)
                * r
                + 0.599_832_206_555_887_9)
                * r
                + 1.0;
        num / den
    };
    if q < 0.0 { -val } else { val }
}

/// The table of conditional means: entry i is E[Z | Φ(Z) ∈ [i/N, (i+1)/N)], i.e.
/// (φ(a_i) − φ(a_{i+1}))·N with a_i = Φ⁻¹(i/N). Antisymmetric, zero mean.
pub fn conditional_mean_table() -> Vec<f64> {
    // allocation: once per effect instance
    let edges: Vec<f64> = (0..=TABLE_SIZE).map(|i| inverse_normal_cdf(i as f64 / TABLE_SIZE as f64)).collect();
    let pdf = |z: f64| if z.is_finite() { normal_pdf(z) } else { 0.0 };
    let mut t: Vec<f64> = (0..TABLE_SIZE).map(|i| (pdf(edges[i]) - pdf(edges[i + 1])) * TABLE_SIZE as f64).collect();
    // Enforce exact antisymmetry (the formula is antisymmetric up to rounding).
    for i in 0..TABLE_SIZE / 2 {
        let m = 0.5 * (t[i] - t[TABLE_SIZE - 1 - i]);
        t[i] = m;
        t[TABLE_SIZE - 1 - i] = -m;
    }
    t
}

/// Exact standard normal deviate from the lower (`upper = false`) or upper extreme bucket.
#[inline(never)]
fn tail_deviate(rng: &mut Rng, upper: bool) -> f64 {
    // U uniform in (0, 1/N): z = Φ⁻¹(U) is exactly the lower tail conditional distribution.
    let u = (rng.uniform() + 0.5 / (1u64 << 53) as f64) / TABLE_SIZE as f64;
    let z = inverse_normal_cdf(u);
    if upper { -z } else { z }
}

/// Fast standard-normal generator (table + exact tails). Bit-reproducible for a given `Rng`.
pub struct NormalTable {
    mean: Vec<f64>,
}

impl Default for NormalTable {
    fn default() -> Self {
        NormalTable { mean: conditional_mean_table() }
    }
}

impl NormalTable {
    /// Conditional mean of bucket `i`.
    pub fn bucket_mean(&self, i: usize) -> f64 {
        self.mean[i]
    }
    /// One standard normal deviate from a 12-bit bucket index and the generator (used only
    /// for the tails).
    #[inline]
    pub fn deviate(&self, idx: usize, rng: &mut Rng) -> f64 {
        if idx == 0 || idx == TABLE_SIZE - 1 { tail_deviate(rng, idx != 0) } else { self.mean[idx] }
    }
    /// Fill `out` with standard normal deviates.
    pub fn fill(&self, rng: &mut Rng, out: &mut [f64]) {
        let mut it = out.chunks_mut(5);
        for chunk in &mut it {
            let mut x = rng.next_u64();
            for o in chunk.iter_mut() {
                let idx = (x & (TABLE_SIZE as u64 - 1)) as usize;
                x >>= TABLE_BITS;
                *o = self.deviate(idx, rng);
            }
        }
    }
}

/// The effect; caches the quantised table for the current sigma.
#[derive(Default)]
pub struct GaussianNoise {
    normal: Option<NormalTable>,
    key: Option<u64>,
    quant: NoiseTable,
}

impl Effect for GaussianNoise {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let sigma = p.get("sigma_dn") * frame.format.dn_scale() as f64;
        if sigma <= 0.0 {
            return Ok(Outcome::Keep);
        }
        let normal = self.normal.get_or_insert_with(NormalTable::default);
        if self.key != Some(sigma.to_bits()) {
            // The two extreme buckets are drawn exactly (tail_q).
            let entry = |(i, m): (usize, &f64)| {
                if i == 0 || i == TABLE_SIZE - 1 { RESOLVE } else { (sigma * m + 0.5).floor() as i32 }
            };
            self.quant.rebuild(TABLE_BITS, normal.mean.iter().enumerate().map(entry));
            self.key = Some(sigma.to_bits());
        }
        let table = Table { normal, quant: &self.quant, sigma };
        let rng = &ctx.rng;
        with_image_mut!(frame, img => add_noise(&mut img, &table, rng));
        Ok(Outcome::Keep)
    }
}

struct Table<'a> {
    normal: &'a NormalTable,
    quant: &'a NoiseTable,
    sigma: f64,
}

fn add_noise<T: Sample>(img: &mut crate::frame::ImageMut<'_, T>, t: &Table<'_>, rng: &Rng) {
    let (stride, row_len, h) = (img.stride, img.row_len(), img.height);
    let used = stride * (h - 1) + row_len;
    img.data[..used].par_chunks_mut(stride * ROWS_PER_TASK).enumerate().for_each(|(band, chunk)| {
        // Band k: table indices from derive(k).derive(0), exact tails from derive(k).derive(1).
        let base = rng.derive(band as u64);
        let mut lanes = RngLanes::new(&base.derive(0));
        let mut exact = base.derive(1);
        for row in chunk.chunks_mut(stride) {
            let row = &mut row[..row_len];
            add_table_noise(row, &mut lanes, t.quant, &mut |idx| tail_q(t, idx, &mut exact));
        }
    });
}

#[cold]
fn tail_q(t: &Table<'_>, idx: usize, rng: &mut Rng) -> i32 {
    let z = t.normal.deviate(idx, rng);
    let n = (t.sigma * z + 0.5).floor();
    n.clamp(-1e9, 1e9) as i32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn run(f: &mut Frame, sigma: f64, seed: u64) {
        let mut p = Params::defaults(&INFO);
        p.set("sigma_dn", sigma).unwrap();
        GaussianNoise::default().apply(f, &p, &mut EffectCtx::new(seed, f.seq, 0)).unwrap();
    }

    fn moments(xs: impl Iterator<Item = f64>) -> (f64, f64, usize) {
        let v: Vec<f64> = xs.collect();
        let n = v.len() as f64;
        let m = v.iter().sum::<f64>() / n;
        let var = v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0);
        (m, var, v.len())
    }

    #[test]
    fn inverse_cdf_matches_known_quantiles() {
        assert_eq!(inverse_normal_cdf(0.5), 0.0);
        assert!((inverse_normal_cdf(0.975) - 1.959_963_984_540_054).abs() < 1e-12);
        assert!((inverse_normal_cdf(0.025) + 1.959_963_984_540_054).abs() < 1e-12);
        assert!((inverse_normal_cdf(0.8413447460685429) - 1.0).abs() < 1e-12);
        assert!((inverse_normal_cdf(1e-10) + 6.361_340_902_404_056).abs() < 1e-9);
    }

    #[test]
    fn table_has_zero_mean_and_unit_variance() {
        let t = conditional_mean_table();
        let n = TABLE_SIZE as f64;
        let mean: f64 = t.iter().sum::<f64>() / n;
        // Inner buckets from the table, outer buckets exactly: E[Z^2 | tail] = 1 + a·φ(a)/p.
        let a = inverse_normal_cdf(1.0 / n).abs();
        let tail_m2 = 1.0 + a * normal_pdf(a) * n;
        let var = (t[1..TABLE_SIZE - 1].iter().map(|m| m * m).sum::<f64>() + 2.0 * tail_m2) / n;
        assert!(mean.abs() < 1e-15, "mean {mean}");
        // Variance lost inside the inner buckets (bucket width <= 0.2 sigma near the edges).
        assert!((var - 1.0).abs() < 1e-5 && var < 1.0, "var {var}");
    }

    #[test]
    fn fast_generator_moments_and_tails() {
        let t = NormalTable::default();
        let mut rng = Rng::new(77);
        let mut z = vec![0.0; 1_000_000];
        t.fill(&mut rng, &mut z);
        let n = z.len() as f64;
        let m = z.iter().sum::<f64>() / n;
        let v = z.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / n;
        let k = z.iter().map(|x| ((x - m) / v.sqrt()).powi(4)).sum::<f64>() / n;
        // 5-sigma bounds: SE(mean) = 1e-3, SE(var) = sqrt(2/n) = 1.4e-3, SE(kurtosis) = sqrt(24/n) = 4.9e-3.
        assert!(m.abs() < 5e-3, "mean {m}");
        assert!((v - 1.0).abs() < 7.1e-3, "var {v}");
        assert!((k - 3.0).abs() < 0.025, "kurtosis {k}");
        // P(|Z| > 3) = 0.0026998; binomial SE = sqrt(p/n) = 5.2e-5.
        let p3 = z.iter().filter(|x| x.abs() > 3.0).count() as f64 / n;
        assert!((p3 - 0.0026998).abs() < 2.6e-4, "P(|z|>3) = {p3}");
        // Exact tails reach beyond the last table bucket.
        assert!(z.iter().any(|x| x.abs() > 4.0));
    }

    #[test]
    fn measured_sigma_matches_on_mid_grey_mono8() {
        let mut f = Frame::new(256, 256, PixelFormat::Mono8).unwrap();
        f.as_u8_mut().unwrap().fill(128);
        let sigma = 4.0;
        run(&mut f, sigma, 3);
        let (m, var, n) = moments(f.as_u8().unwrap().iter().map(|&v| v as f64));
        // Quantisation adds 1/12 DN^2 (Sheppard); no clipping (128 +- 127 is 32 sigma).
        let want = sigma * sigma + 1.0 / 12.0;
        let se_var = want * (2.0 / n as f64).sqrt();
        let se_m = (want / n as f64).sqrt();
        assert!((var - want).abs() < 5.0 * se_var, "var {var} want {want} (5 SE = {})", 5.0 * se_var);
        assert!((m - 128.0).abs() < 5.0 * se_m, "mean {m}");
    }

    #[test]
    fn measured_sigma_matches_on_mono16_and_rgb8() {
        let mut f = Frame::new(200, 150, PixelFormat::Mono16).unwrap();
        f.as_u16_mut().unwrap().fill(30000);
        run(&mut f, 2.0, 5);
        let (_, var, n) = moments(f.as_u16().unwrap().iter().map(|&v| v as f64));
        let want = (2.0f64 * 257.0).powi(2) + 1.0 / 12.0;
        assert!((var - want).abs() < 5.0 * want * (2.0 / n as f64).sqrt(), "mono16 var {var} want {want}");

        let mut f = Frame::new(160, 120, PixelFormat::Rgb8).unwrap();
        f.as_u8_mut().unwrap().fill(100);
        run(&mut f, 3.0, 6);
        for c in 0..3 {
            let (_, var, n) = moments(f.as_u8().unwrap().iter().skip(c).step_by(3).map(|&v| v as f64));
            let want = 9.0 + 1.0 / 12.0;
            assert!((var - want).abs() < 5.0 * want * (2.0 / n as f64).sqrt(), "rgb channel {c}: var {var}");
        }
    }

    #[test]
    fn zero_sigma_is_identity_and_noise_is_new_every_frame() {
        let mut f = Frame::new(64, 48, PixelFormat::Rgb8).unwrap();
        f.as_u8_mut().unwrap().iter_mut().enumerate().for_each(|(i, v)| *v = (i * 7 % 256) as u8);
        let orig = f.clone();
        run(&mut f, 0.0, 1);
        assert_eq!(f, orig);
        let mut a = orig.clone();
        let mut b = orig.clone();
        b.seq = 1;
        run(&mut a, 2.0, 1);
        run(&mut b, 2.0, 1);
        assert_ne!(a.as_u8(), b.as_u8(), "independent noise per frame");
        let mut c = orig.clone();
        run(&mut c, 2.0, 1);
        assert_eq!(a, c, "same seed and seq, same bytes");
    }

    #[test]
    fn clipping_saturates_never_wraps() {
        let mut f = Frame::new(100, 100, PixelFormat::Mono8).unwrap();
        f.as_u8_mut().unwrap().iter_mut().enumerate().for_each(|(i, v)| *v = if i % 2 == 0 { 0 } else { 255 });
        run(&mut f, 20.0, 2);
        let d = f.as_u8().unwrap();
        // Even samples started at 0 and can only go up (or stay): a wrap would give values near 255.
        assert!(d.iter().step_by(2).all(|&v| v < 128));
        assert!(d.iter().skip(1).step_by(2).all(|&v| v > 128));
    }
}
