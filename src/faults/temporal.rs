//! `temporal` (not yet implemented).
