//! Semi-global matching over the fused cost volume: the strong classical method.

use std::sync::atomic::{AtomicUsize, Ordering};

use serde::{Deserialize, Serialize};

use super::{Family, Method, MethodEntry, Progress, configure};
use crate::FuseError;
use crate::cost::PixelCost;
use crate::fusion::Fusion;
use crate::image::DisparityImage;
use crate::postprocess::{WeightedMedian, median3x3, weighted_median};
use crate::sgm::{quantisation_shift, quantise_penalty, select_volume};
use crate::subpixel::{BlockSubpixel, refine_with_block_costs};
use crate::volume::{CostSpec, PreparedProblem, Problem, band_rows};
use crate::wta::SubpixelFit;

/// Configuration of SGM.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SgmConfig {
    /// Cost fusion over the neighbours.
    pub fusion: Fusion,
    /// Per-pixel cost.
    pub cost: PixelCost,
    /// Block radius of the cost aggregation before SGM (0 = pixel-wise).
    #[serde(alias = "block_radius")]
    pub block_radius_px: usize,
    /// Penalty for a ±1 disparity change between neighbouring pixels (in cost units).
    pub p1: u16,
    /// Penalty for larger disparity changes.
    pub p2: u16,
    /// Sub-pixel refinement of the winners.
    pub subpixel: bool,
    /// The curve whose vertex is the sub-pixel disparity: `equiangular` (default; SGM's sums of
    /// census distances have V-shaped minima) or `parabola` (see `wta::SubpixelFit`).
    pub subpixel_fit: SubpixelFit,
    /// 3×3 median filter on the result.
    pub median: bool,
    /// An image-guided weighted median after the rest (`postprocess::WeightedMedian`; `{}` =
    /// its defaults, `null` = none): depth edges snap to the reference's colour edges.
    pub weighted_median: Option<WeightedMedian>,
    /// Sub-pixel from block-matching costs, last (`subpixel::BlockSubpixel`; `{}` = its
    /// defaults, `null` = none, the default: a second cost pass, about the time of
    /// `bm-heuristic`): SGM's integer stays, its fraction is re-read from fused 9×9
    /// Birchfield–Tomasi block costs, which lock to the pixel grid far less than SGM's sums.
    pub block_subpixel: Option<BlockSubpixel>,
}

impl super::FusedConfig for SgmConfig {
    fn set_fusion(&mut self, fusion: Fusion) {
        self.fusion = fusion;
    }
}

impl Default for SgmConfig {
    /// Chosen on `middlebury2006-third-dev` (`replay eval --config`): census 7×7 summed over a 7×7
    /// block, P1 = 300, P2 = 3000 (in those summed census units).
    fn default() -> Self {
        Self {
            fusion: Fusion::Heuristic,
            cost: PixelCost::Census { radius: 3 },
            block_radius_px: 3,
            p1: 300,
            p2: 3000,
            subpixel: true,
            subpixel_fit: SubpixelFit::Equiangular,
            median: true,
            weighted_median: None,
            block_subpixel: None,
        }
    }
}

/// SGM with one fusion.
pub struct Sgm {
    name: &'static str,
    config: SgmConfig,
}

impl Method for Sgm {
    super::name_and_config!();

    fn run(&self, problem: &Problem, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        let spec = CostSpec {
            pixel: self.config.cost,
            block_radius_px: self.config.block_radius_px,
        };
        let prepared = PreparedProblem::new(problem, spec, self.config.fusion)?;
        let (w, h) = (prepared.width(), prepared.height());
        let bands = h.div_ceil(band_rows(h));
        let done = AtomicUsize::new(0);
        // Cost volume: the first half of the work; aggregation the rest.
        let shift = quantisation_shift(spec.max_cost());
        let volume = prepared.fused_volume(shift, &|| {
            progress(0.5 * (done.fetch_add(1, Ordering::Relaxed) + 1) as f32 / bands as f32);
        });
        let (p1, p2) = (
            quantise_penalty(self.config.p1, shift),
            quantise_penalty(self.config.p2, shift),
        );
        let (data, confidence) = select_volume(
            &volume,
            (p1, p2),
            self.config.subpixel.then_some(self.config.subpixel_fit),
        );
        drop(volume);
        progress(0.95);
        let mut disparity = DisparityImage {
            width: w,
            height: h,
            data,
            confidence: Some(confidence),
        };
        disparity.fill_invalid_from_row_neighbours();
        if self.config.median {
            disparity = median3x3(&disparity);
        }
        if let Some(filter) = &self.config.weighted_median {
            disparity = weighted_median(&disparity, &problem.reference, filter)?;
        }
        if let Some(config) = &self.config.block_subpixel {
            refine_with_block_costs(problem, &mut disparity, config)?;
        }
        crate::postprocess::scale_by_local_consistency(&mut disparity);
        progress(1.0);
        Ok(disparity)
    }
}

fn build(
    name: &'static str,
    fusion: Fusion,
    overrides: Option<&serde_json::Value>,
) -> Result<Box<dyn Method>, FuseError> {
    let config: SgmConfig = configure(fusion, overrides)?;
    Ok(Box::new(Sgm { name, config }))
}

/// Registry entries.
pub const ENTRIES: &[MethodEntry] = &[
    MethodEntry {
        name: "sgm-stereo",
        summary: "semi-global matching (census, 8 paths), two-view stereo against the right view",
        family: Family::Sgm,
        build: |o| build("sgm-stereo", Fusion::Stereo, o),
    },
    MethodEntry {
        name: "sgm-mean",
        summary: "semi-global matching over the mean-fused cost volume",
        family: Family::Sgm,
        build: |o| build("sgm-mean", Fusion::Mean, o),
    },
    MethodEntry {
        name: "sgm-min",
        summary: "semi-global matching over the min-fused cost volume",
        family: Family::Sgm,
        build: |o| build("sgm-min", Fusion::Min, o),
    },
    MethodEntry {
        name: "sgm-heuristic",
        summary: "semi-global matching over the heuristic-fused cost volume (the best classical method)",
        family: Family::Sgm,
        build: |o| build("sgm-heuristic", Fusion::Heuristic, o),
    },
];
