//! `record import`: real image sets go into the same log format.

use std::path::Path;

use multiscopic_tests::{Log, assert_success, f32_pixels, middlebury_dev, record, record_str, temp_dir};

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
    let (scenes, out) = (dir.path().join("scenes"), dir.path().join("import.mcap"));
    let import = |out: &Path, extra: &str| {
        record_str(&format!(
            "import {} -o {} --focal-px 100 {extra}",
            scenes.display(),
            out.display()
        ))
    };
    assert_success(&import(&out, ""), "record import");
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
    assert_success(&import(&bare, "--no-blueprint"), "record import --no-blueprint");
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
    let output = record_str(&format!(
        "import {} -o {} --no-ground-truth",
        scene.display(),
        out.display()
    ));
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
    let data = middlebury_dev("");
    let dir = temp_dir();
    let out = dir.path().join("middlebury.mcap");
    let output = record_str(&format!(
        "import {} -o {} --focal-px 1246.67",
        data.display(),
        out.display()
    ));
    assert_success(&output, "record import");
    let log = Log::read(&out);
    let events = log.events();
    let sets: std::collections::BTreeSet<_> = events.iter().map(|e| e.set_name.clone()).collect();
    assert_eq!(sets.len(), 7, "{sets:?}");
    let with_gt = events.iter().filter(|e| e.depth_topic.is_some()).count();
    assert_eq!(with_gt, 7);
}

/// An RGB test pattern, different per view.
fn pattern(w: u32, h: u32, seed: usize) -> Vec<u8> {
    (0..(w * h * 3) as usize)
        .map(|k| ((k * 7 + seed * 13) % 251) as u8)
        .collect()
}

fn save(path: &Path, w: u32, h: u32, color: image::ExtendedColorType, data: &[u8]) {
    image::save_buffer(path, data, w, h, color).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

/// Imports `dir` with `args`, reads the log back through replay's reader.
fn import_and_read(dir: &Path, args: &[&str]) -> Vec<replay::viewset::ViewSet> {
    let out = dir.join("import.mcap");
    let mut all = vec![
        "import",
        dir.to_str().unwrap_or_default(),
        "-o",
        out.to_str().unwrap_or_default(),
    ];
    all.extend_from_slice(args);
    assert_success(&record(&all), "record import");
    replay::log::read_log_file(&out).unwrap_or_else(|e| panic!("{e}")).sets
}

#[test]
fn every_image_format_round_trips_through_the_log() {
    use image::ExtendedColorType as C;
    let (w, h) = (24u32, 16u32);
    // (extension, how the views are written, the 8-bit RGB the log must hold)
    type Writer = fn(&Path, u32, u32, &[u8]);
    type Expected = fn(&[u8]) -> Vec<u8>;
    let cases: [(&str, Writer, Expected); 8] = [
        ("png", |p, w, h, rgb| save(p, w, h, C::Rgb8, rgb), |rgb| rgb.to_vec()),
        (
            "png",
            |p, w, h, rgb| {
                // 16 bit: v·257 is exactly v after the importer's scaling to 8 bits.
                let wide: image::ImageBuffer<image::Rgb<u16>, Vec<u16>> =
                    image::ImageBuffer::from_raw(w, h, rgb.iter().map(|v| u16::from(*v) * 257).collect())
                        .unwrap_or_else(|| panic!("buffer"));
                wide.save(p).unwrap_or_else(|e| panic!("{e}"));
            },
            |rgb| rgb.to_vec(),
        ),
        (
            "png",
            |p, w, h, rgb| save(p, w, h, C::L8, &grey(rgb)),
            |rgb| grey(rgb).iter().flat_map(|v| [*v; 3]).collect(),
        ),
        ("ppm", |p, w, h, rgb| save(p, w, h, C::Rgb8, rgb), |rgb| rgb.to_vec()),
        (
            "pgm",
            |p, w, h, rgb| save(p, w, h, C::L8, &grey(rgb)),
            |rgb| grey(rgb).iter().flat_map(|v| [*v; 3]).collect(),
        ),
        ("tif", |p, w, h, rgb| save(p, w, h, C::Rgb8, rgb), |rgb| rgb.to_vec()),
        ("bmp", |p, w, h, rgb| save(p, w, h, C::Rgb8, rgb), |rgb| rgb.to_vec()),
        // JPEG is lossy: the log must hold what a JPEG decoder reads from the file.
        ("jpg", |p, w, h, rgb| save(p, w, h, C::Rgb8, rgb), |rgb| rgb.to_vec()),
    ];
    for (case, (extension, write, expected)) in cases.iter().enumerate() {
        let dir = temp_dir();
        let names = ["a", "b", "c"];
        for (i, name) in names.iter().enumerate() {
            write(&dir.path().join(format!("{name}.{extension}")), w, h, &pattern(w, h, i));
        }
        let views = format!("a.{extension}@-1,b.{extension}@0,c.{extension}@1");
        let sets = import_and_read(dir.path(), &["--views", &views, "--no-ground-truth", "-q"]);
        assert_eq!(sets.len(), 1, "case {case} ({extension})");
        let set = &sets[0];
        let want = if *extension == "jpg" {
            image::open(dir.path().join("b.jpg"))
                .unwrap_or_else(|e| panic!("{e}"))
                .to_rgb8()
                .into_raw()
        } else {
            expected(&pattern(w, h, 1))
        };
        assert_eq!(
            set.reference.rgb, want,
            "case {case} ({extension}): reference pixels changed"
        );
        let left = set
            .neighbours
            .iter()
            .find(|n| n.role == "left")
            .unwrap_or_else(|| panic!("no left"));
        if *extension != "jpg" {
            assert_eq!(left.rgb, expected(&pattern(w, h, 0)), "case {case} ({extension}): left");
        }
        assert_eq!(left.offset, [-1, 0]);
    }
}

fn grey(rgb: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3).map(|p| p[1]).collect()
}

/// Writes a binary PGM (16 bit big-endian when `wide`).
fn write_pgm(path: &Path, w: u32, h: u32, values: &[u16], wide: bool) {
    let mut bytes = format!("P5\n# ground truth\n{w} {h}\n{}\n", if wide { 65535 } else { 255 }).into_bytes();
    for v in values {
        if wide {
            bytes.extend_from_slice(&v.to_be_bytes());
        } else {
            bytes.push(*v as u8);
        }
    }
    std::fs::write(path, bytes).unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn every_ground_truth_format_round_trips_with_its_scale_and_unknown_value() {
    let (w, h) = (20u32, 10u32);
    // The true disparity to a direct neighbour: 2.5 … 7.25 px; unknown in the first row.
    let truth = |i: usize| {
        if i < w as usize {
            None
        } else {
            Some(2.5 + (i % 20) as f32 * 0.25)
        }
    };
    let n = (w * h) as usize;
    type Writer = fn(&Path, u32, u32, &[Option<f32>]);
    let cases: [(&str, &str, Writer); 6] = [
        ("png", "4", |p, w, h, t| {
            let v: Vec<u8> = t.iter().map(|d| d.map_or(0, |d| (d * 4.0) as u8)).collect();
            save(p, w, h, image::ExtendedColorType::L8, &v);
        }),
        ("png", "256", |p, w, h, t| {
            let v: Vec<u16> = t.iter().map(|d| d.map_or(0, |d| (d * 256.0) as u16)).collect();
            let b: image::ImageBuffer<image::Luma<u16>, Vec<u16>> =
                image::ImageBuffer::from_raw(w, h, v).unwrap_or_else(|| panic!("buffer"));
            b.save(p).unwrap_or_else(|e| panic!("{e}"));
        }),
        ("pgm", "16", |p, w, h, t| {
            write_pgm(
                p,
                w,
                h,
                &t.iter().map(|d| d.map_or(0, |d| (d * 16.0) as u16)).collect::<Vec<_>>(),
                false,
            )
        }),
        ("pgm", "1000", |p, w, h, t| {
            write_pgm(
                p,
                w,
                h,
                &t.iter()
                    .map(|d| d.map_or(0, |d| (d * 1000.0) as u16))
                    .collect::<Vec<_>>(),
                true,
            )
        }),
        ("pfm", "1", |p, w, h, t| {
            let v: Vec<f32> = t.iter().map(|d| d.unwrap_or(f32::INFINITY)).collect();
            viz::files::write_pfm(p, w as usize, h as usize, &v).unwrap_or_else(|e| panic!("{e}"));
        }),
        ("tif", "256", |p, w, h, t| {
            let v: Vec<u16> = t.iter().map(|d| d.map_or(0, |d| (d * 256.0) as u16)).collect();
            let b: image::ImageBuffer<image::Luma<u16>, Vec<u16>> =
                image::ImageBuffer::from_raw(w, h, v).unwrap_or_else(|| panic!("buffer"));
            b.save(p).unwrap_or_else(|e| panic!("{e}"));
        }),
    ];
    let t: Vec<Option<f32>> = (0..n).map(truth).collect();
    for (extension, scale, write) in cases {
        let dir = temp_dir();
        for (i, name) in ["l", "c", "r"].iter().enumerate() {
            save(
                &dir.path().join(format!("{name}.png")),
                w,
                h,
                image::ExtendedColorType::Rgb8,
                &pattern(w, h, i),
            );
        }
        let gt = format!("gt.{extension}");
        write(&dir.path().join(&gt), w, h, &t);
        let sets = import_and_read(
            dir.path(),
            &[
                "--views",
                "l.png@-1,c.png@0,r.png@1",
                "--ground-truth",
                &gt,
                "--ground-truth-scale",
                scale,
                "--focal-px",
                "500",
                "--baseline-mm",
                "30",
                "-q",
            ],
        );
        let read = sets[0]
            .ground_truth_disparity()
            .unwrap_or_else(|| panic!("{gt} ÷ {scale}: no ground truth in the log"));
        for (i, (got, want)) in read.iter().zip(&t).enumerate() {
            match want {
                None => assert!(got.is_nan(), "{gt} ÷ {scale}: pixel {i} should be unknown, is {got}"),
                Some(d) => assert!((got - d).abs() < 1e-4, "{gt} ÷ {scale}: pixel {i} {got} vs {d}"),
            }
        }
    }
}

#[test]
fn a_five_view_line_with_twice_the_baseline_keeps_its_multiples() {
    // Tsukuba's naming: five views in a row, ground truth ÷ 16 as an 8-bit PGM.
    let dir = temp_dir();
    let (w, h) = (32u32, 12u32);
    for col in 1..=5 {
        save(
            &dir.path().join(format!("scene1.row3.col{col}.ppm")),
            w,
            h,
            image::ExtendedColorType::Rgb8,
            &pattern(w, h, col),
        );
    }
    write_pgm(
        &dir.path().join("truedisp.row3.col3.pgm"),
        w,
        h,
        &vec![64; (w * h) as usize],
        false,
    );
    let out = dir.path().join("tsukuba.mcap");
    let output = record(&[
        "import",
        dir.path().to_str().unwrap_or_default(),
        "-o",
        out.to_str().unwrap_or_default(),
        "--views",
        "scene1.row3.col1.ppm@-2,scene1.row3.col2.ppm@-1,scene1.row3.col3.ppm@0,scene1.row3.col4.ppm@1,scene1.row3.col5.ppm@2",
        "--ground-truth",
        "truedisp.row3.col3.pgm",
        "--ground-truth-scale",
        "16",
        "--focal-px",
        "615",
        "--baseline-mm",
        "100",
    ]);
    assert_success(&output, "record import of a five-view line");
    let log = Log::read(&out);
    let mut events: Vec<_> = log
        .events()
        .into_iter()
        .map(|e| (e.grid_offset, e.role, e.rig, e.world_from_camera.translation_m[0]))
        .collect();
    events.sort_by_key(|e| e.0);
    let roles: Vec<&str> = events.iter().map(|e| e.1.as_str()).collect();
    assert_eq!(roles, ["left2", "left", "center", "right", "right2"]);
    for (offset, _, rig, x) in &events {
        assert_eq!(rig, "line5");
        assert!((x - f64::from(offset[0]) * 0.1).abs() < 1e-12, "{offset:?} at x = {x}");
    }
    let sets = replay::log::read_log_file(&out).unwrap_or_else(|e| panic!("{e}")).sets;
    let truth = sets[0].ground_truth_disparity().unwrap_or_default();
    assert!(truth.iter().all(|d| (d - 4.0).abs() < 1e-5), "64 ÷ 16 = 4 px");
}

#[test]
fn a_described_folder_with_a_middlebury_2014_calibration_needs_no_flags() {
    let dir = temp_dir();
    let set = dir.path().join("Scene-perfect");
    std::fs::create_dir_all(&set).unwrap_or_else(|e| panic!("{e}"));
    let (w, h) = (30u32, 20u32);
    for (i, name) in ["im0.png", "im1.png"].iter().enumerate() {
        save(&set.join(name), w, h, image::ExtendedColorType::Rgb8, &pattern(w, h, i));
    }
    let disparity: Vec<f32> = (0..w * h).map(|i| if i == 0 { f32::INFINITY } else { 10.0 }).collect();
    viz::files::write_pfm(&set.join("disp0.pfm"), w as usize, h as usize, &disparity).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(
        set.join("calib.txt"),
        format!(
            "cam0=[1000 0 14.5; 0 1000 9.5; 0 0 1]\ncam1=[1000 0 19.5; 0 1000 9.5; 0 0 1]\ndoffs=5\nbaseline=200\nwidth={w}\nheight={h}\nndisp=64\n"
        ),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    // The description sits above the set folders and applies to each.
    std::fs::write(
        dir.path().join("multiscopic.toml"),
        "views = [\"im0.png@0\", \"im1.png@1\"]\nground_truth = \"disp0.pfm\"\n",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let out = dir.path().join("described.mcap");
    let output = record_str(&format!("import {} -o {}", dir.path().display(), out.display()));
    assert_success(&output, "record import of a described folder");
    let sets = replay::log::read_log_file(&out).unwrap_or_else(|e| panic!("{e}")).sets;
    assert_eq!(sets.len(), 1);
    let set = &sets[0];
    assert_eq!(set.name, "Scene-perfect");
    assert_eq!((set.reference.camera.fx, set.reference.camera.cx), (1000.0, 14.5));
    assert_eq!(
        set.neighbours[0].camera.cx, 19.5,
        "doffs moves the right camera's principal point"
    );
    assert!((set.baseline_m - 0.2).abs() < 1e-12);
    assert!((set.disparity_offset_px() - 5.0).abs() < 1e-12);
    // Depth uses doffs: z = f·b/(d + doffs) = 1000 · 0.2 / 15.
    let z = set.ground_truth_depth_m.as_ref().map(|d| d[1]).unwrap_or_default();
    assert!((f64::from(z) - 200.0 / 15.0).abs() < 1e-4, "{z}");
    let truth = set.ground_truth_disparity().unwrap_or_default();
    assert!(truth[0].is_nan(), "inf in the PFM is unknown");
    assert!(truth[1..].iter().all(|d| (d - 10.0).abs() < 1e-4));
    assert!((set.disparity_to_depth_m()(10.0).unwrap_or_default() - 200.0 / 15.0).abs() < 1e-9);
    // replay eval reads the same folder without flags.
    let output = multiscopic_tests::replay_str(&format!(
        "eval {} --methods bm-stereo --num-disparities 16 --format json",
        dir.path().display()
    ));
    assert_success(&output, "replay eval of a described folder");
    let rows: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("{e}"));
    assert!(rows.to_string().contains("Scene-perfect"), "{rows}");
}

#[test]
fn bad_inputs_name_the_file_exit_1_or_2_and_leave_no_log() {
    let dir = temp_dir();
    let (w, h) = (16u32, 8u32);
    for (i, name) in ["a.png", "b.png", "c.png"].iter().enumerate() {
        save(
            &dir.path().join(name),
            w,
            h,
            image::ExtendedColorType::Rgb8,
            &pattern(w, h, i),
        );
    }
    save(
        &dir.path().join("small.png"),
        8,
        8,
        image::ExtendedColorType::Rgb8,
        &pattern(8, 8, 0),
    );
    save(
        &dir.path().join("gt_small.png"),
        8,
        8,
        image::ExtendedColorType::L8,
        &[12; 64],
    );
    std::fs::write(dir.path().join("gt_text.png"), "not an image").unwrap_or_else(|e| panic!("{e}"));
    let out = dir.path().join("bad.mcap");
    let base = ["--baseline-mm", "10", "--focal-px", "100"];
    // (arguments, exit code, text the error must contain)
    let cases: [(&[&str], i32, &str); 7] = [
        (
            &["--views", "a.png@-1,b.png@0,missing.png@1", "--no-ground-truth"],
            1,
            "missing.png",
        ),
        (
            &["--views", "a.png@-1,b.png@0,small.png@1", "--no-ground-truth"],
            1,
            "small.png",
        ),
        (
            &["--views", "a.png@-1,b.png@0,c.png@1", "--ground-truth", "gt_small.png"],
            1,
            "gt_small.png",
        ),
        (
            &["--views", "a.png@-1,b.png@0,c.png@1", "--ground-truth", "gt_text.png"],
            1,
            "gt_text.png",
        ),
        (
            &["--views", "a.png@-1,b.png@0,c.png@0", "--no-ground-truth"],
            2,
            "c.png",
        ),
        (&["--views", "a.png@-1,c.png@1", "--no-ground-truth"], 2, "no reference"),
        (
            &["--views", "a.png@-1,b.png@zero", "--no-ground-truth"],
            2,
            "b.png@zero",
        ),
    ];
    for (args, code, needle) in cases {
        let mut all = vec![
            "import",
            dir.path().to_str().unwrap_or_default(),
            "-o",
            out.to_str().unwrap_or_default(),
        ];
        all.extend_from_slice(&base);
        all.extend_from_slice(args);
        let output = record(&all);
        let message = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(code), "{args:?}: {message}");
        assert!(
            message.contains(needle),
            "{args:?}: the error does not name '{needle}': {message}"
        );
        assert!(!out.exists(), "{args:?}: a log was left behind");
        let leftovers: Vec<_> = std::fs::read_dir(dir.path())
            .into_iter()
            .flatten()
            .filter_map(Result::ok)
            .filter(|e| e.file_name().to_string_lossy().contains("partial"))
            .collect();
        assert!(leftovers.is_empty(), "{args:?}: partial files {leftovers:?}");
    }
}
