//! Training MFuseNet on synthetic captures made by `record` (never on the evaluation scenes):
//! a dataset of simulated five-view sets with ground truth, each reduced once to its four
//! per-neighbour input volumes (cached as safetensors in the run folder), then Adam on random
//! crops with the smooth-L1 loss, validation on sets of other seeds, checkpoints and resume.
//!
//! Everything is seeded: the scenes (`seed + i` for training, `seed + 1_000_000 + i` for
//! validation), the initial weights and every crop (drawn from the seed and the step, so a
//! resumed run draws what the uninterrupted one would have).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use fuse::mfusenet::infer::{DEFAULT_REFINE_REACH, DEFAULT_SUBPIXEL_FIT};
use fuse::mfusenet::input::{InputSpec, input_volumes_below, mirror_order, neighbour_offsets, ordered_neighbours};
use fuse::mfusenet::network::BatchNormMode;
use fuse::mfusenet::train::{
    Adam, Example, clip_gradients, crop, flipped, load_checkpoint, recalibrate_batch_norm, save_checkpoint,
};
use fuse::mfusenet::{Network, WeightsInfo, weights};
use fuse::nn::Tensor;
use fuse::nn::regression::soft_argmin;
use fuse::volume::{CostVolume, VolumeSource};
use fuse::wta::LockingCurve;
use record::capture::{Simulation, SimulationConfig};
use record::rig::RigKind;
use record::scene::SceneKind;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};

use crate::viewset::ViewSet;

/// Errors of a training run.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The simulator refused a configuration or failed.
    #[error("simulating training set {index}")]
    Simulation {
        /// Set index.
        index: usize,
        /// Cause.
        #[source]
        source: record::capture::SimulationError,
    },
    /// A simulated set did not become a view set.
    #[error("training set {index}")]
    Replay {
        /// Set index.
        index: usize,
        /// Cause.
        #[source]
        source: crate::ReplayError,
    },
    /// The cost volumes could not be made.
    #[error("cost volumes of training set {index}")]
    Fuse {
        /// Set index.
        index: usize,
        /// Cause.
        #[source]
        source: fuse::FuseError,
    },
    /// The network or a weights/checkpoint file.
    #[error(transparent)]
    Network(#[from] fuse::mfusenet::Error),
    /// A file of the run folder.
    #[error("cannot write or read '{path}': {reason}")]
    File {
        /// File.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// A configuration value is unusable.
    #[error("invalid training configuration: {field} = {value} ({reason})")]
    Config {
        /// Field.
        field: &'static str,
        /// Value.
        value: String,
        /// What is allowed.
        reason: &'static str,
    },
}

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
    /// Exposure differences between the views of a capture: each view's gain is drawn from
    /// 1 ± this (`record::capture::ErrorInjection::exposure_jitter`), as an auto-exposure camera
    /// gives; 0 = every view alike (the shipped files).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub exposure_jitter: f64,
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

fn is_zero_f32(x: &f32) -> bool {
    *x == 0.0
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            views: 2,
            steps: 3000,
            crop_px: 64,
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
            context_below: 0,
            flips: false,
            keep_hopeless: false,
            exposure_jitter: 0.0,
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
        }
    }
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

/// One sample of the cache: the four per-neighbour volumes (left, right, top, bottom) and the
/// ground-truth disparity.
pub struct Sample {
    /// Left, right, top, bottom.
    pub volumes: Vec<CostVolume<u8>>,
    /// `[y][x]` px, 0 = unknown.
    pub truth: Vec<f32>,
}

impl Sample {
    /// The volumes a network of `views` inputs takes (see `fuse::mfusenet::input`).
    pub fn for_views(&self, views: usize) -> Vec<&CostVolume<u8>> {
        let indices: &[usize] = match views {
            1 => &[1],
            2 => &[0, 1],
            _ => &[0, 1, 2, 3],
        };
        indices.iter().map(|i| &self.volumes[*i]).collect()
    }
}

/// What the caller sees after each step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    /// Steps done.
    pub step: u64,
    /// Loss of this step.
    pub loss: f32,
    /// Mean loss over the last 50 steps.
    pub mean_loss: f32,
    /// Seconds per step (mean over this session's steps).
    pub seconds_per_step: f64,
    /// The last validation `(AvgErr px, Bad1 %)`.
    pub validation: Option<(f64, f64)>,
}

/// The outcome of a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainSummary {
    /// The configuration.
    pub config: TrainConfig,
    /// Steps done (all sessions).
    pub steps_done: u64,
    /// Whether the run stopped early (interrupted).
    pub interrupted: bool,
    /// Seconds of training, all sessions.
    pub train_seconds: f64,
    /// Seconds to make the dataset (this session; 0 when cached).
    pub dataset_seconds: f64,
    /// Final validation AvgErr (px) on the validation crops.
    pub val_avg_err_px: Option<f64>,
    /// Final validation Bad1 (%).
    pub val_bad1_percent: Option<f64>,
    /// AvgErr (px) of the winner-take-all of the mean input volume on the validation crops:
    /// the inputs' own answer, which the network must beat (and a check that the crops'
    /// targets and volumes agree on where disparity 0 is).
    pub val_wta_avg_err_px: f64,
    /// Trainable parameters.
    pub parameters: usize,
    /// The weights file written.
    pub weights: PathBuf,
}

fn file_error(path: &Path, reason: String) -> TrainError {
    TrainError::File {
        path: path.to_path_buf(),
        reason,
    }
}

impl TrainConfig {
    /// Checks the values.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |field, value: String, reason| Err(TrainError::Config { field, value, reason });
        if !matches!(self.views, 1 | 2 | 4) {
            return bad("views", self.views.to_string(), "1, 2 or 4");
        }
        if self.crop_px < 16
            || !self.crop_px.is_multiple_of(4)
            || self.crop_px as u32 > self.resolution[0].min(self.resolution[1])
        {
            return bad(
                "crop_px",
                self.crop_px.to_string(),
                "a multiple of 4, ≥ 16, within the resolution",
            );
        }
        if !self.disparity_shift.is_multiple_of(4) || self.disparity_shift + 8 > self.num_disparities {
            return bad(
                "disparity_shift",
                self.disparity_shift.to_string(),
                "a multiple of 4 leaving at least 8 disparities",
            );
        }
        if self.scenes.is_empty() || self.scenes.contains(&SceneKind::Bin) {
            return bad(
                "scenes",
                format!("{:?}", self.scenes),
                "one or more families, never `bin` (the held-out family, for checking generalisation)",
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
            // Bumped when `record`'s scene generator changes what a seed draws.
            "scene_generator": 5,
        });
        // Only when set, so that the keys of datasets made without it stay as they were.
        if self.context_below > 0 {
            key["context_below"] = self.context_below.into();
        }
        if self.exposure_jitter > 0.0 {
            key["exposure_jitter"] = self.exposure_jitter.into();
        }
        let key = key.to_string();
        // FNV-1a.
        key.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
        })
    }

    /// The simulation of dataset capture `index` (validation captures have other seeds).
    /// `attempt` > 0 draws another scene for the same index (after an unreachable station).
    pub fn capture_config(&self, index: usize, validation: bool, attempt: u64) -> SimulationConfig {
        let seed = self.seed + index as u64 + if validation { 1_000_000 } else { 0 } + attempt * 10_000_000;
        let mut rng = Rng(seed.wrapping_mul(0x2545_F491_4F6C_DD1D));
        let unit = rng.unit();
        SimulationConfig {
            rig: RigKind::FiveView,
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

/// A small seeded generator (xorshift*), for crops.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.max(1).wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// Makes (or reads from `cache_dir`) one dataset sample.
pub fn sample(config: &TrainConfig, index: usize, validation: bool, cache_dir: &Path) -> Result<Sample, TrainError> {
    let name = format!(
        "{}-{index:04}-{:016x}.safetensors",
        if validation { "val" } else { "train" },
        config.data_key()
    );
    let path = cache_dir.join(name);
    if let Ok(bytes) = std::fs::read(&path)
        && let Some(sample) = read_sample(&bytes, config.depth())
    {
        return Ok(sample);
    }
    // Some random stations are out of the arm's reach: draw another scene (a few times).
    let mut attempt = 0;
    let set = loop {
        let stop = AtomicBool::new(false);
        let captured = Simulation::new(config.capture_config(index, validation, attempt))
            .and_then(|mut sim| sim.capture_set(0, &stop, |_| {}));
        match captured {
            Ok(Some(set)) => break set,
            Ok(None) => return Err(file_error(&path, "the simulation produced no set".to_owned())),
            Err(source) if attempt >= 4 => return Err(TrainError::Simulation { index, source }),
            Err(source) => tracing::debug!("training set {index}: {source}; drawing another scene"),
        }
        attempt += 1;
    };
    let view_set = ViewSet::from_captured(&set).map_err(|source| TrainError::Replay { index, source })?;
    let problem = view_set
        .problem(0, config.num_disparities, false)
        .map_err(|source| TrainError::Replay { index, source })?;
    let neighbours = ordered_neighbours(&problem, 4).map_err(|source| TrainError::Fuse { index, source })?;
    // Samples are in slice coordinates, as `read_sample` gives them back: the first slice (the
    // context's, under 0) is 0 and the truth is shifted up by the context.
    let volumes = input_volumes_below(&problem, &neighbours, config.input, config.context_below, &|| {})
        .map_err(|source| TrainError::Fuse { index, source })?
        .0
        .into_iter()
        .map(|v| CostVolume { min_disparity: 0, ..v })
        .collect();
    let below = config.context_below as f32;
    let truth = view_set
        .ground_truth_disparity()
        .ok_or_else(|| file_error(&path, "the simulated set has no ground truth".to_owned()))?
        .into_iter()
        .map(|t| if t.is_finite() && t > 0.0 { t + below } else { 0.0 })
        .collect();
    let sample = Sample { volumes, truth };
    write_sample(&sample, &path)?;
    Ok(sample)
}

fn write_sample(sample: &Sample, path: &Path) -> Result<(), TrainError> {
    let v = &sample.volumes[0];
    let truth: Vec<u8> = sample.truth.iter().flat_map(|t| t.to_le_bytes()).collect();
    let mut views = Vec::new();
    for (i, volume) in sample.volumes.iter().enumerate() {
        let view = TensorView::new(Dtype::U8, vec![v.height, v.width, v.num_disparities], &volume.data)
            .map_err(|e| file_error(path, e.to_string()))?;
        views.push((format!("volume.{i}"), view));
    }
    views.push((
        "truth".to_owned(),
        TensorView::new(Dtype::F32, vec![v.height, v.width], &truth).map_err(|e| file_error(path, e.to_string()))?,
    ));
    let bytes = safetensors::serialize(views, None).map_err(|e| file_error(path, e.to_string()))?;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| file_error(dir, e.to_string()))?;
    }
    let temporary = path.with_extension("partial");
    std::fs::write(&temporary, bytes).map_err(|e| file_error(&temporary, e.to_string()))?;
    std::fs::rename(&temporary, path).map_err(|e| file_error(path, e.to_string()))
}

fn read_sample(bytes: &[u8], num_disparities: usize) -> Option<Sample> {
    let tensors = SafeTensors::deserialize(bytes).ok()?;
    let truth_view = tensors.tensor("truth").ok()?;
    let (height, width) = (*truth_view.shape().first()?, *truth_view.shape().get(1)?);
    let truth = truth_view
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let roles = [
        ("left", [-1, 0]),
        ("right", [1, 0]),
        ("top", [0, -1]),
        ("bottom", [0, 1]),
    ];
    let mut volumes = Vec::new();
    for (i, (role, offset)) in roles.iter().enumerate() {
        let view = tensors.tensor(&format!("volume.{i}")).ok()?;
        if view.shape() != [height, width, num_disparities] {
            return None;
        }
        volumes.push(CostVolume {
            width,
            height,
            min_disparity: 0,
            num_disparities,
            data: view.data().to_vec(),
            max_cost: 255,
            source: VolumeSource::Neighbour {
                role: (*role).to_owned(),
                offset: *offset,
            },
        });
    }
    Some(Sample { volumes, truth })
}

/// Validation crops: the centre `side × side` (largest multiple of 4 that fits, at most 160)
/// of every validation sample.
pub fn validation_examples(samples: &[Sample], views: usize, num_disparities: usize) -> Vec<Example> {
    samples
        .iter()
        .map(|s| {
            let (w, h) = (s.volumes[0].width, s.volumes[0].height);
            let side = (w.min(h).min(160)) / 4 * 4;
            crop(
                &s.for_views(views),
                &s.truth,
                ((h - side) / 2, (w - side) / 2),
                (side, side),
                num_disparities,
            )
        })
        .collect()
}

/// The errors (px) over the masked pixels of the winner-take-all of the mean input volume (with
/// parabola refinement): what the network's inputs say on their own.
pub fn winner_take_all_errors(example: &Example) -> Vec<f32> {
    let Some(first) = example.inputs.first() else {
        return Vec::new();
    };
    let [_, d, h, w] = first.shape;
    let plane = h * w;
    (0..plane)
        .filter(|pixel| example.mask[*pixel])
        .map(|pixel| {
            let cost = |z: usize| example.inputs.iter().map(|t| t.data[z * plane + pixel]).sum::<f32>();
            let best = (0..d).min_by(|a, b| cost(*a).total_cmp(&cost(*b))).unwrap_or(0);
            let mut estimate = best as f32;
            if best > 0 && best + 1 < d {
                let (l, c, r) = (cost(best - 1), cost(best), cost(best + 1));
                let denominator = l - 2.0 * c + r;
                if denominator > 0.0 {
                    estimate += 0.5 * (l - r) / denominator;
                }
            }
            (estimate - example.target[pixel]).abs()
        })
        .collect()
}

/// AvgErr (px) and Bad1 (%) of [`winner_take_all_errors`] over the examples.
pub fn winner_take_all_reference(examples: &[Example]) -> (f64, f64) {
    let (mut sum, mut bad, mut count) = (0f64, 0usize, 0usize);
    for error in examples.iter().flat_map(winner_take_all_errors) {
        sum += f64::from(error);
        bad += usize::from(error > 1.0);
        count += 1;
    }
    let count = count.max(1) as f64;
    (sum / count, 100.0 * bad as f64 / count)
}

/// A crop is hopeless when the inputs are wrong by more than this (px) on more than
/// [`HOPELESS_FRACTION`] of its labelled pixels: a periodic or blank surface filling the crop,
/// where no local fusion can know the answer. Training draws another unless
/// [`TrainConfig::keep_hopeless`] (occlusions and reflections, wrong in one neighbour only, stay
/// in either way).
pub const HOPELESS_ERROR_PX: f32 = 3.0;
/// See [`HOPELESS_ERROR_PX`].
pub const HOPELESS_FRACTION: f32 = 0.4;

fn hopeless(example: &Example) -> bool {
    let errors = winner_take_all_errors(example);
    let wrong = errors.iter().filter(|e| **e > HOPELESS_ERROR_PX).count();
    wrong as f32 > HOPELESS_FRACTION * errors.len() as f32
}

/// Validation figures `(AvgErr px, Bad1 %)` of both ways to read the network's output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Validation {
    /// The paper's soft-argmin over the whole range.
    pub soft_argmin: (f64, f64),
    /// The integer nearest the soft-argmin, refined by the shipped fit through the summed
    /// inputs (`fuse::mfusenet::infer::Estimate::refine`, `DEFAULT_SUBPIXEL_FIT`) with the
    /// given locking correction.
    pub refined: (f64, f64),
    /// Mean over the validated pixels of the logits' range over disparity (max − min): how
    /// peaked the softmax is. Tens in a healthy network; the three- and five-view files
    /// trained with frozen statistics reach about 10⁵ (saturated, one-hot).
    pub logit_range: f64,
}

impl Validation {
    /// Whether the refined estimate has the lower AvgErr (what the weights' metadata
    /// `estimate` then asks inference to use).
    pub fn refine_is_better(&self) -> bool {
        self.refined.0 < self.soft_argmin.0
    }
}

/// The refined readout's pixel-locking curve on these samples' inputs for a network of `views`
/// inputs (`fuse::wta::LockingCurve::fit` over [`locking_pairs`]). `None` when too few pixels
/// have a minimum there.
pub fn fit_locking(samples: &[Sample], views: usize) -> Option<LockingCurve> {
    LockingCurve::fit(locking_pairs(samples, views))
}

/// At every pixel with ground truth, the fit's offset through the summed input costs at the
/// integer nearest the truth (where that integer is a minimum of them), and the truth's
/// offset from that integer.
pub fn locking_pairs(samples: &[Sample], views: usize) -> impl Iterator<Item = (f64, f64)> + '_ {
    samples.iter().flat_map(move |sample| {
        let volumes = sample.for_views(views);
        let (w, depth) = (volumes[0].width, volumes[0].num_disparities);
        sample.truth.iter().enumerate().filter_map(move |(pixel, &t)| {
            let d = t.round();
            if !(t > 0.0 && d >= 1.0 && d + 1.0 < depth as f32) {
                return None;
            }
            let (x, y, d) = (pixel % w, pixel / w, d as usize);
            let cost = |z: usize| volumes.iter().map(|v| f64::from(v.costs(x, y)[z])).sum::<f64>();
            DEFAULT_SUBPIXEL_FIT
                .offset([cost(d - 1), cost(d), cost(d + 1)])
                .map(|delta| (delta, f64::from(t) - d as f64))
        })
    })
}

/// What [`calibrate_locking`] fitted and how far it moves the readout on its captures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    /// The curve written into the file.
    pub curve: LockingCurve,
    /// Pixels it was fitted on.
    pub pixels: usize,
    /// Mean |offset − truth's offset| (px) of the fit's own offsets on them.
    pub error_before_px: f64,
    /// The same with the curve applied.
    pub error_after_px: f64,
    /// The same with half the curve (`LockingCurve::damped(0.5)`, inference's default).
    pub error_half_px: f64,
}

/// Fits the refined readout's locking curve ([`fit_locking`]) for a weights file made by
/// `replay train` and writes the file again at `out` (the same tensors) with the curve in its
/// metadata (`locking_curve`, with `locking_note`): the training captures its metadata
/// `train_config` names (made again, or read from the cache in `dataset_dir`), never
/// evaluation scenes. For files trained before `replay train` wrote the curve itself.
pub fn calibrate_locking(
    weights_file: &Path,
    dataset_dir: &Path,
    out: &Path,
    on_dataset: &mut dyn FnMut(usize, usize),
) -> Result<Calibration, TrainError> {
    let (net, mut info) = weights::load(weights_file, None)?;
    let file = weights_file.display().to_string();
    let config: TrainConfig = info
        .get("train_config")
        .and_then(|json| serde_json::from_str(json).ok())
        .ok_or_else(|| TrainError::Config {
            field: "train_config",
            value: file.clone(),
            reason: "the weights file's metadata has no training configuration to make its captures from",
        })?;
    let mut samples = Vec::with_capacity(config.train_sets);
    for index in 0..config.train_sets {
        samples.push(sample(&config, index, false, dataset_dir)?);
        on_dataset(index + 1, config.train_sets);
    }
    let curve = fit_locking(&samples, net.views).ok_or_else(|| TrainError::Config {
        field: "train_sets",
        value: config.train_sets.to_string(),
        reason: "too few pixels with ground truth to fit the locking curve",
    })?;
    let (mut pixels, mut before, mut after, mut half) = (0usize, 0f64, 0f64, 0f64);
    let damped = curve.damped(0.5);
    for (delta, truth) in locking_pairs(&samples, net.views) {
        pixels += 1;
        before += (delta - truth).abs();
        after += (curve.apply(delta) - truth).abs();
        half += (damped.apply(delta) - truth).abs();
    }
    let pixels_f = pixels.max(1) as f64;
    info.set("locking_curve", serde_json::to_string(&curve).unwrap_or_default());
    info.set(
        "locking_note",
        format!(
            "fitted after training by `replay train --calibrate {file}` on the {} training captures of train_config",
            config.train_sets
        ),
    );
    weights::save(&net, &info, out)?;
    Ok(Calibration {
        curve,
        pixels,
        error_before_px: before / pixels_f,
        error_after_px: after / pixels_f,
        error_half_px: half / pixels_f,
    })
}

/// AvgErr (px) and Bad1 (%) of the eval-mode network over the examples' masked pixels, for
/// both estimates (the refined one with `locking`).
pub fn validate_estimates(
    net: &Network,
    examples: &[Example],
    locking: Option<LockingCurve>,
) -> Result<Validation, TrainError> {
    let mut sums = [(0f64, 0usize); 2];
    let mut count = 0usize;
    let mut range_sum = 0f64;
    for example in examples {
        let logits = net.logits(&example.inputs)?;
        let (disparity, _) = soft_argmin(&logits);
        let [_, depth, h, w] = logits.shape;
        let plane = h * w;
        for (pixel, ((d, t), m)) in disparity.iter().zip(&example.target).zip(&example.mask).enumerate() {
            if !*m {
                continue;
            }
            let (lo, hi) = (0..depth)
                .map(|z| logits.data[z * plane + pixel])
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
            range_sum += f64::from(hi - lo);
            let cost = |z: usize| {
                example
                    .inputs
                    .iter()
                    .map(|v| f64::from(v.data[z * plane + pixel]))
                    .sum::<f64>()
            };
            let refined = fuse::mfusenet::infer::refined(
                f64::from(*d),
                cost,
                depth,
                DEFAULT_REFINE_REACH,
                DEFAULT_SUBPIXEL_FIT,
                locking,
            );
            for (sum, value) in sums.iter_mut().zip([f64::from(*d), refined]) {
                let error = (value - f64::from(*t)).abs();
                sum.0 += error;
                sum.1 += usize::from(error > 1.0);
            }
            count += 1;
        }
    }
    let count = count.max(1) as f64;
    let figures = |(sum, bad): (f64, usize)| (sum / count, 100.0 * bad as f64 / count);
    Ok(Validation {
        soft_argmin: figures(sums[0]),
        refined: figures(sums[1]),
        logit_range: range_sum / count,
    })
}

/// Where a run keeps its files.
#[derive(Debug, Clone, Copy)]
pub struct TrainPaths<'a> {
    /// The run folder: checkpoint, curves, `training.json`.
    pub dir: &'a Path,
    /// The dataset cache (shared by runs).
    pub dataset: &'a Path,
    /// The weights written at the end.
    pub weights: &'a Path,
}

/// Paths of a run folder.
pub struct RunFiles {
    /// The folder.
    pub dir: PathBuf,
}

impl RunFiles {
    /// Checkpoint (weights + Adam + step).
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join("checkpoint.safetensors")
    }
    /// Loss and validation per step (CSV).
    pub fn curves_csv(&self) -> PathBuf {
        self.dir.join("curves.csv")
    }
    /// The same as a Rerun recording.
    pub fn curves_rrd(&self) -> PathBuf {
        self.dir.join("curves.rrd")
    }
    /// The run's record.
    pub fn summary(&self) -> PathBuf {
        self.dir.join("training.json")
    }
}

/// Runs (or resumes) training in `dir` with the dataset cached in `dataset_dir`; writes the weights to `weights_out`. `on_dataset(done,
/// total)` reports the dataset, `on_step` every step; `stop` ends the run early after a
/// checkpoint (the summary says it was interrupted).
pub fn train(
    config: &TrainConfig,
    paths: &TrainPaths<'_>,
    command: &str,
    stop: &AtomicBool,
    on_dataset: &mut dyn FnMut(usize, usize),
    on_step: &mut dyn FnMut(&StepReport),
) -> Result<TrainSummary, TrainError> {
    config.validate()?;
    let TrainPaths {
        dir,
        dataset: dataset_dir,
        weights: weights_out,
    } = *paths;
    let files = RunFiles { dir: dir.to_path_buf() };
    std::fs::create_dir_all(dir).map_err(|e| file_error(dir, e.to_string()))?;
    let dataset_started = Instant::now();
    let total = config.train_sets + config.val_sets;
    let mut train_samples = Vec::new();
    let mut val_samples = Vec::new();
    for i in 0..total {
        let validation = i >= config.train_sets;
        let index = if validation { i - config.train_sets } else { i };
        let s = sample(config, index, validation, dataset_dir)?;
        if validation {
            val_samples.push(s);
        } else {
            train_samples.push(s);
        }
        on_dataset(i + 1, total);
        if stop.load(Ordering::SeqCst) {
            break;
        }
    }
    let dataset_seconds = dataset_started.elapsed().as_secs_f64();
    if train_samples.len() < config.train_sets || val_samples.len() < config.val_sets {
        return Err(TrainError::Config {
            field: "dataset",
            value: format!("{} of {total} captures", train_samples.len() + val_samples.len()),
            reason: "interrupted before the dataset was complete (the captures made so far are cached)",
        });
    }
    let val_examples = validation_examples(&val_samples, config.views, config.depth());
    let (wta_avg, wta_bad1) = winner_take_all_reference(&val_examples);
    let locking = fit_locking(&train_samples, config.views);
    tracing::info!(
        "validation crops: winner-take-all of the mean input volume gives AvgErr {wta_avg:.3} px, Bad1 {wta_bad1:.2} % (the network must do better)"
    );

    // BatchNorm statistics: batch statistics of a few dozen fixed crops at the start, then frozen
    // (see `BatchNorm::forward_frozen`; one crop per step is far too small a batch to normalise
    // with), recalibrated every `recalibrate_every` steps, or tracked (`statistics_momentum`).
    let mut calibration_rng = Rng(config.seed ^ 0x5EED_CA1B);
    let calibration: Vec<Example> = (0..CALIBRATION_CROPS)
        .map(|_| random_crop(config, &train_samples, &mut calibration_rng))
        .collect();
    // Resume or start.
    let (mut net, mut adam, mut history, mut train_seconds) = match load_checkpoint(&files.checkpoint(), config.views) {
        Ok((net, adam, info))
            if info.get("train_config") == Some(&serde_json::to_string(config).unwrap_or_default()) =>
        {
            let history = read_curves(&files.curves_csv(), adam.step);
            let seconds = info.get("train_seconds").and_then(|s| s.parse().ok()).unwrap_or(0.0);
            (net, adam, history, seconds)
        }
        _ => {
            let mut net = match &config.init_weights {
                Some(path) => {
                    let mut net = weights::load(path, Some(config.views))?.0;
                    if config.recalibrate_every > 0 {
                        recalibrate_batch_norm(&mut net, &calibration)?;
                    }
                    net
                }
                None => {
                    let mut net = Network::init(config.views, config.seed);
                    recalibrate_batch_norm(&mut net, &calibration)?;
                    net
                }
            };
            let adam = Adam::new(&mut net, config.learning_rate);
            (net, adam, Vec::new(), 0.0)
        }
    };
    // The momentum is not part of the weights: set it on every (re)start.
    let batch_norm_mode = if config.statistics_momentum > 0.0 {
        for layer in net.layers_mut() {
            layer.bn.momentum = Some(config.statistics_momentum);
        }
        BatchNormMode::Tracking
    } else {
        BatchNormMode::Frozen
    };
    let started = Instant::now();
    let session_start_step = adam.step;
    let mut recent: Vec<f32> = history.iter().rev().take(50).map(|r: &CurveRow| r.loss).collect();
    let mut last_validation = history.iter().rev().find_map(|r| r.val_avg_err_px.zip(r.val_bad1));
    // The last validation with both estimates and its step, reused for the metadata.
    let mut last_estimates: Option<(u64, Validation)> = None;
    let info_for = |seconds: f64| {
        let mut info = WeightsInfo::default();
        info.set("train_config", serde_json::to_string(config).unwrap_or_default());
        info.set("train_seconds", format!("{seconds:.1}"));
        info
    };
    let mut interrupted = false;
    while adam.step < config.steps {
        if stop.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        let step = adam.step;
        adam.learning_rate = if step >= config.steps * 3 / 4 {
            config.learning_rate / 4.0
        } else {
            config.learning_rate
        };
        let mut rng = Rng((config.seed ^ 0x9E37_79B9_7F4A_7C15).wrapping_add(step.wrapping_mul(0xD1B5_4A32_D192_ED03)));
        let example = random_crop(config, &train_samples, &mut rng);
        let (loss, _, mut gradients) =
            net.loss_and_gradients_with(&example.inputs, &example.target, &example.mask, batch_norm_mode)?;
        clip_gradients(&mut gradients, MAX_GRADIENT_NORM);
        adam.update(&mut net, &gradients);
        if config.recalibrate_every > 0 && adam.step % config.recalibrate_every == 0 {
            recalibrate_batch_norm(&mut net, &calibration)?;
        }
        recent.insert(0, loss);
        recent.truncate(50);
        let done = adam.step;
        let mut row = CurveRow {
            step: done,
            loss,
            val_avg_err_px: None,
            val_bad1: None,
        };
        if done % config.validate_every == 0 || done == config.steps {
            let estimates = validate_estimates(&net, &val_examples, locking)?;
            tracing::info!(
                "step {done}: validation AvgErr {:.3} px / Bad1 {:.2} % (refined {:.3} / {:.2}), logit range {:.1} (tens is healthy, thousands saturated)",
                estimates.soft_argmin.0,
                estimates.soft_argmin.1,
                estimates.refined.0,
                estimates.refined.1,
                estimates.logit_range
            );
            last_estimates = Some((done, estimates));
            let (avg, bad1) = estimates.soft_argmin;
            row.val_avg_err_px = Some(avg);
            row.val_bad1 = Some(bad1);
            last_validation = Some((avg, bad1));
        }
        history.push(row);
        let elapsed = started.elapsed().as_secs_f64();
        on_step(&StepReport {
            step: done,
            loss,
            mean_loss: recent.iter().sum::<f32>() / recent.len().max(1) as f32,
            seconds_per_step: elapsed / (done - session_start_step).max(1) as f64,
            validation: last_validation,
        });
        if done % config.checkpoint_every == 0 || done == config.steps {
            let seconds = train_seconds + elapsed;
            save_checkpoint(&mut net, &adam, &info_for(seconds), &files.checkpoint())?;
            write_curves(&files, &history)?;
        }
    }
    train_seconds += started.elapsed().as_secs_f64();
    save_checkpoint(&mut net, &adam, &info_for(train_seconds), &files.checkpoint())?;
    write_curves(&files, &history)?;
    let mut info = info_for(train_seconds);
    info.set("format", "mfusenet-weights/1");
    info.set("variant", variant_name(config.views));
    info.set("views", config.views.to_string());
    info.set(
        "input_order",
        match config.views {
            1 => "right",
            2 => "left,right",
            _ => "left,right,top,bottom",
        },
    );
    info.set("disparities_trained", config.num_disparities.to_string());
    info.set(
        "input_normalisation",
        "per neighbour: census 7x7 block-summed, SGM 8 paths; (S - min_d S) / (8 P2), steps of 1/128, max 255 steps; tensor = byte / 128",
    );
    info.set("input_spec", serde_json::to_string(&config.input).unwrap_or_default());
    info.set(
        "input_steps_per_unit",
        fuse::mfusenet::input::STEPS_PER_UNIT.to_string(),
    );
    // A network trained on crops that start below their answers (`--disparity-shift`) is run
    // with 4 slices of context below the searched range (measured: the three-view network on
    // Middlebury 0.442 -> 0.410 px); one trained without them never saw that and is run without.
    // A network trained with context below its range (`context_below`) is run with as much.
    let context = if config.context_below > 0 {
        config.context_below
    } else {
        config.disparity_shift.min(4)
    };
    info.set("context_below", context.to_string());
    info.set("made_by", command);
    info.set("steps", adam.step.to_string());
    if let Some((avg, bad1)) = last_validation {
        info.set("val_avg_err_px", format!("{avg:.4}"));
        info.set("val_bad1_percent", format!("{bad1:.3}"));
    }
    // How inference should read this network: whichever estimate validates better (the last
    // step's validation when it had one, e.g. not after an interruption or a resumed finished run).
    let estimates = match last_estimates {
        Some((step, estimates)) if step == adam.step => estimates,
        _ => validate_estimates(&net, &val_examples, locking)?,
    };
    let (avg, bad1) = estimates.refined;
    info.set("val_refined_avg_err_px", format!("{avg:.4}"));
    info.set("val_refined_bad1_percent", format!("{bad1:.3}"));
    info.set("val_logit_range", format!("{:.1}", estimates.logit_range));
    if let Some(curve) = locking {
        info.set("locking_curve", serde_json::to_string(&curve).unwrap_or_default());
    }
    info.set(
        "estimate",
        if estimates.refine_is_better() {
            "refine"
        } else {
            "soft-argmin"
        },
    );
    weights::save(&net, &info, weights_out)?;
    let summary = TrainSummary {
        config: config.clone(),
        steps_done: adam.step,
        interrupted,
        train_seconds,
        dataset_seconds,
        val_avg_err_px: last_validation.map(|v| v.0),
        val_bad1_percent: last_validation.map(|v| v.1),
        val_wta_avg_err_px: wta_avg,
        parameters: net.parameter_count(),
        weights: weights_out.to_path_buf(),
    };
    let json = serde_json::to_string_pretty(&summary).map_err(|e| file_error(&files.summary(), e.to_string()))?;
    std::fs::write(files.summary(), json).map_err(|e| file_error(&files.summary(), e.to_string()))?;
    Ok(summary)
}

/// Crops whose batch statistics set the BatchNorms.
const CALIBRATION_CROPS: usize = 32;
/// Largest global gradient norm (larger ones are scaled down).
const MAX_GRADIENT_NORM: f32 = 1.0;

/// A random training crop with ground truth on at least half its pixels (the last of a few
/// tries otherwise).
fn random_crop(config: &TrainConfig, samples: &[Sample], rng: &mut Rng) -> Example {
    let mut example = None;
    for _ in 0..8 {
        let s = &samples[rng.below(samples.len())];
        let (w, h) = (s.volumes[0].width, s.volumes[0].height);
        let (y0, x0) = (rng.below(h - config.crop_px + 1), rng.below(w - config.crop_px + 1));
        let mut e = crop(
            &s.for_views(config.views),
            &s.truth,
            (y0, x0),
            (config.crop_px, config.crop_px),
            config.depth(),
        );
        if config.disparity_shift > 0 {
            e = shifted(e, 4 * rng.below(config.disparity_shift / 4 + 1), config.context_below);
        }
        if config.flips {
            let (vertical, horizontal) = (rng.below(2) == 1, rng.below(2) == 1);
            let offsets = neighbour_offsets(s.for_views(config.views)).unwrap_or_default();
            // A flip the rig has no mirror for (a single right neighbour, left to right) is not made.
            let possible = |v: bool, h: bool| mirror_order(&offsets, v, h).is_some();
            let (vertical, horizontal) = (vertical && possible(true, false), horizontal && possible(false, true));
            if let Some(mirror) = flipped(&e, &offsets, vertical, horizontal) {
                e = mirror;
            }
        }
        let enough = acceptable(config, &e);
        example = Some(e);
        if enough {
            break;
        }
    }
    example.unwrap_or_else(|| Example {
        inputs: Vec::new(),
        target: Vec::new(),
        mask: Vec::new(),
    })
}

/// Whether training takes this crop_px: ground truth on more than half its pixels, and inputs
/// that are not hopeless unless the configuration keeps those.
fn acceptable(config: &TrainConfig, example: &Example) -> bool {
    example.mask.iter().filter(|m| **m).count() * 2 > example.mask.len() && (config.keep_hopeless || !hopeless(example))
}

/// `example` without its first `slices` disparity slices: targets move down by as many, and
/// pixels whose truth falls below the new range, or in its first `context` slices (context
/// below the range, `TrainConfig::context_below`: real costs under the crop's range where the
/// shift reaches past them, the mirrored ones where it does not), no longer count.
pub fn shifted(example: Example, slices: usize, context: usize) -> Example {
    if slices == 0 {
        // The targets are already above the context (the dataset moved them up by it).
        return example;
    }
    let inputs = example
        .inputs
        .into_iter()
        .map(|t| {
            let [n, d, h, w] = t.shape;
            let kept = d.saturating_sub(slices);
            Tensor {
                shape: [n, kept, h, w],
                data: t.data.get(slices * h * w..).unwrap_or_default().to_vec(),
            }
        })
        .collect();
    let offset = slices as f32;
    let mask = example
        .mask
        .iter()
        .zip(&example.target)
        .map(|(m, t)| *m && *t >= offset + context as f32)
        .collect();
    let target = example.target.iter().map(|t| (t - offset).max(0.0)).collect();
    Example { inputs, target, mask }
}

/// The registry name of a variant.
pub fn variant_name(views: usize) -> &'static str {
    match views {
        1 => "mfusenet-stereo",
        2 => "mfusenet-3view",
        _ => "mfusenet-5view",
    }
}

/// One row of `curves.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct CurveRow {
    step: u64,
    loss: f32,
    val_avg_err_px: Option<f64>,
    val_bad1: Option<f64>,
}

fn read_curves(path: &Path, up_to: u64) -> Vec<CurveRow> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return Vec::new();
    };
    text.lines()
        .skip(1)
        .filter_map(|line| {
            let f: Vec<&str> = line.split(',').collect();
            Some(CurveRow {
                step: f.first()?.parse().ok()?,
                loss: f.get(1)?.parse().ok()?,
                val_avg_err_px: f.get(2).and_then(|v| v.parse().ok()),
                val_bad1: f.get(3).and_then(|v| v.parse().ok()),
            })
        })
        .filter(|r| r.step <= up_to)
        .collect()
}

fn write_curves(files: &RunFiles, history: &[CurveRow]) -> Result<(), TrainError> {
    let mut csv = String::from("step,loss,val_avg_err_px,val_bad1_percent\n");
    let opt = |v: Option<f64>| v.map_or_else(String::new, |v| format!("{v:.5}"));
    for r in history {
        csv.push_str(&format!(
            "{},{:.6},{},{}\n",
            r.step,
            r.loss,
            opt(r.val_avg_err_px),
            opt(r.val_bad1)
        ));
    }
    let path = files.curves_csv();
    std::fs::write(&path, csv).map_err(|e| file_error(&path, e.to_string()))?;
    // Mean loss over windows of 25 steps, and the validations.
    let mut series: HashMap<&str, Vec<(i64, f64)>> = HashMap::new();
    for chunk in history.chunks(25) {
        if let Some(last) = chunk.last() {
            let mean = chunk.iter().map(|r| f64::from(r.loss)).sum::<f64>() / chunk.len() as f64;
            series.entry("train/loss").or_default().push((last.step as i64, mean));
        }
    }
    for r in history {
        if let (Some(avg), Some(bad1)) = (r.val_avg_err_px, r.val_bad1) {
            series.entry("val/avg_err_px").or_default().push((r.step as i64, avg));
            series
                .entry("val/bad1_percent")
                .or_default()
                .push((r.step as i64, bad1));
        }
    }
    let mut series: Vec<(&str, Vec<(i64, f64)>)> = series.into_iter().collect();
    series.sort_by(|a, b| a.0.cmp(b.0));
    viz::stream::write_curves(&files.curves_rrd(), "mfusenet_training", &series)
        .map_err(|e| file_error(&files.curves_rrd(), e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use fuse::nn::Tensor;

    /// Two views whose costs are |d − m| around a minimum `m` per pixel.
    fn example(minimum: impl Fn(usize) -> f32, target: f32) -> Example {
        let (d, h, w) = (16, 4, 5);
        let mut volume = Tensor::zeros([1, d, h, w]);
        for z in 0..d {
            for p in 0..h * w {
                volume.data[z * h * w + p] = (z as f32 - minimum(p)).abs();
            }
        }
        Example {
            inputs: vec![volume.clone(), volume],
            target: vec![target; h * w],
            mask: vec![true; h * w],
        }
    }

    #[test]
    fn the_held_out_family_and_bad_exposure_spreads_are_refused() {
        let ok = TrainConfig {
            scenes: vec![SceneKind::Random, SceneKind::Clutter],
            exposure_jitter: 0.1,
            ..TrainConfig::default()
        };
        assert!(ok.validate().is_ok());
        for bad in [
            TrainConfig {
                scenes: vec![SceneKind::Random, SceneKind::Bin],
                ..TrainConfig::default()
            },
            TrainConfig {
                scenes: Vec::new(),
                ..TrainConfig::default()
            },
            TrainConfig {
                exposure_jitter: 0.6,
                ..TrainConfig::default()
            },
        ] {
            let error = bad.validate().map(|()| String::new()).unwrap_or_else(|e| e.to_string());
            assert!(
                error.contains("scenes") || error.contains("exposure_jitter"),
                "{error:?}"
            );
        }
        // The jitter changes the data (its key), a run without it keeps the old key.
        assert_ne!(
            ok.data_key(),
            TrainConfig {
                exposure_jitter: 0.0,
                ..ok.clone()
            }
            .data_key()
        );
    }

    #[test]
    fn inputs_that_agree_with_the_truth_are_not_hopeless() {
        let right = example(|_| 6.0, 6.0);
        assert!(winner_take_all_errors(&right).iter().all(|e| *e < 1e-6));
        assert!(!hopeless(&right));
        // Off by 5 px on 12 of 20 pixels (60 %): hopeless; on 4 of 20 (20 %): kept.
        let mostly_wrong = example(|p| if p < 12 { 11.0 } else { 6.0 }, 6.0);
        assert!(hopeless(&mostly_wrong));
        let partly_wrong = example(|p| if p < 4 { 11.0 } else { 6.0 }, 6.0);
        assert!(!hopeless(&partly_wrong));
        // Training redraws the hopeless crop unless told to keep it; a crop mostly without
        // ground truth is redrawn either way.
        let keep = TrainConfig {
            keep_hopeless: true,
            ..TrainConfig::default()
        };
        assert!(!acceptable(&TrainConfig::default(), &mostly_wrong));
        assert!(acceptable(&keep, &mostly_wrong));
        assert!(acceptable(&TrainConfig::default(), &partly_wrong));
        let mut unlabelled = right.clone();
        unlabelled.mask.iter_mut().take(10).for_each(|m| *m = false);
        assert!(!acceptable(&keep, &unlabelled));
        let (avg, bad1) = winner_take_all_reference(&[partly_wrong]);
        assert!((avg - 1.0).abs() < 1e-6 && (bad1 - 20.0).abs() < 1e-6, "{avg} {bad1}");
    }

    #[test]
    fn the_locking_fit_reads_the_truth_through_the_inputs() {
        // Costs 20·|d − t|^p around each pixel's truth t ∈ [2, 9]. With p = 1 (a V) the
        // equiangular fit reads t exactly: the curve is the identity. With p = 2 (a parabola)
        // the lines read it locked towards the integer: the curve undoes that.
        let (w, h, nd) = (40, 30, 12);
        let truth: Vec<f32> = (0..w * h).map(|p| 2.0 + 7.0 * p as f32 / (w * h) as f32).collect();
        let sample = |power: i32| {
            let volume = CostVolume::<u8> {
                width: w,
                height: h,
                min_disparity: 0,
                num_disparities: nd,
                data: truth
                    .iter()
                    .flat_map(|t| (0..nd).map(move |d| (20.0 * (d as f32 - t).abs().powi(power)).min(255.0) as u8))
                    .collect(),
                max_cost: 255,
                source: VolumeSource::Fused(fuse::fusion::Fusion::Mean),
            };
            Sample {
                volumes: vec![volume; 4],
                truth: truth.clone(),
            }
        };
        let v = fit_locking(&[sample(1)], 2).unwrap_or_else(|| panic!("no curve"));
        for (k, value) in fuse::wta::LOCKING_KNOTS.iter().zip(v.0) {
            assert!((value - k).abs() < 0.03, "V: knot {k}: {value}");
        }
        let parabola = fit_locking(&[sample(2)], 2).unwrap_or_else(|| panic!("no curve"));
        // A parabola's minimum t = d + 0.25 reads as (l − r) / (2 (max(l, r) − c)) =
        // ((1.25)² − (0.75)²) / (2 ((1.25)² − (0.25)²)) = 1/3 through the lines: the curve takes
        // about 1/3 back to 1/4.
        let corrected = parabola.apply(1.0 / 3.0);
        assert!((corrected - 0.25).abs() < 0.03, "{corrected}");
        // Too few pixels: none.
        assert_eq!(
            fit_locking(
                &[Sample {
                    truth: vec![0.0; w * h],
                    ..sample(1)
                }],
                2
            ),
            None
        );
    }

    #[test]
    fn calibration_needs_the_files_training_configuration() {
        let dir = std::env::temp_dir().join(format!("replay-calibrate-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&dir);
        let file = dir.join("bare.safetensors");
        let saved = weights::save(&Network::init(2, 1), &WeightsInfo::default(), &file);
        assert!(saved.is_ok(), "{saved:?}");
        let error = calibrate_locking(&file, &dir, &dir.join("out.safetensors"), &mut |_, _| {}).err();
        assert!(
            matches!(&error, Some(TrainError::Config { field: "train_config", value, .. }) if value.ends_with("bare.safetensors")),
            "{error:?}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_shifted_crop_keeps_its_minimum_on_its_target() {
        // Minima at 6 (first 10 pixels) and 2 (the rest); dropping 4 slices moves the first to
        // slice 2 and leaves the second below the range, no longer counted.
        let mut original = example(|p| if p < 10 { 6.0 } else { 2.0 }, 0.0);
        original.target = (0..20).map(|p| if p < 10 { 6.0 } else { 2.0 }).collect();
        let shifted = shifted(original.clone(), 4, 0);
        assert_eq!(shifted.inputs[0].shape, [1, 12, 4, 5]);
        assert_eq!(shifted.inputs[1].data, original.inputs[1].data[4 * 20..]);
        assert!(shifted.target[..10].iter().all(|t| (*t - 2.0).abs() < 1e-6));
        assert!(shifted.mask[..10].iter().all(|m| *m) && shifted.mask[10..].iter().all(|m| !*m));
        let errors = winner_take_all_errors(&shifted);
        assert!(errors.iter().all(|e| *e < 1e-6), "{errors:?}");
        assert_eq!(super::shifted(original.clone(), 0, 0), original);
        // The first 10 pixels' truth lands on slice 2 after the shift: just above 2 slices of
        // context, still asked for; inside 3, no longer.
        let context2 = super::shifted(original.clone(), 4, 2);
        assert_eq!(context2.mask, shifted.mask);
        let context3 = super::shifted(original.clone(), 4, 3);
        assert!(context3.mask.iter().all(|m| !*m));
        assert_eq!(context3.target, shifted.target);
    }
}
