//! Plain loop implementations of the layers, straight from PyTorch's definitions, in `f64`
//! accumulators: the oracles the fast kernels of [`super::conv`] are tested against.

use super::Tensor;

/// A position in the zero-padded input (`padding` on each side) as an index of the unpadded
/// `shape`, or `None` in the padding.
fn unpadded(at: [usize; 3], padding: isize, shape: [usize; 3]) -> Option<[usize; 3]> {
    let mut out = [0; 3];
    for ((o, a), n) in out.iter_mut().zip(at).zip(shape) {
        let v = a as isize - padding;
        if v < 0 || v >= n as isize {
            return None;
        }
        *o = v as usize;
    }
    Some(out)
}

/// `Conv3d(cin, cout, k, stride, padding = k / 2, bias=False)` as PyTorch defines it:
/// `out[o][z] = Σ_{i, t} w[o][i][t] · x[i][stride·z − k/2 + t]` (zero outside).
/// `weight` is `[cout][cin][k][k][k]`.
pub fn conv3d(x: &Tensor, weight: &[f32], cout: usize, k: usize, stride: usize) -> Tensor {
    let [cin, d, h, w] = x.shape;
    let p = (k / 2) as isize;
    let out_dim = |n: usize| (n + 2 * (k / 2) - k) / stride + 1;
    let shape = [cout, out_dim(d), out_dim(h), out_dim(w)];
    let mut out = Tensor::zeros(shape);
    for o in 0..cout {
        for zd in 0..shape[1] {
            for zh in 0..shape[2] {
                for zw in 0..shape[3] {
                    let mut sum = 0f64;
                    for i in 0..cin {
                        for td in 0..k {
                            for th in 0..k {
                                for tw in 0..k {
                                    let at = [stride * zd + td, stride * zh + th, stride * zw + tw];
                                    let Some([sd, sh, sw]) = unpadded(at, p, [d, h, w]) else {
                                        continue;
                                    };
                                    let wv = weight[(((o * cin + i) * k + td) * k + th) * k + tw];
                                    let xv = x.data[x.index(i, sd, sh, sw)];
                                    sum += f64::from(wv) * f64::from(xv);
                                }
                            }
                        }
                    }
                    let at = out.index(o, zd, zh, zw);
                    out.data[at] = sum as f32;
                }
            }
        }
    }
    out
}

/// `ConvTranspose3d(cin, cout, 3, stride=2, padding=1, output_padding=1, bias=False)`:
/// `out[o][j] += x[i][z] · w[i][o][t]` for every `j = 2z − 1 + t` in range (output `2·` the
/// input size). `weight` is `[cin][cout][3][3][3]`.
pub fn conv_transpose3d(x: &Tensor, weight: &[f32], cout: usize) -> Tensor {
    let [cin, d, h, w] = x.shape;
    let shape = [cout, 2 * d, 2 * h, 2 * w];
    let mut acc = vec![0f64; shape.iter().product()];
    for i in 0..cin {
        for zd in 0..d {
            for zh in 0..h {
                for zw in 0..w {
                    let xv = f64::from(x.data[x.index(i, zd, zh, zw)]);
                    for o in 0..cout {
                        for td in 0..3 {
                            for th in 0..3 {
                                for tw in 0..3 {
                                    let full = [2 * zd + td, 2 * zh + th, 2 * zw + tw];
                                    let Some([jd, jh, jw]) = unpadded(full, 1, [shape[1], shape[2], shape[3]]) else {
                                        continue;
                                    };
                                    let wv = f64::from(weight[(((i * cout + o) * 3 + td) * 3 + th) * 3 + tw]);
                                    let at = ((o * shape[1] + jd) * shape[2] + jh) * shape[3] + jw;
                                    acc[at] += xv * wv;
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    Tensor {
        shape,
        data: acc.into_iter().map(|v| v as f32).collect(),
    }
}

/// Gradient of `Σ grad · conv3d(x, w)` with respect to `w` for a stride-1 "same" convolution:
/// `dw[o][i][t] = Σ_z grad[o][z] · x[i][z − k/2 + t]`.
pub fn conv3d_weight_grad(x: &Tensor, grad: &Tensor, k: usize) -> Vec<f32> {
    let [cin, d, h, w] = x.shape;
    let cout = grad.shape[0];
    let p = (k / 2) as isize;
    let mut dw = vec![0f32; cout * cin * k * k * k];
    for o in 0..cout {
        for i in 0..cin {
            for td in 0..k {
                for th in 0..k {
                    for tw in 0..k {
                        let mut sum = 0f64;
                        for zd in 0..d {
                            for zh in 0..h {
                                for zw in 0..w {
                                    let Some([sd, sh, sw]) = unpadded([zd + td, zh + th, zw + tw], p, [d, h, w]) else {
                                        continue;
                                    };
                                    sum += f64::from(grad.data[grad.index(o, zd, zh, zw)])
                                        * f64::from(x.data[x.index(i, sd, sh, sw)]);
                                }
                            }
                        }
                        dw[(((o * cin + i) * k + td) * k + th) * k + tw] = sum as f32;
                    }
                }
            }
        }
    }
    dw
}

/// The mean (channels `0..C`) and the maximum (channels `C..2C`) across `views`, each `[C, D, H,
/// W]`, value by value in `f64`.
pub fn mean_max(views: &[Tensor]) -> Tensor {
    let Some(first) = views.first() else {
        return Tensor::zeros([0; 4]);
    };
    let [c, d, h, w] = first.shape;
    let mut out = Tensor::zeros([2 * c, d, h, w]);
    let n = first.data.len();
    for i in 0..n {
        let values: Vec<f64> = views.iter().map(|v| f64::from(v.data[i])).collect();
        out.data[i] = (values.iter().sum::<f64>() / values.len() as f64) as f32;
        out.data[n + i] = values.iter().copied().fold(f64::NEG_INFINITY, f64::max) as f32;
    }
    out
}
