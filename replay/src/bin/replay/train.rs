//! `replay train`: train MFuseNet on synthetic captures (see `replay::train`).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use anyhow::{Context, Result};
use clap::Args;
use fuse::mfusenet::input::InputSpec;
use record::cli::{Outcome, UsageError, progress_bar};
use record::scene::SceneKind;
use replay::train::{BaselineDraw, TrainConfig, TrainPaths, calibrate_locking, train, variant_name};
use tracing::info;

/// Arguments of `replay train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Network variant: cost volumes per set (1 = mfusenet-stereo, 2 = three-view, 4 = five-view).
    #[arg(long, default_value = "2", value_parser = ["1", "2", "4"])]
    views: String,
    /// Run folder: dataset cache, checkpoint, curves.csv, curves.rrd, training.json
    /// (default: train/<variant>; a run in it resumes).
    #[arg(long)]
    dir: Option<PathBuf>,
    /// Cache of the simulated captures' input volumes, shared by runs (default: train/dataset).
    #[arg(long, default_value = "train/dataset")]
    dataset_dir: PathBuf,
    /// Where the trained weights go (default: <dir>/<variant>.safetensors).
    #[arg(long)]
    weights_out: Option<PathBuf>,
    /// Optimiser steps.
    #[arg(long, default_value_t = TrainConfig::default().steps)]
    steps: u64,
    /// Side of the square training crops (px, a multiple of 4).
    #[arg(long, default_value_t = TrainConfig::default().crop)]
    crop: usize,
    /// Disparities of the training volumes (a multiple of 4).
    #[arg(long, default_value_t = TrainConfig::default().disparities)]
    disparities: usize,
    /// Adam's learning rate (÷4 for the last quarter).
    #[arg(long, default_value_t = TrainConfig::default().learning_rate)]
    learning_rate: f32,
    /// Seed of the scenes, the initial weights and the crops.
    #[arg(long, default_value_t = TrainConfig::default().seed)]
    seed: u64,
    /// Simulated training captures.
    #[arg(long, default_value_t = TrainConfig::default().train_sets)]
    train_sets: usize,
    /// Simulated validation captures (other seeds).
    #[arg(long, default_value_t = TrainConfig::default().val_sets)]
    val_sets: usize,
    /// Capture resolution, WxH.
    #[arg(long, default_value = "448x336")]
    resolution: String,
    /// Baselines drawn from LOW,HIGH (mm), see --baseline-draw.
    #[arg(long, default_value = "3,30")]
    baseline_mm: String,
    /// How baselines are drawn from --baseline-mm.
    #[arg(long, value_enum, default_value_t = BaselineDraw::LogUniform)]
    baseline_draw: BaselineDraw,
    /// Start from these weights (the variant's safetensors, e.g. fuse/weights/mfusenet-3view.safetensors)
    /// instead of a random initialisation: fine-tuning.
    #[arg(long, value_name = "FILE")]
    init_weights: Option<PathBuf>,
    /// Disparity-shift augmentation: drop the first 0, 4, …, N slices of each crop's volumes
    /// (targets shifted alike), so that answers near the range's start are as common as
    /// elsewhere; a multiple of 4, 0 = off. The weights then ask inference for 4 disparities of
    /// context below the searched range (metadata `context_below`; N with --context-below N).
    #[arg(long, value_name = "N", default_value_t = 0)]
    disparity_shift: usize,
    /// Block radius of the inputs' aggregation before SGM (the inputs' `block_radius`; the
    /// weights' metadata `input_spec` records it and inference reads it from there).
    #[arg(long, value_name = "R", default_value_t = TrainConfig::default().input.block_radius)]
    input_block_radius: usize,
    /// Re-estimate the BatchNorm statistics on 32 fixed crops at the start and every N steps
    /// (0 = once at a random initialisation, then frozen), so that activations stay normalised
    /// while the weights move. Each recalibration changes the function being trained: every
    /// 100 steps it slowed learning from scratch (README, MFuseNet, Training (6)).
    #[arg(long, value_name = "N", default_value_t = 0)]
    recalibrate_every: u64,
    /// Track the BatchNorm statistics: each step normalises with the running statistics (what
    /// inference computes) and then moves them by M towards its crop's, so that they follow
    /// the weights a little at a time and the activations stay normalised (0.005 ≈ the last
    /// 200 crops; 0.05 broke learning); 0 = frozen after the start, as the shipped files were
    /// trained (their activations grew tenfold per layer, yet they score better: README,
    /// MFuseNet, Training (6)).
    #[arg(long, value_name = "M", default_value_t = 0.0)]
    statistics_momentum: f32,
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
    context_below: usize,
    /// Mirror augmentation: each crop is flipped top to bottom and (three- and five-view) left to
    /// right with probability ½ each, its neighbours' volumes swapped as the mirrored rig would
    /// see them (left ↔ right, top ↔ bottom), so that the network answers a scene and its mirror
    /// image alike (the shipped three-view network does not: averaging it over the mirror at
    /// inference, `{"flips": true}`, took Middlebury AvgErr 0.363 → 0.352 px).
    #[arg(long)]
    flips: bool,
    /// Keep hopeless crops (inputs wrong by more than 3 px on more than 40 % of the labelled
    /// pixels: blank, periodic or mirror-like surfaces filling the crop) instead of drawing
    /// another, so that the network also learns what to answer where the costs cannot tell (the
    /// shipped three-view network's last stage: Middlebury Bad1 5.38 → 4.85 %, README, MFuseNet,
    /// Training (9))
    #[arg(long)]
    keep_hopeless: bool,
    /// Do not train: fit the pixel-locking curve of the refined readout for FILE, a weights
    /// file made by `replay train` before it wrote the curve itself, on the training captures
    /// its metadata names (cached in --dataset-dir), and write FILE again with the curve in its
    /// metadata (or write --weights-out; the tensors are unchanged). README, "Pixel locking".
    #[arg(long, value_name = "FILE")]
    calibrate: Option<PathBuf>,
    /// Scene families of the captures, used in turn (comma-separated; `bin` is held out of
    /// training: it is the check of how the networks do on a family they never saw).
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "random,random,toy,workpiece"
    )]
    scenes: Vec<SceneKind>,
    /// Exposure differences between the views: each view's gain drawn from 1 ± this (e.g. 0.1),
    /// as an auto-exposure camera gives; 0 = all alike.
    #[arg(long, value_name = "SPREAD", default_value_t = 0.0)]
    exposure_jitter: f64,
    /// Steps between validations.
    #[arg(long, default_value_t = TrainConfig::default().validate_every)]
    validate_every: u64,
    /// Steps between checkpoints.
    #[arg(long, default_value_t = TrainConfig::default().checkpoint_every)]
    checkpoint_every: u64,
}

impl TrainArgs {
    fn config(&self) -> Result<TrainConfig> {
        let usage = |m: String| -> anyhow::Error { UsageError(m).into() };
        let (w, h) = self
            .resolution
            .split_once('x')
            .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
            .ok_or_else(|| usage(format!("--resolution {}: expected WxH, e.g. 448x336", self.resolution)))?;
        let (lo, hi) = self
            .baseline_mm
            .split_once(',')
            .and_then(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)))
            .ok_or_else(|| {
                usage(format!(
                    "--baseline-mm {}: expected LOW,HIGH, e.g. 3,30",
                    self.baseline_mm
                ))
            })?;
        let config = TrainConfig {
            views: self.views.parse().unwrap_or(2),
            steps: self.steps,
            crop: self.crop,
            disparities: self.disparities,
            learning_rate: self.learning_rate,
            seed: self.seed,
            train_sets: self.train_sets,
            val_sets: self.val_sets,
            resolution: [w, h],
            baseline_mm: [lo, hi],
            baseline_draw: self.baseline_draw,
            checkpoint_every: self.checkpoint_every.max(1),
            validate_every: self.validate_every.max(1),
            init_weights: self.init_weights.clone(),
            disparity_shift: self.disparity_shift,
            recalibrate_every: self.recalibrate_every,
            statistics_momentum: self.statistics_momentum,
            context_below: self.context_below,
            flips: self.flips,
            keep_hopeless: self.keep_hopeless,
            scenes: self.scenes.clone(),
            exposure_jitter: self.exposure_jitter,
            input: InputSpec {
                block_radius: self.input_block_radius,
                ..InputSpec::default()
            },
            ..TrainConfig::default()
        };
        config.validate().map_err(|e| usage(e.to_string()))?;
        Ok(config)
    }
}

/// Runs `replay train`.
pub fn run(args: &TrainArgs, quiet: bool) -> Result<Outcome> {
    if let Some(file) = &args.calibrate {
        let out = args.weights_out.clone().unwrap_or_else(|| file.clone());
        let bar = progress_bar(0, quiet, "captures");
        bar.set_message("the training captures' cost volumes (cached)");
        let fitted = calibrate_locking(file, &args.dataset_dir, &out, &mut |done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        })
        .with_context(|| format!("fitting the locking curve of {}", file.display()))?;
        bar.finish_and_clear();
        info!(
            "locking curve {:?} → {}; on the {} training pixels it was fitted on, the fit's offsets were {:.4} px off the truth's on average, {:.4} px with the curve (half of it, inference's default: {:.4} px)",
            fitted.curve.0,
            out.display(),
            fitted.pixels,
            fitted.error_before_px,
            fitted.error_after_px,
            fitted.error_half_px,
        );
        return Ok(Outcome::Complete);
    }
    let config = args.config()?;
    let variant = variant_name(config.views);
    let dir = args.dir.clone().unwrap_or_else(|| PathBuf::from("train").join(variant));
    let weights_out = args
        .weights_out
        .clone()
        .unwrap_or_else(|| dir.join(format!("{variant}.safetensors")));
    let stop = Arc::new(AtomicBool::new(false));
    let presses = AtomicU32::new(0);
    let flag = Arc::clone(&stop);
    let _ = ctrlc::set_handler(move || {
        if presses.fetch_add(1, Ordering::SeqCst) == 0 {
            flag.store(true, Ordering::SeqCst);
            eprintln!(
                "\ninterrupt: saving a checkpoint and the weights so far (Ctrl-C again to abort; rerun to resume)"
            );
        } else {
            std::process::exit(130);
        }
    });
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    info!(
        "training {variant} ({} steps, {}×{} crops, {} disparities) in {}",
        config.steps,
        config.crop,
        config.crop,
        config.disparities,
        dir.display()
    );
    let dataset_bar = progress_bar((config.train_sets + config.val_sets) as u64, quiet, "captures");
    dataset_bar.set_message("simulating captures and their cost volumes (cached)");
    let step_bar = progress_bar(config.steps, quiet, "steps");
    let summary = train(
        &config,
        &TrainPaths {
            dir: &dir,
            dataset: &args.dataset_dir,
            weights: &weights_out,
        },
        &command,
        &stop,
        &mut |done, _| {
            dataset_bar.set_position(done as u64);
        },
        &mut |report| {
            if report.step == 1 || step_bar.position() == 0 {
                dataset_bar.finish_and_clear();
            }
            step_bar.set_position(report.step);
            let validation = report.validation.map_or_else(String::new, |(avg, bad1)| {
                format!(" · val AvgErr {avg:.3} px Bad1 {bad1:.1} %")
            });
            step_bar.set_message(format!(
                "loss {:.3} (mean {:.3}) · {:.2} s/step{validation}",
                report.loss, report.mean_loss, report.seconds_per_step
            ));
        },
    )
    .with_context(|| format!("training in {}", dir.display()))?;
    step_bar.finish_and_clear();
    info!(
        "{} steps in {:.0} s (dataset {:.0} s): validation AvgErr {} px, Bad1 {} % → {} (curves: {}, {})",
        summary.steps_done,
        summary.train_seconds,
        summary.dataset_seconds,
        summary.val_avg_err_px.map_or("–".into(), |v| format!("{v:.3}")),
        summary.val_bad1_percent.map_or("–".into(), |v| format!("{v:.2}")),
        summary.weights.display(),
        dir.join("curves.csv").display(),
        dir.join("curves.rrd").display()
    );
    Ok(if summary.interrupted {
        Outcome::Incomplete
    } else {
        Outcome::Complete
    })
}
