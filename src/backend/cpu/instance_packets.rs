//! Packets through an instance accel: a packet of coherent rays walks the instance accel's wide nodes together
//! ([`PacketTree::walk`], each instance's box tested ray by ray in the lanes), and the rays that reach an instance are
//! carried into its space together and walk its child there as a packet where the child is a geometry accel, static or
//! moving ([`super::triangles::TriangleBvh::walk_packet`]), a static transform over one, or an instance accel (this
//! walk again), and the carried rays still make one. Otherwise each of them enters the instance as it would alone
//! ([`carried_into`], then the child's own walk).
//!
//! **Same answers as alone.** Each ray is carried as [`crate::intersect::PreparedRay::transformed`] carries it alone
//! ([`carried`]), and a packet gives its rays the answers they get alone ([`super::packet`]); the instance's box and
//! the child's are tested with margins ([`PacketTree::walk`], [`crate::intersect::aabb::reaches`]), which only decide
//! where a ray looks, not what it finds.

use std::ops::Range;

use glam::Affine3A;

use super::instances::{InstanceBvh, cpu_child};
use super::moving_packets::{BoxesAtTimes, in_segments};
use super::packet::{MAX_ORIGIN_SPREAD, NodeBoxes, PacketAccel, PacketEntry, PacketLanes, PacketTree};
use super::ray_lanes::{MAX_PACKET_RAYS, RayLanes};
use super::traverse::{StackEntry, Stacks, carried_into};
use super::{CpuAccel, set_bits};
use crate::format::Ray;
use crate::geometry::Transform;
use crate::intersect::{PreparedRay, carried};
use crate::query::{Collector, InstanceScope, TraceStats};

impl PacketAccel for InstanceBvh {
    #[inline(always)]
    unsafe fn trace_packet_in_order<V: RayLanes, const NEAREST_FIRST: bool>(
        &self,
        stacks: &mut Stacks,
        rays: &[Ray],
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> bool {
        let (stacks, every_ray) = ((&mut stacks.packet[..], &mut stacks.single[..]), (1 << V::RAYS) - 1);
        // SAFETY: the CPU has `V`'s instruction set and AVX2 (this function's contract).
        unsafe {
            self.walk_packet::<V, NEAREST_FIRST>(stacks, rays, every_ray, &InstanceScope::WORLD, collectors, stats)
        }
    }
}

/// The packet stack (for the instance nodes' walk, then a child's) and the single-ray stack (for rays that enter an
/// instance one by one) of a packet's walk through an instance accel.
type PacketStacks<'a> = (&'a mut [PacketEntry], &'a mut [StackEntry]);

impl InstanceBvh {
    /// Walks the rays of `rays` ([`RayLanes::RAYS`] of them, as [`crate::intersect::traced`] makes them, in this
    /// accel's space) whose bits are set in `active` as a packet, in `scope`, if all of them head the same way from
    /// nearby origins ([`PacketLanes::coherent`]), and says whether it did; for the visit order `NEAREST_FIRST`, which
    /// must be what the collectors want. A motion instance accel's nodes are walked with their boxes at each ray's time
    /// ([`super::moving_packets`]). The packet stack must hold the accel's [`InstanceBvh::stack_size`] entries.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX2.
    #[inline(always)]
    unsafe fn walk_packet<V: RayLanes, const NEAREST_FIRST: bool>(
        &self,
        (packet_stack, single_stack): PacketStacks<'_>,
        rays: &[Ray],
        active: u32,
        scope: &InstanceScope,
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> bool {
        // SAFETY (all): the CPU has `V`'s instruction set and AVX2 (this function's contract).
        let Some(lanes) = (unsafe { PacketLanes::<V>::new(rays) }) else { return false };
        // The instance nodes are few and small; their boxes are tested exactly, ray by ray, at every node.
        let (tree, own_size) = match self.node_keys {
            None => {
                let root = (self.bounds.0.into(), self.bounds.1.into());
                (PacketTree { tree: self.wide.tree(), root, in_cache: false }, self.wide.stack_size())
            }
            Some(_) => (self.moving.packet_tree(self.bounds), self.moving.stack_size()),
        };
        if !unsafe { lanes.coherent(&rays[0], MAX_ORIGIN_SPREAD * tree.diagonal()) } {
            return false;
        }
        let (own, rest) = packet_stack.split_at_mut(own_size);
        if self.node_keys.is_none() {
            let leaf = self.leaf::<V, NEAREST_FIRST>(rays, (rest, single_stack), scope);
            unsafe {
                tree.walk::<V, _, NEAREST_FIRST>(own, &lanes, &NodeBoxes, active, collectors, stats, leaf, |_| {})
            };
            return true;
        }
        // A motion instance accel: its nodes' boxes at each ray's time, a packet for each segment of the keys. (Each
        // segment's walk makes its own leaf: a closure handed on by reference is called through a function compiled
        // without the instruction sets.)
        let walk = {
            #[inline(always)]
            |segment: usize, group: u32, fractions: &[f32; MAX_PACKET_RAYS]| unsafe {
                let boxes = BoxesAtTimes::new(&self.moving, segment, fractions);
                let leaf = self.leaf::<V, NEAREST_FIRST>(rays, (&mut *rest, &mut *single_stack), scope);
                tree.walk::<V, _, NEAREST_FIRST>(own, &lanes, &boxes, group, collectors, stats, leaf, |_| {})
            }
        };
        in_segments(&self.motion, rays, active, walk);
        true
    }

    /// What a packet walk of this accel does at a leaf: enters each of its instances with the rays of `rays` the walk
    /// hands it (on `stacks`, below `scope`), and returns the rays it finished. Inlined at once, so that it is
    /// compiled with the instruction sets of the function it is called from.
    #[inline(always)]
    fn leaf<'a, V: RayLanes, const NEAREST_FIRST: bool>(
        &'a self,
        rays: &'a [Ray],
        (rest, single_stack): PacketStacks<'a>,
        scope: &'a InstanceScope,
    ) -> impl FnMut(Range<usize>, u32, &mut [Collector<'_>], &mut TraceStats) -> u32 + 'a {
        #[inline(always)]
        move |slots: Range<usize>, active: u32, collectors: &mut [Collector<'_>], stats: &mut TraceStats| {
            let mut finished = 0;
            for slot in slots {
                let (walking, stacks) = (active & !finished, (&mut rest[..], &mut single_stack[..]));
                // SAFETY: the CPU has `V`'s instruction set and AVX2 (the packet walk's contract).
                finished |= unsafe {
                    self.enter_instance::<V, NEAREST_FIRST>(slot, rays, walking, stacks, scope, collectors, stats)
                };
            }
            finished
        }
    }

    /// Walks the child of the instance in `slot` with those of `rays` (a packet's, [`RayLanes::RAYS`] of them) whose
    /// bits are set in `active` and whose visibility mask sees the instance, below `scope`: carried into its space as a
    /// packet where they make one there and the child is a geometry accel, a static transform over one or an instance
    /// accel, each on its own otherwise (on the single-ray stack). Returns the rays it finished (their collectors done).
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX2.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    unsafe fn enter_instance<V: RayLanes, const NEAREST_FIRST: bool>(
        &self,
        slot: usize,
        rays: &[Ray],
        active: u32,
        (packet_stack, single_stack): PacketStacks<'_>,
        scope: &InstanceScope,
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> u32 {
        let instance = &self.instances[slot];
        let visible = lanes_where(active, |lane| rays[lane].visibility & instance.mask != 0);
        // Rays past their work enter no instance ([`Collector::stop_past`]): they are done.
        let stopped = lanes_where(visible, |lane| collectors[lane].stop_past(stats));
        let visible = visible & !stopped;
        if visible == 0 {
            return stopped;
        }
        let Ok(child) = cpu_child(&instance.child) else { return stopped };
        let scope = scope.enter(instance);
        let stacks = (&mut packet_stack[..], &mut single_stack[..]);
        // SAFETY: the CPU has `V`'s instruction set and AVX2 (this function's contract).
        let packed = unsafe {
            self.carry_packet::<V, NEAREST_FIRST>(slot, child, rays, visible, stacks, &scope, collectors, stats)
        };
        if !packed {
            let (to_object, child_box) = (&instance.placement.world_to_object, self.child_boxes[slot]);
            for lane in set_bits(visible) {
                let (ray, collector) = (PreparedRay::from_traced(&rays[lane]), &mut collectors[lane]);
                if let Some(local) = carried_into(&ray, to_object, child_box, collector, stats) {
                    child.traverse(single_stack, &local, &scope, collector, stats);
                }
            }
        }
        stopped | lanes_where(visible, |lane| collectors[lane].done())
    }

    /// Walks `child`, the child of the instance in `slot`, in `scope` (the instance's) with those of `rays` whose bits
    /// are set in `active`, carried into the instance's space together as a packet, and says whether it did: only a
    /// geometry accel (static or moving), a static transform over one or an instance accel is walked so, and only where
    /// the carried rays make a packet there.
    ///
    /// # Safety
    /// The CPU must have `V`'s instruction set and AVX2.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    unsafe fn carry_packet<V: RayLanes, const NEAREST_FIRST: bool>(
        &self,
        slot: usize,
        child: &CpuAccel,
        rays: &[Ray],
        active: u32,
        stacks: PacketStacks<'_>,
        scope: &InstanceScope,
        collectors: &mut [Collector<'_>],
        stats: &mut TraceStats,
    ) -> bool {
        let to_object = &self.instances[slot].placement.world_to_object;
        let mut local = [Ray::default(); MAX_PACKET_RAYS];
        let rays = &rays[..V::RAYS];
        // SAFETY (both): the CPU has `V`'s instruction set and AVX2 (this function's contract).
        match child {
            CpuAccel::Triangles(bvh) => unsafe {
                let local = carried_all(rays, to_object, &mut local);
                bvh.walk_packet::<V, NEAREST_FIRST>(stacks.0, local, active, scope, collectors, stats)
            },
            // A static transform over a geometry accel places it for every ray alike: as one more instance. (Rays
            // carried through a motion transform, each as placed at its own time, seldom make a packet there: their
            // origins drift apart with the motion, and placing every ray for nothing cost more than packets saved,
            // BENCHMARKS.md, "Rays at their own times walked as packets…".)
            CpuAccel::Transform(node) => match (&node.transform, cpu_child(&node.child)) {
                (Transform::Static(placement), Ok(CpuAccel::Triangles(bvh))) => unsafe {
                    let mut placed = [Ray::default(); MAX_PACKET_RAYS];
                    let local =
                        carried_all(carried_all(rays, to_object, &mut local), &placement.world_to_object, &mut placed);
                    let scope = scope.through(placement);
                    bvh.walk_packet::<V, NEAREST_FIRST>(stacks.0, local, active, &scope, collectors, stats)
                },
                _ => false,
            },
            CpuAccel::Instances(bvh) => unsafe {
                let local = carried_all(rays, to_object, &mut local);
                walk_nested::<V, NEAREST_FIRST>(bvh, stacks, local, active, scope, collectors, stats)
            },
        }
    }
}

/// [`InstanceBvh::walk_packet`] of `bvh` (an instance accel placed in another) through an entry compiled for `V`'s
/// instruction set: the walks of a packet inline into one function for each instruction set, and an instance accel
/// inside another calls that function again (the call cannot be inlined, and a function that is not compiled for the
/// instruction set makes calls of its intrinsics).
///
/// # Safety
/// The CPU must have `V`'s instruction set and AVX2.
#[inline(always)]
unsafe fn walk_nested<V: RayLanes, const NEAREST_FIRST: bool>(
    bvh: &InstanceBvh,
    stacks: PacketStacks<'_>,
    rays: &[Ray],
    active: u32,
    scope: &InstanceScope,
    collectors: &mut [Collector<'_>],
    stats: &mut TraceStats,
) -> bool {
    // SAFETY: the CPU has `V`'s instruction set and AVX2 (this function's contract): AVX-512F where `V` has 16 lanes.
    unsafe {
        match V::RAYS {
            8 => walk_nested_avx2::<NEAREST_FIRST>(bvh, stacks, rays, active, scope, collectors, stats),
            _ => walk_nested_avx512::<NEAREST_FIRST>(bvh, stacks, rays, active, scope, collectors, stats),
        }
    }
}

/// Defines `$name`, [`InstanceBvh::walk_packet`] in `$lanes` registers compiled with the target features `$features`.
macro_rules! walk_nested_compiled_for {
    ($(#[$doc:meta])* $name:ident, $lanes:ty, $features:literal) => {
        $(#[$doc])*
        ///
        /// # Safety
        /// The CPU must have the features this build is compiled with; `rays` are as many as its registers' lanes.
        #[target_feature(enable = $features)]
        unsafe fn $name<const NEAREST_FIRST: bool>(
            bvh: &InstanceBvh,
            stacks: PacketStacks<'_>,
            rays: &[Ray],
            active: u32,
            scope: &InstanceScope,
            collectors: &mut [Collector<'_>],
            stats: &mut TraceStats,
        ) -> bool {
            // SAFETY: the CPU has the features (this function's contract).
            unsafe { bvh.walk_packet::<$lanes, NEAREST_FIRST>(stacks, rays, active, scope, collectors, stats) }
        }
    };
}

walk_nested_compiled_for!(
    /// [`InstanceBvh::walk_packet`] in AVX2 registers, 8 rays.
    walk_nested_avx2,
    std::arch::x86_64::__m256,
    "avx2,fma,bmi1,bmi2,lzcnt,popcnt"
);

walk_nested_compiled_for!(
    /// [`InstanceBvh::walk_packet`] in AVX-512 registers, 16 rays.
    walk_nested_avx512,
    std::arch::x86_64::__m512,
    "avx512f,avx2,fma,bmi1,bmi2,lzcnt,popcnt"
);

/// `rays` carried into the space `to_object` maps into ([`carried`]), written into the first of `local`.
#[inline(always)]
fn carried_all<'a>(rays: &[Ray], to_object: &Affine3A, local: &'a mut [Ray; MAX_PACKET_RAYS]) -> &'a [Ray] {
    for (local, ray) in local.iter_mut().zip(rays) {
        *local = carried(ray, to_object);
    }
    &local[..rays.len()]
}

/// The lanes set in `lanes` for which `keep` holds, a bit each.
#[inline(always)]
fn lanes_where(lanes: u32, mut keep: impl FnMut(usize) -> bool) -> u32 {
    set_bits(lanes).filter(|&lane| keep(lane)).fold(0, |kept, lane| kept | 1 << lane)
}

#[cfg(test)]
mod tests {
    use std::arch::x86_64::__m256;
    use std::sync::Arc;

    use glam::{Affine3A, Quat, Vec3};

    use super::*;
    use crate::accel::BuildOptions;
    use crate::backend::cpu::moving_packets::tests::at_times;
    use crate::backend::cpu::packet::tests::{camera_rays, in_packet_order, lattice, packets_agree, widths};
    use crate::cpu_features::has_avx2;
    use crate::format::{Hit, HitFormat, RayFlags, RayFormat};
    use crate::geometry::{
        BuildInput, Instance, InstanceFlags, MotionFlags, MotionOptions, Placement, TransformInput, TriangleInput,
    };
    use crate::intersect::traced;
    use crate::query::Query;
    use crate::{Accel, Context, Device};

    /// An instance of `child` placed by `to_world`.
    fn instance(id: u32, to_world: Affine3A, mask: u8, flags: InstanceFlags, child: &Arc<Accel>) -> Instance {
        Instance { transform: Placement::rows(&to_world), instance_id: id, mask, flags, child: Arc::clone(child) }
    }

    /// The packet tests' lattice (with its Prime masks) placed as itself, turned and shrunk (its faces flipped),
    /// mirrored (its faces never culled), tilted, inside an instance accel of its own, and under a static transform,
    /// each seen by other visibility bits; with the lattice's geometry accel.
    fn scene(context: &Context) -> (Arc<Accel>, Arc<Accel>) {
        let (_, mesh) = lattice(true);
        let packed = mesh.pack();
        let masks: Vec<u8> =
            (0..mesh.triangles.len() as u32).flat_map(|t| u32::from(t % 5 == 0).to_le_bytes()).collect();
        let input = TriangleInput { masks: Some(&masks), ..packed.input() };
        let lattice = context.build_accel(&[BuildInput::Triangles(input)], &BuildOptions::default()).unwrap();
        let lifted = Affine3A::from_translation(Vec3::new(0.1, 0.2, 0.4));
        let nested = [instance(9, lifted, 0xFF, InstanceFlags::empty(), &lattice)];
        let nested = context.build_instance_accel(&nested, &BuildOptions::default()).unwrap();
        // Turned a little too, so that the transform turns the hits' normals.
        let lowered = Affine3A::from_rotation_translation(Quat::from_rotation_x(0.05), Vec3::new(0.0, -0.2, -0.3));
        let lowered = Placement::rows(&lowered);
        let moved = context.build_transform(&TransformInput::Static(lowered), &lattice).unwrap();
        let turned = Affine3A::from_scale_rotation_translation(
            Vec3::splat(0.8),
            Quat::from_rotation_z(0.5),
            Vec3::new(0.6, -0.3, 0.25),
        );
        let mirrored =
            Affine3A::from_translation(Vec3::new(6.0, 0.0, 0.05)) * Affine3A::from_scale(Vec3::new(-1.0, 1.0, 1.0));
        let tilted = Affine3A::from_translation(Vec3::new(0.5, 1.0, 0.6)) * Affine3A::from_rotation_x(0.6);
        let instances = [
            instance(1, Affine3A::IDENTITY, 0x01, InstanceFlags::empty(), &lattice),
            instance(2, turned, 0x02, InstanceFlags::FLIP_FACING, &lattice),
            instance(3, mirrored, 0x03, InstanceFlags::DISABLE_FACE_CULLING, &lattice),
            instance(4, tilted, 0x04, InstanceFlags::empty(), &lattice),
            instance(5, Affine3A::from_translation(Vec3::new(-0.2, 0.1, 0.3)), 0x08, InstanceFlags::empty(), &nested),
            instance(6, Affine3A::from_translation(Vec3::new(0.3, 0.0, 0.7)), 0x10, InstanceFlags::empty(), &moved),
        ];
        let scene = context.build_instance_accel(&instances, &BuildOptions::default()).unwrap();
        (scene, lattice)
    }

    /// [`camera_rays`], pixel by pixel seen by all instances or by some.
    fn rays() -> Vec<Ray> {
        let visibility = [0xFF, 0x01, 0x06, 0x0B, 0x18];
        let rays = camera_rays().into_iter().enumerate();
        rays.map(|(pixel, ray)| Ray { visibility: visibility[pixel / 3 % visibility.len()], ..ray }).collect()
    }

    #[test]
    fn packets_through_instances_give_every_ray_the_answer_it_gets_alone() {
        let context = Context::new(Device::cpu());
        let (scene, _) = scene(&context);
        let accel = cpu_child(&scene).unwrap();
        for width in widths() {
            let rays = in_packet_order(&rays(), width);
            // The full format: instance ids and paths, world normals and facing, which the instances' scopes make.
            packets_agree(accel, "pinhole through instances", &rays, width, HitFormat::Full);
        }
    }

    /// [`InstanceBvh::carry_packet`] of 8 rays in AVX2 registers, for a closest-hit query.
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn carry_packet(bvh: &InstanceBvh, slot: usize, rays: &[Ray]) -> bool {
        let child = cpu_child(&bvh.instances[slot].child).unwrap();
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        let rays: Vec<Ray> = rays.iter().map(|ray| traced(ray, RayFlags::empty())).collect();
        let mut parts = vec![Hit::MISS; rays.len()];
        let mut parts = parts.chunks_mut(1);
        let mut collectors: Vec<Collector<'_>> =
            rays.iter().map(|ray| Collector::new(&query, ray, parts.next().unwrap())).collect();
        let (mut packet_stack, mut single_stack) =
            (vec![PacketEntry::default(); bvh.stack_size], vec![StackEntry::default(); bvh.stack_size]);
        let stacks = (&mut packet_stack[..], &mut single_stack[..]);
        let scope = InstanceScope::WORLD.enter(&bvh.instances[slot]);
        let mut stats = TraceStats::default();
        // SAFETY: the CPU has AVX2 and the rest (this function's contract).
        unsafe {
            bvh.carry_packet::<__m256, true>(slot, child, &rays, 0xFF, stacks, &scope, &mut collectors, &mut stats)
        }
    }

    #[test]
    fn rays_that_make_a_packet_make_one_in_turned_and_nested_instances_and_under_a_transform() {
        if !has_avx2() {
            return;
        }
        let context = Context::new(Device::cpu());
        let (scene, _) = scene(&context);
        let CpuAccel::Instances(bvh) = cpu_child(&scene).unwrap() else { panic!("an instance accel") };
        let slot = |id: u32| bvh.instances.iter().position(|instance| instance.instance_id == id).unwrap();
        let rays = camera_rays();
        let neighbours = &rays[64 * 30..64 * 30 + 8];
        // SAFETY (all): the CPU has AVX2 and the rest, as checked above.
        for id in [1, 2, 3, 4, 5, 6] {
            assert!(unsafe { carry_packet(bvh, slot(id), neighbours) }, "instance {id}");
        }
    }

    #[test]
    fn packets_that_meet_motion_transforms_give_every_ray_the_answer_it_gets_alone() {
        let context = Context::new(Device::cpu());
        let (_, lattice) = scene(&context);
        let motion = |keys: u32, flags: MotionFlags| MotionOptions { keys, time_begin: 0.0, time_end: 1.0, flags };
        let shifted = |by: Vec3| Placement::rows(&Affine3A::from_translation(by));
        let sliding = TransformInput::MatrixMotion {
            keys: vec![shifted(Vec3::ZERO), shifted(Vec3::new(0.1, -0.05, 0.05))],
            motion: motion(2, MotionFlags::END_VANISH),
        };
        // Turning about z through 3 keys (OptiX's SRT layout: the quaternion in elements 9–12).
        let turned = |angle: f32| {
            let mut key = [1., 0., 0., 0., 1., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0.];
            key[9..13].copy_from_slice(&Quat::from_rotation_z(angle).to_array());
            key
        };
        let turning = TransformInput::SrtMotion {
            keys: vec![turned(0.0), turned(0.1), turned(0.25)],
            motion: motion(3, MotionFlags::START_VANISH),
        };
        let [sliding, turning] = [sliding, turning].map(|input| context.build_transform(&input, &lattice).unwrap());
        let tilted = Affine3A::from_rotation_translation(Quat::from_rotation_x(0.15), Vec3::new(0.3, 0.2, 0.2));
        let instances = [
            instance(1, Affine3A::IDENTITY, 0xFF, InstanceFlags::empty(), &sliding),
            instance(2, tilted, 0xFF, InstanceFlags::FLIP_FACING, &turning),
        ];
        let scene = context.build_instance_accel(&instances, &BuildOptions::default()).unwrap();
        let accel = cpu_child(&scene).unwrap();
        for width in widths() {
            let rays = in_packet_order(&at_times(camera_rays()), width);
            // The full format: world normals, which each ray's own placement of the lattice turns.
            packets_agree(accel, "pinhole", &rays, width, HitFormat::Full);
        }
    }
}
