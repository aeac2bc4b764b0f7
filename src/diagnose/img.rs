//! Float image planes for analysis, image loading and pairing, and the small filters the
//! signature tests need (box and Gaussian blur, min/max filters, distance transform,
//! derivatives, sub-pixel shift).
//!
//! All analysis happens in **8-bit DN** (`f32`, full scale 255) whatever the file format, so that
//! every threshold and every reported parameter has one unit (EFFECTS.md: parameters "in DN" are
//! 8-bit DN). 16-bit data are divided by 257; their quantisation step is then 1/257.

use super::types::DiagnoseError;
use crate::frame::{Frame, FrameData, PixelFormat};
use std::path::{Path, PathBuf};

/// Full scale of the analysis unit.
pub const FS: f32 = 255.0;

/// A sample at or above this level (8-bit DN) is at the top code of its data: saturated. Half a
/// 16-bit step below FS, so that it holds at every ADC depth read here (8-, 10-, 12-bit data by
/// bit replication and plain 16-bit data all put their top code at FS exactly, and their next
/// code at least 1/257 DN lower). A 10-bit code one below the top (254.75 DN) is not saturated:
/// counting it as such (a threshold of FS − 0.5 for every depth) takes the bright rim of a
/// saturated spot, or a near-saturated feature, for saturation.
pub const SAT_DN: f32 = FS - 0.5 / 257.0;

/// One channel, row-major, packed.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    pub w: usize,
    pub h: usize,
    pub data: Vec<f32>,
}

impl Plane {
    pub fn new(w: usize, h: usize) -> Plane {
        Plane { w, h, data: vec![0.0; w * h] }
    }
    pub fn filled(w: usize, h: usize, v: f32) -> Plane {
        Plane { w, h, data: vec![v; w * h] }
    }
    #[inline(always)]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.w + x]
    }
    /// Clamped access (edge replicate).
    #[inline(always)]
    pub fn at_clamped(&self, x: isize, y: isize) -> f32 {
        let xx = x.clamp(0, self.w as isize - 1) as usize;
        let yy = y.clamp(0, self.h as isize - 1) as usize;
        self.data[yy * self.w + xx]
    }
    pub fn len(&self) -> usize {
        self.data.len()
    }
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
    /// Elementwise `self - other`.
    pub fn sub(&self, other: &Plane) -> Plane {
        Plane { w: self.w, h: self.h, data: self.data.iter().zip(&other.data).map(|(a, b)| a - b).collect() }
    }
    pub fn map(&self, f: impl Fn(f32) -> f32) -> Plane {
        Plane { w: self.w, h: self.h, data: self.data.iter().map(|&v| f(v)).collect() }
    }

    /// Separable convolution with a symmetric 1-D kernel (odd length), edges replicated.
    pub fn convolve_sep(&self, kx: &[f32], ky: &[f32]) -> Plane {
        let (w, h) = (self.w, self.h);
        let mut tmp = vec![0.0f32; w * h];
        let rx = (kx.len() / 2) as isize;
        for y in 0..h {
            let row = &self.data[y * w..(y + 1) * w];
            for x in 0..w {
                let mut s = 0.0;
                for (i, &k) in kx.iter().enumerate() {
                    let xx = (x as isize + i as isize - rx).clamp(0, w as isize - 1) as usize;
                    s += k * row[xx];
                }
                tmp[y * w + x] = s;
            }
        }
        let ry = (ky.len() / 2) as isize;
        let mut out = vec![0.0f32; w * h];
        for y in 0..h {
            for (i, &k) in ky.iter().enumerate() {
                let yy = (y as isize + i as isize - ry).clamp(0, h as isize - 1) as usize;
                let src = &tmp[yy * w..(yy + 1) * w];
                let dst = &mut out[y * w..(y + 1) * w];
                for x in 0..w {
                    dst[x] += k * src[x];
                }
            }
        }
        Plane { w, h, data: out }
    }

    /// Gaussian blur of standard deviation `sigma` px (identity for `sigma <= 0`).
    pub fn gaussian(&self, sigma: f32) -> Plane {
        if sigma <= 0.0 {
            return self.clone();
        }
        let k = crate::faults::util::gaussian_kernel(sigma);
        self.convolve_sep(&k, &k)
    }

    /// Mean over a (2r+1)^2 box (edges handled by averaging only the pixels inside).
    pub fn box_mean(&self, r: usize) -> Plane {
        let (w, h) = (self.w, self.h);
        let mut ii = vec![0.0f64; (w + 1) * (h + 1)];
        for y in 0..h {
            let mut s = 0.0;
            for x in 0..w {
                s += self.data[y * w + x] as f64;
                ii[(y + 1) * (w + 1) + x + 1] = ii[y * (w + 1) + x + 1] + s;
            }
        }
        let mut out = Plane::new(w, h);
        for y in 0..h {
            let y0 = y.saturating_sub(r);
            let y1 = (y + r + 1).min(h);
            for x in 0..w {
                let x0 = x.saturating_sub(r);
                let x1 = (x + r + 1).min(w);
                let s = ii[y1 * (w + 1) + x1] - ii[y0 * (w + 1) + x1] - ii[y1 * (w + 1) + x0] + ii[y0 * (w + 1) + x0];
                out.data[y * w + x] = (s / ((x1 - x0) * (y1 - y0)) as f64) as f32;
            }
        }
        out
    }

    /// Max (or min with `max = false`) over a (2r+1)^2 square window, separable.
    pub fn extreme_filter(&self, r: usize, max: bool) -> Plane {
        let (w, h) = (self.w, self.h);
        let pick = |a: f32, b: f32| if max { a.max(b) } else { a.min(b) };
        let mut tmp = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut m = self.data[y * w + x];
                for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                    m = pick(m, self.data[y * w + xx]);
                }
                tmp[y * w + x] = m;
            }
        }
        let mut out = Plane::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let mut m = tmp[y * w + x];
                for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                    m = pick(m, tmp[yy * w + x]);
                }
                out.data[y * w + x] = m;
            }
        }
        out
    }

    /// Bilinear sample at a real position (edges replicated).
    #[inline]
    pub fn bilinear(&self, x: f32, y: f32) -> f32 {
        let x0 = x.floor();
        let y0 = y.floor();
        let fx = x - x0;
        let fy = y - y0;
        let (xi, yi) = (x0 as isize, y0 as isize);
        let a = self.at_clamped(xi, yi);
        let b = self.at_clamped(xi + 1, yi);
        let c = self.at_clamped(xi, yi + 1);
        let d = self.at_clamped(xi + 1, yi + 1);
        (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + d * fx) * fy
    }

    /// Content moved by (dx, dy) px (+dx right, +dy down), bilinear.
    pub fn shifted(&self, dx: f32, dy: f32) -> Plane {
        let mut out = Plane::new(self.w, self.h);
        for y in 0..self.h {
            for x in 0..self.w {
                out.data[y * self.w + x] = self.bilinear(x as f32 - dx, y as f32 - dy);
            }
        }
        out
    }

    /// Block-mean downsampling by an integer factor (partial blocks at the edge are dropped).
    pub fn downsample(&self, f: usize) -> Plane {
        let f = f.max(1);
        let (w, h) = ((self.w / f).max(1), (self.h / f).max(1));
        let mut out = Plane::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let mut s = 0.0;
                let mut n = 0.0;
                for yy in y * f..((y + 1) * f).min(self.h) {
                    for xx in x * f..((x + 1) * f).min(self.w) {
                        s += self.at(xx, yy);
                        n += 1.0;
                    }
                }
                out.data[y * w + x] = s / n;
            }
        }
        out
    }
}

/// Approximate Euclidean distance (px) from every pixel to the nearest `true` pixel of `mask`
/// (two-pass chamfer 3-4, divided by 3). `f32::INFINITY` everywhere when the mask is empty.
pub fn distance_transform(mask: &[bool], w: usize, h: usize) -> Vec<f32> {
    let big = 1e9f32;
    let mut d: Vec<f32> = mask.iter().map(|&m| if m { 0.0 } else { big }).collect();
    if !mask.iter().any(|&m| m) {
        return vec![f32::INFINITY; w * h];
    }
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let mut v = d[i];
            if x > 0 {
                v = v.min(d[i - 1] + 3.0);
            }
            if y > 0 {
                v = v.min(d[i - w] + 3.0);
                if x > 0 {
                    v = v.min(d[i - w - 1] + 4.0);
                }
                if x + 1 < w {
                    v = v.min(d[i - w + 1] + 4.0);
                }
            }
            d[i] = v;
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let i = y * w + x;
            let mut v = d[i];
            if x + 1 < w {
                v = v.min(d[i + 1] + 3.0);
            }
            if y + 1 < h {
                v = v.min(d[i + w] + 3.0);
                if x + 1 < w {
                    v = v.min(d[i + w + 1] + 4.0);
                }
                if x > 0 {
                    v = v.min(d[i + w - 1] + 4.0);
                }
            }
            d[i] = v;
        }
    }
    d.iter_mut().for_each(|v| *v /= 3.0);
    d
}

/// Channels of a frame as planes in 8-bit DN.
pub fn planes_of(frame: &Frame) -> Vec<Plane> {
    let (w, h, c) = (frame.width as usize, frame.height as usize, frame.channels());
    let scale = 255.0 / frame.full_scale();
    let mut out: Vec<Plane> = (0..c).map(|_| Plane { w, h, data: Vec::with_capacity(w * h) }).collect();
    // One pass per row and channel, the sample type matched once (this runs on every forward-
    // model evaluation of `diagnose`).
    fn rows<T: Copy>(d: &[T], stride: usize, w: usize, h: usize, out: &mut [Plane], f: impl Fn(T) -> f32) {
        let c = out.len();
        for y in 0..h {
            let row = &d[y * stride..y * stride + w * c];
            if c == 1 {
                out[0].data.extend(row.iter().map(|&v| f(v)));
            } else {
                for (ch, p) in out.iter_mut().enumerate() {
                    p.data.extend(row[ch..].iter().step_by(c).map(|&v| f(v)));
                }
            }
        }
    }
    match &frame.data {
        FrameData::U8(d) => rows(d, frame.stride, w, h, &mut out, |v| v as f32 * scale),
        FrameData::U16(d) => rows(d, frame.stride, w, h, &mut out, |v| v as f32 * scale),
    }
    out
}

/// Luma (BT.601 for three channels, the plane itself for one).
pub fn luma(planes: &[Plane]) -> Plane {
    if planes.len() == 3 {
        let (r, g, b) = (&planes[0], &planes[1], &planes[2]);
        Plane {
            w: r.w,
            h: r.h,
            data: (0..r.data.len()).map(|i| 0.299 * r.data[i] + 0.587 * g.data[i] + 0.114 * b.data[i]).collect(),
        }
    } else {
        planes[0].clone()
    }
}

/// A frame of the same format as `like` from planes in 8-bit DN (rounded, clipped).
pub fn frame_from_planes(planes: &[Plane], like: &Frame) -> Frame {
    let (w, h) = (planes[0].w, planes[0].h);
    let c = planes.len();
    let mut f = Frame::new(w as u32, h as u32, like.format).unwrap_or_else(|_| like.clone());
    let scale = like.full_scale() / 255.0;
    for y in 0..h {
        for x in 0..w {
            for (ch, p) in planes.iter().enumerate().take(c) {
                f.set(x, y, ch, p.data[y * w + x] * scale);
            }
        }
    }
    f
}

/// One sim/real pair.
#[derive(Debug, Clone)]
pub struct Pair {
    /// File name (the pairing key).
    pub name: String,
    pub sim_frame: Frame,
    pub real_frame: Frame,
    /// Channels in 8-bit DN.
    pub sim: Vec<Plane>,
    pub real: Vec<Plane>,
}

impl Pair {
    pub fn w(&self) -> usize {
        self.sim[0].w
    }
    pub fn h(&self) -> usize {
        self.sim[0].h
    }
    pub fn channels(&self) -> usize {
        self.sim.len()
    }
}

const IMAGE_EXT: &[&str] = &["png", "jpg", "jpeg", "tif", "tiff", "pgm", "ppm", "pnm", "pbm", "pam"];

/// Image files of a folder, sorted by name.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>, DiagnoseError> {
    let rd = std::fs::read_dir(dir).map_err(|source| DiagnoseError::Io { path: dir.to_path_buf(), source })?;
    let mut out = Vec::new();
    for e in rd {
        let e = e.map_err(|source| DiagnoseError::Io { path: dir.to_path_buf(), source })?;
        let p = e.path();
        let ok = p
            .extension()
            .and_then(|x| x.to_str())
            .map(|x| IMAGE_EXT.contains(&x.to_ascii_lowercase().as_str()))
            .unwrap_or(false);
        if ok && p.is_file() {
            out.push(p);
        }
    }
    out.sort();
    Ok(out)
}

/// Decode an image file into a frame (Mono8, Mono16 or Rgb8).
pub fn load_image(path: &Path) -> Result<Frame, DiagnoseError> {
    let img = crate::limits::load_image(path, &crate::limits::ImageLimits::current())
        .map_err(|message| DiagnoseError::Decode { path: path.to_path_buf(), message })?;
    let (w, h) = (img.width(), img.height());
    let bad = |what: &str| DiagnoseError::Decode { path: path.to_path_buf(), message: what.to_string() };
    use image::DynamicImage as D;
    let frame = match img {
        D::ImageLuma8(b) => Frame::from_data(w, h, w as usize, PixelFormat::Mono8, FrameData::U8(b.into_raw())),
        D::ImageLumaA8(_) => {
            let b = img.to_luma8();
            Frame::from_data(w, h, w as usize, PixelFormat::Mono8, FrameData::U8(b.into_raw()))
        }
        D::ImageLuma16(b) => Frame::from_data(w, h, w as usize, PixelFormat::Mono16, FrameData::U16(b.into_raw())),
        D::ImageLumaA16(_) => {
            let b = img.to_luma16();
            Frame::from_data(w, h, w as usize, PixelFormat::Mono16, FrameData::U16(b.into_raw()))
        }
        D::ImageRgb8(b) => Frame::from_data(w, h, 3 * w as usize, PixelFormat::Rgb8, FrameData::U8(b.into_raw())),
        D::ImageRgba8(_) => {
            let b = img.to_rgb8();
            Frame::from_data(w, h, 3 * w as usize, PixelFormat::Rgb8, FrameData::U8(b.into_raw()))
        }
        D::ImageRgb16(_) | D::ImageRgba16(_) => {
            // faultcam has no 16-bit colour format: analyse 16-bit colour as 8-bit colour.
            let b = img.to_rgb8();
            Frame::from_data(w, h, 3 * w as usize, PixelFormat::Rgb8, FrameData::U8(b.into_raw()))
        }
        _ => return Err(bad("unsupported pixel type (expected 8/16-bit grey or 8-bit RGB)")),
    };
    frame.map_err(|e| bad(&e.to_string()))
}

/// Quantisation step (8-bit DN) of a frame's samples: 1 for 8-bit formats; for 16-bit data the
/// step of the ADC behind it, found from the samples: b-bit codes stored in 16 bits by bit
/// replication (`code << (16 − b) | code >> (2b − 16)`, the usual PNG scaling, step
/// FS/(2^b − 1)) or by a plain shift (`code << (16 − b)`, step 2^(16 − b)/257), for b = 8..15;
/// otherwise 1/257 (true 16-bit data).
pub fn code_step(frame: &Frame) -> f64 {
    let FrameData::U16(d) = &frame.data else { return 1.0 };
    for b in 8u32..16 {
        let rep = |v: u16| -> bool {
            let code = (v as u32) >> (16 - b);
            ((code << (16 - b)) | (code >> (2 * b - 16))) == v as u32
        };
        if d.iter().all(|&v| rep(v)) {
            return FS as f64 / ((1u32 << b) - 1) as f64;
        }
        let mask = (1u32 << (16 - b)) - 1;
        if d.iter().all(|&v| (v as u32) & mask == 0) {
            return (1u32 << (16 - b)) as f64 / 257.0;
        }
    }
    1.0 / 257.0
}

/// Pair the images of two folders by file name (the stem decides, so `a.png` pairs with `a.tif`).
/// Returns the pairs and notes about unpaired files.
pub fn load_pairs(sim_dir: &Path, real_dir: &Path) -> Result<(Vec<Pair>, Vec<String>), DiagnoseError> {
    let sims = list_images(sim_dir)?;
    let reals = list_images(real_dir)?;
    let stem = |p: &Path| p.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
    let mut notes = Vec::new();
    let mut pairs = Vec::new();
    for s in &sims {
        let st = stem(s);
        let exact = reals.iter().find(|r| r.file_name() == s.file_name());
        let r = exact.or_else(|| reals.iter().find(|r| stem(r) == st));
        let Some(r) = r else {
            notes.push(format!("{}: no real image with this name in {}", s.display(), real_dir.display()));
            continue;
        };
        let sf = load_image(s)?;
        let rf = load_image(r)?;
        if sf.width != rf.width || sf.height != rf.height || sf.channels() != rf.channels() {
            return Err(DiagnoseError::SizeMismatch {
                name: s.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default(),
                sim: format!("{}x{} {}", sf.width, sf.height, sf.format),
                real: format!("{}x{} {}", rf.width, rf.height, rf.format),
                real_path: r.clone(),
            });
        }
        if sf.format != rf.format {
            notes
                .push(format!("{}: sim is {} and real is {}; both are analysed in 8-bit DN", st, sf.format, rf.format));
        }
        let sim = planes_of(&sf);
        let real = planes_of(&rf);
        pairs.push(Pair {
            name: s.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default(),
            sim_frame: sf,
            real_frame: rf,
            sim,
            real,
        });
    }
    for r in &reals {
        if !sims.iter().any(|s| stem(s) == stem(r)) {
            notes.push(format!("{}: no sim image with this name in {}", r.display(), sim_dir.display()));
        }
    }
    if pairs.is_empty() {
        return Err(DiagnoseError::NoPairs { sim: sim_dir.to_path_buf(), real: real_dir.to_path_buf() });
    }
    Ok((pairs, notes))
}

/// Load every image of a folder (unpaired mode).
pub fn load_folder(dir: &Path) -> Result<Vec<(String, Frame)>, DiagnoseError> {
    let files = list_images(dir)?;
    if files.is_empty() {
        return Err(DiagnoseError::NoImages { dir: dir.to_path_buf() });
    }
    files
        .iter()
        .map(|p| Ok((p.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default(), load_image(p)?)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 10- and 12-bit data in 16-bit PNG (bit replication) are read as code·FS/(2^b − 1) DN with
    /// that quantisation step; plain 16-bit data keep the step 1/257; 8-bit data 1.
    #[test]
    fn sixteen_bit_pngs_are_read_at_their_adc_depth() {
        let dir = tempfile::tempdir().unwrap();
        for bits in [10u32, 12] {
            let l = (1u32 << bits) - 1;
            let codes: Vec<u32> = (0..64 * 16).map(|i| (i as u32 * 37) % (l + 1)).collect();
            let data: Vec<u16> = codes.iter().map(|&c| ((c << (16 - bits)) | (c >> (2 * bits - 16))) as u16).collect();
            let path = dir.path().join(format!("b{bits}.png"));
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(64, 16, data).unwrap().save(&path).unwrap();
            let f = load_image(&path).unwrap();
            assert_eq!(f.format, PixelFormat::Mono16);
            let step = code_step(&f);
            assert!((step - 255.0 / l as f64).abs() < 1e-12, "{bits} bits: step {step}");
            let p = &planes_of(&f)[0];
            for (v, &c) in p.data.iter().zip(&codes) {
                assert!((*v as f64 - c as f64 * step).abs() < 0.02, "{bits} bits: code {c} read as {v}");
            }
        }
        let full: Vec<u16> = (0..1024u32).map(|i| (i.wrapping_mul(2654435761) >> 16) as u16).collect();
        let f = Frame::from_data(64, 16, 64, PixelFormat::Mono16, FrameData::U16(full)).unwrap();
        assert!((code_step(&f) - 1.0 / 257.0).abs() < 1e-12);
        let f8 = Frame::from_data(4, 1, 4, PixelFormat::Mono8, FrameData::U8(vec![1, 2, 3, 4])).unwrap();
        assert_eq!(code_step(&f8), 1.0);
    }

    /// Every sample of a padded (stride > width · channels) RGB frame and a 16-bit mono frame
    /// lands in its channel's plane at its place, scaled to 8-bit DN.
    #[test]
    fn planes_of_reads_each_channel_at_its_place() {
        let (w, h, stride) = (5usize, 3usize, 17usize);
        let data: Vec<u8> = (0..stride * h).map(|i| (i * 7 % 256) as u8).collect();
        let f = Frame::from_data(w as u32, h as u32, stride, PixelFormat::Rgb8, FrameData::U8(data.clone())).unwrap();
        let p = planes_of(&f);
        assert_eq!(p.len(), 3);
        for (c, plane) in p.iter().enumerate() {
            assert_eq!((plane.w, plane.h, plane.data.len()), (w, h, w * h));
            for y in 0..h {
                for x in 0..w {
                    assert_eq!(plane.data[y * w + x], data[y * stride + x * 3 + c] as f32, "c {c} x {x} y {y}");
                }
            }
        }
        let d16: Vec<u16> = (0..(w + 2) * h).map(|i| (i * 4099 % 65536) as u16).collect();
        let f = Frame::from_data(w as u32, h as u32, w + 2, PixelFormat::Mono16, FrameData::U16(d16.clone())).unwrap();
        let p = planes_of(&f);
        for y in 0..h {
            for x in 0..w {
                assert_eq!(p[0].data[y * w + x], d16[y * (w + 2) + x] as f32 * (255.0 / 65535.0));
            }
        }
    }

    #[test]
    fn distance_transform_is_close_to_euclidean() {
        let (w, h) = (41, 41);
        let mut m = vec![false; w * h];
        m[20 * w + 20] = true;
        let d = distance_transform(&m, w, h);
        assert_eq!(d[20 * w + 20], 0.0);
        assert!((d[20 * w + 30] - 10.0).abs() < 0.01);
        // diagonal: 10*sqrt(2) = 14.14; chamfer 3-4 gives 13.33
        assert!((d[30 * w + 30] - 14.14).abs() < 1.0);
    }

    #[test]
    fn blur_keeps_the_mean_and_shift_moves_content() {
        let mut p = Plane::new(32, 32);
        p.data[16 * 32 + 16] = 100.0;
        let b = p.gaussian(1.5);
        let s: f32 = b.data.iter().sum();
        assert!((s - 100.0).abs() < 0.01);
        let sh = p.shifted(2.0, 1.0);
        assert_eq!(sh.at(18, 17), 100.0);
        let bm = Plane::filled(9, 7, 3.0).box_mean(2);
        assert!(bm.data.iter().all(|&v| (v - 3.0).abs() < 1e-6));
        let mx = p.extreme_filter(1, true);
        assert_eq!(mx.at(15, 17), 100.0);
        assert_eq!(mx.at(14, 16), 0.0);
    }
}
