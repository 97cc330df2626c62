//! `replay watch DIR`: the real binary watching a folder while logs appear in it as a cell's
//! controller writes them (the recorder's hidden partial file renamed into place, a copy still
//! growing, a corrupt file), each finished log replayed into `OUT/<log name>/`.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use multiscopic_tests::{binary, record_args, temp_dir};

/// Waits for `child` at most `limit`; kills it and fails if it is still running.
fn wait_for(mut child: Child, limit: Duration) -> (Option<i32>, String) {
    let start = Instant::now();
    loop {
        match child.try_wait() {
            Ok(Some(status)) => {
                let output = child.wait_with_output().unwrap_or_else(|e| panic!("{e}"));
                return (status.code(), String::from_utf8_lossy(&output.stderr).into_owned());
            }
            Ok(None) if start.elapsed() < limit => std::thread::sleep(Duration::from_millis(20)),
            Ok(None) => {
                let _ = child.kill();
                let output = child.wait_with_output().unwrap_or_else(|e| panic!("{e}"));
                panic!(
                    "replay watch still running after {limit:?}\nstderr:\n{}",
                    String::from_utf8_lossy(&output.stderr)
                );
            }
            Err(e) => panic!("{e}"),
        }
    }
}

fn watch(dir: &Path, out: &Path, extra: &[&str]) -> Child {
    Command::new(binary("replay"))
        .args([
            "watch",
            dir.to_str().unwrap_or_default(),
            "--method",
            "bm-heuristic",
            "--outputs",
            "depth",
        ])
        .args(["--out", out.to_str().unwrap_or_default(), "--poll-ms", "5"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start replay watch: {e}"))
}

fn summary(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn the_watch_replays_each_log_that_appears_finished_and_goes_on_past_a_bad_one() {
    let scratch = temp_dir();
    let (cell, out) = (scratch.path().join("cell"), scratch.path().join("results"));
    std::fs::create_dir_all(&cell).unwrap_or_else(|e| panic!("{e}"));
    let log = record_args(scratch.path(), "capture.mcap", "--rig five-view --resolution 160x120");
    let bytes = std::fs::read(&log).unwrap_or_else(|e| panic!("{e}"));
    // There before the watch: left alone without --existing.
    std::fs::write(cell.join("yesterday.mcap"), &bytes).unwrap_or_else(|e| panic!("{e}"));
    let child = watch(&cell, &out, &["--exit-after", "2"]);
    std::thread::sleep(Duration::from_millis(300));
    // A copy still being written (no magic at its end yet) and the recorder's partial file.
    std::fs::write(cell.join("growing.mcap"), &bytes[..bytes.len() / 2]).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(cell.join(".part-0001.mcap.partial-77"), &bytes).unwrap_or_else(|e| panic!("{e}"));
    // A corrupt log that ends as a finished one does: reported, and the watch goes on.
    std::fs::write(
        cell.join("corrupt.mcap"),
        [b"garbage ".repeat(8).as_slice(), b"\x89MCAP0\r\n"].concat(),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    std::thread::sleep(Duration::from_millis(300));
    // The recorder's way: the whole log renamed into place.
    std::fs::rename(cell.join(".part-0001.mcap.partial-77"), cell.join("part-0001.mcap"))
        .unwrap_or_else(|e| panic!("{e}"));
    let (code, stderr) = wait_for(child, Duration::from_secs(120));
    assert_eq!(code, Some(3), "one log failed: exit 3\n{stderr}");
    assert!(
        stderr.contains("corrupt.mcap") && stderr.contains("the watch goes on"),
        "{stderr}"
    );
    let done = summary(&out.join("part-0001/summary.json"));
    assert_eq!(done["methods"][0], "bm-heuristic");
    let set = &done["sets"][0];
    assert!(set["seconds"].as_f64().is_some_and(|s| s > 0.0), "{set}");
    let files: Vec<&str> = set["outputs"]["files"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|f| f.as_str())
        .collect();
    assert!(files.iter().any(|f| f.ends_with("depth_mm.png")), "{files:?}");
    assert!(
        files
            .iter()
            .all(|f| Path::new(f).exists() || out.join("part-0001").join(f).exists()),
        "{files:?}"
    );
    for skipped in ["yesterday", "growing", "corrupt"] {
        assert!(
            !out.join(skipped).join("summary.json").exists(),
            "{skipped} has results"
        );
    }
}

#[test]
fn with_existing_the_watch_replays_the_folder_s_logs_and_bags_and_stops_when_idle() {
    let scratch = temp_dir();
    let (cell, out) = (scratch.path().join("cell"), scratch.path().join("results"));
    std::fs::create_dir_all(&cell).unwrap_or_else(|e| panic!("{e}"));
    record_args(&cell, "a.mcap", "--rig three-view --resolution 160x120");
    record_args(&cell, "b.mcap", "--rig five-view --resolution 160x120 --captures 2");
    // A robot's way: a ROS 2 bag folder (`metadata.yaml` and its MCAP files).
    record_args(&cell, "bag", "--rig five-view --resolution 160x120 --format ros2");
    assert!(cell.join("bag/metadata.yaml").is_file());
    let child = watch(&cell, &out, &["--existing", "--idle-exit", "0.5"]);
    let (code, stderr) = wait_for(child, Duration::from_secs(120));
    assert_eq!(code, Some(0), "{stderr}");
    assert_eq!(
        summary(&out.join("a/summary.json"))["sets"].as_array().map(Vec::len),
        Some(1)
    );
    assert_eq!(
        summary(&out.join("b/summary.json"))["sets"].as_array().map(Vec::len),
        Some(2)
    );
    assert_eq!(
        summary(&out.join("bag/summary.json"))["sets"].as_array().map(Vec::len),
        Some(1)
    );
}

#[test]
fn watching_something_that_is_not_a_folder_is_a_usage_error() {
    let scratch = temp_dir();
    let output = Command::new(binary("replay"))
        .args(["watch", scratch.path().join("missing").to_str().unwrap_or_default()])
        .output()
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(output.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&output.stderr).contains("is not a folder"));
}
