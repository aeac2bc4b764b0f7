//! `faultcam apply` (not yet implemented).

/// Arguments of `faultcam apply`.
#[derive(clap::Args, Debug)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<u8> {
    anyhow::bail!("faultcam apply is not implemented yet")
}
