//! Radiation effects (injection): `cosmic_rays` (particle tracks, new every frame), `bit_flip`
//! (single-event upsets in the pixel data) and `dead_pixels` (permanent displacement damage).

use super::kit::{SparsePattern, for_each_bernoulli, par_bands};
use super::{ALL_FORMATS, Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, Sample};
use crate::with_image_mut;

// ---------------------------------------------------------------------------------------------
// cosmic_rays

pub static INFO_COSMIC: EffectInfo = EffectInfo {
    name: "cosmic_rays",
    stage: Stage::Sensor,
    order: 50,
    summary: "charged-particle hits: short bright tracks deposited in the pixels, new every frame",
    model: "The number of hits in a frame is Poisson with mean rate * width * height (rate in hits per \
            pixel per frame; e.g. 5 protons/cm^2/s on 5 um pixels with 0.1 s exposure gives ~1e-7). Each hit \
            has a uniform random centre in the frame and a uniform random direction in [0, 180) deg; it is a \
            straight segment of length track_len_px (the projected path through the depletion layer; \
            0 = a point hit) that deposits charge_dn * FS/255 per pixel of path length (point hits deposit \
            charge_dn into one pixel). The segment is sampled every 1/8 px and each sample is spread \
            bilinearly over its four nearest pixels, so the deposit is anti-aliased and its total is \
            charge_dn * max(track_len_px, 1). v' = min(v + round(deposit), FS) on every channel. \
            rate = 0 or charge_dn = 0 is the identity.",
    params: &[
        ParamSpec::float("rate", "1/px/frame", 0.0, 1e-3, 1e-5, "expected hits per pixel per frame").log(),
        ParamSpec::float("track_len_px", "px", 0.0, 200.0, 8.0, "projected length of each track (0 = point)"),
        ParamSpec::float("charge_dn", "DN", 0.0, 1000.0, 180.0, "deposit per pixel of track length, 8-bit DN").extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create_cosmic() -> Box<dyn Effect> {
    Box::new(CosmicRays::default())
}

#[derive(Default)]
pub struct CosmicRays {
    // allocation: once per (rate, size): room for the deposits of mean + 10 sigma hits
    deposits: Vec<(u32, f32)>,
}

/// Spread `amount` at sub-pixel position (x, y) over the four nearest pixel centres.
fn splat(out: &mut Vec<(u32, f32)>, w: usize, h: usize, x: f32, y: f32, amount: f32) {
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (x0, y0) = (x0 as i64, y0 as i64);
    for (dx, dy, wt) in
        [(0, 0, (1.0 - fx) * (1.0 - fy)), (1, 0, fx * (1.0 - fy)), (0, 1, (1.0 - fx) * fy), (1, 1, fx * fy)]
    {
        let (xx, yy) = (x0 + dx, y0 + dy);
        if wt > 0.0 && xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
            out.push(((yy as usize * w + xx as usize) as u32, amount * wt));
        }
    }
}

impl Effect for CosmicRays {
    fn info(&self) -> &'static EffectInfo {
        &INFO_COSMIC
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO_COSMIC.accepts(frame.format) {
            return Err(super::unsupported(&INFO_COSMIC, frame.format));
        }
        let rate = p.get("rate");
        let len = p.get("track_len_px") as f32;
        let charge = p.get("charge_dn") as f32 * frame.format.dn_scale();
        if rate == 0.0 || charge == 0.0 {
            return Ok(Outcome::Keep);
        }
        let (w, h) = (frame.width as usize, frame.height as usize);
        let mean_hits = rate * (w * h) as f64;
        let hits = ctx.rng.poisson(mean_hits);
        self.deposits.clear();
        // Room for far more hits than a frame will have (mean + 10 sigma + 16: a Poisson count
        // beyond it has probability < 1e-20), so the buffer stops growing after the first frame.
        let per_hit = if len <= 0.0 { 1 } else { 4 * (len * 8.0).ceil() as usize };
        let room = (mean_hits + 10.0 * mean_hits.sqrt() + 16.0) as usize * per_hit;
        self.deposits.reserve(room.max(hits as usize * per_hit));
        for _ in 0..hits {
            let cx = ctx.rng.uniform() as f32 * w as f32 - 0.5;
            let cy = ctx.rng.uniform() as f32 * h as f32 - 0.5;
            let ang = ctx.rng.uniform() as f32 * std::f32::consts::PI;
            if len <= 0.0 {
                // Point hit: the whole charge into the pixel containing the hit.
                let (x, y) = ((cx + 0.5) as usize, (cy + 0.5) as usize);
                self.deposits.push(((y.min(h - 1) * w + x.min(w - 1)) as u32, charge));
                continue;
            }
            let n = (len * 8.0).ceil() as usize;
            let step = len / n as f32;
            let (dx, dy) = (ang.cos(), -ang.sin());
            for i in 0..n {
                let t = -0.5 * len + (i as f32 + 0.5) * step;
                splat(&mut self.deposits, w, h, cx + t * dx, cy + t * dy, charge * step);
            }
        }
        // Sum deposits per pixel (sorted), then add the rounded total once per pixel.
        self.deposits.sort_unstable_by_key(|d| d.0);
        let (stride, ch) = (frame.stride, frame.channels());
        let deps = &self.deposits;
        with_image_mut!(frame, img => {
            let mut i = 0;
            while i < deps.len() {
                let px = deps[i].0;
                let mut total = 0.0f32;
                while i < deps.len() && deps[i].0 == px {
                    total += deps[i].1;
                    i += 1;
                }
                let add = (total + 0.5) as u32;
                let s = (px as usize / w) * stride + (px as usize % w) * ch;
                for v in &mut img.data[s..s + ch] {
                    *v = Sample::from_u32_sat(v.to_u32() + add);
                }
            }
        });
        Ok(Outcome::Keep)
    }
}

// ---------------------------------------------------------------------------------------------
// bit_flip

pub static INFO_BIT_FLIP: EffectInfo = EffectInfo {
    name: "bit_flip",
    stage: Stage::Transmission,
    order: 20,
    summary: "single-event upsets: random bits flipped in the pixel data, new every frame",
    model: "Every sample (one byte of Mono8/Rgb8, one 16-bit word of Mono16) is upset independently with \
            probability `rate` per frame; an upset flips one bit chosen uniformly among the sample's 8 or 16 \
            bits (so the expected fraction of changed samples is exactly `rate`). Rows are processed in bands \
            of 64 with the frame generator's child derive(band), independent of the thread count. \
            rate = 0 is the identity.",
    params: &[ParamSpec::float("rate", "1/sample/frame", 0.0, 0.01, 1e-6, "upset probability per sample").log()],
    formats: ALL_FORMATS,
};

pub fn create_bit_flip() -> Box<dyn Effect> {
    Box::new(BitFlip)
}

pub struct BitFlip;

impl Effect for BitFlip {
    fn info(&self) -> &'static EffectInfo {
        &INFO_BIT_FLIP
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO_BIT_FLIP.accepts(frame.format) {
            return Err(super::unsupported(&INFO_BIT_FLIP, frame.format));
        }
        let rate = p.get("rate");
        if rate == 0.0 {
            return Ok(Outcome::Keep);
        }
        let (stride, height, row_len) = (frame.stride, frame.height as usize, frame.row_len());
        let rng = &ctx.rng;
        with_image_mut!(frame, img => {
            let bits = if std::mem::size_of_val(&img.data[0]) == 1 { 8 } else { 16 };
            par_bands(img.data, stride, height, |k, _, band| {
                let rows = band.len().div_ceil(stride);
                let mut r = rng.derive(k as u64);
                for_each_bernoulli(&mut r, rows * row_len, rate, |i, r| {
                    let s = (i / row_len) * stride + i % row_len;
                    let b = r.below(bits);
                    band[s] = Sample::from_u32_sat(band[s].to_u32() ^ (1 << b));
                });
            });
        });
        Ok(Outcome::Keep)
    }
}

// ---------------------------------------------------------------------------------------------
// dead_pixels

pub static INFO_DEAD: EffectInfo = EffectInfo {
    name: "dead_pixels",
    stage: Stage::Sensor,
    order: 80,
    summary: "permanently dead pixels (displacement damage): fixed pattern reading a constant",
    model: "Each pixel is dead independently with probability `rate` (fixed pattern for the recording from \
            Rng::new(pattern_seed), nested in rate like hot_pixels). A dead pixel reads value_dn * FS/255 \
            (default 0, black) on every channel whatever the light. rate = 0 is the identity.",
    params: &[
        ParamSpec::float("rate", "fraction", 0.0, 0.01, 1e-5, "fraction of dead pixels").log(),
        ParamSpec::float("value_dn", "DN", 0.0, 255.0, 0.0, "value a dead pixel reads, 8-bit DN").extra(),
    ],
    formats: ALL_FORMATS,
};

pub fn create_dead() -> Box<dyn Effect> {
    Box::new(DeadPixels::default())
}

#[derive(Default)]
pub struct DeadPixels {
    pattern: SparsePattern,
}

impl Effect for DeadPixels {
    fn info(&self) -> &'static EffectInfo {
        &INFO_DEAD
    }

    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        if !INFO_DEAD.accepts(frame.format) {
            return Err(super::unsupported(&INFO_DEAD, frame.format));
        }
        let rate = p.get("rate");
        if rate == 0.0 {
            return Ok(Outcome::Keep);
        }
        let value = p.get("value_dn") as f32 * frame.format.dn_scale();
        let (w, stride, ch) = (frame.width as usize, frame.stride, frame.channels());
        let pixels = w * frame.height as usize;
        let dead = self.pattern.ensure(pixels, ctx.pattern_seed, INFO_DEAD.params[0].max, rate);
        with_image_mut!(frame, img => {
            let v = Sample::from_f32(value);
            for &i in dead {
                let s = (i as usize / w) * stride + (i as usize % w) * ch;
                img.data[s..s + ch].fill(v);
            }
        });
        Ok(Outcome::Keep)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PixelFormat;

    fn grey(w: u32, h: u32, format: PixelFormat, v: f32) -> Frame {
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

    fn binomial_ok(count: usize, n: f64, p: f64) -> bool {
        (count as f64 - n * p).abs() < 5.0 * (n * p * (1.0 - p)).sqrt() + 1.0
    }

    #[test]
    fn bit_flips_change_rate_samples_by_one_bit_any_thread_count() {
        let orig = grey(300, 200, PixelFormat::Rgb8, 77.0);
        let mut p = Params::defaults(&INFO_BIT_FLIP);
        p.set("rate", 2e-3).unwrap();
        let run = |threads| {
            let mut f = orig.clone();
            rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| {
                BitFlip.apply(&mut f, &p, &mut EffectCtx::new(3, 1, 0)).unwrap();
            });
            f
        };
        let f = run(1);
        assert_eq!(f, run(2));
        let a = orig.as_u8().unwrap();
        let b = f.as_u8().unwrap();
        let changed: Vec<usize> = (0..a.len()).filter(|&i| a[i] != b[i]).collect();
        assert!(changed.iter().all(|&i| (a[i] ^ b[i]).count_ones() == 1));
        assert!(binomial_ok(changed.len(), a.len() as f64, 2e-3), "{}", changed.len());
        let mut g = Frame::new(8, 8, PixelFormat::Mono16).unwrap();
        p.set("rate", 0.0).unwrap();
        BitFlip.apply(&mut g, &p, &mut EffectCtx::new(3, 1, 0)).unwrap();
        assert!(g.as_u16().unwrap().iter().all(|&v| v == 0));
    }

    #[test]
    fn dead_pixels_are_fixed_black_at_rate() {
        let (w, h) = (500u32, 400u32);
        let mut p = Params::defaults(&INFO_DEAD);
        p.set("rate", 4e-3).unwrap();
        let mut e = DeadPixels::default();
        let mut a = grey(w, h, PixelFormat::Mono8, 120.0);
        let mut b = grey(w, h, PixelFormat::Mono8, 200.0);
        e.apply(&mut a, &p, &mut EffectCtx::new(1, 0, 3)).unwrap();
        e.apply(&mut b, &p, &mut EffectCtx::new(1, 1, 3)).unwrap();
        let da: Vec<usize> = a.as_u8().unwrap().iter().enumerate().filter(|v| *v.1 != 120).map(|v| v.0).collect();
        let db: Vec<usize> = b.as_u8().unwrap().iter().enumerate().filter(|v| *v.1 != 200).map(|v| v.0).collect();
        assert_eq!(da, db, "same dead pixels on every frame");
        assert!(da.iter().all(|&i| a.as_u8().unwrap()[i] == 0));
        assert!(binomial_ok(da.len(), (w * h) as f64, 4e-3), "{}", da.len());
    }

    #[test]
    fn cosmic_ray_count_track_length_and_total_charge() {
        let (w, h) = (512u32, 512u32);
        let rate = 2e-5; // 5.2 hits per frame
        let mut p = Params::defaults(&INFO_COSMIC);
        p.set("rate", rate).unwrap();
        p.set("track_len_px", 20.0).unwrap();
        p.set("charge_dn", 40.0).unwrap();
        let mut e = CosmicRays::default();
        let frames = 40;
        let mut total = 0.0;
        for seq in 0..frames {
            let mut f = Frame::new(w, h, PixelFormat::Mono16).unwrap();
            e.apply(&mut f, &p, &mut EffectCtx::new(2, seq, 0)).unwrap();
            total += f.as_u16().unwrap().iter().map(|&v| v as f64).sum::<f64>();
        }
        // Deposited charge per hit = 40 DN * 257 * 20 px minus what leaves the frame (tracks
        // near the border: expected fraction about len/(2*512)*... < 4 %), rounding per pixel.
        let per_hit = 40.0 * 257.0 * 20.0;
        let hits = total / per_hit;
        let expect = rate * (w * h) as f64 * frames as f64; // 209.7
        // Poisson count: std sqrt(209.7) = 14.5; allow 5 std plus 4 % edge loss.
        assert!(hits < expect + 5.0 * expect.sqrt() && hits > 0.96 * expect - 5.0 * expect.sqrt(), "{hits}");
        // A single long horizontal-ish track: its extent matches track_len_px.
        let mut f = Frame::new(w, h, PixelFormat::Mono8).unwrap();
        p.set("rate", 1.0 / (w * h) as f64).unwrap();
        p.set("track_len_px", 60.0).unwrap();
        p.set("charge_dn", 200.0).unwrap();
        let mut seq = 0;
        loop {
            f.as_u8_mut().unwrap().fill(0);
            e.apply(&mut f, &p, &mut EffectCtx::new(5, seq, 0)).unwrap();
            seq += 1;
            let lit: Vec<(f64, f64)> = (0..(w * h) as usize)
                .filter(|&i| f.as_u8().unwrap()[i] > 0)
                .map(|i| ((i % w as usize) as f64, (i / w as usize) as f64))
                .collect();
            if lit.is_empty() {
                continue;
            }
            // Only test a frame with one track fully inside.
            let (minx, maxx) = lit.iter().fold((1e9f64, -1e9f64), |a, p| (a.0.min(p.0), a.1.max(p.0)));
            let (miny, maxy) = lit.iter().fold((1e9f64, -1e9f64), |a, p| (a.0.min(p.1), a.1.max(p.1)));
            if minx < 1.0 || miny < 1.0 || maxx > (w - 2) as f64 || maxy > (h - 2) as f64 {
                continue;
            }
            let extent = ((maxx - minx).powi(2) + (maxy - miny).powi(2)).sqrt();
            if extent > 80.0 {
                continue; // two hits in this frame
            }
            // Bilinear spreading adds up to one pixel at each end and each side.
            assert!(extent > 58.0 && extent < 63.0, "extent {extent}");
            break;
        }
    }
}
