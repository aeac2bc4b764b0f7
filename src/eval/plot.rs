//! Minimal bar plots drawn straight into an RGB image (no plotting dependency): histograms of
//! score distributions and of grey levels, with a title, axis ticks and an optional threshold
//! line. Text uses a built-in 5x7 pixel font.

use super::EvalError;
use image::{Rgb, RgbImage};
use std::path::Path;

/// One series of a bar plot: a value per bin.
pub struct Series<'a> {
    pub label: &'a str,
    pub colour: [u8; 3],
    pub values: &'a [f64],
}

/// A histogram-style plot over `x_range` with equal-width bins.
pub struct BarPlot<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub x_range: (f64, f64),
    pub series: Vec<Series<'a>>,
    /// Vertical dashed line at this x (e.g. an acceptance threshold).
    pub marker: Option<f64>,
}

/// Counts of `values` in `bins` equal bins over `[lo, hi]` (values outside are clamped into the
/// end bins; non-finite values are ignored).
pub fn bin_counts(values: &[f64], bins: usize, lo: f64, hi: f64) -> Vec<f64> {
    let mut c = vec![0.0; bins.max(1)];
    let n = c.len();
    for &v in values.iter().filter(|v| v.is_finite()) {
        let k = (((v - lo) / (hi - lo)) * n as f64).floor();
        c[(k.max(0.0) as usize).min(n - 1)] += 1.0;
    }
    c
}

const W: u32 = 720;
const H: u32 = 400;
const LEFT: u32 = 60;
const RIGHT: u32 = 20;
const TOP: u32 = 40;
const BOTTOM: u32 = 50;

impl BarPlot<'_> {
    /// Render to an image. Series are drawn side by side within each bin.
    pub fn render(&self) -> RgbImage {
        let mut img = RgbImage::from_pixel(W, H, Rgb([255, 255, 255]));
        let (pw, ph) = (W - LEFT - RIGHT, H - TOP - BOTTOM);
        let bins = self.series.iter().map(|s| s.values.len()).max().unwrap_or(1).max(1);
        let ymax = self.series.iter().flat_map(|s| s.values.iter().copied()).fold(0.0f64, f64::max);
        let ymax = if ymax > 0.0 { ymax } else { 1.0 };
        // Axes.
        fill(&mut img, LEFT, TOP + ph, pw, 1, [0, 0, 0]);
        fill(&mut img, LEFT - 1, TOP, 1, ph + 1, [0, 0, 0]);
        let ns = self.series.len().max(1) as u32;
        let bin_w = pw as f64 / bins as f64;
        for (si, s) in self.series.iter().enumerate() {
            for (b, &v) in s.values.iter().enumerate() {
                let bh = ((v / ymax) * ph as f64).round() as u32;
                let x0 = LEFT as f64 + b as f64 * bin_w + si as f64 * bin_w / ns as f64;
                let bw = (bin_w / ns as f64).max(1.0);
                let (x0u, bwu) = (x0.floor() as u32, (bw.floor() as u32).max(1));
                let gap = u32::from(bwu > 3);
                fill(&mut img, x0u, TOP + ph - bh, bwu - gap, bh, s.colour);
            }
        }
        // Threshold marker.
        let (lo, hi) = self.x_range;
        if let Some(m) = self.marker
            && m >= lo
            && m <= hi
        {
            let x = LEFT + (((m - lo) / (hi - lo)) * pw as f64).round() as u32;
            let mut y = TOP;
            while y < TOP + ph {
                fill(&mut img, x.min(W - 1), y, 1, 4, [200, 0, 0]);
                y += 8;
            }
        }
        // X ticks: 5 intervals.
        for i in 0..=4u32 {
            let xv = lo + (hi - lo) * i as f64 / 4.0;
            let x = LEFT + pw * i / 4;
            fill(&mut img, x, TOP + ph, 1, 5, [0, 0, 0]);
            let t = tick(xv);
            text(&mut img, x.saturating_sub(text_width(&t) / 2), TOP + ph + 9, &t, [0, 0, 0]);
        }
        // Y ticks: 0 and max.
        text(&mut img, 4, TOP + ph - 3, "0", [0, 0, 0]);
        text(&mut img, 4, TOP - 3, &tick(ymax), [0, 0, 0]);
        fill(&mut img, LEFT - 5, TOP, 5, 1, [0, 0, 0]);
        text(&mut img, LEFT, 12, self.title, [0, 0, 0]);
        text(&mut img, LEFT + pw / 2 - text_width(self.x_label) / 2, H - 16, self.x_label, [0, 0, 0]);
        // Legend.
        let mut lx = LEFT + pw;
        for s in self.series.iter().rev() {
            lx = lx.saturating_sub(text_width(s.label) + 22);
            fill(&mut img, lx, 26, 10, 7, s.colour);
            text(&mut img, lx + 14, 26, s.label, [0, 0, 0]);
        }
        img
    }

    /// Render and save as PNG.
    pub fn save(&self, path: &Path) -> Result<(), EvalError> {
        self.render().save(path).map_err(|e| EvalError::Image { path: path.to_path_buf(), message: e.to_string() })
    }
}

fn tick(v: f64) -> String {
    if v == v.round() && v.abs() < 1e6 { format!("{v:.0}") } else { format!("{v:.2}") }
}

fn fill(img: &mut RgbImage, x0: u32, y0: u32, w: u32, h: u32, c: [u8; 3]) {
    for y in y0..(y0 + h).min(img.height()) {
        for x in x0..(x0 + w).min(img.width()) {
            img.put_pixel(x, y, Rgb(c));
        }
    }
}

/// Pixel width of `s` in the built-in font (6 px per character).
pub fn text_width(s: &str) -> u32 {
    s.chars().count() as u32 * 6
}

/// Draw `s` with the 5x7 font, top-left at (x, y). Unknown characters draw as blanks;
/// lower-case letters draw as capitals.
pub fn text(img: &mut RgbImage, x: u32, y: u32, s: &str, c: [u8; 3]) {
    for (i, ch) in s.chars().enumerate() {
        let g = glyph(ch.to_ascii_uppercase());
        for (row, bits) in g.iter().enumerate() {
            for col in 0..5u32 {
                if bits & (0x10 >> col) != 0 {
                    let (px, py) = (x + i as u32 * 6 + col, y + row as u32);
                    if px < img.width() && py < img.height() {
                        img.put_pixel(px, py, Rgb(c));
                    }
                }
            }
        }
    }
}

/// 5x7 glyphs, one byte per row, bit 4 = leftmost column.
fn glyph(c: char) -> [u8; 7] {
    match c {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '.' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C],
        ',' => [0x00, 0x00, 0x00, 0x00, 0x0C, 0x04, 0x08],
        ':' => [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00],
        '-' => [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00],
        '+' => [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00],
        '=' => [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00],
        '/' => [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00],
        '%' => [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '>' => [0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08],
        '<' => [0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02],
        '_' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1F],
        _ => [0; 7],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bins_clamp_and_count() {
        let c = bin_counts(&[0.0, 0.05, 0.5, 0.99, 1.0, 2.0, -1.0, f64::NAN], 10, 0.0, 1.0);
        assert_eq!(c, vec![3.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 3.0]);
    }

    #[test]
    fn bars_have_the_series_colour_and_height() {
        let v = [1.0, 0.0, 2.0, 0.0];
        let p = BarPlot {
            title: "t",
            x_label: "x",
            x_range: (0.0, 1.0),
            series: vec![Series { label: "a", colour: [0, 0, 255], values: &v }],
            marker: Some(0.5),
        };
        let img = p.render();
        let (pw, ph) = (W - LEFT - RIGHT, H - TOP - BOTTOM);
        let col = |b: u32| LEFT + pw * b / 4 + pw / 8;
        // Bin 2 (value 2 = max) fills the full plot height; bin 0 half of it; bin 1 is empty.
        assert_eq!(img.get_pixel(col(2), TOP + 1).0, [0, 0, 255]);
        assert_eq!(img.get_pixel(col(0), TOP + ph / 2 + 2).0, [0, 0, 255]);
        assert_eq!(img.get_pixel(col(0), TOP + ph / 2 - 2).0, [255, 255, 255]);
        assert_eq!(img.get_pixel(col(1), TOP + ph - 2).0, [255, 255, 255]);
    }
}
