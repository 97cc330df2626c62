//! The convolutions' inner loop on Intel's matrix unit (AMX: `tdpbf16ps` multiplies a 16 × 32
//! bfloat16 tile by a 32 × 16 one into 16 × 16 f32 sums, 8,192 products per instruction), where
//! the host has AMX-BF16 and the kernel grants this process the tile state (Linux's
//! `ARCH_REQ_XCOMP_PERM`). On the Xeons that have it, the vector units' `vdpbf16ps` issue on
//! one port ([`super::bf16_kernel::preferred`] declines them), while one core's matrix unit makes
//! about sixteen times the products per cycle of its two FMA ports.
//!
//! It reads what the channel-pair path of [`super::bf16_kernel`] reads: the padded input as
//! bfloat16 channel pairs (slot `i` of row `2p` holding `(x_2p[i], x_2p+1[i])`), a table of each
//! pair's `K²` rows, and writes the same wide block (4 output channels × 48 columns). The block
//! is a matrix product per input row `r`:
//!
//! - **A** (12 × `K + 3` pairs): tile row `m` is the row's `K + 3` pairs from column `4m`, a load
//!   with a stride of 4 slots (the rows overlap; no copy is made);
//! - **B** (`K + 3` × 16, packed once per layer by [`pack_weights`]): column `4o + j` of row `k`
//!   holds the pair of weights of tap `k − j` for output channel `o` (zero outside the kernel);
//! - **C** (12 × 16): row `m`, column `4o + j` is output channel `o` at column `4m + j`.
//!
//! So every tile row makes four columns of all four channels; per product a third to a half of a
//! tile's slots are zero taps (a 3³ kernel uses 3 of every 6 × 4, a 7³ one 7 of 10 × 4), which
//! the unit's throughput pays for several times over. One call makes four output rows' blocks
//! ([`ROWS_AT_ONCE`]), each B tile loaded once for the four (the unit takes about one tile row
//! per cycle from memory and a product of 12-row tiles about 12 cycles: loads, not products, were
//! the limit with a B tile per product), the four rows' C tiles summed in turn (the unit's
//! latency hidden), then transposed into the blocks.
//!
//! Inputs and weights are bfloat16, the sums f32 (denormal inputs read as zero, as the unit
//! does): the products of [`super::bf16_kernel`], summed in another order. Inference only, where
//! the layer runs in bfloat16 ([`super::conv::Precision`]).

use std::sync::atomic::{AtomicBool, Ordering};

use super::fma_kernel::RowTable;
use super::wide_kernel::COLUMNS;

/// The smallest kernel whose layers [`super::conv::Precision::Auto`] puts on the matrix unit:
/// a 3³ layer's few products per row loaded do not pay for the unit's stalls on rows outside
/// L1 (the lite network 1.69–1.87 s in f32 against 1.90–2.06 s with its 3³ layers here), a 7³
/// layer's 49 rows per channel pair do (docs/benchmarks.md).
pub const MIN_KERNEL: usize = 5;

/// Output columns per tile row.
const SPAN: usize = 4;
/// Tile rows of A and C: the block's 48 columns, 4 per row.
const TILE_ROWS: usize = COLUMNS / SPAN;
/// Columns of B and C: 4 output channels × [`SPAN`] columns.
const TILE_COLUMNS: usize = 16;

/// Whether the matrix unit may run (see [`set_enabled`]).
static ENABLED: AtomicBool = AtomicBool::new(true);

/// Lets the convolutions use the matrix unit where the host has it (`true`, the default) or
/// keeps them on the vector units (`false`: for comparisons; `MULTISCOPIC_NO_AMX=1` for `replay`).
pub fn set_enabled(enabled: bool) {
    ENABLED.store(enabled, Ordering::Relaxed);
}

/// Whether the kernel runs here: the host has AMX-BF16 and AVX512-BF16 (what the layer's
/// bfloat16 rewrite needs), the operating system granted the tile state, and neither
/// [`set_enabled`] nor the 512-bit switch ([`crate::wide::set_enabled`]) turned it off.
pub fn available() -> bool {
    ENABLED.load(Ordering::Relaxed) && super::bf16_kernel::available() && host_has_amx()
}

/// Whether this process may run AMX-BF16 instructions, whatever the switches say: the processor
/// has them, and the kernel granted the tile data state (asked once, the first time).
pub fn host_has_amx() -> bool {
    static GRANTED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *GRANTED.get_or_init(detected::amx)
}

/// Pairs of one A tile row (and rows of B): the `K − 1 + SPAN` input columns that `SPAN`
/// output columns read.
const fn pairs_per_tile_row(k: usize) -> usize {
    k - 1 + SPAN
}

/// Slots (32-bit pairs) of one row's B tile.
pub(super) const fn tile_len(k: usize) -> usize {
    pairs_per_tile_row(k) * TILE_COLUMNS
}

/// One group's weights as [`super::bf16_kernel::pack_channel_weights`] packs them (`[row][tw][o]`
/// pairs, `rows` rows of `K` taps × 4 channels) as B tiles, one per row: slot `(k, 4o + j)` of
/// row `r`'s tile is the pair of tap `k − j` of channel `o` (zero where that is no tap).
pub(super) fn pack_weights<const K: usize>(channel_weights: &[f32], rows: usize) -> Vec<f32> {
    let mut tiles = vec![0f32; rows * tile_len(K)];
    for (r, tile) in tiles.chunks_exact_mut(tile_len(K)).enumerate() {
        for (k, tile_row) in tile.chunks_exact_mut(TILE_COLUMNS).enumerate() {
            for o in 0..4 {
                for j in 0..SPAN {
                    let Some(tap) = k.checked_sub(j).filter(|&t| t < K) else {
                        continue;
                    };
                    tile_row[o * SPAN + j] = channel_weights.get((r * K + tap) * 4 + o).copied().unwrap_or(0.0);
                }
            }
        }
    }
    tiles
}

/// Output rows one call computes: every B tile loaded once for all of them (the unit loads about
/// one tile row per cycle, so a B tile per product made the loads, not the products, the limit).
pub const ROWS_AT_ONCE: usize = 4;

/// For each of [`ROWS_AT_ONCE`] output rows `b` (input rows from `bases[b]`): `outs[b][o][c] =
/// Σ_r Σ_tw ⟨pairs[bases[b] + rows[r] + tw + c], weights[r][tw][o]⟩` for the 48 columns `c` of one
/// wide block, every value written: [`super::bf16_kernel::channel_rows`]'s sums on the matrix
/// unit, `tiles` holding [`pack_weights`]'s. Answers `false`, doing nothing, where the kernel
/// does not run here ([`available`]) or a read would leave `pairs` or `tiles`; the caller then
/// runs the vector kernels.
#[allow(unsafe_code)]
pub(super) fn channel_rows<const K: usize>(
    pairs: &[f32],
    bases: [usize; ROWS_AT_ONCE],
    rows: &RowTable,
    tiles: &[f32],
    outs: &mut [[f32; 4 * COLUMNS]; ROWS_AT_ONCE],
) -> bool {
    // The last pair a row's A tile reads is column 4 · 11 + K + 2 = K − 1 + 47: the block's.
    let tiles_needed = rows.offsets().len().checked_mul(tile_len(K));
    let odd_up_to_7 = K % 2 == 1 && K <= 7;
    if !odd_up_to_7
        || !bases
            .iter()
            .all(|&base| rows.fits(base, (K, COLUMNS), pairs.len(), usize::MAX))
        || tiles_needed.is_none_or(|n| n > tiles.len())
        || !available()
    {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        let at = bases.map(|base| pairs.as_ptr().wrapping_add(base));
        // SAFETY: the process may run AMX-BF16 (`available`). Every A tile reads `pairs[base +
        // offset + 4m .. + K + 3]` for m < 12, inside `pairs` (`fits` for every base: base +
        // offset + K − 1 + 48 ≤ len); every B tile `tiles[r · tile_len .. (r + 1) · tile_len]`
        // for r < rows (checked above).
        unsafe { sums::<K>(at, rows.offsets(), tiles.as_ptr(), outs) };
        true
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = outs;
        false
    }
}

#[cfg(target_arch = "x86_64")]
thread_local! {
    /// The kernel size whose tile shapes this thread's tile configuration holds (0: none).
    static CONFIGURED: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

/// The tile configuration for kernel size `k` (palette 1): tiles 0–3 the C sums (12 rows of 16
/// f32), 4 and 5 the A inputs (12 rows of `k + 3` pairs), 6 and 7 the B weights (`k + 3` rows of
/// 16 pairs).
#[cfg(target_arch = "x86_64")]
#[repr(C, align(64))]
struct TileConfig([u8; 64]);

#[cfg(target_arch = "x86_64")]
impl TileConfig {
    fn for_kernel(k: usize) -> Self {
        let mut bytes = [0u8; 64];
        bytes[0] = 1;
        let pairs = pairs_per_tile_row(k);
        // (u16 bytes per row at 16 + 2t, u8 rows at 48 + t; every value below 256.)
        let shapes = [
            (TILE_ROWS, 64),
            (TILE_ROWS, 64),
            (TILE_ROWS, 64),
            (TILE_ROWS, 64),
            (TILE_ROWS, pairs * 4),
            (TILE_ROWS, pairs * 4),
            (pairs, 64),
            (pairs, 64),
        ];
        for (t, (rows, bytes_per_row)) in shapes.into_iter().enumerate() {
            bytes[16 + 2 * t] = bytes_per_row as u8;
            bytes[48 + t] = rows as u8;
        }
        Self(bytes)
    }
}

/// The sums of [`ROWS_AT_ONCE`] blocks, each `[o][column]`, started from zero. Per input row
/// `r`: its B tile loaded once, then each output row's A tile, each product added into that
/// row's C tile (four chains in turn, so that the unit's latency is hidden).
///
/// # Safety
/// The process may run AMX-BF16 ([`host_has_amx`]); `at[b] + offset + K − 1 + 48` stays inside
/// the caller's slice for every base and every offset in `rows`; `tiles` holds `rows.len() ·
/// tile_len(K)` slots; `K` is odd and at most 7.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
unsafe fn sums<const K: usize>(
    at: [*const f32; ROWS_AT_ONCE],
    rows: &[usize],
    tiles: *const f32,
    outs: &mut [[f32; 4 * COLUMNS]; ROWS_AT_ONCE],
) {
    use std::arch::asm;
    if CONFIGURED.get() != K {
        let config = TileConfig::for_kernel(K);
        // SAFETY: a valid palette-1 configuration (every shape within 16 rows of 64 bytes),
        // 64 bytes read; the process may use the tiles (the caller's contract).
        unsafe { asm!("ldtilecfg [{0}]", in(reg) config.0.as_ptr(), options(nostack, readonly, preserves_flags)) };
        CONFIGURED.set(K);
    }
    // (The blocks are volatile, so they stay in order; the tiles are invisible to the compiler.)
    macro_rules! load_b {
        ($b:literal, $r:expr) => {
            asm!(
                concat!("tileloadd tmm", $b, ", [{b} + {sb}*1]"),
                b = in(reg) tiles.add($r * tile_len(K)), sb = in(reg) TILE_COLUMNS * 4,
                options(nostack, readonly, preserves_flags)
            )
        };
    }
    macro_rules! product {
        ($c:literal, $a:literal, $b:literal, $row:expr, $offset:expr) => {
            asm!(
                concat!("tileloadd tmm", $a, ", [{a} + {sa}*1]"),
                a = in(reg) at[$row].add($offset), sa = in(reg) SPAN * 4,
                options(nostack, readonly, preserves_flags)
            );
            asm!(concat!("tdpbf16ps tmm", $c, ", tmm", $a, ", tmm", $b), options(nostack, nomem, preserves_flags));
        };
    }
    macro_rules! input_row {
        ($b:literal, $r:expr) => {{
            let offset = rows[$r];
            load_b!($b, $r);
            product!("0", "4", $b, 0, offset);
            product!("1", "5", $b, 1, offset);
            product!("2", "4", $b, 2, offset);
            product!("3", "5", $b, 3, offset);
        }};
    }
    // SAFETY (every block below): the tiles configured above; every A and B read inside the
    // caller's slices (the contract); the stores write the local `sums`.
    unsafe {
        asm!(
            "tilezero tmm0",
            "tilezero tmm1",
            "tilezero tmm2",
            "tilezero tmm3",
            options(nostack, nomem, preserves_flags)
        );
        let n = rows.len();
        let mut r = 0;
        while r + 2 <= n {
            input_row!("6", r);
            input_row!("7", r + 1);
            r += 2;
        }
        if r < n {
            input_row!("6", r);
        }
    }
    let mut sums = [[[0f32; TILE_COLUMNS]; TILE_ROWS]; ROWS_AT_ONCE];
    let stride = TILE_COLUMNS * 4;
    // SAFETY: each store writes 12 rows of 64 bytes into its own `[[f32; 16]; 12]`.
    unsafe {
        asm!("tilestored [{p} + {s}*1], tmm0", p = in(reg) sums[0].as_mut_ptr(), s = in(reg) stride, options(nostack, preserves_flags));
        asm!("tilestored [{p} + {s}*1], tmm1", p = in(reg) sums[1].as_mut_ptr(), s = in(reg) stride, options(nostack, preserves_flags));
        asm!("tilestored [{p} + {s}*1], tmm2", p = in(reg) sums[2].as_mut_ptr(), s = in(reg) stride, options(nostack, preserves_flags));
        asm!("tilestored [{p} + {s}*1], tmm3", p = in(reg) sums[3].as_mut_ptr(), s = in(reg) stride, options(nostack, preserves_flags));
    }
    // Row m, columns 4o .. 4o + 4 of a C tile → channel o, columns 4m .. 4m + 4 of its block.
    for (out, tile) in outs.iter_mut().zip(&sums) {
        for (m, tile_row) in tile.iter().enumerate() {
            for o in 0..4 {
                let to = o * COLUMNS + m * SPAN;
                out[to..to + SPAN].copy_from_slice(&tile_row[o * SPAN..(o + 1) * SPAN]);
            }
        }
    }
}

#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
mod detected {
    /// The processor's AMX-TILE and AMX-BF16 (CPUID leaf 7: EDX bits 24 and 22), the tile state
    /// enabled by the operating system (XCR0 bits 17 and 18), and the kernel's grant of the tile
    /// data to this process (`arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`, Linux 5.16
    /// on).
    #[allow(unsafe_code)]
    pub(super) fn amx() -> bool {
        const SYS_ARCH_PRCTL: i64 = 158;
        const ARCH_REQ_XCOMP_PERM: i64 = 0x1023;
        const XFEATURE_XTILEDATA: i64 = 18;
        if std::arch::x86_64::__cpuid(0).eax < 7 {
            return false;
        }
        let leaf7 = std::arch::x86_64::__cpuid_count(7, 0);
        let (tile, bf16) = (leaf7.edx & (1 << 24) != 0, leaf7.edx & (1 << 22) != 0);
        // XGETBV needs OSXSAVE (CPUID leaf 1, ECX bit 27).
        if !(tile && bf16) || std::arch::x86_64::__cpuid(1).ecx & (1 << 27) == 0 {
            return false;
        }
        let (low, _high): (u32, u32);
        // SAFETY: XGETBV with ECX = 0 reads XCR0; the processor has it (OSXSAVE above).
        unsafe {
            std::arch::asm!("xgetbv", in("ecx") 0u32, out("eax") low, out("edx") _high, options(nomem, nostack, preserves_flags));
        }
        if low & (0b11 << 17) != 0b11 << 17 {
            return false;
        }
        let answer: i64;
        // SAFETY: the arch_prctl system call with an integer request and argument; it reads and
        // writes no memory of ours. `syscall` clobbers rcx and r11.
        unsafe {
            std::arch::asm!(
                "syscall",
                inlateout("rax") SYS_ARCH_PRCTL => answer,
                in("rdi") ARCH_REQ_XCOMP_PERM,
                in("rsi") XFEATURE_XTILEDATA,
                lateout("rcx") _,
                lateout("r11") _,
                options(nostack)
            );
        }
        answer == 0
    }
}

#[cfg(not(all(target_arch = "x86_64", target_os = "linux")))]
mod detected {
    pub(super) fn amx() -> bool {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::bf16_kernel::{pack_channel_weights, to_channel_pairs};

    fn check<const K: usize>(channels: usize) {
        let (data, row, _, pair_rows, weights) = crate::nn::int16_kernel::tests::case::<K>(channels);
        let base = 3;
        let mut pairs = data.clone();
        to_channel_pairs(&mut pairs, channels, row);
        let packed = pack_channel_weights::<K>(&weights, channels);
        let table = RowTable::new(pair_rows);
        let tiles = pack_weights::<K>(&packed, table.offsets().len());
        // Four output rows from four bases (one repeated, as at a plane's last rows).
        let bases = [base, base + 1, base, base + 2];
        let mut outs = [[f32::NAN; 4 * COLUMNS]; ROWS_AT_ONCE];
        let ran = channel_rows::<K>(&pairs, bases, &table, &tiles, &mut outs);
        assert_eq!(
            ran,
            available(),
            "K = {K}: runs exactly where the matrix unit is granted"
        );
        if !ran {
            println!("skipped the AMX kernel: this host or process has no AMX-BF16");
            return;
        }
        // Against the vector kernels' portable loops: the same bfloat16 products.
        for (b, out) in bases.iter().zip(&outs) {
            let mut portable = [f32::NAN; 4 * COLUMNS];
            crate::nn::bf16_kernel::channel_rows_portable::<K>(&pairs, *b, &table, &packed, &mut portable);
            for (i, (p, k)) in portable.iter().zip(out).enumerate() {
                assert!(
                    (p - k).abs() <= 1e-4 * (1.0 + k.abs()),
                    "K = {K}, {channels} channels, base {b}, value {i}: portable {p}, AMX {k}"
                );
            }
        }
        // A table reaching past the data (for one base), or too few tiles: refused, the sums
        // left alone.
        let mut untouched = [[1f32; 4 * COLUMNS]; ROWS_AT_ONCE];
        let far =
            base + 1 + pairs.len() - (base + table.offsets().iter().max().copied().unwrap_or(0) + K - 1 + COLUMNS);
        assert!(!channel_rows::<K>(
            &pairs,
            [base, far, base, base],
            &table,
            &tiles,
            &mut untouched
        ));
        assert!(!channel_rows::<K>(
            &pairs,
            bases,
            &table,
            &tiles[..tiles.len() - 1],
            &mut untouched
        ));
        assert!(untouched.iter().flatten().all(|&v| v == 1.0));
    }

    #[test]
    fn the_matrix_unit_sums_the_products_of_the_channel_pair_loops() {
        check::<3>(4);
        check::<3>(5);
        check::<5>(4);
        check::<7>(8);
        check::<3>(16);
        check::<3>(2);
        // Another kernel size on the same thread after: the tiles configured again.
        check::<5>(6);
        check::<3>(4);
    }

    #[test]
    fn a_tile_column_holds_one_channel_at_four_columns() {
        // K = 3, one row of one channel pair: weights (w_o at tap t) = 10o + t + 1.
        let packed: Vec<f32> = (0..3)
            .flat_map(|t| (0..4).map(move |o| (10 * o + t + 1) as f32))
            .collect();
        let tiles = pack_weights::<3>(&packed, 1);
        assert_eq!(tiles.len(), 6 * 16);
        for k in 0..6 {
            for o in 0..4 {
                for j in 0..4 {
                    let want = if (j..j + 3).contains(&k) {
                        (10 * o + (k - j) + 1) as f32
                    } else {
                        0.0
                    };
                    assert_eq!(tiles[k * 16 + o * 4 + j], want, "k {k}, o {o}, j {j}");
                }
            }
        }
    }
}
