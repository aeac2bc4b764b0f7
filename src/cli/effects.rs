//! `faultcam effects`: every registered effect with its stage, model and parameters (name,
//! unit, accepted range, default, meaning), as text or JSON.

use anyhow::bail;
use faultcam::faults::registry::{self, Registration};
use faultcam::faults::{ParamKind, Scale};
use serde_json::{Value, json};
use std::io::Write;

/// Arguments of `faultcam effects`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Show only this effect.
    #[arg(long)]
    pub name: Option<String>,
    /// Print JSON (an array of effects) instead of text.
    #[arg(long)]
    pub json: bool,
}

fn selected(name: Option<&str>) -> anyhow::Result<Vec<&'static Registration>> {
    let all = registry::all();
    match name {
        None => Ok(all.iter().collect()),
        Some(n) => match registry::find(n) {
            Some(r) => Ok(vec![r]),
            None => bail!(
                "unknown effect '{n}'; known effects: {}",
                all.iter().map(|r| r.info.name).collect::<Vec<_>>().join(", ")
            ),
        },
    }
}

/// One effect as JSON.
pub fn effect_json(r: &Registration) -> Value {
    let i = r.info;
    let params: Vec<Value> = i
        .params
        .iter()
        .map(|p| {
            let (kind, choices) = match p.kind {
                ParamKind::Float => ("float", None),
                ParamKind::Int => ("int", None),
                ParamKind::Bool => ("bool", None),
                ParamKind::Choice(c) => ("choice", Some(c)),
            };
            let default = match p.kind {
                ParamKind::Choice(c) => json!(c.get(p.default as usize).copied().unwrap_or("")),
                ParamKind::Bool => json!(p.default != 0.0),
                ParamKind::Int => json!(p.default as i64),
                ParamKind::Float => json!(p.default),
            };
            let mut v = json!({
                "name": p.name,
                "unit": p.unit,
                "kind": kind,
                "min": p.min,
                "max": p.max,
                "default": default,
                "range": p.range_text(),
                "scale": if p.scale == Scale::Log { "log" } else { "linear" },
                "canonical": p.canonical,
                "doc": p.doc,
            });
            if let Some(c) = choices {
                v["choices"] = json!(c);
            }
            v
        })
        .collect();
    json!({
        "name": i.name,
        "stage": i.stage.name(),
        "order": i.order,
        "summary": i.summary,
        "model": i.model,
        "formats": i.formats.iter().map(|f| f.name()).collect::<Vec<_>>(),
        "params": params,
    })
}

fn default_text(p: &faultcam::ParamSpec) -> String {
    match p.kind {
        ParamKind::Choice(c) => c.get(p.default as usize).copied().unwrap_or("").to_string(),
        ParamKind::Bool => (p.default != 0.0).to_string(),
        _ => format!("{}", p.default),
    }
}

/// Wrap `text` at `width` columns with `indent`.
fn wrap(text: &str, indent: &str, width: usize) -> String {
    let mut out = String::new();
    let mut line = String::new();
    for word in text.split_whitespace() {
        if !line.is_empty() && indent.len() + line.len() + 1 + word.len() > width {
            out.push_str(indent);
            out.push_str(&line);
            out.push('\n');
            line.clear();
        }
        if !line.is_empty() {
            line.push(' ');
        }
        line.push_str(word);
    }
    if !line.is_empty() {
        out.push_str(indent);
        out.push_str(&line);
        out.push('\n');
    }
    out
}

/// One effect as text.
pub fn effect_text(r: &Registration) -> String {
    let i = r.info;
    let mut s = format!("{} [{} stage, order {}]\n", i.name, i.stage.name(), i.order);
    s.push_str(&wrap(i.summary, "  ", 100));
    s.push_str("  model:\n");
    s.push_str(&wrap(i.model, "    ", 100));
    s.push_str(&format!("  formats: {}\n", i.formats.iter().map(|f| f.name()).collect::<Vec<_>>().join(", ")));
    if i.params.is_empty() {
        s.push_str("  parameters: none\n");
    } else {
        s.push_str("  parameters (name, unit, accepted range, default, meaning):\n");
        for p in i.params {
            let tag = if p.canonical { "" } else { " (extra)" };
            s.push_str(&format!(
                "    {}{tag}  [{}]  {}  default {}\n",
                p.name,
                p.unit,
                p.range_text(),
                default_text(p)
            ));
            s.push_str(&wrap(p.doc, "        ", 100));
        }
    }
    s
}

pub fn run(args: Args) -> anyhow::Result<u8> {
    let regs = selected(args.name.as_deref())?;
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    if args.json {
        let v: Vec<Value> = regs.iter().map(|r| effect_json(r)).collect();
        // Serialise first so a closed pipe surfaces as an io::Error (exit 0, see main.rs).
        let text = serde_json::to_string_pretty(&v)?;
        writeln!(out, "{text}")?;
    } else {
        for (k, r) in regs.iter().enumerate() {
            if k > 0 {
                writeln!(out)?;
            }
            write!(out, "{}", effect_text(r))?;
        }
    }
    out.flush()?;
    Ok(0)
}
