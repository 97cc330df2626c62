//! The options of `record` (a simulated capture) and the simulation they configure.

use std::path::PathBuf;

use clap::Args;
use record::ImageFormat;
use record::adaptive::AdaptiveConfig;
use record::capture::{ErrorInjection, SimulationConfig, ViewExposure, ViewPoseError};
use record::rig::RigKind;
use record::scene::SceneKind;

use crate::parse::{
    parse_exposure, parse_non_negative, parse_pose_error, parse_positive_m, parse_positive_mm, parse_resolution,
    parse_triple,
};

#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Watch the capture in the Rerun viewer: `spawn` (start a viewer), `save FILE.rrd`, or
    /// `connect [URL]` (default rerun+http://127.0.0.1:9876/proxy).
    #[arg(long, num_args = 1..=2, value_names = ["MODE", "ARG"])]
    pub(crate) rerun: Vec<String>,
    /// View layout: five-view (centre, left, right, top, bottom), three-view, stereo, grid3x3,
    /// line5 (five in a row at −2 … 2 baselines), grid-cross (the 3×3 grid plus the cross at two
    /// baselines: 13 views), or adaptive (the centre, then each next view
    /// where a plan from the depth so far says it resolves most; see --views).
    #[arg(long, value_enum, default_value = "five-view")]
    pub(crate) rig: RigKind,
    /// Adaptive rig: views per set, the centre included (2 … 9).
    #[arg(long, default_value = "5", value_parser = clap::value_parser!(u32).range(2..=9))]
    pub(crate) views: u32,
    /// Adaptive rig: the method run on the views so far to plan the next (MFuseNet plans left and
    /// right or top and bottom in pairs, which its networks take).
    #[arg(long, default_value = "mfusenet", value_name = "METHOD")]
    pub(crate) plan_method: String,
    /// Adaptive rig: longest candidate offset, in baselines (1: the direct neighbours' ring; 2
    /// lets it take twice the baseline where the disparities stay in the search).
    #[arg(long, default_value = "2", value_parser = clap::value_parser!(i32).range(1..=4))]
    pub(crate) plan_max_offset: i32,
    /// Adaptive rig: the widest disparity search (px) a candidate may need at its offset, table to
    /// tallest part (default: replay's default search, a fifteenth of the width rounded up to 16).
    #[arg(long, value_name = "PX")]
    pub(crate) plan_max_disparity: Option<f32>,
    /// Log the scene's working disparity range (table to tallest part, at the set's baseline)
    /// so that replay searches it (always for --converge-m and --rig adaptive).
    #[arg(long)]
    pub(crate) log_working_range: bool,
    /// Distance between the centre view and each direct neighbour (mm).
    #[arg(long, default_value = "20", value_parser = parse_positive_mm)]
    pub(crate) baseline_mm: f64,
    /// A converged rig: every view's principal point shifted so that a plane at this distance
    /// (m) has disparity 0 (nearer points positive, farther negative; the log carries the signed
    /// working range, which replay searches).
    #[arg(long, value_name = "DIST", value_parser = parse_positive_m)]
    pub(crate) converge_m: Option<f64>,
    /// Number of view sets, each from a different arm station.
    #[arg(long, default_value = "1", value_parser = clap::value_parser!(u32).range(1..=10_000))]
    pub(crate) captures: u32,
    /// Scene: toy (textured toys), workpiece (reflective metal part on a metal table), random (from the seed).
    #[arg(long, value_enum, default_value = "toy")]
    pub(crate) scene: SceneKind,
    /// Seed of the scene, stations, noise and errors.
    #[arg(long, default_value = "0")]
    pub(crate) seed: u64,
    /// Image size WIDTHxHEIGHT (the paper's IMX322: 1920x1080).
    #[arg(long, default_value = "1920x1080", value_parser = parse_resolution)]
    pub(crate) resolution: (u32, u32),
    /// Horizontal field of view (degrees).
    #[arg(long, default_value = "60", value_parser = clap::value_parser!(u32).range(5..=150))]
    pub(crate) fov_deg: u32,
    /// Image encoding in the log: raw (foxglove.RawImage rgb8) or png (foxglove.CompressedImage).
    #[arg(long, value_enum, default_value = "raw")]
    pub(crate) image_format: ImageFormat,
    /// Anti-aliasing samples per pixel (4 = rotated grid).
    #[arg(long, default_value = "4", value_parser = clap::value_parser!(u32).range(1..=64))]
    pub(crate) samples_per_pixel: u32,
    /// Sensor noise, standard deviation in 8-bit levels.
    #[arg(long, default_value = "1.0", value_parser = parse_non_negative)]
    pub(crate) noise_sigma: f64,
    /// Robot repeatability: radius of the random flange position error (mm; UR10: 0.1).
    #[arg(long, default_value = "0.1", value_parser = parse_non_negative)]
    pub(crate) repeatability_mm: f64,
    /// Inject a rotation into a view's commanded pose: ROLE:AXIS:DEG (axis z = roll). Repeatable.
    #[arg(long, value_parser = parse_pose_error, value_name = "ROLE:AXIS:DEG")]
    pub(crate) rotation_error: Vec<ViewPoseError>,
    /// Inject an offset into a view's commanded pose: ROLE:AXIS:MM (axis z = out of plane). Repeatable.
    #[arg(long, value_parser = parse_pose_error, value_name = "ROLE:AXIS:MM")]
    pub(crate) offset_error: Vec<ViewPoseError>,
    /// Hand-eye calibration error, translation X,Y,Z (mm, flange frame).
    #[arg(long, value_parser = parse_triple, value_name = "X,Y,Z", allow_hyphen_values = true)]
    pub(crate) hand_eye_error_mm: Option<[f64; 3]>,
    /// Hand-eye calibration error, rotation RX,RY,RZ (degrees).
    #[arg(long, value_parser = parse_triple, value_name = "RX,RY,RZ", allow_hyphen_values = true)]
    pub(crate) hand_eye_error_deg: Option<[f64; 3]>,
    /// Random exposure change per view: gain uniform in [1-J, 1+J].
    #[arg(long, default_value = "0", value_parser = parse_non_negative, value_name = "J")]
    pub(crate) exposure_jitter: f64,
    /// Force a view's exposure gain: ROLE:GAIN. Repeatable.
    #[arg(long, value_parser = parse_exposure, value_name = "ROLE:GAIN")]
    pub(crate) exposure: Vec<ViewExposure>,
    /// Output log (a ROS 2 bag directory with `--format ros2`, unless it ends in .mcap).
    #[arg(short, long, default_value = "capture.mcap")]
    pub(crate) output: PathBuf,
    /// Log format: mcap (our own log, Foxglove schemas) or ros2 (a ROS 2 bag: sensor_msgs, tf2,
    /// CDR; a directory NAME/ with NAME_0.mcap and metadata.yaml, for ros2 bag play, rviz, Foxglove).
    #[arg(long, value_enum, default_value = "mcap")]
    pub(crate) format: record::session::LogFormat,
    /// zstd level of the log's chunks (1 fastest … 19 smallest; 3 writes a 1080p set in twice
    /// the time, 12 % smaller).
    #[arg(long, default_value_t = record::log::DEFAULT_ZSTD_LEVEL, value_parser = clap::value_parser!(u32).range(1..=19))]
    pub(crate) zstd_level: u32,
    /// Do not write the viewer layout beside the log (`<log stem>.rbl`, opened with
    /// `rerun LOG.mcap LOG.rbl`).
    #[arg(long)]
    pub(crate) no_blueprint: bool,
}

/// The simulation the options ask for.
pub fn simulation_config(args: &SimulateArgs) -> SimulationConfig {
    SimulationConfig {
        rig: args.rig,
        baseline_mm: args.baseline_mm,
        captures: args.captures,
        scene: args.scene,
        seed: args.seed,
        width: args.resolution.0,
        height: args.resolution.1,
        horizontal_fov_deg: f64::from(args.fov_deg),
        image_format: args.image_format,
        samples_per_pixel: args.samples_per_pixel,
        noise_sigma_levels: args.noise_sigma,
        errors: ErrorInjection {
            repeatability_mm: args.repeatability_mm,
            rotation_deg: args.rotation_error.clone(),
            offset_mm: args.offset_error.clone(),
            hand_eye_translation_mm: args.hand_eye_error_mm.unwrap_or_default(),
            hand_eye_rotation_deg: args.hand_eye_error_deg.unwrap_or_default(),
            exposure_jitter: args.exposure_jitter,
            exposure: args.exposure.clone(),
        },
        converge_m: args.converge_m,
        log_working_range: args.log_working_range,
        adaptive: AdaptiveConfig {
            views: args.views,
            method: args.plan_method.clone(),
            max_offset: args.plan_max_offset,
            max_disparity_px: args.plan_max_disparity,
            ..AdaptiveConfig::default()
        },
        ..SimulationConfig::default()
    }
}
