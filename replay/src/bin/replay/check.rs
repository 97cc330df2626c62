//! `replay check LOG`: the alignment report of every set.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use cli::Outcome;
use tracing::warn;

/// Arguments of `replay check`.
#[derive(Debug, Args)]
pub struct CheckArgs {
    /// The log to check.
    log: PathBuf,
    /// Print JSON instead of the table.
    #[arg(long)]
    json: bool,
    /// Disparities searched by the image-based shift estimate (default: as for replay).
    #[arg(long)]
    num_disparities: Option<usize>,
    /// Warn from this predicted epipolar error or measured image shift (px).
    #[arg(long, value_name = "PX", default_value_t = replay::check::DEFAULT_PIXEL_LIMITS.warn_px)]
    warn_px: f64,
    /// Fail from this predicted epipolar error or measured image shift (px).
    #[arg(long, value_name = "PX", default_value_t = replay::check::DEFAULT_PIXEL_LIMITS.fail_px)]
    fail_px: f64,
    /// Only images logged at least this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    start: Option<f64>,
    /// Only images logged at most this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    end: Option<f64>,
    #[command(flatten)]
    stream: crate::info::StreamArgs,
}

/// Runs `replay check`.
pub fn run(args: &CheckArgs) -> Result<Outcome> {
    let contents = replay::log::read_log_file_with(
        &args.log,
        &replay::log::ReadOptions {
            start_secs: args.start,
            end_secs: args.end,
            stream: args.stream.options(),
            ..replay::log::ReadOptions::default()
        },
    )
    .with_context(|| format!("reading {}", args.log.display()))?;
    if !(args.warn_px > 0.0 && args.fail_px >= args.warn_px) {
        return Err(cli::UsageError(format!(
            "--warn-px {} and --fail-px {} must be positive, the second at least the first",
            args.warn_px, args.fail_px
        ))
        .into());
    }
    let limits = replay::check::PixelLimits {
        warn_px: args.warn_px,
        fail_px: args.fail_px,
    };
    for line in contents.damage() {
        warn!("{}: {line}", args.log.display());
    }
    let checks: Vec<replay::check::SetCheck> = contents
        .sets
        .iter()
        .map(|set| {
            replay::check::check_set(
                set,
                args.num_disparities.unwrap_or_else(|| set.default_num_disparities()),
                limits,
            )
        })
        .collect();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&checks)?);
    } else {
        for check in &checks {
            print!("{}", replay::check::table(check));
        }
    }
    let failed = checks
        .iter()
        .filter(|c| c.status == replay::check::Status::Fail)
        .count();
    if failed > 0 || contents.lost_anything() {
        if failed > 0 {
            warn!("{failed} of {} set(s) failed the alignment check", checks.len());
        }
        return Ok(Outcome::Incomplete);
    }
    Ok(Outcome::Complete)
}
