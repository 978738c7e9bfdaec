//! The watertight triangle test on SIMD lanes: [`crate::intersect::triangle::may_hit`] ([`may_hit_lanes`]) and the
//! rest of [`crate::intersect::triangle::intersect`] short of its exact rule for edges and vertices ([`meet`]), with
//! the same operations in the same order, so each lane's answer is bit for bit the scalar one. Written once over
//! [`Lanes`] and used two ways: four triangles against one ray in SSE ([`super::blocks`]), and one triangle against a
//! packet's 8 rays in AVX or 16 in AVX-512 ([`super::packet`]).

use std::arch::x86_64::*;

use super::blocks::MetLanes;

/// A SIMD register of f32 lanes, with what the filter needs of it.
pub(super) trait Lanes: Copy {
    /// Lanes a register.
    const LANES: usize;

    /// Stores the lanes into the first [`Lanes::LANES`] of `values`.
    ///
    /// # Safety
    /// The CPU must have the register's instruction set; `values` must hold at least [`Lanes::LANES`] floats.
    unsafe fn write_to(self, values: &mut [f32]);

    /// `self − other`, lane by lane.
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn sub(self, other: Self) -> Self;

    /// `self · other`, lane by lane.
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn mul(self, other: Self) -> Self;

    /// `self + other`, lane by lane.
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn add(self, other: Self) -> Self;

    /// `self / other`, lane by lane.
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn div(self, other: Self) -> Self;

    /// `|self|`, lane by lane.
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn abs(self) -> Self;

    /// A bit per lane: `0 < |self|` (false with NaN).
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn nonzero(self) -> u32;

    /// A bit per lane: `|self| < ∞` (false with NaN).
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn finite(self) -> u32;

    /// A bit per lane: `low ≤ self ≤ high` (false with NaN).
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn within(self, low: Self, high: Self) -> u32;

    /// A bit per lane: some of `u`, `v`, `w` is 0, or they are not of mixed signs (comparisons with NaN are false,
    /// as Rust's are).
    ///
    /// # Safety
    /// The CPU must have the register's instruction set.
    unsafe fn zero_or_not_mixed(u: Self, v: Self, w: Self) -> u32;
}

impl Lanes for __m128 {
    const LANES: usize = 4;

    #[inline(always)]
    unsafe fn write_to(self, values: &mut [f32]) {
        // SAFETY: SSE is part of x86-64; `values` holds 4 floats at least (the caller's contract).
        unsafe { _mm_storeu_ps(values.as_mut_ptr(), self) }
    }

    #[inline(always)]
    unsafe fn sub(self, other: Self) -> Self {
        // SAFETY: SSE is part of x86-64.
        unsafe { _mm_sub_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn mul(self, other: Self) -> Self {
        // SAFETY: SSE is part of x86-64.
        unsafe { _mm_mul_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn add(self, other: Self) -> Self {
        // SAFETY: SSE is part of x86-64.
        unsafe { _mm_add_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn div(self, other: Self) -> Self {
        // SAFETY: SSE is part of x86-64.
        unsafe { _mm_div_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn abs(self) -> Self {
        // SAFETY: SSE is part of x86-64.
        unsafe { _mm_and_ps(self, _mm_castsi128_ps(_mm_set1_epi32(i32::MAX))) }
    }

    #[inline(always)]
    unsafe fn nonzero(self) -> u32 {
        // SAFETY: SSE is part of x86-64.
        unsafe { _mm_movemask_ps(_mm_cmplt_ps(_mm_setzero_ps(), self.abs())) as u32 }
    }

    #[inline(always)]
    unsafe fn finite(self) -> u32 {
        // SAFETY: SSE is part of x86-64.
        unsafe { _mm_movemask_ps(_mm_cmplt_ps(self.abs(), _mm_set1_ps(f32::INFINITY))) as u32 }
    }

    #[inline(always)]
    unsafe fn within(self, low: Self, high: Self) -> u32 {
        // SAFETY: SSE is part of x86-64.
        unsafe { _mm_movemask_ps(_mm_and_ps(_mm_cmple_ps(low, self), _mm_cmple_ps(self, high))) as u32 }
    }

    #[inline(always)]
    unsafe fn zero_or_not_mixed(u: Self, v: Self, w: Self) -> u32 {
        // SAFETY: SSE is part of x86-64.
        unsafe {
            let zero = _mm_setzero_ps();
            let any = |f: unsafe fn(__m128, __m128) -> __m128| _mm_or_ps(_mm_or_ps(f(u, zero), f(v, zero)), f(w, zero));
            let (on_edge, negative, positive) = (any(_mm_cmpeq_ps), any(_mm_cmplt_ps), any(_mm_cmpgt_ps));
            // on_edge | !mixed, a lane's four bytes all ones or all zeros.
            let mixed = _mm_and_ps(negative, positive);
            _mm_movemask_ps(_mm_or_ps(on_edge, _mm_andnot_ps(mixed, _mm_castsi128_ps(_mm_set1_epi32(-1))))) as u32
        }
    }
}

impl Lanes for __m256 {
    const LANES: usize = 8;

    #[inline(always)]
    unsafe fn write_to(self, values: &mut [f32]) {
        // SAFETY: the CPU has AVX, and `values` holds 8 floats at least (the caller's contract).
        unsafe { _mm256_storeu_ps(values.as_mut_ptr(), self) }
    }

    #[inline(always)]
    unsafe fn sub(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { _mm256_sub_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn mul(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { _mm256_mul_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn add(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { _mm256_add_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn div(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { _mm256_div_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn abs(self) -> Self {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { _mm256_and_ps(self, _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX))) }
    }

    #[inline(always)]
    unsafe fn nonzero(self) -> u32 {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_setzero_ps(), self.abs())) as u32 }
    }

    #[inline(always)]
    unsafe fn finite(self) -> u32 {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(self.abs(), _mm256_set1_ps(f32::INFINITY))) as u32 }
    }

    #[inline(always)]
    unsafe fn within(self, low: Self, high: Self) -> u32 {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe {
            _mm256_movemask_ps(_mm256_and_ps(
                _mm256_cmp_ps::<_CMP_LE_OQ>(low, self),
                _mm256_cmp_ps::<_CMP_LE_OQ>(self, high),
            )) as u32
        }
    }

    #[inline(always)]
    unsafe fn zero_or_not_mixed(u: Self, v: Self, w: Self) -> u32 {
        // No closures here: a closure is compiled without AVX and might not be inlined.
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe {
            let zero = _mm256_setzero_ps();
            let on_edge = _mm256_or_ps(
                _mm256_or_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(u, zero), _mm256_cmp_ps::<_CMP_EQ_OQ>(v, zero)),
                _mm256_cmp_ps::<_CMP_EQ_OQ>(w, zero),
            );
            let negative = _mm256_or_ps(
                _mm256_or_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(u, zero), _mm256_cmp_ps::<_CMP_LT_OQ>(v, zero)),
                _mm256_cmp_ps::<_CMP_LT_OQ>(w, zero),
            );
            let positive = _mm256_or_ps(
                _mm256_or_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(u, zero), _mm256_cmp_ps::<_CMP_GT_OQ>(v, zero)),
                _mm256_cmp_ps::<_CMP_GT_OQ>(w, zero),
            );
            let mixed = _mm256_and_ps(negative, positive);
            let all = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
            _mm256_movemask_ps(_mm256_or_ps(on_edge, _mm256_andnot_ps(mixed, all))) as u32
        }
    }
}

impl Lanes for __m512 {
    const LANES: usize = 16;

    #[inline(always)]
    unsafe fn write_to(self, values: &mut [f32]) {
        // SAFETY: the CPU has AVX-512F, and `values` holds 16 floats at least (the caller's contract).
        unsafe { _mm512_storeu_ps(values.as_mut_ptr(), self) }
    }

    #[inline(always)]
    unsafe fn sub(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe { _mm512_sub_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn mul(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe { _mm512_mul_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn add(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe { _mm512_add_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn div(self, other: Self) -> Self {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe { _mm512_div_ps(self, other) }
    }

    #[inline(always)]
    unsafe fn abs(self) -> Self {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe { _mm512_abs_ps(self) }
    }

    #[inline(always)]
    unsafe fn nonzero(self) -> u32 {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe { u32::from(_mm512_cmp_ps_mask::<_CMP_LT_OQ>(_mm512_setzero_ps(), self.abs())) }
    }

    #[inline(always)]
    unsafe fn finite(self) -> u32 {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe { u32::from(_mm512_cmp_ps_mask::<_CMP_LT_OQ>(self.abs(), _mm512_set1_ps(f32::INFINITY))) }
    }

    #[inline(always)]
    unsafe fn within(self, low: Self, high: Self) -> u32 {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe { u32::from(_mm512_cmp_ps_mask::<_CMP_LE_OQ>(low, self) & _mm512_cmp_ps_mask::<_CMP_LE_OQ>(self, high)) }
    }

    #[inline(always)]
    unsafe fn zero_or_not_mixed(u: Self, v: Self, w: Self) -> u32 {
        // SAFETY: the CPU has AVX-512F (the caller's contract).
        unsafe {
            let zero = _mm512_setzero_ps();
            let on_edge = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(u, zero)
                | _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(v, zero)
                | _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(w, zero);
            let negative = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(u, zero)
                | _mm512_cmp_ps_mask::<_CMP_LT_OQ>(v, zero)
                | _mm512_cmp_ps_mask::<_CMP_LT_OQ>(w, zero);
            let positive = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(u, zero)
                | _mm512_cmp_ps_mask::<_CMP_GT_OQ>(v, zero)
                | _mm512_cmp_ps_mask::<_CMP_GT_OQ>(w, zero);
            u32::from(on_edge | !(negative & positive))
        }
    }
}

/// Where the filter reads a triangle's corners from, one corner at a time as it needs them (so that no more
/// registers are live than the arithmetic needs).
pub(super) trait Corners<L> {
    /// Corner `c` on the ray's projection axes (`kx`, `ky`, `kz`).
    ///
    /// # Safety
    /// The CPU must have the registers' instruction set; `c` must be 0, 1 or 2.
    unsafe fn corner(&self, c: usize) -> [L; 3];
}

/// A triangle in a ray's sheared space, lane by lane, as the watertight test computes it: the three f32 edge
/// functions and each corner's distance from the origin along the ray's axis (`a[kz]` … of
/// [`crate::intersect::triangle::intersect`]).
pub(super) struct Sheared<L> {
    /// The edge functions `u`, `v`, `w`.
    pub edges: [L; 3],
    /// Each corner's coordinate along the ray's axis, relative to the origin.
    pub along: [L; 3],
}

/// The triangle `corners` in the sheared space of the rays with origin `origin` (on their projection axes) and first
/// two shear constants `shear`: the same operations in the same order as the scalar test.
///
/// # Safety
/// The CPU must have the registers' instruction set.
#[inline(always)]
pub(super) unsafe fn shear<L: Lanes>(corners: &impl Corners<L>, origin: [L; 3], shear: [L; 2]) -> Sheared<L> {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe {
        let (ax, ay, az) = project(corners.corner(0), origin, shear);
        let (bx, by, bz) = project(corners.corner(1), origin, shear);
        let (cx, cy, cz) = project(corners.corner(2), origin, shear);
        let u = cx.mul(by).sub(cy.mul(bx));
        let v = ax.mul(cy).sub(ay.mul(cx));
        let w = bx.mul(ay).sub(by.mul(ax));
        Sheared { edges: [u, v, w], along: [az, bz, cz] }
    }
}

/// A bit per lane: whether the ray may hit the triangle ([`crate::intersect::triangle::may_hit`]). `origin` is the
/// ray's origin on its projection axes and `shear` its first two shear constants.
///
/// # Safety
/// The CPU must have the registers' instruction set.
#[inline(always)]
pub(super) unsafe fn may_hit_lanes<L: Lanes>(corners: &impl Corners<L>, origin: [L; 3], shear: [L; 2]) -> u32 {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe {
        let [u, v, w] = self::shear(corners, origin, shear).edges;
        L::zero_or_not_mixed(u, v, w)
    }
}

/// Where the lanes of `may_hit` (those [`may_hit_lanes`] leaves) meet the `sheared` triangle, as
/// [`crate::intersect::triangle::intersect`] finds it with the same operations in the same order, as far as it goes
/// without its exact rule for edges and vertices.
pub(super) struct Meeting<L> {
    /// The lanes with an f32 edge function exactly 0, on an edge or a vertex: they are to take the scalar test.
    pub on_edge: u32,
    /// The lanes whose line meets the triangle at a finite `t` (its edge functions all nonzero, their sum finite and
    /// nonzero): the scalar test's hit, found here.
    pub met: u32,
    /// Where they meet it.
    pub t: L,
    /// The sums of the edge functions: `u` and `v` of the hit are the second and third edge functions over it.
    pub det: L,
}

impl<const N: usize> MetLanes<N> {
    /// Keeps what `meeting` found of the `sheared` triangle.
    ///
    /// # Safety
    /// The CPU must have the registers' instruction set.
    #[inline(always)]
    pub unsafe fn keep<L: Lanes>(&mut self, meeting: &Meeting<L>, sheared: &Sheared<L>) {
        const { assert!(N >= L::LANES, "a lane for every lane of the register") };
        let [_, v, w] = sheared.edges;
        // SAFETY: the CPU has the instruction set (the caller's contract); each array holds the register's lanes.
        unsafe {
            meeting.t.write_to(&mut self.t);
            meeting.det.write_to(&mut self.det);
            v.write_to(&mut self.v);
            w.write_to(&mut self.w);
        }
    }
}

/// The rest of the watertight test of the lanes of `may_hit` against the `sheared` triangle ([`Meeting`]);
/// `shear_z` is the rays' third shear constant.
///
/// # Safety
/// The CPU must have the registers' instruction set.
#[inline(always)]
pub(super) unsafe fn meet<L: Lanes>(sheared: &Sheared<L>, shear_z: L, may_hit: u32) -> Meeting<L> {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe {
        let ([u, v, w], [az, bz, cz]) = (sheared.edges, sheared.along);
        let nonzero = u.nonzero() & v.nonzero() & w.nonzero();
        let det = u.add(v).add(w);
        let t = u.mul(shear_z.mul(az)).add(v.mul(shear_z.mul(bz))).add(w.mul(shear_z.mul(cz))).div(det);
        let met = may_hit & nonzero & det.nonzero() & det.finite() & t.finite();
        Meeting { on_edge: may_hit & !nonzero, met, t, det }
    }
}

/// A corner translated to the ray's origin and sheared: (x, y) in the plane across the ray, and z along it (not yet
/// scaled by the third shear constant).
///
/// # Safety
/// The CPU must have the registers' instruction set.
#[inline(always)]
unsafe fn project<L: Lanes>([x, y, z]: [L; 3], origin: [L; 3], shear: [L; 2]) -> (L, L, L) {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe {
        let z = z.sub(origin[2]);
        (x.sub(origin[0]).sub(shear[0].mul(z)), y.sub(origin[1]).sub(shear[1].mul(z)), z)
    }
}
