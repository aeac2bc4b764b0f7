//! `radiation` (not yet implemented).
