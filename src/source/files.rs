//! `files:` source: a folder of images replayed in file-name order.
//!
//! URI: `files:DIR[?loop=true&fps=30&timestamps=FILE&shard=K/N&poses=FILE&fx=..&fy=..&cx=..&cy=..]`.
//!
//! - Formats: PNG (8 and 16 bit), JPEG, PGM/PPM/PNM/PAM, TIFF (by content; the extension only
//!   decides what is listed as an image).
//! - Pixel formats: grey 8-bit → `mono8`, grey 16-bit → `mono16`, RGB 8-bit → `rgb8`. Alpha is
//!   dropped (RGBA → `rgb8`, grey+alpha → `mono8`/`mono16`). Other conversions, all documented
//!   in [`format_of`]: RGB 16-bit → `rgb8` by `round(v / 257)` (there is no 16-bit colour
//!   format), 32-bit float RGB(A) → `rgb8` by `round(clamp(v, 0, 1) · 255)`.
//! - The first frame fixes the stream format: the reference is the header of the first file in
//!   the full sorted listing whose header can be read. A file that differs from it (size or
//!   pixel format), a corrupt file, or a file that is not an image gives
//!   [`SourceError::BadInput`] naming the file and the expected vs got; the caller logs it as a
//!   `skip` record and calls again. Hidden files (`.name`) and sub-folders are ignored.
//! - `seq` is the file's index in the full sorted listing (plus `loop × files` when looping),
//!   so a skipped file leaves a gap in `seq` and `apply --shard` sees the same numbering as an
//!   unsharded run.
//! - `fps=F` sets `pts_ns = seq / F` (default 30). `timestamps=FILE` reads `<file name>
//!   <pts_ns>` lines (`#` comments allowed) and uses the recorded times instead; pacing in
//!   real time is the pipeline's job. `loop=true` restarts at the end (for timed replay).
//! - `shard=K/N` (0-based K) yields only the files whose index mod N == K.
//! - `poses=FILE` (JSON Lines `{"file":..,"q":[w,x,y,z],"t":[x,y,z]}` or SPEED+-style CSV
//!   `filename,qw,qx,qy,qz,x,y,z`, see [`crate::pose`] for the convention) gives each file's
//!   target pose, carried into the ground-truth log; files without a line have no pose. A JSON
//!   line may carry `"camera":{"fx":..,"fy":..,"cx":..,"cy":..}`; `fx,fy,cx,cy` options (all
//!   four, pixels) give the camera of every file. A relative path is tried as given, then
//!   inside DIR; a poses file inside DIR is not an input.
//! - A header claiming a size over [`crate::limits::ImageLimits`] (default 16384 x 16384,
//!   1024 MB decoded) is a [`SourceError::BadInput`] found before any allocation.

use super::{Source, SourceError, UriOptions, split_uri};
use crate::frame::{Frame, FrameData, PixelFormat};
use image::{ColorType, ImageDecoder};
use std::path::{Path, PathBuf};

/// Extensions listed as images (case-insensitive).
pub const IMAGE_EXTENSIONS: &[&str] = &["png", "jpg", "jpeg", "pgm", "ppm", "pnm", "pbm", "pam", "tif", "tiff"];

/// Frames kept for reuse by [`FilesSource::recycle`].
const POOL_SIZE: usize = 4;

/// One file of a listing.
#[derive(Debug, Clone, PartialEq)]
pub struct Item {
    pub path: PathBuf,
    /// File name (lossy UTF-8), used as the item name and by sinks that keep names.
    pub name: String,
}

impl Item {
    /// True when the extension is one of [`IMAGE_EXTENSIONS`].
    pub fn is_image(&self) -> bool {
        self.path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)))
    }
}

/// Width, height and pixel format of a stream or a file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shape {
    pub width: u32,
    pub height: u32,
    pub format: PixelFormat,
}

impl std::fmt::Display for Shape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}x{} {}", self.width, self.height, self.format)
    }
}

/// Regular, non-hidden files of `dir`, sorted by file name (byte order).
pub fn list(dir: &Path) -> Result<Vec<Item>, SourceError> {
    let fatal = |reason: String| SourceError::Fatal { uri: format!("files:{}", dir.display()), reason };
    let rd = std::fs::read_dir(dir).map_err(|e| fatal(format!("cannot read folder: {e}")))?;
    let mut items = Vec::new();
    for entry in rd {
        let entry = entry.map_err(|e| fatal(format!("cannot read folder: {e}")))?;
        let name_os = entry.file_name();
        let name = name_os.to_string_lossy().into_owned();
        if name.starts_with('.') {
            continue;
        }
        // Follows symlinks: a link to an image is an image.
        let is_file = std::fs::metadata(entry.path()).map(|m| m.is_file()).unwrap_or(false);
        if is_file {
            items.push((name_os, Item { path: entry.path(), name }));
        }
    }
    items.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(items.into_iter().map(|(_, i)| i).collect())
}

/// Our pixel format for a decoded colour type (see the module documentation).
pub fn format_of(c: ColorType) -> PixelFormat {
    match c {
        ColorType::L8 | ColorType::La8 => PixelFormat::Mono8,
        ColorType::L16 | ColorType::La16 => PixelFormat::Mono16,
        // Rgb8, Rgba8, Rgb16 (→ v/257), Rgba16, Rgb32F, Rgba32F (→ clamp·255) and any future type.
        _ => PixelFormat::Rgb8,
    }
}

fn bad(item: &Item, reason: impl Into<String>) -> SourceError {
    SourceError::BadInput { item: item.path.display().to_string(), reason: reason.into() }
}

fn decoder(item: &Item) -> Result<impl ImageDecoder + use<>, SourceError> {
    if !item.is_image() {
        return Err(bad(item, format!("not an image file (accepted extensions: {})", IMAGE_EXTENSIONS.join(", "))));
    }
    // The header's size is checked against the limits before anything is allocated.
    crate::limits::open_decoder(&item.path, &crate::limits::ImageLimits::current()).map_err(|e| bad(item, e))
}

/// Size and pixel format from the file header only (cheap).
pub fn probe(item: &Item) -> Result<Shape, SourceError> {
    let d = decoder(item)?;
    let (width, height) = d.dimensions();
    Ok(Shape { width, height, format: format_of(d.color_type()) })
}

/// Shape of the first file of `items` whose header can be read: the stream's reference.
pub fn reference_shape(items: &[Item]) -> Option<Shape> {
    items.iter().find_map(|i| probe(i).ok())
}

/// Decode `item` into `frame`, reusing `frame`'s buffer and `scratch` (no allocation once they
/// are large enough). With `expect`, a file of another shape is a [`SourceError::BadInput`].
/// Sets width, height, stride (packed), format and data; `seq`/`pts_ns` are left to the caller.
pub fn decode_into(
    item: &Item,
    expect: Option<Shape>,
    frame: &mut Frame,
    scratch: &mut Vec<u8>,
) -> Result<Shape, SourceError> {
    let d = decoder(item)?;
    let (width, height) = d.dimensions();
    let color = d.color_type();
    let shape = Shape { width, height, format: format_of(color) };
    if let Some(e) = expect
        && e != shape
    {
        return Err(bad(item, format!("differs from the first frame: expected {e}, got {shape}")));
    }
    if width == 0 || height == 0 {
        return Err(bad(item, format!("empty image {width}x{height}")));
    }
    let pixels = (width as usize)
        .checked_mul(height as usize)
        .ok_or_else(|| bad(item, format!("image size {width}x{height} overflows")))?;
    let total = usize::try_from(d.total_bytes()).map_err(|_| bad(item, "image too large"))?;
    let corrupt = |e: image::ImageError| bad(item, format!("corrupt image: {e}"));

    // Make the frame's storage the right type and length (reusing its allocation).
    let n = pixels * shape.format.channels();
    match (&mut frame.data, shape.format) {
        (FrameData::U16(v), PixelFormat::Mono16) => v.resize(n, 0),
        (FrameData::U8(v), f) if f != PixelFormat::Mono16 => v.resize(n, 0),
        // allocation: only when a recycled frame had the other sample type
        (data, PixelFormat::Mono16) => *data = FrameData::U16(vec![0; n]),
        (data, _) => *data = FrameData::U8(vec![0; n]),
    }
    frame.width = width;
    frame.height = height;
    frame.stride = width as usize * shape.format.channels();
    frame.format = shape.format;

    match (color, &mut frame.data) {
        // Direct decode into the frame.
        (ColorType::L8 | ColorType::Rgb8, FrameData::U8(out)) => d.read_image(out).map_err(corrupt)?,
        (_, data) => {
            scratch.resize(total, 0);
            d.read_image(scratch).map_err(corrupt)?;
            convert(color, scratch, data);
        }
    }
    Ok(shape)
}

/// Convert decoded native-endian bytes of colour type `c` into our sample storage.
fn convert(c: ColorType, src: &[u8], dst: &mut FrameData) {
    let u16s = |b: &[u8]| u16::from_ne_bytes([b[0], b[1]]);
    let f32s = |b: &[u8]| f32::from_ne_bytes([b[0], b[1], b[2], b[3]]);
    let from16 = |v: u16| ((v as u32 + 128) / 257) as u8;
    let from_f = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    match (c, dst) {
        (ColorType::L16, FrameData::U16(o)) => o.iter_mut().zip(src.chunks_exact(2)).for_each(|(o, b)| *o = u16s(b)),
        (ColorType::La16, FrameData::U16(o)) => o.iter_mut().zip(src.chunks_exact(4)).for_each(|(o, b)| *o = u16s(b)),
        (ColorType::La8, FrameData::U8(o)) => o.iter_mut().zip(src.chunks_exact(2)).for_each(|(o, b)| *o = b[0]),
        (ColorType::Rgba8, FrameData::U8(o)) => {
            o.chunks_exact_mut(3).zip(src.chunks_exact(4)).for_each(|(o, b)| o.copy_from_slice(&b[..3]))
        }
        (ColorType::Rgb16 | ColorType::Rgba16, FrameData::U8(o)) => {
            let px = if c == ColorType::Rgb16 { 6 } else { 8 };
            for (o, b) in o.chunks_exact_mut(3).zip(src.chunks_exact(px)) {
                for k in 0..3 {
                    o[k] = from16(u16s(&b[2 * k..]));
                }
            }
        }
        (ColorType::Rgb32F | ColorType::Rgba32F, FrameData::U8(o)) => {
            let px = if c == ColorType::Rgb32F { 12 } else { 16 };
            for (o, b) in o.chunks_exact_mut(3).zip(src.chunks_exact(px)) {
                for k in 0..3 {
                    o[k] = from_f(f32s(&b[4 * k..]));
                }
            }
        }
        (ColorType::L8 | ColorType::Rgb8, FrameData::U8(o)) => {
            let n = o.len();
            o.copy_from_slice(&src[..n])
        }
        // Unreachable by construction of `format_of`; leave the zeroed buffer.
        _ => {}
    }
}

/// Recorded timestamps: `<file name> <pts_ns>` per line.
fn read_timestamps(path: &Path, items: &[Item]) -> Result<Vec<u64>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("timestamps file {}: {e}", path.display()))?;
    let mut map = std::collections::HashMap::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut parts = line.split(|c: char| c.is_whitespace() || c == ',').filter(|s| !s.is_empty());
        let (name, t) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
        let t: u64 = t.parse().map_err(|_| {
            format!("{}:{}: expected '<file name> <pts_ns>' with pts_ns a non-negative integer", path.display(), i + 1)
        })?;
        map.insert(name.to_string(), t);
    }
    items
        .iter()
        .map(|it| {
            map.get(&it.name)
                .copied()
                .ok_or_else(|| format!("timestamps file {} has no entry for {}", path.display(), it.name))
        })
        .collect()
}

/// Parse `K/N` (0-based K < N).
pub fn parse_shard(s: &str) -> Result<(u64, u64), String> {
    let err = || format!("shard '{s}' is not accepted; expected K/N with 0 <= K < N (0-based), e.g. 0/4");
    let (k, n) = s.split_once('/').ok_or_else(err)?;
    let (k, n): (u64, u64) = (k.trim().parse().map_err(|_| err())?, n.trim().parse().map_err(|_| err())?);
    if n == 0 || k >= n {
        return Err(err());
    }
    Ok((k, n))
}

/// The `files:` source.
pub struct FilesSource {
    dir: PathBuf,
    items: Vec<Item>,
    /// Indices into `items` this source yields (all, or one shard).
    order: Vec<usize>,
    reference: Option<Shape>,
    looping: bool,
    fps: f64,
    timestamps: Option<Vec<u64>>,
    /// Position in `order` and loop count.
    pos: usize,
    loops: u64,
    current: Option<usize>,
    pool: Vec<Frame>,
    scratch: Vec<u8>,
    /// Truth per item (`poses=FILE` and the camera options), by index into `items`.
    truths: Vec<crate::pose::Truth>,
}

impl FilesSource {
    pub fn open(uri: &str) -> Result<FilesSource, SourceError> {
        let (_, body, opts) = split_uri(uri);
        let bad_uri = |reason: String| SourceError::BadUri { uri: uri.to_string(), reason };
        if body.is_empty() {
            return Err(bad_uri("expected files:DIR (a folder of images)".into()));
        }
        let dir = PathBuf::from(body);
        if !dir.is_dir() {
            return Err(bad_uri(format!("{} is not a folder", dir.display())));
        }
        let mut o = UriOptions::new(opts);
        let looping = o.flag("loop").map_err(bad_uri)?.unwrap_or(false);
        let fps = o.num("fps", 1e-3, 1e6).map_err(bad_uri)?.unwrap_or(30.0);
        let ts_path = o.raw("timestamps");
        let shard = o.raw("shard").map(|s| parse_shard(&s)).transpose().map_err(bad_uri)?;
        let poses_path = o.raw("poses");
        let mut k = [0.0; 4];
        let mut given = 0;
        for (v, key) in k.iter_mut().zip(["fx", "fy", "cx", "cy"]) {
            if let Some(x) = o.num(key, -1e9, 1e9).map_err(bad_uri)? {
                *v = x;
                given += 1;
            }
        }
        if given != 0 && given != 4 {
            return Err(bad_uri("give all four of fx, fy, cx, cy (pixels) or none".into()));
        }
        let camera = (given == 4).then_some(crate::pose::Intrinsics { fx: k[0], fy: k[1], cx: k[2], cy: k[3] });
        o.finish().map_err(bad_uri)?;

        let mut items = list(&dir)?;
        let ts_path = ts_path.map(|p| {
            let p = PathBuf::from(p);
            if p.exists() { p } else { dir.join(p) }
        });
        let poses_path = poses_path.map(|p| {
            let p = PathBuf::from(p);
            if p.exists() { p } else { dir.join(p) }
        });
        for tp in ts_path.iter().chain(poses_path.iter()) {
            // The timestamps and poses files may live in the folder: they are not inputs.
            let canon = std::fs::canonicalize(tp).ok();
            items.retain(|i| std::fs::canonicalize(&i.path).ok() != canon);
        }
        if items.is_empty() {
            return Err(SourceError::Fatal { uri: uri.to_string(), reason: "no files in the folder".into() });
        }
        let timestamps = ts_path.map(|p| read_timestamps(&p, &items)).transpose().map_err(bad_uri)?;
        let order = match shard {
            Some((k, n)) => (0..items.len()).filter(|i| *i as u64 % n == k).collect(),
            None => (0..items.len()).collect(),
        };
        let poses = poses_path.map(|p| crate::pose::read_poses(&p)).transpose().map_err(bad_uri)?;
        let truths = items
            .iter()
            .map(|it| {
                let line = poses.as_ref().and_then(|m| m.get(&it.name));
                crate::pose::Truth { pose: line.map(|l| l.pose), camera: line.and_then(|l| l.camera).or(camera) }
            })
            .collect();
        let reference = reference_shape(&items);
        Ok(FilesSource {
            truths,
            dir,
            items,
            order,
            reference,
            looping,
            fps,
            timestamps,
            pos: 0,
            loops: 0,
            current: None,
            pool: Vec::new(),
            scratch: Vec::new(),
        })
    }

    /// The full sorted listing.
    pub fn items(&self) -> &[Item] {
        &self.items
    }
    /// Stream shape fixed by the first readable file, if any.
    pub fn reference(&self) -> Option<Shape> {
        self.reference
    }

    fn pts_ns(&self, index: usize, seq: u64) -> u64 {
        match &self.timestamps {
            Some(ts) => {
                let (first, last) = (ts[0], ts[ts.len() - 1]);
                let n = ts.len() as u64;
                // One loop lasts the recorded span plus one mean frame interval.
                let period = if n > 1 { (last - first.min(last)) * n / (n - 1) } else { (1e9 / self.fps) as u64 };
                ts[index].saturating_add(self.loops.saturating_mul(period))
            }
            None => (seq as f64 * 1e9 / self.fps).round() as u64,
        }
    }
}

impl Source for FilesSource {
    fn describe(&self) -> String {
        let shape = self.reference.map(|s| s.to_string()).unwrap_or_else(|| "no readable image".into());
        let mut s = format!("files:{} ({} files, {shape}", self.dir.display(), self.items.len());
        if self.order.len() != self.items.len() {
            s.push_str(&format!(", shard of {} files", self.order.len()));
        }
        match &self.timestamps {
            Some(_) => s.push_str(", recorded timestamps"),
            None => s.push_str(&format!(", {} fps", self.fps)),
        }
        if self.looping {
            s.push_str(", loop");
        }
        s.push(')');
        s
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, SourceError> {
        if self.pos >= self.order.len() {
            if !self.looping || self.order.is_empty() {
                return Ok(None);
            }
            self.pos = 0;
            self.loops += 1;
        }
        let index = self.order[self.pos];
        self.pos += 1;
        self.current = Some(index);
        let seq = self.loops * self.items.len() as u64 + index as u64;
        let mut frame = match self.pool.pop() {
            Some(f) => f,
            // allocation: until the pool holds recycled frames
            None => Frame { seq, ..Frame::empty() },
        };
        match decode_into(&self.items[index], self.reference, &mut frame, &mut self.scratch) {
            Ok(_) => {
                frame.seq = seq;
                frame.pts_ns = self.pts_ns(index, seq);
                Ok(Some(frame))
            }
            Err(e) => {
                self.pool.push(frame);
                Err(e)
            }
        }
    }

    fn item_name(&self) -> Option<&str> {
        self.current.map(|i| self.items[i].name.as_str())
    }

    fn truth(&self) -> crate::pose::Truth {
        self.current.map(|i| self.truths[i]).unwrap_or_default()
    }

    fn recycle(&mut self, frame: Frame) {
        if self.pool.len() < POOL_SIZE {
            self.pool.push(frame);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shard_parsing() {
        assert_eq!(parse_shard("0/3"), Ok((0, 3)));
        assert_eq!(parse_shard("2/3"), Ok((2, 3)));
        assert!(parse_shard("3/3").unwrap_err().contains("0 <= K < N"));
        assert!(parse_shard("1/0").is_err());
        assert!(parse_shard("x").is_err());
    }

    #[test]
    fn conversions_drop_alpha_and_scale() {
        let mut d = FrameData::U8(vec![0; 3]);
        convert(ColorType::Rgba8, &[1, 2, 3, 4], &mut d);
        assert_eq!(d, FrameData::U8(vec![1, 2, 3]));
        let mut d = FrameData::U8(vec![0; 1]);
        convert(ColorType::La8, &[9, 200], &mut d);
        assert_eq!(d, FrameData::U8(vec![9]));
        let mut src = Vec::new();
        for v in [65535u16, 257, 0] {
            src.extend_from_slice(&v.to_ne_bytes());
        }
        let mut d = FrameData::U8(vec![0; 3]);
        convert(ColorType::Rgb16, &src, &mut d);
        assert_eq!(d, FrameData::U8(vec![255, 1, 0]));
    }
}
