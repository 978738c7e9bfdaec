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
use crate::geometry::{GatheredTriangles, GeometryFlags, MotionOptions, TriangleRef, is_degenerate};

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
    /// leaves, in leaf order, then the degenerate ones (never traversed, kept for random vertex access). With
    /// motion no triangle is left out: one degenerate at every key may have area in between.
    pub(crate) corners: Vec<[Vec3; 3]>,
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
    let random_access = if options.flags.contains(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS) { 4 * n + 8 * g } else { 0 };
    let updatable = options.flags.contains(BuildFlags::ALLOW_UPDATE);
    let update_order = if updatable { 4 * n } else { 0 };
    let output_bytes = FIXED_BYTES + nodes + wide + n * per_triangle + 4 * g + random_access + update_order;
    let temp_bytes = BUILD_TEMP_FIXED_BYTES + n * BUILD_TEMP_BYTES_PER_TRIANGLE;
    // An update gathers the new triangles (corners, ids, masks) and writes a refitted copy of the accel.
    let gathered = n * (per_triangle + 4) + 4 * g;
    let temp_update_bytes = if updatable { output_bytes + gathered + FIXED_BYTES } else { 0 };
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
        let moving = !options.motion.is_static();
        let hittable: Vec<u32> = (0..triangles.len() as u32)
            .into_par_iter()
            .filter(|&i| moving || !is_degenerate(&triangles.vertices[i as usize]))
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
        if moving {
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

    /// Stack entries a traversal needs.
    pub(super) fn stack_size(&self) -> usize {
        (self.depth + 1).max(self.wide.stack_size()).max(self.moving.stack_size())
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
        }
    }

    /// A copy with the positions (and masks) of `triangles`, of the same structure, and its boxes refitted;
    /// `None` unless it was built with `ALLOW_UPDATE`. Triangles degenerate at the build stay out of the leaves.
    pub fn refit(&self, triangles: &GatheredTriangles) -> Option<TriangleBvh> {
        let order = self.update_order.as_ref()?;
        let mut next = self.clone();
        let keys = self.motion.keys as usize;
        for (slot, &i) in order.iter().enumerate() {
            next.corners[slot * keys..(slot + 1) * keys].copy_from_slice(triangles.corners(i as usize));
        }
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
        next.bounds = corner_bounds(&next.corners);
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
        (index < end).then(|| self.corners[access.slots[index as usize] as usize * self.motion.keys as usize])
    }
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
