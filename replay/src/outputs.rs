//! Result files of one set: disparity (PFM, invalid = +inf), depth in metres (PFM) and
//! millimetres (16-bit PNG), a colour-mapped disparity PNG with its range in the name, the
//! back-projected points (PLY), and with ground truth an error map (PNG, 0–4 px in the name) and
//! `metrics.json`.

use std::path::{Path, PathBuf};

use crate::regions::RegionMetrics;
use fuse::DisparityImage;
use serde::Serialize;

use crate::viewset::ViewSet;

/// Range of the error-map colours (px): 0 is dark blue, 4 px and more dark red.
pub const ERROR_MAP_RANGE_PX: (f32, f32) = (0.0, 4.0);

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
    let set_dir = dir.join(sanitize(&format!("{:03}-{}", set.index, set.name)));
    std::fs::create_dir_all(&set_dir).map_err(|source| viz::files::FileError::Io {
        path: set_dir.clone(),
        source,
    })?;
    let (w, h) = (disparity.width, disparity.height);
    let mut files = Vec::new();
    let disparity_path = set_dir.join(format!("{method}_disparity.pfm"));
    viz::files::write_pfm(&disparity_path, w, h, &disparity.data)?;
    files.push(disparity_path);
    let depth_m = set.disparity_to_depth_m();
    let depth: Vec<f32> = disparity
        .data
        .iter()
        .map(|d| depth_m(*d).map_or(f32::INFINITY, |z| z as f32))
        .collect();
    let depth_pfm = set_dir.join(format!("{method}_depth_m.pfm"));
    viz::files::write_pfm(&depth_pfm, w, h, &depth)?;
    files.push(depth_pfm);
    let depth_png = set_dir.join(format!("{method}_depth_mm.png"));
    viz::files::write_depth_png_mm(&depth_png, w, h, &depth)?;
    files.push(depth_png);
    if let Some(confidence) = &disparity.confidence {
        let pfm = set_dir.join(format!("{method}_confidence.pfm"));
        viz::files::write_pfm(&pfm, w, h, confidence)?;
        files.push(pfm);
        let png = set_dir.join(format!("{method}_confidence.png"));
        viz::files::write_unit_png16(&png, w, h, confidence)?;
        files.push(png);
    }
    let range = viz::files::finite_range(&disparity.data);
    if let Some(range) = range {
        files.push(viz::files::write_colormap_png(
            &set_dir,
            &format!("{method}_disparity"),
            w,
            h,
            &disparity.data,
            range,
        )?);
    }
    let ply = set_dir.join(format!("{method}_points.ply"));
    // The PLY writer takes z = f·b/d: hand it d + doffs (0 unless the set's calibration has one).
    let doffs = set.disparity_offset_px() as f32;
    let shifted: Vec<f32> = disparity.data.iter().map(|d| d + doffs).collect();
    viz::files::write_ply_points(
        &ply,
        (w, h),
        &shifted,
        &set.reference.rgb,
        [
            set.reference.camera.fx,
            set.reference.camera.fy,
            set.reference.camera.cx,
            set.reference.camera.cy,
        ],
        set.baseline_m,
    )?;
    files.push(ply);
    if let Some(truth) = set.ground_truth_disparity() {
        // |estimate − truth| where the truth is known (no estimate counts as the largest error).
        let error: Vec<f32> = disparity
            .data
            .iter()
            .zip(&truth)
            .map(|(d, t)| match (t.is_finite(), d.is_finite()) {
                (true, true) => (d - t).abs(),
                (true, false) => ERROR_MAP_RANGE_PX.1,
                _ => f32::NAN,
            })
            .collect();
        files.push(viz::files::write_colormap_png(
            &set_dir,
            &format!("{method}_error"),
            w,
            h,
            &error,
            ERROR_MAP_RANGE_PX,
        )?);
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
        dir: set_dir,
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

/// Writes results as a new log: the inputs' metadata records, then per set (at the reference
/// image's log time) the disparity, depth, colour map, calibration and a JSON summary.
pub struct ResultLog {
    writer: record::log::LogWriter<record::log::SyncedWriter>,
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

impl ResultLog {
    /// Starts the log, copying the input's metadata records.
    pub fn create(
        path: &Path,
        input_metadata: &std::collections::BTreeMap<String, std::collections::BTreeMap<String, String>>,
        run: std::collections::BTreeMap<String, String>,
    ) -> Result<Self, record::log::LogError> {
        let (file, writer) = record::log::OutputFile::create(path)?;
        let mut writer = record::log::LogOptions::new().create(writer)?;
        for (name, records) in input_metadata {
            writer.write_metadata(name, records.clone())?;
        }
        writer.write_metadata("multiscopic.replay", run)?;
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
        let time = set.reference.capture_time_nanos;
        let (w, h) = (disparity.width, disparity.height);
        let depth_m = set.disparity_to_depth_m();
        let depth: Vec<f32> = disparity
            .data
            .iter()
            .map(|d| depth_m(*d).map_or(0.0, |z| z as f32))
            .collect();
        self.writer.write_message(
            &result_disparity_topic(method),
            time,
            &raw_f32(time, w, h, &disparity.data),
        )?;
        self.writer
            .write_message(&result_depth_topic(method), time, &raw_f32(time, w, h, &depth))?;
        if let Some(confidence) = &disparity.confidence {
            self.writer
                .write_message(&result_confidence_topic(method), time, &raw_f32(time, w, h, confidence))?;
        }
        if let Some((lo, hi)) = viz::files::finite_range(&disparity.data) {
            let mut color = raw_f32(time, w, h, &[]);
            color.encoding = "rgb8".into();
            color.step = (w * 3) as u32;
            color.data = viz::files::colorize(&disparity.data, lo, hi).into();
            self.writer.write_message(&result_color_topic(method), time, &color)?;
        }
        self.writer.write_message(
            RESULT_CALIBRATION_TOPIC,
            time,
            &record::log::calibration_message(
                &set.reference.camera,
                time,
                &record::log::view_frame(&set.reference.role),
            ),
        )?;
        self.writer
            .write_json(RESULT_SUMMARY_TOPIC, "multiscopic.SetResult", time, summary)
    }

    /// Finishes and renames the log into place.
    pub fn finish(self) -> Result<PathBuf, record::log::LogError> {
        let writer = self.writer.finish()?;
        self.file.commit(writer)
    }
}
