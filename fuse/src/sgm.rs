//! Semi-global matching (Hirschmüller, PAMI 2008) over a fused cost volume: eight paths,
//! penalties P1 for ±1 disparity steps and P2 for larger jumps, summed in `u16`.
//!
//! Costs are bytes ([`quantise`]): at 1080p and 128 disparities a volume is 265 MB instead of
//! 530 MB, for a change in the Middlebury AvgErr of about 0.002 px. Either a volume is held
//! ([`aggregate_volume`], [`select_volume`]) or the costs are made from the prepared views where
//! the passes read them, a band of rows at a time ([`aggregate_prepared`], [`select_prepared`]:
//! the same bytes, 265 MB less at that size).
//!
//! The winners ([`select_volume`], [`select_prepared`]) never hold the image's summed volume
//! (530 MB at that size): the sums live one band of rows at a time, the downward paths started
//! afresh a few dozen rows above each band (`select_in_bands`; within 0.01 px of the exact paths
//! for 99.3 % of the winners at 1080p). The whole sums ([`aggregate_volume`],
//! [`aggregate_prepared`]) are for the consumers that read them, exact.

use std::ops::Range;
use std::sync::atomic::{AtomicU16, AtomicUsize, Ordering};

use rayon::prelude::*;

use crate::cost::INVALID_COST;
use crate::volume::{BandScratch, CostVolume, PreparedProblem, VolumeSource};
use crate::wta::{SubpixelFit, winner_take_all, winner_take_all_confident};

/// Scales costs so that the sum of eight paths fits `u16`: returns the right shift to apply.
pub fn cost_shift(max_cost: u32, p2: u32) -> u32 {
    let mut shift = 0;
    while 8 * ((max_cost >> shift) + p2) >= u32::from(u16::MAX) {
        shift += 1;
    }
    shift
}

/// A quantised cost whose correspondence leaves the neighbour image.
pub const INVALID_QUANTISED: u8 = u8::MAX;

/// The smallest right shift that brings `max_cost` to at most 254 (255 marks invalid costs).
pub fn quantisation_shift(max_cost: u32) -> u32 {
    let mut shift = 0;
    while (max_cost >> shift) > u32::from(INVALID_QUANTISED - 1) {
        shift += 1;
    }
    shift
}

/// A cost quantised to a byte by `shift` ([`INVALID_COST`] → [`INVALID_QUANTISED`]).
#[inline]
pub fn quantise(cost: u16, shift: u32) -> u8 {
    if cost == INVALID_COST {
        INVALID_QUANTISED
    } else {
        (cost >> shift).min(u16::from(INVALID_QUANTISED - 1)) as u8
    }
}

/// [`quantise`] over a slice, branch-free so that it vectorises.
pub fn quantise_into(costs: &[u16], out: &mut [u8], shift: u32) {
    let shift = shift.min(15);
    let top = u16::from(INVALID_QUANTISED - 1);
    for (q, c) in out.iter_mut().zip(costs) {
        let value = (*c >> shift).min(top) as u8;
        let invalid = u8::from(*c == INVALID_COST);
        // 0xFF where invalid, else the value.
        *q = value | invalid.wrapping_neg();
    }
}

/// A penalty in the units of costs quantised by `shift`, rounded.
pub fn quantise_penalty(penalty: u16, shift: u32) -> u16 {
    if shift == 0 {
        penalty
    } else {
        ((u32::from(penalty) + (1 << (shift - 1))) >> shift) as u16
    }
}

/// Path costs of one pixel are stored with a sentinel on each side of the disparity axis
/// (`[MAX, L(d=0), …, L(d=n−1), MAX]`), so that `L(d±1)` needs no edge case.
const PAD: usize = 1;
/// The sentinel: `MAX + P1` saturates to `MAX`, which never wins a minimum.
const SENTINEL: u16 = u16::MAX;

/// Penalties and cost scaling shared by every path.
#[derive(Debug, Clone, Copy)]
struct Penalties {
    p1: u16,
    p2: u16,
    shift: u32,
    cap: u16,
}

impl Penalties {
    /// The data cost as the paths see it: scaled and capped (invalid costs become the cap).
    #[inline]
    fn data(&self, cost: u8) -> u16 {
        (u16::from(cost) >> self.shift).min(self.cap)
    }

    /// Path cost at a pixel with no predecessor on the path: the data cost. `out` is padded.
    /// Returns the smallest value.
    #[inline]
    fn start(&self, cost: &[u8], out: &mut [u16]) -> u16 {
        let n = cost.len();
        out[0] = SENTINEL;
        out[n + 1] = SENTINEL;
        let mut smallest = u16::MAX;
        for (o, c) in out[PAD..PAD + n].iter_mut().zip(cost) {
            *o = self.data(*c);
            smallest = smallest.min(*o);
        }
        smallest
    }

    /// `L(p, d) = C(p, d) + min(L(p−r, d), L(p−r, d±1) + P1, min L(p−r) + P2) − min L(p−r)`
    /// in one vectorised pass; `previous` and `out` are padded, `previous_min` is `min L(p−r)`.
    /// Returns `min L(p)`.
    #[inline]
    fn step(&self, cost: &[u8], previous: &[u16], previous_min: u16, out: &mut [u16]) -> u16 {
        let n = cost.len();
        let (below, centre, above) = (&previous[..n], &previous[1..n + 1], &previous[2..n + 2]);
        out[0] = SENTINEL;
        out[n + 1] = SENTINEL;
        let jump = previous_min.saturating_add(self.p2);
        let mut smallest = u16::MAX;
        for d in 0..n {
            let best = centre[d]
                .min(below[d].saturating_add(self.p1))
                .min(above[d].saturating_add(self.p1))
                .min(jump);
            let value = self.data(cost[d]) + best - previous_min;
            out[PAD + d] = value;
            smallest = smallest.min(value);
        }
        smallest
    }
}

/// The eight paths' summed costs of a [`CostVolume`], a volume of the same
/// source whose `max_cost` bounds the sums (`8 · (cap + P2)` in the scaled units).
pub fn aggregate_volume(volume: &CostVolume<u8>, p1: u16, p2: u16) -> CostVolume<u16> {
    let penalties = Penalties::new(volume.max_cost, p1, p2);
    let geometry = Geometry {
        width: volume.width,
        height: volume.height,
        nd: volume.num_disparities,
    };
    let data = passes(Costs::Stored(&volume.data), geometry, &penalties, Vec::new(), &|| {});
    volume.with_data(data, 8 * (u32::from(penalties.cap) + u32::from(p2)))
}

/// [`aggregate_volume`] of `prepared`'s fused volume quantised by `shift`
/// ([`PreparedProblem::fused_volume`]), without that volume: each pass makes the costs of the
/// rows it reaches. The same numbers. The sums are written into `reuse` when it has their size
/// (a caller aggregating several volumes in turn keeps one buffer's pages), else into a new
/// buffer; `on_band` is called after each band of the first pass.
pub fn aggregate_prepared(
    prepared: &PreparedProblem,
    shift: u32,
    (p1, p2): (u16, u16),
    reuse: Vec<u16>,
    on_band: &(dyn Fn() + Sync),
) -> CostVolume<u16> {
    let max_cost = prepared.quantised_max_cost(shift);
    let penalties = Penalties::new(max_cost, p1, p2);
    let geometry = Geometry {
        width: prepared.width(),
        height: prepared.height(),
        nd: prepared.num_disparities(),
    };
    let data = passes(Costs::Made { prepared, shift }, geometry, &penalties, reuse, on_band);
    CostVolume {
        width: geometry.width,
        height: geometry.height,
        min_disparity: prepared.min_disparity(),
        num_disparities: geometry.nd,
        data,
        max_cost: 8 * (u32::from(penalties.cap) + u32::from(p2)),
        source: VolumeSource::Fused(prepared.fusion()),
    }
}

/// Winner-take-all over the eight-path sums of `volume` (as [`aggregate_volume`] then
/// [`crate::wta::winner_take_all`]), picked while the last pass visits each pixel, the sums held
/// one band of rows at a time (`select_in_bands`, the downward paths warmed up above each band:
/// [`SELECT_WARMUP_ROWS`]). Returns the disparities and their
/// confidences (`[y][x]`, [`crate::wta::peak_confidence`] of the summed costs).
#[allow(clippy::too_many_arguments)]
pub(crate) fn select(
    volume: &[u8],
    width: usize,
    height: usize,
    num_disparities: usize,
    max_cost: u32,
    (p1, p2): (u16, u16),
    min_disparity: i32,
    subpixel: Option<SubpixelFit>,
) -> (Vec<f32>, Vec<f32>) {
    let penalties = Penalties::new(max_cost, p1, p2);
    let geometry = Geometry {
        width,
        height,
        nd: num_disparities,
    };
    let pick = Pick {
        min_disparity,
        subpixel,
        confidence: true,
    };
    select_from(Costs::Stored(volume), geometry, &penalties, pick, &|_| {})
}

/// How the last pass picks each pixel's winner: the first slice's disparity, the sub-pixel fit,
/// and whether it also rates the winner ([`crate::wta::peak_confidence`]; without, the
/// confidences returned are all 0).
#[derive(Debug, Clone, Copy)]
struct Pick {
    min_disparity: i32,
    subpixel: Option<SubpixelFit>,
    confidence: bool,
}

/// [`select`] over the costs `costs` of `geometry`, in bands of [`SELECT_BAND_ROWS`];
/// `on_band` gets the fraction of the rows done after each band.
fn select_from(
    costs: Costs<'_>,
    geometry: Geometry,
    penalties: &Penalties,
    pick: Pick,
    on_band: &dyn Fn(f32),
) -> (Vec<f32>, Vec<f32>) {
    let bands = (SELECT_BAND_ROWS, Some(SELECT_WARMUP_ROWS));
    select_in_bands(costs, geometry, penalties, pick, bands, on_band)
}

/// Rows per band of [`select_in_bands`]: at 1080p and 128 disparities a band's sums are 63 MB
/// and the 8 saved rows of paths 12 MB, where the whole image's sums are 530 MB. Bands of 64
/// rows took more time there (each band's passes start cold), bands of 256 no less.
const SELECT_BAND_ROWS: usize = 128;

/// Rows above each band over which [`select_in_bands`] starts its downward paths afresh instead
/// of carrying them from the image's first row. A path forgets where it started within a few
/// dozen rows: at 1080p with 128 disparities 0.66 % of the winners move by more than 0.01 px and
/// 0.06 % by more than 1 px against the exact paths (16 rows: 0.92 % and 0.12 %), the AvgErr of
/// Middlebury's dev scenes 0.4006 → 0.4011 px and of the five-view 1080p capture 0.2868 → 0.2864;
/// the selection takes 0.235–0.258 s there instead of 0.247–0.323 s (docs/experiments.md).
const SELECT_WARMUP_ROWS: usize = 32;

/// [`select`] without the image's summed volume: band by band from the bottom, the horizontal
/// paths, the downward paths resumed at the band's first row, and the upward paths carried from
/// the band below are summed in one band's buffer and the winners picked. The sums' pages are
/// faulted in once per band-sized buffer instead of once per pixel.
///
/// Where the downward paths resume from: with `warmup_rows` `None`, a first pass runs them over
/// the whole image and keeps their values at the last row of every band (the exact numbers of
/// [`aggregate_volume`]'s sums; 11 paths' work instead of 8); with `Some(k)`, each band starts
/// them afresh `k` rows above its first row (8 paths' work and `3k ⁄ band_rows` more; the paths
/// at the band differ from the exact ones where their start still shows).
fn select_in_bands(
    costs: Costs<'_>,
    geometry: Geometry,
    penalties: &Penalties,
    pick: Pick,
    (band_rows, warmup_rows): (usize, Option<usize>),
    on_band: &dyn Fn(f32),
) -> (Vec<f32>, Vec<f32>) {
    let Geometry { width, height, nd } = geometry;
    let mut out = vec![f32::INFINITY; 2 * width * height];
    let row_len = width * nd;
    if row_len == 0 || height == 0 {
        return out.chunks_exact(2).map(|pair| (pair[0], pair[1])).unzip();
    }
    let band_rows = band_rows.max(1);
    let bands: Vec<Range<usize>> = (0..height)
        .step_by(band_rows)
        .map(|start| start..(start + band_rows).min(height))
        .collect();
    // The downward paths at the last row of every band but the last (exact), or of the band
    // above the one being summed (warmed up).
    let saved_rows = match warmup_rows {
        None => bands.len() - 1,
        Some(_) => usize::from(bands.len() > 1),
    };
    let mut saved: Vec<PathRow> = (0..saved_rows).map(|_| PathRow::new(width, nd)).collect();
    let mut scratch = Vec::new();
    if !saved.is_empty() && warmup_rows.is_none() {
        let saves = bands
            .iter()
            .zip(saved.iter_mut())
            .map(|(band, state)| (band.end - 1, state))
            .collect();
        // Down to the last saved row: the last band's rows are not needed.
        let rows = bands[bands.len() - 2].end;
        let sweep = Sweep {
            costs: match costs {
                Costs::Stored(volume) => Costs::Stored(&volume[..rows * row_len]),
                made => made,
            },
            geometry: Geometry {
                height: rows,
                ..geometry
            },
            penalties,
            downward: true,
        };
        vertical_pass(sweep, None, None, (None, saves), &mut scratch);
    }
    let mut sums = vec![0u16; band_rows.min(height) * row_len];
    // Made costs: the rows `made_rows` (the band and the warm-up rows above it).
    let (mut made, mut made_rows) = (Vec::new(), 0..0);
    // The upward paths at the first row of the band below, and the same for this band.
    let (mut below, mut this) = (PathRow::new(width, nd), PathRow::new(width, nd));
    for (index, band) in bands.iter().enumerate().rev() {
        let band_geometry = Geometry {
            width,
            height: band.len(),
            nd,
        };
        // The downward paths' warm-up rows above the band.
        let warm_rows = match warmup_rows {
            Some(warmup) if index > 0 => band.start.saturating_sub(warmup.max(1))..band.start,
            _ => band.start..band.start,
        };
        let (warm_costs, band_costs): (&[u8], &[u8]) = match costs {
            Costs::Stored(volume) => (
                &volume[warm_rows.start * row_len..warm_rows.end * row_len],
                &volume[band.start * row_len..band.end * row_len],
            ),
            Costs::Made { prepared, shift } => {
                // The rows below the band above's warm-up were made with it: moved, not made again.
                let need = warm_rows.start..band.end;
                let kept = need.start.max(made_rows.start)..need.end.min(made_rows.end);
                let kept = if kept.end == need.end && kept.start < kept.end {
                    kept
                } else {
                    need.end..need.end
                };
                let to = kept.start - need.start;
                made.resize(made.len().max(need.len() * row_len), 0);
                if !kept.is_empty() {
                    let from = kept.start - made_rows.start;
                    made.copy_within(from * row_len..(from + kept.len()) * row_len, to * row_len);
                }
                made.truncate(need.len() * row_len);
                make_rows(prepared, shift, need.start..kept.start, &mut made[..to * row_len]);
                made_rows = need;
                made.split_at(warm_rows.len() * row_len)
            }
        };
        let band_sums = &mut sums[..band.len() * row_len];
        // On threads of their own, as the vertical passes: a pool's idle workers would spin
        // beside those passes' workers for a while after a parallel iterator.
        let share = band.len().div_ceil(vertical_workers(width)) * row_len;
        std::thread::scope(|scope| {
            for (sums, costs) in band_sums.chunks_mut(share).zip(band_costs.chunks(share)) {
                scope.spawn(move || {
                    let (mut previous, mut current) = (vec![0u16; nd + 2], vec![0u16; nd + 2]);
                    for (sum_row, cost_row) in sums.chunks_mut(row_len).zip(costs.chunks(row_len)) {
                        horizontal_paths(penalties, cost_row, sum_row, nd, &mut previous, &mut current);
                    }
                });
            }
        });
        let above = match warmup_rows {
            None => index.checked_sub(1),
            Some(_) => (index > 0).then_some(0),
        };
        if let (Some(_), Some(state)) = (warmup_rows, above.and_then(|i| saved.get_mut(i))) {
            // The downward paths at the row above the band, started afresh at the warm-up rows.
            let rows = warm_rows.clone();
            let sweep = Sweep {
                costs: Costs::Stored(warm_costs),
                geometry: Geometry {
                    height: rows.len(),
                    ..geometry
                },
                penalties,
                downward: true,
            };
            vertical_pass(sweep, None, None, (None, vec![(rows.len() - 1, state)]), &mut scratch);
        }
        let band_costs = Costs::Stored(band_costs);
        let above = above.and_then(|i| saved.get(i));
        let resume = (above, Vec::new());
        let sweep = Sweep {
            costs: band_costs,
            geometry: band_geometry,
            penalties,
            downward: true,
        };
        vertical_pass(sweep, Some(&mut *band_sums), None, resume, &mut scratch);
        let mut selection = Selection {
            pick,
            out: &mut out[2 * band.start * width..2 * band.end * width],
        };
        let resume = (index + 1 < bands.len()).then_some(&below);
        // The last row of the upward pass over the band is its first row.
        let save = if index > 0 {
            vec![(band.len() - 1, &mut this)]
        } else {
            Vec::new()
        };
        let resume = (resume, save);
        let sweep = Sweep {
            downward: false,
            ..sweep
        };
        vertical_pass(sweep, Some(band_sums), Some(&mut selection), resume, &mut scratch);
        std::mem::swap(&mut below, &mut this);
        on_band((height - band.start) as f32 / height as f32);
    }
    out.chunks_exact(2).map(|pair| (pair[0], pair[1])).unzip()
}

/// The fused costs of `rows` quantised by `shift` into `out` (`[y][x][d]`), shares of the rows
/// in parallel, each with its block's 2ρ rows before it.
fn make_rows(prepared: &PreparedProblem, shift: u32, rows: Range<usize>, out: &mut [u8]) {
    let row_len = prepared.width() * prepared.num_disparities();
    if rows.is_empty() || row_len == 0 {
        return;
    }
    let share = rows.len().div_ceil(rayon::current_num_threads().max(1));
    out.par_chunks_mut(share * row_len)
        .enumerate()
        .for_each_init(BandScratch::default, |scratch, (k, out)| {
            let first = rows.start + k * share;
            let rows = first..first + out.len() / row_len;
            prepared.fused_quantised_into(rows, 0..prepared.width(), shift, out, scratch);
        });
}

/// [`select_volume`] of `prepared`'s fused volume quantised by `shift`, without that volume
/// (as [`aggregate_prepared`]): the same disparities and confidences as [`select_volume`], or
/// with `confidence` false the same disparities and every confidence 0 (the winners not rated).
/// `on_band` gets the fraction of the rows done after each band of 128 (for a progress bar).
pub fn select_prepared(
    prepared: &PreparedProblem,
    shift: u32,
    (p1, p2): (u16, u16),
    subpixel: Option<SubpixelFit>,
    confidence: bool,
    on_band: &dyn Fn(f32),
) -> (Vec<f32>, Vec<f32>) {
    let penalties = Penalties::new(prepared.quantised_max_cost(shift), p1, p2);
    let geometry = Geometry {
        width: prepared.width(),
        height: prepared.height(),
        nd: prepared.num_disparities(),
    };
    let pick = Pick {
        min_disparity: prepared.min_disparity(),
        subpixel,
        confidence,
    };
    select_from(Costs::Made { prepared, shift }, geometry, &penalties, pick, on_band)
}

/// SGM's winners on a [`CostVolume`] (quantised costs; its `max_cost` bounds the valid ones, its
/// `min_disparity` is the first slice's): the disparities and confidences, `[y][x]`.
pub fn select_volume(
    volume: &CostVolume<u8>,
    penalties: (u16, u16),
    subpixel: Option<SubpixelFit>,
) -> (Vec<f32>, Vec<f32>) {
    select(
        &volume.data,
        volume.width,
        volume.height,
        volume.num_disparities,
        volume.max_cost,
        penalties,
        volume.min_disparity,
        subpixel,
    )
}

/// Where the last pass puts the winners instead of the sums.
struct Selection<'a> {
    pick: Pick,
    /// Per pixel (`[y][x]`), its disparity and its confidence.
    out: &'a mut [f32],
}

impl Penalties {
    fn new(max_cost: u32, p1: u16, p2: u16) -> Self {
        let shift = cost_shift(max_cost, u32::from(p2));
        Self {
            p1,
            p2,
            shift,
            cap: ((max_cost >> shift).min(u32::from(INVALID_COST) - 1)) as u16,
        }
    }
}

/// Where the passes read their data costs: a stored byte volume `[y][x][d]`, or the fused costs
/// of prepared views quantised by `shift`, made a band of rows at a time where a pass reaches them.
#[derive(Clone, Copy)]
enum Costs<'a> {
    Stored(&'a [u8]),
    Made { prepared: &'a PreparedProblem, shift: u32 },
}

/// Rows per band of costs made for a pass: each band also makes the block's 2ρ rows before it
/// (6 of 64 at ρ = 3), and a worker's band of 1,000 columns × 132 disparities is 8 MB.
const MADE_BAND_ROWS: usize = 64;

/// One worker's rows of [`Costs`] over a block of columns.
struct RowCosts<'a> {
    costs: Costs<'a>,
    geometry: Geometry,
    columns: Range<usize>,
    /// The rows in `buffer` (made costs only).
    band: Range<usize>,
    buffer: Vec<u8>,
    scratch: BandScratch,
}

impl<'a> RowCosts<'a> {
    fn new(costs: Costs<'a>, geometry: Geometry, columns: Range<usize>) -> Self {
        Self {
            costs,
            geometry,
            columns,
            band: 0..0,
            buffer: Vec::new(),
            scratch: BandScratch::default(),
        }
    }

    /// Row `y`'s costs over the columns (`[x][d]`); a pass `downward` makes the band from `y`
    /// on, else the band up to `y`.
    fn row(&mut self, y: usize, downward: bool) -> &[u8] {
        let Geometry { width, height, nd } = self.geometry;
        let cells = self.columns.len() * nd;
        match self.costs {
            Costs::Stored(volume) => {
                let at = (y * width + self.columns.start) * nd;
                &volume[at..at + cells]
            }
            Costs::Made { prepared, shift } => {
                if !self.band.contains(&y) {
                    self.band = if downward {
                        y..(y + MADE_BAND_ROWS).min(height)
                    } else {
                        (y + 1).saturating_sub(MADE_BAND_ROWS)..y + 1
                    };
                    self.buffer.resize(self.band.len() * cells, 0);
                    prepared.fused_quantised_into(
                        self.band.clone(),
                        self.columns.clone(),
                        shift,
                        &mut self.buffer,
                        &mut self.scratch,
                    );
                }
                let at = (y - self.band.start) * cells;
                &self.buffer[at..at + cells]
            }
        }
    }
}

/// The eight paths' sums of the whole image in three passes, each parallel: the two horizontal
/// paths (rows in parallel) write the sums; the three paths from the row above are added row by
/// row from the top, and the three from the row below from the bottom ([`vertical_pass`]). The
/// sums go into `reuse` when it has their length, else into a new
/// buffer; `on_band` is called after each band of the horizontal pass over made costs.
fn passes(
    costs: Costs<'_>,
    geometry: Geometry,
    penalties: &Penalties,
    reuse: Vec<u16>,
    on_band: &(dyn Fn() + Sync),
) -> Vec<u16> {
    let Geometry { width, height, nd } = geometry;
    let row_len = width * nd;
    // The horizontal pass writes every sum before any is read: a reused buffer needs no clearing.
    let mut sum = if reuse.len() == height * row_len {
        reuse
    } else {
        drop(reuse);
        vec![0u16; height * row_len]
    };
    if row_len == 0 {
        return sum;
    }
    match costs {
        Costs::Stored(volume) => sum
            .par_chunks_mut(row_len)
            .zip(volume.par_chunks(row_len))
            .for_each_init(
                || (vec![0u16; nd + 2], vec![0u16; nd + 2]),
                |(previous, current), (sum_row, cost_row)| {
                    horizontal_paths(penalties, cost_row, sum_row, nd, previous, current);
                },
            ),
        Costs::Made { .. } => sum.par_chunks_mut(MADE_BAND_ROWS * row_len).enumerate().for_each_init(
            || {
                (
                    RowCosts::new(costs, geometry, 0..width),
                    vec![0u16; nd + 2],
                    vec![0u16; nd + 2],
                )
            },
            |(rows, previous, current), (band, sums)| {
                for (k, sum_row) in sums.chunks_mut(row_len).enumerate() {
                    let cost_row = rows.row(band * MADE_BAND_ROWS + k, true);
                    horizontal_paths(penalties, cost_row, sum_row, nd, previous, current);
                }
                on_band();
            },
        ),
    }
    let scratch = &mut Vec::new();
    let sweep = Sweep {
        costs,
        geometry,
        penalties,
        downward: true,
    };
    vertical_pass(sweep, Some(&mut sum), None, (None, Vec::new()), scratch);
    let resume = (None, Vec::new());
    let sweep = Sweep {
        downward: false,
        ..sweep
    };
    vertical_pass(sweep, Some(&mut sum), None, resume, scratch);
    sum
}

/// Image size and disparities of a pass.
#[derive(Debug, Clone, Copy)]
struct Geometry {
    width: usize,
    height: usize,
    nd: usize,
}

/// The three paths that reach a pixel from the row before (`downward`: the row above; else the
/// row below), added into `sum`, or, with a `selection`, summed with it per pixel and the
/// winner picked.
///
/// A pixel depends only on the row before, so each worker thread owns a block of columns for
/// the whole pass and the workers meet at a spinning barrier after every row. The only values
/// that cross blocks are the diagonal paths at the block edges, handed over through a small
/// exchange (double-buffered by row parity, so a worker never overwrites what its neighbour has
/// yet to read). Workers never sleep between rows: a pool's wake-ups cost more than a row.
fn vertical_pass(
    sweep: Sweep<'_>,
    sum: Option<&mut [u16]>,
    selection: Option<&mut Selection<'_>>,
    (start, saves): (Option<&PathRow>, Vec<(usize, &mut PathRow)>),
    scratch: &mut Vec<PassScratch>,
) {
    let Sweep {
        costs,
        geometry,
        penalties,
        downward,
    } = sweep;
    let Geometry { width, height, nd } = geometry;
    let workers = vertical_workers(width);
    if scratch.len() < workers {
        scratch.resize_with(workers, PassScratch::default);
    }
    let block = width.div_ceil(workers);
    // Each worker's column block of every row (rows in image order).
    let mut sum_blocks: Vec<Vec<&mut [u16]>> = (0..workers).map(|_| Vec::with_capacity(height)).collect();
    for row in sum.into_iter().flat_map(|sum| sum.chunks_mut(width * nd)) {
        let mut rest = row;
        for blocks in &mut sum_blocks {
            let (left, right) = rest.split_at_mut((block * nd).min(rest.len()));
            blocks.push(left);
            rest = right;
        }
    }
    // Each worker's column block of every saved state.
    let mut save_blocks: Vec<Vec<(usize, SavedBlock<'_>)>> =
        (0..workers).map(|_| Vec::with_capacity(saves.len())).collect();
    for (row_index, state) in saves {
        for (blocks, saved) in save_blocks.iter_mut().zip(state.blocks(block, nd)) {
            blocks.push((row_index, saved));
        }
    }
    let pick = selection.as_ref().map(|s| s.pick);
    let mut winner_blocks: Vec<Vec<&mut [f32]>> = (0..workers).map(|_| Vec::new()).collect();
    if let Some(selection) = selection {
        for row in selection.out.chunks_mut(2 * width) {
            let mut rest = row;
            for blocks in &mut winner_blocks {
                let (left, right) = rest.split_at_mut((2 * block).min(rest.len()));
                blocks.push(left);
                rest = right;
            }
        }
    }
    let exchange = Exchange::new(workers, nd);
    let barrier = SpinBarrier::new(workers);
    std::thread::scope(|scope| {
        let jobs = sum_blocks
            .into_iter()
            .zip(winner_blocks)
            .zip(save_blocks)
            .zip(scratch.iter_mut());
        for (worker, (((sums, winners), saves), scratch)) in jobs.enumerate() {
            let columns = worker * block..((worker + 1) * block).min(width);
            let job = BlockJob {
                costs,
                geometry,
                penalties,
                downward,
                pick,
                columns,
                worker,
                exchange: &exchange,
                barrier: &barrier,
                start,
            };
            scope.spawn(move || job.run(sums, winners, saves, scratch));
        }
    });
}

/// What a vertical pass runs over: its costs, their size, the penalties and the direction.
#[derive(Clone, Copy)]
struct Sweep<'a> {
    costs: Costs<'a>,
    geometry: Geometry,
    penalties: &'a Penalties,
    /// From the top row down, else from the bottom row up.
    downward: bool,
}

/// Column blocks (worker threads) of a vertical pass over `width` columns.
fn vertical_workers(width: usize) -> usize {
    rayon::current_num_threads().clamp(1, width.div_ceil(MIN_CHUNK_COLUMNS).max(1))
}

/// The three vertical paths' values at one row, the state a pass resumes from: per path (the
/// diagonal from the left, the vertical, the diagonal from the right), every column's padded
/// path vector (`[x][PAD + d + PAD]`) and its minimum.
struct PathRow {
    paths: [Vec<u16>; 3],
    minima: [Vec<u16>; 3],
}

/// One worker's columns of a [`PathRow`]: its paths and minima, per path.
type SavedBlock<'a> = ([&'a mut [u16]; 3], [&'a mut [u16]; 3]);

impl PathRow {
    fn new(width: usize, nd: usize) -> Self {
        Self {
            paths: std::array::from_fn(|_| vec![0u16; width * (nd + 2)]),
            minima: std::array::from_fn(|_| vec![0u16; width]),
        }
    }

    /// The row split into column blocks of `block` columns.
    fn blocks(&mut self, block: usize, nd: usize) -> Vec<SavedBlock<'_>> {
        let [p0, p1, p2] = &mut self.paths;
        let [m0, m1, m2] = &mut self.minima;
        let stride = nd + 2;
        let paths = p0
            .chunks_mut(block * stride)
            .zip(p1.chunks_mut(block * stride))
            .zip(p2.chunks_mut(block * stride));
        let minima = m0.chunks_mut(block).zip(m1.chunks_mut(block)).zip(m2.chunks_mut(block));
        paths
            .zip(minima)
            .map(|(((a, b), c), ((x, y), z))| ([a, b, c], [x, y, z]))
            .collect()
    }
}

/// One worker's share of a vertical pass.
struct BlockJob<'a> {
    costs: Costs<'a>,
    geometry: Geometry,
    penalties: &'a Penalties,
    downward: bool,
    pick: Option<Pick>,
    columns: Range<usize>,
    worker: usize,
    exchange: &'a Exchange,
    barrier: &'a SpinBarrier,
    /// The paths at the row before the first (in the pass's direction), else the first row starts them.
    start: Option<&'a PathRow>,
}

impl BlockJob<'_> {
    /// Runs the pass over the rows, adding into `sums` (none: the paths alone), or with a
    /// selection into `winners`, and copies the paths after row index `i` into each `saves` entry `(i, _)`.
    fn run(
        self,
        mut sums: Vec<&mut [u16]>,
        mut winners: Vec<&mut [f32]>,
        mut saves: Vec<(usize, SavedBlock<'_>)>,
        scratch: &mut PassScratch,
    ) {
        let Geometry { width, height, nd } = self.geometry;
        let stride = nd + 2;
        let count = self.columns.len();
        let x0 = self.columns.start;
        let PassScratch {
            previous,
            current,
            previous_min,
            current_min,
        } = scratch;
        for paths in [&mut *previous, &mut *current] {
            paths.iter_mut().for_each(|path| path.resize(count * stride, 0));
        }
        for minima in [&mut *previous_min, &mut *current_min] {
            minima.iter_mut().for_each(|minimum| minimum.resize(count, 0));
        }
        // The previous row's diagonal paths just outside the block: path 0 of x0 − 1 (from the
        // left neighbour) and path 2 of the block's end (from the right neighbour), with their minima.
        let mut left_ghost = vec![0u16; stride];
        let mut right_ghost = vec![0u16; stride];
        let (mut left_ghost_min, mut right_ghost_min) = (0u16, 0u16);
        let mut total = vec![0u16; nd];
        let mut rows = RowCosts::new(self.costs, self.geometry, self.columns.clone());
        for row_index in 0..height {
            let y = if self.downward {
                row_index
            } else {
                height - 1 - row_index
            };
            if row_index > 0 {
                self.barrier.wait();
                let parity = (row_index - 1) % 2;
                if self.worker > 0 {
                    left_ghost_min = self
                        .exchange
                        .read(self.worker - 1, Side::Right, parity, &mut left_ghost);
                }
                if x0 + count < width {
                    right_ghost_min = self
                        .exchange
                        .read(self.worker + 1, Side::Left, parity, &mut right_ghost);
                }
            }
            let cost_row = rows.row(y, self.downward);
            let mut sum_row = sums.get_mut(y).map(|row| &mut **row);
            for i in 0..count {
                let x = x0 + i;
                let cost = &cost_row[i * nd..(i + 1) * nd];
                for (k, dx) in [-1isize, 0, 1].into_iter().enumerate() {
                    let px = x as isize + dx;
                    let cell = &mut current[k][i * stride..(i + 1) * stride];
                    current_min[k][i] = if px < 0 || px as usize >= width {
                        self.penalties.start(cost, cell)
                    } else if row_index == 0 {
                        match self.start {
                            Some(state) => {
                                let p = px as usize;
                                self.penalties.step(
                                    cost,
                                    &state.paths[k][p * stride..(p + 1) * stride],
                                    state.minima[k][p],
                                    cell,
                                )
                            }
                            None => self.penalties.start(cost, cell),
                        }
                    } else if (px as usize) < x0 {
                        self.penalties.step(cost, &left_ghost, left_ghost_min, cell)
                    } else if px as usize >= x0 + count {
                        self.penalties.step(cost, &right_ghost, right_ghost_min, cell)
                    } else {
                        let p = px as usize - x0;
                        let before = &previous[k][p * stride..(p + 1) * stride];
                        self.penalties.step(cost, before, previous_min[k][p], cell)
                    };
                }
                let [a, b, c] =
                    [&current[0], &current[1], &current[2]].map(|o| &o[i * stride + PAD..i * stride + PAD + nd]);
                let Some(sum_row) = sum_row.as_deref_mut() else {
                    continue;
                };
                let sum_cell = &mut sum_row[i * nd..(i + 1) * nd];
                match self.pick {
                    Some(pick) => {
                        for ((((t, s), a), b), c) in total.iter_mut().zip(&*sum_cell).zip(a).zip(b).zip(c) {
                            *t = s.saturating_add(*a + *b + *c);
                        }
                        let (disparity, confidence) = winners[y][2 * i..2 * i + 2].split_at_mut(1);
                        let (min_disparity, subpixel) = (pick.min_disparity, pick.subpixel);
                        if pick.confidence {
                            winner_take_all_confident(&total, nd, min_disparity, subpixel, disparity, confidence);
                        } else {
                            winner_take_all(&total, nd, min_disparity, subpixel, disparity);
                            confidence[0] = 0.0;
                        }
                    }
                    None => {
                        for (((s, a), b), c) in sum_cell.iter_mut().zip(a).zip(b).zip(c) {
                            *s = s.saturating_add(*a + *b + *c);
                        }
                    }
                }
            }
            if count > 0 {
                let parity = row_index % 2;
                let last = count - 1;
                self.exchange.write(
                    self.worker,
                    Side::Left,
                    parity,
                    &current[2][..stride],
                    current_min[2][0],
                );
                self.exchange.write(
                    self.worker,
                    Side::Right,
                    parity,
                    &current[0][last * stride..(last + 1) * stride],
                    current_min[0][last],
                );
            }
            if let Some(at) = saves.iter().position(|(after, _)| *after == row_index) {
                let (_, (paths, minima)) = saves.swap_remove(at);
                for k in 0..3 {
                    paths[k].copy_from_slice(&current[k]);
                    minima[k].copy_from_slice(&current_min[k]);
                }
            }
            std::mem::swap(previous, current);
            std::mem::swap(previous_min, current_min);
        }
    }
}

/// A worker's path values of the row before and the current row in a vertical pass, per path,
/// kept from one pass to the next: fresh pages for each band's passes would cost more than
/// the band's rows.
#[derive(Default)]
struct PassScratch {
    previous: [Vec<u16>; 3],
    current: [Vec<u16>; 3],
    previous_min: [Vec<u16>; 3],
    current_min: [Vec<u16>; 3],
}

/// Which edge of a worker's block.
#[derive(Debug, Clone, Copy)]
enum Side {
    Left,
    Right,
}

/// Edge path values handed between neighbouring workers: per worker, side and row parity, one
/// padded path vector followed by its minimum. Plain relaxed atomics: the barrier orders them.
struct Exchange {
    slots: Vec<AtomicU16>,
    slot_len: usize,
}

impl Exchange {
    fn new(workers: usize, nd: usize) -> Self {
        let slot_len = nd + 3;
        Self {
            slots: (0..workers * 4 * slot_len).map(|_| AtomicU16::new(0)).collect(),
            slot_len,
        }
    }

    fn slot(&self, worker: usize, side: Side, parity: usize) -> &[AtomicU16] {
        let index = (worker * 2 + side as usize) * 2 + parity;
        &self.slots[index * self.slot_len..(index + 1) * self.slot_len]
    }

    fn write(&self, worker: usize, side: Side, parity: usize, path: &[u16], minimum: u16) {
        let slot = self.slot(worker, side, parity);
        for (cell, value) in slot.iter().zip(path.iter().chain(std::iter::once(&minimum))) {
            cell.store(*value, Ordering::Relaxed);
        }
    }

    /// Copies the padded path into `path` and returns its minimum.
    fn read(&self, worker: usize, side: Side, parity: usize, path: &mut [u16]) -> u16 {
        let slot = self.slot(worker, side, parity);
        for (value, cell) in path.iter_mut().zip(slot) {
            *value = cell.load(Ordering::Relaxed);
        }
        slot[self.slot_len - 1].load(Ordering::Relaxed)
    }
}

/// How long a waiter spins in [`SpinBarrier::wait`] before it sleeps: a row takes tens of
/// microseconds, so a partner later than this has lost its CPU (another process runs there).
const SPIN_BEFORE_SLEEP: std::time::Duration = std::time::Duration::from_micros(20);

/// A reusable barrier whose waiters spin, then sleep, instead of sleeping at once (a sleeper's
/// wake-up costs more than a row).
///
/// Waiters never yield: on a host where other processes run (a robot's drivers, a training run
/// at the lowest priority), `sched_yield` hands the CPU to them for a whole time slice, the
/// partner then waits on this thread in turn, and the pass took twice as long. A waiter whose
/// partner is late sleeps on a condition variable instead, which the last to arrive signals
/// (`sgm-heuristic` at 1080p beside a training run at nice 19: 1.93–2.05 s → 1.08–1.25 s; alone,
/// the same as spinning within the host's noise).
struct SpinBarrier {
    threads: usize,
    arrived: AtomicUsize,
    generation: AtomicUsize,
    /// Waiters asleep (or about to sleep): the last to arrive signals only when there are some.
    sleepers: AtomicUsize,
    lock: std::sync::Mutex<()>,
    wake: std::sync::Condvar,
}

impl SpinBarrier {
    fn new(threads: usize) -> Self {
        Self {
            threads,
            arrived: AtomicUsize::new(0),
            generation: AtomicUsize::new(0),
            sleepers: AtomicUsize::new(0),
            lock: std::sync::Mutex::new(()),
            wake: std::sync::Condvar::new(),
        }
    }

    /// Returns once every thread has called `wait` for this generation; what each wrote before
    /// its call is visible to all after it.
    fn wait(&self) {
        let generation = self.generation.load(Ordering::Acquire);
        if self.arrived.fetch_add(1, Ordering::AcqRel) + 1 == self.threads {
            self.arrived.store(0, Ordering::Relaxed);
            // Sequentially consistent with the sleepers' count: either a waiter counted itself
            // before this load (and is signalled) or it sees the new generation before it sleeps.
            self.generation.fetch_add(1, Ordering::SeqCst);
            if self.sleepers.load(Ordering::SeqCst) > 0 {
                let _guard = self.lock.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                self.wake.notify_all();
            }
            return;
        }
        let mut spins = 0u32;
        let mut since: Option<std::time::Instant> = None;
        while self.generation.load(Ordering::Acquire) == generation {
            spins = spins.wrapping_add(1);
            std::hint::spin_loop();
            if !spins.is_multiple_of(256) {
                continue;
            }
            let started = *since.get_or_insert_with(std::time::Instant::now);
            if started.elapsed() < SPIN_BEFORE_SLEEP {
                continue;
            }
            let mut guard = self.lock.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            self.sleepers.fetch_add(1, Ordering::SeqCst);
            while self.generation.load(Ordering::SeqCst) == generation {
                guard = self.wake.wait(guard).unwrap_or_else(std::sync::PoisonError::into_inner);
            }
            self.sleepers.fetch_sub(1, Ordering::SeqCst);
            return;
        }
    }
}

/// Fewest columns per worker in the row-by-row passes.
const MIN_CHUNK_COLUMNS: usize = 256;

/// The left-to-right and right-to-left paths of one row: written (first touch) into `sum_row`.
fn horizontal_paths(
    penalties: &Penalties,
    cost_row: &[u8],
    sum_row: &mut [u16],
    nd: usize,
    previous: &mut Vec<u16>,
    current: &mut Vec<u16>,
) {
    let width = cost_row.len() / nd;
    for leftward in [false, true] {
        let mut previous_min = 0;
        for i in 0..width {
            let x = if leftward { width - 1 - i } else { i };
            let cost = &cost_row[x * nd..(x + 1) * nd];
            previous_min = if i == 0 {
                penalties.start(cost, current)
            } else {
                penalties.step(cost, previous, previous_min, current)
            };
            let sum_cell = &mut sum_row[x * nd..(x + 1) * nd];
            let path = &current[PAD..PAD + nd];
            if leftward {
                for (s, v) in sum_cell.iter_mut().zip(path) {
                    *s = s.saturating_add(*v);
                }
            } else {
                // First touch writes: a fresh page is faulted in once, not read as the shared
                // zero page and then copied on write.
                sum_cell.copy_from_slice(path);
            }
            std::mem::swap(previous, current);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Path cost at a pixel with no predecessor on the path: the (scaled, capped) data cost.
    #[inline]
    fn path_start(cost: &[u8], out: &mut [u16], shift: u32, cap: u16) {
        for (o, c) in out.iter_mut().zip(cost) {
            *o = (u16::from(*c) >> shift).min(cap);
        }
    }

    /// `L(p, d) = C(p, d) + min(L(p−r, d), L(p−r, d±1) + P1, min L(p−r) + P2) − min L(p−r)`,
    /// written as whole-slice passes so that the compiler vectorises them.
    #[inline]
    fn path_step(cost: &[u8], previous: &[u16], out: &mut [u16], p1: u16, p2: u16, shift: u32, cap: u16) {
        let n = out.len();
        let (cost, previous) = (&cost[..n], &previous[..n]);
        let min_prev = previous.iter().copied().min().unwrap_or(0);
        let jump = min_prev.saturating_add(p2);
        for (o, p) in out.iter_mut().zip(previous) {
            *o = (*p).min(jump);
        }
        for (o, p) in out[1..].iter_mut().zip(&previous[..n - 1]) {
            *o = (*o).min(p.saturating_add(p1));
        }
        for (o, p) in out[..n - 1].iter_mut().zip(&previous[1..]) {
            *o = (*o).min(p.saturating_add(p1));
        }
        for (o, c) in out.iter_mut().zip(cost) {
            *o = (u16::from(*c) >> shift).min(cap) + *o - min_prev;
        }
    }

    /// Raw `[y][x][d]` costs as a (left neighbour's) volume whose largest valid cost is `max_cost`.
    fn as_volume(costs: &[u8], [w, h, nd]: [usize; 3], max_cost: u32) -> CostVolume<u8> {
        let volume = CostVolume::from_fn([w, h, nd], 0, ("left", [-1, 0]), |x, y, d| costs[(y * w + x) * nd + d]);
        CostVolume { max_cost, ..volume }
    }

    /// The previous sequential implementation, kept as the definition the parallel one must match.
    /// Aggregates `volume` (`[y][x][d]`) along eight paths and returns the summed costs.
    /// `max_cost` bounds the valid costs (invalid ones count as `max_cost`).
    fn aggregate_reference(
        volume: &[u8],
        width: usize,
        height: usize,
        num_disparities: usize,
        max_cost: u32,
        p1: u16,
        p2: u16,
    ) -> Vec<u16> {
        let shift = cost_shift(max_cost, u32::from(p2));
        let cap = ((max_cost >> shift).min(u32::from(INVALID_COST) - 1)) as u16;
        assert_eq!(cap, Penalties::new(max_cost, p1, p2).cap);
        let nd = num_disparities;
        let row_len = width * nd;
        let mut sum = vec![0u16; volume.len()];
        for forward in [true, false] {
            // Path costs of the previous and current row for the three paths that come from the
            // previous row (diagonal, vertical, other diagonal); the horizontal path keeps one pixel.
            let mut previous: Vec<Vec<u16>> = vec![vec![0u16; row_len]; 3];
            let mut current: Vec<Vec<u16>> = vec![vec![0u16; row_len]; 3];
            let mut horizontal = vec![0u16; nd];
            let mut scratch = vec![0u16; nd];
            let mut total = vec![0u16; nd];
            for row_index in 0..height {
                let y = if forward { row_index } else { height - 1 - row_index };
                for col_index in 0..width {
                    let x = if forward { col_index } else { width - 1 - col_index };
                    let cell = (y * width + x) * nd;
                    let cost = &volume[cell..cell + nd];
                    // Horizontal path: the previous pixel of this row.
                    if col_index == 0 {
                        path_start(cost, &mut horizontal, shift, cap);
                    } else {
                        scratch.copy_from_slice(&horizontal);
                        path_step(cost, &scratch, &mut horizontal, p1, p2, shift, cap);
                    }
                    total.copy_from_slice(&horizontal);
                    // Paths from the previous row: x − step, x, x + step (step = ±1 with the sweep).
                    for (k, dx) in [-1isize, 0, 1].into_iter().enumerate() {
                        let dx = if forward { dx } else { -dx };
                        let px = x as isize + dx;
                        let out = &mut current[k][x * nd..(x + 1) * nd];
                        if row_index > 0 && px >= 0 && (px as usize) < width {
                            let p = px as usize * nd;
                            path_step(cost, &previous[k][p..p + nd], out, p1, p2, shift, cap);
                        } else {
                            path_start(cost, out, shift, cap);
                        }
                        for (t, v) in total.iter_mut().zip(out.iter()) {
                            *t = t.saturating_add(*v);
                        }
                    }
                    let cell_sum = &mut sum[cell..cell + nd];
                    if forward {
                        // First touch writes: a fresh page is faulted in once, not read as the shared
                        // zero page and then copied on write.
                        cell_sum.copy_from_slice(&total);
                    } else {
                        for (s, t) in cell_sum.iter_mut().zip(&total) {
                            *s = s.saturating_add(*t);
                        }
                    }
                }
                std::mem::swap(&mut previous, &mut current);
            }
        }
        sum
    }

    #[test]
    fn the_barrier_holds_every_thread_until_the_last_arrives_whether_its_waiters_spin_or_sleep() {
        // Each round every thread writes the round into its slot, waits, and must then see every
        // slot at that round; a second wait keeps the next round's writes after the reads. One
        // thread is late on some rounds (longer than the spin), so that the others sleep there.
        let threads = 3;
        let rounds = 300usize;
        let barrier = SpinBarrier::new(threads);
        let slots: Vec<AtomicUsize> = (0..threads).map(|_| AtomicUsize::new(usize::MAX)).collect();
        let seen_wrong = AtomicUsize::new(0);
        std::thread::scope(|scope| {
            for t in 0..threads {
                let (barrier, slots, seen_wrong) = (&barrier, &slots, &seen_wrong);
                scope.spawn(move || {
                    for round in 0..rounds {
                        if t == 0 && round % 7 == 0 {
                            std::thread::sleep(SPIN_BEFORE_SLEEP * 5);
                        }
                        slots[t].store(round, Ordering::Relaxed);
                        barrier.wait();
                        if slots.iter().any(|s| s.load(Ordering::Relaxed) != round) {
                            seen_wrong.fetch_add(1, Ordering::Relaxed);
                        }
                        barrier.wait();
                    }
                });
            }
        });
        assert_eq!(seen_wrong.load(Ordering::Relaxed), 0);
        assert_eq!(barrier.sleepers.load(Ordering::Relaxed), 0, "every sleeper woke");
        assert_eq!(barrier.generation.load(Ordering::Relaxed), 2 * rounds);
    }

    #[test]
    fn parallel_passes_match_the_sequential_definition() {
        let mut state = 3u32;
        for (w, h, nd) in [(7, 5, 6), (300, 9, 12), (1, 4, 3), (513, 3, 2), (800, 6, 5)] {
            let volume: Vec<u8> = (0..w * h * nd)
                .map(|_| {
                    state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    let v = (state >> 16) as u16 % 1200;
                    quantise(if v > 1150 { INVALID_COST } else { v }, 3)
                })
                .collect();
            let max_cost = 1100 >> 3;
            let reference = aggregate_reference(&volume, w, h, nd, max_cost, 40, 400);
            let mut expected = vec![0.0f32; w * h];
            let mut expected_confidence = vec![0.0f32; w * h];
            winner_take_all_confident(
                &reference,
                nd,
                3,
                Some(SubpixelFit::Parabola),
                &mut expected,
                &mut expected_confidence,
            );
            // One, two and three column blocks (with edge exchanges between them).
            for threads in [1, 2, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap_or_else(|e| panic!("{e}"));
                pool.install(|| {
                    assert!(
                        aggregate_volume(&as_volume(&volume, [w, h, nd], max_cost), 40, 400).data == reference,
                        "{w}x{h}x{nd} {threads}"
                    );
                    let check = |(selected, confidence): (Vec<f32>, Vec<f32>), bands: usize| {
                        assert!(
                            selected
                                .iter()
                                .zip(&expected)
                                .all(|(a, b)| a == b || (a.is_infinite() && b.is_infinite())),
                            "{w}x{h}x{nd} selection, {threads} threads, bands of {bands}"
                        );
                        assert!(
                            confidence == expected_confidence,
                            "{w}x{h}x{nd} confidence, {threads} threads, bands of {bands}"
                        );
                    };
                    let fit = Some(SubpixelFit::Parabola);
                    check(select(&volume, w, h, nd, max_cost, (40, 400), 3, fit), SELECT_BAND_ROWS);
                    // Bands of one row, of two, and bands that end inside the image.
                    let pick = Pick {
                        min_disparity: 3,
                        subpixel: fit,
                        confidence: true,
                    };
                    for band_rows in [1, 2, 4] {
                        let geometry = Geometry {
                            width: w,
                            height: h,
                            nd,
                        };
                        let penalties = Penalties::new(max_cost, 40, 400);
                        let costs = Costs::Stored(&volume);
                        check(
                            select_in_bands(costs, geometry, &penalties, pick, (band_rows, None), &|_| {}),
                            band_rows,
                        );
                        // Warmed up from the first row: the exact paths.
                        check(
                            select_in_bands(costs, geometry, &penalties, pick, (band_rows, Some(h)), &|_| {}),
                            band_rows,
                        );
                    }
                });
            }
        }
    }

    #[test]
    fn paths_warmed_up_above_each_band_pick_the_exact_winners_on_a_noisy_slope() {
        // A slope of disparities 2 … 14 over 160 rows, costs |d − d*| × 8 plus noise up to 40 and
        // a few invalid cells: bands of 32 rows warmed up over 32 rows against the exact paths.
        let (w, h, nd) = (96, 160, 16);
        let mut state = 11u32;
        let volume: Vec<u8> = (0..h)
            .flat_map(|y| (0..w).flat_map(move |x| (0..nd).map(move |d| (x, y, d))))
            .map(|(x, y, d)| {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let noise = (state >> 24) % 41;
                if noise == 40 && (state >> 8).is_multiple_of(7) {
                    return INVALID_QUANTISED;
                }
                let truth = 2.0 + 12.0 * (y as f32 + 0.3 * x as f32) / (h as f32 + 0.3 * w as f32);
                ((d as f32 - truth).abs() * 8.0 + noise as f32).min(250.0) as u8
            })
            .collect();
        let geometry = Geometry {
            width: w,
            height: h,
            nd,
        };
        let penalties = Penalties::new(250, 10, 120);
        let costs = Costs::Stored(&volume);
        let pick = Pick {
            min_disparity: 0,
            subpixel: Some(SubpixelFit::Parabola),
            confidence: true,
        };
        let (exact, _) = select_in_bands(costs, geometry, &penalties, pick, (32, None), &|_| {});
        let (warmed, _) = select_in_bands(costs, geometry, &penalties, pick, (32, Some(32)), &|_| {});
        let moved = exact
            .iter()
            .zip(&warmed)
            .filter(|(a, b)| (*a - *b).abs() > 0.01)
            .count();
        // (Started afresh one row above each band instead, 721 move.)
        assert!(moved * 100 <= w * h, "{moved} of {} winners moved", w * h);
        // The first band has no band above: exact.
        assert_eq!(exact[..32 * w], warmed[..32 * w]);
    }

    #[test]
    fn smoothing_fills_an_ambiguous_pixel_from_its_neighbours() {
        // A 5×5 image whose pixels all prefer disparity 2, except the centre, whose costs are flat
        // (textureless): SGM must give it 2 as well; WTA alone cannot.
        let (w, h, nd) = (5, 5, 5);
        let mut volume = vec![0u8; w * h * nd];
        for p in 0..w * h {
            for d in 0..nd {
                volume[p * nd + d] = if p == 12 {
                    10
                } else if d == 2 {
                    0
                } else {
                    20
                };
            }
        }
        let sum = aggregate_volume(&as_volume(&volume, [w, h, nd], 20), 3, 12).data;
        let mut disparity = vec![0.0f32; w * h];
        winner_take_all(&sum, nd, 0, None, &mut disparity);
        assert!(disparity.iter().all(|d| *d == 2.0), "{disparity:?}");
    }

    #[test]
    fn quantised_costs_keep_their_order_and_the_invalid_mark() {
        assert_eq!(quantisation_shift(254), 0);
        assert_eq!(quantisation_shift(2352), 4);
        assert_eq!(quantise(2352, 4), 147);
        assert_eq!(quantise(INVALID_COST, 4), INVALID_QUANTISED);
        assert_eq!(quantise(60_000, 4), 254);
        let costs = [0, 17, 2352, INVALID_COST, 60_000];
        let mut out = [0u8; 5];
        quantise_into(&costs, &mut out, 4);
        assert_eq!(out.to_vec(), costs.iter().map(|c| quantise(*c, 4)).collect::<Vec<_>>());
        assert_eq!(quantise_penalty(300, 4), 19);
        assert_eq!(quantise_penalty(300, 0), 300);
    }

    #[test]
    fn costs_are_scaled_to_fit_u16() {
        assert_eq!(cost_shift(100, 50), 0);
        let shift = cost_shift(81 * 255, 500);
        assert!(8 * (((81 * 255) >> shift) + 500) < 65_535);
    }

    #[test]
    fn costs_made_band_by_band_give_the_stored_volume_s_sums_and_winners() {
        use crate::cost::PixelCost;
        use crate::fusion::Fusion;
        use crate::volume::{CostSpec, Neighbour, Problem};
        use crate::{Image, rng::SplitMix64};
        // 600 columns on three workers (200 each) and 150 rows: made bands of 64 rows end
        // inside the image going down and going up.
        let (w, h) = (600, 150);
        let mut rng = SplitMix64::new(5);
        let texture: Vec<u8> = (0..(w + 40) * h).map(|_| (rng.next_u64() >> 56) as u8).collect();
        let view = |shift: [i32; 2]| {
            let data = (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as i32 + 20 + 5 * shift[0], (i / w) as i32 + 5 * shift[1]);
                    texture[y.clamp(0, h as i32 - 1) as usize * (w + 40) + x as usize]
                })
                .collect();
            Image::gray(w, h, data).unwrap_or_else(|e| panic!("{e}"))
        };
        let neighbour = |role: &str, offset: [i32; 2]| Neighbour {
            role: role.into(),
            image: view(offset),
            offset,
            baseline_ratio: 1.0,
        };
        let problem = Problem {
            reference: view([0, 0]),
            neighbours: vec![
                neighbour("left", [-1, 0]),
                neighbour("right", [1, 0]),
                neighbour("top", [0, -1]),
            ],
            min_disparity: -3,
            num_disparities: 20,
        };
        let spec = CostSpec {
            pixel: PixelCost::Census {
                radius: 3,
                symmetric: false,
            },
            block_radius_px: 3,
        };
        let prepared = PreparedProblem::new(&problem, spec, Fusion::Heuristic).unwrap_or_else(|e| panic!("{e}"));
        let shift = quantisation_shift(spec.max_cost());
        let penalties = (quantise_penalty(300, shift), quantise_penalty(3000, shift));
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap_or_else(|e| panic!("{e}"));
        pool.install(|| {
            let stored = prepared.fused_volume(shift, &|| {});
            let expected = aggregate_volume(&stored, penalties.0, penalties.1);
            // A reused buffer full of other numbers, and a new one.
            for reuse in [vec![7u16; expected.data.len()], Vec::new()] {
                let made = aggregate_prepared(&prepared, shift, penalties, reuse, &|| {});
                assert_eq!(made.shape(), expected.shape());
                assert_eq!(
                    (made.min_disparity, made.max_cost),
                    (expected.min_disparity, expected.max_cost)
                );
                assert!(made.data == expected.data, "sums differ");
            }
            let fit = Some(SubpixelFit::Equiangular);
            let (disparity, confidence) = select_prepared(&prepared, shift, penalties, fit, true, &|_| {});
            // Without the confidence: the same winners, none rated.
            let (unrated, zeros) = select_prepared(&prepared, shift, penalties, fit, false, &|_| {});
            assert!(unrated == disparity && zeros.iter().all(|&c| c == 0.0));
            let (expected_disparity, expected_confidence) = select_volume(&stored, penalties, fit);
            assert!(disparity == expected_disparity && confidence == expected_confidence);
            // The scene: a plane at 5 px.
            let inside = disparity[75 * w + 300];
            assert!((inside - 5.0).abs() < 0.5, "{inside}");
        });
    }
}
