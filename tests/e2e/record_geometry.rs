//! Geometry of recorded sets: camera centres coplanar at ±baseline along the centre camera's
//! axes, optical axes parallel (within the injected noise); the logged transform chain, joint
//! states and capture events agree; injected errors land on the named view only.

use multiscopic_tests::{Log, record_args, recorded};
use nalgebra::Vector3;
use record::log::{CAMERA_FRAME, PoseJson};
use record::ur10::Ur10;

/// Relative translation error allowed between two views: twice the UR10's ±0.1 mm repeatability.
const REPEATABILITY_PAIR_TOLERANCE_M: f64 = 2.0 * 0.1e-3 + 1e-9;

struct Relative {
    role: String,
    in_plane_error_m: f64,
    out_of_plane_m: f64,
    rotation_deg: f64,
}

fn relative_poses(log: &Log, set: u32, use_true_pose: bool) -> Vec<Relative> {
    let events: Vec<_> = log.events().into_iter().filter(|e| e.set_index == set).collect();
    let pose = |e: &record::log::CaptureEvent| {
        if use_true_pose {
            e.true_world_from_camera
                .as_ref()
                .map(PoseJson::to_isometry)
                .unwrap_or_else(|| panic!("no true pose"))
        } else {
            e.world_from_camera.to_isometry()
        }
    };
    let center = events
        .iter()
        .find(|e| e.role == "center")
        .unwrap_or_else(|| panic!("no centre view"));
    let world_from_center = pose(center);
    events
        .iter()
        .map(|e| {
            let relative = world_from_center.inverse() * pose(e);
            let expected = Vector3::new(f64::from(e.grid_offset[0]), f64::from(e.grid_offset[1]), 0.0) * e.baseline_m;
            let t = relative.translation.vector;
            Relative {
                role: e.role.clone(),
                in_plane_error_m: (t.xy() - expected.xy()).norm(),
                out_of_plane_m: t.z,
                rotation_deg: relative.rotation.angle().to_degrees(),
            }
        })
        .collect()
}

#[test]
fn five_view_sets_are_coplanar_at_the_baseline_with_parallel_axes() {
    let (_dir, path) = recorded("five.mcap", "--captures 3 --resolution 48x32 --samples-per-pixel 1");
    let log = Log::read(&path);
    let arm = Ur10::default();
    let metadata = &log.metadata[record::log::METADATA_NAME];
    let hand_eye: PoseJson =
        serde_json::from_str(&metadata["hand_eye_flange_from_camera"]).unwrap_or_else(|e| panic!("{e}"));
    let hand_eye = hand_eye.to_isometry();
    let mut worst_in_plane = 0.0f64;
    for set in 0..3 {
        for use_true_pose in [false, true] {
            for r in relative_poses(&log, set, use_true_pose) {
                assert!(
                    r.in_plane_error_m <= REPEATABILITY_PAIR_TOLERANCE_M,
                    "set {set} {}: {:.3} mm off the baseline grid",
                    r.role,
                    r.in_plane_error_m * 1e3
                );
                assert!(
                    r.out_of_plane_m.abs() <= REPEATABILITY_PAIR_TOLERANCE_M,
                    "set {set} {}: out of plane",
                    r.role
                );
                assert!(
                    r.rotation_deg < 1e-6,
                    "set {set} {}: axes not parallel ({} deg)",
                    r.role,
                    r.rotation_deg
                );
                worst_in_plane = worst_in_plane.max(r.in_plane_error_m);
            }
        }
    }
    // Repeatability noise is really there (the check above is not vacuous).
    assert!(worst_in_plane > 1e-6, "no repeatability noise at all: {worst_in_plane}");
    for event in log.events() {
        // The /tf chain at the capture time composes to the pose in the capture event…
        let from_tf = log.world_from(CAMERA_FRAME, event.capture_time_nanos);
        let from_event = event.world_from_camera.to_isometry();
        assert!((from_tf.translation.vector - from_event.translation.vector).norm() < 1e-9);
        assert!(from_tf.rotation.angle_to(&from_event.rotation) < 1e-9);
        // …and so do the logged joints through forward kinematics and the hand-eye transform.
        let joints = event.joint_positions_rad.unwrap_or_else(|| panic!("no joints"));
        let from_fk = arm.forward_kinematics(&joints) * hand_eye;
        assert!((from_fk.translation.vector - from_event.translation.vector).norm() < 1e-9);
        // IK of that flange pose round-trips to the logged joints.
        let flange = arm.forward_kinematics(&joints);
        let solved = arm.closest_solution(&flange, &joints).unwrap_or_else(|e| panic!("{e}"));
        let worst = solved
            .iter()
            .zip(&joints)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-7, "IK did not round-trip: {worst} rad");
        // The commanded pose was reached within repeatability.
        let commanded = event
            .commanded_world_from_camera
            .as_ref()
            .map(PoseJson::to_isometry)
            .unwrap_or_else(|| panic!("no commanded pose"));
        assert!((commanded.translation.vector - from_event.translation.vector).norm() <= 0.1e-3 + 1e-9);
    }
}

#[test]
fn injected_errors_land_on_the_named_view_only() {
    let (dir, path) = recorded(
        "errors.mcap",
        "--resolution 48x32 --samples-per-pixel 1 --repeatability-mm 0 --rotation-error left:z:0.5 --offset-error top:z:1",
    );
    let log = Log::read(&path);
    let poses = relative_poses(&log, 0, false);
    let mut roles: Vec<&str> = poses.iter().map(|r| r.role.as_str()).collect();
    roles.sort_unstable();
    assert_eq!(
        roles,
        ["bottom", "center", "left", "right", "top"],
        "every view's pose is checked"
    );
    for r in &poses {
        match r.role.as_str() {
            "left" => {
                assert!((r.rotation_deg - 0.5).abs() < 1e-6, "left roll {}", r.rotation_deg);
                assert!(r.out_of_plane_m.abs() < 1e-9);
            }
            "top" => {
                assert!(
                    (r.out_of_plane_m - 1e-3).abs() < 1e-9,
                    "top offset {}",
                    r.out_of_plane_m
                );
                assert!(r.rotation_deg < 1e-6);
            }
            other => {
                assert!(
                    r.rotation_deg < 1e-6 && r.out_of_plane_m.abs() < 1e-9 && r.in_plane_error_m < 1e-9,
                    "{other} is affected"
                );
            }
        }
    }
    // A hand-eye error is invisible in the logged (believed) poses but present in the true ones.
    let path = record_args(
        dir.path(),
        "hand_eye.mcap",
        "--resolution 48x32 --samples-per-pixel 1 --repeatability-mm 0 --hand-eye-error-deg 0,0,2",
    );
    let log = Log::read(&path);
    let believed = relative_poses(&log, 0, false);
    let truth = relative_poses(&log, 0, true);
    assert!(believed.iter().all(|r| r.in_plane_error_m < 1e-9));
    let worst = truth.iter().map(|r| r.in_plane_error_m).fold(0.0, f64::max);
    // 2° of mount rotation turns a 20 mm move by 2°: about 0.7 mm sideways.
    assert!(worst > 0.5e-3 && worst < 1.0e-3, "true in-plane error {worst}");
}
