//! Winner-take-all disparity selection with sub-pixel refinement: a curve through the costs at
//! the winner and its two neighbours ([`SubpixelFit`]).

use serde::{Deserialize, Serialize};

use crate::cost::INVALID_COST;

/// The curve through the costs `l, c, r` at `d − 1, d, d + 1` whose vertex is the sub-pixel
/// disparity.
///
/// A parabola suits costs that grow quadratically away from the match (squared differences);
/// costs that grow linearly (absolute differences, census Hamming distances, and SGM's sums of
/// them) have a V-shaped minimum, where the parabola's vertex is pulled towards the integer
/// ("pixel locking") and the equiangular fit (two lines of opposite slope, Shimizu & Okutomi,
/// ICCV 2001) is unbiased. Measured on `middlebury2006-third-dev` (`replay eval`, AvgErr):
/// `sgm-mean` 0.400 → 0.371 px, `sgm-heuristic` 0.430 → 0.401, `mfusenet` 0.391 → 0.363, every
/// scene better; on the held-out simulated captures (`scripts/eval-simulated.sh`) `sgm-heuristic`
/// 0.998 → 0.961 and three-view `mfusenet` 0.985 → 0.950. Block matching on Birchfield–Tomasi
/// colour costs keeps the parabola (`bm-mean` 0.753 → 0.759 with the lines).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SubpixelFit {
    /// `δ = (l − r) / (2 (l − 2c + r))`.
    Parabola,
    /// `δ = (l − r) / (2 (max(l, r) − c))`: lines of equal and opposite slope through the
    /// lower neighbour and the steeper side.
    Equiangular,
}

impl SubpixelFit {
    /// The offset δ ∈ [−½, ½] of the vertex from the middle sample, when `c` is a minimum of the
    /// three with a vertex (positive curvature, or a positive slope for the lines); `None` for
    /// non-finite costs.
    pub fn offset(self, [l, c, r]: [f64; 3]) -> Option<f64> {
        if !(c <= l && c <= r && l.is_finite() && r.is_finite()) {
            return None;
        }
        let denominator = match self {
            Self::Parabola => l - 2.0 * c + r,
            Self::Equiangular => l.max(r) - c,
        };
        (denominator > 0.0).then(|| (0.5 * (l - r) / denominator).clamp(-0.5, 0.5))
    }
}

/// `|δ|` at which a [`LockingCurve`] gives its corrected offsets.
pub const LOCKING_KNOTS: [f64; 10] = [0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5];

/// Fewest samples [`LockingCurve::fit`] fits a curve to.
pub const LOCKING_MIN_SAMPLES: usize = 1000;

/// A correction of a [`SubpixelFit`]'s pixel locking: the sub-pixel offset expected of the truth
/// given the fit's offset δ, an odd piecewise-linear map through `(0, 0)` and
/// `(LOCKING_KNOTS[i], self.0[i])` ([`LockingCurve::fit`] on the ground truth of training
/// captures). The identity is `LOCKING_KNOTS` itself.
///
/// Census distances summed by SGM lock hard even with the equiangular fit: on the simulated
/// training captures a surface 0.2 px off an integer reads as about 0.05 px. MFuseNet's refined
/// readout takes the curve its weights file carries (`locking_curve`, written by `replay
/// train`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LockingCurve(pub [f64; 10]);

impl LockingCurve {
    /// The curve that changes nothing.
    pub const IDENTITY: Self = Self(LOCKING_KNOTS);

    /// The curve moved `strength` of the way from the identity (0) to itself (1).
    pub fn damped(self, strength: f64) -> Self {
        let mut values = LOCKING_KNOTS;
        for (v, c) in values.iter_mut().zip(self.0) {
            *v += strength * (c - *v);
        }
        Self(values)
    }

    /// The corrected offset for the fit's offset `delta` (∈ [−½, ½]).
    pub fn apply(&self, delta: f64) -> f64 {
        let a = delta.abs().min(0.5);
        let (mut x0, mut y0) = (0.0, 0.0);
        for (&x1, &y1) in LOCKING_KNOTS.iter().zip(&self.0) {
            if a <= x1 {
                return delta.signum() * (y0 + (y1 - y0) * (a - x0) / (x1 - x0));
            }
            (x0, y0) = (x1, y1);
        }
        delta.signum() * y0
    }

    /// The least-squares curve through `(δ, truth)` pairs: the fit's offset at the integer
    /// nearest the truth and the truth's offset from that integer (both in [−½, ½]). The map is
    /// odd (a surface ¼ px left of an integer locks as one ¼ px right does, mirrored); knots no
    /// sample reaches stay near the identity (a small ridge towards it). `None` with fewer than
    /// [`LOCKING_MIN_SAMPLES`] usable pairs. Values are rounded to 1e-4.
    pub fn fit(pairs: impl IntoIterator<Item = (f64, f64)>) -> Option<Self> {
        const N: usize = LOCKING_KNOTS.len();
        let mut normal = [[0.0f64; N]; N];
        let mut rhs = [0.0f64; N];
        let mut count = 0usize;
        for (delta, truth) in pairs {
            if !(delta.is_finite() && truth.is_finite()) || delta == 0.0 {
                continue;
            }
            let (a, t) = (delta.abs().min(0.5), delta.signum() * truth);
            // The hat functions of the two knots around `a` (the one at 0 is pinned to 0).
            let upper = LOCKING_KNOTS.iter().position(|&k| a <= k).unwrap_or(N - 1);
            let (x0, x1) = (
                if upper == 0 { 0.0 } else { LOCKING_KNOTS[upper - 1] },
                LOCKING_KNOTS[upper],
            );
            let w1 = (a - x0) / (x1 - x0);
            let basis = [Some((upper, w1)), upper.checked_sub(1).map(|lower| (lower, 1.0 - w1))];
            for &(i, wi) in basis.iter().flatten() {
                rhs[i] += wi * t;
                for &(j, wj) in basis.iter().flatten() {
                    normal[i][j] += wi * wj;
                }
            }
            count += 1;
        }
        if count < LOCKING_MIN_SAMPLES {
            return None;
        }
        let ridge = 1e-6 * count as f64;
        for (i, row) in normal.iter_mut().enumerate() {
            row[i] += ridge;
            rhs[i] += ridge * LOCKING_KNOTS[i];
        }
        // Rounded to 1e-4 px: the curve is read back from JSON metadata.
        solve(normal, rhs).map(|values| Self(values.map(|v| (v * 1e4).round() / 1e4)))
    }
}

/// `x` with `a x = b` by Gaussian elimination with partial pivoting; `None` when singular.
fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    for col in 0..N {
        let pivot = (col..N).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[pivot][col].abs() < 1e-12 {
            return None;
        }
        a.swap(col, pivot);
        b.swap(col, pivot);
        let (pivot_row, pivot_b) = (a[col], b[col]);
        for (row, rhs) in a.iter_mut().zip(b.iter_mut()).skip(col + 1) {
            let f = row[col] / pivot_row[col];
            for (v, p) in row.iter_mut().zip(&pivot_row).skip(col) {
                *v -= f * p;
            }
            *rhs -= f * pivot_b;
        }
    }
    let mut x = [0.0; N];
    for row in (0..N).rev() {
        let tail: f64 = (row + 1..N).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - tail) / a[row][row];
    }
    Some(x)
}

/// Picks the disparity of least cost for every pixel of `costs` (`[x][d]` rows, any number of
/// rows) and writes `min_disparity + d + δ` into `out`, where δ ∈ [−½, ½] is the vertex of the
/// `subpixel` fit through the costs at `d − 1, d, d + 1` (when both exist; `None`: δ = 0). Pixels
/// whose best cost is [`INVALID_COST`] get `f32::INFINITY`.
pub fn winner_take_all(
    costs: &[u16],
    num_disparities: usize,
    min_disparity: i32,
    subpixel: Option<SubpixelFit>,
    out: &mut [f32],
) {
    winners(costs, num_disparities, min_disparity, subpixel, out, None);
}

/// [`winner_take_all`] that also writes each pixel's [`peak_confidence`] into `confidence`.
pub fn winner_take_all_confident(
    costs: &[u16],
    num_disparities: usize,
    min_disparity: i32,
    subpixel: Option<SubpixelFit>,
    out: &mut [f32],
    confidence: &mut [f32],
) {
    winners(costs, num_disparities, min_disparity, subpixel, out, Some(confidence));
}

/// The confidence of the winner `best` of one pixel's costs, in [0, 1]: `1 − c₁/c₂`, where `c₁` is
/// its cost and `c₂` the least cost at least 2 disparities away from it (the naive peak ratio,
/// Hu & Mordohai 2012, with the winner's own slope left out): 0 where another disparity matches
/// as well, near 1 where the winner stands alone; 1 when no other disparity is valid, 0 when
/// the winner itself is invalid.
pub fn peak_confidence(costs: &[u16], best: usize) -> f32 {
    let Some(&c1) = costs.get(best) else {
        return 0.0;
    };
    if c1 == INVALID_COST {
        return 0.0;
    }
    // The least cost more than one disparity from `best` (an invalid cost is `u16::MAX`, so it
    // never wins unless every one is invalid): one pass over whole runs of lanes with the three
    // around `best` masked, whose trip count is fixed (two minima of slices whose lengths
    // change from pixel to pixel spent as long in their unaligned heads and tails as in the
    // minima, 2026-12-06).
    let c2 = if let Ok(best) = u16::try_from(best)
        && costs.len() <= usize::from(u16::MAX)
    {
        // Lane `l` of run `k` is disparity `16k + l`; it is within one of `best` where
        // `d − best + 1` (mod 2¹⁶) is at most 2: 16-bit lanes throughout.
        let mut lanes = [INVALID_COST; CONFIDENCE_LANES];
        let (runs, rest) = costs.as_chunks::<CONFIDENCE_LANES>();
        // `d − best + 1` of each lane, stepped by a run at a time.
        let mut offsets: [u16; CONFIDENCE_LANES] =
            std::array::from_fn(|l| (l as u16).wrapping_sub(best).wrapping_add(1));
        for run in runs {
            for ((lane, v), offset) in lanes.iter_mut().zip(run).zip(&mut offsets) {
                // All ones (an invalid cost) within one of `best`, else the cost.
                let near = 0u16.wrapping_sub(u16::from(*offset <= 2));
                *lane = (*lane).min(*v | near);
                *offset = offset.wrapping_add(CONFIDENCE_LANES as u16);
            }
        }
        let near = |d: usize| d.abs_diff(usize::from(best)) <= 1;
        let tail = runs.len() * CONFIDENCE_LANES;
        rest.iter()
            .enumerate()
            .filter(|(l, _)| !near(tail + l))
            .fold(lanes.into_iter().fold(INVALID_COST, u16::min), |m, (_, v)| m.min(*v))
    } else {
        let below = costs.get(..best.saturating_sub(1)).unwrap_or(&[]);
        let above = costs.get(best + 2..).unwrap_or(&[]);
        below
            .iter()
            .copied()
            .fold(INVALID_COST, u16::min)
            .min(above.iter().copied().fold(INVALID_COST, u16::min))
    };
    match c2 {
        INVALID_COST => 1.0,
        0 => 0.0,
        c2 => (1.0 - f32::from(c1) / f32::from(c2)).clamp(0.0, 1.0),
    }
}

/// Costs [`peak_confidence`] takes at once (one AVX2 register of `u16`).
const CONFIDENCE_LANES: usize = 16;

/// The smallest of `costs` and its first index (`(0, INVALID_COST)` when empty): a vectorised
/// minimum, then the runs of [`MINIMUM_RUN`] searched for it with one comparison each (they
/// vectorise too) before the run holding it is scanned.
#[inline]
fn first_minimum(costs: &[u16]) -> (usize, u16) {
    let least = costs.iter().copied().fold(INVALID_COST, u16::min);
    let mut start = 0;
    for run in costs.chunks(MINIMUM_RUN) {
        if run.iter().fold(false, |found, v| found | (*v == least)) {
            let at = run.iter().position(|v| *v == least).unwrap_or(0);
            return (start + at, least);
        }
        start += run.len();
    }
    (0, least)
}

/// Costs [`first_minimum`] compares at once.
const MINIMUM_RUN: usize = 16;

fn winners(
    costs: &[u16],
    num_disparities: usize,
    min_disparity: i32,
    subpixel: Option<SubpixelFit>,
    out: &mut [f32],
    mut confidence: Option<&mut [f32]>,
) {
    for (i, (pixel, c)) in out.iter_mut().zip(costs.chunks_exact(num_disparities)).enumerate() {
        let (best, best_cost) = first_minimum(c);
        if let Some(confidence) = confidence.as_deref_mut() {
            confidence[i] = peak_confidence(c, best);
        }
        if best_cost == INVALID_COST {
            *pixel = f32::INFINITY;
            continue;
        }
        let mut delta = 0.0f32;
        if let Some(fit) = subpixel
            && best > 0
            && best + 1 < num_disparities
            && c[best - 1] != INVALID_COST
            && c[best + 1] != INVALID_COST
        {
            let costs = [c[best - 1], best_cost, c[best + 1]].map(f64::from);
            delta = fit.offset(costs).unwrap_or(0.0) as f32;
        }
        *pixel = min_disparity as f32 + best as f32 + delta;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_peak_confidence_is_the_plain_peak_ratio() {
        // The definition: the least cost more than one disparity from `best`.
        let plain = |c: &[u16], best: usize| -> f32 {
            let c1 = c.get(best).copied().unwrap_or(INVALID_COST);
            if c1 == INVALID_COST {
                return 0.0;
            }
            let c2 = c
                .iter()
                .enumerate()
                .filter(|(d, _)| d.abs_diff(best) > 1)
                .map(|(_, v)| *v)
                .min()
                .unwrap_or(INVALID_COST);
            match c2 {
                INVALID_COST => 1.0,
                0 => 0.0,
                c2 => (1.0 - f32::from(c1) / f32::from(c2)).clamp(0.0, 1.0),
            }
        };
        let mut state = 11u32;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            state >> 16
        };
        for n in [1usize, 2, 3, 5, 16, 17, 31, 33, 128, 131] {
            for _ in 0..40 {
                let costs: Vec<u16> = (0..n)
                    .map(|_| {
                        if next() % 7 == 0 {
                            INVALID_COST
                        } else {
                            (next() % 300) as u16
                        }
                    })
                    .collect();
                for best in [0, 1, n / 2, n.saturating_sub(2), n - 1] {
                    assert_eq!(
                        peak_confidence(&costs, best),
                        plain(&costs, best),
                        "{n} costs, best {best}: {costs:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_first_minimum_is_the_packed_minimum() {
        // Cost and disparity packed into one u32 (cost high): the smallest cost at its first
        // disparity, the definition the search by runs must reproduce.
        let packed = |c: &[u16]| {
            let p = c
                .iter()
                .zip(0u32..)
                .map(|(v, d)| (u32::from(*v) << 16) | d)
                .min()
                .unwrap_or(u32::from(INVALID_COST) << 16);
            ((p & 0xFFFF) as usize, (p >> 16) as u16)
        };
        let mut state = 7u32;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            state >> 16
        };
        for n in [1, 5, 16, 17, 33, 128, 131] {
            for spread in [3u32, 40, 60_000] {
                let costs: Vec<u16> = (0..n)
                    .map(|_| {
                        if next() % 9 == 0 {
                            INVALID_COST
                        } else {
                            (next() % spread) as u16
                        }
                    })
                    .collect();
                assert_eq!(first_minimum(&costs), packed(&costs), "{costs:?}");
            }
            let invalid = vec![INVALID_COST; n];
            assert_eq!(first_minimum(&invalid), packed(&invalid));
        }
    }

    #[test]
    fn the_peak_confidence_compares_the_winner_with_the_best_cost_away_from_it() {
        // A lone minimum: 1 − 10/40; its own slope (d ± 1) does not count.
        assert!((peak_confidence(&[50, 40, 12, 10, 11, 45], 3) - 0.75).abs() < 1e-6);
        // A second minimum as good as the first: no confidence.
        assert_eq!(peak_confidence(&[10, 30, 30, 10, 30], 0), 0.0);
        // Invalid costs never count; an invalid winner has none; a lone valid one is certain.
        assert!((peak_confidence(&[INVALID_COST, 9, 20, 30], 1) - (1.0 - 9.0 / 30.0)).abs() < 1e-6);
        assert_eq!(peak_confidence(&[INVALID_COST; 4], 0), 0.0);
        assert_eq!(peak_confidence(&[INVALID_COST, 3, INVALID_COST], 1), 1.0);
        let costs = [50u16, 40, 12, 10, 11, 45, 60, 20];
        let (mut d, mut c) = ([0.0f32; 1], [0.0f32; 1]);
        winner_take_all_confident(&costs, 8, -2, None, &mut d, &mut c);
        assert_eq!(d[0], 1.0);
        assert!((c[0] - 0.5).abs() < 1e-6, "{}", c[0]);
    }

    #[test]
    fn the_identity_curve_changes_nothing_and_a_curve_is_odd() {
        for delta in [-0.5, -0.31, -0.02, 0.0, 0.07, 0.25, 0.5] {
            assert!((LockingCurve::IDENTITY.apply(delta) - delta).abs() < 1e-12, "{delta}");
        }
        let doubled = LockingCurve(LOCKING_KNOTS.map(|k| (2.0 * k).min(0.5)));
        // Between knots the map is linear: 0.0375 lies halfway from 0.025 (0.05) to 0.05 (0.1).
        assert!((doubled.apply(0.0375) - 0.075).abs() < 1e-12);
        assert!((doubled.apply(-0.0375) + 0.075).abs() < 1e-12);
        assert!((doubled.apply(0.4) - 0.5).abs() < 1e-12);
        // Damped: part of the way from the identity.
        assert_eq!(doubled.damped(0.0), LockingCurve::IDENTITY);
        assert_eq!(doubled.damped(1.0), doubled);
        assert!((doubled.damped(0.5).apply(0.0375) - 0.05625).abs() < 1e-12);
    }

    #[test]
    fn fit_recovers_a_known_locking_from_samples() {
        // Truth offsets t uniform in [−½, ½]; the fit reads them locked towards the integer:
        // δ = t (½ + 2t²) (odd, monotone, δ(½) = ½, half the slope at 0). Its inverse at the
        // knots (by bisection) is what the fit must find, to within the piecewise-linear
        // approximation between knots.
        let lock = |t: f64| t * (0.5 + 2.0 * t * t);
        let pairs: Vec<(f64, f64)> = (0..20_000)
            .map(|i| {
                let t = -0.5 + (f64::from(i) + 0.5) / 20_000.0;
                (lock(t), t)
            })
            .collect();
        let curve = LockingCurve::fit(pairs.iter().copied()).expect("enough samples");
        for (k, v) in LOCKING_KNOTS.iter().zip(curve.0) {
            let (mut lo, mut hi) = (0.0, 0.5);
            for _ in 0..60 {
                let mid = 0.5 * (lo + hi);
                if lock(mid) < *k { lo = mid } else { hi = mid }
            }
            assert!((v - lo).abs() < 0.01, "knot {k}: {v} vs {lo}");
        }
        // The corrected offsets are far nearer the truth than the locked ones.
        let error = |f: &dyn Fn(f64) -> f64| pairs.iter().map(|(d, t)| (f(*d) - t).abs()).sum::<f64>();
        assert!(error(&|d| curve.apply(d)) < 0.2 * error(&|d| d));
        // Unlocked samples give (about) the identity; too few give none.
        let unlocked = LockingCurve::fit(pairs.iter().map(|(_, t)| (*t, *t))).expect("enough samples");
        for (k, v) in LOCKING_KNOTS.iter().zip(unlocked.0) {
            assert!((v - k).abs() < 1e-3, "knot {k}: {v}");
        }
        assert_eq!(
            LockingCurve::fit(pairs.iter().copied().take(LOCKING_MIN_SAMPLES - 1)),
            None
        );
    }

    #[test]
    fn parabola_vertex_is_recovered() {
        // Costs sampled from (d − 2.3)²: the minimum sits at 2.3.
        let costs: Vec<u16> = (0..6).map(|d| ((d as f32 - 2.3).powi(2) * 100.0) as u16).collect();
        let mut out = [0.0f32];
        winner_take_all(&costs, 6, 10, Some(SubpixelFit::Parabola), &mut out);
        assert!((out[0] - 12.3).abs() < 0.02, "{}", out[0]);
        winner_take_all(&costs, 6, 10, None, &mut out);
        assert_eq!(out[0], 12.0);
        winner_take_all(&[INVALID_COST; 6], 6, 0, Some(SubpixelFit::Parabola), &mut out);
        assert!(out[0].is_infinite());
    }

    #[test]
    fn each_fit_recovers_the_vertex_of_its_own_shape_and_the_lines_undo_pixel_locking() {
        // Sampled at d − 1, d, d + 1 = −1, 0, 1 around true minima m ∈ [−0.5, 0.5].
        let v = |m: f64| [-1.0, 0.0, 1.0].map(|d: f64| 100.0 * (d - m).abs());
        let q = |m: f64| [-1.0, 0.0, 1.0].map(|d: f64| 100.0 * (d - m).powi(2));
        let (mut locked, mut lines) = (0f64, 0f64);
        for step in -5..=5 {
            let m = f64::from(step) / 10.0;
            let offset = |fit: SubpixelFit, costs| fit.offset(costs).unwrap_or(f64::NAN);
            assert!(
                (offset(SubpixelFit::Parabola, q(m)) - m).abs() < 1e-9,
                "parabola at {m}"
            );
            assert!(
                (offset(SubpixelFit::Equiangular, v(m)) - m).abs() < 1e-9,
                "lines at {m}"
            );
            // A V sampled by a parabola: the vertex is pulled towards the integer.
            let pulled = offset(SubpixelFit::Parabola, v(m));
            assert!(pulled.abs() <= m.abs() + 1e-9, "parabola on a V at {m}: {pulled}");
            locked = locked.max((pulled - m).abs());
            lines = lines.max((offset(SubpixelFit::Equiangular, v(m)) - m).abs());
        }
        assert!(locked > 0.08 && lines < 1e-9, "pixel locking {locked}, lines {lines}");
        // No minimum at the middle sample, flat, or not finite: no vertex.
        for fit in [SubpixelFit::Parabola, SubpixelFit::Equiangular] {
            assert_eq!(fit.offset([1.0, 2.0, 3.0]), None);
            assert_eq!(fit.offset([2.0, 2.0, 2.0]), None);
            assert_eq!(fit.offset([f64::INFINITY, 1.0, 3.0]), None);
            assert_eq!(fit.offset([f64::NAN, 1.0, 3.0]), None);
        }
        // Configuration names.
        for (fit, name) in [
            (SubpixelFit::Parabola, "parabola"),
            (SubpixelFit::Equiangular, "equiangular"),
        ] {
            assert_eq!(serde_json::to_value(fit).ok(), Some(serde_json::json!(name)));
            assert_eq!(
                serde_json::from_value::<SubpixelFit>(serde_json::json!(name)).ok(),
                Some(fit)
            );
        }
        // Through the winner-take-all: a V with its minimum at 2.3.
        let costs: Vec<u16> = (0..6).map(|d| ((d as f32 - 2.3).abs() * 1000.0) as u16).collect();
        let mut out = [0.0f32];
        winner_take_all(&costs, 6, 10, Some(SubpixelFit::Equiangular), &mut out);
        assert!((out[0] - 12.3).abs() < 1e-3, "{}", out[0]);
        winner_take_all(&costs, 6, 10, Some(SubpixelFit::Parabola), &mut out);
        assert!((out[0] - 12.3).abs() > 0.05, "{}", out[0]);
    }
}
