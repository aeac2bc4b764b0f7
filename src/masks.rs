//! `masks` (not yet implemented).
