//! `channel_shift` (not yet implemented).
