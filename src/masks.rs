//! Per-pixel fault masks: which effect changed each pixel of a frame, and by how much.
//!
//! [`Chain::apply_recording`](crate::faults::chain::Chain::apply_recording) runs the chain with a
//! [`MaskRecorder`]: before each applied effect the recorder keeps a copy of the frame, after it
//! compares the output with that copy. Bit k of a pixel's label is set when the k-th applied effect
//! (`FrameReport::applied[k]`, the k-th entry of the frame record's `effects`, in application =
//! physical order) changed any channel of the pixel; a pixel no effect changed has label 0. With
//! deltas enabled the recorder also keeps, per effect, the signed change `out − in` of every sample
//! in DN of the frame's format (exact integers).
//!
//! Files written by [`MaskRecorder::write`] (`STEM` = the output image's file stem):
//!
//! - `STEM.labels.png` — 16-bit grey PNG, W×H: bit k (value 2^k) = effect k changed the pixel,
//!   k = 0..=15. A chain of more than 16 applied effects continues in `STEM.labels-1.png`
//!   (effects 16..=31, bit k−16), up to [`MAX_MASK_EFFECTS`] effects.
//! - with deltas, `STEM.delta-KK-NAME.tiff` for every effect KK (two digits) that changed at least
//!   one pixel — 32-bit float TIFF, grey (mono) or RGB, the exact signed change in DN (integers,
//!   exactly representable in f32). Effects that changed nothing get no file.
//!
//! The frame record of the ground-truth log names them in its `masks` field ([`MaskRecord`]):
//! `{"labels": "…labels.png", "bits": ["lens_flare", …], "changed_px": [1234, …],
//!   "deltas": [{"bit": 0, "effect": "lens_flare", "path": "…delta-00-lens_flare.tiff"}]}`.
//!
//! Streams (`faultcam run`): create one [`MaskRecorder`] per stream (options from the config's
//! optional `[masks]` section via [`MaskConfig::from_config`], or from the command line), then per
//! frame call [`apply_with_masks`] instead of `Chain::apply`: it runs the chain, writes the masks
//! of a kept frame into the folder as `STEM.*` ([`mask_stem`] gives the files sink's naming) and
//! returns the [`MaskRecord`] to put in the frame record's `masks` field. Run the fault stage's
//! loop inside a rayon pool (`pool.install`) so that the effects' parallel work does not go
//! through rayon's global injector, which allocates.
//!
//! Real time: the recorder's buffers (a frame copy, one u32 label per pixel, and with deltas one
//! i16 (8-bit formats) or i32 (Mono16) per sample and effect) are allocated when the frame size
//! first appears and reused; recording allocates nothing per frame. Only [`MaskRecorder::write`]
//! (PNG/TIFF encoding, file names, the record) allocates.
//!
//! Temporal effects: `frame_freeze` and `reorder` replace a frame's content; their bit marks the
//! pixels where the emitted content differs from the frame that entered them (for `reorder`, the
//! bits of the earlier effects describe the frame that entered and is now held). A dropped frame
//! has no output and so no masks.

use crate::faults::Outcome;
use crate::faults::chain::ChainObserver;
use crate::faults::kit::ROWS_PER_TASK;
use crate::frame::{Frame, FrameData, PixelFormat};
use crate::sink::files::{ImageFormat, WriteOptions, write_image};
use rayon::prelude::*;
use serde::Serialize;
use std::path::Path;
use thiserror::Error;

/// Most effects one frame's masks can record (bits of the internal label).
pub const MAX_MASK_EFFECTS: usize = 32;
/// Label bits per 16-bit label PNG.
pub const LABEL_BITS_PER_FILE: usize = 16;

/// What to record.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MaskOptions {
    /// Also keep (and write) the per-effect signed change of every sample.
    pub deltas: bool,
}

/// Errors writing masks.
#[derive(Debug, Error)]
pub enum MaskError {
    #[error("masks: no frame has been recorded (call Chain::apply_recording first)")]
    NothingRecorded,
    #[error("masks: cannot write {path}: {reason}")]
    Write { path: String, reason: String },
    /// The chain failed on the frame (nothing was written).
    #[error(transparent)]
    Chain(#[from] crate::faults::FaultError),
    #[error("[masks].{key}: {reason}")]
    Config { key: String, reason: String },
}

/// The optional `[masks]` section of a fault config (for `faultcam run`):
///
/// ```toml
/// [masks]
/// enabled = true      # default true when the section exists
/// deltas = false      # also write per-effect delta images
/// dir = "masks"       # folder (relative paths: relative to the run's output)
/// ```
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MaskConfig {
    pub options: MaskOptions,
    pub dir: Option<std::path::PathBuf>,
}

impl MaskConfig {
    /// Read `[masks]` from a config's extra sections; `None` when absent or `enabled = false`.
    pub fn from_config(cfg: &crate::config::FaultConfig) -> Result<Option<MaskConfig>, MaskError> {
        let Some(v) = cfg.extra.get("masks") else { return Ok(None) };
        let bad = |key: &str, reason: &str| MaskError::Config { key: key.into(), reason: reason.into() };
        let t = v.as_table().ok_or_else(|| bad("", "must be a table: [masks]"))?;
        let mut out = MaskConfig { options: MaskOptions::default(), dir: None };
        let mut enabled = true;
        for (k, v) in t {
            match (k.as_str(), v) {
                ("enabled", toml::Value::Boolean(b)) => enabled = *b,
                ("deltas", toml::Value::Boolean(b)) => out.options.deltas = *b,
                ("dir", toml::Value::String(d)) => out.dir = Some(d.into()),
                ("enabled" | "deltas", _) => return Err(bad(k, "must be true or false")),
                ("dir", _) => return Err(bad(k, "must be a folder name (string)")),
                _ => return Err(bad(k, "unknown key; accepted: enabled, deltas, dir")),
            }
        }
        Ok(enabled.then_some(out))
    }
}

/// One call per frame for a stream: apply the chain recording masks and, when the frame is
/// kept, write them to `dir` as `stem.*` (see [`MaskRecorder::write`]). Returns the outcome and
/// the record for the log (`None` for a dropped frame). Recording allocates nothing per frame;
/// writing encodes PNG/TIFF files.
pub fn apply_with_masks(
    chain: &mut crate::faults::chain::Chain,
    frame: &mut Frame,
    report: &mut crate::faults::chain::FrameReport,
    rec: &mut MaskRecorder,
    dir: &Path,
    stem: &str,
) -> Result<(Outcome, Option<MaskRecord>), MaskError> {
    let out = chain.apply_recording(frame, report, rec)?;
    if out == Outcome::Drop {
        return Ok((out, None));
    }
    Ok((out, Some(rec.write(dir, stem)?)))
}

/// One per-effect delta image.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DeltaFile {
    /// Label bit = position in the frame record's `effects`.
    pub bit: usize,
    pub effect: &'static str,
    pub path: String,
}

/// The `masks` field of a frame record.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct MaskRecord {
    /// 16-bit grey PNG: bit k set where the k-th applied effect changed the pixel (k < 16).
    pub labels: String,
    /// Further label PNGs when more than 16 effects were applied: file i holds effects
    /// 16·(i+1) .. 16·(i+2)−1 as bits 0..15.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub labels_more: Vec<String>,
    /// Bit k → effect name (the frame record's `effects[k].name`).
    pub bits: Vec<&'static str>,
    /// Pixels changed by each effect (same order as `bits`).
    pub changed_px: Vec<u64>,
    /// Per-effect signed delta images (with `--mask-deltas`), for the effects that changed pixels.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub deltas: Vec<DeltaFile>,
}

/// Signed per-sample change storage: i16 holds any 8-bit change, i32 any 16-bit change.
#[derive(Debug, Default)]
enum Deltas {
    #[default]
    Off,
    I16(Vec<i16>),
    I32(Vec<i32>),
}

/// Records per-pixel fault masks of one frame at a time (see the module documentation).
#[derive(Debug)]
pub struct MaskRecorder {
    opts: MaskOptions,
    width: usize,
    height: usize,
    channels: usize,
    format: PixelFormat,
    // allocation: once per frame size: the frame as it entered the current effect
    before: Frame,
    // allocation: once per frame size: one label per pixel
    labels: Vec<u32>,
    // allocation: once per frame size (deltas only): MAX_MASK_EFFECTS planes grown on demand
    deltas: Deltas,
    // allocation: once (capacity MAX_MASK_EFFECTS)
    names: Vec<&'static str>,
    changed: Vec<u64>,
    recorded: bool,
    // allocation: once per frame size, for writing: a Mono16 label image and encoder scratch
    label_frame: Frame,
    png_scratch: Vec<u8>,
    f32_scratch: Vec<f32>,
}

fn empty_frame(format: PixelFormat) -> Frame {
    let data = if format == PixelFormat::Mono16 { FrameData::U16(Vec::new()) } else { FrameData::U8(Vec::new()) };
    Frame { seq: 0, pts_ns: 0, width: 0, height: 0, stride: 0, format, data }
}

impl MaskRecorder {
    pub fn new(opts: MaskOptions) -> MaskRecorder {
        MaskRecorder {
            opts,
            width: 0,
            height: 0,
            channels: 1,
            format: PixelFormat::Mono8,
            before: empty_frame(PixelFormat::Mono8),
            labels: Vec::new(),
            deltas: Deltas::Off,
            names: Vec::with_capacity(MAX_MASK_EFFECTS),
            changed: Vec::with_capacity(MAX_MASK_EFFECTS),
            recorded: false,
            label_frame: empty_frame(PixelFormat::Mono16),
            png_scratch: Vec::new(),
            f32_scratch: Vec::new(),
        }
    }

    pub fn options(&self) -> MaskOptions {
        self.opts
    }

    /// Start a frame: clear the labels (called by `Chain::apply_recording`).
    pub fn begin(&mut self, frame: &Frame) {
        let (w, h, ch) = (frame.width as usize, frame.height as usize, frame.channels());
        if (w, h, ch, frame.format) != (self.width, self.height, self.channels, self.format) {
            self.width = w;
            self.height = h;
            self.channels = ch;
            self.format = frame.format;
            self.labels.clear();
            self.labels.resize(w * h, 0);
            self.deltas = match (self.opts.deltas, frame.format) {
                (false, _) => Deltas::Off,
                (true, PixelFormat::Mono16) => Deltas::I32(Vec::new()),
                (true, _) => Deltas::I16(Vec::new()),
            };
        } else {
            self.labels.par_iter_mut().for_each(|l| *l = 0);
        }
        self.names.clear();
        self.changed.clear();
        self.recorded = true;
    }

    /// Width and height of the recorded frame.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }
    /// Effect names by bit (application order).
    pub fn bits(&self) -> &[&'static str] {
        &self.names
    }
    /// Per-pixel labels, row-major, `width × height`.
    pub fn labels(&self) -> &[u32] {
        &self.labels
    }
    /// Label of pixel (x, y).
    pub fn label(&self, x: usize, y: usize) -> u32 {
        self.labels[y * self.width + x]
    }
    /// Pixels changed by effect `k`.
    pub fn changed_pixels(&self, k: usize) -> u64 {
        self.changed.get(k).copied().unwrap_or(0)
    }
    /// Signed change of sample (x, y, c) by effect `k` in DN (None without deltas or if `k` was
    /// not applied).
    pub fn delta(&self, k: usize, x: usize, y: usize, c: usize) -> Option<i32> {
        if k >= self.names.len() {
            return None;
        }
        let n = self.width * self.height * self.channels;
        let i = k * n + (y * self.width + x) * self.channels + c;
        match &self.deltas {
            Deltas::Off => None,
            Deltas::I16(d) => d.get(i).map(|&v| v as i32),
            Deltas::I32(d) => d.get(i).copied(),
        }
    }

    /// Compare the frame after effect `k` with the copy taken before it.
    fn compare(&mut self, k: usize, frame: &Frame) {
        let (w, h, ch) = (self.width, self.height, self.channels);
        let same_shape = frame.width as usize == w
            && frame.height as usize == h
            && frame.format == self.format
            && frame.stride == self.before.stride;
        let bit = 1u32 << k;
        if !same_shape {
            // Only a temporal effect can hand out a frame of another size: every pixel changed,
            // and there is no sample-wise delta (left 0).
            self.labels.par_iter_mut().for_each(|l| *l |= bit);
            self.changed.push((w * h) as u64);
            return;
        }
        let n = w * h * ch;
        let stride = frame.stride;
        let band_px = w * ROWS_PER_TASK;
        let changed: u64 = match (&frame.data, &self.before.data, &mut self.deltas) {
            (FrameData::U8(a), FrameData::U8(b), Deltas::I16(d)) => {
                let plane = &mut d[k * n..(k + 1) * n];
                self.labels
                    .par_chunks_mut(band_px)
                    .zip(plane.par_chunks_mut(band_px * ch))
                    .enumerate()
                    .map(|(band, (lab, dl))| diff_band(a, b, stride, w, ch, band, lab, Some(dl), bit))
                    .sum()
            }
            (FrameData::U16(a), FrameData::U16(b), Deltas::I32(d)) => {
                let plane = &mut d[k * n..(k + 1) * n];
                self.labels
                    .par_chunks_mut(band_px)
                    .zip(plane.par_chunks_mut(band_px * ch))
                    .enumerate()
                    .map(|(band, (lab, dl))| diff_band(a, b, stride, w, ch, band, lab, Some(dl), bit))
                    .sum()
            }
            (FrameData::U8(a), FrameData::U8(b), _) => self
                .labels
                .par_chunks_mut(band_px)
                .enumerate()
                .map(|(band, lab)| diff_band::<u8, i16>(a, b, stride, w, ch, band, lab, None, bit))
                .sum(),
            (FrameData::U16(a), FrameData::U16(b), _) => self
                .labels
                .par_chunks_mut(band_px)
                .enumerate()
                .map(|(band, lab)| diff_band::<u16, i32>(a, b, stride, w, ch, band, lab, None, bit))
                .sum(),
            _ => 0,
        };
        self.changed.push(changed);
    }

    /// Write the recorded masks of the last frame into `dir` (created if missing) as
    /// `STEM.labels.png` (+ `STEM.labels-1.png` beyond 16 effects) and, with deltas,
    /// `STEM.delta-KK-NAME.tiff`; returns the record for the ground-truth log.
    pub fn write(&mut self, dir: &Path, stem: &str) -> Result<MaskRecord, MaskError> {
        if !self.recorded {
            return Err(MaskError::NothingRecorded);
        }
        std::fs::create_dir_all(dir)
            .map_err(|e| MaskError::Write { path: dir.display().to_string(), reason: e.to_string() })?;
        let (w, h) = (self.width, self.height);
        let files = self.names.len().div_ceil(LABEL_BITS_PER_FILE).max(1);
        let mut rec = MaskRecord { bits: self.names.clone(), changed_px: self.changed.clone(), ..Default::default() };
        for i in 0..files {
            let name = if i == 0 { format!("{stem}.labels.png") } else { format!("{stem}.labels-{i}.png") };
            let path = dir.join(&name);
            self.label_frame.width = w as u32;
            self.label_frame.height = h as u32;
            self.label_frame.stride = w;
            self.label_frame.format = PixelFormat::Mono16;
            let shift = LABEL_BITS_PER_FILE * i;
            if let FrameData::U16(d) = &mut self.label_frame.data {
                d.clear();
                d.extend(self.labels.iter().map(|&l| (l >> shift) as u16));
            }
            let opts = WriteOptions { format: ImageFormat::Png, ..WriteOptions::default() };
            write_image(&path, &self.label_frame, &opts, &mut self.png_scratch)
                .map_err(|reason| MaskError::Write { path: path.display().to_string(), reason })?;
            let text = path.display().to_string();
            if i == 0 {
                rec.labels = text;
            } else {
                rec.labels_more.push(text);
            }
        }
        if !matches!(self.deltas, Deltas::Off) {
            for k in 0..self.names.len() {
                if self.changed[k] == 0 {
                    continue;
                }
                let name = format!("{stem}.delta-{k:02}-{}.tiff", self.names[k]);
                let path = dir.join(&name);
                self.fill_f32(k);
                write_tiff_f32(&path, w as u32, h as u32, self.channels, &self.f32_scratch)
                    .map_err(|reason| MaskError::Write { path: path.display().to_string(), reason })?;
                rec.deltas.push(DeltaFile { bit: k, effect: self.names[k], path: path.display().to_string() });
            }
        }
        Ok(rec)
    }

    fn fill_f32(&mut self, k: usize) {
        let n = self.width * self.height * self.channels;
        self.f32_scratch.clear();
        match &self.deltas {
            Deltas::Off => {}
            Deltas::I16(d) => self.f32_scratch.extend(d[k * n..(k + 1) * n].iter().map(|&v| v as f32)),
            Deltas::I32(d) => self.f32_scratch.extend(d[k * n..(k + 1) * n].iter().map(|&v| v as f32)),
        }
    }
}

impl ChainObserver for MaskRecorder {
    fn before_effect(&mut self, k: usize, _name: &'static str, frame: &Frame) {
        self.before.copy_from(frame);
        if k >= MAX_MASK_EFFECTS {
            return;
        }
        // Grow the delta planes to hold effect k (once per stream and chain length).
        let n = self.width * self.height * self.channels;
        match &mut self.deltas {
            Deltas::Off => {}
            Deltas::I16(d) if d.len() < (k + 1) * n => d.resize((k + 1) * n, 0),
            Deltas::I32(d) if d.len() < (k + 1) * n => d.resize((k + 1) * n, 0),
            _ => {}
        }
    }

    fn after_effect(&mut self, k: usize, name: &'static str, frame: &Frame, _outcome: Outcome) {
        if k >= MAX_MASK_EFFECTS || self.names.len() != k {
            return;
        }
        self.names.push(name);
        self.compare(k, frame);
    }
}

/// A signed delta sample type.
trait Delta: Copy + Send + Default {
    fn from_diff(d: i32) -> Self;
}
impl Delta for i16 {
    #[inline(always)]
    fn from_diff(d: i32) -> Self {
        d as i16
    }
}
impl Delta for i32 {
    #[inline(always)]
    fn from_diff(d: i32) -> Self {
        d
    }
}

/// Compare one band of rows; set `bit` in `lab` where a pixel differs, write the signed change
/// into `dl` when given. Returns the number of changed pixels.
#[allow(clippy::too_many_arguments)]
fn diff_band<T: crate::frame::Sample, D: Delta>(
    after: &[T],
    before: &[T],
    stride: usize,
    w: usize,
    ch: usize,
    band: usize,
    lab: &mut [u32],
    mut dl: Option<&mut [D]>,
    bit: u32,
) -> u64 {
    let mut changed = 0u64;
    let rl = w * ch;
    for (i, lrow) in lab.chunks_mut(w).enumerate() {
        let y = band * ROWS_PER_TASK + i;
        let a = &after[y * stride..y * stride + rl];
        let b = &before[y * stride..y * stride + rl];
        match dl.as_deref_mut() {
            Some(dl) => {
                let drow = &mut dl[i * rl..(i + 1) * rl];
                for (x, l) in lrow.iter_mut().enumerate() {
                    let mut any = false;
                    for c in 0..ch {
                        let d = a[x * ch + c].to_u32() as i32 - b[x * ch + c].to_u32() as i32;
                        drow[x * ch + c] = D::from_diff(d);
                        any |= d != 0;
                    }
                    if any {
                        *l |= bit;
                        changed += 1;
                    }
                }
            }
            None => {
                for (x, l) in lrow.iter_mut().enumerate() {
                    let any = a[x * ch..(x + 1) * ch] != b[x * ch..(x + 1) * ch];
                    if any {
                        *l |= bit;
                        changed += 1;
                    }
                }
            }
        }
    }
    changed
}

/// Write samples (`channels` = 1 or 3, row-major, packed) as a 32-bit float TIFF via a
/// temporary file and a rename.
fn write_tiff_f32(path: &Path, w: u32, h: u32, channels: usize, data: &[f32]) -> Result<(), String> {
    use tiff::encoder::{TiffEncoder, colortype};
    let tmp = path.with_extension("tiff.tmp");
    let res = (|| -> Result<(), String> {
        let file = std::fs::File::create(&tmp).map_err(|e| format!("cannot create {}: {e}", tmp.display()))?;
        let mut buf = std::io::BufWriter::new(file);
        {
            let mut enc = TiffEncoder::new(&mut buf).map_err(|e| e.to_string())?;
            if channels == 3 {
                enc.write_image::<colortype::RGB32Float>(w, h, data).map_err(|e| e.to_string())?;
            } else {
                enc.write_image::<colortype::Gray32Float>(w, h, data).map_err(|e| e.to_string())?;
            }
        }
        std::io::Write::flush(&mut buf).map_err(|e| e.to_string())
    })();
    if let Err(e) = res {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, path).map_err(|e| format!("cannot rename {} to {}: {e}", tmp.display(), path.display()))
}

/// File stem for a frame's masks: the input's stem, else `frame_{seq:06}` (the `files:` sink's
/// naming).
pub fn mask_stem(input: Option<&str>, seq: u64) -> String {
    match input {
        Some(name) => Path::new(name).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or(name.into()),
        None => format!("frame_{seq:06}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::faults::chain::{Chain, FrameReport};
    use crate::faults::{EffectCtx, create, default_params};

    fn params(name: &str, kv: &[(&str, f64)]) -> crate::faults::Params {
        let mut p = default_params(name).unwrap();
        for (k, v) in kv {
            p.set(k, *v).unwrap();
        }
        p
    }

    /// Effects that each touch only part of the frame, so labels are informative.
    fn sparse_chain(seed: u64) -> Chain {
        let mut c = Chain::new(seed);
        c.push("vertical_glitch", params("vertical_glitch", &[("count", 2.0), ("max_offset_px", 9.0)])).unwrap();
        c.push("hot_pixels", params("hot_pixels", &[("rate", 0.004)])).unwrap();
        c.push("smear", params("smear", &[("strength", 0.004), ("sat_level", 0.95)])).unwrap();
        c.push("channel_shift", params("channel_shift", &[("dx_r", 1.5), ("dy_b", -0.5)])).unwrap();
        c.push("gaussian_noise", params("gaussian_noise", &[("sigma_dn", 0.3)])).unwrap();
        c
    }

    /// Apply the chain's effects one by one with the chain's seeds and keep every intermediate
    /// frame: the reference for what each effect changed.
    fn steps(chain: &Chain, input: &Frame) -> Vec<Frame> {
        let mut out = vec![input.clone()];
        let mut f = input.clone();
        for e in chain.entries().iter().filter(|e| e.enabled) {
            let mut eff = create(e.name()).unwrap();
            let mut ctx = EffectCtx::new(chain.seed(), f.seq, e.index);
            eff.apply(&mut f, &e.params, &mut ctx).unwrap();
            out.push(f.clone());
        }
        out
    }

    #[test]
    fn labels_and_deltas_match_what_each_effect_changed() {
        for format in [PixelFormat::Mono8, PixelFormat::Rgb8, PixelFormat::Mono16] {
            let mut input = crate::faults::kit::bench_scene(160, 130, format, 3).unwrap();
            input.seq = 5;
            let mut chain = sparse_chain(11);
            let reference = steps(&chain, &input);
            let mut rec = MaskRecorder::new(MaskOptions { deltas: true });
            let mut report = FrameReport::default();
            // Two frames through the same recorder: the second must not see the first's labels.
            for seq in [4u64, 5] {
                let mut f = input.clone();
                f.seq = seq;
                assert_eq!(chain.apply_recording(&mut f, &mut report, &mut rec).unwrap(), Outcome::Keep);
                if seq == 5 {
                    assert_eq!(&f, reference.last().unwrap(), "{format}: recording does not change the output");
                }
            }
            let names: Vec<_> = report.applied.iter().map(|a| a.name).collect();
            assert_eq!(rec.bits(), &names[..]);
            let (w, h, ch) = (160usize, 130usize, format.channels());
            let mut untouched = 0;
            for k in 0..names.len() {
                let (a, b) = (&reference[k], &reference[k + 1]);
                let mut changed = 0u64;
                for y in 0..h {
                    for x in 0..w {
                        let diff: Vec<i32> = (0..ch).map(|c| b.get(x, y, c) as i32 - a.get(x, y, c) as i32).collect();
                        let any = diff.iter().any(|&d| d != 0);
                        changed += any as u64;
                        assert_eq!(rec.label(x, y) >> k & 1 == 1, any, "{format} {} at ({x},{y})", names[k]);
                        for c in 0..ch {
                            assert_eq!(rec.delta(k, x, y, c), Some(diff[c]), "{format} {} delta", names[k]);
                        }
                    }
                }
                assert_eq!(rec.changed_pixels(k), changed);
                assert!(
                    changed > 0 || (names[k] == "channel_shift" && ch == 1),
                    "{format}: {} changed nothing",
                    names[k]
                );
                assert!(changed < (w * h) as u64 || names[k] == "gaussian_noise", "{} changed everything", names[k]);
            }
            for y in 0..h {
                for x in 0..w {
                    let same = (0..ch).all(|c| reference[0].get(x, y, c) == reference.last().unwrap().get(x, y, c));
                    if rec.label(x, y) == 0 {
                        untouched += 1;
                        assert!(same, "{format}: a pixel with label 0 changed at ({x},{y})");
                    }
                }
            }
            assert!(untouched > 0, "{format}: weak noise leaves some pixels untouched");
        }
    }

    #[test]
    fn files_hold_the_labels_and_exact_deltas() {
        let dir = tempfile::tempdir().unwrap();
        let mut input = crate::faults::kit::bench_scene(96, 64, PixelFormat::Rgb8, 1).unwrap();
        input.seq = 2;
        let mut chain = sparse_chain(3);
        let mut rec = MaskRecorder::new(MaskOptions { deltas: true });
        let mut report = FrameReport::default();
        assert!(matches!(rec.write(dir.path(), "x"), Err(MaskError::NothingRecorded)));
        let mut f = input.clone();
        chain.apply_recording(&mut f, &mut report, &mut rec).unwrap();
        let out = rec.write(&dir.path().join("m"), "img_007").unwrap();
        assert!(out.labels.ends_with("img_007.labels.png") && out.labels_more.is_empty());
        assert_eq!(out.bits.len(), 5);
        let png = image::open(&out.labels).unwrap().into_luma16();
        assert_eq!(png.dimensions(), (96, 64));
        for (x, y, v) in png.enumerate_pixels() {
            assert_eq!(v.0[0] as u32, rec.label(x as usize, y as usize));
        }
        // One delta file per effect that changed something, named by bit and effect.
        let with_changes: Vec<usize> = (0..5).filter(|&k| rec.changed_pixels(k) > 0).collect();
        assert_eq!(out.deltas.iter().map(|d| d.bit).collect::<Vec<_>>(), with_changes);
        for d in &out.deltas {
            assert!(d.path.ends_with(&format!("img_007.delta-{:02}-{}.tiff", d.bit, d.effect)), "{}", d.path);
            let mut dec = tiff::decoder::Decoder::new(std::fs::File::open(&d.path).unwrap()).unwrap();
            assert_eq!(dec.dimensions().unwrap(), (96, 64));
            let tiff::decoder::DecodingResult::F32(v) = dec.read_image().unwrap() else { panic!("not f32") };
            for y in 0..64 {
                for x in 0..96 {
                    for c in 0..3 {
                        assert_eq!(v[(y * 96 + x) * 3 + c] as i32, rec.delta(d.bit, x, y, c).unwrap());
                    }
                }
            }
        }
        let json = serde_json::to_value(&out).unwrap();
        assert_eq!(json["bits"][0], "channel_shift");
        assert!(json["deltas"][0]["path"].is_string() && json["changed_px"].is_array());
    }

    #[test]
    fn more_than_sixteen_effects_continue_in_a_second_label_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut chain = Chain::new(0);
        for _ in 0..18 {
            chain.push("gain_offset", params("gain_offset", &[("offset_dn", 1.0)])).unwrap();
        }
        let mut f = Frame::new(8, 4, PixelFormat::Mono8).unwrap();
        let mut rec = MaskRecorder::new(MaskOptions::default());
        let mut report = FrameReport::default();
        chain.apply_recording(&mut f, &mut report, &mut rec).unwrap();
        assert!(rec.labels().iter().all(|&l| l == (1 << 18) - 1));
        let out = rec.write(dir.path(), "f").unwrap();
        assert_eq!(out.labels_more.len(), 1);
        let lo = image::open(&out.labels).unwrap().into_luma16();
        let hi = image::open(&out.labels_more[0]).unwrap().into_luma16();
        assert!(lo.pixels().all(|p| p.0[0] == 0xffff) && hi.pixels().all(|p| p.0[0] == 3));
        for _ in 0..15 {
            chain.push("gain_offset", params("gain_offset", &[("offset_dn", 1.0)])).unwrap();
        }
        let e = chain.apply_recording(&mut f, &mut report, &mut rec).unwrap_err().to_string();
        assert!(e.contains("33 enabled effects") && e.contains("at most 32"), "{e}");
    }

    #[test]
    fn config_section_and_one_call_helper() {
        let cfg = crate::config::FaultConfig::parse(
            "[[effects]]\nname = \"hot_pixels\"\nrate = 0.01\n\n[masks]\ndeltas = true\ndir = \"m\"\n",
            "t",
        )
        .unwrap();
        let mc = MaskConfig::from_config(&cfg).unwrap().unwrap();
        assert_eq!(mc, MaskConfig { options: MaskOptions { deltas: true }, dir: Some("m".into()) });
        let off = crate::config::FaultConfig::parse("[masks]\nenabled = false\n", "t").unwrap();
        assert_eq!(MaskConfig::from_config(&off).unwrap(), None);
        let bad = crate::config::FaultConfig::parse("[masks]\ndelta = true\n", "t").unwrap();
        assert!(MaskConfig::from_config(&bad).unwrap_err().to_string().contains("[masks].delta: unknown key"));
        assert_eq!(MaskConfig::from_config(&crate::config::FaultConfig::parse("", "t").unwrap()).unwrap(), None);

        let dir = tempfile::tempdir().unwrap();
        let mut chain = Chain::from_config(&cfg).unwrap();
        let mut rec = MaskRecorder::new(mc.options);
        let mut report = FrameReport::default();
        let mut f = crate::faults::kit::bench_scene(64, 48, PixelFormat::Mono8, 1).unwrap();
        let (out, m) = apply_with_masks(&mut chain, &mut f, &mut report, &mut rec, dir.path(), "frame_000000").unwrap();
        assert_eq!(out, Outcome::Keep);
        let m = m.unwrap();
        assert_eq!(m.bits, vec!["hot_pixels"]);
        assert!(std::path::Path::new(&m.labels).exists() && m.deltas.len() == 1);
        let mut drop_chain = Chain::new(0);
        drop_chain.push("frame_drop", params("frame_drop", &[("p", 1.0)])).unwrap();
        let (out, m) = apply_with_masks(&mut drop_chain, &mut f, &mut report, &mut rec, dir.path(), "x").unwrap();
        assert_eq!((out, m), (Outcome::Drop, None));
    }

    #[test]
    fn a_dropped_frame_stops_recording_at_the_dropping_effect() {
        let mut chain = Chain::new(0);
        chain.push("gain_offset", params("gain_offset", &[("offset_dn", 2.0)])).unwrap();
        chain.push("frame_drop", params("frame_drop", &[("p", 1.0)])).unwrap();
        let mut f = Frame::new(8, 4, PixelFormat::Mono8).unwrap();
        let mut rec = MaskRecorder::new(MaskOptions::default());
        let mut report = FrameReport::default();
        assert_eq!(chain.apply_recording(&mut f, &mut report, &mut rec).unwrap(), Outcome::Drop);
        assert_eq!(rec.bits(), &["gain_offset", "frame_drop"]);
        assert!(rec.labels().iter().all(|&l| l == 1), "frame_drop changes no pixel");
        assert_eq!(mask_stem(Some("a/b/img.png"), 3), "img");
        assert_eq!(mask_stem(None, 3), "frame_000003");
    }
}
