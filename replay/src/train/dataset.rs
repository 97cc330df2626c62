//! The training dataset: simulated five-view (or grid-cross) captures reduced once to their input volumes and
//! ground truth (cached as safetensors), validation crops, and how hard a crop is for the
//! inputs alone (winner-take-all, hopeless crops).

use std::path::Path;
use std::sync::atomic::AtomicBool;

use fuse::fusion::SideRule;
use fuse::mfusenet::input::{input_volumes_below, sharp_volumes_of_sides_below};
use fuse::mfusenet::train::{Example, crop};
use fuse::volume::{CostVolume, VolumeSource};
use record::capture::Simulation;
use record::rig::RigKind;
use record::rng::SplitMix64;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use crate::viewset::ViewSet;

use super::{TrainConfig, TrainError, file_error};

/// The neighbours a sample keeps, in its order: the cross at one baseline (what the fixed
/// networks take), then a `grid-cross` capture's diagonals and the cross at two baselines.
pub const NEIGHBOURS: [(&str, [i32; 2]); 12] = [
    ("left", [-1, 0]),
    ("right", [1, 0]),
    ("top", [0, -1]),
    ("bottom", [0, 1]),
    ("top-left", [-1, -1]),
    ("top-right", [1, -1]),
    ("bottom-right", [1, 1]),
    ("bottom-left", [-1, 1]),
    ("left2", [-2, 0]),
    ("right2", [2, 0]),
    ("top2", [0, -2]),
    ("bottom2", [0, 2]),
];

/// A `line5` capture's neighbours in the five-view network's input order: the near pair in
/// its left and right inputs, the far pair (`left2`, `right2`) in its top and bottom ones, as
/// `mfusenet`'s `line_cross` feeds a line of five.
pub const LINE_NEIGHBOURS: [(&str, [i32; 2]); 4] = [
    ("left", [-1, 0]),
    ("right", [1, 0]),
    ("left2", [-2, 0]),
    ("right2", [2, 0]),
];

/// The neighbours a sample of a capture of `rig` keeps, in its order (the rigs training
/// accepts): the cross at one baseline, all twelve of [`NEIGHBOURS`] for `grid-cross`, the
/// line's four ([`LINE_NEIGHBOURS`]) for `line5`.
pub fn kept_neighbours(rig: RigKind) -> &'static [(&'static str, [i32; 2])] {
    match rig {
        RigKind::GridCross => &NEIGHBOURS,
        RigKind::Line5 => &LINE_NEIGHBOURS,
        _ => &NEIGHBOURS[..4],
    }
}

/// How many neighbours a sample of a capture of `rig` keeps ([`kept_neighbours`]).
pub fn neighbours_kept(rig: RigKind) -> usize {
    kept_neighbours(rig).len()
}

/// The most views a training crop of the view-count-agnostic network draws: a 3 × 3 grid's
/// eight neighbours are pooled at inference, but crops of up to twelve would hold twice the
/// activations of the four-view network's for the rarest sets.
pub const MAX_DRAWN_VIEWS: usize = 6;

/// One sample of the cache: the per-neighbour volumes (its rig's [`kept_neighbours`]) and the
/// ground-truth disparity.
pub struct Sample {
    /// In the order of [`kept_neighbours`]: left, right, top, bottom, then (grid-cross) the
    /// rest; a line's left, right, left2, right2.
    pub volumes: Vec<CostVolume<u8>>,
    /// `[y][x]` px, 0 = unknown.
    pub truth: Vec<f32>,
    /// A sharp run's ([`TrainConfig::sharp`]): each neighbour's sharp volume, in the order of
    /// `volumes`; empty otherwise.
    pub sharp: Vec<CostVolume<u8>>,
}

impl Sample {
    /// The neighbours (indices into `volumes`) a network of `views` inputs takes, in its order
    /// (see `fuse::mfusenet::input`); the cross at one baseline for the view-count-agnostic
    /// network (`views` = 0), as its validation reads it.
    fn view_indices(views: usize) -> &'static [usize] {
        match views {
            1 => &[1],
            2 => &[0, 1],
            _ => &[0, 1, 2, 3],
        }
    }

    /// The volumes a network of `views` inputs takes ([`Sample::view_indices`]).
    pub fn for_views(&self, views: usize) -> Vec<&CostVolume<u8>> {
        Self::view_indices(views).iter().map(|i| &self.volumes[*i]).collect()
    }

    /// What a network of `views` inputs reads: [`Sample::for_views`], then (a sharp network) the
    /// same neighbours' sharp volumes.
    pub fn inputs(&self, views: usize, sharp: bool) -> Vec<&CostVolume<u8>> {
        let mut inputs = self.for_views(views);
        if sharp {
            inputs.extend(Self::view_indices(views).iter().filter_map(|i| self.sharp.get(*i)));
        }
        inputs
    }

    /// [`Sample::for_views`] for a training crop: the view-count-agnostic network (`views` = 0)
    /// gets a random non-empty subset of the sample's neighbours (four, or twelve from a
    /// grid-cross capture) in a random order, the count uniform from 1 to the fewer of those and
    /// [`MAX_DRAWN_VIEWS`], so
    /// that it learns from any number of views at any offset alike; the fixed networks their own.
    /// Draws from `rng` only for `views` = 0.
    pub fn for_views_drawn(&self, views: usize, rng: &mut SplitMix64) -> Vec<&CostVolume<u8>> {
        if views != 0 {
            return self.for_views(views);
        }
        let mut order: Vec<usize> = (0..self.volumes.len()).collect();
        for i in (1..order.len()).rev() {
            order.swap(i, rng.range_usize(0, i + 1));
        }
        let count = rng.range_usize(1, order.len().min(MAX_DRAWN_VIEWS) + 1);
        order[..count].iter().map(|i| &self.volumes[*i]).collect()
    }
}

/// The cache's file name of training (or `validation`) capture `index`: `train-`, `val-`, or
/// `renew-` for a renewing pool's captures past the first `train_sets` (their seeds are their
/// own, so a run with more `train_sets` never reads one as its own `train-` capture).
pub fn sample_file_name(config: &TrainConfig, index: usize, validation: bool) -> String {
    let kind = if validation {
        "val"
    } else if index >= config.train_sets {
        "renew"
    } else {
        "train"
    };
    format!("{kind}-{index:04}-{:016x}.safetensors", config.data_key())
}

/// Makes (or reads from `cache_dir`) one dataset sample.
pub fn sample(config: &TrainConfig, index: usize, validation: bool, cache_dir: &Path) -> Result<Sample, TrainError> {
    let path = cache_dir.join(sample_file_name(config, index, validation));
    let kept = kept_neighbours(config.rig);
    if let Ok(bytes) = std::fs::read(&path)
        && let Some(sample) = read_sample(&bytes, config.depth(), kept, config.sharp.is_some())
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
    let neighbours = kept
        .iter()
        .map(|(_, offset)| problem.neighbours.iter().find(|n| n.offset == *offset))
        .collect::<Option<Vec<_>>>()
        .ok_or_else(|| TrainError::Fuse {
            index,
            source: fuse::FuseError::Config {
                field: "neighbours",
                value: problem.neighbour_list(),
                reason: "a training capture needs every neighbour its rig keeps (the cross at one baseline; grid-cross: also the diagonals and the cross at two; line5: both pairs)",
            },
        })?;
    // Samples are in slice coordinates, as `read_sample` gives them back: the first slice (the
    // context's, under 0) is 0 and the truth is shifted up by the context.
    let volumes = input_volumes_below(&problem, &neighbours, config.input, config.context_below, &|| {})
        .map_err(|source| TrainError::Fuse { index, source })?
        .0
        .into_iter()
        .map(|v| CostVolume { min_disparity: 0, ..v })
        .collect();
    let sharp = match config.sharp {
        Some(spec) => {
            let sides: Vec<Vec<&fuse::volume::Neighbour>> = neighbours.iter().map(|n| vec![*n]).collect();
            sharp_volumes_of_sides_below(&problem, &sides, SideRule::Min, spec, config.context_below)
                .map_err(|source| TrainError::Fuse { index, source })?
                .0
                .into_iter()
                .map(|v| CostVolume { min_disparity: 0, ..v })
                .collect()
        }
        None => Vec::new(),
    };
    let below = config.context_below as f32;
    let truth = view_set
        .ground_truth_disparity()
        .ok_or_else(|| file_error(&path, "the simulated set has no ground truth".to_owned()))?
        .into_iter()
        .map(|t| if t.is_finite() && t > 0.0 { t + below } else { 0.0 })
        .collect();
    let sample = Sample { volumes, truth, sharp };
    write_sample(&sample, &path)?;
    Ok(sample)
}

fn write_sample(sample: &Sample, path: &Path) -> Result<(), TrainError> {
    let v = &sample.volumes[0];
    let truth: Vec<u8> = sample.truth.iter().flat_map(|t| t.to_le_bytes()).collect();
    let mut views = Vec::new();
    let named = sample
        .volumes
        .iter()
        .enumerate()
        .map(|(i, volume)| (format!("volume.{i}"), volume))
        .chain(
            sample
                .sharp
                .iter()
                .enumerate()
                .map(|(i, volume)| (format!("sharp.{i}"), volume)),
        );
    for (name, volume) in named {
        let view = TensorView::new(Dtype::U8, vec![v.height, v.width, v.num_disparities], &volume.data)
            .map_err(|e| file_error(path, e.to_string()))?;
        views.push((name, view));
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

fn read_sample(bytes: &[u8], num_disparities: usize, kept: &[(&str, [i32; 2])], sharp: bool) -> Option<Sample> {
    let tensors = SafeTensors::deserialize(bytes).ok()?;
    let truth_view = tensors.tensor("truth").ok()?;
    let (height, width) = (*truth_view.shape().first()?, *truth_view.shape().get(1)?);
    let truth = truth_view
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let read = |kind: &str| -> Option<Vec<CostVolume<u8>>> {
        kept.iter()
            .enumerate()
            .map(|(i, (role, offset))| {
                let view = tensors.tensor(&format!("{kind}.{i}")).ok()?;
                (view.shape() == [height, width, num_disparities]).then(|| CostVolume {
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
                })
            })
            .collect()
    };
    let volumes = read("volume")?;
    let sharp = if sharp { read("sharp")? } else { Vec::new() };
    Some(Sample { volumes, truth, sharp })
}

/// Validation crops: the centre `side × side` (largest multiple of 4 that fits, at most 160)
/// of every validation sample.
pub fn validation_examples(samples: &[Sample], views: usize, sharp: bool, num_disparities: usize) -> Vec<Example> {
    samples
        .iter()
        .map(|s| {
            let (w, h) = (s.volumes[0].width, s.volumes[0].height);
            let side = (w.min(h).min(160)) / 4 * 4;
            crop(
                &s.inputs(views, sharp),
                &s.truth,
                ((h - side) / 2, (w - side) / 2),
                (side, side),
                num_disparities,
            )
        })
        .collect()
}

/// The errors (px) over the masked pixels of the winner-take-all of the mean input volume (with
/// parabola refinement): what the network's inputs say on their own. A sharp example's sharp
/// volumes (its second half) are not counted.
pub fn winner_take_all_errors(example: &Example, sharp: bool) -> Vec<f32> {
    let views = &example.inputs[..if sharp {
        example.inputs.len() / 2
    } else {
        example.inputs.len()
    }];
    let Some(first) = views.first() else {
        return Vec::new();
    };
    let [_, d, h, w] = first.shape;
    let plane = h * w;
    (0..plane)
        .filter(|pixel| example.mask[*pixel])
        .map(|pixel| {
            let cost = |z: usize| views.iter().map(|t| t.data[z * plane + pixel]).sum::<f32>();
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
pub fn winner_take_all_reference(examples: &[Example], sharp: bool) -> (f64, f64) {
    let (mut sum, mut bad, mut count) = (0f64, 0usize, 0usize);
    for error in examples.iter().flat_map(|e| winner_take_all_errors(e, sharp)) {
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

pub(super) fn hopeless(example: &Example, sharp: bool) -> bool {
    let errors = winner_take_all_errors(example, sharp);
    let wrong = errors.iter().filter(|e| **e > HOPELESS_ERROR_PX).count();
    wrong as f32 > HOPELESS_FRACTION * errors.len() as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use fuse::fusion::Fusion;
    use fuse::volume::VolumeSource;

    #[test]
    fn drawn_views_are_distinct_subsets_of_every_size_for_the_pooled_network_only() {
        let volume = CostVolume {
            width: 1,
            height: 1,
            min_disparity: 0,
            num_disparities: 1,
            data: vec![0u8],
            max_cost: 1,
            source: VolumeSource::Fused(Fusion::Mean),
        };
        let sample = Sample {
            volumes: vec![volume; 4],
            truth: vec![0.0],
            sharp: Vec::new(),
        };
        let index = |v: &CostVolume<u8>| sample.volumes.iter().position(|s| std::ptr::eq(s, v));
        let mut rng = SplitMix64::new(1);
        let mut counts = [0usize; 5];
        let mut firsts = [0usize; 4];
        for _ in 0..400 {
            let drawn: Vec<usize> = sample
                .for_views_drawn(0, &mut rng)
                .into_iter()
                .filter_map(index)
                .collect();
            let distinct: std::collections::BTreeSet<usize> = drawn.iter().copied().collect();
            assert_eq!(distinct.len(), drawn.len(), "{drawn:?} repeats a view");
            counts[drawn.len()] += 1;
            firsts[drawn[0]] += 1;
        }
        assert_eq!(counts[0], 0);
        assert!(counts[1..].iter().all(|c| *c > 60), "sizes {counts:?}");
        assert!(firsts.iter().all(|c| *c > 60), "first views {firsts:?}");
        // A grid-cross sample's twelve: every one drawn, never more than MAX_DRAWN_VIEWS at once.
        let wide = Sample {
            volumes: vec![sample.volumes[0].clone(); NEIGHBOURS.len()],
            truth: vec![0.0],
            sharp: Vec::new(),
        };
        let mut seen = [0usize; NEIGHBOURS.len()];
        let mut sizes = [0usize; MAX_DRAWN_VIEWS + 1];
        for _ in 0..600 {
            let drawn = wide.for_views_drawn(0, &mut rng);
            sizes[drawn.len()] += 1;
            for v in drawn {
                if let Some(i) = wide.volumes.iter().position(|s| std::ptr::eq(s, v)) {
                    seen[i] += 1;
                }
            }
        }
        assert_eq!(sizes[0], 0);
        assert!(sizes[1..].iter().all(|c| *c > 50), "sizes {sizes:?}");
        assert!(seen.iter().all(|c| *c > 100), "views {seen:?}");
        // The fixed networks get their own views and draw nothing.
        let mut untouched = SplitMix64::new(7);
        let right: Vec<usize> = sample
            .for_views_drawn(1, &mut untouched)
            .into_iter()
            .filter_map(index)
            .collect();
        assert_eq!(right, [1]);
        assert_eq!(
            untouched.range_usize(0, 1_000_000),
            SplitMix64::new(7).range_usize(0, 1_000_000)
        );
    }
}
