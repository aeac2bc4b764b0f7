//! `motion_blur` (not yet implemented).
