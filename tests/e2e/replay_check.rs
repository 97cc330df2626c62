//! `replay check`: clean captures pass; an injected roll or out-of-plane offset is flagged on
//! that view only; a hand-eye error, invisible in the poses, shows in the image-based shift.

use multiscopic_tests::{assert_success, record_args, record_log, recorded, replay, replay_str, temp_dir};

fn check(extra: &[&str], name: &str) -> (Option<i32>, serde_json::Value) {
    let dir = temp_dir();
    let args: Vec<&str> = ["--resolution", "640x360"].iter().chain(extra).copied().collect();
    let log = record_log(dir.path(), name, &args);
    let output = replay_str(&format!("check {} --json -q", log.display()));
    let json = serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("replay check printed no JSON: {e}"));
    (output.status.code(), json)
}

/// The neighbours' reports of a five-view set's check (all four, or the test fails).
fn four_neighbours(json: &serde_json::Value) -> Vec<serde_json::Value> {
    let neighbours = json[0]["neighbours"].as_array().cloned().unwrap_or_default();
    assert_eq!(
        neighbours.len(),
        4,
        "every neighbour of the five-view set is checked: {json}"
    );
    neighbours
}

fn statuses(json: &serde_json::Value) -> Vec<(String, String)> {
    json[0]["neighbours"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|n| {
            (
                n["role"].as_str().unwrap_or_default().to_owned(),
                n["status"].as_str().unwrap_or_default().to_owned(),
            )
        })
        .collect()
}

#[test]
fn clean_capture_passes() {
    let (code, json) = check(&[], "clean.mcap");
    assert_eq!(code, Some(0), "{json}");
    let statuses = statuses(&json);
    let mut roles: Vec<&str> = statuses.iter().map(|(role, _)| role.as_str()).collect();
    roles.sort_unstable();
    // The default five-view rig: one status per neighbour (an empty list must not pass).
    assert_eq!(roles, ["bottom", "left", "right", "top"], "{json}");
    assert!(statuses.iter().all(|(_, s)| s == "ok"), "{json}");
}

#[test]
fn injected_roll_and_out_of_plane_offset_are_flagged_on_their_view_only() {
    let (code, json) = check(
        &["--rotation-error", "left:z:0.5", "--offset-error", "top:z:1"],
        "misaligned.mcap",
    );
    assert_eq!(code, Some(3), "{json}");
    assert_eq!(statuses(&json).len(), 4, "{json}");
    for (role, status) in statuses(&json) {
        match role.as_str() {
            "left" | "top" => assert_eq!(status, "fail", "{role}: {json}"),
            _ => assert_eq!(status, "ok", "{role}: {json}"),
        }
    }
    let left = &json[0]["neighbours"]
        .as_array()
        .and_then(|n| n.iter().find(|v| v["role"] == "left"))
        .cloned()
        .unwrap_or_default();
    assert!(
        (left["rotation_deg"]["value"].as_f64().unwrap_or_default() - 0.5).abs() < 0.01,
        "{left}"
    );
}

#[test]
fn hand_eye_error_shows_in_the_images_only() {
    let (_, json) = check(
        &["--hand-eye-error-deg", "0,0,3", "--repeatability-mm", "0"],
        "hand_eye.mcap",
    );
    let neighbours = four_neighbours(&json);
    for n in &neighbours {
        let epipolar = n["epipolar_error_px"]["value"].as_f64().unwrap_or(f64::NAN);
        let shift = n["image_shift_px"]["value"].as_f64().unwrap_or(f64::NAN);
        // 3° of mount rotation turn a 20 mm move by 1 mm sideways: f·1 mm / 0.55 m ≈ 1.5 px at 640 px.
        assert!(epipolar < 0.05, "poses should look ideal: {n}");
        assert!(shift.abs() > 0.9 && shift.abs() < 2.5, "image shift {shift}: {n}");
    }
}

#[test]
fn a_hand_eye_error_just_over_half_a_pixel_warns() {
    // 1.25° of mount rotation: about 0.58 px of true epipolar error at the near end of the scene
    // (seed 2 of `scripts/misalignment-sweep.py`), where the image estimate reads low.
    let (code, json) = check(
        &["--seed", "2", "--hand-eye-error-deg", "0,0,1.25"],
        "hand_eye_small.mcap",
    );
    let neighbours = four_neighbours(&json);
    let truth = neighbours
        .iter()
        .filter_map(|n| n["true_epipolar_error_px"].as_f64())
        .fold(0.0f64, f64::max);
    assert!(
        (0.5..1.0).contains(&truth),
        "the case must sit just over the warning limit: {json}"
    );
    let worst = statuses(&json)
        .into_iter()
        .map(|(_, s)| s)
        .max_by_key(|s| match s.as_str() {
            "ok" => 0,
            "warn" => 1,
            _ => 2,
        });
    assert_ne!(worst.as_deref(), Some("ok"), "true {truth:.2} px not warned: {json}");
    assert_ne!(code, Some(1), "{json}");
}

#[test]
fn rectify_recovers_depth_quality_lost_to_a_rolled_view() {
    let (_dir, log) = recorded("rolled.mcap", "--resolution 640x360 --rotation-error left:z:1");
    let avg_err_px = |extra: &[&str]| {
        let mut all = vec![
            "eval",
            log.to_str().unwrap_or_default(),
            "--methods",
            "sgm-heuristic",
            "--format",
            "json",
            "-q",
        ];
        all.extend_from_slice(extra);
        let output = replay(&all);
        assert_success(&output, "replay eval");
        let rows: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("{e}"));
        rows[0]["mean"]["avg_err_px"].as_f64().unwrap_or(f64::NAN)
    };
    let (raw, rectified) = (avg_err_px(&[]), avg_err_px(&["--rectify"]));
    println!("1° roll on the left view: AvgErr {raw:.3} raw, {rectified:.3} rectified");
    assert!(rectified < raw, "rectify did not help: {rectified} ≥ {raw}");
}

#[test]
fn half_a_pixel_of_epipolar_error_warns_and_the_limits_are_configurable() {
    let dir = temp_dir();
    // A 0.1° roll of the left view: about 0.55 px of epipolar error at the image's left and right
    // edges (640 px wide).
    let log = record_args(
        dir.path(),
        "roll.mcap",
        "--resolution 640x360 --rotation-error left:z:0.1",
    );
    let log = log.to_str().unwrap_or_default();
    let left = |extra: &[&str]| {
        let mut args = vec!["check", log, "--json", "-q"];
        args.extend_from_slice(extra);
        let output = replay(&args);
        let json: serde_json::Value =
            serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("replay check printed no JSON: {e}"));
        let left = json[0]["neighbours"]
            .as_array()
            .and_then(|n| n.iter().find(|v| v["role"] == "left"))
            .cloned()
            .unwrap_or_else(|| panic!("no left view in {json}"));
        (output.status.code(), left)
    };
    let (code, view) = left(&[]);
    let epipolar = view["epipolar_error_px"]["value"].as_f64().unwrap_or(f64::NAN);
    let truth = view["true_epipolar_error_px"].as_f64().unwrap_or(f64::NAN);
    println!("0.1° roll: epipolar {epipolar:.3} px (true {truth:.3}), {view}");
    assert!((0.5..1.5).contains(&epipolar), "{view}");
    assert!(
        (epipolar - truth).abs() < 0.05,
        "the logged poses hold the roll: {view}"
    );
    assert_eq!(view["status"], "warn", "{view}");
    assert_eq!(code, Some(0), "a warning alone does not fail the check");
    let (_, relaxed) = left(&["--warn-px", "1", "--fail-px", "2"]);
    assert_eq!(relaxed["epipolar_error_px"]["status"], "ok", "{relaxed}");
    let (_, strict) = left(&["--warn-px", "0.2", "--fail-px", "0.4"]);
    assert_eq!(strict["status"], "fail", "{strict}");
    let usage = replay_str(&format!("check {} --warn-px 2 --fail-px 1", log));
    assert_eq!(
        usage.status.code(),
        Some(2),
        "a failure limit below the warning one is a usage error: {}",
        String::from_utf8_lossy(&usage.stderr)
    );
}
