//! The fused cost volume, computed in bands of rows (in parallel) and, within a band, in tiles of
//! columns, never holding one full volume per neighbour: per tile row, each neighbour's costs are
//! aggregated over the block and fused, and the fused row is handed to the caller (`[x][d]`,
//! `u16`), who keeps it (SGM) or picks the winners straight away (block matching).

use std::ops::Range;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::{
    DisparityResampler, MAX_BLOCK_RADIUS, MAX_CENSUS_RADIUS, PixelCost, PreparedView, ValidDisparities, pixel_cost_tile,
};
use crate::fusion::{Fusion, SideRule, fuse_rows};
use crate::image::Image;
use crate::lines::{SearchLines, pixel_cost_tile_lines};
use crate::sgm::quantise_into;

/// The role a stereo method matches against when the set has it.
pub const STEREO_ROLE: &str = "right";

/// A neighbour view of a multiscopic set.
#[derive(Debug, Clone, PartialEq)]
pub struct Neighbour {
    /// Role (`left`, `right`, `top`, …).
    pub role: String,
    /// Image (grey or RGB), same size and channels as the reference.
    pub image: Image,
    /// Position in baselines along the reference camera's x (right) and y (down).
    pub offset: [i32; 2],
    /// Real baseline along the offset ÷ nominal (1 for an ideal rig): its costs are resampled
    /// along the disparity axis so that every neighbour agrees on one disparity.
    pub baseline_ratio: f32,
}

impl Neighbour {
    /// How many baselines out it sits: its offset's larger component (a line's `left2` 2, a
    /// grid's diagonal 1).
    pub fn reach(&self) -> i32 {
        self.offset[0].abs().max(self.offset[1].abs())
    }

    /// Whether it sits on the x or the y axis (not the reference, not a diagonal).
    pub fn on_axis(&self) -> bool {
        (self.offset[0] == 0) != (self.offset[1] == 0)
    }
}

/// A plane seen from a cross of four neighbours (tests): the reference `view([0, 0])` and each
/// neighbour `view(offset)` (the view one baseline along `offset`, which the caller shifts by
/// its plane's disparity), searched over `0..num_disparities`.
#[cfg(test)]
pub(crate) fn plane_of_cross(view: impl Fn([i32; 2]) -> Image, num_disparities: usize) -> Problem {
    Problem {
        reference: view([0, 0]),
        neighbours: [
            ("left", [-1, 0]),
            ("right", [1, 0]),
            ("top", [0, -1]),
            ("bottom", [0, 1]),
        ]
        .into_iter()
        .map(|(role, offset)| Neighbour {
            role: role.into(),
            image: view(offset),
            offset,
            baseline_ratio: 1.0,
        })
        .collect(),
        min_disparity: 0,
        num_disparities,
    }
}

/// A fronto-parallel plane at disparity `d` seen from views along x (tests): the reference
/// `view(0)` and, per `(role, k)`, the view `k` baselines away, `view(k · d)`; disparities
/// searched from 0.
#[cfg(test)]
pub(crate) fn plane_along_x(
    view: impl Fn(i64) -> Image,
    roles: &[(&str, i64)],
    d: i64,
    num_disparities: usize,
) -> Problem {
    Problem {
        reference: view(0),
        neighbours: roles
            .iter()
            .map(|&(role, k)| Neighbour {
                role: role.into(),
                image: view(k * d),
                offset: [k as i32, 0],
                baseline_ratio: 1.0,
            })
            .collect(),
        min_disparity: 0,
        num_disparities,
    }
}

/// What a method gets: the reference view, its neighbours and the disparity search range.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    /// The reference (centre) view (grey or RGB).
    pub reference: Image,
    /// Neighbours at one baseline (or grid offsets) from the reference.
    pub neighbours: Vec<Neighbour>,
    /// Smallest disparity searched (px); negative for a converged rig, whose views' optical axes
    /// meet in front of the camera (points beyond that distance shift the other way).
    pub min_disparity: i32,
    /// Number of disparities searched.
    pub num_disparities: usize,
}

impl Problem {
    /// The same problem on the views' luma ([`Image::to_gray`]), the views converted in parallel.
    pub fn to_gray(&self) -> Self {
        let mut images: Vec<Image> = std::iter::once(&self.reference)
            .chain(self.neighbours.iter().map(|n| &n.image))
            .collect::<Vec<_>>()
            .par_iter()
            .map(|image| image.to_gray())
            .collect();
        let neighbours = self
            .neighbours
            .iter()
            .zip(images.drain(1..))
            // Field by field: `..n.clone()` would copy the colour image only to drop it.
            .map(|(n, image)| Neighbour {
                role: n.role.clone(),
                image,
                offset: n.offset,
                baseline_ratio: n.baseline_ratio,
            })
            .collect();
        Self {
            reference: images.swap_remove(0),
            neighbours,
            min_disparity: self.min_disparity,
            num_disparities: self.num_disparities,
        }
    }

    /// The neighbours as errors name them: `role [dx, dy]`, comma-separated.
    pub fn neighbour_list(&self) -> String {
        self.neighbours
            .iter()
            .map(|n| format!("{} {:?}", n.role, n.offset))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// One past the largest disparity searched.
    pub fn end_disparity(&self) -> i32 {
        self.min_disparity
            .saturating_add(i32::try_from(self.num_disparities).unwrap_or(i32::MAX))
    }

    /// Checks sizes, offsets and the search range.
    pub fn validate(&self) -> Result<(), FuseError> {
        if self.neighbours.is_empty() {
            return Err(FuseError::NoNeighbours);
        }
        if self.num_disparities == 0 || self.num_disparities > 1024 || self.min_disparity.unsigned_abs() > 1 << 20 {
            return Err(FuseError::DisparityRange {
                min_disparity: self.min_disparity,
                num_disparities: self.num_disparities,
            });
        }
        for n in &self.neighbours {
            if (n.image.width, n.image.height, n.image.channels)
                != (self.reference.width, self.reference.height, self.reference.channels)
            {
                return Err(FuseError::SizeMismatch {
                    role: n.role.clone(),
                    width: n.image.width,
                    height: n.image.height,
                    reference_width: self.reference.width,
                    reference_height: self.reference.height,
                });
            }
            if n.offset == [0, 0] || !(n.baseline_ratio.is_finite() && n.baseline_ratio > 0.0) {
                return Err(FuseError::ZeroOffset { role: n.role.clone() });
            }
        }
        Ok(())
    }

    /// The neighbours a fusion uses: one for stereo (`right` if present), all otherwise.
    pub fn neighbours_for(&self, fusion: Fusion) -> Vec<&Neighbour> {
        match fusion {
            Fusion::Stereo => self
                .neighbours
                .iter()
                .find(|n| n.role == STEREO_ROLE)
                .or_else(|| self.neighbours.first())
                .into_iter()
                .collect(),
            _ => self.neighbours.iter().collect(),
        }
    }
}

/// What a [`CostVolume`] holds the costs of.
#[derive(Debug, Clone, PartialEq)]
pub enum VolumeSource {
    /// One neighbour's costs against the reference.
    Neighbour {
        /// Role.
        role: String,
        /// Grid offset.
        offset: [i32; 2],
    },
    /// The neighbours' costs fused by a rule.
    Fused(Fusion),
}

/// A cost volume of the reference view, `[y][x][d]` (disparity fastest): one neighbour's or the
/// fused costs, block-aggregated or aggregated along SGM's paths, quantised to bytes (`u8`,
/// [`crate::sgm::INVALID_QUANTISED`] where the correspondence leaves the neighbour), summed
/// (`u16`) or normalised. SGM, MFuseNet (inference and training) and the viewer take volumes
/// of this type; graph cuts keep their data term in label-major planes for their moves. Rows of
/// it (`[x][d]`) are what the streaming kernels (fused bands, winner-take-all) pass around.
#[derive(Debug, Clone, PartialEq)]
pub struct CostVolume<T> {
    /// Width of the reference view.
    pub width: usize,
    /// Height of the reference view.
    pub height: usize,
    /// Disparity of the first slice (signed).
    pub min_disparity: i32,
    /// Disparities per pixel.
    pub num_disparities: usize,
    /// `height × width × disparities` costs.
    pub data: Vec<T>,
    /// Largest valid cost.
    pub max_cost: u32,
    /// Whose costs these are.
    pub source: VolumeSource,
}

impl<T> CostVolume<T> {
    /// `[height, width, num_disparities]`, the order of [`CostVolume::data`].
    pub fn shape(&self) -> [usize; 3] {
        [self.height, self.width, self.num_disparities]
    }

    /// A volume of the same pixels, disparities and source holding `data` (e.g. this volume's
    /// costs aggregated or normalised), whose largest valid cost is `max_cost`.
    pub fn with_data<U>(&self, data: Vec<U>, max_cost: u32) -> CostVolume<U> {
        CostVolume {
            width: self.width,
            height: self.height,
            min_disparity: self.min_disparity,
            num_disparities: self.num_disparities,
            data,
            max_cost,
            source: self.source.clone(),
        }
    }

    /// The costs of pixel `(x, y)` over the disparities.
    pub fn costs(&self, x: usize, y: usize) -> &[T] {
        let at = (y * self.width + x) * self.num_disparities;
        &self.data[at..at + self.num_disparities]
    }
}

impl CostVolume<u8> {
    /// A neighbour's byte volume of `width × height` pixels and `num_disparities` slices from
    /// `min_disparity`, whose cost at pixel `(x, y)` and slice `d` is `cost(x, y, d)` (synthetic
    /// volumes for tests and examples); largest valid cost 255.
    pub fn from_fn(
        [width, height, num_disparities]: [usize; 3],
        min_disparity: i32,
        (role, offset): (&str, [i32; 2]),
        mut cost: impl FnMut(usize, usize, usize) -> u8,
    ) -> Self {
        let mut data = Vec::with_capacity(width * height * num_disparities);
        for y in 0..height {
            for x in 0..width {
                data.extend((0..num_disparities).map(|d| cost(x, y, d)));
            }
        }
        Self {
            width,
            height,
            min_disparity,
            num_disparities,
            data,
            max_cost: 255,
            source: VolumeSource::Neighbour {
                role: role.to_owned(),
                offset,
            },
        }
    }
}

/// Costs stored one disparity plane after another, `[d][y][x]` (pixel fastest): the layout of
/// moves that visit one label at a time, as graph cuts' α-expansion does (which keeps its own
/// data term in this order, or computes it where it is read). The same metadata as a
/// [`CostVolume`]; [`CostVolume::to_planes`] and [`DisparityPlanes::to_volume`] are the only
/// transposes between the two.
#[derive(Debug, Clone, PartialEq)]
pub struct DisparityPlanes<T> {
    /// Width of the reference view.
    pub width: usize,
    /// Height of the reference view.
    pub height: usize,
    /// Disparity of the first plane (signed).
    pub min_disparity: i32,
    /// Planes.
    pub num_disparities: usize,
    /// `num_disparities × height × width` costs.
    pub data: Vec<T>,
    /// Largest valid cost.
    pub max_cost: u32,
}

impl<T: Copy> DisparityPlanes<T> {
    /// Planes all holding `value`.
    pub fn filled(
        (width, height): (usize, usize),
        (min_disparity, num_disparities): (i32, usize),
        value: T,
        max_cost: u32,
    ) -> Self {
        Self {
            width,
            height,
            min_disparity,
            num_disparities,
            data: vec![value; width * height * num_disparities],
            max_cost,
        }
    }

    /// The costs of plane `d` (`[y][x]`).
    pub fn plane(&self, d: usize) -> &[T] {
        let n = self.width * self.height;
        &self.data[d * n..(d + 1) * n]
    }

    /// The cost of pixel `p` (`y · width + x`) at plane `d`.
    #[inline]
    pub fn at(&self, p: usize, d: usize) -> T {
        self.data[d * self.width * self.height + p]
    }

    /// The same costs pixel-major, as a [`CostVolume`] of `source`.
    pub fn to_volume(&self, source: VolumeSource) -> CostVolume<T> {
        let (n, nd) = (self.width * self.height, self.num_disparities);
        CostVolume {
            width: self.width,
            height: self.height,
            min_disparity: self.min_disparity,
            num_disparities: nd,
            data: transposed(&self.data, nd, n),
            max_cost: self.max_cost,
            source,
        }
    }
}

/// `data` read as `rows × columns` (row-major), written column by column: the transpose
/// between pixel-major (`[p][d]`) and plane-major (`[d][p]`) costs.
fn transposed<T: Copy>(data: &[T], rows: usize, columns: usize) -> Vec<T> {
    (0..columns)
        .flat_map(|c| (0..rows).map(move |r| data[r * columns + c]))
        .collect()
}

impl<T: Copy> CostVolume<T> {
    /// The same costs plane by plane ([`DisparityPlanes`]).
    pub fn to_planes(&self) -> DisparityPlanes<T> {
        let (n, nd) = (self.width * self.height, self.num_disparities);
        DisparityPlanes {
            width: self.width,
            height: self.height,
            min_disparity: self.min_disparity,
            num_disparities: nd,
            data: transposed(&self.data, n, nd),
            max_cost: self.max_cost,
        }
    }
}

/// Each neighbour's block-aggregated costs as its own volume, quantised to bytes by `shift`
/// ([`crate::sgm::quantise`]), in the order of `neighbours`; `on_band` is called after each band.
pub fn neighbour_volumes(
    problem: &Problem,
    neighbours: &[&Neighbour],
    spec: CostSpec,
    shift: u32,
    on_band: &(dyn Fn() + Sync),
) -> Result<Vec<CostVolume<u8>>, FuseError> {
    neighbours
        .iter()
        .map(|n| {
            let single = Problem {
                reference: problem.reference.clone(),
                neighbours: vec![(*n).clone()],
                min_disparity: problem.min_disparity,
                num_disparities: problem.num_disparities,
            };
            // With one neighbour every fusion rule returns its costs.
            let prepared = PreparedProblem::new(&single, spec, Fusion::Min)?;
            let mut volume = prepared.fused_volume(shift, on_band);
            volume.source = VolumeSource::Neighbour {
                role: n.role.clone(),
                offset: n.offset,
            };
            Ok(volume)
        })
        .collect()
}

/// The data term: pixel cost and aggregation block.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CostSpec {
    /// Per-pixel dissimilarity.
    pub pixel: PixelCost,
    /// Aggregation block radius ρ: costs are summed over `(2ρ+1)²` pixels.
    pub block_radius_px: usize,
}

impl CostSpec {
    /// Checks the radii.
    pub fn validate(&self) -> Result<(), FuseError> {
        if self.block_radius_px > MAX_BLOCK_RADIUS {
            return Err(FuseError::Config {
                field: "block_radius_px",
                value: self.block_radius_px.to_string(),
                reason: "must be ≤ 7 (costs are u16)",
            });
        }
        if let PixelCost::Census { radius, .. } = self.pixel
            && !(1..=MAX_CENSUS_RADIUS).contains(&radius)
        {
            return Err(FuseError::Config {
                field: "census radius",
                value: radius.to_string(),
                reason: "must be 1..=3",
            });
        }
        Ok(())
    }

    /// Largest aggregated cost this spec can produce.
    pub fn max_cost(&self) -> u32 {
        let per_pixel = match self.pixel {
            PixelCost::AbsoluteDifference | PixelCost::BirchfieldTomasi => 255,
            // The symmetric census counts each of its half as many bits twice: the same range.
            PixelCost::Census { radius, .. } => ((2 * radius + 1) * (2 * radius + 1) - 1) as u32,
        };
        let side = 2 * self.block_radius_px as u32 + 1;
        per_pixel * side * side
    }
}

/// Cost cells (columns × disparities) per tile row: with the block's rows of pixel costs, the
/// column sums and the aggregated row of up to four neighbours, a tile's working set stays in a
/// 1 MiB L2 cache (about 0.75 MiB at radius 4: 96 columns at 128 disparities). Each tile computes
/// the pixel costs of `2ρ` columns beyond it: 8192 cells (64 columns, 12.5 % more pixel costs)
/// made block matching at 1080p × 128 about 10 % slower (docs/experiments.md, 2026-11-27).
const TILE_CELLS: usize = 12288;

/// Columns per tile for `disparities`.
fn tile_columns(num_disparities: usize) -> usize {
    (TILE_CELLS / num_disparities.max(1)).clamp(16, 1024)
}

/// Rows per band of parallel work for an image `height` rows high: a few bands per worker
/// (progress steps, load balance), tall enough that the 2ρ rows each band re-reads stay cheap.
pub fn band_rows(height: usize) -> usize {
    height
        .div_ceil(rayon::current_num_threads().max(1) * BANDS_PER_WORKER)
        .max(MIN_BAND_ROWS)
}

/// Bands per worker thread (see [`band_rows`]).
const BANDS_PER_WORKER: usize = 4;
/// Fewest rows per band.
const MIN_BAND_ROWS: usize = 32;

/// Buffers of one band worker, reused from tile to tile and band to band.
#[derive(Debug, Default)]
pub struct BandScratch {
    neighbours: Vec<NeighbourScratch>,
    fused: Vec<u16>,
    /// One combined row per side with several views (see [`crate::fusion::direction_groups`]).
    sides: Vec<Vec<u16>>,
}

/// One neighbour's tile buffers.
#[derive(Debug, Default)]
struct NeighbourScratch {
    /// Pixel costs of the last `2ρ+1` rows (`[x][d]`, tile plus ρ columns each side).
    rows: Vec<Vec<u8>>,
    /// Pixel costs of the incoming row.
    incoming: Vec<u8>,
    /// Vertical sums over the block's rows, per column and disparity.
    column_sums: Vec<u16>,
    /// Block sums of the tile's columns.
    aggregated: Vec<u16>,
    /// One pixel's costs while resampling.
    resample: Vec<u16>,
}

/// Where a neighbour's pixel costs are read from.
enum CostSource {
    /// Its samples in search-line order (axis neighbours), made straight from its image: no
    /// whole-image planes of the cost's samples are held (or faulted) besides.
    Lines(SearchLines),
    /// The prepared view, through the generic cost loop (diagonal neighbours).
    View(PreparedView),
}

/// A neighbour prepared for one cost.
struct PreparedNeighbour {
    offset: [i32; 2],
    source: CostSource,
    /// Resampling along the disparity axis (baseline ratio ≠ 1).
    resampler: Option<DisparityResampler>,
    /// Disparities whose correspondence stays inside the image.
    valid: ValidDisparities,
}

/// A problem with its views prepared for one cost.
pub struct PreparedProblem {
    reference: PreparedView,
    neighbours: Vec<PreparedNeighbour>,
    width: usize,
    height: usize,
    min_disparity: i32,
    num_disparities: usize,
    spec: CostSpec,
    fusion: Fusion,
    /// The neighbours by side for the heuristic (whose sides count once, by `side_rule`); one
    /// group per neighbour otherwise or when no two share a side.
    sides: Vec<Vec<usize>>,
    /// How a side's views become its cost ([`SideRule::Min`] unless [`Self::with_side_rule`]).
    side_rule: SideRule,
}

impl PreparedProblem {
    /// `self` with the views of each side made one cost by `rule`.
    #[must_use]
    pub fn with_side_rule(self, rule: SideRule) -> Self {
        Self {
            side_rule: rule,
            ..self
        }
    }

    /// Prepares the views a fusion needs (census codes, BT interpolants).
    pub fn new(problem: &Problem, spec: CostSpec, fusion: Fusion) -> Result<Self, FuseError> {
        problem.validate()?;
        spec.validate()?;
        let (reference, neighbours) = rayon::join(
            || PreparedView::new(problem.reference.clone(), spec.pixel),
            || Self::prepare_neighbours(problem, spec, fusion),
        );
        let offsets: Vec<[i32; 2]> = neighbours.iter().map(|n| n.offset).collect();
        let sides = if fusion == Fusion::Heuristic {
            crate::fusion::direction_groups(&offsets)
        } else {
            (0..offsets.len()).map(|i| vec![i]).collect()
        };
        Ok(Self {
            sides,
            side_rule: SideRule::Min,
            reference,
            neighbours,
            width: problem.reference.width,
            height: problem.reference.height,
            min_disparity: problem.min_disparity,
            num_disparities: problem.num_disparities,
            spec,
            fusion,
        })
    }

    fn prepare_neighbours(problem: &Problem, spec: CostSpec, fusion: Fusion) -> Vec<PreparedNeighbour> {
        problem
            .neighbours_for(fusion)
            .into_par_iter()
            .map(|n| {
                let end = problem.end_disparity();
                // A resampled neighbour reads up to ratio × the range.
                let scaled = |d: i32| (d as f32 * n.baseline_ratio.max(1.0)).ceil() as i32;
                let reach = scaled(problem.min_disparity).min(problem.min_disparity)..scaled(end) + 1;
                let source = match SearchLines::new(&n.image, spec.pixel, n.offset, reach) {
                    Some(lines) => CostSource::Lines(lines),
                    None => CostSource::View(PreparedView::new(n.image.clone(), spec.pixel)),
                };
                PreparedNeighbour {
                    offset: n.offset,
                    source,
                    resampler: DisparityResampler::new(
                        problem.min_disparity,
                        problem.num_disparities,
                        n.baseline_ratio,
                    ),
                    valid: ValidDisparities::new(
                        n.offset,
                        (problem.reference.width, problem.reference.height),
                        (problem.min_disparity, problem.num_disparities),
                        n.baseline_ratio,
                    ),
                }
            })
            .collect()
    }

    /// Image width.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Disparities per pixel.
    pub fn num_disparities(&self) -> usize {
        self.num_disparities
    }

    /// Disparity of the first slice.
    pub fn min_disparity(&self) -> i32 {
        self.min_disparity
    }

    /// How the neighbours' costs are fused.
    pub fn fusion(&self) -> Fusion {
        self.fusion
    }

    /// Pixel costs of one neighbour for reference row `y` (clamped into the image), columns `xs`.
    fn pixel_costs(&self, neighbour: &PreparedNeighbour, y: isize, xs: Range<isize>, out: &mut [u8]) {
        let y = y.clamp(0, self.height as isize - 1) as usize;
        match &neighbour.source {
            CostSource::Lines(lines) => pixel_cost_tile_lines(
                self.spec.pixel,
                &self.reference,
                lines,
                y,
                xs,
                self.min_disparity,
                self.num_disparities,
                out,
            ),
            CostSource::View(view) => pixel_cost_tile(
                self.spec.pixel,
                &self.reference,
                view,
                neighbour.offset,
                y,
                xs,
                self.min_disparity,
                self.num_disparities,
                out,
            ),
        }
    }

    /// Fused, block-aggregated costs of `rows`, handed to `sink(y, x_start, costs)` one tile row
    /// at a time (`costs` is `[x][d]` for columns `x_start ..`, disparity fastest).
    ///
    /// Works in tiles of columns so that everything between the pixel costs and the fused row
    /// stays in cache: per neighbour, the pixel costs of the block's last `2ρ+1` rows (bytes), their
    /// column sums (updated by the incoming and outgoing row), and the horizontal sums of those.
    pub fn fused_band_with(
        &self,
        rows: Range<usize>,
        buffers: &mut BandScratch,
        sink: &mut dyn FnMut(usize, usize, &[u16]),
    ) {
        self.fused_tile_with(rows, 0..self.width, buffers, sink);
    }

    /// [`Self::fused_band_with`] over the image's `columns` only (the same numbers there: a
    /// tile reads ρ columns beyond its edges, as inside the image).
    pub fn fused_tile_with(
        &self,
        rows: Range<usize>,
        columns: Range<usize>,
        buffers: &mut BandScratch,
        sink: &mut dyn FnMut(usize, usize, &[u16]),
    ) {
        let columns = columns.start.min(self.width)..columns.end.min(self.width);
        if rows.is_empty() || columns.is_empty() {
            return;
        }
        let (nd, r) = (self.num_disparities, self.spec.block_radius_px);
        let window = 2 * r + 1;
        let tile = tile_columns(nd);
        let BandScratch {
            neighbours,
            fused,
            sides,
        } = buffers;
        neighbours.resize_with(self.neighbours.len(), NeighbourScratch::default);
        for scratch in neighbours.iter_mut() {
            scratch.rows.resize_with(window, Vec::new);
        }
        // Virtual row `v` (may lie outside the image) lives in ring slot `(v − first) mod window`.
        let first = rows.start as isize - r as isize;
        let slot = |v: isize| (v - first) as usize % window;
        for x_start in columns.clone().step_by(tile) {
            let columns = tile.min(columns.end - x_start);
            let xs = x_start as isize - r as isize..(x_start + columns + r) as isize;
            let ext_cells = xs.len() * nd;
            let cells = columns * nd;
            for (scratch, neighbour) in neighbours.iter_mut().zip(&self.neighbours) {
                scratch.column_sums.clear();
                scratch.column_sums.resize(ext_cells, 0);
                scratch.incoming.resize(ext_cells, 0);
                scratch.aggregated.resize(cells, 0);
                // The block's first 2ρ rows.
                for v in first..first + 2 * r as isize {
                    let row = &mut scratch.rows[slot(v)];
                    row.resize(ext_cells, 0);
                    self.pixel_costs(neighbour, v, xs.clone(), row);
                    for (sum, cost) in scratch.column_sums.iter_mut().zip(row.iter()) {
                        *sum += u16::from(*cost);
                    }
                }
            }
            for y in rows.clone() {
                let incoming_row = y as isize + r as isize;
                let outgoing_present = y > rows.start;
                for (scratch, neighbour) in neighbours.iter_mut().zip(&self.neighbours) {
                    let NeighbourScratch {
                        rows: ring,
                        incoming,
                        column_sums,
                        aggregated,
                        resample,
                    } = scratch;
                    // (The buffer swapped in from the ring may be sized for another tile.)
                    incoming.resize(ext_cells, 0);
                    self.pixel_costs(neighbour, incoming_row, xs.clone(), incoming);
                    let outgoing = &mut ring[slot(incoming_row)];
                    if outgoing_present {
                        for ((sum, new), old) in column_sums.iter_mut().zip(incoming.iter()).zip(outgoing.iter()) {
                            *sum = sum.wrapping_add(u16::from(*new)).wrapping_sub(u16::from(*old));
                        }
                    } else {
                        for (sum, new) in column_sums.iter_mut().zip(incoming.iter()) {
                            *sum = sum.wrapping_add(u16::from(*new));
                        }
                    }
                    std::mem::swap(outgoing, incoming);
                    horizontal_block_sums(column_sums, aggregated, nd, r);
                    if let Some(resampler) = &neighbour.resampler {
                        resampler.apply(aggregated, resample);
                    }
                    neighbour.valid.mark(aggregated, (x_start, y));
                }
                fused.resize(cells, 0);
                if self.sides.len() < self.neighbours.len() {
                    // Several views on one side: the side's rule, then the rule across sides.
                    sides.resize_with(self.sides.len(), Vec::new);
                    for (side, members) in sides.iter_mut().zip(&self.sides) {
                        side.clear();
                        side.resize(cells, 0);
                        let rows: Vec<&[u16]> = members.iter().map(|k| &neighbours[*k].aggregated[..cells]).collect();
                        crate::fusion::fuse_side_rows(self.side_rule, &rows, side);
                    }
                    let sources: Vec<&[u16]> = sides.iter().map(Vec::as_slice).collect();
                    fuse_rows(self.fusion, &sources, fused, self.spec.max_cost());
                } else {
                    let sources: Vec<&[u16]> = neighbours.iter().map(|n| n.aggregated.as_slice()).collect();
                    fuse_rows(self.fusion, &sources, fused, self.spec.max_cost());
                }
                sink(y, x_start, fused);
            }
        }
    }

    /// Fused, aggregated costs of `rows` into `out` (`rows.len() × width × disparities`).
    pub fn fused_band(&self, rows: Range<usize>, out: &mut [u16]) {
        self.fused_band_into(rows, out, &mut BandScratch::default());
    }

    /// [`Self::fused_band`] reusing a worker's buffers.
    pub fn fused_band_into(&self, rows: Range<usize>, out: &mut [u16], buffers: &mut BandScratch) {
        let row_len = self.width * self.num_disparities;
        let (first, nd) = (rows.start, self.num_disparities);
        self.fused_band_with(rows, buffers, &mut |y, x_start, costs| {
            let at = (y - first) * row_len + x_start * nd;
            out[at..at + costs.len()].copy_from_slice(costs);
        });
    }

    /// The fused costs of `rows` × `columns` quantised to bytes by `shift`
    /// ([`crate::sgm::quantise`]) into `out` (`[y][x][d]` over the tile): the numbers of
    /// [`Self::fused_volume`] there, for consumers that make their costs band by band.
    pub fn fused_quantised_into(
        &self,
        rows: Range<usize>,
        columns: Range<usize>,
        shift: u32,
        out: &mut [u8],
        buffers: &mut BandScratch,
    ) {
        let (first_row, first_column, nd) = (rows.start, columns.start, self.num_disparities);
        let row_len = columns.len() * nd;
        self.fused_tile_with(rows, columns, buffers, &mut |y, x_start, costs| {
            let at = (y - first_row) * row_len + (x_start - first_column) * nd;
            quantise_into(costs, &mut out[at..at + costs.len()], shift);
        });
    }

    /// The largest valid cost of [`Self::fused_volume`] quantised by `shift`.
    pub fn quantised_max_cost(&self, shift: u32) -> u32 {
        (self.spec.max_cost() >> shift).min(u32::from(crate::sgm::INVALID_QUANTISED) - 1)
    }

    /// The whole fused volume `[y][x][d]` for global optimisers, quantised to bytes by `shift`
    /// ([`crate::sgm::quantise`]) and computed band-parallel; `on_band` is called after each band.
    pub fn fused_volume(&self, shift: u32, on_band: &(dyn Fn() + Sync)) -> CostVolume<u8> {
        let row_len = self.width * self.num_disparities;
        let band = band_rows(self.height);
        let nd = self.num_disparities;
        let mut volume = vec![0u8; self.height * row_len];
        volume.par_chunks_mut(band * row_len).enumerate().for_each_init(
            BandScratch::default,
            |buffers, (index, chunk)| {
                let start = index * band;
                let rows = start..start + chunk.len() / row_len;
                self.fused_band_with(rows, buffers, &mut |y, x_start, costs| {
                    let at = (y - start) * row_len + x_start * nd;
                    quantise_into(costs, &mut chunk[at..at + costs.len()], shift);
                });
                on_band();
            },
        );
        CostVolume {
            width: self.width,
            height: self.height,
            min_disparity: self.min_disparity,
            num_disparities: nd,
            data: volume,
            max_cost: self.quantised_max_cost(shift),
            source: VolumeSource::Fused(self.fusion),
        }
    }
}

/// Sums `2r+1` neighbouring columns of `column_sums` (`[x][d]`, `r` extra columns on each side)
/// into `out` (`[x][d]` for the inner columns).
fn horizontal_block_sums(column_sums: &[u16], out: &mut [u16], num_disparities: usize, r: usize) {
    let nd = num_disparities;
    let columns = out.len() / nd;
    let (first, rest) = out.split_at_mut(nd.min(out.len()));
    first.fill(0);
    for column in column_sums.chunks_exact(nd).take(2 * r + 1) {
        for (a, v) in first.iter_mut().zip(column) {
            *a = a.wrapping_add(*v);
        }
    }
    let mut previous: &[u16] = first;
    for (i, current) in rest.chunks_exact_mut(nd).enumerate().take(columns.saturating_sub(1)) {
        // Column i + 1: add column i + 1 + 2r of the extended tile, drop column i.
        let incoming = &column_sums[(i + 1 + 2 * r) * nd..(i + 2 + 2 * r) * nd];
        let outgoing = &column_sums[i * nd..(i + 1) * nd];
        for (((c, p), inc), out) in current.iter_mut().zip(previous).zip(incoming).zip(outgoing) {
            *c = p.wrapping_add(*inc).wrapping_sub(*out);
        }
        previous = current;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn planes_and_pixel_major_volumes_are_the_same_costs() {
        let (w, h, nd) = (5, 3, 4);
        let volume = CostVolume {
            width: w,
            height: h,
            min_disparity: -2,
            num_disparities: nd,
            data: (0..w * h * nd).map(|i| i as u16).collect(),
            max_cost: 999,
            source: VolumeSource::Fused(Fusion::Min),
        };
        let planes = volume.to_planes();
        for y in 0..h {
            for x in 0..w {
                for d in 0..nd {
                    assert_eq!(planes.at(y * w + x, d), volume.costs(x, y)[d]);
                    assert_eq!(planes.plane(d)[y * w + x], volume.costs(x, y)[d]);
                }
            }
        }
        assert_eq!(planes.to_volume(VolumeSource::Fused(Fusion::Min)), volume);
        assert_eq!((planes.min_disparity, planes.max_cost), (-2, 999));
    }
    use crate::cost::{INVALID_COST, mark_invalid};
    use crate::fusion::fuse_values;

    fn view(width: usize, height: usize, seed: usize) -> Image {
        let data = (0..width * height * 3)
            .map(|i| (((i / 3) % width) * 7 + ((i / 3) / width) * 13 + (i % 3) * 29 + seed * 31 + (i * i) % 17) as u8)
            .collect();
        Image::rgb(width, height, data).unwrap_or_else(|e| panic!("{e}"))
    }

    /// The fused costs by the definition: the block sum of clamped pixel costs, resampled,
    /// invalid outside the neighbour, fused.
    fn brute_force(problem: &Problem, spec: CostSpec, fusion: Fusion) -> Vec<u16> {
        let (w, h) = (problem.reference.width, problem.reference.height);
        let (min_d, nd, r) = (
            problem.min_disparity,
            problem.num_disparities,
            spec.block_radius_px as isize,
        );
        let reference = PreparedView::new(problem.reference.clone(), spec.pixel);
        let per_neighbour: Vec<Vec<u16>> = problem
            .neighbours_for(fusion)
            .into_iter()
            .map(|n| {
                let view = PreparedView::new(n.image.clone(), spec.pixel);
                // Pixel costs from `low` (0, or the range's start when negative).
                let low = min_d.min(0);
                let reach = ((min_d + nd as i32) as f32 * n.baseline_ratio.max(1.0)).ceil() as usize
                    + 1
                    + low.unsigned_abs() as usize;
                let mut pixel = vec![0u8; w * h * reach];
                for y in 0..h {
                    let row = &mut pixel[y * w * reach..(y + 1) * w * reach];
                    pixel_cost_tile(
                        spec.pixel,
                        &reference,
                        &view,
                        n.offset,
                        y,
                        0..w as isize,
                        low,
                        reach,
                        row,
                    );
                }
                let at = |x: isize, y: isize, d: i32| {
                    let (x, y) = (x.clamp(0, w as isize - 1) as usize, y.clamp(0, h as isize - 1) as usize);
                    u16::from(pixel[(y * w + x) * reach + (d - low) as usize])
                };
                let mut out = vec![0u16; w * h * nd];
                for y in 0..h {
                    for x in 0..w {
                        let cell = &mut out[(y * w + x) * nd..(y * w + x + 1) * nd];
                        for (d, c) in cell.iter_mut().enumerate() {
                            let mut sum = 0u16;
                            for dy in -r..=r {
                                for dx in -r..=r {
                                    sum += at(x as isize + dx, y as isize + dy, min_d + d as i32);
                                }
                            }
                            *c = sum;
                        }
                        if let Some(resampler) = DisparityResampler::new(min_d, nd, n.baseline_ratio) {
                            resampler.apply(cell, &mut Vec::new());
                        }
                        mark_invalid(cell, n.offset, (x, y), (w, h), (min_d, nd), n.baseline_ratio);
                    }
                }
                out
            })
            .collect();
        let offsets: Vec<[i32; 2]> = problem.neighbours_for(fusion).iter().map(|n| n.offset).collect();
        let sides = crate::fusion::direction_groups(&offsets);
        let mut scratch = Vec::new();
        (0..w * h * nd)
            .map(|i| {
                let values: Vec<u16> = per_neighbour.iter().map(|v| v[i]).collect();
                if fusion == Fusion::Heuristic {
                    crate::fusion::fuse_heuristic_by_side(&values, &sides, &mut scratch)
                } else {
                    fuse_values(fusion, &values)
                }
            })
            .collect()
    }

    #[test]
    fn tiled_bands_give_the_defined_fused_costs() {
        // 384 disparities make 32-column tiles: 70 columns are two full tiles and a partial one.
        let (w, h, nd) = (70, 19, 384);
        let neighbour = |role: &str, offset: [i32; 2], seed: usize, ratio: f32| Neighbour {
            role: role.into(),
            image: view(w, h, seed),
            offset,
            baseline_ratio: ratio,
        };
        let problem = |min_disparity| Problem {
            reference: view(w, h, 0),
            neighbours: vec![
                neighbour("left", [-1, 0], 1, 1.0),
                neighbour("right", [1, 0], 2, 1.07),
                neighbour("top", [0, -1], 3, 1.0),
                neighbour("top-right", [1, -1], 4, 0.95),
                // Twice the baseline on the right's side: the heuristic takes the side's minimum.
                neighbour("right2", [2, 0], 5, 1.0),
            ],
            min_disparity,
            num_disparities: nd,
        };
        assert_eq!(tile_columns(nd), 32);
        // A range from 1 and a signed one (a converged rig) reaching well under 0.
        for (problem, (spec, fusion)) in [problem(1), problem(-100)].iter().flat_map(|p| {
            [
                (
                    CostSpec {
                        pixel: PixelCost::BirchfieldTomasi,
                        block_radius_px: 2,
                    },
                    Fusion::Heuristic,
                ),
                (
                    CostSpec {
                        pixel: PixelCost::Census {
                            radius: 1,
                            symmetric: false,
                        },
                        block_radius_px: 1,
                    },
                    Fusion::Mean,
                ),
                (
                    CostSpec {
                        pixel: PixelCost::AbsoluteDifference,
                        block_radius_px: 0,
                    },
                    Fusion::Stereo,
                ),
            ]
            .map(|case| (p, case))
        }) {
            let expected = brute_force(problem, spec, fusion);
            assert!(expected.contains(&INVALID_COST) && expected.iter().any(|c| *c != INVALID_COST));
            let prepared = PreparedProblem::new(problem, spec, fusion).unwrap_or_else(|e| panic!("{e}"));
            // Bands of uneven heights, one scratch reused across them.
            let row_len = w * nd;
            let mut got = vec![0u16; w * h * nd];
            let mut scratch = BandScratch::default();
            for rows in [0..5, 5..6, 6..19] {
                let (a, b) = (rows.start * row_len, rows.end * row_len);
                prepared.fused_band_into(rows, &mut got[a..b], &mut scratch);
            }
            if let Some(i) = (0..got.len()).find(|i| got[*i] != expected[*i]) {
                let (pixel, d) = (i / nd, i % nd);
                panic!(
                    "{spec:?} {fusion:?} from {}: x {} y {} d {d}: got {} expected {}",
                    problem.min_disparity,
                    pixel % w,
                    pixel / w,
                    got[i],
                    expected[i]
                );
            }
            let quantised: Vec<u8> = expected.iter().map(|c| crate::sgm::quantise(*c, 2)).collect();
            assert!(
                prepared.fused_volume(2, &|| {}).data == quantised,
                "{spec:?} {fusion:?} volume"
            );
        }
    }
}
