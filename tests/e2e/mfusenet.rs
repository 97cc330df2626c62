//! MFuseNet through the real binaries: the shipped weights read by the reference Python
//! safetensors client, `replay --method mfusenet` on a recorded capture, bad weight files, and a
//! tiny `replay train` that is interrupted (by its step budget) and resumed.

use std::path::Path;
use std::process::Command;

use multiscopic_tests::{
    assert_success, binary, python_with_mcap, record_args, recorded, replay, replay_summary, run, temp_dir,
    workspace_root,
};

fn weights(file: &str) -> String {
    workspace_root().join("fuse/weights").join(file).display().to_string()
}

#[test]
fn shipped_weights_have_the_reference_state_dict_names_and_shapes() {
    let script = workspace_root().join("tests/python/check_weights.py");
    let output = run(Command::new(python_with_mcap()).arg(&script).args([
        "1",
        &weights("mfusenet-stereo.safetensors"),
        "2",
        &weights("mfusenet-3view.safetensors"),
        "4",
        &weights("mfusenet-5view.safetensors"),
        "4",
        &weights("mfusenet-5view-lite.safetensors"),
    ]));
    assert_success(&output, "check_weights.py");
    let text = String::from_utf8_lossy(&output.stdout);
    println!("{text}");
    for count in [
        "33441 trainable",
        "38929 trainable",
        "49905 trainable",
        "14425 trainable parameters, variant mfusenet-5view-lite, architecture lite, sharp volumes",
    ] {
        assert!(text.contains(count), "{count} not in {text}");
    }
}

#[test]
fn integer_products_and_the_256_bit_switch_run_and_say_so() {
    // `MULTISCOPIC_NO_AVX512` keeps the convolutions to what an AVX2 host runs: no bfloat16
    // (which needs AVX-512), f32 by default; `"precision": "int16"` takes 16-bit integer pairs.
    let (dir, log) = recorded("five.mcap", "--resolution 256x192 --samples-per-pixel 1");
    let run_with = |name: &str, config: &str| {
        let out = dir.path().join(name);
        let output = run(Command::new(binary("replay"))
            .env("MULTISCOPIC_NO_AVX512", "1")
            .args([
                log.to_str().unwrap_or_default(),
                "--method",
                "mfusenet",
                "--config",
                config,
            ])
            .args(["--outputs", "none", "--out", out.to_str().unwrap_or_default(), "-q"]));
        assert_success(&output, &format!("MULTISCOPIC_NO_AVX512=1 replay --config '{config}'"));
        let summary = read_summary(&out);
        let set = &summary["sets"][0];
        let avg = set["outputs"]["metrics"]["all"]["avg_err_px"]
            .as_f64()
            .unwrap_or(f64::NAN);
        (set["details"]["precision"].clone(), avg)
    };
    let (default_ran, f32_avg) = run_with("default", "{}");
    assert_eq!(default_ran, "f32", "bfloat16 needs the 512-bit paths");
    let (int16_ran, int16_avg) = run_with("int16", r#"{"precision": "int16"}"#);
    let expected = if cfg!(all(target_arch = "x86_64", target_feature = "avx2")) {
        "int16"
    } else {
        "f32"
    };
    assert_eq!(int16_ran, expected);
    println!("AvgErr f32 {f32_avg:.4} px, int16 {int16_avg:.4} px");
    assert!(f32_avg.is_finite() && f32_avg < 3.0, "f32 AvgErr {f32_avg}");
    assert!(
        (int16_avg - f32_avg).abs() <= 0.01 * f32_avg.max(0.1),
        "int16 AvgErr {int16_avg} against {f32_avg}"
    );
}

#[test]
fn replay_runs_mfusenet_and_names_bad_weight_files() {
    let (dir, log) = recorded("five.mcap", "--resolution 256x192 --samples-per-pixel 1");
    let out = dir.path().join("results");
    let summary = replay_summary(&log, &out, "--method mfusenet,mfusenet-stereo");
    let log = log.to_str().unwrap_or_default();
    for method in ["mfusenet", "mfusenet-stereo"] {
        let set = summary["sets"]
            .as_array()
            .and_then(|sets| sets.iter().find(|s| s["method"] == method))
            .unwrap_or_else(|| panic!("no {method} in {summary}"));
        let avg = set["outputs"]["metrics"]["all"]["avg_err_px"]
            .as_f64()
            .unwrap_or(f64::NAN);
        println!("{method}: AvgErr {avg:.3} px");
        assert!(avg.is_finite() && avg < 3.0, "{method}: AvgErr {avg}");
        let files = set["outputs"]["files"].as_array().map_or(0, Vec::len);
        assert!(files >= 5, "{method} wrote {files} files");
    }

    // Test-time flips: the network and its mirror image averaged, recorded in the summary.
    let flipped_out = dir.path().join("flipped");
    let output = replay(&[
        log,
        "--method",
        "mfusenet",
        "--config",
        r#"{"flips": true}"#,
        "--out",
        flipped_out.to_str().unwrap_or_default(),
        "-q",
    ]);
    assert_success(&output, "replay --method mfusenet --config '{\"flips\": true}'");
    let flipped = read_summary(&flipped_out);
    assert_eq!(flipped["config"]["flips"], true, "{flipped}");
    // The image-guided weighted median is MFuseNet's default, with its parameters recorded.
    assert_eq!(flipped["config"]["weighted_median"]["radius_px"], 10, "{flipped}");
    let avg = flipped["sets"][0]["outputs"]["metrics"]["all"]["avg_err_px"]
        .as_f64()
        .unwrap_or(f64::NAN);
    println!("mfusenet with flips: AvgErr {avg:.3} px");
    assert!(avg.is_finite() && avg < 3.0, "with flips: AvgErr {avg}");

    // Bad weight files: exit 1, the file (and tensor) named, nothing panics.
    let truncated = dir.path().join("truncated.safetensors");
    let bytes = std::fs::read(weights("mfusenet-3view.safetensors")).unwrap_or_default();
    std::fs::write(&truncated, &bytes[..bytes.len() / 3]).unwrap_or_else(|e| panic!("{e}"));
    let cases: [(&str, String, &str); 3] = [
        (
            "mfusenet",
            dir.path().join("missing.safetensors").display().to_string(),
            "missing.safetensors",
        ),
        ("mfusenet", truncated.display().to_string(), "truncated.safetensors"),
        (
            "mfusenet-stereo",
            weights("mfusenet-3view.safetensors"),
            "concat.0.weight",
        ),
    ];
    // Exit 1 with `expected` in the message, and no panic.
    let fails_naming = |args: &[&str], expected: &str| {
        let mut all = vec![log];
        all.extend_from_slice(args);
        all.extend(["--out", out.to_str().unwrap_or_default()]);
        let output = replay(&all);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{args:?}: {stderr}");
        assert!(
            stderr.contains(expected) && !stderr.contains("panicked"),
            "{args:?}: {stderr}"
        );
    };
    for (method, file, expected) in cases {
        fails_naming(&["--method", method, "--weights", &file], expected);
    }
    // The five-view weights on a three-view selection say what the network needs.
    let five = weights("mfusenet-5view.safetensors");
    fails_naming(
        &["--method", "mfusenet", "--neighbours", "left,right", "--weights", &five],
        "five-view network needs",
    );
    // A bad parameter is named with its value: a readout reach that is no distance, a share of
    // the locking correction outside 0..=1, a farther view's vote of nothing, and a bad
    // weighted-median parameter for a classical method that opts in as well.
    let cases = [
        ("mfusenet", r#"{"refine_reach": -1}"#, "refine_reach = -1"),
        ("mfusenet", r#"{"locking_strength": 2}"#, "locking_strength = 2"),
        ("mfusenet", r#"{"farther_vote": 0}"#, "farther_vote = 0"),
        (
            "sgm-heuristic",
            r#"{"weighted_median": {"sigma_colour": 0}}"#,
            "weighted_median.sigma_colour = 0",
        ),
    ];
    for (method, config, expected) in cases {
        // The JSON holds blanks: the arguments as a list.
        fails_naming(&["--method", method, "--config", config], expected);
    }
}

fn train(dir: &Path, steps: &str) -> serde_json::Value {
    train_with(dir, steps, &[])
}

/// `replay train` of the three-view network on a tiny dataset (two 96×72 captures, 12
/// disparities, 32-px crops) in `run_dir`, `extra` appended.
fn tiny_training(run_dir: &Path, dataset: &Path, steps: &str, extra: &[&str]) -> std::process::Output {
    let (run_dir, dataset) = (
        run_dir.to_str().unwrap_or_default(),
        dataset.to_str().unwrap_or_default(),
    );
    let mut args: Vec<&str> =
        "train --views 2 --resolution 96x72 --num-disparities 12 --crop-px 32 --train-sets 2 --val-sets 1 -q"
            .split_whitespace()
            .collect();
    args.extend(["--dir", run_dir, "--dataset-dir", dataset, "--steps", steps]);
    args.extend_from_slice(extra);
    replay(&args)
}

fn train_with(dir: &Path, steps: &str, extra: &[&str]) -> serde_json::Value {
    let run_dir = dir.join("run");
    let every = ["--checkpoint-every", "2", "--validate-every", "3"];
    let output = tiny_training(&run_dir, &dir.join("dataset"), steps, &[&every[..], extra].concat());
    assert_success(&output, "replay train");
    serde_json::from_slice(&std::fs::read(run_dir.join("training.json")).unwrap_or_default())
        .unwrap_or_else(|e| panic!("training.json: {e}"))
}

#[test]
fn training_grows_its_crops_on_schedule() {
    // `--crop-px-from STEP:PX` trains the steps from STEP on with crops of PX. A stage that has
    // not begun changes nothing (the same weights, byte for byte, as a run without it); a stage
    // added when a run resumes is the same run, and its larger crops give other weights; a stage
    // that does not parse or fit is a usage error.
    let dir = temp_dir();
    let dataset = dir.path().join("dataset");
    let weights =
        |name: &str| std::fs::read(dir.path().join(name).join("mfusenet-3view.safetensors")).unwrap_or_default();
    let trained = |name: &str, steps: &str, extra: &[&str]| -> serde_json::Value {
        let run = dir.path().join(name);
        assert_success(&tiny_training(&run, &dataset, steps, extra), "replay train");
        serde_json::from_slice(&std::fs::read(run.join("training.json")).unwrap_or_default())
            .unwrap_or_else(|e| panic!("training.json: {e}"))
    };
    let plain = trained("plain", "4", &[]);
    let later = trained("later", "4", &["--crop-px-from", "10:64"]);
    assert_eq!(later["config"]["crop_stages"][0]["crop_px"], 64, "{later}");
    assert!(plain["config"].get("crop_stages").is_none(), "{plain}");
    // The weights' metadata names the run's configuration, which differs: compare the tensors.
    let tensors = |bytes: &[u8]| -> Vec<Vec<u8>> {
        let file = safetensors::SafeTensors::deserialize(bytes).unwrap_or_else(|e| panic!("{e}"));
        let mut names: Vec<String> = file.names().into_iter().map(str::to_owned).collect();
        names.sort();
        names
            .iter()
            .map(|n| file.tensor(n).map(|t| t.data().to_vec()).unwrap_or_default())
            .collect()
    };
    let (plain_weights, later_weights) = (weights("plain"), weights("later"));
    assert!(
        !plain_weights.is_empty() && tensors(&plain_weights) == tensors(&later_weights),
        "a stage not begun changed the weights"
    );

    trained("grown", "2", &[]);
    let grown = trained("grown", "4", &["--crop-px-from", "2:64"]);
    assert_eq!(grown["resumed_at_step"], 2, "{grown}");
    assert_eq!(grown["steps_done"], 4, "{grown}");
    assert!(
        tensors(&weights("grown")) != tensors(&plain_weights),
        "64 px crops from step 2 trained as 32 px ones"
    );

    for (stage, says) in [("2-64", "expected STEP:PX"), ("2:66", "crop_stages"), ("2:64", "")] {
        let extra = ["--crop-px-from", "1:48", "--crop-px-from", stage];
        let output = tiny_training(&dir.path().join("bad"), &dataset, "0", &extra);
        let stderr = String::from_utf8_lossy(&output.stderr);
        if says.is_empty() {
            assert_success(&output, "replay train with two stages");
        } else {
            assert_eq!(output.status.code(), Some(2), "{stage}: {stderr}");
            assert!(stderr.contains(says), "{stage}: {stderr}");
        }
    }
}

#[test]
fn training_can_keep_its_batch_norm_statistics_up_to_date() {
    // `--recalibrate-every N` re-estimates the statistics every N steps: the option reaches the
    // run's configuration, and runs with it (at the start and at steps 2 and 4) finish with a
    // finite validation. (Resuming is `training_resumes_and_its_weights_run`'s.)
    let dir = temp_dir();
    let first = train_with(dir.path(), "2", &["--recalibrate-every", "2"]);
    assert_eq!(first["config"]["recalibrate_every"], 2, "{first}");
    let second = train_with(dir.path(), "4", &["--recalibrate-every", "2"]);
    assert_eq!(second["steps_done"], 4, "{second}");
    assert!(
        second["val_avg_err_px"].as_f64().is_some_and(f64::is_finite),
        "{second}"
    );
}

#[test]
fn training_can_track_its_batch_norm_statistics() {
    // `--statistics-momentum M` moves the running statistics towards each step's crop's: from the
    // same calibration (same seed, same data), a tracked run's statistics differ from a frozen
    // run's, and its validation (eval mode, with those statistics) is finite.
    let (frozen_dir, tracked_dir) = (temp_dir(), temp_dir());
    let frozen = train(frozen_dir.path(), "2");
    let tracked = train_with(tracked_dir.path(), "2", &["--statistics-momentum", "0.5"]);
    assert_eq!(tracked["config"]["statistics_momentum"], 0.5, "{tracked}");
    assert!(frozen["config"].get("statistics_momentum").is_none(), "{frozen}");
    assert!(
        tracked["val_avg_err_px"].as_f64().is_some_and(f64::is_finite),
        "{tracked}"
    );
    let statistics = |dir: &Path| -> Vec<f32> {
        let path = dir.join("run/mfusenet-3view.safetensors");
        let (net, _) =
            fuse::mfusenet::weights::load(&path, Some(2)).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        net.layers().flat_map(|l| l.bn.running_mean.clone()).collect()
    };
    let (a, b) = (statistics(frozen_dir.path()), statistics(tracked_dir.path()));
    assert_eq!(a.len(), b.len());
    let moved = a.iter().zip(&b).filter(|(x, y)| (*x - *y).abs() > 1e-6).count();
    assert!(moved > a.len() / 2, "{moved} of {} running means moved", a.len());
}

#[test]
fn training_can_average_its_weights_and_switch_the_average_on_when_resuming() {
    // A run without an average resumes with `--average-decay` (the average never changes a
    // step, so it is the same run): the checkpoint then keeps the average beside the live
    // weights, the exported file is the average (not the live weights) and says so, and a later
    // resume continues the same average.
    let dir = temp_dir();
    let first = train(dir.path(), "3");
    assert_eq!(first["steps_done"], 3, "{first}");
    let average = ["--average-decay", "0.5"];
    let second = train_with(dir.path(), "6", &average);
    assert_eq!(second["resumed_at_step"], 3, "{second}");
    assert_eq!(second["config"]["average_decay"], 0.5, "{second}");
    assert!(first["config"].get("average_decay").is_none(), "{first}");
    let checkpoint = dir.path().join("run/checkpoint.safetensors");
    let header = safetensors_header(&checkpoint);
    assert_eq!(
        header["__metadata__"]["average_updates"], "3",
        "{}",
        header["__metadata__"]
    );
    assert_eq!(
        header["average.classify.bias"], header["model.classify.bias"],
        "{header}"
    );
    let tensor = |path: &Path, name: &str| -> Vec<u8> {
        let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let tensors = safetensors::SafeTensors::deserialize(&bytes).unwrap_or_else(|e| panic!("{e}"));
        let view = tensors
            .tensor(name)
            .unwrap_or_else(|e| panic!("{name} in {}: {e}", path.display()));
        view.data().to_vec()
    };
    let weights = dir.path().join("run/mfusenet-3view.safetensors");
    assert_eq!(
        tensor(&weights, "classify.bias"),
        tensor(&checkpoint, "average.classify.bias"),
        "the exported weights are the average"
    );
    assert_ne!(
        tensor(&weights, "concat.0.weight"),
        tensor(&checkpoint, "model.concat.0.weight"),
        "the average equals the live weights"
    );
    let metadata = safetensors_header(&weights)["__metadata__"].clone();
    assert_eq!(metadata["average_decay"], "0.5", "{metadata}");
    assert!(
        second["val_avg_err_px"].as_f64().is_some_and(f64::is_finite),
        "{second}"
    );
    let third = train_with(dir.path(), "8", &average);
    assert_eq!(third["resumed_at_step"], 6, "{third}");
    // The run keeps its best-validated network across the legs: the step whose validation in
    // the curves is the least, with that validation in its metadata.
    let curves = std::fs::read_to_string(dir.path().join("run/curves.csv")).unwrap_or_else(|e| panic!("{e}"));
    let best_row = curves
        .lines()
        .skip(1)
        .filter_map(|line| {
            let fields: Vec<&str> = line.split(',').collect();
            Some((fields[0].parse::<u64>().ok()?, fields.get(2)?.parse::<f64>().ok()?))
        })
        .fold(None, |best: Option<(u64, f64)>, (step, avg)| match best {
            Some((_, b)) if b <= avg => best,
            _ => Some((step, avg)),
        })
        .unwrap_or_else(|| panic!("no validation in the curves:\n{curves}"));
    let best = safetensors_header(&dir.path().join("run/best.safetensors"))["__metadata__"].clone();
    assert_eq!(best["steps"], best_row.0.to_string(), "{best}\n{curves}");
    let kept: f64 = best["val_avg_err_px"]
        .as_str()
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{best}"));
    assert!((kept - best_row.1).abs() < 1e-3, "{kept} against {best_row:?}");
    let header = safetensors_header(&checkpoint);
    assert_eq!(
        header["__metadata__"]["average_updates"], "5",
        "{}",
        header["__metadata__"]
    );
    // Other options in the same folder are another run: refused, naming what differs, and the
    // run's checkpoint is left as it was (it used to be started over and overwritten).
    let before = std::fs::read(&checkpoint).unwrap_or_default();
    let output = tiny_training(
        &dir.path().join("run"),
        &dir.path().join("dataset"),
        "10",
        &["--learning-rate", "0.01"],
    );
    assert_eq!(output.status.code(), Some(1), "{output:?}");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("another run") && stderr.contains("learning_rate: 0.0005 → 0.01"),
        "{stderr}"
    );
    assert_eq!(
        std::fs::read(&checkpoint).unwrap_or_default(),
        before,
        "the checkpoint changed"
    );
}

/// `--views any`: the view-count-agnostic network trains on random subsets of the neighbours of
/// grid-cross captures (twelve kept per sample), from a fixed network's file, resumes, its
/// weights say what they are, and `mfusenet` runs them over every view of a set (a line of five
/// here), nearest first.
#[test]
fn the_view_count_agnostic_network_trains_resumes_and_is_named() {
    let dir = temp_dir();
    let run = dir.path().join("any");
    let shipped = weights("mfusenet-5view.safetensors");
    let extra = ["--init-weights", shipped.as_str(), "--flips", "--checkpoint-every", "2"];
    let train = |steps: &str| {
        let (run_dir, dataset) = (run.to_str().unwrap_or_default(), dir.path().join("dataset"));
        let mut args: Vec<&str> =
            "train --views any --rig grid-cross --resolution 96x72 --num-disparities 12 --crop-px 32 --train-sets 2 --val-sets 1 -q"
                .split_whitespace()
                .collect();
        args.extend(["--dir", run_dir, "--dataset-dir", dataset.to_str().unwrap_or_default()]);
        args.extend(["--steps", steps]);
        args.extend_from_slice(&extra);
        let output = replay(&args);
        assert_success(&output, "replay train --views any");
        serde_json::from_slice::<serde_json::Value>(&std::fs::read(run.join("training.json")).unwrap_or_default())
            .unwrap_or_default()
    };
    let first = train("2");
    assert_eq!(first["steps_done"], 2, "{first}");
    assert_eq!(first["config"]["rig"], "grid-cross", "{first}");
    // Each cached sample keeps the twelve neighbours within two baselines.
    assert_sample_keeps(&dir.path().join("dataset"), 12);
    let second = train("4");
    assert_eq!(second["resumed_at_step"], 2, "{second}");
    assert!(
        second["val_avg_err_px"].as_f64().is_some_and(f64::is_finite),
        "{second}"
    );
    let weights = run.join("mfusenet-any.safetensors");
    let header = safetensors_header(&weights);
    assert_eq!(header["__metadata__"]["view_fusion"], "mean-max", "{header}");
    assert_eq!(header["__metadata__"]["views"], "any");
    assert_eq!(header["concat.0.weight"]["shape"], serde_json::json!([4, 8, 7, 7, 7]));
    // `mfusenet` runs it over the four neighbours of a line of five, the near pair first, and
    // says so.
    let (logs, log) = recorded("any.mcap", "--rig line5 --resolution 96x72 --samples-per-pixel 1");
    // (No blank in the JSON: the helper splits its arguments at blanks.)
    let config = format!("{{\"weights\":\"{}\"}}", weights.display());
    let summary = replay_summary(
        &log,
        &logs.path().join("out"),
        &format!("--method mfusenet --config {config}"),
    );
    let set = &summary["sets"][0];
    assert_eq!(set["details"]["network"], "view-count-agnostic", "{set}");
    assert_eq!(
        set["details"]["views"],
        serde_json::json!(["left", "right", "left2", "right2"]),
        "{set}"
    );
    assert!(
        set["outputs"]["metrics"]["all"]["avg_err_px"]
            .as_f64()
            .is_some_and(f64::is_finite),
        "{set}"
    );
}

/// `--rig line5 --views 4`: the five-view network trains on lines of five (the near pair in
/// its left and right inputs, the far pair in its top and bottom ones), its file says so, and
/// `mfusenet` with `line_cross` runs it on a line of five's four neighbours.
#[test]
fn the_five_view_network_trains_on_lines_of_five_and_runs_on_them() {
    let dir = temp_dir();
    let run = dir.path().join("line");
    let dataset = dir.path().join("dataset");
    let shipped = weights("mfusenet-5view.safetensors");
    let mut args: Vec<&str> =
        "train --views 4 --rig line5 --resolution 96x72 --num-disparities 12 --crop-px 32 --train-sets 2 --val-sets 1 --steps 2 -q"
            .split_whitespace()
            .collect();
    args.extend([
        "--dir",
        run.to_str().unwrap_or_default(),
        "--dataset-dir",
        dataset.to_str().unwrap_or_default(),
        "--init-weights",
        shipped.as_str(),
        "--flips",
    ]);
    assert_success(&replay(&args), "replay train --rig line5");
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("training.json")).unwrap_or_default()).unwrap_or_default();
    assert_eq!(record["config"]["rig"], "line5", "{record}");
    // Each cached sample keeps the line's four neighbours.
    assert_sample_keeps(&dataset, 4);
    let weights = run.join("mfusenet-5view.safetensors");
    let header = safetensors_header(&weights);
    assert_eq!(
        header["__metadata__"]["input_order"], "left,right,left2,right2",
        "{header}"
    );
    let (logs, log) = recorded("line.mcap", "--rig line5 --resolution 96x72 --samples-per-pixel 1");
    // (No blank in the JSON: the helper splits its arguments at blanks.)
    // A file trained on lines implies `line_cross`.
    let config = format!("{{\"weights\":\"{}\"}}", weights.display());
    let summary = replay_summary(
        &log,
        &logs.path().join("out"),
        &format!("--method mfusenet --config {config}"),
    );
    let set = &summary["sets"][0];
    assert_eq!(
        set["details"]["networks"],
        serde_json::json!(["five-view [left, right, left2, right2]"]),
        "{set}"
    );
    assert!(
        set["outputs"]["metrics"]["all"]["avg_err_px"]
            .as_f64()
            .is_some_and(f64::is_finite),
        "{set}"
    );
    // The shipped files: the three-view network on each pair by default, the shipped five-view
    // file on all four with `line_cross`.
    let networks = |config: &str, out: &str| {
        let summary = replay_summary(
            &log,
            &logs.path().join(out),
            &format!("--method mfusenet --config {config}"),
        );
        summary["sets"][0]["details"]["networks"].clone()
    };
    assert_eq!(
        networks("{}", "default"),
        serde_json::json!(["three-view [left, right]", "three-view [left2, right2]"])
    );
    assert_eq!(
        networks("{\"line_cross\":true}", "crossed"),
        serde_json::json!(["five-view (lite) [left, right, left2, right2]"])
    );
}

#[test]
fn a_cross_missing_arms_runs_the_five_view_network_with_them_filled() {
    // A 3 × 3 grid replayed as a T (left, right, top) and as an L (left, top): by default the
    // five-view network, each missing arm's input filled by its opposite view; with
    // `fill_cross` off, the pair's three-view network and the stereo one on each odd view.
    let (logs, log) = recorded("grid.mcap", "--rig grid3x3 --resolution 96x72 --samples-per-pixel 1");
    let run_with = |neighbours: &str, config: &str, out: &str| {
        let summary = replay_summary(
            &log,
            &logs.path().join(out),
            &format!("--method mfusenet --rectify --neighbours {neighbours} --config {config}"),
        );
        let set = &summary["sets"][0];
        let avg = set["outputs"]["metrics"]["all"]["avg_err_px"]
            .as_f64()
            .unwrap_or(f64::NAN);
        assert!(avg.is_finite() && avg < 3.0, "{neighbours} {config}: AvgErr {avg}");
        set["details"]["networks"].clone()
    };
    assert_eq!(
        run_with("left,right,top", "{}", "t"),
        serde_json::json!(["five-view (lite) [left, right, top, top]"])
    );
    assert_eq!(
        run_with("left,top", "{}", "l"),
        serde_json::json!(["five-view (lite) [left, left, top, top]"])
    );
    assert_eq!(
        run_with("left,right,top", "{\"fill_cross\":false}", "t-unfilled"),
        serde_json::json!(["three-view [left, right]", "stereo [top]"])
    );
    // A single axis view beside a diagonal has nothing to fill: the stereo network alone.
    let summary = replay_summary(
        &log,
        &logs.path().join("diagonal"),
        "--method mfusenet --rectify --neighbours top-left,right",
    );
    assert_eq!(summary["sets"][0]["details"]["network"], "stereo", "{summary}");
}

#[test]
fn a_renewing_pool_trains_on_new_captures_deletes_the_old_and_resumes_alike() {
    // Two captures in memory, one replaced every two steps in turn: steps 2 and 4 bring in
    // captures 2 and 3, steps 6 and 8 captures 4 and 5 (2 and 3 then leave the cache; the
    // first two stay), also when the run stops at 6 and resumes (the pool at a step is a
    // function of the step: `TrainConfig::pool_index`, unit-tested against the renewals made
    // one by one).
    let dir = temp_dir();
    let dataset = dir.path().join("dataset");
    let renew = ["--renew-every", "2", "--checkpoint-every", "2", "--validate-every", "5"];
    let cached = || -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(&dataset)
            .map(|entries| {
                entries
                    .filter_map(|e| e.ok()?.file_name().into_string().ok())
                    .filter(|n| n.starts_with("train-") || n.starts_with("renew-"))
                    .map(|n| n.split('-').take(2).collect::<Vec<_>>().join("-"))
                    .collect()
            })
            .unwrap_or_default();
        names.sort();
        names
    };
    let run = |name: &str, steps: &str| {
        let output = tiny_training(&dir.path().join(name), &dataset, steps, &renew);
        assert_success(&output, "replay train --renew-every 2");
    };
    run("legs", "6");
    assert_eq!(cached(), ["renew-0002", "renew-0003", "train-0000", "train-0001"]);
    run("legs", "10");
    assert_eq!(cached(), ["renew-0004", "renew-0005", "train-0000", "train-0001"]);
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("legs/training.json")).unwrap_or_default())
            .unwrap_or_else(|e| panic!("training.json: {e}"));
    assert_eq!(summary["config"]["renew_every"], 2, "{summary}");
    assert_eq!(summary["resumed_at_step"], 6, "{summary}");
    let tensors = |name: &str| safetensors_tensor_bytes(&dir.path().join(name).join("mfusenet-3view.safetensors"));
    let legs = tensors("legs");
    assert!(!legs.is_empty());
    // Without renewal the same steps give other weights (the captures differ from step 2 on).
    let fixed = tiny_training(&dir.path().join("fixed"), &dataset, "10", &renew[2..]);
    assert_success(&fixed, "replay train");
    assert!(legs != tensors("fixed"), "renewal changed nothing");
}

#[test]
fn training_resumes_and_its_weights_run() {
    let dir = temp_dir();
    let first = train(dir.path(), "4");
    assert_eq!(first["steps_done"], 4);
    // A longer budget resumes from the checkpoint instead of starting over.
    let second = train(dir.path(), "6");
    assert_eq!(second["steps_done"], 6);
    assert_eq!(first["resumed_at_step"], 0, "{first}");
    assert_eq!(second["resumed_at_step"], 4, "{second}");
    let curves = std::fs::read_to_string(dir.path().join("run/curves.csv")).unwrap_or_default();
    let steps: Vec<&str> = curves.lines().skip(1).filter_map(|l| l.split(',').next()).collect();
    assert_eq!(steps, ["1", "2", "3", "4", "5", "6"], "{curves}");
    assert!(dir.path().join("run/curves.rrd").is_file());
    assert!(
        second["val_avg_err_px"].as_f64().is_some_and(f64::is_finite),
        "{second}"
    );
    // The weights load through --weights, and their metadata says how to read the output
    // (the estimate that validated better).
    let weights = dir.path().join("run/mfusenet-3view.safetensors");
    let header = safetensors_header(&weights);
    let metadata = &header["__metadata__"];
    assert!(
        matches!(metadata["estimate"].as_str(), Some("refine" | "soft-argmin")),
        "{metadata}"
    );
    assert!(
        metadata["val_refined_avg_err_px"]
            .as_str()
            .and_then(|v| v.parse::<f64>().ok())
            .is_some_and(f64::is_finite),
        "{metadata}"
    );
    // The refined readout's locking curve, fitted on the training captures, is in the metadata;
    // `--calibrate` fits it again for a file (the same captures: the same curve) and writes the
    // file with the same tensors.
    let curve: Vec<f64> = metadata["locking_curve"]
        .as_str()
        .and_then(|v| serde_json::from_str(v).ok())
        .unwrap_or_default();
    assert!(curve.len() == 10 && curve.iter().all(|v| v.is_finite()), "{metadata}");
    let calibrated = dir.path().join("calibrated.safetensors");
    let output = replay(&[
        "train",
        "--calibrate",
        weights.to_str().unwrap_or_default(),
        "--weights-out",
        calibrated.to_str().unwrap_or_default(),
        "--dataset-dir",
        dir.path().join("dataset").to_str().unwrap_or_default(),
        "-q",
    ]);
    assert_success(&output, "replay train --calibrate");
    let again = safetensors_header(&calibrated);
    assert_eq!(
        again["__metadata__"]["locking_curve"], metadata["locking_curve"],
        "{again}"
    );
    assert!(again["__metadata__"]["locking_note"].is_string(), "{again}");
    let before = safetensors_tensor_bytes(&weights);
    assert!(!before.is_empty());
    assert_eq!(before, safetensors_tensor_bytes(&calibrated), "tensors changed");
    replay_three_view_with(dir.path(), &weights);
}

#[test]
fn a_sharp_network_trains_resumes_and_runs() {
    // `--sharp`: the dataset keeps each neighbour's sharp volume (its own cache key), the network
    // takes them beside its input volumes (`concat` reads five channels a view), the run resumes,
    // its weights say how the sharp volumes are made, and `mfusenet` makes them to run the file.
    // Another run in the same folder without `--sharp` is refused.
    let dir = temp_dir();
    let first = train_with(dir.path(), "2", &["--sharp"]);
    assert!(first["config"]["sharp"].is_object(), "{first}");
    let second = train_with(dir.path(), "4", &["--sharp"]);
    assert_eq!(second["resumed_at_step"], 2, "{second}");
    assert_eq!(second["steps_done"], 4, "{second}");
    assert!(
        second["val_avg_err_px"].as_f64().is_some_and(f64::is_finite),
        "{second}"
    );
    let weights = dir.path().join("run/mfusenet-3view.safetensors");
    let header = safetensors_header(&weights);
    assert_eq!(
        header["concat.0.weight"]["shape"][1], 10,
        "two views, five channels each"
    );
    assert!(header["__metadata__"]["sharp_spec"].is_string(), "{header}");
    let files: Vec<String> = std::fs::read_dir(dir.path().join("dataset"))
        .map(|entries| {
            entries
                .filter_map(Result::ok)
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    assert!(files.iter().any(|f| f.starts_with("train-0000-")), "{files:?}");
    let plain = tiny_training(&dir.path().join("run"), &dir.path().join("dataset"), "4", &[]);
    assert_eq!(
        plain.status.code(),
        Some(1),
        "{}",
        String::from_utf8_lossy(&plain.stderr)
    );
    assert!(String::from_utf8_lossy(&plain.stderr).contains("sharp"));
    let out = replay_three_view_with(dir.path(), &weights);
    assert!(out.join("summary.json").is_file());
}

/// Records a tiny three-view capture into `dir` and replays it with `mfusenet` and `weights`
/// (which must run); returns the results folder.
fn replay_three_view_with(dir: &Path, weights: &Path) -> std::path::PathBuf {
    let log = record_args(
        dir,
        "three.mcap",
        "--rig three-view --resolution 96x72 --samples-per-pixel 1",
    );
    let out = dir.join("out");
    let output = replay(&[
        log.to_str().unwrap_or_default(),
        "--method",
        "mfusenet",
        "--weights",
        weights.to_str().unwrap_or_default(),
        "--out",
        out.to_str().unwrap_or_default(),
        "-q",
    ]);
    assert_success(&output, &format!("replay with the weights {}", weights.display()));
    out
}

/// The `summary.json` that `replay --out DIR` wrote.
fn read_summary(out: &Path) -> serde_json::Value {
    let path = out.join("summary.json");
    serde_json::from_slice(&std::fs::read(&path).unwrap_or_default())
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The first cached training sample in `dataset` holds exactly `views` neighbours' volumes.
fn assert_sample_keeps(dataset: &Path, views: usize) {
    let sample = std::fs::read_dir(dataset)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .find(|p| p.extension().is_some_and(|x| x == "safetensors"))
        .unwrap_or_default();
    let tensors = safetensors_header(&sample);
    assert!(
        tensors.get(format!("volume.{}", views - 1)).is_some() && tensors.get(format!("volume.{views}")).is_none(),
        "{tensors}"
    );
}

/// A safetensors file's header as JSON (each tensor's `shape` and `dtype`, and `__metadata__`),
/// read with the `safetensors` crate.
fn safetensors_header(path: &Path) -> serde_json::Value {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (_, metadata) = safetensors::SafeTensors::read_metadata(&bytes)
        .unwrap_or_else(|e| panic!("safetensors header of {}: {e}", path.display()));
    let tensors = safetensors::SafeTensors::deserialize(&bytes)
        .unwrap_or_else(|e| panic!("safetensors file {}: {e}", path.display()));
    let mut header = serde_json::Map::new();
    if let Some(entries) = metadata.metadata() {
        header.insert("__metadata__".into(), serde_json::json!(entries));
    }
    for (name, view) in tensors.tensors() {
        header.insert(
            name,
            serde_json::json!({"shape": view.shape(), "dtype": format!("{:?}", view.dtype())}),
        );
    }
    serde_json::Value::Object(header)
}

/// Every tensor's bytes, in the order of their names.
fn safetensors_tensor_bytes(path: &Path) -> Vec<u8> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let tensors = safetensors::SafeTensors::deserialize(&bytes)
        .unwrap_or_else(|e| panic!("safetensors file {}: {e}", path.display()));
    let mut named = tensors.tensors();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    named.iter().flat_map(|(_, view)| view.data().to_vec()).collect()
}

#[test]
fn training_the_lite_architecture_gives_a_file_mfusenet_runs() {
    // `--architecture lite`: smaller kernels, the same tensor names; the file says so in its
    // metadata and its shapes, `replay --weights` runs it, and it cannot seed a paper run.
    let dir = temp_dir();
    let run = train_with(dir.path(), "2", &["--architecture", "lite"]);
    assert_eq!(run["config"]["architecture"], "lite", "{run}");
    assert!(run["val_avg_err_px"].as_f64().is_some_and(f64::is_finite), "{run}");
    let weights = dir.path().join("run/mfusenet-3view-lite.safetensors");
    let header = safetensors_header(&weights);
    assert_eq!(header["__metadata__"]["architecture"], "lite", "{header}");
    assert_eq!(header["__metadata__"]["variant"], "mfusenet-3view-lite", "{header}");
    assert_eq!(
        header["concat.0.weight"]["shape"],
        serde_json::json!([4, 8, 3, 3, 3]),
        "{header}"
    );
    assert_eq!(
        header["feature.0.0.weight"]["shape"],
        serde_json::json!([4, 1, 5, 5, 5]),
        "{header}"
    );
    let out = replay_three_view_with(dir.path(), &weights);
    assert!(read_summary(&out)["sets"][0]["outputs"]["metrics"].is_object());
    // A paper run cannot start from a lite file: an error naming the option.
    let output = tiny_training(
        &dir.path().join("paper"),
        &dir.path().join("dataset"),
        "1",
        &["--init-weights", weights.to_str().unwrap_or_default()],
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("architecture") && stderr.contains("lite"), "{stderr}");
}

#[test]
fn training_can_give_its_network_context_below_the_range() {
    // `--context-below 4`: the dataset's volumes are 4 slices deeper (costs under 0), the run's
    // configuration says it, and the weights' metadata asks inference for the same context.
    let dir = temp_dir();
    let run = train_with(dir.path(), "2", &["--context-below", "4"]);
    assert_eq!(run["config"]["context_below"], 4, "{run}");
    assert!(run["val_avg_err_px"].as_f64().is_some_and(f64::is_finite), "{run}");
    // The crops' targets count their slices from the context's first, as the volumes do: the
    // inputs' own winner-take-all lands near them (a target shifted by the context once too
    // often puts it 4 px off).
    let wta = run["val_wta_avg_err_px"].as_f64().unwrap_or(f64::NAN);
    assert!(
        wta < 2.5,
        "winner-take-all of the inputs is {wta} px from the targets: {run}"
    );
    let metadata = &safetensors_header(&dir.path().join("run/mfusenet-3view.safetensors"))["__metadata__"];
    assert_eq!(metadata["context_below"], "4", "{metadata}");
    let samples: Vec<_> = std::fs::read_dir(dir.path().join("dataset"))
        .map(|entries| entries.filter_map(Result::ok).map(|e| e.path()).collect())
        .unwrap_or_default();
    assert_eq!(samples.len(), 3, "{samples:?}");
    for sample in &samples {
        let header = safetensors_header(sample);
        // 96×72 px, 12 disparities + 4 below.
        assert_eq!(
            header["volume.0"]["shape"],
            serde_json::json!([72, 96, 16]),
            "{}",
            sample.display()
        );
    }
    // With the disparity shift and the mirror augmentation as well, on the same dataset (both
    // are drawn per crop: the samples are reused, none is added), and the metadata still asks
    // for the context.
    let shifted_run = dir.path().join("shifted");
    let dataset = dir.path().join("dataset");
    let output = tiny_training(
        &shifted_run,
        &dataset,
        "2",
        &["--context-below", "4", "--disparity-shift", "4", "--flips"],
    );
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let metadata = &safetensors_header(&shifted_run.join("mfusenet-3view.safetensors"))["__metadata__"];
    assert_eq!(metadata["context_below"], "4", "{metadata}");
    let shifted: serde_json::Value = std::fs::read_to_string(shifted_run.join("training.json"))
        .ok()
        .and_then(|text| serde_json::from_str(&text).ok())
        .unwrap_or_default();
    assert_eq!(shifted["config"]["context_below"], 4, "{shifted}");
    assert_eq!(shifted["config"]["disparity_shift"], 4, "{shifted}");
    assert_eq!(shifted["config"]["flips"], true, "{shifted}");
    assert!(
        shifted["val_avg_err_px"].as_f64().is_some_and(f64::is_finite),
        "{shifted}"
    );
    assert_eq!(std::fs::read_dir(&dataset).map(Iterator::count).unwrap_or(0), 3);
    // Not a multiple of 4: an error naming the option.
    let other = dir.path().join("other");
    let output = tiny_training(&other, &dataset, "2", &["--context-below", "6"]);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success() && stderr.contains("context_below"), "{stderr}");
}

#[test]
fn a_wide_range_goes_coarse_to_fine_and_the_summary_says_what_the_network_saw() {
    // A 60 mm baseline at 320×240 puts the toy scene at about 27–40 px, searched over 0..64. So
    // small a volume (4.9 M voxels) runs at full size by default; without the volume budget the
    // network (the lite five-view one) runs at half size over 0..33 with the 8 slices of context
    // below its file asks for (−8..33) and the full-size band is ± 2 px.
    let (dir, log) = recorded(
        "wide.mcap",
        "--resolution 320x240 --baseline-mm 60 --samples-per-pixel 1",
    );
    let out = dir.path().join("results");
    let output = replay(&[
        log.to_str().unwrap_or_default(),
        "--method",
        "mfusenet,sgm-heuristic",
        "--num-disparities",
        "64",
        "--out",
        out.to_str().unwrap_or_default(),
    ]);
    assert_success(&output, "replay --method mfusenet,sgm-heuristic --num-disparities 64");
    let summary = read_summary(&out);
    let sets = summary["sets"].as_array().cloned().unwrap_or_default();
    assert_eq!(sets.len(), 2, "{summary}");
    assert_eq!(sets[0]["details"]["scale"], "1/1", "{summary}");
    // SGM has nothing to add.
    assert!(sets[1].get("details").is_none(), "{summary}");
    let coarse_out = dir.path().join("results-coarse");
    let output = replay(&[
        log.to_str().unwrap_or_default(),
        "--method",
        "mfusenet",
        "--num-disparities",
        "64",
        "--config",
        r#"{"max_direct_voxels": 0}"#,
        "--out",
        coarse_out.to_str().unwrap_or_default(),
    ]);
    assert_success(
        &output,
        "replay --method mfusenet --num-disparities 64 (no volume budget)",
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("architecture lite")
            && stderr.contains("scale 1/2")
            && stderr.contains("network_min_disparity -8, network_num_disparities 41"),
        "the log names the level and range the network saw: {stderr}"
    );
    let coarse = read_summary(&coarse_out);
    let coarse_sets = coarse["sets"].as_array().cloned().unwrap_or_default();
    assert_eq!(coarse_sets.len(), 1, "{coarse}");
    let details = &coarse_sets[0]["details"];
    assert_eq!(details["scale"], "1/2", "{coarse}");
    assert_eq!(details["network_width"], 160, "{coarse}");
    assert_eq!(details["full_size_band_px"], 2, "{coarse}");
    // A fixed network names the neighbours it took, in its input order.
    assert_eq!(
        details["views"],
        serde_json::json!(["left", "right", "top", "bottom"]),
        "{coarse}"
    );
    let avg = |set: &serde_json::Value| {
        set["outputs"]["metrics"]["all"]["avg_err_px"]
            .as_f64()
            .unwrap_or(f64::NAN)
    };
    println!(
        "0..64: mfusenet AvgErr {:.3} px at full size, {:.3} px coarse to fine, sgm-heuristic {:.3} px",
        avg(&sets[0]),
        avg(&coarse_sets[0]),
        avg(&sets[1])
    );
    for mfusenet in [&sets[0], &coarse_sets[0]] {
        assert!(avg(mfusenet) < 1.0, "{summary}\n{coarse}");
        assert!(avg(mfusenet) <= avg(&sets[1]) + 0.05, "{summary}\n{coarse}");
    }
}

/// A Python with `torch` and `safetensors`: `$TORCH_PYTHON`, else the checkout's `.venv-torch`
/// (`python3 -m venv .venv-torch && .venv-torch/bin/pip install torch safetensors`). `None` when
/// neither has them: CI installs no torch (5 GB with its CUDA libraries).
fn python_with_torch() -> Option<std::path::PathBuf> {
    let candidates = std::env::var_os("TORCH_PYTHON")
        .map(std::path::PathBuf::from)
        .into_iter()
        .chain([workspace_root().join(".venv-torch/bin/python")]);
    candidates.into_iter().find(|python| {
        Command::new(python)
            .args(["-c", "import torch, safetensors"])
            .output()
            .is_ok_and(|o| o.status.success())
    })
}

#[test]
fn a_training_run_moves_to_pytorch_and_back() {
    // `replay train --steps 0` makes the dataset and the step-0 checkpoint; `train-torch.py`
    // takes three steps of two crops in PyTorch and writes the checkpoint back; `replay train`
    // resumes it (nothing left: it validates and writes the weights, which keep the PyTorch
    // steps on record), and then trains two more steps of its own from PyTorch's Adam moments.
    // Both validate the same network on the same crops: the same AvgErr.
    let Some(python) = python_with_torch() else {
        eprintln!(
            "skipped: no Python with torch and safetensors (set TORCH_PYTHON or make .venv-torch); \
             this test checks scripts/train-torch.py, which CI does not install"
        );
        return;
    };
    // Once without a moving average of the weights and once with one (and larger crops from
    // step 1, which PyTorch's steps take too): PyTorch updates the checkpoint's average as
    // `replay train` does, and both validate it.
    let plain = ["--context-below", "4", "--disparity-shift", "4", "--flips"];
    let averaged = [&plain[..], &["--average-decay", "0.9", "--crop-px-from", "1:48"]].concat();
    // And a sharp network, whose crops carry each view's sharp volume after the views'.
    let sharp = [&plain[..], &["--sharp"]].concat();
    for options in [&plain[..], &averaged[..], &sharp[..]] {
        moves_to_pytorch_and_back(&python, options);
    }
}

fn moves_to_pytorch_and_back(python: &Path, options: &[&str]) {
    let dir = temp_dir();
    let (run_dir, dataset) = (dir.path().join("run"), dir.path().join("dataset"));
    assert_success(
        &tiny_training(&run_dir, &dataset, "0", options),
        "replay train --steps 0",
    );
    let output = run(Command::new(python)
        .arg(workspace_root().join("scripts/train-torch.py"))
        .args(["--dir", &run_dir.display().to_string()])
        .args(["--dataset-dir", &dataset.display().to_string()])
        .args(["--steps", "3", "--batch", "2", "--device", "cpu"]));
    assert_success(&output, "train-torch.py");
    let text = String::from_utf8_lossy(&output.stdout);
    println!("{text}");
    let torch_avg: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("step 3: validation AvgErr "))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no step-3 validation in {text}"));

    let summary = |output: std::process::Output| -> serde_json::Value {
        assert_success(&output, "replay train");
        serde_json::from_slice(&std::fs::read(run_dir.join("training.json")).unwrap_or_default())
            .unwrap_or_else(|e| panic!("training.json: {e}"))
    };
    let finished = summary(tiny_training(&run_dir, &dataset, "3", options));
    assert_eq!(finished["resumed_at_step"], 3, "{finished}");
    assert_eq!(finished["steps_done"], 3, "{finished}");
    let rust_avg = finished["val_avg_err_px"].as_f64().unwrap_or(f64::NAN);
    assert!(
        (rust_avg - torch_avg).abs() < 2e-3,
        "AvgErr: PyTorch {torch_avg}, replay {rust_avg}"
    );
    let metadata = safetensors_header(&run_dir.join("mfusenet-3view.safetensors"))["__metadata__"].clone();
    assert_eq!(metadata["torch_steps"], "3", "{metadata}");
    assert_eq!(metadata["torch_batch"], "2", "{metadata}");
    if options.contains(&"--average-decay") {
        assert_eq!(metadata["average_updates"], "3", "{metadata}");
    } else {
        assert!(metadata.get("average_updates").is_none(), "{metadata}");
    }

    let longer = summary(tiny_training(&run_dir, &dataset, "5", options));
    assert_eq!(longer["resumed_at_step"], 3, "{longer}");
    assert_eq!(longer["steps_done"], 5, "{longer}");
    let curves = std::fs::read_to_string(run_dir.join("curves.csv")).unwrap_or_default();
    assert_eq!(curves.lines().count(), 6, "{curves}");
}
