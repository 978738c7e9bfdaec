//! The BVH every CPU accel uses: built by `obvhs` (PLOC, reinsertion, leaf collapsing) over primitive boxes and
//! copied into a compact depth-first node array whose leaves index the primitives in leaf order.

use glam::{Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::bvh2::{Bvh2, leaf_collapser::collapse, reinsertion::ReinsertionOptimizer};
use obvhs::ploc::{PlocBuilder, PlocSearchDistance, SortPrecision};

use crate::accel::BuildFlags;
use crate::geometry::motion::{Bounds, EMPTY, KeyTime, lerp, time_average, union};

/// One BVH node, 32 bytes: `0 min.xyz f32×3 | 12 index u32 | 16 max.xyz f32×3 | 28 count u32`.
/// An inner node has `count` 0 and its two children at `index` and `index + 1`; a leaf holds primitives
/// `index .. index + count` of its accel's primitive arrays.
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C)]
pub(crate) struct Node {
    /// Box minimum.
    pub min: Vec3,
    /// First child (inner node) or first primitive (leaf).
    pub index: u32,
    /// Box maximum.
    pub max: Vec3,
    /// Primitives in the leaf, 0 for an inner node.
    pub count: u32,
}

impl Node {
    /// Half the surface area of the node's box.
    pub fn half_area(&self) -> f32 {
        let d = self.max - self.min;
        d.x * d.y + d.y * d.z + d.z * d.x
    }
}

/// Bytes an accel needs besides its arrays: its own struct and the context's handle record around it.
pub(super) const FIXED_BYTES: u64 = 1024;

/// How an accel's arrays are counted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Footprint {
    /// As allocated (capacity).
    Allocated,
    /// As an exact-size copy would allocate them (length): the compacted size.
    Exact,
}

/// The length and capacity of a vector, whatever its element.
pub(super) trait VecLen {
    /// Elements held.
    fn len(&self) -> usize;
    /// Elements allocated.
    fn capacity(&self) -> usize;
}

impl<T> VecLen for Vec<T> {
    fn len(&self) -> usize {
        Vec::len(self)
    }

    fn capacity(&self) -> usize {
        Vec::capacity(self)
    }
}

impl Footprint {
    /// Elements of `v` counted.
    pub(super) fn of(self, v: &dyn VecLen) -> usize {
        match self {
            Footprint::Allocated => v.capacity(),
            Footprint::Exact => v.len(),
        }
    }
}

/// A BVH laid out for traversal.
#[derive(Debug, Default)]
pub(super) struct Layout {
    /// Depth-first nodes; empty when there were no boxes.
    pub nodes: Vec<Node>,
    /// The caller's primitive indices in leaf order.
    pub order: Vec<u32>,
    /// Longest root-to-leaf path, in nodes.
    pub depth: usize,
}

/// The deepest a BVH may be, in nodes from the root to a leaf: traversal stacks, which every chunk of rays
/// allocates, are sized by the depth. SAH trees of millions of ordinary triangles are a few dozen deep; boxes nested
/// in each other (concentric triangles) made obvhs's trees as deep as their count, and such trees are built again
/// by median splits ([`Layout::build`]). Blobs of deeper trees are refused.
pub(crate) const MAX_DEPTH: usize = 1024;

/// Leaves of a tree built by median splits hold at most this many primitives.
const MEDIAN_SPLIT_LEAF: u32 = 4;

impl Layout {
    /// Builds a BVH over `boxes`, the boxes of the caller's primitives `primitives` (parallel to them), with leaves
    /// of at most `max_leaf` primitives (fewer as the builder's cost model finds best). Boxes whose scene's surface
    /// area overflows binary32 (finite coordinates far apart), whose costs and Morton codes obvhs computes as NaN
    /// (it panicked), and a tree deeper than [`MAX_DEPTH`] are built by median splits instead
    /// ([`Layout::median_split`]).
    pub fn build(boxes: &[Aabb], primitives: &[u32], flags: BuildFlags, max_leaf: u32) -> Layout {
        if boxes.is_empty() {
            return Layout::default();
        }
        let scene = boxes.iter().fold(Aabb::empty(), |scene, b| scene.union(b));
        if scene.half_area().is_finite() {
            let mut params = build_params(flags);
            params.max_prims_per_leaf = params.max_prims_per_leaf.min(max_leaf);
            let layout = Layout::from_bvh2(&build_bvh2(boxes, params), primitives);
            if layout.depth <= MAX_DEPTH {
                return layout;
            }
        }
        Layout::median_split(boxes, primitives, max_leaf.min(MEDIAN_SPLIT_LEAF))
    }

    /// The depth-first copy of obvhs's `bvh`, its leaves' indices mapped to `primitives`.
    fn from_bvh2(bvh: &Bvh2, primitives: &[u32]) -> Layout {
        let mut layout = Layout { nodes: Vec::with_capacity(bvh.nodes.len()), ..Layout::default() };
        layout.nodes.push(Node { min: Vec3::ZERO, index: 0, max: Vec3::ZERO, count: 0 });
        let mut pending = vec![(0usize, 0usize, 1usize)];
        while let Some((source, target, level)) = pending.pop() {
            let node = &bvh.nodes[source];
            let (min, max) = (node.aabb.min.into(), node.aabb.max.into());
            layout.depth = layout.depth.max(level);
            if node.prim_count == 0 {
                let first = layout.nodes.len();
                layout.nodes.push(layout.nodes[target]);
                layout.nodes.push(layout.nodes[target]);
                layout.nodes[target] = Node { min, index: first as u32, max, count: 0 };
                pending.push((node.first_index as usize + 1, first + 1, level + 1));
                pending.push((node.first_index as usize, first, level + 1));
            } else {
                let start = layout.order.len() as u32;
                let leaf = node.first_index as usize..(node.first_index + node.prim_count) as usize;
                layout.order.extend(bvh.primitive_indices[leaf].iter().map(|&p| primitives[p as usize]));
                layout.nodes[target] = Node { min, index: start, max, count: node.prim_count };
            }
        }
        layout
    }

    /// A BVH over `boxes` by median splits: each node's boxes split in half by their centres along the axis where
    /// the centres spread most, leaves of at most `max_leaf`. At most ⌈log2 n⌉ + 1 deep whatever the boxes, and
    /// computed with comparisons, minima and maxima only (no sums of coordinates that could overflow).
    fn median_split(boxes: &[Aabb], primitives: &[u32], max_leaf: u32) -> Layout {
        let centre = |i: u32| boxes[i as usize].min * 0.5 + boxes[i as usize].max * 0.5;
        let mut items: Vec<u32> = (0..boxes.len() as u32).collect();
        let mut layout = Layout { nodes: Vec::with_capacity(2 * boxes.len()), ..Layout::default() };
        layout.nodes.push(Node { min: Vec3::ZERO, index: 0, max: Vec3::ZERO, count: 0 });
        let mut pending = vec![(0..items.len(), 0usize, 1usize)];
        while let Some((range, target, level)) = pending.pop() {
            layout.depth = layout.depth.max(level);
            let here = &mut items[range.clone()];
            let bounds = here.iter().fold(Aabb::empty(), |b, &i| b.union(&boxes[i as usize]));
            let (min, max) = (bounds.min.into(), bounds.max.into());
            if here.len() <= max_leaf as usize {
                let start = layout.order.len() as u32;
                layout.order.extend(here.iter().map(|&i| primitives[i as usize]));
                layout.nodes[target] = Node { min, index: start, max, count: here.len() as u32 };
                continue;
            }
            let (low, high) = here.iter().fold((Vec3A::INFINITY, Vec3A::NEG_INFINITY), |(low, high), &i| {
                (low.min(centre(i)), high.max(centre(i)))
            });
            let spread = high - low;
            let axis = if spread.x >= spread.y && spread.x >= spread.z {
                0
            } else if spread.y >= spread.z {
                1
            } else {
                2
            };
            let half = here.len() / 2;
            here.select_nth_unstable_by(half, |&a, &b| centre(a)[axis].total_cmp(&centre(b)[axis]));
            let first = layout.nodes.len();
            layout.nodes.push(layout.nodes[target]);
            layout.nodes.push(layout.nodes[target]);
            layout.nodes[target] = Node { min, index: first as u32, max, count: 0 };
            pending.push((range.start + half..range.end, first + 1, level + 1));
            pending.push((range.start..range.start + half, first, level + 1));
        }
        layout
    }

    /// Appends the primitives of `0..total` that no leaf holds (those left out of the build) after the leaves' order,
    /// so that `order` places every primitive.
    pub fn append_unplaced(&mut self, total: usize) {
        let mut in_leaves = vec![false; total];
        for &i in &self.order {
            in_leaves[i as usize] = true;
        }
        self.order.extend((0..total as u32).filter(|&i| !in_leaves[i as usize]));
    }
}

/// The obvhs parameters for the build flags.
fn build_params(flags: BuildFlags) -> obvhs::BvhBuildParams {
    let mut params = if flags.contains(BuildFlags::PREFER_FAST_BUILD) {
        obvhs::BvhBuildParams::fast_build()
    } else if flags.contains(BuildFlags::PREFER_FAST_TRACE) {
        obvhs::BvhBuildParams::slow_build()
    } else {
        obvhs::BvhBuildParams::medium_build()
    };
    // Spatial splits would make a primitive appear in several leaves; rayd keeps one reference per primitive.
    params.pre_split = false;
    params
}

/// Runs obvhs's PLOC builder, reinsertion optimizer and leaf collapser over the primitives' boxes.
fn build_bvh2(boxes: &[Aabb], params: obvhs::BvhBuildParams) -> Bvh2 {
    let search_distance: PlocSearchDistance = params.ploc_search_distance;
    let precision: SortPrecision = params.sort_precision;
    let indices = (0..boxes.len() as u32).collect();
    let mut bvh = PlocBuilder::with_capacity(boxes.len()).build(
        search_distance,
        boxes,
        indices,
        precision,
        params.search_depth_threshold,
    );
    let mut optimizer = ReinsertionOptimizer::default();
    optimizer.run(&mut bvh, params.reinsertion_batch_ratio, None);
    collapse(&mut bvh, params.max_prims_per_leaf.clamp(1, 255), params.collapse_traversal_cost);
    optimizer.run(
        &mut bvh,
        params.reinsertion_batch_ratio * params.post_collapse_reinsertion_batch_ratio_multiplier,
        None,
    );
    bvh
}

/// Per-node boxes at each motion key of a motion BVH: node `i`'s box at key `k` is `boxes[i·keys + k]`. Between
/// keys a node's box is the interpolation of its two key boxes ([`NodeKeys::at`]), which holds its primitives
/// at that time because each leaf's key boxes do.
#[derive(Debug, Clone)]
pub(crate) struct NodeKeys {
    /// Motion keys, at least 2.
    pub keys: usize,
    /// The boxes, `keys` a node.
    pub boxes: Vec<Bounds>,
}

impl NodeKeys {
    /// Room for `nodes` nodes' boxes; [`refit`] fills them.
    pub fn new(nodes: usize, keys: usize) -> NodeKeys {
        NodeKeys { keys, boxes: vec![EMPTY; nodes * keys] }
    }

    /// Node `node`'s box at `at`.
    #[inline(always)]
    pub fn at(&self, node: u32, at: KeyTime) -> (Vec3A, Vec3A) {
        let first = node as usize * self.keys + at.segment;
        let (a, b) = (self.boxes[first], self.boxes[first + 1]);
        (lerp(a.0, b.0, at.fraction).into(), lerp(a.1, b.1, at.fraction).into())
    }

    /// The nodes of `binary` (whose key boxes these are) with each box their average over time ([`time_average`]):
    /// what a motion BVH's collapse ranks its choices by, as its binary tree was built over its items' averages.
    pub fn time_averaged(&self, binary: &[Node]) -> Vec<Node> {
        let at_keys = self.boxes.chunks(self.keys);
        binary
            .iter()
            .zip(at_keys)
            .map(|(node, boxes)| {
                let (min, max) = time_average(boxes.iter().copied());
                Node { min, max, ..*node }
            })
            .collect()
    }

    /// The root's box at each key (none for an empty BVH).
    pub fn root(&self) -> &[Bounds] {
        &self.boxes[..self.keys.min(self.boxes.len())]
    }
}

/// Recomputes every node's box bottom-up from its leaves' primitives: `leaf_bounds(slots, key)` bounds a leaf's
/// primitive slots at a key. Without `keys` each node's own box is its box (key 0); with them, each node's key
/// boxes are filled and its own box is their union (its box over all of time). Children always follow their
/// parent in the depth-first array, so a reverse sweep sees them first.
pub(super) fn refit(
    nodes: &mut [Node],
    mut keys: Option<&mut NodeKeys>,
    leaf_bounds: impl Fn(std::ops::Range<usize>, usize) -> Bounds,
) {
    for i in (0..nodes.len()).rev() {
        let node = nodes[i];
        let slots = node.index as usize..(node.index + node.count) as usize;
        let children = [node.index as usize, node.index as usize + 1];
        let (min, max) = match keys.as_deref_mut() {
            None if node.count > 0 => leaf_bounds(slots, 0),
            None => children.map(|c| (nodes[c].min, nodes[c].max)).into_iter().fold(EMPTY, union),
            Some(NodeKeys { keys, boxes }) => (0..*keys).fold(EMPTY, |all, k| {
                let b = if node.count > 0 {
                    leaf_bounds(slots.clone(), k)
                } else {
                    children.map(|c| boxes[c * *keys + k]).into_iter().fold(EMPTY, union)
                };
                boxes[i * *keys + k] = b;
                union(all, b)
            }),
        };
        nodes[i] = Node { min, max, ..node };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn leaves_hold_at_most_the_primitives_asked_for() {
        // 64 small boxes in a row, close enough together that the builder's cost model makes leaves of several.
        let boxes: Vec<Aabb> = (0..64)
            .map(|i| {
                let x = i as f32 * 0.1;
                Aabb::new(Vec3::new(x, 0.0, 0.0).into(), Vec3::new(x + 0.05, 0.05, 0.05).into())
            })
            .collect();
        let primitives: Vec<u32> = (100..164).collect();
        let largest = |max_leaf| {
            let layout = Layout::build(&boxes, &primitives, BuildFlags::empty(), max_leaf);
            let mut order = layout.order.clone();
            order.sort_unstable();
            assert_eq!(order, primitives, "every primitive in one leaf");
            layout.nodes.iter().map(|node| node.count).max().unwrap()
        };
        assert!(largest(u32::MAX) > 1, "the builder's own leaves hold several");
        assert_eq!(largest(1), 1);
    }

    /// Checks that `layout` over `boxes` is a tree whose leaves hold every primitive once and whose every node's box
    /// holds its children's (its primitives' for a leaf); returns its depth.
    fn checked(layout: &Layout, boxes: &[Aabb]) -> usize {
        let mut order = layout.order.clone();
        order.sort_unstable();
        assert_eq!(order, (0..boxes.len() as u32).collect::<Vec<_>>(), "every primitive in one leaf");
        let holds = |node: &Node, b: &Aabb| {
            Vec3A::from(node.min).cmple(b.min).all() && Vec3A::from(node.max).cmpge(b.max).all()
        };
        for node in &layout.nodes {
            let (first, count) = (node.index as usize, node.count as usize);
            let inside: Vec<Aabb> = match count {
                0 => layout.nodes[first..first + 2].iter().map(|c| Aabb::new(c.min.into(), c.max.into())).collect(),
                _ => layout.order[first..first + count].iter().map(|&p| boxes[p as usize]).collect(),
            };
            assert!(inside.iter().all(|b| holds(node, b)), "{node:?} does not hold {inside:?}");
        }
        layout.depth
    }

    #[test]
    fn nested_boxes_and_a_scene_wider_than_binary32_get_trees_of_bounded_depth() {
        // 100,000 boxes nested in each other: obvhs chained them, 99,993 deep (thousands deep with the patch to its
        // PLOC, past MAX_DEPTH: median splits); median splits are checked on their own too.
        let nested: Vec<Aabb> = (0..100_000)
            .map(|i| Aabb::new(Vec3A::splat(-1.0001f32.powi(i)), Vec3A::splat(1.0001f32.powi(i))))
            .collect();
        // Finite boxes spread over ±3.3e38: the scene's extent overflows, and obvhs panicked.
        let wide: Vec<Aabb> = (0..100_000)
            .map(|i| {
                let x = (i as f32 / 50_000.0 - 1.0) * 3.3e38;
                Aabb::new(Vec3A::new(x, 0.0, 0.0), Vec3A::new(x + 1e34, 1.0, 0.0))
            })
            .collect();
        for (name, boxes) in [("nested", nested), ("wide", wide)] {
            let primitives: Vec<u32> = (0..boxes.len() as u32).collect();
            for flags in [BuildFlags::empty(), BuildFlags::PREFER_FAST_BUILD, BuildFlags::PREFER_FAST_TRACE] {
                let depth = checked(&Layout::build(&boxes, &primitives, flags, u32::MAX), &boxes);
                assert!(depth <= 18, "{name}, {flags:?}: {depth} deep");
            }
            let depth = checked(&Layout::median_split(&boxes, &primitives, MEDIAN_SPLIT_LEAF), &boxes);
            assert_eq!(depth, 16, "{name}: 2^15 < 100,000 / 4 ≤ 2^16 leaves");
        }
    }
}
