//! `files:` sink (not yet implemented).
