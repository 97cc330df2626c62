//! Import of real image sets into the same log format, so that real data goes through exactly the
//! same replay path as simulated captures.
//!
//! **Views** are files with a grid offset in baselines (`FILE@DX` on a horizontal line,
//! `FILE@DX:DY` on a grid; x right, y down): `view0@-1,view1@0,view2@1` is Middlebury's three-view
//! set, `scene1.row3.col1.ppm@-2 … col5.ppm@2` Tsukuba's five views in a row. The view at `0` is the
//! reference; a view at a multiple of the baseline keeps that multiple in the log (its capture
//! event's `grid_offset`, its pose) and every method samples its costs at `multiple × d`. Role
//! names follow the offsets ([`crate::rig::role_for_offset`]: `left`, `right2`, `top-left`, …).
//! The named layouts stay as shorthands ([`RigKind::file_order`]).
//!
//! **Images** are read by the `image` crate: PNG (8 and 16 bit), PPM/PGM, JPEG, TIFF, BMP; grey
//! images become RGB, 16-bit ones are scaled to 8 bits.
//!
//! **Ground truth** is the disparity of the reference to a *direct* neighbour (one baseline),
//! `stored value ÷ ground_truth_scale`:
//! - PNG, TIFF, BMP (8 or 16 bit, first channel) and PGM/PPM (raw values, any maxval up to
//!   65535): 0 = unknown (Middlebury 2006 `disp1.png` ÷ 12 at third size, Tsukuba
//!   `truedisp.row3.col3.pgm` ÷ 16, KITTI-style 16-bit PNG ÷ 256);
//! - PFM (float disparity, Middlebury 2014 `disp0.pfm`, ETH3D): `inf`/NaN = unknown; the scale
//!   defaults to 1 like every format's.
//!
//! A disparity of 0 (infinitely far) is unknown too. It is stored as depth `z = f·b/(d + doffs)`,
//! so replay recovers the disparity exactly from the logged focal length, baseline and principal
//! points.
//!
//! **Calibration**: focal length, principal point, baseline and `doffs` (the principal points'
//! difference between adjacent views, Middlebury 2014) come from a Middlebury 2014 `calib.txt`
//! in the set folder when there is one, else from the options (`focal_px` or a horizontal field of
//! view, `principal_point_px` or the image centre, `baseline_mm`, `doffs_px`). A neighbour at
//! offset `(dx, dy)` gets the principal point `(cx + dx·doffs, cy + dy·doffs)`.
//!
//! **Self-describing folders**: a [`DESCRIPTION_FILE`] (`multiscopic.toml`) beside the images,
//! or at the top of a folder of sets (one sub-folder per set), holds the same settings as the
//! options, so that `record import DIR` and `replay eval DIR` need no flags:
//!
//! ```toml
//! views = ["scene1.row3.col1.ppm@-2", "scene1.row3.col2.ppm@-1", "scene1.row3.col3.ppm@0",
//!          "scene1.row3.col4.ppm@1", "scene1.row3.col5.ppm@2"]
//! ground_truth = "truedisp.row3.col3.pgm"
//! ground_truth_scale = 16
//! baseline_mm = 100
//! focal_px = 615
//! ```
//!
//! Options given on the command line override the file; without either, the Middlebury 2006
//! third-size three-view setting of the paper is assumed ([`ImportConfig::default`]).

use std::path::{Path, PathBuf};
use std::str::FromStr;

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::camera::PinholeCamera;
use crate::capture::SIM_EPOCH_NANOS;
use crate::rig::{REFERENCE_ROLE, RigKind, role_for_offset};
use crate::{CapturedSet, CapturedView};

/// Time between imported sets in the log (s).
const SET_SPACING_SECS: u64 = 10;
/// Time between imported views of a set (ms).
const VIEW_SPACING_MS: u64 = 500;
/// The file a dataset folder describes itself with.
pub const DESCRIPTION_FILE: &str = "multiscopic.toml";
/// A Middlebury 2014 calibration file, read when present in a set folder.
pub const CALIBRATION_FILE: &str = "calib.txt";
/// Focal length of the Middlebury 2006 scenes at third size (3740 px at full size).
pub const MIDDLEBURY_2006_THIRD_FOCAL_PX: f64 = 3740.0 / 3.0;
/// Most views per set (a 5 × 5 grid).
pub const MAX_VIEWS: usize = 25;

/// One view file and its grid offset in baselines (`FILE@DX` or `FILE@DX:DY`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct ViewFile {
    /// File name in the set folder (`.png` is appended when there is no extension).
    pub file: String,
    /// Offset `[dx, dy]` in baselines along the reference camera's x (right) and y (down).
    pub offset: [i32; 2],
}

impl FromStr for ViewFile {
    type Err = ImportError;

    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let bad = |reason: &'static str| ImportError::BadViewSpec {
            spec: spec.to_owned(),
            reason,
        };
        let (file, offset) = spec
            .rsplit_once('@')
            .ok_or_else(|| bad("expected FILE@DX or FILE@DX:DY, e.g. view0@-1 or im5@1:-1"))?;
        if file.is_empty() {
            return Err(bad("the file name is empty"));
        }
        let number = |s: &str| {
            s.trim()
                .parse::<i32>()
                .ok()
                .filter(|v| v.abs() <= 64)
                .ok_or_else(|| bad("an offset is not an integer in -64..=64 (baselines)"))
        };
        let offset = match offset.split_once(':') {
            Some((dx, dy)) => [number(dx)?, number(dy)?],
            None => [number(offset)?, 0],
        };
        Ok(Self {
            file: file.to_owned(),
            offset,
        })
    }
}

impl TryFrom<String> for ViewFile {
    type Error = ImportError;

    fn try_from(spec: String) -> Result<Self, Self::Error> {
        spec.parse()
    }
}

impl From<ViewFile> for String {
    fn from(view: ViewFile) -> Self {
        view.to_string()
    }
}

impl std::fmt::Display for ViewFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.offset {
            [dx, 0] => write!(f, "{}@{dx}", self.file),
            [dx, dy] => write!(f, "{}@{dx}:{dy}", self.file),
        }
    }
}

/// The views of a named layout, given its files in the layout's file order.
pub fn layout_views(layout: RigKind, files: &[String]) -> Result<Vec<ViewFile>, ImportError> {
    let slots = layout.file_order();
    if files.len() != slots.len() {
        return Err(ImportError::ViewCount {
            layout: layout.name(),
            expected: slots.len(),
            given: files.len(),
        });
    }
    Ok(slots
        .iter()
        .zip(files)
        .map(|(slot, file)| ViewFile {
            file: file.clone(),
            offset: slot.grid_offset,
        })
        .collect())
}

fn default_scale() -> f64 {
    1.0
}

fn default_fov() -> f64 {
    crate::camera::DEFAULT_HORIZONTAL_FOV_DEG
}

/// What to import and how to interpret it; also the schema of [`DESCRIPTION_FILE`] (every field
/// but `views` optional there).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImportConfig {
    /// View files with their grid offsets; the one at `[0, 0]` is the reference.
    pub views: Vec<ViewFile>,
    /// Ground-truth disparity file of the reference view, if any.
    #[serde(default)]
    pub ground_truth: Option<String>,
    /// Stored value ÷ scale = disparity (pixels) between the reference and a direct neighbour.
    #[serde(default = "default_scale")]
    pub ground_truth_scale: f64,
    /// Baseline between the reference and a direct neighbour (mm); required unless the set
    /// folder has a `calib.txt`.
    #[serde(default)]
    pub baseline_mm: Option<f64>,
    /// Focal length (pixels); when absent (and no `calib.txt`) it follows from
    /// `horizontal_fov_deg`.
    #[serde(default)]
    pub focal_px: Option<f64>,
    /// Principal point of the reference `[cx, cy]` (pixels); default: the image centre.
    #[serde(default)]
    pub principal_point_px: Option<[f64; 2]>,
    /// Principal-point offset between adjacent views (pixels, Middlebury 2014's `doffs`):
    /// depth `z = f·b / (d + doffs)`.
    #[serde(default)]
    pub doffs_px: f64,
    /// Horizontal field of view used when no focal length is known (deg).
    #[serde(default = "default_fov")]
    pub horizontal_fov_deg: f64,
    /// Calibration file in each set folder (Middlebury 2014 format); default: `calib.txt` when
    /// present. A named file that is missing is an error.
    #[serde(default)]
    pub calibration: Option<String>,
    /// Only these set folders (names), all when empty.
    #[serde(default)]
    pub sets: Vec<String>,
    /// Smallest disparity to search (px, signed: negative for a converged rig, whose far points
    /// shift the other way); written into the log, where replay takes it unless told otherwise.
    #[serde(default)]
    pub min_disparity: Option<i32>,
    /// Disparities to search (from `min_disparity`, or from 0); written into the log.
    #[serde(default)]
    pub num_disparities: Option<u32>,
}

impl Default for ImportConfig {
    /// The Middlebury 2006 three-view setting of the paper at third size: left view0, centre
    /// view1, right view2, ground truth disp1.png ÷ 12, 40 mm between adjacent views, focal length
    /// 3740/3 px.
    fn default() -> Self {
        Self {
            views: ["view0@-1", "view1@0", "view2@1"]
                .iter()
                .filter_map(|s| s.parse().ok())
                .collect(),
            ground_truth: Some("disp1".into()),
            ground_truth_scale: 12.0,
            baseline_mm: Some(40.0),
            focal_px: Some(MIDDLEBURY_2006_THIRD_FOCAL_PX),
            principal_point_px: None,
            doffs_px: 0.0,
            horizontal_fov_deg: crate::camera::DEFAULT_HORIZONTAL_FOV_DEG,
            calibration: None,
            sets: Vec::new(),
            min_disparity: None,
            num_disparities: None,
        }
    }
}

/// Settings given on the command line; each one given replaces the description file's (or the
/// default's). Shared by `record import` and `replay eval`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ImportOverrides {
    /// Views with their offsets in baselines: FILE@DX on a line, FILE@DX:DY on a grid; the view at
    /// 0 is the reference (e.g. view0@-1,view1@0,view2@1,view3@2). Without offsets, the files of
    /// --layout in its order.
    #[arg(long, value_delimiter = ',', value_name = "FILE@DX[:DY]")]
    pub views: Vec<String>,
    /// Named layout for --views given without offsets (three-view: left,center,right; five-view:
    /// center,left,right,top,bottom; line5: the five from left to right; grid3x3 and grid-cross:
    /// row-major).
    #[arg(long, value_enum)]
    pub layout: Option<RigKind>,
    /// Ground-truth disparity of the reference: PNG/TIFF/BMP (8 or 16 bit) or PGM (0 = unknown),
    /// or PFM (inf = unknown).
    #[arg(long, value_name = "FILE")]
    pub ground_truth: Option<String>,
    /// Import without ground truth.
    #[arg(long, conflicts_with = "ground_truth")]
    pub no_ground_truth: bool,
    /// Stored ground-truth value ÷ scale = disparity (px) to a direct neighbour (default 1; 12 for
    /// the built-in Middlebury 2006 setting).
    #[arg(long, value_name = "SCALE")]
    pub ground_truth_scale: Option<f64>,
    /// Baseline between the reference and a direct neighbour (mm).
    #[arg(long, value_name = "MM")]
    pub baseline_mm: Option<f64>,
    /// Focal length (pixels); Middlebury 2006 third size: 1246.67.
    #[arg(long, value_name = "PX")]
    pub focal_px: Option<f64>,
    /// Principal point of the reference, CX,CY (pixels); default: the image centre.
    #[arg(long, value_parser = parse_pair, value_name = "CX,CY", allow_hyphen_values = true)]
    pub principal_point_px: Option<[f64; 2]>,
    /// Principal-point offset between adjacent views (px, Middlebury 2014 doffs).
    #[arg(long, value_name = "PX", allow_hyphen_values = true)]
    pub doffs_px: Option<f64>,
    /// Horizontal field of view used when no focal length is known (degrees).
    #[arg(long, value_name = "DEG")]
    pub fov_deg: Option<f64>,
    /// Calibration file in each set folder (Middlebury 2014 calib.txt format; default: calib.txt
    /// when present).
    #[arg(long, value_name = "FILE")]
    pub calibration: Option<String>,
    /// Only these set folders (comma-separated names).
    #[arg(long, value_delimiter = ',')]
    pub sets: Vec<String>,
}

fn parse_pair(text: &str) -> Result<[f64; 2], String> {
    let (a, b) = text.split_once(',').ok_or_else(|| format!("'{text}' is not CX,CY"))?;
    let number = |s: &str| {
        s.trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| format!("'{s}' in '{text}' is not a number"))
    };
    Ok([number(a)?, number(b)?])
}

impl ImportConfig {
    /// The search range the folder asks for: `min_disparity` (default 0) and `num_disparities`
    /// (default: replay's per-set default from the width), `None` when it names neither.
    pub fn disparity_range(&self) -> Option<crate::DisparityRange> {
        if self.min_disparity.is_none() && self.num_disparities.is_none() {
            return None;
        }
        Some(crate::DisparityRange {
            min_disparity: self.min_disparity.unwrap_or(0),
            num_disparities: self.num_disparities,
        })
    }
}

impl ImportOverrides {
    /// `base` with the given settings replaced.
    pub fn apply(&self, base: &ImportConfig) -> Result<ImportConfig, ImportError> {
        let mut config = base.clone();
        if !self.views.is_empty() {
            let with_offsets = self.views.iter().filter(|v| v.contains('@')).count();
            config.views = if with_offsets == self.views.len() {
                self.views.iter().map(|v| v.parse()).collect::<Result<_, _>>()?
            } else if with_offsets == 0 {
                let layout = self.layout.ok_or_else(|| ImportError::BadViewSpec {
                    spec: self.views.join(","),
                    reason: "views without offsets need --layout (or give each as FILE@DX)",
                })?;
                layout_views(layout, &self.views)?
            } else {
                return Err(ImportError::BadViewSpec {
                    spec: self.views.join(","),
                    reason: "give every view an offset (FILE@DX) or none (with --layout)",
                });
            };
        } else if let Some(layout) = self.layout {
            // A layout alone: the base's files in order.
            let files: Vec<String> = base.views.iter().map(|v| v.file.clone()).collect();
            config.views = layout_views(layout, &files)?;
        }
        if let Some(file) = &self.ground_truth {
            config.ground_truth = Some(file.clone());
            if self.ground_truth_scale.is_none() && base.ground_truth.as_deref() != Some(file.as_str()) {
                config.ground_truth_scale = 1.0;
            }
        }
        if self.no_ground_truth {
            config.ground_truth = None;
        }
        if let Some(scale) = self.ground_truth_scale {
            config.ground_truth_scale = scale;
        }
        if let Some(b) = self.baseline_mm {
            config.baseline_mm = Some(b);
        }
        if let Some(f) = self.focal_px {
            config.focal_px = Some(f);
        }
        if let Some(point) = self.principal_point_px {
            config.principal_point_px = Some(point);
        }
        if let Some(d) = self.doffs_px {
            config.doffs_px = d;
        }
        if let Some(fov) = self.fov_deg {
            config.horizontal_fov_deg = fov;
            if self.focal_px.is_none() {
                config.focal_px = None;
            }
        }
        if let Some(file) = &self.calibration {
            config.calibration = Some(file.clone());
        }
        if !self.sets.is_empty() {
            config.sets = self.sets.clone();
        }
        config.validate()?;
        Ok(config)
    }
}

/// Errors of the importer; each names the file and what was wrong with it.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The directory holds neither view files nor set directories with them.
    #[error(
        "'{dir}' holds no image set: expected {expected} in it or in its sub-directories (or a {DESCRIPTION_FILE})"
    )]
    NoSets {
        /// Directory searched.
        dir: PathBuf,
        /// Files looked for.
        expected: String,
    },
    /// A view specification does not parse.
    #[error("view '{spec}': {reason}")]
    BadViewSpec {
        /// The text given.
        spec: String,
        /// What is wrong.
        reason: &'static str,
    },
    /// The layout needs a different number of views (an adaptive capture has no fixed layout:
    /// its one slot is the centre; name the views with their offsets instead).
    #[error(
        "layout {layout} has {expected} views, but {given} view files were named (give each file its offset, FILE@DX[:DY], for other layouts)"
    )]
    ViewCount {
        /// Layout name.
        layout: &'static str,
        /// Views of the layout.
        expected: usize,
        /// Names given.
        given: usize,
    },
    /// Two views at one grid offset.
    #[error("views '{first}' and '{second}' are both at offset {offset:?}: each offset may be used once")]
    DuplicateOffset {
        /// Offset.
        offset: [i32; 2],
        /// First file.
        first: String,
        /// Second file.
        second: String,
    },
    /// No view at offset 0.
    #[error("no reference view: none of {views} is at offset 0 (FILE@0)")]
    NoReference {
        /// The views given.
        views: String,
    },
    /// A set needs a neighbour.
    #[error("only one view ({view}): a set needs the reference and at least one neighbour")]
    NoNeighbour {
        /// The view given.
        view: String,
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
    /// A file is not an image (or ground truth) this importer understands.
    #[error("cannot decode '{path}': {reason}")]
    Decode {
        /// File.
        path: PathBuf,
        /// Cause.
        reason: String,
    },
    /// A description or calibration file does not parse.
    #[error("'{path}' is not a valid {what}: {reason}")]
    BadFile {
        /// File.
        path: PathBuf,
        /// What the file should be.
        what: &'static str,
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
    /// No baseline is known.
    #[error("no baseline for the set in '{dir}': give baseline_mm (--baseline-mm) or a calib.txt")]
    NoBaseline {
        /// Set folder.
        dir: PathBuf,
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

impl ImportError {
    /// Whether the error is in the settings (command line or description) rather than the files.
    pub fn is_usage(&self) -> bool {
        matches!(
            self,
            Self::BadViewSpec { .. }
                | Self::ViewCount { .. }
                | Self::DuplicateOffset { .. }
                | Self::NoReference { .. }
                | Self::NoNeighbour { .. }
                | Self::InvalidOption { .. }
        )
    }
}

/// Extensions tried, in order, for a view or ground-truth name given without one.
const IMAGE_EXTENSIONS: [&str; 9] = ["png", "ppm", "pgm", "pfm", "jpg", "jpeg", "tif", "tiff", "bmp"];

/// The file a view or ground-truth name stands for in `dir`: the name itself when such a file
/// exists (`im0.png`, or a stem with dots such as `scene1.row3.col3.ppm`), else the name with
/// the first image extension that exists (`view1` → `view1.png`, `scene1.row3.col3` →
/// `scene1.row3.col3.ppm`), else the name with `.png` (for the error message).
fn file_in(dir: &Path, name: &str) -> PathBuf {
    let exact = dir.join(name);
    if exact.is_file() {
        return exact;
    }
    IMAGE_EXTENSIONS
        .iter()
        .map(|ext| dir.join(format!("{name}.{ext}")))
        .find(|p| p.is_file())
        .unwrap_or_else(|| dir.join(format!("{name}.png")))
}

impl ImportConfig {
    /// Checks the views (one reference, offsets used once, at least one neighbour) and the
    /// numbers.
    pub fn validate(&self) -> Result<(), ImportError> {
        let list = || {
            self.views
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        };
        if self.views.len() > MAX_VIEWS {
            return Err(ImportError::BadViewSpec {
                spec: list(),
                reason: "more than 25 views",
            });
        }
        for (i, a) in self.views.iter().enumerate() {
            if let Some(b) = self.views[..i].iter().find(|b| b.offset == a.offset) {
                return Err(ImportError::DuplicateOffset {
                    offset: a.offset,
                    first: b.file.clone(),
                    second: a.file.clone(),
                });
            }
        }
        if !self.views.iter().any(|v| v.offset == [0, 0]) {
            return Err(ImportError::NoReference { views: list() });
        }
        if self.views.len() < 2 {
            return Err(ImportError::NoNeighbour { view: list() });
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
        positive("ground_truth_scale", self.ground_truth_scale)?;
        positive("horizontal_fov_deg", self.horizontal_fov_deg)?;
        if self.horizontal_fov_deg >= 180.0 {
            return Err(ImportError::InvalidOption {
                field: "horizontal_fov_deg",
                value: self.horizontal_fov_deg,
                reason: "must be below 180",
            });
        }
        if let Some(b) = self.baseline_mm {
            positive("baseline_mm", b)?;
        }
        if let Some(n) = self.num_disparities
            && !(1..=1024).contains(&n)
        {
            return Err(ImportError::InvalidOption {
                field: "num_disparities",
                value: f64::from(n),
                reason: "must be 1 to 1024",
            });
        }
        if let Some(m) = self.min_disparity
            && m.unsigned_abs() > 1 << 20
        {
            return Err(ImportError::InvalidOption {
                field: "min_disparity",
                value: f64::from(m),
                reason: "must be within ±1048576",
            });
        }
        if let Some(f) = self.focal_px {
            positive("focal_px", f)?;
        }
        if !self.doffs_px.is_finite() {
            return Err(ImportError::InvalidOption {
                field: "doffs_px",
                value: self.doffs_px,
                reason: "must be a finite number",
            });
        }
        if let Some([cx, cy]) = self.principal_point_px
            && !(cx.is_finite() && cy.is_finite())
        {
            return Err(ImportError::InvalidOption {
                field: "principal_point_px",
                value: if cx.is_finite() { cy } else { cx },
                reason: "must be finite",
            });
        }
        Ok(())
    }

    /// The layout name of these offsets: a named rig when they are one (`three-view`, `line5`,
    /// …), else `custom`.
    pub fn rig_name(&self) -> &'static str {
        let mut offsets: Vec<[i32; 2]> = self.views.iter().map(|v| v.offset).collect();
        offsets.sort_unstable();
        RigKind::ALL
            .iter()
            .find(|rig| {
                let mut named: Vec<[i32; 2]> = rig.capture_order().iter().map(|s| s.grid_offset).collect();
                named.sort_unstable();
                named == offsets
            })
            .map_or("custom", |rig| rig.name())
    }
}

/// Reads a description file.
pub fn read_description(path: &Path) -> Result<ImportConfig, ImportError> {
    let text = std::fs::read_to_string(path).map_err(|source| ImportError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let config: ImportConfig = toml::from_str(&text).map_err(|e| ImportError::BadFile {
        path: path.to_path_buf(),
        what: "dataset description (TOML)",
        reason: e.to_string(),
    })?;
    config.validate().map_err(|e| ImportError::BadFile {
        path: path.to_path_buf(),
        what: "dataset description",
        reason: e.to_string(),
    })?;
    Ok(config)
}

/// The sets of a folder with their settings: the folder itself when it holds a set (a
/// description file or one of its view files), else each sub-folder that does (sorted, filtered
/// by `sets`). Settings: the command line's over the nearest description file over the
/// Middlebury 2006 default.
pub fn plan_import(dir: &Path, overrides: &ImportOverrides) -> Result<Vec<(PathBuf, ImportConfig)>, ImportError> {
    if !dir.is_dir() {
        return Err(ImportError::Read {
            path: dir.to_path_buf(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "not a directory"),
        });
    }
    let description = |d: &Path| {
        let path = d.join(DESCRIPTION_FILE);
        path.is_file().then(|| read_description(&path)).transpose()
    };
    let top = description(dir)?;
    let top_config = overrides.apply(top.as_ref().unwrap_or(&ImportConfig::default()))?;
    let holds_set = |d: &Path, config: &ImportConfig| config.views.iter().any(|v| file_in(d, &v.file).is_file());
    if holds_set(dir, &top_config) {
        return Ok(vec![(dir.to_path_buf(), top_config)]);
    }
    let entries = std::fs::read_dir(dir).map_err(|source| ImportError::Read {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut dirs: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    let mut sets = Vec::new();
    for sub in dirs {
        let own = description(&sub)?;
        let config = match (&own, &top) {
            (Some(own), _) => overrides.apply(own)?,
            _ => top_config.clone(),
        };
        let selected = config.sets.is_empty()
            || sub
                .file_name()
                .is_some_and(|n| config.sets.iter().any(|s| s.as_str() == n.to_string_lossy()));
        if selected && (own.is_some() || holds_set(&sub, &config)) {
            sets.push((sub, config));
        }
    }
    if sets.is_empty() {
        return Err(ImportError::NoSets {
            dir: dir.to_path_buf(),
            expected: top_config
                .views
                .iter()
                .map(|v| {
                    file_in(dir, &v.file)
                        .file_name()
                        .map_or_else(|| v.file.clone(), |n| n.to_string_lossy().into_owned())
                })
                .collect::<Vec<_>>()
                .join(", "),
        });
    }
    Ok(sets)
}

/// A Middlebury 2014 `calib.txt`: `cam0=[f 0 cx; 0 f cy; 0 0 1]`, `doffs`, `baseline` (mm),
/// `width`, `height`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    /// Focal length (px).
    pub focal_px: f64,
    /// Principal point of the reference (px).
    pub principal_point_px: [f64; 2],
    /// Principal-point offset between adjacent views (px).
    pub doffs_px: f64,
    /// Baseline between adjacent views (mm).
    pub baseline_mm: f64,
    /// Image size, when the file gives it.
    pub size: Option<(u32, u32)>,
}

/// Parses a Middlebury 2014 `calib.txt`.
pub fn read_calibration(path: &Path) -> Result<Calibration, ImportError> {
    let text = std::fs::read_to_string(path).map_err(|source| ImportError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let bad = |reason: String| ImportError::BadFile {
        path: path.to_path_buf(),
        what: "Middlebury calib.txt",
        reason,
    };
    let mut fields = std::collections::HashMap::new();
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let (key, value) = line
            .split_once('=')
            .ok_or_else(|| bad(format!("line '{line}' is not KEY=VALUE")))?;
        fields.insert(key.trim().to_owned(), value.trim().to_owned());
    }
    let number = |key: &str| -> Result<f64, ImportError> {
        let value = fields.get(key).ok_or_else(|| bad(format!("no '{key}='")))?;
        value
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| bad(format!("{key}={value} is not a number")))
    };
    let cam0 = fields.get("cam0").ok_or_else(|| bad("no 'cam0='".into()))?;
    let k: Vec<f64> = cam0
        .trim_matches(|c| c == '[' || c == ']')
        .split(|c: char| c == ';' || c.is_whitespace())
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<f64>()
                .map_err(|_| bad(format!("cam0 entry '{s}' is not a number")))
        })
        .collect::<Result<_, _>>()?;
    if k.len() != 9 || !k[0].is_finite() || k[0] <= 0.0 {
        return Err(bad(format!("cam0 = {cam0} is not a 3×3 camera matrix with f > 0")));
    }
    let size = match (number("width"), number("height")) {
        (Ok(w), Ok(h)) if w >= 1.0 && h >= 1.0 => Some((w as u32, h as u32)),
        _ => None,
    };
    let baseline_mm = number("baseline")?;
    if baseline_mm <= 0.0 {
        return Err(bad(format!("baseline={baseline_mm} is not positive")));
    }
    Ok(Calibration {
        focal_px: k[0],
        principal_point_px: [k[2], k[5]],
        doffs_px: number("doffs").unwrap_or(0.0),
        baseline_mm,
        size,
    })
}

/// Reads a view image as 8-bit RGB (grey replicated, 16 bit scaled).
fn read_rgb(path: &Path) -> Result<(u32, u32, Vec<u8>), ImportError> {
    let decoded = decode(path)?;
    let rgb = decoded.to_rgb8();
    Ok((rgb.width(), rgb.height(), rgb.into_raw()))
}

fn decode(path: &Path) -> Result<image::DynamicImage, ImportError> {
    let reader = image::ImageReader::open(path)
        .map_err(|source| ImportError::Read {
            path: path.to_path_buf(),
            source,
        })?
        .with_guessed_format()
        .map_err(|source| ImportError::Read {
            path: path.to_path_buf(),
            source,
        })?;
    reader.decode().map_err(|e| ImportError::Decode {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })
}

fn first_channel<T: Copy + Into<f64>>(raw: &[T], channels: usize) -> Vec<f64> {
    raw.chunks_exact(channels).map(|p| p[0].into()).collect()
}

/// Reads a ground-truth file as raw values (see the module docs for the formats); unknown =
/// `NaN`.
pub fn read_ground_truth(path: &Path) -> Result<(u32, u32, Vec<f64>), ImportError> {
    let extension = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let unknown_if_zero = |v: f64| if v == 0.0 { f64::NAN } else { v };
    match extension.as_str() {
        "pfm" => {
            let (w, h, data) = viz::files::read_pfm(path).map_err(|e| ImportError::Decode {
                path: path.to_path_buf(),
                reason: format!("not a single-channel PFM ({e})"),
            })?;
            let values = data
                .iter()
                .map(|v| if v.is_finite() { f64::from(*v) } else { f64::NAN })
                .collect();
            Ok((w as u32, h as u32, values))
        }
        "pgm" | "ppm" | "pnm" => {
            let (w, h, values) = read_pnm_raw(path)?;
            Ok((w, h, values.into_iter().map(unknown_if_zero).collect()))
        }
        _ => {
            use image::DynamicImage as D;
            let decoded = decode(path)?;
            let (w, h) = (decoded.width(), decoded.height());
            let values = match &decoded {
                D::ImageLuma8(b) => first_channel(b.as_raw(), 1),
                D::ImageLumaA8(b) => first_channel(b.as_raw(), 2),
                D::ImageRgb8(b) => first_channel(b.as_raw(), 3),
                D::ImageRgba8(b) => first_channel(b.as_raw(), 4),
                D::ImageLuma16(b) => first_channel(b.as_raw(), 1),
                D::ImageLumaA16(b) => first_channel(b.as_raw(), 2),
                D::ImageRgb16(b) => first_channel(b.as_raw(), 3),
                D::ImageRgba16(b) => first_channel(b.as_raw(), 4),
                D::ImageRgb32F(b) => first_channel(b.as_raw(), 3),
                D::ImageRgba32F(b) => first_channel(b.as_raw(), 4),
                other => {
                    return Err(ImportError::Decode {
                        path: path.to_path_buf(),
                        reason: format!(
                            "{:?} is not a ground-truth format (8/16-bit grey or RGB)",
                            other.color()
                        ),
                    });
                }
            };
            Ok((w, h, values.into_iter().map(unknown_if_zero).collect()))
        }
    }
}

/// Raw sample values of a binary (P5/P6) or ASCII (P2/P3) PGM/PPM, first channel, without
/// scaling to the maxval.
fn read_pnm_raw(path: &Path) -> Result<(u32, u32, Vec<f64>), ImportError> {
    let bytes = std::fs::read(path).map_err(|source| ImportError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let bad = |reason: &str| ImportError::Decode {
        path: path.to_path_buf(),
        reason: reason.to_owned(),
    };
    // Header: magic, width, height, maxval, separated by whitespace and `#` comments.
    let mut tokens = Vec::new();
    let mut i = 0;
    while tokens.len() < 4 && i < bytes.len() {
        if bytes[i] == b'#' {
            while i < bytes.len() && bytes[i] != b'\n' {
                i += 1;
            }
        } else if bytes[i].is_ascii_whitespace() {
            i += 1;
        } else {
            let start = i;
            while i < bytes.len() && !bytes[i].is_ascii_whitespace() {
                i += 1;
            }
            tokens.push(String::from_utf8_lossy(&bytes[start..i]).into_owned());
        }
    }
    // Exactly one whitespace byte ends the header of a binary file.
    let body = &bytes[(i + 1).min(bytes.len())..];
    let [magic, w, h, maxval] = tokens.as_slice() else {
        return Err(bad("truncated PNM header"));
    };
    let channels = match magic.as_str() {
        "P2" | "P5" => 1,
        "P3" | "P6" => 3,
        _ => return Err(bad("not a PGM/PPM (P2, P3, P5 or P6)")),
    };
    let parse = |s: &str| s.parse::<u32>().ok().filter(|v| *v > 0);
    let (w, h, maxval) = match (parse(w), parse(h), parse(maxval)) {
        (Some(w), Some(h), Some(m)) if m <= 65535 => (w, h, m),
        _ => return Err(bad("bad PNM width, height or maxval")),
    };
    let samples = w as usize * h as usize * channels;
    let values: Vec<f64> = if matches!(magic.as_str(), "P2" | "P3") {
        let text = String::from_utf8_lossy(&bytes[i..]);
        text.split_ascii_whitespace()
            .take(samples)
            .map(|s| s.parse::<f64>().map_err(|_| bad("bad ASCII PNM sample")))
            .collect::<Result<_, _>>()?
    } else if maxval > 255 {
        body.chunks_exact(2)
            .take(samples)
            .map(|b| f64::from(u16::from_be_bytes([b[0], b[1]])))
            .collect()
    } else {
        body.iter().take(samples).map(|v| f64::from(*v)).collect()
    };
    if values.len() < samples {
        return Err(bad("truncated PNM data"));
    }
    Ok((w, h, first_channel(&values, channels)))
}

/// Reads one set folder.
pub fn import_set(dir: &Path, index: u32, config: &ImportConfig) -> Result<CapturedSet, ImportError> {
    config.validate()?;
    let images = config
        .views
        .iter()
        .map(|view| {
            let path = file_in(dir, &view.file);
            read_rgb(&path).map(|image| (path, image))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let reference_position = config.views.iter().position(|v| v.offset == [0, 0]).unwrap_or(0);
    let (width, height) = (images[reference_position].1.0, images[reference_position].1.1);
    for (path, (w, h, _)) in &images {
        if (*w, *h) != (width, height) {
            return Err(ImportError::SizeMismatch {
                path: path.clone(),
                width: *w,
                height: *h,
                expected_width: width,
                expected_height: height,
            });
        }
    }
    let calibration_path = match &config.calibration {
        Some(name) => Some(dir.join(name)),
        None => Some(dir.join(CALIBRATION_FILE)).filter(|p| p.is_file()),
    };
    let calibration = calibration_path.as_deref().map(read_calibration).transpose()?;
    if let (Some(c), Some(path)) = (&calibration, &calibration_path)
        && let Some((w, h)) = c.size
        && (w, h) != (width, height)
    {
        return Err(ImportError::SizeMismatch {
            path: path.clone(),
            width: w,
            height: h,
            expected_width: width,
            expected_height: height,
        });
    }
    let mut camera = PinholeCamera::from_horizontal_fov(width, height, config.horizontal_fov_deg);
    let (baseline_mm, doffs) = match &calibration {
        Some(c) => {
            camera.fx = c.focal_px;
            camera.fy = c.focal_px;
            [camera.cx, camera.cy] = c.principal_point_px;
            (c.baseline_mm, c.doffs_px)
        }
        None => {
            if let Some(f) = config.focal_px {
                camera.fx = f;
                camera.fy = f;
            }
            if let Some([cx, cy]) = config.principal_point_px {
                camera.cx = cx;
                camera.cy = cy;
            }
            let baseline = config
                .baseline_mm
                .ok_or_else(|| ImportError::NoBaseline { dir: dir.to_path_buf() })?;
            (baseline, config.doffs_px)
        }
    };
    let baseline_m = baseline_mm / 1000.0;
    let depth = match &config.ground_truth {
        Some(name) => {
            let path = file_in(dir, name);
            let (w, h, values) = read_ground_truth(&path)?;
            if (w, h) != (width, height) {
                return Err(ImportError::SizeMismatch {
                    path,
                    width: w,
                    height: h,
                    expected_width: width,
                    expected_height: height,
                });
            }
            let focal_times_baseline = camera.fx * baseline_m;
            Some(
                values
                    .into_iter()
                    .map(|v| {
                        let d = v / config.ground_truth_scale + doffs;
                        if d.is_finite() && d > 0.0 && v.is_finite() && v != 0.0 {
                            (focal_times_baseline / d) as f32
                        } else {
                            0.0
                        }
                    })
                    .collect::<Vec<f32>>(),
            )
        }
        None => None,
    };
    let set_time = SIM_EPOCH_NANOS + u64::from(index) * SET_SPACING_SECS * 1_000_000_000;
    let mut views: Vec<CapturedView> = config
        .views
        .iter()
        .zip(images)
        .enumerate()
        .map(|(i, (view, (_, (_, _, rgb))))| {
            let [dx, dy] = view.offset.map(f64::from);
            let mut view_camera = camera;
            view_camera.cx += dx * doffs;
            view_camera.cy += dy * doffs;
            CapturedView::new(
                (&role_for_offset(view.offset), view.offset),
                view_camera,
                Isometry3::translation(dx * baseline_m, dy * baseline_m, 0.0),
                set_time + i as u64 * VIEW_SPACING_MS * 1_000_000,
                rgb,
            )
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
    debug_assert_eq!(views[0].role, REFERENCE_ROLE);
    Ok(CapturedSet {
        index,
        name: dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| format!("set-{index}")),
        rig: config.rig_name().to_owned(),
        baseline_m,
        motion: Vec::new(),
        views,
        disparity_range: config.disparity_range(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_view_name_finds_its_file_with_or_without_extension_and_with_dots_in_its_stem() {
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        for name in ["scene1.row3.col3.ppm", "view0.png", "disp.pfm"] {
            std::fs::write(dir.path().join(name), b"x").unwrap_or_else(|e| panic!("{e}"));
        }
        let found = |name: &str| {
            file_in(dir.path(), name)
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
        };
        assert_eq!(found("scene1.row3.col3.ppm").as_deref(), Some("scene1.row3.col3.ppm"));
        assert_eq!(found("scene1.row3.col3").as_deref(), Some("scene1.row3.col3.ppm"));
        assert_eq!(found("view0").as_deref(), Some("view0.png"));
        assert_eq!(found("disp").as_deref(), Some("disp.pfm"));
        assert_eq!(
            found("missing").as_deref(),
            Some("missing.png"),
            "the name in the error"
        );
    }

    #[test]
    fn view_specs_parse_and_print() {
        let v: ViewFile = "scene1.row3.col1.ppm@-2".parse().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(v.file, "scene1.row3.col1.ppm");
        assert_eq!(v.offset, [-2, 0]);
        assert_eq!(v.to_string(), "scene1.row3.col1.ppm@-2");
        let g: ViewFile = "a@b.png@1:-1".parse().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((g.file.as_str(), g.offset), ("a@b.png", [1, -1]));
        assert_eq!(g.to_string(), "a@b.png@1:-1");
        for bad in ["view0", "@1", "v@x", "v@1:", "v@100"] {
            assert!(bad.parse::<ViewFile>().is_err(), "{bad}");
        }
    }

    #[test]
    fn settings_are_checked() {
        let with = |views: &[&str]| ImportConfig {
            views: views
                .iter()
                .map(|v| v.parse().unwrap_or_else(|e| panic!("{e}")))
                .collect(),
            ..ImportConfig::default()
        };
        assert!(matches!(
            with(&["a@-1", "b@1"]).validate(),
            Err(ImportError::NoReference { .. })
        ));
        assert!(matches!(
            with(&["a@0", "b@1", "c@1"]).validate(),
            Err(ImportError::DuplicateOffset { offset: [1, 0], .. })
        ));
        assert!(matches!(
            with(&["a@0"]).validate(),
            Err(ImportError::NoNeighbour { .. })
        ));
        assert_eq!(with(&["a@-1", "b@0", "c@1"]).rig_name(), "three-view");
        assert_eq!(with(&["a@-2", "b@-1", "c@0", "d@1", "e@2"]).rig_name(), "line5");
        assert_eq!(with(&["a@-1", "b@0", "c@1", "d@2"]).rig_name(), "custom");
    }

    #[test]
    fn descriptions_parse_with_defaults_and_reject_unknown_fields() {
        let config: ImportConfig =
            toml::from_str("views = [\"l.png@-1\", \"c.png@0\"]\nground_truth = \"gt.pfm\"\nbaseline_mm = 10\n")
                .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(config.ground_truth_scale, 1.0);
        assert_eq!(config.focal_px, None);
        assert_eq!(config.views[0].offset, [-1, 0]);
        assert!(toml::from_str::<ImportConfig>("views = [\"c@0\", \"r@1\"]\nbaseline = 3\n").is_err());
        assert!(toml::from_str::<ImportConfig>("views = [\"c\"]\n").is_err());
    }

    #[test]
    fn overrides_replace_what_they_name() {
        let base = ImportConfig::default();
        let overrides = ImportOverrides {
            views: vec!["im0.png@0".into(), "im1.png@1".into()],
            ground_truth: Some("disp0.pfm".into()),
            ..ImportOverrides::default()
        };
        let config = overrides.apply(&base).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(config.views.len(), 2);
        // A new ground-truth file does not inherit the Middlebury 2006 scale.
        assert_eq!(config.ground_truth_scale, 1.0);
        assert_eq!(config.baseline_mm, Some(40.0));
        let layout = ImportOverrides {
            views: vec!["c".into(), "l".into(), "r".into(), "t".into(), "b".into()],
            layout: Some(RigKind::FiveView),
            ..ImportOverrides::default()
        };
        let config = layout.apply(&base).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(config.views[3].offset, [0, -1]);
        let mixed = ImportOverrides {
            views: vec!["c@0".into(), "r".into()],
            ..ImportOverrides::default()
        };
        assert!(mixed.apply(&base).is_err_and(|e| e.is_usage()));
    }

    #[test]
    fn middlebury_2014_calibration_parses() {
        let dir = std::env::temp_dir().join(format!("calib-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
        let path = dir.join("calib.txt");
        std::fs::write(
            &path,
            "cam0=[3997.684 0 1176.728; 0 3997.684 1011.728; 0 0 1]\ncam1=[3997.684 0 1307.839; 0 3997.684 1011.728; 0 0 1]\ndoffs=131.111\nbaseline=193.001\nwidth=2964\nheight=1988\nndisp=280\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let c = read_calibration(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(c.focal_px, 3997.684);
        assert_eq!(c.principal_point_px, [1176.728, 1011.728]);
        assert_eq!(
            (c.doffs_px, c.baseline_mm, c.size),
            (131.111, 193.001, Some((2964, 1988)))
        );
        std::fs::write(&path, "cam0=[1 2 3]\nbaseline=1\n").unwrap_or_else(|e| panic!("{e}"));
        assert!(read_calibration(&path).is_err_and(|e| e.to_string().contains("calib.txt")));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
