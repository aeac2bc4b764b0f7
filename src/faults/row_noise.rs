//! `row_noise` (not yet implemented).
