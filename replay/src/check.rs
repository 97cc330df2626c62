//! Alignment checks of a view set: how far each neighbour is from the ideal multiscopic rig
//! (same orientation as the reference, displaced by `offset × baseline` in the image plane), from
//! the logged poses and from the images themselves.
//!
//! Per neighbour: baseline length and its relative deviation, direction error, out-of-plane
//! offset, relative rotation, the worst epipolar (perpendicular-to-search-line) error those cause
//! over the image for the scene's depth range, and an image-based estimate of the residual
//! perpendicular shift. Each gets ok / warn / fail against the thresholds below.

use nalgebra::{Matrix3, Vector2, Vector3};
use rayon::prelude::*;
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
/// Default limits (px) of the worst epipolar error over the image and depth range, and of the
/// residual perpendicular shift measured in the images: warn from 0.5 px (the precision every
/// method is judged at, Bad0.5), fail from 1.5 px.
pub const DEFAULT_PIXEL_LIMITS: PixelLimits = PixelLimits {
    warn_px: 0.5,
    fail_px: 1.5,
};

/// Where a pixel error (the predicted epipolar error, the measured image shift) starts to warn and
/// to fail.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PixelLimits {
    /// Warn from this many pixels.
    pub warn_px: f64,
    /// Fail from this many pixels.
    pub fail_px: f64,
}

impl Default for PixelLimits {
    fn default() -> Self {
        DEFAULT_PIXEL_LIMITS
    }
}

impl PixelLimits {
    fn pair(self) -> (f64, f64) {
        (self.warn_px, self.fail_px)
    }
}
/// Depth range assumed when the set has no ground truth (m).
pub const DEFAULT_DEPTH_RANGE_M: (f64, f64) = (0.3, 2.0);
/// Perpendicular shifts tried by the image-based estimate (px, each side).
const IMAGE_SHIFT_SEARCH_PX: i32 = 3;
/// Block radius of the image-based estimate.
const IMAGE_BLOCK_RADIUS: i32 = 3;
/// The side of those blocks (px).
const IMAGE_BLOCK_SIDE: usize = (2 * IMAGE_BLOCK_RADIUS + 1) as usize;
/// Sample pixels per axis of the image-based estimate.
const IMAGE_SAMPLES_PER_AXIS: usize = 40;
/// Smallest standard deviation (px) of the samples' disparities for the image-based estimate to
/// fit a shift that grows with disparity.
const MIN_DISPARITY_SPREAD_PX: f64 = 2.0;
/// A sample's best match must beat every match 2 or more disparities away by this fraction.
const IMAGE_UNIQUENESS: f32 = 0.15;
/// Smallest eigenvalue of a sample window's gradient matrix (per pixel, in squared 8-bit levels
/// per pixel) for both directions to be observable: below it the window is an edge or flat.
const IMAGE_MIN_TEXTURE: f64 = 8.0;
/// The image-based shift is graded against this fraction of the pixel limits (warn from 0.35 px,
/// fail from 1.05 px by default): its estimate reads 0.66–1.24 × (median 0.95) the true worst
/// error of a hand-eye rotation (`scripts/misalignment-sweep.py`), so a case at a limit must not
/// pass on an under-reading; clean simulated captures read at most 0.17 px.
pub const IMAGE_LIMIT_FRACTION: f64 = 0.7;

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
    if !value.is_finite() || value >= fail {
        Status::Fail
    } else if value >= warn {
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
    /// The worst epipolar error from the true poses (px), when the log has them (simulation):
    /// what the two estimates above should catch. Not graded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub true_epipolar_error_px: Option<f64>,
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
    // The 2 % and 98 % quantiles by selection (linear time) rather than a sort of every pixel.
    let last = valid.len() - 1;
    let (high, low) = (((last as f64) * 0.98) as usize, ((last as f64) * 0.02) as usize);
    let (below, at_high, _) = valid.select_nth_unstable_by(high, f32::total_cmp);
    let high_m = f64::from(*at_high);
    let low_m = if low == high {
        high_m
    } else {
        f64::from(*below.select_nth_unstable_by(low, f32::total_cmp).1)
    };
    (low_m, high_m)
}

/// Worst perpendicular-to-search-line error (px) of a neighbour over a 5×5 grid of pixels and the
/// ends of the depth range.
fn epipolar_error(
    set: &ViewSet,
    neighbour: &View,
    depth_range: (f64, f64),
    reference_pose: &nalgebra::Isometry3<f64>,
    neighbour_pose: &nalgebra::Isometry3<f64>,
) -> f64 {
    let k = k_matrix(&set.reference);
    let k_inv = k.try_inverse().unwrap_or_else(Matrix3::identity);
    let relative = reference_pose.inverse() * neighbour_pose;
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

/// The perpendicular shift (px) that best aligns a group of sample pixels: for each candidate
/// shift, the sum of the samples' best block costs over the disparities; the minimum refined by
/// equiangular lines.
fn pooled_shift(samples: &[Vec<f32>]) -> Option<f64> {
    let mut totals = vec![0.0f64; (2 * IMAGE_SHIFT_SEARCH_PX + 1) as usize];
    for best_per_shift in samples {
        for (total, b) in totals.iter_mut().zip(best_per_shift) {
            *total += f64::from(*b);
        }
    }
    let (best, _) = totals.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let mut shift = best as f64 - f64::from(IMAGE_SHIFT_SEARCH_PX);
    if best > 0 && best + 1 < totals.len() {
        // Equiangular lines: block SAD sums are V-shaped at their minimum, and a parabola would
        // pull the shift toward the nearest integer.
        let (l, c, r) = (totals[best - 1], totals[best], totals[best + 1]);
        let rise = l.max(r) - c;
        if rise > 0.0 {
            shift += (0.5 * (l - r) / rise).clamp(-0.5, 0.5);
        }
    }
    Some(shift)
}

/// A grey image borrowed for bilinear sampling.
struct Luma<'a> {
    data: &'a [f32],
    width: i32,
    height: i32,
}

impl<'a> Luma<'a> {
    fn new(data: &'a [f32], width: i32, height: i32) -> Self {
        Self { data, width, height }
    }

    /// The sum of absolute differences between this image's block around `at` and `other`'s
    /// around `other_at` ([`IMAGE_BLOCK_RADIUS`]), in row-major order. Both blocks lie within
    /// the images: rows are sliced straight, without clamping each pixel.
    fn block_sad(&self, other: &Luma<'_>, at: (i32, i32), other_at: (i32, i32)) -> f32 {
        fn row<'d>(luma: &Luma<'d>, (x, y): (i32, i32), by: i32) -> &'d [f32] {
            let start = ((y + by) * luma.width + x - IMAGE_BLOCK_RADIUS) as usize;
            &luma.data[start..start + IMAGE_BLOCK_SIDE]
        }
        let mut sad = 0.0f32;
        for by in -IMAGE_BLOCK_RADIUS..=IMAGE_BLOCK_RADIUS {
            for (a, b) in row(self, at, by).iter().zip(row(other, other_at, by)) {
                sad += (a - b).abs();
            }
        }
        sad
    }

    /// Whether the block around `(x, y)` lies within the image.
    fn holds_block(&self, x: i32, y: i32) -> bool {
        let r = IMAGE_BLOCK_RADIUS;
        x >= r && y >= r && x < self.width - r && y < self.height - r
    }

    fn pixel(&self, x: i32, y: i32) -> f32 {
        self.data[(y.clamp(0, self.height - 1) * self.width + x.clamp(0, self.width - 1)) as usize]
    }

    fn bilinear(&self, x: f64, y: f64) -> f64 {
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i32, y0 as i32);
        let p = |dx, dy| f64::from(self.pixel(x0 + dx, y0 + dy));
        (1.0 - fy) * ((1.0 - fx) * p(0, 0) + fx * p(1, 0)) + fy * ((1.0 - fx) * p(0, 1) + fx * p(1, 1))
    }
}

/// Refines a sample's integer match `(d, s)` (disparity along the search line, shift across it)
/// to sub-pixel in both by Lucas–Kanade on a window about the sample, with both windows' means
/// removed. `None` when the window's texture leaves either direction unobservable (aperture) or
/// the refinement leaves the integer cell or does not converge.
fn refine_match(
    template: &Luma<'_>,
    image: &Luma<'_>,
    (x, y): (i32, i32),
    (along, across): ([i32; 2], [i32; 2]),
    start: (f64, f64),
) -> Option<(f64, f64)> {
    let r = IMAGE_BLOCK_RADIUS + 1;
    let offsets: Vec<(i32, i32)> = (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| (dx, dy))).collect();
    let t: Vec<f64> = offsets
        .iter()
        .map(|(dx, dy)| f64::from(template.pixel(x + dx, y + dy)))
        .collect();
    let t_mean = t.iter().sum::<f64>() / t.len() as f64;
    let (a, c) = (
        [f64::from(along[0]), f64::from(along[1])],
        [f64::from(across[0]), f64::from(across[1])],
    );
    let (mut d, mut s) = start;
    for _ in 0..8 {
        let (qx, qy) = (f64::from(x) + a[0] * d + c[0] * s, f64::from(y) + a[1] * d + c[1] * s);
        let values: Vec<f64> = offsets
            .iter()
            .map(|(dx, dy)| image.bilinear(qx + f64::from(*dx), qy + f64::from(*dy)))
            .collect();
        let mean = values.iter().sum::<f64>() / values.len() as f64;
        // Jacobian of each window pixel in (disparity, shift), with its means removed as the
        // window's own mean is.
        let jacobian: Vec<(f64, f64)> = offsets
            .iter()
            .map(|(dx, dy)| {
                let (sx, sy) = (qx + f64::from(*dx), qy + f64::from(*dy));
                let gx = 0.5 * (image.bilinear(sx + 1.0, sy) - image.bilinear(sx - 1.0, sy));
                let gy = 0.5 * (image.bilinear(sx, sy + 1.0) - image.bilinear(sx, sy - 1.0));
                (gx * a[0] + gy * a[1], gx * c[0] + gy * c[1])
            })
            .collect();
        let n = offsets.len() as f64;
        let (jd_mean, js_mean) = jacobian
            .iter()
            .fold((0.0, 0.0), |(sd, ss), (jd, js)| (sd + jd / n, ss + js / n));
        let (mut h00, mut h01, mut h11, mut g0, mut g1) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (((jd, js), v), tv) in jacobian.iter().zip(&values).zip(&t) {
            let (jd, js) = (jd - jd_mean, js - js_mean);
            let residual = (v - mean) - (tv - t_mean);
            h00 += jd * jd;
            h01 += jd * js;
            h11 += js * js;
            g0 += jd * residual;
            g1 += js * residual;
        }
        let trace = h00 + h11;
        let det = h00 * h11 - h01 * h01;
        let smallest = 0.5 * (trace - (trace * trace - 4.0 * det).max(0.0).sqrt());
        if smallest / n < IMAGE_MIN_TEXTURE {
            return None;
        }
        let step_d = -(h11 * g0 - h01 * g1) / det;
        let step_s = -(h00 * g1 - h01 * g0) / det;
        d += step_d;
        s += step_s;
        if (d - start.0).abs() > 1.0 || (s - start.1).abs() > 1.0 {
            return None;
        }
        if step_d.abs() < 0.002 && step_s.abs() < 0.002 {
            return Some((d, s));
        }
    }
    // Not converged: no measurement.
    None
}

/// Whether a sample's best match along the search line is unambiguous: every disparity 2 or more
/// away costs at least `1 +` [`IMAGE_UNIQUENESS`] times the best (not a repeated texture).
fn is_unique(along: &[f32], best: usize) -> bool {
    let rival = along
        .iter()
        .enumerate()
        .filter(|(d, _)| d.abs_diff(best) >= 2)
        .map(|(_, v)| *v)
        .fold(f32::MAX, f32::min);
    rival >= (1.0 + IMAGE_UNIQUENESS) * along[best]
}

/// Tukey's biweights of points `(d, shift)` about the line `shift = a + b·d`, at 4.685 robust
/// standard deviations (1.4826 × the median absolute residual, at least 0.05 px).
fn biweights(points: &[(f64, f64)], a: f64, b: f64) -> Vec<f64> {
    let residuals: Vec<f64> = points.iter().map(|p| (p.1 - a - b * p.0).abs()).collect();
    let mut sorted = residuals.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
    let scale = (1.4826 * median).max(0.05) * 4.685;
    residuals
        .into_iter()
        .map(|r| {
            let u = r / scale;
            if u < 1.0 { (1.0 - u * u).powi(2) } else { 0.0 }
        })
        .collect()
}

/// Block costs of the sample at `(x, y)` at every shift across the search line (rows of
/// `costs`) and disparity along it (columns): the sum of absolute differences of the template's
/// block and the image's block displaced by `-offset · d + across · shift`; `f32::MAX` where the
/// displaced block leaves the image. The sample lies at least the shift search plus a block's
/// radius inside the image.
///
/// For a unit offset along an axis (every direct neighbour) the image strip the search covers is
/// first copied into `patch` in the search's own frame (rows across the line, columns along it),
/// so that each block pixel's differences run over consecutive disparities in vector lanes; other
/// offsets (diagonals, farther views of a line) take each block in turn.
fn search_costs(
    template: &Luma<'_>,
    image: &Luma<'_>,
    (x, y): (i32, i32),
    offset: [i32; 2],
    across: [i32; 2],
    patch: &mut Vec<f32>,
    costs: &mut [f32],
) {
    let r = IMAGE_BLOCK_RADIUS;
    let shifts = 2 * IMAGE_SHIFT_SEARCH_PX + 1;
    let num_disparities = costs.len() / shifts as usize;
    if offset[0].abs() + offset[1].abs() != 1 {
        search_costs_blockwise(template, image, (x, y), offset, across, costs);
        return;
    }
    let along = [-offset[0], -offset[1]];
    // The strip: row `a` lies `a - (search + r)` across the line, column `k` lies `k - r` along
    // it (disparity `d`'s block spans columns `d … d + 2r`).
    let rows = (shifts + 2 * r) as usize;
    let columns = num_disparities + 2 * r as usize;
    patch.clear();
    patch.resize(rows * columns, 0.0);
    for (a, strip_row) in patch.chunks_exact_mut(columns).enumerate() {
        let a = a as i32 - (IMAGE_SHIFT_SEARCH_PX + r);
        for (k, value) in strip_row.iter_mut().enumerate() {
            let k = k as i32 - r;
            *value = image.pixel(x + across[0] * a + along[0] * k, y + across[1] * a + along[1] * k);
        }
    }
    // The template's block in the same frame.
    let mut block = [0.0f32; IMAGE_BLOCK_SIDE * IMAGE_BLOCK_SIDE];
    for (a, block_row) in block.chunks_exact_mut(IMAGE_BLOCK_SIDE).enumerate() {
        let a = a as i32 - r;
        for (b, value) in block_row.iter_mut().enumerate() {
            let b = b as i32 - r;
            *value = template.pixel(x + across[0] * a + along[0] * b, y + across[1] * a + along[1] * b);
        }
    }
    for (row, sums) in costs.chunks_exact_mut(num_disparities).enumerate() {
        sums.fill(0.0);
        for (a, block_row) in block.chunks_exact(IMAGE_BLOCK_SIDE).enumerate() {
            let strip_row = &patch[(row + a) * columns..(row + a + 1) * columns];
            for (b, t) in block_row.iter().enumerate() {
                for (sum, v) in sums.iter_mut().zip(&strip_row[b..b + num_disparities]) {
                    *sum += (t - v).abs();
                }
            }
        }
    }
    // Disparities whose block leaves the image (the shift keeps it inside across the line).
    for d in 0..num_disparities {
        let (qx, qy) = (x + along[0] * d as i32, y + along[1] * d as i32);
        if !image.holds_block(qx, qy) {
            for row in 0..shifts as usize {
                costs[row * num_disparities + d] = f32::MAX;
            }
        }
    }
}

/// [`search_costs`] one block at a time, for any offset.
fn search_costs_blockwise(
    template: &Luma<'_>,
    image: &Luma<'_>,
    (x, y): (i32, i32),
    offset: [i32; 2],
    across: [i32; 2],
    costs: &mut [f32],
) {
    let num_disparities = costs.len() / (2 * IMAGE_SHIFT_SEARCH_PX + 1) as usize;
    costs.fill(f32::MAX);
    for (row, shift) in (-IMAGE_SHIFT_SEARCH_PX..=IMAGE_SHIFT_SEARCH_PX).enumerate() {
        for d in 0..num_disparities as i32 {
            let (qx, qy) = (
                x - offset[0] * d + across[0] * shift,
                y - offset[1] * d + across[1] * shift,
            );
            if image.holds_block(qx, qy) {
                costs[row * num_disparities + d as usize] = template.block_sad(image, (x, y), (qx, qy));
            }
        }
    }
}

/// The worst perpendicular shift (px) between a neighbour and the reference over the disparities
/// of `depth_range`, measured in the images with the disparity along the search line free.
///
/// A rotation about the axis across the search line shifts every pixel alike; a displacement
/// off the search line's direction (a hand-eye rotation: the poses look ideal) shifts each pixel
/// in proportion to its disparity. So each textured sample pixel with an unambiguous match gives
/// its own sub-pixel (disparity, shift) ([`refine_match`]), a line `shift = a + b·d` is fitted
/// through them (Tukey's biweight, robust to wrong matches) and evaluated at both ends of the
/// set's disparity range; with too little disparity spread, the shift pooled over every sample
/// ([`pooled_shift`]) is the answer.
fn image_shift(
    set: &ViewSet,
    reference: &[f32],
    neighbour: &View,
    num_disparities: usize,
    depth_range: (f64, f64),
) -> Option<f64> {
    let (w, h) = (set.width() as i32, set.height() as i32);
    let other = fuse::image::luma_levels(&neighbour.rgb);
    let (ox, oy) = (neighbour.offset[0], neighbour.offset[1]);
    let (px, py) = (-oy.signum(), ox.signum());
    let margin = IMAGE_BLOCK_RADIUS + IMAGE_SHIFT_SEARCH_PX + 1;
    let image = Luma::new(&other, w, h);
    let template = Luma::new(reference, w, h);
    // Per unambiguous textured sample: its best block cost at each integer shift (for the pooled
    // constant), and its match refined to sub-pixel (disparity, shift).
    let mut pooled: Vec<Vec<f32>> = Vec::new();
    let mut points: Vec<(f64, f64)> = Vec::new();
    // Block costs at every shift (rows) and disparity (columns) of one sample; f32::MAX off the
    // image.
    let shifts = (2 * IMAGE_SHIFT_SEARCH_PX + 1) as usize;
    let mut costs = vec![f32::MAX; shifts * num_disparities];
    let mut patch = Vec::new();
    for sy in 0..IMAGE_SAMPLES_PER_AXIS {
        for sx in 0..IMAGE_SAMPLES_PER_AXIS {
            let x = margin + ((w - 2 * margin) as usize * sx / IMAGE_SAMPLES_PER_AXIS) as i32;
            let y = margin + ((h - 2 * margin) as usize * sy / IMAGE_SAMPLES_PER_AXIS) as i32;
            // Texture across the search line, or the shift is not observable here.
            let gradient = (template.pixel(x + px, y + py) - template.pixel(x - px, y - py)).abs();
            if gradient < 8.0 {
                continue;
            }
            search_costs(&template, &image, (x, y), [ox, oy], [px, py], &mut patch, &mut costs);
            let best_per_shift: Vec<f32> = costs
                .chunks_exact(num_disparities)
                .map(|row| row.iter().copied().fold(f32::MAX, f32::min))
                .collect();
            if best_per_shift.contains(&f32::MAX) {
                continue;
            }
            let Some((best_index, _)) = costs.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1)) else {
                continue;
            };
            let (row, d_best) = (best_index / num_disparities, best_index % num_disparities);
            let along = &costs[row * num_disparities..(row + 1) * num_disparities];
            if !is_unique(along, d_best) {
                continue;
            }
            let start = (d_best as f64, row as f64 - f64::from(IMAGE_SHIFT_SEARCH_PX));
            // A refined shift near the end of the search is not a measurement (a wrong match or a
            // shift beyond the search).
            let refined = refine_match(&template, &image, (x, y), ([-ox, -oy], [px, py]), start)
                .filter(|(_, s)| s.abs() < f64::from(IMAGE_SHIFT_SEARCH_PX) - 0.5);
            pooled.push(best_per_shift);
            if let Some(point) = refined {
                points.push(point);
            }
        }
    }
    if pooled.len() < 20 {
        return None;
    }
    let constant = pooled_shift(&pooled)?;
    // Disparity along the search line per unit of grid offset at the ends of the depth range.
    let scale = f64::from(ox.abs().max(oy.abs()));
    let focal_baseline = set.reference.camera.fx * set.baseline_m * scale;
    let (d_near, d_far) = (focal_baseline / depth_range.0, focal_baseline / depth_range.1);
    let mean = |values: &mut dyn Iterator<Item = f64>| {
        let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
        sum / n.max(1) as f64
    };
    let d_mean = mean(&mut points.iter().map(|p| p.0));
    let d_spread = mean(&mut points.iter().map(|p| (p.0 - d_mean).powi(2))).sqrt();
    // Too little spread to see a slope (a fronto-parallel scene): the constant shift.
    if d_spread < MIN_DISPARITY_SPREAD_PX || points.len() < 20 {
        return Some(constant);
    }
    // Start from the pooled constant, weighted by the biweight of its residuals, so that the
    // first line is not a plain least-squares fit pulled by the wrong matches.
    let (mut a, mut b) = (constant, 0.0);
    let mut weights = biweights(&points, a, b);
    for _ in 0..5 {
        let total: f64 = weights.iter().sum();
        if total <= 0.0 {
            break;
        }
        let dm = points.iter().zip(&weights).map(|(p, w)| w * p.0).sum::<f64>() / total;
        let sm = points.iter().zip(&weights).map(|(p, w)| w * p.1).sum::<f64>() / total;
        let sxx: f64 = points.iter().zip(&weights).map(|(p, w)| w * (p.0 - dm).powi(2)).sum();
        let sxy: f64 = points
            .iter()
            .zip(&weights)
            .map(|(p, w)| w * (p.0 - dm) * (p.1 - sm))
            .sum();
        b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
        a = sm - b * dm;
        weights = biweights(&points, a, b);
    }
    let ends = [a + b * d_near, a + b * d_far];
    ends.into_iter().max_by(|x, y| x.abs().total_cmp(&y.abs()))
}

/// Checks one set; `num_disparities` bounds the image-based search, `limits` grade the epipolar
/// error and the image shift.
pub fn check_set(set: &ViewSet, num_disparities: usize, limits: PixelLimits) -> SetCheck {
    let range = depth_range(set);
    // The reference's grey levels, once for every neighbour's image-shift search.
    let reference = fuse::image::luma_levels(&set.reference.rgb);
    // One neighbour per task: the image-shift search is most of a check.
    let neighbours: Vec<NeighbourCheck> = set
        .neighbours
        .par_iter()
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
                Measure::new(
                    epipolar_error(set, n, range, &set.reference.world_from_camera, &n.world_from_camera),
                    limits.pair(),
                ),
            ];
            let image_shift_px = image_shift(set, &reference, n, num_disparities, range).map(|s| {
                let (warn, fail) = limits.pair();
                Measure::new(s, (warn * IMAGE_LIMIT_FRACTION, fail * IMAGE_LIMIT_FRACTION))
            });
            let true_epipolar_error_px = set
                .reference
                .true_world_from_camera
                .as_ref()
                .zip(n.true_world_from_camera.as_ref())
                .map(|(reference, neighbour)| epipolar_error(set, n, range, reference, neighbour));
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
                true_epipolar_error_px,
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

    /// A smooth two-frequency texture, the same function sampled at any sub-pixel offset.
    fn texture(x: f64, y: f64) -> f32 {
        (128.0 + 60.0 * (0.5 * x + 0.3 * y).sin() + 50.0 * (0.45 * y - 0.2 * x).cos()) as f32
    }

    #[test]
    fn refinement_finds_a_sub_pixel_displacement_in_both_directions() {
        let (w, h) = (64, 48);
        let reference: Vec<f32> = (0..w * h)
            .map(|i| texture(f64::from(i % w), f64::from(i / w)))
            .collect();
        // The neighbour sees the scene moved by 7.3 px along the search line (left: −x) and
        // 0.4 px across it (+y): its pixel (x − 7.3, y + 0.4) shows the reference's (x, y).
        let (d, s) = (7.3, 0.4);
        let neighbour: Vec<f32> = (0..w * h)
            .map(|i| texture(f64::from(i % w) + d, f64::from(i / w) - s))
            .collect();
        let template = Luma::new(&reference, w, h);
        let image = Luma::new(&neighbour, w, h);
        let mut checked = 0;
        for (x, y) in [(30, 20), (40, 24), (25, 30)] {
            let refined = refine_match(&template, &image, (x, y), ([-1, 0], [0, 1]), (7.0, 0.0));
            let (found_d, found_s) = refined.unwrap_or_else(|| panic!("no refinement at ({x}, {y})"));
            assert!(
                (found_d - d).abs() < 0.05 && (found_s - s).abs() < 0.05,
                "({found_d}, {found_s}) at ({x}, {y})"
            );
            checked += 1;
        }
        assert_eq!(checked, 3);
    }

    #[test]
    fn refinement_refuses_an_edge_that_hides_one_direction() {
        let (w, h) = (64, 48);
        // Vertical stripes only: a shift along y is not observable.
        let stripes: Vec<f32> = (0..w * h).map(|i| texture(f64::from(i % w), 0.0)).collect();
        let image = Luma::new(&stripes, w, h);
        assert_eq!(
            refine_match(&image, &image, (30, 20), ([-1, 0], [0, 1]), (0.0, 0.0)),
            None
        );
    }

    #[test]
    fn strip_search_matches_the_block_by_block_search() {
        let (w, h): (usize, usize) = (96, 80);
        let image = |phase: f64| -> Vec<f32> {
            (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f64, (i / w) as f64);
                    texture(x + phase, y - 0.5 * phase) + (((i * 7919) % 13) as f32)
                })
                .collect()
        };
        let (reference, other) = (image(0.0), image(2.3));
        let template = Luma::new(&reference, w as i32, h as i32);
        let neighbour = Luma::new(&other, w as i32, h as i32);
        let shifts = (2 * IMAGE_SHIFT_SEARCH_PX + 1) as usize;
        let mut patch = Vec::new();
        let mut off_image = 0;
        for (offset, across) in [
            ([1, 0], [0, 1]),
            ([-1, 0], [0, -1]),
            ([0, 1], [-1, 0]),
            ([0, -1], [1, 0]),
        ] {
            for (x, y, num_disparities) in [(20, 30, 24), (50, 12, 40), (12, 60, 70), (70, 70, 9)] {
                let mut fast = vec![0.0f32; shifts * num_disparities];
                let mut plain = fast.clone();
                search_costs(&template, &neighbour, (x, y), offset, across, &mut patch, &mut fast);
                search_costs_blockwise(&template, &neighbour, (x, y), offset, across, &mut plain);
                off_image += plain.iter().filter(|c| **c == f32::MAX).count();
                for (i, (a, b)) in fast.iter().zip(&plain).enumerate() {
                    let close = if *b == f32::MAX {
                        *a == f32::MAX
                    } else {
                        (a - b).abs() <= 1e-3 * b.max(1.0)
                    };
                    assert!(
                        close,
                        "offset {offset:?} at ({x}, {y}), cell {i}: strip {a} against blockwise {b}"
                    );
                }
            }
        }
        // Some searches ran off the image, so the edge handling was compared too.
        assert!(off_image > 0);
    }

    #[test]
    fn a_repeated_match_along_the_line_is_ambiguous() {
        assert!(is_unique(&[9.0, 5.0, 1.0, 5.0, 9.0], 2));
        assert!(!is_unique(&[9.0, 1.1, 5.0, 1.0, 9.0], 3));
    }
}
