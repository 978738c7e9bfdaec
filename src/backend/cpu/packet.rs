//! Packets: eight coherent rays — consecutive in the batch, heading the same way from nearby origins, as a camera's
//! or a lidar's are — traced together through a static accel's wide nodes on a CPU with AVX2. Each child box of a
//! node is tested against the eight rays at once (a ray a lane), and each leaf triangle is sorted out for the eight
//! rays at once ([`filter`]); the rays share the loads of nodes and triangles and the traversal's bookkeeping.
//!
//! **Same answers as alone.** A ray takes part only in the box tests of nodes it entered, with the same operations
//! as [`super::wide`]'s lane test and its own nearest hit so far, and a popped node is re-checked against that hit.
//! The triangles it meets go to its own collector through the same test. So every triangle that the ray alone
//! would find nearest is offered to it, and the tie rule (distance, then ids) picks the same hit whatever the
//! order: closest, `all` and `count` answers are byte for byte those of tracing each ray alone; only which hit an
//! `any` query stops at may differ. Nodes are visited in the packet's order: nearest first by the nearest of the
//! rays entering them for closest-hit queries, lane order for the others.

use std::arch::x86_64::*;
use std::mem::offset_of;
use std::ops::Range;

use super::blocks::Block;
use super::filter;
use super::triangles::TriangleBvh;
use super::wide::{CACHE_LINE, WIDTH, WideBvh, WideNode, has_avx2, prefetch};
use crate::intersect::PreparedRay;
use crate::intersect::aabb::SLACK;
use crate::query::{Collector, GROUP_RAYS, InstanceScope, TraceStats, TriangleCandidate, consider_triangle};

/// Rays in a packet: a ray a lane of an AVX register. The batch driver hands the backend groups of this size.
pub(super) const PACKET_RAYS: usize = 8;
const _: () = assert!(PACKET_RAYS == GROUP_RAYS);

/// The widest angle between a packet's first ray and another, as its cosine (about 8°): a camera's eight
/// neighbouring pixels are well within it.
const MIN_COSINE: f32 = 0.99;

/// How far a packet's origins may lie from its first ray's, as a fraction of the scene box's diagonal.
const MAX_ORIGIN_SPREAD: f32 = 0.01;

/// A node lane waiting on a packet's stack: the rays that enter its box, and the distance at which each does.
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(32))]
pub(crate) struct PacketEntry {
    /// Per ray, the distance at which it enters the lane's box.
    near: [f32; PACKET_RAYS],
    /// The lane, as `node · WIDTH + lane`.
    lane_ref: u32,
    /// A bit per ray that enters it.
    rays: u32,
}

/// Whether `rays` (with their collectors) may make a packet, by what is cheapest to check: [`PACKET_RAYS`] of them,
/// which may share an order of boxes, with the same direction signs and projection axes (the box test and the triangle
/// filter treat them alike: the answers need only this). Most incoherent groups fail at their second ray. The rest
/// of the test is [`PacketLanes::coherent`].
fn may_pack<'r>(rays: &'r [PreparedRay], collectors: &[Collector<'_>]) -> Option<&'r [PreparedRay; PACKET_RAYS]> {
    let rays: &[PreparedRay; PACKET_RAYS] = rays.try_into().ok()?;
    let axes = |ray: &PreparedRay| (ray.kx, ray.ky, ray.kz, ray.negative);
    let same = rays[1..].iter().all(|ray| axes(ray) == axes(&rays[0]));
    (same && collectors.iter().all(Collector::may_share_order)).then_some(rays)
}

impl TriangleBvh {
    /// Traces `rays` together when they make a packet through a static accel on a CPU with AVX2, and says whether it
    /// did; otherwise it does nothing and the rays are to be traced alone.
    pub(super) fn trace_packet(
        &self,
        stack: &mut [PacketEntry],
        rays: &[PreparedRay],
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> bool {
        match may_pack(rays, collectors) {
            Some(rays) if self.node_keys.is_none() && has_avx2() => {
                // SAFETY: the CPU has the features, as just checked.
                unsafe { self.trace_packet_avx2(stack, rays, collectors, stats) }
            }
            _ => false,
        }
    }

    /// [`TriangleBvh::trace_packet`] once the rays may make a packet: traces them if they head the same way from
    /// nearby origins ([`PacketLanes::coherent`]), and says whether they did.
    ///
    /// # Safety
    /// The CPU must have the features [`has_avx2`] checks.
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn trace_packet_avx2(
        &self,
        stack: &mut [PacketEntry],
        rays: &[PreparedRay; PACKET_RAYS],
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> bool {
        // SAFETY: the CPU has AVX2 (this function's contract), so AVX too.
        let lanes = unsafe { PacketLanes::new(rays) };
        if !unsafe { lanes.coherent(rays, MAX_ORIGIN_SPREAD * self.wide.diagonal()) } {
            return false;
        }
        let leaf = |slots: Range<usize>, mut active: u32, collectors: &mut [Collector<'_>], stats: &mut TraceStats| {
            stats.triangle_tests += (slots.len() * active.count_ones() as usize) as u64;
            for slot in slots {
                // SAFETY: as above.
                let mut candidates = unsafe { lanes.may_hit(self.wide.blocks.lane_of(slot)) } & active;
                if candidates == 0 {
                    continue;
                }
                let (corners, id) = (self.wide.blocks.corners(slot), self.refs[slot]);
                let candidate = TriangleCandidate {
                    corners: &corners,
                    id,
                    mask: self.masks.as_ref().map_or(0, |m| m[slot]),
                    geometry_flags: self.geometry_flags[id.geom_id as usize],
                };
                while candidates != 0 {
                    let ray = candidates.trailing_zeros() as usize;
                    candidates &= candidates - 1;
                    consider_triangle(&rays[ray], &candidate, &InstanceScope::WORLD, &mut collectors[ray]);
                    if collectors[ray].done() {
                        active &= !(1 << ray);
                    }
                }
                if active == 0 {
                    return;
                }
            }
        };
        let prefetch_leaf = |slots: Range<usize>| self.prefetch_leaf(slots);
        // SAFETY: as above.
        unsafe { self.wide.walk_packet(stack, &lanes, collectors, stats, leaf, prefetch_leaf) };
        true
    }
}

impl WideBvh {
    /// The length of the root box's diagonal (0 when there are no nodes).
    fn diagonal(&self) -> f32 {
        (self.root.1 - self.root.0).length()
    }

    /// Walks the nodes with a packet of rays, nearest first (by the nearest of the rays entering a box) when the
    /// collectors want it, and hands each leaf some of them reach (its slots and those rays, a bit each) to `leaf`.
    /// `prefetch_leaf` starts loading a leaf's data as soon as a ray enters the leaf's box.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    unsafe fn walk_packet(
        &self,
        stack: &mut [PacketEntry],
        lanes: &PacketLanes,
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
        mut leaf: impl FnMut(Range<usize>, u32, &mut [Collector<'_>], &mut TraceStats),
        prefetch_leaf: impl Fn(Range<usize>),
    ) {
        if self.nodes.is_empty() {
            return;
        }
        let mut cull: [f32; PACKET_RAYS] = std::array::from_fn(|ray| collectors[ray].cull_tmax());
        let (lo, hi) = (self.root.0.to_array(), self.root.1.to_array());
        let first = std::array::from_fn(|axis| if lanes.negative[axis] { hi[axis] } else { lo[axis] });
        let last = std::array::from_fn(|axis| if lanes.negative[axis] { lo[axis] } else { hi[axis] });
        // SAFETY: the CPU has AVX2 (this function's contract).
        let (mut alive, _) = unsafe {
            let (far, all) = (_mm256_loadu_ps(cull.as_ptr()), PacketLanes::select(u32::MAX));
            lanes.enter_box(first, last, far, all, &mut [0.0; PACKET_RAYS])
        };
        stats.nodes_visited += PACKET_RAYS as u64;
        let nearest_first = collectors[0].wants_nearest_first();
        let (mut len, mut node, mut rays_in_node) = (0usize, 0usize, alive);
        while rays_in_node != 0 {
            let active = rays_in_node;
            let owner = &self.nodes[node];
            let children = usize::from(self.children[node]);
            stats.nodes_visited += (children * active.count_ones() as usize) as u64;
            // The entered lanes: (rays entering, the nearest of their distances, lane); each one's distances.
            let mut entered = [(0u32, 0f32, 0usize); WIDTH];
            let mut near = [[0f32; PACKET_RAYS]; WIDTH];
            let mut count = 0;
            // The lanes some active ray may enter, by the packet's interval; then each of them exactly.
            let mut lanes_left = match &lanes.interval {
                Some(interval) => {
                    let (mut bits, mut largest) = (active, f32::NEG_INFINITY);
                    while bits != 0 {
                        largest = largest.max(cull[bits.trailing_zeros() as usize]);
                        bits &= bits - 1;
                    }
                    // SAFETY: the CPU has AVX2 (this function's contract).
                    unsafe { interval.may_enter(owner, lanes.rows, largest) }
                }
                None => u32::MAX,
            } & ((1 << children) - 1);
            // SAFETY: as above.
            let (far, active_lanes) = unsafe { (_mm256_loadu_ps(cull.as_ptr()), PacketLanes::select(active)) };
            while lanes_left != 0 {
                let lane = lanes_left.trailing_zeros() as usize;
                lanes_left &= lanes_left - 1;
                let near = &mut near[lane];
                // SAFETY: as above.
                let (rays_in, nearest) = unsafe { lanes.enter(owner, lane, far, active_lanes, near) };
                // Kept or overwritten by the next lane, without a branch (which lanes are entered is hard to predict).
                entered[count] = (rays_in, nearest, lane);
                count += usize::from(rays_in != 0);
            }
            for &(_, _, lane) in &entered[..count] {
                let index = owner.index[lane] as usize;
                match owner.count[lane] as usize {
                    0 => prefetch::<{ size_of::<WideNode>() / CACHE_LINE }>(self.nodes.as_ptr().wrapping_add(index)),
                    leaf_size => prefetch_leaf(index..index + leaf_size),
                }
            }
            if nearest_first {
                // Insertion by distance, nearest first.
                for at in 1..count {
                    let mut at = at;
                    while at > 0 && entered[at - 1].1 > entered[at].1 {
                        entered.swap(at - 1, at);
                        at -= 1;
                    }
                }
            }
            for &(rays_in, _, lane) in entered[..count].iter().skip(1).rev() {
                stack[len] = PacketEntry { near: near[lane], lane_ref: (node * WIDTH + lane) as u32, rays: rays_in };
                len += 1;
            }
            let mut next = (count > 0).then(|| ((node * WIDTH + entered[0].2) as u32, entered[0].0));
            // Leaves are handled as they come; the first inner lane reached is visited next, with its rays.
            rays_in_node = 0;
            while rays_in_node == 0 {
                let (lane_ref, rays_in) = match next.take() {
                    Some(next) => next,
                    None => {
                        if len == 0 {
                            return;
                        }
                        len -= 1;
                        let entry = &stack[len];
                        // SAFETY: as above.
                        let within = unsafe { lanes.within(&entry.near, &cull) };
                        (entry.lane_ref, entry.rays & alive & within)
                    }
                };
                if rays_in == 0 {
                    continue;
                }
                let (owner, lane) = (&self.nodes[lane_ref as usize / WIDTH], lane_ref as usize % WIDTH);
                let (index, size) = (owner.index[lane] as usize, owner.count[lane] as usize);
                if size == 0 {
                    (node, rays_in_node) = (index, rays_in);
                    continue;
                }
                leaf(index..index + size, rays_in, collectors, stats);
                let mut bits = rays_in;
                while bits != 0 {
                    let ray = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    cull[ray] = collectors[ray].cull_tmax();
                    if collectors[ray].done() {
                        alive &= !(1 << ray);
                    }
                }
                if alive == 0 {
                    return;
                }
            }
        }
    }
}

/// A packet's rays spread over AVX lanes, a ray a lane, once a packet.
struct PacketLanes {
    /// Origin, by axis.
    origin: [__m256; 3],
    /// `1/direction`, by axis.
    inv_direction: [__m256; 3],
    /// `tmin`.
    tmin: __m256,
    /// Per axis, whether the rays meet the boxes' maxima first (the same for every ray of a packet).
    negative: [bool; 3],
    /// Per axis, where in a node the row of the planes the rays meet first lies, and the row of those they meet last
    /// (byte offsets, from `negative`).
    rows: [(usize, usize); 3],
    /// The projection axes of the triangle test, `kx`, `ky`, `kz` (the same for every ray of a packet).
    axes: [usize; 3],
    /// Origin on the projection axes.
    projected_origin: [__m256; 3],
    /// The first two shear constants.
    shear: [__m256; 2],
    /// The rays as one interval, for a first test of a node's children all at once; `None` where an interval bound
    /// could be NaN.
    interval: Option<PacketInterval>,
}

/// A packet's rays as one interval: per axis the smallest and largest origin and `1/direction` over its rays, each
/// spread over a node's eight lanes, and the smallest `tmin`.
struct PacketInterval {
    /// Per axis, the smallest and the largest origin.
    origin: [[__m256; 2]; 3],
    /// Per axis, the smallest and the largest `1/direction`.
    inv_direction: [[__m256; 2]; 3],
    /// The smallest `tmin`.
    tmin: __m256,
}

impl PacketLanes {
    /// # Safety
    /// The CPU must have AVX; `rays` may make a packet ([`may_pack`]).
    #[inline(always)]
    unsafe fn new(rays: &[PreparedRay; PACKET_RAYS]) -> PacketLanes {
        let first = &rays[0];
        let axes = [first.kx, first.ky, first.kz];
        // SAFETY (all): the CPU has AVX (the caller's contract).
        let origin =
            unsafe { [gather(rays, |r| r.origin.x), gather(rays, |r| r.origin.y), gather(rays, |r| r.origin.z)] };
        let inv_direction = unsafe {
            [
                gather(rays, |r| r.inv_direction.x),
                gather(rays, |r| r.inv_direction.y),
                gather(rays, |r| r.inv_direction.z),
            ]
        };
        let tmin = unsafe { gather(rays, |r| r.tmin) };
        PacketLanes {
            origin,
            inv_direction,
            tmin,
            negative: first.negative,
            rows: std::array::from_fn(|axis| {
                let row = |bound: usize| bound + 4 * WIDTH * axis;
                let (lo, hi) = (row(offset_of!(WideNode, lo)), row(offset_of!(WideNode, hi)));
                if first.negative[axis] { (hi, lo) } else { (lo, hi) }
            }),
            axes,
            projected_origin: axes.map(|axis| origin[axis]),
            shear: unsafe { [gather(rays, |r| r.shear.x), gather(rays, |r| r.shear.y)] },
            interval: unsafe { PacketInterval::new(origin, inv_direction, tmin) },
        }
    }

    /// Whether the rays head within [`MIN_COSINE`] of the first's direction and start within `spread` of its origin
    /// (so that they meet much the same boxes; a NaN fails), all at once.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[inline(always)]
    unsafe fn coherent(&self, rays: &[PreparedRay; PACKET_RAYS], spread: f32) -> bool {
        // SAFETY: the CPU has AVX2 (the caller's contract).
        unsafe {
            // No `map` with intrinsics here: its closure is compiled without AVX and might not be inlined.
            let first = |v: __m256| _mm256_broadcastss_ps(_mm256_castps256_ps128(v));
            let dot3 = |a: [__m256; 3], b: [__m256; 3]| {
                _mm256_add_ps(
                    _mm256_add_ps(_mm256_mul_ps(a[0], b[0]), _mm256_mul_ps(a[1], b[1])),
                    _mm256_mul_ps(a[2], b[2]),
                )
            };
            let direction =
                [gather(rays, |r| r.direction.x), gather(rays, |r| r.direction.y), gather(rays, |r| r.direction.z)];
            let heading = [first(direction[0]), first(direction[1]), first(direction[2])];
            // cos(angle)² ≥ MIN_COSINE², without a square root: dot² ≥ MIN_COSINE² · |heading|² · |d|², with dot > 0.
            let dot = dot3(direction, heading);
            let lengths = dot3(direction, direction);
            let least = _mm256_mul_ps(_mm256_set1_ps(MIN_COSINE * MIN_COSINE), first(lengths));
            let along = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(dot, _mm256_setzero_ps()),
                _mm256_cmp_ps::<_CMP_GE_OQ>(_mm256_mul_ps(dot, dot), _mm256_mul_ps(least, lengths)),
            );
            let offset = |axis: usize| _mm256_sub_ps(self.origin[axis], first(self.origin[axis]));
            let offset = [offset(0), offset(1), offset(2)];
            let near = _mm256_cmp_ps::<_CMP_LE_OQ>(dot3(offset, offset), _mm256_set1_ps(spread * spread));
            _mm256_movemask_ps(_mm256_and_ps(along, near)) == 0xff
        }
    }

    /// Which of the `active` rays (their lanes all ones: [`PacketLanes::select`]) enter lane `lane` of `node` within
    /// `[tmin, far]`, a bit each: [`PacketLanes::enter_box`] on the lane's box.
    ///
    /// # Safety
    /// The CPU must have AVX; `lane` must be below [`WIDTH`].
    #[inline(always)]
    unsafe fn enter(
        &self,
        node: &WideNode,
        lane: usize,
        far: __m256,
        active: __m256,
        near: &mut [f32; PACKET_RAYS],
    ) -> (u32, f32) {
        // SAFETY: each offset is that of a row of `WIDTH` floats in the node, and `lane` is below `WIDTH`.
        let plane =
            |offset: usize| unsafe { *(node as *const WideNode).cast::<u8>().add(offset).cast::<f32>().add(lane) };
        let (first, last) = (self.rows.map(|(first, _)| plane(first)), self.rows.map(|(_, last)| plane(last)));
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { self.enter_box(first, last, far, active, near) }
    }

    /// Which of the `active` rays (their lanes all ones: [`PacketLanes::select`]) enter the box whose planes they meet
    /// first are `first` and last are `last` (by axis), within `[tmin, far]`, a bit each: the lane test of
    /// [`super::wide`] (so [`crate::intersect::aabb::intersect`]'s) with the rays in the lanes. Stores each ray's entry
    /// distance into `near` and returns the rays with the nearest of their distances.
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[inline(always)]
    unsafe fn enter_box(
        &self,
        first: [f32; 3],
        last: [f32; 3],
        far: __m256,
        active: __m256,
        near: &mut [f32; PACKET_RAYS],
    ) -> (u32, f32) {
        // SAFETY: the CPU has AVX (the caller's contract); the store writes the whole array.
        unsafe {
            let (mut entry, mut exit) = (self.tmin, far);
            for axis in 0..3 {
                let (origin, inv) = (self.origin[axis], self.inv_direction[axis]);
                let t0 = _mm256_mul_ps(_mm256_sub_ps(_mm256_set1_ps(first[axis]), origin), inv);
                entry = _mm256_max_ps(t0, entry);
                let t1 = _mm256_mul_ps(_mm256_sub_ps(_mm256_set1_ps(last[axis]), origin), inv);
                exit = _mm256_min_ps(t1, exit);
            }
            let (slack, magnitude) = (_mm256_set1_ps(SLACK), _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX)));
            let entry = _mm256_sub_ps(entry, _mm256_mul_ps(_mm256_and_ps(entry, magnitude), slack));
            let exit = _mm256_add_ps(exit, _mm256_mul_ps(_mm256_and_ps(exit, magnitude), slack));
            let inside = _mm256_and_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(entry, exit), active);
            _mm256_storeu_ps(near.as_mut_ptr(), entry);
            // The nearest entry among those rays: the others set to +∞, then the minimum across lanes.
            let masked = _mm256_blendv_ps(_mm256_set1_ps(f32::INFINITY), entry, inside);
            let half = _mm_min_ps(_mm256_castps256_ps128(masked), _mm256_extractf128_ps::<1>(masked));
            let quarter = _mm_min_ps(half, _mm_movehl_ps(half, half));
            let nearest = _mm_min_ss(quarter, _mm_shuffle_ps::<0b01>(quarter, quarter));
            (_mm256_movemask_ps(inside) as u32, _mm_cvtss_f32(nearest))
        }
    }

    /// The lanes of the rays in `rays` (a bit each) all ones, the others zero.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[inline(always)]
    unsafe fn select(rays: u32) -> __m256 {
        // SAFETY: the CPU has AVX2 (the caller's contract).
        unsafe {
            let bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
            let set = _mm256_and_si256(_mm256_set1_epi32(rays as i32), bits);
            _mm256_castsi256_ps(_mm256_cmpeq_epi32(set, bits))
        }
    }

    /// A bit per ray whose entry distance `near` is within its cull distance `cull` (`near ≤ cull`).
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[inline(always)]
    unsafe fn within(&self, near: &[f32; PACKET_RAYS], cull: &[f32; PACKET_RAYS]) -> u32 {
        // SAFETY: the CPU has AVX (the caller's contract); the loads read whole arrays.
        unsafe {
            let (near, cull) = (_mm256_loadu_ps(near.as_ptr()), _mm256_loadu_ps(cull.as_ptr()));
            _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, cull)) as u32
        }
    }

    /// A bit per ray that may hit the triangle in lane `lane` of a block ([`crate::intersect::triangle::may_hit`]).
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[inline(always)]
    unsafe fn may_hit(&self, (rows, lane): (&Block, usize)) -> u32 {
        let corners = Splat { rows, lane, axes: self.axes };
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe { filter::may_hit_lanes(&corners, self.projected_origin, self.shear) }
    }
}

impl PacketInterval {
    /// The interval of a packet's rays, given as their origins, `1/direction` and `tmin` (a ray a lane); `None` when
    /// a ray has a zero or infinite direction component (`1/direction` ∞ or 0, where a bound could be `0 · ∞`) or a
    /// NaN `tmin`. Origins are finite in a packet ([`PacketLanes::coherent`]).
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[inline(always)]
    unsafe fn new(origin: [__m256; 3], inv_direction: [__m256; 3], tmin: __m256) -> Option<PacketInterval> {
        // SAFETY: the CPU has AVX (the caller's contract).
        unsafe {
            let (infinity, zero) = (_mm256_set1_ps(f32::INFINITY), _mm256_setzero_ps());
            let magnitude = _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX));
            let usable = inv_direction.iter().fold(_mm256_cmp_ps::<_CMP_ORD_Q>(tmin, tmin), |usable, &inv| {
                let finite = _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_and_ps(inv, magnitude), infinity);
                _mm256_and_ps(usable, _mm256_and_ps(finite, _mm256_cmp_ps::<_CMP_NEQ_OQ>(inv, zero)))
            });
            if _mm256_movemask_ps(usable) != 0xff {
                return None;
            }
            Some(PacketInterval {
                origin: spread_range(origin),
                inv_direction: spread_range(inv_direction),
                tmin: spread_min(tmin),
            })
        }
    }

    /// A bit per lane of `node` that some ray of the packet may enter within `[tmin, cull]` (`cull` the largest cull
    /// distance of the rays still active): a lane left out is entered by none of them, so that the exact test
    /// ([`PacketLanes::enter`]) needs to run on the others only. Each slab distance is bounded over the interval
    /// by its four corners (it is monotonic in the origin and in `1/direction`, and so are the rounded operations),
    /// and the interval widened by four times [`SLACK`], more than the exact test's.
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[inline(always)]
    unsafe fn may_enter(&self, node: &WideNode, rows: [(usize, usize); 3], cull: f32) -> u32 {
        // SAFETY: the CPU has AVX (the caller's contract); each offset is that of a row of the node, 32-byte aligned.
        unsafe {
            let row = |offset: usize| _mm256_load_ps((node as *const WideNode).cast::<u8>().add(offset).cast::<f32>());
            let (mut entry, mut exit) = (self.tmin, _mm256_set1_ps(cull));
            for (axis, (first, last)) in rows.into_iter().enumerate() {
                let ([o_lo, o_hi], [i_lo, i_hi]) = (self.origin[axis], self.inv_direction[axis]);
                let (near, far) = (row(first), row(last));
                let (a, b) = (_mm256_sub_ps(near, o_lo), _mm256_sub_ps(near, o_hi));
                let lowest = _mm256_min_ps(
                    _mm256_min_ps(_mm256_mul_ps(a, i_lo), _mm256_mul_ps(a, i_hi)),
                    _mm256_min_ps(_mm256_mul_ps(b, i_lo), _mm256_mul_ps(b, i_hi)),
                );
                entry = _mm256_max_ps(lowest, entry);
                let (c, d) = (_mm256_sub_ps(far, o_lo), _mm256_sub_ps(far, o_hi));
                let highest = _mm256_max_ps(
                    _mm256_max_ps(_mm256_mul_ps(c, i_lo), _mm256_mul_ps(c, i_hi)),
                    _mm256_max_ps(_mm256_mul_ps(d, i_lo), _mm256_mul_ps(d, i_hi)),
                );
                exit = _mm256_min_ps(highest, exit);
            }
            let (slack, magnitude) = (_mm256_set1_ps(4.0 * SLACK), _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX)));
            let entry = _mm256_sub_ps(entry, _mm256_mul_ps(_mm256_and_ps(entry, magnitude), slack));
            let exit = _mm256_add_ps(exit, _mm256_mul_ps(_mm256_and_ps(exit, magnitude), slack));
            _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(entry, exit)) as u32
        }
    }
}

/// The packet's `value` of each ray, a ray a lane.
///
/// # Safety
/// The CPU must have AVX.
#[inline(always)]
unsafe fn gather(rays: &[PreparedRay; PACKET_RAYS], value: impl Fn(&PreparedRay) -> f32) -> __m256 {
    let [a, b, c, d, e, f, g, h] = rays;
    // SAFETY: the CPU has AVX (the caller's contract).
    unsafe { _mm256_setr_ps(value(a), value(b), value(c), value(d), value(e), value(f), value(g), value(h)) }
}

/// The smallest of `v`'s lanes, in every lane (`v` holds no NaN).
///
/// # Safety
/// The CPU must have AVX.
#[inline(always)]
unsafe fn spread_min(v: __m256) -> __m256 {
    // SAFETY: the CPU has AVX (the caller's contract).
    unsafe {
        let v = _mm256_min_ps(v, _mm256_permute2f128_ps::<1>(v, v));
        let v = _mm256_min_ps(v, _mm256_shuffle_ps::<0b0100_1110>(v, v));
        _mm256_min_ps(v, _mm256_shuffle_ps::<0b1011_0001>(v, v))
    }
}

/// Per axis, the smallest and the largest of `v`'s lanes, each in every lane (`v` holds no NaN). Written out, not with
/// `map`: a closure is compiled without AVX and might not be inlined.
///
/// # Safety
/// The CPU must have AVX.
#[inline(always)]
unsafe fn spread_range(v: [__m256; 3]) -> [[__m256; 2]; 3] {
    // SAFETY: the CPU has AVX (the caller's contract).
    unsafe {
        [
            [spread_min(v[0]), spread_max(v[0])],
            [spread_min(v[1]), spread_max(v[1])],
            [spread_min(v[2]), spread_max(v[2])],
        ]
    }
}

/// The largest of `v`'s lanes, in every lane (`v` holds no NaN).
///
/// # Safety
/// The CPU must have AVX.
#[inline(always)]
unsafe fn spread_max(v: __m256) -> __m256 {
    // SAFETY: the CPU has AVX (the caller's contract).
    unsafe {
        let v = _mm256_max_ps(v, _mm256_permute2f128_ps::<1>(v, v));
        let v = _mm256_max_ps(v, _mm256_shuffle_ps::<0b0100_1110>(v, v));
        _mm256_max_ps(v, _mm256_shuffle_ps::<0b1011_0001>(v, v))
    }
}

/// One triangle of a block as [`filter::Corners`] for a packet: each of its coordinates in every ray's lane.
struct Splat<'a> {
    /// The block.
    rows: &'a Block,
    /// The triangle's lane in it.
    lane: usize,
    /// The packet's `kx`, `ky`, `kz`.
    axes: [usize; 3],
}

impl filter::Corners<__m256> for Splat<'_> {
    #[inline(always)]
    unsafe fn corner(&self, c: usize) -> [__m256; 3] {
        let ([kx, ky, kz], rows, lane) = (self.axes, &self.rows[3 * c..3 * c + 3], self.lane);
        // No closure here: it would be compiled without AVX. SAFETY: the CPU has AVX (the caller's contract).
        unsafe { [_mm256_set1_ps(rows[kx][lane]), _mm256_set1_ps(rows[ky][lane]), _mm256_set1_ps(rows[kz][lane])] }
    }
}

#[cfg(test)]
mod tests {
    use glam::{Vec3, Vec3A};

    use super::*;
    use crate::accel::BuildOptions;
    use crate::backend::cpu::CpuAccel;
    use crate::format::{Hit, HitFormat, Ray, RayFlags, RayFormat};
    use crate::geometry::{BuildInput, TriangleInput, gather};
    use crate::mesh::Mesh;
    use crate::query::{Query, QueryKind};

    /// A bumpy lattice (shared edges and vertices that rays pass exactly through), with a floor and slivers across
    /// it, and a Prime mask on every fifth triangle.
    fn scene() -> (TriangleBvh, Mesh) {
        let side = 24;
        let height = |i: u32, j: u32| ((i * 7 + j * 3) % 5) as f32 * 0.05;
        let mut lattice = Mesh::default();
        for j in 0..=side {
            for i in 0..=side {
                lattice.positions.push(Vec3::new(i as f32 * 0.125, j as f32 * 0.125, height(i, j)));
            }
        }
        for j in 0..side {
            for i in 0..side {
                let at = |i: u32, j: u32| j * (side + 1) + i;
                lattice.triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                lattice.triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
        let mesh = lattice.with_floor_and_slivers(40, 3);
        let packed = mesh.pack();
        let masks: Vec<u8> =
            (0..mesh.triangles.len() as u32).flat_map(|t| u32::from(t % 5 == 0).to_le_bytes()).collect();
        let input = TriangleInput { masks: Some(&masks), ..packed.input() };
        let triangles = gather(&[BuildInput::Triangles(input)], 1).expect("valid scene");
        (TriangleBvh::build(triangles, &BuildOptions::default()), mesh)
    }

    /// Rays from a camera over the lattice through a grid of points, some through its vertices and edges, some
    /// cut short by their range, some masked; in groups of eight neighbours.
    fn camera_rays() -> Vec<PreparedRay> {
        rays_from(|_| Vec3A::new(1.4, 1.6, 3.0), |target, eye| target - eye)
    }

    /// Rays to the same grid of points as [`camera_rays`] from origins (by pixel) along directions (by point and
    /// origin), with the same ranges and masks.
    fn rays_from(origin: impl Fn(u32) -> Vec3A, direction: impl Fn(Vec3A, Vec3A) -> Vec3A) -> Vec<PreparedRay> {
        (0..64 * 64)
            .map(|pixel| {
                let (x, y) = ((pixel % 64) as f32 / 16.0, (pixel / 64) as f32 / 16.0 - 0.5);
                let eye = origin(pixel);
                let direction = direction(Vec3A::new(x, y, 0.1), eye);
                let (tmin, tmax) = match pixel % 7 {
                    0 => (0.5, f32::INFINITY),
                    1 => (0.0, 0.9),
                    _ => (0.0, f32::INFINITY),
                };
                let mask = u32::from(pixel % 3 == 0);
                PreparedRay::new(&Ray { origin: eye, direction, tmin, tmax, mask, ..Ray::default() }, RayFlags::empty())
            })
            .collect()
    }

    /// Each ray's records of `query`, traced in groups of eight as packets where they make one (returns how many
    /// did), or each alone.
    fn trace(bvh: &TriangleBvh, query: &Query, rays: &[PreparedRay], packets: bool) -> (Vec<u8>, Vec<u8>, usize) {
        let accel = CpuAccel::Triangles(bvh.clone());
        let mut stacks = accel.new_stacks();
        let records = query.records_per_ray();
        let mut hits = vec![0u8; query.hit_format.buffer_len(rays.len() * records)];
        let mut counts = vec![0u8; 4 * rays.len()];
        let mut scratch = vec![Hit::MISS; PACKET_RAYS * records];
        let mut packed = 0;
        for (group, rays) in rays.chunks(PACKET_RAYS).enumerate() {
            let mut parts = scratch.chunks_mut(records);
            let mut collectors: Vec<Collector<'_>> =
                rays.iter().map(|ray| Collector::new(query, ray, parts.next().expect("a part a ray"))).collect();
            let mut stats = TraceStats::default();
            if packets && bvh.trace_packet(&mut stacks.packet, rays, &mut collectors, &mut stats) {
                packed += 1;
            } else {
                for (ray, collector) in rays.iter().zip(&mut collectors) {
                    accel.traverse(&mut stacks.single, ray, &InstanceScope::WORLD, collector, &mut stats);
                }
            }
            for (i, collector) in collectors.iter().enumerate() {
                let index = group * PACKET_RAYS + i;
                collector.write(query, &mut hits, index * records, &mut counts, index);
            }
        }
        (hits, counts, packed)
    }

    #[test]
    fn packets_give_every_ray_the_answer_it_gets_alone() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let (bvh, _) = scene();
        // A pinhole camera (one origin); origins moved a little pixel by pixel (the packet's interval test then
        // spans several origins); parallel rays from a grid of origins, slanted (every `1/direction` finite) and
        // straight down (zero direction components: no interval test).
        let ray_sets = [
            ("pinhole", camera_rays()),
            (
                "moving eye",
                rays_from(|pixel| Vec3A::new(1.4, 1.6, 3.0) + 0.007 * (pixel % 8) as f32, |target, eye| target - eye),
            ),
            ("slanted", rays_from(|_| Vec3A::ZERO, |_, _| Vec3A::new(0.05, -0.03, -1.0))),
            ("straight down", rays_from(|_| Vec3A::ZERO, |_, _| -Vec3A::Z)),
        ]
        .map(|(name, rays)| match name {
            // Parallel rays start above their grid point.
            "slanted" | "straight down" => {
                (name, rays.iter().enumerate().map(|(pixel, ray)| parallel(ray, pixel as u32)).collect())
            }
            _ => (name, rays),
        });
        for (name, rays) in &ray_sets {
            packets_agree(&bvh, name, rays);
        }
    }

    /// `ray`, moved to start 3 units above point `pixel` of a grid as fine as a packet's origins must be close
    /// (its range and mask kept).
    fn parallel(ray: &PreparedRay, pixel: u32) -> PreparedRay {
        let (x, y) = (1.0 + (pixel % 64) as f32 / 128.0, 1.0 + (pixel / 64) as f32 / 128.0);
        let origin = Vec3A::new(x, y, 0.1) - ray.direction * 3.0;
        let moved =
            Ray { origin, direction: ray.direction, tmin: ray.tmin, tmax: ray.tmax, mask: ray.mask, ..Ray::default() };
        PreparedRay::new(&moved, RayFlags::empty())
    }

    /// Checks that `rays` traced in packets get the answers they get alone, for every query kind.
    fn packets_agree(bvh: &TriangleBvh, name: &str, rays: &[PreparedRay]) {
        let groups = rays.len() / PACKET_RAYS;
        for kind in [QueryKind::Closest, QueryKind::All, QueryKind::Count, QueryKind::Any] {
            for flags in [RayFlags::empty(), RayFlags::CULL_BACK_FACING] {
                let query = Query {
                    kind,
                    flags,
                    max_hits_per_ray: 4,
                    ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV)
                };
                let (alone, alone_counts, _) = trace(bvh, &query, rays, false);
                let (packed, packed_counts, packets) = trace(bvh, &query, rays, true);
                // Pinhole groups across a change of direction signs are traced alone.
                assert!(packets > groups * 3 / 4, "{name} {kind:?}: {packets} of {groups} groups packed");
                assert!(name != "pinhole" || packets < groups, "{name}: no group traced alone");
                let first_record = |ray: usize| ray * query.records_per_ray();
                let hit = |hits: &[u8], ray: usize| HitFormat::TTriidUV.read(hits, first_record(ray)).is_hit();
                let hits = (0..rays.len()).filter(|&ray| hit(&alone, ray)).count();
                assert!(hits > rays.len() / 3 && hits < rays.len(), "{name} {kind:?}: {hits} rays hit");
                match kind {
                    // Any hit may be another one; whether there is one may not.
                    QueryKind::Any => {
                        let agree = (0..rays.len()).all(|ray| hit(&alone, ray) == hit(&packed, ray));
                        assert!(agree, "{name} {kind:?}: hit/miss")
                    }
                    _ => {
                        let same = alone == packed && alone_counts == packed_counts;
                        assert!(same, "{name} {kind:?} {flags:?}: answers differ")
                    }
                }
            }
        }
    }

    #[test]
    fn the_interval_test_keeps_every_lane_a_ray_enters() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let u = |k: &mut u64| {
            *k += 1;
            crate::raygen::uniform(11, *k)
        };
        let (mut k, mut entered_lanes, mut ruled_out) = (0u64, 0, 0);
        for _ in 0..3000 {
            // Eight rays from origins up to 0.3 apart, heading within a few degrees of one direction, and eight
            // boxes of all sizes in the unit cube around them.
            let base = Vec3A::new(u(&mut k), u(&mut k), u(&mut k)) * 2.0 - Vec3A::ONE;
            let heading = Vec3A::new(u(&mut k) - 0.5, u(&mut k) - 0.5, u(&mut k) - 0.5).normalize_or(Vec3A::X);
            let rays: Vec<PreparedRay> = (0..PACKET_RAYS)
                .map(|_| {
                    let origin = base + Vec3A::new(u(&mut k), u(&mut k), u(&mut k)) * 0.3;
                    let direction = heading + Vec3A::new(u(&mut k), u(&mut k), u(&mut k)) * 0.05;
                    let tmin = if u(&mut k) < 0.2 { 0.5 } else { 0.0 };
                    PreparedRay::new(&Ray { origin, direction, tmin, ..Ray::default() }, RayFlags::empty())
                })
                .collect();
            if rays.iter().any(|ray| {
                (ray.kx, ray.ky, ray.kz, ray.negative) != (rays[0].kx, rays[0].ky, rays[0].kz, rays[0].negative)
            }) {
                continue;
            }
            let mut node = WideNode::EMPTY;
            for lane in 0..WIDTH {
                for axis in 0..3 {
                    let (a, size) = (u(&mut k) * 2.0 - 1.0, u(&mut k) * 1.5);
                    node.lo[axis][lane] = a;
                    node.hi[axis][lane] = a + size;
                }
            }
            let cull: [f32; PACKET_RAYS] = std::array::from_fn(|_| if u(&mut k) < 0.5 { 1.5 } else { f32::INFINITY });
            // SAFETY: the CPU has AVX2, as checked above.
            unsafe {
                let lanes = PacketLanes::new(rays[..].try_into().expect("a packet"));
                let interval = lanes.interval.as_ref().expect("finite directions");
                let largest = cull.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
                let kept = interval.may_enter(&node, lanes.rows, largest);
                let (far, all) = (_mm256_loadu_ps(cull.as_ptr()), PacketLanes::select(u32::MAX));
                for lane in 0..WIDTH {
                    let (rays_in, _) = lanes.enter(&node, lane, far, all, &mut [0.0; PACKET_RAYS]);
                    if rays_in != 0 {
                        entered_lanes += 1;
                        assert!(kept & (1 << lane) != 0, "lane {lane} entered by rays {rays_in:#b} but ruled out");
                    }
                    ruled_out += usize::from(kept & (1 << lane) == 0);
                }
            }
        }
        assert!(entered_lanes > 1000 && ruled_out > 1000, "{entered_lanes} lanes entered, {ruled_out} ruled out");
    }

    #[test]
    fn only_neighbours_heading_the_same_way_make_a_packet() {
        let (bvh, mesh) = scene();
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        let rays = camera_rays();
        let neighbours = &rays[64 * 30..64 * 30 + PACKET_RAYS];
        if !has_avx2() {
            return;
        }
        let packs = |rays: &[PreparedRay], query: &Query| {
            let mut collectors: Vec<Collector<'_>> =
                rays.iter().map(|ray| Collector::new(query, ray, &mut [])).collect();
            let mut stack = vec![PacketEntry::default(); bvh.wide.stack_size()];
            bvh.trace_packet(&mut stack, rays, &mut collectors, &mut TraceStats::default())
        };
        let diagonal = bvh.wide.diagonal();
        assert!(packs(neighbours, &query));
        assert!(!packs(&neighbours[..7], &query), "seven rays");
        let (lo, hi) = mesh.bounds();
        let random = crate::raygen::random_rays(lo, hi, PACKET_RAYS, 5, RayFormat::OriginTminDirectionTmax);
        let random: Vec<PreparedRay> = (0..PACKET_RAYS)
            .map(|i| {
                PreparedRay::new(
                    &RayFormat::OriginTminDirectionTmax.decode(&random[32 * i..32 * (i + 1)]),
                    RayFlags::empty(),
                )
            })
            .collect();
        assert!(!packs(&random, &query), "random rays");
        // One ray turned by 10° or moved by 2% of the scene: not a packet.
        let mut turned = neighbours.to_vec();
        let d = turned[3].direction;
        let ray = Ray { origin: turned[3].origin, direction: glam::Quat::from_rotation_x(0.17) * d, ..Ray::default() };
        turned[3] = PreparedRay::new(&ray, RayFlags::empty());
        assert!(!packs(&turned, &query), "a ray turned");
        let mut moved = neighbours.to_vec();
        moved[5].origin += Vec3A::X * 0.02 * diagonal;
        assert!(!packs(&moved, &query), "an origin moved");
        // A closest-hit ray that stops at its first hit keeps its own nearest-first order.
        let mut stopping = neighbours.to_vec();
        stopping[2].flags |= RayFlags::TERMINATE_ON_FIRST_HIT;
        assert!(!packs(&stopping, &query), "terminate on first hit");
        let any = Query { kind: QueryKind::Any, ..query };
        assert!(packs(&stopping, &any), "any query");
    }
}
