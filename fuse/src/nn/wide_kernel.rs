//! The convolutions' inner loop on 512-bit vectors, where the host has AVX-512F (detected at
//! run time; the workspace builds for x86-64-v3, so these functions are compiled for AVX-512
//! on their own). One output block of 4 channels × 48 columns — a whole column tile of
//! [`super::conv`], two of its 24-column blocks — is held in 12 of the 32 `zmm` registers: per
//! kernel tap, three loads feed twelve fused multiply-adds, the weight broadcast from memory.
//! Twice the columns per instruction of the AVX2 kernels ([`super::fma_kernel`] and LLVM's
//! loop) for every kernel size; the products are summed in the same order, so the outputs are
//! bit for bit those of the 256-bit paths.
//!
//! [`available`] answers whether the host has it and it is not switched off
//! ([`crate::wide::set_enabled`]: `false` makes every layer take the 256-bit paths).

use super::fma_kernel::RowTable;

/// Output columns of one wide block: two of the 256-bit paths' blocks.
pub(super) const COLUMNS: usize = 48;

/// Whether the wide kernel runs here: the host has AVX-512F and [`crate::wide::set_enabled`]
/// has not switched it off.
pub fn available() -> bool {
    crate::wide::avx512f()
}

/// `out[o][c] = Σ_r Σ_tw weights[r][tw][o] · data[base + rows[r] + tw + c]` for the 48 columns
/// `c` of one wide block (the two 24-column blocks of the 256-bit paths side by side in each
/// channel's row), every value written. Answers `false`, doing nothing, where the host lacks
/// AVX-512F, or where a read would leave `data` or `weights`; the caller then runs the 256-bit
/// paths.
#[allow(unsafe_code)]
pub(super) fn rows<const K: usize>(
    data: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &[f32],
    out: &mut [f32; 4 * COLUMNS],
) -> bool {
    // The last float read from a row is column (K − 1) + 47.
    // The host's feature, not the switch: the caller checks [`available`] once per layer, and
    // a switch flipped by another thread meanwhile must not change what this call answers.
    if !rows.fits(base, (K, COLUMNS), data.len(), weights.len()) || !crate::wide::host_has_avx512f() {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: the host has AVX-512F (`host_has_avx512f`). Every row read is `data[base + r ..
        // base + r + K − 1 + 48]` with `r` at most the table's largest entry, inside `data`
        // (checked above); the weights read are `weights[.. rows · K · 4]` (checked above).
        unsafe { sums::<K>(data.as_ptr().add(base), rows.offsets(), weights.as_ptr(), out) };
        true
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = out;
        false
    }
}

/// The sums of one wide block, `[o][column]`, started from zero. Per row, per tap: three
/// 16-lane loads at the tap's column, then per output channel the weight broadcast into three
/// multiply-adds (the order of the 256-bit kernels, lane by lane).
///
/// # Safety
/// The host has AVX-512F; `data + offset + K − 1 + 48` stays inside the caller's slice for
/// every offset in `rows`; `weights` holds `rows.len() · K · 4` floats.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
#[target_feature(enable = "avx512f")]
unsafe fn sums<const K: usize>(data: *const f32, rows: &[usize], weights: *const f32, out: &mut [f32; 4 * COLUMNS]) {
    use std::arch::x86_64::{
        __m512, _mm512_fmadd_ps, _mm512_loadu_ps, _mm512_set1_ps, _mm512_setzero_ps, _mm512_storeu_ps,
    };
    let mut acc: [[__m512; 3]; 4] = [[_mm512_setzero_ps(); 3]; 4];
    for (r, &offset) in rows.iter().enumerate() {
        // SAFETY: inside the caller's slices (this function's contract).
        unsafe {
            let row = data.add(offset);
            let w = weights.add(r * K * 4);
            for tw in 0..K {
                let x = [
                    _mm512_loadu_ps(row.add(tw)),
                    _mm512_loadu_ps(row.add(tw + 16)),
                    _mm512_loadu_ps(row.add(tw + 32)),
                ];
                for (o, acc_o) in acc.iter_mut().enumerate() {
                    let wv = _mm512_set1_ps(*w.add(tw * 4 + o));
                    for (a, xv) in acc_o.iter_mut().zip(&x) {
                        *a = _mm512_fmadd_ps(*xv, wv, *a);
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

    fn check<const K: usize>() {
        let (data, offsets, weights) = case::<K>();
        let table = RowTable::new(offsets.clone());
        let base = 40;
        let mut out = [f32::NAN; 4 * COLUMNS];
        let ran = rows::<K>(&data, base, &table, &weights, &mut out);
        assert_eq!(
            ran,
            crate::wide::host_has_avx512f(),
            "K = {K}: the kernel runs exactly where the host has AVX-512F"
        );
        if !ran {
            println!("skipped: this host has no AVX-512F (the 256-bit paths run)");
            return;
        }
        // Each 24-column block as the 256-bit kernel's reference sums it (`[o][j][lane]`), 24
        // columns on; every value written (the buffer started as NaN).
        let expected = [0, 1].map(|b| plain::<K>(&data, base + 24 * b, &offsets, &weights));
        for (b, want) in expected.iter().enumerate() {
            for o in 0..4 {
                for c in 0..24 {
                    let (got, want) = (out[o * COLUMNS + 24 * b + c], want[o * 24 + c]);
                    assert!(
                        (got - want).abs() <= 1e-4 * (1.0 + want.abs()),
                        "K = {K}, block {b}, channel {o}, column {c}: {got} against {want}"
                    );
                }
            }
        }
        // A table reaching past the data is refused and leaves the accumulators alone.
        let mut untouched = [1f32; 4 * COLUMNS];
        let far = RowTable::new(vec![0, data.len() - base - (K - 1 + COLUMNS) + 1]);
        assert!(!rows::<K>(&data, base, &far, &weights, &mut untouched));
        assert!(untouched.iter().all(|&v| v == 1.0));
        // Too few weights for the rows: refused.
        let short = &weights[..weights.len() - 1];
        assert!(!rows::<K>(&data, base, &table, short, &mut untouched));
    }

    #[test]
    fn the_wide_kernel_equals_plain_loops_and_refuses_reads_outside() {
        check::<3>();
        check::<5>();
        check::<7>();
    }
}
