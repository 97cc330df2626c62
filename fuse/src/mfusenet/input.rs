//! The network's inputs: one cost volume per neighbour, each aggregated on its own by SGM (the
//! paper fed MC-CNN costs after SGM; we use our census costs, block-summed, after SGM's eight
//! paths), then normalised per pixel and stored as bytes until a tile needs them as floats.
//!
//! Normalisation: `c(x, y, d) = (S(d) − min_d S) / (8 · P2)` with `S` the sum of the eight path
//! costs and `P2` the large-jump penalty in the same units, so that one unit is what eight paths
//! pay for one disparity jump, whatever the image size, cost or block; values are kept in steps
//! of 1/[`STEPS_PER_UNIT`] up to 255 steps (≈ 2 units: farther costs never win, while near the
//! minimum, where the curve rises by about P1/P2 = 0.1 unit per disparity, a step is 1/13 of
//! that rise, enough for sub-pixel positions). Costs whose
//! correspondence leaves the neighbour image enter SGM as its largest cost, so every pixel has a
//! full curve and no value is missing.
//!
//! Context below the range: [`input_volumes_below`] starts the volumes a few disparities under
//! the searched range (negative disparities from each neighbour mirrored), for networks whose
//! weights ask for it (`context_below`); the estimate is read from the searched range only.
//!
//! Order of the volumes (fixed; the weights depend on it): N = 1, the stereo neighbour (`right`
//! when present); N = 2, the two horizontal neighbours (offsets −1 then +1 along x) or, lacking
//! them, the two vertical ones; N = 4, left, right, top, bottom (offsets `[−1, 0]`, `[1, 0]`,
//! `[0, −1]`, `[0, 1]`). Top and bottom costs are computed along the image columns by the same
//! matcher (equivalent to the authors' transposed images, transposed back).

use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::PixelCost;
use crate::fusion::{Fusion, SideRule};
use crate::nn::Tensor;
use crate::sgm::{aggregate_prepared, quantisation_shift, quantise_penalty};
use crate::volume::{CostSpec, CostVolume, Neighbour, PreparedProblem, Problem, VolumeSource};

/// Byte steps per normalised cost unit.
pub const STEPS_PER_UNIT: f32 = 128.0;

/// How the per-neighbour volumes are made.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputSpec {
    /// Per-pixel cost.
    pub cost: PixelCost,
    /// Block radius of the aggregation before SGM.
    #[serde(alias = "block_radius")]
    pub block_radius_px: usize,
    /// SGM penalty for ±1 disparity steps (cost units).
    pub p1: u16,
    /// SGM penalty for larger jumps.
    pub p2: u16,
}

impl Default for InputSpec {
    /// Our SGM's defaults (census 7×7 summed over 7×7, P1 300, P2 3000).
    fn default() -> Self {
        Self {
            cost: PixelCost::Census {
                radius: 3,
                symmetric: false,
            },
            block_radius_px: 3,
            p1: 300,
            p2: 3000,
        }
    }
}

/// The neighbours the network takes, in its fixed order, for a network of `views` inputs. For
/// the view-count-agnostic one (`views` = 0): the neighbours on the axes at the nearest baseline,
/// in the set's order (its nearest group; [`pooled_neighbours`] adds the rest).
pub fn ordered_neighbours(problem: &Problem, views: usize) -> Result<Vec<&Neighbour>, FuseError> {
    let at = |offset: [i32; 2]| problem.neighbours.iter().find(|n| n.offset == offset);
    let on_axis = |n: &&Neighbour| n.on_axis();
    let nearest = problem.neighbours.iter().filter(on_axis).map(Neighbour::reach).min();
    let found: Option<Vec<&Neighbour>> = match views {
        0 => nearest.map(|k| {
            problem
                .neighbours
                .iter()
                .filter(on_axis)
                .filter(|n| n.reach() == k)
                .collect()
        }),
        1 => problem.neighbours_for(Fusion::Stereo).first().map(|n| vec![*n]),
        2 => [[-1, 0], [1, 0]]
            .iter()
            .map(|o| at(*o))
            .collect::<Option<Vec<_>>>()
            .or_else(|| [[0, -1], [0, 1]].iter().map(|o| at(*o)).collect()),
        4 => [[-1, 0], [1, 0], [0, -1], [0, 1]].iter().map(|o| at(*o)).collect(),
        _ => None,
    };
    found.ok_or_else(|| FuseError::Config {
        field: "neighbours",
        value: problem.neighbour_list(),
        reason: match views {
            2 => "the three-view network needs left and right (or top and bottom) at one baseline",
            4 => "the five-view network needs left, right, top and bottom at one baseline",
            0 => "the view-count-agnostic network needs a neighbour along x or y",
            _ => "MFuseNet has variants for 1, 2 and 4 neighbours, and one for any number",
        },
    })
}

/// The view-count-agnostic network's neighbours: those of [`ordered_neighbours`] (the axes at the
/// nearest baseline) first, then, with `every`, the set's other views by reach (a line's ±2
/// after its ±1, a grid's diagonals after its cross), each in the set's order. The first
/// `ordered_neighbours(problem, 0)?.len()` are the nearest group.
pub fn pooled_neighbours(problem: &Problem, every: bool) -> Result<Vec<&Neighbour>, FuseError> {
    let mut out = ordered_neighbours(problem, 0)?;
    if every {
        let mut rest: Vec<&Neighbour> = problem
            .neighbours
            .iter()
            .filter(|n| !out.iter().any(|o| std::ptr::eq(*o, *n)))
            .collect();
        rest.sort_by_key(|n| n.reach());
        out.extend(rest);
    }
    Ok(out)
}

/// One network's part of a set: which variant (by its number of inputs) and the neighbours it
/// takes, in its input order.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewGroup<'a> {
    /// Inputs of the network: 4 (five-view), 2 (three-view) or 1 (stereo).
    pub views: usize,
    /// The neighbours, in the network's order (each once).
    pub neighbours: Vec<&'a Neighbour>,
    /// For each of the network's inputs, the index in `neighbours` of the view that fills it:
    /// `0..views` but for a cross with a missing arm (`fill_cross`), whose empty input takes the
    /// opposite view's volume.
    pub slots: Vec<usize>,
}

impl ViewGroup<'_> {
    /// Whether an input repeats another's view (a cross with a missing arm filled).
    pub fn filled(&self) -> bool {
        self.slots.len() != self.neighbours.len()
    }
}

/// The set's neighbours placed in the networks that take them, nearest baselines first: at each
/// multiple `k` of the baseline, the cross `(±k, 0), (0, ±k)` for the five-view network (when
/// `available`), else its horizontal and vertical opposite pairs for the three-view one; then
/// each view on an axis at the set's nearest baseline that no pair took, alone, for the stereo
/// network (an L of two views: both; a cross missing an arm: the pair and the odd view; on the
/// held-out grids' L subsets 0.30 → 0.16 px, docs/results.md "Irregular sets"). What no group
/// takes is returned apart: a farther view without its opposite (the stereo network on it did not
/// move Middlebury's lines; a single network reads it as a side input) and the diagonal views of
/// a grid (the three-view network on a diagonal pair raised a simulated 3 × 3 grid's AvgErr by
/// 5 %, the five-view one on the turned cross by 8 %; docs/experiments.md). With `line_cross`
/// a line of five on an axis without a cross of its own goes whole to the five-view network:
/// left, right, then the far pair in its top and bottom inputs. With `fill_cross`, a cross
/// missing arms at a baseline that still has a view on each axis (a T of three views, an L of
/// two) goes to the five-view network too, each missing arm's input filled with its opposite
/// view's volume (the same correspondences, without that arm's own occlusions), at the
/// nearest baseline only (farther views without their opposite stay unused, as without it).
pub fn view_groups<'a>(
    problem: &'a Problem,
    available: &[usize],
    line_cross: bool,
    fill_cross: bool,
) -> (Vec<ViewGroup<'a>>, Vec<&'a Neighbour>) {
    let mut left: Vec<&Neighbour> = problem.neighbours.iter().collect();
    let has =
        |left: &Vec<&Neighbour>, offsets: &[[i32; 2]]| offsets.iter().all(|o| left.iter().any(|n| n.offset == *o));
    let reach = problem.neighbours.iter().map(Neighbour::reach).max().unwrap_or(0);
    let mut groups = Vec::new();
    let group = |groups: &mut Vec<ViewGroup<'a>>, views: usize, offsets: &[[i32; 2]], left: &mut Vec<&'a Neighbour>| {
        let neighbours: Vec<&Neighbour> = offsets
            .iter()
            .filter_map(|o| left.iter().position(|n| n.offset == *o).map(|i| left.remove(i)))
            .collect();
        let slots = (0..neighbours.len()).collect();
        groups.push(ViewGroup {
            views,
            neighbours,
            slots,
        });
    };
    // A line of five into the five-view network (`line_cross`): ±1 in its left and right
    // inputs, ±2 in its top and bottom ones, on an axis with no cross of its own.
    if line_cross && available.contains(&4) {
        for line in [[[-1, 0], [1, 0], [-2, 0], [2, 0]], [[0, -1], [0, 1], [0, -2], [0, 2]]] {
            if has(&left, &line) && !has(&left, &[[-1, 0], [1, 0], [0, -1], [0, 1]]) {
                group(&mut groups, 4, &line, &mut left);
            }
        }
    }
    // The nearest baseline with a view on an axis: its odd views, or its cross missing arms.
    let nearest = problem
        .neighbours
        .iter()
        .filter(|n| n.on_axis())
        .map(Neighbour::reach)
        .min();
    for k in 1..=reach {
        let cross = [[-k, 0], [k, 0], [0, -k], [0, k]];
        if available.contains(&4) && has(&left, &cross) {
            group(&mut groups, 4, &cross, &mut left);
        } else if fill_cross
            && nearest == Some(k)
            && available.contains(&4)
            && let Some(filled) = filled_cross(cross, &mut left)
        {
            groups.push(filled);
        }
        if available.contains(&2) {
            for pair in [[[-k, 0], [k, 0]], [[0, -k], [0, k]]] {
                if has(&left, &pair) {
                    group(&mut groups, 2, &pair, &mut left);
                }
            }
        }
    }
    // The odd views at the nearest baseline, each alone.
    if available.contains(&1)
        && let Some(k) = nearest
    {
        let (odd, rest): (Vec<&Neighbour>, Vec<&Neighbour>) =
            left.into_iter().partition(|n| n.on_axis() && n.reach() == k);
        groups.extend(odd.into_iter().map(|n| ViewGroup {
            views: 1,
            neighbours: vec![n],
            slots: vec![0],
        }));
        left = rest;
    }
    (groups, left)
}

/// The five-view group of a cross `cross` (left, right, top, bottom offsets) with missing
/// arms, taken out of `left`: each input its own view, else the opposite one's (`slots`).
/// `None`, and `left` untouched, when an axis has no view.
fn filled_cross<'a>(cross: [[i32; 2]; 4], left: &mut Vec<&'a Neighbour>) -> Option<ViewGroup<'a>> {
    let has = |left: &[&Neighbour], o: [i32; 2]| left.iter().any(|n| n.offset == o);
    if !(0..4).all(|i| has(left, cross[i]) || has(left, cross[i ^ 1])) {
        return None;
    }
    let mut neighbours: Vec<&Neighbour> = Vec::new();
    let mut slots = Vec::with_capacity(4);
    for (i, o) in cross.iter().enumerate() {
        let view = if has(left, *o) || neighbours.iter().any(|n| n.offset == *o) {
            *o
        } else {
            cross[i ^ 1]
        };
        let at = match neighbours.iter().position(|n| n.offset == view) {
            Some(at) => at,
            None => {
                let i = left.iter().position(|n| n.offset == view)?;
                neighbours.push(left.remove(i));
                neighbours.len() - 1
            }
        };
        slots.push(at);
    }
    Some(ViewGroup {
        views: 4,
        neighbours,
        slots,
    })
}

/// The grid offsets of the neighbours whose volumes these are (`None` if one is not a single
/// neighbour's).
pub fn neighbour_offsets<'a>(volumes: impl IntoIterator<Item = &'a CostVolume<u8>>) -> Option<Vec<[i32; 2]>> {
    volumes
        .into_iter()
        .map(|v| match &v.source {
            VolumeSource::Neighbour { offset, .. } => Some(*offset),
            VolumeSource::Fused(_) => None,
        })
        .collect()
}

/// For the mirror image of a set whose neighbours sit at `offsets` (rows flipped if `vertical`,
/// columns if `horizontal`): for each input slot, the slot whose neighbour the mirror puts there
/// (a mirrored camera's offset is mirrored too: left ↔ right in a left-to-right mirror, top ↔
/// bottom in a top-to-bottom one). `None` when the mirror moves a neighbour where the set has
/// none (a single right neighbour mirrored left to right).
pub fn mirror_order(offsets: &[[i32; 2]], vertical: bool, horizontal: bool) -> Option<Vec<usize>> {
    let mirror = |[x, y]: [i32; 2]| [if horizontal { -x } else { x }, if vertical { -y } else { y }];
    offsets
        .iter()
        .map(|&slot| offsets.iter().position(|&o| mirror(o) == slot))
        .collect()
}

/// The mirror `(vertical, horizontal)` that test-time flips use for neighbours at `offsets`:
/// along the axis the first neighbour matches on (left to right for a left/right pair and for
/// the four-view cross, whose volumes swap; top to bottom for a top/bottom pair), or across it
/// when the set has no mirror along it (a single neighbour: top to bottom for a right one).
/// `None` for no neighbours or a set with no mirror on either axis.
pub fn flip_axes(offsets: &[[i32; 2]]) -> Option<(bool, bool)> {
    let along = if offsets.first()?[0] != 0 {
        (false, true)
    } else {
        (true, false)
    };
    [along, (along.1, along.0)]
        .into_iter()
        .find(|&(vertical, horizontal)| mirror_order(offsets, vertical, horizontal).is_some())
}

/// The network's inputs (one `[1, D, H, W]` volume per neighbour at `offsets`) for the mirror
/// image of the set: each volume flipped (rows if `vertical`, columns if `horizontal`) and moved
/// to the slot of its mirrored neighbour ([`mirror_order`]: a mirrored neighbour's matches move
/// the other way, so a mirrored left volume is a right one). `None` when the set has no such
/// mirror. Mirroring twice gives the inputs back. A sharp network's inputs (the views' volumes,
/// then as many sharp volumes: twice `offsets`) move each half alike.
pub fn mirrored(inputs: &[Tensor], offsets: &[[i32; 2]], vertical: bool, horizontal: bool) -> Option<Vec<Tensor>> {
    let n = offsets.len();
    if n == 0 || (inputs.len() != n && inputs.len() != 2 * n) {
        return None;
    }
    let order = mirror_order(offsets, vertical, horizontal)?;
    Some(
        inputs
            .chunks(n)
            .flat_map(|half| order.iter().map(|&i| half[i].flipped(vertical, horizontal)))
            .collect(),
    )
}

/// The number of inputs `mfusenet` uses for a problem: 4 with a full cross of neighbours, 2
/// with an opposite pair, else 1.
pub fn views_for(problem: &Problem) -> usize {
    [4, 2, 1]
        .into_iter()
        .find(|v| ordered_neighbours(problem, *v).is_ok() && problem.neighbours.len() >= *v)
        .unwrap_or(1)
}

/// The normalised per-neighbour volumes (`[y][x][d]` bytes, see the module docs) of `neighbours`.
pub fn input_volumes(
    problem: &Problem,
    neighbours: &[&Neighbour],
    spec: InputSpec,
    on_band: &(dyn Fn() + Sync),
) -> Result<Vec<CostVolume<u8>>, FuseError> {
    let sides: Vec<Vec<&Neighbour>> = neighbours.iter().map(|n| vec![*n]).collect();
    input_volumes_of_sides(problem, &sides, SideRule::Min, spec, on_band)
}

/// [`input_volumes`] with each input made of several views: their costs made one by `rule` (one
/// side of the reference: views along one ray share their occlusions), then SGM.
pub fn input_volumes_of_sides(
    problem: &Problem,
    sides: &[Vec<&Neighbour>],
    rule: SideRule,
    spec: InputSpec,
    on_band: &(dyn Fn() + Sync),
) -> Result<Vec<CostVolume<u8>>, FuseError> {
    let mut out = Vec::with_capacity(sides.len());
    for_each_aggregated(problem, sides, rule, spec, on_band, |sums, p2| {
        out.push(normalise(sums, p2))
    })?;
    Ok(out)
}

/// Each of `neighbours` with the set's views farther along its ray (offsets `k ·` its offset,
/// `k` ≥ 2), nearest first: the views [`input_volumes_of_sides`] makes one input of.
pub fn sides_of<'a>(problem: &'a Problem, neighbours: &[&'a Neighbour]) -> Vec<Vec<&'a Neighbour>> {
    neighbours
        .iter()
        .map(|n| {
            let [dx, dy] = n.offset;
            let mut side: Vec<(i32, &Neighbour)> = problem
                .neighbours
                .iter()
                .filter_map(|m| {
                    let k = if dx != 0 {
                        m.offset[0] / dx
                    } else if dy != 0 {
                        m.offset[1] / dy
                    } else {
                        0
                    };
                    (k >= 1 && m.offset == [k * dx, k * dy]).then_some((k, m))
                })
                .collect();
            side.sort_by_key(|(k, _)| *k);
            side.into_iter().map(|(_, m)| m).collect()
        })
        .collect()
}

/// Each side's cost volume (its views' costs made one by `rule`; a side of one view: its costs)
/// aggregated by SGM on its own, handed to `each` with the quantised large-jump penalty, one
/// side at a time. The costs are made where SGM's passes read them ([`aggregate_prepared`]: no
/// byte volume, 265 MB at 1080p and 132 disparities), and every side's sums share one buffer.
fn for_each_aggregated(
    problem: &Problem,
    sides: &[Vec<&Neighbour>],
    rule: SideRule,
    spec: InputSpec,
    on_band: &(dyn Fn() + Sync),
    mut each: impl FnMut(&CostVolume<u16>, u16),
) -> Result<(), FuseError> {
    let cost = CostSpec {
        pixel: spec.cost,
        block_radius_px: spec.block_radius_px,
    };
    let shift = quantisation_shift(cost.max_cost());
    let (p1, p2) = (quantise_penalty(spec.p1, shift), quantise_penalty(spec.p2, shift));
    let mut buffer = Vec::new();
    for side in sides {
        let Some(n) = side.first() else { continue };
        // The heuristic over one side is its side rule.
        let prepared =
            PreparedProblem::new(&side_problem(problem, side), cost, Fusion::Heuristic)?.with_side_rule(rule);
        let mut sums = aggregate_prepared(&prepared, shift, (p1, p2), buffer, on_band);
        sums.source = VolumeSource::Neighbour {
            role: n.role.clone(),
            offset: n.offset,
        };
        each(&sums, p2);
        buffer = sums.data;
    }
    Ok(())
}

/// `problem` with `side`'s views as its only neighbours: one input's costs.
fn side_problem(problem: &Problem, side: &[&Neighbour]) -> Problem {
    Problem {
        reference: problem.reference.clone(),
        neighbours: side.iter().map(|m| (*m).clone()).collect(),
        min_disparity: problem.min_disparity,
        num_disparities: problem.num_disparities,
    }
}

/// `problem` with its range started `below` disparities lower.
fn with_context_below(problem: &Problem, below: usize) -> Problem {
    let below_i32 = i32::try_from(below).unwrap_or(i32::MAX);
    Problem {
        min_disparity: problem.min_disparity.saturating_sub(below_i32),
        num_disparities: problem.num_disparities + below,
        ..problem.clone()
    }
}

/// [`input_volumes`] over a range that starts `below` disparities under the problem's: the
/// networks answer badly when the truth lies in the first slices of their range (Middlebury's
/// far backgrounds at 1–2 px searched from 0: Bowling1), so inference gives them room. The
/// extended range may reach under 0 (signed num_disparities: the costs of `−d` towards offset `o`
/// are those of `d` towards `−o`); SGM aggregates each neighbour over the whole extended range.
/// Returns the volumes and the disparity of their first slice.
pub fn input_volumes_below(
    problem: &Problem,
    neighbours: &[&Neighbour],
    spec: InputSpec,
    below: usize,
    on_band: &(dyn Fn() + Sync),
) -> Result<(Vec<CostVolume<u8>>, i64), FuseError> {
    let sides: Vec<Vec<&Neighbour>> = neighbours.iter().map(|n| vec![*n]).collect();
    input_volumes_of_sides_below(problem, &sides, SideRule::Min, spec, below, on_band)
}

/// [`input_volumes_below`] of [`input_volumes_of_sides`].
pub fn input_volumes_of_sides_below(
    problem: &Problem,
    sides: &[Vec<&Neighbour>],
    rule: SideRule,
    spec: InputSpec,
    below: usize,
    on_band: &(dyn Fn() + Sync),
) -> Result<(Vec<CostVolume<u8>>, i64), FuseError> {
    let extended = with_context_below(problem, below);
    let volumes = input_volumes_of_sides(&extended, sides, rule, spec, on_band)?;
    Ok((volumes, i64::from(extended.min_disparity)))
}

/// How the sharp volumes of a network with [`crate::mfusenet::Network::sharp`] are made: each
/// side's per-pixel costs (no block sums, no SGM: what still shows a 1–6 px part, or the gap
/// between two), normalised per pixel like the inputs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SharpSpec {
    /// Per-pixel cost.
    pub cost: PixelCost,
    /// Cost units of one network unit: a voxel holds `(C − min_d C) / unit` in steps of
    /// 1/[`STEPS_PER_UNIT`], capped at 255 steps (two units).
    pub unit: f32,
}

impl Default for SharpSpec {
    /// Birchfield–Tomasi on colour (what graph cuts and the thin-part recovery read), 32 cost
    /// levels a unit (the colour cost sums the channels' halves: about 21 grey levels of their
    /// mean): differences up to 64 cost levels are kept.
    fn default() -> Self {
        Self {
            cost: PixelCost::BirchfieldTomasi,
            unit: 32.0,
        }
    }
}

/// The sharp volumes of `sides` (one per side, each its views' per-pixel costs made one by
/// `rule`) over the range of [`input_volumes_of_sides_below`] with `below` disparities of
/// context, the same shape and first disparity as its volumes: `(C − min_d C) / spec.unit` per
/// pixel in steps of 1/[`STEPS_PER_UNIT`], capped at 255 steps; correspondences that leave a
/// neighbour's image cost the most.
pub fn sharp_volumes_of_sides_below(
    problem: &Problem,
    sides: &[Vec<&Neighbour>],
    rule: SideRule,
    spec: SharpSpec,
    below: usize,
) -> Result<(Vec<CostVolume<u8>>, i64), FuseError> {
    use rayon::prelude::*;
    let extended = with_context_below(problem, below);
    let cost = CostSpec {
        pixel: spec.cost,
        block_radius_px: 0,
    };
    let shift = quantisation_shift(cost.max_cost());
    let scale = STEPS_PER_UNIT * (1u32 << shift) as f32 / spec.unit.max(f32::MIN_POSITIVE);
    let mut out = Vec::with_capacity(sides.len());
    for side in sides {
        let Some(n) = side.first() else { continue };
        let prepared =
            PreparedProblem::new(&side_problem(&extended, side), cost, Fusion::Heuristic)?.with_side_rule(rule);
        let mut volume = prepared.fused_volume(shift, &|| {});
        let nd = volume.num_disparities.max(1);
        volume.data.par_chunks_mut(nd).for_each(|pixel| {
            let min = pixel.iter().copied().min().unwrap_or(0);
            for c in pixel.iter_mut() {
                *c = (f32::from(*c - min) * scale).round().min(255.0) as u8;
            }
        });
        volume.max_cost = 255;
        volume.source = VolumeSource::Neighbour {
            role: n.role.clone(),
            offset: n.offset,
        };
        out.push(volume);
    }
    Ok((out, i64::from(extended.min_disparity)))
}

/// `(S − min_d S) / (8 · P2)` in steps of 1/[`STEPS_PER_UNIT`], capped at 255 steps.
pub fn normalise(sums: &CostVolume<u16>, p2: u16) -> CostVolume<u8> {
    let mut data = vec![0u8; sums.data.len()];
    normalise_each(sums, p2, &mut data, |out, step| *out = step);
    sums.with_data(data, 255)
}

/// [`normalise`]'s steps of each voxel of `sums` handed to `put` with the voxel's place in `out`.
fn normalise_each<T: Send>(sums: &CostVolume<u16>, p2: u16, out: &mut [T], put: impl Fn(&mut T, u8) + Sync) {
    use rayon::prelude::*;
    let scale = STEPS_PER_UNIT / (8.0 * f32::from(p2.max(1)));
    let nd = sums.num_disparities.max(1);
    // Rows of pixels in parallel: the volume is hundreds of MB at full size.
    let row = nd * sums.width.max(1);
    out.par_chunks_mut(row)
        .zip(sums.data.par_chunks(row))
        .for_each(|(out, sums)| {
            for (out, pixel) in out.chunks_exact_mut(nd).zip(sums.chunks_exact(nd)) {
                let min = pixel.iter().copied().min().unwrap_or(0);
                for (o, s) in out.iter_mut().zip(pixel) {
                    put(o, (f32::from(s - min) * scale).round().min(255.0) as u8);
                }
            }
        });
}

/// The sum over `volumes` of their costs, voxel by voxel (what the post-processing reads: the
/// set's costs, not each neighbour's), in one volume of `volumes[0]`'s shape; `None` without
/// volumes or when their shapes differ.
pub fn summed(volumes: &[CostVolume<u8>]) -> Option<CostVolume<u16>> {
    use rayon::prelude::*;
    let first = volumes.first()?;
    if volumes.iter().any(|v| v.shape() != first.shape()) {
        return None;
    }
    let mut data = vec![0u16; first.data.len()];
    let chunk = first.num_disparities.max(1) * first.width.max(1);
    data.par_chunks_mut(chunk).enumerate().for_each(|(i, out)| {
        let range = i * chunk..i * chunk + out.len();
        for v in volumes {
            for (o, c) in out.iter_mut().zip(&v.data[range.clone()]) {
                *o += u16::from(*c);
            }
        }
    });
    let max_cost = volumes.iter().map(|v| v.max_cost).sum();
    let mut sum = first.with_data(data, max_cost);
    // The sum is the neighbours' mean times their count.
    sum.source = VolumeSource::Fused(Fusion::Mean);
    Some(sum)
}

/// The sum over `sides` of their normalised volumes ([`input_volumes_of_sides_below`], `below`
/// disparities of context), made one side at a time, so that only one side's SGM sums and the
/// total are held at once instead of every side's bytes: the full-size costs of coarse to fine.
/// The same numbers as [`summed`] of [`input_volumes_of_sides_below`]'s volumes.
pub fn summed_input_volume_below(
    problem: &Problem,
    sides: &[Vec<&Neighbour>],
    rule: SideRule,
    spec: InputSpec,
    below: usize,
) -> Result<(CostVolume<u16>, i64), FuseError> {
    let extended = with_context_below(problem, below);
    let mut total: Option<CostVolume<u16>> = None;
    for_each_aggregated(&extended, sides, rule, spec, &|| {}, |sums, p2| {
        let total = total.get_or_insert_with(|| {
            let mut t = sums.with_data(vec![0u16; sums.data.len()], 0);
            t.source = VolumeSource::Fused(Fusion::Mean);
            t
        });
        normalise_each(sums, p2, &mut total.data, |o, step| *o += u16::from(step));
        total.max_cost += 255;
    })?;
    let total = total.ok_or(FuseError::Config {
        field: "neighbours",
        value: "0".into(),
        reason: "the network's inputs need at least one neighbour",
    })?;
    Ok((total, i64::from(extended.min_disparity)))
}

/// The network's input tensor `[1, depth, rows, columns]` of a window of `volume` whose top-left
/// pixel is `(y0, x0)`: costs in units of [`STEPS_PER_UNIT`], pixels past the volume's edge
/// repeating its last row or column and slices past its last repeating that slice (the padding
/// to multiples of 4). The one conversion from a volume to the network's numbers, for
/// inference's tiles and training's crops.
pub fn to_tensor(
    volume: &CostVolume<u8>,
    (y0, x0): (usize, usize),
    (rows, columns): (usize, usize),
    depth: usize,
) -> Tensor {
    let [h, w, nd] = volume.shape();
    let mut t = Tensor::zeros([1, depth, rows, columns]);
    if h == 0 || w == 0 || nd == 0 {
        return t;
    }
    // A row's pixels in chunks whose costs stay in L1, each slice written as a run of columns:
    // the tensor is slice-major and the volume pixel-major, so one side is always strided.
    const CHUNK: usize = 64;
    let plane = rows * columns;
    let scale = 1.0 / STEPS_PER_UNIT; // a power of two: the same numbers as a division
    for yy in 0..rows {
        let y = (y0 + yy).min(h - 1);
        let row = &volume.data[y * w * nd..(y + 1) * w * nd];
        for xs in (0..columns).step_by(CHUNK) {
            let xe = (xs + CHUNK).min(columns);
            for d in 0..depth {
                let dd = d.min(nd - 1);
                let at = d * plane + yy * columns;
                for (xx, o) in (xs..xe).zip(&mut t.data[at + xs..at + xe]) {
                    let x = (x0 + xx).min(w - 1);
                    *o = f32::from(row[x * nd + dd]) * scale;
                }
            }
        }
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tensor_holds_each_pixels_costs_slice_by_slice_with_the_edges_repeated() {
        let volume = CostVolume::from_fn([70, 9, 5], 0, ("right", [1, 0]), |x, y, d| {
            ((x * 7 + y * 13 + d * 29) % 251) as u8
        });
        // Past the right and bottom edges, and 8 slices for the volume's 5: every clamp.
        let (y0, x0, rows, columns, depth) = (3, 5, 8, 69, 8);
        let t = to_tensor(&volume, (y0, x0), (rows, columns), depth);
        assert_eq!(t.shape, [1, depth, rows, columns]);
        for d in 0..depth {
            for yy in 0..rows {
                for xx in 0..columns {
                    let c = volume.costs((x0 + xx).min(69), (y0 + yy).min(8))[d.min(4)];
                    assert_eq!(
                        t.data[(d * rows + yy) * columns + xx],
                        f32::from(c) / STEPS_PER_UNIT,
                        "{d} {yy} {xx}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_side_holds_the_views_along_its_ray_nearest_first() {
        let image = Image::gray(4, 4, vec![0; 16]).unwrap_or_else(|e| panic!("{e}"));
        let neighbour = |offset: [i32; 2]| Neighbour {
            role: format!("{offset:?}"),
            image: image.clone(),
            offset,
            baseline_ratio: 1.0,
        };
        let problem = Problem {
            reference: image.clone(),
            neighbours: [[2, 0], [-1, 0], [1, 0], [-2, 0], [1, 1], [3, 0], [0, -1], [2, 1]]
                .into_iter()
                .map(neighbour)
                .collect(),
            min_disparity: 0,
            num_disparities: 8,
        };
        let nearest: Vec<&Neighbour> = problem.neighbours[1..3]
            .iter()
            .chain(&problem.neighbours[6..7])
            .collect();
        let offsets: Vec<Vec<[i32; 2]>> = sides_of(&problem, &nearest)
            .iter()
            .map(|side| side.iter().map(|n| n.offset).collect())
            .collect();
        assert_eq!(
            offsets,
            vec![vec![[-1, 0], [-2, 0]], vec![[1, 0], [2, 0], [3, 0]], vec![[0, -1]]]
        );
    }

    #[test]
    fn every_cross_and_opposite_pair_goes_to_its_network_nearest_first() {
        let image = Image {
            width: 4,
            height: 4,
            channels: 1,
            data: vec![0; 16],
        };
        let problem = |offsets: &[[i32; 2]]| Problem {
            reference: image.clone(),
            neighbours: offsets
                .iter()
                .map(|o| Neighbour {
                    role: format!("{o:?}"),
                    image: image.clone(),
                    offset: *o,
                    baseline_ratio: 1.0,
                })
                .collect(),
            min_disparity: 0,
            num_disparities: 4,
        };
        let groups = |offsets: &[[i32; 2]], available: &[usize]| {
            let p = problem(offsets);
            let (groups, rest) = view_groups(&p, available, false, false);
            (
                groups
                    .iter()
                    .map(|g| (g.views, g.neighbours.iter().map(|n| n.offset).collect::<Vec<_>>()))
                    .collect::<Vec<_>>(),
                rest.iter().map(|n| n.offset).collect::<Vec<_>>(),
            )
        };
        // The view-count-agnostic network: the nearest baseline's neighbours on the axes.
        let pooled = |offsets: &[[i32; 2]]| {
            let p = problem(offsets);
            ordered_neighbours(&p, 0)
                .map(|n| n.iter().map(|n| n.offset).collect::<Vec<_>>())
                .ok()
        };
        assert_eq!(pooled(&[[2, 0], [-1, 0], [1, 0], [-2, 0]]), Some(vec![[-1, 0], [1, 0]]));
        assert_eq!(pooled(&[[2, 0], [0, 2]]), Some(vec![[2, 0], [0, 2]]));
        assert_eq!(pooled(&[[1, 1], [0, -1]]), Some(vec![[0, -1]]));
        assert_eq!(pooled(&[[1, 1]]), None);
        // With every view: the nearest group first, then the rest by reach.
        let every = |offsets: &[[i32; 2]]| {
            let p = problem(offsets);
            pooled_neighbours(&p, true)
                .map(|n| n.iter().map(|n| n.offset).collect::<Vec<_>>())
                .ok()
        };
        assert_eq!(
            every(&[[2, 0], [-1, 0], [1, 1], [1, 0], [-2, 0]]),
            Some(vec![[-1, 0], [1, 0], [1, 1], [2, 0], [-2, 0]])
        );
        assert_eq!(every(&[[1, 1]]), None);
        // A line of five: the near pair, then the far one.
        let line = [[2, 0], [-1, 0], [1, 0], [-2, 0]];
        assert_eq!(
            groups(&line, &[1, 2, 4]),
            (vec![(2, vec![[-1, 0], [1, 0]]), (2, vec![[-2, 0], [2, 0]])], vec![])
        );
        // … or, with `line_cross`, all four in the five-view network, the far pair as its top
        // and bottom inputs; a set with a cross keeps its crosses.
        let p = problem(&line);
        let (crossed, rest) = view_groups(&p, &[1, 2, 4], true, false);
        let crossed: Vec<_> = crossed
            .iter()
            .map(|g| (g.views, g.neighbours.iter().map(|n| n.offset).collect::<Vec<_>>()))
            .collect();
        assert_eq!(
            (crossed, rest.len()),
            (vec![(4, vec![[-1, 0], [1, 0], [-2, 0], [2, 0]])], 0)
        );
        let p = problem(&[[-1, 0], [1, 0], [0, -1], [0, 1], [-2, 0], [2, 0]]);
        assert_eq!(
            view_groups(&p, &[1, 2, 4], true, false),
            view_groups(&p, &[1, 2, 4], false, false)
        );
        // A 3 × 3 grid: the cross in the five-view network's order; the diagonals unused.
        let grid = [[-1, -1], [0, -1], [1, -1], [1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0]];
        assert_eq!(
            groups(&grid, &[1, 2, 4]),
            (
                vec![(4, vec![[-1, 0], [1, 0], [0, -1], [0, 1]])],
                vec![[-1, -1], [1, -1], [1, 1], [-1, 1]]
            )
        );
        // With `fill_cross`, an L and a T at the nearest baseline go to the five-view network,
        // each missing arm's input filled by the opposite view; a diagonal stays unused, and a
        // set with one axis only keeps its pair or its single view.
        let filled = |offsets: &[[i32; 2]]| {
            let p = problem(offsets);
            let (groups, rest) = view_groups(&p, &[1, 2, 4], false, true);
            (
                groups
                    .iter()
                    .map(|g| {
                        let inputs: Vec<[i32; 2]> = g.slots.iter().map(|&s| g.neighbours[s].offset).collect();
                        (g.views, inputs, g.filled())
                    })
                    .collect::<Vec<_>>(),
                rest.iter().map(|n| n.offset).collect::<Vec<_>>(),
            )
        };
        assert_eq!(
            filled(&[[0, -1], [-1, 0]]),
            (vec![(4, vec![[-1, 0], [-1, 0], [0, -1], [0, -1]], true)], vec![])
        );
        assert_eq!(
            filled(&[[-1, 0], [1, 0], [0, -1], [1, -1]]),
            (vec![(4, vec![[-1, 0], [1, 0], [0, -1], [0, -1]], true)], vec![[1, -1]])
        );
        assert_eq!(
            filled(&[[0, 1], [1, 0], [0, -1], [2, 0]]),
            (vec![(4, vec![[1, 0], [1, 0], [0, -1], [0, 1]], true)], vec![[2, 0]])
        );
        assert_eq!(
            filled(&[[-1, 0], [1, 0]]),
            (vec![(2, vec![[-1, 0], [1, 0]], false)], vec![])
        );
        assert_eq!(
            filled(&[[1, 1], [1, 0]]),
            (vec![(1, vec![[1, 0]], false)], vec![[1, 1]])
        );
        assert_eq!(
            filled(&[[-1, 0], [1, 0], [0, -1], [0, 1]]),
            (vec![(4, vec![[-1, 0], [1, 0], [0, -1], [0, 1]], false)], vec![])
        );
        // Only at the nearest baseline: a far L beside a near pair stays unused.
        assert_eq!(
            filled(&[[-1, 0], [1, 0], [2, 0], [0, 2]]),
            (vec![(2, vec![[-1, 0], [1, 0]], false)], vec![[2, 0], [0, 2]])
        );
        // An L, a cross missing an arm: the odd views at the nearest baseline alone.
        assert_eq!(
            groups(&[[0, -1], [-1, 0]], &[1, 2, 4]),
            (vec![(1, vec![[0, -1]]), (1, vec![[-1, 0]])], vec![])
        );
        assert_eq!(
            groups(&[[-1, 0], [1, 0], [0, -1], [1, -1]], &[1, 2, 4]),
            (vec![(2, vec![[-1, 0], [1, 0]]), (1, vec![[0, -1]])], vec![[1, -1]])
        );
        // A line from one end: its nearest view alone, the farther one left for its side.
        assert_eq!(
            groups(&[[1, 0], [2, 0]], &[1, 2, 4]),
            (vec![(1, vec![[1, 0]])], vec![[2, 0]])
        );
        // Crosses at two baselines.
        let crosses = [[-1, 0], [1, 0], [0, -1], [0, 1], [-2, 0], [2, 0], [0, -2], [0, 2]];
        assert_eq!(
            groups(&crosses, &[1, 2, 4]),
            (
                vec![
                    (4, vec![[-1, 0], [1, 0], [0, -1], [0, 1]]),
                    (4, vec![[-2, 0], [2, 0], [0, -2], [0, 2]])
                ],
                vec![]
            )
        );
        // Without the five-view network the cross is two pairs.
        assert_eq!(groups(&grid[..0], &[2]), (vec![], vec![]));
        let cross = [[-1, 0], [1, 0], [0, -1], [0, 1]];
        assert_eq!(
            groups(&cross, &[2]),
            (vec![(2, vec![[-1, 0], [1, 0]]), (2, vec![[0, -1], [0, 1]])], vec![])
        );
        // Middlebury's line from view1: the farther views have no opposite.
        assert_eq!(
            groups(&[[-1, 0], [1, 0], [2, 0], [3, 0]], &[1, 2, 4]),
            (vec![(2, vec![[-1, 0], [1, 0]])], vec![[2, 0], [3, 0]])
        );
    }
    use crate::image::Image;

    /// A textured fronto-parallel plane at (signed) disparity `d` seen from the left and right.
    fn plane(d: i64, min_disparity: i32, num_disparities: usize) -> Problem {
        let view = |shift: i64| crate::image::textured_view(64, 32, shift);
        let neighbour = |role: &str, offset: i32| Neighbour {
            role: role.into(),
            image: view(i64::from(offset) * d),
            offset: [offset, 0],
            baseline_ratio: 1.0,
        };
        Problem {
            reference: view(0),
            neighbours: vec![neighbour("left", -1), neighbour("right", 1)],
            min_disparity,
            num_disparities,
        }
    }

    /// The same plane seen from the top and bottom (the views transposed).
    fn vertical(problem: &Problem) -> Problem {
        let transpose = |image: &Image| {
            let (w, h) = (image.width, image.height);
            let data = (0..w)
                .flat_map(|x| (0..h).map(move |y| image.data[y * w + x]))
                .collect();
            Image::gray(h, w, data).unwrap_or_else(|e| panic!("{e}"))
        };
        Problem {
            reference: transpose(&problem.reference),
            neighbours: problem
                .neighbours
                .iter()
                .map(|n| Neighbour {
                    role: if n.offset[0] < 0 { "top" } else { "bottom" }.into(),
                    image: transpose(&n.image),
                    offset: [0, n.offset[0]],
                    baseline_ratio: 1.0,
                })
                .collect(),
            ..problem.clone()
        }
    }

    /// A step (disparity 3 on the left half, 6 on the right, with the occlusions that go with
    /// it) seen from neighbours at `offsets`, the world mirrored in `x` and/or `y` if asked: the
    /// neighbour at offset `o` of the mirrored rig sees the mirror image of what the neighbour at
    /// the mirrored offset saw.
    fn step(offsets: &[[i32; 2]], mirror_x: bool, mirror_y: bool) -> (Problem, Vec<f32>) {
        let (w, h) = (48usize, 24usize);
        let d = |x: usize| if x < w / 2 { 3i64 } else { 6 };
        let texture = |x: i64, y: i64| (((x * 37 + y * 11) ^ (x * y)) % 97 * 2 + 20) as u8;
        let (sx, sy) = (
            move |x: usize| if mirror_x { w - 1 - x } else { x },
            move |y: usize| if mirror_y { h - 1 - y } else { y },
        );
        let view = |[ox, oy]: [i32; 2]| {
            // The unmirrored camera this one is the mirror image of.
            let (ox, oy) = (
                i64::from(if mirror_x { -ox } else { ox }),
                i64::from(if mirror_y { -oy } else { oy }),
            );
            let data = (0..h)
                .flat_map(|y| {
                    (0..w).map(move |x| {
                        let (x, y) = (sx(x), sy(y));
                        texture(x as i64 + ox * d(x), y as i64 + oy * d(x))
                    })
                })
                .collect();
            Image::gray(w, h, data).unwrap_or_else(|e| panic!("{e}"))
        };
        let truth = (0..h).flat_map(|_| (0..w).map(move |x| d(sx(x)) as f32)).collect();
        let problem = Problem {
            reference: view([0, 0]),
            neighbours: offsets
                .iter()
                .map(|&offset| Neighbour {
                    role: format!("{offset:?}"),
                    image: view(offset),
                    offset,
                    baseline_ratio: 1.0,
                })
                .collect(),
            min_disparity: 0,
            num_disparities: 12,
        };
        (problem, truth)
    }

    #[test]
    fn a_mirrored_rig_sees_the_flipped_example() {
        use crate::mfusenet::train::{crop, flipped};
        let example = |(problem, truth): (Problem, Vec<f32>)| {
            let neighbours: Vec<&Neighbour> = problem.neighbours.iter().collect();
            let volumes =
                input_volumes(&problem, &neighbours, InputSpec::default(), &|| {}).unwrap_or_else(|e| panic!("{e}"));
            let refs: Vec<&CostVolume<u8>> = volumes.iter().collect();
            assert_eq!(
                neighbour_offsets(refs.iter().copied()),
                Some(problem.neighbours.iter().map(|n| n.offset).collect())
            );
            let (w, h) = (problem.reference.width, problem.reference.height);
            crop(&refs, &truth, (0, 0), (h, w), 12)
        };
        let (right, left, top, bottom) = ([1, 0], [-1, 0], [0, -1], [0, 1]);
        let rigs: [&[[i32; 2]]; 4] = [&[right], &[left, right], &[top, bottom], &[left, right, top, bottom]];
        for offsets in rigs {
            let original = example(step(offsets, false, false));
            for (mirror_x, mirror_y) in [(true, false), (false, true), (true, true)] {
                let Some(flipped) = flipped(&original, offsets, mirror_y, mirror_x) else {
                    // Only a single right neighbour has no left-to-right mirror.
                    assert!(
                        offsets.len() == 1 && mirror_x,
                        "{offsets:?}: no mirror {mirror_x} {mirror_y}"
                    );
                    continue;
                };
                let mirrored = example(step(offsets, mirror_x, mirror_y));
                assert!(mirrored != original, "{offsets:?}: the step is symmetric");
                assert_eq!(flipped, mirrored, "{offsets:?}: mirror x {mirror_x}, y {mirror_y}");
            }
        }
    }

    fn volumes_below(problem: &Problem, below: usize) -> (Vec<CostVolume<u8>>, i64) {
        let neighbours: Vec<&Neighbour> = problem.neighbours.iter().collect();
        input_volumes_below(problem, &neighbours, InputSpec::default(), below, &|| {}).unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn the_summed_volume_of_sides_is_the_sum_of_their_volumes() {
        // A line of three views at 1, 2 and −1 baselines: the right side holds two.
        let mut problem = plane(3, 0, 16);
        problem.neighbours.push(Neighbour {
            role: "right2".into(),
            image: crate::image::textured_view(64, 32, 6),
            offset: [2, 0],
            baseline_ratio: 1.0,
        });
        let nearest: Vec<&Neighbour> = problem.neighbours[..2].iter().collect();
        let sides = sides_of(&problem, &nearest);
        assert_eq!(sides.iter().map(Vec::len).collect::<Vec<_>>(), [1, 2]);
        let (total, first) = summed_input_volume_below(&problem, &sides, SideRule::Min, InputSpec::default(), 4)
            .unwrap_or_else(|e| panic!("{e}"));
        let (volumes, expected_first) =
            input_volumes_of_sides_below(&problem, &sides, SideRule::Min, InputSpec::default(), 4, &|| {})
                .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(first, expected_first);
        let expected = summed(&volumes).unwrap_or_else(|| panic!("two volumes of one shape"));
        assert!(total.data == expected.data && total.max_cost == expected.max_cost);
        // The side of two is not the near view alone.
        let alone = volumes_below(&problem, 4).0;
        assert!(volumes[1] != alone[1]);
    }

    #[test]
    fn sharp_volumes_lie_beside_the_inputs_with_their_minimum_at_the_plane() {
        // The same shape and first slice as the inputs, each neighbour's own; every pixel's
        // minimum is 0, and a textured plane's lies at its disparity.
        let problem = plane(3, 0, 12);
        let neighbours: Vec<&Neighbour> = problem.neighbours.iter().collect();
        let sides: Vec<Vec<&Neighbour>> = neighbours.iter().map(|n| vec![*n]).collect();
        let (inputs, first) = volumes_below(&problem, 4);
        let (sharp, sharp_first) =
            sharp_volumes_of_sides_below(&problem, &sides, SideRule::Min, SharpSpec::default(), 4)
                .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(sharp_first, first);
        for (s, i) in sharp.iter().zip(&inputs) {
            assert_eq!((s.shape(), &s.source), (i.shape(), &i.source));
            // The plane at 3, four slices of context: slice 7.
            let (mut right, mut total) = (0, 0);
            for y in 2..s.height - 2 {
                for x in 12..s.width - 12 {
                    let costs = s.costs(x, y);
                    assert_eq!(costs.iter().min(), Some(&0));
                    right += usize::from(costs[7] == 0);
                    total += 1;
                }
            }
            assert!(right * 100 >= total * 95, "{:?}: {right} of {total}", s.source);
        }
    }

    #[test]
    fn room_above_zero_is_the_wider_range() {
        let problem = plane(9, 8, 16);
        let (volumes, first) = volumes_below(&problem, 4);
        assert_eq!(first, 4);
        let wider = Problem {
            min_disparity: 4,
            num_disparities: 20,
            ..problem.clone()
        };
        let neighbours: Vec<&Neighbour> = wider.neighbours.iter().collect();
        let expected =
            input_volumes(&wider, &neighbours, InputSpec::default(), &|| {}).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(volumes, expected);
    }

    #[test]
    fn room_under_zero_finds_negative_disparities_in_both_directions() {
        // Searched from 0 with 4 below: slices are −4 … 11, the plane at −2 is slice 2.
        for (d, slice) in [(-2i64, 2usize), (0, 4), (3, 7)] {
            let (mut volumes, first) = volumes_below(&plane(d, 0, 12), 4);
            assert_eq!(first, -4);
            volumes.extend(volumes_below(&vertical(&plane(d, 0, 12)), 4).0);
            for v in &volumes {
                assert_eq!((v.num_disparities, v.min_disparity), (16, -4));
                let (mut right, mut total) = (0, 0);
                let (mx, my) = if v.width > v.height { (12, 4) } else { (4, 12) };
                for y in my..v.height - my {
                    for x in mx..v.width - mx {
                        let costs = v.costs(x, y);
                        let best = (0..costs.len()).min_by_key(|&i| costs[i]).unwrap_or(usize::MAX);
                        right += usize::from(best == slice);
                        total += 1;
                    }
                }
                assert!(right * 100 >= total * 95, "d {d} {:?}: {right} of {total}", v.source);
            }
        }
    }
}
