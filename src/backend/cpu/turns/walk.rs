//! The walk in turns ([`super`]), in AVX2: where a ray is between its turns, and the loop that gives them.

use std::mem::MaybeUninit;
use std::ops::Range;

use crate::backend::cpu::blocks::BlockRay;
use crate::backend::cpu::set_bits;
use crate::backend::cpu::traverse::StackEntry;
use crate::backend::cpu::triangles::TriangleBvh;
use crate::backend::cpu::wide::{WideBvh, WideNode, avx, pop};
use crate::format::Ray;
use crate::intersect::PreparedRay;
use crate::query::{Collector, InstanceScope, TraceStats};

/// Rays walked in turns together, at most: a group of the batch driver's.
pub(in crate::backend::cpu) const TURNS: usize = crate::query::GROUP_RAYS;

/// Where a ray walked in turns is: what it visits at its next turn (a lane's index and count: an inner node's
/// count is 0), its stack's depth and its cull distance.
#[derive(Debug, Clone, Copy)]
struct Turn {
    index: u32,
    count: u32,
    len: u32,
    tmax: f32,
}

impl TriangleBvh {
    /// Offers each of `rays` whose bit is set in `walking` the triangles of the leaves it reaches in this static accel,
    /// the rays walked in turns: what [`TriangleBvh::traverse_alone`] does one ray after another (with `IN_LANES` as
    /// there).
    ///
    /// # Safety
    /// The CPU must have the features [`crate::cpu_features::has_avx2`] checks (the caller is compiled with them);
    /// the accel must be static (no `node_keys`); `rays` holds at most [`TURNS`] rays.
    #[inline(always)]
    pub(in crate::backend::cpu) unsafe fn traverse_in_turns<const IN_LANES: bool>(
        &self,
        stacks: &mut [StackEntry],
        rays: &[Ray],
        collectors: &mut [Collector<'_>],
        walking: u32,
        stats: &mut TraceStats,
    ) {
        let mut prepared = [const { MaybeUninit::<PreparedRay>::uninit() }; TURNS];
        for i in set_bits(walking) {
            prepared[i].write(PreparedRay::from_traced(&rays[i]));
        }
        // SAFETY (here and below): ray `i` walks, so it was prepared just above.
        let prepared = |i: usize| unsafe { prepared.get_unchecked(i).assume_init_ref() };
        let mut block_rays = [const { MaybeUninit::<BlockRay<'_>>::uninit() }; TURNS];
        let mut lanes = [const { MaybeUninit::<avx::RayLanes>::uninit() }; TURNS];
        for i in set_bits(walking) {
            block_rays[i].write(BlockRay::new(prepared(i)));
            // SAFETY: the CPU has AVX2 (this function's contract), so AVX too.
            lanes[i].write(unsafe { avx::RayLanes::new(prepared(i)) });
        }
        let leaf = {
            #[inline(always)]
            |i: usize, slots, collector: &mut Collector<'_>, stats: &mut TraceStats| {
                // SAFETY: ray `i` walks, so its block test's numbers were made just above.
                let block_ray = unsafe { block_rays.get_unchecked(i).assume_init_ref() };
                match IN_LANES {
                    true => {
                        (self.lanes_leaf(block_ray, prepared(i), collector.keeps_no_hit()))(slots, collector, stats)
                    }
                    false => (self.static_leaf(block_ray, prepared(i), &InstanceScope::WORLD))(slots, collector, stats),
                }
            }
        };
        let prefetch_leaf = |slots| self.prefetch_leaf(slots);
        // SAFETY: the CPU has the features (this function's contract); each walking ray's lanes were made above.
        unsafe { self.wide.walk_in_turns(stacks, &lanes, walking, collectors, stats, leaf, prefetch_leaf) };
    }
}

impl WideBvh {
    /// Walks the rays whose bit is set in `walking` in turns (see the module's documentation), each with its box
    /// test's numbers in `lanes` and its collector in `collectors`, and hands each leaf a ray reaches to `leaf` with
    /// the ray's index (see [`crate::backend::cpu::wide::Tree::walk`]).
    ///
    /// Panics when `stacks` holds fewer than [`WideBvh::stack_size`] entries for each of [`TURNS`] rays.
    ///
    /// # Safety
    /// The CPU must have the features [`crate::cpu_features::has_avx2`] checks (the caller is compiled with them);
    /// `lanes` holds the numbers of every ray walked.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    unsafe fn walk_in_turns(
        &self,
        stacks: &mut [StackEntry],
        lanes: &[MaybeUninit<avx::RayLanes>; TURNS],
        walking: u32,
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
        mut leaf: impl FnMut(usize, Range<usize>, &mut Collector<'_>, &mut TraceStats) -> bool,
        prefetch_leaf: impl Fn(Range<usize>),
    ) {
        if self.nodes.is_empty() || walking == 0 {
            return;
        }
        let size = self.stack_size();
        assert!(stacks.len() >= TURNS * size, "stacks of {} entries for {TURNS} of {size}", stacks.len());
        let nearest_first = collectors[walking.trailing_zeros() as usize].wants_nearest_first();
        let mut turns = [Turn { index: 0, count: 0, len: 0, tmax: 0.0 }; TURNS];
        for i in set_bits(walking) {
            turns[i].tmax = collectors[i].cull_tmax();
        }
        let mut boxes = 0u64;
        let mut walking = walking;
        while walking != 0 {
            let mut round = walking;
            while round != 0 {
                let i = round.trailing_zeros() as usize;
                round &= round - 1;
                // SAFETY: `i` is a bit of `walking`, whose every bit indexed `turns` and `collectors` with checks
                // above; ray `i`'s stack lies within `stacks` (checked above); its lanes were made (the contract).
                let (turn, stack, collector, ray_lanes) = unsafe {
                    (
                        turns.get_unchecked_mut(i),
                        stacks.get_unchecked_mut(i * size..(i + 1) * size),
                        collectors.get_unchecked_mut(i),
                        lanes.get_unchecked(i).assume_init_ref(),
                    )
                };
                let Turn { mut index, mut count, len, mut tmax } = *turn;
                let mut len = len as usize;
                // The ray's turn: up to the next lane it enters, whose data was only now asked for. A lane taken off
                // the stack was asked for when it was pushed, and is visited at once.
                let walks_on = loop {
                    if count == 0 {
                        // SAFETY: `index` is the root or an inner lane's index; a walk leaves at most `WIDTH − 1`
                        // lanes waiting a level: `stack_size` entries.
                        let next = unsafe {
                            let enter = {
                                #[inline(always)]
                                |node: &WideNode, tmax| ray_lanes.enter(node, tmax)
                            };
                            self.tree().visit_node(
                                index as usize,
                                tmax,
                                &enter,
                                stack,
                                &mut len,
                                nearest_first,
                                &prefetch_leaf,
                                &mut boxes,
                            )
                        };
                        if let Some(lane) = next {
                            (index, count) = lane;
                            break true;
                        }
                    } else {
                        if leaf(i, index as usize..(index + count) as usize, collector, stats) {
                            break false;
                        }
                        tmax = collector.cull_tmax();
                    }
                    match pop(stack, &mut len, tmax) {
                        Some(lane) => (index, count) = lane,
                        None => break false,
                    }
                };
                *turn = Turn { index, count, len: len as u32, tmax };
                if !walks_on {
                    walking &= !(1 << i);
                }
            }
        }
        stats.nodes_visited += boxes;
    }
}

#[cfg(test)]
mod tests {
    use crate::backend::cpu::packet::tests::scene;
    use crate::backend::cpu::traverse::tests::{Walk, scattered_rays, trace};
    use crate::cpu_features::has_avx2;
    use crate::format::{HitFormat, RayFlags, RayFormat};
    use crate::query::{Query, QueryKind};

    #[test]
    fn rays_walked_in_turns_get_the_answers_and_statistics_of_rays_walked_alone() {
        if !has_avx2() {
            return;
        }
        let (bvh, _) = scene();
        let rays = scattered_rays();
        for kind in [QueryKind::Closest, QueryKind::Any, QueryKind::All, QueryKind::Count] {
            for flags in [RayFlags::empty(), RayFlags::CULL_BACK_FACING, RayFlags::TERMINATE_ON_FIRST_HIT] {
                let query = Query {
                    kind,
                    flags,
                    max_hits_per_ray: 4,
                    ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV)
                };
                let alone = trace(&bvh, &query, &rays, Walk::Alone);
                let in_turns = trace(&bvh, &query, &rays, Walk::InTurns);
                let first_record = |ray: usize| ray * query.records_per_ray();
                let hits = (0..rays.len())
                    .filter(|&ray| HitFormat::TTriidUV.read(&alone.0, first_record(ray)).is_hit())
                    .count();
                assert!(hits > rays.len() / 4 && hits < rays.len(), "{kind:?} {flags:?}: {hits} rays hit");
                assert!(alone == in_turns, "{kind:?} {flags:?}: {:?} against {:?}", in_turns.2, alone.2);
            }
        }
    }
}
