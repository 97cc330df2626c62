//! Evaluation regions of a view set with ground truth: pixels occluded in a neighbour (from the
//! ground-truth disparity by forward warping with a z-buffer) and view-dependent surfaces (the
//! simulator's glossy and mirror classes), where multiscopic fusion should help most.

use fuse::metrics::{Metrics, evaluate};
use serde::Serialize;

/// Disparity margin (px) by which a warped pixel must be hidden to count as occluded.
const OCCLUSION_MARGIN_PX: f32 = 1.0;

/// `true` where the reference pixel is hidden in the neighbour at `offset` (grid units): some
/// other pixel with a larger disparity lands on the same neighbour pixel.
pub fn occluded_in(disparity: &[f32], width: usize, height: usize, offset: [i32; 2]) -> Vec<bool> {
    let target = |x: usize, y: usize, d: f32| -> Option<usize> {
        let qx = (x as f32 - offset[0] as f32 * d).round();
        let qy = (y as f32 - offset[1] as f32 * d).round();
        (qx >= 0.0 && qy >= 0.0 && (qx as usize) < width && (qy as usize) < height)
            .then(|| qy as usize * width + qx as usize)
    };
    // Pixels row by row (no division per pixel).
    let pixels = || (0..height).flat_map(move |y| (0..width).map(move |x| (x, y)));
    let mut front = vec![f32::NEG_INFINITY; width * height];
    for ((x, y), d) in pixels().zip(disparity) {
        if d.is_finite()
            && let Some(q) = target(x, y, *d)
        {
            front[q] = front[q].max(*d);
        }
    }
    pixels()
        .zip(disparity)
        .map(|((x, y), d)| d.is_finite() && target(x, y, *d).is_none_or(|q| front[q] > d + OCCLUSION_MARGIN_PX))
        .collect()
}

/// Metrics over the whole image and over the regions that exist in this set.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct RegionMetrics {
    /// All pixels with ground truth.
    pub all: Metrics,
    /// Pixels occluded in at least one neighbour of the set.
    pub occluded: Option<Metrics>,
    /// Pixels occluded in none.
    pub visible: Option<Metrics>,
    /// Glossy or mirror-like surfaces (simulated sets).
    pub specular: Option<Metrics>,
}

/// Evaluates `estimate` against `truth` overall and per region.
pub fn region_metrics(
    estimate: &[f32],
    truth: &[f32],
    occluded: &[bool],
    surface_class: Option<&[u8]>,
    missing_error_px: f64,
) -> Option<RegionMetrics> {
    let all = evaluate(estimate, truth, None, missing_error_px)?;
    let visible_mask: Vec<bool> = occluded.iter().map(|o| !o).collect();
    let specular_mask: Option<Vec<bool>> = surface_class.map(|classes| {
        classes
            .iter()
            .map(|c| *c == record::scene::SurfaceClass::Glossy as u8 || *c == record::scene::SurfaceClass::Mirror as u8)
            .collect()
    });
    Some(RegionMetrics {
        all,
        occluded: evaluate(estimate, truth, Some(occluded), missing_error_px),
        visible: evaluate(estimate, truth, Some(&visible_mask), missing_error_px),
        specular: specular_mask.and_then(|mask| evaluate(estimate, truth, Some(&mask), missing_error_px)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn background_left_of_a_foreground_step_is_occluded_in_the_right_view() {
        // Row: background disparity 2 for x < 5, foreground 6 from x = 5. In the right view
        // (q = x − d) the foreground covers q = 0..=3 and hides the background at x = 2..=4;
        // x = 0, 1 and the foreground at x = 5 fall off the image.
        let width = 10;
        let disparity: Vec<f32> = (0..width).map(|x| if x < 5 { 2.0 } else { 6.0 }).collect();
        let occluded = occluded_in(&disparity, width, 1, [1, 0]);
        assert_eq!(
            occluded,
            vec![true, true, true, true, true, true, false, false, false, false]
        );
        // In the left view (q = x + d) nothing is hidden except what leaves the image.
        let occluded = occluded_in(&disparity, width, 1, [-1, 0]);
        assert_eq!(occluded.iter().filter(|o| **o).count(), 5, "{occluded:?}");
        assert!(occluded[5..].iter().all(|o| *o));
    }
}
