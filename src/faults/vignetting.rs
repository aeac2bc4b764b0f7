//! `vignetting` (not yet implemented).
