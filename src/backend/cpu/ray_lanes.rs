//! The registers a packet of rays is traced in, a ray a lane: what [`super::packet`]'s arithmetic needs of them,
//! written once for AVX (8 rays in a `__m256`) and once for AVX-512 (16 rays in a `__m512`), so that the packet walk
//! itself is written once. Each operation is the same IEEE operation lane by lane on either, so a ray gets the same
//! bits whichever register it is traced in.

use std::arch::x86_64::*;

use super::filter;
use crate::format::Ray;

/// The most rays a packet holds: the lanes of the widest register.
pub(super) const MAX_PACKET_RAYS: usize = 16;

/// A register of f32 lanes, a ray each.
///
/// # Safety
/// Every method is `unsafe` because it needs the register's instruction set (AVX for `__m256`, AVX-512F for
/// `__m512`); callers must make sure the CPU has it.
pub(super) trait RayLanes: filter::Lanes {
    /// A bit per lane, in the instruction set's own form (a register of all-ones lanes, or a mask register).
    type Mask: Copy;

    /// Lanes: rays a packet.
    const RAYS: usize;

    /// `x` in every lane.
    unsafe fn splat(x: f32) -> Self;

    /// `value` of each ray of `rays` (exactly [`RayLanes::RAYS`] of them), a ray a lane.
    unsafe fn gather(rays: &[Ray], value: impl Fn(&Ray) -> f32) -> Self;

    /// The first [`RayLanes::RAYS`] of `values`.
    unsafe fn load(values: &[f32; MAX_PACKET_RAYS]) -> Self;

    /// Stores the lanes into the first [`RayLanes::RAYS`] of `values`.
    unsafe fn store(self, values: &mut [f32; MAX_PACKET_RAYS]);

    /// `self + other`, lane by lane.
    unsafe fn add(self, other: Self) -> Self;

    /// `self / other`, lane by lane.
    unsafe fn div(self, other: Self) -> Self;

    /// The smaller lane by lane; `other` where either is NaN (as `vminps` does).
    unsafe fn min(self, other: Self) -> Self;

    /// The larger lane by lane; `other` where either is NaN (as `vmaxps` does).
    unsafe fn max(self, other: Self) -> Self;

    /// `|self|`, lane by lane.
    unsafe fn abs(self) -> Self;

    /// Where `self ≤ other` (false with NaN).
    unsafe fn le(self, other: Self) -> Self::Mask;

    /// Where `self < other` (false with NaN).
    unsafe fn lt(self, other: Self) -> Self::Mask;

    /// Where `self == other` (false with NaN; `0 == −0`).
    unsafe fn eq(self, other: Self) -> Self::Mask;

    /// `a` in the lanes set in `mask`, `b` in the others.
    unsafe fn select(mask: Self::Mask, a: Self, b: Self) -> Self;

    /// Where both masks are set.
    unsafe fn and(a: Self::Mask, b: Self::Mask) -> Self::Mask;

    /// The mask as bits, lane `i` in bit `i`.
    unsafe fn bits(mask: Self::Mask) -> u32;

    /// The mask of the lanes whose bits are set in `bits`.
    unsafe fn mask(bits: u32) -> Self::Mask;

    /// The smallest of the lanes set in `mask`; +∞ when none is.
    unsafe fn least(self, mask: Self::Mask) -> f32;

    /// The largest of the lanes set in `mask`, a NaN lane counted as −∞; −∞ when none is set.
    unsafe fn most(self, mask: Self::Mask) -> f32;

    /// The smallest lane (the lanes hold no NaN).
    unsafe fn smallest(self) -> f32;

    /// The largest lane (the lanes hold no NaN).
    unsafe fn largest(self) -> f32;

    /// The lanes folded to eight, for a reduction over all of them: lane by lane the smaller and the larger of the
    /// two halves of sixteen lanes, or eight lanes themselves twice (the lanes hold no NaN).
    unsafe fn fold_to_eight(self) -> (__m256, __m256);
}

impl RayLanes for __m256 {
    type Mask = __m256;
    const RAYS: usize = 8;

    #[inline(always)]
    unsafe fn splat(x: f32) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_set1_ps(x) }
    }

    #[inline(always)]
    unsafe fn gather(rays: &[Ray], value: impl Fn(&Ray) -> f32) -> Self {
        let [a, b, c, d, e, f, g, h] = rays else { panic!("a packet of 8 rays") };
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_setr_ps(value(a), value(b), value(c), value(d), value(e), value(f), value(g), value(h)) }
    }

    #[inline(always)]
    unsafe fn load(values: &[f32; MAX_PACKET_RAYS]) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract); the first eight of sixteen floats are read.
        unsafe { _mm256_loadu_ps(values.as_ptr()) }
    }

    #[inline(always)]
    unsafe fn store(self, values: &mut [f32; MAX_PACKET_RAYS]) {
        // SAFETY: the CPU has AVX (the trait's contract); the first eight of sixteen floats are written.
        unsafe { _mm256_storeu_ps(values.as_mut_ptr(), self) }
    }

    #[inline(always)]
    unsafe fn add(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_add_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn div(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_div_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn min(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_min_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn max(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_max_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn abs(self) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_and_ps(self, _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX))) }
    }

    #[inline(always)]
    unsafe fn le(self, other: Self) -> Self::Mask {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_cmp_ps::<_CMP_LE_OQ>(self, other) }
    }

    #[inline(always)]
    unsafe fn lt(self, other: Self) -> Self::Mask {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_cmp_ps::<_CMP_LT_OQ>(self, other) }
    }

    #[inline(always)]
    unsafe fn eq(self, other: Self) -> Self::Mask {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_cmp_ps::<_CMP_EQ_OQ>(self, other) }
    }

    #[inline(always)]
    unsafe fn select(mask: Self::Mask, a: Self, b: Self) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_blendv_ps(b, a, mask) }
    }

    #[inline(always)]
    unsafe fn and(a: Self::Mask, b: Self::Mask) -> Self::Mask {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_and_ps(a, b) }
    }

    #[inline(always)]
    unsafe fn bits(mask: Self::Mask) -> u32 {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_movemask_ps(mask) as u32 }
    }

    #[inline(always)]
    unsafe fn mask(bits: u32) -> Self::Mask {
        // Lane i keeps bit i of `bits`, compared with that bit alone. (An integer compare: AVX2.)
        unsafe {
            let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
            let set = _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane_bits);
            _mm256_castsi256_ps(_mm256_cmpeq_epi32(set, lane_bits))
        }
    }

    #[inline(always)]
    unsafe fn least(self, mask: Self::Mask) -> f32 {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe { _mm256_blendv_ps(_mm256_set1_ps(f32::INFINITY), self, mask).smallest() }
    }

    #[inline(always)]
    unsafe fn most(self, mask: Self::Mask) -> f32 {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe {
            // `vmaxps` gives its second operand, −∞, where `self` is NaN.
            let lowest = _mm256_set1_ps(f32::NEG_INFINITY);
            _mm256_blendv_ps(lowest, _mm256_max_ps(self, lowest), mask).largest()
        }
    }

    #[inline(always)]
    unsafe fn smallest(self) -> f32 {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe {
            let half = _mm_min_ps(_mm256_castps256_ps128(self), _mm256_extractf128_ps::<1>(self));
            let quarter = _mm_min_ps(half, _mm_movehl_ps(half, half));
            _mm_cvtss_f32(_mm_min_ss(quarter, _mm_shuffle_ps::<0b01>(quarter, quarter)))
        }
    }

    #[inline(always)]
    unsafe fn largest(self) -> f32 {
        // SAFETY: the CPU has AVX (the trait's contract).
        unsafe {
            let half = _mm_max_ps(_mm256_castps256_ps128(self), _mm256_extractf128_ps::<1>(self));
            let quarter = _mm_max_ps(half, _mm_movehl_ps(half, half));
            _mm_cvtss_f32(_mm_max_ss(quarter, _mm_shuffle_ps::<0b01>(quarter, quarter)))
        }
    }

    #[inline(always)]
    unsafe fn fold_to_eight(self) -> (__m256, __m256) {
        (self, self)
    }
}

impl RayLanes for __m512 {
    type Mask = __mmask16;
    const RAYS: usize = 16;

    #[inline(always)]
    unsafe fn splat(x: f32) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_set1_ps(x) }
    }

    #[inline(always)]
    unsafe fn gather(rays: &[Ray], value: impl Fn(&Ray) -> f32) -> Self {
        let [a, b, c, d, e, f, g, h, i, j, k, l, m, n, o, p] = rays else { panic!("a packet of 16 rays") };
        let values = [
            value(a),
            value(b),
            value(c),
            value(d),
            value(e),
            value(f),
            value(g),
            value(h),
            value(i),
            value(j),
            value(k),
            value(l),
            value(m),
            value(n),
            value(o),
            value(p),
        ];
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_loadu_ps(values.as_ptr()) }
    }

    #[inline(always)]
    unsafe fn load(values: &[f32; MAX_PACKET_RAYS]) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_loadu_ps(values.as_ptr()) }
    }

    #[inline(always)]
    unsafe fn store(self, values: &mut [f32; MAX_PACKET_RAYS]) {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_storeu_ps(values.as_mut_ptr(), self) }
    }

    #[inline(always)]
    unsafe fn add(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_add_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn div(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_div_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn min(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_min_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn max(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_max_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn abs(self) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_abs_ps(self) }
    }

    #[inline(always)]
    unsafe fn le(self, other: Self) -> Self::Mask {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_cmp_ps_mask::<_CMP_LE_OQ>(self, other) }
    }

    #[inline(always)]
    unsafe fn lt(self, other: Self) -> Self::Mask {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_cmp_ps_mask::<_CMP_LT_OQ>(self, other) }
    }

    #[inline(always)]
    unsafe fn eq(self, other: Self) -> Self::Mask {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(self, other) }
    }

    #[inline(always)]
    unsafe fn select(mask: Self::Mask, a: Self, b: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_mask_blend_ps(mask, b, a) }
    }

    #[inline(always)]
    unsafe fn and(a: Self::Mask, b: Self::Mask) -> Self::Mask {
        a & b
    }

    #[inline(always)]
    unsafe fn bits(mask: Self::Mask) -> u32 {
        u32::from(mask)
    }

    #[inline(always)]
    unsafe fn mask(bits: u32) -> Self::Mask {
        bits as u16
    }

    #[inline(always)]
    unsafe fn least(self, mask: Self::Mask) -> f32 {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_mask_blend_ps(mask, _mm512_set1_ps(f32::INFINITY), self).smallest() }
    }

    #[inline(always)]
    unsafe fn most(self, mask: Self::Mask) -> f32 {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe {
            // `vmaxps` gives its second operand, −∞, where `self` is NaN.
            let lowest = _mm512_set1_ps(f32::NEG_INFINITY);
            _mm512_mask_blend_ps(mask, lowest, _mm512_max_ps(self, lowest)).largest()
        }
    }

    #[inline(always)]
    unsafe fn smallest(self) -> f32 {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm256_min_ps(_mm512_castps512_ps256(self), upper_half(self)).smallest() }
    }

    #[inline(always)]
    unsafe fn largest(self) -> f32 {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm256_max_ps(_mm512_castps512_ps256(self), upper_half(self)).largest() }
    }

    #[inline(always)]
    unsafe fn fold_to_eight(self) -> (__m256, __m256) {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe {
            let (low, high) = (_mm512_castps512_ps256(self), upper_half(self));
            (_mm256_min_ps(low, high), _mm256_max_ps(low, high))
        }
    }
}

/// Lanes 8 to 15 of `v`.
///
/// # Safety
/// The CPU must have AVX-512F.
#[inline(always)]
unsafe fn upper_half(v: __m512) -> __m256 {
    // SAFETY: the CPU has AVX-512F (the caller's contract).
    unsafe { _mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(_mm512_castps_pd(v))) }
}
