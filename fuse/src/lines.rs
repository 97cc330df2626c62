//! Search lines: a neighbour's samples rearranged so that, for every reference pixel, the samples
//! along its search line `q = p − offset·s` (s = …, −1, 0, 1, 2, …, signed for converged rigs) are
//! contiguous in memory. The cost
//! loops over the disparities then read straight runs that the compiler vectorises, instead of
//! computing and clamping a 2-D index per (pixel, disparity).
//!
//! Built for the four axis neighbours (left, right, top, bottom); diagonal neighbours use the
//! generic [`crate::cost::pixel_cost_row`].

use std::ops::Range;

use crate::cost::{PixelCost, PreparedView, mean_of_three};

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
    /// Lays out `view`'s samples for `offset`, long enough for the disparities `reach` (signed:
    /// a converged rig searches below 0). `None` for diagonal offsets.
    pub fn new(view: &PreparedView, cost: PixelCost, offset: [i32; 2], reach: Range<i32>) -> Option<Self> {
        if !matches!(offset, [1, 0] | [-1, 0] | [0, 1] | [0, -1]) {
            return None;
        }
        let image = view.image();
        let (w, h, channels) = (image.width, image.height, image.channels);
        let before = reach.start.min(0).unsigned_abs() as usize;
        let after = reach.end.max(0) as usize;
        let line_len = before + if offset[1] == 0 { w } else { h } + after + 1;
        let layout = (offset, (w, h), (before, line_len));
        let mut planes = Vec::new();
        let mut census = Vec::new();
        match cost {
            PixelCost::AbsoluteDifference => {
                for c in 0..channels {
                    planes.push(gather_lines(layout, |p| image.data[p * channels + c]));
                }
            }
            PixelCost::BirchfieldTomasi => {
                let (lo, hi) = view.bt_bounds();
                for c in 0..channels {
                    planes.push(gather_lines(layout, |p| lo[p * channels + c]));
                    planes.push(gather_lines(layout, |p| hi[p * channels + c]));
                }
            }
            PixelCost::Census { .. } => {
                census = view
                    .census_planes()
                    .iter()
                    .map(|plane| gather_lines(layout, |p| plane[p]))
                    .collect();
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

/// One plane in search-line order: line `k` is image row `k` (horizontal offsets) or column `k`
/// (vertical), read away from the neighbour's side, preceded by `before` copies of its first
/// sample and continued past the far border with the border value; `value(p)` gives the sample
/// of pixel index `p`. Lines are filled as runs (the rows forwards or backwards, the columns with a
/// stride) rather than per-sample index arithmetic.
fn gather_lines(
    (offset, (w, h), (before, line_len)): ([i32; 2], (usize, usize), (usize, usize)),
    value: impl Fn(usize) -> u8,
) -> Vec<u8> {
    let horizontal = offset[1] == 0;
    let (lines, run) = if horizontal { (h, w) } else { (w, h) };
    let mut plane = Vec::with_capacity(lines * line_len);
    for k in 0..lines {
        let start = plane.len() + before;
        let first = match offset {
            [-1, 0] => value(k * w),
            [1, 0] => value(k * w + w - 1),
            [0, -1] => value(k),
            _ => value((h - 1) * w + k),
        };
        plane.resize(start, first);
        match offset {
            [-1, 0] => plane.extend((0..w).map(|x| value(k * w + x))),
            [1, 0] => plane.extend((0..w).rev().map(|x| value(k * w + x))),
            [0, -1] => plane.extend((0..h).map(|y| value(y * w + k))),
            _ => plane.extend((0..h).rev().map(|y| value(y * w + k))),
        }
        let border = plane[start + run - 1];
        plane.resize(start - before + line_len, border);
    }
    plane
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
                    let sum = u16::from(bt(c0, l0[d], h0[d]))
                        + u16::from(bt(c1, l1[d], h1[d]))
                        + u16::from(bt(c2, l2[d], h2[d]));
                    *o = mean_of_three(sum);
                }
            }
            (PixelCost::Census { .. }, _) => {
                costs.fill(0);
                let codes = reference.census_planes().iter().map(|plane| plane[y * width + x]);
                for (plane, c) in lines.census.iter().zip(codes) {
                    for (o, v) in costs.iter_mut().zip(&plane[range.clone()]) {
                        *o += (c ^ v).count_ones() as u8;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::pixel_cost_tile;
    use crate::image::Image;

    #[test]
    fn search_lines_give_the_generic_costs_for_every_axis_and_cost() {
        let (w, h) = (23, 17);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| ((i * 37 + i / 7) % 251) as u8).collect();
        let other: Vec<u8> = (0..w * h * 3).map(|i| ((i * 53 + 11) % 241) as u8).collect();
        for cost in [
            PixelCost::AbsoluteDifference,
            PixelCost::BirchfieldTomasi,
            PixelCost::Census { radius: 2 },
        ] {
            for channels in [1, 3] {
                let make = |data: &[u8]| {
                    let image = Image::rgb(w, h, data.to_vec()).unwrap_or_else(|e| panic!("{e}"));
                    PreparedView::new(if channels == 1 { image.to_gray() } else { image }, cost)
                };
                let (reference, neighbour) = (make(&rgb), make(&other));
                for (offset, min_d) in [[1, 0], [-1, 0], [0, 1], [0, -1]]
                    .into_iter()
                    .flat_map(|o| [(o, 2), (o, -6)])
                {
                    let nd = 9;
                    let lines = SearchLines::new(&neighbour, cost, offset, min_d..min_d + nd as i32)
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
