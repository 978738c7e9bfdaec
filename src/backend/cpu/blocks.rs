//! The corners of a static accel's triangles regrouped [`BLOCK`] slots a block, one row per corner and axis
//! (structure of arrays), so that a leaf's triangles are sorted out four at a time: the same first step of the
//! watertight test as [`crate::intersect::triangle::may_hit`], in SSE on x86-64 (elsewhere `may_hit` itself, lane by
//! lane), and on x86-64 the rest of the test for the triangles left, four at a time too
//! ([`CornerBlocks::met_within`]); a leaf's corners are read from here. A block starts at a slot that is a multiple of
//! [`BLOCK`], whatever leaf the slots belong to, so a leaf finds its blocks by its slots alone; a leaf's triangles fill
//! one or two blocks.

use glam::Vec3;

use super::bvh::{Footprint, VecLen};
#[cfg(target_arch = "x86_64")]
use super::filter;
use super::large_pages::LargePageArray;
use crate::intersect::PreparedRay;
use crate::intersect::triangle::TriangleHit;

/// Slots a block.
pub(super) const BLOCK: usize = 4;

/// Rows of a block: corner `c`'s axis `k` is row `3c + k`.
const ROWS: usize = 9;

/// One block: for each corner and axis, that coordinate of the block's [`BLOCK`] triangles.
pub(super) type Block = [[f32; BLOCK]; ROWS];

/// Where `N` lanes' rays met triangles (a ray against a block's triangles, or a packet's rays against a triangle), as
/// the watertight test in lanes left it (`filter::meet`, kept by `MetLanes::keep`): what the scalar test's hit is
/// made of, lane by lane.
pub(super) struct MetLanes<const N: usize> {
    /// Distances.
    pub(super) t: [f32; N],
    /// The sums of the edge functions.
    pub(super) det: [f32; N],
    /// The second edge functions.
    pub(super) v: [f32; N],
    /// The third edge functions.
    pub(super) w: [f32; N],
}

impl<const N: usize> MetLanes<N> {
    /// Nothing met yet.
    pub const NONE: MetLanes<N> = MetLanes { t: [0.0; N], det: [0.0; N], v: [0.0; N], w: [0.0; N] };

    /// Lane `lane`'s hit, as the scalar test reports it.
    #[inline(always)]
    pub fn hit(&self, lane: usize) -> TriangleHit {
        TriangleHit::from_edges(self.t[lane], self.det[lane], self.v[lane], self.w[lane])
    }
}

/// Every slot's corners, in blocks; slots past the last triangle are NaN (and never asked for).
#[derive(Debug, Clone, Default)]
pub(super) struct CornerBlocks {
    /// Block `b` holds slots `b·BLOCK .. (b + 1)·BLOCK`.
    blocks: LargePageArray<Block>,
}

impl CornerBlocks {
    /// The blocks of `corners` (one triangle a slot).
    pub fn new(corners: &[[Vec3; 3]]) -> CornerBlocks {
        let blocks = LargePageArray::from_fn(corners.len().div_ceil(BLOCK), |b| {
            let mut block = [[f32::NAN; BLOCK]; ROWS];
            for (lane, triangle) in corners[b * BLOCK..].iter().take(BLOCK).enumerate() {
                for (corner, point) in triangle.iter().enumerate() {
                    for axis in 0..3 {
                        block[3 * corner + axis][lane] = point[axis];
                    }
                }
            }
            block
        });
        CornerBlocks { blocks }
    }

    /// Bytes the blocks of `triangles` slots take.
    pub const fn bytes_for(triangles: u64) -> u64 {
        triangles.div_ceil(BLOCK as u64) * size_of::<Block>() as u64
    }

    /// Bytes they occupy.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        (footprint.of(&self.blocks as &dyn VecLen) * size_of::<Block>()) as u64
    }

    /// The corners of the triangle in `slot`, as [`CornerBlocks::new`] was given them.
    #[inline(always)]
    pub fn corners(&self, slot: usize) -> [Vec3; 3] {
        let (rows, lane) = (&self.blocks[slot / BLOCK], slot % BLOCK);
        std::array::from_fn(|corner| Vec3::from_array(std::array::from_fn(|axis| rows[3 * corner + axis][lane])))
    }

    /// The block holding `slot`, and the slot's lane in it.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub fn lane_of(&self, slot: usize) -> (&Block, usize) {
        (&self.blocks[slot / BLOCK], slot % BLOCK)
    }

    /// Where the block holding `slot` starts (to prefetch it; past the end for a slot past the last).
    pub fn block_ptr(&self, slot: usize) -> *const Block {
        self.blocks.as_ptr().wrapping_add(slot / BLOCK)
    }

    /// The lanes of block `block` the ray may hit, a bit each: SSE (every x86-64 CPU has it), four lanes in one
    /// register, through [`filter::may_hit_lanes`].
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub fn block_candidates(&self, ray: &BlockRay<'_>, block: usize) -> u32 {
        let rows = BlockRows { rows: &self.blocks[block], axes: ray.axes };
        // SAFETY: SSE is part of x86-64.
        unsafe { filter::may_hit_lanes(&rows, ray.origin, ray.shear) }
    }

    /// Of the lanes of block `block` set in `lanes`, those whose triangle the ray meets at a `t` within `[tmin,
    /// tmax]` as the watertight test finds it, whose hits it leaves in `met`, and those on an edge or a vertex of
    /// theirs, which need the test's exact rule ([`filter::meet`]), a bit each; SSE, four lanes in one register.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub fn met_within(
        &self,
        ray: &BlockRay<'_>,
        block: usize,
        lanes: u32,
        (tmin, tmax): (f32, f32),
        met: &mut MetLanes<BLOCK>,
    ) -> (u32, u32) {
        use std::arch::x86_64::{__m128, _mm_set1_ps};

        use filter::Lanes;
        let rows = BlockRows { rows: &self.blocks[block], axes: ray.axes };
        // SAFETY: SSE is part of x86-64.
        unsafe {
            let sheared = filter::shear(&rows, ray.origin, ray.shear);
            let [u, v, w] = sheared.edges;
            let may_hit = <__m128 as Lanes>::zero_or_not_mixed(u, v, w) & lanes;
            if may_hit == 0 {
                return (0, 0);
            }
            let meeting = filter::meet(&sheared, ray.shear_z, may_hit);
            let within = meeting.met & meeting.t.within(_mm_set1_ps(tmin), _mm_set1_ps(tmax));
            if within != 0 {
                met.keep(&meeting, &sheared);
            }
            (within, meeting.on_edge)
        }
    }

    /// The lanes of block `block` the ray may hit, a bit each: [`crate::intersect::triangle::may_hit`] lane by lane.
    #[cfg(not(target_arch = "x86_64"))]
    #[inline(always)]
    pub fn block_candidates(&self, ray: &BlockRay<'_>, block: usize) -> u32 {
        (0..BLOCK).fold(0, |maybe, lane| {
            let corners = self.corners(block * BLOCK + lane);
            maybe | u32::from(crate::intersect::triangle::may_hit(ray.ray, &corners)) << lane
        })
    }
}

/// What the block test needs of a ray, made once a ray: on x86-64 its origin on its projection axes and its shear
/// constants, each in every lane of an SSE register.
#[derive(Clone, Copy)]
pub(super) struct BlockRay<'r> {
    /// The ray.
    #[cfg_attr(target_arch = "x86_64", allow(dead_code))]
    ray: &'r PreparedRay,
    /// The ray's projection axes `kx`, `ky`, `kz`.
    #[cfg(target_arch = "x86_64")]
    axes: [usize; 3],
    /// The origin on those axes.
    #[cfg(target_arch = "x86_64")]
    origin: [std::arch::x86_64::__m128; 3],
    /// `shear.x`, `shear.y`.
    #[cfg(target_arch = "x86_64")]
    shear: [std::arch::x86_64::__m128; 2],
    /// `shear.z`.
    #[cfg(target_arch = "x86_64")]
    shear_z: std::arch::x86_64::__m128,
}

impl<'r> BlockRay<'r> {
    /// The block test's numbers of `ray`.
    #[inline(always)]
    pub fn new(ray: &'r PreparedRay) -> BlockRay<'r> {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::_mm_set1_ps;
            let axes = [ray.kx, ray.ky, ray.kz];
            assert!(axes.iter().all(|&axis| axis < 3), "projection axes {axes:?}");
            let origin = ray.origin.to_array();
            // SAFETY: SSE is part of x86-64.
            unsafe {
                BlockRay {
                    ray,
                    axes,
                    origin: axes.map(|axis| _mm_set1_ps(origin[axis])),
                    shear: [_mm_set1_ps(ray.shear.x), _mm_set1_ps(ray.shear.y)],
                    shear_z: _mm_set1_ps(ray.shear.z),
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        BlockRay { ray }
    }
}

/// A block's rows as [`filter::Corners`]: four triangles, a lane each, on a ray's projection axes.
#[cfg(target_arch = "x86_64")]
struct BlockRows<'a> {
    /// The block.
    rows: &'a Block,
    /// The ray's `kx`, `ky`, `kz`, each below 3 ([`BlockRay::new`] checks them).
    axes: [usize; 3],
}

#[cfg(target_arch = "x86_64")]
impl filter::Corners<std::arch::x86_64::__m128> for BlockRows<'_> {
    #[inline(always)]
    unsafe fn corner(&self, c: usize) -> [std::arch::x86_64::__m128; 3] {
        use std::arch::x86_64::_mm_loadu_ps;
        // SAFETY: SSE is part of x86-64; `c` is below 3 (the trait's contract) and so is every axis, so each row
        // `3c + axis` is one of the block's nine, read whole.
        unsafe { self.axes.map(|axis| _mm_loadu_ps(self.rows.get_unchecked(3 * c + axis).as_ptr())) }
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3A;

    use super::*;
    use crate::format::{Ray, RayFlags};
    use crate::intersect::triangle::may_hit;

    #[test]
    fn blocks_give_back_the_corners_and_sort_out_exactly_what_the_scalar_test_does() {
        // Eleven triangles of a fan and strays (the last block half full), rays from several directions through
        // points on a grid.
        let corners: Vec<[Vec3; 3]> = (0..11)
            .map(|i| {
                let angle = i as f32 * 0.6;
                let p = Vec3::new(angle.cos(), angle.sin(), 0.1 * i as f32);
                [Vec3::ZERO, p, p + Vec3::new(-0.3, 0.5, 0.2)]
            })
            .collect();
        let blocks = CornerBlocks::new(&corners);
        assert!((0..corners.len()).all(|slot| blocks.corners(slot) == corners[slot]), "corners read back");
        let mut ruled_out = 0;
        for direction in [-Vec3A::Z, Vec3A::new(0.3, -0.2, -1.0), Vec3A::new(1.0, 0.1, 0.2), Vec3A::new(0.0, -1.0, 0.0)]
        {
            for point in (0..25).map(|i| Vec3A::new((i % 5) as f32 * 0.25 - 0.5, (i / 5) as f32 * 0.25 - 0.5, 0.3)) {
                let ray = PreparedRay::new(
                    &Ray { origin: point - direction * 4.0, direction, ..Ray::default() },
                    RayFlags::empty(),
                );
                for block in 0..corners.len().div_ceil(BLOCK) {
                    let slots = block * BLOCK..((block + 1) * BLOCK).min(corners.len());
                    let got = blocks.block_candidates(&BlockRay::new(&ray), block) & ((1 << slots.len()) - 1);
                    let want =
                        slots.fold(0, |bits, slot| bits | u32::from(may_hit(&ray, &corners[slot])) << (slot % BLOCK));
                    assert_eq!(got, want, "block {block}");
                }
                ruled_out += (0..corners.len()).filter(|&slot| !may_hit(&ray, &corners[slot])).count();
            }
        }
        assert!(ruled_out > 100, "{ruled_out} triangles ruled out");
    }
}
