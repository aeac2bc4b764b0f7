//! `faultcam bench` (not yet implemented).

/// Arguments of `faultcam bench`.
#[derive(clap::Args, Debug)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<u8> {
    anyhow::bail!("faultcam bench is not implemented yet")
}
