//! `hot_pixels` (not yet implemented).
