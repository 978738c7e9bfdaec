//! What the CPU's vector units can do, detected at run time (once, then read from a cache): the engine is built for
//! plain x86-64 and picks kernels compiled with `#[target_feature]` where the CPU has them.

/// Whether the CPU has every feature the AVX2 kernels are compiled with (`#[target_feature(enable =
/// "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]`): CPUs with AVX2 have the others too, but each is checked.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) fn has_avx2() -> bool {
    static AVX2: std::sync::LazyLock<bool> = std::sync::LazyLock::new(|| {
        std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("bmi1")
            && std::arch::is_x86_feature_detected!("bmi2")
            && std::arch::is_x86_feature_detected!("lzcnt")
            && std::arch::is_x86_feature_detected!("popcnt")
    });
    *AVX2
}

/// Whether the CPU has AVX-512F besides what [`has_avx2`] checks.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) fn has_avx512() -> bool {
    static AVX512: std::sync::LazyLock<bool> =
        std::sync::LazyLock::new(|| has_avx2() && std::arch::is_x86_feature_detected!("avx512f"));
    *AVX512
}

/// Whether the CPU has AVX-512VL besides what [`has_avx512`] checks: the 256-bit instructions in the EVEX encoding,
/// which reach 32 vector registers instead of 16 (the walks of single rays compiled with it keep a ray's numbers in
/// registers instead of reloading them from the stack).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) fn has_avx512vl() -> bool {
    static AVX512VL: std::sync::LazyLock<bool> =
        std::sync::LazyLock::new(|| has_avx512() && std::arch::is_x86_feature_detected!("avx512vl"));
    *AVX512VL
}
