//! Plain loop implementations of the layers, straight from PyTorch's definitions, in `f64`
//! accumulators: the oracles the fast kernels of [`super::conv`] are tested against.

use super::Tensor;

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
                                    let sd = (stride * zd + td) as isize - p;
                                    let sh = (stride * zh + th) as isize - p;
                                    let sw = (stride * zw + tw) as isize - p;
                                    if sd < 0
                                        || sh < 0
                                        || sw < 0
                                        || sd >= d as isize
                                        || sh >= h as isize
                                        || sw >= w as isize
                                    {
                                        continue;
                                    }
                                    let wv = weight[(((o * cin + i) * k + td) * k + th) * k + tw];
                                    let xv = x.data[x.index(i, sd as usize, sh as usize, sw as usize)];
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
                                    let jd = (2 * zd + td) as isize - 1;
                                    let jh = (2 * zh + th) as isize - 1;
                                    let jw = (2 * zw + tw) as isize - 1;
                                    if jd < 0
                                        || jh < 0
                                        || jw < 0
                                        || jd >= shape[1] as isize
                                        || jh >= shape[2] as isize
                                        || jw >= shape[3] as isize
                                    {
                                        continue;
                                    }
                                    let wv = f64::from(weight[(((i * cout + o) * 3 + td) * 3 + th) * 3 + tw]);
                                    let at = ((o * shape[1] + jd as usize) * shape[2] + jh as usize) * shape[3]
                                        + jw as usize;
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
                                    let sd = (zd + td) as isize - p;
                                    let sh = (zh + th) as isize - p;
                                    let sw = (zw + tw) as isize - p;
                                    if sd < 0
                                        || sh < 0
                                        || sw < 0
                                        || sd >= d as isize
                                        || sh >= h as isize
                                        || sw >= w as isize
                                    {
                                        continue;
                                    }
                                    sum += f64::from(grad.data[grad.index(o, zd, zh, zw)])
                                        * f64::from(x.data[x.index(i, sd as usize, sh as usize, sw as usize)]);
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
