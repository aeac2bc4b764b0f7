//! Types and helpers the signature modules share: the per-pair masks of the sim ([`Masks`]), the
//! camera noise model ([`NoiseModel`]) and the effect parameters a signature initialises
//! ([`params_from_signature`]). Depends only on [`super::types`], [`super::img`] and
//! [`super::stats`], so that a signature module needs nothing but these (see the dependency rule
//! in the module doc of `diagnose`).

#[cfg(test)]
use super::img::Pair;
use super::img::{FS, Plane, SAT_DN, distance_transform};
use super::stats;
use super::types::Signature;
use crate::faults::{ParamKind, Params, registry};

/// Largest Laplacian (DN) of the base in a 3x3 neighbourhood for a high-pass sample.
pub const QUIET_LAPLACIAN: f32 = 2.0;

/// Per-pair masks computed from the sim image (all channels).
#[derive(Debug, Clone)]
pub struct Masks {
    /// Any channel at full scale.
    pub sat: BitMask,
    /// Distance to the nearest saturated pixel (px; infinite without saturation).
    pub dist_sat: DistMap,
    /// Inside saturated regions: distance to the nearest unsaturated pixel.
    pub dist_in: DistMap,
    /// Smooth (gradient <= 4 DN/px and |Laplacian| <= 4 DN over the 3x3 neighbourhood): blur and
    /// sub-pixel shifts change these pixels by little, so the photometric regression uses them.
    pub smooth: BitMask,
    /// Quiet (|Laplacian| <= 2 DN over the 3x3 neighbourhood): high-pass noise measurements.
    pub quiet: BitMask,
    /// Distance to the nearest edge pixel (gradient > 8 DN/px).
    pub dist_edge: DistMap,
    /// Distance to the nearest edge pixel that is not the border of a saturated region.
    pub dist_edge_unsat: DistMap,
}

/// A per-pixel yes/no mask packed 64 pixels to a word (an eighth of a `Vec<bool>`: the masks of
/// every pair are held through the whole diagnosis).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BitMask {
    words: Vec<u64>,
    len: usize,
}

impl BitMask {
    pub fn from_bools(v: &[bool]) -> BitMask {
        let mut words = vec![0u64; v.len().div_ceil(64)];
        for (i, _) in v.iter().enumerate().filter(|(_, b)| **b) {
            words[i / 64] |= 1 << (i % 64);
        }
        BitMask { words, len: v.len() }
    }
    #[inline]
    pub fn get(&self, i: usize) -> bool {
        assert!(i < self.len, "BitMask index {i} out of range (length {})", self.len);
        self.words[i / 64] >> (i % 64) & 1 == 1
    }
    pub fn len(&self) -> usize {
        self.len
    }
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    /// Any pixel set.
    pub fn any(&self) -> bool {
        self.words.iter().any(|&w| w != 0)
    }
    pub fn to_bools(&self) -> Vec<bool> {
        (0..self.len).map(|i| self.get(i)).collect()
    }
}

/// A distance map of [`distance_transform`] held compactly with the same values: that transform's
/// distances are 3-4 chamfer integers divided by 3, so they are kept as the integer (u16, a half
/// of the f32 map) and divided on reading, which gives the f32 the transform computed bit for bit.
/// A map with a value the integer cannot hold exactly (an image side above 16383 px) is kept as
/// f32.
#[derive(Debug, Clone, PartialEq)]
pub enum DistMap {
    /// Chamfer integers; [`DistMap::INF`] for an infinite distance (no such pixel in the image).
    Chamfer(Vec<u16>),
    Full(Vec<f32>),
}

impl DistMap {
    /// Marks an infinite distance in [`DistMap::Chamfer`].
    pub const INF: u16 = u16::MAX;

    pub fn from_f32(d: Vec<f32>) -> DistMap {
        let code = |v: f32| -> Option<u16> {
            if v == f32::INFINITY {
                return Some(Self::INF);
            }
            let c = (v as f64 * 3.0).round();
            (c >= 0.0 && c < Self::INF as f64 && (c as u16) as f32 / 3.0 == v).then_some(c as u16)
        };
        match d.iter().map(|&v| code(v)).collect::<Option<Vec<u16>>>() {
            Some(c) => DistMap::Chamfer(c),
            None => DistMap::Full(d),
        }
    }
    /// Distance (px) at pixel `i`.
    #[inline]
    pub fn get(&self, i: usize) -> f32 {
        match self {
            DistMap::Chamfer(c) => match c[i] {
                Self::INF => f32::INFINITY,
                v => v as f32 / 3.0,
            },
            DistMap::Full(d) => d[i],
        }
    }
    pub fn len(&self) -> usize {
        match self {
            DistMap::Chamfer(c) => c.len(),
            DistMap::Full(d) => d.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Masks {
    pub fn compute(sim: &[Plane]) -> Masks {
        let (w, h) = (sim[0].w, sim[0].h);
        let n = w * h;
        let mut grad = Plane::new(w, h);
        let mut lap = Plane::new(w, h);
        let mut sat = vec![false; n];
        for s in sim {
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    let (xi, yi) = (x as isize, y as isize);
                    let c = s.at(x, y);
                    let l = s.at_clamped(xi - 1, yi);
                    let r = s.at_clamped(xi + 1, yi);
                    let u = s.at_clamped(xi, yi - 1);
                    let d = s.at_clamped(xi, yi + 1);
                    let g = 0.5 * ((r - l).abs() + (d - u).abs());
                    grad.data[i] = grad.data[i].max(g);
                    lap.data[i] = lap.data[i].max((l + r + u + d - 4.0 * c).abs());
                    if c >= SAT_DN {
                        sat[i] = true;
                    }
                }
            }
        }
        let lap3 = lap.extreme_filter(1, true);
        let grad3 = grad.extreme_filter(1, true);
        let smooth: Vec<bool> = (0..n).map(|i| lap3.data[i] <= 4.0 && grad3.data[i] <= 4.0).collect();
        let quiet: Vec<bool> = lap3.data.iter().map(|&v| v <= QUIET_LAPLACIAN).collect();
        let dist_sat = distance_transform(&sat, w, h);
        let unsat: Vec<bool> = sat.iter().map(|&s| !s).collect();
        let dist_in = distance_transform(&unsat, w, h);
        let edge: Vec<bool> = grad.data.iter().map(|&g| g > 8.0).collect();
        let dist_edge = distance_transform(&edge, w, h);
        let edge_unsat: Vec<bool> = (0..n).map(|i| edge[i] && dist_sat[i] > 3.0).collect();
        let dist_edge_unsat = distance_transform(&edge_unsat, w, h);
        Masks {
            sat: BitMask::from_bools(&sat),
            dist_sat: DistMap::from_f32(dist_sat),
            dist_in: DistMap::from_f32(dist_in),
            smooth: BitMask::from_bools(&smooth),
            quiet: BitMask::from_bools(&quiet),
            dist_edge: DistMap::from_f32(dist_edge),
            dist_edge_unsat: DistMap::from_f32(dist_edge_unsat),
        }
    }
}

/// One level bin of the high-pass measurement.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct NoiseBin {
    /// Level (8-bit DN) of the bin centre.
    pub level: f64,
    /// Variance of the continuous noise (DN²), quantisation removed.
    pub var: f64,
    pub n: usize,
}

/// Censored fit of one dark block.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct LowBlock {
    /// Pair index and channel.
    pub k: usize,
    pub c: usize,
    /// Block centre (px).
    pub xc: f64,
    pub yc: f64,
    /// Mean base level of the fitted pixels (DN).
    pub base: f64,
    /// Additive level real - base (DN), its standard error, and the noise sigma.
    pub mu: f64,
    pub se_mu: f64,
    pub sigma: f64,
    pub n: usize,
    /// Fraction of the block's values clipped at 0.
    pub clipped: f64,
}

/// Noise model in 8-bit DN.
#[derive(Debug, Clone, serde::Serialize)]
pub struct NoiseModel {
    /// Variance intercept (DN²) of the continuous noise.
    pub a: f64,
    pub se_a: f64,
    /// Variance per DN of signal (1 / gain_e_per_dn).
    pub b: f64,
    pub se_b: f64,
    /// Variance per DN² of signal (prnu sigma²), held fixed.
    pub c: f64,
    /// Quantisation step of the real data (1 for 8-bit files, 1/257 for 16-bit).
    pub quant: f64,
    pub bins: Vec<NoiseBin>,
    pub low: Vec<LowBlock>,
    /// Levels covered by the fit.
    pub fit_range: (f64, f64),
    /// Whether the slope could be measured (two or more separated levels).
    pub slope_identified: bool,
}

impl NoiseModel {
    /// Variance (DN²) of an observed value whose noise-free level is `s` (quantisation included).
    #[inline]
    pub fn var(&self, s: f64) -> f64 {
        let s = s.clamp(0.0, FS as f64);
        (self.a + self.b * s + self.c * s * s).max(0.02) + self.quant * self.quant / 12.0
    }
    pub fn sd(&self, s: f64) -> f64 {
        self.var(s).sqrt()
    }
    /// Standard deviation of the signal-independent noise (DN).
    pub fn read_sigma(&self) -> f64 {
        self.a.max(0.0).sqrt()
    }
    /// A flat prior for the start of the analysis.
    pub fn prior(quant: f64) -> NoiseModel {
        NoiseModel {
            a: 4.0,
            se_a: f64::INFINITY,
            b: 0.1,
            se_b: f64::INFINITY,
            c: 0.0,
            quant,
            bins: Vec::new(),
            low: Vec::new(),
            fit_range: (0.0, FS as f64),
            slope_identified: false,
        }
    }
    /// Additive level of the dark regions: inverse-variance mean of the low blocks' μ with its
    /// standard error across blocks (None without low blocks).
    pub fn dark_level(&self) -> Option<(f64, f64, usize)> {
        if self.low.len() < 2 {
            return None;
        }
        let mus: Vec<f64> = self.low.iter().map(|b| b.mu).collect();
        let (m, se) = stats::mean_se(&mus);
        let se_model = (1.0 / self.low.iter().map(|b| 1.0 / (b.se_mu * b.se_mu).max(1e-9)).sum::<f64>()).sqrt();
        Some((m, se.max(se_model), self.low.len()))
    }
}

/// Per-row offsets (frame, channel, row) removed from the residual (row noise).
pub type RowOffsets = Vec<Vec<Vec<f32>>>;

/// Parameters of a registered effect initialised from a signature.
pub fn params_from_signature(sig: &Signature) -> Option<Params> {
    let reg = registry::find(sig.effect)?;
    let mut p = Params::defaults(reg.info);
    for (n, v) in &sig.params {
        if let Some((_, spec)) = reg.info.param(n) {
            let v = match spec.kind {
                ParamKind::Int => v.round(),
                _ => *v,
            };
            if v.is_finite() {
                let _ = p.set(n, v.clamp(spec.min, spec.max));
            }
        }
    }
    for (n, w) in &sig.choices {
        let _ = p.set_choice(n, w);
    }
    Some(p)
}

#[cfg(test)]
/// (Tests) A textured scene (anti-aliased discs and bars on a ramp, 3x3 supersampled, never
/// saturated) as the sim, and the same scene through the PSF `k` plus camera noise as the real
/// image, two frames.
pub fn blurred_test_pairs(k: &[f64], half: usize, seed: u64) -> Vec<Pair> {
    let (w, h) = (160usize, 120usize);
    let mut r = crate::rng::Rng::new(seed);
    let shapes: Vec<(f64, f64, f64, f64)> = (0..40)
        .map(|_| (r.uniform() * w as f64, r.uniform() * h as f64, 2.0 + 8.0 * r.uniform(), 40.0 + 150.0 * r.uniform()))
        .collect();
    let mut pairs = Vec::new();
    for frame in 0..2u64 {
        let mut sim = Plane::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for sy in 0..3 {
                    for sx in 0..3 {
                        let (fx, fy) = (x as f64 + (sx as f64 + 0.5) / 3.0, y as f64 + (sy as f64 + 0.5) / 3.0);
                        let mut v = 20.0 + 0.2 * fx;
                        for (i, &(cx, cy, rad, lv)) in shapes.iter().enumerate() {
                            let cx = cx + 3.0 * frame as f64;
                            let inside = if i.is_multiple_of(3) {
                                (fx - cx).abs() < rad && (fy - cy).abs() < 0.4 * rad
                            } else {
                                (fx - cx).powi(2) + (fy - cy).powi(2) < rad * rad
                            };
                            if inside {
                                v = lv;
                            }
                        }
                        acc += v;
                    }
                }
                sim.data[y * w + x] = (acc / 9.0).round() as f32;
            }
        }
        let n = 2 * half + 1;
        let mut real = Plane::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for j in 0..n {
                    for i in 0..n {
                        let v = sim.at_clamped(
                            x as isize + i as isize - half as isize,
                            y as isize + j as isize - half as isize,
                        );
                        acc += k[j * n + i] * v as f64;
                    }
                }
                let sd = (1.0 + acc / 8.0).sqrt();
                real.data[y * w + x] = (acc + sd * r.normal()).round().clamp(0.0, 255.0) as f32;
            }
        }
        let f = super::img::frame_from_planes(
            std::slice::from_ref(&sim),
            &crate::frame::Frame::new(w as u32, h as u32, crate::frame::PixelFormat::Mono8).unwrap(),
        );
        let g = super::img::frame_from_planes(std::slice::from_ref(&real), &f);
        pairs.push(Pair { name: format!("{frame}"), sim_frame: f, real_frame: g, sim: vec![sim], real: vec![real] });
    }
    pairs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bit_mask_round_trips() {
        // A length that is not a multiple of 64 and a pattern with runs and isolated pixels.
        for n in [0usize, 1, 63, 64, 65, 1000] {
            let v: Vec<bool> = (0..n).map(|i| (i * 7919) % 13 < 4 || i % 64 == 63).collect();
            let m = BitMask::from_bools(&v);
            assert_eq!(m.len(), n);
            assert_eq!(m.to_bools(), v);
            assert_eq!(m.any(), v.iter().any(|&b| b));
            assert!((0..n).all(|i| m.get(i) == v[i]));
        }
    }

    #[test]
    fn distance_map_holds_the_transform_bit_for_bit() {
        let (w, h) = (97usize, 61usize);
        let mask: Vec<bool> = (0..w * h).map(|i| (i * 31) % 211 == 0 || (i / w == 30 && i % w < 40)).collect();
        let d = distance_transform(&mask, w, h);
        let m = DistMap::from_f32(d.clone());
        assert!(matches!(m, DistMap::Chamfer(_)), "chamfer distances are held as integers");
        assert_eq!(m.len(), d.len());
        assert!((0..d.len()).all(|i| m.get(i).to_bits() == d[i].to_bits()));
        // No pixel of the kind: infinite everywhere, kept as such.
        let none = distance_transform(&vec![false; w * h], w, h);
        let m = DistMap::from_f32(none.clone());
        assert!((0..none.len()).all(|i| m.get(i) == f32::INFINITY));
        // A value that is not a chamfer integer / 3 is kept as it is.
        let odd = vec![0.0, 0.1, 2.0 / 3.0, f32::INFINITY];
        let m = DistMap::from_f32(odd.clone());
        assert!(matches!(m, DistMap::Full(_)));
        assert!((0..odd.len()).all(|i| m.get(i).to_bits() == odd[i].to_bits()));
    }

    #[test]
    fn masks_of_a_scene_with_saturation_match_the_transform() {
        // The compact masks read back as the f32 maps and bool masks they replace.
        let (w, h) = (80usize, 50usize);
        let mut p = Plane::filled(w, h, 40.0);
        for y in 10..20 {
            for x in 30..45 {
                p.data[y * w + x] = FS;
            }
        }
        for x in 0..w {
            p.data[35 * w + x] = 120.0;
        }
        let m = Masks::compute(std::slice::from_ref(&p));
        let sat: Vec<bool> = p.data.iter().map(|&v| v >= SAT_DN).collect();
        assert_eq!(m.sat.to_bools(), sat);
        let d = distance_transform(&sat, w, h);
        assert!((0..w * h).all(|i| m.dist_sat.get(i).to_bits() == d[i].to_bits()));
        assert!(m.dist_sat.get(15 * w + 37) == 0.0 && m.dist_sat.get(15 * w + 50) > 4.0);
    }
}
