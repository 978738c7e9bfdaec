//! Collapsing a binary BVH into a wide one: each wide node takes its binary node's two children, then keeps
//! replacing the inner child of largest surface area by its two children while it has room. The CPU's 8-wide
//! nodes ([`super::wide`]) and the wgpu backend's 4-wide ones are both made from this.

use super::bvh::Node;

/// A lane no binary node is in.
pub(crate) const EMPTY_LANE: u32 = u32::MAX;

/// One lane of a wide node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Lane {
    /// The binary node in it, [`EMPTY_LANE`] when none.
    pub binary: u32,
    /// For an inner binary node: the wide node its subtree became; otherwise [`EMPTY_LANE`].
    pub child: u32,
}

/// A binary BVH collapsed to `width` lanes a node.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Collapsed {
    /// Lanes of the wide nodes, `width` a node, the root's first; a node's occupied lanes come before its empty
    /// ones. Empty when the binary BVH was.
    pub lanes: Vec<Lane>,
    /// Longest root-to-leaf path, in wide nodes.
    pub depth: usize,
    /// Entries a nearest-first walk's stack holds at most: over root-to-leaf paths, the sum of each node's occupied
    /// lanes but one (the lanes it leaves waiting).
    pub stack_need: usize,
}

/// Collapses a depth-first binary BVH into nodes of `width` (≥ 2) lanes. A binary root that is a leaf becomes the
/// one lane of the one wide node.
pub(crate) fn collapse(binary: &[Node], width: usize) -> Collapsed {
    assert!(width >= 2, "a wide node has at least two lanes");
    if binary.is_empty() {
        return Collapsed::default();
    }
    let empty = Lane { binary: EMPTY_LANE, child: EMPTY_LANE };
    let mut collapsed =
        Collapsed { lanes: Vec::with_capacity((binary.len() / 2 + 1) * width), depth: 0, stack_need: 0 };
    collapsed.lanes.resize(width, empty);
    let children = |n: usize| [binary[n].index as usize, binary[n].index as usize + 1];
    let area = |n: usize| {
        let d = binary[n].max - binary[n].min;
        d.x * d.y + d.y * d.z + d.z * d.x
    };
    // (binary node whose subtree a wide node holds, that wide node, its level, lanes left waiting above it)
    let mut pending = vec![(0usize, 0usize, 1usize, 0usize)];
    let mut lanes = Vec::with_capacity(width);
    while let Some((source, target, level, waiting)) = pending.pop() {
        collapsed.depth = collapsed.depth.max(level);
        lanes.clear();
        if binary[source].count > 0 {
            lanes.push(source);
        } else {
            lanes.extend(children(source));
        }
        while lanes.len() < width {
            let widest = (0..lanes.len())
                .filter(|&l| binary[lanes[l]].count == 0)
                .max_by(|&a, &b| area(lanes[a]).total_cmp(&area(lanes[b])));
            let Some(lane) = widest else { break };
            let inner = lanes.swap_remove(lane);
            lanes.extend(children(inner));
        }
        let waiting = waiting + lanes.len() - 1;
        collapsed.stack_need = collapsed.stack_need.max(waiting);
        for (lane, &n) in lanes.iter().enumerate() {
            let child = if binary[n].count > 0 {
                EMPTY_LANE
            } else {
                let child = collapsed.lanes.len() / width;
                collapsed.lanes.extend(std::iter::repeat_n(empty, width));
                pending.push((n, child, level + 1, waiting));
                child as u32
            };
            collapsed.lanes[target * width + lane] = Lane { binary: n as u32, child };
        }
    }
    collapsed
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    /// A complete depth-first binary tree of `leaves` (a power of two) unit-box leaves along x.
    fn complete(leaves: u32) -> Vec<Node> {
        fn build(binary: &mut Vec<Node>, at: usize, first: u32, leaves: u32) {
            if leaves == 1 {
                let x = first as f32;
                binary[at] =
                    Node { min: Vec3::new(x, 0.0, 0.0), index: first, max: Vec3::new(x + 1.0, 1.0, 1.0), count: 1 };
                return;
            }
            let child = binary.len();
            binary.push(binary[at]);
            binary.push(binary[at]);
            build(binary, child, first, leaves / 2);
            build(binary, child + 1, first + leaves / 2, leaves / 2);
            let (l, r) = (binary[child], binary[child + 1]);
            binary[at] = Node { min: l.min.min(r.min), index: child as u32, max: l.max.max(r.max), count: 0 };
        }
        let mut binary = vec![Node { min: Vec3::ZERO, index: 0, max: Vec3::ZERO, count: 0 }];
        build(&mut binary, 0, 0, leaves);
        binary
    }

    #[test]
    fn every_leaf_lands_in_one_lane_and_inner_lanes_name_their_wide_node() {
        let binary = complete(16);
        for (width, depth) in [(2, 4), (4, 2), (8, 2)] {
            let collapsed = collapse(&binary, width);
            assert_eq!(collapsed.depth, depth, "width {width}");
            // A complete tree: every node on a path is full but the last level's.
            let full_levels = (collapsed.lanes.len() / width).min(depth);
            assert!(collapsed.stack_need <= full_levels * (width - 1), "width {width}");
            assert!(collapsed.stack_need >= width - 1, "width {width}: the root leaves its other lanes waiting");
            let mut leaves = Vec::new();
            for node in collapsed.lanes.chunks(width) {
                let occupied = node.iter().take_while(|l| l.binary != EMPTY_LANE).count();
                assert!(node[occupied..].iter().all(|l| l.binary == EMPTY_LANE), "empty lanes come last");
                for lane in &node[..occupied] {
                    let binary_node = binary[lane.binary as usize];
                    if binary_node.count > 0 {
                        assert_eq!(lane.child, EMPTY_LANE);
                        leaves.push(binary_node.index);
                    } else {
                        // The wide node it became starts with one of its descendants.
                        let first = collapsed.lanes[lane.child as usize * width];
                        assert!(first.binary > lane.binary);
                    }
                }
            }
            leaves.sort();
            assert_eq!(leaves, (0..16).collect::<Vec<_>>(), "width {width}");
            assert!(collapsed.lanes[..width].iter().all(|l| l.binary != EMPTY_LANE), "the root is filled");
        }
    }

    #[test]
    fn a_leaf_root_is_one_lane_and_nothing_is_empty() {
        let leaf = [Node { min: Vec3::ZERO, index: 0, max: Vec3::ONE, count: 3 }];
        let collapsed = collapse(&leaf, 4);
        assert_eq!(collapsed.lanes[0], Lane { binary: 0, child: EMPTY_LANE });
        assert!(collapsed.lanes[1..].iter().all(|l| l.binary == EMPTY_LANE));
        assert_eq!((collapsed.depth, collapsed.stack_need), (1, 0));
        assert_eq!(collapse(&[], 4), Collapsed::default());
    }
}
