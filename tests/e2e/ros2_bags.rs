//! ROS 2 bags in and out: `record --format ros2` writes a bag that `replay` reads as it reads our
//! own log, and that `rosbags`, `mcap-ros2-support`, Foxglove's reader and Rerun read; a bag shaped
//! like a real UR + camera recording (written by `rosbags`, not by us: the camera streaming through
//! the moves, `/tf` at 20 Hz, the hand-eye transform on `/tf_static`, joints at 125 Hz out of
//! order) gives the set that `record import` gives of the same images; bad bags fail clearly.

use std::path::{Path, PathBuf};
use std::process::Command;

use multiscopic_tests::{
    assert_success, copy_messages, foxglove_read, middlebury_dev, python_with_mcap, record_args, replay,
    replay_summary, rerun_cli, run, strip_capture_events, temp_dir, workspace_root,
};
use replay::viewset::{View, ViewSet};

const SIM: &str = "--rig five-view --resolution 160x120 --seed 3 --samples-per-pixel 1";

fn read(path: &Path) -> replay::log::LogContents {
    replay::log::read_log_file(path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()))
}

fn views(set: &ViewSet) -> Vec<&View> {
    let mut all: Vec<&View> = std::iter::once(&set.reference).chain(&set.neighbours).collect();
    all.sort_by_key(|v| v.offset);
    all
}

fn assert_same_pose(a: &View, b: &View, what: &str) {
    let moved = (a.world_from_camera.translation.vector - b.world_from_camera.translation.vector).norm();
    let turned = a
        .world_from_camera
        .rotation
        .angle_to(&b.world_from_camera.rotation)
        .to_degrees();
    assert!(
        moved <= 1e-5 && turned <= 1e-3,
        "{what} view {:?}: poses differ by {:.6} mm and {turned:.6}°",
        a.offset,
        moved * 1e3
    );
}

/// The disparity files of a replay's output folder, by method.
fn disparities(out: &Path) -> Vec<(String, Vec<u8>)> {
    let mut found = Vec::new();
    for set in std::fs::read_dir(out)
        .unwrap_or_else(|e| panic!("{e}"))
        .filter_map(Result::ok)
    {
        if !set.path().is_dir() {
            continue;
        }
        for file in std::fs::read_dir(set.path())
            .unwrap_or_else(|e| panic!("{e}"))
            .filter_map(Result::ok)
        {
            let name = file.file_name().to_string_lossy().into_owned();
            if let Some(method) = name.strip_suffix("_disparity.pfm") {
                found.push((
                    method.to_owned(),
                    std::fs::read(file.path()).unwrap_or_else(|e| panic!("{e}")),
                ));
            }
        }
    }
    found.sort();
    found
}

fn python(script: &str, args: &[&Path]) -> std::process::Output {
    run(Command::new(python_with_mcap())
        .arg(workspace_root().join("tests/python").join(script))
        .args(args))
}

#[test]
fn a_simulated_capture_as_a_ros2_bag_replays_like_our_own_log() {
    let dir = temp_dir();
    let own = record_args(dir.path(), "own.mcap", SIM);
    let bag = record_args(dir.path(), "capture", &format!("{SIM} --format ros2"));
    let file = bag.join("capture_0.mcap");
    assert!(
        bag.join("metadata.yaml").is_file() && file.is_file(),
        "the bag directory lacks its files"
    );

    // The same sets, views, images, ground truth and poses through the capture events.
    let (a, b) = (read(&own), read(&bag));
    assert_eq!(a.sets.len(), 1);
    assert_eq!(b.sets.len(), 1, "{:?}", b.incomplete_sets);
    let (a, b) = (&a.sets[0], &b.sets[0]);
    assert_eq!((&a.name, &a.rig, a.baseline_m), (&b.name, &b.rig, b.baseline_m));
    assert_eq!(a.ground_truth_depth_m, b.ground_truth_depth_m);
    assert_eq!(a.surface_class, b.surface_class);
    for (x, y) in views(a).into_iter().zip(views(b)) {
        assert_eq!(
            (&x.role, x.offset, x.camera, x.capture_time_nanos),
            (&y.role, y.offset, y.camera, y.capture_time_nanos)
        );
        assert!(x.rgb == y.rgb, "view {} differs", x.role);
        assert_same_pose(x, y, "bag");
    }

    // Without the events, the set comes from the stream: TF at each image's stamp (the arm's
    // links at the motion rate, the hand-eye transform on /tf_static) gives the same poses.
    let stripped = dir.path().join("stream.mcap");
    copy_messages(&file, &stripped, |topic, _| topic != "/capture/events");
    let stream = read(&stripped);
    assert_eq!(stream.sets.len(), 1, "{:?}", stream.notes());
    let report = stream.stream.as_ref().unwrap_or_else(|| panic!("no stream report"));
    assert_eq!((report.stations.len(), report.moving_images), (5, 0), "{report:?}");
    assert!(
        (stream.sets[0].baseline_m - a.baseline_m).abs() < 5e-4,
        "baseline {}",
        stream.sets[0].baseline_m
    );
    for (x, y) in views(a).into_iter().zip(views(&stream.sets[0])) {
        assert_eq!((&x.role, x.offset), (&y.role, y.offset));
        assert!(x.rgb == y.rgb, "view {} differs", x.role);
        assert_same_pose(x, y, "stream");
    }

    // Without the arm's /tf, the UR10's forward kinematics of /joint_states at each stamp carries
    // the camera's pose on from the flange (the hand-eye transform stays on /tf_static).
    let no_tf = dir.path().join("no-tf.mcap");
    copy_messages(&file, &no_tf, |topic, _| topic != "/capture/events" && topic != "/tf");
    let by_kinematics = read(&no_tf);
    assert_eq!(by_kinematics.sets.len(), 1, "{:?}", by_kinematics.notes());
    for (x, y) in views(a).into_iter().zip(views(&by_kinematics.sets[0])) {
        assert_eq!(x.offset, y.offset);
        assert_same_pose(x, y, "forward kinematics");
    }

    // The same disparities from both, bit for bit.
    let (out_a, out_b) = (dir.path().join("out-own"), dir.path().join("out-bag"));
    replay_summary(&own, &out_a, "--method bm-heuristic,sgm-heuristic");
    replay_summary(&bag, &out_b, "--method bm-heuristic,sgm-heuristic");
    let (da, db) = (disparities(&out_a), disparities(&out_b));
    assert_eq!(da.len(), 2);
    assert!(da == db, "the bag's disparities differ from the log's");

    // `replay info` says what it is.
    let info = replay(&["info", bag.to_str().unwrap_or_default()]);
    assert_success(&info, "replay info");
    let text = String::from_utf8_lossy(&info.stdout);
    assert!(
        text.contains("ROS 2 bag file") && text.contains("sensor_msgs/msg/Image"),
        "{text}"
    );
    assert!(text.contains("five-view") && text.contains("right"), "{text}");
}

#[test]
fn our_bags_are_read_by_rosbags_mcap_ros2_foxglove_and_rerun() {
    let dir = temp_dir();
    let bag = record_args(
        dir.path(),
        "capture",
        &format!("{SIM} --format ros2 --image-format png"),
    );
    let file = bag.join("capture_0.mcap");
    for input in [&bag, &file] {
        let output = python("check_ros2_bag.py", &[input]);
        assert_success(&output, "check_ros2_bag.py");
        let report: serde_json::Value =
            serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("no JSON from check_ros2_bag.py: {e}"));
        assert_eq!(report["profile"], "ros2");
        for (topic, kind) in [
            ("/camera/image_raw", "sensor_msgs/msg/CompressedImage"),
            ("/camera/camera_info", "sensor_msgs/msg/CameraInfo"),
            ("/camera/ground_truth/depth", "sensor_msgs/msg/Image"),
            ("/tf", "tf2_msgs/msg/TFMessage"),
            ("/tf_static", "tf2_msgs/msg/TFMessage"),
            ("/joint_states", "sensor_msgs/msg/JointState"),
            ("/capture/events", "std_msgs/msg/String"),
        ] {
            assert_eq!(report["rosbags"][topic]["type"], kind, "{topic}");
            assert_eq!(
                report["rosbags"][topic]["count"], report["mcap_ros2"][topic]["count"],
                "{topic}"
            );
        }
        assert_eq!(report["rosbags"]["/capture/events"]["count"], 5);
        assert_eq!(report["qos"]["/tf_static"][0], "QosDurability.TRANSIENT_LOCAL");
        let static_frames = multiscopic_tests::json_strings(&report["static_frames"]);
        assert!(
            static_frames.contains(&"tool0->camera_link")
                && static_frames.contains(&"camera_link->camera_optical_frame"),
            "{static_frames:?}"
        );
        let depth = report["images"]
            .as_array()
            .into_iter()
            .flatten()
            .find(|i| i["topic"] == "/camera/ground_truth/depth")
            .unwrap_or_else(|| panic!("no depth image"));
        assert_eq!(
            (depth["encoding"].as_str(), depth["frame_id"].as_str()),
            (Some("32FC1"), Some("camera_optical_frame"))
        );
    }
    match foxglove_read(&file) {
        Some(Ok(report)) => assert!(report.to_string().contains("/camera/image_raw"), "{report}"),
        Some(Err(e)) => panic!("Foxglove's reader failed on our bag: {e}"),
        None => {}
    }
    // Rerun decodes ros2msg images, camera info and transforms into a recording it verifies.
    let rrd = dir.path().join("bag.rrd");
    let converted = run(rerun_cli().args(["mcap", "convert"]).arg(&file).arg("-o").arg(&rrd));
    assert_success(&converted, "rerun mcap convert");
    let printed = run(rerun_cli().args(["rrd", "print", "-v"]).arg(&rrd));
    assert_success(&printed, "rerun rrd print");
    let text = String::from_utf8_lossy(&printed.stdout);
    for archetype in ["Pinhole", "Transform3D", "EncodedImage"] {
        assert!(text.contains(archetype), "Rerun's conversion has no {archetype}");
    }
    assert_success(&run(rerun_cli().args(["rrd", "verify"]).arg(&rrd)), "rerun rrd verify");

    // Results of a bag are ROS 2 too, in the reference image's frame and at its stamp.
    let results = dir.path().join("results.mcap");
    let out = dir.path().join("out");
    replay_summary(
        &bag,
        &out,
        &format!("--method sgm-heuristic --out-mcap {}", results.display()),
    );
    let output = python("check_ros2_bag.py", &[&results]);
    assert_success(&output, "check_ros2_bag.py on the results");
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("{e}"));
    for (topic, kind) in [
        ("/results/sgm-heuristic/disparity", "sensor_msgs/msg/Image"),
        ("/results/sgm-heuristic/depth", "sensor_msgs/msg/Image"),
        ("/results/sgm-heuristic/confidence", "sensor_msgs/msg/Image"),
        (
            "/results/sgm-heuristic/disparity_image",
            "stereo_msgs/msg/DisparityImage",
        ),
        ("/results/sgm-heuristic/points", "sensor_msgs/msg/PointCloud2"),
        ("/results/camera_info", "sensor_msgs/msg/CameraInfo"),
        ("/results/summary", "std_msgs/msg/String"),
    ] {
        assert_eq!(report["rosbags"][topic]["type"], kind, "{topic}: {report}");
        assert_eq!(report["mcap_ros2"][topic]["count"], 1, "{topic}");
    }
    let depth = report["images"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|i| i["topic"] == "/results/sgm-heuristic/depth")
        .unwrap_or_else(|| panic!("no depth result"));
    let input = report_of_first_image(&bag);
    assert_eq!(depth["frame_id"], "camera_optical_frame");
    assert_eq!(
        depth["stamp"], input,
        "the result is not stamped as the reference image"
    );
    let rrd = dir.path().join("results.rrd");
    assert_success(
        &run(rerun_cli().args(["mcap", "convert"]).arg(&results).arg("-o").arg(&rrd)),
        "rerun mcap convert of the results",
    );
    let printed = run(rerun_cli().args(["rrd", "print", "-v"]).arg(&rrd));
    let text = String::from_utf8_lossy(&printed.stdout);
    for archetype in ["DepthImage", "Points3D", "Pinhole"] {
        assert!(
            text.contains(archetype),
            "Rerun's conversion of the results has no {archetype}"
        );
    }
}

/// The stamp of the reference (centre) image of a bag of ours: its first capture event's time.
fn report_of_first_image(bag: &Path) -> serde_json::Value {
    let contents = read(bag);
    serde_json::json!(contents.sets[0].reference.capture_time_nanos)
}

/// Writes the "real robot" bag of Aloe's views 0–4 (a row of five) with rosbags.
fn robot_bag(dir: &Path, name: &str, views: &str, extra: &[&str]) -> PathBuf {
    let bag = dir.join(name);
    let scene = middlebury_dev("Aloe");
    let mut args = vec![scene.as_path(), bag.as_path()];
    let owned: Vec<PathBuf> = ["--views", views].iter().chain(extra).map(PathBuf::from).collect();
    args.extend(owned.iter().map(PathBuf::as_path));
    let output = python("write_ros2_capture.py", &args);
    assert_success(&output, "write_ros2_capture.py");
    bag
}

#[test]
fn a_robot_bag_gives_the_set_that_importing_its_images_gives() {
    let dir = temp_dir();
    // With what a RealSense streams besides (infrared in its own frame, 16UC1 depth, a yuv422
    // stream replay does not decode): the colour camera is the one used, the rest is listed.
    let bag = robot_bag(
        dir.path(),
        "aloe",
        "view2@0,view1@-1,view3@1,view0@-2,view4@2",
        &["--realsense"],
    );
    let contents = read(&bag);
    assert_eq!(
        contents.sets.len(),
        1,
        "{:?} {:?}",
        contents.notes(),
        contents.incomplete_sets
    );
    let set = &contents.sets[0];
    let report = contents.stream.as_ref().unwrap_or_else(|| panic!("no stream report"));
    assert_eq!(report.stations.len(), 5, "{report:?}");
    assert!(report.moving_images > 20, "{report:?}");
    assert!((set.baseline_m - 0.040).abs() < 1e-5, "baseline {}", set.baseline_m);
    let notes = contents.notes();
    for (topic, what) in [
        ("/diagnostics", "std_msgs/msg/Float64"),
        ("/camera/camera/depth/image_rect_raw", "16UC1"),
        ("/camera/camera/color/image_yuv", "yuv422"),
    ] {
        assert!(
            notes.iter().any(|n| n.contains(topic) && n.contains(what)),
            "{topic}: {notes:?}"
        );
    }
    assert_eq!(report.camera_frames, ["camera_color_optical_frame"], "{report:?}");

    // With room for a few images only, the reader keeps what each image is, drops the pixels,
    // and reads the chosen frames again: the same set.
    let bounded = replay::log::read_log_file_with(
        &bag,
        &replay::log::ReadOptions {
            image_budget_bytes: Some(2 << 20),
            ..replay::log::ReadOptions::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert!(bounded.sets == contents.sets, "a bounded read gives other sets");

    // The same images, cameras and offsets as `record import` of the same views.
    let imported = dir.path().join("import.mcap");
    let scene = middlebury_dev("Aloe");
    assert_success(
        &multiscopic_tests::record(&[
            "import",
            scene.to_str().unwrap_or_default(),
            "--views",
            "view0@-2,view1@-1,view2@0,view3@1,view4@2",
            "--no-ground-truth",
            "-o",
            imported.to_str().unwrap_or_default(),
            "-q",
        ]),
        "record import",
    );
    let reference = read(&imported);
    let expected = &reference.sets[0];
    let (a, b) = (views(expected), views(set));
    assert_eq!(
        a.iter().map(|v| v.offset).collect::<Vec<_>>(),
        b.iter().map(|v| v.offset).collect::<Vec<_>>()
    );
    for (x, y) in a.iter().zip(&b) {
        assert!(
            x.rgb == y.rgb,
            "view {:?}: the bag's image is not the imported one",
            x.offset
        );
        assert!(
            (x.camera.fx - y.camera.fx).abs() < 1e-3,
            "{:?} {:?}",
            x.camera,
            y.camera
        );
    }
    // So every method gives the same disparities (and so the same metrics).
    let (out_a, out_b) = (dir.path().join("out-import"), dir.path().join("out-bag"));
    let args = "--method bm-heuristic,sgm-heuristic,mfusenet --min-disparity 0 --num-disparities 48";
    replay_summary(&imported, &out_a, args);
    replay_summary(&bag, &out_b, args);
    let (da, db) = (disparities(&out_a), disparities(&out_b));
    assert_eq!(da.len(), 3);
    for ((method, x), (_, y)) in da.iter().zip(&db) {
        let mean = mean_abs_difference(x, y);
        assert!(mean <= 0.01, "{method}: disparities differ by {mean} px on average");
    }

    // `replay check` grades the bag's set as it grades our own logs' (ideal poses: nothing fails).
    let checked = replay(&["check", bag.to_str().unwrap_or_default(), "--json"]);
    assert_success(&checked, "replay check of the bag");
    let report: serde_json::Value = serde_json::from_slice(&checked.stdout).unwrap_or_else(|e| panic!("{e}"));
    let text = report.to_string();
    assert!(text.contains("\"ok\"") && !text.contains("\"fail\""), "{report}");

    // A bag split into two storage files reads as one stream.
    let split = robot_bag(dir.path(), "split", "view1@0,view0@-1,view2@1", &["--split"]);
    let contents = read(&split);
    assert_eq!(contents.sets.len(), 1, "{:?}", contents.notes());
    assert_eq!(contents.sets[0].neighbours.len(), 2);
}

/// Mean absolute difference of two PFM files' finite pixels.
fn mean_abs_difference(a: &[u8], b: &[u8]) -> f64 {
    let floats = |bytes: &[u8]| -> Vec<f32> {
        // Header: three text lines.
        let mut newlines = 0;
        let start = bytes
            .iter()
            .position(|c| {
                newlines += usize::from(*c == b'\n');
                newlines == 3
            })
            .map_or(bytes.len(), |i| i + 1);
        bytes[start..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    };
    let (x, y) = (floats(a), floats(b));
    assert_eq!(x.len(), y.len());
    let pairs: Vec<f64> = x
        .iter()
        .zip(&y)
        .filter(|(p, q)| p.is_finite() && q.is_finite())
        .map(|(p, q)| f64::from((p - q).abs()))
        .collect();
    pairs.iter().sum::<f64>() / pairs.len().max(1) as f64
}

#[test]
fn bad_bags_fail_clearly_naming_topic_frame_and_time() {
    let dir = temp_dir();
    let bag = robot_bag(dir.path(), "good", "view1@0,view0@-1,view2@1", &[]);
    let file = bag.join("good.mcap");
    let broken = |name: &str, keep: &dyn Fn(&str, u64) -> bool| {
        let path = dir.path().join(name);
        copy_messages(&file, &path, keep);
        path
    };
    let run_replay = |path: &Path| {
        let out = dir.path().join("out");
        replay(&[
            path.to_str().unwrap_or_default(),
            "--method",
            "bm-heuristic",
            "--out",
            out.to_str().unwrap_or_default(),
        ])
    };
    let stderr = |o: &std::process::Output| String::from_utf8_lossy(&o.stderr).into_owned();

    // No camera_info.
    let output = run_replay(&broken("no-info.mcap", &|t, _| !t.ends_with("camera_info")));
    assert_eq!(output.status.code(), Some(1), "{}", stderr(&output));
    assert!(
        stderr(&output).contains("/camera/camera/color/image_raw")
            && stderr(&output).contains("'camera_color_optical_frame' has no camera calibration"),
        "{}",
        stderr(&output)
    );
    // No hand-eye transform to the image's frame.
    let output = run_replay(&broken("no-static.mcap", &|t, _| t != "/tf_static"));
    assert_eq!(output.status.code(), Some(1), "{}", stderr(&output));
    assert!(
        stderr(&output).contains("no image on /camera/camera/color/image_raw has a camera pose")
            && stderr(&output).contains("'camera_color_optical_frame'"),
        "{}",
        stderr(&output)
    );
    // Transforms only for the first half: the later images are left out and said so.
    let start = 1_700_000_000_000_000_000u64;
    let half = broken("half-tf.mcap", &|t, time| t != "/tf" || time < start + 3_500_000_000);
    let output = run_replay(&half);
    let text = stderr(&output);
    assert!(
        text.contains("left out without a camera pose")
            && text.contains("base_link → wrist_3_link is known from")
            && text.contains("stamp"),
        "{text}"
    );
    // A cut bag: what is complete is read, the loss is reported, `replay recover` finishes it.
    let bytes = std::fs::read(&file).unwrap_or_else(|e| panic!("{e}"));
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 7 / 10]).unwrap_or_else(|e| panic!("{e}"));
    let output = run_replay(&cut);
    assert_eq!(output.status.code(), Some(3), "{}", stderr(&output));
    assert!(stderr(&output).contains("cut"), "{}", stderr(&output));
    let fixed = dir.path().join("fixed.mcap");
    let recovered = replay(&[
        "recover",
        cut.to_str().unwrap_or_default(),
        "-o",
        fixed.to_str().unwrap_or_default(),
    ]);
    assert_eq!(recovered.status.code(), Some(3), "{}", stderr(&recovered));
    let contents = read(&fixed);
    assert!(contents.truncation.is_none());
    assert_eq!(contents.sets.len(), 1, "{:?}", contents.notes());
    // One station's images of another size (a camera reconfigured mid-capture).
    let cropped = robot_bag(dir.path(), "cropped", "view1@0,view0@-1,view2@1", &["--crop", "view2"]);
    let output = run_replay(&cropped);
    assert_eq!(output.status.code(), Some(1), "{}", stderr(&output));
    assert!(
        stderr(&output).contains("is 417x370, the reference is 427x370")
            && stderr(&output).contains("camera_color_optical_frame"),
        "{}",
        stderr(&output)
    );
    // Not a bag at all: an empty directory.
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap_or_else(|e| panic!("{e}"));
    let output = run_replay(&empty);
    assert_eq!(output.status.code(), Some(1));
    assert!(
        stderr(&output).contains("without a rosbag2 metadata.yaml"),
        "{}",
        stderr(&output)
    );
    // Stripped of its events, our own bag still replays from its stream.
    let ours = record_args(dir.path(), "ours", &format!("{SIM} --format ros2"));
    let stripped = dir.path().join("ours-stream.mcap");
    strip_capture_events(&ours.join("ours_0.mcap"), &stripped);
    assert_eq!(read(&stripped).sets.len(), 1);
}
