//! `replay demo`: the one-command demo (record a simulated capture, replay it, view it).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use record::cli::{Outcome, UsageError, progress_bar};
use tracing::info;

use crate::run::RunArgs;

/// The demo's default methods: every family, graph cuts by its heuristic member only.
const DEMO_METHODS: &str = "bm-stereo,bm-mean,bm-min,bm-heuristic,sgm-stereo,sgm-mean,sgm-min,sgm-heuristic,gc-heuristic,mfusenet-stereo,mfusenet";

/// Arguments of `replay demo`.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output folder (the log goes to OUT/capture.mcap, results beside it). The demo writes a
    /// `.gitignore` (`*`) into it, so that its ≈ 400 MB never show up as work in a repository.
    #[arg(long, default_value = "demo")]
    out: PathBuf,
    /// Methods (comma-separated, or `all`); the results of each are written and shown. The
    /// default is every method but `gc-stereo`, `gc-mean` and `gc-min` (about 10 s each here),
    /// so that the demo stays within 90 s; `all` runs them too.
    #[arg(long, default_value = DEMO_METHODS)]
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
    /// Image size, WxH (960x540 keeps the whole demo, MFuseNet included, near a minute).
    #[arg(long, default_value = "960x540")]
    resolution: String,
}

/// Writes `DIR/.gitignore` ignoring everything in `DIR` (as Cargo does for `target/`), unless the
/// folder already has one: the demo's outputs are results, never work to commit.
fn ignore_in_git(dir: &std::path::Path) -> Result<()> {
    let path = dir.join(".gitignore");
    if !path.exists() {
        std::fs::write(
            &path,
            "# Written by `replay demo`: its outputs are results, not sources.\n*\n",
        )
        .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Runs `replay demo`.
pub fn run(args: &DemoArgs, quiet: bool) -> Result<Outcome> {
    let (width, height) = args
        .resolution
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
        .ok_or_else(|| UsageError(format!("--resolution {}: expected WxH, e.g. 960x540", args.resolution)))?;
    let config = record::capture::SimulationConfig {
        scene: args.scene,
        rig: args.rig,
        seed: args.seed,
        width,
        height,
        ..record::capture::SimulationConfig::default()
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    ignore_in_git(&args.out)?;
    let log = args.out.join("capture.mcap");
    let mut sim = record::capture::Simulation::new(config.clone()).map_err(|e| UsageError(e.to_string()))?;
    let range = sim.working_disparity_range();
    let (min_disparity, num_disparities) = (range.min_disparity, range.num_disparities.unwrap_or(16) as usize);
    info!(
        "disparities {min_disparity}..{} px from the working depth (table at {:.2} m, objects up to {:.2} m above it)",
        min_disparity + num_disparities as i32,
        sim.scene().camera_height_m,
        sim.scene().highest_point_m()
    );
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
    info!(
        "outputs go to {} (git-ignored through {})",
        args.out.display(),
        args.out.join(".gitignore").display()
    );
    let outcome = crate::run::run(
        &RunArgs {
            log: Some(log),
            method: args.method.clone(),
            config: None,
            out: args.out.join("results"),
            num_disparities: Some(num_disparities),
            min_disparity: Some(min_disparity),
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
