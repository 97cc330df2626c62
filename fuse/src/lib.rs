//! `fuse`: the multiscopic depth algorithms — cost volumes between the reference view and each
//! neighbour, their fusion (mean, min, the paper's heuristic, MFuseNet), and the optimisers
//! (winner-take-all, SGM, graph cuts).
//!
//! This crate is the leaf of the workspace: plain buffers in, disparity out. No log formats, no
//! command line, no viewer (see ARCHITECTURE.md).
//!
//! - [`volume::Problem`]: the reference view, its neighbours (with their grid offsets) and the
//!   disparity range; [`cost`] and [`fusion`] build the fused data term band by band;
//!   [`volume::CostVolume`] holds a whole volume (one neighbour's or fused, quantised, summed or
//!   normalised) for the methods that need one (SGM, MFuseNet).
//! - [`methods`]: every method behind the [`methods::Method`] trait, listed in
//!   [`methods::registry`] with its family.
//! - [`maxflow`]: Boykov–Kolmogorov max-flow and the binary energies it minimises;
//!   [`graph_cuts`]: Kolmogorov–Zabih's energy with occlusion and uniqueness over several views,
//!   minimised by α-expansion.
//! - [`nn`]: the 3D convolutions, BatchNorm and soft-argmin MFuseNet is made of (forward and
//!   backward, fast kernels checked against plain loops); [`mfusenet`]: the network, its
//!   safetensors weights, its inputs, tiled inference and the training pieces.
//! - [`metrics`]: the paper's error measures against ground truth.
//! - [`plan`]: next-best-view planning: which grid offset would resolve most of what the
//!   current depth lacks (occlusions, texture direction, depth resolution).

pub mod borders;
pub mod cost;
pub mod fusion;
pub mod graph_cuts;
pub mod image;
pub mod lines;
pub mod maxflow;
pub mod methods;
pub mod metrics;
pub mod mfusenet;
pub mod nn;
pub mod photometric;
pub mod plan;
pub mod postprocess;
pub mod rng;
pub mod sgm;
pub mod subpixel;
pub mod thin_parts;
pub mod volume;
pub mod wide;
pub mod wta;

pub use image::{DisparityImage, Image};
pub use volume::{Neighbour, Problem};

/// Errors of the algorithms; each carries the offending values.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FuseError {
    /// A buffer does not match its image size.
    #[error("{what} of {width}x{height} has {len} values")]
    ImageSize {
        /// Which buffer.
        what: &'static str,
        /// Width.
        width: usize,
        /// Height.
        height: usize,
        /// Values present.
        len: usize,
    },
    /// A neighbour's size differs from the reference.
    #[error("neighbour '{role}' is {width}x{height}, the reference is {reference_width}x{reference_height}")]
    SizeMismatch {
        /// Role.
        role: String,
        /// Width.
        width: usize,
        /// Height.
        height: usize,
        /// Reference width.
        reference_width: usize,
        /// Reference height.
        reference_height: usize,
    },
    /// A neighbour sits at the reference position.
    #[error(
        "neighbour '{role}' has a zero offset or a non-positive baseline ratio (zero baseline): no disparity to search"
    )]
    ZeroOffset {
        /// Role.
        role: String,
    },
    /// The set has no neighbour.
    #[error("the view set has no neighbour view")]
    NoNeighbours,
    /// The disparity range is empty or too large.
    #[error(
        "disparity range {min_disparity}+{num_disparities} is invalid (1..=1024 disparities from at most ±1048576)"
    )]
    DisparityRange {
        /// First disparity.
        min_disparity: i32,
        /// Count.
        num_disparities: usize,
    },
    /// A configuration value is out of range.
    #[error("invalid configuration {field} = {value}: {reason}")]
    Config {
        /// Field.
        field: &'static str,
        /// Value.
        value: String,
        /// What is allowed.
        reason: &'static str,
    },
    /// JSON overrides that do not fit a configuration's fields, or a configuration that does
    /// not serialise.
    #[error("method configuration {value} does not fit: {reason}")]
    ConfigJson {
        /// The overrides (or the method whose configuration failed).
        value: String,
        /// What serde said.
        reason: String,
    },
    /// The MFuseNet network or its weights.
    #[error(transparent)]
    MFuseNet(#[from] mfusenet::Error),
    /// No method has this name.
    #[error("unknown method '{name}' (known: {known})")]
    UnknownMethod {
        /// Name given.
        name: String,
        /// Registered names.
        known: String,
    },
}

/// Disparity (pixels) of a point at z-depth `depth_m` for a neighbour at `baseline_m`:
/// `d = f·b / z`. Returns `None` for unknown depth (≤ 0 or not finite).
pub fn disparity_from_depth(focal_px: f64, baseline_m: f64, depth_m: f64) -> Option<f64> {
    (depth_m.is_finite() && depth_m > 0.0).then(|| focal_px * baseline_m / depth_m)
}

/// The disparities searched when nothing says otherwise for an image `width_px` wide: a
/// fifteenth of the width, rounded up to a multiple of 16 (16 … 256).
pub fn default_num_disparities(width_px: usize) -> usize {
    (width_px / 15).div_ceil(16).clamp(1, 16) * 16
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
