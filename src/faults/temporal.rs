//! Temporal effects of the transmission link (injection only): `frame_drop`, `frame_freeze`,
//! `frame_delay`, `jitter`, `reorder`. They act on the stream rather than on pixels: dropping
//! (`Outcome::Drop`), repeating content, asking the pipeline to delay output
//! (`EffectCtx::delay_ns`, summed over the chain) or holding frames back.

use super::{Effect, EffectCtx, EffectInfo, FaultError, Outcome, ParamSpec, Params, Stage};
use crate::frame::{Frame, FrameData, PixelFormat};

/// Every format, including raw Bayer: temporal effects never look at pixels.
const ANY_FORMAT: &[PixelFormat] = &[PixelFormat::Mono8, PixelFormat::Mono16, PixelFormat::Rgb8, PixelFormat::Bayer8];

// ---------------------------------------------------------------------------------------------
// frame_drop

pub static INFO_DROP: EffectInfo = EffectInfo {
    name: "frame_drop",
    stage: Stage::Transmission,
    order: 40,
    summary: "frames lost in transmission, independently with probability p",
    model: "Each frame is dropped (Outcome::Drop; later effects are not applied and the ground-truth log \
            records dropped_by = \"frame_drop\") independently with probability p, drawn from the frame's \
            generator. p = 0 is the identity, p = 1 drops everything.",
    params: &[ParamSpec::float("p", "probability", 0.0, 1.0, 0.05, "drop probability per frame")],
    formats: ANY_FORMAT,
};

pub fn create_drop() -> Box<dyn Effect> {
    Box::new(FrameDrop)
}

pub struct FrameDrop;

impl Effect for FrameDrop {
    fn info(&self) -> &'static EffectInfo {
        &INFO_DROP
    }
    fn apply(&mut self, _frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let prob = p.get("p");
        if prob > 0.0 && ctx.rng.bernoulli(prob) { Ok(Outcome::Drop) } else { Ok(Outcome::Keep) }
    }
}

// ---------------------------------------------------------------------------------------------
// frame_freeze

pub static INFO_FREEZE: EffectInfo = EffectInfo {
    name: "frame_freeze",
    stage: Stage::Transmission,
    order: 30,
    summary: "frozen video: the content of a frame is repeated for the following `frames` frames",
    model: "While the effect is enabled, a frame passes unchanged and its content is kept; the next `frames` \
            frames carry that content instead of their own (their seq and timestamps are kept, so the stream \
            timing is unchanged), then the next frame passes and is kept in turn. A timeline window of \
            frames + 1 frames therefore gives one freeze; left enabled, the output shows every \
            (frames + 1)-th input frame, each held for frames + 1 frame times. A gap in seq (the effect was \
            disabled) or a change of frame size starts afresh. frames = 0 is the identity. The held copy \
            lives in the effect (no per-frame allocation).",
    params: &[ParamSpec::int("frames", "frames", 0.0, 100_000.0, 10.0, "number of frames that repeat the held one")],
    formats: ANY_FORMAT,
};

pub fn create_freeze() -> Box<dyn Effect> {
    Box::new(FrameFreeze::default())
}

#[derive(Default)]
pub struct FrameFreeze {
    // allocation: once per stream (and per frame-size change)
    held: Option<Frame>,
    remaining: u64,
    last_seq: Option<u64>,
}

fn same_shape(a: &Frame, b: &Frame) -> bool {
    a.width == b.width && a.height == b.height && a.stride == b.stride && a.format == b.format
}

fn copy_pixels(dst: &mut Frame, src: &Frame) -> bool {
    match (&mut dst.data, &src.data) {
        (FrameData::U8(d), FrameData::U8(s)) if d.len() == s.len() => d.copy_from_slice(s),
        (FrameData::U16(d), FrameData::U16(s)) if d.len() == s.len() => d.copy_from_slice(s),
        _ => return false,
    }
    true
}

impl Effect for FrameFreeze {
    fn info(&self) -> &'static EffectInfo {
        &INFO_FREEZE
    }
    fn apply(&mut self, frame: &mut Frame, p: &Params, _ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let frames = p.get("frames") as u64;
        let continuous = self.last_seq.is_some_and(|s| s.wrapping_add(1) == frame.seq);
        self.last_seq = Some(frame.seq);
        if frames == 0 {
            self.remaining = 0;
            return Ok(Outcome::Keep);
        }
        if self.remaining > 0
            && continuous
            && let Some(h) = &self.held
            && same_shape(h, frame)
            && copy_pixels(frame, h)
        {
            self.remaining -= 1;
            return Ok(Outcome::Keep);
        }
        match &mut self.held {
            Some(h) => h.copy_from(frame),
            None => self.held = Some(frame.clone()),
        }
        self.remaining = frames;
        Ok(Outcome::Keep)
    }
}

// ---------------------------------------------------------------------------------------------
// frame_delay and jitter

pub static INFO_DELAY: EffectInfo = EffectInfo {
    name: "frame_delay",
    stage: Stage::Transmission,
    order: 50,
    summary: "constant extra latency of the link",
    model: "Adds ms milliseconds to EffectCtx::delay_ns; the pipeline delivers the frame that much later \
            (delays of several effects add). Pixels are untouched. ms = 0 is the identity.",
    params: &[ParamSpec::float("ms", "ms", 0.0, 10_000.0, 100.0, "added output latency")],
    formats: ANY_FORMAT,
};

pub fn create_delay() -> Box<dyn Effect> {
    Box::new(FrameDelay)
}

pub struct FrameDelay;

impl Effect for FrameDelay {
    fn info(&self) -> &'static EffectInfo {
        &INFO_DELAY
    }
    fn apply(&mut self, _frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        ctx.delay_ns += (p.get("ms") * 1e6).round() as u64;
        Ok(Outcome::Keep)
    }
}

pub static INFO_JITTER: EffectInfo = EffectInfo {
    name: "jitter",
    stage: Stage::Transmission,
    order: 60,
    summary: "random extra latency per frame (timing jitter)",
    model: "Adds a delay uniform in [0, ms] milliseconds, drawn per frame from the frame's generator, to \
            EffectCtx::delay_ns. One-sided (a link can delay a frame, not deliver it early): mean ms/2, \
            standard deviation ms/sqrt(12). Frames keep their order unless the pipeline reorders by due \
            time. ms = 0 is the identity.",
    params: &[ParamSpec::float("ms", "ms", 0.0, 1000.0, 10.0, "width of the uniform delay distribution")],
    formats: ANY_FORMAT,
};

pub fn create_jitter() -> Box<dyn Effect> {
    Box::new(Jitter)
}

pub struct Jitter;

impl Effect for Jitter {
    fn info(&self) -> &'static EffectInfo {
        &INFO_JITTER
    }
    fn apply(&mut self, _frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let ms = p.get("ms");
        if ms > 0.0 {
            ctx.delay_ns += (ctx.rng.uniform() * ms * 1e6).round() as u64;
        }
        Ok(Outcome::Keep)
    }
}

// ---------------------------------------------------------------------------------------------
// reorder

pub static INFO_REORDER: EffectInfo = EffectInfo {
    name: "reorder",
    stage: Stage::Transmission,
    order: 70,
    summary: "frames delivered out of order (buffer of `depth` frames)",
    model: "The effect holds up to `depth` frames. While the buffer fills, each incoming frame is taken into \
            it and the call returns Outcome::Drop (the frame is held, not lost: the log shows \
            dropped_by = \"reorder\" and the frame appears later under its own seq). Once full, each \
            incoming frame is swapped with a held one chosen uniformly from the frame's generator, and the \
            held frame (with its own seq, timestamp and content) continues down the chain. At the end of the \
            stream Chain::drain returns the held frames (in buffer order) through the later effects, so every \
            input frame is emitted exactly once. A frame waits a geometric number of frames (mean depth). \
            depth = 0 is the identity. Buffer frames are allocated while filling, once per stream.",
    params: &[ParamSpec::int("depth", "frames", 0.0, 64.0, 3.0, "number of frames held back")],
    formats: ANY_FORMAT,
};

pub fn create_reorder() -> Box<dyn Effect> {
    Box::new(Reorder::default())
}

#[derive(Default)]
pub struct Reorder {
    // allocation: `depth` frames, once per stream
    held: Vec<Frame>,
}

impl Effect for Reorder {
    fn info(&self) -> &'static EffectInfo {
        &INFO_REORDER
    }
    fn apply(&mut self, frame: &mut Frame, p: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let depth = p.get("depth") as usize;
        if depth == 0 {
            return Ok(Outcome::Keep);
        }
        if self.held.len() < depth {
            self.held.push(frame.clone());
            return Ok(Outcome::Drop);
        }
        let j = ctx.rng.below(self.held.len() as u64) as usize;
        std::mem::swap(frame, &mut self.held[j]);
        Ok(Outcome::Keep)
    }
    fn drain(&mut self) -> Option<Frame> {
        if self.held.is_empty() { None } else { Some(self.held.remove(0)) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(seq: u64) -> Frame {
        let mut f = Frame::new(4, 3, PixelFormat::Mono8).unwrap();
        f.seq = seq;
        f.pts_ns = seq * 1000;
        f.as_u8_mut().unwrap().fill(seq as u8);
        f
    }

    #[test]
    fn drop_rate_within_binomial_bound() {
        let mut e = FrameDrop;
        let mut p = Params::defaults(&INFO_DROP);
        p.set("p", 0.2).unwrap();
        let n = 20_000u64;
        let mut f = frame(0);
        let dropped = (0..n)
            .filter(|&s| e.apply(&mut f, &p, &mut EffectCtx::new(7, s, 0)).unwrap() == Outcome::Drop)
            .count() as f64;
        let sd = (n as f64 * 0.2 * 0.8).sqrt();
        assert!((dropped - 0.2 * n as f64).abs() < 5.0 * sd, "{dropped}");
        p.set("p", 0.0).unwrap();
        assert!((0..1000).all(|s| e.apply(&mut f, &p, &mut EffectCtx::new(7, s, 0)).unwrap() == Outcome::Keep));
    }

    #[test]
    fn freeze_repeats_content_and_keeps_timing() {
        let mut e = FrameFreeze::default();
        let mut p = Params::defaults(&INFO_FREEZE);
        p.set("frames", 2.0).unwrap();
        let mut out = Vec::new();
        for s in 0..7 {
            let mut f = frame(s);
            assert_eq!(e.apply(&mut f, &p, &mut EffectCtx::new(0, s, 0)).unwrap(), Outcome::Keep);
            assert_eq!((f.seq, f.pts_ns), (s, s * 1000));
            out.push(f.as_u8().unwrap()[0]);
        }
        assert_eq!(out, vec![0, 0, 0, 3, 3, 3, 6]);
        // A gap in seq (effect was disabled) starts afresh.
        let mut f = frame(20);
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 20, 0)).unwrap();
        assert_eq!(f.as_u8().unwrap()[0], 20);
        p.set("frames", 0.0).unwrap();
        let mut f = frame(21);
        e.apply(&mut f, &p, &mut EffectCtx::new(0, 21, 0)).unwrap();
        assert_eq!(f, frame(21));
    }

    #[test]
    fn delay_and_jitter_add_to_ctx() {
        let mut p = Params::defaults(&INFO_DELAY);
        p.set("ms", 12.5).unwrap();
        let mut ctx = EffectCtx::new(0, 0, 0);
        FrameDelay.apply(&mut frame(0), &p, &mut ctx).unwrap();
        assert_eq!(ctx.delay_ns, 12_500_000);
        let mut p = Params::defaults(&INFO_JITTER);
        p.set("ms", 10.0).unwrap();
        let n = 20_000;
        let d: Vec<f64> = (0..n)
            .map(|s| {
                let mut ctx = EffectCtx::new(1, s, 0);
                Jitter.apply(&mut frame(0), &p, &mut ctx).unwrap();
                ctx.delay_ns as f64 / 1e6
            })
            .collect();
        assert!(d.iter().all(|&v| (0.0..=10.0).contains(&v)));
        let m = d.iter().sum::<f64>() / n as f64;
        // Uniform [0, 10]: mean 5, std of the mean 2.887/sqrt(n) = 0.02; 5 sigma.
        assert!((m - 5.0).abs() < 0.1, "{m}");
    }

    #[test]
    fn reorder_emits_every_frame_exactly_once() {
        let mut e = Reorder::default();
        let mut p = Params::defaults(&INFO_REORDER);
        p.set("depth", 4.0).unwrap();
        let mut out = Vec::new();
        for s in 0..50 {
            let mut f = frame(s);
            if e.apply(&mut f, &p, &mut EffectCtx::new(3, s, 0)).unwrap() == Outcome::Keep {
                assert_eq!(f.as_u8().unwrap()[0], f.seq as u8, "content travels with its seq");
                out.push(f.seq);
            }
        }
        assert_eq!(out.len(), 46);
        while let Some(f) = e.drain() {
            out.push(f.seq);
        }
        assert_ne!(out, (0..50).collect::<Vec<_>>(), "order changed");
        out.sort();
        assert_eq!(out, (0..50).collect::<Vec<_>>());
    }
}
