//! Cut the SPEED+ figure tiles that the README's real-data numbers use from the published figure
//! images (see tests/data/README.md for where to get them and why they are not shipped).
//!
//! `cargo run --release --example speedplus_tiles -- ORIGINALS_DIR OUT_DIR`
//!
//! ORIGINALS_DIR holds `speedplus_teaser.jpg` and `acta2023_spec2021_teaser.jpg`. Each tile is
//! the crop box (left, top, right, bottom, source pixels) of the reference data's index, the
//! decoded JPEG converted to 8-bit grey with ITU-R 601 luma in 16-bit fixed point
//! (`(19595 R + 38470 G + 7471 B + 32768) >> 16`, as Pillow's `convert("L")`), no resampling,
//! saved as PNG.

use std::path::Path;

/// (tile, source figure, crop box left, top, right, bottom).
const TILES: &[(&str, &str, [u32; 4])] = &[
    ("speedplus_synthetic_r1c1", "speedplus_teaser.jpg", [0, 0, 330, 205]),
    ("speedplus_synthetic_r2c1", "speedplus_teaser.jpg", [0, 208, 330, 413]),
    ("speedplus_synthetic_r1c2", "speedplus_teaser.jpg", [332, 0, 662, 205]),
    ("speedplus_synthetic_r2c2", "speedplus_teaser.jpg", [332, 208, 662, 413]),
    ("speedplus_lightbox_r1c1", "speedplus_teaser.jpg", [719, 0, 1047, 205]),
    ("speedplus_lightbox_r2c1", "speedplus_teaser.jpg", [719, 208, 1047, 413]),
    ("speedplus_lightbox_r1c2", "speedplus_teaser.jpg", [1051, 0, 1379, 205]),
    ("speedplus_lightbox_r2c2", "speedplus_teaser.jpg", [1051, 208, 1379, 413]),
    ("speedplus_sunlamp_r1c1", "speedplus_teaser.jpg", [1436, 0, 1766, 205]),
    ("speedplus_sunlamp_r2c1", "speedplus_teaser.jpg", [1436, 208, 1766, 413]),
    ("speedplus_sunlamp_r1c2", "speedplus_teaser.jpg", [1768, 0, 2098, 205]),
    ("speedplus_sunlamp_r2c2", "speedplus_teaser.jpg", [1768, 208, 2098, 413]),
    ("acta_sunlamp_img000338", "acta2023_spec2021_teaser.jpg", [437, 218, 635, 339]),
    ("acta_sunlamp_img000044", "acta2023_spec2021_teaser.jpg", [437, 378, 635, 499]),
    ("acta_sunlamp_img001755", "acta2023_spec2021_teaser.jpg", [437, 537, 635, 656]),
];

fn main() -> std::process::ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [originals, out] = args.as_slice() else {
        eprintln!("usage: speedplus_tiles ORIGINALS_DIR OUT_DIR");
        return std::process::ExitCode::from(2);
    };
    if let Err(e) = run(Path::new(originals), Path::new(out)) {
        eprintln!("speedplus_tiles: {e}");
        return std::process::ExitCode::FAILURE;
    }
    std::process::ExitCode::SUCCESS
}

fn run(originals: &Path, out: &Path) -> Result<(), String> {
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let mut cache: Option<(&str, image::RgbImage)> = None;
    for &(name, src, [l, t, r, b]) in TILES {
        if cache.as_ref().is_none_or(|(s, _)| *s != src) {
            let p = originals.join(src);
            let img = image::open(&p).map_err(|e| format!("{}: {e}", p.display()))?.to_rgb8();
            cache = Some((src, img));
        }
        let Some((_, img)) = &cache else { unreachable!() };
        if r > img.width() || b > img.height() {
            return Err(format!("{src}: {}x{} is smaller than the crop box of {name}", img.width(), img.height()));
        }
        let tile = image::GrayImage::from_fn(r - l, b - t, |x, y| {
            let [pr, pg, pb] = img.get_pixel(l + x, t + y).0;
            image::Luma([((19595 * pr as u32 + 38470 * pg as u32 + 7471 * pb as u32 + 32768) >> 16) as u8])
        });
        let p = out.join(format!("{name}.png"));
        tile.save(&p).map_err(|e| format!("{}: {e}", p.display()))?;
    }
    println!("{} tiles in {}", TILES.len(), out.display());
    Ok(())
}
