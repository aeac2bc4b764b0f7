//! `files:` source (not yet implemented).
