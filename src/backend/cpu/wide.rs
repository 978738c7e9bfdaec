//! The 8-wide BVH that static geometry accels are traversed with: the binary BVH of [`super::bvh`] collapsed so that
//! each node holds up to eight children's boxes in lanes (structure of arrays), tested against a ray all at once.
//! The lane loops are written so that the compiler turns them into SIMD: 8 lanes in one AVX2 register where the CPU
//! has AVX2 (detected at run time), two SSE registers otherwise.
//!
//! The box test is [`crate::intersect::aabb::intersect`]'s slab test lane by lane, with the same NaN rule (a NaN slab
//! distance leaves the interval as it was) and the same relative widening by [`SLACK`], which a ray that starts at or
//! after its origin (`tmin ≥ 0`) takes in its reciprocals once a walk instead of at every node ([`SlabRay`]). Both
//! tests are conservative, so which lanes a ray enters may differ from the binary walk's in the last bits of a
//! distance, never in a hit. For closest-hit queries (which prune by their nearest hit) the nearest child is visited
//! first, the second nearest next and the others after them in lane order; for the others (which must see every hit,
//! or stop at any) all in lane order. A node's lanes are ranked by how likely each child is to stop an any-hit ray for
//! what it costs ([`super::occlusion`]). Which triangles a ray can hit, and so every query's answer but which hit an
//! `any` query or a ray that stops at its first hit stops at, does not depend on the order.

use std::hint::select_unpredictable;
use std::ops::Range;

use glam::{Vec3, Vec3A};

use super::blocks::{Block, CornerBlocks, Placement};
use super::bvh::{Footprint, Node, VecLen};
use super::collapse::{EMPTY_LANE, Lane, collapse};
use super::large_pages::{LargePageArray, LargePages, Room};
use super::occlusion::stop_chance_per_cost;
use super::traverse::{LeafSlots, StackEntry};
use super::triangles::corner_bounds;
use super::turns::{exceed_last_level_cache, walks_in_turns};
#[cfg(target_arch = "x86_64")]
use crate::cpu_features::has_avx2;
use crate::geometry::TriangleRef;
use crate::geometry::motion::{Bounds, EMPTY, union};
use crate::intersect::PreparedRay;
use crate::intersect::aabb::SLACK;
use crate::query::{Collector, TraceStats};

/// Children per node.
pub(super) const WIDTH: usize = 8;

/// One node, 256 bytes (four cache lines, aligned to them): `0 lo[axis][lane] f32×24 | 96 hi[axis][lane] f32×24 |
/// 192 index u32×8 | 224 count u32×8`.
/// Lane `l` is a child: an inner node (`count[l]` 0, its node at `index[l]`), a leaf (its slots in the blocks,
/// `index[l] .. index[l] + count[l]`: [`WideBvh::ids`]), or empty (box `+∞ .. −∞`; the children come first, the
/// empty lanes after).
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C, align(64))]
pub(super) struct WideNode {
    /// Box minima, by axis then lane.
    pub(super) lo: [[f32; WIDTH]; 3],
    /// Box maxima, by axis then lane.
    pub(super) hi: [[f32; WIDTH]; 3],
    /// Per lane: the child node (inner) or the leaf's first slot in the blocks.
    pub(super) index: [u32; WIDTH],
    /// Per lane: primitives of a leaf, 0 for an inner or empty lane.
    pub(super) count: [u32; WIDTH],
}

impl WideNode {
    /// A node whose lanes are all empty.
    pub(super) const EMPTY: WideNode = WideNode {
        lo: [[f32::INFINITY; WIDTH]; 3],
        hi: [[f32::NEG_INFINITY; WIDTH]; 3],
        index: [0; WIDTH],
        count: [0; WIDTH],
    };

    /// Puts binary node `node` in lane `lane`, pointing at `index`.
    fn set_lane(&mut self, lane: usize, node: &Node, index: u32) {
        self.set_box(lane, node.min, node.max);
        self.index[lane] = index;
        self.count[lane] = node.count;
    }

    /// Makes `min .. max` the box of lane `lane`.
    pub(super) fn set_box(&mut self, lane: usize, min: Vec3, max: Vec3) {
        for axis in 0..3 {
            self.lo[axis][lane] = min[axis];
            self.hi[axis][lane] = max[axis];
        }
    }

    /// The box of lane `lane`.
    fn lane_box(&self, lane: usize) -> Bounds {
        let (lo, hi) = (self.lo.map(|row| row[lane]), self.hi.map(|row| row[lane]));
        (Vec3::from_array(lo), Vec3::from_array(hi))
    }
}

/// A static BVH collapsed to [`WIDTH`] children a node.
///
/// What the walks read without bounds checks, and [`WideBvh::collapse`] makes sure of: `children` has an entry a
/// node; every inner lane's index is below `nodes.len()`, which a `u32` holds.
#[derive(Debug, Clone, Default)]
pub(super) struct WideBvh {
    /// Nodes, the root first; empty when the binary BVH was.
    pub(super) nodes: LargePageArray<WideNode>,
    /// Children of each node: its first lanes, the rest are empty.
    pub(super) children: Vec<u8>,
    /// The root's box (the binary root's), which the packets read (x86-64 only).
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    pub(super) root: (Vec3A, Vec3A),
    /// Longest root-to-leaf path, in wide nodes.
    depth: usize,
    /// The leaves' triangles' corners in blocks, each leaf in as few blocks as it fits ([`Placement`]).
    pub(super) blocks: CornerBlocks,
    /// The ids of the triangles in the blocks' slots (a slot left empty before a leaf holds a stand-in).
    pub(super) ids: LargePageArray<TriangleRef>,
    /// Their Prime masks, where the accel has masks.
    pub(super) masks: Option<Vec<u32>>,
    /// Whether the nodes and blocks fit the CPU's last-level cache, where a node visited in vain costs little:
    /// packets that want no distances then enter inner nodes by their interval alone
    /// ([`super::packet::PacketTree::walk`]).
    pub(super) in_cache: bool,
    /// Whether incoherent rays are walked in turns ([`super::turns`]): as a rule, where the nodes and blocks exceed
    /// the CPU's last-level cache.
    pub(super) in_turns: bool,
}

impl WideBvh {
    /// Collapses a depth-first binary BVH ([`collapse`]) over triangles whose slots hold `corners`, `refs` and
    /// `masks` (where the accel has masks); the leaves' triangles are copied into blocks ([`Placement`]).
    pub fn collapse(binary: &[Node], corners: &[[Vec3; 3]], refs: &[TriangleRef], masks: Option<&[u32]>) -> WideBvh {
        let Some(root) = binary.first() else { return WideBvh::default() };
        let mut collapsed = collapse(binary, WIDTH);
        let rank = stop_chance_per_cost(binary, corners);
        for lanes in collapsed.lanes.chunks_mut(WIDTH) {
            let occupied = occupied(lanes);
            // Stable: equally ranked lanes keep the collapse's order.
            lanes[..occupied].sort_by(|a, b| rank[b.binary as usize].total_cmp(&rank[a.binary as usize]));
        }
        let placement = placement_of_leaves(binary);
        let leaf_slot = |leaf: &Node| placement.slot_of(leaf.index as usize) as u32;
        let node = |n: usize| wide_node(binary, &collapsed.lanes[n * WIDTH..(n + 1) * WIDTH], leaf_slot);
        let skeleton = Skeleton {
            children: collapsed.lanes.chunks(WIDTH).map(|lanes| occupied(lanes) as u8).collect(),
            root: (root.min.into(), root.max.into()),
            depth: collapsed.depth,
        };
        let ids = placement.gather(refs, TriangleRef { geom_id: 0, prim_id: 0 });
        WideBvh::lay_out(skeleton, node, corners, &placement, &ids, masks)
    }

    /// This wide BVH refitted to the triangles' new `corners` (and `masks`), `binary` being its binary BVH refitted
    /// to them: the same nodes, lanes, leaves and slots, each lane's box made again bottom-up — a leaf's the bounds of
    /// its triangles' corners, an inner lane's the union of its node's lanes' — and the blocks made again. Minima and
    /// maxima are exact, so every box is the one the refitted binary node in its lane has, which a collapse of
    /// `binary` would have put there; the collapse's choice of lanes and their ranking are kept instead of made again
    /// (what a refit is for: BENCHMARKS.md, "Refit against rebuild").
    pub fn refit(&self, binary: &[Node], corners: &[[Vec3; 3]], masks: Option<&[u32]>) -> WideBvh {
        let Some(root) = binary.first() else { return WideBvh::default() };
        let placement = placement_of_leaves(binary);
        let mut nodes = self.nodes.to_vec();
        // Inner lanes point to later nodes (checked by `lay_out`), so a node's children are refitted before it.
        for n in (0..nodes.len()).rev() {
            for lane in 0..usize::from(self.children[n]) {
                let (index, count) = (nodes[n].index[lane] as usize, nodes[n].count[lane] as usize);
                let (min, max) = match count {
                    0 => (0..usize::from(self.children[index])).map(|l| nodes[index].lane_box(l)).fold(EMPTY, union),
                    _ => {
                        let first = placement.held(index);
                        corner_bounds(&corners[first..first + count])
                    }
                };
                nodes[n].set_box(lane, min, max);
            }
        }
        let skeleton =
            Skeleton { children: self.children.clone(), root: (root.min.into(), root.max.into()), depth: self.depth };
        WideBvh::lay_out(skeleton, |n| nodes[n], corners, &placement, &self.ids, masks)
    }

    /// A wide BVH of `skeleton` whose node `n` is `node(n)`, its leaves' triangles (`corners`, `ids` of the blocks'
    /// slots, the accel slots' `masks`) placed in blocks by `placement`: nodes, blocks and ids in one allocation, in
    /// that order, so that the ids, read least, take the ordinary pages at its end ([`super::large_pages`]). Checks
    /// what the walks and [`WideBvh::refit`] rely on.
    fn lay_out(
        skeleton: Skeleton,
        node: impl Fn(usize) -> WideNode + Sync,
        corners: &[[Vec3; 3]],
        placement: &Placement,
        ids: &[TriangleRef],
        masks: Option<&[u32]>,
    ) -> WideBvh {
        let node_count = skeleton.children.len();
        let room = Room::default().and::<WideNode>(node_count);
        let mut pages =
            LargePages::new(room.and::<Block>(CornerBlocks::count(placement)).and::<TriangleRef>(ids.len()));
        let mut wide = WideBvh {
            nodes: pages.array_from_fn(node_count, node),
            children: skeleton.children,
            root: skeleton.root,
            depth: skeleton.depth,
            blocks: CornerBlocks::new(corners, placement, &mut pages),
            ids: pages.array_from_fn(ids.len(), |i| ids[i]),
            masks: masks.map(|masks| placement.gather(masks, 0)),
            in_cache: true,
            in_turns: false,
        };
        let exceeding_cache = exceed_last_level_cache(wide.size_bytes(Footprint::Exact));
        (wide.in_cache, wide.in_turns) = (!exceeding_cache, walks_in_turns(exceeding_cache));
        assert_well_formed(&wide.nodes, &wide.children);
        wide
    }

    /// The union of the images under `place` of the boxes of the root's lanes: a box around the triangles as `place`
    /// moves them (e.g. an instance's placement), tighter than the image of the root's box when `place` turns it;
    /// empty without nodes. (The lanes a level further down, up to `WIDTH²` boxes, traced no faster for eight times
    /// the instance build's time: BENCHMARKS.md, "Instances entered through their children's own boxes".)
    pub fn placed_bounds(&self, place: impl Fn(Bounds) -> Bounds) -> Bounds {
        let Some(root) = self.nodes.first() else { return EMPTY };
        (0..usize::from(self.children[0])).map(|lane| place(root.lane_box(lane))).fold(EMPTY, union)
    }

    /// What the leaves' slots in the blocks hold besides corners.
    pub(super) fn leaf_slots(&self) -> LeafSlots<'_> {
        LeafSlots { ids: &self.ids, masks: self.masks.as_deref() }
    }

    /// Stack entries a traversal needs ([`stack_size_of`]).
    pub fn stack_size(&self) -> usize {
        stack_size_of(self.depth)
    }

    /// Bytes it occupies.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        (footprint.of(&self.nodes as &dyn VecLen) * size_of::<WideNode>()
            + footprint.of(&self.children)
            + footprint.of(&self.ids) * size_of::<TriangleRef>()
            + self.masks.as_ref().map_or(0, |masks| footprint.of(masks) * 4)) as u64
            + self.blocks.size_bytes(footprint)
    }

    /// Its nodes as a walk reads them.
    #[inline(always)]
    pub(super) fn tree(&self) -> Tree<'_> {
        Tree { nodes: &self.nodes, children: &self.children, stack_size: self.stack_size() }
    }
}

/// Wide nodes as a walk reads them: a [`WideBvh`]'s ([`WideBvh::tree`]) or a [`WideTree`]'s, whose leaves are other
/// things than triangles (an instance accel's instances).
#[derive(Clone, Copy)]
pub(super) struct Tree<'a> {
    /// Nodes, the root first (every inner lane's index below their count, a `u32`).
    pub(super) nodes: &'a [WideNode],
    /// Children of each node: its first lanes, the rest are empty.
    pub(super) children: &'a [u8],
    /// Stack entries a walk needs.
    stack_size: usize,
}

impl Tree<'_> {
    /// Walks the nodes front to back and hands each leaf the ray reaches (its slots in the blocks, the collector and
    /// the statistics) to `leaf`, which returns whether the collector is done. `prefetch_leaf` starts loading a leaf's
    /// data (by its slots) as soon as the ray enters the leaf's box.
    ///
    /// Panics when `stack` holds fewer than [`WideBvh::stack_size`] (the tree's `stack_size`) entries.
    #[inline(always)]
    pub fn walk(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        leaf: impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool,
        prefetch_leaf: impl Fn(Range<usize>),
    ) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has AVX2 and the other features, as just checked.
            unsafe { self.walk_avx2(stack, ray, collector, stats, leaf, prefetch_leaf) };
            return;
        }
        let slab = SlabRay::new(ray);
        let enter = |node: &WideNode, tmax: f32| enter_lanes(node, &slab, tmax);
        self.walk_lanes(stack, collector, stats, enter, leaf, prefetch_leaf);
    }

    /// [`Tree::walk`] of nodes whose boxes move with time: the box test of node `n` reads its lanes' boxes from
    /// `boxes_at(n)` (a [`WideNode`] whose `lo` and `hi` are the boxes at the ray's time) instead of from the node; no
    /// leaf data is prefetched.
    ///
    /// Panics when `stack` holds fewer than the tree's `stack_size` entries.
    #[inline]
    pub fn walk_moving(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        leaf: impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool,
        boxes_at: impl Fn(usize) -> WideNode,
    ) {
        let first = self.nodes.as_ptr();
        // SAFETY: the walk hands the box test references into `nodes` only.
        let index = move |node: &WideNode| unsafe { (node as *const WideNode).offset_from(first) as usize };
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has AVX2 and the other features, as just checked.
            unsafe { self.walk_moving_avx2(stack, ray, collector, stats, leaf, move |node| boxes_at(index(node))) };
            return;
        }
        let slab = SlabRay::new(ray);
        let enter = |node: &WideNode, tmax: f32| enter_lanes(&boxes_at(index(node)), &slab, tmax);
        self.walk_lanes(stack, collector, stats, enter, leaf, |_| {});
    }

    /// [`Tree::walk_moving`]'s walk compiled for AVX2, the boxes of each node visited given by `boxes_of`.
    ///
    /// # Safety
    /// The CPU must have the features [`has_avx2`] checks.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn walk_moving_avx2(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        leaf: impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool,
        boxes_of: impl Fn(&WideNode) -> WideNode,
    ) {
        // SAFETY (both): the CPU has AVX2 (this function's contract), so AVX too.
        let lanes = unsafe { avx::RayLanes::new(ray) };
        let enter = {
            #[inline(always)]
            |node: &WideNode, tmax: f32| unsafe { lanes.enter(&boxes_of(node), tmax) }
        };
        self.walk_lanes(stack, collector, stats, enter, leaf, |_| {});
    }

    /// [`Tree::walk_avx`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must have the features [`has_avx2`] checks.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    #[inline]
    unsafe fn walk_avx2(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        leaf: impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool,
        prefetch_leaf: impl Fn(Range<usize>),
    ) {
        // SAFETY: the CPU has the features (this function's contract).
        unsafe { self.walk_avx(stack, ray, collector, stats, leaf, prefetch_leaf) }
    }

    /// [`Tree::walk_lanes`] with its box tests written with AVX intrinsics, inlined into its caller, which is
    /// compiled for AVX2 or for more (the static accels' walks of single rays also for AVX-512VL, whose 32 vector
    /// registers keep the ray's numbers).
    ///
    /// # Safety
    /// The CPU must have the features [`has_avx2`] checks, and the caller be compiled with them.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(super) unsafe fn walk_avx(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        leaf: impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool,
        prefetch_leaf: impl Fn(Range<usize>),
    ) {
        // SAFETY (all three): the CPU has AVX2 (this function's contract), so AVX too.
        let lanes = unsafe { avx::RayLanes::new(ray) };
        // One walk for each place of the slack, so that the node visits of the common one (`tmin ≥ 0`) do not ask.
        // The box tests are closures inlined at once: a closure left to itself is compiled without the features of
        // the function it is inlined into (and its intrinsics become calls).
        if lanes.slack_at_nodes() {
            let enter = {
                #[inline(always)]
                |node: &WideNode, tmax: f32| unsafe { lanes.enter_with::<true>(node, tmax) }
            };
            self.walk_lanes(stack, collector, stats, enter, leaf, prefetch_leaf);
        } else {
            let enter = {
                #[inline(always)]
                |node: &WideNode, tmax: f32| unsafe { lanes.enter_with::<false>(node, tmax) }
            };
            self.walk_lanes(stack, collector, stats, enter, leaf, prefetch_leaf);
        }
    }

    /// The walk itself, for whatever instruction set it is compiled with, with `enter` as the box test of a node's
    /// lanes ([`enter_lanes`]). Stack entries hold a lane's index and count with the distance at which the ray enters
    /// its box, so that a lane taken off the stack is visited without reading its node again (that read waited on the
    /// cache whenever the node had left it). The collector's cull distance changes only at leaves, so it is read again
    /// only after one.
    ///
    /// The walk is one loop over the lane at hand, its index and count, so that the compiler keeps them in registers:
    /// with the leaves handled in an inner loop of their own, the next node's index went through the stack, a store
    /// and a load on the path of every node visit (BENCHMARKS.md, "The node at hand kept in registers").
    ///
    /// Nodes and stack entries are read without bounds checks: the stack's depth is checked once here, and every
    /// node index the walk follows is the root's or an inner lane's, below `nodes.len()` by construction
    /// ([`WideBvh::collapse`] builds the nodes from a binary BVH whose children come after their parents).
    #[inline(always)]
    fn walk_lanes(
        &self,
        stack: &mut [StackEntry],
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        enter: impl Fn(&WideNode, f32) -> (u32, [f32; WIDTH]),
        mut leaf: impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool,
        prefetch_leaf: impl Fn(Range<usize>),
    ) {
        if self.nodes.is_empty() {
            return;
        }
        assert!(stack.len() >= self.stack_size, "a stack of {} entries for {}", stack.len(), self.stack_size);
        let mut tmax = collector.cull_tmax();
        // Boxes tested, added to the statistics at the end. The root's own box is not tested: its lanes are, and a
        // ray that misses the root's box misses them (it is their union) at the cost of one node test.
        let mut boxes = 0u64;
        let nearest_first = collector.wants_nearest_first();
        let mut len = 0usize;
        // The lane at hand: an inner node's (`count` 0) or a leaf's; the root first.
        let (mut index, mut count) = (0u32, 0u32);
        loop {
            if count == 0 {
                let node = index as usize;
                // SAFETY: `node` is the root or an inner lane's index; a walk leaves at most `WIDTH − 1` lanes waiting
                // a level: `stack_size` entries, checked above.
                let next = unsafe {
                    self.visit_node(node, tmax, &enter, stack, &mut len, nearest_first, &prefetch_leaf, &mut boxes)
                };
                if let Some(next) = next {
                    (index, count) = next;
                    continue;
                }
            } else {
                let slots = index as usize..index as usize + count as usize;
                if leaf(slots, collector, stats) {
                    break;
                }
                tmax = collector.cull_tmax();
            }
            let Some(next) = pop(stack, &mut len, tmax) else { break };
            (index, count) = next;
        }
        stats.nodes_visited += boxes;
    }

    /// Visits inner node `node`: tests its lanes' boxes with `enter` within `tmax` (adding them to `boxes`), starts
    /// loading what the entered lanes lead to, pushes all of them but the one visited next ([`visit_order`]) and
    /// returns that one's index and count; `None` when the ray enters none.
    ///
    /// # Safety
    /// `node` is the root or an inner lane's index, and `stack` has room for `WIDTH − 1` entries from `*len` on.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(super) unsafe fn visit_node(
        &self,
        node: usize,
        tmax: f32,
        enter: &impl Fn(&WideNode, f32) -> (u32, [f32; WIDTH]),
        stack: &mut [StackEntry],
        len: &mut usize,
        nearest_first: bool,
        prefetch_leaf: &impl Fn(Range<usize>),
        boxes: &mut u64,
    ) -> Option<(u32, u32)> {
        // SAFETY: `node` is below `nodes.len()` (the contract), and `children` has an entry a node (the type's
        // invariants).
        let (owner, children) = unsafe { (self.nodes.get_unchecked(node), *self.children.get_unchecked(node)) };
        *boxes += u64::from(children);
        let (entered, near) = enter(owner, tmax);
        // Lanes past the children are empty; a ray with a NaN origin "enters" every box, theirs too.
        let entered = entered & ((1u32 << children) - 1);
        self.prefetch_lanes(owner, entered, prefetch_leaf);
        // SAFETY: there is room for the entries pushed (the contract).
        unsafe { visit_order(owner, entered, &near, stack, len, nearest_first) }
    }

    /// Starts loading what the entered lanes of `owner` lead to (their nodes; their leaves' data through
    /// `prefetch_leaf`), so that the memory is on its way while the nearer lanes are visited: random rays spend
    /// much of their time waiting for nodes and triangles that are not in the cache.
    #[inline(always)]
    fn prefetch_lanes(&self, owner: &WideNode, entered: u32, prefetch_leaf: &impl Fn(Range<usize>)) {
        let mut bits = entered;
        while bits != 0 {
            let lane = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let (index, count) = (owner.index[lane] as usize, owner.count[lane] as usize);
            match count {
                0 => prefetch::<{ size_of::<WideNode>() / CACHE_LINE }>(self.nodes.as_ptr().wrapping_add(index)),
                _ => prefetch_leaf(index..index + count),
            }
        }
    }
}

/// The wide node of `lanes` (a node's lanes of a [`collapse`] of `binary`): each lane's box and count its binary
/// node's, its index the wide node of an inner lane, `leaf_index` of a leaf.
fn wide_node(binary: &[Node], lanes: &[Lane], leaf_index: impl Fn(&Node) -> u32) -> WideNode {
    let mut node = WideNode::EMPTY;
    for (lane, &Lane { binary: b, child }) in lanes[..occupied(lanes)].iter().enumerate() {
        let b = &binary[b as usize];
        node.set_lane(lane, b, if b.count > 0 { leaf_index(b) } else { child });
    }
    node
}

/// Stack entries a walk of wide nodes `depth` deep needs: each node visited leaves at most `WIDTH − 1` lanes waiting.
const fn stack_size_of(depth: usize) -> usize {
    depth * (WIDTH - 1) + 1
}

/// How many of a collapsed node's `lanes` are occupied (they come first).
pub(super) fn occupied(lanes: &[Lane]) -> usize {
    lanes.iter().take_while(|lane| lane.binary != EMPTY_LANE).count()
}

/// Checks what the walks (which read nodes without bounds checks) and refits rely on: every inner lane leads to a
/// later node, and a `u32` holds every node's index. A failure is a bug of [`collapse`].
fn assert_well_formed(nodes: &[WideNode], children: &[u8]) {
    let inner_lanes_in_range = nodes.iter().zip(children).enumerate().all(|(n, (node, &children))| {
        (0..usize::from(children))
            .all(|l| node.count[l] > 0 || (n + 1..nodes.len()).contains(&(node.index[l] as usize)))
    });
    assert!(
        inner_lanes_in_range && children.len() == nodes.len() && nodes.len() <= u32::MAX as usize,
        "a malformed wide BVH"
    );
}

/// Wide nodes over leaves of other things than triangles (an instance accel's instances): a binary BVH collapsed,
/// each leaf lane holding its binary leaf's slots as they are. Walked as [`Tree`].
#[derive(Debug, Clone, Default)]
pub(super) struct WideTree {
    /// Nodes, the root first; empty when the binary BVH was.
    nodes: Vec<WideNode>,
    /// Children of each node: its first lanes, the rest are empty.
    children: Vec<u8>,
    /// Longest root-to-leaf path, in wide nodes.
    depth: usize,
}

impl WideTree {
    /// Collapses the depth-first binary BVH `binary` ([`collapse`]); lanes in the collapse's order.
    pub fn collapse(binary: &[Node]) -> WideTree {
        Self::collapse_with_lanes(binary).0
    }

    /// [`WideTree::collapse`], with the collapse's lanes: [`WIDTH`] a node, each naming the binary node in it.
    pub fn collapse_with_lanes(binary: &[Node]) -> (WideTree, Vec<Lane>) {
        if binary.is_empty() {
            return (WideTree::default(), Vec::new());
        }
        let collapsed = collapse(binary, WIDTH);
        let lanes = collapsed.lanes.chunks(WIDTH);
        let tree = WideTree {
            nodes: lanes.clone().map(|lanes| wide_node(binary, lanes, |leaf| leaf.index)).collect(),
            children: lanes.map(|lanes| occupied(lanes) as u8).collect(),
            depth: collapsed.depth,
        };
        assert_well_formed(&tree.nodes, &tree.children);
        (tree, collapsed.lanes)
    }

    /// The most nodes a collapse of a binary BVH of `leaves` leaves makes ([`super::collapse::most_nodes`]).
    pub const fn most_nodes(leaves: usize) -> usize {
        super::collapse::most_nodes(leaves, WIDTH)
    }

    /// Stack entries a walk needs ([`stack_size_of`]).
    pub fn stack_size(&self) -> usize {
        stack_size_of(self.depth)
    }

    /// Stack entries enough for a walk of a collapse of binary nodes `depth` deep (a collapse is no deeper than
    /// `depth + 1` wide nodes), and for a walk of the binary nodes themselves (`depth + 1`).
    pub const fn stack_size_within(depth: usize) -> usize {
        stack_size_of(depth + 1)
    }

    /// Bytes it occupies.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        (footprint.of(&self.nodes) * size_of::<WideNode>() + footprint.of(&self.children)) as u64
    }

    /// Its nodes as a walk reads them.
    #[inline(always)]
    pub fn tree(&self) -> Tree<'_> {
        Tree { nodes: &self.nodes, children: &self.children, stack_size: self.stack_size() }
    }

    /// Its nodes, to set their lanes' boxes (their indices and counts are the collapse's, which walks trust).
    pub fn nodes_mut(&mut self) -> &mut [WideNode] {
        &mut self.nodes
    }
}

/// What a wide BVH is besides its nodes' boxes and its leaves' triangles.
struct Skeleton {
    /// Children of each node ([`WideBvh::children`]).
    children: Vec<u8>,
    /// The root's box.
    root: (Vec3A, Vec3A),
    /// Longest root-to-leaf path, in wide nodes.
    depth: usize,
}

/// Where the triangles of the leaves of `binary` go in the blocks ([`Placement`]).
fn placement_of_leaves(binary: &[Node]) -> Placement {
    let mut leaves: Vec<Range<usize>> =
        binary.iter().filter(|b| b.count > 0).map(|b| b.index as usize..(b.index + b.count) as usize).collect();
    leaves.sort_unstable_by_key(|leaf| leaf.start);
    Placement::of_leaves(leaves)
}

/// Bytes of a cache line on x86-64 CPUs.
pub(super) const CACHE_LINE: usize = 64;

/// Asks the CPU to start loading `LINES` cache lines from the one `start` points into, which are about to be read.
/// Only a hint: what the program reads does not change, and the address need not be valid.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn prefetch<const LINES: usize>(start: *const impl Sized) {
    use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
    for line in 0..LINES {
        // SAFETY: a prefetch reads nothing the program sees and never faults, whatever the address.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(start.cast::<i8>().wrapping_add(line * CACHE_LINE)) };
    }
}

/// Elsewhere the hint is left out: stable Rust has no prefetch instruction for other architectures.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub(super) fn prefetch<const LINES: usize>(_start: *const impl Sized) {}

/// `1 − SLACK` and `1 + SLACK`: the factors a near and a far distance are shrunk and grown by where [`SlabRay`] folds
/// the slack into a ray's reciprocals.
const SHRINK: f32 = 1.0 - SLACK;
const GROW: f32 = 1.0 + SLACK;

/// A ray as the wide box test takes it, prepared once a walk.
///
/// A ray with `tmin ≥ 0` has the slack folded into its reciprocals: near planes' distances are taken with
/// `(1/d)·(1 − SLACK)`, far planes' with `(1/d)·(1 + SLACK)`, the interval starts from `tmin·(1 − SLACK)` and
/// `tmax·(1 + SLACK)`, and a node visit widens nothing (six operations fewer on the walk's dependent chain). That stays
/// conservative: a near distance decides the entry only when it is ≥ `tmin` ≥ 0, where shrinking lowers it (a
/// negative one stays below `tmin`'s); a negative far distance puts the box behind the origin, out of reach either
/// way; and the subtraction, the reciprocal, the folded factor and the product round by at most 4 units of 2⁻²⁴
/// (relative) in all, against the slack's 16–17: a margin of about 12 at either end, as the per-node form leaves,
/// which must cover the triangle test's `t` so that ties reach the tie rule. Other rays (`tmin` < 0 or NaN) are
/// widened at every node as [`crate::intersect::aabb::intersect`] does.
#[derive(Debug, Clone, Copy)]
struct SlabRay {
    /// Origin, by axis.
    origin: [f32; 3],
    /// Per axis, the reciprocals the near and the far planes' distances are taken with.
    inv_direction: [(f32, f32); 3],
    /// Per axis, whether the direction is negative: whether the box's maxima are the near planes.
    negative: [bool; 3],
    /// Where a node's interval starts: `tmin`, shrunk when the slack is in the reciprocals.
    near_start: f32,
    /// Whether the slack is applied at every node instead of in the reciprocals.
    slack_at_nodes: bool,
}

impl SlabRay {
    /// `ray`'s numbers for the box test.
    #[inline(always)]
    fn new(ray: &PreparedRay) -> SlabRay {
        // `tmin` NaN widens at every node too.
        let slack_in_reciprocals = ray.tmin >= 0.0;
        let (shrink, grow) = if slack_in_reciprocals { (SHRINK, GROW) } else { (1.0, 1.0) };
        let inv = ray.inv_direction;
        SlabRay {
            origin: ray.origin.into(),
            inv_direction: [
                (inv.x * shrink, inv.x * grow),
                (inv.y * shrink, inv.y * grow),
                (inv.z * shrink, inv.z * grow),
            ],
            negative: ray.negative,
            near_start: ray.tmin * shrink,
            slack_at_nodes: !slack_in_reciprocals,
        }
    }
}

/// Where a node's interval ends before its planes cut it: `tmax`, grown when the slack is in the reciprocals.
#[inline(always)]
fn far_start(slack_at_nodes: bool, tmax: f32) -> f32 {
    if slack_at_nodes { tmax } else { tmax * GROW }
}

/// Which lanes of `node` the ray enters within `[tmin, tmax]` (bit per lane), and at what distance.
#[inline(always)]
fn enter_lanes(node: &WideNode, ray: &SlabRay, tmax: f32) -> (u32, [f32; WIDTH]) {
    let mut near = [ray.near_start; WIDTH];
    let mut far = [far_start(ray.slack_at_nodes, tmax); WIDTH];
    for axis in 0..3 {
        let (lo, hi) =
            if ray.negative[axis] { (&node.hi[axis], &node.lo[axis]) } else { (&node.lo[axis], &node.hi[axis]) };
        let (origin, (inv_near, inv_far)) = (ray.origin[axis], ray.inv_direction[axis]);
        for lane in 0..WIDTH {
            // `a > b ? a : b` keeps `b` when `a` is NaN, as `f32::max` does in the scalar test.
            let t0 = (lo[lane] - origin) * inv_near;
            near[lane] = if t0 > near[lane] { t0 } else { near[lane] };
            let t1 = (hi[lane] - origin) * inv_far;
            far[lane] = if t1 < far[lane] { t1 } else { far[lane] };
        }
    }
    if ray.slack_at_nodes {
        for lane in 0..WIDTH {
            (near[lane], far[lane]) = (near[lane] - near[lane].abs() * SLACK, far[lane] + far[lane].abs() * SLACK);
        }
    }
    let mut entered = 0u32;
    for lane in 0..WIDTH {
        entered |= u32::from(near[lane] <= far[lane]) << lane;
    }
    (entered, near)
}

/// [`enter_lanes`] in AVX intrinsics: the same operations in the same order on eight lanes at once (`vmaxps` and
/// `vminps` keep their second operand when the first is NaN, as the portable test's `a > b ? a : b` does), the
/// entered lanes taken from the comparison's sign bits in one instruction.
#[cfg(target_arch = "x86_64")]
pub(super) mod avx {
    use std::arch::x86_64::*;
    use std::mem::offset_of;

    use super::{SLACK, SlabRay, WIDTH, WideNode, far_start};
    use crate::intersect::PreparedRay;

    /// A ray's numbers ([`SlabRay`]'s) spread over the lanes once a walk.
    pub(in crate::backend::cpu) struct RayLanes {
        /// Origin, by axis.
        origin: [__m256; 3],
        /// Per axis, the reciprocals the near and the far planes' distances are taken with.
        inv_direction: [(__m256, __m256); 3],
        /// Per axis, where in a node the row of the planes the ray meets first lies, and the row of those it meets
        /// last (byte offsets: the minima's row when the direction is positive, the maxima's when negative), chosen
        /// once a walk instead of at every node.
        rows: [(usize, usize); 3],
        /// Where a node's interval starts.
        near_start: __m256,
        /// Whether the slack is applied at every node.
        slack_at_nodes: bool,
    }

    impl RayLanes {
        /// # Safety
        /// The CPU must have AVX.
        #[inline(always)]
        pub(in crate::backend::cpu) unsafe fn new(ray: &PreparedRay) -> RayLanes {
            let slab = SlabRay::new(ray);
            // SAFETY: the CPU has AVX (the caller's contract).
            unsafe {
                RayLanes {
                    origin: std::array::from_fn(|axis| _mm256_set1_ps(slab.origin[axis])),
                    inv_direction: std::array::from_fn(|axis| {
                        let (inv_near, inv_far) = slab.inv_direction[axis];
                        (_mm256_set1_ps(inv_near), _mm256_set1_ps(inv_far))
                    }),
                    rows: std::array::from_fn(|axis| {
                        let (lo, hi) =
                            (offset_of!(WideNode, lo) + 4 * WIDTH * axis, offset_of!(WideNode, hi) + 4 * WIDTH * axis);
                        if slab.negative[axis] { (hi, lo) } else { (lo, hi) }
                    }),
                    near_start: _mm256_set1_ps(slab.near_start),
                    slack_at_nodes: slab.slack_at_nodes,
                }
            }
        }

        /// Whether the slack is applied at every node (the ray's `tmin` is negative or NaN).
        #[inline(always)]
        pub(in crate::backend::cpu) fn slack_at_nodes(&self) -> bool {
            self.slack_at_nodes
        }

        /// Which lanes of `node` the ray enters within `[tmin, tmax]` (bit per lane), and at what distance.
        ///
        /// # Safety
        /// The CPU must have AVX.
        #[inline(always)]
        pub(in crate::backend::cpu) unsafe fn enter(&self, node: &WideNode, tmax: f32) -> (u32, [f32; WIDTH]) {
            // SAFETY: the CPU has AVX (the caller's contract).
            unsafe {
                match self.slack_at_nodes {
                    true => self.enter_with::<true>(node, tmax),
                    false => self.enter_with::<false>(node, tmax),
                }
            }
        }

        /// [`RayLanes::enter`] for a walk that knows where its slack is (`SLACK_AT_NODES`, which must be
        /// [`RayLanes::slack_at_nodes`]), so that its node visits do not ask.
        ///
        /// # Safety
        /// The CPU must have AVX.
        #[inline(always)]
        pub(in crate::backend::cpu) unsafe fn enter_with<const SLACK_AT_NODES: bool>(
            &self,
            node: &WideNode,
            tmax: f32,
        ) -> (u32, [f32; WIDTH]) {
            debug_assert_eq!(SLACK_AT_NODES, self.slack_at_nodes);
            // SAFETY: the CPU has AVX (the caller's contract); the loads read whole rows of the node (32-byte aligned:
            // the node is aligned to 64 and its rows are 32 bytes long).
            unsafe {
                let (mut near, mut far) = (self.near_start, _mm256_set1_ps(far_start(SLACK_AT_NODES, tmax)));
                let row = |offset: usize| (node as *const WideNode).cast::<u8>().add(offset).cast::<f32>();
                for axis in 0..3 {
                    let (first, last) = self.rows[axis];
                    let (origin, (inv_near, inv_far)) = (self.origin[axis], self.inv_direction[axis]);
                    let t0 = _mm256_mul_ps(_mm256_sub_ps(_mm256_load_ps(row(first)), origin), inv_near);
                    near = _mm256_max_ps(t0, near);
                    let t1 = _mm256_mul_ps(_mm256_sub_ps(_mm256_load_ps(row(last)), origin), inv_far);
                    far = _mm256_min_ps(t1, far);
                }
                if SLACK_AT_NODES {
                    let (slack, magnitude) = (_mm256_set1_ps(SLACK), _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX)));
                    near = _mm256_sub_ps(near, _mm256_mul_ps(_mm256_and_ps(near, magnitude), slack));
                    far = _mm256_add_ps(far, _mm256_mul_ps(_mm256_and_ps(far, magnitude), slack));
                }
                let entered = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32;
                let mut distances = [0.0; WIDTH];
                _mm256_storeu_ps(distances.as_mut_ptr(), near);
                (entered, distances)
            }
        }
    }
}

/// Takes entries off `stack` (of `len` entries) until one the ray may still enter within `tmax`, and returns its
/// lane's index and count; `None` when there is none.
#[inline(always)]
pub(super) fn pop(stack: &[StackEntry], len: &mut usize, tmax: f32) -> Option<(u32, u32)> {
    while *len > 0 {
        *len -= 1;
        // SAFETY: below the entries pushed.
        let StackEntry { index, count, near } = unsafe { *stack.get_unchecked(*len) };
        if near <= tmax {
            return Some((index, count));
        }
    }
    None
}

/// Pushes the entered lanes of `owner` but one on the stack and returns that one's index and count, the lane visited
/// next: `by_distance`, the nearest ([`nearest_lane`]), with the second nearest waiting on top of the others;
/// otherwise the first in lane order. The others wait in lane order (pushed so that the lowest is on top): for a
/// closest-hit walk the two nearest lanes first are most of what an order by distance saves, and finding them takes no
/// branch, where a sort of all took as much time as it saved (BENCHMARKS.md, "The two nearest lanes without a sort").
///
/// # Safety
/// `stack` must have room for `WIDTH − 1` entries from `*len` on.
#[inline(always)]
unsafe fn visit_order(
    owner: &WideNode,
    entered: u32,
    near: &[f32; WIDTH],
    stack: &mut [StackEntry],
    len: &mut usize,
    by_distance: bool,
) -> Option<(u32, u32)> {
    let index_and_count = |lane: u32| (owner.index[lane as usize], owner.count[lane as usize]);
    let first = entered.trailing_zeros();
    let rest = entered & entered.wrapping_sub(1);
    if entered == 0 {
        return None;
    }
    // `next` is visited next; `then` (a single lane or none) waits on top of the others, which wait in lane order.
    let (next, then) = if !by_distance || rest == 0 {
        (first, 0)
    } else if rest & rest.wrapping_sub(1) == 0 {
        // Two lanes: the nearer, the first when they are equally near (as `nearest_lane` chooses).
        let second = rest.trailing_zeros();
        (if near[second as usize] < near[first as usize] { second } else { first }, 0)
    } else {
        let next = nearest_lane(entered, near);
        (next, 1 << nearest_lane(entered & !(1 << next), near))
    };
    let mut push = |lane: u32| {
        let (index, count) = index_and_count(lane);
        // SAFETY: at most `WIDTH − 1` entries are pushed a call, and there is room for them (the contract).
        unsafe { *stack.get_unchecked_mut(*len) = StackEntry { index, count, near: near[lane as usize] } };
        *len += 1;
    };
    let mut waiting = entered & !(1 << next) & !then;
    while waiting != 0 {
        let lane = 31 - waiting.leading_zeros();
        waiting &= !(1 << lane);
        push(lane);
    }
    if then != 0 {
        push(then.trailing_zeros());
    }
    Some(index_and_count(next))
}

/// The nearest of the `entered` lanes (at least one) by their distances `near`, the lowest of equally near ones, found
/// without a branch: a tournament of neighbouring pairs, round after round, in which the higher lane wins only when it
/// is nearer. Lanes not entered play at +∞, nearer than no entered lane (an entered lane's distance is below its far
/// one, finite for a finite box); should one win all the same, the first entered lane is taken.
#[inline(always)]
fn nearest_lane(entered: u32, near: &[f32; WIDTH]) -> u32 {
    let mut round: [(u32, f32); WIDTH] =
        std::array::from_fn(|lane| (lane as u32, if entered >> lane & 1 != 0 { near[lane] } else { f32::INFINITY }));
    let mut players = WIDTH;
    while players > 1 {
        players /= 2;
        for pair in 0..players {
            let ((low, low_near), (high, high_near)) = (round[2 * pair], round[2 * pair + 1]);
            let take = high_near < low_near;
            round[pair] = (select_unpredictable(take, high, low), select_unpredictable(take, high_near, low_near));
        }
    }
    let winner = round[0].0;
    select_unpredictable(entered >> winner & 1 != 0, winner, entered.trailing_zeros())
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use proptest::prelude::*;

    use super::*;
    use crate::format::{Ray, RayFlags};

    /// Coordinates of every kind a box test meets: ordinary, zeros of both signs, infinities, NaN, tiny.
    fn coordinate() -> impl Strategy<Value = f32> {
        prop_oneof![
            4 => -10.0f32..10.0,
            1 => Just(0.0f32),
            1 => Just(-0.0f32),
            1 => Just(f32::INFINITY),
            1 => Just(f32::NEG_INFINITY),
            1 => Just(f32::NAN),
            1 => Just(1e-39f32),
            1 => proptest::num::f32::ANY,
        ]
    }

    /// A node whose lanes' minima and then maxima (by axis, then lane) are `bounds`.
    fn node_with_bounds(bounds: &[f32]) -> WideNode {
        let mut node = WideNode::EMPTY;
        for (value, bound) in bounds.iter().zip(node.lo.iter_mut().chain(&mut node.hi).flatten()) {
            *bound = *value;
        }
        node
    }

    proptest! {
        #[test]
        fn the_avx_box_test_is_the_portable_one_bit_for_bit(
            bounds in proptest::collection::vec(coordinate(), 2 * 3 * WIDTH),
            origin in proptest::array::uniform3(coordinate()),
            direction in proptest::array::uniform3(coordinate()),
            (tmin, tmax) in (coordinate(), coordinate()),
        ) {
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx") {
                let node = node_with_bounds(&bounds);
                let ray = Ray { origin: origin.into(), direction: direction.into(), tmin, tmax, ..Ray::default() };
                let ray = PreparedRay::new(&ray, RayFlags::empty());
                let (entered, near) = enter_lanes(&node, &SlabRay::new(&ray), tmax);
                // SAFETY: the CPU has AVX, as just checked.
                let (avx_entered, avx_near) = unsafe { avx::RayLanes::new(&ray).enter(&node, tmax) };
                prop_assert_eq!(entered, avx_entered);
                prop_assert_eq!(near.map(f32::to_bits), avx_near.map(f32::to_bits));
            }
        }
    }

    /// Finite ray coordinates: ordinary, zeros of both signs, tiny.
    fn finite_coordinate() -> impl Strategy<Value = f32> {
        prop_oneof![6 => -10.0f32..10.0, 1 => Just(0.0f32), 1 => Just(-0.0f32), 1 => Just(1e-39f32)]
    }

    /// Direction components whose reciprocals `f32` holds (a subnormal one's overflows, and the ray then takes it as
    /// zero), zeros of both signs included.
    fn direction_component() -> impl Strategy<Value = f32> {
        prop_oneof![
            6 => (-10.0f32..10.0).prop_map(|d| if d.abs() < 1e-30 { 0.0 } else { d }),
            1 => Just(0.0f32),
            1 => Just(-0.0f32),
            1 => prop_oneof![Just(1e-20f32), Just(-1e-20f32)],
        ]
    }

    /// The relative margin by which the box test must widen a box's exact interval at either end, beyond its own
    /// rounding: what covers the rounding of the triangle test's `t`, so that a hit at a box's entry distance is
    /// still reached with `tmax` at that distance (ties).
    const MARGIN: f64 = 8.0 / (1u32 << 24) as f64;

    /// `x` moved by [`MARGIN`] of itself towards −∞ (`direction` −1) or +∞ (1); infinities stay.
    fn widened(x: f64, direction: f64) -> f64 {
        if x.is_finite() { x + direction * x.abs() * MARGIN } else { x }
    }

    /// What the checks allow for the rounding of subnormal distances, which is absolute: the smallest normal `f32`.
    const SUBNORMAL_ROUNDING: f64 = f32::MIN_POSITIVE as f64;

    /// The interval the ray spends in each lane's box within `[tmin, tmax]`, in `f64` (the slab test's own rounding,
    /// 2⁻⁵³ relative, is far below [`MARGIN`]) with the ray's conventions: a zero direction component's reciprocal is
    /// +∞, a NaN distance leaves the interval as it was.
    fn exact_intervals(node: &WideNode, ray: &PreparedRay, tmax: f32) -> [(f64, f64); WIDTH] {
        std::array::from_fn(|lane| {
            let (mut near, mut far) = (ray.tmin as f64, tmax as f64);
            for axis in 0..3 {
                let d = ray.direction[axis] as f64;
                let inv = if d == 0.0 { f64::INFINITY } else { 1.0 / d };
                let (lo, hi) = (node.lo[axis][lane] as f64, node.hi[axis][lane] as f64);
                let (first, last) = if ray.negative[axis] { (hi, lo) } else { (lo, hi) };
                let o = ray.origin[axis] as f64;
                let (t0, t1) = ((first - o) * inv, (last - o) * inv);
                near = if t0 > near { t0 } else { near };
                far = if t1 < far { t1 } else { far };
            }
            (near, far)
        })
    }

    /// Checks that the box test enters every lane whose exact interval, widened by [`MARGIN`], is not empty and starts
    /// within `f32`'s range (one that starts beyond it holds no hit: neither one past `f32::MAX` nor one at +∞, where a
    /// ray with a zero direction component meets a slab off its origin), at a distance no farther than the widened
    /// interval's start.
    fn check_conservative(node: &WideNode, ray: &PreparedRay, tmax: f32) -> Result<(), TestCaseError> {
        let (entered, near) = enter_lanes(node, &SlabRay::new(ray), tmax);
        for (lane, (exact_near, exact_far)) in exact_intervals(node, ray, tmax).into_iter().enumerate() {
            let (near_bound, far_bound) = (widened(exact_near, -1.0), widened(exact_far, 1.0));
            if exact_near <= f32::MAX as f64 && near_bound + SUBNORMAL_ROUNDING <= far_bound - SUBNORMAL_ROUNDING {
                prop_assert!(entered & 1 << lane != 0, "lane {lane} ({exact_near} ..= {exact_far}) not entered");
                prop_assert!(
                    near[lane] as f64 <= near_bound + SUBNORMAL_ROUNDING,
                    "lane {lane} entered at {} beyond {near_bound} (exact {exact_near})",
                    near[lane]
                );
            }
        }
        Ok(())
    }

    proptest! {
        #[test]
        fn the_box_test_enters_every_box_the_ray_meets_with_a_margin(
            bounds in proptest::collection::vec(coordinate(), 2 * 3 * WIDTH),
            origin in proptest::array::uniform3(finite_coordinate()),
            direction in proptest::array::uniform3(direction_component()),
            tmin in prop_oneof![2 => Just(0.0f32), 1 => Just(-0.0f32), 2 => 0.0f32..10.0, 2 => -10.0f32..0.0],
            tmax in prop_oneof![3 => -1.0f32..20.0, 1 => Just(f32::INFINITY)],
        ) {
            let node = node_with_bounds(&bounds);
            let ray = Ray { origin: origin.into(), direction: direction.into(), tmin, tmax, ..Ray::default() };
            let ray = PreparedRay::new(&ray, RayFlags::empty());
            check_conservative(&node, &ray, tmax)?;
            // The ties: `tmax` at each lane's exact entry distance, as after a hit there, must still enter it.
            for (exact_near, _) in exact_intervals(&node, &ray, tmax) {
                if exact_near.is_finite() {
                    check_conservative(&node, &ray, exact_near as f32)?;
                }
            }
        }
    }

    proptest! {
        /// Boxes the ray grazes: it leaves them through one axis's last plane where it enters through another's first
        /// (up to the planes' rounding), or passes them by less than the two ends' margins (`gap`, in units of 2⁻²⁴
        /// relative), so that only the test's widening keeps it from culling them.
        #[test]
        fn the_box_test_enters_boxes_the_ray_grazes(
            origin in proptest::array::uniform3(-10.0f32..10.0),
            direction in proptest::array::uniform3(prop_oneof![-10.0f32..-0.01, 0.01f32..10.0]),
            t in 0.01f32..10.0,
            gap in 0.0f32..15.0,
            (entry_axis, exit_axis) in (0..3usize, 1..3usize).prop_map(|(a, step)| (a, (a + step) % 3)),
            tmin in prop_oneof![Just(0.0f32), Just(-1.0f32)],
        ) {
            let ray = Ray { origin: origin.into(), direction: direction.into(), tmin, ..Ray::default() };
            let ray = PreparedRay::new(&ray, RayFlags::empty());
            let mut node = WideNode::EMPTY;
            for axis in 0..3 {
                let (mut first, mut last) = (-1e3 * direction[axis].signum(), 1e3 * direction[axis].signum());
                if axis == entry_axis {
                    first = origin[axis] + t * direction[axis];
                }
                if axis == exit_axis {
                    last = origin[axis] + t * (1.0 - gap * f32::EPSILON / 2.0) * direction[axis];
                }
                (node.lo[axis][0], node.hi[axis][0]) = if ray.negative[axis] { (last, first) } else { (first, last) };
            }
            check_conservative(&node, &ray, f32::INFINITY)?;
            check_conservative(&node, &ray, t)?;
        }
    }

    /// A binary BVH: a root over a leaf of slots 0..2 and an inner node over two leaves (slots 2..3, 3..5).
    fn three_leaves() -> [Node; 5] {
        let node = |min: f32, max: f32, index: u32, count: u32| Node {
            min: Vec3::splat(min),
            index,
            max: Vec3::splat(max),
            count,
        };
        [node(0.0, 9.0, 1, 0), node(0.0, 1.0, 0, 2), node(2.0, 9.0, 3, 0), node(2.0, 3.0, 2, 1), node(4.0, 9.0, 3, 2)]
    }

    #[test]
    fn lanes_hold_their_childrens_boxes_and_leaves_their_slots() {
        let binary = three_leaves();
        let refs: Vec<TriangleRef> = (0..5).map(|prim_id| TriangleRef { geom_id: 0, prim_id }).collect();
        let wide = WideBvh::collapse(&binary, &[[Vec3::ZERO; 3]; 5], &refs, None);
        assert_eq!((wide.nodes.len(), wide.children.as_slice(), wide.depth), (1, &[3u8][..], 1));
        let root = &wide.nodes[0];
        // The leaf first, then the inner node's two children in its place and after; the last leaf starts the second
        // block (from slot 3 on it would span two), at slot 4 of the blocks, which hold the leaves' ids there.
        let lanes: Vec<(f32, f32, u32, u32)> =
            (0..3).map(|l| (root.lo[0][l], root.hi[2][l], root.index[l], root.count[l])).collect();
        assert_eq!(lanes, [(0.0, 1.0, 0, 2), (2.0, 3.0, 2, 1), (4.0, 9.0, 4, 2)]);
        assert_eq!(wide.ids.iter().map(|id| id.prim_id).collect::<Vec<_>>(), [0, 1, 2, 0, 3, 4]);
        assert!((3..WIDTH).all(|l| root.lo[1][l] == f32::INFINITY && root.hi[1][l] == f32::NEG_INFINITY));
        assert_eq!(wide.root, (Vec3A::ZERO, Vec3A::splat(9.0)));
    }

    #[test]
    fn a_tree_of_other_leaves_keeps_each_binary_leafs_slots_and_box() {
        let binary = three_leaves();
        let tree = WideTree::collapse(&binary);
        assert_eq!((tree.nodes.len(), tree.children.as_slice(), tree.depth), (1, &[3u8][..], 1));
        let root = &tree.nodes[0];
        let lanes: Vec<(f32, f32, u32, u32)> =
            (0..3).map(|l| (root.lo[0][l], root.hi[2][l], root.index[l], root.count[l])).collect();
        assert_eq!(lanes, [(0.0, 1.0, 0, 2), (2.0, 3.0, 2, 1), (4.0, 9.0, 3, 2)]);
        assert!(WideTree::collapse(&[]).nodes.is_empty());
        assert!(tree.stack_size() <= WideTree::stack_size_within(2), "the binary nodes are 2 deep below the root");
    }

    #[test]
    fn a_refit_keeps_the_lanes_and_gives_each_the_bounds_of_its_new_corners() {
        let (bvh, _) = crate::backend::cpu::packet::tests::lattice(true);
        let old = &bvh.wide;
        // Twisted about z and lifted by x: every box moves; the masks change too.
        let corners: Vec<[Vec3; 3]> = bvh
            .corners
            .iter()
            .map(|c| c.map(|p| Vec3::new(p.x - 0.4 * p.y, p.y + 0.3 * p.x, p.z + 0.5 * p.x * p.x)))
            .collect();
        let masks: Vec<u32> = bvh.masks.as_ref().expect("a masked lattice").iter().map(|m| m ^ 1).collect();
        let mut binary = bvh.nodes.clone();
        super::super::bvh::refit(&mut binary, None, |slots, _| corner_bounds(&corners[slots]));
        let wide = old.refit(&binary, &corners, Some(&masks));

        assert_eq!((wide.children.as_slice(), wide.depth), (old.children.as_slice(), old.depth));
        assert_eq!(&wide.ids[..], &old.ids[..]);
        assert_eq!(wide.root, (binary[0].min.into(), binary[0].max.into()));
        let slot_of: std::collections::HashMap<TriangleRef, usize> =
            bvh.refs.iter().enumerate().map(|(slot, &id)| (id, slot)).collect();
        // Each lane's box is the bounds of the new corners of the triangles under it, found by walking down to them.
        fn under(wide: &WideBvh, node: usize, lane: usize, slots: &mut Vec<usize>) {
            let (index, count) = (wide.nodes[node].index[lane] as usize, wide.nodes[node].count[lane] as usize);
            match count {
                0 => (0..usize::from(wide.children[index])).for_each(|l| under(wide, index, l, slots)),
                _ => slots.extend(index..index + count),
            }
        }
        let (mut lanes, mut moved) = (0, 0);
        for (n, (node, old_node)) in wide.nodes.iter().zip(old.nodes.iter()).enumerate() {
            assert_eq!((node.index, node.count), (old_node.index, old_node.count), "node {n}");
            for lane in 0..usize::from(wide.children[n]) {
                let mut slots = Vec::new();
                under(&wide, n, lane, &mut slots);
                let accel_slots: Vec<usize> = slots.iter().map(|&s| slot_of[&wide.ids[s]]).collect();
                let triangles: Vec<[Vec3; 3]> = accel_slots.iter().map(|&slot| corners[slot]).collect();
                assert_eq!(node.lane_box(lane), corner_bounds(&triangles), "node {n} lane {lane}");
                moved += usize::from(node.lane_box(lane) != old_node.lane_box(lane));
                for (&s, &slot) in slots.iter().zip(&accel_slots) {
                    assert_eq!(wide.blocks.corners(s), corners[slot], "block slot {s}");
                    assert_eq!(wide.masks.as_ref().unwrap()[s], masks[slot], "block slot {s}");
                }
                lanes += 1;
            }
        }
        assert!(lanes > 2 * wide.nodes.len(), "{lanes} lanes in {} nodes", wide.nodes.len());
        assert!(moved * 10 > lanes * 9, "{moved} of {lanes} lanes moved");
    }

    #[test]
    fn lanes_are_ordered_by_their_chance_of_stopping_a_ray_for_its_cost() {
        // A root over two unit-cube leaves along x: the first holds a sliver, the second a triangle across its box.
        let node = |min: Vec3, max: Vec3, index: u32, count: u32| Node { min, index, max, count };
        let binary = [
            node(Vec3::ZERO, Vec3::new(2.0, 1.0, 1.0), 1, 0),
            node(Vec3::ZERO, Vec3::ONE, 0, 1),
            node(Vec3::X, Vec3::new(2.0, 1.0, 1.0), 1, 1),
        ];
        let corners = [
            [Vec3::ZERO, Vec3::new(1e-3, 0.0, 0.0), Vec3::Y],
            [Vec3::X, Vec3::new(2.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 1.0)],
        ];
        let refs: Vec<TriangleRef> = (0..2).map(|prim_id| TriangleRef { geom_id: 0, prim_id }).collect();
        let root = WideBvh::collapse(&binary, &corners, &refs, None).nodes[0];
        assert_eq!((root.lo[0][0], root.lo[0][1]), (1.0, 0.0));
    }

    /// The order `visit_order` gives entered lanes, written plainly: the lane visited next, then the others as they
    /// will pop. By distance: the nearest, the second nearest, the rest in lane order (equally near ones by lane);
    /// otherwise all in lane order.
    fn expected_order(entered: u32, near: &[f32; WIDTH], by_distance: bool) -> Vec<u32> {
        let mut lanes: Vec<u32> = (0..WIDTH as u32).filter(|lane| entered >> lane & 1 != 0).collect();
        if by_distance {
            for place in 0..lanes.len().min(2) {
                let nearest =
                    (place..lanes.len()).min_by(|&a, &b| near[lanes[a] as usize].total_cmp(&near[lanes[b] as usize]));
                let lane = lanes.remove(nearest.expect("a lane is left"));
                lanes.insert(place, lane);
            }
        }
        lanes
    }

    proptest! {
        #[test]
        fn entered_lanes_are_visited_the_two_nearest_first_then_in_lane_order(
            entered in 1u32..1 << WIDTH,
            // Few distinct distances, so that ties are common.
            near in proptest::array::uniform8(prop_oneof![(0u8..4).prop_map(f32::from), -1e30f32..1e30]),
            by_distance: bool,
        ) {
            let mut node = WideNode::EMPTY;
            node.index = std::array::from_fn(|lane| 100 + lane as u32);
            node.count = std::array::from_fn(|lane| lane as u32);
            let mut stack = [StackEntry::default(); WIDTH];
            let mut len = 0;
            // SAFETY: the stack has room for `WIDTH` entries.
            let next = unsafe { visit_order(&node, entered, &near, &mut stack, &mut len, by_distance) };
            let (index, count) = next.expect("a lane was entered");
            prop_assert_eq!(index, 100 + count);
            let mut order = vec![count];
            for entry in stack[..len].iter().rev() {
                prop_assert_eq!(entry.index, 100 + entry.count);
                prop_assert_eq!(entry.near.to_bits(), near[entry.count as usize].to_bits());
                order.push(entry.count);
            }
            prop_assert_eq!(order, expected_order(entered, &near, by_distance));
        }
    }
}
