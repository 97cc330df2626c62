//! Result files of one set: disparity (PFM, invalid = +inf), depth in metres (PFM) and
//! millimetres (16-bit PNG), a colour-mapped disparity PNG with its range in the name, the
//! back-projected points (PLY), and with ground truth an error map (PNG, 0–4 px in the name), the
//! signed error (PFM, estimate − truth) and `metrics.json`.

use std::path::{Path, PathBuf};

use crate::regions::RegionMetrics;
use fuse::DisparityImage;
use serde::Serialize;

use crate::viewset::ViewSet;

/// Range of the error-map colours (px): 0 is dark blue, 4 px and more dark red.
pub const ERROR_MAP_RANGE_PX: (f32, f32) = (0.0, 4.0);

/// Which result files of a set are written (`replay LOG --outputs`); `metrics.json` always is,
/// when the set has ground truth. A workcell that needs only the depth skips the rest: at
/// 1080p the points alone are 31 MB of PLY.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResultFiles {
    /// `disparity`: the disparity PFM.
    pub disparity: bool,
    /// `colormap`: the colour-mapped disparity PNG.
    pub colormap: bool,
    /// `depth`: depth in metres (PFM) and millimetres (16-bit PNG).
    pub depth: bool,
    /// `confidence`: the method's confidence (PFM and 16-bit PNG), when it gives one.
    pub confidence: bool,
    /// `points`: the back-projected points (PLY).
    pub points: bool,
    /// `error`: the error map against the ground truth (PNG, 0–4 px) and the signed error
    /// (PFM, estimate − truth in px), when there is a truth.
    pub error: bool,
}

impl ResultFiles {
    /// Every file.
    pub const ALL: Self = Self {
        disparity: true,
        colormap: true,
        depth: true,
        confidence: true,
        points: true,
        error: true,
    };

    /// The names [`Self::parse`] takes.
    pub const NAMES: [&'static str; 6] = ["disparity", "colormap", "depth", "confidence", "points", "error"];

    /// `all`, `none`, or a comma-separated list of [`Self::NAMES`].
    pub fn parse(spec: &str) -> Result<Self, UnknownResultFile> {
        let none = Self {
            disparity: false,
            colormap: false,
            depth: false,
            confidence: false,
            points: false,
            error: false,
        };
        match spec.trim() {
            "all" => return Ok(Self::ALL),
            "none" => return Ok(none),
            _ => {}
        }
        let mut files = none;
        for name in spec.split(',').map(str::trim).filter(|n| !n.is_empty()) {
            let flag = match name {
                "disparity" => &mut files.disparity,
                "colormap" => &mut files.colormap,
                "depth" => &mut files.depth,
                "confidence" => &mut files.confidence,
                "points" => &mut files.points,
                "error" => &mut files.error,
                _ => {
                    return Err(UnknownResultFile { name: name.to_owned() });
                }
            };
            *flag = true;
        }
        Ok(files)
    }
}

impl Default for ResultFiles {
    fn default() -> Self {
        Self::ALL
    }
}

/// A name `--outputs` does not know.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown result file `{name}`: expected all, none or a comma-separated list of {}", ResultFiles::NAMES.join(", "))]
pub struct UnknownResultFile {
    /// The name given.
    pub name: String,
}

/// What was written for one set.
#[derive(Debug, Clone, Serialize)]
pub struct SetOutputs {
    /// Set index.
    pub set: u32,
    /// Set name.
    pub name: String,
    /// Directory of the files.
    pub dir: PathBuf,
    /// Files written.
    pub files: Vec<PathBuf>,
    /// Metrics against ground truth, when present (overall, occluded, visible, specular).
    pub metrics: Option<RegionMetrics>,
    /// Disparity range shown by the colour map (px).
    pub disparity_range_px: Option<(f32, f32)>,
}

/// Writes the files of one set into `dir/<set name>/`.
pub fn write_set_outputs(
    dir: &Path,
    set: &ViewSet,
    method: &str,
    disparity: &DisparityImage,
    metrics: Option<RegionMetrics>,
) -> Result<SetOutputs, viz::files::FileError> {
    let truth = set.ground_truth_disparity();
    write_set_outputs_evaluating(dir, set, method, disparity, truth.as_deref(), ResultFiles::ALL, || {
        metrics
    })
}

/// [`write_set_outputs`] with the metrics computed by `evaluate` while the files are written
/// (the evaluation's sorts and the files' compression take turns on the cores instead of
/// following each other), and the set's ground-truth disparity (for the error map) as made
/// once by the caller.
pub fn write_set_outputs_evaluating(
    dir: &Path,
    set: &ViewSet,
    method: &str,
    disparity: &DisparityImage,
    truth: Option<&[f32]>,
    wanted: ResultFiles,
    evaluate: impl FnOnce() -> Option<RegionMetrics> + Send,
) -> Result<SetOutputs, viz::files::FileError> {
    let set_dir = dir.join(sanitize(&format!("{:03}-{}", set.index, set.name)));
    std::fs::create_dir_all(&set_dir).map_err(|source| viz::files::FileError::Io {
        path: set_dir.clone(),
        source,
    })?;
    let (w, h) = (disparity.width, disparity.height);
    let range = viz::files::finite_range(&disparity.data);
    // Each file is written by its own task (PNG compression and the PLY's text are the costly
    // ones): the files of a 1080p set in about the time of the slowest.
    type Writer<'w> = Box<dyn FnOnce() -> Result<Vec<PathBuf>, viz::files::FileError> + Send + 'w>;
    let set_dir = &set_dir;
    // The depth map, made by whichever of its two files' tasks comes first.
    let depth = std::sync::OnceLock::new();
    let depth = &depth;
    let depth_of = move || -> &Vec<f32> { depth.get_or_init(|| depth_map(set, disparity, f32::INFINITY)) };
    let mut writers: Vec<Writer<'_>> = Vec::new();
    if wanted.disparity {
        writers.push(Box::new(move || {
            let path = set_dir.join(format!("{method}_disparity.pfm"));
            viz::files::write_pfm(&path, w, h, &disparity.data)?;
            Ok(vec![path])
        }));
    }
    if wanted.depth {
        // The PNG's compression and the PFM's write side by side.
        writers.push(Box::new(move || {
            let pfm = set_dir.join(format!("{method}_depth_m.pfm"));
            viz::files::write_pfm(&pfm, w, h, depth_of())?;
            Ok(vec![pfm])
        }));
        writers.push(Box::new(move || {
            let png = set_dir.join(format!("{method}_depth_mm.png"));
            viz::files::write_depth_png_mm(&png, w, h, depth_of())?;
            Ok(vec![png])
        }));
    }
    if let Some(confidence) = disparity.confidence.as_ref().filter(|_| wanted.confidence) {
        writers.push(Box::new(move || {
            let pfm = set_dir.join(format!("{method}_confidence.pfm"));
            viz::files::write_pfm(&pfm, w, h, confidence)?;
            let png = set_dir.join(format!("{method}_confidence.png"));
            viz::files::write_unit_png16(&png, w, h, confidence)?;
            Ok(vec![pfm, png])
        }));
    }
    if let Some(range) = range.filter(|_| wanted.colormap) {
        writers.push(Box::new(move || {
            Ok(vec![viz::files::write_colormap_png(
                set_dir,
                &format!("{method}_disparity"),
                w,
                h,
                &disparity.data,
                range,
            )?])
        }));
    }
    if wanted.points {
        writers.push(Box::new(move || {
            let ply = set_dir.join(format!("{method}_points.ply"));
            // z = f·b / (d + doffs), doffs 0 unless the set's calibration has one.
            viz::files::write_ply_points(
                &ply,
                (w, h),
                &disparity.data,
                set.disparity_offset_px() as f32,
                &set.reference.rgb,
                [
                    set.reference.camera.fx,
                    set.reference.camera.fy,
                    set.reference.camera.cx,
                    set.reference.camera.cy,
                ],
                set.baseline_m,
            )?;
            Ok(vec![ply])
        }));
    }
    if wanted.error {
        writers.push(Box::new(move || {
            let Some(truth) = truth else {
                return Ok(Vec::new());
            };
            // |estimate − truth| where the truth is known (no estimate counts as the largest error).
            let error: Vec<f32> = disparity
                .data
                .iter()
                .zip(truth)
                .map(|(d, t)| match (t.is_finite(), d.is_finite()) {
                    (true, true) => (d - t).abs(),
                    (true, false) => ERROR_MAP_RANGE_PX.1,
                    _ => f32::NAN,
                })
                .collect();
            // The signed error as well (estimate − truth, px; NaN where the truth is unknown,
            // +inf where the method gave no estimate): for tools that split the errors into
            // too near and too far, or compare two methods pixel by pixel.
            let signed: Vec<f32> = disparity
                .data
                .iter()
                .zip(truth)
                .map(|(d, t)| match (t.is_finite(), d.is_finite()) {
                    (true, true) => d - t,
                    (true, false) => f32::INFINITY,
                    _ => f32::NAN,
                })
                .collect();
            let pfm = set_dir.join(format!("{method}_error_px.pfm"));
            viz::files::write_pfm(&pfm, w, h, &signed)?;
            Ok(vec![
                viz::files::write_colormap_png(set_dir, &format!("{method}_error"), w, h, &error, ERROR_MAP_RANGE_PX)?,
                pfm,
            ])
        }));
    }
    let (written, metrics): (Vec<Result<Vec<PathBuf>, viz::files::FileError>>, _) = rayon::join(
        || {
            use rayon::prelude::*;
            writers.into_par_iter().map(|write| write()).collect()
        },
        evaluate,
    );
    let mut files = Vec::new();
    for paths in written {
        files.extend(paths?);
    }
    if let Some(metrics) = metrics {
        let path = set_dir.join(format!("{method}_metrics.json"));
        let json = serde_json::to_string_pretty(&serde_json::json!({
            "method": method,
            "set": set.index,
            "name": set.name,
            "metrics": metrics,
        }))
        .unwrap_or_default();
        std::fs::write(&path, json).map_err(|source| viz::files::FileError::Io {
            path: path.clone(),
            source,
        })?;
        files.push(path);
    }
    Ok(SetOutputs {
        set: set.index,
        name: set.name.clone(),
        dir: set_dir.to_path_buf(),
        files,
        metrics,
        disparity_range_px: range,
    })
}

fn sanitize(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Topic of a method's disparity result for a set (`foxglove.RawImage`, `32FC1`, pixels,
/// +inf = no estimate).
pub fn result_disparity_topic(method: &str) -> String {
    format!("/results/{method}/disparity")
}

/// Topic of a method's depth result (`foxglove.RawImage`, `32FC1`, metres, 0 = unknown).
pub fn result_depth_topic(method: &str) -> String {
    format!("/results/{method}/depth")
}

/// Topic of a method's per-pixel confidence (`foxglove.RawImage`, `32FC1`, 0 … 1).
pub fn result_confidence_topic(method: &str) -> String {
    format!("/results/{method}/confidence")
}

/// Topic of a method's colour-mapped disparity (`foxglove.RawImage`, `rgb8`).
pub fn result_color_topic(method: &str) -> String {
    format!("/results/{method}/disparity_color")
}

/// Topic of the reference calibration beside the results (so viewers can back-project depth).
pub const RESULT_CALIBRATION_TOPIC: &str = "/results/calibration";
/// Topic of per-set result summaries (JSON: set, method, metrics, timing).
pub const RESULT_SUMMARY_TOPIC: &str = "/results/summary";

/// Topic of a method's disparity as `stereo_msgs/msg/DisparityImage` (ROS 2 result logs).
pub fn result_disparity_image_topic(method: &str) -> String {
    format!("/results/{method}/disparity_image")
}

/// Topic of a method's points as `sensor_msgs/msg/PointCloud2` (ROS 2 result logs).
pub fn result_points_topic(method: &str) -> String {
    format!("/results/{method}/points")
}

/// The ROS 2 result log's camera info topic.
pub const RESULT_CAMERA_INFO_TOPIC: &str = "/results/camera_info";

/// How a result log is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ResultFormat {
    /// Our own log's Foxglove schemas (`foxglove.RawImage` 32FC1, …).
    Mcap,
    /// ROS 2 (`sensor_msgs/msg/Image` 32FC1 disparity, depth and confidence,
    /// `stereo_msgs/msg/DisparityImage`, `sensor_msgs/msg/PointCloud2`, `CameraInfo`), stamped
    /// and framed as the reference image, so that rviz and Foxglove show them beside the bag.
    Ros2,
}

/// The writer of a result log.
enum ResultWriter {
    Foxglove(Box<record::log::LogWriter<record::log::SyncedWriter>>),
    Ros2(Box<record::bag::BagWriter<record::log::SyncedWriter>>),
}

/// Writes results as a new log: the inputs' metadata records, then per set (at the reference
/// image's log time) the disparity, depth, colour map, calibration and a JSON summary (ROS 2:
/// also a `DisparityImage` and the points).
pub struct ResultLog {
    writer: ResultWriter,
    file: record::log::OutputFile,
}

fn raw_f32(time: u64, width: usize, height: usize, data: &[f32]) -> foxglove::messages::RawImage {
    let mut bytes = Vec::with_capacity(data.len() * 4);
    for v in data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    foxglove::messages::RawImage {
        timestamp: Some(record::log::timestamp(time)),
        frame_id: record::log::view_frame(record::rig::REFERENCE_ROLE),
        width: width as u32,
        height: height as u32,
        encoding: "32FC1".into(),
        step: (width * 4) as u32,
        data: bytes.into(),
    }
}

/// A little-endian `32FC1` image; values that are not finite become NaN (ROS's "no data").
fn ros_f32<'a>(time: u64, frame: &str, width: usize, height: usize, data: &[f32]) -> ros2::msg::Image<'a> {
    let mut bytes = Vec::with_capacity(data.len() * 4);
    for v in data {
        let v = if v.is_finite() { *v } else { f32::NAN };
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    ros2::msg::Image {
        header: record::bag::stamp(time, frame),
        height: height as u32,
        width: width as u32,
        encoding: "32FC1".into(),
        is_bigendian: 0,
        step: (width * 4) as u32,
        data: std::borrow::Cow::Owned(bytes),
    }
}

/// The depth (m) of every pixel's disparity, `unknown` where there is none.
fn depth_map(set: &ViewSet, disparity: &DisparityImage, unknown: f32) -> Vec<f32> {
    let depth_m = set.disparity_to_depth_m();
    disparity
        .data
        .iter()
        .map(|d| depth_m(*d).map_or(unknown, |z| z as f32))
        .collect()
}

impl ResultLog {
    /// Starts the log, copying the input's metadata records.
    pub fn create(
        path: &Path,
        format: ResultFormat,
        input_metadata: &std::collections::BTreeMap<String, std::collections::BTreeMap<String, String>>,
        run: std::collections::BTreeMap<String, String>,
    ) -> Result<Self, record::log::LogError> {
        let (file, writer) = record::log::OutputFile::create(path)?;
        let options = record::log::LogOptions::new();
        let mut writer = match format {
            ResultFormat::Mcap => ResultWriter::Foxglove(Box::new(options.create(writer)?)),
            ResultFormat::Ros2 => {
                let name = path
                    .file_name()
                    .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
                ResultWriter::Ros2(Box::new(record::bag::BagWriter::create(options, &name, writer)?))
            }
        };
        for (name, records) in input_metadata
            .iter()
            .filter(|(name, _)| *name != ros2::bag::METADATA_RECORD)
        {
            match &mut writer {
                ResultWriter::Foxglove(w) => w.write_metadata(name, records.clone())?,
                ResultWriter::Ros2(w) => w.write_metadata(name, records.clone())?,
            }
        }
        match &mut writer {
            ResultWriter::Foxglove(w) => w.write_metadata("multiscopic.replay", run)?,
            ResultWriter::Ros2(w) => w.write_metadata("multiscopic.replay", run)?,
        }
        Ok(Self { writer, file })
    }

    /// Writes one set's results.
    pub fn write_set(
        &mut self,
        set: &ViewSet,
        method: &str,
        disparity: &DisparityImage,
        summary: &serde_json::Value,
    ) -> Result<(), record::log::LogError> {
        let ResultWriter::Foxglove(writer) = &mut self.writer else {
            return self.write_ros2_set(set, method, disparity, summary);
        };
        let time = set.reference.capture_time_nanos;
        let (w, h) = (disparity.width, disparity.height);
        let depth = depth_map(set, disparity, 0.0);
        writer.write_message(
            &result_disparity_topic(method),
            time,
            &raw_f32(time, w, h, &disparity.data),
        )?;
        writer.write_message(&result_depth_topic(method), time, &raw_f32(time, w, h, &depth))?;
        if let Some(confidence) = &disparity.confidence {
            writer.write_message(&result_confidence_topic(method), time, &raw_f32(time, w, h, confidence))?;
        }
        if let Some((lo, hi)) = viz::files::finite_range(&disparity.data) {
            let mut color = raw_f32(time, w, h, &[]);
            color.encoding = "rgb8".into();
            color.step = (w * 3) as u32;
            color.data = viz::files::colorize(&disparity.data, lo, hi).into();
            writer.write_message(&result_color_topic(method), time, &color)?;
        }
        writer.write_message(
            RESULT_CALIBRATION_TOPIC,
            time,
            &record::log::calibration_message(
                &set.reference.camera,
                time,
                &record::log::view_frame(&set.reference.role),
            ),
        )?;
        writer.write_json(RESULT_SUMMARY_TOPIC, "multiscopic.SetResult", time, summary)
    }

    /// One set's results as ROS 2 messages, stamped and framed as the reference image.
    fn write_ros2_set(
        &mut self,
        set: &ViewSet,
        method: &str,
        disparity: &DisparityImage,
        summary: &serde_json::Value,
    ) -> Result<(), record::log::LogError> {
        use ros2::{msg, schema};
        let ResultWriter::Ros2(bag) = &mut self.writer else {
            return Ok(());
        };
        let time = set.reference.capture_time_nanos;
        let frame = set.reference.frame_id.as_str();
        let camera = &set.reference.camera;
        let (w, h) = (disparity.width, disparity.height);
        let depth = depth_map(set, disparity, f32::NAN);
        bag.write(
            &result_disparity_topic(method),
            schema::IMAGE,
            time,
            &ros_f32(time, frame, w, h, &disparity.data),
        )?;
        bag.write(
            &result_depth_topic(method),
            schema::IMAGE,
            time,
            &ros_f32(time, frame, w, h, &depth),
        )?;
        if let Some(confidence) = &disparity.confidence {
            bag.write(
                &result_confidence_topic(method),
                schema::IMAGE,
                time,
                &ros_f32(time, frame, w, h, confidence),
            )?;
        }
        let range = viz::files::finite_range(&disparity.data);
        if let Some((lo, hi)) = range {
            let color = msg::Image {
                encoding: "rgb8".into(),
                step: (w * 3) as u32,
                data: std::borrow::Cow::Owned(viz::files::colorize(&disparity.data, lo, hi)),
                ..ros_f32(time, frame, w, h, &[])
            };
            bag.write(&result_color_topic(method), schema::IMAGE, time, &color)?;
        }
        // stereo_msgs: Z = f·T / d, so the disparity carries Middlebury's doffs.
        let doffs = set.disparity_offset_px() as f32;
        let shifted: Vec<f32> = disparity.data.iter().map(|d| d + doffs).collect();
        let (lo, hi) = range.unwrap_or((0.0, 0.0));
        let stereo = msg::DisparityImage {
            header: record::bag::stamp(time, frame),
            image: ros_f32(time, frame, w, h, &shifted),
            f: camera.fx as f32,
            t: set.baseline_m as f32,
            valid_window: msg::RegionOfInterest {
                x_offset: 0,
                y_offset: 0,
                height: h as u32,
                width: w as u32,
                do_rectify: false,
            },
            min_disparity: lo + doffs,
            max_disparity: hi + doffs,
            delta_d: 1.0 / 16.0,
        };
        bag.write(
            &result_disparity_image_topic(method),
            schema::DISPARITY_IMAGE,
            time,
            &stereo,
        )?;
        // The points in the camera's optical frame, organised as the image (NaN: no estimate),
        // coloured by the reference image (PCL's packed float `rgb`).
        let mut points = Vec::with_capacity(w * h * 16);
        for (i, z) in depth.iter().enumerate() {
            let (u, v) = ((i % w) as f64, (i / w) as f64);
            let z = f64::from(*z);
            let (x, y) = ((u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z);
            for c in [x as f32, y as f32, z as f32] {
                points.extend_from_slice(&c.to_le_bytes());
            }
            let p = set.reference.rgb.get(i * 3..i * 3 + 3).unwrap_or(&[0, 0, 0]);
            let packed = (u32::from(p[0]) << 16) | (u32::from(p[1]) << 8) | u32::from(p[2]);
            points.extend_from_slice(&packed.to_le_bytes());
        }
        let field = |name: &str, offset: u32| msg::PointField {
            name: name.into(),
            offset,
            datatype: msg::POINT_FIELD_FLOAT32,
            count: 1,
        };
        let cloud = msg::PointCloud2 {
            header: record::bag::stamp(time, frame),
            height: h as u32,
            width: w as u32,
            fields: vec![field("x", 0), field("y", 4), field("z", 8), field("rgb", 12)],
            is_bigendian: false,
            point_step: 16,
            row_step: (w * 16) as u32,
            data: std::borrow::Cow::Owned(points),
            is_dense: false,
        };
        bag.write(&result_points_topic(method), schema::POINT_CLOUD2, time, &cloud)?;
        bag.write(
            RESULT_CAMERA_INFO_TOPIC,
            schema::CAMERA_INFO,
            time,
            &record::bag::camera_info(camera, time, frame),
        )?;
        bag.write_json(RESULT_SUMMARY_TOPIC, time, summary)
    }

    /// Finishes and renames the log into place.
    pub fn finish(self) -> Result<PathBuf, record::log::LogError> {
        let writer = match self.writer {
            ResultWriter::Foxglove(w) => w.finish()?,
            ResultWriter::Ros2(w) => w.finish()?.0,
        };
        self.file.commit(writer)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn result_files_parse_all_none_and_lists_and_name_what_they_know() {
        assert_eq!(ResultFiles::parse("all"), Ok(ResultFiles::ALL));
        let none = ResultFiles::parse("none").unwrap_or(ResultFiles::ALL);
        assert!(!(none.disparity || none.colormap || none.depth || none.confidence || none.points || none.error));
        let some = ResultFiles::parse(" depth , points").unwrap_or(ResultFiles::ALL);
        assert!(some.depth && some.points && !some.disparity && !some.error);
        for name in ResultFiles::NAMES {
            assert!(ResultFiles::parse(name).is_ok(), "{name}");
        }
        let error = ResultFiles::parse("depth,cloud").err();
        assert_eq!(error.as_ref().map(|e| e.name.as_str()), Some("cloud"));
        assert!(error.is_some_and(|e| e.to_string().contains("points")));
    }
}
