//! The fault chain: effects applied in physical order, each with its own per-frame generator.

use super::{Effect, EffectCtx, FaultError, Outcome, Params, Stage, create};
use crate::config::FaultConfig;
use crate::frame::Frame;
use crate::masks::{MAX_MASK_EFFECTS, MaskRecorder};

/// One configured effect.
pub struct ChainEntry {
    pub effect: Box<dyn Effect>,
    /// Parameters used for the next frame (timelines and triggers change them between frames).
    pub params: Params,
    /// Position in the config file: part of the generator seed, so reordering the file's
    /// physical order never changes the random streams.
    pub index: usize,
    /// Disabled entries are skipped (timelines switch effects on and off).
    pub enabled: bool,
}

impl ChainEntry {
    pub fn name(&self) -> &'static str {
        self.effect.info().name
    }
    pub fn stage(&self) -> Stage {
        self.effect.info().stage
    }
}

/// What the chain did to one frame (for the ground-truth log).
#[derive(Debug, Clone, serde::Serialize)]
pub struct AppliedEffect {
    pub name: &'static str,
    pub stage: Stage,
    /// Config index of the effect.
    pub index: usize,
    /// Seed of the per-frame generator the effect received.
    pub seed: u64,
    pub params: Params,
}

/// Per-frame report; reuse one across frames (its vector keeps its capacity).
#[derive(Debug, Clone, Default)]
pub struct FrameReport {
    pub applied: Vec<AppliedEffect>,
    /// `Some(name)` when an effect dropped the frame.
    pub dropped_by: Option<&'static str>,
    /// Output delay requested by temporal effects (ns).
    pub delay_ns: u64,
}

impl FrameReport {
    pub fn clear(&mut self) {
        self.applied.clear();
        self.dropped_by = None;
        self.delay_ns = 0;
    }
}

/// Effects in physical order.
pub struct Chain {
    seed: u64,
    entries: Vec<ChainEntry>,
}

impl Chain {
    /// Empty chain with a campaign seed.
    pub fn new(seed: u64) -> Chain {
        Chain { seed, entries: Vec::new() }
    }

    /// Chain from a parsed fault config.
    pub fn from_config(cfg: &FaultConfig) -> Result<Chain, FaultError> {
        let mut c = Chain::new(cfg.seed);
        for e in &cfg.effects {
            c.push_entry(create(&e.name)?, e.params, e.enabled);
        }
        Ok(c)
    }

    /// Append an effect by name with parameters; the chain re-sorts into physical order.
    pub fn push(&mut self, name: &str, params: Params) -> Result<(), FaultError> {
        let effect = create(name)?;
        self.push_entry(effect, params, true);
        Ok(())
    }

    fn push_entry(&mut self, effect: Box<dyn Effect>, params: Params, enabled: bool) {
        let index = self.entries.len();
        self.entries.push(ChainEntry { effect, params, index, enabled });
        // Stable sort: equal (stage, order) keep config order.
        self.entries.sort_by_key(|e| (e.effect.info().stage, e.effect.info().order));
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }
    pub fn set_seed(&mut self, seed: u64) {
        self.seed = seed;
    }

    /// Entries in application (physical) order.
    pub fn entries(&self) -> &[ChainEntry] {
        &self.entries
    }
    pub fn entries_mut(&mut self) -> &mut [ChainEntry] {
        &mut self.entries
    }
    /// Entry by config index.
    pub fn entry_by_index_mut(&mut self, index: usize) -> Option<&mut ChainEntry> {
        self.entries.iter_mut().find(|e| e.index == index)
    }
    /// First entry with this effect name.
    pub fn entry_by_name_mut(&mut self, name: &str) -> Option<&mut ChainEntry> {
        self.entries.iter_mut().find(|e| e.name() == name)
    }

    /// Apply all enabled effects to `frame` in physical order. Stops at the first effect that
    /// drops the frame. `report` is cleared and filled.
    pub fn apply(&mut self, frame: &mut Frame, report: &mut FrameReport) -> Result<Outcome, FaultError> {
        self.apply_observed(frame, report, &mut NoObserver)
    }

    /// [`Chain::apply`], recording per-pixel fault masks into `rec` (see [`crate::masks`]): bit k
    /// of a pixel's label is set when the k-th applied effect (`report.applied[k]`) changed it.
    /// The output bytes are the same as without recording.
    pub fn apply_recording(
        &mut self,
        frame: &mut Frame,
        report: &mut FrameReport,
        rec: &mut MaskRecorder,
    ) -> Result<Outcome, FaultError> {
        let n = self.entries.iter().filter(|e| e.enabled).count();
        if n > MAX_MASK_EFFECTS {
            return Err(FaultError::Failed {
                effect: "masks",
                reason: format!(
                    "the chain has {n} enabled effects; masks record at most {MAX_MASK_EFFECTS} (bits of the label)"
                ),
            });
        }
        rec.begin(frame);
        self.apply_observed(frame, report, rec)
    }

    /// [`Chain::apply`] with an observer called around every applied effect (masks, per-effect
    /// timing). Observers see the frame but cannot change it.
    pub fn apply_observed(
        &mut self,
        frame: &mut Frame,
        report: &mut FrameReport,
        obs: &mut dyn ChainObserver,
    ) -> Result<Outcome, FaultError> {
        report.clear();
        run_entries(&mut self.entries, self.seed, frame, report, obs)
    }

    /// The next frame an effect still holds at the end of the stream ([`Effect::drain`]: a
    /// `reorder` buffer), passed through the enabled effects after the one that held it (which
    /// may hold it in turn: then the next call finds it there). `report` is cleared and filled
    /// with those effects. `None` once no effect holds a frame. The frame keeps its own `seq`
    /// and `pts_ns`. Used at the end of a stream by `faultcam run`, the GStreamer element (at EOS)
    /// and the Python package (`Chain.drain()`).
    pub fn drain_next(&mut self, report: &mut FrameReport) -> Option<(Frame, Result<Outcome, FaultError>)> {
        report.clear();
        let n = self.entries.len();
        let (pos, mut frame) = (0..n).find_map(|pos| self.entries[pos].effect.drain().map(|f| (pos, f)))?;
        let result = run_entries(&mut self.entries[pos + 1..], self.seed, &mut frame, report, &mut NoObserver);
        Some((frame, result))
    }
}

/// Apply the enabled `entries` in order to `frame`, appending to `report`; stops at the first
/// effect that drops the frame (or fails).
fn run_entries(
    entries: &mut [ChainEntry],
    seed: u64,
    frame: &mut Frame,
    report: &mut FrameReport,
    obs: &mut dyn ChainObserver,
) -> Result<Outcome, FaultError> {
    for e in entries.iter_mut().filter(|e| e.enabled) {
        let mut ctx = EffectCtx::new(seed, frame.seq, e.index);
        let k = report.applied.len();
        let name = e.effect.info().name;
        report.applied.push(AppliedEffect {
            name,
            stage: e.effect.info().stage,
            index: e.index,
            seed: ctx.rng.seed(),
            params: e.params,
        });
        obs.before_effect(k, name, frame);
        let out = e.effect.apply(frame, &e.params, &mut ctx)?;
        obs.after_effect(k, name, frame, out);
        report.delay_ns += ctx.delay_ns;
        if out == Outcome::Drop {
            report.dropped_by = Some(name);
            return Ok(Outcome::Drop);
        }
    }
    Ok(Outcome::Keep)
}

/// Hooks around each effect of [`Chain::apply_observed`]. `k` is the effect's position among the
/// effects applied to this frame (its index in `FrameReport::applied`).
pub trait ChainObserver {
    /// Just before effect `k` runs on `frame`.
    fn before_effect(&mut self, k: usize, name: &'static str, frame: &Frame);
    /// Just after effect `k` ran; `frame` is its output (`outcome` = Drop: the chain stops).
    fn after_effect(&mut self, k: usize, name: &'static str, frame: &Frame, outcome: Outcome);
}

/// Observer that does nothing (plain [`Chain::apply`]).
struct NoObserver;

impl ChainObserver for NoObserver {
    #[inline(always)]
    fn before_effect(&mut self, _: usize, _: &'static str, _: &Frame) {}
    #[inline(always)]
    fn after_effect(&mut self, _: usize, _: &'static str, _: &Frame, _: Outcome) {}
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::faults::default_params;
    use crate::frame::PixelFormat;

    #[test]
    fn applies_in_order_and_reports() {
        let mut c = Chain::new(5);
        let mut p = default_params("gain_offset").unwrap();
        p.set("offset_dn", 3.0).unwrap();
        c.push("gain_offset", p).unwrap();
        let mut f = Frame::new(8, 8, PixelFormat::Mono8).unwrap();
        let mut r = FrameReport::default();
        assert_eq!(c.apply(&mut f, &mut r).unwrap(), Outcome::Keep);
        assert_eq!(f.get(3, 3, 0), 3.0);
        assert_eq!(r.applied.len(), 1);
        assert_eq!(r.applied[0].name, "gain_offset");
        c.entries_mut()[0].enabled = false;
        c.apply(&mut f, &mut r).unwrap();
        assert!(r.applied.is_empty());
        assert_eq!(f.get(3, 3, 0), 3.0);
    }
}
