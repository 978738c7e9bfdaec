//! Packets through moving geometry accels: coherent rays at their own times (a motion-blurred camera's, each pixel's
//! ray at a time of its own) walked together through a moving accel's wide nodes ([`super::moving_wide`]) as static
//! packets walk a static accel's ([`super::packet`]). Each lane's box is interpolated at each ray's time, a ray a
//! lane, and so are each leaf triangle's corners, with the operations a ray alone uses
//! ([`MovingWideTree::boxes_at`], [`crate::geometry::motion::lerp`]): every ray meets each triangle where it meets it
//! alone, and gets the answer it gets alone. A packet's rays in different segments of the keys walk as one packet a
//! segment ([`in_segments`]); a ray whose time the accel's vanish flags leave it out of meets nothing, as alone. A
//! motion instance accel's packets walk its nodes the same way ([`super::instance_packets`]).

use glam::{Vec3, Vec3A};

use super::moving_wide::{MovingWideTree, holding};
use super::packet::{LaneBoxes, Packet, PacketEntry, PacketTree, plane};
use super::ray_lanes::{MAX_PACKET_RAYS, RayLanes};
use super::traverse::LeafSlots;
use super::triangles::TriangleBvh;
use super::wide::WideNode;
use super::{filter, set_bits};
use crate::format::Ray;
use crate::geometry::motion::{Bounds, KeyTime, MotionOptions, lerp};
use crate::query::{Collector, TraceStats};

impl TriangleBvh {
    /// [`TriangleBvh::walk_packet`] of a moving accel, once its rays make a packet: walks `tree` (the accel's moving
    /// wide nodes as a packet walks them) with the `active` rays of `packet`, each at its own time, a packet for each
    /// segment of the keys the rays' times fall in.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX2; the accel must be moving.
    #[inline(always)]
    pub(super) unsafe fn walk_packet_at_times<V: RayLanes, const NEAREST_FIRST: bool>(
        &self,
        tree: &PacketTree<'_>,
        stack: &mut [PacketEntry],
        packet: &Packet<'_, V>,
        active: u32,
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) {
        let (corners, keys) = (&self.corners, self.motion.keys as usize);
        let leaf_slots = LeafSlots { ids: &self.refs, masks: self.masks.as_deref() };
        let walk = {
            #[inline(always)]
            |segment: usize, rays: u32, fractions: &[f32; MAX_PACKET_RAYS]| {
                // SAFETY (all): the CPU has `V`'s instruction set and AVX2 (this function's contract).
                let boxes = unsafe { BoxesAtTimes::new(&self.moving, segment, fractions) };
                let (fraction, rest) = (boxes.fraction, boxes.rest);
                let keys_of = move |slot: usize| (&corners[slot * keys + segment], &corners[slot * keys + segment + 1]);
                // The closures are inlined at once: one left to itself is compiled without the instruction sets of
                // the function it is called from, and its intrinsics become calls.
                let lane_corners = {
                    #[inline(always)]
                    |slot: usize| {
                        let (from, to) = keys_of(slot);
                        CornersAtTimes { from, to, fraction, rest, axes: packet.lanes.axes }
                    }
                };
                let ray_corners = {
                    #[inline(always)]
                    |slot: usize, ray: usize| {
                        let (from, to) = keys_of(slot);
                        std::array::from_fn(|c| lerp(from[c], to[c], fractions[ray]))
                    }
                };
                let leaf = self.packet_leaf(packet, leaf_slots, lane_corners, ray_corners);
                let lanes = packet.lanes;
                unsafe {
                    tree.walk::<V, _, NEAREST_FIRST>(stack, lanes, &boxes, rays, collectors, stats, leaf, |_| {})
                };
            }
        };
        in_segments(&self.motion, packet.rays, active, walk);
    }
}

/// Calls `walk` for each group of the `active` rays of `rays` whose times fall in one segment of `motion`'s keys,
/// with the segment, the group (a bit a ray) and each ray's fraction of the way through the segment (by lane; 0 for
/// the rays not in the group). A ray whose time `motion`'s vanish flags leave out is in none.
#[inline(always)]
pub(super) fn in_segments(
    motion: &MotionOptions,
    rays: &[Ray],
    active: u32,
    mut walk: impl FnMut(usize, u32, &[f32; MAX_PACKET_RAYS]),
) {
    let mut times = [KeyTime { segment: 0, fraction: 0.0 }; MAX_PACKET_RAYS];
    let mut waiting = 0u32;
    for ray in set_bits(active) {
        if let Some(at) = motion.locate(rays[ray].time) {
            (times[ray], waiting) = (at, waiting | 1 << ray);
        }
    }
    while waiting != 0 {
        let segment = times[waiting.trailing_zeros() as usize].segment;
        let (mut group, mut fractions) = (0u32, [0f32; MAX_PACKET_RAYS]);
        for ray in set_bits(waiting).filter(|&ray| times[ray].segment == segment) {
            (group, fractions[ray]) = (group | 1 << ray, times[ray].fraction);
        }
        waiting &= !group;
        walk(segment, group, &fractions);
    }
}

impl MovingWideTree {
    /// Its nodes as a packet walks them, `root` the box around what the accel holds (triangles or instances) at every
    /// key: widened as the nodes' boxes are ([`MovingWideTree::collapse`]), so that it holds its lanes at every time.
    pub(super) fn packet_tree(&self, (min, max): Bounds) -> PacketTree<'_> {
        let planes = |axis: usize| [min[axis], max[axis]].into_iter();
        let lo = Vec3A::from_array(std::array::from_fn(|axis| holding(planes(axis), f32::min, -1.0)));
        let hi = Vec3A::from_array(std::array::from_fn(|axis| holding(planes(axis), f32::max, 1.0)));
        PacketTree { tree: self.tree(), root: (lo, hi), in_cache: false }
    }
}

/// A moving tree's lanes' boxes at the times of a packet's rays, all in one segment of its keys: each lane's two key
/// boxes interpolated, a ray a lane, with the operations of [`MovingWideTree::boxes_at`].
pub(super) struct BoxesAtTimes<'a, V> {
    /// The tree.
    tree: &'a MovingWideTree,
    /// The segment of the keys the rays' times fall in.
    segment: usize,
    /// Each ray's fraction of the way through the segment.
    fraction: V,
    /// `1 − fraction`.
    rest: V,
}

impl<'a, V: RayLanes> BoxesAtTimes<'a, V> {
    /// The boxes of `tree`'s lanes in segment `segment` of its keys, at each ray's `fractions` of the way through it.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set.
    #[inline(always)]
    pub(super) unsafe fn new(
        tree: &'a MovingWideTree,
        segment: usize,
        fractions: &[f32; MAX_PACKET_RAYS],
    ) -> BoxesAtTimes<'a, V> {
        // SAFETY: the CPU has the instruction set (the caller's contract).
        let fraction = unsafe { V::load(fractions) };
        BoxesAtTimes { tree, segment, fraction, rest: unsafe { V::splat(1.0).sub(fraction) } }
    }
}

impl<V: RayLanes> LaneBoxes<V> for BoxesAtTimes<'_, V> {
    #[inline(always)]
    unsafe fn planes(&self, node: usize, _: &WideNode, lane: usize, rows: &[(usize, usize); 3]) -> ([V; 3], [V; 3]) {
        let (from, to) = self.tree.segment_boxes(node, self.segment);
        let [(f0, l0), (f1, l1), (f2, l2)] = *rows;
        // No closure here: it would be compiled without the instruction set.
        // SAFETY: the CPU has the instruction set (the caller's contract); the rows are a node's, `lane` below `WIDTH`.
        unsafe {
            let at = |row: usize| (plane(from, row, lane), plane(to, row, lane));
            let (rest, fraction) = (self.rest, self.fraction);
            (
                [
                    interpolated(at(f0), rest, fraction),
                    interpolated(at(f1), rest, fraction),
                    interpolated(at(f2), rest, fraction),
                ],
                [
                    interpolated(at(l0), rest, fraction),
                    interpolated(at(l1), rest, fraction),
                    interpolated(at(l2), rest, fraction),
                ],
            )
        }
    }
}

/// A moving triangle's corners at the times of a packet's rays as [`filter::Corners`]: its corners at the two keys of
/// the rays' segment interpolated, a ray a lane, with the operations of [`lerp`].
struct CornersAtTimes<'a, V> {
    /// The corners at the segment's first key.
    from: &'a [Vec3; 3],
    /// The corners at its second key.
    to: &'a [Vec3; 3],
    /// Each ray's fraction of the way through the segment.
    fraction: V,
    /// `1 − fraction`.
    rest: V,
    /// The packet's `kx`, `ky`, `kz`.
    axes: [usize; 3],
}

impl<V: RayLanes> filter::Corners<V> for CornersAtTimes<'_, V> {
    #[inline(always)]
    unsafe fn corner(&self, c: usize) -> [V; 3] {
        let ([kx, ky, kz], from, to) = (self.axes, self.from[c].as_ref(), self.to[c].as_ref());
        let (rest, fraction) = (self.rest, self.fraction);
        // SAFETY: the CPU has `V`'s instruction set (the caller's contract).
        unsafe {
            [
                interpolated((from[kx], to[kx]), rest, fraction),
                interpolated((from[ky], to[ky]), rest, fraction),
                interpolated((from[kz], to[kz]), rest, fraction),
            ]
        }
    }
}

/// `a·(1 − f) + b·f` ([`lerp`]'s operations) a lane at a time, for `a` and `b` the same in every lane, `rest` = 1 − f.
///
/// # Safety
/// The CPU must have `V`'s instruction set.
#[inline(always)]
unsafe fn interpolated<V: RayLanes>((a, b): (f32, f32), rest: V, fraction: V) -> V {
    // SAFETY: the CPU has the instruction set (the caller's contract).
    unsafe { V::splat(a).mul(rest).add(V::splat(b).mul(fraction)) }
}

#[cfg(test)]
pub(super) mod tests {
    use std::sync::Arc;

    use glam::{Affine3A, Quat, Vec3A};

    use super::*;
    use crate::accel::BuildOptions;
    use crate::backend::cpu::instances::cpu_child;
    use crate::backend::cpu::packet::tests::{camera_rays, in_packet_order, lattice, packets_agree, rays_from, widths};
    use crate::format::{HitFormat, Ray};
    use crate::geometry::{BuildInput, Instance, InstanceFlags, MotionFlags, MotionOptions, Placement, TriangleInput};
    use crate::raygen::uniform;
    use crate::{Accel, Context, Device};

    /// The packet tests' lattice (its Prime masks too) moving over [0, 1] through `keys` keys (1, static; 2 or 3): as
    /// it is, then moved, then (the third) each vertex scattered.
    fn moving_lattice(context: &Context, keys: u32, flags: MotionFlags) -> Arc<Accel> {
        let (_, mesh) = lattice(true);
        let bytes = |points: Vec<Vec3>| -> Vec<u8> {
            points.iter().flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect()
        };
        let moved = bytes(mesh.positions.iter().map(|&p| p + Vec3::new(0.08, -0.05, 0.03)).collect());
        let scattered = bytes(
            (mesh.positions.iter().enumerate())
                .map(|(i, &p)| p + 0.02 * Vec3::new((i % 7) as f32, (i % 3) as f32, (i % 5) as f32))
                .collect(),
        );
        let packed = mesh.pack();
        let masks: Vec<u8> =
            (0..mesh.triangles.len() as u32).flat_map(|t| u32::from(t % 5 == 0).to_le_bytes()).collect();
        let motion_vertices = [&moved[..], &scattered[..]];
        let input = TriangleInput {
            motion_vertices: &motion_vertices[..keys as usize - 1],
            masks: Some(&masks),
            ..packed.input()
        };
        let motion = MotionOptions { keys, time_begin: 0.0, time_end: 1.0, flags };
        context
            .build_accel(&[BuildInput::Triangles(input)], &BuildOptions { motion, ..BuildOptions::default() })
            .unwrap()
    }

    /// `rays`, each at a pseudo-random time of its own in [−0.1, 1.1]: neighbours at different times, some before
    /// and after the motion.
    pub(in crate::backend::cpu) fn at_times(rays: Vec<Ray>) -> Vec<Ray> {
        let time = |i: usize| 1.2 * uniform(5, i as u64) - 0.1;
        rays.into_iter().enumerate().map(|(i, ray)| Ray { time: time(i), ..ray }).collect()
    }

    #[test]
    fn packets_at_their_own_times_give_every_ray_the_answer_it_gets_alone() {
        let context = Context::new(Device::cpu());
        let vanish = MotionFlags::START_VANISH | MotionFlags::END_VANISH;
        for (keys, flags) in [(2, MotionFlags::empty()), (3, MotionFlags::empty()), (2, vanish)] {
            let accel = moving_lattice(&context, keys, flags);
            let accel = cpu_child(&accel).unwrap();
            let eye = |pixel: u32| Vec3A::new(1.4, 1.6, 3.0) + 0.007 * (pixel % 8) as f32;
            for width in widths() {
                for (name, rays) in [("pinhole", camera_rays()), ("moving eye", rays_from(eye, |to, eye| to - eye))] {
                    let rays = in_packet_order(&at_times(rays), width);
                    packets_agree(accel, name, &rays, width, HitFormat::Full);
                }
            }
        }
    }

    #[test]
    fn packets_carried_into_moving_instances_give_every_ray_the_answer_it_gets_alone() {
        let context = Context::new(Device::cpu());
        let child = moving_lattice(&context, 3, MotionFlags::empty());
        let placed = |id: u32, placement: Affine3A, flags: InstanceFlags| Instance {
            transform: Placement::rows(&placement),
            instance_id: id,
            mask: 0xFF,
            flags,
            child: Arc::clone(&child),
        };
        let tilted = Affine3A::from_rotation_translation(Quat::from_rotation_z(0.2), Vec3::new(0.4, -0.3, 0.5));
        let instances =
            [placed(1, Affine3A::IDENTITY, InstanceFlags::empty()), placed(2, tilted, InstanceFlags::FLIP_FACING)];
        let scene = context.build_instance_accel(&instances, &BuildOptions::default()).unwrap();
        let accel = cpu_child(&scene).unwrap();
        for width in widths() {
            let rays = in_packet_order(&at_times(camera_rays()), width);
            // The full format: instance ids and paths, world normals and facing.
            packets_agree(accel, "pinhole", &rays, width, HitFormat::Full);
        }
    }

    #[test]
    fn packets_through_motion_instance_accels_give_every_ray_the_answer_it_gets_alone() {
        let context = Context::new(Device::cpu());
        let (moving, still) =
            (moving_lattice(&context, 3, MotionFlags::empty()), moving_lattice(&context, 1, MotionFlags::empty()));
        let placed = |id: u32, placement: Affine3A, child: &Arc<Accel>| Instance {
            transform: Placement::rows(&placement),
            instance_id: id,
            mask: 0xFF,
            flags: InstanceFlags::empty(),
            child: Arc::clone(child),
        };
        let tilted = Affine3A::from_rotation_translation(Quat::from_rotation_y(0.1), Vec3::new(0.5, 0.4, 0.3));
        let instances = [placed(1, Affine3A::IDENTITY, &moving), placed(2, tilted, &still)];
        for flags in [MotionFlags::empty(), MotionFlags::START_VANISH | MotionFlags::END_VANISH] {
            let motion = MotionOptions { keys: 2, time_begin: 0.0, time_end: 1.0, flags };
            let options = BuildOptions { motion, ..BuildOptions::default() };
            let scene = context.build_instance_accel(&instances, &options).unwrap();
            let accel = cpu_child(&scene).unwrap();
            for width in widths() {
                let rays = in_packet_order(&at_times(camera_rays()), width);
                packets_agree(accel, "pinhole", &rays, width, HitFormat::Full);
            }
        }
    }
}
