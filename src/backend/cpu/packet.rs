//! Packets: coherent rays — neighbours in the batch (a group of the batch driver: consecutive rays, or a 4×4 tile of
//! rays that follow an image's rows), heading the same way from nearby origins, as a camera's or a lidar's are —
//! traced together through a static accel's wide nodes (and a moving one's, each ray at its own time:
//! [`super::moving_packets`]): 16 at a time on a CPU with AVX-512, 8 with AVX2
//! ([`RayLanes`]: the walk is written once over the register). Each child box of a node is tested against the packet's
//! rays at once (a ray a lane), and each leaf triangle is sorted out for them at once ([`filter`]); the rays share the
//! loads of nodes and triangles and the traversal's bookkeeping.
//!
//! **Same answers as alone.** A ray takes part only in the box tests of nodes it entered, with the same operations
//! as [`super::wide`]'s lane test and its own nearest hit so far, and a popped node is re-checked against that hit
//! (walks that want no distances may enter inner nodes by the packet's interval alone, but test leaves ray by ray:
//! the same leaves, [`PacketTree::walk`]). The triangles it meets go to its own collector through the same test
//! (or, for an `any` query that keeps no hit, the same range test in the lanes). So every triangle that the ray alone
//! would find nearest is offered to it, and the tie rule (distance, then ids) picks the same hit whatever the
//! order: closest, `all` and `count` answers are byte for byte those of tracing each ray alone; only which hit an
//! `any` query stops at may differ. Nodes are visited in the packet's order: nearest first by the nearest of the
//! rays entering them for closest-hit queries, lane order for the others.

use std::arch::x86_64::*;
use std::mem::offset_of;
use std::ops::Range;

use glam::{Vec3, Vec3A};

use super::blocks::{Block, MetLanes};
use super::filter;
use super::ray_lanes::{MAX_PACKET_RAYS, RayLanes};
use super::traverse::{LeafSlots, Stacks};
use super::triangles::TriangleBvh;
use super::wide::{CACHE_LINE, Tree, WIDTH, WideBvh, WideNode, prefetch};
use crate::cpu_features::{has_avx2, has_avx512};
use crate::format::{Ray, RayFlags};
use crate::intersect::PreparedRay;
use crate::intersect::aabb::SLACK;
use crate::query::{
    Collector, GROUP_RAYS, InstanceScope, TraceStats, TriangleCandidate, accept_hit, consider_triangle,
};

/// Rays in an AVX2 packet; an AVX-512 packet holds [`MAX_PACKET_RAYS`].
const AVX2_PACKET_RAYS: usize = 8;
const _: () = assert!(MAX_PACKET_RAYS == GROUP_RAYS && GROUP_RAYS.is_multiple_of(AVX2_PACKET_RAYS));

/// The widest angle between a packet's first ray and another, as its cosine (about 8°): a camera's sixteen
/// neighbouring pixels are well within it.
const MIN_COSINE: f32 = 0.99;

/// How far a packet's origins may lie from its first ray's, as a fraction of the scene box's diagonal.
pub(super) const MAX_ORIGIN_SPREAD: f32 = 0.01;

/// A node lane waiting on a packet's stack: its index and count (as its node holds them), the rays that enter its
/// box, and (in a closest-hit walk) the distance at which each does.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct PacketEntry {
    /// Per ray, the distance at which it enters the lane's box (the first [`RayLanes::RAYS`] in use); kept by
    /// closest-hit walks only, stale in the others'.
    near: [f32; MAX_PACKET_RAYS],
    /// The lane's child node or first slot in the blocks.
    index: u32,
    /// The lane's primitives; 0 for an inner lane.
    count: u32,
    /// A bit per ray that enters it.
    rays: u32,
}

/// Whether `rays` (with their collectors) may make a packet, by what is cheapest to check: queries that let them share
/// an order of boxes, and the same direction signs for the first two rays and the last (most incoherent groups fail
/// there). The rest of the test is [`PacketLanes::new`] (every ray's signs, which the box test treats alike, and the
/// same projection axes, which the triangle test needs) and [`PacketLanes::coherent`].
pub(super) fn may_pack(rays: &[Ray], collectors: &[Collector<'_>]) -> bool {
    // `PreparedRay::negative`: a −0 component is not negative.
    let signs = |ray: &Ray| ray.direction.cmplt(Vec3A::ZERO).bitmask();
    let [first, second, .., last] = rays else { return false };
    // Only closest-hit rays may not share an order (the query kind is every collector's).
    let share_order = || !collectors[0].wants_nearest_first() || collectors.iter().all(Collector::may_share_order);
    signs(second) == signs(first) && signs(last) == signs(first) && share_order()
}

/// An accel whose coherent rays are walked together as packets: a geometry accel ([`TriangleBvh`], static or moving:
/// [`super::moving_packets`]), or an instance accel, whose packets are carried into the instances' spaces
/// ([`super::instance_packets`]).
pub(super) trait PacketAccel {
    /// Traces `rays` ([`RayLanes::RAYS`] of them, which [`may_pack`]) as a packet in `V` registers if they head the
    /// same way from nearby origins ([`PacketLanes::coherent`]), and says whether it did, for the visit order
    /// `NEAREST_FIRST` (which must be what the collectors want, [`Collector::wants_nearest_first`]).
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX2, and the caller be compiled with them.
    unsafe fn trace_packet_in_order<V: RayLanes, const NEAREST_FIRST: bool>(
        &self,
        stacks: &mut Stacks,
        rays: &[Ray],
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> bool;
}

/// Traces those of `rays` (a group of the batch driver's) that make packets through `accel`, and says which it traced
/// (a bit a ray): the whole group as one AVX-512 packet where the CPU has AVX-512 and the rays make one, else each
/// half as an AVX2 packet where it makes one. The rest are to be traced alone.
pub(super) fn trace_packets(
    accel: &impl PacketAccel,
    stacks: &mut Stacks,
    rays: &[Ray],
    collectors: &mut [Collector<'_>],
    stats: &mut TraceStats,
) -> u32 {
    if !has_avx2() {
        return 0;
    }
    if rays.len() == MAX_PACKET_RAYS && has_avx512() && may_pack(rays, collectors) {
        // SAFETY: the CPU has AVX-512F and the AVX2 features, as just checked.
        if unsafe { trace_packet_avx512(accel, stacks, rays, collectors, stats) } {
            return (1 << MAX_PACKET_RAYS) - 1;
        }
    }
    let mut traced = 0;
    let halves = rays.chunks_exact(AVX2_PACKET_RAYS).zip(collectors.chunks_exact_mut(AVX2_PACKET_RAYS));
    for (half, (rays, collectors)) in halves.enumerate() {
        // SAFETY: the CPU has the AVX2 features, as checked above.
        if may_pack(rays, collectors) && unsafe { trace_packet_avx2(accel, stacks, rays, collectors, stats) } {
            traced |= ((1 << AVX2_PACKET_RAYS) - 1) << (half * AVX2_PACKET_RAYS);
        }
    }
    traced
}

/// Defines `$name`, [`trace_packet`] in `$lanes` registers compiled with the target features `$features`.
macro_rules! trace_packet_compiled_for {
    ($(#[$doc:meta])* $name:ident, $lanes:ty, $features:literal) => {
        $(#[$doc])*
        ///
        /// # Safety
        /// The CPU must have the features this build is compiled with; `rays` are as many as its registers' lanes.
        #[target_feature(enable = $features)]
        unsafe fn $name(
            accel: &impl PacketAccel,
            stacks: &mut Stacks,
            rays: &[Ray],
            collectors: &mut [Collector<'_>],
            stats: &mut TraceStats,
        ) -> bool {
            // SAFETY: the CPU has the features (this function's contract).
            unsafe { trace_packet::<$lanes>(accel, stacks, rays, collectors, stats) }
        }
    };
}

trace_packet_compiled_for!(
    /// [`trace_packet`] in AVX2 registers, 8 rays (the features [`has_avx2`] checks).
    trace_packet_avx2,
    __m256,
    "avx2,fma,bmi1,bmi2,lzcnt,popcnt"
);

trace_packet_compiled_for!(
    /// [`trace_packet`] in AVX-512 registers, 16 rays (AVX-512F and the features [`has_avx2`] checks).
    trace_packet_avx512,
    __m512,
    "avx512f,avx2,fma,bmi1,bmi2,lzcnt,popcnt"
);

/// [`PacketAccel::trace_packet_in_order`] compiled once for each visit order, the one the collectors want.
///
/// # Safety
/// The CPU must have `V`'s instruction set and AVX2.
#[inline(always)]
unsafe fn trace_packet<V: RayLanes>(
    accel: &impl PacketAccel,
    stacks: &mut Stacks,
    rays: &[Ray],
    collectors: &mut [Collector<'_>],
    stats: &mut TraceStats,
) -> bool {
    // SAFETY: the CPU has `V`'s instruction set and AVX2 (this function's contract).
    unsafe {
        match collectors[0].wants_nearest_first() {
            true => accel.trace_packet_in_order::<V, true>(stacks, rays, collectors, stats),
            false => accel.trace_packet_in_order::<V, false>(stacks, rays, collectors, stats),
        }
    }
}

impl PacketAccel for TriangleBvh {
    #[inline(always)]
    unsafe fn trace_packet_in_order<V: RayLanes, const NEAREST_FIRST: bool>(
        &self,
        stacks: &mut Stacks,
        rays: &[Ray],
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> bool {
        let every_ray = (1 << V::RAYS) - 1;
        // SAFETY: the CPU has `V`'s instruction set and AVX2 (this function's contract).
        unsafe {
            self.walk_packet::<V, NEAREST_FIRST>(
                &mut stacks.packet,
                rays,
                every_ray,
                &InstanceScope::WORLD,
                collectors,
                stats,
            )
        }
    }
}

impl TriangleBvh {
    /// Walks the rays of `rays` ([`RayLanes::RAYS`] of them, as [`crate::intersect::traced`] makes them, in this
    /// accel's space) whose bits are set in `active` as a packet, in `scope`, if all of them head the same way from
    /// nearby origins ([`PacketLanes::coherent`]), and says whether it did; for the visit order `NEAREST_FIRST`,
    /// which must be what the collectors want. A moving accel's rays are walked at their own times
    /// ([`super::moving_packets`]).
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX2.
    #[inline(always)]
    pub(super) unsafe fn walk_packet<V: RayLanes, const NEAREST_FIRST: bool>(
        &self,
        stack: &mut [PacketEntry],
        rays: &[Ray],
        active: u32,
        scope: &InstanceScope,
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> bool {
        // SAFETY (all): the CPU has `V`'s instruction set and AVX2 (this function's contract).
        let Some(lanes) = (unsafe { PacketLanes::<V>::new(rays) }) else { return false };
        let tree = match self.node_keys {
            None => self.wide.packet_tree(),
            Some(_) => self.moving.packet_tree(self.bounds),
        };
        if !unsafe { lanes.coherent(&rays[0], MAX_ORIGIN_SPREAD * tree.diagonal()) } {
            return false;
        }
        // An any-hit query that keeps no hit, without face culling: a hit in a ray's range is all that matters to it.
        let culling = RayFlags::CULL_BACK_FACING | RayFlags::CULL_FRONT_FACING;
        let accepts_in_lanes = collectors[0].keeps_no_hit() && !rays.iter().any(|ray| ray.flags.intersects(culling));
        let packet = Packet { lanes: &lanes, rays, scope, accepts_in_lanes };
        if self.node_keys.is_some() {
            unsafe { self.walk_packet_at_times::<V, NEAREST_FIRST>(&tree, stack, &packet, active, collectors, stats) };
            return true;
        }
        // The closures are inlined at once: one left to itself is compiled without the instruction sets of the
        // function it is called from, and its intrinsics become calls.
        let blocks = &self.wide.blocks;
        let lane_corners = {
            #[inline(always)]
            |slot: usize| {
                let (rows, lane) = blocks.lane_of(slot);
                Splat { rows, lane, axes: lanes.axes }
            }
        };
        let ray_corners = {
            #[inline(always)]
            |slot: usize, _: usize| blocks.corners(slot)
        };
        let leaf = self.packet_leaf(&packet, self.wide.leaf_slots(), lane_corners, ray_corners);
        let prefetch_leaf = {
            #[inline(always)]
            |slots: Range<usize>| self.prefetch_leaf(slots)
        };
        unsafe {
            tree.walk::<V, _, NEAREST_FIRST>(stack, &lanes, &NodeBoxes, active, collectors, stats, leaf, prefetch_leaf)
        };
        true
    }

    /// What a packet walk does at a leaf of this accel (over the slots `leaf_slots` describes): each triangle is
    /// tested against the packet's rays at once, its corners in the rays' lanes from `lane_corners` (by slot), and
    /// offered to each ray that meets it (or is on an edge or a vertex), with its corners as that ray meets them from
    /// `ray_corners` (by slot and ray). Returns the rays it finished.
    #[inline(always)]
    pub(super) fn packet_leaf<'a, V: RayLanes, C: filter::Corners<V>>(
        &'a self,
        packet: &'a Packet<'a, V>,
        leaf_slots: LeafSlots<'a>,
        lane_corners: impl Fn(usize) -> C + 'a,
        ray_corners: impl Fn(usize, usize) -> [Vec3; 3] + 'a,
    ) -> impl FnMut(Range<usize>, u32, &mut [Collector<'_>], &mut TraceStats) -> u32 + 'a {
        let &Packet { lanes, rays, scope, accepts_in_lanes } = packet;
        #[inline(always)]
        move |slots: Range<usize>, mut active: u32, collectors: &mut [Collector<'_>], stats: &mut TraceStats| {
            stats.triangle_tests += (slots.len() * active.count_ones() as usize) as u64;
            let (mut met, mut finished) = (MetLanes::NONE, 0u32);
            for slot in slots {
                // SAFETY: the CPU has `V`'s instruction set (the walk's contract).
                let (edges, hits) = unsafe { lanes.intersect(&lane_corners(slot), active, &mut met) };
                let mut candidates = edges | hits;
                if candidates == 0 {
                    continue;
                }
                let (id, mask) = leaf_slots.id_and_mask(slot);
                let geometry_flags = self.geometry_flags[id.geom_id as usize];
                if accepts_in_lanes && mask == 0 {
                    // What `accept_hit` would ask of each hit ray, asked in the lanes: its range.
                    let accepted = hits & unsafe { lanes.within_range(&met.t) };
                    let mut bits = accepted;
                    while bits != 0 {
                        collectors[bits.trailing_zeros() as usize].offer_found();
                        bits &= bits - 1;
                    }
                    finished |= accepted;
                    candidates = edges;
                }
                // Ray by ray in lane order, as each alone would be offered the triangle: rays on an edge or a vertex
                // through the whole scalar test (its exact rule), the others from the hit found in the lanes.
                while candidates != 0 {
                    let lane = candidates.trailing_zeros() as usize;
                    candidates &= candidates - 1;
                    let (ray, collector) = (&rays[lane], &mut collectors[lane]);
                    let corners = ray_corners(slot, lane);
                    let candidate = TriangleCandidate { corners: &corners, id, mask, geometry_flags };
                    if edges & (1 << lane) != 0 {
                        consider_on_edge(ray, &candidate, scope, collector);
                    } else if ray.mask & mask == 0 {
                        accept_hit(ray.tmin, ray.flags, &candidate, scope, collector, met.hit(lane));
                    }
                    // Without a branch: which rays a triangle finishes is hard to predict.
                    finished |= u32::from(collector.done()) << lane;
                }
                active &= !finished;
                if active == 0 {
                    break;
                }
            }
            finished
        }
    }
}

/// A packet as its leaves test triangles: its rays (as [`crate::intersect::traced`] makes them) and their lanes, the
/// instance scope, and whether a hit within a ray's range is all its collectors ask (an any-hit query that keeps no
/// hit, without face culling), which the lanes then check.
pub(super) struct Packet<'a, V> {
    /// The rays in the lanes.
    pub(super) lanes: &'a PacketLanes<V>,
    /// The rays.
    pub(super) rays: &'a [Ray],
    /// Where they are traced.
    pub(super) scope: &'a InstanceScope,
    /// Whether a hit in a ray's range is accepted in the lanes.
    pub(super) accepts_in_lanes: bool,
}

/// [`consider_triangle`] for a packet's ray on an edge or a vertex of the triangle, which takes the scalar test and its
/// exact rule: prepared alone, which is rare enough not to be worth keeping a prepared ray for every ray.
#[cold]
#[inline(never)]
fn consider_on_edge(
    ray: &Ray,
    candidate: &TriangleCandidate<'_>,
    scope: &InstanceScope,
    collector: &mut Collector<'_>,
) {
    consider_triangle(&PreparedRay::from_traced(ray), candidate, scope, collector);
}

/// Wide nodes as a packet walks them: the nodes, the box around them all, and whether they fit the CPU's last-level
/// cache, where a node visited in vain costs little ([`PacketTree::walk`]).
pub(super) struct PacketTree<'a> {
    /// The nodes.
    pub(super) tree: Tree<'a>,
    /// The box around them (the root's).
    pub(super) root: (Vec3A, Vec3A),
    /// Whether they fit the last-level cache.
    pub(super) in_cache: bool,
}

impl WideBvh {
    /// Its nodes as a packet walks them.
    fn packet_tree(&self) -> PacketTree<'_> {
        PacketTree { tree: self.tree(), root: self.root, in_cache: self.in_cache }
    }
}

impl PacketTree<'_> {
    /// The length of the root box's diagonal (0 when there are no nodes).
    pub(super) fn diagonal(&self) -> f32 {
        (self.root.1 - self.root.0).length()
    }

    /// Walks the nodes with the rays of a packet whose bits are set in `rays`, nearest first (by the nearest of the
    /// rays entering a box) when `NEAREST_FIRST` (which must be what the collectors want,
    /// [`Collector::wants_nearest_first`]), and hands each leaf some of them reach (its slots and those rays, a bit
    /// each) to `leaf`, which returns the rays it finished (their collectors done). `prefetch_leaf` starts loading a
    /// leaf's data as soon as a ray enters the leaf's box.
    ///
    /// Only a closest-hit query moves a ray's cull distance during the walk (to its nearest hit): a lane waiting on
    /// the stack keeps its rays' entry distances, to drop the rays whose hit has come nearer by the time it is taken
    /// off. The other kinds keep their rays' `tmax` as cull distance, so their rays are checked against it as the lane
    /// is pushed (the same rays as when taken off), and the entry holds no distances.
    ///
    /// The other kinds want no distances to order the lanes either, so where the packet has its interval and the
    /// nodes fit the cache ([`PacketTree::in_cache`]), an inner lane is entered by all the active rays as soon as the
    /// interval lets some of them in: each ray's own box test waits for the leaves, which are tested ray by ray
    /// before their triangles are. A ray then walks nodes it would not enter alone (a box it misses inside one its
    /// packet's interval meets), but it meets the same leaves and triangles: a leaf's box lies within its ancestors',
    /// so one that a ray enters is one whose every ancestor it enters. This saves most of the exact box tests of the
    /// nodes, for a node now and then that no ray enters, which costs more than it saves where it must come from
    /// memory.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX2.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn walk<V: RayLanes, B: LaneBoxes<V>, const NEAREST_FIRST: bool>(
        &self,
        stack: &mut [PacketEntry],
        lanes: &PacketLanes<V>,
        boxes: &B,
        rays: u32,
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
        mut leaf: impl FnMut(Range<usize>, u32, &mut [Collector<'_>], &mut TraceStats) -> u32,
        prefetch_leaf: impl Fn(Range<usize>),
    ) {
        let Tree { nodes, children, .. } = self.tree;
        if nodes.is_empty() {
            return;
        }
        let mut cull = [0f32; MAX_PACKET_RAYS];
        for (cull, collector) in cull.iter_mut().zip(collectors.iter()) {
            *cull = collector.cull_tmax();
        }
        let (lo, hi) = (self.root.0.to_array(), self.root.1.to_array());
        let first: [f32; 3] = std::array::from_fn(|axis| if lanes.negative[axis] { hi[axis] } else { lo[axis] });
        let last: [f32; 3] = std::array::from_fn(|axis| if lanes.negative[axis] { lo[axis] } else { hi[axis] });
        // SAFETY (all): the CPU has `V`'s instruction set and AVX2 (this function's contract).
        let (mut alive, _) = unsafe {
            let (far, given) = (V::load(&cull), V::mask(rays));
            let first = [V::splat(first[0]), V::splat(first[1]), V::splat(first[2])];
            let last = [V::splat(last[0]), V::splat(last[1]), V::splat(last[2])];
            lanes.enter_box::<false>(first, last, far, given, &mut [0.0; MAX_PACKET_RAYS])
        };
        stats.nodes_visited += u64::from(rays.count_ones());
        debug_assert_eq!(NEAREST_FIRST, collectors[0].wants_nearest_first());
        let (mut len, mut node, mut rays_in_node) = (0usize, 0usize, alive);
        let inner_by_interval = !NEAREST_FIRST && self.in_cache && lanes.interval.is_some();
        let most_at_root = unsafe { V::load(&cull).most(V::mask(alive)) };
        // A node's entered lanes: (rays entering, the nearest of their distances, lane); each one's distances. Made
        // once a walk: a node reads only what it wrote.
        let mut entered = [(0u32, 0f32, 0usize); WIDTH];
        let mut near = [[0f32; MAX_PACKET_RAYS]; WIDTH];
        while rays_in_node != 0 {
            let active = rays_in_node;
            let owner = &nodes[node];
            let children = usize::from(children[node]);
            stats.nodes_visited += (children * active.count_ones() as usize) as u64;
            let mut count = 0;
            // The lanes some active ray may enter, by the packet's interval; then each of them exactly.
            let (far, active_lanes) = unsafe { (V::load(&cull), V::mask(active)) };
            // The largest cull distance of the active rays (a NaN one counts as −∞: that ray enters nothing); of the
            // rays alive at the root where cull distances do not move (at least the active rays').
            let most = match NEAREST_FIRST {
                true => unsafe { far.most(active_lanes) },
                false => most_at_root,
            };
            let mut lanes_left = match &lanes.interval {
                Some(interval) => unsafe { interval.may_enter(owner, lanes.rows, most) },
                None => u32::MAX,
            } & ((1 << children) - 1);
            // Where the walk wants no distances, an inner lane the interval lets in is taken with all the active rays
            // ([`PacketTree::walk`]); only leaves are tested ray by ray.
            let by_interval = |lane: usize| inner_by_interval && owner.count[lane] == 0;
            while lanes_left != 0 {
                let lane = lanes_left.trailing_zeros() as usize;
                lanes_left &= lanes_left - 1;
                let near = &mut near[lane];
                let (rays_in, nearest) = match by_interval(lane) {
                    true => (active, 0.0),
                    false => unsafe {
                        let (first, last) = boxes.planes(node, owner, lane, &lanes.rows);
                        lanes.enter_box::<NEAREST_FIRST>(first, last, far, active_lanes, near)
                    },
                };
                // Kept or overwritten by the next lane, without a branch (which lanes are entered is hard to predict).
                entered[count] = (rays_in, nearest, lane);
                count += usize::from(rays_in != 0);
            }
            for &(_, _, lane) in &entered[..count] {
                let index = owner.index[lane] as usize;
                match owner.count[lane] as usize {
                    0 => prefetch::<{ size_of::<WideNode>() / CACHE_LINE }>(nodes.as_ptr().wrapping_add(index)),
                    leaf_size => prefetch_leaf(index..index + leaf_size),
                }
            }
            if NEAREST_FIRST {
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
                let (index, count) = (owner.index[lane], owner.count[lane]);
                let entry = &mut stack[len];
                if NEAREST_FIRST {
                    *entry = PacketEntry { near: near[lane], index, count, rays: rays_in };
                } else {
                    let within = match by_interval(lane) {
                        true => u32::MAX,
                        false => unsafe { V::bits(V::load(&near[lane]).le(V::load(&cull))) },
                    };
                    (entry.index, entry.count, entry.rays) = (index, count, rays_in & within);
                }
                len += 1;
            }
            let mut next = (count > 0).then(|| (owner.index[entered[0].2], owner.count[entered[0].2], entered[0].0));
            // Leaves are handled as they come; the first inner lane reached is visited next, with its rays.
            rays_in_node = 0;
            while rays_in_node == 0 {
                let (index, size, rays_in) = match next.take() {
                    Some(next) => next,
                    None => {
                        if len == 0 {
                            return;
                        }
                        len -= 1;
                        let entry = &stack[len];
                        let within = match NEAREST_FIRST {
                            true => unsafe { V::bits(V::load(&entry.near).le(V::load(&cull))) },
                            false => u32::MAX,
                        };
                        (entry.index, entry.count, entry.rays & alive & within)
                    }
                };
                if rays_in == 0 {
                    continue;
                }
                let (index, size) = (index as usize, size as usize);
                if size == 0 {
                    (node, rays_in_node) = (index, rays_in);
                    continue;
                }
                alive &= !leaf(index..index + size, rays_in, collectors, stats);
                if NEAREST_FIRST {
                    let mut bits = rays_in;
                    while bits != 0 {
                        let ray = bits.trailing_zeros() as usize;
                        bits &= bits - 1;
                        cull[ray] = collectors[ray].cull_tmax();
                    }
                }
                if alive == 0 {
                    return;
                }
            }
        }
    }
}

/// Where a packet walk finds the boxes of a node's lanes that its rays enter: in the node ([`NodeBoxes`]), or, for the
/// nodes of a moving accel, interpolated at each ray's time (`BoxesAtTimes` in [`super::moving_packets`]). Either way
/// the node's own lanes' boxes, and the tree's root box, hold them: the packet's interval tests a node's lanes all at
/// once by those ([`PacketInterval::may_enter`]), and the root's box sorts out the rays that enter no lane.
pub(super) trait LaneBoxes<V> {
    /// Per axis, the planes of lane `lane` of node `node` (`owner`) that the rays meet first, and those they meet
    /// last, a ray a lane; `rows` says where in a node they lie ([`PacketLanes::rows`]).
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set; `node` is a node of the tree walked, `owner` that node, and `lane` is
    /// below [`WIDTH`].
    unsafe fn planes(&self, node: usize, owner: &WideNode, lane: usize, rows: &[(usize, usize); 3])
    -> ([V; 3], [V; 3]);
}

/// The boxes of a static tree's lanes: the nodes' own, the same for every ray.
pub(super) struct NodeBoxes;

impl<V: RayLanes> LaneBoxes<V> for NodeBoxes {
    #[inline(always)]
    unsafe fn planes(&self, _: usize, owner: &WideNode, lane: usize, rows: &[(usize, usize); 3]) -> ([V; 3], [V; 3]) {
        let [(f0, l0), (f1, l1), (f2, l2)] = *rows;
        // No closure here: it would be compiled without the instruction set.
        // SAFETY: the CPU has the instruction set (the caller's contract); the rows are a node's, `lane` below `WIDTH`.
        unsafe {
            (
                [V::splat(plane(owner, f0, lane)), V::splat(plane(owner, f1, lane)), V::splat(plane(owner, f2, lane))],
                [V::splat(plane(owner, l0, lane)), V::splat(plane(owner, l1, lane)), V::splat(plane(owner, l2, lane))],
            )
        }
    }
}

/// Lane `lane` of the row at byte offset `row` of `node` (one of its `lo` or `hi` rows).
///
/// # Safety
/// `row` is the offset of one of a node's rows of [`WIDTH`] floats, and `lane` is below [`WIDTH`].
#[inline(always)]
pub(super) unsafe fn plane(node: &WideNode, row: usize, lane: usize) -> f32 {
    // SAFETY: the row is one of the node's, and the lane one of its floats (the contract).
    unsafe { *(node as *const WideNode).cast::<u8>().add(row).cast::<f32>().add(lane) }
}

/// A packet's rays spread over `V`'s lanes, a ray a lane, once a packet: what [`PreparedRay::new`] computes for a ray
/// alone, computed for all of them at once with the same operations (so the same bits).
pub(super) struct PacketLanes<V> {
    /// Origin, by axis.
    origin: [V; 3],
    /// Direction, by axis.
    direction: [V; 3],
    /// `1/direction`, by axis.
    inv_direction: [V; 3],
    /// `tmin`.
    tmin: V,
    /// `tmax`.
    tmax: V,
    /// Per axis, whether the rays meet the boxes' maxima first (the same for every ray of a packet).
    negative: [bool; 3],
    /// Per axis, where in a node the row of the planes the rays meet first lies, and the row of those they meet last
    /// (byte offsets, from `negative`).
    rows: [(usize, usize); 3],
    /// The projection axes of the triangle test, `kx`, `ky`, `kz` (the same for every ray of a packet).
    pub(super) axes: [usize; 3],
    /// Origin on the projection axes.
    projected_origin: [V; 3],
    /// The first two shear constants.
    shear: [V; 2],
    /// The third shear constant, `1/direction[kz]`.
    shear_z: V,
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

impl<V: RayLanes> PacketLanes<V> {
    /// The lanes of `rays` ([`RayLanes::RAYS`] of them, which [`may_pack`]); `None` when their directions' signs or
    /// their projection axes differ.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX.
    #[inline(always)]
    pub(super) unsafe fn new(rays: &[Ray]) -> Option<PacketLanes<V>> {
        // No `map` over registers here: its closure is compiled without the instruction set and might not be inlined.
        // SAFETY (all): the CPU has the instruction sets (the caller's contract).
        unsafe {
            let [dx, dy, dz, _] = V::columns(rays, offset_of!(Ray, direction));
            let direction = [dx, dy, dz];
            if !same_signs(direction) {
                return None;
            }
            // The axes are those of the first ray, and the directions' signs those of every ray (just checked).
            let first = PreparedRay::from_traced(&rays[0]);
            let axes = [first.kx, first.ky, first.kz];
            if !same_projection_axis(direction, first.kz) {
                return None;
            }
            let [ox, oy, oz, _] = V::columns(rays, offset_of!(Ray, origin));
            let origin = [ox, oy, oz];
            let inv_direction = [reciprocal(direction[0]), reciprocal(direction[1]), reciprocal(direction[2])];
            let [tmin, tmax, ..] = V::columns(rays, offset_of!(Ray, tmin));
            let (one, along) = (V::splat(1.0), direction[axes[2]]);
            Some(PacketLanes {
                origin,
                direction,
                inv_direction,
                tmin,
                tmax,
                negative: first.negative,
                rows: std::array::from_fn(|axis| {
                    let row = |bound: usize| bound + 4 * WIDTH * axis;
                    let (lo, hi) = (row(offset_of!(WideNode, lo)), row(offset_of!(WideNode, hi)));
                    if first.negative[axis] { (hi, lo) } else { (lo, hi) }
                }),
                axes,
                projected_origin: [origin[axes[0]], origin[axes[1]], origin[axes[2]]],
                shear: [direction[axes[0]].div(along), direction[axes[1]].div(along)],
                shear_z: one.div(along),
                interval: PacketInterval::new(origin, inv_direction, tmin),
            })
        }
    }

    /// Whether the rays head within [`MIN_COSINE`] of the first's direction and start within `spread` of its origin
    /// (so that they meet much the same boxes; a NaN fails), all at once.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set.
    #[inline(always)]
    pub(super) unsafe fn coherent(&self, first: &Ray, spread: f32) -> bool {
        // No closures with register arithmetic here: they are compiled without the instruction set.
        // SAFETY: the CPU has the instruction set (the caller's contract).
        unsafe {
            let direction = self.direction;
            let heading = [V::splat(first.direction.x), V::splat(first.direction.y), V::splat(first.direction.z)];
            // cos(angle)² ≥ MIN_COSINE², without a square root: dot² ≥ MIN_COSINE² · |heading|² · |d|², with dot > 0.
            let dot = dot3(direction, heading);
            let least = V::splat(MIN_COSINE * MIN_COSINE * first.direction.length_squared());
            let along = V::and(V::splat(0.0).lt(dot), least.mul(dot3(direction, direction)).le(dot.mul(dot)));
            let offset = [
                self.origin[0].sub(V::splat(first.origin.x)),
                self.origin[1].sub(V::splat(first.origin.y)),
                self.origin[2].sub(V::splat(first.origin.z)),
            ];
            let near = dot3(offset, offset).le(V::splat(spread * spread));
            V::bits(V::and(along, near)) == (1 << V::RAYS) - 1
        }
    }

    /// Which of the `active` rays enter the box whose planes they meet first are `first` and last are `last` (by
    /// axis), within `[tmin, far]`, a bit each: the lane test of [`super::wide`] (so
    /// [`crate::intersect::aabb::intersect`]'s) with the rays in the lanes. Stores each ray's entry distance into
    /// `near` and returns the rays with, when `NEAREST`, the nearest of their distances (else 0: a walk that does not
    /// order its lanes saves the reduction).
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set.
    #[inline(always)]
    unsafe fn enter_box<const NEAREST: bool>(
        &self,
        first: [V; 3],
        last: [V; 3],
        far: V,
        active: V::Mask,
        near: &mut [f32; MAX_PACKET_RAYS],
    ) -> (u32, f32) {
        // SAFETY: the CPU has the instruction set (the caller's contract).
        unsafe {
            let (mut entry, mut exit) = (self.tmin, far);
            for axis in 0..3 {
                let (origin, inv) = (self.origin[axis], self.inv_direction[axis]);
                entry = first[axis].sub(origin).mul(inv).max(entry);
                exit = last[axis].sub(origin).mul(inv).min(exit);
            }
            let slack = V::splat(SLACK);
            let entry = entry.sub(entry.abs().mul(slack));
            let exit = exit.add(exit.abs().mul(slack));
            let inside = V::and(entry.le(exit), active);
            entry.write_to(near);
            (V::bits(inside), if NEAREST { entry.least(inside) } else { 0.0 })
        }
    }

    /// The rays whose distance `t` (a ray a lane) lies within their `[tmin, tmax]`, a bit each, as [`accept_hit`] asks
    /// it (false with NaN).
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set.
    #[inline(always)]
    unsafe fn within_range(&self, t: &[f32; MAX_PACKET_RAYS]) -> u32 {
        // SAFETY: the CPU has the instruction set (the caller's contract).
        unsafe { V::load(t).within(self.tmin, self.tmax) }
    }

    /// The watertight test ([`crate::intersect::triangle::intersect`]) of the triangle `corners` (its coordinates in
    /// the rays' lanes) against the `active` rays at once, with the same operations in the same order, as far as it goes without its exact
    /// rule for edges and vertices: returns the rays whose f32 edge functions are not all nonzero and whose line may
    /// meet the triangle (they are to take the scalar test), and the rays whose line meets it, whose hit is left in
    /// `met` ([`MetLanes::hit`]).
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set.
    #[inline(always)]
    unsafe fn intersect(
        &self,
        corners: &impl filter::Corners<V>,
        active: u32,
        met: &mut MetLanes<MAX_PACKET_RAYS>,
    ) -> (u32, u32) {
        // SAFETY: the CPU has the instruction set (the caller's contract).
        unsafe {
            let sheared = filter::shear(corners, self.projected_origin, self.shear);
            let [u, v, w] = sheared.edges;
            let may_hit = V::zero_or_not_mixed(u, v, w) & active;
            if may_hit == 0 {
                return (0, 0);
            }
            let meeting = filter::meet(&sheared, self.shear_z, may_hit);
            if meeting.met != 0 {
                met.keep(&meeting, &sheared);
            }
            (meeting.on_edge, meeting.met)
        }
    }
}

impl PacketInterval {
    /// The interval of a packet's rays, given as their origins, `1/direction` and `tmin` (a ray a lane); `None` when
    /// a ray has a zero or infinite direction component (`1/direction` ∞ or 0, where a bound could be `0 · ∞`) or a
    /// NaN `tmin`. Origins are finite in a packet ([`PacketLanes::coherent`]).
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX.
    #[inline(always)]
    unsafe fn new<V: RayLanes>(origin: [V; 3], inv_direction: [V; 3], tmin: V) -> Option<PacketInterval> {
        // No closures with register arithmetic here: they are compiled without the instruction set.
        // SAFETY: the CPU has the instruction sets (the caller's contract).
        unsafe {
            let (zero, infinity) = (V::splat(0.0), V::splat(f32::INFINITY));
            let [x, y, z] = [inv_direction[0].abs(), inv_direction[1].abs(), inv_direction[2].abs()];
            let finite = V::and(V::and(x.lt(infinity), y.lt(infinity)), z.lt(infinity));
            let nonzero = V::and(V::and(zero.lt(x), zero.lt(y)), zero.lt(z));
            if V::bits(V::and(V::and(finite, nonzero), tmin.le(tmin))) != (1 << V::RAYS) - 1 {
                return None;
            }
            let [x, y] = spread_ranges([origin[0], origin[1]]);
            let [z, inv_x] = spread_ranges([origin[2], inv_direction[0]]);
            let [inv_y, inv_z] = spread_ranges([inv_direction[1], inv_direction[2]]);
            Some(PacketInterval {
                origin: [x, y, z],
                inv_direction: [inv_x, inv_y, inv_z],
                tmin: _mm256_set1_ps(tmin.smallest()),
            })
        }
    }

    /// A bit per lane of `node` that some ray of the packet may enter within `[tmin, cull]` (`cull` the largest cull
    /// distance of the rays still active): a lane left out is entered by none of them, so that the exact test
    /// ([`PacketLanes::enter_box`]) needs to run on the others only. Each slab distance is bounded over the interval
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

/// `1/d` lane by lane, +∞ where `d` is 0: [`PreparedRay::inv_direction`].
///
/// # Safety
/// The CPU must have `V`'s instruction set.
#[inline(always)]
unsafe fn reciprocal<V: RayLanes>(d: V) -> V {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe { V::select(d.eq(V::splat(0.0)), V::splat(f32::INFINITY), V::splat(1.0).div(d)) }
}

/// Whether every lane of `direction` has the same signs: each component negative in all lanes or in none, as
/// [`PreparedRay::negative`] has it (a −0 or NaN component is not negative).
///
/// # Safety
/// The CPU must have `V`'s instruction set.
#[inline(always)]
unsafe fn same_signs<V: RayLanes>(direction: [V; 3]) -> bool {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe {
        let zero = V::splat(0.0);
        let all = (1 << V::RAYS) - 1;
        let uniform = |negative: u32| negative == 0 || negative == all;
        let [x, y, z] =
            [V::bits(direction[0].lt(zero)), V::bits(direction[1].lt(zero)), V::bits(direction[2].lt(zero))];
        uniform(x) && uniform(y) && uniform(z)
    }
}

/// Whether every lane of `direction` projects along axis `kz` in the triangle test: the axis of its largest
/// component, as [`PreparedRay::new`] picks it (ties to the earlier axis; NaN components lose every comparison).
///
/// # Safety
/// The CPU must have `V`'s instruction set.
#[inline(always)]
unsafe fn same_projection_axis<V: RayLanes>(direction: [V; 3], kz: usize) -> bool {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe {
        let [x, y, z] = [direction[0].abs(), direction[1].abs(), direction[2].abs()];
        let x_largest = V::bits(V::and(y.le(x), z.le(x)));
        let y_over_z = V::bits(z.le(y));
        let all = (1 << V::RAYS) - 1;
        match kz {
            0 => x_largest == all,
            1 => x_largest == 0 && y_over_z == all,
            _ => x_largest == 0 && y_over_z == 0,
        }
    }
}

/// `a · b` lane by lane, for vectors of three registers.
///
/// # Safety
/// The CPU must have `V`'s instruction set.
#[inline(always)]
unsafe fn dot3<V: RayLanes>(a: [V; 3], b: [V; 3]) -> V {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe { a[0].mul(b[0]).add(a[1].mul(b[1])).add(a[2].mul(b[2])) }
}

/// For each of two registers, the smallest and the largest of its lanes, each in every lane of an AVX register (the
/// lanes hold no NaN). The two are reduced together, each in one half of an AVX register, which takes about half the
/// instructions of reducing them one after the other.
///
/// # Safety
/// The CPU must have `V`'s instruction set and AVX.
#[inline(always)]
unsafe fn spread_ranges<V: RayLanes>([a, b]: [V; 2]) -> [[__m256; 2]; 2] {
    // SAFETY: the CPU has the instruction sets (the caller's contract).
    unsafe {
        let ((a_low, a_high), (b_low, b_high)) = (a.fold_to_eight(), b.fold_to_eight());
        let [a_smallest, b_smallest] = spread_both::<false>(a_low, b_low);
        let [a_largest, b_largest] = spread_both::<true>(a_high, b_high);
        [[a_smallest, a_largest], [b_smallest, b_largest]]
    }
}

/// The smallest (or with `LARGEST` the largest) lane of `a` and of `b`, each in every lane of an AVX register: `a`'s
/// lanes folded into the lower half of one register and `b`'s into its upper half, then each half folded on itself
/// twice.
///
/// # Safety
/// The CPU must have AVX.
#[inline(always)]
unsafe fn spread_both<const LARGEST: bool>(a: __m256, b: __m256) -> [__m256; 2] {
    // SAFETY: the CPU has AVX (the caller's contract).
    unsafe {
        let halves = pick::<LARGEST>(_mm256_permute2f128_ps::<0x20>(a, b), _mm256_permute2f128_ps::<0x31>(a, b));
        // Within each half: lanes 2, 3, 0, 1, then lanes 1, 0, 3, 2, so that every lane ends with the half's pick.
        let pairs = pick::<LARGEST>(halves, _mm256_permute_ps::<0b01_00_11_10>(halves));
        let all = pick::<LARGEST>(pairs, _mm256_permute_ps::<0b10_11_00_01>(pairs));
        [_mm256_permute2f128_ps::<0x00>(all, all), _mm256_permute2f128_ps::<0x11>(all, all)]
    }
}

/// `vmaxps` with `LARGEST`, `vminps` otherwise.
///
/// # Safety
/// The CPU must have AVX.
#[inline(always)]
unsafe fn pick<const LARGEST: bool>(a: __m256, b: __m256) -> __m256 {
    // SAFETY: the CPU has AVX (the caller's contract).
    unsafe { if LARGEST { _mm256_max_ps(a, b) } else { _mm256_min_ps(a, b) } }
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

impl<V: RayLanes> filter::Corners<V> for Splat<'_> {
    #[inline(always)]
    unsafe fn corner(&self, c: usize) -> [V; 3] {
        let ([kx, ky, kz], rows, lane) = (self.axes, &self.rows[3 * c..3 * c + 3], self.lane);
        // No closure here: it would be compiled without the instruction set.
        // SAFETY: the CPU has `V`'s instruction set (the caller's contract).
        unsafe { [V::splat(rows[kx][lane]), V::splat(rows[ky][lane]), V::splat(rows[kz][lane])] }
    }
}

#[cfg(test)]
pub(super) mod tests {
    use glam::{Vec3, Vec3A};

    use super::*;
    use crate::accel::BuildOptions;
    use crate::backend::cpu::CpuAccel;
    use crate::format::{Hit, HitFormat, RayFlags, RayFormat};
    use crate::geometry::{BuildInput, TriangleInput, gather};
    use crate::intersect::traced;
    use crate::mesh::Mesh;
    use crate::query::{Query, QueryKind};

    /// A bumpy lattice (shared edges and vertices that rays pass exactly through), with a floor and slivers across
    /// it, and a Prime mask on every fifth triangle.
    pub(in crate::backend::cpu) fn scene() -> (TriangleBvh, Mesh) {
        lattice(true)
    }

    /// [`scene`]'s triangles, with its masks or without.
    pub(in crate::backend::cpu) fn lattice(masked: bool) -> (TriangleBvh, Mesh) {
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
        let input = TriangleInput { masks: masked.then_some(&masks[..]), ..packed.input() };
        let triangles = gather(&[BuildInput::Triangles(input)], 1).expect("valid scene");
        (TriangleBvh::build(triangles, &BuildOptions::default(), &|| true).expect("a build that goes on"), mesh)
    }

    /// Rays from a camera over the lattice through a grid of points, some through its vertices and edges, some
    /// cut short by their range, some masked; in groups of eight neighbours.
    pub(in crate::backend::cpu) fn camera_rays() -> Vec<Ray> {
        rays_from(|_| Vec3A::new(1.4, 1.6, 3.0), |target, eye| target - eye)
    }

    /// Rays to the same grid of points as [`camera_rays`] from origins (by pixel) along directions (by point and
    /// origin), with the same ranges and masks.
    pub(in crate::backend::cpu) fn rays_from(
        origin: impl Fn(u32) -> Vec3A,
        direction: impl Fn(Vec3A, Vec3A) -> Vec3A,
    ) -> Vec<Ray> {
        (0..64 * 64)
            .map(|pixel| {
                let (x, y) = ((pixel % 64) as f32 / 16.0, (pixel / 64) as f32 / 16.0 - 0.5);
                let eye = origin(pixel);
                let direction = direction(Vec3A::new(x, y, 0.1), eye);
                // Some ranges end or start at the grid's points, among the lattice's bumps (a camera ray's `t` is 1
                // there): they cut hits short inside leaves.
                let (tmin, tmax) = match pixel % 7 {
                    0 => (0.5, f32::INFINITY),
                    1 => (0.0, 0.9),
                    2 => (1.0, f32::INFINITY),
                    3 => (0.0, 1.0),
                    _ => (0.0, f32::INFINITY),
                };
                let mask = u32::from(pixel % 3 == 0);
                Ray { origin: eye, direction, tmin, tmax, mask, ..Ray::default() }
            })
            .collect()
    }

    /// Each ray's records of `query`, traced in packets of `width` rays (8: AVX2, 16: AVX-512) where they make one
    /// (returns how many did), or each alone when `width` is 1.
    pub(in crate::backend::cpu) fn trace(
        accel: &CpuAccel,
        query: &Query,
        rays: &[Ray],
        width: usize,
    ) -> (Vec<u8>, Vec<u8>, usize) {
        let rays: Vec<Ray> = rays.iter().map(|ray| traced(ray, query.flags)).collect();
        let mut stacks = accel.new_stacks();
        let records = query.records_per_ray();
        let mut hits = vec![0u8; query.hit_format.buffer_len(rays.len() * records)];
        let mut counts = vec![0u8; 4 * rays.len()];
        let mut scratch = vec![Hit::MISS; width * records];
        let mut packed = 0;
        for (group, rays) in rays.chunks(width).enumerate() {
            let mut parts = scratch.chunks_mut(records);
            let mut collectors: Vec<Collector<'_>> =
                rays.iter().map(|ray| Collector::new(query, ray, parts.next().expect("a part a ray"))).collect();
            let mut stats = TraceStats::default();
            let packet = width > 1 && rays.len() == width && may_pack(rays, &collectors);
            // SAFETY: the tests call this only where the CPU has the width's instruction set.
            let traced = packet
                && unsafe {
                    match (accel, width) {
                        (CpuAccel::Triangles(bvh), AVX2_PACKET_RAYS) => {
                            trace_packet_avx2(bvh.as_ref(), &mut stacks, rays, &mut collectors, &mut stats)
                        }
                        (CpuAccel::Triangles(bvh), _) => {
                            trace_packet_avx512(bvh.as_ref(), &mut stacks, rays, &mut collectors, &mut stats)
                        }
                        (CpuAccel::Instances(bvh), AVX2_PACKET_RAYS) => {
                            trace_packet_avx2(bvh, &mut stacks, rays, &mut collectors, &mut stats)
                        }
                        (CpuAccel::Instances(bvh), _) => {
                            trace_packet_avx512(bvh, &mut stacks, rays, &mut collectors, &mut stats)
                        }
                        (CpuAccel::Transform(_), _) => false,
                    }
                };
            if traced {
                packed += 1;
            } else {
                for (ray, collector) in rays.iter().zip(&mut collectors) {
                    let ray = PreparedRay::new(ray, RayFlags::empty());
                    accel.traverse(&mut stacks.single, &ray, &InstanceScope::WORLD, collector, &mut stats);
                }
            }
            for (i, collector) in collectors.iter().enumerate() {
                let index = group * width + i;
                collector.write(query.hit_format, &mut hits, index * records, &mut counts, index);
            }
        }
        (hits, counts, packed)
    }

    /// `rays` (a 64 × 64 image's, row by row) reordered for packets of `width`: rows of 8 pixels make packets of 8;
    /// packets of 16 are 4 × 4 tiles, which head closer together than 16 pixels of a row of this small image.
    pub(in crate::backend::cpu) fn in_packet_order(rays: &[Ray], width: usize) -> Vec<Ray> {
        match width {
            AVX2_PACKET_RAYS => rays.to_vec(),
            _ => (0..rays.len()).map(|i| rays[(i / 256 * 4 + i % 16 / 4) * 64 + i / 16 % 16 * 4 + i % 4]).collect(),
        }
    }

    /// The packet widths this CPU runs: 8 with AVX2, and 16 too with AVX-512.
    pub(in crate::backend::cpu) fn widths() -> Vec<usize> {
        [(AVX2_PACKET_RAYS, has_avx2()), (MAX_PACKET_RAYS, has_avx512())]
            .into_iter()
            .filter_map(|(width, runs)| runs.then_some(width))
            .collect()
    }

    #[test]
    fn packets_give_every_ray_the_answer_it_gets_alone() {
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
        // Packets walk an accel that fits the cache otherwise than one that does not.
        let accels = [true, false].map(|in_cache| {
            let mut bvh = bvh.clone();
            bvh.wide.in_cache = in_cache;
            CpuAccel::Triangles(Box::new(bvh))
        });
        for (width, accel) in widths().into_iter().flat_map(|width| accels.iter().map(move |accel| (width, accel))) {
            for (name, rays) in &ray_sets {
                packets_agree(accel, name, &in_packet_order(rays, width), width, HitFormat::TTriidUV);
            }
        }
    }

    /// `ray`, moved to start 3 units above point `pixel` of a grid as fine as a packet's origins must be close
    /// (its range and mask kept).
    fn parallel(ray: &Ray, pixel: u32) -> Ray {
        let (x, y) = (1.0 + (pixel % 64) as f32 / 128.0, 1.0 + (pixel / 64) as f32 / 128.0);
        Ray { origin: Vec3A::new(x, y, 0.1) - ray.direction * 3.0, ..*ray }
    }

    /// Checks that `rays` traced in packets of `width` get the answers they get alone, for every query kind, without
    /// face culling, with the query's, and with some rays' own, in records of `records` (a format that holds `t`);
    /// `any` in the bitmask format too.
    pub(in crate::backend::cpu) fn packets_agree(
        accel: &CpuAccel,
        name: &str,
        rays: &[Ray],
        width: usize,
        records: HitFormat,
    ) {
        let groups = rays.len() / width;
        let culling = [(RayFlags::empty(), false), (RayFlags::CULL_BACK_FACING, false), (RayFlags::empty(), true)];
        let kinds = [QueryKind::Closest, QueryKind::All, QueryKind::Count, QueryKind::Any];
        let formats = [records, HitFormat::Bitmask];
        let cases = kinds.into_iter().flat_map(|kind| formats.map(|format| (kind, format)));
        for (kind, format) in cases.filter(|&(kind, format)| format == records || kind == QueryKind::Any) {
            for (flags, some_rays_cull) in culling {
                // Every fifth ray culls front faces itself.
                let rays: Vec<Ray> = (rays.iter().enumerate())
                    .map(|(i, ray)| match some_rays_cull && i % 5 == 0 {
                        true => Ray { flags: RayFlags::CULL_FRONT_FACING, ..*ray },
                        false => *ray,
                    })
                    .collect();
                let query = Query {
                    kind,
                    flags,
                    max_hits_per_ray: 4,
                    ..Query::closest(RayFormat::OriginTminDirectionTmax, format)
                };
                let (alone, alone_counts, _) = trace(accel, &query, &rays, 1);
                let (packed, packed_counts, packets) = trace(accel, &query, &rays, width);
                if format == HitFormat::Bitmask {
                    // A bit a ray: whether it hits, which packets must not change.
                    assert!(alone == packed, "{name} {kind:?} {flags:?} ×{width}: bitmasks differ");
                    continue;
                }
                // Pinhole groups across a change of direction signs are traced alone.
                assert!(packets > groups * 3 / 4, "{name} {kind:?} ×{width}: {packets} of {groups} groups packed");
                assert!(name != "pinhole" || packets < groups, "{name} ×{width}: no group traced alone");
                let first_record = |ray: usize| ray * query.records_per_ray();
                let hit = |hits: &[u8], ray: usize| records.read(hits, first_record(ray)).is_hit();
                let hits = (0..rays.len()).filter(|&ray| hit(&alone, ray)).count();
                assert!(hits > rays.len() / 4 && hits < rays.len(), "{name} {kind:?}: {hits} rays hit");
                match kind {
                    // Any hit may be another one; whether there is one may not.
                    QueryKind::Any => {
                        let agree = (0..rays.len()).all(|ray| hit(&alone, ray) == hit(&packed, ray));
                        assert!(agree, "{name} {kind:?} ×{width}: hit/miss")
                    }
                    _ => {
                        let same = alone == packed && alone_counts == packed_counts;
                        assert!(same, "{name} {kind:?} {flags:?} ×{width}: answers differ")
                    }
                }
            }
        }
    }

    proptest::proptest! {
        #[test]
        fn lanes_share_a_projection_axis_exactly_when_their_prepared_rays_do(
            pool in proptest::collection::vec(
                proptest::prop_oneof![
                    4 => -2.0f32..2.0,
                    2 => proptest::sample::select(vec![1.0f32, -1.0, 0.5, -0.5, 0.0, -0.0]),
                    1 => proptest::sample::select(vec![f32::NAN, f32::INFINITY]),
                ],
                3 * 3,
            ),
            picks in proptest::collection::vec(0..3usize, AVX2_PACKET_RAYS),
        ) {
            if has_avx2() {
                // Each lane one of three directions (so that lanes often agree), whose components tie (the selected
                // values), are zeros of both signs or NaN.
                let rays: Vec<Ray> = picks
                    .iter()
                    .map(|&pick| Ray { direction: Vec3A::from_slice(&pool[3 * pick..3 * pick + 3]), ..Ray::default() })
                    .collect();
                // SAFETY: the CPU has AVX2, as just checked.
                let [x, y, z, _] = unsafe { __m256::columns(&rays, offset_of!(Ray, direction)) };
                let direction = [x, y, z];
                for kz in 0..3 {
                    let alone = rays.iter().all(|ray| PreparedRay::from_traced(ray).kz == kz);
                    // SAFETY: as above.
                    proptest::prop_assert_eq!(unsafe { same_projection_axis(direction, kz) }, alone, "kz {}", kz);
                }
            }
        }
    }

    /// Checks [`spread_ranges`] in `V` registers against [`RayLanes::smallest`] and [`RayLanes::largest`] of
    /// the first [`RayLanes::RAYS`] of `a` and `b`.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX.
    unsafe fn spreads_as_reduced_one_by_one<V: RayLanes>(a: &[f32; MAX_PACKET_RAYS], b: &[f32; MAX_PACKET_RAYS]) {
        // SAFETY: the CPU has the instruction sets (the caller's contract).
        unsafe {
            let (a, b) = (V::load(a), V::load(b));
            let spread = spread_ranges([a, b]);
            let expected = [[a.smallest(), a.largest()], [b.smallest(), b.largest()]];
            for (register, (spread, expected)) in spread.iter().zip(expected).enumerate() {
                for (bound, (spread, expected)) in spread.iter().zip(expected).enumerate() {
                    let mut lanes = [0.0; WIDTH];
                    _mm256_storeu_ps(lanes.as_mut_ptr(), *spread);
                    assert_eq!(lanes, [expected; WIDTH], "{} lanes: register {register}, bound {bound}", V::RAYS);
                }
            }
        }
    }

    proptest::proptest! {
        #[test]
        fn two_registers_reduced_together_spread_their_smallest_and_largest_lanes(
            a in proptest::array::uniform16(-1e30f32..1e30),
            b in proptest::array::uniform16(-1e30f32..1e30),
            (tie, at) in (0usize..MAX_PACKET_RAYS, 0usize..MAX_PACKET_RAYS),
        ) {
            // The extreme lane anywhere, once with a copy of it in another lane.
            let mut b = b;
            b[at] = b[tie];
            // SAFETY: each width is checked only where the CPU has its instruction set.
            unsafe {
                if has_avx2() {
                    spreads_as_reduced_one_by_one::<__m256>(&a, &b);
                }
                if has_avx512() {
                    spreads_as_reduced_one_by_one::<__m512>(&a, &b);
                }
            }
        }
    }

    #[test]
    fn the_interval_test_keeps_every_lane_a_ray_enters() {
        if !has_avx2() {
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
            let rays: Vec<Ray> = (0..AVX2_PACKET_RAYS)
                .map(|_| {
                    let origin = base + Vec3A::new(u(&mut k), u(&mut k), u(&mut k)) * 0.3;
                    let direction = heading + Vec3A::new(u(&mut k), u(&mut k), u(&mut k)) * 0.05;
                    let tmin = if u(&mut k) < 0.2 { 0.5 } else { 0.0 };
                    Ray { origin, direction, tmin, ..Ray::default() }
                })
                .collect();
            let axes = |ray: &Ray| {
                let ray = PreparedRay::new(ray, RayFlags::empty());
                (ray.kx, ray.ky, ray.kz, ray.negative)
            };
            if rays.iter().any(|ray| axes(ray) != axes(&rays[0])) {
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
            let cull: [f32; MAX_PACKET_RAYS] =
                std::array::from_fn(|_| if u(&mut k) < 0.5 { 1.5 } else { f32::INFINITY });
            // SAFETY: the CPU has AVX2, as checked above.
            unsafe {
                let lanes = PacketLanes::<__m256>::new(&rays).expect("the same axes");
                let interval = lanes.interval.as_ref().expect("finite directions");
                let (far, all) = (__m256::load(&cull), __m256::mask(u32::MAX));
                let kept = interval.may_enter(&node, lanes.rows, far.most(all));
                for lane in 0..WIDTH {
                    let (first, last) = LaneBoxes::<__m256>::planes(&NodeBoxes, 0, &node, lane, &lanes.rows);
                    let (rays_in, _) = lanes.enter_box::<false>(first, last, far, all, &mut [0.0; MAX_PACKET_RAYS]);
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
        let diagonal = bvh.wide.packet_tree().diagonal();
        let bvh = CpuAccel::Triangles(Box::new(bvh));
        for width in widths() {
            let rays = in_packet_order(&camera_rays(), width);
            let packs = |rays: &[Ray], query: &Query| trace(&bvh, query, rays, width).2 == 1;
            let neighbours = &rays[64 * 30..64 * 30 + width];
            assert!(packs(neighbours, &query), "×{width}");
            assert!(!packs(&neighbours[..width - 1], &query), "×{width}: a ray short");
            let (lo, hi) = mesh.bounds();
            let random = crate::raygen::random_rays(lo, hi, width, 5, RayFormat::OriginTminDirectionTmax);
            let random: Vec<Ray> =
                random.chunks_exact(32).map(|bytes| RayFormat::OriginTminDirectionTmax.decode(bytes)).collect();
            assert!(!packs(&random, &query), "×{width}: random rays");
            // One ray turned by 10° or moved by 2% of the scene: not a packet.
            let mut turned = neighbours.to_vec();
            let d = turned[3].direction;
            turned[3] =
                Ray { origin: turned[3].origin, direction: glam::Quat::from_rotation_x(0.17) * d, ..Ray::default() };
            assert!(!packs(&turned, &query), "×{width}: a ray turned");
            // Rays whose x components are all a negligible +1e-7 make a packet; one of them at −1e-7 has a sign of
            // its own (its box test would take the other rays' planes): not a packet.
            let mut flipped: Vec<Ray> =
                neighbours.iter().map(|ray| Ray { direction: ray.direction.with_x(1e-7), ..*ray }).collect();
            assert!(packs(&flipped, &query), "×{width}: x components of +1e-7");
            flipped[5].direction.x = -1e-7;
            assert!(!packs(&flipped, &query), "×{width}: a sign of its own");
            let mut moved = neighbours.to_vec();
            moved[5].origin += Vec3A::X * 0.02 * diagonal;
            assert!(!packs(&moved, &query), "×{width}: an origin moved");
            // A closest-hit ray that stops at its first hit keeps its own nearest-first order.
            let mut stopping = neighbours.to_vec();
            stopping[2].flags |= RayFlags::TERMINATE_ON_FIRST_HIT;
            assert!(!packs(&stopping, &query), "×{width}: terminate on first hit");
            let any = Query { kind: QueryKind::Any, ..query };
            assert!(packs(&stopping, &any), "×{width}: any query");
        }
    }
}
