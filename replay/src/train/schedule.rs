//! What each step trains on: random crops drawn from the seed and the step (so that a resumed
//! run draws what an uninterrupted one would), the crops kept, the disparity shift, and the
//! BatchNorm calibration crops and gradient clipping.

use fuse::mfusenet::input::{mirror_order, neighbour_offsets};
use fuse::mfusenet::train::{Example, crop, flipped, flipped_unordered};
use fuse::nn::Tensor;

use record::rng::SplitMix64;

use super::TrainConfig;
use super::dataset::{Sample, hopeless};

/// Crops whose batch statistics set the BatchNorms.
pub(super) const CALIBRATION_CROPS: usize = 32;
/// Largest global gradient norm (larger ones are scaled down).
pub(super) const MAX_GRADIENT_NORM: f32 = 1.0;

/// A random training crop `side` px square with ground truth on at least half its pixels (the
/// last of a few tries otherwise).
pub(super) fn random_crop(config: &TrainConfig, samples: &[Sample], side: usize, rng: &mut SplitMix64) -> Example {
    let mut example = None;
    for _ in 0..8 {
        let s = &samples[rng.range_usize(0, samples.len())];
        let (w, h) = (s.volumes[0].width, s.volumes[0].height);
        let (y0, x0) = (
            rng.range_usize(0, h.saturating_sub(side) + 1),
            rng.range_usize(0, w.saturating_sub(side) + 1),
        );
        let sharp = config.sharp.is_some();
        let volumes = if sharp {
            s.inputs(config.views, true)
        } else {
            s.for_views_drawn(config.views, rng)
        };
        let mut e = crop(&volumes, &s.truth, (y0, x0), (side, side), config.depth());
        if config.disparity_shift > 0 {
            e = shifted(
                e,
                4 * rng.range_usize(0, config.disparity_shift / 4 + 1),
                config.context_below,
            );
        }
        if config.flips {
            let (vertical, horizontal) = (rng.range_usize(0, 2) == 1, rng.range_usize(0, 2) == 1);
            if config.views == 0 {
                // The pooled network does not know which neighbour gave which volume: every
                // mirror exists.
                e = flipped_unordered(&e, vertical, horizontal);
            } else {
                // The views' offsets (a sharp crop's sharp volumes follow their views).
                let views = if sharp { volumes.len() / 2 } else { volumes.len() };
                let offsets = neighbour_offsets(volumes[..views].iter().copied()).unwrap_or_default();
                // A flip the rig has no mirror for (a single right neighbour, left to right) is
                // not made.
                let possible = |v: bool, h: bool| mirror_order(&offsets, v, h).is_some();
                let (vertical, horizontal) = (vertical && possible(true, false), horizontal && possible(false, true));
                if let Some(mirror) = flipped(&e, &offsets, vertical, horizontal) {
                    e = mirror;
                }
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

/// Whether training takes this crop: ground truth on more than half its pixels, and inputs
/// that are not hopeless unless the configuration keeps those.
pub(super) fn acceptable(config: &TrainConfig, example: &Example) -> bool {
    example.mask.iter().filter(|m| **m).count() * 2 > example.mask.len()
        && (config.keep_hopeless || !hopeless(example, config.sharp.is_some()))
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
