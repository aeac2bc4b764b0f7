//! Bright zones: 8-connected components of the pixels at or above a level, with their bounding
//! boxes. The outer contour of a component (OpenCV `findContours(RETR_EXTERNAL)`) has the same
//! bounding box, so this needs no OpenCV; a test checks it against OpenCV.

use crate::metrics::Grey;

/// One connected bright region.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct Zone {
    /// Bounding box, `x0..x1` x `y0..y1` (exclusive ends), px.
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
    /// Pixels in the component.
    pub area: usize,
}

impl Zone {
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }
    pub fn height(&self) -> usize {
        self.y1 - self.y0
    }
    /// Box grown symmetrically about its centre to at least `min_w` x `min_h`, then shifted and
    /// clipped to stay inside a `w` x `h` image.
    pub fn expanded(&self, min_w: usize, min_h: usize, w: usize, h: usize) -> Zone {
        fn axis(a0: usize, a1: usize, min: usize, size: usize) -> (usize, usize) {
            let len = (a1 - a0).max(min).min(size);
            let centre2 = a0 + a1; // twice the centre
            let start = (centre2.saturating_sub(len) / 2).min(size - len);
            (start, start + len)
        }
        let (x0, x1) = axis(self.x0, self.x1, min_w, w);
        let (y0, y1) = axis(self.y0, self.y1, min_h, h);
        Zone { x0, y0, x1, y1, area: self.area }
    }
}

/// 8-connected components of `g >= level` (px count at least `min_area`), largest first.
pub fn bright_zones(g: &Grey, level: f32, min_area: usize) -> Vec<Zone> {
    let (w, h) = (g.width, g.height);
    let mut seen = vec![false; w * h];
    let mut stack = Vec::new();
    let mut zones = Vec::new();
    for start in 0..w * h {
        if seen[start] || g.data[start] < level {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut z = Zone { x0: usize::MAX, y0: usize::MAX, x1: 0, y1: 0, area: 0 };
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            z.x0 = z.x0.min(x);
            z.y0 = z.y0.min(y);
            z.x1 = z.x1.max(x + 1);
            z.y1 = z.y1.max(y + 1);
            z.area += 1;
            for ny in y.saturating_sub(1)..(y + 2).min(h) {
                for nx in x.saturating_sub(1)..(x + 2).min(w) {
                    let j = ny * w + nx;
                    if !seen[j] && g.data[j] >= level {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        if z.area >= min_area {
            zones.push(z);
        }
    }
    // Largest first; ties by position for determinism.
    zones.sort_by(|a, b| b.area.cmp(&a.area).then((a.y0, a.x0).cmp(&(b.y0, b.x0))));
    zones
}

/// Number of pixels at or above `level`.
pub fn count_at_or_above(g: &Grey, level: f32) -> usize {
    g.data.iter().filter(|&&v| v >= level).count()
}

/// Level used to find the blooming zone of a *bloomed* image (one that had a saturated region
/// before blooming): the threshold (250) if the image reaches it, else `0.98 * max(g)`. With a
/// camera that reads full scale at saturation this is the threshold itself; an image whose
/// saturated pixels read a full well below it (e.g. `blooming` with `full_well_fraction` 0.9
/// reads 0.9 FS = 230 DN) is cut just under its own saturation plateau instead. Real images are
/// cut at the threshold itself (no fallback: a dark real image has no blooming zone).
pub fn zone_level(g: &Grey, threshold: f32) -> f32 {
    let max = g.data.iter().copied().fold(0.0f32, f32::max);
    if max >= threshold { threshold } else { 0.98 * max }
}

/// The brightest blooming zone: the largest (most pixels) 8-connected region at or above
/// `level` with at least `min_area` px, or `None`.
pub fn blooming_zone(g: &Grey, level: f32, min_area: usize) -> Option<Zone> {
    if level <= 0.0 {
        return None;
    }
    bright_zones(g, level, min_area).into_iter().next()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: usize, h: usize, blobs: &[(usize, usize, usize, usize, f32)]) -> Grey {
        let mut g = Grey::new(w, h, vec![10.0; w * h]).unwrap();
        for &(x0, y0, bw, bh, v) in blobs {
            for y in y0..y0 + bh {
                for x in x0..x0 + bw {
                    g.data[y * w + x] = v;
                }
            }
        }
        g
    }

    #[test]
    fn components_and_boxes() {
        // Two blobs; a diagonal neighbour joins the second one (8-connectivity).
        let mut g = img(20, 10, &[(1, 1, 3, 2, 255.0), (10, 4, 5, 5, 252.0)]);
        g.data[9 * 20 + 15] = 255.0; // diagonal to (14, 8)
        let z = bright_zones(&g, 250.0, 1);
        assert_eq!(z.len(), 2);
        assert_eq!(z[0], Zone { x0: 10, y0: 4, x1: 16, y1: 10, area: 26 });
        assert_eq!(z[1], Zone { x0: 1, y0: 1, x1: 4, y1: 3, area: 6 });
        assert_eq!(bright_zones(&g, 250.0, 7).len(), 1);
        assert_eq!(count_at_or_above(&g, 250.0), 32);
    }

    #[test]
    fn zone_level_follows_a_low_full_well() {
        let g = img(8, 8, &[(2, 2, 2, 2, 229.5)]);
        assert!((zone_level(&g, 250.0) - 0.98 * 229.5).abs() < 1e-4);
        assert_eq!(blooming_zone(&g, zone_level(&g, 250.0), 1).unwrap().area, 4);
        assert_eq!(blooming_zone(&g, 250.0, 1), None);
        let g = img(8, 8, &[(2, 2, 2, 2, 255.0)]);
        assert_eq!(zone_level(&g, 250.0), 250.0);
    }

    #[test]
    fn expansion_stays_inside() {
        let z = Zone { x0: 0, y0: 5, x1: 2, y1: 7, area: 4 };
        let e = z.expanded(6, 4, 10, 8);
        assert_eq!((e.x0, e.x1, e.y0, e.y1), (0, 6, 4, 8));
        let e = z.expanded(20, 1, 10, 8);
        assert_eq!((e.x0, e.x1), (0, 10));
        assert_eq!((e.y0, e.y1), (5, 7));
        let z = Zone { x0: 8, y0: 0, x1: 10, y1: 1, area: 2 };
        assert_eq!(z.expanded(4, 1, 10, 8).x0, 6);
    }
}
