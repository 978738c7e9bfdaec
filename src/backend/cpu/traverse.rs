//! Stack-based traversal of the CPU BVHs: nearer child first, boxes tested against the collector's current cull
//! distance, popped entries re-checked against it. Leaves of a geometry accel offer triangles to the collector;
//! leaves of an instance accel carry the ray into each visible instance's space and traverse its child there,
//! on the rest of the same stack.

use std::ops::Range;

use glam::{Affine3A, Vec3, Vec3A};

use super::CpuAccel;
use super::blocks::{BLOCK, BlockRay, MetLanes};
use super::bvh::Node;
use super::instances::{InstanceBvh, TransformNode, cpu_child};
#[cfg(target_arch = "x86_64")]
use super::packet::{PacketEntry, trace_packets};
use super::triangles::TriangleBvh;
#[cfg(target_arch = "x86_64")]
use super::turns::TURNS;
use super::wide::{CACHE_LINE, prefetch};
#[cfg(target_arch = "x86_64")]
use crate::cpu_features::{has_avx2, has_avx512vl};
use crate::format::Ray;
use crate::geometry::TriangleRef;
use crate::geometry::motion::{Bounds, lerp};
use crate::intersect::{PreparedRay, aabb, triangle};
use crate::query::{Collector, InstanceScope, TraceStats, TriangleCandidate, accept_hit, consider_triangle};

/// What waits on a traversal stack, with the distance at which the ray enters its box: a binary node (its index;
/// `count` 0), or a wide node's lane as [`super::wide::WideNode`] holds it (its child node or first slot in the blocks,
/// and its primitives: 0 for an inner lane), so that a wide walk takes the lane off the stack without reading its
/// node again.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct StackEntry {
    /// The node, or the lane's index.
    pub(super) index: u32,
    /// The lane's primitives; 0 for a binary node or an inner lane.
    pub(super) count: u32,
    /// Where the ray enters the box.
    pub(super) near: f32,
}

/// The traversal stacks a chunk of rays reuses: one for rays traced alone, one for packets, one for rays walked in
/// turns.
pub(crate) struct Stacks {
    /// For a ray traced alone.
    pub(super) single: Vec<StackEntry>,
    /// For a packet (empty where there are none: other accels, other CPUs).
    #[cfg(target_arch = "x86_64")]
    pub(super) packet: Vec<PacketEntry>,
    /// For the rays of a group walked in turns, one stack after another (empty where none are).
    #[cfg(target_arch = "x86_64")]
    pub(super) turns: Vec<StackEntry>,
}

impl CpuAccel {
    /// Stacks for [`CpuAccel::traverse_group`], deep enough for this accel and everything below it.
    pub(crate) fn new_stacks(&self) -> Stacks {
        Stacks {
            single: vec![StackEntry::default(); self.stack_size()],
            #[cfg(target_arch = "x86_64")]
            packet: match self {
                CpuAccel::Triangles(bvh) => {
                    vec![PacketEntry::default(); bvh.wide.stack_size().max(bvh.moving.stack_size())]
                }
                // The instance nodes' walk, then a child's ([`super::instance_packets`]).
                CpuAccel::Instances(bvh) => vec![PacketEntry::default(); bvh.stack_size],
                CpuAccel::Transform(_) => Vec::new(),
            },
            #[cfg(target_arch = "x86_64")]
            turns: match self {
                CpuAccel::Triangles(bvh) if bvh.wide.in_turns => {
                    vec![StackEntry::default(); TURNS * bvh.wide.stack_size()]
                }
                _ => Vec::new(),
            },
        }
    }

    /// Offers each of `rays` (a group of neighbouring rays of a batch, [`crate::query::trace_batch`]'s, as
    /// [`crate::intersect::traced`] makes them, with a collector each) the triangles it reaches: together, as packets
    /// ([`super::packet`]), where they make them through a geometry accel (a moving one at each ray's time:
    /// [`super::moving_packets`]) or an instance accel ([`super::instance_packets`]); one by one otherwise.
    pub(crate) fn traverse_group(
        &self,
        stacks: &mut Stacks,
        rays: &[Ray],
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) {
        #[allow(unused_mut)]
        let mut traced = 0u32;
        #[cfg(target_arch = "x86_64")]
        if !binary_traversal() {
            traced = match self {
                CpuAccel::Triangles(bvh) => trace_packets(bvh.as_ref(), stacks, rays, collectors, stats),
                CpuAccel::Instances(bvh) => trace_packets(bvh, stacks, rays, collectors, stats),
                CpuAccel::Transform(_) => 0,
            };
        }
        let alone = !traced & ((1u64 << rays.len()) - 1) as u32;
        if alone == 0 {
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if let CpuAccel::Triangles(bvh) = self
            && bvh.node_keys.is_none()
            && !binary_traversal()
            && has_avx2()
        {
            // SAFETY: the CPU has AVX2 and the other features (and AVX-512VL where it is asked for), as just checked;
            // the accel is static; a group holds at most `TURNS` rays.
            unsafe {
                match has_avx512vl() {
                    true => bvh.traverse_static_avx512(stacks, rays, collectors, alone, stats),
                    false => bvh.traverse_static_avx2(stacks, rays, collectors, alone, stats),
                }
            }
            return;
        }
        for (i, (ray, collector)) in rays.iter().zip(collectors).enumerate() {
            if alone & (1 << i) != 0 {
                let ray = PreparedRay::from_traced(ray);
                self.traverse(&mut stacks.single, &ray, &InstanceScope::WORLD, collector, stats);
            }
        }
    }

    /// Offers every triangle the ray reaches, in `scope`, to `collector`, until it is done.
    pub(crate) fn traverse(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        scope: &InstanceScope,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
    ) {
        match self {
            CpuAccel::Triangles(bvh) => bvh.traverse(stack, ray, scope, collector, stats),
            CpuAccel::Instances(bvh) => bvh.traverse(stack, ray, scope, collector, stats),
            CpuAccel::Transform(node) => node.traverse(stack, ray, scope, collector, stats),
        }
    }
}

/// Defines `$name`, [`TriangleBvh::traverse_static`] compiled with the target features `$features`: its builds for
/// the CPUs that have them.
#[cfg(target_arch = "x86_64")]
macro_rules! traverse_static_compiled_for {
    ($(#[$doc:meta])* $name:ident, $features:literal) => {
        impl TriangleBvh {
            $(#[$doc])*
            ///
            /// # Safety
            /// As [`TriangleBvh::traverse_static`]'s, and the CPU must have the features this build is compiled with.
            #[target_feature(enable = $features)]
            unsafe fn $name(
                &self,
                stacks: &mut Stacks,
                rays: &[Ray],
                collectors: &mut [Collector<'_>],
                walking: u32,
                stats: &mut TraceStats,
            ) {
                // SAFETY: the CPU has the features (this function's contract), the rest is the caller's.
                unsafe { self.traverse_static(stacks, rays, collectors, walking, stats) }
            }
        }
    };
}

#[cfg(target_arch = "x86_64")]
traverse_static_compiled_for!(
    /// [`TriangleBvh::traverse_static`] compiled for AVX2 (what [`has_avx2`] checks).
    traverse_static_avx2,
    "avx2,fma,bmi1,bmi2,lzcnt,popcnt"
);

#[cfg(target_arch = "x86_64")]
traverse_static_compiled_for!(
    /// [`TriangleBvh::traverse_static`] compiled for AVX2 with AVX-512VL (what [`has_avx512vl`] checks): the same
    /// 8-lane instructions, which then reach 32 vector registers, so that the walk keeps its ray's numbers in them
    /// (random rays +4–10%, BENCHMARKS.md, "Single rays walked with 32 vector registers").
    traverse_static_avx512,
    "avx512f,avx512vl,avx2,fma,bmi1,bmi2,lzcnt,popcnt"
);

/// Whether geometry accels (static or moving) walk their binary nodes instead of their wide ones:
/// `RAYD_CPU_TRAVERSAL=binary`, read once, for A/B benchmarks of the traversal (BENCHMARKS.md, "CPU traversal step 1");
/// the answers are the same either way except which hit a ray that terminates on its first hit stops at. (`turns` and
/// `alone` choose how incoherent rays walk the wide nodes instead: [`super::turns::walks_in_turns`].)
fn binary_traversal() -> bool {
    static BINARY: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *BINARY.get_or_init(|| std::env::var("RAYD_CPU_TRAVERSAL").as_deref() == Ok("binary"))
}

impl TriangleBvh {
    /// Offers the triangles of the leaves the ray reaches, as they are at the ray's time: a static accel through its
    /// wide nodes, a moving one through its wide nodes with their boxes at that time ([`super::moving_wide`]); the
    /// binary nodes instead with `RAYD_CPU_TRAVERSAL=binary`.
    fn traverse(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        scope: &InstanceScope,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
    ) {
        let Some(at) = self.motion.locate(ray.time) else { return };
        match (&self.node_keys, binary_traversal()) {
            (None, false) => {
                let block_ray = BlockRay::new(ray);
                let leaf = self.static_leaf(&block_ray, ray, scope);
                self.wide.tree().walk(stack, ray, collector, stats, leaf, |slots| self.prefetch_leaf(slots))
            }
            (None, true) => {
                let leaf = with_stack(self.binary_leaf(|slot| self.corners[slot], ray, scope));
                walk(&self.nodes, static_boxes(&self.nodes), stack, ray, collector, stats, leaf)
            }
            (Some(keys), binary) => {
                let stride = keys.keys;
                let corners = move |slot: usize| {
                    let (a, b) =
                        (&self.corners[slot * stride + at.segment], &self.corners[slot * stride + at.segment + 1]);
                    std::array::from_fn(|c| lerp(a[c], b[c], at.fraction))
                };
                let leaf = self.binary_leaf(corners, ray, scope);
                match binary {
                    false => {
                        let boxes_at = |node: usize| self.moving.boxes_at(node, at);
                        self.moving.tree().walk_moving(stack, ray, collector, stats, leaf, boxes_at)
                    }
                    true => walk(&self.nodes, |node| keys.at(node, at), stack, ray, collector, stats, with_stack(leaf)),
                }
            }
        }
    }

    /// What a walk of the binary nodes does at a leaf ([`TriangleBvh::offer_leaf`] over the accel's own slots): each
    /// triangle, its corners from `corners` (by slot), sorted out by the scalar test's first step.
    #[inline(always)]
    fn binary_leaf<'a>(
        &'a self,
        corners: impl Fn(usize) -> [Vec3; 3] + Copy + 'a,
        ray: &'a PreparedRay,
        scope: &'a InstanceScope,
    ) -> impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool + 'a {
        let candidates = move |block: usize, lanes: u32, _: f32, _: &mut MetLanes<BLOCK>| {
            let may_hit = (0..BLOCK).fold(0, |bits, lane| match lanes >> lane & 1 {
                0 => bits,
                _ => bits | u32::from(triangle::may_hit(ray, &corners(block * BLOCK + lane))) << lane,
            });
            (0, may_hit)
        };
        let slots = LeafSlots { ids: &self.refs, masks: self.masks.as_deref() };
        self.offer_leaf(slots, corners, candidates, false, ray, scope)
    }

    /// Offers each of `rays` whose bit is set in `walking` the triangles of the leaves it reaches in this static
    /// accel, in turns where the accel walks them so and more than one does, one after another otherwise, with
    /// their leaves' hits taken from the blocks' lanes where the accel has no Prime masks.
    ///
    /// # Safety
    /// The CPU must have the features [`has_avx2`] checks (the caller is compiled with them); the accel must be
    /// static (no `node_keys`); a group holds at most [`TURNS`] rays.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn traverse_static(
        &self,
        stacks: &mut Stacks,
        rays: &[Ray],
        collectors: &mut [Collector<'_>],
        walking: u32,
        stats: &mut TraceStats,
    ) {
        let (turns, single) = (&mut stacks.turns, &mut stacks.single);
        // SAFETY: this function's contract is theirs.
        unsafe {
            match (self.wide.in_turns && walking.count_ones() > 1, self.masks.is_none()) {
                (true, true) => self.traverse_in_turns::<true>(turns, rays, collectors, walking, stats),
                (true, false) => self.traverse_in_turns::<false>(turns, rays, collectors, walking, stats),
                (false, true) => self.traverse_alone::<true>(single, rays, collectors, walking, stats),
                (false, false) => self.traverse_alone::<false>(single, rays, collectors, walking, stats),
            }
        }
    }

    /// Offers each of `rays` whose bit is set in `alone` the triangles of the leaves it reaches in this static accel,
    /// one ray after another: [`TriangleBvh::traverse`] of each ray as [`CpuAccel::traverse_group`] would call it,
    /// inlined into one loop, so that preparing a ray and starting its walk take no calls.
    ///
    /// With `IN_LANES`, the rays take their leaves' hits from the blocks' lanes ([`TriangleBvh::lanes_leaf`]): the
    /// accel must have no Prime masks.
    ///
    /// # Safety
    /// The CPU must have the features [`has_avx2`] checks (the caller is compiled with them); the accel must be
    /// static (no `node_keys`).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn traverse_alone<const IN_LANES: bool>(
        &self,
        stack: &mut [StackEntry],
        rays: &[Ray],
        collectors: &mut [Collector<'_>],
        alone: u32,
        stats: &mut TraceStats,
    ) {
        let (mut alone, tree) = (alone, self.wide.tree());
        while alone != 0 {
            let i = alone.trailing_zeros() as usize;
            alone &= alone - 1;
            let ray = PreparedRay::from_traced(&rays[i]);
            let block_ray = BlockRay::new(&ray);
            let prefetch_leaf = |slots| self.prefetch_leaf(slots);
            // SAFETY (both): the CPU has the features (this function's contract).
            if IN_LANES {
                let leaf = self.lanes_leaf(&block_ray, &ray, collectors[i].keeps_no_hit());
                unsafe { tree.walk_avx(stack, &ray, &mut collectors[i], stats, leaf, prefetch_leaf) };
            } else {
                let leaf = self.static_leaf(&block_ray, &ray, &InstanceScope::WORLD);
                unsafe { tree.walk_avx(stack, &ray, &mut collectors[i], stats, leaf, prefetch_leaf) };
            }
        }
    }

    /// What a walk of a static accel without Prime masks does at a leaf: as [`TriangleBvh::static_leaf`], but the
    /// rest of the watertight test runs in the block's lanes too ([`super::blocks::CornerBlocks::met_within`]), and
    /// the hits met within the ray's range are offered from there: where the collector keeps no hit (`keeps_no_hit`:
    /// [`Collector::keeps_no_hit`]) and the ray culls no faces, it is told only that there is one
    /// ([`Collector::offer_found`]); otherwise it is handed the hit ([`accept_hit`]). The lanes on an edge or a
    /// vertex take the scalar test and slots are taken in the same order, so the answers and the statistics are those
    /// of the scalar test.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(super) fn lanes_leaf<'a>(
        &'a self,
        block_ray: &'a BlockRay<'a>,
        ray: &'a PreparedRay,
        keeps_no_hit: bool,
    ) -> impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool + 'a {
        let blocks = &self.wide.blocks;
        let met = |block, lanes, cull_tmax, met: &mut MetLanes<BLOCK>| {
            blocks.met_within(block_ray, block, lanes, (ray.tmin, cull_tmax), met)
        };
        let culling = crate::format::RayFlags::CULL_BACK_FACING | crate::format::RayFlags::CULL_FRONT_FACING;
        let found_only = keeps_no_hit && !ray.flags.intersects(culling);
        self.offer_leaf(
            self.wide.leaf_slots(),
            |slot| blocks.corners(slot),
            met,
            found_only,
            ray,
            &InstanceScope::WORLD,
        )
    }

    /// What a walk of a static accel does at a leaf ([`TriangleBvh::offer_leaf`]): its triangles sorted out a block
    /// at a time by `block_ray`, their corners read from the blocks too, so that a leaf's triangles are read from
    /// one place.
    #[inline(always)]
    pub(super) fn static_leaf<'a>(
        &'a self,
        block_ray: &'a BlockRay<'a>,
        ray: &'a PreparedRay,
        scope: &'a InstanceScope,
    ) -> impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool + 'a {
        let blocks = &self.wide.blocks;
        let candidates =
            |block, lanes, _, _: &mut MetLanes<BLOCK>| (0, blocks.block_candidates(block_ray, block) & lanes);
        self.offer_leaf(self.wide.leaf_slots(), |slot| blocks.corners(slot), candidates, false, ray, scope)
    }

    /// Starts loading the data of the leaf over the blocks' `slots` of a static accel: its blocks of corners (one, or
    /// two in a row for a leaf of more than [`BLOCK`] triangles: [`super::blocks::Placement`]) and its ids.
    #[inline(always)]
    pub(super) fn prefetch_leaf(&self, slots: Range<usize>) {
        // A block is 144 bytes: three cache lines from the one it starts in hold it whole, and the two lines after
        // them most of the block after it. Those two are asked for without a branch: a leaf of one block asks for its
        // first two lines again instead (a hint the cache already has).
        let first = self.wide.blocks.block_ptr(slots.start).cast::<u8>();
        let second = usize::from(slots.len() > BLOCK) * 3 * CACHE_LINE;
        prefetch::<3>(first);
        prefetch::<2>(first.wrapping_add(second));
        prefetch::<1>(self.wide.ids.as_ptr().wrapping_add(slots.start));
    }

    /// What a walk does at a leaf: offers each of its triangles, with its corners from `corners` and its ids and mask
    /// from `leaf_slots` (by slot), in slot order, and says whether the collector is done. The triangles the ray's line
    /// cannot cross are first sorted out, a block of [`BLOCK`] slots at a time, by `sort_out`: given a block, a bit for
    /// each of its lanes in the leaf, the collector's cull distance and room for the hits it finds, it returns the
    /// lanes whose hit within the ray's range it found (left in that room), and the lanes the ray may hit otherwise,
    /// which take the scalar test ([`triangle::may_hit`], or the same test on the block at once, rules out the rest). A
    /// found hit is offered as it is: with `found_only`, the collector is told only that there is one
    /// ([`Collector::offer_found`]; it must [`Collector::keeps_no_hit`] and the ray cull no faces). The answers and the
    /// statistics (triangles tested up to where the collector is done) are those of offering every one to the scalar
    /// test.
    #[inline(always)]
    fn offer_leaf<'a>(
        &'a self,
        leaf_slots: LeafSlots<'a>,
        corners: impl Fn(usize) -> [Vec3; 3] + 'a,
        sort_out: impl Fn(usize, u32, f32, &mut MetLanes<BLOCK>) -> (u32, u32) + 'a,
        found_only: bool,
        ray: &'a PreparedRay,
        scope: &'a InstanceScope,
    ) -> impl FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool + 'a {
        #[inline(always)]
        move |slots, collector, stats| {
            let mut met = MetLanes::NONE;
            for block in slots.start / BLOCK..slots.end.div_ceil(BLOCK) {
                let (found, candidates) = sort_out(block, lanes_within(block, &slots), collector.cull_tmax(), &mut met);
                let mut lanes = found | candidates;
                while lanes != 0 {
                    let lane = lanes.trailing_zeros() as usize;
                    lanes &= lanes - 1;
                    let slot = block * BLOCK + lane;
                    let was_found = found & (1 << lane) != 0;
                    if was_found && found_only {
                        collector.offer_found();
                    } else {
                        let (id, mask) = leaf_slots.id_and_mask(slot);
                        let candidate = TriangleCandidate {
                            corners: &corners(slot),
                            id,
                            mask,
                            geometry_flags: self.geometry_flags[id.geom_id as usize],
                        };
                        match was_found {
                            true if ray.mask & candidate.mask == 0 => {
                                accept_hit(ray.tmin, ray.flags, &candidate, scope, collector, met.hit(lane));
                            }
                            true => {}
                            false => consider_triangle(ray, &candidate, scope, collector),
                        }
                    }
                    if collector.done() {
                        stats.triangle_tests += (slot + 1 - slots.start) as u64;
                        return true;
                    }
                }
            }
            stats.triangle_tests += slots.len() as u64;
            false
        }
    }
}

/// What a leaf's slots hold besides corners: the slots of the accel ([`TriangleBvh::refs`], [`TriangleBvh::masks`])
/// for a binary walk, those of the wide BVH's blocks ([`super::wide::WideBvh::ids`]) for a wide one.
#[derive(Clone, Copy)]
pub(super) struct LeafSlots<'a> {
    /// Each slot's triangle ids.
    pub(super) ids: &'a [TriangleRef],
    /// Each slot's Prime mask, where the accel has masks.
    pub(super) masks: Option<&'a [u32]>,
}

impl LeafSlots<'_> {
    /// The ids and the Prime mask (0 without masks) of the triangle in `slot`.
    #[inline(always)]
    pub(super) fn id_and_mask(&self, slot: usize) -> (TriangleRef, u32) {
        (self.ids[slot], self.masks.map_or(0, |m| m[slot]))
    }
}

/// A bit for each lane of block `block` whose slot is in `slots`.
#[inline(always)]
fn lanes_within(block: usize, slots: &Range<usize>) -> u32 {
    let first = block * BLOCK;
    let (from, to) = (slots.start.saturating_sub(first).min(BLOCK), (slots.end - first).min(BLOCK));
    ((1u32 << to) - 1) & !((1u32 << from) - 1)
}

/// A leaf of a wide walk as one of a binary walk, which also hands it the free part of the stack.
#[inline(always)]
fn with_stack<L: FnMut(Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool>(
    mut leaf: L,
) -> impl FnMut(Range<usize>, &mut [StackEntry], &mut Collector<'_>, &mut TraceStats) -> bool {
    move |slots, _, collector, stats| leaf(slots, collector, stats)
}

impl InstanceBvh {
    /// Traverses the child of every visible instance whose box the ray reaches (at its time), in the instance's
    /// space: through the wide nodes, with their boxes at the ray's time for a motion accel ([`super::moving_wide`]);
    /// a motion accel's binary nodes instead with `RAYD_CPU_TRAVERSAL=binary`.
    fn traverse(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        scope: &InstanceScope,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
    ) {
        let Some(at) = self.motion.locate(ray.time) else { return };
        match (&self.node_keys, binary_traversal()) {
            (keys @ Some(_), false) | (keys @ None, _) => {
                let own_size = if keys.is_some() { self.moving.stack_size() } else { self.wide.stack_size() };
                let (own, rest) = stack.split_at_mut(own_size);
                let leaf = |slots, collector: &mut Collector<'_>, stats: &mut TraceStats| {
                    self.enter_instances(slots, rest, ray, scope, collector, stats)
                };
                match keys {
                    None => self.wide.tree().walk(own, ray, collector, stats, leaf, |_| {}),
                    Some(_) => {
                        let boxes_at = |node: usize| self.moving.boxes_at(node, at);
                        self.moving.tree().walk_moving(own, ray, collector, stats, leaf, boxes_at)
                    }
                }
            }
            (Some(keys), true) => walk(
                &self.nodes,
                |node| keys.at(node, at),
                stack,
                ray,
                collector,
                stats,
                |slots, rest, c, s| self.enter_instances(slots, rest, ray, scope, c, s),
            ),
        }
    }

    /// Traverses the child of each visible instance in `slots` that the ray reaches, with the free part of the stack
    /// `rest`, and says whether the collector is done.
    #[inline(always)]
    fn enter_instances(
        &self,
        slots: Range<usize>,
        rest: &mut [StackEntry],
        ray: &PreparedRay,
        scope: &InstanceScope,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
    ) -> bool {
        for (instance, &(min, max)) in self.instances[slots.clone()].iter().zip(&self.child_boxes[slots]) {
            if ray.visibility & instance.mask == 0 {
                continue;
            }
            let Ok(child) = cpu_child(&instance.child) else { continue };
            let to_object = &instance.placement.world_to_object;
            let Some(local) = carried_into(ray, to_object, (min, max), collector, stats) else { continue };
            child.traverse(rest, &local, &scope.enter(instance), collector, stats);
            if collector.done() {
                return true;
            }
        }
        false
    }
}

impl TransformNode {
    /// Traverses the child in its own space, as the transform places it at the ray's time.
    fn traverse(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        scope: &InstanceScope,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
    ) {
        let Some(placement) = self.transform.placement_at(ray.time) else { return };
        let Ok(child) = cpu_child(&self.child) else { return };
        let to_object = &placement.world_to_object;
        if let Some(local) = carried_into(ray, to_object, self.child_box, collector, stats) {
            child.traverse(stack, &local, &scope.through(&placement), collector, stats);
        }
    }
}

/// `ray` carried into the space `to_object` maps into and prepared there, if it reaches the box `(min, max)` there
/// (a child's own box) within its `tmin` and `tmax`; the box is tested before the ray is prepared, which costs
/// several times the test, and counted as a box tested. Most rays that reach a turned child's placed box miss the
/// child (BENCHMARKS.md, "Instances entered through their children's own boxes"). None for a ray past its work,
/// which `collector` stops ([`Collector::stop_past`]).
#[inline(always)]
pub(super) fn carried_into(
    ray: &PreparedRay,
    to_object: &Affine3A,
    (min, max): Bounds,
    collector: &mut Collector<'_>,
    stats: &mut TraceStats,
) -> Option<PreparedRay> {
    if collector.stop_past(stats) {
        return None;
    }
    let (origin, direction) = ray.carried(to_object);
    stats.nodes_visited += 1;
    let tmax = collector.cull_tmax();
    aabb::reaches(origin, direction, min.into(), max.into(), ray.tmin, tmax).then(|| ray.moved(origin, direction))
}

/// The boxes of a static BVH: each node's own.
#[inline(always)]
fn static_boxes(nodes: &[Node]) -> impl Fn(u32) -> (Vec3A, Vec3A) + '_ {
    |node| {
        let node = &nodes[node as usize];
        (Vec3A::from(node.min), Vec3A::from(node.max))
    }
}

/// Walks `nodes` (whose boxes `node_box` gives by index) front to back and hands each leaf the ray reaches (its
/// primitive slots, the free part of the stack, the collector and the statistics) to `leaf`, which returns whether
/// the collector is done.
#[inline(always)]
fn walk(
    nodes: &[Node],
    node_box: impl Fn(u32) -> (Vec3A, Vec3A),
    stack: &mut [StackEntry],
    ray: &PreparedRay,
    collector: &mut Collector<'_>,
    stats: &mut TraceStats,
    mut leaf: impl FnMut(Range<usize>, &mut [StackEntry], &mut Collector<'_>, &mut TraceStats) -> bool,
) {
    if nodes.is_empty() {
        return;
    }
    let test = |node: u32, tmax: f32| {
        let (min, max) = node_box(node);
        aabb::intersect(ray, min, max, ray.tmin, tmax)
    };
    stats.nodes_visited += 1;
    if test(0, collector.cull_tmax()).is_none() {
        return;
    }
    let mut len = 0usize;
    let mut current = 0u32;
    loop {
        let node = &nodes[current as usize];
        let mut next = None;
        if node.count > 0 {
            let first = node.index as usize;
            if leaf(first..first + node.count as usize, &mut stack[len..], collector, stats) {
                return;
            }
        } else {
            let tmax = collector.cull_tmax();
            let (left, right) = (node.index, node.index + 1);
            stats.nodes_visited += 2;
            let near_left = test(left, tmax);
            let near_right = test(right, tmax);
            next = match (near_left, near_right) {
                (Some(l), Some(r)) => {
                    let (first, second) = if r < l { ((right, r), (left, l)) } else { ((left, l), (right, r)) };
                    stack[len] = StackEntry { index: second.0, count: 0, near: second.1 };
                    len += 1;
                    Some(first.0)
                }
                (Some(_), None) => Some(left),
                (None, Some(_)) => Some(right),
                (None, None) => None,
            };
        }
        current = match next {
            Some(node) => node,
            None => loop {
                if len == 0 {
                    return;
                }
                len -= 1;
                let StackEntry { index, near, .. } = stack[len];
                if near <= collector.cull_tmax() {
                    break index;
                }
            },
        };
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
pub(super) mod tests {
    use glam::Vec3A;

    use super::*;
    use crate::backend::cpu::packet::tests::{lattice, rays_from};
    use crate::format::{Hit, HitFormat, RayFlags, RayFormat};
    use crate::intersect::traced;
    use crate::query::{Query, QueryKind};

    /// How [`trace`] walks a static accel.
    #[derive(Debug, Clone, Copy, PartialEq)]
    pub(in crate::backend::cpu) enum Walk {
        /// Each ray through [`CpuAccel::traverse`], the leaves' scalar test.
        OneByOne,
        /// In the batch driver's groups through [`CpuAccel::traverse_group`], incoherent rays one after another.
        Alone,
        /// The same, incoherent rays in turns ([`super::super::turns`]).
        InTurns,
        /// Every ray of a group through [`TriangleBvh::traverse_static_avx2`], alone or in turns: the build of the
        /// static walks that CPUs with AVX-512VL do not run otherwise.
        Avx2 { in_turns: bool },
    }

    /// Each ray's records and counts of `query`, and the statistics, traced through `bvh` as `walk` says.
    pub(in crate::backend::cpu) fn trace(
        bvh: &TriangleBvh,
        query: &Query,
        rays: &[Ray],
        walk: Walk,
    ) -> (Vec<u8>, Vec<u8>, TraceStats) {
        let mut bvh = bvh.clone();
        bvh.wide.in_turns = matches!(walk, Walk::InTurns | Walk::Avx2 { in_turns: true });
        let accel = CpuAccel::Triangles(Box::new(bvh));
        let mut stacks = accel.new_stacks();
        let records = query.records_per_ray();
        let mut hits = vec![0u8; query.hit_format.buffer_len(rays.len() * records)];
        let mut counts = vec![0u8; 4 * rays.len()];
        let mut scratch = vec![Hit::MISS; TURNS * records];
        let mut stats = TraceStats::default();
        for (group, rays) in rays.chunks(TURNS).enumerate() {
            let rays: Vec<Ray> = rays.iter().map(|ray| traced(ray, query.flags)).collect();
            let mut parts = scratch.chunks_mut(records);
            let mut collectors: Vec<Collector<'_>> =
                rays.iter().map(|ray| Collector::new(query, ray, parts.next().expect("a part a ray"))).collect();
            match (walk, &accel) {
                (Walk::OneByOne, _) => {
                    for (ray, collector) in rays.iter().zip(&mut collectors) {
                        let ray = PreparedRay::from_traced(ray);
                        accel.traverse(&mut stacks.single, &ray, &InstanceScope::WORLD, collector, &mut stats);
                    }
                }
                (Walk::Avx2 { .. }, CpuAccel::Triangles(bvh)) if has_avx2() => {
                    let every_ray = ((1u64 << rays.len()) - 1) as u32;
                    // SAFETY: the CPU has AVX2 and the rest, as just checked; the accel is static; a group holds
                    // `TURNS` rays at most.
                    unsafe { bvh.traverse_static_avx2(&mut stacks, &rays, &mut collectors, every_ray, &mut stats) };
                }
                _ => accel.traverse_group(&mut stacks, &rays, &mut collectors, &mut stats),
            }
            for (i, collector) in collectors.iter().enumerate() {
                let index = group * TURNS + i;
                collector.write(query.hit_format, &mut hits, index * records, &mut counts, index);
            }
        }
        (hits, counts, stats)
    }

    /// Rays from origins scattered around and inside [`lattice`], ray to ray (no two neighbours make a packet),
    /// towards its grid points, some of them vertices and edges, with [`rays_from`]'s ranges and masks; and rays that
    /// reach nothing or everything: a NaN origin, a zero direction, an empty range.
    pub(in crate::backend::cpu) fn scattered_rays() -> Vec<Ray> {
        let scatter = |pixel: u32, k: u32| ((pixel.wrapping_mul(2_654_435_761) >> (k * 8)) & 255) as f32 / 64.0;
        let mut rays = rays_from(
            |pixel| Vec3A::new(scatter(pixel, 0) - 0.5, scatter(pixel, 1) - 0.5, scatter(pixel, 2) / 2.0 - 1.0),
            |target, eye| target - eye,
        );
        rays[5].origin = Vec3A::new(f32::NAN, 1.0, 1.0);
        rays[17].direction = Vec3A::ZERO;
        (rays[40].tmin, rays[40].tmax) = (2.0, 1.0);
        rays
    }

    #[test]
    fn hits_found_in_the_blocks_lanes_are_the_scalar_tests() {
        if !has_avx2() {
            return;
        }
        let rays = scattered_rays();
        let kinds = [QueryKind::Closest, QueryKind::All, QueryKind::Count, QueryKind::Any];
        let queries = kinds.into_iter().flat_map(|kind| {
            let flags = [RayFlags::empty(), RayFlags::TERMINATE_ON_FIRST_HIT, RayFlags::CULL_BACK_FACING];
            flags.map(|flags| Query {
                kind,
                flags,
                max_hits_per_ray: 4,
                ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV)
            })
        });
        // Any hit in the bitmask format too, whose collectors are told only that there is one; Prime masks (on every
        // fifth triangle and every third ray) take the scalar test.
        let bitmask = |query: &Query| Query { hit_format: HitFormat::Bitmask, ..*query };
        let queries: Vec<Query> = queries.flat_map(|query| [query, bitmask(&query)]).collect();
        for masked in [false, true] {
            let (bvh, _) = lattice(masked);
            for query in queries.iter().filter(|q| q.hit_format == HitFormat::TTriidUV || q.kind == QueryKind::Any) {
                let case = format!("{:?} {:?} {:?}, masked {masked}", query.kind, query.hit_format, query.flags);
                let one_by_one = trace(&bvh, query, &rays, Walk::OneByOne);
                let hit = |ray: usize| match query.hit_format {
                    HitFormat::Bitmask => one_by_one.0[ray / 8] >> (ray % 8) & 1 == 1,
                    _ => HitFormat::TTriidUV.read(&one_by_one.0, ray * query.records_per_ray()).is_hit(),
                };
                let hits = (0..rays.len()).filter(|&ray| hit(ray)).count();
                assert!(hits > rays.len() / 4 && hits < rays.len(), "{case}: {hits} rays hit");
                for walk in [Walk::Alone, Walk::InTurns, Walk::Avx2 { in_turns: false }, Walk::Avx2 { in_turns: true }]
                {
                    let grouped = trace(&bvh, query, &rays, walk);
                    assert!(grouped == one_by_one, "{case}, {walk:?}: {:?} against {:?}", grouped.2, one_by_one.2);
                }
            }
        }
    }
}
