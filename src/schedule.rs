//! `schedule` (not yet implemented).
