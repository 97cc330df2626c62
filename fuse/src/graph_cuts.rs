//! Multiscopic graph cuts: Kolmogorov and Zabih's stereo energy with occlusions and uniqueness
//! (ICCV 2001, as documented by Kolmogorov, Monasse and Tan, IPOL 2014, "KZ2"), extended to several
//! neighbour views as the MFuseNet paper does (section III-C), minimised by α-expansion with one
//! exact minimum cut ([`crate::maxflow`]) per move.
//!
//! An *assignment* `(p, d)` matches reference pixel `p` with the pixel `q_k = p − offset_k·d` of
//! every neighbour `k` the fusion uses. A configuration makes some assignments active: at most one
//! per reference pixel and, towards every neighbour, at most one per neighbour pixel (uniqueness);
//! a reference pixel without an active assignment is occluded. The energy, in integer units of a
//! quarter of a data-cost unit ([`UNITS_PER_COST`]):
//!
//! - data: for each active assignment, the neighbours' Birchfield–Tomasi costs (the 4-neighbour
//!   half-pixel variant, per channel `min(d, 30)`, squared for L2, averaged over the channels)
//!   fused by the rule (stereo, mean, min, heuristic) — neighbours whose `q_k` leaves the image
//!   are left out, and an assignment with none left is not allowed;
//! - occlusion: `K` for every occluded reference pixel (counted as `D − K` per active assignment
//!   plus the constant `K · pixels`);
//! - smoothness: for 4-neighbouring reference pixels `p1, p2` and a disparity `d` where exactly one
//!   of `(p1, d)`, `(p2, d)` is active (both allowed): `λ1` when the two pixels differ by less
//!   than θ in every channel in the reference and in every neighbour view that both assignments
//!   are matched in (at `q_k`), `λ2` otherwise;
//! - uniqueness: infinite.
//!
//! An α-expansion lets every active assignment of a disparity other than α stay or go and every
//! allowed `(p, α)` come: two binary variables per pixel, whose energy is submodular once the
//! first kind is read "0 = stays active" and the second "1 = becomes active" (IPOL article,
//! section 3). Its minimum cut is the best such move, so the energy never increases.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::{INVALID_COST, PixelCost, PreparedView};
use crate::fusion::{Fusion, fuse_values};
use crate::image::{DisparityImage, Image};
use crate::maxflow::BinaryEnergy;
use crate::volume::Problem;

/// Energy units per data-cost unit (so that K, λ1, λ2 may be quarters).
pub const UNITS_PER_COST: f32 = 4.0;
/// Per-channel Birchfield–Tomasi distances are truncated here before squaring (the IPOL
/// program's `CUTOFF`).
pub const BT_TRUNCATION: u16 = 30;

/// The data cost's norm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DataNorm {
    /// Truncated Birchfield–Tomasi distance.
    L1,
    /// Its square (the IPOL program's default).
    L2,
}

/// The parameters of the energy (in data-cost units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnergyParams {
    /// Occlusion penalty K.
    pub occlusion: f32,
    /// Smoothness penalty where the colours agree (λ1).
    pub lambda_similar: f32,
    /// Smoothness penalty across a colour edge (λ2).
    pub lambda_edge: f32,
    /// Colour difference below which two neighbouring pixels are similar (θ).
    pub edge_threshold: u8,
    /// Data norm.
    pub norm: DataNorm,
    /// Where uniqueness is enforced.
    pub uniqueness: Uniqueness,
    /// The data term is stored for every (label, pixel) when that takes at most this many MiB
    /// (3 bytes each), else computed where it is read ([`KzEnergy::new`]); the result is the
    /// same either way.
    pub stored_data_mib: usize,
}

/// Default [`EnergyParams::stored_data_mib`]: Middlebury's third size (32 labels, 15 MB) and
/// 640×480 with 128 labels (118 MB) stored, 1920×1080 with 64 or more labels (0.4–0.8 GB)
/// computed.
pub const DEFAULT_STORED_DATA_MIB: usize = 256;

impl Default for EnergyParams {
    /// The paper's K = 10, λ1 = 9, λ2 = 3, θ = 8 with the IPOL program's squared cost; uniqueness
    /// in the views the fused cost uses.
    fn default() -> Self {
        Self {
            occlusion: 10.0,
            lambda_similar: 9.0,
            lambda_edge: 3.0,
            edge_threshold: 8,
            norm: DataNorm::L2,
            uniqueness: Uniqueness::UsedViews,
            stored_data_mib: DEFAULT_STORED_DATA_MIB,
        }
    }
}

/// Which neighbour views an assignment must match uniquely.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Uniqueness {
    /// The views whose costs the fused data term uses (min: the smallest; heuristic: the two or
    /// three averaged; mean: all): a pixel occluded in one view but matched in another keeps its
    /// match without taking the occluder's pixel in the first.
    UsedViews,
    /// Every view the correspondence falls inside.
    AllViews,
}

/// Most neighbour views graph cuts take (one bit each in the uniqueness masks).
pub const MAX_VIEWS: usize = 8;

/// The views (bit k = view k) whose costs `fusion` uses for `values` ([`INVALID_COST`] = none).
pub fn used_views(fusion: Fusion, values: &[u16]) -> u8 {
    let valid = |v: u16| v != INVALID_COST;
    let mask_where = |keep: &dyn Fn(u16) -> bool| {
        values
            .iter()
            .enumerate()
            .filter(|(_, v)| valid(**v) && keep(**v))
            .fold(0u8, |m, (k, _)| m | 1 << k)
    };
    let mut buffer = [INVALID_COST; MAX_VIEWS];
    let mut count = 0;
    for &v in values.iter().take(MAX_VIEWS) {
        if valid(v) {
            buffer[count] = v;
            count += 1;
        }
    }
    let sorted = &mut buffer[..count];
    sorted.sort_unstable();
    match (fusion, &*sorted) {
        (_, []) => 0,
        (Fusion::Stereo, _) => u8::from(values.first().is_some_and(|v| valid(*v))),
        (Fusion::Mean, _) => mask_where(&|_| true),
        (Fusion::Min, [c1, ..]) | (Fusion::Heuristic, [c1] | [c1, _]) => mask_where(&|v| v == *c1),
        (Fusion::Heuristic, [_, c2, c3, ..]) => {
            let limit = if u32::from(*c3) > 3 * u32::from(*c2) { *c2 } else { *c3 };
            mask_where(&|v| v <= limit)
        }
    }
}

const OCCLUDED: u16 = u16::MAX;
const NO_OWNER: u32 = u32::MAX;
/// The assignment has disparity α before the move and stays active.
const VAR_ALPHA: u32 = u32::MAX;
/// No such assignment (occluded pixel, or α not allowed at this pixel).
const VAR_ABSENT: u32 = u32::MAX - 1;
/// (p, α) is allowed but stays inactive: its data cost exceeds everything activating it could
/// save, so no optimal move activates it and it needs no variable.
const VAR_INACTIVE: u32 = u32::MAX - 2;

#[inline]
fn is_var(v: u32) -> bool {
    v < VAR_INACTIVE
}

/// One neighbour as the energy sees it.
struct View {
    width: usize,
    height: usize,
    /// Image shift per label: `q = (x − shift.0, y − shift.1)`.
    shifts: Vec<(i32, i32)>,
    /// Largest channel difference between each pixel and its right / lower neighbour.
    edges: [Vec<u8>; 2],
    /// Reference pixel matched to each pixel (or [`NO_OWNER`]).
    owner: Vec<u32>,
}

impl View {
    #[inline]
    fn target(&self, x: usize, y: usize, label: usize) -> Option<usize> {
        let (sx, sy) = self.shifts[label];
        let qx = x as i64 - i64::from(sx);
        let qy = y as i64 - i64::from(sy);
        (qx >= 0 && qy >= 0 && (qx as usize) < self.width && (qy as usize) < self.height)
            .then(|| qy as usize * self.width + qx as usize)
    }
}

/// What one α-expansion did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Expansion {
    /// The label expanded.
    pub label: usize,
    /// Energy before.
    pub energy_before: i64,
    /// Energy of the best move (the minimum cut's value plus the constants).
    pub energy_after: i64,
    /// Whether the move was taken (it lowered the energy).
    pub accepted: bool,
}

/// Largest channel difference between each pixel and its right (0) / lower (1) neighbour.
fn edge_maps(image: &Image) -> [Vec<u8>; 2] {
    let (w, h, c) = (image.width, image.height, image.channels);
    let diff = |a: usize, b: usize| {
        (0..c)
            .map(|k| image.data[a * c + k].abs_diff(image.data[b * c + k]))
            .max()
            .unwrap_or(0)
    };
    let mut right = vec![0u8; w * h];
    let mut down = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if x + 1 < w {
                right[p] = diff(p, p + 1);
            }
            if y + 1 < h {
                down[p] = diff(p, p + w);
            }
        }
    }
    [right, down]
}

/// The per-neighbour data cost of the IPOL program: per channel, the Birchfield–Tomasi distance
/// (each pixel's value against the other's half-pixel interval, the smaller of the two) truncated
/// at [`BT_TRUNCATION`], squared for L2, averaged over the channels (rounded down).
#[inline]
fn bt_cost(reference: &PreparedView, neighbour: &PreparedView, p: usize, q: usize, norm: DataNorm) -> u16 {
    let c = reference.image().channels;
    let (rmin, rmax) = reference.bt_bounds();
    let (nmin, nmax) = neighbour.bt_bounds();
    let (ri, ni) = (&reference.image().data, &neighbour.image().data);
    let mut sum = 0u16;
    for k in 0..c {
        let (a, b) = (p * c + k, q * c + k);
        // Distance of v to the interval [lo, hi].
        let interval = |v: u8, lo: u8, hi: u8| lo.saturating_sub(v).max(v.saturating_sub(hi));
        let d = u16::from(interval(ri[a], nmin[b], nmax[b]).min(interval(ni[b], rmin[a], rmax[a]))).min(BT_TRUNCATION);
        sum += match norm {
            DataNorm::L1 => d,
            DataNorm::L2 => d * d,
        };
    }
    sum / c as u16
}

/// The largest data cost of a valid assignment (the truncation, squared).
const MAX_DATA_COST: u16 = BT_TRUNCATION * BT_TRUNCATION;

/// Half-size of the window whose data costs [`KzEnergy::confidence`] compares.
pub const CONFIDENCE_RADIUS: usize = 2;

/// One assignment's part of the data term.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Entry {
    /// The fused data cost, [`INVALID_COST`] where the assignment is not allowed.
    cost: u16,
    /// The views the assignment matches (bit k = view k): those whose costs the fused data term
    /// uses, where uniqueness is enforced.
    used: u8,
}

impl Entry {
    const NONE: Self = Self {
        cost: INVALID_COST,
        used: 0,
    };
}

/// The fused data term of every (label, pixel), label-major (as an expansion reads one label's
/// plane).
struct StoredTerm {
    costs: Vec<u16>,
    used: Vec<u8>,
}

/// The fused data term, computed where it is asked for when storing it for every (label,
/// pixel) would take more than [`EnergyParams::stored_data_mib`] (at 1920×1080 with 128 labels
/// the costs and masks are 0.8 GB). An expansion then computes its label's plane once
/// ([`KzEnergy::expand`]) and every pixel keeps its active assignment's entry; the rest (the
/// labels at depth edges, the readout) is computed when read, at about 1.3–1.5 × the time.
struct DataTerm {
    reference: PreparedView,
    neighbours: Vec<PreparedView>,
    fusion: Fusion,
    norm: DataNorm,
    /// [`Uniqueness::AllViews`]: an assignment uses every view it falls inside.
    strict: bool,
}

impl DataTerm {
    /// The entry of `(p, label)` over `views` (the energy's, one per neighbour) in an image
    /// `width` pixels wide.
    #[inline]
    fn entry(&self, views: &[View], width: usize, p: usize, label: usize) -> Entry {
        let (x, y) = (p % width, p / width);
        let mut buffer = [INVALID_COST; MAX_VIEWS];
        for ((value, view), neighbour) in buffer.iter_mut().zip(views).zip(&self.neighbours) {
            *value = view
                .target(x, y, label)
                .map_or(INVALID_COST, |q| bt_cost(&self.reference, neighbour, p, q, self.norm));
        }
        let values = &buffer[..views.len().min(MAX_VIEWS)];
        let used = if self.strict {
            values
                .iter()
                .enumerate()
                .filter(|(_, v)| **v != INVALID_COST)
                .fold(0u8, |m, (k, _)| m | 1 << k)
        } else {
            used_views(self.fusion, values)
        };
        Entry {
            cost: fuse_values(self.fusion, values),
            used,
        }
    }
}

/// Kolmogorov–Zabih's energy over a multiscopic problem and its current configuration.
pub struct KzEnergy {
    width: usize,
    height: usize,
    min_disparity: i32,
    labels: usize,
    term: DataTerm,
    /// Every entry, when it fits [`EnergyParams::stored_data_mib`].
    stored: Option<StoredTerm>,
    /// The entry of each pixel's active assignment (meaningless where it is occluded).
    current: Vec<Entry>,
    /// The label whose every entry is in `plane` (`usize::MAX`: none yet).
    plane_label: usize,
    plane: Vec<Entry>,
    ref_edges: [Vec<u8>; 2],
    views: Vec<View>,
    /// Label of each reference pixel's active assignment, or [`OCCLUDED`].
    disparity: Vec<u16>,
    occlusion: i64,
    lambda_similar: i64,
    lambda_edge: i64,
    edge_threshold: u8,
    /// Energy of the current configuration without the constant `K · pixels`.
    energy: i64,
    graph: BinaryEnergy,
    vars_current: Vec<u32>,
    vars_alpha: Vec<u32>,
}

impl KzEnergy {
    /// Prepares the energy of `problem` for the neighbours `fusion` uses; every pixel starts
    /// occluded.
    pub fn new(problem: &Problem, fusion: Fusion, params: EnergyParams) -> Result<Self, FuseError> {
        problem.validate()?;
        for (field, value) in [
            ("occlusion_k", params.occlusion),
            ("lambda1", params.lambda_similar),
            ("lambda2", params.lambda_edge),
        ] {
            if !(value.is_finite() && (0.0..=1.0e6).contains(&value)) {
                return Err(FuseError::Config {
                    field,
                    value: value.to_string(),
                    reason: "must be a number in 0..=1e6",
                });
            }
        }
        let (w, h) = (problem.reference.width, problem.reference.height);
        let labels = problem.num_disparities;
        if problem.neighbours.len() > MAX_VIEWS {
            return Err(FuseError::Config {
                field: "neighbours",
                value: problem.neighbours.len().to_string(),
                reason: "graph cuts take at most 8 neighbour views",
            });
        }
        let reference = PreparedView::new(problem.reference.clone(), PixelCost::BirchfieldTomasi);
        let neighbours = problem.neighbours_for(fusion);
        let prepared: Vec<PreparedView> = neighbours
            .iter()
            .map(|n| PreparedView::new(n.image.clone(), PixelCost::BirchfieldTomasi))
            .collect();
        let views: Vec<View> = neighbours
            .iter()
            .map(|n| View {
                width: w,
                height: h,
                shifts: (0..labels)
                    .map(|l| {
                        let d = (problem.min_disparity as f32 + l as f32) * n.baseline_ratio;
                        (
                            (n.offset[0] as f32 * d).round() as i32,
                            (n.offset[1] as f32 * d).round() as i32,
                        )
                    })
                    .collect(),
                edges: edge_maps(&n.image),
                owner: vec![NO_OWNER; w * h],
            })
            .collect();
        let term = DataTerm {
            reference,
            neighbours: prepared,
            fusion,
            norm: params.norm,
            strict: params.uniqueness == Uniqueness::AllViews,
        };
        let n = w * h;
        let stored = (n.saturating_mul(labels).saturating_mul(3) <= params.stored_data_mib.saturating_mul(1 << 20))
            .then(|| {
                let mut costs = vec![INVALID_COST; n * labels];
                let mut used = vec![0u8; n * labels];
                costs
                    .par_chunks_mut(n)
                    .zip(used.par_chunks_mut(n))
                    .enumerate()
                    .for_each(|(l, (costs, used))| {
                        for (p, (c, u)) in costs.iter_mut().zip(used.iter_mut()).enumerate() {
                            let e = term.entry(&views, w, p, l);
                            (*c, *u) = (e.cost, e.used);
                        }
                    });
                StoredTerm { costs, used }
            });
        let units = |v: f32| (v * UNITS_PER_COST).round() as i64;
        let mut energy = Self {
            width: w,
            height: h,
            min_disparity: problem.min_disparity,
            labels,
            term,
            stored,
            current: vec![Entry::NONE; w * h],
            plane_label: usize::MAX,
            plane: Vec::new(),
            ref_edges: edge_maps(&problem.reference),
            views,
            disparity: vec![OCCLUDED; w * h],
            occlusion: units(params.occlusion),
            lambda_similar: units(params.lambda_similar),
            lambda_edge: units(params.lambda_edge),
            edge_threshold: params.edge_threshold,
            energy: 0,
            graph: BinaryEnergy::new(),
            vars_current: vec![VAR_ABSENT; w * h],
            vars_alpha: vec![VAR_ABSENT; w * h],
        };
        energy.energy = energy.compute_energy();
        Ok(energy)
    }

    /// Number of labels (disparities).
    pub fn labels(&self) -> usize {
        self.labels
    }

    /// The current energy (in [`UNITS_PER_COST`] units, including `K` per occluded pixel).
    pub fn energy(&self) -> i64 {
        self.energy + self.occlusion * (self.width * self.height) as i64
    }

    /// The energy of the current configuration computed from scratch (as [`KzEnergy::energy`]).
    pub fn recompute_energy(&self) -> i64 {
        self.compute_energy() + self.occlusion * (self.width * self.height) as i64
    }

    /// Reference pixels without an active assignment.
    pub fn occluded_pixels(&self) -> usize {
        self.disparity.iter().filter(|l| **l == OCCLUDED).count()
    }

    /// The confidence of every reference pixel's assignment: 0 where it is occluded, else the
    /// margin of its label's data cost over the best label at least 2 away, `1 − c₁/c₂` as
    /// [`crate::wta::peak_confidence`], with each label's fused costs summed over the
    /// `(2·`[`CONFIDENCE_RADIUS`]`+1)²` window around the pixel (one pixel's Birchfield–Tomasi
    /// cost is 0 at many labels; a window's is not). Labels are visited one plane at a time, so
    /// the memory is two planes whatever the range.
    pub fn confidence(&self) -> Vec<f32> {
        let (w, h) = (self.width, self.height);
        let plane = w * h;
        let r = CONFIDENCE_RADIUS;
        // Per pixel: the window sum at its own label, the least at labels ≥ 2 away.
        let mut own = vec![f32::NAN; plane];
        let mut other = vec![f32::INFINITY; plane];
        let mut rows = vec![0f32; plane];
        let mut costs = vec![INVALID_COST; plane];
        for label in 0..self.labels {
            costs.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                for (x, c) in row.iter_mut().enumerate() {
                    *c = self.cost(y * w + x, label);
                }
            });
            let costs = &costs;
            // An invalid cell counts as the largest valid cost in the window sums.
            let value = |c: u16| {
                if c == INVALID_COST {
                    f32::from(MAX_DATA_COST)
                } else {
                    f32::from(c)
                }
            };
            rows.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
                let row = &costs[y * w..(y + 1) * w];
                let mut sum: f32 = (0..=r).map(|x| value(row[x.min(w - 1)])).sum::<f32>() + r as f32 * value(row[0]);
                for (x, o) in out.iter_mut().enumerate() {
                    *o = sum;
                    sum += value(row[(x + r + 1).min(w - 1)]) - value(row[x.saturating_sub(r)]);
                }
            });
            own.par_chunks_mut(w)
                .zip(other.par_chunks_mut(w))
                .enumerate()
                .for_each(|(y, (own, other))| {
                    for x in 0..w {
                        let p = y * w + x;
                        let l = self.disparity[p];
                        if l == OCCLUDED || costs[p] == INVALID_COST {
                            continue;
                        }
                        let sum: f32 = (y as isize - r as isize..=(y + r) as isize)
                            .map(|yy| rows[yy.clamp(0, h as isize - 1) as usize * w + x])
                            .sum();
                        if usize::from(l) == label {
                            own[x] = sum;
                        } else if usize::from(l).abs_diff(label) >= 2 {
                            other[x] = other[x].min(sum);
                        }
                    }
                });
        }
        own.iter()
            .zip(&other)
            .map(|(c1, c2)| match (c1.is_finite(), c2.is_finite()) {
                (false, _) => 0.0,
                (true, false) => 1.0,
                (true, true) if *c2 <= 0.0 => 0.0,
                (true, true) => (1.0 - c1 / c2).clamp(0.0, 1.0),
            })
            .collect()
    }

    /// The disparity of every reference pixel (`f32::INFINITY` = occluded), with its
    /// [`Self::confidence`].
    pub fn disparity(&self) -> DisparityImage {
        DisparityImage {
            width: self.width,
            height: self.height,
            data: self
                .disparity
                .iter()
                .map(|&l| {
                    if l == OCCLUDED {
                        f32::INFINITY
                    } else {
                        self.min_disparity as f32 + f32::from(l)
                    }
                })
                .collect(),
            confidence: Some(self.confidence()),
        }
    }

    /// The disparity with a sub-pixel offset: for every matched pixel whose label `d` has both
    /// neighbours in the range, the fused costs at `d − 1`, `d`, `d + 1` summed over the pixels of
    /// the `(2·radius + 1)²` window whose own label is within one of `d` (the same surface), and a
    /// parabola through the three sums; the offset is clamped to ±0.5 (occluded = `f32::INFINITY`).
    pub fn subpixel_disparity(&self, radius: usize) -> DisparityImage {
        let (w, h) = (self.width, self.height);
        let mut out = self.disparity();
        // A window pixel q counts only where its own label is within one of d, so it is read at
        // most two labels from its own: its costs there, computed once (`INVALID_COST` outside
        // the range).
        let mut near = vec![[INVALID_COST; 5]; w * h];
        near.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, costs) in row.iter_mut().enumerate() {
                let q = y * w + x;
                let lq = self.disparity[q];
                if lq == OCCLUDED {
                    continue;
                }
                for (i, c) in costs.iter_mut().enumerate() {
                    let l = usize::from(lq) + i;
                    if (2..self.labels + 2).contains(&l) {
                        *c = self.cost(q, l - 2);
                    }
                }
            }
        });
        let near = &near;
        out.data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, value) in row.iter_mut().enumerate() {
                let l = self.disparity[y * w + x];
                if l == OCCLUDED || l == 0 || usize::from(l) + 1 >= self.labels {
                    continue;
                }
                let l = usize::from(l);
                let mut sums = [0f64; 3];
                for qy in y.saturating_sub(radius)..(y + radius + 1).min(h) {
                    for qx in x.saturating_sub(radius)..(x + radius + 1).min(w) {
                        let q = qy * w + qx;
                        let lq = self.disparity[q];
                        if lq == OCCLUDED || usize::from(lq).abs_diff(l) > 1 {
                            continue;
                        }
                        // Labels l − 1, l, l + 1 sit at l − 1 − lq + 2 … of q's five.
                        let first = l + 1 - usize::from(lq);
                        let c = [near[q][first], near[q][first + 1], near[q][first + 2]];
                        if c.contains(&INVALID_COST) {
                            continue;
                        }
                        for (s, v) in sums.iter_mut().zip(c) {
                            *s += f64::from(v);
                        }
                    }
                }
                let curvature = sums[0] - 2.0 * sums[1] + sums[2];
                if curvature > 0.0 {
                    *value += (0.5 * (sums[0] - sums[2]) / curvature).clamp(-0.5, 0.5) as f32;
                }
            }
        });
        out
    }

    /// The data term's entry of `(p, label)`: from the expanded label's plane, the pixel's
    /// active assignment, or computed.
    #[inline]
    fn entry(&self, p: usize, label: usize) -> Entry {
        if let Some(stored) = &self.stored {
            let i = label * self.width * self.height + p;
            return Entry {
                cost: stored.costs[i],
                used: stored.used[i],
            };
        }
        if label == self.plane_label {
            self.plane[p]
        } else if usize::from(self.disparity[p]) == label {
            self.current[p]
        } else {
            self.term.entry(&self.views, self.width, p, label)
        }
    }

    /// Makes `label`'s entries the plane (once per label in a row).
    fn load_plane(&mut self, label: usize) {
        if self.stored.is_some() || self.plane_label == label {
            return;
        }
        let mut plane = std::mem::take(&mut self.plane);
        plane.resize(self.width * self.height, Entry::NONE);
        let (term, views, w) = (&self.term, &self.views, self.width);
        plane.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, e) in row.iter_mut().enumerate() {
                *e = term.entry(views, w, y * w + x, label);
            }
        });
        self.plane = plane;
        self.plane_label = label;
    }

    #[inline]
    fn cost(&self, p: usize, label: usize) -> u16 {
        self.entry(p, label).cost
    }

    #[inline]
    fn uses(&self, p: usize, label: usize, view: usize) -> bool {
        self.entry(p, label).used & (1 << view) != 0
    }

    #[inline]
    fn allowed(&self, p: usize, label: usize) -> bool {
        self.cost(p, label) != INVALID_COST
    }

    /// `D − K` of an allowed assignment.
    #[inline]
    fn data_occlusion(&self, p: usize, label: usize) -> i64 {
        i64::from(self.cost(p, label)) * UNITS_PER_COST as i64 - self.occlusion
    }

    /// Smoothness penalty between `(p, label)` and `(p + step, label)`, `direction` 0 = right,
    /// 1 = down.
    #[inline]
    fn smoothness(&self, p: usize, direction: usize, label: usize) -> i64 {
        let other = if direction == 0 { p + 1 } else { p + self.width };
        self.smoothness_seen(
            p,
            direction,
            label,
            self.entry(p, label).used & self.entry(other, label).used,
        )
    }

    /// [`Self::smoothness`] given the views `seen` in which both assignments are matched: one
    /// that sees an occluder at either pixel says nothing about whether the two lie on one
    /// surface.
    #[inline]
    fn smoothness_seen(&self, p: usize, direction: usize, label: usize, seen: u8) -> i64 {
        let mut largest = self.ref_edges[direction][p];
        let (x, y) = (p % self.width, p / self.width);
        for (k, view) in self.views.iter().enumerate() {
            if seen & (1 << k) == 0 {
                continue;
            }
            // A view an assignment is matched in holds its pixel, so both pixels are inside.
            if let Some(q) = view.target(x, y, label) {
                largest = largest.max(view.edges[direction][q]);
            }
        }
        if largest < self.edge_threshold {
            self.lambda_similar
        } else {
            self.lambda_edge
        }
    }

    /// Neighbour pixel `p + step` in `direction` (0 = right, 1 = down), if inside.
    #[inline]
    fn next(&self, p: usize, direction: usize) -> Option<usize> {
        if direction == 0 {
            (p % self.width + 1 < self.width).then_some(p + 1)
        } else {
            (p + self.width < self.width * self.height).then_some(p + self.width)
        }
    }

    fn compute_energy(&self) -> i64 {
        let mut e = 0i64;
        for p1 in 0..self.width * self.height {
            let l1 = self.disparity[p1];
            if l1 != OCCLUDED {
                e += self.data_occlusion(p1, usize::from(l1));
            }
            for direction in 0..2 {
                let Some(p2) = self.next(p1, direction) else {
                    continue;
                };
                let l2 = self.disparity[p2];
                if l1 == l2 {
                    continue;
                }
                if l1 != OCCLUDED && self.allowed(p2, usize::from(l1)) {
                    e += self.smoothness(p1, direction, usize::from(l1));
                }
                if l2 != OCCLUDED && self.allowed(p1, usize::from(l2)) {
                    e += self.smoothness(p1, direction, usize::from(l2));
                }
            }
        }
        e
    }

    /// The best α-expansion move for `label`, taken when it lowers the energy.
    pub fn expand(&mut self, label: usize) -> Expansion {
        self.load_plane(label);
        let alpha = label as u16;
        let n = self.width * self.height;
        let mut graph = std::mem::take(&mut self.graph);
        graph.reset();
        // At most per pixel: two α and two current smoothness edges, the reference's uniqueness
        // and one uniqueness edge per view.
        graph.reserve(2 * n, (5 + self.views.len()) * n);
        // Activating (p, α) saves at most the smoothness penalties with its four neighbours; a
        // larger `D − K` makes it a constant 0 (setting it to 0 keeps every constraint and
        // lowers the energy), which keeps the graph small.
        let most_saved = 4 * self.lambda_similar.max(self.lambda_edge);
        // Nodes: data and occlusion.
        for p in 0..n {
            let l = self.disparity[p];
            if l == alpha {
                self.vars_current[p] = VAR_ALPHA;
                self.vars_alpha[p] = VAR_ALPHA;
                graph.add_constant(self.data_occlusion(p, label));
                continue;
            }
            // Current assignment: 0 = stays active; new α assignment: 1 = becomes active.
            self.vars_current[p] = if l != OCCLUDED {
                graph.add_variable(self.data_occlusion(p, usize::from(l)), 0)
            } else {
                VAR_ABSENT
            };
            self.vars_alpha[p] = if !self.allowed(p, label) {
                VAR_ABSENT
            } else if self.data_occlusion(p, label) > most_saved {
                VAR_INACTIVE
            } else {
                graph.add_variable(0, self.data_occlusion(p, label))
            };
        }
        // Smoothness.
        for p1 in 0..n {
            for direction in 0..2 {
                if let Some(p2) = self.next(p1, direction) {
                    self.build_smoothness(&mut graph, p1, p2, direction, label);
                }
            }
        }
        // Uniqueness in the reference: (p, d) and (p, α) not both active.
        for p in 0..n {
            let (o, a) = (self.vars_current[p], self.vars_alpha[p]);
            if is_var(o) && is_var(a) {
                graph.forbid_01(o, a);
            }
        }
        // Uniqueness in every neighbour view (p, α) matches: the pixel it reaches there is not
        // matched by another active assignment.
        for (k, view) in self.views.iter().enumerate() {
            for p in 0..n {
                let a = self.vars_alpha[p];
                if !is_var(a) || !self.uses(p, label, k) {
                    continue;
                }
                let Some(q) = view.target(p % self.width, p / self.width, label) else {
                    continue;
                };
                let owner = view.owner[q];
                if owner != NO_OWNER && owner as usize != p {
                    let o = self.vars_current[owner as usize];
                    if is_var(o) {
                        graph.forbid_01(o, a);
                    }
                }
            }
        }
        let energy_before = self.energy;
        let energy_after = graph.minimize();
        let accepted = energy_after < energy_before;
        if accepted {
            self.apply(&graph, label);
            self.energy = energy_after;
        }
        self.graph = graph;
        let constant = self.occlusion * n as i64;
        Expansion {
            label,
            energy_before: energy_before + constant,
            energy_after: energy_after + constant,
            accepted,
        }
    }

    fn build_smoothness(&self, graph: &mut BinaryEnergy, p1: usize, p2: usize, direction: usize, label: usize) {
        let (l1, l2) = (self.disparity[p1], self.disparity[p2]);
        let (o1, a1) = (self.vars_current[p1], self.vars_alpha[p1]);
        let (o2, a2) = (self.vars_current[p2], self.vars_alpha[p2]);
        // Disparity α.
        if a1 != VAR_ABSENT && a2 != VAR_ABSENT && !(a1 == VAR_INACTIVE && a2 == VAR_INACTIVE) {
            let v = self.smoothness(p1, direction, label);
            match (a1, a2) {
                (VAR_ALPHA, VAR_ALPHA) => {}
                (VAR_ALPHA, VAR_INACTIVE) | (VAR_INACTIVE, VAR_ALPHA) => graph.add_constant(v),
                (VAR_ALPHA, x) | (x, VAR_ALPHA) => graph.add_unary(x, v, 0),
                (VAR_INACTIVE, x) | (x, VAR_INACTIVE) => graph.add_unary(x, 0, v),
                (x, y) => graph.add_potts(x, y, v),
            }
        }
        // The same current disparity d ≠ α on both pixels: both stay or both go.
        if l1 == l2 && is_var(o1) && is_var(o2) {
            let v = self.smoothness(p1, direction, usize::from(l1));
            graph.add_potts(o1, o2, v);
        }
        // Different num_disparities: an active (p1, d1) next to the inactive (p2, d1), and vice
        // versa (the inactive one's entry computed once, for whether it is allowed and where
        // it is matched).
        if l1 != l2 && is_var(o1) {
            let (active, inactive) = (self.entry(p1, usize::from(l1)), self.entry(p2, usize::from(l1)));
            if inactive.cost != INVALID_COST {
                let v = self.smoothness_seen(p1, direction, usize::from(l1), active.used & inactive.used);
                graph.add_unary(o1, v, 0);
            }
        }
        if l1 != l2 && is_var(o2) {
            let (inactive, active) = (self.entry(p1, usize::from(l2)), self.entry(p2, usize::from(l2)));
            if inactive.cost != INVALID_COST {
                let v = self.smoothness_seen(p1, direction, usize::from(l2), inactive.used & active.used);
                graph.add_unary(o2, v, 0);
            }
        }
    }

    fn apply(&mut self, graph: &BinaryEnergy, label: usize) {
        let n = self.width * self.height;
        for p in 0..n {
            let o = self.vars_current[p];
            if is_var(o) && graph.value(o) == 1 {
                let l = usize::from(self.disparity[p]);
                self.set_owner(p, l, false);
                self.disparity[p] = OCCLUDED;
            }
        }
        for p in 0..n {
            let a = self.vars_alpha[p];
            if is_var(a) && graph.value(a) == 1 {
                self.set_owner(p, label, true);
                self.disparity[p] = label as u16;
                self.current[p] = self.entry(p, label);
            }
        }
    }

    /// Marks (or clears) `p` as the match of its assignment's pixels in the views it uses.
    fn set_owner(&mut self, p: usize, label: usize, active: bool) {
        let (x, y) = (p % self.width, p / self.width);
        let mask = self.entry(p, label).used;
        for (k, view) in self.views.iter_mut().enumerate() {
            if mask & (1 << k) != 0
                && let Some(q) = view.target(x, y, label)
            {
                view.owner[q] = if active { p as u32 } else { NO_OWNER };
            }
        }
    }

    /// Whether every neighbour pixel is matched at most once (checked from scratch).
    pub fn is_unique(&self) -> bool {
        let n = self.width * self.height;
        self.views.iter().enumerate().all(|(k, view)| {
            let mut seen = vec![false; n];
            (0..n).all(|p| {
                let l = self.disparity[p];
                if l == OCCLUDED || !self.uses(p, usize::from(l), k) {
                    return true;
                }
                view.target(p % self.width, p / self.width, usize::from(l))
                    .is_none_or(|q| !std::mem::replace(&mut seen[q], true))
            })
        })
    }

    /// The IPOL program's automatic K: the mean over pixels (with every label allowed) of the
    /// k-th smallest data cost, k = max(3, (labels + 2) / 4), in data-cost units.
    pub fn automatic_occlusion(&self) -> f32 {
        occlusion_from_kth_sums(self.kth_cost_sums(0..self.height))
    }

    /// The sum and count behind [`Self::automatic_occlusion`] over the pixels of `rows`: a
    /// problem solved in strips takes its K from the rows each strip keeps.
    pub fn kth_cost_sums(&self, rows: std::ops::Range<usize>) -> (f64, usize) {
        let k = ((self.labels + 2) / 4).max(3).min(self.labels);
        let rows = rows.start.min(self.height)..rows.end.min(self.height);
        // Each pixel's k-th cost in parallel, summed in pixel order (the same sum every time).
        let kth: Vec<Option<u16>> = (rows.start * self.width..rows.end * self.width)
            .into_par_iter()
            .map_init(
                || Vec::with_capacity(self.labels),
                |costs, p| {
                    costs.clear();
                    costs.extend((0..self.labels).map(|l| self.cost(p, l)));
                    if costs.contains(&INVALID_COST) {
                        return None;
                    }
                    costs.select_nth_unstable(k - 1);
                    Some(costs[k - 1])
                },
            )
            .collect();
        let (mut sum, mut count) = (0f64, 0usize);
        for c in kth.into_iter().flatten() {
            sum += f64::from(c);
            count += 1;
        }
        (sum, count)
    }

    /// Replaces the occlusion and smoothness penalties (data-cost units) and recomputes the
    /// energy.
    pub fn set_penalties(&mut self, occlusion: f32, lambda_similar: f32, lambda_edge: f32) {
        let units = |v: f32| (v * UNITS_PER_COST).round() as i64;
        self.occlusion = units(occlusion);
        self.lambda_similar = units(lambda_similar);
        self.lambda_edge = units(lambda_edge);
        self.energy = self.compute_energy();
    }
}

/// The automatic K from [`KzEnergy::kth_cost_sums`]' sum and count (their mean; 0 without
/// pixels).
pub fn occlusion_from_kth_sums((sum, count): (f64, usize)) -> f32 {
    if count == 0 { 0.0 } else { (sum / count as f64) as f32 }
}

/// A random permutation of `0..n` from `seed` (Fisher–Yates on a 64-bit LCG).
pub fn label_order(n: usize, seed: u64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..n).collect();
    let mut state = seed ^ 0x9E37_79B9_7F4A_7C15;
    for i in (1..n).rev() {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let j = ((state >> 33) % (i as u64 + 1)) as usize;
        order.swap(i, j);
    }
    order
}

/// Runs α-expansion rounds over the labels in `order` until a whole round lowers nothing (or
/// `max_rounds`); `on_expansion` sees every move. Returns the energy before the first move and
/// after each.
pub fn expand_until_converged(
    energy: &mut KzEnergy,
    order: &[usize],
    max_rounds: usize,
    on_expansion: &mut dyn FnMut(&Expansion),
) -> Vec<i64> {
    let labels = energy.labels();
    let mut done = vec![false; labels];
    let mut remaining = labels;
    let mut energies = vec![energy.energy()];
    for _ in 0..max_rounds {
        if remaining == 0 {
            break;
        }
        for &label in order {
            if done[label] {
                continue;
            }
            let expansion = energy.expand(label);
            energies.push(energy.energy());
            on_expansion(&expansion);
            if expansion.accepted {
                done.fill(false);
                remaining = labels;
            }
            done[label] = true;
            remaining -= 1;
        }
    }
    energies
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::volume::Neighbour;

    /// A textured fronto-parallel plane at disparity `d` seen from the left and right.
    pub(crate) fn plane_problem(d: usize) -> Problem {
        let view = |shift: i64| crate::image::textured_view(48, 24, shift);
        let d = d as i64;
        Problem {
            reference: view(0),
            neighbours: vec![
                Neighbour {
                    role: "left".into(),
                    image: view(-d),
                    offset: [-1, 0],
                    baseline_ratio: 1.0,
                },
                Neighbour {
                    role: "right".into(),
                    image: view(d),
                    offset: [1, 0],
                    baseline_ratio: 1.0,
                },
            ],
            min_disparity: 0,
            num_disparities: 8,
        }
    }

    #[test]
    fn a_fronto_parallel_plane_gets_its_disparity_and_the_energy_never_rises() {
        for fusion in [Fusion::Stereo, Fusion::Min, Fusion::Mean, Fusion::Heuristic] {
            let problem = plane_problem(3);
            let mut energy = KzEnergy::new(&problem, fusion, EnergyParams::default()).unwrap_or_else(|e| panic!("{e}"));
            let mut checked = 0;
            let energies = expand_until_converged(&mut energy, &label_order(8, 1), 10, &mut |e| {
                assert!(e.energy_after <= e.energy_before || !e.accepted);
                checked += 1;
            });
            assert!(checked > 0);
            assert!(energies.windows(2).all(|w| w[1] <= w[0]), "{energies:?}");
            assert_eq!(energy.energy(), energy.recompute_energy());
            assert!(energy.is_unique());
            let disparity = energy.disparity();
            let (w, h) = (disparity.width, disparity.height);
            // Away from the borders that leave a view, every pixel is matched at 3.
            for y in 0..h {
                for x in 4..w - 4 {
                    assert_eq!(disparity.data[y * w + x], 3.0, "{fusion:?} ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn a_line_of_five_gets_the_plane_with_every_view_at_its_multiple() {
        // The plane at d = 3 with views at ±2 baselines too (shifted by 6).
        let mut problem = plane_problem(3);
        let outer = plane_problem(6);
        for (k, n) in outer.neighbours.into_iter().enumerate() {
            problem.neighbours.push(Neighbour {
                role: if k == 0 { "left2" } else { "right2" }.into(),
                offset: [n.offset[0] * 2, 0],
                ..n
            });
        }
        for fusion in [Fusion::Min, Fusion::Heuristic] {
            let mut energy = KzEnergy::new(&problem, fusion, EnergyParams::default()).unwrap_or_else(|e| panic!("{e}"));
            let energies = expand_until_converged(&mut energy, &label_order(8, 2), 10, &mut |_| {});
            assert!(energies.windows(2).all(|w| w[1] <= w[0]), "{energies:?}");
            assert_eq!(energy.energy(), energy.recompute_energy());
            assert!(energy.is_unique());
            let disparity = energy.disparity();
            let w = disparity.width;
            for y in 0..disparity.height {
                for x in 7..w - 7 {
                    assert_eq!(disparity.data[y * w + x], 3.0, "{fusion:?} ({x}, {y})");
                }
            }
        }
    }

    /// The data term computed where it is read (no memory for it) gives what the stored one
    /// gives, move by move: on two planes side by side (depth edges, labels that differ between
    /// neighbours), with the sub-pixel readout, the confidence and the automatic K.
    #[test]
    fn the_data_term_computed_where_it_is_read_equals_the_stored_one() {
        let mut problem = plane_problem(2);
        let far = plane_problem(5);
        for (n, f) in problem.neighbours.iter_mut().zip(&far.neighbours) {
            let (w, c) = (n.image.width, n.image.channels);
            for y in 0..n.image.height {
                let row = (y * w + w / 2) * c..(y + 1) * w * c;
                n.image.data[row.clone()].copy_from_slice(&f.image.data[row]);
            }
        }
        let run = |stored_data_mib| {
            let params = EnergyParams {
                stored_data_mib,
                ..EnergyParams::default()
            };
            let mut energy = KzEnergy::new(&problem, Fusion::Heuristic, params).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(energy.stored.is_some(), stored_data_mib > 0);
            let k = energy.automatic_occlusion();
            let energies = expand_until_converged(&mut energy, &label_order(8, 5), 10, &mut |_| {});
            assert_eq!(energy.energy(), energy.recompute_energy());
            assert!(energy.is_unique());
            let d = energy.subpixel_disparity(2);
            (k, energies, d.data, d.confidence)
        };
        let (stored, computed) = (run(DEFAULT_STORED_DATA_MIB), run(0));
        assert!(
            stored.2.iter().any(|d| *d < 3.0) && stored.2.iter().any(|d| *d > 4.0),
            "{:?}",
            stored.2
        );
        assert_eq!(stored, computed);
    }

    #[test]
    fn every_accepted_cut_equals_the_energy_it_claims() {
        let problem = plane_problem(2);
        let mut energy =
            KzEnergy::new(&problem, Fusion::Heuristic, EnergyParams::default()).unwrap_or_else(|e| panic!("{e}"));
        for label in label_order(8, 7).into_iter().chain(0..8) {
            let e = energy.expand(label);
            if e.accepted {
                assert_eq!(e.energy_after, energy.recompute_energy(), "label {label}");
            } else {
                assert_eq!(e.energy_before, energy.recompute_energy(), "label {label}");
            }
        }
    }

    #[test]
    fn uniqueness_binds_the_views_the_fused_cost_uses() {
        const X: u16 = INVALID_COST;
        assert_eq!(used_views(Fusion::Min, &[5, 3, 3, X]), 0b0110);
        assert_eq!(used_views(Fusion::Mean, &[5, X, 3]), 0b101);
        assert_eq!(used_views(Fusion::Stereo, &[5, 1]), 0b01);
        assert_eq!(used_views(Fusion::Heuristic, &[9, 2]), 0b10);
        // c3 = 40 > 3·c2 = 30: the two smallest; else the three.
        assert_eq!(used_views(Fusion::Heuristic, &[40, 10, 100, 8]), 0b1010);
        assert_eq!(used_views(Fusion::Heuristic, &[20, 10, 100, 9]), 0b1011);
        assert_eq!(used_views(Fusion::Heuristic, &[X, X]), 0);
    }

    #[test]
    fn label_order_is_a_seeded_permutation() {
        let a = label_order(32, 5);
        let mut sorted = a.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..32).collect::<Vec<_>>());
        assert_eq!(a, label_order(32, 5));
        assert_ne!(a, label_order(32, 6));
    }
}
