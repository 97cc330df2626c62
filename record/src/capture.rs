//! The simulated capture: a planner that moves the UR10 to each view of a multiscopic set, the
//! error model (repeatability, injected per-view rotation/offset, hand-eye and exposure errors),
//! and the renderer producing each view with its ground truth.
//!
//! Time is simulated and deterministic: it starts at [`SIM_EPOCH_NANOS`] and advances with the
//! joint-space moves (speed-limited), the settle time after each move and the exposure time.

use std::sync::atomic::{AtomicBool, Ordering};

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::{DEFAULT_HORIZONTAL_FOV_DEG, DEFAULT_RESOLUTION, PinholeCamera};
use crate::render::{PreparedScene, RenderSettings};
use crate::rig::{REFERENCE_ROLE, RigKind};
use crate::rng::{SplitMix64, hash4};
use crate::scene::{Scene, SceneKind, WORK_AREA_CENTER_M};
use crate::ur10::{HOME_JOINTS_RAD, Joints, KinematicsError, Ur10, interpolate_joint_velocities, interpolate_joints};
use crate::{CapturedSet, CapturedView, ImageFormat, MotionSample};

/// Start of simulated time: 2020-01-01T00:00:00Z (ns since the Unix epoch).
pub const SIM_EPOCH_NANOS: u64 = 1_577_836_800_000_000_000;
/// The UR10's specified pose repeatability (mm).
pub const UR10_REPEATABILITY_MM: f64 = 0.1;
/// Exposure time charged per captured image (s).
const EXPOSURE_SECS: f64 = 0.05;

/// Camera axis named in an injected error.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraAxis {
    /// Camera x (right in the image).
    X,
    /// Camera y (down in the image).
    Y,
    /// Camera z (optical axis): rotation about it is roll; offset along it is out of plane.
    Z,
}

impl CameraAxis {
    fn unit(self) -> Vector3<f64> {
        match self {
            Self::X => Vector3::x(),
            Self::Y => Vector3::y(),
            Self::Z => Vector3::z(),
        }
    }
}

/// An error injected into one view's commanded pose (`ROLE:AXIS:VALUE` on the command line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewPoseError {
    /// Role of the affected view.
    pub role: String,
    /// Camera axis.
    pub axis: CameraAxis,
    /// Rotation (deg) or offset (mm), depending on the list it is in.
    pub value: f64,
}

/// An exposure gain forced on one view (`ROLE:GAIN`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewExposure {
    /// Role of the affected view.
    pub role: String,
    /// Gain (1 = nominal).
    pub gain: f64,
}

/// Error injection for testing alignment checks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorInjection {
    /// Radius of the random flange position error at every pose (mm); the UR10 specifies ±0.1.
    pub repeatability_mm: f64,
    /// Rotations added to views' commanded poses (deg, about a camera axis).
    pub rotation_deg: Vec<ViewPoseError>,
    /// Offsets added to views' commanded poses (mm, along a camera axis; z = out of plane).
    pub offset_mm: Vec<ViewPoseError>,
    /// Hand-eye calibration error: translation of the believed camera mount (mm, flange frame).
    pub hand_eye_translation_mm: [f64; 3],
    /// Hand-eye calibration error: rotation of the believed camera mount (deg, about flange x, y, z).
    pub hand_eye_rotation_deg: [f64; 3],
    /// Random exposure gain per view, uniform in [1 − j, 1 + j].
    pub exposure_jitter: f64,
    /// Exposure gains forced on given views.
    pub exposure: Vec<ViewExposure>,
}

impl Default for ErrorInjection {
    fn default() -> Self {
        Self {
            repeatability_mm: UR10_REPEATABILITY_MM,
            rotation_deg: Vec::new(),
            offset_mm: Vec::new(),
            hand_eye_translation_mm: [0.0; 3],
            hand_eye_rotation_deg: [0.0; 3],
            exposure_jitter: 0.0,
            exposure: Vec::new(),
        }
    }
}

/// The full effective configuration of a simulated recording (stored in the log's metadata).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimulationConfig {
    /// Rig layout.
    pub rig: RigKind,
    /// Distance between the reference view and each direct neighbour (mm).
    pub baseline_mm: f64,
    /// Number of view sets, each from a different arm station.
    pub captures: u32,
    /// Scene family.
    pub scene: SceneKind,
    /// Seed of everything random (scene, stations, noise, errors).
    pub seed: u64,
    /// Image width (pixels).
    pub width: u32,
    /// Image height (pixels).
    pub height: u32,
    /// Horizontal field of view (deg).
    pub horizontal_fov_deg: f64,
    /// Image encoding in the log.
    pub image_format: ImageFormat,
    /// Anti-aliasing samples per pixel.
    pub samples_per_pixel: u32,
    /// Sensor noise (8-bit levels, standard deviation).
    pub noise_sigma_levels: f64,
    /// Rate of the arm's transform and joint-state messages during motion (Hz).
    pub motion_rate_hz: f64,
    /// Wait after each move before the exposure (s).
    pub settle_secs: f64,
    /// Injected errors.
    pub errors: ErrorInjection,
    /// A converged rig: each view's principal point is shifted by its grid offset × `f·b/DIST`
    /// (Middlebury's `doffs`), so that a plane at this distance (m) has disparity 0, nearer points
    /// positive and farther ones negative disparities. `None`: parallel views (disparities ≥ 0).
    #[serde(default)]
    pub converge_m: Option<f64>,
    /// How an adaptive set is planned (rig `adaptive` only).
    #[serde(default)]
    pub adaptive: crate::adaptive::AdaptiveConfig,
    /// Log each set's working disparity range ([`Simulation::working_disparity_range`]) so that
    /// replay searches it, as a workcell that knows its table and tallest part would (always for
    /// converged rigs, whose range is signed, and adaptive sets, planned within it).
    #[serde(default)]
    pub log_working_range: bool,
}

impl Default for SimulationConfig {
    fn default() -> Self {
        Self {
            rig: RigKind::FiveView,
            baseline_mm: 20.0,
            captures: 1,
            scene: SceneKind::Toy,
            seed: 0,
            width: DEFAULT_RESOLUTION.0,
            height: DEFAULT_RESOLUTION.1,
            horizontal_fov_deg: DEFAULT_HORIZONTAL_FOV_DEG,
            image_format: ImageFormat::Raw,
            samples_per_pixel: 4,
            noise_sigma_levels: 1.0,
            motion_rate_hz: 30.0,
            settle_secs: 0.3,
            errors: ErrorInjection::default(),
            converge_m: None,
            adaptive: crate::adaptive::AdaptiveConfig::default(),
            log_working_range: false,
        }
    }
}

/// Errors of the simulation.
#[derive(Debug, thiserror::Error)]
pub enum SimulationError {
    /// The arm cannot reach a planned camera pose.
    #[error("set {set} view '{role}': the arm cannot reach the planned camera pose")]
    Kinematics {
        /// Set index.
        set: u32,
        /// View role.
        role: String,
        /// Why.
        #[source]
        source: KinematicsError,
    },
    /// The adaptive loop's method or planner rejected the views so far.
    #[error("set {set}: planning the next view failed")]
    Planning {
        /// Set index.
        set: u32,
        /// Cause.
        #[source]
        source: fuse::FuseError,
    },
    /// No candidate view of an adaptive set is both feasible and reachable.
    #[error("set {set}: no candidate for view {step} is within the search range and the arm's reach: {candidates}")]
    NothingToTake {
        /// Set index.
        set: u32,
        /// Which neighbour was being planned (1 = the first).
        step: u32,
        /// The candidates with what ruled each out.
        candidates: String,
    },
    /// A configuration value is out of range.
    #[error("invalid configuration: {field} = {value} ({reason})")]
    InvalidConfig {
        /// Field name.
        field: &'static str,
        /// Offending value.
        value: String,
        /// What is allowed.
        reason: &'static str,
    },
    /// An injected error names a role that the rig does not have.
    #[error("error injection names view '{role}', but the {rig} rig has only {roles}")]
    UnknownRole {
        /// The role given.
        role: String,
        /// Rig name.
        rig: &'static str,
        /// Roles of the rig.
        roles: String,
    },
}

/// The mount of the camera on the flange (`flange_from_camera`): 60 mm off-axis, 45 mm out,
/// rotated 90° about the tool axis, as a typical side-mounted USB camera bracket.
pub fn default_hand_eye() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.0, 0.06, 0.045),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
    )
}

/// A camera pose looking from `eye` at `target`, with the image's up direction (−y) towards
/// `up_hint` as far as possible.
pub fn look_at(eye: Point3<f64>, target: Point3<f64>, up_hint: Vector3<f64>) -> Isometry3<f64> {
    let z = (target - eye).normalize();
    let down_hint = -up_hint;
    let y = (down_hint - z * down_hint.dot(&z)).normalize();
    let x = y.cross(&z);
    Isometry3::from_parts(Translation3::from(eye.coords), crate::ur10::rotation_from_axes(x, y, z))
}

/// The simulator: scene, arm, camera and planner state.
pub struct Simulation {
    config: SimulationConfig,
    scene: Scene,
    prepared: PreparedScene,
    arm: Ur10,
    camera: PinholeCamera,
    hand_eye_true: Isometry3<f64>,
    hand_eye_believed: Isometry3<f64>,
    joints: Joints,
    time_nanos: u64,
    rng: SplitMix64,
}

fn secs_to_nanos(secs: f64) -> u64 {
    (secs * 1e9).round() as u64
}

impl Simulation {
    /// Validates the configuration and builds the scene.
    pub fn new(config: SimulationConfig) -> Result<Self, SimulationError> {
        validate(&config)?;
        let scene = Scene::build(config.scene, config.seed);
        let prepared = PreparedScene::new(&scene);
        let camera = PinholeCamera::from_horizontal_fov(config.width, config.height, config.horizontal_fov_deg);
        let hand_eye_true = default_hand_eye();
        let e = &config.errors;
        let error = Isometry3::from_parts(
            Translation3::new(
                e.hand_eye_translation_mm[0] / 1000.0,
                e.hand_eye_translation_mm[1] / 1000.0,
                e.hand_eye_translation_mm[2] / 1000.0,
            ),
            UnitQuaternion::from_euler_angles(
                e.hand_eye_rotation_deg[0].to_radians(),
                e.hand_eye_rotation_deg[1].to_radians(),
                e.hand_eye_rotation_deg[2].to_radians(),
            ),
        );
        Ok(Self {
            hand_eye_believed: error * hand_eye_true,
            rng: SplitMix64::new(config.seed ^ 0x706c_616e),
            config,
            scene,
            prepared,
            arm: Ur10::default(),
            camera,
            hand_eye_true,
            joints: HOME_JOINTS_RAD,
            time_nanos: SIM_EPOCH_NANOS,
        })
    }

    /// The effective configuration.
    pub fn config(&self) -> &SimulationConfig {
        &self.config
    }

    /// The scene being recorded.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The camera intrinsics (of the reference view; a converged rig's neighbours have their
    /// principal points shifted by [`Self::principal_point_shift_px`] per baseline).
    pub fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    /// The principal-point shift per baseline of grid offset (px; Middlebury's `doffs`):
    /// `f·b / converge_m` for a converged rig, 0 for parallel views.
    pub fn principal_point_shift_px(&self) -> f64 {
        self.config.converge_m.map_or(0.0, |distance| {
            self.camera.fx * self.config.baseline_mm / 1000.0 / distance
        })
    }

    /// The disparity search range of the capture from its known working depth: the table at the
    /// scene's camera height is the farthest point, the top of its highest object the nearest
    /// (2 px of margin each side, the count a multiple of 16), less the principal-point shift of
    /// a converged rig (its range is signed).
    pub fn working_disparity_range(&self) -> crate::DisparityRange {
        self.working_disparity_range_at(1)
    }

    /// [`Self::working_disparity_range`] of a set at `factor` times the baseline (its disparities
    /// `factor` times larger; the margins and the rounding stay in pixels).
    pub fn working_disparity_range_at(&self, factor: i32) -> crate::DisparityRange {
        let [far_px, near_px] = self.expected_disparity_px().map(|d| d * f64::from(factor.max(1)));
        let first = far_px.floor() as i32 - 2;
        let first = if self.config.converge_m.is_some() {
            first
        } else {
            first.max(0)
        };
        let last = near_px.ceil() as i32 + 2;
        let count = (last - first).max(1).unsigned_abs().div_ceil(16) * 16;
        crate::DisparityRange {
            min_disparity: first,
            num_disparities: Some(count),
        }
    }

    /// The disparities (px at one baseline) of the scene's farthest and nearest points as the
    /// workcell knows them before anything is measured: the table at the camera's height, the
    /// top of the highest object (at most 80 % of the way up), less a converged rig's shift.
    pub fn expected_disparity_px(&self) -> [f64; 2] {
        let far_m = self.scene.camera_height_m;
        let near_m = (far_m - self.scene.highest_point_m()).max(0.2 * far_m);
        let fb = self.camera.fx * self.config.baseline_mm / 1000.0;
        let shift = self.principal_point_shift_px();
        [fb / far_m - shift, fb / near_m - shift]
    }

    /// The arm model.
    pub fn arm(&self) -> &Ur10 {
        &self.arm
    }

    /// The hand-eye transform the system believes (`flange_from_camera`, logged).
    pub fn hand_eye_believed(&self) -> &Isometry3<f64> {
        &self.hand_eye_believed
    }

    /// Current simulated time (ns since the Unix epoch).
    pub fn time_nanos(&self) -> u64 {
        self.time_nanos
    }

    /// Current joints.
    pub fn joints(&self) -> &Joints {
        &self.joints
    }

    /// The station (reference camera pose) of set `index`: above the work area at the scene's
    /// camera height, looking at the work-area centre; later sets circle around the first. A
    /// later set's circle shrinks (halved, down to the first set's station) where the arm could
    /// not take every view of the rig from it: a high camera over the far side of the work area.
    pub fn station(&self, index: u32) -> Isometry3<f64> {
        let c = WORK_AREA_CENTER_M;
        let height = self.scene.camera_height_m;
        let target = Point3::new(c[0], c[1], 0.0);
        let angle = f64::from(index) * 2.399_963; // golden angle: stations spread evenly
        let at = |radius: f64| {
            let eye = Point3::new(c[0] + radius * angle.cos(), c[1] + radius * angle.sin(), height);
            look_at(eye, target, Vector3::x())
        };
        if index == 0 {
            return at(0.0);
        }
        let radius = 0.05 + 0.1 * (f64::from(index) / f64::from(self.config.captures.max(1)));
        [1.0, 0.5, 0.25]
            .into_iter()
            .map(|f| at(f * radius))
            .find(|station| self.reaches_every_view(station))
            .unwrap_or_else(|| at(0.0))
    }

    /// Whether the arm has an inverse-kinematics solution within its joint limits for every view
    /// of the rig from the reference pose `station` (what [`Self::capture_set`] asks of it).
    fn reaches_every_view(&self, station: &Isometry3<f64>) -> bool {
        let baseline_m = self.config.baseline_mm / 1000.0;
        self.config.rig.capture_order().into_iter().all(|slot| {
            let pose = crate::reach::view_pose(station, slot.grid_offset, baseline_m);
            self.arm
                .closest_solution(&(pose * self.hand_eye_believed.inverse()), &self.joints)
                .is_ok()
        })
    }

    fn move_to(&mut self, target: Joints, samples: &mut Vec<MotionSample>) {
        let start = self.joints;
        let duration = self.arm.move_duration_secs(&start, &target);
        let step = 1.0 / self.config.motion_rate_hz;
        let steps = (duration / step).ceil().max(1.0) as u64;
        let start_nanos = self.time_nanos;
        for i in 1..=steps {
            let fraction = i as f64 / steps as f64;
            let joints = interpolate_joints(&start, &target, fraction);
            let velocities = interpolate_joint_velocities(&start, &target, fraction, duration);
            samples.push(MotionSample {
                time_nanos: start_nanos + secs_to_nanos(duration * fraction),
                joints,
                joint_velocities: velocities,
                base_from_flange: self.arm.forward_kinematics(&joints),
            });
        }
        self.time_nanos = start_nanos + secs_to_nanos(duration);
        self.joints = target;
    }

    /// Plans, moves and renders one set. Returns `Ok(None)` if `stop` was raised before the set
    /// finished (nothing of the partial set is returned). `on_view` is called after each view.
    pub fn capture_set(
        &mut self,
        set: u32,
        stop: &AtomicBool,
        mut on_view: impl FnMut(&CapturedView),
    ) -> Result<Option<CapturedSet>, SimulationError> {
        let baseline_m = self.config.baseline_mm / 1000.0;
        let mut motion = Vec::new();
        let mut views = Vec::new();
        let mut believed_reference: Option<Isometry3<f64>> = None;
        let station = self.station(set);
        for slot in self.config.rig.capture_order() {
            if stop.load(Ordering::SeqCst) {
                return Ok(None);
            }
            let view = self.capture_view(
                set,
                (slot.role, slot.grid_offset),
                &station,
                believed_reference.as_ref(),
                baseline_m,
                &mut motion,
            )?;
            if slot.role == REFERENCE_ROLE {
                believed_reference = Some(view.world_from_camera);
            }
            on_view(&view);
            views.push(view);
        }
        Ok(Some(CapturedSet {
            index: set,
            name: format!("{}-{}", self.config.scene_name(), set),
            rig: self.config.rig.name().to_owned(),
            baseline_m,
            motion,
            views,
            // A converged rig's range is signed: replay would search from 0 without it.
            disparity_range: (self.config.converge_m.is_some() || self.config.log_working_range)
                .then(|| self.working_disparity_range()),
        }))
    }

    /// Moves to and renders the view `(role, grid_offset)` of set `set`, displaced from the
    /// believed reference pose (or the station, for the reference itself).
    pub(crate) fn capture_view(
        &mut self,
        set: u32,
        (role, grid_offset): (&str, [i32; 2]),
        station: &Isometry3<f64>,
        believed_reference: Option<&Isometry3<f64>>,
        baseline_m: f64,
        motion: &mut Vec<MotionSample>,
    ) -> Result<CapturedView, SimulationError> {
        let kinematics_error = |source| SimulationError::Kinematics {
            set,
            role: role.to_owned(),
            source,
        };
        // Target: displaced along the reference camera's own axes, as far as the system knows them.
        let reference = believed_reference.unwrap_or(station);
        let displacement = Vector3::new(
            f64::from(grid_offset[0]) * baseline_m,
            f64::from(grid_offset[1]) * baseline_m,
            0.0,
        );
        let mut commanded = reference * Isometry3::translation(displacement.x, displacement.y, displacement.z);
        let errors = self.config.errors.clone();
        for e in errors.rotation_deg.iter().filter(|e| e.role == role) {
            commanded *= Isometry3::from_parts(
                Translation3::identity(),
                UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(e.axis.unit()), e.value.to_radians()),
            );
        }
        for e in errors.offset_mm.iter().filter(|e| e.role == role) {
            let offset = e.axis.unit() * (e.value / 1000.0);
            commanded *= Isometry3::translation(offset.x, offset.y, offset.z);
        }
        let flange_target = commanded * self.hand_eye_believed.inverse();
        let target_joints = self
            .arm
            .closest_solution(&flange_target, &self.joints)
            .map_err(kinematics_error)?;
        // Repeatability: the arm settles within a small ball around the commanded flange pose.
        let repeatability_m = errors.repeatability_mm / 1000.0;
        let reached_joints = if repeatability_m > 0.0 {
            let direction = Vector3::new(self.rng.gaussian(), self.rng.gaussian(), self.rng.gaussian())
                .try_normalize(1e-12)
                .unwrap_or_else(Vector3::x);
            let radius = repeatability_m * self.rng.unit().cbrt();
            let offset = direction * radius;
            let reached = Isometry3::translation(offset.x, offset.y, offset.z) * flange_target;
            self.arm
                .closest_solution(&reached, &target_joints)
                .map_err(kinematics_error)?
        } else {
            target_joints
        };
        self.move_to(reached_joints, motion);
        self.time_nanos += secs_to_nanos(self.config.settle_secs);
        let capture_time_nanos = self.time_nanos;
        self.time_nanos += secs_to_nanos(EXPOSURE_SECS);
        let base_from_flange = self.arm.forward_kinematics(&reached_joints);
        motion.push(MotionSample {
            time_nanos: capture_time_nanos,
            joints: reached_joints,
            joint_velocities: [0.0; 6],
            base_from_flange,
        });
        let true_world_from_camera = base_from_flange * self.hand_eye_true;
        let world_from_camera = base_from_flange * self.hand_eye_believed;
        // A fixed rig's view by its place in the capture order; a planned view by its offset.
        let place = self.config.rig.capture_order().iter().position(|s| s.role == role);
        let view_index = u64::from(set) << 8
            | place.map_or_else(
                || 0x80 | ((grid_offset[0] + 8) as u64 & 0xf) << 4 | ((grid_offset[1] + 8) as u64 & 0xf),
                |p| p as u64,
            );
        let mut gain = 1.0;
        if errors.exposure_jitter > 0.0 {
            let u = crate::rng::unit_from_bits(hash4(self.config.seed, view_index, 0xe7, 0));
            gain = 1.0 + errors.exposure_jitter * (2.0 * u - 1.0);
        }
        if let Some(forced) = errors.exposure.iter().find(|e| e.role == role) {
            gain = forced.gain;
        }
        let settings = RenderSettings {
            samples_per_pixel: self.config.samples_per_pixel,
            max_bounces: 2,
            exposure_gain: gain,
            noise_sigma_levels: self.config.noise_sigma_levels,
            noise_seed: hash4(self.config.seed, view_index, 0x6e6f, 0),
        };
        let mut camera = self.camera;
        let shift = self.principal_point_shift_px();
        camera.cx += f64::from(grid_offset[0]) * shift;
        camera.cy += f64::from(grid_offset[1]) * shift;
        let rendered = self.prepared.render(&camera, &true_world_from_camera, &settings);
        Ok(CapturedView {
            role: role.to_owned(),
            grid_offset,
            camera,
            capture_time_nanos,
            rgb: rendered.rgb,
            depth_m: Some(rendered.depth_m),
            surface_class: Some(rendered.surface_class),
            world_from_camera,
            true_world_from_camera: Some(true_world_from_camera),
            commanded_world_from_camera: Some(commanded),
            joints: Some(reached_joints),
            exposure_gain: gain,
        })
    }
}

impl SimulationConfig {
    /// Views per set: the rig's, or an adaptive set's count.
    pub fn views_per_set(&self) -> u32 {
        if self.rig == RigKind::Adaptive {
            self.adaptive.views
        } else {
            self.rig.capture_order().len() as u32
        }
    }

    /// Scene name used in set names.
    pub fn scene_name(&self) -> &'static str {
        match self.scene {
            SceneKind::Toy => "toy",
            SceneKind::Workpiece => "workpiece",
            SceneKind::Random => "random",
            SceneKind::Clutter => "clutter",
            SceneKind::Bin => "bin",
            SceneKind::Thin => "thin",
            SceneKind::Fence => "fence",
            SceneKind::Lamps => "lamps",
            SceneKind::Slanted => "slanted",
        }
    }
}

/// Largest image side accepted (pixels).
pub const MAX_IMAGE_SIDE: u32 = 16_384;
/// Largest baseline accepted (mm): beyond this the rig leaves the UR10's 1.3 m reach anyway.
pub const MAX_BASELINE_MM: f64 = 1000.0;

fn validate(config: &SimulationConfig) -> Result<(), SimulationError> {
    let invalid = |field, value: String, reason| Err(SimulationError::InvalidConfig { field, value, reason });
    if !(config.baseline_mm > 0.0 && config.baseline_mm <= MAX_BASELINE_MM) {
        return invalid("baseline_mm", config.baseline_mm.to_string(), "must be > 0 and ≤ 1000");
    }
    if config.width < 8 || config.height < 8 || config.width > MAX_IMAGE_SIDE || config.height > MAX_IMAGE_SIDE {
        return invalid(
            "resolution",
            format!("{}x{}", config.width, config.height),
            "each side must be 8..=16384",
        );
    }
    if !(config.horizontal_fov_deg > 1.0 && config.horizontal_fov_deg < 170.0) {
        return invalid(
            "horizontal_fov_deg",
            config.horizontal_fov_deg.to_string(),
            "must be in (1, 170)",
        );
    }
    if config.captures == 0 {
        return invalid("captures", "0".into(), "must be at least 1");
    }
    if config.rig == RigKind::Adaptive {
        let adaptive = &config.adaptive;
        if !(2..=crate::adaptive::MAX_ADAPTIVE_VIEWS).contains(&adaptive.views) {
            return invalid("views", adaptive.views.to_string(), "an adaptive set has 2 to 9 views");
        }
        if fuse::methods::entry(&adaptive.method).is_none() {
            return invalid(
                "method",
                adaptive.method.clone(),
                "not a method (replay --list-methods)",
            );
        }
        if !(1..=4).contains(&adaptive.max_offset) {
            return invalid(
                "max_offset",
                adaptive.max_offset.to_string(),
                "must be 1 to 4 baselines",
            );
        }
        if let Some(px) = adaptive.max_disparity_px
            && !(px.is_finite() && px > 0.0)
        {
            return invalid("max_disparity_px", px.to_string(), "a disparity in pixels, > 0");
        }
    }
    if let Some(distance) = config.converge_m
        && !(distance.is_finite() && distance > 0.0)
    {
        return invalid("converge_m", distance.to_string(), "a distance in metres, > 0");
    }
    if !(config.motion_rate_hz > 0.0 && config.motion_rate_hz <= 1000.0) {
        return invalid(
            "motion_rate_hz",
            config.motion_rate_hz.to_string(),
            "must be in (0, 1000]",
        );
    }
    if !(config.errors.repeatability_mm >= 0.0 && config.errors.repeatability_mm < 100.0) {
        return invalid(
            "repeatability_mm",
            config.errors.repeatability_mm.to_string(),
            "must be in [0, 100)",
        );
    }
    let roles: Vec<&str> = config.rig.capture_order().iter().map(|s| s.role).collect();
    let named = config
        .errors
        .rotation_deg
        .iter()
        .chain(&config.errors.offset_mm)
        .map(|e| e.role.as_str())
        .chain(config.errors.exposure.iter().map(|e| e.role.as_str()));
    for role in named {
        if !roles.contains(&role) {
            return Err(SimulationError::UnknownRole {
                role: role.to_owned(),
                rig: config.rig.name(),
                roles: roles.join(", "),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small(config: SimulationConfig) -> SimulationConfig {
        SimulationConfig {
            width: 64,
            height: 40,
            samples_per_pixel: 1,
            ..config
        }
    }

    #[test]
    fn every_station_of_every_family_is_reachable_by_construction() {
        // Seeds whose camera was once drawn out of the arm's reach (1.32–1.37 m from the base),
        // then the highest of the first seeds of each family, with eight sets on the widest rig.
        let mut cases = vec![
            (SceneKind::Random, 7004),
            (SceneKind::Random, 3101),
            (SceneKind::Random, 3104),
        ];
        for kind in [
            SceneKind::Random,
            SceneKind::Clutter,
            SceneKind::Bin,
            SceneKind::Thin,
            SceneKind::Fence,
            SceneKind::Lamps,
            SceneKind::Slanted,
        ] {
            let highest = (0..200)
                .max_by(|a, b| {
                    let h = |s| Scene::build(kind, s).camera_height_m;
                    h(*a).total_cmp(&h(*b))
                })
                .unwrap_or(0);
            cases.push((kind, highest));
        }
        for (scene, seed) in cases {
            for rig in [RigKind::FiveView, RigKind::Grid3x3, RigKind::Line5, RigKind::GridCross] {
                let config = SimulationConfig {
                    scene,
                    seed,
                    rig,
                    captures: 8,
                    ..SimulationConfig::default()
                };
                let sim = Simulation::new(config).unwrap_or_else(|e| panic!("{scene:?} {seed}: {e}"));
                assert!(sim.scene.camera_height_m <= crate::scene::MAX_CAMERA_HEIGHT_M);
                for set in 0..8 {
                    let station = sim.station(set);
                    assert!(
                        sim.reaches_every_view(&station),
                        "{scene:?} seed {seed}, {rig:?}, set {set}: a view out of reach at {:.3} m",
                        sim.scene.camera_height_m
                    );
                }
            }
        }
    }

    #[test]
    fn a_slanted_plane_fills_the_view_within_the_working_range() {
        // Every pixel of the reference sees the plane (no background), its disparity spreads over
        // the view (a tilted plane) and stays inside the range the workcell expects from the
        // scene (`Scene::surface_top_m`: the plane's lowest point on the table, its highest
        // there), for the steepest and the flattest of the first seeds.
        for seed in 1..=6 {
            let config = small(SimulationConfig {
                scene: SceneKind::Slanted,
                seed,
                rig: RigKind::FiveView,
                ..SimulationConfig::default()
            });
            let mut sim = Simulation::new(config).unwrap_or_else(|e| panic!("seed {seed}: {e}"));
            let set = sim
                .capture_set(0, &AtomicBool::new(false), |_| {})
                .unwrap_or_else(|e| panic!("seed {seed}: {e}"))
                .unwrap_or_else(|| panic!("seed {seed}: no set"));
            let reference = set
                .views
                .iter()
                .find(|v| v.role == REFERENCE_ROLE)
                .unwrap_or_else(|| panic!("no reference"));
            let depth = reference.depth_m.as_ref().unwrap_or_else(|| panic!("no depth"));
            let fb = sim.camera.fx * sim.config.baseline_mm / 1000.0;
            let disparities: Vec<f64> = depth.iter().map(|d| fb / f64::from(*d)).collect();
            assert!(
                disparities.iter().all(|d| d.is_finite() && *d > 0.0),
                "seed {seed}: a pixel misses the plane"
            );
            let (low, high) = disparities
                .iter()
                .fold((f64::MAX, f64::MIN), |(l, h), d| (l.min(*d), h.max(*d)));
            let [far, near] = sim.expected_disparity_px();
            assert!(
                high > 1.05 * low,
                "seed {seed}: disparity {low:.3}–{high:.3} px is not slanted"
            );
            assert!(
                low >= far - 0.5 && high <= near + 0.5,
                "seed {seed}: {low:.2}–{high:.2} px outside {far:.2}–{near:.2}"
            );
        }
    }

    #[test]
    fn five_view_set_is_coplanar_at_the_baseline() {
        let config = small(SimulationConfig {
            errors: ErrorInjection {
                repeatability_mm: 0.0,
                ..ErrorInjection::default()
            },
            ..SimulationConfig::default()
        });
        let mut sim = Simulation::new(config).unwrap();
        let set = sim.capture_set(0, &AtomicBool::new(false), |_| {}).unwrap().unwrap();
        let center = set.views[0].true_world_from_camera.unwrap();
        for view in &set.views {
            let relative = center.inverse() * view.true_world_from_camera.unwrap();
            let expected = Vector3::new(f64::from(view.grid_offset[0]), f64::from(view.grid_offset[1]), 0.0) * 0.02;
            assert!(
                (relative.translation.vector - expected).norm() < 1e-9,
                "{}: {}",
                view.role,
                relative.translation.vector
            );
            assert!(relative.rotation.angle() < 1e-9);
        }
        // Time only moves forward.
        assert!(set.motion.windows(2).all(|w| w[0].time_nanos <= w[1].time_nanos));
    }

    #[test]
    fn bad_config_and_unknown_roles_are_rejected() {
        let zero = SimulationConfig {
            baseline_mm: 0.0,
            ..SimulationConfig::default()
        };
        assert!(matches!(
            Simulation::new(zero),
            Err(SimulationError::InvalidConfig {
                field: "baseline_mm",
                ..
            })
        ));
        let mut stereo = SimulationConfig {
            rig: RigKind::Stereo,
            ..SimulationConfig::default()
        };
        stereo.errors.offset_mm.push(ViewPoseError {
            role: "top".into(),
            axis: CameraAxis::Z,
            value: 1.0,
        });
        assert!(matches!(
            Simulation::new(stereo),
            Err(SimulationError::UnknownRole { .. })
        ));
    }
}
