//! Matching costs between the reference view and one neighbour, and their box aggregation.
//!
//! Costs are `u16`, laid out per image row as `[x][d]` (disparity fastest), and computed for the
//! correspondence `q = p − offset·d`, where `offset` is the neighbour's position in baselines
//! along the reference camera's x and y (right `[1, 0]`, left `[-1, 0]`, top `[0, -1]`, …).
//! One code path therefore serves horizontal, vertical and diagonal neighbours.

use std::ops::Range;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::image::Image;

/// Marks a cost whose correspondence falls outside the neighbour image.
pub const INVALID_COST: u16 = u16::MAX;
/// Largest block radius: (2·7+1)² · 255 still fits `u16`.
pub const MAX_BLOCK_RADIUS: usize = 7;
/// Largest census window radius (a 7×9 window fills 63 bits).
pub const MAX_CENSUS_RADIUS: usize = 3;

/// Per-pixel dissimilarity. Absolute difference and Birchfield–Tomasi use every channel of the
/// views (absolute differences: the mean over R, G, B for colour views; Birchfield–Tomasi: the
/// channels' halves summed, `colour_birchfield_tomasi`); census uses luma.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", tag = "kind")]
pub enum PixelCost {
    /// Absolute difference of grey values (summed over the block: SAD).
    AbsoluteDifference,
    /// Birchfield–Tomasi, the paper's variant: the neighbour's half-pixel interpolants are taken
    /// over its 4-neighbourhood (left, right, up, down), which tolerates small epipolar errors.
    BirchfieldTomasi,
    /// Census transform over a `(2r+1)×(2r+1)` window, Hamming distance.
    Census {
        /// Window radius (1..=3).
        radius: usize,
        /// The centre-symmetric census (Spangenberg et al. 2013): each bit compares a window
        /// position with its mirror through the centre instead of with the centre, so the code
        /// has half the bits (24 for 7×7) and the distance half the work; each differing bit
        /// counts twice, so that costs keep the full census's scale (and SGM its penalties).
        #[serde(default, skip_serializing_if = "is_false")]
        symmetric: bool,
    },
}

/// `skip_serializing_if` of a default-false flag (the configuration written stays as it was).
#[allow(clippy::trivially_copy_pass_by_ref)]
fn is_false(value: &bool) -> bool {
    !*value
}

/// A view prepared for one pixel cost: its pixels plus what the cost needs.
#[derive(Debug, Clone)]
pub struct PreparedView {
    image: Image,
    /// Birchfield–Tomasi: smallest half-pixel interpolant around each pixel, per channel.
    bt_min: Vec<u8>,
    /// Birchfield–Tomasi: largest half-pixel interpolant around each pixel, per channel.
    bt_max: Vec<u8>,
    /// Census codes (of the luma) sliced into bytes: plane `b`, pixel `p` holds bits
    /// `8b .. 8b + 8` of the code of `p` (see [`census_planes`]).
    census: Vec<Vec<u8>>,
}

impl PreparedView {
    /// Prepares `image` for `cost`.
    pub fn new(image: Image, cost: PixelCost) -> Self {
        let (mut bt_min, mut bt_max, mut census) = (Vec::new(), Vec::new(), Vec::new());
        match cost {
            PixelCost::AbsoluteDifference => {}
            PixelCost::BirchfieldTomasi => (bt_min, bt_max) = birchfield_tomasi_bounds(&image),
            PixelCost::Census { radius, symmetric } => {
                census = census_planes(&image.to_gray(), radius.clamp(1, MAX_CENSUS_RADIUS), symmetric);
            }
        }
        Self {
            image,
            bt_min,
            bt_max,
            census,
        }
    }

    /// The view's pixels.
    pub fn image(&self) -> &Image {
        &self.image
    }

    /// Birchfield–Tomasi bounds (smallest, largest half-pixel interpolant), per pixel and channel.
    pub fn bt_bounds(&self) -> (&[u8], &[u8]) {
        (&self.bt_min, &self.bt_max)
    }

    /// Census codes as byte planes (plane `b`: bits `8b .. 8b + 8` of every pixel's code).
    pub fn census_planes(&self) -> &[Vec<u8>] {
        &self.census
    }
}

/// Birchfield–Tomasi bounds of every pixel and channel: the smallest and largest of the pixel
/// and its half-pixel interpolants towards its 4-neighbours (left, right, up, down; borders
/// replicated), `(c + n) / 2` rounded down.
fn birchfield_tomasi_bounds(image: &Image) -> (Vec<u8>, Vec<u8>) {
    let stride = image.width * image.channels;
    let mut bt_min = vec![0u8; image.data.len()];
    let mut bt_max = vec![0u8; image.data.len()];
    for (y, (lo, hi)) in bt_min
        .chunks_exact_mut(stride.max(1))
        .zip(bt_max.chunks_exact_mut(stride.max(1)))
        .enumerate()
    {
        birchfield_tomasi_row(image, y, lo, hi);
    }
    (bt_min, bt_max)
}

/// [`birchfield_tomasi_bounds`] of row `y` into `lo` and `hi` (`width × channels` each).
pub(crate) fn birchfield_tomasi_row(image: &Image, y: usize, lo: &mut [u8], hi: &mut [u8]) {
    let (w, h, channels) = (image.width, image.height, image.channels);
    let stride = w * channels;
    let half = |c: u8, n: u8| ((u16::from(c) + u16::from(n)) / 2) as u8;
    let row = &image.data[y * stride..(y + 1) * stride];
    let up = &image.data[y.saturating_sub(1) * stride..][..stride];
    let down = &image.data[(y + 1).min(h - 1) * stride..][..stride];
    let (lo, hi) = (&mut lo[..stride], &mut hi[..stride]);
    // Interior columns: straight slices that the compiler vectorises.
    if w > 2 {
        let inner = channels..stride - channels;
        let (centre, left, right) = (&row[inner.clone()], &row[..stride - 2 * channels], &row[2 * channels..]);
        let (up, down) = (&up[inner.clone()], &down[inner.clone()]);
        let (lo, hi) = (&mut lo[inner.clone()], &mut hi[inner]);
        for i in 0..centre.len() {
            let c = centre[i];
            let (a, b, u, d) = (half(c, left[i]), half(c, right[i]), half(c, up[i]), half(c, down[i]));
            lo[i] = c.min(a).min(b).min(u).min(d);
            hi[i] = c.max(a).max(b).max(u).max(d);
        }
    }
    // Border columns (or every column of a narrow image).
    for x in (0..w).filter(|x| *x == 0 || *x + 1 >= w) {
        for channel in 0..channels {
            let i = x * channels + channel;
            let c = row[i];
            let left = row[x.saturating_sub(1) * channels + channel];
            let right = row[(x + 1).min(w - 1) * channels + channel];
            let (a, b, u, d) = (half(c, left), half(c, right), half(c, up[i]), half(c, down[i]));
            lo[i] = c.min(a).min(b).min(u).min(d);
            hi[i] = c.max(a).max(b).max(u).max(d);
        }
    }
}

/// A grey image with `r` replicated border pixels on every side, and its row length.
pub(crate) fn padded_gray(gray: &Image, r: usize) -> (Vec<u8>, usize) {
    let (w, h) = (gray.width, gray.height);
    let padded_w = w + 2 * r;
    let mut padded = Vec::with_capacity(padded_w * (h + 2 * r));
    for py in 0..h + 2 * r {
        let y = py as isize - r as isize;
        for px in 0..padded_w {
            padded.push(gray.clamped(px as isize - r as isize, y, 0));
        }
    }
    (padded, padded_w)
}

/// Census codes of a grey image as byte planes: plane `b` holds bits `8b .. 8b + 8` of
/// [`census_transform`]'s codes. Each byte is built from eight comparisons on 32 byte lanes,
/// eight times less work than shifting whole 64-bit codes.
pub fn census_planes(gray: &Image, radius: usize, symmetric: bool) -> Vec<Vec<u8>> {
    let (w, h, r) = (gray.width, gray.height, radius);
    let (padded, padded_w) = padded_gray(gray, r);
    (0..census_plane_count(r, symmetric))
        .map(|b| {
            let mut plane = vec![0u8; w * h];
            plane.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                census_row((&padded, padded_w), (r, symmetric), y, b, row);
            });
            plane
        })
        .collect()
}

/// Bits of a census code over a `(2r+1)²` window: every position but the centre, or (the
/// centre-symmetric census) the positions before the centre, each paired with its mirror.
pub(crate) fn census_bits(r: usize, symmetric: bool) -> usize {
    let positions = (2 * r + 1).pow(2) - 1;
    if symmetric { positions / 2 } else { positions }
}

/// Byte planes of a census code over a `(2r+1)²` window.
pub(crate) fn census_plane_count(r: usize, symmetric: bool) -> usize {
    census_bits(r, symmetric).div_ceil(8)
}

/// Plane `b` of [`census_planes`] for row `y` into `row` (its `width` bytes, all overwritten), from
/// the padded grey image ([`padded_gray`] with radius `r`).
pub(crate) fn census_row(
    (padded, padded_w): (&[u8], usize),
    (r, symmetric): (usize, bool),
    y: usize,
    b: usize,
    row: &mut [u8],
) {
    let w = row.len();
    let side = 2 * r + 1;
    let bits = census_bits(r, symmetric);
    row.fill(0);
    for j in 0..8 {
        let Some(i) = (bits - 1).checked_sub(8 * b + j) else {
            break;
        };
        // The i-th window position in code order (row-major, the centre skipped) sits at bit
        // `bits − 1 − i`; it is compared with the centre, or with its mirror through the centre
        // (the symmetric census, whose positions all come before the centre).
        let i = if !symmetric && i >= side * r + r { i + 1 } else { i };
        let (dx, dy) = (i % side, i / side);
        let (ox, oy) = if symmetric { (2 * r - dx, 2 * r - dy) } else { (r, r) };
        let source = &padded[(y + dy) * padded_w + dx..][..w];
        let other = &padded[(y + oy) * padded_w + ox..][..w];
        for ((value, s), c) in row.iter_mut().zip(source).zip(other) {
            *value |= u8::from(s < c) << j;
        }
    }
}

/// Census codes of a grey image over a `(2r+1)²` window, border replicated: bit set where the
/// neighbour is darker than the centre, row-major over the window without the centre (the
/// centre-symmetric census: where a position before the centre is darker than its mirror
/// through it). Works on a padded copy so that the inner loops index without clamping.
pub fn census_transform(gray: &Image, radius: usize, symmetric: bool) -> Vec<u64> {
    let (w, h, r) = (gray.width, gray.height, radius);
    let (padded, padded_w) = padded_gray(gray, r);
    let mut codes = vec![0u64; w * h];
    let bits = census_bits(r, symmetric);
    codes.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let positions = (0..(2 * r + 1).pow(2)).filter(|i| *i != (2 * r + 1) * r + r);
        for i in positions.take(bits) {
            let (dx, dy) = (i % (2 * r + 1), i / (2 * r + 1));
            let (ox, oy) = if symmetric { (2 * r - dx, 2 * r - dy) } else { (r, r) };
            let source = &padded[(y + dy) * padded_w + dx..][..w];
            let other = &padded[(y + oy) * padded_w + ox..][..w];
            for ((code, s), c) in row.iter_mut().zip(source).zip(other) {
                *code = (*code << 1) | u64::from(s < c);
            }
        }
    });
    codes
}

/// Pixel costs of reference row `y`, columns `xs`, against a neighbour for disparities
/// `min_disparity .. min_disparity + disparities`, written as `[x][d]` into `out`
/// (`xs.len() × disparities`, one byte each: every pixel cost fits 0..=255). Columns outside the
/// image repeat the border column (the block aggregation replicates borders); correspondences
/// outside the neighbour are clamped to its border here and flagged by [`mark_invalid`] after
/// aggregation. The generic path for any offset (diagonal neighbours); axis neighbours use
/// [`crate::lines::pixel_cost_tile_lines`], which gives the same values faster.
#[allow(clippy::too_many_arguments)]
pub fn pixel_cost_tile(
    cost: PixelCost,
    reference: &PreparedView,
    neighbour: &PreparedView,
    offset: [i32; 2],
    y: usize,
    xs: Range<isize>,
    min_disparity: i32,
    num_disparities: usize,
    out: &mut [u8],
) {
    let width = reference.image.width;
    let height = neighbour.image.height as isize;
    let channels = reference.image.channels;
    let (ox, oy) = (offset[0] as isize, offset[1] as isize);
    for (costs, x) in out.chunks_exact_mut(num_disparities).zip(xs) {
        let x = x.clamp(0, width as isize - 1) as usize;
        let base_qx = x as isize - ox * min_disparity as isize;
        let base_qy = y as isize - oy * min_disparity as isize;
        let pixel = |d: usize| {
            let qx = (base_qx - ox * d as isize).clamp(0, width as isize - 1) as usize;
            let qy = (base_qy - oy * d as isize).clamp(0, height - 1) as usize;
            qy * width + qx
        };
        let p = (y * width + x) * channels;
        let c = &reference.image.data[p..p + channels];
        match (cost, channels) {
            (PixelCost::AbsoluteDifference, 1) => {
                for (d, out) in costs.iter_mut().enumerate() {
                    *out = c[0].abs_diff(neighbour.image.data[pixel(d)]);
                }
            }
            (PixelCost::AbsoluteDifference, _) => {
                for (d, out) in costs.iter_mut().enumerate() {
                    let q = pixel(d) * channels;
                    let n = &neighbour.image.data[q..q + channels];
                    let sum: u16 = c.iter().zip(n).map(|(a, b)| u16::from(a.abs_diff(*b))).sum();
                    *out = mean_of_channels(sum, channels);
                }
            }
            (PixelCost::BirchfieldTomasi, _) => {
                for (d, out) in costs.iter_mut().enumerate() {
                    let q = pixel(d) * channels;
                    let bt = |k: usize| {
                        let above = c[k].saturating_sub(neighbour.bt_max[q + k]);
                        let below = neighbour.bt_min[q + k].saturating_sub(c[k]);
                        above.max(below)
                    };
                    *out = if channels == 3 {
                        colour_birchfield_tomasi(bt(0), bt(1), bt(2))
                    } else {
                        bt(0)
                    };
                }
            }
            (PixelCost::Census { symmetric, .. }, _) => {
                let p = y * width + x;
                for (d, out) in costs.iter_mut().enumerate() {
                    let q = pixel(d);
                    let distance: u8 = reference
                        .census
                        .iter()
                        .zip(&neighbour.census)
                        .map(|(a, b)| (a[p] ^ b[q]).count_ones() as u8)
                        .sum();
                    *out = distance << u8::from(symmetric);
                }
            }
        }
    }
}

/// The Birchfield–Tomasi cost of a colour pixel from its three channels' costs: each halved
/// (rounded down) and the halves summed, saturating at 255: 1.5 × the channels' mean up to a
/// mean of 170 levels, clipped above. In byte lanes only (32 to an AVX2 register; the exact mean
/// needs 16-bit lanes), so the colour cost loop runs in about half the instructions; and the
/// clip, a truncated cost, matched as well as the mean or better on nearly every set measured
/// (dev scenes `bm-heuristic` AvgErr 0.696 → 0.675 px, slanted planes' BadPix 0.07 16.6 →
/// 14.9 %; the `thin` family +0.5 %; docs/experiments.md, "The colour cost in bytes").
#[inline]
pub(crate) fn colour_birchfield_tomasi(r: u8, g: u8, b: u8) -> u8 {
    (r >> 1).saturating_add(g >> 1).saturating_add(b >> 1)
}

/// `⌊s / 3⌋` for a sum of three channel costs (s ≤ 765) in 16-bit arithmetic only, so that the
/// cost loops vectorise on 16-bit lanes: with s = 256·h + l, `⌊s/3⌋ = 85·h + ⌊(h + l)/3⌋` (as
/// 256 = 3·85 + 1), and `⌊t/3⌋ = (171·t) >> 9` is exact for t ≤ 257.
#[inline]
pub(crate) fn mean_of_three(sum: u16) -> u8 {
    let (high, low) = (sum >> 8, sum & 0xFF);
    (85 * high + ((171 * (high + low)) >> 9)) as u8
}

/// Mean of `channels` (1 or 3) channel costs summing to `sum`, rounded down.
#[inline]
pub(crate) fn mean_of_channels(sum: u16, channels: usize) -> u8 {
    if channels == 3 {
        mean_of_three(sum)
    } else {
        sum.min(255) as u8
    }
}

/// Sets to [`INVALID_COST`] every `(x, d)` of the `[x][d]` costs of reference pixels
/// `(x_start.., y)` whose correspondence lies outside the neighbour image. `baseline_ratio`
/// scales the disparity of this neighbour (see [`DisparityResampler`]).
pub fn mark_invalid(
    costs: &mut [u16],
    offset: [i32; 2],
    (x_start, y): (usize, usize),
    size: (usize, usize),
    disparity_axis: (i32, usize),
    baseline_ratio: f32,
) {
    let (min_disparity, disparities) = disparity_axis;
    let (width, height) = (size.0 as f32, size.1 as f32);
    let (ox, oy) = (offset[0] as f32, offset[1] as f32);
    let valid = |x: usize, d: usize| {
        let disparity = (min_disparity as f32 + d as f32) * baseline_ratio;
        let qx = (x as f32 - ox * disparity).round();
        let qy = (y as f32 - oy * disparity).round();
        qx >= 0.0 && qx < width && qy >= 0.0 && qy < height
    };
    let pixels = costs.len() / disparities.max(1);
    if pixels == 0 {
        return;
    }
    // The correspondence is a rounded affine function of (x, d), so the valid (x, d) form a convex
    // set: when the four corners of the row's (x, d) rectangle are valid, every cost is.
    let x_end = x_start + pixels - 1;
    let last_d = disparities - 1;
    if valid(x_start, 0) && valid(x_start, last_d) && valid(x_end, 0) && valid(x_end, last_d) {
        return;
    }
    for (x, costs) in (x_start..).zip(costs.chunks_exact_mut(disparities)) {
        // The correspondence moves monotonically with d: the valid disparities form one interval.
        if valid(x, 0) && valid(x, last_d) {
            continue;
        }
        let first = (0..disparities).find(|d| valid(x, *d)).unwrap_or(disparities);
        let last = (first..disparities)
            .rev()
            .find(|d| valid(x, *d))
            .map_or(first, |d| d + 1);
        costs[..first].fill(INVALID_COST);
        costs[last..].fill(INVALID_COST);
    }
}

/// The disparities whose correspondence stays inside the neighbour image, tabulated once per
/// neighbour: the horizontal condition depends only on the column, the vertical one only on the
/// row, and each allows one interval of disparities. Gives the same marks as [`mark_invalid`].
#[derive(Debug, Clone)]
pub struct ValidDisparities {
    /// `[first, end)` allowed by the column, per reference column.
    by_column: Vec<(usize, usize)>,
    /// `[first, end)` allowed by the row, per reference row.
    by_row: Vec<(usize, usize)>,
    num_disparities: usize,
}

impl ValidDisparities {
    /// Tabulates the valid disparities of a neighbour at `offset` (see [`mark_invalid`]).
    pub fn new(offset: [i32; 2], size: (usize, usize), disparity_axis: (i32, usize), baseline_ratio: f32) -> Self {
        let (min_disparity, num_disparities) = disparity_axis;
        let interval = |position: usize, step: i32, limit: usize| {
            let inside = |d: usize| {
                let disparity = (min_disparity as f32 + d as f32) * baseline_ratio;
                let q = (position as f32 - step as f32 * disparity).round();
                q >= 0.0 && q < limit as f32
            };
            let first = (0..num_disparities).find(|d| inside(*d)).unwrap_or(num_disparities);
            let end = (first..num_disparities)
                .rev()
                .find(|d| inside(*d))
                .map_or(first, |d| d + 1);
            (first, end)
        };
        Self {
            by_column: (0..size.0).map(|x| interval(x, offset[0], size.0)).collect(),
            by_row: (0..size.1).map(|y| interval(y, offset[1], size.1)).collect(),
            num_disparities,
        }
    }

    /// The disparities `[first, end)` (indices into the axis) whose correspondence from pixel
    /// `(x, y)` stays inside the neighbour image.
    pub fn at(&self, x: usize, y: usize) -> (usize, usize) {
        let nd = self.num_disparities;
        Self::both(
            self.by_row.get(y).copied().unwrap_or((nd, nd)),
            self.by_column.get(x).copied().unwrap_or((nd, nd)),
            nd,
        )
    }

    /// The disparities allowed by both a row's and a column's interval.
    fn both(
        (row_first, row_end): (usize, usize),
        (column_first, column_end): (usize, usize),
        nd: usize,
    ) -> (usize, usize) {
        let first = row_first.max(column_first).min(nd);
        (first, row_end.min(column_end).max(first))
    }

    /// Sets to [`INVALID_COST`] the costs (`[x][d]`, columns `x_start ..` of row `y`) whose
    /// correspondence leaves the neighbour image.
    pub fn mark(&self, costs: &mut [u16], (x_start, y): (usize, usize)) {
        let nd = self.num_disparities;
        let row = self.by_row[y];
        let columns = &self.by_column[x_start..];
        for (costs, &column) in costs.chunks_exact_mut(nd).zip(columns) {
            let (first, end) = Self::both(row, column, nd);
            if first == 0 && end == nd {
                continue;
            }
            costs[..first].fill(INVALID_COST);
            costs[end..].fill(INVALID_COST);
        }
    }
}

/// Resamples `[x][d]` costs along the disparity axis for a neighbour whose real baseline is
/// `ratio` × the nominal one: its cost at the common disparity `d` is its own cost at `d · ratio`,
/// linearly interpolated. The interpolation table is the same for every pixel and built once.
#[derive(Debug, Clone)]
pub struct DisparityResampler {
    /// Per common disparity: lower source index, upper source index, weight of the upper in 1/256.
    table: Vec<(usize, usize, u32)>,
    /// Runs of disparities whose source indices both advance by one per disparity, so that
    /// each run is one vectorised loop over contiguous slices.
    runs: Vec<ResampleRun>,
}

/// Disparities `start .. end` read sources `lower .. lower + len` and `upper .. upper + len`.
#[derive(Debug, Clone, Copy)]
struct ResampleRun {
    start: usize,
    end: usize,
    lower: usize,
    upper: usize,
}

impl DisparityResampler {
    /// `None` when `ratio` is 1 (nothing to resample).
    pub fn new(min_disparity: i32, num_disparities: usize, ratio: f32) -> Option<Self> {
        if (ratio - 1.0).abs() < 1e-6 || num_disparities == 0 {
            return None;
        }
        let table: Vec<(usize, usize, u32)> = (0..num_disparities)
            .map(|d| {
                let source = ((min_disparity as f32 + d as f32) * ratio - min_disparity as f32)
                    .clamp(0.0, (num_disparities - 1) as f32);
                let lower = source.floor() as usize;
                let upper = (lower + 1).min(num_disparities - 1);
                (lower, upper, ((source - lower as f32) * 256.0).round() as u32)
            })
            .collect();
        let mut runs: Vec<ResampleRun> = Vec::new();
        for (d, &(lower, upper, _)) in table.iter().enumerate() {
            match runs.last_mut() {
                Some(run) if run.lower + (d - run.start) == lower && run.upper + (d - run.start) == upper => {
                    run.end = d + 1;
                }
                _ => runs.push(ResampleRun {
                    start: d,
                    end: d + 1,
                    lower,
                    upper,
                }),
            }
        }
        Some(Self { table, runs })
    }

    /// Resamples every pixel of `costs` (`[x][d]`) in place; `scratch` holds a copy of them.
    pub fn apply(&self, costs: &mut [u16], scratch: &mut Vec<u16>) {
        let disparities = self.table.len();
        scratch.clear();
        scratch.extend_from_slice(costs);
        for (costs, scratch) in costs
            .chunks_exact_mut(disparities)
            .zip(scratch.chunks_exact(disparities))
        {
            for run in &self.runs {
                let len = run.end - run.start;
                let lower = &scratch[run.lower..run.lower + len];
                let upper = &scratch[run.upper..run.upper + len];
                let weights = &self.table[run.start..run.end];
                let out = &mut costs[run.start..run.end];
                for i in 0..len {
                    let (a, b, w) = (lower[i], upper[i], weights[i].2);
                    let mixed = ((u32::from(a) * (256 - w) + u32::from(b) * w + 128) >> 8) as u16;
                    out[i] = if a == INVALID_COST || b == INVALID_COST {
                        INVALID_COST
                    } else {
                        mixed
                    };
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(width: usize, height: usize) -> Image {
        let data = (0..width * height).map(|i| ((i % width) * 9 % 256) as u8).collect();
        Image::gray(width, height, data).unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn shifted_copy_has_zero_cost_at_its_shift() {
        // The right neighbour sees the scene shifted left by 3 px: q = p − 3.
        let reference = ramp(20, 4);
        let mut shifted = reference.clone();
        for y in 0..4 {
            for x in 0..20 {
                shifted.data[y * 20 + x] = reference.clamped(x as isize + 3, y as isize, 0);
            }
        }
        for cost in [
            PixelCost::AbsoluteDifference,
            PixelCost::BirchfieldTomasi,
            PixelCost::Census {
                radius: 1,
                symmetric: false,
            },
        ] {
            let a = PreparedView::new(reference.clone(), cost);
            let b = PreparedView::new(shifted.clone(), cost);
            let mut row = vec![0u8; 20 * 8];
            pixel_cost_tile(cost, &a, &b, [1, 0], 2, 0..20, 0, 8, &mut row);
            for x in 5..15 {
                assert_eq!(row[x * 8 + 3], 0, "{cost:?} x {x}");
                assert!(
                    row[x * 8 + 1] > 0 || matches!(cost, PixelCost::Census { .. }),
                    "{cost:?}"
                );
            }
        }
    }

    #[test]
    fn the_colour_cost_is_its_halves_summed_and_clipped() {
        for (r, g, b) in [
            (0, 0, 0),
            (1, 1, 1),
            (3, 5, 7),
            (100, 101, 102),
            (170, 170, 170),
            (171, 171, 171),
            (255, 255, 255),
            (255, 0, 0),
        ] {
            let exact = u32::from(r / 2) + u32::from(g / 2) + u32::from(b / 2);
            assert_eq!(
                u32::from(colour_birchfield_tomasi(r, g, b)),
                exact.min(255),
                "{r} {g} {b}"
            );
        }
        // Up to a mean of 170 levels it is 1.5 × the mean of even channel costs.
        assert_eq!(colour_birchfield_tomasi(20, 40, 60), 60);
        assert_eq!(colour_birchfield_tomasi(200, 200, 200), 255);
    }

    #[test]
    fn mean_of_three_is_exact() {
        for sum in 0..=765u16 {
            assert_eq!(u16::from(mean_of_three(sum)), sum / 3, "{sum}");
        }
    }

    #[test]
    fn birchfield_tomasi_bounds_match_the_definition() {
        for (w, h, channels) in [(9, 7, 3), (2, 3, 1), (1, 4, 3)] {
            let data = (0..w * h * channels).map(|i| ((i * 97 + i / 5) % 256) as u8).collect();
            let image = Image::new(w, h, channels, data).unwrap_or_else(|e| panic!("{e}"));
            let (lo, hi) = birchfield_tomasi_bounds(&image);
            for y in 0..h as isize {
                for x in 0..w as isize {
                    for channel in 0..channels {
                        let c = u16::from(image.clamped(x, y, channel));
                        let halves = [(-1, 0), (1, 0), (0, -1), (0, 1)]
                            .map(|(dx, dy)| (c + u16::from(image.clamped(x + dx, y + dy, channel))) / 2);
                        let i = image.clamped_index(x, y) + channel;
                        assert_eq!(u16::from(lo[i]), halves.iter().fold(c, |a, v| a.min(*v)));
                        assert_eq!(u16::from(hi[i]), halves.iter().fold(c, |a, v| a.max(*v)));
                    }
                }
            }
        }
    }

    #[test]
    fn census_transform_matches_the_definition() {
        let (w, h) = (9, 7);
        let image =
            Image::gray(w, h, (0..w * h).map(|i| ((i * 71) % 253) as u8).collect()).unwrap_or_else(|e| panic!("{e}"));
        let codes = census_transform(&image, 2, false);
        let planes = census_planes(&image, 2, false);
        assert_eq!(planes.len(), 3);
        for (p, code) in codes.iter().enumerate() {
            let from_planes = planes
                .iter()
                .enumerate()
                .fold(0u64, |a, (b, plane)| a | (u64::from(plane[p]) << (8 * b)));
            assert_eq!(from_planes, *code);
        }
        for y in 0..h as isize {
            for x in 0..w as isize {
                let c = image.clamped(x, y, 0);
                let mut code = 0u64;
                for dy in -2..=2 {
                    for dx in -2..=2 {
                        if dx != 0 || dy != 0 {
                            code = (code << 1) | u64::from(image.clamped(x + dx, y + dy, 0) < c);
                        }
                    }
                }
                assert_eq!(codes[(y as usize) * w + x as usize], code);
            }
        }
    }

    #[test]
    fn symmetric_census_compares_each_position_with_its_mirror() {
        let (w, h) = (9, 7);
        let image =
            Image::gray(w, h, (0..w * h).map(|i| ((i * 71) % 253) as u8).collect()).unwrap_or_else(|e| panic!("{e}"));
        for r in 1..=MAX_CENSUS_RADIUS {
            let codes = census_transform(&image, r, true);
            let planes = census_planes(&image, r, true);
            let pairs = ((2 * r + 1).pow(2) - 1) / 2;
            assert_eq!(planes.len(), pairs.div_ceil(8), "radius {r}");
            for (p, code) in codes.iter().enumerate() {
                let from_planes = planes
                    .iter()
                    .enumerate()
                    .fold(0u64, |a, (b, plane)| a | (u64::from(plane[p]) << (8 * b)));
                assert_eq!(from_planes, *code, "radius {r}, pixel {p}");
            }
            let r = r as isize;
            for y in 0..h as isize {
                for x in 0..w as isize {
                    // Row-major positions before the centre, each against its mirror.
                    let mut code = 0u64;
                    for dy in -r..=0 {
                        for dx in -r..=r {
                            if dy == 0 && dx >= 0 {
                                break;
                            }
                            let (a, b) = (image.clamped(x + dx, y + dy, 0), image.clamped(x - dx, y - dy, 0));
                            code = (code << 1) | u64::from(a < b);
                        }
                    }
                    assert_eq!(codes[(y as usize) * w + x as usize], code, "radius {r} at ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn resampling_moves_the_minimum_by_the_baseline_ratio() {
        // A neighbour 10 % farther away sees disparity 11 where the nominal rig sees 10.
        let nd = 16;
        let mut row: Vec<u16> = (0..nd).map(|d| ((d as i32 - 11).abs() * 10) as u16).collect();
        let resampler = DisparityResampler::new(0, nd, 1.1).unwrap_or_else(|| panic!("ratio 1.1 resamples"));
        resampler.apply(&mut row, &mut Vec::new());
        assert!(DisparityResampler::new(0, nd, 1.0).is_none());
        // The vectorised runs give the table's definition, for ratios above and below 1.
        for ratio in [1.0012f32, 1.3, 0.97, 0.5] {
            let resampler = DisparityResampler::new(3, 40, ratio).unwrap_or_else(|| panic!("ratio {ratio}"));
            let costs: Vec<u16> = (0..40 * 3)
                .map(|i| {
                    if i % 17 == 5 {
                        INVALID_COST
                    } else {
                        (i * 37 % 500) as u16
                    }
                })
                .collect();
            let mut fast = costs.clone();
            resampler.apply(&mut fast, &mut Vec::new());
            for (pixel, (got, original)) in fast.chunks(40).zip(costs.chunks(40)).enumerate() {
                for (d, &(lower, upper, w)) in resampler.table.iter().enumerate() {
                    let (a, b) = (original[lower], original[upper]);
                    let expected = if a == INVALID_COST || b == INVALID_COST {
                        INVALID_COST
                    } else {
                        ((u32::from(a) * (256 - w) + u32::from(b) * w + 128) >> 8) as u16
                    };
                    assert_eq!(got[d], expected, "ratio {ratio} pixel {pixel} d {d}");
                }
            }
        }
        let best = (0..nd).min_by_key(|d| row[*d]).unwrap_or(0);
        assert_eq!(best, 10, "{row:?}");
    }

    #[test]
    fn out_of_image_correspondences_are_invalid() {
        let mut row = vec![0u16; 5 * 4];
        mark_invalid(&mut row, [1, 0], (0, 0), (5, 5), (0, 4), 1.0);
        // x = 1: d ≥ 2 leaves the image on the left.
        assert_eq!(&row[4..8], &[0, 0, INVALID_COST, INVALID_COST]);
        let mut row = vec![0u16; 5 * 4];
        mark_invalid(&mut row, [0, -1], (0, 3), (5, 5), (0, 4), 1.0);
        // top neighbour: q_y = y + d; y = 3: d ≥ 2 leaves the bottom.
        assert_eq!(&row[0..4], &[0, 0, INVALID_COST, INVALID_COST]);
        // The same pixel seen through a tile that starts at x = 1.
        let mut tile = vec![0u16; 2 * 4];
        mark_invalid(&mut tile, [1, 0], (1, 0), (5, 5), (0, 4), 1.0);
        assert_eq!(&tile[0..4], &[0, 0, INVALID_COST, INVALID_COST]);
    }

    #[test]
    fn tabulated_valid_disparities_match_the_definition() {
        let (w, h, nd) = (13, 9, 11);
        for offset in [[1, 0], [-1, 0], [0, 1], [0, -1], [1, -1], [-1, 1], [2, 0]] {
            for (min_d, ratio) in [(0, 1.0), (2, 1.13), (1, 0.9)] {
                let table = ValidDisparities::new(offset, (w, h), (min_d, nd), ratio);
                for y in 0..h {
                    let mut expected = vec![7u16; w * nd];
                    mark_invalid(&mut expected, offset, (0, y), (w, h), (min_d, nd), ratio);
                    for x_start in [0, 4] {
                        let mut got = vec![7u16; (w - x_start) * nd];
                        table.mark(&mut got, (x_start, y));
                        assert_eq!(
                            got,
                            expected[x_start * nd..],
                            "{offset:?} {min_d} {ratio} y {y} from {x_start}"
                        );
                    }
                }
            }
        }
    }
}
