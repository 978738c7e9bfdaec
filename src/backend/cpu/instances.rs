//! The instance accel and the static transform of the CPU backend: a BVH over the placed boxes of other accels,
//! and one accel under one placement.

use std::sync::Arc;

use glam::Vec3;
use obvhs::aabb::Aabb;

use super::CpuAccel;
use super::bvh::{FIXED_BYTES, Footprint, Layout, Node, refit};
use crate::accel::{BuildFlags, BuildOptions, MemoryUsage};
use crate::context::Accel;
use crate::error::{Error, Result};
use crate::geometry::{PlacedInstance, Placement};

/// The build's working memory per instance (boxes, PLOC's and the optimizer's arrays), as for triangles.
const BUILD_TEMP_BYTES_PER_INSTANCE: u64 = 384;
/// Working memory of a build that does not depend on its size.
const BUILD_TEMP_FIXED_BYTES: u64 = 4 << 20;

/// A BVH over instances, ready to trace. Cloning it makes an exact-size copy over the same children.
#[derive(Debug, Clone)]
pub struct InstanceBvh {
    /// Depth-first nodes over the instances' world boxes; empty when no instance has anything to hit.
    pub(super) nodes: Vec<Node>,
    /// The instances in leaf order, then those with empty boxes (never traversed).
    pub(super) instances: Vec<PlacedInstance>,
    /// Stack entries a trace through it needs: its own path and its deepest child's stack.
    pub(super) stack_size: usize,
    /// The box around every placed child.
    bounds: (Vec3, Vec3),
    /// With `ALLOW_UPDATE`: the input index of the instance in each slot, to refit with new placements.
    update_order: Option<Vec<u32>>,
}

/// One accel under a static transform.
#[derive(Debug, Clone)]
pub struct TransformNode {
    /// Where the child is placed.
    pub(super) placement: Placement,
    /// The child.
    pub(super) child: Arc<Accel>,
    /// The child's stack size.
    pub(super) stack_size: usize,
    /// The child's box, placed.
    bounds: (Vec3, Vec3),
}

/// The CPU structure of a child accel; FAILED_PRECONDITION for an accel of another device.
pub(super) fn cpu_child(accel: &Accel) -> Result<&CpuAccel> {
    super::cpu(accel.backend_accel())
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
    let nodes = (2 * n).saturating_sub(1) * size_of::<Node>() as u64;
    let updatable = options.flags.contains(BuildFlags::ALLOW_UPDATE);
    let output_bytes = FIXED_BYTES + nodes + n * size_of::<PlacedInstance>() as u64 + if updatable { 4 * n } else { 0 };
    MemoryUsage {
        output_bytes,
        temp_bytes: BUILD_TEMP_FIXED_BYTES + n * BUILD_TEMP_BYTES_PER_INSTANCE,
        // An update checks the new instances and writes a refitted copy.
        temp_update_bytes: if updatable { output_bytes + n * size_of::<PlacedInstance>() as u64 } else { 0 },
    }
}

impl InstanceBvh {
    /// Builds the BVH over the instances' placed boxes.
    pub fn build(instances: &[PlacedInstance], options: &BuildOptions) -> Result<InstanceBvh> {
        let mut child_stack = 0;
        let mut boxes = Vec::with_capacity(instances.len());
        let mut hittable = Vec::with_capacity(instances.len());
        let mut bounds = (Vec3::INFINITY, Vec3::NEG_INFINITY);
        for (index, instance) in instances.iter().enumerate() {
            child_stack = child_stack.max(cpu_child(&instance.child)?.stack_size());
            let (min, max) = instance.placement.place_bounds(instance.child.info().bounds);
            if min.cmple(max).all() {
                boxes.push(Aabb::new(min.into(), max.into()));
                hittable.push(index as u32);
                bounds = (bounds.0.min(min), bounds.1.max(max));
            }
        }
        let Layout { nodes, mut order, depth } = Layout::build(&boxes, &hittable, options.flags);
        let mut in_leaves = vec![false; instances.len()];
        for &i in &order {
            in_leaves[i as usize] = true;
        }
        order.extend((0..instances.len() as u32).filter(|&i| !in_leaves[i as usize]));
        Ok(InstanceBvh {
            nodes,
            instances: order.iter().map(|&i| instances[i as usize].clone()).collect(),
            stack_size: depth + 1 + child_stack,
            bounds,
            update_order: options.flags.contains(BuildFlags::ALLOW_UPDATE).then(|| {
                order.shrink_to_fit();
                order
            }),
        })
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
            if was.handle() != now.handle() {
                return Err(mismatch(format!(
                    "instance {i} places accel {} where the build placed accel {}",
                    now.handle().0,
                    was.handle().0
                )));
            }
            next.instances[slot] = instances[i as usize].clone();
        }
        let placed = |instance: &PlacedInstance| instance.placement.place_bounds(instance.child.info().bounds);
        let empty = (Vec3::INFINITY, Vec3::NEG_INFINITY);
        let union = |(lo, hi): (Vec3, Vec3), (min, max): (Vec3, Vec3)| (lo.min(min), hi.max(max));
        let members = &next.instances;
        refit(&mut next.nodes, |slots| members[slots].iter().map(placed).fold(empty, union));
        next.bounds = next.instances.iter().map(placed).filter(|(min, max)| min.cmple(*max).all()).fold(empty, union);
        Ok(next)
    }

    /// Bytes it occupies, counted as `footprint` says.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        FIXED_BYTES
            + (footprint.of(&self.nodes) * size_of::<Node>()) as u64
            + (footprint.of(&self.instances) * size_of::<PlacedInstance>()) as u64
            + self.update_order.as_ref().map_or(0, |o| 4 * footprint.of(o) as u64)
    }

    /// The box around every placed child.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }
}

impl TransformNode {
    /// Places `child` with `placement`.
    pub fn build(placement: &Placement, child: &Arc<Accel>) -> Result<TransformNode> {
        let stack_size = cpu_child(child)?.stack_size();
        let bounds = placement.place_bounds(child.info().bounds);
        Ok(TransformNode { placement: *placement, child: Arc::clone(child), stack_size, bounds })
    }

    /// Bytes it occupies.
    pub fn size_bytes(&self) -> u64 {
        FIXED_BYTES + size_of::<TransformNode>() as u64
    }

    /// The child's box, placed.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }
}
