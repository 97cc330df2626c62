//! The border bands: where a neighbour's correspondences leave its image (the last `d` columns
//! on the side a view shifts from), a learned fusion that was fed that neighbour's mirrored
//! costs can settle on a fake minimum near the range's start while the views that do see the
//! pixel agree on another disparity (a near part at the image's edge: 25–34 px of truth read as
//! 1–5 px). The classical fusions take only the views that see the pixel; [`recheck_borders`]
//! does the same for a finished estimate: the fused Birchfield–Tomasi block costs of the views
//! that see each disparity (the paper's heuristic), and an estimate they contradict is replaced
//! by their minimum where some view cannot see that minimum.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::{INVALID_COST, PixelCost};
use crate::fusion::Fusion;
use crate::image::DisparityImage;
use crate::volume::{BandScratch, CostSpec, PreparedProblem, Problem, band_rows};

/// How [`recheck_borders`] decides.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BorderCheck {
    /// Block radius of the cost sums (px; block side 2ρ+1).
    pub block_radius_px: usize,
    /// An estimate is replaced only where the fused block cost of the minimum is under this
    /// share of the cost at the estimate.
    pub ratio: f32,
    /// … and the minimum lies farther than this from the estimate (px).
    pub min_jump_px: f32,
    /// … and the estimate lies within this many pixels of the range's start, where the failure
    /// puts it: the neighbour that cannot see a pixel's larger disparities still has finite
    /// (mirrored) costs at the start and below it, the network's context.
    pub near_start_px: f32,
    /// … and the minimum is distinct: under this share of the lowest cost more than 2 px
    /// from it (a blank wall's flat costs decide nothing).
    pub uniqueness: f32,
    /// … and more than half of the `(2r+1)²` window around the pixel would be replaced by a
    /// disparity within 1 px of its own (0: each pixel alone).
    pub region_radius_px: usize,
}

impl Default for BorderCheck {
    fn default() -> Self {
        Self {
            block_radius_px: 4,
            ratio: 0.5,
            min_jump_px: 2.0,
            near_start_px: 6.0,
            uniqueness: 0.8,
            region_radius_px: 3,
        }
    }
}

impl BorderCheck {
    /// Refuses ratios outside (0, 1] and negative or non-finite jumps.
    pub fn validate(&self) -> Result<(), FuseError> {
        if !(self.uniqueness > 0.0 && self.uniqueness <= 1.0) {
            return Err(FuseError::Config {
                field: "border_check.uniqueness",
                value: self.uniqueness.to_string(),
                reason: "a share of the runner-up's cost, over 0 and at most 1",
            });
        }
        if !(self.ratio > 0.0 && self.ratio <= 1.0) {
            return Err(FuseError::Config {
                field: "border_check.ratio",
                value: self.ratio.to_string(),
                reason: "a share of the estimate's cost, over 0 and at most 1",
            });
        }
        if !(self.near_start_px >= 0.0 && self.near_start_px.is_finite()) {
            return Err(FuseError::Config {
                field: "border_check.near_start_px",
                value: self.near_start_px.to_string(),
                reason: "a distance in pixels, 0 or more",
            });
        }
        if !(self.min_jump_px >= 0.0 && self.min_jump_px.is_finite()) {
            return Err(FuseError::Config {
                field: "border_check.min_jump_px",
                value: self.min_jump_px.to_string(),
                reason: "a distance in pixels, 0 or more",
            });
        }
        Ok(())
    }
}

/// Replaces each finite estimate of `disparity` (over `problem`'s range) within
/// `config.near_start_px` of the range's start by the minimum of the fused block costs of the
/// views that see each disparity when (1) some neighbour's correspondence at that minimum lies
/// outside its image (the border bands only), (2) the minimum lies more than
/// `config.min_jump_px` above the estimate, (3) its cost is under `config.ratio` times the cost at
/// the estimate (or no view sees the estimate) and under `config.uniqueness` times the lowest
/// cost more than 2 px from it, and (4) most of its `config.region_radius_px` window would be
/// replaced alike. Returns how many changed.
pub fn recheck_borders(
    problem: &Problem,
    disparity: &mut DisparityImage,
    config: &BorderCheck,
) -> Result<usize, FuseError> {
    config.validate()?;
    let spec = CostSpec {
        pixel: PixelCost::BirchfieldTomasi,
        block_radius_px: config.block_radius_px,
    };
    let prepared = PreparedProblem::new(problem, spec, Fusion::Heuristic)?;
    let (w, h, nd) = (prepared.width(), prepared.height(), prepared.num_disparities());
    disparity.check_size(w, h, "disparity map for the border check (the reference's size)")?;
    let min = problem.min_disparity as f32;
    // Each neighbour's shift per disparity: it sees the reference's pixel p at p − offset·d·ratio.
    let shifts: Vec<(f32, f32)> = problem
        .neighbours
        .iter()
        .map(|n| {
            (
                n.offset[0] as f32 * n.baseline_ratio,
                n.offset[1] as f32 * n.baseline_ratio,
            )
        })
        .collect();
    // The widest band on each axis: the largest shift over the range's largest magnitude.
    let magnitude = problem.min_disparity.unsigned_abs() as f32 + nd as f32;
    let band_of =
        |axis: fn(&(f32, f32)) -> f32| (shifts.iter().map(axis).fold(0.0f32, f32::max) * magnitude).ceil() as usize;
    let (reach_x, reach_y) = (band_of(|s| s.0.abs()), band_of(|s| s.1.abs()));
    let leaves = |x: usize, y: usize, d: f32| {
        shifts.iter().any(|(sx, sy)| {
            let (cx, cy) = (x as f32 - sx * d, y as f32 - sy * d);
            cx < 0.0 || cx > (w - 1) as f32 || cy < 0.0 || cy > (h - 1) as f32
        })
    };
    let band = band_rows(h);
    // Each pixel's replacement, NaN where none (first all of them, then those in regions).
    let estimates = &disparity.data;
    let mut found = vec![f32::NAN; w * h];
    found
        .par_chunks_mut(band * w)
        .enumerate()
        .for_each_init(BandScratch::default, |buffers, (index, out)| {
            let start = index * band;
            let rows = start..start + out.len() / w;
            let mut check = |y: usize, x_start: usize, costs: &[u16]| {
                let at = (y - start) * w + x_start;
                for (i, (found, costs)) in out[at..].iter_mut().zip(costs.chunks_exact(nd)).enumerate() {
                    let x = x_start + i;
                    let estimate = &estimates[y * w + x];
                    // Only estimates near the range's start, where the failure puts them.
                    if !estimate.is_finite() || *estimate - min > config.near_start_px {
                        continue;
                    }
                    let Some((best, best_cost)) = costs
                        .iter()
                        .enumerate()
                        .filter(|(_, c)| **c != INVALID_COST)
                        .min_by_key(|(_, c)| **c)
                    else {
                        continue;
                    };
                    let best_d = best as f32 + min;
                    // Only upwards: a view that cannot see the larger disparities leaves the
                    // smaller ones' fake minimum to the network, not the reverse.
                    if best_d - *estimate <= config.min_jump_px || !leaves(x, y, best_d) {
                        continue;
                    }
                    let runner_up = costs
                        .iter()
                        .enumerate()
                        .filter(|(k, c)| k.abs_diff(best) > 2 && **c != INVALID_COST)
                        .map(|(_, c)| *c)
                        .min()
                        .unwrap_or(INVALID_COST);
                    if f32::from(*best_cost) >= config.uniqueness * f32::from(runner_up) {
                        continue;
                    }
                    let k = ((*estimate - min).round().max(0.0) as usize).min(nd - 1);
                    let at_estimate = costs[k];
                    if at_estimate == INVALID_COST || f32::from(*best_cost) < config.ratio * f32::from(at_estimate) {
                        *found = best_d;
                    }
                }
            };
            // Rows and columns farther from every border than any view shifts need no look: the
            // bands of rows along the top and bottom whole, the other rows at their ends.
            let (top, bottom) = (
                start..rows.end.min(reach_y),
                rows.start.max(h.saturating_sub(reach_y))..rows.end,
            );
            let middle = rows.start.max(top.end)..rows.end.min(bottom.start);
            for whole in [top.start.max(rows.start)..top.end, bottom.clone()] {
                if !whole.is_empty() {
                    prepared.fused_tile_with(whole, 0..w, buffers, &mut check);
                }
            }
            if !middle.is_empty() && reach_x > 0 {
                prepared.fused_tile_with(middle.clone(), 0..reach_x.min(w), buffers, &mut check);
                if w > reach_x {
                    prepared.fused_tile_with(middle, (w - reach_x).max(reach_x)..w, buffers, &mut check);
                }
            }
        });
    // A part at the image's edge is a region: keep the replacements that most of their
    // window agrees with (within 1 px), not scattered matches of one view.
    let r = config.region_radius_px;
    let window = (2 * r + 1) * (2 * r + 1);
    let keep: Vec<(usize, f32)> = (0..w * h)
        .into_par_iter()
        .filter_map(|i| {
            let d = found[i];
            if !d.is_finite() {
                return None;
            }
            let (x, y) = (i % w, i / w);
            let agree = (y.saturating_sub(r)..(y + r + 1).min(h))
                .flat_map(|v| (x.saturating_sub(r)..(x + r + 1).min(w)).map(move |u| v * w + u))
                .filter(|&j| (found[j] - d).abs() <= 1.0)
                .count();
            (agree * 2 > window).then_some((i, d))
        })
        .collect();
    for &(i, d) in &keep {
        disparity.data[i] = d;
    }
    Ok(keep.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::Image;
    use crate::volume::plane_along_x;

    /// A textured plane at disparity `d` seen by a left/right pair (the neighbour at offset `k`
    /// sees the reference's pixel `x` at `x − k·d`).
    fn plane(d: i32, (w, h): (usize, usize)) -> Problem {
        let texture = |x: i64, y: i64| {
            let v = (x.wrapping_mul(73_856_093) ^ y.wrapping_mul(19_349_663)).rem_euclid(1 << 20);
            (((v * 2_654_435_761) >> 7) & 0xFF) as u8
        };
        let view = |shift: i64| {
            let data = (0..h as i64)
                .flat_map(|y| (0..w as i64).map(move |x| texture(x + shift, y)))
                .collect();
            Image::gray(w, h, data).unwrap_or_else(|e| panic!("{e}"))
        };
        plane_along_x(view, &[("left", -1), ("right", 1)], i64::from(d), 32)
    }

    #[test]
    fn a_fake_minimum_in_a_border_band_is_replaced_and_the_rest_kept() {
        let (w, h, d) = (96, 24, 20);
        let problem = plane(d, (w, h));
        // Right in the middle; 2 px (a fake minimum at the range's start) in the last 20 columns,
        // where the left view cannot see the plane; and 2 px in the middle too, which no border
        // check may touch.
        let mut data = vec![d as f32; w * h];
        for y in 0..h {
            for x in w - 20..w {
                data[y * w + x] = 2.0;
            }
            data[y * w + w / 2] = 2.0;
        }
        let mut disparity = DisparityImage {
            width: w,
            height: h,
            data,
            confidence: None,
        };
        let changed =
            recheck_borders(&problem, &mut disparity, &BorderCheck::default()).unwrap_or_else(|e| panic!("{e}"));
        let band_right = (0..h)
            .flat_map(|y| (w - 20..w).map(move |x| (x, y)))
            .filter(|&(x, y)| (disparity.data[y * w + x] - d as f32).abs() < 0.5)
            .count();
        assert!(
            band_right * 10 >= 20 * h * 9,
            "{band_right} of {} band pixels restored",
            20 * h
        );
        assert!(changed >= band_right, "{changed} changed");
        // The middle column keeps its (wrong) estimate: not a border band.
        assert!((0..h).all(|y| disparity.data[y * w + w / 2] == 2.0));
        // An estimate the costs back stays.
        let mut right = DisparityImage {
            width: w,
            height: h,
            data: vec![d as f32; w * h],
            confidence: None,
        };
        assert_eq!(
            recheck_borders(&problem, &mut right, &BorderCheck::default()).unwrap_or_else(|e| panic!("{e}")),
            0
        );
        // Bad settings are refused by name.
        let bad = BorderCheck {
            ratio: 0.0,
            ..BorderCheck::default()
        };
        assert!(recheck_borders(&problem, &mut right, &bad).is_err());
    }
}
