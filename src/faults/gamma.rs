//! `gamma` (not yet implemented).
