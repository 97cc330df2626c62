//! Logs without capture events (foreign logs: images, calibrations and transforms from another
//! recorder, ROS 2 bags of a real arm translated by `crate::ros2`): view sets are inferred from
//! the camera's stream, the way a real capture looks. The camera may stream at 10–30 Hz while
//! the arm moves between stations:
//!
//! 1. each image's camera pose is the transform from the root of its TF tree (or `--base-frame`)
//!    to its `frame_id` at its own stamp (the acquisition time, not the log time), looked up the
//!    way tf2 does: each edge interpolated between its two samples around the stamp (lerp and
//!    slerp), an exact stamp taken as it is, never extrapolated; `/tf_static` edges hold at all
//!    times. An image with no transform at its stamp is left out and reported.
//! 2. an image is *moving* when the joint states nearest its stamp (within 60 ms) have a joint
//!    faster than 0.01 rad/s, or, without joint states near it, when its camera pose 50 ms
//!    before and after the stamp differs by more than 0.2 mm or 0.02°; moving images are left
//!    out.
//! 3. consecutive settled images whose poses stay within 0.5 mm and 0.05° of the first of them
//!    form a *station*; one frame of each station becomes its view ([`StationFrame`]: the middle
//!    one by default, or the first, the last, or the mean of them all).
//! 4. consecutive stations whose cameras keep one orientation and stay close to the first of them
//!    form a set; the medoid station is the reference; the baseline is the distance to its
//!    nearest neighbour; each view's grid offset is its position in the reference camera frame in
//!    baselines, which names its role.
//!
//! Images whose calibration has lens distortion (`plumb_bob`, `rational_polynomial`) are
//! undistorted to their K before matching; other distortion models are refused.

use std::collections::HashMap;

use foxglove::messages::{CameraCalibration, FrameTransforms, JointStates};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector2};
use record::camera::PinholeCamera;

use crate::ReplayError;
use crate::log::decode_rgb;
use crate::viewset::{View, ViewSet};

/// Schema of transforms.
pub const TRANSFORMS_SCHEMA: &str = "foxglove.FrameTransforms";
const RAW_IMAGE_SCHEMA: &str = "foxglove.RawImage";
const COMPRESSED_IMAGE_SCHEMA: &str = "foxglove.CompressedImage";
const CALIBRATION_SCHEMA: &str = "foxglove.CameraCalibration";
/// Largest orientation change within a set (deg).
const SET_ORIENTATION_TOLERANCE_DEG: f64 = 2.0;
/// A view belongs to the set while it stays within this many first-step distances of the first
/// view (a 3×3 grid spans 2√2 baselines from a corner).
const SET_RADIUS_IN_STEPS: f64 = 3.0;
/// Largest distance of a view from its grid position, in baselines.
const GRID_TOLERANCE: f64 = 0.25;
/// Encodings that are colour or grey images (not depth or masks).
const IMAGE_ENCODINGS: [&str; 6] = ["rgb8", "bgr8", "rgba8", "bgra8", "8UC3", "mono8"];
/// The frame the UR10's forward kinematics ends at (the DH flange frame, UR's `tool0`; UR's own
/// `flange` frame is rotated from it).
const FLANGE_FRAME: &str = "tool0";
/// The frame the forward kinematics starts from (the arm's base, as the UR controller's).
const FK_BASE_FRAME: &str = "base";
/// Two cameras stream at once when their images come within this of each other (ns).
const CONCURRENT_NANOS: u64 = 50_000_000;
/// A joint faster than this (rad/s) means the arm moves.
const MOVING_JOINT_RAD_PER_S: f64 = 0.01;
/// Joint states further than this from an image's stamp say nothing about it (ns).
const JOINT_STATE_REACH_NANOS: u64 = 60_000_000;
/// The camera pose is compared this long before and after an image's stamp (ns).
const MOTION_PROBE_NANOS: u64 = 50_000_000;
/// The camera moved between the probes when it moved further (m) or turned more (deg).
const MOVING_TRANSLATION_M: f64 = 0.0002;
const MOVING_ROTATION_DEG: f64 = 0.02;
/// A settled image belongs to the current station while it stays this close to its first image.
const STATION_TRANSLATION_M: f64 = 0.0005;
const STATION_ROTATION_DEG: f64 = 0.05;

/// The fields of a `foxglove.RawImage` that say what it is, decoded without its pixels (prost
/// skips the fields a message type does not name).
#[derive(Clone, PartialEq, prost::Message)]
struct RawImageHeader {
    #[prost(message, optional, tag = "1")]
    timestamp: Option<foxglove::messages::Timestamp>,
    #[prost(fixed32, tag = "2")]
    width: u32,
    #[prost(string, tag = "4")]
    encoding: String,
    #[prost(string, tag = "7")]
    frame_id: String,
}

/// The same of a `foxglove.CompressedImage`.
#[derive(Clone, PartialEq, prost::Message)]
struct CompressedImageHeader {
    #[prost(message, optional, tag = "1")]
    timestamp: Option<foxglove::messages::Timestamp>,
    #[prost(string, tag = "3")]
    format: String,
    #[prost(string, tag = "4")]
    frame_id: String,
}

/// A colour or grey image of the stream: its key, frame, stamp and whether it is grey.
#[derive(Debug, Clone)]
struct ImageEntry {
    key: (String, u64),
    frame_id: String,
    stamp: Option<u64>,
    grey: bool,
}

impl ImageEntry {
    /// What an image message is, when it is a colour or grey view (not depth, not a mask).
    fn of(key: (String, u64), data: &[u8]) -> Option<Self> {
        let (frame_id, stamp, grey) = match <RawImageHeader as prost::Message>::decode(data) {
            Ok(raw) if raw.width > 0 => {
                if !IMAGE_ENCODINGS.contains(&raw.encoding.as_str()) {
                    return None;
                }
                let grey = raw.encoding == "mono8";
                (raw.frame_id, raw.timestamp.map(|t| t.total_nanos()), grey)
            }
            _ => match <CompressedImageHeader as prost::Message>::decode(data) {
                Ok(c) if c.format.eq_ignore_ascii_case("png") => {
                    (c.frame_id, c.timestamp.map(|t| t.total_nanos()), false)
                }
                _ => return None,
            },
        };
        Some(Self {
            key,
            frame_id: frame_id.trim_start_matches('/').to_owned(),
            stamp: stamp.filter(|s| *s > 0),
            grey,
        })
    }
}

/// The `frame_id` of a `foxglove.RawImage` or `CompressedImage` (without decoding its pixels).
pub fn image_frame_id(data: &[u8]) -> Option<String> {
    let frame = match <RawImageHeader as prost::Message>::decode(data) {
        Ok(raw) if raw.width > 0 => raw.frame_id,
        _ => <CompressedImageHeader as prost::Message>::decode(data).ok()?.frame_id,
    };
    (!frame.is_empty()).then(|| frame.trim_start_matches('/').to_owned())
}

/// Which frame of a settled station becomes its view.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum StationFrame {
    /// The first settled frame.
    First,
    /// The middle one (the default: clear of the settling at the start and the next move).
    #[default]
    Middle,
    /// The last one.
    Last,
    /// The mean of every settled frame (less sensor noise).
    Mean,
}

/// How views are taken from a camera stream.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StreamOptions {
    /// Only the images of this topic (default: every colour or grey image topic).
    pub image_topic: Option<String>,
    /// The frame the camera poses are expressed in (default: the root of the camera's TF tree).
    pub base_frame: Option<String>,
    /// Which frame of a station becomes its view.
    pub station_frame: StationFrame,
}

/// Whether a schema is one foreign-log inference needs.
pub fn is_foreign_input(schema: &str) -> bool {
    matches!(
        schema,
        TRANSFORMS_SCHEMA
            | RAW_IMAGE_SCHEMA
            | COMPRESSED_IMAGE_SCHEMA
            | CALIBRATION_SCHEMA
            | crate::ros2::JOINT_STATES_SCHEMA
    )
}

/// Whether a schema is an image's (colour, grey, depth or mask).
pub fn is_image_schema(schema: &str) -> bool {
    matches!(schema, RAW_IMAGE_SCHEMA | COMPRESSED_IMAGE_SCHEMA)
}

/// Whether a schema carries poses, joints or calibrations (read whatever the time window: a
/// view's pose needs the transforms around it, and its calibration may have been sent once).
pub fn is_pose_source(schema: &str) -> bool {
    matches!(
        schema,
        TRANSFORMS_SCHEMA
            | crate::ros2::JOINT_STATES_SCHEMA
            | CALIBRATION_SCHEMA
            | "tf2_msgs/msg/TFMessage"
            | "sensor_msgs/msg/JointState"
            | "sensor_msgs/msg/CameraInfo"
    )
}

/// One edge of the transform tree: `parent_from_child` samples, or one static transform.
#[derive(Debug)]
struct Edge {
    /// (stamp, parent, parent_from_child), sorted by stamp once read.
    samples: Vec<(u64, String, Isometry3<f64>)>,
    /// Static (`/tf_static`): valid at all times (the latest static transform of the edge).
    fixed: Option<(String, Isometry3<f64>)>,
}

/// Why a camera pose cannot be had at a time.
#[derive(Debug, Clone, PartialEq)]
enum TfError {
    /// No transform names the frame.
    Unknown { frame: String },
    /// The time lies outside an edge's samples (tf2 never extrapolates).
    OutOfRange {
        parent: String,
        child: String,
        first: u64,
        last: u64,
    },
    /// The base frame is not above the frame.
    NotConnected { frame: String, base: String, root: String },
    /// The transforms above the frame loop (or climb past 64 frames).
    Cycle { frame: String },
}

impl std::fmt::Display for TfError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Unknown { frame } => write!(f, "no transform (on /tf or /tf_static) names the frame '{frame}'"),
            Self::OutOfRange {
                parent,
                child,
                first,
                last,
            } => write!(
                f,
                "the transform {parent} → {child} is known from {first} to {last} ns only (transforms are interpolated, never extrapolated)"
            ),
            Self::NotConnected { frame, base, root } => {
                write!(
                    f,
                    "'{base}' is not above '{frame}' in the transform tree (its root is '{root}')"
                )
            }
            Self::Cycle { frame } => write!(f, "the transforms above '{frame}' form a loop"),
        }
    }
}

/// A camera pose looked up.
#[derive(Debug, Clone)]
struct Lookup {
    root_from_frame: Isometry3<f64>,
    /// The widest gap between the two samples an edge was interpolated between (ns; 0: exact).
    gap_nanos: u64,
    /// The frame the pose is in (the tree's root, or the base asked for).
    root: String,
}

/// Time-stamped transforms, child → edge.
#[derive(Debug, Default)]
struct TfBuffer {
    edges: HashMap<String, Edge>,
    /// The first transform whose rotation is not one (reported when the poses are needed).
    invalid: Option<ReplayError>,
}

/// Norm below which a quaternion is not a rotation (the protobuf default is all zeros).
const MIN_QUATERNION_NORM: f64 = 1e-6;

impl TfBuffer {
    /// Adds the transforms of one message (static when its topic is `…tf_static`). A transform
    /// without a rotation field is a pure translation (identity rotation); a rotation that is zero
    /// or not finite is kept out and remembered as an error naming the topic and frames.
    fn add(&mut self, topic: &str, time: u64, message: &FrameTransforms) {
        let fixed = topic.ends_with("tf_static");
        for t in &message.transforms {
            let translation = t.translation.unwrap_or_default();
            let rotation = match t.rotation {
                None => UnitQuaternion::identity(),
                Some(q) => {
                    let quaternion = Quaternion::new(q.w, q.x, q.y, q.z);
                    let norm = quaternion.norm();
                    if !(norm.is_finite() && norm > MIN_QUATERNION_NORM) {
                        self.invalid.get_or_insert(ReplayError::BadTransform {
                            topic: topic.to_owned(),
                            parent_frame: t.parent_frame_id.clone(),
                            child_frame: t.child_frame_id.clone(),
                            log_time: time,
                            rotation_xyzw: [q.x, q.y, q.z, q.w],
                        });
                        continue;
                    }
                    UnitQuaternion::from_quaternion(quaternion)
                }
            };
            if ![translation.x, translation.y, translation.z]
                .iter()
                .all(|v| v.is_finite())
            {
                self.invalid.get_or_insert(ReplayError::BadField {
                    set: 0,
                    topic: topic.to_owned(),
                    field: "translation",
                    value: format!(
                        "{} → {} at log time {time}: ({}, {}, {})",
                        t.parent_frame_id, t.child_frame_id, translation.x, translation.y, translation.z
                    ),
                });
                continue;
            }
            let pose = Isometry3::from_parts(Translation3::new(translation.x, translation.y, translation.z), rotation);
            // tf2 takes frame ids without a leading '/'.
            let parent = t.parent_frame_id.trim_start_matches('/').to_owned();
            let child = t.child_frame_id.trim_start_matches('/').to_owned();
            let edge = self.edges.entry(child).or_insert_with(|| Edge {
                samples: Vec::new(),
                fixed: None,
            });
            if fixed {
                edge.fixed = Some((parent, pose));
            } else {
                let stamp = t.timestamp.map_or(time, |s| s.total_nanos());
                edge.samples.push((stamp, parent, pose));
            }
        }
    }

    fn sort(&mut self) {
        for edge in self.edges.values_mut() {
            edge.samples.sort_by_key(|s| s.0);
        }
    }

    /// `base_from_frame` at `time` (the root of the tree when `base` is `None`).
    fn lookup(&self, frame: &str, time: u64, base: Option<&str>) -> Result<Lookup, TfError> {
        let frame = frame.trim_start_matches('/');
        let mut pose = Isometry3::identity();
        let mut gap_nanos = 0;
        let mut child = frame.to_owned();
        if !self.edges.contains_key(frame) && base != Some(frame) {
            return Err(TfError::Unknown { frame: frame.into() });
        }
        for _ in 0..64 {
            if base == Some(child.as_str()) {
                return Ok(Lookup {
                    root_from_frame: pose,
                    gap_nanos,
                    root: child,
                });
            }
            let Some(edge) = self.edges.get(&child) else {
                return match base {
                    Some(base) => Err(TfError::NotConnected {
                        frame: frame.into(),
                        base: base.into(),
                        root: child,
                    }),
                    None => Ok(Lookup {
                        root_from_frame: pose,
                        gap_nanos,
                        root: child,
                    }),
                };
            };
            let (parent, parent_from_child) = match &edge.fixed {
                Some((parent, p)) => (parent.clone(), *p),
                None => {
                    let samples = &edge.samples;
                    let (Some(first), Some(last)) = (samples.first(), samples.last()) else {
                        return Err(TfError::Unknown { frame: child });
                    };
                    if time < first.0 || time > last.0 {
                        return Err(TfError::OutOfRange {
                            parent: first.1.clone(),
                            child,
                            first: first.0,
                            last: last.0,
                        });
                    }
                    let after = samples.partition_point(|s| s.0 < time);
                    let b = &samples[after.min(samples.len() - 1)];
                    if b.0 == time || after == 0 {
                        (b.1.clone(), b.2)
                    } else {
                        let a = &samples[after - 1];
                        let t = (time - a.0) as f64 / (b.0 - a.0) as f64;
                        let translation = a.2.translation.vector.lerp(&b.2.translation.vector, t);
                        let rotation = a.2.rotation.slerp(&b.2.rotation, t);
                        gap_nanos = gap_nanos.max(b.0 - a.0);
                        (a.1.clone(), Isometry3::from_parts(translation.into(), rotation))
                    }
                }
            };
            pose = parent_from_child * pose;
            child = parent;
        }
        Err(TfError::Cycle { frame: frame.into() })
    }
}

/// What the stream inference found and used, for `replay info` and the run's report.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct StreamReport {
    /// Image topics and how many colour or grey images each had.
    pub image_topics: Vec<(String, usize)>,
    /// The camera frames the images named.
    pub camera_frames: Vec<String>,
    /// The frame poses are expressed in.
    pub base_frame: Option<String>,
    /// Images with a pose, and of them those taken while the arm moved.
    pub images_with_pose: usize,
    /// Images taken while the arm moved (left out).
    pub moving_images: usize,
    /// Images left out for want of a transform at their stamp, with the first reason.
    pub images_without_pose: usize,
    /// Why the first image without a pose has none.
    pub first_missing_pose: Option<String>,
    /// Settled stations: (first stamp, last stamp, frames, the chosen frame's widest
    /// interpolation gap in ns).
    pub stations: Vec<(u64, u64, usize, u64)>,
    /// Which frame of each station was used.
    pub station_frame: StationFrame,
    /// Joint-state messages read.
    pub joint_states: usize,
}

/// What a scan keeps for inference.
#[derive(Debug, Default)]
pub struct ForeignMessages {
    images: Vec<ImageEntry>,
    /// Image messages seen (views or not): whether the log has images at all.
    image_messages: usize,
    calibrations: Vec<(String, u64)>,
    /// (stamp, largest |joint velocity|), when the message had velocities.
    joint_speeds: Vec<(u64, f64)>,
    /// (stamp, the UR's six joint positions in its order), when the message named all six.
    joint_positions: Vec<(u64, [f64; 6])>,
    joint_states: usize,
    tf: TfBuffer,
}

impl ForeignMessages {
    /// Takes one message; returns whether its payload should be kept.
    pub fn add(&mut self, topic: &str, schema: &str, time: u64, data: &[u8]) -> bool {
        match schema {
            TRANSFORMS_SCHEMA => {
                if let Ok(message) = <FrameTransforms as prost::Message>::decode(data) {
                    self.tf.add(topic, time, &message);
                }
                false
            }
            crate::ros2::JOINT_STATES_SCHEMA => {
                if let Ok(message) = <JointStates as prost::Message>::decode(data) {
                    self.joint_states += 1;
                    let stamp = message.timestamp.map_or(time, |s| s.total_nanos());
                    // By name (a tf_prefix allowed), never by place: drivers publish them in any order.
                    let position = |name: &str| {
                        message
                            .joints
                            .iter()
                            .find(|j| j.name.ends_with(name))
                            .and_then(|j| j.position)
                    };
                    let positions: Vec<f64> = record::ur10::JOINT_NAMES.iter().filter_map(|n| position(n)).collect();
                    if let Ok(positions) = <[f64; 6]>::try_from(positions) {
                        self.joint_positions.push((stamp, positions));
                    }
                    let speeds: Vec<f64> = message.joints.iter().filter_map(|j| j.velocity).collect();
                    if !speeds.is_empty() {
                        self.joint_speeds
                            .push((stamp, speeds.iter().fold(0.0f64, |m, v| m.max(v.abs()))));
                    }
                }
                false
            }
            RAW_IMAGE_SCHEMA | COMPRESSED_IMAGE_SCHEMA => {
                self.image_messages += 1;
                self.images.extend(ImageEntry::of((topic.to_owned(), time), data));
                true
            }
            CALIBRATION_SCHEMA => {
                self.calibrations.push((topic.to_owned(), time));
                true
            }
            _ => true,
        }
    }

    /// Whether the log had any image.
    pub fn has_images(&self) -> bool {
        self.image_messages > 0
    }

    /// The arm's joints at `stamp`, interpolated between the two joint states around it (never
    /// extrapolated).
    fn joints_at(&self, stamp: u64) -> Option<([f64; 6], u64)> {
        let samples = &self.joint_positions;
        let after = samples.partition_point(|s| s.0 < stamp);
        let b = samples.get(after)?;
        if b.0 == stamp {
            return Some((b.1, 0));
        }
        let a = samples.get(after.checked_sub(1)?)?;
        let t = (stamp - a.0) as f64 / (b.0 - a.0) as f64;
        Some((std::array::from_fn(|i| a.1[i] + (b.1[i] - a.1[i]) * t), b.0 - a.0))
    }

    /// `base_from_frame` at `stamp` (the tree's root when `base` is `None`) from the transforms;
    /// where the tree stops at the arm's flange (`flange`, `tool0`: a bag without the arm's
    /// `/tf`), the UR10's forward kinematics of `/joint_states` at the stamp carries it on to the
    /// arm's `base`, and the transforms above `base` (if any) beyond.
    fn pose(&self, frame: &str, stamp: u64, base: Option<&str>) -> Result<Lookup, TfError> {
        let direct = self.tf.lookup(frame, stamp, base);
        let root = match &direct {
            Ok(lookup) if base.is_none() => lookup.root.clone(),
            Err(TfError::NotConnected { root, .. }) => root.clone(),
            _ => return direct,
        };
        if root != FLANGE_FRAME || self.joint_positions.is_empty() {
            return direct;
        }
        let below = self.tf.lookup(frame, stamp, Some(&root))?;
        let (Some(first), Some(last)) = (self.joint_positions.first(), self.joint_positions.last()) else {
            return direct;
        };
        let (joints, joint_gap) = self.joints_at(stamp).ok_or_else(|| TfError::OutOfRange {
            parent: format!("{FK_BASE_FRAME} (forward kinematics of /joint_states)"),
            child: root.clone(),
            first: first.0,
            last: last.0,
        })?;
        let base_from_flange = record::ur10::Ur10::default().forward_kinematics(&joints);
        let above = match self.tf.lookup(FK_BASE_FRAME, stamp, base) {
            Ok(above) => above,
            Err(TfError::Unknown { .. }) if base.is_none() || base == Some(FK_BASE_FRAME) => Lookup {
                root_from_frame: Isometry3::identity(),
                gap_nanos: 0,
                root: FK_BASE_FRAME.into(),
            },
            Err(error) => return Err(error),
        };
        Ok(Lookup {
            root_from_frame: above.root_from_frame * base_from_flange * below.root_from_frame,
            gap_nanos: below.gap_nanos.max(above.gap_nanos).max(joint_gap),
            root: above.root,
        })
    }

    /// Whether the arm moved at `stamp`: the joint states when there are some near it (the
    /// arm's own 125–500 Hz measurement), else the transforms around it; `None` when neither says.
    fn moving(&self, frame: &str, stamp: u64, base: Option<&str>) -> Option<bool> {
        let by_joints = {
            let after = self.joint_speeds.partition_point(|s| s.0 < stamp);
            [after.checked_sub(1), Some(after)]
                .into_iter()
                .flatten()
                .filter_map(|i| self.joint_speeds.get(i))
                .filter(|s| s.0.abs_diff(stamp) <= JOINT_STATE_REACH_NANOS)
                .min_by_key(|s| s.0.abs_diff(stamp))
                .map(|s| s.1 > MOVING_JOINT_RAD_PER_S)
        };
        if by_joints.is_some() {
            return by_joints;
        }
        match (
            self.pose(frame, stamp.saturating_sub(MOTION_PROBE_NANOS), base),
            self.pose(frame, stamp.saturating_add(MOTION_PROBE_NANOS), base),
        ) {
            (Ok(before), Ok(after)) => {
                let (a, b) = (before.root_from_frame, after.root_from_frame);
                let moved = (a.translation.vector - b.translation.vector).norm();
                let turned = a.rotation.angle_to(&b.rotation).to_degrees();
                Some(moved > MOVING_TRANSLATION_M || turned > MOVING_ROTATION_DEG)
            }
            _ => None,
        }
    }

    /// Infers the view sets.
    pub fn infer_sets(
        self,
        payloads: &HashMap<(String, u64), Vec<u8>>,
    ) -> Result<(Vec<ViewSet>, StreamReport), ReplayError> {
        self.infer_sets_with(payloads, &StreamOptions::default())
    }

    /// Infers the view sets with the stream options given.
    pub fn infer_sets_with(
        self,
        payloads: &HashMap<(String, u64), Vec<u8>>,
        options: &StreamOptions,
    ) -> Result<(Vec<ViewSet>, StreamReport), ReplayError> {
        let plan = self.plan(options)?;
        plan.build(payloads)
    }

    /// The stations of the stream and the frames that make their views, from the image headers,
    /// transforms and joints alone (no pixels): [`StreamPlan::needed`] names the payloads that
    /// [`StreamPlan::build`] then decodes.
    pub fn plan(mut self, options: &StreamOptions) -> Result<StreamPlan, ReplayError> {
        if let Some(error) = self.tf.invalid.take() {
            return Err(error);
        }
        self.tf.sort();
        self.joint_speeds.sort_by_key(|s| s.0);
        self.joint_positions.sort_by_key(|s| s.0);
        let base = options.base_frame.as_deref();
        let mut report = StreamReport {
            base_frame: options.base_frame.clone(),
            station_frame: options.station_frame,
            joint_states: self.joint_states,
            ..StreamReport::default()
        };
        // Colour/grey images: (stamp, frame, key); one per (frame, stamp), preferring colour.
        let mut frames: Vec<Frame> = Vec::new();
        for image in &self.images {
            let key = &image.key;
            if options.image_topic.as_ref().is_some_and(|t| *t != key.0) {
                continue;
            }
            let frame_id = image.frame_id.clone();
            let stamp = image.stamp.unwrap_or(key.1);
            let grey = image.grey;
            match report.image_topics.iter_mut().find(|(t, _)| *t == key.0) {
                Some((_, count)) => *count += 1,
                None => report.image_topics.push((key.0.clone(), 1)),
            }
            if !report.camera_frames.contains(&frame_id) {
                report.camera_frames.push(frame_id.clone());
            }
            frames.push(Frame {
                key: key.clone(),
                stamp,
                frame_id,
                grey,
                lookup: None,
                moving: false,
            });
        }
        // One camera: where several cameras stream at once (a RealSense's colour and infrared:
        // most of one's images have one of the other's within 50 ms), the one with the most
        // colour images (then the most images); `--image-topic` picks another. Frames that do
        // not stream at once (a log with one fixed frame per view) all stay.
        if report.camera_frames.len() > 1 {
            let score = |frame: &str| {
                let of = frames.iter().filter(|f| f.frame_id == frame);
                (
                    of.clone().filter(|f| !f.grey).count(),
                    of.count(),
                    std::cmp::Reverse(frame.to_owned()),
                )
            };
            if let Some(best) = report.camera_frames.iter().max_by_key(|f| score(f)).cloned() {
                let mut best_stamps: Vec<u64> = frames.iter().filter(|f| f.frame_id == best).map(|f| f.stamp).collect();
                best_stamps.sort_unstable();
                let near_best = |stamp: u64| {
                    let after = best_stamps.partition_point(|s| *s < stamp);
                    [after.checked_sub(1), Some(after)]
                        .into_iter()
                        .flatten()
                        .filter_map(|i| best_stamps.get(i))
                        .any(|s| s.abs_diff(stamp) <= CONCURRENT_NANOS)
                };
                let concurrent = |frame: &str| {
                    let stamps: Vec<u64> = frames.iter().filter(|f| f.frame_id == frame).map(|f| f.stamp).collect();
                    2 * stamps.iter().filter(|s| near_best(**s)).count() >= stamps.len()
                };
                let dropped: Vec<String> = report
                    .camera_frames
                    .iter()
                    .filter(|f| **f != best && concurrent(f))
                    .cloned()
                    .collect();
                frames.retain(|f| !dropped.contains(&f.frame_id));
                report.camera_frames.retain(|f| !dropped.contains(f));
                report
                    .image_topics
                    .retain(|(t, _)| frames.iter().any(|f| f.key.0 == *t));
            }
        }
        // Colour before grey at one stamp: of a camera seen twice at once, the colour view is kept.
        frames.sort_by(|a, b| (a.stamp, a.grey, &a.key.0).cmp(&(b.stamp, b.grey, &b.key.0)));
        // Poses and motion.
        let mut first_error = None;
        for frame in &mut frames {
            match self.pose(&frame.frame_id, frame.stamp, base) {
                Ok(lookup) => {
                    frame.lookup = Some(lookup);
                    frame.moving = self.moving(&frame.frame_id, frame.stamp, base).unwrap_or(false);
                    report.images_with_pose += 1;
                    report.moving_images += usize::from(frame.moving);
                }
                Err(error) => {
                    report.images_without_pose += 1;
                    first_error.get_or_insert_with(|| error.to_string());
                    report.first_missing_pose.get_or_insert_with(|| {
                        format!(
                            "{} image at stamp {} ns in frame '{}': {error}",
                            frame.key.0, frame.stamp, frame.frame_id
                        )
                    });
                }
            }
        }
        if report.images_with_pose == 0
            && let Some(first) = frames.first()
        {
            let reason = first_error.unwrap_or_default();
            return Err(ReplayError::NoPose {
                topic: first.key.0.clone(),
                frame: first.frame_id.clone(),
                stamp_nanos: first.stamp,
                reason,
            });
        }
        // Stations: runs of settled frames that stay put; a moving frame ends a run.
        let mut stations: Vec<Vec<Frame>> = Vec::new();
        let mut open = false;
        for frame in &frames {
            let Some(lookup) = &frame.lookup else { continue };
            if frame.moving {
                open = false;
                continue;
            }
            let joins = open
                && stations.last().and_then(|s| s.first()).is_some_and(|first| {
                    let a = first
                        .lookup
                        .as_ref()
                        .map_or(lookup.root_from_frame, |l| l.root_from_frame);
                    let b = lookup.root_from_frame;
                    first.frame_id == frame.frame_id
                        && (a.translation.vector - b.translation.vector).norm() <= STATION_TRANSLATION_M
                        && a.rotation.angle_to(&b.rotation).to_degrees() <= STATION_ROTATION_DEG
                });
            // The same camera seen twice at one stamp (a colour and a grey stream): keep one.
            if let Some(last) = stations.last_mut().and_then(|s| s.last_mut())
                && last.stamp == frame.stamp
                && last.frame_id == frame.frame_id
            {
                continue;
            }
            if joins {
                if let Some(station) = stations.last_mut() {
                    station.push(frame.clone());
                }
            } else {
                stations.push(vec![frame.clone()]);
            }
            open = true;
        }
        let calibrations = self.calibrations;
        Ok(StreamPlan {
            stations,
            calibrations,
            options: options.clone(),
            report,
        })
    }
}

/// The stations of a camera stream and the frames of each that make its view.
#[derive(Debug)]
pub struct StreamPlan {
    stations: Vec<Vec<Frame>>,
    calibrations: Vec<(String, u64)>,
    options: StreamOptions,
    report: StreamReport,
}

impl StreamPlan {
    /// The messages whose payloads [`StreamPlan::build`] reads: every calibration, and the
    /// frames that make the views (every frame of a station for `--station-frame mean`).
    pub fn needed(&self) -> Vec<(String, u64)> {
        let mut keys = self.calibrations.clone();
        for station in &self.stations {
            if self.options.station_frame == StationFrame::Mean {
                keys.extend(station.iter().map(|f| f.key.clone()));
            } else {
                keys.push(self.chosen(station).key.clone());
            }
        }
        keys
    }

    fn chosen<'a>(&self, station: &'a [Frame]) -> &'a Frame {
        match self.options.station_frame {
            StationFrame::First => &station[0],
            StationFrame::Last => &station[station.len() - 1],
            StationFrame::Middle | StationFrame::Mean => &station[(station.len() - 1) / 2],
        }
    }

    /// Decodes the views of the stations and groups them into sets.
    pub fn build(
        self,
        payloads: &HashMap<(String, u64), Vec<u8>>,
    ) -> Result<(Vec<ViewSet>, StreamReport), ReplayError> {
        let mut report = self.report.clone();
        let (stations, options) = (&self.stations, &self.options);
        let payload = |key: &(String, u64)| payloads.get(key).map(Vec::as_slice).unwrap_or_default();
        // Calibrations by frame id, in time: an image takes the latest one at or before its
        // stamp (else the first after it), so a camera reconfigured mid-capture keeps each
        // image with its own.
        let mut calibrations: HashMap<String, Vec<(u64, CameraCalibration)>> = HashMap::new();
        for key in &self.calibrations {
            if let Ok(c) = <CameraCalibration as prost::Message>::decode(payload(key)) {
                let stamp = c.timestamp.map_or(key.1, |t| t.total_nanos());
                calibrations
                    .entry(c.frame_id.trim_start_matches('/').to_owned())
                    .or_default()
                    .push((stamp, c));
            }
        }
        for list in calibrations.values_mut() {
            list.sort_by_key(|(stamp, _)| *stamp);
        }
        let calibration_at = |frame: &str, stamp: u64| {
            let list = calibrations.get(frame)?;
            let after = list.partition_point(|(s, _)| *s <= stamp);
            list.get(after.saturating_sub(1)).map(|(_, c)| c)
        };
        // One view per station.
        let mut views: Vec<View> = Vec::with_capacity(stations.len());
        for station in stations {
            let chosen = self.chosen(station);
            let Some(lookup) = &chosen.lookup else { continue };
            report.stations.push((
                station[0].stamp,
                station[station.len() - 1].stamp,
                station.len(),
                lookup.gap_nanos,
            ));
            let calibration = calibration_at(&chosen.frame_id, chosen.stamp).ok_or_else(|| ReplayError::BadField {
                set: 0,
                topic: chosen.key.0.clone(),
                field: "frame_id",
                value: format!(
                    "'{}' has no camera calibration in the log (sensor_msgs/msg/CameraInfo or foxglove.CameraCalibration with that frame_id)",
                    chosen.frame_id
                ),
            })?;
            let (width, height, mut rgb) = decode_rgb(0, &chosen.key.0, payload(&chosen.key))?;
            if options.station_frame == StationFrame::Mean && station.len() > 1 {
                let mut sum: Vec<u32> = rgb.iter().map(|v| u32::from(*v)).collect();
                let mut count = 1;
                for other in station.iter().filter(|f| f.key != chosen.key) {
                    let (w, h, more) = decode_rgb(0, &other.key.0, payload(&other.key))?;
                    if (w, h) == (width, height) {
                        sum.iter_mut().zip(&more).for_each(|(s, v)| *s += u32::from(*v));
                        count += 1;
                    }
                }
                rgb = sum.iter().map(|s| ((s + count / 2) / count) as u8).collect();
            }
            let camera = camera_of(calibration, width, height, &chosen.key.0)?;
            let rgb =
                crate::undistort::undistort(calibration, &camera, &rgb).map_err(|reason| ReplayError::BadField {
                    set: 0,
                    topic: chosen.key.0.clone(),
                    field: "distortion_model",
                    value: reason,
                })?;
            views.push(View {
                role: String::new(),
                offset: [0, 0],
                camera,
                rgb,
                world_from_camera: lookup.root_from_frame,
                true_world_from_camera: None,
                // The acquisition time: results written beside the log are stamped with it.
                capture_time_nanos: chosen.stamp,
                joints: None,
                frame_id: chosen.frame_id.clone(),
            });
        }
        let mut sets = Vec::new();
        let mut start = 0;
        while start < views.len() {
            let first = &views[start];
            let mut end = start + 1;
            let step = views.get(start + 1).map_or(0.0, |v| {
                (v.world_from_camera.translation.vector - first.world_from_camera.translation.vector).norm()
            });
            while end < views.len() && end - start < 9 {
                let v = &views[end];
                let distance =
                    (v.world_from_camera.translation.vector - first.world_from_camera.translation.vector).norm();
                let turned = v
                    .world_from_camera
                    .rotation
                    .angle_to(&first.world_from_camera.rotation)
                    .to_degrees();
                if step <= 0.0 || distance > SET_RADIUS_IN_STEPS * step || turned > SET_ORIENTATION_TOLERANCE_DEG {
                    break;
                }
                end += 1;
            }
            if end - start >= 2 {
                sets.push(assemble(sets.len() as u32, views[start..end].to_vec())?);
            }
            start = end;
        }
        Ok((sets, report))
    }
}

/// One image of the stream.
#[derive(Debug, Clone)]
struct Frame {
    key: (String, u64),
    stamp: u64,
    frame_id: String,
    /// A grey (mono8) image: a colour one of the same camera and stamp is preferred.
    grey: bool,
    lookup: Option<Lookup>,
    moving: bool,
}

/// The pinhole camera of a calibration for an image of `width × height`.
fn camera_of(
    calibration: &CameraCalibration,
    width: u32,
    height: u32,
    topic: &str,
) -> Result<PinholeCamera, ReplayError> {
    let k = &calibration.k;
    if k.len() != 9 || !(k[0].is_finite() && k[0] > 0.0 && k[4].is_finite() && k[4] > 0.0) {
        return Err(ReplayError::BadField {
            set: 0,
            topic: topic.to_owned(),
            field: "k",
            value: format!("{k:?} (the calibration of frame '{}')", calibration.frame_id),
        });
    }
    if (calibration.width, calibration.height) != (0, 0) && (calibration.width, calibration.height) != (width, height) {
        return Err(ReplayError::BadField {
            set: 0,
            topic: topic.to_owned(),
            field: "width/height",
            value: format!(
                "the image is {width}x{height}, its calibration (frame '{}') is for {}x{}",
                calibration.frame_id, calibration.width, calibration.height
            ),
        });
    }
    Ok(PinholeCamera {
        width,
        height,
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
    })
}

fn assemble(index: u32, mut views: Vec<View>) -> Result<ViewSet, ReplayError> {
    // The medoid is the reference.
    let centre_index = (0..views.len())
        .min_by(|a, b| {
            let cost = |i: usize| -> f64 {
                views
                    .iter()
                    .map(|v| {
                        (v.world_from_camera.translation.vector - views[i].world_from_camera.translation.vector).norm()
                    })
                    .sum()
            };
            cost(*a).total_cmp(&cost(*b))
        })
        .unwrap_or(0);
    let mut reference = views.remove(centre_index);
    let inverse = reference.world_from_camera.inverse();
    let relative: Vec<Vector2<f64>> = views
        .iter()
        .map(|v| (inverse * v.world_from_camera).translation.vector.xy())
        .collect();
    let baseline = relative.iter().map(|r| r.norm()).fold(f64::INFINITY, f64::min);
    if !(baseline.is_finite() && baseline > 0.0) {
        return Err(ReplayError::BadField {
            set: index,
            topic: "/tf".into(),
            field: "camera poses",
            value: "the views of the set do not move in the image plane (zero baseline)".into(),
        });
    }
    reference.role = "center".into();
    let mut neighbours = Vec::new();
    for (mut view, r) in views.into_iter().zip(relative) {
        let grid = r / baseline;
        let offset = [grid.x.round() as i32, grid.y.round() as i32];
        if (grid - Vector2::new(f64::from(offset[0]), f64::from(offset[1]))).norm() > GRID_TOLERANCE || offset == [0, 0]
        {
            continue;
        }
        view.offset = offset;
        view.role = record::rig::role_for_offset(offset);
        if neighbours.iter().any(|n: &View| n.offset == offset) {
            continue;
        }
        if (view.camera.width, view.camera.height) != (reference.camera.width, reference.camera.height) {
            return Err(ReplayError::SizeMismatch {
                set: index,
                role: view.role,
                topic: format!(
                    "the image in frame '{}' at stamp {} ns",
                    view.frame_id, view.capture_time_nanos
                ),
                width: view.camera.width,
                height: view.camera.height,
                reference_width: reference.camera.width,
                reference_height: reference.camera.height,
            });
        }
        neighbours.push(view);
    }
    let rig = match neighbours.len() {
        1 => "stereo",
        2 => "three-view",
        4 => "five-view",
        8 => "grid3x3",
        _ => "inferred",
    };
    Ok(ViewSet {
        index,
        name: format!("inferred-{index}"),
        rig: rig.into(),
        baseline_m: baseline,
        reference,
        neighbours,
        ground_truth_depth_m: None,
        surface_class: None,
        disparity_range: None,
    })
}

#[cfg(test)]
mod tests {
    use foxglove::messages::{FrameTransform, Quaternion as QuaternionMessage, Vector3};

    use super::*;

    fn transform(child: &str, rotation: Option<QuaternionMessage>) -> FrameTransforms {
        FrameTransforms {
            transforms: vec![FrameTransform {
                timestamp: None,
                parent_frame_id: "world".into(),
                child_frame_id: child.into(),
                translation: Some(Vector3 { x: 0.1, y: 0.0, z: 0.5 }),
                rotation,
            }],
        }
    }

    #[test]
    fn a_missing_rotation_is_identity_and_a_zero_quaternion_is_an_error() {
        let mut tf = TfBuffer::default();
        tf.add("/tf", 10, &transform("camera", None));
        tf.sort();
        let pose = tf
            .lookup("camera", 10, None)
            .unwrap_or_else(|e| panic!("{e}"))
            .root_from_frame;
        assert_eq!(pose.rotation, UnitQuaternion::identity());
        assert!((pose.translation.vector - nalgebra::Vector3::new(0.1, 0.0, 0.5)).norm() < 1e-12);
        assert!(tf.invalid.is_none());

        let zero = QuaternionMessage {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 0.0,
        };
        let mut messages = ForeignMessages::default();
        let bytes = prost::Message::encode_to_vec(&transform("camera_left", Some(zero)));
        messages.add("/tf", TRANSFORMS_SCHEMA, 20, &bytes);
        let error = match messages.infer_sets(&HashMap::new()) {
            Err(e) => e.to_string(),
            Ok((sets, _)) => panic!("a zero quaternion was accepted ({} sets)", sets.len()),
        };
        assert!(
            error.contains("/tf") && error.contains("world → camera_left") && error.contains("not a rotation"),
            "{error}"
        );
    }

    fn sampled(child: &str, samples: &[(u64, f64)]) -> TfBuffer {
        let mut tf = TfBuffer::default();
        for (time, x) in samples {
            let message = FrameTransforms {
                transforms: vec![FrameTransform {
                    timestamp: Some(foxglove::messages::Timestamp::new(0, *time as u32)),
                    parent_frame_id: "base_link".into(),
                    child_frame_id: child.into(),
                    translation: Some(Vector3 { x: *x, y: 0.0, z: 0.0 }),
                    rotation: None,
                }],
            };
            tf.add("/tf", *time, &message);
        }
        tf.sort();
        tf
    }

    #[test]
    fn transforms_interpolate_between_samples_and_never_extrapolate() {
        let mut tf = sampled("tool0", &[(100, 0.0), (200, 1.0)]);
        let at = |tf: &TfBuffer, frame: &str, time| tf.lookup(frame, time, None);
        let mid = at(&tf, "tool0", 150).unwrap_or_else(|e| panic!("{e}"));
        assert!((mid.root_from_frame.translation.x - 0.5).abs() < 1e-12);
        assert_eq!(mid.gap_nanos, 100);
        assert_eq!(
            at(&tf, "tool0", 200).map(|l| l.gap_nanos),
            Ok(0).map_err(|e: TfError| e)
        );
        let error = at(&tf, "tool0", 201).map(|_| ()).unwrap_err().to_string();
        assert!(
            error.contains("base_link → tool0") && error.contains("from 100 to 200"),
            "{error}"
        );
        // A static edge below holds at every time; the dynamic one above still bounds the time.
        let hand_eye = FrameTransforms {
            transforms: vec![FrameTransform {
                timestamp: Some(foxglove::messages::Timestamp::new(0, 0)),
                parent_frame_id: "tool0".into(),
                child_frame_id: "/camera_optical".into(),
                translation: Some(Vector3 { x: 0.0, y: 0.0, z: 0.1 }),
                rotation: None,
            }],
        };
        tf.add("/tf_static", 0, &hand_eye);
        tf.sort();
        let pose = at(&tf, "camera_optical", 150)
            .unwrap_or_else(|e| panic!("{e}"))
            .root_from_frame;
        assert!((pose.translation.vector - nalgebra::Vector3::new(0.5, 0.0, 0.1)).norm() < 1e-12);
        assert!(at(&tf, "camera_optical", 250).is_err());
        assert!(matches!(at(&tf, "elsewhere", 150), Err(TfError::Unknown { .. })));
        // Transforms that loop are an error, not a pose.
        let mut looped = sampled("a", &[(100, 0.0)]);
        let back = FrameTransforms {
            transforms: vec![FrameTransform {
                timestamp: Some(foxglove::messages::Timestamp::new(0, 100)),
                parent_frame_id: "a".into(),
                child_frame_id: "base_link".into(),
                translation: None,
                rotation: None,
            }],
        };
        looped.add("/tf", 100, &back);
        looped.sort();
        assert!(matches!(at(&looped, "a", 100), Err(TfError::Cycle { .. })));
        let error = tf
            .lookup("camera_optical", 150, Some("world"))
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("'world' is not above 'camera_optical'") && error.contains("root is 'base_link'"),
            "{error}"
        );
    }
}
