//! Line plots of sweep curves drawn straight into PNG with the `image` crate: per effect the
//! failure rate and the median / p95 score against the level (level 0 = the clean baseline),
//! and one plot of every effect's failure rate.

use super::report::{Curve, Report};
use crate::eval::plot::{text, text_width};
use image::{Rgb, RgbImage};
use std::path::Path;

const COLOURS: [[u8; 3]; 8] = [
    [0, 114, 178],
    [213, 94, 0],
    [0, 158, 115],
    [204, 121, 167],
    [230, 159, 0],
    [86, 180, 233],
    [0, 0, 0],
    [240, 228, 66],
];

struct Series {
    label: String,
    colour: [u8; 3],
    /// y per x = 0..n (None = no value).
    ys: Vec<Option<f64>>,
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, Rgb(c));
    }
}

fn line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), c: [u8; 3], thick: i64) {
    let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as i64).max(1);
    for i in 0..=n {
        let t = i as f64 / n as f64;
        let (x, y) = (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1));
        for d in 0..thick * thick {
            put(img, x.round() as i64 + d % thick - thick / 2, y.round() as i64 + d / thick - thick / 2, c);
        }
    }
}

fn tick(v: f64) -> String {
    if v == v.round() { format!("{v:.0}") } else { format!("{v:.2}") }
}

/// A plot with x = 0..=n levels and y over [0, y_max].
fn plot(path: &Path, title: &str, y_label: &str, n: usize, y_max: f64, series: &[Series]) -> Result<(), String> {
    let (w, h) = (640u32, 400u32);
    let (l, r, t, b) = (56.0, 170.0, 28.0, 40.0);
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let n = n.max(1);
    let px = |x: f64| l + x / n as f64 * (w as f64 - l - r);
    let py = |y: f64| h as f64 - b - y.min(y_max) / y_max * (h as f64 - t - b);
    let (grey, black) = ([210, 210, 210], [0, 0, 0]);
    for i in 0..=4 {
        let y = y_max * i as f64 / 4.0;
        line(&mut img, (l, py(y)), (w as f64 - r, py(y)), grey, 1);
        let s = tick(y);
        text(&mut img, (l as u32).saturating_sub(text_width(&s) + 4), py(y) as u32 - 3, &s, black);
    }
    for x in 0..=n {
        line(&mut img, (px(x as f64), t), (px(x as f64), h as f64 - b), grey, 1);
        let s = x.to_string();
        text(&mut img, px(x as f64) as u32 - text_width(&s) / 2, h - b as u32 + 6, &s, black);
    }
    line(&mut img, (l, t), (l, h as f64 - b), black, 1);
    line(&mut img, (l, h as f64 - b), (w as f64 - r, h as f64 - b), black, 1);
    text(&mut img, 8, 8, title, black);
    text(&mut img, (w - r as u32) / 2, h - 14, "LEVEL (0 = BASELINE)", black);
    text(&mut img, 8, 18, y_label, [90, 90, 90]);
    for (si, s) in series.iter().enumerate() {
        let mut prev: Option<(f64, f64)> = None;
        for (x, y) in s.ys.iter().enumerate() {
            match y {
                Some(y) if y.is_finite() => {
                    let q = (px(x as f64), py(*y));
                    line(&mut img, prev.unwrap_or(q), q, s.colour, 2);
                    line(&mut img, q, q, s.colour, 5);
                    prev = Some(q);
                }
                _ => prev = None,
            }
        }
        let ly = t as u32 + 12 * si as u32;
        line(&mut img, (w as f64 - r + 8.0, ly as f64 + 3.0), (w as f64 - r + 22.0, ly as f64 + 3.0), s.colour, 3);
        let mut label = s.label.clone();
        label.truncate(22);
        text(&mut img, w - r as u32 + 26, ly, &label, black);
    }
    img.save(path).map_err(|e| format!("cannot write {}: {e}", path.display()))
}

fn with_baseline(base: Option<f64>, c: &Curve, get: impl Fn(&super::report::Stats) -> Option<f64>) -> Vec<Option<f64>> {
    std::iter::once(base).chain(c.levels.iter().map(get)).collect()
}

/// `plots/<name>.png` per effect and pair, and `plots/failure_rate.png`.
pub fn write_plots(dir: &Path, r: &Report) -> Result<(), String> {
    let b = &r.baseline;
    for c in r.effects.iter().chain(&r.pairs) {
        let series = vec![
            Series {
                label: "failure rate".into(),
                colour: COLOURS[1],
                ys: with_baseline(b.failure_rate, c, |s| s.failure_rate),
            },
            Series {
                label: "median score".into(),
                colour: COLOURS[0],
                ys: with_baseline(b.median_score, c, |s| s.median_score),
            },
            Series {
                label: "p95 score".into(),
                colour: COLOURS[5],
                ys: with_baseline(b.p95_score, c, |s| s.p95_score),
            },
        ];
        let top = series.iter().flat_map(|s| s.ys.iter().flatten()).fold(1.0f64, |m, v| m.max(*v));
        let title = format!("{} ({} per level)", c.name, c.param);
        plot(
            &dir.join(format!("{}.png", c.name)),
            &title,
            "RATE / SCORE (CAPPED AT 2)",
            c.values.len(),
            top.min(2.0),
            &series,
        )?;
    }
    let series: Vec<Series> = r
        .effects
        .iter()
        .enumerate()
        .map(|(i, c)| Series {
            label: c.name.clone(),
            colour: COLOURS[i % COLOURS.len()],
            ys: with_baseline(b.failure_rate, c, |s| s.failure_rate),
        })
        .collect();
    let n = r.effects.iter().map(|c| c.values.len()).max().unwrap_or(1);
    plot(&dir.join("failure_rate.png"), "failure rate per effect", "FAILURE RATE", n, 1.0, &series)
}
