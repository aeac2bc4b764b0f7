//! `glitch` (not yet implemented).
