//! Motion blur, at the engine level, against exact expectations:
//!
//! 1. Vertex motion: a triangle translating along x is hit at a ray's time where it is then, and missed where it
//!    is not; `t`, `u`, `v` and the normal are those of the interpolated triangle (bit for bit those of a static
//!    build of it), for both ray formats that carry a time.
//! 2. The seeds' SRT example 1 (60° about z), through an instance: at time 1 the triangle is where a static 60°
//!    rotation puts it; at 0.5 and 0.25 where nlerp of the quaternions and C = T·R·S put it (computed here with
//!    glam), which at 0.25 is measurably not where slerp would.
//! 3. The seeds' SRT examples 2 and 3: a rotation and a scaling about a pivot keep the pivot fixed and carry
//!    other points where `P + R·(p − P)` and `G + s·(p − G)` say. (With example 2's first key the identity, the
//!    pivot terms are interpolated too, so the pivot is fixed only at the keys; with the pivot in both keys it is
//!    fixed throughout. Both are checked.)
//! 4. Clamp and vanish at both ends, for a geometry accel, matrix and SRT motion transforms and motion instance
//!    accels (vanishing hides every instance outside the accel's range; clamping shows the end keys, and children
//!    of a clamped instance accel stay where their own motion puts them beyond its range).
//! 5. An irregular range, [−1, 1.5] with 3 keys (key times −1, 0.25, 1.5): piecewise-linear positions for vertex
//!    motion, matrix and SRT transforms and a motion instance accel.
//! 6. Random scenes (matrix motion over SRT motion over a static transform over a moving geometry accel, motion
//!    instance accels whose children move over narrower or wider ranges, vanishing children): for 16 ray times,
//!    the closest and `all` hits (t, u, v, ids, instance path, counts) equal those of the scene frozen at that
//!    time (vertices and transforms computed here by the documented formulas, built static and traced). And every
//!    accel's `info().bounds` holds its triangles at every time (a bar turning 170° included). A motion-blurred
//!    camera's rays (neighbours at different times, which the CPU backend walks together as packets) hit moving
//!    meshes, and instances of them and of a matrix motion transform over them (in a static and in a motion instance
//!    accel), as the scene frozen at each ray's time.
//! 7. A NaN ray time fails the trace (INVALID_ARGUMENT naming `rays.time`); infinite times clamp.
//! 8. Bad motion inputs are refused precisely (field, element, rule).
//! 9. Updates of a motion geometry accel trace as a fresh build with the new keys.
//! 10. A moving mesh's tree is built for where its triangles are on average, not for their paths: a sphere sliding by
//!     twenty times its triangles' size costs a ray at its own time about the triangle tests of the sphere built
//!     static.
//!
//! The reference interpolates as the engine documents it: with `K` keys over `[begin, end]`,
//! `u = (t − begin)/(end − begin)·(K − 1)`, segment `s = min(⌊u⌋, K − 2)`, `f = u − s`, values `(1 − f)·a + f·b`
//! (as `a·(1 − f) + b·f` in f32); before `begin` the first key holds (or the object vanishes), after `end` the
//! last. Frozen scenes built from such values see the very same triangles and rays as the moving ones, so their
//! hits are compared bit for bit; only below SRT transforms (whose quaternion arithmetic this file does its own
//! way) are `t`, `u` and `v` compared within a tight tolerance.

mod common;

use std::rc::Rc;
use std::sync::Arc;

use common::{f32_at, icosphere, pack_rays, random_soup, u32_at};
use glam::{Affine3A, Quat, Vec3, Vec3A};
use rayd_engine::accel::{AccelKind, BuildFlags, BuildOptions};
use rayd_engine::format::{HitFormat, MISS_ID, Ray, RayFormat};
use rayd_engine::geometry::{
    BuildInput, Instance, InstanceFlags, MotionFlags, MotionOptions, Placement, TransformInput, TriangleInput,
};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::raygen::{Camera, uniform};
use rayd_engine::{Accel, Context, Device, Error, ErrorKind};

// ---------------------------------------------------------------------------------------------------------------
// Motion, as documented.
// ---------------------------------------------------------------------------------------------------------------

/// Motion options.
fn motion(keys: u32, time_begin: f32, time_end: f32, flags: MotionFlags) -> MotionOptions {
    MotionOptions { keys, time_begin, time_end, flags }
}

/// Both vanish flags.
const VANISH: MotionFlags = MotionFlags::START_VANISH.union(MotionFlags::END_VANISH);

/// Every combination of the vanish flags.
const FLAG_SETS: [MotionFlags; 4] = [MotionFlags::empty(), MotionFlags::START_VANISH, MotionFlags::END_VANISH, VANISH];

/// Where `time` falls among the keys of `m`, by the documented formula: `(segment, fraction)`, or `None` when
/// the object has vanished.
fn key_at(m: &MotionOptions, time: f32) -> Option<(usize, f32)> {
    if m.keys <= 1 {
        return Some((0, 0.0));
    }
    let last_segment = m.keys as usize - 2;
    if time < m.time_begin {
        return (!m.flags.contains(MotionFlags::START_VANISH)).then_some((0, 0.0));
    }
    if time > m.time_end {
        return (!m.flags.contains(MotionFlags::END_VANISH)).then_some((last_segment, 1.0));
    }
    let u = (time - m.time_begin) / (m.time_end - m.time_begin) * (m.keys - 1) as f32;
    let segment = (u.floor() as usize).min(last_segment);
    Some((segment, u - segment as f32))
}

/// `(1 − f)·a + f·b`, as the engine documents it.
fn lerp(a: f32, b: f32, f: f32) -> f32 {
    a * (1.0 - f) + b * f
}

/// The 3×4 row-major matrix between two matrix keys.
fn matrix_between(a: &[f32; 12], b: &[f32; 12], f: f32) -> [f32; 12] {
    std::array::from_fn(|i| lerp(a[i], b[i], f))
}

/// The object-to-world map between two SRT keys (`sx a b pvx sy c pvy sz pvz qx qy qz qw tx ty tz`): S and T per
/// element, R by nlerp of the normalized quaternions, then C = T·R·S.
fn srt_between(a: &[f32; 16], b: &[f32; 16], f: f32) -> Affine3A {
    let [sx, sa, sb, pvx, sy, sc, pvy, sz, pvz, _, _, _, _, tx, ty, tz] = std::array::from_fn(|i| lerp(a[i], b[i], f));
    let quat = |k: &[f32; 16]| Quat::from_xyzw(k[9], k[10], k[11], k[12]).normalize();
    let rotation = (quat(a) * (1.0 - f) + quat(b) * f).normalize();
    let scale = Affine3A::from_cols(
        Vec3A::new(sx, 0.0, 0.0),
        Vec3A::new(sa, sy, 0.0),
        Vec3A::new(sb, sc, sz),
        Vec3A::new(pvx, pvy, pvz),
    );
    Affine3A::from_translation(Vec3::new(tx, ty, tz)) * Affine3A::from_quat(rotation) * scale
}

/// The object-to-world matrix of a transform at `time` (3×4 row-major), or `None` when it has vanished.
fn transform_at(input: &TransformInput, time: f32) -> Option<[f32; 12]> {
    match input {
        TransformInput::Static(matrix) => Some(*matrix),
        TransformInput::MatrixMotion { keys, motion } => {
            let (s, f) = key_at(motion, time)?;
            Some(matrix_between(&keys[s], &keys[s + 1], f))
        }
        TransformInput::SrtMotion { keys, motion } => {
            let (s, f) = key_at(motion, time)?;
            Some(Placement::rows(&srt_between(&keys[s], &keys[s + 1], f)))
        }
    }
}

/// An SRT key: scale `s` (diagonal), shear `(a, b, c)`, pivot `pv`, rotation `q`, translation `t`.
fn srt(s: Vec3, shear: [f32; 3], pv: Vec3, q: Quat, t: Vec3) -> [f32; 16] {
    let [a, b, c] = shear;
    [s.x, a, b, pv.x, s.y, c, pv.y, s.z, pv.z, q.x, q.y, q.z, q.w, t.x, t.y, t.z]
}

/// The identity SRT key.
fn srt_identity() -> [f32; 16] {
    srt(Vec3::ONE, [0.0; 3], Vec3::ZERO, Quat::IDENTITY, Vec3::ZERO)
}

/// The 3×4 matrix of a translation.
fn translation(t: Vec3) -> [f32; 12] {
    Placement::rows(&Affine3A::from_translation(t))
}

// ---------------------------------------------------------------------------------------------------------------
// Moving geometry.
// ---------------------------------------------------------------------------------------------------------------

/// One triangle build input with its vertex positions at every motion key.
#[derive(Debug, Clone)]
struct Moving {
    /// Positions, one list a key (all of the same length).
    keys: Vec<Vec<Vec3>>,
    /// Three vertex indices a triangle.
    triangles: Vec<[u32; 3]>,
}

impl Moving {
    /// A static mesh.
    fn still(mesh: Mesh) -> Moving {
        Moving { keys: vec![mesh.positions], triangles: mesh.triangles }
    }

    /// A mesh whose positions at key `k` are `at_key(k, position)`.
    fn from_mesh(mesh: &Mesh, keys: usize, at_key: impl Fn(usize, usize, Vec3) -> Vec3) -> Moving {
        let keys =
            (0..keys).map(|k| mesh.positions.iter().enumerate().map(|(i, &p)| at_key(k, i, p)).collect()).collect();
        Moving { keys, triangles: mesh.triangles.clone() }
    }

    /// The mesh between keys `s` and `s + 1`, `f` of the way.
    fn at(&self, (s, f): (usize, f32)) -> Mesh {
        let positions = if self.keys.len() == 1 {
            self.keys[0].clone()
        } else {
            let (a, b) = (&self.keys[s], &self.keys[s + 1]);
            a.iter().zip(b).map(|(a, b)| *a * (1.0 - f) + *b * f).collect()
        };
        Mesh { positions, triangles: self.triangles.clone() }
    }
}

/// Little-endian float3 bytes.
fn vertex_bytes(positions: &[Vec3]) -> Vec<u8> {
    positions.iter().flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect()
}

/// The build-input bytes of moving meshes: each one's vertices at every key, and its indices.
struct Packed {
    /// Per input, per key: float3 vertex bytes.
    keys: Vec<Vec<Vec<u8>>>,
    /// Per input: u32×3 index bytes.
    indices: Vec<Vec<u8>>,
}

impl Packed {
    /// Packs `inputs`.
    fn new(inputs: &[Moving]) -> Packed {
        Packed {
            keys: inputs.iter().map(|m| m.keys.iter().map(|k| vertex_bytes(k)).collect()).collect(),
            indices: inputs
                .iter()
                .map(|m| m.triangles.iter().flatten().flat_map(|i| i.to_le_bytes()).collect())
                .collect(),
        }
    }

    /// Per input: the vertex bytes of keys 1, 2, …
    fn motion_vertices(&self) -> Vec<Vec<&[u8]>> {
        self.keys.iter().map(|k| k[1..].iter().map(Vec::as_slice).collect()).collect()
    }

    /// The build inputs, with `motion_vertices` (one list an input) as their vertex bytes of keys 1, 2, …
    fn inputs<'a>(&'a self, motion_vertices: &'a [Vec<&'a [u8]>]) -> Vec<BuildInput<'a>> {
        (0..self.keys.len())
            .map(|i| {
                BuildInput::Triangles(TriangleInput {
                    motion_vertices: &motion_vertices[i],
                    ..TriangleInput::indexed(&self.keys[i][0], &self.indices[i])
                })
            })
            .collect()
    }
}

/// Builds a geometry accel over `inputs` (one build input each, every key's vertices given).
fn build_geometry(context: &Context, inputs: &[Moving], options: &BuildOptions) -> rayd_engine::Result<Arc<Accel>> {
    let packed = Packed::new(inputs);
    let motion_vertices = packed.motion_vertices();
    context.build_accel(&packed.inputs(&motion_vertices), options)
}

/// A still mesh of one triangle.
fn one_triangle(corners: [Vec3; 3]) -> Moving {
    Moving { keys: vec![corners.to_vec()], triangles: vec![[0, 1, 2]] }
}

/// Build options with motion.
fn with_motion(motion: MotionOptions) -> BuildOptions {
    BuildOptions { motion, ..BuildOptions::default() }
}

/// A right triangle with legs 1 along x and y, its right angle at `corner`, front facing +z.
fn unit_triangle(corner: Vec3) -> Vec<Vec3> {
    vec![corner, corner + Vec3::X, corner + Vec3::Y]
}

/// A one-triangle input sliding from `from` (key 0) by `step` a key, `keys` keys.
fn sliding(from: Vec3, step: Vec3, keys: usize) -> Moving {
    Moving { keys: (0..keys).map(|k| unit_triangle(from + step * k as f32)).collect(), triangles: vec![[0, 1, 2]] }
}

/// A one-triangle input at the given positions of its right-angle corner, a key each.
fn at_corners(corners: &[Vec3]) -> Moving {
    Moving { keys: corners.iter().map(|&c| unit_triangle(c)).collect(), triangles: vec![[0, 1, 2]] }
}

// ---------------------------------------------------------------------------------------------------------------
// Tracing.
// ---------------------------------------------------------------------------------------------------------------

/// A CPU context.
fn cpu() -> Context {
    Context::new(Device::cpu())
}

/// A hit record of the full format.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Record {
    t: f32,
    prim: u32,
    geom: u32,
    inst: u32,
    u: f32,
    v: f32,
    normal: Vec3,
    back_face: bool,
    path_len: u32,
    path: [u32; 8],
}

impl Record {
    /// What a missed ray reports.
    const MISS: Record = Record {
        t: -1.0,
        prim: MISS_ID,
        geom: MISS_ID,
        inst: MISS_ID,
        u: 0.0,
        v: 0.0,
        normal: Vec3::ZERO,
        back_face: false,
        path_len: 0,
        path: [MISS_ID; 8],
    };

    /// Whether it is a hit.
    fn hit(&self) -> bool {
        self.t >= 0.0
    }

    /// The instance ids above the hit.
    fn path(&self) -> &[u32] {
        &self.path[..self.path_len as usize]
    }
}

/// Record `index` of a full hit buffer.
fn record(hits: &[u8], index: usize) -> Record {
    let word = |w: usize| u32_at(hits, 20 * index + w);
    let float = |w: usize| f32_at(hits, 20 * index + w);
    Record {
        t: float(0),
        prim: word(1),
        geom: word(2),
        inst: word(3),
        u: float(4),
        v: float(5),
        normal: Vec3::new(float(6), float(7), float(8)),
        back_face: word(9) & 1 == 1,
        path_len: word(10),
        path: std::array::from_fn(|slot| word(12 + slot)),
    }
}

/// Traces `rays` (packed in the query's ray format; the hit format must be `Full`): the records (as many a ray as
/// the query writes) and the counts.
fn trace(context: &Context, accel: &Accel, query: &Query, rays: &[Ray]) -> (Vec<Record>, Vec<u32>) {
    assert_eq!(query.hit_format, HitFormat::Full);
    let bytes = pack_rays(rays, query.ray_format);
    let layout = query.output_layout(bytes.len()).unwrap();
    let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
    context.trace(accel, query, &bytes, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
    let records = (0..rays.len() * query.records_per_ray()).map(|i| record(&hits, i)).collect();
    (records, (0..layout.counts / 4).map(|i| u32_at(&counts, i)).collect())
}

/// Closest hits of `rays` at their times (36-byte rays with time, full hits).
fn closest(context: &Context, accel: &Accel, rays: &[Ray]) -> Vec<Record> {
    trace(context, accel, &Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::Full), rays).0
}

/// A ray straight down onto the plane z = 0 at `(x, y)`, from height 5, at `time`.
fn down(x: f32, y: f32, time: f32) -> Ray {
    Ray { origin: Vec3A::new(x, y, 5.0), direction: -Vec3A::Z, time, ..Ray::default() }
}

/// One instance, visible to every ray.
fn instance(transform: [f32; 12], id: u32, child: &Arc<Accel>) -> Instance {
    Instance { transform, instance_id: id, mask: 0xFF, flags: InstanceFlags::empty(), child: Arc::clone(child) }
}

// ---------------------------------------------------------------------------------------------------------------
// 1. Vertex motion.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn a_translating_triangle_is_hit_where_it_is_at_the_ray_time() {
    let context = cpu();
    let options = motion(2, 0.0, 1.0, MotionFlags::empty());
    let slide = sliding(Vec3::ZERO, Vec3::new(2.0, 0.0, 0.0), 2);
    // A second geometry tilts as it moves: its third corner rises, so its normal turns.
    let tilt = Moving {
        keys: vec![unit_triangle(Vec3::new(10.0, 0.0, 0.0)), {
            let mut raised = unit_triangle(Vec3::new(10.0, 0.0, 0.0));
            raised[2].z = 1.0;
            raised
        }],
        triangles: vec![[0, 1, 2]],
    };
    let accel = build_geometry(&context, &[slide.clone(), tilt.clone()], &with_motion(options)).unwrap();
    assert_eq!(accel.info().options.motion, options);
    let (lo, hi) = accel.info().bounds;
    assert!(lo.x <= 0.0 && hi.x >= 3.0 && hi.z >= 1.0, "the bounds hold every key: {lo} {hi}");

    for format in [RayFormat::OriginTminDirectionTmaxTime, RayFormat::Full] {
        let query = Query::closest(format, HitFormat::Full);
        for time in [0.0, 0.125, 0.3, 0.5, 0.7, 0.999, 1.0] {
            let at = key_at(&options, time).unwrap();
            let x = lerp(0.0, 2.0, at.1);
            let rays =
                [down(x + 0.25, 0.5, time), down(x + 1.5, 0.5, time), down(x - 0.5, 0.5, time), down(10.25, 0.5, time)];
            let (hits, _) = trace(&context, &accel, &query, &rays);
            let slid = hits[0];
            assert!(slid.hit(), "{format:?} t {time}: the triangle is at x = {x}");
            assert_eq!((slid.geom, slid.prim), (0, 0));
            assert!((slid.t - 5.0).abs() < 1e-6 && (slid.u - 0.25).abs() < 1e-6 && (slid.v - 0.5).abs() < 1e-6);
            assert_eq!(slid.normal, Vec3::Z);
            assert!(!hits[1].hit() && !hits[2].hit(), "{format:?} t {time}: nothing beside the moved triangle");
            let tilted = tilt.at(at).corners(0);
            let normal = (tilted[1] - tilted[0]).cross(tilted[2] - tilted[0]).normalize();
            assert!((hits[3].normal - normal).length() < 1e-6, "t {time}: {:?} against {normal}", hits[3]);
            if time > 0.0 {
                assert!(hits[3].normal.y < 0.0, "t {time}: the tilting triangle's normal has turned");
            }
            // Exactly the hits of a static build of the geometry as it is at that time.
            let still = [Moving::still(slide.at(at)), Moving::still(tilt.at(at))];
            let frozen = build_geometry(&context, &still, &BuildOptions::default()).unwrap();
            assert_eq!(trace(&context, &frozen, &query, &rays).0, hits, "{format:?} t {time}");
        }
    }
    // Where the triangle is at time 0 and at time 1, as rays at the other time see it.
    let early_spot = [down(0.25, 0.5, 1.0), down(0.25, 0.5, 0.0)];
    let late_spot = [down(2.25, 0.5, 0.0), down(2.25, 0.5, 1.0)];
    let (early, late) = (closest(&context, &accel, &early_spot), closest(&context, &accel, &late_spot));
    assert_eq!([early[0].hit(), early[1].hit(), late[0].hit(), late[1].hit()], [false, true, false, true]);
}

// ---------------------------------------------------------------------------------------------------------------
// 2. and 3. SRT motion: the seeds' examples.
// ---------------------------------------------------------------------------------------------------------------

/// The corners of the test triangle of the SRT examples.
const SRT_TRIANGLE: [Vec3; 3] = [Vec3::new(1.0, 0.0, 0.0), Vec3::new(6.0, 0.0, 0.0), Vec3::new(1.0, 5.0, 0.0)];

/// The point of a triangle with barycentrics `(u, v)` (weights of its second and third corners).
fn point_of(corners: &[Vec3; 3], (u, v): (f32, f32)) -> Vec3 {
    corners[0] + (corners[1] - corners[0]) * u + (corners[2] - corners[0]) * v
}

/// Points inside the triangle, by barycentrics.
const INSIDE: [(f32, f32); 5] = [(0.2, 0.3), (0.5, 0.25), (0.1, 0.6), (0.3, 0.3), (0.7, 0.1)];
/// Points outside it.
const OUTSIDE: [(f32, f32); 4] = [(-0.2, 0.3), (0.7, 0.6), (0.3, -0.1), (-0.1, -0.1)];

/// Rays straight down from 4 above the world points `to_world(p)` of the object points `points`, at `time`.
fn rays_onto(to_world: &Affine3A, corners: &[Vec3; 3], points: &[(f32, f32)], time: f32) -> Vec<Ray> {
    points
        .iter()
        .map(|&uv| {
            let w = to_world.transform_point3(point_of(corners, uv));
            Ray { origin: Vec3A::from(w) + Vec3A::new(0.0, 0.0, 4.0), direction: -Vec3A::Z, time, ..Ray::default() }
        })
        .collect()
}

/// Asserts that the rays onto the inside points hit with their barycentrics and the others miss.
fn assert_lands(hits: &[Record], inside: &[(f32, f32)], tolerance: f32, what: &str) {
    for (hit, &(u, v)) in hits.iter().zip(inside) {
        assert!(hit.hit(), "{what}: the ray onto ({u}, {v}) misses");
        assert!((hit.u - u).abs() < tolerance && (hit.v - v).abs() < tolerance, "{what}: ({u}, {v}) hit at {hit:?}");
        assert!((hit.t - 4.0).abs() < 1e-4, "{what}: {hit:?}");
    }
    for hit in &hits[inside.len()..] {
        assert!(!hit.hit(), "{what}: a ray beside the triangle hits {hit:?}");
    }
}

#[test]
fn srt_rotation_of_60_degrees_about_z_is_reached_at_the_end_and_follows_nlerp_between() {
    let context = cpu();
    let corners = SRT_TRIANGLE;
    let geometry = build_geometry(&context, &[one_triangle(corners)], &BuildOptions::default()).unwrap();
    let half = std::f32::consts::FRAC_PI_6;
    let q60 = Quat::from_xyzw(0.0, 0.0, half.sin(), half.cos());
    let turned = srt(Vec3::ONE, [0.0; 3], Vec3::ZERO, q60, Vec3::ZERO);
    let options = motion(2, 0.0, 1.0, MotionFlags::empty());
    let srt_motion = TransformInput::SrtMotion { keys: vec![srt_identity(), turned], motion: options };
    let moving = context.build_transform(&srt_motion, &geometry).unwrap();
    assert_eq!((moving.info().kind, moving.info().options.motion), (AccelKind::SrtMotionTransform, options));
    let placed = Affine3A::from_rotation_translation(Quat::from_rotation_z(0.2), Vec3::new(3.0, -2.0, 0.5));
    let scene =
        context.build_instance_accel(&[instance(Placement::rows(&placed), 7, &moving)], &BuildOptions::default());
    let scene = scene.unwrap();
    let points: Vec<(f32, f32)> = INSIDE.iter().chain(&OUTSIDE).copied().collect();

    // Time 1: where a static 60° rotation puts it.
    let rotated = Affine3A::from_rotation_z(std::f32::consts::FRAC_PI_3);
    let still = context.build_transform(&TransformInput::Static(Placement::rows(&rotated)), &geometry).unwrap();
    let reference =
        context.build_instance_accel(&[instance(Placement::rows(&placed), 7, &still)], &BuildOptions::default());
    let reference = reference.unwrap();
    let rays = rays_onto(&(placed * rotated), &corners, &points, 1.0);
    let (hits, expected) = (closest(&context, &scene, &rays), closest(&context, &reference, &rays));
    assert_lands(&hits, &INSIDE, 1e-5, "time 1");
    for (hit, want) in hits.iter().zip(&expected) {
        assert_eq!((hit.hit(), hit.prim, hit.geom, hit.path()), (want.hit(), want.prim, want.geom, want.path()));
        assert!((hit.t - want.t).abs() < 1e-5 && (hit.u - want.u).abs() < 1e-5 && (hit.v - want.v).abs() < 1e-5);
        assert!(!hit.hit() || (hit.normal - want.normal).length() < 1e-5);
    }
    assert!(hits.iter().filter(|h| h.hit()).all(|h| h.path() == [7] && h.inst == 7));
    // The unrotated places are not where the triangle is (the rotation is applied).
    let unturned = closest(&context, &scene, &rays_onto(&placed, &corners, &[(0.8, 0.1), (0.9, 0.05)], 1.0));
    assert!(unturned.iter().all(|h| !h.hit()), "{unturned:?}");

    // Between the keys (and at the first): where nlerp and C = T·R·S put it.
    for time in [0.0, 0.25, 0.5, 0.8] {
        let f = time; // the range is [0, 1] with 2 keys
        let rotation = (Quat::IDENTITY * (1.0 - f) + q60 * f).normalize();
        let c = Affine3A::from_translation(Vec3::ZERO) * Affine3A::from_quat(rotation) * Affine3A::IDENTITY;
        let hits = closest(&context, &scene, &rays_onto(&(placed * c), &corners, &points, time));
        assert_lands(&hits, &INSIDE, 1e-5, &format!("time {time}"));
        if time == 0.25 {
            // Slerp turns by 15° here; nlerp by 14.74°: its points would be hit elsewhere on the triangle.
            let slerp = Affine3A::from_quat(Quat::IDENTITY.slerp(q60, f));
            let (u, v) = (0.5, 0.25);
            let seen = slerp.inverse().transform_point3(c.transform_point3(point_of(&corners, (u, v))));
            let (su, sv) = ((seen.x - 1.0) / 5.0, seen.y / 5.0);
            assert!((su - u).abs() + (sv - v).abs() > 2e-3, "the test tells nlerp from slerp: {su} {sv}");
        }
    }
}

#[test]
fn srt_rotation_and_scaling_about_a_pivot_keep_the_pivot_fixed() {
    let context = cpu();
    let options = motion(2, 0.0, 1.0, MotionFlags::empty());

    // Example 2: 90° about z around P = (2, 1, 0): S' = P⁻¹·S (pivot −P), T' = T·P (translation P).
    let pivot = Vec3::new(2.0, 1.0, 0.0);
    let corners = [Vec3::new(1.0, 0.0, 0.0), Vec3::new(4.0, 0.0, 0.0), Vec3::new(1.0, 3.0, 0.0)];
    let geometry = build_geometry(&context, &[one_triangle(corners)], &BuildOptions::default()).unwrap();
    let quarter = Quat::from_xyzw(0.0, 0.0, std::f32::consts::FRAC_PI_4.sin(), std::f32::consts::FRAC_PI_4.cos());
    let pivoted = |q: Quat| srt(Vec3::ONE, [0.0; 3], -pivot, q, pivot);
    let centre = (1.0 / 3.0, 1.0 / 3.0); // the pivot's barycentrics
    assert!((point_of(&corners, centre) - pivot).length() < 1e-6);
    let inside = [centre, (0.2, 0.3), (0.5, 0.2), (0.1, 0.6)];
    let points: Vec<(f32, f32)> = inside.iter().chain(&OUTSIDE).copied().collect();
    // As the seed gives it, the first key the identity: the pivot terms are interpolated per element too (pivot
    // −f·P, translation f·P), so C = T·R·S turns about P only at the keys; between them p ↦ f·P + R·(p − f·P).
    let seed_keys = TransformInput::SrtMotion { keys: vec![srt_identity(), pivoted(quarter)], motion: options };
    // With the pivot in both keys it turns about P all along: p ↦ P + R·(p − P).
    let both_keys =
        TransformInput::SrtMotion { keys: vec![pivoted(Quat::IDENTITY), pivoted(quarter)], motion: options };
    for (keys, fixed_throughout) in [(seed_keys, false), (both_keys, true)] {
        let spinning = context.build_transform(&keys, &geometry).unwrap();
        for time in [-1.0f32, 0.0, 0.3, 0.5, 1.0, 3.0] {
            let f = time.clamp(0.0, 1.0);
            let rotation = (Quat::IDENTITY * (1.0 - f) + quarter * f).normalize();
            let about = if fixed_throughout { pivot } else { pivot * f };
            let expected =
                Affine3A::from_translation(about) * Affine3A::from_quat(rotation) * Affine3A::from_translation(-about);
            let what = format!("rotation about the pivot (fixed throughout: {fixed_throughout}), time {time}");
            let hits = closest(&context, &spinning, &rays_onto(&expected, &corners, &points, time));
            assert_lands(&hits, &inside, 1e-5, &what);
            let at_pivot = closest(&context, &spinning, &[down(pivot.x, pivot.y, time)])[0];
            let stays = (at_pivot.u - centre.0).abs() < 1e-5 && (at_pivot.v - centre.1).abs() < 1e-5;
            assert_eq!(stays, fixed_throughout || f == 0.0 || f == 1.0, "{what}: {at_pivot:?}");
        }
        // At the end a corner has turned a quarter about the pivot: (4, 0) → (3, 3).
        let turned_corner = closest(&context, &spinning, &[down(3.0 - 0.05, 3.0 - 0.1, 1.0), down(3.05, 3.0, 1.0)]);
        assert!(turned_corner[0].hit() && !turned_corner[1].hit(), "{turned_corner:?}");
    }

    // Example 3: scaling by 3 about G = (1, 2, 0): pvx' = −sx·Gx + Gx (and so on).
    let g = Vec3::new(1.0, 2.0, 0.0);
    let corners = [Vec3::new(0.0, 1.0, 0.0), Vec3::new(3.0, 1.0, 0.0), Vec3::new(0.0, 4.0, 0.0)];
    let geometry = build_geometry(&context, &[one_triangle(corners)], &BuildOptions::default()).unwrap();
    let s = 3.0;
    let key = srt(Vec3::splat(s), [0.0; 3], -s * g + g, Quat::IDENTITY, Vec3::ZERO);
    let grow = TransformInput::SrtMotion { keys: vec![srt_identity(), key], motion: options };
    let growing = context.build_transform(&grow, &geometry).unwrap();
    let centre = (1.0 / 3.0, 1.0 / 3.0);
    assert!((point_of(&corners, centre) - g).length() < 1e-6);
    for time in [0.0, 0.25, 0.5, 1.0] {
        let scale = 1.0 + (s - 1.0) * time;
        // About the pivot: p ↦ G + s·(p − G).
        let about_pivot = Affine3A::from_translation(g)
            * Affine3A::from_scale(Vec3::new(scale, scale, scale))
            * Affine3A::from_translation(-g);
        let points: Vec<(f32, f32)> = INSIDE.iter().chain(&OUTSIDE).copied().collect();
        let hits = closest(&context, &growing, &rays_onto(&about_pivot, &corners, &points, time));
        assert_lands(&hits, &INSIDE, 1e-5, &format!("scaling about the pivot, time {time}"));
        let at_pivot = closest(&context, &growing, &[down(g.x, g.y, time)])[0];
        assert!((at_pivot.u - centre.0).abs() < 1e-5 && (at_pivot.v - centre.1).abs() < 1e-5, "{at_pivot:?}");
    }
    // At the end the corner (3, 1) is at G + 3·((3, 1) − G) = (7, −1).
    let far_corner = closest(&context, &growing, &[down(6.9, -0.95, 1.0), down(6.9, -0.95, 0.5), down(7.1, -0.9, 1.0)]);
    assert_eq!(far_corner.iter().map(Record::hit).collect::<Vec<_>>(), [true, false, false], "{far_corner:?}");
}

// ---------------------------------------------------------------------------------------------------------------
// 4. Clamp and vanish.
// ---------------------------------------------------------------------------------------------------------------

/// The x of the rays of [`hit_pattern`]: 0.05, 0.15, …, 2.95 (never on a triangle's edge below).
fn pattern_xs() -> impl Iterator<Item = f32> {
    (0..30).map(|j| 0.05 + 0.1 * j as f32)
}

/// Which of the rays down at y = 0.1 and x in [`pattern_xs`] hit a unit triangle whose right-angle corner is at
/// `(offset, 0, 0)` (nothing when `None`): x in (offset, offset + 0.9).
fn expected_pattern(offset: Option<f32>) -> Vec<bool> {
    pattern_xs().map(|x| offset.is_some_and(|o| x > o && x < o + 0.9)).collect()
}

/// Which of those rays, at `time`, hit `accel`.
fn hit_pattern(context: &Context, accel: &Accel, time: f32) -> Vec<bool> {
    let rays: Vec<Ray> = pattern_xs().map(|x| down(x, 0.1, time)).collect();
    closest(context, accel, &rays).iter().map(Record::hit).collect()
}

/// Where a subject's sliding triangle is at a time (its right-angle corner's x), or `None` when it has vanished.
type Offset<'a> = Box<dyn Fn(f32) -> Option<f32> + 'a>;

/// Times before, at, inside and after the range [0, 1].
const EDGE_TIMES: [f32; 10] = [f32::NEG_INFINITY, -1.0, -0.25, 0.0, 0.5, 0.75, 1.0, 1.5, 2.5, f32::INFINITY];

#[test]
fn clamp_and_vanish_at_both_ends_for_geometry_transforms_and_instance_accels() {
    let context = cpu();
    let still = build_geometry(&context, &[at_corners(&[Vec3::ZERO])], &BuildOptions::default()).unwrap();
    // A child moving over [−0.5, 2] from x = 0 to x = 2, clamped, for the instance accels.
    let wide = motion(2, -0.5, 2.0, MotionFlags::empty());
    let wide_child = build_geometry(&context, &[sliding(Vec3::ZERO, Vec3::new(2.0, 0.0, 0.0), 2)], &with_motion(wide));
    let wide_child = wide_child.unwrap();
    let slide_x = |m: &MotionOptions, time: f32| key_at(m, time).map(|(s, f)| lerp(s as f32, (s + 1) as f32, f) * 2.0);
    let mut checked = 0;
    for flags in FLAG_SETS {
        let options = motion(2, 0.0, 1.0, flags);
        let geometry =
            build_geometry(&context, &[sliding(Vec3::ZERO, Vec3::new(2.0, 0.0, 0.0), 2)], &with_motion(options));
        let matrix = TransformInput::MatrixMotion {
            keys: vec![translation(Vec3::ZERO), translation(Vec3::new(2.0, 0.0, 0.0))],
            motion: options,
        };
        let srt_motion = TransformInput::SrtMotion {
            keys: vec![srt_identity(), srt(Vec3::ONE, [0.0; 3], Vec3::ZERO, Quat::IDENTITY, Vec3::new(2.0, 0.0, 0.0))],
            motion: options,
        };
        let identity = translation(Vec3::ZERO);
        let over_still = context.build_instance_accel(&[instance(identity, 1, &still)], &with_motion(options));
        let three_keys = with_motion(motion(3, 0.0, 1.0, flags));
        let over_wide = context.build_instance_accel(&[instance(identity, 2, &wide_child)], &three_keys).unwrap();
        // Instance accels over [−2, 3] whose children's motion stops at [0, 1] (clamped).
        let broad = with_motion(motion(3, -2.0, 3.0, flags));
        let clamped = motion(2, 0.0, 1.0, MotionFlags::empty());
        let by_matrix = TransformInput::MatrixMotion {
            keys: vec![translation(Vec3::ZERO), translation(Vec3::new(2.0, 0.0, 0.0))],
            motion: clamped,
        };
        let by_srt = TransformInput::SrtMotion {
            keys: vec![srt_identity(), srt(Vec3::ONE, [0.0; 3], Vec3::ZERO, Quat::IDENTITY, Vec3::new(2.0, 0.0, 0.0))],
            motion: clamped,
        };
        let broad_over = |t: &TransformInput| {
            let child = context.build_transform(t, &still).unwrap();
            context.build_instance_accel(&[instance(identity, 3, &child)], &broad).unwrap()
        };
        let in_broad = move |t: f32| key_at(&broad.motion, t).and(slide_x(&clamped, t));
        let subjects: [(&str, Arc<Accel>, Offset<'_>); 7] = [
            ("geometry accel", geometry.unwrap(), Box::new(|t| slide_x(&options, t))),
            (
                "matrix motion transform",
                context.build_transform(&matrix, &still).unwrap(),
                Box::new(|t| slide_x(&options, t)),
            ),
            (
                "SRT motion transform",
                context.build_transform(&srt_motion, &still).unwrap(),
                Box::new(|t| slide_x(&options, t)),
            ),
            ("instance accel over a still child", over_still.unwrap(), Box::new(|t| key_at(&options, t).map(|_| 0.0))),
            (
                "instance accel over a child moving over [-0.5, 2]",
                over_wide,
                Box::new(|t| key_at(&options, t).and(slide_x(&wide, t))),
            ),
            ("instance accel over [-2, 3] over a matrix motion transform", broad_over(&by_matrix), Box::new(in_broad)),
            ("instance accel over [-2, 3] over an SRT motion transform", broad_over(&by_srt), Box::new(in_broad)),
        ];
        for (what, accel, offset) in &subjects {
            for time in EDGE_TIMES {
                let expected = offset(time);
                let (begin, end) = if what.contains("[-2, 3]") { (-2.0, 3.0) } else { (0.0, 1.0) };
                let vanished = (time < begin && flags.contains(MotionFlags::START_VANISH))
                    || (time > end && flags.contains(MotionFlags::END_VANISH));
                assert_eq!(expected.is_none(), vanished, "the expectation itself, {what} {flags:?} {time}");
                assert_eq!(
                    hit_pattern(&context, accel, time),
                    expected_pattern(expected),
                    "{what}, {flags:?}, time {time}"
                );
                checked += 1;
            }
        }
        // The clamped ends are the end keys: x = 0 before, x = 2 after (x = 0 for the still child).
        if flags.is_empty() {
            assert_eq!(subjects[0].2(-1.0), Some(0.0));
            assert_eq!(subjects[1].2(7.0), Some(2.0));
        }
    }
    assert_eq!(checked, 4 * 7 * EDGE_TIMES.len());
}

// ---------------------------------------------------------------------------------------------------------------
// 5. Irregular ranges.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn an_irregular_range_puts_three_keys_at_minus_one_a_quarter_and_one_and_a_half() {
    let context = cpu();
    let options = motion(3, -1.0, 1.5, MotionFlags::empty());
    assert_eq!([options.key_time(0), options.key_time(1), options.key_time(2)], [-1.0, 0.25, 1.5]);
    // The right-angle corner's x at the three keys, and in between (piecewise linear in time, in f64).
    let key_x = [0.0, 4.0, 5.0];
    let key_times = [-1.0, 0.25, 1.5];
    let x_at = |time: f64| {
        if time <= key_times[0] {
            return key_x[0];
        }
        let k = if time <= key_times[1] { 0 } else { 1 };
        let f = ((time - key_times[k]) / (key_times[k + 1] - key_times[k])).min(1.0);
        key_x[k] + (key_x[k + 1] - key_x[k]) * f
    };
    let key_corners: Vec<Vec3> = key_x.iter().map(|&x| Vec3::new(x as f32, 0.0, 0.0)).collect();
    let still = build_geometry(&context, &[at_corners(&[Vec3::ZERO])], &BuildOptions::default()).unwrap();
    let matrix =
        TransformInput::MatrixMotion { keys: key_corners.iter().map(|&c| translation(c)).collect(), motion: options };
    let srt_motion = TransformInput::SrtMotion {
        keys: key_corners.iter().map(|&c| srt(Vec3::ONE, [0.0; 3], Vec3::ZERO, Quat::IDENTITY, c)).collect(),
        motion: options,
    };
    let moved_by_matrix = context.build_transform(&matrix, &still).unwrap();
    let subjects = [
        ("geometry accel", build_geometry(&context, &[at_corners(&key_corners)], &with_motion(options)).unwrap()),
        ("SRT motion transform", context.build_transform(&srt_motion, &still).unwrap()),
        (
            "motion instance accel over the matrix motion transform",
            context
                .build_instance_accel(&[instance(translation(Vec3::ZERO), 3, &moved_by_matrix)], &with_motion(options))
                .unwrap(),
        ),
        ("matrix motion transform", moved_by_matrix),
    ];
    for (what, accel) in &subjects {
        for time in [-3.0f32, -1.0, -0.7, -0.375, 0.0, 0.25, 0.5, 0.875, 1.2, 1.5, 4.0] {
            let x = x_at(time as f64) as f32;
            let rays = [down(x + 0.25, 0.1, time), down(x + 1.25, 0.1, time), down(x - 0.25, 0.1, time)];
            let hits = closest(&context, accel, &rays);
            assert!(hits[0].hit(), "{what}, time {time}: the triangle is at x = {x}");
            assert!((hits[0].u - 0.25).abs() < 1e-5 && (hits[0].v - 0.1).abs() < 1e-5, "{what}, {time}: {:?}", hits[0]);
            assert!(!hits[1].hit() && !hits[2].hit(), "{what}, time {time}: only at x = {x}");
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// 6. Random scenes against the scene frozen at each ray's time.
// ---------------------------------------------------------------------------------------------------------------

/// A node of a test scene: the engine's accel and what it was built from.
struct Node {
    /// The built accel.
    accel: Arc<Accel>,
    /// Its description.
    shape: Shape,
}

/// What a node was built from.
enum Shape {
    /// A geometry accel: one build input each, and its motion.
    Triangles(Vec<Moving>, MotionOptions),
    /// An instance accel: its instances and its motion.
    Instances(Vec<Member>, MotionOptions),
    /// A transform over a child.
    Transform(TransformInput, Rc<Node>),
}

/// One instance of a test scene.
struct Member {
    transform: [f32; 12],
    id: u32,
    child: Rc<Node>,
}

/// Instance ids from here on mark instances with an SRT motion transform below them.
const SRT_BELOW: u32 = 100;

/// A geometry accel node.
fn geometry_node(context: &Context, inputs: Vec<Moving>, motion: MotionOptions) -> Rc<Node> {
    let accel = build_geometry(context, &inputs, &with_motion(motion)).unwrap();
    Rc::new(Node { accel, shape: Shape::Triangles(inputs, motion) })
}

/// An instance accel node.
fn instances_node(context: &Context, members: Vec<Member>, motion: MotionOptions) -> Rc<Node> {
    let list: Vec<Instance> = members.iter().map(|m| instance(m.transform, m.id, &m.child.accel)).collect();
    let accel = context.build_instance_accel(&list, &with_motion(motion)).unwrap();
    Rc::new(Node { accel, shape: Shape::Instances(members, motion) })
}

/// A transform node.
fn transform_node(context: &Context, input: TransformInput, child: Rc<Node>) -> Rc<Node> {
    let accel = context.build_transform(&input, &child.accel).unwrap();
    assert_eq!(accel.info().depth, child.accel.info().depth + 1);
    Rc::new(Node { accel, shape: Shape::Transform(input, child) })
}

/// The node as it is at `time`, built static (`None` when nothing of it is there).
fn frozen(context: &Context, node: &Node, time: f32) -> Option<Arc<Accel>> {
    match &node.shape {
        Shape::Triangles(inputs, motion) => {
            let at = key_at(motion, time)?;
            let still: Vec<Moving> = inputs.iter().map(|m| Moving::still(m.at(at))).collect();
            Some(build_geometry(context, &still, &BuildOptions::default()).unwrap())
        }
        Shape::Instances(members, motion) => {
            key_at(motion, time)?;
            let list: Vec<Instance> = members
                .iter()
                .filter_map(|m| Some(instance(m.transform, m.id, &frozen(context, &m.child, time)?)))
                .collect();
            (!list.is_empty()).then(|| context.build_instance_accel(&list, &BuildOptions::default()).unwrap())
        }
        Shape::Transform(input, child) => {
            let matrix = transform_at(input, time)?;
            let child = frozen(context, child, time)?;
            Some(context.build_transform(&TransformInput::Static(matrix), &child).unwrap())
        }
    }
}

/// A random rotation, non-uniform scale and shift (no mirror, so that interpolated matrices stay invertible).
fn random_affine(seed: u64, k: u64, reach: f32) -> Affine3A {
    let u = |j: u64| uniform(seed, k * 32 + j);
    let axis = Vec3::new(u(0) - 0.5, u(1) - 0.5, u(2) - 0.5).normalize_or(Vec3::Z);
    let rotation = Quat::from_axis_angle(axis, u(3) * std::f32::consts::TAU);
    let scale = Vec3::new(0.5 + u(4), 0.5 + u(5), 0.5 + u(6));
    let shift = Vec3::new(u(7) - 0.5, u(8) - 0.5, u(9) - 0.5) * reach;
    Affine3A::from_scale_rotation_translation(scale, rotation, shift)
}

/// A random point of the cube [−0.5, 0.5]³ times `size`.
fn random_offset(seed: u64, k: u64, size: f32) -> Vec3 {
    (Vec3::new(uniform(seed, 3 * k), uniform(seed, 3 * k + 1), uniform(seed, 3 * k + 2)) - 0.5) * size
}

/// `count` random triangles with corners within 0.35 of an anchor in the unit cube (large enough for random rays
/// to meet often).
fn chunky_soup(count: usize, seed: u64) -> Mesh {
    let positions: Vec<Vec3> = (0..count as u64)
        .flat_map(|i| {
            let anchor = random_offset(seed, 4 * i, 1.0) + 0.5;
            (1..4).map(move |c| anchor + random_offset(seed, 4 * i + c, 0.7))
        })
        .collect();
    Mesh { triangles: (0..count as u32).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect(), positions }
}

/// The scene: matrix motion over SRT motion over a static transform over a moving geometry accel, motion instance
/// accels over children moving over other ranges (or vanishing), all under a static instance accel.
fn random_scene(context: &Context, seed: u64) -> Rc<Node> {
    // Random triangles jittering over 3 keys, and a sphere sliding and swelling, over [−0.5, 2], clamped.
    let soup = chunky_soup(40, seed);
    let cloud_motion = motion(3, -0.5, 2.0, MotionFlags::empty());
    let jitter = Moving::from_mesh(&soup, 3, |k, i, p| p + random_offset(seed + 1, (k * 1000 + i) as u64, 0.3));
    let ball = Moving::from_mesh(&icosphere(1, Vec3::ZERO), 3, |k, _, p| {
        p * (0.3 + 0.1 * k as f32) + Vec3::new(3.0 * k as f32 - 3.0, 0.5, 0.5 * k as f32)
    });
    let cloud = geometry_node(context, vec![jitter, ball], cloud_motion);
    // Triangles there only during [0.2, 0.8].
    let blink = Moving::from_mesh(&chunky_soup(20, seed + 2), 2, |k, i, p| {
        p + random_offset(seed + 3, i as u64, 0.4) * k as f32
    });
    let blinker = geometry_node(context, vec![blink], motion(2, 0.2, 0.8, VANISH));
    // A static sphere, and 4 keys over [0, 1] that vanish before.
    let ball = Moving::from_mesh(&icosphere(2, Vec3::ZERO), 1, |_, _, p| p * 0.4 + Vec3::new(2.0, 0.5, 0.5));
    let still = geometry_node(context, vec![ball], MotionOptions::STATIC);
    let quick = Moving::from_mesh(&chunky_soup(20, seed + 4), 4, |k, i, p| {
        p + random_offset(seed + 5, (k * 100 + i) as u64, 0.5)
    });
    let quick = geometry_node(context, vec![quick], motion(4, 0.0, 1.0, MotionFlags::START_VANISH));

    // The chain of transforms over the cloud.
    let fixed = TransformInput::Static(Placement::rows(&random_affine(seed, 1, 1.0)));
    let placed = transform_node(context, fixed, Rc::clone(&cloud));
    let axis = random_offset(seed + 6, 0, 1.0).normalize();
    let srt_keys = (0..3u64)
        .map(|k| {
            let u = |j: u64| uniform(seed + 7, k * 16 + j);
            let tilt = (axis + random_offset(seed + 8, k, 0.2)).normalize();
            srt(
                Vec3::new(0.7 + 0.6 * u(0), 0.7 + 0.6 * u(1), 0.7 + 0.6 * u(2)),
                [0.4 * u(3) - 0.2, 0.4 * u(4) - 0.2, 0.4 * u(5) - 0.2],
                random_offset(seed + 9, k, 1.0),
                Quat::from_axis_angle(tilt, k as f32 * 1.7),
                random_offset(seed + 10, k, 1.5),
            )
        })
        .collect();
    let turning = transform_node(
        context,
        TransformInput::SrtMotion { keys: srt_keys, motion: motion(3, -1.0, 1.5, MotionFlags::empty()) },
        placed,
    );
    let matrix_keys =
        vec![Placement::rows(&random_affine(seed, 2, 1.0)), Placement::rows(&random_affine(seed, 3, 1.0))];
    let swept = transform_node(
        context,
        TransformInput::MatrixMotion { keys: matrix_keys, motion: motion(2, 0.25, 1.25, MotionFlags::END_VANISH) },
        Rc::clone(&turning),
    );
    let blinker_keys = (0..3).map(|k| Placement::rows(&random_affine(seed, 4 + k, 1.0))).collect();
    let waving = transform_node(
        context,
        TransformInput::MatrixMotion { keys: blinker_keys, motion: motion(3, 0.0, 1.0, MotionFlags::empty()) },
        Rc::clone(&blinker),
    );

    // Motion instance accels whose ranges differ from their children's.
    let member = |k: u64, id: u32, child: &Rc<Node>| Member {
        transform: Placement::rows(&random_affine(seed, 10 + k, 2.0)),
        id,
        child: Rc::clone(child),
    };
    let group = instances_node(
        context,
        vec![
            member(0, SRT_BELOW + 1, &swept),
            member(1, 2, &cloud),
            member(2, 3, &blinker),
            member(3, 4, &still),
            member(4, 5, &waving),
            member(5, 6, &quick),
        ],
        motion(3, 0.0, 1.0, MotionFlags::empty()),
    );
    let fading =
        instances_node(context, vec![member(6, 7, &cloud), member(7, 8, &waving)], motion(2, 0.0, 1.0, VANISH));
    // And one over [−2, 3], beyond its children's ranges.
    let broad = instances_node(
        context,
        vec![member(13, 1, &waving), member(14, SRT_BELOW + 2, &turning), member(15, 3, &quick)],
        motion(3, -2.0, 3.0, MotionFlags::empty()),
    );
    let top = vec![
        Member { transform: translation(Vec3::ZERO), id: 10, child: Rc::clone(&group) },
        member(8, 11, &group),
        member(9, SRT_BELOW + 12, &turning),
        member(10, 13, &fading),
        member(11, 14, &cloud),
        member(12, 15, &quick),
        member(16, 16, &broad),
    ];
    instances_node(context, top, MotionOptions::STATIC)
}

/// Calls `visit` with the corners of each triangle of `node` as it is at `time`, placed by `to_world`.
fn each_triangle(node: &Node, time: f32, to_world: Affine3A, visit: &mut dyn FnMut([Vec3; 3])) {
    let place = |matrix: &[f32; 12]| to_world * Placement::new(matrix).unwrap().object_to_world;
    match &node.shape {
        Shape::Triangles(inputs, motion) => {
            let Some(at) = key_at(motion, time) else { return };
            for mesh in inputs.iter().map(|m| m.at(at)) {
                for triangle in 0..mesh.triangles.len() {
                    visit(mesh.corners(triangle).map(|c| to_world.transform_point3(c)));
                }
            }
        }
        Shape::Instances(members, motion) => {
            if key_at(motion, time).is_some() {
                for m in members {
                    each_triangle(&m.child, time, place(&m.transform), visit);
                }
            }
        }
        Shape::Transform(input, child) => {
            if let Some(matrix) = transform_at(input, time) {
                each_triangle(child, time, place(&matrix), visit);
            }
        }
    }
}

/// A point of each triangle of `node` as it is at `time` (at barycentrics drawn from `seed`).
fn points_on(node: &Node, time: f32, seed: u64) -> Vec<Vec3> {
    let mut points = Vec::new();
    each_triangle(node, time, Affine3A::IDENTITY, &mut |corners| {
        let k = points.len() as u64;
        let (u, v) = (0.1 + 0.4 * uniform(seed, 2 * k), 0.1 + 0.4 * uniform(seed, 2 * k + 1));
        points.push(point_of(&corners, (u, v)));
    });
    points
}

/// Every node of the scene below `node` (itself included).
fn nodes_below<'a>(node: &'a Node, out: &mut Vec<&'a Node>) {
    out.push(node);
    match &node.shape {
        Shape::Triangles(..) => {}
        Shape::Instances(members, _) => members.iter().for_each(|m| nodes_below(&m.child, out)),
        Shape::Transform(_, child) => nodes_below(child, out),
    }
}

/// Whether a hit lies within `margin` of its triangle's edges.
fn near_edge(record: &Record, margin: f32) -> bool {
    record.hit() && record.u.min(record.v).min(1.0 - record.u - record.v) < margin
}

/// Whether two hits are the same up to rounding: same ids and path, `t`, `u` and `v` within a tight tolerance.
fn close(a: &Record, b: &Record) -> bool {
    (a.prim, a.geom, a.inst, a.path(), a.back_face) == (b.prim, b.geom, b.inst, b.path(), b.back_face)
        && (a.t - b.t).abs() <= 2e-5 * a.t.abs().max(1.0)
        && (a.u - b.u).abs() <= 2e-5
        && (a.v - b.v).abs() <= 2e-5
        && (a.normal - b.normal).length() <= 1e-4
}

#[test]
fn moving_scenes_hit_as_the_scene_frozen_at_each_ray_time() {
    let context = cpu();
    let seed = 23;
    let scene = random_scene(&context, seed);
    assert_eq!(scene.accel.info().depth, 6, "top, group, matrix, SRT, static, geometry");
    let times =
        [f32::NEG_INFINITY, -1.5, -1.0, -0.5, -0.1, 0.0, 0.2, 0.25, 0.4, 0.5, 0.77, 0.8, 1.0, 1.25, 1.7, f32::INFINITY];
    let rays_per_time = 600;
    let (lo, hi) = scene.accel.info().bounds;
    assert!(lo.is_finite() && hi.is_finite(), "{lo} {hi}");
    // Rays from anywhere around the scene, most to a point of some triangle as it is at the ray's time.
    let targets: Vec<Vec<Vec3>> = times.iter().map(|&time| points_on(&scene, time, seed + 99)).collect();
    let rays: Vec<Ray> = (0..(times.len() * rays_per_time) as u64)
        .map(|i| {
            let u = |j: u64| uniform(seed + 100, i * 8 + j);
            let from = lo + (hi - lo) * (Vec3::new(u(0), u(1), u(2)) * 1.5 - 0.25);
            let (time, targets) = (times[i as usize % times.len()], &targets[i as usize % times.len()]);
            // One ray in four to anywhere in the scene's box (they mostly miss).
            let to = if (i / times.len() as u64) % 4 == 3 {
                lo + (hi - lo) * Vec3::new(u(3), u(4), u(5))
            } else {
                targets[(u(3) * targets.len() as f32) as usize % targets.len()]
            };
            Ray { origin: from.into(), direction: (to - from).into(), time, ..Ray::default() }
        })
        .collect();
    let closest_query = Query::closest(RayFormat::Full, HitFormat::Full);
    let all_query = Query {
        kind: QueryKind::All,
        max_hits_per_ray: 6,
        ..Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::Full)
    };
    let engine: Vec<(Vec<Record>, Vec<u32>)> =
        [closest_query, all_query].iter().map(|q| trace(&context, &scene.accel, q, &rays)).collect();

    let (mut compared, mut hits, mut rounded, mut all_hits) = (0, 0, 0, 0);
    let mut hits_by_time = vec![0; times.len()];
    let mut tops = std::collections::BTreeSet::new();
    for (ti, &time) in times.iter().enumerate() {
        let members: Vec<usize> = (ti..rays.len()).step_by(times.len()).collect();
        let subset: Vec<Ray> = members.iter().map(|&i| rays[i]).collect();
        let reference = frozen(&context, &scene, time);
        for (query, (got, got_counts)) in [closest_query, all_query].iter().zip(&engine) {
            let per_ray = query.records_per_ray();
            let (want, want_counts) = match &reference {
                Some(accel) => trace(&context, accel, query, &subset),
                None => (
                    vec![Record::MISS; subset.len() * per_ray],
                    vec![0; if query.kind.has_counts() { subset.len() } else { 0 }],
                ),
            };
            for (j, &i) in members.iter().enumerate() {
                let got = &got[i * per_ray..(i + 1) * per_ray];
                let want = &want[j * per_ray..(j + 1) * per_ray];
                let (got_count, want_count) =
                    if query.kind.has_counts() { (got_counts[i], want_counts[j]) } else { (0, 0) };
                compared += 1;
                if query.kind == QueryKind::Closest {
                    hits += usize::from(want[0].hit());
                    hits_by_time[ti] += usize::from(got[0].hit());
                    tops.extend(got[0].path().first().copied());
                } else {
                    all_hits += want_count as usize;
                }
                if got == want && got_count == want_count {
                    continue;
                }
                // Only below an SRT transform may rounding differ: then the same hits, within a tolerance, or a
                // different hit at a triangle's edge.
                let srt_below = got.iter().chain(want).any(|r| r.path().iter().any(|&id| id >= SRT_BELOW));
                let same_up_to_rounding =
                    got_count == want_count && got.iter().zip(want).all(|(a, b)| a == b || close(a, b));
                let at_edge = got.iter().chain(want).any(|r| near_edge(r, 1e-4));
                assert!(
                    srt_below && (same_up_to_rounding || at_edge),
                    "{:?} ray {i} at time {time}: moving scene {got:?} ({got_count} hits), frozen {want:?} \
                     ({want_count} hits)",
                    query.kind
                );
                rounded += 1;
            }
        }
    }
    eprintln!(
        "{compared} rays compared, {hits} closest hits, {all_hits} hits of `all` queries, {rounded} equal up to \
         rounding; closest hits by time: {hits_by_time:?}; top instances hit: {tops:?}"
    );
    assert!(rounded * 100 <= compared, "{rounded} of {compared} rays differ in rounding");
    let rays_closest = compared / 2;
    assert!(
        hits * 2 > rays_closest && hits * 10 < rays_closest * 9,
        "most rays hit, not all: {hits} of {rays_closest}"
    );
    assert!(hits_by_time.iter().all(|&n| n > 20), "every time sees something: {hits_by_time:?}");
    assert_eq!(
        tops.into_iter().collect::<Vec<_>>(),
        [10, 11, 13, 14, 15, 16, SRT_BELOW + 12],
        "every top instance is hit"
    );
}

#[test]
fn a_motion_blurred_cameras_rays_hit_moving_scenes_as_they_are_frozen_at_each_rays_time() {
    // A camera's neighbouring rays head the same way from one origin: the CPU backend walks them together, as packets
    // whose rays are each at a time of their own, through a moving accel and through instances of motion transforms,
    // and each must get what the scene frozen at its time gives it.
    let context = cpu();
    let seed = 41;
    let swelling = |k: usize, i: usize, p: Vec3| {
        p * (1.0 + 0.15 * k as f32) + Vec3::X * 0.2 * k as f32 + random_offset(seed, (k * 10_000 + i) as u64, 0.02)
    };
    let shaken = |k: usize, i: usize, p: Vec3| p + random_offset(seed + 1, (k * 10_000 + i) as u64, 0.1);
    let meshes = vec![
        Moving::from_mesh(&icosphere(3, Vec3::splat(0.5)), 3, swelling),
        Moving::from_mesh(&random_soup(300, seed), 3, shaken),
    ];
    let moving = geometry_node(&context, meshes, motion(3, 0.0, 1.0, MotionFlags::END_VANISH));
    // The moving meshes as they are, and slid and tilted by a matrix motion transform that is not there before its
    // range.
    let slide = TransformInput::MatrixMotion {
        keys: vec![translation(Vec3::ZERO), Placement::rows(&random_affine(seed, 2, 0.3))],
        motion: motion(2, 0.0, 1.0, MotionFlags::START_VANISH),
    };
    let slid = transform_node(&context, slide, Rc::clone(&moving));
    let members = || {
        vec![
            Member { transform: translation(Vec3::ZERO), id: 1, child: Rc::clone(&moving) },
            Member { transform: translation(Vec3::new(1.2, 0.0, 0.0)), id: 2, child: Rc::clone(&slid) },
        ]
    };
    // Placed by a static instance accel, and by a motion instance accel (its nodes' boxes move with time).
    let placed = instances_node(&context, members(), MotionOptions::STATIC);
    let placed_moving = instances_node(&context, members(), motion(3, 0.0, 1.0, MotionFlags::empty()));
    let times = [-0.3, 0.0, 0.2, 0.5, 0.5001, 0.75, 1.0, 1.1];
    let scenes = [
        ("moving meshes", &moving),
        ("instances of them and of a motion transform", &placed),
        ("the same in a motion instance accel", &placed_moving),
    ];
    for (scene, node) in scenes {
        let (lo, hi) = node.accel.info().bounds;
        let camera = Camera::framing(lo, hi, 64, 64);
        let rays: Vec<Ray> = (0..64 * 64u32)
            .map(|i| Ray { time: times[i as usize * 5 % times.len()], ..camera.ray(i % 64, i / 64) })
            .collect();
        let all =
            Query { kind: QueryKind::All, max_hits_per_ray: 4, ..Query::closest(RayFormat::Full, HitFormat::Full) };
        for query in [Query::closest(RayFormat::Full, HitFormat::Full), all] {
            let (got, got_counts) = trace(&context, &node.accel, &query, &rays);
            let per_ray = query.records_per_ray();
            let mut hits_by_time = vec![0; times.len()];
            for (ti, &time) in times.iter().enumerate() {
                let members: Vec<usize> = (0..rays.len()).filter(|&i| rays[i].time == time).collect();
                let subset: Vec<Ray> = members.iter().map(|&i| rays[i]).collect();
                let (want, want_counts) = match frozen(&context, node, time) {
                    Some(accel) => trace(&context, &accel, &query, &subset),
                    None => (vec![Record::MISS; subset.len() * per_ray], vec![0; subset.len()]),
                };
                for (j, &i) in members.iter().enumerate() {
                    let (got, want) = (&got[i * per_ray..(i + 1) * per_ray], &want[j * per_ray..(j + 1) * per_ray]);
                    assert_eq!(got, want, "{scene}: {:?} ray {i} at time {time}", query.kind);
                    if query.kind.has_counts() {
                        assert_eq!(got_counts[i], want_counts[j], "{scene}: {:?} ray {i} at time {time}", query.kind);
                    }
                    hits_by_time[ti] += usize::from(got[0].hit());
                }
            }
            // Every time but the one past the meshes' vanishing end sees them.
            let seen = (0..times.len() - 1).all(|ti| hits_by_time[ti] > 20);
            assert!(seen && hits_by_time[times.len() - 1] == 0, "{scene}: hits by time {hits_by_time:?}");
        }
    }
}

#[test]
fn a_moving_mesh_is_built_into_a_tree_for_where_its_triangles_are_on_average_not_for_their_paths() {
    // Built over each triangle's box over all of time (a slab twenty triangles long), the tree's area cost fell
    // little when such boxes were split, and a ray tested 30% more triangles than in the sphere built static; built
    // over the box each triangle has on average over time, a ray at any time meets leaves like the static sphere's.
    let context = cpu();
    let sphere = icosphere(5, Vec3::ZERO);
    let edge = sphere.corners(0)[0].distance(sphere.corners(0)[1]);
    let sliding = Moving::from_mesh(&sphere, 2, |k, _, p| p + Vec3::X * 20.0 * edge * k as f32);
    let two_keys = with_motion(motion(2, 0.0, 1.0, MotionFlags::empty()));
    let moving = build_geometry(&context, std::slice::from_ref(&sliding), &two_keys).unwrap();
    let halfway = build_geometry(&context, &[Moving::still(sliding.at((0, 0.5)))], &BuildOptions::default()).unwrap();
    let (lo, hi) = moving.info().bounds;
    let camera = Camera::framing(lo, hi, 128, 128);
    let rays: Vec<Ray> =
        (0..128 * 128u32).map(|i| Ray { time: uniform(3, u64::from(i)), ..camera.ray(i % 128, i / 128) }).collect();
    let query = Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::TTriid);
    let bytes = pack_rays(&rays, query.ray_format);
    let mut hits = vec![0u8; query.output_layout(bytes.len()).unwrap().hits];
    let mut tests_a_ray = |accel: &Accel| {
        let out = TraceOutput { hits: &mut hits, counts: &mut [] };
        let stats = context.trace(accel, &query, &bytes, out).unwrap();
        stats.triangle_tests as f64 / rays.len() as f64
    };
    let (moving_tests, static_tests) = (tests_a_ray(&moving), tests_a_ray(&halfway));
    assert!(static_tests > 1.0, "the camera sees the sphere: {static_tests:.2} triangle tests a ray");
    assert!(
        moving_tests <= 1.15 * static_tests,
        "triangle tests a ray: {moving_tests:.2} moving against {static_tests:.2} static"
    );
}

#[test]
fn every_accel_of_a_moving_scene_bounds_its_triangles_at_every_time() {
    let context = cpu();
    let scene = random_scene(&context, 29);
    // A bar from the origin to x = 10 turning 170° about z: its tip passes y = 10 between the ends' boxes.
    let bar = geometry_node(
        &context,
        vec![one_triangle([Vec3::ZERO, Vec3::new(10.0, 0.0, 0.0), Vec3::new(10.0, 0.1, 0.0)])],
        MotionOptions::STATIC,
    );
    let half = 85f32.to_radians();
    let turn = srt(Vec3::ONE, [0.0; 3], Vec3::ZERO, Quat::from_xyzw(0.0, 0.0, half.sin(), half.cos()), Vec3::ZERO);
    let options = motion(2, 0.0, 1.0, MotionFlags::empty());
    let turning =
        transform_node(&context, TransformInput::SrtMotion { keys: vec![srt_identity(), turn], motion: options }, bar);
    let member = Member { transform: translation(Vec3::ZERO), id: 0, child: Rc::clone(&turning) };
    let over_turning = instances_node(&context, vec![member], motion(2, -0.5, 1.5, MotionFlags::empty()));
    let mut nodes = Vec::new();
    nodes_below(&scene, &mut nodes);
    nodes_below(&over_turning, &mut nodes);
    let mut times: Vec<f32> = (-192..=256).map(|i| i as f32 / 64.0).collect();
    times.extend([f32::NEG_INFINITY, f32::INFINITY, -0.375, 0.875, 1.7, 0.77]);
    let mut corners_checked = 0;
    for node in nodes {
        let (lo, hi) = node.accel.info().bounds;
        let slack = lo.abs().max(hi.abs()).max(Vec3::ONE) * 1e-5;
        for &time in &times {
            each_triangle(node, time, Affine3A::IDENTITY, &mut |corners| {
                for c in corners {
                    assert!(
                        c.cmpge(lo - slack).all() && c.cmple(hi + slack).all(),
                        "{:?} at time {time}: corner {c} outside its bounds {lo} {hi}",
                        node.accel.info().kind
                    );
                    corners_checked += 1;
                }
            });
        }
    }
    assert!(corners_checked > 100_000, "{corners_checked}");
}

// ---------------------------------------------------------------------------------------------------------------
// 7. Ray times that are not numbers, and infinite ones.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn a_nan_ray_time_fails_the_trace_and_infinite_times_clamp() {
    let context = cpu();
    let options = motion(2, 0.0, 1.0, MotionFlags::empty());
    let accel = build_geometry(&context, &[sliding(Vec3::ZERO, Vec3::new(2.0, 0.0, 0.0), 2)], &with_motion(options));
    let accel = accel.unwrap();
    let still = build_geometry(&context, &[at_corners(&[Vec3::ZERO])], &BuildOptions::default()).unwrap();
    for format in [RayFormat::OriginTminDirectionTmaxTime, RayFormat::Full] {
        let query = Query::closest(format, HitFormat::Full);
        let rays = [down(0.25, 0.1, 0.5), down(0.25, 0.1, f32::NAN), down(0.25, 0.1, 0.0)];
        let bytes = pack_rays(&rays, format);
        for target in [&accel, &still] {
            let mut hits = vec![0u8; query.output_layout(bytes.len()).unwrap().hits];
            let error = context.trace(target, &query, &bytes, TraceOutput { hits: &mut hits, counts: &mut [] });
            let error = error.unwrap_err();
            assert_eq!(error.kind(), ErrorKind::InvalidArgument, "{error}");
            assert!(matches!(error, Error::InvalidQuery { field: "rays.time", .. }), "{error:?}");
            assert!(error.to_string().contains("ray 1"), "names the ray: {error}");
        }
        // A format without time carries no NaN: the same bytes as a 32-byte ray are fine.
        let untimed = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::Full);
        assert!(trace(&context, &accel, &untimed, &rays).0.iter().all(Record::hit));

        let infinite = [down(0.25, 0.1, f32::NEG_INFINITY), down(2.25, 0.1, f32::INFINITY)];
        let (hits, _) = trace(&context, &accel, &query, &infinite);
        assert!(hits.iter().all(Record::hit), "−∞ sees the first key, +∞ the last: {hits:?}");
        let (crossed, _) =
            trace(&context, &accel, &query, &[down(2.25, 0.1, f32::NEG_INFINITY), down(0.25, 0.1, f32::INFINITY)]);
        assert!(crossed.iter().all(|h| !h.hit()), "{crossed:?}");
    }
    let vanishing =
        build_geometry(&context, &[at_corners(&[Vec3::ZERO, Vec3::ZERO])], &with_motion(motion(2, 0.0, 1.0, VANISH)));
    let hits = closest(
        &context,
        &vanishing.unwrap(),
        &[down(0.25, 0.1, f32::NEG_INFINITY), down(0.25, 0.1, f32::INFINITY), down(0.25, 0.1, 1.0)],
    );
    assert_eq!(hits.iter().map(Record::hit).collect::<Vec<_>>(), [false, false, true]);
}

// ---------------------------------------------------------------------------------------------------------------
// 8. Bad motion inputs.
// ---------------------------------------------------------------------------------------------------------------

/// Asserts that `result` is an invalid build input naming `field` and `element`, with `rule` in its message.
fn assert_refused<T: std::fmt::Debug>(result: rayd_engine::Result<T>, field: &str, element: Option<u64>, rule: &str) {
    match result {
        Err(error @ Error::InvalidBuildInput { field: f, element: e, .. }) => {
            assert_eq!((f, e), (field, element), "{error}");
            assert!(error.to_string().contains(rule), "{error}");
            assert_eq!(error.kind(), ErrorKind::InvalidArgument);
        }
        other => panic!("expected an invalid {field}, got {other:?}"),
    }
}

/// Asserts that `result` is invalid build options with `rule` in the message.
fn assert_bad_options<T: std::fmt::Debug>(result: rayd_engine::Result<T>, rule: &str) {
    match result {
        Err(error @ Error::InvalidBuildOptions(_)) => {
            assert!(error.to_string().contains(rule), "{error}");
            assert_eq!(error.kind(), ErrorKind::InvalidArgument);
        }
        other => panic!("expected invalid build options ({rule}), got {other:?}"),
    }
}

#[test]
fn bad_motion_inputs_are_refused_naming_field_element_and_rule() {
    let context = cpu();
    let two = motion(2, 0.0, 1.0, MotionFlags::empty());
    let three = motion(3, 0.0, 1.0, MotionFlags::empty());
    let still = build_geometry(&context, &[at_corners(&[Vec3::ZERO])], &BuildOptions::default()).unwrap();
    let good = at_corners(&[Vec3::ZERO, Vec3::X, Vec3::Y]);

    // Vertex buffers: one a key besides `vertices`, each as long as `vertices`.
    let short = Moving { keys: good.keys[..2].to_vec(), ..good.clone() };
    let rule = "1 vertex buffers given besides `vertices`; the build's 3 motion keys need 2";
    assert_refused(
        build_geometry(&context, &[good.clone(), short], &with_motion(three)),
        "motion_vertices",
        None,
        rule,
    );
    assert_refused(
        build_geometry(&context, std::slice::from_ref(&good), &BuildOptions::default()),
        "motion_vertices",
        None,
        "need 0",
    );
    let vertices = vertex_bytes(&good.keys[0]);
    let (key1, key2) = (vertex_bytes(&good.keys[1]), vertex_bytes(&good.keys[2]));
    let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect();
    let truncated = &key2[..key2.len() - 12];
    for (motion_vertices, element, rule) in [
        ([&key1[..], truncated], 1, "24 bytes for motion key 2, `vertices` has 36"),
        ([&key2[..12], &key1[..]], 0, "12 bytes for motion key 1, `vertices` has 36"),
    ] {
        let input = TriangleInput { motion_vertices: &motion_vertices, ..TriangleInput::indexed(&vertices, &indices) };
        let built = context.build_accel(&[BuildInput::Triangles(input)], &with_motion(three));
        assert_refused(built, "motion_vertices", Some(element), rule);
        assert!(context.compute_memory_usage(&[BuildInput::Triangles(input)], &with_motion(three)).is_err());
    }
    let mut nan = good.keys[2].clone();
    nan[1].y = f32::NAN;
    let nan_key = Moving { keys: vec![good.keys[0].clone(), good.keys[1].clone(), nan], ..good.clone() };
    assert_refused(
        build_geometry(&context, &[nan_key], &with_motion(three)),
        "motion_vertices",
        Some(1),
        "key 2, vertex 1",
    );

    // Motion options: keys 0, an empty or reversed range with 2 keys, an infinite range or one of infinite length; 1
    // key ignores the range.
    let identity = translation(Vec3::ZERO);
    for (options, rule) in [
        (motion(0, 0.0, 1.0, MotionFlags::empty()), "0 motion keys"),
        (motion(2, 1.0, 1.0, MotionFlags::empty()), "time_end 1 must be greater than time_begin 1"),
        (motion(2, 1.0, 0.5, MotionFlags::empty()), "time_end 0.5 must be greater than time_begin 1"),
        (motion(2, 0.0, f32::INFINITY, MotionFlags::empty()), "must be finite"),
        // Finite ends, but a length beyond f32: key times and a time's place among the keys would be NaN or ∞.
        (motion(2, -3e38, 3e38, MotionFlags::empty()), "and so must its length"),
        (motion(1025, 0.0, 1.0, MotionFlags::empty()), "1025 motion keys"),
    ] {
        let keys = (options.keys as usize).min(3);
        let input = at_corners(&vec![Vec3::ZERO; keys.max(1)]);
        assert_bad_options(build_geometry(&context, &[input], &with_motion(options)), rule);
        assert_bad_options(context.build_instance_accel(&[instance(identity, 0, &still)], &with_motion(options)), rule);
        assert_bad_options(context.compute_instance_arrays_memory_usage(1, &with_motion(options)), rule);
        let matrix = TransformInput::MatrixMotion { keys: vec![identity; options.keys as usize], motion: options };
        assert_refused(context.build_transform(&matrix, &still), "transform.motion", None, rule);
    }
    let still_range = motion(1, 5.0, 5.0, VANISH);
    assert!(build_geometry(&context, &[at_corners(&[Vec3::ZERO])], &with_motion(still_range)).is_ok());
    let one_key = TransformInput::MatrixMotion { keys: vec![identity], motion: still_range };
    assert_refused(context.build_transform(&one_key, &still), "transform.motion", None, "at least 2 motion keys");
    let too_few = TransformInput::MatrixMotion { keys: vec![identity; 2], motion: three };
    assert_refused(context.build_transform(&too_few, &still), "transform.keys", None, "2 keys given");
    let mut singular = identity;
    singular[5] = 0.0;
    let flat = TransformInput::MatrixMotion { keys: vec![identity, singular], motion: two };
    assert_refused(context.build_transform(&flat, &still), "transform.keys", Some(1), "invertible");

    // SRT keys: neighbouring quaternions 180° or more apart (dot product not positive) are refused by key.
    let about_z = |degrees: f32| {
        let half = degrees.to_radians() / 2.0;
        srt(Vec3::ONE, [0.0; 3], Vec3::ZERO, Quat::from_xyzw(0.0, 0.0, half.sin(), half.cos()), Vec3::ZERO)
    };
    let exactly_half_turn = srt(Vec3::ONE, [0.0; 3], Vec3::ZERO, Quat::from_xyzw(0.0, 0.0, 1.0, 0.0), Vec3::ZERO);
    for (keys, element) in [
        (vec![srt_identity(), about_z(200.0)], 1),
        (vec![srt_identity(), exactly_half_turn], 1),
        (vec![srt_identity(), about_z(120.0), about_z(300.5)], 2),
        (vec![about_z(-100.0), about_z(100.0), about_z(120.0)], 1),
    ] {
        let options = motion(keys.len() as u32, 0.0, 1.0, MotionFlags::empty());
        let input = TransformInput::SrtMotion { keys, motion: options };
        assert_refused(context.build_transform(&input, &still), "transform.keys", Some(element), "180° or more");
    }
    // Just under half a turn a key, and a quaternion given with another length, are fine.
    let fine = TransformInput::SrtMotion { keys: vec![srt_identity(), about_z(179.0), about_z(358.0)], motion: three };
    assert!(context.build_transform(&fine, &still).is_ok());
    let mut long = about_z(90.0);
    long[9..13].iter_mut().for_each(|q| *q *= 3.0);
    let scaled = TransformInput::SrtMotion { keys: vec![srt_identity(), long], motion: two };
    let turned = context.build_transform(&scaled, &still).unwrap();
    let hit = closest(&context, &turned, &[down(-0.1, 0.25, 1.0)])[0];
    assert!(hit.hit() && (hit.u - 0.25).abs() < 1e-5 && (hit.v - 0.1).abs() < 1e-5, "a quarter turn: {hit:?}");
    let mut zero = srt_identity();
    zero[12] = 0.0;
    let zero = TransformInput::SrtMotion { keys: vec![srt_identity(), zero], motion: two };
    assert_refused(context.build_transform(&zero, &still), "transform.keys", Some(1), "must not be 0");
    let mut no_scale = srt_identity();
    no_scale[7] = 0.0;
    let no_scale = TransformInput::SrtMotion { keys: vec![no_scale, srt_identity()], motion: two };
    assert_refused(context.build_transform(&no_scale, &still), "transform.keys", Some(0), "S must be invertible");
}

// ---------------------------------------------------------------------------------------------------------------
// 9. Updates.
// ---------------------------------------------------------------------------------------------------------------

#[test]
fn an_updated_motion_geometry_accel_traces_as_a_fresh_build() {
    let context = cpu();
    let seed = 31;
    let options =
        BuildOptions { flags: BuildFlags::ALLOW_UPDATE, motion: motion(3, -0.5, 1.5, MotionFlags::END_VANISH) };
    let soup = random_soup(200, seed);
    let sphere = icosphere(2, Vec3::splat(0.5));
    let shaken = |salt: u64, size: f32| {
        vec![
            Moving::from_mesh(&soup, 3, |k, i, p| p + random_offset(seed + salt, (k * 1000 + i) as u64, size)),
            Moving::from_mesh(&sphere, 3, |k, _, p| p * (0.3 + 0.1 * k as f32) + Vec3::X * (salt as f32 * 0.1)),
        ]
    };
    let (before, after) = (shaken(1, 0.2), shaken(2, 0.5));
    let accel = build_geometry(&context, &before, &options).unwrap();
    let packed = Packed::new(&after);
    let motion_vertices = packed.motion_vertices();
    // As many keys as the build, or refused as a change of structure.
    let mut one_short = motion_vertices.clone();
    one_short[0].truncate(1);
    let refused = context.update_accel(&accel, &packed.inputs(&one_short)).unwrap_err();
    assert_eq!(refused.kind(), ErrorKind::FailedPrecondition, "{refused}");
    assert!(refused.to_string().contains("input 0: 2 motion keys where the build had 3"), "{refused}");
    let updated = context.update_accel(&accel, &packed.inputs(&motion_vertices)).unwrap();
    assert_eq!(updated.handle(), accel.handle());
    let fresh = build_geometry(&context, &after, &options).unwrap();
    assert_eq!(updated.info().bounds, fresh.info().bounds);
    let old = build_geometry(&context, &before, &options).unwrap();

    let rays: Vec<Ray> = common::random_rays(4000, seed)
        .into_iter()
        .enumerate()
        .map(|(i, ray)| Ray {
            time: -0.8 + 2.6 * uniform(seed + 9, i as u64),
            mask: 0,
            flags: Default::default(),
            ..ray
        })
        .collect();
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 4, ..Query::closest(RayFormat::Full, HitFormat::Full) };
    for query in [Query::closest(RayFormat::Full, HitFormat::Full), all] {
        let expected = trace(&context, &fresh, &query, &rays);
        assert_eq!(trace(&context, &updated, &query, &rays), expected, "{:?}", query.kind);
        assert_eq!(trace(&context, &accel, &query, &rays), trace(&context, &old, &query, &rays), "the old version");
        assert_ne!(trace(&context, &accel, &query, &rays), expected, "the update changed something");
        assert!(expected.0.iter().filter(|r| r.hit()).count() > rays.len() / 10, "the rays hit");
    }
}
