//! Evaluation regions of a view set with ground truth: pixels occluded in a neighbour (from the
//! ground-truth disparity by forward warping with a z-buffer) and view-dependent surfaces (the
//! simulator's glossy and mirror classes), where multiscopic fusion should help most.

use fuse::metrics::{MetricSums, Metrics};
use serde::Serialize;

/// Disparity margin (px) by which a warped pixel must be hidden to count as occluded.
const OCCLUSION_MARGIN_PX: f32 = 1.0;

/// `true` where the reference pixel is hidden in the neighbour at `offset` (grid units): some
/// other pixel with a larger disparity lands on the same neighbour pixel.
pub fn occluded_in(disparity: &[f32], width: usize, height: usize, offset: [i32; 2]) -> Vec<bool> {
    let mut hidden = vec![false; width * height];
    mark_occluded(disparity, width, height, offset, &mut hidden);
    hidden
}

/// Columns a tile of the vertical neighbours' z-buffers spans: the tile's 1080 rows of 64
/// columns, transposed, stay in L2.
const COLUMN_TILE: usize = 64;
/// Rows per task of the horizontal neighbours' z-buffers.
const ROW_BAND: usize = 16;

/// Sets `hidden` where [`occluded_in`] is `true` (leaves the other pixels as they are), for
/// `height` rows of `width` pixels ([`mark_occluded_all`] with one offset).
pub fn mark_occluded(disparity: &[f32], width: usize, height: usize, offset: [i32; 2], hidden: &mut [bool]) {
    mark_occluded_all(disparity, width, height, &[offset], hidden);
}

/// Sets `hidden` where the reference pixel is hidden in the neighbour at any of `offsets`
/// (grid units; [`occluded_in`] of each, or-ed), leaving the other pixels as they are. A
/// neighbour along a row (or a column) moves pixels only within their row (column), so its
/// z-buffer is one line, reused and cache-resident: bands of rows run in parallel for the
/// horizontal neighbours, tiles of columns (transposed, so that a column is a line) for the
/// vertical ones, every neighbour of a kind in the same pass over the pixels. A diagonal
/// neighbour gets a whole-image z-buffer.
pub fn mark_occluded_all(disparity: &[f32], width: usize, height: usize, offsets: &[[i32; 2]], hidden: &mut [bool]) {
    use rayon::prelude::*;
    let pixels = (width * height).min(disparity.len()).min(hidden.len());
    if width == 0 || pixels == 0 {
        return;
    }
    let rows = pixels / width;
    let (disparity, hidden) = (&disparity[..rows * width], &mut hidden[..rows * width]);
    let along = |pick: fn(&[i32; 2]) -> (i32, i32)| -> Vec<f32> {
        offsets
            .iter()
            .map(pick)
            .filter(|(other, o)| *other == 0 && *o != 0)
            .map(|(_, o)| o as f32)
            .collect()
    };
    let horizontal = along(|o| (o[1], o[0]));
    let vertical = along(|o| (o[0], o[1]));
    if !horizontal.is_empty() {
        disparity
            .par_chunks(ROW_BAND * width)
            .zip(hidden.par_chunks_mut(ROW_BAND * width))
            .for_each_init(LineScratch::default, |scratch, (band, out)| {
                for (line, out) in band.chunks_exact(width).zip(out.chunks_exact_mut(width)) {
                    for &o in &horizontal {
                        mark_line(line, o, out, scratch);
                    }
                }
            });
    }
    if !vertical.is_empty() {
        // Each tile's hidden pixels, transposed (`[x][y]`), merged by bands of rows after.
        let tiles: Vec<Vec<bool>> = (0..width.div_ceil(COLUMN_TILE))
            .into_par_iter()
            .map_init(
                || (LineScratch::default(), Vec::new()),
                |(scratch, columns), tile| {
                    let x0 = tile * COLUMN_TILE;
                    let span = COLUMN_TILE.min(width - x0);
                    columns.clear();
                    columns.resize(span * rows, 0.0f32);
                    for (y, row) in disparity.chunks_exact(width).enumerate() {
                        for (x, &d) in row[x0..x0 + span].iter().enumerate() {
                            columns[x * rows + y] = d;
                        }
                    }
                    let mut out = vec![false; span * rows];
                    for (line, out) in columns.chunks_exact(rows).zip(out.chunks_exact_mut(rows)) {
                        for &o in &vertical {
                            mark_line(line, o, out, scratch);
                        }
                    }
                    out
                },
            )
            .collect();
        hidden
            .par_chunks_mut(ROW_BAND * width)
            .enumerate()
            .for_each(|(band, out)| {
                for (k, row) in out.chunks_exact_mut(width).enumerate() {
                    let y = band * ROW_BAND + k;
                    for (tile, transposed) in tiles.iter().enumerate() {
                        let x0 = tile * COLUMN_TILE;
                        for (x, h) in row[x0..(x0 + COLUMN_TILE).min(width)].iter_mut().enumerate() {
                            *h |= transposed[x * rows + y];
                        }
                    }
                }
            });
    }
    for &offset in offsets.iter().filter(|o| o[0] != 0 && o[1] != 0) {
        mark_diagonal(disparity, width, rows, offset, hidden);
    }
}

/// A line's z-buffer and its pixels' targets, reused from line to line.
#[derive(Default)]
struct LineScratch {
    /// Per pixel, where it lands along the line; [`OUTSIDE`] off the line, [`UNKNOWN`] without a
    /// finite disparity.
    targets: Vec<i32>,
    front: Vec<f32>,
}

/// A target of [`LineScratch`]: the pixel lands outside the line (hidden).
const OUTSIDE: i32 = -1;
/// A target of [`LineScratch`]: no finite disparity (never hidden).
const UNKNOWN: i32 = -2;

/// Sets `out` where a pixel of `line` (disparities along a row or a column) is hidden in the
/// neighbour `o` baselines along it: it lands at `round(p − o·d)`, outside the line or where a
/// pixel of larger disparity (by more than [`OCCLUSION_MARGIN_PX`]) lands too.
fn mark_line(line: &[f32], o: f32, out: &mut [bool], scratch: &mut LineScratch) {
    let n = line.len();
    let LineScratch { targets, front } = scratch;
    targets.clear();
    // The same rounding as the plain definition; the targets first, in a loop of their own.
    targets.extend(line.iter().enumerate().map(|(p, &d)| {
        let q = (p as f32 - o * d).round();
        if !d.is_finite() {
            UNKNOWN
        } else if q >= 0.0 && q < n as f32 {
            q as i32
        } else {
            OUTSIDE
        }
    }));
    front.clear();
    front.resize(n, f32::NEG_INFINITY);
    for (&q, &d) in targets.iter().zip(line) {
        if let Some(cell) = usize::try_from(q).ok().and_then(|q| front.get_mut(q)) {
            *cell = cell.max(d);
        }
    }
    for ((&q, &d), out) in targets.iter().zip(line).zip(out.iter_mut()) {
        let hidden = match usize::try_from(q) {
            Ok(q) => front.get(q).is_some_and(|f| *f > d + OCCLUSION_MARGIN_PX),
            Err(_) => q == OUTSIDE,
        };
        *out |= hidden;
    }
}

/// [`mark_occluded`] for a neighbour off both axes: a whole-image z-buffer.
fn mark_diagonal(disparity: &[f32], width: usize, rows: usize, offset: [i32; 2], hidden: &mut [bool]) {
    let (ox, oy) = (offset[0] as f32, offset[1] as f32);
    let inside = |q: f32, n: usize| q >= 0.0 && (q as usize) < n;
    let target = |x: usize, y: usize, d: f32| -> Option<usize> {
        let (qx, qy) = ((x as f32 - ox * d).round(), (y as f32 - oy * d).round());
        (inside(qx, width) && inside(qy, rows)).then(|| qy as usize * width + qx as usize)
    };
    let mut front = vec![f32::NEG_INFINITY; width * rows];
    for (y, row) in disparity.chunks_exact(width).enumerate() {
        for (x, &d) in row.iter().enumerate() {
            if d.is_finite()
                && let Some(q) = target(x, y, d)
            {
                front[q] = front[q].max(d);
            }
        }
    }
    for (y, (row, out)) in disparity
        .chunks_exact(width)
        .zip(hidden.chunks_exact_mut(width))
        .enumerate()
    {
        for (x, (&d, out)) in row.iter().zip(out).enumerate() {
            if d.is_finite() && target(x, y, d).is_none_or(|q| front[q] > d + OCCLUSION_MARGIN_PX) {
                *out = true;
            }
        }
    }
}

/// Metrics over the whole image and over the regions that exist in this set.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct RegionMetrics {
    /// All pixels with ground truth.
    pub all: Metrics,
    /// Pixels occluded in at least one neighbour of the set.
    pub occluded: Option<Metrics>,
    /// Pixels occluded in none.
    pub visible: Option<Metrics>,
    /// Glossy or mirror-like surfaces (simulated sets).
    pub specular: Option<Metrics>,
    /// AvgErr of the most confident pixels, when the method gives a confidence.
    pub sparsification: Option<Sparsification>,
}

/// The sparsification curve at three points: the AvgErr (px) of the most confident 50 %, 75 %
/// and 90 % of the pixels with ground truth, ranked by the method's confidence. A useful
/// confidence makes these fall well below the AvgErr of all pixels; a random one leaves them
/// equal. Ties keep the image order.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct Sparsification {
    /// The most confident half.
    pub avg_err_top50_px: f64,
    /// The most confident three quarters.
    pub avg_err_top75_px: f64,
    /// The most confident 90 %.
    pub avg_err_top90_px: f64,
    /// All the pixels ranked (the curve's end).
    #[serde(default)]
    pub avg_err_all_px: f64,
    /// The same shares of the pixels ranked by their true error (the best any confidence could
    /// do): 50, 75 and 90 %.
    pub oracle_avg_err_px: [f64; 3],
}

/// Pixels' errors (px) with their confidence, to be ranked: one scene's, or several scenes'
/// pooled, as a robot with one confidence threshold for every scene keeps them.
#[derive(Debug, Clone, Default)]
pub struct RankedErrors {
    /// (confidence, error): an error is an `f32` difference, or the missing estimate's error,
    /// so `f32` holds it exactly.
    pairs: Vec<(f32, f32)>,
}

impl RankedErrors {
    /// The errors of `estimate` against `truth` (NaN = unknown) with their `confidence`; a pixel
    /// without an estimate counts as an error of `missing_error_px`.
    pub fn new(estimate: &[f32], confidence: &[f32], truth: &[f32], missing_error_px: f64) -> Self {
        let mut pairs = Vec::new();
        ImagePixels {
            estimate,
            confidence,
            truth,
            missing_error_px,
        }
        .each(|c, e| pairs.push((c, e)));
        Self { pairs }
    }

    /// Adds another scene's pixels.
    pub fn extend(&mut self, other: Self) {
        self.pairs.extend(other.pairs);
    }

    /// The curve over every pixel held, ranked by confidence (stable: ties keep their order).
    /// `None` without pixels.
    pub fn curve(self) -> Option<Sparsification> {
        curve_of(&self.pairs[..])
    }
}

/// Pixels to rank: (confidence, error) pairs, in an order, walked as often as needed.
trait Ranked: Sync {
    /// Calls `f(confidence, error)` for every pixel, in order.
    fn each(&self, f: impl FnMut(f32, f32));
}

impl Ranked for [(f32, f32)] {
    #[inline]
    fn each(&self, mut f: impl FnMut(f32, f32)) {
        self.iter().for_each(|(c, e)| f(*c, *e));
    }
}

/// One image's pixels with a known truth, in image order, without a copy.
struct ImagePixels<'a> {
    estimate: &'a [f32],
    confidence: &'a [f32],
    truth: &'a [f32],
    missing_error_px: f64,
}

impl Ranked for ImagePixels<'_> {
    #[inline]
    fn each(&self, mut f: impl FnMut(f32, f32)) {
        let missing = self.missing_error_px as f32;
        for ((e, c), t) in self.estimate.iter().zip(self.confidence).zip(self.truth) {
            if t.is_finite() {
                f(*c, if e.is_finite() { (e - t).abs() } else { missing });
            }
        }
    }
}

/// A confidence's ranking key: ascending keys are descending confidences (total order).
#[inline]
fn descending(c: f32) -> u32 {
    let bits = c.to_bits();
    !(if bits >> 31 == 1 { !bits } else { bits | 0x8000_0000 })
}

/// The sparsification curve of the pixels `each` calls back with (confidence, error), in their
/// order, as often as it is called. `None` without pixels.
fn curve_of<P: Ranked + ?Sized>(pixels: &P) -> Option<Sparsification> {
    let (mut count, mut all) = (0usize, 0.0f64);
    pixels.each(|_, e| {
        count += 1;
        all += f64::from(e);
    });
    if count == 0 {
        return None;
    }
    let kept = Sparsification::SHARES.map(|share| ((count as f64 * share).round() as usize).clamp(1, count));
    // Ranked by confidence (ties in their order), and the oracle's ranking by the error itself
    // (errors are non-negative, so their bits order as they do).
    let ranked = || ranked_sums(kept, pixels, |c, _| descending(c));
    let oracle = || ranked_sums(kept, pixels, |_, e| e.to_bits());
    let (ranked, oracle) = rayon::join(ranked, oracle);
    let mean = |sums: [f64; 3], k: usize| sums[k] / kept[k] as f64;
    Some(Sparsification {
        avg_err_top50_px: mean(ranked, 0),
        avg_err_top75_px: mean(ranked, 1),
        avg_err_top90_px: mean(ranked, 2),
        avg_err_all_px: all / count as f64,
        oracle_avg_err_px: [0, 1, 2].map(|k| mean(oracle, k)),
    })
}

/// Bins of one level of [`ranked_sums`]' histograms: 16 bits of the key.
const LEVEL_BINS: usize = 1 << 16;

/// The sums of the errors of the first `kept[j]` pixels in ascending `key(confidence, error)`
/// order, ties in the pixels' order (a stable sort's), for each `j` (`kept` ascending, each in
/// `1..=count`).
/// Three passes over the items and no copy of them: counts and sums per top 16 bits of the key
/// find the bin where each share ends, counts and sums per low 16 bits within that bin find
/// the key, and a last pass adds the first items of that key the share still needs.
fn ranked_sums<P: Ranked + ?Sized>(kept: [usize; 3], pixels: &P, key: impl Fn(f32, f32) -> u32) -> [f64; 3] {
    // Where in `counts` (cumulative count and sum before `bin`) share `need` ends: (bin, count
    // before it, sum before it).
    let boundary = |counts: &[u32], sums: &[f64], need: usize| {
        let (mut before, mut sum) = (0usize, 0.0f64);
        for (bin, (&c, &s)) in counts.iter().zip(sums).enumerate() {
            if before + c as usize >= need {
                return (bin, before, sum);
            }
            before += c as usize;
            sum += s;
        }
        (counts.len().saturating_sub(1), before, sum)
    };
    let mut counts = vec![0u32; LEVEL_BINS];
    let mut sums = vec![0.0f64; LEVEL_BINS];
    pixels.each(|c, e| {
        let bin = (key(c, e) >> 16) as usize;
        counts[bin] += 1;
        sums[bin] += f64::from(e);
    });
    let high = kept.map(|need| boundary(&counts, &sums, need));
    // The second level, per share (shares often end in one bin: counted once).
    let mut low: Vec<(usize, Vec<u32>, Vec<f64>)> = Vec::with_capacity(3);
    for (bin, _, _) in high {
        if !low.iter().any(|(b, _, _)| *b == bin) {
            low.push((bin, vec![0u32; LEVEL_BINS], vec![0.0f64; LEVEL_BINS]));
        }
    }
    pixels.each(|c, e| {
        let key = key(c, e);
        let bin = (key >> 16) as usize;
        for (b, counts, sums) in low.iter_mut() {
            if *b == bin {
                let at = (key & 0xffff) as usize;
                counts[at] += 1;
                sums[at] += f64::from(e);
            }
        }
    });
    // Per share: the exact key where it ends, how many items of that key it takes, and the sum
    // of every item before that key.
    let ends: [(u32, usize, f64); 3] = std::array::from_fn(|j| {
        let (bin, before, sum) = high[j];
        let need = kept[j] - before;
        let (counts, sums) = low
            .iter()
            .find(|(b, _, _)| *b == bin)
            .map(|(_, c, s)| (c.as_slice(), s.as_slice()))
            .unwrap_or((&[], &[]));
        let (at, before_low, sum_low) = boundary(counts, sums, need);
        (((bin as u32) << 16) | at as u32, need - before_low, sum + sum_low)
    });
    let mut taken = [0usize; 3];
    let mut tail = [0.0f64; 3];
    pixels.each(|c, e| {
        let key = key(c, e);
        for j in 0..3 {
            if key == ends[j].0 && taken[j] < ends[j].1 {
                taken[j] += 1;
                tail[j] += f64::from(e);
            }
        }
    });
    std::array::from_fn(|j| ends[j].2 + tail[j])
}

impl Sparsification {
    /// The shares of the pixels kept, in the order of the fields.
    pub const SHARES: [f64; 3] = [0.5, 0.75, 0.9];

    /// The curve of `estimate` against `truth` (NaN = unknown) ranked by `confidence`; a pixel
    /// without an estimate counts as an error of `missing_error_px`. `None` without pixels.
    pub fn measure(estimate: &[f32], confidence: &[f32], truth: &[f32], missing_error_px: f64) -> Option<Self> {
        curve_of(&ImagePixels {
            estimate,
            confidence,
            truth,
            missing_error_px,
        })
    }

    /// The AvgErr of the most confident 75 % ÷ that of all pixels (0.5: they err half as much).
    pub fn top75_ratio(&self) -> f64 {
        self.avg_err_top75_px / self.avg_err_all_px
    }

    /// The mean curve of several scenes.
    pub fn average(curves: &[Self]) -> Option<Self> {
        let n = curves.len() as f64;
        let mean = |field: fn(&Self) -> f64| curves.iter().map(field).sum::<f64>() / n;
        (!curves.is_empty()).then(|| Self {
            avg_err_top50_px: mean(|c| c.avg_err_top50_px),
            avg_err_top75_px: mean(|c| c.avg_err_top75_px),
            avg_err_top90_px: mean(|c| c.avg_err_top90_px),
            avg_err_all_px: mean(|c| c.avg_err_all_px),
            oracle_avg_err_px: [0, 1, 2].map(|k| curves.iter().map(|c| c.oracle_avg_err_px[k]).sum::<f64>() / n),
        })
    }
}

/// Pixels occluded (as [`occluded_in`]) in a view one baseline away along +x, −x, +y or −y,
/// from the reference's `truth` disparity (px per baseline, NaN = unknown; `width` pixels a
/// row): the occlusions of the five-view cross, the same pixels whichever views a set has.
pub fn hidden_from_axis_views(width: usize, truth: &[f32]) -> Vec<bool> {
    let height = truth.len() / width.max(1);
    let mut hidden = vec![false; truth.len()];
    mark_occluded_all(truth, width, height, &[[1, 0], [-1, 0], [0, 1], [0, -1]], &mut hidden);
    hidden
}

/// Evaluates `estimate` against `truth` overall and per region, and, with the method's
/// `confidence`, its sparsification curve.
pub fn region_metrics(
    estimate: &[f32],
    confidence: Option<&[f32]>,
    truth: &[f32],
    occluded: &[bool],
    surface_class: Option<&[u8]>,
    missing_error_px: f64,
) -> Option<RegionMetrics> {
    // The regions in one pass beside the sparsification's.
    let (regions, sparsification) = rayon::join(
        || {
            let is_specular = |c: u8| {
                c == record::scene::SurfaceClass::Glossy as u8 || c == record::scene::SurfaceClass::Mirror as u8
            };
            let [mut all, mut hidden, mut visible, mut specular] = [MetricSums::default(); 4];
            for (i, (&e, &g)) in estimate.iter().zip(truth).enumerate() {
                if !g.is_finite() {
                    continue;
                }
                all.add(e, g, missing_error_px);
                if occluded[i] {
                    hidden.add(e, g, missing_error_px);
                } else {
                    visible.add(e, g, missing_error_px);
                }
                if surface_class.is_some_and(|classes| is_specular(classes[i])) {
                    specular.add(e, g, missing_error_px);
                }
            }
            (
                all.metrics(),
                hidden.metrics(),
                visible.metrics(),
                surface_class.and_then(|_| specular.metrics()),
            )
        },
        || confidence.and_then(|c| Sparsification::measure(estimate, c, truth, missing_error_px)),
    );
    let (all, occluded, visible, specular) = regions;
    Some(RegionMetrics {
        all: all?,
        occluded,
        visible,
        specular,
        sparsification,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A linear congruential generator's high bits from `seed`: the tests' repeatable noise.
    fn lcg(seed: u64) -> impl FnMut() -> u32 {
        let mut state = seed;
        move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as u32
        }
    }

    /// The z-buffer over the whole image, plainly: what [`occluded_in`] must give.
    fn occluded_plainly(disparity: &[f32], width: usize, height: usize, offset: [i32; 2]) -> Vec<bool> {
        let target = |x: usize, y: usize, d: f32| -> Option<usize> {
            let qx = (x as f32 - offset[0] as f32 * d).round();
            let qy = (y as f32 - offset[1] as f32 * d).round();
            (qx >= 0.0 && qy >= 0.0 && (qx as usize) < width && (qy as usize) < height)
                .then(|| qy as usize * width + qx as usize)
        };
        let mut front = vec![f32::NEG_INFINITY; width * height];
        for y in 0..height {
            for x in 0..width {
                let d = disparity[y * width + x];
                if let Some(q) = target(x, y, d).filter(|_| d.is_finite()) {
                    front[q] = front[q].max(d);
                }
            }
        }
        (0..width * height)
            .map(|p| {
                let d = disparity[p];
                d.is_finite() && target(p % width, p / width, d).is_none_or(|q| front[q] > d + OCCLUSION_MARGIN_PX)
            })
            .collect()
    }

    /// Blocks of 20 × 5 px at random disparities 0–13 px, one pixel in `one_in` unknown (NaN),
    /// one more infinite and, with `strays`, one more at a random disparity of its own.
    fn blocky_disparities(seed: u64, (w, h): (usize, usize), one_in: u32, strays: bool) -> Vec<f32> {
        let mut next = lcg(seed);
        let cells: Vec<f32> = (0..64).map(|_| (next() % 1300) as f32 / 100.0).collect();
        (0..w * h)
            .map(|p| match next() % one_in {
                0 => f32::NAN,
                1 => f32::INFINITY,
                2 if strays => (next() % 1200) as f32 / 100.0,
                _ => cells[(p % w) / 20 + 8 * ((p / w) / 5)],
            })
            .collect()
    }

    #[test]
    fn row_and_column_z_buffers_hide_what_the_whole_image_one_hides() {
        // Blocky random disparities 0–12 px with unknown pixels, 150 columns (two tiles of
        // columns and a partial one) by 37 rows, every kind of offset.
        let (w, h) = (150, 37);
        let disparity = blocky_disparities(7, (w, h), 50, true);
        let mut hidden_anywhere = 0;
        for offset in [[1, 0], [-1, 0], [0, 1], [0, -1], [2, 0], [0, -2], [1, 1], [-1, 2]] {
            let want = occluded_plainly(&disparity, w, h, offset);
            assert_eq!(occluded_in(&disparity, w, h, offset), want, "offset {offset:?}");
            hidden_anywhere += want.iter().filter(|o| **o).count();
        }
        assert!(hidden_anywhere > 800, "the case hides pixels: {hidden_anywhere}");
    }

    #[test]
    fn every_neighbour_in_one_pass_hides_what_each_hides() {
        // The five-view cross and a 3×3 grid's direct neighbours at once, against each
        // neighbour's plain z-buffer or-ed: 150 columns (a partial tile), 37 rows (a partial band).
        let (w, h) = (150, 37);
        let disparity = blocky_disparities(19, (w, h), 40, false);
        let cross = [[1, 0], [-1, 0], [0, 1], [0, -1]];
        let grid = [[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, -1], [1, -1], [-1, 1]];
        for offsets in [&cross[..], &grid[..]] {
            let mut want = vec![false; w * h];
            for offset in offsets {
                for (want, plain) in want.iter_mut().zip(occluded_plainly(&disparity, w, h, *offset)) {
                    *want |= plain;
                }
            }
            let mut got = vec![false; w * h];
            mark_occluded_all(&disparity, w, h, offsets, &mut got);
            assert_eq!(got, want, "offsets {offsets:?}");
            assert!(want.iter().filter(|o| **o).count() > 300);
        }
    }

    #[test]
    fn the_cross_hides_both_sides_of_a_step() {
        // A bar 3 px wide, at 6 px of disparity, before a background at 2 px, running the image's
        // height: the view to the right hides the 3 px of background left of the bar, the view to
        // the left the 3 px right of it; the borders fall out of the side views.
        let (w, h) = (20, 20);
        let truth: Vec<f32> = (0..w * h)
            .map(|p| if (8..11).contains(&(p % w)) { 6.0 } else { 2.0 })
            .collect();
        let hidden = hidden_from_axis_views(w, &truth);
        let row: Vec<usize> = (0..w).filter(|x| hidden[10 * w + x]).collect();
        assert_eq!(row, [0, 1, 4, 5, 6, 12, 13, 14, 18, 19]);
        // The views above and below add the rows they cannot see: the background's first and
        // last two rows (2 px of disparity out of the image), and nothing else in a column.
        let column: Vec<usize> = (0..h).filter(|y| hidden[y * w + 3]).collect();
        assert_eq!(column, [0, 1, 18, 19]);
    }

    #[test]
    fn ties_in_confidence_keep_the_pixels_order_as_a_stable_sort_does() {
        // Few confidence levels (many ties, negative and zero among them) and errors that differ
        // within a tie: which pixels of a tie fall inside the top 50 / 75 / 90 % decides the
        // curve, so it must be the stable order by descending confidence.
        let n = 1001;
        let truth = vec![0.0f32; n];
        let estimate: Vec<f32> = (0..n).map(|i| ((i * 37) % 101) as f32 / 10.0).collect();
        let confidence: Vec<f32> = (0..n).map(|i| [0.5, -0.0, 0.0, 0.25, -1.0, 0.5][(i * 7) % 6]).collect();
        let curve = Sparsification::measure(&estimate, &confidence, &truth, 3.0).unwrap_or_else(|| panic!("none"));
        let mut ranked: Vec<(f32, f64)> = confidence
            .iter()
            .zip(&estimate)
            .map(|(c, e)| (*c, f64::from(*e)))
            .collect();
        ranked.sort_by(|a, b| b.0.total_cmp(&a.0));
        let mean_of_first = |share: f64| {
            let kept = ((n as f64 * share).round() as usize).max(1);
            ranked.iter().take(kept).map(|(_, e)| e).sum::<f64>() / kept as f64
        };
        assert_eq!(curve.avg_err_top50_px, mean_of_first(0.5));
        assert_eq!(curve.avg_err_top75_px, mean_of_first(0.75));
        assert_eq!(curve.avg_err_top90_px, mean_of_first(0.9));
    }

    #[test]
    fn the_most_confident_pixels_are_kept_first() {
        // Errors 0, 1, 2, 3 (and one unknown truth), confidence highest where the error is least.
        let truth = [10.0, 10.0, 10.0, 10.0, f32::NAN];
        let estimate = [10.0, 11.0, 12.0, f32::INFINITY, 10.0];
        let confidence = [0.9, 0.5, 0.4, 0.0, 1.0];
        let curve = Sparsification::measure(&estimate, &confidence, &truth, 3.0).unwrap_or_else(|| panic!("none"));
        assert_eq!(curve.avg_err_top50_px, 0.5, "two of four kept: errors 0 and 1");
        assert_eq!(curve.avg_err_top75_px, 1.0, "three: 0, 1, 2");
        assert_eq!(curve.avg_err_top90_px, 1.5, "all four, the missing one at 3");
        assert_eq!(
            curve.oracle_avg_err_px,
            [0.5, 1.0, 1.5],
            "this confidence is the oracle's ranking"
        );
        // Ranked the other way round the curve rises instead.
        let reversed = [0.0, 0.4, 0.5, 0.9, 1.0];
        let worse = Sparsification::measure(&estimate, &reversed, &truth, 3.0).unwrap_or_else(|| panic!("none"));
        assert_eq!(worse.avg_err_top50_px, 2.5);
        assert_eq!(worse.oracle_avg_err_px, curve.oracle_avg_err_px);
        assert_eq!(Sparsification::measure(&[1.0], &[1.0], &[f32::NAN], 3.0), None);
    }

    #[test]
    fn the_curve_equals_a_stable_sort_of_the_pixels() {
        // Many ties (confidence in 16 levels) and errors in 8 levels: the partition must pick the
        // same pixels as a stable sort by confidence, and the oracle the smallest errors.
        let n = 10_007;
        let mut next = lcg(12345);
        let truth = vec![0.0f32; n];
        let estimate: Vec<f32> = (0..n).map(|_| (next() % 8) as f32 * 0.5).collect();
        let confidence: Vec<f32> = (0..n).map(|_| (next() % 16) as f32 / 16.0).collect();
        let curve = Sparsification::measure(&estimate, &confidence, &truth, 9.0).unwrap_or_else(|| panic!("none"));
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|a, b| confidence[*b].total_cmp(&confidence[*a]));
        let mut sorted_errors: Vec<f64> = estimate.iter().map(|e| f64::from(*e)).collect();
        sorted_errors.sort_by(f64::total_cmp);
        for (share, got, oracle) in [
            (0.5, curve.avg_err_top50_px, curve.oracle_avg_err_px[0]),
            (0.75, curve.avg_err_top75_px, curve.oracle_avg_err_px[1]),
            (0.9, curve.avg_err_top90_px, curve.oracle_avg_err_px[2]),
        ] {
            let k = (n as f64 * share).round() as usize;
            let want = order[..k].iter().map(|i| f64::from(estimate[*i])).sum::<f64>() / k as f64;
            let want_oracle = sorted_errors[..k].iter().sum::<f64>() / k as f64;
            assert!((got - want).abs() < 1e-12, "{share}: {got} vs {want}");
            assert!(
                (oracle - want_oracle).abs() < 1e-12,
                "{share}: {oracle} vs {want_oracle}"
            );
        }
        assert!(
            curve.avg_err_top50_px != curve.oracle_avg_err_px[0],
            "a random confidence is not the oracle"
        );
    }

    #[test]
    fn confidences_and_errors_alike_in_their_high_bits_rank_by_their_low_bits() {
        // Confidences 0.5 + k·ulp and errors 1 + k·ulp (k < 64): every key shares its high 16
        // bits with the others, so the ranking is decided in the histogram's second level and
        // by the pixels' order within a key.
        let n = 5003;
        let mut next = lcg(99);
        let truth = vec![0.0f32; n];
        let estimate: Vec<f32> = (0..n).map(|_| f32::from_bits(1.0f32.to_bits() + next() % 64)).collect();
        let confidence: Vec<f32> = (0..n).map(|_| f32::from_bits(0.5f32.to_bits() + next() % 8)).collect();
        let curve = Sparsification::measure(&estimate, &confidence, &truth, 9.0).unwrap_or_else(|| panic!("none"));
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|a, b| confidence[*b].total_cmp(&confidence[*a]));
        let mut sorted_errors: Vec<f64> = estimate.iter().map(|e| f64::from(*e)).collect();
        sorted_errors.sort_by(f64::total_cmp);
        for (j, share) in Sparsification::SHARES.into_iter().enumerate() {
            let k = (n as f64 * share).round() as usize;
            let want = order[..k].iter().map(|i| f64::from(estimate[*i])).sum::<f64>() / k as f64;
            let want_oracle = sorted_errors[..k].iter().sum::<f64>() / k as f64;
            let got = [curve.avg_err_top50_px, curve.avg_err_top75_px, curve.avg_err_top90_px][j];
            assert!((got - want).abs() < 1e-12, "{share}: {got} vs {want}");
            let oracle = curve.oracle_avg_err_px[j];
            assert!(
                (oracle - want_oracle).abs() < 1e-12,
                "{share}: {oracle} vs {want_oracle}"
            );
        }
        // The pooled path walks its pairs the same way.
        let pooled = RankedErrors::new(&estimate, &confidence, &truth, 9.0).curve();
        assert_eq!(pooled, Some(curve));
    }

    #[test]
    fn pooled_scenes_give_up_the_hard_scene_first() {
        // An easy scene, sure of itself, errs 0 and 1 px; a hard one, unsure, errs 4 and 6 px.
        let truth = [0.0; 2];
        let easy = RankedErrors::new(&[0.0, 1.0], &[0.9, 0.8], &truth, 9.0);
        let hard = RankedErrors::new(&[4.0, 6.0], &[0.3, 0.2], &truth, 9.0);
        let per_scene = Sparsification::average(&[
            easy.clone().curve().unwrap_or_else(|| panic!("easy")),
            hard.clone().curve().unwrap_or_else(|| panic!("hard")),
        ])
        .unwrap_or_else(|| panic!("average"));
        assert_eq!(
            per_scene.avg_err_top50_px, 2.0,
            "each scene keeps its better half: (0 + 4) / 2"
        );
        assert_eq!(per_scene.avg_err_all_px, 2.75);
        let mut pooled = easy;
        pooled.extend(hard);
        let pooled = pooled.curve().unwrap_or_else(|| panic!("pooled"));
        assert_eq!(
            pooled.avg_err_top50_px, 0.5,
            "one threshold keeps the easy scene's two pixels"
        );
        assert_eq!(pooled.avg_err_all_px, 2.75);
        assert!((pooled.top75_ratio() - (5.0 / 3.0) / 2.75).abs() < 1e-12);
    }

    #[test]
    fn background_left_of_a_foreground_step_is_occluded_in_the_right_view() {
        // Row: background disparity 2 for x < 5, foreground 6 from x = 5. In the right view
        // (q = x − d) the foreground covers q = 0..=3 and hides the background at x = 2..=4;
        // x = 0, 1 and the foreground at x = 5 fall off the image.
        let width = 10;
        let disparity: Vec<f32> = (0..width).map(|x| if x < 5 { 2.0 } else { 6.0 }).collect();
        let occluded = occluded_in(&disparity, width, 1, [1, 0]);
        assert_eq!(
            occluded,
            vec![true, true, true, true, true, true, false, false, false, false]
        );
        // In the left view (q = x + d) nothing is hidden except what leaves the image.
        let occluded = occluded_in(&disparity, width, 1, [-1, 0]);
        assert_eq!(occluded.iter().filter(|o| **o).count(), 5, "{occluded:?}");
        assert!(occluded[5..].iter().all(|o| *o));
    }
}
