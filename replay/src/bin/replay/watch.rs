//! `replay watch DIR`: replay each finished log that appears in a folder, in one process that
//! stays up (the workcell's replay; `replay::watch`).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args;
use cli::Outcome;
use replay::pipeline::RunOptions;
use replay::watch::{WatchRequest, WatchedLog, watch};
use tracing::{error, info, warn};

/// Arguments of `replay watch`.
#[derive(Debug, Args)]
pub struct WatchArgs {
    /// The folder the logs appear in (e.g. `record … -o DIR/part-0042.mcap` from the cell's
    /// controller, or a ROS 2 recorder's output folder).
    dir: PathBuf,
    /// Method (see --list-methods); several comma-separated, or `all`.
    #[arg(long, default_value = "sgm-heuristic")]
    method: String,
    /// Method configuration overrides as a JSON object, e.g. '{"block_radius_px": 3}'.
    #[arg(long, value_name = "JSON")]
    config: Option<String>,
    /// MFuseNet weights (safetensors) instead of the shipped ones.
    #[arg(long, value_name = "FILE")]
    weights: Option<PathBuf>,
    /// Each log's results go to OUT/<log name>/ (summary.json last: it says the log is done).
    #[arg(long, default_value = "results")]
    out: PathBuf,
    /// Which result files each set gets, as for `replay LOG` (a workcell that needs only the
    /// depth: `--outputs depth`).
    #[arg(long, default_value = "all", value_name = "FILES", value_parser = crate::run::parse_outputs)]
    outputs: replay::outputs::ResultFiles,
    /// Disparities searched (default: each log's range for the set, else width/15 rounded up
    /// to a multiple of 16).
    #[arg(long)]
    num_disparities: Option<usize>,
    /// Smallest disparity searched, signed (default: each log's range, else 0).
    #[arg(long, value_name = "PX", allow_hyphen_values = true)]
    min_disparity: Option<i32>,
    /// Only these neighbours (roles, comma-separated).
    #[arg(long, value_delimiter = ',')]
    neighbours: Vec<String>,
    /// De-rotate each neighbour and resample its costs by its real baseline ratio.
    #[arg(long)]
    rectify: bool,
    /// Also replay the logs already in the folder (by default only those that appear later).
    #[arg(long)]
    existing: bool,
    /// How often the folder is listed (ms).
    #[arg(long, default_value_t = 20, value_name = "MS")]
    poll_ms: u64,
    /// Stop after this many logs (default: run until interrupted).
    #[arg(long, value_name = "N")]
    exit_after: Option<usize>,
    /// Stop when no log has appeared (or been written to) for this many seconds.
    #[arg(long, value_name = "SECS")]
    idle_exit: Option<f64>,
}

/// One log's line: where its results are and how long they took.
fn report(log: &WatchedLog) {
    let name = log.path.display();
    match &log.result {
        Ok(report) => {
            let methods: Vec<String> = report
                .summary
                .sets
                .iter()
                .map(|s| format!("set {} {} {:.2} s", s.outputs.set, s.method, s.seconds))
                .collect();
            let line = format!(
                "{name}: {} — {:.2} s from finished log to results → {}",
                methods.join(", "),
                log.seconds,
                log.out.display()
            );
            if report.lost_anything {
                warn!("{line} (something was lost: see above)");
            } else {
                info!("{line}");
            }
        }
        Err(e) => {
            let mut chain = e.to_string();
            let mut source = std::error::Error::source(e);
            while let Some(cause) = source {
                chain.push_str(&format!(": {cause}"));
                source = cause.source();
            }
            error!("{name}: {chain} (the watch goes on)");
        }
    }
}

/// Runs `replay watch`.
pub fn run(args: &WatchArgs, quiet: bool) -> Result<Outcome> {
    if !args.dir.is_dir() {
        return Err(cli::UsageError(format!("{} is not a folder", args.dir.display())).into());
    }
    let overrides = crate::parse_overrides(args.config.as_deref())?;
    let methods = crate::build_methods(&args.method, overrides.as_ref(), args.weights.as_deref())?;
    let idle_exit = match args.idle_exit {
        Some(secs) if !(secs.is_finite() && secs >= 0.0) => {
            return Err(cli::UsageError(format!("--idle-exit {secs}: a number of seconds, 0 or more")).into());
        }
        Some(secs) => Some(Duration::from_secs_f64(secs)),
        None => None,
    };
    let request = WatchRequest {
        dir: &args.dir,
        methods: &methods,
        method_spec: &args.method,
        options: RunOptions {
            num_disparities: args.num_disparities,
            min_disparity: args.min_disparity,
            neighbours: args.neighbours.clone(),
            rectify: args.rectify,
        },
        out: &args.out,
        outputs: args.outputs,
        existing: args.existing,
        poll: Duration::from_millis(args.poll_ms.max(1)),
        exit_after: args.exit_after,
        idle_exit,
    };
    info!(
        "watching {} for finished logs ({}); results in {}/<log name>/",
        args.dir.display(),
        args.method,
        args.out.display()
    );
    let progress = |message: &str| crate::run::method_progress(message, quiet);
    let done = watch(&request, &progress, &mut report).with_context(|| format!("watching {}", args.dir.display()))?;
    info!("{} logs replayed, {} failed", done.replayed, done.failed);
    Ok(if done.failed > 0 {
        Outcome::Incomplete
    } else {
        Outcome::Complete
    })
}
