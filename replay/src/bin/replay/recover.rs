//! `replay recover LOG -o FIXED.mcap`: what survived of a cut or corrupt log, as a finished one.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use cli::Outcome;
use tracing::{info, warn};

/// Arguments of `replay recover`.
#[derive(Debug, Args)]
#[command(after_help = "Examples:\n  \
    replay recover .capture.mcap.partial-4242 -o capture.mcap   the recorder's temporary file after a crash\n  \
    replay recover cut.mcap -o fixed.mcap --json               the report as JSON on stdout\n\n\
    Exit status: 0 the log was whole, 3 something was lost (and the rest written), 1 error.")]
pub struct RecoverArgs {
    /// The damaged log: cut off by a crash (the recorder's hidden `.NAME.partial-PID` file),
    /// truncated in a copy, or with a corrupt chunk.
    log: PathBuf,
    /// The recovered log to write (indexed, with CRCs; written under a temporary name, then
    /// renamed).
    #[arg(short, long, value_name = "FIXED.mcap")]
    output: PathBuf,
    /// Print the report as JSON on stdout.
    #[arg(long)]
    json: bool,
}

/// Runs `replay recover`.
pub fn run(args: &RecoverArgs) -> Result<Outcome> {
    let report = replay::recover::recover_file(&args.log, &args.output)
        .with_context(|| format!("recovering {}", args.log.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    }
    if let Some(cut) = &report.cut {
        warn!("{}: {cut}", args.log.display());
    }
    for chunk in &report.bad_chunks {
        warn!("{}: left out the {chunk}", args.log.display());
    }
    for (set, reason) in &report.incomplete_sets {
        warn!("set {set} is incomplete: {reason}");
    }
    info!(
        "wrote {}: {} complete set(s) ({}), {} messages on {} channels, {} attachment(s), {} metadata record(s)",
        report.output.display(),
        report.sets.len(),
        report
            .sets
            .iter()
            .map(|(index, name)| format!("{index} {name}"))
            .collect::<Vec<_>>()
            .join(", "),
        report.messages,
        report.channels,
        report.attachments,
        report.metadata
    );
    Ok(if report.lost_anything() {
        Outcome::Incomplete
    } else {
        Outcome::Complete
    })
}
