//! `defocus` (not yet implemented).
