//! Bad input to replay: clear errors naming the topic, set and field; exit codes; never a panic.

use std::path::Path;

use foxglove::messages::RawImage;
use multiscopic_tests::{record_args, recorded, replay_str, replay_summary, temp_dir};
use record::camera::PinholeCamera;
use record::log::{LogOptions, LogWriter};
use record::rig::RigKind;
use record::rng::SplitMix64;
use record::{CapturedSet, CapturedView};

fn view(role: &str, dx: i32, time: u64, size: (u32, u32)) -> CapturedView {
    let camera = PinholeCamera::from_horizontal_fov(size.0, size.1, 60.0);
    let pixels = (size.0 * size.1) as usize;
    CapturedView {
        depth_m: (dx == 0).then(|| vec![0.5; pixels]),
        ..CapturedView::new(
            (role, [dx, 0]),
            camera,
            nalgebra::Isometry3::translation(f64::from(dx) * 0.02, 0.0, 0.0),
            time,
            (0..pixels * 3).map(|i| (i * 13 % 256) as u8).collect(),
        )
    }
}

fn three_view_set() -> CapturedSet {
    CapturedSet {
        index: 0,
        name: "crafted".into(),
        rig: RigKind::ThreeView.name().to_owned(),
        baseline_m: 0.02,
        motion: Vec::new(),
        views: vec![
            view("center", 0, 10, (32, 24)),
            view("left", -1, 20, (32, 24)),
            view("right", 1, 30, (32, 24)),
        ],
        disparity_range: None,
    }
}

fn write_log(path: &Path, build: impl FnOnce(&mut LogWriter<std::io::BufWriter<std::fs::File>>)) {
    let file = std::fs::File::create(path).unwrap_or_else(|e| panic!("{e}"));
    let mut writer = LogOptions::new()
        .create(std::io::BufWriter::new(file))
        .unwrap_or_else(|e| panic!("{e}"));
    build(&mut writer);
    writer.finish().unwrap_or_else(|e| panic!("{e}"));
}

fn replay_err(log: &Path, out: &Path) -> (Option<i32>, String) {
    let output = replay_str(&format!(
        "{} --method bm-heuristic --out {} -q",
        log.display(),
        out.display()
    ));
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "replay panicked:\n{stderr}");
    (output.status.code(), stderr)
}

#[test]
fn crafted_bad_logs_give_errors_naming_topic_set_and_field() {
    let dir = temp_dir();
    let out = dir.path().join("out");
    let cases: Vec<(&str, CapturedSet, &[&str])> = vec![
        (
            "nan_depth",
            {
                let mut set = three_view_set();
                if let Some(depth) = set.views[0].depth_m.as_mut() {
                    depth[5] = f32::NAN;
                }
                set
            },
            &["/camera/center/ground_truth/depth", "depth", "NaN", "set 0"],
        ),
        (
            "inf_depth",
            {
                let mut set = three_view_set();
                if let Some(depth) = set.views[0].depth_m.as_mut() {
                    depth[0] = f32::INFINITY;
                }
                set
            },
            &["/camera/center/ground_truth/depth", "inf"],
        ),
        (
            "zero_baseline",
            CapturedSet {
                baseline_m: 0.0,
                ..three_view_set()
            },
            &["baseline_m", "set 0", "/capture/events"],
        ),
        (
            "mismatched_size",
            {
                let mut set = three_view_set();
                set.views[2] = view("right", 1, 30, (30, 24));
                set
            },
            &["set 0", "right", "/camera/right/image", "30x24", "32x24"],
        ),
        (
            "missing_view",
            {
                let mut set = three_view_set();
                set.views.retain(|v| v.role != "center");
                set
            },
            &["set 0", "center"],
        ),
    ];
    for (name, set, needles) in cases {
        let path = dir.path().join(format!("{name}.mcap"));
        write_log(&path, |w| w.write_set(&set, None).unwrap_or_else(|e| panic!("{e}")));
        let (code, stderr) = replay_err(&path, &out);
        assert_eq!(code, Some(1), "{name}: {stderr}");
        for needle in needles {
            assert!(stderr.contains(needle), "{name}: message lacks '{needle}':\n{stderr}");
        }
    }
    // An image encoding replay cannot read.
    let path = dir.path().join("yuv.mcap");
    write_log(&path, |w| {
        let set = three_view_set();
        w.write_set(&set, None).unwrap_or_else(|e| panic!("{e}"));
        let image = RawImage {
            timestamp: None,
            frame_id: "camera".into(),
            width: 32,
            height: 24,
            encoding: "yuv422".into(),
            step: 64,
            data: vec![0u8; 64 * 24].into(),
        };
        // A second image at the left view's time replaces the first on lookup.
        w.write_message("/camera/left/image", 20, &image)
            .unwrap_or_else(|e| panic!("{e}"));
    });
    let (code, stderr) = replay_err(&path, &out);
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("yuv422") && stderr.contains("/camera/left/image"),
        "{stderr}"
    );
}

#[test]
fn garbage_and_cut_off_logs() {
    let dir = temp_dir();
    let out = dir.path().join("out");
    let garbage = dir.path().join("garbage.mcap");
    std::fs::write(&garbage, b"this is not an MCAP file at all").unwrap_or_else(|e| panic!("{e}"));
    let (code, stderr) = replay_err(&garbage, &out);
    assert_eq!(code, Some(1));
    assert!(stderr.contains("not a readable MCAP log"), "{stderr}");
    let missing = dir.path().join("missing.mcap");
    let (code, stderr) = replay_err(&missing, &out);
    assert_eq!(code, Some(1));
    assert!(stderr.contains("missing.mcap"), "{stderr}");
    // A recording cut off part-way: the complete sets are replayed, exit 3 says something was lost.
    let full = record_args(
        dir.path(),
        "full.mcap",
        "--resolution 640x360 --captures 3 --rig three-view",
    );
    let bytes = std::fs::read(&full).unwrap_or_else(|e| panic!("{e}"));
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 3 / 4]).unwrap_or_else(|e| panic!("{e}"));
    let (code, stderr) = replay_err(&cut, &out);
    assert_eq!(code, Some(3), "{stderr}");
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap_or_else(|e| panic!("{e}")))
            .unwrap_or_else(|e| panic!("{e}"));
    let recovered = summary["sets"].as_array().map_or(0, Vec::len);
    assert!((1..3).contains(&recovered), "recovered {recovered} sets: {summary}");
    assert!(summary["truncation"].is_string(), "{summary}");
}

#[test]
fn random_bytes_and_truncations_never_panic_the_reader() {
    let (_dir, path) = recorded("fuzz.mcap", "--resolution 48x32 --captures 2 --samples-per-pixel 1");
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{e}"));
    let mut rng = SplitMix64::new(2024);
    let mut outcomes = [0usize; 2];
    for round in 0..400 {
        let mut data = bytes.clone();
        if round % 2 == 0 {
            data.truncate(rng.range_usize(0, bytes.len()));
        } else {
            for _ in 0..rng.range_usize(1, 16) {
                let at = rng.range_usize(0, data.len());
                data[at] = rng.next_u64() as u8;
            }
        }
        if round % 50 == 0 {
            data = (0..rng.range_usize(0, 4096)).map(|_| rng.next_u64() as u8).collect();
        }
        let result = std::panic::catch_unwind(|| replay::log::read_log(&data).map(|c| c.sets.len()));
        match result {
            Ok(Ok(_)) => outcomes[0] += 1,
            Ok(Err(_)) => outcomes[1] += 1,
            Err(_) => panic!("read_log panicked on round {round} ({} bytes)", data.len()),
        }
    }
    println!("fuzz: {} read, {} rejected with an error", outcomes[0], outcomes[1]);
    assert!(outcomes[0] > 0 && outcomes[1] > 0);
}

/// A copy of a log without its capture events: what another recorder would write.
#[test]
fn foreign_logs_without_capture_events_get_their_sets_from_the_poses() {
    let (dir, ours) = recorded("ours.mcap", "--resolution 160x90 --samples-per-pixel 1 --captures 3");
    let foreign = dir.path().join("foreign.mcap");
    multiscopic_tests::strip_capture_events(&ours, &foreign);
    let contents = replay::log::read_log_file(&foreign).unwrap_or_else(|e| panic!("{e}"));
    let original = replay::log::read_log_file(&ours).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(contents.sets.len(), 3, "sets inferred from the poses");
    assert_eq!(original.sets.len(), 3, "sets logged");
    for (inferred, logged) in contents.sets.iter().zip(&original.sets) {
        assert_eq!(
            inferred.reference.rgb, logged.reference.rgb,
            "set {}: wrong reference view",
            inferred.index
        );
        let mut roles: Vec<(String, [i32; 2])> =
            inferred.neighbours.iter().map(|n| (n.role.clone(), n.offset)).collect();
        let mut expected: Vec<(String, [i32; 2])> =
            logged.neighbours.iter().map(|n| (n.role.clone(), n.offset)).collect();
        roles.sort();
        expected.sort();
        assert_eq!(roles, expected, "set {}", inferred.index);
        assert!(
            (inferred.baseline_m - 0.02).abs() < 0.0005,
            "baseline {}",
            inferred.baseline_m
        );
    }
    let summary = replay_summary(&foreign, &dir.path().join("out"), "--method bm-heuristic");
    assert_eq!(
        summary["sets"].as_array().map(Vec::len),
        Some(3),
        "every inferred set replayed"
    );
}

#[test]
fn time_range_selects_sets() {
    let (_dir, log) = recorded("three.mcap", "--resolution 96x64 --samples-per-pixel 1 --captures 3");
    let all = replay::log::read_log_file(&log).unwrap_or_else(|e| panic!("{e}"));
    let start = all.sets[0].reference.capture_time_nanos;
    let first_of = |i: usize| {
        all.sets[i].reference.capture_time_nanos.min(
            all.sets[i]
                .neighbours
                .iter()
                .map(|n| n.capture_time_nanos)
                .min()
                .unwrap_or(u64::MAX),
        )
    };
    let last_of = |i: usize| {
        all.sets[i]
            .neighbours
            .iter()
            .map(|n| n.capture_time_nanos)
            .max()
            .unwrap_or(0)
    };
    // The log starts with the arm's first motion sample, before the first image.
    let origin = mcap::Summary::read(&std::fs::read(&log).unwrap_or_default())
        .ok()
        .flatten()
        .and_then(|s| s.stats.map(|s| s.message_start_time))
        .unwrap_or(start);
    let secs = |t: u64| (t - origin) as f64 / 1e9;
    let window = replay::log::read_log_file_in(&log, Some(secs(first_of(1)) - 0.001), Some(secs(last_of(1)) + 0.001))
        .unwrap_or_else(|e| panic!("{e}"));
    let indexes: Vec<u32> = window.sets.iter().map(|s| s.index).collect();
    assert_eq!(indexes, vec![1], "only the middle set lies in the window");
}
