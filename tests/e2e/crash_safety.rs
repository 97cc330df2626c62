//! Logs that survive a crash: every cut of a recording keeps the sets completed before it,
//! `replay recover` finishes what is left, and a recorder killed with SIGKILL loses only the set
//! in flight.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use multiscopic_tests::{Log, binary, foxglove_read, python_with_mcap, recorded, replay, replay_str, run, temp_dir};

/// The byte offsets where each chunk record ends, in file order (from the summary).
fn chunk_ends(bytes: &[u8]) -> Vec<usize> {
    let summary = mcap::Summary::read(bytes)
        .unwrap_or_else(|e| panic!("summary: {e}"))
        .unwrap_or_else(|| panic!("the finished log has no summary"));
    let mut ends: Vec<usize> = summary
        .chunk_indexes
        .iter()
        .map(|c| (c.chunk_start_offset + c.chunk_length) as usize)
        .collect();
    ends.sort_unstable();
    ends
}

/// Complete sets per the reference Python reader (CRCs checked): capture events grouped by set,
/// a set counting when all its views are there.
fn python_complete_sets(path: &Path) -> (Vec<u64>, serde_json::Value) {
    let script = multiscopic_tests::workspace_root().join("tests/python/complete_sets.py");
    let output = run(Command::new(python_with_mcap()).arg(script).arg(path));
    assert!(
        output.status.success(),
        "the Python mcap reader rejects {}: {}",
        path.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("python printed no JSON: {e}"));
    let complete = report["complete"]
        .as_array()
        .unwrap_or_else(|| panic!("{report}"))
        .iter()
        .filter_map(serde_json::Value::as_u64)
        .collect();
    (complete, report)
}

/// `replay recover LOG -o FIXED`, which must say that something was lost (exit 3).
fn recover_losing_something(log: &Path, fixed: &Path) {
    let recover = replay_str(&format!("recover {} -o {}", log.display(), fixed.display()));
    assert_eq!(
        recover.status.code(),
        Some(3),
        "recover of {}: {}",
        log.display(),
        String::from_utf8_lossy(&recover.stderr)
    );
}

#[test]
fn every_cut_keeps_the_sets_completed_before_it_and_recover_finishes_them() {
    let (dir, log) = recorded("six.mcap", "--resolution 320x240 --captures 6 --samples-per-pixel 1");
    let bytes = std::fs::read(&log).unwrap_or_else(|e| panic!("{e}"));
    let ends = chunk_ends(&bytes);
    assert_eq!(ends.len(), 6, "one chunk per set: {ends:?}");
    // Every 4 KiB, and every byte within 64 of each chunk's end.
    let mut cuts: Vec<usize> = (1..bytes.len() / 4096).map(|k| k * 4096).collect();
    for end in &ends {
        cuts.extend(end.saturating_sub(64)..(end + 65).min(bytes.len()));
    }
    cuts.sort_unstable();
    cuts.dedup();
    let expected = |cut: usize| ends.iter().filter(|end| **end <= cut).count();
    let started = Instant::now();
    let failures: Vec<String> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..2)
            .map(|worker| {
                let (cuts, bytes) = (&cuts, &bytes);
                scope.spawn(move || {
                    let mut failures = Vec::new();
                    for cut in cuts.iter().skip(worker).step_by(2) {
                        match replay::log::read_log(&bytes[..*cut]) {
                            Ok(contents) => {
                                let got: Vec<u32> = contents.sets.iter().map(|s| s.index).collect();
                                let want: Vec<u32> = (0..expected(*cut) as u32).collect();
                                if got != want || contents.truncation.is_none() {
                                    failures.push(format!(
                                        "cut {cut}: sets {got:?}, expected {want:?}, truncation {:?}",
                                        contents.truncation
                                    ));
                                }
                            }
                            Err(error) => failures.push(format!("cut {cut}: error {error}")),
                        }
                    }
                    failures
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|w| w.join().unwrap_or_else(|_| vec!["a reader thread panicked".into()]))
            .collect()
    });
    println!(
        "{} cuts of a {}-byte log read in {:.1} s; chunk ends {ends:?}",
        cuts.len(),
        bytes.len(),
        started.elapsed().as_secs_f64()
    );
    assert!(
        failures.is_empty(),
        "{} cuts wrong, e.g. {:?}",
        failures.len(),
        &failures[..failures.len().min(5)]
    );

    // Through the binaries: check says what was kept (exit 3), recover writes a finished log
    // that the reference reader reads with its CRCs, holding exactly the complete sets.
    for cut in [9000, ends[1] - 1, ends[1], ends[1] + 200, (ends[3] + ends[4]) / 2] {
        let path = dir.path().join(format!("cut-{cut}.mcap"));
        std::fs::write(&path, &bytes[..cut]).unwrap_or_else(|e| panic!("{e}"));
        let path_text = path.to_str().unwrap_or_default();
        let check = replay_str(&format!("check {} --json", path_text));
        assert_eq!(
            check.status.code(),
            Some(3),
            "check of cut {cut}: {}",
            String::from_utf8_lossy(&check.stderr)
        );
        let stderr = String::from_utf8_lossy(&check.stderr);
        assert!(stderr.contains("is cut at byte"), "where the log was cut: {stderr}");
        let sets: Vec<serde_json::Value> =
            serde_json::from_slice(&check.stdout).unwrap_or_else(|e| panic!("check --json: {e}"));
        assert_eq!(sets.len(), expected(cut), "cut {cut}");
        let fixed = dir.path().join(format!("fixed-{cut}.mcap"));
        recover_losing_something(Path::new(path_text), &fixed);
        let (complete, report) = python_complete_sets(&fixed);
        assert_eq!(
            complete,
            (0..expected(cut) as u64).collect::<Vec<_>>(),
            "cut {cut}: {report}"
        );
        if expected(cut) > 0 {
            // Written before the first set: the scene and how the recording was made.
            assert_eq!(report["attachments"], serde_json::json!(["scene.json"]), "{report}");
            assert_eq!(
                report["metadata"],
                serde_json::json!(["multiscopic.recording"]),
                "{report}"
            );
        }
        // Foxglove's own reader reads the recovered log through its indexes, CRCs checked, and
        // finds every message our reader finds.
        if let Some(read) = foxglove_read(&fixed) {
            let report = read.unwrap_or_else(|e| panic!("cut {cut}: Foxglove's reader: {e}"));
            let ours = Log::read(&fixed);
            let mut counts = std::collections::BTreeMap::<String, u64>::new();
            for message in &ours.messages {
                *counts.entry(message.topic.clone()).or_default() += 1;
            }
            let theirs: std::collections::BTreeMap<String, u64> =
                serde_json::from_value(report["topics"].clone()).unwrap_or_else(|e| panic!("cut {cut}: {e}: {report}"));
            assert_eq!(
                theirs, counts,
                "cut {cut}: messages per topic, Foxglove's reader against ours"
            );
        }
        // The recovered log is whole: replayed again, nothing is lost.
        let again = replay(&["check", fixed.to_str().unwrap_or_default()]);
        println!(
            "cut {cut}: {} set(s) kept, the recovered log re-checked with exit {:?} (3 where it keeps an incomplete set)",
            expected(cut),
            again.status.code()
        );
        assert!(
            matches!(again.status.code(), Some(0 | 3)),
            "{}",
            String::from_utf8_lossy(&again.stderr)
        );
    }
}

#[test]
fn a_corrupt_chunk_loses_its_set_only() {
    let (dir, log) = recorded("three.mcap", "--resolution 160x120 --captures 3 --samples-per-pixel 1");
    let mut bytes = std::fs::read(&log).unwrap_or_else(|e| panic!("{e}"));
    let summary = mcap::Summary::read(&bytes)
        .unwrap_or_else(|e| panic!("{e}"))
        .unwrap_or_else(|| panic!("no summary"));
    let mut chunks: Vec<_> = summary.chunk_indexes.iter().collect();
    chunks.sort_by_key(|c| c.chunk_start_offset);
    assert_eq!(chunks.len(), 3);
    // Flip a byte in the middle of the second chunk's compressed records.
    let middle = (chunks[1].chunk_start_offset + chunks[1].chunk_length / 2) as usize;
    bytes[middle] ^= 0x55;
    let bad = dir.path().join("bad.mcap");
    std::fs::write(&bad, &bytes).unwrap_or_else(|e| panic!("{e}"));
    let contents = replay::log::read_log(&bytes).unwrap_or_else(|e| panic!("{e}"));
    let kept: Vec<u32> = contents.sets.iter().map(|s| s.index).collect();
    assert_eq!(kept, vec![0, 2], "the corrupt chunk's set only is lost");
    assert_eq!(contents.bad_chunks.len(), 1, "{:?}", contents.bad_chunks);
    let check = replay(&["check", bad.to_str().unwrap_or_default()]);
    assert_eq!(check.status.code(), Some(3));
    let stderr = String::from_utf8_lossy(&check.stderr);
    assert!(
        stderr.contains("is corrupt") && stderr.contains("set 1"),
        "the warning names the chunk and its set: {stderr}"
    );
}

/// Sets the recorder had reported done when it was killed, and the temporary file it left.
fn record_and_kill(dir: &Path, after: Duration) -> (usize, std::path::PathBuf) {
    let output = dir.join("killed.mcap");
    let mut child = Command::new(binary("record"))
        .args([
            "--resolution",
            "640x480",
            "--captures",
            "6",
            "--samples-per-pixel",
            "1",
            "-o",
        ])
        .arg(&output)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("record: {e}"));
    let stderr = child.stderr.take().unwrap_or_else(|| panic!("no stderr"));
    let (sender, receiver) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if line.contains(" done (") {
                let _ = sender.send(());
            }
        }
    });
    std::thread::sleep(after);
    child.kill().unwrap_or_else(|e| panic!("kill: {e}"));
    let _ = child.wait();
    // Lines logged before the kill; give the reader thread a moment to drain the pipe.
    std::thread::sleep(Duration::from_millis(100));
    let done = receiver.try_iter().count();
    let partial = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{e}"))
        .filter_map(Result::ok)
        .map(|e| e.path())
        .find(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with(".killed.mcap.partial-"))
        });
    (done, partial.unwrap_or_else(|| output.clone()))
}

#[test]
fn a_recorder_killed_mid_run_leaves_every_set_it_reported_done() {
    // SIGKILL at three instants: early, mid-run, late (the sets take about a second each here).
    for (k, millis) in [700u64, 2500, 4500].into_iter().enumerate() {
        let dir = temp_dir();
        let (done, left) = record_and_kill(dir.path(), Duration::from_millis(millis));
        if !left.exists() {
            assert_eq!(done, 0, "the recorder reported {done} set(s) done but left no file");
            continue;
        }
        let fixed = dir.path().join(format!("fixed-{k}.mcap"));
        let recover = replay_str(&format!("recover {} -o {}", left.display(), fixed.display()));
        let finished_anyway = !left.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.'));
        assert!(
            matches!(recover.status.code(), Some(0 | 3)),
            "recover: {}",
            String::from_utf8_lossy(&recover.stderr)
        );
        let (complete, report) = python_complete_sets(&fixed);
        println!(
            "killed after {millis} ms: {done} set(s) reported done, {} recovered{}",
            complete.len(),
            if finished_anyway { " (it had finished)" } else { "" }
        );
        assert!(complete.len() >= done, "lost a set reported done: {report}");
        assert_eq!(complete, (0..complete.len() as u64).collect::<Vec<_>>());
    }
}

#[test]
fn a_full_disk_exits_1_naming_the_file_and_the_sets_safe_in_it() {
    let dir = temp_dir();
    let out = dir.path().join("full.mcap");
    // A 3 MB file-size limit stands in for a full disk: with SIGXFSZ ignored the write fails with
    // EFBIG, as it would with ENOSPC. The first 320×240 set (about 1.1 MB) fits, the second not.
    let output = run(Command::new("bash")
        .arg("-c")
        .arg("trap '' XFSZ; ulimit -f 3000; exec \"$0\" --resolution 320x240 --captures 6 --samples-per-pixel 1 -o \"$1\"")
        .arg(binary("record"))
        .arg(&out));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let safe: usize = stderr
        .split(" complete set(s) were synced to disk")
        .next()
        .and_then(|head| head.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("the error says how many sets are safe: {stderr}"));
    assert!(safe >= 1, "{stderr}");
    let kept = std::fs::read_dir(dir.path())
        .unwrap_or_else(|e| panic!("{e}"))
        .filter_map(Result::ok)
        .map(|e| e.path())
        .find(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with(".full.mcap.partial-"))
        })
        .unwrap_or_else(|| panic!("the temporary file is kept: {stderr}"));
    assert!(
        stderr.contains(&*kept.to_string_lossy()),
        "the error names the file: {stderr}"
    );
    assert!(!out.exists(), "no file under the final name");
    let fixed = dir.path().join("fixed.mcap");
    recover_losing_something(&kept, &fixed);
    let (complete, report) = python_complete_sets(&fixed);
    assert_eq!(complete, (0..safe as u64).collect::<Vec<_>>(), "{report}");
}
