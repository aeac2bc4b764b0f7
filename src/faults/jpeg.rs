//! `jpeg`: JPEG compression round trip at a libjpeg quality.
//!
//! The default `codec = model` computes exactly the lossy part of baseline JPEG as libjpeg /
//! libjpeg-turbo perform it — RGB→YCbCr in 16-bit fixed point, 4:2:0 chroma averaging (or 4:4:4),
//! edge replication to whole MCUs, 8x8 DCT, quantisation with the IJG tables scaled by
//! `jpeg_quality_scaling`, dequantisation, inverse DCT, "fancy" (triangular) chroma upsampling
//! and YCbCr→RGB in fixed point — and skips the entropy coding, which is lossless: the result is
//! what a decoder shows. 8-bit frames use libjpeg's default integer DCTs (`jfdctint` /
//! `jidctint`, "islow") with its rounding, vectorised over the columns of the blocks (two blocks
//! at a time in 16-bit lanes with AVX2, as libjpeg-turbo's SIMD does; eight 32-bit lanes or the
//! scalar reference otherwise; exact arithmetic, so the bits do not depend on the path): the
//! output is bit-identical to libjpeg-turbo's encode/decode (tested against OpenCV's
//! imencode/imdecode).
//! Mono16 uses the AAN float DCT (`jfdctflt` / `jidctflt`) at full precision. `codec = encoder`
//! runs a real encode/decode through the `image` crate instead (reference; allocates per frame).

use super::kit::multiversion;
use super::util::ROWS_PER_TASK;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, FrameData, ImageMut, PixelFormat, Sample};
use crate::with_image_mut;
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "jpeg",
    stage: Stage::Transmission,
    order: 10,
    summary: "JPEG compression round trip (baseline, libjpeg quality scaling)",
    model: "Baseline JPEG round trip at libjpeg quality 1..=100: quantisation tables = IJG Annex K tables scaled by \
            libjpeg's jpeg_quality_scaling (q < 50: 5000/q %, else 200 - 2q %; entries rounded and clamped to \
            1..=255). codec = model (default): the lossy part computed directly (no entropy coding, which is \
            lossless) — Rgb8: RGB->YCbCr (JFIF, 16-bit fixed point as libjpeg), chroma 4:2:0 by 2x2 averaging \
            (libjpeg's alternating bias) or 4:4:4, edges replicated to whole MCUs, libjpeg's integer 8x8 DCT \
            (islow), coefficients quantised (round half away from zero) and dequantised, integer inverse DCT, \
            range limit to 0..255, chroma upsampled with libjpeg's triangular 'fancy' filter, YCbCr->RGB in fixed \
            point: bit-identical to a libjpeg-turbo encode + decode with default settings. Mono8: the luminance \
            path only. Mono16: the same quantisation applied to v/257 with the float DCT at full precision \
            (baseline JPEG is 8-bit; this models an 8-bit-equivalent codec without the 8-bit rounding). \
            codec = encoder: a real encode/decode with the image crate (its encoder is always 4:4:4 and rounds \
            differently from libjpeg: about 1 DN mean difference; Mono16 goes through 8 bits). quality = 100 is \
            nearly but not exactly the identity (DCT rounding); error grows as quality drops. Deterministic.",
    params: &[
        ParamSpec::int("quality", "1", 1.0, 100.0, 75.0, "libjpeg quality (100 = best)"),
        ParamSpec::choice(
            "codec",
            &["model", "encoder"],
            0,
            false,
            "model = fast exact lossy model; encoder = real encode/decode (image crate, slow)",
        ),
        ParamSpec::choice("chroma", &["420", "444"], 0, false, "chroma subsampling of colour frames (model)"),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(Jpeg::default())
}

/// IJG luminance table (Annex K.1), natural (row-major) order.
pub const STD_LUMA: [u16; 64] = [
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57, 69, 56, 14, 17, 22, 29, 51,
    87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92, 49, 64, 78, 87, 103, 121, 120, 101,
    72, 92, 95, 98, 112, 100, 103, 99,
];
/// IJG chrominance table (Annex K.2).
pub const STD_CHROMA: [u16; 64] = [
    17, 18, 24, 47, 99, 99, 99, 99, 18, 21, 26, 66, 99, 99, 99, 99, 24, 26, 56, 99, 99, 99, 99, 99, 47, 66, 99, 99, 99,
    99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99,
    99, 99, 99, 99, 99, 99,
];

/// libjpeg's `jpeg_quality_scaling` applied to a base table (baseline: clamped to 1..=255).
pub fn scaled_table(base: &[u16; 64], quality: u32) -> [u16; 64] {
    let q = quality.clamp(1, 100);
    let scale = if q < 50 { 5000 / q } else { 200 - 2 * q };
    base.map(|b| ((b as u32 * scale + 50) / 100).clamp(1, 255) as u16)
}

type Block = [[f32; 8]; 8];
type Row = [f32; 8];

#[inline(always)]
fn add(a: Row, b: Row) -> Row {
    std::array::from_fn(|i| a[i] + b[i])
}
#[inline(always)]
fn sub(a: Row, b: Row) -> Row {
    std::array::from_fn(|i| a[i] - b[i])
}
#[inline(always)]
fn mul(a: Row, k: f32) -> Row {
    a.map(|v| v * k)
}

/// AAN forward DCT along the first index (8 columns at once), libjpeg `jfdctflt` scaling:
/// output = 8 * s_k * F(k) per dimension pair, s_0 = 1, s_k = sqrt(2) cos(k pi / 16).
#[inline(always)]
fn fdct_pass(b: &mut Block) {
    let tmp0 = add(b[0], b[7]);
    let tmp7 = sub(b[0], b[7]);
    let tmp1 = add(b[1], b[6]);
    let tmp6 = sub(b[1], b[6]);
    let tmp2 = add(b[2], b[5]);
    let tmp5 = sub(b[2], b[5]);
    let tmp3 = add(b[3], b[4]);
    let tmp4 = sub(b[3], b[4]);
    // Even part.
    let tmp10 = add(tmp0, tmp3);
    let tmp13 = sub(tmp0, tmp3);
    let tmp11 = add(tmp1, tmp2);
    let tmp12 = sub(tmp1, tmp2);
    b[0] = add(tmp10, tmp11);
    b[4] = sub(tmp10, tmp11);
    let z1 = mul(add(tmp12, tmp13), 0.707_106_77);
    b[2] = add(tmp13, z1);
    b[6] = sub(tmp13, z1);
    // Odd part.
    let tmp10 = add(tmp4, tmp5);
    let tmp11 = add(tmp5, tmp6);
    let tmp12 = add(tmp6, tmp7);
    let z5 = mul(sub(tmp10, tmp12), 0.382_683_43);
    let z2 = add(mul(tmp10, 0.541_196_1), z5);
    let z4 = add(mul(tmp12, 1.306_563), z5);
    let z3 = mul(tmp11, 0.707_106_77);
    let z11 = add(tmp7, z3);
    let z13 = sub(tmp7, z3);
    b[5] = add(z13, z2);
    b[3] = sub(z13, z2);
    b[1] = add(z11, z4);
    b[7] = sub(z11, z4);
}

/// AAN inverse DCT along the first index (libjpeg `jidctflt`, without the final 1/8).
#[inline(always)]
fn idct_pass(b: &mut Block) {
    // Even part.
    let tmp10 = add(b[0], b[4]);
    let tmp11 = sub(b[0], b[4]);
    let tmp13 = add(b[2], b[6]);
    let tmp12 = sub(mul(sub(b[2], b[6]), std::f32::consts::SQRT_2), tmp13);
    let tmp0 = add(tmp10, tmp13);
    let tmp3 = sub(tmp10, tmp13);
    let tmp1 = add(tmp11, tmp12);
    let tmp2 = sub(tmp11, tmp12);
    // Odd part.
    let z13 = add(b[5], b[3]);
    let z10 = sub(b[5], b[3]);
    let z11 = add(b[1], b[7]);
    let z12 = sub(b[1], b[7]);
    let tmp7 = add(z11, z13);
    let tmp11 = mul(sub(z11, z13), std::f32::consts::SQRT_2);
    let z5 = mul(add(z10, z12), 1.847_759);
    let tmp10 = sub(mul(z12, 1.082_392_2), z5);
    let tmp12 = add(mul(z10, -2.613_126), z5);
    let tmp6 = sub(tmp12, tmp7);
    let tmp5 = sub(tmp11, tmp6);
    let tmp4 = add(tmp10, tmp5);
    b[0] = add(tmp0, tmp7);
    b[7] = sub(tmp0, tmp7);
    b[1] = add(tmp1, tmp6);
    b[6] = sub(tmp1, tmp6);
    b[2] = add(tmp2, tmp5);
    b[5] = sub(tmp2, tmp5);
    b[4] = add(tmp3, tmp4);
    b[3] = sub(tmp3, tmp4);
}

#[inline(always)]
fn transpose(b: &mut Block) {
    for i in 0..8 {
        for j in i + 1..8 {
            let t = b[i][j];
            b[i][j] = b[j][i];
            b[j][i] = t;
        }
    }
}

/// Round to nearest (ties to even) for |x| < 2^22, vectorisable without SSE4.1.
#[inline(always)]
fn round_ne(x: f32) -> f32 {
    const M: f32 = 12_582_912.0; // 1.5 * 2^23
    (x + M) - M
}

type IBlock = [[i32; 8]; 8];
type IRow = [i32; 8];

/// Eight i32 lanes (one block row): the integer DCT is written once over this trait and runs
/// either on plain arrays (the scalar reference) or on AVX2 registers (same integer operations,
/// so the same bits).
trait Lanes: Copy {
    fn add(self, b: Self) -> Self;
    fn sub(self, b: Self) -> Self;
    fn mul(self, k: i32) -> Self;
    fn shl(self, n: u32) -> Self;
    /// DESCALE(x, n): add one half, arithmetic shift right.
    fn descale(self, n: u32) -> Self;
}

impl Lanes for IRow {
    #[inline(always)]
    fn add(self, b: Self) -> Self {
        std::array::from_fn(|i| self[i] + b[i])
    }
    #[inline(always)]
    fn sub(self, b: Self) -> Self {
        std::array::from_fn(|i| self[i] - b[i])
    }
    #[inline(always)]
    fn mul(self, k: i32) -> Self {
        self.map(|v| v * k)
    }
    #[inline(always)]
    fn shl(self, n: u32) -> Self {
        self.map(|v| v << n)
    }
    #[inline(always)]
    fn descale(self, n: u32) -> Self {
        self.map(|v| (v + (1 << (n - 1))) >> n)
    }
}

// libjpeg jfdctint.c / jidctint.c constants (CONST_BITS = 13).
const CONST_BITS: u32 = 13;
const PASS1_BITS: u32 = 2;
const FIX_0_298631336: i32 = 2446;
const FIX_0_390180644: i32 = 3196;
const FIX_0_541196100: i32 = 4433;
const FIX_0_765366865: i32 = 6270;
const FIX_0_899976223: i32 = 7373;
const FIX_1_175875602: i32 = 9633;
const FIX_1_501321110: i32 = 12299;
const FIX_1_847759065: i32 = 15137;
const FIX_1_961570560: i32 = 16069;
const FIX_2_053119869: i32 = 16819;
const FIX_2_562915447: i32 = 20995;
const FIX_3_072711026: i32 = 25172;

/// libjpeg's integer forward DCT (jfdctint, "islow") along the first index; pass 1 keeps
/// PASS1_BITS of extra precision, pass 2 removes it (output = 8 x true DCT).
#[inline(always)]
fn fdct_int_pass<L: Lanes>(b: &mut [L; 8], pass1: bool) {
    let tmp0 = b[0].add(b[7]);
    let tmp7 = b[0].sub(b[7]);
    let tmp1 = b[1].add(b[6]);
    let tmp6 = b[1].sub(b[6]);
    let tmp2 = b[2].add(b[5]);
    let tmp5 = b[2].sub(b[5]);
    let tmp3 = b[3].add(b[4]);
    let tmp4 = b[3].sub(b[4]);
    let tmp10 = tmp0.add(tmp3);
    let tmp13 = tmp0.sub(tmp3);
    let tmp11 = tmp1.add(tmp2);
    let tmp12 = tmp1.sub(tmp2);
    if pass1 {
        b[0] = tmp10.add(tmp11).shl(PASS1_BITS);
        b[4] = tmp10.sub(tmp11).shl(PASS1_BITS);
    } else {
        b[0] = tmp10.add(tmp11).descale(PASS1_BITS);
        b[4] = tmp10.sub(tmp11).descale(PASS1_BITS);
    }
    let n = if pass1 { CONST_BITS - PASS1_BITS } else { CONST_BITS + PASS1_BITS };
    let z1 = tmp12.add(tmp13).mul(FIX_0_541196100);
    b[2] = z1.add(tmp13.mul(FIX_0_765366865)).descale(n);
    b[6] = z1.add(tmp12.mul(-FIX_1_847759065)).descale(n);
    // Odd part.
    let z1 = tmp4.add(tmp7);
    let z2 = tmp5.add(tmp6);
    let z3 = tmp4.add(tmp6);
    let z4 = tmp5.add(tmp7);
    let z5 = z3.add(z4).mul(FIX_1_175875602);
    let tmp4 = tmp4.mul(FIX_0_298631336);
    let tmp5 = tmp5.mul(FIX_2_053119869);
    let tmp6 = tmp6.mul(FIX_3_072711026);
    let tmp7 = tmp7.mul(FIX_1_501321110);
    let z1 = z1.mul(-FIX_0_899976223);
    let z2 = z2.mul(-FIX_2_562915447);
    let z3 = z3.mul(-FIX_1_961570560).add(z5);
    let z4 = z4.mul(-FIX_0_390180644).add(z5);
    b[7] = tmp4.add(z1).add(z3).descale(n);
    b[5] = tmp5.add(z2).add(z4).descale(n);
    b[3] = tmp6.add(z2).add(z3).descale(n);
    b[1] = tmp7.add(z1).add(z4).descale(n);
}

/// libjpeg's integer inverse DCT (jidctint) along the first index; `n` is the final descale
/// (CONST_BITS - PASS1_BITS after pass 1, CONST_BITS + PASS1_BITS + 3 after pass 2).
#[inline(always)]
fn idct_int_pass<L: Lanes>(b: &mut [L; 8], n: u32) {
    let z1 = b[2].add(b[6]).mul(FIX_0_541196100);
    let tmp2 = z1.add(b[6].mul(-FIX_1_847759065));
    let tmp3 = z1.add(b[2].mul(FIX_0_765366865));
    let tmp0 = b[0].add(b[4]).shl(CONST_BITS);
    let tmp1 = b[0].sub(b[4]).shl(CONST_BITS);
    let tmp10 = tmp0.add(tmp3);
    let tmp13 = tmp0.sub(tmp3);
    let tmp11 = tmp1.add(tmp2);
    let tmp12 = tmp1.sub(tmp2);
    // Odd part.
    let (t0, t1, t2, t3) = (b[7], b[5], b[3], b[1]);
    let z1 = t0.add(t3);
    let z2 = t1.add(t2);
    let z3 = t0.add(t2);
    let z4 = t1.add(t3);
    let z5 = z3.add(z4).mul(FIX_1_175875602);
    let z1 = z1.mul(-FIX_0_899976223);
    let z2 = z2.mul(-FIX_2_562915447);
    let z3 = z3.mul(-FIX_1_961570560).add(z5);
    let z4 = z4.mul(-FIX_0_390180644).add(z5);
    let t0 = t0.mul(FIX_0_298631336).add(z1.add(z3));
    let t1 = t1.mul(FIX_2_053119869).add(z2.add(z4));
    let t2 = t2.mul(FIX_3_072711026).add(z2.add(z3));
    let t3 = t3.mul(FIX_1_501321110).add(z1.add(z4));
    b[0] = tmp10.add(t3).descale(n);
    b[7] = tmp10.sub(t3).descale(n);
    b[1] = tmp11.add(t2).descale(n);
    b[6] = tmp11.sub(t2).descale(n);
    b[2] = tmp12.add(t1).descale(n);
    b[5] = tmp12.sub(t1).descale(n);
    b[3] = tmp13.add(t0).descale(n);
    b[4] = tmp13.sub(t0).descale(n);
}

#[inline(always)]
fn itranspose(b: &mut IBlock) {
    for i in 0..8 {
        for j in i + 1..8 {
            let t = b[i][j];
            b[i][j] = b[j][i];
            b[j][i] = t;
        }
    }
}

/// Integer quantiser in natural order: divisor Q*8 (islow output is 8x the DCT), rounding half
/// away from zero as libjpeg's `quantize`, by exact reciprocal multiplication.
#[derive(Clone, Copy)]
pub struct IQuant {
    q: IBlock,
    half: IBlock,
    /// ceil(2^32 / (8 Q)) < 2^29.
    recip: [[u32; 8]; 8],
    /// Rows of the 16-bit quantiser, repeated for the two blocks of the AVX2 kernel: 4 Q (the
    /// rounding half), the multiplier m = ceil(2^(14 + l) / (8 Q)) with 2^(l - 1) < 8 Q <= 2^l,
    /// the bias 2^(l - 3) and the scale 2^(17 - l) of the second step, and Q. For 0 <= a < 2^14,
    /// floor(a / (8 Q)) = floor(a m / 2^(14 + l)) (a m / 2^(14 + l) exceeds a / (8 Q) by less
    /// than 2^-l <= 1 / (8 Q)) = floor(t / 2^(l - 2)) with t = (a m) >> 16, and that is
    /// `vpmulhrsw`'s ((t - 2^(l - 3)) 2^(17 - l) + 2^14) >> 15 (see [`quant16`]).
    half_w: [[i16; 16]; 8],
    mul_w: [[u16; 16]; 8],
    bias_w: [[i16; 16]; 8],
    scale_w: [[i16; 16]; 8],
    q_w: [[i16; 16]; 8],
}

impl IQuant {
    pub fn new(table: &[u16; 64]) -> IQuant {
        let mut out = IQuant {
            q: [[0; 8]; 8],
            half: [[0; 8]; 8],
            recip: [[0; 8]; 8],
            half_w: [[0; 16]; 8],
            mul_w: [[0; 16]; 8],
            bias_w: [[0; 16]; 8],
            scale_w: [[0; 16]; 8],
            q_w: [[0; 16]; 8],
        };
        for v in 0..8 {
            for u in 0..8 {
                let qv = table[v * 8 + u] as u64 * 8;
                out.q[v][u] = table[v * 8 + u] as i32;
                out.half[v][u] = (qv / 2) as i32;
                // floor(n / qv) = (n * ceil(2^32 / qv)) >> 32 exactly for n < 2^32 / qv (n < 2^15 here).
                out.recip[v][u] = (1u64 << 32).div_ceil(qv) as u32;
                // Tables are clamped to 1..=255 (baseline), so these fit 16 bits.
                let (m, bias, scale) = quant16(qv.min(2040) as u32);
                for k in [u, u + 8] {
                    out.half_w[v][k] = (qv / 2).min(1020) as i16;
                    out.mul_w[v][k] = m;
                    out.bias_w[v][k] = bias;
                    out.scale_w[v][k] = scale;
                    out.q_w[v][k] = table[v * 8 + u].min(255) as i16;
                }
            }
        }
        out
    }
}

/// Multiplier, bias and scale of the 16-bit quantiser for the divisor `d` = 8 Q (8..=2040):
/// with 2^(l - 1) < d <= 2^l (3 <= l <= 11), m = ceil(2^(14 + l) / d) (2^14..2^15), 2^(l - 3)
/// and 2^(17 - l). (`vpmulhrsw` for the second step, whose shift is per lane: AVX2 has no
/// variable 16-bit shift, and a second `vpmulhuw` is widened to 32 bits by the compiler.)
const fn quant16(d: u32) -> (u16, i16, i16) {
    let l = 32 - (d - 1).leading_zeros();
    (((1u32 << (14 + l)).div_ceil(d)) as u16, (1i32 << (l - 3)) as i16, (1i32 << (17 - l)) as i16)
}

/// Samples (already level-shifted by -128) in, decoded samples (0..=255) out: libjpeg islow
/// forward DCT, quantisation, dequantisation, islow inverse DCT, range limit.
#[inline(always)]
pub fn roundtrip_block_int(b: &mut IBlock, q: &IQuant) {
    itranspose(b);
    fdct_int_pass(b, true);
    itranspose(b);
    fdct_int_pass(b, false);
    // Quantise and dequantise: a = |c| + Q*8/2, level = floor(a / (Q*8)) by the exact reciprocal.
    for v in 0..8 {
        let (c, half, recip, qq) = (b[v], q.half[v], q.recip[v], q.q[v]);
        b[v] = std::array::from_fn(|u| {
            let a = c[u].unsigned_abs() + half[u] as u32;
            let level = ((a as u64 * recip[u] as u64) >> 32) as i32 * qq[u];
            if c[u] < 0 { -level } else { level }
        });
    }
    idct_int_pass(b, CONST_BITS - PASS1_BITS);
    itranspose(b);
    idct_int_pass(b, CONST_BITS + PASS1_BITS + 3);
    itranspose(b);
    for row in b.iter_mut() {
        for v in row.iter_mut() {
            *v = (*v + 128).clamp(0, 255);
        }
    }
}

/// Quantiser in the transposed AAN layout: `div[u][v]` multiplies the forward output, `mul[u][v]`
/// turns the integer level back into the inverse input (including the final 1/8).
#[derive(Clone, Copy)]
pub struct Quant {
    div: Block,
    mul: Block,
}

impl Quant {
    pub fn new(table: &[u16; 64]) -> Quant {
        let s = |k: usize| if k == 0 { 1.0 } else { 2f64.sqrt() * (k as f64 * std::f64::consts::PI / 16.0).cos() };
        let mut div = [[0f32; 8]; 8];
        let mut mul = [[0f32; 8]; 8];
        for u in 0..8 {
            for v in 0..8 {
                // Layout [u][v]: u = horizontal frequency, v = vertical (table row).
                let q = table[v * 8 + u] as f64;
                div[u][v] = (1.0 / (q * s(u) * s(v) * 8.0)) as f32;
                mul[u][v] = (q * s(u) * s(v) / 8.0) as f32;
            }
        }
        Quant { div, mul }
    }
}

/// Level-shifted samples in, decoded level-shifted samples out (rows are image rows).
#[inline(always)]
pub fn roundtrip_block(b: &mut Block, q: &Quant) {
    fdct_pass(b);
    transpose(b);
    fdct_pass(b);
    for (row, (d, m)) in b.iter_mut().zip(q.div.iter().zip(&q.mul)) {
        for ((v, d), m) in row.iter_mut().zip(d).zip(m) {
            *v = round_ne(*v * d) * m;
        }
    }
    idct_pass(b);
    transpose(b);
    idct_pass(b);
}

/// AVX2 implementation of [`roundtrip_block_int`]: the same integer operations on eight lanes
/// at a time (checked against the scalar reference in the tests).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{CONST_BITS, IBlock, IQuant, Lanes, PASS1_BITS, fdct_int_pass, idct_int_pass};
    use std::arch::x86_64::*;

    #[derive(Clone, Copy)]
    pub struct V(__m256i);

    // SAFETY (all methods): only called from `roundtrip`, which runs with AVX2 enabled (its
    // caller checked the CPU); `#[inline(always)]` puts the intrinsics in that context.
    impl Lanes for V {
        #[inline(always)]
        fn add(self, b: Self) -> Self {
            V(unsafe { _mm256_add_epi32(self.0, b.0) })
        }
        #[inline(always)]
        fn sub(self, b: Self) -> Self {
            V(unsafe { _mm256_sub_epi32(self.0, b.0) })
        }
        #[inline(always)]
        fn mul(self, k: i32) -> Self {
            V(unsafe { _mm256_mullo_epi32(self.0, _mm256_set1_epi32(k)) })
        }
        #[inline(always)]
        fn shl(self, n: u32) -> Self {
            V(unsafe { _mm256_sll_epi32(self.0, _mm_cvtsi32_si128(n as i32)) })
        }
        #[inline(always)]
        fn descale(self, n: u32) -> Self {
            unsafe {
                let r = _mm256_add_epi32(self.0, _mm256_set1_epi32(1 << (n - 1)));
                V(_mm256_sra_epi32(r, _mm_cvtsi32_si128(n as i32)))
            }
        }
    }

    #[inline(always)]
    unsafe fn transpose(r: &mut [V; 8]) {
        // SAFETY: AVX2, as every caller of this module's kernels.
        let t = unsafe { crate::faults::kit::transpose8x8_epi32(r.map(|v| v.0)) };
        *r = t.map(V);
    }

    /// Upper 32 bits of the unsigned 32x32-bit products, lane by lane.
    #[inline(always)]
    unsafe fn mulhi_epu32(a: __m256i, b: __m256i) -> __m256i {
        unsafe {
            let even = _mm256_srli_epi64(_mm256_mul_epu32(a, b), 32);
            let odd = _mm256_mul_epu32(_mm256_srli_epi64(a, 32), _mm256_srli_epi64(b, 32));
            _mm256_blend_epi32(even, odd, 0b1010_1010)
        }
    }

    #[target_feature(enable = "avx2")]
    pub unsafe fn roundtrip(b: &mut IBlock, q: &IQuant) {
        unsafe {
            let mut r: [V; 8] = std::array::from_fn(|i| V(_mm256_loadu_si256(b[i].as_ptr() as *const __m256i)));
            transpose(&mut r);
            fdct_int_pass(&mut r, true);
            transpose(&mut r);
            fdct_int_pass(&mut r, false);
            for (v, row) in r.iter_mut().enumerate() {
                let c = row.0;
                let half = _mm256_loadu_si256(q.half[v].as_ptr() as *const __m256i);
                let recip = _mm256_loadu_si256(q.recip[v].as_ptr() as *const __m256i);
                let qq = _mm256_loadu_si256(q.q[v].as_ptr() as *const __m256i);
                let a = _mm256_add_epi32(_mm256_abs_epi32(c), half);
                let level = _mm256_mullo_epi32(mulhi_epu32(a, recip), qq);
                // sign(c) * level (level is 0 where c is 0).
                row.0 = _mm256_sign_epi32(level, c);
            }
            idct_int_pass(&mut r, CONST_BITS - PASS1_BITS);
            transpose(&mut r);
            idct_int_pass(&mut r, CONST_BITS + PASS1_BITS + 3);
            transpose(&mut r);
            let (lo, hi, off) = (_mm256_setzero_si256(), _mm256_set1_epi32(255), _mm256_set1_epi32(128));
            for (i, row) in r.iter().enumerate() {
                let v = _mm256_min_epi32(_mm256_max_epi32(_mm256_add_epi32(row.0, off), lo), hi);
                _mm256_storeu_si256(b[i].as_mut_ptr() as *mut __m256i, v);
            }
        }
    }

    /// Eight i32 lanes (0..=255) to eight bytes.
    #[inline(always)]
    unsafe fn pack8(v: __m256i) -> u64 {
        unsafe {
            let p16 = _mm256_packus_epi32(v, v); // per 128-bit lane: a0..a3 a0..a3
            let p8 = _mm256_packus_epi16(p16, p16); // per lane: a0..a3 x4
            let lo = _mm256_extract_epi32(p8, 0) as u32 as u64;
            let hi = _mm256_extract_epi32(p8, 4) as u32 as u64;
            lo | hi << 32
        }
    }

    /// Weight pair (a, b) for `vpmaddwd`: a on even 16-bit lanes, b on odd ones.
    #[inline(always)]
    fn pair(a: i32, b: i32) -> __m256i {
        debug_assert!(i16::try_from(a).is_ok() && i16::try_from(b).is_ok());
        // SAFETY: only inlined into functions that enable AVX2.
        unsafe { _mm256_set1_epi32((a & 0xffff) | (b << 16)) }
    }

    /// Byte shuffles that pick, in each 128-bit lane, the (r, g) and (b, 0) byte pairs of four
    /// pixels whose red byte is at `first` (+3 per pixel) as 16-bit words.
    const fn pick_pairs(first: usize) -> ([i8; 32], [i8; 32]) {
        let (mut rg, mut b) = ([-1i8; 32], [-1i8; 32]);
        let mut k = 0;
        while k < 8 {
            let p = k % 4;
            rg[4 * k] = (first + 3 * p) as i8;
            rg[4 * k + 2] = (first + 3 * p + 1) as i8;
            b[4 * k] = (first + 3 * p + 2) as i8;
            k += 1;
        }
        (rg, b)
    }
    const PICK_X: ([i8; 32], [i8; 32]) = pick_pairs(0);
    const PICK_Z: ([i8; 32], [i8; 32]) = pick_pairs(4);

    /// AVX2 version of `rgb_to_ycc_row_scalar` (same integers), 16 pixels per step in 16-bit
    /// lanes: the products as `vpmaddwd` of (r, g) and (b, 128) word pairs with 16-bit weights
    /// (the AVX-512 kernel's split), Cb and Cr computed negated so that their rounding constant
    /// is 2^15 as Y's: (x + 2^15 - 1) >> 16 = -((2^15 - x) >> 16) for integers.
    #[target_feature(enable = "avx2")]
    pub unsafe fn rgb_to_ycc_row(src: &[u8], y: &mut [u8], cb: &mut [u8], cr: &mut [u8]) {
        use super::{ONE_HALF, fix};
        let n = y.len().min(cb.len()).min(cr.len()).min(src.len() / 3);
        // SAFETY: 32-byte tables; unaligned loads.
        let ld = |t: &[i8; 32]| unsafe { _mm256_loadu_si256(t.as_ptr() as *const __m256i) };
        let (rg_x, b_x, rg_z, b_z) = (ld(&PICK_X.0), ld(&PICK_X.1), ld(&PICK_Z.0), ld(&PICK_Z.1));
        let c128w = _mm256_set1_epi32(128 << 16);
        // Y = 19595 r + 38470 g + 7471 b + 2^15: g's weight split as 65536 - 27066 (the 65536 g
        // is the (r, g) pair's high word), the rounding as 128 * 256.
        let ky1 = pair(fix(0.299), fix(0.587) - 65536);
        let ky2 = pair(fix(0.114), ONE_HALF / 128);
        let hi16 = _mm256_set1_epi32(0xffff_0000u32 as i32);
        // -(Cb - 128) = (11059 r + 21709 g - 32768 b + 2^15) >> 16.
        let kb1 = pair(fix(0.168_74), fix(0.331_26));
        let kb2 = pair(-fix(0.5), ONE_HALF / 128);
        // -(Cr - 128) = (-32768 r + 27439 g + 5329 b + 2^15) >> 16.
        let kr1 = pair(-fix(0.5), fix(0.418_69));
        let kr2 = pair(fix(0.081_31), ONE_HALF / 128);
        let c128 = _mm256_set1_epi16(128);
        let mut i = 0;
        while i + 16 <= n {
            // Lane 0: pixels i .. i + 8, lane 1: i + 8 .. i + 16; x from each group's first byte,
            // z from its eighth (pixels 4..8 start at byte 12 = 8 + 4).
            // SAFETY: bytes 3i .. 3i + 48 are inside `src` (i + 16 <= n pixels).
            let (x, z) = unsafe {
                let p = src.as_ptr().add(3 * i);
                (
                    _mm256_loadu2_m128i(p.add(24) as *const __m128i, p as *const __m128i),
                    _mm256_loadu2_m128i(p.add(32) as *const __m128i, p.add(8) as *const __m128i),
                )
            };
            let conv = |v: __m256i, rgm: __m256i, bm: __m256i| {
                let rg = _mm256_shuffle_epi8(v, rgm);
                let b = _mm256_or_si256(_mm256_shuffle_epi8(v, bm), c128w);
                let yv = _mm256_add_epi32(
                    _mm256_add_epi32(_mm256_madd_epi16(rg, ky1), _mm256_madd_epi16(b, ky2)),
                    _mm256_and_si256(rg, hi16),
                );
                let cbv = _mm256_add_epi32(_mm256_madd_epi16(rg, kb1), _mm256_madd_epi16(b, kb2));
                let crv = _mm256_add_epi32(_mm256_madd_epi16(rg, kr1), _mm256_madd_epi16(b, kr2));
                (_mm256_srai_epi32::<16>(yv), _mm256_srai_epi32::<16>(cbv), _mm256_srai_epi32::<16>(crv))
            };
            let (y0, cb0, cr0) = conv(x, rg_x, b_x);
            let (y1, cb1, cr1) = conv(z, rg_z, b_z);
            // packs keeps the pixel order: [x0-3 z4-7 | x8-11 z12-15].
            let yw = _mm256_packs_epi32(y0, y1);
            let cbw = _mm256_sub_epi16(c128, _mm256_packs_epi32(cb0, cb1));
            let crw = _mm256_sub_epi16(c128, _mm256_packs_epi32(cr0, cr1));
            let ycb = _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_packus_epi16(yw, cbw));
            let crr = _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_packus_epi16(crw, crw));
            // SAFETY: 16 bytes at i of each output (i + 16 <= n); values are 0..=255.
            unsafe {
                _mm_storeu_si128(y.as_mut_ptr().add(i) as *mut __m128i, _mm256_castsi256_si128(ycb));
                _mm_storeu_si128(cb.as_mut_ptr().add(i) as *mut __m128i, _mm256_extracti128_si256::<1>(ycb));
                _mm_storeu_si128(cr.as_mut_ptr().add(i) as *mut __m128i, _mm256_castsi256_si128(crr));
            }
            i += 16;
        }
        super::rgb_to_ycc_row_scalar(&src[3 * i..3 * n], &mut y[i..n], &mut cb[i..n], &mut cr[i..n]);
    }

    /// Byte shuffles from [r0-7 g0-7] and [b0-7 b0-7] (per 128-bit lane) to the interleaved RGB
    /// bytes `start .. start + 16` of the lane's eight pixels (`start` per lane).
    const fn interleave(start0: usize, start1: usize) -> ([i8; 32], [i8; 32]) {
        let (mut rg, mut b) = ([-1i8; 32], [-1i8; 32]);
        let mut k = 0;
        while k < 32 {
            let j = if k < 16 { start0 + k } else { start1 + k - 16 };
            let (p, c) = (j / 3, j % 3);
            match c {
                0 => rg[k] = p as i8,
                1 => rg[k] = (8 + p) as i8,
                _ => b[k] = p as i8,
            }
            k += 1;
        }
        (rg, b)
    }
    const INTERLEAVE_A: ([i8; 32], [i8; 32]) = interleave(0, 8);
    const INTERLEAVE_B: ([i8; 32], [i8; 32]) = interleave(8, 0);

    /// `(v * k + 2^15) >> 16` in 16-bit lanes for |k| < 2^15: high product plus the carry of the
    /// low half's rounding.
    #[inline(always)]
    fn mul_round(v: __m256i, k: __m256i) -> __m256i {
        // SAFETY: only inlined into functions that enable AVX2.
        unsafe { _mm256_add_epi16(_mm256_mulhi_epi16(v, k), _mm256_srli_epi16::<15>(_mm256_mullo_epi16(v, k))) }
    }

    /// AVX2 version of `ycc_to_rgb_row_scalar` (same integers), 16 pixels per step in 16-bit
    /// lanes (the AVX-512 kernel's split of the products).
    #[target_feature(enable = "avx2")]
    pub unsafe fn ycc_to_rgb_row(y: &[u8], cb: &[u8], cr: &[u8], out: &mut [u8]) {
        use super::{ONE_HALF, fix};
        let n = y.len().min(cb.len()).min(cr.len()).min(out.len() / 3);
        // R = crx + ((26345 crx + 2^15) >> 16)            (91881 = 65536 + 26345)
        // B = 2 cbx + ((-14942 cbx + 2^15) >> 16)         (116130 = 131072 - 14942)
        // G = -crx + ((-22554 cbx + 18734 crx + 2^15) >> 16)   (46802 = 65536 - 18734)
        let kr = _mm256_set1_epi16((fix(1.402) - 65536) as i16);
        let kb = _mm256_set1_epi16((fix(1.772) - 131072) as i16);
        let kg = pair(-fix(0.344_14), 65536 - fix(0.714_14));
        let half = _mm256_set1_epi32(ONE_HALF);
        let c128 = _mm256_set1_epi16(128);
        // SAFETY: 32-byte tables; unaligned loads.
        let ld = |t: &[i8; 32]| unsafe { _mm256_loadu_si256(t.as_ptr() as *const __m256i) };
        let (ia_rg, ia_b, ib_rg, ib_b) =
            (ld(&INTERLEAVE_A.0), ld(&INTERLEAVE_A.1), ld(&INTERLEAVE_B.0), ld(&INTERLEAVE_B.1));
        let mut i = 0;
        while i + 16 <= n {
            // SAFETY: 16 bytes at i of each input (i + 16 <= n).
            let (yv, cbx, crx) = unsafe {
                let ld = |s: &[u8]| _mm256_cvtepu8_epi16(_mm_loadu_si128(s.as_ptr().add(i) as *const __m128i));
                (ld(y), _mm256_sub_epi16(ld(cb), c128), _mm256_sub_epi16(ld(cr), c128))
            };
            let r = _mm256_add_epi16(crx, mul_round(crx, kr));
            let b = _mm256_add_epi16(_mm256_add_epi16(cbx, cbx), mul_round(cbx, kb));
            let g_lo = _mm256_madd_epi16(_mm256_unpacklo_epi16(cbx, crx), kg);
            let g_hi = _mm256_madd_epi16(_mm256_unpackhi_epi16(cbx, crx), kg);
            let g = _mm256_sub_epi16(
                _mm256_packs_epi32(
                    _mm256_srai_epi32::<16>(_mm256_add_epi32(g_lo, half)),
                    _mm256_srai_epi32::<16>(_mm256_add_epi32(g_hi, half)),
                ),
                crx,
            );
            // y + term, range-limited to 0..=255 by the unsigned saturation of the packs.
            let rg = _mm256_packus_epi16(_mm256_add_epi16(yv, r), _mm256_add_epi16(yv, g));
            let bb = _mm256_add_epi16(yv, b);
            let bb = _mm256_packus_epi16(bb, bb);
            let a = _mm256_or_si256(_mm256_shuffle_epi8(rg, ia_rg), _mm256_shuffle_epi8(bb, ia_b));
            let bv = _mm256_or_si256(_mm256_shuffle_epi8(rg, ib_rg), _mm256_shuffle_epi8(bb, ib_b));
            // SAFETY: bytes 3i .. 3i + 48 of `out` exist (i + 16 <= n); a holds output bytes
            // 0..16 and 32..48, bv 8..24 and 24..40 (the overlaps get the same bytes).
            unsafe {
                let o = out.as_mut_ptr().add(3 * i);
                _mm_storeu_si128(o as *mut __m128i, _mm256_castsi256_si128(a));
                _mm_storeu_si128(o.add(8) as *mut __m128i, _mm256_castsi256_si128(bv));
                _mm_storeu_si128(o.add(24) as *mut __m128i, _mm256_extracti128_si256::<1>(bv));
                _mm_storeu_si128(o.add(32) as *mut __m128i, _mm256_extracti128_si256::<1>(a));
            }
            i += 16;
        }
        super::ycc_to_rgb_row_scalar(&y[i..n], &cb[i..n], &cr[i..n], &mut out[3 * i..3 * n]);
    }

    /// AVX2 version of `fancy_row_scalar` (same integers): 16 chroma columns (32 outputs) per
    /// step in 16-bit lanes (column sums are at most 1020); the column sums `cs` are filled only
    /// where the scalar edges read them.
    #[target_feature(enable = "avx2")]
    pub unsafe fn fancy_row(near: &[u8], far: &[u8], cs: &mut [i32], out: &mut [u8]) {
        let n = cs.len();
        let w = out.len();
        if n < 24 || near.len() < n || far.len() < n || w < 2 * n - 1 {
            return super::fancy_row_scalar(near, far, cs, out);
        }
        let (e8, o7) = (_mm256_set1_epi16(8), _mm256_set1_epi16(7));
        let mut c = 1;
        // Columns c .. c + 16 need chroma columns c - 1 .. c + 17 (inside 0..n) and write
        // outputs 2c .. 2c + 32 (inside the row: 2(c + 16) <= 2n - 2 < w).
        while c + 17 <= n {
            // SAFETY: the loads read bytes c - 1 .. c + 17 of `near` and `far` (<= n).
            let (l, t, r) = unsafe {
                let sum = |k: usize| {
                    let a = _mm256_cvtepu8_epi16(_mm_loadu_si128(near.as_ptr().add(k) as *const __m128i));
                    let b = _mm256_cvtepu8_epi16(_mm_loadu_si128(far.as_ptr().add(k) as *const __m128i));
                    _mm256_add_epi16(_mm256_add_epi16(_mm256_add_epi16(a, a), a), b)
                };
                (sum(c - 1), sum(c), sum(c + 1))
            };
            let t3 = _mm256_add_epi16(_mm256_add_epi16(t, t), t);
            let even = _mm256_srli_epi16::<4>(_mm256_add_epi16(_mm256_add_epi16(t3, l), e8));
            let odd = _mm256_srli_epi16::<4>(_mm256_add_epi16(_mm256_add_epi16(t3, r), o7));
            // Little-endian words (even, odd) are the output bytes 2c, 2c + 1.
            let words = _mm256_or_si256(even, _mm256_slli_epi16::<8>(odd));
            // SAFETY: bytes 2c .. 2c + 32 of `out` exist (see above).
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().add(2 * c) as *mut __m256i, words) };
            c += 16;
        }
        // The rest (both edges and the tail) as the scalar reference does it, from the column
        // sums it reads: 0, 1 and c - 1 ...
        for k in (0..2).chain(c - 1..n) {
            cs[k] = 3 * near[k] as i32 + far[k] as i32;
        }
        super::fancy_edges(cs, out, 2 * c);
    }

    /// Round trip of the 8x8 block of `plane` whose top-left sample is `off` (rows `pitch`
    /// apart), in place.
    #[target_feature(enable = "avx2")]
    pub unsafe fn roundtrip_in_plane(plane: &mut [u8], off: usize, pitch: usize, q: &IQuant) {
        if off + 7 * pitch + 8 > plane.len() {
            return;
        }
        let mut b: IBlock = [[0; 8]; 8];
        let c128 = _mm256_set1_epi32(128);
        for (dy, row) in b.iter_mut().enumerate() {
            // SAFETY: the block lies inside `plane` (checked above); unaligned 8-byte load and
            // 32-byte store into the row.
            unsafe {
                let v = _mm256_cvtepu8_epi32(_mm_loadl_epi64(plane.as_ptr().add(off + dy * pitch) as *const __m128i));
                _mm256_storeu_si256(row.as_mut_ptr() as *mut __m256i, _mm256_sub_epi32(v, c128));
            }
        }
        // SAFETY: AVX2 is enabled in this function (the caller checked the CPU).
        unsafe { roundtrip(&mut b, q) };
        for (dy, row) in b.iter().enumerate() {
            // SAFETY: as above; values are in 0..=255 after the range limit.
            unsafe {
                let v = _mm256_loadu_si256(row.as_ptr() as *const __m256i);
                let bytes = pack8(v);
                std::ptr::copy_nonoverlapping(
                    bytes.to_le_bytes().as_ptr(),
                    plane.as_mut_ptr().add(off + dy * pitch),
                    8,
                );
            }
        }
    }
}

/// Scalar reference of [`avx2::roundtrip_in_plane`].
fn roundtrip_in_plane_scalar(plane: &mut [u8], off: usize, pitch: usize, q: &IQuant) {
    let mut b: IBlock = [[0; 8]; 8];
    for (dy, row) in b.iter_mut().enumerate() {
        for (v, &s) in row.iter_mut().zip(&plane[off + dy * pitch..][..8]) {
            *v = s as i32 - 128;
        }
    }
    roundtrip_block_int(&mut b, q);
    for (dy, row) in b.iter().enumerate() {
        for (d, &v) in plane[off + dy * pitch..][..8].iter_mut().zip(row) {
            *d = v as u8;
        }
    }
}

/// The fastest implementation of the in-plane block round trip (all give the same bits).
/// Round trip of the block(s) of a plane at an offset, with the plane's pitch.
type PlaneBlockFn = fn(&mut [u8], usize, usize, &IQuant);

fn plane_block_fn() -> PlaneBlockFn {
    #[cfg(target_arch = "x86_64")]
    if crate::faults::kit::has_avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return |p, o, s, q| unsafe { avx2::roundtrip_in_plane(p, o, s, q) };
    }
    roundtrip_in_plane_scalar
}

/// The fastest implementation of [`roundtrip_block_int`] this CPU runs (all give the same bits).
fn block_fn() -> fn(&mut IBlock, &IQuant) {
    #[cfg(target_arch = "x86_64")]
    if crate::faults::kit::has_avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return |b, q| unsafe { avx2::roundtrip(b, q) };
    }
    roundtrip_block_int
}

/// libjpeg's fixed-point colour conversion (`jccolor.c` / `jdcolor.c`, SCALEBITS = 16). libjpeg
/// tabulates the products `FIX(c) * i`; computing them directly gives the same integers and lets
/// the compiler vectorise whole rows.
const fn fix(x: f64) -> i32 {
    (x * 65536.0 + 0.5) as i32
}
const ONE_HALF: i32 = 1 << 15;
const CBCR_OFFSET: i32 = 128 << 16;

/// Pixels per step of the row conversions: fixed-size planar blocks the compiler vectorises.
const CONV: usize = 16;

#[inline(always)]
fn ycc_of(r: i32, g: i32, b: i32) -> (u8, u8, u8) {
    let y = (fix(0.299) * r + fix(0.587) * g + fix(0.114) * b + ONE_HALF) >> 16;
    let cb = (-fix(0.168_74) * r - fix(0.331_26) * g + fix(0.5) * b + CBCR_OFFSET + ONE_HALF - 1) >> 16;
    let cr = (fix(0.5) * r - fix(0.418_69) * g - fix(0.081_31) * b + CBCR_OFFSET + ONE_HALF - 1) >> 16;
    (y as u8, cb as u8, cr as u8)
}

#[inline(always)]
fn rgb_of(y: i32, cb: i32, cr: i32) -> [u8; 3] {
    let (cbx, crx) = (cb - 128, cr - 128);
    let r = y + ((fix(1.402) * crx + ONE_HALF) >> 16);
    let g = y + ((-fix(0.344_14) * cbx + ONE_HALF - fix(0.714_14) * crx) >> 16);
    let b = y + ((fix(1.772) * cbx + ONE_HALF) >> 16);
    [r.clamp(0, 255) as u8, g.clamp(0, 255) as u8, b.clamp(0, 255) as u8]
}

/// One row RGB -> Y, Cb, Cr (full resolution); `src` holds `y.len()` pixels. Scalar reference.
#[inline(always)]
fn rgb_to_ycc_row_scalar(src: &[u8], y: &mut [u8], cb: &mut [u8], cr: &mut [u8]) {
    let n = y.len().min(cb.len()).min(cr.len()).min(src.len() / 3);
    let mut i = 0;
    while i + CONV <= n {
        let (Ok(s), Ok(yo), Ok(cbo), Ok(cro)) = (
            <&[u8; 3 * CONV]>::try_from(&src[3 * i..3 * (i + CONV)]),
            <&mut [u8; CONV]>::try_from(&mut y[i..i + CONV]),
            <&mut [u8; CONV]>::try_from(&mut cb[i..i + CONV]),
            <&mut [u8; CONV]>::try_from(&mut cr[i..i + CONV]),
        ) else {
            break;
        };
        let r: [i32; CONV] = std::array::from_fn(|k| s[3 * k] as i32);
        let g: [i32; CONV] = std::array::from_fn(|k| s[3 * k + 1] as i32);
        let b: [i32; CONV] = std::array::from_fn(|k| s[3 * k + 2] as i32);
        for k in 0..CONV {
            (yo[k], cbo[k], cro[k]) = ycc_of(r[k], g[k], b[k]);
        }
        i += CONV;
    }
    for k in i..n {
        (y[k], cb[k], cr[k]) = ycc_of(src[3 * k] as i32, src[3 * k + 1] as i32, src[3 * k + 2] as i32);
    }
}

/// One row Y, Cb, Cr -> RGB with libjpeg's range limit. Scalar reference.
#[inline(always)]
fn ycc_to_rgb_row_scalar(y: &[u8], cb: &[u8], cr: &[u8], out: &mut [u8]) {
    let n = y.len().min(cb.len()).min(cr.len()).min(out.len() / 3);
    let mut i = 0;
    while i + CONV <= n {
        let (Ok(yi), Ok(cbi), Ok(cri), Ok(o)) = (
            <&[u8; CONV]>::try_from(&y[i..i + CONV]),
            <&[u8; CONV]>::try_from(&cb[i..i + CONV]),
            <&[u8; CONV]>::try_from(&cr[i..i + CONV]),
            <&mut [u8; 3 * CONV]>::try_from(&mut out[3 * i..3 * (i + CONV)]),
        ) else {
            break;
        };
        let px: [[u8; 3]; CONV] = std::array::from_fn(|k| rgb_of(yi[k] as i32, cbi[k] as i32, cri[k] as i32));
        for k in 0..CONV {
            o[3 * k..3 * k + 3].copy_from_slice(&px[k]);
        }
        i += CONV;
    }
    for k in i..n {
        out[3 * k..3 * k + 3].copy_from_slice(&rgb_of(y[k] as i32, cb[k] as i32, cr[k] as i32));
    }
}

/// Outputs 0, 1 and `from..` of [`fancy_row_scalar`] from the column sums `cs` (the edges and
/// tail the SIMD versions leave to it).
#[cfg(target_arch = "x86_64")]
fn fancy_edges(cs: &[i32], out: &mut [u8], from: usize) {
    let n = cs.len();
    let edge = |x: usize| -> u8 {
        let c = x / 2;
        let this = cs[c];
        let v = if x & 1 == 0 {
            (3 * this + cs[c.saturating_sub(1)] + 8) >> 4
        } else {
            (3 * this + cs[(c + 1).min(n - 1)] + 7) >> 4
        };
        v as u8
    };
    out[0] = edge(0);
    out[1] = edge(1);
    for x in from..out.len() {
        out[x] = edge(x);
    }
}

/// libjpeg's h2v2 "fancy" (triangular) upsampling of one output row: `near` is the chroma row
/// nearest to the output row, `far` the other neighbour; `cs` scratch (column sums), `out` has the
/// output width (`cs.len() = ceil(out.len() / 2)` real chroma columns).
#[inline(always)]
fn fancy_row_scalar(near: &[u8], far: &[u8], cs: &mut [i32], out: &mut [u8]) {
    let n = cs.len();
    for ((c, &a), &b) in cs.iter_mut().zip(near).zip(far) {
        *c = 3 * a as i32 + b as i32;
    }
    // Edges: the missing neighbour is the column itself.
    let edge = |x: usize| -> u8 {
        let c = x / 2;
        let this = cs[c];
        let v = if x & 1 == 0 {
            (3 * this + cs[c.saturating_sub(1)] + 8) >> 4
        } else {
            (3 * this + cs[(c + 1).min(n - 1)] + 7) >> 4
        };
        v as u8
    };
    let w = out.len();
    if n < 3 {
        for x in 0..w {
            out[x] = edge(x);
        }
        return;
    }
    out[0] = edge(0);
    out[1] = edge(1);
    // Interior columns 1..n-1 (both neighbours exist), two outputs each.
    for (pair, win) in out[2..2 * (n - 1)].chunks_exact_mut(2).zip(cs.windows(3)) {
        let t = 3 * win[1];
        pair[0] = ((t + win[0] + 8) >> 4) as u8;
        pair[1] = ((t + win[2] + 7) >> 4) as u8;
    }
    for x in 2 * (n - 1)..w {
        out[x] = edge(x);
    }
}

multiversion! {
    /// libjpeg's h2v2 downsampling: the mean of each 2x2 block with the alternating bias 1, 2, 1,
    /// 2, ... (`out` has half the width of the rows `a` and `b`).
    fn downsample_h2v2<T: Copy>(out: &mut [u8], a: &[u8], b: &[u8], _t: T) {
        for (cx, ((o, pa), pb)) in out.iter_mut().zip(a.chunks_exact(2)).zip(b.chunks_exact(2)).enumerate() {
            let bias = 1 + (cx & 1) as u32;
            let sum = pa[0] as u32 + pa[1] as u32 + pb[0] as u32 + pb[1] as u32;
            *o = ((sum + bias) >> 2) as u8;
        }
    }
}

/// RGB row in; Y, Cb, Cr rows out.
type ToYcc = fn(&[u8], &mut [u8], &mut [u8], &mut [u8]);
/// Y, Cb, Cr rows in; RGB row out.
type ToRgb = fn(&[u8], &[u8], &[u8], &mut [u8]);
/// Near and far chroma rows, column-sum scratch, upsampled row out.
type Fancy = fn(&[u8], &[u8], &mut [i32], &mut [u8]);

/// Row converters of one CPU (AVX2 or the scalar references; the same integers either way).
#[derive(Clone, Copy)]
struct RowFns {
    to_ycc: ToYcc,
    to_rgb: ToRgb,
    fancy: Fancy,
}

fn row_fns() -> RowFns {
    #[cfg(target_arch = "x86_64")]
    if super::kit::has_avx512_vbmi() {
        // SAFETY (all three): the CPU supports AVX-512 F/BW/VL/VBMI (checked just above).
        return RowFns {
            to_ycc: |s, y, b, r| unsafe { avx512::rgb_to_ycc_row(s, y, b, r) },
            to_rgb: |y, b, r, o| unsafe { avx512::ycc_to_rgb_row(y, b, r, o) },
            fancy: |n, f, c, o| unsafe { avx512::fancy_row(n, f, c, o) },
        };
    }
    #[cfg(target_arch = "x86_64")]
    if crate::faults::kit::has_avx2() {
        // SAFETY (all three): the CPU supports AVX2 (checked just above).
        return RowFns {
            to_ycc: |s, y, b, r| unsafe { avx2::rgb_to_ycc_row(s, y, b, r) },
            to_rgb: |y, b, r, o| unsafe { avx2::ycc_to_rgb_row(y, b, r, o) },
            fancy: |n, f, c, o| unsafe { avx2::fancy_row(n, f, c, o) },
        };
    }
    RowFns { to_ycc: rgb_to_ycc_row_scalar, to_rgb: ycc_to_rgb_row_scalar, fancy: fancy_row_scalar }
}

/// The integer DCT round trip of two horizontally adjacent blocks in 16-bit lanes (AVX2), in the
/// manner of libjpeg-turbo's SIMD islow: every product pair of [`fdct_int_pass`] /
/// [`idct_int_pass`] regrouped as `vpmaddwd` of interleaved 16-bit operands with 16-bit
/// constants (integer identities, so the 32-bit sums are the reference's), descaled and packed
/// back to 16 bits (the values fit: samples are -128..=127 and the tables baseline). The
/// quantiser divides by two unsigned 16-bit high products, exact for 0 <= a < 2^14 and
/// 8 <= 8 Q <= 2040 (see [`IQuant`]; checked for every a and Q in the tests).
#[cfg(target_arch = "x86_64")]
mod dct16 {
    use super::{
        CONST_BITS, FIX_0_298631336, FIX_0_390180644, FIX_0_541196100, FIX_0_765366865, FIX_0_899976223,
        FIX_1_175875602, FIX_1_501321110, FIX_1_847759065, FIX_1_961570560, FIX_2_053119869, FIX_2_562915447,
        FIX_3_072711026, IQuant, PASS1_BITS,
    };
    use std::arch::x86_64::*;

    type R = [__m256i; 8];

    // SAFETY (all helpers): `#[inline(always)]` into `roundtrip_pair`, which enables AVX2.
    #[inline(always)]
    fn add(a: __m256i, b: __m256i) -> __m256i {
        unsafe { _mm256_add_epi16(a, b) }
    }
    #[inline(always)]
    fn sub(a: __m256i, b: __m256i) -> __m256i {
        unsafe { _mm256_sub_epi16(a, b) }
    }
    #[inline(always)]
    fn add32(a: (__m256i, __m256i), b: (__m256i, __m256i)) -> (__m256i, __m256i) {
        unsafe { (_mm256_add_epi32(a.0, b.0), _mm256_add_epi32(a.1, b.1)) }
    }
    #[inline(always)]
    fn sub32(a: (__m256i, __m256i), b: (__m256i, __m256i)) -> (__m256i, __m256i) {
        unsafe { (_mm256_sub_epi32(a.0, b.0), _mm256_sub_epi32(a.1, b.1)) }
    }
    /// Interleaved (a, b) pairs, low and high halves of each 128-bit lane.
    #[inline(always)]
    fn pairs(a: __m256i, b: __m256i) -> (__m256i, __m256i) {
        unsafe { (_mm256_unpacklo_epi16(a, b), _mm256_unpackhi_epi16(a, b)) }
    }
    /// a * ka + b * kb in 32 bits for the pairs of [`pairs`].
    #[inline(always)]
    fn madd(p: (__m256i, __m256i), ka: i32, kb: i32) -> (__m256i, __m256i) {
        debug_assert!(i16::try_from(ka).is_ok() && i16::try_from(kb).is_ok());
        unsafe {
            let k = _mm256_set1_epi32((ka & 0xffff) | (kb << 16));
            (_mm256_madd_epi16(p.0, k), _mm256_madd_epi16(p.1, k))
        }
    }
    /// DESCALE(x, n) of both halves, packed back to 16 bits in the original lane order.
    #[inline(always)]
    fn descale(x: (__m256i, __m256i), n: u32) -> __m256i {
        unsafe {
            let r = _mm256_set1_epi32(1 << (n - 1));
            let c = _mm_cvtsi32_si128(n as i32);
            _mm256_packs_epi32(
                _mm256_sra_epi32(_mm256_add_epi32(x.0, r), c),
                _mm256_sra_epi32(_mm256_add_epi32(x.1, r), c),
            )
        }
    }

    const F0298: i32 = FIX_0_298631336;
    const F0390: i32 = FIX_0_390180644;
    const F0541: i32 = FIX_0_541196100;
    const F0765: i32 = FIX_0_765366865;
    const F0899: i32 = FIX_0_899976223;
    const F1175: i32 = FIX_1_175875602;
    const F1501: i32 = FIX_1_501321110;
    const F1847: i32 = FIX_1_847759065;
    const F1961: i32 = FIX_1_961570560;
    const F2053: i32 = FIX_2_053119869;
    const F2562: i32 = FIX_2_562915447;
    const F3072: i32 = FIX_3_072711026;

    /// The odd part shared by both directions: for inputs (x4, x5, x6, x7) (forward: tmp4..tmp7;
    /// inverse: b7, b5, b3, b1) the four sums before descaling, in the order of the forward
    /// outputs 7, 5, 3, 1 (inverse: t0', t1', t2', t3').
    #[inline(always)]
    #[allow(clippy::type_complexity)]
    fn odd(x4: __m256i, x5: __m256i, x6: __m256i, x7: __m256i) -> [(__m256i, __m256i); 4] {
        let z = pairs(add(x4, x6), add(x5, x7));
        let z3 = madd(z, F1175 - F1961, F1175);
        let z4 = madd(z, F1175, F1175 - F0390);
        let a = pairs(x4, x7);
        let c = pairs(x5, x6);
        [
            add32(madd(a, F0298 - F0899, -F0899), z3),
            add32(madd(c, F2053 - F2562, -F2562), z4),
            add32(madd(c, -F2562, F3072 - F2562), z3),
            add32(madd(a, -F0899, F1501 - F0899), z4),
        ]
    }

    /// [`super::fdct_int_pass`] in 16-bit lanes.
    #[inline(always)]
    fn fdct(b: &mut R, pass1: bool) {
        let (tmp0, tmp7) = (add(b[0], b[7]), sub(b[0], b[7]));
        let (tmp1, tmp6) = (add(b[1], b[6]), sub(b[1], b[6]));
        let (tmp2, tmp5) = (add(b[2], b[5]), sub(b[2], b[5]));
        let (tmp3, tmp4) = (add(b[3], b[4]), sub(b[3], b[4]));
        let (tmp10, tmp13) = (add(tmp0, tmp3), sub(tmp0, tmp3));
        let (tmp11, tmp12) = (add(tmp1, tmp2), sub(tmp1, tmp2));
        // SAFETY: AVX2 context (see above).
        unsafe {
            if pass1 {
                b[0] = _mm256_slli_epi16::<{ PASS1_BITS as i32 }>(add(tmp10, tmp11));
                b[4] = _mm256_slli_epi16::<{ PASS1_BITS as i32 }>(sub(tmp10, tmp11));
            } else {
                let r = _mm256_set1_epi16(1 << (PASS1_BITS - 1));
                b[0] = _mm256_srai_epi16::<{ PASS1_BITS as i32 }>(add(add(tmp10, tmp11), r));
                b[4] = _mm256_srai_epi16::<{ PASS1_BITS as i32 }>(add(sub(tmp10, tmp11), r));
            }
        }
        let n = if pass1 { CONST_BITS - PASS1_BITS } else { CONST_BITS + PASS1_BITS };
        let e = pairs(tmp13, tmp12);
        b[2] = descale(madd(e, F0541 + F0765, F0541), n);
        b[6] = descale(madd(e, F0541, F0541 - F1847), n);
        let [o7, o5, o3, o1] = odd(tmp4, tmp5, tmp6, tmp7);
        b[7] = descale(o7, n);
        b[5] = descale(o5, n);
        b[3] = descale(o3, n);
        b[1] = descale(o1, n);
    }

    /// [`super::idct_int_pass`] in 16-bit lanes (32-bit sums), final descale `n`.
    #[inline(always)]
    fn idct(b: &mut R, n: u32) {
        let e = pairs(b[2], b[6]);
        let tmp2 = madd(e, F0541, F0541 - F1847);
        let tmp3 = madd(e, F0541 + F0765, F0541);
        let d = pairs(b[0], b[4]);
        let tmp0 = madd(d, 1 << CONST_BITS, 1 << CONST_BITS);
        let tmp1 = madd(d, 1 << CONST_BITS, -(1 << CONST_BITS));
        let (tmp10, tmp13) = (add32(tmp0, tmp3), sub32(tmp0, tmp3));
        let (tmp11, tmp12) = (add32(tmp1, tmp2), sub32(tmp1, tmp2));
        let [t0, t1, t2, t3] = odd(b[7], b[5], b[3], b[1]);
        b[0] = descale(add32(tmp10, t3), n);
        b[7] = descale(sub32(tmp10, t3), n);
        b[1] = descale(add32(tmp11, t2), n);
        b[6] = descale(sub32(tmp11, t2), n);
        b[2] = descale(add32(tmp12, t1), n);
        b[5] = descale(sub32(tmp12, t1), n);
        b[3] = descale(add32(tmp13, t0), n);
        b[4] = descale(sub32(tmp13, t0), n);
    }

    /// Transpose the 8x8 16-bit block in each 128-bit lane.
    #[inline(always)]
    fn transpose(r: &mut R) {
        // SAFETY: AVX2 context (see above).
        unsafe {
            let a0 = _mm256_unpacklo_epi16(r[0], r[1]);
            let a1 = _mm256_unpackhi_epi16(r[0], r[1]);
            let a2 = _mm256_unpacklo_epi16(r[2], r[3]);
            let a3 = _mm256_unpackhi_epi16(r[2], r[3]);
            let a4 = _mm256_unpacklo_epi16(r[4], r[5]);
            let a5 = _mm256_unpackhi_epi16(r[4], r[5]);
            let a6 = _mm256_unpacklo_epi16(r[6], r[7]);
            let a7 = _mm256_unpackhi_epi16(r[6], r[7]);
            let b0 = _mm256_unpacklo_epi32(a0, a2);
            let b1 = _mm256_unpackhi_epi32(a0, a2);
            let b2 = _mm256_unpacklo_epi32(a1, a3);
            let b3 = _mm256_unpackhi_epi32(a1, a3);
            let b4 = _mm256_unpacklo_epi32(a4, a6);
            let b5 = _mm256_unpackhi_epi32(a4, a6);
            let b6 = _mm256_unpacklo_epi32(a5, a7);
            let b7 = _mm256_unpackhi_epi32(a5, a7);
            r[0] = _mm256_unpacklo_epi64(b0, b4);
            r[1] = _mm256_unpackhi_epi64(b0, b4);
            r[2] = _mm256_unpacklo_epi64(b1, b5);
            r[3] = _mm256_unpackhi_epi64(b1, b5);
            r[4] = _mm256_unpacklo_epi64(b2, b6);
            r[5] = _mm256_unpackhi_epi64(b2, b6);
            r[6] = _mm256_unpacklo_epi64(b3, b7);
            r[7] = _mm256_unpackhi_epi64(b3, b7);
        }
    }

    /// Quantise and dequantise row `v` (both blocks): sign(c) * floor((|c| + 4Q) / 8Q) * Q, the
    /// division by two unsigned high products (see [`IQuant`]).
    #[inline(always)]
    fn quant(c: __m256i, q: &IQuant, v: usize) -> __m256i {
        // SAFETY: AVX2 context; 16-lane table rows (unaligned 32-byte loads).
        unsafe {
            let a = _mm256_add_epi16(_mm256_abs_epi16(c), _mm256_loadu_si256(q.half_w[v].as_ptr() as *const __m256i));
            let t = _mm256_mulhi_epu16(a, _mm256_loadu_si256(q.mul_w[v].as_ptr() as *const __m256i));
            let t = _mm256_sub_epi16(t, _mm256_loadu_si256(q.bias_w[v].as_ptr() as *const __m256i));
            let level = _mm256_mulhrs_epi16(t, _mm256_loadu_si256(q.scale_w[v].as_ptr() as *const __m256i));
            let qq = _mm256_loadu_si256(q.q_w[v].as_ptr() as *const __m256i);
            _mm256_sign_epi16(_mm256_mullo_epi16(level, qq), c)
        }
    }

    /// Round trip of the two 8x8 blocks of `plane` at `off` and `off + 8` (rows `pitch` apart),
    /// in place: the bytes of two calls of [`super::roundtrip_in_plane_scalar`].
    #[target_feature(enable = "avx2")]
    pub unsafe fn roundtrip_pair(plane: &mut [u8], off: usize, pitch: usize, q: &IQuant) {
        if off + 7 * pitch + 16 > plane.len() {
            return;
        }
        let c128 = _mm256_set1_epi16(128);
        let mut r: R = std::array::from_fn(|dy| {
            // SAFETY: bytes off + dy * pitch .. + 16 lie inside `plane` (checked above).
            let v = unsafe { _mm_loadu_si128(plane.as_ptr().add(off + dy * pitch) as *const __m128i) };
            _mm256_sub_epi16(_mm256_cvtepu8_epi16(v), c128)
        });
        transpose(&mut r);
        fdct(&mut r, true);
        transpose(&mut r);
        fdct(&mut r, false);
        for (v, row) in r.iter_mut().enumerate() {
            *row = quant(*row, q, v);
        }
        idct(&mut r, CONST_BITS - PASS1_BITS);
        transpose(&mut r);
        idct(&mut r, CONST_BITS + PASS1_BITS + 3);
        transpose(&mut r);
        for dy in (0..8).step_by(2) {
            // Range limit clamp(v + 128, 0, 255) by the unsigned saturation of the pack, two rows
            // at a time: [A(dy) A(dy + 1) | B(dy) B(dy + 1)] -> [A(dy) B(dy) | A(dy + 1) B(dy + 1)].
            let p = _mm256_packus_epi16(_mm256_add_epi16(r[dy], c128), _mm256_add_epi16(r[dy + 1], c128));
            let p = _mm256_permute4x64_epi64::<0b11_01_10_00>(p);
            // SAFETY: as for the loads.
            unsafe {
                let o = plane.as_mut_ptr().add(off + dy * pitch);
                _mm_storeu_si128(o as *mut __m128i, _mm256_castsi256_si128(p));
                _mm_storeu_si128(o.add(pitch) as *mut __m128i, _mm256_extracti128_si256::<1>(p));
            }
        }
    }
}

/// AVX-512 (BW, VBMI) row converters: the same integers as the scalar references, with the
/// fixed-point products split so that they run in 16-bit lanes (`vpmaddwd`, `vpmulhw`) and
/// byte permutes for the RGB (de-)interleaving.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{CBCR_OFFSET, ONE_HALF, fix};
    use std::arch::x86_64::*;

    /// Weight pair (a, b) for `vpmaddwd`: a on even 16-bit lanes, b on odd ones.
    #[inline(always)]
    fn pair(a: i32, b: i32) -> __m512i {
        debug_assert!(i16::try_from(a).is_ok() && i16::try_from(b).is_ok());
        // SAFETY: only inlined into functions that enable AVX-512F.
        unsafe { _mm512_set1_epi32((a & 0xffff) | (b << 16)) }
    }

    const fn rgb_pick() -> [u8; 64] {
        // Bytes 0..32: r0 g0 r1 g1 .. r15 g15; bytes 32..64: b0 - b1 - .. b15 - (from 48 bytes).
        let mut t = [0u8; 64];
        let mut p = 0;
        while p < 16 {
            t[2 * p] = (3 * p) as u8;
            t[2 * p + 1] = (3 * p + 1) as u8;
            t[32 + 2 * p] = (3 * p + 2) as u8;
            t[32 + 2 * p + 1] = 0;
            p += 1;
        }
        t
    }
    const RGB_PICK: [u8; 64] = rgb_pick();

    /// RGB -> Y, Cb, Cr for 16 pixels per step.
    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub unsafe fn rgb_to_ycc_row(src: &[u8], y: &mut [u8], cb: &mut [u8], cr: &mut [u8]) {
        let n = y.len().min(cb.len()).min(cr.len()).min(src.len() / 3);
        // SAFETY: 64-byte table; unaligned load.
        let pick = unsafe { _mm512_loadu_si512(RGB_PICK.as_ptr() as *const __m512i) };
        let c128 = _mm512_set1_epi8(-128);
        // Odd bytes of the upper half: the constant 128 paired with b.
        let odd_hi: __mmask64 = 0xaaaa_aaaa_0000_0000;
        // Y = 19595 r + 38470 g + 7471 b + 2^15: g's weight split as 65536 - 27066 (the 65536 g
        // comes from the (r, g) pair's high word), the rounding as 128 * 256.
        let ky1 = pair(fix(0.299), fix(0.587) - 65536);
        let ky2 = pair(fix(0.114), ONE_HALF / 128);
        // Cb = -11059 r - 21709 g + 32768 b + CBCR_OFFSET + 2^15 - 1 (32768 b = 2 * 16384 b).
        let kb1 = pair(-fix(0.168_74), -fix(0.331_26));
        let kb2 = pair(fix(0.5) / 2, 0);
        // Cr = 32768 r - 27439 g - 5329 b + CBCR_OFFSET + 2^15 - 1.
        let kr1 = pair(0, -fix(0.418_69));
        let kr1b = pair(fix(0.5) / 2, 0);
        let kr2 = pair(-fix(0.081_31), 0);
        let coff = _mm512_set1_epi32(CBCR_OFFSET + ONE_HALF - 1);
        let hi16 = _mm512_set1_epi32(0xffff_0000u32 as i32);
        let mut i = 0;
        while i + 16 <= n {
            // SAFETY: bytes 3i .. 3i + 48 are inside `src` (masked load of exactly 48 bytes).
            let v = unsafe { _mm512_maskz_loadu_epi8(0xffff_ffff_ffff, src.as_ptr().add(3 * i) as *const i8) };
            let v = _mm512_mask_mov_epi8(_mm512_permutexvar_epi8(pick, v), odd_hi, c128);
            let p1 = _mm512_cvtepu8_epi16(_mm512_castsi512_si256(v)); // (r, g) pairs
            let pb = _mm512_cvtepu8_epi16(_mm512_extracti64x4_epi64::<1>(v)); // (b, 128) pairs
            let yv = _mm512_srai_epi32::<16>(_mm512_add_epi32(
                _mm512_add_epi32(_mm512_madd_epi16(p1, ky1), _mm512_madd_epi16(pb, ky2)),
                _mm512_and_si512(p1, hi16),
            ));
            let cbv = _mm512_srai_epi32::<16>(_mm512_add_epi32(
                _mm512_add_epi32(_mm512_madd_epi16(p1, kb1), _mm512_slli_epi32::<1>(_mm512_madd_epi16(pb, kb2))),
                coff,
            ));
            let crv = _mm512_srai_epi32::<16>(_mm512_add_epi32(
                _mm512_add_epi32(_mm512_madd_epi16(p1, kr1), _mm512_slli_epi32::<1>(_mm512_madd_epi16(p1, kr1b))),
                _mm512_add_epi32(_mm512_madd_epi16(pb, kr2), coff),
            ));
            // SAFETY: 16 bytes at i of each output (i + 16 <= n); values are 0..=255.
            unsafe {
                _mm_storeu_si128(y.as_mut_ptr().add(i) as *mut __m128i, _mm512_cvtepi32_epi8(yv));
                _mm_storeu_si128(cb.as_mut_ptr().add(i) as *mut __m128i, _mm512_cvtepi32_epi8(cbv));
                _mm_storeu_si128(cr.as_mut_ptr().add(i) as *mut __m128i, _mm512_cvtepi32_epi8(crv));
            }
            i += 16;
        }
        super::rgb_to_ycc_row_scalar(&src[3 * i..3 * n], &mut y[i..n], &mut cb[i..n], &mut cr[i..n]);
    }

    const fn interleave(first: usize, len: usize) -> [u8; 64] {
        // Byte j: channel (first + j) % 3 of pixel (first + j) / 3 from [r 0..32 | g 32..64] and
        // b (64..96).
        let mut t = [0u8; 64];
        let mut j = 0;
        while j < len {
            let (p, c) = ((first + j) / 3, (first + j) % 3);
            t[j] = (32 * c + p) as u8;
            j += 1;
        }
        t
    }
    const INTERLEAVE0: [u8; 64] = interleave(0, 64);
    const INTERLEAVE1: [u8; 64] = interleave(64, 32);

    /// `(v * k + 2^15) >> 16` in 16-bit lanes for |k| < 2^15: high product plus the carry of the
    /// low half's rounding.
    #[inline(always)]
    fn mul_round(v: __m512i, k: __m512i) -> __m512i {
        // SAFETY: only inlined into functions that enable AVX-512BW.
        unsafe { _mm512_add_epi16(_mm512_mulhi_epi16(v, k), _mm512_srli_epi16::<15>(_mm512_mullo_epi16(v, k))) }
    }

    /// Y, Cb, Cr -> RGB for 32 pixels per step.
    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub unsafe fn ycc_to_rgb_row(y: &[u8], cb: &[u8], cr: &[u8], out: &mut [u8]) {
        let n = y.len().min(cb.len()).min(cr.len()).min(out.len() / 3);
        // R = crx + ((26345 crx + 2^15) >> 16)            (91881 = 65536 + 26345)
        // B = 2 cbx + ((-14942 cbx + 2^15) >> 16)         (116130 = 131072 - 14942)
        // G = -crx + ((-22554 cbx + 18734 crx + 2^15) >> 16)   (46802 = 65536 - 18734)
        let kr = _mm512_set1_epi16((fix(1.402) - 65536) as i16);
        let kb = _mm512_set1_epi16((fix(1.772) - 131072) as i16);
        let kg = pair(-fix(0.344_14), 65536 - fix(0.714_14));
        let half = _mm512_set1_epi32(ONE_HALF);
        let c128 = _mm512_set1_epi16(128);
        let zero = _mm512_setzero_si512();
        // SAFETY: 64-byte tables; unaligned loads.
        let (il0, il1) = unsafe {
            (
                _mm512_loadu_si512(INTERLEAVE0.as_ptr() as *const __m512i),
                _mm512_loadu_si512(INTERLEAVE1.as_ptr() as *const __m512i),
            )
        };
        let mut i = 0;
        while i + 32 <= n {
            // SAFETY: 32 bytes at i of each input (i + 32 <= n).
            let (yv, cbx, crx) = unsafe {
                let ld = |s: &[u8]| _mm512_cvtepu8_epi16(_mm256_loadu_si256(s.as_ptr().add(i) as *const __m256i));
                (ld(y), _mm512_sub_epi16(ld(cb), c128), _mm512_sub_epi16(ld(cr), c128))
            };
            let r = _mm512_add_epi16(crx, mul_round(crx, kr));
            let b = _mm512_add_epi16(_mm512_add_epi16(cbx, cbx), mul_round(cbx, kb));
            let g_lo = _mm512_madd_epi16(_mm512_unpacklo_epi16(cbx, crx), kg);
            let g_hi = _mm512_madd_epi16(_mm512_unpackhi_epi16(cbx, crx), kg);
            let g = _mm512_sub_epi16(
                _mm512_packs_epi32(
                    _mm512_srai_epi32::<16>(_mm512_add_epi32(g_lo, half)),
                    _mm512_srai_epi32::<16>(_mm512_add_epi32(g_hi, half)),
                ),
                crx,
            );
            // y + term, range-limited to 0..=255 (unsigned saturation after the lower clamp).
            let lim = |t: __m512i| _mm512_cvtusepi16_epi8(_mm512_max_epi16(_mm512_add_epi16(yv, t), zero));
            let rg = _mm512_inserti64x4::<1>(_mm512_castsi256_si512(lim(r)), lim(g));
            let bb = _mm512_castsi256_si512(lim(b));
            // SAFETY: bytes 3i .. 3i + 96 of `out` exist (i + 32 <= n).
            unsafe {
                let o = out.as_mut_ptr().add(3 * i);
                _mm512_storeu_si512(o as *mut __m512i, _mm512_permutex2var_epi8(rg, il0, bb));
                _mm512_mask_storeu_epi8(o.add(64) as *mut i8, 0xffff_ffff, _mm512_permutex2var_epi8(rg, il1, bb));
            }
            i += 32;
        }
        super::ycc_to_rgb_row_scalar(&y[i..n], &cb[i..n], &cr[i..n], &mut out[3 * i..3 * n]);
    }

    /// libjpeg's h2v2 fancy upsampling of one output row, 32 chroma columns (64 outputs) per step
    /// in 16-bit lanes (column sums are at most 1020).
    #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vbmi")]
    pub unsafe fn fancy_row(near: &[u8], far: &[u8], cs: &mut [i32], out: &mut [u8]) {
        let n = cs.len();
        let w = out.len();
        if n < 40 || near.len() < n || far.len() < n || w < 2 * n - 1 {
            return super::fancy_row_scalar(near, far, cs, out);
        }
        for ((c, &a), &b) in cs.iter_mut().zip(near).zip(far) {
            *c = 3 * a as i32 + b as i32;
        }
        let (e8, o7) = (_mm512_set1_epi16(8), _mm512_set1_epi16(7));
        let mut c = 1;
        // Columns c .. c + 32 need chroma columns c - 1 .. c + 33 (inside 0..n) and write
        // outputs 2c .. 2c + 64 (inside the row: 2(c + 32) <= 2n - 2 < w).
        while c + 33 <= n {
            // SAFETY: the loads read bytes c - 1 .. c + 33 of `near` and `far` (<= n).
            let (l, t, r) = unsafe {
                let sum = |k: usize| {
                    let a = _mm512_cvtepu8_epi16(_mm256_loadu_si256(near.as_ptr().add(k) as *const __m256i));
                    let b = _mm512_cvtepu8_epi16(_mm256_loadu_si256(far.as_ptr().add(k) as *const __m256i));
                    _mm512_add_epi16(_mm512_add_epi16(_mm512_add_epi16(a, a), a), b)
                };
                (sum(c - 1), sum(c), sum(c + 1))
            };
            let t3 = _mm512_add_epi16(_mm512_add_epi16(t, t), t);
            let even = _mm512_srli_epi16::<4>(_mm512_add_epi16(_mm512_add_epi16(t3, l), e8));
            let odd = _mm512_srli_epi16::<4>(_mm512_add_epi16(_mm512_add_epi16(t3, r), o7));
            // Little-endian words (even, odd) are the output bytes 2c, 2c + 1.
            let words = _mm512_or_si512(even, _mm512_slli_epi16::<8>(odd));
            // SAFETY: bytes 2c .. 2c + 64 of `out` exist (see above).
            unsafe { _mm512_storeu_si512(out.as_mut_ptr().add(2 * c) as *mut __m512i, words) };
            c += 32;
        }
        // The rest (both edges and the tail) as the scalar reference does it.
        super::fancy_edges(cs, out, 2 * c);
    }
}

/// The effect: tables and padded component planes, kept across frames.
#[derive(Default)]
pub struct Jpeg {
    key: Option<u32>,
    luma: Option<Quant>,
    iluma: Option<IQuant>,
    ichroma: Option<IQuant>,
    // allocation: once per frame size: per band, full-resolution chroma of two rows (encode) and
    // upsampled chroma rows and column sums (decode)
    rows8: Vec<u8>,
    rows32: Vec<i32>,
    // allocation: once per stream (component planes padded to whole MCUs)
    y: Vec<u8>,
    cb: Vec<u8>,
    cr: Vec<u8>,
}

impl Effect for Jpeg {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let quality = p.get("quality") as u32;
        if p.choice("codec") == "encoder" {
            return encoder_roundtrip(frame, quality).map(|_| Outcome::Keep);
        }
        if self.key != Some(quality) {
            self.luma = Some(Quant::new(&scaled_table(&STD_LUMA, quality)));
            self.iluma = Some(IQuant::new(&scaled_table(&STD_LUMA, quality)));
            self.ichroma = Some(IQuant::new(&scaled_table(&STD_CHROMA, quality)));
            self.key = Some(quality);
        }
        let (Some(luma), Some(iluma), Some(ichroma)) = (self.luma, self.iluma, self.ichroma) else {
            return Ok(Outcome::Keep);
        };
        match frame.format {
            PixelFormat::Rgb8 => {
                let sub = p.choice("chroma") != "444";
                self.colour(frame, &iluma, &ichroma, sub);
            }
            PixelFormat::Mono16 => {
                with_image_mut!(frame, img => gray(&mut img, &luma, 257.0));
            }
            _ => {
                let (w, h, stride) = (frame.width as usize, frame.height as usize, frame.stride);
                if let Some(d) = frame.as_u8_mut() {
                    gray8(d, w, h, stride, &iluma);
                }
            }
        }
        Ok(Outcome::Keep)
    }
}

/// Luminance-only round trip with the float DCT (Mono16, at full precision). Edge blocks
/// replicate the last row/column, as libjpeg pads to whole blocks.
fn gray<T: Sample>(img: &mut ImageMut<'_, T>, q: &Quant, scale: f32) {
    let (w, h, stride) = (img.width, img.height, img.stride);
    let used = stride * (h - 1) + w;
    let inv = 1.0 / scale;
    img.data[..used].par_chunks_mut(stride * ROWS_PER_TASK).for_each(|chunk| {
        let rows = chunk.len().div_ceil(stride);
        for by in (0..rows).step_by(8) {
            for bx in (0..w).step_by(8) {
                let mut b: Block = [[0.0; 8]; 8];
                for (dy, brow) in b.iter_mut().enumerate() {
                    let r = &chunk[(by + dy).min(rows - 1) * stride..];
                    for (dx, v) in brow.iter_mut().enumerate() {
                        *v = r[(bx + dx).min(w - 1)].to_f32() * inv - 128.0;
                    }
                }
                roundtrip_block(&mut b, q);
                for (dy, brow) in b.iter().enumerate().take(rows - by) {
                    let r = &mut chunk[(by + dy) * stride..];
                    for (dx, v) in brow.iter().enumerate().take(w - bx) {
                        r[bx + dx] = T::from_f32((v + 128.0) * scale);
                    }
                }
            }
        }
    });
}

/// Mono8 round trip on the frame with libjpeg's integer DCT; edge blocks replicate the last
/// row/column, as libjpeg pads to whole blocks.
fn gray8(data: &mut [u8], w: usize, h: usize, stride: usize, q: &IQuant) {
    let used = stride * (h - 1) + w;
    let (f, fp, pair) = (block_fn(), plane_block_fn(), plane_pair_fn());
    data[..used].par_chunks_mut(stride * ROWS_PER_TASK).for_each(|chunk| {
        let rows = chunk.len().div_ceil(stride);
        for by in (0..rows).step_by(8) {
            let mut next = 0;
            for bx in (0..w).step_by(8) {
                if bx < next {
                    continue;
                }
                if let Some(pair) = pair
                    && bx + 16 <= w
                    && by + 8 <= rows
                {
                    pair(chunk, by * stride + bx, stride, q);
                    next = bx + 16;
                    continue;
                }
                if bx + 8 <= w && by + 8 <= rows {
                    fp(chunk, by * stride + bx, stride, q);
                    continue;
                }
                let mut b: IBlock = [[0; 8]; 8];
                for (dy, brow) in b.iter_mut().enumerate() {
                    let r = &chunk[(by + dy).min(rows - 1) * stride..];
                    if bx + 8 <= w {
                        for (v, s) in brow.iter_mut().zip(&r[bx..bx + 8]) {
                            *v = *s as i32 - 128;
                        }
                    } else {
                        for (dx, v) in brow.iter_mut().enumerate() {
                            *v = r[(bx + dx).min(w - 1)] as i32 - 128;
                        }
                    }
                }
                f(&mut b, q);
                for (dy, brow) in b.iter().enumerate().take(rows - by) {
                    let r = &mut chunk[(by + dy) * stride..];
                    for (dx, v) in brow.iter().enumerate().take(w - bx) {
                        r[bx + dx] = *v as u8;
                    }
                }
            }
        }
    });
}

/// Two horizontally adjacent blocks at once, when this CPU has a kernel for it (the same bits as
/// two calls of [`plane_block_fn`]).
fn plane_pair_fn() -> Option<PlaneBlockFn> {
    #[cfg(target_arch = "x86_64")]
    if crate::faults::kit::has_avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return Some(|p, o, s, q| unsafe { dct16::roundtrip_pair(p, o, s, q) });
    }
    None
}

/// Round trip of the 8x8 blocks of plane rows `r0 .. r0 + 8` (`pw` wide, a multiple of 8).
fn block_row(plane: &mut [u8], r0: usize, pw: usize, q: &IQuant, one: PlaneBlockFn, pair: Option<PlaneBlockFn>) {
    let mut bx = 0;
    if let Some(pair) = pair {
        while bx + 16 <= pw {
            pair(plane, r0 * pw + bx, pw, q);
            bx += 16;
        }
    }
    while bx < pw {
        one(plane, r0 * pw + bx, pw, q);
        bx += 8;
    }
}

/// Decode of one output row: chroma rows (near, far) upsampled (h2v2 fancy) into `up` with the
/// column sums `sums`, or taken as they are (4:4:4, `far` unused), then YCbCr -> RGB into `out`.
#[allow(clippy::too_many_arguments)]
fn decode_row(
    fns: &RowFns,
    sub: bool,
    yrow: &[u8],
    cb: (&[u8], &[u8]),
    cr: (&[u8], &[u8]),
    sums: (&mut [i32], &mut [i32]),
    up: (&mut [u8], &mut [u8]),
    out: &mut [u8],
) {
    if sub {
        (fns.fancy)(cb.0, cb.1, sums.0, up.0);
        (fns.fancy)(cr.0, cr.1, sums.1, up.1);
        (fns.to_rgb)(yrow, up.0, up.1, out);
    } else {
        (fns.to_rgb)(yrow, cb.0, cr.0, out);
    }
}

impl Jpeg {
    /// Rgb8 round trip, one band of `ROWS_PER_TASK` rows per task and one MCU row at a time
    /// inside it (so that the rows of the three planes are still in cache when they are
    /// transformed and decoded): RGB -> YCbCr with edges replicated to whole MCUs and chroma 2x2
    /// averaged with libjpeg's alternating bias (1, 2, 1, 2, ...) or kept (4:4:4); DCT,
    /// quantisation and inverse DCT of the MCU row's blocks; then the output rows whose chroma
    /// neighbours are done (libjpeg h2v2 fancy upsampling and YCbCr -> RGB). The first and last
    /// output rows of a band need the neighbouring bands' chroma and are decoded after all bands.
    fn colour(&mut self, frame: &mut Frame, luma: &IQuant, chroma: &IQuant, sub: bool) {
        let (w, h, stride) = (frame.width as usize, frame.height as usize, frame.stride);
        let mcu = if sub { 16 } else { 8 };
        let (pw, ph) = (w.next_multiple_of(mcu), h.next_multiple_of(mcu));
        let (cw, chh) = if sub { (pw / 2, ph / 2) } else { (pw, ph) };
        self.y.resize(pw * ph, 0);
        self.cb.resize(cw * chh, 0);
        self.cr.resize(cw * chh, 0);
        let nb = ph.div_ceil(ROWS_PER_TASK);
        self.rows8.resize(nb * 4 * pw, 0);
        self.rows32.resize(nb * 2 * pw, 0);
        let Some(data) = frame.as_u8_mut() else {
            return;
        };
        let used = stride * (h - 1) + w * 3;
        let data = &mut data[..used];
        let fns = row_fns();
        let (one, pair) = (plane_block_fn(), plane_pair_fn());
        let csub = if sub { 2 } else { 1 };
        let band_c = ROWS_PER_TASK / csub;
        let (cw_real, ch_real) = if sub { (w.div_ceil(2), h.div_ceil(2)) } else { (w, h) };
        // Chroma rows (near, far) of output row y (absolute; 4:4:4: the row itself).
        let chroma_rows = |y: usize| -> (usize, usize) {
            if !sub {
                return (y, y);
            }
            let cy = y / 2;
            (cy, if y.is_multiple_of(2) { cy.saturating_sub(1) } else { (cy + 1).min(ch_real - 1) })
        };
        data.par_chunks_mut(stride * ROWS_PER_TASK)
            .zip(self.y.par_chunks_mut(pw * ROWS_PER_TASK))
            .zip(self.cb.par_chunks_mut(cw * band_c).zip(self.cr.par_chunks_mut(cw * band_c)))
            .zip(self.rows8.par_chunks_mut(4 * pw).zip(self.rows32.par_chunks_mut(2 * pw)))
            .enumerate()
            .for_each(|(band, (((chunk, yp), (cbp, crp)), (rows, sums)))| {
                let y0 = band * ROWS_PER_TASK;
                let frows = chunk.len().div_ceil(stride);
                let (c0, prows) = (y0 / csub, yp.len() / pw);
                let (cbf, crf) = rows.split_at_mut(2 * pw);
                let (sb, sr) = sums.split_at_mut(pw);
                let (sb, sr) = (&mut sb[..cw_real], &mut sr[..cw_real]);
                for k in 0..prows / mcu {
                    // 1. RGB -> YCbCr of the MCU row (frame rows past the end repeat the last).
                    for cy in k * mcu / csub..(k + 1) * mcu / csub {
                        for j in 0..csub {
                            let dy = cy * csub + j;
                            let sy = (y0 + dy).min(h - 1) - y0;
                            let yrow = &mut yp[dy * pw..(dy + 1) * pw];
                            let (cbk, crk) = (&mut cbf[j * pw..(j + 1) * pw], &mut crf[j * pw..(j + 1) * pw]);
                            (fns.to_ycc)(
                                &chunk[sy * stride..sy * stride + w * 3],
                                &mut yrow[..w],
                                &mut cbk[..w],
                                &mut crk[..w],
                            );
                            let (ly, lb, lr) = (yrow[w - 1], cbk[w - 1], crk[w - 1]);
                            yrow[w..].fill(ly);
                            cbk[w..].fill(lb);
                            crk[w..].fill(lr);
                        }
                        let (cbrow, crrow) = (&mut cbp[cy * cw..(cy + 1) * cw], &mut crp[cy * cw..(cy + 1) * cw]);
                        if sub {
                            let (b0, b1) = cbf.split_at(pw);
                            let (r0, r1) = crf.split_at(pw);
                            downsample_h2v2(cbrow, b0, b1, 0u8);
                            downsample_h2v2(crrow, r0, r1, 0u8);
                        } else {
                            cbrow.copy_from_slice(&cbf[..pw]);
                            crrow.copy_from_slice(&crf[..pw]);
                        }
                    }
                    // 2. DCT, quantisation, inverse DCT of its blocks.
                    for r0 in (k * mcu..(k + 1) * mcu).step_by(8) {
                        block_row(yp, r0, pw, luma, one, pair);
                    }
                    let r0 = k * mcu / csub;
                    block_row(cbp, r0, cw, chroma, one, pair);
                    block_row(crp, r0, cw, chroma, one, pair);
                    // 3. Decode of the output rows whose chroma rows are done: with 4:2:0 the
                    //    MCU row's last output row needs the next MCU row's first chroma row.
                    let (lo, hi) = if sub {
                        ((k * mcu).saturating_sub(1).max(1), ((k + 1) * mcu - 1).min(frows.saturating_sub(1)))
                    } else {
                        (k * mcu, ((k + 1) * mcu).min(frows))
                    };
                    let (ucb, ucr) = (&mut cbf[..w], &mut crf[..w]);
                    for dy in lo..hi {
                        let (near, far) = chroma_rows(y0 + dy);
                        let (n, f) = ((near - c0) * cw, (far - c0) * cw);
                        decode_row(
                            &fns,
                            sub,
                            &yp[dy * pw..][..w],
                            (&cbp[n..n + cw_real], &cbp[f..f + cw_real]),
                            (&crp[n..n + cw_real], &crp[f..f + cw_real]),
                            (&mut *sb, &mut *sr),
                            (&mut *ucb, &mut *ucr),
                            &mut chunk[dy * stride..dy * stride + w * 3],
                        );
                    }
                }
            });
        if !sub {
            return;
        }
        // 4. The first and last output rows of each band (4:2:0), from the whole planes.
        let (yp, cbp, crp) = (&self.y, &self.cb, &self.cr);
        data.par_chunks_mut(stride * ROWS_PER_TASK)
            .zip(self.rows8.par_chunks_mut(4 * pw).zip(self.rows32.par_chunks_mut(2 * pw)))
            .enumerate()
            .for_each(|(band, (chunk, (rows, sums)))| {
                let y0 = band * ROWS_PER_TASK;
                let frows = chunk.len().div_ceil(stride);
                let (ucb, ucr) = rows.split_at_mut(2 * pw);
                let (sb, sr) = sums.split_at_mut(pw);
                for dy in [0, frows - 1].into_iter().take(frows.min(2)) {
                    let (near, far) = chroma_rows(y0 + dy);
                    let (n, f) = (near * cw, far * cw);
                    decode_row(
                        &fns,
                        sub,
                        &yp[(y0 + dy) * pw..][..w],
                        (&cbp[n..n + cw_real], &cbp[f..f + cw_real]),
                        (&crp[n..n + cw_real], &crp[f..f + cw_real]),
                        (&mut sb[..cw_real], &mut sr[..cw_real]),
                        (&mut ucb[..w], &mut ucr[..w]),
                        &mut chunk[dy * stride..dy * stride + w * 3],
                    );
                }
            });
    }
}

fn codec_error(reason: String) -> FaultError {
    FaultError::Failed { effect: INFO.name, reason }
}

/// Real encode/decode with the `image` crate (its encoder: baseline, 4:4:4, libjpeg tables and
/// quality scaling). Allocates per frame (reference path).
fn encoder_roundtrip(frame: &mut Frame, quality: u32) -> Result<(), FaultError> {
    use image::ExtendedColorType;
    let (w, h) = (frame.width, frame.height);
    let packed = frame.to_packed();
    let (bytes, color): (Vec<u8>, ExtendedColorType) = match (&packed.data, frame.format) {
        (FrameData::U8(d), PixelFormat::Rgb8) => (d.clone(), ExtendedColorType::Rgb8),
        (FrameData::U8(d), _) => (d.clone(), ExtendedColorType::L8),
        (FrameData::U16(d), _) => (d.iter().map(|&v| u8::from_f32(v as f32 / 257.0)).collect(), ExtendedColorType::L8),
    };
    let mut encoded = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut encoded, quality as u8)
        .encode(&bytes, w, h, color)
        .map_err(|e| codec_error(format!("encode: {e}")))?;
    let decoded = image::load_from_memory_with_format(&encoded, image::ImageFormat::Jpeg)
        .map_err(|e| codec_error(format!("decode: {e}")))?;
    let ch = frame.channels();
    let out: Vec<u8> = if ch == 3 { decoded.to_rgb8().into_raw() } else { decoded.to_luma8().into_raw() };
    let stride = frame.stride;
    let row = w as usize * ch;
    match &mut frame.data {
        FrameData::U8(d) => {
            for (dst, src) in d.chunks_mut(stride).zip(out.chunks(row)) {
                dst[..row].copy_from_slice(src);
            }
        }
        FrameData::U16(d) => {
            for (dst, src) in d.chunks_mut(stride).zip(out.chunks(row)) {
                for (o, s) in dst[..row].iter_mut().zip(src) {
                    *o = *s as u16 * 257;
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Direct 2-D DCT-II with JPEG normalisation: F(u,v) = 1/4 C(u) C(v) sum f cos cos.
    fn direct_dct(f: &Block) -> [[f64; 8]; 8] {
        let c = |k: usize| if k == 0 { 1.0 / 2f64.sqrt() } else { 1.0 };
        let pi = std::f64::consts::PI;
        let mut out = [[0.0; 8]; 8];
        for (v, orow) in out.iter_mut().enumerate() {
            for (u, o) in orow.iter_mut().enumerate() {
                let mut s = 0.0;
                for (y, frow) in f.iter().enumerate() {
                    for (x, &fv) in frow.iter().enumerate() {
                        s += fv as f64
                            * ((2 * x + 1) as f64 * u as f64 * pi / 16.0).cos()
                            * ((2 * y + 1) as f64 * v as f64 * pi / 16.0).cos();
                    }
                }
                *o = 0.25 * c(u) * c(v) * s;
            }
        }
        out
    }

    fn random_block(r: &mut Rng) -> Block {
        std::array::from_fn(|_| std::array::from_fn(|_| r.range(-128.0, 127.0) as f32))
    }

    #[test]
    fn simd_block_round_trip_equals_the_scalar_reference() {
        #[cfg(target_arch = "x86_64")]
        if crate::faults::kit::has_avx2() {
            let mut r = Rng::new(17);
            for trial in 0..3000 {
                let q = 1 + (trial % 100) as u32;
                let table = if trial % 2 == 0 { &STD_LUMA } else { &STD_CHROMA };
                let iq = IQuant::new(&scaled_table(table, q));
                // Random blocks, flat blocks and extreme checkerboards (largest coefficients).
                let block: IBlock = std::array::from_fn(|y| {
                    std::array::from_fn(|x| match trial % 3 {
                        0 => r.below(256) as i32 - 128,
                        1 => (trial % 256) - 128,
                        _ => {
                            if (x + y) % 2 == 0 {
                                127
                            } else {
                                -128
                            }
                        }
                    })
                });
                let (mut a, mut b) = (block, block);
                roundtrip_block_int(&mut a, &iq);
                // SAFETY: AVX2 is available (checked above).
                unsafe { avx2::roundtrip(&mut b, &iq) };
                assert_eq!(a, b, "trial {trial} quality {q}");
            }
        }
    }

    /// One set of row converters against the scalar references on rows of many lengths.
    fn check_colour_rows(f: RowFns, seed: u64) {
        let mut r = Rng::new(seed);
        for n in (0..100).chain([255, 960, 1921]) {
            let src: Vec<u8> = (0..3 * n).map(|_| r.below(256) as u8).collect();
            let (mut a, mut b) =
                ((vec![0u8; n], vec![0u8; n], vec![0u8; n]), (vec![0u8; n], vec![0u8; n], vec![0u8; n]));
            rgb_to_ycc_row_scalar(&src, &mut a.0, &mut a.1, &mut a.2);
            (f.to_ycc)(&src, &mut b.0, &mut b.1, &mut b.2);
            assert_eq!(a, b, "rgb -> ycc, {n} px");
            let (mut o1, mut o2) = (vec![0u8; 3 * n], vec![0u8; 3 * n]);
            ycc_to_rgb_row_scalar(&src[..n], &src[n..2 * n], &src[2 * n..], &mut o1);
            (f.to_rgb)(&src[..n], &src[n..2 * n], &src[2 * n..], &mut o2);
            assert_eq!(o1, o2, "ycc -> rgb, {n} px");
            let cw = n.div_ceil(2);
            if cw > 0 {
                let (mut c1, mut c2) = (vec![0i32; cw], vec![0i32; cw]);
                let (mut u1, mut u2) = (vec![0u8; n], vec![0u8; n]);
                fancy_row_scalar(&src[..cw], &src[cw..2 * cw], &mut c1, &mut u1);
                (f.fancy)(&src[..cw], &src[cw..2 * cw], &mut c2, &mut u2);
                assert_eq!(u1, u2, "fancy upsampling, {n} px");
            }
        }
    }

    #[test]
    fn simd_colour_rows_equal_the_scalar_references() {
        #[cfg(target_arch = "x86_64")]
        if crate::faults::kit::has_avx2() {
            // SAFETY (all three): AVX2 is available (checked above).
            check_colour_rows(
                RowFns {
                    to_ycc: |s, y, b, r| unsafe { avx2::rgb_to_ycc_row(s, y, b, r) },
                    to_rgb: |y, b, r, o| unsafe { avx2::ycc_to_rgb_row(y, b, r, o) },
                    fancy: |n, f, c, o| unsafe { avx2::fancy_row(n, f, c, o) },
                },
                5,
            );
        }
    }

    #[test]
    fn high_product_quantiser_division_is_exact() {
        for q in 1..=255u32 {
            let d = 8 * q;
            let (m, bias, scale) = quant16(d);
            for a in 0..1u32 << 14 {
                // vpmulhuw, vpsubw, vpmulhrsw.
                let t = ((a * m as u32) >> 16) as i32 - bias as i32;
                let level = ((t * scale as i32) + (1 << 14)) >> 15;
                assert_eq!(level, (a / d) as i32, "a {a}, Q {q}");
            }
        }
    }

    /// The two-block 16-bit kernel gives, for each block, the scalar reference's bytes.
    #[test]
    fn block_pair_round_trip_equals_the_scalar_reference() {
        let Some(pair) = plane_pair_fn() else { return };
        check_pair(pair);
    }

    fn check_pair(pair: PlaneBlockFn) {
        let mut r = Rng::new(23);
        let pitch = 40;
        for trial in 0..2000 {
            let q = 1 + (trial % 100) as u32;
            let table = if trial % 2 == 0 { &STD_LUMA } else { &STD_CHROMA };
            let iq = IQuant::new(&scaled_table(table, q));
            // Random samples, flat areas and checkerboards at the extremes (largest coefficients).
            // Random samples, flat areas, checkerboards and stripes at the extremes (the largest
            // coefficients of every frequency).
            let plane: Vec<u8> = (0..pitch * 9)
                .map(|i| {
                    let (x, y) = (i % pitch, i / pitch);
                    let ext = |on: bool| if on { 255 } else { 0 };
                    match trial % 6 {
                        0 => r.below(256) as u8,
                        1 => (trial % 256) as u8,
                        2 => ext((x + y) % 2 == 0),
                        3 => ext(x % 2 == 0),
                        4 => ext((y / (1 + trial % 4)) % 2 == 0),
                        _ => ext(r.below(2) == 0),
                    }
                })
                .collect();
            let off = 1 + trial % 7;
            let (mut a, mut b) = (plane.clone(), plane);
            roundtrip_in_plane_scalar(&mut a, off, pitch, &iq);
            roundtrip_in_plane_scalar(&mut a, off + 8, pitch, &iq);
            pair(&mut b, off, pitch, &iq);
            assert_eq!(a, b, "trial {trial} quality {q}");
        }
    }

    #[test]
    fn avx512_colour_rows_equal_the_scalar_references() {
        #[cfg(target_arch = "x86_64")]
        if crate::faults::kit::has_avx512_vbmi() {
            // SAFETY (all three): AVX-512 VBMI is available (checked above).
            check_colour_rows(
                RowFns {
                    to_ycc: |s, y, b, r| unsafe { avx512::rgb_to_ycc_row(s, y, b, r) },
                    to_rgb: |y, b, r, o| unsafe { avx512::ycc_to_rgb_row(y, b, r, o) },
                    fancy: |n, f, c, o| unsafe { avx512::fancy_row(n, f, c, o) },
                },
                6,
            );
            // Every (Cb, Cr) pair with extreme and middle luma, and every RGB triple on a grid
            // that includes the ends of the range.
            let cbcr: Vec<(u8, u8)> = (0..=255u8).flat_map(|b| (0..=255u8).map(move |c| (b, c))).collect();
            for yv in [0u8, 1, 77, 128, 200, 254, 255] {
                let yrow = vec![yv; cbcr.len()];
                let cb: Vec<u8> = cbcr.iter().map(|p| p.0).collect();
                let cr: Vec<u8> = cbcr.iter().map(|p| p.1).collect();
                let (mut o1, mut o2) = (vec![0u8; 3 * cbcr.len()], vec![0u8; 3 * cbcr.len()]);
                ycc_to_rgb_row_scalar(&yrow, &cb, &cr, &mut o1);
                // SAFETY: as above.
                unsafe { avx512::ycc_to_rgb_row(&yrow, &cb, &cr, &mut o2) };
                assert_eq!(o1, o2, "ycc -> rgb, all chroma pairs, y = {yv}");
            }
            let grid: Vec<u8> = (0..=255u8).step_by(5).chain([1, 2, 127, 128, 129, 253, 254]).collect();
            let mut src = Vec::new();
            for &r in &grid {
                for &g in &grid {
                    for &b in &grid {
                        src.extend([r, g, b]);
                    }
                }
            }
            let n = src.len() / 3;
            let (mut a, mut b) =
                ((vec![0u8; n], vec![0u8; n], vec![0u8; n]), (vec![0u8; n], vec![0u8; n], vec![0u8; n]));
            rgb_to_ycc_row_scalar(&src, &mut a.0, &mut a.1, &mut a.2);
            // SAFETY: as above.
            unsafe { avx512::rgb_to_ycc_row(&src, &mut b.0, &mut b.1, &mut b.2) };
            assert_eq!(a, b, "rgb -> ycc on the grid");
        }
    }

    #[test]
    fn quality_scaling_matches_libjpeg() {
        assert_eq!(scaled_table(&STD_LUMA, 50), STD_LUMA);
        assert_eq!(scaled_table(&STD_LUMA, 100), [1; 64]);
        assert_eq!(scaled_table(&STD_LUMA, 75)[0], 8); // (16 * 50 + 50) / 100
        assert_eq!(scaled_table(&STD_LUMA, 10)[0], 80); // scale 500 %
        assert_eq!(scaled_table(&STD_CHROMA, 1)[63], 255); // clamped for baseline
    }

    #[test]
    fn aan_dct_matches_the_direct_formula() {
        let mut r = Rng::new(1);
        let s = |k: usize| if k == 0 { 1.0 } else { 2f64.sqrt() * (k as f64 * std::f64::consts::PI / 16.0).cos() };
        for _ in 0..20 {
            let f = random_block(&mut r);
            let want = direct_dct(&f);
            let mut b = f;
            fdct_pass(&mut b);
            transpose(&mut b);
            fdct_pass(&mut b);
            for u in 0..8 {
                for v in 0..8 {
                    let got = b[u][v] as f64 / (8.0 * s(u) * s(v));
                    assert!((got - want[v][u]).abs() < 2e-3, "F({u},{v}) {got} vs {}", want[v][u]);
                }
            }
            // Inverse: with all-ones tables and no rounding, the round trip is the identity.
            let mut b = f;
            fdct_pass(&mut b);
            transpose(&mut b);
            fdct_pass(&mut b);
            let q1 = Quant::new(&[1; 64]);
            for (row, (d, m)) in b.iter_mut().zip(q1.div.iter().zip(&q1.mul)) {
                for ((v, d), m) in row.iter_mut().zip(d).zip(m) {
                    *v = *v * d * m; // no rounding
                }
            }
            idct_pass(&mut b);
            transpose(&mut b);
            idct_pass(&mut b);
            for y in 0..8 {
                for x in 0..8 {
                    assert!((b[y][x] - f[y][x]).abs() < 1e-3, "({x},{y}) {} vs {}", b[y][x], f[y][x]);
                }
            }
        }
    }

    /// Natural-looking test image: smooth shading, edges, fine texture and noise.
    fn natural(fmt: PixelFormat, w: u32, h: u32) -> Frame {
        let mut f = Frame::new(w, h, fmt).unwrap();
        let mut r = Rng::new(8);
        for y in 0..h as usize {
            for x in 0..w as usize {
                let (fx, fy) = (x as f32 / w as f32, y as f32 / h as f32);
                let disc = ((fx - 0.4).powi(2) + (fy - 0.5).powi(2)).sqrt() < 0.3;
                for c in 0..fmt.channels() {
                    let base = if disc { 150.0 + 60.0 * (fx * 9.0 + c as f32).sin() } else { 40.0 + 80.0 * fy };
                    let tex = 12.0 * ((x / 3 + y / 2 + c) % 3) as f32;
                    f.set(x, y, c, (base + tex + 4.0 * r.normal() as f32) * fmt.dn_scale());
                }
            }
        }
        f
    }

    fn run(f: &mut Frame, q: f64, codec: &str, chroma: &str) {
        let mut p = Params::defaults(&INFO);
        p.set("quality", q).unwrap();
        p.set_choice("codec", codec).unwrap();
        p.set_choice("chroma", chroma).unwrap();
        Jpeg::default().apply(f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
    }

    /// (mean abs diff, 99th percentile abs diff) in DN.
    fn diff_stats(a: &Frame, b: &Frame) -> (f64, f64) {
        let mut d: Vec<f64> =
            a.packed_samples_f32().iter().zip(b.packed_samples_f32()).map(|(x, y)| (*x - y).abs() as f64).collect();
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        d.sort_by(f64::total_cmp);
        (mean, d[d.len() * 99 / 100])
    }

    #[test]
    fn model_matches_the_image_crate_codec() {
        // The image crate's encoder is 4:4:4, so compare against the model's 4:4:4 path.
        for fmt in [PixelFormat::Mono8, PixelFormat::Rgb8] {
            for q in [30.0, 75.0, 95.0] {
                let orig = natural(fmt, 123, 77);
                let mut m = orig.clone();
                let mut e = orig.clone();
                run(&mut m, q, "model", "444");
                run(&mut e, q, "encoder", "444");
                let (mean, p99) = diff_stats(&m, &e);
                // The image crate is not libjpeg: its encoder truncates the DCT output before
                // rounding and zune-jpeg's IDCT rounds differently (measured: mean 0.2..1.0 DN,
                // p99 3..7 DN on this image), so the bound is looser than against libjpeg-turbo.
                assert!(mean < 1.5 && p99 <= 8.0, "{fmt} q{q}: model vs image crate mean {mean:.3} p99 {p99}");
                let (err, _) = diff_stats(&m, &orig);
                assert!(err > mean, "{fmt} q{q}: the codec's own error ({err:.2}) dominates the model mismatch");
            }
        }
    }

    #[test]
    fn error_grows_as_quality_drops_and_q100_is_near_identity() {
        for (fmt, chroma) in [(PixelFormat::Mono8, "420"), (PixelFormat::Rgb8, "420"), (PixelFormat::Mono16, "420")] {
            let orig = natural(fmt, 96, 64);
            let mut prev = -1.0;
            for q in [100.0, 95.0, 85.0, 75.0, 50.0, 25.0, 10.0, 1.0] {
                let mut f = orig.clone();
                run(&mut f, q, "model", chroma);
                let (mean, p99) = diff_stats(&f, &orig);
                let mean8 = mean / fmt.dn_scale() as f64;
                if q == 100.0 && fmt != PixelFormat::Rgb8 {
                    assert!(p99 / (fmt.dn_scale() as f64) <= 1.0, "{fmt} q100: p99 {p99}");
                }
                assert!(mean8 > prev, "{fmt}: error must grow as quality drops (q{q}: {mean8:.3} <= {prev:.3})");
                prev = mean8;
            }
        }
    }

    #[test]
    fn model_is_deterministic_and_keeps_padding() {
        let mut d = vec![0u8; 30 * 21];
        let mut r = Rng::new(2);
        d.iter_mut().for_each(|v| *v = r.below(256) as u8);
        for y in 0..21 {
            d[y * 30 + 27..y * 30 + 30].fill(7);
        }
        let f0 = Frame::from_data(9, 21, 30, PixelFormat::Rgb8, FrameData::U8(d)).unwrap();
        let mut a = f0.clone();
        let mut b = f0.clone();
        run(&mut a, 60.0, "model", "420");
        run(&mut b, 60.0, "model", "420");
        assert_eq!(a, b);
        for y in 0..21 {
            assert_eq!(&a.as_u8().unwrap()[y * 30 + 27..y * 30 + 30], &[7, 7, 7]);
        }
    }

    /// libjpeg-turbo (through OpenCV's imencode/imdecode, default 4:2:0, islow DCT, fancy
    /// upsampling): the model reproduces it exactly.
    #[cfg(feature = "opencv")]
    #[test]
    fn model_is_bit_exact_with_libjpeg_turbo_via_opencv() {
        use opencv::core::{Mat, Vector};
        use opencv::imgcodecs;
        use opencv::prelude::*;
        for fmt in [PixelFormat::Rgb8, PixelFormat::Mono8] {
            let (w, h) = (121usize, 75usize);
            let orig = natural(fmt, w as u32, h as u32);
            for q in [5, 40, 75, 92, 100] {
                // OpenCV wants BGR.
                let src: Vec<u8> = match fmt {
                    PixelFormat::Rgb8 => orig.as_u8().unwrap().chunks(3).flat_map(|p| [p[2], p[1], p[0]]).collect(),
                    _ => orig.as_u8().unwrap().to_vec(),
                };
                let m = match fmt {
                    PixelFormat::Rgb8 => Mat::new_rows_cols_with_bytes::<opencv::core::Vec3b>(h as i32, w as i32, &src),
                    _ => Mat::new_rows_cols_with_bytes::<u8>(h as i32, w as i32, &src),
                }
                .unwrap();
                let mut buf = Vector::<u8>::new();
                let params = Vector::<i32>::from_slice(&[imgcodecs::IMWRITE_JPEG_QUALITY, q]);
                imgcodecs::imencode(".jpg", &m, &mut buf, &params).unwrap();
                let flag = if fmt == PixelFormat::Rgb8 { imgcodecs::IMREAD_COLOR } else { imgcodecs::IMREAD_GRAYSCALE };
                let dec = imgcodecs::imdecode(&buf, flag).unwrap();
                let bytes = dec.data_bytes().unwrap();
                let mut real = orig.clone();
                match fmt {
                    PixelFormat::Rgb8 => {
                        for (o, p) in real.as_u8_mut().unwrap().chunks_mut(3).zip(bytes.chunks(3)) {
                            o.copy_from_slice(&[p[2], p[1], p[0]]);
                        }
                    }
                    _ => real.as_u8_mut().unwrap().copy_from_slice(&bytes[..w * h]),
                }
                let mut model = orig.clone();
                run(&mut model, q as f64, "model", "420");
                let (mean, _) = diff_stats(&model, &real);
                let max = model
                    .packed_samples_f32()
                    .iter()
                    .zip(real.packed_samples_f32())
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f32::max);
                assert!(max == 0.0, "{fmt} q{q}: model vs libjpeg-turbo: mean {mean:.4}, max {max}");
            }
        }
    }
}
