//! `record import`: real image sets go into the same log format.

use std::path::Path;

use multiscopic_tests::{Log, assert_success, f32_pixels, record, shared_data, temp_dir};

fn write_png(path: &Path, width: u32, height: u32, color: png::ColorType, data: &[u8]) {
    let file = std::fs::File::create(path).unwrap_or_else(|e| panic!("{e}"));
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    encoder.set_color(color);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().unwrap_or_else(|e| panic!("{e}"));
    writer.write_image_data(data).unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn imported_set_round_trips_pixels_and_ground_truth() {
    let dir = temp_dir();
    let scene = dir.path().join("scenes/plane");
    std::fs::create_dir_all(&scene).unwrap_or_else(|e| panic!("{e}"));
    let (w, h) = (40u32, 30u32);
    for (i, name) in ["view0", "view1", "view2"].iter().enumerate() {
        let data: Vec<u8> = (0..w * h * 3)
            .map(|k| ((k as usize * 7 + i * 13) % 251) as u8)
            .collect();
        write_png(&scene.join(format!("{name}.png")), w, h, png::ColorType::Rgb, &data);
    }
    // Ground truth: disparity 5 px everywhere (value 60 / 12), unknown in the first row.
    let gt: Vec<u8> = (0..w * h).map(|k| if k < w { 0 } else { 60 }).collect();
    write_png(&scene.join("disp1.png"), w, h, png::ColorType::Grayscale, &gt);
    let out = dir.path().join("import.mcap");
    let output = record(&[
        "import",
        dir.path().join("scenes").to_str().unwrap_or_default(),
        "-o",
        out.to_str().unwrap_or_default(),
        "--focal-px",
        "100",
    ]);
    assert_success(&output, "record import");
    let log = Log::read(&out);
    let events = log.events();
    assert_eq!(events.len(), 3);
    assert_eq!(events[0].role, "center");
    assert_eq!(events[0].set_name, "plane");
    let center = log.raw_image("/camera/center/image", events[0].capture_time_nanos);
    let expected: Vec<u8> = (0..w * h * 3).map(|k| ((k as usize * 7 + 13) % 251) as u8).collect();
    assert_eq!(center.data.to_vec(), expected, "centre pixels changed on import");
    let depth = f32_pixels(&log.raw_image("/camera/center/ground_truth/depth", events[0].capture_time_nanos));
    // z = f·b/d = 100 px · 0.04 m / 5 px = 0.8 m; 0 stays unknown.
    assert!(depth[..w as usize].iter().all(|d| *d == 0.0));
    assert!(depth[w as usize..].iter().all(|d| (d - 0.8).abs() < 1e-6));
    let left = events
        .iter()
        .find(|e| e.role == "left")
        .unwrap_or_else(|| panic!("no left view"));
    assert!((left.world_from_camera.translation_m[0] + 0.04).abs() < 1e-12);
    assert!(left.depth_topic.is_none());
    // The viewer layout is written beside the log, unless asked not to.
    assert!(out.with_extension("rbl").exists(), "no import.rbl beside the log");
    let bare = dir.path().join("bare.mcap");
    let output = record(&[
        "import",
        dir.path().join("scenes").to_str().unwrap_or_default(),
        "-o",
        bare.to_str().unwrap_or_default(),
        "--focal-px",
        "100",
        "--no-blueprint",
    ]);
    assert_success(&output, "record import --no-blueprint");
    assert!(bare.exists() && !bare.with_extension("rbl").exists());
}

#[test]
fn import_errors_name_the_file() {
    let dir = temp_dir();
    let scene = dir.path().join("s");
    std::fs::create_dir_all(&scene).unwrap_or_else(|e| panic!("{e}"));
    for name in ["view0", "view1"] {
        write_png(&scene.join(format!("{name}.png")), 8, 8, png::ColorType::Rgb, &[9; 192]);
    }
    write_png(&scene.join("view2.png"), 9, 8, png::ColorType::Rgb, &[9; 216]);
    let out = dir.path().join("x.mcap");
    let output = record(&[
        "import",
        scene.to_str().unwrap_or_default(),
        "-o",
        out.to_str().unwrap_or_default(),
        "--no-ground-truth",
    ]);
    assert_eq!(output.status.code(), Some(1));
    let message = String::from_utf8_lossy(&output.stderr);
    assert!(message.contains("view2.png") && message.contains("9x8"), "{message}");
    assert!(!out.exists());
    let output = record(&[
        "import",
        dir.path().join("nothing").to_str().unwrap_or_default(),
        "-o",
        out.to_str().unwrap_or_default(),
    ]);
    assert_eq!(output.status.code(), Some(1));
    let output = record(&["import", scene.to_str().unwrap_or_default(), "--views", "view0,view1"]);
    assert_eq!(
        output.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn middlebury_scenes_import_with_ground_truth() {
    let data = shared_data().join("middlebury2006-third-dev");
    if !data.is_dir() {
        panic!(
            "fixture missing: {} (the shared evaluation data must sit beside the checkout as ../shared/data)",
            data.display()
        );
    }
    let dir = temp_dir();
    let out = dir.path().join("middlebury.mcap");
    let output = record(&[
        "import",
        data.to_str().unwrap_or_default(),
        "-o",
        out.to_str().unwrap_or_default(),
        "--focal-px",
        "1246.67",
    ]);
    assert_success(&output, "record import");
    let log = Log::read(&out);
    let events = log.events();
    let sets: std::collections::BTreeSet<_> = events.iter().map(|e| e.set_name.clone()).collect();
    assert_eq!(sets.len(), 7, "{sets:?}");
    let with_gt = events.iter().filter(|e| e.depth_topic.is_some()).count();
    assert_eq!(with_gt, 7);
}
