//! Training MFuseNet on synthetic captures made by `record` (never on the evaluation scenes):
//! a dataset of simulated five-view sets with ground truth, each reduced once to its four
//! per-neighbour input volumes (cached as safetensors in the run folder), then Adam on random
//! crops with the smooth-L1 loss, validation on sets of other seeds, checkpoints and resume.
//!
//! Everything is seeded: the scenes (`seed + i` for training, `seed + 1_000_000 + i` for
//! validation), the initial weights and every crop (drawn from the seed and the step, so a
//! resumed run draws what the uninterrupted one would have).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use fuse::mfusenet::network::BatchNormMode;
use fuse::mfusenet::train::{
    Adam, Average, Checkpoint, Example, clip_gradients, load_checkpoint, recalibrate_batch_norm, save_checkpoint,
};
use fuse::mfusenet::{Network, WeightsInfo, weights};
use serde::{Deserialize, Serialize};

use record::rng::SplitMix64;

mod calibration;
mod config;
mod curves;
mod dataset;
mod schedule;

pub use calibration::*;
pub use config::*;
use curves::*;
pub use dataset::*;
pub use schedule::*;

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
    /// The run folder holds the checkpoint of another run: nothing is trained, nothing is
    /// overwritten.
    #[error(
        "'{path}' is the checkpoint of another run (its configuration differs in: {fields}); resume it with its own options (training.json beside it has them), train in another --dir, or delete it to start over"
    )]
    OtherRun {
        /// The checkpoint.
        path: PathBuf,
        /// The fields that differ (`field: stored → given`), or why its configuration cannot be read.
        fields: String,
    },
    /// A value of the weights' metadata does not serialise.
    #[error("metadata {key} cannot be written: {reason}")]
    Metadata {
        /// The metadata key.
        key: &'static str,
        /// What serde said.
        reason: String,
    },
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
    /// The checkpoint's step this session started from (0: a new run).
    pub resumed_at_step: u64,
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

/// The fields in which the run configuration `stored` (a checkpoint's `train_config`) differs
/// from `config`, each `field: stored → given`, or why `stored` cannot be read; empty when it is
/// the same run. The step budget, the moving average and how often the run saves and validates
/// never count (none changes a step), so that a longer (or shorter) `--steps`, or an average
/// switched on, resumes the run.
fn run_differences(stored: Option<&str>, config: &TrainConfig) -> Vec<String> {
    let Some(stored) = stored else {
        return vec!["train_config (missing: not a checkpoint of `replay train`)".to_owned()];
    };
    let stored = match serde_json::from_str::<TrainConfig>(stored) {
        Ok(stored) => TrainConfig {
            steps: config.steps,
            crop_stages: config.crop_stages.clone(),
            average_decay: config.average_decay,
            checkpoint_every: config.checkpoint_every,
            validate_every: config.validate_every,
            ..stored
        },
        Err(e) => return vec![format!("train_config (unreadable: {e})")],
    };
    // Through text, so that an `f32` reads as written (0.001, not 0.0010000000474974513).
    let object = |c: &TrainConfig| match serde_json::to_string(c).and_then(|text| serde_json::from_str(&text)) {
        Ok(serde_json::Value::Object(map)) => map,
        _ => serde_json::Map::new(),
    };
    let (stored, given) = (object(&stored), object(config));
    let mut keys: Vec<&String> = stored.keys().chain(given.keys()).collect();
    keys.sort();
    keys.dedup();
    let shown = |v: Option<&serde_json::Value>| v.map_or_else(|| "(unset)".to_owned(), ToString::to_string);
    keys.into_iter()
        .filter(|k| stored.get(*k) != given.get(*k))
        .map(|k| format!("{k}: {} → {}", shown(stored.get(k)), shown(given.get(k))))
        .collect()
}

/// Refuses a run folder whose checkpoint belongs to another run (or cannot be read), before
/// anything is made or overwritten: training there would replace that run's checkpoint.
fn check_run_folder(files: &RunFiles, config: &TrainConfig) -> Result<(), TrainError> {
    let path = files.checkpoint();
    if !path.exists() {
        return Ok(());
    }
    let bytes = std::fs::read(&path).map_err(|e| file_error(&path, e.to_string()))?;
    let fields = match safetensors::SafeTensors::read_metadata(&bytes) {
        Ok((_, metadata)) => {
            let stored = metadata
                .metadata()
                .as_ref()
                .and_then(|m| m.get("train_config").cloned());
            run_differences(stored.as_deref(), config)
        }
        Err(e) => vec![format!("everything (not a safetensors file: {e})")],
    };
    if fields.is_empty() {
        return Ok(());
    }
    Err(TrainError::OtherRun {
        path,
        fields: fields.join(", "),
    })
}

/// The network a run validates and exports: the moving average when it keeps one (its
/// BatchNorm statistics re-estimated on `calibration` when the run moves them, else the live
/// network's frozen ones), else the live network.
fn exported(
    net: &Network,
    average: Option<&Average>,
    config: &TrainConfig,
    calibration: &[Example],
) -> Result<Network, TrainError> {
    let Some(average) = average else {
        return Ok(net.clone());
    };
    let mut averaged = average.network(net);
    if config.recalibrate_every > 0 || config.statistics_momentum > 0.0 {
        recalibrate_batch_norm(&mut averaged, calibration)?;
    }
    Ok(averaged)
}

/// A value as JSON for the weights' metadata (a failure is an error, never an empty entry).
pub(super) fn to_json<T: Serialize + ?Sized>(key: &'static str, value: &T) -> Result<String, TrainError> {
    serde_json::to_string(value).map_err(|e| TrainError::Metadata {
        key,
        reason: e.to_string(),
    })
}

pub(super) fn file_error(path: &Path, reason: String) -> TrainError {
    TrainError::File {
        path: path.to_path_buf(),
        reason,
    }
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
    /// The best-validated network so far (the exported network, with its metadata) across
    /// every leg of the run: a run that worsens later keeps its best.
    pub fn best(&self) -> PathBuf {
        self.dir.join("best.safetensors")
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

/// Spare buffers the training thread keeps ([`fuse::nn::conv::keep_spares`]).
const TRAINING_SPARES: usize = 8;

/// The thread's spare-buffer limit before training, restored when training ends, however it ends.
struct RestoreSpares(usize);

impl Drop for RestoreSpares {
    fn drop(&mut self) {
        fuse::nn::conv::keep_spares(self.0);
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
    // Each step's tensors, freed at its end, serve the next step's layers (a few MB each).
    let _restore = RestoreSpares(fuse::nn::conv::keep_spares(TRAINING_SPARES));
    let TrainPaths {
        dir,
        dataset: dataset_dir,
        weights: weights_out,
    } = *paths;
    let files = RunFiles { dir: dir.to_path_buf() };
    check_run_folder(&files, config)?;
    std::fs::create_dir_all(dir).map_err(|e| file_error(dir, e.to_string()))?;
    let dataset_started = Instant::now();
    let total = config.train_sets + config.val_sets;
    let mut train_samples = Vec::new();
    let mut val_samples = Vec::new();
    // Resume (the folder's checkpoint is this run's: `check_run_folder`) or start; read first,
    // as a renewing pool resumes with the captures its slots hold at the checkpoint's step.
    let resumed = if files.checkpoint().exists() {
        Some(load_checkpoint(&files.checkpoint(), config.views)?)
    } else {
        None
    };
    let start_step = match &resumed {
        Some(checkpoint) if config.renew_every > 0 => checkpoint.adam.step,
        _ => 0,
    };
    let mut pool: Vec<usize> = (0..config.train_sets)
        .map(|slot| config.pool_index(slot, start_step))
        .collect();
    if start_step > 0 {
        // The renewal at the checkpoint's step is taken here: what it replaced leaves the cache.
        for (slot, index) in pool.iter().enumerate() {
            let before = config.pool_index(slot, start_step - 1);
            if before != *index && before >= config.train_sets {
                let _ = std::fs::remove_file(dataset_dir.join(sample_file_name(config, before, false)));
            }
        }
    }
    for i in 0..total {
        let validation = i >= config.train_sets;
        let index = if validation {
            i - config.train_sets
        } else {
            pool.get(i).copied().unwrap_or(i)
        };
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
    let sharp = config.sharp.is_some();
    let val_examples = validation_examples(&val_samples, config.views, sharp, config.depth());
    let (wta_avg, wta_bad1) = winner_take_all_reference(&val_examples, sharp);
    let locking = fit_locking(&train_samples, config.views);
    tracing::info!(
        "validation crops: winner-take-all of the mean input volume gives AvgErr {wta_avg:.3} px, Bad1 {wta_bad1:.2} % (the network must do better)"
    );

    // BatchNorm statistics: batch statistics of a few dozen fixed crops at the start, then frozen
    // (see `BatchNorm::forward_frozen`; one crop per step is far too small a batch to normalise
    // with), recalibrated every `recalibrate_every` steps, or tracked (`statistics_momentum`).
    let mut calibration_rng = SplitMix64::new(config.seed ^ 0x5EED_CA1B);
    let calibration: Vec<Example> = (0..CALIBRATION_CROPS)
        .map(|_| random_crop(config, &train_samples, config.crop_px, &mut calibration_rng))
        .collect();
    let (mut net, mut adam, mut average, mut history, mut train_seconds, continued) = match resumed {
        Some(Checkpoint {
            net,
            adam,
            average,
            info,
        }) => {
            let history = read_curves(&files.curves_csv(), adam.step)?;
            let seconds = info.get("train_seconds").and_then(|s| s.parse().ok()).unwrap_or(0.0);
            // Steps another trainer took (`scripts/train-torch.py`: `torch_batch`, `torch_steps`, …)
            // stay on record in every later checkpoint and in the weights.
            let continued: Vec<(String, String)> = info
                .entries
                .iter()
                .filter(|(k, _)| k.starts_with("torch_"))
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect();
            (net, adam, average, history, seconds, continued)
        }
        None => {
            let mut net = match &config.init_weights {
                Some(path) => {
                    // The view-count-agnostic network starts from any fixed one.
                    let mut net = if config.views == 0 {
                        Network::pooled_from(&weights::load(path, None)?.0)
                    } else {
                        weights::load(path, Some(config.views))?.0
                    };
                    if net.architecture != config.architecture {
                        return Err(TrainError::Config {
                            field: "architecture",
                            value: config.architecture.name().to_owned(),
                            reason: if net.architecture == fuse::mfusenet::Architecture::Lite {
                                "the --init-weights file is a lite network (--architecture lite)"
                            } else {
                                "the --init-weights file is the paper's network (--architecture paper)"
                            },
                        });
                    }
                    if config.recalibrate_every > 0 {
                        recalibrate_batch_norm(&mut net, &calibration)?;
                    }
                    net
                }
                None => {
                    let mut net = Network::init_with(config.views, config.architecture, config.seed);
                    if config.sharp.is_some() {
                        net = net.sharpened().unwrap_or(net);
                    }
                    recalibrate_batch_norm(&mut net, &calibration)?;
                    net
                }
            };
            // A sharp run widens its start with zero weights for the sharp volumes: it begins
            // by computing what that network computes.
            if config.sharp.is_some() {
                net = net.sharpened().unwrap_or(net);
            }
            let adam = Adam::new(&mut net, config.learning_rate);
            (net, adam, None, Vec::new(), 0.0, Vec::new())
        }
    };
    // The average the run keeps: the checkpoint's (at this run's decay), or a new one on the
    // weights as they are; none when switched off.
    let mut average = match (config.average_decay > 0.0, average.take()) {
        (false, _) => None,
        (true, Some(kept)) => Some(Average {
            decay: config.average_decay,
            ..kept
        }),
        (true, None) => {
            if adam.step > 0 {
                tracing::info!(
                    "starting a moving average of the weights (decay {}) at step {}",
                    config.average_decay,
                    adam.step
                );
            }
            Some(Average::new(&mut net, config.average_decay))
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
    if session_start_step > 0 {
        tracing::info!("resuming at step {session_start_step} of {}", config.steps);
    }
    let mut recent: Vec<f32> = history.iter().rev().take(50).map(|r: &CurveRow| r.loss).collect();
    let mut last_validation = history
        .iter()
        .rev()
        .find_map(|r| r.val_avg_err_px.zip(r.val_bad1_percent));
    // The last validation with both estimates and its step, reused for the metadata.
    let mut last_estimates: Option<(u64, Validation)> = None;
    let config_json = to_json("train_config", config)?;
    let data_key = config.data_key();
    let info_for = |seconds: f64| {
        let mut info = WeightsInfo::default();
        info.set("train_config", config_json.clone());
        info.set("train_seconds", format!("{seconds:.1}"));
        // Where the samples are cached (`<train|val>-NNNN-<key>.safetensors`), for other trainers.
        info.set("dataset_key", format!("{data_key:016x}"));
        for (key, value) in &continued {
            info.set(key, value.clone());
        }
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
        if config.renew_every > 0 && step > 0 && step.is_multiple_of(config.renew_every as u64) {
            renew(config, step, &mut pool, &mut train_samples, dataset_dir)?;
        }
        let mut rng = SplitMix64::new(
            (config.seed ^ 0x9E37_79B9_7F4A_7C15).wrapping_add(step.wrapping_mul(0xD1B5_4A32_D192_ED03)),
        );
        let example = random_crop(config, &train_samples, config.crop_px_at(step), &mut rng);
        let (loss, _, mut gradients) =
            net.loss_and_gradients_with(&example.inputs, &example.target, &example.mask, batch_norm_mode)?;
        clip_gradients(&mut gradients, MAX_GRADIENT_NORM);
        adam.update(&mut net, &gradients);
        if let Some(average) = &mut average {
            average.update(&mut net);
        }
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
            val_bad1_percent: None,
        };
        if done % config.validate_every == 0 || done == config.steps {
            let candidate = exported(&net, average.as_ref(), config, &calibration)?;
            let estimates = validate_estimates(&candidate, &val_examples, locking)?;
            tracing::info!(
                "step {done}: validation{} AvgErr {:.3} px / Bad1 {:.2} % (refined {:.3} / {:.2}), logit range {:.1} (tens is healthy, thousands saturated)",
                if average.is_some() {
                    " of the moving average:"
                } else {
                    ""
                },
                estimates.soft_argmin.0,
                estimates.soft_argmin.1,
                estimates.refined.0,
                estimates.refined.1,
                estimates.logit_range
            );
            last_estimates = Some((done, estimates));
            let (avg, bad1) = estimates.soft_argmin;
            // Best so far across every leg (the curves keep earlier legs' validations; a leg
            // that resumes a run made before this file existed saves only what beats them).
            let best_before = history
                .iter()
                .filter_map(|r| r.val_avg_err_px)
                .fold(f64::INFINITY, f64::min);
            if avg < best_before {
                let info = export_info(
                    info_for(train_seconds + started.elapsed().as_secs_f64()),
                    config,
                    done,
                    average.as_ref(),
                    &estimates,
                    locking,
                    command,
                )?;
                weights::save(&candidate, &info, &files.best())?;
                tracing::info!(
                    "step {done}: the best validation so far, saved as {}",
                    files.best().display()
                );
            }
            row.val_avg_err_px = Some(avg);
            row.val_bad1_percent = Some(bad1);
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
            save_checkpoint(
                &mut net,
                &adam,
                average.as_ref(),
                &info_for(seconds),
                &files.checkpoint(),
            )?;
            write_curves(&files, &history)?;
        }
    }
    train_seconds += started.elapsed().as_secs_f64();
    save_checkpoint(
        &mut net,
        &adam,
        average.as_ref(),
        &info_for(train_seconds),
        &files.checkpoint(),
    )?;
    write_curves(&files, &history)?;
    let net = exported(&net, average.as_ref(), config, &calibration)?;
    // The final network's validation (the last step's when it validated; else made now, e.g.
    // after an interruption or for a run another trainer finished), and from it how inference
    // should read this network: whichever estimate validates better.
    let estimates = match last_estimates {
        Some((step, estimates)) if step == adam.step => estimates,
        _ => validate_estimates(&net, &val_examples, locking)?,
    };
    let last_validation = Some(estimates.soft_argmin);
    let info = export_info(
        info_for(train_seconds),
        config,
        adam.step,
        average.as_ref(),
        &estimates,
        locking,
        command,
    )?;
    weights::save(&net, &info, weights_out)?;
    let summary = TrainSummary {
        config: config.clone(),
        steps_done: adam.step,
        resumed_at_step: session_start_step,
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

/// A renewing pool's renewal at `step` (a multiple of `renew_every`): the slot whose turn it is
/// gets the capture [`TrainConfig::pool_index`] names for it now (made, or read from the cache),
/// and the capture it held leaves the cache when it was itself a renewed one (the first
/// `train_sets` stay: a later run starts from them).
fn renew(
    config: &TrainConfig,
    step: u64,
    pool: &mut [usize],
    samples: &mut [Sample],
    dataset_dir: &Path,
) -> Result<(), TrainError> {
    let renewal = (step / config.renew_every as u64) as usize;
    let slot = (renewal - 1) % config.train_sets.max(1);
    let index = config.pool_index(slot, step);
    let (Some(held), Some(kept)) = (pool.get_mut(slot), samples.get_mut(slot)) else {
        return Ok(());
    };
    if *held == index {
        return Ok(());
    }
    let started = Instant::now();
    *kept = sample(config, index, false, dataset_dir)?;
    let retired = std::mem::replace(held, index);
    if retired >= config.train_sets {
        let path = dataset_dir.join(sample_file_name(config, retired, false));
        // A missing file is fine (another run sharing the cache removed it).
        let _ = std::fs::remove_file(path);
    }
    tracing::debug!(
        "step {step}: training capture {index} replaces {retired} in slot {slot} ({:.1} s)",
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The metadata of a network a run exports after `steps` steps (the final file and the
/// best-validated one): `info` (the run's own entries) with the variant, its inputs, how it
/// was made and validated (`estimates`), and how inference should read it.
fn export_info(
    info: WeightsInfo,
    config: &TrainConfig,
    steps: u64,
    average: Option<&Average>,
    estimates: &Validation,
    locking: Option<fuse::wta::LockingCurve>,
    command: &str,
) -> Result<WeightsInfo, TrainError> {
    let mut info = info;
    info.set("format", "mfusenet-weights/1");
    info.set("variant", variant_name(config.views, config.architecture));
    info.set(
        "views",
        if config.views == 0 {
            "any".to_owned()
        } else {
            config.views.to_string()
        },
    );
    info.set(
        "input_order",
        match config.views {
            0 if config.rig == record::rig::RigKind::GridCross => {
                "any subset of the neighbours within two baselines (axes and diagonals), in any order"
            }
            0 => "any subset of left,right,top,bottom, in any order",
            1 => "right",
            2 => "left,right",
            _ if config.rig == record::rig::RigKind::Line5 => "left,right,left2,right2",
            _ => "left,right,top,bottom",
        },
    );
    info.set("disparities_trained", config.num_disparities.to_string());
    info.set(
        "input_normalisation",
        "per neighbour: census 7x7 block-summed, SGM 8 paths; (S - min_d S) / (8 P2), steps of 1/128, max 255 steps; tensor = byte / 128",
    );
    info.set("input_spec", to_json("input_spec", &config.input)?);
    if let Some(sharp) = &config.sharp {
        info.set("sharp_spec", to_json("sharp_spec", sharp)?);
    }
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
    info.set("steps", steps.to_string());
    if let Some(average) = average {
        // The exported weights are the average of the last ≈ 1 / (1 − decay) steps' weights.
        info.set("average_decay", average.decay.to_string());
        info.set("average_updates", average.updates.to_string());
    }
    let (avg, bad1) = estimates.soft_argmin;
    info.set("val_avg_err_px", format!("{avg:.4}"));
    info.set("val_bad1_percent", format!("{bad1:.3}"));
    let (avg, bad1) = estimates.refined;
    info.set("val_refined_avg_err_px", format!("{avg:.4}"));
    info.set("val_refined_bad1_percent", format!("{bad1:.3}"));
    info.set("val_logit_range", format!("{:.1}", estimates.logit_range));
    if let Some(curve) = locking {
        info.set("locking_curve", to_json("locking_curve", &curve)?);
    }
    info.set(
        "estimate",
        if estimates.refine_is_better() {
            "refine"
        } else {
            "soft-argmin"
        },
    );
    Ok(info)
}

/// The registry name of a variant: `mfusenet-stereo`, `mfusenet-3view`, `mfusenet-5view` or
/// `mfusenet-any`, with `-lite` for the lite architecture.
pub fn variant_name(views: usize, architecture: fuse::mfusenet::Architecture) -> String {
    let name = match views {
        0 => "mfusenet-any",
        1 => "mfusenet-stereo",
        2 => "mfusenet-3view",
        _ => "mfusenet-5view",
    };
    match architecture {
        fuse::mfusenet::Architecture::Paper => name.to_owned(),
        other => format!("{name}-{}", other.name()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fuse::nn::Tensor;
    use fuse::volume::{CostVolume, VolumeSource};
    use record::scene::SceneKind;

    /// A renewing pool's captures at every step, in closed form, are the ones the renewals
    /// made one by one give (slot `(r − 1) mod sets` takes the next capture after the last
    /// one any slot took), so a run that resumes at any step holds what it held there; without
    /// renewal every slot keeps its capture; renewed captures draw seeds of their own.
    #[test]
    fn a_renewing_pool_holds_at_each_step_what_its_renewals_gave_it() {
        for (sets, every) in [(1, 1), (3, 2), (4, 5), (48, 25)] {
            let config = TrainConfig {
                train_sets: sets,
                renew_every: every,
                ..TrainConfig::default()
            };
            let mut pool: Vec<usize> = (0..sets).collect();
            let mut next = sets;
            for step in 0..400u64 {
                if step > 0 && step.is_multiple_of(every as u64) {
                    let renewal = (step / every as u64) as usize;
                    pool[(renewal - 1) % sets] = next;
                    next += 1;
                }
                let closed: Vec<usize> = (0..sets).map(|slot| config.pool_index(slot, step)).collect();
                assert_eq!(closed, pool, "{sets} sets, every {every}, step {step}");
            }
        }
        let fixed = TrainConfig::default();
        assert_eq!(fixed.pool_index(1, 1_000), 1);
        let renewing = TrainConfig {
            renew_every: 10,
            ..TrainConfig::default()
        };
        let seeds: Vec<u64> = (0..3 * renewing.train_sets)
            .map(|index| renewing.capture_config(index, false, 0).seed)
            .collect();
        let validation = renewing.capture_config(0, true, 0).seed;
        assert!(seeds[..renewing.train_sets].iter().all(|s| *s < 1_000_000));
        assert!(seeds[renewing.train_sets..].iter().all(|s| *s > 2_000_000));
        assert!(!seeds.contains(&validation));
    }

    /// The rig is part of the dataset's key only when it is not the five-view one, so the caches
    /// and checkpoints of five-view runs made before the option stay theirs; only the rigs
    /// whose neighbours the dataset keeps are accepted.
    #[test]
    fn the_rig_keys_the_dataset_only_when_it_is_not_five_view() {
        let five = TrainConfig::default();
        let json = serde_json::to_value(&five).unwrap_or_default();
        assert!(json.get("rig").is_none(), "{json}");
        let read: TrainConfig = serde_json::from_value(json).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(read.rig, record::rig::RigKind::FiveView);
        assert_eq!(read.data_key(), five.data_key());
        let grid = TrainConfig {
            rig: record::rig::RigKind::GridCross,
            ..TrainConfig::default()
        };
        assert_ne!(grid.data_key(), five.data_key());
        assert!(grid.validate().is_ok());
        // A line of five trains the five-view network only; rigs whose views the dataset does
        // not keep are refused.
        let line = TrainConfig {
            rig: record::rig::RigKind::Line5,
            views: 4,
            ..TrainConfig::default()
        };
        assert!(line.validate().is_ok(), "{:?}", line.validate());
        assert_ne!(line.data_key(), five.data_key());
        for (rig, views) in [(record::rig::RigKind::Line5, 2), (record::rig::RigKind::Grid3x3, 4)] {
            let refused = TrainConfig {
                rig,
                views,
                ..TrainConfig::default()
            };
            assert!(
                matches!(refused.validate(), Err(TrainError::Config { field: "rig", .. })),
                "{rig:?} with {views} views: {:?}",
                refused.validate()
            );
        }
    }

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
        assert!(winner_take_all_errors(&right, false).iter().all(|e| *e < 1e-6));
        assert!(!hopeless(&right, false));
        // Off by 5 px on 12 of 20 pixels (60 %): hopeless; on 4 of 20 (20 %): kept.
        let mostly_wrong = example(|p| if p < 12 { 11.0 } else { 6.0 }, 6.0);
        assert!(hopeless(&mostly_wrong, false));
        let partly_wrong = example(|p| if p < 4 { 11.0 } else { 6.0 }, 6.0);
        assert!(!hopeless(&partly_wrong, false));
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
        let (avg, bad1) = winner_take_all_reference(&[partly_wrong], false);
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
                sharp: Vec::new(),
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
    fn a_folder_holding_another_runs_checkpoint_is_refused_and_left_as_it_was() {
        let config = TrainConfig::default();
        let json = |c: &TrainConfig| serde_json::to_string(c).unwrap_or_else(|e| panic!("{e}"));
        // Another budget or average is the same run; another learning rate is not.
        let longer = TrainConfig {
            steps: 10,
            average_decay: 0.9,
            checkpoint_every: 7,
            crop_stages: vec![CropStage {
                from_step: 5,
                crop_px: 128,
            }],
            ..config.clone()
        };
        assert!(run_differences(Some(&json(&longer)), &config).is_empty());
        let other = TrainConfig {
            learning_rate: 1e-3,
            flips: true,
            ..longer
        };
        assert_eq!(
            run_differences(Some(&json(&other)), &config),
            ["flips: true → (unset)", "learning_rate: 0.001 → 0.0005"]
        );
        assert_eq!(run_differences(None, &config).len(), 1);
        assert!(run_differences(Some("{"), &config)[0].starts_with("train_config (unreadable"));

        let dir = std::env::temp_dir().join(format!("replay-other-run-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&dir);
        let files = RunFiles { dir: dir.clone() };
        assert!(
            check_run_folder(&files, &config).is_ok(),
            "an empty folder starts a run"
        );
        let mut net = Network::init(2, 1);
        let adam = Adam::new(&mut net, 1e-3);
        let mut info = WeightsInfo::default();
        info.set("train_config", json(&other));
        let saved = save_checkpoint(&mut net, &adam, None, &info, &files.checkpoint());
        assert!(saved.is_ok(), "{saved:?}");
        let before = std::fs::read(files.checkpoint()).unwrap_or_default();
        let error = check_run_folder(&files, &config).err();
        assert!(
            matches!(&error, Some(TrainError::OtherRun { fields, .. }) if fields.contains("learning_rate")),
            "{error:?}"
        );
        assert!(check_run_folder(&files, &other).is_ok(), "its own run resumes");
        assert_eq!(std::fs::read(files.checkpoint()).unwrap_or_default(), before);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn crops_follow_their_stages_and_bad_stages_are_refused() {
        let stage = |from_step, crop_px| CropStage { from_step, crop_px };
        let config = TrainConfig {
            crop_px: 32,
            crop_stages: vec![stage(10, 64), stage(20, 16)],
            ..TrainConfig::default()
        };
        assert!(config.validate().is_ok(), "{:?}", config.validate());
        let sides: Vec<usize> = [0, 9, 10, 19, 20, 1000].map(|s| config.crop_px_at(s)).to_vec();
        assert_eq!(sides, [32, 32, 64, 64, 16, 16]);
        assert_eq!(TrainConfig::default().crop_px_at(5), TrainConfig::default().crop_px);
        // The stage's side is what a step draws: a sample of 80 × 72 px, 8 slices.
        let (w, h, nd) = (80, 72, 8);
        let volume = CostVolume {
            width: w,
            height: h,
            min_disparity: 0,
            num_disparities: nd,
            data: vec![7u8; w * h * nd],
            max_cost: 255,
            source: VolumeSource::Fused(fuse::fusion::Fusion::Mean),
        };
        let sample = Sample {
            volumes: vec![volume.clone(), volume],
            truth: vec![3.0; w * h],
            sharp: Vec::new(),
        };
        let small = TrainConfig {
            num_disparities: nd,
            keep_hopeless: true,
            ..config.clone()
        };
        for step in [0, 10, 20] {
            let side = small.crop_px_at(step);
            let mut rng = SplitMix64::new(step);
            let example = random_crop(&small, std::slice::from_ref(&sample), side, &mut rng);
            assert_eq!(example.target.len(), side * side, "step {step}");
            assert_eq!(example.inputs[0].shape, [1, nd, side, side], "step {step}");
        }
        for (stages, why) in [
            (vec![stage(10, 64), stage(10, 128)], "one stage per step"),
            (vec![stage(10, 64), stage(5, 128)], "in order"),
            (vec![stage(10, 66)], "a multiple of 4"),
            (vec![stage(10, 512)], "within the resolution"),
        ] {
            let bad = TrainConfig {
                crop_stages: stages,
                ..config.clone()
            };
            let error = bad.validate().err();
            assert!(
                matches!(&error, Some(TrainError::Config { field: "crop_stages", reason, .. }) if reason.contains(why)),
                "{error:?}"
            );
        }
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
        let errors = winner_take_all_errors(&shifted, false);
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
