//! Triangles without area are never hit, on every device, however they got that way: built so, updated into it, or
//! moving but degenerate throughout; and a triangle built without area but updated to have some is hit. Random
//! vertex access still gives such a triangle's own vertices, and a saved accel loads back the same.

mod common;

use glam::Vec3;
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::format::{Hit, HitFormat, Ray, RayFormat};
use rayd_engine::geometry::{BuildInput, MotionOptions, TriangleInput};
use rayd_engine::query::{Query, TraceOutput};
use rayd_engine::{Accel, Context, Device};

/// Three distinct points on one line: f32 shearing leaves their projected triangle a sliver of area, so the
/// watertight test alone accepts the ray below.
const COLLINEAR: [Vec3; 3] = [Vec3::new(1.5, -2.0, -1.0), Vec3::new(2.5, -2.5, -2.0), Vec3::new(3.5, -3.0, -3.0)];

/// A ray through a point of [`COLLINEAR`]'s segment at t = 4, in a direction not along its line.
fn through_the_line(time: f32) -> Ray {
    Ray {
        origin: Vec3::new(-1.5, -5.25, -1.5).into(),
        direction: Vec3::new(0.875, 0.75, 0.0).into(),
        time,
        ..Ray::default()
    }
}

/// A triangle with area that the same ray crosses at t = 4.
fn crossed() -> [Vec3; 3] {
    let centre = Vec3::new(2.0, -2.25, -1.5);
    [centre + Vec3::new(0.0, 0.0, -1.0), centre + Vec3::new(-1.0, 1.0, 1.0), centre + Vec3::new(1.0, -1.0, 1.0)]
}

/// The packed vertices of one triangle.
fn packed(corners: [Vec3; 3]) -> Vec<u8> {
    corners.iter().flat_map(|c| c.to_array()).flat_map(f32::to_le_bytes).collect()
}

/// Every device to check: the CPU, and a wgpu adapter where there is one.
fn devices() -> Vec<Device> {
    std::iter::once(Device::cpu()).chain(common::gpu_with(Default::default())).collect()
}

/// The closest hit of `ray`.
fn closest(context: &Context, accel: &Accel, ray: &Ray) -> Hit {
    let query = Query::closest(RayFormat::Full, HitFormat::Full);
    let mut rays = vec![0u8; RayFormat::Full.size()];
    RayFormat::Full.encode(ray, &mut rays);
    let mut hits = vec![0u8; query.output_layout(rays.len()).unwrap().hits];
    context.trace(accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
    HitFormat::Full.read(&hits, 0)
}

#[test]
fn a_collinear_triangle_is_missed_and_the_same_triangle_with_area_is_hit() {
    for device in devices() {
        let context = Context::new(device);
        let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect();
        let build = |corners, flags| {
            let vertices = packed(corners);
            let input = BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices));
            context.build_accel(&[input], &BuildOptions::new(flags)).unwrap()
        };
        let update = |accel: &Accel, corners| {
            let vertices = packed(corners);
            context.update_accel(accel, &[BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))]).unwrap()
        };
        let ray = through_the_line(0.0);
        let name = context.device().info().id.clone();
        assert!(closest(&context, &build(crossed(), BuildFlags::empty()), &ray).t == 4.0, "{name}: the ray's aim");
        assert!(!closest(&context, &build(COLLINEAR, BuildFlags::empty()), &ray).is_hit(), "{name}: built collinear");

        // Updated into a line: missed. Built without area, then given some: hit.
        let flags = BuildFlags::ALLOW_UPDATE | BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS;
        let accel = update(&build(crossed(), flags), COLLINEAR);
        assert!(!closest(&context, &accel, &ray).is_hit(), "{name}: updated into a line");
        assert_eq!(accel.triangle_vertices(0, 0).unwrap(), COLLINEAR, "{name}: its own vertices");
        let blob = context.serialize_accel(&accel, &[]).unwrap();
        let loaded = context.deserialize_accel(&blob, &[]).unwrap().pop().unwrap();
        assert!(!closest(&context, &loaded, &ray).is_hit(), "{name}: loaded");
        assert_eq!(loaded.triangle_vertices(0, 0).unwrap(), COLLINEAR, "{name}: its own vertices, loaded");
        assert_eq!(closest(&context, &update(&loaded, crossed()), &ray).t, 4.0, "{name}: loaded, then given area");
        for placeholder in [COLLINEAR, [Vec3::ZERO; 3]] {
            let given_area = update(&build(placeholder, flags), crossed());
            assert_eq!(
                closest(&context, &given_area, &ray).t,
                4.0,
                "{name}: built as {placeholder:?}, then given area"
            );
        }
    }
}

#[test]
fn a_moving_triangle_without_area_throughout_is_missed() {
    for device in devices() {
        let context = Context::new(device);
        let name = context.device().info().id.clone();
        let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect();
        let moving = |first: [Vec3; 3], last: [Vec3; 3]| {
            let (first, last) = (packed(first), packed(last));
            let motion_vertices = [last.as_slice()];
            let input = TriangleInput { motion_vertices: &motion_vertices, ..TriangleInput::indexed(&first, &indices) };
            let motion = MotionOptions { keys: 2, time_begin: 0.0, time_end: 1.0, ..MotionOptions::STATIC };
            let options = BuildOptions { flags: BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS, motion };
            context.build_accel(&[BuildInput::Triangles(input)], &options).unwrap()
        };
        // Still on its line, and sliding along it: no area at any time.
        let slid = COLLINEAR.map(|c| c + Vec3::new(1.0, -0.5, -1.0));
        for (last, what) in [(COLLINEAR, "still"), (slid, "sliding along its line")] {
            let accel = moving(COLLINEAR, last);
            assert!(!closest(&context, &accel, &through_the_line(0.0)).is_hit(), "{name}: {what}, at its first key");
            assert_eq!(accel.triangle_vertices(0, 0).unwrap(), COLLINEAR, "{name}: {what}: its own vertices");
        }
        // A line at its first key that opens into a triangle: hit once it has area.
        let opening = moving(COLLINEAR, crossed());
        assert!(closest(&context, &opening, &through_the_line(1.0)).is_hit(), "{name}: opened");
    }
}

#[test]
fn many_triangles_held_collapsed_keep_their_own_vertices_through_a_save_and_a_load() {
    // Two inputs, the second's primitive ids from 100, each: collinear, with area, collinear elsewhere, all zeros.
    let shifted = COLLINEAR.map(|c| c + Vec3::splat(7.0));
    let corners = [COLLINEAR, crossed(), shifted, [Vec3::ZERO; 3]];
    let vertices: Vec<u8> = corners.iter().flat_map(|&c| packed(c)).collect();
    let indices: Vec<u8> = (0..12u32).flat_map(u32::to_le_bytes).collect();
    let input = || TriangleInput::indexed(&vertices, &indices);
    let motion_vertices = [vertices.as_slice()];
    let moving = MotionOptions { keys: 2, time_begin: 0.0, time_end: 1.0, ..MotionOptions::STATIC };
    let random = BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS;
    for device in devices() {
        let context = Context::new(device);
        let name = context.device().info().id.clone();
        let builds = [
            (BuildOptions::new(random | BuildFlags::ALLOW_UPDATE), input()),
            (
                BuildOptions { flags: random, motion: moving },
                TriangleInput { motion_vertices: &motion_vertices, ..input() },
            ),
        ];
        for (options, first) in builds {
            let second = TriangleInput { primitive_index_offset: 100, ..first };
            let built =
                context.build_accel(&[BuildInput::Triangles(first), BuildInput::Triangles(second)], &options).unwrap();
            let blob = context.serialize_accel(&built, &[]).unwrap();
            let loaded = context.deserialize_accel(&blob, &[]).unwrap().pop().unwrap();
            for accel in [&built, &loaded] {
                for (geom_id, offset) in [(0, 0), (1, 100)] {
                    for (index, expected) in corners.iter().enumerate() {
                        let found = accel.triangle_vertices(geom_id, offset + index as u32).unwrap();
                        assert_eq!(&found, expected, "{name}, {options:?}: geometry {geom_id}, triangle {index}");
                    }
                }
                // Only the triangles with area are hit: the first input's, of the two at the same t.
                let hit = closest(&context, accel, &through_the_line(0.0));
                assert_eq!((hit.t, hit.geom_id, hit.prim_id), (4.0, 0, 1), "{name}, {options:?}");
            }
        }
    }
}

/// An updatable accel as `Context::serialize_accel` saved it before 2026-12-07 (`0bf3250`), when a build left its
/// degenerate triangles out of its leaves: one input of two triangles, indexed 0 to 5, built with `ALLOW_UPDATE |
/// ALLOW_RANDOM_VERTEX_ACCESS`; triangle 0 a placeholder (every corner at the origin), triangle 1 the corners
/// (−1, −1, −2), (1, −1, −2), (0, 1, −2).
const SAVED_WITH_A_PLACEHOLDER_LEFT_OUT: &[u8] = &[
    0x52, 0x41, 0x59, 0x44, 0x41, 0x43, 0x43, 0x4c, 0x6a, 0xd4, 0x98, 0x39, 0x04, 0x03, 0x02, 0x01, 0x01, 0x00, 0x00,
    0x00, 0x01, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x54, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x14, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x80, 0x3f,
    0x00, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x18,
    0x00, 0x00, 0x00, 0xca, 0x23, 0x72, 0x46, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0xe0, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x80, 0xbf, 0x00, 0x00, 0x80, 0xbf, 0x00, 0x00, 0x00, 0xc0, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x80, 0x3f, 0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x00, 0xc0, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x80, 0xbf, 0x00, 0x00, 0x80, 0xbf,
    0x00, 0x00, 0x00, 0xc0, 0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x80, 0xbf, 0x00, 0x00, 0x00, 0xc0, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x00, 0xc0, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x01,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
];

#[test]
fn an_updatable_accel_saved_with_its_placeholders_left_out_is_laid_out_again_when_loaded() {
    let down = Ray { origin: Vec3::ZERO.into(), direction: Vec3::NEG_Z.into(), ..Ray::default() };
    let given_area: Vec<u8> = [[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0], [0.0, 1.0, -1.0], [-1.0, -1.0, -2.0]]
        .into_iter()
        .chain([[1.0, -1.0, -2.0], [0.0, 1.0, -2.0]])
        .flat_map(|corner: [f32; 3]| corner.map(f32::to_le_bytes))
        .flatten()
        .collect();
    let indices: Vec<u8> = (0..6u32).flat_map(u32::to_le_bytes).collect();
    for device in devices() {
        let context = Context::new(device);
        let name = context.device().info().id.clone();
        let loaded = context.deserialize_accel(SAVED_WITH_A_PLACEHOLDER_LEFT_OUT, &[]).unwrap().pop().unwrap();
        let hit = closest(&context, &loaded, &down);
        assert_eq!((hit.t, hit.prim_id), (2.0, 1), "{name}: the placeholder is not hit");
        assert_eq!(loaded.triangle_vertices(0, 0).unwrap(), [Vec3::ZERO; 3], "{name}");
        let input = BuildInput::Triangles(TriangleInput::indexed(&given_area, &indices));
        let updated = context.update_accel(&loaded, &[input]).unwrap();
        let hit = closest(&context, &updated, &down);
        assert_eq!((hit.t, hit.prim_id), (1.0, 0), "{name}: the placeholder, given area, is hit in front");
    }
}
