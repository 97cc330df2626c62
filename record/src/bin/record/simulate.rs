//! `record [OPTIONS]`: a simulated UR10 capture into a log, optionally watched in Rerun.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use cli::{Outcome, UsageError, interrupt_flag, progress_bar, report_log_layout};
use record::capture::{Simulation, SimulationError};
use record::live::{LiveCapture, log_layout};
use record::session::record_simulation;
use tracing::{error, info, warn};
use viz::stream::ViewerSink;

use crate::options::{SimulateArgs, simulation_config};

/// Runs `record`.
pub fn run(args: &SimulateArgs, quiet: bool) -> Result<Outcome> {
    let started = Instant::now();
    let config = simulation_config(args);
    let mut sim = Simulation::new(config.clone()).map_err(|e| match e {
        SimulationError::InvalidConfig { .. } | SimulationError::UnknownRole { .. } => {
            anyhow::Error::new(UsageError(e.to_string()))
        }
        other => anyhow::Error::new(other),
    })?;
    let stop = interrupt_flag(
        "interrupt: finishing the log with the sets completed so far (interrupt again to abort)",
        "aborted: no log written",
    );
    let views_per_set = u64::from(config.views_per_set());
    let bar = progress_bar(u64::from(config.captures) * views_per_set, quiet, "views");
    info!(
        "recording {} {} set(s) of the {} scene at {}x{}, baseline {} mm → {}",
        config.captures,
        config.rig.name(),
        config.scene_name(),
        config.width,
        config.height,
        config.baseline_mm,
        args.output.display()
    );
    let mut viewer_lost = false;
    let viewer = if args.rerun.is_empty() {
        None
    } else {
        let sink = ViewerSink::parse(&args.rerun).map_err(|e| UsageError(e.to_string()))?;
        let roles = config.rig.capture_order().iter().map(|s| s.role.to_owned()).collect();
        LiveCapture::open(&sink, roles, sim.arm().clone())
            .inspect_err(|e| {
                error!("Rerun: {e}\n  (the recording goes on; the log is still written)");
                viewer_lost = true;
            })
            .ok()
    };
    let viewer_error = std::cell::Cell::new(None::<viz::stream::VizError>);
    let camera = *sim.camera();
    let mut layout_of_log = None;
    let output = record::session::Output {
        path: args.output.clone(),
        format: args.format,
        zstd_level: args.zstd_level,
    };
    let outcome = record_simulation(
        &mut sim,
        &output,
        &stop,
        |set, view| {
            bar.set_message(format!("set {set} {}", view.role));
            bar.inc(1);
            if let Some(live) = &viewer
                && let Err(e) = live.view(view)
            {
                viewer_error.set(Some(e));
            }
        },
        |step, estimate| {
            bar.suspend(|| info!("{}", step.summary()));
            if let Some(live) = &viewer
                && let Err(e) = live.plan(step, estimate, &camera, config.baseline_mm / 1000.0)
            {
                viewer_error.set(Some(e));
            }
        },
        |set| {
            layout_of_log.get_or_insert_with(|| log_layout(set));
            bar.suspend(|| {
                info!(
                    "set {}/{} done ({} views)",
                    set.index + 1,
                    config.captures,
                    set.views.len()
                )
            });
            if let Some(live) = &viewer
                && let Err(e) = live.motion(set)
            {
                viewer_error.set(Some(e));
            }
        },
    )
    .with_context(|| format!("recording {}", args.output.display()))?;
    if let Some(live) = viewer
        && let Err(e) = live.finish()
    {
        viewer_error.set(Some(e));
    }
    if let Some(e) = viewer_error.take() {
        error!("Rerun: {e}");
        viewer_lost = true;
    }
    bar.finish_and_clear();
    let Some(path) = &outcome.path else {
        eprintln!("interrupted before the first set was complete: no log written");
        return Ok(Outcome::Incomplete);
    };
    report(path, outcome.completed_sets, started);
    // A bag's topics are ROS ones: the layout of our own log does not fit it.
    if !args.no_blueprint
        && args.format == record::session::LogFormat::Mcap
        && let Some(layout) = &layout_of_log
        && !report_log_layout(path, record::live::write_log_blueprint(path, layout))
    {
        viewer_lost = true;
    }
    if outcome.interrupted() {
        warn!(
            "interrupted: the log holds {} of {} requested sets",
            outcome.completed_sets, outcome.requested_sets
        );
        return Ok(Outcome::Incomplete);
    }
    if viewer_lost {
        return Ok(Outcome::Incomplete);
    }
    Ok(Outcome::Complete)
}

/// Logs what was written.
pub(crate) fn report(path: &Path, sets: u32, started: Instant) {
    // A bag directory's size is its files'.
    let size = match std::fs::read_dir(path) {
        Ok(entries) => entries
            .filter_map(Result::ok)
            .filter_map(|e| e.metadata().ok())
            .map(|m| m.len())
            .sum(),
        Err(_) => std::fs::metadata(path).map(|m| m.len()).unwrap_or(0),
    };
    info!(
        "wrote {} ({:.1} MB, {} set(s)) in {:.1} s",
        path.display(),
        size as f64 / 1e6,
        sets,
        started.elapsed().as_secs_f64()
    );
}
