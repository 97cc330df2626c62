//! Semi-global matching (Hirschmüller, PAMI 2008) over a fused cost volume: eight paths,
//! penalties P1 for ±1 disparity steps and P2 for larger jumps, summed into one `u16` volume.

use crate::cost::INVALID_COST;

/// Directions of the eight paths, as `(dx, dy)` of the previous pixel on the path: the first
/// four are swept top-down, the last four bottom-up.
const FORWARD: [(isize, isize); 4] = [(-1, 0), (-1, -1), (0, -1), (1, -1)];

/// Scales costs so that the sum of eight paths fits `u16`: returns the right shift to apply.
pub fn cost_shift(max_cost: u32, p2: u32) -> u32 {
    let mut shift = 0;
    while 8 * ((max_cost >> shift) + p2) >= u32::from(u16::MAX) {
        shift += 1;
    }
    shift
}

#[inline]
fn path_step(cost: &[u16], previous: Option<&[u16]>, out: &mut [u16], p1: u16, p2: u16, shift: u32, cap: u16) {
    match previous {
        None => {
            for (o, c) in out.iter_mut().zip(cost) {
                *o = (*c >> shift).min(cap);
            }
        }
        Some(prev) => {
            let min_prev = prev.iter().copied().min().unwrap_or(0);
            let jump = min_prev.saturating_add(p2);
            let n = cost.len();
            for d in 0..n {
                let mut best = prev[d].min(jump);
                if d > 0 {
                    best = best.min(prev[d - 1].saturating_add(p1));
                }
                if d + 1 < n {
                    best = best.min(prev[d + 1].saturating_add(p1));
                }
                out[d] = ((cost[d] >> shift).min(cap) + best) - min_prev;
            }
        }
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
    let row_len = width * disparities;
    let mut sum = vec![0u16; volume.len()];
    let mut scratch = vec![0u16; disparities];
    for forward in [true, false] {
        // Path costs of the previous and current row, per direction.
        let mut previous: Vec<Vec<u16>> = vec![vec![0u16; row_len]; 4];
        let mut current: Vec<Vec<u16>> = vec![vec![0u16; row_len]; 4];
        let ys: Vec<usize> = if forward {
            (0..height).collect()
        } else {
            (0..height).rev().collect()
        };
        for (row_index, &y) in ys.iter().enumerate() {
            let xs: Vec<usize> = if forward {
                (0..width).collect()
            } else {
                (0..width).rev().collect()
            };
            for (col_index, &x) in xs.iter().enumerate() {
                let cell = (y * width + x) * disparities;
                let cost = &volume[cell..cell + disparities];
                for (k, (dx, dy)) in FORWARD.iter().enumerate() {
                    let (dx, dy) = if forward { (*dx, *dy) } else { (-dx, -dy) };
                    let px = x as isize + dx;
                    let source: Option<&[u16]> = if dy == 0 {
                        // Same row: the path's previous pixel was processed just before.
                        (col_index > 0).then(|| {
                            let p = px as usize * disparities;
                            &current[k][p..p + disparities]
                        })
                    } else if row_index > 0 && px >= 0 && (px as usize) < width {
                        let p = px as usize * disparities;
                        Some(&previous[k][p..p + disparities])
                    } else {
                        None
                    };
                    path_step(cost, source, &mut scratch, p1, p2, shift, cap);
                    current[k][x * disparities..(x + 1) * disparities].copy_from_slice(&scratch);
                    for (s, v) in sum[cell..cell + disparities].iter_mut().zip(&scratch) {
                        *s = s.saturating_add(*v);
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
