//! The options of `replay train`.

use std::path::PathBuf;

use clap::Args;
use record::scene::SceneKind;
use replay::train::{BaselineDraw, TrainConfig};

/// Arguments of `replay train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Network variant: cost volumes per set (1 = mfusenet-stereo, 2 = three-view, 4 = five-view),
    /// or `any`: the view-count-agnostic network (the views' features pooled by mean and maximum),
    /// each crop a random subset of the captures' neighbours (one to four of a five-view
    /// capture's; one to six of the twelve with `--rig grid-cross`); with `--init-weights` it
    /// starts from any fixed network or a pooled file.
    #[arg(long, default_value = "2", value_parser = ["1", "2", "4", "any"])]
    pub(crate) views: String,
    /// The layers' kernel sizes: `paper` (the paper's 7³ and 5³ kernels) or `lite` (3³ and 5³
    /// where the paper's cost the most: about a fifth of the work per voxel, same channels and
    /// tensor names); a lite file records it in its metadata and `mfusenet` runs it as it is.
    #[arg(long, default_value = "paper", value_parser = ["paper", "lite"])]
    pub(crate) architecture: String,
    /// Run folder: checkpoint, curves.csv, curves.rrd, training.json (default:
    /// train/<variant>). The run whose checkpoint it holds resumes (any --steps,
    /// --average-decay, --checkpoint-every, --validate-every); other options are another run,
    /// refused with the options that differ, its checkpoint left as it was.
    #[arg(long)]
    pub(crate) dir: Option<PathBuf>,
    /// Cache of the simulated captures' input volumes, shared by runs (default: train/dataset).
    #[arg(long, default_value = "train/dataset")]
    pub(crate) dataset_dir: PathBuf,
    /// Where the trained weights go (default: <dir>/<variant>.safetensors).
    #[arg(long)]
    pub(crate) weights_out: Option<PathBuf>,
    /// Optimiser steps.
    #[arg(long, default_value_t = TrainConfig::default().steps)]
    pub(crate) steps: u64,
    /// Side of the square training crops (px, a multiple of 4).
    #[arg(long = "crop-px", alias = "crop", value_name = "PX", default_value_t = TrainConfig::default().crop_px)]
    pub(crate) crop_px: usize,
    /// A multi-scale schedule: crops of PX from step STEP (0-based) on, e.g. `--crop-px 128
    /// --crop-px-from 15000:256` (repeat for more stages, in order). A large crop holds wider
    /// occlusions and depth jumps, and less of it lies within the network's reach of its
    /// zero-padded border, for about (PX / --crop-px)² the time a step. Validation keeps
    /// --crop-px. May be added or changed when a run resumes, like --steps.
    #[arg(long = "crop-px-from", value_name = "STEP:PX")]
    pub(crate) crop_px_from: Vec<String>,
    /// Train a sharp network: each view's per-pixel costs (Birchfield–Tomasi on colour, no
    /// block sums, no SGM: what still shows 1–6 px parts and the gaps between them) beside its
    /// input volume, straight into `concat`. The start (--init-weights or a random one) is
    /// widened with zero weights for them; the dataset keeps them (its own cache key); the
    /// weights record how they are made (metadata `sharp_spec`) and `mfusenet` makes them.
    /// Fixed networks only (--views 1, 2 or 4).
    #[arg(long)]
    pub(crate) sharp: bool,
    /// Disparities of the training volumes (a multiple of 4).
    #[arg(long, alias = "disparities", value_name = "N", default_value_t = TrainConfig::default().num_disparities)]
    pub(crate) num_disparities: usize,
    /// Adam's learning rate (÷4 for the last quarter).
    #[arg(long, default_value_t = TrainConfig::default().learning_rate)]
    pub(crate) learning_rate: f32,
    /// Seed of the scenes, the initial weights and the crops.
    #[arg(long, default_value_t = TrainConfig::default().seed)]
    pub(crate) seed: u64,
    /// Simulated training captures.
    #[arg(long, default_value_t = TrainConfig::default().train_sets)]
    pub(crate) train_sets: usize,
    /// Simulated validation captures (other seeds).
    #[arg(long, default_value_t = TrainConfig::default().val_sets)]
    pub(crate) val_sets: usize,
    /// Capture resolution, WxH.
    #[arg(long, default_value = "448x336")]
    pub(crate) resolution: String,
    /// Baselines drawn from LOW,HIGH (mm), see --baseline-draw.
    #[arg(long, default_value = "3,30")]
    pub(crate) baseline_mm: String,
    /// How baselines are drawn from --baseline-mm.
    #[arg(long, value_enum, default_value_t = BaselineDraw::LogUniform)]
    pub(crate) baseline_draw: BaselineDraw,
    /// Start from these weights (the variant's safetensors, e.g. fuse/weights/mfusenet-3view.safetensors)
    /// instead of a random initialisation: fine-tuning.
    #[arg(long, value_name = "FILE")]
    pub(crate) init_weights: Option<PathBuf>,
    /// Disparity-shift augmentation: drop the first 0, 4, …, N slices of each crop's volumes
    /// (targets shifted alike), so that answers near the range's start are as common as
    /// elsewhere; a multiple of 4, 0 = off. The weights then ask inference for 4 disparities of
    /// context below the searched range (metadata `context_below`; N with --context-below N).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub(crate) disparity_shift: usize,
    /// Block radius of the inputs' aggregation before SGM (the inputs' `block_radius_px`; the
    /// weights' metadata `input_spec` records it and inference reads it from there).
    #[arg(long, alias = "input-block-radius", value_name = "PX", default_value_t = TrainConfig::default().input.block_radius_px)]
    pub(crate) input_block_radius_px: usize,
    /// Re-estimate the BatchNorm statistics on 32 fixed crops at the start and every N steps
    /// (0 = once at a random initialisation, then frozen), so that activations stay normalised
    /// while the weights move. Each recalibration changes the function being trained: every
    /// 100 steps it slowed learning from scratch (README, MFuseNet, Training (6)).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub(crate) recalibrate_every: u64,
    /// Track the BatchNorm statistics: each step normalises with the running statistics (what
    /// inference computes) and then moves them by M towards its crop's, so that they follow
    /// the weights a little at a time and the activations stay normalised (0.005 ≈ the last
    /// 200 crops; 0.05 broke learning); 0 = frozen after the start, as the shipped files were
    /// trained (their activations grew tenfold per layer, yet they score better: README,
    /// MFuseNet, Training (6)).
    #[arg(long, value_name = "M", default_value_t = 0.0)]
    pub(crate) statistics_momentum: f32,
    /// Keep a moving average of the weights (decay D per step: 0.999 ≈ the last thousand
    /// steps) in the checkpoint, and validate and export it instead of the last step's weights,
    /// which batch-1 steps make swing from checkpoint to checkpoint. Recommended for runs of
    /// thousands of steps; a run resumes with it switched on or off (the average starts on the
    /// resumed weights). 0 = off.
    #[arg(long, value_name = "D", default_value_t = 0.0)]
    pub(crate) average_decay: f32,
    /// Train with N disparities of context below the range, as inference gives it (costs under
    /// 0 from each neighbour mirrored; the dataset is made anew): the network learns those
    /// slices are never the answer, at the image borders too, where a neighbour's only finite
    /// costs are under 0 (the three-view network's stage-3 file, trained with --disparity-shift
    /// instead and run with 4 slices of context, failed there: README, More views of a line).
    /// A multiple of 4 up to 16. With --disparity-shift the crop's first N slices after the
    /// shift are its context (real costs below the crop's range where the shift reaches past
    /// them, as inside a wider range at inference, mirrored ones where it does not), and pixels
    /// whose truth falls there are not asked for.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub(crate) context_below: usize,
    /// Mirror augmentation: each crop is flipped top to bottom and (three- and five-view) left to
    /// right with probability ½ each, its neighbours' volumes swapped as the mirrored rig would
    /// see them (left ↔ right, top ↔ bottom), so that the network answers a scene and its mirror
    /// image alike (the shipped three-view network does not: averaging it over the mirror at
    /// inference, `{"flips": true}`, took Middlebury AvgErr 0.363 → 0.352 px).
    #[arg(long)]
    pub(crate) flips: bool,
    /// Keep hopeless crops (inputs wrong by more than 3 px on more than 40 % of the labelled
    /// pixels: blank, periodic or mirror-like surfaces filling the crop) instead of drawing
    /// another, so that the network also learns what to answer where the costs cannot tell (the
    /// shipped three-view network's last stage: Middlebury Bad1 5.38 → 4.85 %, README, MFuseNet,
    /// Training (9))
    #[arg(long)]
    pub(crate) keep_hopeless: bool,
    /// Training at scale: every N steps one of the --train-sets captures in memory is replaced
    /// by a new one (in turn, made when it is needed and deleted from the cache when it is
    /// replaced), so that a long run sees step / N more scenes than it holds instead of
    /// learning its few captures by heart. Which captures a step sees depends only on the step:
    /// a resumed run sees the same ones. 0 = the same captures throughout (default)
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub(crate) renew_every: usize,
    /// Do not train: fit the pixel-locking curve of the refined readout for FILE, a weights
    /// file made by `replay train` before it wrote the curve itself, on the training captures
    /// its metadata names (cached in --dataset-dir), and write FILE again with the curve in its
    /// metadata (or write --weights-out; the tensors are unchanged). docs/methods.md, "Pixel locking".
    #[arg(long, value_name = "FILE")]
    pub(crate) calibrate: Option<PathBuf>,
    /// Scene families of the captures, used in turn (comma-separated; `bin`, `thin` and `slanted` are held
    /// out of training: they check how the networks do on families they never saw).
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "random,random,toy,workpiece"
    )]
    pub(crate) scenes: Vec<SceneKind>,
    /// Exposure differences between the views: each view's gain drawn from 1 ± this (e.g. 0.1),
    /// as an auto-exposure camera gives; 0 = all alike.
    #[arg(long, value_name = "SPREAD", default_value_t = 0.0)]
    pub(crate) exposure_jitter: f64,
    /// Rig of the training captures: five-view, grid-cross (the 3×3 grid and the cross at two
    /// baselines, 13 views) from which `--views any` also draws far and diagonal neighbours, or
    /// line5 with `--views 4`: the five-view network on a line of five, the near pair in its
    /// left and right inputs and the far pair in its top and bottom ones, as `mfusenet`'s
    /// `line_cross` runs it (other rigs are refused).
    #[arg(long, value_enum, default_value = "five-view")]
    pub(crate) rig: record::rig::RigKind,
    /// Steps between validations.
    #[arg(long, default_value_t = TrainConfig::default().validate_every)]
    pub(crate) validate_every: u64,
    /// Steps between checkpoints.
    #[arg(long, default_value_t = TrainConfig::default().checkpoint_every)]
    pub(crate) checkpoint_every: u64,
}
