//! `viz`: what users look at — captures, cost volumes, disparity and point clouds streamed to the
//! Rerun viewer, or written as files (colour-mapped PNG, PFM, PLY) for people without a viewer.
//!
//! It never depends on `replay`; binaries hand it plain data. [`files`] writes PFM, 16-bit
//! depth PNG and colour-mapped disparity PNG; [`stream`] logs captures, cost volumes and results
//! to the Rerun viewer (spawned, connected, or saved as `.rrd`) with a blueprint built in code;
//! [`log_blueprint`] writes the layout a recorded MCAP log is opened with (`rerun log.mcap log.rbl`);
//! [`turbo`] is the colour map.

pub mod files;
pub mod log_blueprint;
pub mod stream;

/// Turbo colour map (Mikhailov, Google 2019) at `t` ∈ [0, 1], as 8-bit RGB, by the published
/// polynomial approximation. Values outside [0, 1] are clamped; NaN maps to black.
pub fn turbo(t: f64) -> [u8; 3] {
    if t.is_nan() {
        return [0, 0, 0];
    }
    let x = t.clamp(0.0, 1.0);
    let poly = |c: [f64; 6]| c[0] + x * (c[1] + x * (c[2] + x * (c[3] + x * (c[4] + x * c[5]))));
    let r = poly([
        0.135_721_38,
        4.615_392_6,
        -42.660_322,
        132.131_08,
        -152.942_39,
        59.286_38,
    ]);
    let g = poly([
        0.091_402_61,
        2.194_188_4,
        4.842_966_6,
        -14.185_033,
        4.277_298_6,
        2.829_566,
    ]);
    let b = poly([0.106_673_3, 12.641_946, -60.582_05, 110.362_77, -89.903_11, 27.348_25]);
    [r, g, b].map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turbo_runs_from_dark_blue_through_green_to_dark_red() {
        let low = turbo(0.15);
        let mid = turbo(0.5);
        let high = turbo(1.0);
        assert!(low[2] > low[0] && low[2] > low[1], "{low:?}");
        assert!(mid[1] > mid[0] && mid[1] > mid[2], "{mid:?}");
        assert!(high[0] > high[1] && high[0] > high[2], "{high:?}");
        assert_eq!(turbo(-3.0), turbo(0.0));
        assert_eq!(turbo(f64::NAN), [0, 0, 0]);
    }
}
