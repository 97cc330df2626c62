//! Everything that defines a training run ([`TrainConfig`]: stored in the weights' metadata and
//! `training.json`), its checks, the key of the dataset it makes, and the simulated captures it
//! draws.

use std::path::PathBuf;

use fuse::mfusenet::Architecture;
use fuse::mfusenet::input::{InputSpec, SharpSpec};
use fuse::mfusenet::weights;
use record::capture::SimulationConfig;
use record::rig::RigKind;
use record::rng::SplitMix64;
use record::scene::SceneKind;
use serde::{Deserialize, Serialize};

use super::TrainError;

/// Everything that defines a training run (stored in the weights' metadata and `training.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Cost volumes of the network: 1 (stereo), 2 (three-view) or 4 (five-view).
    pub views: usize,
    /// Optimiser steps.
    pub steps: u64,
    /// Side of the square training crops (px, a multiple of 4).
    #[serde(alias = "crop")]
    pub crop_px: usize,
    /// Larger (or smaller) crops from a step on, a multi-scale schedule: each stage's crops from
    /// its `from_step` until the next stage's, [`TrainConfig::crop_px`] before the first. More
    /// of a large crop lies farther than the network's reach from the crop's zero-padded
    /// border, and occlusions and depth jumps wider than a small crop fit in it, at about
    /// (side / `crop_px`)² the time a step. Validation and the BatchNorm calibration keep their
    /// crops. Like `steps`, stages may be added or changed when a run resumes: the steps taken
    /// stand as they were trained.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub crop_stages: Vec<CropStage>,
    /// Disparities of the training volumes (a multiple of 4).
    #[serde(alias = "disparities")]
    pub num_disparities: usize,
    /// Adam's learning rate (divided by 4 for the last quarter of the steps).
    pub learning_rate: f32,
    /// Seed of scenes, weights and crops.
    pub seed: u64,
    /// Training captures.
    pub train_sets: usize,
    /// Validation captures (other seeds).
    pub val_sets: usize,
    /// Image size of the captures (px).
    pub resolution: [u32; 2],
    /// Baselines drawn from this range (mm), see `baseline_draw`.
    pub baseline_mm: [f64; 2],
    /// How baselines are drawn from `baseline_mm`.
    #[serde(default)]
    pub baseline_draw: BaselineDraw,
    /// Scene families, used in turn.
    pub scenes: Vec<SceneKind>,
    /// Samples per pixel of the renderer.
    pub samples_per_pixel: u32,
    /// How the input volumes are made.
    pub input: InputSpec,
    /// Steps between checkpoints.
    pub checkpoint_every: u64,
    /// Steps between validations.
    pub validate_every: u64,
    /// The layers' kernel sizes (`paper`, or `lite`: about a fifth of the paper's work per
    /// voxel); with `init_weights`, the file's must be the same.
    #[serde(default, skip_serializing_if = "is_paper")]
    pub architecture: Architecture,
    /// Start from these weights (safetensors, the variant's) instead of a random initialisation
    /// (their BatchNorm statistics are kept): fine-tuning.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init_weights: Option<PathBuf>,
    /// Disparity-shift augmentation: each crop drops its first `s` slices, `s` drawn from
    /// 0, 4, …, this (a multiple of 4), so that answers fall in the first slices of the range
    /// as often as elsewhere (without it a truth one slice above the range start was answered
    /// several pixels off). 0 = off.
    #[serde(default)]
    pub disparity_shift: usize,
    /// Re-estimate the BatchNorm statistics on the calibration crops at the start (also of a
    /// fine-tuning) and every this many steps, so that they keep normalising while the weights
    /// move; 0 = only at a random initialisation, then frozen. Without it the activations of
    /// the shipped three- and five-view networks grew about tenfold per layer (logits ≈ 10⁵, a
    /// saturated softmax with no gradient for the sub-pixel part).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub recalibrate_every: u64,
    /// Track the BatchNorm statistics while training: every step normalises with the running
    /// statistics (as inference does) and then moves them by this momentum towards the step's
    /// crop's batch statistics (`BatchNorm::forward_tracking`), so that they follow the weights
    /// a little at a time; 0 = frozen after the start (how the shipped files were trained).
    #[serde(default, skip_serializing_if = "is_zero_f32")]
    pub statistics_momentum: f32,
    /// Keep an exponential moving average of the weights with this decay per step
    /// ([`fuse::mfusenet::train::Average`]; 0.999 ≈ the last thousand steps) in the checkpoint,
    /// and validate and export it instead of the last step's weights, which single-crop steps
    /// make swing from checkpoint to checkpoint. 0 = off. It never changes the training steps,
    /// so a run resumes with it switched on or off (the average starts on the resumed weights).
    #[serde(default, skip_serializing_if = "is_zero_f32")]
    pub average_decay: f32,
    /// Context below the range, as inference gives it (`fuse::mfusenet::input::input_volumes_below`):
    /// the dataset's volumes start this many disparities under 0 (each neighbour mirrored) and
    /// the targets move up by as many, so the network trains on what it sees at inference,
    /// image borders included (where a neighbour's correspondences leave its image and its
    /// costs under 0 are its only finite ones); the weights' metadata `context_below` says it.
    /// A multiple of 4 up to 16; with `disparity_shift` a crop's first `context_below` slices
    /// after the shift are its context (pixels whose truth falls there are not asked for). 0 = off.
    #[serde(default, skip_serializing_if = "is_zero_usize")]
    pub context_below: usize,
    /// Mirror augmentation ([`fuse::mfusenet::train::flipped`]): each crop is flipped top to
    /// bottom and (two or four neighbours) left to right with probability ½ each, its
    /// neighbours' volumes swapped as the mirrored rig would see them. Off in the shipped files.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub flips: bool,
    /// Keep hopeless crops ([`HOPELESS_ERROR_PX`]: the inputs' winner-take-all wrong by more
    /// than 3 px on more than 40 % of the labelled pixels: blank, periodic or mirror-like
    /// surfaces filling the crop) instead of drawing another, so that the network also learns
    /// what to answer where the costs cannot tell. Off in the shipped stereo and five-view files.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub keep_hopeless: bool,
    /// Every this many steps one training capture in memory is replaced by a new one (slot by
    /// slot in turn: [`TrainConfig::pool_index`]); 0 = the same `train_sets` captures throughout.
    #[serde(default, skip_serializing_if = "is_zero_usize")]
    pub renew_every: usize,
    /// Exposure differences between the views of a capture: each view's gain is drawn from
    /// 1 ± this (`record::capture::ErrorInjection::exposure_jitter`), as an auto-exposure camera
    /// gives; 0 = every view alike (the shipped files).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub exposure_jitter: f64,
    /// The rig of the captures: `five-view` (every shipped file) or `grid-cross` (13 views: the
    /// 3 × 3 grid and the cross at two baselines), whose far and diagonal neighbours the
    /// view-count-agnostic network draws from as well ([`super::dataset::Sample`]); the fixed
    /// networks take the cross at one baseline from either; or `line5` (a line of five), whose
    /// near pair fills the five-view network's left and right inputs and its far pair the top
    /// and bottom ones ([`super::dataset::LINE_NEIGHBOURS`]; `--views 4` only).
    #[serde(default = "five_view", skip_serializing_if = "is_five_view")]
    pub rig: RigKind,
    /// Train a sharp network (`fuse::mfusenet::Network::sharp`): each view's per-pixel costs
    /// beside its input volume, straight into `concat` (the dataset keeps them too; the network,
    /// from `init_weights` or a random start, is widened with zero weights for them). Fixed
    /// networks only; `None` = off (every shipped file).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sharp: Option<SharpSpec>,
}

fn five_view() -> RigKind {
    RigKind::FiveView
}

fn is_five_view(rig: &RigKind) -> bool {
    *rig == RigKind::FiveView
}

fn is_zero_f64(x: &f64) -> bool {
    *x == 0.0
}

fn is_zero_usize(n: &usize) -> bool {
    *n == 0
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

fn is_paper(architecture: &Architecture) -> bool {
    *architecture == Architecture::Paper
}

fn is_zero_f32(x: &f32) -> bool {
    *x == 0.0
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            views: 2,
            steps: 3000,
            crop_px: 64,
            crop_stages: Vec::new(),
            num_disparities: 32,
            learning_rate: 5e-4,
            seed: 1,
            train_sets: 40,
            val_sets: 6,
            resolution: [448, 336],
            baseline_mm: [3.0, 30.0],
            baseline_draw: BaselineDraw::LogUniform,
            disparity_shift: 0,
            recalibrate_every: 0,
            statistics_momentum: 0.0,
            average_decay: 0.0,
            context_below: 0,
            flips: false,
            keep_hopeless: false,
            renew_every: 0,
            exposure_jitter: 0.0,
            rig: RigKind::FiveView,
            sharp: None,
            scenes: vec![
                SceneKind::Random,
                SceneKind::Random,
                SceneKind::Toy,
                SceneKind::Workpiece,
            ],
            samples_per_pixel: 2,
            input: InputSpec::default(),
            checkpoint_every: 100,
            validate_every: 250,
            init_weights: None,
            architecture: Architecture::Paper,
        }
    }
}

/// A stage of [`TrainConfig::crop_stages`]: crops of `crop_px` from step `from_step` (0-based:
/// the step that makes checkpoint step `from_step + 1`) on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CropStage {
    /// The first step (0-based) of the stage.
    pub from_step: u64,
    /// Side of the stage's square crops (px, a multiple of 4).
    pub crop_px: usize,
}

/// How the baselines of the training captures are drawn.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum BaselineDraw {
    /// Uniform in millimetres.
    #[default]
    Uniform,
    /// Uniform in log-baseline: as many captures at 3–6 mm as at 15–30 mm, so that small
    /// disparities (far backgrounds, the low end of the searched range) are as common as large.
    LogUniform,
}

impl TrainConfig {
    /// Checks the values.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |field, value: String, reason| Err(TrainError::Config { field, value, reason });
        if !matches!(self.views, 0 | 1 | 2 | 4) {
            return bad("views", self.views.to_string(), "1, 2, 4 or 0 (any)");
        }
        let fits = |side: usize| {
            side >= 16 && side.is_multiple_of(4) && side as u32 <= self.resolution[0].min(self.resolution[1])
        };
        if !fits(self.crop_px) {
            return bad(
                "crop_px",
                self.crop_px.to_string(),
                "a multiple of 4, ≥ 16, within the resolution",
            );
        }
        if let Some(stage) = self.crop_stages.iter().find(|s| !fits(s.crop_px)) {
            return bad(
                "crop_stages",
                format!("{}:{}", stage.from_step, stage.crop_px),
                "each stage's crops a multiple of 4, ≥ 16, within the resolution",
            );
        }
        if self.crop_stages.windows(2).any(|w| w[1].from_step <= w[0].from_step) {
            let stages: Vec<String> = self
                .crop_stages
                .iter()
                .map(|s| format!("{}:{}", s.from_step, s.crop_px))
                .collect();
            return bad(
                "crop_stages",
                stages.join(","),
                "stages in order of their first steps, one stage per step",
            );
        }
        if !self.disparity_shift.is_multiple_of(4) || self.disparity_shift + 8 > self.num_disparities {
            return bad(
                "disparity_shift",
                self.disparity_shift.to_string(),
                "a multiple of 4 leaving at least 8 disparities",
            );
        }
        if self.scenes.is_empty()
            || self
                .scenes
                .iter()
                .any(|s| matches!(s, SceneKind::Bin | SceneKind::Thin | SceneKind::Slanted))
        {
            return bad(
                "scenes",
                format!("{:?}", self.scenes),
                "one or more families, never `bin`, `thin` or `slanted` (the held-out families, for checking generalisation)",
            );
        }
        if self.sharp.is_some() && self.views == 0 {
            return bad(
                "sharp",
                "on".to_owned(),
                "sharp volumes are for the fixed networks (--views 1, 2 or 4)",
            );
        }
        if !matches!(self.rig, RigKind::FiveView | RigKind::GridCross | RigKind::Line5) {
            return bad(
                "rig",
                self.rig.name().to_owned(),
                "five-view, grid-cross or line5 (the rigs whose views the dataset keeps)",
            );
        }
        if self.rig == RigKind::Line5 && self.views != 4 {
            return bad(
                "rig",
                self.rig.name().to_owned(),
                "line5 trains the five-view network (--views 4) on a line of five: the near pair in its left and right inputs, the far pair in its top and bottom ones",
            );
        }
        if !(0.0..0.5).contains(&self.exposure_jitter) {
            return bad(
                "exposure_jitter",
                self.exposure_jitter.to_string(),
                "a relative gain spread from 0 to below 0.5",
            );
        }
        if !self.context_below.is_multiple_of(4) || self.context_below > weights::MAX_CONTEXT_BELOW {
            return bad(
                "context_below",
                self.context_below.to_string(),
                "a multiple of 4 up to 16",
            );
        }
        if !(0.0..1.0).contains(&self.statistics_momentum) {
            return bad(
                "statistics_momentum",
                self.statistics_momentum.to_string(),
                "in [0, 1): 0 = frozen statistics",
            );
        }
        if !(0.0..1.0).contains(&self.average_decay) {
            return bad(
                "average_decay",
                self.average_decay.to_string(),
                "in [0, 1): 0 = no average, 0.999 ≈ the last thousand steps",
            );
        }
        if self.num_disparities < 4 || !self.num_disparities.is_multiple_of(4) {
            return bad(
                "num_disparities",
                self.num_disparities.to_string(),
                "a multiple of 4, ≥ 4",
            );
        }
        if self.train_sets == 0 || self.val_sets == 0 || self.scenes.is_empty() {
            return bad("train_sets/val_sets/scenes", String::new(), "at least one each");
        }
        if !(self.baseline_mm[0] > 0.0 && self.baseline_mm[1] >= self.baseline_mm[0]) {
            return bad("baseline_mm", format!("{:?}", self.baseline_mm), "0 < low ≤ high");
        }
        Ok(())
    }

    /// Side of the training crops of step `step` (0-based): the last of
    /// [`TrainConfig::crop_stages`] begun by then, else [`TrainConfig::crop_px`].
    pub fn crop_px_at(&self, step: u64) -> usize {
        self.crop_stages
            .iter()
            .rev()
            .find(|s| s.from_step <= step)
            .map_or(self.crop_px, |s| s.crop_px)
    }

    /// Disparity slices of the dataset's volumes and of every crop_px: the range plus the context
    /// below it.
    pub fn depth(&self) -> usize {
        self.num_disparities + self.context_below
    }

    /// A hash of everything that makes the dataset (seed, captures, volumes): cached samples
    /// are reused only by runs that would make the same ones.
    pub fn data_key(&self) -> u64 {
        let mut key = serde_json::json!({
            "seed": self.seed,
            "resolution": self.resolution,
            "baseline_mm": self.baseline_mm,
            "baseline_draw": self.baseline_draw,
            "scenes": self.scenes,
            "samples_per_pixel": self.samples_per_pixel,
            "disparities": self.num_disparities,
            "input": self.input,
            "steps_per_unit": fuse::mfusenet::input::STEPS_PER_UNIT,
            // Bumped when what a seed draws changes (record's scene generator, the baseline draw).
            "scene_generator": 7,
        });
        // Only when set, so that the keys of datasets made without it stay as they were.
        if self.context_below > 0 {
            key["context_below"] = self.context_below.into();
        }
        if self.exposure_jitter > 0.0 {
            key["exposure_jitter"] = self.exposure_jitter.into();
        }
        if self.rig != RigKind::FiveView {
            key["rig"] = self.rig.name().into();
        }
        if let Some(sharp) = &self.sharp {
            key["sharp"] = serde_json::json!(sharp);
        }
        let key = key.to_string();
        // FNV-1a.
        key.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
        })
    }

    /// The simulation of dataset capture `index` (validation captures have other seeds).
    /// `attempt` > 0 draws another scene for the same index (after an unreachable station).
    /// The training capture that slot `slot` (of `train_sets`) holds at step `step`: the slot's
    /// own index until it is first renewed, then one `train_sets` further on at each renewal.
    /// Renewal `r` (at step `r · renew_every`) replaces slot `(r − 1) mod train_sets`.
    pub fn pool_index(&self, slot: usize, step: u64) -> usize {
        let sets = self.train_sets.max(1);
        if self.renew_every == 0 {
            return slot;
        }
        let renewals = (step / self.renew_every as u64) as usize;
        let of_slot = if renewals > slot {
            (renewals - 1 - slot) / sets + 1
        } else {
            0
        };
        slot + of_slot * sets
    }

    /// The simulation of training capture `index` (validation capture with `validation`), on its
    /// `attempt`-th draw. Captures past the first `train_sets` (a renewing pool's) take seeds
    /// from 2,000,000 on, clear of the validation seeds and of every held-out evaluation's.
    pub fn capture_config(&self, index: usize, validation: bool, attempt: u64) -> SimulationConfig {
        let renewed = !validation && index >= self.train_sets;
        let seed = self.seed
            + index as u64
            + if validation { 1_000_000 } else { 0 }
            + if renewed { 2_000_000 } else { 0 }
            + attempt * 10_000_000;
        let mut rng = SplitMix64::new(seed.wrapping_mul(0x2545_F491_4F6C_DD1D));
        let unit = rng.unit();
        SimulationConfig {
            rig: self.rig,
            baseline_mm: match self.baseline_draw {
                BaselineDraw::Uniform => self.baseline_mm[0] + (self.baseline_mm[1] - self.baseline_mm[0]) * unit,
                BaselineDraw::LogUniform => {
                    self.baseline_mm[0] * (self.baseline_mm[1] / self.baseline_mm[0]).powf(unit)
                }
            },
            captures: 1,
            scene: self.scenes[index % self.scenes.len()],
            seed,
            width: self.resolution[0],
            height: self.resolution[1],
            samples_per_pixel: self.samples_per_pixel,
            errors: record::capture::ErrorInjection {
                exposure_jitter: self.exposure_jitter,
                ..Default::default()
            },
            ..SimulationConfig::default()
        }
    }
}
