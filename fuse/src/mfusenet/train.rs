//! Training pieces that need no data source: random crops of the input volumes with their
//! target, Adam, and checkpoints (weights, Adam's moments and the step, in one safetensors file)
//! so that an interrupted run resumes where it stopped. The loop itself, with the synthetic
//! captures, lives in `replay::train`.

use std::collections::HashMap;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use super::Error;
use super::network::{Gradients, Network};
use super::weights::{self, WeightsInfo};
use crate::nn::Tensor;
use crate::volume::CostVolume;

/// One training example: the network's inputs and the target disparity (in slices, i.e. minus
/// the volumes' first disparity) with the pixels that count.
#[derive(Debug, Clone, PartialEq)]
pub struct Example {
    /// `[1, D, H, W]` per view.
    pub inputs: Vec<Tensor>,
    /// `H·W` targets.
    pub target: Vec<f32>,
    /// `H·W`: ground truth known and inside the searched range.
    pub mask: Vec<bool>,
}

/// The crop `rows × columns` at `(y0, x0)` of the volumes (padded to `depth` slices, a multiple
/// of 4, by repeating the last) with the ground-truth disparity `truth` (px, `[y][x]`, 0 or
/// non-finite = unknown).
pub fn crop(
    volumes: &[&CostVolume<u8>],
    truth: &[f32],
    (y0, x0): (usize, usize),
    (rows, columns): (usize, usize),
    depth: usize,
) -> Example {
    let (w, nd) = (volumes[0].width, volumes[0].num_disparities);
    let min = volumes[0].min_disparity as f32;
    let inputs = volumes
        .iter()
        .map(|v| super::input::to_tensor(v, (y0, x0), (rows, columns), depth))
        .collect();
    let mut target = Vec::with_capacity(rows * columns);
    let mut mask = Vec::with_capacity(rows * columns);
    for y in 0..rows {
        for x in 0..columns {
            let d = truth[(y0 + y) * w + x0 + x] - min;
            let known = truth[(y0 + y) * w + x0 + x] > 0.0 && d.is_finite() && d >= 0.0 && d <= (nd - 1) as f32;
            target.push(if known { d } else { 0.0 });
            mask.push(known);
        }
    }
    Example { inputs, target, mask }
}

/// `example` seen in a mirror, as the same network must answer it: its inputs
/// [`super::input::mirrored`] (rows flipped if `vertical`, columns if `horizontal`, each volume
/// moved to its mirrored neighbour's slot; `offsets` are the neighbours'), its targets and mask
/// moved with their pixels; disparities are unchanged. `None` when the set has no such mirror
/// (a single right neighbour mirrored left to right).
pub fn flipped(example: &Example, offsets: &[[i32; 2]], vertical: bool, horizontal: bool) -> Option<Example> {
    let inputs = super::input::mirrored(&example.inputs, offsets, vertical, horizontal)?;
    with_flipped_targets(example, inputs, vertical, horizontal)
}

/// `example` seen in a mirror by a network indifferent to which neighbour gave which volume (the
/// pooled one, `Network::pooled`): every input flipped where it is, targets and mask moved with
/// their pixels. A mirrored right neighbour's volume is a left neighbour's, which such a network
/// takes as well, so every mirror exists.
pub fn flipped_unordered(example: &Example, vertical: bool, horizontal: bool) -> Example {
    let inputs: Vec<Tensor> = example.inputs.iter().map(|t| t.flipped(vertical, horizontal)).collect();
    with_flipped_targets(example, inputs, vertical, horizontal).unwrap_or_else(|| example.clone())
}

/// `example`'s targets and mask flipped, with `inputs` (already flipped). `None` without inputs.
fn with_flipped_targets(example: &Example, inputs: Vec<Tensor>, vertical: bool, horizontal: bool) -> Option<Example> {
    let [_, _, h, w] = inputs.first()?.shape;
    let plane = |values: Vec<f32>| {
        Tensor {
            shape: [1, 1, h, w],
            data: values,
        }
        .flipped(vertical, horizontal)
        .data
    };
    let target = plane(example.target.clone());
    let mask = plane(example.mask.iter().map(|m| f32::from(u8::from(*m))).collect())
        .into_iter()
        .map(|m| m > 0.5)
        .collect();
    Some(Example { inputs, target, mask })
}

/// Re-estimates every BatchNorm's running statistics as the plain average of the batch
/// statistics over `examples` in train mode (PyTorch's `momentum=None` after resetting the
/// counts), instead of the exponential average of the last training steps: the eval-mode network
/// then normalises with the population statistics. Weights are unchanged.
pub fn recalibrate_batch_norm<'a>(
    net: &mut Network,
    examples: impl IntoIterator<Item = &'a Example>,
) -> Result<usize, Error> {
    let saved: Vec<(i64, Option<f32>)> = net
        .layers()
        .map(|l| (l.bn.num_batches_tracked, l.bn.momentum))
        .collect();
    for layer in net.layers_mut() {
        layer.bn.num_batches_tracked = 0;
        layer.bn.momentum = None;
    }
    let mut passes = 0;
    let mut outcome = Ok(());
    for example in examples {
        if let Err(e) = net.forward_train(&example.inputs) {
            outcome = Err(e);
            break;
        }
        passes += 1;
    }
    for (layer, (count, momentum)) in net.layers_mut().zip(saved) {
        layer.bn.num_batches_tracked += count;
        layer.bn.momentum = momentum;
    }
    outcome.map(|()| passes)
}

/// Scales the gradients so that their global L2 norm is at most `max_norm`; returns the norm
/// before scaling.
pub fn clip_gradients(gradients: &mut Gradients, max_norm: f32) -> f32 {
    let norm = gradients
        .tensors
        .iter()
        .flat_map(|(_, g)| g.iter())
        .map(|v| f64::from(*v) * f64::from(*v))
        .sum::<f64>()
        .sqrt() as f32;
    if norm > max_norm && norm.is_finite() {
        let scale = max_norm / norm;
        for (_, g) in &mut gradients.tensors {
            for v in g.iter_mut() {
                *v *= scale;
            }
        }
    }
    norm
}

/// Adam (Kingma & Ba) with PyTorch's defaults (β = 0.9, 0.999, ε = 1e-8), no weight decay.
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    /// Learning rate.
    pub learning_rate: f32,
    /// Steps taken.
    pub step: u64,
    /// First moments, per parameter tensor (in [`Network::parameters_mut`] order).
    pub m: Vec<Vec<f32>>,
    /// Second moments.
    pub v: Vec<Vec<f32>>,
}

impl Adam {
    /// Zero moments for `net`.
    pub fn new(net: &mut Network, learning_rate: f32) -> Self {
        let sizes: Vec<usize> = net.parameters_mut().iter().map(|(_, p)| p.len()).collect();
        Self {
            learning_rate,
            step: 0,
            m: sizes.iter().map(|n| vec![0.0; *n]).collect(),
            v: sizes.iter().map(|n| vec![0.0; *n]).collect(),
        }
    }

    /// One update of every parameter from its gradient.
    pub fn update(&mut self, net: &mut Network, gradients: &Gradients) {
        const BETA1: f32 = 0.9;
        const BETA2: f32 = 0.999;
        const EPS: f32 = 1e-8;
        self.step += 1;
        let bias1 = 1.0 - BETA1.powi(self.step as i32);
        let bias2 = 1.0 - BETA2.powi(self.step as i32);
        for (((_, param), (_, grad)), (m, v)) in net
            .parameters_mut()
            .into_iter()
            .zip(&gradients.tensors)
            .zip(self.m.iter_mut().zip(self.v.iter_mut()))
        {
            for (((p, g), m), v) in param.iter_mut().zip(grad).zip(m.iter_mut()).zip(v.iter_mut()) {
                *m = BETA1 * *m + (1.0 - BETA1) * g;
                *v = BETA2 * *v + (1.0 - BETA2) * g * g;
                *p -= self.learning_rate * (*m / bias1) / ((*v / bias2).sqrt() + EPS);
            }
        }
    }
}

/// An exponential moving average of a network's trainable parameters (Polyak averaging): the
/// network a long run exports and validates, steadier than the last step's when single-crop
/// steps make consecutive checkpoints swing. Each update moves every value towards the live
/// network's by `1 − d`, with `d = min(decay, (1 + n) / (10 + n))` after `n` updates, so that
/// an average started late (on resuming a run that had none) forgets its start within a few
/// dozen steps instead of a few thousand.
#[derive(Debug, Clone, PartialEq)]
pub struct Average {
    /// The decay per step (0.999: about the last thousand steps).
    pub decay: f32,
    /// Updates taken.
    pub updates: u64,
    /// The averaged values, per parameter tensor (in [`Network::parameters_mut`] order).
    pub values: Vec<Vec<f32>>,
}

impl Average {
    /// An average that starts at `net`'s parameters.
    pub fn new(net: &mut Network, decay: f32) -> Self {
        Self {
            decay,
            updates: 0,
            values: net.parameters_mut().into_iter().map(|(_, p)| p.clone()).collect(),
        }
    }

    /// The decay of the next update.
    pub fn next_decay(&self) -> f32 {
        let n = self.updates as f32;
        self.decay.min((1.0 + n) / (10.0 + n))
    }

    /// Moves the average towards `net`'s parameters (after an optimiser step).
    pub fn update(&mut self, net: &mut Network) {
        let d = self.next_decay();
        for ((_, param), average) in net.parameters_mut().into_iter().zip(self.values.iter_mut()) {
            for (a, p) in average.iter_mut().zip(param.iter()) {
                *a = d * *a + (1.0 - d) * *p;
            }
        }
        self.updates += 1;
    }

    /// `net` with its trainable parameters replaced by the average (its BatchNorm statistics
    /// are `net`'s).
    pub fn network(&self, net: &Network) -> Network {
        let mut averaged = net.clone();
        for ((_, param), average) in averaged.parameters_mut().into_iter().zip(&self.values) {
            param.clone_from(average);
        }
        averaged
    }
}

/// Writes a checkpoint: the weights (`model.<name>`), Adam's moments (`adam_m.<name>`,
/// `adam_v.<name>`), the moving average when there is one (`average.<name>`, with
/// `average_decay` and `average_updates`), and `info` with the step, through a temporary file
/// renamed when complete.
pub fn save_checkpoint(
    net: &mut Network,
    adam: &Adam,
    average: Option<&Average>,
    info: &WeightsInfo,
    path: &Path,
) -> Result<(), Error> {
    let model = weights::to_bytes(net, info)?;
    let model = SafeTensors::deserialize(&model).map_err(|e| Error::Format {
        file: path.display().to_string(),
        reason: e.to_string(),
    })?;
    let mut owned: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = Vec::new();
    for (name, view) in model.tensors() {
        owned.push((
            format!("model.{name}"),
            view.dtype(),
            view.shape().to_vec(),
            view.data().to_vec(),
        ));
    }
    let names: Vec<String> = net.parameters_mut().into_iter().map(|(n, _)| n).collect();
    let kinds = [("adam_m", &adam.m), ("adam_v", &adam.v)]
        .into_iter()
        .chain(average.map(|a| ("average", &a.values)));
    for (kind, moments) in kinds {
        for (name, values) in names.iter().zip(moments) {
            owned.push((
                format!("{kind}.{name}"),
                Dtype::F32,
                vec![values.len()],
                values.iter().flat_map(|v| v.to_le_bytes()).collect(),
            ));
        }
    }
    let format = |e: safetensors::SafeTensorError| Error::Format {
        file: path.display().to_string(),
        reason: e.to_string(),
    };
    let views = owned
        .iter()
        .map(|(n, d, s, b)| TensorView::new(*d, s.clone(), b).map(|v| (n.clone(), v)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(format)?;
    let mut metadata: HashMap<String, String> = info.entries.clone().into_iter().collect();
    if net.views == 0 {
        metadata.insert(weights::VIEW_FUSION_KEY.to_owned(), weights::MEAN_MAX.to_owned());
    } else {
        metadata.remove(weights::VIEW_FUSION_KEY);
    }
    metadata.insert("adam_step".to_owned(), adam.step.to_string());
    metadata.insert("adam_learning_rate".to_owned(), adam.learning_rate.to_string());
    metadata.remove("average_decay");
    metadata.remove("average_updates");
    if let Some(average) = average {
        metadata.insert("average_decay".to_owned(), average.decay.to_string());
        metadata.insert("average_updates".to_owned(), average.updates.to_string());
    }
    let bytes = safetensors::serialize(views, Some(metadata)).map_err(format)?;
    let io = |e: std::io::Error| Error::Write {
        file: path.display().to_string(),
        reason: e.to_string(),
    };
    let temporary = path.with_extension("partial");
    std::fs::write(&temporary, bytes).map_err(io)?;
    std::fs::rename(&temporary, path).map_err(io)
}

/// What [`load_checkpoint`] reads.
#[derive(Debug, Clone, PartialEq)]
pub struct Checkpoint {
    /// The live network.
    pub net: Network,
    /// The optimiser's state.
    pub adam: Adam,
    /// The moving average, when the run keeps one.
    pub average: Option<Average>,
    /// The metadata.
    pub info: WeightsInfo,
}

/// Reads a checkpoint written by [`save_checkpoint`].
pub fn load_checkpoint(path: &Path, views: usize) -> Result<Checkpoint, Error> {
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| Error::Read {
        file: file.clone(),
        reason: e.to_string(),
    })?;
    let (mut net, info) = weights::from_bytes(&bytes, &file, "model.", Some(views))?;
    let tensors = SafeTensors::deserialize(&bytes).map_err(|e| Error::Format {
        file: file.clone(),
        reason: e.to_string(),
    })?;
    let mut adam = Adam::new(
        &mut net,
        info.get("adam_learning_rate")
            .and_then(|v| v.parse().ok())
            .unwrap_or(1e-3),
    );
    adam.step = info.get("adam_step").and_then(|v| v.parse().ok()).unwrap_or(0);
    let mut average = info
        .get("average_decay")
        .and_then(|v| v.parse().ok())
        .map(|decay| Average {
            updates: info.get("average_updates").and_then(|v| v.parse().ok()).unwrap_or(0),
            ..Average::new(&mut net, decay)
        });
    let names: Vec<String> = net.parameters_mut().into_iter().map(|(n, _)| n).collect();
    let kinds = [("adam_m", &mut adam.m), ("adam_v", &mut adam.v)]
        .into_iter()
        .chain(average.as_mut().map(|a| ("average", &mut a.values)));
    for (kind, moments) in kinds {
        for (name, values) in names.iter().zip(moments.iter_mut()) {
            let tensor = format!("{kind}.{name}");
            let view = tensors.tensor(&tensor).map_err(|_| Error::MissingTensor {
                file: file.clone(),
                tensor: tensor.clone(),
            })?;
            if view.dtype() != Dtype::F32 || view.data().len() != values.len() * 4 {
                return Err(Error::TensorShape {
                    file: file.clone(),
                    tensor,
                    expected: format!("[{}] F32", values.len()),
                    got: view.shape().to_vec(),
                });
            }
            for (v, b) in values.iter_mut().zip(view.data().chunks_exact(4)) {
                *v = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
        }
    }
    Ok(Checkpoint {
        net,
        adam,
        average,
        info,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mfusenet::Architecture;

    /// Two views of a fronto-parallel plane at disparity 5: each volume's cost is lowest at 5.
    fn plane_volumes(w: usize, h: usize, nd: usize) -> (Vec<CostVolume<u8>>, Vec<f32>) {
        let volume = |noise: usize| {
            CostVolume::from_fn([w, h, nd], 0, ("left", [-1, 0]), |x, y, d| {
                let i = (y * w + x) * nd + d;
                ((d as i32 - 5).unsigned_abs() * 12 + ((i * 7 + noise) % 5) as u32) as u8
            })
        };
        (vec![volume(0), volume(3)], vec![5.0; w * h])
    }

    /// Largest logit magnitude of the eval-mode network on `example`.
    fn logit_scale(net: &Network, example: &Example) -> f32 {
        let logits = net.logits(&example.inputs).unwrap_or_else(|e| panic!("{e}"));
        logits.data.iter().fold(0f32, |m, v| m.max(v.abs()))
    }

    #[test]
    fn recalibration_undoes_activations_grown_under_frozen_statistics() {
        // Weights that grew while the statistics stayed frozen (every convolution ×3, as Adam
        // can do over thousands of steps): the activations grow ×3 per layer and the logits by
        // orders of magnitude, a saturated softmax. Re-estimating the statistics brings them back
        // to the scale of a freshly calibrated network.
        let (volumes, truth) = plane_volumes(16, 16, 12);
        let refs: Vec<&CostVolume<u8>> = volumes.iter().collect();
        let example = crop(&refs, &truth, (0, 0), (16, 16), 12);
        let mut net = Network::init(2, 5);
        recalibrate_batch_norm(&mut net, [&example]).unwrap_or_else(|e| panic!("{e}"));
        let fresh = logit_scale(&net, &example);
        for layer in net.layers_mut() {
            layer.weight.iter_mut().for_each(|w| *w *= 3.0);
        }
        let grown = logit_scale(&net, &example);
        assert!(grown > 1000.0 * fresh, "logits {fresh} → {grown}");
        recalibrate_batch_norm(&mut net, [&example]).unwrap_or_else(|e| panic!("{e}"));
        let again = logit_scale(&net, &example);
        assert!((again / fresh - 1.0).abs() < 0.05, "logits {fresh} → {grown} → {again}");
    }

    #[test]
    fn the_moving_average_follows_its_formula_and_forgets_a_late_start() {
        let mut net = Network::init(2, 5);
        let start = net.classify.bias.clone();
        let mut average = Average::new(&mut net, 0.999);
        // The live network moves to a new value and stays: a plain reference of the update
        // a ← d·a + (1 − d)·p with d = min(0.999, (1 + n) / (10 + n)).
        net.classify.bias.iter_mut().for_each(|b| *b += 1.0);
        let mut reference: Vec<f64> = start.iter().map(|b| f64::from(*b)).collect();
        for n in 0..50u32 {
            let d = (f64::from(1 + n) / f64::from(10 + n)).min(0.999);
            assert!((f64::from(average.next_decay()) - d).abs() < 1e-6, "update {n}");
            average.update(&mut net);
            for (r, p) in reference.iter_mut().zip(&net.classify.bias) {
                *r = d * *r + (1.0 - d) * f64::from(*p);
            }
        }
        let index = average.values.len() - 1;
        for (got, want) in average.values[index].iter().zip(&reference) {
            assert!((f64::from(*got) - want).abs() < 1e-5, "{got} vs {want}");
        }
        // After 50 updates the start weighs Π d = 50!·9! / 59!, about 8·10⁻¹¹: a late start is forgotten.
        for ((got, s), p) in average.values[index].iter().zip(&start).zip(&net.classify.bias) {
            assert!((got - p).abs() < 0.01 * (p - s).abs(), "{got}: start {s}, live {p}");
        }
        let averaged = average.network(&net);
        assert_eq!(averaged.classify.bias, average.values[index]);
        assert_eq!(averaged.layers().count(), net.layers().count());
    }

    #[test]
    fn training_lowers_the_loss_on_a_tiny_set_and_resumes() {
        let (volumes, truth) = plane_volumes(16, 16, 12);
        let refs: Vec<&CostVolume<u8>> = volumes.iter().collect();
        let example = crop(&refs, &truth, (0, 0), (16, 16), 12);
        assert!(example.mask.iter().all(|m| *m));
        for architecture in Architecture::ALL {
            let mut net = Network::init_with(2, architecture, 3);
            let mut adam = Adam::new(&mut net, 1e-2);
            let mut average = Average::new(&mut net, 0.9);
            let mut losses = Vec::new();
            for _ in 0..30 {
                let (loss, _, gradients) = net
                    .loss_and_gradients(&example.inputs, &example.target, &example.mask)
                    .unwrap_or_else(|e| panic!("{e}"));
                adam.update(&mut net, &gradients);
                average.update(&mut net);
                losses.push(loss);
            }
            let first = losses[..3].iter().sum::<f32>() / 3.0;
            let last = losses[losses.len() - 3..].iter().sum::<f32>() / 3.0;
            assert!(
                last < 0.5 * first,
                "{architecture:?}: loss {first} → {last}: {losses:?}"
            );

            let dir =
                std::env::temp_dir().join(format!("mfusenet-ckpt-{}-{}", std::process::id(), architecture.name()));
            std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
            let path = dir.join("checkpoint.safetensors");
            let mut info = WeightsInfo::default();
            info.set("step", "30");
            save_checkpoint(&mut net, &adam, Some(&average), &info, &path).unwrap_or_else(|e| panic!("{e}"));
            let again = load_checkpoint(&path, 2).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(again.net, net);
            assert_eq!(again.adam, adam);
            assert_eq!(again.average.as_ref(), Some(&average));
            assert_eq!(again.info.get("step"), Some("30"));
            // The averaged network is not the last step's, and it fits the loss too.
            let averaged = average.network(&net);
            assert_ne!(averaged, net);
            let (loss, _, _) = averaged
                .clone()
                .loss_and_gradients(&example.inputs, &example.target, &example.mask)
                .unwrap_or_else(|e| panic!("{e}"));
            assert!(
                loss < 0.5 * first,
                "{architecture:?}: averaged loss {loss} vs first {first}"
            );
            // Saved without an average, the checkpoint has none (a run that keeps none).
            save_checkpoint(&mut net, &adam, None, &info, &path).unwrap_or_else(|e| panic!("{e}"));
            let bare = load_checkpoint(&path, 2).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(bare.average, None);
            assert_eq!(bare.net, net);
            std::fs::remove_dir_all(&dir).ok();
        }
    }

    #[test]
    fn an_unordered_flip_moves_every_volume_and_the_target_in_place_and_undoes_itself() {
        let input = |seed: u64| crate::nn::conv::tests::random([1, 4, 3, 5], seed);
        let example = Example {
            inputs: vec![input(1), input(2), input(3)],
            target: (0..15).map(|i| i as f32).collect(),
            mask: (0..15).map(|i| i % 4 != 0).collect(),
        };
        let mirror = flipped_unordered(&example, false, true);
        // Column x of row y comes from column 4 − x; the views keep their slots.
        for (got, original) in mirror.inputs.iter().zip(&example.inputs) {
            assert_eq!(got, &original.flipped(false, true));
        }
        assert_eq!(&mirror.target[..5], &[4.0, 3.0, 2.0, 1.0, 0.0]);
        // Row 1's mask (pixels 5..10: 8 is unlabelled) reversed.
        assert_eq!(&mirror.mask[5..10], &[true, false, true, true, true]);
        assert_ne!(mirror, example);
        for (vertical, horizontal) in [(true, false), (false, true), (true, true)] {
            let twice = flipped_unordered(&flipped_unordered(&example, vertical, horizontal), vertical, horizontal);
            assert_eq!(twice, example, "{vertical} {horizontal}");
        }
    }
}
