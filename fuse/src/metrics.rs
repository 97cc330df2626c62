//! Error measures against ground-truth disparity, as in the paper's evaluation code: over every
//! pixel whose ground truth is known (finite: signed truths of converged rigs count, NaN is
//! unknown), RMS, AvgErr (mean absolute error) and the
//! percentages of pixels with an error above 0.5, 1 and 2 px, and above 0.07 px (BadPix 0.07, the
//! light-field benchmarks' sub-pixel measure). A pixel without an estimate counts
//! as an error of the whole search range (it is never silently left out).

use serde::{Deserialize, Serialize};

/// Metrics of one disparity map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// Root-mean-square error (px).
    pub rms: f64,
    /// Mean absolute error (px).
    #[serde(alias = "avg_err")]
    pub avg_err_px: f64,
    /// % of pixels with error > 0.5 px.
    pub bad_0_5: f64,
    /// % of pixels with error > 1 px.
    pub bad_1: f64,
    /// % of pixels with error > 2 px.
    pub bad_2: f64,
    /// % of pixels with error > 0.07 px (BadPix 0.07): sub-pixel precision, where smooth surfaces
    /// tell it apart (slanted planes, light fields).
    #[serde(default)]
    pub bad_0_07: f64,
    /// Pixels with known ground truth.
    pub pixels: usize,
    /// Of those, pixels the method left without an estimate.
    pub missing: usize,
    /// Mean signed error (estimate − truth, px) of the pixels within 2 px: a sub-pixel bias
    /// that AvgErr cannot tell from noise.
    #[serde(default)]
    pub bias: f64,
}

/// Compares `estimate` with `ground_truth` over the pixels where `mask` (if any) is true and the
/// ground truth is known. Missing estimates count as an error of `missing_error_px`.
pub fn evaluate(
    estimate: &[f32],
    ground_truth: &[f32],
    mask: Option<&[bool]>,
    missing_error_px: f64,
) -> Option<Metrics> {
    let mut sums = MetricSums::default();
    for (i, (&e, &g)) in estimate.iter().zip(ground_truth).enumerate() {
        if !g.is_finite() || mask.is_some_and(|m| !m[i]) {
            continue;
        }
        sums.add(e, g, missing_error_px);
    }
    sums.metrics()
}

/// The running sums behind [`Metrics`], one pixel at a time: several regions of one image are
/// measured in a single pass, each region's sums fed the same pixels in the same order as
/// [`evaluate`] over its mask (the same bits).
#[derive(Debug, Clone, Copy, Default)]
pub struct MetricSums {
    n: usize,
    missing: usize,
    sum_abs: f64,
    sum_sq: f64,
    bad: [usize; 4],
    sum_inlier: f64,
    inliers: usize,
}

impl MetricSums {
    /// Adds one pixel whose ground truth `g` is known (finite); a non-finite `e` is a missing
    /// estimate, an error of `missing_error_px`.
    #[inline]
    pub fn add(&mut self, e: f32, g: f32, missing_error_px: f64) {
        let error = if e.is_finite() {
            f64::from((e - g).abs())
        } else {
            self.missing += 1;
            missing_error_px
        };
        if error <= 2.0 {
            self.sum_inlier += f64::from(e - g);
            self.inliers += 1;
        }
        self.n += 1;
        self.sum_abs += error;
        self.sum_sq += error * error;
        for (count, threshold) in self.bad.iter_mut().zip([0.5, 1.0, 2.0, 0.07]) {
            if error > threshold {
                *count += 1;
            }
        }
    }

    /// The metrics of the pixels added; `None` without any.
    pub fn metrics(&self) -> Option<Metrics> {
        let n = self.n;
        (n > 0).then(|| {
            let percent = |c: usize| 100.0 * c as f64 / n as f64;
            Metrics {
                rms: (self.sum_sq / n as f64).sqrt(),
                avg_err_px: self.sum_abs / n as f64,
                bad_0_5: percent(self.bad[0]),
                bad_1: percent(self.bad[1]),
                bad_2: percent(self.bad[2]),
                bad_0_07: percent(self.bad[3]),
                pixels: n,
                missing: self.missing,
                bias: if self.inliers > 0 {
                    self.sum_inlier / self.inliers as f64
                } else {
                    0.0
                },
            }
        })
    }
}

/// The mean of per-scene metrics (the paper averages per scene).
pub fn average(scenes: &[Metrics]) -> Option<Metrics> {
    let n = scenes.len() as f64;
    (!scenes.is_empty()).then(|| Metrics {
        rms: scenes.iter().map(|m| m.rms).sum::<f64>() / n,
        avg_err_px: scenes.iter().map(|m| m.avg_err_px).sum::<f64>() / n,
        bad_0_5: scenes.iter().map(|m| m.bad_0_5).sum::<f64>() / n,
        bad_1: scenes.iter().map(|m| m.bad_1).sum::<f64>() / n,
        bad_2: scenes.iter().map(|m| m.bad_2).sum::<f64>() / n,
        bad_0_07: scenes.iter().map(|m| m.bad_0_07).sum::<f64>() / n,
        pixels: scenes.iter().map(|m| m.pixels).sum(),
        missing: scenes.iter().map(|m| m.missing).sum(),
        bias: scenes.iter().map(|m| m.bias).sum::<f64>() / n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_of_a_known_error_pattern() {
        let gt = [10.0f32, 10.0, 10.0, 10.0, f32::NAN];
        let estimate = [10.0f32, 10.6, 11.5, 13.0, 99.0];
        let m = evaluate(&estimate, &gt, None, 64.0).unwrap_or_else(|| panic!("no pixels"));
        assert_eq!(m.pixels, 4);
        assert!((m.avg_err_px - (0.0 + 0.6 + 1.5 + 3.0) / 4.0).abs() < 1e-6);
        assert!((m.bad_0_5 - 75.0).abs() < 1e-9);
        assert!((m.bad_0_07 - 75.0).abs() < 1e-9);
        assert!((m.bad_1 - 50.0).abs() < 1e-9);
        assert!((m.bad_2 - 25.0).abs() < 1e-9);
        assert!((m.bias - (0.0 + 0.6 + 1.5) / 3.0).abs() < 1e-6, "{}", m.bias);
        let rms = ((0.36f64 + 2.25 + 9.0) / 4.0).sqrt();
        assert!((m.rms - rms).abs() < 1e-5);
        let missing = evaluate(&[f32::INFINITY], &[5.0], None, 32.0).unwrap_or_else(|| panic!("no pixels"));
        assert_eq!((missing.missing, missing.avg_err_px), (1, 32.0));
        // A converged rig's truths are signed: 0 and negative disparities are known values.
        let signed = evaluate(&[-2.5, 0.5], &[-3.0, 0.0], None, 32.0).unwrap_or_else(|| panic!("no pixels"));
        assert_eq!(signed.pixels, 2);
        assert!((signed.avg_err_px - 0.5).abs() < 1e-6);
    }
}
