//! The corners of a static accel's triangles regrouped [`BLOCK`] slots a block, one row per corner and axis
//! (structure of arrays), so that a leaf's triangles are sorted out four at a time: the same first step of the
//! watertight test as [`crate::intersect::triangle::may_hit`], in SSE on x86-64 (elsewhere `may_hit` itself, lane by
//! lane), and on x86-64 the rest of the test for the triangles left, four at a time too
//! ([`CornerBlocks::met_within`]); a leaf's corners are read from here. The blocks have slots of their own: each
//! leaf's triangles lie in as few blocks as they fit ([`Placement`]), a slot left empty where a leaf would otherwise
//! span one block more.

use std::ops::Range;

use glam::Vec3;

use super::bvh::{Footprint, VecLen};
#[cfg(target_arch = "x86_64")]
use super::filter;
use super::large_pages::{LargePageArray, LargePages};
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

/// Where the triangles of an accel's leaves lie in the blocks' slots: each leaf's in order, in as few blocks as they
/// fit (a leaf of up to [`BLOCK`] triangles in one, of up to 2·[`BLOCK`] in two), so that a leaf visit sorts out no
/// block more than it must. A leaf starts where the one before it ends unless it would then span one block more: it
/// starts the next block instead and the slots skipped stay empty, as long as the empty slots stay within a quarter
/// of the triangles ([`Placement::most_slots`]).
#[derive(Debug)]
pub(super) struct Placement {
    /// For each of the accel's slots in a leaf, its slot in the blocks.
    slot_of: Vec<u32>,
    /// For each slot of the blocks, the accel's slot it holds; `u32::MAX` for one left empty.
    held: Vec<u32>,
}

impl Placement {
    /// Places `leaves`, the slot ranges of an accel's leaves, in slot order; no slot may be in two (builds make none
    /// such, and loaded accels are checked for them).
    pub fn of_leaves(leaves: impl IntoIterator<Item = Range<usize>>) -> Placement {
        let leaves: Vec<Range<usize>> = leaves.into_iter().collect();
        let triangles = leaves.iter().map(|leaf| leaf.end).max().unwrap_or(0);
        let mut budget = triangles / 4;
        let mut held = Vec::with_capacity(Self::most_slots(triangles));
        for leaf in leaves {
            let (taken, count) = (held.len() % BLOCK, leaf.len());
            let skipped = BLOCK - taken;
            if taken + count > count.div_ceil(BLOCK) * BLOCK && skipped <= budget {
                budget -= skipped;
                held.resize(held.len() + skipped, u32::MAX);
            }
            held.extend(leaf.map(|slot| slot as u32));
        }
        let mut slot_of = vec![u32::MAX; triangles];
        for (placed, &slot) in held.iter().enumerate().filter(|(_, slot)| **slot != u32::MAX) {
            debug_assert_eq!(slot_of[slot as usize], u32::MAX, "slot {slot} in two leaves");
            slot_of[slot as usize] = placed as u32;
        }
        Placement { slot_of, held }
    }

    /// The most slots the blocks of `triangles` triangles in leaves take: a quarter more.
    pub const fn most_slots(triangles: usize) -> usize {
        triangles + triangles / 4
    }

    /// The slot in the blocks of the accel's slot `slot`, which must be in a leaf.
    pub fn slot_of(&self, slot: usize) -> usize {
        self.slot_of[slot] as usize
    }

    /// The accel's slot the blocks' slot `slot` holds, which must not be one left empty.
    pub fn held(&self, slot: usize) -> usize {
        self.held[slot] as usize
    }

    /// The items of the accel's slots (`items`, one a slot) in the blocks' slots, `empty` in those left empty.
    pub fn gather<T: Copy>(&self, items: &[T], empty: T) -> Vec<T> {
        self.held.iter().map(|&slot| items.get(slot as usize).copied().unwrap_or(empty)).collect()
    }
}

/// The corners of the triangles in leaves, in blocks; empty slots, and slots past the last triangle, are NaN (and
/// never asked for).
#[derive(Debug, Clone, Default)]
pub(super) struct CornerBlocks {
    /// Block `b` holds the blocks' slots `b·BLOCK .. (b + 1)·BLOCK`.
    blocks: LargePageArray<Block>,
}

impl CornerBlocks {
    /// Blocks for the slots of `placement`.
    pub fn count(placement: &Placement) -> usize {
        placement.held.len().div_ceil(BLOCK)
    }

    /// The blocks of `corners` (one triangle a slot of the accel) as `placement` places them, made in `pages` (which
    /// must have room for [`CornerBlocks::count`] blocks next).
    pub fn new(corners: &[[Vec3; 3]], placement: &Placement, pages: &mut LargePages) -> CornerBlocks {
        let held = &placement.held;
        let blocks = pages.array_from_fn(Self::count(placement), |b| {
            let mut block = [[f32::NAN; BLOCK]; ROWS];
            for (lane, &slot) in held[b * BLOCK..].iter().take(BLOCK).enumerate() {
                let Some(triangle) = corners.get(slot as usize) else { continue };
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

    /// The most bytes the blocks of `triangles` triangles in leaves take.
    pub const fn bytes_for(triangles: u64) -> u64 {
        (Placement::most_slots(triangles as usize) as u64).div_ceil(BLOCK as u64) * size_of::<Block>() as u64
    }

    /// Bytes they occupy.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        (footprint.of(&self.blocks as &dyn VecLen) * size_of::<Block>()) as u64
    }

    /// The corners of the triangle in the blocks' slot `slot`, as [`CornerBlocks::new`] was given them.
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
    use crate::backend::cpu::large_pages::Room;
    use crate::format::{Ray, RayFlags};
    use crate::intersect::triangle::may_hit;

    /// Leaves of `sizes` triangles, one after another from slot 0.
    fn leaves_of(sizes: &[usize]) -> Vec<Range<usize>> {
        sizes.iter().scan(0, |next, &size| Some((*next, *next += size).0..*next)).collect()
    }

    #[test]
    fn a_placement_puts_each_leaf_in_as_few_blocks_as_it_fits_in_order() {
        // Sizes of every kind up to two blocks, in an order that leaves blocks part full.
        let sizes: Vec<usize> = (0..400).map(|i| 1 + (i * 7 + i / 3) % 8).collect();
        let leaves = leaves_of(&sizes);
        let placement = Placement::of_leaves(leaves.clone());
        let triangles = leaves.last().unwrap().end;
        let mut last = None;
        for leaf in &leaves {
            let placed: Vec<usize> = leaf.clone().map(|slot| placement.slot_of(slot)).collect();
            assert!(placed.windows(2).all(|pair| pair[1] == pair[0] + 1), "{leaf:?} at {placed:?}: not in a row");
            assert!(last < Some(placed[0]), "{leaf:?} at {placed:?}: out of order");
            let blocks = placed[placed.len() - 1] / BLOCK - placed[0] / BLOCK + 1;
            assert_eq!(blocks, leaf.len().div_ceil(BLOCK), "{leaf:?} at {placed:?}");
            last = placed.last().copied();
        }
        let empty = placement.held.len() - triangles;
        assert!(empty > 0 && empty <= triangles / 4, "{empty} empty slots for {triangles} triangles");
        let items: Vec<usize> = (0..triangles).collect();
        let gathered = placement.gather(&items, usize::MAX);
        assert!((0..triangles).all(|slot| gathered[placement.slot_of(slot)] == slot), "gathered");
        assert_eq!(gathered.iter().filter(|&&item| item == usize::MAX).count(), empty);
    }

    #[test]
    fn a_placement_leaves_no_more_than_a_quarter_of_its_slots_empty() {
        // Leaves of three from lane 3 on would each skip a slot of every four; the budget runs out first.
        let sizes: Vec<usize> = std::iter::once(3).chain(std::iter::repeat_n([2, 3], 200).flatten()).collect();
        let leaves = leaves_of(&sizes);
        let placement = Placement::of_leaves(leaves.clone());
        let triangles = leaves.last().unwrap().end;
        assert!(placement.held.len() <= Placement::most_slots(triangles), "{} slots", placement.held.len());
        let spanning = leaves.iter().filter(|leaf| {
            let (first, last) = (placement.slot_of(leaf.start), placement.slot_of(leaf.end - 1));
            last / BLOCK != first / BLOCK
        });
        assert!(spanning.count() > 0, "the budget never ran out");
    }

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
        let placement = Placement::of_leaves(std::iter::once(0..corners.len()));
        let mut pages = LargePages::new(Room::default().and::<Block>(CornerBlocks::count(&placement)));
        let blocks = CornerBlocks::new(&corners, &placement, &mut pages);
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
