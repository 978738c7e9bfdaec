//! The registers a packet of rays is traced in, a ray a lane: what [`super::packet`]'s arithmetic needs of them,
//! written once for AVX (8 rays in a `__m256`) and once for AVX-512 (16 rays in a `__m512`), so that the packet walk
//! itself is written once. Each operation is the same IEEE operation lane by lane on either, so a ray gets the same
//! bits whichever register it is traced in.

use std::arch::x86_64::*;
use std::mem::offset_of;

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

    /// The four floats at byte `offset` of each ray of `rays` (exactly [`RayLanes::RAYS`] of them), a register for
    /// each float, a ray a lane: `origin` or `direction` (`x`, `y`, `z`, padding), or `tmin` and the three fields
    /// after it. The rays' 16-byte quarters are read whole and transposed, four rays at a time.
    ///
    /// Panics unless the four floats lie within a ray.
    unsafe fn columns(rays: &[Ray], offset: usize) -> [Self; 4];

    /// The first [`RayLanes::RAYS`] of `values`.
    unsafe fn load(values: &[f32; MAX_PACKET_RAYS]) -> Self;

    /// The smaller lane by lane; `other` where either is NaN (as `vminps` does).
    unsafe fn min(self, other: Self) -> Self;

    /// The larger lane by lane; `other` where either is NaN (as `vmaxps` does).
    unsafe fn max(self, other: Self) -> Self;

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
    unsafe fn columns(rays: &[Ray], offset: usize) -> [Self; 4] {
        let q = quarters::<{ Self::RAYS }>(rays, offset);
        // No closures with intrinsics here: they are compiled without the instruction set and might not be inlined.
        // SAFETY: the CPU has AVX (the trait's contract); each pointer reads 16 bytes within a ray (`quarters`).
        // Register `j` holds ray `j` in its low half and ray `j + 4` in its high half, so that transposing the halves
        // alike leaves ray `i` in lane `i`.
        unsafe {
            let (a, b) = (_mm256_loadu2_m128(q[4], q[0]), _mm256_loadu2_m128(q[5], q[1]));
            let (c, d) = (_mm256_loadu2_m128(q[6], q[2]), _mm256_loadu2_m128(q[7], q[3]));
            let (ab_low, cd_low) =
                (_mm256_castps_pd(_mm256_unpacklo_ps(a, b)), _mm256_castps_pd(_mm256_unpacklo_ps(c, d)));
            let (ab_high, cd_high) =
                (_mm256_castps_pd(_mm256_unpackhi_ps(a, b)), _mm256_castps_pd(_mm256_unpackhi_ps(c, d)));
            [
                _mm256_castpd_ps(_mm256_unpacklo_pd(ab_low, cd_low)),
                _mm256_castpd_ps(_mm256_unpackhi_pd(ab_low, cd_low)),
                _mm256_castpd_ps(_mm256_unpacklo_pd(ab_high, cd_high)),
                _mm256_castpd_ps(_mm256_unpackhi_pd(ab_high, cd_high)),
            ]
        }
    }

    #[inline(always)]
    unsafe fn load(values: &[f32; MAX_PACKET_RAYS]) -> Self {
        // SAFETY: the CPU has AVX (the trait's contract); the first eight of sixteen floats are read.
        unsafe { _mm256_loadu_ps(values.as_ptr()) }
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
    unsafe fn columns(rays: &[Ray], offset: usize) -> [Self; 4] {
        let q = quarters::<{ Self::RAYS }>(rays, offset);
        // No closures with intrinsics here: they are compiled without the instruction set and might not be inlined.
        // SAFETY: the CPU has AVX-512F (the trait's contract); each pointer reads 16 bytes within a ray (`quarters`).
        // Register `j` holds rays `j`, `j + 4`, `j + 8` and `j + 12` in its four 128-bit blocks, so that transposing
        // the blocks alike leaves ray `i` in lane `i`.
        unsafe {
            let (a, b) = (blocks_of_four(q[0], q[4], q[8], q[12]), blocks_of_four(q[1], q[5], q[9], q[13]));
            let (c, d) = (blocks_of_four(q[2], q[6], q[10], q[14]), blocks_of_four(q[3], q[7], q[11], q[15]));
            let (ab_low, cd_low) =
                (_mm512_castps_pd(_mm512_unpacklo_ps(a, b)), _mm512_castps_pd(_mm512_unpacklo_ps(c, d)));
            let (ab_high, cd_high) =
                (_mm512_castps_pd(_mm512_unpackhi_ps(a, b)), _mm512_castps_pd(_mm512_unpackhi_ps(c, d)));
            [
                _mm512_castpd_ps(_mm512_unpacklo_pd(ab_low, cd_low)),
                _mm512_castpd_ps(_mm512_unpackhi_pd(ab_low, cd_low)),
                _mm512_castpd_ps(_mm512_unpacklo_pd(ab_high, cd_high)),
                _mm512_castpd_ps(_mm512_unpackhi_pd(ab_high, cd_high)),
            ]
        }
    }

    #[inline(always)]
    unsafe fn load(values: &[f32; MAX_PACKET_RAYS]) -> Self {
        // SAFETY: the CPU has AVX-512F (the trait's contract).
        unsafe { _mm512_loadu_ps(values.as_ptr()) }
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

/// Pointers to the 16 bytes at byte `offset` of each of `rays` (exactly `RAYS` of them).
///
/// Panics unless there are `RAYS` rays and the 16 bytes are four of a ray's floats: whole fields before `visibility`
/// (after it lies padding). glam's `Vec3A` is an SSE register on x86-64, so its fourth float is a value too.
#[inline(always)]
fn quarters<const RAYS: usize>(rays: &[Ray], offset: usize) -> [*const f32; RAYS] {
    let fields = offset_of!(Ray, visibility);
    assert!(
        rays.len() == RAYS && offset.is_multiple_of(4) && offset + 16 <= fields,
        "{} rays, bytes {offset}..",
        rays.len()
    );
    // No `array::from_fn`: its closure might not be inlined.
    let mut quarters = [std::ptr::null(); RAYS];
    for (quarter, ray) in quarters.iter_mut().zip(rays) {
        *quarter = (&raw const *ray).cast::<u8>().wrapping_add(offset).cast::<f32>();
    }
    quarters
}

/// The 16 bytes `a`, `b`, `c` and `d` point to as the four 128-bit blocks of an AVX-512 register.
///
/// # Safety
/// The CPU must have AVX-512F; each pointer must be valid for reading 16 bytes.
#[inline(always)]
unsafe fn blocks_of_four(a: *const f32, b: *const f32, c: *const f32, d: *const f32) -> __m512 {
    // SAFETY: the CPU has AVX-512F, and the pointers are valid (the caller's contract).
    unsafe {
        let v = _mm512_castps128_ps512(_mm_loadu_ps(a));
        let v = _mm512_insertf32x4::<1>(v, _mm_loadu_ps(b));
        let v = _mm512_insertf32x4::<2>(v, _mm_loadu_ps(c));
        _mm512_insertf32x4::<3>(v, _mm_loadu_ps(d))
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3A;

    use super::*;
    use crate::cpu_features::{has_avx2, has_avx512};

    /// Sixteen rays whose fields all differ: ray `i`'s `k`-th float of the first 48 bytes is `100·i + k`.
    fn numbered_rays() -> Vec<Ray> {
        (0..16)
            .map(|i| {
                let f = |k: usize| (100 * i + k) as f32;
                Ray {
                    origin: Vec3A::new(f(0), f(1), f(2)),
                    direction: Vec3A::new(f(4), f(5), f(6)),
                    tmin: f(8),
                    tmax: f(9),
                    time: f(10),
                    mask: f(11).to_bits(),
                    ..Ray::default()
                }
            })
            .collect()
    }

    /// Checks `columns` of `V` against each ray's fields: lane `i` of column `k` at `offset` is ray `i`'s float there.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set.
    unsafe fn columns_hold_each_rays_fields<V: RayLanes>() {
        let rays = numbered_rays();
        let rays = &rays[..V::RAYS];
        for (offset, first) in
            [(offset_of!(Ray, origin), 0), (offset_of!(Ray, direction), 4), (offset_of!(Ray, tmin), 8)]
        {
            // SAFETY: the CPU has the instruction set (this function's contract).
            let columns = unsafe { V::columns(rays, offset) };
            for (k, column) in columns.into_iter().enumerate() {
                let mut lanes = [0.0; MAX_PACKET_RAYS];
                // SAFETY: as above.
                unsafe { column.write_to(&mut lanes) };
                let expected: Vec<f32> = (0..V::RAYS).map(|i| (100 * i + first + k) as f32).collect();
                // The origin's and the direction's fourth float is glam's copy of `z`.
                let expected = match (first, k) {
                    (0 | 4, 3) => expected.iter().map(|v| v - 1.0).collect(),
                    _ => expected,
                };
                assert_eq!(lanes[..V::RAYS], expected[..], "offset {offset}, column {k}");
            }
        }
    }

    #[test]
    fn columns_hold_each_rays_fields_a_ray_a_lane() {
        if has_avx2() {
            // SAFETY: the CPU has AVX2, as just checked.
            unsafe { columns_hold_each_rays_fields::<__m256>() };
        }
        if has_avx512() {
            // SAFETY: the CPU has AVX-512F, as just checked.
            unsafe { columns_hold_each_rays_fields::<__m512>() };
        }
    }

    #[test]
    #[should_panic(expected = "bytes 48..")]
    fn columns_refuse_the_padding_after_the_fields() {
        if has_avx2() {
            // SAFETY: the CPU has AVX2, as just checked.
            unsafe { __m256::columns(&numbered_rays()[..8], offset_of!(Ray, visibility)) };
        } else {
            panic!("bytes 48.. (no AVX2 here: the check is the same)");
        }
    }
}
