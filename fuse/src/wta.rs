//! Winner-take-all disparity selection with sub-pixel parabola refinement.

use crate::cost::INVALID_COST;

/// Picks the disparity of least cost for every pixel of `costs` (`[x][d]` rows, any number of
/// rows) and writes `min_disparity + d + δ` into `out`, where δ ∈ (−½, ½) is the vertex of the
/// parabola through the costs at `d − 1, d, d + 1` (when `subpixel` and both exist). Pixels whose
/// best cost is [`INVALID_COST`] get `f32::INFINITY`.
pub fn winner_take_all(costs: &[u16], disparities: usize, min_disparity: usize, subpixel: bool, out: &mut [f32]) {
    for (pixel, c) in out.iter_mut().zip(costs.chunks_exact(disparities)) {
        // Cost and disparity packed into one u32 (cost high): one vectorised min finds the
        // smallest cost at its first disparity.
        let packed = c
            .iter()
            .zip(0u32..)
            .map(|(v, d)| (u32::from(*v) << 16) | d)
            .min()
            .unwrap_or(u32::from(INVALID_COST) << 16);
        let (best, best_cost) = ((packed & 0xFFFF) as usize, (packed >> 16) as u16);
        if best_cost == INVALID_COST {
            *pixel = f32::INFINITY;
            continue;
        }
        let mut delta = 0.0f32;
        if subpixel && best > 0 && best + 1 < disparities && c[best - 1] != INVALID_COST && c[best + 1] != INVALID_COST
        {
            let (left, centre, right) = (f32::from(c[best - 1]), f32::from(best_cost), f32::from(c[best + 1]));
            let curvature = left - 2.0 * centre + right;
            if curvature > 0.0 {
                delta = (0.5 * (left - right) / curvature).clamp(-0.5, 0.5);
            }
        }
        *pixel = (min_disparity + best) as f32 + delta;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parabola_vertex_is_recovered() {
        // Costs sampled from (d − 2.3)²: the minimum sits at 2.3.
        let costs: Vec<u16> = (0..6).map(|d| ((d as f32 - 2.3).powi(2) * 100.0) as u16).collect();
        let mut out = [0.0f32];
        winner_take_all(&costs, 6, 10, true, &mut out);
        assert!((out[0] - 12.3).abs() < 0.02, "{}", out[0]);
        winner_take_all(&costs, 6, 10, false, &mut out);
        assert_eq!(out[0], 12.0);
        winner_take_all(&[INVALID_COST; 6], 6, 0, true, &mut out);
        assert!(out[0].is_infinite());
    }
}
