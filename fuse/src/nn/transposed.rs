//! The stride-2 transposed convolution at inference (PyTorch's `ConvTranspose3d(k = 3,
//! stride = 2, padding = 1, output_padding = 1)`, MFuseNet's `up1` and `up2`), read by output
//! parity instead of as a "same" convolution of a zero-upsampled input.
//!
//! Along each axis an even output `2j` takes one tap of the input (`j`), an odd output `2j + 1`
//! two (`j` and `j + 1`): 1.5³ ≈ 3.4 of the kernel's 27 taps on average. The "same" convolution
//! of the zero-upsampled input multiplies all 27, seven in eight by a zero, and first writes
//! and pads that input eight times the size of the layer's. Training keeps that form
//! ([`crate::nn::conv`]'s gradients); only the forward in eval mode takes this one.

use rayon::prelude::*;

use super::Tensor;

/// Per output index along one axis, the input indices it reads and the tap of the equivalent
/// "same" convolution's kernel (`[cout][cin][3][3][3]`, [`super::conv::transposed_as_conv`]):
/// `2j` ← `(j, 1)`; `2j + 1` ← `(j, 0)` and `(j + 1, 2)` where `j + 1` is inside.
fn taps(z: usize, n: usize) -> ([(usize, usize); 2], usize) {
    let j = z / 2;
    if z.is_multiple_of(2) {
        ([(j, 1), (0, 0)], 1)
    } else if j + 1 < n {
        ([(j, 0), (j + 1, 2)], 2)
    } else {
        ([(j, 0), (0, 0)], 1)
    }
}

/// `max(0, ·)` where `relu`, of the transposed convolution of `x` (`[cin][d][h][w]`) with the
/// equivalent "same" convolution's kernel `weight` (`[cout][cin][3][3][3]`, a BatchNorm folded in
/// or not) plus `bias`: `[cout][2d][2h][2w]`. The sums differ from the zero-upsampled
/// convolution's only by their order (rounding). A `weight` shorter than `cout · cin · 27` (a
/// caller's mistake) gives zeros rather than a read past its end.
pub fn transposed_conv3d_eval(x: &Tensor, weight: &[f32], cout: usize, bias: Option<&[f32]>, relu: bool) -> Tensor {
    let [cin, d, h, w] = x.shape;
    let (od, oh, ow) = (2 * d, 2 * h, 2 * w);
    let mut out = Tensor::zeros([cout, od, oh, ow]);
    let plane_len = oh * ow;
    if plane_len == 0 || cin == 0 || weight.len() < cout * cin * 27 {
        return out;
    }
    // One output plane of one channel per task: `o · 2d + zd`.
    out.data.par_chunks_mut(plane_len).enumerate().for_each_init(
        || (vec![0f32; w], vec![0f32; w]),
        |(even, odd), (index, plane)| {
            let (o, zd) = (index / od, index % od);
            let b = bias.and_then(|b| b.get(o)).copied().unwrap_or(0.0);
            let (dtaps, nd) = taps(zd, d);
            for (zh, row) in plane.chunks_exact_mut(ow).enumerate() {
                let (htaps, nh) = taps(zh, h);
                even.fill(b);
                odd.fill(b);
                for i in 0..cin {
                    for &(jd, td) in &dtaps[..nd] {
                        for &(jh, th) in &htaps[..nh] {
                            let at = ((i * d + jd) * h + jh) * w;
                            let src = &x.data[at..at + w];
                            let k = (((o * cin + i) * 3 + td) * 3 + th) * 3;
                            let (w0, w1, w2) = (weight[k], weight[k + 1], weight[k + 2]);
                            // 2j ← x[j]·w1; 2j + 1 ← x[j]·w0 + x[j + 1]·w2.
                            for (e, s) in even.iter_mut().zip(src) {
                                *e += s * w1;
                            }
                            for ((q, s), next) in odd.iter_mut().zip(src).zip(&src[1..]) {
                                *q += s * w0 + next * w2;
                            }
                            if let (Some(q), Some(s)) = (odd.last_mut(), src.last()) {
                                *q += s * w0;
                            }
                        }
                    }
                }
                for ((pair, e), q) in row.chunks_exact_mut(2).zip(even.iter()).zip(odd.iter()) {
                    let (e, q) = if relu { (e.max(0.0), q.max(0.0)) } else { (*e, *q) };
                    pair[0] = e;
                    pair[1] = q;
                }
            }
        },
    );
    out
}

#[cfg(test)]
mod tests {
    use super::super::conv::{tests::random, transposed_as_conv};
    use super::super::reference;
    use super::*;

    #[test]
    fn the_parity_form_equals_pytorchs_transposed_convolution() {
        // Odd and even sizes, one row or column, several channel counts.
        for (shape, cout) in [
            ([4, 3, 5, 7], 4),
            ([2, 1, 1, 1], 3),
            ([3, 2, 4, 1], 2),
            ([8, 2, 3, 6], 4),
            ([1, 3, 1, 9], 1),
        ] {
            let x = random(shape, 11);
            let cin = shape[0];
            let weight_t = random([cin, cout, 9, 3], 5).data; // [cin][cout][3][3][3]
            let expected = reference::conv_transpose3d(&x, &weight_t, cout);
            let bias: Vec<f32> = (0..cout).map(|o| 0.1 * o as f32 - 0.15).collect();
            let got = transposed_conv3d_eval(&x, &transposed_as_conv(&weight_t, cin, cout), cout, Some(&bias), false);
            assert_eq!(got.shape, expected.shape);
            let plane = expected.channel_len();
            for (at, (g, e)) in got.data.iter().zip(&expected.data).enumerate() {
                let e = e + bias[at / plane];
                assert!(
                    (g - e).abs() < 1e-5 * (1.0 + e.abs()),
                    "{shape:?} at {at}: {g} against {e}"
                );
            }
            let rectified =
                transposed_conv3d_eval(&x, &transposed_as_conv(&weight_t, cin, cout), cout, Some(&bias), true);
            for (r, g) in rectified.data.iter().zip(&got.data) {
                assert_eq!(*r, g.max(0.0));
            }
        }
    }
}
