//! Streams to the Rerun viewer (0.36): spawn a viewer, connect to one, or save an `.rrd` file,
//! with one recording per run and a blueprint built in code.
//!
//! Entity tree (roles and methods readable in the paths):
//! - `world/table`, `world/arm/base`, `world/arm/links` (capsules between the joint origins,
//!   animated on the `capture_time` timeline), `world/arm/flange`;
//! - `world/camera/<role>`: `Transform3D` (world from camera) and `Pinhole`; below it `image`
//!   and `ground_truth_depth` (`DepthImage`, metres);
//! - `world/camera/center/<method>`: the result as a `DepthImage` under the centre pinhole, so the
//!   3D view back-projects it to a point cloud; `results/<method>/error`: |disparity − truth|
//!   (a colour-mapped `DepthImage` in 1/64 px, so that the viewer shows its scale);
//!   `results/<method>/confidence`: the method's per-pixel confidence (0 … 1, turbo);
//! - `cost/<source>`: a bounded cost volume `Tensor` (height × width × disparity, the `fuse::volume::CostVolume` order);
//!   `cost_curves/<probe>/<source>`: cost against disparity (`Scalars` on the `disparity` timeline);
//! - `metrics/<method>/<name>`: `Scalars` per set; `alignment`: the alignment report (`TextLog`).

use std::path::PathBuf;

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use rerun::blueprint::components::{PanelState, PlayState};
use rerun::blueprint::{
    Blueprint, BlueprintPanel, ContainerLike, Grid, Horizontal, SelectionPanel, Spatial2DView, Spatial3DView, Tabs,
    TensorView, TextLogView, TimePanel, TimeSeriesView, Vertical,
};
use rerun::{RecordingStream, RecordingStreamBuilder};

/// Timeline of everything the arm and cameras do (simulated or logged time).
pub const CAPTURE_TIMELINE: &str = "capture_time";
/// Timeline along which cost curves are drawn.
pub const DISPARITY_TIMELINE: &str = "disparity";
/// Timeline of per-set figures.
pub const SET_TIMELINE: &str = "set";

/// Where a recording goes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ViewerSink {
    /// Start a viewer (the `rerun` executable on `PATH`) and stream to it.
    Spawn,
    /// Write an `.rrd` file.
    Save(PathBuf),
    /// Stream to a running viewer, e.g. `rerun+http://127.0.0.1:9876/proxy`.
    Connect(String),
}

impl ViewerSink {
    /// Parses the words after `--rerun`: `spawn`, `save FILE.rrd` or `connect [URL]`.
    pub fn parse(words: &[String]) -> Result<Self, VizError> {
        match words {
            [mode] if mode == "spawn" => Ok(Self::Spawn),
            [mode, path] if mode == "save" => Ok(Self::Save(PathBuf::from(path))),
            [mode] if mode == "connect" => Ok(Self::Connect(DEFAULT_CONNECT_URL.to_owned())),
            [mode, url] if mode == "connect" => Ok(Self::Connect(url.clone())),
            _ => Err(VizError::Usage { given: words.join(" ") }),
        }
    }
}

/// The URL a local viewer (`rerun`) listens on by default.
pub const DEFAULT_CONNECT_URL: &str = "rerun+http://127.0.0.1:9876/proxy";

/// Errors of the Rerun streams.
#[derive(Debug, thiserror::Error)]
pub enum VizError {
    /// `--rerun` was given something else than `spawn`, `save FILE` or `connect [URL]`.
    #[error("--rerun {given}: expected `spawn`, `save FILE.rrd` or `connect [URL]`")]
    Usage {
        /// The words given.
        given: String,
    },
    /// No viewer could be started.
    #[error(
        "cannot start the Rerun viewer: {reason}\n  install it with `pip install rerun-sdk==0.36.3` (or `cargo install rerun-cli --version 0.36.3`), \
         or write a file instead with `--rerun save run.rrd` and open it later with `rerun run.rrd`"
    )]
    Spawn {
        /// What the SDK said.
        reason: String,
    },
    /// The `.rrd` file could not be created.
    #[error("cannot write the Rerun recording '{path}': {reason}")]
    Save {
        /// File.
        path: PathBuf,
        /// What the SDK said.
        reason: String,
    },
    /// The viewer URL is not usable.
    #[error("cannot connect to the Rerun viewer at '{url}': {reason}")]
    Connect {
        /// URL.
        url: String,
        /// What the SDK said.
        reason: String,
    },
    /// Logging an entity failed.
    #[error("cannot log '{entity}' to Rerun: {reason}")]
    Log {
        /// Entity path.
        entity: String,
        /// What the SDK said.
        reason: String,
    },
    /// A buffer does not match its size.
    #[error("'{entity}': {len} values for {expected}")]
    Size {
        /// Entity path.
        entity: String,
        /// Values given.
        len: usize,
        /// Values expected.
        expected: usize,
    },
}

/// A camera of a view set as the viewer needs it.
#[derive(Debug, Clone, Copy)]
pub struct CameraView<'a> {
    /// Role (`center`, `left`, …).
    pub role: &'a str,
    /// Pose (world from the optical frame: x right, y down, z forward).
    pub world_from_camera: &'a Isometry3<f64>,
    /// Intrinsics `[fx, fy, cx, cy]` (pixels).
    pub intrinsics: [f64; 4],
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// 8-bit RGB, row-major.
    pub rgb: &'a [u8],
    /// Ground-truth z-depth (m, 0 = unknown), when known.
    pub depth_m: Option<&'a [f32]>,
    /// Image time (ns since the epoch).
    pub time_nanos: u64,
}

/// One candidate view of a plan as drawn: where the camera would be and how it scored.
#[derive(Debug, Clone)]
pub struct PlannedFrustum {
    /// Pose (world from the optical frame).
    pub world_from_camera: Isometry3<f64>,
    /// Score relative to the plan's best (0 … 1).
    pub score: f32,
    /// Label (role and expected pixels).
    pub label: String,
    /// Whether the plan chose it.
    pub chosen: bool,
    /// Whether the arm can take it (unreachable ones are drawn grey).
    pub reachable: bool,
}

/// What the layout shows: the camera roles and the methods.
#[derive(Debug, Clone, Default)]
pub struct Layout {
    /// Camera roles, reference first.
    pub roles: Vec<String>,
    /// Methods whose results are logged.
    pub methods: Vec<String>,
    /// Sources of cost volumes (`fused` and the neighbour roles).
    pub cost_sources: Vec<String>,
}

/// The blueprint: the views in a grid, the 3D scene, the cost tensors and curves, the metrics and
/// the alignment report, so that a user opening the file sees the comparison at once.
pub fn blueprint(layout: &Layout) -> Blueprint {
    // Each camera's own image: the depth maps logged under the same pinhole (ground truth, the
    // methods' results) get their own tabs instead of covering it.
    let mut cameras: Vec<ContainerLike> = layout
        .roles
        .iter()
        .map(|role| {
            let origin = format!("world/camera/{role}");
            let image = Spatial2DView::new(role.as_str())
                .with_origin(origin.as_str())
                .with_contents([format!("+ {origin}/image")]);
            if role == REFERENCE_ROLE {
                Tabs::new([
                    ContainerLike::from(image),
                    Spatial2DView::new(format!("{role} ground truth"))
                        .with_origin(origin.as_str())
                        .with_contents([format!("+ {origin}/ground_truth_depth")])
                        .into(),
                ])
                .into()
            } else {
                image.into()
            }
        })
        .collect();
    for method in &layout.methods {
        cameras.push(
            Tabs::new([
                ContainerLike::from(
                    Spatial2DView::new(format!("{method} error"))
                        .with_origin(format!("results/{method}"))
                        .with_contents([
                            format!("+ results/{method}/error"),
                            format!("+ results/{method}/no_estimate"),
                        ]),
                ),
                Spatial2DView::new(format!("{method} confidence"))
                    .with_origin(format!("results/{method}/confidence"))
                    .into(),
                Spatial2DView::new(format!("{method} depth"))
                    .with_origin(format!("world/camera/{REFERENCE_ROLE}"))
                    .with_contents([format!("+ world/camera/{REFERENCE_ROLE}/{method}")])
                    .into(),
            ])
            .into(),
        );
    }
    let grid = Grid::new(cameras).with_name("views");
    let scene = Spatial3DView::new("3D scene").with_origin("world");
    let tensors: Vec<ContainerLike> = layout
        .cost_sources
        .iter()
        .map(|source| {
            TensorView::new(format!("cost {source}"))
                .with_origin(format!("cost/{source}"))
                .into()
        })
        .collect();
    let analysis = Tabs::new([
        ContainerLike::from(Tabs::new(tensors).with_name("cost volumes")),
        TimeSeriesView::new("cost curves").with_origin("cost_curves").into(),
        TimeSeriesView::new("metrics").with_origin("metrics").into(),
        TextLogView::new("alignment").with_origin("alignment").into(),
    ])
    .with_name("analysis");
    Blueprint::new(Horizontal::new([
        ContainerLike::from(Vertical::new([
            ContainerLike::from(scene),
            ContainerLike::from(analysis),
        ])),
        grid.into(),
    ]))
    // Room for the views: the blueprint tree and selection panels start collapsed.
    .with_blueprint_panel(BlueprintPanel::new().with_state(PanelState::Collapsed))
    .with_selection_panel(SelectionPanel::new().with_state(PanelState::Collapsed))
    // Open at the end of the capture (every camera and result present), not at its first instant.
    .with_time_panel(
        TimePanel::new()
            .with_timeline(CAPTURE_TIMELINE)
            .with_play_state(PlayState::Following),
    )
}

/// The role whose camera the results are computed for.
pub const REFERENCE_ROLE: &str = "center";

/// One recording, open on its sink.
pub struct Viewer {
    recording: RecordingStream,
}

/// Error maps are sent as bytes in steps of 1/64 px (0 = no ground truth, 255 = ≥ 4 px).
const ERROR_STEPS_PER_PX: f32 = 64.0;

/// A link of the arm as drawn: capsule radius (m) per segment between consecutive joint origins.
const LINK_RADIUS_M: f32 = 0.05;

impl Viewer {
    /// Opens a recording named `app_id` on `sink`, with `layout`'s blueprint.
    pub fn create(app_id: &'static str, sink: &ViewerSink, layout: &Layout) -> Result<Self, VizError> {
        let builder = RecordingStreamBuilder::new(app_id).with_blueprint(blueprint(layout));
        let recording = match sink {
            ViewerSink::Spawn => builder.spawn().map_err(|e| VizError::Spawn { reason: e.to_string() })?,
            ViewerSink::Save(path) => builder.save(path).map_err(|e| VizError::Save {
                path: path.clone(),
                reason: e.to_string(),
            })?,
            ViewerSink::Connect(url) => builder.connect_grpc_opts(url.as_str()).map_err(|e| VizError::Connect {
                url: url.clone(),
                reason: e.to_string(),
            })?,
        };
        let viewer = Self { recording };
        // The optical frame convention of every camera below `world`.
        viewer.log_static("world", &rerun::ViewCoordinates::RIGHT_HAND_Z_UP())?;
        Ok(viewer)
    }

    fn log<AS: ?Sized + rerun::AsComponents>(&self, entity: &str, archetype: &AS) -> Result<(), VizError> {
        self.recording.log(entity, archetype).map_err(|e| VizError::Log {
            entity: entity.to_owned(),
            reason: e.to_string(),
        })
    }

    fn log_static<AS: ?Sized + rerun::AsComponents>(&self, entity: &str, archetype: &AS) -> Result<(), VizError> {
        self.recording.log_static(entity, archetype).map_err(|e| VizError::Log {
            entity: entity.to_owned(),
            reason: e.to_string(),
        })
    }

    /// Sets the capture-time timeline (ns since the epoch).
    pub fn set_capture_time(&self, time_nanos: u64) {
        self.recording
            .set_timestamp_nanos_since_epoch(CAPTURE_TIMELINE, time_nanos as i64);
    }

    /// Sets the set timeline.
    pub fn set_set_index(&self, set: u32) {
        self.recording.set_time_sequence(SET_TIMELINE, i64::from(set));
    }

    /// The work table: a box whose top is the plane z = 0 (static).
    pub fn log_table(&self, centre_m: [f32; 2], size_m: [f32; 2]) -> Result<(), VizError> {
        let thickness = 0.04;
        self.log_static(
            "world/table",
            &rerun::Boxes3D::from_centers_and_half_sizes(
                [(centre_m[0], centre_m[1], -thickness / 2.0)],
                [(size_m[0] / 2.0, size_m[1] / 2.0, thickness / 2.0)],
            )
            .with_colors([rerun::Color::from_rgb(150, 120, 90)]),
        )
    }

    /// The arm at the current capture time: the base as a box, capsules between consecutive
    /// joint origins (`world_from_links`: each joint frame, base first, flange last).
    pub fn log_arm(&self, world_from_links: &[Isometry3<f64>]) -> Result<(), VizError> {
        if let Some(base) = world_from_links.first() {
            let t = base.translation.vector;
            self.log(
                "world/arm/base",
                &rerun::Boxes3D::from_centers_and_half_sizes(
                    [(t.x as f32, t.y as f32, (t.z as f32 - 0.05).max(0.05))],
                    [(0.09, 0.09, 0.05)],
                )
                .with_colors([rerun::Color::from_rgb(60, 60, 70)]),
            )?;
        }
        let mut lengths = Vec::new();
        let mut translations = Vec::new();
        let mut rotations = Vec::new();
        for pair in world_from_links.windows(2) {
            let (a, b) = (pair[0].translation.vector, pair[1].translation.vector);
            let direction = b - a;
            let length = direction.norm();
            if length < 1e-6 {
                continue;
            }
            let rotation = UnitQuaternion::rotation_between(&Vector3::z(), &(direction / length))
                .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
            lengths.push(length as f32);
            translations.push([a.x as f32, a.y as f32, a.z as f32]);
            rotations.push(quaternion(&rotation));
        }
        let count = lengths.len();
        self.log(
            "world/arm/links",
            &rerun::Capsules3D::from_lengths_and_radii(lengths, vec![LINK_RADIUS_M; count])
                .with_translations(translations)
                .with_quaternions(rotations)
                .with_colors(vec![rerun::Color::from_rgb(90, 140, 200); count]),
        )?;
        if let Some(flange) = world_from_links.last() {
            self.log("world/arm/flange", &transform(flange))?;
            self.log("world/arm/flange", &rerun::TransformAxes3D::new(0.08))?;
        }
        Ok(())
    }

    /// One camera of a set at its capture time: pose, pinhole, image and ground-truth depth.
    pub fn log_camera(&self, view: &CameraView<'_>) -> Result<(), VizError> {
        let base = format!("world/camera/{}", view.role);
        self.set_capture_time(view.time_nanos);
        self.log(&base, &transform(view.world_from_camera))?;
        let [fx, fy, cx, cy] = view.intrinsics;
        self.log(
            &base,
            &rerun::Pinhole::from_focal_length_and_resolution(
                [fx as f32, fy as f32],
                [view.width as f32, view.height as f32],
            )
            .with_principal_point([cx as f32, cy as f32])
            .with_image_plane_distance(0.05),
        )?;
        let pixels = (view.width * view.height) as usize;
        let image_entity = format!("{base}/image");
        if view.rgb.len() != pixels * 3 {
            return Err(VizError::Size {
                entity: image_entity,
                len: view.rgb.len(),
                expected: pixels * 3,
            });
        }
        self.log(
            &image_entity,
            &rerun::Image::from_rgb24(view.rgb.to_vec(), [view.width, view.height]),
        )?;
        if let Some(depth) = view.depth_m {
            self.log_depth(&format!("{base}/ground_truth_depth"), depth, [view.width, view.height])?;
        }
        Ok(())
    }

    /// A depth map in metres (0 or non-finite = unknown), sent as 16-bit millimetres (half the
    /// bytes of `f32`, the precision of the depth PNG files).
    fn log_depth(&self, entity: &str, depth_m: &[f32], size: [u32; 2]) -> Result<(), VizError> {
        let expected = (size[0] * size[1]) as usize;
        if depth_m.len() != expected {
            return Err(VizError::Size {
                entity: entity.to_owned(),
                len: depth_m.len(),
                expected,
            });
        }
        let bytes: Vec<u8> = depth_m
            .iter()
            .flat_map(|z| {
                let mm = if z.is_finite() && *z > 0.0 {
                    (z * 1000.0).round().min(65_535.0) as u16
                } else {
                    0
                };
                mm.to_le_bytes()
            })
            .collect();
        self.log(
            entity,
            &rerun::DepthImage::from_data_type_and_bytes(bytes, size, rerun::datatypes::ChannelDatatype::U16)
                .with_meter(1000.0)
                .with_colormap(rerun::components::Colormap::Turbo),
        )
    }

    /// A method's per-pixel confidence (0 … 1) as `results/<method>/confidence`, a colour map
    /// in 1/255 steps (u8, turbo: dark where the method is unsure).
    pub fn log_confidence(&self, method: &str, size: [u32; 2], confidence: &[f32]) -> Result<(), VizError> {
        let levels: Vec<u8> = confidence
            .iter()
            .map(|c| {
                if c.is_finite() {
                    (c.clamp(0.0, 1.0) * 255.0).round() as u8
                } else {
                    0
                }
            })
            .collect();
        self.log(
            &format!("results/{method}/confidence"),
            &rerun::DepthImage::from_data_type_and_bytes(levels, size, rerun::datatypes::ChannelDatatype::U8)
                .with_meter(255.0)
                .with_colormap(rerun::components::Colormap::Turbo)
                .with_depth_range([0.0, 1.0]),
        )
    }

    /// A method's result for the centre view at the current capture time: its depth as a
    /// `DepthImage` under the centre pinhole (back-projected to a point cloud in 3D; failed
    /// matches far behind the scene are left out, see [`drop_far_outliers`]), and, with ground
    /// truth, the absolute disparity error as a colour map (0 … `error_scale_px`); pixels without
    /// an estimate, when there are any, as a mask (`results/<method>/no_estimate`). Depth is
    /// `z = f·b / (d + doffs)` (`disparity_offset_px`: the principal points' offset between
    /// adjacent views, 0 unless the set's calibration says otherwise).
    #[allow(clippy::too_many_arguments)]
    pub fn log_result(
        &self,
        method: &str,
        size: [u32; 2],
        disparity_px: &[f32],
        focal_baseline_px_m: f64,
        disparity_offset_px: f64,
        ground_truth_disparity_px: Option<&[f32]>,
        error_scale_px: f32,
    ) -> Result<(), VizError> {
        let mut depth: Vec<f32> = disparity_px
            .iter()
            .map(|d| {
                let d = f64::from(*d) + disparity_offset_px;
                if d.is_finite() && d > 0.0 {
                    (focal_baseline_px_m / d) as f32
                } else {
                    0.0
                }
            })
            .collect();
        drop_far_outliers(&mut depth);
        self.log_depth(&format!("world/camera/{REFERENCE_ROLE}/{method}"), &depth, size)?;
        // Pixels without an estimate (graph cuts' occlusions, …) as a segmentation mask: class 1.
        let missing: Vec<u8> = disparity_px.iter().map(|d| u8::from(!d.is_finite())).collect();
        if missing.contains(&1) {
            let entity = format!("results/{method}/no_estimate");
            self.log_static(
                &entity,
                &rerun::AnnotationContext::new([(1, "no estimate (occluded)", rerun::Rgba32::from_rgb(255, 0, 255))]),
            )?;
            self.log(
                &entity,
                &rerun::SegmentationImage::new(
                    missing,
                    rerun::components::ImageFormat::segmentation(size, rerun::datatypes::ChannelDatatype::U8),
                ),
            )?;
        }
        if let Some(truth) = ground_truth_disparity_px {
            // |error| in steps of 1/64 px (u8, capped), colour-mapped over 0 … error_scale_px by
            // the viewer: a quarter of the bytes of an RGB image. 0 also marks "no ground truth".
            let error: Vec<u8> = disparity_px
                .iter()
                .zip(truth)
                .map(|(d, t)| {
                    if t.is_finite() && d.is_finite() {
                        ((d - t).abs() * ERROR_STEPS_PER_PX).round().clamp(1.0, 255.0) as u8
                    } else {
                        0
                    }
                })
                .collect();
            self.log(
                &format!("results/{method}/error"),
                &rerun::DepthImage::from_data_type_and_bytes(error, size, rerun::datatypes::ChannelDatatype::U8)
                    .with_meter(ERROR_STEPS_PER_PX)
                    .with_colormap(rerun::components::Colormap::Turbo)
                    .with_depth_range([0.0, f64::from(error_scale_px * ERROR_STEPS_PER_PX)]),
            )?;
        }
        Ok(())
    }

    /// A plan of the next view on the capture timeline: every candidate's frustum at `world/plan`
    /// (`intrinsics` `[fx, fy, cx, cy]` and `size` of the camera; drawn 4 cm deep), coloured by
    /// score from blue (worst) to red (best), unreachable ones grey, the chosen one thicker; and
    /// the estimate the plan was made from as the centre's `plan` depth (`focal_baseline_px_m`:
    /// `f·b`) and `results/plan/confidence`.
    pub fn log_plan(
        &self,
        frusta: &[PlannedFrustum],
        (intrinsics, size): ([f64; 4], [u32; 2]),
        estimate: Option<(&[f32], &[f32], f64)>,
    ) -> Result<(), VizError> {
        let [fx, fy, cx, cy] = intrinsics;
        let depth = 0.04;
        let corners: Vec<nalgebra::Point3<f64>> = [
            (0.0, 0.0),
            (f64::from(size[0]), 0.0),
            (f64::from(size[0]), f64::from(size[1])),
            (0.0, f64::from(size[1])),
        ]
        .iter()
        .map(|(u, v)| nalgebra::Point3::new((u - cx) / fx * depth, (v - cy) / fy * depth, depth))
        .collect();
        let mut strips = Vec::new();
        let (mut colours, mut radii, mut labels) = (Vec::new(), Vec::new(), Vec::new());
        for frustum in frusta {
            let at = |p: &nalgebra::Point3<f64>| {
                let w = frustum.world_from_camera * p;
                [w.x as f32, w.y as f32, w.z as f32]
            };
            let apex = at(&nalgebra::Point3::origin());
            let c: Vec<[f32; 3]> = corners.iter().map(at).collect();
            strips.push(vec![apex, c[0], c[1], c[2], c[3], c[0], apex, c[1], c[2], apex, c[3]]);
            let t = frustum.score.clamp(0.0, 1.0);
            colours.push(if frustum.reachable {
                rerun::Color::from_rgb((255.0 * t) as u8, 60, (255.0 * (1.0 - t)) as u8)
            } else {
                rerun::Color::from_rgb(128, 128, 128)
            });
            radii.push(if frustum.chosen { 0.0015f32 } else { 0.0006 });
            labels.push(frustum.label.clone());
        }
        self.log(
            "world/plan",
            &rerun::LineStrips3D::new(strips)
                .with_colors(colours)
                .with_radii(radii)
                .with_labels(labels),
        )?;
        if let Some((disparity_px, confidence, focal_baseline_px_m)) = estimate {
            self.log_result("plan", size, disparity_px, focal_baseline_px_m, 0.0, None, 4.0)?;
            self.log_confidence("plan", size, confidence)?;
        }
        Ok(())
    }

    /// Figures of a method for the current set, one series each (`metrics/<method>/<name>`).
    pub fn log_metrics(&self, method: &str, figures: &[(&str, f64)]) -> Result<(), VizError> {
        for (name, value) in figures {
            if value.is_finite() {
                self.log(&format!("metrics/{method}/{name}"), &rerun::Scalars::single(*value))?;
            }
        }
        Ok(())
    }

    /// The alignment report of a set: `level` is `INFO`, `WARN` or `ERROR`.
    pub fn log_alignment(&self, text: &str, level: &str) -> Result<(), VizError> {
        self.log(
            "alignment",
            &rerun::TextLog::new(text).with_level(rerun::TextLogLevel::from(level)),
        )
    }

    /// A cost volume `[y][x][d]` (bytes, 255 = no correspondence) as a tensor
    /// `height × width × disparity`: the viewer shows the two large dimensions as the image and
    /// puts a slider on disparity.
    pub fn log_cost_volume(
        &self,
        source: &str,
        costs: &[u8],
        [height, width, num_disparities]: [usize; 3],
    ) -> Result<(), VizError> {
        let entity = format!("cost/{source}");
        if costs.len() != height * width * num_disparities {
            return Err(VizError::Size {
                entity,
                len: costs.len(),
                expected: height * width * num_disparities,
            });
        }
        let data = rerun::datatypes::TensorData::new(
            vec![height as u64, width as u64, num_disparities as u64],
            rerun::datatypes::TensorBuffer::U8(costs.to_vec().into()),
        )
        .with_dim_names(["height", "width", "disparity"]);
        self.log(&entity, &rerun::Tensor::new(data))
    }

    /// The costs of one probe pixel against disparity, for one source (a neighbour or `fused`):
    /// `costs[i]` belongs to disparity `first_disparity + i · step` (a downsampled volume has
    /// `step` > 1).
    pub fn log_cost_curve(
        &self,
        probe: &str,
        source: &str,
        first_disparity: i64,
        step: usize,
        costs: &[f32],
    ) -> Result<(), VizError> {
        let entity = format!("cost_curves/{probe}/{source}");
        for (i, cost) in costs.iter().enumerate() {
            if cost.is_finite() {
                self.recording
                    .set_time_sequence(DISPARITY_TIMELINE, first_disparity + (i * step) as i64);
                self.log(&entity, &rerun::Scalars::single(f64::from(*cost)))?;
            }
        }
        self.recording.disable_timeline(DISPARITY_TIMELINE);
        Ok(())
    }

    /// Sends everything still buffered (blocks until the sink has it).
    pub fn finish(self) -> Result<(), VizError> {
        self.recording.flush_blocking().map_err(|e| VizError::Log {
            entity: "(flush)".to_owned(),
            reason: e.to_string(),
        })
    }
}

/// Depths beyond this multiple of the 95th percentile are not drawn.
const FAR_LIMIT_PER_P95_DEPTH: f32 = 2.0;

/// Marks unknown (0) the depths beyond [`FAR_LIMIT_PER_P95_DEPTH`] × their 95th percentile.
///
/// A failed match at a disparity near zero puts a point tens of metres behind the scene; the
/// viewer frames the 3D view on everything drawn, so a handful of them shrink the arm, the table
/// and the cloud itself to a streak. The disparity maps, files and metrics keep every value.
pub fn drop_far_outliers(depth_m: &mut [f32]) {
    let mut valid: Vec<f32> = depth_m.iter().copied().filter(|d| *d > 0.0).collect();
    if valid.is_empty() {
        return;
    }
    let rank = (valid.len() - 1) * 95 / 100;
    let (_, p95, _) = valid.select_nth_unstable_by(rank, f32::total_cmp);
    let far_limit = *p95 * FAR_LIMIT_PER_P95_DEPTH;
    for d in depth_m.iter_mut() {
        if *d > far_limit {
            *d = 0.0;
        }
    }
}

fn quaternion(rotation: &UnitQuaternion<f64>) -> rerun::Quaternion {
    let q = rotation.coords;
    rerun::Quaternion::from_xyzw([q.x as f32, q.y as f32, q.z as f32, q.w as f32])
}

/// `Transform3D` of a pose (the parent from the entity's frame).
fn transform(pose: &Isometry3<f64>) -> rerun::Transform3D {
    let t = pose.translation.vector;
    rerun::Transform3D::from_translation_rotation([t.x as f32, t.y as f32, t.z as f32], quaternion(&pose.rotation))
}

/// Writes training curves as a Rerun recording: each series `(entity, [(step, value)])` as
/// `Scalars` on a `step` sequence timeline (`rerun curves.rrd` plots them, one line per entity).
/// The file is rewritten whole, so that a resumed run's file holds its full history.
pub fn write_curves(
    path: &std::path::Path,
    app_id: &'static str,
    series: &[(&str, Vec<(i64, f64)>)],
) -> Result<(), VizError> {
    let recording = RecordingStreamBuilder::new(app_id)
        .save(path)
        .map_err(|e| VizError::Save {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
    for (entity, points) in series {
        for (step, value) in points {
            if !value.is_finite() {
                continue;
            }
            recording.set_time_sequence("step", *step);
            recording
                .log(*entity, &rerun::Scalars::single(*value))
                .map_err(|e| VizError::Log {
                    entity: (*entity).to_owned(),
                    reason: e.to_string(),
                })?;
        }
    }
    recording.flush_blocking().map_err(|e| VizError::Log {
        entity: "(flush)".to_owned(),
        reason: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn far_outliers_are_dropped_and_the_scene_kept() {
        // A plane at 0.8 m with two failed matches at 33 m and one unknown pixel.
        let mut depth = vec![0.8_f32; 100];
        depth[3] = 33.0;
        depth[50] = 40.0;
        depth[7] = 0.0;
        depth[9] = 1.5;
        drop_far_outliers(&mut depth);
        assert_eq!((depth[3], depth[50], depth[7]), (0.0, 0.0, 0.0));
        assert_eq!(depth[9], 1.5, "within twice the 95th percentile");
        assert_eq!(depth.iter().filter(|d| **d == 0.8).count(), 96);
        drop_far_outliers(&mut []);
    }

    #[test]
    fn sinks_parse_from_the_command_line_words() {
        let words = |s: &str| s.split_whitespace().map(str::to_owned).collect::<Vec<_>>();
        assert_eq!(ViewerSink::parse(&words("spawn")).ok(), Some(ViewerSink::Spawn));
        assert_eq!(
            ViewerSink::parse(&words("save run.rrd")).ok(),
            Some(ViewerSink::Save(PathBuf::from("run.rrd")))
        );
        assert_eq!(
            ViewerSink::parse(&words("connect")).ok(),
            Some(ViewerSink::Connect(DEFAULT_CONNECT_URL.to_owned()))
        );
        assert!(matches!(ViewerSink::parse(&words("show")), Err(VizError::Usage { .. })));
        assert!(matches!(ViewerSink::parse(&words("save")), Err(VizError::Usage { .. })));
    }
}
