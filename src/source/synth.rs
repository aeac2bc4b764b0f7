//! `synth:` source (not yet implemented).
