//! `eval` (not yet implemented).
