//! Post-processing of disparity maps: the 3×3 median every method applies, and the
//! image-guided weighted median ([`WeightedMedian`]) that keeps depth edges on colour edges.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::image::{DisparityImage, Image};

/// 3×3 median of the valid values around each pixel (invalid pixels stay invalid). Rows run in
/// parallel; runs of eight interior pixels whose nine values are all valid go through
/// a 19-exchange sorting network lane by lane (it vectorises), the others (borders, next to
/// invalid pixels) one by one: through the same network when their nine values are valid, else
/// through a sort of their valid values.
pub fn median3x3(input: &DisparityImage) -> DisparityImage {
    let (w, h) = (input.width, input.height);
    let mut data = input.data.clone();
    data.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        let mut window = Vec::with_capacity(9);
        let rows = [y.saturating_sub(1), y, (y + 1).min(h - 1)].map(|r| &input.data[r * w..(r + 1) * w]);
        // Pixels from `x` on are left for the one-by-one loop.
        let mut x = 1;
        if y > 0 && y + 1 < h {
            while x + MEDIAN_LANES < w {
                let mut p: [[f32; MEDIAN_LANES]; 9] = [[0.0; MEDIAN_LANES]; 9];
                for (k, lane) in p.iter_mut().enumerate() {
                    let start = x - 1 + k % 3;
                    lane.copy_from_slice(&rows[k / 3][start..start + MEDIAN_LANES]);
                }
                if p.iter().flatten().all(|v| v.is_finite()) {
                    out[x..x + MEDIAN_LANES].copy_from_slice(&median_of_nine_lanes(&mut p));
                } else {
                    for (at, value) in out[x..x + MEDIAN_LANES].iter_mut().enumerate() {
                        median_at(&input.data, (w, h), (x + at, y), &rows, &mut window, value);
                    }
                }
                x += MEDIAN_LANES;
            }
        }
        for at in (0..1.min(w)).chain(x..w) {
            median_at(&input.data, (w, h), (at, y), &rows, &mut window, &mut out[at]);
        }
    });
    DisparityImage {
        width: w,
        height: h,
        data,
        confidence: input.confidence.clone(),
    }
}

/// An image-guided weighted median (the joint weighted median of stereo post-processing, e.g.
/// Ma et al., "Constant time weighted median filtering for stereo matching", ICCV 2013): each
/// pixel takes the weighted median of the disparities in its window, each weighted by how alike
/// its colour is to the centre pixel's and how near it is,
/// `exp(−mean |ΔI| / sigma_colour − r² / (2 sigma_space²))`. Disparities bleeding across a
/// colour edge (a 3D CNN's or a census window's fattened foreground) lose to those of the
/// pixel's own surface; values are only ever chosen, never averaged, so sub-pixel values and
/// depth edges stay sharp. The window is sampled every `step_px` pixels (offsets that are
/// multiples of it, the centre included): on `middlebury2006-third-dev` a step of 2 over a
/// radius of 10 gave the same result as every pixel of a radius of 9 at a third of the work.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WeightedMedian {
    /// Window radius (px): offsets up to this far in x and y.
    pub radius_px: usize,
    /// Sampling step of the window (px): offsets are its multiples.
    pub step_px: usize,
    /// Colour scale: the mean absolute channel difference (0–255) at which a weight falls by e.
    pub sigma_colour: f32,
    /// Spatial scale (px) of the Gaussian fall-off.
    pub sigma_space_px: f32,
}

impl Default for WeightedMedian {
    /// Chosen on `middlebury2006-third-dev` and the held-out simulated captures (docs/methods.md,
    /// "Weighted median").
    fn default() -> Self {
        Self {
            radius_px: 10,
            step_px: 2,
            sigma_colour: 8.0,
            sigma_space_px: 7.0,
        }
    }
}

impl WeightedMedian {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<(), FuseError> {
        let bad = |field, value: f32| FuseError::Config {
            field,
            value: value.to_string(),
            reason: "a positive finite scale",
        };
        if !(self.sigma_colour > 0.0 && self.sigma_colour.is_finite()) {
            return Err(bad("weighted_median.sigma_colour", self.sigma_colour));
        }
        if !(self.sigma_space_px > 0.0 && self.sigma_space_px.is_finite()) {
            return Err(bad("weighted_median.sigma_space_px", self.sigma_space_px));
        }
        if self.radius_px > 64 {
            return Err(FuseError::Config {
                field: "weighted_median.radius_px",
                value: self.radius_px.to_string(),
                reason: "a window radius of at most 64 px",
            });
        }
        if self.step_px == 0 || self.step_px > self.radius_px.max(1) {
            return Err(FuseError::Config {
                field: "weighted_median.step_px",
                value: self.step_px.to_string(),
                reason: "a sampling step of 1 px up to the radius",
            });
        }
        Ok(())
    }
}

/// A second, wider weighted median that may only move pixels *farther*
/// ([`farther_by_wider_median`]): a 3D network fattens a foreground over a background of another
/// colour by up to its receptive field, wider than [`WeightedMedian`]'s window can undo, and a
/// wider window alone rounds off steep slants and the thin near rims of same-coloured walls
/// (a tote's). Taken only where it answers at least `min_move_px` farther than the first
/// filter, it undoes the bands and blobs of foreground without touching a surface's own
/// disparities. MFuseNet's default (docs/methods.md, "Weighted median").
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FartherMedian {
    /// The wider filter.
    pub filter: WeightedMedian,
    /// How much farther (px) its answer must be to be taken.
    pub min_move_px: f32,
}

impl Default for FartherMedian {
    /// Chosen on `middlebury2006-third-dev`, the `thin` family as five-view crosses and as rows
    /// of five, and the `bin` grid's cross (docs/experiments.md, 2026-12-06, "A wider weighted
    /// median that only moves pixels farther"): twice [`WeightedMedian`]'s radius at the same
    /// number of samples.
    fn default() -> Self {
        Self {
            filter: WeightedMedian {
                radius_px: 20,
                step_px: 4,
                sigma_colour: 8.0,
                sigma_space_px: 14.0,
            },
            min_move_px: 2.0,
        }
    }
}

impl FartherMedian {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<(), FuseError> {
        self.filter.validate()?;
        if !(self.min_move_px >= 0.0 && self.min_move_px.is_finite()) {
            return Err(FuseError::Config {
                field: "farther_median.min_move_px",
                value: self.min_move_px.to_string(),
                reason: "a finite move of 0 px or more",
            });
        }
        Ok(())
    }
}

/// [`FartherMedian`]: the wider weighted median of `disparity` (with `votes` as
/// [`weighted_median_with_votes`]), taken into `filtered` (the first filter's answer for the
/// same `disparity`, the same size) wherever it is at least `min_move_px` farther (smaller).
/// Invalid pixels stay as they are.
pub fn farther_by_wider_median(
    disparity: &DisparityImage,
    reference: &Image,
    farther: &FartherMedian,
    votes: Option<&[f32]>,
    filtered: &mut DisparityImage,
) -> Result<(), FuseError> {
    farther.validate()?;
    if filtered.data.len() != disparity.data.len() {
        return Err(FuseError::ImageSize {
            what: "farther median's filtered map",
            width: disparity.width,
            height: disparity.height,
            len: filtered.data.len(),
        });
    }
    // Only a pixel whose window holds a value at least `min_move_px` below its answer can move:
    // the least value of its whole box (a superset of the sampled window) says which, so the
    // filter runs only near depth edges, with the same result.
    let radius = farther.filter.radius_px;
    let least = box_minimum(disparity, radius);
    let only: Vec<bool> = least
        .iter()
        .zip(&filtered.data)
        .map(|(low, d)| *low < *d - farther.min_move_px)
        .collect();
    let wide = weighted_median_of(disparity, reference, &farther.filter, votes, Some(&only))?;
    for (d, f) in filtered.data.iter_mut().zip(&wide.data) {
        if *f < *d - farther.min_move_px {
            *d = *f;
        }
    }
    Ok(())
}

/// The least finite value within `radius` px (a square box) of each pixel, `+∞` where none: the
/// running minimum of [`crate::thin_parts`] (blocks of `2r + 1` with their prefix and suffix
/// minima, so its cost does not grow with the radius).
fn box_minimum(disparity: &DisparityImage, radius: usize) -> Vec<f32> {
    let (w, h) = (disparity.width, disparity.height);
    if w == 0 || h == 0 || disparity.data.len() != w * h {
        return vec![f32::INFINITY; disparity.data.len()];
    }
    crate::thin_parts::window_min(&disparity.data, w, h, radius)
}

/// [`WeightedMedian`] of `disparity`, guided by `reference` (grey or RGB, the same size).
/// Invalid (non-finite) disparities neither vote nor change. Rows run in parallel.
pub fn weighted_median(
    disparity: &DisparityImage,
    reference: &Image,
    filter: &WeightedMedian,
) -> Result<DisparityImage, FuseError> {
    weighted_median_with_votes(disparity, reference, filter, None)
}

/// [`weighted_median`] with each pixel's weight also scaled by its entry of `votes` (one per
/// pixel, 0 or more; `None` = all 1): a confidence, so that the pixels a method trusts decide
/// (MFuseNet: those whose estimate its input costs back). A pixel whose window has no weight at
/// all keeps its value.
pub fn weighted_median_with_votes(
    disparity: &DisparityImage,
    reference: &Image,
    filter: &WeightedMedian,
    votes: Option<&[f32]>,
) -> Result<DisparityImage, FuseError> {
    weighted_median_of(disparity, reference, filter, votes, None)
}

/// [`weighted_median_with_votes`] at the pixels `only` marks (`None`: every pixel); the others
/// keep their values.
fn weighted_median_of(
    disparity: &DisparityImage,
    reference: &Image,
    filter: &WeightedMedian,
    votes: Option<&[f32]>,
    only: Option<&[bool]>,
) -> Result<DisparityImage, FuseError> {
    let ones;
    let votes = match votes {
        Some(v) if v.len() != disparity.data.len() => {
            return Err(FuseError::ImageSize {
                what: "weighted median's votes",
                width: disparity.width,
                height: disparity.height,
                len: v.len(),
            });
        }
        Some(v) => v,
        None => {
            ones = vec![1.0f32; disparity.data.len()];
            &ones
        }
    };
    filter.validate()?;
    let (w, h, c) = (disparity.width, disparity.height, reference.channels);
    if (reference.width, reference.height) != (w, h) {
        return Err(FuseError::ImageSize {
            what: "weighted median's guide image",
            width: w,
            height: h,
            len: reference.width * reference.height,
        });
    }
    // Offsets k·step for |k| ≤ reach; weights by the summed channel difference and by k.
    let (step, reach) = (filter.step_px, filter.radius_px / filter.step_px);
    let colour: Vec<f32> = (0..=255 * c)
        .map(|sum| (-(sum as f32 / c as f32) / filter.sigma_colour).exp())
        .collect();
    let two_var = 2.0 * filter.sigma_space_px * filter.sigma_space_px;
    let side = 2 * reach + 1;
    let space: Vec<f32> = (0..side * side)
        .map(|i| {
            let (dx, dy) = ((i % side) as f32 - reach as f32, (i / side) as f32 - reach as f32);
            (-(dx * dx + dy * dy) * (step * step) as f32 / two_var).exp()
        })
        .collect();
    // The window's values are binned by 64ths of a pixel (coarser beyond 64 px of range, so
    // that there are at most 4096 bins), the bins grouped in blocks of 32: the block holding the
    // weighted median is found from the blocks' sums, its bin from the bins', and only that
    // bin's values are sorted (on a smooth surface the window's 121 values fall within a pixel:
    // eighths of a pixel left dozens of them to sort).
    const BINS_PER_PX: f32 = 64.0;
    const MAX_BINS: f32 = 4096.0;
    const BLOCK: usize = MEDIAN_BLOCK;
    let finite = || disparity.data.iter().copied().filter(|v| v.is_finite());
    let (low, high) = (
        finite().fold(f32::INFINITY, f32::min),
        finite().fold(f32::NEG_INFINITY, f32::max),
    );
    if low > high {
        // No finite value at all.
        return Ok(disparity.clone());
    }
    // Coarser bins for a range wider than 64 px, so that the bins stay few.
    let per_px = BINS_PER_PX.min(MAX_BINS / (high - low).max(1.0));
    let bins = ((high - low) * per_px) as usize + 1;
    let bin = |v: f32| (((v - low) * per_px) as usize).min(bins - 1);
    // Each pixel's bin once (a window reads each pixel 121 times); 0 where not finite (unread).
    let bin_of: Vec<u16> = disparity
        .data
        .par_iter()
        .map(|&v| if v.is_finite() { bin(v) as u16 } else { 0 })
        .collect();
    let mut data = disparity.data.clone();
    data.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        let mut sums = vec![0.0f32; bins];
        let mut block_sums = vec![0.0f32; bins.div_ceil(BLOCK)];
        let mut chosen: Vec<(f32, f32)> = Vec::new();
        // Offsets that stay inside the image: k in ks(p, size).
        let ks = |p: usize, size: usize| (reach.min(p / step), reach.min((size - 1 - p) / step));
        let (up, down) = ks(y, h);
        let centre_row = &reference.data[y * w * c..(y + 1) * w * c];
        let sources = Sources {
            values: &disparity.data,
            bins: &bin_of,
            colours: &reference.data,
            votes,
            colour: &colour,
        };
        for (x, value) in out.iter_mut().enumerate() {
            if !value.is_finite() || only.is_some_and(|only| !only[y * w + x]) {
                continue;
            }
            let (left, right) = ks(x, w);
            let centre = &centre_row[x * c..(x + 1) * c];
            // The weights summed into their bins and blocks as they are gathered (in the
            // window's order), with the lowest and highest bin: the blocks below the lowest are
            // empty, so the search for the median starts there, and the bins between the two
            // are all that is cleared after.
            let mut acc = Accumulated {
                sums: &mut sums,
                block_sums: &mut block_sums,
                total: 0.0,
                lowest: u16::MAX,
                highest: 0,
            };
            let rows = reach - up..=reach + down;
            let row = |ky: usize| {
                let yy = y + ky * step - reach * step;
                let first = yy * w + x - left * step;
                (first, &space[ky * side + reach - left..=ky * side + reach + right])
            };
            for ky in rows.clone() {
                let (first, spaced) = row(ky);
                let add = |_: f32, weight: f32, b: u16| acc.add(weight, b);
                match c {
                    3 => visit::<3>(centre, &sources, (first, step), spaced, None, add),
                    _ => visit::<1>(centre, &sources, (first, step), spaced, None, add),
                }
            }
            let (total, lowest, highest) = (acc.total, usize::from(acc.lowest), usize::from(acc.highest));
            // The bin where the running sum reaches half the total, and the sum below it; none
            // when the window has no weight (every vote 0): the pixel keeps its value.
            let half = 0.5 * total;
            let median = (total > 0.0).then(|| {
                let skipped = lowest / BLOCK;
                let (block, below) = reaching(&block_sums[skipped..], 0.0, half);
                let block = skipped + block;
                let first = block * BLOCK;
                let (b, below) = reaching(&sums[first..(first + BLOCK).min(bins)], below, half);
                (first + b, below)
            });
            if lowest <= highest {
                sums[lowest..=highest].fill(0.0);
                block_sums[lowest / BLOCK..=highest / BLOCK].fill(0.0);
            }
            // The median bin's values with their weights, gathered again in the window's order
            // (the same weights: the same arithmetic).
            chosen.clear();
            if let Some((m, _)) = median {
                let m = m as u16;
                for ky in rows {
                    let (first, spaced) = row(ky);
                    let keep = |v: f32, weight: f32, _: u16| chosen.push((v, weight));
                    match c {
                        3 => visit::<3>(centre, &sources, (first, step), spaced, Some(m), keep),
                        _ => visit::<1>(centre, &sources, (first, step), spaced, Some(m), keep),
                    }
                }
            }
            if let Some((_, mut sum)) = median {
                // One value in the bin (a pixel-locked surface gives dozens of equal values):
                // it is the median, whatever the sums.
                if let Some(&(v, _)) = chosen.first()
                    && chosen.iter().all(|c| c.0.to_bits() == v.to_bits())
                {
                    *value = v;
                    continue;
                }
                chosen.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
                for &(v, weight) in &chosen {
                    sum += weight;
                    *value = v;
                    if sum >= half {
                        break;
                    }
                }
            }
        }
    });
    Ok(DisparityImage {
        width: w,
        height: h,
        data,
        confidence: disparity.confidence.clone(),
    })
}

/// The first index where the running sum of `sums`, starting from `below`, reaches `half`, and
/// the sum before it (the last index when rounding keeps it short).
fn reaching(sums: &[f32], mut below: f32, half: f32) -> (usize, f32) {
    for (i, s) in sums.iter().enumerate() {
        if below + s >= half {
            return (i, below);
        }
        below += s;
    }
    let last = sums.len().saturating_sub(1);
    (last, below - sums.get(last).copied().unwrap_or(0.0))
}

/// What a weighted median's window reads, per pixel: the estimates, their bins, the guide's
/// colours, the votes; and the colour weights by summed channel difference.
struct Sources<'a> {
    values: &'a [f32],
    bins: &'a [u16],
    colours: &'a [u8],
    votes: &'a [f32],
    colour: &'a [f32],
}

/// A weighted median window's weights summed by bin and by block of bins as they are gathered,
/// their total and the lowest and highest bins holding one.
struct Accumulated<'a> {
    sums: &'a mut [f32],
    block_sums: &'a mut [f32],
    total: f32,
    lowest: u16,
    highest: u16,
}

impl Accumulated<'_> {
    /// Adds `weight` to bin `b`.
    #[inline(always)]
    fn add(&mut self, weight: f32, b: u16) {
        let i = usize::from(b);
        self.total += weight;
        self.sums[i] += weight;
        self.block_sums[i / MEDIAN_BLOCK] += weight;
        self.lowest = self.lowest.min(b);
        self.highest = self.highest.max(b);
    }
}

/// Calls `f(value, weight, bin)` for one window row's finite values (those of bin `only` where
/// given), in order: pixels `first`, `first + step`, … (one per entry of `spaced`), each weight
/// the colour table at the summed channel difference from `centre`, times the row's spatial
/// weight, times the vote.
#[inline(always)]
fn visit<const C: usize>(
    centre: &[u8],
    sources: &Sources<'_>,
    (first, step): (usize, usize),
    spaced: &[f32],
    only: Option<u16>,
    mut f: impl FnMut(f32, f32, u16),
) {
    let centre: [u8; C] = std::array::from_fn(|k| centre[k]);
    let n = spaced.len();
    if n == 0 {
        return;
    }
    let last = first + (n - 1) * step;
    // Bounds checked once for the row, not per pixel.
    let (values, bins, votes) = (
        &sources.values[first..=last],
        &sources.bins[first..=last],
        &sources.votes[first..=last],
    );
    let colours = &sources.colours[first * C..(last + 1) * C];
    for (j, &space) in spaced.iter().enumerate() {
        let i = j * step;
        let (v, b) = (values[i], bins[i]);
        if v.is_finite() && only.is_none_or(|only| only == b) {
            let pixel = &colours[i * C..i * C + C];
            let diff: usize = (0..C).map(|k| centre[k].abs_diff(pixel[k]) as usize).sum();
            f(v, sources.colour[diff] * space * votes[i], b);
        }
    }
}

/// Bins per block of the weighted median's two-level search for its bin.
const MEDIAN_BLOCK: usize = 32;

/// Pixels a lane-wise median network handles at once (8 f32 lanes: one AVX2 register).
const MEDIAN_LANES: usize = 8;

/// [`median3x3`] of one pixel `(x, y)` into `value` (left alone where invalid); `rows` are the
/// rows above, at and below `y` (clamped).
fn median_at(
    data: &[f32],
    (w, h): (usize, usize),
    (x, y): (usize, usize),
    rows: &[&[f32]; 3],
    window: &mut Vec<f32>,
    value: &mut f32,
) {
    if !value.is_finite() {
        return;
    }
    if y > 0 && y + 1 < h && x > 0 && x + 1 < w {
        let mut p = [
            rows[0][x - 1],
            rows[0][x],
            rows[0][x + 1],
            rows[1][x - 1],
            rows[1][x],
            rows[1][x + 1],
            rows[2][x - 1],
            rows[2][x],
            rows[2][x + 1],
        ];
        if p.iter().all(|v| v.is_finite()) {
            *value = median_of_nine(&mut p);
            return;
        }
    }
    window.clear();
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            let v = data[yy * w + xx];
            if v.is_finite() {
                window.push(v);
            }
        }
    }
    window.sort_unstable_by(f32::total_cmp);
    *value = window[window.len() / 2];
}

/// [`median_of_nine`] of each lane: the same exchanges (and so the same values, bit for bit) on
/// `MEDIAN_LANES` pixels at once.
#[inline]
fn median_of_nine_lanes(p: &mut [[f32; MEDIAN_LANES]; 9]) -> [f32; MEDIAN_LANES] {
    for (a, b) in MEDIAN_EXCHANGES {
        let (pa, pb) = (p[a], p[b]);
        p[a] = std::array::from_fn(|i| pa[i].min(pb[i]));
        p[b] = std::array::from_fn(|i| pa[i].max(pb[i]));
    }
    p[4]
}

/// The median of nine finite values by the 19 compare-exchanges of Paeth's network.
#[inline]
fn median_of_nine(p: &mut [f32; 9]) -> f32 {
    for (a, b) in MEDIAN_EXCHANGES {
        let (low, high) = (p[a].min(p[b]), p[a].max(p[b]));
        p[a] = low;
        p[b] = high;
    }
    p[4]
}

/// Paeth's median-of-nine network: after these compare-exchanges, element 4 is the median.
const MEDIAN_EXCHANGES: [(usize, usize); 19] = [
    (1, 2),
    (4, 5),
    (7, 8),
    (0, 1),
    (3, 4),
    (6, 7),
    (1, 2),
    (4, 5),
    (7, 8),
    (0, 3),
    (5, 8),
    (4, 7),
    (3, 6),
    (1, 4),
    (2, 5),
    (4, 7),
    (4, 2),
    (6, 4),
    (4, 2),
];

/// Half-size of the window [`scale_by_local_consistency`] looks at.
pub const CONSISTENCY_RADIUS: usize = 2;

/// Scales each pixel's confidence by the consistency of the disparity around it:
/// `1 / (1 + max − min)` of the finite disparities in the `(2·CONSISTENCY_RADIUS + 1)²` window.
/// A pixel on or next to a depth edge, or in a noisy patch, is less sure than one inside a
/// smooth surface whatever its cost curve says (on Middlebury, the errors that remain after
/// the filters sit mostly there). Without a confidence nothing changes.
pub fn scale_by_local_consistency(disparity: &mut DisparityImage) {
    let (w, h) = (disparity.width, disparity.height);
    let Some(confidence) = disparity.confidence.as_mut() else {
        return;
    };
    if w == 0 || h == 0 {
        return;
    }
    let r = CONSISTENCY_RADIUS;
    // Row-wise minima and maxima of the finite values over the window's columns, then over its
    // rows; rows in parallel, each pass as elementwise minima of shifted rows (they vectorise).
    let mut row_lo = vec![f32::INFINITY; w * h];
    let mut row_hi = vec![f32::NEG_INFINITY; w * h];
    row_lo
        .par_chunks_mut(w)
        .zip(row_hi.par_chunks_mut(w))
        .zip(disparity.data.par_chunks(w))
        .for_each(|((lo, hi), row)| {
            // Invalid values become the neutral element of each side.
            let low: Vec<f32> = row
                .iter()
                .map(|v| if v.is_finite() { *v } else { f32::INFINITY })
                .collect();
            let high: Vec<f32> = row
                .iter()
                .map(|v| if v.is_finite() { *v } else { f32::NEG_INFINITY })
                .collect();
            sliding_extreme(&low, lo, r, f32::min);
            sliding_extreme(&high, hi, r, f32::max);
        });
    confidence.par_chunks_mut(w).enumerate().for_each(|(y, sure)| {
        let rows = y.saturating_sub(r)..(y + r + 1).min(h);
        let mut lo = row_lo[rows.start * w..(rows.start + 1) * w].to_vec();
        let mut hi = row_hi[rows.start * w..(rows.start + 1) * w].to_vec();
        for yy in rows.skip(1) {
            for (a, b) in lo.iter_mut().zip(&row_lo[yy * w..(yy + 1) * w]) {
                *a = a.min(*b);
            }
            for (a, b) in hi.iter_mut().zip(&row_hi[yy * w..(yy + 1) * w]) {
                *a = a.max(*b);
            }
        }
        for ((c, lo), hi) in sure.iter_mut().zip(&lo).zip(&hi) {
            if hi >= lo {
                *c /= 1.0 + (hi - lo);
            }
        }
    });
}

/// `out[x]` = `pick` over `values[x − r ..= x + r]` (the window clipped to the row): in the
/// row's interior as `2r` elementwise passes over shifted slices.
fn sliding_extreme(values: &[f32], out: &mut [f32], r: usize, pick: impl Fn(f32, f32) -> f32 + Copy) {
    let w = values.len();
    let clipped = |x: usize| {
        values[x.saturating_sub(r)..(x + r + 1).min(w)]
            .iter()
            .copied()
            .reduce(pick)
            .unwrap_or(f32::NAN)
    };
    if w <= 2 * r {
        for (x, o) in out.iter_mut().enumerate() {
            *o = clipped(x);
        }
        return;
    }
    let inner = r..w - r;
    out[inner.clone()].copy_from_slice(&values[..inner.len()]);
    for shift in 1..=2 * r {
        for (o, v) in out[inner.clone()].iter_mut().zip(&values[shift..]) {
            *o = pick(*o, *v);
        }
    }
    for x in (0..r).chain(w - r..w) {
        out[x] = clipped(x);
    }
}

#[cfg(test)]
mod tests {

    /// A disparity map of pseudo-random values with invalid pixels sprinkled in (`every`-th).
    fn speckled(width: usize, height: usize, every: usize) -> DisparityImage {
        let mut d = disparity(width, height, |x, y| {
            ((x * 7919 + y * 104_729) % 61) as f32 * 0.25 - 3.0
        });
        for (i, v) in d.data.iter_mut().enumerate() {
            if (i * 2_654_435_761) % every == 0 {
                *v = f32::INFINITY;
            }
        }
        d.confidence = Some((0..width * height).map(|i| (i % 13) as f32 / 13.0).collect());
        d
    }

    #[test]
    fn the_median_in_lanes_is_the_median_pixel_by_pixel() {
        for (w, h, every) in [(37, 11, 9), (64, 5, 1000), (9, 3, 7), (8, 8, 5), (2, 9, 3), (1, 1, 2)] {
            let d = speckled(w, h, every);
            let fast = median3x3(&d);
            let rows = |y: usize| [y.saturating_sub(1), y, (y + 1).min(h - 1)].map(|r| &d.data[r * w..(r + 1) * w]);
            let mut window = Vec::new();
            for y in 0..h {
                for x in 0..w {
                    let mut value = d.data[y * w + x];
                    median_at(&d.data, (w, h), (x, y), &rows(y), &mut window, &mut value);
                    assert_eq!(fast.data[y * w + x].to_bits(), value.to_bits(), "{w}×{h} at ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn consistency_scaling_is_the_plain_window_scan() {
        for (w, h, every) in [(37, 11, 9), (64, 6, 1000), (4, 3, 5), (5, 5, 2), (1, 7, 3)] {
            let mut d = speckled(w, h, every);
            let before = d.clone();
            scale_by_local_consistency(&mut d);
            let r = CONSISTENCY_RADIUS as isize;
            let confidence = before.confidence.as_deref().unwrap_or_default();
            for y in 0..h as isize {
                for x in 0..w as isize {
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let (xx, yy) = ((x + dx).clamp(0, w as isize - 1), (y + dy).clamp(0, h as isize - 1));
                            let v = before.data[(yy * w as isize + xx) as usize];
                            if v.is_finite() {
                                lo = lo.min(v);
                                hi = hi.max(v);
                            }
                        }
                    }
                    let i = (y * w as isize + x) as usize;
                    let expected = if hi >= lo {
                        confidence[i] / (1.0 + (hi - lo))
                    } else {
                        confidence[i]
                    };
                    let got = d.confidence.as_deref().unwrap_or_default()[i];
                    assert_eq!(got.to_bits(), expected.to_bits(), "{w}×{h} at ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn confidence_falls_next_to_a_depth_edge() {
        // A step from 2 to 6 px at x = 10: the windows of x = 8 … 11 see both sides (range 4).
        let mut d = disparity(20, 5, |x, _| if x < 10 { 2.0 } else { 6.0 });
        d.confidence = Some(vec![0.8; 100]);
        scale_by_local_consistency(&mut d);
        let c = d.confidence.unwrap_or_default();
        assert_eq!(c[2 * 20 + 7], 0.8, "inside the surface");
        assert!((c[2 * 20 + 8] - 0.8 / 5.0).abs() < 1e-6, "2 columns left of the step");
        assert!((c[2 * 20 + 11] - 0.8 / 5.0).abs() < 1e-6, "2 columns right of it");
        assert_eq!(c[2 * 20 + 12], 0.8);
    }
    use super::*;

    fn grey(width: usize, height: usize, value: impl Fn(usize, usize) -> u8) -> Image {
        let data = (0..width * height).map(|i| value(i % width, i / width)).collect();
        Image {
            width,
            height,
            channels: 1,
            data,
        }
    }

    fn disparity(width: usize, height: usize, value: impl Fn(usize, usize) -> f32) -> DisparityImage {
        DisparityImage {
            width,
            height,
            data: (0..width * height).map(|i| value(i % width, i / width)).collect(),
            confidence: None,
        }
    }

    #[test]
    fn a_slanted_plane_keeps_its_disparities_inside_the_window_margin() {
        let (w, h) = (48, 40);
        let plane = disparity(w, h, |x, y| 5.0 + 0.25 * x as f32 + 0.125 * y as f32);
        let image = grey(w, h, |x, y| ((x * 7 + y * 3) % 40) as u8 + 100);
        // Symmetric weights around the centre and values linear in the offset: the centre's.
        let flat = grey(w, h, |_, _| 90);
        let filter = WeightedMedian::default();
        let out = weighted_median(&plane, &flat, &filter).unwrap();
        let r = filter.radius_px;
        for y in r..h - r {
            for x in r..w - r {
                assert_eq!(out.data[y * w + x], plane.data[y * w + x], "({x}, {y})");
            }
        }
        // With texture the weights are no longer symmetric, but a value is only ever chosen.
        let textured = weighted_median(&plane, &image, &filter).unwrap();
        assert!(textured.data.iter().all(|v| plane.data.contains(v)));
    }

    #[test]
    fn a_fattened_foreground_snaps_back_to_the_colour_edge() {
        // Colour edge at x = 20; the foreground's disparity bleeds 3 px onto the background.
        let (w, h) = (40, 24);
        let image = grey(w, h, |x, _| if x < 20 { 60 } else { 190 });
        let fattened = disparity(w, h, |x, _| if x < 17 { 10.0 } else { 20.5 });
        let out = weighted_median(&fattened, &image, &WeightedMedian::default()).unwrap();
        for y in 0..h {
            for x in 0..w {
                let want = if x < 20 { 10.0 } else { 20.5 };
                assert_eq!(out.data[y * w + x], want, "({x}, {y})");
            }
        }
        // The plain 3×3 median keeps the bleed.
        assert_eq!(median3x3(&fattened).data[5 * w + 18], 20.5);
    }

    #[test]
    fn a_wide_band_of_foreground_moves_back_only_farther() {
        // Colour edge at x = 30; the foreground (x < 30, disparity 20) bleeds 10 px onto the
        // background (10), as wide as the first window's radius; a thin near rod (3 px,
        // disparity 25) of a colour of its own stands at x = 60..63.
        let (w, h) = (90, 40);
        let image = grey(w, h, |x, _| match x {
            0..30 => 60,
            60..63 => 120,
            _ => 190,
        });
        let truth = |x: usize| match x {
            0..30 => 20.0,
            60..63 => 25.0,
            _ => 10.0,
        };
        let fattened = disparity(w, h, |x, _| if x < 40 { 20.0 } else { truth(x) });
        let first = weighted_median(&fattened, &image, &WeightedMedian::default()).unwrap();
        let mut out = first.clone();
        farther_by_wider_median(&fattened, &image, &FartherMedian::default(), None, &mut out).unwrap();
        for y in 0..h {
            let row = |m: &DisparityImage| m.data[y * w..(y + 1) * w].to_vec();
            let (before, after) = (row(&first), row(&out));
            // The first filter leaves the band; the wider one takes most of it back.
            assert!(before[30..40].iter().all(|d| *d == 20.0), "row {y}: {before:?}");
            let back = after[30..40].iter().filter(|d| **d == 10.0).count();
            assert!(back >= 5, "row {y}: {back} of the band's 10 px back: {after:?}");
            for x in 0..w {
                // Farther only: never nearer than the first filter's answer, a value of the map.
                assert!(
                    after[x] <= before[x] && (after[x] == 10.0 || after[x] == before[x]),
                    "({x}, {y})"
                );
                if !(30..40).contains(&x) {
                    assert_eq!(after[x], truth(x), "kept at ({x}, {y})");
                }
            }
        }
        // The same as the wider filter run at every pixel.
        let wide = weighted_median(&fattened, &image, &FartherMedian::default().filter).unwrap();
        let mut everywhere = first.clone();
        for (d, f) in everywhere.data.iter_mut().zip(&wide.data) {
            if *f < *d - FartherMedian::default().min_move_px {
                *d = *f;
            }
        }
        assert_eq!(out, everywhere);
        // A move below `min_move_px` is not taken.
        let mut small = first.clone();
        let far = FartherMedian {
            min_move_px: 10.0,
            ..Default::default()
        };
        farther_by_wider_median(&fattened, &image, &far, None, &mut small).unwrap();
        assert_eq!(small, first);
        let bad = FartherMedian {
            min_move_px: -1.0,
            ..Default::default()
        };
        assert!(matches!(
            farther_by_wider_median(&fattened, &image, &bad, None, &mut small),
            Err(FuseError::Config {
                field: "farther_median.min_move_px",
                ..
            })
        ));
    }

    #[test]
    fn a_huge_range_of_values_is_filtered_with_coarser_bins() {
        let (w, h) = (16, 12);
        let d = disparity(
            w,
            h,
            |x, y| if (x + y) % 7 == 0 { 3.0e9 } else { 5.0 + x as f32 * 0.01 },
        );
        let f = WeightedMedian {
            radius_px: 3,
            step_px: 1,
            ..Default::default()
        };
        let out = weighted_median(&d, &grey(w, h, |_, _| 50), &f).unwrap();
        let plain = plain_weighted_median(&d, &grey(w, h, |_, _| 50), &f);
        assert_eq!(plain.len(), out.data.len());
        let mut compared = 0;
        for (got, (want, margin)) in out.data.iter().zip(plain) {
            if margin > 1e-5 {
                assert_eq!(*got, want);
                compared += 1;
            }
        }
        assert!(compared > w * h / 2, "only {compared} clear decisions");
        assert!(out.data.iter().all(|v| *v < 1.0e9), "the outliers are voted out");
    }

    #[test]
    fn invalid_pixels_stay_invalid_and_do_not_vote() {
        let (w, h) = (20, 16);
        let image = grey(w, h, |_, _| 128);
        let d = disparity(w, h, |x, y| match (x + y) % 5 {
            0 => f32::INFINITY,
            _ => 7.0 + (x % 3) as f32 * 0.1,
        });
        let out = weighted_median(&d, &image, &WeightedMedian::default()).unwrap();
        for (a, b) in d.data.iter().zip(&out.data) {
            assert_eq!(a.is_finite(), b.is_finite());
            if b.is_finite() {
                assert!((7.0..=7.2).contains(b));
            }
        }
    }

    #[test]
    fn the_box_minimum_is_the_least_finite_value_of_each_box() {
        let (w, h) = (37, 23);
        let data: Vec<f32> = (0..w * h)
            .map(|i| match i % 11 {
                3 => f32::NAN,
                7 => f32::INFINITY,
                _ => ((i * 7919) % 101) as f32 / 7.0,
            })
            .collect();
        let d = DisparityImage {
            width: w,
            height: h,
            data,
            confidence: None,
        };
        for radius in [0, 1, 4, 20, 40] {
            let got = box_minimum(&d, radius);
            for y in 0..h {
                for x in 0..w {
                    let mut want = f32::INFINITY;
                    for yy in y.saturating_sub(radius)..(y + radius + 1).min(h) {
                        for xx in x.saturating_sub(radius)..(x + radius + 1).min(w) {
                            let v = d.data[yy * w + xx];
                            if v.is_finite() {
                                want = want.min(v);
                            }
                        }
                    }
                    assert_eq!(got[y * w + x], want, "radius {radius} at ({x}, {y})");
                }
            }
        }
    }

    /// The weighted median by the definition: every window value sorted, in f64.
    fn plain_weighted_median(d: &DisparityImage, image: &Image, f: &WeightedMedian) -> Vec<(f32, f64)> {
        plain_with_votes(d, image, f, &vec![1.0; d.data.len()])
    }

    fn plain_with_votes(d: &DisparityImage, image: &Image, f: &WeightedMedian, votes: &[f32]) -> Vec<(f32, f64)> {
        let (w, h, c) = (d.width as isize, d.height as isize, image.channels);
        let (step, reach) = (f.step_px as isize, (f.radius_px / f.step_px) as isize);
        let mut out = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let at = (y * w + x) as usize;
                if !d.data[at].is_finite() {
                    out.push((d.data[at], 1.0));
                    continue;
                }
                let mut window = Vec::new();
                for ky in -reach..=reach {
                    for kx in -reach..=reach {
                        let (xx, yy) = (x + kx * step, y + ky * step);
                        if xx < 0 || yy < 0 || xx >= w || yy >= h {
                            continue;
                        }
                        let q = (yy * w + xx) as usize;
                        if !d.data[q].is_finite() {
                            continue;
                        }
                        let diff: f64 = (0..c)
                            .map(|k| (f64::from(image.data[at * c + k]) - f64::from(image.data[q * c + k])).abs())
                            .sum();
                        let r2 = ((kx * kx + ky * ky) * step * step) as f64;
                        let sigma = f64::from(f.sigma_space_px);
                        let weight = (-diff / c as f64 / f64::from(f.sigma_colour) - r2 / (2.0 * sigma * sigma)).exp();
                        window.push((d.data[q], weight * f64::from(votes[q])));
                    }
                }
                window.sort_by(|a, b| a.0.total_cmp(&b.0));
                let total: f64 = window.iter().map(|p| p.1).sum();
                if total <= 0.0 {
                    out.push((d.data[at], 1.0));
                    continue;
                }
                let mut sum = 0.0;
                // The value, and how close its decision was (distance of half from a step).
                let mut pick = (window[0].0, f64::INFINITY);
                for &(v, weight) in &window {
                    let margin = ((sum - total / 2.0).abs()).min((sum + weight - total / 2.0).abs()) / total;
                    sum += weight;
                    if sum >= total / 2.0 {
                        pick = (v, margin);
                        break;
                    }
                }
                out.push(pick);
            }
        }
        out
    }

    #[test]
    fn the_binned_filter_equals_the_plain_definition_on_random_maps() {
        let mut state = 5u32;
        let mut next = move || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            state >> 8
        };
        // The clusters 17.3 px apart, or 1730 px (bins coarser than 1/64 px: at most 4096 of them).
        for case in [
            (37, 29, 3, WeightedMedian::default(), 17.3),
            (23, 31, 1, WeightedMedian::default(), 17.3),
            (29, 23, 3, WeightedMedian::default(), 1730.0),
            (
                30,
                20,
                3,
                WeightedMedian {
                    radius_px: 4,
                    step_px: 1,
                    sigma_colour: 20.0,
                    sigma_space_px: 3.0,
                },
                17.3,
            ),
        ]
        .into_iter()
        .flat_map(|case| [(case, false), (case, true)])
        {
            let ((w, h, channels, f, apart), locked) = case;
            let image = Image {
                width: w,
                height: h,
                channels,
                data: (0..w * h * channels).map(|_| (next() % 256) as u8).collect(),
            };
            // Values in a few clusters (several per bin) and some invalid pixels; `locked`:
            // on quarter pixels, as a pixel-locked estimate (bins holding only equal values).
            let d = DisparityImage {
                width: w,
                height: h,
                data: (0..w * h)
                    .map(|_| match next() % 10 {
                        0 => f32::INFINITY,
                        k => {
                            let v = (k % 3) as f32 * apart + (next() % 1000) as f32 / 997.0;
                            if locked { (v * 4.0).round() / 4.0 } else { v }
                        }
                    })
                    .collect(),
                confidence: None,
            };
            // Votes: all 1, then a third of the pixels at 0.05 and some at 0.
            let ones = vec![1.0f32; w * h];
            let mixed: Vec<f32> = (0..w * h)
                .map(|_| match next() % 9 {
                    0 => 0.0,
                    1..=3 => 0.05,
                    _ => 1.0,
                })
                .collect();
            for votes in [&ones, &mixed] {
                let fast = weighted_median_with_votes(&d, &image, &f, Some(votes)).unwrap();
                let plain = plain_with_votes(&d, &image, &f, votes);
                let mut compared = 0;
                for (i, (&got, &(want, margin))) in fast.data.iter().zip(&plain).enumerate() {
                    if margin > 1e-5 {
                        assert_eq!(got.to_bits(), want.to_bits(), "{w}x{h}x{channels} pixel {i}");
                        compared += 1;
                    }
                }
                assert!(compared > w * h * 8 / 10, "only {compared} clear decisions");
            }
            let plain = weighted_median(&d, &image, &f).unwrap();
            let all_ones = weighted_median_with_votes(&d, &image, &f, Some(&ones)).unwrap();
            assert_eq!(plain, all_ones);
        }
    }

    #[test]
    fn bad_parameters_and_sizes_are_errors_naming_them() {
        let d = disparity(8, 8, |_, _| 1.0);
        let image = grey(8, 8, |_, _| 1);
        for (f, field) in [
            (
                WeightedMedian {
                    sigma_colour: 0.0,
                    ..Default::default()
                },
                "weighted_median.sigma_colour",
            ),
            (
                WeightedMedian {
                    sigma_space_px: f32::NAN,
                    ..Default::default()
                },
                "weighted_median.sigma_space_px",
            ),
            (
                WeightedMedian {
                    step_px: 0,
                    ..Default::default()
                },
                "weighted_median.step_px",
            ),
            (
                WeightedMedian {
                    radius_px: 65,
                    ..Default::default()
                },
                "weighted_median.radius_px",
            ),
        ] {
            match weighted_median(&d, &image, &f) {
                Err(FuseError::Config { field: got, .. }) => assert_eq!(got, field),
                other => panic!("{field}: {other:?}"),
            }
        }
        assert!(matches!(
            weighted_median_with_votes(&d, &image, &WeightedMedian::default(), Some(&[1.0; 63])),
            Err(FuseError::ImageSize { len: 63, .. })
        ));
        let small = grey(8, 7, |_, _| 1);
        assert!(matches!(
            weighted_median(&d, &small, &WeightedMedian::default()),
            Err(FuseError::ImageSize { .. })
        ));
    }

    #[test]
    fn median_removes_a_spike() {
        let mut data = vec![3.0f32; 25];
        data[12] = 40.0;
        let out = median3x3(&DisparityImage {
            width: 5,
            height: 5,
            data,
            confidence: None,
        });
        assert!(out.data.iter().all(|d| *d == 3.0));
    }

    #[test]
    fn the_network_gives_the_sorted_median() {
        let mut state = 11u32;
        for _ in 0..5000 {
            let mut values = [0.0f32; 9];
            for v in &mut values {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                *v = (state >> 20) as f32 / 16.0;
            }
            let mut sorted = values;
            sorted.sort_unstable_by(f32::total_cmp);
            assert_eq!(median_of_nine(&mut values), sorted[4]);
        }
    }
}
