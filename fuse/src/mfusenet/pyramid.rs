//! Coarse-to-fine MFuseNet for wide disparity ranges and large images (the paper's rig: 1920×1080
//! with 128 disparities): the networks were trained on 32 disparities, so a range far wider than
//! that is searched in two steps.
//!
//! 1. The set is reduced by an integer `factor` (box averages of `factor × factor` pixels, every
//!    view alike): disparities shrink by the same factor, so the network sees a range that fits
//!    its training ([`pyramid_factor_for`], [`downsampled`]).
//! 2. At full size, each pixel's disparity is the minimum of the neighbours' summed input costs
//!    (the network's own inputs, computed at full size) within a band of `± factor` px around the
//!    coarse answers of its 3 × 3 nearest coarse pixels (so that a depth edge may take either
//!    side), sub-pixel from the fit through those costs ([`band_minimum`]).
//!
//! Measured against the network over the whole range at full size in docs/experiments.md
//! ("Coarse to fine for wide ranges").

use crate::image::{DisparityImage, Image};
use crate::mfusenet::infer::refined;
use crate::volume::{CostVolume, Neighbour, Problem};
use crate::wta::{LockingCurve, SubpixelFit};

/// The disparities a reduced level is made to fit: the depth the shipped networks were
/// trained on.
pub const NETWORK_DISPARITIES: usize = 32;

/// The default widest range the network is run on at full size (within
/// [`DEFAULT_MAX_DIRECT_VOXELS`]); wider ranges go coarse to fine. The networks were trained on
/// 32–48 disparities; over 64 and 96 at full size they score as over 32 (Middlebury's dev scenes
/// 0.268, 0.269, 0.270 px).
pub const DEFAULT_MAX_DIRECT_DISPARITIES: usize = 96;

/// The default budget of the network at full size: the reference's pixels times the range's
/// disparities (32 M: 640×360 at 96 disparities, 960×540 at 61, 1280×720 at 34; not 1920×1080
/// at 16). Past it a reduced level costs little accuracy (a large image's parts are wide in
/// pixels: two 1080p captures over 32 disparities +1 % and +4 % AvgErr) for a third of the time
/// and half the memory (24 s and 1.58 GB at full size, over the 1.5 GB a 1080p set may take);
/// below it a reduced level loses parts a few pixels wide (the held-out `thin` crosses at
/// 640×360 over 64 disparities 0.392 px at full size, 0.419 at half size).
pub const DEFAULT_MAX_DIRECT_VOXELS: usize = 32_000_000;

/// The reduction for a `width × height` reference and a range of `num_disparities`: 1 (full size)
/// when the range is at most `max_direct` and `width · height · num_disparities` at most
/// `max_direct_voxels`, else the smallest integer (at least 2) that brings the range to at most
/// [`NETWORK_DISPARITIES`] (64 → 2, 96 → 3, 128 → 4).
pub fn pyramid_factor_for(
    (width, height): (usize, usize),
    num_disparities: usize,
    max_direct: usize,
    max_direct_voxels: usize,
) -> usize {
    let voxels = width.saturating_mul(height).saturating_mul(num_disparities);
    if num_disparities <= max_direct && voxels <= max_direct_voxels {
        1
    } else {
        num_disparities.div_ceil(NETWORK_DISPARITIES).max(2)
    }
}

/// `image` reduced by `factor`: each output pixel the mean of its `factor × factor` block (the
/// last row and column of blocks may be partial).
pub fn box_downsampled(image: &Image, factor: usize) -> Image {
    let factor = factor.max(1);
    let (w, h, c) = (image.width, image.height, image.channels);
    let (cw, ch) = (w.div_ceil(factor), h.div_ceil(factor));
    let mut data = vec![0u8; cw * ch * c];
    for cy in 0..ch {
        let rows = cy * factor..((cy + 1) * factor).min(h);
        for cx in 0..cw {
            let cols = cx * factor..((cx + 1) * factor).min(w);
            let count = (rows.len() * cols.len()) as u32;
            for k in 0..c {
                let sum: u32 = rows
                    .clone()
                    .flat_map(|y| cols.clone().map(move |x| (y * w + x) * c + k))
                    .map(|i| u32::from(image.data[i]))
                    .sum();
                data[(cy * cw + cx) * c + k] = ((sum + count / 2) / count) as u8;
            }
        }
    }
    Image {
        width: cw,
        height: ch,
        channels: c,
        data,
    }
}

/// The range `(first disparity, count)` covering `problem`'s at 1/`factor` size: its first
/// disparity rounded down, its last up.
pub fn reduced_range(problem: &Problem, factor: usize) -> (i32, usize) {
    let f = i32::try_from(factor.max(1)).unwrap_or(i32::MAX);
    let first = problem.min_disparity.div_euclid(f);
    let last =
        (problem.end_disparity() - 1).div_euclid(f) + i32::from((problem.end_disparity() - 1).rem_euclid(f) != 0);
    (first, usize::try_from(last - first + 1).unwrap_or(1))
}

/// The problem reduced by `factor`: every view box-averaged, the range [`reduced_range`].
pub fn downsampled(problem: &Problem, factor: usize) -> Problem {
    let (min_disparity, num_disparities) = reduced_range(problem, factor);
    Problem {
        reference: box_downsampled(&problem.reference, factor),
        neighbours: problem
            .neighbours
            .iter()
            .map(|n| Neighbour {
                image: box_downsampled(&n.image, factor),
                ..n.clone()
            })
            .collect(),
        min_disparity,
        num_disparities,
    }
}

/// How the full-size disparity is read in the band the coarse answer leaves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Band {
    /// The reduction the coarse answer was made at.
    pub factor: usize,
    /// Half the band's width around each coarse candidate (px at full size).
    pub half_width: f64,
    /// The sub-pixel fit through the summed costs at the chosen integer.
    pub fit: SubpixelFit,
    /// Its pixel-locking correction.
    pub locking: Option<LockingCurve>,
}

/// The full-size disparity (and the coarse confidence, nearest coarse pixel) from a coarse
/// answer: per pixel, the minimum of the summed input `costs` (`first` = the disparity of their
/// first slice) over the slices within `band.half_width` px of `factor ×` any finite coarse answer in
/// the 3 × 3 coarse pixels around it, refined by the fit there. A pixel without a finite coarse
/// answer nearby, or whose band misses the volumes, is `f32::INFINITY`.
pub fn band_minimum(
    coarse: &DisparityImage,
    costs: &CostVolume<u16>,
    first: i64,
    (width, height): (usize, usize),
    band: Band,
) -> DisparityImage {
    let nd = costs.num_disparities;
    let f = band.factor.max(1);
    let (cw, ch) = (coarse.width, coarse.height);
    let mut data = vec![f32::INFINITY; width * height];
    let mut confidence = vec![0.0f32; width * height];
    let mut allowed = vec![false; nd];
    for y in 0..height {
        let cy = (y / f).min(ch.saturating_sub(1));
        for x in 0..width {
            let cx = (x / f).min(cw.saturating_sub(1));
            let i = y * width + x;
            if let Some(c) = &coarse.confidence {
                confidence[i] = c[cy * cw + cx];
            }
            allowed.fill(false);
            let mut any = false;
            for ny in cy.saturating_sub(1)..(cy + 2).min(ch) {
                for nx in cx.saturating_sub(1)..(cx + 2).min(cw) {
                    let d = coarse.data[ny * cw + nx];
                    if !d.is_finite() {
                        continue;
                    }
                    let centre = f64::from(d) * f as f64 - first as f64;
                    let lo = (centre - band.half_width).ceil().max(0.0);
                    let hi = (centre + band.half_width).floor().min(nd as f64 - 1.0);
                    if lo > hi {
                        continue;
                    }
                    for a in &mut allowed[lo as usize..=hi as usize] {
                        *a = true;
                        any = true;
                    }
                }
            }
            if !any {
                continue;
            }
            let sums = costs.costs(x, y);
            let best = (0..nd).filter(|k| allowed[*k]).min_by_key(|k| sums[*k]).unwrap_or(0);
            let d = refined(best as f64, |k| f64::from(sums[k]), nd, 0.0, band.fit, band.locking);
            data[i] = (d + first as f64) as f32;
        }
    }
    DisparityImage {
        width,
        height,
        data,
        confidence: Some(confidence),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::VolumeSource;

    #[test]
    fn wide_ranges_are_brought_to_the_networks_depth() {
        // Without a volume budget only the range decides.
        let range_only =
            |num_disparities, max_direct| pyramid_factor_for((64, 48), num_disparities, max_direct, usize::MAX);
        assert_eq!(range_only(24, 48), 1);
        assert_eq!(range_only(48, 48), 1);
        assert_eq!(range_only(49, 48), 2);
        assert_eq!(range_only(64, 48), 2);
        assert_eq!(range_only(96, 48), 3);
        assert_eq!(range_only(128, 48), 4);
        assert_eq!(range_only(256, 48), 8);
        // No direct run at all: every range goes through a level of at least half size.
        assert_eq!(range_only(16, 0), 2);
    }

    #[test]
    fn the_network_runs_at_full_size_within_the_range_and_the_volume_budget() {
        let (range, budget) = (DEFAULT_MAX_DIRECT_DISPARITIES, DEFAULT_MAX_DIRECT_VOXELS);
        assert_eq!(pyramid_factor_for((640, 360), 16, range, budget), 1);
        assert_eq!(pyramid_factor_for((960, 540), 48, range, budget), 1);
        assert_eq!(pyramid_factor_for((640, 360), 64, range, budget), 1);
        assert_eq!(pyramid_factor_for((640, 360), 96, range, budget), 1);
        // Past the budget: a reduced level, at least half size.
        assert_eq!(pyramid_factor_for((1920, 1080), 16, range, budget), 2);
        assert_eq!(pyramid_factor_for((1920, 1080), 32, range, budget), 2);
        assert_eq!(pyramid_factor_for((960, 540), 64, range, budget), 2);
        assert_eq!(pyramid_factor_for((1920, 1080), 128, range, budget), 4);
        // Past the range, however small the image.
        assert_eq!(pyramid_factor_for((64, 48), 128, range, budget), 4);
        // No direct range, or no budget: never full size.
        assert_eq!(pyramid_factor_for((64, 48), 16, 0, budget), 2);
        assert_eq!(pyramid_factor_for((64, 48), 16, range, 0), 2);
    }

    #[test]
    fn a_box_average_keeps_a_constant_image_and_averages_partial_blocks() {
        let image = Image::gray(5, 3, (0..15).map(|i| (i * 10) as u8).collect()).unwrap_or_else(|e| panic!("{e}"));
        let small = box_downsampled(&image, 2);
        assert_eq!((small.width, small.height), (3, 2));
        // Blocks: {0,10,50,60} → 30; {20,30,70,80} → 50; {40,90} → 65; {100,110} → 105; …
        assert_eq!(small.data, vec![30, 50, 65, 105, 125, 140]);
        let flat = Image::gray(7, 7, vec![77; 49]).unwrap_or_else(|e| panic!("{e}"));
        assert!(box_downsampled(&flat, 3).data.iter().all(|v| *v == 77));
    }

    #[test]
    fn the_reduced_range_covers_the_requested_one_signed_or_not() {
        let problem = |min_disparity, num_disparities| Problem {
            reference: Image::gray(8, 8, vec![0; 64]).unwrap_or_else(|e| panic!("{e}")),
            neighbours: Vec::new(),
            min_disparity,
            num_disparities,
        };
        let range = |p: Problem| (p.min_disparity, p.num_disparities);
        // 0..128 at 1/4: 0..=32 (127/4 rounded up).
        assert_eq!(range(downsampled(&problem(0, 128), 4)), (0, 33));
        // −10..=53 at 1/2: −5..=27.
        assert_eq!(range(downsampled(&problem(-10, 64), 2)), (-5, 33));
        // −11..=52 at 1/3: −4 (−11/3 rounded down) ..= 18 (52/3 rounded up).
        assert_eq!(range(downsampled(&problem(-11, 64), 3)), (-4, 23));
    }

    #[test]
    fn the_band_finds_the_costs_minimum_near_the_coarse_answer_and_not_a_deeper_one_outside() {
        // 8 × 4 pixels, 40 slices from disparity 10; every pixel's costs have their deepest
        // minimum at slice 35 (disparity 45) and a shallower V at slice 21.4 (disparity 31.4).
        let (w, h, nd) = (8, 4, 40);
        let costs: Vec<u8> = (0..nd)
            .map(|k| {
                let v = (20.0 * (k as f64 - 21.4).abs()).min(200.0);
                if k == 35 { 0 } else { v as u8 + 10 }
            })
            .collect();
        let volume = CostVolume {
            width: w,
            height: h,
            min_disparity: 10,
            num_disparities: nd,
            data: (0..w * h).flat_map(|_| costs.clone()).collect(),
            max_cost: 255,
            source: VolumeSource::Neighbour {
                role: "right".into(),
                offset: [1, 0],
            },
        };
        // A coarse answer at half size: 15.5 → 31 px at full size.
        let coarse = DisparityImage {
            width: 4,
            height: 2,
            data: vec![15.5; 8],
            confidence: Some(vec![0.75; 8]),
        };
        let band = Band {
            factor: 2,
            half_width: 2.0,
            fit: SubpixelFit::Equiangular,
            locking: None,
        };
        let costs = crate::mfusenet::input::summed(&[volume]).unwrap_or_else(|| panic!("one volume"));
        let out = band_minimum(&coarse, &costs, 10, (w, h), band);
        for d in &out.data {
            assert!((d - 31.4).abs() < 0.05, "{d}");
        }
        assert_eq!(out.confidence, Some(vec![0.75; w * h]));
        // With the coarse answers unknown, so is every pixel.
        let unknown = DisparityImage {
            data: vec![f32::INFINITY; 8],
            ..coarse
        };
        let zero = CostVolume {
            width: w,
            height: h,
            min_disparity: 10,
            num_disparities: nd,
            data: vec![0u16; w * h * nd],
            max_cost: 255,
            source: VolumeSource::Fused(crate::fusion::Fusion::Mean),
        };
        assert!(
            band_minimum(&unknown, &zero, 10, (w, h), band)
                .data
                .iter()
                .all(|d| d.is_infinite())
        );
    }
}
