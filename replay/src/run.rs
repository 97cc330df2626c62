//! `replay LOG`: every requested method on every set of a log, the result files, the optional
//! result log and Rerun recording, and `summary.json`. The binary parses arguments and draws the
//! progress; everything else is here, so that `replay demo` and tests run the same pipeline.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use fuse::methods::{Method, Needs};
use tracing::{debug, error, info, warn};
use viz::stream::{Viewer, ViewerSink, VizError};

use crate::ReplayError;
use crate::log::LogContents;
use crate::outputs::{ResultLog, write_set_outputs_evaluating};
use crate::pipeline::{PreparedSet, RunOptions, RunSummary, SetSummary};
use crate::viewset::ViewSet;

/// Progress of one method on one set (a fraction 0 … 1); the binary draws it. Dropped when
/// the method is done.
pub trait Progress: Sync {
    /// The fraction done.
    fn set(&self, fraction: f32);
}

/// What `replay LOG` is asked to do.
pub struct RunRequest<'a> {
    /// The log.
    pub log: &'a Path,
    /// The methods, built with their overrides.
    pub methods: &'a [Box<dyn Method>],
    /// `--method` as given (for the summary).
    pub method_spec: &'a str,
    /// Disparity range, neighbours, rectification.
    pub options: RunOptions,
    /// Only these set indexes (all when empty).
    pub sets: &'a [u32],
    /// Only images logged within these seconds after the log's first message.
    pub start_secs: Option<f64>,
    /// See `start_secs`.
    pub end_secs: Option<f64>,
    /// How sets are taken from a camera stream (logs without capture events: ROS 2 bags).
    pub stream: crate::foreign::StreamOptions,
    /// Folder of the result files and `summary.json`.
    pub out: &'a Path,
    /// Which result files each set gets.
    pub outputs: crate::outputs::ResultFiles,
    /// Also write the results as an MCAP log here.
    pub out_mcap: Option<&'a Path>,
    /// Its format (default: ROS 2 for a ROS 2 bag's results, else our own log's).
    pub out_format: Option<crate::outputs::ResultFormat>,
    /// `--rerun` words (`spawn`, `save FILE.rrd`, `connect [URL]`), empty for none.
    pub rerun: &'a [String],
}

/// How a run ended.
#[derive(Debug)]
pub struct RunReport {
    /// What `summary.json` holds.
    pub summary: RunSummary,
    /// Where it was written.
    pub summary_path: PathBuf,
    /// Something was lost: a damaged log's sets, or the viewer (the binary exits 3).
    pub lost_anything: bool,
}

/// Opens the Rerun recording when `--rerun` was given.
fn open_viewer(words: &[String], set: Option<&ViewSet>, methods: &[&str]) -> Result<Option<Viewer>, VizError> {
    if words.is_empty() {
        return Ok(None);
    }
    let sink = ViewerSink::parse(words)?;
    let layout = match set {
        Some(set) => crate::viewer::layout(set, methods),
        None => viz::stream::Layout::default(),
    };
    Viewer::create("multiscopic_replay", &sink, &layout).map(Some)
}

/// The viewer of a run: errors are reported once each and the run goes on without it (its
/// files are still written; the run then ends as incomplete).
struct RunViewer {
    viewer: Option<Viewer>,
    lost: bool,
    seconds: f64,
}

impl RunViewer {
    fn open(words: &[String], set: Option<&ViewSet>, methods: &[&str]) -> Self {
        match open_viewer(words, set, methods) {
            Ok(viewer) => Self {
                viewer,
                lost: false,
                seconds: 0.0,
            },
            Err(e) => {
                error!("{e}\n  (the run goes on; its files are still written)");
                Self {
                    viewer: None,
                    lost: true,
                    seconds: 0.0,
                }
            }
        }
    }

    /// Runs `log` against the viewer when there is one, timing it.
    fn log(&mut self, what: impl FnOnce(&Viewer) -> Result<(), VizError>) {
        let Some(viewer) = &self.viewer else { return };
        let started = Instant::now();
        if let Err(e) = what(viewer) {
            error!("Rerun: {e}; the run goes on without the viewer");
            self.lost = true;
        }
        self.seconds += started.elapsed().as_secs_f64();
    }

    fn finish(&mut self, words: &[String]) {
        let Some(viewer) = self.viewer.take() else { return };
        let started = Instant::now();
        if let Err(e) = viewer.finish() {
            error!("Rerun: {e}");
            self.lost = true;
        }
        self.seconds += started.elapsed().as_secs_f64();
        if let (Some("save"), Some(path)) = (words.first().map(String::as_str), words.get(1)) {
            info!("wrote {path} (open it with `rerun {path}`)");
        }
    }
}

/// The run's identity in the result log's metadata.
fn result_log_metadata(
    request: &RunRequest<'_>,
    names: &[&str],
    configs: &[serde_json::Value],
) -> BTreeMap<String, String> {
    BTreeMap::from([
        ("tool".to_owned(), "replay".to_owned()),
        ("tool_version".to_owned(), env!("CARGO_PKG_VERSION").to_owned()),
        ("input".to_owned(), request.log.display().to_string()),
        ("method".to_owned(), names.join(",")),
        (
            "config".to_owned(),
            serde_json::Value::Array(configs.to_vec()).to_string(),
        ),
        ("rectify".to_owned(), request.options.rectify.to_string()),
    ])
}

fn report_alignment(set: &ViewSet, alignment: &crate::check::SetCheck, rectify: bool) {
    if alignment.status != crate::check::Status::Ok {
        warn!(
            "set {} alignment {:?} (see `replay check`):\n{}",
            set.index,
            alignment.status,
            crate::check::table(alignment)
        );
    }
    if rectify {
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
}

fn report_result(set: &ViewSet, method: &str, result: &crate::pipeline::MethodResult, dir: &Path) {
    if let Some(details) = result.details.as_object() {
        let pairs: Vec<String> = details
            .iter()
            .filter(|(_, v)| !v.is_null())
            .map(|(k, v)| format!("{k} {}", v.as_str().map_or_else(|| v.to_string(), str::to_owned)))
            .collect();
        info!("set {} {method}: {}", set.index, pairs.join(", "));
    }
    let head = format!("set {} ({}): {method} in {:.2} s", set.index, set.name, result.seconds);
    match result.regions.map(|r| r.all) {
        Some(m) => info!(
            "{head} — AvgErr {:.3} px, RMS {:.3}, Bad1 {:.2} % → {}",
            m.avg_err_px,
            m.rms,
            m.bad_1,
            dir.display()
        ),
        None => info!("{head} → {}", dir.display()),
    }
}

/// Reads the log, keeps the requested sets and says what a damaged log lost.
fn read_sets(request: &RunRequest<'_>) -> Result<LogContents, ReplayError> {
    let contents = crate::log::read_log_file_with(
        request.log,
        &crate::log::ReadOptions {
            start_secs: request.start_secs,
            end_secs: request.end_secs,
            stream: request.stream.clone(),
            ..crate::log::ReadOptions::default()
        },
    )?;
    for line in contents.damage() {
        warn!("{}: {line}", request.log.display());
    }
    for line in contents.notes() {
        info!("{}: {line}", request.log.display());
    }
    if contents.lost_anything() {
        warn!(
            "`replay recover {} -o FIXED.mcap` writes what survived as a finished log",
            request.log.display()
        );
    }
    Ok(contents)
}

/// Runs every method on every requested set of the log, writing the result files as it goes.
/// `progress` makes the progress of one method on one set from its description.
pub fn replay_log(
    request: &RunRequest<'_>,
    progress: &dyn Fn(&str) -> Box<dyn Progress>,
) -> Result<RunReport, ReplayError> {
    let started = Instant::now();
    let contents = read_sets(request)?;
    debug!("read the log in {:.3} s", started.elapsed().as_secs_f64());
    let sets: Vec<&ViewSet> = contents
        .sets
        .iter()
        .filter(|s| request.sets.is_empty() || request.sets.contains(&s.index))
        .collect();
    if sets.is_empty() {
        return Err(ReplayError::NoSets {
            path: request.log.to_path_buf(),
        });
    }
    let out = request.out;
    std::fs::create_dir_all(out).map_err(|source| ReplayError::Io {
        path: out.to_path_buf(),
        source,
    })?;
    let names: Vec<&str> = request.methods.iter().map(|m| m.name()).collect();
    let configs = request
        .methods
        .iter()
        .map(|m| m.config_json())
        .collect::<Result<Vec<_>, _>>()
        .map_err(ReplayError::MethodConfig)?;
    let mut viewer = RunViewer::open(request.rerun, sets.first().copied(), &names);
    let mut result_log = match request.out_mcap {
        Some(path) => Some(ResultLog::create(
            path,
            request.out_format.unwrap_or(if crate::log::is_ros2_log(request.log) {
                crate::outputs::ResultFormat::Ros2
            } else {
                crate::outputs::ResultFormat::Mcap
            }),
            &contents.metadata,
            result_log_metadata(request, &names, &configs),
        )?),
        None => None,
    };
    let mut summaries = Vec::new();
    for set in sets {
        let preparing = Instant::now();
        let prepared = PreparedSet::new(set, &request.options)?;
        debug!(
            "set {}: problem in {:.3} s",
            set.index,
            preparing.elapsed().as_secs_f64()
        );
        viewer.log(|v| crate::viewer::log_capture(v, &prepared.selected));
        viewer.log(|v| crate::viewer::log_plans(v, &prepared.selected, &contents.plans));
        viewer.log(|v| crate::viewer::log_costs(v, &prepared.selected, &prepared.problem, prepared.occluded()));
        debug!("rerun: {:.3} s so far", viewer.seconds);
        for (index, method) in request.methods.iter().enumerate() {
            let name = method.name();
            let bar = progress(&format!(
                "set {} {name} ({} neighbours, disparities {}..{})",
                set.index,
                prepared.problem.neighbours.len(),
                prepared.min_disparity,
                prepared.problem.end_disparity()
            ));
            // The confidence where something reads it: its files, the evaluation's
            // sparsification curves, the viewer, the result log.
            let needs = Needs {
                confidence: request.outputs.confidence
                    || prepared.truth().is_some()
                    || viewer.viewer.is_some()
                    || result_log.is_some(),
            };
            let run = prepared.run_unevaluated(method.as_ref(), needs, &|fraction| bar.set(fraction));
            drop(bar);
            let mut result = match run {
                Ok(result) => result,
                Err(source) => {
                    // A misaligned set may be why: say so before the error.
                    report_alignment(set, prepared.alignment(), request.options.rectify);
                    return Err(ReplayError::InSet {
                        set: set.index,
                        method: name.to_owned(),
                        source: Box::new(source),
                    });
                }
            };
            let writing = Instant::now();
            // The alignment check (made once per set) beside the files and the evaluation: it
            // says how far to trust a result, so it need not delay the first.
            let (outputs, alignment) = rayon::join(
                || {
                    write_set_outputs_evaluating(
                        out,
                        set,
                        name,
                        &result.disparity,
                        prepared.truth(),
                        request.outputs,
                        || prepared.evaluate(&result.disparity),
                    )
                },
                || prepared.alignment(),
            );
            let outputs = outputs?;
            result.regions = outputs.metrics;
            debug!(
                "set {} {name}: result files, evaluation and alignment check in {:.3} s",
                set.index,
                writing.elapsed().as_secs_f64()
            );
            if index == 0 {
                report_alignment(set, alignment, request.options.rectify);
            }
            report_result(set, name, &result, &outputs.dir);
            viewer.log(|v| {
                crate::viewer::log_result(
                    v,
                    set,
                    name,
                    &result.disparity,
                    result.regions.as_ref(),
                    prepared.alignment(),
                )
            });
            let set_summary = SetSummary {
                method: name.to_owned(),
                outputs,
                seconds: result.seconds,
                min_disparity: prepared.min_disparity,
                num_disparities: prepared.num_disparities,
                alignment: prepared.alignment().clone(),
                details: result.details.clone(),
            };
            if let Some(result_log) = result_log.as_mut() {
                result_log.write_set(set, name, &result.disparity, &serde_json::to_value(&set_summary)?)?;
            }
            summaries.push(set_summary);
        }
    }
    viewer.finish(request.rerun);
    let summary = RunSummary {
        tool: "replay",
        tool_version: env!("CARGO_PKG_VERSION"),
        log: request.log.to_path_buf(),
        method: request.method_spec.to_owned(),
        methods: names.iter().map(|m| (*m).to_owned()).collect(),
        config: match configs.as_slice() {
            [one] => one.clone(),
            _ => serde_json::Value::Array(configs),
        },
        min_disparity: request.options.min_disparity,
        sets: summaries,
        incomplete_sets: contents.incomplete_sets.clone(),
        truncation: contents.truncation.clone(),
        log_metadata: contents.metadata.clone(),
        rerun: request.rerun.to_vec(),
        rerun_seconds: viewer.seconds,
        rerun_lost: viewer.lost,
        seconds: started.elapsed().as_secs_f64(),
    };
    if let Some(result_log) = result_log {
        let path = result_log.finish()?;
        info!("wrote {}", path.display());
    }
    let summary_path = out.join("summary.json");
    std::fs::write(&summary_path, serde_json::to_string_pretty(&summary)?).map_err(|source| ReplayError::Io {
        path: summary_path.clone(),
        source,
    })?;
    info!("wrote {}", summary_path.display());
    Ok(RunReport {
        lost_anything: contents.lost_anything() || viewer.lost,
        summary,
        summary_path,
    })
}
