//! `faultcam run` (not yet implemented).

/// Arguments of `faultcam run`.
#[derive(clap::Args, Debug)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<u8> {
    anyhow::bail!("faultcam run is not implemented yet")
}
