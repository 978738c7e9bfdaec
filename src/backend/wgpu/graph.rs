//! An accel's graph flattened into the device's arrays ([`super::layout`] documents them): every distinct accel
//! below it (itself included) once, children before parents. A BVH's nodes, key boxes, corners and triangle ids
//! are appended to the shared arrays with its node indices made global (inner nodes' children, geometry leaves'
//! triangle slots; instance leaves keep their own slots); instances, transforms and one record a BVH or transform
//! (an *object*) go to the graph words.

use std::collections::HashMap;

use glam::{Affine3A, Vec3};

use super::kernel::Variant;
use super::layout::{INSTANCE_WORDS, NODE_WIDTH, NODE_WORDS, OBJECT_WORDS, ObjectKind, Prim};
use crate::backend::cpu::bvh::{Node, NodeKeys};
#[cfg(doc)]
use crate::backend::cpu::collapse::Collapsed;
use crate::backend::cpu::collapse::{EMPTY_LANE, Lane, collapse};
use crate::backend::cpu::{CpuAccel, InstanceBvh, TransformNode, TriangleBvh, cpu_child};
use crate::error::Result;
use crate::geometry::motion::Bounds;
use crate::geometry::{MotionOptions, Transform};

/// The flattened arrays.
#[derive(Debug, Default)]
pub(super) struct Flat {
    /// Node words, [`NODE_WORDS`] a node.
    pub nodes: Vec<u32>,
    /// Per-key lane boxes of motion BVHs, 6 floats a box.
    pub boxes: Vec<f32>,
    /// Triangle corners, 3 vectors a triangle a key (`x, y, z, 0`: one aligned load a corner).
    pub corners: Vec<[f32; 4]>,
    /// Triangle ids, one a slot.
    pub prims: Vec<Prim>,
    /// Objects, instance records and transform keys.
    pub graph: Vec<u32>,
    /// The root object's word offset in `graph`.
    pub root: u32,
    /// Traversal stack entries a ray through the graph needs at most.
    pub stack: usize,
    /// What the trace pipeline can be specialised for.
    pub variant: Variant,
}

/// Flattens the graph under `host`.
pub(super) fn flatten(host: &CpuAccel) -> Result<Flat> {
    let mut flattener = Flattener { flat: Flat::default(), seen: HashMap::new(), motion: false };
    let (root, stack) = flattener.object(host)?;
    let levels = !matches!(host, CpuAccel::Triangles(_));
    let variant = Variant::for_graph(levels, flattener.motion);
    Ok(Flat { root, stack, variant, ..flattener.flat })
}

/// The flattening in progress.
struct Flattener {
    /// What is flattened so far.
    flat: Flat,
    /// The objects already flattened, by address of their host structure: their offset and stack need.
    seen: HashMap<usize, (u32, usize)>,
    /// Whether an object flattened so far has motion keys.
    motion: bool,
}

/// Where [`Flattener::bvh`] put a BVH.
struct PlacedBvh {
    /// Its root node's index in `nodes`.
    first: u32,
    /// Its first key box's float offset in `boxes`.
    box_base: u32,
    /// Its nodes.
    node_count: u32,
    /// Stack entries a walk of it needs at most ([`Collapsed::stack_need`]).
    stack_need: usize,
}

/// The 12 floats of an affine map, column by column (x axis, y axis, z axis, translation).
fn columns(affine: &Affine3A) -> [f32; 12] {
    let m = affine.matrix3;
    let mut out = [0.0; 12];
    for (i, v) in [m.x_axis, m.y_axis, m.z_axis, affine.translation].iter().enumerate() {
        out[3 * i..3 * i + 3].copy_from_slice(&v.to_array());
    }
    out
}

/// The key box of an empty lane (read with the others, never entered: the lane's index marks it empty).
const EMPTY_KEY_BOX: Bounds = (Vec3::ZERO, Vec3::ZERO);

impl Flattener {
    /// Flattens `host` (once) and returns its object's offset and its stack need.
    fn object(&mut self, host: &CpuAccel) -> Result<(u32, usize)> {
        let key = std::ptr::from_ref(host) as usize;
        if let Some(&known) = self.seen.get(&key) {
            return Ok(known);
        }
        let flattened = match host {
            CpuAccel::Triangles(bvh) => self.triangles(bvh),
            CpuAccel::Instances(bvh) => self.instances(bvh)?,
            CpuAccel::Transform(node) => self.transform(node)?,
        };
        self.seen.insert(key, flattened);
        Ok(flattened)
    }

    /// Appends a BVH's nodes collapsed to [`NODE_WIDTH`] lanes (inner lanes' nodes made global, leaf lanes' first
    /// slot moved by `leaf_base`) and their lanes' key boxes. A motion BVH is collapsed by its nodes' boxes on average
    /// over time, as the CPU's is ([`NodeKeys::time_averaged`]).
    fn bvh(&mut self, nodes: &[Node], keys: Option<&NodeKeys>, leaf_base: u32) -> PlacedBvh {
        let first = (self.flat.nodes.len() / NODE_WORDS) as u32;
        let box_base = self.flat.boxes.len() as u32;
        let collapsed = match keys {
            None => collapse(nodes, NODE_WIDTH),
            Some(keys) => collapse(&keys.time_averaged(nodes), NODE_WIDTH),
        };
        for lanes in collapsed.lanes.chunks(NODE_WIDTH) {
            let mut words = [0u32; NODE_WORDS];
            for (lane, &Lane { binary, child }) in lanes.iter().enumerate() {
                // The lane's words: boxes by axis (lo x, y, z, hi x, y, z), then index, then count.
                let (index_word, count_word) = (6 * NODE_WIDTH + lane, 7 * NODE_WIDTH + lane);
                if binary == EMPTY_LANE {
                    words[index_word] = EMPTY_LANE;
                    continue;
                }
                let node = &nodes[binary as usize];
                for axis in 0..3 {
                    words[axis * NODE_WIDTH + lane] = node.min[axis].to_bits();
                    words[(3 + axis) * NODE_WIDTH + lane] = node.max[axis].to_bits();
                }
                words[index_word] = if node.count == 0 { first + child } else { node.index + leaf_base };
                words[count_word] = node.count;
            }
            self.flat.nodes.extend(words);
            if let Some(keys) = keys {
                for &Lane { binary, .. } in lanes {
                    for key in 0..keys.keys {
                        let (min, max) = if binary == EMPTY_LANE {
                            EMPTY_KEY_BOX
                        } else {
                            keys.boxes[binary as usize * keys.keys + key]
                        };
                        self.flat.boxes.extend(min.to_array().into_iter().chain(max.to_array()));
                    }
                }
            }
        }
        let node_count = (collapsed.lanes.len() / NODE_WIDTH) as u32;
        PlacedBvh { first, box_base, node_count, stack_need: collapsed.stack_need }
    }

    /// Appends an object record (`placed`: a BVH's place; a transform's child object as `first`); returns its
    /// offset.
    fn record(
        &mut self,
        kind: ObjectKind,
        motion: &MotionOptions,
        placed: &PlacedBvh,
        base: u32,
        corner_base: u32,
    ) -> u32 {
        let offset = self.flat.graph.len() as u32;
        self.motion |= motion.keys > 1;
        let words: [u32; OBJECT_WORDS] = [
            kind as u32,
            motion.keys,
            motion.flags.bits(),
            motion.time_begin.to_bits(),
            motion.time_end.to_bits(),
            placed.first,
            placed.node_count,
            placed.box_base,
            base,
            corner_base,
        ];
        self.flat.graph.extend(words);
        offset
    }

    /// A geometry accel.
    fn triangles(&mut self, bvh: &TriangleBvh) -> (u32, usize) {
        let slot_base = self.flat.prims.len() as u32;
        let corner_base = self.flat.corners.len() as u32;
        let placed = self.bvh(&bvh.nodes, bvh.node_keys.as_ref(), slot_base);
        self.flat.corners.extend(bvh.corners.iter().flat_map(|c| c.iter().map(|v| v.extend(0.0).to_array())));
        self.flat.prims.extend(bvh.refs.iter().enumerate().map(|(slot, r)| Prim {
            geom_id: r.geom_id,
            prim_id: r.prim_id,
            mask: bvh.masks.as_ref().map_or(0, |m| m[slot]),
            geometry_flags: bvh.geometry_flags[r.geom_id as usize].bits(),
        }));
        let offset = self.record(ObjectKind::Triangles, &bvh.motion, &placed, slot_base, corner_base);
        (offset, placed.stack_need)
    }

    /// An instance accel: its children first, then its instance records, nodes and object.
    fn instances(&mut self, bvh: &InstanceBvh) -> Result<(u32, usize)> {
        let mut children = Vec::with_capacity(bvh.instances.len());
        let mut child_stack = 0;
        for instance in &bvh.instances {
            let (child, stack) = self.object(cpu_child(&instance.child)?)?;
            children.push(child);
            child_stack = child_stack.max(stack);
        }
        let records = self.flat.graph.len() as u32;
        for (instance, child) in bvh.instances.iter().zip(children) {
            let mut record = [0u32; INSTANCE_WORDS];
            record[..12].copy_from_slice(&columns(&instance.placement.world_to_object).map(f32::to_bits));
            record[12..].copy_from_slice(&[
                instance.instance_id,
                u32::from(instance.mask),
                instance.flags.bits(),
                child,
            ]);
            self.flat.graph.extend(record);
        }
        let placed = self.bvh(&bvh.nodes, bvh.node_keys.as_ref(), 0);
        let offset = self.record(ObjectKind::Instances, &bvh.motion, &placed, records, 0);
        // A walk's pending lanes, then a leaf's resume entry and the marker below it.
        Ok((offset, placed.stack_need + 2 + child_stack))
    }

    /// A transform: its child first, then its keys and object.
    fn transform(&mut self, node: &TransformNode) -> Result<(u32, usize)> {
        let (child, child_stack) = self.object(cpu_child(&node.child)?)?;
        let base = self.flat.graph.len() as u32;
        let floats: Vec<f32> = match &node.transform {
            Transform::Static(placement) => columns(&placement.world_to_object).to_vec(),
            Transform::Matrix { keys, .. } => keys.iter().flat_map(columns).collect(),
            Transform::Srt { keys, .. } => keys.iter().flat_map(|k| k.floats()).collect(),
        };
        self.flat.graph.extend(floats.iter().map(|f| f.to_bits()));
        let kind = match &node.transform {
            Transform::Static(_) => ObjectKind::StaticTransform,
            Transform::Matrix { .. } => ObjectKind::MatrixTransform,
            Transform::Srt { .. } => ObjectKind::SrtTransform,
        };
        let child = PlacedBvh { first: child, box_base: 0, node_count: 0, stack_need: 0 };
        let offset = self.record(kind, &node.transform.motion(), &child, base, 0);
        // The marker below it.
        Ok((offset, 1 + child_stack))
    }
}
