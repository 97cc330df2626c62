//! `replay demo`: a simulated capture recorded into a folder that git ignores, with the disparity
//! range its working depth gives; the binary then replays it with [`crate::run::replay_log`].

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use record::capture::{Simulation, SimulationConfig};
use record::session::{SessionError, record_simulation};
use tracing::info;

/// Errors of the demo's recording.
#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    /// The configuration cannot be simulated.
    #[error("the demo's capture cannot be simulated")]
    Config(#[from] record::capture::SimulationError),
    /// Recording failed.
    #[error(transparent)]
    Record(Box<SessionError>),
    /// The output folder could not be made.
    #[error("cannot write '{}'", path.display())]
    Io {
        /// Folder or file.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// The recording ended before its first set was complete.
    #[error("the recording of '{}' produced no complete set", path.display())]
    NoSet {
        /// The log.
        path: PathBuf,
    },
}

/// The demo's recorded capture.
#[derive(Debug)]
pub struct DemoCapture {
    /// `OUT/capture.mcap`.
    pub log: PathBuf,
    /// The viewer layout of the log (from its first set), for the caller to write beside it
    /// (`record::live::write_log_blueprint`).
    pub layout: Option<viz::log_blueprint::LogLayout>,
}

/// Writes `DIR/.gitignore` ignoring everything in `DIR` (as Cargo does for `target/`), unless the
/// folder already has one: the demo's outputs are results, never work to commit.
pub fn ignore_in_git(dir: &Path) -> Result<(), DemoError> {
    let path = dir.join(".gitignore");
    if path.exists() {
        return Ok(());
    }
    std::fs::write(
        &path,
        "# Written by `replay demo`: its outputs are results, not sources.\n*\n",
    )
    .map_err(|source| DemoError::Io { path, source })
}

/// Records the demo's capture into `out/capture.mcap`;
/// `on_view` is called after each rendered view with the set index and the view's role.
pub fn record_capture(
    config: SimulationConfig,
    out: &Path,
    mut on_view: impl FnMut(u32, &str),
) -> Result<DemoCapture, DemoError> {
    std::fs::create_dir_all(out).map_err(|source| DemoError::Io {
        path: out.to_path_buf(),
        source,
    })?;
    ignore_in_git(out)?;
    info!(
        "outputs go to {} (git-ignored through {})",
        out.display(),
        out.join(".gitignore").display()
    );
    let log = out.join("capture.mcap");
    // Every set carries its working range at its own baseline (an adaptive set may have taken a
    // longer one), which the replay searches.
    let config = SimulationConfig {
        log_working_range: true,
        ..config
    };
    let mut sim = Simulation::new(config)?;
    let range = sim.working_disparity_range();
    let (min_disparity, num_disparities) = (range.min_disparity, range.num_disparities.unwrap_or(16) as usize);
    info!(
        "disparities {min_disparity}..{} px from the working depth (table at {:.2} m, objects up to {:.2} m above it)",
        min_disparity + num_disparities as i32,
        sim.scene().camera_height_m,
        sim.scene().highest_point_m()
    );
    info!(
        "recording a simulated {} capture of the {} scene → {}",
        sim.config().rig.name(),
        sim.config().scene_name(),
        log.display()
    );
    let stop = AtomicBool::new(false);
    let mut layout = None;
    let recorded = record_simulation(
        &mut sim,
        &record::session::Output::mcap(&log),
        &stop,
        |set, view| on_view(set, &view.role),
        |_, _| {},
        |set| {
            layout.get_or_insert_with(|| record::live::log_layout(set));
        },
    )
    .map_err(|e| DemoError::Record(Box::new(e)))?;
    if recorded.path.is_none() {
        return Err(DemoError::NoSet { path: log });
    }
    Ok(DemoCapture { log, layout })
}
