//! `faultcam eval` (not yet implemented).

/// Arguments of `faultcam eval`.
#[derive(clap::Args, Debug)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<u8> {
    anyhow::bail!("faultcam eval is not implemented yet")
}
