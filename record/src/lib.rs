//! `record`: multiscopic captures as MCAP logs.
//!
//! Two sources feed the same log format (the contract `replay` reads, see [`log`] and
//! ARCHITECTURE.md):
//! - [`capture::Simulation`]: a simulated UR10 ([`ur10`]) moving a camera ([`camera`]) in its
//!   own image plane over a procedural scene ([`scene`]) rendered by a CPU ray tracer
//!   ([`render`]) with ground-truth depth;
//! - [`import`]: real image sets on disk (e.g. the Middlebury layout) with their ground truth.
//!
//! Both produce [`CapturedSet`]s, which [`log::LogWriter`] writes as Foxglove-schema messages.

pub mod adaptive;
pub mod bag;
pub mod camera;
pub mod capture;
pub mod import;
pub mod live;
pub mod log;
pub mod reach;
pub mod render;
pub mod rig;
pub mod rng;
pub mod scene;
mod sensor_noise;
pub mod session;
pub mod ur10;

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::camera::PinholeCamera;
use crate::ur10::Joints;

/// The tool version written into every log's metadata.
pub const TOOL_VERSION: &str = env!("CARGO_PKG_VERSION");

/// How images are stored in the log.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum ImageFormat {
    /// `foxglove.RawImage`, `rgb8` (largest, fastest, exact).
    Raw,
    /// `foxglove.CompressedImage`, PNG (lossless, smaller, slower to write).
    Png,
}

/// The arm's state at one instant of a move (or at a capture).
#[derive(Debug, Clone, PartialEq)]
pub struct MotionSample {
    /// Simulated time (ns since the Unix epoch).
    pub time_nanos: u64,
    /// Joint positions (rad).
    pub joints: Joints,
    /// Joint velocities (rad/s).
    pub joint_velocities: Joints,
    /// Forward kinematics of `joints`.
    pub base_from_flange: Isometry3<f64>,
}

/// One captured view with everything the log records about it.
#[derive(Debug, Clone, PartialEq)]
pub struct CapturedView {
    /// Role in the rig (`center`, `left`, …).
    pub role: String,
    /// Offset in baselines along the reference camera's x and y axes.
    pub grid_offset: [i32; 2],
    /// Intrinsics.
    pub camera: PinholeCamera,
    /// Exposure time (ns since the Unix epoch).
    pub capture_time_nanos: u64,
    /// 8-bit RGB, row-major.
    pub rgb: Vec<u8>,
    /// Ground-truth z-depth (m), 0 = unknown.
    pub depth_m: Option<Vec<f32>>,
    /// Ground-truth surface class per pixel (see [`scene::SurfaceClass`]).
    pub surface_class: Option<Vec<u8>>,
    /// Camera pose as the system knows it (arm forward kinematics and the hand-eye estimate).
    pub world_from_camera: Isometry3<f64>,
    /// The true camera pose the image was rendered from (simulation only).
    pub true_world_from_camera: Option<Isometry3<f64>>,
    /// The pose the planner commanded.
    pub commanded_world_from_camera: Option<Isometry3<f64>>,
    /// Joint positions at the capture.
    pub joints: Option<Joints>,
    /// Exposure gain applied (1 = nominal).
    pub exposure_gain: f64,
}

impl CapturedView {
    /// A view as an import knows it: role, grid offset, intrinsics, the believed pose, the
    /// capture time and the image; no ground truth, true or commanded pose or joints, nominal
    /// exposure.
    pub fn new(
        (role, grid_offset): (&str, [i32; 2]),
        camera: PinholeCamera,
        world_from_camera: Isometry3<f64>,
        capture_time_nanos: u64,
        rgb: Vec<u8>,
    ) -> Self {
        Self {
            role: role.to_owned(),
            grid_offset,
            camera,
            capture_time_nanos,
            rgb,
            depth_m: None,
            surface_class: None,
            world_from_camera,
            true_world_from_camera: None,
            commanded_world_from_camera: None,
            joints: None,
            exposure_gain: 1.0,
        }
    }
}

/// One multiscopic view set: a reference view and its neighbours.
#[derive(Debug, Clone, PartialEq)]
pub struct CapturedSet {
    /// Index of the set in the log.
    pub index: u32,
    /// Name (scene and station, or the imported scene folder).
    pub name: String,
    /// Layout name (a [`rig::RigKind`] name, or `custom` for an imported set of other offsets).
    pub rig: String,
    /// Baseline between the reference and each direct neighbour (m).
    pub baseline_m: f64,
    /// Arm motion before and between the captures (empty for imports).
    pub motion: Vec<MotionSample>,
    /// The views, reference first.
    pub views: Vec<CapturedView>,
    /// The disparities to search, when the source knows them (an imported folder's
    /// `min_disparity`/`num_disparities`, a simulated converged rig's working range).
    pub disparity_range: Option<DisparityRange>,
}

/// A disparity search range (px, signed: a converged rig's far points have negative
/// disparities).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct DisparityRange {
    /// Smallest disparity searched.
    pub min_disparity: i32,
    /// Disparities searched; `None`: replay's default for the image width.
    pub num_disparities: Option<u32>,
}
