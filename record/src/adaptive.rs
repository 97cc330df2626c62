//! Adaptive capture (`record --rig adaptive --views N`): the closed loop of next-best-view
//! planning. The arm takes the centre view; the first neighbour is planned from the centre's
//! texture and the scene's working range (no depth yet; the range bounds the baselines the search
//! affords); then, until the set has N views, the chosen method runs on the
//! views so far, the planner (`fuse::plan`) scores every grid offset not yet taken by the pixels
//! it would resolve, the best one the arm reaches clear of the table (`crate::reach`) is taken.
//!
//! Every step is a [`PlanStep`]: the candidates with their scores and poses, and the choice. The
//! log carries them on [`crate::log::CAPTURE_PLAN_TOPIC`], so that replay and the viewer can show
//! why each view was taken.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use fuse::methods::Family;
use fuse::plan::{Candidate, LayoutRule, PlanConfig, PlanInput};
use fuse::{DisparityImage, FuseError};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use crate::capture::{Simulation, SimulationError};
use crate::log::PoseJson;
use crate::reach::{reach, view_pose};
use crate::rig::{REFERENCE_ROLE, RigKind, role_for_offset};
use crate::{CapturedSet, CapturedView};

/// Largest number of views of an adaptive set.
pub const MAX_ADAPTIVE_VIEWS: u32 = 9;

/// How an adaptive set is captured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AdaptiveConfig {
    /// Views per set, the centre included (2 … [`MAX_ADAPTIVE_VIEWS`]).
    pub views: u32,
    /// The method run on the views so far to plan the next (a registry name).
    pub method: String,
    /// Longest candidate offset, in baselines (a longer baseline resolves depth finer where the
    /// disparities it makes stay in the search range).
    pub max_offset: i32,
    /// Candidates as single views or opposite pairs (default: pairs for MFuseNet, whose networks
    /// take left and right or top and bottom; single views otherwise).
    pub layout: Option<LayoutRule>,
    /// The widest disparity search (px) a candidate may need at its own offset, from the working
    /// range's far end to its near end (`None`: the search a replay makes by default,
    /// `fuse::default_num_disparities` of the width).
    pub max_disparity_px: Option<f32>,
}

impl Default for AdaptiveConfig {
    fn default() -> Self {
        Self {
            views: 5,
            method: "mfusenet".to_owned(),
            max_offset: 2,
            layout: None,
            max_disparity_px: None,
        }
    }
}

impl AdaptiveConfig {
    /// The layout rule in force for `method`.
    pub fn layout_for(&self, family: Option<Family>) -> LayoutRule {
        self.layout.unwrap_or_else(|| LayoutRule::for_family(family))
    }
}

/// One scored candidate of a plan step, as the log records it: the planner's scores and whether
/// the arm reaches its views.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanCandidate {
    /// The planner's scores (offsets, expected pixels, gain, …).
    #[serde(flatten)]
    pub score: Candidate,
    /// Whether the arm reaches every view of it clear of the table.
    pub reachable: bool,
    /// Why not, when not.
    pub unreachable_because: Option<String>,
    /// The camera poses of its views (world = arm base frame).
    pub world_from_camera: Vec<PoseJson>,
}

impl PlanCandidate {
    /// Its offsets and whether it could be taken, or what ruled it out.
    pub fn verdict(&self) -> String {
        let verdict = match (&self.unreachable_because, self.score.feasible) {
            (Some(why), _) => format!("unreachable ({why})"),
            (None, false) => "past the disparity search".to_owned(),
            (None, true) => "takeable".to_owned(),
        };
        format!("{:?} {verdict}", self.score.offsets)
    }
}

/// One step of the loop: what was known, what was scored, what was taken.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanStep {
    /// Index of the set in the log.
    pub set_index: u32,
    /// 1 for the first neighbour, 2 for the second, …
    pub step: u32,
    /// When the plan was made (ns since the Unix epoch; the log time of its message).
    pub time_nanos: u64,
    /// The method whose estimate was planned from (`None`: the first step, from texture and the
    /// working range).
    pub method: Option<String>,
    /// Seconds the method took.
    pub method_seconds: f64,
    /// Seconds the planning took (scoring and reach).
    pub planning_seconds: f64,
    /// How candidates were grouped.
    pub layout: LayoutRule,
    /// The baseline (m) the step's offsets count in: the capture's. A set whose offsets all
    /// share a factor is stored as a set at that multiple of it (its views' `grid_offset`
    /// divided by the factor, its `baseline_m` multiplied), so a view's offset here is its
    /// event's `grid_offset × baseline_m ÷` this.
    #[serde(default)]
    pub baseline_m: f64,
    /// Offsets taken before this step.
    pub taken: Vec<[i32; 2]>,
    /// Every candidate, best first.
    pub candidates: Vec<PlanCandidate>,
    /// The offset taken.
    pub chosen_offset: [i32; 2],
    /// Its role.
    pub chosen_role: String,
}

impl PlanStep {
    /// One line: which view was chosen of how many candidates, its expected gain, and the
    /// planning and method times.
    pub fn summary(&self) -> String {
        format!(
            "set {} view {}: {} chosen of {} candidates ({:.0} px expected), planned in {:.3} s after {:.2} s of {}",
            self.set_index,
            self.step + 1,
            self.chosen_role,
            self.candidates.len(),
            self.candidates.first().map_or(0.0, |c| c.score.expected_pixels),
            self.planning_seconds,
            self.method_seconds,
            self.method.as_deref().unwrap_or("texture and the working range")
        )
    }
}

impl PlanStep {
    /// Every candidate view as the viewer draws it: pose, score relative to the best, label.
    pub fn frusta(&self) -> Vec<viz::stream::PlannedFrustum> {
        let best = self
            .candidates
            .iter()
            .map(|c| c.score.expected_pixels)
            .fold(0.0f64, f64::max)
            .max(1.0);
        self.candidates
            .iter()
            .flat_map(|c| {
                c.score
                    .offsets
                    .iter()
                    .zip(&c.world_from_camera)
                    .map(move |(offset, pose)| viz::stream::PlannedFrustum {
                        world_from_camera: pose.to_isometry(),
                        score: (c.score.expected_pixels / best) as f32,
                        label: format!("{} {:.0} px", role_for_offset(*offset), c.score.expected_pixels),
                        chosen: *offset == self.chosen_offset,
                        reachable: c.reachable && c.score.feasible,
                    })
            })
            .collect()
    }
}

/// A set captured adaptively, with its plan steps.
#[derive(Debug, Clone, PartialEq)]
pub struct AdaptiveSet {
    /// The set (rig `adaptive`).
    pub set: CapturedSet,
    /// The plan of each neighbour, in capture order.
    pub steps: Vec<PlanStep>,
}

/// The matching problem of the views so far (the first is the centre), in units of the common
/// factor of their offsets (a centre with views at ±2 baselines is a set at twice the baseline,
/// as MFuseNet's networks need it), with that factor.
fn problem(views: &[CapturedView], sim: &Simulation) -> Result<(fuse::Problem, i32), FuseError> {
    let factor = common_factor(views[1..].iter().map(|v| v.grid_offset));
    let range = sim.working_disparity_range_at(factor);
    let image = |v: &CapturedView| fuse::Image::rgb(v.camera.width as usize, v.camera.height as usize, v.rgb.clone());
    let problem = fuse::Problem {
        reference: image(&views[0])?,
        neighbours: views[1..]
            .iter()
            .map(|v| {
                let offset = v.grid_offset.map(|o| o / factor);
                Ok(fuse::Neighbour {
                    role: role_for_offset(offset),
                    image: image(v)?,
                    offset,
                    baseline_ratio: 1.0,
                })
            })
            .collect::<Result<_, FuseError>>()?,
        min_disparity: range.min_disparity,
        num_disparities: range.num_disparities.unwrap_or(64) as usize,
    };
    Ok((problem, factor))
}

/// The common factor of the neighbours' offsets (a set planned at twice the baseline has
/// offsets ±2 only: it is a set at twice the baseline).
pub fn common_factor(offsets: impl Iterator<Item = [i32; 2]>) -> i32 {
    fn gcd(a: i32, b: i32) -> i32 {
        if b == 0 { a.abs() } else { gcd(b, a % b) }
    }
    offsets.fold(0, |g, [x, y]| gcd(gcd(g, x), y)).max(1)
}

impl Simulation {
    /// Captures set `set` adaptively (see the module docs). `on_view` follows every view;
    /// `on_step` every plan, with the estimate it was made from. `Ok(None)` if `stop` was raised
    /// before the set finished.
    pub fn capture_adaptive_set(
        &mut self,
        set: u32,
        stop: &AtomicBool,
        mut on_view: impl FnMut(&CapturedView),
        mut on_step: impl FnMut(&PlanStep, Option<&DisparityImage>),
    ) -> Result<Option<AdaptiveSet>, SimulationError> {
        let adaptive = self.config().adaptive.clone();
        let planning = |source| SimulationError::Planning { set, source };
        let method = fuse::methods::build(&adaptive.method, None).map_err(planning)?;
        let family = fuse::methods::entry(&adaptive.method).map(|e| e.family);
        let plan_config = PlanConfig {
            max_offset: adaptive.max_offset,
            layout: adaptive.layout_for(family),
            ..PlanConfig::for_family(family)
        };
        let baseline_m = self.config().baseline_mm / 1000.0;
        let station = self.station(set);
        let mut motion = Vec::new();
        let centre = self.capture_view(set, (REFERENCE_ROLE, [0, 0]), &station, None, baseline_m, &mut motion)?;
        on_view(&centre);
        let believed_reference = centre.world_from_camera;
        let centre_luma = fuse::image::luma_levels(&centre.rgb);
        // What the first plan knows of each pixel: nothing.
        let (w, h) = (centre.camera.width as usize, centre.camera.height as usize);
        let unknown = (vec![f32::INFINITY; w * h], vec![0.0f32; w * h]);
        let mut views = vec![centre];
        let mut steps = Vec::new();
        while views.len() < adaptive.views as usize {
            if stop.load(Ordering::SeqCst) {
                return Ok(None);
            }
            let step = views.len() as u32;
            let started = Instant::now();
            let estimate = if views.len() >= 2 {
                let (problem, factor) = problem(&views, self).map_err(planning)?;
                let mut estimate = method.run(&problem, &|_| {}).map_err(planning)?;
                // Back to pixels per baseline of grid offset, as the planner counts.
                estimate.data.iter_mut().for_each(|d| *d /= factor as f32);
                Some(estimate)
            } else {
                None
            };
            let method_seconds = started.elapsed().as_secs_f64();
            let started = Instant::now();
            let (disparity, confidence) = estimate.as_ref().map_or((&unknown.0, &unknown.1), |e| {
                (&e.data, e.confidence.as_ref().unwrap_or(&unknown.1))
            });
            let taken: Vec<[i32; 2]> = views[1..].iter().map(|v| v.grid_offset).collect();
            let input = PlanInput {
                width: w,
                height: h,
                luma: &centre_luma,
                disparity_px: disparity,
                confidence,
                taken: &taken,
                max_disparity_px: adaptive
                    .max_disparity_px
                    .unwrap_or(fuse::default_num_disparities(w) as f32),
                expected_range_px: Some(self.expected_disparity_px().map(|d| d as f32)),
            };
            let scored = fuse::plan::plan(&input, &plan_config).map_err(planning)?;
            let remaining = adaptive.views as usize - views.len();
            let candidates: Vec<PlanCandidate> = scored
                .into_iter()
                .filter(|c| c.offsets.len() <= remaining)
                .map(|c| self.with_reach(c, &believed_reference, baseline_m))
                .collect();
            let chosen = candidates
                .iter()
                .find(|c| c.score.feasible && c.reachable)
                // The other half of a pair already begun is taken even if the estimate now
                // reaches past the search: the method needs it.
                .or_else(|| {
                    candidates.iter().find(|c| {
                        let completes = |o: &[i32; 2]| taken.contains(&o.map(|v| -v));
                        plan_config.layout == LayoutRule::Pairs && c.reachable && c.score.offsets.iter().all(completes)
                    })
                })
                .map(|c| c.score.offsets[0])
                .ok_or_else(|| SimulationError::NothingToTake {
                    set,
                    step,
                    candidates: candidates
                        .iter()
                        .map(PlanCandidate::verdict)
                        .collect::<Vec<_>>()
                        .join("; "),
                })?;
            let plan = PlanStep {
                set_index: set,
                step,
                time_nanos: self.time_nanos(),
                method: estimate.as_ref().map(|_| method.name().to_owned()),
                method_seconds,
                planning_seconds: started.elapsed().as_secs_f64(),
                layout: plan_config.layout,
                baseline_m,
                taken,
                candidates,
                chosen_offset: chosen,
                chosen_role: role_for_offset(chosen),
            };
            on_step(&plan, estimate.as_ref());
            let view = self.capture_view(
                set,
                (&plan.chosen_role, chosen),
                &station,
                Some(&believed_reference),
                baseline_m,
                &mut motion,
            )?;
            on_view(&view);
            views.push(view);
            steps.push(plan);
        }
        // Offsets that are all multiples of one are a set at that multiple of the baseline.
        let factor = common_factor(views[1..].iter().map(|v| v.grid_offset));
        if factor > 1 {
            for view in &mut views[1..] {
                view.grid_offset = view.grid_offset.map(|v| v / factor);
                view.role = role_for_offset(view.grid_offset);
            }
        }
        Ok(Some(AdaptiveSet {
            set: CapturedSet {
                index: set,
                name: format!("{}-{}", self.config().scene_name(), set),
                rig: RigKind::Adaptive.name().to_owned(),
                baseline_m: baseline_m * f64::from(factor),
                motion,
                views,
                // Searched by replay as the loop searched it: the working range at the set's
                // baseline.
                disparity_range: Some(self.working_disparity_range_at(factor)),
            },
            steps,
        }))
    }

    /// A scored candidate with its views' poses and whether the arm reaches them from here.
    fn with_reach(&self, score: Candidate, believed_reference: &Isometry3<f64>, baseline_m: f64) -> PlanCandidate {
        let mut unreachable_because = None;
        let world_from_camera: Vec<PoseJson> = score
            .offsets
            .iter()
            .map(|offset| {
                let pose = view_pose(believed_reference, *offset, baseline_m);
                if let Err(e) = reach(self.arm(), self.hand_eye_believed(), &pose, self.joints()) {
                    unreachable_because.get_or_insert_with(|| format!("{offset:?}: {e}"));
                }
                PoseJson::from(&pose)
            })
            .collect();
        PlanCandidate {
            score,
            reachable: unreachable_because.is_none(),
            unreachable_because,
            world_from_camera,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_at_one_multiple_make_a_set_at_that_baseline() {
        assert_eq!(common_factor([[2, 0], [-2, 0]].into_iter()), 2);
        assert_eq!(common_factor([[2, 0], [0, -1]].into_iter()), 1);
        assert_eq!(common_factor(std::iter::empty()), 1);
    }
}
