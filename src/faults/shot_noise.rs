//! `shot_noise` (not yet implemented).
