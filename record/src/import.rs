//! Import of real image sets into the same log format, so that real data goes through exactly the
//! same replay path as simulated captures.
//!
//! A directory holds either the view files of one set directly, or one sub-directory per set
//! (the Middlebury layout: `scene/view0.png …`). Views are listed in the layout's file order
//! (see [`RigKind::file_order`]); ground truth for the reference view is a disparity PNG whose
//! value divided by `ground_truth_scale` is the disparity in pixels between the reference and a
//! direct neighbour (0 = unknown). It is stored as depth `z = f·b/d`, so replay recovers the
//! disparity exactly from the logged focal length and baseline.

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::camera::PinholeCamera;
use crate::capture::SIM_EPOCH_NANOS;
use crate::rig::{REFERENCE_ROLE, RigKind};
use crate::{CapturedSet, CapturedView};

/// Time between imported sets in the log (s).
const SET_SPACING_SECS: u64 = 10;
/// Time between imported views of a set (ms).
const VIEW_SPACING_MS: u64 = 500;

/// What to import and how to interpret it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImportConfig {
    /// Layout of the views.
    pub layout: RigKind,
    /// View file names in the layout's file order (`.png` is appended when there is no extension).
    pub views: Vec<String>,
    /// Ground-truth disparity file of the reference view, if any.
    pub ground_truth: Option<String>,
    /// Stored value ÷ scale = disparity (pixels) between the reference and a direct neighbour.
    pub ground_truth_scale: f64,
    /// Baseline between the reference and a direct neighbour (mm).
    pub baseline_mm: f64,
    /// Focal length (pixels); when absent it follows from `horizontal_fov_deg`.
    pub focal_px: Option<f64>,
    /// Horizontal field of view used when no focal length is given (deg).
    pub horizontal_fov_deg: f64,
    /// Only these set directories (names), all when empty.
    pub sets: Vec<String>,
}

impl Default for ImportConfig {
    /// The Middlebury 2006 three-view setting of the paper: left view0, centre view1, right
    /// view2, ground truth disp1.png ÷ 12 at third size, 40 mm between adjacent views.
    fn default() -> Self {
        Self {
            layout: RigKind::ThreeView,
            views: vec!["view0".into(), "view1".into(), "view2".into()],
            ground_truth: Some("disp1".into()),
            ground_truth_scale: 12.0,
            baseline_mm: 40.0,
            focal_px: None,
            horizontal_fov_deg: crate::camera::DEFAULT_HORIZONTAL_FOV_DEG,
            sets: Vec::new(),
        }
    }
}

/// Errors of the importer; each names the file and what was wrong with it.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The directory holds neither view files nor set directories with them.
    #[error("'{dir}' holds no image set: expected {expected} in it or in its sub-directories")]
    NoSets {
        /// Directory searched.
        dir: PathBuf,
        /// Files looked for.
        expected: String,
    },
    /// The layout needs a different number of views.
    #[error("layout {layout} has {expected} views, but {given} view files were named")]
    ViewCount {
        /// Layout name.
        layout: &'static str,
        /// Views of the layout.
        expected: usize,
        /// Names given.
        given: usize,
    },
    /// A file is missing or unreadable.
    #[error("cannot read '{path}'")]
    Read {
        /// File.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// A file is not a PNG this importer understands.
    #[error("cannot decode '{path}' as PNG: {reason}")]
    Decode {
        /// File.
        path: PathBuf,
        /// Cause.
        reason: String,
    },
    /// Views of a set (or the ground truth) differ in size.
    #[error("'{path}' is {width}x{height}, but the reference view is {expected_width}x{expected_height}")]
    SizeMismatch {
        /// File.
        path: PathBuf,
        /// Its width.
        width: u32,
        /// Its height.
        height: u32,
        /// Reference width.
        expected_width: u32,
        /// Reference height.
        expected_height: u32,
    },
    /// A numeric option is out of range.
    #[error("invalid import option {field} = {value}: {reason}")]
    InvalidOption {
        /// Option.
        field: &'static str,
        /// Value.
        value: f64,
        /// What is allowed.
        reason: &'static str,
    },
}

/// A decoded 8-bit image.
struct Image8 {
    width: u32,
    height: u32,
    channels: usize,
    data: Vec<u8>,
}

fn read_png(path: &Path) -> Result<Image8, ImportError> {
    let file = std::fs::File::open(path).map_err(|source| ImportError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let decode = |reason: String| ImportError::Decode {
        path: path.to_path_buf(),
        reason,
    };
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().map_err(|e| decode(e.to_string()))?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| decode("image too large".into()))?;
    let mut data = vec![0; size];
    let info = reader.next_frame(&mut data).map_err(|e| decode(e.to_string()))?;
    data.truncate(info.buffer_size());
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err(decode("indexed colour after expansion".into())),
    };
    Ok(Image8 {
        width: info.width,
        height: info.height,
        channels,
        data,
    })
}

impl Image8 {
    fn to_rgb(&self) -> Vec<u8> {
        match self.channels {
            3 => self.data.clone(),
            4 => self.data.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect(),
            2 => self.data.chunks_exact(2).flat_map(|p| [p[0]; 3]).collect(),
            _ => self.data.iter().flat_map(|v| [*v; 3]).collect(),
        }
    }

    fn first_channel(&self) -> Vec<u8> {
        self.data.chunks_exact(self.channels).map(|p| p[0]).collect()
    }
}

fn file_name(name: &str) -> String {
    if Path::new(name).extension().is_some() {
        name.to_owned()
    } else {
        format!("{name}.png")
    }
}

/// The set directories under `dir` (sorted), or `dir` itself when it holds the views.
pub fn find_set_dirs(dir: &Path, config: &ImportConfig) -> Result<Vec<PathBuf>, ImportError> {
    let holds_views = |d: &Path| config.views.iter().all(|v| d.join(file_name(v)).is_file());
    if holds_views(dir) {
        return Ok(vec![dir.to_path_buf()]);
    }
    let entries = std::fs::read_dir(dir).map_err(|source| ImportError::Read {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut dirs: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir() && holds_views(p))
        .filter(|p| {
            config.sets.is_empty()
                || p.file_name()
                    .is_some_and(|n| config.sets.iter().any(|s| s.as_str() == n.to_string_lossy()))
        })
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        return Err(ImportError::NoSets {
            dir: dir.to_path_buf(),
            expected: config.views.iter().map(|v| file_name(v)).collect::<Vec<_>>().join(", "),
        });
    }
    Ok(dirs)
}

fn validate(config: &ImportConfig) -> Result<(), ImportError> {
    let expected = config.layout.file_order().len();
    if config.views.len() != expected {
        return Err(ImportError::ViewCount {
            layout: config.layout.name(),
            expected,
            given: config.views.len(),
        });
    }
    let positive = |field, value: f64| {
        if value.is_finite() && value > 0.0 {
            Ok(())
        } else {
            Err(ImportError::InvalidOption {
                field,
                value,
                reason: "must be a positive number",
            })
        }
    };
    positive("baseline_mm", config.baseline_mm)?;
    positive("ground_truth_scale", config.ground_truth_scale)?;
    positive("horizontal_fov_deg", config.horizontal_fov_deg)?;
    if let Some(f) = config.focal_px {
        positive("focal_px", f)?;
    }
    Ok(())
}

/// Reads one set directory.
pub fn import_set(dir: &Path, index: u32, config: &ImportConfig) -> Result<CapturedSet, ImportError> {
    validate(config)?;
    let slots = config.layout.file_order();
    let baseline_m = config.baseline_mm / 1000.0;
    let images = config
        .views
        .iter()
        .map(|name| {
            let path = dir.join(file_name(name));
            read_png(&path).map(|image| (path, image))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let reference_position = slots.iter().position(|s| s.role == REFERENCE_ROLE).unwrap_or(0);
    let (width, height) = (images[reference_position].1.width, images[reference_position].1.height);
    for (path, image) in &images {
        if (image.width, image.height) != (width, height) {
            return Err(ImportError::SizeMismatch {
                path: path.clone(),
                width: image.width,
                height: image.height,
                expected_width: width,
                expected_height: height,
            });
        }
    }
    let mut camera = PinholeCamera::from_horizontal_fov(width, height, config.horizontal_fov_deg);
    if let Some(f) = config.focal_px {
        camera.fx = f;
        camera.fy = f;
    }
    let depth = match &config.ground_truth {
        Some(name) => {
            let path = dir.join(file_name(name));
            let image = read_png(&path)?;
            if (image.width, image.height) != (width, height) {
                return Err(ImportError::SizeMismatch {
                    path,
                    width: image.width,
                    height: image.height,
                    expected_width: width,
                    expected_height: height,
                });
            }
            let focal_times_baseline = camera.fx * baseline_m;
            Some(
                image
                    .first_channel()
                    .into_iter()
                    .map(|v| {
                        if v == 0 {
                            0.0
                        } else {
                            (focal_times_baseline / (f64::from(v) / config.ground_truth_scale)) as f32
                        }
                    })
                    .collect::<Vec<f32>>(),
            )
        }
        None => None,
    };
    let set_time = SIM_EPOCH_NANOS + u64::from(index) * SET_SPACING_SECS * 1_000_000_000;
    let mut views: Vec<CapturedView> = slots
        .iter()
        .zip(&images)
        .enumerate()
        .map(|(i, (slot, (_, image)))| {
            let offset = Isometry3::translation(
                f64::from(slot.grid_offset[0]) * baseline_m,
                f64::from(slot.grid_offset[1]) * baseline_m,
                0.0,
            );
            CapturedView {
                role: slot.role.to_owned(),
                grid_offset: slot.grid_offset,
                camera,
                capture_time_nanos: set_time + i as u64 * VIEW_SPACING_MS * 1_000_000,
                rgb: image.to_rgb(),
                depth_m: None,
                surface_class: None,
                world_from_camera: offset,
                world_from_camera_true: None,
                commanded_world_from_camera: None,
                joints: None,
                exposure_gain: 1.0,
            }
        })
        .collect();
    views[reference_position].depth_m = depth;
    // Reference first, like simulated sets; log times stay increasing per view.
    let reference = views.remove(reference_position);
    views.insert(0, reference);
    let mut times: Vec<u64> = views.iter().map(|v| v.capture_time_nanos).collect();
    times.sort_unstable();
    for (view, time) in views.iter_mut().zip(times) {
        view.capture_time_nanos = time;
    }
    Ok(CapturedSet {
        index,
        name: dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| format!("set-{index}")),
        rig: config.layout,
        baseline_m,
        motion: Vec::new(),
        views,
    })
}
