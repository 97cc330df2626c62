//! The 48-bit census distances of [`super::pixel_cost_tile_lines`] in AVX2 intrinsics: one
//! pixel's code against a run of its search line's codes, 32 cells per register, the six byte
//! planes' differing bits summed by carry-save adders and counted by nibble tables.
//!
//! The portable loop ([`super::census_distances_48`]) computes the same bytes, but LLVM keeps
//! the six plane pointers, the code bytes and each run's six 32-byte copies on the stack and
//! reloads them per run: at 1080p × 128 disparities that per-pixel work cost as much as the
//! distances (`perf annotate`, docs/experiments.md 2026-12-06). Here the planes are read in
//! place, the codes broadcast once per pixel and the nibble tables once per tile row.
//!
//! Where the host has AVX-512 with byte population counts (AVX512-BITALG: Intel from Ice Lake,
//! AMD from Zen 4; detected at run time, [`crate::wide::avx512bitalg`]) 64 cells per register
//! instead, each plane's differing bits counted by `vpopcntb`: the same bytes.
//!
//! Built only where the target has AVX2 (this workspace builds for x86-64-v3); elsewhere
//! [`Planes48::distances`] answers `false` and the portable loop runs.

/// Cells per run: one AVX2 register of bytes.
const RUN: usize = 32;

/// The six census planes of a neighbour's search lines, borrowed for one tile row.
pub(super) struct Planes48<'a> {
    planes: [&'a [u8]; 6],
    /// The shortest plane's length: a run ending at or before it reads inside every plane.
    len: usize,
    /// Whether the 512-bit kernel runs ([`crate::wide::avx512bitalg`], asked once per tile row).
    wide: bool,
}

impl<'a> Planes48<'a> {
    pub(super) fn new(planes: [&'a [u8]; 6]) -> Self {
        let len = planes.iter().map(|p| p.len()).min().unwrap_or(0);
        Self {
            planes,
            len,
            wide: crate::wide::avx512bitalg(),
        }
    }

    /// Writes the distances of `codes` to the cells `from .. from + out.len()` of the planes into
    /// `out`. Answers `false`, writing nothing, where the kernel is not built for this target or
    /// where the whole runs it reads would pass a plane's end (the caller then runs the portable
    /// loop).
    #[allow(unsafe_code)]
    #[inline]
    pub(super) fn distances(&self, from: usize, codes: [u8; 6], out: &mut [u8]) -> bool {
        let runs = out.len().div_ceil(RUN);
        let end = runs.checked_mul(RUN).and_then(|n| n.checked_add(from));
        if end.is_none_or(|end| end > self.len) {
            return false;
        }
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        {
            // SAFETY: the target has AVX2 (compile-time feature); every run reads
            // `from + 32·k .. from + 32·(k + 1)` with `k < runs` of each plane, which ends at or
            // before `self.len` (checked above), and writes inside `out` (the last partial run
            // through a local buffer).
            if self.wide {
                // SAFETY: the host has AVX-512F, BW and BITALG (`wide`); every byte read lies in
                // `from .. from + out.len()` of a plane, inside `self.len` (checked above), and
                // every byte written inside `out`.
                unsafe { avx512::distances(&self.planes, from, codes, out) };
            } else {
                unsafe { avx2::distances(&self.planes, from, codes, out) };
            }
            true
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        {
            let _ = (from, codes, self.planes);
            false
        }
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[allow(unsafe_code)]
mod avx2 {
    use std::arch::x86_64::{
        __m256i, _mm256_add_epi8, _mm256_and_si256, _mm256_loadu_si256, _mm256_or_si256, _mm256_set1_epi8,
        _mm256_setr_epi8, _mm256_shuffle_epi8, _mm256_srli_epi16, _mm256_storeu_si256, _mm256_xor_si256,
    };

    use super::RUN;

    /// Population counts of the bytes of `v` by two nibble look-ups in `table`.
    #[inline(always)]
    unsafe fn count(v: __m256i, table: __m256i, low: __m256i) -> __m256i {
        // SAFETY: AVX2 (the module's condition); registers only.
        unsafe {
            let lo = _mm256_and_si256(v, low);
            let hi = _mm256_and_si256(_mm256_srli_epi16::<4>(v), low);
            _mm256_add_epi8(_mm256_shuffle_epi8(table, lo), _mm256_shuffle_epi8(table, hi))
        }
    }

    /// One run: the distances of the six broadcast `codes` to the 32 cells at `at` of each plane.
    #[inline(always)]
    unsafe fn run(planes: &[*const u8; 6], at: usize, codes: &[__m256i; 6], tables: &[__m256i; 3]) -> __m256i {
        // SAFETY: AVX2 (the module's condition); the caller guarantees that the 32 bytes at
        // `at` of every plane are readable.
        unsafe {
            let load = |k: usize| _mm256_xor_si256(_mm256_loadu_si256(planes[k].add(at).cast()), codes[k]);
            let (x0, x1, x2) = (load(0), load(1), load(2));
            let (x3, x4, x5) = (load(3), load(4), load(5));
            // Full adders: (sum, carry) of three bits.
            let u = _mm256_xor_si256(x0, x1);
            let s1 = _mm256_xor_si256(u, x2);
            let k1 = _mm256_or_si256(_mm256_and_si256(x0, x1), _mm256_and_si256(u, x2));
            let u = _mm256_xor_si256(x3, x4);
            let s2 = _mm256_xor_si256(u, x5);
            let k2 = _mm256_or_si256(_mm256_and_si256(x3, x4), _mm256_and_si256(u, x5));
            let ones = _mm256_xor_si256(s1, s2);
            let t = _mm256_and_si256(s1, s2);
            let u = _mm256_xor_si256(t, k1);
            let twos = _mm256_xor_si256(u, k2);
            let fours = _mm256_or_si256(_mm256_and_si256(t, k1), _mm256_and_si256(u, k2));
            let low = _mm256_set1_epi8(0x0f);
            // The tables hold 1, 2 and 4 × a nibble's population count: the weights of the bits.
            _mm256_add_epi8(
                count(ones, tables[0], low),
                _mm256_add_epi8(count(twos, tables[1], low), count(fours, tables[2], low)),
            )
        }
    }

    /// A nibble population-count table scaled by `w`, in both 128-bit lanes.
    #[inline(always)]
    fn table(w: i8) -> __m256i {
        let c = [0i8, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4].map(|n| n * w);
        // SAFETY: AVX is enabled for this module's target.
        unsafe {
            _mm256_setr_epi8(
                c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], c[10], c[11], c[12], c[13], c[14], c[15],
                c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], c[10], c[11], c[12], c[13], c[14], c[15],
            )
        }
    }

    /// See [`super::Planes48::distances`]; the caller has checked every read.
    #[inline(always)]
    pub(super) unsafe fn distances(planes: &[&[u8]; 6], from: usize, codes: [u8; 6], out: &mut [u8]) {
        let pointers = planes.map(<[u8]>::as_ptr);
        // SAFETY: AVX2 (the module's condition); every run reads inside the planes (the
        // caller's check) and writes one of `out`'s whole runs or a local buffer.
        unsafe {
            let codes = codes.map(|c| _mm256_set1_epi8(c as i8));
            let tables = [table(1), table(2), table(4)];
            let (whole, rest) = out.as_chunks_mut::<RUN>();
            let done = whole.len() * RUN;
            for (k, cells) in whole.iter_mut().enumerate() {
                let v = run(&pointers, from + k * RUN, &codes, &tables);
                _mm256_storeu_si256(cells.as_mut_ptr().cast(), v);
            }
            if !rest.is_empty() {
                let mut last = [0u8; RUN];
                let v = run(&pointers, from + done, &codes, &tables);
                _mm256_storeu_si256(last.as_mut_ptr().cast(), v);
                let m = rest.len();
                rest.copy_from_slice(&last[..m]);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod avx512 {
    use std::arch::x86_64::{
        __m512i, __mmask64, _mm512_add_epi8, _mm512_mask_storeu_epi8, _mm512_maskz_loadu_epi8, _mm512_popcnt_epi8,
        _mm512_set1_epi8, _mm512_xor_si512,
    };

    /// Cells per register.
    const WIDE: usize = 64;

    /// See [`super::Planes48::distances`]: 64 cells at a time, the last run masked, so that only
    /// the bytes `from .. from + out.len()` of each plane are read.
    ///
    /// # Safety
    /// The host has AVX-512F, BW and BITALG; each plane holds at least `from + out.len()` bytes.
    #[target_feature(enable = "avx512f,avx512bw,avx512bitalg")]
    pub(super) unsafe fn distances(planes: &[&[u8]; 6], from: usize, codes: [u8; 6], out: &mut [u8]) {
        let codes = codes.map(|c| _mm512_set1_epi8(c as i8));
        let pointers = planes.map(<[u8]>::as_ptr);
        let mut done = 0;
        while done < out.len() {
            let n = (out.len() - done).min(WIDE);
            let mask: __mmask64 = if n == WIDE { !0 } else { (1u64 << n) - 1 };
            // SAFETY: the masked loads read only the `n` bytes at `from + done` of each plane
            // (inside it, the caller's guarantee); the masked store writes `out[done .. done + n]`.
            unsafe {
                let count = |k: usize| -> __m512i {
                    let cells = _mm512_maskz_loadu_epi8(mask, pointers[k].add(from + done).cast());
                    _mm512_popcnt_epi8(_mm512_xor_si512(cells, codes[k]))
                };
                let sum = _mm512_add_epi8(
                    _mm512_add_epi8(_mm512_add_epi8(count(0), count(1)), _mm512_add_epi8(count(2), count(3))),
                    _mm512_add_epi8(count(4), count(5)),
                );
                _mm512_mask_storeu_epi8(out.as_mut_ptr().add(done).cast(), mask, sum);
            }
            done += n;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain definition: the bits in which the 48-bit codes differ.
    fn plain(planes: [&[u8]; 6], from: usize, codes: [u8; 6], n: usize) -> Vec<u8> {
        (0..n)
            .map(|d| {
                (0..6)
                    .map(|k| (planes[k][from + d] ^ codes[k]).count_ones() as u8)
                    .sum()
            })
            .collect()
    }

    /// A xorshift stream of bytes from `state`.
    fn bytes(mut state: u64) -> impl FnMut() -> u8 {
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 24) as u8
        }
    }

    /// The six planes of `planes` as the kernels take them.
    fn six(planes: &[Vec<u8>]) -> [&[u8]; 6] {
        std::array::from_fn(|k| &planes[k][..])
    }

    #[test]
    #[allow(unsafe_code)]
    fn the_512_bit_kernel_matches_the_plain_definition_reading_only_its_cells() {
        if !crate::wide::host_has_avx512bitalg() {
            eprintln!("skipped: this host has no AVX512-BITALG (the 256-bit kernel runs; tested below)");
            return;
        }
        let mut byte = bytes(0x9e37_79b9_7f4a_7c15);
        // Planes exactly as long as the cells read: a read past them would leave the slice.
        for n in [1usize, 31, 63, 64, 65, 128, 130] {
            for from in [0usize, 5] {
                let planes: Vec<Vec<u8>> = (0..6).map(|_| (0..from + n).map(|_| byte()).collect()).collect();
                let view = six(&planes);
                let codes = [byte(), byte(), byte(), byte(), byte(), byte()];
                // One cell past the run stays as it was.
                let mut out = vec![0xaa; n + 1];
                // SAFETY: the host has the features (checked above); each plane holds `from + n` bytes.
                unsafe { avx512::distances(&view, from, codes, &mut out[..n]) };
                assert_eq!(out[..n], plain(view, from, codes, n)[..], "n {n} from {from}");
                assert_eq!(out[n], 0xaa, "n {n} from {from}");
            }
        }
    }

    #[test]
    fn distances_match_the_plain_definition_and_refuse_reads_past_a_plane() {
        let mut byte = bytes(0x2545_f491_4f6c_dd1d);
        // Planes of different lengths: the shortest bounds the runs.
        let planes: Vec<Vec<u8>> = (0..6).map(|k| (0..300 + 7 * k).map(|_| byte()).collect()).collect();
        let view = six(&planes);
        let kernel = Planes48::new(view);
        let built = cfg!(all(target_arch = "x86_64", target_feature = "avx2"));
        for n in [1usize, 31, 32, 33, 64, 100, 128] {
            for from in [0, 1, 17, 300 - n.div_ceil(RUN) * RUN, 300 - n.div_ceil(RUN) * RUN + 1] {
                let codes = [byte(), byte(), byte(), byte(), byte(), byte()];
                let mut out = vec![0xaa; n];
                let fits = from + n.div_ceil(RUN) * RUN <= 300;
                let answered = kernel.distances(from, codes, &mut out);
                assert_eq!(answered, built && fits, "n {n} from {from}");
                if answered {
                    assert_eq!(out, plain(view, from, codes, n), "n {n} from {from}");
                    // The 256-bit kernel on its own (the 512-bit one may have answered above).
                    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
                    {
                        let mut narrow = vec![0xaa; n];
                        // SAFETY: AVX2 (compile-time); the runs fit the planes (`fits`).
                        #[allow(unsafe_code)]
                        unsafe {
                            avx2::distances(&view, from, codes, &mut narrow)
                        };
                        assert_eq!(narrow, out, "n {n} from {from}");
                    }
                } else {
                    assert!(out.iter().all(|v| *v == 0xaa), "nothing written when refused");
                }
            }
        }
    }
}
