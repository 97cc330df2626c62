//! Fuzzing on stable Rust: every reader of outside input gets mutated copies of the corpus in
//! `tests/corpus` (proptest; bit flips, byte writes, cuts, duplicated and inserted runs) and must
//! return, without a panic, and without any single allocation larger than the input allows.
//!
//! `FUZZ_CASES` sets the cases per target (default 2,000: a few seconds in all;
//! `scripts/fuzz.sh` runs a longer campaign). The corpus files themselves are replayed first.
//! The two logs of the corpus are remade, after a change of the log format, by
//! `cargo test -p multiscopic-tests --test e2e -- --ignored make_the_log_corpus`.

use std::path::{Path, PathBuf};

use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};

use multiscopic_tests::{recorded, temp_dir, workspace_root};

/// Largest single allocation allowed for an input of `len` bytes: the readers may decompress
/// (a chunk up to 4096 × its compressed size) and build images and networks, never more.
fn allocation_bound(len: usize) -> usize {
    len.saturating_mul(4096).max(256 << 20)
}

fn corpus(name: &str) -> Vec<u8> {
    let path = workspace_root().join("tests/corpus").join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("corpus file {} missing: {e}", path.display()))
}

fn cases() -> u32 {
    std::env::var("FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000)
}

/// One mutation of an input.
#[derive(Debug, Clone)]
enum Mutation {
    /// Flip bit `bit` of the byte at this fraction of the length.
    Flip(f64, u8),
    /// Write a byte.
    Set(f64, u8),
    /// Cut the input here.
    Cut(f64),
    /// Copy a run of the input (start, length fraction) to another place.
    Duplicate(f64, f64, f64),
    /// Insert bytes.
    Insert(f64, Vec<u8>),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let fraction = 0.0..1.0f64;
    prop_oneof![
        4 => (fraction.clone(), 0..8u8).prop_map(|(at, bit)| Mutation::Flip(at, bit)),
        3 => (fraction.clone(), any::<u8>()).prop_map(|(at, byte)| Mutation::Set(at, byte)),
        1 => fraction.clone().prop_map(Mutation::Cut),
        1 => (fraction.clone(), 0.0..0.2f64, fraction.clone()).prop_map(|(a, l, b)| Mutation::Duplicate(a, l, b)),
        1 => (fraction, proptest::collection::vec(any::<u8>(), 1..16)).prop_map(|(at, bytes)| Mutation::Insert(at, bytes)),
    ]
}

fn apply(input: &[u8], mutations: &[Mutation]) -> Vec<u8> {
    let mut data = input.to_vec();
    let at = |fraction: f64, len: usize| ((fraction * len as f64) as usize).min(len.saturating_sub(1));
    for m in mutations {
        if data.is_empty() {
            break;
        }
        let len = data.len();
        match m {
            Mutation::Flip(f, bit) => data[at(*f, len)] ^= 1 << bit,
            Mutation::Set(f, byte) => data[at(*f, len)] = *byte,
            Mutation::Cut(f) => data.truncate(at(*f, len)),
            Mutation::Duplicate(a, l, b) => {
                let start = at(*a, len);
                let end = (start + (*l * len as f64) as usize).min(len);
                let run = data[start..end].to_vec();
                let to = at(*b, len);
                data.splice(to..to, run);
            }
            Mutation::Insert(f, bytes) => {
                let to = at(*f, len);
                data.splice(to..to, bytes.iter().copied());
            }
        }
    }
    data
}

/// Runs `target` on every corpus file as it is, then on `cases()` mutated copies; panics (with
/// proptest's smallest failing mutation list) on a panic of the target or an allocation over the
/// bound. Returns the inputs run.
fn fuzz(name: &str, seeds: &[Vec<u8>], target: impl Fn(&[u8])) -> u32 {
    let run_one = |data: &[u8]| -> Result<(), String> {
        multiscopic_tests::allocations::reset();
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| target(data)));
        let largest = multiscopic_tests::allocations::largest();
        if outcome.is_err() {
            return Err(format!("{name}: the target panicked on {} bytes", data.len()));
        }
        if largest > allocation_bound(data.len()) {
            return Err(format!(
                "{name}: an allocation of {largest} bytes for an input of {} bytes",
                data.len()
            ));
        }
        Ok(())
    };
    for seed in seeds {
        run_one(seed).unwrap_or_else(|e| panic!("corpus: {e}"));
    }
    let mut runner = TestRunner::new(Config {
        cases: cases(),
        failure_persistence: None,
        ..Config::default()
    });
    let strategy = (0..seeds.len(), proptest::collection::vec(mutation(), 1..8));
    let started = std::time::Instant::now();
    let result = runner.run(&strategy, |(seed, mutations)| {
        run_one(&apply(&seeds[seed], &mutations)).map_err(TestCaseError::fail)
    });
    println!(
        "{name}: {} corpus inputs and {} mutated cases in {:.1} s, largest allocation bound {} MiB",
        seeds.len(),
        cases(),
        started.elapsed().as_secs_f64(),
        allocation_bound(seeds.iter().map(Vec::len).max().unwrap_or(0)) >> 20
    );
    if let Err(error) = result {
        panic!("{error}");
    }
    seeds.len() as u32 + cases()
}

/// Path-based readers get the input through a file.
fn with_file(dir: &Path, name: &str, data: &[u8]) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, data).unwrap_or_else(|e| panic!("{e}"));
    path
}

/// Writes `tests/corpus/five.mcap` (a two-set five-view capture, 48×32) and `foreign.mcap` (the
/// same without capture events, so the reader must infer its sets from the poses).
#[test]
#[ignore = "writes tests/corpus: run by hand after a change of the log format"]
fn make_the_log_corpus() {
    let (_dir, five) = recorded("five.mcap", "--captures 2 --resolution 48x32 --samples-per-pixel 1");
    let corpus = workspace_root().join("tests/corpus");
    std::fs::copy(&five, corpus.join("five.mcap")).unwrap_or_else(|e| panic!("{e}"));
    multiscopic_tests::strip_capture_events(&five, &corpus.join("foreign.mcap"));
    let contents = replay::log::read_log_file(&corpus.join("foreign.mcap")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        contents.sets.len(),
        2,
        "the foreign log's sets are inferred from the poses"
    );
}

#[test]
fn the_log_reader_and_foreign_set_assembly_survive_mutated_logs() {
    fuzz("read_log", &[corpus("five.mcap"), corpus("foreign.mcap")], |data| {
        let _ = replay::log::read_log(data);
        // A time window goes through the summary's indexes when the summary holds.
        let window = replay::log::TimeRange {
            start_nanos: 1_577_836_800_000_000_000,
            end_nanos: 1_577_836_805_000_000_000,
        };
        let _ = replay::log::read_log_in(data, &window);
    });
}

#[test]
fn ground_truth_readers_survive_mutated_files() {
    let dir = temp_dir();
    for name in ["gt.pfm", "gt.pgm", "gt.png"] {
        fuzz(name, &[corpus(name)], |data| {
            let path = with_file(dir.path(), name, data);
            let _ = record::import::read_ground_truth(&path);
        });
    }
}

#[test]
fn the_dataset_description_and_method_configs_survive_mutated_text() {
    let dir = temp_dir();
    fuzz("multiscopic.toml", &[corpus("multiscopic.toml")], |data| {
        let path = with_file(dir.path(), "multiscopic.toml", data);
        let _ = record::import::read_description(&path);
    });
    fuzz("method config JSON", &[corpus("config.json")], |data| {
        if let Ok(value) = serde_json::from_slice::<serde_json::Value>(data) {
            for method in ["sgm-heuristic", "gc-heuristic", "mfusenet"] {
                let _ = fuse::methods::build(method, Some(&value));
            }
        }
    });
}

#[test]
fn the_weights_loader_survives_mutated_safetensors() {
    let stereo = std::fs::read(workspace_root().join("fuse/weights/mfusenet-stereo.safetensors"))
        .unwrap_or_else(|e| panic!("{e}"));
    fuzz("weights", &[stereo], |data| {
        let _ = fuse::mfusenet::weights::from_bytes(data, "fuzz.safetensors", "", None);
    });
}

#[test]
fn the_ros2_decoder_survives_mutated_cdr() {
    // The golden payloads rosbags wrote (tests/corpus/ros2), each through the translator of its
    // type: CDR decoding (either byte order) and the conversion to the reader's messages.
    for (file, schema) in [
        ("image_rgb8.cdr", "sensor_msgs/msg/Image"),
        ("image_32fc1.cdr", "sensor_msgs/msg/Image"),
        ("compressed_image.cdr", "sensor_msgs/msg/CompressedImage"),
        ("camera_info.cdr", "sensor_msgs/msg/CameraInfo"),
        ("camera_info_be.cdr", "sensor_msgs/msg/CameraInfo"),
        ("tf.cdr", "tf2_msgs/msg/TFMessage"),
        ("joint_state.cdr", "sensor_msgs/msg/JointState"),
        ("string.cdr", "std_msgs/msg/String"),
    ] {
        fuzz(file, &[corpus(&format!("ros2/{file}"))], |data| {
            let mut translator = replay::ros2::Ros2Translator::default();
            let _ = translator.translate("/fuzz", schema, data);
        });
    }
}
