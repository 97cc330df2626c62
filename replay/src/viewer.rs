//! What `replay --rerun` shows: each set's arm, cameras and images, a bounded cost volume per
//! neighbour and fused with the cost curves of probe pixels, and each method's result, error map,
//! metrics and alignment report. The drawing is `viz::stream`'s; this module picks the data.

use fuse::cost::PixelCost;
use fuse::fusion::Fusion;
use fuse::sgm::{INVALID_QUANTISED, quantisation_shift};
use fuse::volume::{CostSpec, PreparedProblem, VolumeSource, neighbour_volumes};
use fuse::{Image, Neighbour, Problem};
use rayon::prelude::*;
use record::ur10::Ur10;
use viz::stream::{CameraView, Layout, Viewer, VizError};

use crate::check::{SetCheck, Status};
use crate::regions::RegionMetrics;
use crate::viewset::{View, ViewSet};

/// Largest cost volume sent to the viewer (cells): larger problems are shown downsampled.
pub const MAX_TENSOR_CELLS: usize = 6_000_000;
/// Error map colour range (px): errors at or above it are dark red.
pub const ERROR_SCALE_PX: f32 = 4.0;

/// The blueprint's contents for a set and methods.
pub fn layout(set: &ViewSet, methods: &[&str]) -> Layout {
    let mut roles = vec![set.reference.role.clone()];
    roles.extend(set.neighbours.iter().map(|n| n.role.clone()));
    let mut cost_sources = vec!["fused".to_owned()];
    cost_sources.extend(set.neighbours.iter().map(|n| n.role.clone()));
    Layout {
        roles,
        methods: methods.iter().map(|m| (*m).to_owned()).collect(),
        cost_sources,
    }
}

fn camera_view<'a>(view: &'a View, depth_m: Option<&'a [f32]>) -> CameraView<'a> {
    CameraView {
        role: &view.role,
        world_from_camera: &view.world_from_camera,
        intrinsics: [view.camera.fx, view.camera.fy, view.camera.cx, view.camera.cy],
        width: view.camera.width,
        height: view.camera.height,
        rgb: &view.rgb,
        depth_m,
        time_nanos: view.capture_time_nanos,
    }
}

/// The set's capture: the table, the arm at each view's capture time (when the log has the
/// joints), and every camera with its image (and the reference's ground-truth depth).
pub fn log_capture(viewer: &Viewer, set: &ViewSet) -> Result<(), VizError> {
    record::live::log_table(viewer)?;
    let arm = Ur10::default();
    let mut views: Vec<&View> = std::iter::once(&set.reference).chain(&set.neighbours).collect();
    views.sort_by_key(|v| v.capture_time_nanos);
    for view in views {
        viewer.set_capture_time(view.capture_time_nanos);
        if let Some(joints) = &view.joints {
            viewer.log_arm(&arm.frames_from_base(joints))?;
        }
        let depth = if view.role == set.reference.role {
            set.ground_truth_depth_m.as_deref()
        } else {
            None
        };
        viewer.log_camera(&camera_view(view, depth))?;
    }
    Ok(())
}

/// The plans of an adaptive set (`/capture/plan`) on the capture timeline: at each plan's time,
/// every candidate's frustum coloured by score and the chosen one marked, and the depth and
/// confidence the plan was made from, computed again by the plan's method from the views taken
/// before it (the log keeps the scores, not the estimates).
pub fn log_plans(viewer: &Viewer, set: &ViewSet, plans: &[record::adaptive::PlanStep]) -> Result<(), VizError> {
    let camera = &set.reference.camera;
    for step in plans.iter().filter(|p| p.set_index == set.index) {
        let estimate = estimate_before(set, step);
        viewer.set_capture_time(step.time_nanos);
        viewer.log_plan(
            &step.frusta(),
            (
                [camera.fx, camera.fy, camera.cx, camera.cy],
                [camera.width, camera.height],
            ),
            estimate
                .as_ref()
                .map(|(e, c, fb)| (e.data.as_slice(), c.as_slice(), *fb)),
        )?;
    }
    Ok(())
}

/// What `step` was planned from: its method's disparity and confidence on the reference and the
/// views taken before it, with the focal length × baseline of that estimate. `None` for the
/// first step (planned before any depth) and where the views or the method are not there.
fn estimate_before(set: &ViewSet, step: &record::adaptive::PlanStep) -> Option<(fuse::DisparityImage, Vec<f32>, f64)> {
    let name = step.method.as_deref()?;
    // The set's offsets are the plan's divided by the factor the set was stored at.
    let stored = (set.baseline_m / step.baseline_m).round().max(1.0) as i32;
    let taken: Vec<&View> = set
        .neighbours
        .iter()
        .filter(|n| step.taken.contains(&n.offset.map(|o| o * stored)))
        .collect();
    if taken.is_empty() || taken.len() != step.taken.len() {
        return None;
    }
    // As the loop ran it: at the common factor of the views taken so far.
    let factor = record::adaptive::common_factor(step.taken.iter().copied());
    let ratio = f64::from(factor) / f64::from(stored);
    let (min_disparity, num_disparities) = set.search_range(None, None);
    let subset = ViewSet {
        neighbours: taken
            .into_iter()
            .map(|v| {
                let offset = v.offset.map(|o| o * stored / factor);
                View {
                    role: record::rig::role_for_offset(offset),
                    offset,
                    ..v.clone()
                }
            })
            .collect(),
        baseline_m: step.baseline_m * f64::from(factor),
        ..set.clone()
    };
    let problem = subset
        .problem(
            (f64::from(min_disparity) * ratio).floor() as i32,
            (num_disparities as f64 * ratio).ceil() as usize,
            false,
        )
        .ok()?;
    let method = fuse::methods::build(name, None).ok()?;
    let estimate = method.run(&problem, &|_| {}).ok()?;
    let confidence = estimate
        .confidence
        .clone()
        .unwrap_or_else(|| vec![0.0; estimate.data.len()]);
    Some((estimate, confidence, set.reference.camera.fx * subset.baseline_m))
}

/// Box-averages an image by `factor` (rows and columns beyond a whole block are dropped).
fn downsample(image: &Image, factor: usize) -> Image {
    let (w, h, c) = (image.width / factor, image.height / factor, image.channels);
    let mut data = vec![0u8; w * h * c];
    let area = (factor * factor) as u32;
    data.par_chunks_mut(w * c).enumerate().for_each(|(y, out)| {
        let mut sums = vec![0u32; w * c];
        for row in 0..factor {
            let source = &image.data[(y * factor + row) * image.width * c..][..w * factor * c];
            for (x, block) in source.chunks_exact(factor * c).enumerate() {
                for pixel in block.chunks_exact(c) {
                    for (sum, value) in sums[x * c..(x + 1) * c].iter_mut().zip(pixel) {
                        *sum += u32::from(*value);
                    }
                }
            }
        }
        for (o, sum) in out.iter_mut().zip(&sums) {
            *o = (sum / area) as u8;
        }
    });
    Image {
        width: w,
        height: h,
        channels: c,
        data,
    }
}

/// Probe pixels whose cost curves are shown: where ground truth says the pixel is occluded in
/// some neighbour, textureless, or specular. Each is `(name, x, y)` in full-resolution pixels.
pub fn probe_pixels(set: &ViewSet, occluded: Option<&[bool]>) -> Vec<(String, usize, usize)> {
    let (w, h) = (set.width(), set.height());
    let mut probes = Vec::new();
    let Some(truth) = set.ground_truth_disparity() else {
        // Without ground truth: the image centre.
        return vec![("centre".to_owned(), w / 2, h / 2)];
    };
    let margin = w.min(h) / 8;
    let inside = |x: usize, y: usize| x >= margin && y >= margin && x + margin < w && y + margin < h;
    let no_occlusion = vec![false; w * h];
    let occluded = occluded.unwrap_or(&no_occlusion);
    let pick = |keep: &dyn Fn(usize) -> bool| {
        (0..w * h)
            .step_by(7)
            .find(|p| truth[*p].is_finite() && inside(p % w, p / w) && keep(*p))
            .map(|p| (p % w, p / w))
    };
    if let Some((x, y)) = pick(&|p| occluded[p]) {
        probes.push(("occluded".to_owned(), x, y));
    }
    if let Some(surface) = &set.surface_class
        && let Some((x, y)) = pick(&|p| {
            surface[p] == record::scene::SurfaceClass::Glossy as u8
                || surface[p] == record::scene::SurfaceClass::Mirror as u8
        })
    {
        probes.push(("specular".to_owned(), x, y));
    }
    // Textureless: the smallest local gradient on a coarse grid.
    let grey = |x: usize, y: usize| {
        let p = (y * w + x) * 3;
        i32::from(set.reference.rgb[p]) + i32::from(set.reference.rgb[p + 1]) + i32::from(set.reference.rgb[p + 2])
    };
    let step = (w / 64).max(4);
    let mut best: Option<(i32, usize, usize)> = None;
    for y in (margin..h.saturating_sub(margin)).step_by(step) {
        for x in (margin..w.saturating_sub(margin)).step_by(step) {
            if !truth[y * w + x].is_finite() || occluded[y * w + x] {
                continue;
            }
            let mut gradient = 0;
            for d in 1..4 {
                gradient += (grey(x + d, y) - grey(x - d, y)).abs() + (grey(x, y + d) - grey(x, y - d)).abs();
            }
            if best.is_none_or(|(g, _, _)| gradient < g) {
                best = Some((gradient, x, y));
            }
        }
    }
    if let Some((_, x, y)) = best {
        probes.push(("textureless".to_owned(), x, y));
    }
    probes
}

/// Cost volumes (each neighbour's and the fused one, block matching's data term) at a
/// resolution that keeps each under [`MAX_TENSOR_CELLS`], and the cost curves of the probe pixels.
pub fn log_costs(viewer: &Viewer, set: &ViewSet, problem: &Problem, occluded: Option<&[bool]>) -> Result<(), VizError> {
    let (w, h, nd) = (
        problem.reference.width,
        problem.reference.height,
        problem.num_disparities,
    );
    let mut factor = 1;
    while (w / factor) * (h / factor) * nd.div_ceil(factor) > MAX_TENSOR_CELLS && factor < 16 {
        factor *= 2;
    }
    let small = |image: &Image| {
        if factor == 1 {
            image.clone()
        } else {
            downsample(image, factor)
        }
    };
    let reference = small(&problem.reference);
    let (sw, sh, snd) = (reference.width, reference.height, nd.div_ceil(factor));
    let spec = CostSpec {
        pixel: PixelCost::BirchfieldTomasi,
        block_radius_px: 4,
    };
    let neighbours: Vec<Neighbour> = problem
        .neighbours
        .iter()
        .map(|n| Neighbour {
            role: n.role.clone(),
            image: small(&n.image),
            offset: n.offset,
            baseline_ratio: n.baseline_ratio,
        })
        .collect();
    let started = std::time::Instant::now();
    let probes = probe_pixels(set, occluded);
    tracing::debug!(
        "rerun costs: downsampled and probes chosen in {:.3} s",
        started.elapsed().as_secs_f64()
    );
    let min_disparity = problem.min_disparity.div_euclid(factor as i32);
    // Each neighbour's aggregated costs and their heuristic fusion, as the methods fuse them,
    // quantised to bytes (255 = no correspondence), the viewer's tensor encoding.
    let small_problem = Problem {
        reference,
        neighbours,
        min_disparity,
        num_disparities: snd,
    };
    let shift = quantisation_shift(spec.max_cost());
    let refs: Vec<&Neighbour> = small_problem.neighbours.iter().collect();
    let mut volumes = match neighbour_volumes(&small_problem, &refs, spec, shift, &|| {}) {
        Ok(volumes) => volumes,
        Err(e) => {
            tracing::warn!("Rerun: the cost volumes are not shown: {e}");
            return Ok(());
        }
    };
    match PreparedProblem::new(&small_problem, spec, Fusion::Heuristic) {
        Ok(prepared) => volumes.insert(0, prepared.fused_volume(shift, &|| {})),
        Err(e) => tracing::warn!("Rerun: the fused cost volume is not shown: {e}"),
    }
    tracing::debug!(
        "rerun costs: volumes computed in {:.3} s",
        started.elapsed().as_secs_f64()
    );
    // Mean cost per block pixel, in the units of the pixel cost.
    let block_pixels = ((2 * spec.block_radius_px + 1) * (2 * spec.block_radius_px + 1)) as f32;
    let unit = (1u32 << shift) as f32 / block_pixels;
    for volume in &volumes {
        let name = match &volume.source {
            VolumeSource::Neighbour { role, .. } => role.as_str(),
            VolumeSource::Fused(_) => "fused",
        };
        viewer.log_cost_volume(name, &volume.data, volume.shape())?;
        for (probe, x, y) in &probes {
            let (px, py) = ((x / factor).min(sw - 1), (y / factor).min(sh - 1));
            let curve: Vec<f32> = volume
                .costs(px, py)
                .iter()
                .map(|c| {
                    if *c == INVALID_QUANTISED {
                        f32::NAN
                    } else {
                        f32::from(*c) * unit
                    }
                })
                .collect();
            viewer.log_cost_curve(probe, name, i64::from(min_disparity) * factor as i64, factor, &curve)?;
        }
    }
    Ok(())
}

/// A method's result on a set: depth under the centre pinhole, error map, metrics, and the
/// set's alignment report.
pub fn log_result(
    viewer: &Viewer,
    set: &ViewSet,
    method: &str,
    disparity: &fuse::DisparityImage,
    metrics: Option<&RegionMetrics>,
    alignment: &SetCheck,
) -> Result<(), VizError> {
    viewer.set_capture_time(set.reference.capture_time_nanos);
    viewer.set_set_index(set.index);
    let truth = set.ground_truth_disparity();
    viewer.log_result(
        method,
        [disparity.width as u32, disparity.height as u32],
        &disparity.data,
        set.reference.camera.fx * set.baseline_m,
        set.disparity_offset_px(),
        truth.as_deref(),
        ERROR_SCALE_PX,
    )?;
    if let Some(confidence) = &disparity.confidence {
        viewer.log_confidence(method, [disparity.width as u32, disparity.height as u32], confidence)?;
    }
    if let Some(m) = metrics {
        viewer.log_metrics(
            method,
            &[
                ("avg_err_px", m.all.avg_err_px),
                ("rms_px", m.all.rms),
                ("bad1_percent", m.all.bad_1),
                ("avg_err_occluded_px", m.occluded.map_or(f64::NAN, |o| o.avg_err_px)),
                ("avg_err_specular_px", m.specular.map_or(f64::NAN, |s| s.avg_err_px)),
            ],
        )?;
    }
    let level = match alignment.status {
        Status::Ok => "INFO",
        Status::Warn => "WARN",
        Status::Fail => "ERROR",
    };
    viewer.log_alignment(
        &format!(
            "set {} ({}) alignment {:?}\n{}",
            set.index,
            set.name,
            alignment.status,
            crate::check::table(alignment)
        ),
        level,
    )
}
