//! `v4l2:` source (not yet implemented).
