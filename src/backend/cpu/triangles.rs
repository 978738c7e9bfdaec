//! The geometry accel of the CPU backend: a BVH over triangles, with the triangles reordered to match its
//! leaves.

use glam::Vec3;
use obvhs::aabb::Aabb;
use rayon::prelude::*;

use super::blocks::{CornerBlocks, Placement};
use super::bvh::{FIXED_BYTES, Footprint, Layout, Node, NodeKeys, VecLen, refit};
use super::moving_wide::MovingWideTree;
use super::wide::{WideBvh, WideNode, WideTree};
use crate::accel::{BuildFlags, BuildOptions, MemoryUsage};
use crate::error::{Error, Result};
use crate::geometry::motion::{Bounds, EMPTY, TimeSpan, time_average, union};
use crate::geometry::{
    GatheredTriangles, GeometryFlags, MotionOptions, TriangleRef, is_degenerate, is_degenerate_throughout,
};

/// The build's working memory per triangle: measured at 243–257 bytes on the shared meshes and random soups for
/// every preset (`tests/memory_usage.rs` prints it); 384 leaves a 1.5× margin.
const BUILD_TEMP_BYTES_PER_TRIANGLE: u64 = 384;
/// Working memory of a build that does not depend on its size (thread-local buffers, rayon bookkeeping).
const BUILD_TEMP_FIXED_BYTES: u64 = 4 << 20;

/// A BVH over triangles, ready to trace. Cloning it makes an exact-size copy.
#[derive(Debug, Clone)]
pub struct TriangleBvh {
    /// Depth-first nodes (with motion, each box is the node's box over all of time); empty when no triangle can
    /// be hit.
    pub(crate) nodes: Vec<Node>,
    /// With motion: each node's box at each key.
    pub(crate) node_keys: Option<NodeKeys>,
    /// Without motion: the nodes collapsed to 8 children a node, which traversal uses (empty with motion).
    pub(super) wide: WideBvh,
    /// With motion: the nodes collapsed to 8 children a node with their boxes at each key, which traversal uses
    /// (empty without motion).
    pub(super) moving: MovingWideTree,
    /// The motion options (static without motion).
    pub(crate) motion: MotionOptions,
    /// Triangle corners, `motion.keys` sets a triangle (slot `i`'s at key `k` at `i·keys + k`): first those of the
    /// leaves, in leaf order, then the degenerate ones of a static accel without `ALLOW_UPDATE` (never traversed,
    /// kept for random vertex access). An updatable or moving accel leaves no triangle out (an update may give one
    /// area; one degenerate at every key may have area in between); those of its leaves without area at any time
    /// are held collapsed, every corner at the first ([`TriangleBvh::collapse_degenerate`]), which no test hits.
    pub(crate) corners: Vec<[Vec3; 3]>,
    /// The first key's corners of the triangles held collapsed, by slot, where random vertex access needs them
    /// (not those whose corners are all one point already).
    pub(super) collapsed: Vec<(u32, [Vec3; 3])>,
    /// Ids of each triangle, parallel to `corners`.
    pub(crate) refs: Vec<TriangleRef>,
    /// Prime masks parallel to `corners`, when the build had masks.
    pub(crate) masks: Option<Vec<u32>>,
    /// Flags of each geometry.
    pub(crate) geometry_flags: Vec<GeometryFlags>,
    /// Longest root-to-leaf path, in nodes: the traversal stack's size.
    pub(crate) depth: usize,
    /// The box around every corner at every key.
    pub(super) bounds: Bounds,
    /// With `ALLOW_UPDATE`: the input index of the triangle in each slot, to refit with new positions.
    pub(super) update_order: Option<Vec<u32>>,
    /// With `ALLOW_RANDOM_VERTEX_ACCESS`: where each input triangle went.
    pub(super) random_access: Option<RandomAccess>,
}

/// Maps (geometry id, primitive id) to a triangle's position in the accel.
#[derive(Debug, Clone)]
pub(super) struct RandomAccess {
    /// Per geometry: its first triangle's index in input order, and its primitive-index offset.
    pub(super) geometries: Vec<(u32, u32)>,
    /// Per triangle in input order: its index in `corners`.
    pub(super) slots: Vec<u32>,
}

/// Upper bounds of a build's memory for `triangles` triangles in `geometries` inputs.
pub(super) fn memory_bounds(triangles: usize, geometries: usize, masks: bool, options: &BuildOptions) -> MemoryUsage {
    let n = triangles as u64;
    let g = geometries as u64;
    let keys = u64::from(options.motion.keys);
    let node_count = (2 * n).saturating_sub(1);
    let node_keys = if keys > 1 { keys * size_of::<Bounds>() as u64 } else { 0 };
    let nodes = node_count * (size_of::<Node>() as u64 + node_keys);
    // Static accels also collapse their nodes to wide ones, at most one for every leaf but three in seven.
    let wide_nodes = if keys > 1 { 0 } else { WideTree::most_nodes(triangles) as u64 };
    // … and copy their corners into blocks for the leaves' first test.
    let blocks = if keys > 1 { 0 } else { CornerBlocks::bytes_for(n) };
    // … with the ids (and masks) of the blocks' slots.
    let slots = if keys > 1 { 0 } else { Placement::most_slots(triangles) as u64 };
    let slot_ids = slots * (size_of::<TriangleRef>() as u64 + if masks { 4 } else { 0 });
    // Moving accels collapse theirs too, with their lanes' boxes at each key.
    let moving = if keys > 1 { MovingWideTree::most_bytes(n, keys) } else { 0 };
    let wide = wide_nodes * (size_of::<WideNode>() as u64 + 1) + blocks + slot_ids + moving;
    let per_triangle =
        (keys as usize * size_of::<[Vec3; 3]>() + size_of::<TriangleRef>()) as u64 + if masks { 4 } else { 0 };
    let random = options.flags.contains(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS);
    let updatable = options.flags.contains(BuildFlags::ALLOW_UPDATE);
    // With the first key's corners of every triangle held collapsed, at most.
    let collapsed = if holds_all(updatable, options.motion) { n * size_of::<(u32, [Vec3; 3])>() as u64 } else { 0 };
    let random_access = if random { 4 * n + 8 * g + collapsed } else { 0 };
    let update_order = if updatable { 4 * n } else { 0 };
    let output_bytes = FIXED_BYTES + nodes + wide + n * per_triangle + 4 * g + random_access + update_order;
    let temp_bytes = BUILD_TEMP_FIXED_BYTES + n * BUILD_TEMP_BYTES_PER_TRIANGLE;
    // An update gathers the new triangles (corners, ids, masks) and writes a refitted copy of the accel.
    let gathered = n * (per_triangle + 4) + 4 * g;
    // The copy it refits starts with the old version's collapsed corners too, until it collapses its own.
    let copied_collapsed = if random { collapsed } else { 0 };
    let temp_update_bytes = if updatable { output_bytes + gathered + copied_collapsed + FIXED_BYTES } else { 0 };
    MemoryUsage { output_bytes, temp_bytes, temp_update_bytes }
}

impl TriangleBvh {
    /// Builds the BVH over gathered, validated triangles, with `options.motion.keys` keys, asking `go_on` before
    /// each phase after the boxes whether to go on ([`Error::Stopped`] once it says no). A motion BVH's topology is
    /// built over each triangle's box on average over time ([`time_average`]); its nodes then get their boxes at
    /// each key.
    pub fn build(
        triangles: GatheredTriangles,
        options: &BuildOptions,
        go_on: &dyn Fn() -> bool,
    ) -> Result<TriangleBvh> {
        let phase = || if go_on() { Ok(()) } else { Err(Error::Stopped) };
        let all_placed = holds_all(options.flags.contains(BuildFlags::ALLOW_UPDATE), options.motion);
        let hittable: Vec<u32> = (0..triangles.len() as u32)
            .into_par_iter()
            .filter(|&i| all_placed || !is_degenerate(&triangles.vertices[i as usize]))
            .collect();
        let boxes: Vec<Aabb> = hittable
            .par_iter()
            .map(|&i| {
                let keys = triangles.corners(i as usize).iter().map(|key| corner_bounds(std::slice::from_ref(key)));
                let (min, max) = time_average(keys);
                Aabb::new(min.into(), max.into())
            })
            .collect();
        phase()?;
        let layout = Layout::build(&boxes, &hittable, options.flags, u32::MAX);
        drop(boxes);
        phase()?;
        let mut bvh = Self::lay_out(&triangles, layout, options);
        bvh.collapse_degenerate();
        if !options.motion.is_static() {
            bvh.node_keys = Some(NodeKeys::new(bvh.nodes.len(), triangles.keys));
            bvh.refit_nodes();
        }
        phase()?;
        bvh.collapse_wide();
        Ok(bvh)
    }

    /// Derives the wide nodes from the binary ones: with their corners in blocks for a static accel, with their boxes
    /// at each key for a moving one.
    pub(super) fn collapse_wide(&mut self) {
        (self.wide, self.moving) = match &self.node_keys {
            None => (
                WideBvh::collapse(&self.nodes, &self.corners, &self.refs, self.masks.as_deref()),
                MovingWideTree::default(),
            ),
            Some(keys) => (WideBvh::default(), MovingWideTree::collapse(&self.nodes, keys)),
        };
    }

    /// Stack entries a traversal needs: enough for a walk of the binary nodes and of any collapse of them
    /// ([`WideTree::stack_size_within`]), so that the versions updates make, whose moving wide trees are collapsed
    /// again from the refitted boxes (deeper where boxes degenerate), need no more than the build did: an instance
    /// accel keeps its child's stack size from its build.
    pub(super) fn stack_size(&self) -> usize {
        WideTree::stack_size_within(self.depth)
    }

    /// Holds collapsed, in `corners`, the triangles of an accel that leaves none out ([`holds_all`]) which have no
    /// area at any time, keeping their first key's corners for random vertex access, and makes `bounds` again.
    /// A collapsed triangle's edge functions are exactly 0 for every ray, on every path and device, so it is never
    /// hit; left as it was, a triangle of distinct collinear corners can be, its sheared corners rounded off the line.
    pub(super) fn collapse_degenerate(&mut self) {
        if !holds_all(self.update_order.is_some(), self.motion) {
            return;
        }
        let keep = self.random_access.is_some();
        self.collapsed = self
            .corners
            .par_chunks_mut(self.motion.keys as usize)
            .enumerate()
            .filter_map(|(slot, keys)| {
                let first = keys[0];
                let point = keys.iter().all(|[a, b, c]| a == b && b == c);
                if point || !is_degenerate_throughout(keys) {
                    return None;
                }
                keys.iter_mut().for_each(|key| *key = [key[0]; 3]);
                keep.then_some((slot as u32, first))
            })
            .collect();
        // Counted as allocated: no spare room.
        self.collapsed.shrink_to_fit();
        self.bounds = corner_bounds(&self.corners);
    }

    /// The corners with the first key's own corners of the triangles held collapsed, where they were kept: what
    /// a blob stores, from which [`TriangleBvh::collapse_degenerate`] makes the same accel again.
    pub(super) fn corners_as_given(&self) -> std::borrow::Cow<'_, [[Vec3; 3]]> {
        if self.collapsed.is_empty() {
            return std::borrow::Cow::Borrowed(&self.corners);
        }
        let mut corners = self.corners.clone();
        for &(slot, first) in &self.collapsed {
            corners[slot as usize * self.motion.keys as usize] = first;
        }
        std::borrow::Cow::Owned(corners)
    }

    /// Recomputes the nodes' boxes (and key boxes) from the corners.
    fn refit_nodes(&mut self) {
        let keys = self.motion.keys as usize;
        let corners = &self.corners;
        refit(&mut self.nodes, self.node_keys.as_mut(), |slots, k| {
            slots.map(|slot| corner_bounds(&corners[slot * keys + k..=slot * keys + k])).fold(EMPTY, union)
        });
    }

    /// Puts the triangles in leaf order (then the degenerate ones) beside the laid-out nodes.
    fn lay_out(triangles: &GatheredTriangles, mut layout: Layout, options: &BuildOptions) -> TriangleBvh {
        let total = triangles.len();
        layout.append_unplaced(total);
        let Layout { nodes, mut order, depth } = layout;
        // Gathered by rayon's threads: a random read a triangle, which one core would wait on alone.
        let mut corners = vec![[Vec3::ZERO; 3]; total * triangles.keys];
        corners
            .par_chunks_mut(triangles.keys)
            .zip(order.par_iter())
            .for_each(|(slot, &i)| slot.copy_from_slice(triangles.corners(i as usize)));
        let refs = gather(&order, &triangles.refs);
        let masks = triangles.masks.as_ref().map(|m| gather(&order, m));
        let random_access = options.flags.contains(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS).then(|| {
            let mut slots = vec![0u32; total];
            for (slot, &i) in order.iter().enumerate() {
                slots[i as usize] = slot as u32;
            }
            let mut geometries = Vec::with_capacity(triangles.geometry_flags.len());
            for (i, r) in triangles.refs.iter().enumerate() {
                if geometries.len() == r.geom_id as usize {
                    geometries.push((i as u32, r.prim_id));
                }
            }
            RandomAccess { geometries, slots }
        });
        let update_order = options.flags.contains(BuildFlags::ALLOW_UPDATE).then(|| {
            order.shrink_to_fit();
            order
        });
        TriangleBvh {
            nodes,
            node_keys: None,
            wide: WideBvh::default(),
            moving: MovingWideTree::default(),
            motion: options.motion,
            bounds: corner_bounds(&corners),
            corners,
            refs,
            masks,
            geometry_flags: triangles.geometry_flags.clone(),
            depth,
            random_access,
            update_order,
            collapsed: Vec::new(),
        }
    }

    /// A copy with the positions (and masks) of `triangles`, of the same structure, and its boxes refitted;
    /// `None` unless it was built with `ALLOW_UPDATE`. Its leaves hold every triangle: one without area, at the build
    /// or now, is held collapsed ([`TriangleBvh::collapse_degenerate`]) until an update gives it area.
    pub fn refit(&self, triangles: &GatheredTriangles) -> Option<TriangleBvh> {
        let order = self.update_order.as_ref()?;
        let mut next = self.clone();
        let keys = self.motion.keys as usize;
        for (slot, &i) in order.iter().enumerate() {
            next.corners[slot * keys..(slot + 1) * keys].copy_from_slice(triangles.corners(i as usize));
        }
        next.collapse_degenerate();
        if let (Some(masks), Some(new)) = (next.masks.as_mut(), triangles.masks.as_ref()) {
            for (slot, &i) in order.iter().enumerate() {
                masks[slot] = new[i as usize];
            }
        }
        next.refit_nodes();
        match &next.node_keys {
            None => next.wide = self.wide.refit(&next.nodes, &next.corners, next.masks.as_deref()),
            Some(keys) => next.moving = MovingWideTree::collapse(&next.nodes, keys),
        }
        Some(next)
    }

    /// Bytes it occupies: its arrays as allocated (`Footprint::Allocated`), or as an exact copy would allocate them.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        let bytes = |v: &dyn VecLen, size: usize| (footprint.of(v) * size) as u64;
        let random_access = self.random_access.as_ref().map_or(0, |r| bytes(&r.slots, 4) + bytes(&r.geometries, 8));
        let update_order = self.update_order.as_ref().map_or(0, |o| bytes(o, 4));
        FIXED_BYTES
            + bytes(&self.nodes, size_of::<Node>())
            + self.wide.size_bytes(footprint)
            + self.moving.size_bytes(footprint)
            + self.node_keys.as_ref().map_or(0, |k| bytes(&k.boxes, size_of::<Bounds>()))
            + bytes(&self.corners, size_of::<[Vec3; 3]>())
            + bytes(&self.refs, size_of::<TriangleRef>())
            + self.masks.as_ref().map_or(0, |m| bytes(m, 4))
            + bytes(&self.geometry_flags, 4)
            + random_access
            + update_order
            + bytes(&self.collapsed, size_of::<(u32, [Vec3; 3])>())
    }

    /// A box around every triangle at every time of `span`.
    pub fn bounds_during(&self, span: TimeSpan) -> Bounds {
        match &self.node_keys {
            Some(keys) if !keys.boxes.is_empty() => self.motion.bounds_of_keys(keys.root(), span),
            _ => self.bounds,
        }
    }

    /// The corners of a triangle (at the first key, with motion), with random vertex access.
    pub fn triangle_vertices(&self, geom_id: u32, prim_id: u32) -> Option<[Vec3; 3]> {
        let access = self.random_access.as_ref()?;
        let &(first, offset) = access.geometries.get(geom_id as usize)?;
        let end = access.geometries.get(geom_id as usize + 1).map_or(access.slots.len() as u32, |g| g.0);
        let index = first.checked_add(prim_id.checked_sub(offset)?)?;
        let slot = *access.slots.get(index as usize).filter(|_| index < end)?;
        match self.collapsed.binary_search_by_key(&slot, |&(collapsed, _)| collapsed) {
            Ok(at) => Some(self.collapsed[at].1),
            Err(_) => Some(self.corners[slot as usize * self.motion.keys as usize]),
        }
    }
}

/// Whether an accel places every triangle in its leaves, degenerate ones too: an `updatable` one (an update may give
/// them area) or one with `motion` (a triangle degenerate at every key may have area in between).
fn holds_all(updatable: bool, motion: MotionOptions) -> bool {
    updatable || !motion.is_static()
}

/// `items` in the order of `order` (indices into them), gathered by rayon's threads into a vector of exactly their
/// number (an accel's arrays count as allocated: [`Footprint::Allocated`]).
fn gather<T: Copy + Send + Sync>(order: &[u32], items: &[T]) -> Vec<T> {
    let mut gathered = Vec::with_capacity(order.len());
    order.par_iter().map(|&i| items[i as usize]).collect_into_vec(&mut gathered);
    gathered
}

/// The box around a run of triangles' corners.
pub(super) fn corner_bounds(corners: &[[Vec3; 3]]) -> Bounds {
    corners.iter().flatten().fold(EMPTY, |acc, &p| union(acc, (p, p)))
}
