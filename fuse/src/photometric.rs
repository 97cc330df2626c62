//! Sub-pixel refinement by photometric consistency: each estimate moves, by Gauss–Newton steps
//! on the views' brightness, to where the reference matches the neighbours' images sampled at
//! the continuous disparity (bilinear), instead of to the vertex of a curve through costs at
//! integer disparities, which locks to the pixel grid wherever the costs' shape is not the one
//! the fit assumes.
//!
//! One step: every pixel `u` and view `v` that sees it give the linearised residual
//! `r(d) ≈ r_v(u) + J_v(u)·(d − d_u)`, where `r_v(u) = I_ref(u) − I_v(u − o_v·d_u)` and
//! `J_v(u) = ∇I_v · o_v` there (`o_v` the view's offset in baselines times its baseline ratio,
//! `d_u` the current estimate), so the pixel's own solution is `t = d_u − r⁄J`, as sure as `J²`
//! is large. Over each pixel's `(2ρ+1)²` window those solutions, weighted by `J²`, are fitted
//! by a plane (a slanted surface's disparity is linear in position; a weighted mean would read
//! it at the weights' centroid), read at the pixel. The sums are box filters of per-pixel
//! quantities, so a step costs a few passes over the image whatever the window.
//!
//! Views are chosen per pixel by their window's mean squared residual at the estimates: both of
//! each opposite pair, but one whose residual is far above the other's (it does not see the
//! surface: an occlusion); a view without an opposite where its residual is near the best
//! view's. An estimate keeps its start where the window has too little gradient, where the
//! fitted plane leaves more than `max_misfit` grey levels (RMS) unexplained (a depth edge, a
//! reflection, a thin part across the window: the model does not hold there), and never moves
//! more than `max_shift_px` from its start.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::image::{DisparityImage, Image};
use crate::volume::Problem;

/// How [`refine_photometric`] refines.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Photometric {
    /// Window radius (px; side 2ρ+1).
    pub window_radius_px: usize,
    /// Gauss–Newton steps.
    pub iterations: usize,
    /// The largest change of an estimate (px) from its start.
    pub max_shift_px: f32,
    /// A view is left out where its window's mean squared residual is over this many times its
    /// opposite's (or, without an opposite in the set, the best view's) plus one grey level²:
    /// it does not see the surface there (an occlusion).
    pub occluded_ratio: f32,
    /// The least summed squared gradient (grey levels² per window pixel) a window must have for
    /// its estimate to move.
    pub min_gradient: f32,
    /// Passes of a [1 2 1]/4 blur over every view's grey levels first (bilinear interpolation
    /// of fine texture is biased towards the samples).
    pub blur_passes: usize,
    /// The largest RMS brightness difference (grey levels) the fitted plane leaves over the
    /// window for the estimate to move.
    pub max_misfit: f32,
    /// The largest standard error (px) of the refined value for the estimate to move.
    pub max_error_px: f32,
}

impl Default for Photometric {
    fn default() -> Self {
        Self {
            window_radius_px: 7,
            iterations: 2,
            max_shift_px: 0.25,
            occluded_ratio: 2.0,
            min_gradient: 4.0,
            blur_passes: 0,
            max_misfit: 3.0,
            max_error_px: 0.05,
        }
    }
}

/// A view's grey levels and their gradients, as `f32` planes.
struct Plane {
    grey: Vec<f32>,
    dx: Vec<f32>,
    dy: Vec<f32>,
}

impl Plane {
    fn new(image: &Image, blur_passes: usize) -> Self {
        let (w, h) = (image.width, image.height);
        let grey = grey_levels(image, blur_passes);
        let mut dx = vec![0f32; w * h];
        let mut dy = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let at = y * w + x;
                let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
                let (t, b) = (y.saturating_sub(1), (y + 1).min(h - 1));
                dx[at] = (grey[y * w + r] - grey[y * w + l]) / (r - l).max(1) as f32;
                dy[at] = (grey[b * w + x] - grey[t * w + x]) / (b - t).max(1) as f32;
            }
        }
        Self { grey, dx, dy }
    }

    /// Grey level and gradient at `(x, y)` (bilinear), `None` outside the image.
    fn sample(&self, (w, h): (usize, usize), x: f32, y: f32) -> Option<[f32; 3]> {
        if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let at = |plane: &[f32]| {
            let top = plane[y0 * w + x0] * (1.0 - fx) + plane[y0 * w + x1] * fx;
            let bottom = plane[y1 * w + x0] * (1.0 - fx) + plane[y1 * w + x1] * fx;
            top * (1.0 - fy) + bottom * fy
        };
        Some([at(&self.grey), at(&self.dx), at(&self.dy)])
    }
}

/// An image's grey levels (Rec. 601 luma) as `f32`, blurred `blur_passes` times: the
/// fractions `Image::to_gray` rounds away are what the sub-pixel steps read.
fn grey_levels(image: &Image, blur_passes: usize) -> Vec<f32> {
    let mut grey: Vec<f32> = if image.channels == 3 {
        image
            .data
            .chunks_exact(3)
            .map(|p| 0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]))
            .collect()
    } else {
        image.data.iter().map(|v| f32::from(*v)).collect()
    };
    for _ in 0..blur_passes {
        grey = blurred(&grey, (image.width, image.height));
    }
    grey
}

/// `plane` blurred by [1 2 1]/4 along both axes (borders repeated).
fn blurred(plane: &[f32], (w, h): (usize, usize)) -> Vec<f32> {
    let mut across = vec![0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
            across[y * w + x] = 0.25 * (plane[y * w + l] + 2.0 * plane[y * w + x] + plane[y * w + r]);
        }
    }
    let mut out = vec![0f32; w * h];
    for y in 0..h {
        let (t, b) = (y.saturating_sub(1), (y + 1).min(h - 1));
        for x in 0..w {
            out[y * w + x] = 0.25 * (across[t * w + x] + 2.0 * across[y * w + x] + across[b * w + x]);
        }
    }
    out
}

/// Per view and pixel: the residual at the pixel's own estimate and its derivative in `d`
/// (`NaN` where the view does not see the correspondence).
fn linearised(
    reference: &[f32],
    plane: &Plane,
    (ox, oy): (f32, f32),
    disparity: &[f32],
    (w, h): (usize, usize),
) -> (Vec<f32>, Vec<f32>) {
    let mut residual = vec![f32::NAN; w * h];
    let mut slope = vec![f32::NAN; w * h];
    residual
        .par_chunks_mut(w)
        .zip(slope.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (r_row, j_row))| {
            for x in 0..w {
                let d = disparity[y * w + x];
                if !d.is_finite() {
                    continue;
                }
                if let Some([value, gx, gy]) = plane.sample((w, h), x as f32 - ox * d, y as f32 - oy * d) {
                    r_row[x] = reference[y * w + x] - value;
                    j_row[x] = gx * ox + gy * oy;
                }
            }
        });
    (residual, slope)
}

/// The weighted least-squares plane `t ≈ a + gx·x + gy·y` through the window pixels' solutions,
/// from its normal equations' moments `m` (Σw, Σwx, Σwy, Σwx², Σwxy, Σwy²) and right-hand
/// side `c` (Σwt, Σwtx, Σwty): `[a, gx, gy]`, or the weighted mean `[Σwt ⁄ Σw, 0, 0]` where the
/// positions do not determine a plane (the weights on one line); and the first diagonal entry
/// of the moments' inverse (`a`'s variance per unit of residual variance).
fn fitted_plane(m: [f64; 6], c: [f64; 3]) -> Option<([f64; 3], f64)> {
    let a = [[m[0], m[1], m[2]], [m[1], m[3], m[4]], [m[2], m[4], m[5]]];
    let det = |a: [[f64; 3]; 3]| {
        a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
            + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
    };
    let full = det(a);
    if full.abs() > 1e-9 * m[0].powi(3).max(f64::MIN_POSITIVE) {
        // Cramer's rule.
        let mut out = [0f64; 3];
        for (k, coefficient) in out.iter_mut().enumerate() {
            let mut replaced = a;
            for (row, value) in replaced.iter_mut().zip(c) {
                row[k] = value;
            }
            *coefficient = det(replaced) / full;
        }
        return Some((out, (m[3] * m[5] - m[4] * m[4]) / full));
    }
    (m[0] > 0.0).then(|| ([c[0] / m[0], 0.0, 0.0], 1.0 / m[0]))
}

/// Rows of the output refined together (their window sums held at once).
const BAND_ROWS: usize = 32;
/// Per view and pixel, the window sums of: the valid samples, their squared residuals, and of
/// `w = J²` times 1, x, y, x², x·y, y², t, t·x, t·y, t² (`t = d_u − r⁄J`, positions from the
/// band's first row), and the samples with a slope.
const QUANTITIES: usize = 13;
const COUNT: usize = 0;
const SQUARED: usize = 1;
const W: usize = 2;
const WX: usize = 3;
const WY: usize = 4;
const WXX: usize = 5;
const WXY: usize = 6;
const WYY: usize = 7;
const WT: usize = 8;
const WTX: usize = 9;
const WTY: usize = 10;
const WTT: usize = 11;
const COUNT_USED: usize = 12;

/// The [`QUANTITIES`] summed over the `(2r+1)²` window of every pixel of the `rows` rows from
/// `y0` (`[pixel][quantity]`, pixels in row order), from one view's residuals and slopes at
/// the estimates `disparity`; windows are cut at the image's borders.
fn window_sums(
    (residual, slope): (&[f32], &[f32]),
    disparity: &[f32],
    (w, h): (usize, usize),
    (y0, rows): (usize, usize),
    r: usize,
) -> Vec<f64> {
    let (top, bottom) = (y0.saturating_sub(r), (y0 + rows + r).min(h));
    let halo = bottom - top;
    // Each halo row's values, then their sums along the row (a running window).
    let mut across = vec![0f64; halo * w * QUANTITIES];
    let mut values = vec![0f64; w * QUANTITIES];
    for (k, y) in (top..bottom).enumerate() {
        values.fill(0.0);
        for x in 0..w {
            let at = y * w + x;
            let (rv, jv, d) = (residual[at], slope[at], disparity[at]);
            if !rv.is_finite() {
                continue;
            }
            let q = &mut values[x * QUANTITIES..(x + 1) * QUANTITIES];
            let rv = f64::from(rv);
            q[COUNT] = 1.0;
            q[SQUARED] = rv * rv;
            if jv != 0.0 && jv.is_finite() {
                let jv = f64::from(jv);
                let (px, py) = (x as f64, (y as f64) - (y0 as f64));
                let weight = jv * jv;
                let t = f64::from(d) - rv / jv;
                q[W] = weight;
                q[WX] = weight * px;
                q[WY] = weight * py;
                q[WXX] = weight * px * px;
                q[WXY] = weight * px * py;
                q[WYY] = weight * py * py;
                q[WT] = weight * t;
                q[WTX] = weight * t * px;
                q[WTY] = weight * t * py;
                q[WTT] = weight * t * t;
                q[COUNT_USED] = 1.0;
            }
        }
        let row = &mut across[k * w * QUANTITIES..(k + 1) * w * QUANTITIES];
        let mut running = [0f64; QUANTITIES];
        // Columns 0..=r enter before the first output.
        for x in 0..=r.min(w - 1) {
            running
                .iter_mut()
                .zip(&values[x * QUANTITIES..])
                .for_each(|(s, v)| *s += v);
        }
        for x in 0..w {
            row[x * QUANTITIES..(x + 1) * QUANTITIES].copy_from_slice(&running);
            if x + r + 1 < w {
                let entering = &values[(x + r + 1) * QUANTITIES..(x + r + 2) * QUANTITIES];
                running.iter_mut().zip(entering).for_each(|(s, v)| *s += v);
            }
            if x >= r {
                let leaving = &values[(x - r) * QUANTITIES..(x - r + 1) * QUANTITIES];
                running.iter_mut().zip(leaving).for_each(|(s, v)| *s -= v);
            }
        }
    }
    // Then down the columns.
    let mut out = vec![0f64; rows * w * QUANTITIES];
    let row_of = |y: usize| &across[(y - top) * w * QUANTITIES..(y - top + 1) * w * QUANTITIES];
    let mut running = vec![0f64; w * QUANTITIES];
    for y in y0.saturating_sub(r)..(y0 + r + 1).min(h) {
        running.iter_mut().zip(row_of(y)).for_each(|(s, v)| *s += v);
    }
    for k in 0..rows {
        let y = y0 + k;
        out[k * w * QUANTITIES..(k + 1) * w * QUANTITIES].copy_from_slice(&running);
        if k + 1 == rows {
            break;
        }
        if y + r + 1 < h {
            running.iter_mut().zip(row_of(y + r + 1)).for_each(|(s, v)| *s += v);
        }
        if y >= r {
            running.iter_mut().zip(row_of(y - r)).for_each(|(s, v)| *s -= v);
        }
    }
    out
}

/// Refines every finite estimate of `disparity` over `problem`'s views (see the module's doc).
/// Returns how many moved.
pub fn refine_photometric(
    problem: &Problem,
    disparity: &mut DisparityImage,
    config: &Photometric,
) -> Result<usize, FuseError> {
    let reference = &problem.reference;
    let (w, h) = (reference.width, reference.height);
    disparity.check_size(
        w,
        h,
        "disparity map for the photometric refinement (the reference's size)",
    )?;
    if problem.neighbours.is_empty() || config.iterations == 0 {
        return Ok(0);
    }
    let grey = grey_levels(reference, config.blur_passes);
    let planes: Vec<(Plane, (f32, f32))> = problem
        .neighbours
        .iter()
        .map(|n| {
            let s = n.baseline_ratio;
            (
                Plane::new(&n.image, config.blur_passes),
                (n.offset[0] as f32 * s, n.offset[1] as f32 * s),
            )
        })
        .collect();
    // Each view's opposite in the set, if any.
    let opposite: Vec<Option<usize>> = problem
        .neighbours
        .iter()
        .map(|n| {
            problem
                .neighbours
                .iter()
                .position(|m| m.offset == [-n.offset[0], -n.offset[1]])
        })
        .collect();
    let start = disparity.data.clone();
    let r = config.window_radius_px;
    let area = ((2 * r + 1) * (2 * r + 1)) as f64;
    for _ in 0..config.iterations {
        let current = disparity.data.clone();
        let views: Vec<(Vec<f32>, Vec<f32>)> = planes
            .iter()
            .map(|(plane, offset)| linearised(&grey, plane, *offset, &current, (w, h)))
            .collect();
        let band = BAND_ROWS.min(h.max(1));
        disparity
            .data
            .par_chunks_mut(band * w)
            .enumerate()
            .for_each(|(index, rows)| {
                let y0 = index * band;
                let sums: Vec<Vec<f64>> = views
                    .iter()
                    .map(|(residual, slope)| window_sums((residual, slope), &current, (w, h), (y0, rows.len() / w), r))
                    .collect();
                let mut energy = vec![0f64; views.len()];
                for (i, out) in rows.iter_mut().enumerate() {
                    let (x, y) = (i % w, y0 + i / w);
                    if !current[y * w + x].is_finite() {
                        continue;
                    }
                    let quantities = |v: usize| &sums[v][i * QUANTITIES..(i + 1) * QUANTITIES];
                    // Each view's mean squared residual over the window at the estimates.
                    for (v, e) in energy.iter_mut().enumerate() {
                        let q = quantities(v);
                        *e = if q[COUNT] >= 0.5 * area {
                            q[SQUARED] / q[COUNT]
                        } else {
                            f64::INFINITY
                        };
                    }
                    let best = energy.iter().copied().fold(f64::INFINITY, f64::min);
                    if !best.is_finite() {
                        continue;
                    }
                    let mut total = [0f64; QUANTITIES];
                    for (v, e) in energy.iter().enumerate() {
                        let used = e.is_finite()
                            && match opposite[v] {
                                Some(o) => *e <= f64::from(config.occluded_ratio) * e.min(energy[o]) + 1.0,
                                None => *e <= f64::from(config.occluded_ratio) * best + 1.0,
                            };
                        if used {
                            total.iter_mut().zip(quantities(v)).for_each(|(t, q)| *t += q);
                        }
                    }
                    if total[W] < f64::from(config.min_gradient) * area {
                        continue;
                    }
                    // The moments about this pixel (the sums hold positions from the band's
                    // first row and the image's first column).
                    let (cx, cy) = (x as f64, (y - y0) as f64);
                    let m = [
                        total[W],
                        total[WX] - cx * total[W],
                        total[WY] - cy * total[W],
                        total[WXX] - 2.0 * cx * total[WX] + cx * cx * total[W],
                        total[WXY] - cx * total[WY] - cy * total[WX] + cx * cy * total[W],
                        total[WYY] - 2.0 * cy * total[WY] + cy * cy * total[W],
                    ];
                    let c = [total[WT], total[WTX] - cx * total[WT], total[WTY] - cy * total[WT]];
                    let Some((plane, spread)) = fitted_plane(m, c) else {
                        continue;
                    };
                    // The views' brightness the fitted plane leaves unexplained (RMS, grey levels:
                    // Σ J²·(t − plane)² = Σ (r + J·(plane − d_u))²): an edge, a reflection or a
                    // thin part across the window, where the model does not hold.
                    let left = total[WTT] - plane.iter().zip(c).map(|(p, c)| p * c).sum::<f64>();
                    let misfit = (left.max(0.0) / total[COUNT_USED].max(1.0)).sqrt();
                    // The refined value's standard error (px) from the residuals' variance (at least
                    // a grey level's: the sensor's noise) and the window's gradients: faint
                    // texture cannot place it to a fraction of a pixel.
                    let error = misfit.max(1.0) * spread.max(0.0).sqrt();
                    if misfit > f64::from(config.max_misfit) || error > f64::from(config.max_error_px) {
                        continue;
                    }
                    let s = start[y * w + x];
                    *out = (plane[0] as f32).clamp(s - config.max_shift_px, s + config.max_shift_px);
                }
            });
    }
    Ok(disparity
        .data
        .iter()
        .zip(&start)
        .filter(|(a, b)| a.to_bits() != b.to_bits())
        .count())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::subpixel::fixtures::{inner_error, quarter_pixels, slanted};
    use crate::volume::Neighbour;

    #[test]
    fn a_slanted_plane_converges_from_quarter_pixels() {
        let (w, h) = (96, 40);
        let (problem, truth) = slanted(w, h, 4.0, 4.0 / w as f32);
        let mut disparity = quarter_pixels(&truth, w, h);
        let was = inner_error(&disparity, &truth);
        let before = disparity.clone();
        refine_photometric(&problem, &mut disparity, &Photometric::default()).unwrap_or_else(|e| panic!("{e}"));
        let now = inner_error(&disparity, &truth);
        println!("mean error {was:.4} → {now:.4} px");
        assert!(now < 0.3 * was, "mean error {was:.4} → {now:.4} px");
        let config = Photometric::default();
        for (a, b) in before.data.iter().zip(&disparity.data) {
            assert!((a - b).abs() <= config.max_shift_px + 1e-6, "{a} → {b}");
        }
    }

    /// A depth step seen by a left and a right neighbour: a background plane at disparity 4
    /// and, from column `edge` on, a nearer one at 9 that hides part of the background from
    /// each neighbour. Textures are functions of the reference's column on each surface.
    fn step(w: usize, h: usize, edge: usize) -> (Problem, Vec<f32>) {
        let background = |x: f32, y: f32| 128.0 + (x * 0.41).sin() * 60.0 + (y * 0.19 + x * 0.13).cos() * 50.0;
        let foreground = |x: f32, y: f32| 120.0 + (x * 0.29 + 1.0).cos() * 70.0 + (y * 0.31 - x * 0.07).sin() * 40.0;
        let (near, far) = (9.0f32, 4.0f32);
        let edge_f = edge as f32;
        // What a view at offset `o` shows at its column q, row y.
        let seen = |o: f32, q: f32, y: f32| {
            let x_near = q + o * near;
            if x_near >= edge_f {
                foreground(x_near, y)
            } else {
                background(q + o * far, y)
            }
        };
        let image = |o: f32| {
            let mut data = Vec::with_capacity(w * h);
            for y in 0..h {
                for x in 0..w {
                    data.push(seen(o, x as f32, y as f32).clamp(0.0, 255.0) as u8);
                }
            }
            Image::new(w, h, 1, data).unwrap_or_else(|e| panic!("{e}"))
        };
        let neighbour = |o: i32, role: &str| Neighbour {
            image: image(o as f32),
            offset: [o, 0],
            role: role.into(),
            baseline_ratio: 1.0,
        };
        let problem = Problem {
            reference: image(0.0),
            neighbours: vec![neighbour(1, "right"), neighbour(-1, "left")],
            min_disparity: 0,
            num_disparities: 16,
        };
        let truth = (0..h)
            .flat_map(|_| (0..w).map(move |x| if x >= edge { near } else { far }))
            .collect();
        (problem, truth)
    }

    #[test]
    fn a_depth_step_keeps_its_edge_and_its_occlusions() {
        // From the truth 0.25 px off, the planes come back and the columns beside the step,
        // which a neighbour cannot see, get no worse than they started.
        let (w, h, edge) = (96, 32, 48);
        let (problem, truth) = step(w, h, edge);
        let mut disparity = DisparityImage {
            width: w,
            height: h,
            data: truth.iter().map(|t| t + 0.25).collect(),
            confidence: None,
        };
        refine_photometric(&problem, &mut disparity, &Photometric::default()).unwrap_or_else(|e| panic!("{e}"));
        let error = |columns: std::ops::Range<usize>| {
            let (mut sum, mut n) = (0.0, 0);
            for y in 0..h {
                for x in columns.clone() {
                    sum += (disparity.data[y * w + x] - truth[y * w + x]).abs();
                    n += 1;
                }
            }
            sum / n as f32
        };
        let (planes, beside) = (
            0.5 * (error(12..edge - 10) + error(edge + 10..w - 12)),
            error(edge - 6..edge + 6),
        );
        println!("planes {planes:.4} px, beside the step {beside:.4} px (started 0.25)");
        assert!(planes < 0.05, "planes {planes:.4} px");
        assert!(beside <= 0.25 + 1e-3, "beside the step {beside:.4} px");
    }
}
