//! The CPU backend's payload in a blob (see [`crate::serialize`]): its accels' arrays as they are, and their
//! careful reading back. Every length, index and range is checked so that traversal, refits and random vertex
//! access stay in bounds and terminate; depths, stack sizes, the wide nodes (with a static accel's corner blocks), a
//! geometry accel's bounds and an instance accel's child boxes are made again from what was read, placements
//! re-derived from their matrices. Triangle corners must be finite, as a build's vertices must. Node boxes, key
//! boxes and an instance accel's bounds are taken as stored (a build over coordinates near `f32::MAX` can write NaN
//! ones, which must load again): wrong ones make a blob trace wrongly, never out of bounds.
//!
//! Layout version [`LAYOUT_VERSION`], using the blob's arrays and optional parts. A geometry accel:
//!
//! 1. array of nodes, 32 bytes each: `f32` min.xyz, `u32` index, `f32` max.xyz, `u32` count (as [`Node`]);
//! 2. array of node key boxes (motion only: nodes × keys, node-major), 24 bytes each: `f32` min.xyz, max.xyz;
//! 3. array of triangle corners, slots × keys (slot-major), 36 bytes each: 3 × `f32` xyz (as given: a triangle held
//!    collapsed has its first key's own corners, where random vertex access kept them, and is collapsed again when
//!    read, as a build collapses it);
//! 4. array of triangle ids, one a slot, 8 bytes each: `u32` geometry id, `u32` primitive id;
//! 5. optional array of `u32` masks, one a slot;
//! 6. array of `u32` geometry flags, one a geometry;
//! 7. optional random vertex access: an array of `u32` pairs (first triangle, primitive-index offset) per
//!    geometry, then an array of `u32` slots, one per triangle in input order;
//! 8. optional array of `u32` update order (the input triangle of each slot).
//!
//! An instance accel:
//!
//! 1. and 2. nodes and node key boxes, as above;
//! 3. array of instances, 64 bytes each: 12 `f32` object-to-world rows (as [`crate::geometry::Instance`] takes
//!    them), `u32` instance id, `u32` mask (0–255), `u32` instance flags, `u32` child (a position in the
//!    entry's child references);
//! 4. its bounds, 24 bytes: `f32` min.xyz, max.xyz;
//! 5. optional array of `u32` update order (the input instance of each slot).

use std::collections::HashMap;
use std::sync::Arc;

use glam::Vec3;

use super::CpuAccel;
use super::bvh::{MAX_DEPTH, Node, NodeKeys};
use super::instances::{InstanceBvh, child_boxes, cpu_child};
use super::moving_wide::MovingWideTree;
use super::triangles::{RandomAccess, TriangleBvh, corner_bounds};
use super::wide::{WideBvh, WideTree};
use crate::accel::{AccelKind, BuildFlags, BuildOptions};
use crate::backend::Shape;
use crate::context::Accel;
use crate::error::{Error, Result};
use crate::geometry::motion::Bounds;
use crate::geometry::{GatheredTriangles, GeometryFlags, InstanceFlags, PlacedInstance, Placement, TriangleRef};
use crate::serialize::wire::{Reader, Wire, f32_at, invalid, put, put_array, put_optional, u32_at};

/// The version of this layout: bump it whenever the layout or the structures it encodes change.
pub(super) const LAYOUT_VERSION: u32 = 1;

impl Wire for Node {
    const SIZE: usize = 32;

    fn put(&self, bytes: &mut [u8]) {
        self.min.put(&mut bytes[..12]);
        self.index.put(&mut bytes[12..16]);
        self.max.put(&mut bytes[16..28]);
        self.count.put(&mut bytes[28..32]);
    }

    fn get(bytes: &[u8]) -> Self {
        Node {
            min: Vec3::get(&bytes[..12]),
            index: u32_at(bytes, 12),
            max: Vec3::get(&bytes[16..28]),
            count: u32_at(bytes, 28),
        }
    }
}

impl Wire for TriangleRef {
    const SIZE: usize = 8;

    fn put(&self, bytes: &mut [u8]) {
        (self.geom_id, self.prim_id).put(bytes);
    }

    fn get(bytes: &[u8]) -> Self {
        TriangleRef { geom_id: u32_at(bytes, 0), prim_id: u32_at(bytes, 4) }
    }
}

/// An instance as the payload stores it.
struct StoredInstance {
    /// Object-to-world rows.
    rows: [f32; 12],
    /// The user's id.
    instance_id: u32,
    /// Visibility mask (8 bits).
    mask: u32,
    /// Instance flags.
    flags: u32,
    /// Position of its child among the accel's children.
    child: u32,
}

impl Wire for StoredInstance {
    const SIZE: usize = 64;

    fn put(&self, bytes: &mut [u8]) {
        self.rows.put(&mut bytes[..48]);
        for (i, word) in [self.instance_id, self.mask, self.flags, self.child].into_iter().enumerate() {
            word.put(&mut bytes[48 + 4 * i..52 + 4 * i]);
        }
    }

    fn get(bytes: &[u8]) -> Self {
        StoredInstance {
            rows: std::array::from_fn(|i| f32_at(bytes, 4 * i)),
            instance_id: u32_at(bytes, 48),
            mask: u32_at(bytes, 52),
            flags: u32_at(bytes, 56),
            child: u32_at(bytes, 60),
        }
    }
}

impl StoredInstance {
    /// The instance, checked, placing one of `children`; the error says what is wrong.
    fn placed(&self, children: &[Arc<Accel>]) -> std::result::Result<PlacedInstance, String> {
        let child = children.get(self.child as usize).ok_or(format!("child {} of {}", self.child, children.len()))?;
        Ok(PlacedInstance {
            placement: Placement::new(&self.rows).ok_or("transform not finite and invertible")?,
            instance_id: self.instance_id,
            mask: u8::try_from(self.mask).map_err(|_| format!("mask {:#x} wider than 8 bits", self.mask))?,
            flags: InstanceFlags::from_bits(self.flags).ok_or(format!("unknown flags {:#x}", self.flags))?,
            child: Arc::clone(child),
        })
    }
}

impl CpuAccel {
    /// Appends its payload; instances name their children by position in `children`.
    pub(super) fn encode_payload(&self, children: &[Arc<Accel>], out: &mut Vec<u8>) -> Result<()> {
        match self {
            CpuAccel::Triangles(bvh) => bvh.encode(out),
            CpuAccel::Instances(bvh) => bvh.encode(children, out)?,
            CpuAccel::Transform(_) => {}
        }
        Ok(())
    }

    /// Reads the payload of an accel of `shape` built with `options`, placing `children`.
    pub(super) fn decode_payload(
        shape: &Shape,
        options: &BuildOptions,
        payload: &[u8],
        children: &[Arc<Accel>],
    ) -> Result<CpuAccel> {
        let mut reader = Reader::new(payload);
        let accel = match shape.kind {
            AccelKind::Triangles => CpuAccel::Triangles(Box::new(TriangleBvh::decode(&mut reader, shape, options)?)),
            AccelKind::Instances => CpuAccel::Instances(InstanceBvh::decode(&mut reader, shape, options, children)?),
            kind => return Err(invalid(format!("a {kind:?} accel has no CPU payload"))),
        };
        reader.finish("the CPU payload")?;
        Ok(accel)
    }
}

/// Appends a BVH's nodes and node key boxes (none without motion).
fn put_nodes(out: &mut Vec<u8>, nodes: &[Node], keys: Option<&NodeKeys>) {
    put_array(out, nodes);
    put_array(out, keys.map_or(&[][..], |k| &k.boxes));
}

/// Reads a BVH's nodes over `slots` primitive slots and its key boxes for `options`' motion, and checks them
/// ([`check_nodes`]); returns them with the BVH's depth.
fn read_nodes(
    reader: &mut Reader<'_>,
    slots: usize,
    options: &BuildOptions,
) -> Result<(Vec<Node>, Option<NodeKeys>, usize)> {
    let nodes: Vec<Node> = reader.array("nodes")?;
    let boxes: Vec<Bounds> = reader.array("node key boxes")?;
    let keys = options.motion.keys as usize;
    let expected = if keys > 1 { nodes.len() * keys } else { 0 };
    if boxes.len() != expected {
        return Err(invalid(format!("{} node key boxes for {} nodes of {keys} keys", boxes.len(), nodes.len())));
    }
    let node_keys = (keys > 1).then_some(NodeKeys { keys, boxes });
    let depth = check_nodes(&nodes, slots)?;
    Ok((nodes, node_keys, depth))
}

/// Checks a depth-first node array over `slots` primitive slots: each inner node's children (at `index` and
/// `index + 1`) come after it in the array, every node but the root is the child of exactly one node (so the
/// nodes form one tree), each leaf's primitives lie within the slots, no slot in two leaves (the wide BVH
/// copies each leaf's triangles into blocks of its own: [`super::blocks::Placement`]), and no node lies deeper than
/// [`MAX_DEPTH`] (which rayd's builds keep to). Returns the longest root-to-leaf path, in nodes (what the traversal
/// stack is sized by).
fn check_nodes(nodes: &[Node], slots: usize) -> Result<usize> {
    if nodes.len() > u32::MAX as usize {
        return Err(invalid(format!("{} nodes, more than a u32 index reaches", nodes.len())));
    }
    // Each node's level (the root's is 1), set by its parent; 0 until then.
    let mut level = vec![0u32; nodes.len()];
    if let Some(root) = level.first_mut() {
        *root = 1;
    }
    let mut depth = 0;
    // The leaves' slot ranges and nodes, to check that no two share a slot (sized by the nodes, which the blob holds,
    // not by `slots`, which it only claims).
    let mut leaves = Vec::new();
    for (i, node) in nodes.iter().enumerate() {
        let here = level[i];
        if here == 0 {
            return Err(invalid(format!("node {i} is the child of no node before it")));
        }
        if here as usize > MAX_DEPTH {
            return Err(invalid(format!("node {i} is {here} nodes deep; a BVH may be at most {MAX_DEPTH}")));
        }
        depth = depth.max(here);
        if node.count > 0 {
            if node.index.checked_add(node.count).is_none_or(|end| end as usize > slots) {
                return Err(invalid(format!(
                    "leaf node {i} holds primitives {}..+{} of {slots}",
                    node.index, node.count
                )));
            }
            leaves.push((node.index, node.index + node.count, i));
            continue;
        }
        let first = node.index as usize;
        if first <= i || first + 1 >= nodes.len() {
            return Err(invalid(format!("inner node {i} of {} has children at {first}", nodes.len())));
        }
        for child in [first, first + 1] {
            if level[child] != 0 {
                return Err(invalid(format!("node {child} is the child of two nodes")));
            }
            level[child] = here + 1;
        }
    }
    leaves.sort_unstable();
    if let Some(pair) = leaves.windows(2).find(|pair| pair[1].0 < pair[0].1) {
        let ((_, _, first), (shared, _, second)) = (pair[0], pair[1]);
        return Err(invalid(format!("leaf node {second} holds slot {shared}, which leaf node {first} holds")));
    }
    Ok(depth as usize)
}

/// The triangles of an accel's slots (`corners`, `refs`, `masks`, `keys` corners a slot) in the order of its build
/// input, which `order` gives (a checked permutation: the input index of each slot).
fn in_input_order(
    order: &[u32],
    keys: usize,
    corners: &[[Vec3; 3]],
    refs: &[TriangleRef],
    masks: Option<&[u32]>,
    geometry_flags: Vec<GeometryFlags>,
) -> GatheredTriangles {
    let mut vertices = vec![[Vec3::ZERO; 3]; corners.len()];
    let (mut input_refs, mut input_masks) = (refs.to_vec(), masks.map(<[u32]>::to_vec));
    for (slot, &input) in order.iter().enumerate() {
        let input = input as usize;
        vertices[input * keys..(input + 1) * keys].copy_from_slice(&corners[slot * keys..(slot + 1) * keys]);
        input_refs[input] = refs[slot];
        if let (Some(input_masks), Some(masks)) = (input_masks.as_mut(), masks) {
            input_masks[input] = masks[slot];
        }
    }
    GatheredTriangles { keys, vertices, refs: input_refs, masks: input_masks, geometry_flags }
}

/// Checks that `order` (the input index of each of `slots` slots) is a permutation of `0..slots`.
fn check_update_order(order: &[u32], slots: usize) -> Result<()> {
    if order.len() != slots {
        return Err(invalid(format!("an update order of {} entries for {slots} slots", order.len())));
    }
    let mut seen = vec![false; slots];
    for (slot, &input) in order.iter().enumerate() {
        match seen.get_mut(input as usize) {
            Some(seen) if !*seen => *seen = true,
            _ => return Err(invalid(format!("update order slot {slot}: input {input} out of range or repeated"))),
        }
    }
    Ok(())
}

/// Checks that an optional part is there exactly when `flag` is among `options`' flags.
fn check_presence<T>(part: &Option<T>, options: &BuildOptions, flag: BuildFlags, what: &str) -> Result<()> {
    let wanted = options.flags.contains(flag);
    if part.is_some() != wanted {
        return Err(invalid(format!(
            "{what} is {} but the accel was built {} {flag:?}",
            if part.is_some() { "present" } else { "absent" },
            if wanted { "with" } else { "without" }
        )));
    }
    Ok(())
}

/// Fails unless `found` elements of `what` are the `expected`.
fn check_len(what: &str, found: usize, expected: u64) -> Result<()> {
    if found as u64 != expected {
        return Err(invalid(format!("{found} {what} where {expected} are expected")));
    }
    Ok(())
}

impl TriangleBvh {
    /// Appends the payload of a geometry accel.
    fn encode(&self, out: &mut Vec<u8>) {
        put_nodes(out, &self.nodes, self.node_keys.as_ref());
        put_array(out, &self.corners_as_given());
        put_array(out, &self.refs);
        put_optional(out, self.masks.as_ref(), |out, masks| put_array(out, masks));
        put_array(out, &self.geometry_flags.iter().map(|f| f.bits()).collect::<Vec<_>>());
        put_optional(out, self.random_access.as_ref(), |out, access| {
            put_array(out, &access.geometries);
            put_array(out, &access.slots);
        });
        put_optional(out, self.update_order.as_ref(), |out, order| put_array(out, order));
    }

    /// Reads and checks the payload of a geometry accel of `shape` built with `options`.
    fn decode(reader: &mut Reader<'_>, shape: &Shape, options: &BuildOptions) -> Result<TriangleBvh> {
        let keys = options.motion.keys as usize;
        let slots = usize::try_from(shape.triangle_count)
            .map_err(|_| invalid(format!("{} triangles", shape.triangle_count)))?;
        let (nodes, node_keys, depth) = read_nodes(reader, slots, options)?;
        let corners: Vec<[Vec3; 3]> = reader.array("corners")?;
        check_len("corners", corners.len(), (slots as u64).saturating_mul(keys as u64))?;
        if let Some(i) = corners.iter().position(|triangle| !triangle.iter().all(|corner| corner.is_finite())) {
            return Err(invalid(format!("slot {}, key {}: a corner is not finite", i / keys, i % keys)));
        }
        let refs: Vec<TriangleRef> = reader.array("triangle ids")?;
        check_len("triangle ids", refs.len(), shape.triangle_count)?;
        let masks: Option<Vec<u32>> = reader.optional("masks", |r| r.array("masks"))?;
        if let Some(masks) = &masks {
            check_len("masks", masks.len(), shape.triangle_count)?;
        }
        let flags: Vec<u32> = reader.array("geometry flags")?;
        check_len("geometry flags", flags.len(), u64::from(shape.geometry_count))?;
        if let Some(g) = flags.iter().position(|&f| GeometryFlags::from_bits(f).is_none()) {
            return Err(invalid(format!("geometry {g}: unknown flags {:#x}", flags[g])));
        }
        let geometry_flags: Vec<GeometryFlags> = flags.into_iter().map(GeometryFlags::from_bits_retain).collect();
        if let Some((slot, r)) = refs.iter().enumerate().find(|(_, r)| r.geom_id >= shape.geometry_count) {
            return Err(invalid(format!("slot {slot}: geometry id {} of {}", r.geom_id, shape.geometry_count)));
        }
        let random_access = reader.optional("random vertex access", |r| {
            Ok(RandomAccess {
                geometries: r.array("random access geometries")?,
                slots: r.array("random access slots")?,
            })
        })?;
        check_presence(&random_access, options, BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS, "random vertex access")?;
        if let Some(access) = &random_access {
            check_random_access(access, slots, shape.geometry_count)?;
        }
        let update_order: Option<Vec<u32>> = reader.optional("update order", |r| r.array("update order"))?;
        check_presence(&update_order, options, BuildFlags::ALLOW_UPDATE, "update order")?;
        if let Some(order) = &update_order {
            check_update_order(order, slots)?;
        }
        let placed: usize = nodes.iter().filter(|node| node.count > 0).map(|node| node.count as usize).sum();
        if let Some(order) = update_order.as_ref().filter(|_| placed < slots) {
            // Written by a rayd that left an updatable accel's degenerate triangles out of its leaves (before
            // 2026-12-07): laid out again, as a build of its triangles now would be, so that an update can give them
            // area.
            let triangles = in_input_order(order, keys, &corners, &refs, masks.as_deref(), geometry_flags);
            return TriangleBvh::build(triangles, options, &|| true);
        }
        let mut bvh = TriangleBvh {
            nodes,
            node_keys,
            wide: WideBvh::default(),
            moving: MovingWideTree::default(),
            motion: options.motion,
            bounds: corner_bounds(&corners),
            corners,
            refs,
            masks,
            geometry_flags,
            depth,
            update_order,
            random_access,
            collapsed: Vec::new(),
        };
        bvh.collapse_degenerate();
        bvh.collapse_wide();
        Ok(bvh)
    }
}

/// Checks random vertex access over `slots` slots and `geometries` geometries: at most one entry a geometry, their
/// first triangles in order and within the triangles, one slot a triangle, each within the slots.
fn check_random_access(access: &RandomAccess, slots: usize, geometries: u32) -> Result<()> {
    if access.geometries.len() > geometries as usize {
        return Err(invalid(format!("random access over {} geometries of {geometries}", access.geometries.len())));
    }
    check_len("random access slots", access.slots.len(), slots as u64)?;
    let mut previous = 0;
    for (g, &(first, _)) in access.geometries.iter().enumerate() {
        if first < previous || first as usize > slots {
            return Err(invalid(format!("random access geometry {g} starts at triangle {first}")));
        }
        previous = first;
    }
    if let Some(i) = access.slots.iter().position(|&s| s as usize >= slots) {
        return Err(invalid(format!("random access triangle {i} in slot {} of {slots}", access.slots[i])));
    }
    Ok(())
}

impl InstanceBvh {
    /// Appends the payload of an instance accel, its instances naming their children by position in `children`.
    fn encode(&self, children: &[Arc<Accel>], out: &mut Vec<u8>) -> Result<()> {
        let positions: HashMap<*const Accel, u32> =
            children.iter().enumerate().map(|(i, c)| (Arc::as_ptr(c), i as u32)).collect();
        let stored = self
            .instances
            .iter()
            .map(|instance| {
                let child = positions.get(&Arc::as_ptr(&instance.child)).copied().ok_or_else(|| {
                    Error::FailedPrecondition(format!(
                        "accel {} is placed by an instance but is not among the accel's children",
                        instance.child.handle().0
                    ))
                })?;
                Ok(StoredInstance {
                    rows: Placement::rows(&instance.placement.object_to_world),
                    instance_id: instance.instance_id,
                    mask: u32::from(instance.mask),
                    flags: instance.flags.bits(),
                    child,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        put_nodes(out, &self.nodes, self.node_keys.as_ref());
        put_array(out, &stored);
        put(out, &self.bounds);
        put_optional(out, self.update_order.as_ref(), |out, order| put_array(out, order));
        Ok(())
    }

    /// Reads and checks the payload of an instance accel of `shape` built with `options`, placing `children`
    /// (each of which some instance must place).
    fn decode(
        reader: &mut Reader<'_>,
        shape: &Shape,
        options: &BuildOptions,
        children: &[Arc<Accel>],
    ) -> Result<InstanceBvh> {
        let slots = usize::try_from(shape.instance_count)
            .map_err(|_| invalid(format!("{} instances", shape.instance_count)))?;
        let (nodes, node_keys, depth) = read_nodes(reader, slots, options)?;
        let stored: Vec<StoredInstance> = reader.array("instances")?;
        check_len("instances", stored.len(), shape.instance_count)?;
        let mut placed = vec![false; children.len()];
        let mut instances = Vec::with_capacity(stored.len());
        for (slot, s) in stored.iter().enumerate() {
            instances.push(s.placed(children).map_err(|what| invalid(format!("instance slot {slot}: {what}")))?);
            placed[s.child as usize] = true;
        }
        if let Some(c) = placed.iter().position(|&p| !p) {
            return Err(invalid(format!("child {c} is placed by no instance")));
        }
        let bounds: Bounds = reader.value("bounds")?;
        let update_order: Option<Vec<u32>> = reader.optional("update order", |r| r.array("update order"))?;
        check_presence(&update_order, options, BuildFlags::ALLOW_UPDATE, "update order")?;
        if let Some(order) = &update_order {
            check_update_order(order, slots)?;
        }
        let child_stack = children
            .iter()
            .map(|c| cpu_child(c).map(CpuAccel::stack_size))
            .try_fold(0, |deepest, s| s.map(|s| deepest.max(s)))?;
        let mut bvh = InstanceBvh {
            nodes,
            node_keys,
            wide: WideTree::default(),
            moving: MovingWideTree::default(),
            motion: options.motion,
            child_boxes: child_boxes(&instances),
            instances,
            stack_size: WideTree::stack_size_within(depth) + child_stack,
            bounds,
            update_order,
        };
        bvh.collapse();
        Ok(bvh)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tree `depth` nodes deep in which every inner node has a leaf for its first child (a caterpillar), in
    /// depth-first order, with one slot a leaf.
    fn caterpillar(depth: usize) -> Vec<Node> {
        let node = |index: usize, count: u32| Node { min: Vec3::ZERO, index: index as u32, max: Vec3::ONE, count };
        let mut nodes: Vec<Node> = (0..depth - 1).flat_map(|k| [node(2 * k + 1, 0), node(k, 1)]).collect();
        nodes.push(node(depth - 1, 1));
        nodes
    }

    #[test]
    fn trees_deeper_than_a_loaded_bvh_may_be_are_refused() {
        assert_eq!(check_nodes(&caterpillar(MAX_DEPTH), MAX_DEPTH).unwrap(), MAX_DEPTH);
        let deeper = MAX_DEPTH + 1;
        let refused = check_nodes(&caterpillar(deeper), deeper).unwrap_err().to_string();
        assert!(refused.contains("1025 nodes deep; a BVH may be at most 1024"), "{refused}");
    }
}
