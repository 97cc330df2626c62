//! MFuseNet's network (paper, section IV; the authors' `FuseNetwork` in `weihaosky/MFuseNet`,
//! `network.py`, MIT), layer for layer and with PyTorch's parameter names:
//!
//! ```text
//! per view i:  [1, D, H, W] ─ feature (shared): convbn 1→4 k7, 4→4 k5, 4→4 k5, 4→4 k3, ReLU each
//! concat:      [4N, D, H, W] ─ convbn 4N→4 k7, ReLU                                   = c
//!   (pooled, N = 0: [8, D, H, W] = the views' mean and maximum, `nn::pool`, for any number)
//! down1:       c      ─ convbn k3 stride 2, ReLU                                      = d1   (½)
//! dconv1:      cdown1 = ReLU(convbn k3 (d1)) + d1
//! down2:       cdown1 ─ convbn k3 stride 2, ReLU                                      = d2   (¼)
//! dconv21/22:  e1 = ReLU(convbn k7 (d2)) + d2;  cdown2 = ReLU(convbn k3 (e1)) + e1
//! up1, uconv1: cup1 = ReLU(convbn 8→4 k3 ([ReLU(convTbn (cdown2)), cdown1]))         (½)
//! up2, uconv2: cup2 = ReLU(convbn 8→4 k7 ([ReLU(convTbn (cup1)), c]))                (1)
//! distill1:    f = ReLU(convbn k5 (cup2)) + cup2
//! classify:    logits = conv 4→1 k3 + bias;  disparity = Σ_d d · softmax_d(logits)
//! ```
//!
//! [`Architecture::Lite`] keeps every layer, channel count and name but shrinks the kernels
//! that cost the most per voxel at full resolution (about 11 k multiply-adds per voxel with four
//! views against the paper's 58 k): feature 1→4 k5, 4→4 k3 (three times), `concat` k3, `uconv2`
//! k3, `distill1` k3; `dconv21` keeps k7 at a quarter of the size, where it is cheap.
//!
//! D, H and W must be multiples of 4 here ([`super::infer`] pads and crops). Eval mode folds
//! every BatchNorm into its convolution; train mode keeps what the backward pass needs.

use super::Error;
use crate::nn::Tensor;
use crate::nn::batch_norm::{BatchNorm, BatchNormCache};
use crate::nn::conv::{
    ConvInput, Epilogue, PaddedTensor, conv3d_accumulate_input, conv3d_input, conv3d_padded, conv3d_padded_pairs,
    conv3d_same, conv3d_same_input_grad, conv3d_same_weight_grad, conv3d_with, input_channels, transposed_as_conv,
    transposed_weight_grad,
};
use crate::nn::regression::{smooth_l1, soft_argmin, soft_argmin_backward};
use crate::nn::transposed::transposed_conv3d_eval;

/// How the BatchNorms behave in a training pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BatchNormMode {
    /// PyTorch's train mode: batch statistics, running statistics updated.
    #[default]
    Batch,
    /// Running statistics, frozen (see [`BatchNorm::forward_frozen`]); only γ and β learn.
    Frozen,
    /// Running statistics in the forward pass (the frozen gradient), then moved by each
    /// BatchNorm's `momentum` towards the pass's batch statistics (see
    /// [`BatchNorm::forward_tracking`]).
    Tracking,
}

/// How a convolution samples its input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvKind {
    /// Stride 1, padding `k / 2`.
    Same,
    /// Kernel 3, stride 2, padding 1 (half the size).
    Down,
    /// Transposed: kernel 3, stride 2, padding 1, output padding 1 (twice the size); weight
    /// `[cin][cout][3][3][3]`.
    Up,
}

/// The kernel sizes of the network's layers (channels, names and connections are the same).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Architecture {
    /// The paper's: feature k7, k5, k5, k3; `concat` k7; `dconv21` k7; `uconv2` k7; `distill1` k5.
    #[default]
    Paper,
    /// About a fifth of the paper's work per voxel: feature k5, k3, k3, k3; `concat` k3;
    /// `dconv21` k7 (a quarter of the size); `uconv2` k3; `distill1` k3.
    Lite,
}

impl Architecture {
    /// Both, the paper's first.
    pub const ALL: [Architecture; 2] = [Architecture::Paper, Architecture::Lite];

    /// `paper` or `lite` (the weights' metadata value and the command-line word).
    pub fn name(self) -> &'static str {
        match self {
            Architecture::Paper => "paper",
            Architecture::Lite => "lite",
        }
    }

    /// The architecture named `name` ([`Self::name`]).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|a| a.name() == name)
    }

    /// Kernel sizes of `feature.0`, `.2`, `.4`, `.6`.
    const fn feature_kernels(self) -> [usize; 4] {
        match self {
            Architecture::Paper => [7, 5, 5, 3],
            Architecture::Lite => [5, 3, 3, 3],
        }
    }

    /// Kernel sizes of `concat`, `dconv21`, `uconv2` and `distill1` (the other layers are k3).
    const fn fuse_kernels(self) -> [usize; 4] {
        match self {
            Architecture::Paper => [7, 7, 7, 5],
            Architecture::Lite => [3, 7, 3, 3],
        }
    }

    /// Kernel size of `concat` (how a weights file without metadata tells the two apart).
    pub fn concat_kernel(self) -> usize {
        self.fuse_kernels()[0]
    }

    /// The receptive radius (px, in H and W) of the last full-resolution layers together:
    /// `uconv2`, `distill1` and `classify` (k3: 1); 6 for the paper's (3 + 2 + 1).
    pub const fn last_layers_radius(self) -> usize {
        let [_, _, uconv2, distill1] = self.fuse_kernels();
        uconv2 / 2 + distill1 / 2 + 1
    }

    /// The receptive radius (px, in H and W) of a logit: how far an input voxel can change it.
    /// The longest path runs through the quarter-size level: the feature tower and `concat`,
    /// `down1` and `dconv1` (± 1 px and ± 2 px at half size), `down2` (± 2 px), `dconv21` and
    /// `dconv22` at a quarter (± 4 px per tap), back up through `up1` (± 2 px), `uconv1` (± 2 px)
    /// and `up2` (± 1 px), then the last layers. 43 for the paper's kernels, 35 for the lite
    /// ones: what an impulse reaches at any phase of the quarter-size grid (test).
    pub const fn receptive_radius(self) -> usize {
        let [f0, f2, f4, f6] = self.feature_kernels();
        let tower = f0 / 2 + f2 / 2 + f4 / 2 + f6 / 2;
        let [concat, dconv21, ..] = self.fuse_kernels();
        let u_net = 1 + 2 + 2 + 4 * (dconv21 / 2) + 4 + 2 + 2 + 1;
        tower + concat / 2 + u_net + self.last_layers_radius()
    }

    /// Pixels of context around each inference tile: the receptive radius rounded up to a
    /// multiple of 4, so that every tile's stride-2 grids are the whole image's: 44 for the
    /// paper's kernels, 36 for the lite ones.
    pub const fn halo(self) -> usize {
        self.receptive_radius().div_ceil(4) * 4
    }
}

/// `convbn3d` / `convTbn3d` of the reference: a convolution without bias and a BatchNorm3d
/// (`<name>.0.weight`, `<name>.1.*`), followed in this network by a ReLU.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvBn {
    /// PyTorch module path (`feature.0`, `concat`, `up1`, …).
    pub name: String,
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Kernel size.
    pub k: usize,
    /// Sampling.
    pub kind: ConvKind,
    /// Weights, `[cout][cin][k³]` (`[cin][cout][k³]` for [`ConvKind::Up`]).
    pub weight: Vec<f32>,
    /// The BatchNorm after it.
    pub bn: BatchNorm,
}

/// What [`ConvBn::backward`] needs from the train-mode forward pass.
#[derive(Debug, Clone)]
pub struct ConvBnCache {
    /// The input of the stride-1 convolution (zero-upsampled for [`ConvKind::Up`]).
    input: Tensor,
    /// Spatial size of the layer's real input.
    input_spatial: [usize; 3],
    bn: BatchNormCache,
    /// Which BatchNorm pass made it.
    mode: BatchNormMode,
    /// The output after the ReLU (its sign is the ReLU's mask).
    output: Tensor,
}

/// Gradients of one [`ConvBn`].
#[derive(Debug, Clone, PartialEq)]
pub struct ConvBnGrad {
    /// ∂L/∂weight (the weight's layout).
    pub weight: Vec<f32>,
    /// ∂L/∂γ.
    pub bn_weight: Vec<f32>,
    /// ∂L/∂β.
    pub bn_bias: Vec<f32>,
}

impl ConvBnGrad {
    fn add(&mut self, other: &ConvBnGrad) {
        for (a, b) in [
            (&mut self.weight, &other.weight),
            (&mut self.bn_weight, &other.bn_weight),
            (&mut self.bn_bias, &other.bn_bias),
        ] {
            for (x, y) in a.iter_mut().zip(b) {
                *x += y;
            }
        }
    }
}

impl ConvBn {
    /// A layer with zero weights and a fresh BatchNorm.
    pub fn new(name: &str, cin: usize, cout: usize, k: usize, kind: ConvKind) -> Self {
        Self {
            name: name.to_owned(),
            cin,
            cout,
            k,
            kind,
            weight: vec![0.0; cin * cout * k * k * k],
            bn: BatchNorm::new(cout),
        }
    }

    /// PyTorch's shape of the weight.
    pub fn weight_shape(&self) -> [usize; 5] {
        match self.kind {
            ConvKind::Up => [self.cin, self.cout, self.k, self.k, self.k],
            _ => [self.cout, self.cin, self.k, self.k, self.k],
        }
    }

    /// The weights of the equivalent stride-1 convolution (`[cout][cin][k³]`).
    fn conv_weight(&self) -> Vec<f32> {
        match self.kind {
            ConvKind::Up => transposed_as_conv(&self.weight, self.cin, self.cout),
            _ => self.weight.clone(),
        }
    }

    /// The input of the stride-1 convolution.
    fn conv_input(&self, x: &Tensor) -> Tensor {
        match self.kind {
            ConvKind::Up => x.upsample2_zeros([2 * x.shape[1], 2 * x.shape[2], 2 * x.shape[3]]),
            _ => x.clone(),
        }
    }

    fn sample(&self, z: Tensor) -> Tensor {
        match self.kind {
            ConvKind::Down => z.subsample2(),
            _ => z,
        }
    }

    /// Eval mode: `ReLU(BN(conv(x)))` with the BatchNorm folded into the convolution.
    pub fn forward_eval(&self, x: &Tensor) -> Tensor {
        let (weight, bias) = self.bn.fold_into(&self.conv_weight());
        // The ReLU and the stride-2 sampling as the outputs are written (only the kept planes and
        // rows computed).
        let epilogue = |stride| Epilogue { stride, relu: true };
        match self.kind {
            // By output parity: no zero-upsampled copy, an eighth of the products.
            ConvKind::Up if self.k == 3 => transposed_conv3d_eval(x, &weight, self.cout, Some(&bias), true),
            ConvKind::Up => conv3d_with(
                &self.conv_input(x),
                &weight,
                self.cout,
                self.k,
                Some(&bias),
                epilogue(1),
            ),
            ConvKind::Down => conv3d_with(x, &weight, self.cout, self.k, Some(&bias), epilogue(2)),
            // No copy of the input: the convolution pads its own.
            ConvKind::Same => conv3d_with(x, &weight, self.cout, self.k, Some(&bias), epilogue(1)),
        }
    }

    /// [`ConvBn::forward_eval`] of an input it is handed: a "same" layer frees it as soon as its
    /// padded copy is made, so that input and output are never alive together with that copy.
    pub fn forward_eval_owned(&self, x: Tensor) -> Tensor {
        if self.kind != ConvKind::Same {
            return self.forward_eval(&x);
        }
        let (weight, bias) = self.bn.fold_into(&self.conv_weight());
        let epilogue = Epilogue { stride: 1, relu: true };
        conv3d_input(ConvInput::Owned(x), &weight, self.cout, self.k, Some(&bias), epilogue)
    }

    /// [`ConvBn::forward_eval`] of any input, written straight into the padded tiles that a layer
    /// with kernel `next_k` reads (a chain of "same" layers: each skips the padded copy of its
    /// input). Other kinds compute their tensor and pad it. With `pairs`, as the bfloat16
    /// channel pairs of a next layer that pairs channels ([`conv3d_padded_pairs`]): only for a
    /// layer's input.
    pub fn forward_eval_padded(&self, x: ConvInput<'_>, next_k: usize, pairs: bool) -> PaddedTensor {
        if self.kind != ConvKind::Same {
            let y = match x {
                ConvInput::Borrowed(x) => self.forward_eval(x),
                ConvInput::Owned(x) => self.forward_eval(&x),
                ConvInput::Padded(x) => self.forward_eval(&x.to_tensor()),
                ConvInput::Window(x, rows, columns) => self.forward_eval(&x.crop_hw(rows, columns)),
            };
            return PaddedTensor::of(&y, next_k);
        }
        let (weight, bias) = self.bn.fold_into(&self.conv_weight());
        if pairs {
            conv3d_padded_pairs(x, &weight, self.cout, self.k, Some(&bias), true, next_k)
        } else {
            conv3d_padded(x, &weight, self.cout, self.k, Some(&bias), true, next_k)
        }
    }

    /// Train mode: `ReLU(BN(conv(x)))` with batch statistics (running statistics updated) or
    /// frozen ones.
    pub fn forward_train(&mut self, x: &Tensor, mode: BatchNormMode) -> (Tensor, ConvBnCache) {
        let input = self.conv_input(x);
        let z = self.sample(conv3d_same(&input, &self.conv_weight(), self.cout, self.k, None));
        let (y, bn) = match mode {
            BatchNormMode::Batch => self.bn.forward_train(z),
            BatchNormMode::Frozen => self.bn.forward_frozen(z),
            BatchNormMode::Tracking => self.bn.forward_tracking(z),
        };
        let output = y.relu();
        let cache = ConvBnCache {
            input,
            input_spatial: [x.shape[1], x.shape[2], x.shape[3]],
            bn,
            mode,
            output: output.clone(),
        };
        (output, cache)
    }

    /// Backward of [`ConvBn::forward_train`]: the input gradient (skipped when `need_input` is
    /// false, for the first layer) and the parameter gradients.
    pub fn backward(&self, grad: &Tensor, cache: &ConvBnCache, need_input: bool) -> (Option<Tensor>, ConvBnGrad) {
        let mut g = grad.clone();
        for (v, y) in g.data.iter_mut().zip(&cache.output.data) {
            if *y <= 0.0 {
                *v = 0.0;
            }
        }
        let (gz, bn_grad) = match cache.mode {
            BatchNormMode::Batch => self.bn.backward(&g, &cache.bn),
            BatchNormMode::Frozen | BatchNormMode::Tracking => self.bn.backward_frozen(&g, &cache.bn),
        };
        let gz = match self.kind {
            ConvKind::Down => gz.upsample2_zeros(cache.input_spatial),
            _ => gz,
        };
        let conv_weight_grad = conv3d_same_weight_grad(&cache.input, &gz, self.k);
        let weight = match self.kind {
            ConvKind::Up => transposed_weight_grad(&conv_weight_grad, self.cin, self.cout),
            _ => conv_weight_grad,
        };
        let input_grad = need_input.then(|| {
            let gi = conv3d_same_input_grad(&gz, &self.conv_weight(), self.cin, self.k);
            match self.kind {
                ConvKind::Up => gi.subsample2(),
                _ => gi,
            }
        });
        (
            input_grad,
            ConvBnGrad {
                weight,
                bn_weight: bn_grad.weight,
                bn_bias: bn_grad.bias,
            },
        )
    }
}

/// The final `Conv3d(4, 1, 3, padding=1)` with bias.
#[derive(Debug, Clone, PartialEq)]
pub struct Classify {
    /// `[1][4][3][3][3]`.
    pub weight: Vec<f32>,
    /// `[1]`.
    pub bias: Vec<f32>,
}

/// The whole network for `views` cost volumes.
#[derive(Debug, Clone, PartialEq)]
pub struct Network {
    /// Number of cost volumes N (1, 2 or 4), or 0: any number, their features pooled by mean and
    /// maximum ([`crate::nn::pool`]) instead of concatenated, so that `concat` reads 8 channels
    /// whatever the count and the order of the views (see [`Network::pooled`]).
    pub views: usize,
    /// The layers' kernel sizes.
    pub architecture: Architecture,
    /// Each view also brings a sharp volume (its per-pixel costs, no block sums, no SGM: what
    /// keeps 1–6 px parts and the gaps between them) straight into `concat`, beside its four
    /// feature channels: inputs `N + i` beside the views' `i`, five `concat` channels a view.
    /// Fixed networks only; [`Network::sharpened`] makes one from a fixed network.
    pub sharp: bool,
    /// `feature.0`, `feature.2`, `feature.4`, `feature.6` (shared by the views).
    pub feature: Vec<ConvBn>,
    /// `concat`, `down1`, `dconv1`, `down2`, `dconv21`, `dconv22`, `up1`, `uconv1`, `up2`,
    /// `uconv2`, `distill1`, in this order.
    pub fuse: Vec<ConvBn>,
    /// `classify`.
    pub classify: Classify,
}

/// Input channels of `concat`: four per view (five with a sharp volume), or the pooled mean and
/// maximum (views = 0).
fn concat_channels(views: usize, sharp: bool) -> usize {
    match (views, sharp) {
        (0, _) => 8,
        (_, false) => 4 * views,
        (_, true) => 5 * views,
    }
}

/// Feature channels a view gives `concat` (its sharp volume's channel follows them).
const VIEW_FEATURES: usize = 4;

/// Indices into [`Network::fuse`].
const CONCAT: usize = 0;
const DOWN1: usize = 1;
const DCONV1: usize = 2;
const DOWN2: usize = 3;
const DCONV21: usize = 4;
const DCONV22: usize = 5;
const UP1: usize = 6;
const UCONV1: usize = 7;
const UP2: usize = 8;
const UCONV2: usize = 9;
const DISTILL1: usize = 10;

/// What the backward pass needs from a train-mode forward pass.
pub struct Tape {
    feature: Vec<Vec<ConvBnCache>>,
    /// A pooled network's maximum: which view gave each value ([`crate::nn::pool`]).
    argmax: Option<Vec<u16>>,
    fuse: Vec<ConvBnCache>,
    /// Input of `classify`.
    head_input: Tensor,
    probabilities: Tensor,
    /// The predicted disparity (`[H·W]`).
    pub disparity: Vec<f32>,
}

/// Gradients of every trainable parameter, in [`Network::parameters_mut`] order.
#[derive(Debug, Clone, PartialEq)]
pub struct Gradients {
    /// `(PyTorch name, gradient)`.
    pub tensors: Vec<(String, Vec<f32>)>,
}

impl Network {
    /// The paper's architecture with zero weights and fresh BatchNorms.
    pub fn zeros(views: usize) -> Self {
        Self::zeros_with(views, Architecture::Paper)
    }

    /// An architecture with zero weights and fresh BatchNorms.
    pub fn zeros_with(views: usize, architecture: Architecture) -> Self {
        use ConvKind::{Down, Same, Up};
        let [f0, f2, f4, f6] = architecture.feature_kernels();
        let [concat, dconv21, uconv2, distill1] = architecture.fuse_kernels();
        let feature = vec![
            ConvBn::new("feature.0", 1, 4, f0, Same),
            ConvBn::new("feature.2", 4, 4, f2, Same),
            ConvBn::new("feature.4", 4, 4, f4, Same),
            ConvBn::new("feature.6", 4, 4, f6, Same),
        ];
        let fuse = vec![
            ConvBn::new("concat", concat_channels(views, false), 4, concat, Same),
            ConvBn::new("down1", 4, 4, 3, Down),
            ConvBn::new("dconv1", 4, 4, 3, Same),
            ConvBn::new("down2", 4, 4, 3, Down),
            ConvBn::new("dconv21", 4, 4, dconv21, Same),
            ConvBn::new("dconv22", 4, 4, 3, Same),
            ConvBn::new("up1", 4, 4, 3, Up),
            ConvBn::new("uconv1", 8, 4, 3, Same),
            ConvBn::new("up2", 4, 4, 3, Up),
            ConvBn::new("uconv2", 8, 4, uconv2, Same),
            ConvBn::new("distill1", 4, 4, distill1, Same),
        ];
        Self {
            views,
            architecture,
            sharp: false,
            feature,
            fuse,
            classify: Classify {
                weight: vec![0.0; 4 * 27],
                bias: vec![0.0],
            },
        }
    }

    /// The view-count-agnostic architecture (`views` = 0) with zero weights: any number of cost
    /// volumes, their features pooled by mean and maximum before `concat`.
    pub fn pooled() -> Self {
        Self::zeros(0)
    }

    /// A view-count-agnostic network started from a fixed one: every layer copied, `concat`'s
    /// weights for the features' mean the sum of the fixed network's per-view weights and those
    /// for their maximum zero, so that where every view's features are the same it computes what
    /// the fixed network computes (a start for fine-tuning on varied view counts).
    pub fn pooled_from(fixed: &Network) -> Self {
        let mut net = fixed.clone();
        net.views = 0;
        if fixed.views == 0 {
            return net;
        }
        let source = &fixed.fuse[CONCAT];
        let k3 = source.k * source.k * source.k;
        let mut concat = ConvBn::new(
            "concat",
            concat_channels(0, false),
            source.cout,
            source.k,
            ConvKind::Same,
        );
        concat.bn = source.bn.clone();
        for o in 0..source.cout {
            for v in 0..fixed.views {
                for i in 0..4 {
                    let from = &source.weight[(o * source.cin + v * 4 + i) * k3..][..k3];
                    let to = &mut concat.weight[(o * 8 + i) * k3..][..k3];
                    for (t, f) in to.iter_mut().zip(from) {
                        *t += f;
                    }
                }
            }
        }
        net.fuse[CONCAT] = concat;
        net
    }

    /// A fixed network (N views) that also takes each view's sharp volume ([`Network::sharp`]):
    /// every layer copied, `concat` widened to five channels a view with zero weights for the
    /// sharp ones, so that it computes what the fixed network computes whatever the sharp
    /// volumes hold (a start for fine-tuning). `None` for a pooled network; a sharp one is
    /// returned as it is.
    pub fn sharpened(&self) -> Option<Self> {
        if self.views == 0 {
            return None;
        }
        let mut net = self.clone();
        if self.sharp {
            return Some(net);
        }
        net.sharp = true;
        let source = &self.fuse[CONCAT];
        let k3 = source.k * source.k * source.k;
        let cin = concat_channels(self.views, true);
        let mut concat = ConvBn::new("concat", cin, source.cout, source.k, ConvKind::Same);
        concat.bn = source.bn.clone();
        for o in 0..source.cout {
            for v in 0..self.views {
                let from = &source.weight[(o * source.cin + v * VIEW_FEATURES) * k3..][..VIEW_FEATURES * k3];
                concat.weight[(o * cin + v * (VIEW_FEATURES + 1)) * k3..][..VIEW_FEATURES * k3].copy_from_slice(from);
            }
        }
        net.fuse[CONCAT] = concat;
        Some(net)
    }

    /// Inputs a pass of a fixed network takes: the views' volumes, and as many sharp volumes
    /// after them (0 for the pooled network, which takes any number).
    pub fn input_count(&self) -> usize {
        if self.sharp { 2 * self.views } else { self.views }
    }

    /// PyTorch's default initialisation (`kaiming_uniform_(a=√5)`: U(±1/√fan_in) for weights and
    /// the classifier's bias; γ = 1, β = 0), from a seed.
    pub fn init(views: usize, seed: u64) -> Self {
        Self::init_with(views, Architecture::Paper, seed)
    }

    /// [`Self::init`] for an architecture.
    pub fn init_with(views: usize, architecture: Architecture, seed: u64) -> Self {
        let mut net = Self::zeros_with(views, architecture);
        let mut rng = crate::rng::SplitMix64::new(seed);
        for layer in net.feature.iter_mut().chain(net.fuse.iter_mut()) {
            // PyTorch's fan_in is weight.size(1)·k³: cin for convolutions, cout for transposed.
            let [_, fan, k, ..] = layer.weight_shape();
            let bound = 1.0 / ((fan * k * k * k) as f32).sqrt();
            for w in &mut layer.weight {
                *w = rng.uniform_f32(-bound, bound);
            }
        }
        let bound = 1.0 / ((4 * 27) as f32).sqrt();
        for w in net.classify.weight.iter_mut().chain(net.classify.bias.iter_mut()) {
            *w = rng.uniform_f32(-bound, bound);
        }
        net
    }

    /// Every layer with a BatchNorm, feature tower first.
    pub fn layers(&self) -> impl Iterator<Item = &ConvBn> {
        self.feature.iter().chain(self.fuse.iter())
    }

    /// Mutable [`Network::layers`].
    pub fn layers_mut(&mut self) -> impl Iterator<Item = &mut ConvBn> {
        self.feature.iter_mut().chain(self.fuse.iter_mut())
    }

    /// Trainable parameters with their PyTorch names: per layer `<name>.0.weight`,
    /// `<name>.1.weight`, `<name>.1.bias`; then `classify.weight`, `classify.bias`.
    pub fn parameters_mut(&mut self) -> Vec<(String, &mut Vec<f32>)> {
        let mut out = Vec::new();
        for layer in self.feature.iter_mut().chain(self.fuse.iter_mut()) {
            let name = layer.name.clone();
            out.push((format!("{name}.0.weight"), &mut layer.weight));
            out.push((format!("{name}.1.weight"), &mut layer.bn.weight));
            out.push((format!("{name}.1.bias"), &mut layer.bn.bias));
        }
        out.push(("classify.weight".to_owned(), &mut self.classify.weight));
        out.push(("classify.bias".to_owned(), &mut self.classify.bias));
        out
    }

    /// Number of trainable values (convolution weights, BatchNorm γ and β, classifier bias):
    /// 33,441 / 38,929 / 49,905 for N = 1 / 2 / 4, as the reference; 38,929 pooled (N = 0).
    pub fn parameter_count(&self) -> usize {
        self.layers()
            .map(|l| l.weight.len() + 2 * l.bn.channels())
            .sum::<usize>()
            + self.classify.weight.len()
            + self.classify.bias.len()
    }

    fn check_inputs(&self, inputs: &[Tensor]) -> Result<[usize; 3], Error> {
        self.check_input_shapes(inputs.iter().map(|t| t.shape))
    }

    /// [`Network::check_inputs`] of inputs of these shapes.
    fn check_input_shapes(&self, shapes: impl ExactSizeIterator<Item = [usize; 4]>) -> Result<[usize; 3], Error> {
        let count = shapes.len();
        let count_ok = if self.views == 0 {
            (1..=crate::nn::pool::MAX_VIEWS).contains(&count)
        } else {
            count == self.input_count()
        };
        if !count_ok {
            return Err(Error::InputCount {
                expected: self.input_count(),
                got: count,
            });
        }
        let mut first = None;
        for shape in shapes {
            let [c, d, h, w] = shape;
            if *first.get_or_insert(shape) != shape
                || c != 1
                || d % 4 != 0
                || h % 4 != 0
                || w % 4 != 0
                || d * h * w == 0
            {
                return Err(Error::InputShape { shape });
            }
        }
        let [_, d, h, w] = first.unwrap_or_default();
        Ok([d, h, w])
    }

    /// Eval-mode logits `[1, D, H, W]` of `views` cost volumes `[1, D, H, W]` (D, H, W multiples
    /// of 4), freeing each intermediate as soon as it is used.
    pub fn logits(&self, inputs: &[Tensor]) -> Result<Tensor, Error> {
        let [_, _, h, w] = inputs.first().map_or([0; 4], |t| t.shape);
        self.logits_within(inputs, &(0..h, 0..w)).map(|(logits, _)| logits)
    }

    /// [`Network::logits`] where only the rows and columns `keep` are wanted: the last
    /// full-resolution layers (`uconv2`, `distill1`, `classify`, whose receptive radius together
    /// is [`Architecture::last_layers_radius`] px) run on `keep` widened by that radius only, not on the whole
    /// input (which the U-Net's coarse levels need). The logits of `keep` equal
    /// [`Network::logits`]'s; returned with those of the margin around it, and the margin's
    /// first row and column: `(logits [1, D, rows, columns], (row, column))`.
    pub fn logits_within(
        &self,
        inputs: &[Tensor],
        keep: &(std::ops::Range<usize>, std::ops::Range<usize>),
    ) -> Result<(Tensor, (usize, usize)), Error> {
        self.check_inputs(inputs)?;
        self.logits_of(Inputs::Given(inputs), keep)
    }

    /// [`Network::logits_within`] of `count` inputs of `shape` that `make(i)` makes when the
    /// pass reaches view `i`'s feature tower, each freed after it: a pass holds one view's input
    /// at a time (inference's tiles, where the inputs were a fifth of the peak memory).
    pub fn logits_within_made(
        &self,
        (count, shape): (usize, [usize; 4]),
        make: &dyn Fn(usize) -> Tensor,
        keep: &(std::ops::Range<usize>, std::ops::Range<usize>),
    ) -> Result<(Tensor, (usize, usize)), Error> {
        self.check_input_shapes(std::iter::repeat_n(shape, count))?;
        self.logits_of(Inputs::Made { count, shape, make }, keep)
    }

    /// [`Network::logits_within`] of checked inputs.
    fn logits_of(
        &self,
        inputs: Inputs<'_>,
        keep: &(std::ops::Range<usize>, std::ops::Range<usize>),
    ) -> Result<(Tensor, (usize, usize)), Error> {
        let [_, d, h, w] = inputs.shape();
        // The feature tower, each layer writing the next one's padded tiles (the last one's for
        // `concat`), so that no layer copies its input.
        let concat_k = self.fuse[CONCAT].k;
        // Every layer's output is a convolution's input, in bfloat16 channel pairs where that
        // layer pairs channels, but for the last one's when the views' features are pooled
        // (values then).
        let last = self.feature.len().saturating_sub(1);
        let pairs = |i: usize| i < last || self.views != 0;
        let tower = |x: &Tensor| -> PaddedTensor {
            let next_k = |i: usize| self.feature.get(i + 1).map_or(concat_k, |l| l.k);
            let mut y = self.feature[0].forward_eval_padded(ConvInput::Borrowed(x), next_k(0), pairs(0));
            for (i, layer) in self.feature.iter().enumerate().skip(1) {
                y = layer.forward_eval_padded(ConvInput::Padded(y), next_k(i), pairs(i));
            }
            y
        };
        let c = if self.views == 0 {
            // The views' mean and maximum pooled as each view's features come out of the tower,
            // in `concat`'s padded tiles (the zero border stays zero), then `concat` over the
            // two halves, the mean's channels first ([`crate::nn::pool::mean_max`]'s order, the
            // same arithmetic value by value): one view's features held at a time, no unpadded
            // copies.
            let count = inputs.count();
            let mut pooled: Option<(PaddedTensor, PaddedTensor)> = None;
            for i in 0..count.min(crate::nn::pool::MAX_VIEWS) {
                let features = tower(inputs.get(i)?.as_ref());
                match pooled.as_mut() {
                    None => pooled = Some((features.duplicate(), features)),
                    Some((sum, max)) => {
                        if !(sum.combine(&features, |s, x| s + x) && max.combine(&features, f32::max)) {
                            return Err(Error::InputShape {
                                shape: features.shape(),
                            });
                        }
                    }
                }
            }
            let Some((mut mean, max)) = pooled else {
                return Err(Error::InputCount {
                    expected: self.input_count(),
                    got: count,
                });
            };
            mean.scale(1.0 / count.min(crate::nn::pool::MAX_VIEWS) as f32);
            let layer = &self.fuse[CONCAT];
            let (weight, bias) = layer.bn.fold_into(&layer.conv_weight());
            let [cout, cin, k] = [layer.cout, layer.cin, layer.k];
            let half = cin / 2;
            let of_mean = input_channels(&weight, cout, cin, k, 0..half);
            let of_max = input_channels(&weight, cout, cin, k, half..cin);
            let plain = Epilogue { stride: 1, relu: false };
            let sum = conv3d_input(ConvInput::Padded(mean), &of_mean, cout, k, Some(&bias), plain);
            conv3d_accumulate_input(ConvInput::Padded(max), &of_max, k, sum, true)
        } else {
            // The widest layer, `concat` over the views' 4·N feature channels, a view at a time:
            // each view's features convolved with its channels of the kernel and added in, then
            // freed, so that the concatenation never exists (16 channels with four views, and
            // their padded copy: the network's peak memory before). The BatchNorm's bias goes in
            // with the first view, the ReLU after the last. A sharp network adds the views'
            // sharp volumes after their features (the fifth of each view's channels).
            let layer = &self.fuse[CONCAT];
            let (weight, bias) = layer.bn.fold_into(&layer.conv_weight());
            let [cout, cin, k] = [layer.cout, layer.cin, layer.k];
            let per_view = if self.sharp { VIEW_FEATURES + 1 } else { VIEW_FEATURES };
            let mut c: Option<Tensor> = None;
            let last = self.views - 1;
            for i in 0..self.views {
                let first = per_view * i;
                let own = input_channels(&weight, cout, cin, k, first..first + VIEW_FEATURES);
                let features = ConvInput::Padded(tower(inputs.get(i)?.as_ref()));
                let relu = i == last && !self.sharp;
                c = Some(match c {
                    None => conv3d_input(features, &own, cout, k, Some(&bias), Epilogue { stride: 1, relu }),
                    Some(sum) => conv3d_accumulate_input(features, &own, k, sum, relu),
                });
            }
            if self.sharp
                && let Some(sum) = c.take()
            {
                // The views' sharp volumes as one input of a channel per view, added in by one
                // convolution with their channels of the kernel: one pass over the sum's four
                // channels instead of one per view (each pass reads and writes all of them: 0.13
                // → 0.06 s of the toy capture's network on an Intel Xeon), and two input channels
                // to pair in bfloat16 where one could not be. Made one volume at a time.
                let mut data = Vec::with_capacity(self.views * d * h * w);
                for i in 0..self.views {
                    data.extend_from_slice(&inputs.get(self.views + i)?.data);
                }
                let sharp = Tensor {
                    shape: [self.views, d, h, w],
                    data,
                };
                let channels: Vec<usize> = (0..self.views).map(|i| per_view * i + VIEW_FEATURES).collect();
                let own = channels_of(&weight, cout, cin, k, &channels);
                c = Some(conv3d_accumulate_input(ConvInput::Owned(sharp), &own, k, sum, true));
            }
            // (`check_inputs` holds at least one input.)
            c.unwrap_or_else(|| Tensor::zeros([cout, d, h, w]))
        };
        let d1 = self.fuse[DOWN1].forward_eval(&c);
        let cdown1 = residual(self.fuse[DCONV1].forward_eval(&d1), &d1);
        drop(d1);
        let d2 = self.fuse[DOWN2].forward_eval(&cdown1);
        let e1 = residual(self.fuse[DCONV21].forward_eval(&d2), &d2);
        drop(d2);
        let cdown2 = residual(self.fuse[DCONV22].forward_eval(&e1), &e1);
        drop(e1);
        let u1 = self.fuse[UP1].forward_eval(&cdown2);
        drop(cdown2);
        let skip1 = Tensor::concat(&[&u1, &cdown1]);
        drop((u1, cdown1));
        let cup1 = self.fuse[UCONV1].forward_eval_owned(skip1);
        let u2 = self.fuse[UP2].forward_eval(&cup1);
        drop(cup1);
        // The last layers at full resolution over `keep` and their reach only (a row or column
        // the crop cuts off is read as the zero padding: it only changes outputs within the
        // margin, which are not kept).
        let radius = self.architecture.last_layers_radius();
        let rows = keep.0.start.saturating_sub(radius)..(keep.0.end + radius).min(h);
        let columns = keep.1.start.saturating_sub(radius)..(keep.1.end + radius).min(w);
        let origin = (rows.start, columns.start);
        // `uconv2` over the skip connection's two halves, one after the other (each convolved
        // with its channels of the kernel and added in), as `concat` over the views: the
        // 8-channel concatenation and its padded copy, the network's widest point, never exist,
        // and each half's window is padded without a cropped copy first.
        let layer = &self.fuse[UCONV2];
        let (weight, bias) = layer.bn.fold_into(&layer.conv_weight());
        let [cout, k] = [layer.cout, layer.k];
        let halves = [u2.shape[0], u2.shape[0] + c.shape[0]];
        let upper = input_channels(&weight, cout, halves[1], k, 0..halves[0]);
        let skipped = input_channels(&weight, cout, halves[1], k, halves[0]..halves[1]);
        let plain = Epilogue { stride: 1, relu: false };
        let upper_half = ConvInput::Window(&u2, rows.clone(), columns.clone());
        let cup2 = conv3d_input(upper_half, &upper, cout, k, Some(&bias), plain);
        drop(u2);
        let cup2 = conv3d_accumulate_input(ConvInput::Window(&c, rows, columns), &skipped, k, cup2, true);
        drop(c);
        let f = residual(self.fuse[DISTILL1].forward_eval(&cup2), &cup2);
        drop(cup2);
        let logits = conv3d_same(&f, &self.classify.weight, 1, 3, Some(&self.classify.bias));
        drop(f);
        crate::nn::conv::release_spares();
        Ok((logits, origin))
    }

    /// Train mode: the disparity with batch-statistics BatchNorms (running statistics updated,
    /// once per view in the shared feature tower as in the reference) and the tape for
    /// [`Network::backward`].
    pub fn forward_train(&mut self, inputs: &[Tensor]) -> Result<Tape, Error> {
        self.forward_train_with(inputs, BatchNormMode::Batch)
    }

    /// [`Network::forward_train`] with the BatchNorms in `mode`.
    pub fn forward_train_with(&mut self, inputs: &[Tensor], mode: BatchNormMode) -> Result<Tape, Error> {
        self.check_inputs(inputs)?;
        let mut feature_caches = Vec::new();
        let mut features = Vec::new();
        // A sharp network's sharp volumes (the inputs after the views') skip the tower.
        let towered = if self.sharp { self.views } else { inputs.len() };
        for x in &inputs[..towered] {
            let mut caches = Vec::new();
            let mut y = x.clone();
            for layer in &mut self.feature {
                let (out, cache) = layer.forward_train(&y, mode);
                caches.push(cache);
                y = out;
            }
            feature_caches.push(caches);
            features.push(y);
        }
        let mut caches = Vec::new();
        let mut step = |net: &mut Self, index: usize, x: &Tensor| {
            let (y, cache) = net.fuse[index].forward_train(x, mode);
            caches.push(cache);
            y
        };
        let (fused, argmax) = if self.views == 0 {
            let (pooled, argmax) = crate::nn::pool::mean_max_train(&features);
            (pooled, Some(argmax))
        } else if self.sharp {
            let parts: Vec<&Tensor> = features
                .iter()
                .zip(&inputs[towered..])
                .flat_map(|(f, s)| [f, s])
                .collect();
            (Tensor::concat(&parts), None)
        } else {
            (Tensor::concat(&features.iter().collect::<Vec<_>>()), None)
        };
        drop(features);
        let c = step(self, CONCAT, &fused);
        drop(fused);
        let d1 = step(self, DOWN1, &c);
        let cdown1 = residual(step(self, DCONV1, &d1), &d1);
        let d2 = step(self, DOWN2, &cdown1);
        let e1 = residual(step(self, DCONV21, &d2), &d2);
        let cdown2 = residual(step(self, DCONV22, &e1), &e1);
        let u1 = step(self, UP1, &cdown2);
        let cup1 = step(self, UCONV1, &Tensor::concat(&[&u1, &cdown1]));
        let u2 = step(self, UP2, &cup1);
        let cup2 = step(self, UCONV2, &Tensor::concat(&[&u2, &c]));
        let f = residual(step(self, DISTILL1, &cup2), &cup2);
        let logits = conv3d_same(&f, &self.classify.weight, 1, 3, Some(&self.classify.bias));
        let (disparity, probabilities) = soft_argmin(&logits);
        Ok(Tape {
            feature: feature_caches,
            argmax,
            fuse: caches,
            head_input: f,
            probabilities,
            disparity,
        })
    }

    /// Gradients of every parameter given ∂L/∂disparity (`[H·W]`).
    pub fn backward(&self, tape: &Tape, grad_disparity: &[f32]) -> Gradients {
        let mut grads: Vec<Option<ConvBnGrad>> = vec![None; self.fuse.len()];
        let mut back = |index: usize, g: &Tensor| -> Tensor {
            let (input_grad, grad) = self.fuse[index].backward(g, &tape.fuse[index], true);
            grads[index] = Some(grad);
            input_grad.unwrap_or_else(|| Tensor::zeros(g.shape))
        };
        let g_logits = soft_argmin_backward(grad_disparity, &tape.disparity, &tape.probabilities);
        let classify_weight = conv3d_same_weight_grad(&tape.head_input, &g_logits, 3);
        let classify_bias = vec![g_logits.data.iter().map(|v| f64::from(*v)).sum::<f64>() as f32];
        let g_f = conv3d_same_input_grad(&g_logits, &self.classify.weight, 4, 3);
        // f = distill1(cup2) + cup2
        let mut g_cup2 = back(DISTILL1, &g_f);
        g_cup2.add_assign(&g_f);
        let parts = back(UCONV2, &g_cup2).split(&[4, 4]);
        let (g_u2, mut g_c) = (parts[0].clone(), parts[1].clone());
        let g_cup1 = back(UP2, &g_u2);
        let parts = back(UCONV1, &g_cup1).split(&[4, 4]);
        let (g_u1, mut g_cdown1) = (parts[0].clone(), parts[1].clone());
        let g_cdown2 = back(UP1, &g_u1);
        // cdown2 = dconv22(e1) + e1
        let mut g_e1 = back(DCONV22, &g_cdown2);
        g_e1.add_assign(&g_cdown2);
        // e1 = dconv21(d2) + d2
        let mut g_d2 = back(DCONV21, &g_e1);
        g_d2.add_assign(&g_e1);
        g_cdown1.add_assign(&back(DOWN2, &g_d2));
        // cdown1 = dconv1(d1) + d1
        let mut g_d1 = back(DCONV1, &g_cdown1);
        g_d1.add_assign(&g_cdown1);
        g_c.add_assign(&back(DOWN1, &g_d1));
        let g_fused = back(CONCAT, &g_c);
        let g_features = match &tape.argmax {
            Some(argmax) => crate::nn::pool::mean_max_backward(&g_fused, argmax, tape.feature.len()),
            None if self.sharp => g_fused
                .split(&[VIEW_FEATURES, 1].repeat(self.views))
                .into_iter()
                .step_by(2)
                .collect(),
            None => g_fused.split(&vec![VIEW_FEATURES; self.views]),
        };

        let mut feature_grads: Vec<Option<ConvBnGrad>> = vec![None; self.feature.len()];
        for (g_view, caches) in g_features.iter().zip(&tape.feature) {
            let mut g = g_view.clone();
            for index in (0..self.feature.len()).rev() {
                let (input_grad, grad) = self.feature[index].backward(&g, &caches[index], index > 0);
                match &mut feature_grads[index] {
                    Some(sum) => sum.add(&grad),
                    slot => *slot = Some(grad),
                }
                if let Some(next) = input_grad {
                    g = next;
                }
            }
        }
        let mut tensors = Vec::new();
        for (layer, grad) in self.layers().zip(feature_grads.into_iter().chain(grads)) {
            let grad = grad.unwrap_or_else(|| ConvBnGrad {
                weight: vec![0.0; layer.weight.len()],
                bn_weight: vec![0.0; layer.cout],
                bn_bias: vec![0.0; layer.cout],
            });
            tensors.push((format!("{}.0.weight", layer.name), grad.weight));
            tensors.push((format!("{}.1.weight", layer.name), grad.bn_weight));
            tensors.push((format!("{}.1.bias", layer.name), grad.bn_bias));
        }
        tensors.push(("classify.weight".to_owned(), classify_weight));
        tensors.push(("classify.bias".to_owned(), classify_bias));
        Gradients { tensors }
    }

    /// One train-mode pass with the smooth-L1 loss against `target` on `mask`: returns the loss,
    /// the disparity and the gradients.
    pub fn loss_and_gradients(
        &mut self,
        inputs: &[Tensor],
        target: &[f32],
        mask: &[bool],
    ) -> Result<(f32, Vec<f32>, Gradients), Error> {
        self.loss_and_gradients_with(inputs, target, mask, BatchNormMode::Batch)
    }

    /// [`Network::loss_and_gradients`] with the BatchNorms in `mode`.
    pub fn loss_and_gradients_with(
        &mut self,
        inputs: &[Tensor],
        target: &[f32],
        mask: &[bool],
        mode: BatchNormMode,
    ) -> Result<(f32, Vec<f32>, Gradients), Error> {
        let tape = self.forward_train_with(inputs, mode)?;
        let (loss, grad) = smooth_l1(&tape.disparity, target, mask);
        let gradients = self.backward(&tape, &grad);
        Ok((loss, tape.disparity, gradients))
    }
}

/// Where a forward pass takes its views' input tensors from.
#[derive(Clone, Copy)]
enum Inputs<'a> {
    /// Tensors the caller holds.
    Given(&'a [Tensor]),
    /// `count` tensors of `shape`, each made when the pass reaches it.
    Made {
        count: usize,
        shape: [usize; 4],
        make: &'a dyn Fn(usize) -> Tensor,
    },
}

impl Inputs<'_> {
    fn count(&self) -> usize {
        match self {
            Inputs::Given(inputs) => inputs.len(),
            Inputs::Made { count, .. } => *count,
        }
    }

    /// The shape every input has (checked).
    fn shape(&self) -> [usize; 4] {
        match self {
            Inputs::Given(inputs) => inputs.first().map_or([0; 4], |t| t.shape),
            Inputs::Made { shape, .. } => *shape,
        }
    }

    /// Input `i`, made if it is made; one made with another shape is an error.
    fn get(&self, i: usize) -> Result<std::borrow::Cow<'_, Tensor>, Error> {
        match self {
            Inputs::Given(inputs) => Ok(std::borrow::Cow::Borrowed(&inputs[i])),
            Inputs::Made { shape, make, .. } => {
                let made = make(i);
                if made.shape != *shape {
                    return Err(Error::InputShape { shape: made.shape });
                }
                Ok(std::borrow::Cow::Owned(made))
            }
        }
    }
}

/// The kernel `weight` (`[cout][cin][k³]`) restricted to the input channels `channels`, in that
/// order: `[cout][channels.len()][k³]` ([`input_channels`] of channels that are not a range).
fn channels_of(weight: &[f32], cout: usize, cin: usize, k: usize, channels: &[usize]) -> Vec<f32> {
    let taps = k * k * k;
    (0..cout)
        .flat_map(|o| {
            channels
                .iter()
                .flat_map(move |&ch| weight[(o * cin + ch) * taps..(o * cin + ch + 1) * taps].iter().copied())
        })
        .collect()
}

fn residual(mut y: Tensor, skip: &Tensor) -> Tensor {
    y.add_assign(skip);
    y
}

#[cfg(test)]
mod layer_tests {
    use super::*;
    use crate::nn::conv::tests::{random, random_values};

    #[test]
    fn conv_bn_layers_match_finite_differences_in_every_mode() {
        for mode in [BatchNormMode::Frozen, BatchNormMode::Tracking, BatchNormMode::Batch] {
            for (kind, k, shape) in [
                (ConvKind::Same, 3, [4, 4, 6, 6]),
                (ConvKind::Down, 3, [4, 4, 6, 6]),
                (ConvKind::Up, 3, [4, 2, 3, 3]),
            ] {
                let mut layer = ConvBn::new("l", 4, 4, k, kind);
                layer.weight = random_values(layer.weight.len(), 3);
                layer.bn.running_mean = vec![0.1, -0.2, 0.0, 0.3];
                layer.bn.running_var = vec![0.5, 1.5, 0.8, 1.1];
                layer.bn.weight = vec![1.2, 0.7, -0.9, 1.0];
                layer.bn.bias = vec![0.1, 0.2, -0.1, 0.05];
                let x = random(shape, 4);
                let (y, cache) = layer.clone().forward_train(&x, mode);
                let u = random(y.shape, 5);
                let value = |l: &ConvBn, x: &Tensor| -> f64 {
                    let (y, _) = l.clone().forward_train(x, mode);
                    y.data
                        .iter()
                        .zip(&u.data)
                        .map(|(a, b)| f64::from(*a) * f64::from(*b))
                        .sum()
                };
                let (dx, grad) = layer.backward(&u, &cache, true);
                let dx = dx.unwrap_or_else(|| Tensor::zeros([0; 4]));
                let h = 1e-3f32;
                for c in 0..4 {
                    let (mut p, mut m) = (layer.clone(), layer.clone());
                    p.bn.bias[c] += h;
                    m.bn.bias[c] -= h;
                    let numeric = (value(&p, &x) - value(&m, &x)) / (2.0 * f64::from(h));
                    assert!(
                        (numeric - f64::from(grad.bn_bias[c])).abs() < 1e-2 * (1.0 + numeric.abs()),
                        "{mode:?} {kind:?} dβ[{c}] {} vs {numeric}",
                        grad.bn_bias[c]
                    );
                }
                for i in [0, 5, 17, 40] {
                    let (mut p, mut m) = (x.clone(), x.clone());
                    p.data[i] += h;
                    m.data[i] -= h;
                    let numeric = (value(&layer, &p) - value(&layer, &m)) / (2.0 * f64::from(h));
                    assert!(
                        (numeric - f64::from(dx.data[i])).abs() < 1e-2 * (1.0 + numeric.abs()),
                        "{mode:?} {kind:?} dx[{i}] {} vs {numeric}",
                        dx.data[i]
                    );
                }
            }
        }
    }
}

#[cfg(test)]
mod mode_tests {
    use super::*;
    use crate::nn::conv::tests::random;

    /// With the running statistics set to this batch's own, frozen mode computes the batch-mode
    /// forward pass, and the last BatchNorm's β gradient (nothing normalises after it) is the same.
    #[test]
    fn frozen_mode_equals_batch_mode_at_the_batch_statistics() {
        let mut net = Network::init(1, 11);
        let inputs = vec![random([1, 8, 8, 8], 1)];
        let target: Vec<f32> = (0..64).map(|i| (i % 8) as f32 * 0.9).collect();
        let mask: Vec<bool> = (0..64).map(|i| i % 5 != 0).collect();
        let mut stats = net.clone();
        for layer in stats.layers_mut() {
            layer.bn.momentum = Some(1.0);
        }
        let batch = stats.clone().forward_train(&inputs).unwrap_or_else(|e| panic!("{e}"));
        let _ = stats.forward_train(&inputs);
        let sizes = [512, 512, 512, 512, 512, 64, 64, 8, 8, 8, 64, 64, 512, 512, 512];
        for ((layer, fitted), n) in net.layers_mut().zip(stats.layers()).zip(sizes) {
            layer.bn.running_mean = fitted.bn.running_mean.clone();
            layer.bn.running_var = fitted
                .bn
                .running_var
                .iter()
                .map(|v| v * (n - 1) as f32 / n as f32)
                .collect();
        }
        let frozen = net
            .clone()
            .forward_train_with(&inputs, BatchNormMode::Frozen)
            .unwrap_or_else(|e| panic!("{e}"));
        let worst = batch
            .disparity
            .iter()
            .zip(&frozen.disparity)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-3, "forward differs by {worst}");
        let (_, _, gb) = net
            .clone()
            .loss_and_gradients_with(&inputs, &target, &mask, BatchNormMode::Batch)
            .unwrap_or_else(|e| panic!("{e}"));
        let (_, _, gf) = net
            .clone()
            .loss_and_gradients_with(&inputs, &target, &mask, BatchNormMode::Frozen)
            .unwrap_or_else(|e| panic!("{e}"));
        for name in ["distill1.1.bias", "distill1.1.weight", "classify.weight"] {
            let b = &gb
                .tensors
                .iter()
                .find(|(n, _)| n == name)
                .unwrap_or_else(|| panic!("{name}"))
                .1;
            let f = &gf
                .tensors
                .iter()
                .find(|(n, _)| n == name)
                .unwrap_or_else(|| panic!("{name}"))
                .1;
            let scale = b.iter().fold(0f32, |m, v| m.max(v.abs()));
            let worst = b.iter().zip(f).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
            assert!(
                scale > 1e-4 && worst <= 1e-3 * scale,
                "{name}: worst {worst} of {scale}"
            );
        }
    }
}

#[cfg(test)]
mod pooled_tests {
    use super::*;
    use crate::nn::conv::tests::random;

    /// Within `tolerance` of the largest expected magnitude (at least 1e-4: the classifier bias's
    /// gradient is zero in exact arithmetic and about 1e-8 in rounding).
    fn close(got: &[f32], expected: &[f32], tolerance: f32, what: &str) {
        assert_eq!(got.len(), expected.len(), "{what}");
        let scale = expected.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-4);
        for (i, (a, b)) in got.iter().zip(expected).enumerate() {
            assert!(
                (a - b).abs() <= tolerance * scale,
                "{what}[{i}]: {a} vs {b} (scale {scale})"
            );
        }
    }

    /// With one view the mean and the maximum are both its features: the pooled network is the
    /// stereo network whose `concat` weights are the sum of the pooled ones over mean and max,
    /// in its output and in every gradient (the backward pass through the pooling).
    #[test]
    fn a_pooled_network_with_one_view_is_the_stereo_network_with_concat_summed() {
        let pooled = Network::init(0, 21);
        assert_eq!(pooled.parameter_count(), Network::init(2, 21).parameter_count());
        let k3 = 7 * 7 * 7;
        let concat = &pooled.fuse[CONCAT];
        let mut stereo = pooled.clone();
        stereo.views = 1;
        let mut summed = ConvBn::new("concat", 4, 4, 7, ConvKind::Same);
        summed.bn = concat.bn.clone();
        for o in 0..4 {
            for i in 0..4 {
                for t in 0..k3 {
                    summed.weight[(o * 4 + i) * k3 + t] =
                        concat.weight[(o * 8 + i) * k3 + t] + concat.weight[(o * 8 + 4 + i) * k3 + t];
                }
            }
        }
        stereo.fuse[CONCAT] = summed;
        let x = random([1, 8, 8, 8], 9);
        let got = pooled
            .logits(std::slice::from_ref(&x))
            .unwrap_or_else(|e| panic!("{e}"));
        let want = stereo
            .logits(std::slice::from_ref(&x))
            .unwrap_or_else(|e| panic!("{e}"));
        close(&got.data, &want.data, 1e-4, "logits");
        let target: Vec<f32> = (0..64).map(|i| (i % 7) as f32).collect();
        let mask = vec![true; 64];
        let run = |net: &Network| {
            net.clone()
                .loss_and_gradients_with(std::slice::from_ref(&x), &target, &mask, BatchNormMode::Frozen)
                .unwrap_or_else(|e| panic!("{e}"))
        };
        let ((loss_p, _, grads_p), (loss_s, _, grads_s)) = (run(&pooled), run(&stereo));
        assert!(
            (loss_p - loss_s).abs() <= 1e-4 * loss_s.abs().max(1.0),
            "{loss_p} vs {loss_s}"
        );
        for ((name, g_p), (name_s, g_s)) in grads_p.tensors.iter().zip(&grads_s.tensors) {
            assert_eq!(name, name_s);
            if name == "concat.0.weight" {
                // ∂L/∂W_mean = ∂L/∂W_max = the stereo network's ∂L/∂W.
                for o in 0..4 {
                    for half in 0..2 {
                        for i in 0..4 {
                            let p = &g_p[(o * 8 + half * 4 + i) * k3..][..k3];
                            close(p, &g_s[(o * 4 + i) * k3..][..k3], 1e-3, "concat weight gradient");
                        }
                    }
                }
            } else {
                close(g_p, g_s, 1e-3, name);
            }
        }
    }

    #[test]
    fn a_sharpened_network_computes_the_fixed_one_until_its_sharp_weights_move() {
        // Zero weights for the sharp channels: the fixed network's logits (to the bit: each
        // sharp volume adds exact zeros) and, in training, its loss and every gradient but the
        // new channels' own.
        let fixed = Network::init_with(2, Architecture::Lite, 23);
        let sharp = fixed.sharpened().unwrap_or_else(|| panic!("a fixed network sharpens"));
        assert!(sharp.sharp && !fixed.sharp);
        assert_eq!(sharp.fuse[CONCAT].cin, 10);
        assert_eq!(
            sharp.parameter_count(),
            fixed.parameter_count() + 4 * 2 * 27,
            "one kernel per view and output channel more"
        );
        assert!(
            Network::init(0, 1).sharpened().is_none(),
            "a pooled network has no sharp inputs"
        );
        let views: Vec<Tensor> = (0..2).map(|v| random([1, 8, 8, 8], 40 + v)).collect();
        let sharp_volumes: Vec<Tensor> = (0..2).map(|v| random([1, 8, 8, 8], 50 + v)).collect();
        let both: Vec<Tensor> = views.iter().chain(&sharp_volumes).cloned().collect();
        let want = fixed.logits(&views).unwrap_or_else(|e| panic!("{e}"));
        let got = sharp.logits(&both).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(got.data, want.data, "logits");
        assert!(matches!(
            sharp.logits(&views),
            Err(Error::InputCount { expected: 4, got: 2 })
        ));

        let target: Vec<f32> = (0..64).map(|i| (i % 7) as f32).collect();
        let mask = vec![true; 64];
        let run = |net: &Network, inputs: &[Tensor]| {
            net.clone()
                .loss_and_gradients_with(inputs, &target, &mask, BatchNormMode::Frozen)
                .unwrap_or_else(|e| panic!("{e}"))
        };
        let ((loss_f, _, grads_f), (loss_s, _, grads_s)) = (run(&fixed, &views), run(&sharp, &both));
        assert!(
            (loss_f - loss_s).abs() <= 1e-5 * loss_f.abs().max(1.0),
            "{loss_f} vs {loss_s}"
        );
        let k3 = 27;
        for ((name, g_f), (name_s, g_s)) in grads_f.tensors.iter().zip(&grads_s.tensors) {
            assert_eq!(name, name_s);
            if name == "concat.0.weight" {
                for o in 0..4 {
                    for v in 0..2 {
                        let features = &g_s[(o * 10 + v * 5) * k3..][..4 * k3];
                        close(
                            features,
                            &g_f[(o * 8 + v * 4) * k3..][..4 * k3],
                            1e-4,
                            "concat, features",
                        );
                    }
                }
            } else {
                close(g_s, g_f, 1e-4, name);
            }
        }
    }

    #[test]
    fn a_pooled_network_pools_in_its_padded_tiles_as_the_plain_pooling_does() {
        // The eval pass pools each view's features as they come out of the tower, in `concat`'s
        // padded tiles (several tiles across: 100 columns, 48 a tile), and runs `concat` over the
        // two halves; the training pass pools plain tensors ([`crate::nn::pool::mean_max`]) and
        // runs one 8-channel `concat`. Both architectures, 1 to 5 views.
        for architecture in Architecture::ALL {
            let mut net = Network::pooled_from(&Network::init_with(4, architecture, 31));
            // Max weights of their own, so that the maximum's half counts.
            for (i, w) in net.fuse[CONCAT].weight.iter_mut().enumerate() {
                *w += 0.01 * ((i % 7) as f32 - 3.0);
            }
            for count in [1, 2, 3, 5] {
                let inputs: Vec<Tensor> = (0..count).map(|v| random([1, 8, 8, 100], 70 + v)).collect();
                eval_is_training(&net, &inputs, &format!("{architecture:?}, {count} views"));
            }
        }
    }

    /// The eval pass's soft-argmin disparity against the training pass's with frozen statistics;
    /// the eval logits.
    fn eval_is_training(net: &Network, inputs: &[Tensor], what: &str) -> Tensor {
        let logits = net.logits(inputs).unwrap_or_else(|e| panic!("{e}"));
        let (eval, _) = soft_argmin(&logits);
        let tape = net
            .clone()
            .forward_train_with(inputs, BatchNormMode::Frozen)
            .unwrap_or_else(|e| panic!("{e}"));
        close(&tape.disparity, &eval, 1e-4, what);
        logits
    }

    #[test]
    fn a_sharp_network_reads_its_sharp_volumes_alike_in_eval_and_training() {
        // Non-zero sharp weights: the eval pass (each view's features added into `concat` in
        // turn, then the sharp volumes by one convolution) gives the training pass's disparity, the sharp volumes change it, and
        // the gradient of a sharp weight is the loss's finite difference.
        let mut net = Network::init_with(2, Architecture::Lite, 29)
            .sharpened()
            .unwrap_or_else(|| panic!("a fixed network sharpens"));
        let k3 = 27;
        for o in 0..4 {
            for v in 0..2 {
                for t in 0..k3 {
                    net.fuse[CONCAT].weight[(o * 10 + v * 5 + 4) * k3 + t] = 0.05 * (((o + v + t) % 5) as f32 - 2.0);
                }
            }
        }
        let inputs: Vec<Tensor> = (0..4).map(|v| random([1, 8, 8, 8], 60 + v)).collect();
        let logits = eval_is_training(&net, &inputs, "disparity, eval against training");
        let mut other = inputs.clone();
        other[3] = random([1, 8, 8, 8], 99);
        let moved = net.logits(&other).unwrap_or_else(|e| panic!("{e}"));
        assert_ne!(moved.data, logits.data, "the sharp volumes reach the logits");

        let target: Vec<f32> = (0..64).map(|i| (i % 5) as f32 + 0.5).collect();
        let mask = vec![true; 64];
        let loss = |net: &Network| {
            net.clone()
                .loss_and_gradients_with(&inputs, &target, &mask, BatchNormMode::Frozen)
                .unwrap_or_else(|e| panic!("{e}"))
        };
        let (_, _, grads) = loss(&net);
        let concat = grads
            .tensors
            .iter()
            .find(|(name, _)| name == "concat.0.weight")
            .map(|(_, g)| g.clone())
            .unwrap_or_default();
        // Along the sharp channels' own gradient (a direction the loss moves in measurably):
        // the directional derivative is the squared norm of that part of the gradient.
        let sharp_taps: Vec<usize> = (0..4)
            .flat_map(|o| (0..2).flat_map(move |v| (o * 10 + v * 5 + 4) * k3..(o * 10 + v * 5 + 5) * k3))
            .collect();
        let norm = sharp_taps.iter().map(|&i| concat[i] * concat[i]).sum::<f32>().sqrt();
        assert!(norm > 0.0, "the sharp weights have a gradient");
        let h = 1e-2;
        let moved = |sign: f32| {
            let mut net = net.clone();
            for &i in &sharp_taps {
                net.fuse[CONCAT].weight[i] += sign * h * concat[i] / norm;
            }
            loss(&net).0
        };
        let difference = (moved(1.0) - moved(-1.0)) / (2.0 * h);
        assert!(
            (difference - norm).abs() <= 0.05 * norm,
            "∂L along the sharp weights' gradient: finite difference {difference}, backward {norm}"
        );
    }

    #[test]
    fn a_pooled_network_takes_any_number_of_views_in_any_order() {
        let net = Network::init(0, 5);
        for count in [1, 2, 3, 5] {
            let inputs: Vec<Tensor> = (0..count).map(|v| random([1, 8, 8, 8], 30 + v)).collect();
            let logits = net.logits(&inputs).unwrap_or_else(|e| panic!("{count} views: {e}"));
            let mut reversed = inputs.clone();
            reversed.reverse();
            let again = net.logits(&reversed).unwrap_or_else(|e| panic!("{e}"));
            close(&again.data, &logits.data, 1e-4, "the views reversed");
            let tape = net.clone().forward_train(&inputs).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(tape.disparity.len(), 64);
        }
        assert!(matches!(net.logits(&[]), Err(Error::InputCount { .. })));
        // A fixed-count network still wants its count.
        assert!(matches!(
            Network::init(2, 5).logits(&[random([1, 8, 8, 8], 1)]),
            Err(Error::InputCount { expected: 2, got: 1 })
        ));
    }

    #[test]
    fn inputs_made_one_at_a_time_give_the_logits_of_inputs_given() {
        for (net, count) in [(Network::init(4, 3), 4usize), (Network::init(0, 4), 3)] {
            let inputs: Vec<Tensor> = (0..count).map(|v| random([1, 8, 12, 16], 40 + v as u64)).collect();
            let keep = (2..10, 4..12);
            let given = net.logits_within(&inputs, &keep).unwrap_or_else(|e| panic!("{e}"));
            let made = net
                .logits_within_made((count, [1, 8, 12, 16]), &|i| inputs[i].clone(), &keep)
                .unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(made, given, "{count} views");
            // A count or a shape the network does not take, announced or made, is an error.
            let wrong = net.logits_within_made((count, [1, 8, 12, 16]), &|_| random([1, 8, 12, 12], 1), &keep);
            assert!(matches!(wrong, Err(Error::InputShape { shape: [1, 8, 12, 12] })));
            let odd = net.logits_within_made((count, [1, 7, 12, 16]), &|i| inputs[i].clone(), &keep);
            assert!(matches!(odd, Err(Error::InputShape { .. })));
        }
        let few =
            Network::init(4, 3).logits_within_made((2, [1, 8, 8, 8]), &|_| random([1, 8, 8, 8], 1), &(0..8, 0..8));
        assert!(matches!(few, Err(Error::InputCount { expected: 4, got: 2 })));
    }

    #[test]
    fn a_pooled_network_from_a_fixed_one_agrees_where_the_views_agree() {
        let five = Network::init(4, 13);
        let pooled = Network::pooled_from(&five);
        assert_eq!(pooled.views, 0);
        let x = random([1, 8, 8, 8], 17);
        let same = vec![x.clone(); 4];
        let want = five.logits(&same).unwrap_or_else(|e| panic!("{e}"));
        close(
            &pooled.logits(&same).unwrap_or_else(|e| panic!("{e}")).data,
            &want.data,
            1e-4,
            "four",
        );
        close(
            &pooled.logits(&[x]).unwrap_or_else(|e| panic!("{e}")).data,
            &want.data,
            1e-4,
            "one",
        );
        // The weights file says which it is, and reads back as it was written.
        let info = crate::mfusenet::weights::WeightsInfo::default();
        let bytes = crate::mfusenet::weights::to_bytes(&pooled, &info).unwrap_or_else(|e| panic!("{e}"));
        let (read, read_info) =
            crate::mfusenet::weights::from_bytes(&bytes, "pooled", "", Some(0)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(read_info.get("view_fusion"), Some("mean-max"));
        assert_eq!(read.views, 0);
        assert_eq!(read.fuse[CONCAT].weight, pooled.fuse[CONCAT].weight);
        assert!(matches!(
            crate::mfusenet::weights::from_bytes(&bytes, "pooled", "", Some(2)),
            Err(Error::Variant {
                expected: 2,
                got: 0,
                ..
            })
        ));
    }
}

#[cfg(test)]
mod receptive_tests {
    use super::*;
    use crate::nn::conv::tests::random;

    /// How far (px, in H and W) a change of one input pixel (every slice) of a random network
    /// reaches in its logits.
    fn measured_radius(architecture: Architecture) -> usize {
        let mut net = Network::init_with(2, architecture, 3);
        // Non-zero BatchNorm shifts, so that the ReLUs pass the change on.
        for layer in net.feature.iter_mut().chain(net.fuse.iter_mut()) {
            for (i, b) in layer.bn.bias.iter_mut().enumerate() {
                *b = 0.1 * (i as f32 + 1.0);
            }
        }
        let (d, h, w) = (8, 8, 128);
        let inputs = [random([1, d, h, w], 1), random([1, d, h, w], 2)];
        let before = net.logits(&inputs).unwrap_or_else(|e| panic!("{e}"));
        // The impulse at each phase of the quarter-size grid.
        let mut reach = 0;
        for x0 in 60..64 {
            let mut changed = inputs.clone();
            for z in 0..d {
                let at = changed[0].index(0, z, 4, x0);
                changed[0].data[at] += 10.0;
            }
            let after = net.logits(&changed).unwrap_or_else(|e| panic!("{e}"));
            for (i, (a, b)) in before.data.iter().zip(&after.data).enumerate() {
                if a != b {
                    reach = reach.max((i % w).abs_diff(x0));
                }
            }
        }
        reach
    }

    #[test]
    fn the_receptive_radius_is_what_an_impulse_reaches_and_the_halo_covers_it() {
        for architecture in Architecture::ALL {
            let measured = measured_radius(architecture);
            let radius = architecture.receptive_radius();
            assert!(
                measured == radius,
                "{}: an impulse reaches {measured} px, the formula says {radius}",
                architecture.name()
            );
            assert!(architecture.halo() >= measured && architecture.halo() % 4 == 0);
        }
        assert_eq!((Architecture::Paper.halo(), Architecture::Lite.halo()), (44, 36));
    }
}
