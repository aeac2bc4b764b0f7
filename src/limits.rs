//! Caps on the size of an image or a negotiated stream format, checked from the header (or the
//! caps, or the camera's region) **before** anything of that size is allocated: a 100-byte PNG
//! whose header claims 100000x100000 is rejected as a bad input instead of asking for 10 GB.
//!
//! - Default: at most 16384 x 16384 pixels and 1024 MB of decoded samples per image
//!   ([`ImageLimits::default`]); 16384² RGB8 (768 MB) fits.
//! - Change: `faultcam --max-image-dims WxH --max-image-mb N SUBCOMMAND ...` (global flags, any
//!   subcommand), which sets the process-wide limits ([`ImageLimits::set_current`]).
//! - Applied to: every image decoder (PNG, JPEG, PNM, TIFF through [`open_decoder`]: the
//!   `files:` source, `apply`, `eval`, `diagnose`), the `image` crate's own allocation cap
//!   (`image::Limits::max_alloc`, for the decoders' internal buffers), GStreamer caps, the
//!   Aravis region, the V4L2 format and the `synth:` size.
//! - Decoded bytes = width · height · bytes per pixel as decoded (e.g. RGBA 16-bit = 8 B/px);
//!   the frame itself is never larger than that, so one image needs at most twice the cap.

use image::{ImageDecoder, ImageReader};
use std::path::Path;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};

/// Default largest width and height, in pixels.
pub const DEFAULT_MAX_DIM: u32 = 16384;
/// Default largest decoded image, in MB (2^20 bytes).
pub const DEFAULT_MAX_MB: u64 = 1024;
/// Largest value accepted for `--max-image-dims` (each side).
pub const MAX_DIM_ACCEPTED: u32 = 1 << 20;
/// Largest value accepted for `--max-image-mb` (1 TB).
pub const MAX_MB_ACCEPTED: u64 = 1 << 20;
/// How the user changes the limits (named in every limit error).
pub const FLAGS_HINT: &str = "raise it with --max-image-dims WxH / --max-image-mb N";

/// Size caps for one image or one frame of a stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageLimits {
    /// Largest width, pixels.
    pub max_width: u32,
    /// Largest height, pixels.
    pub max_height: u32,
    /// Largest decoded size, bytes.
    pub max_bytes: u64,
}

impl Default for ImageLimits {
    fn default() -> ImageLimits {
        ImageLimits { max_width: DEFAULT_MAX_DIM, max_height: DEFAULT_MAX_DIM, max_bytes: DEFAULT_MAX_MB << 20 }
    }
}

static MAX_W: AtomicU32 = AtomicU32::new(DEFAULT_MAX_DIM);
static MAX_H: AtomicU32 = AtomicU32::new(DEFAULT_MAX_DIM);
static MAX_BYTES: AtomicU64 = AtomicU64::new(DEFAULT_MAX_MB << 20);

impl ImageLimits {
    /// The process-wide limits (the defaults unless [`ImageLimits::set_current`] changed them).
    pub fn current() -> ImageLimits {
        ImageLimits {
            max_width: MAX_W.load(Ordering::Relaxed),
            max_height: MAX_H.load(Ordering::Relaxed),
            max_bytes: MAX_BYTES.load(Ordering::Relaxed),
        }
    }

    /// Make these the process-wide limits (the CLI does this once, before any work starts).
    pub fn set_current(self) {
        MAX_W.store(self.max_width, Ordering::Relaxed);
        MAX_H.store(self.max_height, Ordering::Relaxed);
        MAX_BYTES.store(self.max_bytes, Ordering::Relaxed);
    }

    /// Limits from the CLI values: `dims` as `WxH` (1..=1048576 each), `mb` in 1..=1048576.
    pub fn from_flags(dims: Option<&str>, mb: Option<u64>) -> Result<ImageLimits, String> {
        let mut l = ImageLimits::default();
        if let Some(d) = dims {
            (l.max_width, l.max_height) = parse_dims(d)?;
        }
        if let Some(mb) = mb {
            if !(1..=MAX_MB_ACCEPTED).contains(&mb) {
                return Err(format!("--max-image-mb {mb} is not accepted; accepted: 1..={MAX_MB_ACCEPTED} (MB)"));
            }
            l.max_bytes = mb << 20;
        }
        Ok(l)
    }

    /// `Err(reason)` when a `width` x `height` image of `bytes_per_pixel` is over the limits.
    /// `what` says where the size came from ("header", "negotiated caps", ...).
    pub fn check(&self, what: &str, width: u32, height: u32, bytes_per_pixel: u64) -> Result<(), String> {
        let bytes = (width as u64).saturating_mul(height as u64).saturating_mul(bytes_per_pixel);
        if width > self.max_width || height > self.max_height || bytes > self.max_bytes {
            return Err(format!(
                "{what} claims {width}x{height} ({} MB decoded), over the image limit {}x{} pixels and {} MB ({FLAGS_HINT})",
                bytes.div_ceil(1 << 20),
                self.max_width,
                self.max_height,
                self.max_bytes >> 20
            ));
        }
        Ok(())
    }

    /// The `image` crate's limits for the decoders' internal allocations. Width and height are
    /// left open so the header can be read and [`ImageLimits::check`] can name the claimed size.
    pub fn for_image_crate(&self) -> image::Limits {
        let mut l = image::Limits::default();
        l.max_image_width = None;
        l.max_image_height = None;
        l.max_alloc = Some(self.max_bytes);
        l
    }
}

/// `WxH` → (W, H), each 1..=1048576.
pub fn parse_dims(s: &str) -> Result<(u32, u32), String> {
    let err = || {
        format!(
            "--max-image-dims '{s}' is not accepted; expected WxH with 1..={MAX_DIM_ACCEPTED} each, e.g. 16384x16384"
        )
    };
    let (w, h) = s.trim().split_once(['x', 'X']).ok_or_else(err)?;
    let (w, h): (u32, u32) = (w.trim().parse().map_err(|_| err())?, h.trim().parse().map_err(|_| err())?);
    if !(1..=MAX_DIM_ACCEPTED).contains(&w) || !(1..=MAX_DIM_ACCEPTED).contains(&h) {
        return Err(err());
    }
    Ok((w, h))
}

/// Open an image file (format from its content) and check the header's size against `limits`
/// before anything is decoded. The error is a reason without the path (callers name the file).
pub fn open_decoder(path: &Path, limits: &ImageLimits) -> Result<impl ImageDecoder + use<>, String> {
    let mut reader = ImageReader::open(path)
        .map_err(|e| format!("cannot open: {e}"))?
        .with_guessed_format()
        .map_err(|e| format!("cannot read: {e}"))?;
    if reader.format().is_none() {
        return Err("unsupported or unrecognised image format (accepted: PNG, JPEG, PNM, TIFF)".into());
    }
    reader.limits(limits.for_image_crate());
    let d = reader.into_decoder().map_err(|e| match e {
        image::ImageError::Limits(l) => {
            format!("over the decoder's memory limit of {} MB: {l} ({FLAGS_HINT})", limits.max_bytes >> 20)
        }
        e => format!("corrupt or unsupported image: {e}"),
    })?;
    let (w, h) = d.dimensions();
    limits.check("header", w, h, d.color_type().bytes_per_pixel() as u64)?;
    Ok(d)
}

/// Decode a whole image file (for `eval` and `diagnose`), size checked first.
pub fn load_image(path: &Path, limits: &ImageLimits) -> Result<image::DynamicImage, String> {
    let d = open_decoder(path, limits)?;
    image::DynamicImage::from_decoder(d).map_err(|e| format!("corrupt image: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_parse_and_are_range_checked() {
        assert_eq!(parse_dims("640x480"), Ok((640, 480)));
        assert_eq!(parse_dims(" 8X9 "), Ok((8, 9)));
        for bad in ["0x5", "5", "x", "5x-1", "2000000x5"] {
            let e = parse_dims(bad).unwrap_err();
            assert!(e.contains("--max-image-dims") && e.contains("1..=1048576"), "{e}");
        }
        let l = ImageLimits::from_flags(Some("100x50"), Some(3)).unwrap();
        assert_eq!(l, ImageLimits { max_width: 100, max_height: 50, max_bytes: 3 << 20 });
        assert!(ImageLimits::from_flags(None, Some(0)).unwrap_err().contains("--max-image-mb 0"));
        assert_eq!(ImageLimits::from_flags(None, None).unwrap(), ImageLimits::default());
    }

    #[test]
    fn check_bounds_each_side_and_the_bytes() {
        let l = ImageLimits { max_width: 100, max_height: 50, max_bytes: 10_000 };
        assert!(l.check("header", 100, 50, 1).is_ok());
        assert!(l.check("header", 101, 1, 1).is_err());
        assert!(l.check("header", 1, 51, 1).is_err());
        // 100 x 50 x 3 = 15000 bytes > 10000.
        let e = l.check("header", 100, 50, 3).unwrap_err();
        assert!(e.contains("100x50") && e.contains("100x50 pixels") && e.contains("--max-image-dims"), "{e}");
        // Saturating: no overflow on absurd sizes.
        assert!(l.check("header", u32::MAX, u32::MAX, 16).is_err());
        let d = ImageLimits::default();
        assert!(d.check("header", 16384, 16384, 3).is_ok(), "16384² RGB8 fits the default");
        assert!(d.check("header", 100_000, 100_000, 1).unwrap_err().contains("16384x16384"));
    }
}
