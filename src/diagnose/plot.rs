//! Minimal PNG plots drawn with the `image` crate: line plots with axes and numeric tick labels
//! (a built-in 3x5 digit font), and diverging residual maps.

use super::img::Plane;
use super::types::Profile;
use image::{Rgb, RgbImage};
use std::path::Path;

/// Series colours (colour-blind friendly Okabe–Ito).
pub const COLOURS: [[u8; 3]; 6] =
    [[0, 114, 178], [213, 94, 0], [0, 158, 115], [204, 121, 167], [230, 159, 0], [86, 180, 233]];

pub fn colour_name(i: usize) -> &'static str {
    ["blue", "vermillion", "green", "pink", "orange", "sky blue"][i % 6]
}

/// 3x5 glyphs for digits, '.', '-', 'e', '+'.
fn glyph(c: char) -> Option<[u8; 5]> {
    Some(match c {
        '0' => [0b111, 0b101, 0b101, 0b101, 0b111],
        '1' => [0b010, 0b110, 0b010, 0b010, 0b111],
        '2' => [0b111, 0b001, 0b111, 0b100, 0b111],
        '3' => [0b111, 0b001, 0b111, 0b001, 0b111],
        '4' => [0b101, 0b101, 0b111, 0b001, 0b001],
        '5' => [0b111, 0b100, 0b111, 0b001, 0b111],
        '6' => [0b111, 0b100, 0b111, 0b101, 0b111],
        '7' => [0b111, 0b001, 0b010, 0b010, 0b010],
        '8' => [0b111, 0b101, 0b111, 0b101, 0b111],
        '9' => [0b111, 0b101, 0b111, 0b001, 0b111],
        '.' => [0b000, 0b000, 0b000, 0b000, 0b010],
        '-' => [0b000, 0b000, 0b111, 0b000, 0b000],
        '+' => [0b000, 0b010, 0b111, 0b010, 0b000],
        'e' => [0b000, 0b111, 0b111, 0b100, 0b111],
        _ => return None,
    })
}

fn text(img: &mut RgbImage, x: i32, y: i32, s: &str, scale: i32, col: [u8; 3]) {
    let mut cx = x;
    for ch in s.chars() {
        if let Some(g) = glyph(ch) {
            for (row, bits) in g.iter().enumerate() {
                for bit in 0..3 {
                    if bits & (0b100 >> bit) != 0 {
                        for dy in 0..scale {
                            for dx in 0..scale {
                                put(img, cx + bit * scale + dx, y + row as i32 * scale + dy, col);
                            }
                        }
                    }
                }
            }
        }
        cx += 4 * scale;
    }
}

#[inline]
fn put(img: &mut RgbImage, x: i32, y: i32, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, Rgb(c));
    }
}

fn line(img: &mut RgbImage, x0: f64, y0: f64, x1: f64, y1: f64, c: [u8; 3], thick: i32) {
    let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as i32).max(1);
    for i in 0..=n {
        let t = i as f64 / n as f64;
        let (x, y) = (x0 + t * (x1 - x0), y0 + t * (y1 - y0));
        for dx in 0..thick {
            for dy in 0..thick {
                put(img, x.round() as i32 + dx - thick / 2, y.round() as i32 + dy - thick / 2, c);
            }
        }
    }
}

/// Short tick label.
fn fmt_tick(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.1e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else if a >= 1.0 {
        format!("{v:.2}").trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{v:.3}").trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

/// Line plot of a profile into a PNG (640x400).
pub fn line_plot(p: &Profile, path: &Path) -> Result<(), image::ImageError> {
    let (w, h) = (640u32, 400u32);
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let (l, r, t, b) = (70.0, 20.0, 20.0, 40.0);
    let xs: Vec<f64> = p.x.iter().copied().filter(|v| v.is_finite()).collect();
    let ys: Vec<f64> = p.series.iter().flat_map(|s| s.1.iter().copied()).filter(|v| v.is_finite()).collect();
    if xs.is_empty() || ys.is_empty() {
        return img.save(path);
    }
    let (mut x0, mut x1) =
        (xs.iter().copied().fold(f64::INFINITY, f64::min), xs.iter().copied().fold(f64::NEG_INFINITY, f64::max));
    let (mut y0, mut y1) =
        (ys.iter().copied().fold(f64::INFINITY, f64::min), ys.iter().copied().fold(f64::NEG_INFINITY, f64::max));
    if x1 <= x0 {
        x1 = x0 + 1.0;
        x0 -= 1.0;
    }
    if y1 <= y0 {
        y1 = y0 + 1.0;
        y0 -= 1.0;
    }
    let pad = 0.05 * (y1 - y0);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let px = |x: f64| l + (x - x0) / (x1 - x0) * (w as f64 - l - r);
    let py = |y: f64| h as f64 - b - (y - y0) / (y1 - y0) * (h as f64 - t - b);
    let grey = [200, 200, 200];
    let black = [0, 0, 0];
    for i in 0..=4 {
        let fy = y0 + (y1 - y0) * i as f64 / 4.0;
        line(&mut img, l, py(fy), w as f64 - r, py(fy), grey, 1);
        let s = fmt_tick(fy);
        text(&mut img, 4, py(fy) as i32 - 5, &s, 2, black);
        let fx = x0 + (x1 - x0) * i as f64 / 4.0;
        line(&mut img, px(fx), t, px(fx), h as f64 - b, grey, 1);
        let s = fmt_tick(fx);
        text(&mut img, px(fx) as i32 - (s.len() as i32 * 4), h as i32 - b as i32 + 8, &s, 2, black);
    }
    if y0 < 0.0 && y1 > 0.0 {
        line(&mut img, l, py(0.0), w as f64 - r, py(0.0), [120, 120, 120], 1);
    }
    line(&mut img, l, t, l, h as f64 - b, black, 1);
    line(&mut img, l, h as f64 - b, w as f64 - r, h as f64 - b, black, 1);
    for (si, (_, vals)) in p.series.iter().enumerate() {
        let c = COLOURS[si % COLOURS.len()];
        let mut prev: Option<(f64, f64)> = None;
        for (x, y) in p.x.iter().zip(vals) {
            if !x.is_finite() || !y.is_finite() {
                prev = None;
                continue;
            }
            let q = (px(*x), py(*y));
            if let Some(pp) = prev {
                line(&mut img, pp.0, pp.1, q.0, q.1, c, 2);
            } else {
                line(&mut img, q.0, q.1, q.0, q.1, c, 3);
            }
            prev = Some(q);
        }
    }
    img.save(path)
}

/// Diverging colour map of a residual plane: blue negative, white zero, red positive, saturating
/// at ±`scale` DN.
pub fn residual_map(p: &Plane, scale: f32, path: &Path) -> Result<(), image::ImageError> {
    let mut img = RgbImage::new(p.w as u32, p.h as u32);
    for y in 0..p.h {
        for x in 0..p.w {
            let v = (p.at(x, y) / scale.max(1e-6)).clamp(-1.0, 1.0);
            let c = if v >= 0.0 {
                let t = v;
                [255, (255.0 * (1.0 - t)) as u8, (255.0 * (1.0 - t)) as u8]
            } else {
                let t = -v;
                [(255.0 * (1.0 - t)) as u8, (255.0 * (1.0 - t)) as u8, 255]
            };
            img.put_pixel(x as u32, y as u32, Rgb(c));
        }
    }
    img.save(path)
}
