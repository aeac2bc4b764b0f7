//! `blooming` (not yet implemented).
