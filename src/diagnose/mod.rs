//! Diagnosis: find the physics a simulation left out, fit it with the effect library's forward
//! models, and show the fit improve (EFFECTS.md, "Diagnosis contract").
//!
//! Pipeline (`diagnose_dirs`):
//!
//! 1. **Load** sim/real pairs by file name ([`img`]); everything is analysed in 8-bit DN floats.
//! 2. **Locate** ([`locate`]): masks from the sim image (saturation, flat and linear regions,
//!    edges), a first noise model, then one signature test per effect, each a statistic with a
//!    null distribution: tone/spatial photometric regression ([`photometric`]: gain_offset,
//!    gamma, vignetting, stray_light, dark level), edge-derivative regression ([`edges`]:
//!    defocus, motion_blur, channel_shift; [`psf`]: the blur kernel's taps measured directly,
//!    its direction and its best-fitting Gaussian), saturation neighbourhoods ([`saturation`]: blooming
//!    plateau and halo, smear column/row profiles), lens_flare ghost plateaus on the source–centre
//!    line ([`flare`]),
//!    fixed pattern and noise structure ([`fixed`]: prnu by cross-frame covariance, hot pixels
//!    by recurrence, row noise by split-half covariance), JPEG by the DCT quantisation lattice
//!    ([`jpeg`]) and camera noise (variance against signal, [`noise`]).
//! 3. **Select and fit** ([`fit`]): significant candidates are fitted jointly on the library's
//!    forward models (`faults::create`, `Effect::apply` on copies of the sim frames with a fixed
//!    seed) with a Huber loss on noise-normalised residuals; stochastic effects by moment
//!    matching through the same forward models. Each finding must survive a drop-one test.
//! 4. **Report** ([`report`]): `report.json`, `fitted.toml`, `report.md` with residual maps and
//!    evidence plots ([`plot`]).
//!
//! `--unpaired` ([`unpaired`]) compares statistics instead of pixels.
//!
//! # Module dependencies
//!
//! The modules form layers; a module imports (`super::x`, `crate::diagnose::x`) only modules of
//! the layers above its own, never a module of its own layer (the test
//! `tests::module_layers_hold` reads the sources and enforces this):
//!
//! 1. **Shared** — [`types`] (errors, [`Options`], [`Signature`], [`Profile`], [`progress`];
//!    re-exported here) and [`stats`] import nothing of `diagnose`; [`img`] imports `types`;
//!    [`common`] ([`Masks`](common::Masks), [`NoiseModel`](common::NoiseModel),
//!    [`params_from_signature`](common::params_from_signature)) imports `types`, `img`, `stats`;
//!    [`plot`] imports `types`, `img`.
//! 2. **Signatures** — [`edges`], [`fixed`], [`flare`], [`glare`], [`jpeg`], [`moments`], [`noise`],
//!    [`photometric`], [`psf`], [`saturation`], [`tone`], [`levelmap`] and every new file not named below: they import
//!    only `types`, `img`, `stats` and `common`, never each other nor an orchestrator. A new
//!    signature is one new file; only the orchestrators import it.
//! 3. **Orchestrators**, in this order, each importing the shared and signature modules and the
//!    orchestrators before it: [`locate`] (masks, first noise model, the signature tests),
//!    [`select`] (forward-model selection), [`fit`], [`report`], [`unpaired`], and this module
//!    (`diagnose_dirs`).

pub mod common;
pub mod dither;
pub mod edges;
pub mod fit;
pub mod fixed;
/// Lens flare: matched search for ghost plateaus on the line from the brightest source through the centre.
pub mod flare;
/// Veiling glare: signature (sky level against the lit scene convolved with the PSF) and fit.
pub mod glare;
pub mod img;
pub mod jpeg;
/// Level or position: a tone curve against stray light, veiling glare and vignetting on smoothly lit scenes.
pub mod levelmap;
pub mod locate;
pub mod moments;
pub mod noise;
pub mod photometric;
pub mod plot;
/// Blur kernel measured directly (taps by least squares): direction and best-fitting Gaussian.
pub mod psf;
pub mod report;
pub mod saturation;
pub mod select;
pub mod stats;
pub mod tone;
pub mod types;
pub mod unpaired;

pub use types::{DiagnoseError, Options, Profile, Signature, progress};

use std::path::Path;

/// Run a diagnosis on two folders and write the report into `out`.
pub fn diagnose_dirs(sim: &Path, real: &Path, out: &Path, opts: &Options) -> Result<report::Report, DiagnoseError> {
    std::fs::create_dir_all(out).map_err(|source| DiagnoseError::Io { path: out.to_path_buf(), source })?;
    if opts.unpaired {
        let sims = img::load_folder(sim)?;
        let reals = img::load_folder(real)?;
        let rep = unpaired::run(&sims, &reals, opts)?;
        report::write_unpaired(&rep, out, opts)?;
        return Ok(rep.report);
    }
    progress("loading pairs");
    let (pairs, notes) = img::load_pairs(sim, real)?;
    progress(&format!("{} pairs loaded; locating", pairs.len()));
    let mut located = locate::locate(&pairs, opts);
    progress("located; forward-model selection");
    let fitted = fit::fit(&pairs, &mut located, opts)?;
    progress("fitted; writing the report");
    let rep = report::build(&pairs, &located, &fitted, notes, opts);
    progress("report built");
    report::write(&rep, &pairs, &located, &fitted, out, opts)?;
    progress("report written");
    Ok(rep)
}

#[cfg(test)]
mod tests {
    use std::collections::{BTreeMap, BTreeSet};

    /// Orchestrators in dependency order: each may import the ones before it.
    const ORCHESTRATORS: [&str; 6] = ["locate", "select", "fit", "report", "unpaired", "mod"];
    /// Shared modules and the modules each may import.
    const SHARED: [(&str, &[&str]); 5] = [
        ("types", &[]),
        ("stats", &[]),
        ("img", &["types"]),
        ("common", &["types", "img", "stats"]),
        ("plot", &["types", "img"]),
    ];
    /// What a signature module (any other file) may import.
    const FOR_SIGNATURES: [&str; 4] = ["types", "img", "stats", "common"];

    /// Modules of `diagnose` a source refers to outside comments: `super::x`, `super::super::x`,
    /// `crate::diagnose::x` and the members of `super::{..}` groups. Names re-exported by mod.rs
    /// count as their module (`types`), items defined in mod.rs as `mod`; other names (items of
    /// the file itself, seen from its test module) are not module references.
    fn referenced(src: &str, names: &BTreeMap<String, String>) -> BTreeSet<String> {
        let code: Vec<&str> = src.lines().map(|l| l.split("//").next().unwrap_or("")).collect();
        let code = code.join("\n");
        let ident = |s: &str| -> String { s.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect() };
        let mut out = BTreeSet::new();
        for prefix in ["super::", "crate::diagnose::"] {
            let mut rest = code.as_str();
            while let Some(i) = rest.find(prefix) {
                rest = &rest[i + prefix.len()..];
                let mut tail = rest;
                while let Some(t) = tail.strip_prefix("super::") {
                    tail = t;
                }
                let mut found = Vec::new();
                if let Some(group) = tail.strip_prefix('{') {
                    let (mut depth, mut start) = (0usize, 0usize);
                    for (k, ch) in group.char_indices() {
                        match ch {
                            '{' => depth += 1,
                            '}' if depth == 0 => {
                                found.push(ident(group[start..k].trim()));
                                break;
                            }
                            '}' => depth -= 1,
                            ',' if depth == 0 => {
                                found.push(ident(group[start..k].trim()));
                                start = k + 1;
                            }
                            _ => {}
                        }
                    }
                } else {
                    found.push(ident(tail));
                }
                out.extend(found.into_iter().filter_map(|n| names.get(&n).cloned()));
            }
        }
        out
    }

    /// Name → module for the names a path after `super::` can mean: the module files, the
    /// re-exports of mod.rs (`pub use types::{..}`) and the items mod.rs defines.
    fn names(stems: &BTreeSet<String>, mod_rs: &str) -> BTreeMap<String, String> {
        let mut m: BTreeMap<String, String> = stems.iter().map(|s| (s.clone(), s.clone())).collect();
        for line in mod_rs.lines() {
            if let Some(r) = line.strip_prefix("pub use ")
                && let Some((module, items)) = r.split_once("::")
            {
                for item in items.trim_matches(|c| "{};".contains(c)).split(',') {
                    m.insert(item.trim().to_string(), module.to_string());
                }
            }
            for kw in ["pub fn ", "pub struct ", "pub enum ", "pub const ", "pub static ", "pub type "] {
                if let Some(r) = line.strip_prefix(kw) {
                    let n: String = r.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
                    m.insert(n, "mod".to_string());
                }
            }
        }
        m
    }

    /// Violations of the layer rule (module doc) in `sources` (module name → source).
    fn violations(sources: &BTreeMap<String, String>) -> Vec<String> {
        let stems: BTreeSet<String> = sources.keys().cloned().collect();
        let names = names(&stems, sources.get("mod").map(String::as_str).unwrap_or(""));
        let mut bad = Vec::new();
        for (module, src) in sources {
            let allowed: Vec<&str> = if let Some(k) = ORCHESTRATORS.iter().position(|o| o == module) {
                let later = &ORCHESTRATORS[k + 1..];
                stems.iter().map(String::as_str).filter(|s| !later.contains(s)).collect()
            } else if let Some((_, a)) = SHARED.iter().find(|(s, _)| s == module) {
                a.to_vec()
            } else {
                FOR_SIGNATURES.to_vec()
            };
            for r in referenced(src, &names) {
                if r != *module && !allowed.contains(&r.as_str()) {
                    bad.push(format!("src/diagnose/{module}.rs imports `{r}` (allowed: {})", allowed.join(", ")));
                }
            }
        }
        bad
    }

    fn sources() -> BTreeMap<String, String> {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/diagnose");
        let mut out = BTreeMap::new();
        for e in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "rs") {
                let stem = p.file_stem().unwrap().to_string_lossy().into_owned();
                let src = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
                out.insert(stem, src);
            }
        }
        out
    }

    /// The module layers of the module doc hold in the sources: no signature module imports an
    /// orchestrator or another signature module, shared modules import only the shared modules
    /// listed, and orchestrators only the ones before them.
    #[test]
    fn module_layers_hold() {
        let src = sources();
        for m in ORCHESTRATORS.iter().chain(SHARED.iter().map(|(s, _)| s)).chain(FOR_SIGNATURES.iter()) {
            assert!(src.contains_key(*m), "src/diagnose/{m}.rs named in the layer rule does not exist");
        }
        let bad = violations(&src);
        assert!(bad.is_empty(), "module layer rule broken (see src/diagnose/mod.rs):\n{}", bad.join("\n"));
    }

    /// The check sees the forms of import the sources use and ignores comments.
    #[test]
    fn layer_check_catches_imports() {
        let mut src = sources();
        let case = |src: &mut BTreeMap<String, String>, module: &str, text: &str| -> Vec<String> {
            let keep = src.insert(module.to_string(), text.to_string());
            let v = violations(src);
            if let Some(k) = keep {
                src.insert(module.to_string(), k);
            }
            v
        };
        assert_eq!(case(&mut src, "edges", "use super::locate::Masks;").len(), 1);
        assert_eq!(case(&mut src, "edges", "use super::{Signature, diagnose_dirs, fixed};").len(), 2);
        assert_eq!(case(&mut src, "edges", "fn f() { super::fit::params_from_signature(s) }").len(), 1);
        assert_eq!(case(&mut src, "edges", "mod t { use crate::diagnose::select::X; }").len(), 1);
        assert_eq!(case(&mut src, "edges", "mod t { use super::super::noise::X; }").len(), 1);
        assert_eq!(case(&mut src, "new_signature", "use super::common::Masks;\nuse super::types::Signature;").len(), 0);
        assert_eq!(case(&mut src, "new_signature", "/// see [`super::locate`]\nuse super::img::Plane;").len(), 0);
        assert_eq!(case(&mut src, "img", "use super::common::Masks;").len(), 1);
        assert_eq!(case(&mut src, "locate", "use super::fit::X;").len(), 1);
    }
}
