//! Inputs for the evaluation tests, generated in temporary folders (no reference data needed).

#![allow(dead_code)]

use faultcam::rng::Rng;
use faultcam::sink::{Sink, files::FilesSink};
use faultcam::source::Source;
use faultcam::source::synth::SynthSource;
use std::path::Path;

/// Write `n` synthetic spacecraft frames (`synth:`, saturated glints) as `gen_NNN.png`.
pub fn write_synth(dir: &Path, n: usize, w: u32, h: u32) {
    let uri = format!("synth:?width={w}&height={h}&frames={n}&spin_dps=25&distance_m=14&fps=1");
    let mut src = SynthSource::open(&uri).unwrap();
    let mut sink = FilesSink::open(&format!("files:{}", dir.display())).unwrap();
    let mut i = 0;
    while let Some(f) = src.next_frame().unwrap() {
        sink.write_frame(&f, Some(&format!("gen_{i:03}.png"))).unwrap();
        i += 1;
    }
}

/// A "real" sunlamp-like frame: hazy noisy background, textured rectangles (corners for ORB), and
/// a saturated elliptical blob with a Gaussian glow around it.
pub fn sunlamp_like(w: usize, h: usize, seed: u64) -> Vec<u8> {
    let mut rng = Rng::new(seed);
    let mut d: Vec<f64> = (0..w * h).map(|_| 30.0 + 5.0 * rng.normal()).collect();
    for _ in 0..25 {
        let (rw, rh) = (3 + rng.below(w as u64 / 6) as usize, 3 + rng.below(h as u64 / 6) as usize);
        let (x0, y0) = (rng.below((w - rw) as u64) as usize, rng.below((h - rh) as u64) as usize);
        let v = rng.range(40.0, 200.0);
        for y in y0..y0 + rh {
            for x in x0..x0 + rw {
                d[y * w + x] = v;
            }
        }
    }
    let (cx, cy) = (rng.range(0.35, 0.65) * w as f64, rng.range(0.35, 0.65) * h as f64);
    let (ax, ay) = (rng.range(6.0, 14.0), rng.range(5.0, 11.0));
    for y in 0..h {
        for x in 0..w {
            let r = (((x as f64 - cx) / ax).powi(2) + ((y as f64 - cy) / ay).powi(2)).sqrt();
            let glow = if r <= 1.0 { 255.0 } else { 255.0 * (-(r - 1.0).powi(2) * 2.0).exp() };
            d[y * w + x] = d[y * w + x].max(glow);
        }
    }
    d.iter().map(|v| v.round().clamp(0.0, 255.0) as u8).collect()
}

pub fn save_grey(path: &Path, w: usize, h: usize, data: Vec<u8>) {
    image::GrayImage::from_raw(w as u32, h as u32, data).unwrap().save(path).unwrap();
}

/// `n` sunlamp-like frames `real_NN.png`.
pub fn write_reals(dir: &Path, n: usize, w: usize, h: usize) {
    for i in 0..n {
        save_grey(&dir.join(format!("real_{i:02}.png")), w, h, sunlamp_like(w, h, 100 + i as u64));
    }
}
