//! File helpers shared by the integration tests (each test crate uses some of them).
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::path::Path;

/// A temporary folder of `n` small grey PNGs `img_000.png`, ... (16x8, different per file).
pub fn png_folder(n: usize) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for i in 0..n {
        let img = image::GrayImage::from_fn(16, 8, |x, y| image::Luma([(x * 10 + y + i as u32 * 20) as u8]));
        img.save(dir.path().join(format!("img_{i:03}.png"))).unwrap();
    }
    dir
}

/// File name → bytes of every PNG in `dir` (not the logs).
pub fn pngs(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap()))
        .collect()
}
