//! Inference over whole images with bounded memory: D, H and W are padded to multiples of 4
//! (edge values repeated), the image is cut into square tiles whose side follows from a memory
//! budget, each tile is run with a halo of [`Architecture::halo`](super::network::Architecture::halo) pixels (the network's receptive
//! radius, 43 px for the paper's kernels and 35 for the lite ones, rounded up to a multiple of 4
//! so that every tile's stride-2 grids are the whole image's),
//! and only the tile's core is kept. The result equals the untiled run up to rounding. The
//! soft-argmin runs over the real disparities only (padded slices are dropped).

use std::ops::Range;

use super::Error;
use super::input::{flip_axes, mirrored};
use super::network::Network;
use crate::cost::ValidDisparities;
use crate::nn::Tensor;
use crate::volume::CostVolume;
use crate::wta::{LockingCurve, SubpixelFit};

/// Default memory budget of one tile's activations (a Middlebury third-size set runs whole, and
/// a five-view 640×360 set of 36 slices). With the allocator keeping freed pages the process
/// holds about 1.5 times this: the demo's 960×540 capture 1.18 GB peak RSS and 20.0 s at
/// 768 MiB, 1.53 GB and 18.5 s at 1 GiB (docs/benchmarks.md).
pub const DEFAULT_TILE_BUDGET_BYTES: usize = 768 << 20;

/// Peak bytes per voxel of a forward pass with `views` inputs, as planned: the N input volumes
/// plus about 20 channels, 4 bytes each. A pass now needs less: each view's input is made when
/// its feature tower starts and freed after it, and at the widest point (a view's tower: its
/// padded input and output and a spare buffer of 4 channels each, beside the 4 of `concat`'s
/// sum) neither the concatenated features nor `uconv2`'s 8 input channels are ever whole.
/// Measured at N = 4, the demo's 960×540 capture (24 slices) in one tile: 957 MB peak RSS for
/// the process with `MIMALLOC_PURGE_DELAY=0`, against 155 MB in tiles of 32 MiB: 64 B per
/// voxel. The plan keeps the larger figure, so tiles are no larger than before: that capture in
/// one tile ran 5 % faster, but the allocator then held 1.19 GB (docs/experiments.md).
pub fn bytes_per_voxel(views: usize) -> usize {
    4 * (views + 20)
}

fn round4(n: usize) -> usize {
    n.div_ceil(4) * 4
}

/// The side of a square tile core (a multiple of 4, at least 16) whose padded region fits
/// `budget_bytes` at `disparities` slices with a `halo` around it.
pub fn tile_side(views: usize, num_disparities: usize, budget_bytes: usize, halo: usize) -> usize {
    let voxels = budget_bytes / bytes_per_voxel(views) / round4(num_disparities).max(1);
    let region = (voxels as f64).sqrt() as usize;
    (region.saturating_sub(2 * halo) / 4 * 4).max(16)
}

/// The tiles along one axis: each core and its region (the core with its halo).
pub type AxisTiles = Vec<Tile>;

/// One axis of a tile: its core and its region (the core with its halo).
pub type Tile = (Range<usize>, Range<usize>);

/// One axis cut into tile cores of `core` pixels (a multiple of 4; the last may be shorter) over
/// `length` pixels: the cores and their regions with `halo` pixels either side (clipped to the
/// axis).
fn axis_tiles(length: usize, core: usize, halo: usize) -> AxisTiles {
    (0..length)
        .step_by(core.max(4))
        .map(|start| {
            let end = (start + core.max(4)).min(length);
            (start..end, start.saturating_sub(halo)..(end + halo).min(length))
        })
        .collect()
}

/// The tiles of a `height × width` image (multiples of 4) whose regions (cores with their
/// halo) each hold at most `max_region_pixels`, with the fewest region pixels in all: every
/// split of each axis into equal cores (multiples of 4) is tried, so that the halos, which are
/// computed twice, cost as little as the budget allows (a 960 × 540 image of 36 slices at 192
/// bytes a voxel under a 1 GiB budget: 3 × 2 tiles of 320 × 272 instead of 4 × 2 squares of
/// 296, 11 % fewer voxels). The square
/// tiles of [`tile_side`] are among the splits tried, so the plan is never worse than them.
/// `(row cores and regions, column cores and regions)`.
pub fn plan_tiles(height: usize, width: usize, max_region_pixels: usize, halo: usize) -> (AxisTiles, AxisTiles) {
    // Per axis and core size: (sum of region lengths, longest region, core).
    let options = |length: usize| -> Vec<(usize, usize, usize)> {
        let mut seen = Vec::new();
        for count in 1..=length.div_ceil(4).max(1) {
            let core = round4(length.div_ceil(count)).max(4);
            if seen.iter().any(|(_, _, c)| *c == core) {
                continue;
            }
            let tiles = axis_tiles(length, core, halo);
            let total = tiles.iter().map(|(_, r)| r.len()).sum();
            let longest = tiles.iter().map(|(_, r)| r.len()).max().unwrap_or(0);
            seen.push((total, longest, core));
        }
        seen
    };
    let (rows, columns) = (options(height), options(width));
    let mut best: Option<(usize, usize, usize)> = None;
    for &(row_total, row_longest, row_core) in &rows {
        for &(column_total, column_longest, column_core) in &columns {
            if row_longest * column_longest > max_region_pixels {
                continue;
            }
            let cost = row_total * column_total;
            if best.is_none_or(|(b, ..)| cost < b) {
                best = Some((cost, row_core, column_core));
            }
        }
    }
    // Nothing fits: the smallest tiles there are.
    let (_, row_core, column_core) = best.unwrap_or((0, 4, 4));
    (axis_tiles(height, row_core, halo), axis_tiles(width, column_core, halo))
}

/// Disparities (`min_disparity + Σ d·p(d)`, `[y][x]`) of the normalised per-neighbour volumes
/// (bytes, [`super::input`]) with the network in eval mode, in tiles that fit `budget_bytes`;
/// `progress` gets the fraction of tiles done. `estimate.window: Some(r)` takes the soft-argmin
/// over the `2r + 1` disparities around each pixel's most probable one only (renormalised), so
/// that a second mode of the distribution does not pull the estimate between the two; `None` is
/// the paper's soft-argmin over the whole range; `estimate.context_below` slices at the start are
/// left out of it. `estimate.refine` takes the sub-pixel part from
/// the inputs instead (see [`Estimate`]).
pub fn infer(
    net: &Network,
    volumes: &[CostVolume<u8>],
    budget_bytes: usize,
    estimate: Estimate,
    progress: &dyn Fn(f32),
) -> Result<Vec<f32>, Error> {
    infer_with_confidence(net, volumes, budget_bytes, estimate, progress).map(|(disparity, _)| disparity)
}

/// [`infer`] that also gives each pixel's confidence: how far its most probable disparity stands
/// out of the rest ([`peak_margin`]).
pub fn infer_with_confidence(
    net: &Network,
    volumes: &[CostVolume<u8>],
    budget_bytes: usize,
    estimate: Estimate,
    progress: &dyn Fn(f32),
) -> Result<(Vec<f32>, Vec<f32>), Error> {
    let Some(first) = volumes.first() else {
        return Err(Error::InputCount {
            expected: net.views,
            got: 0,
        });
    };
    let (w, h, nd) = (first.width, first.height, first.num_disparities);
    // The view-count-agnostic network (views = 0) takes any number; a sharp one its views'
    // volumes and then as many sharp volumes.
    if net.views != 0 && volumes.len() != net.input_count() {
        return Err(Error::InputCount {
            expected: net.input_count(),
            got: volumes.len(),
        });
    }
    let views = if net.views == 0 { volumes.len() } else { net.views };
    let view_volumes = &volumes[..views];
    check_shapes(volumes, (w, h, nd))?;
    let skip = estimate.context_below;
    if skip >= nd {
        return Err(Error::ContextBelow {
            context_below: skip,
            num_disparities: nd,
        });
    }
    // Test-time flips: the mirror that maps this set's neighbours onto themselves.
    let offsets = super::input::neighbour_offsets(view_volumes).unwrap_or_default();
    let no_mirror = || Error::NoMirror {
        offsets: offsets.clone(),
    };
    // A pooled network does not know which neighbour gave a volume: every mirror exists, and the
    // volumes are flipped where they are.
    let pooled = net.views == 0;
    let mirror = match (estimate.flips, pooled) {
        (false, _) => None,
        (true, true) => Some((false, true)),
        (true, false) => Some(flip_axes(&offsets).ok_or_else(no_mirror)?),
    };
    let dp = round4(nd);
    let tiles = tiles((w, h, nd), volumes.len(), budget_bytes, net.architecture.halo());
    let mut disparity = vec![0f32; w * h];
    let mut confidence = vec![0f32; w * h];
    for (done, ((rows, region_rows), (columns, region_columns))) in tiles.iter().enumerate() {
        let (y0, y1, x0, x1) = (rows.start, rows.end, columns.start, columns.end);
        let (ry0, rx0) = (region_rows.start, region_columns.start);
        let (rh, rw) = (region_rows.len(), region_columns.len());
        let input = |i: usize| super::input::to_tensor(&volumes[i], (ry0, rx0), (rh, rw), dp);
        // Only the core's logits are read: the last layers skip most of the halo.
        let (core_rows, core_columns) = (y0 - ry0..y1 - ry0, x0 - rx0..x1 - rx0);
        let keep = (core_rows.clone(), core_columns.clone());
        // The estimate and its confidence over the core, from the logits of the region from
        // `(oy, ox)`.
        let read_tile =
            |logits: &Tensor, (oy, ox): (usize, usize), (disparity, confidence): (&mut [f32], &mut [f32])| {
                let (lh, lw) = (logits.shape[2], logits.shape[3]);
                let plane = lh * lw;
                for y in y0..y1.min(h) {
                    for x in x0..x1.min(w) {
                        let at = (y - ry0 - oy) * lw + (x - rx0 - ox);
                        let column = |d: usize| logits.data[d * plane + at];
                        let mut value = expected_disparity_from(column, nd, skip, estimate.window);
                        if estimate.refine {
                            let cost = |d: usize| view_volumes.iter().map(|v| f64::from(v.costs(x, y)[d])).sum::<f64>();
                            value = refined(value, cost, nd, estimate.refine_reach, estimate.fit, estimate.locking);
                        }
                        disparity[y * w + x] = (first.min_disparity as f64 + value) as f32;
                        confidence[y * w + x] = peak_margin(column, nd, skip);
                    }
                }
            };
        let Some((vertical, horizontal)) = mirror else {
            // Each view's input made when the pass reaches it.
            let (logits, origin) = net.logits_within_made((volumes.len(), [1, dp, rh, rw]), &input, &keep)?;
            read_tile(&logits, origin, (&mut disparity, &mut confidence));
            progress((done + 1) as f32 / tiles.len() as f32);
            continue;
        };
        let inputs: Vec<Tensor> = (0..volumes.len()).map(input).collect();
        let (mut logits, origin) = net.logits_within(&inputs, &keep)?;
        // The set's mirror image answered and mirrored back; the mean of the two passes'
        // logits is the network made symmetric, at its own temperature (where the logits
        // are peaked, the surer pass decides).
        let flipped = if pooled {
            inputs.iter().map(|t| t.flipped(vertical, horizontal)).collect()
        } else {
            // (The sharp volumes, after the views', move with their views.)
            mirrored(&inputs, &offsets, vertical, horizontal).ok_or_else(no_mirror)?
        };
        drop(inputs);
        // The core mirrored: its margin, mirrored back, is the same rows and columns.
        let mirror_range = |range: &Range<usize>, length: usize, flip: bool| {
            if flip {
                length - range.end..length - range.start
            } else {
                range.clone()
            }
        };
        let (answer, _) = net.logits_within(
            &flipped,
            &(
                mirror_range(&core_rows, rh, vertical),
                mirror_range(&core_columns, rw, horizontal),
            ),
        )?;
        drop(flipped);
        let answer = answer.flipped(vertical, horizontal);
        logits
            .data
            .iter_mut()
            .zip(&answer.data)
            .for_each(|(a, b)| *a = 0.5 * (*a + b));
        read_tile(&logits, origin, (&mut disparity, &mut confidence));
        progress((done + 1) as f32 / tiles.len() as f32);
    }
    Ok((disparity, confidence))
}

/// Every volume is `w × h × nd` (none empty).
fn check_shapes(volumes: &[CostVolume<u8>], (w, h, nd): (usize, usize, usize)) -> Result<(), Error> {
    for v in volumes {
        if (v.width, v.height, v.num_disparities) != (w, h, nd) || v.data.len() != w * h * nd || w * h * nd == 0 {
            return Err(Error::InputShape {
                shape: [1, v.num_disparities, v.height, v.width],
            });
        }
    }
    Ok(())
}

/// The tiles `(rows, region rows), (columns, region columns)` of a `w × h × nd` set for a
/// network of `views` inputs under `budget_bytes`: the whole padded image when it fits, else
/// [`plan_tiles`]'s cores with their `halo`.
fn tiles((w, h, nd): (usize, usize, usize), views: usize, budget_bytes: usize, halo: usize) -> Vec<(Tile, Tile)> {
    let (dp, hp, wp) = (round4(nd), round4(h), round4(w));
    let whole = dp * hp * wp * bytes_per_voxel(views) <= budget_bytes;
    let (row_tiles, column_tiles) = if whole {
        (axis_tiles(hp, hp, 0), axis_tiles(wp, wp, 0))
    } else {
        let side = tile_side(views, nd, budget_bytes, halo) + 2 * halo;
        plan_tiles(hp, wp, side * side, halo)
    };
    row_tiles
        .iter()
        .flat_map(|row| column_tiles.iter().map(move |column| (row.clone(), column.clone())))
        .collect()
}

/// One network's part in [`infer_fused`]: the network and the indices of its input volumes,
/// in its input order.
pub struct Member<'a> {
    /// The network.
    pub net: &'a Network,
    /// Indices into the volumes, in the network's input order.
    pub inputs: Vec<usize>,
    /// Where the member votes: `None`, at every disparity of every pixel; else its views'
    /// disparities inside their images ([`ValidDisparities`] over the volumes' axis), and the
    /// member's logits count only there. A farther group's correspondences leave the image in
    /// border bands as wide as its baseline times the range, where its network answers from
    /// mirrored costs.
    pub reach: Option<Vec<ValidDisparities>>,
    /// The vote of each of its views, relative to one of a member that votes 1 (the nearest
    /// group's): with saturated logits, two members that disagree are nearly tied, and a
    /// farther group's smaller vote settles it for the nearer views, which alias less
    /// (`MFuseNetConfig::farther_vote`); a filled cross's scaled by its views over its inputs,
    /// so that each view still has one vote.
    pub vote: f32,
}

/// [`infer_with_confidence`] for several networks over one set, each on its own neighbours'
/// volumes (`members`), their logits averaged (each weighted by its number of inputs times its
/// [`Member::vote`], so that every view has its vote; with a member's [`Member::reach`], their
/// log-probabilities, each where its member votes) before the estimate is read; the refinement
/// reads `costs` (the set's fused costs, of the volumes' shape). Test-time flips are not
/// applied here.
pub fn infer_fused(
    members: &[Member<'_>],
    volumes: &[CostVolume<u8>],
    costs: &CostVolume<u16>,
    budget_bytes: usize,
    estimate: Estimate,
    progress: &dyn Fn(f32),
) -> Result<(Vec<f32>, Vec<f32>), Error> {
    let Some(first) = volumes.first() else {
        return Err(Error::InputCount { expected: 1, got: 0 });
    };
    let (w, h, nd) = (first.width, first.height, first.num_disparities);
    if costs.shape() != first.shape() {
        return Err(Error::InputShape {
            shape: [1, costs.num_disparities, costs.height, costs.width],
        });
    }
    check_shapes(volumes, (w, h, nd))?;
    for m in members {
        if m.inputs.len() != m.net.input_count() || m.inputs.iter().any(|i| *i >= volumes.len()) {
            return Err(Error::InputCount {
                expected: m.net.input_count(),
                got: m.inputs.iter().filter(|i| **i < volumes.len()).count(),
            });
        }
    }
    let skip = estimate.context_below;
    if skip >= nd {
        return Err(Error::ContextBelow {
            context_below: skip,
            num_disparities: nd,
        });
    }
    let widest = members.iter().map(|m| m.net.views).max().unwrap_or(1);
    let dp = round4(nd);
    let halo = members.iter().map(|m| m.net.architecture.halo()).max().unwrap_or(0);
    let tiles = tiles((w, h, nd), widest, budget_bytes, halo);
    let total_weight: f32 = members.iter().map(|m| m.net.views as f32 * m.vote).sum();
    // With a member that votes only where its views see, each member's logits become
    // log-probabilities (their softmax is unchanged; their offsets then agree) and every
    // (pixel, disparity) averages those of the members that vote there.
    let partial = members.iter().any(|m| m.reach.is_some());
    let mut disparity = vec![0f32; w * h];
    let mut confidence = vec![0f32; w * h];
    let steps = (tiles.len() * members.len()).max(1);
    for (t, ((rows, region_rows), (columns, region_columns))) in tiles.iter().enumerate() {
        let (y0, y1, x0, x1) = (rows.start, rows.end, columns.start, columns.end);
        let (ry0, rx0) = (region_rows.start, region_columns.start);
        let (rh, rw) = (region_rows.len(), region_columns.len());
        let (core_rows, core_columns) = (y0 - ry0..y1 - ry0, x0 - rx0..x1 - rx0);
        let (ch, cw) = (core_rows.len(), core_columns.len());
        // The members' logits over the core, `[d][row][column]`, weighted and summed.
        let mut fused = vec![0f32; dp * ch * cw];
        let mut votes = if partial { vec![0f32; nd * ch * cw] } else { Vec::new() };
        for (done, m) in members.iter().enumerate() {
            // Each view's input made when the pass reaches it.
            let input = |i: usize| super::input::to_tensor(&volumes[m.inputs[i]], (ry0, rx0), (rh, rw), dp);
            let (logits, (oy, ox)) = m.net.logits_within_made(
                (m.inputs.len(), [1, dp, rh, rw]),
                &input,
                &(core_rows.clone(), core_columns.clone()),
            )?;
            let core = logits.crop_hw(
                core_rows.start - oy..core_rows.end - oy,
                core_columns.start - ox..core_columns.end - ox,
            );
            drop(logits);
            if partial {
                add_log_probabilities(m, &core.data, (&mut fused, &mut votes), nd, (y0, x0), (ch, cw));
            } else {
                let weight = m.net.views as f32 * m.vote / total_weight;
                fused.iter_mut().zip(&core.data).for_each(|(f, l)| *f += weight * l);
            }
            progress((t * members.len() + done + 1) as f32 / steps as f32);
        }
        let plane = ch * cw;
        if partial {
            for (f, v) in fused.iter_mut().zip(&votes) {
                *f = if *v > 0.0 { *f / v } else { f32::NEG_INFINITY };
            }
        }
        for y in y0..y1.min(h) {
            for x in x0..x1.min(w) {
                let at = (y - y0) * cw + (x - x0);
                let column = |d: usize| fused[d * plane + at];
                let mut value = expected_disparity_from(column, nd, skip, estimate.window);
                if estimate.refine {
                    let pixel = costs.costs(x, y);
                    let cost = |d: usize| f64::from(pixel[d]);
                    value = refined(value, cost, nd, estimate.refine_reach, estimate.fit, estimate.locking);
                }
                disparity[y * w + x] = (first.min_disparity as f64 + value) as f32;
                confidence[y * w + x] = peak_margin(column, nd, skip);
            }
        }
    }
    Ok((disparity, confidence))
}

/// Adds `member`'s log-probabilities (from its core logits `[d][row][column]`, `ch × cw` from
/// pixel `(y0, x0)`) weighted by its views' votes into `sums` where it votes, and its weight into
/// `votes` (both `[d][row][column]` over the first `nd` slices).
fn add_log_probabilities(
    member: &Member<'_>,
    logits: &[f32],
    (sums, votes): (&mut [f32], &mut [f32]),
    nd: usize,
    (y0, x0): (usize, usize),
    (ch, cw): (usize, usize),
) {
    let plane = ch * cw;
    let weight = member.net.views as f32 * member.vote;
    for at in 0..plane {
        let (y, x) = (y0 + at / cw, x0 + at % cw);
        let (first, end) = member.reach.as_ref().map_or((0, nd), |views| {
            views.iter().fold((0, nd), |(first, end), v| {
                let (f, e) = v.at(x, y);
                (first.max(f), end.min(e))
            })
        });
        if first >= end {
            continue;
        }
        let max = (0..nd)
            .map(|d| logits[d * plane + at])
            .fold(f32::NEG_INFINITY, f32::max);
        let sum: f32 = (0..nd).map(|d| (logits[d * plane + at] - max).exp()).sum();
        let norm = max + sum.ln();
        for d in first..end {
            sums[d * plane + at] += weight * (logits[d * plane + at] - norm);
            votes[d * plane + at] += weight;
        }
    }
}

/// How a pixel's disparity is read from the network's distribution. The default is the
/// paper's soft-argmin over the whole range (with, for `refine`, the shipped reach and fit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// Soft-argmin over `2r + 1` disparities around the most probable one (`None`: all, the paper).
    pub window: Option<usize>,
    /// The volumes' first this many slices are context for the network only: the most probable
    /// disparity is looked for after them (in the searched range), never in them, but the
    /// distribution around it and the refining costs reach into them, so that a truth at the
    /// range's first slice is read without bias (the caller clamps the result into the range).
    pub context_below: usize,
    /// Keep the integer disparity nearest the network's estimate, and take the sub-pixel offset
    /// from the `fit` through the summed input costs there (where they have a minimum), as
    /// the classical methods do.
    pub refine: bool,
    /// With `refine`: how far (px) the estimate may move from the network's integer to a
    /// neighbouring minimum of the input costs (see [`refined`]); 0 = only the integer's own.
    pub refine_reach: f64,
    /// With `refine`: the curve through the summed input costs whose vertex is the sub-pixel
    /// disparity ([`DEFAULT_SUBPIXEL_FIT`]).
    pub fit: SubpixelFit,
    /// With `refine`: the correction of the fit's pixel locking (`None`: the fit's offset).
    pub locking: Option<LockingCurve>,
    /// Test-time flips: the network also answers the set's mirror image
    /// ([`super::input::flip_axes`]: left to right for a left/right pair and the four-view
    /// cross, top to bottom for a top/bottom pair or a single neighbour; the volumes move to
    /// their mirrored neighbours' slots) and the two passes' logits are averaged, mirrored
    /// back, before the estimate is read, at twice the time.
    pub flips: bool,
}

impl Default for Estimate {
    fn default() -> Self {
        Self {
            window: None,
            context_below: 0,
            refine: false,
            refine_reach: DEFAULT_REFINE_REACH,
            fit: DEFAULT_SUBPIXEL_FIT,
            locking: None,
            flips: false,
        }
    }
}

/// How far (px) from the network's integer the refined estimate may move to a neighbouring
/// minimum of the summed input costs ([`refined`]). On `middlebury2006-third-dev` (three-view,
/// shipped network, parabola fit): 0 → 1 px took AvgErr 0.410 → 0.395 and Bad0.5 11.96 → 10.33 %
/// with Bad1 unchanged (6.60 → 6.59 %); 1.5 (any neighbouring minimum) raised Bad1 to 6.80 %.
pub const DEFAULT_REFINE_REACH: f64 = 1.0;

/// The refined estimate's sub-pixel fit: the inputs are SGM sums of census distances, V-shaped
/// at their minima, where a parabola locks to the integer. On `middlebury2006-third-dev`
/// (three-view, shipped network, reach 1, median) the lines took AvgErr 0.391 → 0.363 px (every
/// scene better; Bad1 6.42 → 6.42 %, Bad0.5 9.93 → 10.31 %); held-out simulated three-view
/// 0.985 → 0.950 px, five-view 0.338 → 0.295 px.
pub const DEFAULT_SUBPIXEL_FIT: SubpixelFit = SubpixelFit::Equiangular;

/// `estimate` moved to the vertex of the `fit` through `cost` at the nearest integer
/// disparity `d` and its two neighbours, when `d` is a local minimum of `cost`. When it is not,
/// the neighbouring integer on its downhill side is tried instead, and its vertex taken if it is
/// a local minimum and the vertex lies within `reach` px of `d` (the network chose the integer to
/// within one; the costs place the surface between the two); else `estimate` is kept.
pub fn refined(
    estimate: f64,
    cost: impl Fn(usize) -> f64,
    nd: usize,
    reach: f64,
    fit: SubpixelFit,
    locking: Option<LockingCurve>,
) -> f64 {
    let offset = |costs| fit.offset(costs).map(|o| locking.map_or(o, |curve| curve.apply(o)));
    let d = estimate.round().clamp(0.0, nd.saturating_sub(1) as f64) as usize;
    if d == 0 || d + 1 >= nd {
        return estimate;
    }
    let (l, c, r) = (cost(d - 1), cost(d), cost(d + 1));
    if let Some(offset) = offset([l, c, r]) {
        return d as f64 + offset;
    }
    let n = if l < r { d - 1 } else { d + 1 };
    if reach > 0.0 && n >= 1 && n + 1 < nd {
        let vertex = offset([cost(n - 1), cost(n), cost(n + 1)]).map(|offset| n as f64 + offset);
        if let Some(v) = vertex.filter(|v| (v - d as f64).abs() <= reach) {
            return v;
        }
    }
    estimate
}

/// The soft-argmin `Σ d·softmax(logit)_d` of one pixel's `nd` logits, over the whole range or,
/// with `window: Some(r)`, over the `2r + 1` disparities around the most probable one.
pub fn expected_disparity(logit: impl Fn(usize) -> f32, nd: usize, window: Option<usize>) -> f64 {
    expected_disparity_from(logit, nd, 0, window)
}

/// How far under the first searched slice the whole-range soft-argmin reaches, when the most
/// probable disparity is that close to it: the peak's lower tail, not the context's own modes.
pub const CONTEXT_TAIL: usize = 2;

/// The most probable slice at or after `first_mode` (the first of equals) and its logit.
fn searched_mode(logit: impl Fn(usize) -> f32, nd: usize, first_mode: usize) -> (usize, f32) {
    (first_mode.min(nd.saturating_sub(1))..nd).map(|d| (d, logit(d))).fold(
        (first_mode, f32::NEG_INFINITY),
        |best, (d, v)| if v > best.1 { (d, v) } else { best },
    )
}

/// How much the most probable slice (at or after `first_mode`) stands out of the network's
/// distribution: `(l₁ − l₂) / (l₁ − l_min)` of the logits, `l₁` the mode's, `l₂` the largest at
/// least 2 slices away, `l_min` the smallest; 1 for a single peak over a flat floor, 0 where a
/// second disparity is as likely. Ratios of logit differences do not depend on the softmax's
/// temperature: the shipped networks' logits reach 10⁵, their softmax is one-hot almost
/// everywhere, so the probability near the mode would say 1 for every pixel.
pub fn peak_margin(logit: impl Fn(usize) -> f32, nd: usize, first_mode: usize) -> f32 {
    let (mode, top) = searched_mode(&logit, nd, first_mode);
    let floor = (0..nd).map(&logit).fold(f32::INFINITY, f32::min);
    let second = (0..nd)
        .filter(|d| d.abs_diff(mode) >= 2)
        .map(&logit)
        .fold(f32::NEG_INFINITY, f32::max);
    let spread = top - floor;
    if !(spread > 0.0 && spread.is_finite()) {
        return 0.0;
    }
    if second == f32::NEG_INFINITY {
        return 1.0;
    }
    ((top - second) / spread).clamp(0.0, 1.0)
}

/// [`expected_disparity`] with the most probable disparity looked for from slice `first_mode`
/// on only: the slices under it are context, never the mode. A window around the mode reaches
/// into them; the whole-range sum (`window: None`) takes them only within [`CONTEXT_TAIL`] of
/// the mode (a truth at the range's start keeps its peak's lower tail, while an occluded pixel's
/// mass in the context does not pull the estimate).
pub fn expected_disparity_from(
    logit: impl Fn(usize) -> f32,
    nd: usize,
    first_mode: usize,
    window: Option<usize>,
) -> f64 {
    let (mode, _) = searched_mode(&logit, nd, first_mode);
    let range = match window {
        Some(r) => mode.saturating_sub(r)..(mode + r + 1).min(nd),
        None => first_mode.min(mode.saturating_sub(CONTEXT_TAIL))..nd,
    };
    let max = range.clone().map(&logit).fold(f32::NEG_INFINITY, f32::max);
    let (mut sum, mut weighted) = (0f64, 0f64);
    for d in range {
        let e = f64::from((logit(d) - max).exp());
        sum += e;
        weighted += d as f64 * e;
    }
    weighted / sum
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mfusenet::network::Architecture;

    /// The halo of the paper's kernels, which the test networks have.
    const HALO: usize = Architecture::Paper.halo();

    #[test]
    fn the_peak_margin_measures_the_searched_mode_against_the_next_best() {
        let logits = [0.0f32, 5.0, 4.0, 1.0, 3.0, 2.0, 0.0];
        let logit = |d: usize| logits[d];
        // Mode 1; the best ≥ 2 away is 4 (3.0); the floor 0: (5 − 3) / 5.
        assert!((peak_margin(logit, 7, 0) - 0.4).abs() < 1e-6);
        // With three slices of context the mode is 4: the best ≥ 2 away is 1 (5.0): none.
        assert_eq!(peak_margin(logit, 7, 3), 0.0);
        // Scaled logits (the temperature) change nothing; a flat distribution has no peak.
        assert!((peak_margin(|d| 1e4 * logits[d], 7, 0) - 0.4).abs() < 1e-6);
        assert_eq!(peak_margin(|_| 1.0, 10, 0), 0.0);
        assert_eq!(peak_margin(|d| [0.0, 9.0, 1.0][d], 3, 0), 1.0, "nothing 2 slices away");
    }

    #[test]
    fn a_window_keeps_a_second_mode_from_pulling_the_estimate() {
        // Two modes: 70 % around 5 (symmetric), 30 % at 20.
        let p = |d: usize| match d {
            4 | 6 => 0.15f32,
            5 => 0.4,
            20 => 0.3,
            _ => 1e-9,
        };
        let logit = |d: usize| p(d).ln();
        let whole = expected_disparity(logit, 32, None);
        assert!((whole - (0.7 * 5.0 + 0.3 * 20.0)).abs() < 1e-4, "{whole}");
        let windowed = expected_disparity(logit, 32, Some(3));
        assert!((windowed - 5.0).abs() < 1e-4, "{windowed}");
        // A window over the whole range is the soft-argmin; at the edges it is cut.
        assert!((expected_disparity(logit, 32, Some(40)) - whole).abs() < 1e-9);
        let edge = expected_disparity(|d| if d < 2 { 0.0 } else { -30.0 }, 32, Some(1));
        assert!((edge - 0.5).abs() < 1e-6, "{edge}");
    }

    #[test]
    fn refine_takes_the_costs_vertex_within_reach_of_the_networks_integer() {
        // Summed costs with their minimum at m: a parabola for the parabola fit, a V for the
        // equiangular lines; each fit recovers its own shape's vertex exactly.
        type Shape = fn(f64, usize) -> f64;
        let shapes: [(SubpixelFit, Shape); 2] = [
            (SubpixelFit::Parabola, |m, d| (d as f64 - m).powi(2)),
            (SubpixelFit::Equiangular, |m, d| (d as f64 - m).abs()),
        ];
        for (fit, shape) in shapes {
            let at = |m: f64| move |d: usize| shape(m, d);
            let refined = |estimate, m, reach| refined(estimate, at(m), 32, reach, fit, None);
            // The network's integer is the costs' minimum: the vertex, whatever the reach.
            for reach in [0.0, 1.0] {
                assert!((refined(7.0, 7.3, reach) - 7.3).abs() < 1e-9, "{fit:?}");
            }
            // One off (8 for a minimum at 7.3): kept without reach; with reach 1 the vertex at
            // 7.3 is 0.7 px from 8 and taken.
            assert_eq!(refined(8.0, 7.3, 0.0), 8.0);
            assert!((refined(8.0, 7.3, 1.0) - 7.3).abs() < 1e-9, "{fit:?}");
            // Minimum at 6.8: its integer 7 is one off 8, but the vertex is 1.2 px away: kept.
            assert_eq!(refined(8.0, 6.8, 1.0), 8.0);
            assert!((refined(8.0, 6.8, 1.5) - 6.8).abs() < 1e-9, "{fit:?}");
            // Two off: the downhill neighbour is no minimum: kept.
            assert_eq!(refined(9.0, 7.0, 1.0), 9.0);
            // At the range's ends there is no vertex.
            assert_eq!(refined(0.2, 0.0, 1.0), 0.2);
            assert_eq!(refined(31.0, 31.0, 1.0), 31.0);
        }
        // A parabola through a V is pulled towards the integer (pixel locking).
        let v = |d: usize| (d as f64 - 7.3).abs();
        let locked = refined(7.0, v, 32, 0.0, SubpixelFit::Parabola, None);
        assert!((7.05..7.25).contains(&locked), "{locked}");
    }

    #[test]
    fn the_tile_plan_fits_the_budget_and_costs_no_more_than_squares() {
        for (h, w, side) in [
            (540, 960, 296),
            (1080, 1920, 296),
            (372, 428, 64),
            (64, 16, 16),
            (544, 960, 16),
        ] {
            let region = side + 2 * HALO;
            let (rows, columns) = plan_tiles(h, w, region * region, HALO);
            // The cores cover each axis once, in order, on the stride-2 grids (multiples of 4).
            for (tiles, length) in [(&rows, h), (&columns, w)] {
                let covered: Vec<usize> = tiles.iter().flat_map(|(core, _)| core.clone()).collect();
                assert_eq!(covered, (0..length).collect::<Vec<_>>());
                assert!(tiles.iter().all(|(core, _)| core.start % 4 == 0));
            }
            let longest = |t: &AxisTiles| t.iter().map(|(_, r)| r.len()).max().unwrap_or(0);
            assert!(longest(&rows) * longest(&columns) <= region * region, "{h}×{w}");
            let total = |t: &AxisTiles| t.iter().map(|(_, r)| r.len()).sum::<usize>();
            let squares = (axis_tiles(h, side, HALO), axis_tiles(w, side, HALO));
            assert!(
                total(&rows) * total(&columns) <= total(&squares.0) * total(&squares.1),
                "{h}×{w}: the plan computes more than squares of {side}"
            );
        }
        // The demo's 960 × 540 under the default budget: three tiles of whole columns (3 × 2
        // at 192 bytes a voxel and 1 GiB, when the concatenated features were whole).
        let side = tile_side(4, 36, DEFAULT_TILE_BUDGET_BYTES, HALO) + 2 * HALO;
        let (rows, columns) = plan_tiles(540, 960, side * side, HALO);
        assert_eq!((rows.len(), columns.len()), (1, 3));
    }

    #[test]
    fn fused_networks_average_their_logits_and_equal_one_network_alone() {
        let mut a = Network::init(2, 7);
        let mut b = Network::init(2, 8);
        for net in [&mut a, &mut b] {
            for w in &mut net.classify.weight {
                *w *= 40.0;
            }
        }
        let (w, h, nd) = (60, 44, 10);
        let volume = |seed: usize, offset: [i32; 2]| {
            CostVolume::from_fn([w, h, nd], 3, ("v", offset), move |x, y, d| {
                ((x * 7 + y * 3 + d * (11 + seed) + seed * 5 + (x * y + d) % 13) as u8) % 97
            })
        };
        let volumes = [
            volume(0, [-1, 0]),
            volume(1, [1, 0]),
            volume(2, [-2, 0]),
            volume(3, [2, 0]),
        ];
        let refine = Estimate {
            refine: true,
            ..Estimate::default()
        };
        let near = crate::mfusenet::input::summed(&volumes[..2]).unwrap_or_else(|| panic!("one shape"));
        // One member: the single network's answer, refined with the same costs.
        let alone =
            infer_with_confidence(&a, &volumes[..2], usize::MAX, refine, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        let member = |net, inputs| Member {
            net,
            inputs,
            reach: None,
            vote: 1.0,
        };
        let one = infer_fused(&[member(&a, vec![0, 1])], &volumes, &near, usize::MAX, refine, &|_| {})
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(one, alone);
        // Two members: the estimate from the mean of their logits, tiled or not.
        let members = [member(&a, vec![0, 1]), member(&b, vec![2, 3])];
        let fused = infer_fused(&members, &volumes, &near, usize::MAX, Estimate::default(), &|_| {})
            .unwrap_or_else(|e| panic!("{e}"));
        let logits = |net: &Network, v: &[CostVolume<u8>]| {
            let inputs: Vec<Tensor> = v
                .iter()
                .map(|v| super::super::input::to_tensor(v, (0, 0), (h, w), 12))
                .collect();
            net.logits(&inputs).unwrap_or_else(|e| panic!("{e}"))
        };
        let (la, lb) = (logits(&a, &volumes[..2]), logits(&b, &volumes[2..]));
        let plane = h * w;
        for (y, x) in [(0, 0), (20, 31), (43, 59)] {
            let column = |d: usize| 0.5 * (la.data[d * plane + y * w + x] + lb.data[d * plane + y * w + x]);
            let expected = 3.0 + expected_disparity_from(column, nd, 0, None);
            assert!((f64::from(fused.0[y * w + x]) - expected).abs() < 1e-4, "({y}, {x})");
        }
        let differs = |a: &[f32], b: &[f32]| a.iter().zip(b).filter(|(a, b)| (*a - *b).abs() > 0.01).count();
        let first_alone =
            infer(&a, &volumes[..2], usize::MAX, Estimate::default(), &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        assert!(
            differs(&fused.0, &first_alone) > 100,
            "the second network changed nothing"
        );
        let budget = (16 + 2 * HALO).pow(2) * 12 * bytes_per_voxel(2);
        let tiled = infer_fused(&members, &volumes, &near, budget, Estimate::default(), &|_| {})
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(fused.0.iter().zip(&tiled.0).all(|(a, b)| (a - b).abs() < 1e-3));
        // A member whose inputs are not the network's count is refused.
        assert!(infer_fused(&[member(&a, vec![0])], &volumes, &near, usize::MAX, refine, &|_| {}).is_err());
        // The second member voting where its views see: at disparity 3 + d the view at +2
        // baselines reaches x − 2·(3 + d), so from column x it sees d ≤ x/2 − 3. Columns under
        // 6 see nothing (the first member alone); from column 2·(3 + nd) on, everything (the
        // mean of the logits, as without reach); between, its log-probabilities join the first
        // member's where it sees.
        let reach = vec![ValidDisparities::new([2, 0], (w, h), (3, nd), 1.0)];
        let partial = [
            member(&a, vec![0, 1]),
            Member {
                reach: Some(reach),
                ..member(&b, vec![2, 3])
            },
        ];
        let seen = infer_fused(&partial, &volumes, &near, usize::MAX, Estimate::default(), &|_| {})
            .unwrap_or_else(|e| panic!("{e}"));
        let log_probabilities = |l: &Tensor, y: usize, x: usize| {
            let column: Vec<f32> = (0..nd).map(|d| l.data[d * plane + y * w + x]).collect();
            let max = column.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let norm = max + column.iter().map(|v| (v - max).exp()).sum::<f32>().ln();
            column.into_iter().map(move |v| v - norm)
        };
        for (y, x) in [(0, 0), (20, 5), (7, 11), (30, 14), (43, 26), (10, 59)] {
            let (pa, pb): (Vec<f32>, Vec<f32>) = (
                log_probabilities(&la, y, x).collect(),
                log_probabilities(&lb, y, x).collect(),
            );
            let column = |d: usize| {
                if 2 * (3 + d) <= x { 0.5 * (pa[d] + pb[d]) } else { pa[d] }
            };
            let expected = 3.0 + expected_disparity_from(column, nd, 0, None);
            assert!((f64::from(seen.0[y * w + x]) - expected).abs() < 1e-4, "({y}, {x})");
            if x < 6 {
                assert!((seen.0[y * w + x] - first_alone[y * w + x]).abs() < 1e-4, "({y}, {x})");
            }
            if x >= 2 * (3 + nd) {
                assert!((seen.0[y * w + x] - fused.0[y * w + x]).abs() < 1e-4, "({y}, {x})");
            }
        }
        // The second member at a quarter of the first's vote: where it sees, each disparity's
        // log-probability is (pa + pb / 4) / (1 + 1 / 4); elsewhere the first member's alone.
        let [near_member, far_member] = partial;
        let quieter = [
            near_member,
            Member {
                vote: 0.25,
                ..far_member
            },
        ];
        let weighted = infer_fused(&quieter, &volumes, &near, usize::MAX, Estimate::default(), &|_| {})
            .unwrap_or_else(|e| panic!("{e}"));
        for (y, x) in [(0, 0), (20, 5), (7, 11), (30, 14), (43, 26), (10, 59)] {
            let (pa, pb): (Vec<f32>, Vec<f32>) = (
                log_probabilities(&la, y, x).collect(),
                log_probabilities(&lb, y, x).collect(),
            );
            let column = |d: usize| {
                if 2 * (3 + d) <= x {
                    (pa[d] + 0.25 * pb[d]) / 1.25
                } else {
                    pa[d]
                }
            };
            let expected = 3.0 + expected_disparity_from(column, nd, 0, None);
            assert!((f64::from(weighted.0[y * w + x]) - expected).abs() < 1e-4, "({y}, {x})");
        }
        assert!(differs(&weighted.0, &seen.0) > 10, "the smaller vote changed nothing");
    }

    /// The largest difference (px) between `whole` and the network run in tiles under `budget`.
    fn worst_tiled_difference(net: &Network, volumes: &[CostVolume<u8>], budget: usize, whole: &[f32]) -> f32 {
        let tiled = infer(net, volumes, budget, Estimate::default(), &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        whole
            .iter()
            .zip(&tiled)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max)
    }

    #[test]
    fn tiled_inference_equals_the_whole_image() {
        let mut net = Network::init(2, 7);
        // A peaked softmax, so that the disparity depends on every layer (as in the fixtures).
        for w in &mut net.classify.weight {
            *w *= 400.0;
        }
        // Odd sizes: every axis needs padding; 150 × 129 px cut into tiles whose regions hold
        // at most 112 × 112 px (16-px squares with their halo).
        let (w, h, nd) = (150, 129, 10);
        let volume = |seed: usize| {
            let (role, offset) = if seed == 0 {
                ("left", [-1, 0])
            } else {
                ("right", [1, 0])
            };
            CostVolume::from_fn([w, h, nd], 3, (role, offset), |x, y, d| {
                let i = (y * w + x) * nd + d;
                ((x * 7 + y * 3 + d * (11 + seed) + seed * 5 + (i * i) % 13) as u8) % 97
            })
        };
        let volumes = [volume(0), volume(1)];
        let whole = infer(&net, &volumes, usize::MAX, Estimate::default(), &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        let budget = (16 + 2 * HALO).pow(2) * 12 * bytes_per_voxel(2);
        assert_eq!(tile_side(2, nd, budget, HALO), 16);
        let (rows, columns) = plan_tiles(132, 152, (16 + 2 * HALO).pow(2), HALO);
        assert!(rows.len() * columns.len() > 1, "the test must cut tiles");
        let worst = worst_tiled_difference(&net, &volumes, budget, &whole);
        assert!(worst < 1e-3, "tiled differs by {worst} px");
        // With test-time flips too: each haloed tile's mirror is the mirrored image's tile.
        let flips = Estimate {
            flips: true,
            ..Estimate::default()
        };
        let whole_flipped = infer(&net, &volumes, usize::MAX, flips, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        let tiled_flipped = infer(&net, &volumes, budget, flips, &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        let worst = whole_flipped
            .iter()
            .zip(&tiled_flipped)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-3, "tiled with flips differs by {worst} px");
        assert!(whole_flipped != whole, "the flips changed nothing");
        assert!(whole.iter().all(|d| (3.0..=12.0).contains(d)));
        // Not constant: the test would pass trivially on a flat output.
        let spread = whole.iter().fold(0f32, |m, d| m.max(*d)) - whole.iter().fold(f32::MAX, |m, d| m.min(*d));
        assert!(spread > 0.1, "spread {spread}");
        // Slices kept as context are never the most probable answer: with 5 of them, every mode
        // (a window of 0) is ≥ 3 + 5 (the whole range's are not); the distribution around it
        // reaches into them.
        let mode = |context_below| Estimate {
            context_below,
            window: Some(0),
            ..Estimate::default()
        };
        let modes = infer(&net, &volumes, usize::MAX, mode(0), &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        let lowest = modes.iter().fold(f32::MAX, |m, d| m.min(*d));
        assert!(lowest < 7.5, "lowest {lowest}");
        let read = infer(&net, &volumes, usize::MAX, mode(5), &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        assert!(read.iter().all(|d| (8.0..=12.0).contains(d)));
        let context = Estimate {
            context_below: 5,
            ..Estimate::default()
        };
        let error = infer(
            &net,
            &volumes,
            usize::MAX,
            Estimate {
                context_below: nd,
                ..context
            },
            &|_| {},
        )
        .err();
        assert!(
            matches!(
                error,
                Some(Error::ContextBelow {
                    context_below: 10,
                    num_disparities: 10
                })
            ),
            "{error:?}"
        );
    }

    #[test]
    fn the_lite_network_tiled_with_its_own_smaller_halo_equals_the_whole_image() {
        let halo = Architecture::Lite.halo();
        assert!(halo < HALO);
        let mut net = Network::init_with(2, Architecture::Lite, 9);
        // Weights that carry far context into every output (PyTorch's initialisation damps it
        // below f32's resolution within the halo of the paper's network) and a soft softmax, so
        // that a halo too small changes the disparities.
        for layer in net.feature.iter_mut().chain(net.fuse.iter_mut()) {
            for w in &mut layer.weight {
                *w *= 3.0;
            }
        }
        for w in &mut net.classify.weight {
            *w *= 40.0;
        }
        let (w, h, nd) = (150, 129, 10);
        let volumes: Vec<_> = [("left", [-1, 0]), ("right", [1, 0])]
            .into_iter()
            .enumerate()
            .map(|(seed, (role, offset))| {
                CostVolume::from_fn([w, h, nd], 3, (role, offset), |x, y, d| {
                    let i = (y * w + x) * nd + d;
                    ((x * 5 + y * 7 + d * (13 + seed) + seed * 3 + (i * i) % 11) as u8) % 89
                })
            })
            .collect();
        let whole = infer(&net, &volumes, usize::MAX, Estimate::default(), &|_| {}).unwrap_or_else(|e| panic!("{e}"));
        let budget = (16 + 2 * halo).pow(2) * 12 * bytes_per_voxel(2);
        assert!(tiles((w, h, nd), 2, budget, halo).len() > 1, "the test must cut tiles");
        let worst = worst_tiled_difference(&net, &volumes, budget, &whole);
        // Bit for bit: every output's sums run in the same order whole or tiled, and the halo
        // holds all that reaches it (4 px less moves outputs by up to 0.007 px, 12 px less 0.35 px).
        assert!(worst == 0.0, "tiled differs by {worst} px");
        let spread = whole.iter().fold(0f32, |m, d| m.max(*d)) - whole.iter().fold(f32::MAX, |m, d| m.min(*d));
        assert!(spread > 0.01, "spread {spread}");
    }

    #[test]
    fn flips_make_the_network_answer_a_mirrored_set_mirrored() {
        // Sizes that need no padding, so that the mirror image's padding is the original's.
        let (w, h, nd) = (40, 24, 12);
        let volume = |seed: usize, offset: [i32; 2]| {
            CostVolume::from_fn([w, h, nd], 2, (&format!("{offset:?}"), offset), |x, y, d| {
                let i = (y * w + x) * nd + d;
                ((x * 7 + y * 3 * (seed + 1) + d * (11 + seed) + seed * 5 + (i * i) % 13) as u8) % 97
            })
        };
        // The volume seen in a mirror, `[y][x][d]` layout.
        let flip = |v: &CostVolume<u8>, vertical: bool, horizontal: bool| {
            let mut out = v.clone();
            for y in 0..h {
                for x in 0..w {
                    let (sy, sx) = (
                        if vertical { h - 1 - y } else { y },
                        if horizontal { w - 1 - x } else { x },
                    );
                    out.data[(y * w + x) * nd..][..nd].copy_from_slice(v.costs(sx, sy));
                }
            }
            out
        };
        let (right, left, top, bottom) = ([1, 0], [-1, 0], [0, -1], [0, 1]);
        // A right neighbour alone mirrors top to bottom, a top/bottom pair top to bottom with a
        // swap, a left/right pair and the cross left to right with one.
        type Rig<'a> = (&'a [[i32; 2]], (bool, bool));
        let rigs: [Rig; 4] = [
            (&[right], (true, false)),
            (&[left, right], (false, true)),
            (&[top, bottom], (true, false)),
            (&[left, right, top, bottom], (false, true)),
        ];
        for (offsets, axes) in rigs {
            let views = offsets.len();
            assert_eq!(flip_axes(offsets), Some(axes), "{offsets:?}");
            let (vertical, horizontal) = axes;
            let mut net = Network::init(views, 11);
            for weight in &mut net.classify.weight {
                *weight *= 400.0;
            }
            let volumes: Vec<CostVolume<u8>> = offsets.iter().enumerate().map(|(i, o)| volume(i, *o)).collect();
            // The mirrored rig: each slot holds its mirrored neighbour's volume, flipped, and
            // keeps its own offset.
            let order = super::super::input::mirror_order(offsets, vertical, horizontal).unwrap_or_default();
            let seen: Vec<CostVolume<u8>> = order
                .iter()
                .zip(&volumes)
                .map(|(&i, slot)| CostVolume {
                    source: slot.source.clone(),
                    ..flip(&volumes[i], vertical, horizontal)
                })
                .collect();
            for refine in [false, true] {
                let run = |volumes: &[CostVolume<u8>], flips: bool| {
                    let estimate = Estimate {
                        refine,
                        flips,
                        ..Estimate::default()
                    };
                    infer(&net, volumes, usize::MAX, estimate, &|_| {}).unwrap_or_else(|e| panic!("{e}"))
                };
                let worst = |a: &[f32], b: &[f32]| {
                    let mut worst = 0f32;
                    for y in 0..h {
                        for x in 0..w {
                            let (sy, sx) = (
                                if vertical { h - 1 - y } else { y },
                                if horizontal { w - 1 - x } else { x },
                            );
                            worst = worst.max((a[y * w + x] - b[sy * w + sx]).abs());
                        }
                    }
                    worst
                };
                let symmetric = worst(&run(&seen, true), &run(&volumes, true));
                assert!(symmetric < 1e-4, "{offsets:?}, refine {refine}: {symmetric} px");
                // The network alone is not symmetric: without flips the mirror answers otherwise.
                let plain = worst(&run(&seen, false), &run(&volumes, false));
                assert!(plain > 0.01, "{offsets:?}, refine {refine}: only {plain} px");
            }
        }
        // Right and bottom: no mirror maps the pair onto itself.
        let net = Network::init(2, 11);
        let error = infer(
            &net,
            &[volume(0, right), volume(1, bottom)],
            usize::MAX,
            Estimate {
                flips: true,
                ..Estimate::default()
            },
            &|_| {},
        )
        .err();
        assert!(
            matches!(&error, Some(Error::NoMirror { offsets }) if offsets == &[right, bottom]),
            "{error:?}"
        );
    }
}
