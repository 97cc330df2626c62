//! `replay plan`: the next best views of a set. The chosen method runs on the set; its disparity
//! and confidence feed the planner (`fuse::plan`), which scores every grid offset not yet taken;
//! each candidate's camera pose is checked against the arm (`record::reach`: inverse kinematics
//! within the joint limits, clear of the table); the best reachable ones are the plan.
//!
//! The arm's mount (`flange_from_camera`) is read off the reference view itself: its logged
//! joints give the flange pose, its logged pose the camera's (the log's world frame is the arm's
//! base frame). A set without joints (an imported image folder) gets its candidates scored but
//! not checked for reach.

use std::time::Instant;

use fuse::methods::Method;
use fuse::plan::{Candidate, LayoutRule, PlanConfig, PlanInput};
use nalgebra::Isometry3;
use record::rig::role_for_offset;
use record::ur10::Ur10;
use serde::Serialize;

use crate::ReplayError;
use crate::pipeline::{PreparedSet, RunOptions};
use crate::viewset::ViewSet;

/// How a set is planned.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanOptions {
    /// How many views (or pairs) to propose.
    pub budget: usize,
    /// The planner's settings; its layout rule is taken from the method unless `layout` is set.
    pub config: PlanConfig,
    /// Grouping of candidates (default: pairs for MFuseNet, single views otherwise).
    pub layout: Option<LayoutRule>,
    /// Largest disparity a candidate may reach (px; `None`: the end of the range the set is
    /// searched over, as for replay).
    pub max_disparity_px: Option<f32>,
    /// How the set is run.
    pub run: RunOptions,
}

impl Default for PlanOptions {
    fn default() -> Self {
        Self {
            budget: 3,
            config: PlanConfig::default(),
            layout: None,
            max_disparity_px: None,
            run: RunOptions::default(),
        }
    }
}

/// One view of a planned candidate: where the camera goes and whether the arm can take it there.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlannedPose {
    /// Grid offset (baselines along the reference camera's x and y).
    pub offset: [i32; 2],
    /// The role such a view gets (`right`, `top2`, …).
    pub role: String,
    /// Camera position in the world (arm base) frame (m).
    pub position_m: [f64; 3],
    /// Camera orientation, quaternion `[x, y, z, w]`.
    pub orientation_xyzw: [f64; 4],
    /// Whether the arm reaches it clear of the table (`None`: the log has no joints to check
    /// against).
    pub reachable: Option<bool>,
    /// The joints that take the camera there (rad).
    pub joints_rad: Option<[f64; 6]>,
    /// Largest joint move from the reference view's joints (rad).
    pub largest_move_rad: Option<f64>,
    /// Lowest clearance over the table of the arm and camera there (m).
    pub table_clearance_m: Option<f64>,
    /// Why it cannot be reached.
    pub unreachable_because: Option<String>,
}

/// A scored candidate with its poses.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlannedCandidate {
    /// The planner's scores.
    #[serde(flatten)]
    pub score: Candidate,
    /// Its views' poses and reach.
    pub poses: Vec<PlannedPose>,
}

impl PlannedCandidate {
    /// Feasible for the methods and not known to be out of the arm's reach.
    pub fn takeable(&self) -> bool {
        self.score.feasible && self.poses.iter().all(|p| p.reachable != Some(false))
    }
}

/// The plan of one set.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SetPlan {
    /// Set index in the log.
    pub set: u32,
    /// Set name.
    pub name: String,
    /// The method whose estimate was planned from.
    pub method: String,
    /// Seconds the method took.
    pub method_seconds: f64,
    /// Seconds the planning took (scoring and reach).
    pub planning_seconds: f64,
    /// How candidates were grouped.
    pub layout: LayoutRule,
    /// Offsets the set already has.
    pub taken: Vec<[i32; 2]>,
    /// The `budget` best takeable candidates, best first.
    pub chosen: Vec<PlannedCandidate>,
    /// Every candidate scored, best first (takeable or not).
    pub candidates: Vec<PlannedCandidate>,
}

/// The arm's mount read off a view: `flange_from_camera = (base_from_flange)⁻¹ · world_from_camera`.
fn mount(arm: &Ur10, world_from_camera: &Isometry3<f64>, joints: &[f64; 6]) -> Isometry3<f64> {
    arm.forward_kinematics(joints).inverse() * world_from_camera
}

/// Scores the candidates of `set` from a disparity and confidence already computed, and checks
/// their poses against the arm.
pub fn plan_from_estimate(
    set: &ViewSet,
    disparity: &fuse::DisparityImage,
    config: &PlanConfig,
    max_disparity_px: f32,
) -> Result<Vec<PlannedCandidate>, ReplayError> {
    let luma = fuse::image::luma_levels(&set.reference.rgb);
    let confidence = disparity
        .confidence
        .clone()
        .unwrap_or_else(|| vec![0.5; disparity.data.len()]);
    let taken: Vec<[i32; 2]> = set.neighbours.iter().map(|n| n.offset).collect();
    let input = PlanInput {
        width: disparity.width,
        height: disparity.height,
        luma: &luma,
        disparity_px: &disparity.data,
        confidence: &confidence,
        taken: &taken,
        max_disparity_px,
        expected_range_px: None,
    };
    let scored = fuse::plan::plan(&input, config).map_err(|source| ReplayError::Fuse { set: set.index, source })?;
    let arm = Ur10::default();
    let reference = &set.reference;
    let arm_state = reference
        .joints
        .map(|joints| (joints, mount(&arm, &reference.world_from_camera, &joints)));
    Ok(scored
        .into_iter()
        .map(|score| {
            let poses = score
                .offsets
                .iter()
                .map(|offset| {
                    let pose = record::reach::view_pose(&reference.world_from_camera, *offset, set.baseline_m);
                    let reached = arm_state
                        .as_ref()
                        .map(|(joints, hand_eye)| record::reach::reach(&arm, hand_eye, &pose, joints));
                    let q = pose.rotation.coords;
                    let t = pose.translation.vector;
                    PlannedPose {
                        offset: *offset,
                        role: role_for_offset(*offset),
                        position_m: [t.x, t.y, t.z],
                        orientation_xyzw: [q.x, q.y, q.z, q.w],
                        reachable: reached.as_ref().map(Result::is_ok),
                        joints_rad: reached.as_ref().and_then(|r| r.as_ref().ok()).map(|r| r.joints_rad),
                        largest_move_rad: reached
                            .as_ref()
                            .and_then(|r| r.as_ref().ok())
                            .map(|r| r.largest_move_rad),
                        table_clearance_m: reached
                            .as_ref()
                            .and_then(|r| r.as_ref().ok())
                            .map(|r| r.table_clearance_m),
                        unreachable_because: reached.and_then(|r| r.err()).map(|e| e.to_string()),
                    }
                })
                .collect();
            PlannedCandidate { score, poses }
        })
        .collect())
}

/// Runs `method` on `set` and plans its next views.
pub fn plan_set(set: &ViewSet, method: &dyn Method, options: &PlanOptions) -> Result<SetPlan, ReplayError> {
    let prepared = PreparedSet::new(set, &options.run)?;
    let result = prepared.run(method, &|_| {})?;
    let started = Instant::now();
    let family = PlanConfig::for_family(fuse::methods::entry(method.name()).map(|e| e.family));
    let config = PlanConfig {
        layout: options.layout.unwrap_or(family.layout),
        vertical_weight: family.vertical_weight,
        ..options.config
    };
    let searched_px = (prepared.min_disparity + prepared.num_disparities as i32) as f32;
    let max_disparity_px = options.max_disparity_px.unwrap_or(searched_px);
    let candidates = plan_from_estimate(&prepared.selected, &result.disparity, &config, max_disparity_px)?;
    let planning_seconds = started.elapsed().as_secs_f64();
    let chosen = candidates
        .iter()
        .filter(|c| c.takeable())
        .take(options.budget)
        .cloned()
        .collect();
    Ok(SetPlan {
        set: set.index,
        name: set.name.clone(),
        method: method.name().to_owned(),
        method_seconds: result.seconds,
        planning_seconds,
        layout: config.layout,
        taken: prepared.selected.neighbours.iter().map(|n| n.offset).collect(),
        chosen,
        candidates,
    })
}

/// A plan as a table: one row per chosen candidate.
pub fn table(plan: &SetPlan) -> String {
    let mut out = format!(
        "set {} ({}): {} took {:.2} s, planning {:.3} s; has {}\n",
        plan.set,
        plan.name,
        plan.method,
        plan.method_seconds,
        plan.planning_seconds,
        plan.taken
            .iter()
            .map(|o| role_for_offset(*o))
            .collect::<Vec<_>>()
            .join(", ")
    );
    out.push_str(&format!(
        "  {:<4} {:<24} {:>10} {:>7} {:>9} {:>8}  {}\n",
        "rank", "views", "pixels", "gain %", "reveals %", "texture", "arm"
    ));
    for (rank, c) in plan.chosen.iter().enumerate() {
        let roles: Vec<String> = c.poses.iter().map(|p| p.role.clone()).collect();
        let arm = match c.poses.iter().map(|p| p.reachable).collect::<Option<Vec<bool>>>() {
            None => "not checked (no joints in the log)".to_owned(),
            Some(_) => {
                let moves: Vec<String> = c
                    .poses
                    .iter()
                    .filter_map(|p| p.largest_move_rad.map(|m| format!("{:.1}°", m.to_degrees())))
                    .collect();
                format!("reachable, largest joint move {}", moves.join(" / "))
            }
        };
        out.push_str(&format!(
            "  {:<4} {:<24} {:>10.0} {:>7.2} {:>9.1} {:>8.2}  {}\n",
            rank + 1,
            roles.join("+"),
            c.score.expected_pixels,
            100.0 * c.score.gain,
            100.0 * c.score.reveals_share,
            c.score.texture,
            arm
        ));
    }
    if plan.chosen.is_empty() {
        out.push_str("  no takeable candidate (see --json for every candidate and why)\n");
    }
    out
}
