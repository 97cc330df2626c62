//! View sets: the reference view, its neighbours with their roles and grid offsets, intrinsics,
//! poses, baseline and ground truth, as replay and the methods need them.

use nalgebra::Isometry3;
use record::camera::PinholeCamera;
use record::rig::REFERENCE_ROLE;
use record::{CapturedSet, CapturedView};

use crate::ReplayError;

/// One view of a set.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Role (`center`, `left`, …).
    pub role: String,
    /// Position in baselines along the reference camera's x and y.
    pub offset: [i32; 2],
    /// Intrinsics.
    pub camera: PinholeCamera,
    /// 8-bit RGB.
    pub rgb: Vec<u8>,
    /// Pose as logged (`/tf` at the image time).
    pub world_from_camera: Isometry3<f64>,
    /// Ground-truth pose, when the log has it (simulation).
    pub true_world_from_camera: Option<Isometry3<f64>>,
    /// Image time (ns).
    pub capture_time_nanos: u64,
    /// Arm joint positions at the image time (rad), when the log has them.
    pub joints: Option<[f64; 6]>,
    /// The image's frame in the log (its `frame_id`; our own logs: `camera_<role>`), which
    /// results written beside it name.
    pub frame_id: String,
}

/// A multiscopic view set.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewSet {
    /// Index in the log.
    pub index: u32,
    /// Name.
    pub name: String,
    /// Rig layout name.
    pub rig: String,
    /// Commanded baseline (m).
    pub baseline_m: f64,
    /// The reference view.
    pub reference: View,
    /// The neighbours.
    pub neighbours: Vec<View>,
    /// Ground-truth z-depth of the reference (m, 0 = unknown).
    pub ground_truth_depth_m: Option<Vec<f32>>,
    /// Ground-truth surface classes of the reference (simulation).
    pub surface_class: Option<Vec<u8>>,
    /// The disparities to search, when the log says (imported folders, converged rigs).
    pub disparity_range: Option<record::DisparityRange>,
}

fn view_from_captured(view: &CapturedView) -> View {
    View {
        role: view.role.clone(),
        offset: view.grid_offset,
        camera: view.camera,
        rgb: view.rgb.clone(),
        world_from_camera: view.world_from_camera,
        true_world_from_camera: view.true_world_from_camera,
        capture_time_nanos: view.capture_time_nanos,
        joints: view.joints,
        frame_id: record::log::view_frame(&view.role),
    }
}

impl ViewSet {
    /// A set from a captured (simulated or imported) set.
    pub fn from_captured(set: &CapturedSet) -> Result<Self, ReplayError> {
        let reference =
            set.views
                .iter()
                .find(|v| v.role == REFERENCE_ROLE)
                .ok_or_else(|| ReplayError::MissingView {
                    set: set.index,
                    role: REFERENCE_ROLE.into(),
                })?;
        Ok(Self {
            index: set.index,
            name: set.name.clone(),
            rig: set.rig.clone(),
            baseline_m: set.baseline_m,
            reference: view_from_captured(reference),
            neighbours: set
                .views
                .iter()
                .filter(|v| v.role != REFERENCE_ROLE)
                .map(view_from_captured)
                .collect(),
            ground_truth_depth_m: reference.depth_m.clone(),
            surface_class: reference.surface_class.clone(),
            disparity_range: set.disparity_range,
        })
    }

    /// Image width.
    pub fn width(&self) -> usize {
        self.reference.camera.width as usize
    }

    /// Image height.
    pub fn height(&self) -> usize {
        self.reference.camera.height as usize
    }

    /// Disparities searched when none are given: about a fifteenth of the width, rounded up to
    /// a multiple of 16 (32 for Middlebury's third size, 128 for 1920 px).
    pub fn default_num_disparities(&self) -> usize {
        fuse::default_num_disparities(self.width())
    }

    /// The range `(min, count)` searched: each of `min_disparity` and `num_disparities` as given,
    /// else as the log's range for the set says, else from 0 over
    /// [`Self::default_num_disparities`].
    pub fn search_range(&self, min_disparity: Option<i32>, num_disparities: Option<usize>) -> (i32, usize) {
        let logged = self.disparity_range.as_ref();
        let min = min_disparity.or(logged.map(|r| r.min_disparity)).unwrap_or(0);
        let count = num_disparities
            .or(logged.and_then(|r| r.num_disparities).map(|n| n as usize))
            .unwrap_or_else(|| self.default_num_disparities());
        (min, count)
    }

    /// Principal-point offset between the reference and a direct neighbour (px; Middlebury 2014's
    /// `doffs`) from the logged intrinsics: `(c_n − c_ref) / offset` along the first neighbour
    /// on an axis (x preferred); 0 for simulated sets. A pixel disparity `d` (what the methods
    /// estimate) is at depth `z = f·b / (d + doffs)`.
    pub fn disparity_offset_px(&self) -> f64 {
        let along = |axis: usize| {
            self.neighbours
                .iter()
                .find(|n| n.offset[axis] != 0 && n.offset[1 - axis] == 0)
                .map(|n| {
                    let (c_n, c_ref) = if axis == 0 {
                        (n.camera.cx, self.reference.camera.cx)
                    } else {
                        (n.camera.cy, self.reference.camera.cy)
                    };
                    (c_n - c_ref) / f64::from(n.offset[axis])
                })
        };
        along(0).or_else(|| along(1)).filter(|d| d.is_finite()).unwrap_or(0.0)
    }

    /// Depth (m) of a pixel disparity to a direct neighbour, `f·b / (d + doffs)` (`None` when not
    /// finite and positive), with `f·b` and doffs worked out once for a whole image.
    pub fn disparity_to_depth_m(&self) -> impl Fn(f32) -> Option<f64> + use<> {
        let fb = self.reference.camera.fx * self.baseline_m;
        let doffs = self.disparity_offset_px();
        move |disparity_px| fuse::depth_from_disparity(fb, 1.0, f64::from(disparity_px) + doffs)
    }

    /// Ground-truth pixel disparity `f·b/z − doffs` of the reference to a direct neighbour (NaN =
    /// unknown; signed: a converged rig's far points are negative).
    pub fn ground_truth_disparity(&self) -> Option<Vec<f32>> {
        let fb = self.reference.camera.fx * self.baseline_m;
        let doffs = self.disparity_offset_px();
        self.ground_truth_depth_m.as_ref().map(|depth| {
            depth
                .iter()
                .map(|z| {
                    fuse::disparity_from_depth(fb, 1.0, f64::from(*z))
                        .map(|d| d - doffs)
                        .filter(|d| d.is_finite())
                        .map_or(f32::NAN, |d| d as f32)
                })
                .collect()
        })
    }

    /// The same set restricted to the neighbours with these roles (all when empty).
    pub fn with_neighbours(&self, roles: &[String]) -> Result<Self, ReplayError> {
        if roles.is_empty() {
            return Ok(self.clone());
        }
        if let Some(missing) = roles.iter().find(|r| !self.neighbours.iter().any(|n| &n.role == *r)) {
            return Err(ReplayError::MissingView {
                set: self.index,
                role: missing.clone(),
            });
        }
        Ok(Self {
            neighbours: self
                .neighbours
                .iter()
                .filter(|n| roles.contains(&n.role))
                .cloned()
                .collect(),
            ..self.clone()
        })
    }

    /// Metrics of a disparity estimate against the ground truth, overall and in the regions
    /// occluded in at least one of this set's direct neighbours and on specular surfaces.
    pub fn region_metrics(&self, estimate: &[f32], missing_error_px: f64) -> Option<crate::regions::RegionMetrics> {
        let truth = self.ground_truth_disparity()?;
        crate::regions::region_metrics(
            estimate,
            None,
            &truth,
            &self.occlusion_mask(&truth),
            self.surface_class.as_deref(),
            missing_error_px,
        )
    }

    /// Pixels occluded in at least one *direct* neighbour (one baseline away, diagonals
    /// included), from the set's [`Self::ground_truth_disparity`] `truth` (a forward warp per
    /// neighbour, each in parallel). Views at a multiple of the baseline are left out so that a
    /// set and its subsets with more or fewer far views are measured on the same region. Compute
    /// once per set when several estimates are evaluated.
    pub fn occlusion_mask(&self, truth: &[f32]) -> Vec<bool> {
        let (w, h) = (self.width(), self.height());
        let direct: Vec<&View> = self
            .neighbours
            .iter()
            .filter(|n| n.offset[0].abs().max(n.offset[1].abs()) == 1)
            .collect();
        let warped = if direct.is_empty() {
            self.neighbours.iter().collect()
        } else {
            direct
        };
        let offsets: Vec<[i32; 2]> = warped.iter().map(|n| n.offset).collect();
        let mut occluded = vec![false; w * h];
        crate::regions::mark_occluded_all(truth, w, h, &offsets, &mut occluded);
        occluded
    }

    /// Position of a neighbour's camera centre in the reference camera frame (m), from the
    /// logged poses.
    pub fn relative_translation(&self, neighbour: &View) -> nalgebra::Vector3<f64> {
        (self.reference.world_from_camera.inverse() * neighbour.world_from_camera)
            .translation
            .vector
    }

    /// Real baseline of a neighbour along its nominal direction ÷ the nominal baseline
    /// (`|offset| · baseline_m`), from the logged poses; 1 when the poses are ideal.
    pub fn baseline_ratio(&self, neighbour: &View) -> f64 {
        let direction = nalgebra::Vector3::new(f64::from(neighbour.offset[0]), f64::from(neighbour.offset[1]), 0.0);
        let nominal = direction.norm() * self.baseline_m;
        if nominal <= 0.0 {
            return 1.0;
        }
        let along = self.relative_translation(neighbour).dot(&direction.normalize());
        if along > 0.0 { along / nominal } else { 1.0 }
    }

    /// A neighbour's image re-rendered as if taken with the reference camera's orientation (the
    /// homography `K Rᵀ K⁻¹` of its relative rotation R, bilinear); translation errors cannot be
    /// corrected this way.
    pub fn derotated_rgb(&self, neighbour: &View) -> Vec<u8> {
        let relative = self.reference.world_from_camera.inverse() * neighbour.world_from_camera;
        if relative.rotation.angle() < 1e-9 {
            return neighbour.rgb.clone();
        }
        let k = neighbour.camera.k_matrix();
        let k_inv = k.try_inverse().unwrap_or_else(nalgebra::Matrix3::identity);
        let h = k * relative.rotation.to_rotation_matrix().matrix().transpose() * k_inv;
        let (w, ht) = (neighbour.camera.width as usize, neighbour.camera.height as usize);
        let mut out = vec![0u8; w * ht * 3];
        for y in 0..ht {
            for x in 0..w {
                let p = h * nalgebra::Vector3::new(x as f64, y as f64, 1.0);
                let (u, v) = (p.x / p.z, p.y / p.z);
                let (u, v) = (u.clamp(0.0, (w - 1) as f64), v.clamp(0.0, (ht - 1) as f64));
                let (x0, y0) = (u.floor() as usize, v.floor() as usize);
                let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(ht - 1));
                let (tx, ty) = (u - x0 as f64, v - y0 as f64);
                for c in 0..3 {
                    let at = |xx: usize, yy: usize| f64::from(neighbour.rgb[(yy * w + xx) * 3 + c]);
                    let top = at(x0, y0) * (1.0 - tx) + at(x1, y0) * tx;
                    let bottom = at(x0, y1) * (1.0 - tx) + at(x1, y1) * tx;
                    out[(y * w + x) * 3 + c] = (top * (1.0 - ty) + bottom * ty).round() as u8;
                }
            }
        }
        out
    }

    /// The matching problem of this set (RGB images). With `rectify`, what the logged poses allow
    /// is corrected: each neighbour is de-rotated by a homography and its costs are resampled by
    /// its real baseline ratio. Out-of-plane and perpendicular translation remain (see `check`).
    pub fn problem(
        &self,
        min_disparity: i32,
        num_disparities: usize,
        rectify: bool,
    ) -> Result<fuse::Problem, ReplayError> {
        let image = |view: &View| {
            let rgb = if rectify && view.role != self.reference.role {
                self.derotated_rgb(view)
            } else {
                view.rgb.clone()
            };
            fuse::Image::rgb(view.camera.width as usize, view.camera.height as usize, rgb).map_err(|source| {
                ReplayError::Fuse {
                    set: self.index,
                    source,
                }
            })
        };
        Ok(fuse::Problem {
            reference: image(&self.reference)?,
            neighbours: self
                .neighbours
                .iter()
                .map(|n| {
                    Ok(fuse::Neighbour {
                        role: n.role.clone(),
                        image: image(n)?,
                        offset: n.offset,
                        baseline_ratio: if rectify { self.baseline_ratio(n) as f32 } else { 1.0 },
                    })
                })
                .collect::<Result<_, ReplayError>>()?,
            min_disparity,
            num_disparities,
        })
    }
}
