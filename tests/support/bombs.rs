//! Crafted image files whose headers claim a huge size over a few bytes of data
//! ("decompression bombs"), one per decoder: PNG, TIFF, PNM, JPEG.
#![allow(dead_code)]

/// CRC-32 (IEEE, as PNG uses).
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let start = out.len();
    out.extend_from_slice(kind);
    out.extend_from_slice(data);
    let crc = crc32(&out[start..]);
    out.extend_from_slice(&crc.to_be_bytes());
}

/// A valid-looking 8-bit grey PNG header claiming `w` x `h`, with a 16-byte zlib stream (about
/// 90 bytes in all).
pub fn png(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    png_chunk(&mut out, b"IHDR", &ihdr);
    // zlib, one stored block of 16 zero bytes, Adler-32 of 16 zeros = 0x00100001.
    let mut z = vec![0x78, 0x01, 0x01, 16, 0, !16u8, 0xFF];
    z.extend_from_slice(&[0; 16]);
    z.extend_from_slice(&0x0010_0001u32.to_be_bytes());
    png_chunk(&mut out, b"IDAT", &z);
    png_chunk(&mut out, b"IEND", &[]);
    out
}

/// A binary PGM header claiming `w` x `h` (8-bit), with 16 bytes of data.
pub fn pnm(w: u32, h: u32) -> Vec<u8> {
    let mut out = format!("P5\n{w} {h}\n255\n").into_bytes();
    out.extend_from_slice(&[0; 16]);
    out
}

/// A little-endian baseline TIFF claiming `w` x `h` 8-bit grey in one uncompressed strip of
/// which 16 bytes exist.
pub fn tiff(w: u32, h: u32) -> Vec<u8> {
    let entries: [(u16, u16, u32); 9] = [
        (256, 4, w),  // ImageWidth, LONG
        (257, 4, h),  // ImageLength
        (258, 3, 8),  // BitsPerSample, SHORT
        (259, 3, 1),  // Compression: none
        (262, 3, 1),  // Photometric: BlackIsZero
        (273, 4, 0),  // StripOffsets (patched below)
        (277, 3, 1),  // SamplesPerPixel
        (278, 4, h),  // RowsPerStrip: one strip
        (279, 4, 16), // StripByteCounts
    ];
    let data_at = 8 + 2 + entries.len() as u32 * 12 + 4;
    let mut out = b"II*\0".to_vec();
    out.extend_from_slice(&8u32.to_le_bytes());
    out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, ty, v) in entries {
        let v = if tag == 273 { data_at } else { v };
        out.extend_from_slice(&tag.to_le_bytes());
        out.extend_from_slice(&ty.to_le_bytes());
        out.extend_from_slice(&1u32.to_le_bytes());
        if ty == 3 {
            out.extend_from_slice(&(v as u16).to_le_bytes());
            out.extend_from_slice(&[0, 0]);
        } else {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out.extend_from_slice(&0u32.to_le_bytes());
    out.extend_from_slice(&[0; 16]);
    out
}

/// A real 8x8 grey baseline JPEG whose SOF0 header is patched to claim `w` x `h` (at most
/// 65535 each, the format's limit).
pub fn jpeg(w: u16, h: u16) -> Vec<u8> {
    let img = image::GrayImage::from_fn(8, 8, |x, y| image::Luma([(x * 30 + y) as u8]));
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90).encode_image(&img).unwrap();
    let sof = out.windows(2).position(|m| m == [0xFF, 0xC0]).expect("baseline SOF0 marker");
    // FF C0, length (2), precision (1), height (2), width (2).
    out[sof + 5..sof + 7].copy_from_slice(&h.to_be_bytes());
    out[sof + 7..sof + 9].copy_from_slice(&w.to_be_bytes());
    out
}

/// (file name, bytes) of one bomb per decoder, named to sort before ordinary inputs.
pub fn all() -> Vec<(&'static str, Vec<u8>)> {
    vec![
        ("0-bomb-png.png", png(100_000, 100_000)),
        ("0-bomb-tiff.tiff", tiff(100_000, 100_000)),
        ("0-bomb-pgm.pgm", pnm(100_000, 100_000)),
        ("0-bomb-jpg.jpg", jpeg(65_535, 65_535)),
    ]
}
