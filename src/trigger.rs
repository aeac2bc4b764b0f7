//! `trigger` (not yet implemented).
