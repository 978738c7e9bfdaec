//! The 8-wide BVH that static geometry accels are traversed with: the binary BVH of [`super::bvh`] collapsed so that
//! each node holds up to eight children's boxes in lanes (structure of arrays), tested against a ray all at once.
//! The lane loops are written so that the compiler turns them into SIMD: 8 lanes in one AVX2 register where the CPU
//! has AVX2 (detected at run time), two SSE registers otherwise.
//!
//! The box test is [`crate::intersect::aabb::intersect`] lane by lane: same operations in the same order, the same
//! NaN rule (a NaN slab distance leaves the interval as it was) and the same [`SLACK`], so a lane is entered exactly
//! when the binary BVH would enter that node. Children are visited nearest first; which triangles a ray can hit,
//! and so every query's answer, does not depend on the order.

use std::ops::Range;

use glam::Vec3A;

use super::bvh::{Footprint, Node, VecLen};
use super::collapse::{EMPTY_LANE, Lane, collapse};
use super::traverse::StackEntry;
use crate::intersect::PreparedRay;
use crate::intersect::aabb::{self, SLACK};
use crate::query::{Collector, TraceStats};

/// Children per node.
pub(super) const WIDTH: usize = 8;

/// One node, 256 bytes: `0 lo[axis][lane] f32×24 | 96 hi[axis][lane] f32×24 | 192 index u32×8 | 224 count u32×8`.
/// Lane `l` is a child: an inner node (`count[l]` 0, its node at `index[l]`), a leaf (its primitive slots
/// `index[l] .. index[l] + count[l]`), or empty (box `+∞ .. −∞`; the children come first, the empty lanes after).
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C, align(32))]
pub(super) struct WideNode {
    /// Box minima, by axis then lane.
    lo: [[f32; WIDTH]; 3],
    /// Box maxima, by axis then lane.
    hi: [[f32; WIDTH]; 3],
    /// Per lane: the child node (inner) or the first primitive slot (leaf).
    index: [u32; WIDTH],
    /// Per lane: primitives of a leaf, 0 for an inner or empty lane.
    count: [u32; WIDTH],
}

impl WideNode {
    /// A node whose lanes are all empty.
    const EMPTY: WideNode = WideNode {
        lo: [[f32::INFINITY; WIDTH]; 3],
        hi: [[f32::NEG_INFINITY; WIDTH]; 3],
        index: [0; WIDTH],
        count: [0; WIDTH],
    };

    /// Puts binary node `node` in lane `lane`, pointing at `index`.
    fn set_lane(&mut self, lane: usize, node: &Node, index: u32) {
        for axis in 0..3 {
            self.lo[axis][lane] = node.min[axis];
            self.hi[axis][lane] = node.max[axis];
        }
        self.index[lane] = index;
        self.count[lane] = node.count;
    }
}

/// A static BVH collapsed to [`WIDTH`] children a node.
#[derive(Debug, Clone, Default)]
pub(super) struct WideBvh {
    /// Nodes, the root first; empty when the binary BVH was.
    nodes: Vec<WideNode>,
    /// Children of each node: its first lanes, the rest are empty.
    children: Vec<u8>,
    /// The root's box (the binary root's).
    root: (Vec3A, Vec3A),
    /// Longest root-to-leaf path, in wide nodes.
    depth: usize,
}

impl WideBvh {
    /// Collapses a depth-first binary BVH ([`collapse`]).
    pub fn collapse(binary: &[Node]) -> WideBvh {
        let Some(root) = binary.first() else { return WideBvh::default() };
        let collapsed = collapse(binary, WIDTH);
        let mut wide = WideBvh {
            nodes: Vec::with_capacity(collapsed.lanes.len() / WIDTH),
            children: Vec::with_capacity(collapsed.lanes.len() / WIDTH),
            root: (root.min.into(), root.max.into()),
            depth: collapsed.depth,
        };
        for lanes in collapsed.lanes.chunks(WIDTH) {
            let mut node = WideNode::EMPTY;
            let occupied = lanes.iter().take_while(|l| l.binary != EMPTY_LANE).count();
            for (lane, &Lane { binary: n, child }) in lanes[..occupied].iter().enumerate() {
                let n = &binary[n as usize];
                node.set_lane(lane, n, if n.count > 0 { n.index } else { child });
            }
            wide.nodes.push(node);
            wide.children.push(occupied as u8);
        }
        wide
    }

    /// Stack entries a traversal needs: each node visited leaves at most `WIDTH − 1` children waiting.
    pub fn stack_size(&self) -> usize {
        self.depth * (WIDTH - 1) + 1
    }

    /// Bytes it occupies.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        (footprint.of(&self.nodes as &dyn VecLen) * size_of::<WideNode>() + footprint.of(&self.children)) as u64
    }

    /// Walks the nodes front to back and hands each leaf the ray reaches (its primitive slots, the free part of the
    /// stack, the collector and the statistics) to `leaf`, which returns whether the collector is done.
    #[inline(always)]
    pub fn walk(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        leaf: impl FnMut(Range<usize>, &mut [StackEntry], &mut Collector<'_>, &mut TraceStats) -> bool,
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2, as just checked.
            unsafe { self.walk_avx2(stack, ray, collector, stats, leaf) };
            return;
        }
        self.walk_lanes(stack, ray, collector, stats, leaf);
    }

    /// [`WideBvh::walk_lanes`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn walk_avx2(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        leaf: impl FnMut(Range<usize>, &mut [StackEntry], &mut Collector<'_>, &mut TraceStats) -> bool,
    ) {
        self.walk_lanes(stack, ray, collector, stats, leaf);
    }

    /// The walk itself, for whatever instruction set it is compiled with. Stack entries name a lane (`node ·
    /// WIDTH + lane`) with the distance at which the ray enters its box.
    #[inline(always)]
    fn walk_lanes(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
        mut leaf: impl FnMut(Range<usize>, &mut [StackEntry], &mut Collector<'_>, &mut TraceStats) -> bool,
    ) {
        if self.nodes.is_empty() {
            return;
        }
        stats.nodes_visited += 1;
        if aabb::intersect(ray, self.root.0, self.root.1, ray.tmin, collector.cull_tmax()).is_none() {
            return;
        }
        let mut len = 0usize;
        let mut node = 0usize;
        loop {
            let children = self.children[node];
            stats.nodes_visited += u64::from(children);
            let (entered, near) = enter_lanes(&self.nodes[node], ray, collector.cull_tmax());
            // Lanes past the children are empty; a ray with a NaN origin "enters" every box, theirs too.
            let entered = entered & ((1u32 << children) - 1);
            let mut next = nearest_first(node, entered, &near, stack, &mut len);
            // Leaves are handled as they come; the first inner lane reached is visited next.
            loop {
                let lane_ref = match next.take() {
                    Some(lane_ref) => lane_ref,
                    None => loop {
                        if len == 0 {
                            return;
                        }
                        len -= 1;
                        let (lane_ref, near) = stack[len];
                        if near <= collector.cull_tmax() {
                            break lane_ref;
                        }
                    },
                };
                let (owner, lane) = (&self.nodes[lane_ref as usize / WIDTH], lane_ref as usize % WIDTH);
                let count = owner.count[lane] as usize;
                if count == 0 {
                    node = owner.index[lane] as usize;
                    break;
                }
                let first = owner.index[lane] as usize;
                if leaf(first..first + count, &mut stack[len..], collector, stats) {
                    return;
                }
            }
        }
    }
}

/// Which lanes of `node` the ray enters within `[ray.tmin, tmax]` (bit per lane), and at what distance.
#[inline(always)]
fn enter_lanes(node: &WideNode, ray: &PreparedRay, tmax: f32) -> (u32, [f32; WIDTH]) {
    let mut near = [ray.tmin; WIDTH];
    let mut far = [tmax; WIDTH];
    for axis in 0..3 {
        let (lo, hi) =
            if ray.negative[axis] { (&node.hi[axis], &node.lo[axis]) } else { (&node.lo[axis], &node.hi[axis]) };
        let (origin, inv) = (ray.origin[axis], ray.inv_direction[axis]);
        for lane in 0..WIDTH {
            // `a > b ? a : b` keeps `b` when `a` is NaN, as `f32::max` does in the scalar test.
            let t0 = (lo[lane] - origin) * inv;
            near[lane] = if t0 > near[lane] { t0 } else { near[lane] };
            let t1 = (hi[lane] - origin) * inv;
            far[lane] = if t1 < far[lane] { t1 } else { far[lane] };
        }
    }
    let mut entered = 0u32;
    for lane in 0..WIDTH {
        let (n, f) = (near[lane] - near[lane].abs() * SLACK, far[lane] + far[lane].abs() * SLACK);
        near[lane] = n;
        entered |= u32::from(n <= f) << lane;
    }
    (entered, near)
}

/// Pushes the entered lanes of `node` but the nearest on the stack, farthest first, and returns the nearest.
#[inline(always)]
fn nearest_first(
    node: usize,
    entered: u32,
    near: &[f32; WIDTH],
    stack: &mut [StackEntry],
    len: &mut usize,
) -> Option<u32> {
    let lane_ref = |lane: u32| (node * WIDTH) as u32 + lane;
    match entered.count_ones() {
        0 => None,
        1 => Some(lane_ref(entered.trailing_zeros())),
        _ => {
            let mut order = [(0f32, 0u32); WIDTH];
            let mut count = 0;
            let mut bits = entered;
            while bits != 0 {
                let lane = bits.trailing_zeros();
                bits &= bits - 1;
                // Insertion by distance, nearest first.
                let d = near[lane as usize];
                let mut at = count;
                while at > 0 && order[at - 1].0 > d {
                    order[at] = order[at - 1];
                    at -= 1;
                }
                order[at] = (d, lane);
                count += 1;
            }
            for &(d, lane) in order[1..count].iter().rev() {
                stack[*len] = (lane_ref(lane), d);
                *len += 1;
            }
            Some(lane_ref(order[0].1))
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    #[test]
    fn lanes_hold_their_childrens_boxes_and_leaves_their_slots() {
        // A root over a leaf of 2 triangles (slots 0..2) and an inner node over two leaves (slots 2..3, 3..5).
        let node = |min: f32, max: f32, index: u32, count: u32| Node {
            min: Vec3::splat(min),
            index,
            max: Vec3::splat(max),
            count,
        };
        let binary = [
            node(0.0, 9.0, 1, 0),
            node(0.0, 1.0, 0, 2),
            node(2.0, 9.0, 3, 0),
            node(2.0, 3.0, 2, 1),
            node(4.0, 9.0, 3, 2),
        ];
        let wide = WideBvh::collapse(&binary);
        assert_eq!((wide.nodes.len(), wide.children.as_slice(), wide.depth), (1, &[3u8][..], 1));
        let root = &wide.nodes[0];
        // The leaf first, then the inner node's two children in its place and after.
        let lanes: Vec<(f32, f32, u32, u32)> =
            (0..3).map(|l| (root.lo[0][l], root.hi[2][l], root.index[l], root.count[l])).collect();
        assert_eq!(lanes, [(0.0, 1.0, 0, 2), (2.0, 3.0, 2, 1), (4.0, 9.0, 3, 2)]);
        assert!((3..WIDTH).all(|l| root.lo[1][l] == f32::INFINITY && root.hi[1][l] == f32::NEG_INFINITY));
        assert_eq!(wide.root, (Vec3A::ZERO, Vec3A::splat(9.0)));
    }
}
