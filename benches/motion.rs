//! Motion blur: rays/s on moving scenes against the same scenes static, as motion grows. Prints two tables; run
//! with `cargo bench --bench motion`.
//!
//! - Vertex motion: a shared mesh (scaled to a unit cube) with 2 keys over [0, 1], its second key moved by `d`
//!   (a rigid translation along a diagonal, or every vertex by its own pseudo-random offset of length `d`: a
//!   deformation that scatters neighbouring triangles), against its first key built static.
//! - Transform motion: 1,000 instances of a shared mesh on a grid, each under a matrix motion transform (a
//!   translation of length `d`) or an SRT motion transform (a turn of `90·d`° about a pseudo-random axis
//!   through the mesh's centre, for `d` up to 1), placed by a motion instance accel (2 keys) and by a static one, against the
//!   instances at their first key without transforms.
//!
//! Rays: 512×512 camera rays framing the whole moving scene, each at a pseudo-random time in [0, 1] (the static
//! scenes ignore it); closest hit, `t_triid`. The references: the scene static at its first key, and static as it
//! is half-way (t = 0.5), which has the kind of geometry the rays meet on average (a scattered mesh is a cloud of
//! stretched triangles half-way; that cost is the geometry's, not the BVH's). The columns give rays/s (median of
//! 3 runs) and, per ray, the nodes whose boxes were tested and the triangles tested: motion must not degrade
//! traversal to brute force.

use std::sync::Arc;
use std::time::Instant;

use glam::{Affine3A, Quat, Vec3};
use rayd_engine::accel::BuildOptions;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{
    BuildInput, Instance, InstanceFlags, MotionFlags, MotionOptions, Placement, TransformInput, TriangleInput,
};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, TraceOutput, TraceStats};
use rayd_engine::raygen::{Camera, uniform};
use rayd_engine::{Accel, Context, Device};

/// Timed repetitions of each trace; the median is reported.
const RUNS: usize = 3;
/// Image side of the camera rays.
const SIDE: u32 = 512;
/// Motion over [0, 1] with two keys.
const TWO_KEYS: MotionOptions = MotionOptions { keys: 2, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
/// How far things move, in units of a mesh's size.
const DISTANCES: [f32; 5] = [0.01, 0.1, 0.5, 1.0, 4.0];

/// A shared mesh scaled to a unit cube at the origin.
fn shared_mesh(name: &str) -> Mesh {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../shared/data/meshes/{name}.obj"));
    Mesh::load_obj(path).expect("a shared mesh").normalized_at(Vec3::ZERO)
}

/// Camera rays framing `bounds`, each at a pseudo-random time in [0, 1].
fn timed_rays(bounds: (Vec3, Vec3)) -> Vec<u8> {
    let camera = Camera::framing(bounds.0, bounds.1, SIDE, SIDE);
    let format = RayFormat::OriginTminDirectionTmaxTime;
    let mut bytes = vec![0u8; (SIDE * SIDE) as usize * format.size()];
    for (i, slot) in bytes.chunks_exact_mut(format.size()).enumerate() {
        let mut ray = camera.ray(i as u32 % SIDE, i as u32 / SIDE);
        ray.time = uniform(7, i as u64);
        format.encode(&ray, slot);
    }
    bytes
}

/// Rays/s of a trace of `rays` (median of [`RUNS`]) and its statistics.
fn measure(context: &Context, accel: &Accel, rays: &[u8]) -> (f64, TraceStats) {
    let query = Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::TTriid);
    let mut hits = vec![0u8; query.output_layout(rays.len()).unwrap().hits];
    let mut stats = TraceStats::default();
    let mut times: Vec<f64> = (0..RUNS)
        .map(|_| {
            let start = Instant::now();
            stats = context.trace(accel, &query, rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
            start.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    (stats.rays as f64 / times[RUNS / 2], stats)
}

/// One table row: the moving scene against the scene static at its first key and static as it is at t = 0.5.
fn row(label: &str, moving: (f64, TraceStats), first: (f64, TraceStats), middle: (f64, TraceStats)) {
    let three = |n: fn(&TraceStats) -> u64| {
        [&moving.1, &first.1, &middle.1].map(|s| format!("{:.1}", n(s) as f64 / s.rays as f64)).join(" / ")
    };
    println!(
        "{label} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {} | {}",
        moving.0 / 1e6,
        first.0 / 1e6,
        middle.0 / 1e6,
        moving.0 / first.0,
        moving.0 / middle.0,
        three(|s| s.nodes_visited),
        three(|s| s.triangle_tests),
    );
}

/// The vertex-motion table for one mesh.
fn vertex_motion(context: &Context, name: &str) {
    let mesh = shared_mesh(name);
    let packed = mesh.pack();
    let still = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let diagonal = Vec3::ONE.normalize();
    for d in DISTANCES {
        for (kind, offset) in [
            ("translate", &(|_: usize| diagonal) as &dyn Fn(usize) -> Vec3),
            ("scatter", &|v: usize| {
                let u = |k: u64| 2.0 * uniform(11, v as u64 * 4 + k) - 1.0;
                Vec3::new(u(0), u(1), u(2)).normalize_or(Vec3::X)
            }),
        ] {
            let moved = |by: f32| Mesh {
                positions: mesh.positions.iter().enumerate().map(|(v, p)| *p + offset(v) * by).collect(),
                triangles: mesh.triangles.clone(),
            };
            let (second, halfway) = (moved(d).pack(), moved(d * 0.5).pack());
            let middle =
                context.build_accel(&[BuildInput::Triangles(halfway.input())], &BuildOptions::default()).unwrap();
            let keys = [second.vertices.as_slice()];
            let input = TriangleInput { motion_vertices: &keys, ..packed.input() };
            let options = BuildOptions { motion: TWO_KEYS, ..BuildOptions::default() };
            let accel = context.build_accel(&[BuildInput::Triangles(input)], &options).unwrap();
            let rays = timed_rays(accel.info().bounds);
            let label = format!("{name} | {} | {kind} {d}", mesh.triangles.len());
            let [moving, first, half] = [&accel, &still, &middle].map(|a| measure(context, a, &rays));
            row(&label, moving, first, half);
            for done in [accel, middle] {
                context.destroy_accel(done.handle()).unwrap();
            }
        }
    }
    context.destroy_accel(still.handle()).unwrap();
}

/// Instance `i` of a 10×10×10 grid with spacing 2: its translation.
fn grid(i: usize) -> Vec3 {
    Vec3::new((i % 10) as f32, (i / 10 % 10) as f32, (i / 100) as f32) * 2.0
}

/// Instances placing `children` at their grid positions, each moved by `motion(i)` first.
fn instances(children: &[Arc<Accel>], motion: impl Fn(usize) -> Affine3A) -> Vec<Instance> {
    children
        .iter()
        .enumerate()
        .map(|(i, child)| Instance {
            transform: Placement::rows(&(Affine3A::from_translation(grid(i)) * motion(i))),
            instance_id: i as u32,
            mask: 0xFF,
            flags: InstanceFlags::empty(),
            child: Arc::clone(child),
        })
        .collect()
}

/// The transform-motion table.
fn transform_motion(context: &Context, name: &str) {
    let mesh = shared_mesh(name);
    let packed = mesh.pack();
    let geometry = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let copies = vec![Arc::clone(&geometry); 1000];
    let unmoved = instances(&copies, |_| Affine3A::IDENTITY);
    let still = context.build_instance_accel(&unmoved, &BuildOptions::default()).unwrap();
    let identity_srt = [1., 0., 0., 0., 1., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0.];
    for d in DISTANCES {
        for kind in ["matrix translate", "srt turn"] {
            if kind == "srt turn" && d > 1.0 {
                continue;
            }
            // Instance i's motion `f` of the way (the SRT's nlerp turns half-way at f = 0.5).
            let motion = |i: usize, f: f32| {
                let u = |k: u64| 2.0 * uniform(13, i as u64 * 4 + k) - 1.0;
                let direction = Vec3::new(u(0), u(1), u(2)).normalize_or(Vec3::X);
                if kind == "srt turn" {
                    Affine3A::from_quat(Quat::from_axis_angle(direction, (f * d * 90.0).to_radians()))
                } else {
                    Affine3A::from_translation(direction * d * f)
                }
            };
            let transforms: Vec<Arc<Accel>> = (0..1000)
                .map(|i| {
                    let input = if kind == "srt turn" {
                        let mut key = identity_srt;
                        let turn = Quat::from_mat3a(&motion(i, 1.0).matrix3);
                        key[9..13].copy_from_slice(&(if turn.w < 0.0 { -turn } else { turn }).to_array());
                        TransformInput::SrtMotion { keys: vec![identity_srt, key], motion: TWO_KEYS }
                    } else {
                        let keys = vec![Placement::rows(&motion(i, 0.0)), Placement::rows(&motion(i, 1.0))];
                        TransformInput::MatrixMotion { keys, motion: TWO_KEYS }
                    };
                    context.build_transform(&input, &geometry).unwrap()
                })
                .collect();
            let halfway = instances(&copies, |i| motion(i, 0.5));
            let middle = context.build_instance_accel(&halfway, &BuildOptions::default()).unwrap();
            let placed = instances(&transforms, |_| Affine3A::IDENTITY);
            let moving_options = BuildOptions { motion: TWO_KEYS, ..BuildOptions::default() };
            let moving = context.build_instance_accel(&placed, &moving_options).unwrap();
            let flat = context.build_instance_accel(&placed, &BuildOptions::default()).unwrap();
            let rays = timed_rays(moving.info().bounds);
            let label = |accel: &str| format!("{name} ×1000 | {kind} {d} | {accel}");
            let [first, half] = [&still, &middle].map(|a| measure(context, a, &rays));
            row(&label("motion instance accel"), measure(context, &moving, &rays), first, half);
            row(&label("static instance accel"), measure(context, &flat, &rays), first, half);
            for accel in [moving, flat, middle].into_iter().chain(transforms) {
                context.destroy_accel(accel.handle()).unwrap();
            }
        }
    }
}

fn main() {
    let context = Context::new(Device::cpu());
    let threads = rayon::current_num_threads();
    println!("{threads} threads; {SIDE}×{SIDE} camera rays at random times in [0, 1]; closest hit");
    let columns = "moving Mrays/s | static at key 0 | static at t = 0.5 | moving / key 0 | moving / t = 0.5 | \
                   nodes per ray (moving / key 0 / t = 0.5) | triangle tests per ray (same)";
    println!("mesh | triangles | motion (distance in mesh sizes) | {columns}");
    for name in ["stanford-bunny", "nefertiti"] {
        vertex_motion(&context, name);
    }
    println!();
    println!("scene | motion | instance accel | {columns}");
    transform_motion(&context, "spot");
}
