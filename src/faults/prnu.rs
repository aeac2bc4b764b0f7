//! `prnu` (not yet implemented).
