//! Depth quality: the paper's claims on real and simulated data, through the real binaries.

use std::path::Path;

use multiscopic_tests::{
    assert_success, eval_json, json_strings, middlebury_dev, recorded, replay_str, replay_summary, temp_dir,
};

fn metric(rows: &[serde_json::Value], method: &str, region: &str, field: &str) -> f64 {
    rows.iter()
        .find(|r| r["method"] == method)
        .and_then(|r| r[region][field].as_f64())
        .unwrap_or_else(|| panic!("no {region}.{field} for {method} in {rows:?}"))
}

#[test]
fn middlebury_multiscopic_beats_stereo_and_opencv_sgbm() {
    let data = middlebury_dev("");
    let rows = eval_json(&[
        data.to_str().unwrap_or_default(),
        "--methods",
        "bm-stereo,bm-heuristic,sgm-stereo,sgm-heuristic",
    ]);
    let avg = |m: &str| metric(&rows, m, "mean", "avg_err_px");
    println!(
        "AvgErr bm-stereo {:.3} bm-heuristic {:.3} sgm-stereo {:.3} sgm-heuristic {:.3}; sgm-heuristic Bad1 {:.2} %",
        avg("bm-stereo"),
        avg("bm-heuristic"),
        avg("sgm-stereo"),
        avg("sgm-heuristic"),
        metric(&rows, "sgm-heuristic", "mean", "bad_1")
    );
    assert!(
        avg("bm-heuristic") <= 0.8 * avg("bm-stereo"),
        "bm-heuristic is not 20 % better than bm-stereo"
    );
    assert!(
        avg("sgm-heuristic") <= 0.8 * avg("sgm-stereo"),
        "sgm-heuristic is not 20 % better than sgm-stereo"
    );
    // OpenCV StereoSGBM on these seven scenes (../shared/data/README.md): AvgErr 0.456, Bad1 7.69 %.
    assert!(
        avg("sgm-heuristic") < 0.456,
        "sgm-heuristic AvgErr {} does not beat OpenCV SGBM",
        avg("sgm-heuristic")
    );
    assert!(metric(&rows, "sgm-heuristic", "mean", "bad_1") < 7.69);
    // The confidence ranks: each scene's most confident 75 % and the scenes' pooled 75 % err
    // well below all pixels (measured: 0.53 and 0.30 of them for sgm-heuristic).
    for curve in ["sparsification", "sparsification_pooled"] {
        let ratio = metric(&rows, "sgm-heuristic", curve, "avg_err_top75_px")
            / metric(&rows, "sgm-heuristic", curve, "avg_err_all_px");
        println!("sgm-heuristic {curve}: most confident 75 % / all = {ratio:.3}");
        assert!(ratio < 0.7, "{curve}: {ratio}");
    }
    assert!(
        (metric(&rows, "sgm-heuristic", "sparsification", "avg_err_all_px") - avg("sgm-heuristic")).abs() < 1e-9,
        "the per-scene curve ends at the scenes' mean AvgErr"
    );
}

#[test]
fn five_views_beat_three_which_beat_stereo_most_in_occlusions() {
    let (_dir, log) = recorded("five.mcap", "--resolution 640x360 --captures 2");
    let log = log.to_str().unwrap_or_default();
    let five = eval_json(&[
        log,
        "--rectify",
        "--methods",
        "bm-stereo,bm-heuristic,sgm-stereo,sgm-heuristic",
    ]);
    let three = eval_json(&[
        log,
        "--rectify",
        "--neighbours",
        "left,right",
        "--methods",
        "bm-heuristic,sgm-heuristic",
    ]);
    for family in ["bm", "sgm"] {
        let method = format!("{family}-heuristic");
        let stereo = format!("{family}-stereo");
        let (s, t, f) = (
            metric(&five, &stereo, "mean", "avg_err_px"),
            metric(&three, &method, "mean", "avg_err_px"),
            metric(&five, &method, "mean", "avg_err_px"),
        );
        println!("{family}: AvgErr stereo {s:.3}, three-view {t:.3}, five-view {f:.3}");
        assert!(
            f < t && t < s,
            "{family}: five-view {f} < three-view {t} < stereo {s} does not hold"
        );
        let occluded_gain =
            1.0 - metric(&five, &method, "occluded", "avg_err_px") / metric(&five, &stereo, "occluded", "avg_err_px");
        let overall_gain = 1.0 - f / s;
        println!(
            "{family}: five-view vs stereo, AvgErr −{:.0} % overall, −{:.0} % in occlusions",
            100.0 * overall_gain,
            100.0 * occluded_gain
        );
        assert!(
            occluded_gain > overall_gain,
            "{family}: occlusions did not improve most"
        );
    }
}

#[test]
fn outputs_writes_only_the_files_asked_for_and_the_same_numbers() {
    let (dir, log) = recorded("capture.mcap", "--resolution 320x180 --rig three-view");
    let files_of = |out: &Path| -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(out.join("000-toy-0"))
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    let all = dir.path().join("all");
    let every = replay_summary(&log, &all, "--method bm-heuristic");
    let depth = dir.path().join("depth");
    let some = replay_summary(&log, &depth, "--method bm-heuristic --outputs depth,disparity");
    assert_eq!(
        files_of(&depth),
        [
            "bm-heuristic_depth_m.pfm",
            "bm-heuristic_depth_mm.png",
            "bm-heuristic_disparity.pfm",
            "bm-heuristic_metrics.json"
        ]
    );
    assert!(files_of(&all).len() > 8, "{:?}", files_of(&all));
    // The same disparity, metrics and alignment report whichever files are written.
    for name in ["bm-heuristic_disparity.pfm", "bm-heuristic_depth_m.pfm"] {
        assert_eq!(
            std::fs::read(all.join("000-toy-0").join(name)).ok(),
            std::fs::read(depth.join("000-toy-0").join(name)).ok(),
            "{name}"
        );
    }
    for key in ["metrics", "alignment"] {
        let pick = |summary: &serde_json::Value| {
            let set = &summary["sets"][0];
            if key == "metrics" {
                set["outputs"]["metrics"].clone()
            } else {
                set[key].clone()
            }
        };
        assert_eq!(pick(&every), pick(&some), "{key}");
        assert!(!pick(&some).is_null(), "{key} missing");
    }
    let none = dir.path().join("none");
    replay_summary(&log, &none, "--method bm-heuristic --outputs none");
    assert_eq!(files_of(&none), ["bm-heuristic_metrics.json"]);
    let wrong = multiscopic_tests::replay(&[
        log.to_str().unwrap_or_default(),
        "--outputs",
        "depth,cloud",
        "--out",
        none.to_str().unwrap_or_default(),
    ]);
    assert_eq!(wrong.status.code(), Some(2), "a usage error");
    let stderr = String::from_utf8_lossy(&wrong.stderr);
    assert!(stderr.contains("cloud") && stderr.contains("points"), "{stderr}");
}

#[test]
fn replay_writes_result_files_and_a_result_log_other_tools_read() {
    let (dir, log) = recorded("capture.mcap", "--resolution 320x180 --rig three-view");
    let out = dir.path().join("results");
    let result_log = dir.path().join("results.mcap");
    replay_summary(
        &log,
        &out,
        &format!("--method bm-heuristic --out-mcap {}", result_log.display()),
    );
    let set_dir = out.join("000-toy-0");
    let (w, h, disparity) =
        viz::files::read_pfm(&set_dir.join("bm-heuristic_disparity.pfm")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((w, h), (320, 180));
    assert!(
        disparity.iter().all(|d| d.is_finite() && *d >= 0.0 && *d < 32.0),
        "disparities out of the search range"
    );
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(set_dir.join("bm-heuristic_metrics.json")).unwrap_or_default())
            .unwrap_or_else(|e| panic!("metrics.json: {e}"));
    assert!(
        metrics["metrics"]["all"]["avg_err_px"]
            .as_f64()
            .is_some_and(|e| e < 2.0),
        "{metrics}"
    );
    // The signed error: estimate − truth, its mean magnitude the metrics' AvgErr.
    let (_, _, signed) =
        viz::files::read_pfm(&set_dir.join("bm-heuristic_error_px.pfm")).unwrap_or_else(|e| panic!("{e}"));
    let known: Vec<f64> = signed.iter().filter(|e| e.is_finite()).map(|e| f64::from(*e)).collect();
    assert!(
        known.len() > signed.len() / 2,
        "{} of {} pixels with a truth",
        known.len(),
        signed.len()
    );
    let mean_abs = known.iter().map(|e| e.abs()).sum::<f64>() / known.len() as f64;
    let avg_err = metrics["metrics"]["all"]["avg_err_px"].as_f64().unwrap_or(f64::NAN);
    assert!(
        (mean_abs - avg_err).abs() < 1e-3,
        "signed error's mean |e| {mean_abs} against AvgErr {avg_err}"
    );
    assert!(
        known.iter().any(|e| *e > 0.0) && known.iter().any(|e| *e < 0.0),
        "both signs"
    );
    let names: Vec<String> = std::fs::read_dir(&set_dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    let pngs = names.iter().filter(|n| n.ends_with(".png")).count();
    assert_eq!(
        pngs, 4,
        "depth PNG, colour-mapped disparity PNG, error map and confidence: {names:?}"
    );
    // The confidence: a 16-bit PNG and a PFM of values in [0, 1], not all alike, and the
    // sparsification curve in the metrics (its most confident half better than all pixels).
    let confidence_png = image::open(set_dir.join("bm-heuristic_confidence.png")).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        matches!(confidence_png, image::DynamicImage::ImageLuma16(_)),
        "16-bit grey"
    );
    let (_, _, confidence) =
        viz::files::read_pfm(&set_dir.join("bm-heuristic_confidence.pfm")).unwrap_or_else(|e| panic!("{e}"));
    assert!(confidence.iter().all(|c| (0.0..=1.0).contains(c)));
    assert!(confidence.iter().any(|c| *c < 0.5) && confidence.iter().any(|c| *c > 0.5));
    let top50 = metrics["metrics"]["sparsification"]["avg_err_top50_px"]
        .as_f64()
        .unwrap_or_else(|| panic!("no sparsification in {metrics}"));
    assert!(
        top50 < metrics["metrics"]["all"]["avg_err_px"].as_f64().unwrap_or(0.0),
        "{metrics}"
    );
    assert!(
        names.contains(&"bm-heuristic_error_0.0-4.0px.png".to_owned()),
        "{names:?}"
    );
    // The point cloud: a PLY header naming one vertex per pixel with an estimate.
    let ply = std::fs::read(set_dir.join("bm-heuristic_points.ply")).unwrap_or_default();
    let header = String::from_utf8_lossy(&ply[..ply.len().min(400)]).into_owned();
    let vertices: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or(0);
    assert!(
        header.starts_with("ply\nformat binary_little_endian 1.0") && vertices > 320 * 180 / 2,
        "PLY header: {header}"
    );
    let body = ply.len()
        - header
            .find("end_header\n")
            .map_or(ply.len(), |i| i + "end_header\n".len());
    assert_eq!(body, vertices * 15, "15 bytes a vertex (x y z float, r g b)");
    let script = multiscopic_tests::workspace_root().join("tests/python/check_mcap.py");
    let check = multiscopic_tests::run(
        std::process::Command::new(multiscopic_tests::python_with_mcap())
            .arg(script)
            .arg(&result_log),
    );
    assert_success(&check, "Python mcap on the result log");
    let report: serde_json::Value = serde_json::from_slice(&check.stdout).unwrap_or_else(|e| panic!("{e}"));
    for topic in [
        "/results/bm-heuristic/disparity",
        "/results/bm-heuristic/depth",
        "/results/bm-heuristic/confidence",
        "/results/calibration",
        "/results/summary",
    ] {
        assert_eq!(report["topics"][topic].as_u64(), Some(1), "{topic}: {report}");
    }
    let metadata = json_strings(&report["metadata"]);
    assert!(
        metadata.contains(&"multiscopic.recording") && metadata.contains(&"multiscopic.replay"),
        "{metadata:?}"
    );
}

#[test]
fn graph_cuts_leave_occlusions_unmatched_and_five_views_beat_stereo() {
    let (dir, log) = recorded("metal.mcap", "--scene workpiece --resolution 320x240 --captures 1");
    let log_arg = log.to_str().unwrap_or_default();
    // Without filling, pixels left without a match have no estimate (+inf in the PFM).
    let out = dir.path().join("results");
    replay_summary(&log, &out, "--rectify --method gc-heuristic");
    let set_dir = std::fs::read_dir(&out)
        .unwrap_or_else(|e| panic!("{}: {e}", out.display()))
        .filter_map(Result::ok)
        .find(|e| e.path().is_dir())
        .map(|e| e.path())
        .unwrap_or_else(|| panic!("no set folder in {}", out.display()));
    let (w, h, disparity) =
        viz::files::read_pfm(&set_dir.join("gc-heuristic_disparity.pfm")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((w, h), (320, 240));
    let occluded = disparity.iter().filter(|d| !d.is_finite()).count();
    println!("gc-heuristic: {occluded} of {} pixels occluded", w * h);
    assert!(occluded > 0 && occluded < w * h / 5, "{occluded} occluded pixels");
    assert!(
        disparity
            .iter()
            .filter(|d| d.is_finite())
            .all(|d| *d >= 0.0 && *d < 32.0)
    );

    let fill = r#"{"fill_occlusions": true}"#;
    let five = eval_json(&[
        log_arg,
        "--rectify",
        "--methods",
        "gc-stereo,gc-heuristic",
        "--config",
        fill,
    ]);
    assert_eq!(metric(&five, "gc-heuristic", "mean", "missing"), 0.0, "filled");
    let (stereo, multi) = (
        metric(&five, "gc-stereo", "mean", "avg_err_px"),
        metric(&five, "gc-heuristic", "mean", "avg_err_px"),
    );
    let (stereo_occluded, multi_occluded) = (
        metric(&five, "gc-stereo", "occluded", "avg_err_px"),
        metric(&five, "gc-heuristic", "occluded", "avg_err_px"),
    );
    println!("gc AvgErr stereo {stereo:.3} five-view {multi:.3}; occluded {stereo_occluded:.3} -> {multi_occluded:.3}");
    assert!(
        multi < stereo,
        "five-view gc-heuristic {multi} is not better than gc-stereo {stereo}"
    );
    assert!(multi_occluded < stereo_occluded);
}

#[test]
fn a_line_of_five_runs_through_every_method_against_its_three_view_subset() {
    let (_dir, log) = recorded("line5.mcap", "--rig line5 --resolution 320x180 --seed 3");
    let log = log.to_str().unwrap_or_default();
    let methods: Vec<&str> = fuse::methods::registry().iter().map(|e| e.name).collect();
    let methods = methods.join(",");
    let line = eval_json(&[log, "--rectify", "--methods", &methods]);
    let three = eval_json(&[log, "--rectify", "--neighbours", "left,right", "--methods", &methods]);
    for entry in fuse::methods::registry() {
        let m = entry.name;
        let (l, t) = (
            metric(&line, m, "mean", "avg_err_px"),
            metric(&three, m, "mean", "avg_err_px"),
        );
        let (lo, to) = (
            metric(&line, m, "occluded", "avg_err_px"),
            metric(&three, m, "occluded", "avg_err_px"),
        );
        println!("{m}: AvgErr line of five {l:.3} (occluded {lo:.3}), three-view subset {t:.3} (occluded {to:.3})");
        assert!(l.is_finite() && t.is_finite(), "{m}: no result");
        let uses_far_views = !m.ends_with("-stereo");
        if m == "mfusenet" {
            // The outer pair through the three-view network beside the inner one: used, and
            // never costing more than 2 % of AvgErr.
            assert_ne!(l, t, "{m}: the views at ±2 baselines were not used");
            assert!(l <= 1.02 * t, "{m}: AvgErr {l} with five views against {t} with three");
        } else if uses_far_views {
            // The outer views change the fused costs …
            assert_ne!(l, t, "{m}: the views at ±2 baselines were not used");
            // … and a multiscopic method on five views still beats its family's stereo.
            if let Some(stereo) = fuse::methods::stereo_baseline_of(m) {
                let s = metric(&line, stereo, "occluded", "avg_err_px");
                assert!(
                    lo < s,
                    "{m}: occluded AvgErr {lo} on five views is not below {stereo}'s {s}"
                );
            }
        } else {
            // Stereo methods use one neighbour only.
            assert_eq!(l, t, "{m}: a method without far-view inputs changed with them");
        }
    }
}

#[test]
fn the_demo_writes_where_git_ignores_it() {
    let dir = temp_dir();
    let out = dir.path().join("demo");
    let output = replay_str(&format!(
        "demo --out {} --resolution 160x96 --method bm-heuristic -q",
        out.display()
    ));
    assert_success(&output, "replay demo");
    assert!(out.join("capture.mcap").is_file() && out.join("results/summary.json").is_file());
    let ignore = std::fs::read_to_string(out.join(".gitignore")).unwrap_or_default();
    assert!(
        ignore.lines().any(|l| l.trim() == "*"),
        "the demo folder does not ignore its contents: {ignore:?}"
    );
    // git agrees, when it is installed: nothing of the demo shows as new work.
    let git = |args: &[&str]| {
        std::process::Command::new("git")
            .current_dir(dir.path())
            .args(args)
            .output()
    };
    if git(&["init", "-q"]).is_ok_and(|o| o.status.success()) {
        let status = git(&["status", "--porcelain", "--untracked-files=all"]).unwrap_or_else(|e| panic!("{e}"));
        let listed = String::from_utf8_lossy(&status.stdout);
        assert!(
            !listed.contains("demo/"),
            "git status lists the demo's outputs:\n{listed}"
        );
    } else {
        println!("git not available: checked the .gitignore only");
    }
}

#[test]
fn errors_at_a_common_baseline_are_the_set_errors_scaled_to_it() {
    // A set at 30 mm evaluated at 15 mm: every disparity, and so every error, halves; an error
    // over 1 px at 15 mm is one over 2 px at 30 mm. The occluded region becomes the cross's at
    // 15 mm, the same pixels whatever views a set has.
    let (_dir, path) = recorded(
        "wide.mcap",
        "--rig five-view --baseline-mm 30 --resolution 160x120 --samples-per-pixel 1",
    );
    let log = path.to_str().unwrap_or_default();
    let own = eval_json(&[log, "--methods", "sgm-heuristic"]);
    let common = eval_json(&[log, "--methods", "sgm-heuristic", "--at-baseline-mm", "15"]);
    let at = |rows: &[serde_json::Value], field: &str| metric(rows, "sgm-heuristic", "mean", field);
    assert!(
        (at(&common, "avg_err_px") - 0.5 * at(&own, "avg_err_px")).abs() < 1e-6,
        "AvgErr {} at 15 mm against {} at 30 mm",
        at(&common, "avg_err_px"),
        at(&own, "avg_err_px")
    );
    assert!((at(&common, "bad_1") - at(&own, "bad_2")).abs() < 1e-9);
    // Half the baseline hides fewer pixels.
    let hidden = |rows: &[serde_json::Value]| metric(rows, "sgm-heuristic", "occluded", "pixels");
    assert!(
        0.0 < hidden(&common) && hidden(&common) < hidden(&own),
        "occluded pixels {} at 15 mm, {} at 30 mm",
        hidden(&common),
        hidden(&own)
    );
    let output = replay_str(&format!("eval {log} --methods sgm-heuristic --at-baseline-mm 0"));
    assert_eq!(output.status.code(), Some(2), "{output:?}");
}
