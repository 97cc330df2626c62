//! `replay watch DIR`: the workcell's replay. One process stays up beside the robot; each
//! finished log that appears in a folder (the recorder writes a hidden partial file and renames
//! it once the log is whole; a copy or a ROS 2 recorder ends the file with the MCAP magic) is
//! replayed as `replay LOG` would replay it, its results in `OUT/<log name>/`; so is each ROS 2
//! bag folder once rosbag2 has written its `metadata.yaml` and closed its files.
//!
//! What staying up buys: the methods are built once (MFuseNet's networks loaded and prepared
//! once), and the memory a set used stays with the process (`replay` never hands freed pages
//! back), so the next set's buffers are not faulted afresh. On virtual machines that return
//! freed memory to the host, a fresh page costs a host fault as well: there a five-view 1080p
//! set's `sgm-heuristic` takes about half the time in a process that has run a set before
//! (docs/benchmarks.md, "A watching process").

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

use fuse::methods::Method;

use crate::ReplayError;
use crate::pipeline::RunOptions;
use crate::run::{Progress, RunReport, RunRequest, replay_log};
use crate::salvage::MCAP_MAGIC;

/// What `replay watch` is asked to do.
pub struct WatchRequest<'a> {
    /// The folder the logs appear in.
    pub dir: &'a Path,
    /// The methods, built once with their overrides.
    pub methods: &'a [Box<dyn Method>],
    /// `--method` as given (for each summary).
    pub method_spec: &'a str,
    /// Disparity range, neighbours, rectification (the same for every log).
    pub options: RunOptions,
    /// Each log's results go to `out/<log file stem>/`.
    pub out: &'a Path,
    /// Which result files each set gets.
    pub outputs: crate::outputs::ResultFiles,
    /// Also replay the logs already in the folder when the watch starts (by default only those
    /// that appear after it: the folder may hold a day's captures already replayed).
    pub existing: bool,
    /// How often the folder is listed.
    pub poll: Duration,
    /// Stop after this many logs (replayed or failed).
    pub exit_after: Option<usize>,
    /// Stop when no new log has appeared for this long.
    pub idle_exit: Option<Duration>,
}

/// One log the watch replayed (or failed to).
#[derive(Debug)]
pub struct WatchedLog {
    /// The log.
    pub path: PathBuf,
    /// Its results' folder.
    pub out: PathBuf,
    /// The replay's report, or why it failed (the watch goes on either way).
    pub result: Result<RunReport, ReplayError>,
    /// From the moment the watch saw the log finished to its results written.
    pub seconds: f64,
}

/// How a watch ended.
#[derive(Debug, Default)]
pub struct WatchReport {
    /// Logs replayed whole.
    pub replayed: usize,
    /// Logs that failed or lost something (damaged sets, a viewer).
    pub failed: usize,
}

/// How long an unfinished log may stay the same size before the watch says so.
const STALLED: Duration = Duration::from_secs(10);

/// A log seen unfinished.
struct Waiting {
    /// Its size when last listed.
    size: u64,
    /// When that size was first seen.
    changed: Instant,
    /// Whether the stall was reported.
    reported: bool,
}

/// Whether `path` is a finished MCAP log to replay: a visible `.mcap` file (not the recorder's
/// hidden partial file) whose last bytes are the MCAP magic (a log still being written or
/// copied does not end with it yet).
pub fn is_finished_log(path: &Path) -> bool {
    use std::io::{Read, Seek, SeekFrom};
    let visible_mcap = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap"))
        && path
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| !n.starts_with('.'));
    if !visible_mcap {
        return false;
    }
    let Ok(mut file) = std::fs::File::open(path) else {
        return false;
    };
    let magic = MCAP_MAGIC.len() as i64;
    let mut tail = [0u8; 8];
    file.metadata()
        .is_ok_and(|m| m.is_file() && m.len() >= 2 * MCAP_MAGIC.len() as u64)
        && file.seek(SeekFrom::End(-magic)).is_ok()
        && file.read_exact(&mut tail).is_ok()
        && tail.as_slice() == MCAP_MAGIC
}

/// Whether `path` is a finished ROS 2 bag: a folder holding `metadata.yaml` (rosbag2 writes it
/// when the recording closes) and MCAP files that all end as finished logs do.
pub fn is_finished_bag(path: &Path) -> bool {
    if !path.join("metadata.yaml").is_file() {
        return false;
    }
    let Ok(entries) = std::fs::read_dir(path) else {
        return false;
    };
    let files: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap")))
        .collect();
    !files.is_empty() && files.iter().all(|f| is_finished_log(f))
}

/// Whether `path` is a visible folder, which may be a ROS 2 bag being recorded.
fn is_visible_dir(path: &Path) -> bool {
    path.is_dir()
        && path
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| !n.starts_with('.'))
}

/// The `.mcap` files and the ROS 2 bag folders of `dir` (finished or not; a folder counts once
/// it holds an `.mcap` file or `metadata.yaml`), oldest first (then by name).
fn logs_in(dir: &Path) -> Result<Vec<PathBuf>, ReplayError> {
    let io = |source| ReplayError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut logs: Vec<(SystemTime, PathBuf)> = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let entry = entry.map_err(io)?;
        let path = entry.path();
        let bag = is_visible_dir(&path)
            && std::fs::read_dir(&path).is_ok_and(|mut entries| {
                entries.any(|e| {
                    e.is_ok_and(|e| {
                        let name = e.file_name();
                        let name = name.to_string_lossy();
                        name == "metadata.yaml" || name.to_ascii_lowercase().ends_with(".mcap")
                    })
                })
            });
        if bag || path.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap")) {
            let modified = entry
                .metadata()
                .and_then(|m| m.modified())
                .unwrap_or(SystemTime::UNIX_EPOCH);
            logs.push((modified, path));
        }
    }
    logs.sort();
    Ok(logs.into_iter().map(|(_, path)| path).collect())
}

/// A log's size, or a bag folder's files' sizes summed (what grows while it is written).
fn size_of(path: &Path) -> u64 {
    if path.is_dir() {
        std::fs::read_dir(path).map_or(0, |entries| {
            entries
                .filter_map(Result::ok)
                .filter_map(|e| e.metadata().ok())
                .map(|m| m.len())
                .sum()
        })
    } else {
        std::fs::metadata(path).map_or(0, |m| m.len())
    }
}

/// The results' folder of `log`: `out/<file stem>` (a bag folder's: `out/<folder name>`).
pub fn results_dir(out: &Path, log: &Path) -> PathBuf {
    let name = if log.is_dir() { log.file_name() } else { log.file_stem() };
    out.join(name.unwrap_or(log.as_os_str()))
}

/// Watches `request.dir` and replays each finished log as it appears, calling `on_log` after
/// each; returns when `exit_after` logs are done or the folder stayed idle for `idle_exit`
/// (never, without either: the caller's process is stopped by a signal). A log that fails is
/// reported and the watch goes on; the folder itself unreadable ends it with the error.
pub fn watch(
    request: &WatchRequest<'_>,
    progress: &dyn Fn(&str) -> Box<dyn Progress>,
    on_log: &mut dyn FnMut(&WatchedLog),
) -> Result<WatchReport, ReplayError> {
    let mut report = WatchReport::default();
    // Logs seen and done with (replayed, failed, or finished before the watch when not `existing`).
    let mut done: HashSet<PathBuf> = HashSet::new();
    if !request.existing {
        // Those finished already; one still being written when the watch starts is replayed
        // once it finishes.
        done.extend(
            logs_in(request.dir)?
                .into_iter()
                .filter(|p| is_finished_log(p) || is_finished_bag(p)),
        );
    }
    // Logs seen unfinished (their size, when it last changed, whether the wait was reported):
    // they are read once they end with the magic.
    let mut waiting: BTreeMap<PathBuf, Waiting> = BTreeMap::new();
    let mut last_activity = Instant::now();
    loop {
        let mut ready = Vec::new();
        for path in logs_in(request.dir)? {
            if done.contains(&path) {
                continue;
            }
            if is_finished_log(&path) || is_finished_bag(&path) {
                waiting.remove(&path);
                ready.push(path);
            } else {
                let size = size_of(&path);
                let entry = waiting.entry(path.clone()).or_insert(Waiting {
                    size,
                    changed: Instant::now(),
                    reported: false,
                });
                if entry.size != size {
                    *entry = Waiting {
                        size,
                        changed: Instant::now(),
                        reported: false,
                    };
                }
                if entry.changed.elapsed() < STALLED {
                    // A log being written counts as activity: the watch waits for it to finish.
                    last_activity = last_activity.max(entry.changed);
                } else if !entry.reported {
                    entry.reported = true;
                    tracing::warn!(
                        "{} has not grown for {} s and does not end as a finished log does: a recorder that stopped? (`replay recover {} -o FIXED.mcap` writes what it holds)",
                        path.display(),
                        STALLED.as_secs(),
                        path.display()
                    );
                }
            }
        }
        for path in ready {
            let seen = Instant::now();
            let out = results_dir(request.out, &path);
            let run = RunRequest {
                log: &path,
                methods: request.methods,
                method_spec: request.method_spec,
                options: request.options.clone(),
                sets: &[],
                start_secs: None,
                end_secs: None,
                stream: crate::foreign::StreamOptions::default(),
                out: &out,
                outputs: request.outputs,
                out_mcap: None,
                out_format: None,
                rerun: &[],
            };
            let result = replay_log(&run, progress);
            match &result {
                Ok(run_report) if !run_report.lost_anything => report.replayed += 1,
                _ => report.failed += 1,
            }
            on_log(&WatchedLog {
                path: path.clone(),
                out,
                result,
                seconds: seen.elapsed().as_secs_f64(),
            });
            done.insert(path);
            last_activity = Instant::now();
            if request.exit_after.is_some_and(|n| report.replayed + report.failed >= n) {
                return Ok(report);
            }
        }
        if request.idle_exit.is_some_and(|idle| last_activity.elapsed() >= idle) {
            return Ok(report);
        }
        std::thread::sleep(request.poll);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_visible_mcap_files_that_end_with_the_magic_are_finished() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let write = |name: &str, bytes: &[u8]| {
            let path = dir.path().join(name);
            std::fs::write(&path, bytes).unwrap_or_else(|e| panic!("{e}"));
            path
        };
        let whole = [MCAP_MAGIC, b"records", MCAP_MAGIC].concat();
        assert!(is_finished_log(&write("set.mcap", &whole)));
        assert!(is_finished_log(&write("SET2.MCAP", &whole)));
        // Still being written: no magic at the end yet.
        assert!(!is_finished_log(&write(
            "writing.mcap",
            &[MCAP_MAGIC, b"records"].concat()
        )));
        // The recorder's partial file, whatever it ends with.
        assert!(!is_finished_log(&write(".set.mcap.partial-42", &whole)));
        assert!(!is_finished_log(&write(".hidden.mcap", &whole)));
        // Not a log, too short, missing.
        assert!(!is_finished_log(&write("notes.txt", &whole)));
        assert!(!is_finished_log(&write("short.mcap", MCAP_MAGIC)));
        assert!(!is_finished_log(&dir.path().join("gone.mcap")));
    }

    #[test]
    fn a_bag_folder_is_finished_once_its_metadata_is_written_and_its_files_end_whole() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let bag = dir.path().join("capture.v2");
        std::fs::create_dir_all(&bag).unwrap_or_else(|e| panic!("{e}"));
        let whole = [MCAP_MAGIC, b"records", MCAP_MAGIC].concat();
        std::fs::write(bag.join("capture_0.mcap"), &whole).unwrap_or_else(|e| panic!("{e}"));
        assert!(!is_finished_bag(&bag), "no metadata.yaml yet");
        std::fs::write(bag.join("capture_1.mcap"), MCAP_MAGIC).unwrap_or_else(|e| panic!("{e}"));
        std::fs::write(bag.join("metadata.yaml"), "rosbag2_bagfile_information: {}").unwrap_or_else(|e| panic!("{e}"));
        assert!(!is_finished_bag(&bag), "its second file is still open");
        std::fs::write(bag.join("capture_1.mcap"), &whole).unwrap_or_else(|e| panic!("{e}"));
        assert!(is_finished_bag(&bag));
        assert_eq!(results_dir(Path::new("out"), &bag), Path::new("out/capture.v2"));
        assert!(!is_finished_bag(dir.path()), "a folder without metadata");
    }

    #[test]
    fn results_go_to_a_folder_named_after_the_log() {
        assert_eq!(
            results_dir(Path::new("out"), Path::new("/cell/captures/part-0042.mcap")),
            Path::new("out/part-0042")
        );
    }
}
