//! Validation of `[[events]]`, `[triggers]` and `[campaign]`: the whole file is checked before
//! a run and every problem is reported with `file:line`, the event and field, and the accepted
//! values.

use super::{Baseline, Campaign, Chance, EventSpec, ParamRamp, Ramp, Repeat, Start, Tick, TriggerSettings, Unit, ms};
use crate::config::{FaultConfig, line_of};
use crate::faults::{ParamKind, ParamSpec, registry};
use crate::trigger::{EdgeMode, LineTrigger, ModemLine, TriggerError, valid_name};
use std::collections::BTreeMap;
use thiserror::Error;
use toml::{Spanned, Value};

type Map = BTreeMap<String, Spanned<Value>>;

/// One problem in a campaign file.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    pub line: usize,
    /// What is wrong where, e.g. `event 'flash' field 'duration_s'`.
    pub what: String,
    pub message: String,
}

/// Errors of campaigns and their trigger inputs.
#[derive(Debug, Error)]
pub enum ScheduleError {
    /// Every problem found in the file, one per line of the message.
    #[error("{}", render(.file, .problems))]
    Invalid { file: String, problems: Vec<Problem> },
    #[error(transparent)]
    Trigger(#[from] TriggerError),
    #[error("{0}")]
    Options(String),
}

fn render(file: &str, problems: &[Problem]) -> String {
    problems.iter().map(|p| format!("{file}:{}: {}: {}", p.line, p.what, p.message)).collect::<Vec<_>>().join("\n")
}

/// Fields of an `[[events]]` entry.
pub const EVENT_FIELDS: &[&str] = &[
    "name",
    "effect",
    "effect_index",
    "at_frame",
    "at_s",
    "trigger",
    "rate_hz",
    "p_per_frame",
    "window_frames",
    "window_s",
    "duration_frames",
    "duration_s",
    "repeat",
    "period_frames",
    "period_s",
    "enable",
    "ramp_unit",
    "params",
];
const START_FIELDS: &[&str] = &["at_frame", "at_s", "trigger", "rate_hz", "p_per_frame"];
/// Keys of `[triggers]`.
pub const TRIGGER_FIELDS: &[&str] =
    &["armed", "port", "baud", "max_line_bytes", "partial_timeout_ms", "poll_ms", "debounce_polls", "lines"];
/// Keys of `[campaign]`.
pub const CAMPAIGN_FIELDS: &[&str] = &["name", "description"];
/// Longest time value accepted (s): 100 days.
const MAX_SECONDS: f64 = 8.64e6;
/// Occurrences compared per event when looking for contradictory overlaps.
const OVERLAP_CHECK_OCCURRENCES: u64 = 10_000;

#[derive(serde::Deserialize)]
struct Raw {
    #[serde(default)]
    effects: Vec<Spanned<Map>>,
    #[serde(default)]
    events: Vec<Spanned<Map>>,
    #[serde(default)]
    triggers: Option<Spanned<Map>>,
    #[serde(default)]
    campaign: Option<Spanned<Map>>,
}

#[derive(serde::Deserialize)]
struct RawParamSpans {
    #[serde(default)]
    events: Vec<RawEventParams>,
}
#[derive(serde::Deserialize)]
struct RawEventParams {
    #[serde(default)]
    params: Option<Map>,
}
#[derive(serde::Deserialize)]
struct RawLineSpans {
    #[serde(default)]
    triggers: Option<RawTriggerLines>,
}
#[derive(serde::Deserialize)]
struct RawTriggerLines {
    #[serde(default)]
    lines: Option<Map>,
}

struct Ctx<'a> {
    text: &'a str,
    problems: Vec<Problem>,
}

impl Ctx<'_> {
    fn line(&self, v: &Spanned<Value>) -> usize {
        line_of(self.text, v.span().start)
    }
    fn push(&mut self, line: usize, what: impl Into<String>, message: impl Into<String>) {
        self.problems.push(Problem { line, what: what.into(), message: message.into() });
    }
}

/// 64-bit FNV-1a of the text: identifies the campaign a log was made with.
pub fn fingerprint(text: &str) -> u64 {
    text.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
}

fn number(v: &Value) -> Option<f64> {
    match v {
        Value::Integer(i) => Some(*i as f64),
        Value::Float(f) if f.is_finite() => Some(*f),
        _ => None,
    }
}

fn seconds_to_ns(s: f64) -> u64 {
    (s * 1e9).round() as u64
}

/// Value of a parameter from TOML (number, boolean or choice word) by the parameter's kind.
fn param_value(spec: &ParamSpec, effect: &'static str, v: &Value) -> Result<f64, String> {
    let x = match (spec.kind, v) {
        (ParamKind::Choice(c), Value::String(w)) => match c.iter().position(|x| x == w) {
            Some(k) => k as f64,
            None => {
                return Err(format!("{effect}.{} = '{w}' is not accepted; accepted: {}", spec.name, spec.range_text()));
            }
        },
        (ParamKind::Bool, Value::Boolean(b)) => f64::from(u8::from(*b)),
        (ParamKind::Int | ParamKind::Float, v) if number(v).is_some() => number(v).unwrap_or(f64::NAN),
        (_, other) => {
            return Err(format!("{effect}.{} = {other} is not accepted; accepted: {}", spec.name, spec.range_text()));
        }
    };
    spec.check(effect, x).map_err(|e| e.to_string())
}

/// Validate the campaign parts of `cfg`.
pub fn campaign(cfg: &FaultConfig) -> Result<Campaign, super::ScheduleError> {
    // A config built in code has no text: validate its TOML form.
    let owned;
    let text: &str = if cfg.text.is_empty() {
        owned = cfg.to_toml();
        &owned
    } else {
        &cfg.text
    };
    let file = cfg.origin.clone();
    let mut cx = Ctx { text, problems: Vec::new() };
    let invalid = |problems: Vec<Problem>| super::ScheduleError::Invalid { file: file.clone(), problems };

    let raw: Raw = match toml::from_str(text) {
        Ok(r) => r,
        Err(e) => {
            let line = e.span().map(|s| line_of(text, s.start)).unwrap_or(1);
            return Err(invalid(vec![Problem {
                line,
                what: "campaign".into(),
                message: format!("{} ([[events]] entries, [triggers] and [campaign] must be tables)", e.message()),
            }]));
        }
    };
    let param_spans: Vec<Option<Map>> = toml::from_str::<RawParamSpans>(text)
        .map(|r| r.events.into_iter().map(|e| e.params).collect())
        .unwrap_or_default();
    let line_spans: Option<Map> =
        toml::from_str::<RawLineSpans>(text).ok().and_then(|r| r.triggers).and_then(|t| t.lines);

    // Baselines (config order = chain index).
    let mut baseline: Vec<Baseline> = Vec::new();
    let mut explicit_enabled: Vec<bool> = Vec::new();
    for (i, e) in cfg.effects.iter().enumerate() {
        let Some(reg) = registry::find(&e.name) else {
            cx.push(e.line, format!("effect '{}'", e.name), "unknown effect");
            continue;
        };
        baseline.push(Baseline { name: reg.info.name, info: reg.info, params: e.params, enabled: e.enabled });
        explicit_enabled.push(raw.effects.get(i).map(|m| m.get_ref().contains_key("enabled")).unwrap_or(true));
    }
    if !cx.problems.is_empty() {
        return Err(invalid(cx.problems));
    }

    // [campaign]
    let (mut name, mut description) = (None, None);
    if let Some(c) = &raw.campaign {
        for (k, v) in c.get_ref() {
            let line = cx.line(v);
            match (k.as_str(), v.get_ref()) {
                ("name", Value::String(s)) => name = Some(s.clone()),
                ("description", Value::String(s)) => description = Some(s.clone()),
                ("name" | "description", other) => cx.push(
                    line,
                    format!("[campaign] field '{k}'"),
                    format!("{other} is not accepted; accepted: a string"),
                ),
                _ => cx.push(
                    line,
                    format!("[campaign] field '{k}'"),
                    format!("unknown field; accepted: {}", CAMPAIGN_FIELDS.join(", ")),
                ),
            }
        }
    }

    // [[events]]
    let mut events: Vec<EventSpec> = Vec::new();
    for (k, entry) in raw.events.iter().enumerate() {
        let spans = param_spans.get(k).and_then(|p| p.as_ref());
        if let Some(ev) = parse_event(&mut cx, k, entry, spans, cfg, &baseline) {
            events.push(ev);
        }
    }
    // Unique names.
    for (i, e) in events.iter().enumerate() {
        if let Some(prev) = events[..i].iter().find(|p| p.name == e.name) {
            cx.push(
                e.line,
                format!("event '{}' field 'name'", e.name),
                format!("duplicate event name (first at line {}); names must be unique", prev.line),
            );
        }
    }
    let mut by_name: BTreeMap<String, Vec<usize>> = BTreeMap::new();
    for (i, e) in events.iter().enumerate() {
        by_name.entry(e.name.clone()).or_default().push(i);
        if let Start::Trigger(t) = &e.start {
            let v = by_name.entry(t.clone()).or_default();
            if !v.contains(&i) {
                v.push(i);
            }
        }
    }
    check_overlaps(&mut cx, &events);

    // Events that change nothing.
    for e in &events {
        let b = &baseline[e.effect];
        if e.enable && e.params.is_empty() && b.enabled && explicit_enabled[e.effect] {
            cx.push(
                e.line,
                format!("event '{}'", e.name),
                format!(
                    "changes nothing: '{}' is always enabled (enabled = true) and the event sets no params",
                    b.name
                ),
            );
        }
    }
    // Effects driven by events only start disabled unless `enabled` is written.
    for (i, b) in baseline.iter_mut().enumerate() {
        if !explicit_enabled[i] && events.iter().any(|e| e.effect == i && e.enable) {
            b.enabled = false;
        }
    }

    // [triggers]
    let triggers = parse_triggers(&mut cx, raw.triggers.as_ref(), line_spans.as_ref(), &by_name);

    if !cx.problems.is_empty() {
        cx.problems.sort_by_key(|p| p.line);
        return Err(invalid(cx.problems));
    }
    Ok(Campaign {
        origin: file,
        seed: cfg.seed,
        fingerprint: fingerprint(text),
        name,
        description,
        events,
        triggers,
        baseline,
        by_name,
    })
}

fn parse_event(
    cx: &mut Ctx<'_>,
    k: usize,
    entry: &Spanned<Map>,
    param_spans: Option<&Map>,
    cfg: &FaultConfig,
    baseline: &[Baseline],
) -> Option<EventSpec> {
    let line = line_of(cx.text, entry.span().start);
    let map = entry.get_ref();
    let before = cx.problems.len();
    let name = match map.get("name") {
        Some(v) => match v.get_ref() {
            Value::String(s) if valid_name(s) => s.clone(),
            other => {
                let l = cx.line(v);
                cx.push(
                    l,
                    format!("event #{} field 'name'", k + 1),
                    format!("{other} is not accepted; accepted: 1..=64 characters of letters, digits, _ . -"),
                );
                format!("#{}", k + 1)
            }
        },
        None => format!("event{}", k + 1),
    };
    let what = |field: &str| format!("event '{name}' field '{field}'");

    for (key, v) in map {
        if !EVENT_FIELDS.contains(&key.as_str()) {
            let l = cx.line(v);
            cx.push(l, what(key), format!("unknown field; accepted: {}", EVENT_FIELDS.join(", ")));
        }
    }

    // Typed getters that record problems.
    let get = |key: &str| map.get(key);
    let non_neg_int = |cx: &mut Ctx<'_>, key: &str, min: u64, accepted: &str| -> Option<u64> {
        let v = get(key)?;
        match v.get_ref() {
            Value::Integer(i) if *i >= min as i64 => Some(*i as u64),
            other => {
                let l = cx.line(v);
                cx.push(l, what(key), format!("{other} is not accepted; accepted: {accepted}"));
                None
            }
        }
    };
    let seconds = |cx: &mut Ctx<'_>, key: &str, positive: bool| -> Option<u64> {
        let v = get(key)?;
        match number(v.get_ref()) {
            Some(s) if (if positive { s > 0.0 } else { s >= 0.0 }) && s <= MAX_SECONDS => Some(seconds_to_ns(s)),
            _ => {
                let l = cx.line(v);
                let rel = if positive { ">" } else { ">=" };
                cx.push(
                    l,
                    what(key),
                    format!("{} is not accepted; accepted: seconds {rel} 0 and <= {MAX_SECONDS}", v.get_ref()),
                );
                None
            }
        }
    };

    // Target effect.
    let configured =
        || cfg.effects.iter().enumerate().map(|(i, e)| format!("{}#{i}", e.name)).collect::<Vec<_>>().join(", ");
    let index = non_neg_int(cx, "effect_index", 0, "the position of the effect in [[effects]], counting from 0");
    let effect = match (get("effect"), index) {
        (None, None) => {
            cx.push(line, what("effect"), format!("missing; name a configured effect: {}", configured()));
            None
        }
        (None, Some(i)) => {
            if i as usize >= baseline.len() {
                let l = get("effect_index").map(|v| cx.line(v)).unwrap_or(line);
                cx.push(
                    l,
                    what("effect_index"),
                    format!(
                        "{i} is out of range; accepted: 0..={} ({})",
                        baseline.len().saturating_sub(1),
                        configured()
                    ),
                );
                None
            } else {
                Some(i as usize)
            }
        }
        (Some(v), idx) => {
            let l = cx.line(v);
            match v.get_ref() {
                Value::String(s) => {
                    let hits: Vec<usize> =
                        cfg.effects.iter().enumerate().filter(|(_, e)| &e.name == s).map(|(i, _)| i).collect();
                    match (hits.len(), idx) {
                        (0, _) => {
                            let msg = if registry::find(s).is_some() {
                                format!(
                                    "'{s}' is not in [[effects]]; add an [[effects]] entry with name = \"{s}\" \
                                     (configured: {})",
                                    configured()
                                )
                            } else {
                                format!("unknown effect '{s}'; configured: {}", configured())
                            };
                            cx.push(l, what("effect"), msg);
                            None
                        }
                        (1, None) => Some(hits[0]),
                        (_, None) => {
                            let lines: Vec<String> = hits.iter().map(|&i| cfg.effects[i].line.to_string()).collect();
                            let idxs: Vec<String> = hits.iter().map(|i| i.to_string()).collect();
                            cx.push(
                                l,
                                what("effect"),
                                format!(
                                    "'{s}' is configured {} times (lines {}); add effect_index = one of {}",
                                    hits.len(),
                                    lines.join(", "),
                                    idxs.join(", ")
                                ),
                            );
                            None
                        }
                        (_, Some(i)) if hits.contains(&(i as usize)) => Some(i as usize),
                        (_, Some(i)) => {
                            let idxs: Vec<String> = hits.iter().map(|i| i.to_string()).collect();
                            cx.push(
                                l,
                                what("effect_index"),
                                format!("{i} is not a '{s}' entry; accepted: {}", idxs.join(", ")),
                            );
                            None
                        }
                    }
                }
                other => {
                    cx.push(l, what("effect"), format!("{other} is not accepted; accepted: an effect name"));
                    None
                }
            }
        }
    };

    // Start.
    let starts: Vec<&str> = START_FIELDS.iter().copied().filter(|f| map.contains_key(*f)).collect();
    if starts.len() != 1 {
        let msg = if starts.is_empty() {
            format!("missing start; give exactly one of {}", START_FIELDS.join(", "))
        } else {
            format!("{} given; give exactly one of {}", starts.join(" and "), START_FIELDS.join(", "))
        };
        cx.push(line, what("start"), msg);
    }
    let mut start = None;
    if starts.len() == 1 {
        match starts[0] {
            "at_frame" => {
                start = non_neg_int(cx, "at_frame", 0, "a frame seq >= 0").map(|f| Start::At(Tick::Frames(f)))
            }
            "at_s" => start = seconds(cx, "at_s", false).map(|n| Start::At(Tick::Nanos(n))),
            "trigger" => {
                if let Some(v) = get("trigger") {
                    match v.get_ref() {
                        Value::String(s) if valid_name(s) => start = Some(Start::Trigger(s.clone())),
                        other => {
                            let l = cx.line(v);
                            cx.push(
                                l,
                                what("trigger"),
                                format!(
                                    "{other} is not accepted; accepted: 1..=64 characters of letters, digits, _ . -"
                                ),
                            )
                        }
                    }
                }
            }
            "rate_hz" | "p_per_frame" => {
                let key = starts[0];
                if let Some(v) = get(key) {
                    let x = number(v.get_ref());
                    let chance = match (key, x) {
                        ("rate_hz", Some(r)) if r > 0.0 && r <= 1e6 => Some(Chance::RateHz(r)),
                        ("p_per_frame", Some(p)) if p > 0.0 && p <= 1.0 => Some(Chance::PerFrame(p)),
                        _ => {
                            let l = cx.line(v);
                            let acc = if key == "rate_hz" {
                                "events per second of stream time, 0 < rate_hz <= 1e6"
                            } else {
                                "a probability per frame, 0 < p_per_frame <= 1"
                            };
                            cx.push(l, what(key), format!("{} is not accepted; accepted: {acc}", v.get_ref()));
                            None
                        }
                    };
                    let window = parse_window(cx, map, &what);
                    if let Some(chance) = chance {
                        start = Some(Start::Random { chance, window: window.flatten() });
                    }
                }
            }
            _ => {}
        }
    }
    let random =
        matches!(start, Some(Start::Random { .. })) || map.contains_key("rate_hz") || map.contains_key("p_per_frame");
    if !random {
        for key in ["window_frames", "window_s"] {
            if let Some(v) = get(key) {
                let l = cx.line(v);
                cx.push(l, what(key), "a window applies only to random events (rate_hz, p_per_frame)");
            }
        }
    }

    // Duration.
    let mut duration = match (get("duration_frames").is_some(), get("duration_s").is_some()) {
        (true, true) => {
            cx.push(line, what("duration"), "give duration_frames or duration_s, not both");
            None
        }
        (true, false) => non_neg_int(cx, "duration_frames", 1, "an integer number of frames >= 1").map(Tick::Frames),
        (false, true) => seconds(cx, "duration_s", true).map(Tick::Nanos),
        (false, false) => None,
    };
    if random && duration.is_none() && get("duration_frames").is_none() && get("duration_s").is_none() {
        // A random event without a duration lasts one frame.
        duration = Some(Tick::Frames(1));
    }

    // Repeat and period.
    let repeat = match get("repeat") {
        None => Repeat::Count(1),
        Some(v) => match v.get_ref() {
            Value::Integer(i) if *i >= 1 => Repeat::Count(*i as u64),
            Value::String(s) if s == "forever" => Repeat::Forever,
            other => {
                let l = cx.line(v);
                cx.push(
                    l,
                    what("repeat"),
                    format!("{other} is not accepted; accepted: an integer >= 1 or \"forever\""),
                );
                Repeat::Count(1)
            }
        },
    };
    let period = match (get("period_frames").is_some(), get("period_s").is_some()) {
        (true, true) => {
            cx.push(line, what("period"), "give period_frames or period_s, not both");
            None
        }
        (true, false) => non_neg_int(cx, "period_frames", 1, "an integer number of frames >= 1").map(Tick::Frames),
        (false, true) => seconds(cx, "period_s", true).map(Tick::Nanos),
        (false, false) => None,
    };
    let repeats = repeat != Repeat::Count(1);
    if random && get("repeat").is_some() {
        let l = get("repeat").map(|v| cx.line(v)).unwrap_or(line);
        cx.push(l, what("repeat"), "random events repeat by themselves; remove repeat (and period)");
    } else if repeats && period.is_none() && !(get("period_frames").is_some() || get("period_s").is_some()) {
        cx.push(line, what("period"), "repeat needs period_frames or period_s (time from one start to the next)");
    } else if !repeats && period.is_some() {
        cx.push(line, what("period"), "a period needs repeat > 1 or repeat = \"forever\"");
    }
    if repeats && duration.is_none() && !random {
        cx.push(line, what("duration"), "a repeating event needs duration_frames or duration_s");
    }
    if let (Some(p), Some(d)) = (period, duration)
        && p.unit() == d.unit()
        && p.raw() < d.raw()
    {
        cx.push(
            line,
            what("period"),
            format!(
                "period {} {} is shorter than the duration {} {}; occurrences would overlap",
                p.value(),
                p.unit().name(),
                d.value(),
                d.unit().name()
            ),
        );
    }

    // enable, ramp_unit.
    let enable = match get("enable") {
        None => true,
        Some(v) => match v.get_ref() {
            Value::Boolean(b) => *b,
            other => {
                let l = cx.line(v);
                cx.push(l, what("enable"), format!("{other} is not accepted; accepted: true or false"));
                true
            }
        },
    };
    let ramp_unit = match get("ramp_unit") {
        None => None,
        Some(v) => match v.get_ref() {
            Value::String(s) if s == "frames" => Some(Unit::Frames),
            Value::String(s) if s == "s" => Some(Unit::Seconds),
            other => {
                let l = cx.line(v);
                cx.push(l, what("ramp_unit"), format!("{other} is not accepted; accepted: \"frames\" or \"s\""));
                None
            }
        },
    };
    let base_unit = ramp_unit.or(duration.map(|d| d.unit())).or(match &start {
        Some(Start::At(t)) => Some(t.unit()),
        _ => None,
    });

    // Params.
    let mut params = Vec::new();
    if let Some(v) = get("params") {
        let pline = cx.line(v);
        match v.get_ref() {
            Value::Table(t) => {
                if !enable && !t.is_empty() {
                    cx.push(pline, what("params"), "params have no effect while enable = false");
                }
                if let Some(ei) = effect {
                    let info = baseline[ei].info;
                    for (pname, pval) in t {
                        let l = param_spans.and_then(|m| m.get(pname)).map(|s| cx.line(s)).unwrap_or(pline);
                        let pwhat = format!("event '{name}' field 'params.{pname}'");
                        let Some((pi, spec)) = info.param(pname) else {
                            cx.push(
                                l,
                                pwhat,
                                format!(
                                    "{}: unknown parameter; accepted: {}",
                                    info.name,
                                    info.params.iter().map(|p| p.name).collect::<Vec<_>>().join(", ")
                                ),
                            );
                            continue;
                        };
                        match parse_ramp(spec, info.name, pval, duration, base_unit) {
                            Ok(ramp) => params.push(ParamRamp { param: pi, spec, ramp, line: l }),
                            Err(msg) => cx.push(l, pwhat, msg),
                        }
                    }
                }
            }
            other => cx.push(
                pline,
                what("params"),
                format!("{other} is not accepted; accepted: a table of parameter = value or ramp"),
            ),
        }
    }

    if cx.problems.len() > before {
        return None;
    }
    let effect = effect?;
    Some(EventSpec {
        name,
        line,
        effect,
        effect_name: baseline[effect].name,
        start: start?,
        duration,
        repeat,
        period,
        enable,
        params,
        ramp_unit: base_unit,
    })
}

fn parse_window(cx: &mut Ctx<'_>, map: &Map, what: &dyn Fn(&str) -> String) -> Option<Option<(Tick, Tick)>> {
    let mut out = None;
    for (key, unit) in [("window_frames", Unit::Frames), ("window_s", Unit::Seconds)] {
        let Some(v) = map.get(key) else { continue };
        let l = cx.line(v);
        let pair = match v.get_ref() {
            Value::Array(a) if a.len() == 2 => match (number(&a[0]), number(&a[1])) {
                (Some(x), Some(y)) if x >= 0.0 && x < y && y <= MAX_SECONDS * 1e3 => Some((x, y)),
                _ => None,
            },
            _ => None,
        };
        let Some((x, y)) = pair else {
            cx.push(
                l,
                what(key),
                format!("{} is not accepted; accepted: [from, to] with 0 <= from < to ({})", v.get_ref(), unit.name()),
            );
            return None;
        };
        if out.is_some() {
            cx.push(l, what(key), "give window_frames or window_s, not both");
            return None;
        }
        out = Some(match unit {
            Unit::Frames if x.fract() == 0.0 && y.fract() == 0.0 => (Tick::Frames(x as u64), Tick::Frames(y as u64)),
            Unit::Frames => {
                cx.push(l, what(key), "frame windows take whole frame numbers");
                return None;
            }
            Unit::Seconds => (Tick::Nanos(seconds_to_ns(x)), Tick::Nanos(seconds_to_ns(y))),
        });
    }
    Some(out)
}

fn parse_ramp(
    spec: &'static ParamSpec,
    effect: &'static str,
    v: &Value,
    duration: Option<Tick>,
    unit: Option<Unit>,
) -> Result<Ramp, String> {
    let interpolable = matches!(spec.kind, ParamKind::Float | ParamKind::Int);
    let Value::Table(t) = v else {
        return param_value(spec, effect, v).map(Ramp::Const);
    };
    const KINDS: &str = "a value, { linear = [from, to] }, { keyframes = [[t, v], ...] } or { steps = [[t, v], ...] }";
    if t.len() != 1 {
        return Err(format!("a ramp has exactly one key; accepted: {KINDS}"));
    }
    let (kind, body) = t.iter().next().map(|(k, v)| (k.as_str(), v)).ok_or("empty ramp")?;
    let need_unit = || {
        unit.ok_or_else(|| {
            "this ramp needs a time base: give duration_frames / duration_s, a scheduled start, or ramp_unit"
                .to_string()
        })
    };
    match kind {
        "linear" => {
            if !interpolable {
                return Err(format!(
                    "{effect}.{} ({}) cannot be interpolated; use steps",
                    spec.name,
                    spec.range_text()
                ));
            }
            let Some(d) = duration else {
                return Err("a linear ramp needs duration_frames or duration_s (it spans the event)".into());
            };
            if unit.is_some_and(|u| u != d.unit()) {
                return Err(format!("a linear ramp runs over the duration, in {}; remove ramp_unit", d.unit().name()));
            }
            let pair = match body {
                Value::Array(a) if a.len() == 2 => Some((&a[0], &a[1])),
                _ => None,
            };
            let Some((a, b)) = pair else {
                return Err(format!("linear = {body} is not accepted; accepted: [from, to]"));
            };
            let from = param_value(spec, effect, a)?;
            let to = param_value(spec, effect, b)?;
            Ok(Ramp::Linear { from, to, over: d.value() })
        }
        "keyframes" | "steps" => {
            if kind == "keyframes" && !interpolable {
                return Err(format!(
                    "{effect}.{} ({}) cannot be interpolated; use steps",
                    spec.name,
                    spec.range_text()
                ));
            }
            need_unit()?;
            let Value::Array(a) = body else {
                return Err(format!("{kind} = {body} is not accepted; accepted: [[t, value], ...]"));
            };
            if a.is_empty() {
                return Err(format!("{kind} needs at least one [t, value] point"));
            }
            let mut pts = Vec::with_capacity(a.len());
            for (i, p) in a.iter().enumerate() {
                let pair = match p {
                    Value::Array(q) if q.len() == 2 => number(&q[0]).map(|t| (t, &q[1])),
                    _ => None,
                };
                let Some((t, val)) = pair else {
                    return Err(format!("{kind}[{i}] = {p} is not accepted; accepted: [t, value] with t a number"));
                };
                if t < 0.0 {
                    return Err(format!("{kind}[{i}]: time {t} is negative; accepted: t >= 0"));
                }
                if let Some(&(prev, _)) = pts.last()
                    && t <= prev
                {
                    return Err(format!("{kind}[{i}]: times must increase ({prev} then {t})"));
                }
                if i == 0 && t != 0.0 {
                    return Err(format!("{kind}[0]: the first point must be at t = 0 (the event's start), got {t}"));
                }
                let x = param_value(spec, effect, val).map_err(|e| format!("{kind}[{i}]: {e}"))?;
                pts.push((t, x));
            }
            Ok(if kind == "keyframes" { Ramp::Keyframes(pts) } else { Ramp::Steps(pts) })
        }
        other => Err(format!("unknown ramp '{other}'; accepted: {KINDS}")),
    }
}

/// Clock on which all of an event's scheduled times are given, if one.
fn single_clock(e: &EventSpec) -> Option<Unit> {
    let u = e.start_unit()?;
    if e.duration.is_some_and(|d| d.unit() != u) || e.period.is_some_and(|p| p.unit() != u) {
        return None;
    }
    Some(u)
}

/// Occurrence intervals `[start, end)` of a scheduled event on its own clock.
fn occurrences(e: &EventSpec) -> Vec<(u64, u64)> {
    let Start::At(at) = e.start else { return Vec::new() };
    let mut out = Vec::new();
    let mut k = 0u64;
    while e.repeat.allows(k) && k < OVERLAP_CHECK_OCCURRENCES {
        let s = at.raw().saturating_add(k.saturating_mul(e.period.map(|p| p.raw()).unwrap_or(0)));
        let end = e.duration.map(|d| s.saturating_add(d.raw())).unwrap_or(u64::MAX);
        out.push((s, end));
        if e.period.is_none() {
            break;
        }
        k += 1;
    }
    out
}

fn check_overlaps(cx: &mut Ctx<'_>, events: &[EventSpec]) {
    for (j, b) in events.iter().enumerate() {
        for a in &events[..j] {
            if a.effect != b.effect {
                continue;
            }
            let (Some(ua), Some(ub)) = (single_clock(a), single_clock(b)) else { continue };
            if ua != ub {
                continue;
            }
            let shared: Vec<&str> =
                a.params.iter().filter(|p| b.params.iter().any(|q| q.param == p.param)).map(|p| p.spec.name).collect();
            if shared.is_empty() && a.enable == b.enable {
                continue;
            }
            let (oa, ob) = (occurrences(a), occurrences(b));
            let (mut i, mut k) = (0, 0);
            while i < oa.len() && k < ob.len() {
                let (s1, e1) = oa[i];
                let (s2, e2) = ob[k];
                if s1 < e2 && s2 < e1 {
                    let conflict = if shared.is_empty() {
                        "one enables and the other disables the effect".to_string()
                    } else {
                        format!("both set {}", shared.join(", "))
                    };
                    let unit = ua.name();
                    let scale = if ua == Unit::Seconds { 1e-9 } else { 1.0 };
                    cx.push(
                        b.line,
                        format!("event '{}'", b.name),
                        format!(
                            "overlaps event '{}' (line {}) on '{}' from {} {unit} and {conflict}; \
                             move one or merge them into one event with keyframes",
                            a.name,
                            a.line,
                            b.effect_name,
                            s1.max(s2) as f64 * scale,
                        ),
                    );
                    break;
                }
                if e1 <= e2 {
                    i += 1;
                } else {
                    k += 1;
                }
            }
        }
    }
}

fn parse_triggers(
    cx: &mut Ctx<'_>,
    t: Option<&Spanned<Map>>,
    line_spans: Option<&Map>,
    by_name: &BTreeMap<String, Vec<usize>>,
) -> TriggerSettings {
    let mut s = TriggerSettings::default();
    let Some(t) = t else { return s };
    let what = |f: &str| format!("[triggers] field '{f}'");
    for (key, v) in t.get_ref() {
        let l = cx.line(v);
        let int_in = |cx: &mut Ctx<'_>, lo: i64, hi: i64, unit: &str| -> Option<u64> {
            match v.get_ref() {
                Value::Integer(i) if (lo..=hi).contains(i) => Some(*i as u64),
                other => {
                    cx.push(l, what(key), format!("{other} is not accepted; accepted: integer {lo}..={hi} {unit}"));
                    None
                }
            }
        };
        match key.as_str() {
            "armed" => match v.get_ref() {
                Value::Boolean(b) => s.armed = *b,
                other => cx.push(l, what(key), format!("{other} is not accepted; accepted: true or false")),
            },
            "port" => match v.get_ref() {
                Value::String(p) if !p.is_empty() => s.port = Some(p.clone()),
                other => cx.push(l, what(key), format!("{other} is not accepted; accepted: a device path")),
            },
            "baud" => s.baud = int_in(cx, 50, 4_000_000, "baud").map(|b| b as u32),
            "max_line_bytes" => {
                if let Some(n) = int_in(cx, 16, 4096, "bytes") {
                    s.serial.max_line_bytes = n as usize;
                }
            }
            "partial_timeout_ms" => {
                if let Some(n) = int_in(cx, 10, 60_000, "ms") {
                    s.serial.partial_timeout = ms(n);
                }
            }
            "poll_ms" => {
                if let Some(n) = int_in(cx, 1, 1000, "ms") {
                    s.serial.poll = ms(n);
                }
            }
            "debounce_polls" => {
                if let Some(n) = int_in(cx, 0, 100, "polls") {
                    s.serial.debounce_polls = n as u32;
                }
            }
            "lines" => match v.get_ref() {
                Value::Table(lines) => {
                    for (lname, lv) in lines {
                        let ll = line_spans.and_then(|m| m.get(lname)).map(|s| cx.line(s)).unwrap_or(l);
                        let lwhat = format!("[triggers] field 'lines.{lname}'");
                        let Some(line) = ModemLine::parse(lname) else {
                            cx.push(ll, lwhat, "unknown modem-status line; accepted: cts, dsr, dcd, ri");
                            continue;
                        };
                        let (trigger, edge) = match lv {
                            Value::String(n) => (Some(n.clone()), Some(EdgeMode::Rising)),
                            Value::Table(m) => {
                                let mut bad = None;
                                for k in m.keys() {
                                    if k != "trigger" && k != "edge" {
                                        bad = Some(k.clone());
                                    }
                                }
                                if let Some(k) = bad {
                                    cx.push(ll, lwhat.clone(), format!("unknown key '{k}'; accepted: trigger, edge"));
                                }
                                let trig = match m.get("trigger") {
                                    Some(Value::String(n)) => Some(n.clone()),
                                    _ => None,
                                };
                                let edge = match m.get("edge") {
                                    None => Some(EdgeMode::Rising),
                                    Some(Value::String(e)) => EdgeMode::parse(e),
                                    Some(_) => None,
                                };
                                if edge.is_none() {
                                    cx.push(ll, lwhat.clone(), format!("edge: accepted: {}", EdgeMode::NAMES));
                                }
                                (trig, edge)
                            }
                            _ => (None, None),
                        };
                        match (trigger, edge) {
                            (Some(n), Some(edge)) if by_name.contains_key(&n) => {
                                s.serial.lines.push(LineTrigger { line, trigger: n, edge })
                            }
                            (Some(n), Some(_)) => cx.push(
                                ll,
                                lwhat,
                                format!(
                                    "no event or trigger named '{n}'; accepted: {}",
                                    by_name.keys().cloned().collect::<Vec<_>>().join(", ")
                                ),
                            ),
                            (None, _) => cx.push(
                                ll,
                                lwhat,
                                "accepted: \"<trigger>\" or { trigger = \"<trigger>\", edge = \"rising\" }",
                            ),
                            _ => {}
                        }
                    }
                }
                other => cx.push(
                    l,
                    what(key),
                    format!("{other} is not accepted; accepted: a table like {{ cts = \"flash\" }}"),
                ),
            },
            _ => cx.push(l, what(key), format!("unknown field; accepted: {}", TRIGGER_FIELDS.join(", "))),
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Campaign, String> {
        let cfg = FaultConfig::parse(text, "c.toml").map_err(|e| e.to_string())?;
        Campaign::from_config(&cfg).map_err(|e| e.to_string())
    }

    #[test]
    fn implied_disable_and_by_name() {
        let c = parse(
            "seed = 3\n[[effects]]\nname = \"gain_offset\"\n[[effects]]\nname = \"row_noise\"\nenabled = true\n\
             [[events]]\nname = \"a\"\neffect = \"gain_offset\"\ntrigger = \"flash\"\n\
             [[events]]\neffect = \"row_noise\"\nat_frame = 3\n[events.params]\nsigma_dn = 4.0\n",
        )
        .unwrap();
        assert!(!c.baseline[0].enabled, "driven only by events");
        assert!(c.baseline[1].enabled, "explicitly enabled");
        assert_eq!(c.by_name["flash"], vec![0]);
        assert_eq!(c.by_name["a"], vec![0]);
        assert_eq!(c.by_name["event2"], vec![1]);
        // Line 15: `sigma_dn = 4.0` (the string has 15 lines).
        assert_eq!(c.events[1].params[0].line, 15);
    }

    #[test]
    fn fingerprint_changes_with_text() {
        assert_ne!(fingerprint("a"), fingerprint("b"));
    }
}
