//! `fuse`: the multiscopic depth algorithms — cost volumes between the reference view and each
//! neighbour, their fusion (mean, min, the paper's heuristic, MFuseNet), and the optimisers
//! (winner-take-all, SGM, graph cuts).
//!
//! This crate is the leaf of the workspace: plain buffers in, disparity out. No log formats, no
//! command line, no viewer (see ARCHITECTURE.md). It starts with the geometry every method
//! shares: disparity and depth of a rectified, equal-baseline multiscopic rig.

/// Disparity (pixels) of a point at z-depth `depth_m` for a neighbour at `baseline_m`:
/// `d = f·b / z`. Returns `None` for unknown depth (≤ 0 or not finite).
pub fn disparity_from_depth(focal_px: f64, baseline_m: f64, depth_m: f64) -> Option<f64> {
    (depth_m.is_finite() && depth_m > 0.0).then(|| focal_px * baseline_m / depth_m)
}

/// Z-depth (m) of a pixel with disparity `disparity_px`: `z = f·b / d`. Returns `None` for
/// disparities ≤ 0 or not finite (no finite depth).
pub fn depth_from_disparity(focal_px: f64, baseline_m: f64, disparity_px: f64) -> Option<f64> {
    (disparity_px.is_finite() && disparity_px > 0.0).then(|| focal_px * baseline_m / disparity_px)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_and_disparity_are_inverse() {
        // The paper's rig: f ≈ 1663 px (1920 px, 60° field of view), 20 mm baseline, 0.6 m away.
        let d = disparity_from_depth(1662.77, 0.02, 0.6).unwrap_or_default();
        assert!((d - 55.4257).abs() < 1e-3, "{d}");
        let z = depth_from_disparity(1662.77, 0.02, d).unwrap_or_default();
        assert!((z - 0.6).abs() < 1e-12);
        assert_eq!(disparity_from_depth(1000.0, 0.02, 0.0), None);
        assert_eq!(depth_from_disparity(1000.0, 0.02, f64::NAN), None);
    }
}
