//! `vertical_glitch` and `horizontal_glitch`: readout / transport glitches that displace bands
//! of columns (up/down) or rows (left/right). A band's content is rolled cyclically inside the
//! band, so it is moved, never altered.

use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, ImageMut, Sample};
use crate::rng::Rng;
use crate::with_image_mut;

const MODEL_V: &str = "count bands of adjacent columns are displaced vertically, each by its own integer offset drawn \
     uniformly in [-max_offset_px, max_offset_px] (new every frame): out(x, y) = in(x, (y - o) mod H) for x in the \
     band, so +o moves the content down and what leaves the bottom re-enters at the top (cyclic roll: the band's \
     content is unchanged, only moved). Band widths are uniform in [min_band_px, max_band_px] (clipped to the \
     frame), positions uniform; bands never overlap (a band that cannot be placed without overlap after 16 draws \
     is skipped). Pixels outside the bands are untouched. count = 0 or max_offset_px = 0 is the identity.";

const MODEL_H: &str = "count bands of adjacent rows are displaced horizontally, each by its own integer offset drawn \
     uniformly in [-max_offset_px, max_offset_px] (new every frame): out(x, y) = in((x - o) mod W, y) for y in the \
     band, so +o moves the content right, cyclically (whole pixels; all channels move together). Band heights are \
     uniform in [min_band_px, max_band_px] (clipped to the frame), positions uniform; bands never overlap (a band \
     that cannot be placed after 16 draws is skipped). Rows outside the bands are untouched. count = 0 or \
     max_offset_px = 0 is the identity.";

const PARAMS: &[ParamSpec] = &[
    ParamSpec::int("count", "bands", 0.0, 64.0, 3.0, "number of displaced bands per frame"),
    ParamSpec::int("max_offset_px", "px", 0.0, 4096.0, 24.0, "largest displacement (px), either sign"),
    ParamSpec::int("min_band_px", "px", 1.0, 4096.0, 8.0, "smallest band width (px)").extra(),
    ParamSpec::int("max_band_px", "px", 1.0, 4096.0, 64.0, "largest band width (px), >= min_band_px").extra(),
];

pub static INFO_VERTICAL: EffectInfo = EffectInfo {
    name: "vertical_glitch",
    stage: Stage::Readout,
    order: 30,
    summary: "bands of columns displaced up/down (cyclic roll inside the band)",
    model: MODEL_V,
    params: PARAMS,
    formats: ALL_FORMATS,
};

pub static INFO_HORIZONTAL: EffectInfo = EffectInfo {
    name: "horizontal_glitch",
    stage: Stage::Readout,
    order: 35,
    summary: "bands of rows displaced left/right (cyclic roll inside the band)",
    model: MODEL_H,
    params: PARAMS,
    formats: ALL_FORMATS,
};

pub fn create_vertical() -> Box<dyn Effect> {
    Box::new(Glitch { vertical: true, bands: Vec::new(), scratch: Scratch::default() })
}

pub fn create_horizontal() -> Box<dyn Effect> {
    Box::new(Glitch { vertical: false, bands: Vec::new(), scratch: Scratch::default() })
}

/// One displaced band: columns (vertical) or rows (horizontal) `start..start + width`, rolled by
/// `offset` px (+ = down / right).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Band {
    pub start: usize,
    pub width: usize,
    pub offset: i64,
}

/// Draw the bands of one frame (the exact plan `apply` uses, given the same generator).
/// `extent` is the frame width (vertical glitch) or height (horizontal glitch).
pub fn plan_bands(
    rng: &mut Rng,
    count: usize,
    max_offset: i64,
    extent: usize,
    min_w: usize,
    max_w: usize,
    out: &mut Vec<Band>,
) {
    out.clear();
    let (lo, hi) = (min_w.min(extent).max(1), max_w.min(extent).max(1));
    for _ in 0..count {
        for _attempt in 0..16 {
            let width = lo + rng.below((hi - lo + 1) as u64) as usize;
            let start = rng.below((extent - width + 1) as u64) as usize;
            let offset = rng.below(2 * max_offset as u64 + 1) as i64 - max_offset;
            if out.iter().all(|b| start + width <= b.start || b.start + b.width <= start) {
                out.push(Band { start, width, offset });
                break;
            }
        }
    }
}

/// One effect type for both directions.
pub struct Glitch {
    vertical: bool,
    // allocation: the band list and the scratch band grow to their largest size once per stream
    bands: Vec<Band>,
    scratch: Scratch,
}

impl Effect for Glitch {
    fn info(&self) -> &'static EffectInfo {
        if self.vertical { &INFO_VERTICAL } else { &INFO_HORIZONTAL }
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let count = p.get("count") as usize;
        let max_offset = p.get("max_offset_px") as i64;
        let (min_w, max_w) = (p.get("min_band_px") as usize, p.get("max_band_px") as usize);
        if min_w > max_w {
            return Err(FaultError::ParamOutOfRange {
                effect: self.info().name,
                param: "max_band_px",
                value: max_w as f64,
                accepted: format!("integer {min_w}..=4096 px (at least min_band_px = {min_w})"),
            });
        }
        if count == 0 || max_offset == 0 {
            return Ok(Outcome::Keep);
        }
        let extent = if self.vertical { frame.width } else { frame.height } as usize;
        plan_bands(&mut ctx.rng, count, max_offset, extent, min_w, max_w, &mut self.bands);
        let vertical = self.vertical;
        let bands = &self.bands;
        let scratch = &mut self.scratch;
        with_image_mut!(frame, img => apply_bands(&mut img, bands, vertical, scratch));
        Ok(Outcome::Keep)
    }
}

/// Scratch band buffers of both sample types.
#[derive(Default)]
struct Scratch {
    u8s: Vec<u8>,
    u16s: Vec<u16>,
}

/// Typed access to the scratch buffer of a sample type.
trait ScratchOf<T> {
    fn buf(&mut self) -> &mut Vec<T>;
}
impl ScratchOf<u8> for Scratch {
    fn buf(&mut self) -> &mut Vec<u8> {
        &mut self.u8s
    }
}
impl ScratchOf<u16> for Scratch {
    fn buf(&mut self) -> &mut Vec<u16> {
        &mut self.u16s
    }
}

/// Roll every band.
fn apply_bands<T: Sample>(img: &mut ImageMut<'_, T>, bands: &[Band], vertical: bool, scratch: &mut Scratch)
where
    Scratch: ScratchOf<T>,
{
    for b in bands {
        if vertical {
            roll_columns(img, b, scratch.buf());
        } else {
            roll_rows(img, b);
        }
    }
}

fn roll_columns<T: Sample>(img: &mut ImageMut<'_, T>, b: &Band, scratch: &mut Vec<T>) {
    let (h, ch) = (img.height, img.channels);
    let (x0, n) = (b.start * ch, b.width * ch);
    let shift = b.offset.rem_euclid(h as i64) as usize;
    if shift == 0 {
        return;
    }
    scratch.clear();
    for y in 0..h {
        scratch.extend_from_slice(&img.row(y)[x0..x0 + n]);
    }
    for y in 0..h {
        let src = (y + h - shift) % h;
        img.row_mut(y)[x0..x0 + n].copy_from_slice(&scratch[src * n..src * n + n]);
    }
}

fn roll_rows<T: Sample>(img: &mut ImageMut<'_, T>, b: &Band) {
    let (w, ch) = (img.width, img.channels);
    let shift = b.offset.rem_euclid(w as i64) as usize;
    if shift == 0 {
        return;
    }
    for y in b.start..b.start + b.width {
        img.row_mut(y).rotate_right(shift * ch);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn textured(fmt: PixelFormat, w: u32, h: u32) -> Frame {
        let mut f = Frame::new(w, h, fmt).unwrap();
        let mut r = Rng::new(11);
        for y in 0..h as usize {
            for x in 0..w as usize {
                for c in 0..fmt.channels() {
                    f.set(x, y, c, r.uniform_f32() * fmt.full_scale());
                }
            }
        }
        f
    }

    fn params(info: &'static EffectInfo, count: f64, max: f64) -> Params {
        let mut p = Params::defaults(info);
        p.set("count", count).unwrap();
        p.set("max_offset_px", max).unwrap();
        p.set("min_band_px", 3.0).unwrap();
        p.set("max_band_px", 12.0).unwrap();
        p
    }

    #[test]
    fn vertical_bands_are_rolled_copies_and_the_rest_is_untouched() {
        for fmt in [PixelFormat::Mono8, PixelFormat::Mono16, PixelFormat::Rgb8] {
            let (w, h) = (90usize, 60usize);
            let orig = textured(fmt, w as u32, h as u32);
            let mut f = orig.clone();
            let p = params(&INFO_VERTICAL, 4.0, 25.0);
            let mut ctx = EffectCtx::new(9, 3, 0);
            let mut plan = Vec::new();
            plan_bands(&mut ctx.rng.clone(), 4, 25, w, 3, 12, &mut plan);
            assert!(!plan.is_empty());
            assert!(plan.iter().any(|b| b.offset != 0));
            create_vertical().apply(&mut f, &p, &mut ctx).unwrap();
            for x in 0..w {
                let band = plan.iter().find(|b| (b.start..b.start + b.width).contains(&x));
                for y in 0..h {
                    let src_y = match band {
                        Some(b) => (y as i64 - b.offset).rem_euclid(h as i64) as usize,
                        None => y,
                    };
                    for c in 0..fmt.channels() {
                        assert_eq!(f.get(x, y, c), orig.get(x, src_y, c), "{fmt} x {x} y {y}");
                    }
                }
            }
        }
    }

    #[test]
    fn horizontal_bands_are_rolled_copies() {
        let (w, h) = (70usize, 50usize);
        let orig = textured(PixelFormat::Rgb8, w as u32, h as u32);
        let mut f = orig.clone();
        let p = params(&INFO_HORIZONTAL, 5.0, 30.0);
        let mut ctx = EffectCtx::new(4, 8, 1);
        let mut plan = Vec::new();
        plan_bands(&mut ctx.rng.clone(), 5, 30, h, 3, 12, &mut plan);
        create_horizontal().apply(&mut f, &p, &mut ctx).unwrap();
        for y in 0..h {
            let band = plan.iter().find(|b| (b.start..b.start + b.width).contains(&y));
            for x in 0..w {
                let src_x = band.map_or(x, |b| (x as i64 - b.offset).rem_euclid(w as i64) as usize);
                for c in 0..3 {
                    assert_eq!(f.get(x, y, c), orig.get(src_x, y, c));
                }
            }
        }
        // Content is moved, not altered: each row's multiset of pixels is unchanged.
        for y in 0..h {
            let mut a: Vec<f32> = (0..w).map(|x| orig.get(x, y, 0)).collect();
            let mut b: Vec<f32> = (0..w).map(|x| f.get(x, y, 0)).collect();
            a.sort_by(f32::total_cmp);
            b.sort_by(f32::total_cmp);
            assert_eq!(a, b);
        }
    }

    #[test]
    fn bands_do_not_overlap_and_offsets_are_in_range() {
        let mut r = Rng::new(5);
        let mut plan = Vec::new();
        for _ in 0..200 {
            plan_bands(&mut r, 8, 7, 100, 2, 20, &mut plan);
            for (i, a) in plan.iter().enumerate() {
                assert!(a.offset.abs() <= 7 && a.start + a.width <= 100 && (2..=20).contains(&a.width));
                for b in &plan[..i] {
                    assert!(a.start + a.width <= b.start || b.start + b.width <= a.start, "{a:?} {b:?}");
                }
            }
        }
    }

    #[test]
    fn identity_at_zero_and_error_on_bad_widths() {
        let orig = textured(PixelFormat::Mono8, 40, 30);
        for (count, max) in [(0.0, 10.0), (3.0, 0.0)] {
            let mut f = orig.clone();
            create_vertical().apply(&mut f, &params(&INFO_VERTICAL, count, max), &mut EffectCtx::new(1, 0, 0)).unwrap();
            assert_eq!(f, orig);
        }
        let mut p = params(&INFO_VERTICAL, 2.0, 5.0);
        p.set("min_band_px", 20.0).unwrap();
        p.set("max_band_px", 10.0).unwrap();
        let e = create_vertical().apply(&mut orig.clone(), &p, &mut EffectCtx::new(1, 0, 0)).unwrap_err();
        assert!(e.to_string().contains("max_band_px"), "{e}");
    }
}
