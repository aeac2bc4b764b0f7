//! `lens_flare` (not yet implemented).
