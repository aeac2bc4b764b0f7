//! The campaign controller: runs the timeline and applies trigger commands between frames.
//!
//! Before each frame (`before_frame(seq, t_ns)`), in this order:
//! 1. occurrences whose duration is over end (`event_stop`, reason `duration`);
//! 2. pending trigger commands are applied (START/STOP/SET/ARM/DISARM/MARK/PING), each logged
//!    as a `trigger` event and acknowledged with this frame's seq and stream time;
//! 3. scheduled occurrences that are due start, then random events draw;
//! 4. every effect's state (enabled + parameters) is computed from its baseline and the active
//!    events (file order: later events win) and written to the chain where it changed
//!    (`effect_state` events).
//!
//! Everything depends only on (campaign, seed, frame seqs and stream times, trigger commands
//! and the frames they were applied at), so replaying the recorded triggers reproduces a run.

use super::{Campaign, Chance, EventSpec, Start, Tick, Unit};
use crate::control::{Controller, LogEvent};
use crate::faults::chain::Chain;
use crate::faults::{ParamKind, Params};
use crate::gtlog::FrameStatus;
use crate::rng::{Rng, mix_seed};
use crate::trigger::{Catalog, Command, Incoming, Origin, SetTarget, TriggerInput};
use serde_json::{Map, Value, json};

/// Domain tag of the random-event draws (independent of every effect's generator).
const TAG_EVENTS: u64 = 0xF5A3_0E01;

#[derive(Debug, Clone, Copy)]
struct Occ {
    /// Zero of the ramp clock and of the duration: the scheduled start where there is one,
    /// else the frame where it started.
    origin_seq: u64,
    origin_t: u64,
    k: u64,
    cause: &'static str,
    frames: u64,
}

#[derive(Debug, Clone, Default)]
struct EvState {
    active: Option<Occ>,
    /// (seq, t) origin of occurrence 0 of the current sequence (scheduled or triggered).
    base: Option<(u64, u64)>,
    next_k: u64,
}

/// Drives the chain from a [`Campaign`] and an optional trigger input.
pub struct CampaignController {
    plan: Campaign,
    catalog: Catalog,
    states: Vec<EvState>,
    /// Per config index: (enabled, params) outside events; `SET` changes it.
    baseline: Vec<(bool, Params)>,
    /// Scratch: the state each effect should have on this frame.
    desired: Vec<(bool, Params)>,
    input: Option<Box<dyn TriggerInput>>,
    incoming: Vec<Incoming>,
    armed: bool,
    started: bool,
    last_seq: u64,
    last_t: Option<u64>,
    /// Last acknowledged serial command (seq, command, reply): a retransmission is re-acked.
    last_ack: Option<(u64, Command, String)>,
    dropped_logged: u64,
}

impl CampaignController {
    pub fn new(plan: Campaign, input: Option<Box<dyn TriggerInput>>) -> CampaignController {
        let baseline: Vec<(bool, Params)> = plan.baseline.iter().map(|b| (b.enabled, b.params)).collect();
        CampaignController {
            catalog: plan.catalog(),
            states: vec![EvState::default(); plan.events.len()],
            desired: baseline.clone(),
            baseline,
            input,
            // allocation: once per stream
            incoming: Vec::with_capacity(64),
            armed: plan.triggers.armed,
            started: false,
            last_seq: 0,
            last_t: None,
            last_ack: None,
            dropped_logged: 0,
            plan,
        }
    }

    /// The validated campaign.
    pub fn campaign(&self) -> &Campaign {
        &self.plan
    }

    fn event_json(&self, kind: &str, i: usize, seq: u64, t: u64) -> Map<String, Value> {
        let e = &self.plan.events[i];
        let mut m = Map::new();
        m.insert("event".into(), kind.into());
        m.insert("seq".into(), seq.into());
        m.insert("t_ns".into(), t.into());
        m.insert("name".into(), e.name.clone().into());
        m.insert("effect".into(), e.effect_name.into());
        m.insert("index".into(), e.effect.into());
        m
    }

    fn start(&mut self, i: usize, occ: Occ, seq: u64, t: u64, events: &mut Vec<LogEvent>) {
        if self.states[i].active.is_some() {
            let reason = if occ.cause == "schedule" { "next_occurrence" } else { "restart" };
            self.stop(i, reason, seq, t, events);
        }
        let e = &self.plan.events[i];
        let mut m = self.event_json("event_start", i, seq, t);
        m.insert("occurrence".into(), occ.k.into());
        m.insert("cause".into(), occ.cause.into());
        m.insert("origin_seq".into(), occ.origin_seq.into());
        m.insert("origin_t_ns".into(), occ.origin_t.into());
        match e.duration {
            Some(Tick::Frames(d)) => {
                m.insert("end_seq".into(), (occ.origin_seq + d).into());
            }
            Some(Tick::Nanos(d)) => {
                m.insert("end_t_ns".into(), (occ.origin_t + d).into());
            }
            None => {}
        }
        events.push(Value::Object(m));
        self.states[i].active = Some(occ);
    }

    fn stop(&mut self, i: usize, reason: &str, seq: u64, t: u64, events: &mut Vec<LogEvent>) {
        if let Some(o) = self.states[i].active.take() {
            let mut m = self.event_json("event_stop", i, seq, t);
            m.insert("occurrence".into(), o.k.into());
            m.insert("reason".into(), reason.into());
            m.insert("frames".into(), o.frames.into());
            events.push(Value::Object(m));
        }
    }

    /// Origin of scheduled occurrence `k` if it is due at (seq, t).
    fn due(e: &EventSpec, st: &EvState, seq: u64, t: u64) -> Option<(u64, u64)> {
        let k = st.next_k;
        if !e.repeat.allows(k) {
            return None;
        }
        if k == 0 {
            return match e.start {
                Start::At(Tick::Frames(f)) if seq >= f => Some((f, t)),
                Start::At(Tick::Nanos(n)) if t >= n => Some((seq, n)),
                _ => None,
            };
        }
        let (bs, bt) = st.base?;
        match e.period? {
            Tick::Frames(p) => {
                let s = bs.saturating_add(k.saturating_mul(p));
                (seq >= s).then_some((s, t))
            }
            Tick::Nanos(p) => {
                let s = bt.saturating_add(k.saturating_mul(p));
                (t >= s).then_some((seq, s))
            }
        }
    }

    fn reply(&mut self, line: String, cmd_seq: Option<u64>, seq: u64, t: u64, events: &mut Vec<LogEvent>) {
        if let Some(inp) = self.input.as_mut() {
            inp.reply(&line);
        }
        events.push(json!({"event": "ack", "seq": seq, "t_ns": t, "cmd_seq": cmd_seq, "reply": line}));
    }

    fn nak(&mut self, cmd_seq: Option<u64>, reason: &str, command: &str, seq: u64, t: u64, events: &mut Vec<LogEvent>) {
        let s = cmd_seq.map(|s| s.to_string()).unwrap_or_else(|| "-".into());
        if let Some(inp) = self.input.as_mut() {
            inp.reply(&format!("NAK {s} {reason}"));
        }
        events.push(json!({"event": "nak", "seq": seq, "t_ns": t, "cmd_seq": cmd_seq, "command": command,
                           "reason": reason}));
    }

    fn apply_command(
        &mut self,
        cmd_seq: Option<u64>,
        cmd: Command,
        origin: Origin,
        seq: u64,
        t: u64,
        events: &mut Vec<LogEvent>,
    ) {
        let text = cmd.text(&self.catalog);
        // A retransmitted serial command (same seq, same command) is acknowledged again, once applied.
        if origin == Origin::Serial
            && let (Some(cs), Some((ls, lc, reply))) = (cmd_seq, self.last_ack.as_ref())
            && cs == *ls
            && cmd == *lc
        {
            let reply = reply.clone();
            if let Some(inp) = self.input.as_mut() {
                inp.reply(&reply);
            }
            events.push(json!({"event": "ack", "seq": seq, "t_ns": t, "cmd_seq": cs, "reply": reply,
                               "duplicate": true}));
            return;
        }
        let needs_arm = matches!(cmd, Command::Start(_) | Command::Set { .. });
        if needs_arm && !self.armed {
            match &origin {
                Origin::Line { line, rising } => events.push(json!({
                    "event": "trigger_ignored", "seq": seq, "t_ns": t, "source": line.name(),
                    "edge": if *rising { "rising" } else { "falling" }, "command": text, "reason": "disarmed"})),
                _ => self.nak(cmd_seq, "disarmed: send ARM first", &text, seq, t, events),
            }
            return;
        }
        let mut rec = Map::new();
        rec.insert("event".into(), "trigger".into());
        rec.insert("seq".into(), seq.into());
        rec.insert("t_ns".into(), t.into());
        rec.insert("source".into(), origin.source().into());
        if let Some(cs) = cmd_seq {
            rec.insert("cmd_seq".into(), cs.into());
        }
        rec.insert("command".into(), text.clone().into());
        if let Origin::Line { rising, .. } = origin {
            rec.insert("edge".into(), (if rising { "rising" } else { "falling" }).into());
        }
        if matches!(origin, Origin::Replay { .. }) {
            rec.insert("replayed".into(), true.into());
        }
        events.push(Value::Object(rec));

        match &cmd {
            Command::Start(name) => {
                let idx = self.plan.by_name.get(name).cloned().unwrap_or_default();
                for i in idx {
                    let triggered = matches!(self.plan.events[i].start, Start::Trigger(_));
                    let cause = if triggered { "trigger" } else { "command" };
                    if triggered {
                        self.states[i].base = Some((seq, t));
                        self.states[i].next_k = 1;
                    }
                    self.start(i, Occ { origin_seq: seq, origin_t: t, k: 0, cause, frames: 0 }, seq, t, events);
                }
            }
            Command::Stop(name) => {
                let idx = self.plan.by_name.get(name).cloned().unwrap_or_default();
                for i in idx {
                    if matches!(self.plan.events[i].start, Start::Trigger(_)) {
                        self.states[i].base = None;
                        self.states[i].next_k = 0;
                    }
                    self.stop(i, "command", seq, t, events);
                }
            }
            Command::Set { index, target } => {
                if let Some(b) = self.baseline.get_mut(*index) {
                    match target {
                        SetTarget::Enabled(on) => b.0 = *on,
                        SetTarget::Param { param, value } => {
                            if let Some(spec) = b.1.info().params.get(*param) {
                                // Validated on arrival; a failure here leaves the value unchanged.
                                let _ = b.1.set(spec.name, *value);
                            }
                        }
                    }
                }
            }
            Command::Arm => self.armed = true,
            Command::Disarm => self.armed = false,
            Command::Mark(label) => {
                events.push(json!({"event": "mark", "seq": seq, "t_ns": t, "cmd_seq": cmd_seq, "label": label}))
            }
            Command::Ping => {}
        }

        match origin {
            Origin::Serial => {
                let cs = cmd_seq.unwrap_or(0);
                let line = format!("ACK {cs} frame={seq} t_ns={t}");
                self.last_ack = Some((cs, cmd, line.clone()));
                self.reply(line, cmd_seq, seq, t, events);
            }
            Origin::Line { line, rising } => {
                let edge = if rising { "rising" } else { "falling" };
                self.reply(format!("EDGE {} {edge} frame={seq} t_ns={t}", line.name()), None, seq, t, events);
            }
            Origin::Replay { .. } => {}
        }
    }

    fn ramp_time(e: &EventSpec, o: &Occ, seq: u64, t: u64) -> f64 {
        match e.ramp_unit {
            Some(Unit::Seconds) => t.saturating_sub(o.origin_t) as f64 * 1e-9,
            _ => seq.saturating_sub(o.origin_seq) as f64,
        }
    }

    fn sync_chain(&mut self, seq: u64, t: u64, chain: &mut Chain, events: &mut Vec<LogEvent>) {
        self.desired.clone_from_slice(&self.baseline);
        for (e, st) in self.plan.events.iter().zip(&self.states) {
            let Some(o) = &st.active else { continue };
            let Some(d) = self.desired.get_mut(e.effect) else { continue };
            d.0 = e.enable;
            if e.params.is_empty() {
                continue;
            }
            let u = Self::ramp_time(e, o, seq, t);
            for p in &e.params {
                let mut v = p.ramp.eval(u).clamp(p.spec.min, p.spec.max);
                if !matches!(p.spec.kind, ParamKind::Float) {
                    v = v.round();
                }
                // Ranges were checked along the whole ramp at validation.
                let _ = d.1.set(p.spec.name, v);
            }
        }
        for entry in chain.entries_mut() {
            let Some(&(en, p)) = self.desired.get(entry.index) else { continue };
            if entry.enabled == en && entry.params == p {
                continue;
            }
            let mut changed = Map::new();
            for ((spec, new), old) in p.iter().zip(entry.params.iter().map(|(_, v)| v)) {
                if new.to_bits() != old.to_bits() {
                    let v: Value = match spec.kind {
                        ParamKind::Choice(c) => c.get(new as usize).copied().unwrap_or("").into(),
                        ParamKind::Bool => (new != 0.0).into(),
                        ParamKind::Int => (new as i64).into(),
                        ParamKind::Float => new.into(),
                    };
                    changed.insert(spec.name.into(), v);
                }
            }
            // allocation: only on frames where an effect's state changes
            events.push(json!({"event": "effect_state", "seq": seq, "t_ns": t, "effect": entry.name(),
                               "index": entry.index, "enabled": en, "params": changed}));
            entry.enabled = en;
            entry.params = p;
        }
    }
}

impl Controller for CampaignController {
    fn before_frame(
        &mut self,
        seq: u64,
        t_ns: u64,
        chain: &mut Chain,
        events: &mut Vec<LogEvent>,
    ) -> anyhow::Result<()> {
        let t = t_ns;
        if !self.started {
            self.started = true;
            let p = &self.plan;
            events.push(json!({
                "event": "campaign", "seq": seq, "t_ns": t, "origin": p.origin, "name": p.name,
                "seed": p.seed, "fingerprint": format!("{:016x}", p.fingerprint), "events": p.events.len(),
                "triggers": self.input.as_ref().map(|i| i.describe()), "armed": self.armed,
            }));
            if let Some(expected) = self.input.as_ref().and_then(|i| i.expected_fingerprint())
                && expected != format!("{:016x}", p.fingerprint)
            {
                events.push(json!({"event": "replay_mismatch", "seq": seq, "t_ns": t,
                    "message": format!("the trigger log was recorded with campaign {expected}, this is {:016x}: \
                                        the replay may not reproduce the recorded output", p.fingerprint)}));
            }
        }
        // 1. Ends.
        for i in 0..self.plan.events.len() {
            let Some(o) = self.states[i].active else { continue };
            let over = match self.plan.events[i].duration {
                Some(Tick::Frames(d)) => seq >= o.origin_seq.saturating_add(d),
                Some(Tick::Nanos(d)) => t >= o.origin_t.saturating_add(d),
                None => false,
            };
            if over {
                self.stop(i, "duration", seq, t, events);
            }
        }
        // 2. Commands.
        let mut incoming = std::mem::take(&mut self.incoming);
        if let Some(inp) = self.input.as_mut() {
            inp.pending(seq, &mut incoming);
        }
        for item in incoming.drain(..) {
            match item {
                Incoming::Command { cmd_seq, cmd, origin } => self.apply_command(cmd_seq, cmd, origin, seq, t, events),
                Incoming::Rejected { cmd_seq, reason, raw } => events.push(json!({
                    "event": "nak", "seq": seq, "t_ns": t, "cmd_seq": cmd_seq, "reason": reason, "raw": raw})),
                Incoming::Notice { message } => {
                    events.push(json!({"event": "trigger_notice", "seq": seq, "t_ns": t, "message": message}))
                }
            }
        }
        self.incoming = incoming;
        // 3. Scheduled and random starts.
        let dt_s = self.last_t.map(|p| t.saturating_sub(p) as f64 * 1e-9).unwrap_or(0.0);
        for i in 0..self.plan.events.len() {
            let e = &self.plan.events[i];
            match &e.start {
                Start::At(_) | Start::Trigger(_) => {
                    if let Some((os, ot)) = Self::due(e, &self.states[i], seq, t) {
                        let st = &mut self.states[i];
                        let k = st.next_k;
                        if k == 0 {
                            st.base = Some((os, ot));
                        }
                        st.next_k += 1;
                        let cause = if matches!(e.start, Start::Trigger(_)) { "trigger" } else { "schedule" };
                        self.start(i, Occ { origin_seq: os, origin_t: ot, k, cause, frames: 0 }, seq, t, events);
                    }
                }
                Start::Random { chance, window } => {
                    if self.states[i].active.is_some() {
                        continue;
                    }
                    let inside = match window {
                        Some((Tick::Frames(a), Tick::Frames(b))) => (*a..*b).contains(&seq),
                        Some((Tick::Nanos(a), Tick::Nanos(b))) => (*a..*b).contains(&t),
                        Some(_) => false,
                        None => true,
                    };
                    if !inside {
                        continue;
                    }
                    let p = match chance {
                        Chance::PerFrame(p) => *p,
                        Chance::RateHz(r) => 1.0 - (-r * dt_s).exp(),
                    };
                    let mut rng = Rng::new(mix_seed(&[TAG_EVENTS, self.plan.seed, i as u64, seq]));
                    if rng.bernoulli(p) {
                        let st = &mut self.states[i];
                        let k = st.next_k;
                        st.next_k += 1;
                        self.start(
                            i,
                            Occ { origin_seq: seq, origin_t: t, k, cause: "random", frames: 0 },
                            seq,
                            t,
                            events,
                        );
                    }
                }
            }
        }
        // 4. Effect states.
        self.sync_chain(seq, t, chain, events);
        for st in &mut self.states {
            if let Some(o) = st.active.as_mut() {
                o.frames += 1;
            }
        }
        if let Some(inp) = self.input.as_ref() {
            let dropped = inp.dropped_replies();
            if dropped > self.dropped_logged {
                events.push(json!({"event": "trigger_notice", "seq": seq, "t_ns": t,
                    "message": format!("{} replies to the rig could not be sent (rig not reading?)",
                                       dropped - self.dropped_logged)}));
                self.dropped_logged = dropped;
            }
        }
        self.last_seq = seq;
        self.last_t = Some(t);
        Ok(())
    }

    fn after_frame(&mut self, _seq: u64, _t_ns: u64, _status: FrameStatus, _events: &mut Vec<LogEvent>) {}

    fn finish(&mut self, events: &mut Vec<LogEvent>) {
        let (seq, t) = (self.last_seq, self.last_t.unwrap_or(0));
        for i in 0..self.plan.events.len() {
            self.stop(i, "end_of_stream", seq, t, events);
        }
        if let Some(inp) = self.input.as_mut() {
            inp.stop_reading();
            // Items that arrived after the last frame were never applied: the rig gets a NAK
            // (a replay has nothing left here: its triggers all fall on recorded frames).
            let mut late = Vec::new();
            inp.pending(u64::MAX, &mut late);
            for item in late {
                match item {
                    Incoming::Command { cmd_seq, cmd, origin } => {
                        let text = cmd.text(&self.catalog);
                        let reason = "the stream ended before it could apply";
                        if origin == Origin::Serial {
                            let s = cmd_seq.map(|s| s.to_string()).unwrap_or_else(|| "-".into());
                            inp.reply(&format!("NAK {s} {reason}"));
                        }
                        events.push(json!({"event": "nak", "seq": seq, "t_ns": t, "cmd_seq": cmd_seq,
                                           "command": text, "reason": reason}));
                    }
                    Incoming::Rejected { cmd_seq, reason, raw } => events.push(json!({
                        "event": "nak", "seq": seq, "t_ns": t, "cmd_seq": cmd_seq, "reason": reason, "raw": raw})),
                    Incoming::Notice { message } => {
                        events.push(json!({"event": "trigger_notice", "seq": seq, "t_ns": t, "message": message}))
                    }
                }
            }
            inp.finish();
        }
    }
}
