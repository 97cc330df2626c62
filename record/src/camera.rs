//! The pinhole camera model shared by the renderer, the log and the importer.
//!
//! Conventions (OpenCV/ROS, as in `foxglove.CameraCalibration`): camera frame x right, y down,
//! z forward along the optical axis; the centre of pixel `(col, row)` sits at image coordinates
//! `(col, row)`, so a centred principal point is `((width − 1)/2, (height − 1)/2)`.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// The IMX322 sensor of the paper's capture rig: 1920 × 1080.
pub const DEFAULT_RESOLUTION: (u32, u32) = (1920, 1080);
/// Horizontal field of view of the default lens (degrees).
pub const DEFAULT_HORIZONTAL_FOV_DEG: f64 = 60.0;

/// An ideal pinhole camera (no distortion).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PinholeCamera {
    /// Image width (pixels).
    pub width: u32,
    /// Image height (pixels).
    pub height: u32,
    /// Focal length along x (pixels).
    pub fx: f64,
    /// Focal length along y (pixels).
    pub fy: f64,
    /// Principal point x (pixels).
    pub cx: f64,
    /// Principal point y (pixels).
    pub cy: f64,
}

impl PinholeCamera {
    /// A camera with square pixels, a centred principal point and the given horizontal field of view.
    pub fn from_horizontal_fov(width: u32, height: u32, horizontal_fov_deg: f64) -> Self {
        let fx = 0.5 * f64::from(width) / (0.5 * horizontal_fov_deg.to_radians()).tan();
        Self {
            width,
            height,
            fx,
            fy: fx,
            cx: (f64::from(width) - 1.0) / 2.0,
            cy: (f64::from(height) - 1.0) / 2.0,
        }
    }

    /// The intrinsic matrix K.
    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// K as the 9 row-major values of `foxglove.CameraCalibration.k`.
    pub fn k_row_major(&self) -> [f64; 9] {
        [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]
    }

    /// Unit ray direction in the camera frame through image coordinates `(u, v)`.
    pub fn ray_direction(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0).normalize()
    }

    /// Projects a camera-frame point to image coordinates; `None` behind the camera.
    pub fn project(&self, point_camera: &Vector3<f64>) -> Option<(f64, f64)> {
        (point_camera.z > 0.0).then(|| {
            (
                self.fx * point_camera.x / point_camera.z + self.cx,
                self.fy * point_camera.y / point_camera.z + self.cy,
            )
        })
    }

    /// Number of pixels.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn principal_ray_projects_to_principal_point() {
        let camera = PinholeCamera::from_horizontal_fov(1920, 1080, 60.0);
        let ray = camera.ray_direction(camera.cx, camera.cy);
        assert!((ray - Vector3::z()).norm() < 1e-12);
        // The image edge sits at half the field of view.
        let edge = camera.ray_direction(camera.cx + 960.0, camera.cy);
        assert!((edge.x.atan2(edge.z).to_degrees() - 30.0).abs() < 1e-9);
        let point = Vector3::new(0.1, -0.05, 0.8);
        let (u, v) = camera.project(&point).unwrap();
        let back = camera.ray_direction(u, v) * point.norm();
        assert!((back - point).norm() < 1e-12);
    }
}
