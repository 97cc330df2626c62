//! `--rerun` of `replay` and `record`: the saved `.rrd` passes the real viewer's checks (`rerun rrd
//! verify`, `rerun rrd stats`), holds the entities the issue names, renders in the headless viewer
//! with non-empty panels, and a missing viewer fails clearly without losing the other outputs.

use std::path::{Path, PathBuf};
use std::process::Command;

use multiscopic_tests::{assert_success, binary, record_args, replay_summary, rerun_cli, run, temp_dir};

/// Records a small five-view capture (fast at this size, still every role and ground truth).
fn small_capture(dir: &Path) -> PathBuf {
    record_args(dir, "capture.mcap", "--resolution 320x180 --samples-per-pixel 1")
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

/// The rows `rerun rrd print` counts for `entity` (each chunk's "with N rows").
fn rows_of(printed: &str, entity: &str) -> usize {
    columns_of(printed, entity)
        .lines()
        .filter_map(|l| l.split(" with ").nth(1)?.split(' ').next()?.parse::<usize>().ok())
        .sum()
}

/// Asserts that `rerun rrd print` lists `column` for `entity`.
fn assert_column(printed: &str, entity: &str, column: &str) {
    let columns = columns_of(printed, entity);
    assert!(
        columns.contains(column),
        "{entity} lacks {column}; its columns:\n{columns}"
    );
}

/// A small capture replayed with three methods into `dir/run.rrd`, returned.
fn recording(dir: &Path) -> PathBuf {
    let log = small_capture(dir);
    let rrd = dir.join("run.rrd");
    replay_summary(
        &log,
        &dir.join("results"),
        &format!(
            "--method bm-heuristic,sgm-heuristic,gc-stereo --rectify --rerun save {}",
            rrd.display()
        ),
    );
    rrd
}

#[test]
fn replay_saves_a_recording_the_viewer_verifies_with_every_entity() {
    let dir = temp_dir();
    let rrd = recording(dir.path());
    for check in [["rrd", "verify"], ["rrd", "stats"]] {
        let output = run(rerun_cli().args(check).arg(&rrd));
        assert_success(&output, &format!("rerun {}", check.join(" ")));
    }
    let printed = printed(&rrd);
    let expect = |entity: &str, column: &str| assert_column(&printed, entity, column);
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
    // Graph cuts leave the columns whose right-view match leaves the image unmatched: a mask.
    expect("/results/gc-stereo/no_estimate", "SegmentationImage:buffer");
    expect("/results/gc-stereo/no_estimate", "AnnotationContext:context");
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
    assert_eq!(summary["sets"].as_array().map(Vec::len), Some(3), "{summary}");
    assert_eq!(summary["rerun_lost"], false);
}

/// Runs the headless viewer on `input` and saves a screenshot to `shot`. One viewer at a time
/// (software rendering of two at once can miss the viewer's render deadline), each on its own
/// gRPC port, and a second try when the first left no screenshot.
fn headless_screenshot(inputs: &[&Path], shot: &Path, window: &str) -> std::process::Output {
    static ONE_VIEWER: std::sync::Mutex<u16> = std::sync::Mutex::new(0);
    let mut runs = ONE_VIEWER.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    let mut output = None;
    for _attempt in 0..2 {
        *runs += 1;
        let port = 19_876 + *runs;
        let result = run(rerun_cli()
            .arg("--headless")
            .args(inputs)
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

/// The screenshot's pixels: (RGB or RGBA bytes, channels, width, height).
fn read_screenshot(shot: &Path) -> (Vec<u8>, usize, usize, usize) {
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(shot).unwrap_or_else(|e| panic!("no screenshot {}: {e}", shot.display())),
    ));
    let mut reader = decoder.read_info().unwrap_or_else(|e| panic!("{e}"));
    let mut pixels = vec![0u8; reader.output_buffer_size().unwrap_or(0)];
    let info = reader.next_frame(&mut pixels).unwrap_or_else(|e| panic!("{e}"));
    let channels = info.color_type.samples();
    (pixels, channels, info.width as usize, info.height as usize)
}

/// Asserts that each named region (fractions of the width and height: x0, y0, x1, y1) of the
/// screenshot shows content: a luminance deviation above `min_deviation`, not an empty panel.
fn assert_regions_filled(shot: &Path, regions: &[(&str, [f64; 4], f64)]) {
    let (pixels, channels, w, h) = read_screenshot(shot);
    for (name, [x0, y0, x1, y1], min_deviation) in regions {
        let region = [
            (x0 * w as f64) as usize,
            (y0 * h as f64) as usize,
            (x1 * w as f64) as usize,
            (y1 * h as f64) as usize,
        ];
        let (mean, deviation) = luminance_stats(&pixels, channels, w, region);
        println!("{name}: mean luminance {mean:.1}, deviation {deviation:.1}");
        assert!(
            deviation > *min_deviation,
            "{name} looks empty (luminance deviation {deviation:.1} ≤ {min_deviation}, mean {mean:.1}) in {}",
            shot.display()
        );
    }
}

#[test]
fn the_recording_renders_in_the_headless_viewer_with_every_panel_filled() {
    let dir = temp_dir();
    let rrd = recording(dir.path());
    let shot = dir.path().join("shot.png");
    let output = headless_screenshot(&[&rrd], &shot, "1600x900");
    assert_success(
        &output,
        "rerun --headless --screenshot-to (needs Debian's mesa-vulkan-drivers)",
    );
    // The blueprint: the 3D scene (top left), the analysis tabs (bottom left), the views grid
    // (right half). Each region must show content, not an empty dark panel.
    assert_regions_filled(
        &shot,
        &[
            ("3D scene", [0.05, 0.125, 0.45, 0.4], 12.0),
            ("views grid, upper", [0.55, 0.125, 0.95, 0.4], 12.0),
            ("views grid, lower", [0.55, 0.5, 0.95, 0.8], 12.0),
        ],
    );
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
fn the_viewer_shows_a_recorded_log_with_its_cameras_and_images() {
    let dir = temp_dir();
    let log = small_capture(dir.path());
    let blueprint = log.with_extension("rbl");
    assert!(blueprint.exists(), "record writes the viewer layout beside the log");
    // The viewer's own checks of the file, then its Foxglove import: every view's image, its
    // calibration as a pinhole, the transforms.
    let check = run(rerun_cli().args(["mcap", "check"]).arg(&log));
    assert_success(&check, "rerun mcap check");
    let converted = dir.path().join("converted.rrd");
    assert_success(
        &run(rerun_cli()
            .args(["mcap", "convert"])
            .arg(&log)
            .arg("-o")
            .arg(&converted)),
        "rerun mcap convert",
    );
    assert_success(
        &run(rerun_cli().args(["rrd", "verify"]).arg(&converted)),
        "rerun rrd verify",
    );
    let printed = printed(&converted);
    let expect = |entity: &str, column: &str| assert_column(&printed, entity, column);
    expect("/tf", "Transform3D:translation");
    expect("/tf", "Transform3D:child_frame");
    for role in ["center", "left", "right", "top", "bottom"] {
        expect(&format!("/camera/{role}/image"), "Image:buffer");
        expect(&format!("/camera/{role}/image"), "CoordinateFrame:frame");
        expect(&format!("/camera/{role}/calibration"), "Pinhole:image_from_camera");
        expect(&format!("/camera/{role}/calibration"), "Pinhole:parent_frame");
    }
    // Rendered with its layout: `rerun capture.mcap capture.rbl`.
    let shot = dir.path().join("mcap.png");
    let output = headless_screenshot(&[&log, &blueprint], &shot, "1280x720");
    assert_success(&output, "rerun --headless capture.mcap capture.rbl");
    let stderr = String::from_utf8_lossy(&output.stderr);
    // Each view's images and calibration carry their own frame (`camera_<role>`): the viewer's
    // MCAP importer must not find two pinholes claiming one image plane.
    assert!(
        !stderr.contains("define the same child frame"),
        "frame conflict in the viewer:\n{stderr}"
    );
    // The layout: the 3D scene (left half: the five frustums with their images), the images grid
    // (right; the viewer's notifications cover its right column, so the left column is checked).
    // Without the images in the frustums the 3D region measures a deviation of about 7.
    assert_regions_filled(
        &shot,
        &[
            ("3D scene", [0.02, 0.1, 0.48, 0.62], 20.0),
            ("images grid, upper left", [0.51, 0.15, 0.66, 0.31], 12.0),
            ("images grid, lower left", [0.51, 0.45, 0.66, 0.6], 12.0),
        ],
    );
}

#[test]
fn the_adaptive_demo_records_plans_and_shows_their_candidates() {
    let dir = temp_dir();
    let out = dir.path().join("demo");
    let output = run(Command::new(binary("replay")).args([
        "demo",
        "--adaptive",
        "--out",
        out.to_str().unwrap_or_default(),
        "--resolution",
        "160x96",
        "--method",
        "bm-heuristic",
        "-q",
    ]));
    assert_success(&output, "replay demo --adaptive");
    let printed = printed(&out.join("demo.rrd"));
    assert_column(&printed, "/world/plan", "LineStrips3D:strips");
    assert_column(&printed, "/world/plan", "LineStrips3D:colors");
    // Four plans (views 2 … 5), one row each.
    assert_eq!(
        rows_of(&printed, "/world/plan"),
        4,
        "{}",
        columns_of(&printed, "/world/plan")
    );
    // The depth and confidence each plan after the first was made from, computed again from the
    // views taken before it.
    assert_column(&printed, "/world/camera/center/plan", "DepthImage:buffer");
    assert_eq!(
        rows_of(&printed, "/results/plan/confidence"),
        3,
        "{}",
        columns_of(&printed, "/results/plan/confidence")
    );
}
