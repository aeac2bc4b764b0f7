//! `gst:` sink (not yet implemented).
