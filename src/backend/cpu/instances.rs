//! The instance accel and the static transform of the CPU backend: a BVH over the placed boxes of other accels,
//! and one accel under one placement.

use std::sync::Arc;

use obvhs::aabb::Aabb;
use rayon::prelude::*;

use super::CpuAccel;
use super::bvh::{FIXED_BYTES, Footprint, Layout, Node, NodeKeys, refit};
use super::moving_wide::MovingWideTree;
use super::wide::{WideNode, WideTree};
use crate::accel::{BuildFlags, BuildOptions, MemoryUsage};
use crate::context::Accel;
use crate::error::{Error, Result};
use crate::geometry::motion::{Bounds, EMPTY, TimeSpan, is_empty, time_average, union};
use crate::geometry::{MotionOptions, PlacedInstance, Transform};

/// Instances a leaf of the BVH holds at most: one, so that a walk tests each instance's box in the nodes' lanes before
/// it carries the ray into the instance's space (BENCHMARKS.md, "Instances entered through their children's own
/// boxes").
const MAX_LEAF: u32 = 1;

/// Parts each motion segment is checked in when an instance's key boxes are fitted.
const FIT_CUTS: usize = 8;

/// The build's working memory per instance (boxes, PLOC's and the optimizer's arrays), as for triangles.
const BUILD_TEMP_BYTES_PER_INSTANCE: u64 = 384;
/// Working memory of a build that does not depend on its size.
const BUILD_TEMP_FIXED_BYTES: u64 = 4 << 20;

/// A BVH over instances, ready to trace. Cloning it makes an exact-size copy over the same children.
#[derive(Debug, Clone)]
pub struct InstanceBvh {
    /// Depth-first nodes over the instances' world boxes (the tree built over their averages over time, each node's
    /// box the union of its boxes at the keys); empty when no instance has anything to hit.
    pub(crate) nodes: Vec<Node>,
    /// With motion: each node's box at each key, fitted so that their interpolation holds the placed children at
    /// every time.
    pub(crate) node_keys: Option<NodeKeys>,
    /// Without motion: the nodes collapsed to wide ones, which rays walk instead (empty with motion).
    pub(super) wide: WideTree,
    /// With motion: the nodes collapsed to wide ones with their boxes at each key, which rays walk instead (empty
    /// without motion).
    pub(super) moving: MovingWideTree,
    /// The motion options (static without motion).
    pub(crate) motion: MotionOptions,
    /// The instances in leaf order, then those with empty boxes (never traversed).
    pub(crate) instances: Vec<PlacedInstance>,
    /// The box of each slot's child in its own space over all of time ([`child_boxes`]), which a ray tests before it
    /// is prepared there: the placed boxes of turned children are loose, and most rays that reach one miss the child.
    pub(super) child_boxes: Vec<Bounds>,
    /// Stack entries a trace through it needs: its own path and its deepest child's stack.
    pub(super) stack_size: usize,
    /// The box around every placed child at every time.
    pub(super) bounds: Bounds,
    /// With `ALLOW_UPDATE`: the input index of the instance in each slot, to refit with new placements.
    pub(super) update_order: Option<Vec<u32>>,
}

/// One accel under a transform (static or moving).
#[derive(Debug, Clone)]
pub struct TransformNode {
    /// Where the child is placed, at each time.
    pub(crate) transform: Transform,
    /// The child.
    pub(crate) child: Arc<Accel>,
    /// The child's stack size.
    pub(super) stack_size: usize,
    /// The placed child's boxes over time as [`Transform::key_bounds`] keeps them (none for a static transform), from
    /// which its box over any span is found without asking the child.
    key_bounds: Vec<Bounds>,
    /// The child's box, placed, over all of time.
    bounds: Bounds,
    /// The child's box in its own space over all of time, which a ray tests before it is prepared there.
    pub(super) child_box: Bounds,
}

/// The host structure of a child accel (a CPU accel, or the host side of another backend's); FAILED_PRECONDITION
/// for an accel that keeps none.
pub(crate) fn cpu_child(accel: &Accel) -> Result<&CpuAccel> {
    accel
        .backend_accel()
        .host()
        .ok_or_else(|| Error::FailedPrecondition("the child accel has no host structure".into()))
}

/// The error of an update of an accel built without `ALLOW_UPDATE`.
pub(super) fn not_updatable() -> Error {
    Error::FailedPrecondition("the accel was built without ALLOW_UPDATE".into())
}

/// The error of an update whose input differs in structure from the build's.
pub(super) fn mismatch(difference: String) -> Error {
    Error::FailedPrecondition(format!("the update's structure differs from the build's: {difference}"))
}

/// Upper bounds of an instance build's memory for `instances` instances.
pub(super) fn memory_bounds(instances: usize, options: &BuildOptions) -> MemoryUsage {
    let n = instances as u64;
    let keys = u64::from(options.motion.keys);
    let node_keys = if keys > 1 { keys * size_of::<Bounds>() as u64 } else { 0 };
    let nodes = (2 * n).saturating_sub(1) * (size_of::<Node>() as u64 + node_keys);
    let wide_nodes = match keys > 1 {
        true => MovingWideTree::most_bytes(n, keys),
        false => WideTree::most_nodes(instances) as u64 * (size_of::<WideNode>() as u64 + 1),
    };
    let updatable = options.flags.contains(BuildFlags::ALLOW_UPDATE);
    let per_instance = (size_of::<PlacedInstance>() + size_of::<Bounds>()) as u64;
    let output_bytes = FIXED_BYTES + nodes + wide_nodes + n * per_instance + if updatable { 4 * n } else { 0 };
    MemoryUsage {
        output_bytes,
        temp_bytes: BUILD_TEMP_FIXED_BYTES + n * (BUILD_TEMP_BYTES_PER_INSTANCE + keys * size_of::<Bounds>() as u64),
        // An update checks the new instances and writes a refitted copy.
        temp_update_bytes: if updatable { output_bytes + n * size_of::<PlacedInstance>() as u64 } else { 0 },
    }
}

/// The box of each of `instances`' children in its own space, over all of time.
pub(super) fn child_boxes(instances: &[PlacedInstance]) -> Vec<Bounds> {
    instances.iter().map(|instance| instance.child.backend_accel().bounds_during(TimeSpan::ALL)).collect()
}

/// The box of each instance at each of `motion`'s keys (`keys` a row, in input order): their interpolation holds
/// the placed child at every time (see [`MotionOptions::fit_key_bounds`]).
fn instance_key_boxes(instances: &[PlacedInstance], motion: &MotionOptions) -> Vec<Bounds> {
    let keys = |instance| motion.fit_key_bounds(FIT_CUTS, |span| placed_child(instance, span));
    instances.par_iter().flat_map_iter(keys).collect()
}

/// A box around `instance`'s child, placed, during `span`: for a static triangle accel, which is the same at every
/// time, the placed boxes of its wide nodes' lanes ([`super::wide::WideBvh::placed_bounds`]), which leave out most of
/// what the placed box of a turned child holds besides it (BENCHMARKS.md, "Instances entered through their children's
/// own boxes"); otherwise its box during `span`, placed.
fn placed_child(instance: &PlacedInstance, span: TimeSpan) -> Bounds {
    match cpu_child(&instance.child) {
        Ok(CpuAccel::Triangles(bvh)) if bvh.node_keys.is_none() => {
            bvh.wide.placed_bounds(|bounds| instance.placement.place_bounds(bounds))
        }
        _ => instance.placement.place_bounds(instance.child.backend_accel().bounds_during(span)),
    }
}

impl InstanceBvh {
    /// Builds the BVH over the instances' placed boxes: their average over time for its topology ([`time_average`]),
    /// and at each motion key for a motion instance accel.
    pub fn build(instances: &[PlacedInstance], options: &BuildOptions) -> Result<InstanceBvh> {
        let keys = options.motion.keys as usize;
        let key_boxes = instance_key_boxes(instances, &options.motion);
        let mut child_stack = 0;
        let mut boxes = Vec::with_capacity(instances.len());
        let mut hittable = Vec::with_capacity(instances.len());
        let mut bounds = EMPTY;
        for (index, instance) in instances.iter().enumerate() {
            child_stack = child_stack.max(cpu_child(&instance.child)?.stack_size());
            let at_keys = &key_boxes[index * keys..(index + 1) * keys];
            let (min, max) = at_keys.iter().copied().fold(EMPTY, union);
            if !is_empty(&(min, max)) {
                let (mean_min, mean_max) = time_average(at_keys.iter().copied());
                boxes.push(Aabb::new(mean_min.into(), mean_max.into()));
                hittable.push(index as u32);
                bounds = union(bounds, (min, max));
            }
        }
        let mut layout = Layout::build(&boxes, &hittable, options.flags, MAX_LEAF);
        layout.append_unplaced(instances.len());
        let Layout { nodes, mut order, depth } = layout;
        let instances: Vec<PlacedInstance> = order.iter().map(|&i| instances[i as usize].clone()).collect();
        let mut bvh = InstanceBvh {
            nodes,
            node_keys: (keys > 1).then(|| NodeKeys::new(0, keys)),
            wide: WideTree::default(),
            moving: MovingWideTree::default(),
            motion: options.motion,
            child_boxes: child_boxes(&instances),
            instances,
            stack_size: WideTree::stack_size_within(depth) + child_stack,
            bounds,
            update_order: None,
        };
        bvh.refit_boxes(&order, &key_boxes);
        bvh.collapse();
        if options.flags.contains(BuildFlags::ALLOW_UPDATE) {
            order.shrink_to_fit();
            bvh.update_order = Some(order);
        }
        Ok(bvh)
    }

    /// Collapses the nodes into wide ones (after a build, a refit or a read): with their boxes at each key for a
    /// motion accel. Its stack size, set from the binary nodes' depth ([`WideTree::stack_size_within`]), holds a walk
    /// of either and of any collapse.
    pub(super) fn collapse(&mut self) {
        match &self.node_keys {
            None => self.wide = WideTree::collapse(&self.nodes),
            Some(keys) => self.moving = MovingWideTree::collapse(&self.nodes, keys),
        }
    }

    /// Refits the nodes (and their key boxes) to `key_boxes` of the instances in input order; `order` gives the
    /// input index of each slot. The BVH's own box stays as it is.
    fn refit_boxes(&mut self, order: &[u32], key_boxes: &[Bounds]) {
        let keys = self.motion.keys as usize;
        if let Some(node_keys) = self.node_keys.as_mut() {
            *node_keys = NodeKeys::new(self.nodes.len(), keys);
        }
        refit(&mut self.nodes, self.node_keys.as_mut(), |slots, k| {
            slots.map(|slot| key_boxes[order[slot] as usize * keys + k]).fold(EMPTY, union)
        });
    }

    /// A copy with the placements, ids, masks and flags of `instances` (as many as at the build, each placing an
    /// accel with the same handle) and its boxes refitted. Fails (naming what differs) for an accel built without
    /// `ALLOW_UPDATE` or instances of another structure. Instances whose child was empty at the build stay out of
    /// the leaves.
    pub fn refit(&self, instances: &[PlacedInstance]) -> Result<InstanceBvh> {
        let order = self.update_order.as_ref().ok_or_else(not_updatable)?;
        if instances.len() != order.len() {
            return Err(mismatch(format!("{} instances where the build had {}", instances.len(), order.len())));
        }
        let mut next = self.clone();
        for (slot, &i) in order.iter().enumerate() {
            let (was, now) = (&self.instances[slot].child, &instances[i as usize].child);
            if !was.is_version_of(now) {
                return Err(mismatch(format!(
                    "instance {i} places accel {}, which is not the accel the build placed there (accel {}) nor a \
                     version of it",
                    now.handle().0,
                    was.handle().0
                )));
            }
            next.instances[slot] = instances[i as usize].clone();
        }
        next.child_boxes = child_boxes(&next.instances);
        let key_boxes = instance_key_boxes(instances, &self.motion);
        next.refit_boxes(order, &key_boxes);
        next.collapse();
        next.bounds = key_boxes.iter().copied().fold(EMPTY, union);
        Ok(next)
    }

    /// Bytes it occupies, counted as `footprint` says.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        FIXED_BYTES
            + (footprint.of(&self.nodes) * size_of::<Node>()) as u64
            + (footprint.of(&self.instances) * size_of::<PlacedInstance>()) as u64
            + (footprint.of(&self.child_boxes) * size_of::<Bounds>()) as u64
            + self.wide.size_bytes(footprint)
            + self.moving.size_bytes(footprint)
            + self.node_keys.as_ref().map_or(0, |k| (footprint.of(&k.boxes) * size_of::<Bounds>()) as u64)
            + self.update_order.as_ref().map_or(0, |o| 4 * footprint.of(o) as u64)
    }

    /// A box around every placed child at every time of `span`.
    pub fn bounds_during(&self, span: TimeSpan) -> Bounds {
        match &self.node_keys {
            Some(keys) if !keys.boxes.is_empty() => self.motion.bounds_of_keys(keys.root(), span),
            _ => self.bounds,
        }
    }
}

impl TransformNode {
    /// Places `child` with `transform`.
    pub fn build(transform: &Transform, child: &Arc<Accel>) -> Result<TransformNode> {
        let stack_size = cpu_child(child)?.stack_size();
        let child_box = child.backend_accel().bounds_during(TimeSpan::ALL);
        let node = TransformNode {
            transform: transform.clone(),
            child: Arc::clone(child),
            stack_size,
            key_bounds: transform.key_bounds(&|span| child.backend_accel().bounds_during(span)),
            bounds: EMPTY,
            child_box,
        };
        Ok(TransformNode { bounds: node.bounds_during(TimeSpan::ALL), ..node })
    }

    /// A box around the placed child at every time of `span`.
    pub fn bounds_during(&self, span: TimeSpan) -> Bounds {
        let child = self.child.backend_accel();
        self.transform.bounds_with_keys(&self.key_bounds, span, &|inner| child.bounds_during(inner))
    }

    /// Bytes it occupies.
    pub fn size_bytes(&self) -> u64 {
        FIXED_BYTES
            + size_of::<TransformNode>() as u64
            + self.transform.key_bytes()
            + (self.key_bounds.len() * size_of::<Bounds>()) as u64
    }

    /// The placed child's box over all of time.
    pub fn bounds(&self) -> Bounds {
        self.bounds
    }
}
