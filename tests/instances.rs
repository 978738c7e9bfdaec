//! Instance accels against the same scenes flattened into one triangle soup: random multi-level scenes (non-uniform
//! scale, mirroring, rotations, facing flags, visibility masks, static transforms) give the same hits; explicit
//! checks of the instance path, facing and culling through mirrors and flips; huge translations keep their
//! precision; and the graph rules (invertible transforms, depth limit, children that cannot be destroyed).

mod common;

use std::rc::Rc;
use std::sync::Arc;

use common::{f32_at, icosphere, pack_rays, random_soup, u32_at};
use glam::{Affine3A, Mat3, Quat, UVec3, Vec3, Vec3A};
use rayd_engine::accel::{AccelKind, BuildOptions};
use rayd_engine::format::{HitFormat, MISS_ID, Ray, RayFlags, RayFormat};
use rayd_engine::geometry::{
    BuildInput, GeometryFlags, Instance, InstanceFlags, MAX_GRAPH_DEPTH, Placement, TransformInput, TriangleInput,
    VertexBuffer, VertexFormat,
};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::raygen::uniform;
use rayd_engine::{Accel, Context, Device, ErrorKind};

/// 4-byte words of a `full` hit record.
const FULL_WORDS: usize = 20;

/// A node of a test scene: the engine's accel and what it was built from.
struct Node {
    /// The built accel.
    accel: Arc<Accel>,
    /// Its description.
    shape: Shape,
}

/// What a node was built from.
enum Shape {
    /// A geometry accel: one geometry a mesh.
    Triangles(Vec<Mesh>),
    /// An instance accel.
    Instances(Vec<Placed>),
    /// A static transform.
    Transform([f32; 12], Rc<Node>),
}

/// One instance of a test scene.
#[derive(Clone)]
struct Placed {
    transform: [f32; 12],
    id: u32,
    mask: u8,
    flags: InstanceFlags,
    child: Rc<Node>,
}

/// A geometry accel over `meshes`.
fn triangles(context: &Context, meshes: Vec<Mesh>) -> Rc<Node> {
    let packed: Vec<_> = meshes.iter().map(Mesh::pack).collect();
    let inputs: Vec<_> = packed.iter().map(|p| BuildInput::Triangles(p.input())).collect();
    let accel = context.build_accel(&inputs, &BuildOptions::default()).unwrap();
    Rc::new(Node { accel, shape: Shape::Triangles(meshes) })
}

/// An instance accel over `placed`.
fn instances(context: &Context, placed: Vec<Placed>) -> Rc<Node> {
    let list: Vec<Instance> = placed
        .iter()
        .map(|p| Instance {
            transform: p.transform,
            instance_id: p.id,
            mask: p.mask,
            flags: p.flags,
            child: Arc::clone(&p.child.accel),
        })
        .collect();
    let accel = context.build_instance_accel(&list, &BuildOptions::default()).unwrap();
    Rc::new(Node { accel, shape: Shape::Instances(placed) })
}

/// A static transform over `child`.
fn transform(context: &Context, matrix: [f32; 12], child: Rc<Node>) -> Rc<Node> {
    let accel = context.build_transform(&TransformInput::Static(matrix), &child.accel).unwrap();
    Rc::new(Node { accel, shape: Shape::Transform(matrix, child) })
}

/// One triangle of a flattened scene and what the instanced scene reports for it.
struct Flat {
    /// World-space corners, wound so that the front is the instanced triangle's front.
    corners: [Vec3; 3],
    /// Instance ids above it.
    path: Vec<u32>,
    /// Its geometry and primitive ids in its geometry accel.
    ids: (u32, u32),
    /// Face culling is off for it.
    no_culling: bool,
    /// Its second and third corners were swapped (so its u and v are).
    swapped: bool,
}

/// Flattens `node`, placed by `to_world` under `path`, as a ray with `visibility` sees it.
fn flatten(
    node: &Node,
    to_world: Affine3A,
    path: &[u32],
    (flip, no_culling): (bool, bool),
    visibility: u8,
    out: &mut Vec<Flat>,
) {
    match &node.shape {
        Shape::Triangles(meshes) => {
            let swapped = (to_world.matrix3.determinant() < 0.0) ^ flip;
            for (geom, mesh) in meshes.iter().enumerate() {
                for prim in 0..mesh.triangles.len() {
                    let [a, b, c] = mesh.corners(prim).map(|p| to_world.transform_point3(p));
                    let corners = if swapped { [a, c, b] } else { [a, b, c] };
                    out.push(Flat {
                        corners,
                        path: path.to_vec(),
                        ids: (geom as u32, prim as u32),
                        no_culling,
                        swapped,
                    });
                }
            }
        }
        Shape::Instances(placed) => {
            for p in placed.iter().filter(|p| visibility & p.mask != 0) {
                let path: Vec<u32> = path.iter().copied().chain([p.id]).collect();
                let flags = (
                    flip ^ p.flags.contains(InstanceFlags::FLIP_FACING),
                    no_culling || p.flags.contains(InstanceFlags::DISABLE_FACE_CULLING),
                );
                flatten(
                    &p.child,
                    to_world * Placement::new(&p.transform).unwrap().object_to_world,
                    &path,
                    flags,
                    visibility,
                    out,
                );
            }
        }
        Shape::Transform(matrix, child) => flatten(
            child,
            to_world * Placement::new(matrix).unwrap().object_to_world,
            path,
            (flip, no_culling),
            visibility,
            out,
        ),
    }
}

/// Traces `rays` (full format) against `accel` with `query`; returns the hits and counts.
fn trace(context: &Context, accel: &Accel, query: &Query, rays: &[Ray]) -> (Vec<u8>, Vec<u8>) {
    let bytes = pack_rays(rays, RayFormat::Full);
    let layout = query.output_layout(bytes.len()).unwrap();
    let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
    context.trace(accel, query, &bytes, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
    (hits, counts)
}

/// The flattened triangles as a geometry accel: one geometry for those that cull faces, one for those that do
/// not (each when there are any; a lone degenerate triangle when there are none at all); returns it with the
/// `Flat` index of each of its (geometry, primitive).
fn flat_accel(context: &Context, flat: &[Flat]) -> (Arc<Accel>, Vec<Vec<usize>>) {
    let mut soups = Vec::new();
    let mut index = Vec::new();
    for no_culling in [false, true] {
        let members: Vec<usize> = (0..flat.len()).filter(|&i| flat[i].no_culling == no_culling).collect();
        if members.is_empty() {
            continue;
        }
        let corners = members.iter().flat_map(|&i| flat[i].corners);
        soups.push((no_culling, corners.flat_map(|c| c.to_array()).flat_map(f32::to_le_bytes).collect::<Vec<u8>>()));
        index.push(members);
    }
    if soups.is_empty() {
        soups.push((false, vec![0u8; 36]));
        index.push(Vec::new());
    }
    let inputs: Vec<BuildInput<'_>> = soups
        .iter()
        .map(|(no_culling, soup)| {
            BuildInput::Triangles(TriangleInput {
                vertices: VertexBuffer { data: soup, format: VertexFormat::Float3, stride: None },
                motion_vertices: &[],
                indices: None,
                masks: None,
                flags: if *no_culling { GeometryFlags::DISABLE_FACE_CULLING } else { GeometryFlags::empty() },
                primitive_index_offset: 0,
            })
        })
        .collect();
    (context.build_accel(&inputs, &BuildOptions::default()).unwrap(), index)
}

/// A random rigid motion with non-uniform scale, mirrored when `mirror`, moved by up to `reach`.
fn random_affine(seed: u64, k: u64, reach: f32, mirror: bool) -> Affine3A {
    let u = |j: u64| uniform(seed, k * 32 + j);
    let axis = Vec3::new(u(0) - 0.5, u(1) - 0.5, u(2) - 0.5).normalize_or(Vec3::Z);
    let rotation = Quat::from_axis_angle(axis, u(3) * std::f32::consts::TAU);
    let mut scale = Vec3::new(0.3 + u(4), 0.3 + u(5), 0.3 + u(6));
    if mirror {
        scale.x = -scale.x;
    }
    let shift = Vec3::new(u(7) - 0.5, u(8) - 0.5, u(9) - 0.5) * reach;
    Affine3A::from_scale_rotation_translation(scale, rotation, shift)
}

/// A hit record of the full format, as the comparison needs it.
#[derive(Debug, Clone, PartialEq)]
struct Record {
    t: f32,
    prim: u32,
    geom: u32,
    inst: u32,
    uv: (f32, f32),
    normal: Vec3,
    back_face: bool,
    path: Vec<u32>,
}

/// Record `ray` of a full hit buffer.
fn record(hits: &[u8], ray: usize) -> Record {
    let word = |w: usize| u32_at(hits, FULL_WORDS * ray + w);
    let float = |w: usize| f32_at(hits, FULL_WORDS * ray + w);
    Record {
        t: float(0),
        prim: word(1),
        geom: word(2),
        inst: word(3),
        uv: (float(4), float(5)),
        normal: Vec3::new(float(6), float(7), float(8)),
        back_face: word(9) & 1 == 1,
        path: (0..word(10) as usize).map(|slot| word(12 + slot)).collect(),
    }
}

/// Whether a hit lies within `margin` of its triangle's edges (where rounding may tip it either way).
fn near_edge(record: &Record, margin: f32) -> bool {
    let (u, v) = record.uv;
    record.t >= 0.0 && u.min(v).min(1.0 - u - v) < margin
}

#[test]
fn instanced_scenes_hit_as_their_flattened_triangles() {
    let context = Context::new(Device::cpu());
    let seed = 17;
    let sphere = triangles(&context, vec![icosphere(2, Vec3::ZERO)]);
    let pieces = triangles(&context, vec![random_soup(80, seed), icosphere(1, Vec3::splat(0.5))]);
    // A cluster of instances of both geometry accels: mirrored ones, flipped ones, unculled ones, two mask bits.
    let cluster_members = (0..8u32)
        .map(|i| Placed {
            transform: Placement::rows(&random_affine(seed, u64::from(i), 3.0, i % 3 == 1)),
            id: 100 + i,
            mask: [0x01, 0x02, 0x03][i as usize % 3],
            flags: match i % 4 {
                1 => InstanceFlags::FLIP_FACING,
                2 => InstanceFlags::DISABLE_FACE_CULLING,
                _ => InstanceFlags::empty(),
            },
            child: Rc::clone(if i % 2 == 0 { &sphere } else { &pieces }),
        })
        .collect();
    let cluster = instances(&context, cluster_members);
    let moved = transform(&context, Placement::rows(&random_affine(seed, 50, 4.0, true)), Rc::clone(&sphere));
    let mut top_members: Vec<Placed> = (0..3u32)
        .map(|i| Placed {
            transform: Placement::rows(&random_affine(seed, 60 + u64::from(i), 8.0, i == 2)),
            id: i + 1,
            mask: if i == 1 { 0x04 } else { 0xFF },
            flags: if i == 2 { InstanceFlags::FLIP_FACING } else { InstanceFlags::empty() },
            child: Rc::clone(&cluster),
        })
        .collect();
    top_members.push(Placed {
        transform: Placement::rows(&Affine3A::IDENTITY),
        id: 10,
        mask: 0x08,
        flags: InstanceFlags::empty(),
        child: moved,
    });
    top_members.push(Placed {
        transform: Placement::rows(&random_affine(seed, 70, 8.0, false)),
        id: 11,
        mask: 0x01,
        flags: InstanceFlags::empty(),
        child: Rc::clone(&pieces),
    });
    let scene = instances(&context, top_members);
    assert_eq!(
        (scene.accel.info().kind, scene.accel.info().instance_count, scene.accel.info().depth),
        (AccelKind::Instances, 5, 3)
    );

    let (lo, hi) = scene.accel.info().bounds;
    let mut compared = 0;
    let mut at_edges = 0;
    let mut hit_rays = [0usize; 5];
    for (group, visibility) in [0xFFu8, 0x01, 0x06, 0x08, 0x00].into_iter().enumerate() {
        let mut flat = Vec::new();
        flatten(&scene, Affine3A::IDENTITY, &[], (false, false), visibility, &mut flat);
        let (flat_scene, index) = flat_accel(&context, &flat);
        let flags = |i: u64| match i % 6 {
            0 | 1 => RayFlags::CULL_BACK_FACING,
            2 => RayFlags::CULL_FRONT_FACING,
            _ => RayFlags::empty(),
        };
        let mut rays: Vec<Ray> = (0..4000u64)
            .map(|i| {
                let u = |j: u64| uniform(seed + 1 + group as u64, i * 16 + j);
                let inside = |j: u64| lo + (hi - lo) * Vec3::new(u(j), u(j + 1), u(j + 2));
                let origin = inside(0) * 1.5;
                let direction = (inside(3) - origin).into();
                Ray { origin: origin.into(), direction, visibility, flags: flags(i), ..Ray::default() }
            })
            .collect();
        // And a camera's rays, in rows of 64: neighbours make packets, carried into the instances together.
        let (centre, size) = ((lo + hi) * 0.5, hi - lo);
        let eye = centre + size * Vec3::new(0.2, 0.3, 1.5);
        rays.extend((0..64 * 64u64).map(|pixel| {
            let (x, y) = ((pixel % 64) as f32 / 63.0 - 0.5, (pixel / 64) as f32 / 63.0 - 0.5);
            let direction = (centre + size * Vec3::new(x, y, 0.0) - eye).into();
            Ray { origin: eye.into(), direction, visibility, flags: flags(pixel), ..Ray::default() }
        }));
        let closest = Query::closest(RayFormat::Full, HitFormat::Full);
        let count = Query { kind: QueryKind::Count, ..Query::closest(RayFormat::Full, HitFormat::T) };
        let (hits, _) = trace(&context, &scene.accel, &closest, &rays);
        let (flat_hits, _) = trace(&context, &flat_scene, &closest, &rays);
        let (_, counts) = trace(&context, &scene.accel, &count, &rays);
        let (_, flat_counts) = trace(&context, &flat_scene, &count, &rays);
        for ray in 0..rays.len() {
            let (got, flat_got) = (record(&hits, ray), record(&flat_hits, ray));
            let expected = if flat_got.t < 0.0 {
                flat_got.clone()
            } else {
                let triangle = &flat[index[flat_got.geom as usize][flat_got.prim as usize]];
                let uv = if triangle.swapped { (flat_got.uv.1, flat_got.uv.0) } else { flat_got.uv };
                Record {
                    prim: triangle.ids.1,
                    geom: triangle.ids.0,
                    inst: triangle.path.last().copied().unwrap_or(MISS_ID),
                    uv,
                    path: triangle.path.clone(),
                    ..flat_got.clone()
                }
            };
            compared += 1;
            hit_rays[group] += usize::from(got.t >= 0.0);
            let same_triangle = (got.prim, got.geom, &got.path) == (expected.prim, expected.geom, &expected.path);
            let near_tie =
                got.t >= 0.0 && expected.t >= 0.0 && (got.t - expected.t).abs() <= 1e-4 * expected.t.max(1.0);
            let counts_agree = u32_at(&counts, ray) == u32_at(&flat_counts, ray);
            if !same_triangle || !counts_agree {
                assert!(
                    near_edge(&got, 1e-3) || near_edge(&expected, 1e-3) || (near_tie && counts_agree),
                    "ray {ray} (visibility {visibility:#x}): instanced {got:?}, flattened {expected:?}"
                );
                at_edges += 1;
                continue;
            }
            assert_eq!(got.back_face, expected.back_face, "ray {ray}: facing");
            if got.t >= 0.0 {
                assert!((got.t - expected.t).abs() <= 1e-4 * expected.t.max(1.0), "ray {ray}: t {got:?} {expected:?}");
                assert!(
                    (got.uv.0 - expected.uv.0).abs() < 1e-3 && (got.uv.1 - expected.uv.1).abs() < 1e-3,
                    "ray {ray}: uv"
                );
                assert!(got.normal.dot(expected.normal) > 0.999, "ray {ray}: normal {got:?} {expected:?}");
                assert_eq!(got.inst, expected.inst);
            }
        }
    }
    assert!(at_edges * 200 <= compared, "{at_edges} of {compared} rays differ at edges or ties");
    eprintln!("rays hitting, by visibility group: {hit_rays:?}; {at_edges} of {compared} at edges or ties");
    assert!(hit_rays[0] > 400 && hit_rays[1..4].iter().all(|&n| n > 40), "the rays must hit: {hit_rays:?}");
    assert_eq!(hit_rays[4], 0, "visibility 0 sees no instance");
}

#[test]
fn hits_report_the_instance_path_and_keep_object_space_facing_through_mirrors_unless_flipped() {
    let context = Context::new(Device::cpu());
    let triangle = triangles(&context, vec![common::unit_triangle()]);
    let mirror_x = Placement::rows(&Affine3A::from_mat3(Mat3::from_diagonal(Vec3::new(-1.0, 1.0, 1.0))));
    let lift = Placement::rows(&Affine3A::from_translation(Vec3::new(0.0, 0.0, 5.0)));
    let scene = |flags: InstanceFlags| {
        let inner = instances(
            &context,
            vec![Placed { transform: mirror_x, id: 3, mask: 0x03, flags, child: Rc::clone(&triangle) }],
        );
        instances(
            &context,
            vec![Placed { transform: lift, id: 7, mask: 0x01, flags: InstanceFlags::empty(), child: inner }],
        )
    };
    let down = |visibility: u8, flags: RayFlags| Ray {
        origin: Vec3A::new(-0.25, 0.25, 10.0),
        direction: -Vec3A::Z,
        visibility,
        flags,
        ..Ray::default()
    };
    let query = Query::closest(RayFormat::Full, HitFormat::Full);
    let plain = scene(InstanceFlags::empty());
    let rays = [
        down(0xFF, RayFlags::empty()),
        down(0xFF, RayFlags::CULL_FRONT_FACING),
        down(0xFF, RayFlags::CULL_BACK_FACING),
        down(0x02, RayFlags::empty()),
    ];
    let (hits, _) = trace(&context, &plain.accel, &query, &rays);
    let hit = record(&hits, 0);
    assert_eq!((hit.t, hit.inst, hit.path.as_slice(), hit.back_face), (5.0, 3, &[7, 3][..], false));
    assert_eq!(hit.normal, Vec3::Z, "the front side, in world space");
    assert!(record(&hits, 1).t < 0.0, "a mirror keeps the object-space front face: culled as front");
    assert_eq!(record(&hits, 2).t, 5.0, "not a back face");
    assert!(record(&hits, 3).t < 0.0, "visibility 0x02 misses the top instance's mask 0x01");
    let (hits, _) = trace(&context, &scene(InstanceFlags::FLIP_FACING).accel, &query, &rays);
    let hit = record(&hits, 0);
    assert_eq!((hit.back_face, hit.normal), (true, -Vec3::Z), "flipped: the ray sees the back, the normal turns");
    assert_eq!(record(&hits, 1).t, 5.0, "flipped: no longer a front face");
    assert!(record(&hits, 2).t < 0.0, "flipped: culled as a back face");
    let (hits, _) = trace(&context, &scene(InstanceFlags::DISABLE_FACE_CULLING).accel, &query, &rays);
    assert_eq!((record(&hits, 1).t, record(&hits, 2).t), (5.0, 5.0), "culling disabled below the instance");
    let instid = Query::closest(RayFormat::Full, HitFormat::TTriidInstid);
    let (hits, _) = trace(&context, &plain.accel, &instid, &rays[..1]);
    assert_eq!(u32_at(&hits, 2), 3, "the instance-id formats report the instance above the geometry");
}

#[test]
fn huge_translations_keep_the_precision_of_the_untranslated_scene() {
    let context = Context::new(Device::cpu());
    let sphere = triangles(&context, vec![icosphere(3, Vec3::ZERO)]);
    let far = 1.0e6;
    let moved = instances(
        &context,
        vec![Placed {
            transform: Placement::rows(&Affine3A::from_translation(Vec3::new(far, -far, far))),
            id: 1,
            mask: 0xFF,
            flags: InstanceFlags::empty(),
            child: Rc::clone(&sphere),
        }],
    );
    // Ray origins on a 1/16 grid, which f32 holds exactly next to 1e6, so both scenes see the very same rays.
    let grid = |i: u64, j: u64| (uniform(5, i * 4 + j) * 64.0).round() / 16.0 - 2.0;
    let rays: Vec<Ray> = (0..2000u64)
        .map(|i| {
            let origin = Vec3A::new(grid(i, 0), grid(i, 1), 3.0 + grid(i, 2).abs());
            let target = Vec3A::new(uniform(6, i * 2) - 0.5, uniform(6, i * 2 + 1) - 0.5, 0.0);
            Ray { origin, direction: target - origin, ..Ray::default() }
        })
        .collect();
    let moved_rays: Vec<Ray> =
        rays.iter().map(|r| Ray { origin: r.origin + Vec3A::new(far, -far, far), ..*r }).collect();
    let query = Query::closest(RayFormat::Full, HitFormat::Full);
    let (expected, _) = trace(&context, &sphere.accel, &query, &rays);
    let (got, _) = trace(&context, &moved.accel, &query, &moved_rays);
    let mut hits = 0;
    for ray in 0..rays.len() {
        let (got, expected) = (record(&got, ray), record(&expected, ray));
        assert_eq!((got.t, got.prim), (expected.t, expected.prim), "ray {ray}");
        hits += usize::from(got.t >= 0.0);
    }
    assert!(hits > rays.len() / 2, "most rays hit the sphere ({hits})");
}

#[test]
fn graph_rules_refuse_singular_transforms_deep_graphs_and_destroying_placed_children() {
    let context = Context::new(Device::cpu());
    let triangle = triangles(&context, vec![common::unit_triangle()]);
    let identity = Placement::rows(&Affine3A::IDENTITY);
    let instance = |transform: [f32; 12]| Instance {
        transform,
        instance_id: 0,
        mask: 0xFF,
        flags: InstanceFlags::empty(),
        child: Arc::clone(&triangle.accel),
    };
    let mut singular = identity;
    singular[10] = 0.0;
    let error =
        context.build_instance_accel(&[instance(identity), instance(singular)], &BuildOptions::default()).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::InvalidArgument);
    assert!(error.to_string().contains("instances.transform[1]: must be finite and invertible"), "{error}");

    // Transforms stacked up to the deepest graph allowed, then one too many.
    let mut top = Rc::clone(&triangle);
    for _ in 1..MAX_GRAPH_DEPTH {
        top = transform(&context, identity, top);
    }
    assert_eq!(top.accel.info().depth, MAX_GRAPH_DEPTH);
    let one_instance = context.compute_instance_arrays_memory_usage(1, &BuildOptions::default()).unwrap();
    assert!(top.accel.info().size_bytes <= one_instance.output_bytes, "a transform is bounded as one instance");
    let error = context.build_transform(&TransformInput::Static(identity), &top.accel).unwrap_err();
    assert!(error.to_string().contains(&format!("more than {MAX_GRAPH_DEPTH}")), "{error}");
    let deep = [Instance { child: Arc::clone(&top.accel), ..instance(identity) }];
    assert!(context.build_instance_accel(&deep, &BuildOptions::default()).is_err());

    // A placed child cannot be destroyed while something places it.
    let parent =
        context.build_instance_accel(&[instance(identity), instance(identity)], &BuildOptions::default()).unwrap();
    drop((top, deep));
    let refused = context.destroy_accel(triangle.accel.handle()).unwrap_err();
    assert_eq!(refused.kind(), ErrorKind::FailedPrecondition);
    assert!(refused.to_string().contains("placed by"), "{refused}");
    context.destroy_accel(parent.handle()).unwrap();
    drop(parent);
    // The chain of transforms is still registered in the context: destroy it top down.
    for handle in context.accel_handles().into_iter().rev().filter(|h| *h != triangle.accel.handle()) {
        context.destroy_accel(handle).unwrap();
    }
    context.destroy_accel(triangle.accel.handle()).expect("nothing places it any more");
    // A build that named the child before its destroy (a call resolving its children, then building) is refused: it
    // would place an accel no longer in the context.
    let late = context.build_instance_accel(&[instance(identity)], &BuildOptions::default()).unwrap_err();
    assert_eq!(late.kind(), ErrorKind::FailedPrecondition);
    assert!(late.to_string().contains("was destroyed after it was named to be placed"), "{late}");
    let late = context.build_transform(&TransformInput::Static(identity), &triangle.accel).unwrap_err();
    assert_eq!(late.kind(), ErrorKind::FailedPrecondition, "{late}");
    assert_eq!(context.destroy_accel(triangle.accel.handle()).unwrap_err().kind(), ErrorKind::NotFound);
}

#[test]
fn a_destroy_whose_last_step_fails_keeps_the_accel_and_refuses_placing_it_meanwhile() {
    let context = Context::new(Device::cpu());
    let triangle = triangles(&context, vec![common::unit_triangle()]);
    let placing = || {
        let instance = Instance {
            transform: Placement::rows(&Affine3A::IDENTITY),
            instance_id: 0,
            mask: 0xFF,
            flags: InstanceFlags::empty(),
            child: Arc::clone(&triangle.accel),
        };
        context.build_instance_accel(&[instance], &BuildOptions::default())
    };
    // A server removing the accel's file runs between the mark and the removal: a build placing the accel then is
    // refused, and a failure takes the mark back.
    let failed = context.destroy_accel_after(triangle.accel.handle(), || {
        let refused = placing().unwrap_err();
        assert!(refused.to_string().contains("was destroyed after it was named to be placed"), "{refused}");
        Err(rayd_engine::Error::FailedPrecondition("the file could not be removed".into()))
    });
    assert!(failed.unwrap_err().to_string().contains("the file could not be removed"));
    assert!(context.accel(triangle.accel.handle()).is_ok(), "the accel stays");
    let parent = placing().expect("placed again once the destroy failed");
    assert!(context.destroy_accel(triangle.accel.handle()).unwrap_err().to_string().contains("placed by"));
    context.destroy_accel(parent.handle()).unwrap();
    drop(parent);
    context.destroy_accel(triangle.accel.handle()).unwrap();
    assert_eq!(context.accel(triangle.accel.handle()).unwrap_err().kind(), ErrorKind::NotFound);
}

/// A thin strip along x from −2 to 2, 0.02 wide (128 triangles: several lanes at its root).
fn strip() -> Mesh {
    let positions = (0..=64).flat_map(|i| [-0.01, 0.01].map(|y| Vec3::new(i as f32 / 16.0 - 2.0, y, 0.0))).collect();
    let triangles_of = |i: u32| [[2 * i, 2 * i + 2, 2 * i + 1], [2 * i + 1, 2 * i + 2, 2 * i + 3]];
    Mesh { positions, triangles: (0..64).flat_map(triangles_of).collect() }
}

/// The `t` of the closest hit (negative for a miss) of a ray down from `(x, y, 10)`, and the boxes it tested.
fn down_at(context: &Context, accel: &Accel, x: f32, y: f32) -> (f32, u64) {
    let query = Query::closest(RayFormat::Full, HitFormat::TTriidUV);
    let ray = Ray { origin: Vec3A::new(x, y, 10.0), direction: -Vec3A::Z, ..Ray::default() };
    let bytes = pack_rays(&[ray], RayFormat::Full);
    let mut hits = vec![0u8; query.output_layout(bytes.len()).unwrap().hits];
    let stats = context.trace(accel, &query, &bytes, TraceOutput { hits: &mut hits, counts: &mut [] });
    (f32_at(&hits, 0), stats.unwrap().nodes_visited)
}

#[test]
fn a_ray_through_a_turned_childs_placed_box_that_misses_the_child_tests_only_the_childs_own_box() {
    let context = Context::new(Device::cpu());
    // A thin strip turned 45° about z: its placed box is a square about a diagonal strip, most of which the strip does
    // not cover.
    let turn = Placement::rows(&Affine3A::from_rotation_z(std::f32::consts::FRAC_PI_4));
    let child = triangles(&context, vec![strip()]);
    let scene =
        instances(&context, vec![Placed { transform: turn, id: 0, mask: 0xFF, flags: InstanceFlags::empty(), child }]);
    let (outside_t, outside) = down_at(&context, &scene.accel, 5.0, 5.0);
    let (corner_t, corner) = down_at(&context, &scene.accel, 1.0, -1.0);
    let (strip_t, on_strip) = down_at(&context, &scene.accel, 0.5, 0.5);
    assert!(outside_t < 0.0 && corner_t < 0.0 && strip_t == 10.0, "{outside_t} {corner_t} {strip_t}");
    assert_eq!(corner, outside + 1, "in the placed box's corner: the child's own box, and none of its nodes");
    assert!(on_strip > corner + 1, "on the strip: the child's nodes too ({on_strip} boxes against {corner})");
}

#[test]
fn a_turned_childs_instance_box_holds_its_placed_vertices_and_little_else() {
    let context = Context::new(Device::cpu());
    // A unit sphere turned 45° about z and 30° about x: its own box (a cube) placed reaches √2 from the centre along x
    // and beyond along y and z, where the sphere reaches 1.
    let sphere = icosphere(3, Vec3::ZERO);
    let turn = Affine3A::from_quat(Quat::from_rotation_x(0.5) * Quat::from_rotation_z(std::f32::consts::FRAC_PI_4));
    let child = triangles(&context, vec![sphere.clone()]);
    let flags = InstanceFlags::empty();
    let scene =
        instances(&context, vec![Placed { transform: Placement::rows(&turn), id: 0, mask: 0xFF, flags, child }]);
    let (lo, hi) = scene.accel.info().bounds;
    for p in sphere.positions.iter().map(|&p| turn.transform_point3(p)) {
        assert!(p.cmpge(lo).all() && p.cmple(hi).all(), "{p} outside {lo} .. {hi}");
    }
    let cube = (0..8).map(|c| turn.transform_point3(UVec3::new(c & 1, c >> 1 & 1, c >> 2).as_vec3() * 2.0 - 1.0));
    let (cube_lo, cube_hi) = cube.fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(l, h), p| (l.min(p), h.max(p)));
    let volume = |(lo, hi): (Vec3, Vec3)| (hi - lo).element_product();
    let share = volume((lo, hi)) / volume((cube_lo, cube_hi));
    assert!(share < 0.75, "{lo} .. {hi}: {share} of the placed own box {cube_lo} .. {cube_hi}");
}

#[test]
fn a_ray_through_a_turned_transforms_placed_box_that_misses_the_child_tests_only_the_childs_own_box() {
    let context = Context::new(Device::cpu());
    let turn = Placement::rows(&Affine3A::from_rotation_z(std::f32::consts::FRAC_PI_4));
    let placed = transform(&context, turn, triangles(&context, vec![strip()]));
    let (corner_t, corner) = down_at(&context, &placed.accel, 1.0, -1.0);
    let (strip_t, on_strip) = down_at(&context, &placed.accel, 0.5, 0.5);
    assert!(corner_t < 0.0 && strip_t == 10.0, "{corner_t} {strip_t}");
    assert_eq!(corner, 1, "in the placed box's corner: the child's own box, and none of its nodes");
    assert!(on_strip > 2, "on the strip: the child's nodes too ({on_strip} boxes)");
}

/// A geometry accel of `copies` copies of one triangle (x and y in 0..1, at z = 0) on `context`.
fn pile(context: &Context, copies: usize) -> Arc<Accel> {
    let vertices: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
    let indices: Vec<u8> = [0u32, 1, 2].repeat(copies).iter().flat_map(|i| i.to_le_bytes()).collect();
    let input = [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
    context.build_accel(&input, &BuildOptions::default()).unwrap()
}

/// An instance accel of `count` instances of `child`, all in its place.
fn piled(context: &Context, child: &Arc<Accel>, count: u32) -> Arc<Accel> {
    let instances: Vec<Instance> = (0..count)
        .map(|id| Instance {
            transform: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            instance_id: id,
            mask: 0xFF,
            flags: InstanceFlags::empty(),
            child: Arc::clone(child),
        })
        .collect();
    context.build_instance_accel(&instances, &BuildOptions::default()).unwrap()
}

/// The error of tracing `rays` through `accel` with `query`.
fn trace_error(context: &Context, accel: &Accel, query: &Query, rays: &[Ray]) -> rayd_engine::Error {
    let packed = pack_rays(rays, query.ray_format);
    let layout = query.output_layout(packed.len()).unwrap();
    let (mut hits, mut counts) = (vec![0; layout.hits], vec![0; layout.counts]);
    let output = TraceOutput { hits: &mut hits, counts: &mut counts };
    context.trace(accel, query, &packed, output).unwrap_err()
}

#[test]
fn rays_past_their_work_in_an_instance_graph_fail_the_trace_by_name_and_rays_within_it_are_whole() {
    // 1,000 instances of 1,000 instances of 1,000 copies of one triangle: a ray through them would test 10^9
    // triangles, for seconds; the default limit (2^20 a ray) stops it.
    let context = Context::new(Device::cpu());
    let copies = pile(&context, 1000);
    let deep = piled(&context, &piled(&context, &copies, 1000), 1000);
    let down = |x: f32| Ray { origin: Vec3A::new(x, 0.25, 1.0), direction: -Vec3A::Z, ..Ray::default() };
    // 64 rays, every other one through the pile (too far apart to make packets), and one ray alone.
    let through: Vec<Ray> = (0..64).map(|i| down(if i % 2 == 0 { 0.25 } else { 5.0 })).collect();
    // 16 rays from one origin make a packet, which enters the instances together.
    let packet = vec![down(0.25); 16];
    for query in [
        Query::closest(RayFormat::Full, HitFormat::TTriid),
        Query { kind: QueryKind::Count, ..Query::closest(RayFormat::Full, HitFormat::T) },
    ] {
        for rays in [&through[..], &through[..1], &packet[..]] {
            let error = trace_error(&context, &deep, &query, rays);
            assert_eq!(error.kind(), ErrorKind::ResourceExhausted, "{error}");
            let message = error.to_string();
            assert!(message.contains("1048576") && message.contains("scheduler.cpu_ray_work"), "{message}");
        }
    }
    // The rays beside the pile trace through the same graph.
    let beside: Vec<Ray> = through.iter().copied().skip(1).step_by(2).collect();
    let closest = Query::closest(RayFormat::Full, HitFormat::TTriid);
    let (hits, _) = trace(&context, &deep, &closest, &beside);
    assert!((0..beside.len()).all(|i| !HitFormat::TTriid.read(&hits, i).is_hit()));
    // Within the limit every hit is counted: 10 instances of the pile, 10,000 hits a ray through it.
    let shallow = piled(&context, &copies, 10);
    let count = Query { kind: QueryKind::Count, ..Query::closest(RayFormat::Full, HitFormat::T) };
    let (_, counts) = trace(&context, &shallow, &count, &through);
    let expected = |i: usize| if i.is_multiple_of(2) { 10_000 } else { 0 };
    assert!((0..through.len()).all(|i| u32_at(&counts, i) == expected(i)), "every hit counted");
    // A device held to 1,024 steps a ray refuses that trace by its own limit.
    let strict = Context::new(Device::cpu_with_max_ray_work(1024));
    let shallow = piled(&strict, &pile(&strict, 1000), 10);
    let message = trace_error(&strict, &shallow, &count, &through).to_string();
    assert!(message.contains("1024 node visits") && message.contains("scheduler.cpu_ray_work"), "{message}");
}
