//! `faultcam` command line. Each subcommand lives in `src/cli/<name>.rs` with its `Args` and
//! `run`; errors are printed with their causes and turned into an exit code.

mod cli;

use clap::{Parser, Subcommand};

/// Physically modelled camera faults for hardware-in-the-loop testing of spacecraft vision.
#[derive(Parser, Debug)]
#[command(name = "faultcam", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Largest image or stream frame accepted, WxH pixels (default 16384x16384): checked from
    /// the file header, GStreamer caps, camera region or V4L2 format before any allocation.
    #[arg(long, global = true, value_name = "WxH")]
    max_image_dims: Option<String>,
    /// Largest decoded image accepted, in MB (default 1024).
    #[arg(long, global = true, value_name = "N")]
    max_image_mb: Option<u64>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Stream frames from a source through the fault chain into a sink.
    Run(cli::run::Args),
    /// Apply a fault config to every image of a folder (batch, shardable).
    Apply(cli::apply::Args),
    /// List effects with their parameters, units and physical models.
    Effects(cli::effects::Args),
    /// Measure per-frame latency (p50/p99/max) of effects and chains.
    Bench(cli::bench::Args),
    /// Fidelity metrics between images or sets, and the blooming validation protocol.
    Eval(cli::eval::Args),
    /// Find the physics a simulation left out, fit it, and report the improvement.
    Diagnose(cli::diagnose::Args),
    /// Robustness sweeps: a pose stack under test against every fault and severity.
    Sweep(cli::sweep::Args),
    /// Ground-truth logs: `log check FILE` validates one (truncation, summary, accounting).
    Log(cli::log::Args),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    match faultcam::limits::ImageLimits::from_flags(cli.max_image_dims.as_deref(), cli.max_image_mb) {
        Ok(l) => l.set_current(),
        Err(e) => {
            eprintln!("faultcam: error: {e}");
            return std::process::ExitCode::from(2);
        }
    }
    let result = match cli.command {
        Command::Run(a) => cli::run::run(a),
        Command::Apply(a) => cli::apply::run(a),
        Command::Effects(a) => cli::effects::run(a),
        Command::Bench(a) => cli::bench::run(a),
        Command::Eval(a) => cli::eval::run(a),
        Command::Diagnose(a) => cli::diagnose::run(a),
        Command::Log(a) => cli::log::run(a),
        Command::Sweep(a) => cli::sweep::run(a),
    };
    match result {
        Ok(code) => std::process::ExitCode::from(code),
        Err(e) => {
            // A closed stdout (e.g. `faultcam effects | head`) is not an error.
            if let Some(io) = e.downcast_ref::<std::io::Error>()
                && io.kind() == std::io::ErrorKind::BrokenPipe
            {
                return std::process::ExitCode::SUCCESS;
            }
            eprintln!("faultcam: error: {e:#}");
            std::process::ExitCode::from(2)
        }
    }
}
