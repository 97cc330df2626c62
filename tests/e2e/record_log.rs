//! The log contract: read by the Python reference clients, deterministic payloads.

use std::process::Command;

use multiscopic_tests::{Log, assert_success, json_strings, python_with_mcap, record_log, rerun_cli, run, temp_dir};

const SMALL: &[&str] = &["--resolution", "96x64", "--samples-per-pixel", "1"];

fn record_small(dir: &std::path::Path, name: &str, extra: &[&str]) -> std::path::PathBuf {
    let args: Vec<&str> = SMALL.iter().chain(extra).copied().collect();
    record_log(dir, name, &args)
}

fn python_check(path: &std::path::Path) -> serde_json::Value {
    let script = multiscopic_tests::workspace_root().join("tests/python/check_mcap.py");
    let output = run(Command::new(python_with_mcap()).arg(script).arg(path));
    assert_success(&output, "the Python mcap client");
    serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("check_mcap.py printed no JSON: {e}"))
}

#[test]
fn python_mcap_client_checks_crcs_and_decodes_every_message() {
    let dir = temp_dir();
    for (name, extra) in [
        ("raw.mcap", vec!["--captures", "2"]),
        (
            "png.mcap",
            vec!["--image-format", "png", "--rig", "grid3x3", "--scene", "workpiece"],
        ),
    ] {
        let path = record_small(dir.path(), name, &extra);
        let report = python_check(&path);
        let log = Log::read(&path);
        assert_eq!(report["messages"].as_u64(), Some(log.messages.len() as u64), "{report}");
        let schemas = json_strings(&report["schemas"]);
        for expected in [
            "foxglove.CameraCalibration",
            "foxglove.FrameTransforms",
            "foxglove.JointStates",
            "foxglove.PoseInFrame",
            "foxglove.RawImage",
            "multiscopic.CaptureEvent",
        ] {
            assert!(
                schemas.contains(&expected),
                "{name}: schema {expected} missing from {schemas:?}"
            );
        }
        if name == "png.mcap" {
            assert!(schemas.contains(&"foxglove.CompressedImage"), "{schemas:?}");
        }
        assert_eq!(report["metadata"][0].as_str(), Some(record::log::METADATA_NAME));
        assert_eq!(report["attachments"][0].as_str(), Some("scene.json"));
        assert!(report["chunks"].as_u64().unwrap_or(0) >= 1);
    }
}

#[test]
fn same_arguments_and_seed_give_identical_payloads() {
    let dir = temp_dir();
    let args = [
        "--scene",
        "random",
        "--seed",
        "7",
        "--rig",
        "three-view",
        "--exposure-jitter",
        "0.1",
    ];
    let a = Log::read(&record_small(dir.path(), "a.mcap", &args));
    let b = Log::read(&record_small(dir.path(), "b.mcap", &args));
    assert!(!a.messages.is_empty());
    assert_eq!(a.messages.len(), b.messages.len());
    for (x, y) in a.messages.iter().zip(&b.messages) {
        assert_eq!(x, y, "message on {} at {} differs", x.topic, x.log_time);
    }
    assert_eq!(a.metadata, b.metadata);
    let other = [
        "--scene",
        "random",
        "--seed",
        "8",
        "--rig",
        "three-view",
        "--exposure-jitter",
        "0.1",
    ];
    let c = Log::read(&record_small(dir.path(), "c.mcap", &other));
    let image = |log: &Log| {
        log.messages
            .iter()
            .find(|m| m.topic == "/camera/center/image")
            .map(|m| m.data.clone())
    };
    assert_ne!(image(&a), image(&c), "a different seed must give a different scene");
}

#[test]
fn metadata_holds_the_effective_configuration() {
    let dir = temp_dir();
    let log = Log::read(&record_small(
        dir.path(),
        "m.mcap",
        &["--seed", "42", "--baseline-mm", "25"],
    ));
    let metadata = &log.metadata[record::log::METADATA_NAME];
    assert_eq!(metadata["seed"], "42");
    assert_eq!(metadata["tool_version"], record::TOOL_VERSION);
    let config: record::capture::SimulationConfig =
        serde_json::from_str(&metadata["config"]).unwrap_or_else(|e| panic!("config is not a SimulationConfig: {e}"));
    assert_eq!(config.baseline_mm, 25.0);
    assert_eq!((config.width, config.height), (96, 64));
    assert_eq!(metadata["completed_sets"], "1");
    assert_eq!(metadata["interrupted"], "false");
}

#[test]
fn rerun_opens_the_log_directly_with_images_pinholes_and_transforms() {
    let dir = temp_dir();
    let path = record_small(dir.path(), "rerun.mcap", &["--rig", "three-view"]);
    let rrd = dir.path().join("rerun.rrd");
    let output = run(rerun_cli().args(["mcap", "convert"]).arg(&path).arg("-o").arg(&rrd));
    assert_success(&output, "rerun mcap convert");
    let output = run(rerun_cli().args(["rrd", "print"]).arg(&rrd));
    assert_success(&output, "rerun rrd print");
    let printed = String::from_utf8_lossy(&output.stdout);
    let columns_of = |entity: &str| -> String {
        printed
            .lines()
            .filter(|line| line.contains(&format!(" - {entity} - ")))
            .collect::<Vec<_>>()
            .join("\n")
    };
    for role in ["center", "left", "right"] {
        let image = columns_of(&format!("/camera/{role}/image"));
        assert!(
            image.contains("Image:buffer") && image.contains("CoordinateFrame:frame"),
            "{role} image: {image}"
        );
        let calibration = columns_of(&format!("/camera/{role}/calibration"));
        assert!(
            calibration.contains("Pinhole:image_from_camera"),
            "{role} calibration: {calibration}"
        );
    }
    let tf = columns_of("/tf");
    assert!(
        tf.contains("Transform3D:translation") && tf.contains("Transform3D:child_frame"),
        "/tf: {tf}"
    );
}

#[test]
fn a_copy_without_ground_truth_replays_like_a_real_camera_s_log_with_the_same_disparities() {
    // scripts/strip-truth.py (the workcell's log for scripts/bench-replay.py TRUTH=0), run by the
    // Python mcap client: no ground-truth topic, events without them, the same depth, no metrics.
    let dir = temp_dir();
    let log = record_small(dir.path(), "full.mcap", &["--captures", "2"]);
    let camera = dir.path().join("camera.mcap");
    let script = multiscopic_tests::workspace_root().join("scripts/strip-truth.py");
    let output = run(Command::new(python_with_mcap()).arg(script).arg(&log).arg(&camera));
    assert_success(&output, "scripts/strip-truth.py");
    let (full, stripped) = (Log::read(&log), Log::read(&camera));
    assert!(full.messages.iter().any(|m| m.topic.contains("/ground_truth/")));
    assert!(!stripped.messages.iter().any(|m| m.topic.contains("/ground_truth/")));
    let truth_messages = full
        .messages
        .iter()
        .filter(|m| m.topic.contains("/ground_truth/"))
        .count();
    assert_eq!(stripped.messages.len() + truth_messages, full.messages.len());
    let events = stripped.events();
    assert_eq!(events.len(), full.events().len());
    assert!(
        events
            .iter()
            .all(|e| e.depth_topic.is_none() && e.surface_topic.is_none() && e.true_world_from_camera.is_none())
    );
    let pfm = |summary: &serde_json::Value| {
        let files = summary["sets"][0]["outputs"]["files"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        let path = files
            .iter()
            .filter_map(serde_json::Value::as_str)
            .find(|f| f.ends_with("_disparity.pfm"))
            .map(std::path::PathBuf::from)
            .unwrap_or_else(|| panic!("no disparity file in {summary}"));
        std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
    };
    let args = "--method sgm-heuristic --outputs disparity --sets 1";
    let with_truth = multiscopic_tests::replay_summary(&log, &dir.path().join("a"), args);
    let without = multiscopic_tests::replay_summary(&camera, &dir.path().join("b"), args);
    assert!(with_truth["sets"][0]["outputs"]["metrics"].is_object(), "{with_truth}");
    assert!(without["sets"][0]["outputs"]["metrics"].is_null(), "{without}");
    assert!(
        pfm(&with_truth) == pfm(&without),
        "the same disparities from the same images"
    );
}
