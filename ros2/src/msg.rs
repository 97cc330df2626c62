//! The message types, as serde structs with the fields of their `.msg` files in order (CDR has
//! no field names: the order is the format). `uint8[]` fields are byte sequences, borrowed from
//! the payload when decoding; fixed arrays (`float64[9] k`) are Rust arrays (no count on the
//! wire). Type names are the ROS ones; [`crate::schema`] has their definitions.

use std::borrow::Cow;

use serde::{Deserialize, Serialize};

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds (signed).
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Time {
    /// A time from nanoseconds since the Unix epoch (seconds saturate at `i32::MAX`, 2038).
    pub fn from_nanos(nanos: u64) -> Self {
        Self {
            sec: i32::try_from(nanos / 1_000_000_000).unwrap_or(i32::MAX),
            nanosec: (nanos % 1_000_000_000) as u32,
        }
    }

    /// Nanoseconds since the Unix epoch (`None` before it).
    pub fn nanos(&self) -> Option<u64> {
        let sec = u64::try_from(self.sec).ok()?;
        Some(sec * 1_000_000_000 + u64::from(self.nanosec))
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time (images) or the time the data refers to.
    pub stamp: Time,
    /// The frame the data is in (an optical frame for images).
    pub frame_id: String,
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Image<'a> {
    /// Stamp (acquisition time) and optical frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding (`rgb8`, `bgr8`, `mono8`, `mono16`, `32FC1`, …).
    pub encoding: String,
    /// Whether multi-byte pixels are big-endian.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// `step × height` bytes.
    #[serde(borrow, with = "serde_bytes")]
    pub data: Cow<'a, [u8]>,
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage<'a> {
    /// Stamp and optical frame.
    pub header: Header,
    /// `jpeg`, `png`, or image_transport's `rgb8; jpeg compressed bgr8`.
    pub format: String,
    /// The encoded image.
    #[serde(borrow, with = "serde_bytes")]
    pub data: Cow<'a, [u8]>,
}

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    /// Left column.
    pub x_offset: u32,
    /// Top row.
    pub y_offset: u32,
    /// Rows (0: the full image).
    pub height: u32,
    /// Columns (0: the full image).
    pub width: u32,
    /// Whether the region should be rectified.
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Stamp and optical frame.
    pub header: Header,
    /// Rows of the calibrated image.
    pub height: u32,
    /// Columns of the calibrated image.
    pub width: u32,
    /// `plumb_bob`, `rational_polynomial`, `equidistant`, …
    pub distortion_model: String,
    /// Distortion coefficients (k1, k2, t1, t2, k3[, k4, k5, k6]).
    pub d: Vec<f64>,
    /// Intrinsics of the raw image, row-major 3×3.
    pub k: [f64; 9],
    /// Rectification rotation, row-major 3×3.
    pub r: [f64; 9],
    /// Projection of the rectified image, row-major 3×4.
    pub p: [f64; 12],
    /// Horizontal binning (0 or 1: none).
    pub binning_x: u32,
    /// Vertical binning.
    pub binning_y: u32,
    /// Region of interest (all zero: the full image).
    pub roi: RegionOfInterest,
}

/// `geometry_msgs/msg/Vector3`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

/// `geometry_msgs/msg/Transform`: `parent_from_child`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation (m).
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`: `header.frame_id` is the parent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Stamp and parent frame.
    pub header: Header,
    /// Child frame.
    pub child_frame_id: String,
    /// `parent_from_child`.
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage` (`/tf`, `/tf_static`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// `sensor_msgs/msg/JointState`: joints by name (the order is not guaranteed).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    /// Stamp.
    pub header: Header,
    /// Joint names.
    pub name: Vec<String>,
    /// Positions (rad), one per name or empty.
    pub position: Vec<f64>,
    /// Velocities (rad/s), one per name or empty.
    pub velocity: Vec<f64>,
    /// Efforts, one per name or empty.
    pub effort: Vec<f64>,
}

/// `std_msgs/msg/String`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringMessage {
    /// The text.
    pub data: String,
}

/// `stereo_msgs/msg/DisparityImage`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DisparityImage<'a> {
    /// Stamp and optical frame.
    pub header: Header,
    /// `32FC1` disparities.
    #[serde(borrow)]
    pub image: Image<'a>,
    /// Focal length (px).
    pub f: f32,
    /// Baseline (m).
    pub t: f32,
    /// The region where disparities are valid.
    pub valid_window: RegionOfInterest,
    /// Smallest disparity searched.
    pub min_disparity: f32,
    /// Largest disparity searched.
    pub max_disparity: f32,
    /// Smallest disparity step (sub-pixel resolution).
    pub delta_d: f32,
}

/// `sensor_msgs/msg/PointField`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointField {
    /// Name (`x`, `y`, `z`, `rgb`, …).
    pub name: String,
    /// Byte offset in a point.
    pub offset: u32,
    /// Data type (7 = FLOAT32).
    pub datatype: u8,
    /// Elements.
    pub count: u32,
}

/// `PointField.datatype` of a float32.
pub const POINT_FIELD_FLOAT32: u8 = 7;

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2<'a> {
    /// Stamp and frame.
    pub header: Header,
    /// Rows (1: unordered).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// Fields of a point.
    pub fields: Vec<PointField>,
    /// Byte order of the data.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    #[serde(borrow, with = "serde_bytes")]
    pub data: Cow<'a, [u8]>,
    /// Whether every point is finite.
    pub is_dense: bool,
}

#[cfg(test)]
mod tests {
    //! Golden payloads written by the `rosbags` library (`tests/python/make_ros2_fixtures.py`):
    //! each decodes to the values that script wrote and encodes back to the same bytes.

    use std::path::PathBuf;

    use serde::Serialize;

    use super::*;
    use crate::cdr::{decode, encode};

    fn golden(name: &str) -> Vec<u8> {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../tests/corpus/ros2")
            .join(name);
        std::fs::read(&path).unwrap_or_else(|e| panic!("the golden payload {} is missing: {e}", path.display()))
    }

    fn same_bytes<T: Serialize>(name: &str, bytes: &[u8], message: &T) {
        let again = encode(message).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(again, bytes, "{name}: our encoding differs from rosbags'");
    }

    fn stamp() -> Header {
        Header {
            stamp: Time {
                sec: 1_700_000_000,
                nanosec: 123_456_789,
            },
            frame_id: "camera_color_optical_frame".into(),
        }
    }

    #[test]
    fn images_decode_and_encode_byte_for_byte() {
        let bytes = golden("image_rgb8.cdr");
        let image: Image = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(image.header, stamp());
        assert_eq!(
            (image.width, image.height, image.step, image.encoding.as_str()),
            (3, 2, 9, "rgb8")
        );
        assert_eq!(image.data.as_ref(), (0..18).collect::<Vec<u8>>().as_slice());
        assert!(
            matches!(image.data, Cow::Borrowed(_)),
            "image data is copied when decoding"
        );
        same_bytes("image_rgb8", &bytes, &image);

        let bytes = golden("image_32fc1.cdr");
        let depth: Image = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        let values: Vec<f32> = depth
            .data
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        assert_eq!(values, [0.5, 1.25, 0.0, 2.0]);
        same_bytes("image_32fc1", &bytes, &depth);

        let bytes = golden("compressed_image.cdr");
        let compressed: CompressedImage = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(compressed.format, "rgb8; jpeg compressed bgr8");
        assert_eq!(compressed.data.as_ref(), &[0xFF, 0xD8, 0xFF, 0xD9]);
        same_bytes("compressed_image", &bytes, &compressed);
    }

    #[test]
    fn camera_info_decodes_in_both_byte_orders() {
        let bytes = golden("camera_info.cdr");
        let info: CameraInfo = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(info.header, stamp());
        assert_eq!(
            (info.width, info.height, info.distortion_model.as_str()),
            (640, 480, "plumb_bob")
        );
        assert_eq!(info.d, [0.1, -0.2, 0.001, 0.002, 0.0]);
        assert_eq!(info.k, [600.0, 0.0, 320.5, 0.0, 601.0, 240.25, 0.0, 0.0, 1.0]);
        assert_eq!(info.p[2], 320.5);
        same_bytes("camera_info", &bytes, &info);
        let big: CameraInfo = decode(&golden("camera_info_be.cdr")).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(big, info);
        assert_eq!(
            crate::cdr::encode_with(&info, crate::Endianness::Big).unwrap_or_else(|e| panic!("{e}")),
            golden("camera_info_be.cdr")
        );
    }

    #[test]
    fn transforms_joint_states_and_strings_decode_byte_for_byte() {
        let bytes = golden("tf.cdr");
        let tf: TfMessage = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(tf.transforms.len(), 2);
        assert_eq!(tf.transforms[1].header.frame_id, "tool0");
        assert_eq!(tf.transforms[1].child_frame_id, "camera_color_optical_frame");
        assert_eq!(tf.transforms[1].transform.translation.y, 0.05);
        assert_eq!(tf.transforms[1].transform.rotation.w, 0.5);
        same_bytes("tf", &bytes, &tf);

        let bytes = golden("joint_state.cdr");
        let joints: JointState = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            joints.name,
            ["elbow_joint", "shoulder_lift_joint", "shoulder_pan_joint"]
        );
        assert_eq!(joints.position, [1.5, -1.25, 0.5]);
        assert!(joints.effort.is_empty());
        same_bytes("joint_state", &bytes, &joints);

        let bytes = golden("string.cdr");
        let text: StringMessage = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(text.data, r#"{"set_index": 0}"#);
        same_bytes("string", &bytes, &text);
    }

    #[test]
    fn result_messages_encode_byte_for_byte() {
        let bytes = golden("disparity_image.cdr");
        let disparity: DisparityImage = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((disparity.f, disparity.t, disparity.max_disparity), (600.0, 0.02, 64.0));
        assert_eq!(disparity.image.encoding, "32FC1");
        same_bytes("disparity_image", &bytes, &disparity);

        let bytes = golden("point_cloud2.cdr");
        let cloud: PointCloud2 = decode(&bytes).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(cloud.fields.len(), 3);
        assert_eq!(cloud.fields[2].name, "z");
        assert_eq!(cloud.fields[2].datatype, POINT_FIELD_FLOAT32);
        assert_eq!(cloud.data.len(), 24);
        same_bytes("point_cloud2", &bytes, &cloud);
    }
}
