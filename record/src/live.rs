//! `record --rerun`: the simulated capture streamed to the Rerun viewer as it happens (the arm,
//! the table, each camera with its image), through `viz::stream`. Also the table drawing that
//! `replay --rerun` shares.

use viz::stream::{CameraView, Viewer, VizError};

use crate::ur10::{Joints, Ur10};
use crate::{CapturedSet, CapturedView};

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
