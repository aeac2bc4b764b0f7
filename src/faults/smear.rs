//! `smear` (not yet implemented).
