//! Where the arm can take the camera: a candidate view's pose (the reference camera's pose moved
//! in its own image plane by a grid offset), the UR10's inverse kinematics within its joint
//! limits, and the arm and camera kept clear of the table.
//!
//! Poses are in the arm's base frame, which is the log's world frame for every simulated capture
//! (the table top is the plane `z = 0`). The arm is modelled by the polyline through its joint
//! origins, with [`LINK_RADIUS_M`] of thickness; the camera by a sphere of [`CAMERA_RADIUS_M`].

use nalgebra::Isometry3;
use serde::Serialize;

use crate::ur10::{JOINT_COUNT, Joints, KinematicsError, Ur10};

/// Thickness (radius, m) of the arm's links about the polyline through its joint origins.
pub const LINK_RADIUS_M: f64 = 0.06;
/// Radius (m) of the camera's body about its optical centre.
pub const CAMERA_RADIUS_M: f64 = 0.04;
/// Clearance (m) kept between the table and any part of the arm or the camera.
pub const TABLE_CLEARANCE_M: f64 = 0.02;
/// Points checked per link segment.
const SAMPLES_PER_LINK: usize = 8;

/// Why a candidate pose cannot be taken.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReachError {
    /// No inverse-kinematics solution within the joint limits.
    #[error(transparent)]
    Kinematics(#[from] KinematicsError),
    /// A part of the arm or the camera would come closer to the table than the clearance.
    #[error("{part} would reach down to z = {z_m:.3} m (the table top is 0, clearance {clearance_m} m)")]
    Table {
        /// Which part (a link frame's name, or `camera`).
        part: &'static str,
        /// Lowest height of its surface (m).
        z_m: f64,
        /// Clearance required (m).
        clearance_m: f64,
    },
}

/// A reachable candidate: the joints that take the camera there.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Reached {
    /// Joint positions (rad), the solution nearest the current joints.
    pub joints_rad: Joints,
    /// Largest joint move from the current joints (rad).
    pub largest_move_rad: f64,
    /// Lowest clearance over the table of the arm and camera (m).
    pub table_clearance_m: f64,
}

/// The camera pose of the view at `offset` (baselines along the reference camera's own x and y)
/// from a reference view at `world_from_reference`.
pub fn view_pose(world_from_reference: &Isometry3<f64>, offset: [i32; 2], baseline_m: f64) -> Isometry3<f64> {
    world_from_reference
        * Isometry3::translation(
            f64::from(offset[0]) * baseline_m,
            f64::from(offset[1]) * baseline_m,
            0.0,
        )
}

/// Whether the arm can take the camera (mounted by `flange_from_camera`) to
/// `world_from_camera` from `current` joints: the nearest inverse-kinematics solution within the
/// joint limits, with every link and the camera clear of the table.
pub fn reach(
    arm: &Ur10,
    flange_from_camera: &Isometry3<f64>,
    world_from_camera: &Isometry3<f64>,
    current: &Joints,
) -> Result<Reached, ReachError> {
    let flange = world_from_camera * flange_from_camera.inverse();
    let joints = arm.closest_solution(&flange, current)?;
    let clearance = table_clearance(arm, flange_from_camera, &joints)?;
    Ok(Reached {
        joints_rad: joints,
        largest_move_rad: joints
            .iter()
            .zip(current)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max),
        table_clearance_m: clearance,
    })
}

/// The lowest clearance (m) over the table of the arm's links and the camera at `joints`, or the
/// part that comes too close.
pub fn table_clearance(arm: &Ur10, flange_from_camera: &Isometry3<f64>, joints: &Joints) -> Result<f64, ReachError> {
    let frames = arm.frames_from_base(joints);
    let mut lowest = f64::INFINITY;
    // Segment 0 runs from the base, which stands on the table, to the shoulder: not checked.
    for (i, pair) in frames.windows(2).enumerate().skip(1) {
        let (a, b) = (pair[0].translation.vector, pair[1].translation.vector);
        let part = crate::ur10::LINK_FRAME_NAMES[i.min(JOINT_COUNT - 1)];
        for s in 0..=SAMPLES_PER_LINK {
            let t = s as f64 / SAMPLES_PER_LINK as f64;
            let z = a.z + (b.z - a.z) * t - LINK_RADIUS_M;
            lowest = lowest.min(z);
            if z < TABLE_CLEARANCE_M {
                return Err(ReachError::Table {
                    part,
                    z_m: z,
                    clearance_m: TABLE_CLEARANCE_M,
                });
            }
        }
    }
    let camera = (arm.forward_kinematics(joints) * flange_from_camera).translation.vector;
    let z = camera.z - CAMERA_RADIUS_M;
    if z < TABLE_CLEARANCE_M {
        return Err(ReachError::Table {
            part: "camera",
            z_m: z,
            clearance_m: TABLE_CLEARANCE_M,
        });
    }
    Ok(lowest.min(z))
}

#[cfg(test)]
mod tests {
    use nalgebra::{Point3, Vector3};

    use super::*;
    use crate::capture::{default_hand_eye, look_at};
    use crate::scene::WORK_AREA_CENTER_M;
    use crate::ur10::HOME_JOINTS_RAD;

    fn reference() -> Isometry3<f64> {
        let c = WORK_AREA_CENTER_M;
        look_at(
            Point3::new(c[0], c[1], 0.55),
            Point3::new(c[0], c[1], 0.0),
            Vector3::x(),
        )
    }

    #[test]
    fn the_grid_around_a_capture_station_is_reachable_and_clear() {
        let (arm, hand_eye) = (Ur10::default(), default_hand_eye());
        let mut count = 0;
        for dx in -2..=2 {
            for dy in -2..=2 {
                let pose = view_pose(&reference(), [dx, dy], 0.02);
                let reached = reach(&arm, &hand_eye, &pose, &HOME_JOINTS_RAD)
                    .unwrap_or_else(|e| panic!("offset [{dx}, {dy}]: {e}"));
                let camera = arm.forward_kinematics(&reached.joints_rad) * hand_eye;
                assert!((camera.translation.vector - pose.translation.vector).norm() < 1e-6);
                assert!(reached.table_clearance_m >= TABLE_CLEARANCE_M);
                count += 1;
            }
        }
        assert_eq!(count, 25);
    }

    #[test]
    fn a_view_below_the_table_or_out_of_reach_is_refused_with_the_reason() {
        let (arm, hand_eye) = (Ur10::default(), default_hand_eye());
        // The camera 3 cm above the table: its body (4 cm) would touch it.
        let c = WORK_AREA_CENTER_M;
        let low = look_at(
            Point3::new(c[0], c[1], 0.03),
            Point3::new(c[0] + 0.5, c[1], 0.0),
            Vector3::z(),
        );
        match reach(&arm, &hand_eye, &low, &HOME_JOINTS_RAD) {
            Err(ReachError::Table { z_m, .. }) => assert!(z_m < TABLE_CLEARANCE_M),
            other => panic!("expected a table collision, got {other:?}"),
        }
        // Two metres away: no solution.
        let far = view_pose(&reference(), [100, 0], 0.02);
        assert!(matches!(
            reach(&arm, &hand_eye, &far, &HOME_JOINTS_RAD),
            Err(ReachError::Kinematics(_))
        ));
    }
}
