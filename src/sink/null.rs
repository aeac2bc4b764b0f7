//! `null:` sink (not yet implemented).
