//! Captures as ROS 2 bags: the content of our own log ([`crate::log`]) as the messages a real
//! UR + camera ROS 2 system records, so that `ros2 bag play`, rviz, Foxglove's ROS panels and
//! `rerun` show a simulated or imported capture as they show a robot's, and `replay` reads it
//! back.
//!
//! One camera streams on [`IMAGE_TOPIC`] (`sensor_msgs/msg/Image` rgb8, or `CompressedImage`
//! png) with its `CameraInfo`, in the REP 103 optical frame [`OPTICAL_FRAME`] (x right, y down,
//! z forward) under `camera_link` (x forward, z up); the arm's links go to `/tf` at the motion
//! rate (`world` → `base` static, `base` → … → `tool0` from the UR10's kinematics), the hand-eye
//! transform `tool0` → `camera_link` → `camera_optical_frame` to `/tf_static` (transient local),
//! joints to `/joint_states` by name; ground truth as `32FC1` depth (m) and `mono8` surface
//! classes; the capture events and plans as JSON in `std_msgs/msg/String` on the topics of our own
//! log. An import (no arm) puts `world` → `camera_optical_frame` on `/tf` at each view's time.
//! Chunks are zstd-compressed, one set per chunk, synced as our own log's are.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::io::{Seek, Write};

use nalgebra::{Isometry3, UnitQuaternion};
use ros2::bag::{BagInfo, FileInfo, Qos, TopicInfo};
use ros2::msg::{self, Header, Time, TransformStamped};
use ros2::schema::{self, MessageType};
use serde::Serialize;

use crate::log::{
    CAPTURE_EVENTS_TOPIC, CaptureEvent, DEPTH_ENCODING, LogError, LogOptions, SURFACE_ENCODING, encode_png_rgb8,
};
use crate::ur10::{JOINT_COUNT, JOINT_NAMES, LINK_FRAME_NAMES, Ur10};
use crate::{CapturedSet, CapturedView, ImageFormat};

/// The camera's images.
pub const IMAGE_TOPIC: &str = "/camera/image_raw";
/// The camera's calibration.
pub const CAMERA_INFO_TOPIC: &str = "/camera/camera_info";
/// Ground-truth depth (`32FC1`, m along the optical axis, 0 = unknown).
pub const DEPTH_TOPIC: &str = "/camera/ground_truth/depth";
/// Ground-truth surface classes (`mono8`, [`crate::scene::SurfaceClass`]).
pub const SURFACE_TOPIC: &str = "/camera/ground_truth/surface";
/// Joint positions and velocities by name.
pub const JOINT_STATES_TOPIC: &str = "/joint_states";
/// Moving transforms.
pub const TF_TOPIC: &str = "/tf";
/// Fixed transforms (transient local).
pub const TF_STATIC_TOPIC: &str = "/tf_static";
/// The camera's optical frame (REP 103: x right, y down, z forward), the images' `frame_id`.
pub const OPTICAL_FRAME: &str = "camera_optical_frame";
/// The camera's body frame (x forward, y left, z up).
pub const CAMERA_LINK_FRAME: &str = "camera_link";
/// The arm's flange as the UR description names it (z out of the flange: the DH chain's end).
pub const TOOL_FRAME: &str = "tool0";
/// The arm's base frame.
pub const BASE_FRAME: &str = "base";
/// The root frame (the table, z up).
pub const WORLD_FRAME: &str = crate::log::WORLD_FRAME;

/// `camera_link_from_optical`: the fixed REP 103 rotation (optical z forward is link x).
pub fn link_from_optical() -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(0.5, -0.5, 0.5, -0.5))
}

/// A ROS time from nanoseconds since the Unix epoch.
pub fn stamp(nanos: u64, frame_id: &str) -> Header {
    Header {
        stamp: Time::from_nanos(nanos),
        frame_id: frame_id.to_owned(),
    }
}

/// `parent_from_child` as a stamped transform.
pub fn transform_stamped(
    nanos: u64,
    parent: &str,
    child: &str,
    parent_from_child: &Isometry3<f64>,
) -> TransformStamped {
    let t = parent_from_child.translation.vector;
    let q = parent_from_child.rotation;
    TransformStamped {
        header: stamp(nanos, parent),
        child_frame_id: child.to_owned(),
        transform: msg::Transform {
            translation: msg::Vector3 { x: t.x, y: t.y, z: t.z },
            rotation: msg::Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        },
    }
}

/// The `CameraInfo` of an ideal pinhole camera: K, no distortion (`plumb_bob`, zeros), R = I,
/// P = [K | 0].
pub fn camera_info(camera: &crate::camera::PinholeCamera, nanos: u64, frame_id: &str) -> msg::CameraInfo {
    let c = camera;
    msg::CameraInfo {
        header: stamp(nanos, frame_id),
        height: c.height,
        width: c.width,
        distortion_model: "plumb_bob".into(),
        d: vec![0.0; 5],
        k: c.k_row_major(),
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        binning_x: 0,
        binning_y: 0,
        roi: msg::RegionOfInterest::default(),
    }
}

/// Writes captured sets as a ROS 2 bag's MCAP file (profile `ros2`, `ros2msg` schemas, CDR
/// messages, `offered_qos_profiles` on every channel); [`BagWriter::finish`] returns what the
/// bag's `metadata.yaml` says.
pub struct BagWriter<W: Write + Seek> {
    writer: mcap::Writer<W>,
    options: LogOptions,
    file_name: String,
    schemas: HashMap<&'static str, u16>,
    channels: HashMap<String, (u16, usize)>,
    topics: Vec<TopicInfo>,
    sequences: HashMap<u16, u32>,
    time_span: Option<(u64, u64)>,
    static_written: bool,
    arm: Ur10,
}

impl<W: Write + Seek> BagWriter<W> {
    /// Starts a bag file named `file_name` (what `metadata.yaml` will list) on `writer`.
    pub fn create(options: LogOptions, file_name: &str, writer: W) -> Result<Self, LogError> {
        let mcap_options = options
            .mcap_options(format!("multiscopic-record {}", crate::TOOL_VERSION))
            .profile(ros2::bag::PROFILE);
        let writer = mcap_options.create(writer).map_err(|source| LogError::Mcap {
            topic: "header".into(),
            source,
        })?;
        Ok(Self {
            writer,
            options,
            file_name: file_name.to_owned(),
            schemas: HashMap::new(),
            channels: HashMap::new(),
            topics: Vec::new(),
            sequences: HashMap::new(),
            time_span: None,
            static_written: false,
            arm: Ur10::default(),
        })
    }

    fn mcap_error(topic: &str) -> impl FnOnce(mcap::McapError) -> LogError + '_ {
        move |source| LogError::Mcap {
            topic: topic.to_owned(),
            source,
        }
    }

    fn channel(&mut self, topic: &str, message_type: MessageType, qos: Qos) -> Result<(u16, usize), LogError> {
        if let Some(channel) = self.channels.get(topic) {
            return Ok(*channel);
        }
        let schema_id = match self.schemas.get(message_type.name) {
            Some(id) => *id,
            None => {
                let id = self
                    .writer
                    .add_schema(
                        message_type.name,
                        schema::SCHEMA_ENCODING,
                        message_type.definition.as_bytes(),
                    )
                    .map_err(Self::mcap_error(topic))?;
                self.schemas.insert(message_type.name, id);
                id
            }
        };
        let metadata = BTreeMap::from([
            ("offered_qos_profiles".to_owned(), qos.yaml(0)),
            ("topic_type_hash".to_owned(), message_type.type_hash.to_owned()),
        ]);
        let id = self
            .writer
            .add_channel(schema_id, topic, schema::MESSAGE_ENCODING, &metadata)
            .map_err(Self::mcap_error(topic))?;
        self.topics.push(TopicInfo {
            name: topic.to_owned(),
            type_name: message_type.name.to_owned(),
            type_hash: message_type.type_hash.to_owned(),
            qos,
            message_count: 0,
        });
        let channel = (id, self.topics.len() - 1);
        self.channels.insert(topic.to_owned(), channel);
        Ok(channel)
    }

    /// Writes one message (CDR) on `topic` at `log_time`.
    pub fn write<T: Serialize>(
        &mut self,
        topic: &str,
        message_type: MessageType,
        log_time: u64,
        message: &T,
    ) -> Result<(), LogError> {
        let qos = if topic == TF_STATIC_TOPIC {
            Qos::LATCHED
        } else {
            Qos::STREAM
        };
        let (channel_id, topic_index) = self.channel(topic, message_type, qos)?;
        let data = ros2::encode(message).map_err(|e| LogError::Encode {
            topic: topic.to_owned(),
            reason: e.to_string(),
        })?;
        crate::log::write_sequenced(
            &mut self.writer,
            &mut self.sequences,
            (channel_id, topic),
            log_time,
            &data,
        )?;
        self.topics[topic_index].message_count += 1;
        self.time_span = Some(match self.time_span {
            None => (log_time, log_time),
            Some((a, b)) => (a.min(log_time), b.max(log_time)),
        });
        Ok(())
    }

    /// Writes JSON as a `std_msgs/msg/String` (capture events, plans).
    pub fn write_json<T: Serialize>(&mut self, topic: &str, log_time: u64, value: &T) -> Result<(), LogError> {
        let data = serde_json::to_string(value).map_err(|e| LogError::Encode {
            topic: topic.to_owned(),
            reason: e.to_string(),
        })?;
        self.write(topic, schema::STRING, log_time, &msg::StringMessage { data })
    }

    /// Writes a metadata record.
    pub fn write_metadata(&mut self, name: &str, metadata: BTreeMap<String, String>) -> Result<(), LogError> {
        crate::log::write_metadata_record(&mut self.writer, name, metadata)
    }

    /// Writes an attachment.
    pub fn attach(&mut self, name: &str, media_type: &str, log_time: u64, data: &[u8]) -> Result<(), LogError> {
        crate::log::write_attachment(&mut self.writer, name, media_type, log_time, data)
    }

    fn write_static(&mut self, nanos: u64, flange_from_camera: Option<&Isometry3<f64>>) -> Result<(), LogError> {
        if self.static_written {
            return Ok(());
        }
        self.static_written = true;
        let mut transforms = vec![transform_stamped(
            nanos,
            WORLD_FRAME,
            BASE_FRAME,
            &Isometry3::identity(),
        )];
        if let Some(flange_from_optical) = flange_from_camera {
            let link_from_optical = Isometry3::from_parts(nalgebra::Translation3::identity(), link_from_optical());
            transforms.push(transform_stamped(
                nanos,
                TOOL_FRAME,
                CAMERA_LINK_FRAME,
                &(flange_from_optical * link_from_optical.inverse()),
            ));
            transforms.push(transform_stamped(
                nanos,
                CAMERA_LINK_FRAME,
                OPTICAL_FRAME,
                &link_from_optical,
            ));
        }
        self.write(
            TF_STATIC_TOPIC,
            schema::TF_MESSAGE,
            nanos,
            &msg::TfMessage { transforms },
        )
    }

    fn write_arm_state(&mut self, sample: &crate::MotionSample) -> Result<(), LogError> {
        let nanos = sample.time_nanos;
        let links = self.arm.link_transforms(&sample.joints);
        let mut transforms = Vec::with_capacity(JOINT_COUNT);
        let mut parent = BASE_FRAME;
        for (index, (link, name)) in links.iter().zip(LINK_FRAME_NAMES).enumerate() {
            // The DH chain's end is the UR description's `tool0`.
            let name = if index == JOINT_COUNT - 1 { TOOL_FRAME } else { name };
            transforms.push(transform_stamped(nanos, parent, name, link));
            parent = name;
        }
        self.write(TF_TOPIC, schema::TF_MESSAGE, nanos, &msg::TfMessage { transforms })?;
        let joints = msg::JointState {
            header: stamp(nanos, ""),
            name: JOINT_NAMES.iter().map(|n| (*n).to_owned()).collect(),
            position: sample.joints.to_vec(),
            velocity: sample.joint_velocities.to_vec(),
            effort: Vec::new(),
        };
        self.write(JOINT_STATES_TOPIC, schema::JOINT_STATE, nanos, &joints)
    }

    /// Writes one complete set in time order (arm motion; per view the image, calibration,
    /// ground truth and capture event), then ends the chunk and flushes it, as
    /// [`crate::log::LogWriter::write_set`] does.
    pub fn write_set(
        &mut self,
        set: &CapturedSet,
        flange_from_camera: Option<&Isometry3<f64>>,
    ) -> Result<(), LogError> {
        let first = set
            .motion
            .first()
            .map(|s| s.time_nanos)
            .into_iter()
            .chain(set.views.first().map(|v| v.capture_time_nanos))
            .min()
            .unwrap_or(0);
        self.write_static(first, flange_from_camera)?;
        let mut motion = set.motion.iter().peekable();
        for view in &set.views {
            while let Some(sample) = motion.next_if(|s| s.time_nanos <= view.capture_time_nanos) {
                self.write_arm_state(sample)?;
            }
            if set.motion.is_empty() {
                let t = view.capture_time_nanos;
                let tf = transform_stamped(t, WORLD_FRAME, OPTICAL_FRAME, &view.world_from_camera);
                self.write(
                    TF_TOPIC,
                    schema::TF_MESSAGE,
                    t,
                    &msg::TfMessage { transforms: vec![tf] },
                )?;
            }
            self.write_view(set, view)?;
        }
        for sample in motion {
            self.write_arm_state(sample)?;
        }
        self.writer.flush().map_err(Self::mcap_error("end of set"))
    }

    fn write_view(&mut self, set: &CapturedSet, view: &CapturedView) -> Result<(), LogError> {
        let t = view.capture_time_nanos;
        let (width, height) = (view.camera.width, view.camera.height);
        let check = |field, actual, per_pixel| crate::log::check_buffer_len(set, view, field, actual, per_pixel);
        check("rgb", view.rgb.len(), 3)?;
        fn image<'a>(
            t: u64,
            (width, height): (u32, u32),
            encoding: &str,
            bytes_per_pixel: u32,
            data: &'a [u8],
        ) -> msg::Image<'a> {
            msg::Image {
                header: stamp(t, OPTICAL_FRAME),
                height,
                width,
                encoding: encoding.to_owned(),
                is_bigendian: 0,
                step: width * bytes_per_pixel,
                data: Cow::Borrowed(data),
            }
        }
        let size = (width, height);
        match self.options.image_format_of() {
            ImageFormat::Raw => self.write(IMAGE_TOPIC, schema::IMAGE, t, &image(t, size, "rgb8", 3, &view.rgb))?,
            ImageFormat::Png => {
                let data = encode_png_rgb8(&view.rgb, width, height, self.options.png_compression()).map_err(|e| {
                    LogError::Encode {
                        topic: IMAGE_TOPIC.into(),
                        reason: e.to_string(),
                    }
                })?;
                let compressed = msg::CompressedImage {
                    header: stamp(t, OPTICAL_FRAME),
                    format: "png".into(),
                    data: Cow::Owned(data),
                };
                self.write(IMAGE_TOPIC, schema::COMPRESSED_IMAGE, t, &compressed)?;
            }
        }
        self.write(
            CAMERA_INFO_TOPIC,
            schema::CAMERA_INFO,
            t,
            &camera_info(&view.camera, t, OPTICAL_FRAME),
        )?;
        let depth = match &view.depth_m {
            Some(depth_m) => {
                check("depth_m", depth_m.len(), 1)?;
                let data: Vec<u8> = depth_m.iter().flat_map(|d| d.to_le_bytes()).collect();
                self.write(DEPTH_TOPIC, schema::IMAGE, t, &image(t, size, DEPTH_ENCODING, 4, &data))?;
                Some(DEPTH_TOPIC.to_owned())
            }
            None => None,
        };
        let surface = match &view.surface_class {
            Some(classes) => {
                check("surface_class", classes.len(), 1)?;
                self.write(
                    SURFACE_TOPIC,
                    schema::IMAGE,
                    t,
                    &image(t, size, SURFACE_ENCODING, 1, classes),
                )?;
                Some(SURFACE_TOPIC.to_owned())
            }
            None => None,
        };
        let event = CaptureEvent {
            image_topic: IMAGE_TOPIC.into(),
            calibration_topic: CAMERA_INFO_TOPIC.into(),
            depth_topic: depth,
            surface_topic: surface,
            ..CaptureEvent::of_view(set, view)
        };
        self.write_json(CAPTURE_EVENTS_TOPIC, t, &event)
    }

    /// Writes the `rosbag2` metadata record and the summary (indexes, statistics, CRCs); returns
    /// the writer and what the bag's `metadata.yaml` says.
    pub fn finish(mut self) -> Result<(W, BagInfo), LogError> {
        let info = self.info();
        let yaml = info.to_yaml();
        // The record holds the body of `metadata.yaml`, without its top key, as rosbag2 writes it.
        let body: String = yaml
            .lines()
            .skip(1)
            .map(|l| format!("{}\n", l.strip_prefix("  ").unwrap_or(l)))
            .collect();
        self.write_metadata(
            ros2::bag::METADATA_RECORD,
            BTreeMap::from([("serialized_metadata".to_owned(), body)]),
        )?;
        self.writer.finish().map_err(Self::mcap_error("summary"))?;
        Ok((self.writer.into_inner(), info))
    }

    /// What the bag holds so far.
    pub fn info(&self) -> BagInfo {
        let (start, end) = self.time_span.unwrap_or((0, 0));
        BagInfo {
            files: vec![FileInfo {
                path: self.file_name.clone(),
                starting_time_nanos: start,
                duration_nanos: end - start,
                message_count: self.topics.iter().map(|t| t.message_count).sum(),
            }],
            topics: self.topics.clone(),
            ros_distro: "jazzy".into(),
        }
    }
}
