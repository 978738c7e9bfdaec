//! Stack-based traversal of the CPU BVH: nearer child first, boxes tested against the collector's current cull
//! distance, popped entries re-checked against it.

use glam::Vec3A;

use super::CpuAccel;
use crate::intersect::{PreparedRay, aabb};
use crate::query::{Collector, TraceStats, TriangleCandidate, consider_triangle};

/// A node waiting on the traversal stack, with the distance at which the ray enters its box.
pub(crate) type StackEntry = (u32, f32);

impl CpuAccel {
    /// A traversal stack deep enough for this BVH.
    pub(crate) fn new_stack(&self) -> Vec<StackEntry> {
        vec![(0, 0.0); self.depth + 1]
    }

    /// Offers every triangle whose leaf the ray reaches to `collector`, until it is done.
    #[inline]
    pub(crate) fn traverse(
        &self,
        stack: &mut [StackEntry],
        ray: &PreparedRay,
        collector: &mut Collector<'_>,
        stats: &mut TraceStats,
    ) {
        let Some(root) = self.nodes.first() else {
            return;
        };
        let test = |node: &super::bvh::Node, tmax: f32| {
            aabb::intersect(ray, Vec3A::from(node.min), Vec3A::from(node.max), ray.tmin, tmax)
        };
        stats.nodes_visited += 1;
        if test(root, collector.cull_tmax()).is_none() {
            return;
        }
        let mut len = 0usize;
        let mut current = 0u32;
        loop {
            let node = &self.nodes[current as usize];
            let mut next = None;
            if node.count > 0 {
                let first = node.index as usize;
                for slot in first..first + node.count as usize {
                    stats.triangle_tests += 1;
                    let id = self.refs[slot];
                    let candidate = TriangleCandidate {
                        corners: &self.corners[slot],
                        id,
                        mask: self.masks.as_ref().map_or(0, |m| m[slot]),
                        geometry_flags: self.geometry_flags[id.geom_id as usize],
                    };
                    consider_triangle(ray, &candidate, collector);
                    if collector.done() {
                        return;
                    }
                }
            } else {
                let tmax = collector.cull_tmax();
                let (left, right) = (node.index, node.index + 1);
                stats.nodes_visited += 2;
                let near_left = test(&self.nodes[left as usize], tmax);
                let near_right = test(&self.nodes[right as usize], tmax);
                next = match (near_left, near_right) {
                    (Some(l), Some(r)) => {
                        let (first, second) = if r < l { ((right, r), (left, l)) } else { ((left, l), (right, r)) };
                        stack[len] = second;
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
                    let (node, near) = stack[len];
                    if near <= collector.cull_tmax() {
                        break node;
                    }
                },
            };
        }
    }
}
