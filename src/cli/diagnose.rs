//! `faultcam diagnose` (not yet implemented).

/// Arguments of `faultcam diagnose`.
#[derive(clap::Args, Debug)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<u8> {
    anyhow::bail!("faultcam diagnose is not implemented yet")
}
