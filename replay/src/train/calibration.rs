//! Validation of both readouts of the network, and the refined readout's pixel-locking curve
//! fitted on the training captures (`replay train --calibrate`).

use std::path::Path;

use fuse::mfusenet::infer::{DEFAULT_REFINE_REACH, DEFAULT_SUBPIXEL_FIT};
use fuse::mfusenet::train::Example;
use fuse::mfusenet::{Network, weights};
use fuse::nn::regression::soft_argmin;
use fuse::wta::LockingCurve;

use super::dataset::{Sample, sample};
use super::{TrainConfig, TrainError, to_json};

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
    info.set("locking_curve", to_json("locking_curve", &curve)?);
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
            // The views' volumes (a sharp network's sharp ones follow them), as inference reads.
            let views = if net.sharp {
                example.inputs.len() / 2
            } else {
                example.inputs.len()
            };
            let cost = |z: usize| {
                example.inputs[..views]
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
