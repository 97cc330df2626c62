//! Search lines: a neighbour's samples rearranged so that, for every reference pixel, the samples
//! along its search line `q = p − offset·s` (s = …, −1, 0, 1, 2, …, signed for converged rigs) are
//! contiguous in memory. The cost
//! loops over the disparities then read straight runs that the compiler vectorises, instead of
//! computing and clamping a 2-D index per (pixel, disparity).
//!
//! Built for the four axis neighbours (left, right, top, bottom); diagonal neighbours use the
//! generic [`crate::cost::pixel_cost_tile`].

use std::ops::Range;

use crate::cost::{
    MAX_CENSUS_RADIUS, PixelCost, PreparedView, birchfield_tomasi_row, census_plane_count, census_row,
    colour_birchfield_tomasi, mean_of_three, padded_gray,
};
use crate::image::Image;

mod census_kernel;

/// A neighbour's samples in search-line order, with the border replicated past the image.
#[derive(Debug, Clone)]
pub struct SearchLines {
    offset: [i32; 2],
    line_len: usize,
    /// Samples before s = 0 on every line (the border repeated), for negative disparities.
    before: usize,
    width: usize,
    height: usize,
    /// Per channel: values (absolute difference) or interleaved (min, max) pairs' planes
    /// (Birchfield–Tomasi: `[min₀, max₀, min₁, max₁, …]`).
    planes: Vec<Vec<u8>>,
    /// Census codes sliced into bytes (plane `b` holds bits `8b .. 8b + 8`): the Hamming distance
    /// then runs on 32 byte lanes with a table popcount instead of on 4 × 64-bit lanes.
    census: Vec<Vec<u8>>,
}

impl SearchLines {
    /// Lays out the samples a `cost` reads of the neighbour `image` for `offset`, long enough for
    /// the disparities `reach` (signed: a converged rig searches below 0). `None` for diagonal
    /// offsets. What the cost reads (the Birchfield–Tomasi bounds, the census codes) is made a row
    /// at a time and written straight into the lines: the same samples as
    /// [`PreparedView::new`]'s, without its whole-image planes.
    pub fn new(image: &Image, cost: PixelCost, offset: [i32; 2], reach: Range<i32>) -> Option<Self> {
        if !matches!(offset, [1, 0] | [-1, 0] | [0, 1] | [0, -1]) {
            return None;
        }
        let (w, h, channels) = (image.width, image.height, image.channels);
        let before = reach.start.min(0).unsigned_abs() as usize;
        let after = reach.end.max(0) as usize;
        let line_len = before + if offset[1] == 0 { w } else { h } + after + 1;
        let layout = (offset, (w, h), (before, line_len));
        let stride = w * channels;
        let mut planes = Vec::new();
        let mut census = Vec::new();
        match cost {
            PixelCost::AbsoluteDifference => {
                planes = lay_out(layout, channels, |y, rows| {
                    deinterleave(&image.data[y * stride..(y + 1) * stride], channels, rows, (0, 1));
                });
            }
            PixelCost::BirchfieldTomasi => {
                let (mut lo, mut hi) = (vec![0u8; stride], vec![0u8; stride]);
                // Planes interleaved per channel: [min₀, max₀, min₁, max₁, …].
                planes = lay_out(layout, 2 * channels, |y, rows| {
                    birchfield_tomasi_row(image, y, &mut lo, &mut hi);
                    deinterleave(&lo, channels, rows, (0, 2));
                    deinterleave(&hi, channels, rows, (1, 2));
                });
            }
            PixelCost::Census { radius, symmetric } => {
                let r = radius.clamp(1, MAX_CENSUS_RADIUS);
                let (padded, padded_w) = padded_gray(&image.to_gray(), r);
                census = lay_out(layout, census_plane_count(r, symmetric), |y, rows| {
                    for (b, row) in rows.iter_mut().enumerate() {
                        census_row((&padded, padded_w), (r, symmetric), y, b, row);
                    }
                });
            }
        }
        Some(Self {
            offset,
            line_len,
            before,
            width: w,
            height: h,
            planes,
            census,
        })
    }

    /// Index of the sample at s = 0 on the search line of reference pixel `(x, y)`.
    #[inline]
    fn base(&self, x: usize, y: usize) -> usize {
        self.before
            + match self.offset {
                [-1, 0] => y * self.line_len + x,
                [1, 0] => y * self.line_len + (self.width - 1 - x),
                [0, -1] => x * self.line_len + y,
                _ => x * self.line_len + (self.height - 1 - y),
            }
    }
}

/// The `channels` of an interleaved row `source` into rows of `rows`: channel `c` into row
/// `first + step·c`.
fn deinterleave(source: &[u8], channels: usize, rows: &mut [Vec<u8>], (first, step): (usize, usize)) {
    if channels == 3
        && let Ok([r, g, b]) = rows.get_disjoint_mut([first, first + step, first + 2 * step])
    {
        for (((p, r), g), b) in source
            .chunks_exact(3)
            .zip(r.iter_mut())
            .zip(g.iter_mut())
            .zip(b.iter_mut())
        {
            (*r, *g, *b) = (p[0], p[1], p[2]);
        }
        return;
    }
    for c in 0..channels {
        if let Some(row) = rows.get_mut(first + step * c) {
            for (v, s) in row.iter_mut().zip(source.iter().skip(c).step_by(channels)) {
                *v = *s;
            }
        }
    }
}

/// Image rows a vertical neighbour's lines are written from at once: each column's line then
/// gets runs of this many samples instead of one byte per cache line per row.
const BLOCK_ROWS: usize = 16;

/// `count` planes in search-line order, from the image's rows as `fill_row(y, rows)` makes them
/// (one row of `width` samples per plane): line `k` is image row `k` (horizontal offsets) or
/// column `k` (vertical), read away from the neighbour's side, preceded by `before` copies of its
/// first sample and continued past the far border with the border value.
fn lay_out(
    (offset, (w, h), (before, line_len)): ([i32; 2], (usize, usize), (usize, usize)),
    count: usize,
    mut fill_row: impl FnMut(usize, &mut [Vec<u8>]),
) -> Vec<Vec<u8>> {
    let horizontal = offset[1] == 0;
    let (lines, run) = if horizontal { (h, w) } else { (w, h) };
    // Each plane allocated zeroed on its own (`vec![plane; count]` would copy the first's zeros
    // into every other before they are written over).
    let mut planes: Vec<Vec<u8>> = (0..count).map(|_| vec![0u8; lines * line_len]).collect();
    let mut rows = vec![vec![0u8; w]; count];
    if horizontal {
        for y in 0..h {
            fill_row(y, &mut rows);
            for (plane, row) in planes.iter_mut().zip(&rows) {
                let line = &mut plane[y * line_len + before..y * line_len + before + w];
                if offset[0] < 0 {
                    line.copy_from_slice(row);
                } else {
                    for (s, v) in line.iter_mut().rev().zip(row) {
                        *s = *v;
                    }
                }
            }
        }
    } else {
        // A block of rows per plane (`[row][x]`), then each column's run of it into its line.
        let mut block = vec![vec![0u8; BLOCK_ROWS * w]; count];
        for y0 in (0..h).step_by(BLOCK_ROWS) {
            let m = BLOCK_ROWS.min(h - y0);
            for j in 0..m {
                fill_row(y0 + j, &mut rows);
                for (b, row) in block.iter_mut().zip(&rows) {
                    b[j * w..(j + 1) * w].copy_from_slice(row);
                }
            }
            // Downwards for the neighbour above (rows y0 … at positions y0 …), upwards below.
            let down = offset[1] < 0;
            let first = before + if down { y0 } else { h - y0 - m };
            for (plane, b) in planes.iter_mut().zip(&block) {
                for (x, line) in plane.chunks_exact_mut(line_len).enumerate() {
                    let column = &mut line[first..first + m];
                    for (j, s) in column.iter_mut().enumerate() {
                        let row = if down { j } else { m - 1 - j };
                        *s = b[row * w + x];
                    }
                }
            }
        }
    }
    for plane in &mut planes {
        for line in plane.chunks_exact_mut(line_len) {
            let (first, last) = (line[before], line[before + run - 1]);
            line[..before].fill(first);
            line[before + run..].fill(last);
        }
    }
    planes
}

/// Pixel costs of reference row `y`, columns `xs` (outside the image: the border column), for
/// disparities `min_disparity ..` into `out` (`[x][d]`, one byte each), reading the neighbour
/// through its search lines. Same values as [`crate::cost::pixel_cost_tile`].
#[allow(clippy::too_many_arguments)]
pub fn pixel_cost_tile_lines(
    cost: PixelCost,
    reference: &PreparedView,
    lines: &SearchLines,
    y: usize,
    xs: Range<isize>,
    min_disparity: i32,
    num_disparities: usize,
    out: &mut [u8],
) {
    let image = reference.image();
    let (width, channels) = (image.width, image.channels);
    // The 48-bit census planes for the intrinsics kernel, bounded once per tile row.
    let planes48 = match &lines.census[..] {
        [p0, p1, p2, p3, p4, p5] => Some(census_kernel::Planes48::new([p0, p1, p2, p3, p4, p5])),
        _ => None,
    };
    for (costs, x) in out.chunks_exact_mut(num_disparities).zip(xs) {
        let x = x.clamp(0, width as isize - 1) as usize;
        let start = lines.base(x, y).saturating_add_signed(min_disparity as isize);
        let range = start..start + num_disparities;
        let p = (y * width + x) * channels;
        match (cost, channels) {
            (PixelCost::AbsoluteDifference, 1) => {
                let c = image.data[p];
                for (o, v) in costs.iter_mut().zip(&lines.planes[0][range]) {
                    *o = c.abs_diff(*v);
                }
            }
            (PixelCost::AbsoluteDifference, _) => {
                let (c0, c1, c2) = (image.data[p], image.data[p + 1], image.data[p + 2]);
                let (a, b, c) = (
                    &lines.planes[0][range.clone()],
                    &lines.planes[1][range.clone()],
                    &lines.planes[2][range],
                );
                for (((o, v0), v1), v2) in costs.iter_mut().zip(a).zip(b).zip(c) {
                    let sum = u16::from(c0.abs_diff(*v0)) + u16::from(c1.abs_diff(*v1)) + u16::from(c2.abs_diff(*v2));
                    *o = mean_of_three(sum);
                }
            }
            (PixelCost::BirchfieldTomasi, 1) => {
                let c = image.data[p];
                let (lo, hi) = (&lines.planes[0][range.clone()], &lines.planes[1][range]);
                for ((o, l), h) in costs.iter_mut().zip(lo).zip(hi) {
                    *o = c.saturating_sub(*h).max(l.saturating_sub(c));
                }
            }
            (PixelCost::BirchfieldTomasi, _) => {
                let planes = &lines.planes;
                let (c0, c1, c2) = (image.data[p], image.data[p + 1], image.data[p + 2]);
                let n = costs.len();
                let (l0, h0) = (&planes[0][range.clone()][..n], &planes[1][range.clone()][..n]);
                let (l1, h1) = (&planes[2][range.clone()][..n], &planes[3][range.clone()][..n]);
                let (l2, h2) = (&planes[4][range.clone()][..n], &planes[5][range][..n]);
                for (d, o) in costs.iter_mut().enumerate() {
                    let bt = |c: u8, l: u8, h: u8| c.saturating_sub(h).max(l.saturating_sub(c));
                    *o = colour_birchfield_tomasi(bt(c0, l0[d], h0[d]), bt(c1, l1[d], h1[d]), bt(c2, l2[d], h2[d]));
                }
            }
            (PixelCost::Census { symmetric, .. }, _) => {
                let at = y * width + x;
                if let ([p0, p1, p2], [c0, c1, c2]) = (&lines.census[..], reference.census_planes()) {
                    // 24 bits (the symmetric census over 7×7, or the full one over 5×5).
                    let from = range.start;
                    let planes = [&p0[from..], &p1[from..], &p2[from..]];
                    let codes = [c0[at], c1[at], c2[at]];
                    if symmetric {
                        census_distances_24::<true>(planes, codes, costs);
                    } else {
                        census_distances_24::<false>(planes, codes, costs);
                    }
                } else if let ([p0, p1, p2, p3, p4, p5], [c0, c1, c2, c3, c4, c5]) =
                    (&lines.census[..], reference.census_planes())
                {
                    // The 7×7 window (SGM's default): 48 bits.
                    let from = range.start;
                    let codes = [c0[at], c1[at], c2[at], c3[at], c4[at], c5[at]];
                    if planes48.as_ref().is_some_and(|k| k.distances(from, codes, costs)) {
                        continue;
                    }
                    census_distances_48(
                        [
                            &p0[from..],
                            &p1[from..],
                            &p2[from..],
                            &p3[from..],
                            &p4[from..],
                            &p5[from..],
                        ],
                        codes,
                        costs,
                    );
                } else {
                    costs.fill(0);
                    for (plane, codes) in lines.census.iter().zip(reference.census_planes()) {
                        let c = codes[at];
                        for (o, v) in costs.iter_mut().zip(&plane[range.clone()]) {
                            *o += ((c ^ v).count_ones() as u8) << u8::from(symmetric);
                        }
                    }
                }
            }
        }
    }
}

/// Hamming distances of a 24-bit census code (three byte planes, `codes`) to the first
/// `out.len()` codes along a search line (`planes`, each from the line's first searched sample
/// to the end of its plane), doubled for the symmetric census (`DOUBLED`: its bits count twice):
/// the three planes' differing bits summed by one carry-save adder into bits of weight 1 and 2,
/// two byte population counts for three.
fn census_distances_24<const DOUBLED: bool>(planes: [&[u8]; 3], codes: [u8; 3], out: &mut [u8]) {
    let (runs, rest) = out.as_chunks_mut::<CENSUS_RUN>();
    let whole = runs.len() * CENSUS_RUN;
    for (r, run) in runs.iter_mut().enumerate() {
        census_run_24::<DOUBLED>(planes.map(|p| run_of(p, r * CENSUS_RUN)), codes, run);
    }
    if !rest.is_empty() {
        // As in `census_distances_48`: the last cells from a whole run, the extra ones dropped.
        let mut run = [0u8; CENSUS_RUN];
        census_run_24::<DOUBLED>(planes.map(|p| run_of(p, whole)), codes, &mut run);
        let m = rest.len();
        rest.copy_from_slice(&run[..m]);
    }
}

/// [`census_distances_24`] over one run of cells.
#[inline(always)]
fn census_run_24<const DOUBLED: bool>(lines: [[u8; CENSUS_RUN]; 3], codes: [u8; 3], out: &mut [u8; CENSUS_RUN]) {
    let [l0, l1, l2] = lines;
    let [c0, c1, c2] = codes;
    for d in 0..CENSUS_RUN {
        let (x0, x1, x2) = (l0[d] ^ c0, l1[d] ^ c1, l2[d] ^ c2);
        let u = x0 ^ x1;
        let (ones, twos) = (u ^ x2, (x0 & x1) | (u & x2));
        let distance = ones.count_ones() as u8 + 2 * twos.count_ones() as u8;
        out[d] = if DOUBLED { 2 * distance } else { distance };
    }
}

/// The cells `at .. at + CENSUS_RUN` of a plane (zeros past its end: its last line's last cells).
#[inline(always)]
fn run_of(plane: &[u8], at: usize) -> [u8; CENSUS_RUN] {
    match plane
        .get(at..at + CENSUS_RUN)
        .and_then(|run| <[u8; CENSUS_RUN]>::try_from(run).ok())
    {
        Some(run) => run,
        None => {
            let mut line = [0u8; CENSUS_RUN];
            let tail = plane.get(at..).unwrap_or_default();
            let m = tail.len().min(CENSUS_RUN);
            line[..m].copy_from_slice(&tail[..m]);
            line
        }
    }
}

/// Hamming distances of a 48-bit census code (six byte planes, `codes`) to the first `out.len()`
/// codes along a search line (`planes`, each from the line's first searched sample to the end
/// of its plane), one per disparity: the six planes' differing bits summed by carry-save
/// adders (Harley–Seal) into bits of weight 1, 2 and 4, so that three byte population counts do
/// the work of six.
fn census_distances_48(planes: [&[u8]; 6], codes: [u8; 6], out: &mut [u8]) {
    let (runs, rest) = out.as_chunks_mut::<CENSUS_RUN>();
    let whole = runs.len() * CENSUS_RUN;
    for (r, run) in runs.iter_mut().enumerate() {
        census_run_at(&planes, r * CENSUS_RUN, codes, run);
    }
    if !rest.is_empty() {
        // The last cells from a whole run read on along the planes (the cells past the searched ones are
        // computed and dropped).
        let mut run = [0u8; CENSUS_RUN];
        census_run_at(&planes, whole, codes, &mut run);
        for (o, v) in rest.iter_mut().zip(run) {
            *o = v;
        }
    }
}

/// [`census_run_48`] over the cells `at .. at + CENSUS_RUN` of the six planes (zeros past a
/// plane's end: its last line's last cells).
#[inline(always)]
fn census_run_at(planes: &[&[u8]; 6], at: usize, codes: [u8; 6], out: &mut [u8; CENSUS_RUN]) {
    let run_at = |plane: &[u8]| run_of(plane, at);
    let [p0, p1, p2, p3, p4, p5] = *planes;
    let lines = [run_at(p0), run_at(p1), run_at(p2), run_at(p3), run_at(p4), run_at(p5)];
    census_run_48(
        [&lines[0], &lines[1], &lines[2], &lines[3], &lines[4], &lines[5]],
        codes,
        out,
    );
}

/// Cells per run of [`census_run_48`]: one AVX2 register of bytes.
const CENSUS_RUN: usize = 32;

/// [`census_distances_48`] over one run of cells. Written over named lanes and fixed-size
/// runs: a loop over the whole line, or cells gathered into arrays, compiled to scalar or
/// shuffled code in some callers.
#[inline(always)]
fn census_run_48(lines: [&[u8; CENSUS_RUN]; 6], codes: [u8; 6], out: &mut [u8; CENSUS_RUN]) {
    let [l0, l1, l2, l3, l4, l5] = lines;
    let [c0, c1, c2, c3, c4, c5] = codes;
    for d in 0..CENSUS_RUN {
        let (x0, x1, x2) = (l0[d] ^ c0, l1[d] ^ c1, l2[d] ^ c2);
        let (x3, x4, x5) = (l3[d] ^ c3, l4[d] ^ c4, l5[d] ^ c5);
        // Full adders: (sum, carry) of three bits.
        let u = x0 ^ x1;
        let (s1, k1) = (u ^ x2, (x0 & x1) | (u & x2));
        let u = x3 ^ x4;
        let (s2, k2) = (u ^ x5, (x3 & x4) | (u & x5));
        let (ones, t) = (s1 ^ s2, s1 & s2);
        let u = t ^ k1;
        let (twos, fours) = (u ^ k2, (t & k1) | (u & k2));
        out[d] = ones.count_ones() as u8 + 2 * twos.count_ones() as u8 + 4 * fours.count_ones() as u8;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::pixel_cost_tile;

    #[test]
    fn search_lines_give_the_generic_costs_for_every_axis_and_cost() {
        let (w, h) = (23, 17);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| ((i * 37 + i / 7) % 251) as u8).collect();
        let other: Vec<u8> = (0..w * h * 3).map(|i| ((i * 53 + 11) % 241) as u8).collect();
        for cost in [
            PixelCost::AbsoluteDifference,
            PixelCost::BirchfieldTomasi,
            PixelCost::Census {
                radius: 2,
                symmetric: false,
            },
            PixelCost::Census {
                radius: 3,
                symmetric: false,
            },
            PixelCost::Census {
                radius: 1,
                symmetric: true,
            },
            PixelCost::Census {
                radius: 2,
                symmetric: true,
            },
            PixelCost::Census {
                radius: 3,
                symmetric: true,
            },
        ] {
            for channels in [1, 3] {
                let make = |data: &[u8]| {
                    let image = Image::rgb(w, h, data.to_vec()).unwrap_or_else(|e| panic!("{e}"));
                    PreparedView::new(if channels == 1 { image.to_gray() } else { image }, cost)
                };
                let (reference, neighbour) = (make(&rgb), make(&other));
                let neighbour_image = neighbour.image().clone();
                for (offset, min_d, nd) in [[1, 0], [-1, 0], [0, 1], [0, -1]]
                    .into_iter()
                    .flat_map(|o| [(o, 2, 9), (o, -6, 9), (o, -20, 41)])
                {
                    // 41 disparities: whole runs of 32 and a remainder.
                    let lines = SearchLines::new(&neighbour_image, cost, offset, min_d..min_d + nd as i32)
                        .unwrap_or_else(|| panic!("no lines"));
                    // A tile reaching past both image borders.
                    let xs = -3..w as isize + 2;
                    for y in 0..h {
                        let mut generic = vec![0u8; xs.len() * nd];
                        let mut fast = vec![0u8; xs.len() * nd];
                        pixel_cost_tile(
                            cost,
                            &reference,
                            &neighbour,
                            offset,
                            y,
                            xs.clone(),
                            min_d,
                            nd,
                            &mut generic,
                        );
                        pixel_cost_tile_lines(cost, &reference, &lines, y, xs.clone(), min_d, nd, &mut fast);
                        assert_eq!(
                            generic, fast,
                            "{cost:?} {channels} channels {offset:?} from {min_d} row {y}"
                        );
                    }
                }
            }
        }
    }
}
