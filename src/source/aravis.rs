//! `aravis:` source (not yet implemented).
