//! Whether the hot loops may run on 512-bit vectors: where the host has AVX-512 (detected at run
//! time; the workspace builds for x86-64-v3) and [`set_enabled`] has not switched them off.
//! The convolutions' kernel (`nn::wide_kernel`) and the census distances
//! (`lines::census_kernel`) ask here; their outputs are the same bits either way, only the speed
//! differs.

use std::sync::atomic::{AtomicBool, Ordering};

/// Whether the 512-bit paths may run (see [`set_enabled`]).
static ENABLED: AtomicBool = AtomicBool::new(true);

/// Lets the hot loops use 512-bit vectors where the host has them (`true`, the default) or keeps
/// them on the 256-bit paths (`false`: for comparisons, as `examples/mfusenet_layers.rs narrow`).
pub fn set_enabled(enabled: bool) {
    ENABLED.store(enabled, Ordering::Relaxed);
}

/// AVX-512F (32-bit lanes: the convolutions), enabled.
pub fn avx512f() -> bool {
    ENABLED.load(Ordering::Relaxed) && detected::avx512f()
}

/// AVX-512 with byte population counts (`vpopcntb`: AVX512-BITALG and AVX512-BW), enabled: the
/// census distances' kernel. Intel from Ice Lake, AMD from Zen 4.
pub fn avx512bitalg() -> bool {
    ENABLED.load(Ordering::Relaxed) && detected::avx512bitalg()
}

/// Whether the host has AVX512-BITALG and BW, whatever [`set_enabled`] says: what the census
/// distances' 512-bit kernel needs to run safely.
pub fn host_has_avx512bitalg() -> bool {
    detected::avx512bitalg()
}

/// Whether the host has AVX-512F, whatever [`set_enabled`] says: what a 512-bit kernel needs
/// to run safely (the switch is its caller's choice).
pub fn host_has_avx512f() -> bool {
    detected::avx512f()
}

/// Whether the host has AVX-512F and AVX512-BF16 (`vdpbf16ps`: pairs of bfloat16 products summed
/// into 32-bit lanes), whatever [`set_enabled`] says: what the convolutions' bfloat16 kernel
/// needs to run safely. Intel Xeon from Cooper Lake, AMD from Zen 4.
pub fn host_has_avx512bf16() -> bool {
    detected::avx512bf16()
}

/// Whether the processor says it is AMD's (CPUID's vendor string `AuthenticAMD`): where a
/// kernel's best instruction mix differs between vendors of the same instruction set.
pub fn host_is_amd() -> bool {
    detected::amd()
}

#[cfg(target_arch = "x86_64")]
mod detected {
    pub(super) fn amd() -> bool {
        // Asked once: every convolution asks, and on a virtual machine each CPUID traps to the
        // hypervisor. (Leaf 0 exists on every x86-64 processor.)
        static AMD: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *AMD.get_or_init(|| {
            let id = std::arch::x86_64::__cpuid(0);
            let vendor = [id.ebx, id.edx, id.ecx].map(u32::to_le_bytes).concat();
            vendor == *b"AuthenticAMD"
        })
    }

    pub(super) fn avx512f() -> bool {
        std::arch::is_x86_feature_detected!("avx512f")
    }

    pub(super) fn avx512bf16() -> bool {
        std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512bf16")
    }

    pub(super) fn avx512bitalg() -> bool {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512bitalg")
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod detected {
    pub(super) fn amd() -> bool {
        false
    }

    pub(super) fn avx512f() -> bool {
        false
    }

    pub(super) fn avx512bf16() -> bool {
        false
    }

    pub(super) fn avx512bitalg() -> bool {
        false
    }
}
