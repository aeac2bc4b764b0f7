//! `gaussian_noise` (not yet implemented).
