//! Query semantics on small hand-made scenes: ranges, ties, masks, culling, ids, barycentrics, `all` and
//! `count` layouts, degenerate triangles and the miss encoding.

mod common;

use common::{f32_at, pack_rays, u32_at};
use glam::{Vec3, Vec3A};
use rayd_engine::accel::BuildOptions;
use rayd_engine::format::{HitFormat, MISS_ID, Ray, RayFlags, RayFormat};
use rayd_engine::geometry::{BuildInput, GeometryFlags, TriangleInput};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::{Context, Device};

/// Traces `rays` (full format) against `inputs` and returns (hits, counts).
fn trace(inputs: &[BuildInput<'_>], query: Query, rays: &[Ray]) -> (Vec<u8>, Vec<u8>) {
    let context = Context::new(Device::cpu());
    let accel = context.build_accel(inputs, &BuildOptions::default()).unwrap();
    let query = Query { ray_format: RayFormat::Full, ..query };
    let rays = pack_rays(rays, RayFormat::Full);
    let layout = query.output_layout(rays.len()).unwrap();
    let (mut hits, mut counts) = (vec![0xEE; layout.hits], vec![0xEE; layout.counts]);
    context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
    (hits, counts)
}

/// A unit right triangle in the plane z = `z` (normal +z).
fn quad_triangle(z: f32) -> Mesh {
    Mesh {
        positions: vec![Vec3::new(0.0, 0.0, z), Vec3::new(1.0, 0.0, z), Vec3::new(0.0, 1.0, z)],
        triangles: vec![[0, 1, 2]],
    }
}

fn down(x: f32, y: f32, from_z: f32) -> Ray {
    Ray { origin: Vec3A::new(x, y, from_z), direction: -Vec3A::Z, ..Ray::default() }
}

/// 4-byte words in one `full` hit record.
const FULL_WORDS: usize = 20;

fn closest(format: HitFormat) -> Query {
    Query::closest(RayFormat::Full, format)
}

#[test]
fn tmin_and_tmax_are_inclusive_and_honoured_at_tiny_distances() {
    let mesh = quad_triangle(0.0).pack();
    let input = [BuildInput::Triangles(mesh.input())];
    let at = |tmin: f32, tmax: f32, from: f32| Ray { tmin, tmax, ..down(0.25, 0.25, from) };
    let rays = [
        at(2.0, 9.0, 2.0),
        at(0.0, 2.0, 2.0),
        at(f32::from_bits(2.0f32.to_bits() + 1), 9.0, 2.0),
        at(0.0, f32::from_bits(2.0f32.to_bits() - 1), 2.0),
        // 5e-5 above the triangle: obvhs's CWBVH would miss this; rayd must honour tmin exactly.
        at(0.0, 1.0, 5e-5),
        at(1e-4, 1.0, 5e-5),
    ];
    let (hits, _) = trace(&input, closest(HitFormat::T), &rays);
    let t: Vec<f32> = (0..rays.len()).map(|i| f32_at(&hits, i)).collect();
    assert_eq!(&t[..4], &[2.0, 2.0, -1.0, -1.0]);
    assert!((t[4] - 5e-5).abs() < 1e-9, "{}", t[4]);
    assert_eq!(t[5], -1.0);
}

#[test]
fn equal_t_ties_go_to_the_lowest_geometry_then_primitive_id() {
    // The same triangle three times in geometry 1 and twice in geometry 0, listed so that build order differs.
    let tri = quad_triangle(0.0);
    let soup = |copies: usize| Mesh {
        positions: (0..copies).flat_map(|_| tri.positions.clone()).collect(),
        triangles: (0..copies as u32).map(|c| [3 * c, 3 * c + 1, 3 * c + 2]).collect(),
    };
    let (g0, g1) = (soup(2).pack(), soup(3).pack());
    let inputs = [
        BuildInput::Triangles(TriangleInput { primitive_index_offset: 7, ..g0.input() }),
        BuildInput::Triangles(g1.input()),
    ];
    let rays: Vec<Ray> = (0..64).map(|i| down(0.1 + 0.01 * (i % 8) as f32, 0.1 + 0.01 * (i / 8) as f32, 1.0)).collect();
    let (hits, _) = trace(&inputs, closest(HitFormat::Full), &rays);
    for ray in 0..rays.len() {
        assert_eq!((u32_at(&hits, FULL_WORDS * ray + 1), u32_at(&hits, FULL_WORDS * ray + 2)), (7, 0), "ray {ray}");
    }
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 8, ..closest(HitFormat::Full) };
    let (hits, counts) = trace(&inputs, all, &rays[..1]);
    let order: Vec<(u32, u32)> =
        (0..5).map(|k| (u32_at(&hits, FULL_WORDS * k + 2), u32_at(&hits, FULL_WORDS * k + 1))).collect();
    assert_eq!(order, [(0, 7), (0, 8), (1, 0), (1, 1), (1, 2)]);
    assert_eq!(u32_at(&counts, 0), 5);
}

#[test]
fn prime_masks_skip_triangles_whose_mask_shares_a_bit_with_the_ray() {
    let (near, far) = (quad_triangle(1.0), quad_triangle(0.0));
    let (near, far) = (near.pack(), far.pack());
    let near_mask = 0b0110u32.to_le_bytes();
    let inputs = [
        BuildInput::Triangles(TriangleInput { masks: Some(&near_mask), ..near.input() }),
        BuildInput::Triangles(far.input()),
    ];
    let with_mask = |mask| Ray { mask, ..down(0.2, 0.2, 3.0) };
    let (hits, _) = trace(&inputs, closest(HitFormat::Full), &[with_mask(0), with_mask(0b1001), with_mask(0b0010)]);
    let geometry = |ray: usize| u32_at(&hits, FULL_WORDS * ray + 2);
    assert_eq!([geometry(0), geometry(1), geometry(2)], [0, 0, 1]);
}

#[test]
fn face_culling_follows_ray_and_query_flags_unless_the_geometry_disables_it() {
    let (plain, exempt) = (quad_triangle(0.0).pack(), quad_triangle(-1.0).pack());
    let inputs = [
        BuildInput::Triangles(plain.input()),
        BuildInput::Triangles(TriangleInput { flags: GeometryFlags::DISABLE_FACE_CULLING, ..exempt.input() }),
    ];
    // From above the rays see front faces; from below, back faces.
    let from_above = Ray { flags: RayFlags::CULL_FRONT_FACING, ..down(0.2, 0.2, 2.0) };
    let from_below = Ray { origin: Vec3A::new(0.2, 0.2, -2.0), direction: Vec3A::Z, ..Ray::default() };
    let between = Ray { origin: Vec3A::new(0.2, 0.2, -0.5), ..from_below };
    let (hits, _) = trace(&inputs, closest(HitFormat::Full), &[from_above, from_below, between]);
    assert_eq!((u32_at(&hits, 2), u32_at(&hits, 9)), (1, 0), "front face of geometry 0 culled, geometry 1 exempt");
    let word = |ray: usize, offset: usize| u32_at(&hits, FULL_WORDS * ray + offset);
    assert_eq!((word(1, 2), word(1, 9)), (1, 1), "seen from below: back face flag set");
    assert_eq!((word(2, 2), word(2, 9)), (0, 1));
    let culling_query = Query { flags: RayFlags::CULL_BACK_FACING, ..closest(HitFormat::TTriid) };
    let (hits, _) = trace(&inputs, culling_query, &[from_below, between]);
    assert_eq!(f32_at(&hits, 0), 1.0, "geometry 1 is exempt from culling");
    assert_eq!(f32_at(&hits, 2), -1.0, "the query's flag applies to the ray");
}

#[test]
fn ids_barycentrics_and_normal_describe_the_hit_point() {
    let mesh = Mesh {
        positions: vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(0.0, 2.0, 0.0),
            Vec3::new(1.0, 3.0, 0.5),
        ],
        triangles: vec![[0, 1, 2], [1, 3, 2]],
    }
    .pack();
    let second = quad_triangle(-5.0).pack();
    let inputs = [
        BuildInput::Triangles(TriangleInput { primitive_index_offset: 40, ..mesh.input() }),
        BuildInput::Triangles(second.input()),
    ];
    let ray = Ray { origin: Vec3A::new(1.2, 1.3, 4.0), direction: Vec3A::new(0.0, 0.1, -1.0), ..Ray::default() };
    let (hits, _) = trace(&inputs, closest(HitFormat::Full), &[ray]);
    let (t, prim, geom, inst) = (f32_at(&hits, 0), u32_at(&hits, 1), u32_at(&hits, 2), u32_at(&hits, 3));
    let (u, v) = (f32_at(&hits, 4), f32_at(&hits, 5));
    assert_eq!((prim, geom, inst), (41, 0, MISS_ID));
    let [v0, v1, v2] = [Vec3::new(2.0, 0.0, 0.0), Vec3::new(1.0, 3.0, 0.5), Vec3::new(0.0, 2.0, 0.0)];
    let on_triangle = v0 * (1.0 - u - v) + v1 * u + v2 * v;
    let on_ray = Vec3::from(ray.origin + ray.direction * t);
    assert!(on_triangle.distance(on_ray) < 1e-5, "{on_triangle} vs {on_ray}");
    let normal = Vec3::new(f32_at(&hits, 6), f32_at(&hits, 7), f32_at(&hits, 8));
    assert!(normal.distance((v1 - v0).cross(v2 - v0).normalize()) < 1e-6);
}

#[test]
fn all_sorts_pads_and_flags_overflow_and_count_counts_every_crossing() {
    let layers: Vec<Mesh> = (0..5).map(|k| quad_triangle(k as f32)).collect();
    let packed: Vec<_> = layers.iter().map(Mesh::pack).collect();
    let inputs: Vec<_> = packed.iter().map(|p| BuildInput::Triangles(p.input())).collect();
    let rays = [down(0.25, 0.25, 10.0), down(0.75, 0.75, 10.0), Ray { tmax: 7.5, ..down(0.25, 0.25, 10.0) }];
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 3, ..closest(HitFormat::TTriidInstid) };
    let (hits, counts) = trace(&inputs, all, &rays);
    let t = |ray: usize, slot: usize| f32_at(&hits, 3 * (ray * 3 + slot));
    assert_eq!([t(0, 0), t(0, 1), t(0, 2)], [6.0, 7.0, 8.0]);
    assert_eq!(u32_at(&counts, 0), 5, "5 hits found, 3 kept: overflow");
    assert_eq!([t(1, 0), t(1, 1), t(1, 2)], [-1.0; 3]);
    assert_eq!(u32_at(&hits, 3 * 3 + 1), MISS_ID);
    assert_eq!(u32_at(&counts, 1), 0);
    assert_eq!([t(2, 0), t(2, 1), t(2, 2)], [6.0, 7.0, -1.0]);
    assert_eq!(u32_at(&counts, 2), 2);

    let count = Query { kind: QueryKind::Count, ..closest(HitFormat::T) };
    let (hits, counts) = trace(&inputs, count, &rays);
    assert_eq!([u32_at(&counts, 0), u32_at(&counts, 1), u32_at(&counts, 2)], [5, 0, 2]);
    assert_eq!([f32_at(&hits, 0), f32_at(&hits, 1), f32_at(&hits, 2)], [6.0, -1.0, 6.0]);
}

#[test]
fn degenerate_triangles_are_legal_never_hit_and_keep_their_ids() {
    let mesh = Mesh {
        positions: vec![
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(0.5, 0.0, 1.0),
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ],
        // A collinear triangle, a triangle with a repeated vertex, then a real one.
        triangles: vec![[0, 1, 2], [3, 3, 4], [3, 4, 5]],
    }
    .pack();
    let inputs = [BuildInput::Triangles(mesh.input())];
    // One ray along the degenerate segment's line, one through the real triangle.
    let along = Ray { origin: Vec3A::new(-1.0, 0.0, 1.0), direction: Vec3A::X, ..Ray::default() };
    let (hits, _) = trace(&inputs, closest(HitFormat::TTriid), &[along, down(0.2, 0.2, 2.0)]);
    assert_eq!((f32_at(&hits, 0), u32_at(&hits, 1)), (-1.0, MISS_ID));
    assert_eq!((f32_at(&hits, 2), u32_at(&hits, 3)), (2.0, 2));

    let only_degenerate =
        Mesh { positions: vec![Vec3::ZERO, Vec3::X, Vec3::X * 2.0], triangles: vec![[0, 1, 2]] }.pack();
    let (hits, _) = trace(&[BuildInput::Triangles(only_degenerate.input())], closest(HitFormat::T), &[along]);
    assert_eq!(f32_at(&hits, 0), -1.0);
}

#[test]
fn bitmask_output_of_a_partial_last_byte_is_exact() {
    let mesh = quad_triangle(0.0).pack();
    let inputs = [BuildInput::Triangles(mesh.input())];
    let rays: Vec<Ray> = (0..11).map(|i| down(if i % 3 == 0 { 0.2 } else { 2.0 }, 0.2, 1.0)).collect();
    let (hits, _) = trace(&inputs, closest(HitFormat::Bitmask), &rays);
    assert_eq!(hits, [0b0100_1001, 0b0000_0010]);
}
