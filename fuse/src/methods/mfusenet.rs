//! MFuseNet (paper, section IV): each neighbour's cost volume aggregated on its own by SGM, the
//! volumes fused by the trained 3D CNN, disparity by soft-argmin (`crate::mfusenet`).
//!
//! `mfusenet` picks the network from the set's neighbours: five-view (left, right, top, bottom)
//! when all four are there, else three-view (left and right, or top and bottom), else the
//! stereo network; `mfusenet-stereo` always takes the stereo network and the `right` view. A set
//! with more views (a line of five, a 3 × 3 grid, crosses at several baselines) runs every
//! cross and opposite pair through its network and averages their log-probabilities, a farther
//! group's only at the disparities its views see (`every_view`); the farther views along each
//! side also join the nearest group's inputs (`side_inputs`). A cross missing arms at the
//! nearest baseline (a T, an L) runs the five-view network with each missing input filled by
//! the opposite view (`fill_cross`); a view no group takes there runs the stereo network.
//! The trained weights of the three variants are compiled into the binary (`fuse/weights/`,
//! made by `replay train`, see `fuse/weights/README.md`); `{"weights": "FILE"}` (or replay's
//! `--weights FILE`) takes a safetensors file instead, whose variant must fit the set.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{Family, Method, MethodEntry, Progress, apply_overrides};
use crate::FuseError;
use crate::borders::{BorderCheck, recheck_borders};
use crate::cost::ValidDisparities;
use crate::fusion::SideRule;
use crate::image::DisparityImage;
use crate::mfusenet::infer::{
    DEFAULT_REFINE_REACH, DEFAULT_SUBPIXEL_FIT, DEFAULT_TILE_BUDGET_BYTES, Estimate, Member, infer_fused,
    infer_with_confidence,
};
use crate::mfusenet::input::{
    InputSpec, SharpSpec, ViewGroup, input_volumes_of_sides_below, ordered_neighbours, pooled_neighbours,
    sharp_volumes_of_sides_below, sides_of, summed, summed_input_volume_below, view_groups, views_for,
};
use crate::mfusenet::pyramid::{
    Band, DEFAULT_MAX_DIRECT_DISPARITIES, DEFAULT_MAX_DIRECT_VOXELS, band_minimum, downsampled, pyramid_factor_for,
    reduced_range,
};
use crate::mfusenet::{Architecture, Network, weights};
use crate::nn::conv::{self, Precision};
use crate::postprocess::{
    FartherMedian, WeightedMedian, farther_by_wider_median, median3x3, scale_by_local_consistency,
    weighted_median_with_votes,
};
use crate::subpixel::{BlockSubpixel, refine_with_block_costs};
use crate::thin_parts::{ThinParts, recover_thin_parts};
use crate::volume::Neighbour;
use crate::volume::{CostVolume, Problem};
use crate::wta::{LockingCurve, SubpixelFit};

/// The shipped weights: per number of input volumes, the paper's architecture and, for the
/// five-view network, the lite one ([`MFuseNetConfig::architecture`] picks).
const SHIPPED: [(usize, Architecture, &str, &[u8]); 4] = [
    (
        1,
        Architecture::Paper,
        "mfusenet-stereo.safetensors",
        include_bytes!("../../weights/mfusenet-stereo.safetensors"),
    ),
    (
        2,
        Architecture::Paper,
        "mfusenet-3view.safetensors",
        include_bytes!("../../weights/mfusenet-3view.safetensors"),
    ),
    (
        4,
        Architecture::Paper,
        "mfusenet-5view.safetensors",
        include_bytes!("../../weights/mfusenet-5view.safetensors"),
    ),
    (
        4,
        Architecture::Lite,
        "mfusenet-5view-lite.safetensors",
        include_bytes!("../../weights/mfusenet-5view-lite.safetensors"),
    ),
];

/// Default [`MFuseNetConfig::locking_strength`].
pub const DEFAULT_LOCKING_STRENGTH: f64 = 0.5;

/// Default [`MFuseNetConfig::farther_vote`].
pub const DEFAULT_FARTHER_VOTE: f32 = 0.5;

/// Configuration of MFuseNet.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MFuseNetConfig {
    /// A safetensors weights file (the reference `state_dict`'s names); `null` = the shipped
    /// weights of the variant the set needs.
    pub weights: Option<String>,
    /// Which shipped network runs where both exist (the five-view one): `lite` (default; its
    /// 3³ and 5³ kernels do a fifth of the paper's work per voxel, trained on the paper
    /// five-view file's recipe for three times its steps: 1.4–1.5 × faster on 960×540 captures,
    /// AvgErr ×0.92 on nine 960×540 captures, ×1.00 on 32 held-out simulated ones) or `paper`
    /// (the paper's kernels, as the three-view and stereo files always are).
    pub architecture: Architecture,
    /// How each neighbour's input volume is made (must match the training); `null` = as the
    /// weights file's metadata `input_spec` says (our default inputs when it says nothing).
    pub input: Option<InputSpec>,
    /// Memory budget of one tile's activations (MiB; 768); larger images are cut into tiles. The
    /// process holds up to about 1.5 times it: raise it for speed where memory allows.
    pub tile_budget_mib: usize,
    /// Soft-argmin only over this many disparities either side of the most probable one
    /// (`null` = over the whole range, as in the paper); see `mfusenet::infer::infer`.
    pub window: Option<usize>,
    /// Sub-pixel from the inputs: the integer nearest the network's estimate, refined by the
    /// `subpixel_fit` curve through the summed input costs (see `mfusenet::infer::Estimate`); `null` = as
    /// the weights file's metadata `estimate` says (`refine` or `soft-argmin`, the paper's and
    /// the default when the file does not say).
    pub refine: Option<bool>,
    /// With the refined estimate: how far (px) it may move from the network's integer to a
    /// neighbouring minimum of the summed input costs when the integer is not one itself
    /// (`mfusenet::infer::refined`); 0 = the integer's own minimum only.
    pub refine_reach: f64,
    /// With the refined estimate: the curve through the summed input costs whose vertex is the
    /// sub-pixel disparity, `equiangular` (default) or `parabola` (see `wta::SubpixelFit` and
    /// `mfusenet::infer::DEFAULT_SUBPIXEL_FIT`).
    pub subpixel_fit: SubpixelFit,
    /// With the refined estimate: the correction of the fit's pixel locking, ten numbers
    /// (`wta::LockingCurve`); `null` = the curve the weights file carries (metadata
    /// `locking_curve`, fitted by `replay train` on its training captures), if any.
    pub locking: Option<LockingCurve>,
    /// With the refined estimate: how much of the `locking` correction to apply, from 0 (the
    /// fit's own offset) to 1 (the whole curve, what the simulated training captures call
    /// for). Real images lock less than our renders: on Middlebury 0.5 gave AvgErr 0.303 →
    /// 0.293 px with Bad0.5 8.15 → 8.34 %, the whole curve 0.294 px with 8.58 % (docs/methods.md,
    /// "Pixel locking").
    pub locking_strength: f64,
    /// A 3×3 median on the result, as block matching and SGM do (shipped three-view network:
    /// Middlebury 0.395 → 0.391 px, held-out simulated five-view 0.347 → 0.338 px, both with the
    /// parabola fit).
    pub median: bool,
    /// An image-guided weighted median after the rest (`postprocess::WeightedMedian`; `{}` =
    /// its defaults, `null` = none): depth edges snap to the reference's colour edges, which
    /// the network, seeing only cost volumes, cannot place. On by default (about 5 % of the
    /// time; the classical methods have it opt-in, their speed is held against OpenCV's):
    /// Middlebury three-view 0.346 → 0.305 px, Bad1 5.89 → 4.94 % (without the votes);
    /// held-out simulated five-view 0.295 → 0.278 px (docs/methods.md, "Weighted median").
    pub weighted_median: Option<WeightedMedian>,
    /// After the weighted median, a second one over twice its radius whose answer is taken only
    /// where it is at least `min_move_px` farther (`postprocess::FartherMedian`; `{}` = its
    /// defaults, `null` = none): the network's foreground fattened over a background of another
    /// colour by more than the first window undoes. Needs `weighted_median`. Middlebury
    /// three-view 0.285 → 0.268 px (Bad1 4.77 → 4.55 %), the held-out `thin` crosses 0.516 →
    /// 0.464 px (4.74 → 4.35 %), the `thin` rows of five at 384×288 0.504 → 0.467 px
    /// (docs/experiments.md, 2026-12-06 (late)).
    pub farther_median: Option<FartherMedian>,
    /// In the weighted median, the vote of a pixel whose estimate the input costs do not back
    /// (no local minimum of the summed input costs within 1 px of it), relative to one they do:
    /// where the network and the data disagree, the pixel's neighbours of the same colour that
    /// agree decide. 1 = every pixel alike. Middlebury 0.305 → 0.303 px, Bad1 4.94 → 4.85 %;
    /// held-out simulated five-view 0.278 → 0.265 px (docs/methods.md, "Weighted median").
    pub disagreeing_vote: f32,
    /// The network sees this many disparities under the searched range as well (negative ones
    /// included), so that answers at the range's start are not in its first slices, where it
    /// fails; the estimate is read from the searched range only (see `input_volumes_below`).
    /// `null` = as the weights file's metadata `context_below` says (0 when it says nothing; 4 in
    /// every shipped file: the five-view one, trained without context, put a far wall at the
    /// range's start 4–6 px off without it; with it, it follows mirror-like tables whose
    /// reflections land in the first slices, as the three-view network does; fuse/weights/README.md).
    pub room_below: Option<usize>,
    /// Test-time flips: the network also answers the set's mirror image (left to right for a
    /// left/right pair and the five-view cross, the left and right volumes swapped; top to
    /// bottom for a top/bottom pair, swapped, and for the stereo network) and the two passes'
    /// logits are averaged, at twice the network's time (`mfusenet::input::flip_axes`,
    /// `mfusenet::infer::Estimate`).
    pub flips: bool,
    /// The widest range (disparities) the network is run on at full size (96), when the
    /// reference's pixels times the range's disparities are at most `max_direct_voxels` (32 M).
    /// Otherwise coarse to fine (`mfusenet::pyramid`): the network on the set reduced by the
    /// smallest integer factor (at least 2) that brings the range to 32 disparities, the depth it
    /// was trained on (64 → 1/2, 96 → 1/3, 128 → 1/4), then the minimum of the summed input costs
    /// at full size within ± factor px of its answer. `replay` logs the level and range the
    /// network saw. `{"max_direct_disparities": 0}` always goes coarse to fine.
    pub max_direct_disparities: usize,
    /// The network's budget at full size: the reference's pixels × the range's disparities
    /// (32 M: 640×360 at 96, 960×540 at 61; a 1080p set goes coarse to fine, at a third of the
    /// time and half the memory for +1 to +4 % AvgErr). Small images at wide ranges are where a
    /// reduced level loses most (the held-out `thin` crosses at 640×360 over 64 disparities
    /// 0.419 → 0.392 px at full size, Middlebury's dev scenes over 64 disparities 0.288 → 0.268).
    #[serde(default = "max_direct_voxels")]
    pub max_direct_voxels: usize,
    /// The fewest disparities the network is run on: a narrower search range is widened
    /// evenly on both sides to this many and the result clamped back into it (see
    /// [`widened_range`]); 16 = [`MIN_NETWORK_DISPARITIES`], at most 64. Weights trained without context
    /// below their range may need the 32 they were trained on.
    #[serde(default = "min_network_disparities")]
    pub min_network_disparities: usize,
    /// Every cross and opposite pair of the set, not only the nearest: each baseline's cross or
    /// its horizontal and vertical pairs go to the network that takes them
    /// (`mfusenet::input::view_groups`), and their log-probabilities are averaged with a vote
    /// per view (a farther group's only at the disparities its views see) before the estimate
    /// is read; it is refined and filtered with the nearest group's costs.
    /// A cross missing arms at the nearest baseline (a T, an L) goes to the five-view network
    /// with each missing input filled by the opposite view (`fill_cross`, the default); the
    /// views at that baseline that no cross or pair takes then (a single axis view beside a
    /// diagonal, or every odd view without `fill_cross`) each run the stereo network in the
    /// same vote.
    /// `false`: one network on the nearest cross, pair or view, as the paper, the other views
    /// unused (the run summary lists the networks and the views they took). With a
    /// view-count-agnostic weights file
    /// (`replay train --views any`): one network pools every view of the set, the nearest
    /// baseline's on the axes first, and the post-processing reads those first ones' costs;
    /// `false`: the nearest ones only (the summary's `views` lists what it took). `null` (the
    /// default): `true`, except for a view-count-agnostic file trained on five-view captures
    /// only (its metadata's `train_config` names no `grid-cross` rig), which read far and
    /// diagonal views worse than nothing (docs/experiments.md).
    pub every_view: Option<bool>,
    /// With several groups (`every_view`), the vote of each view of a group `k` baselines out
    /// is `farther_vote^(k − 1)` of a nearest view's. The networks' logits are saturated, so
    /// where two groups disagree the one with the more extreme log-probabilities wins, and a
    /// farther group that reads an alias of periodic texture (at half the nearer one's period)
    /// can win with a wrong answer; a smaller vote gives such near-ties to the nearer views
    /// while a farther group still decides where the nearer one is unsure. 1 = every view
    /// alike (docs/experiments.md, "A farther group's vote"). Every view against the nearest
    /// group alone, 1 → 0.5: the `random` line of seed 8 +9.9 → −10.9 %, crosses at two
    /// baselines of the same scene +874 → −9.2 %, a workpiece line −10.4 → −5.7 % (reflections
    /// the far pair fixed, now partly left); 0.9 kept more of the workpiece's gain but not the
    /// crosses' (`scripts/eval-votes.sh`).
    #[serde(default = "default_farther_vote")]
    pub farther_vote: f32,
    /// A line of five (±1, ±2 on one axis) into the five-view network alone: ±1 in its left
    /// and right inputs, ±2 in its top and bottom ones (their costs at twice the disparity, each
    /// view its own input, no side inputs), in place of the three-view network on each pair;
    /// with `weights`, that file (`replay train --rig line5` trains one; such a file implies
    /// `line_cross`). Off by default: with the shipped five-view file lines of mirror-like
    /// workpieces gain 40–45 % (that file saw workpieces in training), but a periodic texture
    /// read at its alias by the far pair, which fills two of the four inputs, loses 4 ×
    /// (`random` seed 8: 0.134 → 0.524 px), and the `thin` rows of five lose 8 %
    /// (docs/experiments.md, 2026-12-06 (late night), "A line of five in the five-view
    /// network"). Side inputs are off while it is on.
    #[serde(default)]
    pub line_cross: bool,
    /// A cross missing arms (a T of three views, an L of two: a view on each axis at the
    /// nearest baseline) into the five-view network, each missing arm's input filled with
    /// the opposite view's volume (`mfusenet::input::view_groups`; the summary's `networks`
    /// list a filled input under the view that fills it). On by default: on the held-out
    /// irregular grids (`scripts/eval-irregular.sh`) the `thin` T 2.098 → 1.104 px and L
    /// 1.640 → 1.126, the workpiece T and L −25 to −30 %, the matte `bin` L −12 % and T +4 to
    /// +6 %, in a third less time; `false`: the three-view network on the T's pair and the
    /// stereo one on each odd view, in one vote (docs/results.md "Irregular sets").
    #[serde(default = "yes")]
    pub fill_cross: bool,
    /// Each input of a fixed network's nearest group made from its whole side: the costs of
    /// the views along its ray (a line of five's left input from −1 and −2), made one by
    /// `side_rule`, as the classical heuristic counts sides (on by default; a set with one view
    /// per direction does not change). Middlebury's line with four views on one side: 0.289 →
    /// 0.272 px; docs/experiments.md.
    #[serde(default = "yes")]
    pub side_inputs: bool,
    /// With `side_inputs`, how a side's views become one cost: `"near-capped"` (the default;
    /// a farther view lowers the nearest one's cost halfway where it is lower) or `"min"`
    /// (the classical heuristic's: on reflective parts it gains most, a line of five of the
    /// workpiece 1.36 → 1.12 px, but on periodic texture a far view's aliased match wins, a
    /// `random` line 0.61 → 2.04 px).
    #[serde(default = "near_capped")]
    pub side_rule: SideRule,
    /// Sub-pixel from block-matching costs, last (`subpixel::BlockSubpixel`; `{}` = its
    /// defaults, the default; `null` = none): the estimate's integer stays, its fraction is
    /// re-read from a parabola through fused 9×9 Birchfield–Tomasi block costs where that moves
    /// it by at most 0.2 px; those costs lock to the pixel grid far less than the network's census
    /// and SGM inputs. Slanted planes (`scripts/eval-subpixel.sh`): AvgErr 0.077 → 0.044 px,
    /// BadPix 0.07 52.1 → 18.7 %; Middlebury 0.293 → 0.288 px, Bad1 4.87 → 4.87 %.
    pub block_subpixel: Option<BlockSubpixel>,
    /// The border bands re-read before the sub-pixel step (`borders::BorderCheck`; `{}` = its
    /// defaults; `null`, the default = none): where a neighbour's correspondences leave its
    /// image the network reads that neighbour's mirrored costs and can settle near the range's
    /// start under a near part cut by the image's edge; an estimate there is replaced by the
    /// minimum of the fused block costs of the views that see each disparity, in regions.
    /// Opt-in: on a line of five with such a part (clutter seed 501) 1.083 → 0.724 px, but the
    /// held-out `thin` crosses +13 % (block costs fatten rods near the borders), the toy and
    /// demo captures +6 %, Middlebury +0.7 % (docs/experiments.md, 2026-12-07).
    pub border_check: Option<BorderCheck>,
    /// The last step: each estimate refined by Gauss–Newton steps on the views' brightness at
    /// continuous disparities (`fuse::photometric`: a plane fitted over a 15 × 15 window of
    /// each pixel's own solution, both views of each opposite pair unless one does not see,
    /// moves of at most 0.25 px, none where the plane leaves over 3 grey levels unexplained or
    /// the texture cannot place it to 0.05 px). `null` = off. On by default: the slanted planes
    /// BadPix 0.07 16.6 → 4.8 % (`--rectify`: 13.0 → 1 %), the toy capture −25 %, Middlebury
    /// −0.3 % (docs/methods.md, "Photometric refinement").
    #[serde(default = "default_photometric")]
    pub photometric: Option<crate::photometric::Photometric>,
    /// Thin nearer parts (rods, wires, slats) that the block-summed inputs lose, and the
    /// background seen through the gaps between them that they fill, recovered from per-pixel
    /// costs last (`thin_parts::ThinParts`; `{}` = its defaults, the default; `null` = none). The
    /// `thin` family (`scripts/eval-thin.sh`, never trained on): AvgErr 1.047 → 0.516 px, Bad1
    /// 8.88 → 4.74 % (per-pixel costs averaged over cross-shaped supports, moves kept in patches
    /// shaped like parts, farther moves only to a disparity seen nearby); Middlebury and the
    /// simulated lines no worse (docs/methods.md, "Thin parts from per-pixel costs").
    pub thin_parts: Option<ThinParts>,
    /// The thin-part recovery reads every view of the set (`true`, the default), not only the
    /// network's nearest group: a line of five's outer pair confirms a rod or rejects a
    /// periodic texture's alias that the inner pair alone cannot (the `random` line of seed 8
    /// 0.171 → 0.134 px, a line of five of the held-out `thin` family 1.218 → 1.123 px; the
    /// other lines, grids and crosses within ±1 %; docs/experiments.md 2026-12-06). The
    /// sub-pixel re-reading keeps to the nearest group: a 3 × 3 grid's diagonal views move its
    /// fraction off (the `bin` grid 0.110 → 0.116 px).
    #[serde(default = "yes")]
    pub thin_parts_every_view: bool,
    /// The convolutions' products: `"auto"` (the default: bfloat16 where the host's bfloat16
    /// products beat its f32 ones, AMD from Zen 4; f32 elsewhere, Intel's included:
    /// `fuse::nn::bf16_kernel::preferred`), `"bf16"` (inputs and weights rounded to bfloat16,
    /// sums in f32, for the 3³–7³ layers wherever the host has AVX512-BF16, Intel from Cooper
    /// Lake and AMD from Zen 4; f32 elsewhere), `"int16"` (inputs and weights quantised to
    /// 16-bit integers, pairs of input channels multiplied by AVX2's `vpmaddwd`, for the 3³–7³
    /// layers of two or more input channels, f32 for the rest; `fuse::nn::int16_kernel`: the
    /// same figures as f32 to the fourth decimal, but no faster than f32 on an AVX2 path, whose
    /// 3³ layers wait on memory) or `"f32"`. The run's details say which ran. On the Middlebury
    /// dev scenes and the held-out simulated captures AvgErr and Bad1 are the same to the third
    /// decimal in bfloat16, the paper's networks 25 % faster on AMD Zen 4 and 5, 25 % slower on
    /// a Xeon with AVX512-BF16 (`scripts/eval-precision.sh`, docs/benchmarks.md).
    #[serde(default = "auto_precision")]
    pub precision: Precision,
}

impl Default for MFuseNetConfig {
    fn default() -> Self {
        Self {
            weights: None,
            architecture: Architecture::Lite,
            input: None,
            tile_budget_mib: DEFAULT_TILE_BUDGET_BYTES >> 20,
            window: None,
            refine: None,
            refine_reach: DEFAULT_REFINE_REACH,
            subpixel_fit: DEFAULT_SUBPIXEL_FIT,
            locking: None,
            locking_strength: DEFAULT_LOCKING_STRENGTH,
            median: true,
            weighted_median: Some(WeightedMedian::default()),
            farther_median: Some(FartherMedian::default()),
            disagreeing_vote: 0.05,
            room_below: None,
            flips: false,
            max_direct_disparities: DEFAULT_MAX_DIRECT_DISPARITIES,
            max_direct_voxels: DEFAULT_MAX_DIRECT_VOXELS,
            min_network_disparities: MIN_NETWORK_DISPARITIES,
            every_view: None,
            farther_vote: DEFAULT_FARTHER_VOTE,
            line_cross: false,
            fill_cross: true,
            side_inputs: true,
            side_rule: SideRule::NearCapped,
            block_subpixel: Some(BlockSubpixel::default()),
            border_check: None,
            photometric: Some(crate::photometric::Photometric::default()),
            thin_parts: Some(ThinParts::default()),
            thin_parts_every_view: true,
            precision: Precision::Auto,
        }
    }
}

/// Which result [`MFuseNet::finish`] makes: the coarse level's, which the full-size band reads
/// again, or the last.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stage {
    Coarse,
    Last,
}

/// A network and how its weights file asks for it to be run.
struct Loaded {
    views: usize,
    net: Network,
    /// Metadata `estimate = "refine"`.
    refine: bool,
    /// Metadata `context_below`.
    context_below: usize,
    /// Metadata `input_spec`.
    input: InputSpec,
    /// Metadata `sharp_spec` (a sharp network's sharp volumes).
    sharp: SharpSpec,
    /// Metadata `locking_curve`.
    locking: Option<LockingCurve>,
    /// Metadata `train_config` names the `grid-cross` rig: trained on far and diagonal
    /// neighbours too.
    far_views: bool,
    /// Metadata `train_config` names the `line5` rig: a five-view network trained on lines of
    /// five (`replay train --rig line5`), run as `line_cross` runs a line.
    line: bool,
}

impl Loaded {
    fn new(net: Network, info: &weights::WeightsInfo, file: &str) -> Result<Self, FuseError> {
        let config = info
            .get("train_config")
            .and_then(|c| serde_json::from_str::<serde_json::Value>(c).ok());
        let rig = config.as_ref().and_then(|c| c["rig"].as_str());
        Ok(Self {
            views: net.views,
            refine: weights::refine_recommended(info, file)?,
            context_below: weights::context_below_recommended(info, file)?,
            input: weights::input_spec_recommended(info, file)?,
            sharp: weights::sharp_spec_recommended(info, file)?,
            locking: weights::locking_recommended(info, file)?,
            far_views: rig == Some("grid-cross"),
            line: rig == Some("line5"),
            net,
        })
    }
}

/// The networks of a set that several cover: each group with its loaded network, and the
/// neighbours no group takes.
type ViewPlan<'p, 'n> = (Vec<(ViewGroup<'p>, &'n Loaded)>, Vec<&'p Neighbour>);

/// MFuseNet with its networks loaded.
pub struct MFuseNet {
    name: &'static str,
    config: MFuseNetConfig,
    /// The shipped three networks, or the one from `weights`, each with how its metadata asks
    /// for it to be read.
    networks: Vec<Loaded>,
    /// Only the stereo network and neighbour.
    stereo: bool,
}

impl MFuseNet {
    /// Loads the networks (`weights` or the shipped ones); bad files are errors naming the file
    /// and the tensor.
    pub fn new(name: &'static str, config: MFuseNetConfig, stereo: bool) -> Result<Self, FuseError> {
        let networks = match &config.weights {
            Some(path) => {
                let (net, info) = weights::load(Path::new(path), stereo.then_some(1))?;
                vec![Loaded::new(net, &info, path)?]
            }
            None => SHIPPED
                .iter()
                .filter(|(views, ..)| !stereo || *views == 1)
                .map(|(views, _, file, bytes)| {
                    let file = format!("(shipped) {file}");
                    let (net, info) = weights::from_bytes(bytes, &file, "", Some(*views))?;
                    Loaded::new(net, &info, &file)
                })
                .collect::<Result<_, FuseError>>()?,
        };
        Ok(Self {
            name,
            config,
            networks,
            stereo,
        })
    }

    /// `line_cross`, asked for or implied by a `weights` file trained on lines of five.
    fn line_cross(&self) -> bool {
        self.config.line_cross || (self.config.weights.is_some() && self.networks.iter().any(|n| n.line))
    }

    /// The network for `views` volumes: the configured architecture's where one is shipped for
    /// them, else the paper's (a `weights` file is the only network).
    fn network_of(&self, views: usize) -> Option<&Loaded> {
        let of_views = || self.networks.iter().filter(move |n| n.views == views);
        of_views()
            .find(|n| n.net.architecture == self.config.architecture)
            .or_else(|| of_views().find(|n| n.net.architecture == Architecture::Paper))
            .or_else(|| of_views().next())
    }

    /// The network for a problem.
    fn network_for(&self, problem: &Problem) -> Result<&Loaded, FuseError> {
        let views = match (&self.config.weights, self.stereo) {
            (_, true) => 1,
            (Some(_), false) => self.networks.first().map_or(1, |n| n.views),
            (None, false) => views_for(problem),
        };
        self.network_of(views).ok_or(FuseError::Config {
            field: "weights",
            value: String::new(),
            reason: "no network for this number of neighbours",
        })
    }
}

impl Method for MFuseNet {
    super::name_and_config!();

    fn run(&self, problem: &Problem, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        conv::with_precision(self.config.precision, || self.run_in_precision(problem, progress))
    }

    fn details(&self, problem: &Problem) -> serde_json::Value {
        let mut details = self.details_of(problem);
        if let serde_json::Value::Object(map) = &mut details {
            // What the convolutions ran in here (bfloat16 asked for runs in f32 without the
            // instructions).
            let precision = conv::with_precision(self.config.precision, || conv::effective_precision(3));
            map.insert("precision".into(), serde_json::json!(precision));
            // The 7³ layers' own where they differ (`auto` on Intel's matrix unit: bfloat16 there).
            let wide_kernels = conv::with_precision(self.config.precision, || conv::effective_precision(7));
            if wide_kernels != precision {
                map.insert("precision_7x7x7".into(), serde_json::json!(wide_kernels));
            }
        }
        details
    }
}

impl MFuseNet {
    /// The reduction the network runs at for `problem` (1: full size).
    fn pyramid_factor(&self, problem: &Problem) -> usize {
        pyramid_factor_for(
            (problem.reference.width, problem.reference.height),
            problem.num_disparities,
            self.config.max_direct_disparities,
            self.config.max_direct_voxels,
        )
    }

    /// [`Method::run`] with the convolutions' precision set.
    fn run_in_precision(&self, problem: &Problem, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        problem.validate()?;
        self.validate_config()?;
        let factor = self.pyramid_factor(problem);
        if factor == 1 {
            let estimate = self.network_estimate(problem, progress)?;
            return self.finish(problem, estimate, Stage::Last);
        }
        // Coarse to fine (`mfusenet::pyramid`): the network on the reduced set, whose range fits
        // its training, then the band around its answer at full size.
        let coarse = downsampled(problem, factor);
        let estimate = self.network_estimate(&coarse, &|f| progress(0.5 * f))?;
        let coarse_out = self.finish(&coarse, estimate, Stage::Coarse)?;
        let (neighbours, loaded) = self.post_views(problem)?;
        // The full-size costs as one sum, made a neighbour at a time: the post-processing reads
        // only the sum, and four full-size byte volumes would hold twice its memory.
        let sides = self.sides(problem, &neighbours, loaded);
        let (costs, first) = summed_input_volume_below(
            problem,
            &sides,
            self.config.side_rule,
            self.config.input.unwrap_or(loaded.input),
            0,
        )?;
        progress(0.9);
        let band = Band {
            factor,
            half_width: factor as f64,
            fit: self.config.subpixel_fit,
            locking: None,
        };
        let disparity = band_minimum(
            &coarse_out,
            &costs,
            first,
            (problem.reference.width, problem.reference.height),
            band,
        );
        self.finish(
            problem,
            NetworkEstimate {
                disparity,
                costs,
                first,
            },
            Stage::Last,
        )
    }

    /// [`Method::details`] but the precision.
    fn details_of(&self, problem: &Problem) -> serde_json::Value {
        let factor = self.pyramid_factor(problem);
        // The level's size and range, without making it.
        let (width, height) = (
            problem.reference.width.div_ceil(factor),
            problem.reference.height.div_ceil(factor),
        );
        let range = reduced_range(problem, factor);
        let Ok(loaded) = self.network_for(problem) else {
            return serde_json::Value::Null;
        };
        let (min_disparity, num_disparities) =
            widened_range(range, self.config.min_network_disparities).unwrap_or(range);
        let room_below = self.config.room_below.unwrap_or(loaded.context_below);
        // Each input of the nearest group and the views it was made from, where one has several.
        let post = self.post_views(problem).ok();
        let side_inputs = post
            .as_ref()
            .filter(|(_, loaded)| self.side_inputs(loaded))
            .map(|(nearest, _)| sides_of(problem, nearest))
            .filter(|sides| sides.iter().any(|side| side.len() > 1))
            .map(|sides| {
                sides
                    .iter()
                    .map(|side| side.iter().map(|n| n.role.as_str()).collect::<Vec<_>>().join(" + "))
                    .collect::<Vec<_>>()
            });
        // The views the thin-part recovery reads (`thin_parts_every_view`), where they are more
        // than the network's nearest group.
        let thin_parts_views = (self.config.thin_parts.is_some() && self.config.thin_parts_every_view && !self.stereo)
            .then(|| post.as_ref().map_or(0, |(used, _)| used.len()))
            .filter(|used| *used < problem.neighbours.len())
            .map(|_| problem.neighbours.iter().map(|n| n.role.as_str()).collect::<Vec<_>>());
        if let Some(serde_json::Value::Object(plan)) = self.plan_details(problem) {
            let mut out = serde_json::json!({
                "network": "fused",
                "scale": format!("1/{factor}"),
                "network_width": width,
                "network_height": height,
                "full_size_band_px": (factor > 1).then_some(factor),
                "side_inputs": side_inputs,
                "side_rule": side_inputs.is_some().then_some(self.config.side_rule),
                "thin_parts_views": thin_parts_views,
            });
            if let serde_json::Value::Object(map) = &mut out {
                map.extend(plan);
            }
            return out;
        }
        serde_json::json!({
            "network": match loaded.views { 0 => "view-count-agnostic", 1 => "stereo", 2 => "three-view", _ => "five-view" },
            "architecture": loaded.net.architecture.name(),
            "scale": format!("1/{factor}"),
            "network_width": width,
            "network_height": height,
            "network_min_disparity": i64::from(min_disparity) - room_below as i64,
            "network_num_disparities": num_disparities + room_below,
            "full_size_band_px": (factor > 1).then_some(factor),
            // The neighbours the network took, in its input order (a fixed network's nearest
            // group; with side inputs each is its side's first view, `side_inputs` lists the rest).
            "views": self
                .network_neighbours(problem, loaded)
                .map(|used| used.iter().map(|n| n.role.clone()).collect::<Vec<_>>())
                .unwrap_or_default(),
            "side_inputs": side_inputs,
            "side_rule": side_inputs.is_some().then_some(self.config.side_rule),
            "thin_parts_views": thin_parts_views,
        })
    }
}

/// What the network gives before the post-processing: the disparity (in the problem's range)
/// with the network's confidence, and the sum of the input volumes it was read from.
struct NetworkEstimate {
    disparity: DisparityImage,
    costs: CostVolume<u16>,
    /// The disparity of the volumes' first slice.
    first: i64,
}

impl NetworkEstimate {
    /// The network's `(disparity, confidence)` over `problem` (volumes from `first`, `origin`
    /// the shift from the volumes' slices to disparities) clamped back into the `requested`
    /// range `(min, count)` when it was widened.
    fn new(
        problem: &Problem,
        requested: (i32, usize),
        (data, confidence): (Vec<f32>, Vec<f32>),
        origin: f32,
        costs: CostVolume<u16>,
        first: i64,
    ) -> Self {
        let (low, high) = (requested.0 as f32, requested.0 as f32 + (requested.1 - 1) as f32);
        Self {
            disparity: DisparityImage {
                width: problem.reference.width,
                height: problem.reference.height,
                data: data.into_iter().map(|d| (d + origin).clamp(low, high)).collect(),
                confidence: Some(confidence),
            },
            costs,
            first,
        }
    }
}

/// [`summed`], or the error of a set without volumes of one shape.
fn summed_or_error(volumes: &[CostVolume<u8>]) -> Result<CostVolume<u16>, FuseError> {
    summed(volumes).ok_or(FuseError::Config {
        field: "neighbours",
        value: volumes.len().to_string(),
        reason: "the network's inputs need at least one neighbour volume, all of one shape",
    })
}

/// [`MFuseNetConfig::precision`]'s default.
fn auto_precision() -> Precision {
    Precision::Auto
}

/// [`MFuseNetConfig::side_inputs`]' default.
fn yes() -> bool {
    true
}

/// [`MFuseNetConfig::photometric`]'s default (on; `null` in the JSON turns it off).
fn default_photometric() -> Option<crate::photometric::Photometric> {
    Some(crate::photometric::Photometric::default())
}

/// [`MFuseNetConfig::farther_vote`]'s default.
fn default_farther_vote() -> f32 {
    DEFAULT_FARTHER_VOTE
}

/// [`MFuseNetConfig::side_rule`]'s default.
fn near_capped() -> SideRule {
    SideRule::NearCapped
}

impl MFuseNet {
    /// The networks for a set that more than one network covers (`every_view`, shipped
    /// weights): the groups, each with its loaded network, and the neighbours no group takes.
    /// `None`: one network, [`Self::network_for`]'s.
    fn view_plan<'p>(&self, problem: &'p Problem) -> Option<ViewPlan<'p, '_>> {
        if self.stereo
            || !self.config.every_view.unwrap_or(true)
            || (self.config.weights.is_some() && !self.line_cross())
        {
            return None;
        }
        let available: Vec<usize> = self.networks.iter().map(|n| n.views).collect();
        // (A file trained on lines of five takes no filled cross.)
        let fill = self.config.fill_cross && !self.networks.iter().any(|n| n.line);
        let (groups, rest) = view_groups(problem, &available, self.line_cross(), fill);
        if groups.len() < 2 && !self.line_cross() && !groups.iter().any(ViewGroup::filled) {
            return None;
        }
        let groups = groups
            .into_iter()
            .filter_map(|g| {
                let loaded = self.network_of(g.views)?;
                Some((g, loaded))
            })
            .collect();
        Some((groups, rest))
    }

    /// What the run says about its networks: each group's variant and views.
    fn plan_details(&self, problem: &Problem) -> Option<serde_json::Value> {
        let (groups, rest) = self.view_plan(problem)?;
        let name = |views: usize| match views {
            1 => "stereo",
            2 => "three-view",
            _ => "five-view",
        };
        Some(serde_json::json!({
            "networks": groups
                .iter()
                .map(|(g, loaded)| format!(
                    "{}{} [{}]",
                    name(g.views),
                    match loaded.net.architecture {
                        Architecture::Paper => String::new(),
                        other => format!(" ({})", other.name()),
                    },
                    g.slots.iter().map(|&s| g.neighbours[s].role.as_str()).collect::<Vec<_>>().join(", ")
                ))
                .collect::<Vec<_>>(),
            "unused": rest.iter().map(|n| n.role.clone()).collect::<Vec<_>>(),
        }))
    }

    /// The views the post-processing reads and the network they are the inputs of: a filled
    /// cross's views (each once) and the five-view network, else [`Self::network_for`]'s
    /// network and its nearest group ([`Self::nearest_neighbours`]).
    fn post_views<'p>(&self, problem: &'p Problem) -> Result<(Vec<&'p Neighbour>, &Loaded), FuseError> {
        let filled = self
            .view_plan(problem)
            .and_then(|(groups, _)| groups.into_iter().next())
            .filter(|(group, _)| group.filled());
        if let Some((group, loaded)) = filled {
            return Ok((group.neighbours, loaded));
        }
        let loaded = self.network_for(problem)?;
        Ok((self.nearest_neighbours(problem, loaded.views)?, loaded))
    }

    /// The neighbours `loaded`'s network takes, in its order: a fixed network's
    /// [`ordered_neighbours`]; the view-count-agnostic network's nearest group, then with
    /// `every_view` the set's other views ([`pooled_neighbours`]; by default when the file was
    /// trained on them).
    fn network_neighbours<'p>(&self, problem: &'p Problem, loaded: &Loaded) -> Result<Vec<&'p Neighbour>, FuseError> {
        if loaded.views == 0 {
            pooled_neighbours(problem, self.config.every_view.unwrap_or(loaded.far_views))
        } else {
            ordered_neighbours(problem, loaded.views)
        }
    }

    /// The nearest group a network of `views` inputs answers from ([`ordered_neighbours`]); with
    /// `line_cross`, a line of five's near pair for the five-view network (its far pair fills
    /// the network's top and bottom inputs, and the post-processing reads the near pair's costs,
    /// as for the three-view network on the line).
    fn nearest_neighbours<'p>(&self, problem: &'p Problem, views: usize) -> Result<Vec<&'p Neighbour>, FuseError> {
        match ordered_neighbours(problem, views) {
            Err(_) if self.line_cross() && views == 4 => ordered_neighbours(problem, 2),
            found => found,
        }
    }

    /// The configuration's checks, before minutes of work.
    fn validate_config(&self) -> Result<(), FuseError> {
        if !(self.config.refine_reach >= 0.0 && self.config.refine_reach.is_finite()) {
            return Err(FuseError::Config {
                field: "refine_reach",
                value: self.config.refine_reach.to_string(),
                reason: "a distance in pixels, 0 or more",
            });
        }
        if !(self.config.farther_vote > 0.0 && self.config.farther_vote.is_finite()) {
            return Err(FuseError::Config {
                field: "farther_vote",
                value: self.config.farther_vote.to_string(),
                reason: "a farther view's vote relative to a nearest one's, over 0 (1 = every view alike)",
            });
        }
        if !(0.0..=1.0).contains(&self.config.locking_strength) {
            return Err(FuseError::Config {
                field: "locking_strength",
                value: self.config.locking_strength.to_string(),
                reason: "a share of the locking correction from 0 to 1",
            });
        }
        if let Some(filter) = &self.config.weighted_median {
            filter.validate()?;
        }
        if let Some(farther) = &self.config.farther_median {
            farther.validate()?;
        }
        if !(0.0..=1.0).contains(&self.config.disagreeing_vote) {
            return Err(FuseError::Config {
                field: "disagreeing_vote",
                value: self.config.disagreeing_vote.to_string(),
                reason: "a vote weight from 0 to 1",
            });
        }
        if self.config.min_network_disparities > MAX_MIN_NETWORK_DISPARITIES {
            return Err(FuseError::Config {
                field: "min_network_disparities",
                value: self.config.min_network_disparities.to_string(),
                reason: "at most 64 disparities (a narrow range is widened to this many)",
            });
        }
        if let Some(room_below) = self.config.room_below
            && room_below > weights::MAX_CONTEXT_BELOW
        {
            return Err(FuseError::Config {
                field: "room_below",
                value: room_below.to_string(),
                reason: "at most 16 disparities of context below the range",
            });
        }
        Ok(())
    }

    /// The network over the problem's whole range at the problem's size.
    fn network_estimate(&self, problem: &Problem, progress: Progress<'_>) -> Result<NetworkEstimate, FuseError> {
        let requested = (problem.min_disparity, problem.num_disparities);
        let widened;
        let problem = match widened_range(requested, self.config.min_network_disparities) {
            Some((min_disparity, num_disparities)) => {
                widened = Problem {
                    min_disparity,
                    num_disparities,
                    ..problem.clone()
                };
                &widened
            }
            None => problem,
        };
        if let Some(plan) = self.view_plan(problem) {
            return self.fused_estimate(problem, requested, plan, progress);
        }
        let loaded = self.network_for(problem)?;
        let net = &loaded.net;
        let neighbours = self.network_neighbours(problem, loaded)?;
        // The nearest group's volumes come first; the post-processing reads only theirs.
        let nearest = self.nearest_neighbours(problem, net.views)?.len();
        // Cost volumes: about a tenth of the work; the network the rest.
        let (volumes, first, origin) = self.input_volumes(problem, &neighbours, loaded, net.sharp)?;
        progress(0.1);
        let (data, confidence) = infer_with_confidence(
            net,
            &volumes,
            self.config.tile_budget_mib << 20,
            Estimate {
                flips: self.config.flips,
                ..self.estimate(loaded, problem, first)
            },
            &|f| progress(0.1 + 0.9 * f),
        )?;
        // The post-processing reads the nearest group's costs only summed (farther views' costs
        // summed in raised AvgErr on lines of five: docs/experiments.md).
        let costs = summed_or_error(&volumes[..nearest.min(volumes.len())])?;
        drop(volumes);
        Ok(NetworkEstimate::new(
            problem,
            requested,
            (data, confidence),
            origin,
            costs,
            first,
        ))
    }

    /// The input volumes of `neighbours` as `loaded`'s network asks for them (its input spec,
    /// its context below the range), the disparity of their first slice, and the shift from
    /// the volumes' slices to disparities. With `sharp`, the same neighbours' sharp volumes
    /// follow them (`loaded`'s sharp spec), as a sharp network takes them.
    fn input_volumes(
        &self,
        problem: &Problem,
        neighbours: &[&Neighbour],
        loaded: &Loaded,
        sharp: bool,
    ) -> Result<(Vec<CostVolume<u8>>, i64, f32), FuseError> {
        let room_below = self.config.room_below.unwrap_or(loaded.context_below);
        let sides = self.sides(problem, neighbours, loaded);
        let (mut volumes, first) = input_volumes_of_sides_below(
            problem,
            &sides,
            self.config.side_rule,
            self.config.input.unwrap_or(loaded.input),
            room_below,
            &|| {},
        )?;
        if sharp {
            let (sharp, _) =
                sharp_volumes_of_sides_below(problem, &sides, self.config.side_rule, loaded.sharp, room_below)?;
            volumes.extend(sharp);
        }
        let origin = first as f32 - volumes.first().map_or(0, |v| v.min_disparity) as f32;
        Ok((volumes, first, origin))
    }

    /// Whether `loaded`'s inputs are made from whole sides: `side_inputs`, a fixed network, not
    /// the stereo method (one neighbour by definition).
    fn side_inputs(&self, loaded: &Loaded) -> bool {
        self.config.side_inputs && loaded.views > 0 && !self.stereo && !self.line_cross()
    }

    /// The views each input of `loaded`'s network is made from: with [`Self::side_inputs`],
    /// each of `neighbours` with the set's views farther along its ray
    /// ([`sides_of`]); else each alone (a view-count-agnostic network takes the far views as
    /// inputs of their own).
    fn sides<'p>(
        &self,
        problem: &'p Problem,
        neighbours: &[&'p Neighbour],
        loaded: &Loaded,
    ) -> Vec<Vec<&'p Neighbour>> {
        if self.side_inputs(loaded) {
            sides_of(problem, neighbours)
        } else {
            neighbours.iter().map(|n| vec![*n]).collect()
        }
    }

    /// How the estimate is read for `loaded`'s network over `problem`'s range, whose volumes
    /// start at disparity `first` (test-time flips off).
    fn estimate(&self, loaded: &Loaded, problem: &Problem, first: i64) -> Estimate {
        Estimate {
            window: self.config.window,
            refine: self.config.refine.unwrap_or(loaded.refine),
            refine_reach: self.config.refine_reach,
            fit: self.config.subpixel_fit,
            locking: self
                .config
                .locking
                .or(loaded.locking)
                .map(|curve| curve.damped(self.config.locking_strength)),
            context_below: usize::try_from(i64::from(problem.min_disparity) - first).unwrap_or(0),
            flips: false,
        }
    }

    /// [`Self::network_estimate`] with several networks (`plan`, [`Self::view_plan`]): every
    /// group's volumes, the networks' logits fused ([`infer_fused`]). How the estimate is read
    /// (context, refinement, locking) follows the first group's network, the nearest
    /// baseline's.
    fn fused_estimate(
        &self,
        problem: &Problem,
        requested: (i32, usize),
        (groups, _unused): ViewPlan<'_, '_>,
        progress: Progress<'_>,
    ) -> Result<NetworkEstimate, FuseError> {
        let Some((_, primary)) = groups.first() else {
            return Err(FuseError::Config {
                field: "neighbours",
                value: String::new(),
                reason: "no network takes any of the set's neighbours",
            });
        };
        let mut neighbours: Vec<&Neighbour> = Vec::new();
        let mut members = Vec::new();
        let mut starts = Vec::new();
        for (group, _) in &groups {
            starts.push(neighbours.len());
            neighbours.extend(group.neighbours.iter().copied());
        }
        // Every group's sharp volumes after every group's own, when a network takes them.
        let sharp = groups.iter().any(|(_, loaded)| loaded.net.sharp);
        let (volumes, first, origin) = self.input_volumes(problem, &neighbours, primary, sharp)?;
        let total = neighbours.len();
        let size = (problem.reference.width, problem.reference.height);
        let axis = volumes.first().map_or((0, 0), |v| (v.min_disparity, v.num_disparities));
        for (g, ((group, loaded), start)) in groups.iter().zip(&starts).enumerate() {
            // The nearest group votes everywhere; a farther one where its views see the
            // disparity (its network answers from mirrored costs elsewhere).
            let reach = (g > 0).then(|| {
                group
                    .slots
                    .iter()
                    .map(|&s| {
                        let n = group.neighbours[s];
                        ValidDisparities::new(n.offset, size, axis, n.baseline_ratio)
                    })
                    .collect()
            });
            // A group's baseline multiple: its views' farthest offset, in baselines.
            let multiple = group
                .neighbours
                .iter()
                .map(|n| n.offset[0].unsigned_abs().max(n.offset[1].unsigned_abs()))
                .max()
                .unwrap_or(1)
                .max(1);
            // Each input's volume: its slot's view (a filled cross repeats one).
            let own: Vec<usize> = group.slots.iter().map(|s| start + s).collect();
            let mut inputs = own.clone();
            if loaded.net.sharp {
                inputs.extend(own.iter().map(|i| total + i));
            }
            members.push(Member {
                net: &loaded.net,
                inputs,
                reach,
                // A filled cross votes as the views it has, not as its network's inputs.
                vote: self
                    .config
                    .farther_vote
                    .powi(i32::try_from(multiple - 1).unwrap_or(i32::MAX))
                    * group.neighbours.len() as f32
                    / group.slots.len().max(1) as f32,
            });
        }
        // The estimate is refined and filtered with the nearest groups' costs: the farther
        // views' costs, summed in or taken side by side, raised AvgErr on the toy line of five
        // and on Middlebury's lines (docs/experiments.md).
        // The nearest groups: the first and those after it at its baseline (an L's two views,
        // each its own group, read together).
        let nearest_reach = neighbours.first().map_or(1, |n| n.reach());
        // (A line of five's single group: its near pair, which leads it.)
        let nearest = neighbours.iter().take_while(|n| n.reach() == nearest_reach).count();
        let costs = summed_or_error(&volumes[..nearest])?;
        progress(0.1);
        let (data, confidence) = infer_fused(
            &members,
            &volumes,
            &costs,
            self.config.tile_budget_mib << 20,
            self.estimate(primary, problem, first),
            &|f| progress(0.1 + 0.9 * f),
        )?;
        drop(volumes);
        Ok(NetworkEstimate::new(
            problem,
            requested,
            (data, confidence),
            origin,
            costs,
            first,
        ))
    }

    /// The post-processing: the median, the weighted median with the votes of the input costs,
    /// and the confidence from the network's margin, the inputs' peak and what the filters kept.
    fn finish(&self, problem: &Problem, estimate: NetworkEstimate, stage: Stage) -> Result<DisparityImage, FuseError> {
        let NetworkEstimate {
            disparity,
            costs,
            first,
        } = estimate;
        let disparity = if self.config.median {
            median3x3(&disparity)
        } else {
            disparity
        };
        let network = disparity.data.clone();
        let mut out = match &self.config.weighted_median {
            Some(filter) => {
                let votes = (self.config.disagreeing_vote < 1.0)
                    .then(|| cost_agreement(&disparity, &costs, first, self.config.disagreeing_vote));
                let mut out = weighted_median_with_votes(&disparity, &problem.reference, filter, votes.as_deref())?;
                if let Some(farther) = &self.config.farther_median {
                    farther_by_wider_median(&disparity, &problem.reference, farther, votes.as_deref(), &mut out)?;
                }
                out
            }
            None => disparity,
        };
        let data = data_support(&out, &costs, first);
        if let Some(confidence) = &mut out.confidence {
            // The network's margin and the inputs' own peak, where the filters kept the network's
            // answer (within 1 px): docs/experiments.md, "Confidence".
            for ((c, support), (final_d, network_d)) in
                confidence.iter_mut().zip(&data).zip(out.data.iter().zip(&network))
            {
                let kept = 1.0 - (final_d - network_d).abs().min(1.0);
                *c = 0.5 * (*c + support) * if kept.is_finite() { kept } else { 0.0 };
            }
        }
        if stage == Stage::Last
            && (self.config.block_subpixel.is_some()
                || self.config.thin_parts.is_some()
                || self.config.border_check.is_some()
                || self.config.photometric.is_some())
        {
            // The sub-pixel step reads the views the network answered from (the nearest group);
            // the thin-part step every view (`thin_parts_every_view`).
            let (used, _) = self.post_views(problem)?;
            let nearest;
            let costs_of = if used.len() == problem.neighbours.len() {
                problem
            } else {
                nearest = Problem {
                    reference: problem.reference.clone(),
                    neighbours: used.into_iter().cloned().collect(),
                    ..*problem
                };
                &nearest
            };
            if let Some(config) = &self.config.border_check {
                recheck_borders(costs_of, &mut out, config)?;
            }
            if let Some(config) = &self.config.block_subpixel {
                refine_with_block_costs(costs_of, &mut out, config)?;
            }
            if let Some(config) = &self.config.thin_parts {
                // The stereo method's one view only: a stereo baseline that read the set's other
                // views would change with views it does not take.
                let views = if self.config.thin_parts_every_view && !self.stereo {
                    problem
                } else {
                    costs_of
                };
                recover_thin_parts(views, &mut out, config)?;
            }
            if let Some(config) = &self.config.photometric {
                // Every view of the set (a grid's diagonals too); the stereo method's one.
                let views = if self.stereo { costs_of } else { problem };
                crate::photometric::refine_photometric(views, &mut out, config)?;
            }
        }
        scale_by_local_consistency(&mut out);
        Ok(out)
    }
}

/// How well the summed input costs single out each pixel's final disparity:
/// [`crate::wta::peak_confidence`] of the sum over the neighbours at the nearest slice.
fn data_support(disparity: &DisparityImage, costs: &CostVolume<u16>, first: i64) -> Vec<f32> {
    let nd = costs.num_disparities;
    let w = disparity.width;
    disparity
        .data
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            if !d.is_finite() || nd == 0 {
                return 0.0;
            }
            let (x, y) = (i % w, i / w);
            let at = (f64::from(d) - first as f64).round().clamp(0.0, (nd - 1) as f64) as usize;
            crate::wta::peak_confidence(costs.costs(x, y), at)
        })
        .collect()
}

/// Each pixel's vote for the weighted median: 1 where a local minimum of the summed input
/// costs lies within 1 px of its disparity (the network and the data agree), else
/// `disagreeing`. `first` is the disparity of the volumes' first slice.
fn cost_agreement(disparity: &DisparityImage, costs: &CostVolume<u16>, first: i64, disagreeing: f32) -> Vec<f32> {
    let nd = costs.num_disparities;
    let w = disparity.width;
    disparity
        .data
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            let (x, y) = (i % w, i / w);
            let cost = |k: usize| costs.costs(x, y)[k];
            let at = f64::from(d) - first as f64;
            // Slices 1..nd-1 (a minimum needs both neighbours); negative `at` saturates to 0.
            let lo = ((at - 1.0).ceil() as usize).max(1);
            let hi = ((at + 1.0).floor() as usize).min(nd.saturating_sub(2));
            let agrees = d.is_finite() && (lo..=hi).any(|k| cost(k) <= cost(k - 1) && cost(k) <= cost(k + 1));
            if agrees { 1.0 } else { disagreeing }
        })
        .collect()
}

/// The fewest disparities the networks see. A narrower search range gives the network a volume
/// shape it was not trained on (the shipped weights saw 32 and more), so the costs are computed
/// over this many around the requested range, and the result clamped back into it. 32 was
/// needed before the networks had context below their range (the demo's 16 disparities: Bad1
/// 16 % against 2 % over 32); with it, 16 is as accurate as 32 or better for every shipped
/// network and runs the network on 24 slices instead of 40 where the range is 16 (the lite
/// five-view file's 8 of context included: the demo's capture 1.55 × faster;
/// docs/experiments.md, "The networks on 16 disparities").
pub const MIN_NETWORK_DISPARITIES: usize = 16;

/// The largest [`MFuseNetConfig::min_network_disparities`].
pub const MAX_MIN_NETWORK_DISPARITIES: usize = 64;

/// The range `(min, count)` searched for a requested `(min, count)` narrower than
/// [`MIN_NETWORK_DISPARITIES`]: widened evenly on both sides (signed: a range near 0 reaches
/// under it); `None` when wide enough.
pub fn widened_range((min_disparity, num_disparities): (i32, usize), fewest: usize) -> Option<(i32, usize)> {
    let extra = fewest.checked_sub(num_disparities).filter(|e| *e > 0)?;
    let below = i32::try_from(extra / 2).unwrap_or(0);
    Some((min_disparity - below, fewest))
}

fn min_network_disparities() -> usize {
    MIN_NETWORK_DISPARITIES
}

fn max_direct_voxels() -> usize {
    DEFAULT_MAX_DIRECT_VOXELS
}

fn build(
    name: &'static str,
    stereo: bool,
    overrides: Option<&serde_json::Value>,
) -> Result<Box<dyn Method>, FuseError> {
    let config = apply_overrides(MFuseNetConfig::default(), overrides)?;
    Ok(Box::new(MFuseNet::new(name, config, stereo)?))
}

/// Registry entries.
pub const ENTRIES: &[MethodEntry] = &[
    MethodEntry {
        name: "mfusenet-stereo",
        summary: "MFuseNet on one cost volume (the right view's, SGM-aggregated census): the paper's learned stereo baseline",
        family: Family::MFuseNet,
        build: |o| build("mfusenet-stereo", true, o),
    },
    MethodEntry {
        name: "mfusenet",
        summary: "MFuseNet: the per-neighbour SGM cost volumes fused by the trained 3D CNN (the five-view network on each cross of the set, a cross missing arms filled by the opposite views, the three-view one on each pair, the stereo one on each odd view)",
        family: Family::MFuseNet,
        build: |o| build("mfusenet", false, o),
    },
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::Image;

    /// A fronto-parallel textured plane at integer disparity `d` seen by the neighbours at
    /// `offsets`, searched over `min_disparity .. min_disparity + 32`.
    fn plane(offsets: &[[i32; 2]], d: i32, min_disparity: i32) -> Problem {
        plane_sized(offsets, d, (min_disparity, 32), (96, 64))
    }

    /// [`plane`] over `(min_disparity, num_disparities)` in a `(w, h)` image.
    fn plane_sized(offsets: &[[i32; 2]], d: i32, range: (i32, usize), (w, h): (usize, usize)) -> Problem {
        // Blobs of a few pixels (hashed 3×3 cells, smoothed by the bilinear lookup): texture the
        // networks' census costs see at every scale they were trained on.
        let cell = |x: i64, y: i64| {
            let v = (x.wrapping_mul(73_856_093) ^ y.wrapping_mul(19_349_663)).rem_euclid(1 << 20);
            (((v * 2_654_435_761) >> 7) & 0xFF) as f32
        };
        let texture = |x: i64, y: i64| {
            let (cx, cy) = (x.div_euclid(3), y.div_euclid(3));
            let (fx, fy) = (x.rem_euclid(3) as f32 / 3.0, y.rem_euclid(3) as f32 / 3.0);
            let top = cell(cx, cy) * (1.0 - fx) + cell(cx + 1, cy) * fx;
            let bottom = cell(cx, cy + 1) * (1.0 - fx) + cell(cx + 1, cy + 1) * fx;
            (top * (1.0 - fy) + bottom * fy) as u8
        };
        // The neighbour at offset o sees the reference's pixel p at p − o·d.
        let view = |o: [i32; 2]| {
            let (sx, sy) = (i64::from(o[0] * d), i64::from(o[1] * d));
            let data = (0..h as i64)
                .flat_map(|y| (0..w as i64).map(move |x| texture(x + sx, y + sy)))
                .collect();
            Image::gray(w, h, data).unwrap_or_else(|e| panic!("{e}"))
        };
        Problem {
            reference: view([0, 0]),
            neighbours: offsets
                .iter()
                .map(|&offset| Neighbour {
                    role: match offset {
                        [-1, 0] => "left",
                        [1, 0] => "right",
                        [-2, 0] => "left2",
                        [2, 0] => "right2",
                        [0, -1] => "top",
                        _ => "bottom",
                    }
                    .to_owned(),
                    image: view(offset),
                    offset,
                    baseline_ratio: 1.0,
                })
                .collect(),
            min_disparity: range.0,
            num_disparities: range.1,
        }
    }

    /// `|d − truth|` of `out`'s pixels at least `margin` columns from either border.
    fn interior_errors(out: &DisparityImage, margin: usize, truth: f32) -> Vec<f32> {
        let w = out.width;
        out.data
            .iter()
            .enumerate()
            .filter(|(i, _)| (margin..w.saturating_sub(margin)).contains(&(i % w)))
            .map(|(_, d)| (d - truth).abs())
            .collect()
    }

    #[test]
    fn a_wide_range_goes_coarse_to_fine_and_finds_a_plane_far_up_it() {
        // 0..96 → the network at 1/3 size over 0..33, then ± 3 px at full size (an image this
        // small runs at full size within the default voxel budget: no budget here).
        let offsets = [[-1, 0], [1, 0]];
        let problem = plane_sized(&offsets, 61, (0, 96), (240, 120));
        let no_budget = serde_json::json!({"max_direct_voxels": 0});
        let method = crate::methods::build("mfusenet", Some(&no_budget)).unwrap_or_else(|e| panic!("{e}"));
        // Within the default budget the same set runs at full size.
        let default = crate::methods::build("mfusenet", None).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(default.details(&problem)["scale"], "1/1");
        let details = method.details(&problem);
        assert_eq!(details["scale"], "1/3", "{details}");
        assert_eq!(details["network_width"], 80, "{details}");
        assert_eq!(
            details["network_num_disparities"].as_u64().map(|n| n >= 32),
            Some(true),
            "{details}"
        );
        let out = method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        // The pixels both neighbours see (61 px from either border).
        let errors = interior_errors(&out, 61, 61.0);
        assert!(errors.len() > 10_000, "{} pixels", errors.len());
        let mean = errors.iter().sum::<f32>() / errors.len() as f32;
        let bad = errors.iter().filter(|e| **e > 1.0).count();
        assert!(
            mean < 0.25 && bad * 100 < errors.len(),
            "AvgErr {mean:.3} px, {bad} of {} pixels off by > 1 px",
            errors.len()
        );
        // Within the direct limit, the network runs at full size and says so.
        let narrow = plane(&offsets, 10, 0);
        assert_eq!(default.details(&narrow)["scale"], "1/1");
        // An L over the same range: the filled cross at 1/3 size, then the band at full size
        // over both of its views' costs (60 px from the borders each view shifts).
        let l = plane_sized(&[[-1, 0], [0, -1]], 30, (0, 96), (180, 150));
        let details = method.details(&l);
        assert_eq!(
            (&details["scale"], &details["networks"]),
            (
                &serde_json::json!("1/3"),
                &serde_json::json!(["five-view (lite) [left, left, top, top]"])
            ),
            "{details}"
        );
        let out = method.run(&l, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        let (w, h) = (out.width, out.height);
        let errors: Vec<f32> = (60..h - 30)
            .flat_map(|y| (60..w - 30).map(move |x| (x, y)))
            .map(|(x, y)| (out.data[y * w + x] - 30.0).abs())
            .collect();
        let mean = errors.iter().sum::<f32>() / errors.len() as f32;
        assert!(mean < 0.25, "the L coarse to fine: AvgErr {mean:.3} px");
    }

    #[test]
    fn bfloat16_and_integer_products_find_the_plane_as_f32_does_and_the_details_say_which_ran() {
        let problem = plane_sized(&[[-1, 0], [1, 0], [0, -1], [0, 1]], 7, (0, 32), (144, 72));
        let run = |precision: &str| {
            let config = serde_json::json!({ "precision": precision });
            let method = crate::methods::build("mfusenet", Some(&config)).unwrap_or_else(|e| panic!("{e}"));
            let out = method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
            (method.details(&problem)["precision"].clone(), out)
        };
        let (f32_ran, exact) = run("f32");
        assert_eq!(f32_ran, "f32");
        let (bf16_ran, rounded) = run("bf16");
        let bf16_if = |yes: bool| if yes { "bf16" } else { "f32" };
        let host = bf16_if(crate::nn::bf16_kernel::available());
        assert_eq!(bf16_ran, host, "bfloat16 runs where the host has it, f32 elsewhere");
        // The default takes bfloat16 only where the host prefers it, and says so.
        let (auto_ran, auto) = run("auto");
        let preferred = bf16_if(crate::nn::bf16_kernel::preferred());
        assert_eq!(auto_ran, preferred, "auto: bfloat16 where this host prefers it");
        // On Intel's matrix unit, the 7³ layers in bfloat16 beside the others in f32, and the
        // details say so; elsewhere auto runs one precision throughout.
        let on_amx = preferred == "f32" && crate::nn::amx_kernel::available();
        let auto_details = crate::methods::build("mfusenet", Some(&serde_json::json!({ "precision": "auto" })))
            .unwrap_or_else(|e| panic!("{e}"))
            .details(&problem);
        let seven = &auto_details["precision_7x7x7"];
        if on_amx {
            assert_eq!(seven, "bf16", "{auto_details}");
            let worst = exact
                .data
                .iter()
                .zip(&auto.data)
                .map(|(x, y)| (x - y).abs())
                .fold(0f32, f32::max);
            assert!(
                worst < 0.5,
                "a pixel moved by {worst} px with the 7³ layers in bfloat16"
            );
        } else {
            assert!(seven.is_null(), "{auto_details}");
            assert_eq!(
                auto.data,
                if preferred == "bf16" { &rounded } else { &exact }.data,
                "auto gives what the precision it chose gives"
            );
        }
        let default = crate::methods::build("mfusenet", None).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(default.details(&problem)["precision"], preferred);
        let mean = |out: &DisparityImage| {
            let errors = interior_errors(out, 8, 7.0);
            errors.iter().sum::<f32>() / errors.len() as f32
        };
        let (a, b) = (mean(&exact), mean(&rounded));
        assert!(
            a < 0.25 && b < 0.25 && (a - b).abs() < 0.02,
            "AvgErr f32 {a:.4}, bf16 {b:.4} px"
        );
        let worst = exact
            .data
            .iter()
            .zip(&rounded.data)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        assert!(worst < 0.5, "a pixel moved by {worst} px in bfloat16");
        // 16-bit integer products: the same plane, and the details say so where they ran.
        let (int16_ran, quantised) = run("int16");
        let host = if crate::nn::int16_kernel::available() {
            "int16"
        } else {
            "f32"
        };
        assert_eq!(
            int16_ran, host,
            "16-bit integers run where the host has AVX2, f32 elsewhere"
        );
        let c = mean(&quantised);
        assert!(c < 0.25 && (a - c).abs() < 0.02, "AvgErr f32 {a:.4}, int16 {c:.4} px");
        let worst = exact
            .data
            .iter()
            .zip(&quantised.data)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        assert!(worst < 0.5, "a pixel moved by {worst} px in 16-bit integers");
        // Unknown precisions are refused by name.
        let bad = serde_json::json!({ "precision": "fp8" });
        assert!(crate::methods::build("mfusenet", Some(&bad)).is_err());
    }

    #[test]
    fn a_cross_missing_arms_is_filled_and_the_odd_views_run_the_stereo_network() {
        let method = crate::methods::build("mfusenet", None).unwrap_or_else(|e| panic!("{e}"));
        let unfilled = serde_json::json!({ "fill_cross": false });
        let unfilled = crate::methods::build("mfusenet", Some(&unfilled)).unwrap_or_else(|e| panic!("{e}"));
        let plane = |offsets: &[[i32; 2]]| plane_sized(offsets, 6, (0, 32), (128, 96));
        // By default an L and a T run the five-view network, each missing input filled by the
        // opposite view; the post-processing reads the views it took.
        let l = method.details(&plane(&[[-1, 0], [0, -1]]));
        assert_eq!(l["network"], "fused", "{l}");
        assert_eq!(
            l["networks"],
            serde_json::json!(["five-view (lite) [left, left, top, top]"]),
            "{l}"
        );
        let t = method.details(&plane(&[[-1, 0], [1, 0], [0, -1]]));
        assert_eq!(
            t["networks"],
            serde_json::json!(["five-view (lite) [left, right, top, top]"]),
            "{t}"
        );
        // Without the filling: each odd view alone; a cross missing an arm: the pair and the
        // odd view.
        let l = unfilled.details(&plane(&[[-1, 0], [0, -1]]));
        assert_eq!(
            l["networks"],
            serde_json::json!(["stereo [left]", "stereo [top]"]),
            "{l}"
        );
        let t = unfilled.details(&plane(&[[-1, 0], [1, 0], [0, -1]]));
        assert_eq!(
            t["networks"],
            serde_json::json!(["three-view [left, right]", "stereo [top]"]),
            "{t}"
        );
        // What one network takes whole stays with it: one view, a pair, the cross, a line from
        // one end (its far view a side input).
        let details = |offsets: &[[i32; 2]]| method.details(&plane(offsets));
        assert_eq!(details(&[[1, 0]])["network"], "stereo");
        assert_eq!(details(&[[-1, 0], [1, 0]])["network"], "three-view");
        assert_eq!(details(&[[-1, 0], [1, 0], [0, -1], [0, 1]])["network"], "five-view");
        assert_eq!(details(&[[1, 0], [2, 0]])["network"], "stereo");
        // `every_view: false`: the stereo network on one view of the L.
        let fixed = serde_json::json!({ "every_view": false });
        let fixed = crate::methods::build("mfusenet", Some(&fixed)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(fixed.details(&plane(&[[-1, 0], [0, -1]]))["network"], "stereo");
        // The L finds its plane away from the borders its views shift (rows and columns), both
        // ways.
        for method in [&method, &unfilled] {
            let out = method
                .run(&plane(&[[-1, 0], [0, -1]]), &|_| {})
                .unwrap_or_else(|e| panic!("{e}"));
            let (w, h, margin) = (out.width, out.height, 12);
            let errors: Vec<f32> = (margin..h - margin)
                .flat_map(|y| (margin..w - margin).map(move |x| (x, y)))
                .map(|(x, y)| (out.data[y * w + x] - 6.0).abs())
                .collect();
            let mean = errors.iter().sum::<f32>() / errors.len() as f32;
            assert!(mean < 0.25, "AvgErr {mean:.3} px");
        }
    }

    #[test]
    fn side_inputs_take_a_line_of_five_s_far_views_and_find_its_plane() {
        let problem = plane_sized(&[[-2, 0], [-1, 0], [1, 0], [2, 0]], 6, (0, 32), (128, 64));
        let config = serde_json::json!({ "side_inputs": true });
        let method = crate::methods::build("mfusenet", Some(&config)).unwrap_or_else(|e| panic!("{e}"));
        let details = method.details(&problem);
        assert_eq!(
            details["side_inputs"],
            serde_json::json!(["left + left2", "right + right2"]),
            "{details}"
        );
        assert_eq!(details["side_rule"], "near-capped", "{details}");
        let out = method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        // The pixels every view sees (12 px from either border).
        let errors = interior_errors(&out, 12, 6.0);
        let mean = errors.iter().sum::<f32>() / errors.len() as f32;
        assert!(mean < 0.25, "AvgErr {mean:.3} px");
        // On by default; `false` turns them off.
        let default = crate::methods::build("mfusenet", None).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(default.details(&problem)["side_inputs"], details["side_inputs"]);
        let off = serde_json::json!({ "side_inputs": false });
        let off = crate::methods::build("mfusenet", Some(&off)).unwrap_or_else(|e| panic!("{e}"));
        assert!(off.details(&problem)["side_inputs"].is_null());
        // The stereo method keeps its one neighbour.
        let stereo = crate::methods::build("mfusenet-stereo", None).unwrap_or_else(|e| panic!("{e}"));
        assert!(stereo.details(&problem)["side_inputs"].is_null());
    }

    #[test]
    fn a_sharpened_file_answers_as_its_fixed_one_until_its_sharp_weights_move() {
        // A fixed lite five-view network (seeded weights, the shipped lite file's metadata; the
        // shipped file itself is sharp) widened with zero weights for the sharp volumes
        // (`Network::sharpened`): `mfusenet` makes the sharp volumes and feeds them, and the
        // answer is the fixed file's to the bit, test-time flips included; with sharp weights
        // the answer moves.
        let bytes = include_bytes!("../../weights/mfusenet-5view-lite.safetensors");
        let (shipped, info) = weights::from_bytes(bytes, "lite", "", Some(4)).unwrap_or_else(|e| panic!("{e}"));
        assert!(shipped.sharp, "the shipped lite five-view file takes sharp volumes");
        let net = Network::init_with(4, Architecture::Lite, 11);
        let dir = std::env::temp_dir().join(format!("fuse-sharp-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&dir);
        let fixed_file = dir.join("fixed.safetensors");
        let saved = weights::save(&net, &info, &fixed_file);
        assert!(saved.is_ok(), "{saved:?}");
        let sharp_file = dir.join("sharp.safetensors");
        let mut sharp = net.sharpened().unwrap_or_else(|| panic!("a fixed network sharpens"));
        let saved = weights::save(&sharp, &info, &sharp_file);
        assert!(saved.is_ok(), "{saved:?}");
        let problem = plane_sized(&[[-1, 0], [1, 0], [0, -1], [0, 1]], 6, (0, 24), (96, 64));
        let run = |config: serde_json::Value| {
            let method = crate::methods::build("mfusenet", Some(&config)).unwrap_or_else(|e| panic!("{e}"));
            method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{e}"))
        };
        let (fixed_name, file) = (fixed_file.display().to_string(), sharp_file.display().to_string());
        for flips in [false, true] {
            let fixed = run(serde_json::json!({ "weights": fixed_name, "flips": flips }));
            let widened = run(serde_json::json!({ "weights": file, "flips": flips }));
            assert_eq!(widened.data, fixed.data, "flips {flips}");
        }
        let k3 = sharp.fuse[0].k.pow(3);
        for (i, w) in sharp.fuse[0].weight.iter_mut().enumerate() {
            if i / k3 % 5 == 4 {
                *w = 0.02;
            }
        }
        let saved = weights::save(&sharp, &info, &sharp_file);
        assert!(saved.is_ok(), "{saved:?}");
        let moved = run(serde_json::json!({ "weights": file }));
        let fixed = run(serde_json::json!({ "weights": fixed_name }));
        assert_ne!(moved.data, fixed.data, "the sharp volumes reach the answer");
        assert!(moved.data.iter().all(|d| d.is_finite()));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn every_shipped_network_finds_a_plane_at_its_range_start_with_context_up_to_the_borders() {
        // Every shipped file asks for context below the range: 4 slices, 8 for the lite
        // five-view one (the two five-view files since their metadata was set after training:
        // without context they put this plane 6 and 8–11 px off, fuse/weights/README.md); each
        // runs here with its defaults.
        type Layout<'a> = (&'a str, &'a [[i32; 2]], Option<serde_json::Value>);
        let five = &[[-1, 0], [1, 0], [0, -1], [0, 1]];
        let layouts: [Layout<'_>; 4] = [
            ("stereo", &[[1, 0]], None),
            ("three-view", &[[-1, 0], [1, 0]], None),
            ("five-view (lite)", five, None),
            (
                "five-view (paper)",
                five,
                Some(serde_json::json!({"architecture": "paper"})),
            ),
        ];
        for (name, offsets, config) in layouts {
            // A far wall at the start of an unsigned range, and of a converged rig's signed one.
            for (d, min_disparity) in [(2, 2), (-7, -7)] {
                let problem = plane(offsets, d, min_disparity);
                let method = crate::methods::build("mfusenet", config.as_ref()).unwrap_or_else(|e| panic!("{e}"));
                let out = method.run(&problem, &|_| {}).unwrap_or_else(|e| panic!("{name}: {e}"));
                // Every pixel that some neighbour sees counts, the image borders included (the
                // stereo network cannot know the strip its one neighbour does not see).
                let (w, h) = (problem.reference.width as i32, problem.reference.height as i32);
                let seen = |x: i32, y: i32| {
                    offsets.iter().any(|o| {
                        let (qx, qy) = (x - o[0] * d, y - o[1] * d);
                        (0..w).contains(&qx) && (0..h).contains(&qy)
                    })
                };
                let errors: Vec<f32> = out
                    .data
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| seen(*i as i32 % w, *i as i32 / w))
                    .map(|(_, e)| (e - d as f32).abs())
                    .collect();
                assert!(
                    errors.len() >= (w * (h - 7)) as usize,
                    "{name}: {} pixels seen",
                    errors.len()
                );
                let mean = errors.iter().sum::<f32>() / errors.len() as f32;
                let bad = errors.iter().filter(|e| **e > 1.0).count();
                assert!(
                    mean < 0.25 && bad * 100 < errors.len(),
                    "{name}, plane at {d} searched from {min_disparity}: AvgErr {mean:.3} px, {bad} of {} pixels off by > 1 px",
                    errors.len()
                );
            }
        }
    }

    #[test]
    fn narrow_ranges_are_widened_evenly_on_both_sides() {
        assert_eq!(widened_range((24, 8), MIN_NETWORK_DISPARITIES), Some((20, 16)));
        assert_eq!(widened_range((3, 9), MIN_NETWORK_DISPARITIES), Some((0, 16)));
        assert_eq!(widened_range((-4, 9), MIN_NETWORK_DISPARITIES), Some((-7, 16)));
        assert_eq!(widened_range((24, 16), 32), Some((16, 32)));
        assert_eq!(widened_range((0, 8), 32), Some((-12, 32)));
        assert_eq!(widened_range((-20, 16), 32), Some((-28, 32)));
        assert_eq!(widened_range((10, 31), 32), Some((10, 32)));
        assert_eq!(widened_range((0, 16), MIN_NETWORK_DISPARITIES), None);
        assert_eq!(widened_range((0, 32), 32), None);
        assert_eq!(widened_range((5, 64), MIN_NETWORK_DISPARITIES), None);
        // Wider than the networks' trained depths is refused before any work.
        let problem = plane_sized(&[[-1, 0], [1, 0]], 4, (0, 8), (32, 24));
        let config = serde_json::json!({"min_network_disparities": MAX_MIN_NETWORK_DISPARITIES + 1});
        let method = crate::methods::build("mfusenet", Some(&config)).unwrap_or_else(|e| panic!("{e}"));
        let error = method.run(&problem, &|_| {}).err();
        assert!(
            matches!(
                error,
                Some(FuseError::Config {
                    field: "min_network_disparities",
                    ..
                })
            ),
            "{error:?}"
        );
    }

    #[test]
    fn a_pixel_votes_fully_where_the_summed_costs_have_a_minimum_within_a_pixel() {
        // One pixel per column; two neighbours whose costs sum to a V with its minimum at slice 6.
        let nd = 12;
        let volume = |tilt: i32| {
            CostVolume::from_fn([5, 1, nd], 0, ("left", [-1, 0]), |_, _, k| {
                let k = k as i32;
                (10 * (k - 6).abs() + tilt * k + 20) as u8
            })
        };
        let costs = summed(&[volume(1), volume(-1)]).unwrap_or_else(|| panic!("two volumes of one shape"));
        // The volumes start at disparity 10: slice 6 is disparity 16.
        let disparity = DisparityImage {
            width: 5,
            height: 1,
            data: vec![16.0, 16.9, 15.2, 17.5, f32::INFINITY],
            confidence: None,
        };
        let votes = cost_agreement(&disparity, &costs, 10, 0.05);
        assert_eq!(votes, vec![1.0, 1.0, 1.0, 0.05, 0.05]);
        // The same estimates against volumes starting at 0 are far from the minimum.
        assert_eq!(cost_agreement(&disparity, &costs, 0, 0.25), vec![0.25; 5]);
    }
}
