//! Fusion of the per-neighbour costs into one data term (paper, section III-B): mean, min and
//! the heuristic rule. Costs whose correspondence leaves the neighbour image are left out.

use serde::{Deserialize, Serialize};

use crate::cost::INVALID_COST;

/// How the neighbours' costs become one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Fusion {
    /// Two-view stereo: only one neighbour (the `right` view when there is one).
    Stereo,
    /// `c_ave`: the mean of the valid costs.
    Mean,
    /// `c_min`: the smallest cost.
    Min,
    /// `c_heu`: sort, keep the three smallest; if `c³ > 3·c²` average the two smallest, else the
    /// three. With two valid costs it is the minimum; with one, that cost. Views on one side of
    /// the reference along one ray (`[1, 0]` and `[2, 0]` of a line) are hidden by the same
    /// occluders, so they count as one cost: their minimum ([`direction_groups`]); on the paper's
    /// rigs (one view per direction) this changes nothing.
    Heuristic,
}

/// Fuses one value per neighbour.
#[inline]
pub fn fuse_values(fusion: Fusion, values: &[u16]) -> u16 {
    match fusion {
        Fusion::Stereo => values.first().copied().unwrap_or(INVALID_COST),
        Fusion::Min => values.iter().copied().min().unwrap_or(INVALID_COST),
        Fusion::Mean => {
            let (sum, count) = values
                .iter()
                .filter(|v| **v != INVALID_COST)
                .fold((0u32, 0u32), |(s, n), v| (s + u32::from(*v), n + 1));
            (sum + count / 2)
                .checked_div(count)
                .map_or(INVALID_COST, |mean| mean as u16)
        }
        Fusion::Heuristic => {
            let mut smallest = [INVALID_COST; 3];
            for &v in values {
                if v < smallest[2] {
                    if v < smallest[1] {
                        smallest[2] = smallest[1];
                        if v < smallest[0] {
                            smallest[1] = smallest[0];
                            smallest[0] = v;
                        } else {
                            smallest[1] = v;
                        }
                    } else {
                        smallest[2] = v;
                    }
                }
            }
            let [c1, c2, c3] = smallest.map(u32::from);
            if smallest[1] == INVALID_COST || smallest[2] == INVALID_COST {
                // One or two valid costs: the minimum.
                smallest[0]
            } else if c3 > 3 * c2 {
                (c1 + c2).div_ceil(2) as u16
            } else {
                ((c1 + c2 + c3 + 1) / 3) as u16
            }
        }
    }
}

/// The heuristic rule on the three smallest of up to four costs, sorted by a branch-free network,
/// in `u16` arithmetic so that the loop over pixels vectorises on 16 lanes: `c₃ > 3·c₂` with a
/// product that cannot wrap (`c₂ ≤ 21845`; a larger `c₂` has `3·c₂` above every cost), the two-average as the
/// rounding-up mean `(a | b) − ((a ^ b) >> 1)`, the three-average `⌊(s + 1) / 3⌋` by a multiply-high that is exact
/// for s < 2¹⁶. Callers guarantee `3 · max_cost < 2¹⁶` ([`HEURISTIC_U16_MAX_COST`]).
#[inline]
fn heuristic4(a: u16, b: u16, c: u16, d: u16) -> u16 {
    let (s1, s2) = (a.min(b), a.max(b));
    let (s3, s4) = (c.min(d), c.max(d));
    let c1 = s1.min(s3);
    let t1 = s1.max(s3);
    let t2 = s2.min(s4);
    let (c2, c3) = (t1.min(t2), t1.max(t2));
    let two = (c1 | c2) - ((c1 ^ c2) >> 1);
    let sum = c1.wrapping_add(c2).wrapping_add(c3).wrapping_add(1);
    let three = (((u32::from(sum) * 43_691) >> 16) as u16) >> 1;
    let fused = if c2 <= u16::MAX / 3 && c3 > c2.wrapping_mul(3) {
        two
    } else {
        three
    };
    if c2 == INVALID_COST || c3 == INVALID_COST {
        c1
    } else {
        fused
    }
}

/// Largest valid cost for which the four-way heuristic's `u16` arithmetic is exact (three valid costs
/// and the rounding one sum below 2¹⁶).
pub const HEURISTIC_U16_MAX_COST: u16 = 21_844;

/// [`fuse_values`] for the heuristic on up to four costs, in `u32` (any cost).
#[inline]
fn heuristic4_wide(a: u16, b: u16, c: u16, d: u16) -> u16 {
    fuse_values(Fusion::Heuristic, &[a, b, c, d])
}

/// Fuses rows of costs (`rows[k]` = neighbour k, all the same length, valid costs at most
/// `max_cost`) into `out`.
pub fn fuse_rows(fusion: Fusion, rows: &[&[u16]], out: &mut [u16], max_cost: u32) {
    let narrow = max_cost <= u32::from(HEURISTIC_U16_MAX_COST);
    match (fusion, rows) {
        (_, [only]) | (Fusion::Stereo, [only, ..]) => out.copy_from_slice(only),
        (Fusion::Min | Fusion::Heuristic, [a, b]) => {
            for ((o, x), y) in out.iter_mut().zip(a.iter()).zip(b.iter()) {
                *o = (*x).min(*y);
            }
        }
        (Fusion::Min, _) => {
            out.fill(INVALID_COST);
            for row in rows {
                for (o, v) in out.iter_mut().zip(row.iter()) {
                    *o = (*o).min(*v);
                }
            }
        }
        (Fusion::Heuristic, [a, b, c]) if narrow => {
            let n = out.len();
            let (a, b, c) = (&a[..n], &b[..n], &c[..n]);
            for i in 0..n {
                out[i] = heuristic4(a[i], b[i], c[i], INVALID_COST);
            }
        }
        (Fusion::Heuristic, [a, b, c, d]) if narrow => {
            let n = out.len();
            let (a, b, c, d) = (&a[..n], &b[..n], &c[..n], &d[..n]);
            for i in 0..n {
                out[i] = heuristic4(a[i], b[i], c[i], d[i]);
            }
        }
        (Fusion::Heuristic, [a, b, c]) => {
            for (i, o) in out.iter_mut().enumerate() {
                *o = heuristic4_wide(a[i], b[i], c[i], INVALID_COST);
            }
        }
        (Fusion::Mean, _) => {
            for (i, o) in out.iter_mut().enumerate() {
                let (mut sum, mut count) = (0u32, 0u32);
                for row in rows {
                    let v = row[i];
                    let valid = u32::from(v != INVALID_COST);
                    sum += u32::from(v) * valid;
                    count += valid;
                }
                *o = (sum + count / 2)
                    .checked_div(count)
                    .map_or(INVALID_COST, |mean| mean as u16);
            }
        }
        _ => {
            let mut values = Vec::with_capacity(rows.len());
            for (i, o) in out.iter_mut().enumerate() {
                values.clear();
                values.extend(rows.iter().map(|row| row[i]));
                *o = fuse_values(fusion, &values);
            }
        }
    }
}

/// Neighbours grouped by the direction of their offset from the reference (`[2, 0]` joins
/// `[1, 0]`, `[-2, 0]` does not): views on one side of the reference along one ray are hidden
/// from the same occluders, so the occlusion-aware rules (min, heuristic) should count *sides*,
/// not views. Groups keep the neighbours' order (by their first member); each group's members
/// run nearest first.
pub fn direction_groups(offsets: &[[i32; 2]]) -> Vec<Vec<usize>> {
    fn gcd(a: i32, b: i32) -> i32 {
        if b == 0 { a.abs() } else { gcd(b, a % b) }
    }
    let direction = |[x, y]: [i32; 2]| {
        let g = gcd(x, y).max(1);
        [x / g, y / g]
    };
    let mut groups: Vec<([i32; 2], Vec<usize>)> = Vec::new();
    for (i, offset) in offsets.iter().enumerate() {
        let dir = direction(*offset);
        match groups.iter_mut().find(|(d, _)| *d == dir) {
            Some((_, members)) => members.push(i),
            None => groups.push((dir, vec![i])),
        }
    }
    groups
        .into_iter()
        .map(|(_, mut members)| {
            members.sort_by_key(|k| offsets[*k][0].abs() + offsets[*k][1].abs());
            members
        })
        .collect()
}

/// How the views on one side of the reference, along one ray (`[1, 0]`, `[2, 0]` …), become
/// that side's cost. Both are the nearest view's cost where the views agree.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SideRule {
    /// Their minimum, the classical heuristic's: a farther view's match counts wherever the
    /// nearest one misses (reflective parts gain most), and so does its aliased match on a
    /// periodic texture (sampled at `k·d`, it repeats `k` times as often).
    #[default]
    Min,
    /// The mean over the side's views of the smaller of the nearest view's cost and theirs: a
    /// farther view lowers the nearest one's cost (by its share) only where it is lower, never
    /// raises it (occluded farther views do not hurt), and a match that only a farther view
    /// sees counts at most halfway (two views), so its aliases cannot outvote the nearest view.
    NearCapped,
}

/// Fuses the rows of one side's views, nearest first (`rows[k]`, all the same length) into
/// `out` by `rule`. Where the nearest view's cost is invalid, the minimum of the others.
pub fn fuse_side_rows(rule: SideRule, rows: &[&[u16]], out: &mut [u16]) {
    let Some((near, farther)) = rows.split_first() else {
        out.fill(INVALID_COST);
        return;
    };
    out.copy_from_slice(&near[..out.len()]);
    match rule {
        SideRule::Min => {
            for row in farther {
                for (o, v) in out.iter_mut().zip(row.iter()) {
                    *o = (*o).min(*v);
                }
            }
        }
        SideRule::NearCapped => {
            let count = rows.len() as u32;
            for (i, o) in out.iter_mut().enumerate() {
                let n = near[i];
                if n == INVALID_COST {
                    *o = farther.iter().map(|r| r[i]).min().unwrap_or(INVALID_COST);
                } else {
                    let sum: u32 = u32::from(n) + farther.iter().map(|r| u32::from(r[i].min(n))).sum::<u32>();
                    *o = ((sum + count / 2) / count) as u16;
                }
            }
        }
    }
}

/// The heuristic over sides: the minimum of each side's views ([`direction_groups`]), then the
/// paper's rule across the sides. Identical to [`fuse_values`] when no two views share a side
/// (the paper's rigs).
pub fn fuse_heuristic_by_side(values: &[u16], sides: &[Vec<usize>], scratch: &mut Vec<u16>) -> u16 {
    scratch.clear();
    scratch.extend(
        sides
            .iter()
            .map(|members| members.iter().map(|k| values[*k]).min().unwrap_or(INVALID_COST)),
    );
    fuse_values(Fusion::Heuristic, scratch)
}

#[cfg(test)]
mod tests {
    use super::*;

    const X: u16 = INVALID_COST;

    #[test]
    fn heuristic_follows_the_paper() {
        // c3 = 40 > 3·c2 = 30: drop it, average the two smallest.
        assert_eq!(fuse_values(Fusion::Heuristic, &[40, 10, 100, 8]), 9);
        // c3 = 20 ≤ 3·c2 = 30: average the three smallest.
        assert_eq!(fuse_values(Fusion::Heuristic, &[20, 10, 100, 9]), 13);
        // Two neighbours: the minimum.
        assert_eq!(fuse_values(Fusion::Heuristic, &[20, 7]), 7);
        // Invalid costs do not count.
        assert_eq!(fuse_values(Fusion::Heuristic, &[X, 12, X, 30]), 12);
        assert_eq!(fuse_values(Fusion::Heuristic, &[X, X, X, X]), X);
    }

    #[test]
    fn the_sorting_network_agrees_with_the_rule() {
        let mut state = 7u32;
        let mut round = 0u32;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            round += 1;
            // Small costs, and costs up to the largest the u16 arithmetic allows.
            let limit = if round.is_multiple_of(2) {
                300
            } else {
                HEURISTIC_U16_MAX_COST + 1
            };
            let v = (state >> 8) as u16 % (limit + limit / 10);
            if v > limit - 1 { X } else { v }
        };
        for _ in 0..200_000 {
            let values = [next(), next(), next(), next()];
            assert_eq!(
                heuristic4(values[0], values[1], values[2], values[3]),
                fuse_values(Fusion::Heuristic, &values),
                "{values:?}"
            );
            assert_eq!(
                heuristic4(values[0], values[1], values[2], X),
                fuse_values(Fusion::Heuristic, &values[..3]),
                "{values:?}"
            );
        }
    }

    #[test]
    fn mean_and_min_skip_invalid_costs() {
        assert_eq!(fuse_values(Fusion::Mean, &[10, X, 20]), 15);
        // Sides: [1, 0] and [2, 0] share one, [-2, 0], [0, 1] and the diagonal ([1, 1] first, the
        // nearer) have their own.
        let sides = direction_groups(&[[1, 0], [-2, 0], [2, 0], [0, 1], [2, 2], [1, 1]]);
        assert_eq!(sides, vec![vec![0, 2], vec![1], vec![3], vec![5, 4]]);
        let mut scratch = Vec::new();
        // Right side min(50, 8) = 8, left 9, bottom 100, diagonal min(30, 40) = 30: heuristic of
        // 8, 9, 30: 30 > 3·9, so the mean of the two smallest, 8.5 → 9 (over the six views
        // themselves it would be 8, 9, 30 too, but a right side of 8 and 50 now counts once).
        assert_eq!(
            fuse_heuristic_by_side(&[50, 9, 8, 100, 30, 40], &sides, &mut scratch),
            9
        );
        assert_eq!(
            fuse_heuristic_by_side(&[50, 9, 8, 100, 20, 40], &sides, &mut scratch),
            12
        );
        assert_eq!(fuse_values(Fusion::Heuristic, &[50, 9, 8, 100, 20, 40]), 12);
        // Two low costs from one side no longer outvote the others: sides 9, 100, 100, 30 → the
        // mean of 9 and 30 (100 > 3·30) = 19.5 → 20; over the views 9, 10, 30 → 16.
        assert_eq!(
            fuse_heuristic_by_side(&[10, 100, 9, 100, 30, 100], &sides, &mut scratch),
            20
        );
        assert_eq!(fuse_values(Fusion::Heuristic, &[10, 100, 9, 100, 30, 100]), 16);
        let singles = direction_groups(&[[-1, 0], [1, 0], [0, -1], [0, 1]]);
        assert_eq!(
            fuse_heuristic_by_side(&[40, 10, 100, 8], &singles, &mut scratch),
            fuse_values(Fusion::Heuristic, &[40, 10, 100, 8])
        );
        assert_eq!(fuse_values(Fusion::Min, &[10, X, 4]), 4);
        let a = [1u16, X, 9];
        let b = [5u16, 3, X];
        let mut out = [0u16; 3];
        fuse_rows(Fusion::Min, &[&a, &b], &mut out, 100);
        assert_eq!(out, [1, 3, 9]);
        fuse_rows(Fusion::Heuristic, &[&a, &b], &mut out, 100);
        assert_eq!(out, [1, 3, 9]);
        fuse_rows(Fusion::Mean, &[&a, &b], &mut out, 100);
        assert_eq!(out, [3, 3, 9]);
        // Costs too large for the u16 heuristic take the wide path.
        let big = [[60_000u16, 10], [50_000, 11], [40_000, 12], [X, 13]];
        let rows: Vec<&[u16]> = (0..4).map(|k| &big[k][..]).collect();
        let mut fused = [0u16; 2];
        fuse_rows(Fusion::Heuristic, &rows, &mut fused, 60_000);
        assert_eq!(fused, [50_000, 11]);
    }

    #[test]
    fn a_side_s_views_become_one_cost_nearest_first() {
        // Groups run nearest first whatever the neighbours' order.
        assert_eq!(
            direction_groups(&[[2, 0], [-1, 0], [1, 0], [3, 0]]),
            vec![vec![2, 0, 3], vec![1]]
        );
        let near = [10u16, 40, 40, X, 20];
        let far = [30u16, 10, 40, 7, X];
        let mut out = [0u16; 5];
        fuse_side_rows(SideRule::Min, &[&near, &far], &mut out);
        assert_eq!(out, [10, 10, 40, 7, 20]);
        // Near-capped: a farther view lowers the nearest cost halfway where it is lower (40 and
        // 10 → 25), never raises it (10 and 30 → 10; an invalid far cost counts as the near one);
        // without the nearest cost, the farther ones' minimum.
        fuse_side_rows(SideRule::NearCapped, &[&near, &far], &mut out);
        assert_eq!(out, [10, 25, 40, 7, 20]);
        // Three views: the mean of 40, min(40, 10), min(40, 100) = 30.
        let farthest = [100u16; 5];
        fuse_side_rows(SideRule::NearCapped, &[&near, &far, &farthest], &mut out);
        assert_eq!(out[1], 30);
        // An aliased far match (the near view rejects it) ties no longer with the near view's
        // match: 45 against 10.
        let (near, far) = ([10u16, 80], [12u16, 10]);
        let mut side = [0u16; 2];
        fuse_side_rows(SideRule::NearCapped, &[&near, &far], &mut side);
        assert_eq!(side, [10, 45]);
        fuse_side_rows(SideRule::Min, &[&near, &far], &mut side);
        assert_eq!(side, [10, 10]);
    }
}
