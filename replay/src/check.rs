//! Alignment checks of a view set: how far each neighbour is from the ideal multiscopic rig
//! (same orientation as the reference, displaced by `offset × baseline` in the image plane), from
//! the logged poses and from the images themselves.
//!
//! Per neighbour: baseline length and its relative deviation, direction error, out-of-plane
//! offset, relative rotation, the worst epipolar (perpendicular-to-search-line) error those cause
//! over the image for the scene's depth range, and an image-based estimate of the residual
//! perpendicular shift. Each gets ok / warn / fail against the thresholds below.

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::Serialize;

use crate::viewset::{View, ViewSet};

/// Relative baseline-length deviation: warn above 1 %, fail above 5 % (resampling corrects it).
pub const BASELINE_DEVIATION_LIMITS: (f64, f64) = (0.01, 0.05);
/// Angle between the real and nominal displacement (deg).
pub const DIRECTION_ERROR_LIMITS_DEG: (f64, f64) = (0.5, 2.0);
/// Out-of-plane offset as a fraction of the baseline (twice the UR10's repeatability at 20 mm
/// stays below the warning).
pub const OUT_OF_PLANE_LIMITS: (f64, f64) = (0.02, 0.04);
/// Relative rotation (deg).
pub const ROTATION_LIMITS_DEG: (f64, f64) = (0.1, 0.3);
/// Worst epipolar error over the image and depth range (px).
pub const EPIPOLAR_LIMITS_PX: (f64, f64) = (1.0, 2.0);
/// Residual perpendicular shift measured in the images (px).
pub const IMAGE_SHIFT_LIMITS_PX: (f64, f64) = (1.0, 2.0);
/// Depth range assumed when the set has no ground truth (m).
pub const DEFAULT_DEPTH_RANGE_M: (f64, f64) = (0.3, 2.0);
/// Perpendicular shifts tried by the image-based estimate (px, each side).
const IMAGE_SHIFT_SEARCH_PX: i32 = 3;
/// Block radius of the image-based estimate.
const IMAGE_BLOCK_RADIUS: i32 = 3;
/// Sample pixels per axis of the image-based estimate.
const IMAGE_SAMPLES_PER_AXIS: usize = 40;

/// Verdict of one measurement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Within tolerance.
    Ok,
    /// Degrades depth; worth a look.
    Warn,
    /// The set is misaligned.
    Fail,
}

fn grade(value: f64, (warn, fail): (f64, f64)) -> Status {
    if !value.is_finite() || value > fail {
        Status::Fail
    } else if value > warn {
        Status::Warn
    } else {
        Status::Ok
    }
}

/// One measurement with its verdict.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Measure {
    /// Value (units in the field name of the report).
    pub value: f64,
    /// Verdict.
    pub status: Status,
}

impl Measure {
    fn new(value: f64, limits: (f64, f64)) -> Self {
        Self {
            value,
            status: grade(value.abs(), limits),
        }
    }
}

/// The checks of one neighbour.
#[derive(Debug, Clone, Serialize)]
pub struct NeighbourCheck {
    /// Role.
    pub role: String,
    /// Real baseline length (mm).
    pub baseline_mm: f64,
    /// (real − nominal) / nominal.
    pub baseline_deviation: Measure,
    /// Angle between the real and nominal displacement (deg).
    pub direction_error_deg: Measure,
    /// Displacement along the reference optical axis (mm); graded as a fraction of the baseline.
    pub out_of_plane_mm: Measure,
    /// Relative rotation angle (deg).
    pub rotation_deg: Measure,
    /// Worst perpendicular-to-search-line error over the image and depth range (px).
    pub epipolar_error_px: Measure,
    /// Perpendicular shift that best aligns the images (px), when the images allow an estimate.
    pub image_shift_px: Option<Measure>,
    /// Worst of the above.
    pub status: Status,
}

/// The checks of one set.
#[derive(Debug, Clone, Serialize)]
pub struct SetCheck {
    /// Set index.
    pub set: u32,
    /// Set name.
    pub name: String,
    /// Depth range used for the epipolar error (m).
    pub depth_range_m: (f64, f64),
    /// Per neighbour.
    pub neighbours: Vec<NeighbourCheck>,
    /// Worst neighbour.
    pub status: Status,
}

fn k_matrix(view: &View) -> Matrix3<f64> {
    view.camera.k_matrix()
}

/// The depth range of a set: from its ground truth when present (2nd–98th percentile), else the
/// default.
pub fn depth_range(set: &ViewSet) -> (f64, f64) {
    let Some(depth) = &set.ground_truth_depth_m else {
        return DEFAULT_DEPTH_RANGE_M;
    };
    let mut valid: Vec<f32> = depth.iter().copied().filter(|z| *z > 0.0 && z.is_finite()).collect();
    if valid.is_empty() {
        return DEFAULT_DEPTH_RANGE_M;
    }
    valid.sort_unstable_by(f32::total_cmp);
    let at = |q: f64| f64::from(valid[((valid.len() - 1) as f64 * q) as usize]);
    (at(0.02), at(0.98))
}

/// Worst perpendicular-to-search-line error (px) of a neighbour over a 5×5 grid of pixels and the
/// ends of the depth range.
fn epipolar_error(set: &ViewSet, neighbour: &View, depth_range: (f64, f64)) -> f64 {
    let k = k_matrix(&set.reference);
    let k_inv = k.try_inverse().unwrap_or_else(Matrix3::identity);
    let relative = set.reference.world_from_camera.inverse() * neighbour.world_from_camera;
    let direction = Vector2::new(f64::from(neighbour.offset[0]), f64::from(neighbour.offset[1]));
    let along = direction.normalize();
    let perpendicular = Vector2::new(-along.y, along.x);
    let focal_baseline = set.reference.camera.fx * set.baseline_m;
    let (w, h) = (
        f64::from(set.reference.camera.width),
        f64::from(set.reference.camera.height),
    );
    let mut worst = 0.0f64;
    for i in 0..5 {
        for j in 0..5 {
            let p = Vector2::new((w - 1.0) * f64::from(i) / 4.0, (h - 1.0) * f64::from(j) / 4.0);
            for z in [depth_range.0, depth_range.1] {
                let point = k_inv * Vector3::new(p.x, p.y, 1.0) * z;
                let in_neighbour = relative.inverse_transform_point(&point.into());
                if in_neighbour.z <= 0.0 {
                    return f64::INFINITY;
                }
                let projected = k * in_neighbour.coords / in_neighbour.z;
                let actual = Vector2::new(projected.x, projected.y);
                let ideal = p - direction * (focal_baseline / z);
                worst = worst.max((actual - ideal).dot(&perpendicular).abs());
            }
        }
    }
    worst
}

fn luma(view: &View) -> Vec<f32> {
    view.rgb
        .chunks_exact(3)
        .map(|p| 0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]))
        .collect()
}

/// The perpendicular shift (px) that best aligns a neighbour with the reference when the
/// disparity along the search line is free: for each candidate shift, the best block cost over
/// the disparities, summed over textured sample pixels; the minimum refined by a parabola.
fn image_shift(set: &ViewSet, neighbour: &View, num_disparities: usize) -> Option<f64> {
    let (w, h) = (set.width() as i32, set.height() as i32);
    let reference = luma(&set.reference);
    let other = luma(neighbour);
    let at = |image: &[f32], x: i32, y: i32| image[(y.clamp(0, h - 1) * w + x.clamp(0, w - 1)) as usize];
    let (ox, oy) = (neighbour.offset[0], neighbour.offset[1]);
    let (px, py) = (-oy.signum(), ox.signum());
    let margin = IMAGE_BLOCK_RADIUS + IMAGE_SHIFT_SEARCH_PX + 1;
    let mut totals = vec![0.0f64; (2 * IMAGE_SHIFT_SEARCH_PX + 1) as usize];
    let mut used = 0usize;
    for sy in 0..IMAGE_SAMPLES_PER_AXIS {
        for sx in 0..IMAGE_SAMPLES_PER_AXIS {
            let x = margin + ((w - 2 * margin) as usize * sx / IMAGE_SAMPLES_PER_AXIS) as i32;
            let y = margin + ((h - 2 * margin) as usize * sy / IMAGE_SAMPLES_PER_AXIS) as i32;
            // Texture across the search line, or the shift is not observable here.
            let gradient = (at(&reference, x + px, y + py) - at(&reference, x - px, y - py)).abs();
            if gradient < 8.0 {
                continue;
            }
            let mut best_per_shift = Vec::with_capacity(totals.len());
            for shift in -IMAGE_SHIFT_SEARCH_PX..=IMAGE_SHIFT_SEARCH_PX {
                let mut best = f32::MAX;
                for d in 0..num_disparities as i32 {
                    let (qx, qy) = (x - ox * d + px * shift, y - oy * d + py * shift);
                    if qx < IMAGE_BLOCK_RADIUS
                        || qy < IMAGE_BLOCK_RADIUS
                        || qx >= w - IMAGE_BLOCK_RADIUS
                        || qy >= h - IMAGE_BLOCK_RADIUS
                    {
                        continue;
                    }
                    let mut sad = 0.0f32;
                    for by in -IMAGE_BLOCK_RADIUS..=IMAGE_BLOCK_RADIUS {
                        for bx in -IMAGE_BLOCK_RADIUS..=IMAGE_BLOCK_RADIUS {
                            sad += (at(&reference, x + bx, y + by) - at(&other, qx + bx, qy + by)).abs();
                        }
                    }
                    best = best.min(sad);
                }
                best_per_shift.push(best);
            }
            if best_per_shift.iter().all(|b| *b < f32::MAX) {
                for (total, b) in totals.iter_mut().zip(&best_per_shift) {
                    *total += f64::from(*b);
                }
                used += 1;
            }
        }
    }
    if used < 20 {
        return None;
    }
    let (best, _) = totals.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let mut shift = best as f64 - f64::from(IMAGE_SHIFT_SEARCH_PX);
    if best > 0 && best + 1 < totals.len() {
        let (l, c, r) = (totals[best - 1], totals[best], totals[best + 1]);
        let curvature = l - 2.0 * c + r;
        if curvature > 0.0 {
            shift += (0.5 * (l - r) / curvature).clamp(-0.5, 0.5);
        }
    }
    Some(shift)
}

/// Checks one set; `num_disparities` bounds the image-based search.
pub fn check_set(set: &ViewSet, num_disparities: usize) -> SetCheck {
    let range = depth_range(set);
    let neighbours: Vec<NeighbourCheck> = set
        .neighbours
        .iter()
        .map(|n| {
            let relative = set.reference.world_from_camera.inverse() * n.world_from_camera;
            let t = relative.translation.vector;
            let nominal_direction = Vector3::new(f64::from(n.offset[0]), f64::from(n.offset[1]), 0.0);
            let nominal = nominal_direction.norm() * set.baseline_m;
            let baseline = t.norm();
            let direction_error = t.angle(&nominal_direction).to_degrees();
            let out_of_plane_mm = t.z * 1000.0;
            let out_of_plane = Measure {
                value: out_of_plane_mm,
                status: grade(t.z.abs() / nominal, OUT_OF_PLANE_LIMITS),
            };
            let rotation_deg = relative.rotation.angle().to_degrees();
            let measures = [
                Measure::new((baseline - nominal) / nominal, BASELINE_DEVIATION_LIMITS),
                Measure::new(direction_error, DIRECTION_ERROR_LIMITS_DEG),
                out_of_plane,
                Measure::new(rotation_deg, ROTATION_LIMITS_DEG),
                Measure::new(epipolar_error(set, n, range), EPIPOLAR_LIMITS_PX),
            ];
            let image_shift_px = image_shift(set, n, num_disparities).map(|s| Measure::new(s, IMAGE_SHIFT_LIMITS_PX));
            let status = measures
                .iter()
                .map(|m| m.status)
                .chain(image_shift_px.map(|m| m.status))
                .max()
                .unwrap_or(Status::Ok);
            NeighbourCheck {
                role: n.role.clone(),
                baseline_mm: baseline * 1000.0,
                baseline_deviation: measures[0],
                direction_error_deg: measures[1],
                out_of_plane_mm: measures[2],
                rotation_deg: measures[3],
                epipolar_error_px: measures[4],
                image_shift_px,
                status,
            }
        })
        .collect();
    let status = neighbours.iter().map(|n| n.status).max().unwrap_or(Status::Ok);
    SetCheck {
        set: set.index,
        name: set.name.clone(),
        depth_range_m: range,
        neighbours,
        status,
    }
}

fn cell(m: &Measure, precision: usize) -> String {
    let mark = match m.status {
        Status::Ok => "",
        Status::Warn => " (warn)",
        Status::Fail => " (FAIL)",
    };
    format!("{:.*}{mark}", precision, m.value)
}

/// The human-readable table of a set's checks.
pub fn table(check: &SetCheck) -> String {
    let mut out = format!(
        "set {} ({}): {:?}, depth range {:.2}–{:.2} m\n",
        check.set, check.name, check.status, check.depth_range_m.0, check.depth_range_m.1
    );
    out.push_str(&format!(
        "  {:<13} {:>11} {:>16} {:>15} {:>16} {:>15} {:>16} {:>16}  {}\n",
        "neighbour",
        "baseline mm",
        "baseline dev %",
        "direction deg",
        "out-of-plane mm",
        "rotation deg",
        "epipolar px",
        "image shift px",
        "status"
    ));
    for n in &check.neighbours {
        let percent = Measure {
            value: n.baseline_deviation.value * 100.0,
            status: n.baseline_deviation.status,
        };
        out.push_str(&format!(
            "  {:<13} {:>11.3} {:>16} {:>15} {:>16} {:>15} {:>16} {:>16}  {:?}\n",
            n.role,
            n.baseline_mm,
            cell(&percent, 2),
            cell(&n.direction_error_deg, 3),
            cell(&n.out_of_plane_mm, 3),
            cell(&n.rotation_deg, 3),
            cell(&n.epipolar_error_px, 2),
            n.image_shift_px.map_or_else(|| "–".to_owned(), |m| cell(&m, 2)),
            n.status
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grading_uses_the_thresholds() {
        assert_eq!(grade(0.005, BASELINE_DEVIATION_LIMITS), Status::Ok);
        assert_eq!(grade(0.02, BASELINE_DEVIATION_LIMITS), Status::Warn);
        assert_eq!(grade(0.2, BASELINE_DEVIATION_LIMITS), Status::Fail);
        assert_eq!(grade(f64::NAN, BASELINE_DEVIATION_LIMITS), Status::Fail);
    }
}
