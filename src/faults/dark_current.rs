//! `dark_current`: thermally generated charge integrated during the exposure, with its shot
//! noise and a fixed pattern of hot pixels. The mean can be given directly or derived from
//! temperature, exposure and sensor age (EMVA 1288 doubling temperature or Arrhenius law).
//!
//! Fast Poisson sampler: the inverse CDF of Poisson(λ) is tabulated once per parameter change
//! on 4096 equiprobable buckets (65536 when more than 1/2 % of the 4096 would straddle a CDF
//! step, i.e. for large means); the low bits of a 16-bit uniform from the band's [`RngLanes`] pick
//! a bucket (see [`super::noise`], which also has the AVX2 path). When the whole bucket maps to one
//! count the table gives it directly; the few buckets that straddle a
//! step of the CDF (at most one per possible count) are resolved exactly by drawing the position
//! inside the bucket with a 53-bit uniform and searching the stored CDF. The sampler is therefore
//! exact (up to f64 rounding of the CDF), not an approximation.

use super::kit::RngLanes;
use super::noise::{NoiseTable, add_table_noise};
use super::util::ROWS_PER_TASK;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, ImageMut, Sample};
use crate::rng::{Rng, ln_gamma};
use crate::with_image_mut;
use rayon::prelude::*;

/// Boltzmann constant in eV/K.
pub const BOLTZMANN_EV_PER_K: f64 = 8.617_333_262e-5;
/// Largest resolved mean (8-bit DN): twice full scale; beyond it every pixel saturates anyway.
pub const MAX_MEAN_DN: f64 = 510.0;

pub static INFO: EffectInfo = EffectInfo {
    name: "dark_current",
    stage: Stage::Sensor,
    order: 30,
    summary: "additive dark signal with its Poisson (shot) noise and fixed hot pixels; from temperature, exposure, age",
    model: "Electrons n ~ Poisson(lambda), lambda = mean * gain_e_per_dn, per sample and per frame; \
            v' = clip(v + floor(n / gain_e_per_dn * FS/255 + 0.5)), so on a black frame mean = mean_dn and \
            variance = mean_dn / gain_e_per_dn (8-bit DN^2; plus 1/12 DN^2 quantisation when electrons do not map \
            to whole DN). mean_dn and gain_e_per_dn are in 8-bit DN (scaled by FS/255 for 16-bit). The dark \
            shot noise is signal independent but is what dominates dark regions, where photon shot noise is \
            small: this is the study's 'dark-weighted noise'. Hot pixels: a fixed fraction hot_pixel_rate of the \
            pixels (same on every frame: fixed-pattern generator; Rgb8: one colour channel each, a hot photosite of \
            the mosaic) have dark current m_i * mean with m_i = hot_factor * (0.5 + u_i), u_i ~ U(0,1) fixed, \
            i.e. they receive an extra Poisson(lambda * (m_i - 1)) electrons. Raising the rate keeps the \
            existing hot pixels and adds new ones. \
            model = direct: mean = mean_dn. model = doubling (EMVA 1288): mean = ref_rate_dn_s * \
            2^((temperature_c - ref_temp_c) / doubling_temp_c) * exposure_s * (1 + age_growth_per_year * age_years). \
            model = arrhenius: mean = ref_rate_dn_s * exp(-bandgap_ev / k * (1/T - 1/T_ref)) * exposure_s * \
            (1 + age_growth_per_year * age_years), T in kelvin, k = 8.617e-5 eV/K (I0 exp(-Eg/kT) anchored at the \
            reference point; Eg = 1.12 eV is diffusion current in Si, ~0.6 eV mid-gap generation). Sensor age: \
            radiation (displacement damage, total ionising dose) raises dark current roughly linearly with dose, \
            and in a steady orbit dose grows linearly with time; age_growth_per_year is the fractional increase \
            per year of the beginning-of-life value (default 0.25/year, an order of magnitude typical of LEO \
            CCD/CMOS data; set it from your mission's dose and the sensor's damage factor). The resolved mean is \
            clamped to 510 DN (2 FS); see dark_current::resolved_mean_dn. A resolved mean of 0 is the identity.",
    params: &[
        ParamSpec::float("mean_dn", "DN", 0.0, 255.0, 2.0, "mean dark signal in 8-bit DN (model = direct)"),
        ParamSpec::float("hot_pixel_rate", "fraction", 0.0, 0.05, 2e-4, "fraction of pixels that are hot (fixed)"),
        ParamSpec::float("gain_e_per_dn", "e-/DN", 0.01, 1000.0, 1.0, "conversion gain: electrons per 8-bit DN")
            .log()
            .extra(),
        ParamSpec::float("hot_factor", "1", 1.0, 1000.0, 30.0, "mean dark current of a hot pixel / mean").extra(),
        ParamSpec::choice(
            "model",
            &["direct", "doubling", "arrhenius"],
            0,
            false,
            "how the mean is obtained: given (direct) or from temperature, exposure and age",
        ),
        ParamSpec::float("temperature_c", "degC", -60.0, 120.0, 20.0, "sensor temperature").extra(),
        ParamSpec::float("exposure_s", "s", 0.0, 1000.0, 1.0, "exposure (integration) time").extra(),
        ParamSpec::float("ref_rate_dn_s", "DN/s", 0.0, 1000.0, 1.0, "dark rate at ref_temp_c, beginning of life")
            .extra(),
        ParamSpec::float("ref_temp_c", "degC", -60.0, 120.0, 20.0, "temperature of ref_rate_dn_s").extra(),
        ParamSpec::float("doubling_temp_c", "degC", 1.0, 30.0, 6.5, "dark current doubles every this many K").extra(),
        ParamSpec::float("bandgap_ev", "eV", 0.3, 1.5, 1.12, "activation energy of the Arrhenius model").extra(),
        ParamSpec::float("age_years", "years", 0.0, 30.0, 0.0, "time in orbit (radiation dose)").extra(),
        ParamSpec::float("age_growth_per_year", "1/year", 0.0, 10.0, 0.25, "fractional dark-current growth per year")
            .extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(DarkCurrent::default())
}

/// Mean dark signal in 8-bit DN from the parameters (the value the effect applies).
pub fn resolved_mean_dn(p: &Params) -> f64 {
    let age = 1.0 + p.get("age_growth_per_year") * p.get("age_years");
    let base = p.get("ref_rate_dn_s") * p.get("exposure_s") * age;
    let t = p.get("temperature_c");
    let t_ref = p.get("ref_temp_c");
    let mean = match p.choice("model") {
        "doubling" => base * doubling_factor(t, t_ref, p.get("doubling_temp_c")),
        "arrhenius" => base * arrhenius_factor(t, t_ref, p.get("bandgap_ev")),
        _ => p.get("mean_dn"),
    };
    if mean.is_finite() { mean.clamp(0.0, MAX_MEAN_DN) } else { MAX_MEAN_DN }
}

/// EMVA 1288 temperature factor: 2^((T - T_ref) / T_d).
pub fn doubling_factor(t_c: f64, t_ref_c: f64, t_double: f64) -> f64 {
    ((t_c - t_ref_c) / t_double).exp2()
}

/// Arrhenius temperature factor exp(-Eg/k (1/T - 1/T_ref)), temperatures in degC.
pub fn arrhenius_factor(t_c: f64, t_ref_c: f64, eg_ev: f64) -> f64 {
    let (t, t_ref) = (t_c + 273.15, t_ref_c + 273.15);
    (-eg_ev / BOLTZMANN_EV_PER_K * (1.0 / t - 1.0 / t_ref)).exp()
}

/// Marker for a bucket that straddles a CDF step (the noise kernel's "resolve" marker).
const AMBIGUOUS: i32 = super::noise::RESOLVE;
/// Bucket index bits: 12 (a 16 KB table that stays in L1) when at most 1/2 % of the buckets
/// straddle a CDF step, else 16 (finer buckets, fewer exact resolutions).
const SMALL_BITS: u32 = 12;
const LARGE_BITS: u32 = 16;

/// DN offset of `k` electrons.
#[inline]
fn offset(k: u64, dn_per_e: f64) -> i32 {
    (k as f64 * dn_per_e + 0.5).floor().min(1e9) as i32
}

/// Exact Poisson sampler for one mean, producing quantised DN offsets.
#[derive(Default)]
pub struct PoissonTable {
    key: Option<(u64, u64)>,
    /// CDF of Poisson(lambda) for k = 0..=kmax (last entry exactly 1).
    // allocation: once per parameter change
    cdf: Vec<f64>,
    /// Per bucket: the DN offset, or AMBIGUOUS.
    quant: NoiseTable,
    /// Per bucket: the first k with cdf[k] > the bucket's lower edge (where `resolve` starts).
    // allocation: once per parameter change
    start: Vec<u32>,
    /// `offset(k)` for k = 0..=kmax (what `resolve` returns; no float rounding per call).
    // allocation: once per parameter change
    offsets: Vec<i32>,
    dn_per_e: f64,
    /// Index bits of the buckets (quant.len() = 1 << bits).
    bits: u32,
}

impl PoissonTable {
    /// (Re)build for mean `lambda` electrons and `dn_per_e` output DN per electron.
    pub fn prepare(&mut self, lambda: f64, dn_per_e: f64) {
        let key = (lambda.to_bits(), dn_per_e.to_bits());
        if self.key == Some(key) {
            return;
        }
        self.key = Some(key);
        self.dn_per_e = dn_per_e;
        let kmax = (lambda + 14.0 * lambda.sqrt() + 30.0).ceil() as usize;
        self.cdf.clear();
        let ll = lambda.ln();
        let mut acc = 0.0;
        for k in 0..=kmax {
            acc += (-lambda + k as f64 * ll - ln_gamma(k as f64 + 1.0)).exp();
            self.cdf.push(acc);
        }
        let total = acc;
        self.cdf.iter_mut().for_each(|c| *c /= total);
        if let Some(last) = self.cdf.last_mut() {
            *last = 1.0;
        }
        self.offsets.clear();
        self.offsets.extend((0..self.cdf.len()).map(|k| offset(k as u64, dn_per_e)));
        self.fill_buckets(SMALL_BITS);
        if self.ambiguous_buckets() * 200 > self.quant.entries().len() {
            self.fill_buckets(LARGE_BITS);
        }
    }

    fn fill_buckets(&mut self, bits: u32) {
        let buckets = 1usize << bits;
        self.bits = bits;
        self.start.clear();
        let (cdf, start, dn_per_e) = (&self.cdf, &mut self.start, self.dn_per_e);
        let mut k = 0usize;
        let entries = (0..buckets).map(|u| {
            let a = u as f64 / buckets as f64;
            let b = (u + 1) as f64 / buckets as f64;
            while cdf[k] <= a {
                k += 1;
            }
            start.push(k as u32);
            if cdf[k] >= b { offset(k as u64, dn_per_e) } else { AMBIGUOUS }
        });
        self.quant.rebuild(bits, entries);
    }

    /// Index bits of the bucket table.
    pub fn bits(&self) -> u32 {
        self.bits
    }

    /// The bucket table as the noise kernel uses it.
    pub fn noise_table(&self) -> &NoiseTable {
        &self.quant
    }

    #[cfg(test)]
    fn offset(&self, k: u64) -> i32 {
        offset(k, self.dn_per_e)
    }

    /// Exact count for a straddling bucket `u`.
    #[cold]
    fn resolve(&self, u: usize, rng: &mut Rng) -> i32 {
        // The bucket count is a power of two: multiplying by its reciprocal is exact (the same
        // value as dividing).
        let x = (u as f64 + rng.uniform()) * (1.0 / self.quant.entries().len() as f64);
        // The first k with cdf[k] > x: every k below the bucket's start has cdf[k] <= its lower
        // edge <= x, so the search starts there (the same k as a search of the whole CDF).
        let mut k = self.start[u] as usize;
        while k + 1 < self.cdf.len() && self.cdf[k] <= x {
            k += 1;
        }
        self.offsets[k]
    }

    /// One quantised sample (DN offset) from a 16-bit uniform and the generator.
    #[inline(always)]
    pub fn sample(&self, u16_uniform: usize, rng: &mut Rng) -> i32 {
        let u = u16_uniform & (self.quant.entries().len() - 1);
        let q = self.quant.entries()[u];
        if q == AMBIGUOUS { self.resolve(u, rng) } else { q }
    }

    /// Number of straddling buckets (diagnostics and tests).
    pub fn ambiguous_buckets(&self) -> usize {
        self.quant.entries().iter().filter(|&&q| q == AMBIGUOUS).count()
    }
}

/// One hot pixel: row, sample index in the row, multiplier draw u in [0, 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HotPixel {
    pub y: u32,
    pub sample: u32,
    pub u: f32,
}

/// Hot pixels of a stream: the first `round(rate * w * h)` of a fixed sequence drawn from the
/// fixed-pattern generator (sorted by position, duplicates removed).
pub fn hot_pixels(pattern_seed: u64, w: usize, h: usize, ch: usize, rate: f64, out: &mut Vec<HotPixel>) {
    out.clear();
    let n = (rate * (w * h) as f64).round() as usize;
    let mut r = Rng::new(pattern_seed);
    for _ in 0..n {
        let idx = r.below((w * h) as u64) as usize;
        let c = r.below(ch as u64) as usize;
        let u = r.uniform_f32();
        out.push(HotPixel { y: (idx / w) as u32, sample: ((idx % w) * ch + c) as u32, u });
    }
    out.sort_by_key(|p| (p.y, p.sample));
    out.dedup_by_key(|p| (p.y, p.sample));
}

/// The effect: cached sampler table and hot-pixel list.
#[derive(Default)]
pub struct DarkCurrent {
    table: PoissonTable,
    hot_key: Option<(u64, usize, usize, usize, u64)>,
    // allocation: once per stream / rate change
    hot: Vec<HotPixel>,
    /// Per hot pixel, this frame's extra DN (drawn serially, added band by band).
    // allocation: once per stream / rate change
    hot_dn: Vec<i32>,
    last_mean_dn: f64,
}

impl DarkCurrent {
    /// The mean (8-bit DN) used for the last frame.
    pub fn last_mean_dn(&self) -> f64 {
        self.last_mean_dn
    }
}

impl Effect for DarkCurrent {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let mean = resolved_mean_dn(p);
        self.last_mean_dn = mean;
        if mean <= 0.0 {
            return Ok(Outcome::Keep);
        }
        let gain = p.get("gain_e_per_dn");
        let lambda = mean * gain;
        let dn_per_e = frame.format.dn_scale() as f64 / gain;
        self.table.prepare(lambda, dn_per_e);
        let (w, h, ch) = (frame.width as usize, frame.height as usize, frame.channels());
        let rate = p.get("hot_pixel_rate");
        let key = (ctx.pattern_seed, w, h, ch, rate.to_bits());
        if self.hot_key != Some(key) {
            hot_pixels(ctx.pattern_seed, w, h, ch, rate, &mut self.hot);
            self.hot_key = Some(key);
        }
        let hot_factor = p.get("hot_factor");
        // Hot pixels: extra Poisson(lambda * (m - 1)) electrons, drawn serially from their own
        // stream, added after the row's dark noise (in the band that holds the row, while it is
        // in cache).
        let mut r = ctx.rng.derive(u64::MAX);
        self.hot_dn.clear();
        self.hot_dn.extend(self.hot.iter().map(|hp| {
            let m = hot_factor * (0.5 + hp.u as f64);
            let extra = r.poisson(lambda * (m - 1.0).max(0.0));
            (extra as f64 * dn_per_e + 0.5).floor().min(1e9) as i32
        }));
        let table = &self.table;
        let hot = (&self.hot[..], &self.hot_dn[..]);
        let rng = &ctx.rng;
        with_image_mut!(frame, img => add_dark(&mut img, table, rng, hot));
        Ok(Outcome::Keep)
    }
}

/// Dark noise on every sample, then the hot pixels' extra DN (`hot`: the sorted hot pixels and
/// their drawn offsets).
fn add_dark<T: Sample>(img: &mut ImageMut<'_, T>, table: &PoissonTable, rng: &Rng, hot: (&[HotPixel], &[i32])) {
    let (stride, row_len, h) = (img.stride, img.row_len(), img.height);
    let used = stride * (h - 1) + row_len;
    let max = T::MAX_U32 as i32;
    img.data[..used].par_chunks_mut(stride * ROWS_PER_TASK).enumerate().for_each(|(band, chunk)| {
        // Band k: bucket indices from derive(k).derive(0) (see faults::noise), straddling
        // buckets resolved exactly from derive(k).derive(1).
        let base = rng.derive(band as u64);
        let mut lanes = RngLanes::new(&base.derive(0));
        let mut exact = base.derive(1);
        let y0 = band * ROWS_PER_TASK;
        // The band's hot pixels (sorted by row).
        let (lo, hi) = (
            hot.0.partition_point(|p| (p.y as usize) < y0),
            hot.0.partition_point(|p| (p.y as usize) < y0 + ROWS_PER_TASK),
        );
        let mut hot_band = hot.0[lo..hi].iter().zip(&hot.1[lo..hi]).peekable();
        for (dy, row) in chunk.chunks_mut(stride).enumerate() {
            let row = &mut row[..row_len];
            add_table_noise(row, &mut lanes, &table.quant, &mut |u| table.resolve(u, &mut exact));
            while let Some((hp, &n)) = hot_band.next_if(|(hp, _)| hp.y as usize == y0 + dy) {
                let v = &mut row[hp.sample as usize];
                *v = T::from_u32_sat((v.to_u32() as i32).saturating_add(n).clamp(0, max) as u32);
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn params(kv: &[(&str, f64)]) -> Params {
        let mut p = Params::defaults(&INFO);
        p.set("hot_pixel_rate", 0.0).unwrap();
        for (k, v) in kv {
            p.set(k, *v).unwrap();
        }
        p
    }

    fn moments(xs: impl Iterator<Item = f64>) -> (f64, f64, f64) {
        let v: Vec<f64> = xs.collect();
        let n = v.len() as f64;
        let m = v.iter().sum::<f64>() / n;
        (m, v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0), n)
    }

    fn black(fmt: PixelFormat, w: u32, h: u32, seq: u64) -> Frame {
        let mut f = Frame::new(w, h, fmt).unwrap();
        f.seq = seq;
        f
    }

    fn run(f: &mut Frame, p: &Params) -> DarkCurrent {
        let mut e = DarkCurrent::default();
        e.apply(f, p, &mut EffectCtx::new(7, f.seq, 2)).unwrap();
        e
    }

    #[test]
    fn sampler_is_poisson_for_small_and_large_means() {
        for &lam in &[0.05, 0.7, 4.0, 37.5, 900.0, 20000.0] {
            let mut t = PoissonTable::default();
            t.prepare(lam, 1.0);
            // At most one straddling bucket per count value in the bulk.
            assert!(t.ambiguous_buckets() <= t.cdf.len(), "lambda {lam}");
            // Small means use the small table, the largest the fine one.
            assert_eq!(
                t.bits(),
                if lam < 10.0 {
                    12
                } else if lam > 1000.0 {
                    16
                } else {
                    t.bits()
                },
                "lambda {lam}"
            );
            let mut r = Rng::new(lam.to_bits());
            let n = 200_000;
            let xs: Vec<f64> = (0..n).map(|_| t.sample(r.below(1 << 16) as usize, &mut r) as f64).collect();
            let (m, v, nf) = moments(xs.iter().copied());
            // 5-sigma: SE(mean) = sqrt(lam/n), SE(var) = sqrt((2 lam^2 + lam)/n).
            assert!((m - lam).abs() < 5.0 * (lam / nf).sqrt(), "lambda {lam}: mean {m}");
            assert!((v - lam).abs() < 5.0 * ((2.0 * lam * lam + lam) / nf).sqrt(), "lambda {lam}: var {v}");
            // P(0) = exp(-lambda): binomial 5-sigma bound.
            let p0 = (-lam).exp();
            let f0 = xs.iter().filter(|&&x| x == 0.0).count() as f64 / nf;
            assert!((f0 - p0).abs() <= 5.0 * (p0 * (1.0 - p0) / nf).sqrt() + 1e-12, "lambda {lam}: P0 {f0} vs {p0}");
        }
    }

    #[test]
    fn resolving_from_the_bucket_start_equals_a_full_cdf_search() {
        for (lambda, dn_per_e) in [(0.3, 1.0), (30.0, 0.1), (400.0, 0.25), (5000.0, 0.02)] {
            let mut t = PoissonTable::default();
            t.prepare(lambda, dn_per_e);
            let (mut r1, mut r2) = (Rng::new(11), Rng::new(11));
            let mut checked = 0;
            for u in 0..t.quant.entries().len() {
                if t.quant.entries()[u] != AMBIGUOUS {
                    continue;
                }
                for _ in 0..20 {
                    let got = t.resolve(u, &mut r1);
                    let x = (u as f64 + r2.uniform()) / t.quant.entries().len() as f64;
                    let want = t.offset(t.cdf.partition_point(|&c| c <= x) as u64);
                    assert_eq!(got, want, "lambda {lambda}, bucket {u}");
                    checked += 1;
                }
            }
            assert!(checked > 0, "lambda {lambda}: some buckets straddle a CDF step");
        }
    }

    #[test]
    fn black_frame_mean_and_variance_match_parameters() {
        // Mono8, gain 1 e-/DN: every electron is one DN, no quantisation.
        let mut f = black(PixelFormat::Mono8, 256, 200, 0);
        run(&mut f, &params(&[("mean_dn", 6.0), ("gain_e_per_dn", 1.0)]));
        let (m, v, n) = moments(f.as_u8().unwrap().iter().map(|&x| x as f64));
        assert!((m - 6.0).abs() < 5.0 * (6.0 / n).sqrt(), "mean {m}");
        assert!((v - 6.0).abs() < 5.0 * ((2.0 * 36.0 + 6.0) / n).sqrt(), "var {v}");

        // Mono16, gain 4 e-/DN8: variance mean/gain in DN8^2 = (mean/gain)*257^2 DN16^2.
        let mut f = black(PixelFormat::Mono16, 200, 150, 0);
        run(&mut f, &params(&[("mean_dn", 3.0), ("gain_e_per_dn", 4.0)]));
        let (m, v, n) = moments(f.as_u16().unwrap().iter().map(|&x| x as f64 / 257.0));
        let lam = 12.0;
        let want_var = 3.0 / 4.0;
        assert!((m - 3.0).abs() < 5.0 * (want_var / n).sqrt() + 0.5 / 257.0, "mean {m}");
        // SE of the variance in DN8^2: sqrt((2 lam^2 + lam)/n) / gain^2.
        let se_v = ((2.0 * lam * lam + lam) / n).sqrt() / 16.0;
        assert!((v - want_var).abs() < 5.0 * se_v + 1.0 / 12.0 / 257.0 / 257.0, "var {v}");

        // Rgb8: every channel independently.
        let mut f = black(PixelFormat::Rgb8, 128, 96, 0);
        run(&mut f, &params(&[("mean_dn", 4.0), ("gain_e_per_dn", 1.0)]));
        for c in 0..3 {
            let (m, v, n) = moments(f.as_u8().unwrap().iter().skip(c).step_by(3).map(|&x| x as f64));
            assert!((m - 4.0).abs() < 5.0 * (4.0 / n).sqrt() && (v - 4.0).abs() < 5.0 * (36.0 / n).sqrt());
        }
    }

    #[test]
    fn mean_doubles_per_doubling_temperature_step() {
        let base = [("model", 1.0), ("ref_rate_dn_s", 0.5), ("exposure_s", 2.0), ("doubling_temp_c", 7.0)];
        let at = |t: f64| {
            let mut kv = base.to_vec();
            kv.push(("temperature_c", t));
            params(&kv)
        };
        for t in [-10.0, 13.0, 20.0, 41.5] {
            let r = resolved_mean_dn(&at(t + 7.0)) / resolved_mean_dn(&at(t));
            assert!((r - 2.0).abs() < 1e-12, "T {t}: ratio {r}");
        }
        assert!((resolved_mean_dn(&at(20.0)) - 1.0).abs() < 1e-12, "reference point: 0.5 DN/s x 2 s");
        // Measured on images: mean at 34 degC is 4x the mean at 20 degC.
        let measure = |t: f64| {
            let mut f = black(PixelFormat::Mono8, 200, 200, 0);
            run(&mut f, &at(t));
            moments(f.as_u8().unwrap().iter().map(|&x| x as f64)).0
        };
        let (m1, m2) = (measure(20.0), measure(34.0));
        let n = 40_000.0f64;
        assert!((m1 - 1.0).abs() < 5.0 * (1.0 / n).sqrt(), "m1 {m1}");
        assert!((m2 - 4.0).abs() < 5.0 * (4.0 / n).sqrt(), "m2 {m2}");
    }

    #[test]
    fn arrhenius_ratio_matches_activation_energy() {
        let at = |t: f64, eg: f64| params(&[("model", 2.0), ("temperature_c", t), ("bandgap_ev", eg)]);
        for eg in [0.6, 1.12] {
            let (t1, t2) = (10.0f64, 35.0f64);
            let got = resolved_mean_dn(&at(t2, eg)) / resolved_mean_dn(&at(t1, eg));
            let want = (-eg / 8.617_333_262e-5 * (1.0 / (t2 + 273.15) - 1.0 / (t1 + 273.15))).exp();
            assert!((got / want - 1.0).abs() < 1e-12, "Eg {eg}: {got} vs {want}");
        }
        // Si (1.12 eV) near room temperature doubles every ~5 K; mid-gap (0.6 eV) every ~9 K.
        let doubling =
            |eg: f64| 20.0 * 2f64.ln() / (resolved_mean_dn(&at(40.0, eg)) / resolved_mean_dn(&at(20.0, eg))).ln();
        assert!((4.0..6.5).contains(&doubling(1.12)), "{}", doubling(1.12));
        assert!((8.0..11.0).contains(&doubling(0.6)), "{}", doubling(0.6));
    }

    #[test]
    fn dark_current_rises_with_age() {
        let at = |age: f64| params(&[("model", 1.0), ("age_years", age), ("ref_rate_dn_s", 2.0)]);
        let m: Vec<f64> = [0.0, 1.0, 4.0, 10.0].iter().map(|&a| resolved_mean_dn(&at(a))).collect();
        assert!(m.windows(2).all(|w| w[1] > w[0]), "{m:?}");
        assert!((m[2] - 2.0 * (1.0 + 0.25 * 4.0)).abs() < 1e-12);
        let mut young = black(PixelFormat::Mono8, 160, 120, 0);
        let mut old = young.clone();
        run(&mut young, &at(0.0));
        run(&mut old, &at(8.0));
        let my = moments(young.as_u8().unwrap().iter().map(|&x| x as f64)).0;
        let mo = moments(old.as_u8().unwrap().iter().map(|&x| x as f64)).0;
        // 2 DN vs 6 DN; SE < 0.013 DN.
        assert!((my - 2.0).abs() < 0.07 && (mo - 6.0).abs() < 0.12, "young {my} old {mo}");
    }

    #[test]
    fn hot_pixels_are_a_fixed_pattern() {
        let p = params(&[("mean_dn", 1.0), ("hot_pixel_rate", 0.002), ("hot_factor", 100.0)]);
        let mut a = black(PixelFormat::Mono8, 200, 150, 1);
        let mut b = black(PixelFormat::Mono8, 200, 150, 2);
        run(&mut a, &p);
        run(&mut b, &p);
        assert_ne!(a, b, "shot noise differs between frames");
        // Ordinary pixels: Poisson(1) exceeds 25 with probability ~1e-26; hot pixels have >= 50 e-.
        let hot = |f: &Frame| -> Vec<usize> {
            f.as_u8().unwrap().iter().enumerate().filter(|(_, v)| **v > 25).map(|(i, _)| i).collect()
        };
        let (ha, hb) = (hot(&a), hot(&b));
        assert_eq!(ha, hb, "hot pixels identical on frames with different seq");
        assert!((50..=60).contains(&ha.len()), "round(0.002 * 30000) = 60 minus duplicates: {}", ha.len());
        // Raising the rate keeps the existing hot pixels.
        let mut c = black(PixelFormat::Mono8, 200, 150, 1);
        run(&mut c, &params(&[("mean_dn", 1.0), ("hot_pixel_rate", 0.004), ("hot_factor", 100.0)]));
        let hc = hot(&c);
        assert!(ha.iter().all(|i| hc.contains(i)) && hc.len() > ha.len());
    }

    #[test]
    fn zero_mean_is_identity_and_resolved_mean_is_recorded() {
        let mut f = black(PixelFormat::Rgb8, 40, 30, 0);
        f.as_u8_mut().unwrap().iter_mut().enumerate().for_each(|(i, v)| *v = (i % 251) as u8);
        let orig = f.clone();
        let e = run(&mut f, &params(&[("mean_dn", 0.0), ("hot_pixel_rate", 0.01)]));
        assert_eq!(f, orig);
        assert_eq!(e.last_mean_dn(), 0.0);
        let e = run(&mut f, &params(&[("model", 1.0), ("temperature_c", 33.0)]));
        assert!((e.last_mean_dn() - 4.0).abs() < 1e-12, "two doublings of 1 DN/s x 1 s");
    }
}
