//! `replay`: run depth methods on the view sets of a multiscopic log, or evaluate them.
//!
//! Exit codes: 0 ok, 1 error, 2 usage, 3 finished but something was wrong or lost (a cut-off
//! log was recovered, or sets were incomplete).

mod train;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};
use record::cli::{Outcome, UsageError, exit_code, init_logging, parse_args, progress_bar};
use replay::eval::{csv, evaluate_sets, markdown};
use replay::log::read_log_file;
use replay::outputs::write_set_outputs;
use replay::viewset::ViewSet;
use tracing::{debug, error, info, warn};
use viz::stream::{Viewer, ViewerSink, VizError};

/// Run multiscopic depth methods on the view sets of an MCAP log (from `record`), write the
/// results and evaluate them against ground truth.
#[derive(Debug, Parser)]
#[command(name = "replay", version, args_conflicts_with_subcommands = true)]
#[command(
    after_help = "Examples:\n  replay capture.mcap --method sgm-heuristic --out results\n  replay --list-methods\n  replay eval ../shared/data/middlebury2006-third-dev --methods bm-stereo,bm-heuristic,sgm-stereo,sgm-heuristic"
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
    /// List the methods with one line each and exit.
    #[arg(long)]
    list_methods: bool,
    /// Only print errors.
    #[arg(short, long, global = true)]
    quiet: bool,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Evaluate methods over logs and dataset folders; prints the paper's table.
    Eval(EvalArgs),
    /// Check the alignment of every view set of a log (exit 3 when a set fails).
    Check(CheckArgs),
    /// The one-command demo: record a simulated five-view capture, replay it with the best
    /// method, write the results (and the log) into one folder.
    Demo(DemoArgs),
    /// Train MFuseNet on simulated captures (checkpoints, resume, curves); writes safetensors weights.
    Train(train::TrainArgs),
}

#[derive(Debug, Args)]
struct CheckArgs {
    /// The log to check.
    log: PathBuf,
    /// Print JSON instead of the table.
    #[arg(long)]
    json: bool,
    /// Disparities searched by the image-based shift estimate (default: as for replay).
    #[arg(long)]
    num_disparities: Option<usize>,
    /// Only images logged at least this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    start: Option<f64>,
    /// Only images logged at most this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    end: Option<f64>,
}

#[derive(Debug, Args)]
struct DemoArgs {
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

#[derive(Debug, Args)]
struct RunArgs {
    /// The log to replay.
    log: Option<PathBuf>,
    /// Method (see --list-methods); several comma-separated, or `all`.
    #[arg(long, default_value = "sgm-heuristic")]
    method: String,
    /// Method configuration overrides as a JSON object, e.g. '{"block_radius": 3}'.
    #[arg(long, value_name = "JSON")]
    config: Option<String>,
    /// Output directory for the result files.
    #[arg(long, default_value = "results")]
    out: PathBuf,
    /// Disparities searched (default: width/15 rounded up to a multiple of 16).
    #[arg(long)]
    num_disparities: Option<usize>,
    /// Smallest disparity searched.
    #[arg(long, default_value = "0")]
    min_disparity: usize,
    /// Only these sets (indexes, comma-separated).
    #[arg(long, value_delimiter = ',')]
    sets: Vec<u32>,
    /// Only images logged at least this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    start: Option<f64>,
    /// Only images logged at most this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    end: Option<f64>,
    /// Only these neighbours (roles, comma-separated), e.g. left,right for three views of a five-view set.
    #[arg(long, value_delimiter = ',')]
    neighbours: Vec<String>,
    /// Correct what the logged poses allow: de-rotate each neighbour (homography), resample its costs by its real baseline ratio.
    #[arg(long)]
    rectify: bool,
    /// Also write the results as a new MCAP log (with the input's metadata), readable by Foxglove.
    #[arg(long, value_name = "FILE")]
    out_mcap: Option<PathBuf>,
    /// Show the run in the Rerun viewer: `spawn` (start a viewer), `save FILE.rrd`, or
    /// `connect [URL]` (default rerun+http://127.0.0.1:9876/proxy).
    #[arg(long, num_args = 1..=2, value_names = ["MODE", "ARG"])]
    rerun: Vec<String>,
    /// MFuseNet weights (safetensors, e.g. from `replay train` or exported from PyTorch) instead of the shipped ones.
    #[arg(long, value_name = "FILE")]
    weights: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum TableFormat {
    Markdown,
    Csv,
    Json,
}

#[derive(Debug, Args)]
struct EvalArgs {
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
    /// Disparities searched (default: per set, width/15 rounded up to a multiple of 16).
    #[arg(long)]
    num_disparities: Option<usize>,
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
}

fn main() -> ExitCode {
    let cli: Cli = match parse_args() {
        Ok(cli) => cli,
        Err(code) => return code,
    };
    init_logging(cli.quiet);
    let result = if cli.list_methods {
        for entry in fuse::methods::registry() {
            println!("{:<16} {}", entry.name, entry.summary);
        }
        Ok(Outcome::Complete)
    } else {
        match &cli.command {
            Some(Command::Eval(args)) => run_eval(args),
            Some(Command::Demo(args)) => run_demo(args, cli.quiet),
            Some(Command::Check(args)) => run_check(args),
            Some(Command::Train(args)) => train::run(args, cli.quiet),
            None => run_method(&cli.run, cli.quiet),
        }
    };
    exit_code(result)
}

/// The methods named by `--method`: one name, a comma-separated list, or `all`.
fn methods_named(
    names: &str,
    overrides: Option<&serde_json::Value>,
    weights: Option<&Path>,
) -> Result<Vec<Box<dyn fuse::methods::Method>>> {
    let names: Vec<&str> = if names == "all" {
        fuse::methods::registry().iter().map(|e| e.name).collect()
    } else {
        names.split(',').map(str::trim).filter(|n| !n.is_empty()).collect()
    };
    if names.is_empty() {
        return Err(UsageError("--method is empty (see --list-methods)".into()).into());
    }
    names
        .into_iter()
        .map(|name| {
            let overrides = replay::eval::overrides_for(name, overrides, weights);
            fuse::methods::build(name, overrides.as_ref()).map_err(|e| match e {
                // A bad weights file is not a usage error: say which file and tensor, exit 1.
                fuse::FuseError::MFuseNet(_) => anyhow::Error::new(e),
                e => UsageError(e.to_string()).into(),
            })
        })
        .collect()
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

fn run_method(args: &RunArgs, quiet: bool) -> Result<Outcome> {
    let Some(log) = &args.log else {
        return Err(UsageError("no log given: replay LOG --method NAME (or --list-methods)".into()).into());
    };
    let overrides = match &args.config {
        Some(text) => Some(
            serde_json::from_str::<serde_json::Value>(text)
                .map_err(|e| UsageError(format!("--config is not JSON: {e}")))?,
        ),
        None => None,
    };
    let methods = methods_named(&args.method, overrides.as_ref(), args.weights.as_deref())?;
    if !args.rerun.is_empty() {
        ViewerSink::parse(&args.rerun).map_err(|e| UsageError(e.to_string()))?;
    }
    let started = Instant::now();
    let contents = replay::log::read_log_file_in(log, args.start, args.end)
        .with_context(|| format!("reading {}", log.display()))?;
    if let Some(reason) = &contents.truncation {
        warn!(
            "{} is cut off or corrupt after {} messages ({reason}); recovered {} complete set(s)",
            log.display(),
            contents.messages,
            contents.sets.len()
        );
    }
    for (set, reason) in &contents.incomplete_sets {
        warn!("set {set} is incomplete and skipped: {reason}");
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
    let mut summaries = Vec::new();
    let mut viewer_seconds = 0.0;
    for set in sets {
        let nd = args.num_disparities.unwrap_or_else(|| set.default_num_disparities());
        let alignment = replay::check::check_set(set, nd);
        if alignment.status != replay::check::Status::Ok {
            warn!(
                "set {} alignment {:?} (see `replay check`):\n{}",
                set.index,
                alignment.status,
                replay::check::table(&alignment)
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
        let selected = set.with_neighbours(&args.neighbours)?;
        let problem = selected.problem(args.min_disparity, nd, args.rectify)?;
        // Occlusions of the ground truth, once per set (metrics of every method, viewer probes).
        let occluded = set.occlusion_mask();
        if let Some(viewer) = &viewer {
            let viewer_started = Instant::now();
            if let Err(e) = replay::viewer::log_capture(viewer, &selected) {
                viewer_error(e);
            }
            debug!(
                "rerun: capture logged in {:.3} s",
                viewer_started.elapsed().as_secs_f64()
            );
            if let Err(e) = replay::viewer::log_costs(viewer, &selected, &problem, occluded.as_deref()) {
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
                "set {} {} ({} neighbours, {nd} disparities)",
                set.index,
                method.name(),
                problem.neighbours.len()
            ));
            let method_started = Instant::now();
            let disparity = method
                .run(&problem, &|fraction| progress.set_position((fraction * 100.0) as u64))
                .with_context(|| format!("set {}: {}", set.index, method.name()))?;
            let seconds = method_started.elapsed().as_secs_f64();
            progress.finish_and_clear();
            let regions = occluded
                .as_deref()
                .and_then(|mask| set.region_metrics_with(&disparity.data, nd as f64, mask));
            let metrics = regions.map(|r| r.all);
            let outputs = write_set_outputs(&args.out, set, method.name(), &disparity, regions)?;
            match &metrics {
                Some(m) => info!(
                    "set {} ({}): {} in {seconds:.2} s — AvgErr {:.3} px, RMS {:.3}, Bad1 {:.2} % → {}",
                    set.index,
                    set.name,
                    method.name(),
                    m.avg_err,
                    m.rms,
                    m.bad_1,
                    outputs.dir.display()
                ),
                None => info!(
                    "set {} ({}): {} in {seconds:.2} s → {}",
                    set.index,
                    set.name,
                    method.name(),
                    outputs.dir.display()
                ),
            }
            if let Some(viewer) = &viewer {
                let viewer_started = Instant::now();
                if let Err(e) =
                    replay::viewer::log_result(viewer, set, method.name(), &disparity, regions.as_ref(), &alignment)
                {
                    viewer_error(e);
                }
                viewer_seconds += viewer_started.elapsed().as_secs_f64();
            }
            let set_summary = serde_json::json!({
                "method": method.name(),
                "outputs": outputs,
                "seconds": seconds,
                "num_disparities": nd,
                "alignment": alignment,
            });
            if let Some(result_log) = result_log.as_mut() {
                result_log.write_set(set, method.name(), &disparity, &set_summary)?;
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
    let summary = serde_json::json!({
        "tool": "replay",
        "tool_version": env!("CARGO_PKG_VERSION"),
        "log": log,
        "method": args.method,
        "methods": method_names,
        "config": if methods.len() == 1 { methods[0].config_json() } else { serde_json::Value::Array(methods.iter().map(|m| m.config_json()).collect()) },
        "min_disparity": args.min_disparity,
        "sets": summaries,
        "incomplete_sets": contents.incomplete_sets,
        "truncation": contents.truncation,
        "log_metadata": contents.metadata,
        "rerun": args.rerun,
        "rerun_seconds": viewer_seconds,
        "rerun_lost": viewer_lost,
        "seconds": started.elapsed().as_secs_f64(),
    });
    if let Some(result_log) = result_log {
        let path = result_log.finish()?;
        info!("wrote {}", path.display());
    }
    let summary_path = args.out.join("summary.json");
    std::fs::write(&summary_path, serde_json::to_string_pretty(&summary)?)
        .with_context(|| format!("writing {}", summary_path.display()))?;
    info!("wrote {}", summary_path.display());
    if contents.truncation.is_some() || !contents.incomplete_sets.is_empty() || viewer_lost {
        return Ok(Outcome::Incomplete);
    }
    Ok(Outcome::Complete)
}

fn run_check(args: &CheckArgs) -> Result<Outcome> {
    let contents = replay::log::read_log_file_in(&args.log, args.start, args.end)
        .with_context(|| format!("reading {}", args.log.display()))?;
    let checks: Vec<replay::check::SetCheck> = contents
        .sets
        .iter()
        .map(|set| {
            replay::check::check_set(
                set,
                args.num_disparities.unwrap_or_else(|| set.default_num_disparities()),
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
    if failed > 0 || contents.truncation.is_some() || !contents.incomplete_sets.is_empty() {
        if failed > 0 {
            warn!("{failed} of {} set(s) failed the alignment check", checks.len());
        }
        return Ok(Outcome::Incomplete);
    }
    Ok(Outcome::Complete)
}

fn run_demo(args: &DemoArgs, quiet: bool) -> Result<Outcome> {
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
    let outcome = run_method(
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

fn read_inputs(inputs: &[PathBuf]) -> Result<Vec<ViewSet>> {
    let mut sets = Vec::new();
    for input in inputs {
        if input.is_dir() {
            sets.extend(
                replay::dataset::read_dataset(input).with_context(|| format!("reading dataset {}", input.display()))?,
            );
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

fn run_eval(args: &EvalArgs) -> Result<Outcome> {
    for name in &args.methods {
        if !fuse::methods::registry().iter().any(|e| e.name == name) {
            return Err(UsageError(format!("unknown method '{name}' (see --list-methods)")).into());
        }
    }
    let overrides = match &args.config {
        Some(text) => Some(
            serde_json::from_str::<serde_json::Value>(text)
                .map_err(|e| UsageError(format!("--config is not JSON: {e}")))?,
        ),
        None => None,
    };
    let sets = read_inputs(&args.inputs)?;
    let with_truth = sets.iter().filter(|s| s.ground_truth_depth_m.is_some()).count();
    if with_truth == 0 {
        anyhow::bail!("none of the {} view sets has ground truth", sets.len());
    }
    let progress = progress_bar((args.methods.len() * with_truth) as u64, false, "runs");
    let options = replay::eval::EvalOptions {
        num_disparities: args.num_disparities,
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
