//! Result files of one set: disparity (PFM, invalid = +inf), depth in metres (PFM) and
//! millimetres (16-bit PNG), a colour-mapped disparity PNG with its range in the name, and
//! `metrics.json` when ground truth exists.

use std::path::{Path, PathBuf};

use crate::regions::RegionMetrics;
use fuse::DisparityImage;
use serde::Serialize;

use crate::viewset::ViewSet;

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
    let fb = set.reference.camera.fx * set.baseline_m;
    let depth: Vec<f32> = disparity
        .data
        .iter()
        .map(|d| fuse::depth_from_disparity(fb, 1.0, f64::from(*d)).map_or(f32::INFINITY, |z| z as f32))
        .collect();
    let depth_pfm = set_dir.join(format!("{method}_depth_m.pfm"));
    viz::files::write_pfm(&depth_pfm, w, h, &depth)?;
    files.push(depth_pfm);
    let depth_png = set_dir.join(format!("{method}_depth_mm.png"));
    viz::files::write_depth_png_mm(&depth_png, w, h, &depth)?;
    files.push(depth_png);
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
