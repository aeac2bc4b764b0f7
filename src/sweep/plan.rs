//! The sweep plan: what to run (source, SUT, severity grids, seeds, pairs) and its cells.

use crate::faults::{ParamKind, Params, Scale, registry};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Default source: small synthetic frames, so a default sweep is quick.
pub const DEFAULT_SOURCE: &str = "synth:?width=320&height=240&frames=6&spin_dps=20";
/// Effects left out of the default list: they change timing, not pixels (in a batch sweep a
/// dropped or delayed frame is never shown to the SUT).
pub const TIMING_EFFECTS: &[&str] = &["frame_freeze", "frame_drop", "frame_delay", "jitter", "reorder"];

/// Severity axis of one effect: `param` goes from `from` (level 0, the clean baseline) to `to`
/// (the last level), linearly or geometrically (`log`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Axis {
    pub param: String,
    pub from: f64,
    pub to: f64,
    pub log: bool,
}

/// Default axes where the registry's first canonical parameter or its range would make a poor
/// severity grid (reversed severity, identity in the middle of the range, log-scaled gains).
/// Every other effect sweeps its first canonical numeric parameter from its minimum to its
/// maximum.
const AXIS_OVERRIDES: &[(&str, &str, f64, f64, bool)] = &[
    ("lens_flare", "intensity", 0.0, 1.0, false),
    ("channel_shift", "dx_r", 0.0, 64.0, false),
    ("shot_noise", "gain_e_per_dn", 1e6, 0.01, true),
    ("blooming", "full_well_fraction", 1.0, 0.05, false),
    ("gain_offset", "gain", 1.0, 0.0, false),
    ("gamma", "gamma", 1.0, 10.0, false),
    ("jpeg", "quality", 100.0, 1.0, false),
];

/// The default severity axis of an effect (see [`AXIS_OVERRIDES`]); `base` decides for
/// `dark_current`, whose `doubling`/`arrhenius` models read the temperature, not `mean_dn`.
pub fn default_axis(name: &str, base: &Params) -> Result<Axis, String> {
    let reg = registry::find(name).ok_or_else(|| unknown_effect(name))?;
    if name == "dark_current" && base.choice("model") != "direct" {
        let t0 = base.get("temperature_c");
        return Ok(Axis { param: "temperature_c".into(), from: t0, to: 120.0, log: false });
    }
    if let Some(o) = AXIS_OVERRIDES.iter().find(|o| o.0 == name) {
        return Ok(Axis { param: o.1.into(), from: o.2, to: o.3, log: o.4 });
    }
    let p = reg
        .info
        .params
        .iter()
        .find(|p| p.canonical && matches!(p.kind, ParamKind::Float | ParamKind::Int))
        .ok_or_else(|| format!("effect {name} has no numeric canonical parameter to sweep; give `param`"))?;
    Ok(Axis { param: p.name.into(), from: p.min, to: p.max, log: p.scale == Scale::Log && p.min > 0.0 })
}

fn unknown_effect(name: &str) -> String {
    format!(
        "unknown effect '{name}'; accepted: {}",
        registry::all().iter().map(|r| r.info.name).collect::<Vec<_>>().join(", ")
    )
}

impl Axis {
    /// Value of level `k` of `n` (1..=n): `from + (to − from) k/n`, or `from (to/from)^(k/n)`
    /// when `log`; integer parameters are rounded.
    pub fn value(&self, k: usize, n: usize, int: bool) -> f64 {
        let f = k as f64 / n as f64;
        let v =
            if self.log { self.from * (self.to / self.from).powf(f) } else { self.from + (self.to - self.from) * f };
        if int { v.round() } else { v }
    }
}

/// One swept effect: its base parameters and the parameter value of each level (1..=n).
#[derive(Debug, Clone, Serialize)]
pub struct EffectGrid {
    pub name: String,
    pub param: String,
    /// Value at each level, mildest first.
    pub values: Vec<f64>,
    /// Every parameter of the effect at level 1 (the swept one changes per level).
    #[serde(serialize_with = "ser_params")]
    pub base: Params,
}

fn ser_params<S: serde::Serializer>(p: &Params, s: S) -> Result<S::Ok, S::Error> {
    use serde::ser::SerializeMap;
    let mut m = s.serialize_map(None)?;
    for (spec, v) in p.iter() {
        match spec.kind {
            ParamKind::Choice(c) => m.serialize_entry(spec.name, c.get(v as usize).copied().unwrap_or(""))?,
            _ => m.serialize_entry(spec.name, &v)?,
        }
    }
    m.end()
}

impl EffectGrid {
    /// Parameters at level `k` (1-based).
    pub fn params(&self, k: usize) -> Result<Params, String> {
        let mut p = self.base;
        p.set(&self.param, self.values[k - 1]).map_err(|e| e.to_string())?;
        Ok(p)
    }
}

/// A resolved sweep: everything that decides the results (written into every shard file and
/// into report.json, so merges can check they join the same sweep).
#[derive(Debug, Clone, Serialize)]
pub struct Plan {
    /// Source URI (a `files:` source's poses file is folded in as `poses=`).
    pub source: String,
    /// SUT command with `{in_dir}`, `{out_file}` (batch), `{camera}`, `{cell_dir}` and
    /// `{report}` (live) placeholders.
    pub sut: String,
    pub timeout_s: f64,
    pub seeds: Vec<u64>,
    /// A frame fails when the SUT gives no pose for it or its score is above this.
    pub tolerance: f64,
    /// Breaking point: the lowest level whose failure rate is at least this.
    pub threshold: f64,
    pub effects: Vec<EffectGrid>,
    /// Pairs of effects (indices into `effects`), both at the same level.
    pub pairs: Vec<(usize, usize)>,
    /// Live mode (frames streamed into a sink, poses reported per frame); none: batch.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub live: Option<super::live::LivePlan>,
}

/// What a cell runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum CellKind {
    /// No fault: the clean baseline.
    Baseline,
    /// One effect (index into `Plan::effects`) at a level (1-based).
    Effect { effect: usize, level: usize },
    /// Two effects at the same level (index into `Plan::pairs`).
    Pair { pair: usize, level: usize },
}

/// One cell: what and with which seed. `index` is its place in [`Plan::cells`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Cell {
    pub index: usize,
    #[serde(flatten)]
    pub kind: CellKind,
    pub seed: u64,
}

impl Plan {
    /// All cells in a fixed order: baseline per seed, then effect × level × seed, then pair ×
    /// level × seed.
    pub fn cells(&self) -> Vec<Cell> {
        let mut kinds = Vec::new();
        kinds.push(CellKind::Baseline);
        for (e, g) in self.effects.iter().enumerate() {
            for level in 1..=g.values.len() {
                kinds.push(CellKind::Effect { effect: e, level });
            }
        }
        for (p, (a, _)) in self.pairs.iter().enumerate() {
            for level in 1..=self.effects[*a].values.len() {
                kinds.push(CellKind::Pair { pair: p, level });
            }
        }
        let mut cells = Vec::new();
        for kind in kinds {
            for &seed in &self.seeds {
                cells.push(Cell { index: cells.len(), kind, seed });
            }
        }
        cells
    }

    /// Effects and parameters of a cell, in config order.
    pub fn chain_params(&self, kind: CellKind) -> Result<Vec<Params>, String> {
        Ok(match kind {
            CellKind::Baseline => vec![],
            CellKind::Effect { effect, level } => vec![self.effects[effect].params(level)?],
            CellKind::Pair { pair, level } => {
                let (a, b) = self.pairs[pair];
                vec![self.effects[a].params(level)?, self.effects[b].params(level)?]
            }
        })
    }

    /// Short name of a cell's fault, e.g. `defocus@3`, `defocus+gaussian_noise@2`, `baseline`.
    pub fn label(&self, kind: CellKind) -> String {
        match kind {
            CellKind::Baseline => "baseline".into(),
            CellKind::Effect { effect, level } => format!("{}@{level}", self.effects[effect].name),
            CellKind::Pair { pair, level } => {
                let (a, b) = self.pairs[pair];
                format!("{}+{}@{level}", self.effects[a].name, self.effects[b].name)
            }
        }
    }

    /// Canonical JSON of the plan (compared by `merge`).
    pub fn canonical(&self) -> String {
        serde_json::to_string(self).unwrap_or_default()
    }
}

/// An `[[effect]]` table: name, swept parameter, values, fixed parameters.
pub type GridSpec = (String, Option<String>, Option<Vec<f64>>, toml::Table);

/// Settings as read from a config file and the command line, before resolution.
#[derive(Debug, Clone, Default)]
pub struct Settings {
    pub source: Option<String>,
    pub poses: Option<String>,
    pub sut: Option<String>,
    pub timeout_s: Option<f64>,
    pub levels: Option<usize>,
    pub seeds: Option<Vec<u64>>,
    pub tolerance: Option<f64>,
    pub threshold: Option<f64>,
    /// Effect names with default grids.
    pub effects: Option<Vec<String>>,
    /// A fault campaign whose effects (and their parameters as the base) are swept.
    pub campaign: Option<String>,
    /// Explicit grids: name, param, values, fixed params (TOML table).
    pub grids: Vec<GridSpec>,
    pub pairs: Vec<(String, String)>,
    /// Live mode (`mode = "live"`, `--live`).
    pub live: Option<bool>,
    /// Live: sink URI (default `files:{in_dir}`).
    pub sink: Option<String>,
    /// Live: `stdout`, `udp:HOST:PORT`, `serial:DEVICE[?baud=N]` (default stdout).
    pub sut_report: Option<String>,
    pub frame_timeout_s: Option<f64>,
    pub startup_s: Option<f64>,
    /// Live: pacing, frames per second (default: none, lockstep only).
    pub fps: Option<f64>,
}

fn err(origin: &str, key: &str, msg: impl std::fmt::Display) -> String {
    format!("{origin}: {key}: {msg}")
}

impl Settings {
    /// Read a sweep config (TOML). Keys: `source`, `poses`, `sut`, `timeout_s`, `levels`,
    /// `seeds`, `tolerance`, `threshold`, `effects` (names), `campaign` (a fault config whose
    /// effects are swept), `pairs` (`[["a", "b"], ...]`) and `[[effect]]` tables (`name`,
    /// optional `param`, `values` and fixed parameters). Relative paths are relative to the file.
    pub fn load(path: &Path) -> Result<Settings, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        let origin = path.display().to_string();
        let table: toml::Table = toml::from_str(&text).map_err(|e| {
            let line = e.span().map(|s| crate::config::line_of(&text, s.start)).unwrap_or(1);
            format!("{origin}:{line}: {}", e.message())
        })?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let rel = |p: &str| -> String {
            let pb = Path::new(p);
            if pb.is_absolute() || pb.exists() { p.to_string() } else { dir.join(pb).display().to_string() }
        };
        let mut s = Settings::default();
        for (k, v) in &table {
            let bad = |m: &str| err(&origin, k, m);
            match k.as_str() {
                "source" => s.source = Some(v.as_str().ok_or_else(|| bad("expected a URI string"))?.to_string()),
                "poses" => s.poses = Some(rel(v.as_str().ok_or_else(|| bad("expected a file path"))?)),
                "sut" => s.sut = Some(v.as_str().ok_or_else(|| bad("expected a command string"))?.to_string()),
                "mode" => {
                    s.live = Some(match v.as_str() {
                        Some("live") => true,
                        Some("batch") => false,
                        _ => return Err(bad("expected \"batch\" or \"live\"")),
                    })
                }
                "sink" => s.sink = Some(v.as_str().ok_or_else(|| bad("expected a sink URI string"))?.to_string()),
                "sut_report" => {
                    s.sut_report = Some(
                        v.as_str()
                            .ok_or_else(|| bad("expected stdout, udp:HOST:PORT or serial:DEVICE[?baud=N]"))?
                            .to_string(),
                    )
                }
                "campaign" => s.campaign = Some(rel(v.as_str().ok_or_else(|| bad("expected a file path"))?)),
                "timeout_s" | "tolerance" | "threshold" | "frame_timeout_s" | "startup_s" | "fps" => {
                    let x = v
                        .as_float()
                        .or_else(|| v.as_integer().map(|i| i as f64))
                        .ok_or_else(|| bad("expected a number"))?;
                    match k.as_str() {
                        "timeout_s" => s.timeout_s = Some(x),
                        "frame_timeout_s" => s.frame_timeout_s = Some(x),
                        "startup_s" => s.startup_s = Some(x),
                        "fps" => s.fps = Some(x),
                        "tolerance" => s.tolerance = Some(x),
                        _ => s.threshold = Some(x),
                    }
                }
                "levels" => s.levels = Some(v.as_integer().ok_or_else(|| bad("expected an integer 1..=100"))? as usize),
                "seeds" => {
                    let a = v.as_array().ok_or_else(|| bad("expected an array of non-negative integers"))?;
                    s.seeds = Some(
                        a.iter()
                            .map(|x| x.as_integer().filter(|i| *i >= 0).map(|i| i as u64))
                            .collect::<Option<Vec<_>>>()
                            .ok_or_else(|| bad("expected an array of non-negative integers"))?,
                    );
                }
                "effects" => {
                    let a = v.as_array().ok_or_else(|| bad("expected an array of effect names"))?;
                    s.effects = Some(
                        a.iter()
                            .map(|x| x.as_str().map(str::to_string))
                            .collect::<Option<Vec<_>>>()
                            .ok_or_else(|| bad("expected an array of effect names"))?,
                    );
                }
                "pairs" => {
                    let a = v.as_array().ok_or_else(|| bad("expected [[\"a\", \"b\"], ...]"))?;
                    for p in a {
                        let pr = p
                            .as_array()
                            .filter(|p| p.len() == 2)
                            .and_then(|p| Some((p[0].as_str()?.to_string(), p[1].as_str()?.to_string())));
                        s.pairs.push(pr.ok_or_else(|| bad("expected [[\"a\", \"b\"], ...]"))?);
                    }
                }
                "effect" => {
                    let a = v.as_array().ok_or_else(|| bad("expected [[effect]] tables"))?;
                    for (i, t) in a.iter().enumerate() {
                        let key = format!("effect[{i}]");
                        let mut t = t.as_table().ok_or_else(|| err(&origin, &key, "expected a table"))?.clone();
                        let name = t
                            .remove("name")
                            .and_then(|n| n.as_str().map(str::to_string))
                            .ok_or_else(|| err(&origin, &key, "no `name`"))?;
                        let param = match t.remove("param") {
                            Some(p) => Some(
                                p.as_str().ok_or_else(|| err(&origin, &key, "`param` must be a name"))?.to_string(),
                            ),
                            None => None,
                        };
                        let values = match t.remove("values") {
                            Some(vs) => Some(
                                vs.as_array()
                                    .and_then(|a| {
                                        a.iter()
                                            .map(|x| x.as_float().or_else(|| x.as_integer().map(|i| i as f64)))
                                            .collect::<Option<Vec<_>>>()
                                    })
                                    .ok_or_else(|| err(&origin, &key, "`values` must be an array of numbers"))?,
                            ),
                            None => None,
                        };
                        s.grids.push((name, param, values, t));
                    }
                }
                other => {
                    return Err(format!(
                        "{origin}: unknown key '{other}'; accepted: source, poses, sut, timeout_s, levels, seeds, \
                         tolerance, threshold, effects, campaign, pairs, [[effect]], mode, sink, sut_report, \
                         frame_timeout_s, startup_s, fps"
                    ));
                }
            }
        }
        Ok(s)
    }

    /// Command-line values win over the file's.
    pub fn overlay(mut self, o: Settings) -> Settings {
        macro_rules! take {
            ($($f:ident),*) => { $( if o.$f.is_some() { self.$f = o.$f; } )* };
        }
        take!(source, poses, sut, timeout_s, levels, seeds, tolerance, threshold, effects, campaign);
        take!(live, sink, sut_report, frame_timeout_s, startup_s, fps);
        if !o.grids.is_empty() {
            self.grids = o.grids;
        }
        if !o.pairs.is_empty() {
            self.pairs = o.pairs;
        }
        self
    }

    /// Resolve into a plan: defaults, grids, validation (errors name the key and the range).
    pub fn resolve(&self) -> Result<Plan, String> {
        let levels = self.levels.unwrap_or(5);
        if !(1..=100).contains(&levels) {
            return Err(format!("levels = {levels} is out of range; accepted 1..=100"));
        }
        let mut source = self.source.clone().unwrap_or_else(|| DEFAULT_SOURCE.to_string());
        if let Some(p) = &self.poses {
            if !source.starts_with("files:") {
                return Err(format!("poses = {p} needs a files: source (got {source})"));
            }
            source.push(if source.contains('?') { '&' } else { '?' });
            source.push_str(&format!("poses={p}"));
        }
        let sut = self.sut.clone().ok_or("no SUT: give --sut 'CMD {in_dir} {out_file}' or `sut` in the config")?;
        let live = self.resolve_live()?;
        if live.is_none() && !sut.contains("{in_dir}") {
            return Err(format!("sut '{sut}' has no {{in_dir}} placeholder (the folder of images to estimate)"));
        }
        if live.is_some() && sut.contains("{out_file}") {
            return Err(format!(
                "sut '{sut}': {{out_file}} is for batch mode; a live SUT reports each pose with its seq \
                 over sut_report (stdout, udp:HOST:PORT or serial:DEVICE)"
            ));
        }
        let timeout_s = self.timeout_s.unwrap_or(600.0);
        if !(timeout_s > 0.0 && timeout_s <= 86400.0) {
            return Err(format!("timeout_s = {timeout_s} is out of range; accepted (0, 86400] s"));
        }
        let tolerance = self.tolerance.unwrap_or(0.1);
        if !(tolerance > 0.0 && tolerance.is_finite()) {
            return Err(format!("tolerance = {tolerance} is out of range; accepted > 0 (score = E_t + E_q)"));
        }
        let threshold = self.threshold.unwrap_or(0.5);
        if !(threshold > 0.0 && threshold <= 1.0) {
            return Err(format!("threshold = {threshold} is out of range; accepted (0, 1] (a failure rate)"));
        }
        let seeds = self.seeds.clone().unwrap_or_else(|| vec![1]);
        if seeds.is_empty() {
            return Err("seeds is empty; give at least one seed".into());
        }
        // Effects: explicit grids, else a campaign's effects, else names, else the registry.
        let mut effects: Vec<EffectGrid> = Vec::new();
        let mut add = |name: &str, base: Params, param: Option<&str>, values: Option<Vec<f64>>| -> Result<(), String> {
            let axis = match param {
                Some(p) => {
                    let (_, spec) = base
                        .info()
                        .param(p)
                        .ok_or_else(|| format!("effect {name} has no parameter '{p}' (see `faultcam effects`)"))?;
                    Axis { param: p.into(), from: spec.min, to: spec.max, log: false }
                }
                None => default_axis(name, &base)?,
            };
            let (_, spec) = base.info().param(&axis.param).ok_or_else(|| format!("{name}: no {}", axis.param))?;
            let int = !matches!(spec.kind, ParamKind::Float);
            let values = values.unwrap_or_else(|| (1..=levels).map(|k| axis.value(k, levels, int)).collect());
            if values.is_empty() {
                return Err(format!("effect {name}: `values` is empty"));
            }
            for v in &values {
                spec.check(base.info().name, *v).map_err(|e| e.to_string())?;
            }
            effects.push(EffectGrid { name: name.into(), param: axis.param, values, base });
            Ok(())
        };
        if !self.grids.is_empty() {
            for (name, param, values, fixed) in &self.grids {
                let mut base = crate::faults::default_params(name).map_err(|_| unknown_effect(name))?;
                for (k, v) in fixed {
                    crate::config::set_from_toml(&mut base, k, v).map_err(|e| format!("effect {name}: {e}"))?;
                }
                add(name, base, param.as_deref(), values.clone())?;
            }
        } else if let Some(c) = &self.campaign {
            let cfg = crate::FaultConfig::load(Path::new(c)).map_err(|e| e.to_string())?;
            for e in cfg.effects.iter().filter(|e| e.enabled) {
                add(&e.name, e.params, None, None)?;
            }
        } else {
            let names: Vec<String> = match &self.effects {
                Some(n) => n.clone(),
                None => registry::all()
                    .iter()
                    .map(|r| r.info.name.to_string())
                    .filter(|n| !TIMING_EFFECTS.contains(&n.as_str()))
                    .collect(),
            };
            for n in &names {
                let base = crate::faults::default_params(n).map_err(|_| unknown_effect(n))?;
                add(n, base, None, None)?;
            }
        }
        for (i, e) in effects.iter().enumerate() {
            if effects[..i].iter().any(|o| o.name == e.name) {
                return Err(format!("effect {} is listed twice; sweep it once (pairs combine effects)", e.name));
            }
        }
        let mut pairs = Vec::new();
        for (a, b) in &self.pairs {
            let find = |n: &str| {
                effects.iter().position(|e| e.name == n).ok_or_else(|| {
                    format!("pair {a}+{b}: {n} is not among the swept effects; add it to `effects` or [[effect]]")
                })
            };
            let (ia, ib) = (find(a)?, find(b)?);
            if ia == ib {
                return Err(format!("pair {a}+{b}: an effect cannot pair with itself"));
            }
            if effects[ia].values.len() != effects[ib].values.len() {
                return Err(format!("pair {a}+{b}: the two grids have different numbers of levels"));
            }
            pairs.push((ia, ib));
        }
        Ok(Plan { source, sut, timeout_s, seeds, tolerance, threshold, effects, pairs, live })
    }

    /// The live settings (none in batch mode; live-only settings without live mode are an
    /// error).
    fn resolve_live(&self) -> Result<Option<super::live::LivePlan>, String> {
        use super::live::*;
        if self.live != Some(true) {
            let given = [
                ("sink", self.sink.is_some()),
                ("sut_report", self.sut_report.is_some()),
                ("frame_timeout_s", self.frame_timeout_s.is_some()),
                ("startup_s", self.startup_s.is_some()),
                ("fps", self.fps.is_some()),
            ];
            if let Some((k, _)) = given.iter().find(|g| g.1) {
                return Err(format!("{k} is a live-mode setting; give --live or mode = \"live\""));
            }
            return Ok(None);
        }
        let sink = self.sink.clone().unwrap_or_else(|| DEFAULT_SINK.to_string());
        check_sink(&sink)?;
        let report = self.sut_report.clone().unwrap_or_else(|| "stdout".to_string());
        ReportSpec::parse(&report)?;
        let frame_timeout_s = self.frame_timeout_s.unwrap_or(DEFAULT_FRAME_TIMEOUT_S);
        if !(frame_timeout_s > 0.0 && frame_timeout_s <= 3600.0) {
            return Err(format!("frame_timeout_s = {frame_timeout_s} is out of range; accepted (0, 3600] s"));
        }
        let startup_s = self.startup_s.unwrap_or(DEFAULT_STARTUP_S);
        if !(0.0..=3600.0).contains(&startup_s) {
            return Err(format!("startup_s = {startup_s} is out of range; accepted [0, 3600] s"));
        }
        if let Some(fps) = self.fps
            && !(fps > 0.0 && fps <= 10_000.0)
        {
            return Err(format!("fps = {fps} is out of range; accepted (0, 10000] frames per second"));
        }
        Ok(Some(LivePlan { sink, report, frame_timeout_s, startup_s, fps: self.fps }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(effects: &[&str]) -> Settings {
        Settings {
            sut: Some("true {in_dir} {out_file}".into()),
            effects: Some(effects.iter().map(|s| s.to_string()).collect()),
            levels: Some(4),
            seeds: Some(vec![3, 4]),
            ..Default::default()
        }
    }

    #[test]
    fn default_grids_follow_the_registry_ranges_and_directions() {
        let p = settings(&["defocus", "jpeg", "shot_noise"]).resolve().unwrap();
        assert_eq!(p.effects[0].param, "sigma_px");
        assert_eq!(p.effects[0].values, vec![5.0, 10.0, 15.0, 20.0]);
        // JPEG: severity grows as quality falls; integers.
        assert_eq!(p.effects[1].values, vec![75.0, 51.0, 26.0, 1.0]);
        // Shot noise: geometric from 1e6 down to 0.01 e-/DN.
        let v = &p.effects[2].values;
        assert!((v[1] - 100.0).abs() < 1e-9 && (v[3] - 0.01).abs() < 1e-12, "{v:?}");
        // Every value is inside the registry's accepted range.
        for g in &p.effects {
            for k in 1..=g.values.len() {
                g.params(k).unwrap();
            }
        }
    }

    #[test]
    fn cells_cover_baseline_effects_and_pairs_once() {
        let mut s = settings(&["defocus", "gaussian_noise"]);
        s.pairs = vec![("defocus".into(), "gaussian_noise".into())];
        let p = s.resolve().unwrap();
        let cells = p.cells();
        assert_eq!(cells.len(), 2 * (1 + 4 + 4 + 4));
        assert!(cells.iter().enumerate().all(|(i, c)| c.index == i));
        assert_eq!(p.label(cells[2].kind), "defocus@1");
        assert_eq!(p.label(cells.last().unwrap().kind), "defocus+gaussian_noise@4");
        assert_eq!(p.chain_params(cells.last().unwrap().kind).unwrap().len(), 2);
    }

    #[test]
    fn bad_settings_name_the_key_and_range() {
        let mut s = settings(&["nope"]);
        assert!(s.resolve().unwrap_err().contains("unknown effect 'nope'"));
        s.effects = None;
        s.levels = Some(0);
        assert!(s.resolve().unwrap_err().contains("levels = 0"));
        s.levels = None;
        s.sut = Some("true".into());
        assert!(s.resolve().unwrap_err().contains("{in_dir}"));
    }
}
