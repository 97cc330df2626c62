//! The stride-1 "same" 3D convolution (`padding = k / 2`) and its two gradients, as direct
//! convolutions written for MFuseNet's shapes (1–16 input channels, 4 output channels, kernels
//! 3, 5 and 7): the input is copied once into a zero-padded buffer whose rows are long enough
//! for whole vectors, then every output row is computed in blocks of 24 columns with the four
//! output channels' accumulators held in registers (12 AVX vectors): per kernel tap, three
//! unaligned loads feed twelve fused multiply-adds. Work is split over (channel group, depth
//! plane) pairs with rayon.
//!
//! The stride-2 convolution is this convolution sampled at even positions
//! ([`Tensor::subsample2`]), and the stride-2 transposed convolution (kernel 3, padding 1,
//! output padding 1) is this convolution of the zero-upsampled input with the kernel flipped and
//! its channels swapped ([`transposed_as_conv`]); both run at the coarse levels of the U-Net,
//! about 3 % of the work.

use rayon::prelude::*;
use wide::f32x8;

use super::Tensor;

/// Lanes of one vector.
const LANES: usize = 8;
/// Vectors per output block: 24 columns × 4 channels = 12 accumulators.
const VECTORS: usize = 3;
/// Output columns per block.
const BLOCK: usize = LANES * VECTORS;
/// Output channels computed together.
const GROUP: usize = 4;

/// A zero-padded copy of a tensor: `[c][d + 2p][h + 2p][row]`, the value of `(c, z, y, x)` at
/// `(c, z + p, y + p, x + p)`, rows at least `row` long.
struct Padded {
    data: Vec<f32>,
    depth: usize,
    height: usize,
    row: usize,
}

impl Padded {
    fn new(x: &Tensor, p: usize, row: usize) -> Self {
        let [c, d, h, w] = x.shape;
        let (depth, height) = (d + 2 * p, h + 2 * p);
        let mut data = vec![0f32; c * depth * height * row];
        for cc in 0..c {
            for z in 0..d {
                for y in 0..h {
                    let from = x.index(cc, z, y, 0);
                    let to = ((cc * depth + z + p) * height + y + p) * row + p;
                    data[to..to + w].copy_from_slice(&x.data[from..from + w]);
                }
            }
        }
        Self {
            data,
            depth,
            height,
            row,
        }
    }

    /// Row `(c, z, y)` of the padded grid.
    #[inline]
    fn row(&self, c: usize, z: usize, y: usize) -> &[f32] {
        let at = ((c * self.depth + z) * self.height + y) * self.row;
        &self.data[at..at + self.row]
    }
}

#[inline]
fn load(values: &[f32]) -> f32x8 {
    let lanes: [f32; LANES] = values[..LANES].try_into().unwrap_or([0.0; LANES]);
    f32x8::from(lanes)
}

/// `out[o][z] = bias[o] + Σ_{i,t} w[o][i][t] · x[i][z − k/2 + t]` (zero outside), `weight`
/// `[cout][cin][k][k][k]` as PyTorch's Conv3d. `k` is 1, 3, 5 or 7.
pub fn conv3d_same(x: &Tensor, weight: &[f32], cout: usize, k: usize, bias: Option<&[f32]>) -> Tensor {
    match k {
        1 => conv_k::<1>(x, weight, cout, bias),
        3 => conv_k::<3>(x, weight, cout, bias),
        5 => conv_k::<5>(x, weight, cout, bias),
        _ => conv_k::<7>(x, weight, cout, bias),
    }
}

fn conv_k<const K: usize>(x: &Tensor, weight: &[f32], cout: usize, bias: Option<&[f32]>) -> Tensor {
    let [cin, d, h, w] = x.shape;
    let p = K / 2;
    let blocks = w.div_ceil(BLOCK);
    let padded = Padded::new(x, p, blocks * BLOCK + K - 1);
    let groups = cout.div_ceil(GROUP);
    // Weights per group as [i][td][th][tw][4] (missing channels zero).
    let taps = K * K * K;
    let mut packed = vec![0f32; groups * cin * taps * GROUP];
    for o in 0..cout {
        for i in 0..cin {
            for t in 0..taps {
                packed[((o / GROUP * cin + i) * taps + t) * GROUP + o % GROUP] = weight[(o * cin + i) * taps + t];
            }
        }
    }
    let plane = h * w;
    let jobs: Vec<(usize, usize)> = (0..groups).flat_map(|g| (0..d).map(move |z| (g, z))).collect();
    let planes: Vec<Vec<f32>> = jobs
        .par_iter()
        .map(|&(g, z)| {
            let mut out = vec![0f32; GROUP * plane];
            let weights = &packed[g * cin * taps * GROUP..(g + 1) * cin * taps * GROUP];
            for y in 0..h {
                for b in 0..blocks {
                    let x0 = b * BLOCK;
                    let mut acc = [[f32x8::ZERO; VECTORS]; GROUP];
                    for i in 0..cin {
                        for td in 0..K {
                            for th in 0..K {
                                let row = &padded.row(i, z + td, y + th)[x0..x0 + BLOCK + K - 1];
                                let tap = ((i * K + td) * K + th) * K * GROUP;
                                let wk = &weights[tap..tap + K * GROUP];
                                for tw in 0..K {
                                    let xs: [f32x8; VECTORS] = std::array::from_fn(|j| load(&row[tw + LANES * j..]));
                                    for (o, acc_o) in acc.iter_mut().enumerate() {
                                        let wv = f32x8::splat(wk[tw * GROUP + o]);
                                        for (a, xv) in acc_o.iter_mut().zip(&xs) {
                                            *a = xv.mul_add(wv, *a);
                                        }
                                    }
                                }
                            }
                        }
                    }
                    let columns = BLOCK.min(w - x0);
                    for (o, acc_o) in acc.iter().enumerate() {
                        let lanes: [[f32; LANES]; VECTORS] = acc_o.map(|v| v.to_array());
                        let dst = &mut out[o * plane + y * w + x0..o * plane + y * w + x0 + columns];
                        for (c, v) in dst.iter_mut().enumerate() {
                            *v = lanes[c / LANES][c % LANES];
                        }
                    }
                }
            }
            out
        })
        .collect();
    let mut out = Tensor::zeros([cout, d, h, w]);
    for ((g, z), values) in jobs.iter().zip(planes) {
        for o in 0..GROUP.min(cout - g * GROUP) {
            let channel = g * GROUP + o;
            let add = bias.map_or(0.0, |b| b[channel]);
            let at = out.index(channel, *z, 0, 0);
            for (dst, v) in out.data[at..at + plane]
                .iter_mut()
                .zip(&values[o * plane..(o + 1) * plane])
            {
                *dst = v + add;
            }
        }
    }
    out
}

/// The kernel of the input gradient: `[cin][cout][k³]` with every tap flipped, so that the
/// gradient of a "same" convolution is itself a "same" convolution.
pub fn flip_transpose(weight: &[f32], cout: usize, cin: usize, k: usize) -> Vec<f32> {
    let taps = k * k * k;
    let mut out = vec![0f32; weight.len()];
    for o in 0..cout {
        for i in 0..cin {
            for t in 0..taps {
                out[(i * cout + o) * taps + taps - 1 - t] = weight[(o * cin + i) * taps + t];
            }
        }
    }
    out
}

/// Gradient of the input of [`conv3d_same`] (`cin` channels) given the output gradient.
pub fn conv3d_same_input_grad(grad: &Tensor, weight: &[f32], cin: usize, k: usize) -> Tensor {
    let cout = grad.shape[0];
    conv3d_same(grad, &flip_transpose(weight, cout, cin, k), cin, k, None)
}

/// Kernel taps handled together by the weight gradient (4 channels × 3 taps accumulators).
const TAP_RUN: usize = 3;

/// Gradient of the weights of [`conv3d_same`]: `dw[o][i][t] = Σ_z grad[o][z] · x[i][z − k/2 + t]`
/// (`[cout][cin][k][k][k]`), accumulated per row in vectors and across rows in `f64`.
pub fn conv3d_same_weight_grad(x: &Tensor, grad: &Tensor, k: usize) -> Vec<f32> {
    match k {
        1 => weight_grad_k::<1>(x, grad),
        3 => weight_grad_k::<3>(x, grad),
        5 => weight_grad_k::<5>(x, grad),
        _ => weight_grad_k::<7>(x, grad),
    }
}

fn weight_grad_k<const K: usize>(x: &Tensor, grad: &Tensor) -> Vec<f32> {
    let [cin, d, h, w] = x.shape;
    let cout = grad.shape[0];
    let p = K / 2;
    let row = w.div_ceil(LANES) * LANES;
    let xs = Padded::new(x, p, row + K - 1);
    let gs = Padded::new(grad, 0, row);
    let groups = cout.div_ceil(GROUP);
    let taps = K * K * K;
    let len = groups * GROUP * cin * taps;
    let sums = (0..d)
        .into_par_iter()
        .fold(
            || vec![0f64; len],
            |mut acc, z| {
                for y in 0..h {
                    for g in 0..groups {
                        let gr: [&[f32]; GROUP] = std::array::from_fn(|o| {
                            let channel = (g * GROUP + o).min(cout - 1);
                            &gs.row(channel, z, y)[..row]
                        });
                        for i in 0..cin {
                            for td in 0..K {
                                for th in 0..K {
                                    let xr = &xs.row(i, z + td, y + th)[..row + K - 1];
                                    for tw0 in (0..K).step_by(TAP_RUN) {
                                        let run = TAP_RUN.min(K - tw0);
                                        let mut v = [[f32x8::ZERO; TAP_RUN]; GROUP];
                                        for xb in (0..row).step_by(LANES) {
                                            let xv: [f32x8; TAP_RUN] = std::array::from_fn(|j| {
                                                load(&xr[(xb + tw0 + j).min(row + K - 1 - LANES)..])
                                            });
                                            for (o, v_o) in v.iter_mut().enumerate() {
                                                let gv = load(&gr[o][xb..]);
                                                for (a, xj) in v_o.iter_mut().zip(&xv) {
                                                    *a = xj.mul_add(gv, *a);
                                                }
                                            }
                                        }
                                        for (o, v_o) in v.iter().enumerate() {
                                            let base = (((g * GROUP + o) * cin + i) * K + td) * K + th;
                                            for (j, vj) in v_o.iter().enumerate().take(run) {
                                                acc[base * K + tw0 + j] += f64::from(vj.reduce_add());
                                            }
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
                acc
            },
        )
        .reduce(
            || vec![0f64; len],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x += y;
                }
                a
            },
        );
    sums[..cout * cin * taps].iter().map(|v| *v as f32).collect()
}

/// A transposed convolution (kernel 3, stride 2, padding 1, output padding 1; `weight`
/// `[cin][cout][3][3][3]` as PyTorch's ConvTranspose3d) as the kernel of a "same" convolution of
/// the zero-upsampled input: `out = conv3d_same(upsample2_zeros(x), transposed_as_conv(w))`.
pub fn transposed_as_conv(weight: &[f32], cin: usize, cout: usize) -> Vec<f32> {
    // ConvTranspose's [cin][cout] is the gradient kernel's layout of a conv [cout][cin]: the same
    // flip with the roles swapped.
    flip_transpose(weight, cin, cout, 3)
}

/// Weight gradient of a transposed convolution in PyTorch's `[cin][cout][3][3][3]` layout, from
/// the gradient of the equivalent convolution's weights ([`transposed_as_conv`]).
pub fn transposed_weight_grad(conv_grad: &[f32], cin: usize, cout: usize) -> Vec<f32> {
    flip_transpose(conv_grad, cout, cin, 3)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::super::reference;
    use super::*;

    /// A deterministic pseudo-random tensor in [−1, 1].
    pub(crate) fn random(shape: [usize; 4], seed: u64) -> Tensor {
        let n = shape.iter().product();
        Tensor {
            shape,
            data: random_values(n, seed),
        }
    }

    pub(crate) fn random_values(n: usize, seed: u64) -> Vec<f32> {
        let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (0..n)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    fn assert_close(got: &[f32], expected: &[f32], tolerance: f32, what: &str) {
        assert_eq!(got.len(), expected.len(), "{what}");
        for (i, (a, b)) in got.iter().zip(expected).enumerate() {
            assert!((a - b).abs() <= tolerance * (1.0 + b.abs()), "{what}[{i}]: {a} vs {b}");
        }
    }

    #[test]
    fn fast_convolution_matches_the_plain_loops_on_random_shapes() {
        // Widths around the 24-column block and the 8 lanes; channel counts off the group of 4.
        let cases = [
            ([1, 5, 6, 7], 4, 7),
            ([4, 3, 4, 25], 4, 5),
            ([8, 4, 5, 33], 4, 7),
            ([4, 6, 3, 48], 1, 3),
            ([3, 2, 3, 9], 6, 3),
            ([2, 3, 2, 5], 3, 1),
        ];
        for (seed, (shape, cout, k)) in cases.into_iter().enumerate() {
            let x = random(shape, seed as u64);
            let weight = random_values(cout * shape[0] * k * k * k, 100 + seed as u64);
            let bias = random_values(cout, 200 + seed as u64);
            let mut expected = reference::conv3d(&x, &weight, cout, k, 1);
            for (c, chunk) in expected
                .data
                .chunks_mut(expected.shape[1] * expected.shape[2] * expected.shape[3])
                .enumerate()
            {
                for v in chunk {
                    *v += bias[c];
                }
            }
            let got = conv3d_same(&x, &weight, cout, k, Some(&bias));
            assert_eq!(got.shape, expected.shape);
            assert_close(&got.data, &expected.data, 1e-4, &format!("forward {shape:?} k{k}"));

            // Input gradient: <grad, conv(x)> = <input_grad(grad), x> and the reference's form.
            let grad = random(got.shape, 300 + seed as u64);
            let input_grad = conv3d_same_input_grad(&grad, &weight, shape[0], k);
            let expected_input_grad =
                reference::conv3d(&grad, &flip_transpose(&weight, cout, shape[0], k), shape[0], k, 1);
            assert_close(&input_grad.data, &expected_input_grad.data, 1e-4, "input grad");
            let plain = reference::conv3d(&x, &weight, cout, k, 1);
            let lhs: f64 = grad.data.iter().zip(&plain.data).map(|(a, b)| f64::from(a * b)).sum();
            let rhs: f64 = input_grad.data.iter().zip(&x.data).map(|(a, b)| f64::from(a * b)).sum();
            assert!((lhs - rhs).abs() < 1e-3 * (1.0 + lhs.abs()), "adjoint {lhs} {rhs}");

            let weight_grad = conv3d_same_weight_grad(&x, &grad, k);
            let expected_weight_grad = reference::conv3d_weight_grad(&x, &grad, k);
            assert_close(&weight_grad, &expected_weight_grad, 1e-4, "weight grad");
        }
    }

    #[test]
    fn strided_and_transposed_convolutions_through_the_same_convolution() {
        for (seed, shape) in [[4, 4, 6, 10], [4, 5, 7, 9]].into_iter().enumerate() {
            let x = random(shape, 10 + seed as u64);
            let weight = random_values(4 * 4 * 27, 20 + seed as u64);
            let strided = conv3d_same(&x, &weight, 4, 3, None).subsample2();
            let expected = reference::conv3d(&x, &weight, 4, 3, 2);
            assert_eq!(strided.shape, expected.shape);
            assert_close(&strided.data, &expected.data, 1e-4, "stride 2");

            let transposed = conv3d_same(
                &x.upsample2_zeros([2 * shape[1], 2 * shape[2], 2 * shape[3]]),
                &transposed_as_conv(&weight, 4, 4),
                4,
                3,
                None,
            );
            let expected = reference::conv_transpose3d(&x, &weight, 4);
            assert_eq!(transposed.shape, expected.shape);
            assert_close(&transposed.data, &expected.data, 1e-4, "transposed");
        }
    }
}
