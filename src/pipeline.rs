//! `pipeline` (not yet implemented).
