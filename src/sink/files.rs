//! `files:` sink: one image file per frame.
//!
//! URI: `files:DIR[?format=png|pgm|jpg|tiff&quality=95&compression=fast|default|best]`.
//!
//! - `png` (default): 8-bit grey, 8-bit RGB or 16-bit grey, lossless. `pgm`: binary PGM (P5,
//!   8 or 16 bit) for grey and PPM (P6, extension `.ppm`) for RGB. `tiff`: lossless, 8/16 bit.
//!   `jpg`: 8-bit only (quality 1..=100, default 95), refused for `mono16`.
//! - File name: the input's name with the extension of the output format (`img_007.jpg` →
//!   `img_007.png`) when the source has names, else `frame_{seq:06}.<ext>`.
//! - Files are written to `NAME.tmp` and renamed, so a reader never sees half a file.
//! - The folder is created if missing. Buffers are reused: no allocation per frame once the
//!   first frame was written (apart from the encoder's own state).

use super::{Sink, SinkError};
use crate::frame::{Frame, FrameData, PixelFormat};
use crate::source::{UriOptions, split_uri};
use image::codecs::jpeg::JpegEncoder;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::codecs::tiff::TiffEncoder;
use image::{ExtendedColorType, ImageEncoder};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Output image format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageFormat {
    Png,
    Pnm,
    Jpeg,
    Tiff,
}

impl ImageFormat {
    pub fn parse(s: &str) -> Option<ImageFormat> {
        match s.to_ascii_lowercase().as_str() {
            "png" => Some(ImageFormat::Png),
            "pgm" | "ppm" | "pnm" => Some(ImageFormat::Pnm),
            "jpg" | "jpeg" => Some(ImageFormat::Jpeg),
            "tif" | "tiff" => Some(ImageFormat::Tiff),
            _ => None,
        }
    }
    /// File extension for a frame of pixel format `f`.
    pub fn extension(self, f: PixelFormat) -> &'static str {
        match (self, f) {
            (ImageFormat::Png, _) => "png",
            (ImageFormat::Pnm, PixelFormat::Rgb8) => "ppm",
            (ImageFormat::Pnm, _) => "pgm",
            (ImageFormat::Jpeg, _) => "jpg",
            (ImageFormat::Tiff, _) => "tiff",
        }
    }
}

/// How to encode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WriteOptions {
    pub format: ImageFormat,
    /// JPEG quality 1..=100.
    pub quality: u8,
    pub compression: CompressionType,
}

impl Default for WriteOptions {
    fn default() -> Self {
        WriteOptions { format: ImageFormat::Png, quality: 95, compression: CompressionType::Fast }
    }
}

impl WriteOptions {
    /// Read `format`, `quality`, `compression` from URI options.
    pub fn from_options(o: &mut UriOptions) -> Result<WriteOptions, String> {
        let mut w = WriteOptions::default();
        if let Some(f) = o.raw("format") {
            w.format = ImageFormat::parse(&f)
                .ok_or_else(|| format!("option format={f} is not accepted; expected png, pgm, jpg or tiff"))?;
        }
        w.quality = o.int("quality", 1, 100)?.map_or(w.quality, |q| q as u8);
        if let Some(c) = o.raw("compression") {
            w.compression = match c.as_str() {
                "fast" => CompressionType::Fast,
                "default" => CompressionType::Default,
                "best" => CompressionType::Best,
                _ => return Err(format!("option compression={c} is not accepted; expected fast, default or best")),
            };
        }
        Ok(w)
    }
}

/// Output file name for an input name (extension replaced) or a sequence number.
pub fn output_name(input: Option<&str>, seq: u64, ext: &str) -> String {
    match input {
        Some(name) => {
            let stem = Path::new(name).file_stem().map(|s| s.to_string_lossy()).unwrap_or_else(|| name.into());
            format!("{stem}.{ext}")
        }
        None => format!("frame_{seq:06}.{ext}"),
    }
}

/// Packed native-endian bytes of the frame (what `image` encoders take), into `buf`.
fn packed_bytes<'a>(frame: &'a Frame, buf: &'a mut Vec<u8>) -> &'a [u8] {
    let n = frame.row_len();
    let h = frame.height as usize;
    match &frame.data {
        FrameData::U8(d) if frame.stride == n => &d[..n * h],
        FrameData::U8(d) => {
            buf.clear();
            for r in d.chunks(frame.stride).take(h) {
                buf.extend_from_slice(&r[..n]);
            }
            buf
        }
        FrameData::U16(d) => {
            buf.clear();
            for r in d.chunks(frame.stride).take(h) {
                for v in &r[..n] {
                    buf.extend_from_slice(&v.to_ne_bytes());
                }
            }
            buf
        }
    }
}

/// Binary PGM (P5, maxval 255 or 65535, big-endian 16-bit samples) or PPM (P6), written row by
/// row from the strided frame (the `image` crate's PNM encoder has no 16-bit PGM).
fn write_pnm(w: &mut impl Write, frame: &Frame) -> std::io::Result<()> {
    let magic = if frame.format == PixelFormat::Rgb8 { "P6" } else { "P5" };
    let maxval = if frame.format == PixelFormat::Mono16 { 65535 } else { 255 };
    write!(w, "{magic}\n{} {}\n{maxval}\n", frame.width, frame.height)?;
    let n = frame.row_len();
    match &frame.data {
        FrameData::U8(d) => {
            for r in d.chunks(frame.stride).take(frame.height as usize) {
                w.write_all(&r[..n])?;
            }
        }
        FrameData::U16(d) => {
            for r in d.chunks(frame.stride).take(frame.height as usize) {
                for v in &r[..n] {
                    w.write_all(&v.to_be_bytes())?;
                }
            }
        }
    }
    Ok(())
}

/// Encode `frame` into `path` (via `path.tmp` and a rename). `scratch` is reused.
pub fn write_image(path: &Path, frame: &Frame, opts: &WriteOptions, scratch: &mut Vec<u8>) -> Result<(), String> {
    let color = match frame.format {
        PixelFormat::Mono8 | PixelFormat::Bayer8 => ExtendedColorType::L8,
        PixelFormat::Mono16 => ExtendedColorType::L16,
        PixelFormat::Rgb8 => ExtendedColorType::Rgb8,
    };
    if opts.format == ImageFormat::Jpeg && frame.format == PixelFormat::Mono16 {
        return Err("jpg cannot hold 16-bit samples; use format=png, pgm or tiff".into());
    }
    // PNM is written straight from the strided frame; the others take packed bytes.
    let bytes: &[u8] = if opts.format == ImageFormat::Pnm { &[] } else { packed_bytes(frame, scratch) };
    let tmp = path.with_extension(format!("{}.tmp", path.extension().and_then(|e| e.to_str()).unwrap_or("")));
    let file = std::fs::File::create(&tmp).map_err(|e| format!("cannot create {}: {e}", tmp.display()))?;
    let mut w = BufWriter::with_capacity(1 << 16, file);
    let (wd, ht) = (frame.width, frame.height);
    let res = match opts.format {
        ImageFormat::Png => PngEncoder::new_with_quality(&mut w, opts.compression, FilterType::Adaptive)
            .write_image(bytes, wd, ht, color),
        ImageFormat::Pnm => write_pnm(&mut w, frame).map_err(image::ImageError::IoError),
        ImageFormat::Jpeg => JpegEncoder::new_with_quality(&mut w, opts.quality).write_image(bytes, wd, ht, color),
        ImageFormat::Tiff => {
            // The TIFF encoder needs Seek: encode into memory, then write.
            let mut cur = std::io::Cursor::new(Vec::new());
            // allocation: per frame for TIFF only (encoder needs a seekable buffer)
            TiffEncoder::new(&mut cur)
                .write_image(bytes, wd, ht, color)
                .and_then(|_| w.write_all(cur.get_ref()).map_err(image::ImageError::IoError))
        }
    };
    let res = res.map_err(|e| e.to_string()).and_then(|_| w.flush().map_err(|e| e.to_string()));
    drop(w);
    if let Err(e) = res {
        let _ = std::fs::remove_file(&tmp);
        return Err(format!("cannot write {}: {e}", path.display()));
    }
    std::fs::rename(&tmp, path).map_err(|e| format!("cannot rename {} to {}: {e}", tmp.display(), path.display()))
}

/// The `files:` sink.
pub struct FilesSink {
    uri: String,
    dir: PathBuf,
    opts: WriteOptions,
    scratch: Vec<u8>,
    last: Option<String>,
    written: u64,
}

impl FilesSink {
    pub fn open(uri: &str) -> Result<FilesSink, SinkError> {
        let (_, body, opts) = split_uri(uri);
        let bad = |reason: String| SinkError::BadUri { uri: uri.to_string(), reason };
        if body.is_empty() {
            return Err(bad("expected files:DIR (output folder)".into()));
        }
        let mut o = UriOptions::new(opts);
        let wo = WriteOptions::from_options(&mut o).map_err(bad)?;
        o.finish().map_err(bad)?;
        let dir = PathBuf::from(body);
        std::fs::create_dir_all(&dir).map_err(|e| SinkError::Failed {
            uri: uri.to_string(),
            reason: format!("cannot create {}: {e}", dir.display()),
        })?;
        Ok(FilesSink { uri: uri.to_string(), dir, opts: wo, scratch: Vec::new(), last: None, written: 0 })
    }

    /// Folder the files go to.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
    /// Frames written so far.
    pub fn written(&self) -> u64 {
        self.written
    }
}

impl Sink for FilesSink {
    fn describe(&self) -> String {
        let f = match self.opts.format {
            ImageFormat::Png => "png",
            ImageFormat::Pnm => "pgm/ppm",
            ImageFormat::Jpeg => "jpg",
            ImageFormat::Tiff => "tiff",
        };
        format!("files:{} ({f})", self.dir.display())
    }

    fn write_frame(&mut self, frame: &Frame, name: Option<&str>) -> Result<(), SinkError> {
        // allocation: the file name and path, per frame (negligible next to encoding and I/O)
        let file = output_name(name, frame.seq, self.opts.format.extension(frame.format));
        let path = self.dir.join(&file);
        write_image(&path, frame, &self.opts, &mut self.scratch)
            .map_err(|reason| SinkError::Failed { uri: self.uri.clone(), reason })?;
        self.last = Some(path.display().to_string());
        self.written += 1;
        Ok(())
    }

    fn last_output(&self) -> Option<&str> {
        self.last.as_deref()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names() {
        assert_eq!(output_name(Some("img_007.jpg"), 3, "png"), "img_007.png");
        assert_eq!(output_name(Some("noext"), 3, "pgm"), "noext.pgm");
        assert_eq!(output_name(None, 42, "png"), "frame_000042.png");
    }
}
