//! Per-effect cost measurement and the `degrade` overrun policy.
//!
//! The pipeline wraps every effect of the chain in a [`Timed`] wrapper that measures the time
//! of each `apply` call (two clock reads per effect and frame) into a shared [`CostCell`].
//! The wrapper is transparent: same `info()`, same parameters, same output bytes, same
//! `drain()`.
//!
//! **Degrade policy.** The degrade *level* L is the number of effects skipped: while L > 0,
//! each frame runs the chain with its L most expensive enabled effects (by the measured mean
//! cost per frame) switched off for that frame only; the ground-truth log lists exactly the
//! effects that ran, and every level change is an `overrun_degrade` event naming the skipped
//! effects. L rises by one each time a frame processed at the current level misses the budget
//! (reported by the sink) or enters the chain already too late to make it; it falls by one
//! after `hold` consecutive frames without a miss. Frames are never dropped by this policy:
//! late frames are delivered late, like `pass`.

use crate::faults::chain::Chain;
use crate::faults::{Effect, EffectCtx, EffectInfo, FaultError, Outcome, Params};
use crate::frame::Frame;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// Measured cost of one effect (written by the fault stage, read for the summary).
#[derive(Debug, Default)]
pub struct CostCell {
    /// Exponentially weighted mean of the last ~8 calls, ns.
    ewma_ns: AtomicU64,
    /// The last call, ns.
    last_ns: AtomicU64,
    total_ns: AtomicU64,
    max_ns: AtomicU64,
    calls: AtomicU64,
}

impl CostCell {
    fn record(&self, ns: u64) {
        let calls = self.calls.fetch_add(1, Ordering::Relaxed);
        self.total_ns.fetch_add(ns, Ordering::Relaxed);
        self.max_ns.fetch_max(ns, Ordering::Relaxed);
        self.last_ns.store(ns, Ordering::Relaxed);
        let old = self.ewma_ns.load(Ordering::Relaxed);
        let new = if calls == 0 { ns } else { old - old / 8 + ns / 8 };
        self.ewma_ns.store(new, Ordering::Relaxed);
    }
    /// Recent mean cost in ns.
    pub fn recent_ns(&self) -> u64 {
        self.ewma_ns.load(Ordering::Relaxed)
    }
    /// Cost of the last call in ns.
    pub fn last_ns(&self) -> u64 {
        self.last_ns.load(Ordering::Relaxed)
    }
    pub fn calls(&self) -> u64 {
        self.calls.load(Ordering::Relaxed)
    }
    pub fn mean_ns(&self) -> f64 {
        let c = self.calls();
        if c == 0 { 0.0 } else { self.total_ns.load(Ordering::Relaxed) as f64 / c as f64 }
    }
    pub fn max_ns(&self) -> u64 {
        self.max_ns.load(Ordering::Relaxed)
    }
}

/// Transparent timing wrapper around an effect.
pub struct Timed {
    inner: Box<dyn Effect>,
    cell: Arc<CostCell>,
}

impl Effect for Timed {
    fn info(&self) -> &'static EffectInfo {
        self.inner.info()
    }
    fn apply(&mut self, frame: &mut Frame, params: &Params, ctx: &mut EffectCtx) -> Result<Outcome, FaultError> {
        let t = Instant::now();
        let r = self.inner.apply(frame, params, ctx);
        self.cell.record(t.elapsed().as_nanos() as u64);
        r
    }
    fn drain(&mut self) -> Option<Frame> {
        self.inner.drain()
    }
}

/// One wrapped chain entry: its config index, name and cost cell.
#[derive(Debug, Clone)]
pub struct Tracked {
    pub index: usize,
    pub name: &'static str,
    pub cell: Arc<CostCell>,
}

/// Wrap every entry of `chain` in [`Timed`]; returns the cells by config index.
pub fn instrument(chain: &mut Chain) -> Vec<Tracked> {
    let mut out = Vec::with_capacity(chain.entries().len());
    for e in chain.entries_mut() {
        let cell = Arc::new(CostCell::default());
        let name = e.name();
        let inner = std::mem::replace(&mut e.effect, Box::new(Placeholder));
        e.effect = Box::new(Timed { inner, cell: cell.clone() });
        out.push(Tracked { index: e.index, name, cell });
    }
    out
}

/// Stand-in used only during the swap in [`instrument`].
struct Placeholder;
static PLACEHOLDER_INFO: EffectInfo = EffectInfo {
    name: "placeholder",
    stage: crate::faults::Stage::Transmission,
    order: 0,
    summary: "internal",
    model: "internal",
    params: &[],
    formats: &[],
};
impl Effect for Placeholder {
    fn info(&self) -> &'static EffectInfo {
        &PLACEHOLDER_INFO
    }
    fn apply(&mut self, _: &mut Frame, _: &Params, _: &mut EffectCtx) -> Result<Outcome, FaultError> {
        Ok(Outcome::Keep)
    }
}

/// Degrade controller (see the module docs).
#[derive(Debug)]
pub struct Degrader {
    tracked: Vec<Tracked>,
    level: u32,
    max_level_seen: u32,
    hold: u32,
    since_miss: u32,
    /// Chain positions disabled for the current frame (reused; no allocation per frame).
    disabled: Vec<usize>,
    /// Scratch: (cost, position) of enabled entries.
    scratch: Vec<(u64, usize)>,
}

impl Degrader {
    pub fn new(tracked: Vec<Tracked>, hold: u32) -> Degrader {
        let n = tracked.len();
        Degrader {
            tracked,
            level: 0,
            max_level_seen: 0,
            hold: hold.max(1),
            since_miss: 0,
            disabled: Vec::with_capacity(n),
            scratch: Vec::with_capacity(n),
        }
    }
    pub fn level(&self) -> u32 {
        self.level
    }
    pub fn max_level(&self) -> u32 {
        self.max_level_seen
    }
    pub fn tracked(&self) -> &[Tracked] {
        &self.tracked
    }

    fn cost_of(&self, index: usize) -> u64 {
        self.tracked.iter().find(|t| t.index == index).map(|t| t.cell.recent_ns()).unwrap_or(0)
    }

    /// Recent cost estimate of the whole enabled chain (ns): per effect the smaller of its
    /// recent mean and its last call, so one slow frame (a warm-up, a busy moment) does not
    /// make the next frames look too expensive to run.
    pub fn chain_estimate_ns(&self, chain: &Chain) -> u64 {
        chain
            .entries()
            .iter()
            .filter(|e| e.enabled)
            .map(|e| {
                self.tracked
                    .iter()
                    .find(|t| t.index == e.index)
                    .map(|t| t.cell.recent_ns().min(t.cell.last_ns()))
                    .unwrap_or(0)
            })
            .sum()
    }

    /// Feed one frame's outcome: `missed` = a frame processed at level >= the current level
    /// missed its budget. Returns `Some(new_level)` when the level changed.
    pub fn update(&mut self, missed: bool, n_enabled: usize) -> Option<u32> {
        let old = self.level;
        if missed {
            self.level = (self.level + 1).min(n_enabled as u32);
            self.since_miss = 0;
        } else {
            self.since_miss += 1;
            if self.level > 0 && self.since_miss >= self.hold {
                self.level -= 1;
                self.since_miss = 0;
            }
        }
        self.max_level_seen = self.max_level_seen.max(self.level);
        (self.level != old).then_some(self.level)
    }

    /// Switch off the `level` most expensive enabled entries for one frame. Call
    /// [`Degrader::restore`] after the chain ran.
    pub fn disable(&mut self, chain: &mut Chain) {
        self.disabled.clear();
        if self.level == 0 {
            return;
        }
        self.scratch.clear();
        for (pos, e) in chain.entries().iter().enumerate() {
            if e.enabled {
                self.scratch.push((self.cost_of(e.index), pos));
            }
        }
        // Most expensive first; ties by position for determinism.
        self.scratch.sort_unstable_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        let entries = chain.entries_mut();
        for &(_, pos) in self.scratch.iter().take(self.level as usize) {
            entries[pos].enabled = false;
            self.disabled.push(pos);
        }
    }

    /// Re-enable what [`Degrader::disable`] switched off.
    pub fn restore(&mut self, chain: &mut Chain) {
        let entries = chain.entries_mut();
        for &pos in &self.disabled {
            if let Some(e) = entries.get_mut(pos) {
                e.enabled = true;
            }
        }
    }

    /// Names of the effects skipped for the current frame.
    pub fn skipped_names(&self, chain: &Chain) -> Vec<&'static str> {
        self.disabled.iter().filter_map(|&p| chain.entries().get(p).map(|e| e.name())).collect()
    }

    /// True when the current frame runs degraded.
    pub fn active(&self) -> bool {
        !self.disabled.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::faults::chain::FrameReport;
    use crate::faults::default_params;
    use crate::frame::PixelFormat;

    fn chain2() -> Chain {
        let mut c = Chain::new(1);
        let mut p = default_params("gain_offset").unwrap();
        p.set("offset_dn", 2.0).unwrap();
        c.push("gain_offset", p).unwrap();
        p.set("offset_dn", 5.0).unwrap();
        c.push("gain_offset", p).unwrap();
        c
    }

    #[test]
    fn timing_wrapper_is_transparent() {
        let mut plain = chain2();
        let mut timed = chain2();
        let cells = instrument(&mut timed);
        assert_eq!(cells.len(), 2);
        let mut a = Frame::new(16, 8, PixelFormat::Mono8).unwrap();
        let mut b = a.clone();
        let (mut ra, mut rb) = (FrameReport::default(), FrameReport::default());
        plain.apply(&mut a, &mut ra).unwrap();
        timed.apply(&mut b, &mut rb).unwrap();
        assert_eq!(a, b);
        assert_eq!(ra.applied.len(), rb.applied.len());
        assert_eq!(rb.applied[0].name, "gain_offset");
        assert!(cells.iter().all(|c| c.cell.calls() == 1));
    }

    #[test]
    fn degrade_skips_most_expensive_and_restores() {
        let mut c = chain2();
        let cells = instrument(&mut c);
        cells[0].cell.record(1_000);
        cells[1].cell.record(9_000);
        let mut d = Degrader::new(cells, 3);
        assert_eq!(d.update(true, 2), Some(1));
        d.disable(&mut c);
        // Entry with config index 1 is the expensive one.
        let off: Vec<usize> = c.entries().iter().filter(|e| !e.enabled).map(|e| e.index).collect();
        assert_eq!(off, vec![1]);
        let mut f = Frame::new(4, 4, PixelFormat::Mono8).unwrap();
        let mut r = FrameReport::default();
        c.apply(&mut f, &mut r).unwrap();
        assert_eq!(f.get(0, 0, 0), 2.0, "only the cheap entry ran");
        d.restore(&mut c);
        assert!(c.entries().iter().all(|e| e.enabled));
        // Recovers one level after `hold` good frames.
        assert_eq!(d.update(false, 2), None);
        assert_eq!(d.update(false, 2), None);
        assert_eq!(d.update(false, 2), Some(0));
        assert_eq!(d.max_level(), 1);
        // Never skips more than there is.
        for _ in 0..5 {
            d.update(true, 2);
        }
        assert_eq!(d.level(), 2);
    }
}
