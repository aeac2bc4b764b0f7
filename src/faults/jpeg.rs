//! `jpeg`: JPEG compression round trip at a libjpeg quality.
//!
//! The default `codec = model` computes exactly the lossy part of baseline JPEG as libjpeg /
//! libjpeg-turbo perform it — RGB→YCbCr in 16-bit fixed point, 4:2:0 chroma averaging (or 4:4:4),
//! edge replication to whole MCUs, 8x8 DCT, quantisation with the IJG tables scaled by
//! `jpeg_quality_scaling`, dequantisation, inverse DCT, "fancy" (triangular) chroma upsampling
//! and YCbCr→RGB in fixed point — and skips the entropy coding, which is lossless: the result is
//! what a decoder shows. 8-bit frames use libjpeg's default integer DCTs (`jfdctint` /
//! `jidctint`, "islow") with its rounding, vectorised over the eight columns of a block (AVX2
//! when the CPU has it; integer arithmetic, so the bits do not depend on the path): the output
//! is bit-identical to libjpeg-turbo's encode/decode (tested against OpenCV's imencode/imdecode).
//! Mono16 uses the AAN float DCT (`jfdctflt` / `jidctflt`) at full precision. `codec = encoder`
//! runs a real encode/decode through the `image` crate instead (reference; allocates per frame).

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

#[inline(always)]
fn iadd(a: IRow, b: IRow) -> IRow {
    std::array::from_fn(|i| a[i] + b[i])
}
#[inline(always)]
fn isub(a: IRow, b: IRow) -> IRow {
    std::array::from_fn(|i| a[i] - b[i])
}
#[inline(always)]
fn imul(a: IRow, k: i32) -> IRow {
    a.map(|v| v * k)
}
/// DESCALE(x, n): add one half, arithmetic shift right.
#[inline(always)]
fn descale(a: IRow, n: u32) -> IRow {
    a.map(|v| (v + (1 << (n - 1))) >> n)
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
fn fdct_int_pass(b: &mut IBlock, pass1: bool) {
    let tmp0 = iadd(b[0], b[7]);
    let tmp7 = isub(b[0], b[7]);
    let tmp1 = iadd(b[1], b[6]);
    let tmp6 = isub(b[1], b[6]);
    let tmp2 = iadd(b[2], b[5]);
    let tmp5 = isub(b[2], b[5]);
    let tmp3 = iadd(b[3], b[4]);
    let tmp4 = isub(b[3], b[4]);
    let tmp10 = iadd(tmp0, tmp3);
    let tmp13 = isub(tmp0, tmp3);
    let tmp11 = iadd(tmp1, tmp2);
    let tmp12 = isub(tmp1, tmp2);
    if pass1 {
        b[0] = iadd(tmp10, tmp11).map(|v| v << PASS1_BITS);
        b[4] = isub(tmp10, tmp11).map(|v| v << PASS1_BITS);
    } else {
        b[0] = descale(iadd(tmp10, tmp11), PASS1_BITS);
        b[4] = descale(isub(tmp10, tmp11), PASS1_BITS);
    }
    let n = if pass1 { CONST_BITS - PASS1_BITS } else { CONST_BITS + PASS1_BITS };
    let z1 = imul(iadd(tmp12, tmp13), FIX_0_541196100);
    b[2] = descale(iadd(z1, imul(tmp13, FIX_0_765366865)), n);
    b[6] = descale(iadd(z1, imul(tmp12, -FIX_1_847759065)), n);
    // Odd part.
    let z1 = iadd(tmp4, tmp7);
    let z2 = iadd(tmp5, tmp6);
    let z3 = iadd(tmp4, tmp6);
    let z4 = iadd(tmp5, tmp7);
    let z5 = imul(iadd(z3, z4), FIX_1_175875602);
    let tmp4 = imul(tmp4, FIX_0_298631336);
    let tmp5 = imul(tmp5, FIX_2_053119869);
    let tmp6 = imul(tmp6, FIX_3_072711026);
    let tmp7 = imul(tmp7, FIX_1_501321110);
    let z1 = imul(z1, -FIX_0_899976223);
    let z2 = imul(z2, -FIX_2_562915447);
    let z3 = iadd(imul(z3, -FIX_1_961570560), z5);
    let z4 = iadd(imul(z4, -FIX_0_390180644), z5);
    b[7] = descale(iadd(iadd(tmp4, z1), z3), n);
    b[5] = descale(iadd(iadd(tmp5, z2), z4), n);
    b[3] = descale(iadd(iadd(tmp6, z2), z3), n);
    b[1] = descale(iadd(iadd(tmp7, z1), z4), n);
}

/// libjpeg's integer inverse DCT (jidctint) along the first index; `n` is the final descale
/// (CONST_BITS - PASS1_BITS after pass 1, CONST_BITS + PASS1_BITS + 3 after pass 2).
#[inline(always)]
fn idct_int_pass(b: &mut IBlock, n: u32) {
    let z1 = imul(iadd(b[2], b[6]), FIX_0_541196100);
    let tmp2 = iadd(z1, imul(b[6], -FIX_1_847759065));
    let tmp3 = iadd(z1, imul(b[2], FIX_0_765366865));
    let tmp0 = iadd(b[0], b[4]).map(|v| v << CONST_BITS);
    let tmp1 = isub(b[0], b[4]).map(|v| v << CONST_BITS);
    let tmp10 = iadd(tmp0, tmp3);
    let tmp13 = isub(tmp0, tmp3);
    let tmp11 = iadd(tmp1, tmp2);
    let tmp12 = isub(tmp1, tmp2);
    // Odd part.
    let (t0, t1, t2, t3) = (b[7], b[5], b[3], b[1]);
    let z1 = iadd(t0, t3);
    let z2 = iadd(t1, t2);
    let z3 = iadd(t0, t2);
    let z4 = iadd(t1, t3);
    let z5 = imul(iadd(z3, z4), FIX_1_175875602);
    let z1 = imul(z1, -FIX_0_899976223);
    let z2 = imul(z2, -FIX_2_562915447);
    let z3 = iadd(imul(z3, -FIX_1_961570560), z5);
    let z4 = iadd(imul(z4, -FIX_0_390180644), z5);
    let t0 = iadd(imul(t0, FIX_0_298631336), iadd(z1, z3));
    let t1 = iadd(imul(t1, FIX_2_053119869), iadd(z2, z4));
    let t2 = iadd(imul(t2, FIX_3_072711026), iadd(z2, z3));
    let t3 = iadd(imul(t3, FIX_1_501321110), iadd(z1, z4));
    b[0] = descale(iadd(tmp10, t3), n);
    b[7] = descale(isub(tmp10, t3), n);
    b[1] = descale(iadd(tmp11, t2), n);
    b[6] = descale(isub(tmp11, t2), n);
    b[2] = descale(iadd(tmp12, t1), n);
    b[5] = descale(isub(tmp12, t1), n);
    b[3] = descale(iadd(tmp13, t0), n);
    b[4] = descale(isub(tmp13, t0), n);
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
    recip: [[u64; 8]; 8],
}

impl IQuant {
    pub fn new(table: &[u16; 64]) -> IQuant {
        let mut out = IQuant { q: [[0; 8]; 8], half: [[0; 8]; 8], recip: [[0; 8]; 8] };
        for v in 0..8 {
            for u in 0..8 {
                let qv = table[v * 8 + u] as u64 * 8;
                out.q[v][u] = table[v * 8 + u] as i32;
                out.half[v][u] = (qv / 2) as i32;
                // floor(n / qv) = (n * ceil(2^32 / qv)) >> 32 exactly for n < 2^32 / qv (n < 2^15 here).
                out.recip[v][u] = (1u64 << 32).div_ceil(qv);
            }
        }
        out
    }
}

/// Samples (already level-shifted by -128) in, decoded samples (0..=255) out: libjpeg islow
/// forward DCT, quantisation, dequantisation, islow inverse DCT, range limit.
#[inline(always)]
pub fn roundtrip_block_int(b: &mut IBlock, q: &IQuant) {
    itranspose(b);
    fdct_int_pass(b, true);
    itranspose(b);
    fdct_int_pass(b, false);
    for v in 0..8 {
        for u in 0..8 {
            let c = b[v][u];
            let a = (c.unsigned_abs() as u64 + q.half[v][u] as u64) * q.recip[v][u];
            let level = (a >> 32) as i32;
            b[v][u] = if c < 0 { -level } else { level } * q.q[v][u];
        }
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

/// Block round trip, compiled for AVX2 (same integer arithmetic, so bit-identical output).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn roundtrip_block_int_avx2(b: &mut IBlock, q: &IQuant) {
    roundtrip_block_int(b, q)
}

/// The fastest implementation of [`roundtrip_block_int`] this CPU runs (all give the same bits).
fn block_fn() -> fn(&mut IBlock, &IQuant) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        return |b, q| unsafe { roundtrip_block_int_avx2(b, q) };
    }
    roundtrip_block_int
}

/// Fixed-point colour conversion tables (libjpeg `jccolor.c` / `jdcolor.c`).
struct Color {
    // allocation: once per effect instance (8 x 256 entries)
    ry: Vec<i32>,
    gy: Vec<i32>,
    by: Vec<i32>,
    rcb: Vec<i32>,
    gcb: Vec<i32>,
    bcb: Vec<i32>,
    gcr: Vec<i32>,
    bcr: Vec<i32>,
    cr_r: Vec<i32>,
    cb_b: Vec<i32>,
    cr_g: Vec<i32>,
    cb_g: Vec<i32>,
}

impl Color {
    fn new() -> Color {
        const SB: i32 = 16;
        let fix = |x: f64| (x * (1 << SB) as f64 + 0.5) as i32;
        let half = 1 << (SB - 1);
        let off = 128 << SB;
        let t = |f: &dyn Fn(i32) -> i32| (0..256).map(f).collect::<Vec<i32>>();
        Color {
            ry: t(&|i| fix(0.299) * i),
            gy: t(&|i| fix(0.587) * i),
            by: t(&|i| fix(0.114) * i + half),
            rcb: t(&|i| -fix(0.168_74) * i),
            gcb: t(&|i| -fix(0.331_26) * i),
            bcb: t(&|i| fix(0.5) * i + off + half - 1),
            gcr: t(&|i| -fix(0.418_69) * i),
            bcr: t(&|i| -fix(0.081_31) * i),
            cr_r: t(&|i| (fix(1.402) * (i - 128) + half) >> SB),
            cb_b: t(&|i| (fix(1.772) * (i - 128) + half) >> SB),
            cr_g: t(&|i| -fix(0.714_14) * (i - 128)),
            cb_g: t(&|i| -fix(0.344_14) * (i - 128) + half),
        }
    }
    #[inline(always)]
    fn ycc(&self, r: u8, g: u8, b: u8) -> (u8, u8, u8) {
        let (r, g, b) = (r as usize, g as usize, b as usize);
        let y = (self.ry[r] + self.gy[g] + self.by[b]) >> 16;
        let cb = (self.rcb[r] + self.gcb[g] + self.bcb[b]) >> 16;
        let cr = (self.bcb[r] + self.gcr[g] + self.bcr[b]) >> 16;
        (y as u8, cb as u8, cr as u8)
    }
    #[inline(always)]
    fn rgb(&self, y: u8, cb: u8, cr: u8) -> [u8; 3] {
        let (y, cb, cr) = (y as i32, cb as usize, cr as usize);
        let r = y + self.cr_r[cr];
        let g = y + ((self.cb_g[cb] + self.cr_g[cr]) >> 16);
        let b = y + self.cb_b[cb];
        [r.clamp(0, 255) as u8, g.clamp(0, 255) as u8, b.clamp(0, 255) as u8]
    }
}

/// The effect: tables and padded component planes, kept across frames.
#[derive(Default)]
pub struct Jpeg {
    key: Option<u32>,
    luma: Option<Quant>,
    iluma: Option<IQuant>,
    ichroma: Option<IQuant>,
    color: Option<Color>,
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
    let f = block_fn();
    data[..used].par_chunks_mut(stride * ROWS_PER_TASK).for_each(|chunk| {
        let rows = chunk.len().div_ceil(stride);
        for by in (0..rows).step_by(8) {
            for bx in (0..w).step_by(8) {
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

/// Round trip of a tightly packed u8 plane whose size is a multiple of 8 in both directions.
fn plane_roundtrip(plane: &mut [u8], pw: usize, q: &IQuant) {
    let f = block_fn();
    plane.par_chunks_mut(pw * ROWS_PER_TASK).for_each(|chunk| {
        let rows = chunk.len() / pw;
        for by in (0..rows).step_by(8) {
            for bx in (0..pw).step_by(8) {
                let mut b: IBlock = [[0; 8]; 8];
                for (dy, brow) in b.iter_mut().enumerate() {
                    let r = &chunk[(by + dy) * pw + bx..][..8];
                    for (v, s) in brow.iter_mut().zip(r) {
                        *v = *s as i32 - 128;
                    }
                }
                f(&mut b, q);
                for (dy, brow) in b.iter().enumerate() {
                    let r = &mut chunk[(by + dy) * pw + bx..][..8];
                    for (s, v) in r.iter_mut().zip(brow) {
                        *s = *v as u8;
                    }
                }
            }
        }
    });
}

impl Jpeg {
    fn colour(&mut self, frame: &mut Frame, luma: &IQuant, chroma: &IQuant, sub: bool) {
        let (w, h, stride) = (frame.width as usize, frame.height as usize, frame.stride);
        let mcu = if sub { 16 } else { 8 };
        let (pw, ph) = (w.next_multiple_of(mcu), h.next_multiple_of(mcu));
        let (cw, chh) = if sub { (pw / 2, ph / 2) } else { (pw, ph) };
        self.y.resize(pw * ph, 0);
        self.cb.resize(cw * chh, 0);
        self.cr.resize(cw * chh, 0);
        let color = self.color.get_or_insert_with(Color::new);
        let Some(data) = frame.as_u8_mut() else {
            return;
        };
        let used = stride * (h - 1) + w * 3;
        let data = &mut data[..used];
        // 1. RGB -> YCbCr (+ 2x2 averaging), padded by edge replication.
        let csub = if sub { 2 } else { 1 };
        let band_c = ROWS_PER_TASK / csub;
        {
            let src: &[u8] = data;
            let px = |x: usize, y: usize| {
                let i = y.min(h - 1) * stride + x.min(w - 1) * 3;
                (src[i], src[i + 1], src[i + 2])
            };
            self.y
                .par_chunks_mut(pw * ROWS_PER_TASK)
                .zip(self.cb.par_chunks_mut(cw * band_c).zip(self.cr.par_chunks_mut(cw * band_c)))
                .enumerate()
                .for_each(|(band, (yp, (cbp, crp)))| {
                    let y0 = band * ROWS_PER_TASK;
                    for (dy, yrow) in yp.chunks_mut(pw).enumerate() {
                        for (x, out) in yrow.iter_mut().enumerate() {
                            let (r, g, b) = px(x, y0 + dy);
                            *out = color.ycc(r, g, b).0;
                        }
                    }
                    for (dy, (cbrow, crrow)) in cbp.chunks_mut(cw).zip(crp.chunks_mut(cw)).enumerate() {
                        let yy = y0 + dy * csub;
                        for (cx, (cbo, cro)) in cbrow.iter_mut().zip(crrow.iter_mut()).enumerate() {
                            if sub {
                                let bias = 1 + (cx & 1) as i32; // 1, 2, 1, 2, ...
                                let (mut sb, mut sr) = (bias, bias);
                                for (ox, oy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                                    let (r, g, b) = px(2 * cx + ox, yy + oy);
                                    let (_, cb, cr) = color.ycc(r, g, b);
                                    sb += cb as i32;
                                    sr += cr as i32;
                                }
                                *cbo = (sb >> 2) as u8;
                                *cro = (sr >> 2) as u8;
                            } else {
                                let (r, g, b) = px(cx, yy);
                                let (_, cb, cr) = color.ycc(r, g, b);
                                *cbo = cb;
                                *cro = cr;
                            }
                        }
                    }
                });
        }
        // 2. DCT, quantisation, inverse DCT per component.
        plane_roundtrip(&mut self.y, pw, luma);
        plane_roundtrip(&mut self.cb, cw, chroma);
        plane_roundtrip(&mut self.cr, cw, chroma);
        // 3. Upsample (libjpeg h2v2 fancy) and YCbCr -> RGB.
        let (yp, cbp, crp) = (&self.y, &self.cb, &self.cr);
        let (cw_real, ch_real) = if sub { (w.div_ceil(2), h.div_ceil(2)) } else { (w, h) };
        data.par_chunks_mut(stride * ROWS_PER_TASK).enumerate().for_each(|(band, chunk)| {
            for (dy, row) in chunk.chunks_mut(stride).enumerate() {
                let y = band * ROWS_PER_TASK + dy;
                let yrow = &yp[y * pw..][..w];
                let out = &mut row[..w * 3];
                if !sub {
                    for (x, o) in out.chunks_exact_mut(3).enumerate() {
                        o.copy_from_slice(&color.rgb(yrow[x], cbp[y * cw + x], crp[y * cw + x]));
                    }
                    continue;
                }
                let cy = y / 2;
                let far = if y.is_multiple_of(2) { cy.saturating_sub(1) } else { (cy + 1).min(ch_real - 1) };
                let (n0, n1) = (cy * cw, far * cw);
                let colsum = |p: &[u8], c: usize| 3 * p[n0 + c] as i32 + p[n1 + c] as i32;
                for (x, o) in out.chunks_exact_mut(3).enumerate() {
                    let c = x / 2;
                    let up = |p: &[u8]| -> u8 {
                        let this = colsum(p, c);
                        let v = if cw_real == 1 {
                            (this * 4 + 8 - (x & 1) as i32) >> 4
                        } else if x & 1 == 0 {
                            if c == 0 { (this * 4 + 8) >> 4 } else { (this * 3 + colsum(p, c - 1) + 8) >> 4 }
                        } else if c + 1 >= cw_real {
                            (this * 4 + 7) >> 4
                        } else {
                            (this * 3 + colsum(p, c + 1) + 7) >> 4
                        };
                        v as u8
                    };
                    o.copy_from_slice(&color.rgb(yrow[x], up(cbp), up(crp)));
                }
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
