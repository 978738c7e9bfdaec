//! Serialized accels: round trips of every kind of accel (geometry with masks, inputs, random vertex access,
//! updates and compaction; motion geometry; instance accels static and moving over static, matrix and SRT
//! transforms, nested, with a shared child) trace bit for bit as the originals, report the same info and keep
//! working (updates, copies, compaction, vertex access); external children; and blobs that are damaged,
//! truncated, incompatible or hostile (their checksum recomputed) are refused with the right kind of error,
//! never a panic, and leave nothing behind.
//!
//! The blob's layout is the one documented in `rayd_engine::serialize`; the hostile blobs are made by finding
//! fields through it.

mod common;

use std::collections::HashSet;
use std::sync::Arc;

use common::{icosphere, input_with_masks, pack_rays, random_rays, random_soup};
use glam::{Quat, Vec3};
use rayd_engine::accel::{AccelKind, BuildFlags, BuildOptions};
use rayd_engine::format::{HitFormat, Ray, RayFormat};
use rayd_engine::geometry::{
    BuildInput, GeometryFlags, Instance, InstanceFlags, MotionFlags, MotionOptions, Placement, TransformInput,
    TriangleInput,
};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::raygen::uniform;
use rayd_engine::serialize::blob_summary;
use rayd_engine::{Accel, Context, Device, Error, ErrorKind};

// ---------------------------------------------------------------------------------------------------------------
// Scenes.
// ---------------------------------------------------------------------------------------------------------------

/// A CPU context.
fn cpu() -> Context {
    Context::new(Device::cpu())
}

/// Every flag a geometry accel can keep.
const KEEP_ALL: BuildFlags =
    BuildFlags::ALLOW_UPDATE.union(BuildFlags::ALLOW_COMPACTION).union(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS);

/// Little-endian u32 bytes.
fn words(values: impl IntoIterator<Item = u32>) -> Vec<u8> {
    values.into_iter().flat_map(u32::to_le_bytes).collect()
}

/// Little-endian float3 bytes.
fn vertex_bytes(positions: &[Vec3]) -> Vec<u8> {
    positions.iter().flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect()
}

/// Two geometries, the second `shift`ed: a masked icosphere, and a soup with flags and a primitive-index offset
/// (with a degenerate triangle), as build-input bytes: (vertices, indices, masks) of each.
fn two_meshes(shift: Vec3) -> [(Vec<u8>, Vec<u8>, Vec<u8>); 2] {
    let sphere = icosphere(2, Vec3::new(0.5, 0.5, 0.5) + shift);
    let mut soup = random_soup(300, 7);
    soup.positions.iter_mut().for_each(|p| *p += shift);
    soup.triangles.push([0, 0, 1]);
    let pack = |mesh: &Mesh, mask: fn(usize) -> u32| {
        let packed = mesh.pack();
        (packed.vertices, packed.indices, words((0..mesh.triangles.len()).map(mask)))
    };
    [pack(&sphere, |i| 1 << (i % 4)), pack(&soup, |_| 0)]
}

/// The build inputs over [`two_meshes`].
fn two_inputs(meshes: &[(Vec<u8>, Vec<u8>, Vec<u8>); 2]) -> Vec<BuildInput<'_>> {
    let [(v0, i0, m0), (v1, i1, _)] = meshes;
    vec![
        input_with_masks(v0, i0, m0),
        BuildInput::Triangles(TriangleInput {
            flags: GeometryFlags::DISABLE_FACE_CULLING,
            primitive_index_offset: 1000,
            ..TriangleInput::indexed(v1, i1)
        }),
    ]
}

/// A geometry accel over [`two_meshes`] keeping everything.
fn masked_geometry(context: &Context, shift: Vec3) -> Arc<Accel> {
    let meshes = two_meshes(shift);
    context.build_accel(&two_inputs(&meshes), &BuildOptions::new(KEEP_ALL)).unwrap()
}

/// Motion options.
fn motion(keys: u32, time_begin: f32, time_end: f32, flags: MotionFlags) -> MotionOptions {
    MotionOptions { keys, time_begin, time_end, flags }
}

/// A soup of `count` triangles moving along a wobbly path over `options`' keys, scaled by `scale`.
fn moving_geometry(context: &Context, count: usize, options: &BuildOptions, scale: f32) -> Arc<Accel> {
    let soup = random_soup(count, 11);
    let keys: Vec<Vec<u8>> = (0..options.motion.keys)
        .map(|k| {
            let offset = Vec3::new(0.1 * k as f32, 0.05 * (k % 2) as f32, -0.03 * k as f32);
            vertex_bytes(&soup.positions.iter().map(|&p| p * scale + offset).collect::<Vec<_>>())
        })
        .collect();
    let indices = soup.pack().indices;
    let motion_vertices: Vec<&[u8]> = keys[1..].iter().map(Vec::as_slice).collect();
    let input = TriangleInput { motion_vertices: &motion_vertices, ..TriangleInput::indexed(&keys[0], &indices) };
    context.build_accel(&[BuildInput::Triangles(input)], options).unwrap()
}

/// A 3×4 row-major matrix: a rotation about `axis` by `angle`, a scale and a translation.
fn matrix(axis: Vec3, angle: f32, scale: Vec3, translation: Vec3) -> [f32; 12] {
    Placement::rows(&glam::Affine3A::from_scale_rotation_translation(
        scale,
        Quat::from_axis_angle(axis.normalize(), angle),
        translation,
    ))
}

/// An SRT key: scale `s`, rotation `q` (not normalized on purpose), translation `t`.
fn srt(s: Vec3, q: Quat, t: Vec3) -> [f32; 16] {
    [s.x, 0.1, 0.0, 0.2, s.y, 0.0, -0.1, s.z, 0.0, q.x, q.y, q.z, q.w, t.x, t.y, t.z]
}

/// An instance.
fn instance(child: &Arc<Accel>, transform: [f32; 12], id: u32) -> Instance {
    Instance {
        transform,
        instance_id: id,
        mask: if id % 5 == 4 { 0x02 } else { 0xFF },
        flags: if id % 3 == 2 { InstanceFlags::FLIP_FACING } else { InstanceFlags::empty() },
        child: Arc::clone(child),
    }
}

/// A nested graph over every kind of accel:
/// `root` (motion instances, `ALLOW_UPDATE`) places `middle` (static instances) and an SRT transform; `middle`
/// places a geometry accel 12 times, a static transform of it, a matrix motion transform of a moving geometry,
/// and a nested instance accel over that geometry. Returns the root and the distinct accels of the graph.
fn nested_graph(context: &Context) -> (Arc<Accel>, usize) {
    let still = masked_geometry(context, Vec3::ZERO);
    let moving = moving_geometry(
        context,
        200,
        &BuildOptions { motion: motion(3, -0.5, 1.5, MotionFlags::END_VANISH), ..BuildOptions::new(KEEP_ALL) },
        0.6,
    );
    let static_transform = context
        .build_transform(
            &TransformInput::Static(matrix(Vec3::Y, 0.7, Vec3::splat(0.4), Vec3::new(2.0, 0.0, 0.0))),
            &still,
        )
        .unwrap();
    let matrix_motion = context
        .build_transform(
            &TransformInput::MatrixMotion {
                keys: vec![
                    matrix(Vec3::Z, 0.0, Vec3::ONE, Vec3::new(0.0, 1.5, 0.0)),
                    matrix(Vec3::Z, 0.6, Vec3::new(1.0, 0.5, 1.0), Vec3::new(0.3, 1.5, 0.0)),
                ],
                motion: motion(2, 0.0, 1.0, MotionFlags::START_VANISH),
            },
            &moving,
        )
        .unwrap();
    let inner = context
        .build_instance_accel(
            &[instance(&moving, matrix(Vec3::X, 0.3, Vec3::ONE, Vec3::new(-1.5, 0.0, 0.0)), 70)],
            &BuildOptions::default(),
        )
        .unwrap();
    let mut placed: Vec<Instance> = (0..12)
        .map(|i| {
            let at = Vec3::new((i % 4) as f32 * 1.1 - 1.5, (i / 4) as f32 * 1.1 - 1.0, 0.2 * i as f32);
            instance(&still, matrix(Vec3::new(1.0, 1.0, 0.0), i as f32, Vec3::splat(0.3 + 0.05 * i as f32), at), i)
        })
        .collect();
    placed.push(instance(&static_transform, matrix(Vec3::Y, 0.0, Vec3::ONE, Vec3::ZERO), 20));
    placed.push(instance(&matrix_motion, matrix(Vec3::Y, 0.2, Vec3::ONE, Vec3::new(0.0, -0.5, 0.5)), 21));
    placed.push(instance(&inner, matrix(Vec3::X, 0.0, Vec3::ONE, Vec3::ZERO), 22));
    let middle = context.build_instance_accel(&placed, &BuildOptions::new(BuildFlags::ALLOW_COMPACTION)).unwrap();
    let spin = |angle: f32, t: Vec3| srt(Vec3::new(0.5, 0.6, 0.7), Quat::from_rotation_y(angle) * 1.7, t);
    let srt_motion = context
        .build_transform(
            &TransformInput::SrtMotion {
                keys: vec![spin(0.0, Vec3::ZERO), spin(1.0, Vec3::new(0.2, 0.0, 0.0)), spin(2.0, Vec3::ONE)],
                motion: motion(3, 0.0, 1.0, MotionFlags::empty()),
            },
            &middle,
        )
        .unwrap();
    let root = context
        .build_instance_accel(
            &[
                instance(&middle, matrix(Vec3::Z, 0.1, Vec3::ONE, Vec3::ZERO), 100),
                instance(&srt_motion, matrix(Vec3::Z, 0.0, Vec3::ONE, Vec3::new(0.0, 0.0, -2.0)), 101),
                instance(&still, matrix(Vec3::X, 1.0, Vec3::splat(2.0), Vec3::new(0.0, -2.0, 0.0)), 102),
            ],
            &BuildOptions {
                motion: motion(2, 0.0, 1.0, MotionFlags::START_VANISH),
                flags: BuildFlags::ALLOW_UPDATE | BuildFlags::ALLOW_COMPACTION,
            },
        )
        .unwrap();
    (root, 8)
}

/// The accels of `root`'s graph, each once, children first (as a blob embeds them).
fn children_first(root: &Arc<Accel>) -> Vec<Arc<Accel>> {
    fn visit(accel: &Arc<Accel>, seen: &mut HashSet<*const Accel>, out: &mut Vec<Arc<Accel>>) {
        for child in accel.children() {
            if !seen.contains(&Arc::as_ptr(child)) {
                visit(child, seen, out);
            }
        }
        seen.insert(Arc::as_ptr(accel));
        out.push(Arc::clone(accel));
    }
    let mut out = Vec::new();
    visit(root, &mut HashSet::new(), &mut out);
    out
}

// ---------------------------------------------------------------------------------------------------------------
// Tracing.
// ---------------------------------------------------------------------------------------------------------------

/// Random rays around the scenes, at times from −1 to 2 (outside the motion ranges too).
fn rays(count: usize, seed: u64) -> Vec<Ray> {
    random_rays(count, seed)
        .into_iter()
        .enumerate()
        .map(|(i, ray)| Ray {
            origin: ray.origin * 3.0,
            direction: ray.direction,
            time: uniform(seed ^ 0x5eed, i as u64) * 3.0 - 1.0,
            tmax: f32::INFINITY,
            visibility: if i % 7 == 0 { 0x02 } else { 0xFF },
            ..ray
        })
        .collect()
}

/// The queries compared: closest and all hits, in both ray formats that carry a time.
fn queries() -> Vec<Query> {
    let closest = |ray_format| Query::closest(ray_format, HitFormat::Full);
    let mut queries = Vec::new();
    for ray_format in [RayFormat::OriginTminDirectionTmaxTime, RayFormat::Full] {
        queries.push(closest(ray_format));
        queries.push(Query { kind: QueryKind::All, max_hits_per_ray: 6, ..closest(ray_format) });
    }
    queries
}

/// The hit and count bytes of every query over `rays`.
fn trace_all(context: &Context, accel: &Accel, rays: &[Ray]) -> Vec<(Vec<u8>, Vec<u8>)> {
    queries()
        .iter()
        .map(|query| {
            let bytes = pack_rays(rays, query.ray_format);
            let layout = query.output_layout(bytes.len()).unwrap();
            let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
            context.trace(accel, query, &bytes, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
            (hits, counts)
        })
        .collect()
}

/// Hits found by a closest query of [`trace_all`] (to check a scene is not trivially empty).
fn closest_hits(traced: &[(Vec<u8>, Vec<u8>)]) -> usize {
    traced[0].0.chunks_exact(80).filter(|r| f32::from_le_bytes(r[..4].try_into().unwrap()) >= 0.0).count()
}

/// Asserts that `loaded` (in `loaded_context`) reports the info of `original` and traces as it does.
fn assert_same(original_context: &Context, original: &Accel, loaded_context: &Context, loaded: &Accel) {
    assert_eq!(loaded.info(), original.info(), "info");
    assert_traces_same(original_context, original, loaded_context, loaded);
}

/// Asserts that `loaded` (in `loaded_context`) traces as `original` does.
fn assert_traces_same(original_context: &Context, original: &Accel, loaded_context: &Context, loaded: &Accel) {
    let rays = rays(3000, 5);
    let expected = trace_all(original_context, original, &rays);
    assert!(closest_hits(&expected) > 100, "the scene is hit ({} hits)", closest_hits(&expected));
    assert!(trace_all(loaded_context, loaded, &rays) == expected, "traces differ");
}

/// Serializes `root` with everything embedded, loads it into a fresh context and checks the load: as many accels
/// as the graph has distinct ones, each with its original's info, the root tracing as the original, and the
/// loaded graph serializing to the very same bytes.
fn round_trip(context: &Context, root: &Arc<Accel>) -> (Context, Vec<Arc<Accel>>) {
    let blob = context.serialize_accel(root, &[]).unwrap();
    let summary = blob_summary(&blob).unwrap();
    let originals = children_first(root);
    assert_eq!((summary.format_version, summary.external), (1, 0));
    assert_eq!(summary.accels as usize, originals.len());
    assert_eq!(summary.total_bytes, blob.len() as u64);
    let loaded_context = cpu();
    let loaded = loaded_context.deserialize_accel(&blob, &[]).unwrap();
    assert_eq!(loaded.len(), originals.len(), "one accel per distinct accel of the graph");
    assert_eq!(loaded_context.accel_handles().len(), loaded.len());
    for (original, copy) in originals.iter().zip(&loaded) {
        assert_eq!(copy.info(), original.info());
        assert_eq!(copy.children().len(), original.children().len());
    }
    let loaded_root = loaded.last().unwrap();
    assert_same(context, root, &loaded_context, loaded_root);
    let sizes: u64 = loaded.iter().map(|a| a.info().size_bytes).sum();
    assert_eq!(loaded_context.memory_in_use(), sizes, "every loaded accel is charged as a build would be");
    assert!(loaded_context.serialize_accel(loaded_root, &[]).unwrap() == blob, "re-serialized bytes differ");
    (loaded_context, loaded)
}

/// Asserts that `copy` of `accel` (in `context`) and a compacted copy trace as it does.
fn assert_copies_trace_the_same(context: &Context, accel: &Arc<Accel>) {
    for compact in [false, true] {
        let copy = context.copy_accel(accel, compact).unwrap();
        assert_same(context, accel, context, &copy);
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Round trips.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn a_geometry_accel_with_masks_two_inputs_and_every_flag_round_trips_and_keeps_working() {
    let context = cpu();
    let original = masked_geometry(&context, Vec3::ZERO);
    let (loaded_context, loaded) = round_trip(&context, &original);
    let loaded = &loaded[0];
    assert_eq!(loaded.info().geometry_count, 2);
    for (geom, prims) in [(0u32, 0..320u32), (1, 998..1302), (2, 0..2)] {
        for prim in prims {
            let (a, b) = (original.triangle_vertices(geom, prim), loaded.triangle_vertices(geom, prim));
            assert_eq!(a, b, "vertices of ({geom}, {prim})");
        }
    }
    assert!(loaded.triangle_vertices(1, 1300).is_ok() && loaded.triangle_vertices(1, 1301).is_err());

    // An update after the load traces as the same update of the original.
    let moved = two_meshes(Vec3::new(0.05, -0.1, 0.02));
    let updated = context.update_accel(&original, &two_inputs(&moved)).unwrap();
    let loaded_updated = loaded_context.update_accel(loaded, &two_inputs(&moved)).unwrap();
    assert_same(&context, &updated, &loaded_context, &loaded_updated);
    let other = two_meshes(Vec3::ZERO);
    let mut other_inputs = two_inputs(&other);
    other_inputs.pop();
    assert_eq!(
        loaded_context.update_accel(&loaded_updated, &other_inputs).unwrap_err().kind(),
        ErrorKind::FailedPrecondition
    );

    assert_copies_trace_the_same(&loaded_context, &loaded_updated);
}

#[test]
fn motion_geometry_accels_round_trip_with_vanish_flags_and_update_after_the_load() {
    for (keys, flags) in [(2, MotionFlags::START_VANISH | MotionFlags::END_VANISH), (3, MotionFlags::END_VANISH)] {
        let context = cpu();
        let options = BuildOptions { motion: motion(keys, -0.25, 1.25, flags), ..BuildOptions::new(KEEP_ALL) };
        let original = moving_geometry(&context, 500, &options, 1.0);
        let (loaded_context, loaded) = round_trip(&context, &original);
        assert_eq!(loaded[0].info().options.motion, options.motion);
        for prim in [0, 17, 499] {
            assert_eq!(loaded[0].triangle_vertices(0, prim), original.triangle_vertices(0, prim));
        }
        // The same update (new keys of the same structure) after the load.
        let soup = random_soup(500, 11);
        let keys_bytes: Vec<Vec<u8>> = (0..keys)
            .map(|k| {
                vertex_bytes(
                    &soup.positions.iter().map(|&p| p * 0.9 + Vec3::splat(0.02 * k as f32)).collect::<Vec<_>>(),
                )
            })
            .collect();
        let indices = soup.pack().indices;
        let motion_vertices: Vec<&[u8]> = keys_bytes[1..].iter().map(Vec::as_slice).collect();
        let input = [BuildInput::Triangles(TriangleInput {
            motion_vertices: &motion_vertices,
            ..TriangleInput::indexed(&keys_bytes[0], &indices)
        })];
        let updated = context.update_accel(&original, &input).unwrap();
        let loaded_updated = loaded_context.update_accel(&loaded[0], &input).unwrap();
        assert_same(&context, &updated, &loaded_context, &loaded_updated);
        assert_copies_trace_the_same(&loaded_context, &loaded_updated);
    }
}

#[test]
fn a_nested_graph_of_every_kind_round_trips_with_its_shared_children_stored_once() {
    let context = cpu();
    let (root, distinct) = nested_graph(&context);
    let (loaded_context, loaded) = round_trip(&context, &root);
    assert_eq!(loaded.len(), distinct, "the geometry accel placed 14 times is stored once");
    let kinds: Vec<AccelKind> = loaded.iter().map(|a| a.info().kind).collect();
    for kind in [AccelKind::Transform, AccelKind::MatrixMotionTransform, AccelKind::SrtMotionTransform] {
        assert!(kinds.contains(&kind), "{kind:?} in {kinds:?}");
    }
    assert_eq!(root.info().depth, 5);
    let loaded_root = loaded.last().unwrap();

    // The loaded graph shares its children again: the geometry accel placed by `middle` and `root` is one accel.
    let still = &loaded[0];
    assert_eq!(still.info().kind, AccelKind::Triangles);
    let sharers = loaded.iter().filter(|a| a.children().iter().any(|c| Arc::ptr_eq(c, still))).count();
    assert_eq!(sharers, 3, "the static transform, the middle and the root place it");
    // Loaded children cannot be destroyed while loaded parents place them.
    let err = loaded_context.destroy_accel(still.handle()).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::FailedPrecondition);

    // An update of the root after the load, with new transforms over the same (loaded) children.
    let update = |children: &[Arc<Accel>]| -> Vec<Instance> {
        children
            .iter()
            .enumerate()
            .map(|(i, child)| {
                instance(child, matrix(Vec3::Y, 0.3 * i as f32, Vec3::ONE, Vec3::splat(0.1 * i as f32)), 200 + i as u32)
            })
            .collect()
    };
    let updated = context.update_instance_accel(&root, &update(root.children())).unwrap();
    let loaded_updated = loaded_context.update_instance_accel(loaded_root, &update(loaded_root.children())).unwrap();
    assert_same(&context, &updated, &loaded_context, &loaded_updated);
    assert_copies_trace_the_same(&loaded_context, &loaded_updated);

    // Once every loaded parent is gone, the children can go too.
    drop((loaded_updated, loaded));
    for handle in loaded_context.accel_handles().into_iter().rev() {
        loaded_context.destroy_accel(handle).unwrap();
    }
    assert_eq!(loaded_context.memory_in_use(), 0);
}

#[test]
fn a_transform_updated_after_the_load_traces_as_the_original_updated() {
    let context = cpu();
    let geometry = masked_geometry(&context, Vec3::ZERO);
    let keys = |angle: f32| TransformInput::SrtMotion {
        keys: vec![
            srt(Vec3::ONE, Quat::IDENTITY * 2.0, Vec3::ZERO),
            srt(Vec3::splat(0.8), Quat::from_rotation_x(angle), Vec3::X),
        ],
        motion: motion(2, 0.0, 1.0, MotionFlags::END_VANISH),
    };
    let original = context.build_transform(&keys(0.8), &geometry).unwrap();
    let (loaded_context, loaded) = round_trip(&context, &original);
    let updated = context.update_transform(&original, &keys(1.2), &geometry).unwrap();
    let loaded_updated = loaded_context.update_transform(&loaded[1], &keys(1.2), &loaded[0]).unwrap();
    assert_same(&context, &updated, &loaded_context, &loaded_updated);
}

#[test]
fn empty_accels_round_trip() {
    let context = cpu();
    // A geometry accel of degenerate triangles only (no node at all) and an instance accel without instances.
    let flat = vertex_bytes(&[Vec3::ZERO, Vec3::X, Vec3::X * 2.0]);
    let indices = words([0, 1, 2, 2, 1, 0]);
    let inputs = [BuildInput::Triangles(TriangleInput::indexed(&flat, &indices))];
    let geometry = context.build_accel(&inputs, &BuildOptions::new(KEEP_ALL)).unwrap();
    let none = context.build_instance_accel(&[], &BuildOptions::new(BuildFlags::ALLOW_UPDATE)).unwrap();
    let root = context
        .build_instance_accel(
            &[
                instance(&geometry, matrix(Vec3::X, 0.0, Vec3::ONE, Vec3::ZERO), 1),
                instance(&none, matrix(Vec3::X, 0.0, Vec3::ONE, Vec3::ZERO), 2),
            ],
            &BuildOptions::default(),
        )
        .unwrap();
    let blob = context.serialize_accel(&root, &[]).unwrap();
    let loaded_context = cpu();
    let loaded = loaded_context.deserialize_accel(&blob, &[]).unwrap();
    for (original, copy) in children_first(&root).iter().zip(&loaded) {
        assert_eq!(copy.info(), original.info());
    }
    for (geom, prim) in [(0, 0), (0, 1), (0, 2), (1, 0)] {
        assert_eq!(loaded[0].triangle_vertices(geom, prim), geometry.triangle_vertices(geom, prim), "({geom}, {prim})");
    }
    let rays = rays(100, 3);
    assert!(trace_all(&loaded_context, &loaded[2], &rays) == trace_all(&context, &root, &rays));
    assert!(loaded_context.serialize_accel(&loaded[2], &[]).unwrap() == blob);
}

#[test]
fn stale_graphs_and_replaced_versions_are_not_serialized() {
    let context = cpu();
    let geometry = masked_geometry(&context, Vec3::ZERO);
    let parent = context
        .build_instance_accel(
            &[instance(&geometry, matrix(Vec3::X, 0.0, Vec3::ONE, Vec3::ZERO), 1)],
            &BuildOptions::default(),
        )
        .unwrap();
    let moved = two_meshes(Vec3::X);
    let updated = context.update_accel(&geometry, &two_inputs(&moved)).unwrap();
    for accel in [&parent, &geometry] {
        let err = context.serialize_accel(accel, &[]).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::FailedPrecondition, "{err}");
    }
    context.serialize_accel(&updated, &[]).unwrap();
}

// ---------------------------------------------------------------------------------------------------------------
// External children.
// ---------------------------------------------------------------------------------------------------------------

/// The instances of [`over_two_children`]'s instance accel.
fn three_instances(geometry: &Arc<Accel>, transform: &Arc<Accel>) -> Vec<Instance> {
    vec![
        instance(geometry, matrix(Vec3::X, 0.0, Vec3::ONE, Vec3::ZERO), 1),
        instance(transform, matrix(Vec3::X, 0.4, Vec3::ONE, Vec3::ZERO), 2),
        instance(geometry, matrix(Vec3::Y, 0.9, Vec3::splat(0.5), Vec3::new(1.0, 1.0, 0.0)), 3),
    ]
}

/// An instance accel over a geometry accel (placed twice, `shift`ed) and a static transform of a moving one, in
/// `context`; returns it and its direct children.
fn over_two_children(context: &Context, shift: Vec3) -> (Arc<Accel>, Vec<Arc<Accel>>) {
    let geometry = masked_geometry(context, shift);
    let moving = moving_geometry(
        context,
        100,
        &BuildOptions { motion: motion(2, 0.0, 1.0, MotionFlags::empty()), ..BuildOptions::default() },
        1.0,
    );
    let transform =
        context.build_transform(&TransformInput::Static(matrix(Vec3::Z, 0.5, Vec3::ONE, Vec3::Y)), &moving).unwrap();
    let parent = context
        .build_instance_accel(&three_instances(&geometry, &transform), &BuildOptions::new(BuildFlags::ALLOW_UPDATE))
        .unwrap();
    let children = parent.children().to_vec();
    (parent, children)
}

#[test]
fn external_children_are_referred_to_and_must_be_supplied_complete_and_of_their_kinds() {
    let context = cpu();
    let (parent, children) = over_two_children(&context, Vec3::ZERO);
    assert_eq!(children.len(), 2);
    let blob = context.serialize_accel(&parent, &children).unwrap();
    let summary = blob_summary(&blob).unwrap();
    assert_eq!((summary.accels, summary.external), (1, 2));
    assert!(blob.len() < 4096, "the children are not embedded ({} bytes)", blob.len());

    // Another context, with equivalent children built there.
    let other = cpu();
    let (_, equivalent) = over_two_children(&other, Vec3::ZERO);
    let loaded = other.deserialize_accel(&blob, &equivalent).unwrap();
    assert_eq!(loaded.len(), 1);
    assert_same(&context, &parent, &other, &loaded[0]);
    assert!(loaded[0].children().iter().zip(&equivalent).all(|(a, b)| Arc::ptr_eq(a, b)));
    assert_eq!(other.destroy_accel(equivalent[0].handle()).unwrap_err().kind(), ErrorKind::FailedPrecondition);

    // Wrong counts, wrong order: refused, nothing left behind.
    let before = other.accel_handles();
    for given in [&equivalent[..1], &[], &[equivalent[0].clone(), equivalent[1].clone(), equivalent[0].clone()][..]] {
        let err = other.deserialize_accel(&blob, given).unwrap_err();
        assert!(matches!(err, Error::InvalidExternal(_)), "{err}");
        assert_eq!(err.kind(), ErrorKind::InvalidArgument);
    }
    let swapped = [equivalent[1].clone(), equivalent[0].clone()];
    let err = other.deserialize_accel(&blob, &swapped).unwrap_err();
    assert!(err.to_string().contains("external accel 0"), "{err}");
    assert_eq!(other.accel_handles(), before);

    // Children of other bounds (newer versions): the parent loads stale, and traces once updated over them.
    let (moved_parent, moved) = over_two_children(&other, Vec3::new(0.2, -0.1, 0.0));
    let stale = other.deserialize_accel(&blob, &moved).unwrap().pop().unwrap();
    let (rays, query) = (pack_rays(&rays(10, 1), RayFormat::Full), Query::closest(RayFormat::Full, HitFormat::Full));
    let mut hits = vec![0u8; 10 * 80];
    let err = other.trace(&stale, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::FailedPrecondition, "{err}");
    assert_eq!(other.serialize_accel(&stale, &moved).unwrap_err().kind(), ErrorKind::FailedPrecondition);
    // Its copy places the same old versions: it refuses traces as the original does.
    let copy = other.copy_accel(&stale, false).unwrap();
    let err = other.trace(&copy, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::FailedPrecondition, "{err}");
    other.destroy_accel(copy.handle()).unwrap();
    let updated = other.update_instance_accel(&stale, &three_instances(&moved[0], &moved[1])).unwrap();
    assert_traces_same(&other, &moved_parent, &other, &updated);

    // A grandchild external, below an embedded transform: a newer version leaves the transform's parent stale.
    let moving = &children[1].children()[0];
    let blob = context.serialize_accel(&parent, std::slice::from_ref(moving)).unwrap();
    assert_eq!(blob_summary(&blob).unwrap().accels, 3);
    let options = BuildOptions { motion: motion(2, 0.0, 1.0, MotionFlags::empty()), ..BuildOptions::default() };
    for (scale, stale) in [(1.0, false), (1.2, true)] {
        let loaded = other.deserialize_accel(&blob, &[moving_geometry(&other, 100, &options, scale)]).unwrap();
        let traced = other.trace(&loaded[2], &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] });
        assert_eq!(traced.is_err(), stale, "scale {scale}");
    }

    // Refusals at serialization: the root among the external accels.
    assert_eq!(
        context.serialize_accel(&parent, std::slice::from_ref(&parent)).unwrap_err().kind(),
        ErrorKind::InvalidArgument
    );
}

#[test]
fn a_graph_persisted_one_accel_a_blob_restores_children_first() {
    let context = cpu();
    let (root, _) = nested_graph(&context);
    let originals = children_first(&root);
    let blobs: Vec<Vec<u8>> = originals.iter().map(|a| context.serialize_accel(a, a.children()).unwrap()).collect();
    let restored_context = cpu();
    let mut restored: Vec<Arc<Accel>> = Vec::new();
    for (original, blob) in originals.iter().zip(&blobs) {
        let children: Vec<Arc<Accel>> = original
            .children()
            .iter()
            .map(|c| Arc::clone(&restored[originals.iter().position(|o| Arc::ptr_eq(o, c)).unwrap()]))
            .collect();
        let mut made = restored_context.deserialize_accel(blob, &children).unwrap();
        assert_eq!(made.len(), 1);
        restored.push(made.pop().unwrap());
    }
    assert_same(&context, &root, &restored_context, restored.last().unwrap());
}

// ---------------------------------------------------------------------------------------------------------------
// Damaged, incompatible and hostile blobs.
// ---------------------------------------------------------------------------------------------------------------

/// A small graph: an instance accel (with `ALLOW_UPDATE`) placing a small masked geometry accel (every flag) twice
/// and a matrix motion transform of it.
fn small_graph(context: &Context) -> Arc<Accel> {
    let mesh = random_soup(12, 3);
    let packed = mesh.pack();
    let masks = words((0..12).map(|i| i % 3));
    let geometry = context
        .build_accel(&[input_with_masks(&packed.vertices, &packed.indices, &masks)], &BuildOptions::new(KEEP_ALL))
        .unwrap();
    let moving = context
        .build_transform(
            &TransformInput::MatrixMotion {
                keys: vec![matrix(Vec3::Z, 0.0, Vec3::ONE, Vec3::ZERO), matrix(Vec3::Z, 1.0, Vec3::ONE, Vec3::X)],
                motion: motion(2, 0.0, 1.0, MotionFlags::empty()),
            },
            &geometry,
        )
        .unwrap();
    context
        .build_instance_accel(
            &[
                instance(&geometry, matrix(Vec3::X, 0.0, Vec3::ONE, Vec3::ZERO), 1),
                instance(&moving, matrix(Vec3::Y, 0.5, Vec3::ONE, Vec3::new(0.0, 1.0, 0.0)), 2),
                instance(&geometry, matrix(Vec3::Z, 1.5, Vec3::splat(0.5), Vec3::new(1.0, 0.0, 0.0)), 3),
            ],
            &BuildOptions { motion: motion(2, 0.0, 1.0, MotionFlags::END_VANISH), flags: BuildFlags::ALLOW_UPDATE },
        )
        .unwrap()
}

/// Recomputes a blob's checksum (documented: the CRC-32 of every byte from offset 12, at offset 8).
fn reseal(blob: &mut [u8]) {
    let crc = crc32fast::hash(&blob[12..]);
    blob[8..12].copy_from_slice(&crc.to_le_bytes());
}

/// Loads `blob` into a fresh context and returns the error, checking that nothing was left behind.
fn load_error(blob: &[u8]) -> Error {
    let context = cpu();
    let err = context.deserialize_accel(blob, &[]).expect_err("the blob loads");
    assert!(context.accel_handles().is_empty(), "accels left behind after {err}");
    assert_eq!(context.memory_in_use(), 0);
    err
}

/// Asserts that loading `blob` fails as damage (INVALID_ARGUMENT); `what` says what was done to it.
fn assert_damaged(blob: &[u8], what: &str) {
    let err = load_error(blob);
    assert_eq!(err.kind(), ErrorKind::InvalidArgument, "{what}: {err}");
    assert!(matches!(err, Error::InvalidBlob(_)), "{what}: {err}");
}

#[test]
fn every_flipped_header_byte_sampled_payload_byte_truncation_and_appended_garbage_is_refused() {
    let context = cpu();
    let blob = context.serialize_accel(&small_graph(&context), &[]).unwrap();
    assert!(blob.len() < 6000, "a small blob: {} bytes", blob.len());
    for at in 0..blob.len() {
        if at < 48 || at % 3 == 0 {
            for bit in [0x01, 0x80] {
                let mut damaged = blob.clone();
                damaged[at] ^= bit;
                assert_damaged(&damaged, &format!("byte {at} ^ {bit:#x}"));
            }
        }
    }
    for len in 0..blob.len() {
        assert_damaged(&blob[..len], &format!("truncated to {len} bytes"));
    }
    for garbage in [&[0u8][..], b"garbage", &[0; 4096]] {
        let mut longer = blob.clone();
        longer.extend_from_slice(garbage);
        assert_damaged(&longer, &format!("{} bytes appended", garbage.len()));
    }
    assert_eq!(cpu().deserialize_accel(&blob, &[]).unwrap().len(), 3);
}

#[test]
fn incompatible_versions_layouts_backends_and_byte_orders_are_failed_preconditions_naming_the_field() {
    let context = cpu();
    let blob = context.serialize_accel(&small_graph(&context), &[]).unwrap();
    // Backend 2 (wgpu) loads on the CPU (both store the host structure); 3 is none this build knows.
    for (at, field, step) in
        [(12, "byte-order marker", 1), (16, "format version", 1), (20, "backend", 2), (24, "backend layout version", 1)]
    {
        let mut changed = blob.clone();
        let value = u32::from_le_bytes(changed[at..at + 4].try_into().unwrap());
        changed[at..at + 4].copy_from_slice(&(value + step).to_le_bytes());
        reseal(&mut changed);
        let err = load_error(&changed);
        assert_eq!(err.kind(), ErrorKind::FailedPrecondition, "{field}: {err}");
        assert!(matches!(&err, Error::IncompatibleBlob { field: f, .. } if *f == field), "{field}: {err}");
        let message = err.to_string();
        assert!(message.contains(&(value + step).to_string()) || message.contains("0x01020305"), "{message}");
    }
    // Written on a big-endian machine: the marker and the checksum read byte-swapped.
    let mut big = blob.clone();
    big[12..16].reverse();
    reseal(&mut big);
    big[8..12].reverse();
    assert!(matches!(load_error(&big), Error::IncompatibleBlob { field: "byte order", .. }));
}

/// Offsets of the fields of a blob without external accels, found through the documented layout.
struct Fields {
    /// Per entry: offset of its kind.
    entries: Vec<usize>,
    /// Per entry: offset of its child-reference array's count.
    children: Vec<usize>,
    /// Per entry: offset of its backend payload.
    payloads: Vec<usize>,
}

/// The little-endian u64 at `at`.
fn u64_at(blob: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(blob[at..at + 8].try_into().unwrap())
}

/// Finds the entries of `blob` (which has no external accels).
fn fields(blob: &[u8]) -> Fields {
    let accels = u32::from_le_bytes(blob[28..32].try_into().unwrap());
    assert_eq!(u64_at(blob, 48), 0, "no external records");
    let mut at = 56;
    let mut fields = Fields { entries: Vec::new(), children: Vec::new(), payloads: Vec::new() };
    for _ in 0..accels {
        fields.entries.push(at);
        let kind = u32::from_le_bytes(blob[at..at + 4].try_into().unwrap());
        at += 4 + 4 + 16 + 8 + 4 + 8;
        fields.children.push(at);
        at += 8 + 4 * u64_at(blob, at) as usize;
        at += 8 + 32 * u64_at(blob, at) as usize;
        let key_floats = if kind == 4 { 16 } else { 12 };
        at += 8 + 4 * key_floats * u64_at(blob, at) as usize;
        let payload = u64_at(blob, at) as usize;
        fields.payloads.push(at + 8);
        at += 8 + payload;
    }
    assert_eq!(at, blob.len());
    fields
}

/// Asserts that `blob` with `tamper` applied and its checksum recomputed is refused as INVALID_ARGUMENT with a
/// message containing `expected`.
fn assert_hostile(blob: &[u8], what: &str, expected: &str, tamper: impl FnOnce(&mut Vec<u8>)) {
    let mut hostile = blob.to_vec();
    tamper(&mut hostile);
    reseal(&mut hostile);
    let err = load_error(&hostile);
    assert_eq!(err.kind(), ErrorKind::InvalidArgument, "{what}: {err}");
    assert!(err.to_string().contains(expected), "{what}: {err} (expected to mention {expected:?})");
}

/// Writes `value` at `at`.
fn poke(blob: &mut [u8], at: usize, value: &[u8]) {
    blob[at..at + value.len()].copy_from_slice(value);
}

/// A hostile change: what it is, what the error must mention, and the change.
type Tamper = (&'static str, &'static str, Box<dyn FnOnce(&mut Vec<u8>)>);

/// A change that writes `value` at `at`.
fn write_at(what: &'static str, expected: &'static str, at: usize, value: impl AsRef<[u8]> + 'static) -> Tamper {
    (what, expected, Box::new(move |b: &mut Vec<u8>| poke(b, at, value.as_ref())))
}

#[test]
fn hostile_blobs_with_valid_checksums_are_refused_without_panics_or_huge_allocations() {
    let context = cpu();
    let blob = context.serialize_accel(&small_graph(&context), &[]).unwrap();
    let f = fields(&blob);
    assert_eq!(f.entries.len(), 3);
    let (geometry, transform, root) = (f.entries[0], f.entries[1], f.entries[2]);
    let (transform_children, root_children) = (f.children[1], f.children[2]);
    let nodes = f.payloads[0]; // the geometry accel's node count; its root node follows
    let node_count = u64_at(&blob, nodes);
    assert!(node_count >= 3, "the geometry accel has inner nodes");
    let leaf_count = (0..node_count as usize).map(|i| nodes + 8 + 32 * i + 28).find(|&at| blob[at] != 0).unwrap();
    let mut leaves = (0..node_count as usize).map(|i| nodes + 8 + 32 * i).filter(|&at| blob[at + 28] != 0);
    let (first_leaf, second_leaf) = (leaves.next().unwrap(), leaves.next().expect("two leaves"));
    let first_leaf_index: [u8; 4] = blob[first_leaf + 12..first_leaf + 16].try_into().unwrap();
    let cases: Vec<Tamper> = vec![
        write_at("root's children at itself", "inner node 0", nodes + 8 + 12, 0u32.to_le_bytes()),
        write_at("root's children past the end", "inner node 0", nodes + 8 + 12, u32::MAX.to_le_bytes()),
        write_at("a node without a parent", "node 1 is the child of no node", nodes + 8 + 12, 3u32.to_le_bytes()),
        (
            "a node with two parents",
            "node 2 is the child of two nodes",
            Box::new(move |b: &mut Vec<u8>| {
                // Node 1 made an inner node over nodes 2 and 3; node 2 is the root's.
                poke(b, nodes + 8 + 32 + 12, &2u32.to_le_bytes());
                poke(b, nodes + 8 + 32 + 28, &0u32.to_le_bytes());
            }),
        ),
        write_at("node count lowered", "node key boxes", nodes, (node_count - 1).to_le_bytes()),
        write_at("node count huge", "elements of 32 bytes", nodes, (u64::MAX / 4).to_le_bytes()),
        write_at("a leaf's count huge", "leaf node", leaf_count, u32::MAX.to_le_bytes()),
        write_at("two leaves sharing slots", "which leaf node", second_leaf + 12, first_leaf_index),
        write_at("triangle count", "do not add up", geometry + 24, 13u64.to_le_bytes()),
        write_at("geometry count", "structure of 1 inputs", geometry + 32, 2u32.to_le_bytes()),
        write_at("motion keys 0", "motion keys", geometry + 8, 0u32.to_le_bytes()),
        write_at("motion keys 5000", "motion keys", root + 8, 5000u32.to_le_bytes()),
        write_at("unknown kind", "unknown accel kind", root, 9u32.to_le_bytes()),
        write_at("unknown build flags", "unknown build flags", root + 4, 0x100u32.to_le_bytes()),
        write_at("a child naming itself", "child 0 names", root_children + 8, 2u32.to_le_bytes()),
        write_at("a child naming a missing external", "external accels", root_children + 8, (1u32 << 31).to_le_bytes()),
        write_at("a repeated child", "repeats", root_children + 12, 0u32.to_le_bytes()),
        write_at("a child count huge", "elements of 4 bytes", root_children, u64::MAX.to_le_bytes()),
        write_at("a transform with 2 children", "2 children", transform_children, 2u64.to_le_bytes()),
        write_at("a transform of another kind", "static transform", transform, 2u32.to_le_bytes()),
        write_at("a singular transform key", "transform", transform_children + 28, [0u8; 48]),
        write_at("accels counted in the header", "accel 3", 28, 4u32.to_le_bytes()),
        write_at("accels counted in the header, more than fit", "counts 4294967295 accels", 28, u32::MAX.to_le_bytes()),
        write_at("external accels counted in the header, more than fit", "at least", 32, u32::MAX.to_le_bytes()),
        write_at("external accels counted in the header", "refers to 1", 32, 1u32.to_le_bytes()),
        write_at("payload length huge", "payload", f.payloads[2] - 8, (u64::MAX - 7).to_le_bytes()),
    ];
    for (what, expected, tamper) in cases {
        assert_hostile(&blob, what, expected, tamper);
    }
}

/// Moves `at` past an array of `size`-byte elements of `blob` and returns where the array began.
fn skip(blob: &[u8], at: &mut usize, size: usize) -> usize {
    let start = *at;
    *at += 8 + size * u64_at(blob, start) as usize;
    start
}

#[test]
fn hostile_cpu_payloads_are_refused_field_by_field() {
    let context = cpu();
    let blob = context.serialize_accel(&small_graph(&context), &[]).unwrap();
    let f = fields(&blob);
    // The geometry accel's payload: nodes, key boxes, corners, ids, masks, flags, random access, update order.
    let mut at = f.payloads[0];
    skip(&blob, &mut at, 32);
    let key_boxes = skip(&blob, &mut at, 24);
    let corners = skip(&blob, &mut at, 36);
    let ids = skip(&blob, &mut at, 8);
    let masks_flag = at;
    assert_eq!(u32::from_le_bytes(blob[at..at + 4].try_into().unwrap()), 1, "masks present");
    at += 4;
    let masks = skip(&blob, &mut at, 4);
    let geometry_flags = skip(&blob, &mut at, 4);
    at += 4;
    let access_geometries = skip(&blob, &mut at, 8);
    let access_slots = skip(&blob, &mut at, 4);
    at += 4;
    let order = skip(&blob, &mut at, 4);
    assert_eq!(u64_at(&blob, order), 12);
    let first_order = blob[order + 8..order + 12].to_vec();
    // The instance accel's payload: nodes, key boxes, then instances (64 bytes: rows, id, mask, flags, child).
    let mut at = f.payloads[2];
    skip(&blob, &mut at, 32);
    skip(&blob, &mut at, 24);
    let instances = at;
    assert_eq!(u64_at(&blob, instances), 3);
    let first = instances + 8;
    let cases: Vec<Tamper> = vec![
        write_at("key boxes without motion", "node key boxes", key_boxes, 1u64.to_le_bytes()),
        write_at("a NaN corner", "not finite", corners + 8 + 4 * 7, f32::NAN.to_le_bytes()),
        write_at("an infinite corner", "not finite", corners + 8 + 36, f32::NEG_INFINITY.to_le_bytes()),
        write_at("a geometry id", "geometry id", ids + 8, 1u32.to_le_bytes()),
        write_at("masks too few", "masks", masks, 11u64.to_le_bytes()),
        write_at("masks flag", "presence flag", masks_flag, 2u32.to_le_bytes()),
        write_at("unknown geometry flags", "unknown flags", geometry_flags + 8, 0x40u32.to_le_bytes()),
        write_at("random access geometries", "random access", access_geometries, 2u64.to_le_bytes()),
        write_at("random access start", "starts at triangle", access_geometries + 8, 13u32.to_le_bytes()),
        write_at("random access slot", "slot", access_slots + 8 + 4 * 5, 12u32.to_le_bytes()),
        write_at("update order out of range", "update order", order + 8, 12u32.to_le_bytes()),
        write_at("update order repeated", "update order", order + 12, first_order),
        write_at("a singular instance transform", "invertible", first, [0u8; 48]),
        write_at("an infinite instance transform", "invertible", first, f32::INFINITY.to_le_bytes()),
        write_at("a wide mask", "mask", first + 52, 0x100u32.to_le_bytes()),
        write_at("unknown instance flags", "unknown flags", first + 56, 0x80u32.to_le_bytes()),
        write_at("a child out of range", "child", first + 60, 2u32.to_le_bytes()),
        write_at("instances fewer", "instances", instances, 2u64.to_le_bytes()),
        (
            "a child placed by none",
            "placed by no instance",
            Box::new(move |b: &mut Vec<u8>| (0..3).for_each(|i| poke(b, first + 64 * i + 60, &0u32.to_le_bytes()))),
        ),
    ];
    for (what, expected, tamper) in cases {
        assert_hostile(&blob, what, expected, tamper);
    }
}

#[test]
fn random_tampering_with_valid_checksums_never_panics_and_what_loads_traces() {
    let context = cpu();
    let blob = context.serialize_accel(&small_graph(&context), &[]).unwrap();
    let rays = rays(64, 9);
    let mut loaded_some = 0;
    for trial in 0..3000u64 {
        let mut tampered = blob.clone();
        let u = |k: u64| uniform(trial, k);
        for k in 0..1 + (u(0) * 3.0) as u64 {
            let at = 48 + (u(1 + 3 * k) * (blob.len() - 52) as f32) as usize;
            let value = match (u(2 + 3 * k) * 4.0) as u32 {
                0 => 0,
                1 => u32::MAX,
                2 => 1 + (u(3 + 3 * k) * 16.0) as u32,
                _ => (u(3 + 3 * k) * u32::MAX as f32) as u32,
            };
            poke(&mut tampered, at, &value.to_le_bytes());
        }
        reseal(&mut tampered);
        let context = cpu();
        match context.deserialize_accel(&tampered, &[]) {
            Ok(accels) => {
                loaded_some += 1;
                for accel in &accels {
                    trace_all(&context, accel, &rays);
                    let _ = accel.triangle_vertices(0, (u(9) * 16.0) as u32);
                }
            }
            Err(err) => {
                assert!(matches!(err.kind(), ErrorKind::InvalidArgument | ErrorKind::FailedPrecondition), "{err}");
                assert!(context.accel_handles().is_empty());
            }
        }
    }
    assert!(loaded_some > 0, "some tampering (of a float) still loads");
}

// ---------------------------------------------------------------------------------------------------------------
// Speed.
// ---------------------------------------------------------------------------------------------------------------

/// Encode and decode speed over the largest shared mesh tiled to 2M triangles (`cargo test --release --test
/// serialize -- --ignored --nocapture`).
#[test]
#[ignore = "a measurement: run in release"]
fn encode_and_decode_speed() {
    let paths = std::fs::read_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/meshes")).unwrap();
    let largest = paths.map(|p| p.unwrap().path()).max_by_key(|p| p.metadata().unwrap().len()).unwrap();
    let mesh = Mesh::tiled(&[Mesh::load_obj(&largest).unwrap()], 2_000_000);
    let packed = mesh.pack();
    let context = cpu();
    for flags in [BuildFlags::empty(), KEEP_ALL] {
        let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::new(flags)).unwrap();
        let started = std::time::Instant::now();
        let blob = context.serialize_accel(&accel, &[]).unwrap();
        let encode = started.elapsed();
        let started = std::time::Instant::now();
        blob_summary(&blob).unwrap();
        let checksum = started.elapsed();
        let started = std::time::Instant::now();
        let loaded = context.deserialize_accel(&blob, &[]).unwrap();
        let decode = started.elapsed();
        let mb = blob.len() as f64 / 1e6;
        println!(
            "{} ({} triangles, {flags:?}): {mb:.1} MB blob; encode {:.1} ms = {:.0} MB/s; decode {:.1} ms = {:.0} MB/s \
             (the header and checksum alone: {:.1} ms)",
            largest.file_name().unwrap().to_string_lossy(),
            mesh.triangles.len(),
            encode.as_secs_f64() * 1e3,
            mb / encode.as_secs_f64(),
            decode.as_secs_f64() * 1e3,
            mb / decode.as_secs_f64(),
            checksum.as_secs_f64() * 1e3,
        );
        assert_eq!(loaded[0].info(), accel.info());
    }
}
