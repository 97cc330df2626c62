//! `replay demo`: the one-command demo (record a simulated capture, replay it, view it).

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use cli::{Outcome, UsageError, progress_bar, report_log_layout};

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
    /// Next-best-view capture (`--rig adaptive`): the centre, then each of 4 more views where a
    /// plan from MFuseNet's depth so far says it resolves most; the plans go into the log and
    /// the recording (candidate frusta coloured by score).
    #[arg(long, conflicts_with = "rig")]
    adaptive: bool,
    /// Seed.
    #[arg(long, default_value = "0")]
    seed: u64,
    /// Image size, WxH (960x540 keeps the whole demo, MFuseNet included, near a minute).
    #[arg(long, default_value = "960x540")]
    resolution: String,
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
        rig: if args.adaptive {
            record::rig::RigKind::Adaptive
        } else {
            args.rig
        },
        seed: args.seed,
        width,
        height,
        ..record::capture::SimulationConfig::default()
    };
    let views = u64::from(config.views_per_set()) * u64::from(config.captures);
    let progress = progress_bar(views, quiet, "views");
    let capture = replay::demo::record_capture(config, &args.out, |set, role| {
        progress.set_message(format!("rendering set {set} view {role}"));
        progress.inc(1);
    })
    .map_err(|e| match e {
        replay::demo::DemoError::Config(_) => UsageError(format!("{e:#}")).into(),
        e => anyhow::Error::new(e),
    })?;
    progress.finish_and_clear();
    // The capture's own layout, for `rerun OUT/capture.mcap OUT/capture.rbl`.
    let layout_lost = capture.layout.as_ref().is_some_and(|layout| {
        !report_log_layout(&capture.log, record::live::write_log_blueprint(&capture.log, layout))
    });
    let rerun = if args.rerun.is_empty() {
        vec!["save".to_owned(), args.out.join("demo.rrd").display().to_string()]
    } else {
        args.rerun.clone()
    };
    let outcome = crate::run::run(
        &RunArgs {
            log: Some(capture.log),
            method: args.method.clone(),
            config: None,
            out: args.out.join("results"),
            outputs: replay::outputs::ResultFiles::ALL,
            // Each set's logged working range.
            num_disparities: None,
            min_disparity: None,
            sets: Vec::new(),
            start: None,
            end: None,
            neighbours: Vec::new(),
            rectify: true,
            out_mcap: None,
            out_format: None,
            weights: None,
            rerun,
            stream: crate::info::StreamArgs {
                image_topic: None,
                base_frame: None,
                station_frame: replay::foreign::StationFrame::Middle,
            },
        },
        quiet,
    )?;
    Ok(if layout_lost { Outcome::Incomplete } else { outcome })
}
