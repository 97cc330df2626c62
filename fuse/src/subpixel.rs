//! Sub-pixel re-reading from block-matching costs: a method keeps its integer decision, and the
//! fraction comes from the vertex of a parabola through the fused block costs (Birchfield–Tomasi
//! on colour, box-summed, the paper's heuristic fusion) around it. Costs that SGM smoothed, or
//! census distances, lock the vertex to the pixel grid (on slanted planes a third to half of SGM's
//! and MFuseNet's estimates lie within 0.1 px of an integer, against a tenth for an unbiased
//! fraction); plain block sums of Birchfield–Tomasi costs lock far less
//! (`scripts/eval-subpixel.sh`, docs/experiments.md "Sub-pixel precision").

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::PixelCost;
use crate::fusion::Fusion;
use crate::image::DisparityImage;
use crate::volume::{BandScratch, CostSpec, PreparedProblem, Problem, band_rows};
use crate::wta::SubpixelFit;

/// How [`refine_with_block_costs`] re-reads the fraction.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BlockSubpixel {
    /// Block radius of the cost sums (px; block side 2ρ+1).
    pub block_radius_px: usize,
    /// The curve through the three block costs around the integer.
    pub fit: SubpixelFit,
    /// The largest change (px) of an estimate: where the block costs' vertex lies farther from
    /// it, the block costs disagree with the method (an edge, an occlusion) and it stays.
    pub max_shift_px: f32,
}

impl Default for BlockSubpixel {
    fn default() -> Self {
        Self {
            block_radius_px: 4,
            fit: SubpixelFit::Parabola,
            max_shift_px: 0.2,
        }
    }
}

/// Replaces the fraction of every finite estimate of `disparity` (over `problem`'s range) with
/// the vertex of `config.fit` through the fused block costs at the two integers around it whose
/// cost is a local minimum (the nearer first), when that vertex lies within
/// `config.max_shift_px` of the estimate; other estimates stay. Returns how many changed.
pub fn refine_with_block_costs(
    problem: &Problem,
    disparity: &mut DisparityImage,
    config: &BlockSubpixel,
) -> Result<usize, FuseError> {
    let spec = CostSpec {
        pixel: PixelCost::BirchfieldTomasi,
        block_radius_px: config.block_radius_px,
    };
    let prepared = PreparedProblem::new(problem, spec, Fusion::Heuristic)?;
    let (w, h, nd) = (prepared.width(), prepared.height(), prepared.num_disparities());
    disparity.check_size(
        w,
        h,
        "disparity map for the sub-pixel re-reading (the reference's size)",
    )?;
    let min = problem.min_disparity as f32;
    let band = band_rows(h);
    let changed: usize = disparity
        .data
        .par_chunks_mut(band * w)
        .enumerate()
        .map_init(BandScratch::default, |buffers, (index, out)| {
            let start = index * band;
            let rows = start..start + out.len() / w;
            let mut changed = 0;
            prepared.fused_band_with(rows, buffers, &mut |y, x_start, costs| {
                let at = (y - start) * w + x_start;
                for (estimate, costs) in out[at..].iter_mut().zip(costs.chunks_exact(nd)) {
                    if let Some(refined) = reread(*estimate - min, costs, config) {
                        *estimate = refined + min;
                        changed += 1;
                    }
                }
            });
            changed
        })
        .sum();
    Ok(changed)
}

/// The re-read estimate (slices from the range's start) of `estimate` from its pixel's `costs`.
fn reread(estimate: f32, costs: &[u16], config: &BlockSubpixel) -> Option<f32> {
    if !estimate.is_finite() {
        return None;
    }
    let nearest = estimate.round();
    let other = if estimate >= nearest {
        nearest + 1.0
    } else {
        nearest - 1.0
    };
    [nearest, other].into_iter().find_map(|d| {
        if d < 1.0 || d + 2.0 > costs.len() as f32 {
            return None;
        }
        let i = d as usize;
        let [l, c, r] = [costs[i - 1], costs[i], costs[i + 1]].map(f64::from);
        let vertex = d + config.fit.offset([l, c, r])? as f32;
        ((vertex - estimate).abs() <= config.max_shift_px).then_some(vertex)
    })
}

/// Test fixtures shared with `photometric`'s tests.
#[cfg(test)]
pub(crate) mod fixtures {
    use crate::image::{DisparityImage, Image};
    use crate::volume::{Neighbour, Problem};

    /// A reference of smooth texture and a right neighbour of a slanted plane whose disparity is
    /// `a + b·x` at reference column x: the neighbour's column x shows the reference's
    /// `(x + a) / (1 − b)` (sampled from the same texture function, exact).
    pub(crate) fn slanted(w: usize, h: usize, a: f32, b: f32) -> (Problem, Vec<f32>) {
        let texture = |x: f32, y: f32| -> f32 {
            128.0 + (x * 0.37).sin() * 60.0 + (y * 0.23 + x * 0.11).cos() * 50.0 + (x * 0.05 - y * 0.07).sin() * 40.0
        };
        let image = |source: &dyn Fn(usize) -> f32| {
            let mut data = Vec::with_capacity(w * h * 3);
            for y in 0..h {
                for x in 0..w {
                    let v = texture(source(x), y as f32).clamp(0.0, 255.0) as u8;
                    data.extend([v, v / 2 + 40, 255 - v]);
                }
            }
            Image::new(w, h, 3, data).unwrap_or_else(|e| panic!("{e}"))
        };
        let problem = Problem {
            reference: image(&|x| x as f32),
            neighbours: vec![Neighbour {
                image: image(&|x| (x as f32 + a) / (1.0 - b)),
                offset: [1, 0],
                role: "right".into(),
                baseline_ratio: 1.0,
            }],
            min_disparity: 0,
            num_disparities: 16,
        };
        let truth = (0..h).flat_map(|_| (0..w).map(move |x| a + b * x as f32)).collect();
        (problem, truth)
    }

    /// `truth` locked to quarter pixels (errors up to 0.125 px, as SGM's sums give).
    pub(crate) fn quarter_pixels(truth: &[f32], w: usize, h: usize) -> DisparityImage {
        DisparityImage {
            width: w,
            height: h,
            data: truth.iter().map(|t| (t * 4.0).round() / 4.0).collect(),
            confidence: None,
        }
    }

    /// The mean |error| of `image` against `truth` away from the borders (6 px, 14 px on the
    /// left where a right neighbour's correspondences leave its image).
    pub(crate) fn inner_error(image: &DisparityImage, truth: &[f32]) -> f32 {
        let (w, h) = (image.width, image.height);
        let (mut sum, mut n) = (0.0, 0);
        for y in 6..h - 6 {
            for x in 14..w - 6 {
                sum += (image.data[y * w + x] - truth[y * w + x]).abs();
                n += 1;
            }
        }
        sum / n as f32
    }
}

#[cfg(test)]
mod tests {
    use super::fixtures::{inner_error, quarter_pixels, slanted};
    use super::*;

    #[test]
    fn a_slanted_plane_is_read_closer_to_its_truth_than_the_integers() {
        // Disparity 4 → 8 across the image: from the truth locked to quarter pixels (errors up to
        // 0.125 px, as SGM's sums give), the re-reading brings the mean error far down, and it
        // never moves an estimate by more than its limit.
        let (w, h) = (96, 40);
        let (problem, truth) = slanted(w, h, 4.0, 4.0 / w as f32);
        let mut disparity = quarter_pixels(&truth, w, h);
        let before = disparity.clone();
        let config = BlockSubpixel::default();
        let changed = refine_with_block_costs(&problem, &mut disparity, &config).unwrap_or_else(|e| panic!("{e}"));
        let (was, now) = (inner_error(&before, &truth), inner_error(&disparity, &truth));
        assert!(changed > w * h / 2, "{changed} of {} changed", w * h);
        println!("{changed} of {} changed; mean error {was:.4} → {now:.4} px", w * h);
        assert!(now < 0.6 * was, "mean error {was:.3} → {now:.3} px");
        for (a, b) in before.data.iter().zip(&disparity.data) {
            assert!((a - b).abs() <= config.max_shift_px + 1e-6, "{a} → {b}");
        }
    }

    #[test]
    fn estimates_the_block_costs_do_not_back_stay() {
        // An estimate 3 px off: the block costs' minimum is far from it, so it is not moved.
        let (w, h) = (64, 24);
        let (problem, truth) = slanted(w, h, 6.0, 0.0);
        let mut disparity = DisparityImage {
            width: w,
            height: h,
            data: truth.iter().map(|t| t + 3.0).collect(),
            confidence: None,
        };
        let before = disparity.clone();
        refine_with_block_costs(&problem, &mut disparity, &BlockSubpixel::default()).unwrap_or_else(|e| panic!("{e}"));
        let moved = before.data.iter().zip(&disparity.data).filter(|(a, b)| a != b).count();
        assert!(moved < w * h / 20, "{moved} of {} moved", w * h);
    }
}
