//! `--rerun` of `replay` and `record`: the saved `.rrd` passes the real viewer's checks (`rerun rrd
//! verify`, `rerun rrd stats`), holds the entities the issue names, renders in the headless viewer
//! with non-empty panels, and a missing viewer fails clearly without losing the other outputs.

use std::path::{Path, PathBuf};
use std::process::Command;

use multiscopic_tests::{assert_success, binary, record_log, replay, rerun_cli, run, temp_dir};

/// Records a small five-view capture (fast at this size, still every role and ground truth).
fn small_capture(dir: &Path) -> PathBuf {
    record_log(
        dir,
        "capture.mcap",
        &["--resolution", "320x180", "--samples-per-pixel", "1"],
    )
}

/// `rerun rrd print` of a file, checked for success.
fn printed(rrd: &Path) -> String {
    let output = run(rerun_cli().args(["rrd", "print"]).arg(rrd));
    assert_success(&output, "rerun rrd print");
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// The columns `rerun rrd print` lists for one entity.
fn columns_of(printed: &str, entity: &str) -> String {
    printed
        .lines()
        .filter(|line| line.contains(&format!(" - {entity} - ")))
        .collect::<Vec<_>>()
        .join("\n")
}

fn replay_with_rerun(dir: &Path, log: &Path, rrd: &Path) {
    let output = replay(&[
        log.to_str().unwrap_or_default(),
        "--method",
        "bm-heuristic,sgm-heuristic",
        "--rectify",
        "--out",
        dir.join("results").to_str().unwrap_or_default(),
        "--rerun",
        "save",
        rrd.to_str().unwrap_or_default(),
        "-q",
    ]);
    assert_success(&output, "replay --rerun save");
}

#[test]
fn replay_saves_a_recording_the_viewer_verifies_with_every_entity() {
    let dir = temp_dir();
    let log = small_capture(dir.path());
    let rrd = dir.path().join("run.rrd");
    replay_with_rerun(dir.path(), &log, &rrd);
    for check in [["rrd", "verify"], ["rrd", "stats"]] {
        let output = run(rerun_cli().args(check).arg(&rrd));
        assert_success(&output, &format!("rerun {}", check.join(" ")));
    }
    let printed = printed(&rrd);
    let expect = |entity: &str, column: &str| {
        let columns = columns_of(&printed, entity);
        assert!(
            columns.contains(column),
            "{entity} lacks {column}; its columns:\n{columns}"
        );
    };
    for role in ["center", "left", "right", "top", "bottom"] {
        expect(&format!("/world/camera/{role}"), "Pinhole:image_from_camera");
        expect(&format!("/world/camera/{role}"), "Transform3D:translation");
        expect(&format!("/world/camera/{role}/image"), "Image:buffer");
    }
    expect("/world/camera/center/ground_truth_depth", "DepthImage:buffer");
    for method in ["bm-heuristic", "sgm-heuristic"] {
        expect(&format!("/world/camera/center/{method}"), "DepthImage:colormap");
        expect(&format!("/results/{method}/error"), "Image:buffer");
        expect(&format!("/metrics/{method}/avg_err_px"), "Scalars:scalars");
    }
    for source in ["fused", "left", "right", "top", "bottom"] {
        expect(&format!("/cost/{source}"), "Tensor:data");
    }
    expect("/cost_curves/occluded/fused", "Scalars:scalars");
    expect("/cost_curves/occluded/left", "Scalars:scalars");
    expect("/world/arm/links", "Capsules3D:lengths");
    expect("/world/table", "Boxes3D:half_sizes");
    expect("/alignment", "TextLog:text");
    // The files are written as without a viewer.
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("results/summary.json")).unwrap_or_default())
            .unwrap_or_default();
    assert_eq!(summary["sets"].as_array().map(Vec::len), Some(2), "{summary}");
    assert_eq!(summary["rerun_lost"], false);
}

/// Runs the headless viewer on `input` and saves a screenshot to `shot`. One viewer at a time
/// (software rendering of two at once can miss the viewer's render deadline), each on its own
/// gRPC port, and a second try when the first left no screenshot.
fn headless_screenshot(input: &Path, shot: &Path, window: &str) -> std::process::Output {
    static ONE_VIEWER: std::sync::Mutex<u16> = std::sync::Mutex::new(0);
    let mut runs = ONE_VIEWER.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    let mut output = None;
    for _attempt in 0..2 {
        *runs += 1;
        let port = 19_876 + *runs;
        let result = run(rerun_cli()
            .arg("--headless")
            .arg(input)
            .arg("--screenshot-to")
            .arg(shot)
            .args(["--window-size", window, "--port", &port.to_string()]));
        let done = shot.exists();
        output = Some(result);
        if done {
            break;
        }
    }
    output.unwrap_or_else(|| panic!("the headless viewer did not run"))
}

/// Mean and standard deviation of the luminance of a region of an RGBA or RGB image.
fn luminance_stats(pixels: &[u8], channels: usize, width: usize, region: [usize; 4]) -> (f64, f64) {
    let [x0, y0, x1, y1] = region;
    let mut values = Vec::new();
    for y in y0..y1 {
        for x in x0..x1 {
            let p = (y * width + x) * channels;
            values.push(
                0.299 * f64::from(pixels[p]) + 0.587 * f64::from(pixels[p + 1]) + 0.114 * f64::from(pixels[p + 2]),
            );
        }
    }
    let mean = values.iter().sum::<f64>() / values.len().max(1) as f64;
    let variance = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len().max(1) as f64;
    (mean, variance.sqrt())
}

#[test]
fn the_recording_renders_in_the_headless_viewer_with_every_panel_filled() {
    let dir = temp_dir();
    let log = small_capture(dir.path());
    let rrd = dir.path().join("run.rrd");
    replay_with_rerun(dir.path(), &log, &rrd);
    let shot = dir.path().join("shot.png");
    let output = run(rerun_cli()
        .arg("--headless")
        .arg(&rrd)
        .arg("--screenshot-to")
        .arg(&shot)
        .args(["--window-size", "1600x900"]));
    assert_success(
        &output,
        "rerun --headless --screenshot-to (needs Debian's mesa-vulkan-drivers)",
    );
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(&shot).unwrap_or_else(|e| panic!("no screenshot {}: {e}", shot.display())),
    ));
    let mut reader = decoder.read_info().unwrap_or_else(|e| panic!("{e}"));
    let mut pixels = vec![0u8; reader.output_buffer_size().unwrap_or(0)];
    let info = reader.next_frame(&mut pixels).unwrap_or_else(|e| panic!("{e}"));
    let (w, h) = (info.width as usize, info.height as usize);
    let channels = info.color_type.samples();
    // The blueprint: the 3D scene (top left), the analysis tabs (bottom left), the views grid
    // (right half). Each region must show content, not an empty dark panel.
    let regions = [
        ("3D scene", [w / 20, h / 8, w * 9 / 20, h * 4 / 10]),
        ("views grid, upper", [w * 11 / 20, h / 8, w * 19 / 20, h * 4 / 10]),
        ("views grid, lower", [w * 11 / 20, h / 2, w * 19 / 20, h * 8 / 10]),
    ];
    for (name, region) in regions {
        let (mean, deviation) = luminance_stats(&pixels, channels, w, region);
        println!("{name}: mean luminance {mean:.1}, deviation {deviation:.1}");
        assert!(
            deviation > 12.0,
            "{name} looks empty (luminance deviation {deviation:.1}, mean {mean:.1}) in {}",
            shot.display()
        );
    }
}

#[test]
fn spawn_without_a_viewer_says_how_to_get_one_and_still_writes_the_results() {
    let dir = temp_dir();
    let log = small_capture(dir.path());
    let results = dir.path().join("results");
    // A PATH without any `rerun` executable.
    let output = run(Command::new(binary("replay"))
        .env("PATH", "/usr/bin:/bin")
        .env("RERUN_ANALYTICS", "off")
        .arg(&log)
        .args(["--method", "bm-heuristic", "--rerun", "spawn", "--out"])
        .arg(&results));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(3), "exit code; stderr:\n{stderr}");
    assert!(
        stderr.contains("pip install rerun-sdk") && stderr.contains("--rerun save"),
        "the message should say how to install a viewer or save a file:\n{stderr}"
    );
    assert!(results.join("summary.json").exists(), "summary.json missing");
    let set_dir = results.join("000-toy-0");
    assert!(
        set_dir.join("bm-heuristic_disparity.pfm").exists(),
        "disparity missing in {}",
        set_dir.display()
    );
}

#[test]
fn record_streams_the_arm_and_cameras_as_it_captures() {
    let dir = temp_dir();
    let rrd = dir.path().join("record.rrd");
    let log = dir.path().join("capture.mcap");
    let output = run(Command::new(binary("record")).args([
        "--rig",
        "three-view",
        "--resolution",
        "160x90",
        "--samples-per-pixel",
        "1",
        "-q",
        "-o",
        log.to_str().unwrap_or_default(),
        "--rerun",
        "save",
        rrd.to_str().unwrap_or_default(),
    ]));
    assert_success(&output, "record --rerun save");
    assert!(log.exists(), "the log is written too");
    assert_success(&run(rerun_cli().args(["rrd", "verify"]).arg(&rrd)), "rerun rrd verify");
    let printed = printed(&rrd);
    let links = columns_of(&printed, "/world/arm/links");
    assert!(links.contains("Capsules3D:lengths"), "arm links: {links}");
    for role in ["center", "left", "right"] {
        let camera = columns_of(&printed, &format!("/world/camera/{role}/image"));
        assert!(camera.contains("Image:buffer"), "{role}: {camera}");
    }
    // The arm moves: its links are logged at every motion sample, far more rows than the
    // three views' capture times.
    let link_rows: usize = printed
        .lines()
        .filter(|line| line.contains(" - /world/arm/links - "))
        .filter_map(|line| {
            line.split(" with ")
                .nth(1)?
                .split(" rows")
                .next()?
                .trim()
                .parse::<usize>()
                .ok()
        })
        .sum();
    assert!(link_rows > 10, "arm links logged at {link_rows} times only:\n{links}");
    let stats = run(rerun_cli().args(["rrd", "stats"]).arg(&rrd));
    assert_success(&stats, "rerun rrd stats");
}

#[test]
fn the_viewer_opens_a_recorded_log_with_one_frame_per_view() {
    let dir = temp_dir();
    let log = small_capture(dir.path());
    let shot = dir.path().join("mcap.png");
    let output = headless_screenshot(&log, &shot, "1280x720");
    assert_success(&output, "rerun --headless capture.mcap");
    let stderr = String::from_utf8_lossy(&output.stderr);
    // Each view's images and calibration carry their own frame (`camera_<role>`): the viewer's
    // MCAP importer must not find two pinholes claiming one image plane.
    assert!(
        !stderr.contains("define the same child frame"),
        "frame conflict in the viewer:\n{stderr}"
    );
    assert!(shot.exists(), "no screenshot of the log");
}
