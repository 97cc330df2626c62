//! `record --rerun`: the simulated capture streamed to the Rerun viewer as it happens (the arm,
//! the table, each camera with its image), through `viz::stream`. Also the table drawing that
//! `replay --rerun` shares, and the layout file (`<log>.rbl`) the viewer opens a log with.

use std::path::{Path, PathBuf};

use viz::log_blueprint::{LogLayout, LogView, app_id_for_log, blueprint_path_for_log, save_log_blueprint};
use viz::stream::{CameraView, Viewer, VizError};

use crate::log::{depth_topic, image_topic, surface_topic};
use crate::ur10::{Joints, Ur10};
use crate::{CapturedSet, CapturedView};

/// Width of a view's image drawn in the 3D scene, as a fraction of the distance between the
/// closest two views (the images sit side by side with a gap).
const DRAWN_IMAGE_WIDTH_PER_SPACING: f64 = 0.8;

/// The views of a set as the viewer imports a log of it (its entity paths are the log's topics),
/// with image planes drawn at a distance that fits the rig's spacing.
pub fn log_layout(set: &CapturedSet) -> LogLayout {
    let views = set
        .views
        .iter()
        .map(|view| LogView {
            role: view.role.clone(),
            image_entity: image_topic(&view.role),
            depth_entity: view.depth_m.is_some().then(|| depth_topic(&view.role)),
            hidden_in_3d: view
                .surface_class
                .is_some()
                .then(|| surface_topic(&view.role))
                .into_iter()
                .collect(),
        })
        .collect();
    let positions: Vec<_> = set
        .views
        .iter()
        .map(|v| v.world_from_camera.translation.vector)
        .collect();
    let spacing_m = positions
        .iter()
        .enumerate()
        .flat_map(|(i, a)| positions[i + 1..].iter().map(move |b| (a - b).norm()))
        .filter(|d| *d > 0.0)
        .fold(f64::INFINITY, f64::min);
    // An image `width` px wide at distance d spans d · width / fx metres.
    let image_plane_distance_m = set.views.first().and_then(|view| {
        let width_per_distance = f64::from(view.camera.width) / view.camera.fx;
        let distance = DRAWN_IMAGE_WIDTH_PER_SPACING * spacing_m / width_per_distance;
        (distance.is_finite() && distance > 0.0).then_some(distance as f32)
    });
    LogLayout {
        views,
        image_plane_distance_m,
    }
}

/// Writes the viewer layout of the log at `log_path` (from [`log_layout`] of its first set) beside
/// it, as `<stem>.rbl`, so that `rerun <log> <stem>.rbl` opens on the cameras and images; returns
/// its path.
pub fn write_log_blueprint(log_path: &Path, layout: &LogLayout) -> Result<PathBuf, VizError> {
    let path = blueprint_path_for_log(log_path);
    save_log_blueprint(&path, app_id_for_log(log_path)?, layout)?;
    Ok(path)
}

/// The work table under the scene (static): a top of [`crate::scene::TABLE_DRAWN_SIZE_M`]
/// centred on the work area.
pub fn log_table(viewer: &Viewer) -> Result<(), VizError> {
    let [x, y, _] = crate::scene::WORK_AREA_CENTER_M;
    let [w, d] = crate::scene::TABLE_DRAWN_SIZE_M;
    viewer.log_table([x as f32, y as f32], [w as f32, d as f32])
}

/// The arm and cameras as the capture goes.
pub struct LiveCapture {
    viewer: Viewer,
    arm: Ur10,
}

impl LiveCapture {
    /// Opens a viewer on `sink` laid out for views of `roles` and starts on it.
    pub fn open(sink: &viz::stream::ViewerSink, roles: Vec<String>, arm: Ur10) -> Result<Self, VizError> {
        let layout = viz::stream::Layout {
            roles,
            ..viz::stream::Layout::default()
        };
        Self::new(Viewer::create("multiscopic_record", sink, &layout)?, arm)
    }

    /// Starts on an open viewer: logs the table once.
    pub fn new(viewer: Viewer, arm: Ur10) -> Result<Self, VizError> {
        log_table(&viewer)?;
        Ok(Self { viewer, arm })
    }

    fn arm_at(&self, joints: &Joints) -> Result<(), VizError> {
        self.viewer.log_arm(&self.arm.frames_from_base(joints))
    }

    /// One view as soon as it is rendered: the arm where it took it, the camera and its image.
    pub fn view(&self, view: &CapturedView) -> Result<(), VizError> {
        self.viewer.set_capture_time(view.capture_time_nanos);
        if let Some(joints) = &view.joints {
            self.arm_at(joints)?;
        }
        self.viewer.log_camera(&CameraView {
            role: &view.role,
            world_from_camera: &view.world_from_camera,
            intrinsics: [view.camera.fx, view.camera.fy, view.camera.cx, view.camera.cy],
            width: view.camera.width,
            height: view.camera.height,
            rgb: &view.rgb,
            depth_m: view.depth_m.as_deref(),
            time_nanos: view.capture_time_nanos,
        })
    }

    /// A plan of an adaptive set at the time it was made: the candidates' frusta coloured by
    /// score, and the depth and confidence it was planned from (`camera`: the reference's
    /// intrinsics; `baseline_m`: the set's baseline).
    pub fn plan(
        &self,
        step: &crate::adaptive::PlanStep,
        estimate: Option<&fuse::DisparityImage>,
        camera: &crate::camera::PinholeCamera,
        baseline_m: f64,
    ) -> Result<(), VizError> {
        self.viewer.set_capture_time(step.time_nanos);
        let confidence_or_none = estimate.map(|e| e.confidence.clone().unwrap_or_else(|| vec![0.0; e.data.len()]));
        self.viewer.log_plan(
            &step.frusta(),
            (
                [camera.fx, camera.fy, camera.cx, camera.cy],
                [camera.width, camera.height],
            ),
            estimate
                .zip(confidence_or_none.as_deref())
                .map(|(e, c)| (e.data.as_slice(), c, camera.fx * baseline_m)),
        )
    }

    /// The arm's motion between the views of a finished set, on the capture timeline.
    pub fn motion(&self, set: &CapturedSet) -> Result<(), VizError> {
        for sample in &set.motion {
            self.viewer.set_capture_time(sample.time_nanos);
            self.arm_at(&sample.joints)?;
        }
        Ok(())
    }

    /// Sends what is buffered and closes the recording.
    pub fn finish(self) -> Result<(), VizError> {
        self.viewer.finish()
    }
}
