//! `v4l2:` sink (not yet implemented).
