//! `replay demo`: the one-command demo (record a simulated capture, replay it, view it).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use record::cli::{Outcome, progress_bar};
use tracing::info;

use crate::run::RunArgs;

/// Arguments of `replay demo`.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output folder (the log goes to OUT/capture.mcap, results beside it).
    #[arg(long, default_value = "demo")]
    out: PathBuf,
    /// Methods (comma-separated, or `all`); the results of each are written and shown.
    #[arg(long, default_value = "all")]
    method: String,
    /// Where the Rerun recording goes: `save FILE.rrd` (default: OUT/demo.rrd), `spawn`, or
    /// `connect [URL]`.
    #[arg(long, num_args = 1..=2, value_names = ["MODE", "ARG"])]
    rerun: Vec<String>,
    /// Scene.
    #[arg(long, value_enum, default_value = "toy")]
    scene: record::scene::SceneKind,
    /// Rig layout.
    #[arg(long, value_enum, default_value = "five-view")]
    rig: record::rig::RigKind,
    /// Seed.
    #[arg(long, default_value = "0")]
    seed: u64,
}

/// Runs `replay demo`.
pub fn run(args: &DemoArgs, quiet: bool) -> Result<Outcome> {
    let config = record::capture::SimulationConfig {
        scene: args.scene,
        rig: args.rig,
        seed: args.seed,
        ..record::capture::SimulationConfig::default()
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let log = args.out.join("capture.mcap");
    let mut sim = record::capture::Simulation::new(config.clone())?;
    let views = config.rig.capture_order().len() as u64 * u64::from(config.captures);
    let progress = progress_bar(views, quiet, "views");
    info!(
        "recording a simulated {} capture of the {} scene → {}",
        config.rig.name(),
        config.scene_name(),
        log.display()
    );
    let stop = std::sync::atomic::AtomicBool::new(false);
    let mut log_layout = None;
    let recorded = record::session::record_simulation(
        &mut sim,
        &log,
        record::log::DEFAULT_ZSTD_LEVEL,
        &stop,
        |set, view| {
            progress.set_message(format!("rendering set {set} view {}", view.role));
            progress.inc(1);
        },
        |set| {
            log_layout.get_or_insert_with(|| record::live::log_layout(set));
        },
    )?;
    progress.finish_and_clear();
    if recorded.path.is_none() {
        anyhow::bail!("the recording produced no complete set");
    }
    // The capture's own layout, for `rerun demo/capture.mcap demo/capture.rbl`.
    let layout_lost = log_layout.is_some_and(|layout| !record::cli::write_log_layout(&log, &layout));
    let outcome = crate::run::run(
        &RunArgs {
            log: Some(log),
            method: args.method.clone(),
            config: None,
            out: args.out.join("results"),
            num_disparities: None,
            min_disparity: 0,
            sets: Vec::new(),
            start: None,
            end: None,
            neighbours: Vec::new(),
            rectify: true,
            out_mcap: None,
            weights: None,
            rerun: if args.rerun.is_empty() {
                vec!["save".to_owned(), args.out.join("demo.rrd").display().to_string()]
            } else {
                args.rerun.clone()
            },
        },
        quiet,
    )?;
    Ok(if layout_lost { Outcome::Incomplete } else { outcome })
}

