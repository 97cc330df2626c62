//! The convolutions' inner loop in bfloat16 products, where the host has AVX512-BF16 (detected at
//! run time; Intel Xeon from Cooper Lake, AMD from Zen 4): `vdpbf16ps` multiplies two pairs of
//! bfloat16 values per 32-bit lane and adds both products into an f32 accumulator, so one
//! instruction does the work of two fused multiply-adds of [`super::wide_kernel`].
//!
//! The pairs are two neighbouring kernel taps along a row (`tw`, `tw + 1`): the padded input is
//! rewritten in place as *shifted pairs* ([`to_shifted_pairs`]), the value at `i` becoming
//! `(x[i], x[i + 1])` in bfloat16 (same size as the f32 it replaces), so that the 16 lanes of
//! one load are the pairs of 16 consecutive output columns for a pair of taps, and the weights
//! are packed as `(w[tw], w[tw + 1])` ([`pack_weights`]; an odd kernel's last tap pairs with a
//! zero). A 7³ layer then runs 4 instead of 7 steps per row, a 3³ layer 2 instead of 3. The
//! block is the wide kernel's: 4 channels × 48 columns in 12 accumulators, three loads and
//! four broadcasts per pair of taps.
//!
//! A layer of an even number of input channels pairs **channels** instead ([`channel_rows`]):
//! slot `i` of row `2p` of the padded input holds `(x_2p[i], x_2p+1[i])` in bfloat16 (the layout
//! of [`super::int16_kernel`]'s integer pairs), the weights `(w[2p], w[2p + 1])` per tap, and every
//! product is a kernel's: a 3³ layer's pairs of taps are a quarter zero (two pairs for three
//! taps), a 5³ layer's a sixth, a 7³ layer's an eighth.
//!
//! Inputs and weights are rounded to bfloat16 (8 bits of mantissa, round to nearest even), the
//! sums kept in f32: relative errors of about 2⁻⁹ per product that average out over a layer's
//! hundreds of products. Inference only, where the caller asks for it
//! ([`super::conv::set_precision`]); training and the default stay in f32.

use super::fma_kernel::RowTable;
use super::wide_kernel::COLUMNS;

/// Whether the bfloat16 kernel can run here: the host has AVX-512F and AVX512-BF16, and the
/// 512-bit paths are not switched off ([`crate::wide::set_enabled`]).
pub fn available() -> bool {
    crate::wide::avx512f() && crate::wide::host_has_avx512bf16()
}

/// Whether this host's bfloat16 products beat its f32 FMAs, so that [`super::conv::Precision::Auto`]
/// takes them: [`available`] on an AMD processor (Zen 4 and 5 run `vdpbf16ps` on two pipes; the
/// lite network 12–14 % faster per layer than in f32). Intel's run it on one port, where a
/// pair of them makes no more products than two FMAs and the conversions cost the rest.
pub fn preferred() -> bool {
    available() && crate::wide::host_is_amd()
}

/// Pairs of taps of one row of a kernel of size `K`: `⌈K / 2⌉`.
pub(super) const fn pairs_per_row(k: usize) -> usize {
    k.div_ceil(2)
}

/// The bfloat16 bits of `v`, rounded to nearest, ties to even (the rounding of `vcvtneps2bf16`;
/// a NaN stays a NaN).
#[inline(always)]
pub(super) fn bf16_bits(v: f32) -> u32 {
    let bits = v.to_bits();
    let rounded = (bits.wrapping_add(0x7fff + ((bits >> 16) & 1))) >> 16;
    // (A select, not a branch: the loops over many values stay vector code.)
    if v.is_nan() { (bits >> 16) | 0x40 } else { rounded }
}

/// `v` rounded to bfloat16, as an f32 (for references and tests).
pub fn round_to_bf16(v: f32) -> f32 {
    f32::from_bits(bf16_bits(v) << 16)
}

#[inline(always)]
fn pair(low: f32, high: f32) -> f32 {
    f32::from_bits(bf16_bits(low) | (bf16_bits(high) << 16))
}

/// Values per task of [`to_shifted_pairs`] (256 KB).
const CHUNK: usize = 1 << 16;

/// Rewrites `data` in place as shifted pairs: afterwards the bits of `data[i]` are the bfloat16
/// pair `(x[i], x[i + 1])` of the values before (low half first; `x[len]` read as zero).
pub(super) fn to_shifted_pairs(data: &mut [f32]) {
    use rayon::prelude::*;
    // Each chunk's last pair needs the first value of the next chunk, read before any is
    // rewritten.
    let next_first: Vec<f32> = (1..=data.len().div_ceil(CHUNK))
        .map(|c| data.get(c * CHUNK).copied().unwrap_or(0.0))
        .collect();
    data.par_chunks_mut(CHUNK).zip(next_first).for_each(|(chunk, after)| {
        // Forward, 16 values at a time from the 17 read before any is rewritten (fixed-size
        // loops that compile to vector code; one value at a time was 5 % of MFuseNet's time).
        let n = chunk.len();
        let mut i = 0;
        while i + 17 <= n {
            let mut bits = [0u32; 17];
            for (b, v) in bits.iter_mut().zip(&chunk[i..i + 17]) {
                *b = bf16_bits(*v);
            }
            for (j, v) in chunk[i..i + 16].iter_mut().enumerate() {
                *v = f32::from_bits(bits[j] | (bits[j + 1] << 16));
            }
            i += 16;
        }
        for j in i..n {
            let next = chunk.get(j + 1).copied().unwrap_or(after);
            chunk[j] = pair(chunk[j], next);
        }
    });
}

/// The weights of [`super::wide_kernel`]'s order, `[row][tw][o]` (4 channels), as bfloat16 pairs
/// `[row][pair][o]`: pair `q` holds taps `2q` (low half) and `2q + 1` (high half, zero past the
/// kernel). Each packed value is an f32 slot holding the pair's bits.
pub(super) fn pack_weights<const K: usize>(weights: &[f32]) -> Vec<f32> {
    let per_row = K * 4;
    let pairs = pairs_per_row(K);
    let rows = weights.len() / per_row.max(1);
    let mut packed = Vec::with_capacity(rows * pairs * 4);
    for r in 0..rows {
        let row = &weights[r * per_row..(r + 1) * per_row];
        for q in 0..pairs {
            for o in 0..4 {
                let low = row[2 * q * 4 + o];
                let high = if 2 * q + 1 < K { row[(2 * q + 1) * 4 + o] } else { 0.0 };
                packed.push(pair(low, high));
            }
        }
    }
    packed
}

/// Rewrites a padded input of `channels` rows of `row` values side by side (the convolutions'
/// `[tile][z][y][c][row]` layout) in place as bfloat16 channel pairs: afterwards slot `i` of row
/// `2p` holds `(x_2p[i], x_2p+1[i])` (low half first, the second zero past the last channel); the
/// odd rows keep their old values, unread.
pub(super) fn to_channel_pairs(data: &mut [f32], channels: usize, row: usize) {
    super::int16_kernel::to_channel_pairs_by(data, channels, row, pair);
}

/// `low[i]` becomes the bfloat16 pair `(low[i], high[i])` (low half first), as
/// [`to_channel_pairs`] makes each slot of an even row: a layer writes its output's channel
/// pairs for the next one ([`super::conv::conv3d_padded_pairs`]).
pub(super) fn pair_rows_into(low: &mut [f32], high: &[f32]) {
    // Fixed-size runs, so that the loop compiles to vector code.
    let mut lows = low.chunks_exact_mut(16);
    let mut highs = high.chunks_exact(16);
    for (l, h) in lows.by_ref().zip(highs.by_ref()) {
        let mut bits = [0u32; 16];
        for ((b, a), c) in bits.iter_mut().zip(l.iter()).zip(h) {
            *b = bf16_bits(*a) | (bf16_bits(*c) << 16);
        }
        for (v, b) in l.iter_mut().zip(bits) {
            *v = f32::from_bits(b);
        }
    }
    for (l, h) in lows.into_remainder().iter_mut().zip(highs.remainder()) {
        *l = pair(*l, *h);
    }
}

/// One group's weights, `[i][td][th][tw][o]` over `cin` input channels and 4 output channels
/// (the f32 kernels' order), as bfloat16 channel pairs `[pair][td][th][tw][o]`: `(w[2p],
/// w[2p + 1])`, the second zero past the input channels.
pub(super) fn pack_channel_weights<const K: usize>(weights: &[f32], cin: usize) -> Vec<f32> {
    let taps = K * K * K;
    let at = |i: usize, t: usize, o: usize| {
        if i < cin {
            weights.get((i * taps + t) * 4 + o).copied().unwrap_or(0.0)
        } else {
            0.0
        }
    };
    let mut packed = Vec::with_capacity(cin.div_ceil(2) * taps * 4);
    for p in 0..cin.div_ceil(2) {
        for t in 0..taps {
            for o in 0..4 {
                packed.push(pair(at(2 * p, t, o), at(2 * p + 1, t, o)));
            }
        }
    }
    packed
}

/// Pairs of taps along a row ([`rows`]): each pair's first tap two columns after the last's.
const TAP_PAIRS: usize = 2;
/// Pairs of channels at one tap ([`channel_rows`]): one column apart.
const CHANNEL_PAIRS: usize = 1;

/// The pairs of one kernel row: ⌈K/2⌉ pairs of taps, or `K` taps of a channel pair.
const fn steps_per_row(k: usize, stride: usize) -> usize {
    if stride == TAP_PAIRS { pairs_per_row(k) } else { k }
}

/// `out[o][c] = Σ_r Σ_tw ⟨pairs[base + rows[r] + tw + c], weights[r][tw][o]⟩` (each term a
/// channel pair's two products) for the 48 columns `c` of one wide block, every value written.
/// `rows` lists each channel pair's `K²` rows `(td, th)` in turn (the order of `weights`);
/// `pairs` holds [`to_channel_pairs`]'s slots, `weights` [`pack_channel_weights`]'s. Answers
/// `false`, doing nothing, where the host lacks AVX512-BF16, or where a read would leave `pairs`
/// or `weights` (the caller then runs [`channel_rows_portable`]).
pub(super) fn channel_rows<const K: usize>(
    pairs: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &[f32],
    out: &mut [f32; 4 * COLUMNS],
) -> bool {
    strided_rows::<K, CHANNEL_PAIRS>(pairs, base, rows, weights, out)
}

/// [`channel_rows`] by plain loops, for where the kernel declines (no AVX512-BF16 on this host,
/// or a read that would leave `pairs`, read here as zero). Slow; the same products.
pub(super) fn channel_rows_portable<const K: usize>(
    pairs: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &[f32],
    out: &mut [f32; 4 * COLUMNS],
) {
    strided_rows_portable::<K, CHANNEL_PAIRS>(pairs, base, rows, weights, out);
}

/// `out[o][c] = Σ_r Σ_q pairs[base + rows[r] + 2q + c] · weights[r][q][o]` (each a bfloat16 pair's
/// two products) for the 48 columns `c` of one wide block, every value written: the sums of
/// [`super::wide_kernel::rows`] with inputs and weights in bfloat16. `pairs` holds shifted pairs
/// ([`to_shifted_pairs`]), `weights` [`pack_weights`]'s. Answers `false`, doing nothing, where
/// the host lacks AVX512-BF16, or where a read would leave `pairs` or `weights`.
pub(super) fn rows<const K: usize>(
    pairs: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &[f32],
    out: &mut [f32; 4 * COLUMNS],
) -> bool {
    // (For odd K the last pair read from a row ends at column (K − 1) + 47, as for the channel
    // pairs; an even K would read one column more.)
    !K.is_multiple_of(2) && strided_rows::<K, TAP_PAIRS>(pairs, base, rows, weights, out)
}

/// [`rows`] by plain loops, for where the kernel declines (no AVX512-BF16 on this host, or a
/// read that would leave `pairs`, read here as zero): each pair's low half is the input value
/// in bfloat16, its high half the next one, each packed weight's halves two taps' weights. Slow;
/// the same products.
pub(super) fn rows_portable<const K: usize>(
    pairs: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &[f32],
    out: &mut [f32; 4 * COLUMNS],
) {
    strided_rows_portable::<K, TAP_PAIRS>(pairs, base, rows, weights, out);
}

/// [`rows`] (`STRIDE` 2) and [`channel_rows`] (`STRIDE` 1): per row `r`, the pairs at columns
/// `STRIDE · i + c` times the weights `[r][i][o]`.
#[allow(unsafe_code)]
fn strided_rows<const K: usize, const STRIDE: usize>(
    pairs: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &[f32],
    out: &mut [f32; 4 * COLUMNS],
) -> bool {
    let steps = const { steps_per_row(K, STRIDE) };
    let weights_needed = rows.offsets().len().checked_mul(steps * 4);
    if !rows.fits(base, (K, COLUMNS), pairs.len(), usize::MAX)
        || weights_needed.is_none_or(|n| n > weights.len())
        || !crate::wide::host_has_avx512bf16()
    {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: the host has AVX-512F and AVX512-BF16 (`host_has_avx512bf16`). Every row read is
        // `pairs[base + r .. base + r + K − 1 + 48]` with `r` at most the table's largest entry,
        // inside `pairs` (`fits`; the last pair read starts at `STRIDE · (steps − 1) ≤ K − 1`,
        // odd K for pairs of taps); the weights read are `weights[.. rows · steps · 4]` (checked
        // above).
        unsafe { sums::<K, STRIDE>(pairs.as_ptr().add(base), rows.offsets(), weights.as_ptr(), out) };
        true
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = out;
        false
    }
}

/// [`strided_rows`] by plain loops: each term the products of both halves of a weight's pair
/// and an input slot's (a shifted pair's high half is the next value; a channel pair's the
/// next channel's).
fn strided_rows_portable<const K: usize, const STRIDE: usize>(
    pairs: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &[f32],
    out: &mut [f32; 4 * COLUMNS],
) {
    let steps = steps_per_row(K, STRIDE);
    out.fill(0.0);
    let low = |bits: u32| f32::from_bits(bits << 16);
    let high = |bits: u32| f32::from_bits(bits & 0xffff_0000);
    for (r, &offset) in rows.offsets().iter().enumerate() {
        for i in 0..steps {
            for o in 0..4 {
                let w = weights.get((r * steps + i) * 4 + o).map_or(0, |v| v.to_bits());
                for c in 0..COLUMNS {
                    let x = pairs.get(base + offset + STRIDE * i + c).map_or(0, |v| v.to_bits());
                    out[o * COLUMNS + c] += low(w) * low(x) + high(w) * high(x);
                }
            }
        }
    }
}

/// The sums of one wide block, `[o][column]`, started from zero. Per row, per pair: three 16-lane
/// loads of pairs at the pair's first column (`STRIDE · i`), then per output channel the weights'
/// pair broadcast into three `vdpbf16ps`.
///
/// # Safety
/// The host has AVX-512F and AVX512-BF16; `pairs + offset + K − 1 + 48` stays inside the
/// caller's slice for every offset in `rows`, and so does every pair read (`STRIDE · (steps − 1)
/// ≤ K − 1`); `weights` holds `rows.len() · steps · 4` values.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn sums<const K: usize, const STRIDE: usize>(
    pairs: *const f32,
    rows: &[usize],
    weights: *const f32,
    out: &mut [f32; 4 * COLUMNS],
) {
    use std::arch::x86_64::{
        __m512, __m512bh, _mm512_castps_si512, _mm512_dpbf16_ps, _mm512_loadu_ps, _mm512_set1_ps, _mm512_setzero_ps,
        _mm512_storeu_ps,
    };
    // The same 512 bits seen as 32 bfloat16 values (a pair per 32-bit lane).
    #[inline(always)]
    fn bh(v: __m512) -> __m512bh {
        // SAFETY: both types are 512 bits of plain data, every bit pattern valid.
        unsafe { std::mem::transmute::<std::arch::x86_64::__m512i, __m512bh>(_mm512_castps_si512(v)) }
    }
    let steps = const { steps_per_row(K, STRIDE) };
    let mut acc: [[__m512; 3]; 4] = [[_mm512_setzero_ps(); 3]; 4];
    for (r, &offset) in rows.iter().enumerate() {
        // SAFETY: inside the caller's slices (this function's contract).
        unsafe {
            let row = pairs.add(offset);
            let w = weights.add(r * steps * 4);
            for i in 0..steps {
                let at = STRIDE * i;
                let x = [
                    bh(_mm512_loadu_ps(row.add(at))),
                    bh(_mm512_loadu_ps(row.add(at + 16))),
                    bh(_mm512_loadu_ps(row.add(at + 32))),
                ];
                for (o, acc_o) in acc.iter_mut().enumerate() {
                    let wv = bh(_mm512_set1_ps(*w.add(i * 4 + o)));
                    for (a, xv) in acc_o.iter_mut().zip(&x) {
                        *a = _mm512_dpbf16_ps(*a, *xv, wv);
                    }
                }
            }
        }
    }
    for (o, acc_o) in acc.iter().enumerate() {
        for (j, a) in acc_o.iter().enumerate() {
            // SAFETY: `out` holds 4 · 48 floats; this writes 16 of them at `o · 48 + 16j`.
            unsafe { _mm512_storeu_ps(out.as_mut_ptr().add(o * COLUMNS + 16 * j), *a) };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::nn::fma_kernel::tests::{case, plain};

    #[test]
    fn bfloat16_rounding_is_to_nearest_even() {
        assert_eq!(round_to_bf16(1.0), 1.0);
        // 1 + 2⁻⁸ is halfway between 1 and 1 + 2⁻⁷: ties to the even mantissa, 1.
        assert_eq!(round_to_bf16(1.0 + 1.0 / 256.0), 1.0);
        // 1 + 3·2⁻⁸ is halfway between 1 + 2⁻⁷ and 1 + 2⁻⁶: to 1 + 2⁻⁶.
        assert_eq!(round_to_bf16(1.0 + 3.0 / 256.0), 1.0 + 1.0 / 64.0);
        assert_eq!(round_to_bf16(-2.5), -2.5);
        assert!(round_to_bf16(f32::NAN).is_nan());
        assert_eq!(round_to_bf16(f32::INFINITY), f32::INFINITY);
        for v in [0.1f32, -3.7, 1234.5, 1e-3] {
            assert!((round_to_bf16(v) - v).abs() <= v.abs() / 256.0, "{v}");
        }
    }

    #[test]
    fn shifted_pairs_hold_each_value_and_its_right_neighbour() {
        // Across chunk boundaries too.
        let n = 2 * CHUNK + 5;
        let values: Vec<f32> = (0..n).map(|i| (i % 1000) as f32 * 0.25 - 40.0).collect();
        let mut data = values.clone();
        to_shifted_pairs(&mut data);
        for i in 0..n {
            let bits = data[i].to_bits();
            let low = f32::from_bits(bits << 16);
            let high = f32::from_bits(bits & 0xffff_0000);
            assert_eq!(low, round_to_bf16(values[i]), "low half at {i}");
            let next = values.get(i + 1).copied().unwrap_or(0.0);
            assert_eq!(high, round_to_bf16(next), "high half at {i}");
        }
    }

    fn check<const K: usize>() {
        let (data, offsets, weights) = case::<K>();
        let table = RowTable::new(offsets.clone());
        let base = 40;
        let mut pairs = data.clone();
        to_shifted_pairs(&mut pairs);
        let packed = pack_weights::<K>(&weights);
        let mut out = [f32::NAN; 4 * COLUMNS];
        let ran = rows::<K>(&pairs, base, &table, &packed, &mut out);
        assert_eq!(
            ran,
            crate::wide::host_has_avx512bf16(),
            "K = {K}: the kernel runs exactly where the host has AVX512-BF16"
        );
        if !ran {
            println!("skipped: this host has no AVX512-BF16 (the f32 kernels run)");
            return;
        }
        // The plain loops on the inputs and weights rounded to bfloat16 give the same sums but for
        // the order of the f32 additions; against the f32 inputs, within bfloat16's rounding.
        against_plain::<K>(&out, &data, &weights, (base, &offsets), &format!("K = {K}"));
        // The portable loops over the same pairs: the same products, summed in another order.
        let mut portable = [f32::NAN; 4 * COLUMNS];
        rows_portable::<K>(&pairs, base, &table, &packed, &mut portable);
        for (i, (p, k)) in portable.iter().zip(&out).enumerate() {
            assert!(
                (p - k).abs() <= 1e-4 * (1.0 + k.abs()),
                "K = {K}, value {i}: portable {p}, kernel {k}"
            );
        }
        // A table reaching past the data is refused and leaves the sums alone.
        let mut untouched = [1f32; 4 * COLUMNS];
        let far = RowTable::new(vec![0, pairs.len() - base - (K - 1 + COLUMNS) + 1]);
        assert!(!rows::<K>(&pairs, base, &far, &packed, &mut untouched));
        assert!(untouched.iter().all(|&v| v == 1.0));
        // Too few weights for the rows: refused.
        assert!(!rows::<K>(
            &pairs,
            base,
            &table,
            &packed[..packed.len() - 1],
            &mut untouched
        ));
    }

    /// `out` (two blocks of 24 columns from `base`) against the plain loops over `rows` on the
    /// values and weights rounded to bfloat16 (the same products, summed in another order), and
    /// on the f32 values within bfloat16's rounding.
    fn against_plain<const K: usize>(
        out: &[f32; 4 * COLUMNS],
        data: &[f32],
        weights: &[f32],
        (base, rows): (usize, &[usize]),
        what: &str,
    ) {
        let rounded: Vec<f32> = data.iter().map(|&v| round_to_bf16(v)).collect();
        let rounded_weights: Vec<f32> = weights.iter().map(|&v| round_to_bf16(v)).collect();
        let magnitude: Vec<f32> = data.iter().map(|v| v.abs()).collect();
        let magnitude_weights: Vec<f32> = weights.iter().map(|v| v.abs()).collect();
        for b in [0, 1] {
            let at = base + 24 * b;
            let want = plain::<K>(&rounded, at, rows, &rounded_weights);
            let exact = plain::<K>(data, at, rows, weights);
            let scale = plain::<K>(&magnitude, at, rows, &magnitude_weights);
            for o in 0..4 {
                for c in 0..24 {
                    let i = o * 24 + c;
                    let got = out[o * COLUMNS + 24 * b + c];
                    assert!(
                        (got - want[i]).abs() <= 1e-5 * (1.0 + scale[i]),
                        "{what}, block {b}, channel {o}, column {c}: {got} against {} in bfloat16",
                        want[i]
                    );
                    assert!(
                        (got - exact[i]).abs() <= 2.0 * scale[i] / 256.0,
                        "{what}, block {b}, channel {o}, column {c}: {got} against {} in f32",
                        exact[i]
                    );
                }
            }
        }
    }

    fn check_channel_pairs<const K: usize>(channels: usize) {
        let (data, row, f32_rows, pair_rows, weights) = crate::nn::int16_kernel::tests::case::<K>(channels);
        let base = 3;
        let mut pairs = data.clone();
        to_channel_pairs(&mut pairs, channels, row);
        let packed = pack_channel_weights::<K>(&weights, channels);
        let table = RowTable::new(pair_rows);
        let mut out = [f32::NAN; 4 * COLUMNS];
        let ran = channel_rows::<K>(&pairs, base, &table, &packed, &mut out);
        assert_eq!(
            ran,
            crate::wide::host_has_avx512bf16(),
            "K = {K}: runs exactly where the host has AVX512-BF16"
        );
        let mut portable = [f32::NAN; 4 * COLUMNS];
        channel_rows_portable::<K>(&pairs, base, &table, &packed, &mut portable);
        if ran {
            for (i, (p, k)) in portable.iter().zip(&out).enumerate() {
                assert!(
                    (p - k).abs() <= 1e-4 * (1.0 + k.abs()),
                    "K = {K}, value {i}: portable {p}, kernel {k}"
                );
            }
        } else {
            println!("skipped the kernel: this host has no AVX512-BF16 (the portable loops checked)");
            out = portable;
        }
        // Against the plain loops on the rounded values (the same products, summed in another
        // order), and on the f32 values within bfloat16's rounding.
        against_plain::<K>(
            &out,
            &data,
            &weights,
            (base, &f32_rows),
            &format!("K = {K}, {channels} channels"),
        );
        // A table reaching past the data, or too few weights: refused, the sums left alone.
        let mut untouched = [1f32; 4 * COLUMNS];
        let far = RowTable::new(vec![pairs.len() - base - (K - 1 + COLUMNS) + 1; K * K]);
        assert!(!channel_rows::<K>(&pairs, base, &far, &packed, &mut untouched));
        assert!(!channel_rows::<K>(
            &pairs,
            base,
            &table,
            &packed[..packed.len() - 1],
            &mut untouched
        ));
        assert!(untouched.iter().all(|&v| v == 1.0));
    }

    #[test]
    fn the_channel_pair_kernel_sums_the_rounded_products_of_the_plain_loops() {
        check_channel_pairs::<3>(4);
        check_channel_pairs::<3>(5);
        check_channel_pairs::<5>(4);
        check_channel_pairs::<7>(8);
        check_channel_pairs::<3>(16);
    }

    #[test]
    fn channel_pairs_hold_both_channels_in_bfloat16() {
        let (channels, row) = (3, 5);
        let data: Vec<f32> = (0..2 * channels * row).map(|i| i as f32 * 0.37 - 4.1).collect();
        let mut pairs = data.clone();
        to_channel_pairs(&mut pairs, channels, row);
        let halves = |v: f32| {
            (
                f32::from_bits(v.to_bits() << 16),
                f32::from_bits(v.to_bits() & 0xffff_0000),
            )
        };
        for g in 0..2 {
            for i in 0..row {
                let first = g * channels * row + i;
                assert_eq!(
                    halves(pairs[first]),
                    (round_to_bf16(data[first]), round_to_bf16(data[first + row]))
                );
                // The odd count's last channel pairs with zero; the odd rows are left alone.
                let last = first + 2 * row;
                assert_eq!(halves(pairs[last]), (round_to_bf16(data[last]), 0.0));
                assert_eq!(pairs[first + row], data[first + row]);
            }
        }
    }

    #[test]
    fn the_bfloat16_kernel_sums_the_rounded_products_of_the_plain_loops() {
        check::<3>();
        check::<5>();
        check::<7>();
    }
}
