//! `gst:` source (not yet implemented).
