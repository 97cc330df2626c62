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
//! Order of the volumes (fixed; the weights depend on it): N = 1, the stereo neighbour (`right`
//! when present); N = 2, the two horizontal neighbours (offsets −1 then +1 along x) or, lacking
//! them, the two vertical ones; N = 4, left, right, top, bottom (offsets `[−1, 0]`, `[1, 0]`,
//! `[0, −1]`, `[0, 1]`). Top and bottom costs are computed along the image columns by the same
//! matcher (equivalent to the authors' transposed images, transposed back).

use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::PixelCost;
use crate::fusion::Fusion;
use crate::sgm::{aggregate_volume, quantisation_shift, quantise_penalty};
use crate::volume::{CostSpec, CostVolume, Neighbour, Problem, neighbour_volumes};

/// Byte steps per normalised cost unit.
pub const STEPS_PER_UNIT: f32 = 128.0;

/// How the per-neighbour volumes are made.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputSpec {
    /// Per-pixel cost.
    pub cost: PixelCost,
    /// Block radius of the aggregation before SGM.
    pub block_radius: usize,
    /// SGM penalty for ±1 disparity steps (cost units).
    pub p1: u16,
    /// SGM penalty for larger jumps.
    pub p2: u16,
}

impl Default for InputSpec {
    /// Our SGM's defaults (census 7×7 summed over 7×7, P1 300, P2 3000).
    fn default() -> Self {
        Self {
            cost: PixelCost::Census { radius: 3 },
            block_radius: 3,
            p1: 300,
            p2: 3000,
        }
    }
}

/// The neighbours the network takes, in its fixed order, for a network of `views` inputs.
pub fn ordered_neighbours(problem: &Problem, views: usize) -> Result<Vec<&Neighbour>, FuseError> {
    let at = |offset: [i32; 2]| problem.neighbours.iter().find(|n| n.offset == offset);
    let found: Option<Vec<&Neighbour>> = match views {
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
        value: problem
            .neighbours
            .iter()
            .map(|n| format!("{} {:?}", n.role, n.offset))
            .collect::<Vec<_>>()
            .join(", "),
        reason: match views {
            2 => "the three-view network needs left and right (or top and bottom) at one baseline",
            4 => "the five-view network needs left, right, top and bottom at one baseline",
            _ => "MFuseNet has variants for 1, 2 and 4 neighbours",
        },
    })
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
    let cost = CostSpec {
        pixel: spec.cost,
        block_radius: spec.block_radius,
    };
    let shift = quantisation_shift(cost.max_cost());
    let (p1, p2) = (quantise_penalty(spec.p1, shift), quantise_penalty(spec.p2, shift));
    let mut out = Vec::with_capacity(neighbours.len());
    for n in neighbours {
        let volume = neighbour_volumes(problem, &[*n], cost, shift, on_band)?.remove(0);
        let sums = aggregate_volume(&volume, p1, p2);
        drop(volume);
        out.push(normalise(&sums, p2));
    }
    Ok(out)
}

/// `(S − min_d S) / (8 · P2)` in steps of 1/[`STEPS_PER_UNIT`], capped at 255 steps.
pub fn normalise(sums: &CostVolume<u16>, p2: u16) -> CostVolume<u8> {
    let scale = STEPS_PER_UNIT / (8.0 * f32::from(p2.max(1)));
    let mut data = vec![0u8; sums.data.len()];
    for (out, pixel) in data
        .chunks_exact_mut(sums.disparities)
        .zip(sums.data.chunks_exact(sums.disparities))
    {
        let min = pixel.iter().copied().min().unwrap_or(0);
        for (o, s) in out.iter_mut().zip(pixel) {
            *o = (f32::from(s - min) * scale).round().min(255.0) as u8;
        }
    }
    CostVolume {
        width: sums.width,
        height: sums.height,
        min_disparity: sums.min_disparity,
        disparities: sums.disparities,
        data,
        max_cost: 255,
        source: sums.source.clone(),
    }
}
