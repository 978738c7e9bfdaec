//! Updates (refits): a deformed mesh traces as a fresh build of it; structure changes and accels built without
//! `ALLOW_UPDATE` are refused; instance accels follow moved instances; accels placing an updated child refuse
//! traces until they are updated themselves (or the update is undone); handles, referrers and memory stay right.

mod common;

use std::sync::Arc;

use common::shared_mesh;
use glam::{Affine3A, Vec3};
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{
    BuildInput, Instance, InstanceFlags, MotionFlags, MotionOptions, Placement, TriangleInput,
};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, TraceOutput};
use rayd_engine::raygen::Camera;
use rayd_engine::{Accel, Context, Device, ErrorKind};

/// `mesh` bent: y stretched by 1.3 and x sheared by z.
fn deformed(mesh: &Mesh) -> Mesh {
    let positions = mesh.positions.iter().map(|p| Vec3::new(p.x + 0.4 * p.z, p.y * 1.3, p.z)).collect();
    Mesh { positions, triangles: mesh.triangles.clone() }
}

/// Closest hits of a camera framing `lo..hi`, or the error of the trace.
fn hits(context: &Context, accel: &Accel, (lo, hi): (Vec3, Vec3)) -> Result<Vec<u8>, rayd_engine::Error> {
    let rays = Camera::framing(lo, hi, 80, 60).rays(RayFormat::OriginDirection);
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriidInstidUV);
    let mut out = vec![0u8; query.output_layout(rays.len()).unwrap().hits];
    context.trace(accel, &query, &rays, TraceOutput { hits: &mut out, counts: &mut [] })?;
    Ok(out)
}

/// The box around both meshes.
fn around(a: &Mesh, b: &Mesh) -> (Vec3, Vec3) {
    let ((a0, a1), (b0, b1)) = (a.bounds(), b.bounds());
    (a0.min(b0), a1.max(b1))
}

#[test]
fn a_refitted_mesh_traces_as_a_fresh_build_and_structure_changes_are_refused() {
    let context = Context::new(Device::cpu());
    let mesh = shared_mesh("cow");
    let bent = deformed(&mesh);
    let view = around(&mesh, &bent);
    let (packed, packed_bent) = (mesh.pack(), bent.pack());
    let updatable = BuildOptions::new(BuildFlags::ALLOW_UPDATE);
    let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &updatable).unwrap();
    let updated = context.update_accel(&accel, &[BuildInput::Triangles(packed_bent.input())]).unwrap();
    assert_eq!(updated.handle(), accel.handle(), "an update keeps the handle");
    assert_eq!(context.accel(accel.handle()).unwrap().info().bounds, updated.info().bounds);
    let fresh = context.build_accel(&[BuildInput::Triangles(packed_bent.input())], &BuildOptions::default()).unwrap();
    let expected = hits(&context, &fresh, view).unwrap();
    assert_eq!(hits(&context, &updated, view).unwrap(), expected, "refitted = rebuilt, byte for byte");
    assert_ne!(hits(&context, &accel, view).unwrap(), expected, "a trace holding the old version sees the old mesh");
    assert!(updated.info().bounds.1.y > accel.info().bounds.1.y * 1.2, "the bounds follow the vertices");

    // Another topology, another triangle count, and an accel built without ALLOW_UPDATE.
    let mut turned = packed_bent.clone();
    turned.indices.swap(0, 4);
    let error = context.update_accel(&updated, &[BuildInput::Triangles(turned.input())]).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition);
    assert!(error.to_string().contains("input 0: different indices (topology)"), "{error}");
    let mut fewer = packed_bent.clone();
    fewer.indices.truncate(fewer.indices.len() - 12);
    let error = context.update_accel(&updated, &[BuildInput::Triangles(fewer.input())]).unwrap_err();
    assert!(error.to_string().contains("triangles where the build had"), "{error}");
    let error = context.update_accel(&fresh, &[BuildInput::Triangles(packed.input())]).unwrap_err();
    assert!(error.to_string().contains("ALLOW_UPDATE"), "{error}");
    // The version an update replaced cannot be updated again: that would drop the update made since.
    let error = context.update_accel(&accel, &[BuildInput::Triangles(packed.input())]).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition);
    assert!(error.to_string().contains("was replaced by an update"), "{error}");
    assert!(Arc::ptr_eq(&context.accel(accel.handle()).unwrap(), &updated), "the current version stays");

    // The old version's memory goes when its last holder lets go.
    let before = context.memory_in_use();
    drop(accel);
    assert!(context.memory_in_use() < before);
}

#[test]
fn instance_accels_follow_moved_instances_and_refuse_traces_until_updated_after_a_child_is() {
    let context = Context::new(Device::cpu());
    let mesh = shared_mesh("teapot").normalized_at(Vec3::ZERO);
    let bent = deformed(&mesh);
    let (packed, packed_bent) = (mesh.pack(), bent.pack());
    let updatable = BuildOptions::new(BuildFlags::ALLOW_UPDATE);
    let child = context.build_accel(&[BuildInput::Triangles(packed.input())], &updatable).unwrap();
    let at = |child: &Arc<Accel>, x: f32| Instance {
        transform: Placement::rows(&Affine3A::from_translation(Vec3::new(x, 0.0, 0.0))),
        instance_id: 5,
        mask: 0xFF,
        flags: InstanceFlags::empty(),
        child: Arc::clone(child),
    };
    let scene = context.build_instance_accel(&[at(&child, 0.0)], &updatable).unwrap();
    let view = (Vec3::new(-1.5, -1.0, -1.0), Vec3::new(3.5, 1.0, 1.0));
    let moved = context.update_instance_accel(&scene, &[at(&child, 2.0)]).unwrap();
    let expected = context.build_instance_accel(&[at(&child, 2.0)], &BuildOptions::default()).unwrap();
    assert_eq!(hits(&context, &moved, view).unwrap(), hits(&context, &expected, view).unwrap(), "moved");
    context.destroy_accel(expected.handle()).unwrap();
    drop(expected);

    // The child is updated: the scene still places its old version, and refuses to trace.
    let new_child = context.update_accel(&child, &[BuildInput::Triangles(packed_bent.input())]).unwrap();
    let error = hits(&context, &moved, view).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition);
    assert!(error.to_string().contains("as it was before an update"), "{error}");
    // Undone (as a server does when it cannot store the update): the old version is current, and traces, again.
    context.undo_update(&child, &new_child).unwrap();
    assert!(Arc::ptr_eq(&context.accel(child.handle()).unwrap(), &child), "the old version is current again");
    assert!(hits(&context, &moved, view).is_ok(), "the scene traces again");
    let error = context.undo_update(&child, &new_child).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition);
    assert!(error.to_string().contains("is not its current version"), "{error}");
    let new_child = context.update_accel(&child, &[BuildInput::Triangles(packed_bent.input())]).unwrap();
    assert!(hits(&context, &moved, view).is_err(), "superseded again");
    let refreshed = context.update_instance_accel(&moved, &[at(&new_child, 2.0)]).unwrap();
    let fresh_child =
        context.build_accel(&[BuildInput::Triangles(packed_bent.input())], &BuildOptions::default()).unwrap();
    let expected = context.build_instance_accel(&[at(&fresh_child, 2.0)], &BuildOptions::default()).unwrap();
    assert_eq!(hits(&context, &refreshed, view).unwrap(), hits(&context, &expected, view).unwrap(), "refreshed");

    // Another child or another count is refused; the child stays undestroyable while placed.
    let error = context.update_instance_accel(&refreshed, &[at(&fresh_child, 2.0)]).unwrap_err();
    assert!(error.to_string().contains("not the accel the build placed there"), "{error}");
    // An accel of another context with the child's handle number is another accel too.
    let other = Context::new(Device::cpu());
    let lookalike = other.build_accel(&[BuildInput::Triangles(packed_bent.input())], &updatable).unwrap();
    assert_eq!(lookalike.handle(), new_child.handle(), "both contexts' first accels");
    let error = context.update_instance_accel(&refreshed, &[at(&lookalike, 2.0)]).unwrap_err();
    assert!(error.to_string().contains("nor a version of it"), "{error}");
    let error = context.update_instance_accel(&refreshed, &[at(&new_child, 0.0), at(&new_child, 1.0)]).unwrap_err();
    assert!(error.to_string().contains("2 instances where the build had 1"), "{error}");
    assert_eq!(context.destroy_accel(child.handle()).unwrap_err().kind(), ErrorKind::FailedPrecondition);
}

#[test]
fn an_instance_accel_traces_a_moving_child_whose_update_deepened_its_wide_tree() {
    // A moving child's wide tree is collapsed again by every update, from the refitted boxes. Vertices flattened to
    // z = 0 and stretched along x past what a float's box side can hold give the upper boxes an infinite side beside
    // a zero one (a NaN area), so that the collapse opens fewer of their lanes and the tree gets deeper. The instance
    // accel updated over that version must still have stack enough for a walk into it.
    let context = Context::new(Device::cpu());
    let mesh = shared_mesh("cow").normalized_at(Vec3::ZERO);
    let (lo, hi) = mesh.bounds();
    let flat = Mesh {
        positions: mesh
            .positions
            .iter()
            .map(|p| Vec3::new(((p.x - lo.x) / (hi.x - lo.x) * 2.0 - 1.0) * 3e38, p.y, 0.0))
            .collect(),
        triangles: mesh.triangles.clone(),
    };
    let (packed, packed_flat) = (mesh.pack(), flat.pack());
    let motion = MotionOptions { keys: 2, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
    let options = BuildOptions { motion, ..BuildOptions::new(BuildFlags::ALLOW_UPDATE) };
    let (still, flat_keys) = ([packed.vertices.as_slice()], [packed_flat.vertices.as_slice()]);
    let child = context
        .build_accel(&[BuildInput::Triangles(TriangleInput { motion_vertices: &still, ..packed.input() })], &options)
        .unwrap();
    let instance = |child: &Arc<Accel>| Instance {
        transform: Placement::rows(&Affine3A::IDENTITY),
        instance_id: 1,
        mask: 0xFF,
        flags: InstanceFlags::empty(),
        child: Arc::clone(child),
    };
    let updatable = BuildOptions::new(BuildFlags::ALLOW_UPDATE);
    let scene = context.build_instance_accel(&[instance(&child)], &updatable).unwrap();
    let flat_input = BuildInput::Triangles(TriangleInput { motion_vertices: &flat_keys, ..packed_flat.input() });
    let flattened = context.update_accel(&child, &[flat_input]).unwrap();
    let scene = context.update_instance_accel(&scene, &[instance(&flattened)]).unwrap();
    let view = (Vec3::splat(-1.0), Vec3::splat(1.0));
    assert_eq!(hits(&context, &scene, view).unwrap().len(), hits(&context, &flattened, view).unwrap().len());
}
