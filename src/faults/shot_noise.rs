//! `shot_noise`: photon (Poisson) noise of the collected charge.
//!
//! 8-bit frames use exact table sampling: for each of the 256 input values the distribution of
//! the output DN (Poisson electrons → DN, rounded, clipped) is computed once per gain and stored
//! as a Walker/Vose alias table over the 256 output values, with 16-bit thresholds (probability
//! resolution 2^-24). One 32-bit uniform from [`RngLanes`] draws one sample: 8 bits pick the
//! cell, 16 bits decide between the cell and its alias. 16-bit frames draw each sample with
//! [`Rng::poisson`] (exact, slower).

use super::kit::{RngLanes, band_rows, bands, par_bands, par_bands_with};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, FrameData};
use crate::rng::ln_gamma;

pub static INFO: EffectInfo = EffectInfo {
    name: "shot_noise",
    stage: Stage::Sensor,
    order: 20,
    summary: "photon shot noise: Poisson statistics of the collected electrons",
    model: "electrons k ~ Poisson(v * gain_e_per_dn) with v the signal in 8-bit DN (v16/257 for 16-bit), \
            back to DN: v' = round(k / gain_e_per_dn) (exact ties split evenly, so no rounding bias) (16-bit: k * 257 / gain), clipped to [0, FS]. The \
            variance in 8-bit DN^2 is mean / gain_e_per_dn (plus 1/12 of rounding when one electron is \
            less than a DN). Independent per sample and frame; rows are processed in bands of 64 with the \
            frame generator's child derive(band), so the output does not depend on the thread count. \
            Identity in the limit of infinite gain; at the upper bound (1e6 e-/DN) 8-bit output equals the \
            input. 8-bit sampling is exact through per-value alias tables (probability resolution 2^-24).",
    params: &[ParamSpec::float(
        "gain_e_per_dn",
        "e-/DN",
        0.01,
        1e6,
        4.0,
        "conversion gain: electrons per 8-bit DN (full well / 255); small = noisy",
    )
    .log()],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(ShotNoise::default())
}

#[derive(Default)]
pub struct ShotNoise {
    key: Option<u64>,
    // allocation: once per gain: 256 alias tables of 256 cells, (threshold << 8) | alias
    table: Vec<u32>,
    // allocation: once per frame size: per band one row of random words
    rand: Vec<u32>,
}

/// Standard normal CDF (erfc with |relative error| < 1.2e-7, Numerical Recipes `erfcc`).
pub fn normal_cdf(z: f64) -> f64 {
    let x = -z / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.5 * x.abs());
    let y = t
        * (-x * x - 1.265_512_23
            + t * (1.000_023_68
                + t * (0.374_091_96
                    + t * (0.096_784_18
                        + t * (-0.186_288_06
                            + t * (0.278_868_07
                                + t * (-1.135_203_98
                                    + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77)))))))))
            .exp();
    let erfc = if x >= 0.0 { y } else { 2.0 - y };
    0.5 * erfc
}

/// Probabilities of the output DN 0..=255 for input `v` (8-bit DN) and gain `g` (e-/DN).
pub fn output_distribution(v: u32, g: f64) -> [f64; 256] {
    let mut p = [0.0f64; 256];
    let lam = v as f64 * g;
    if lam <= 0.0 {
        p[0] = 1.0;
        return p;
    }
    let sd = lam.sqrt();
    // Rounding k/g to the nearest DN; an exact tie (k/g + 1/2 integral, e.g. odd k at gain 2)
    // is split evenly between the two neighbours so the conversion has no bias.
    let add = |p: &mut [f64; 256], k: f64, pk: f64| {
        let x = k / g + 0.5;
        let d = x.floor();
        if x == d && d >= 1.0 {
            p[(d as usize).min(255)] += 0.5 * pk;
            p[(d as usize - 1).min(255)] += 0.5 * pk;
        } else {
            p[(d.clamp(0.0, 255.0)) as usize] += pk;
        }
    };
    if lam <= 1e4 {
        // Exact: sum the pmf outwards from the mode until it is negligible.
        let mode = lam.floor();
        let lp0 = mode * lam.ln() - lam - ln_gamma(mode + 1.0);
        let p0 = lp0.exp();
        let kmax = lam + 12.0 * sd + 20.0;
        let mut pk = p0;
        let mut k = mode;
        while k <= kmax {
            add(&mut p, k, pk);
            k += 1.0;
            pk *= lam / k;
        }
        let mut pk = p0;
        let mut k = mode;
        while k >= 1.0 {
            pk *= k / lam;
            k -= 1.0;
            add(&mut p, k, pk);
            if pk < 1e-30 && k < lam - 12.0 * sd {
                break;
            }
        }
    } else {
        // lam > 1e4: Edgeworth-corrected normal for the CDF, error O(1/lam) < 1e-4 * pdf.
        let cdf = |k: f64| {
            // P(K <= k) for integer k.
            let z = (k + 0.5 - lam) / sd;
            let phi = (-0.5 * z * z).exp() / (2.0 * std::f64::consts::PI).sqrt();
            (normal_cdf(z) - phi * (z * z - 1.0) / (6.0 * sd)).clamp(0.0, 1.0)
        };
        // Bin d holds the integers k in [g(d - 1/2), g(d + 1/2)).
        let lo_d = ((lam - 12.0 * sd) / g - 1.0).floor().max(0.0) as usize;
        let hi_d = (((lam + 12.0 * sd) / g + 1.0).ceil() as usize).min(255);
        let mut prev = 0.0;
        for (d, pd) in p.iter_mut().enumerate().take(hi_d + 1).skip(lo_d) {
            let upper = if d == 255 { 1.0 } else { cdf((g * (d as f64 + 0.5)).ceil() - 1.0) };
            *pd = (upper - prev).max(0.0);
            prev = upper;
        }
        if hi_d < 255 {
            p[hi_d] += 1.0 - prev;
        }
    }
    let s: f64 = p.iter().sum();
    p.iter_mut().for_each(|x| *x /= s);
    p
}

/// Vose alias table over 256 cells: entry = (threshold << 8) | alias, threshold in [0, 65536].
fn alias_table(p: &[f64; 256], out: &mut [u32]) {
    let mut scaled: [f64; 256] = [0.0; 256];
    let (mut small, mut large): (Vec<usize>, Vec<usize>) = (Vec::with_capacity(256), Vec::with_capacity(256));
    for i in 0..256 {
        scaled[i] = p[i] * 256.0;
        if scaled[i] < 1.0 { small.push(i) } else { large.push(i) }
    }
    let mut alias = [0usize; 256];
    let mut prob = [1.0f64; 256];
    for (i, a) in alias.iter_mut().enumerate() {
        *a = i;
    }
    while let (Some(&s), Some(&l)) = (small.last(), large.last()) {
        small.pop();
        prob[s] = scaled[s];
        alias[s] = l;
        scaled[l] = scaled[l] + scaled[s] - 1.0;
        if scaled[l] < 1.0 {
            large.pop();
            small.push(l);
        }
    }
    // Leftovers (numerical residue) keep probability 1 of their own cell.
    for i in 0..256 {
        let thr = (prob[i] * 65536.0).round().clamp(0.0, 65536.0) as u32;
        out[i] = (thr << 8) | alias[i] as u32;
    }
}

/// Draw one output value from the alias table of one input value.
#[inline(always)]
fn draw(table: &[u32; 256], r: u32) -> u8 {
    let cell = (r & 0xff) as usize;
    let e = table[cell];
    if (r >> 8) & 0xffff < e >> 8 { cell as u8 } else { (e & 0xff) as u8 }
}

/// Draw a row of 8-bit samples: sample i uses the i-th u32 of `RngLanes::fill_u32` for the row
/// (`rand` is scratch of the row's length). Scalar reference.
fn draw_row_scalar(row: &mut [u8], lanes: &mut RngLanes, table: &[u32], rand: &mut [u32]) {
    let rand = &mut rand[..row.len()];
    lanes.fill_u32(rand);
    for (v, &r) in row.iter_mut().zip(rand.iter()) {
        let base = *v as usize * 256;
        let Ok(t) = <&[u32; 256]>::try_from(&table[base..base + 256]) else { return };
        *v = draw(t, r);
    }
}

/// The fastest row drawer this CPU runs (the same bytes as the reference).
fn draw_row_fn() -> fn(&mut [u8], &mut RngLanes, &[u32], &mut [u32]) {
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx512() {
        // SAFETY: the CPU supports AVX-512 F/BW/VL (checked just above).
        return |row, lanes, table, rand| unsafe { simd::draw_row_avx512(row, lanes, table, rand) };
    }
    #[cfg(target_arch = "x86_64")]
    if crate::faults::kit::has_avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return |row, lanes, table, rand| unsafe { simd::draw_row(row, lanes, table, rand) };
    }
    draw_row_scalar
}

#[cfg(target_arch = "x86_64")]
/// The AVX2 and AVX-512 row drawers (the same bytes as `draw_row_scalar`).
mod simd {
    use super::RngLanes;
    use crate::faults::noise::avx2::{load_state, lookup8, next4, store_state};
    use std::arch::x86_64::*;

    /// AVX2 version of `draw_row_scalar`: eight samples per `next4` (the u32 order of
    /// `fill_u32`), alias entries by scalar loads (no gathers: slow on many AMD cores),
    /// threshold compared in lanes.
    #[target_feature(enable = "avx2")]
    pub unsafe fn draw_row(row: &mut [u8], lanes: &mut RngLanes, table: &[u32], rand: &mut [u32]) {
        if table.len() != 256 * 256 {
            return;
        }
        // SAFETY: u32 and i32 have the same size and alignment; the same memory, read only.
        let table32 = unsafe { std::slice::from_raw_parts(table.as_ptr() as *const i32, table.len()) };
        let n8 = row.len() / 8 * 8;
        let (m8, m16) = (_mm256_set1_epi32(0xff), _mm256_set1_epi32(0xffff));
        let mut s = load_state(lanes);
        let draw8 = |chunk: &mut [u8], r: __m256i| {
            // SAFETY: chunk holds 8 bytes; every index v*256 + cell < 65536 = table.len().
            unsafe {
                let v = _mm256_cvtepu8_epi32(_mm_loadl_epi64(chunk.as_ptr() as *const __m128i));
                let cell = _mm256_and_si256(r, m8);
                let idx = _mm256_add_epi32(_mm256_slli_epi32(v, 8), cell);
                let e = lookup8(table32, idx);
                // Own cell when (r >> 8) & 0xffff < threshold (e >> 8, <= 65536): a signed compare
                // is exact for these non-negative values.
                let own = _mm256_cmpgt_epi32(_mm256_srli_epi32(e, 8), _mm256_and_si256(_mm256_srli_epi32(r, 8), m16));
                let out = _mm256_blendv_epi8(_mm256_and_si256(e, m8), cell, own);
                let p16 = _mm256_packus_epi32(out, out);
                let p8 = _mm256_packus_epi16(p16, p16);
                let lo = _mm256_extract_epi32(p8, 0) as u32 as u64;
                let hi = _mm256_extract_epi32(p8, 4) as u32 as u64;
                chunk.copy_from_slice(&(lo | hi << 32).to_le_bytes());
            }
        };
        // Sixteen samples per iteration: two independent gathers in flight.
        let mut pairs = row[..n8].chunks_exact_mut(16);
        for pair in &mut pairs {
            let (r0, r1) = (next4(&mut s), next4(&mut s));
            let (a, b) = pair.split_at_mut(8);
            draw8(a, r0);
            draw8(b, r1);
        }
        for chunk in pairs.into_remainder().chunks_exact_mut(8) {
            draw8(chunk, next4(&mut s));
        }
        store_state(lanes, &s);
        if n8 < row.len() {
            super::draw_row_scalar(&mut row[n8..], lanes, table, rand);
        }
    }

    /// [`draw_row`] with AVX-512: sixteen samples per gather, the threshold test into a mask
    /// and the bytes packed by `vpmovdb` (the same bytes).
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
    pub unsafe fn draw_row_avx512(row: &mut [u8], lanes: &mut RngLanes, table: &[u32], rand: &mut [u32]) {
        if table.len() != 256 * 256 {
            return;
        }
        let n16 = row.len() / 16 * 16;
        let (m8, m16) = (_mm512_set1_epi32(0xff), _mm512_set1_epi32(0xffff));
        let mut s = load_state(lanes);
        for i in (0..n16).step_by(16) {
            // Samples i .. i + 8 from the first step, i + 8 .. i + 16 from the second (the u32
            // order of `fill_u32`).
            let r = _mm512_inserti64x4::<1>(_mm512_castsi256_si512(next4(&mut s)), next4(&mut s));
            // SAFETY: 16 bytes at i are inside the row; every index v*256 + cell < 65536 =
            // table.len().
            unsafe {
                let p = row.as_mut_ptr().add(i);
                let v = _mm512_cvtepu8_epi32(_mm_loadu_si128(p as *const __m128i));
                let cell = _mm512_and_si512(r, m8);
                let idx = _mm512_add_epi32(_mm512_slli_epi32::<8>(v), cell);
                let e = _mm512_i32gather_epi32::<4>(idx, table.as_ptr() as *const i32);
                // Own cell when (r >> 8) & 0xffff < threshold (e >> 8, <= 65536).
                let own = _mm512_cmpgt_epi32_mask(
                    _mm512_srli_epi32::<8>(e),
                    _mm512_and_si512(_mm512_srli_epi32::<8>(r), m16),
                );
                let out = _mm512_mask_blend_epi32(own, _mm512_and_si512(e, m8), cell);
                _mm_storeu_si128(p as *mut __m128i, _mm512_cvtepi32_epi8(out));
            }
        }
        store_state(lanes, &s);
        if n16 < row.len() {
            super::draw_row_scalar(&mut row[n16..], lanes, table, rand);
        }
    }
}

impl ShotNoise {
    fn ensure_table(&mut self, g: f64) {
        if self.key == Some(g.to_bits()) {
            return;
        }
        self.table.resize(256 * 256, 0);
        for v in 0..256u32 {
            let p = output_distribution(v, g);
            alias_table(&p, &mut self.table[v as usize * 256..(v as usize + 1) * 256]);
        }
        self.key = Some(g.to_bits());
    }
}

impl Effect for ShotNoise {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO.accepts(frame.format) {
            return Err(super::unsupported(&INFO, frame.format));
        }
        let g = p.get("gain_e_per_dn");
        let (stride, h, rl) = (frame.stride, frame.height as usize, frame.row_len());
        let rng = &ctx.rng;
        match &mut frame.data {
            FrameData::U8(d) => {
                self.ensure_table(g);
                self.rand.resize(rl * bands(h), 0);
                let table = &self.table;
                let draw_row = draw_row_fn();
                par_bands_with(d, stride, h, &mut self.rand, rl, |k, _, band, rand| {
                    let mut lanes = RngLanes::new(&rng.derive(k as u64));
                    for row in band_rows(band, stride, rl) {
                        draw_row(row, &mut lanes, table, rand);
                    }
                });
            }
            FrameData::U16(d) => {
                let to_e = g / 257.0;
                let to_dn = 257.0 / g;
                par_bands(d, stride, h, |k, _, band| {
                    let mut r = rng.derive(k as u64);
                    for row in band_rows(band, stride, rl) {
                        for v in row.iter_mut() {
                            let e = r.poisson(*v as f64 * to_e);
                            *v = (e as f64 * to_dn).round().min(65535.0) as u16;
                        }
                    }
                });
            }
        }
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn flat(w: u32, h: u32, format: PixelFormat, v: f32) -> Frame {
        let mut f = Frame::new(w, h, format).unwrap();
        for y in 0..h as usize {
            for x in 0..w as usize {
                for c in 0..format.channels() {
                    f.set(x, y, c, v);
                }
            }
        }
        f
    }

    fn moments(xs: impl Iterator<Item = f64>) -> (f64, f64, f64) {
        let v: Vec<f64> = xs.collect();
        let n = v.len() as f64;
        let m = v.iter().sum::<f64>() / n;
        (m, v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0), n)
    }

    #[test]
    fn variance_is_mean_over_gain() {
        // (format, level in 8-bit DN, gain, expected variance in 8-bit DN^2)
        let cases = [
            (PixelFormat::Mono8, 100.0, 0.5, 200.0), // one electron = 2 DN: no rounding
            (PixelFormat::Rgb8, 60.0, 2.3, 60.0 / 2.3 + 1.0 / 12.0),
            (PixelFormat::Mono8, 200.0, 40.0, 5.0 + 1.0 / 12.0),
            (PixelFormat::Mono8, 3.0, 1.0, 3.0),
            (PixelFormat::Mono16, 100.0, 4.0, 25.0),
        ];
        for (format, level, g, want) in cases {
            let s = format.dn_scale() as f64;
            let mut f = flat(256, 256, format, (level * s) as f32);
            let mut p = Params::defaults(&INFO);
            p.set("gain_e_per_dn", g).unwrap();
            ShotNoise::default().apply(&mut f, &p, &mut EffectCtx::new(1, 2, 3)).unwrap();
            let (m, var, n) = moments(f.packed_samples_f32().iter().map(|&v| v as f64 / s));
            // SE of the mean sqrt(var/n); of the variance about var*sqrt(2/n) (+ excess
            // kurtosis 1/lambda, small). 5-sigma bounds.
            assert!((m - level).abs() < 5.0 * (want / n).sqrt() + 0.01, "{format} g {g}: mean {m}");
            let tol = 5.0 * want * (2.0 / n).sqrt() + if format == PixelFormat::Mono16 { 0.01 } else { 0.0 };
            assert!((var - want).abs() < tol, "{format} g {g}: var {var}, want {want}");
        }
    }

    #[test]
    fn table_distribution_matches_poisson_pmf() {
        // Gain 0.5: output 2k, so P(out = 2k) is the Poisson pmf at k.
        let p = output_distribution(10, 0.5);
        let lam: f64 = 5.0;
        for k in 0..20u32 {
            let pmf = (k as f64 * lam.ln() - lam - ln_gamma(k as f64 + 1.0)).exp();
            assert!((p[2 * k as usize] - pmf).abs() < 1e-12, "k {k}");
            assert_eq!(p[2 * k as usize + 1], 0.0);
        }
        // Large-lambda branch: mean and variance in DN.
        let p = output_distribution(200, 1000.0);
        let m: f64 = p.iter().enumerate().map(|(d, q)| d as f64 * q).sum();
        let v: f64 = p.iter().enumerate().map(|(d, q)| (d as f64 - m).powi(2) * q).sum();
        assert!((m - 200.0).abs() < 1e-3 && (v - (0.2 + 1.0 / 12.0)).abs() < 0.02, "{m} {v}");
        // The alias table reproduces the distribution to 2^-24.
        let mut t = [0u32; 256];
        let p = output_distribution(77, 1.3);
        alias_table(&p, &mut t);
        let mut q = [0.0f64; 256];
        for (i, &e) in t.iter().enumerate() {
            let own = (e >> 8) as f64 / 65536.0;
            q[i] += own / 256.0;
            q[(e & 0xff) as usize] += (1.0 - own) / 256.0;
        }
        for d in 0..256 {
            assert!((q[d] - p[d]).abs() < 2.0 / 16_777_216.0, "{d}: {} vs {}", q[d], p[d]);
        }
    }

    #[test]
    fn fast_row_drawer_equals_the_scalar_reference() {
        let mut e = ShotNoise::default();
        e.ensure_table(2.7);
        let mut r = crate::rng::Rng::new(4);
        for n in [0usize, 1, 7, 8, 9, 100, 5761] {
            let row: Vec<u8> = (0..n).map(|_| r.below(256) as u8).collect();
            let (mut a, mut b) = (row.clone(), row.clone());
            let seed = crate::rng::Rng::new(n as u64);
            let (mut la, mut lb) = (RngLanes::new(&seed), RngLanes::new(&seed));
            let mut scratch = vec![0u32; n];
            draw_row_scalar(&mut a, &mut la, &e.table, &mut scratch);
            draw_row_fn()(&mut b, &mut lb, &e.table, &mut scratch);
            assert_eq!(a, b, "{n} samples");
            assert_eq!(la.next4(), lb.next4(), "same stream position");
        }
    }

    #[test]
    fn max_gain_is_identity_for_8_bit_and_thread_count_does_not_matter() {
        let orig = crate::faults::kit::bench_scene(120, 140, PixelFormat::Rgb8, 6).unwrap();
        let mut f = orig.clone();
        let mut p = Params::defaults(&INFO);
        p.set("gain_e_per_dn", 1e6).unwrap();
        ShotNoise::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
        assert_eq!(f, orig);
        p.set("gain_e_per_dn", 3.0).unwrap();
        for format in [PixelFormat::Rgb8, PixelFormat::Mono16] {
            let orig = crate::faults::kit::bench_scene(120, 140, format, 6).unwrap();
            let run = |threads| {
                let mut g = orig.clone();
                rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                    ShotNoise::default().apply(&mut g, &p, &mut EffectCtx::new(0, 4, 0)).unwrap();
                });
                g
            };
            let one = run(1);
            assert_eq!(one, run(2));
            assert_ne!(one, orig);
        }
    }
}
