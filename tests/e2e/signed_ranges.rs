//! Signed disparity ranges: a converged rig's far points have negative disparities. A dev scene
//! cropped so that its disparities are shifted below 0 must score exactly as its unshifted crop,
//! through a described folder, `record import` and `replay` with the range from the log or from
//! `--min-disparity`; a simulated converged capture carries its signed range and truth.

use std::path::Path;

use multiscopic_tests::{assert_success, eval_json as eval, middlebury_dev, record_log, record_str, temp_dir};

/// Disparity shift of the converged copy (px).
const SHIFT: u32 = 8;

/// The simulated converged rig's principal-point shift (px).
const CONVERGE: u32 = 12;

/// Writes a Middlebury three-view scene cropped to `width − 2·SHIFT` columns: the reference from
/// column `SHIFT`, the left view from `SHIFT + left`, the right from `SHIFT − right`, so that
/// every disparity is `d − shift` where `shift = left = right` (0 or SHIFT), with the truth as a
/// PFM and a `multiscopic.toml` naming the range (`min_disparity = −shift`) and, for a shifted
/// copy, `doffs_px = shift` (the depth stays `f·b/(d + doffs)`).
fn write_crop(scene: &Path, out: &Path, shift: u32) {
    std::fs::create_dir_all(out).unwrap_or_else(|e| panic!("{e}"));
    let load =
        |name: &str| image::open(scene.join(name)).unwrap_or_else(|e| panic!("{}: {e}", scene.join(name).display()));
    let (w, h) = (load("view1.png").width(), load("view1.png").height());
    let cw = w - 2 * SHIFT;
    for (name, file, x) in [
        ("view0.png", "left.png", SHIFT + shift),
        ("view1.png", "center.png", SHIFT),
        ("view2.png", "right.png", SHIFT - shift),
    ] {
        load(name)
            .crop_imm(x, 0, cw, h)
            .to_rgb8()
            .save(out.join(file))
            .unwrap_or_else(|e| panic!("{e}"));
    }
    let truth = load("disp1.png").to_luma8();
    let disparity: Vec<f32> = (0..h)
        .flat_map(|y| (SHIFT..SHIFT + cw).map(move |x| (x, y)))
        .map(|(x, y)| match truth.get_pixel(x, y).0[0] {
            0 => f32::INFINITY,
            v => f32::from(v) / 12.0 - shift as f32,
        })
        .collect();
    viz::files::write_pfm(&out.join("truth.pfm"), cw as usize, h as usize, &disparity)
        .unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(
        out.join("multiscopic.toml"),
        format!(
            "views = [\"left.png@-1\", \"center.png@0\", \"right.png@1\"]\nground_truth = \"truth.pfm\"\n\
             baseline_mm = 40\nfocal_px = 1246.6667\ndoffs_px = {shift}\nmin_disparity = -{shift}\nnum_disparities = 32\n"
        ),
    )
    .unwrap_or_else(|e| panic!("{e}"));
}

/// Per method, the (AvgErr, Bad1) of the scene named `scene`.
fn scene_metrics(rows: &[serde_json::Value], scene: &str) -> Vec<(String, f64, f64)> {
    rows.iter()
        .map(|row| {
            let metrics = row["scenes"]
                .as_array()
                .and_then(|scenes| {
                    scenes
                        .iter()
                        .find(|s| s[0].as_str().is_some_and(|n| n.ends_with(scene)))
                })
                .map(|s| &s[1])
                .unwrap_or_else(|| panic!("no scene {scene} in {row}"));
            let value = |f: &str| metrics[f].as_f64().unwrap_or_else(|| panic!("no {f} in {metrics}"));
            (
                row["method"].as_str().unwrap_or_default().to_owned(),
                value("avg_err_px"),
                value("bad_1"),
            )
        })
        .collect()
}

#[test]
fn a_dev_scene_shifted_below_zero_scores_as_its_unshifted_crop() {
    let scene = middlebury_dev("Baby1");
    let dir = temp_dir();
    let (positive, negative) = (dir.path().join("positive"), dir.path().join("negative"));
    write_crop(&scene, &positive, 0);
    write_crop(&scene, &negative, SHIFT);
    let methods = "bm-heuristic,sgm-heuristic,gc-heuristic,mfusenet";
    // Each folder's range from its multiscopic.toml: 0..32 and −8..24.
    let rows = eval(&[
        positive.to_str().unwrap_or_default(),
        negative.to_str().unwrap_or_default(),
        "--methods",
        methods,
    ]);
    let (unshifted, shifted) = (scene_metrics(&rows, "positive"), scene_metrics(&rows, "negative"));
    assert_eq!(unshifted.len(), 4);
    for ((method, avg, bad), (_, shifted_avg, shifted_bad)) in unshifted.iter().zip(&shifted) {
        println!(
            "{method}: AvgErr {avg:.4} px unshifted, {shifted_avg:.4} shifted by −{SHIFT}; Bad1 {bad:.3} / {shifted_bad:.3} %"
        );
        assert!(*avg < 2.0, "{method} failed on the crop: AvgErr {avg}");
        assert!(
            (avg - shifted_avg).abs() <= 0.01 && (bad - shifted_bad).abs() <= 0.05,
            "{method}: AvgErr {avg} unshifted, {shifted_avg} shifted"
        );
    }
    // The same through a log: `record import` writes the folder's range into it, `replay` searches
    // it without flags, and `--min-disparity -8` on the command line gives the same.
    let log = dir.path().join("negative.mcap");
    assert_success(
        &record_str(&format!("import {} -o {}", negative.display(), log.display())),
        "record import",
    );
    let sets = replay::log::read_log_file(&log).unwrap_or_else(|e| panic!("{e}")).sets;
    assert_eq!(
        sets[0].disparity_range,
        Some(record::DisparityRange {
            min_disparity: -(SHIFT as i32),
            num_disparities: Some(32)
        })
    );
    let truth = sets[0].ground_truth_disparity().unwrap_or_default();
    let lowest = truth.iter().copied().filter(|t| t.is_finite()).fold(f32::MAX, f32::min);
    assert!(lowest < 0.0, "the shifted truth reaches below 0 (lowest {lowest})");
    let from_log = eval(&[log.to_str().unwrap_or_default(), "--methods", "sgm-heuristic"]);
    let from_flags = eval(&[
        log.to_str().unwrap_or_default(),
        "--methods",
        "sgm-heuristic",
        "--min-disparity",
        "-8",
        "--num-disparities",
        "32",
    ]);
    let sgm = shifted
        .iter()
        .find(|m| m.0 == "sgm-heuristic")
        .map_or(f64::NAN, |m| m.1);
    for rows in [&from_log, &from_flags] {
        let avg = rows[0]["mean"]["avg_err_px"].as_f64().unwrap_or(f64::NAN);
        assert!(
            (avg - sgm).abs() < 1e-9,
            "sgm-heuristic through the log: {avg}, from the folder {sgm}"
        );
    }
}

#[test]
fn a_converged_capture_carries_its_signed_range_and_scores_as_the_parallel_one() {
    let dir = temp_dir();
    let common = [
        "--rig",
        "three-view",
        "--scene",
        "toy",
        "--resolution",
        "320x240",
        "--noise-sigma",
        "0",
        "--seed",
        "3",
    ];
    let parallel = record_log(dir.path(), "parallel.mcap", &common);
    // Converged where the disparity is CONVERGE px: f·b/z = CONVERGE (f from the 60° field of
    // view), nearer than the table (≈ 9 px at this size).
    let focal_px = 160.0 / 30f64.to_radians().tan();
    let converge_m = (focal_px * 0.02 / f64::from(CONVERGE)).to_string();
    let mut args = common.to_vec();
    args.extend(["--converge-m", converge_m.as_str()]);
    let converged = record_log(dir.path(), "converged.mcap", &args);
    let read = |log: &Path| replay::log::read_log_file(log).unwrap_or_else(|e| panic!("{e}")).sets;
    let (parallel_set, converged_set) = (&read(&parallel)[0], &read(&converged)[0]);
    let range = converged_set
        .disparity_range
        .unwrap_or_else(|| panic!("a converged capture carries its range"));
    assert!(range.min_disparity < 0, "{range:?}");
    assert!((converged_set.disparity_offset_px() - f64::from(CONVERGE)).abs() < 1e-6);
    // The same scene points, SHIFT px lower, and the same depths.
    let (a, b) = (
        parallel_set.ground_truth_disparity().unwrap_or_default(),
        converged_set.ground_truth_disparity().unwrap_or_default(),
    );
    let lowest = b.iter().copied().filter(|t| t.is_finite()).fold(f32::MAX, f32::min);
    assert!(lowest < 0.0, "the table lies beyond the convergence distance: {lowest}");
    let (count, sum) = a
        .iter()
        .zip(&b)
        .filter(|(p, c)| p.is_finite() && c.is_finite())
        .fold((0usize, 0f64), |(n, s), (p, c)| (n + 1, s + f64::from(p - c)));
    assert!(count > 0 && (sum / count as f64 - f64::from(CONVERGE)).abs() < 1e-3);
    // The parallel capture searched over the converged range shifted up by CONVERGE.
    let min = (range.min_disparity + CONVERGE as i32).to_string();
    let methods = "sgm-heuristic,mfusenet";
    let parallel_rows = eval(&[
        parallel.to_str().unwrap_or_default(),
        "--methods",
        methods,
        "--min-disparity",
        &min,
    ]);
    let converged_rows = eval(&[converged.to_str().unwrap_or_default(), "--methods", methods]);
    for (p, c) in parallel_rows.iter().zip(&converged_rows) {
        let avg = |row: &serde_json::Value| row["mean"]["avg_err_px"].as_f64().unwrap_or(f64::NAN);
        println!(
            "{}: AvgErr parallel {:.4} px, converged {:.4} px",
            p["method"],
            avg(p),
            avg(c)
        );
        // The views differ only by what enters and leaves at the image borders.
        assert!((avg(p) - avg(c)).abs() <= 0.05, "{} {} {}", p["method"], avg(p), avg(c));
    }
}
