//! The CPU accel: a binary BVH built by `obvhs` (PLOC, reinsertion, leaf collapsing), copied into a compact
//! depth-first node array, with the triangles reordered to match its leaves.

use std::any::Any;

use glam::Vec3;
use obvhs::aabb::Aabb;
use obvhs::bvh2::{Bvh2, leaf_collapser::collapse, reinsertion::ReinsertionOptimizer};
use obvhs::ploc::{PlocBuilder, PlocSearchDistance, SortPrecision};

use crate::accel::{BuildFlags, BuildOptions, MemoryUsage};
use crate::backend::BackendAccel;
use crate::geometry::{GatheredTriangles, GeometryFlags, TriangleRef, is_degenerate};

/// One BVH node, 32 bytes: `0 min.xyz f32×3 | 12 index u32 | 16 max.xyz f32×3 | 28 count u32`.
/// An inner node has `count` 0 and its two children at `index` and `index + 1`; a leaf holds triangles
/// `index .. index + count` of [`CpuAccel`]'s triangle arrays.
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C)]
pub(super) struct Node {
    /// Box minimum.
    pub min: Vec3,
    /// First child (inner node) or first triangle (leaf).
    pub index: u32,
    /// Box maximum.
    pub max: Vec3,
    /// Triangles in the leaf, 0 for an inner node.
    pub count: u32,
}

/// Bytes an accel needs besides its arrays: its own struct and the context's handle record around it.
const FIXED_BYTES: u64 = 1024;
/// The build's working memory per triangle: measured at 243–257 bytes on the shared meshes and random soups for
/// every preset (`tests/memory_usage.rs` prints it); 384 leaves a 1.5× margin.
const BUILD_TEMP_BYTES_PER_TRIANGLE: u64 = 384;
/// Working memory of a build that does not depend on its size (thread-local buffers, rayon bookkeeping).
const BUILD_TEMP_FIXED_BYTES: u64 = 4 << 20;

/// A BVH over triangles, ready to trace.
#[derive(Debug)]
pub struct CpuAccel {
    /// Depth-first nodes; empty when no triangle can be hit.
    pub(super) nodes: Vec<Node>,
    /// Triangle corners: first those of the leaves, in leaf order, then the degenerate ones (never traversed,
    /// kept for random vertex access).
    pub(super) corners: Vec<[Vec3; 3]>,
    /// Ids of each triangle, parallel to `corners`.
    pub(super) refs: Vec<TriangleRef>,
    /// Prime masks parallel to `corners`, when the build had masks.
    pub(super) masks: Option<Vec<u32>>,
    /// Flags of each geometry.
    pub(super) geometry_flags: Vec<GeometryFlags>,
    /// Longest root-to-leaf path, in nodes: the traversal stack's size.
    pub(super) depth: usize,
    /// With `ALLOW_RANDOM_VERTEX_ACCESS`: where each input triangle went.
    random_access: Option<RandomAccess>,
}

/// Maps (geometry id, primitive id) to a triangle's position in the accel.
#[derive(Debug)]
struct RandomAccess {
    /// Per geometry: its first triangle's index in input order, and its primitive-index offset.
    geometries: Vec<(u32, u32)>,
    /// Per triangle in input order: its index in `corners`.
    slots: Vec<u32>,
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
    // Spatial splits would make a triangle appear in several leaves; rayd keeps one reference per triangle.
    params.pre_split = false;
    params
}

/// Upper bounds of a build's memory for `triangles` triangles in `geometries` inputs.
pub(super) fn memory_bounds(triangles: usize, geometries: usize, masks: bool, options: &BuildOptions) -> MemoryUsage {
    let n = triangles as u64;
    let g = geometries as u64;
    let nodes = (2 * n).saturating_sub(1) * size_of::<Node>() as u64;
    let per_triangle = (size_of::<[Vec3; 3]>() + size_of::<TriangleRef>()) as u64 + if masks { 4 } else { 0 };
    let random_access = if options.flags.contains(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS) { 4 * n + 8 * g } else { 0 };
    let output_bytes = FIXED_BYTES + nodes + n * per_triangle + 4 * g + random_access;
    let temp_bytes = BUILD_TEMP_FIXED_BYTES + n * BUILD_TEMP_BYTES_PER_TRIANGLE;
    // An update recomputes triangle boxes and refits nodes bottom-up with a parent index per node.
    let temp_update_bytes =
        if options.flags.contains(BuildFlags::ALLOW_UPDATE) { n * 32 + 8 * n + FIXED_BYTES } else { 0 };
    MemoryUsage { output_bytes, temp_bytes, temp_update_bytes }
}

impl CpuAccel {
    /// Builds the BVH over gathered, validated triangles.
    pub fn build(triangles: GatheredTriangles, options: &BuildOptions) -> CpuAccel {
        let hittable: Vec<u32> =
            (0..triangles.len() as u32).filter(|&i| !is_degenerate(&triangles.vertices[i as usize])).collect();
        let boxes: Vec<Aabb> = hittable
            .iter()
            .map(|&i| {
                let [a, b, c] = triangles.vertices[i as usize];
                Aabb::new(a.min(b).min(c).into(), a.max(b).max(c).into())
            })
            .collect();
        let bvh = (!boxes.is_empty()).then(|| build_bvh2(&boxes, build_params(options.flags)));
        drop(boxes);
        Self::lay_out(&triangles, &hittable, bvh.as_ref(), options)
    }

    /// Copies the obvhs tree into depth-first [`Node`]s and the triangles into leaf order.
    fn lay_out(
        triangles: &GatheredTriangles,
        hittable: &[u32],
        bvh: Option<&Bvh2>,
        options: &BuildOptions,
    ) -> CpuAccel {
        let total = triangles.len();
        let mut order: Vec<u32> = Vec::with_capacity(total);
        let mut nodes = Vec::new();
        let mut depth = 0;
        if let Some(bvh) = bvh {
            nodes.reserve_exact(bvh.nodes.len());
            nodes.push(Node { min: Vec3::ZERO, index: 0, max: Vec3::ZERO, count: 0 });
            let mut pending = vec![(0usize, 0usize, 1usize)];
            while let Some((source, target, level)) = pending.pop() {
                let node = &bvh.nodes[source];
                let (min, max) = (node.aabb.min.into(), node.aabb.max.into());
                depth = depth.max(level);
                if node.prim_count == 0 {
                    let first = nodes.len();
                    nodes.push(nodes[target]);
                    nodes.push(nodes[target]);
                    nodes[target] = Node { min, index: first as u32, max, count: 0 };
                    pending.push((node.first_index as usize + 1, first + 1, level + 1));
                    pending.push((node.first_index as usize, first, level + 1));
                } else {
                    let start = order.len() as u32;
                    let leaf = node.first_index as usize..(node.first_index + node.prim_count) as usize;
                    order.extend(bvh.primitive_indices[leaf].iter().map(|&p| hittable[p as usize]));
                    nodes[target] = Node { min, index: start, max, count: node.prim_count };
                }
            }
        }
        let mut in_leaves = vec![false; total];
        for &i in &order {
            in_leaves[i as usize] = true;
        }
        order.extend((0..total as u32).filter(|&i| !in_leaves[i as usize]));
        let corners: Vec<[Vec3; 3]> = order.iter().map(|&i| triangles.vertices[i as usize]).collect();
        let refs: Vec<TriangleRef> = order.iter().map(|&i| triangles.refs[i as usize]).collect();
        let masks = triangles.masks.as_ref().map(|m| order.iter().map(|&i| m[i as usize]).collect());
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
        CpuAccel { nodes, corners, refs, masks, geometry_flags: triangles.geometry_flags.clone(), depth, random_access }
    }
}

/// Runs obvhs's PLOC builder, reinsertion optimizer and leaf collapser over the triangles' boxes.
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

impl BackendAccel for CpuAccel {
    fn size_bytes(&self) -> u64 {
        let bytes = |len: usize, size: usize| (len * size) as u64;
        let random_access =
            self.random_access.as_ref().map_or(0, |r| bytes(r.slots.capacity(), 4) + bytes(r.geometries.capacity(), 8));
        FIXED_BYTES
            + bytes(self.nodes.capacity(), size_of::<Node>())
            + bytes(self.corners.capacity(), size_of::<[Vec3; 3]>())
            + bytes(self.refs.capacity(), size_of::<TriangleRef>())
            + self.masks.as_ref().map_or(0, |m| bytes(m.capacity(), 4))
            + bytes(self.geometry_flags.capacity(), 4)
            + random_access
    }

    fn bounds(&self) -> (Vec3, Vec3) {
        self.corners.iter().flatten().fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &p| (lo.min(p), hi.max(p)))
    }

    fn triangle_vertices(&self, geom_id: u32, prim_id: u32) -> Option<[Vec3; 3]> {
        let access = self.random_access.as_ref()?;
        let &(first, offset) = access.geometries.get(geom_id as usize)?;
        let end = access.geometries.get(geom_id as usize + 1).map_or(access.slots.len() as u32, |g| g.0);
        let index = first.checked_add(prim_id.checked_sub(offset)?)?;
        (index < end).then(|| self.corners[access.slots[index as usize] as usize])
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}
