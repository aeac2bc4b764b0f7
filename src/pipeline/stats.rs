//! Latency statistics and the end-of-stream summary.

use serde::Serialize;

/// Sub-buckets per power of two (relative resolution 1/512 ≈ 0.2 %).
const SUB_BITS: u32 = 10;
const SUB: u64 = 1 << SUB_BITS;
const HALF: u64 = SUB / 2;
/// Buckets needed to cover every `u64` nanosecond value.
const BUCKETS: usize = (SUB + (64 - SUB_BITS as u64) * HALF) as usize;

/// Log-linear histogram of durations in nanoseconds (HDR-histogram layout): exact below
/// 1024 ns, then 512 buckets per power of two, so any quantile is within 0.2 % of the true
/// value. Fixed size (about 110 KiB), allocated once per stream: recording never allocates.
#[derive(Clone)]
pub struct LatencyHistogram {
    // allocation: once per stream
    counts: Vec<u32>,
    n: u64,
    max_ns: u64,
    sum_ns: u128,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        LatencyHistogram::new()
    }
}

impl std::fmt::Debug for LatencyHistogram {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LatencyHistogram").field("n", &self.n).field("max_ns", &self.max_ns).finish()
    }
}

fn bucket_of(v: u64) -> usize {
    if v < SUB {
        return v as usize;
    }
    let msb = 63 - v.leading_zeros() as u64; // >= SUB_BITS
    let shift = msb - (SUB_BITS as u64 - 1); // >= 1
    let m = v >> shift; // in [HALF, SUB)
    (SUB + (shift - 1) * HALF + (m - HALF)) as usize
}

/// Midpoint of a bucket's value range.
fn value_of(b: usize) -> u64 {
    let b = b as u64;
    if b < SUB {
        return b;
    }
    let k = b - SUB;
    let shift = k / HALF + 1;
    let m = k % HALF + HALF;
    (m << shift) + ((1u64 << shift) >> 1)
}

impl LatencyHistogram {
    pub fn new() -> LatencyHistogram {
        LatencyHistogram { counts: vec![0; BUCKETS], n: 0, max_ns: 0, sum_ns: 0 }
    }
    pub fn record(&mut self, ns: u64) {
        let b = bucket_of(ns);
        self.counts[b] = self.counts[b].saturating_add(1);
        self.n += 1;
        self.max_ns = self.max_ns.max(ns);
        self.sum_ns += ns as u128;
    }
    pub fn count(&self) -> u64 {
        self.n
    }
    pub fn max_ns(&self) -> u64 {
        self.max_ns
    }
    pub fn mean_ns(&self) -> f64 {
        if self.n == 0 { 0.0 } else { self.sum_ns as f64 / self.n as f64 }
    }
    /// Value below which a fraction `q` (0..=1) of the samples lie (nearest rank).
    pub fn quantile_ns(&self, q: f64) -> u64 {
        if self.n == 0 {
            return 0;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.n as f64).ceil() as u64).max(1);
        let mut seen = 0u64;
        for (b, &c) in self.counts.iter().enumerate() {
            seen += c as u64;
            if seen >= rank {
                return value_of(b).min(self.max_ns);
            }
        }
        self.max_ns
    }
    /// p50 / p99 / max / mean in milliseconds.
    pub fn stats(&self) -> LatencyStats {
        let ms = |ns: u64| ns as f64 / 1e6;
        LatencyStats {
            frames: self.n,
            p50_ms: ms(self.quantile_ns(0.5)),
            p99_ms: ms(self.quantile_ns(0.99)),
            max_ms: ms(self.max_ns),
            mean_ms: self.mean_ns() / 1e6,
        }
    }
}

/// Quantiles of one duration (milliseconds).
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct LatencyStats {
    pub frames: u64,
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
    pub mean_ms: f64,
}

impl std::fmt::Display for LatencyStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms (mean {:.2} ms)",
            self.p50_ms, self.p99_ms, self.max_ms, self.mean_ms
        )
    }
}

/// Mean cost of one effect over the stream.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct EffectCost {
    pub name: &'static str,
    pub frames: u64,
    pub mean_ms: f64,
    pub max_ms: f64,
}

/// Why the stream ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// The source reached its end.
    #[default]
    EndOfStream,
    /// The stop flag was raised (SIGINT).
    Signal,
    /// `max_frames` input frames were read.
    FrameLimit,
    /// `duration` elapsed.
    Duration,
    /// A fatal error (see `Summary::error`).
    Error,
}

impl StopReason {
    pub fn name(self) -> &'static str {
        match self {
            StopReason::EndOfStream => "end of stream",
            StopReason::Signal => "stop requested (signal)",
            StopReason::FrameLimit => "frame limit",
            StopReason::Duration => "duration limit",
            StopReason::Error => "error",
        }
    }
}

/// What happened over a whole stream. Every input frame is counted in exactly one of
/// `delivered`, `dropped_by_fault`, `dropped_overrun` and `failed`; `unaccounted` is the
/// difference between `frames_in` and their sum and is 0 unless something is wrong.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Summary {
    pub source: String,
    pub sink: String,
    pub stopped_by: StopReason,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Frames the source produced (including frames dropped at capture).
    pub frames_in: u64,
    /// Frames written to the sink.
    pub delivered: u64,
    /// Frames dropped by a fault effect (`frame_drop`, ...).
    pub dropped_by_fault: u64,
    /// Frames dropped by the `drop` overrun policy (at capture, before the chain or before the
    /// sink write).
    pub dropped_overrun: u64,
    /// Frames that could not be processed (effect or sink error, or not written because free
    /// space was under the `--min-free-mb` floor).
    pub failed: u64,
    /// Frames counted here whose frame record could not be written to the log (full disk):
    /// the log's records fall short of these counts by exactly this many.
    pub unlogged: u64,
    /// Of `failed`: frames not written under `--low-disk drop` (free space under the floor).
    pub dropped_low_disk: u64,
    /// Records of frames an effect held back (`reorder` while its buffer fills: logged as
    /// `dropped_by_fault` with `dropped_by = "reorder"`); each such frame is logged again when
    /// it is released, so these records are not counted as drops.
    pub held: u64,
    /// Frames given back by effects that held them (`Effect::drain`) at the end of the stream.
    pub drained: u64,
    /// `dropped_by_fault + dropped_overrun`.
    pub dropped: u64,
    /// Input items the source skipped (corrupt or mismatched files, frames a camera or driver
    /// lost), each logged as `skip`; not input frames.
    #[serde(rename = "skipped")]
    pub skipped_inputs: u64,
    /// `frames_in - (delivered + dropped_by_fault + dropped_overrun + failed)`: must be 0.
    pub unaccounted: i64,
    pub budget_ms: Option<f64>,
    pub overrun_policy: &'static str,
    /// Delivered frames whose latency (less any injected delay) exceeded the budget.
    pub late: u64,
    /// `late + dropped_overrun`.
    pub budget_misses: u64,
    /// Frames that went through a degraded (cheaper) chain.
    pub degraded: u64,
    /// Highest degrade level reached (number of effects skipped).
    pub max_degrade_level: u32,
    /// Capture-to-sink latency of delivered frames (includes injected `frame_delay`/`jitter`).
    pub latency: LatencyStats,
    /// Time in the fault chain per frame.
    pub chain: LatencyStats,
    /// Time in `Sink::write_frame` per frame.
    pub sink_write: LatencyStats,
    pub wall_s: f64,
    pub fps_in: f64,
    pub fps_out: f64,
    pub effects: Vec<EffectCost>,
}

impl Summary {
    /// Frames accounted for in the log.
    pub fn accounted(&self) -> u64 {
        self.delivered + self.dropped_by_fault + self.dropped_overrun + self.failed
    }
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "faultcam run summary ({}, {:.1} s)", self.stopped_by.name(), self.wall_s)?;
        writeln!(f, "  source: {}", self.source)?;
        writeln!(f, "  sink:   {}", self.sink)?;
        writeln!(
            f,
            "  frames: in {}, out {}, dropped {} (by fault {}, overrun {}), failed {}, unaccounted {}",
            self.frames_in,
            self.delivered,
            self.dropped_by_fault + self.dropped_overrun,
            self.dropped_by_fault,
            self.dropped_overrun,
            self.failed,
            self.unaccounted
        )?;
        if self.unlogged > 0 {
            writeln!(f, "  frame records not written to the log (log write failed): {}", self.unlogged)?;
        }
        if self.dropped_low_disk > 0 {
            writeln!(f, "  not written for low disk (--low-disk drop, counted as failed): {}", self.dropped_low_disk)?;
        }
        if self.skipped_inputs > 0 || self.drained > 0 || self.held > 0 {
            writeln!(
                f,
                "  skipped inputs: {}, held by effects: {} (released at the end: {})",
                self.skipped_inputs, self.held, self.drained
            )?;
        }
        writeln!(f, "  rate:   in {:.2} fps, out {:.2} fps", self.fps_in, self.fps_out)?;
        writeln!(f, "  latency (capture to sink): {}", self.latency)?;
        writeln!(f, "  chain: {}; sink write: {}", self.chain, self.sink_write)?;
        match self.budget_ms {
            Some(b) => writeln!(
                f,
                "  budget {b} ms, policy {}: misses {} (late {}, dropped {}), degraded frames {} (max level {})",
                self.overrun_policy,
                self.budget_misses,
                self.late,
                self.dropped_overrun,
                self.degraded,
                self.max_degrade_level
            )?,
            None => writeln!(f, "  no latency budget")?,
        }
        if !self.effects.is_empty() {
            write!(f, "  effects (mean ms/frame):")?;
            for e in &self.effects {
                write!(f, " {} {:.2}", e.name, e.mean_ms)?;
            }
            writeln!(f)?;
        }
        if let Some(e) = &self.error {
            writeln!(f, "  error: {e}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_are_monotone_and_tight() {
        let mut last = 0;
        for v in [0u64, 1, 1023, 1024, 1025, 2047, 2048, 4097, 1_000_000, 16_700_000, 1 << 40, u64::MAX] {
            let b = bucket_of(v);
            assert!(b >= last && b < BUCKETS, "{v} -> {b}");
            last = b;
            let mid = value_of(b) as f64;
            assert!((mid - v as f64).abs() <= v as f64 / 500.0 + 1.0, "{v} mid {mid}");
        }
    }

    #[test]
    fn quantiles_match_sorted_samples() {
        let mut h = LatencyHistogram::new();
        let mut r = crate::rng::Rng::new(3);
        let mut v: Vec<u64> = (0..5000).map(|_| (r.uniform() * 4e7) as u64).collect();
        for &x in &v {
            h.record(x);
        }
        v.sort();
        for q in [0.5, 0.9, 0.99] {
            let exact = v[((q * v.len() as f64).ceil() as usize).max(1) - 1] as f64;
            let got = h.quantile_ns(q) as f64;
            assert!((got - exact).abs() <= exact * 0.002 + 1.0, "q{q}: {got} vs {exact}");
        }
        assert_eq!(h.max_ns(), *v.last().unwrap());
        assert_eq!(h.count(), 5000);
    }
}
