//! Fault configuration files (TOML).
//!
//! ```toml
//! seed = 42                      # campaign seed (optional, default 0)
//!
//! [[effects]]
//! name = "blooming"              # an effect from `faultcam effects`
//! full_well_fraction = 0.9       # its parameters; omitted ones take their defaults
//! spread_px = 3.0
//!
//! [[effects]]
//! name = "jpeg"
//! quality = 70
//! enabled = true                 # optional; a disabled effect can be switched on by a timeline
//! ```
//!
//! Other top-level sections (`[[events]]`, `[pipeline]`, `[triggers]`, ...) belong to other
//! modules and are kept in [`FaultConfig::extra`]; unknown sections are errors.

use crate::faults::{self, FaultError, ParamKind, Params};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Top-level sections other modules own. Extend when a module adds one.
pub const KNOWN_SECTIONS: &[&str] = &["events", "triggers", "pipeline", "masks", "campaign"];

/// A configuration error with its place in the file.
#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("{file}: cannot read: {source}")]
    Io { file: String, source: std::io::Error },
    #[error("{file}:{line}: {message}")]
    Syntax { file: String, line: usize, message: String },
    /// The fault error is part of this message, not a separate cause: `{:#}` (anyhow) would
    /// otherwise print it twice.
    #[error("{file}:{line}: {error}")]
    Fault { file: String, line: usize, error: FaultError },
    #[error("{file}:{line}: {message}")]
    Invalid { file: String, line: usize, message: String },
}

/// One configured effect.
#[derive(Debug, Clone)]
pub struct EffectConfig {
    pub name: String,
    pub params: Params,
    pub enabled: bool,
    /// 1-based line of the effect's table in the file.
    pub line: usize,
}

/// A parsed fault configuration.
#[derive(Debug, Clone, Default)]
pub struct FaultConfig {
    pub seed: u64,
    pub effects: Vec<EffectConfig>,
    /// Other known top-level sections, for the modules that own them.
    pub extra: toml::Table,
    /// Where the file came from (for messages).
    pub origin: String,
    /// The text it was parsed from (modules that validate `extra` use it to find lines).
    pub text: String,
}

#[derive(serde::Deserialize)]
struct RawSpans {
    #[serde(default)]
    effects: Vec<toml::Spanned<BTreeMap<String, toml::Spanned<toml::Value>>>>,
}

/// 1-based line number of a byte offset.
pub fn line_of(text: &str, offset: usize) -> usize {
    text[..offset.min(text.len())].bytes().filter(|&b| b == b'\n').count() + 1
}

impl FaultConfig {
    /// Read and validate a file.
    pub fn load(path: &Path) -> Result<FaultConfig, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| ConfigError::Io { file: path.display().to_string(), source })?;
        FaultConfig::parse(&text, &path.display().to_string())
    }

    /// Parse and validate TOML text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<FaultConfig, ConfigError> {
        let file = origin.to_string();
        let syntax = |e: toml::de::Error| ConfigError::Syntax {
            file: file.clone(),
            line: e.span().map(|s| line_of(text, s.start)).unwrap_or(1),
            message: e.message().to_string(),
        };
        let table: toml::Table = toml::from_str(text).map_err(syntax)?;
        let spans: RawSpans = toml::from_str(text).map_err(|e| ConfigError::Syntax {
            file: file.clone(),
            line: e.span().map(|s| line_of(text, s.start)).unwrap_or(1),
            message: format!("{} (each [[effects]] entry must be a table)", e.message()),
        })?;
        let find_line = |key: &str| -> usize {
            // Line of a top-level key: first line that starts with it.
            text.lines()
                .position(|l| {
                    let t = l.trim_start().trim_start_matches('[');
                    t.starts_with(key)
                })
                .map(|i| i + 1)
                .unwrap_or(1)
        };

        let mut cfg = FaultConfig { origin: file.clone(), text: text.to_string(), ..Default::default() };
        for (key, value) in &table {
            match key.as_str() {
                "seed" => {
                    cfg.seed = match value {
                        toml::Value::Integer(i) if *i >= 0 => *i as u64,
                        other => {
                            return Err(ConfigError::Invalid {
                                file,
                                line: find_line("seed"),
                                message: format!("seed must be a non-negative integer, got {other}"),
                            });
                        }
                    }
                }
                "effects" => {}
                k if KNOWN_SECTIONS.contains(&k) => {
                    cfg.extra.insert(k.to_string(), value.clone());
                }
                k => {
                    return Err(ConfigError::Invalid {
                        file,
                        line: find_line(k),
                        message: format!(
                            "unknown top-level key '{k}'; accepted: seed, effects, {}",
                            KNOWN_SECTIONS.join(", ")
                        ),
                    });
                }
            }
        }

        for entry in spans.effects {
            let line = line_of(text, entry.span().start);
            let map = entry.into_inner();
            let name = match map.get("name").map(|v| v.get_ref()) {
                Some(toml::Value::String(s)) => s.clone(),
                _ => {
                    return Err(ConfigError::Invalid {
                        file,
                        line,
                        message: "every [[effects]] entry needs name = \"<effect>\" (see `faultcam effects`)".into(),
                    });
                }
            };
            let info =
                faults::create(&name).map_err(|error| ConfigError::Fault { file: file.clone(), line, error })?.info();
            let mut params = Params::defaults(info);
            let mut enabled = true;
            for (k, v) in &map {
                let vline = line_of(text, v.span().start);
                let err = |error| ConfigError::Fault { file: file.clone(), line: vline, error };
                match k.as_str() {
                    "name" => {}
                    "enabled" => match v.get_ref() {
                        toml::Value::Boolean(b) => enabled = *b,
                        _ => {
                            return Err(ConfigError::Invalid {
                                file,
                                line: vline,
                                message: format!("{name}.enabled must be true or false"),
                            });
                        }
                    },
                    _ => set_from_toml(&mut params, k, v.get_ref()).map_err(err)?,
                }
            }
            cfg.effects.push(EffectConfig { name, params, enabled, line });
        }
        Ok(cfg)
    }

    /// A config from effects and parameters in code.
    pub fn from_effects(seed: u64, effects: Vec<Params>) -> FaultConfig {
        FaultConfig {
            seed,
            effects: effects
                .into_iter()
                .map(|p| EffectConfig { name: p.info().name.to_string(), params: p, enabled: true, line: 0 })
                .collect(),
            origin: "<code>".into(),
            ..Default::default()
        }
    }

    /// TOML text that [`FaultConfig::parse`] reads back to the same configuration
    /// (the `extra` sections are written after the effects).
    pub fn to_toml(&self) -> String {
        let mut s = format!("seed = {}\n", self.seed);
        for e in &self.effects {
            s.push_str(&format!("\n[[effects]]\nname = \"{}\"\n", e.name));
            if !e.enabled {
                s.push_str("enabled = false\n");
            }
            for (spec, v) in e.params.iter() {
                let val = match spec.kind {
                    ParamKind::Choice(c) => format!("\"{}\"", c.get(v as usize).copied().unwrap_or("")),
                    ParamKind::Bool => format!("{}", v != 0.0),
                    ParamKind::Int => format!("{}", v as i64),
                    ParamKind::Float => format_float(v),
                };
                s.push_str(&format!("{} = {}\n", spec.name, val));
            }
        }
        if !self.extra.is_empty() {
            s.push('\n');
            s.push_str(&toml::to_string(&self.extra).unwrap_or_default());
        }
        s
    }

    /// Path of the origin, when it is a file.
    pub fn origin_path(&self) -> Option<PathBuf> {
        let p = PathBuf::from(&self.origin);
        p.exists().then_some(p)
    }
}

/// Float formatted so TOML reads it back as a float and bit-exactly.
fn format_float(v: f64) -> String {
    let s = format!("{v:?}");
    if s.contains('.') || s.contains('e') || s.contains("inf") || s.contains("NaN") { s } else { format!("{s}.0") }
}

/// Set one parameter from a TOML value (numbers, booleans, choice words).
pub fn set_from_toml(params: &mut Params, key: &str, v: &toml::Value) -> Result<(), FaultError> {
    let info = params.info();
    let spec = info.param(key).map(|(_, s)| s);
    match (v, spec.map(|s| s.kind)) {
        (toml::Value::String(w), _) => params.set_choice(key, w),
        // A choice whose words are numbers (jpeg.chroma = 420) may be written unquoted.
        (toml::Value::Integer(i), Some(ParamKind::Choice(_))) => params.set_choice(key, &i.to_string()),
        (toml::Value::Boolean(b), _) => params.set(key, if *b { 1.0 } else { 0.0 }),
        (toml::Value::Integer(i), _) => params.set(key, *i as f64),
        (toml::Value::Float(f), _) => params.set(key, *f),
        (other, _) => Err(FaultError::BadChoice {
            effect: info.name,
            param: spec.map(|s| s.name).unwrap_or("?"),
            got: other.to_string(),
            accepted: spec.map(|s| s.range_text()).unwrap_or_else(|| "a number, boolean or word".into()),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_effects_and_round_trips() {
        let text = "seed = 7\n\n[[effects]]\nname = \"gain_offset\"\ngain = 1.5\noffset_dn = -2\n";
        let c = FaultConfig::parse(text, "t.toml").unwrap();
        assert_eq!(c.seed, 7);
        assert_eq!(c.effects.len(), 1);
        assert_eq!(c.effects[0].line, 3);
        assert_eq!(c.effects[0].params.get("gain"), 1.5);
        assert_eq!(c.effects[0].params.get("offset_dn"), -2.0);
        let back = FaultConfig::parse(&c.to_toml(), "back").unwrap();
        assert_eq!(back.effects[0].params, c.effects[0].params);
        assert_eq!(back.seed, 7);
    }

    #[test]
    fn numeric_choice_words_may_be_unquoted() {
        for text in ["[[effects]]\nname = \"jpeg\"\nchroma = 444\n", "[[effects]]\nname = \"jpeg\"\nchroma = \"444\"\n"]
        {
            let c = FaultConfig::parse(text, "c.toml").unwrap();
            assert_eq!(c.effects[0].params.choice("chroma"), "444", "{text}");
        }
        let e = FaultConfig::parse("[[effects]]\nname = \"jpeg\"\nchroma = 422\n", "c.toml").unwrap_err().to_string();
        assert!(e.starts_with("c.toml:3:") && e.contains("420, 444"), "{e}");
    }

    #[test]
    fn errors_name_file_line_param_and_range() {
        let text = "seed = 1\n[[effects]]\nname = \"gain_offset\"\n\ngain = 9.0\n";
        let e = FaultConfig::parse(text, "bad.toml").unwrap_err().to_string();
        assert!(e.starts_with("bad.toml:5:"), "{e}");
        assert!(e.contains("gain_offset.gain") && e.contains("0..=4"), "{e}");
        let e = FaultConfig::parse("[[effects]]\nname = \"nope\"\n", "x").unwrap_err().to_string();
        assert!(e.contains("unknown effect 'nope'") && e.contains("gain_offset"), "{e}");
        let e = FaultConfig::parse("[[effects]]\nname = \"gain_offset\"\ngainz = 1\n", "x").unwrap_err().to_string();
        assert!(e.contains("x:3:") && e.contains("unknown parameter 'gainz'"), "{e}");
        let e = FaultConfig::parse("seed = 1\nbogus = 2\n", "x").unwrap_err().to_string();
        assert!(e.contains("x:2:") && e.contains("unknown top-level key"), "{e}");
        let e = FaultConfig::parse("seed = [\n", "x").unwrap_err().to_string();
        assert!(e.starts_with("x:"), "{e}");
    }

    #[test]
    fn cli_error_chain_prints_the_message_once() {
        // `main` prints errors with `{:#}`, which appends every `source()`: the fault error must
        // not be both in the message and its cause.
        for text in ["[[effects]]\nname = \"nope\"\n", "[[effects]]\nname = \"gain_offset\"\ngain = 9.0\n"] {
            let e = anyhow::Error::from(FaultConfig::parse(text, "x.toml").unwrap_err());
            let shown = format!("{e:#}");
            let needle = if text.contains("nope") { "unknown effect 'nope'" } else { "gain_offset.gain = 9" };
            assert_eq!(shown.matches(needle).count(), 1, "{shown}");
            assert!(shown.starts_with("x.toml:"), "{shown}");
        }
    }
}
