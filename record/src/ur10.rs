//! Universal Robots UR10 kinematics on nalgebra: forward kinematics for every joint frame,
//! the closed-form inverse kinematics, joint limits and joint-space motion timing.
//!
//! Denavit–Hartenberg parameters (standard/distal convention,
//! `T_i = Rz(θ_i) · Tz(d_i) · Tx(a_i) · Rx(α_i)`) as published by Universal Robots,
//! "DH parameters for calculations of kinematics and dynamics" (UR support article), UR10 (CB-series):
//!
//! | joint | a (m)    | d (m)    | α (rad) |
//! |-------|----------|----------|---------|
//! | 1     | 0        | 0.1273   | π/2     |
//! | 2     | −0.612   | 0        | 0       |
//! | 3     | −0.5723  | 0        | 0       |
//! | 4     | 0        | 0.163941 | π/2     |
//! | 5     | 0        | 0.1157   | −π/2    |
//! | 6     | 0        | 0.0922   | 0       |
//!
//! The inverse kinematics follows K. P. Hawkins, "Analytic Inverse Kinematics for the Universal
//! Robots UR-5/UR-10 Arms" (Georgia Tech, 2013): up to eight solutions from θ1 (shoulder, 2), θ5
//! (wrist, 2) and θ3 (elbow, 2), each checked against forward kinematics.

use std::f64::consts::{FRAC_PI_2, PI, TAU};

use nalgebra::{Isometry3, Matrix4, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Number of revolute joints of the UR10.
pub const JOINT_COUNT: usize = 6;

/// Joint positions in radians, base to wrist 3.
pub type Joints = [f64; JOINT_COUNT];

/// Names of the joint frames in the logged transform tree, base to flange.
pub const LINK_FRAME_NAMES: [&str; JOINT_COUNT] = [
    "shoulder_link",
    "upper_arm_link",
    "forearm_link",
    "wrist_1_link",
    "wrist_2_link",
    "flange",
];

/// Names of the joints as logged in `foxglove.JointStates`.
pub const JOINT_NAMES: [&str; JOINT_COUNT] = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
];

/// Joint home position used at the start of every simulated recording (radians).
pub const HOME_JOINTS_RAD: Joints = [0.0, -FRAC_PI_2, FRAC_PI_2, -FRAC_PI_2, -FRAC_PI_2, 0.0];

/// How far a forward-kinematics check of an IK solution may be off before it is discarded (m).
const IK_POSITION_TOLERANCE_M: f64 = 1e-7;
/// Rotation tolerance of the same check (rad).
const IK_ROTATION_TOLERANCE_RAD: f64 = 1e-7;
/// Below this |sin θ5| the wrist is singular and θ6 is taken from the current joints.
const WRIST_SINGULARITY_SIN: f64 = 1e-9;

/// Denavit–Hartenberg parameters of a six-joint arm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DhParameters {
    /// Link lengths `a_i` (m).
    pub a_m: [f64; JOINT_COUNT],
    /// Link offsets `d_i` (m).
    pub d_m: [f64; JOINT_COUNT],
    /// Link twists `α_i` (rad).
    pub alpha_rad: [f64; JOINT_COUNT],
}

/// The UR10 (CB3) parameters from Universal Robots (see the module docs).
pub const UR10_DH: DhParameters = DhParameters {
    a_m: [0.0, -0.612, -0.5723, 0.0, 0.0, 0.0],
    d_m: [0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922],
    alpha_rad: [FRAC_PI_2, 0.0, 0.0, FRAC_PI_2, -FRAC_PI_2, 0.0],
};

/// Errors of the kinematics.
#[derive(Debug, Clone, thiserror::Error, PartialEq)]
pub enum KinematicsError {
    /// The target pose is outside the arm's workspace (no IK solution at all).
    #[error(
        "pose unreachable: flange target at [{x:.4}, {y:.4}, {z:.4}] m (distance {distance_m:.3} m from the base) has no inverse-kinematics solution"
    )]
    Unreachable {
        /// Target x (m).
        x: f64,
        /// Target y (m).
        y: f64,
        /// Target z (m).
        z: f64,
        /// Distance from the base origin (m).
        distance_m: f64,
    },
    /// Solutions exist but every one violates a joint limit.
    #[error("all {solutions} IK solutions violate the joint limits (joint {joint} wants {value_rad:.3} rad)")]
    JointLimits {
        /// Number of solutions found.
        solutions: usize,
        /// Joint index (0-based) of the first violation.
        joint: usize,
        /// Offending value (rad).
        value_rad: f64,
    },
}

/// The simulated UR10: parameters, limits and motion speeds.
#[derive(Debug, Clone, PartialEq)]
pub struct Ur10 {
    /// Kinematic parameters.
    pub dh: DhParameters,
    /// Lower and upper limit per joint (rad). The UR10 allows ±360° on every joint.
    pub joint_limits_rad: [(f64, f64); JOINT_COUNT],
    /// Largest joint speed the planner commands (rad/s), below the UR10's 120°/s and 180°/s.
    pub max_joint_speed_rad_per_s: [f64; JOINT_COUNT],
}

impl Default for Ur10 {
    fn default() -> Self {
        let speed_base = 60f64.to_radians();
        let speed_wrist = 90f64.to_radians();
        Self {
            dh: UR10_DH,
            joint_limits_rad: [(-TAU, TAU); JOINT_COUNT],
            max_joint_speed_rad_per_s: [
                speed_base,
                speed_base,
                speed_wrist,
                speed_wrist,
                speed_wrist,
                speed_wrist,
            ],
        }
    }
}

/// One DH link transform `Rz(θ) Tz(d) Tx(a) Rx(α)`.
fn dh_link(theta: f64, d: f64, a: f64, alpha: f64) -> Isometry3<f64> {
    let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), theta)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), alpha);
    let translation = Vector3::new(a * theta.cos(), a * theta.sin(), d);
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

impl Ur10 {
    /// `parent_from_child` for every joint frame, base to flange (for the logged transform tree).
    pub fn link_transforms(&self, joints: &Joints) -> [Isometry3<f64>; JOINT_COUNT] {
        std::array::from_fn(|i| dh_link(joints[i], self.dh.d_m[i], self.dh.a_m[i], self.dh.alpha_rad[i]))
    }

    /// `base_from_link` for every joint frame (cumulative), base to flange.
    pub fn link_poses(&self, joints: &Joints) -> [Isometry3<f64>; JOINT_COUNT] {
        let links = self.link_transforms(joints);
        let mut poses = [Isometry3::identity(); JOINT_COUNT];
        let mut current = Isometry3::identity();
        for (pose, link) in poses.iter_mut().zip(links.iter()) {
            current *= link;
            *pose = current;
        }
        poses
    }

    /// The base frame (identity) followed by every joint frame's pose, base to flange: the
    /// polyline of joint origins a viewer draws the arm along.
    pub fn frames_from_base(&self, joints: &Joints) -> Vec<Isometry3<f64>> {
        let mut frames = vec![Isometry3::identity()];
        frames.extend(self.link_poses(joints));
        frames
    }

    /// Forward kinematics: `base_from_flange`.
    pub fn forward_kinematics(&self, joints: &Joints) -> Isometry3<f64> {
        self.link_poses(joints)[JOINT_COUNT - 1]
    }

    /// All closed-form IK solutions for `base_from_flange` (angles in (−π, π]), each verified
    /// by forward kinematics. At a wrist singularity θ6 is taken from `hint`.
    pub fn inverse_kinematics(&self, base_from_flange: &Isometry3<f64>, hint: &Joints) -> Vec<Joints> {
        let DhParameters { a_m: a, d_m: d, .. } = self.dh;
        let (a2, a3, d1, d4, d5, d6) = (a[1], a[2], d[0], d[3], d[4], d[5]);
        let t: Matrix4<f64> = base_from_flange.to_homogeneous();
        let p = Vector3::new(t[(0, 3)], t[(1, 3)], t[(2, 3)]);
        let x_axis = Vector3::new(t[(0, 0)], t[(1, 0)], t[(2, 0)]);
        let y_axis = Vector3::new(t[(0, 1)], t[(1, 1)], t[(2, 1)]);
        let z_axis = Vector3::new(t[(0, 2)], t[(1, 2)], t[(2, 2)]);
        // Wrist centre (origin of frame 5): its component along z1 equals d4.
        let wrist = p - d6 * z_axis;
        let radius = wrist.x.hypot(wrist.y);
        if radius < d4.abs() {
            return Vec::new();
        }
        let psi = wrist.y.atan2(wrist.x);
        let phi = (d4 / radius).clamp(-1.0, 1.0).acos();
        let mut solutions = Vec::with_capacity(8);
        for theta1 in [psi + phi + FRAC_PI_2, psi - phi + FRAC_PI_2] {
            let (s1, c1) = theta1.sin_cos();
            let cos5 = (p.x * s1 - p.y * c1 - d4) / d6;
            if cos5.abs() > 1.0 + 1e-12 {
                continue;
            }
            let base5 = cos5.clamp(-1.0, 1.0).acos();
            for theta5 in [base5, -base5] {
                let s5 = theta5.sin();
                let theta6 = if s5.abs() < WRIST_SINGULARITY_SIN {
                    hint[5]
                } else {
                    let y = -(y_axis.x * s1 - y_axis.y * c1) / s5;
                    let x = (x_axis.x * s1 - x_axis.y * c1) / s5;
                    y.atan2(x)
                };
                // Remove joints 1, 5 and 6 and solve the planar 3R chain of joints 2–4.
                let frame1 = dh_link(theta1, d1, 0.0, FRAC_PI_2);
                let wrist_chain = dh_link(theta5, d5, 0.0, -FRAC_PI_2) * dh_link(theta6, d6, 0.0, 0.0);
                let link1_from_link4 = frame1.inverse() * base_from_flange * wrist_chain.inverse();
                let m = link1_from_link4.to_homogeneous();
                // Frame 3 origin = frame 4 origin minus d4 along the common joint axis (z1).
                let px = m[(0, 3)];
                let py = m[(1, 3)];
                let cos3 = (px * px + py * py - a2 * a2 - a3 * a3) / (2.0 * a2 * a3);
                if cos3.abs() > 1.0 + 1e-12 {
                    continue;
                }
                let base3 = cos3.clamp(-1.0, 1.0).acos();
                for theta3 in [base3, -base3] {
                    let theta2 = py.atan2(px) - (a3 * theta3.sin()).atan2(a2 + a3 * theta3.cos());
                    let theta234 = m[(1, 0)].atan2(m[(0, 0)]);
                    let theta4 = theta234 - theta2 - theta3;
                    let candidate = [theta1, theta2, theta3, theta4, theta5, theta6].map(wrap_to_pi);
                    if self.matches(&candidate, base_from_flange) {
                        solutions.push(candidate);
                    }
                }
            }
        }
        solutions
    }

    fn matches(&self, joints: &Joints, target: &Isometry3<f64>) -> bool {
        let reached = self.forward_kinematics(joints);
        let position_error = (reached.translation.vector - target.translation.vector).norm();
        let rotation_error = reached.rotation.angle_to(&target.rotation);
        position_error < IK_POSITION_TOLERANCE_M && rotation_error < IK_ROTATION_TOLERANCE_RAD
    }

    /// The IK solution closest (max-norm in joint space) to `current`, each angle shifted by
    /// multiples of 2π to the nearest equivalent inside the joint limits.
    pub fn closest_solution(
        &self,
        base_from_flange: &Isometry3<f64>,
        current: &Joints,
    ) -> Result<Joints, KinematicsError> {
        let solutions = self.inverse_kinematics(base_from_flange, current);
        if solutions.is_empty() {
            let v = base_from_flange.translation.vector;
            return Err(KinematicsError::Unreachable {
                x: v.x,
                y: v.y,
                z: v.z,
                distance_m: v.norm(),
            });
        }
        let mut best: Option<(f64, Joints)> = None;
        let mut first_violation = None;
        for solution in &solutions {
            let mut adjusted = *solution;
            let mut valid = true;
            for (joint, angle) in adjusted.iter_mut().enumerate() {
                let (lower, upper) = self.joint_limits_rad[joint];
                match nearest_equivalent(*angle, current[joint], lower, upper) {
                    Some(value) => *angle = value,
                    None => {
                        valid = false;
                        first_violation.get_or_insert((joint, *angle));
                        break;
                    }
                }
            }
            if !valid {
                continue;
            }
            let distance = adjusted
                .iter()
                .zip(current)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            if best.as_ref().is_none_or(|(d, _)| distance < *d) {
                best = Some((distance, adjusted));
            }
        }
        match (best, first_violation) {
            (Some((_, joints)), _) => Ok(joints),
            (None, violation) => {
                let (joint, value_rad) = violation.unwrap_or((0, f64::NAN));
                Err(KinematicsError::JointLimits {
                    solutions: solutions.len(),
                    joint,
                    value_rad,
                })
            }
        }
    }

    /// Duration of a synchronised joint-space move (all joints start and stop together) under the
    /// speed limits, for a smooth (cosine) velocity profile whose peak speed is π/2 × the mean.
    pub fn move_duration_secs(&self, from: &Joints, to: &Joints) -> f64 {
        from.iter()
            .zip(to)
            .zip(&self.max_joint_speed_rad_per_s)
            .map(|((a, b), speed)| FRAC_PI_2 * (b - a).abs() / speed)
            .fold(0.0, f64::max)
    }
}

/// Joint positions along a synchronised smooth move at `fraction` ∈ [0, 1] of its duration
/// (cosine ease: zero velocity at both ends).
pub fn interpolate_joints(from: &Joints, to: &Joints, fraction: f64) -> Joints {
    let s = 0.5 - 0.5 * (PI * fraction.clamp(0.0, 1.0)).cos();
    std::array::from_fn(|i| from[i] + (to[i] - from[i]) * s)
}

/// Joint velocities (rad/s) along the same move, for a move lasting `duration_secs`.
pub fn interpolate_joint_velocities(from: &Joints, to: &Joints, fraction: f64, duration_secs: f64) -> Joints {
    if duration_secs <= 0.0 {
        return [0.0; JOINT_COUNT];
    }
    let ds = 0.5 * PI * (PI * fraction.clamp(0.0, 1.0)).sin() / duration_secs;
    std::array::from_fn(|i| (to[i] - from[i]) * ds)
}

fn wrap_to_pi(angle: f64) -> f64 {
    let wrapped = (angle + PI).rem_euclid(TAU) - PI;
    if wrapped <= -PI { wrapped + TAU } else { wrapped }
}

/// `angle + k·2π` closest to `reference` inside `[lower, upper]`, if any.
fn nearest_equivalent(angle: f64, reference: f64, lower: f64, upper: f64) -> Option<f64> {
    let k = ((reference - angle) / TAU).round();
    [k - 1.0, k, k + 1.0]
        .into_iter()
        .map(|k| angle + k * TAU)
        .filter(|value| *value >= lower && *value <= upper)
        .min_by(|a, b| (a - reference).abs().total_cmp(&(b - reference).abs()))
}

/// `Rotation3` from the columns of a right-handed orthonormal frame.
pub fn rotation_from_axes(x: Vector3<f64>, y: Vector3<f64>, z: Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[
        x, y, z,
    ])))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_joints() -> Vec<Joints> {
        vec![
            [0.3, -1.2, 1.4, -1.8, -1.5, 0.4],
            [-2.0, -0.7, -1.9, 0.5, 1.1, -2.8],
            [1.0, -2.2, 2.0, -0.9, -2.5, 3.0],
            HOME_JOINTS_RAD,
            [0.1, -1.0, 1.0, 0.4, 0.6, -0.5],
        ]
    }

    #[test]
    fn zero_pose_matches_published_geometry() {
        // At all-zero joints the UR10 is stretched along −x: x = a2 + a3, y = −(d4 + d6), z = d1 − d5.
        let arm = Ur10::default();
        let flange = arm.forward_kinematics(&[0.0; 6]);
        let t = flange.translation.vector;
        assert!((t.x - (-0.612 - 0.5723)).abs() < 1e-12, "{t}");
        assert!((t.y - (-(0.163941 + 0.0922))).abs() < 1e-12, "{t}");
        assert!((t.z - (0.1273 - 0.1157)).abs() < 1e-12, "{t}");
    }

    #[test]
    fn ik_round_trips_fk_for_every_solution() {
        let arm = Ur10::default();
        for joints in sample_joints() {
            let target = arm.forward_kinematics(&joints);
            let solutions = arm.inverse_kinematics(&target, &joints);
            assert!(solutions.len() >= 2, "{joints:?}: {} solutions", solutions.len());
            for solution in &solutions {
                let reached = arm.forward_kinematics(solution);
                assert!((reached.translation.vector - target.translation.vector).norm() < 1e-9);
                assert!(reached.rotation.angle_to(&target.rotation) < 1e-9);
            }
            let closest = arm.closest_solution(&target, &joints).unwrap();
            let distance = closest
                .iter()
                .zip(&joints)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(
                distance < 1e-6,
                "closest solution {closest:?} is not the original {joints:?}"
            );
        }
    }

    #[test]
    fn unreachable_pose_is_an_error_with_the_target() {
        let arm = Ur10::default();
        let far = Isometry3::translation(3.0, 0.0, 0.5);
        let error = arm.closest_solution(&far, &HOME_JOINTS_RAD).unwrap_err();
        assert!(matches!(error, KinematicsError::Unreachable { x, .. } if (x - 3.0).abs() < 1e-12));
    }

    #[test]
    fn nearest_equivalent_respects_limits() {
        let shifted = nearest_equivalent(-1.0, 5.0, -TAU, TAU).unwrap();
        assert!((shifted - (TAU - 1.0)).abs() < 1e-12, "{shifted}");
        assert!(nearest_equivalent(3.0, 0.0, -1.0, 1.0).is_none());
    }

    #[test]
    fn smooth_move_starts_and_ends_at_rest() {
        let from = [0.0; 6];
        let to = [1.0, -1.0, 0.5, 0.0, 0.0, 2.0];
        assert_eq!(interpolate_joints(&from, &to, 0.0), from);
        assert_eq!(interpolate_joints(&from, &to, 1.0), to);
        let v0 = interpolate_joint_velocities(&from, &to, 0.0, 2.0);
        assert!(v0.iter().all(|v| v.abs() < 1e-12));
        let arm = Ur10::default();
        let duration = arm.move_duration_secs(&from, &to);
        // Peak speed of the slowest-limited joint equals its limit.
        let mid = interpolate_joint_velocities(&from, &to, 0.5, duration);
        let ratio = mid
            .iter()
            .zip(&arm.max_joint_speed_rad_per_s)
            .map(|(v, m)| v.abs() / m)
            .fold(0.0, f64::max);
        assert!((ratio - 1.0).abs() < 1e-9, "{ratio}");
    }
}
