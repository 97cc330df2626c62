//! The fused cost volume, computed in bands of rows (in parallel), never holding one full volume
//! per neighbour: per band, each neighbour's costs are aggregated over the block and fused
//! straight into the caller's buffer (`[y][x][d]`, `u16`).

use std::ops::Range;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::FuseError;
use crate::cost::{
    MAX_BLOCK_RADIUS, MAX_CENSUS_RADIUS, PixelCost, PreparedView, box_sum_row, mark_invalid, pixel_cost_row,
    resample_disparity_axis,
};
use crate::fusion::{Fusion, fuse_rows};
use crate::image::Image;
use crate::lines::{SearchLines, pixel_cost_row_lines};

/// Rows per band of parallel work.
pub const BAND_ROWS: usize = 32;
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

/// What a method gets: the reference view, its neighbours and the disparity search range.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    /// The reference (centre) view (grey or RGB).
    pub reference: Image,
    /// Neighbours at one baseline (or grid offsets) from the reference.
    pub neighbours: Vec<Neighbour>,
    /// Smallest disparity searched (px).
    pub min_disparity: usize,
    /// Number of disparities searched.
    pub num_disparities: usize,
}

impl Problem {
    /// Checks sizes, offsets and the search range.
    pub fn validate(&self) -> Result<(), FuseError> {
        if self.neighbours.is_empty() {
            return Err(FuseError::NoNeighbours);
        }
        if self.num_disparities == 0 || self.num_disparities > 1024 {
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

/// The data term: pixel cost and aggregation block.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CostSpec {
    /// Per-pixel dissimilarity.
    pub pixel: PixelCost,
    /// Aggregation block radius ρ: costs are summed over `(2ρ+1)²` pixels.
    pub block_radius: usize,
}

impl CostSpec {
    /// Checks the radii.
    pub fn validate(&self) -> Result<(), FuseError> {
        if self.block_radius > MAX_BLOCK_RADIUS {
            return Err(FuseError::Config {
                field: "block_radius",
                value: self.block_radius.to_string(),
                reason: "must be ≤ 7 (costs are u16)",
            });
        }
        if let PixelCost::Census { radius } = self.pixel
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
            PixelCost::Census { radius } => ((2 * radius + 1) * (2 * radius + 1) - 1) as u32,
        };
        let side = 2 * self.block_radius as u32 + 1;
        per_pixel * side * side
    }
}

/// Bands handed to each worker at once, so that rayon creates each worker's buffers once per
/// worker rather than once per split (its `for_each_init` may call `init` per split).
pub fn bands_per_worker(height: usize) -> usize {
    height
        .div_ceil(BAND_ROWS)
        .div_ceil(rayon::current_num_threads().max(1) * 2)
        .max(1)
}

/// Buffers of one band worker, reused from band to band.
#[derive(Debug, Default)]
pub struct BandScratch {
    pixel_row: Vec<u16>,
    horizontal: Vec<Vec<u16>>,
    vertical: Vec<Vec<u16>>,
    finished: Vec<Vec<u16>>,
    resample: Vec<u16>,
}

/// A neighbour prepared for one cost.
struct PreparedNeighbour {
    view: PreparedView,
    offset: [i32; 2],
    baseline_ratio: f32,
    /// Samples in search-line order (axis neighbours); `None` uses the generic cost loop.
    lines: Option<SearchLines>,
}

/// A problem with its views prepared for one cost.
pub struct PreparedProblem {
    reference: PreparedView,
    neighbours: Vec<PreparedNeighbour>,
    width: usize,
    height: usize,
    min_disparity: usize,
    disparities: usize,
    spec: CostSpec,
    fusion: Fusion,
}

impl PreparedProblem {
    /// Prepares the views a fusion needs (census codes, BT interpolants).
    pub fn new(problem: &Problem, spec: CostSpec, fusion: Fusion) -> Result<Self, FuseError> {
        problem.validate()?;
        spec.validate()?;
        let neighbours = problem
            .neighbours_for(fusion)
            .into_par_iter()
            .map(|n| {
                let view = PreparedView::new(n.image.clone(), spec.pixel);
                let max_disparity = problem.min_disparity + problem.num_disparities;
                // A resampled neighbour reads up to ratio × the range.
                let reach = (max_disparity as f32 * n.baseline_ratio.max(1.0)).ceil() as usize + 1;
                let lines = SearchLines::new(&view, spec.pixel, n.offset, reach);
                PreparedNeighbour {
                    view,
                    offset: n.offset,
                    baseline_ratio: n.baseline_ratio,
                    lines,
                }
            })
            .collect();
        Ok(Self {
            reference: PreparedView::new(problem.reference.clone(), spec.pixel),
            neighbours,
            width: problem.reference.width,
            height: problem.reference.height,
            min_disparity: problem.min_disparity,
            disparities: problem.num_disparities,
            spec,
            fusion,
        })
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
    pub fn disparities(&self) -> usize {
        self.disparities
    }

    /// Fused, aggregated costs of `rows` into `out` (`rows.len() × width × disparities`).
    pub fn fused_band(&self, rows: Range<usize>, out: &mut [u16]) {
        self.fused_band_with(rows, out, &mut BandScratch::default());
    }

    /// [`Self::fused_band`] reusing a worker's buffers (no fresh pages per band).
    pub fn fused_band_with(&self, rows: Range<usize>, out: &mut [u16], buffers: &mut BandScratch) {
        let (w, nd, r) = (self.width, self.disparities, self.spec.block_radius);
        let row_len = w * nd;
        let ext = rows.start.saturating_sub(r)..(rows.end + r).min(self.height);
        let k_count = self.neighbours.len();
        let BandScratch {
            pixel_row,
            horizontal,
            vertical,
            finished,
            resample,
        } = buffers;
        pixel_row.resize(row_len, 0);
        horizontal.resize_with(k_count, Vec::new);
        vertical.resize_with(k_count, Vec::new);
        finished.resize_with(k_count, Vec::new);
        // Horizontally aggregated rows of the extended band, per neighbour.
        for (neighbour, rows_h) in self.neighbours.iter().zip(horizontal.iter_mut()) {
            rows_h.resize(ext.len() * row_len, 0);
            for (i, y) in ext.clone().enumerate() {
                match &neighbour.lines {
                    Some(lines) => pixel_cost_row_lines(
                        self.spec.pixel,
                        &self.reference,
                        lines,
                        y,
                        self.min_disparity,
                        nd,
                        pixel_row,
                    ),
                    None => pixel_cost_row(
                        self.spec.pixel,
                        &self.reference,
                        &neighbour.view,
                        neighbour.offset,
                        y,
                        self.min_disparity,
                        nd,
                        pixel_row,
                    ),
                }
                box_sum_row(pixel_row, &mut rows_h[i * row_len..(i + 1) * row_len], w, nd, r);
            }
        }
        let clamp_row = |y: isize| (y.clamp(0, self.height as isize - 1) as usize) - ext.start;
        for (rows_h, acc) in horizontal.iter().zip(vertical.iter_mut()) {
            acc.clear();
            acc.resize(row_len, 0);
            for y in rows.start as isize - r as isize..=rows.start as isize + r as isize {
                let source = &rows_h[clamp_row(y) * row_len..(clamp_row(y) + 1) * row_len];
                for (a, v) in acc.iter_mut().zip(source) {
                    *a = a.wrapping_add(*v);
                }
            }
        }
        for f in finished.iter_mut() {
            f.resize(row_len, 0);
        }
        for (i, y) in rows.clone().enumerate() {
            for (k, neighbour) in self.neighbours.iter().enumerate() {
                let finished_k = &mut finished[k];
                finished_k.copy_from_slice(&vertical[k]);
                resample_disparity_axis(finished_k, self.min_disparity, nd, neighbour.baseline_ratio, resample);
                mark_invalid(
                    finished_k,
                    neighbour.offset,
                    y,
                    (w, self.height),
                    (self.min_disparity, nd),
                    neighbour.baseline_ratio,
                );
                if y + 1 == rows.end {
                    continue;
                }
                // Slide the vertical window down by one row.
                let rows_h = &horizontal[k];
                let incoming = clamp_row(y as isize + r as isize + 1);
                let outgoing = clamp_row(y as isize - r as isize);
                let inc = &rows_h[incoming * row_len..(incoming + 1) * row_len];
                let out_row = &rows_h[outgoing * row_len..(outgoing + 1) * row_len];
                for ((a, v), o) in vertical[k].iter_mut().zip(inc).zip(out_row) {
                    *a = a.wrapping_add(*v).wrapping_sub(*o);
                }
            }
            let refs: Vec<&[u16]> = finished.iter().map(Vec::as_slice).collect();
            fuse_rows(self.fusion, &refs, &mut out[i * row_len..(i + 1) * row_len]);
        }
    }

    /// The whole fused volume `[y][x][d]` (for global optimisers), computed band-parallel.
    pub fn fused_volume(&self, on_band: &(dyn Fn() + Sync)) -> Vec<u16> {
        let row_len = self.width * self.disparities;
        let mut volume = vec![0u16; self.height * row_len];
        volume
            .par_chunks_mut(BAND_ROWS * row_len)
            .enumerate()
            .with_min_len(bands_per_worker(self.height))
            .for_each_init(BandScratch::default, |buffers, (band, chunk)| {
                let start = band * BAND_ROWS;
                let rows = start..start + chunk.len() / row_len;
                self.fused_band_with(rows, chunk, buffers);
                on_band();
            });
        volume
    }
}
