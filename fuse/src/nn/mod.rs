//! The small 3D-CNN toolkit MFuseNet needs, written for its shapes: volumes of a few channels
//! over (disparity, rows, columns), batch 1.
//!
//! - [`Tensor`]: `[channels][depth][height][width]` in one `f32` buffer, width fastest.
//! - [`conv`]: the "same" stride-1 3D convolution (forward, input and weight gradients) as direct
//!   convolutions vectorised along the image rows with four output channels in registers; the
//!   stride-2 convolution and the stride-2 transposed convolution are expressed through it
//!   (the latter in eval mode by output parity instead, [`transposed`]).
//!   Their inner loop runs on 512-bit vectors where the host has AVX-512F ([`wide_kernel`],
//!   detected at run time), with the same sums bit for bit; in inference, where asked
//!   ([`conv::set_precision`]), on bfloat16 pairs of taps where the host has AVX512-BF16
//!   ([`bf16_kernel`]; its channel pairs on Intel's matrix unit where the host has AMX,
//!   [`amx_kernel`]), or on 16-bit integer pairs of input channels on AVX2 hosts
//!   ([`int16_kernel`]).
//! - [`batch_norm`]: BatchNorm3d in train mode (batch statistics, running-statistics update,
//!   backward) and eval mode (folded into the preceding convolution).
//! - [`regression`]: softmax over disparity, soft-argmin and the smooth-L1 loss.
//! - [`pool`]: the mean and the maximum across any number of views' features (order-invariant
//!   fusion), with its backward.
//! - [`reference`](mod@reference): plain loop implementations the fast kernels are tested against.
//!
//! Every layer has its forward and backward here; the network (`crate::mfusenet`) wires them.

pub mod amx_kernel;
pub mod batch_norm;
pub mod bf16_kernel;
pub mod conv;
mod fma_kernel;
pub mod int16_kernel;
pub mod pool;
pub mod reference;
pub mod regression;
pub mod transposed;
pub mod wide_kernel;

/// A volume of `channels × depth × height × width` values, width fastest (PyTorch's `[C, D, H,
/// W]` for batch 1).
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    /// `[channels, depth, height, width]`.
    pub shape: [usize; 4],
    /// `channels · depth · height · width` values.
    pub data: Vec<f32>,
}

impl Tensor {
    /// A tensor of zeros.
    pub fn zeros(shape: [usize; 4]) -> Self {
        Self {
            shape,
            data: vec![0.0; shape.iter().product()],
        }
    }

    /// Values in one channel (`depth · height · width`).
    pub fn channel_len(&self) -> usize {
        self.shape[1] * self.shape[2] * self.shape[3]
    }

    /// The values of channel `c`.
    pub fn channel(&self, c: usize) -> &[f32] {
        let n = self.channel_len();
        &self.data[c * n..(c + 1) * n]
    }

    /// Index of `(c, d, h, w)`.
    #[inline]
    pub fn index(&self, c: usize, d: usize, h: usize, w: usize) -> usize {
        ((c * self.shape[1] + d) * self.shape[2] + h) * self.shape[3] + w
    }

    /// The tensor seen in a mirror: rows reversed if `vertical`, columns if `horizontal`
    /// (`torch.flip(dims=…)` over height and width).
    pub fn flipped(&self, vertical: bool, horizontal: bool) -> Tensor {
        let [_, _, h, w] = self.shape;
        if !(vertical || horizontal) || h * w == 0 {
            return self.clone();
        }
        let mut out = Tensor::zeros(self.shape);
        for (to, from) in out.data.chunks_exact_mut(h * w).zip(self.data.chunks_exact(h * w)) {
            for y in 0..h {
                let sy = if vertical { h - 1 - y } else { y };
                let (row, source) = (&mut to[y * w..(y + 1) * w], &from[sy * w..(sy + 1) * w]);
                if horizontal {
                    row.iter_mut().zip(source.iter().rev()).for_each(|(a, b)| *a = *b);
                } else {
                    row.copy_from_slice(source);
                }
            }
        }
        out
    }

    /// Channels of several tensors of one spatial shape, stacked (`torch.cat(dim=1)`).
    pub fn concat(parts: &[&Tensor]) -> Tensor {
        let spatial = parts.first().map_or([0; 3], |t| [t.shape[1], t.shape[2], t.shape[3]]);
        let channels = parts.iter().map(|t| t.shape[0]).sum();
        let mut data = Vec::with_capacity(channels * spatial.iter().product::<usize>());
        for part in parts {
            data.extend_from_slice(&part.data);
        }
        Tensor {
            shape: [channels, spatial[0], spatial[1], spatial[2]],
            data,
        }
    }

    /// The rows `rows` and columns `columns` of every channel and depth plane.
    pub fn crop_hw(&self, rows: std::ops::Range<usize>, columns: std::ops::Range<usize>) -> Tensor {
        let [c, d, h, w] = self.shape;
        let (rows, columns) = (
            rows.start.min(h)..rows.end.min(h),
            columns.start.min(w)..columns.end.min(w),
        );
        let mut data = Vec::with_capacity(c * d * rows.len() * columns.len());
        for plane in self.data.chunks_exact((h * w).max(1)) {
            for y in rows.clone() {
                data.extend_from_slice(&plane[y * w + columns.start..y * w + columns.end]);
            }
        }
        Tensor {
            shape: [c, d, rows.len(), columns.len()],
            data,
        }
    }

    /// Splits the channels into tensors of `sizes` channels (the inverse of [`Tensor::concat`]).
    pub fn split(&self, sizes: &[usize]) -> Vec<Tensor> {
        let n = self.channel_len();
        let mut start = 0;
        sizes
            .iter()
            .map(|&c| {
                let part = Tensor {
                    shape: [c, self.shape[1], self.shape[2], self.shape[3]],
                    data: self.data[start * n..(start + c) * n].to_vec(),
                };
                start += c;
                part
            })
            .collect()
    }

    /// Element-wise `self += other`.
    pub fn add_assign(&mut self, other: &Tensor) {
        for (a, b) in self.data.iter_mut().zip(&other.data) {
            *a += b;
        }
    }

    /// In-place ReLU.
    pub fn relu(mut self) -> Self {
        for v in &mut self.data {
            *v = v.max(0.0);
        }
        self
    }

    /// Every value at even `(d, h, w)`: the output grid of a stride-2 layer with padding `k / 2`
    /// evaluated at stride 1 (`[c, ⌈d/2⌉, ⌈h/2⌉, ⌈w/2⌉]`).
    pub fn subsample2(&self) -> Tensor {
        let [c, d, h, w] = self.shape;
        let shape = [c, d.div_ceil(2), h.div_ceil(2), w.div_ceil(2)];
        let mut out = Tensor::zeros(shape);
        let mut i = 0;
        for cc in 0..c {
            for dd in 0..shape[1] {
                for hh in 0..shape[2] {
                    let row = self.index(cc, 2 * dd, 2 * hh, 0);
                    for ww in 0..shape[3] {
                        out.data[i] = self.data[row + 2 * ww];
                        i += 1;
                    }
                }
            }
        }
        out
    }

    /// Zeros with this tensor's values at the even positions of a `[c, d, h, w]` grid (the
    /// adjoint of [`Tensor::subsample2`], and the input of a stride-2 transposed convolution).
    pub fn upsample2_zeros(&self, spatial: [usize; 3]) -> Tensor {
        let [c, d, h, w] = self.shape;
        let mut out = Tensor::zeros([c, spatial[0], spatial[1], spatial[2]]);
        let mut i = 0;
        for cc in 0..c {
            for dd in 0..d {
                for hh in 0..h {
                    let row = out.index(cc, 2 * dd, 2 * hh, 0);
                    for ww in 0..w {
                        out.data[row + 2 * ww] = self.data[i];
                        i += 1;
                    }
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flip_moves_each_value_to_its_mirror_position() {
        let shape = [2, 3, 5, 7];
        let t = Tensor {
            shape,
            data: (0..shape.iter().product::<usize>())
                .map(|i| (i * 7919 % 1000) as f32)
                .collect(),
        };
        for (vertical, horizontal) in [(false, false), (true, false), (false, true), (true, true)] {
            let f = t.flipped(vertical, horizontal);
            for c in 0..2 {
                for d in 0..3 {
                    for y in 0..5 {
                        for x in 0..7 {
                            let (sy, sx) = (if vertical { 4 - y } else { y }, if horizontal { 6 - x } else { x });
                            assert_eq!(f.data[f.index(c, d, y, x)], t.data[t.index(c, d, sy, sx)]);
                        }
                    }
                }
            }
            assert_eq!(f.flipped(vertical, horizontal), t);
        }
    }

    #[test]
    fn subsampling_and_zero_upsampling_are_adjoint() {
        let x = Tensor {
            shape: [2, 3, 5, 4],
            data: (0..120).map(|v| v as f32 * 0.5 - 7.0).collect(),
        };
        let small = x.subsample2();
        assert_eq!(small.shape, [2, 2, 3, 2]);
        assert_eq!(small.data[small.index(1, 1, 2, 1)], x.data[x.index(1, 2, 4, 2)]);
        let y = Tensor {
            shape: small.shape,
            data: (0..small.data.len()).map(|v| (v as f32).sin()).collect(),
        };
        // <S x, y> = <x, Sᵀ y>.
        let left: f32 = small.data.iter().zip(&y.data).map(|(a, b)| a * b).sum();
        let up = y.upsample2_zeros([3, 5, 4]);
        let right: f32 = x.data.iter().zip(&up.data).map(|(a, b)| a * b).sum();
        assert!((left - right).abs() < 1e-3, "{left} {right}");
        let parts = Tensor::concat(&[&x, &small.upsample2_zeros([3, 5, 4])]).split(&[2, 2]);
        assert_eq!(parts[0], x);
    }
}
