//! Next-best-view planning: which view, taken next, would resolve most of what the current depth
//! still lacks.
//!
//! The arm moves the camera in its own image plane, so a candidate view is a grid offset `o` (in
//! baselines along the reference camera's x and y). From the set's current disparity (px per
//! baseline), its confidence and the reference image, each reference pixel `p` scores a
//! candidate by
//!
//! `need(p) · visible(p) · texture(p) · resolution(p) · novelty(p)`:
//!
//! - **need**: `1 − confidence`, and 1 where no view taken so far sees the pixel (an occlusion
//!   whose depth is a guess);
//! - **visible**: the candidate would see the pixel, predicted from the current depth: it lands
//!   inside the image at `p − o·d(p)` and no nearer pixel covers it there (a scan along `o`);
//! - **texture**: the reference's texture *along* the offset, which is what a match along it
//!   can use (`e / (e + e₀)` of the windowed mean squared derivative along `o`): horizontal
//!   stripes give a horizontal baseline nothing and a vertical one everything;
//! - **resolution**: `|o|·d / (|o|·d + d½)`: a longer baseline resolves far surfaces better;
//! - **novelty**: a pixel already seen from the same direction counts [`PlanConfig::redundancy`]
//!   (another look from there adds little); one seen only from other directions counts fully
//!   (its occlusions and reflections move differently).
//!
//! A candidate whose disparities would not fit [`PlanInput::max_disparity_px`] (the widest
//! search the methods can afford: from the known working range's far end to its near end, or
//! from 0 to the estimate's largest) is not feasible. The gain is reported as pixels resolved (the sum)
//! and as a share of the image. Methods that need views in opposite pairs (MFuseNet's three- and
//! five-view networks) plan with [`LayoutRule::Pairs`]: a candidate is a pair `{o, −o}` on an
//! axis, scored by the pixels either member resolves.
//!
//! Where the arm can go is not this module's business: `record::reach` checks each candidate's
//! pose by inverse kinematics and against the table.

use rayon::prelude::*;
use serde::Serialize;

use crate::FuseError;

/// How candidates are grouped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum LayoutRule {
    /// Any single offset (methods that take any set of offsets: block matching, SGM, graph cuts).
    #[default]
    Free,
    /// Opposite pairs on an axis, `{o, −o}` (MFuseNet's networks take left and right, or top
    /// and bottom, at one baseline; a set whose offsets are all multiples of one is that
    /// multiple's baseline).
    Pairs,
}

impl LayoutRule {
    /// The rule a method's family needs: opposite pairs for MFuseNet's networks, any offset for
    /// the others (and for an unknown method).
    pub fn for_family(family: Option<crate::methods::Family>) -> Self {
        match family {
            Some(crate::methods::Family::MFuseNet) => Self::Pairs,
            _ => Self::Free,
        }
    }
}

/// The planner's settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlanConfig {
    /// Longest offset considered, in baselines (candidates: the 8 directions at 1 … this).
    pub max_offset: i32,
    /// How candidates are grouped.
    pub layout: LayoutRule,
    /// Mean squared derivative (grey levels² per px²) at which a pixel's texture along an offset
    /// counts half.
    pub texture_half: f32,
    /// Disparity (px) at which a pixel's depth resolution counts half.
    pub resolution_half_px: f32,
    /// What a pixel already seen from the candidate's direction counts.
    pub redundancy: f32,
    /// Radius (px) of the window the texture is averaged over (at the planning resolution).
    pub window_radius_px: usize,
    /// What a vertical candidate's expected pixels count against a horizontal one's: 1 for
    /// methods that match along either axis alike; MFuseNet plans with
    /// [`MFUSENET_VERTICAL_WEIGHT`] ([`PlanConfig::for_family`]).
    pub vertical_weight: f32,
    /// Wider inputs are planned on a box-averaged copy at most this wide (an integer factor
    /// smaller; the expected pixels are scaled back): planning needs the scene's layout, not its
    /// last pixel, and stays a small share of a method's time.
    pub max_width_px: usize,
}

impl Default for PlanConfig {
    fn default() -> Self {
        Self {
            max_offset: 2,
            layout: LayoutRule::Free,
            texture_half: 25.0,
            resolution_half_px: 4.0,
            redundancy: 0.35,
            window_radius_px: 3,
            vertical_weight: 1.0,
            max_width_px: 256,
        }
    }
}

/// [`PlanConfig::vertical_weight`] for MFuseNet: a vertical pair is taken first only where it
/// sees at least twice the texture. Its three-view network was trained on left/right pairs, and
/// on brushed or mirror-like metal, whose streaks run along the rows, the texture a vertical
/// baseline sees is mostly reflection that does not move with the surface: on the simulated
/// workpieces a top/bottom pair at twice the baseline errs by 3.5 px where a left/right pair
/// errs by 0.1 px, and MFuseNet's confidence does not tell (docs/experiments.md).
pub const MFUSENET_VERTICAL_WEIGHT: f32 = 0.5;

impl PlanConfig {
    /// The settings a method's family plans with: its [`LayoutRule::for_family`] and, for
    /// MFuseNet, [`MFUSENET_VERTICAL_WEIGHT`].
    pub fn for_family(family: Option<crate::methods::Family>) -> Self {
        let mfusenet = family == Some(crate::methods::Family::MFuseNet);
        Self {
            layout: LayoutRule::for_family(family),
            vertical_weight: if mfusenet { MFUSENET_VERTICAL_WEIGHT } else { 1.0 },
            ..Self::default()
        }
    }
}

/// What the planner looks at: the reference view and the set's current estimate.
#[derive(Debug, Clone, Copy)]
pub struct PlanInput<'a> {
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// Reference image, grey levels (`width × height`).
    pub luma: &'a [f32],
    /// Current disparity (px per baseline of grid offset); non-finite = no estimate.
    pub disparity_px: &'a [f32],
    /// Current confidence in [0, 1].
    pub confidence: &'a [f32],
    /// Offsets already taken (the reference excluded).
    pub taken: &'a [[i32; 2]],
    /// The widest disparity search (px, at the candidate's own offset) the methods can afford:
    /// a candidate is feasible when the disparities it would have to search fit, from the known
    /// range's far end to its near end ([`Self::expected_range_px`]) or else from 0 to the
    /// estimate's largest.
    pub max_disparity_px: f32,
    /// The disparities (px per baseline) of the farthest and nearest points the scene is known
    /// to span (a workcell's table and tallest part): with no estimate yet they stand in for the
    /// depth; they bound which baselines are feasible, and an estimate only narrows them.
    pub expected_range_px: Option<[f32; 2]>,
}

/// One scored candidate (a single offset, or an opposite pair under [`LayoutRule::Pairs`]).
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct Candidate {
    /// Grid offsets of the views to take (one, or a pair; a pair member already taken is left
    /// out).
    pub offsets: Vec<[i32; 2]>,
    /// Pixels the candidate is expected to resolve (sum of the per-pixel scores; a vertical
    /// candidate's times [`PlanConfig::vertical_weight`]).
    pub expected_pixels: f64,
    /// `expected_pixels` as a share of the image.
    pub gain: f64,
    /// Share of the pixels with an estimate the candidate would see.
    pub visible_share: f64,
    /// Mean texture term along the candidate's direction.
    pub texture: f64,
    /// Share of the needy pixels (need ≥ 0.5) that no view taken so far sees and this one would.
    pub reveals_share: f64,
    /// Whether the methods' search range covers the candidate's disparities.
    pub feasible: bool,
}

/// Errors of the planner's inputs.
fn check(input: &PlanInput<'_>) -> Result<(), FuseError> {
    let n = input.width * input.height;
    for (what, len) in [
        ("planner's image", input.luma.len()),
        ("planner's disparity", input.disparity_px.len()),
        ("planner's confidence", input.confidence.len()),
    ] {
        if len != n || n == 0 {
            return Err(FuseError::ImageSize {
                what,
                width: input.width,
                height: input.height,
                len,
            });
        }
    }
    Ok(())
}

/// The candidate offsets: the 8 directions (axes and diagonals) at 1 … `max_offset` baselines.
pub fn candidate_offsets(max_offset: i32) -> Vec<[i32; 2]> {
    let directions = [[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, -1], [1, -1], [-1, 1]];
    (1..=max_offset.max(1))
        .flat_map(|k| directions.iter().map(move |[x, y]| [k * x, k * y]))
        .collect()
}

/// The unit step and the multiple of an offset on the 8-direction grid (`None` for other offsets
/// such as `[2, 1]`).
fn direction(offset: [i32; 2]) -> Option<([i32; 2], i32)> {
    let [x, y] = offset;
    let k = x.abs().max(y.abs());
    if k == 0 || (x != 0 && y != 0 && x.abs() != y.abs()) {
        return None;
    }
    Some(([x.signum(), y.signum()], k))
}

/// Per pixel, whether a view at `offset` would see it, predicted from `disparity`: it lands in
/// the image at `p − offset·d(p)` and no pixel ahead of it along the offset's direction comes
/// nearer and covers it. Pixels without an estimate count as seen if they land in the image at
/// the median disparity.
pub fn visibility(width: usize, height: usize, disparity: &[f32], offset: [i32; 2]) -> Vec<bool> {
    visibility_with(width, height, disparity, offset, median_disparity(disparity))
}

/// The median of the finite disparities (0 when there are none).
fn median_disparity(disparity: &[f32]) -> f32 {
    let mut finite: Vec<f32> = disparity.iter().copied().filter(|d| d.is_finite()).collect();
    if finite.is_empty() {
        return 0.0;
    }
    let mid = finite.len() / 2;
    *finite.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// Share of the estimated pixels whose disparity may pass the "largest" one: a few outliers
/// (a mismatch on a mirror) must not rule a baseline out.
const LARGEST_DISPARITY_OUTLIERS: f64 = 0.005;

/// The largest of the finite disparities in magnitude, but for [`LARGEST_DISPARITY_OUTLIERS`] of
/// them (0 when there are none).
fn largest_disparity(disparity: &[f32]) -> f32 {
    let mut finite: Vec<f32> = disparity.iter().filter(|d| d.is_finite()).map(|d| d.abs()).collect();
    if finite.is_empty() {
        return 0.0;
    }
    let rank = ((finite.len() - 1) as f64 * (1.0 - LARGEST_DISPARITY_OUTLIERS)).round() as usize;
    *finite.select_nth_unstable_by(rank, f32::total_cmp).1
}

/// [`visibility`] with the disparity assumed where there is no estimate.
fn visibility_with(width: usize, height: usize, disparity: &[f32], offset: [i32; 2], fallback: f32) -> Vec<bool> {
    let mut visible = vec![false; width * height];
    let Some(([ux, uy], k)) = direction(offset) else {
        return visible;
    };
    let kf = k as f32;
    let inside = |x: usize, y: usize, d: f32| {
        let (tx, ty) = (x as f32 - (k * ux) as f32 * d, y as f32 - (k * uy) as f32 * d);
        tx >= 0.0 && ty >= 0.0 && tx <= (width - 1) as f32 && ty <= (height - 1) as f32
    };
    // Every line along the direction, walked from its far end (the side the direction points to)
    // back, keeping the largest `k·d(q) − step(q)` seen ahead: p is covered when it reaches
    // `k·d(p) − step(p)`.
    for start in line_starts(width, height, [ux, uy]) {
        let line: Vec<usize> = walk(width, height, start, [ux, uy]).collect();
        let mut ahead = f32::NEG_INFINITY;
        for (step, &p) in line.iter().enumerate().rev() {
            let d = disparity[p];
            let (x, y) = (p % width, p / width);
            if d.is_finite() {
                let key = kf * d - step as f32;
                // A tolerance of a fifth of a pixel, so that a plane does not hide itself.
                visible[p] = key + 0.2 > ahead && inside(x, y, d);
                ahead = ahead.max(key);
            } else {
                visible[p] = inside(x, y, fallback);
            }
        }
    }
    visible
}

/// The first pixel of every line of `direction` across the image (each pixel on exactly one line).
fn line_starts(width: usize, height: usize, [ux, uy]: [i32; 2]) -> Vec<(usize, usize)> {
    let mut starts = Vec::new();
    // A line starts where stepping back against the direction leaves the image.
    for y in 0..height {
        for x in 0..width {
            let (bx, by) = (x as i64 - i64::from(ux), y as i64 - i64::from(uy));
            if bx < 0 || by < 0 || bx >= width as i64 || by >= height as i64 {
                starts.push((x, y));
            }
        }
    }
    starts
}

/// Pixel indices from `start` along `direction` to the image's edge.
fn walk(width: usize, height: usize, start: (usize, usize), [ux, uy]: [i32; 2]) -> impl Iterator<Item = usize> {
    let (mut x, mut y) = (start.0 as i64, start.1 as i64);
    std::iter::from_fn(move || {
        if x < 0 || y < 0 || x >= width as i64 || y >= height as i64 {
            return None;
        }
        let p = y as usize * width + x as usize;
        x += i64::from(ux);
        y += i64::from(uy);
        Some(p)
    })
}

/// The windowed structure tensor of the image: per pixel the means of `gx²`, `gx·gy` and `gy²`
/// over a `(2r+1)²` window (central differences).
fn structure_tensor(width: usize, height: usize, luma: &[f32], r: usize) -> [Vec<f32>; 3] {
    let at =
        |x: i64, y: i64| luma[(y.clamp(0, height as i64 - 1) as usize) * width + x.clamp(0, width as i64 - 1) as usize];
    let mut products = [
        vec![0.0f32; width * height],
        vec![0.0; width * height],
        vec![0.0; width * height],
    ];
    for y in 0..height as i64 {
        for x in 0..width as i64 {
            let gx = 0.5 * (at(x + 1, y) - at(x - 1, y));
            let gy = 0.5 * (at(x, y + 1) - at(x, y - 1));
            let p = y as usize * width + x as usize;
            products[0][p] = gx * gx;
            products[1][p] = gx * gy;
            products[2][p] = gy * gy;
        }
    }
    products.map(|plane| box_mean(width, height, &plane, r))
}

/// Mean over a `(2r+1)²` window clipped to the image (summed-area table).
fn box_mean(width: usize, height: usize, values: &[f32], r: usize) -> Vec<f32> {
    let mut sums = vec![0.0f64; (width + 1) * (height + 1)];
    for y in 0..height {
        for x in 0..width {
            sums[(y + 1) * (width + 1) + x + 1] =
                f64::from(values[y * width + x]) + sums[y * (width + 1) + x + 1] + sums[(y + 1) * (width + 1) + x]
                    - sums[y * (width + 1) + x];
        }
    }
    let mut out = vec![0.0f32; width * height];
    for y in 0..height {
        let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(height));
        for x in 0..width {
            let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(width));
            let total = sums[y1 * (width + 1) + x1] - sums[y0 * (width + 1) + x1] - sums[y1 * (width + 1) + x0]
                + sums[y0 * (width + 1) + x0];
            out[y * width + x] = (total / ((y1 - y0) * (x1 - x0)) as f64) as f32;
        }
    }
    out
}

/// What the planner computes once per input: per pixel need, the taken views' visibility (and
/// directions, in the same order) and whether any of them sees it, the texture tensor, and the
/// median disparity and the span a search must cover.
struct Prepared {
    need: Vec<f32>,
    seen_from: Vec<Vec<bool>>,
    taken_directions: Vec<Option<[i32; 2]>>,
    hidden: Vec<bool>,
    tensor: [Vec<f32>; 3],
    median_disparity: f32,
    /// The disparity of pixels without an estimate, for their resolution term (from
    /// [`PlanInput::expected_range_px`] before anything is measured).
    assumed_disparity: Option<f32>,
    /// The disparities (px per baseline) a search must span: the known range's (narrowed by
    /// the estimate), else 0 … the estimate's largest ([`largest_disparity`]).
    search_span: f32,
}

fn prepare(input: &PlanInput<'_>, config: &PlanConfig) -> Prepared {
    let (w, h) = (input.width, input.height);
    let median_disparity = median_disparity(input.disparity_px);
    let seen_from: Vec<Vec<bool>> = input
        .taken
        .iter()
        .map(|o| visibility_with(w, h, input.disparity_px, *o, median_disparity))
        .collect();
    let hidden: Vec<bool> = (0..w * h).map(|p| !seen_from.iter().any(|v| v[p])).collect();
    let need = (0..w * h)
        .map(|p| {
            if hidden[p] || !input.disparity_px[p].is_finite() {
                1.0
            } else {
                1.0 - input.confidence[p].clamp(0.0, 1.0)
            }
        })
        .collect();
    let measured = input.disparity_px.iter().any(|d| d.is_finite());
    // Before anything is measured the range's middle stands in for the depth.
    let assumed_disparity = input
        .expected_range_px
        .filter(|_| !measured)
        .map(|[far, near]| 0.5 * (far + near));
    Prepared {
        need,
        taken_directions: input.taken.iter().map(|o| direction(*o).map(|d| d.0)).collect(),
        seen_from,
        hidden,
        tensor: structure_tensor(w, h, input.luma, config.window_radius_px),
        median_disparity: assumed_disparity.unwrap_or(median_disparity),
        assumed_disparity,
        // With a known range the search spans it (from its far end), without one it starts at
        // 0. The estimate may narrow the range, not widen it: disparities past it are
        // mismatches (on a mirror, say).
        search_span: match (measured, input.expected_range_px) {
            (false, Some([far, near])) => (near - far).abs(),
            (true, Some([far, near])) => (largest_disparity(input.disparity_px).min(near) - far).abs(),
            (_, None) => largest_disparity(input.disparity_px),
        },
    }
}

/// Per-pixel score of one offset, with the candidate's summary terms.
struct Scored {
    per_pixel: Vec<f32>,
    visible: Vec<bool>,
    texture: f64,
    feasible: bool,
}

fn score_offset(input: &PlanInput<'_>, config: &PlanConfig, prepared: &Prepared, offset: [i32; 2]) -> Scored {
    let (w, h) = (input.width, input.height);
    let visible = visibility_with(w, h, input.disparity_px, offset, prepared.median_disparity);
    let Some((unit, k)) = direction(offset) else {
        return Scored {
            per_pixel: vec![0.0; w * h],
            visible,
            texture: 0.0,
            feasible: false,
        };
    };
    let (ux, uy) = (unit[0] as f32, unit[1] as f32);
    let norm = (ux * ux + uy * uy).sqrt();
    let (ux, uy) = (ux / norm, uy / norm);
    let feasible = k as f32 * prepared.search_span <= input.max_disparity_px;
    let same_direction: Vec<usize> = prepared
        .taken_directions
        .iter()
        .enumerate()
        .filter(|(_, d)| **d == Some(unit))
        .map(|(i, _)| i)
        .collect();
    let [jxx, jxy, jyy] = &prepared.tensor;
    let mut texture_sum = 0.0f64;
    let per_pixel: Vec<f32> = (0..w * h)
        .map(|p| {
            let energy = ux * ux * jxx[p] + 2.0 * ux * uy * jxy[p] + uy * uy * jyy[p];
            let texture = energy / (energy + config.texture_half);
            texture_sum += f64::from(texture);
            if !visible[p] || !feasible {
                return 0.0;
            }
            let d = input.disparity_px[p];
            let d = if d.is_finite() {
                Some(d)
            } else {
                prepared.assumed_disparity
            };
            let resolution = d.map_or(0.5, |d| {
                let reach = k as f32 * d.abs();
                reach / (reach + config.resolution_half_px)
            });
            let seen_here = same_direction.iter().any(|i| prepared.seen_from[*i][p]);
            let novelty = if seen_here { config.redundancy } else { 1.0 };
            prepared.need[p] * texture * resolution * novelty
        })
        .collect();
    Scored {
        per_pixel,
        visible,
        texture: texture_sum / (w * h) as f64,
        feasible,
    }
}

fn summarise(input: &PlanInput<'_>, prepared: &Prepared, offsets: Vec<[i32; 2]>, members: &[Scored]) -> Candidate {
    let n = input.width * input.height;
    let mut expected = 0.0f64;
    let (mut with_estimate, mut visible_count, mut needy, mut revealed) = (0usize, 0usize, 0usize, 0usize);
    for p in 0..n {
        // Either member resolving the pixel: 1 − Π(1 − sᵢ).
        let missed: f32 = members.iter().map(|m| 1.0 - m.per_pixel[p]).product();
        expected += f64::from(1.0 - missed);
        let seen = members.iter().any(|m| m.visible[p]);
        if input.disparity_px[p].is_finite() {
            with_estimate += 1;
            visible_count += usize::from(seen);
        }
        if prepared.need[p] >= 0.5 {
            needy += 1;
            revealed += usize::from(prepared.hidden[p] && seen);
        }
    }
    Candidate {
        offsets,
        expected_pixels: expected,
        gain: expected / n as f64,
        visible_share: visible_count as f64 / with_estimate.max(1) as f64,
        texture: members.iter().map(|m| m.texture).sum::<f64>() / members.len().max(1) as f64,
        reveals_share: revealed as f64 / needy.max(1) as f64,
        feasible: members.iter().all(|m| m.feasible),
    }
}

/// The input box-averaged by `factor` (disparities in the smaller image's pixels; pixels without
/// an estimate count only when a whole block has none).
fn reduced(input: &PlanInput<'_>, factor: usize) -> (usize, usize, [Vec<f32>; 3]) {
    let (w, h) = (input.width / factor, input.height / factor);
    let mut out = [vec![0.0f32; w * h], vec![f32::INFINITY; w * h], vec![0.0f32; w * h]];
    for y in 0..h {
        for x in 0..w {
            let (mut luma, mut disparity, mut confidence, mut known) = (0.0f32, 0.0f32, 0.0f32, 0usize);
            for dy in 0..factor {
                for dx in 0..factor {
                    let p = (y * factor + dy) * input.width + x * factor + dx;
                    luma += input.luma[p];
                    confidence += input.confidence[p];
                    if input.disparity_px[p].is_finite() {
                        disparity += input.disparity_px[p];
                        known += 1;
                    }
                }
            }
            let n = (factor * factor) as f32;
            let q = y * w + x;
            out[0][q] = luma / n;
            out[2][q] = confidence / n;
            if known > 0 {
                out[1][q] = disparity / known as f32 / factor as f32;
            }
        }
    }
    (w, h, out)
}

/// Scores every candidate not yet taken, best first (infeasible ones last). Inputs wider than
/// [`PlanConfig::max_width_px`] are planned on a reduced copy.
pub fn plan(input: &PlanInput<'_>, config: &PlanConfig) -> Result<Vec<Candidate>, FuseError> {
    check(input)?;
    let factor = input.width.div_ceil(config.max_width_px.max(16));
    if factor <= 1 || input.height / factor < 4 {
        return plan_at(input, config);
    }
    let (width, height, [luma, disparity, confidence]) = reduced(input, factor);
    let small = PlanInput {
        width,
        height,
        luma: &luma,
        disparity_px: &disparity,
        confidence: &confidence,
        taken: input.taken,
        max_disparity_px: input.max_disparity_px / factor as f32,
        expected_range_px: input.expected_range_px.map(|r| r.map(|d| d / factor as f32)),
    };
    // The same terms in the reduced image's units: a gradient spans `factor` times the levels per
    // pixel, a disparity `1 / factor` the pixels.
    let f = factor as f32;
    let scaled = PlanConfig {
        texture_half: config.texture_half * f * f,
        resolution_half_px: config.resolution_half_px / f,
        ..*config
    };
    let area = (factor * factor) as f64;
    Ok(plan_at(&small, &scaled)?
        .into_iter()
        .map(|c| Candidate {
            expected_pixels: c.expected_pixels * area,
            ..c
        })
        .collect())
}

fn plan_at(input: &PlanInput<'_>, config: &PlanConfig) -> Result<Vec<Candidate>, FuseError> {
    let prepared = prepare(input, config);
    let offsets: Vec<[i32; 2]> = candidate_offsets(config.max_offset)
        .into_iter()
        .filter(|o| !input.taken.contains(o))
        .collect();
    let mut candidates: Vec<Candidate> = match config.layout {
        LayoutRule::Free => offsets
            .par_iter()
            .map(|o| {
                summarise(
                    input,
                    &prepared,
                    vec![*o],
                    &[score_offset(input, config, &prepared, *o)],
                )
            })
            .collect(),
        LayoutRule::Pairs => {
            // Each axis pair once (left and right, or top and bottom, at one multiple of the
            // baseline: MFuseNet's layouts), by its member with a positive coordinate; the
            // members already taken are left out of the candidate.
            let all = candidate_offsets(config.max_offset);
            all.iter()
                .filter(|[x, y]| (*x > 0 && *y == 0) || (*x == 0 && *y > 0))
                .filter_map(|o| {
                    let pair: Vec<[i32; 2]> = [*o, [-o[0], -o[1]]]
                        .into_iter()
                        .filter(|m| !input.taken.contains(m))
                        .collect();
                    // A pair whose other member is taken completes a layout; a pair with both
                    // taken has nothing to add. Pairs whose scale differs from a taken view's
                    // would not form one layout with it.
                    let scale_fits = input
                        .taken
                        .iter()
                        .all(|t| direction(*t).is_none_or(|(_, k)| direction(*o).is_some_and(|(_, ko)| ko == k)));
                    (!pair.is_empty() && scale_fits).then(|| {
                        let members: Vec<Scored> = pair
                            .iter()
                            .map(|m| score_offset(input, config, &prepared, *m))
                            .collect();
                        summarise(input, &prepared, pair, &members)
                    })
                })
                .collect()
        }
    };
    for c in &mut candidates {
        if c.offsets.iter().all(|o| o[0] == 0) {
            c.expected_pixels *= f64::from(config.vertical_weight);
            c.gain *= f64::from(config.vertical_weight);
        }
    }
    candidates.sort_by(|a, b| {
        b.feasible
            .cmp(&a.feasible)
            .then(b.expected_pixels.total_cmp(&a.expected_pixels))
    });
    Ok(candidates)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An input with the given buffers, the views `taken` and a 64 px search range.
    fn input<'a>(
        (width, height): (usize, usize),
        (luma, disparity_px, confidence): (&'a [f32], &'a [f32], &'a [f32]),
        taken: &'a [[i32; 2]],
    ) -> PlanInput<'a> {
        PlanInput {
            width,
            height,
            luma,
            disparity_px,
            confidence,
            taken,
            max_disparity_px: 64.0,
            expected_range_px: None,
        }
    }

    /// A textured background at disparity 4 with a near box (disparity 12) standing at the
    /// image's left.
    fn occluder_on_the_left(w: usize, h: usize) -> (Vec<f32>, Vec<f32>) {
        let luma = (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as f32, (p / w) as f32);
                128.0 + 50.0 * (0.9 * x).sin() * (0.7 * y).cos() + 30.0 * (0.37 * x + 0.53 * y).sin()
            })
            .collect();
        let disparity = (0..w * h).map(|p| if (p % w) < w / 3 { 12.0 } else { 4.0 }).collect();
        (luma, disparity)
    }

    #[test]
    fn a_plane_hides_nothing_and_a_near_box_hides_the_background_beside_it() {
        let (w, h) = (40, 10);
        let plane = vec![3.0f32; w * h];
        let seen = visibility(w, h, &plane, [-1, 0]);
        // Left view at offset −1: pixel x lands at x + 3, inside for x ≤ 36.
        assert_eq!(seen.iter().filter(|v| **v).count(), 37 * h);
        // A near box over x < 10 (disparity 9) before a background at 3. A view on the left (−1)
        // sees each point at x + d: the box lands on [9, 19) and covers the background that
        // lands there, x ∈ [10, 15).
        let boxed: Vec<f32> = (0..w * h).map(|p| if p % w < 10 { 9.0 } else { 3.0 }).collect();
        let left = visibility(w, h, &boxed, [-1, 0]);
        let row = &left[..w];
        assert!(row[9], "the box's own edge is seen: {row:?}");
        assert!(
            !row[10] && !row[14],
            "the background right beside the box is hidden: {row:?}"
        );
        assert!(row[16], "the background past the box's shadow is seen: {row:?}");
        // From the right (+1) the box moves away from that background: seen.
        let right = visibility(w, h, &boxed, [1, 0]);
        assert!(right[10] && right[14], "{:?}", &right[..w]);
        // Every row alike: the count pins the whole mask.
        assert_eq!(left.iter().filter(|v| !**v).count(), h * (5 + 3), "{:?}", &left[..w]);
    }

    #[test]
    fn an_occluder_on_the_left_picks_a_view_on_the_right() {
        let (w, h) = (96, 48);
        let (luma, disparity) = occluder_on_the_left(w, h);
        // The set so far: the centre and the left view, in which the box covers the background
        // right beside it.
        let confidence = vec![0.6f32; w * h];
        let input = input((w, h), (&luma, &disparity, &confidence), &[[-1, 0]]);
        let ranked = plan(&input, &PlanConfig::default()).unwrap_or_else(|e| panic!("{e}"));
        let best = &ranked[0];
        assert!(best.offsets[0][0] > 0, "a view on the right: {ranked:#?}");
        assert!(best.reveals_share > 0.0, "{best:?}");
    }

    #[test]
    fn horizontal_stripes_pick_a_vertical_baseline() {
        let (w, h) = (64, 48);
        // Stripes along x: the grey level changes with y only.
        let luma: Vec<f32> = (0..w * h)
            .map(|p| 128.0 + 80.0 * (0.8 * (p / w) as f32).sin())
            .collect();
        let disparity = vec![5.0f32; w * h];
        let confidence = vec![0.2f32; w * h];
        let input = input((w, h), (&luma, &disparity, &confidence), &[]);
        let mfusenet = PlanConfig::for_family(Some(crate::methods::Family::MFuseNet));
        for (layout, vertical_weight) in [
            (LayoutRule::Free, 1.0),
            (LayoutRule::Pairs, 1.0),
            (LayoutRule::Pairs, mfusenet.vertical_weight),
        ] {
            let config = PlanConfig {
                layout,
                vertical_weight,
                ..PlanConfig::default()
            };
            let ranked = plan(&input, &config).unwrap_or_else(|e| panic!("{e}"));
            let best = &ranked[0];
            assert!(
                best.offsets.iter().all(|o| o[0] == 0 && o[1] != 0),
                "{layout:?}: a vertical baseline: {ranked:#?}"
            );
            // Every horizontal candidate resolves nothing.
            let horizontal = ranked.iter().find(|c| c.offsets.iter().all(|o| o[1] == 0));
            assert!(horizontal.is_some_and(|c| c.gain < 0.01), "{ranked:#?}");
        }
    }

    #[test]
    fn mfusenet_takes_a_vertical_pair_first_only_with_twice_the_texture() {
        let (w, h) = (64, 48);
        // Texture along y about 1.9 times that along x, like brushed metal with streaks along
        // the rows.
        let luma: Vec<f32> = (0..w * h)
            .map(|p| 128.0 + 4.0 * (0.9 * (p % w) as f32).sin() + 7.0 * (0.8 * (p / w) as f32).cos())
            .collect();
        let disparity = vec![5.0f32; w * h];
        let confidence = vec![0.2f32; w * h];
        let input = input((w, h), (&luma, &disparity, &confidence), &[]);
        let vertical = |c: &Candidate| c.offsets.iter().all(|o| o[0] == 0);
        let any_axis = PlanConfig {
            layout: LayoutRule::Pairs,
            ..PlanConfig::default()
        };
        let ranked = plan(&input, &any_axis).unwrap_or_else(|e| panic!("{e}"));
        assert!(vertical(&ranked[0]), "more texture along y: {ranked:#?}");
        let mfusenet = PlanConfig::for_family(Some(crate::methods::Family::MFuseNet));
        assert_eq!(mfusenet.layout, LayoutRule::Pairs);
        let ranked = plan(&input, &mfusenet).unwrap_or_else(|e| panic!("{e}"));
        assert!(
            !vertical(&ranked[0]),
            "MFuseNet's first pair is horizontal: {ranked:#?}"
        );
    }

    #[test]
    fn a_far_scene_prefers_the_longer_baseline_while_the_range_allows_it() {
        let (w, h) = (64, 48);
        let luma: Vec<f32> = (0..w * h)
            .map(|p| 128.0 + 60.0 * (0.9 * (p % w) as f32).sin() + 60.0 * (0.8 * (p / w) as f32).cos())
            .collect();
        let disparity = vec![1.5f32; w * h];
        let confidence = vec![0.3f32; w * h];
        let mut input = input((w, h), (&luma, &disparity, &confidence), &[[1, 0]]);
        let ranked = plan(&input, &PlanConfig::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            ranked[0].offsets[0].iter().map(|v| v.abs()).max(),
            Some(2),
            "{ranked:#?}"
        );
        // A search range too short for twice the disparity leaves only one-baseline candidates.
        input.max_disparity_px = 2.0;
        let ranked = plan(&input, &PlanConfig::default()).unwrap_or_else(|e| panic!("{e}"));
        assert!(
            ranked[0].feasible && ranked[0].offsets[0].iter().all(|v| v.abs() <= 1),
            "{ranked:#?}"
        );
        assert!(ranked.iter().any(|c| !c.feasible));
    }

    #[test]
    fn before_any_estimate_the_working_range_decides_the_baseline() {
        let (w, h) = (64, 48);
        let luma: Vec<f32> = (0..w * h)
            .map(|p| 128.0 + 60.0 * (0.9 * (p % w) as f32).sin() + 60.0 * (0.8 * (p / w) as f32).cos())
            .collect();
        let unknown = vec![f32::INFINITY; w * h];
        let confidence = vec![0.0f32; w * h];
        let pairs = PlanConfig {
            layout: LayoutRule::Pairs,
            ..PlanConfig::default()
        };
        let longest = |ranked: &[Candidate]| ranked[0].offsets[0].iter().map(|v| v.abs()).max();
        // A table at 9 px and parts up to 12 px: twice the baseline spans 18 … 24 px, which a
        // 32 px search covers.
        let far = PlanInput {
            max_disparity_px: 32.0,
            expected_range_px: Some([9.0, 12.0]),
            ..input((w, h), (&luma, &unknown, &confidence), &[])
        };
        let ranked = plan(&far, &pairs).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(longest(&ranked), Some(2), "{ranked:#?}");
        assert_eq!(ranked[0].offsets.len(), 2, "a pair: {ranked:#?}");
        // A table at 4 px and parts up to 24 px: twice spans 40 px, past the search; one baseline
        // it is.
        let near = PlanInput {
            expected_range_px: Some([4.0, 24.0]),
            ..far
        };
        let ranked = plan(&near, &pairs).unwrap_or_else(|e| panic!("{e}"));
        assert!(ranked[0].feasible && longest(&ranked) == Some(1), "{ranked:#?}");
        // An estimate that finds nothing nearer than 10 px narrows the range (4 … 10): twice fits.
        let measured = vec![10.0f32; w * h];
        let estimated = PlanInput {
            disparity_px: &measured,
            ..near
        };
        let ranked = plan(&estimated, &pairs).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(longest(&ranked), Some(2), "{ranked:#?}");
    }

    #[test]
    fn a_wide_input_is_planned_on_a_reduced_copy_with_the_same_choice() {
        // The occluder scene of the test above seen by a camera with 4 × the pixels: texture and
        // disparities 4 × larger.
        let (w, h) = (96 * 4, 48 * 4);
        let (small_luma, small_disparity) = occluder_on_the_left(96, 48);
        let at = |p: usize| ((p / w) / 4) * 96 + (p % w) / 4;
        let luma: Vec<f32> = (0..w * h).map(|p| small_luma[at(p)]).collect();
        let disparity: Vec<f32> = (0..w * h).map(|p| 4.0 * small_disparity[at(p)]).collect();
        let confidence = vec![0.6f32; w * h];
        let input = PlanInput {
            max_disparity_px: 256.0,
            ..input((w, h), (&luma, &disparity, &confidence), &[[-1, 0]])
        };
        let full = PlanConfig {
            max_width_px: 4096,
            ..PlanConfig::default()
        };
        let (reduced, whole) = (
            plan(&input, &PlanConfig::default()).unwrap_or_else(|e| panic!("{e}")),
            plan(&input, &full).unwrap_or_else(|e| panic!("{e}")),
        );
        assert_eq!(reduced[0].offsets, whole[0].offsets, "{reduced:#?} vs {whole:#?}");
        let ratio = reduced[0].expected_pixels / whole[0].expected_pixels;
        assert!((0.7..1.3).contains(&ratio), "expected pixels scaled back: {ratio}");
    }

    #[test]
    fn bad_sizes_are_errors() {
        let input = PlanInput {
            width: 4,
            height: 4,
            luma: &[0.0; 16],
            disparity_px: &[0.0; 15],
            confidence: &[0.0; 16],
            taken: &[],
            max_disparity_px: 8.0,
            expected_range_px: None,
        };
        assert!(matches!(
            plan(&input, &PlanConfig::default()),
            Err(FuseError::ImageSize { len: 15, .. })
        ));
    }
}
