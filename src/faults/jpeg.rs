//! `jpeg` (not yet implemented).
