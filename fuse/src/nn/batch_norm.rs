//! BatchNorm3d (PyTorch semantics, batch 1): in train mode each channel is normalised with the
//! mean and biased variance of the batch and the running statistics move by `momentum` towards
//! the batch's (unbiased variance); in eval mode it is an affine map that
//! [`BatchNorm::fold_into`] merges into the preceding convolution.

use rayon::prelude::*;

use super::Tensor;

/// PyTorch's default ε.
pub const EPS: f32 = 1e-5;
/// PyTorch's default momentum.
pub const MOMENTUM: f32 = 0.1;

/// The parameters and running statistics of one BatchNorm3d.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchNorm {
    /// γ (`weight`).
    pub weight: Vec<f32>,
    /// β (`bias`).
    pub bias: Vec<f32>,
    /// Running mean.
    pub running_mean: Vec<f32>,
    /// Running variance.
    pub running_var: Vec<f32>,
    /// Train-mode passes seen.
    pub num_batches_tracked: i64,
    /// Weight of a batch's statistics in the running ones; `None` = the cumulative average of
    /// every batch since `num_batches_tracked` was 0 (PyTorch's `momentum=None`, used to
    /// recalibrate the statistics of a trained network).
    pub momentum: Option<f32>,
}

/// What the backward pass of a train-mode BatchNorm needs.
#[derive(Debug, Clone)]
pub struct BatchNormCache {
    /// The normalised input `(x − μ) / σ`.
    pub normalised: Tensor,
    /// `1 / σ` per channel.
    pub inv_std: Vec<f32>,
}

/// Gradients of a BatchNorm's parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchNormGrad {
    /// ∂L/∂γ.
    pub weight: Vec<f32>,
    /// ∂L/∂β.
    pub bias: Vec<f32>,
}

/// `Σ ∂y` and `Σ ∂y · x̂` over one channel (in f64): the β and γ gradients.
fn sums(grad: &[f32], normalised: &[f32]) -> (f64, f64) {
    grad.iter().zip(normalised).fold((0.0, 0.0), |(g, gx), (a, b)| {
        (g + f64::from(*a), gx + f64::from(*a) * f64::from(*b))
    })
}

impl BatchNorm {
    /// γ = 1, β = 0, running mean 0 and variance 1 (PyTorch's initialisation).
    pub fn new(channels: usize) -> Self {
        Self {
            weight: vec![1.0; channels],
            bias: vec![0.0; channels],
            running_mean: vec![0.0; channels],
            running_var: vec![1.0; channels],
            num_batches_tracked: 0,
            momentum: Some(MOMENTUM),
        }
    }

    /// Channels.
    pub fn channels(&self) -> usize {
        self.weight.len()
    }

    /// Train mode: normalises with the batch statistics, updates the running ones, and returns
    /// the output with the cache for [`BatchNorm::backward`].
    pub fn forward_train(&mut self, x: Tensor) -> (Tensor, BatchNormCache) {
        let n = x.channel_len();
        let mut normalised = x;
        let mut inv_std = Vec::with_capacity(self.channels());
        let mut out = Tensor::zeros(normalised.shape);
        let mut statistics = Vec::with_capacity(self.channels());
        for c in 0..self.channels() {
            let values = &mut normalised.data[c * n..(c + 1) * n];
            let (mean, var) = mean_and_variance(values);
            let inv = 1.0 / (var + f64::from(EPS)).sqrt();
            let (g, b) = (self.weight[c], self.bias[c]);
            for (v, o) in values.iter_mut().zip(&mut out.data[c * n..(c + 1) * n]) {
                *v = ((f64::from(*v) - mean) * inv) as f32;
                *o = *v * g + b;
            }
            inv_std.push(inv as f32);
            statistics.push((mean, var));
        }
        self.update_running(&statistics, n);
        (out, BatchNormCache { normalised, inv_std })
    }

    /// Moves the running statistics by `momentum` (or the cumulative average) towards a batch's
    /// per-channel `(mean, biased variance)` over `n` values; the variance is stored unbiased,
    /// as PyTorch does.
    fn update_running(&mut self, statistics: &[(f64, f64)], n: usize) {
        self.num_batches_tracked += 1;
        let momentum = self.momentum.unwrap_or(1.0 / self.num_batches_tracked as f32);
        for (c, &(mean, var)) in statistics.iter().enumerate() {
            let unbiased = if n > 1 { var * n as f64 / (n - 1) as f64 } else { var };
            self.running_mean[c] = (1.0 - momentum) * self.running_mean[c] + momentum * mean as f32;
            self.running_var[c] = (1.0 - momentum) * self.running_var[c] + momentum * unbiased as f32;
        }
    }

    /// Training with frozen statistics: normalises with the running statistics (as in eval
    /// mode) and leaves them unchanged; only γ and β learn. With batches as small as a CPU
    /// affords (one crop), batch statistics swing from crop to crop and a network trained on
    /// them fails with the running ones at inference; frozen statistics make training and
    /// inference compute the same function.
    pub fn forward_frozen(&self, x: Tensor) -> (Tensor, BatchNormCache) {
        let n = x.channel_len().max(1);
        let mut normalised = x;
        let mut out = Tensor::zeros(normalised.shape);
        let inv_std: Vec<f32> = (0..self.channels())
            .map(|c| 1.0 / (self.running_var[c] + EPS).sqrt())
            .collect();
        // Channels in parallel (each channel's arithmetic as it was: the same numbers).
        normalised
            .data
            .par_chunks_mut(n)
            .zip(out.data.par_chunks_mut(n))
            .enumerate()
            .for_each(|(c, (normalised, out))| {
                let (mean, inv, g, b) = (self.running_mean[c], inv_std[c], self.weight[c], self.bias[c]);
                for (v, o) in normalised.iter_mut().zip(out) {
                    *v = (*v - mean) * inv;
                    *o = *v * g + b;
                }
            });
        (out, BatchNormCache { normalised, inv_std })
    }

    /// Training with tracked statistics: normalises with the running statistics like
    /// [`BatchNorm::forward_frozen`] (the gradient is the frozen one, and training computes
    /// the function inference will), then moves them by `momentum` towards this pass's batch
    /// statistics (unbiased variance, as in train mode). With a small momentum the statistics
    /// are an average over the last few dozen crops: they follow the weights, so the
    /// activations stay normalised, and change little from one step to the next.
    pub fn forward_tracking(&mut self, x: Tensor) -> (Tensor, BatchNormCache) {
        let n = x.channel_len();
        let statistics: Vec<(f64, f64)> = (0..self.channels()).map(|c| mean_and_variance(x.channel(c))).collect();
        let out = self.forward_frozen(x);
        self.update_running(&statistics, n);
        out
    }

    /// Backward of [`BatchNorm::forward_frozen`]: `∂x = γ/σ · ∂y` and the γ, β gradients.
    pub fn backward_frozen(&self, grad: &Tensor, cache: &BatchNormCache) -> (Tensor, BatchNormGrad) {
        self.backward_with(grad, cache, |scale, _, _, g, _| (scale * f64::from(g)) as f32)
    }

    /// Train-mode backward: the input gradient and the parameter gradients from the output's.
    pub fn backward(&self, grad: &Tensor, cache: &BatchNormCache) -> (Tensor, BatchNormGrad) {
        let n = grad.channel_len() as f64;
        self.backward_with(grad, cache, |scale, sum_g, sum_gx, g, xhat| {
            (scale / n * (n * f64::from(g) - sum_g - f64::from(xhat) * sum_gx)) as f32
        })
    }

    /// The parameter gradients, and the input gradient from `input(γ/σ, Σ∂y, Σ∂y·x̂, ∂y, x̂)` per
    /// element of each channel.
    fn backward_with(
        &self,
        grad: &Tensor,
        cache: &BatchNormCache,
        input: impl Fn(f64, f64, f64, f32, f32) -> f32 + Sync,
    ) -> (Tensor, BatchNormGrad) {
        let n = grad.channel_len().max(1);
        let mut input_grad = Tensor::zeros(grad.shape);
        // Channels in parallel (each channel's sums and arithmetic as they were).
        let sums: Vec<(f64, f64)> = input_grad
            .data
            .par_chunks_mut(n)
            .zip(grad.data.par_chunks(n))
            .zip(cache.normalised.data.par_chunks(n))
            .enumerate()
            .map(|(c, ((out, g), xhat))| {
                let (sum_g, sum_gx) = sums(g, xhat);
                let scale = f64::from(self.weight[c]) * f64::from(cache.inv_std[c]);
                for ((out, gv), xv) in out.iter_mut().zip(g).zip(xhat) {
                    *out = input(scale, sum_g, sum_gx, *gv, *xv);
                }
                (sum_g, sum_gx)
            })
            .collect();
        (
            input_grad,
            BatchNormGrad {
                weight: sums.iter().map(|(_, sum_gx)| *sum_gx as f32).collect(),
                bias: sums.iter().map(|(sum_g, _)| *sum_g as f32).collect(),
            },
        )
    }

    /// Eval mode folded into the convolution before it (`weight` `[cout][…]`, no bias): returns
    /// the scaled weights and the bias `β − μ·γ/σ`.
    pub fn fold_into(&self, weight: &[f32]) -> (Vec<f32>, Vec<f32>) {
        let per_channel = weight.len() / self.channels().max(1);
        let mut folded = weight.to_vec();
        let mut bias = Vec::with_capacity(self.channels());
        for c in 0..self.channels() {
            let scale = self.weight[c] / (self.running_var[c] + EPS).sqrt();
            for w in &mut folded[c * per_channel..(c + 1) * per_channel] {
                *w *= scale;
            }
            bias.push(self.bias[c] - self.running_mean[c] * scale);
        }
        (folded, bias)
    }

    /// Eval mode on a tensor (for tests and the transposed convolutions, whose channels are the
    /// weight's second axis): `γ·(x − μ)/σ + β`.
    pub fn forward_eval(&self, mut x: Tensor) -> Tensor {
        let n = x.channel_len();
        for c in 0..self.channels() {
            let scale = self.weight[c] / (self.running_var[c] + EPS).sqrt();
            let shift = self.bias[c] - self.running_mean[c] * scale;
            for v in &mut x.data[c * n..(c + 1) * n] {
                *v = *v * scale + shift;
            }
        }
        x
    }
}

/// Mean and biased variance of one channel's values, accumulated in f64.
fn mean_and_variance(values: &[f32]) -> (f64, f64) {
    let n = values.len().max(1) as f64;
    let mean = values.iter().map(|v| f64::from(*v)).sum::<f64>() / n;
    let var = values.iter().map(|v| (f64::from(*v) - mean).powi(2)).sum::<f64>() / n;
    (mean, var)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::conv::tests::{random, random_values};

    #[test]
    fn backward_matches_finite_differences() {
        let x = random([2, 3, 4, 5], 1);
        let upstream = random(x.shape, 2);
        let mut bn = BatchNorm::new(2);
        bn.weight = vec![1.5, -0.7];
        bn.bias = vec![0.2, 0.1];
        // Loss = <upstream, bn(x)>.
        let loss = |bn: &BatchNorm, x: &Tensor| -> f64 {
            let mut copy = bn.clone();
            let (y, _) = copy.forward_train(x.clone());
            y.data
                .iter()
                .zip(&upstream.data)
                .map(|(a, b)| f64::from(*a) * f64::from(*b))
                .sum()
        };
        let (_, cache) = bn.clone().forward_train(x.clone());
        let (dx, dparams) = bn.backward(&upstream, &cache);
        let h = 1e-2f32;
        for i in [0, 7, 33, 59, 100] {
            let (mut plus, mut minus) = (x.clone(), x.clone());
            plus.data[i] += h;
            minus.data[i] -= h;
            let numeric = (loss(&bn, &plus) - loss(&bn, &minus)) / (2.0 * f64::from(h));
            assert!(
                (numeric - f64::from(dx.data[i])).abs() < 2e-3,
                "dx[{i}] {numeric} vs {}",
                dx.data[i]
            );
        }
        for c in 0..2 {
            let (mut plus, mut minus) = (bn.clone(), bn.clone());
            plus.weight[c] += h;
            minus.weight[c] -= h;
            let numeric = (loss(&plus, &x) - loss(&minus, &x)) / (2.0 * f64::from(h));
            assert!((numeric - f64::from(dparams.weight[c])).abs() < 2e-3, "dγ {numeric}");
        }
        // Folding equals eval mode after the convolution.
        let w = random_values(2 * 3, 3);
        let (folded, bias) = bn.fold_into(&w);
        assert!((folded[4] - w[4] * bn.weight[1] / (1.0 + EPS).sqrt()).abs() < 1e-6);
        assert!((bias[0] - 0.2).abs() < 1e-6);
    }

    #[test]
    fn tracking_normalises_with_the_running_statistics_and_moves_them_like_train_mode() {
        let x = random([2, 3, 4, 5], 6);
        let mut bn = BatchNorm::new(2);
        bn.running_mean = vec![0.4, -0.3];
        bn.running_var = vec![2.0, 0.5];
        bn.weight = vec![1.5, -0.7];
        bn.momentum = Some(0.25);
        let (frozen, _) = bn.forward_frozen(x.clone());
        let mut trained = bn.clone();
        trained.forward_train(x.clone());
        let mut tracked = bn.clone();
        let (y, _) = tracked.forward_tracking(x.clone());
        // The output is the frozen one (the statistics before this pass) ...
        assert_eq!(y.data, frozen.data);
        // ... and the statistics moved a quarter of the way to the batch's, as train mode moves them.
        for c in 0..2 {
            assert!((tracked.running_mean[c] - trained.running_mean[c]).abs() < 1e-6);
            assert!((tracked.running_var[c] - trained.running_var[c]).abs() < 1e-6);
            assert!(
                (tracked.running_mean[c] - bn.running_mean[c]).abs() > 1e-3,
                "the mean did not move"
            );
        }
        assert_eq!(tracked.num_batches_tracked, 1);
    }
}
