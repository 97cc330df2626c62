//! The convolutions' inner loop in 16-bit integer products on AVX2 (`vpmaddwd`: two pairs of
//! 16-bit values multiplied and summed into each 32-bit lane, 16 products per instruction
//! against 8 for a fused multiply-add on f32), for hosts without AVX-512: about 1.5 times the
//! multiply-adds per cycle of [`super::fma_kernel`]'s loop on an AMD EPYC.
//!
//! The pairs are two neighbouring **input channels** at one position (`c`, `c + 1`), so that no
//! kernel size wastes a product: the padded input is rewritten in place
//! ([`to_channel_pairs`]), row `c` of every even `c` holding `(x_c[i], x_{c+1}[i])` as one
//! 32-bit slot (an odd channel count's last pairs with zero), and the weights are packed as
//! `(w[c], w[c + 1])` per tap and output channel ([`pack_weights`]).
//!
//! **Quantisation.** A layer's input is scaled so that its largest magnitude becomes
//! [`INPUT_LEVELS`] (2¹⁴; one scale per layer and tile of the network, read from the values
//! themselves), each output channel's weights by the largest scale that keeps every partial sum
//! inside 32 bits: the kernel sums one pair of input channels' `K³` taps in integers, then adds
//! that into f32 accumulators, so a channel's weight scale is bounded by its largest magnitude
//! (15 bits) and by the largest L1 norm of one input pair's weights (`2¹⁴ · Σ|w_q| < 2³¹`): no
//! sum can overflow, whatever the inputs. The result is the f32 sum divided by both scales.
//! Relative to the layer's largest value, the inputs keep 14 bits; an output channel's largest
//! weight gets 600–1,000 levels in the shipped files' 7³ layers, 1,400–2,300 in their 5³ and
//! 5,000–9,000 in their 3³ ones (the L1 bound decides: a 7³ pair has 686 weights), against
//! bfloat16's 8 bits of mantissa per value ([`super::bf16_kernel`]). Inference only,
//! where the caller asks for it ([`super::conv::with_precision`]); training stays in f32. A
//! non-finite input value becomes zero.

use super::fma_kernel::RowTable;
use super::wide_kernel::COLUMNS;

/// The largest magnitude of a quantised input value.
pub const INPUT_LEVELS: f32 = 16384.0;
/// The largest magnitude of a quantised weight (`i16::MAX`: two products of at most 2¹⁴ · 2¹⁵
/// fit one `vpmaddwd` lane).
const WEIGHT_LEVELS: f32 = 32767.0;
/// The largest `Σ|w_q|` over one input pair's weights of an output channel: `2¹⁴ · Σ|w_q|`
/// stays under `2³¹` with room for the rounding of each weight (at most 0.5 each).
const PAIR_L1_BUDGET: f64 = (i32::MAX as f64) / (INPUT_LEVELS as f64);

/// Whether the integer kernel is built for this target (AVX2; this workspace builds for
/// x86-64-v3, so always on x86-64).
pub fn available() -> bool {
    cfg!(all(target_arch = "x86_64", target_feature = "avx2"))
}

/// The scale that brings `max_abs` to [`INPUT_LEVELS`] (1 for an all-zero or non-finite input).
pub(super) fn input_scale(max_abs: f32) -> f32 {
    if max_abs > 0.0 && max_abs.is_finite() {
        INPUT_LEVELS / max_abs
    } else {
        1.0
    }
}

/// The largest finite magnitude in `data` (0 when there is none).
pub(super) fn max_abs(data: &[f32]) -> f32 {
    use rayon::prelude::*;
    data.par_chunks(CHUNK)
        .map(|chunk| {
            // Eight running maxima, so that the loop vectorises.
            let mut lanes = [0f32; 8];
            let mut blocks = chunk.chunks_exact(8);
            for block in blocks.by_ref() {
                for (m, v) in lanes.iter_mut().zip(block) {
                    let a = v.abs();
                    // A NaN compares false and leaves the maximum; an infinity is dropped below.
                    *m = if a > *m && a.is_finite() { a } else { *m };
                }
            }
            let rest = blocks.remainder().iter().map(|v| v.abs()).filter(|a| a.is_finite());
            lanes.into_iter().chain(rest).fold(0f32, f32::max)
        })
        .reduce(|| 0.0, f32::max)
}

/// Values per task of the parallel passes (256 KB).
const CHUNK: usize = 1 << 16;

/// `v · scale` rounded to the nearest integer, as a 16-bit value (`|v · scale| ≤`
/// [`INPUT_LEVELS`] for the scale of [`input_scale`]; a NaN becomes 0).
#[inline(always)]
fn quantise(v: f32, scale: f32) -> i32 {
    // `as` saturates and maps NaN to 0; the clamp keeps ±∞ and rounding inside the levels.
    ((v * scale).round() as i32).clamp(-(INPUT_LEVELS as i32), INPUT_LEVELS as i32)
}

/// Two 16-bit values as one 32-bit slot: `low` in the low half (the first of `vpmaddwd`'s pair).
#[inline(always)]
fn pack(low: i32, high: i32) -> f32 {
    f32::from_bits(u32::from(low as i16 as u16) | (u32::from(high as i16 as u16) << 16))
}

/// The two 16-bit values of a slot made by [`pack`].
#[inline(always)]
fn unpack(slot: f32) -> (i32, i32) {
    let bits = slot.to_bits();
    (i32::from(bits as u16 as i16), i32::from((bits >> 16) as u16 as i16))
}

/// Rewrites a padded input of `channels` rows of `row` values side by side (the convolutions'
/// `[tile][z][y][c][row]` layout: `data` is whole groups of `channels · row`) in place as
/// quantised channel pairs: afterwards slot `i` of row `2p` holds `(q(x_2p[i]), q(x_2p+1[i]))`
/// (the second zero past the last channel); the odd rows keep their old values, unread.
pub(super) fn to_channel_pairs(data: &mut [f32], channels: usize, row: usize, scale: f32) {
    to_channel_pairs_by(data, channels, row, |a, b| pack(quantise(a, scale), quantise(b, scale)));
}

/// [`to_channel_pairs`]' layout with each slot made by `pair(x_2p[i], x_2p+1[i])` (the second
/// 0 past the last channel): the bfloat16 channel pairs share it
/// ([`super::bf16_kernel::to_channel_pairs`]).
pub(super) fn to_channel_pairs_by(
    data: &mut [f32],
    channels: usize,
    row: usize,
    pair: impl Fn(f32, f32) -> f32 + Sync,
) {
    use rayon::prelude::*;
    let group = channels * row;
    if group == 0 {
        return;
    }
    let per_task = (CHUNK / group).max(1) * group;
    data.par_chunks_mut(per_task).for_each(|chunk| {
        for rows in chunk.chunks_exact_mut(group) {
            for p in 0..channels.div_ceil(2) {
                let (first, second) = rows[2 * p * row..].split_at_mut(row);
                if 2 * p + 1 < channels {
                    for (a, b) in first.iter_mut().zip(&second[..row]) {
                        *a = pair(*a, *b);
                    }
                } else {
                    for a in first.iter_mut() {
                        *a = pair(*a, 0.0);
                    }
                }
            }
        }
    });
}

/// One channel group's weights as quantised pairs for [`rows`], with the factors that turn its
/// integer sums back into the layer's units.
pub(super) struct PairWeights {
    /// `[pair][td][th][tw][o]`: `(w[2p], w[2p + 1])` of output channel `o` (zero past the input
    /// channels or the group's output channels), each slot packed as [`pack`] does.
    pub(super) packed: Vec<f32>,
    /// Per output channel, `1 / (input scale · weight scale)`.
    pub(super) factors: [f32; 4],
}

/// Packs one group's weights, `[i][td][th][tw][o]` over `cin` input channels and 4 output
/// channels (the f32 kernels' order), as quantised channel pairs, for inputs quantised at
/// `input_scale`.
pub(super) fn pack_weights<const K: usize>(weights: &[f32], cin: usize, input_scale: f32) -> PairWeights {
    let taps = K * K * K;
    let pairs = cin.div_ceil(2);
    let at = |i: usize, t: usize, o: usize| {
        if i < cin {
            weights.get((i * taps + t) * 4 + o).copied().unwrap_or(0.0)
        } else {
            0.0
        }
    };
    let mut factors = [0f32; 4];
    let mut scales = [1f32; 4];
    for o in 0..4 {
        let largest = (0..cin)
            .flat_map(|i| (0..taps).map(move |t| (i, t)))
            .map(|(i, t)| at(i, t, o).abs())
            .fold(0f32, f32::max);
        let widest_pair = (0..pairs)
            .map(|p| {
                (0..taps)
                    .map(|t| f64::from(at(2 * p, t, o).abs()) + f64::from(at(2 * p + 1, t, o).abs()))
                    .sum::<f64>()
            })
            .fold(0f64, f64::max);
        let rounding = 0.5 * (2 * taps) as f64;
        let scale = if largest > 0.0 && largest.is_finite() && widest_pair.is_finite() {
            let by_l1 = (PAIR_L1_BUDGET - rounding - 1.0) / widest_pair;
            (f64::from(WEIGHT_LEVELS / largest)).min(by_l1) as f32
        } else {
            1.0
        };
        scales[o] = scale;
        factors[o] = 1.0 / (input_scale * scale);
    }
    let q = |v: f32, o: usize| ((v * scales[o]).round() as i32).clamp(-(WEIGHT_LEVELS as i32), WEIGHT_LEVELS as i32);
    let mut packed = Vec::with_capacity(pairs * taps * 4);
    for p in 0..pairs {
        for t in 0..taps {
            for o in 0..4 {
                packed.push(pack(q(at(2 * p, t, o), o), q(at(2 * p + 1, t, o), o)));
            }
        }
    }
    PairWeights { packed, factors }
}

/// `out[o][c] = factors[o] · Σ_r Σ_tw ⟨pairs[base + rows[r] + tw + c], weights[r][tw][o]⟩` (each
/// term a pair's two integer products) for the 48 columns `c` of one wide block, every value
/// written. `rows` lists each pair's `K²` rows `(td, th)` in turn (the pairs' order of
/// `weights`); the integers are summed per pair, then in f32. `pairs` holds
/// [`to_channel_pairs`]'s slots, `weights` [`pack_weights`]'s. Answers `false`, doing nothing,
/// where the kernel is not built for this target or `K` (3, 5 and 7 are), or where a read would
/// leave `pairs` or `weights` (the caller then runs [`rows_portable`]).
#[allow(unsafe_code)]
pub(super) fn rows<const K: usize>(
    pairs: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &PairWeights,
    out: &mut [f32; 4 * COLUMNS],
) -> bool {
    let per_pair = K * K;
    let weights_needed = rows.offsets().len().checked_mul(K * 4);
    if !matches!(K, 3 | 5 | 7)
        || !rows.offsets().len().is_multiple_of(per_pair)
        || !rows.fits(base, (K, COLUMNS), pairs.len(), usize::MAX)
        || weights_needed.is_none_or(|n| n > weights.packed.len())
    {
        return false;
    }
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    {
        // SAFETY: every row read is `pairs[base + r .. base + r + K − 1 + 48]` with `r` at most
        // the table's largest entry, inside `pairs` (checked above); the weights read are
        // `packed[.. rows · K · 4]` (checked above); the target has AVX2 (cfg).
        unsafe {
            sums::<K>(
                pairs.as_ptr().add(base),
                rows.offsets(),
                weights.packed.as_ptr(),
                &weights.factors,
                out,
            );
        }
        true
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
    {
        let _ = out;
        false
    }
}

/// [`rows`] by plain loops, for where the kernel declines (not built here, or a read that would
/// leave `pairs`, read here as zero): the same integer products and per-pair sums.
pub(super) fn rows_portable<const K: usize>(
    pairs: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &PairWeights,
    out: &mut [f32; 4 * COLUMNS],
) {
    let per_pair = K * K;
    out.fill(0.0);
    for (p, group) in rows.offsets().chunks(per_pair).enumerate() {
        let mut sums = [[0i64; COLUMNS]; 4];
        for (rr, &offset) in group.iter().enumerate() {
            let r = p * per_pair + rr;
            for tw in 0..K {
                for (o, sums_o) in sums.iter_mut().enumerate() {
                    let (w0, w1) = unpack(weights.packed.get((r * K + tw) * 4 + o).copied().unwrap_or(0.0));
                    for (c, s) in sums_o.iter_mut().enumerate() {
                        let (x0, x1) = unpack(pairs.get(base + offset + tw + c).copied().unwrap_or(0.0));
                        *s += i64::from(x0 * w0 + x1 * w1);
                    }
                }
            }
        }
        for (o, sums_o) in sums.iter().enumerate() {
            for (c, s) in sums_o.iter().enumerate() {
                out[o * COLUMNS + c] += *s as f32;
            }
        }
    }
    for (o, factor) in weights.factors.iter().enumerate() {
        for v in &mut out[o * COLUMNS..(o + 1) * COLUMNS] {
            *v *= factor;
        }
    }
}

/// The sums of one wide block, in three runs of 16 columns: per run and pair of input
/// channels, [`pair_sums`] into 8 integer accumulators, which are then converted and added into
/// the run's f32 sums; last, each channel's sums times its factor.
///
/// # Safety
/// The target has AVX2; `pairs + offset + K − 1 + 48` stays inside the caller's slice for every
/// offset in `rows`; `weights` holds `rows.len() · K · 4` values; `rows.len()` is a multiple of
/// `K²`.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[allow(unsafe_code)]
#[target_feature(enable = "avx2")]
unsafe fn sums<const K: usize>(
    pairs: *const f32,
    rows: &[usize],
    weights: *const f32,
    factors: &[f32; 4],
    out: &mut [f32; 4 * COLUMNS],
) {
    use std::arch::x86_64::{
        __m256, __m256i, _mm256_add_ps, _mm256_cvtepi32_ps, _mm256_loadu_si256, _mm256_mul_ps, _mm256_set1_ps,
        _mm256_setzero_ps, _mm256_storeu_ps,
    };
    let per_pair = K * K;
    let mut acc = [0i32; 64];
    for run in 0..COLUMNS / 16 {
        let mut total: [__m256; 8] = [_mm256_setzero_ps(); 8];
        for (p, group) in rows.chunks_exact(per_pair).enumerate() {
            // SAFETY: the pair's rows, read from `16 · run` on, stay inside the caller's slice, and
            // its weights are `per_pair · K · 4` values from `p · per_pair · K · 4` (this
            // function's contract).
            unsafe {
                pair_sums::<K>(pairs.add(16 * run), group, weights.add(p * per_pair * K * 4), &mut acc);
            }
            for (j, t) in total.iter_mut().enumerate() {
                // SAFETY: `acc` holds 64 values; this reads 8 at `8j`.
                let a = unsafe { _mm256_loadu_si256(acc.as_ptr().add(8 * j).cast::<__m256i>()) };
                *t = _mm256_add_ps(*t, _mm256_cvtepi32_ps(a));
            }
        }
        // `total[2o + j]`: channel o, columns 16 run + 8j.
        for (i, t) in total.iter().enumerate() {
            let (o, j) = (i / 2, i % 2);
            // SAFETY: `out` holds 4 · 48 floats; this writes 8 of them at `o · 48 + 16 run + 8j`.
            unsafe {
                _mm256_storeu_ps(
                    out.as_mut_ptr().add(o * COLUMNS + 16 * run + 8 * j),
                    _mm256_mul_ps(*t, _mm256_set1_ps(factors[o])),
                );
            }
        }
    }
}

/// One pair of input channels' integer sums for 16 columns: `acc[2o + j][lane] = Σ_r Σ_tw
/// ⟨data[rows[r] + tw + 8j + lane], weights[r][tw][o]⟩`, in inline assembly (left to LLVM, the
/// sums of products were reassociated and the accumulators spilled to the stack in the inner
/// loop: slower than f32). Per tap, 2 loads of 8 pairs, 4 weight broadcasts and 8
/// `vpmaddwd` + `vpaddd` into 8 accumulators; the 16 registers hold it all.
///
/// # Safety
/// The target has AVX2; `data + r + K − 1 + 16` stays inside the caller's slice for every `r` in
/// `rows` (non-empty); `weights` holds `rows.len() · K · 4` values.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[allow(unsafe_code)]
#[inline]
unsafe fn pair_sums<const K: usize>(data: *const f32, rows: &[usize], weights: *const f32, acc: &mut [i32; 64]) {
    if rows.is_empty() {
        acc.fill(0);
        return;
    }
    // SAFETY: see the function's contract.
    unsafe {
        match K {
            3 => p3(data, rows.as_ptr(), rows.len(), weights, acc),
            5 => p5(data, rows.as_ptr(), rows.len(), weights, acc),
            7 => p7(data, rows.as_ptr(), rows.len(), weights, acc),
            // `rows` declines every other size.
            _ => acc.fill(0),
        }
    }
}

/// The loop of [`pair_sums`] for one `K`: the accumulators zeroed, then per row its address from
/// the table, the `K` taps ([`int_tap`]), the weights advanced by a row's `K · 4` values; the
/// accumulators stored.
macro_rules! pair_kernel {
    ($name:ident, $advance:literal, [$($body:expr),* $(,)?]) => {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        #[allow(unsafe_code)]
        #[inline]
        unsafe fn $name(data: *const f32, rows: *const usize, count: usize, weights: *const f32, acc: &mut [i32; 64]) {
            // SAFETY: see `pair_sums`.
            unsafe {
                std::arch::asm!(
                    "vpxor ymm8, ymm8, ymm8",
                    "vpxor ymm9, ymm9, ymm9",
                    "vpxor ymm10, ymm10, ymm10",
                    "vpxor ymm11, ymm11, ymm11",
                    "vpxor ymm12, ymm12, ymm12",
                    "vpxor ymm13, ymm13, ymm13",
                    "vpxor ymm14, ymm14, ymm14",
                    "vpxor ymm15, ymm15, ymm15",
                    "2:",
                    "mov {src}, [{rows}]",
                    "lea {src}, [{data} + {src} * 4]",
                    $($body,)*
                    $advance,
                    "add {rows}, 8",
                    "dec {count}",
                    "jnz 2b",
                    "vmovdqu [{acc}], ymm8",
                    "vmovdqu [{acc} + 32], ymm9",
                    "vmovdqu [{acc} + 64], ymm10",
                    "vmovdqu [{acc} + 96], ymm11",
                    "vmovdqu [{acc} + 128], ymm12",
                    "vmovdqu [{acc} + 160], ymm13",
                    "vmovdqu [{acc} + 192], ymm14",
                    "vmovdqu [{acc} + 224], ymm15",
                    data = in(reg) data,
                    rows = inout(reg) rows => _,
                    count = inout(reg) count => _,
                    w = inout(reg) weights => _,
                    acc = in(reg) acc.as_mut_ptr(),
                    src = out(reg) _,
                    out("ymm0") _, out("ymm1") _, out("ymm2") _, out("ymm3") _,
                    out("ymm4") _, out("ymm5") _, out("ymm6") _, out("ymm7") _,
                    out("ymm8") _, out("ymm9") _, out("ymm10") _, out("ymm11") _,
                    out("ymm12") _, out("ymm13") _, out("ymm14") _, out("ymm15") _,
                    options(nostack),
                );
            }
        }
    };
}

/// One tap `t` of a row (`{src}` the row, `{w}` its weights): 2 vectors of 8 pairs at column `t`,
/// the 4 channels' weight pairs `[t][o]` broadcast, 8 `vpmaddwd` summed into the accumulators
/// (`ymm8 + 2o + j`).
macro_rules! int_tap {
    ($t:literal) => {
        concat!(
            "vmovdqu ymm0, [{src} + 4*",
            $t,
            "]\n",
            "vmovdqu ymm1, [{src} + 4*",
            $t,
            " + 32]\n",
            "vpbroadcastd ymm2, [{w} + 16*",
            $t,
            "]\n",
            "vpbroadcastd ymm3, [{w} + 16*",
            $t,
            " + 4]\n",
            "vpbroadcastd ymm4, [{w} + 16*",
            $t,
            " + 8]\n",
            "vpbroadcastd ymm5, [{w} + 16*",
            $t,
            " + 12]\n",
            "vpmaddwd ymm6, ymm0, ymm2\n",
            "vpmaddwd ymm7, ymm1, ymm2\n",
            "vpaddd ymm8, ymm8, ymm6\n",
            "vpaddd ymm9, ymm9, ymm7\n",
            "vpmaddwd ymm6, ymm0, ymm3\n",
            "vpmaddwd ymm7, ymm1, ymm3\n",
            "vpaddd ymm10, ymm10, ymm6\n",
            "vpaddd ymm11, ymm11, ymm7\n",
            "vpmaddwd ymm6, ymm0, ymm4\n",
            "vpmaddwd ymm7, ymm1, ymm4\n",
            "vpaddd ymm12, ymm12, ymm6\n",
            "vpaddd ymm13, ymm13, ymm7\n",
            "vpmaddwd ymm6, ymm0, ymm5\n",
            "vpmaddwd ymm7, ymm1, ymm5\n",
            "vpaddd ymm14, ymm14, ymm6\n",
            "vpaddd ymm15, ymm15, ymm7",
        )
    };
}

pair_kernel!(p3, "add {w}, 48", [int_tap!(0), int_tap!(1), int_tap!(2)]);
pair_kernel!(
    p5,
    "add {w}, 80",
    [int_tap!(0), int_tap!(1), int_tap!(2), int_tap!(3), int_tap!(4)]
);
pair_kernel!(
    p7,
    "add {w}, 112",
    [
        int_tap!(0),
        int_tap!(1),
        int_tap!(2),
        int_tap!(3),
        int_tap!(4),
        int_tap!(5),
        int_tap!(6)
    ]
);

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    use crate::nn::fma_kernel::tests::plain;

    /// Data of `channels` rows side by side per group, as the padded layout holds them, with a
    /// table of every pair's `K²` rows and the f32 weights `[i][td][th][tw][o]`.
    pub(in crate::nn) fn case<const K: usize>(channels: usize) -> (Vec<f32>, usize, Vec<usize>, Vec<usize>, Vec<f32>) {
        let row = 48 + K - 1 + 9;
        // K rows (td) of K rows (th) per plane: a group of channel rows per (td, th).
        let groups = K * K + 2;
        let data: Vec<f32> = (0..groups * channels * row)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 25.0)
            .collect();
        let at = |c: usize, td: usize, th: usize| ((td * K + th) * channels + c) * row;
        let f32_rows: Vec<usize> = (0..channels)
            .flat_map(|c| (0..K).flat_map(move |td| (0..K).map(move |th| (c, td, th))))
            .map(|(c, td, th)| at(c, td, th))
            .collect();
        let pair_rows: Vec<usize> = (0..channels.div_ceil(2))
            .flat_map(|p| (0..K).flat_map(move |td| (0..K).map(move |th| (p, td, th))))
            .map(|(p, td, th)| at(2 * p, td, th))
            .collect();
        let weights: Vec<f32> = (0..channels * K * K * K * 4)
            .map(|i| ((i * 13 % 29) as f32 - 14.0) / 70.0)
            .collect();
        (data, row, f32_rows, pair_rows, weights)
    }

    fn check<const K: usize>(channels: usize) {
        let (data, row, f32_rows, pair_rows, weights) = case::<K>(channels);
        let base = 3;
        let scale = input_scale(max_abs(&data));
        let mut pairs = data.clone();
        to_channel_pairs(&mut pairs, channels, row, scale);
        let packed = pack_weights::<K>(&weights, channels, scale);
        let table = RowTable::new(pair_rows);
        let mut out = [f32::NAN; 4 * COLUMNS];
        let ran = rows::<K>(&pairs, base, &table, &packed, &mut out);
        assert_eq!(ran, available(), "K = {K}: the kernel runs exactly where it is built");
        let mut portable = [f32::NAN; 4 * COLUMNS];
        rows_portable::<K>(&pairs, base, &table, &packed, &mut portable);
        if !ran {
            println!("skipped: no AVX2 kernel on this target (the portable loops run)");
            out = portable;
        }
        // The same integers summed: equal but for the order of the f32 additions of the pairs'
        // sums (each exact below 2²⁴).
        for (i, (p, k)) in portable.iter().zip(&out).enumerate() {
            assert!(
                (p - k).abs() <= 1e-5 * (1.0 + k.abs()),
                "K = {K}, value {i}: portable {p}, kernel {k}"
            );
        }
        // Against the f32 sums, within the quantisation: each product's error is at most
        // |x|·δw + |w|·δx + δx·δw, with δx = ½ / scale and δw = ½ / (its channel's weight scale).
        let magnitude: Vec<f32> = data.iter().map(|v| v.abs()).collect();
        let weight_magnitude: Vec<f32> = weights.iter().map(|v| v.abs()).collect();
        let (ones, unit_weights) = (vec![1f32; data.len()], vec![1f32; weights.len()]);
        let taps = (channels * K * K * K) as f32;
        for b in [0, 1] {
            let at = base + 24 * b;
            let exact = plain::<K>(&data, at, &f32_rows, &weights);
            let x_times_w = plain::<K>(&magnitude, at, &f32_rows, &weight_magnitude);
            let x_sums = plain::<K>(&magnitude, at, &f32_rows, &unit_weights);
            let w_sums = plain::<K>(&ones, at, &f32_rows, &weight_magnitude);
            for o in 0..4 {
                let weight_scale = 1.0 / (packed.factors[o] * scale);
                for c in 0..24 {
                    let i = o * 24 + c;
                    let got = out[o * COLUMNS + 24 * b + c];
                    let bound = 0.5 * x_sums[i] / weight_scale
                        + 0.5 * w_sums[i] / scale
                        + taps * 0.25 / (scale * weight_scale)
                        + 1e-5 * (1.0 + x_times_w[i]);
                    assert!(
                        (got - exact[i]).abs() <= bound,
                        "K = {K}, {channels} channels, block {b}, channel {o}, column {c}: {got} against {} in f32 (bound {bound})",
                        exact[i]
                    );
                    assert!(
                        (got - exact[i]).abs() <= 1e-3 * (1.0 + x_times_w[i]),
                        "K = {K}: {got} against {}",
                        exact[i]
                    );
                }
            }
        }
        // A table reaching past the data is refused and leaves the sums alone.
        let mut untouched = [1f32; 4 * COLUMNS];
        let far = RowTable::new(vec![pairs.len() - base - (K - 1 + COLUMNS) + 1; K * K]);
        assert!(!rows::<K>(&pairs, base, &far, &packed, &mut untouched));
        assert!(untouched.iter().all(|&v| v == 1.0));
    }

    #[test]
    fn the_integer_kernel_sums_the_quantised_products_of_the_plain_loops() {
        check::<3>(4);
        check::<3>(5);
        check::<5>(4);
        check::<7>(8);
        check::<7>(16);
    }

    #[test]
    fn channel_pairs_hold_both_channels_quantised() {
        let (channels, row) = (3, 5);
        let data: Vec<f32> = (0..2 * channels * row).map(|i| i as f32 - 12.5).collect();
        let scale = input_scale(max_abs(&data));
        assert_eq!(scale, INPUT_LEVELS / 16.5);
        let mut pairs = data.clone();
        to_channel_pairs(&mut pairs, channels, row, scale);
        for g in 0..2 {
            for i in 0..row {
                let first = g * channels * row + i;
                assert_eq!(
                    unpack(pairs[first]),
                    (quantise(data[first], scale), quantise(data[first + row], scale))
                );
                // The odd count's last channel pairs with zero.
                let last = first + 2 * row;
                assert_eq!(unpack(pairs[last]), (quantise(data[last], scale), 0));
                // The odd rows are left alone.
                assert_eq!(pairs[first + row], data[first + row]);
            }
        }
        assert_eq!(quantise(16.5, scale), 16384);
        assert_eq!(quantise(-17.5, scale), -16384, "clamped");
        assert_eq!(quantise(f32::NAN, scale), 0);
        assert_eq!(quantise(f32::INFINITY, scale), 16384);
        assert_eq!(max_abs(&[1.0, f32::NAN, -3.0, f32::INFINITY]), 3.0);
        assert_eq!(input_scale(0.0), 1.0);
    }

    #[test]
    fn no_weight_scale_lets_a_pair_s_sum_overflow() {
        // Large, same-signed weights over a 7³ kernel: the L1 bound, not the largest weight, sets
        // the scale, and the largest possible sum still fits 32 bits.
        let cin = 16;
        let weights = vec![0.5f32; cin * 343 * 4];
        let packed = pack_weights::<7>(&weights, cin, 1.0);
        let mut worst = 0i64;
        for p in 0..cin / 2 {
            let mut sum = 0i64;
            for t in 0..343 {
                let (a, b) = unpack(packed.packed[(p * 343 + t) * 4]);
                sum += i64::from(a.abs() + b.abs()) * INPUT_LEVELS as i64;
            }
            worst = worst.max(sum);
        }
        assert!(worst <= i64::from(i32::MAX), "{worst}");
        assert!(
            worst > i64::from(i32::MAX) / 2,
            "the scale uses the room it has: {worst}"
        );
    }
}
