//! Block matching: box-aggregated costs, fused over the neighbours, winner-take-all with
//! sub-pixel refinement (paper, section III-B). Streams bands of rows: no full volume is held.

use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Family, Method, MethodEntry, Needs, Progress, configure};
use crate::FuseError;
use crate::cost::PixelCost;
use crate::fusion::{Fusion, SideRule};
use crate::image::DisparityImage;
use crate::postprocess::{WeightedMedian, weighted_median};
use crate::volume::{BandScratch, CostSpec, PreparedProblem, Problem, band_rows};
use crate::wta::{SubpixelFit, winner_take_all, winner_take_all_confident};

/// Configuration of block matching.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BlockMatchingConfig {
    /// Cost fusion over the neighbours.
    pub fusion: Fusion,
    /// Per-pixel cost.
    pub cost: PixelCost,
    /// Block radius ρ (block side 2ρ+1).
    #[serde(alias = "block_radius")]
    pub block_radius_px: usize,
    /// Sub-pixel refinement of the winners.
    pub subpixel: bool,
    /// The curve whose vertex is the sub-pixel disparity: `parabola` (default; measured best on
    /// box-summed Birchfield–Tomasi costs) or `equiangular` (see `wta::SubpixelFit`).
    pub subpixel_fit: SubpixelFit,
    /// Fill pixels without an estimate from their row neighbours (dense output).
    pub fill_invalid: bool,
    /// 3×3 median filter on the result.
    pub median: bool,
    /// An image-guided weighted median after the rest (`postprocess::WeightedMedian`; `{}` =
    /// its defaults, `null` = none): depth edges snap to the reference's colour edges.
    pub weighted_median: Option<WeightedMedian>,
    /// With the heuristic, how the views on one side of the reference along one ray become
    /// that side's cost: `min` (the default) or `near-capped` (see `SgmConfig::side_rule`).
    #[serde(default)]
    pub side_rule: SideRule,
    /// Match on the views' colour (`true`, the default) or on their luma (`false`: one
    /// channel instead of three, as OpenCV's StereoBM does). Luma is about a third faster and
    /// less accurate (docs/experiments.md, "block matching on luma"). Grey sets are matched on
    /// their one channel either way.
    #[serde(default = "yes")]
    pub colour: bool,
}

/// [`BlockMatchingConfig::colour`]'s default.
fn yes() -> bool {
    true
}

impl super::FusedConfig for BlockMatchingConfig {
    fn set_fusion(&mut self, fusion: Fusion) {
        self.fusion = fusion;
    }
}

impl Default for BlockMatchingConfig {
    /// Chosen on `middlebury2006-third-dev` (`replay eval --config`): the paper's Birchfield–Tomasi
    /// on colour, a 9×9 block and a 3×3 median give the lowest AvgErr for stereo and fusion alike.
    fn default() -> Self {
        Self {
            fusion: Fusion::Heuristic,
            cost: PixelCost::BirchfieldTomasi,
            block_radius_px: 4,
            subpixel: true,
            subpixel_fit: SubpixelFit::Parabola,
            fill_invalid: true,
            median: true,
            weighted_median: None,
            side_rule: SideRule::Min,
            colour: true,
        }
    }
}

/// Block matching with one fusion.
pub struct BlockMatching {
    name: &'static str,
    config: BlockMatchingConfig,
}

impl BlockMatching {
    /// A method with a configuration.
    pub fn new(name: &'static str, config: BlockMatchingConfig) -> Self {
        Self { name, config }
    }
}

impl Method for BlockMatching {
    super::name_and_config!();

    fn run(&self, problem: &Problem, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        self.run_for(problem, Needs::ALL, progress)
    }

    fn run_for(&self, problem: &Problem, needs: Needs, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        // Luma: the views converted once, before the search lines are laid out.
        let grey;
        let problem = if self.config.colour || problem.reference.channels == 1 {
            problem
        } else {
            grey = problem.to_gray();
            &grey
        };
        let spec = CostSpec {
            pixel: self.config.cost,
            block_radius_px: self.config.block_radius_px,
        };
        let prepared = PreparedProblem::new(problem, spec, self.config.fusion)?.with_side_rule(self.config.side_rule);
        let (w, h, nd) = (prepared.width(), prepared.height(), prepared.num_disparities());
        let mut data = vec![f32::INFINITY; w * h];
        let band = band_rows(h);
        let bands = h.div_ceil(band);
        // Without the confidence, no buffer: each band's share of it is empty.
        let mut confidence = if needs.confidence {
            vec![0.0f32; w * h]
        } else {
            Vec::new()
        };
        let mut sure_bands: Vec<&mut [f32]> = if needs.confidence {
            confidence.chunks_mut(band * w).collect()
        } else {
            (0..bands).map(|_| <&mut [f32]>::default()).collect()
        };
        let done = AtomicUsize::new(0);
        data.par_chunks_mut(band * w)
            .zip(sure_bands.par_iter_mut())
            .enumerate()
            .for_each_init(BandScratch::default, |buffers, (index, (out, sure))| {
                let start = index * band;
                let rows = start..start + out.len() / w;
                // Winners are picked tile row by tile row: no band of costs is ever held.
                prepared.fused_band_with(rows, buffers, &mut |y, x_start, costs| {
                    let at = (y - start) * w + x_start;
                    let pixels = costs.len() / nd;
                    let subpixel = self.config.subpixel.then_some(self.config.subpixel_fit);
                    let out = &mut out[at..at + pixels];
                    if needs.confidence {
                        let sure = &mut sure[at..at + pixels];
                        winner_take_all_confident(costs, nd, problem.min_disparity, subpixel, out, sure);
                    } else {
                        winner_take_all(costs, nd, problem.min_disparity, subpixel, out);
                    }
                });
                progress((done.fetch_add(1, Ordering::Relaxed) + 1) as f32 / bands as f32);
            });
        let mut disparity = DisparityImage {
            width: w,
            height: h,
            data,
            confidence: needs.confidence.then_some(confidence),
        };
        if self.config.fill_invalid {
            disparity.fill_invalid_from_row_neighbours();
        }
        if self.config.median {
            disparity = crate::postprocess::median3x3(&disparity);
        }
        if let Some(filter) = &self.config.weighted_median {
            disparity = weighted_median(&disparity, &problem.reference, filter)?;
        }
        crate::postprocess::scale_by_local_consistency(&mut disparity);
        Ok(disparity)
    }
}

fn build(
    name: &'static str,
    fusion: Fusion,
    overrides: Option<&serde_json::Value>,
) -> Result<Box<dyn Method>, FuseError> {
    let config: BlockMatchingConfig = configure(fusion, overrides)?;
    Ok(Box::new(BlockMatching::new(name, config)))
}

/// Registry entries.
pub const ENTRIES: &[MethodEntry] = &[
    MethodEntry {
        name: "bm-stereo",
        summary: "block matching (Birchfield–Tomasi, 9×9), two-view stereo against the right view, winner-take-all",
        family: Family::BlockMatching,
        build: |o| build("bm-stereo", Fusion::Stereo, o),
    },
    MethodEntry {
        name: "bm-mean",
        summary: "block matching (Birchfield–Tomasi, 9×9), mean of the neighbours' costs (c_ave)",
        family: Family::BlockMatching,
        build: |o| build("bm-mean", Fusion::Mean, o),
    },
    MethodEntry {
        name: "bm-min",
        summary: "block matching (Birchfield–Tomasi, 9×9), minimum of the neighbours' costs (c_min)",
        family: Family::BlockMatching,
        build: |o| build("bm-min", Fusion::Min, o),
    },
    MethodEntry {
        name: "bm-heuristic",
        summary: "block matching (Birchfield–Tomasi, 9×9), the paper's heuristic fusion (c_heu)",
        family: Family::BlockMatching,
        build: |o| build("bm-heuristic", Fusion::Heuristic, o),
    },
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::Image;

    /// A fronto-parallel plane at disparity `d` seen from left and right, a colour texture on
    /// its first 16 rows and a grey one below.
    fn colour_plane(d: usize) -> Problem {
        let (w, h) = (72, 24);
        let view = |shift: i64| {
            let data = (0..h as i64)
                .flat_map(|y| {
                    (0..w as i64).flat_map(move |x| {
                        let t = ((x + shift) * 37 + y * 11) ^ ((x + shift) * y);
                        let a = (t % 61 * 3 + 20) as u8;
                        if y < 16 { [a, 128, 255 - a] } else { [a, a, a] }
                    })
                })
                .collect();
            Image::rgb(w, h, data).unwrap_or_else(|e| panic!("{e}"))
        };
        crate::volume::plane_along_x(view, &[("left", -1), ("right", 1)], d as i64, 16)
    }

    fn run(problem: &Problem, colour: bool) -> DisparityImage {
        let config = BlockMatchingConfig {
            colour,
            ..BlockMatchingConfig::default()
        };
        BlockMatching::new("bm-heuristic", config)
            .run(problem, &|_| {})
            .unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn luma_matching_is_matching_on_the_grey_set_and_colour_finds_the_plane() {
        let problem = colour_plane(5);
        let on_luma = run(&problem, false);
        // The same as the grey set matched: the option converts, nothing else.
        assert_eq!(on_luma, run(&problem.to_gray(), true));
        // Colour finds the plane away from the borders (the search reaches past them).
        let colour = run(&problem, true);
        let inner = |image: &DisparityImage| {
            (4..image.height - 4)
                .flat_map(|y| (20..image.width - 20).map(move |x| (x, y)))
                .map(|(x, y)| image.data[y * image.width + x])
                .collect::<Vec<f32>>()
        };
        let colour_off = inner(&colour).iter().filter(|d| (**d - 5.0).abs() > 0.5).count();
        assert_eq!(colour_off, 0, "colour: {:?}", inner(&colour));
        assert_ne!(on_luma, colour, "luma and colour gave one answer");
        // Asked for the disparities alone: the same ones, no confidence.
        let alone = BlockMatching::new("bm-heuristic", BlockMatchingConfig::default())
            .run_for(&problem, Needs::DISPARITY, &|_| {})
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(alone.data == colour.data && alone.confidence.is_none());
        assert!(colour.confidence.is_some());
    }
}
