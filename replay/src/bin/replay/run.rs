//! `replay LOG --method …`: run methods on the sets of a log, write and show the results.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use record::cli::{Outcome, UsageError, progress_bar};
use replay::outputs::write_set_outputs;
use replay::pipeline::{PreparedSet, RunOptions, RunSummary, SetSummary};
use replay::viewset::ViewSet;
use tracing::{debug, error, info, warn};
use viz::stream::{Viewer, ViewerSink, VizError};

/// Arguments of `replay LOG`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// The log to replay.
    pub(crate) log: Option<PathBuf>,
    /// Method (see --list-methods); several comma-separated, or `all`.
    #[arg(long, default_value = "sgm-heuristic")]
    pub(crate) method: String,
    /// Method configuration overrides as a JSON object, e.g. '{"block_radius": 3}'.
    #[arg(long, value_name = "JSON")]
    pub(crate) config: Option<String>,
    /// Output directory for the result files.
    #[arg(long, default_value = "results")]
    pub(crate) out: PathBuf,
    /// Disparities searched (default: the log's range for the set, else width/15 rounded up to
    /// a multiple of 16); at most 1024.
    #[arg(long)]
    pub(crate) num_disparities: Option<usize>,
    /// Smallest disparity searched, signed: negative for a converged rig, whose points beyond
    /// the distance its views converge at shift the other way (default: the log's range for the
    /// set, else 0), e.g. --min-disparity -8.
    #[arg(long, value_name = "PX", allow_hyphen_values = true)]
    pub(crate) min_disparity: Option<i32>,
    /// Only these sets (indexes, comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub(crate) sets: Vec<u32>,
    /// Only images logged at least this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    pub(crate) start: Option<f64>,
    /// Only images logged at most this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    pub(crate) end: Option<f64>,
    /// Only these neighbours (roles, comma-separated), e.g. left,right for three views of a five-view set.
    #[arg(long, value_delimiter = ',')]
    pub(crate) neighbours: Vec<String>,
    /// Correct what the logged poses allow: de-rotate each neighbour (homography), resample its costs by its real baseline ratio.
    #[arg(long)]
    pub(crate) rectify: bool,
    /// Also write the results as a new MCAP log (with the input's metadata), readable by Foxglove.
    #[arg(long, value_name = "FILE")]
    pub(crate) out_mcap: Option<PathBuf>,
    /// Show the run in the Rerun viewer: `spawn` (start a viewer), `save FILE.rrd`, or
    /// `connect [URL]` (default rerun+http://127.0.0.1:9876/proxy).
    #[arg(long, num_args = 1..=2, value_names = ["MODE", "ARG"])]
    pub(crate) rerun: Vec<String>,
    /// MFuseNet weights (safetensors, e.g. from `replay train` or exported from PyTorch) instead of the shipped ones.
    #[arg(long, value_name = "FILE")]
    pub(crate) weights: Option<PathBuf>,
}

/// Opens the Rerun recording when `--rerun` was given. A viewer that cannot be started or a file
/// that cannot be written is reported and the run goes on without it (its other outputs are
/// still written; the exit code is then 3).
fn open_viewer(words: &[String], set: Option<&ViewSet>, methods: &[&str]) -> Result<Option<Viewer>, VizError> {
    if words.is_empty() {
        return Ok(None);
    }
    let sink = ViewerSink::parse(words)?;
    let layout = match set {
        Some(set) => replay::viewer::layout(set, methods),
        None => viz::stream::Layout::default(),
    };
    Viewer::create("multiscopic_replay", &sink, &layout).map(Some)
}

/// Runs `replay LOG`.
pub fn run(args: &RunArgs, quiet: bool) -> Result<Outcome> {
    let Some(log) = &args.log else {
        return Err(UsageError("no log given: replay LOG --method NAME (or --list-methods)".into()).into());
    };
    let overrides = crate::parse_overrides(args.config.as_deref())?;
    let methods = crate::build_methods(&args.method, overrides.as_ref(), args.weights.as_deref())?;
    if !args.rerun.is_empty() {
        ViewerSink::parse(&args.rerun).map_err(|e| UsageError(e.to_string()))?;
    }
    let started = Instant::now();
    let contents = replay::log::read_log_file_in(log, args.start, args.end)
        .with_context(|| format!("reading {}", log.display()))?;
    for line in contents.damage() {
        warn!("{}: {line}", log.display());
    }
    if contents.lost_anything() {
        warn!(
            "`replay recover {} -o FIXED.mcap` writes what survived as a finished log",
            log.display()
        );
    }
    let sets: Vec<&ViewSet> = contents
        .sets
        .iter()
        .filter(|s| args.sets.is_empty() || args.sets.contains(&s.index))
        .collect();
    if sets.is_empty() {
        anyhow::bail!("{} holds no complete view set to replay", log.display());
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let method_names: Vec<&str> = methods.iter().map(|m| m.name()).collect();
    let mut viewer_lost = false;
    let viewer = match open_viewer(&args.rerun, sets.first().copied(), &method_names) {
        Ok(viewer) => viewer,
        Err(error) => {
            error!("{error}\n  (the run goes on; its files are still written)");
            viewer_lost = true;
            None
        }
    };
    let mut result_log = match &args.out_mcap {
        Some(path) => {
            let mut run = std::collections::BTreeMap::new();
            run.insert("tool".to_owned(), "replay".to_owned());
            run.insert("tool_version".to_owned(), env!("CARGO_PKG_VERSION").to_owned());
            run.insert("input".to_owned(), log.display().to_string());
            run.insert("method".to_owned(), method_names.join(","));
            run.insert(
                "config".to_owned(),
                serde_json::Value::Array(methods.iter().map(|m| m.config_json()).collect()).to_string(),
            );
            run.insert("rectify".to_owned(), args.rectify.to_string());
            Some(
                replay::outputs::ResultLog::create(path, &contents.metadata, run)
                    .with_context(|| format!("starting {}", path.display()))?,
            )
        }
        None => None,
    };
    let mut viewer_error = |error: VizError| {
        error!("Rerun: {error}; the run goes on without the viewer");
        viewer_lost = true;
    };
    let options = RunOptions {
        num_disparities: args.num_disparities,
        min_disparity: args.min_disparity,
        neighbours: args.neighbours.clone(),
        rectify: args.rectify,
    };
    let mut summaries = Vec::new();
    let mut viewer_seconds = 0.0;
    for set in sets {
        let prepared = PreparedSet::new(set, &options)?;
        let (alignment, nd) = (&prepared.alignment, prepared.num_disparities);
        if alignment.status != replay::check::Status::Ok {
            warn!(
                "set {} alignment {:?} (see `replay check`):\n{}",
                set.index,
                alignment.status,
                replay::check::table(alignment)
            );
        }
        if args.rectify {
            for (n, checked) in set.neighbours.iter().zip(&alignment.neighbours) {
                info!(
                    "rectify {}: de-rotated by {:.3}°, costs resampled by baseline ratio {:.4}; cannot correct {:.3} mm out of plane",
                    n.role,
                    checked.rotation_deg.value,
                    set.baseline_ratio(n),
                    checked.out_of_plane_mm.value
                );
            }
        }
        if let Some(viewer) = &viewer {
            let viewer_started = Instant::now();
            if let Err(e) = replay::viewer::log_capture(viewer, &prepared.selected) {
                viewer_error(e);
            }
            if let Err(e) = replay::viewer::log_costs(
                viewer,
                &prepared.selected,
                &prepared.problem,
                prepared.occluded.as_deref(),
            ) {
                viewer_error(e);
            }
            debug!(
                "rerun: capture and costs logged in {:.3} s",
                viewer_started.elapsed().as_secs_f64()
            );
            viewer_seconds += viewer_started.elapsed().as_secs_f64();
        }
        for method in &methods {
            let progress = progress_bar(100, quiet, "%");
            progress.set_message(format!(
                "set {} {} ({} neighbours, disparities {}..{})",
                set.index,
                method.name(),
                prepared.problem.neighbours.len(),
                prepared.min_disparity,
                prepared.problem.end_disparity()
            ));
            let result = prepared
                .run(method.as_ref(), &|fraction| {
                    progress.set_position((fraction * 100.0) as u64)
                })
                .with_context(|| format!("set {}: {}", set.index, method.name()))?;
            progress.finish_and_clear();
            if let Some(details) = result.details.as_object() {
                let pairs: Vec<String> = details
                    .iter()
                    .filter(|(_, v)| !v.is_null())
                    .map(|(k, v)| format!("{k} {}", v.as_str().map_or_else(|| v.to_string(), str::to_owned)))
                    .collect();
                info!("set {} {}: {}", set.index, method.name(), pairs.join(", "));
            }
            let outputs = write_set_outputs(&args.out, set, method.name(), &result.disparity, result.regions)?;
            match result.regions.map(|r| r.all) {
                Some(m) => info!(
                    "set {} ({}): {} in {:.2} s — AvgErr {:.3} px, RMS {:.3}, Bad1 {:.2} % → {}",
                    set.index,
                    set.name,
                    method.name(),
                    result.seconds,
                    m.avg_err,
                    m.rms,
                    m.bad_1,
                    outputs.dir.display()
                ),
                None => info!(
                    "set {} ({}): {} in {:.2} s → {}",
                    set.index,
                    set.name,
                    method.name(),
                    result.seconds,
                    outputs.dir.display()
                ),
            }
            if let Some(viewer) = &viewer {
                let viewer_started = Instant::now();
                if let Err(e) = replay::viewer::log_result(
                    viewer,
                    set,
                    method.name(),
                    &result.disparity,
                    result.regions.as_ref(),
                    alignment,
                ) {
                    viewer_error(e);
                }
                viewer_seconds += viewer_started.elapsed().as_secs_f64();
            }
            let set_summary = SetSummary {
                method: method.name().to_owned(),
                outputs,
                seconds: result.seconds,
                min_disparity: prepared.min_disparity,
                num_disparities: nd,
                alignment: alignment.clone(),
                details: result.details.clone(),
            };
            if let Some(result_log) = result_log.as_mut() {
                result_log.write_set(
                    set,
                    method.name(),
                    &result.disparity,
                    &serde_json::to_value(&set_summary)?,
                )?;
            }
            summaries.push(set_summary);
        }
    }
    if let Some(viewer) = viewer {
        let viewer_started = Instant::now();
        if let Err(e) = viewer.finish() {
            viewer_error(e);
        }
        viewer_seconds += viewer_started.elapsed().as_secs_f64();
        if let Some(path) = args.rerun.get(1).filter(|_| args.rerun[0] == "save") {
            info!("wrote {path} (open it with `rerun {path}`)");
        }
    }
    let summary = RunSummary {
        tool: "replay",
        tool_version: env!("CARGO_PKG_VERSION"),
        log: log.clone(),
        method: args.method.clone(),
        methods: method_names.iter().map(|m| (*m).to_owned()).collect(),
        config: if methods.len() == 1 {
            methods[0].config_json()
        } else {
            serde_json::Value::Array(methods.iter().map(|m| m.config_json()).collect())
        },
        min_disparity: args.min_disparity,
        sets: summaries,
        incomplete_sets: contents.incomplete_sets.clone(),
        truncation: contents.truncation.clone(),
        log_metadata: contents.metadata.clone(),
        rerun: args.rerun.clone(),
        rerun_seconds: viewer_seconds,
        rerun_lost: viewer_lost,
        seconds: started.elapsed().as_secs_f64(),
    };
    if let Some(result_log) = result_log {
        let path = result_log.finish()?;
        info!("wrote {}", path.display());
    }
    let summary_path = args.out.join("summary.json");
    std::fs::write(&summary_path, serde_json::to_string_pretty(&summary)?)
        .with_context(|| format!("writing {}", summary_path.display()))?;
    info!("wrote {}", summary_path.display());
    if contents.lost_anything() || viewer_lost {
        return Ok(Outcome::Incomplete);
    }
    Ok(Outcome::Complete)
}
