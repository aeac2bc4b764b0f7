//! Reproducible random numbers.
//!
//! faultcam owns its generator (xoshiro256++ seeded through SplitMix64) and its samplers, so
//! output bytes never change with a dependency upgrade. Every stochastic effect receives a
//! generator derived from (campaign seed, frame seq, effect index); effects that work in
//! parallel derive one generator per row or band with [`Rng::derive`], so the output does not
//! depend on the thread count.

/// SplitMix64 step: a strong 64-bit mixer used for seeding and derivation.
#[inline]
pub fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash a list of words into one seed.
pub fn mix_seed(parts: &[u64]) -> u64 {
    let mut s = 0x6A09_E667_F3BC_C908u64;
    let mut out = 0u64;
    for &p in parts {
        s ^= p;
        out = splitmix64(&mut s);
        s = out;
    }
    out
}

/// Domain tags so per-frame and fixed-pattern streams never collide.
const TAG_FRAME: u64 = 0xF5A3_0001;
const TAG_PATTERN: u64 = 0xF5A3_0002;
const TAG_DERIVE: u64 = 0xF5A3_0003;

/// xoshiro256++ generator.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rng {
    s: [u64; 4],
    seed: u64,
}

impl Rng {
    /// Generator from a 64-bit seed.
    pub fn new(seed: u64) -> Rng {
        let mut sm = seed;
        let s = [splitmix64(&mut sm), splitmix64(&mut sm), splitmix64(&mut sm), splitmix64(&mut sm)];
        Rng { s, seed }
    }

    /// Per-frame, per-effect generator.
    pub fn for_frame(campaign_seed: u64, seq: u64, effect_index: u64) -> Rng {
        Rng::new(mix_seed(&[TAG_FRAME, campaign_seed, seq, effect_index]))
    }

    /// Fixed-pattern generator (same for every frame of a recording): PRNU maps, hot pixels.
    pub fn for_pattern(campaign_seed: u64, effect_index: u64) -> Rng {
        Rng::new(mix_seed(&[TAG_PATTERN, campaign_seed, effect_index]))
    }

    /// Independent child generator number `k` (e.g. one per row); does not advance `self`.
    pub fn derive(&self, k: u64) -> Rng {
        Rng::new(mix_seed(&[TAG_DERIVE, self.seed, k]))
    }

    /// The seed this generator was created from (recorded in the ground-truth log).
    pub fn seed(&self) -> u64 {
        self.seed
    }

    #[inline(always)]
    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in [0, 1) with 53 bits.
    #[inline(always)]
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [0, 1) as f32 (24 bits).
    #[inline(always)]
    pub fn uniform_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u32 << 24) as f32)
    }

    /// Uniform in [lo, hi).
    #[inline]
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// Uniform integer in [0, n) (n > 0), unbiased (Lemire).
    #[inline]
    pub fn below(&mut self, n: u64) -> u64 {
        if n == 0 {
            return 0;
        }
        loop {
            let x = self.next_u64();
            let m = (x as u128) * (n as u128);
            let lo = m as u64;
            if lo >= n.wrapping_neg() % n {
                return (m >> 64) as u64;
            }
        }
    }

    /// True with probability p.
    #[inline]
    pub fn bernoulli(&mut self, p: f64) -> bool {
        self.uniform() < p
    }

    /// Standard normal deviate (Marsaglia polar method; deterministic, exact).
    pub fn normal(&mut self) -> f64 {
        loop {
            let u = 2.0 * self.uniform() - 1.0;
            let v = 2.0 * self.uniform() - 1.0;
            let s = u * u + v * v;
            if s > 0.0 && s < 1.0 {
                return u * (-2.0 * s.ln() / s).sqrt();
            }
        }
    }

    /// Poisson deviate with the given mean (>= 0). Knuth's product method below 12,
    /// Hörmann's PTRS transformed rejection above: exact in distribution for all means.
    pub fn poisson(&mut self, mean: f64) -> u64 {
        if mean <= 0.0 || !mean.is_finite() {
            return 0;
        }
        if mean < 12.0 {
            let l = (-mean).exp();
            let mut k = 0u64;
            let mut p = 1.0;
            loop {
                p *= self.uniform();
                if p <= l {
                    return k;
                }
                k += 1;
            }
        }
        // PTRS (Hörmann 1993).
        let slam = mean.sqrt();
        let loglam = mean.ln();
        let b = 0.931 + 2.53 * slam;
        let a = -0.059 + 0.02483 * b;
        let invalpha = 1.1239 + 1.1328 / (b - 3.4);
        let vr = 0.9277 - 3.6224 / (b - 2.0);
        loop {
            let u = self.uniform() - 0.5;
            let v = self.uniform();
            let us = 0.5 - u.abs();
            let k = ((2.0 * a / us + b) * u + mean + 0.43).floor();
            if us >= 0.07 && v <= vr {
                return k as u64;
            }
            if k < 0.0 || (us < 0.013 && v > us) {
                continue;
            }
            if (v * invalpha / (a / (us * us) + b)).ln() <= -mean + k * loglam - ln_gamma(k + 1.0) {
                return k as u64;
            }
        }
    }
}

/// ln Γ(x) for x > 0 (Lanczos, |error| < 1e-13 for the arguments used here).
pub fn ln_gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + G + 0.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn moments(xs: &[f64]) -> (f64, f64) {
        let n = xs.len() as f64;
        let m = xs.iter().sum::<f64>() / n;
        let v = xs.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0);
        (m, v)
    }

    #[test]
    fn same_seed_same_stream_and_derivation_is_independent() {
        let mut a = Rng::for_frame(1, 2, 3);
        let mut b = Rng::for_frame(1, 2, 3);
        let mut c = Rng::for_frame(1, 3, 3);
        let va: Vec<u64> = (0..8).map(|_| a.next_u64()).collect();
        let vb: Vec<u64> = (0..8).map(|_| b.next_u64()).collect();
        let vc: Vec<u64> = (0..8).map(|_| c.next_u64()).collect();
        assert_eq!(va, vb);
        assert_ne!(va, vc);
        assert_ne!(Rng::for_pattern(1, 3).next_u64(), Rng::for_frame(1, 0, 3).next_u64());
        assert_eq!(a.derive(5), b.derive(5));
        assert_ne!(a.derive(5), a.derive(6));
    }

    #[test]
    fn normal_has_unit_moments() {
        let mut r = Rng::new(9);
        let xs: Vec<f64> = (0..200_000).map(|_| r.normal()).collect();
        let (m, v) = moments(&xs);
        // Standard errors: mean 1/sqrt(n) = 0.0022, variance sqrt(2/n) = 0.0032; 5 sigma bounds.
        assert!(m.abs() < 0.012, "mean {m}");
        assert!((v - 1.0).abs() < 0.016, "var {v}");
    }

    #[test]
    fn poisson_mean_equals_variance_small_and_large() {
        for &lam in &[0.3f64, 3.0, 11.5, 12.5, 40.0, 1000.0] {
            let mut r = Rng::new(lam.to_bits());
            let xs: Vec<f64> = (0..100_000).map(|_| r.poisson(lam) as f64).collect();
            let (m, v) = moments(&xs);
            let se_m = (lam / 1e5).sqrt();
            assert!((m - lam).abs() < 5.0 * se_m, "lambda {lam}: mean {m}");
            // var of sample variance ~ (2 lam^2 + lam)/n
            let se_v = ((2.0 * lam * lam + lam) / 1e5).sqrt();
            assert!((v - lam).abs() < 5.0 * se_v, "lambda {lam}: var {v}");
        }
    }

    #[test]
    fn below_is_in_range_and_roughly_uniform() {
        let mut r = Rng::new(4);
        let mut counts = [0u32; 7];
        for _ in 0..70_000 {
            counts[r.below(7) as usize] += 1;
        }
        for c in counts {
            assert!((c as i64 - 10_000).abs() < 500, "{counts:?}");
        }
    }

    #[test]
    fn ln_gamma_matches_factorials() {
        let mut f = 1.0f64;
        for n in 1..20 {
            f *= n as f64;
            assert!((ln_gamma(n as f64 + 1.0) - f.ln()).abs() < 1e-10);
        }
    }
}
