//! Semi-global matching (Hirschmüller, PAMI 2008) over a fused cost volume: eight paths,
//! penalties P1 for ±1 disparity steps and P2 for larger jumps, summed into one `u16` volume.

use crate::cost::INVALID_COST;

/// Scales costs so that the sum of eight paths fits `u16`: returns the right shift to apply.
pub fn cost_shift(max_cost: u32, p2: u32) -> u32 {
    let mut shift = 0;
    while 8 * ((max_cost >> shift) + p2) >= u32::from(u16::MAX) {
        shift += 1;
    }
    shift
}

/// Path cost at a pixel with no predecessor on the path: the (scaled, capped) data cost.
#[inline]
fn path_start(cost: &[u16], out: &mut [u16], shift: u32, cap: u16) {
    for (o, c) in out.iter_mut().zip(cost) {
        *o = (*c >> shift).min(cap);
    }
}

/// `L(p, d) = C(p, d) + min(L(p−r, d), L(p−r, d±1) + P1, min L(p−r) + P2) − min L(p−r)`,
/// written as whole-slice passes so that the compiler vectorises them.
#[inline]
fn path_step(cost: &[u16], previous: &[u16], out: &mut [u16], p1: u16, p2: u16, shift: u32, cap: u16) {
    let n = out.len();
    let (cost, previous) = (&cost[..n], &previous[..n]);
    let min_prev = previous.iter().copied().min().unwrap_or(0);
    let jump = min_prev.saturating_add(p2);
    for (o, p) in out.iter_mut().zip(previous) {
        *o = (*p).min(jump);
    }
    for (o, p) in out[1..].iter_mut().zip(&previous[..n - 1]) {
        *o = (*o).min(p.saturating_add(p1));
    }
    for (o, p) in out[..n - 1].iter_mut().zip(&previous[1..]) {
        *o = (*o).min(p.saturating_add(p1));
    }
    for (o, c) in out.iter_mut().zip(cost) {
        *o = (*c >> shift).min(cap) + *o - min_prev;
    }
}

/// Aggregates `volume` (`[y][x][d]`) along eight paths and returns the summed costs.
/// `max_cost` bounds the valid costs (invalid ones count as `max_cost`).
pub fn aggregate(
    volume: &[u16],
    width: usize,
    height: usize,
    disparities: usize,
    max_cost: u32,
    p1: u16,
    p2: u16,
) -> Vec<u16> {
    let shift = cost_shift(max_cost, u32::from(p2));
    let cap = ((max_cost >> shift).min(u32::from(INVALID_COST) - 1)) as u16;
    let nd = disparities;
    let row_len = width * nd;
    let mut sum = vec![0u16; volume.len()];
    for forward in [true, false] {
        // Path costs of the previous and current row for the three paths that come from the
        // previous row (diagonal, vertical, other diagonal); the horizontal path keeps one pixel.
        let mut previous: Vec<Vec<u16>> = vec![vec![0u16; row_len]; 3];
        let mut current: Vec<Vec<u16>> = vec![vec![0u16; row_len]; 3];
        let mut horizontal = vec![0u16; nd];
        let mut scratch = vec![0u16; nd];
        let mut total = vec![0u16; nd];
        for row_index in 0..height {
            let y = if forward { row_index } else { height - 1 - row_index };
            for col_index in 0..width {
                let x = if forward { col_index } else { width - 1 - col_index };
                let cell = (y * width + x) * nd;
                let cost = &volume[cell..cell + nd];
                // Horizontal path: the previous pixel of this row.
                if col_index == 0 {
                    path_start(cost, &mut horizontal, shift, cap);
                } else {
                    scratch.copy_from_slice(&horizontal);
                    path_step(cost, &scratch, &mut horizontal, p1, p2, shift, cap);
                }
                total.copy_from_slice(&horizontal);
                // Paths from the previous row: x − step, x, x + step (step = ±1 with the sweep).
                for (k, dx) in [-1isize, 0, 1].into_iter().enumerate() {
                    let dx = if forward { dx } else { -dx };
                    let px = x as isize + dx;
                    let out = &mut current[k][x * nd..(x + 1) * nd];
                    if row_index > 0 && px >= 0 && (px as usize) < width {
                        let p = px as usize * nd;
                        path_step(cost, &previous[k][p..p + nd], out, p1, p2, shift, cap);
                    } else {
                        path_start(cost, out, shift, cap);
                    }
                    for (t, v) in total.iter_mut().zip(out.iter()) {
                        *t = t.saturating_add(*v);
                    }
                }
                let cell_sum = &mut sum[cell..cell + nd];
                if forward {
                    // First touch writes: a fresh page is faulted in once, not read as the shared
                    // zero page and then copied on write.
                    cell_sum.copy_from_slice(&total);
                } else {
                    for (s, t) in cell_sum.iter_mut().zip(&total) {
                        *s = s.saturating_add(*t);
                    }
                }
            }
            std::mem::swap(&mut previous, &mut current);
        }
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wta::winner_take_all;

    #[test]
    fn smoothing_fills_an_ambiguous_pixel_from_its_neighbours() {
        // A 5×5 image whose pixels all prefer disparity 2, except the centre, whose costs are flat
        // (textureless): SGM must give it 2 as well; WTA alone cannot.
        let (w, h, nd) = (5, 5, 5);
        let mut volume = vec![0u16; w * h * nd];
        for p in 0..w * h {
            for d in 0..nd {
                volume[p * nd + d] = if p == 12 {
                    10
                } else if d == 2 {
                    0
                } else {
                    20
                };
            }
        }
        let sum = aggregate(&volume, w, h, nd, 20, 3, 12);
        let mut disparity = vec![0.0f32; w * h];
        winner_take_all(&sum, nd, 0, false, &mut disparity);
        assert!(disparity.iter().all(|d| *d == 2.0), "{disparity:?}");
    }

    #[test]
    fn costs_are_scaled_to_fit_u16() {
        assert_eq!(cost_shift(100, 50), 0);
        let shift = cost_shift(81 * 255, 500);
        assert!(8 * (((81 * 255) >> shift) + 500) < 65_535);
    }
}
