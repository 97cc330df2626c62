//! Multiscopic graph cuts (paper, section III-C): Kolmogorov–Zabih's energy with occlusion and
//! uniqueness over the fused Birchfield–Tomasi data term, minimised by α-expansion
//! ([`crate::graph_cuts`]). Occluded pixels have no estimate unless `fill_occlusions` is set.

use std::ops::Range;
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Family, Method, MethodEntry, Progress, configure};
use crate::FuseError;
use crate::fusion::Fusion;
use crate::graph_cuts::{
    DataNorm, EnergyParams, KzEnergy, Uniqueness, expand_until_converged, label_order, occlusion_from_kth_sums,
};
use crate::image::{DisparityImage, Image};
use crate::postprocess::{WeightedMedian, weighted_median};
use crate::volume::{Neighbour, Problem};

/// Configuration of graph cuts. Defaults are the paper's (K = 10, λ1 = 9, λ2 = 3, θ = 8) with the
/// IPOL program's squared Birchfield–Tomasi cost truncated at 30; at most 2 rounds over the labels
/// (the IPOL program's 4 lowered the energy by under 1 % more and changed no metric on
/// `middlebury2006-third-dev` by more than 0.003 px, at twice the time).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraphCutsConfig {
    /// Cost fusion over the neighbours.
    pub fusion: Fusion,
    /// Occlusion penalty K (data-cost units).
    pub occlusion_k: f32,
    /// K from the data (IPOL's heuristic: mean of each pixel's k-th smallest cost, k = labels/4),
    /// with λ1 = 3K/5 and λ2 = K/5; `occlusion_k`, `lambda1` and `lambda2` are then ignored.
    pub automatic_k: bool,
    /// Smoothness penalty between neighbouring pixels of similar colour (λ1).
    pub lambda1: f32,
    /// Smoothness penalty across a colour edge (λ2).
    pub lambda2: f32,
    /// Colour difference (any channel, any view) from which two neighbouring pixels are an edge (θ).
    pub edge_threshold: u8,
    /// Data norm: `l2` (squared, the IPOL default) or `l1`.
    pub data_norm: DataNorm,
    /// Uniqueness towards the views the fused cost uses (`used-views`) or towards every view
    /// (`all-views`).
    pub uniqueness: Uniqueness,
    /// Upsample the views 2× before the cut (the paper's remedy for staircase artefacts; about
    /// 8× slower), disparities come back in half pixels.
    pub upsample: bool,
    /// Seed of the random label order.
    pub seed: u64,
    /// Largest number of rounds over the labels (a round in which no expansion lowers the
    /// energy ends the run earlier).
    pub max_rounds: usize,
    /// Fill occluded pixels with the smaller neighbouring valid disparity on the row.
    pub fill_occlusions: bool,
    /// Sub-pixel num_disparities: a parabola through the fused costs at `d − 1`, `d`, `d + 1`
    /// summed over this radius's window (pixels of the same surface only, see
    /// [`KzEnergy::subpixel_disparity`]); `0` = integer disparities, as the paper and the IPOL
    /// program give.
    #[serde(alias = "subpixel_radius")]
    pub subpixel_radius_px: usize,
    /// An image-guided weighted median after the rest (`postprocess::WeightedMedian`; `{}` =
    /// its defaults, `null` = none): depth edges snap to the reference's colour edges.
    pub weighted_median: Option<WeightedMedian>,
    /// The fused data term is kept for every (label, pixel) when that takes at most this many
    /// MiB (3 bytes each), else computed where it is read: the same result, about 1.3–1.5 × the
    /// time, 0.8 GB less at 1920×1080 with 128 labels (`fuse::graph_cuts::EnergyParams::stored_data_mib`).
    pub stored_data_mib: usize,
    /// Row strips solved side by side (one cut per strip and expansion, the strips' cuts in
    /// parallel), each with the rows around its share that its matches reach plus context
    /// ([`strips_of`]); `1` = the whole image in one cut. A fixed number rather than the host's
    /// threads, so that the result is the same on every host: 2 (the default) takes about
    /// 1.4–1.6 × less time on two cores.
    pub strips: usize,
}

impl super::FusedConfig for GraphCutsConfig {
    fn set_fusion(&mut self, fusion: Fusion) {
        self.fusion = fusion;
    }
}

impl Default for GraphCutsConfig {
    fn default() -> Self {
        let energy = EnergyParams::default();
        Self {
            fusion: Fusion::Heuristic,
            occlusion_k: energy.occlusion,
            automatic_k: false,
            lambda1: energy.lambda_similar,
            lambda2: energy.lambda_edge,
            edge_threshold: energy.edge_threshold,
            data_norm: energy.norm,
            uniqueness: energy.uniqueness,
            upsample: false,
            seed: 1,
            max_rounds: 2,
            weighted_median: None,
            fill_occlusions: false,
            subpixel_radius_px: DEFAULT_SUBPIXEL_RADIUS,
            stored_data_mib: energy.stored_data_mib,
            strips: DEFAULT_STRIPS,
        }
    }
}

/// Row strips by default ([`GraphCutsConfig::strips`]).
pub const DEFAULT_STRIPS: usize = 2;
/// Most row strips.
pub const MAX_STRIPS: usize = 64;
/// Rows of context each strip takes beyond its share and the matches' vertical reach: the
/// smoothness terms and the readout's windows (13 × 13 and 5 × 5) around the rows it keeps.
pub const STRIP_CONTEXT_ROWS: usize = 32;

/// Window radius of the sub-pixel readout: 13 × 13 pixels. On `middlebury2006-third-dev` the
/// error fell with every radius tried (1, 2, 3, 4, 6), most below 3 and little beyond 4.
pub const DEFAULT_SUBPIXEL_RADIUS: usize = 6;
/// Largest window radius of the sub-pixel readout (its work grows with the window's area).
pub const MAX_SUBPIXEL_RADIUS: usize = 32;

/// Graph cuts with one fusion.
pub struct GraphCuts {
    name: &'static str,
    config: GraphCutsConfig,
}

impl Method for GraphCuts {
    super::name_and_config!();

    fn run(&self, problem: &Problem, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        let upsampled;
        let solved = if self.config.upsample {
            upsampled = upsample_problem(problem)?;
            &upsampled
        } else {
            problem
        };
        let c = &self.config;
        // The post-processing's parameters before the cuts' seconds to minutes of work.
        if let Some(filter) = &c.weighted_median {
            filter.validate()?;
        }
        // The views' sizes before they are cut into strips.
        solved.validate()?;
        let strips = strips_of(solved, c.fusion, c.strips);
        // Each strip its own problem and energy, side by side. `stored_data_mib` is the whole
        // run's: every strip stores its data term when all of them together fit, none otherwise.
        let cells: usize = strips
            .iter()
            .map(|s| {
                s.rows
                    .len()
                    .saturating_mul(solved.reference.width)
                    .saturating_mul(solved.num_disparities)
            })
            .fold(0, usize::saturating_add);
        let params = EnergyParams {
            occlusion: c.occlusion_k,
            lambda_similar: c.lambda1,
            lambda_edge: c.lambda2,
            edge_threshold: c.edge_threshold,
            norm: c.data_norm,
            uniqueness: c.uniqueness,
            stored_data_mib: if cells.saturating_mul(3) <= c.stored_data_mib.saturating_mul(1 << 20) {
                usize::MAX
            } else {
                0
            },
        };
        let mut energies = strips
            .par_iter()
            .map(|strip| KzEnergy::new(&strip.problem(solved)?, c.fusion, params))
            .collect::<Result<Vec<_>, FuseError>>()?;
        if c.automatic_k {
            // K from the rows the strips keep: every pixel once.
            let k = occlusion_from_kth_sums(
                energies
                    .iter()
                    .zip(&strips)
                    .map(|(energy, strip)| energy.kth_cost_sums(strip.keep.clone()))
                    .fold((0.0, 0), |(s, n), (sum, count)| (s + sum, n + count)),
            );
            for energy in &mut energies {
                energy.set_penalties(k, 3.0 * k / 5.0, k / 5.0);
            }
        }
        progress(0.05);
        let labels = solved.num_disparities;
        let order = label_order(labels, c.seed);
        // Progress: rounds are at most `max_rounds` but usually end after two or three.
        let expected = (strips.len() * labels * c.max_rounds.min(3)) as f32;
        let (done, reported) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let parts: Vec<DisparityImage> = energies
            .par_iter_mut()
            .map(|energy| {
                expand_until_converged(energy, &order, c.max_rounds, &mut |_| {
                    // Reported only forwards (the strips' threads may call in either order).
                    let done = done.fetch_add(1, Ordering::Relaxed) + 1;
                    if reported.fetch_max(done, Ordering::Relaxed) < done {
                        progress(0.05 + 0.9 * (done as f32 / expected).min(1.0));
                    }
                });
                if c.subpixel_radius_px > 0 {
                    energy.subpixel_disparity(c.subpixel_radius_px)
                } else {
                    energy.disparity()
                }
            })
            .collect();
        drop(energies);
        let mut disparity = stitch(&strips, &parts, solved.reference.width, solved.reference.height);
        if c.upsample {
            disparity = downsample_disparity(&disparity, problem.reference.width, problem.reference.height);
        }
        if c.fill_occlusions {
            disparity.fill_invalid_from_row_neighbours();
        }
        if let Some(filter) = &c.weighted_median {
            disparity = weighted_median(&disparity, &problem.reference, filter)?;
        }
        crate::postprocess::scale_by_local_consistency(&mut disparity);
        progress(1.0);
        Ok(disparity)
    }
}

/// Bilinear 2× upsampling with pixel centres on integers: pixel `u` of the result samples the
/// original at `u / 2` (even: a pixel, odd: the midpoint of two).
fn upsample_image(image: &Image) -> Result<Image, FuseError> {
    let (w, h, c) = (image.width, image.height, image.channels);
    let (uw, uh) = (2 * w - 1, 2 * h - 1);
    let mut data = vec![0u8; uw * uh * c];
    for v in 0..uh {
        let (y0, y1) = (v / 2, v.div_ceil(2).min(h - 1));
        for u in 0..uw {
            let (x0, x1) = (u / 2, u.div_ceil(2).min(w - 1));
            for k in 0..c {
                let at = |x: usize, y: usize| u32::from(image.data[(y * w + x) * c + k]);
                let sum = at(x0, y0) + at(x1, y0) + at(x0, y1) + at(x1, y1);
                data[(v * uw + u) * c + k] = ((sum + 2) / 4) as u8;
            }
        }
    }
    Image::new(uw, uh, c, data)
}

/// `problem` with every view made by `image` from its own (the range unchanged).
fn map_views(problem: &Problem, image: impl Fn(&Image) -> Result<Image, FuseError>) -> Result<Problem, FuseError> {
    Ok(Problem {
        reference: image(&problem.reference)?,
        neighbours: problem
            .neighbours
            .iter()
            .map(|n| {
                Ok(Neighbour {
                    role: n.role.clone(),
                    image: image(&n.image)?,
                    offset: n.offset,
                    baseline_ratio: n.baseline_ratio,
                })
            })
            .collect::<Result<_, FuseError>>()?,
        ..*problem
    })
}

/// The problem at twice the resolution and twice the disparities.
fn upsample_problem(problem: &Problem) -> Result<Problem, FuseError> {
    Ok(Problem {
        min_disparity: 2 * problem.min_disparity,
        num_disparities: 2 * problem.num_disparities - 1,
        ..map_views(problem, upsample_image)?
    })
}

/// Back to the original grid: every other pixel, disparities halved.
fn downsample_disparity(up: &DisparityImage, width: usize, height: usize) -> DisparityImage {
    let at = |y: usize, x: usize| 2 * y * up.width + 2 * x;
    let pixels = || (0..height).flat_map(move |y| (0..width).map(move |x| at(y, x)));
    DisparityImage {
        width,
        height,
        data: pixels().map(|i| up.data[i] / 2.0).collect(),
        confidence: up.confidence.as_ref().map(|c| pixels().map(|i| c[i]).collect()),
    }
}

/// One row strip of a problem solved in strips: the rows it is cut from and, within them, the
/// rows of the result it keeps.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Strip {
    /// Rows of the views the strip's problem holds.
    pub rows: Range<usize>,
    /// Rows of the strip's result kept (relative to `rows.start`).
    pub keep: Range<usize>,
}

impl Strip {
    /// The problem of this strip: every view cut to its rows.
    fn problem(&self, problem: &Problem) -> Result<Problem, FuseError> {
        map_views(problem, |image| {
            let row = image.width * image.channels;
            Image::new(
                image.width,
                self.rows.len(),
                image.channels,
                image.data[self.rows.start * row..self.rows.end * row].to_vec(),
            )
        })
    }
}

/// `wanted` row strips of `problem` solved with `fusion` (fewer where the image is too short
/// for them): equal shares of the rows, each cut with a margin of the largest vertical shift of
/// a match in the views `fusion` uses (a top or bottom neighbour's reach over the searched
/// range) plus [`STRIP_CONTEXT_ROWS`] on each side that has a neighbouring strip, so that the
/// pixels it keeps find their matches where the whole image has them and their smoothness
/// terms and readout windows within the strip (the labels there are the strip's own cut's); a
/// share is at least that margin (a smaller one would cost more rows than it saves). Uniqueness is enforced within each strip: two strips
/// may both match a neighbour pixel near their seam.
pub fn strips_of(problem: &Problem, fusion: Fusion, wanted: usize) -> Vec<Strip> {
    let height = problem.reference.height;
    let ends = [
        problem.min_disparity as f32,
        (problem.min_disparity as f32) + problem.num_disparities.saturating_sub(1) as f32,
    ];
    let reach = problem
        .neighbours_for(fusion)
        .iter()
        .flat_map(|n| ends.map(|d| (n.offset[1] as f32 * d * n.baseline_ratio).abs().ceil() as usize))
        .max()
        .unwrap_or(0)
        .min(height);
    let margin = reach + STRIP_CONTEXT_ROWS;
    let count = wanted.clamp(1, MAX_STRIPS).min(height / margin).max(1);
    (0..count)
        .map(|i| {
            let share = i * height / count..(i + 1) * height / count;
            let rows = share.start.saturating_sub(margin)..(share.end + margin).min(height);
            Strip {
                keep: share.start - rows.start..share.end - rows.start,
                rows,
            }
        })
        .collect()
}

/// The strips' kept rows as one image.
fn stitch(strips: &[Strip], parts: &[DisparityImage], width: usize, height: usize) -> DisparityImage {
    let mut data = Vec::with_capacity(width * height);
    let mut confidence = Some(Vec::with_capacity(width * height));
    for (strip, part) in strips.iter().zip(parts) {
        let kept = strip.keep.start * width..strip.keep.end * width;
        data.extend_from_slice(&part.data[kept.clone()]);
        confidence = match (confidence, &part.confidence) {
            (Some(mut all), Some(own)) => {
                all.extend_from_slice(&own[kept]);
                Some(all)
            }
            _ => None,
        };
    }
    DisparityImage {
        width,
        height,
        data,
        confidence,
    }
}

fn build(
    name: &'static str,
    fusion: Fusion,
    overrides: Option<&serde_json::Value>,
) -> Result<Box<dyn Method>, FuseError> {
    let config: GraphCutsConfig = configure(fusion, overrides)?;
    if config.subpixel_radius_px > MAX_SUBPIXEL_RADIUS {
        return Err(FuseError::Config {
            field: "subpixel_radius_px",
            value: config.subpixel_radius_px.to_string(),
            reason: "at most 32 (a 65 × 65 window; 0 = integer labels)",
        });
    }
    if !(1..=MAX_STRIPS).contains(&config.strips) {
        return Err(FuseError::Config {
            field: "strips",
            value: config.strips.to_string(),
            reason: "1 (the whole image in one cut) to 64 row strips",
        });
    }
    if config.max_rounds == 0 {
        return Err(FuseError::Config {
            field: "max_rounds",
            value: "0".into(),
            reason: "at least one round",
        });
    }
    Ok(Box::new(GraphCuts { name, config }))
}

/// Registry entries.
pub const ENTRIES: &[MethodEntry] = &[
    MethodEntry {
        name: "gc-stereo",
        summary: "graph cuts (Kolmogorov-Zabih: occlusion, uniqueness, alpha-expansion), two-view stereo against the right view",
        family: Family::GraphCuts,
        build: |o| build("gc-stereo", Fusion::Stereo, o),
    },
    MethodEntry {
        name: "gc-mean",
        summary: "graph cuts over the mean-fused data term, uniqueness towards every neighbour",
        family: Family::GraphCuts,
        build: |o| build("gc-mean", Fusion::Mean, o),
    },
    MethodEntry {
        name: "gc-min",
        summary: "graph cuts over the min-fused data term (the paper's three-view choice)",
        family: Family::GraphCuts,
        build: |o| build("gc-min", Fusion::Min, o),
    },
    MethodEntry {
        name: "gc-heuristic",
        summary: "graph cuts over the heuristic-fused data term",
        family: Family::GraphCuts,
        build: |o| build("gc-heuristic", Fusion::Heuristic, o),
    },
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph_cuts::tests::plane_problem;
    use crate::image::textured_view;

    #[test]
    fn every_variant_finds_the_plane_and_marks_or_fills_the_border() {
        let problem = plane_problem(3);
        let (w, h) = (problem.reference.width, problem.reference.height);
        for name in ["gc-stereo", "gc-mean", "gc-min", "gc-heuristic"] {
            let method = super::super::build(name, None).unwrap_or_else(|e| panic!("{e}"));
            let d = method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
            // Away from the borders every pixel is matched at 3 (the sub-pixel readout within
            // 0.15 of it: the texture is a hash, not a smooth signal).
            for y in 0..h {
                for x in 4..w - 4 {
                    let v = d.data[y * w + x];
                    assert!((v - 3.0).abs() < 0.15, "{name} ({x}, {y}): {v}");
                }
            }
            let filled = super::super::build(name, Some(&serde_json::json!({"fill_occlusions": true})))
                .and_then(|m| m.run(&problem, &|_| {}))
                .unwrap_or_else(|e| panic!("{e}"));
            assert!(
                filled.data.iter().all(|v| v.is_finite()),
                "{name}: occlusions left after filling"
            );
        }
        // Stereo against the right view cannot match the columns whose correspondence leaves it.
        let stereo = super::super::build("gc-stereo", None)
            .and_then(|m| m.run(&problem, &|_| {}))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(
            stereo.data[..3].iter().all(|v| !v.is_finite()),
            "{:?}",
            &stereo.data[..4]
        );
    }

    #[test]
    fn options_upsampling_and_automatic_k_run() {
        let problem = plane_problem(2);
        let w = problem.reference.width;
        let overrides = serde_json::json!({"upsample": true, "automatic_k": true, "fill_occlusions": true, "seed": 9});
        let method = super::super::build("gc-mean", Some(&overrides)).unwrap_or_else(|e| panic!("{e}"));
        let d = method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((d.width, d.height), (w, problem.reference.height));
        assert_eq!(d.data[10 * w + 20], 2.0);
        let energy = KzEnergy::new(&problem, Fusion::Mean, EnergyParams::default()).unwrap_or_else(|e| panic!("{e}"));
        let k = energy.automatic_occlusion();
        assert!(k.is_finite() && k > 0.0, "{k}");
        let zero_rounds = super::super::build("gc-min", Some(&serde_json::json!({"max_rounds": 0})))
            .and_then(|m| m.run(&problem, &|_| {}));
        assert!(matches!(
            zero_rounds,
            Err(FuseError::Config {
                field: "max_rounds",
                ..
            })
        ));
        let wide = super::super::build("gc-min", Some(&serde_json::json!({"subpixel_radius_px": 33})))
            .and_then(|m| m.run(&problem, &|_| {}));
        assert!(matches!(
            wide,
            Err(FuseError::Config {
                field: "subpixel_radius_px",
                ..
            })
        ));
    }

    /// A textured fronto-parallel plane at disparity `d` seen from a cross of four neighbours,
    /// `width` × `height`.
    fn cross_plane_problem(width: usize, height: usize, d: i64) -> Problem {
        let view = |[ox, oy]: [i32; 2]| {
            let texture = |x: i64, y: i64| (((x * 37 + y * 11) ^ (x * y)) % 97 * 2 + 20) as u8;
            let (sx, sy) = (i64::from(ox) * d, i64::from(oy) * d);
            let data = (0..height as i64)
                .flat_map(|y| (0..width as i64).map(move |x| texture(x + sx, y + sy)))
                .collect();
            Image::gray(width, height, data).unwrap_or_else(|e| panic!("{e}"))
        };
        crate::volume::plane_of_cross(view, 8)
    }

    #[test]
    fn strips_share_the_rows_out_with_the_margin_their_matches_reach() {
        // A cross searching 0..8: the top and bottom views' matches reach 7 rows.
        let problem = cross_plane_problem(48, 200, 3);
        let margin = 7 + STRIP_CONTEXT_ROWS;
        let strips = strips_of(&problem, Fusion::Heuristic, 2);
        assert_eq!(
            strips,
            vec![
                Strip {
                    rows: 0..100 + margin,
                    keep: 0..100
                },
                Strip {
                    rows: 100 - margin..200,
                    keep: margin..margin + 100
                },
            ]
        );
        // Three shares of 66 rows hold their margin of 39; six of 33 would not: five.
        assert_eq!(strips_of(&problem, Fusion::Heuristic, 3).len(), 3);
        assert_eq!(strips_of(&problem, Fusion::Heuristic, 6).len(), 5);
        assert_eq!(
            strips_of(&problem, Fusion::Heuristic, 1),
            vec![Strip {
                rows: 0..200,
                keep: 0..200
            }]
        );
        // A line (no vertical reach) has room for more.
        let mut line = problem.clone();
        line.neighbours.truncate(2);
        let strips = strips_of(&line, Fusion::Heuristic, 3);
        assert_eq!(strips.len(), 3);
        let kept: Vec<usize> = strips
            .iter()
            .flat_map(|s| s.keep.clone().map(move |y| s.rows.start + y))
            .collect();
        assert_eq!(kept, (0..200).collect::<Vec<_>>(), "every row kept once, in order");
        // Too short for two.
        assert_eq!(
            strips_of(&cross_plane_problem(48, 40, 3), Fusion::Heuristic, 2).len(),
            1
        );
        // The reach is the largest vertical shift the energy gives a label: a signed range and a
        // farther view (−10..6 at 1.5 baselines: 15 rows), and only the views the fusion uses
        // (stereo: the right view, no vertical reach).
        let mut signed = problem.clone();
        signed.min_disparity = -10;
        signed.num_disparities = 17;
        for n in &mut signed.neighbours {
            n.baseline_ratio = 1.5;
        }
        let energy = KzEnergy::new(&signed, Fusion::Heuristic, EnergyParams::default());
        assert!(energy.is_ok());
        let largest_shift = (0..17)
            .map(|l| ((-10.0 + l as f32) * 1.5).round().abs() as usize)
            .max()
            .unwrap_or(0);
        assert_eq!(largest_shift, 15);
        let strips = strips_of(&signed, Fusion::Heuristic, 2);
        assert_eq!(strips[0].rows, 0..100 + largest_shift + STRIP_CONTEXT_ROWS);
        let strips = strips_of(&signed, Fusion::Stereo, 2);
        assert_eq!(strips[0].rows, 0..100 + STRIP_CONTEXT_ROWS);
    }

    #[test]
    fn strips_take_automatic_k_from_every_pixel_once_and_do_not_depend_on_the_threads() {
        let problem = cross_plane_problem(48, 200, 3);
        let h = problem.reference.height;
        let energy = |p: &Problem| {
            KzEnergy::new(p, Fusion::Heuristic, EnergyParams::default()).unwrap_or_else(|e| panic!("{e}"))
        };
        let whole = energy(&problem).kth_cost_sums(0..h);
        let strips = strips_of(&problem, Fusion::Heuristic, 2);
        let parts = strips
            .iter()
            .map(|s| energy(&s.problem(&problem).unwrap_or_else(|e| panic!("{e}"))).kth_cost_sums(s.keep.clone()))
            .fold((0.0, 0), |(s, n), (sum, count)| (s + sum, n + count));
        assert_eq!(parts, whole);
        // The same result on one thread and on four, with every option the strips touch.
        let overrides =
            serde_json::json!({"strips": 2, "automatic_k": true, "upsample": true, "fill_occlusions": true});
        let method = super::super::build("gc-heuristic", Some(&overrides)).unwrap_or_else(|e| panic!("{e}"));
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap_or_else(|e| panic!("{e}"))
                .install(|| method.run(&problem, &|_| {}))
                .unwrap_or_else(|e| panic!("{e}"))
        };
        let one = on(1);
        assert_eq!(one, on(4));
        let w = problem.reference.width;
        let plane = (8..h - 8)
            .flat_map(|y| (8..w - 8).map(move |x| y * w + x))
            .all(|i| (one.data[i] - 3.0).abs() < 0.2);
        assert!(plane, "not the plane");
    }

    #[test]
    fn strips_solved_side_by_side_find_the_plane_as_the_whole_image_does() {
        let problem = cross_plane_problem(48, 200, 3);
        let (w, h) = (problem.reference.width, problem.reference.height);
        let run = |strips: usize| {
            super::super::build("gc-heuristic", Some(&serde_json::json!({"strips": strips})))
                .and_then(|m| m.run(&problem, &|_| {}))
                .unwrap_or_else(|e| panic!("{e}"))
        };
        let (whole, halves) = (run(1), run(2));
        // The data term computed where it is read gives the same strips.
        let computed = super::super::build(
            "gc-heuristic",
            Some(&serde_json::json!({"strips": 2, "stored_data_mib": 0})),
        )
        .and_then(|m| m.run(&problem, &|_| {}))
        .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(computed, halves);
        assert_eq!((halves.width, halves.height), (w, h));
        let confidence = halves.confidence.as_ref().map_or(0, Vec::len);
        assert_eq!(confidence, w * h);
        // Away from the image's borders (where matches leave the views) both are the plane
        // (the sub-pixel readout within 0.2 of it: the texture is a hash), the same values, the
        // seam at row 100 included.
        for y in 8..h - 8 {
            for x in 8..w - 8 {
                let (a, b) = (whole.data[y * w + x], halves.data[y * w + x]);
                assert!((a - 3.0).abs() < 0.2 && a == b, "({x}, {y}): {a} / {b}");
            }
        }
        let none = super::super::build("gc-min", Some(&serde_json::json!({"strips": 0})))
            .and_then(|m| m.run(&problem, &|_| {}));
        assert!(matches!(none, Err(FuseError::Config { field: "strips", .. })));
    }

    #[test]
    fn upsampling_keeps_the_pixels_and_interpolates_between() {
        let image = Image::gray(2, 2, vec![0, 100, 200, 40]).unwrap_or_else(|e| panic!("{e}"));
        let up = upsample_image(&image).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((up.width, up.height), (3, 3));
        assert_eq!(up.data, vec![0, 50, 100, 100, 85, 70, 200, 120, 40]);
        let d = DisparityImage {
            width: 3,
            height: 3,
            data: vec![4.0, 0.0, 6.0, 0.0, 0.0, 0.0, 8.0, 0.0, 3.0],
            confidence: Some(vec![0.1, 0.0, 0.2, 0.0, 0.0, 0.0, 0.3, 0.0, 0.4]),
        };
        let down = downsample_disparity(&d, 2, 2);
        assert_eq!(down.data, vec![2.0, 3.0, 4.0, 1.5]);
        assert_eq!(down.confidence, Some(vec![0.1, 0.2, 0.3, 0.4]));
    }
    #[test]
    fn a_plane_between_two_integers_gets_its_half_pixel() {
        // The plane at d = 3.5: each neighbour the mean of the views at 3 and 4.
        let mut problem = plane_problem(3);
        let (w, h) = (problem.reference.width, problem.reference.height);
        for (neighbour, sign) in problem.neighbours.iter_mut().zip([-1i64, 1]) {
            let (a, b) = (textured_view(w, h, 3 * sign), textured_view(w, h, 4 * sign));
            let data = a
                .data
                .iter()
                .zip(&b.data)
                .map(|(x, y)| (u16::from(*x) + u16::from(*y)).div_ceil(2) as u8)
                .collect();
            neighbour.image = Image::gray(w, h, data).unwrap_or_else(|e| panic!("{e}"));
        }
        let error = |overrides: serde_json::Value| {
            let d = super::super::build("gc-min", Some(&overrides))
                .and_then(|m| m.run(&problem, &|_| {}))
                .unwrap_or_else(|e| panic!("{e}"));
            let interior: Vec<f32> = (2..h - 2)
                .flat_map(|y| (8..w - 8).map(move |x| (y, x)))
                .map(|(y, x)| d.data[y * w + x])
                .collect();
            interior.iter().map(|v| (v - 3.5).abs()).sum::<f32>() / interior.len() as f32
        };
        let integer = error(serde_json::json!({"subpixel_radius_px": 0}));
        let subpixel = error(serde_json::json!({}));
        assert!((integer - 0.5).abs() < 0.05, "integer labels are 3 or 4: {integer}");
        assert!(subpixel < 0.15, "sub-pixel error {subpixel} (integer {integer})");
    }
}
