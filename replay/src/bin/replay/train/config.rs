//! `replay train`'s options as the library's training configuration (usage errors for what
//! does not parse or validate).

use anyhow::Result;
use cli::UsageError;
use fuse::mfusenet::input::InputSpec;
use replay::train::{CropStage, TrainConfig};

use super::options::TrainArgs;

impl TrainArgs {
    /// The training configuration the options ask for.
    pub(crate) fn config(&self) -> Result<TrainConfig> {
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
        let crop_stages = self
            .crop_px_from
            .iter()
            .map(|stage| {
                stage
                    .split_once(':')
                    .and_then(|(step, px)| {
                        Some(CropStage {
                            from_step: step.trim().parse().ok()?,
                            crop_px: px.trim().parse().ok()?,
                        })
                    })
                    .ok_or_else(|| usage(format!("--crop-px-from {stage}: expected STEP:PX, e.g. 15000:256")))
            })
            .collect::<Result<Vec<_>>>()?;
        let config = TrainConfig {
            views: if self.views == "any" {
                0
            } else {
                self.views.parse().unwrap_or(2)
            },
            steps: self.steps,
            crop_px: self.crop_px,
            crop_stages,
            num_disparities: self.num_disparities,
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
            architecture: fuse::mfusenet::Architecture::from_name(&self.architecture)
                .ok_or_else(|| usage(format!("--architecture {}: expected paper or lite", self.architecture)))?,
            disparity_shift: self.disparity_shift,
            recalibrate_every: self.recalibrate_every,
            statistics_momentum: self.statistics_momentum,
            average_decay: self.average_decay,
            context_below: self.context_below,
            flips: self.flips,
            keep_hopeless: self.keep_hopeless,
            renew_every: self.renew_every,
            scenes: self.scenes.clone(),
            exposure_jitter: self.exposure_jitter,
            rig: self.rig,
            sharp: self.sharp.then(fuse::mfusenet::input::SharpSpec::default),
            input: InputSpec {
                block_radius_px: self.input_block_radius_px,
                ..InputSpec::default()
            },
            ..TrainConfig::default()
        };
        config.validate().map_err(|e| usage(e.to_string()))?;
        Ok(config)
    }
}
