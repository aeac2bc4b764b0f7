//! `metrics` (not yet implemented).
