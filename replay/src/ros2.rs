//! ROS 2 messages in a log (a rosbag2 MCAP file: `ros2msg` schemas, CDR payloads), translated
//! as they are read into the Foxglove messages the rest of the reader handles, so that a bag
//! takes the path of our own logs (capture events, when it has them: bags that `record
//! --format ros2` writes) or of foreign logs (sets from the camera poses, `crate::foreign`).
//!
//! | ROS 2 type | becomes |
//! |---|---|
//! | `sensor_msgs/msg/Image` rgb8, bgr8, rgba8, bgra8, mono8, 8UC1, 8UC3 | `foxglove.RawImage` of the same encoding |
//! | `sensor_msgs/msg/Image` mono16, 16UC1 (either byte order) | `RawImage` mono8: the topic's first image sets a shift that brings its largest value under 256, kept for the topic so every view of it is scaled alike |
//! | `sensor_msgs/msg/Image` 32FC1 | `RawImage` 32FC1, little-endian (ground truth) |
//! | `sensor_msgs/msg/CompressedImage` PNG or JPEG (told by their magic bytes, whatever `format` says: `rgb8; jpeg compressed bgr8`) | `foxglove.CompressedImage` png, or a decoded JPEG as `RawImage` rgb8 |
//! | `sensor_msgs/msg/CameraInfo` | `foxglove.CameraCalibration` (K, D, R, P, model) |
//! | `tf2_msgs/msg/TFMessage` | `foxglove.FrameTransforms` (each transform's `header.stamp` kept; `/tf_static` edges are valid at all times) |
//! | `sensor_msgs/msg/JointState` | `foxglove.JointStates` (by name) |
//! | `std_msgs/msg/String` on `/capture/events` or `/capture/plan` | the JSON it carries |
//!
//! Every other type is left out and counted ([`Ros2Translator::ignored`]).

use std::collections::{BTreeMap, HashMap};

use bytes::Bytes;
use foxglove::messages::{
    CameraCalibration, CompressedImage, FrameTransform, FrameTransforms, JointState as FoxgloveJoint, JointStates,
    Quaternion, RawImage, Timestamp, Vector3,
};
use ros2::msg;

use crate::ReplayError;

/// Schema names (and their Foxglove counterparts) this module reads.
const IMAGE: &str = "sensor_msgs/msg/Image";
const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";
const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";
const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";
const JOINT_STATE: &str = "sensor_msgs/msg/JointState";
const STRING: &str = "std_msgs/msg/String";

/// The Foxglove schema of joint states (what `crate::foreign` reads for motion).
pub const JOINT_STATES_SCHEMA: &str = "foxglove.JointStates";

/// Whether a ROS 2 type is an image (raw or compressed).
pub fn is_image_type(schema: &str) -> bool {
    matches!(schema, IMAGE | COMPRESSED_IMAGE)
}

/// A `foxglove.RawImage` with its pixels: the fields encoded by prost, then the data field
/// appended (field order does not matter to a protobuf reader), so the pixels are copied once.
fn raw_image_with(header: &RawImage, data: &[u8]) -> Vec<u8> {
    use prost::Message as _;
    let mut out = Vec::with_capacity(header.encoded_len() + data.len() + 16);
    header.encode_raw(&mut out);
    prost::encoding::encode_key(6, prost::encoding::WireType::LengthDelimited, &mut out);
    prost::encoding::encode_varint(data.len() as u64, &mut out);
    out.extend_from_slice(data);
    out
}

/// Whether a schema name is a ROS 2 type (`pkg/msg/Type`).
pub fn is_ros2_schema(schema: &str) -> bool {
    schema.contains("/msg/")
}

/// What one ROS 2 message became.
#[derive(Debug, PartialEq)]
pub enum Translated {
    /// A Foxglove message (protobuf bytes) of the named schema.
    Foxglove {
        /// The Foxglove schema name.
        schema: &'static str,
        /// The encoded message.
        data: Vec<u8>,
    },
    /// The text of a `std_msgs/msg/String` (JSON for our events and plans).
    Text(Vec<u8>),
    /// A type that is not read (counted).
    Ignored,
}

/// Translates the ROS 2 messages of one log, keeping what must stay the same across its
/// messages (the 16-bit shift of each topic) and what it left out.
#[derive(Debug, Default)]
pub struct Ros2Translator {
    mono16_shift: HashMap<String, u32>,
    ignored: BTreeMap<(String, String), usize>,
}

/// The error of a payload that does not decode as its topic's type.
fn cdr_error<'a>(topic: &'a str, schema: &'a str) -> impl Fn(ros2::CdrError) -> ReplayError + 'a {
    move |e| ReplayError::Decode {
        set: 0,
        topic: topic.to_owned(),
        schema: "CDR",
        reason: format!("{schema}: {e}"),
    }
}

fn timestamp(time: &msg::Time) -> Option<Timestamp> {
    // A stamp before the epoch (negative seconds) cannot be a capture time: no stamp.
    u32::try_from(time.sec)
        .ok()
        .map(|sec| Timestamp::new(sec, time.nanosec))
}

fn encode<M: prost::Message>(schema: &'static str, message: &M) -> Translated {
    Translated::Foxglove {
        schema,
        data: message.encode_to_vec(),
    }
}

/// `sensor_msgs/msg/Image` encodings read as views (besides mono16, read as mono8).
const VIEW_ENCODINGS: [&str; 7] = ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC1", "8UC3"];

impl Ros2Translator {
    /// Counts a message left out under `kind` (its type, and why when it is not the type).
    fn ignore(&mut self, topic: &str, kind: &str) -> Translated {
        *self.ignored.entry((topic.to_owned(), kind.to_owned())).or_default() += 1;
        Translated::Ignored
    }

    /// Counts a message that did not translate (an encoding not read, a corrupt payload): it is
    /// left out and listed, so that one bad topic does not stop the reading of the others.
    pub fn unreadable(&mut self, topic: &str, schema: &str, error: &ReplayError) {
        self.ignore(topic, &format!("{schema}: {error}"));
    }

    /// The (topic, type) pairs left out, with their message counts.
    pub fn ignored(&self) -> &BTreeMap<(String, String), usize> {
        &self.ignored
    }

    /// What an image message is, without its pixels (a `RawImage` or `CompressedImage` whose
    /// data is empty): for a stream whose pixels are read again only for the frames kept.
    pub fn translate_header(&mut self, topic: &str, schema: &str, data: &[u8]) -> Result<Translated, ReplayError> {
        let cdr = cdr_error(topic, schema);
        Ok(match schema {
            IMAGE => {
                let image: msg::Image = ros2::decode(data).map_err(cdr)?;
                let encoding = match image.encoding.as_str() {
                    "mono16" => "mono8".to_owned(),
                    other if VIEW_ENCODINGS.contains(&other) || other == "32FC1" => other.to_owned(),
                    // Not a view (16UC1 depth) or not read: left out or refused as the whole
                    // translation does, so that both list it alike.
                    _ => return self.translate(topic, schema, data),
                };
                encode(
                    "foxglove.RawImage",
                    &RawImage {
                        timestamp: timestamp(&image.header.stamp),
                        frame_id: image.header.frame_id,
                        width: image.width,
                        height: image.height,
                        encoding,
                        step: image.step,
                        data: Bytes::new(),
                    },
                )
            }
            COMPRESSED_IMAGE => {
                let image: msg::CompressedImage = ros2::decode(data).map_err(cdr)?;
                if image.data.starts_with(&[0x89, b'P', b'N', b'G']) {
                    encode(
                        "foxglove.CompressedImage",
                        &CompressedImage {
                            timestamp: timestamp(&image.header.stamp),
                            frame_id: image.header.frame_id,
                            data: Bytes::new(),
                            format: "png".into(),
                        },
                    )
                } else if !image.data.starts_with(&[0xFF, 0xD8]) {
                    // Neither PNG nor JPEG: refused as the whole translation refuses it.
                    return self.translate(topic, schema, data);
                } else {
                    // A JPEG: decoded when kept; its size is not needed to place it.
                    encode(
                        "foxglove.RawImage",
                        &RawImage {
                            timestamp: timestamp(&image.header.stamp),
                            frame_id: image.header.frame_id,
                            width: 1,
                            height: 1,
                            encoding: "rgb8".into(),
                            step: 3,
                            data: Bytes::new(),
                        },
                    )
                }
            }
            _ => self.translate(topic, schema, data)?,
        })
    }

    /// Translates one message of `topic` whose schema is the ROS 2 type `schema`.
    pub fn translate(&mut self, topic: &str, schema: &str, data: &[u8]) -> Result<Translated, ReplayError> {
        let cdr = cdr_error(topic, schema);
        Ok(match schema {
            IMAGE => {
                let image: msg::Image = ros2::decode(data).map_err(cdr)?;
                self.image(topic, &image)?
            }
            COMPRESSED_IMAGE => {
                let image: msg::CompressedImage = ros2::decode(data).map_err(cdr)?;
                compressed(topic, image)?
            }
            CAMERA_INFO => {
                let info: msg::CameraInfo = ros2::decode(data).map_err(cdr)?;
                encode(
                    "foxglove.CameraCalibration",
                    &CameraCalibration {
                        timestamp: timestamp(&info.header.stamp),
                        frame_id: info.header.frame_id,
                        width: info.width,
                        height: info.height,
                        distortion_model: info.distortion_model,
                        d: info.d,
                        k: info.k.to_vec(),
                        r: info.r.to_vec(),
                        p: info.p.to_vec(),
                    },
                )
            }
            TF_MESSAGE => {
                let tf: msg::TfMessage = ros2::decode(data).map_err(cdr)?;
                let transforms = tf
                    .transforms
                    .into_iter()
                    .map(|t| {
                        let (v, q) = (t.transform.translation, t.transform.rotation);
                        FrameTransform {
                            timestamp: timestamp(&t.header.stamp),
                            parent_frame_id: t.header.frame_id,
                            child_frame_id: t.child_frame_id,
                            translation: Some(Vector3 { x: v.x, y: v.y, z: v.z }),
                            rotation: Some(Quaternion {
                                x: q.x,
                                y: q.y,
                                z: q.z,
                                w: q.w,
                            }),
                        }
                    })
                    .collect();
                encode(crate::foreign::TRANSFORMS_SCHEMA, &FrameTransforms { transforms })
            }
            JOINT_STATE => {
                let state: msg::JointState = ros2::decode(data).map_err(cdr)?;
                let joints = state
                    .name
                    .iter()
                    .enumerate()
                    .map(|(i, name)| FoxgloveJoint {
                        name: name.clone(),
                        position: state.position.get(i).copied(),
                        velocity: state.velocity.get(i).copied(),
                        acceleration: None,
                        effort: state.effort.get(i).copied(),
                    })
                    .collect();
                encode(
                    JOINT_STATES_SCHEMA,
                    &JointStates {
                        timestamp: timestamp(&state.header.stamp),
                        joints,
                    },
                )
            }
            STRING => {
                let text: msg::StringMessage = ros2::decode(data).map_err(cdr)?;
                Translated::Text(text.data.into_bytes())
            }
            _ => {
                *self.ignored.entry((topic.to_owned(), schema.to_owned())).or_default() += 1;
                Translated::Ignored
            }
        })
    }

    fn image(&mut self, topic: &str, image: &msg::Image<'_>) -> Result<Translated, ReplayError> {
        let bad = |value: String| ReplayError::BadField {
            set: 0,
            topic: topic.to_owned(),
            field: "data",
            value,
        };
        let (w, h, step) = (image.width as usize, image.height as usize, image.step as usize);
        let raw = |encoding: &str, step: u32, data: &[u8]| {
            let header = RawImage {
                timestamp: timestamp(&image.header.stamp),
                frame_id: image.header.frame_id.clone(),
                width: image.width,
                height: image.height,
                encoding: encoding.to_owned(),
                step,
                data: Bytes::new(),
            };
            Translated::Foxglove {
                schema: "foxglove.RawImage",
                data: raw_image_with(&header, data),
            }
        };
        let rows = |bytes_per_pixel: usize| -> Result<Vec<&[u8]>, ReplayError> {
            let row = w.saturating_mul(bytes_per_pixel);
            let needed = step.saturating_mul(h.saturating_sub(1)).saturating_add(row);
            if step < row || image.data.len() < needed {
                return Err(bad(format!(
                    "{} bytes for {w}x{h} {} with step {step}",
                    image.data.len(),
                    image.encoding
                )));
            }
            Ok((0..h).map(|y| &image.data[y * step..y * step + row]).collect())
        };
        Ok(match image.encoding.as_str() {
            encoding if VIEW_ENCODINGS.contains(&encoding) => raw(&image.encoding, image.step, &image.data),
            // REP 118 depth (a RealSense's aligned depth): not a view.
            "16UC1" => self.ignore(topic, "sensor_msgs/msg/Image (16UC1 depth)"),
            "mono16" => {
                let big = image.is_bigendian != 0;
                let values: Vec<u16> = rows(2)?
                    .into_iter()
                    .flat_map(|row| {
                        row.chunks_exact(2).map(move |b| {
                            if big {
                                u16::from_be_bytes([b[0], b[1]])
                            } else {
                                u16::from_le_bytes([b[0], b[1]])
                            }
                        })
                    })
                    .collect();
                let shift = *self.mono16_shift.entry(topic.to_owned()).or_insert_with(|| {
                    let max = values.iter().copied().max().unwrap_or(0);
                    (16 - max.leading_zeros()).saturating_sub(8)
                });
                let grey: Vec<u8> = values.iter().map(|v| (v >> shift).min(255) as u8).collect();
                raw("mono8", image.width, &grey)
            }
            // Little-endian floats in whole rows: as they are.
            "32FC1" if image.is_bigendian == 0 && step == w * 4 && image.data.len() == step * h => {
                raw("32FC1", image.step, &image.data)
            }
            "32FC1" => {
                let big = image.is_bigendian != 0;
                let data = rows(4)?
                    .into_iter()
                    .flat_map(|row| {
                        row.chunks_exact(4).flat_map(move |b| {
                            let v = if big {
                                f32::from_be_bytes([b[0], b[1], b[2], b[3]])
                            } else {
                                f32::from_le_bytes([b[0], b[1], b[2], b[3]])
                            };
                            v.to_le_bytes()
                        })
                    })
                    .collect::<Vec<u8>>();
                raw("32FC1", image.width * 4, &data)
            }
            other => {
                return Err(ReplayError::UnknownEncoding {
                    set: 0,
                    topic: topic.to_owned(),
                    encoding: other.to_owned(),
                });
            }
        })
    }
}

/// A compressed image by its magic bytes: PNG stays compressed, JPEG is decoded to rgb8.
fn compressed(topic: &str, image: msg::CompressedImage<'_>) -> Result<Translated, ReplayError> {
    const PNG_MAGIC: &[u8] = &[0x89, b'P', b'N', b'G'];
    const JPEG_MAGIC: &[u8] = &[0xFF, 0xD8];
    let stamp = timestamp(&image.header.stamp);
    if image.data.starts_with(PNG_MAGIC) {
        return Ok(encode(
            "foxglove.CompressedImage",
            &CompressedImage {
                timestamp: stamp,
                frame_id: image.header.frame_id,
                data: Bytes::from(image.data.into_owned()),
                format: "png".into(),
            },
        ));
    }
    if image.data.starts_with(JPEG_MAGIC) {
        let decoded = image::load_from_memory_with_format(&image.data, image::ImageFormat::Jpeg).map_err(|e| {
            ReplayError::Decode {
                set: 0,
                topic: topic.to_owned(),
                schema: "JPEG",
                reason: e.to_string(),
            }
        })?;
        let rgb = decoded.to_rgb8();
        let (width, height) = rgb.dimensions();
        return Ok(encode(
            "foxglove.RawImage",
            &RawImage {
                timestamp: stamp,
                frame_id: image.header.frame_id,
                width,
                height,
                encoding: "rgb8".into(),
                step: width * 3,
                data: Bytes::from(rgb.into_raw()),
            },
        ));
    }
    Err(ReplayError::UnknownEncoding {
        set: 0,
        topic: topic.to_owned(),
        encoding: format!(
            "{}, a CompressedImage whose data is neither PNG nor JPEG: it starts with {:02x?}",
            image.format,
            &image.data[..image.data.len().min(4)]
        ),
    })
}

#[cfg(test)]
mod tests {
    use std::borrow::Cow;

    use super::*;

    fn image(encoding: &str, width: u32, step: u32, big: bool, data: Vec<u8>) -> Vec<u8> {
        let message = msg::Image {
            header: msg::Header {
                stamp: msg::Time { sec: 5, nanosec: 7 },
                frame_id: "camera_optical".into(),
            },
            height: 1,
            width,
            encoding: encoding.into(),
            is_bigendian: u8::from(big),
            step,
            data: Cow::Owned(data),
        };
        ros2::encode(&message).unwrap_or_else(|e| panic!("{e}"))
    }

    fn raw(translated: Translated) -> RawImage {
        match translated {
            Translated::Foxglove { schema, data } => {
                assert_eq!(schema, "foxglove.RawImage");
                prost::Message::decode(data.as_slice()).unwrap_or_else(|e| panic!("{e}"))
            }
            other => panic!("not an image: {other:?}"),
        }
    }

    #[test]
    fn sixteen_bit_images_keep_one_shift_per_topic_in_either_byte_order() {
        let mut translator = Ros2Translator::default();
        // 12-bit values: shift 4 from the first image, kept for the second.
        let first = image(
            "mono16",
            2,
            4,
            false,
            [4095u16, 16].iter().flat_map(|v| v.to_le_bytes()).collect(),
        );
        let out = raw(translator
            .translate("/cam", IMAGE, &first)
            .unwrap_or_else(|e| panic!("{e}")));
        assert_eq!((out.encoding.as_str(), out.data.as_ref()), ("mono8", &[255u8, 1][..]));
        let second = image(
            "mono16",
            2,
            4,
            true,
            [160u16, 32].iter().flat_map(|v| v.to_be_bytes()).collect(),
        );
        let out = raw(translator
            .translate("/cam", IMAGE, &second)
            .unwrap_or_else(|e| panic!("{e}")));
        assert_eq!(out.data.as_ref(), &[10u8, 2]);
        assert_eq!(out.timestamp, Some(Timestamp::new(5, 7)));
    }

    #[test]
    fn big_endian_depth_becomes_little_endian_and_short_data_is_an_error() {
        let mut translator = Ros2Translator::default();
        let data = image("32FC1", 1, 4, true, 1.5f32.to_be_bytes().to_vec());
        let out = raw(translator
            .translate("/depth", IMAGE, &data)
            .unwrap_or_else(|e| panic!("{e}")));
        assert_eq!(out.data.as_ref(), &1.5f32.to_le_bytes());
        let short = image("mono16", 2, 4, false, vec![0; 3]);
        let error = translator
            .translate("/cam", IMAGE, &short)
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("/cam") && error.contains("3 bytes for 2x1 mono16"),
            "{error}"
        );
        let odd = image("yuv422", 2, 4, false, vec![0; 4]);
        let error = translator
            .translate("/cam", IMAGE, &odd)
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(error.contains("yuv422"), "{error}");
    }

    #[test]
    fn unknown_types_are_counted_and_compressed_images_are_told_by_their_bytes() {
        let mut translator = Ros2Translator::default();
        assert_eq!(
            translator
                .translate("/odom", "nav_msgs/msg/Odometry", &[0, 1, 0, 0])
                .unwrap_or_else(|e| panic!("{e}")),
            Translated::Ignored
        );
        assert_eq!(
            translator
                .ignored()
                .get(&("/odom".into(), "nav_msgs/msg/Odometry".into())),
            Some(&1)
        );
        let mut png = Vec::new();
        {
            let mut encoder = png::Encoder::new(&mut png, 1, 1);
            encoder.set_color(png::ColorType::Rgb);
            let mut writer = encoder.write_header().unwrap_or_else(|e| panic!("{e}"));
            writer.write_image_data(&[1, 2, 3]).unwrap_or_else(|e| panic!("{e}"));
        }
        let message = msg::CompressedImage {
            header: msg::Header::default(),
            format: "rgb8; jpeg compressed bgr8".into(),
            data: Cow::Owned(png),
        };
        let bytes = ros2::encode(&message).unwrap_or_else(|e| panic!("{e}"));
        match translator
            .translate("/cam/compressed", COMPRESSED_IMAGE, &bytes)
            .unwrap_or_else(|e| panic!("{e}"))
        {
            Translated::Foxglove { schema, .. } => assert_eq!(schema, "foxglove.CompressedImage"),
            other => panic!("{other:?}"),
        }
        let message = msg::CompressedImage {
            header: msg::Header::default(),
            format: "h264".into(),
            data: Cow::Owned(vec![0, 0, 0, 1]),
        };
        let bytes = ros2::encode(&message).unwrap_or_else(|e| panic!("{e}"));
        let error = translator
            .translate("/cam/compressed", COMPRESSED_IMAGE, &bytes)
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("h264") && error.contains("neither PNG nor JPEG"),
            "{error}"
        );
    }
}
