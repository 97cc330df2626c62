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
//! 8-neighbour was moved to within a pixel of it as well (a part is a line of pixels, noise is
//! isolated). The costs it reads are each pixel's averaged over an adaptive cross-shaped support
//! of like-coloured pixels ([`CrossSupport`], the default): a rod's pixels vote together along
//! the rod, never with the background beside it, so its minimum is clear where one pixel's
//! Birchfield–Tomasi curve has several (the thin family's Bad1 6.57 → 6.29 %, and a periodic
//! texture that the network read at its alias, `random` seed 8's line, 0.581 → 0.237 px;
//! docs/experiments.md). Last, a patch of moves stays only if it is shaped like a part, long
//! and thin ([`ThinParts::min_length_px`], [`ThinParts::max_width_px`]): chance matches of the
//! per-pixel costs come in small or spread patches, which is what let the tests be loose enough
//! to bring back most rods (the thin family's Bad1 6.38 → 5.84 %). Farther moves too
//! ([`ThinParts::farther`]): the background seen through gaps between slats, which the estimate
//! fills with the slats' disparity. Mirror-like metal shows reflections at farther disparities
//! as well, and two tests tell them apart: the farther disparity must be one the estimate holds
//! within [`ThinParts::farther_seen_px`] (the background through a gap is the surface seen around
//! the parts; a reflection lies at a depth no real surface near it has), and a patch of farther
//! moves must not border a region already at its disparity along more than
//! [`ThinParts::farther_max_extension`] of its border (a gap meets the background only at its
//! ends; moves that widen a mis-estimated mirror region border it along their length). The
//! thin family's Bad1 5.15 → 4.74 %, its unseen seeds 5–8 6.53 → 5.29 %; the reflective
//! workpiece lines within 1 % (farther moves without the two tests: +4 to +8 %; docs/experiments.md).

use std::ops::Range;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::{INVALID_COST, PixelCost};
use crate::fusion::Fusion;
use crate::image::{DisparityImage, Image};
use crate::volume::{BandScratch, CostSpec, PreparedProblem, Problem};
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
    /// … and at most this share of the lowest cost farther than ±1 from the new disparity (a
    /// clear minimum: a mirror's chance matches have rivals, so the shape test can be looser).
    pub uniqueness: f32,
    /// … and lower than the cost at the estimate by at least this much (cost levels, for colour
    /// views the channels' halves summed, about 1.5 grey levels of their mean: flat regions,
    /// where every cost is noise, never move).
    pub min_margin: f32,
    /// How many of the 8 neighbours must move to within 1 px of the pixel's new disparity.
    pub min_support: usize,
    /// Also move pixels farther: the background seen through a gap between parts (slats, a
    /// grid) that the estimate filled with the parts' disparity.
    pub farther: bool,
    /// The fewest neighbours it runs with: one view's per-pixel costs cannot tell a part from a
    /// chance match (the stereo network on Middlebury: RMS 1.089 → 1.185 px with one).
    pub min_views: usize,
    /// Read each pixel's costs averaged over a cross-shaped support of like-coloured pixels
    /// ([`CrossSupport`]; `null` = the pixel's own costs): a rod's or a gap's pixels vote
    /// together along it, so its minimum is clear where one pixel's is noise.
    pub cross_support: Option<CrossSupport>,
    /// With `farther`, a pixel moves farther only to a disparity no farther than the farthest
    /// estimate within this radius (px) by more than a pixel: the background seen through a
    /// gap is seen beside the parts too, a mirror's reflection lies behind every real surface.
    /// 0 = no such guard.
    pub farther_guard_px: usize,
    /// With `farther`, a pixel moves farther only to a disparity that the estimate holds
    /// (within a slice of its rounded value) somewhere within this reach (px; a square, rounded
    /// up to whole cells of 4 × 4 px): the background seen through a gap between parts is the
    /// surface seen around them, while a mirror's reflection lies at a depth no real surface
    /// near it has. 0 = no such test.
    pub farther_seen_px: usize,
    /// With `farther`, the largest share of a patch of farther moves' border whose estimate
    /// already lies within a pixel of the patch: a gap's background is flanked by the parts
    /// (nearer) and meets the surface seen around them only at its ends, while moves that only
    /// widen a region the estimate already holds at that disparity (a mirror's reflection
    /// creeping over the mirror's frame) border it along their length. A gap `W` px wide and
    /// `L` long meets the background over about `(W + 2) / (L + W + 2)` of its border, so 0.15
    /// keeps gaps longer than about 4.7 `W` + 9 px (a 4 px gap: 28 px). 1 = no such test.
    pub farther_max_extension: f32,
    /// The shape test (`min_length_px`, `max_width_px`) for farther moves too. Without it
    /// (`false`) the occluded strips beside near boards and wide gaps come back as well (the
    /// thin family 0.516 → 0.505 px, Middlebury 0.285 → 0.281 px), but so does more of a
    /// mirror's reflection (the workpiece lines +3.3 and +3.5 %; docs/experiments.md).
    pub farther_shape_test: bool,
    /// The shortest part (px) a move may belong to: moves whose connected patch (8-neighbours
    /// moved to within a pixel of each other) spans fewer pixels than this both across and down
    /// the image are undone. A lost rod, wire or slat is a long line; a chance match of the
    /// per-pixel costs is a small blob. 0 = no limit.
    pub min_length_px: usize,
    /// The widest a patch of moves may be on average (px: its pixels over the diagonal of its
    /// bounding box): a lost part is thin, chance matches over a textured surface spread (a
    /// periodic texture's alias). 0 = no limit.
    pub max_width_px: f32,
    /// A patch shorter than `min_length_px` but spanning at least this many pixels across or down
    /// stays when it is slender: its mean width (pixels over its bounding box's diagonal) at
    /// most its diagonal over `slender_ratio` (an 8 px patch 2 px wide, a 12 px one 3 px wide).
    /// The short pieces of a rod or a wire that the network read only in part are slender;
    /// a mirror's chance matches of that length are blobs. 0 = none.
    pub min_slender_length_px: usize,
    /// How many times its mean width a short patch must be long to stay (see
    /// `min_slender_length_px`).
    pub slender_ratio: f32,
}

/// Adaptive cross-shaped support (Zhang, Lu and Lafruit 2009, as in AD-Census): each pixel's
/// arms reach left, right, up and down while the reference's colour stays within
/// `colour_threshold` of the pixel's (largest channel difference) and for at most `arm_px`
/// pixels; its support is the union of the horizontal arms of the pixels on its vertical arm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CrossSupport {
    /// Longest arm (px; at most [`MAX_ARM_PX`], larger values are taken as that).
    pub arm_px: usize,
    /// Largest colour difference (grey levels) along an arm.
    pub colour_threshold: u8,
}

impl Default for CrossSupport {
    fn default() -> Self {
        Self {
            arm_px: 17,
            colour_threshold: 20,
        }
    }
}

impl Default for ThinParts {
    fn default() -> Self {
        Self {
            min_jump_px: 2.0,
            ratio: 0.8,
            uniqueness: 0.75,
            min_margin: 1.0,
            min_support: 1,
            farther: true,
            min_views: 2,
            cross_support: Some(CrossSupport::default()),
            farther_guard_px: 0,
            farther_seen_px: 32,
            farther_max_extension: 0.15,
            farther_shape_test: true,
            min_length_px: 20,
            max_width_px: 8.0,
            min_slender_length_px: 6,
            slender_ratio: 4.0,
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
    let arms = match config.cross_support {
        Some(support) => Arms::new(&problem.reference, support),
        None => Arms::own(w, h),
    };
    // Rows per chunk of work: each chunk streams its rows through a ring of support sums and
    // makes the costs of `arm_px` rows beyond its ends again (`chunk_rows`).
    let chunk = chunk_rows(h, arms.longest);
    // The farthest estimate near each pixel (slices from the range's start), for the guard.
    let farthest_near = (config.farther && config.farther_guard_px > 0).then(|| {
        let slices: Vec<f32> = disparity.data.iter().map(|d| d - min).collect();
        window_min(&slices, w, h, config.farther_guard_px)
    });
    // The disparities estimated near each pixel, for the test that a farther move goes to one.
    let seen_near = (config.farther && config.farther_seen_px > 0)
        .then(|| SeenNear::new(&disparity.data, (w, h, nd), min, config.farther_seen_px));
    // Each pixel's candidate (the new disparity, its confidence), NaN where none.
    let mut candidates = vec![(f32::NAN, 0.0f32); w * h];
    candidates
        .par_chunks_mut(chunk * w)
        .zip(disparity.data.par_chunks(chunk * w))
        .enumerate()
        .for_each_init(SupportCurves::default, |curves, (index, (out, estimates))| {
            let start = index * chunk;
            let rows = start..start + out.len() / w;
            curves.stream(&heuristic, &mean, rows, &arms, &mut |y, costs, seen_by_all| {
                let row = (y - start) * w;
                let at = |x: usize| &costs[x * nd..(x + 1) * nd];
                let all = |x: usize| &seen_by_all[x * nd..(x + 1) * nd];
                for (x, (candidate, estimate)) in out[row..row + w].iter_mut().zip(&estimates[row..row + w]).enumerate()
                {
                    let farthest = farthest_near.as_ref().map_or(f32::NEG_INFINITY, |f| f[y * w + x]);
                    let seen = |slice: usize| seen_near.as_ref().is_none_or(|s| s.holds(y * w + x, slice));
                    if let Some(found) = candidate_of(*estimate - min, at(x), all(x), (farthest, &seen), config) {
                        *candidate = (found.0 + min, found.1);
                    }
                }
            });
        });
    let mut supported: Vec<bool> = (0..w * h)
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
    if config.min_length_px > 0 || config.max_width_px > 0.0 {
        let moved_to: Vec<f32> = supported
            .iter()
            .zip(&candidates)
            .zip(&disparity.data)
            .map(|((&keep, c), &d)| {
                if keep && (config.farther_shape_test || c.0 > d) {
                    c.0
                } else {
                    f32::NAN
                }
            })
            .collect();
        for (keep, unlike) in supported
            .iter_mut()
            .zip(unlike_parts(&moved_to, (w, h), &PartShape::of(config)))
        {
            *keep &= !unlike;
        }
    }
    if config.farther && config.farther_max_extension < 1.0 {
        let moved_to: Vec<f32> = supported
            .iter()
            .zip(&candidates)
            .zip(&disparity.data)
            .map(|((&keep, c), &d)| if keep && c.0 < d { c.0 } else { f32::NAN })
            .collect();
        for (keep, widens) in supported.iter_mut().zip(extensions(
            &moved_to,
            &disparity.data,
            w,
            h,
            config.farther_max_extension,
        )) {
            *keep &= !widens;
        }
    }
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

/// Rows per chunk of work for an image `height` rows high whose supports reach `reach` rows:
/// two chunks per worker, each making the costs of `2·reach` rows of its neighbours again (at
/// 1080p with arms of 17 px and two workers: 270 rows, 13 % more costs).
fn chunk_rows(height: usize, reach: usize) -> usize {
    height
        .div_ceil(2 * rayon::current_num_threads().max(1))
        .max(MIN_CHUNK_ROWS.max(2 * reach))
}

/// Fewest rows per chunk of [`recover_thin_parts`]'s work.
const MIN_CHUNK_ROWS: usize = 16;

/// Rows of fused costs made at a time.
const COST_BATCH_ROWS: usize = 8;

/// One worker's per-pixel cost curves (`[x][d]` per row, `f32::INFINITY` where a view's
/// correspondence leaves the image), the heuristic fusion's and the mean over every view, each
/// pixel's costs averaged over its support ([`Arms`]; its own costs where the arms are empty).
/// The rows stream through a ring of support sums: the memory is `2·reach + 2` rows of sums
/// whatever the chunk's height (at 1080p with 128 disparities and arms of 17 px, 55 MB per
/// fusion), and every row's costs are made once per chunk.
#[derive(Debug, Default)]
struct SupportCurves {
    rings: [SupportRing; 2],
    /// A batch of rows' fused costs, per fusion.
    costs: [Vec<u16>; 2],
    buffers: BandScratch,
    /// The emitted row's curves, per fusion.
    curves: [Vec<f32>; 2],
}

/// Receives a row's curves: `(y, heuristic, mean)`, each `[x][d]`.
type EmitRow<'a> = dyn FnMut(usize, &[f32], &[f32]) + 'a;

/// The support sums of the last rows of one fusion's costs.
#[derive(Debug, Default)]
struct SupportRing {
    /// Each row's sums over every pixel's horizontal arm, cumulative (wrapping) down the rows
    /// from the first row pushed; row `r` in slot `r % slots`.
    sums: Vec<u32>,
    /// The same for the counts of valid costs.
    counts: Vec<u16>,
    slots: usize,
    /// One row's prefix sums and counts along `x`.
    prefix_sums: Vec<u32>,
    prefix_counts: Vec<u16>,
}

impl SupportCurves {
    /// Calls `emit(y, heuristic, mean)` with the curves of each row of `rows`, in order: rows
    /// `[x][d]` of `heuristic`'s and of `mean`'s fused costs averaged over each pixel's support.
    fn stream(
        &mut self,
        heuristic: &PreparedProblem,
        mean: &PreparedProblem,
        rows: Range<usize>,
        arms: &Arms,
        emit: &mut EmitRow<'_>,
    ) {
        let (w, h, nd) = (heuristic.width(), heuristic.height(), heuristic.num_disparities());
        let reach = arms.longest;
        if rows.is_empty() {
            return;
        }
        // Every row a support of `rows` reaches, each pushed once; row `y` is emitted once the
        // last row its support reaches is in (`y + reach`, or the image's last).
        let halo = rows.start.saturating_sub(reach)..(rows.end + reach).min(h);
        for ring in &mut self.rings {
            ring.reset(w * nd, 2 * reach + 2);
        }
        for curve in &mut self.curves {
            curve.clear();
            curve.resize(w * nd, f32::INFINITY);
        }
        let row_cells = w * nd;
        for batch_start in halo.clone().step_by(COST_BATCH_ROWS) {
            let batch = batch_start..(batch_start + COST_BATCH_ROWS).min(halo.end);
            for (problem, costs) in [heuristic, mean].into_iter().zip(&mut self.costs) {
                costs.clear();
                costs.resize(batch.len() * row_cells, 0);
                problem.fused_band_into(batch.clone(), costs, &mut self.buffers);
            }
            for (b, pushed) in batch.enumerate() {
                if reach == 0 {
                    // Each pixel's own costs: no sums to keep.
                    for (curve, costs) in self.curves.iter_mut().zip(&self.costs) {
                        for (value, &c) in curve.iter_mut().zip(&costs[b * row_cells..(b + 1) * row_cells]) {
                            *value = if c == INVALID_COST { f32::INFINITY } else { f32::from(c) };
                        }
                    }
                    emit(pushed, &self.curves[0], &self.curves[1]);
                    continue;
                }
                for (ring, costs) in self.rings.iter_mut().zip(&self.costs) {
                    ring.push(
                        pushed - halo.start,
                        pushed,
                        &costs[b * row_cells..(b + 1) * row_cells],
                        arms,
                        nd,
                    );
                }
                let ready = if pushed + 1 == h {
                    pushed.saturating_sub(reach).max(rows.start)..rows.end
                } else {
                    let y = pushed.wrapping_sub(reach);
                    if pushed >= reach && rows.contains(&y) {
                        y..y + 1
                    } else {
                        0..0
                    }
                };
                for y in ready {
                    for (ring, curve) in self.rings.iter().zip(&mut self.curves) {
                        ring.curve_row(y, halo.start, arms, nd, curve);
                    }
                    emit(y, &self.curves[0], &self.curves[1]);
                }
            }
        }
    }
}

impl SupportRing {
    fn reset(&mut self, row_cells: usize, slots: usize) {
        self.slots = slots;
        self.sums.clear();
        self.sums.resize(slots * row_cells, 0);
        self.counts.clear();
        self.counts.resize(slots * row_cells, 0);
    }

    /// Adds row `y` (the `r`-th pushed) of costs `[x][d]`: its sums over each pixel's
    /// horizontal arm, plus the cumulative sums of the row before.
    fn push(&mut self, r: usize, y: usize, costs: &[u16], arms: &Arms, nd: usize) {
        let w = costs.len() / nd;
        let row_cells = w * nd;
        self.prefix_sums.resize((w + 1) * nd, 0);
        self.prefix_counts.resize((w + 1) * nd, 0);
        self.prefix_sums[..nd].fill(0);
        self.prefix_counts[..nd].fill(0);
        for x in 0..w {
            let (done, next) = self.prefix_sums.split_at_mut((x + 1) * nd);
            let (done_counts, next_counts) = self.prefix_counts.split_at_mut((x + 1) * nd);
            let cells = next[..nd]
                .iter_mut()
                .zip(&mut next_counts[..nd])
                .zip(done[x * nd..].iter().zip(&done_counts[x * nd..]))
                .zip(&costs[x * nd..(x + 1) * nd]);
            for (((sum, count), (previous, previous_count)), &c) in cells {
                let valid = c != INVALID_COST;
                *sum = previous.wrapping_add(if valid { u32::from(c) } else { 0 });
                *count = previous_count.wrapping_add(u16::from(valid));
            }
        }
        let slot = r % self.slots;
        let above = (r > 0).then(|| (r - 1) % self.slots);
        let (sums, counts) = (&mut self.sums, &mut self.counts);
        for x in 0..w {
            let (left, right) = (x - arms.left_of(x, y), x + arms.right_of(x, y) + 1);
            let cell = (slot * w + x) * nd;
            let (to, from) = (
                &self.prefix_sums[right * nd..][..nd],
                &self.prefix_sums[left * nd..][..nd],
            );
            for d in 0..nd {
                sums[cell + d] = to[d].wrapping_sub(from[d]);
            }
            let (to, from) = (
                &self.prefix_counts[right * nd..][..nd],
                &self.prefix_counts[left * nd..][..nd],
            );
            for d in 0..nd {
                counts[cell + d] = to[d].wrapping_sub(from[d]);
            }
        }
        if let Some(above) = above {
            let (this, previous) = (slot * row_cells, above * row_cells);
            for i in 0..row_cells {
                sums[this + i] = sums[this + i].wrapping_add(sums[previous + i]);
                counts[this + i] = counts[this + i].wrapping_add(counts[previous + i]);
            }
        }
    }

    /// Row `y`'s curves into `out` (`[x][d]`): each pixel's sums over the rows of its vertical
    /// arm (those down to `bottom` less those down to the row above `top`), divided by their
    /// counts; `first` is the image row pushed first.
    fn curve_row(&self, y: usize, first: usize, arms: &Arms, nd: usize, out: &mut [f32]) {
        let w = out.len() / nd;
        let cell = |row: usize, x: usize| ((row % self.slots) * w + x) * nd;
        for (x, curve) in out.chunks_exact_mut(nd).enumerate() {
            let top = y - arms.up_of(x, y) - first;
            let bottom = y + arms.down_of(x, y) - first;
            let (sums, counts) = (
                &self.sums[cell(bottom, x)..][..nd],
                &self.counts[cell(bottom, x)..][..nd],
            );
            let average = |value: &mut f32, sum: u32, count: u16| {
                *value = if count > 0 {
                    sum as f32 / f32::from(count)
                } else {
                    f32::INFINITY
                };
            };
            if top > 0 {
                let (above, above_counts) = (
                    &self.sums[cell(top - 1, x)..][..nd],
                    &self.counts[cell(top - 1, x)..][..nd],
                );
                let terms = curve
                    .iter_mut()
                    .zip(sums.iter().zip(counts))
                    .zip(above.iter().zip(above_counts));
                for ((value, (sum, count)), (above, above_count)) in terms {
                    average(value, sum.wrapping_sub(*above), count.wrapping_sub(*above_count));
                }
            } else {
                for (value, (sum, count)) in curve.iter_mut().zip(sums.iter().zip(counts)) {
                    average(value, *sum, *count);
                }
            }
        }
    }
}

/// The longest arm [`CrossSupport`] takes: a support's count of valid costs (`u16`) then stays
/// below 2¹⁶ (65 × 65 pixels).
pub const MAX_ARM_PX: usize = 32;

/// Each pixel's arms ([`CrossSupport`]) in the reference image: `[left, right, up, down]` (px).
struct Arms {
    width: usize,
    arms: Vec<[u8; 4]>,
    /// The longest arm allowed: how far a support reaches.
    longest: usize,
}

impl Arms {
    fn new(reference: &Image, support: CrossSupport) -> Self {
        let (w, h, channels) = (reference.width, reference.height, reference.channels);
        let longest = support.arm_px.min(MAX_ARM_PX);
        let pixel = |x: usize, y: usize| &reference.data[(y * w + x) * channels..(y * w + x + 1) * channels];
        let alike = |a: &[u8], b: &[u8]| a.iter().zip(b).all(|(p, q)| p.abs_diff(*q) <= support.colour_threshold);
        let arms = (0..w * h)
            .into_par_iter()
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let anchor = pixel(x, y);
                let reach = |steps: usize, at: &dyn Fn(usize) -> (usize, usize)| {
                    (1..=steps.min(longest))
                        .take_while(|&k| {
                            let (qx, qy) = at(k);
                            alike(pixel(qx, qy), anchor)
                        })
                        .count() as u8
                };
                [
                    reach(x, &|k| (x - k, y)),
                    reach(w - 1 - x, &|k| (x + k, y)),
                    reach(y, &|k| (x, y - k)),
                    reach(h - 1 - y, &|k| (x, y + k)),
                ]
            })
            .collect();
        Self {
            width: w,
            arms,
            longest,
        }
    }

    /// Empty arms: each pixel's own costs.
    fn own(width: usize, height: usize) -> Self {
        Self {
            width,
            arms: vec![[0; 4]; width * height],
            longest: 0,
        }
    }

    fn left_of(&self, x: usize, y: usize) -> usize {
        usize::from(self.arms[y * self.width + x][0])
    }

    fn right_of(&self, x: usize, y: usize) -> usize {
        usize::from(self.arms[y * self.width + x][1])
    }

    fn up_of(&self, x: usize, y: usize) -> usize {
        usize::from(self.arms[y * self.width + x][2])
    }

    fn down_of(&self, x: usize, y: usize) -> usize {
        usize::from(self.arms[y * self.width + x][3])
    }
}

/// Which disparities an estimate holds near each pixel: a bit per bin of `bin` slices (at most
/// 128 bins) per cell of [`SEEN_CELL_PX`]² pixels, each cell's the OR over the cells within a
/// radius of it (two running passes), so that a 1080p image's sets take 2 MB.
struct SeenNear {
    bits: Vec<u128>,
    /// The image's width and the cells' grid width.
    width: usize,
    cells_across: usize,
    bin: usize,
    bins: usize,
}

/// The side (px) of [`SeenNear`]'s cells.
const SEEN_CELL_PX: usize = 4;

impl SeenNear {
    /// From `disparity` (`w × h`, non-finite = none) over `nd` slices from `min`: a pixel's
    /// window is every cell within `radius` px (rounded up to whole cells) of its own cell.
    fn new(disparity: &[f32], (w, h, nd): (usize, usize, usize), min: f32, radius: usize) -> Self {
        let bin = nd.div_ceil(128).max(1);
        let bins = nd.div_ceil(bin);
        let (cw, ch) = (w.div_ceil(SEEN_CELL_PX), h.div_ceil(SEEN_CELL_PX));
        let mut own = vec![0u128; cw * ch];
        for (i, d) in disparity.iter().enumerate() {
            let slice = (d - min).round();
            if slice.is_finite() && slice >= 0.0 && (slice as usize) < nd {
                let (x, y) = (i % w / SEEN_CELL_PX, i / w / SEEN_CELL_PX);
                own[y * cw + x] |= 1u128 << (slice as usize / bin);
            }
        }
        Self {
            bits: window_or(&own, cw, ch, radius.div_ceil(SEEN_CELL_PX)),
            width: w,
            cells_across: cw,
            bin,
            bins,
        }
    }

    /// Pixel `i`'s window holds an estimate within a slice of `slice` (within a bin, where bins
    /// are wider than a slice).
    fn holds(&self, i: usize, slice: usize) -> bool {
        let (lo, hi) = (
            slice.saturating_sub(1) / self.bin,
            ((slice + 1) / self.bin).min(self.bins - 1),
        );
        let mask = if hi - lo >= 127 {
            u128::MAX
        } else {
            ((1u128 << (hi - lo + 1)) - 1) << lo
        };
        let (x, y) = (i % self.width / SEEN_CELL_PX, i / self.width / SEEN_CELL_PX);
        self.bits[y * self.cells_across + x] & mask != 0
    }
}

/// The OR of `values` (`w × h`) over the square window within `radius` of each pixel.
fn window_or(values: &[u128], w: usize, h: usize, radius: usize) -> Vec<u128> {
    window_reduce(values, w, h, radius, 0, |a, b| a | b)
}

/// The smallest finite value of `values` (`w × h`) within `radius` of each pixel (a square
/// window; `f32::INFINITY` where there is none): two passes of a running minimum.
pub(crate) fn window_min(values: &[f32], w: usize, h: usize, radius: usize) -> Vec<f32> {
    let finite: Vec<f32> = values
        .iter()
        .map(|&v| if v.is_finite() { v } else { f32::INFINITY })
        .collect();
    window_reduce(&finite, w, h, radius, f32::INFINITY, f32::min)
}

/// `op` (associative, commutative, idempotent: a minimum, an OR) of `values` (`w × h`) over the
/// square window within `radius` of each pixel, `identity` its neutral value: a running pass
/// along the rows, then along the columns (van Herk / Gil–Werman: block prefix and suffix
/// values of width 2r + 1, so the cost does not grow with the radius).
fn window_reduce<T: Copy + Send + Sync>(
    values: &[T],
    w: usize,
    h: usize,
    radius: usize,
    identity: T,
    op: impl Fn(T, T) -> T + Sync,
) -> Vec<T> {
    let line_reduce = |line: &[T], out: &mut [T]| {
        let (n, k) = (line.len(), 2 * radius + 1);
        let mut prefix = vec![identity; n];
        let mut suffix = vec![identity; n];
        for i in 0..n {
            prefix[i] = if i % k == 0 {
                line[i]
            } else {
                op(prefix[i - 1], line[i])
            };
        }
        for i in (0..n).rev() {
            suffix[i] = if i % k == k - 1 || i == n - 1 {
                line[i]
            } else {
                op(suffix[i + 1], line[i])
            };
        }
        for (i, o) in out.iter_mut().enumerate() {
            let (lo, hi) = (i.saturating_sub(radius), (i + radius).min(n - 1));
            // A window cut by the line's ends may lie within one block: its own values.
            *o = if lo / k == hi / k {
                line[lo..=hi].iter().fold(identity, |a, &b| op(a, b))
            } else {
                op(suffix[lo], prefix[hi])
            };
        }
    };
    let mut rows = vec![identity; w * h];
    rows.par_chunks_mut(w)
        .zip(values.par_chunks(w))
        .for_each(|(out, line)| line_reduce(line, out));
    let columns: Vec<Vec<T>> = (0..w)
        .into_par_iter()
        .map(|x| {
            let line: Vec<T> = (0..h).map(|y| rows[y * w + x]).collect();
            let mut column = vec![identity; h];
            line_reduce(&line, &mut column);
            column
        })
        .collect();
    let mut out = vec![identity; w * h];
    for (x, column) in columns.iter().enumerate() {
        for (y, v) in column.iter().enumerate() {
            out[y * w + x] = *v;
        }
    }
    out
}

/// The shape test's limits ([`ThinParts::min_length_px`] and the rest).
#[derive(Debug, Clone, Copy)]
struct PartShape {
    min_length: usize,
    max_width: f32,
    min_slender_length: usize,
    slender_ratio: f32,
}

impl PartShape {
    fn of(config: &ThinParts) -> Self {
        Self {
            min_length: config.min_length_px,
            max_width: config.max_width_px,
            min_slender_length: config.min_slender_length_px,
            slender_ratio: config.slender_ratio,
        }
    }
}

/// The pixels of `disparity` (NaN = none) whose patch is unlike a thin part: it spans fewer
/// than `min_length` pixels both across and down and is not a slender piece (at least
/// `min_slender_length` long, its pixels at most its bounding box's squared diagonal over
/// `slender_ratio`), or holds more than `max_width` (0 = any) times its bounding box's diagonal
/// in pixels. A patch is connected through 8-neighbours within a pixel of each other.
fn unlike_parts(disparity: &[f32], (w, h): (usize, usize), shape: &PartShape) -> Vec<bool> {
    let PartShape {
        min_length,
        max_width,
        min_slender_length,
        slender_ratio,
    } = *shape;
    let mut unlike = vec![false; w * h];
    let mut seen = vec![false; w * h];
    let mut patch = Vec::new();
    for start in 0..w * h {
        if seen[start] || !disparity[start].is_finite() {
            continue;
        }
        seen[start] = true;
        patch.clear();
        patch.push(start);
        let (mut x_range, mut y_range) = ((start % w, start % w), (start / w, start / w));
        let mut next = 0;
        while let Some(&i) = patch.get(next) {
            next += 1;
            let (x, y) = (i % w, i / w);
            x_range = (x_range.0.min(x), x_range.1.max(x));
            y_range = (y_range.0.min(y), y_range.1.max(y));
            for ny in y.saturating_sub(1)..(y + 2).min(h) {
                for nx in x.saturating_sub(1)..(x + 2).min(w) {
                    let j = ny * w + nx;
                    if !seen[j] && (disparity[j] - disparity[i]).abs() <= 1.0 {
                        seen[j] = true;
                        patch.push(j);
                    }
                }
            }
        }
        let (across, down) = (x_range.1 - x_range.0 + 1, y_range.1 - y_range.0 + 1);
        let diagonal = ((across * across + down * down) as f32).sqrt();
        let wide = max_width > 0.0 && patch.len() as f32 > max_width * diagonal;
        let length = across.max(down);
        let slender = min_slender_length > 0
            && length >= min_slender_length
            && patch.len() as f32 * slender_ratio <= diagonal * diagonal;
        if (length < min_length && !slender) || wide {
            for &i in &patch {
                unlike[i] = true;
            }
        }
    }
    unlike
}

/// The pixels of `moved_to` (NaN = none; patches connected through 8-neighbours within a pixel
/// of each other) whose patch's border holds more than `max_share` pixels whose `estimate` lies
/// within a pixel of the patch pixel beside them: moves that widen a region rather than open a
/// gap between parts.
fn extensions(moved_to: &[f32], estimate: &[f32], w: usize, h: usize, max_share: f32) -> Vec<bool> {
    let mut widens = vec![false; w * h];
    let mut seen = vec![false; w * h];
    // The patch (by its first pixel) each pixel last belonged to or was counted as border of:
    // a pixel of the patch is never its border, a border pixel is counted once.
    let mut member = vec![usize::MAX; w * h];
    let mut counted = vec![usize::MAX; w * h];
    let mut patch = Vec::new();
    let neighbours = |i: usize| {
        let (x, y) = (i % w, i / w);
        (y.saturating_sub(1)..(y + 2).min(h))
            .flat_map(move |ny| (x.saturating_sub(1)..(x + 2).min(w)).map(move |nx| ny * w + nx))
            .filter(move |&j| j != i)
    };
    for start in 0..w * h {
        if seen[start] || !moved_to[start].is_finite() {
            continue;
        }
        seen[start] = true;
        member[start] = start;
        patch.clear();
        patch.push(start);
        let mut next = 0;
        while let Some(&i) = patch.get(next) {
            next += 1;
            for j in neighbours(i) {
                if !seen[j] && moved_to[j].is_finite() && (moved_to[j] - moved_to[i]).abs() <= 1.0 {
                    seen[j] = true;
                    member[j] = start;
                    patch.push(j);
                }
            }
        }
        let (mut border, mut alike) = (0usize, 0usize);
        for &i in &patch {
            for j in neighbours(i) {
                if member[j] != start && counted[j] != start {
                    counted[j] = start;
                    border += 1;
                    if (estimate[j] - moved_to[i]).abs() <= 1.0 {
                        alike += 1;
                    }
                }
            }
        }
        if border > 0 && alike as f32 > max_share * border as f32 {
            for &i in &patch {
                widens[i] = true;
            }
        }
    }
    widens
}

/// The disparity (slices from the range's start, with its parabola's fraction) and confidence
/// one pixel moves to, from its cost curves (`costs` with occluded views dropped, `seen_by_all`
/// every view's mean; `f32::INFINITY` where invalid), where [`ThinParts`]'s tests pass: a
/// nearer part on the mean of every view, or (with `config.farther`) the background through a
/// gap on the costs with occluded views dropped (a gap's background is hidden from some views
/// by the part itself), no farther than `farthest` (slices) by more than a pixel.
fn candidate_of(
    estimate: f32,
    costs: &[f32],
    seen_by_all: &[f32],
    (farthest, seen_near): (f32, &dyn Fn(usize) -> bool),
    config: &ThinParts,
) -> Option<(f32, f32)> {
    if !estimate.is_finite() {
        return None;
    }
    let nd = costs.len();
    let near = estimate.round().clamp(0.0, (nd - 1) as f32) as usize;
    let at_estimate = costs[near.saturating_sub(1)..(near + 2).min(nd)]
        .iter()
        .copied()
        .filter(|c| c.is_finite())
        .reduce(f32::min)?;
    let nearer = |best: usize| best as f32 >= estimate + config.min_jump_px;
    let farther = |best: usize| {
        config.farther
            && best as f32 <= estimate - config.min_jump_px
            && best as f32 >= farthest - 1.0
            && seen_near(best)
    };
    clear_minimum(seen_by_all, at_estimate, config, nearer)
        .or_else(|| clear_minimum(costs, at_estimate, config, farther))
}

/// The minimum of `curve` where `wanted` takes its place and it is clearly better than
/// `at_estimate` and unique ([`ThinParts`]), with its parabola's fraction, and its confidence.
fn clear_minimum(
    curve: &[f32],
    at_estimate: f32,
    config: &ThinParts,
    wanted: impl Fn(usize) -> bool,
) -> Option<(f32, f32)> {
    let nd = curve.len();
    let (best, &c_best) = curve
        .iter()
        .enumerate()
        .filter(|(_, c)| c.is_finite())
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    if !wanted(best) {
        return None;
    }
    let second = curve
        .iter()
        .enumerate()
        .filter(|(d, c)| d.abs_diff(best) > 1 && c.is_finite())
        .map(|(_, c)| *c)
        .reduce(f32::min)
        .unwrap_or(f32::from(INVALID_COST));
    let passes = c_best <= config.ratio * at_estimate
        && c_best <= config.uniqueness * second
        && at_estimate - c_best >= config.min_margin;
    if !passes {
        return None;
    }
    let fraction = if best >= 1 && best + 1 < nd {
        let [l, c, r] = [curve[best - 1], curve[best], curve[best + 1]];
        if !(l.is_finite() && r.is_finite()) {
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
    use crate::volume::Neighbour;

    /// The reference `view([0, 0])` and the four views of a cross around it, 16 disparities.
    fn cross_of(view: impl Fn([i32; 2]) -> Image) -> Problem {
        let neighbour = |offset: [i32; 2], role: &str| Neighbour {
            image: view(offset),
            offset,
            role: role.into(),
            baseline_ratio: 1.0,
        };
        Problem {
            reference: view([0, 0]),
            neighbours: vec![
                neighbour([-1, 0], "left"),
                neighbour([1, 0], "right"),
                neighbour([0, -1], "top"),
                neighbour([0, 1], "bottom"),
            ],
            min_disparity: 0,
            num_disparities: 16,
        }
    }

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
        let problem = cross_of(view);
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
        // The whole plane is one patch of moves, far wider than a gap: the shape limits off, and
        // the guards that need the estimate to hold the plane's disparity somewhere off too.
        let config = ThinParts {
            farther: true,
            min_length_px: 0,
            max_width_px: 0.0,
            farther_seen_px: 0,
            farther_max_extension: 1.0,
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
        // The shape limits at their defaults but not for farther moves: the same moves back.
        let shapes_for_nearer_only = ThinParts {
            min_length_px: ThinParts::default().min_length_px,
            max_width_px: ThinParts::default().max_width_px,
            farther_shape_test: false,
            ..config
        };
        let mut same = fattened.clone();
        recover_thin_parts(&problem, &mut same, &shapes_for_nearer_only).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(same.data, disparity.data);
        // With them, the plane (one patch far wider than a gap) stays.
        let shaped = ThinParts {
            farther_shape_test: true,
            ..shapes_for_nearer_only
        };
        let mut kept = fattened.clone();
        recover_thin_parts(&problem, &mut kept, &shaped).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(kept.data, fattened.data);
        // Without `farther` nothing moves back; nor with the defaults (the plane is one patch far
        // wider than a gap), nor with the seen-nearby test alone: no estimate near the plane
        // holds its disparity (a reflection's case).
        let nearer_only = ThinParts {
            farther: false,
            ..ThinParts::default()
        };
        let seen_test_only = ThinParts {
            farther_shape_test: false,
            farther_max_extension: 1.0,
            farther_seen_px: 32,
            ..config
        };
        for config in [nearer_only, ThinParts::default(), seen_test_only] {
            let mut unchanged = fattened.clone();
            recover_thin_parts(&problem, &mut unchanged, &config).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(unchanged.data, fattened.data);
        }
        // The guard: with the rod's disparity everywhere within reach, the plane may not move
        // farther than it by more than a pixel, so nothing moves.
        let guarded = ThinParts {
            farther_guard_px: 40,
            ..config
        };
        let mut kept = fattened.clone();
        recover_thin_parts(&problem, &mut kept, &guarded).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(kept.data, fattened.data);
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
    fn a_rod_comes_back_with_each_pixel_s_own_costs_too() {
        let (w, h) = (80, 44);
        let (problem, on_rod) = rod_before_a_plane(w, h, false);
        let mut disparity = far_everywhere(w, h);
        let own = ThinParts {
            cross_support: None,
            ..ThinParts::default()
        };
        recover_thin_parts(&problem, &mut disparity, &own).unwrap_or_else(|e| panic!("{e}"));
        let found = (0..w * h)
            .filter(|&i| on_rod[i] && (12..w - 12).contains(&(i % w)) && (disparity.data[i] - 10.0).abs() <= 1.0)
            .count();
        assert!(found * 2 >= (w - 24) * 2, "rod {found} of {}", (w - 24) * 2);
    }

    #[test]
    fn cross_support_averages_each_pixel_s_costs_over_the_horizontal_arms_along_its_vertical_arm() {
        // The streamed curves against a plain sum over the support, read from the whole volume.
        let (w, h) = (48, 40);
        let (problem, _) = rod_before_a_plane(w, h, false);
        let spec = CostSpec {
            pixel: PixelCost::BirchfieldTomasi,
            block_radius_px: 0,
        };
        let heuristic = PreparedProblem::new(&problem, spec, Fusion::Heuristic).unwrap_or_else(|e| panic!("{e}"));
        let mean = PreparedProblem::new(&problem, spec, Fusion::Mean).unwrap_or_else(|e| panic!("{e}"));
        let nd = heuristic.num_disparities();
        let support = CrossSupport {
            arm_px: 5,
            colour_threshold: 30,
        };
        let arms = Arms::new(&problem.reference, support);
        let mut whole = vec![0u16; w * h * nd];
        heuristic.fused_band(0..h, &mut whole);
        let rows = 13..29;
        let mut curves = SupportCurves::default();
        let (mut streamed, mut streamed_curves) = (Vec::new(), Vec::new());
        curves.stream(&heuristic, &mean, rows.clone(), &arms, &mut |y, costs, _| {
            streamed.push(y);
            streamed_curves.extend_from_slice(costs);
        });
        assert_eq!(streamed, rows.clone().collect::<Vec<_>>(), "each row once, in order");
        let mut longest_seen = 0;
        for (r, y) in rows.enumerate() {
            for x in 0..w {
                let [left, right, up, down] = arms.arms[y * w + x].map(usize::from);
                longest_seen = longest_seen.max(left.max(right).max(up).max(down));
                for d in 0..nd {
                    let (mut sum, mut count) = (0u64, 0u64);
                    for qy in y - up..=y + down {
                        let [ql, qr, _, _] = arms.arms[qy * w + x].map(usize::from);
                        for qx in x - ql..=x + qr {
                            let c = whole[(qy * w + qx) * nd + d];
                            if c != INVALID_COST {
                                sum += u64::from(c);
                                count += 1;
                            }
                        }
                    }
                    let expected = if count == 0 {
                        f32::INFINITY
                    } else {
                        sum as f32 / count as f32
                    };
                    let got = streamed_curves[(r * w + x) * nd + d];
                    assert!(
                        got == expected || (got - expected).abs() <= 1e-4 * expected,
                        "({x}, {y}) d {d}: {got} against {expected}"
                    );
                }
            }
        }
        // The arms reach their limit somewhere (the plane's smooth colours) and stop short at the rod.
        assert_eq!(longest_seen, 5);
        assert!(arms.arms.iter().any(|a| a.iter().any(|&l| l < 5)));
    }

    #[test]
    fn arms_longer_than_the_limit_are_cut_to_it() {
        let (w, h) = (80, 44);
        let (problem, _) = rod_before_a_plane(w, h, false);
        let long = ThinParts {
            cross_support: Some(CrossSupport {
                arm_px: 1000,
                colour_threshold: 255,
            }),
            ..ThinParts::default()
        };
        let capped = ThinParts {
            cross_support: Some(CrossSupport {
                arm_px: MAX_ARM_PX,
                colour_threshold: 255,
            }),
            ..ThinParts::default()
        };
        let (mut a, mut b) = (far_everywhere(w, h), far_everywhere(w, h));
        recover_thin_parts(&problem, &mut a, &long).unwrap_or_else(|e| panic!("{e}"));
        recover_thin_parts(&problem, &mut b, &capped).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(a.data, b.data);
        let arms = Arms::new(&problem.reference, long.cross_support.unwrap_or_default());
        assert_eq!(arms.longest, MAX_ARM_PX);
        assert!(arms.arms.iter().any(|a| a.contains(&(MAX_ARM_PX as u8))));
    }

    #[test]
    fn a_rod_shorter_or_wider_than_the_shape_limits_stays_lost() {
        // The rod of `a_rod_the_estimate_erased_comes_back…` spans the image (80 px) and is 2
        // px thick: it comes back within the default limits, not under tighter ones.
        let (w, h) = (80, 44);
        let (problem, _) = rod_before_a_plane(w, h, false);
        // Shorter than a limit of 100 px, it stays lost unless slender ones may stay (2 px
        // thick, 80 long).
        for (min_length_px, max_width_px, min_slender_length_px, back) in [
            (20, 8.0, 10, true),
            (100, 0.0, 0, false),
            (100, 0.0, 10, true),
            (0, 1.0, 10, false),
        ] {
            let config = ThinParts {
                min_length_px,
                max_width_px,
                min_slender_length_px,
                ..ThinParts::default()
            };
            let mut disparity = far_everywhere(w, h);
            let moved = recover_thin_parts(&problem, &mut disparity, &config).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(
                moved > 0,
                back,
                "limits {min_length_px} / {max_width_px}: {moved} moved"
            );
            if !back {
                assert_eq!(disparity.data, far_everywhere(w, h).data);
            }
        }
    }

    #[test]
    fn only_long_thin_patches_of_moves_stay() {
        let (w, h) = (90, 70);
        let mut moved = vec![f32::NAN; w * h];
        let mut paint = |x: usize, y: usize, d: f32| moved[y * w + x] = d;
        // Kept: a diagonal line 3 px thick and 40 long; a row 2 px thick and 30 long, its
        // disparity rising by 0.5 px a pixel (neighbours within a pixel of each other).
        for t in 0..40 {
            for k in 0..3 {
                paint(5 + t, 20 + t + k, 12.0);
            }
        }
        for x in 50..80 {
            for y in 2..4 {
                paint(x, y, 5.0 + 0.5 * (x - 50) as f32);
            }
        }
        // Undone: a 6 × 6 blob (short both ways); a 30 × 25 patch (long, but 19 px wide on
        // average); a column 16 px long split in two by a jump of 3 px (two patches of 8).
        for y in 8..14 {
            for x in 60..66 {
                paint(x, y, 9.0);
            }
        }
        for y in 40..65 {
            for x in 55..85 {
                paint(x, y, 7.0);
            }
        }
        for y in 20..36 {
            paint(86, y, if y < 28 { 4.0 } else { 7.0 });
        }
        // Short but slender, kept with the slender limits: a row 14 px long and 1 px thick.
        // Short and not slender enough: a 14 × 4 block (its mean width 3.8 px > 14.6 / 6).
        for x in 60..74 {
            paint(x, 30, 3.0);
        }
        for x in 10..24 {
            for y in 62..66 {
                paint(x, y, 3.0);
            }
        }
        let shape = |min_length, max_width, min_slender_length| PartShape {
            min_length,
            max_width,
            min_slender_length,
            slender_ratio: 6.0,
        };
        let unlike = unlike_parts(&moved, (w, h), &shape(20, 8.0, 0));
        let slender = unlike_parts(&moved, (w, h), &shape(20, 8.0, 10));
        for (i, (u, s)) in unlike.iter().zip(&slender).enumerate() {
            let (x, y) = (i % w, i / w);
            let expected = if y == 30 && (60..74).contains(&x) { false } else { *u };
            assert_eq!(*s, expected, "({x}, {y}) with the slender limits");
        }
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !moved[i].is_finite() {
                    assert!(!unlike[i], "({x}, {y}) is no move");
                } else {
                    // The line is the only patch left of x = 50 but the 14 × 4 block, the row the
                    // only one above y = 4.
                    let expected_kept = (x < 50 && y < 62) || y < 4;
                    assert_eq!(!unlike[i], expected_kept, "({x}, {y}) at {}", moved[i]);
                }
            }
        }
        // Without limits every move stays.
        assert!(unlike_parts(&moved, (w, h), &shape(0, 0.0, 0)).iter().all(|u| !u));
    }

    #[test]
    fn the_window_minimum_is_the_plain_one() {
        let (w, h) = (23, 17);
        let values: Vec<f32> = (0..w * h)
            .map(|i| {
                if i % 11 == 3 {
                    f32::NAN
                } else {
                    ((i * 7919) % 101) as f32
                }
            })
            .collect();
        for radius in [0, 1, 3, 8, 30] {
            let got = window_min(&values, w, h, radius);
            for y in 0..h {
                for x in 0..w {
                    let mut expected = f32::INFINITY;
                    for qy in y.saturating_sub(radius)..(y + radius + 1).min(h) {
                        for qx in x.saturating_sub(radius)..(x + radius + 1).min(w) {
                            let v = values[qy * w + qx];
                            if v.is_finite() {
                                expected = expected.min(v);
                            }
                        }
                    }
                    assert_eq!(got[y * w + x], expected, "radius {radius} at ({x}, {y})");
                }
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

    /// A textured far plane at disparity 2 behind a near board at 10 (rows 8..36, columns
    /// 20..60 of the reference) with a horizontal slit (rows 20..24) through which the plane
    /// shows, seen from the four views of a cross. Returns the problem and the slit's pixels.
    fn board_with_a_slit(w: usize, h: usize) -> (Problem, Vec<bool>) {
        let (far, near) = (2.0f32, 10.0f32);
        let (rows, columns, slit) = (8.0..36.0f32, 20.0..60.0f32, 20.0..24.0f32);
        let plane = |x: f32, y: f32| -> [u8; 3] {
            let v = (128.0 + (x * 0.41).sin() * 50.0 + (y * 0.29 + x * 0.13).cos() * 45.0).clamp(0.0, 255.0) as u8;
            [v, v / 2 + 30, 255 - v]
        };
        let board = |x: f32, y: f32| -> [u8; 3] {
            let v = (150.0 + (x * 0.37 + y * 0.11).sin() * 60.0 + (y * 0.53).cos() * 30.0).clamp(0.0, 255.0) as u8;
            [60, v, 255 - v / 2]
        };
        let on_board = |x: f32, y: f32| rows.contains(&y) && columns.contains(&x) && !slit.contains(&y);
        let view = |[ox, oy]: [i32; 2]| {
            let (ox, oy) = (ox as f32, oy as f32);
            let mut data = Vec::with_capacity(w * h * 3);
            for y in 0..h {
                for x in 0..w {
                    let (x, y) = (x as f32, y as f32);
                    let (bx, by) = (x + ox * near, y + oy * near);
                    data.extend(if on_board(bx, by) {
                        board(bx, by)
                    } else {
                        plane(x + ox * far, y + oy * far)
                    });
                }
            }
            Image::new(w, h, 3, data).unwrap_or_else(|e| panic!("{e}"))
        };
        let problem = cross_of(view);
        let in_slit = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                columns.contains(&x) && slit.contains(&y)
            })
            .collect();
        (problem, in_slit)
    }

    #[test]
    fn the_background_seen_through_a_slit_the_estimate_filled_comes_back() {
        // The estimate gives the whole board's box 10 (the slit filled, as block costs do) and
        // the plane around it 2: the plane is seen beside the board, so the slit may go back.
        let (w, h) = (80, 44);
        let (problem, in_slit) = board_with_a_slit(w, h);
        let boxed = |x: usize, y: usize| (8..36).contains(&y) && (20..60).contains(&x);
        let filled = DisparityImage {
            data: (0..w * h)
                .map(|i| if boxed(i % w, i / w) { 10.0 } else { 2.0 })
                .collect(),
            ..far_everywhere(w, h)
        };
        let mut disparity = filled.clone();
        recover_thin_parts(&problem, &mut disparity, &ThinParts::default()).unwrap_or_else(|e| panic!("{e}"));
        let (mut back, mut total, mut board_moved) = (0, 0, 0);
        for y in 0..h {
            for x in 24..56 {
                let d = disparity.data[y * w + x];
                if in_slit[y * w + x] {
                    total += 1;
                    back += usize::from((d - 2.0).abs() <= 1.0);
                } else if d != filled.data[y * w + x] {
                    board_moved += 1;
                }
            }
        }
        println!("slit {back} of {total} back at 2, {board_moved} other pixels moved");
        assert!(back * 4 >= total * 3, "slit {back} of {total}");
        assert!(board_moved * 50 <= 32 * h, "{board_moved} pixels off the slit moved");
        // Nearer moves only: the slit stays filled.
        let nearer_only = ThinParts {
            farther: false,
            ..ThinParts::default()
        };
        let mut kept = filled.clone();
        recover_thin_parts(&problem, &mut kept, &nearer_only).unwrap_or_else(|e| panic!("{e}"));
        let slit_back = (0..w * h)
            .filter(|&i| in_slit[i] && (kept.data[i] - 2.0).abs() <= 1.0)
            .count();
        assert_eq!(slit_back, 0);
    }

    #[test]
    fn moves_that_widen_a_region_at_their_disparity_are_told_from_a_gap_between_parts() {
        let (w, h) = (40, 20);
        // A strip of moves to 2 on rows 8..11, columns 5..35.
        let strip = |x: usize, y: usize| (8..11).contains(&y) && (5..35).contains(&x);
        let moved_to: Vec<f32> = (0..w * h)
            .map(|i| if strip(i % w, i / w) { 2.0 } else { f32::NAN })
            .collect();
        // A gap: parts at 10 above and below, the background at 2 only beyond its ends.
        let gap: Vec<f32> = (0..w * h)
            .map(|i| if (5..35).contains(&(i % w)) { 10.0 } else { 2.0 })
            .collect();
        assert!(extensions(&moved_to, &gap, w, h, 0.15).iter().all(|&b| !b));
        // A widening: the rows below it already at 2 (the strip creeps over their edge).
        let edge: Vec<f32> = (0..w * h).map(|i| if i / w >= 11 { 2.0 } else { 10.0 }).collect();
        let widens = extensions(&moved_to, &edge, w, h, 0.15);
        assert!((0..w * h).all(|i| widens[i] == strip(i % w, i / w)));
        // 1 lets every patch through whatever borders it.
        assert!(extensions(&moved_to, &edge, w, h, 1.0).iter().all(|&b| !b));
    }

    #[test]
    fn the_disparities_held_near_each_pixel_are_those_of_a_plain_window_search() {
        // Radius 6 px: every 4 × 4 cell within two cells of the pixel's own. A few estimates
        // among non-finite ones, so that most windows hold few disparities; slices of one bin
        // (40 disparities) and of three (300: 100 bins, a slice's neighbours within a bin).
        let (w, h, radius) = (23, 17, 6);
        for nd in [40usize, 300] {
            let bin = nd.div_ceil(128);
            let disparity: Vec<f32> = (0..w * h)
                .map(|i| {
                    if i % 29 == 3 {
                        ((i * 37 + i / w * 11) % (nd + 4)) as f32 - 1.4
                    } else {
                        f32::NAN
                    }
                })
                .collect();
            let seen = SeenNear::new(&disparity, (w, h, nd), -2.0, radius);
            let cell = |v: usize| v / SEEN_CELL_PX;
            let (mut held, mut not_held) = (0, 0);
            for y in 0..h {
                for x in 0..w {
                    for slice in 0..nd {
                        let (lo, hi) = (slice.saturating_sub(1) / bin, (slice + 1) / bin);
                        let mut plain = false;
                        for ny in 0..h {
                            for nx in 0..w {
                                if cell(nx).abs_diff(cell(x)) > 2 || cell(ny).abs_diff(cell(y)) > 2 {
                                    continue;
                                }
                                let s = (disparity[ny * w + nx] + 2.0).round();
                                plain |= s.is_finite()
                                    && s >= 0.0
                                    && (s as usize) < nd
                                    && (lo..=hi).contains(&(s as usize / bin));
                            }
                        }
                        assert_eq!(seen.holds(y * w + x, slice), plain, "nd {nd}: ({x}, {y}) slice {slice}");
                        if plain {
                            held += 1;
                        } else {
                            not_held += 1;
                        }
                    }
                }
            }
            assert!(held > 0 && not_held > held, "nd {nd}: {held} held, {not_held} not");
        }
    }
}
