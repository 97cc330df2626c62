//! Bad input, failures and interruption: clear errors, correct exit codes, no file that looks
//! complete unless it is.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use multiscopic_tests::{Log, binary, record, record_str, temp_dir};

fn stderr(output: &std::process::Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn invalid_arguments_exit_2_with_a_clear_message() {
    let dir = temp_dir();
    let out = dir.path().join("never.mcap");
    let out = out.to_str().unwrap_or_default();
    let cases: &[(&[&str], &str)] = &[
        (&["--rig", "nine-view"], "nine-view"),
        (&["--baseline-mm", "0"], "out of range"),
        (&["--baseline-mm", "abc"], "not a number"),
        (&["--resolution", "1920"], "WIDTHxHEIGHT"),
        (&["--resolution", "4x4"], "8..=16384"),
        (&["--captures", "0"], "captures"),
        (&["--rotation-error", "left:w:1"], "axis"),
        (&["--rig", "stereo", "--offset-error", "top:z:1"], "top"),
        (&["--no-such-flag"], "no-such-flag"),
    ];
    for (args, needle) in cases {
        let mut all = vec!["-o", out];
        all.extend_from_slice(args);
        let output = record(&all);
        assert_eq!(output.status.code(), Some(2), "{args:?}: {}", stderr(&output));
        assert!(
            stderr(&output).contains(needle),
            "{args:?}: message lacks '{needle}': {}",
            stderr(&output)
        );
        assert!(!dir.path().join("never.mcap").exists());
    }
}

#[test]
fn unwritable_output_exits_1_and_leaves_nothing() {
    let dir = temp_dir();
    let missing = dir.path().join("no/such/dir/capture.mcap");
    let output = record_str(&format!("-o {} --resolution 32x24 -q", missing.display()));
    assert_eq!(output.status.code(), Some(1), "{}", stderr(&output));
    assert!(stderr(&output).contains("no/such/dir"), "{}", stderr(&output));
    // A directory as the output path.
    let output = record_str(&format!("-o {} --resolution 32x24 -q", dir.path().display()));
    assert_eq!(output.status.code(), Some(1), "{}", stderr(&output));
    assert_eq!(std::fs::read_dir(dir.path()).map(|d| d.count()).unwrap_or(99), 0);
}

#[test]
fn failure_mid_run_leaves_no_file() {
    // The centre view is captured, then the left view lies outside the UR10's reach.
    let dir = temp_dir();
    let path = dir.path().join("capture.mcap");
    let output = record_str(&format!(
        "-o {} --baseline-mm 1000 --resolution 32x24 -q",
        path.display()
    ));
    assert_eq!(output.status.code(), Some(1), "{}", stderr(&output));
    assert!(stderr(&output).contains("cannot reach"), "{}", stderr(&output));
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name())
        .collect();
    assert!(left.is_empty(), "files left behind: {left:?}");
}

#[test]
fn ctrl_c_finishes_a_readable_log_of_the_completed_sets() {
    interrupted_record_finishes_its_log("INT");
}

/// What a shutdown, a job scheduler or `kill` sends: the same orderly end as Ctrl-C.
#[test]
fn sigterm_finishes_a_readable_log_of_the_completed_sets() {
    interrupted_record_finishes_its_log("TERM");
}

/// `nohup` starts a run with SIGHUP ignored so that it outlives the terminal: the interrupt
/// handler must leave it so.
#[test]
fn a_nohup_recording_ignores_a_hang_up() {
    let dir = temp_dir();
    let path = dir.path().join("nohup.mcap");
    let mut command = Command::new("nohup");
    command.arg(binary("record"));
    // `nohup` replaced itself with `record`: the child's pid is the recorder's.
    signal_and_expect_exit(record_two_of_200_sets(command, &path), "HUP", 0);
    let sets: std::collections::BTreeSet<u32> = Log::read(&path).events().iter().map(|e| e.set_index).collect();
    assert_eq!(sets.len(), 200, "every set recorded");
}

/// A recording under way: the child, the rest of its stderr, what it printed so far.
type Recording = (
    std::process::Child,
    std::io::Lines<BufReader<std::process::ChildStderr>>,
    String,
);

/// Starts `command` (the `record` binary, or a wrapper whose arguments end with it) recording
/// 200 small sets into `path`, and waits until two are done: the child, the rest of its stderr
/// and what it printed so far.
fn record_two_of_200_sets(mut command: Command, path: &std::path::Path) -> Recording {
    let mut child = command
        .args(["-o", path.to_str().unwrap_or_default()])
        .args(["--captures", "200", "--resolution", "64x48", "--samples-per-pixel", "1"])
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start record: {e}"));
    let stderr = child.stderr.take().unwrap_or_else(|| panic!("no stderr pipe"));
    let mut lines = BufReader::new(stderr).lines();
    let started = Instant::now();
    let mut seen = String::new();
    loop {
        let Some(Ok(line)) = lines.next() else {
            panic!("record ended before two sets were done:\n{seen}");
        };
        seen.push_str(&line);
        seen.push('\n');
        if line.contains("set 2/200 done") {
            break;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "no progress:\n{seen}");
    }
    (child, lines, seen)
}

/// Sends SIG`signal` to a recording started by [`record_two_of_200_sets`] and asserts its exit
/// code.
fn signal_and_expect_exit((mut child, lines, seen): Recording, signal: &str, code: i32) {
    let kill = Command::new("kill")
        .args([&format!("-{signal}"), &child.id().to_string()])
        .status();
    assert!(
        kill.is_ok_and(|s| s.success()),
        "cannot send SIG{signal} (record already done?)"
    );
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let status = child.wait().unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        status.code(),
        Some(code),
        "SIG{signal}: exit {code} expected\n{seen}{}",
        rest.join("\n")
    );
}

fn interrupted_record_finishes_its_log(signal: &str) {
    let dir = temp_dir();
    let path = dir.path().join("interrupted.mcap");
    signal_and_expect_exit(record_two_of_200_sets(Command::new(binary("record")), &path), signal, 3);
    let log = Log::read(&path);
    let events = log.events();
    let sets: std::collections::BTreeSet<u32> = events.iter().map(|e| e.set_index).collect();
    assert!(sets.len() >= 2 && sets.len() < 200, "{} sets", sets.len());
    for set in &sets {
        let views = events.iter().filter(|e| e.set_index == *set).count();
        assert_eq!(views, 5, "set {set} is incomplete in the log");
    }
    let metadata = &log.metadata[record::log::METADATA_NAME];
    assert_eq!(metadata["interrupted"], "true");
    assert_eq!(metadata["completed_sets"], sets.len().to_string());
}
