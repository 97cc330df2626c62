//! Register-blocked FMA kernels for the small 3D convolutions (kernels 3 and 5), in inline
//! assembly. The same sums as [`super::conv`]'s portable loop: one output block of 4 channels ×
//! 24 columns held in 12 AVX registers, fed by every input row the block reads (a list of
//! offsets into the padded input) and that row's `K` taps × 4 channels of weights. LLVM, given
//! that loop, unrolls the taps and hoists their loads ahead of the multiply-adds, so that at
//! `K` = 3 the accumulators spilled to the stack around every row (the lite network's 3³ layers
//! at 21–36 % of the host's FMA peak against 87 % for the paper's 7³ ones,
//! `examples/mfusenet_layers.rs`); written out, the loop keeps 3 input vectors, 1 broadcast
//! weight and the 12 accumulators in the 16 registers. At `K` = 7 LLVM's own loop is as fast.
//!
//! Built only where the target has AVX2 and FMA (this workspace builds for x86-64-v3); elsewhere
//! [`rows`] answers `false` and the portable loop runs.

/// Floats in an output block's accumulators: 4 channels × 3 vectors × 8 lanes, `[o][j][lane]`.
pub(super) const ACCUMULATORS: usize = 96;

/// The input rows an output block reads, as offsets from the block's first column, with their
/// largest (so that one comparison bounds every read).
pub(super) struct RowTable {
    offsets: Vec<usize>,
    max: usize,
}

impl RowTable {
    pub(super) fn new(offsets: Vec<usize>) -> Self {
        let max = offsets.iter().copied().max().unwrap_or(0);
        Self { offsets, max }
    }

    /// Whether a block `columns` wide at `base` with `k` taps reads inside `data_len` floats
    /// from every row of the table, and `weights_len` floats hold the rows' `k · 4` weights.
    pub(super) fn fits(&self, base: usize, (k, columns): (usize, usize), data_len: usize, weights_len: usize) -> bool {
        let end = base.checked_add(self.max).and_then(|a| a.checked_add(k - 1 + columns));
        end.is_some_and(|end| end <= data_len) && weights_len >= self.offsets.len() * k * 4
    }

    /// The offsets, in the order of the weights' rows.
    pub(super) fn offsets(&self) -> &[usize] {
        &self.offsets
    }
}

/// `acc[o][j][l] += Σ_r Σ_tw weights[r][tw][o] · data[base + rows[r] + tw + 8j + l]` for
/// `K` ∈ {3, 5}: every row of one output block, `weights` `[row][tw][o]`. Answers `false`,
/// doing nothing, where the kernel is not built for this target or `K`, or where a read would
/// leave `data` or `weights` (the caller then runs the portable loop).
#[allow(unsafe_code)]
pub(super) fn rows<const K: usize>(
    data: &[f32],
    base: usize,
    rows: &RowTable,
    weights: &[f32],
    acc: &mut [f32; ACCUMULATORS],
) -> bool {
    // The last float read from a row is column (K − 1) + 23.
    if !rows.fits(base, (K, 24), data.len(), weights.len()) {
        return false;
    }
    let rows = &rows.offsets;
    if rows.is_empty() {
        return true;
    }
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    {
        // SAFETY: every row read is `data[base + r .. base + r + K − 1 + 24]` with `r` at most
        // the table's largest entry (made with it, never changed), inside `data` (checked); the
        // weights read are `weights[.. rows.len() · K · 4]` (checked); `acc` is 96 floats read
        // and written whole; the target has AVX2 and FMA (cfg). The loop runs `rows.len() ≥ 1`
        // times. The registers it uses are declared clobbered; it touches no stack.
        unsafe {
            match K {
                3 => k3(
                    data.as_ptr().add(base),
                    rows.as_ptr(),
                    rows.len(),
                    weights.as_ptr(),
                    acc,
                ),
                5 => k5(
                    data.as_ptr().add(base),
                    rows.as_ptr(),
                    rows.len(),
                    weights.as_ptr(),
                    acc,
                ),
                _ => return false,
            }
        }
        true
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma")))]
    {
        let _ = acc;
        false
    }
}

/// The kernel of [`rows`] for one `K`, `data` at the block's `base`: the accumulators loaded,
/// then per row its address from the table, the `K` taps ([`tap`]), the weights advanced by a
/// row's `K · 4` floats; the accumulators stored.
macro_rules! kernel {
    ($name:ident, $advance:literal, [$($body:expr),* $(,)?]) => {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
        #[allow(unsafe_code)]
        #[inline]
        unsafe fn $name(
            data: *const f32,
            rows: *const usize,
            count: usize,
            weights: *const f32,
            acc: &mut [f32; ACCUMULATORS],
        ) {
            // SAFETY: see `rows`.
            unsafe {
                std::arch::asm!(
                    "vmovups ymm4, [{acc}]",
                    "vmovups ymm5, [{acc} + 32]",
                    "vmovups ymm6, [{acc} + 64]",
                    "vmovups ymm7, [{acc} + 96]",
                    "vmovups ymm8, [{acc} + 128]",
                    "vmovups ymm9, [{acc} + 160]",
                    "vmovups ymm10, [{acc} + 192]",
                    "vmovups ymm11, [{acc} + 224]",
                    "vmovups ymm12, [{acc} + 256]",
                    "vmovups ymm13, [{acc} + 288]",
                    "vmovups ymm14, [{acc} + 320]",
                    "vmovups ymm15, [{acc} + 352]",
                    "2:",
                    "mov {src}, [{rows}]",
                    "lea {src}, [{data} + {src} * 4]",
                    $($body,)*
                    $advance,
                    "add {rows}, 8",
                    "dec {count}",
                    "jnz 2b",
                    "vmovups [{acc}], ymm4",
                    "vmovups [{acc} + 32], ymm5",
                    "vmovups [{acc} + 64], ymm6",
                    "vmovups [{acc} + 96], ymm7",
                    "vmovups [{acc} + 128], ymm8",
                    "vmovups [{acc} + 160], ymm9",
                    "vmovups [{acc} + 192], ymm10",
                    "vmovups [{acc} + 224], ymm11",
                    "vmovups [{acc} + 256], ymm12",
                    "vmovups [{acc} + 288], ymm13",
                    "vmovups [{acc} + 320], ymm14",
                    "vmovups [{acc} + 352], ymm15",
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

/// One tap `t` of a row (`{src}` the row, `{w}` its weights): the 3 input vectors at column
/// `t`, then per output channel `o` the weight `[t][o]` broadcast into 3 multiply-adds.
macro_rules! tap {
    ($t:literal) => {
        concat!(
            "vmovups ymm0, [{src} + 4*",
            $t,
            "]\n",
            "vmovups ymm1, [{src} + 4*",
            $t,
            " + 32]\n",
            "vmovups ymm2, [{src} + 4*",
            $t,
            " + 64]\n",
            "vbroadcastss ymm3, [{w} + 16*",
            $t,
            "]\n",
            "vfmadd231ps ymm4, ymm0, ymm3\n",
            "vfmadd231ps ymm5, ymm1, ymm3\n",
            "vfmadd231ps ymm6, ymm2, ymm3\n",
            "vbroadcastss ymm3, [{w} + 16*",
            $t,
            " + 4]\n",
            "vfmadd231ps ymm7, ymm0, ymm3\n",
            "vfmadd231ps ymm8, ymm1, ymm3\n",
            "vfmadd231ps ymm9, ymm2, ymm3\n",
            "vbroadcastss ymm3, [{w} + 16*",
            $t,
            " + 8]\n",
            "vfmadd231ps ymm10, ymm0, ymm3\n",
            "vfmadd231ps ymm11, ymm1, ymm3\n",
            "vfmadd231ps ymm12, ymm2, ymm3\n",
            "vbroadcastss ymm3, [{w} + 16*",
            $t,
            " + 12]\n",
            "vfmadd231ps ymm13, ymm0, ymm3\n",
            "vfmadd231ps ymm14, ymm1, ymm3\n",
            "vfmadd231ps ymm15, ymm2, ymm3",
        )
    };
}

kernel!(k3, "add {w}, 48", [tap!(0), tap!(1), tap!(2)]);
kernel!(k5, "add {w}, 80", [tap!(0), tap!(1), tap!(2), tap!(3), tap!(4)]);

/// Asks the cache for the input rows `data[at + offset ..][..len]` of every `K`-th offset of
/// `rows` from the `K − 1`-th (each group's last kernel row: the rows an output row reads first
/// that the row before did not). The convolutions' loads waited on these rows: an output row
/// reads `K²` rows per input channel, scattered over `K` planes, which the hardware prefetchers
/// did not bring in time (MFuseNet's kernel stalled at each row's first load; asked two output
/// rows ahead, the 640×360 five-view network took a fifth less time). A prefetch never faults:
/// addresses past `data` are not asked for.
#[inline]
#[allow(unsafe_code)]
pub(super) fn prefetch_last_rows<const K: usize>(data: &[f32], at: usize, rows: &RowTable, len: usize) {
    #[cfg(target_arch = "x86_64")]
    for &offset in rows.offsets().iter().skip(K - 1).step_by(K) {
        let Some(row) = data.get(at + offset..(at + offset + len).min(data.len())) else {
            return;
        };
        for line in row.chunks(16) {
            // SAFETY: a prefetch reads nothing the program sees and never faults; the address is
            // inside `data` besides.
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(line.as_ptr().cast::<i8>())
            };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, at, rows, len);
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    #[test]
    fn asking_for_rows_past_the_data_is_harmless() {
        // Rows inside, straddling the end and wholly past it (a last output row's rows ahead).
        let data = vec![1f32; 1000];
        let table = RowTable::new(vec![0, 100, 200, 900, 990, 5000]);
        for at in [0, 500, 999, 1000, usize::MAX / 2] {
            prefetch_last_rows::<3>(&data, at, &table, 50);
            prefetch_last_rows::<1>(&data, at, &table, 50);
        }
        assert_eq!(data.iter().sum::<f32>(), 1000.0, "nothing written");
    }

    /// The sums of [`rows`] by plain loops (also the wide kernel's reference, a block at a time).
    pub(in crate::nn) fn plain<const K: usize>(
        data: &[f32],
        base: usize,
        offsets: &[usize],
        weights: &[f32],
    ) -> Vec<f32> {
        let mut acc = vec![0f32; ACCUMULATORS];
        for (r, &offset) in offsets.iter().enumerate() {
            for tw in 0..K {
                for o in 0..4 {
                    for c in 0..24 {
                        acc[o * 24 + c] += weights[(r * K + tw) * 4 + o] * data[base + offset + tw + c];
                    }
                }
            }
        }
        acc
    }

    /// Data, scattered row offsets and their weights for one kernel size (shared with the wide
    /// kernel's tests).
    pub(in crate::nn) fn case<const K: usize>() -> (Vec<f32>, Vec<usize>, Vec<f32>) {
        let data: Vec<f32> = (0..4000).map(|i| ((i * 37 % 101) as f32 - 50.0) / 25.0).collect();
        let offsets = vec![0, 50, 100, 1200, 1250, 3000, 7, 2900];
        let weights: Vec<f32> = (0..offsets.len() * K * 4)
            .map(|i| ((i * 13 % 29) as f32 - 14.0) / 7.0)
            .collect();
        (data, offsets, weights)
    }

    fn check<const K: usize>() {
        let (data, offsets, weights) = case::<K>();
        let table = RowTable::new(offsets.clone());
        let base = 40;
        let mut acc = [0f32; ACCUMULATORS];
        let built = cfg!(all(
            target_arch = "x86_64",
            target_feature = "avx2",
            target_feature = "fma"
        ));
        let ran = rows::<K>(&data, base, &table, &weights, &mut acc);
        assert_eq!(ran, built, "K = {K}: the kernel runs exactly where it is built");
        if !built {
            println!("skipped: no AVX2/FMA kernel on this target (the portable loop runs)");
            return;
        }
        let expected = plain::<K>(&data, base, &offsets, &weights);
        for (i, (got, want)) in acc.iter().zip(&expected).enumerate() {
            assert!(
                (got - want).abs() <= 1e-4 * (1.0 + want.abs()),
                "K = {K}, accumulator {i}: {got} against {want}"
            );
        }
        // A table reaching past the data is refused and leaves the accumulators alone.
        let mut untouched = [1f32; ACCUMULATORS];
        let far = RowTable::new(vec![0, data.len() - base - (K - 1 + 24) + 1]);
        assert!(!rows::<K>(&data, base, &far, &weights, &mut untouched));
        assert!(untouched.iter().all(|&v| v == 1.0));
        // Too few weights for the rows: refused.
        assert!(!rows::<K>(
            &data,
            base,
            &table,
            &weights[..weights.len() - 1],
            &mut untouched
        ));
    }

    #[test]
    fn the_assembly_kernels_equal_plain_loops_and_refuse_reads_outside() {
        check::<3>();
        check::<5>();
    }
}
