//! `faultcam log check FILE`: validate a ground-truth log (see [`faultcam::gtlog::check_log`]):
//! every record parses, no partial last line, a summary that says how the run ended, and every
//! input frame accounted for. Exit code 0 when the log is valid, 1 when it has problems.

use anyhow::Context;
use std::path::PathBuf;

/// Arguments of `faultcam log`.
#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    pub command: LogCommand,
}

#[derive(clap::Subcommand, Debug)]
pub enum LogCommand {
    /// Validate a ground-truth log: parse every record, report a truncated last record, a
    /// missing summary and unaccounted frames (exit code 1 on any problem).
    Check {
        /// The ground-truth log (JSON Lines).
        file: PathBuf,
    },
}

pub fn run(args: Args) -> anyhow::Result<u8> {
    let LogCommand::Check { file } = args.command;
    let bytes = std::fs::read(&file).with_context(|| format!("cannot read {}", file.display()))?;
    let c = faultcam::gtlog::check_log(&bytes);
    println!(
        "{}: {} records ({} frames, {} events, {} skips, {})",
        file.display(),
        c.records,
        c.frames,
        c.events,
        c.skips,
        if c.summary { "summary" } else { "no summary" }
    );
    if c.summary {
        println!(
            "  frame records: delivered {}, dropped by fault {}, dropped by overrun {}, failed {}",
            c.counts[0], c.counts[1], c.counts[2], c.counts[3]
        );
        println!(
            "  ended: {}{}",
            c.stopped_by.as_deref().unwrap_or("(not stated)"),
            c.error.as_deref().map(|e| format!("; error: {e}")).unwrap_or_default()
        );
        if c.unlogged > 0 {
            println!("  frame records the summary declares unwritten (log write failed): {}", c.unlogged);
        }
    }
    if c.ok() {
        println!("{}: ok", file.display());
        return Ok(0);
    }
    for p in &c.problems {
        println!("{}: {p}", file.display());
    }
    println!("{}: {} problems", file.display(), c.problems.len());
    Ok(1)
}
