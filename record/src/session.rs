//! A whole recording to a file: for a simulation, the scene attachment, the sets as they
//! complete, the metadata with the effective configuration, and the atomic commit
//! ([`record_simulation`], used by `record` and `replay demo`); for an import, every set read
//! before the log is started, so that a bad file leaves nothing behind ([`record_import`]).

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use crate::adaptive::PlanStep;
use crate::bag::BagWriter;
use crate::capture::{Simulation, SimulationError};
use crate::log::{
    CAPTURE_PLAN_SCHEMA, CAPTURE_PLAN_TOPIC, LogError, LogOptions, LogWriter, METADATA_NAME, OutputFile, PoseJson,
    SyncedWriter,
};
use crate::rig::RigKind;
use crate::{CapturedSet, CapturedView, TOOL_VERSION};

/// Errors of a recording.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The simulation failed (e.g. an unreachable pose).
    #[error(transparent)]
    Simulation(#[from] SimulationError),
    /// Writing the log failed.
    #[error(transparent)]
    Log(#[from] LogError),
    /// Writing failed (a full disk, a file-size limit, an I/O error) after some sets were safe.
    #[error(
        "writing the log failed while {stage}; {safe_sets} complete set(s) were synced to disk before that and are kept in '{kept}' (`replay recover` finishes it)"
    )]
    WriteFailed {
        /// What was being written.
        stage: String,
        /// Sets completely written and synced.
        safe_sets: u32,
        /// The temporary file left in place.
        kept: PathBuf,
        /// Cause.
        #[source]
        source: LogError,
    },
    /// Reading an image set to import failed.
    #[error("importing '{}'", dir.display())]
    Import {
        /// The set's folder.
        dir: PathBuf,
        /// Cause.
        #[source]
        source: Box<crate::import::ImportError>,
    },
    /// Planning an import failed (the folder, its description or the flags).
    #[error(transparent)]
    Plan(Box<crate::import::ImportError>),
    /// Serialising the configuration or scene failed.
    #[error("cannot serialise {what}")]
    Json {
        /// What.
        what: &'static str,
        /// Cause.
        #[source]
        source: serde_json::Error,
    },
}

/// What a recording produced.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordingOutcome {
    /// The finished log (`None` when stopped before the first set was complete: no file).
    pub path: Option<PathBuf>,
    /// Sets in the log.
    pub completed_sets: u32,
    /// Sets asked for.
    pub requested_sets: u32,
}

impl RecordingOutcome {
    /// Whether the recording stopped early.
    pub fn interrupted(&self) -> bool {
        self.completed_sets < self.requested_sets
    }
}

fn json<T: serde::Serialize>(what: &'static str, value: &T) -> Result<String, SessionError> {
    serde_json::to_string(value).map_err(|source| SessionError::Json { what, source })
}

/// What a recording writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LogFormat {
    /// Our own log: one MCAP file with Foxglove schemas (the format documented in ARCHITECTURE.md).
    #[default]
    Mcap,
    /// A ROS 2 bag (`record::bag`): a directory `NAME/` with `NAME_0.mcap` and `metadata.yaml`,
    /// or, when the output ends in `.mcap`, that one file with the `ros2` profile.
    Ros2,
}

/// Where a recording goes and how it is written.
#[derive(Debug, Clone)]
pub struct Output {
    /// The log file, or the bag directory.
    pub path: PathBuf,
    /// The format.
    pub format: LogFormat,
    /// Chunk compression level.
    pub zstd_level: u32,
}

impl Output {
    /// Our own log at `path`, chunks at the default zstd level.
    pub fn mcap(path: &Path) -> Self {
        Self {
            path: path.to_path_buf(),
            format: LogFormat::Mcap,
            zstd_level: crate::log::DEFAULT_ZSTD_LEVEL,
        }
    }

    /// The bag directory, when the output is one (a ROS 2 bag not named `*.mcap`).
    fn bag_directory(&self) -> Option<&Path> {
        (self.format == LogFormat::Ros2 && self.path.extension().is_none_or(|e| e != "mcap")).then_some(&self.path)
    }

    /// The MCAP file written: the output itself, or `NAME/NAME_0.mcap` in a bag directory.
    pub fn mcap_file(&self) -> PathBuf {
        match self.bag_directory() {
            Some(dir) => {
                let name = dir
                    .file_name()
                    .map_or_else(|| "bag".into(), |n| n.to_string_lossy().into_owned());
                dir.join(format!("{name}_0.mcap"))
            }
            None => self.path.clone(),
        }
    }
}

/// A log of either format being written.
enum SetWriter {
    Log(Box<LogWriter<SyncedWriter>>),
    Bag(Box<BagWriter<SyncedWriter>>),
}

impl SetWriter {
    fn write_set(
        &mut self,
        set: &CapturedSet,
        flange_from_camera: Option<&nalgebra::Isometry3<f64>>,
    ) -> Result<(), LogError> {
        match self {
            Self::Log(log) => log.write_set(set, flange_from_camera),
            Self::Bag(bag) => bag.write_set(set, flange_from_camera),
        }
    }

    fn write_metadata(&mut self, name: &str, metadata: BTreeMap<String, String>) -> Result<(), LogError> {
        match self {
            Self::Log(log) => log.write_metadata(name, metadata),
            Self::Bag(bag) => bag.write_metadata(name, metadata),
        }
    }

    fn attach(&mut self, name: &str, media_type: &str, log_time: u64, data: &[u8]) -> Result<(), LogError> {
        match self {
            Self::Log(log) => log.attach(name, media_type, log_time, data),
            Self::Bag(bag) => bag.attach(name, media_type, log_time, data),
        }
    }

    fn write_plan(&mut self, step: &PlanStep) -> Result<(), LogError> {
        let value = serde_json::to_value(step).map_err(|e| LogError::Encode {
            topic: CAPTURE_PLAN_TOPIC.into(),
            reason: e.to_string(),
        })?;
        match self {
            Self::Log(log) => log.write_json(CAPTURE_PLAN_TOPIC, CAPTURE_PLAN_SCHEMA, step.time_nanos, &value),
            Self::Bag(bag) => bag.write_json(CAPTURE_PLAN_TOPIC, step.time_nanos, &value),
        }
    }

    fn finish(self) -> Result<(SyncedWriter, Option<ros2::bag::BagInfo>), LogError> {
        match self {
            Self::Log(log) => Ok((log.finish()?, None)),
            Self::Bag(bag) => bag.finish().map(|(writer, info)| (writer, Some(info))),
        }
    }
}

/// Creates the output (the bag directory first, for a bag) and starts its writer.
fn open_output(output: &Output, options: LogOptions) -> Result<(OutputFile, SetWriter), LogError> {
    if let Some(dir) = output.bag_directory() {
        std::fs::create_dir_all(dir).map_err(|source| LogError::Io {
            action: "cannot create the bag directory",
            path: dir.to_path_buf(),
            source,
        })?;
    }
    let path = output.mcap_file();
    let (file, writer) = OutputFile::create(&path)?;
    let writer = match output.format {
        LogFormat::Mcap => SetWriter::Log(Box::new(options.create(writer)?)),
        LogFormat::Ros2 => {
            let name = path
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
            SetWriter::Bag(Box::new(BagWriter::create(options, &name, writer)?))
        }
    };
    Ok((file, writer))
}

/// Commits the finished file; for a bag directory also writes its `metadata.yaml` (atomically,
/// after the file it lists). Returns the output's path.
fn commit_output(
    output: &Output,
    file: OutputFile,
    (writer, info): (SyncedWriter, Option<ros2::bag::BagInfo>),
) -> Result<PathBuf, LogError> {
    let path = file.commit(writer)?;
    match (output.bag_directory(), info) {
        (Some(dir), Some(info)) => {
            let (metadata, mut writer) = OutputFile::create(&dir.join(ros2::bag::METADATA_FILE))?;
            writer
                .write_all(info.to_yaml().as_bytes())
                .map_err(|source| LogError::Io {
                    action: "cannot write",
                    path: metadata.temp_path().to_path_buf(),
                    source,
                })?;
            metadata.commit(writer)?;
            Ok(dir.to_path_buf())
        }
        _ => Ok(path),
    }
}

/// Records every set of `sim` into `output` (written under a temporary name, renamed when
/// finished). When `stop` is raised, the log is finished with the sets completed so far.
/// `on_view(set, view)` follows every view; `on_plan(step, estimate)` every plan of an adaptive
/// set (with the estimate it was planned from); `on_set(set)` every completed set (with the
/// arm's motion samples). An adaptive set's plans are written to
/// [`crate::log::CAPTURE_PLAN_TOPIC`] with the set.
pub fn record_simulation(
    sim: &mut Simulation,
    output: &Output,
    stop: &AtomicBool,
    mut on_view: impl FnMut(u32, &CapturedView),
    mut on_plan: impl FnMut(&PlanStep, Option<&fuse::DisparityImage>),
    mut on_set: impl FnMut(&CapturedSet),
) -> Result<RecordingOutcome, SessionError> {
    let config = sim.config().clone();
    let options = LogOptions::new()
        .image_format(config.image_format)
        .zstd_level(output.zstd_level);
    let (file, mut log) = open_output(output, options)?;
    let scene =
        serde_json::to_vec_pretty(sim.scene()).map_err(|source| SessionError::Json { what: "scene", source })?;
    log.attach("scene.json", "application/json", sim.time_nanos(), &scene)?;
    let mut metadata = BTreeMap::new();
    metadata.insert("tool".to_owned(), "record".to_owned());
    metadata.insert("tool_version".to_owned(), TOOL_VERSION.to_owned());
    metadata.insert("source".to_owned(), "simulation".to_owned());
    metadata.insert("seed".to_owned(), config.seed.to_string());
    metadata.insert("config".to_owned(), json("configuration", &config)?);
    metadata.insert(
        "hand_eye_flange_from_camera".to_owned(),
        json("hand-eye transform", &PoseJson::from(sim.hand_eye_believed()))?,
    );
    metadata.insert("requested_sets".to_owned(), config.captures.to_string());
    // Written first too, so that a log cut by a crash still says how it was made; the record
    // at the end (same name, read last) adds how many sets were completed.
    log.write_metadata(METADATA_NAME, metadata.clone())?;
    let mut completed = 0u32;
    let failed = |stage: String, completed: u32, file: OutputFile, source: LogError| {
        if completed == 0 {
            // Nothing worth recovering: the temporary file goes.
            drop(file);
            SessionError::Log(source)
        } else {
            SessionError::WriteFailed {
                stage,
                safe_sets: completed,
                kept: file.keep(),
                source,
            }
        }
    };
    for index in 0..config.captures {
        let (set, steps) = if config.rig == RigKind::Adaptive {
            let Some(adaptive) = sim.capture_adaptive_set(index, stop, |view| on_view(index, view), &mut on_plan)?
            else {
                break;
            };
            (adaptive.set, adaptive.steps)
        } else {
            let Some(set) = sim.capture_set(index, stop, |view| on_view(index, view))? else {
                break;
            };
            (set, Vec::new())
        };
        let hand_eye = *sim.hand_eye_believed();
        // The plans first: they go into the set's chunk, flushed with it.
        let plans = steps.iter().try_for_each(|step| log.write_plan(step));
        if let Err(source) = plans.and_then(|()| log.write_set(&set, Some(&hand_eye))) {
            return Err(failed(format!("writing set {index}"), completed, file, source));
        }
        completed += 1;
        on_set(&set);
        if stop.load(Ordering::SeqCst) {
            break;
        }
    }
    let outcome = |path| RecordingOutcome {
        path,
        completed_sets: completed,
        requested_sets: config.captures,
    };
    if completed == 0 {
        // Stopped before anything was complete: the temporary file is removed on drop.
        return Ok(outcome(None));
    }
    metadata.insert("completed_sets".to_owned(), completed.to_string());
    metadata.insert("interrupted".to_owned(), (completed < config.captures).to_string());
    let finished = log.write_metadata(METADATA_NAME, metadata).and_then(|()| log.finish());
    let writer = match finished {
        Ok(writer) => writer,
        Err(source) => return Err(failed("writing the summary".into(), completed, file, source)),
    };
    Ok(outcome(Some(commit_output(output, file, writer)?)))
}

/// What an import produced.
#[derive(Debug, Clone, PartialEq)]
pub struct ImportOutcome {
    /// The finished log.
    pub path: PathBuf,
    /// The sets it holds, in order.
    pub sets: Vec<CapturedSet>,
}

/// Imports the image sets under `dir` (one set, or one per sub-folder; see
/// [`crate::import::plan_import`]) into the log `output`. A search range given here
/// (`min_disparity`, `num_disparities`) overrides the folder's description. Every set is read before the log is started; `on_set`
/// follows each set read.
pub fn record_import(
    dir: &Path,
    settings: &crate::import::ImportOverrides,
    min_disparity: Option<i32>,
    num_disparities: Option<u32>,
    output: &Output,
    mut on_set: impl FnMut(&CapturedSet),
) -> Result<ImportOutcome, SessionError> {
    let mut plan = crate::import::plan_import(dir, settings).map_err(|e| SessionError::Plan(Box::new(e)))?;
    for (_, config) in &mut plan {
        config.min_disparity = min_disparity.or(config.min_disparity);
        config.num_disparities = num_disparities.or(config.num_disparities);
    }
    let mut sets = Vec::with_capacity(plan.len());
    for (index, (set_dir, config)) in plan.iter().enumerate() {
        let set = crate::import::import_set(set_dir, index as u32, config).map_err(|source| SessionError::Import {
            dir: set_dir.clone(),
            source: Box::new(source),
        })?;
        on_set(&set);
        sets.push(set);
    }
    let (file, mut log) = open_output(output, LogOptions::new().zstd_level(output.zstd_level))?;
    for set in &sets {
        log.write_set(set, None)?;
    }
    let configs: Vec<_> = plan.iter().map(|(_, config)| config).collect();
    let metadata = BTreeMap::from([
        ("tool".to_owned(), "record import".to_owned()),
        ("tool_version".to_owned(), TOOL_VERSION.to_owned()),
        ("source".to_owned(), format!("import:{}", dir.display())),
        ("config".to_owned(), json("the import configuration", &configs)?),
        ("completed_sets".to_owned(), sets.len().to_string()),
    ]);
    log.write_metadata(METADATA_NAME, metadata)?;
    let finished = log.finish()?;
    let path = commit_output(output, file, finished)?;
    Ok(ImportOutcome { path, sets })
}
