//! `diagnose` (not yet implemented).
