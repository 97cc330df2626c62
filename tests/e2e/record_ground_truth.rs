//! Ground truth agrees with the images: warping each side view into the centre view with the
//! ground-truth disparity f·b/z reproduces the centre image on visible, non-specular pixels.

use multiscopic_tests::{Log, f32_pixels, record_log, temp_dir};
use record::scene::SurfaceClass;

/// Relative depth difference below which a centre pixel counts as visible in the side view.
const VISIBLE_DEPTH_TOLERANCE: f64 = 0.01;
/// Relative depth spread in a 3×3 neighbourhood above which a pixel sits on a depth edge.
const DEPTH_EDGE_SPREAD: f64 = 0.02;

struct View {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
    depth: Vec<f32>,
    surface: Vec<u8>,
}

fn load(log: &Log, role: &str, time: u64) -> View {
    let image = log.raw_image(&record::log::image_topic(role), time);
    let depth = log.raw_image(&record::log::depth_topic(role), time);
    let surface = log.raw_image(&record::log::surface_topic(role), time);
    assert_eq!(image.encoding, "rgb8");
    assert_eq!(depth.encoding, "32FC1");
    View {
        width: image.width as usize,
        height: image.height as usize,
        rgb: image.data.to_vec(),
        depth: f32_pixels(&depth),
        surface: surface.data.to_vec(),
    }
}

fn bilinear(view: &View, x: f64, y: f64, channel: usize) -> Option<f64> {
    if x < 0.0 || y < 0.0 || x > (view.width - 1) as f64 || y > (view.height - 1) as f64 {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(view.width - 1), (y0 + 1).min(view.height - 1));
    let (tx, ty) = (x - x0 as f64, y - y0 as f64);
    let at = |xx: usize, yy: usize| f64::from(view.rgb[(yy * view.width + xx) * 3 + channel]);
    let top = at(x0, y0) * (1.0 - tx) + at(x1, y0) * tx;
    let bottom = at(x0, y1) * (1.0 - tx) + at(x1, y1) * tx;
    Some(top * (1.0 - ty) + bottom * ty)
}

/// Mean absolute colour difference over usable pixels, and how many were usable, when the side
/// view is warped with the ground-truth disparity plus `disparity_bias` pixels.
fn warp_error(
    center: &View,
    side: &View,
    offset: [i32; 2],
    focal_px: f64,
    baseline_m: f64,
    disparity_bias: f64,
) -> (f64, usize) {
    let mut total = 0.0;
    let mut count = 0usize;
    for y in 1..center.height - 1 {
        for x in 1..center.width - 1 {
            let i = y * center.width + x;
            let z = f64::from(center.depth[i]);
            if z <= 0.0 || center.surface[i] != SurfaceClass::Diffuse as u8 {
                continue;
            }
            let mut lo = f64::MAX;
            let mut hi = f64::MIN;
            for dy in [-1i64, 0, 1] {
                for dx in [-1i64, 0, 1] {
                    let j = ((y as i64 + dy) as usize) * center.width + (x as i64 + dx) as usize;
                    lo = lo.min(f64::from(center.depth[j]));
                    hi = hi.max(f64::from(center.depth[j]));
                }
            }
            if hi - lo > DEPTH_EDGE_SPREAD * z {
                continue;
            }
            let disparity = focal_px * baseline_m / z;
            // The camera moved by +offset baselines: the scene shifts the opposite way.
            let sx = x as f64 - f64::from(offset[0]) * disparity;
            let sy = y as f64 - f64::from(offset[1]) * disparity;
            let (nx, ny) = (sx.round() as i64, sy.round() as i64);
            if nx < 0 || ny < 0 || nx >= side.width as i64 || ny >= side.height as i64 {
                continue;
            }
            let j = ny as usize * side.width + nx as usize;
            let visible = (f64::from(side.depth[j]) - z).abs() < VISIBLE_DEPTH_TOLERANCE * z;
            if !visible || side.surface[j] != SurfaceClass::Diffuse as u8 {
                continue;
            }
            let bias_x = -f64::from(offset[0]) * disparity_bias;
            let bias_y = -f64::from(offset[1]) * disparity_bias;
            let mut pixel_error = 0.0;
            let mut inside = true;
            for channel in 0..3 {
                match bilinear(side, sx + bias_x, sy + bias_y, channel) {
                    Some(value) => pixel_error += (value - f64::from(center.rgb[i * 3 + channel])).abs(),
                    None => inside = false,
                }
            }
            if inside {
                total += pixel_error / 3.0;
                count += 1;
            }
        }
    }
    (if count > 0 { total / count as f64 } else { f64::INFINITY }, count)
}

#[test]
fn warping_side_views_with_ground_truth_reproduces_the_centre() {
    let dir = temp_dir();
    // The line rig's outer views sit at twice the baseline: their ground truth warps at 2·d.
    for (scene, rig) in [("toy", "five-view"), ("workpiece", "five-view"), ("toy", "line5")] {
        let path = record_log(
            dir.path(),
            &format!("{scene}-{rig}.mcap"),
            &[
                "--scene",
                scene,
                "--rig",
                rig,
                "--resolution",
                "320x180",
                "--repeatability-mm",
                "0",
            ],
        );
        let log = Log::read(&path);
        let events = log.events();
        let center_event = events
            .iter()
            .find(|e| e.role == "center")
            .unwrap_or_else(|| panic!("no centre"));
        let center = load(&log, "center", center_event.capture_time_nanos);
        let calibration: foxglove::messages::CameraCalibration = prost::Message::decode(
            log.message(&center_event.calibration_topic, center_event.capture_time_nanos)
                .data
                .as_slice(),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let focal_px = calibration.k[0];
        let mut offsets: Vec<[i32; 2]> = events.iter().map(|e| e.grid_offset).collect();
        offsets.sort_unstable();
        if rig == "line5" {
            assert_eq!(offsets, [[-2, 0], [-1, 0], [0, 0], [1, 0], [2, 0]]);
        }
        let sides: Vec<_> = events.iter().filter(|e| e.role != "center").collect();
        assert_eq!(sides.len(), 4, "{scene} {rig}: four side views");
        for event in sides {
            let side = load(&log, &event.role, event.capture_time_nanos);
            let (error, count) = warp_error(&center, &side, event.grid_offset, focal_px, event.baseline_m, 0.0);
            let (shifted_error, _) = warp_error(&center, &side, event.grid_offset, focal_px, event.baseline_m, 2.0);
            println!(
                "{scene} {rig} {}: mean |Δ| {error:.2} levels over {count} pixels (with a 2 px disparity error: {shifted_error:.2})",
                event.role
            );
            assert!(
                count > center.width * center.height / 20,
                "{scene} {}: only {count} usable pixels",
                event.role
            );
            assert!(
                error < 3.5,
                "{scene} {}: warped side view differs by {error:.2} levels",
                event.role
            );
            assert!(
                shifted_error > 2.0 * error,
                "{scene} {}: a 2 px disparity error is not detectable ({shifted_error:.2} vs {error:.2})",
                event.role
            );
        }
    }
}
