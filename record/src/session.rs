//! A whole simulated recording to a file: the scene attachment, the sets as they complete, the
//! metadata with the effective configuration, and the atomic commit. Used by the `record`
//! binary and by `replay demo`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use crate::capture::{Simulation, SimulationError};
use crate::log::{LogError, LogOptions, METADATA_NAME, OutputFile, PoseJson};
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

/// Records every set of `sim` into `output` (written under a temporary name, renamed when
/// finished). When `stop` is raised, the log is finished with the sets completed so far.
/// `on_view(set, view)` follows every view; `on_set(set)` every completed set (with the arm's
/// motion samples).
pub fn record_simulation(
    sim: &mut Simulation,
    output: &Path,
    zstd_level: u32,
    stop: &AtomicBool,
    mut on_view: impl FnMut(u32, &CapturedView),
    mut on_set: impl FnMut(&CapturedSet),
) -> Result<RecordingOutcome, SessionError> {
    let config = sim.config().clone();
    let (file, writer) = OutputFile::create(output)?;
    let mut log = LogOptions::new()
        .image_format(config.image_format)
        .zstd_level(zstd_level)
        .create(writer)?;
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
        let Some(set) = sim.capture_set(index, stop, |view| on_view(index, view))? else {
            break;
        };
        let hand_eye = *sim.hand_eye_believed();
        if let Err(source) = log.write_set(&set, Some(&hand_eye)) {
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
    Ok(outcome(Some(file.commit(writer)?)))
}
