//! `replay eval INPUTS…`: the paper's table over logs and dataset folders.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use record::cli::{Outcome, UsageError, progress_bar};
use replay::eval::{csv, evaluate_sets, markdown};
use replay::log::read_log_file;
use replay::viewset::ViewSet;
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
    /// width/15 rounded up to a multiple of 16).
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
    /// How dataset folders are read (as `record import`; logs ignore these).
    #[command(flatten, next_help_heading = "Dataset folders")]
    dataset: record::import::ImportOverrides,
}

fn read_inputs(inputs: &[PathBuf], dataset: &record::import::ImportOverrides) -> Result<Vec<ViewSet>> {
    let mut sets = Vec::new();
    for input in inputs {
        if input.is_dir() {
            match replay::dataset::read_dataset_with(input, dataset) {
                Ok(read) => sets.extend(read),
                Err(replay::ReplayError::Import(e)) if e.is_usage() => {
                    return Err(UsageError(format!("{}: {e}", input.display())).into());
                }
                Err(e) => return Err(anyhow::Error::new(e).context(format!("reading dataset {}", input.display()))),
            }
        } else {
            let contents = read_log_file(input).with_context(|| format!("reading {}", input.display()))?;
            let name = input
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            for mut set in contents.sets {
                set.name = format!("{name}/{}", set.name);
                sets.push(set);
            }
        }
    }
    Ok(sets)
}

/// Runs `replay eval`.
pub fn run(args: &EvalArgs) -> Result<Outcome> {
    for name in &args.methods {
        if !fuse::methods::registry().iter().any(|e| e.name == name) {
            return Err(UsageError(format!("unknown method '{name}' (see --list-methods)")).into());
        }
    }
    let overrides = crate::parse_overrides(args.config.as_deref())?;
    let sets = read_inputs(&args.inputs, &args.dataset)?;
    let with_truth = sets.iter().filter(|s| s.ground_truth_depth_m.is_some()).count();
    if with_truth == 0 {
        anyhow::bail!("none of the {} view sets has ground truth", sets.len());
    }
    let progress = progress_bar((args.methods.len() * with_truth) as u64, false, "runs");
    let options = replay::eval::EvalOptions {
        num_disparities: args.num_disparities,
        min_disparity: args.min_disparity,
        overrides,
        neighbours: args.neighbours.clone(),
        rectify: args.rectify,
        weights: args.weights.clone(),
    };
    let rows = evaluate_sets(&sets, &args.methods, &options, |method, scene| {
        progress.set_message(format!("{method} on {scene}"));
        progress.inc(1);
    })?;
    progress.finish_and_clear();
    let table = markdown(&rows);
    match args.format {
        TableFormat::Markdown => print!("{table}"),
        TableFormat::Csv => print!("{}", csv(&rows)),
        TableFormat::Json => println!("{}", serde_json::to_string_pretty(&rows)?),
    }
    if let Some(dir) = &args.out {
        write_tables(dir, &rows, &table)?;
    }
    Ok(Outcome::Complete)
}

fn write_tables(dir: &Path, rows: &[replay::eval::EvalRow], table: &str) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    std::fs::write(dir.join("eval.md"), table)?;
    std::fs::write(dir.join("eval.csv"), csv(rows))?;
    std::fs::write(dir.join("eval.json"), serde_json::to_string_pretty(rows)?)?;
    info!("wrote eval.md, eval.csv and eval.json to {}", dir.display());
    Ok(())
}
