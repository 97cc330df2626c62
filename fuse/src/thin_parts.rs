//! Thin foreground parts recovered from per-pixel costs. Methods that read block sums (MFuseNet's
//! census volumes summed over 7×7 blocks, then SGM) lose rods, wires and slats 1–6 px wide in
//! front of a far background: a block centred on a wire is mostly background, so the block costs
//! pick the background's disparity and the wire vanishes. Per-pixel costs (Birchfield–Tomasi on
//! colour) still see it: at the background's disparity a wire pixel matches background pixels
//! of another colour, at its own it matches itself in every view.
//!
//! [`recover_thin_parts`] moves a pixel to the minimum of the mean over every view (a nearer
//! part is seen by all) only where that minimum is nearer than the method's estimate by a clear
//! jump, much lower than the costs at the estimate (the paper's heuristic fusion, which drops the
//! views that the part hides from the background), and unique along the range; and only where an
//! 8-neighbour was moved to within a
//! pixel of it as well (a part is a line of pixels, noise is isolated). Nearer only by default:
//! block sums erase thin *foreground*. Moving pixels farther too (`farther`: the background
//! seen through gaps between slats, which the estimate fills with the slats' disparity) helps
//! there and on Middlebury, but mirror-like metal shows reflections at farther disparities:
//! the reflective workpiece line lost 17 % (docs/experiments.md).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::{INVALID_COST, PixelCost};
use crate::fusion::Fusion;
use crate::image::DisparityImage;
use crate::volume::{BandScratch, CostSpec, PreparedProblem, Problem, band_rows};
use crate::wta::SubpixelFit;

/// How [`recover_thin_parts`] decides.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ThinParts {
    /// The smallest jump (px) towards the camera a pixel may take.
    pub min_jump_px: f32,
    /// The per-pixel cost at the new disparity is at most this share of the lowest cost within
    /// ±1 of the estimate.
    pub ratio: f32,
    /// … and at most this share of the lowest cost farther than ±1 from the new disparity.
    pub uniqueness: f32,
    /// … and lower than the cost at the estimate by at least this much (grey levels: flat
    /// regions, where every cost is noise, never move).
    pub min_margin: f32,
    /// How many of the 8 neighbours must move to within 1 px of the pixel's new disparity.
    pub min_support: usize,
    /// Also move pixels farther: the background seen through a gap between parts (slats, a
    /// grid) that the estimate filled with the parts' disparity.
    pub farther: bool,
    /// The fewest neighbours it runs with: one view's per-pixel costs cannot tell a part from a
    /// chance match (the stereo network on Middlebury: RMS 1.089 → 1.185 px with one).
    pub min_views: usize,
}

impl Default for ThinParts {
    fn default() -> Self {
        Self {
            min_jump_px: 2.0,
            ratio: 0.5,
            uniqueness: 0.9,
            min_margin: 8.0,
            min_support: 1,
            farther: false,
            min_views: 2,
        }
    }
}

/// Moves the pixels of `disparity` (over `problem`'s range) where the per-pixel costs show a thin
/// nearer part that the estimate missed (module docs); their confidence becomes the per-pixel
/// costs' own peak margin. Nothing moves with fewer than `config.min_views` neighbours. Returns
/// how many moved.
pub fn recover_thin_parts(
    problem: &Problem,
    disparity: &mut DisparityImage,
    config: &ThinParts,
) -> Result<usize, FuseError> {
    if problem.neighbours.len() < config.min_views {
        return Ok(0);
    }
    let spec = CostSpec {
        pixel: PixelCost::BirchfieldTomasi,
        block_radius_px: 0,
    };
    // The estimate's costs with the views a part hides dropped (the heuristic fusion), the
    // candidate's with every view (a nearer part is seen by all: the mean, which the
    // heuristic's two smallest costs would let a horizontal bar's aperture fool).
    let (heuristic, mean) = rayon::join(
        || PreparedProblem::new(problem, spec, Fusion::Heuristic),
        || PreparedProblem::new(problem, spec, Fusion::Mean),
    );
    let (heuristic, mean) = (heuristic?, mean?);
    let (w, h, nd) = (heuristic.width(), heuristic.height(), heuristic.num_disparities());
    disparity.check_size(w, h, "disparity map for the thin-part recovery (the reference's size)")?;
    let min = problem.min_disparity as f32;
    let band = band_rows(h);
    // Each pixel's candidate (the new disparity, its confidence), NaN where none.
    let mut candidates = vec![(f32::NAN, 0.0f32); w * h];
    candidates
        .par_chunks_mut(band * w)
        .zip(disparity.data.par_chunks(band * w))
        .enumerate()
        .for_each_init(
            || (BandScratch::default(), Vec::new()),
            |(buffers, all_views), (index, (out, estimates))| {
                let start = index * band;
                let rows = start..start + out.len() / w;
                all_views.clear();
                all_views.resize(rows.len() * w * nd, 0u16);
                mean.fused_band_into(rows.clone(), all_views, buffers);
                heuristic.fused_band_with(rows, buffers, &mut |y, x_start, costs| {
                    let at = (y - start) * w + x_start;
                    for (i, (candidate, estimate)) in out[at..].iter_mut().zip(&estimates[at..]).enumerate() {
                        let Some(costs) = costs.get(i * nd..(i + 1) * nd) else {
                            break;
                        };
                        let seen_by_all = &all_views[(at + i) * nd..(at + i + 1) * nd];
                        if let Some(found) = candidate_of(*estimate - min, costs, seen_by_all, config) {
                            *candidate = (found.0 + min, found.1);
                        }
                    }
                });
            },
        );
    let supported: Vec<bool> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let d = candidates[i].0;
            if !d.is_finite() {
                return false;
            }
            let (x, y) = (i % w, i / w);
            let mut support = 0;
            for ny in y.saturating_sub(1)..(y + 2).min(h) {
                for nx in x.saturating_sub(1)..(x + 2).min(w) {
                    let other = candidates[ny * w + nx].0;
                    if (nx, ny) != (x, y) && (other - d).abs() <= 1.0 {
                        support += 1;
                    }
                }
            }
            support >= config.min_support
        })
        .collect();
    let mut moved = 0;
    for (i, keep) in supported.into_iter().enumerate() {
        if keep {
            disparity.data[i] = candidates[i].0;
            if let Some(confidence) = &mut disparity.confidence {
                confidence[i] = candidates[i].1;
            }
            moved += 1;
        }
    }
    Ok(moved)
}

/// The disparity (slices from the range's start, with its parabola's fraction) and confidence
/// one pixel moves to, from its per-pixel costs (`costs` with occluded views dropped,
/// `seen_by_all` every view's mean), where [`ThinParts`]'s tests pass: a nearer part on the mean
/// of every view, or (with `config.farther`) the background through a gap on the costs with
/// occluded views dropped (a gap's background is hidden from some views by the part itself).
fn candidate_of(estimate: f32, costs: &[u16], seen_by_all: &[u16], config: &ThinParts) -> Option<(f32, f32)> {
    if !estimate.is_finite() {
        return None;
    }
    let nd = costs.len();
    let near = estimate.round().clamp(0.0, (nd - 1) as f32) as usize;
    let at_estimate = costs[near.saturating_sub(1)..(near + 2).min(nd)]
        .iter()
        .filter(|c| **c != INVALID_COST)
        .min()
        .copied()?;
    let nearer = |best: usize| best as f32 >= estimate + config.min_jump_px;
    let farther = |best: usize| config.farther && best as f32 <= estimate - config.min_jump_px;
    clear_minimum(seen_by_all, at_estimate, config, nearer)
        .or_else(|| clear_minimum(costs, at_estimate, config, farther))
}

/// The minimum of `curve` where `wanted` takes its place and it is clearly better than
/// `at_estimate` and unique ([`ThinParts`]), with its parabola's fraction, and its confidence.
fn clear_minimum(
    curve: &[u16],
    at_estimate: u16,
    config: &ThinParts,
    wanted: impl Fn(usize) -> bool,
) -> Option<(f32, f32)> {
    let nd = curve.len();
    let (best, &c_best) = curve
        .iter()
        .enumerate()
        .filter(|(_, c)| **c != INVALID_COST)
        .min_by_key(|(_, c)| **c)?;
    if !wanted(best) {
        return None;
    }
    let second = curve
        .iter()
        .enumerate()
        .filter(|(d, c)| d.abs_diff(best) > 1 && **c != INVALID_COST)
        .map(|(_, c)| *c)
        .min()
        .unwrap_or(INVALID_COST);
    let (c_best, at_estimate, second) = (f32::from(c_best), f32::from(at_estimate), f32::from(second));
    let passes = c_best <= config.ratio * at_estimate
        && c_best <= config.uniqueness * second
        && at_estimate - c_best >= config.min_margin;
    if !passes {
        return None;
    }
    let fraction = if best >= 1 && best + 1 < nd {
        let [l, c, r] = [curve[best - 1], curve[best], curve[best + 1]];
        if l == INVALID_COST || r == INVALID_COST {
            0.0
        } else {
            // A flat bottom (two equal costs: Birchfield–Tomasi forgives half a pixel) says
            // nothing about the fraction.
            SubpixelFit::Parabola
                .offset([l, c, r].map(f64::from))
                .filter(|o| o.abs() < 0.5)
                .map_or(0.0, |o| o as f32)
        }
    } else {
        0.0
    };
    let confidence = 1.0 - c_best / second.max(1.0);
    Some((best as f32 + fraction, confidence.clamp(0.0, 1.0)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::Image;
    use crate::volume::Neighbour;

    /// A textured far plane at disparity 2 with a rod two pixels thick across it at disparity
    /// 10 (rows 20 and 21 of the reference), seen from the four views of a cross: the view at
    /// offset `o` shows at `p` the point that the reference shows at `p + o·d`.
    fn rod_before_a_plane(w: usize, h: usize, flat: bool) -> (Problem, Vec<bool>) {
        let (far, near, rod) = (2.0f32, 10.0f32, 20.0..22.0f32);
        let plane = |x: f32, y: f32| -> [u8; 3] {
            if flat {
                return [120, 120, 120];
            }
            let v = 128.0 + (x * 0.41).sin() * 50.0 + (y * 0.29 + x * 0.13).cos() * 45.0;
            let v = v.clamp(0.0, 255.0) as u8;
            [v, v / 2 + 30, 255 - v]
        };
        let rod_colour = |x: f32| -> [u8; 3] {
            let v = (200.0 + (x * 0.23).sin() * 40.0).clamp(0.0, 255.0) as u8;
            [v, 40, 60]
        };
        let view = |[ox, oy]: [i32; 2]| {
            let (ox, oy) = (ox as f32, oy as f32);
            let mut data = Vec::with_capacity(w * h * 3);
            for y in 0..h {
                for x in 0..w {
                    let (x, y) = (x as f32, y as f32);
                    // The rod is nearer: where it covers the pixel it hides the plane.
                    let rod_y = y + oy * near;
                    data.extend(if rod.contains(&rod_y) {
                        rod_colour(x + ox * near)
                    } else {
                        plane(x + ox * far, y + oy * far)
                    });
                }
            }
            Image::new(w, h, 3, data).unwrap_or_else(|e| panic!("{e}"))
        };
        let neighbour = |offset: [i32; 2], role: &str| Neighbour {
            image: view(offset),
            offset,
            role: role.into(),
            baseline_ratio: 1.0,
        };
        let problem = Problem {
            reference: view([0, 0]),
            neighbours: vec![
                neighbour([-1, 0], "left"),
                neighbour([1, 0], "right"),
                neighbour([0, -1], "top"),
                neighbour([0, 1], "bottom"),
            ],
            min_disparity: 0,
            num_disparities: 16,
        };
        let on_rod = (0..h)
            .flat_map(|y| std::iter::repeat_n(rod.contains(&(y as f32)), w))
            .collect();
        (problem, on_rod)
    }

    fn far_everywhere(w: usize, h: usize) -> DisparityImage {
        DisparityImage {
            width: w,
            height: h,
            data: vec![2.0; w * h],
            confidence: Some(vec![0.5; w * h]),
        }
    }

    #[test]
    fn a_rod_the_estimate_erased_comes_back_and_the_plane_stays() {
        let (w, h) = (80, 44);
        let (problem, on_rod) = rod_before_a_plane(w, h, false);
        let mut disparity = far_everywhere(w, h);
        let moved =
            recover_thin_parts(&problem, &mut disparity, &ThinParts::default()).unwrap_or_else(|e| panic!("{e}"));
        // Over half of the rod's pixels away from the borders (the views' shifted rows and
        // columns leave the image there) return to within a pixel of 10, the others stay (where
        // its colour is flattest the far plane's costs look as good); the plane keeps 2.
        let (mut rod_found, mut rod_total, mut plane_moved) = (0, 0, 0);
        for y in 0..h {
            for x in 12..w - 12 {
                let d = disparity.data[y * w + x];
                if on_rod[y * w + x] {
                    rod_total += 1;
                    rod_found += usize::from((d - 10.0).abs() <= 1.0);
                    assert!(d == 2.0 || (d - 10.0).abs() <= 1.0, "rod pixel ({x}, {y}) moved to {d}");
                } else if d != 2.0 {
                    plane_moved += 1;
                }
            }
        }
        println!("{moved} moved; rod {rod_found} of {rod_total}; plane pixels moved {plane_moved}");
        assert!(rod_found * 2 >= rod_total, "rod {rod_found} of {rod_total}");
        assert!(plane_moved * 100 <= (w - 24) * h, "{plane_moved} plane pixels moved");
    }

    #[test]
    fn farther_takes_back_a_plane_the_estimate_gave_the_rod_s_disparity() {
        // The rod's disparity everywhere (a fattened foreground): with `farther` the textured
        // plane returns to 2 where its texture is clear (most of it) and the rod keeps 10;
        // without it nothing moves back.
        let (w, h) = (80, 44);
        let (problem, on_rod) = rod_before_a_plane(w, h, false);
        let fattened = DisparityImage {
            data: vec![10.0; w * h],
            ..far_everywhere(w, h)
        };
        let config = ThinParts {
            farther: true,
            ..ThinParts::default()
        };
        let mut disparity = fattened.clone();
        recover_thin_parts(&problem, &mut disparity, &config).unwrap_or_else(|e| panic!("{e}"));
        let (mut plane_back, mut plane_total) = (0, 0);
        for y in 12..h - 12 {
            for x in 12..w - 12 {
                let d = disparity.data[y * w + x];
                if on_rod[y * w + x] {
                    assert_eq!(d, 10.0, "rod pixel ({x}, {y})");
                } else {
                    plane_total += 1;
                    plane_back += usize::from((d - 2.0).abs() <= 1.0);
                }
            }
        }
        println!("plane {plane_back} of {plane_total} back at 2");
        assert!(
            plane_back * 10 >= plane_total * 6,
            "plane {plane_back} of {plane_total}"
        );
        let mut unchanged = fattened.clone();
        recover_thin_parts(&problem, &mut unchanged, &ThinParts::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(unchanged.data, fattened.data);
    }

    #[test]
    fn a_flat_region_never_moves() {
        // Every cost is about zero everywhere: no disparity is clearly better than the estimate.
        let (w, h) = (64, 44);
        let (problem, _) = rod_before_a_plane(w, h, true);
        let mut disparity = far_everywhere(w, h);
        let before = disparity.clone();
        let config = ThinParts {
            min_support: 0,
            ..ThinParts::default()
        };
        recover_thin_parts(&problem, &mut disparity, &config).unwrap_or_else(|e| panic!("{e}"));
        // The rod itself may move (it is textured against the flat plane); the rows away from it
        // (and from where the vertical views show it) may not.
        for y in (0..8).chain(34..h) {
            for x in 0..w {
                assert_eq!(disparity.data[y * w + x], before.data[y * w + x], "({x}, {y})");
            }
        }
    }

    #[test]
    fn a_map_of_another_size_is_refused() {
        let (problem, _) = rod_before_a_plane(40, 30, false);
        let mut disparity = far_everywhere(41, 30);
        assert!(matches!(
            recover_thin_parts(&problem, &mut disparity, &ThinParts::default()),
            Err(FuseError::ImageSize { .. })
        ));
    }

    #[test]
    fn one_view_moves_nothing_by_default() {
        let (w, h) = (80, 44);
        let (mut problem, _) = rod_before_a_plane(w, h, false);
        problem.neighbours.truncate(1);
        let mut disparity = far_everywhere(w, h);
        let moved =
            recover_thin_parts(&problem, &mut disparity, &ThinParts::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(moved, 0);
        assert_eq!(disparity.data, far_everywhere(w, h).data);
        let one = ThinParts {
            min_views: 1,
            ..ThinParts::default()
        };
        assert!(recover_thin_parts(&problem, &mut disparity, &one).unwrap_or_else(|e| panic!("{e}")) > 0);
    }
}
