//! The log format (the contract `replay` reads) and its writer.
//!
//! Every topic is documented in ARCHITECTURE.md. Foxglove protobuf schemas are used wherever one
//! exists; the capture events are JSON with a JSON schema. Chunks are zstd-compressed, with
//! message and chunk indexes, statistics and CRCs; [`LogWriter::finish`] writes the summary.
//! Every set ends its chunk and is flushed; [`OutputFile`] makes files appear only when complete
//! (temporary name, then rename) and its [`SyncedWriter`] syncs each set to the disk, so a crash
//! or a power cut loses only the set in flight (`replay recover` finishes the temporary file).

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::{Path, PathBuf};

use bytes::Bytes;
use foxglove::Encode;
use foxglove::messages::{
    CameraCalibration, CompressedImage, FrameTransform, FrameTransforms, JointState, JointStates, Pose, PoseInFrame,
    Quaternion, RawImage, Timestamp, Vector3,
};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::ur10::{JOINT_COUNT, JOINT_NAMES, LINK_FRAME_NAMES, Ur10};
use crate::{CapturedSet, CapturedView, ImageFormat};

/// Root frame of every log: the robot base (z up, table top at z = 0).
pub const WORLD_FRAME: &str = "world";
/// Frame of the UR10 base (identical to `world` in simulated logs).
pub const BASE_FRAME: &str = "base";
/// The camera's optical frame (x right, y down, z forward).
pub const CAMERA_FRAME: &str = "camera";

/// The frame of one view (`camera_<role>`): where the camera was when it took that view, fixed
/// in the world; the view's images, ground truth and calibration carry it as `frame_id`.
pub fn view_frame(role: &str) -> String {
    format!("{CAMERA_FRAME}_{role}")
}
/// All transforms (`foxglove.FrameTransforms`).
pub const TF_TOPIC: &str = "/tf";
/// Joint positions and velocities (`foxglove.JointStates`).
pub const JOINT_STATES_TOPIC: &str = "/arm/joint_states";
/// The camera pose the planner commanded for each capture (`foxglove.PoseInFrame`, in `world`).
pub const COMMANDED_POSE_TOPIC: &str = "/arm/commanded_camera_pose";
/// Which image is which view of which set (JSON, [`CaptureEvent`]).
pub const CAPTURE_EVENTS_TOPIC: &str = "/capture/events";
/// Schema name of [`CaptureEvent`].
pub const CAPTURE_EVENT_SCHEMA: &str = "multiscopic.CaptureEvent";
/// Each plan of an adaptive set: candidates, scores, poses, the choice (JSON,
/// [`crate::adaptive::PlanStep`]), at the time it was made.
pub const CAPTURE_PLAN_TOPIC: &str = "/capture/plan";
/// Schema name of [`crate::adaptive::PlanStep`].
pub const CAPTURE_PLAN_SCHEMA: &str = "multiscopic.CapturePlan";
/// Metadata record name holding the effective configuration.
pub const METADATA_NAME: &str = "multiscopic.recording";
/// Encoding of `surface` ground-truth images; values are [`crate::scene::SurfaceClass`].
pub const SURFACE_ENCODING: &str = "mono8";
/// Encoding of depth ground truth: metres along the optical axis, 0 = unknown.
pub const DEPTH_ENCODING: &str = "32FC1";
/// Default chunk size (bytes before compression). A chunk ends after the message that takes it
/// past this size, so with each view written as calibration, image, surface classes, depth, a
/// 1080p view's image (6.2 MB) ends one chunk and its ground truth (10.4 MB) another: a reader
/// that skips the neighbours' ground truth decompresses half of a simulated set's bytes. Sets
/// under this size (320×240 five-view) stay one chunk each.
pub const DEFAULT_CHUNK_SIZE: u64 = 4 * 1024 * 1024;
/// Default zstd level: the fastest. A five-view 1080p set (83 MB of images and ground truth)
/// is written in 0.16–0.19 s at level 1 against 0.39–0.40 s at level 3, for a log 13 % larger
/// (30.3 against 26.7 MB); the images' sensor noise leaves little for a slower level to find.
pub const DEFAULT_ZSTD_LEVEL: u32 = 1;

/// Image topic of a view role.
pub fn image_topic(role: &str) -> String {
    format!("/camera/{role}/image")
}
/// Calibration topic of a view role.
pub fn calibration_topic(role: &str) -> String {
    format!("/camera/{role}/calibration")
}
/// Ground-truth depth topic of a view role.
pub fn depth_topic(role: &str) -> String {
    format!("/camera/{role}/ground_truth/depth")
}
/// Ground-truth surface-class topic of a view role.
pub fn surface_topic(role: &str) -> String {
    format!("/camera/{role}/ground_truth/surface")
}

/// A rigid transform in JSON: translation (m) and unit quaternion (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseJson {
    /// Translation (m).
    pub translation_m: [f64; 3],
    /// Rotation quaternion `[x, y, z, w]`.
    pub rotation_xyzw: [f64; 4],
}

impl From<&Isometry3<f64>> for PoseJson {
    fn from(pose: &Isometry3<f64>) -> Self {
        let t = pose.translation.vector;
        let q = pose.rotation.coords;
        Self {
            translation_m: [t.x, t.y, t.z],
            rotation_xyzw: [q.x, q.y, q.z, q.w],
        }
    }
}

impl PoseJson {
    /// Back to an isometry (the quaternion is renormalised).
    pub fn to_isometry(&self) -> Isometry3<f64> {
        let [x, y, z] = self.translation_m;
        let [qx, qy, qz, qw] = self.rotation_xyzw;
        Isometry3::from_parts(
            nalgebra::Translation3::new(x, y, z),
            nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(qw, qx, qy, qz)),
        )
    }
}

/// The capture event: one per view, at the image's time, on [`CAPTURE_EVENTS_TOPIC`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureEvent {
    /// Index of the set in the log.
    pub set_index: u32,
    /// Set name.
    pub set_name: String,
    /// Rig layout name (`five-view`, `three-view`, `stereo`, `grid3x3`, `line5`, `grid-cross`, or `custom` for
    /// an imported set of other offsets).
    pub rig: String,
    /// Number of views in the set.
    pub views_in_set: u32,
    /// Role of this view.
    pub role: String,
    /// Offset in baselines along the reference camera's x and y axes; a view at a multiple of
    /// the baseline (e.g. `[2, 0]`) has its disparity at that multiple of the direct neighbours'.
    pub grid_offset: [i32; 2],
    /// Commanded baseline between the reference and each direct neighbour (m).
    pub baseline_m: f64,
    /// Image time (ns since the Unix epoch): the log time of this view's messages.
    pub capture_time_nanos: u64,
    /// Topic of the image.
    pub image_topic: String,
    /// Topic of the calibration.
    pub calibration_topic: String,
    /// Topic of the ground-truth depth, when present.
    pub depth_topic: Option<String>,
    /// Topic of the ground-truth surface classes, when present.
    pub surface_topic: Option<String>,
    /// Camera pose as the system knows it (same as the `/tf` chain at this time).
    pub world_from_camera: PoseJson,
    /// Pose commanded by the planner.
    pub commanded_world_from_camera: Option<PoseJson>,
    /// Ground truth: the pose the image was really taken from (simulation only).
    pub true_world_from_camera: Option<PoseJson>,
    /// Joint positions at the capture (rad).
    pub joint_positions_rad: Option<[f64; JOINT_COUNT]>,
    /// Exposure gain applied (simulation; 1 = nominal).
    pub exposure_gain: f64,
    /// The disparities to search for this set, when its source knows them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disparity_range: Option<crate::DisparityRange>,
}

/// JSON schema of [`CaptureEvent`].
pub fn capture_event_json_schema() -> serde_json::Value {
    let pose = serde_json::json!({
        "type": "object",
        "properties": {
            "translation_m": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
            "rotation_xyzw": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4}
        },
        "required": ["translation_m", "rotation_xyzw"]
    });
    let nullable_pose = serde_json::json!({"anyOf": [pose, {"type": "null"}]});
    serde_json::json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": CAPTURE_EVENT_SCHEMA,
        "description": "One view of a multiscopic set: which image it is, its role, pose and baseline.",
        "type": "object",
        "properties": {
            "set_index": {"type": "integer", "minimum": 0},
            "set_name": {"type": "string"},
            "rig": {"type": "string", "description": "five-view, three-view, stereo, grid3x3, line5, grid-cross, or custom (imported sets; the offsets are in grid_offset)"},
            "views_in_set": {"type": "integer", "minimum": 1},
            "role": {"type": "string"},
            "grid_offset": {"type": "array", "items": {"type": "integer"}, "minItems": 2, "maxItems": 2},
            "baseline_m": {"type": "number", "exclusiveMinimum": 0},
            "capture_time_nanos": {"type": "integer", "minimum": 0},
            "image_topic": {"type": "string"},
            "calibration_topic": {"type": "string"},
            "depth_topic": {"type": ["string", "null"]},
            "surface_topic": {"type": ["string", "null"]},
            "world_from_camera": pose,
            "commanded_world_from_camera": nullable_pose,
            "true_world_from_camera": nullable_pose,
            "joint_positions_rad": {"anyOf": [{"type": "array", "items": {"type": "number"}}, {"type": "null"}]},
            "exposure_gain": {"type": "number"},
            "disparity_range": {
                "description": "the disparities to search (px, signed), when the source knows them",
                "type": "object",
                "properties": {
                    "min_disparity": {"type": "integer"},
                    "num_disparities": {"anyOf": [{"type": "integer", "minimum": 1}, {"type": "null"}]}
                },
                "required": ["min_disparity"]
            }
        },
        "required": ["set_index", "set_name", "rig", "views_in_set", "role", "grid_offset", "baseline_m",
                     "capture_time_nanos", "image_topic", "calibration_topic", "world_from_camera", "exposure_gain"]
    })
}

/// Errors writing a log.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// The MCAP writer failed.
    #[error("MCAP write to topic '{topic}' failed")]
    Mcap {
        /// Topic (or record kind) being written.
        topic: String,
        /// Cause.
        #[source]
        source: mcap::McapError,
    },
    /// A message could not be encoded.
    #[error("encoding a message for topic '{topic}' failed: {reason}")]
    Encode {
        /// Topic.
        topic: String,
        /// Cause.
        reason: String,
    },
    /// Creating, writing or renaming the output file failed.
    #[error("{action} '{path}'")]
    Io {
        /// What was being done.
        action: &'static str,
        /// File.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// A view's buffers do not match its size.
    #[error("set {set} view '{role}': {field} has {actual} values, expected {expected} for {width}x{height}")]
    BufferSize {
        /// Set index.
        set: u32,
        /// Role.
        role: String,
        /// Which buffer.
        field: &'static str,
        /// Values present.
        actual: usize,
        /// Values expected.
        expected: usize,
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
    },
}

impl CaptureEvent {
    /// The event of `view` in `set`, with the topics of our own log (`/camera/<role>/…`; ground
    /// truth named only when the view has it).
    pub fn of_view(set: &CapturedSet, view: &CapturedView) -> Self {
        Self {
            set_index: set.index,
            set_name: set.name.clone(),
            rig: set.rig.clone(),
            views_in_set: set.views.len() as u32,
            role: view.role.clone(),
            grid_offset: view.grid_offset,
            baseline_m: set.baseline_m,
            capture_time_nanos: view.capture_time_nanos,
            image_topic: image_topic(&view.role),
            calibration_topic: calibration_topic(&view.role),
            depth_topic: view.depth_m.as_ref().map(|_| depth_topic(&view.role)),
            surface_topic: view.surface_class.as_ref().map(|_| surface_topic(&view.role)),
            world_from_camera: (&view.world_from_camera).into(),
            commanded_world_from_camera: view.commanded_world_from_camera.as_ref().map(Into::into),
            true_world_from_camera: view.true_world_from_camera.as_ref().map(Into::into),
            joint_positions_rad: view.joints,
            exposure_gain: view.exposure_gain,
            disparity_range: set.disparity_range,
        }
    }
}

/// Options of a log, builder style with a terminal [`LogOptions::create`].
#[derive(Debug, Clone)]
pub struct LogOptions {
    chunk_size: u64,
    zstd_level: u32,
    image_format: ImageFormat,
    png_compression: png::Compression,
}

impl Default for LogOptions {
    fn default() -> Self {
        Self {
            chunk_size: DEFAULT_CHUNK_SIZE,
            zstd_level: DEFAULT_ZSTD_LEVEL,
            image_format: ImageFormat::Raw,
            png_compression: png::Compression::Fast,
        }
    }
}

impl LogOptions {
    /// Default options.
    pub fn new() -> Self {
        Self::default()
    }

    /// Uncompressed chunk size (bytes).
    pub fn chunk_size(mut self, bytes: u64) -> Self {
        self.chunk_size = bytes;
        self
    }

    /// zstd level of the chunks.
    pub fn zstd_level(mut self, level: u32) -> Self {
        self.zstd_level = level;
        self
    }

    /// How images are stored.
    pub fn image_format(mut self, format: ImageFormat) -> Self {
        self.image_format = format;
        self
    }

    /// How images are stored.
    pub fn image_format_of(&self) -> ImageFormat {
        self.image_format
    }

    /// The PNG compression of images stored as PNG.
    pub fn png_compression(&self) -> png::Compression {
        self.png_compression
    }

    /// The `mcap` writer settings of every log: zstd chunks of this size and level, indexes,
    /// statistics and every CRC; `library` names the writing tool. Also for tools that copy
    /// records as they are (`replay recover`).
    pub fn mcap_options(&self, library: String) -> mcap::WriteOptions {
        mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(self.zstd_level)
            .compression_threads(0)
            .chunk_size(Some(self.chunk_size))
            .profile("")
            .library(library)
            .calculate_chunk_crcs(true)
            .calculate_data_section_crc(true)
            .calculate_summary_section_crc(true)
            .calculate_attachment_crcs(true)
    }

    /// Starts a log on any seekable writer.
    pub fn create<W: Write + Seek>(self, writer: W) -> Result<LogWriter<W>, LogError> {
        let options = self.mcap_options(format!("multiscopic-record {}", crate::TOOL_VERSION));
        let writer = options.create(writer).map_err(|source| LogError::Mcap {
            topic: "header".into(),
            source,
        })?;
        Ok(LogWriter {
            writer,
            options: self,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            sequences: HashMap::new(),
            arm: Ur10::default(),
        })
    }
}

/// Writes captured sets as a log.
pub struct LogWriter<W: Write + Seek> {
    writer: mcap::Writer<W>,
    options: LogOptions,
    schemas: HashMap<String, u16>,
    channels: HashMap<String, u16>,
    sequences: HashMap<u16, u32>,
    arm: Ur10,
}

/// Writes one message on a known channel with that channel's next sequence number (1, 2, …),
/// logged and published at `log_time`, into any log (ours, a bag, a result log).
pub fn write_sequenced<W: Write + Seek>(
    writer: &mut mcap::Writer<W>,
    sequences: &mut HashMap<u16, u32>,
    (channel_id, topic): (u16, &str),
    log_time: u64,
    data: &[u8],
) -> Result<(), LogError> {
    let sequence = sequences.entry(channel_id).or_insert(0);
    *sequence += 1;
    let header = mcap::records::MessageHeader {
        channel_id,
        sequence: *sequence,
        log_time,
        publish_time: log_time,
    };
    writer
        .write_to_known_channel(&header, data)
        .map_err(|source| LogError::Mcap {
            topic: topic.to_owned(),
            source,
        })
}

/// Checks that a view's buffer `field` holds `per_pixel` values per pixel of its camera.
pub(crate) fn check_buffer_len(
    set: &CapturedSet,
    view: &CapturedView,
    field: &'static str,
    actual: usize,
    per_pixel: usize,
) -> Result<(), LogError> {
    let expected = view.camera.pixel_count() * per_pixel;
    if actual == expected {
        Ok(())
    } else {
        Err(LogError::BufferSize {
            set: set.index,
            role: view.role.clone(),
            field,
            actual,
            expected,
            width: view.camera.width,
            height: view.camera.height,
        })
    }
}

/// Writes a metadata record into any log (ours, a bag, a result log).
pub fn write_metadata_record<W: Write + Seek>(
    writer: &mut mcap::Writer<W>,
    name: &str,
    metadata: BTreeMap<String, String>,
) -> Result<(), LogError> {
    writer
        .write_metadata(&mcap::records::Metadata {
            name: name.to_owned(),
            metadata,
        })
        .map_err(|source| LogError::Mcap {
            topic: "metadata".into(),
            source,
        })
}

/// Writes an attachment (created when logged) into any log.
pub fn write_attachment<W: Write + Seek>(
    writer: &mut mcap::Writer<W>,
    name: &str,
    media_type: &str,
    log_time: u64,
    data: &[u8],
) -> Result<(), LogError> {
    writer
        .attach(&mcap::Attachment {
            log_time,
            create_time: log_time,
            name: name.to_owned(),
            media_type: media_type.to_owned(),
            data: std::borrow::Cow::Borrowed(data),
        })
        .map_err(|source| LogError::Mcap {
            topic: "attachment".into(),
            source,
        })
}

/// A `foxglove` timestamp from nanoseconds since the Unix epoch.
pub fn timestamp(nanos: u64) -> Timestamp {
    Timestamp::new((nanos / 1_000_000_000) as u32, (nanos % 1_000_000_000) as u32)
}

fn vector3(v: &nalgebra::Vector3<f64>) -> Vector3 {
    Vector3 { x: v.x, y: v.y, z: v.z }
}

fn quaternion(q: &nalgebra::UnitQuaternion<f64>) -> Quaternion {
    Quaternion {
        x: q.i,
        y: q.j,
        z: q.k,
        w: q.w,
    }
}

fn frame_transform(nanos: u64, parent: &str, child: &str, parent_from_child: &Isometry3<f64>) -> FrameTransform {
    FrameTransform {
        timestamp: Some(timestamp(nanos)),
        parent_frame_id: parent.to_owned(),
        child_frame_id: child.to_owned(),
        translation: Some(vector3(&parent_from_child.translation.vector)),
        rotation: Some(quaternion(&parent_from_child.rotation)),
    }
}

impl<W: Write + Seek> LogWriter<W> {
    fn mcap_error(topic: &str) -> impl FnOnce(mcap::McapError) -> LogError + '_ {
        move |source| LogError::Mcap {
            topic: topic.to_owned(),
            source,
        }
    }

    fn channel(
        &mut self,
        topic: &str,
        schema_name: &str,
        schema_encoding: &str,
        schema: &[u8],
        message_encoding: &str,
    ) -> Result<u16, LogError> {
        if let Some(id) = self.channels.get(topic) {
            return Ok(*id);
        }
        let schema_id = match self.schemas.get(schema_name) {
            Some(id) => *id,
            None => {
                let id = self
                    .writer
                    .add_schema(schema_name, schema_encoding, schema)
                    .map_err(Self::mcap_error(topic))?;
                self.schemas.insert(schema_name.to_owned(), id);
                id
            }
        };
        let id = self
            .writer
            .add_channel(schema_id, topic, message_encoding, &BTreeMap::new())
            .map_err(Self::mcap_error(topic))?;
        self.channels.insert(topic.to_owned(), id);
        Ok(id)
    }

    fn write_raw(&mut self, channel_id: u16, topic: &str, log_time: u64, data: &[u8]) -> Result<(), LogError> {
        write_sequenced(
            &mut self.writer,
            &mut self.sequences,
            (channel_id, topic),
            log_time,
            data,
        )
    }

    /// Writes a Foxglove message.
    pub fn write_message<T: Encode>(&mut self, topic: &str, log_time: u64, message: &T) -> Result<(), LogError> {
        let schema = T::get_schema().ok_or_else(|| LogError::Encode {
            topic: topic.to_owned(),
            reason: "message type has no schema".into(),
        })?;
        let channel_id = self.channel(
            topic,
            &schema.name,
            &schema.encoding,
            &schema.data,
            &T::get_message_encoding(),
        )?;
        let mut buffer = Vec::with_capacity(message.encoded_len().unwrap_or(256));
        message.encode(&mut buffer).map_err(|e| LogError::Encode {
            topic: topic.to_owned(),
            reason: e.to_string(),
        })?;
        self.write_raw(channel_id, topic, log_time, &buffer)
    }

    /// Writes a capture event.
    pub fn write_event(&mut self, log_time: u64, event: &CaptureEvent) -> Result<(), LogError> {
        let schema = capture_event_json_schema().to_string();
        let channel_id = self.channel(
            CAPTURE_EVENTS_TOPIC,
            CAPTURE_EVENT_SCHEMA,
            "jsonschema",
            schema.as_bytes(),
            "json",
        )?;
        let data = serde_json::to_vec(event).map_err(|e| LogError::Encode {
            topic: CAPTURE_EVENTS_TOPIC.into(),
            reason: e.to_string(),
        })?;
        self.write_raw(channel_id, CAPTURE_EVENTS_TOPIC, log_time, &data)
    }

    /// Writes a JSON message (schema: `{"type": "object"}` under `schema_name`).
    pub fn write_json(
        &mut self,
        topic: &str,
        schema_name: &str,
        log_time: u64,
        value: &serde_json::Value,
    ) -> Result<(), LogError> {
        let schema = serde_json::json!({"title": schema_name, "type": "object"}).to_string();
        let channel_id = self.channel(topic, schema_name, "jsonschema", schema.as_bytes(), "json")?;
        let data = serde_json::to_vec(value).map_err(|e| LogError::Encode {
            topic: topic.to_owned(),
            reason: e.to_string(),
        })?;
        self.write_raw(channel_id, topic, log_time, &data)
    }

    /// Writes a metadata record.
    pub fn write_metadata(&mut self, name: &str, metadata: BTreeMap<String, String>) -> Result<(), LogError> {
        write_metadata_record(&mut self.writer, name, metadata)
    }

    /// Writes an attachment.
    pub fn attach(&mut self, name: &str, media_type: &str, log_time: u64, data: &[u8]) -> Result<(), LogError> {
        write_attachment(&mut self.writer, name, media_type, log_time, data)
    }

    fn write_arm_state(
        &mut self,
        nanos: u64,
        sample: &crate::MotionSample,
        flange_from_camera: Option<&Isometry3<f64>>,
    ) -> Result<(), LogError> {
        let links = self.arm.link_transforms(&sample.joints);
        let mut transforms = Vec::with_capacity(JOINT_COUNT + 2);
        transforms.push(frame_transform(nanos, WORLD_FRAME, BASE_FRAME, &Isometry3::identity()));
        let mut parent = BASE_FRAME;
        for (link, name) in links.iter().zip(LINK_FRAME_NAMES) {
            transforms.push(frame_transform(nanos, parent, name, link));
            parent = name;
        }
        if let Some(hand_eye) = flange_from_camera {
            transforms.push(frame_transform(nanos, parent, CAMERA_FRAME, hand_eye));
        }
        self.write_message(TF_TOPIC, nanos, &FrameTransforms { transforms })?;
        let joints = JOINT_NAMES
            .iter()
            .enumerate()
            .map(|(i, name)| JointState {
                name: (*name).to_owned(),
                position: Some(sample.joints[i]),
                velocity: Some(sample.joint_velocities[i]),
                acceleration: None,
                effort: None,
            })
            .collect();
        self.write_message(
            JOINT_STATES_TOPIC,
            nanos,
            &JointStates {
                timestamp: Some(timestamp(nanos)),
                joints,
            },
        )
    }

    /// Writes one complete set: arm motion, then per view the transforms, calibration, image,
    /// ground truth (surface classes, then depth), commanded pose and the capture event, all in
    /// time order; then ends the chunk and flushes it, so that every set written is whole on disk
    /// before the next starts (the chunk size still bounds a huge set's chunks).
    pub fn write_set(
        &mut self,
        set: &CapturedSet,
        flange_from_camera: Option<&Isometry3<f64>>,
    ) -> Result<(), LogError> {
        let mut motion = set.motion.iter().peekable();
        for view in &set.views {
            while let Some(sample) = motion.next_if(|s| s.time_nanos <= view.capture_time_nanos) {
                self.write_arm_state(sample.time_nanos, sample, flange_from_camera)?;
            }
            let t = view.capture_time_nanos;
            // The view's own frame, fixed in the world where it was taken (its images and
            // calibration refer to it, so viewers keep every view's frustum in place); without an
            // arm the moving camera frame is given directly too.
            let mut transforms = vec![frame_transform(
                t,
                WORLD_FRAME,
                &view_frame(&view.role),
                &view.world_from_camera,
            )];
            if set.motion.is_empty() {
                transforms.push(frame_transform(t, WORLD_FRAME, CAMERA_FRAME, &view.world_from_camera));
            }
            self.write_message(TF_TOPIC, t, &FrameTransforms { transforms })?;
            self.write_view(set, view)?;
        }
        for sample in motion {
            self.write_arm_state(sample.time_nanos, sample, flange_from_camera)?;
        }
        self.end_set()
    }

    /// Ends the chunk (so that it holds whole sets: a crash later cannot tear this one) and
    /// flushes it to the writer, which for a [`SyncedWriter`] also syncs it to the disk.
    fn end_set(&mut self) -> Result<(), LogError> {
        self.writer.flush().map_err(Self::mcap_error("end of set"))
    }

    fn write_view(&mut self, set: &CapturedSet, view: &CapturedView) -> Result<(), LogError> {
        let t = view.capture_time_nanos;
        let (width, height) = (view.camera.width, view.camera.height);
        check_buffer_len(set, view, "rgb", view.rgb.len(), 3)?;
        let image = image_topic(&view.role);
        // A raw image of this view on `topic`: `encoding`, `bytes_per_pixel`, little-endian data.
        let raw = |encoding: &str, bytes_per_pixel: u32, data: Bytes| RawImage {
            timestamp: Some(timestamp(t)),
            frame_id: view_frame(&view.role),
            width,
            height,
            encoding: encoding.into(),
            step: width * bytes_per_pixel,
            data,
        };
        // The calibration first: the image then ends its chunk with it (`DEFAULT_CHUNK_SIZE`).
        let calibration = calibration_topic(&view.role);
        let frame = view_frame(&view.role);
        self.write_message(&calibration, t, &calibration_message(&view.camera, t, &frame))?;
        match self.options.image_format {
            ImageFormat::Raw => self.write_message(&image, t, &raw("rgb8", 3, Bytes::copy_from_slice(&view.rgb)))?,
            ImageFormat::Png => {
                let data = encode_png_rgb8(&view.rgb, width, height, self.options.png_compression).map_err(|e| {
                    LogError::Encode {
                        topic: image.clone(),
                        reason: e.to_string(),
                    }
                })?;
                self.write_message(
                    &image,
                    t,
                    &CompressedImage {
                        timestamp: Some(timestamp(t)),
                        frame_id: view_frame(&view.role),
                        data: Bytes::from(data),
                        format: "png".into(),
                    },
                )?
            }
        }
        // The ground truth after the image, the largest last: the two in a chunk of their own.
        let surface = match &view.surface_class {
            Some(classes) => {
                check_buffer_len(set, view, "surface_class", classes.len(), 1)?;
                let topic = surface_topic(&view.role);
                self.write_message(&topic, t, &raw(SURFACE_ENCODING, 1, Bytes::copy_from_slice(classes)))?;
                Some(topic)
            }
            None => None,
        };
        let depth = match &view.depth_m {
            Some(depth_m) => {
                check_buffer_len(set, view, "depth_m", depth_m.len(), 1)?;
                let topic = depth_topic(&view.role);
                let data: Vec<u8> = depth_m.iter().flat_map(|d| d.to_le_bytes()).collect();
                self.write_message(&topic, t, &raw(DEPTH_ENCODING, 4, Bytes::from(data)))?;
                Some(topic)
            }
            None => None,
        };
        if let Some(commanded) = &view.commanded_world_from_camera {
            self.write_message(
                COMMANDED_POSE_TOPIC,
                t,
                &PoseInFrame {
                    timestamp: Some(timestamp(t)),
                    frame_id: WORLD_FRAME.into(),
                    pose: Some(Pose {
                        position: Some(vector3(&commanded.translation.vector)),
                        orientation: Some(quaternion(&commanded.rotation)),
                    }),
                },
            )?;
        }
        let event = CaptureEvent {
            image_topic: image,
            calibration_topic: calibration,
            depth_topic: depth,
            surface_topic: surface,
            ..CaptureEvent::of_view(set, view)
        };
        self.write_event(t, &event)
    }

    /// Writes the summary section (indexes, statistics, CRCs) and returns the underlying writer.
    pub fn finish(mut self) -> Result<W, LogError> {
        self.writer.finish().map_err(Self::mcap_error("summary"))?;
        Ok(self.writer.into_inner())
    }
}

/// The `foxglove.CameraCalibration` of an ideal pinhole camera in [`CAMERA_FRAME`]: K, R = I,
/// P = [K | 0], `plumb_bob` with zero distortion.
pub fn calibration_message(camera: &crate::camera::PinholeCamera, nanos: u64, frame_id: &str) -> CameraCalibration {
    let c = camera;
    CameraCalibration {
        timestamp: Some(timestamp(nanos)),
        frame_id: frame_id.into(),
        width: c.width,
        height: c.height,
        distortion_model: "plumb_bob".into(),
        d: vec![0.0; 5],
        k: c.k_row_major().to_vec(),
        r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: vec![c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    }
}

/// Encodes 8-bit RGB as PNG.
pub fn encode_png_rgb8(
    rgb: &[u8],
    width: u32,
    height: u32,
    compression: png::Compression,
) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::with_capacity(rgb.len() / 2);
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(compression);
        let mut writer = encoder.write_header()?;
        writer.write_image_data(rgb)?;
        writer.finish()?;
    }
    Ok(out)
}

/// The writer of an [`OutputFile`]: buffered, and each `flush` (the log writer's at every set's
/// end, and at its finish) also syncs the data to the disk (`fdatasync`).
#[derive(Debug)]
pub struct SyncedWriter {
    inner: BufWriter<File>,
}

impl Write for SyncedWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.inner.write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.inner.write_all(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()?;
        self.inner.get_ref().sync_data()
    }
}

impl Seek for SyncedWriter {
    fn seek(&mut self, position: std::io::SeekFrom) -> std::io::Result<u64> {
        self.inner.seek(position)
    }
}

/// Syncs a directory, so that a file created or renamed in it survives a power cut.
fn sync_directory(directory: &Path) -> std::io::Result<()> {
    File::open(directory)?.sync_all()
}

/// An output file that appears under its final name only when committed: it is written under a
/// hidden temporary name in the same directory and renamed atomically by [`OutputFile::commit`];
/// dropped without a commit, the temporary file is removed, unless [`OutputFile::keep`] said
/// that it holds something worth recovering.
#[derive(Debug)]
pub struct OutputFile {
    final_path: PathBuf,
    temp_path: PathBuf,
    committed: bool,
}

impl OutputFile {
    /// Creates the temporary file next to `final_path` (and syncs the directory, so that the
    /// file's name survives a power cut too).
    pub fn create(final_path: &Path) -> Result<(Self, SyncedWriter), LogError> {
        let directory = match final_path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let file_name = final_path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .ok_or_else(|| LogError::Io {
                action: "output path has no file name",
                path: final_path.to_path_buf(),
                source: std::io::Error::from(std::io::ErrorKind::InvalidInput),
            })?;
        if final_path.is_dir() {
            return Err(LogError::Io {
                action: "output path is a directory",
                path: final_path.to_path_buf(),
                source: std::io::Error::from(std::io::ErrorKind::IsADirectory),
            });
        }
        let temp_path = directory.join(format!(".{file_name}.partial-{}", std::process::id()));
        let file = File::create(&temp_path).map_err(|source| LogError::Io {
            action: "cannot create output file",
            path: temp_path.clone(),
            source,
        })?;
        sync_directory(&directory).map_err(|source| LogError::Io {
            action: "cannot sync the output directory",
            path: directory.clone(),
            source,
        })?;
        Ok((
            Self {
                final_path: final_path.to_path_buf(),
                temp_path,
                committed: false,
            },
            SyncedWriter {
                inner: BufWriter::with_capacity(1 << 20, file),
            },
        ))
    }

    /// The temporary file being written.
    pub fn temp_path(&self) -> &Path {
        &self.temp_path
    }

    /// Leaves the temporary file in place (it holds sets that `replay recover` can finish) and
    /// returns its path.
    pub fn keep(mut self) -> PathBuf {
        self.committed = true;
        self.temp_path.clone()
    }

    /// Flushes, syncs and renames the file to its final name, then syncs the directory.
    pub fn commit(mut self, writer: SyncedWriter) -> Result<PathBuf, LogError> {
        let io = |action| {
            let path = self.temp_path.clone();
            move |source| LogError::Io { action, path, source }
        };
        let file = writer
            .inner
            .into_inner()
            .map_err(|e| e.into_error())
            .map_err(io("cannot flush"))?;
        file.sync_all().map_err(io("cannot sync"))?;
        drop(file);
        std::fs::rename(&self.temp_path, &self.final_path).map_err(io("cannot rename into place"))?;
        self.committed = true;
        if let Some(directory) = self.final_path.parent().filter(|p| !p.as_os_str().is_empty()) {
            sync_directory(directory).map_err(|source| LogError::Io {
                action: "cannot sync the output directory",
                path: directory.to_path_buf(),
                source,
            })?;
        }
        Ok(self.final_path.clone())
    }
}

impl Drop for OutputFile {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.temp_path);
        }
    }
}
