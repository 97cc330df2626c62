//! Semi-global matching over the fused cost volume: the strong classical method.

use std::sync::atomic::{AtomicUsize, Ordering};

use serde::{Deserialize, Serialize};

use super::{Family, Method, MethodEntry, Needs, Progress, configure};
use crate::FuseError;
use crate::cost::PixelCost;
use crate::fusion::{Fusion, SideRule};
use crate::image::DisparityImage;
use crate::postprocess::{WeightedMedian, median3x3, weighted_median};
use crate::sgm::{quantisation_shift, quantise_penalty, select_prepared, select_volume};
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
    /// Photometric sub-pixel refinement after the rest (`photometric::Photometric`; `{}` = its
    /// defaults, `null` = none, the default: about the method's time again at 1080p):
    /// Gauss–Newton on the views' brightness at continuous disparities, MFuseNet's last step.
    pub photometric: Option<crate::photometric::Photometric>,
    /// Make the fused costs a band of rows at a time where SGM's passes read them
    /// (`sgm::select_prepared`; the default) instead of holding them as one byte volume
    /// (`false`): the same result without the volume's pages to fault (1080p with 128
    /// disparities: 0.55 → 0.34 GB peak RSS and 0.50–0.55 → 0.48–0.51 s; docs/methods.md).
    #[serde(default = "default_costs_in_passes")]
    pub costs_in_passes: bool,
    /// With the heuristic, how the views on one side of the reference along one ray (a line's
    /// −1 and −2) become that side's cost: `min` (the default: a farther view's match counts
    /// wherever the nearest one misses, on reflective parts a line of five gains 23 %) or
    /// `near-capped` (a farther view lowers the nearest one's cost halfway where it is lower:
    /// on a periodic texture the far views' aliased matches cannot win, a `random` line of five
    /// 1.320 → 0.201 px, but the reflective gain is gone; docs/experiments.md).
    #[serde(default)]
    pub side_rule: SideRule,
}

/// The serde default of [`SgmConfig::costs_in_passes`]: configurations written before it was
/// the default read as it is now.
fn default_costs_in_passes() -> bool {
    true
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
            cost: PixelCost::Census {
                radius: 3,
                symmetric: false,
            },
            block_radius_px: 3,
            p1: 300,
            p2: 3000,
            subpixel: true,
            subpixel_fit: SubpixelFit::Equiangular,
            median: true,
            weighted_median: None,
            block_subpixel: None,
            photometric: None,
            costs_in_passes: true,
            side_rule: SideRule::Min,
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
        self.run_for(problem, Needs::ALL, progress)
    }

    fn run_for(&self, problem: &Problem, needs: Needs, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        let spec = CostSpec {
            pixel: self.config.cost,
            block_radius_px: self.config.block_radius_px,
        };
        let prepared = PreparedProblem::new(problem, spec, self.config.fusion)?.with_side_rule(self.config.side_rule);
        let (w, h) = (prepared.width(), prepared.height());
        let bands = h.div_ceil(band_rows(h));
        let done = AtomicUsize::new(0);
        // Cost volume: the first half of the work; aggregation the rest.
        let shift = quantisation_shift(spec.max_cost());
        let (p1, p2) = (
            quantise_penalty(self.config.p1, shift),
            quantise_penalty(self.config.p2, shift),
        );
        let subpixel = self.config.subpixel.then_some(self.config.subpixel_fit);
        let (data, confidence) = if self.config.costs_in_passes {
            let confidence = needs.confidence;
            select_prepared(&prepared, shift, (p1, p2), subpixel, confidence, &|done| {
                progress(0.95 * done);
            })
        } else {
            let volume = prepared.fused_volume(shift, &|| {
                progress(0.5 * (done.fetch_add(1, Ordering::Relaxed) + 1) as f32 / bands as f32);
            });
            select_volume(&volume, (p1, p2), subpixel)
        };
        progress(0.95);
        let mut disparity = DisparityImage {
            width: w,
            height: h,
            data,
            confidence: needs.confidence.then_some(confidence),
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
        if let Some(config) = &self.config.photometric {
            crate::photometric::refine_photometric(problem, &mut disparity, config)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Image;
    use crate::rng::SplitMix64;
    use crate::volume::Neighbour;

    #[test]
    fn costs_made_in_the_passes_give_the_same_result() {
        // A textured plane at 4 px seen by a cross of four views, 300 × 140 (bands of made
        // costs end inside the image).
        let (w, h, d) = (300, 140, 4i32);
        let mut rng = SplitMix64::new(11);
        let (tw, th) = (w + 20, h + 20);
        let texture: Vec<u8> = (0..tw * th).map(|_| (rng.next_u64() >> 56) as u8).collect();
        let view = |[ox, oy]: [i32; 2]| {
            let data = (0..w * h)
                .map(|i| {
                    let x = (i % w) as i32 + 10 + ox * d;
                    let y = (i / w) as i32 + 10 + oy * d;
                    texture[y as usize * tw + x as usize]
                })
                .collect();
            Image::gray(w, h, data).unwrap_or_else(|e| panic!("{e}"))
        };
        let problem = crate::volume::plane_of_cross(view, 16);
        let run = |costs_in_passes: bool| {
            let method = Sgm {
                name: "sgm-heuristic",
                config: SgmConfig {
                    costs_in_passes,
                    ..SgmConfig::default()
                },
            };
            let reported = std::sync::Mutex::new(Vec::new());
            let disparity = method
                .run(&problem, &|p| {
                    reported.lock().unwrap_or_else(|e| e.into_inner()).push(p)
                })
                .unwrap_or_else(|e| panic!("{e}"));
            (disparity, reported.into_inner().unwrap_or_else(|e| e.into_inner()))
        };
        let ((stored, _), (made, progress)) = (run(false), run(true));
        assert!(stored.data == made.data && stored.confidence == made.confidence);
        // Made band by band, the progress moves with the bands (two of 128 rows), then ends at 1.
        assert!(progress.windows(2).all(|p| p[0] <= p[1]), "{progress:?}");
        assert!(progress.iter().any(|p| *p > 0.0 && *p < 0.95), "{progress:?}");
        assert_eq!(progress.last(), Some(&1.0), "{progress:?}");
        let inside = stored.data[70 * w + 150];
        assert!((inside - 4.0).abs() < 0.5, "{inside}");
        // Asked for the disparities alone: the same ones, no confidence.
        let method = Sgm {
            name: "sgm-heuristic",
            config: SgmConfig::default(),
        };
        let alone = method
            .run_for(&problem, Needs::DISPARITY, &|_| {})
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(alone.data == made.data && alone.confidence.is_none());
        assert!(made.confidence.is_some());
    }

    #[test]
    fn near_capped_sides_keep_a_far_view_s_false_match_from_winning() {
        // A line of five over a textured plane at 4 px, the inner views noisy; the outer views
        // (±2 baselines) show the texture as if the plane lay at 7 px: a perfect match at the
        // wrong disparity, as a periodic texture's alias gives. The minimum over a side takes
        // it; near-capped keeps the inner views' answer.
        let (w, h) = (160, 80);
        let mut rng = SplitMix64::new(5);
        let (tw, th) = (w + 40, h + 4);
        let texture: Vec<u8> = (0..tw * th).map(|_| (rng.next_u64() >> 56) as u8).collect();
        let mut view = |ox: i32, d: i32, noise: bool| {
            let data = (0..w * h)
                .map(|i| {
                    let x = (i % w) as i32 + 20 + ox * d;
                    let v = texture[(i / w + 2) * tw + x as usize];
                    if noise {
                        v.saturating_add((rng.next_u64() >> 61) as u8)
                    } else {
                        v
                    }
                })
                .collect();
            Image::gray(w, h, data).unwrap_or_else(|e| panic!("{e}"))
        };
        let reference = view(0, 0, false);
        let neighbours = [("left2", -2, 7), ("left", -1, 4), ("right", 1, 4), ("right2", 2, 7)]
            .into_iter()
            .map(|(role, ox, d)| Neighbour {
                role: role.into(),
                image: view(ox, d, ox.abs() == 1),
                offset: [ox, 0],
                baseline_ratio: 1.0,
            })
            .collect();
        let problem = Problem {
            reference,
            neighbours,
            min_disparity: 0,
            num_disparities: 10,
        };
        let share_at = |side_rule: SideRule, d: f32| {
            let method = Sgm {
                name: "sgm-heuristic",
                config: SgmConfig {
                    side_rule,
                    ..SgmConfig::default()
                },
            };
            let out = method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
            // Columns 20 … 139: every view sees both disparities.
            let interior: Vec<f32> = (0..h)
                .flat_map(|y| (20..w - 20).map(move |x| (x, y)))
                .map(|(x, y)| out.data[y * w + x])
                .collect();
            interior.iter().filter(|v| (**v - d).abs() < 0.5).count() as f32 / interior.len() as f32
        };
        let (capped, min) = (share_at(SideRule::NearCapped, 4.0), share_at(SideRule::Min, 7.0));
        assert!(capped > 0.9, "near-capped: {:.0} % at the plane", 100.0 * capped);
        assert!(
            min > 0.5,
            "min: only {:.0} % at the far views' false match",
            100.0 * min
        );
    }
}
