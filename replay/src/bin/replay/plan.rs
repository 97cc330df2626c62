//! `replay plan LOG`: the next best views of a set, as arm poses and grid offsets with their
//! expected gain.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use cli::{Outcome, UsageError};
use fuse::plan::{LayoutRule, PlanConfig};
use tracing::warn;

/// Arguments of `replay plan`.
#[derive(Debug, Args)]
pub struct PlanArgs {
    /// The log whose set is planned.
    log: PathBuf,
    /// The set to plan (its index in the log).
    #[arg(long, default_value_t = 0)]
    set: u32,
    /// How many views to propose (pairs under `--layout pairs`).
    #[arg(long, default_value_t = 3)]
    budget: usize,
    /// The method whose depth and confidence are planned from.
    #[arg(long, default_value = "mfusenet")]
    method: String,
    /// Plan as if the set had only these neighbours (comma-separated roles; default all), e.g.
    /// `--neighbours left` for the second view of a capture that has the centre and the left.
    #[arg(long, value_delimiter = ',')]
    neighbours: Vec<String>,
    /// Candidates as single views (`free`) or opposite pairs (`pairs`, what MFuseNet's networks
    /// take); default: pairs for the MFuseNet family, free otherwise.
    #[arg(long, value_parser = ["free", "pairs"])]
    layout: Option<String>,
    /// Longest candidate offset, in baselines (the 8 directions at 1 … this).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(i32).range(1..=4))]
    max_offset: i32,
    /// Largest disparity (px) a candidate may reach at its own offset (default: the end of the
    /// range the set is searched over).
    #[arg(long, value_name = "PX")]
    max_disparity: Option<f32>,
    /// Disparities the method searches (default: as for replay).
    #[arg(long)]
    num_disparities: Option<usize>,
    /// Smallest disparity the method searches (default: as for replay).
    #[arg(long, allow_hyphen_values = true)]
    min_disparity: Option<i32>,
    /// Print the plan as JSON (every candidate, its scores, poses, joints and reach).
    #[arg(long)]
    json: bool,
    /// Also write the plan as JSON to this file.
    #[arg(long, short)]
    out: Option<PathBuf>,
}

/// Runs `replay plan`.
pub fn run(args: &PlanArgs) -> Result<Outcome> {
    if args.budget == 0 {
        return Err(UsageError("--budget must be at least 1".into()).into());
    }
    let contents = replay::log::read_log_file(&args.log).with_context(|| format!("reading {}", args.log.display()))?;
    for line in contents.damage() {
        warn!("{}: {line}", args.log.display());
    }
    let set = contents.sets.iter().find(|s| s.index == args.set).ok_or_else(|| {
        UsageError(format!(
            "{} has no set {} (it has {})",
            args.log.display(),
            args.set,
            contents
                .sets
                .iter()
                .map(|s| s.index.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    let method = crate::build_methods(&args.method, None, None)?
        .into_iter()
        .next()
        .ok_or_else(|| UsageError("--method names no method".into()))?;
    let options = replay::plan::PlanOptions {
        budget: args.budget,
        config: PlanConfig {
            max_offset: args.max_offset,
            ..PlanConfig::default()
        },
        layout: args.layout.as_deref().map(|l| match l {
            "pairs" => LayoutRule::Pairs,
            _ => LayoutRule::Free,
        }),
        max_disparity_px: args.max_disparity,
        run: replay::pipeline::RunOptions {
            num_disparities: args.num_disparities,
            min_disparity: args.min_disparity,
            neighbours: args.neighbours.clone(),
            rectify: false,
        },
    };
    let plan = replay::plan::plan_set(set, method.as_ref(), &options)
        .with_context(|| format!("planning set {} of {}", args.set, args.log.display()))?;
    let json = serde_json::to_string_pretty(&plan)?;
    if let Some(path) = &args.out {
        std::fs::write(path, &json).with_context(|| format!("writing {}", path.display()))?;
    }
    if args.json {
        println!("{json}");
    } else {
        print!("{}", replay::plan::table(&plan));
    }
    if plan.chosen.is_empty() || contents.lost_anything() {
        return Ok(Outcome::Incomplete);
    }
    Ok(Outcome::Complete)
}
