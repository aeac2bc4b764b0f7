//! `smear`: frame-transfer / readout smear. While charge is shifted through the sensor, every
//! pixel of a column passes under the bright (saturated) pixels of that column and collects a
//! little extra charge; the result is a uniform streak along the readout direction.

use super::kit::multiversion;
use super::util::ROWS_PER_TASK;
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, ImageMut, Sample};
use crate::with_image_mut;
use rayon::prelude::*;

pub static INFO: EffectInfo = EffectInfo {
    name: "smear",
    stage: Stage::Sensor,
    order: 70,
    summary: "frame-transfer smear: uniform streaks through the columns (or rows) of saturated pixels",
    model: "direction = vertical: n_c = number of saturated samples in column c (v >= sat_level * FS); every \
            sample of column c gains strength * FS * n_c. direction = horizontal: the same along rows. \
            Rgb8: counted and applied per channel (each colour plane has its own columns). The added \
            signal is rounded half up (v' = v + floor(strength*FS*n_c + 0.5)) and clipped to [0, FS]. \
            strength is the smear per saturated pixel as a fraction of full scale (typically the ratio of the \
            per-row transfer time to the exposure time); 0 is the identity, as is a frame with no saturated \
            pixel. When blooming runs first (saturated pixels then read W = full_well_fraction * FS), set \
            sat_level <= blooming.full_well_fraction. well (extra): a photosite at its full well holds no more \
            charge, so a sample at or above round(well * FS) keeps its value (the smear charge of its column \
            overflows); 1 (the default) leaves only samples at FS unchanged, as the clip does.",
    params: &[
        ParamSpec::float("strength", "fraction of FS", 0.0, 0.05, 0.003, "added signal per saturated pixel / FS"),
        ParamSpec::choice(
            "direction",
            &["vertical", "horizontal"],
            0,
            true,
            "readout direction: vertical = column streaks, horizontal = row streaks",
        ),
        ParamSpec::float(
            "sat_level",
            "fraction of FS",
            0.5,
            1.0,
            0.98,
            "a sample counts as saturated when v >= sat_level * FS",
        )
        .extra(),
        ParamSpec::float(
            "well",
            "fraction of FS",
            0.05,
            1.0,
            1.0,
            "a sample at or above well * FS (a full photosite) gains no smear",
        )
        .extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create() -> Box<dyn Effect> {
    Box::new(Smear::default())
}

/// Scratch: per-band partial column counts and per-column offsets.
#[derive(Default)]
pub struct Smear {
    // allocation: once per stream (bands x row length)
    partial: Vec<u32>,
    counts8: Vec<u8>,
    offsets: Vec<u32>,
    offsets8: Vec<u8>,
}

multiversion! {
    /// `cnt[i] += (row[i] >= thr)` (wrapping byte counters).
    fn count_ge_u8<T: Copy>(row: &[u8], thr: u8, cnt: &mut [u8], _t: T) {
        for (c, &v) in cnt.iter_mut().zip(row) {
            *c = c.wrapping_add((v >= thr) as u8);
        }
    }
}

multiversion! {
    /// `row[i] = row[i] + offs[i]`, saturating.
    fn add_sat_u8<T: Copy>(row: &mut [u8], offs: &[u8], _t: T) {
        for (v, &o) in row.iter_mut().zip(offs) {
            *v = v.saturating_add(o);
        }
    }
}

/// Offset added to every sample of a line holding `n` saturated samples.
#[inline]
pub fn offset_dn(n: u32, strength: f64, fs: f64) -> u32 {
    ((n as f64 * strength * fs + 0.5).floor()).min(fs) as u32
}

impl Effect for Smear {
    fn info(&self) -> &'static EffectInfo {
        &INFO
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let strength = p.get("strength");
        if strength <= 0.0 {
            return Ok(Outcome::Keep);
        }
        let fs = frame.format.full_scale() as f64;
        // Smallest integer DN that counts as saturated.
        let thr = (p.get("sat_level") * fs).ceil() as u32;
        let vertical = p.choice("direction") != "horizontal";
        // Level (DN) of a full photosite, which takes no smear charge: FS unless a well below it is set.
        let cap = ((p.get("well") * fs).round() as u32).min(fs as u32);
        let cap = (cap < fs as u32).then_some(cap);
        let s = &mut *self;
        with_image_mut!(frame, img => {
            if vertical {
                s.vertical(&mut img, thr, strength, fs, cap)
            } else {
                horizontal(&mut img, thr, strength, fs, cap)
            }
        });
        Ok(Outcome::Keep)
    }
}

impl Smear {
    fn vertical<T: Sample>(&mut self, img: &mut ImageMut<'_, T>, thr: u32, strength: f64, fs: f64, cap: Option<u32>) {
        let (stride, row_len, h) = (img.stride, img.row_len(), img.height);
        let used = stride * (h - 1) + row_len;
        let bands = h.div_ceil(ROWS_PER_TASK);
        self.partial.clear();
        self.partial.resize(bands * row_len, 0);
        let thr_t = T::from_u32_sat(thr);
        let data = &mut img.data[..used];
        const _: () = assert!(ROWS_PER_TASK <= 255, "8-bit counters per band");
        self.counts8.clear();
        self.counts8.resize(bands * row_len, 0);
        data.par_chunks(stride * ROWS_PER_TASK)
            .zip(self.partial.par_chunks_mut(row_len).zip(self.counts8.par_chunks_mut(row_len)))
            .for_each(|(chunk, (cnt, cnt8))| {
                for row in chunk.chunks(stride) {
                    match T::bytes(&row[..row_len]) {
                        // 8-bit: byte counters (a band has at most 255 rows), widened once.
                        Some(bytes) => count_ge_u8(bytes, thr.min(255) as u8, cnt8, 0u8),
                        None => {
                            for (c, v) in cnt.iter_mut().zip(&row[..row_len]) {
                                *c += (*v >= thr_t) as u32;
                            }
                        }
                    }
                }
                for (c, &k) in cnt.iter_mut().zip(cnt8.iter()) {
                    *c += k as u32;
                }
            });
        self.offsets.clear();
        self.offsets.resize(row_len, 0);
        let mut first = row_len;
        let mut last = 0;
        for (i, o) in self.offsets.iter_mut().enumerate() {
            let n: u32 = (0..bands).map(|b| self.partial[b * row_len + i]).sum();
            if n > 0 {
                *o = offset_dn(n, strength, fs);
                if *o > 0 {
                    first = first.min(i);
                    last = i;
                }
            }
        }
        if first > last {
            return;
        }
        let offs = &self.offsets[first..=last];
        self.offsets8.clear();
        self.offsets8.extend(offs.iter().map(|&o| o.min(255) as u8));
        let offs8 = &self.offsets8;
        data.par_chunks_mut(stride * ROWS_PER_TASK).for_each(|chunk| {
            for row in chunk.chunks_mut(stride) {
                if let Some(cap) = cap {
                    for (v, &o) in row[first..=last].iter_mut().zip(offs) {
                        *v = T::from_u32_sat(add_capped(v.to_u32(), o, cap));
                    }
                    continue;
                }
                match T::bytes_mut(&mut row[first..=last]) {
                    // 8-bit: saturating byte adds (an offset above 255 saturates either way).
                    Some(bytes) => add_sat_u8(bytes, offs8, 0u8),
                    None => {
                        for (v, &o) in row[first..=last].iter_mut().zip(offs) {
                            *v = T::from_u32_sat(v.to_u32() + o);
                        }
                    }
                }
            }
        });
    }
}

/// `v + o`, except that a sample at or above `full` (a photosite at its full well) keeps its value.
#[inline]
fn add_capped(v: u32, o: u32, full: u32) -> u32 {
    if v >= full { v } else { v + o }
}

fn horizontal<T: Sample>(img: &mut ImageMut<'_, T>, thr: u32, strength: f64, fs: f64, cap: Option<u32>) {
    let (stride, row_len, h, ch) = (img.stride, img.row_len(), img.height, img.channels);
    let used = stride * (h - 1) + row_len;
    let thr_t = T::from_u32_sat(thr);
    img.data[..used].par_chunks_mut(stride * ROWS_PER_TASK).for_each(|chunk| {
        for row in chunk.chunks_mut(stride) {
            let row = &mut row[..row_len];
            for c in 0..ch {
                let n = row.iter().skip(c).step_by(ch).filter(|v| **v >= thr_t).count() as u32;
                let o = offset_dn(n, strength, fs);
                if o > 0 {
                    let full = cap.unwrap_or(u32::MAX);
                    row.iter_mut()
                        .skip(c)
                        .step_by(ch)
                        .for_each(|v| *v = T::from_u32_sat(add_capped(v.to_u32(), o, full)));
                }
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;
    use crate::rng::Rng;

    fn scene(fmt: PixelFormat, w: u32, h: u32, seed: u64) -> Frame {
        let mut f = Frame::new(w, h, fmt).unwrap();
        let fs = fmt.full_scale();
        let mut r = Rng::new(seed);
        for y in 0..h as usize {
            for x in 0..w as usize {
                for c in 0..fmt.channels() {
                    f.set(x, y, c, (0.1 + 0.5 * r.uniform_f32()) * fs);
                }
            }
        }
        f
    }

    fn run(f: &mut Frame, strength: f64, dir: &str) {
        let mut p = Params::defaults(&INFO);
        p.set("strength", strength).unwrap();
        p.set_choice("direction", dir).unwrap();
        Smear::default().apply(f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
    }

    #[test]
    fn vertical_smear_only_in_saturated_columns_by_exact_amount() {
        for fmt in [PixelFormat::Mono8, PixelFormat::Mono16, PixelFormat::Rgb8] {
            let mut f = scene(fmt, 96, 80, 1);
            let fs = fmt.full_scale();
            // Saturated spots: 3 pixels in column 10 (all channels), 5 in column 40 (channel 0 only).
            for y in [5, 6, 70] {
                for c in 0..fmt.channels() {
                    f.set(10, y, c, fs);
                }
            }
            for y in 30..35 {
                f.set(40, y, 0, fs);
            }
            let orig = f.clone();
            let strength = 0.01;
            run(&mut f, strength, "vertical");
            let ch = fmt.channels();
            for x in 0..96 {
                for c in 0..ch {
                    let n = (0..80).filter(|&y| orig.get(x, y, c) >= 0.98 * fs).count() as u32;
                    let o = offset_dn(n, strength, fs as f64) as f32;
                    if n > 0 {
                        assert!(o > 0.0);
                    }
                    for y in 0..80 {
                        let want = (orig.get(x, y, c) + o).min(fs);
                        assert_eq!(f.get(x, y, c), want, "{fmt} x {x} y {y} c {c} n {n}");
                    }
                }
            }
            // The exact amount: 3 saturated pixels at 1% of FS.
            assert_eq!(offset_dn(3, strength, fs as f64), (0.03 * fs as f64 + 0.5).floor() as u32);
        }
    }

    #[test]
    fn horizontal_smear_follows_rows() {
        let mut f = scene(PixelFormat::Rgb8, 64, 48, 2);
        for x in [3, 4] {
            f.set(x, 20, 1, 255.0);
        }
        let orig = f.clone();
        run(&mut f, 0.02, "horizontal");
        for y in 0..48 {
            for x in 0..64 {
                for c in 0..3 {
                    let o = if y == 20 && c == 1 { 10.0 } else { 0.0 }; // floor(2 * 0.02 * 255 + 0.5) = 10
                    assert_eq!(f.get(x, y, c), (orig.get(x, y, c) + o).min(255.0));
                }
            }
        }
    }

    /// (h31bloom) A photosite at its full well takes no smear charge: with `well` set, samples at
    /// or above it keep their value and the others gain the column's (row's) smear as before.
    #[test]
    fn full_photosites_take_no_smear() {
        for (fmt, dir) in
            [(PixelFormat::Mono8, "vertical"), (PixelFormat::Mono16, "vertical"), (PixelFormat::Rgb8, "horizontal")]
        {
            let mut f = scene(fmt, 40, 30, 4);
            let fs = fmt.full_scale();
            let well = (0.96 * fs).round();
            // Saturated photosites read the well (as after blooming); one bright sample under it.
            for t in 10..16 {
                for c in 0..fmt.channels() {
                    if dir == "vertical" { f.set(7, t, c, well) } else { f.set(t, 7, c, well) }
                }
            }
            let under = (0.9 * fs).round();
            if dir == "vertical" {
                f.set(7, 3, 0, under)
            } else {
                f.set(3, 7, 0, under)
            }
            let orig = f.clone();
            let mut p = Params::defaults(&INFO);
            p.set("strength", 0.01).unwrap();
            p.set_choice("direction", dir).unwrap();
            p.set("sat_level", 0.955).unwrap();
            p.set("well", 0.96).unwrap();
            Smear::default().apply(&mut f, &p, &mut EffectCtx::new(0, 0, 0)).unwrap();
            let o = offset_dn(6, 0.01, fs as f64) as f32;
            for y in 0..30 {
                for x in 0..40 {
                    for c in 0..fmt.channels() {
                        let line = if dir == "vertical" { x == 7 } else { y == 7 };
                        let v = orig.get(x, y, c);
                        let want = if !line || v >= well { v } else { (v + o).min(fs) };
                        assert_eq!(f.get(x, y, c), want, "{fmt} {dir} x {x} y {y} c {c}");
                    }
                }
            }
        }
    }

    #[test]
    fn identity_without_strength_or_saturation() {
        let mut f = scene(PixelFormat::Mono8, 50, 40, 3);
        let orig = f.clone();
        run(&mut f, 0.02, "vertical");
        assert_eq!(f, orig, "no saturated pixel: identity");
        f.set(5, 5, 0, 255.0);
        let orig = f.clone();
        run(&mut f, 0.0, "vertical");
        assert_eq!(f, orig, "zero strength: identity");
    }

    #[test]
    fn strided_frames_keep_padding() {
        use crate::frame::FrameData;
        let mut d = vec![7u8; 12 * 10];
        for y in 0..10 {
            d[y * 12 + 10] = 99; // padding
            d[y * 12 + 11] = 99;
        }
        d[3 * 12 + 4] = 255;
        let mut f = Frame::from_data(10, 10, 12, PixelFormat::Mono8, FrameData::U8(d)).unwrap();
        run(&mut f, 0.01, "vertical");
        let d = f.as_u8().unwrap();
        for y in 0..10 {
            assert_eq!(d[y * 12 + 10], 99);
            assert_eq!(d[y * 12 + 4], if y == 3 { 255 } else { 10 });
        }
    }
}
