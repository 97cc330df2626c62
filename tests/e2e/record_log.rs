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
