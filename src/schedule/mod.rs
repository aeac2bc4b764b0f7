//! Fault campaigns: a fault config plus a timeline of `[[events]]` and `[triggers]` settings.
//!
//! ```toml
//! seed = 7
//!
//! [[effects]]
//! name = "gain_offset"            # driven only by events: starts disabled
//!
//! [[events]]
//! name = "dim"
//! effect = "gain_offset"
//! at_s = 1.0                      # or at_frame, trigger, rate_hz, p_per_frame
//! duration_s = 2.0                # or duration_frames; none = until STOP / end of stream
//! repeat = 3                      # occurrences (or "forever"), with period_s / period_frames
//! period_s = 5.0
//! [events.params]
//! gain = { linear = [1.0, 0.2] }  # constant, { linear }, { keyframes }, { steps }
//! ```
//!
//! [`Campaign::from_config`] validates the whole file before a run (every problem names
//! `file:line`, the event, the field and the accepted values); [`CampaignController`] drives
//! the chain frame by frame and takes serial triggers ([`crate::trigger`]) or replays them
//! from a ground-truth log. The format is documented in README.md ("Campaigns and triggers")
//! and `hil/trigger-protocol.md`.
//!
//! Semantics, in short:
//! * An event *occurrence* starts on the first frame whose `seq` reaches `at_frame` (or whose
//!   stream time reaches `at_s`), or on the frame where its trigger / START command is applied,
//!   or on a frame where its random draw fires. It is active for `duration_frames` frames
//!   (`seq < start + d`) or `duration_s` seconds (`t < start + d`).
//! * While active, the event enables its effect (`enable = true`, default; `false` switches it
//!   off) and sets its parameters; afterwards they return to the baseline. Later events in the
//!   file win over earlier ones on the same parameter; overlapping events with a deterministic
//!   schedule on the same clock that set the same parameter are rejected.
//! * An effect targeted by an enabling event and without an explicit `enabled` key starts
//!   disabled (it is driven by events only); with `enabled = true` it runs all the time and the
//!   events only change its parameters.
//! * Ramps run on the event's time base: the unit of its duration (frames or seconds), else of
//!   its start, else `ramp_unit`.

pub mod parse;
pub mod timeline;

pub use parse::{Problem, ScheduleError};
pub use timeline::CampaignController;

use crate::config::FaultConfig;
use crate::control::Controller;
use crate::faults::{EffectInfo, ParamSpec, Params};
use crate::trigger::{Catalog, LineTrigger, SerialSettings, SerialTriggers, TriggerInput, TriggerReplay};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

/// Clock of a time value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unit {
    Frames,
    Seconds,
}

impl Unit {
    pub fn name(self) -> &'static str {
        match self {
            Unit::Frames => "frames",
            Unit::Seconds => "s",
        }
    }
}

/// A point or length on one clock: frames, or nanoseconds of stream time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tick {
    Frames(u64),
    Nanos(u64),
}

impl Tick {
    pub fn unit(self) -> Unit {
        match self {
            Tick::Frames(_) => Unit::Frames,
            Tick::Nanos(_) => Unit::Seconds,
        }
    }
    pub fn raw(self) -> u64 {
        match self {
            Tick::Frames(v) | Tick::Nanos(v) => v,
        }
    }
    /// Length in its own unit (frames or seconds).
    pub fn value(self) -> f64 {
        match self {
            Tick::Frames(v) => v as f64,
            Tick::Nanos(v) => v as f64 * 1e-9,
        }
    }
}

/// How a random event fires.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Chance {
    /// Probability per frame.
    PerFrame(f64),
    /// Poisson rate in events per second of stream time: per frame `1 − exp(−rate·Δt)`, Δt the
    /// stream time since the previous frame.
    RateHz(f64),
}

/// How an event starts.
#[derive(Debug, Clone, PartialEq)]
pub enum Start {
    /// At a frame seq or stream time.
    At(Tick),
    /// On a trigger (serial `START <name>` or a modem line).
    Trigger(String),
    /// At random, only inside the optional `[from, to)` window.
    Random { chance: Chance, window: Option<(Tick, Tick)> },
}

/// How many occurrences.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Repeat {
    Count(u64),
    Forever,
}

impl Repeat {
    pub fn allows(self, k: u64) -> bool {
        match self {
            Repeat::Count(n) => k < n,
            Repeat::Forever => true,
        }
    }
}

/// How a parameter moves during an event. Times `t` are in the event's ramp unit, from the
/// start of the occurrence.
#[derive(Debug, Clone, PartialEq)]
pub enum Ramp {
    /// One value for the whole event (a step at its start and back at its end).
    Const(f64),
    /// `from + (to − from)·u/D`, u the elapsed time, D the event's duration.
    Linear { from: f64, to: f64, over: f64 },
    /// Piecewise linear through `(t, value)`; the last value holds after the last point.
    Keyframes(Vec<(f64, f64)>),
    /// Piecewise constant: each value holds from its `t` until the next.
    Steps(Vec<(f64, f64)>),
}

impl Ramp {
    /// Value at elapsed time `u` (>= 0).
    pub fn eval(&self, u: f64) -> f64 {
        match self {
            Ramp::Const(v) => *v,
            Ramp::Linear { from, to, over } => {
                let f = if *over > 0.0 { (u / over).clamp(0.0, 1.0) } else { 1.0 };
                from + (to - from) * f
            }
            Ramp::Keyframes(k) => {
                let i = k.partition_point(|(t, _)| *t <= u);
                if i == 0 {
                    return k.first().map(|p| p.1).unwrap_or(0.0);
                }
                if i == k.len() {
                    return k[i - 1].1;
                }
                let (t0, v0) = k[i - 1];
                let (t1, v1) = k[i];
                v0 + (v1 - v0) * (u - t0) / (t1 - t0)
            }
            Ramp::Steps(k) => {
                let i = k.partition_point(|(t, _)| *t <= u);
                k[i.saturating_sub(1)].1
            }
        }
    }
    /// Every value the ramp passes through lies between these.
    pub fn bounds(&self) -> (f64, f64) {
        let vals: Vec<f64> = match self {
            Ramp::Const(v) => vec![*v],
            Ramp::Linear { from, to, .. } => vec![*from, *to],
            Ramp::Keyframes(k) | Ramp::Steps(k) => k.iter().map(|p| p.1).collect(),
        };
        vals.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| (lo.min(v), hi.max(v)))
    }
}

/// One parameter an event drives.
#[derive(Debug, Clone)]
pub struct ParamRamp {
    /// Index into the effect's `info.params`.
    pub param: usize,
    pub spec: &'static ParamSpec,
    pub ramp: Ramp,
    pub line: usize,
}

/// One validated `[[events]]` entry.
#[derive(Debug, Clone)]
pub struct EventSpec {
    pub name: String,
    /// 1-based line of the `[[events]]` header.
    pub line: usize,
    /// Config index (position in `[[effects]]`) of the target effect.
    pub effect: usize,
    pub effect_name: &'static str,
    pub start: Start,
    /// `None`: until STOP or the end of the stream.
    pub duration: Option<Tick>,
    pub repeat: Repeat,
    pub period: Option<Tick>,
    /// Effect state while the event is active.
    pub enable: bool,
    pub params: Vec<ParamRamp>,
    pub ramp_unit: Option<Unit>,
}

impl EventSpec {
    /// The clock on which the event's starts are scheduled.
    pub fn start_unit(&self) -> Option<Unit> {
        match &self.start {
            Start::At(t) => Some(t.unit()),
            _ => None,
        }
    }
}

/// `[triggers]` settings.
#[derive(Debug, Clone)]
pub struct TriggerSettings {
    /// Trigger inputs are accepted from the start (else only after `ARM`).
    pub armed: bool,
    /// Default serial device (the CLI's `--trigger` overrides).
    pub port: Option<String>,
    pub baud: Option<u32>,
    pub serial: SerialSettings,
}

impl Default for TriggerSettings {
    fn default() -> Self {
        TriggerSettings { armed: true, port: None, baud: None, serial: SerialSettings::default() }
    }
}

/// An effect's state outside events.
#[derive(Debug, Clone, Copy)]
pub struct Baseline {
    pub name: &'static str,
    pub info: &'static EffectInfo,
    pub params: Params,
    pub enabled: bool,
}

/// A validated campaign.
#[derive(Debug, Clone)]
pub struct Campaign {
    pub origin: String,
    pub seed: u64,
    /// Hash of the source text (recorded in the log, checked on replay).
    pub fingerprint: u64,
    pub name: Option<String>,
    pub description: Option<String>,
    pub events: Vec<EventSpec>,
    pub triggers: TriggerSettings,
    /// Per config index.
    pub baseline: Vec<Baseline>,
    /// START/STOP name → events it addresses (by event name or trigger name), in file order.
    pub by_name: BTreeMap<String, Vec<usize>>,
}

impl Campaign {
    /// Validate the campaign parts of a fault config (see [`parse`]).
    pub fn from_config(cfg: &FaultConfig) -> Result<Campaign, ScheduleError> {
        parse::campaign(cfg)
    }

    /// Names and effects the trigger protocol may use.
    pub fn catalog(&self) -> Catalog {
        Catalog {
            names: self.by_name.keys().cloned().collect(),
            effects: self.baseline.iter().map(|b| (b.name.to_string(), b.info)).collect(),
        }
    }

    /// True when the campaign needs a controller (events, or trigger settings).
    pub fn is_active(&self) -> bool {
        !self.events.is_empty() || !self.triggers.serial.lines.is_empty() || self.triggers.port.is_some()
    }

    /// Modem-line mappings.
    pub fn line_triggers(&self) -> &[LineTrigger] {
        &self.triggers.serial.lines
    }
}

/// Where trigger commands come from in a run.
#[derive(Debug, Clone, Default)]
pub struct TriggerOptions {
    /// Serial device (overrides `[triggers] port`).
    pub serial: Option<String>,
    /// Baud rate (overrides `[triggers] baud`; default 115200).
    pub baud: Option<u32>,
    /// Replay the triggers recorded in this ground-truth log instead of a serial port.
    pub replay: Option<PathBuf>,
    /// Ignore `[triggers] port` (e.g. validating or replaying on a machine without the rig).
    pub no_serial: bool,
}

/// The controllers for a run: none when the config has no campaign parts and no trigger input
/// is asked for, else one [`CampaignController`] (timeline + serial or replayed triggers).
pub fn controllers_from_config(
    cfg: &FaultConfig,
    opts: &TriggerOptions,
) -> Result<Vec<Box<dyn Controller>>, ScheduleError> {
    let campaign = Campaign::from_config(cfg)?;
    let input = trigger_input(&campaign, opts)?;
    if !campaign.is_active() && input.is_none() {
        return Ok(Vec::new());
    }
    Ok(vec![Box::new(CampaignController::new(campaign, input))])
}

/// Open the trigger input the options and the campaign ask for.
pub fn trigger_input(
    campaign: &Campaign,
    opts: &TriggerOptions,
) -> Result<Option<Box<dyn TriggerInput>>, ScheduleError> {
    if let Some(log) = &opts.replay {
        if opts.serial.is_some() {
            return Err(ScheduleError::Options(
                "--trigger and --replay-triggers exclude each other: a replay takes the triggers from the log".into(),
            ));
        }
        return Ok(Some(Box::new(TriggerReplay::from_log(log, campaign.catalog())?)));
    }
    let port = opts.serial.clone().or_else(|| if opts.no_serial { None } else { campaign.triggers.port.clone() });
    let Some(port) = port else { return Ok(None) };
    let baud = opts.baud.or(campaign.triggers.baud).unwrap_or(crate::trigger::DEFAULT_BAUD);
    if !(50..=4_000_000).contains(&baud) {
        return Err(ScheduleError::Options(format!("baud rate {baud} is out of range; accepted: 50..=4000000")));
    }
    let t = SerialTriggers::open(&port, baud, campaign.triggers.serial.clone(), campaign.catalog())?;
    Ok(Some(Box::new(t)))
}

/// Milliseconds to a [`Duration`].
pub(crate) fn ms(v: u64) -> Duration {
    Duration::from_millis(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ramps_evaluate() {
        let l = Ramp::Linear { from: 1.0, to: 3.0, over: 4.0 };
        assert_eq!(l.eval(0.0), 1.0);
        assert_eq!(l.eval(2.0), 2.0);
        assert_eq!(l.eval(9.0), 3.0);
        let k = Ramp::Keyframes(vec![(0.0, 0.0), (2.0, 4.0), (4.0, 0.0)]);
        assert_eq!(k.eval(1.0), 2.0);
        assert_eq!(k.eval(3.0), 2.0);
        assert_eq!(k.eval(2.0), 4.0);
        assert_eq!(k.eval(7.0), 0.0);
        let s = Ramp::Steps(vec![(0.0, 1.0), (2.0, 5.0)]);
        assert_eq!(s.eval(1.99), 1.0);
        assert_eq!(s.eval(2.0), 5.0);
        assert_eq!(k.bounds(), (0.0, 4.0));
    }
}
