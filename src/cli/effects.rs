//! `faultcam effects` (not yet implemented).

/// Arguments of `faultcam effects`.
#[derive(clap::Args, Debug)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<u8> {
    anyhow::bail!("faultcam effects is not implemented yet")
}
