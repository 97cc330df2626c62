//! Logs without capture events (foreign logs: images, calibrations and `/tf` from another
//! recorder): view sets are inferred from the camera poses. Consecutive images whose cameras keep
//! one orientation and stay close to the first of them form a set; the medoid view is the
//! reference; the baseline is the distance to its nearest neighbour; each view's grid offset is
//! its position in the reference camera frame in baselines, which names its role.

use std::collections::HashMap;

use foxglove::messages::{CameraCalibration, CompressedImage, FrameTransforms, RawImage};
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

/// Whether a schema is one foreign-log inference needs.
pub fn is_foreign_input(schema: &str) -> bool {
    matches!(
        schema,
        TRANSFORMS_SCHEMA | RAW_IMAGE_SCHEMA | COMPRESSED_IMAGE_SCHEMA | CALIBRATION_SCHEMA
    )
}

/// Time-stamped transforms, parent ← child.
#[derive(Debug, Default)]
struct TfBuffer {
    /// child → (time, parent, parent_from_child), sorted by time.
    edges: HashMap<String, Vec<(u64, String, Isometry3<f64>)>>,
    /// The first transform whose rotation is not one (reported when the poses are needed).
    invalid: Option<ReplayError>,
}

/// Norm below which a quaternion is not a rotation (the protobuf default is all zeros).
const MIN_QUATERNION_NORM: f64 = 1e-6;

impl TfBuffer {
    /// Adds the transforms of one message. A transform without a rotation field is a pure
    /// translation (identity rotation); a rotation that is zero or not finite is kept out and
    /// remembered as an error naming the topic and frames.
    fn add(&mut self, topic: &str, time: u64, message: &FrameTransforms) {
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
            let stamp = t.timestamp.map_or(time, |s| s.total_nanos());
            self.edges
                .entry(t.child_frame_id.clone())
                .or_default()
                .push((stamp, t.parent_frame_id.clone(), pose));
        }
    }

    fn sort(&mut self) {
        for samples in self.edges.values_mut() {
            samples.sort_by_key(|s| s.0);
        }
    }

    /// `root_from_frame` at `time`: each edge interpolated between its samples around `time`.
    fn root_from(&self, frame: &str, time: u64) -> Option<Isometry3<f64>> {
        let mut pose = Isometry3::identity();
        let mut child = frame.to_owned();
        for _ in 0..64 {
            let Some(samples) = self.edges.get(&child) else {
                return Some(pose);
            };
            let after = samples.partition_point(|s| s.0 < time);
            let (parent, edge) = match (after.checked_sub(1).map(|i| &samples[i]), samples.get(after)) {
                (Some(a), Some(b)) if b.0 > a.0 => {
                    let t = (time - a.0) as f64 / (b.0 - a.0) as f64;
                    let translation = a.2.translation.vector.lerp(&b.2.translation.vector, t);
                    let rotation = a.2.rotation.slerp(&b.2.rotation, t);
                    (a.1.clone(), Isometry3::from_parts(translation.into(), rotation))
                }
                (Some(a), _) => (a.1.clone(), a.2),
                (None, Some(b)) => (b.1.clone(), b.2),
                (None, None) => return None,
            };
            pose = edge * pose;
            child = parent;
        }
        None
    }
}

/// What a scan keeps for inference.
#[derive(Debug, Default)]
pub struct ForeignMessages {
    images: Vec<(String, u64)>,
    calibrations: Vec<(String, u64)>,
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
            RAW_IMAGE_SCHEMA | COMPRESSED_IMAGE_SCHEMA => {
                self.images.push((topic.to_owned(), time));
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
        !self.images.is_empty()
    }

    /// Infers the view sets.
    pub fn infer_sets(mut self, payloads: &HashMap<(String, u64), Vec<u8>>) -> Result<Vec<ViewSet>, ReplayError> {
        if let Some(error) = self.tf.invalid.take() {
            return Err(error);
        }
        self.tf.sort();
        let payload = |key: &(String, u64)| payloads.get(key).map(Vec::as_slice).unwrap_or_default();
        // Calibrations by frame id (the latest wins).
        let mut calibrations: HashMap<String, CameraCalibration> = HashMap::new();
        for key in &self.calibrations {
            if let Ok(c) = <CameraCalibration as prost::Message>::decode(payload(key)) {
                calibrations.insert(c.frame_id.clone(), c);
            }
        }
        // Colour/grey images with a pose; one per (frame, time), preferring colour.
        let mut views: Vec<(u64, String, View)> = Vec::new();
        self.images.sort_by_key(|(topic, time)| (*time, topic.clone()));
        for key in &self.images {
            let data = payload(key);
            let frame_id = match <RawImage as prost::Message>::decode(data) {
                Ok(raw) if raw.width > 0 => {
                    if !IMAGE_ENCODINGS.contains(&raw.encoding.as_str()) {
                        continue;
                    }
                    raw.frame_id
                }
                _ => match <CompressedImage as prost::Message>::decode(data) {
                    Ok(c) if c.format.eq_ignore_ascii_case("png") => c.frame_id,
                    _ => continue,
                },
            };
            let time = key.1;
            if let Some(existing) = views.iter_mut().find(|(t, f, _)| *t == time && *f == frame_id) {
                // A grey mask or second stream of the same camera at the same time: keep colour.
                if existing.2.rgb.chunks_exact(3).all(|p| p[0] == p[1] && p[1] == p[2]) {
                    let (w, h, rgb) = decode_rgb(0, &key.0, data)?;
                    if (w, h) == (existing.2.camera.width, existing.2.camera.height) {
                        existing.2.rgb = rgb;
                    }
                }
                continue;
            }
            let calibration = calibrations.get(&frame_id).ok_or_else(|| ReplayError::BadField {
                set: 0,
                topic: key.0.clone(),
                field: "frame_id",
                value: format!("'{frame_id}' has no foxglove.CameraCalibration in the log"),
            })?;
            let pose = self
                .tf
                .root_from(&frame_id, time)
                .ok_or_else(|| ReplayError::BadField {
                    set: 0,
                    topic: key.0.clone(),
                    field: "frame_id",
                    value: format!("no transform reaches '{frame_id}' at log time {time}"),
                })?;
            let (width, height, rgb) = decode_rgb(0, &key.0, data)?;
            let camera = PinholeCamera {
                width,
                height,
                fx: calibration.k.first().copied().unwrap_or(0.0),
                fy: calibration.k.get(4).copied().unwrap_or(0.0),
                cx: calibration.k.get(2).copied().unwrap_or(0.0),
                cy: calibration.k.get(5).copied().unwrap_or(0.0),
            };
            views.push((
                time,
                frame_id,
                View {
                    role: String::new(),
                    offset: [0, 0],
                    camera,
                    rgb,
                    world_from_camera: pose,
                    true_world_from_camera: None,
                    capture_time_nanos: time,
                    joints: None,
                },
            ));
        }
        let views: Vec<View> = views.into_iter().map(|(_, _, v)| v).collect();
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
        Ok(sets)
    }
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
        let pose = tf.root_from("camera", 10).unwrap_or_else(|| panic!("no pose"));
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
            Ok(sets) => panic!("a zero quaternion was accepted ({} sets)", sets.len()),
        };
        assert!(
            error.contains("/tf") && error.contains("world → camera_left") && error.contains("not a rotation"),
            "{error}"
        );
    }
}
