//! `stray_light` (not yet implemented).
