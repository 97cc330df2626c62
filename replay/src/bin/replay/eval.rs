//! `replay eval INPUTS…`: the paper's table over logs and dataset folders.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, ValueEnum};
use cli::{Outcome, UsageError, progress_bar};
use replay::eval::{csv, evaluate_sets, markdown};
use tracing::info;

/// Table formats.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum TableFormat {
    Markdown,
    Csv,
    Json,
}

/// Arguments of `replay eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Logs (.mcap) and dataset folders (e.g. ../shared/data/middlebury2006-third-dev).
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Methods to compare (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "bm-stereo,bm-mean,bm-min,bm-heuristic,sgm-stereo,sgm-heuristic"
    )]
    methods: Vec<String>,
    /// Disparities searched (default: per set, the range its log or multiscopic.toml gives, else
    /// width/15 rounded up to a multiple of 16); at most 1024.
    #[arg(long)]
    num_disparities: Option<usize>,
    /// Smallest disparity searched, signed: negative for converged rigs (default: per set, as
    /// its log or multiscopic.toml says, else 0), e.g. --min-disparity -8.
    #[arg(long, value_name = "PX", allow_hyphen_values = true)]
    min_disparity: Option<i32>,
    /// Table format on stdout.
    #[arg(long, value_enum, default_value = "markdown")]
    format: TableFormat,
    /// Also write the table as Markdown, CSV and JSON into this directory.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Configuration overrides applied to every method, as a JSON object.
    #[arg(long, value_name = "JSON")]
    config: Option<String>,
    /// Only these neighbours (roles, comma-separated), e.g. left,right for three views of a five-view set.
    #[arg(long, value_delimiter = ',')]
    neighbours: Vec<String>,
    /// Correct what the logged poses allow: de-rotate each neighbour (homography), resample its costs by its real baseline ratio.
    #[arg(long)]
    rectify: bool,
    /// MFuseNet weights (safetensors) instead of the shipped ones.
    #[arg(long, value_name = "FILE")]
    weights: Option<PathBuf>,
    /// Errors in pixels of disparity at this baseline (mm), "occluded" = hidden from a view at it
    /// along either axis (from the ground truth): compares rigs that took different baselines
    /// (an adaptive capture at twice the baseline) on the same depth errors and pixels.
    #[arg(long, value_name = "MM")]
    at_baseline_mm: Option<f64>,
    /// How dataset folders are read (as `record import`; logs ignore these).
    #[command(flatten, next_help_heading = "Dataset folders")]
    dataset: record::import::ImportOverrides,
}

/// Runs `replay eval`.
pub fn run(args: &EvalArgs, quiet: bool) -> Result<Outcome> {
    for name in &args.methods {
        if !fuse::methods::registry().iter().any(|e| e.name == name) {
            return Err(UsageError(format!("unknown method '{name}' (see --list-methods)")).into());
        }
    }
    if args.at_baseline_mm.is_some_and(|mm| !(mm > 0.0 && mm.is_finite())) {
        return Err(UsageError("--at-baseline-mm must be a positive number of millimetres".to_owned()).into());
    }
    let overrides = crate::parse_overrides(args.config.as_deref())?;
    let sets = replay::eval::read_inputs(&args.inputs, &args.dataset).map_err(|e| match e {
        replay::ReplayError::Import(e) if e.is_usage() => UsageError(e.to_string()).into(),
        e => anyhow::Error::new(e),
    })?;
    let with_truth = sets.iter().filter(|s| s.ground_truth_depth_m.is_some()).count();
    if with_truth == 0 {
        anyhow::bail!("none of the {} view sets has ground truth", sets.len());
    }
    let progress = progress_bar((args.methods.len() * with_truth) as u64, quiet, "runs");
    let options = replay::eval::EvalOptions {
        num_disparities: args.num_disparities,
        min_disparity: args.min_disparity,
        overrides,
        neighbours: args.neighbours.clone(),
        rectify: args.rectify,
        weights: args.weights.clone(),
        at_baseline_m: args.at_baseline_mm.map(|mm| mm / 1000.0),
    };
    let rows = evaluate_sets(&sets, &args.methods, &options, |method, scene| {
        progress.set_message(format!("{method} on {scene}"));
        progress.inc(1);
    })?;
    progress.finish_and_clear();
    let table = markdown(&rows);
    match args.format {
        TableFormat::Markdown => print!("{table}"),
        TableFormat::Csv => print!("{}", csv(&rows)?),
        TableFormat::Json => println!("{}", serde_json::to_string_pretty(&rows)?),
    }
    if let Some(dir) = &args.out {
        replay::eval::write_tables(dir, &rows)?;
        info!("wrote eval.md, eval.csv and eval.json to {}", dir.display());
    }
    Ok(Outcome::Complete)
}
