//! Hostile geometry and rays (issue 13, point 2), on the engine: every input is either traced by a documented rule
//! (`proto/rayd/v1/formats.proto`, `accels.proto`) or refused with an error of kind InvalidArgument that names it.

mod common;

use common::pack_rays;
use glam::Vec3A;
use rayd_engine::accel::BuildOptions;
use rayd_engine::format::{Hit, HitFormat, Ray, RayFormat};
use rayd_engine::geometry::{BuildInput, TriangleInput};
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::{Accel, Context, Device, ErrorKind};
use std::sync::Arc;

/// Packs float3 vertices.
fn floats(values: &[[f32; 3]]) -> Vec<u8> {
    values.iter().flatten().flat_map(|v| v.to_le_bytes()).collect()
}

/// Packs u32 indices.
fn indices(values: &[[u32; 3]]) -> Vec<u8> {
    values.iter().flatten().flat_map(|v| v.to_le_bytes()).collect()
}

/// Builds a soup of `triangles` on the CPU.
fn build(context: &Context, triangles: &[[f32; 3]]) -> rayd_engine::Result<Arc<Accel>> {
    let vertices = floats(triangles);
    let input = TriangleInput { indices: None, ..TriangleInput::indexed(&vertices, &[]) };
    context.build_accel(&[BuildInput::Triangles(input)], &BuildOptions::default())
}

/// Traces `rays` with `kind` and returns each ray's first record and its count.
fn trace(context: &Context, accel: &Accel, kind: QueryKind, rays: &[Ray]) -> Vec<(Hit, u32)> {
    let query = Query { kind, ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV) };
    let rays = pack_rays(rays, RayFormat::OriginTminDirectionTmax);
    let layout = query.output_layout(rays.len()).unwrap();
    let (mut hits, mut counts) = (vec![0; layout.hits], vec![0; layout.counts]);
    context.trace(accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
    (0..layout.rays)
        .map(|i| {
            let count = if counts.is_empty() { 0 } else { common::u32_at(&counts, i) };
            (HitFormat::TTriidUV.read(&hits, i * query.records_per_ray()), count)
        })
        .collect()
}

/// A ray from `origin` along `direction` over `[tmin, tmax]`.
fn ray(origin: [f32; 3], direction: [f32; 3], tmin: f32, tmax: f32) -> Ray {
    Ray { origin: Vec3A::from(origin), direction: Vec3A::from(direction), tmin, tmax, ..Ray::default() }
}

/// The triangle `(-s, -s, 5) (s, -s, 5) (0, s, 5)` around the z axis.
fn triangle(size: f32) -> [[f32; 3]; 3] {
    [[-size, -size, 5.0], [size, -size, 5.0], [0.0, size, 5.0]]
}

/// A miss: `t` −1, no primitive, no crossing.
const MISS: (f32, u32, u32) = (-1.0, u32::MAX, 0);

/// Each ray's `(t, prim_id, count)` of a count query (its hit is the closest).
fn crossings(context: &Context, accel: &Accel, rays: &[Ray]) -> Vec<(f32, u32, u32)> {
    trace(context, accel, QueryKind::Count, rays).into_iter().map(|(hit, count)| (hit.t, hit.prim_id, count)).collect()
}

#[test]
fn non_finite_vertices_and_indices_beyond_the_vertices_are_invalid_arguments_naming_them() {
    let context = Context::new(Device::cpu());
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let error = build(&context, &[[0.0; 3], [1.0, 0.0, 0.0], [0.0, bad, 5.0]]).unwrap_err();
        assert_eq!(error.kind(), ErrorKind::InvalidArgument);
        let message = error.to_string();
        assert!(
            message.contains("vertices") && message.contains("vertex 2") && message.contains("finite"),
            "{message}"
        );
    }
    let vertices = floats(&triangle(1.0));
    for index in [3, u32::MAX] {
        let indices = indices(&[[0, 1, 2], [0, index, 2]]);
        let input = BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices));
        let error = context.build_accel(&[input], &BuildOptions::default()).unwrap_err();
        assert_eq!(error.kind(), ErrorKind::InvalidArgument);
        let message = error.to_string();
        assert!(message.contains("indices") && message.contains(&format!("vertex {index}")), "{message}");
    }
}

#[test]
fn extreme_triangles_are_hit_where_binary32_holds_them_and_missed_otherwise_never_at_a_bad_t() {
    let context = Context::new(Device::cpu());
    let down = |z: f32| ray([0.0, 0.0, z], [0.0, 0.0, 1.0], 0.0, f32::INFINITY);
    // (size, ray origin z, hit): a hit is at t = 5 − z, up to rounding (an ulp).
    let cases = [
        (1e-40, 0.0, false),
        (1e-30, 0.0, false),
        (1e-19, 0.0, true),
        (1e-6, 0.0, true),
        (1e12, 0.0, true),
        (1e12, -5e11, true),
        (1e18, 0.0, true),
        (1e13, -5e12, false),
        (1e19, 0.0, false),
        (1e30, 0.0, false),
    ];
    for (size, z, hit) in cases {
        let accel = build(&context, &triangle(size)).unwrap();
        let [(t, prim, count)] = crossings(&context, &accel, &[down(z)])[..] else { unreachable!() };
        let what = format!("a triangle of size {size:e} from z = {z:e}: t {t}, primitive {prim}, {count} crossings");
        if hit {
            assert!((prim, count) == (0, 1) && (t - (5.0 - z)).abs() <= 1e-6 * (5.0 - z), "{what}");
        } else {
            assert_eq!((t, prim, count), MISS, "{what}");
        }
    }
    // All three vertices equal: degenerate, legal, never hit.
    let accel = build(&context, &[[0.0, 0.0, 5.0]; 3]).unwrap();
    assert_eq!(crossings(&context, &accel, &[down(0.0)]), [MISS]);
}

#[test]
fn hostile_rays_hit_nothing_or_follow_the_range_rule() {
    let context = Context::new(Device::cpu());
    let accel = build(&context, &triangle(1.0)).unwrap();
    let (nan, inf) = (f32::NAN, f32::INFINITY);
    let misses = [
        ray([0.0; 3], [0.0; 3], 0.0, inf),
        ray([0.0; 3], [0.0, nan, 1.0], 0.0, inf),
        ray([0.0; 3], [0.0, 0.0, inf], 0.0, inf),
        ray([0.0; 3], [1e-30, 0.0, -inf], 0.0, inf),
        ray([0.0; 3], [0.0, 0.0, 1e-40], 0.0, inf),
        ray([0.0; 3], [0.0, 0.0, 1.0], 6.0, 4.0),
        ray([0.0; 3], [0.0, 0.0, 1.0], nan, inf),
        ray([0.0; 3], [0.0, 0.0, 1.0], 0.0, nan),
        ray([nan, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, inf),
        ray([0.0, 0.0, -inf], [0.0, 0.0, 1.0], 0.0, inf),
    ];
    for kind in [QueryKind::Closest, QueryKind::Any, QueryKind::Count] {
        for (i, (hit, count)) in trace(&context, &accel, kind, &misses).into_iter().enumerate() {
            assert_eq!((hit.t, hit.prim_id, count), MISS, "{kind:?}, ray {i}: {:?}", misses[i]);
        }
    }
    let hits = [
        (ray([0.0; 3], [0.0, 0.0, 1e-30], 0.0, inf), 5e30),
        (ray([0.0; 3], [0.0, 0.0, 1e30], 0.0, inf), 5e-30),
        (ray([0.0, 0.0, -1e30], [0.0, 0.0, 1.0], 0.0, inf), 1e30),
        (ray([1e-40, -1e-40, 0.0], [0.0, 0.0, 1.0], 0.0, inf), 5.0),
        (ray([0.0; 3], [0.0, 0.0, 1.0], -inf, inf), 5.0),
        (ray([0.0; 3], [0.0, 0.0, 1.0], 5.0, 5.0), 5.0),
    ];
    let rays: Vec<Ray> = hits.iter().map(|(r, _)| *r).collect();
    for (i, (hit, count)) in trace(&context, &accel, QueryKind::Count, &rays).into_iter().enumerate() {
        assert_eq!((hit.t, hit.prim_id, count), (hits[i].1, 0, 1), "ray {i}: {:?}", rays[i]);
    }
}

#[test]
fn a_pile_of_copies_of_one_triangle_or_a_row_of_them_builds_and_traces_by_the_tie_rule() {
    // Quadratic before the obvhs patch (vendor/obvhs/PATCHED.md): 20,000 copies took 12 s, these would take hours,
    // far past CI's limit. The build's time itself is benchmarked, not asserted here (`cargo bench --bench build`).
    let copies = 200_000;
    let context = Context::new(Device::cpu());
    let pile: Vec<[f32; 3]> = (0..copies).flat_map(|_| triangle(1.0)).collect();
    let accel = build(&context, &pile).unwrap();
    let rays = [
        ray([0.0; 3], [0.0, 0.0, 1.0], 0.0, f32::INFINITY),
        ray([0.3, -0.2, 0.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY),
        ray([2.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY),
    ];
    let expected = [(5.0, 0, copies as u32), (5.0, 0, copies as u32), MISS];
    assert_eq!(crossings(&context, &accel, &rays), expected, "the lowest primitive id, every copy crossed");
    let row: Vec<[f32; 3]> =
        (0..copies).flat_map(|i| triangle(1.0).map(|[x, y, z]| [x + 4.0 * i as f32, y, z])).collect();
    let accel = build(&context, &row).unwrap();
    let rays: Vec<Ray> = [0, 1, 4999, 77_777]
        .iter()
        .map(|&i| ray([4.0 * i as f32, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY))
        .collect();
    let traced: Vec<u32> = crossings(&context, &accel, &rays).into_iter().map(|c| c.1).collect();
    assert_eq!(traced, [0, 1, 4999, 77_777]);
}

#[test]
fn nested_triangles_and_triangles_spread_wider_than_binary32_spans_build_and_trace() {
    // Each prefers the same neighbour (a box nested in the next): obvhs's PLOC merged one pair a pass, quadratic
    // (20,000 nested boxes 9 s, these about a quarter of an hour) and a chain as deep as the count (vendor/obvhs/PATCHED.md); its trees
    // deeper than a BVH may be are built by median splits. Triangle `i` scaled by 1.00001^i: boxes nested in each
    // other, each crossed by the z axis at z = s/3.
    let context = Context::new(Device::cpu());
    let copies = 200_000;
    let nested: Vec<[f32; 3]> = (0..copies)
        .flat_map(|i| {
            let s = 1.00001f32.powi(i);
            [[-s, -s, -s], [2.0 * s, -s, s], [-s, 2.0 * s, s]]
        })
        .collect();
    let accel = build(&context, &nested).unwrap();
    let rays = [
        ray([0.0, 0.0, -100.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY),
        ray([0.0, 0.0, 100.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY),
    ];
    let [(up, lowest, crossed_up), (down, highest, crossed_down)] = crossings(&context, &accel, &rays)[..] else {
        unreachable!()
    };
    assert_eq!((lowest, highest, crossed_up, crossed_down), (0, copies as u32 - 1, copies as u32, copies as u32));
    let s_last = 1.00001f32.powi(copies - 1);
    let near = |t: f32, expected: f32| (t - expected).abs() < 1e-3;
    assert!(near(up, 100.0 + 1.0 / 3.0) && near(down, 100.0 - s_last / 3.0), "{up} {down}, {s_last}");
    // Finite corners over ±3.3e38: the scene's extent and area overflow binary32, and obvhs panicked on them.
    let spacing = 3.3e38 / (copies / 2) as f32;
    let x = |i: usize| (i as f32 / (copies / 2) as f32 - 1.0) * 3.3e38;
    let wide: Vec<[f32; 3]> = (0..copies as usize)
        .flat_map(|i| [[x(i), -1.0, 5.0], [x(i) + 0.9 * spacing, -1.0, 5.0], [x(i), 1.0, 5.0]])
        .collect();
    let accel = build(&context, &wide).unwrap();
    let rays: Vec<Ray> = [0, 1, 99_999, 199_999]
        .iter()
        .map(|&i| ray([x(i) + 0.1 * spacing, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY))
        .collect();
    let expected = [0, 1, 99_999, 199_999].map(|i| (5.0, i, 1));
    assert_eq!(crossings(&context, &accel, &rays), expected);
}
