//! Instancing against flattening: instance accels over the shared meshes (each scaled to a unit cube, one
//! geometry accel each) against the same scenes flattened into one triangle soup. Prints one table; run with
//! `cargo bench --bench instances`.
//!
//! - `10k`: 10,000 instances of all eight shared meshes, randomly turned and scaled on a jittered 3D grid. Its
//!   flattened form (about 1.5 billion triangles) does not fit this machine: its memory is the instance scene's
//!   flattened triangle count times the bytes per triangle the `2k` flattened build measured.
//! - `2k`: 2,000 instances of the four smallest meshes, small enough to flatten and build here: both forms are
//!   built and traced, and their hits compared ray by ray before any speed is printed.
//!
//! Rays: 1,048,576 camera rays framing the scene, and as many random rays through its box; closest hit,
//! `t_triid_instid`.

use std::sync::Arc;
use std::time::Instant;

use glam::{Affine3A, Quat, Vec3};
use rayd_engine::accel::BuildOptions;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{BuildInput, Instance, InstanceFlags, Placement};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, TraceOutput};
use rayd_engine::raygen::{Camera, random_rays, uniform};
use rayd_engine::{Accel, Context, Device};

/// Timed repetitions of each trace; the median is reported.
const TRACE_RUNS: usize = 3;

/// The shared meshes, smallest first, each scaled to a unit cube at the origin.
fn shared_meshes() -> Vec<(String, Mesh)> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/meshes");
    let mut meshes: Vec<(String, Mesh)> = std::fs::read_dir(&dir)
        .expect("the shared meshes")
        .map(|entry| entry.expect("a directory entry").path())
        .filter(|path| path.extension().is_some_and(|e| e == "obj"))
        .map(|path| {
            let mesh = Mesh::load_obj(&path).expect("a shared mesh");
            (path.file_stem().unwrap().to_string_lossy().into_owned(), mesh.normalized_at(Vec3::ZERO))
        })
        .collect();
    meshes.sort_by_key(|(_, mesh)| mesh.triangles.len());
    meshes
}

/// Object-to-world placements of `count` instances: a jittered cubic grid 1.5 units apart, random turns,
/// scales from 0.5 to 1.
fn placements(count: usize) -> Vec<Affine3A> {
    let side = (count as f32).cbrt().ceil() as usize;
    (0..count)
        .map(|i| {
            let u = |k: u64| uniform(99, i as u64 * 8 + k);
            let cell = Vec3::new((i % side) as f32, ((i / side) % side) as f32, (i / side / side) as f32);
            let jitter = Vec3::new(u(0), u(1), u(2)) - 0.5;
            let axis = (Vec3::new(u(3), u(4), u(5)) - 0.5).normalize_or(Vec3::Y);
            let turn = Quat::from_axis_angle(axis, u(6) * std::f32::consts::TAU);
            Affine3A::from_scale_rotation_translation(Vec3::splat(0.5 + 0.5 * u(7)), turn, (cell + jitter * 0.4) * 1.5)
        })
        .collect()
}

/// Seconds `f` takes, and its result.
fn timed<T>(f: impl FnOnce() -> T) -> (f64, T) {
    let start = Instant::now();
    let value = f();
    (start.elapsed().as_secs_f64(), value)
}

/// Median seconds of [`TRACE_RUNS`] traces of `rays`, and the hits of the last.
fn trace(context: &Context, accel: &Accel, query: &Query, rays: &[u8]) -> (f64, Vec<u8>) {
    let mut hits = vec![0u8; query.output_layout(rays.len()).unwrap().hits];
    let mut times: Vec<f64> = (0..TRACE_RUNS)
        .map(|_| timed(|| context.trace(accel, query, rays, TraceOutput { hits: &mut hits, counts: &mut [] })).0)
        .collect();
    times.sort_by(f64::total_cmp);
    (times[TRACE_RUNS / 2], hits)
}

/// One scene: its geometry accels and its instance accel.
struct Instanced {
    /// The instance accel.
    scene: Arc<Accel>,
    /// Bytes of the geometry accels and the instance accel.
    bytes: u64,
    /// Triangles the flattened scene has.
    flattened_triangles: u64,
    /// Seconds the instance accel's build took.
    build_s: f64,
}

/// Builds `count` instances of `meshes` (instance `i` places mesh `i % meshes.len()` with `placement[i]`).
fn instanced(context: &Context, meshes: &[(String, Mesh)], placement: &[Affine3A]) -> Instanced {
    let children: Vec<Arc<Accel>> = meshes
        .iter()
        .map(|(_, mesh)| {
            context.build_accel(&[BuildInput::Triangles(mesh.pack().input())], &BuildOptions::default()).unwrap()
        })
        .collect();
    let instances: Vec<Instance> = placement
        .iter()
        .enumerate()
        .map(|(i, &to_world)| Instance {
            transform: Placement::rows(&to_world),
            instance_id: i as u32,
            mask: 0xFF,
            flags: InstanceFlags::empty(),
            child: Arc::clone(&children[i % children.len()]),
        })
        .collect();
    let (build_s, scene) = timed(|| context.build_instance_accel(&instances, &BuildOptions::default()).unwrap());
    let flattened_triangles = (0..placement.len()).map(|i| meshes[i % meshes.len()].1.triangles.len() as u64).sum();
    let bytes = scene.info().size_bytes + children.iter().map(|c| c.info().size_bytes).sum::<u64>();
    Instanced { scene, bytes, flattened_triangles, build_s }
}

/// The scene flattened into one mesh.
fn flattened(meshes: &[(String, Mesh)], placement: &[Affine3A]) -> Mesh {
    let mut flat = Mesh::default();
    for (i, to_world) in placement.iter().enumerate() {
        let mesh = &meshes[i % meshes.len()].1;
        let base = flat.positions.len() as u32;
        flat.positions.extend(mesh.positions.iter().map(|&p| to_world.transform_point3(p)));
        flat.triangles.extend(mesh.triangles.iter().map(|t| t.map(|v| v + base)));
    }
    flat
}

/// Camera rays framing `accel`'s box, and random rays through it.
fn ray_sets(accel: &Accel) -> [(&'static str, Vec<u8>); 2] {
    let (lo, hi) = accel.info().bounds;
    let format = RayFormat::OriginTminDirectionTmax;
    [("camera", Camera::framing(lo, hi, 1024, 1024).rays(format)), ("random", random_rays(lo, hi, 1 << 20, 7, format))]
}

fn main() {
    let context = Context::new(Device::cpu());
    let meshes = shared_meshes();
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidInstid);
    println!(
        "{} threads; meshes: {}",
        rayon::current_num_threads(),
        meshes.iter().map(|(n, m)| format!("{n} {}", m.triangles.len())).collect::<Vec<_>>().join(", ")
    );

    // 2k: both forms, hits compared.
    let small = &meshes[..4];
    let placement = placements(2000);
    let scene = instanced(&context, small, &placement);
    let flat = flattened(small, &placement);
    let (flat_build_s, flat_accel) =
        timed(|| context.build_accel(&[BuildInput::Triangles(flat.pack().input())], &BuildOptions::default()).unwrap());
    let flat_bytes = flat_accel.info().size_bytes;
    let bytes_per_flat_triangle = flat_bytes as f64 / scene.flattened_triangles as f64;
    println!(
        "2k: {} instances of {} meshes ({} triangles flattened): instance accel built in {:.1} ms, {:.1} MB with its \
         meshes; flattened built in {:.1} s, {:.1} MB ({:.1}x the memory)",
        placement.len(),
        small.len(),
        scene.flattened_triangles,
        scene.build_s * 1e3,
        scene.bytes as f64 / 1e6,
        flat_build_s,
        flat_bytes as f64 / 1e6,
        flat_bytes as f64 / scene.bytes as f64
    );
    for (name, rays) in ray_sets(&scene.scene) {
        let count = rays.len() / 32;
        let (instanced_s, hits) = trace(&context, &scene.scene, &query, &rays);
        let (flat_s, flat_hits) = trace(&context, &flat_accel, &query, &rays);
        // Instanced: (t, prim within the mesh, instance); flattened: (t, prim of the soup). Compare t and hit or miss.
        let t = |hits: &[u8], r: usize| f32::from_le_bytes(hits[12 * r..12 * r + 4].try_into().unwrap());
        let differing = (0..count)
            .filter(|&r| {
                let (a, b) = (t(&hits, r), t(&flat_hits, r));
                (a >= 0.0) != (b >= 0.0) || (a - b).abs() > 1e-3 * b.abs().max(1.0)
            })
            .count();
        assert!(differing * 1000 <= count, "{differing} of {count} {name} rays differ between the two forms");
        let hit = (0..count).filter(|&r| t(&hits, r) >= 0.0).count();
        println!(
            "2k {name}: instanced {:.2} M rays/s, flattened {:.2} M rays/s, ratio {:.2} ({:.1}% of rays hit; {differing} \
             of {count} differ by more than 1e-3 in t)",
            count as f64 / instanced_s / 1e6,
            count as f64 / flat_s / 1e6,
            flat_s / instanced_s,
            100.0 * hit as f64 / count as f64
        );
    }
    drop((flat, flat_accel));

    // 10k: the instance accel alone; the flattened memory extrapolated from the 2k flattened build.
    let placement = placements(10_000);
    let scene = instanced(&context, &meshes, &placement);
    println!(
        "10k: {} instances of {} meshes ({} triangles flattened): instance accel built in {:.1} ms, {:.1} MB with its \
         meshes; flattened would take about {:.0} GB ({:.0}x)",
        placement.len(),
        meshes.len(),
        scene.flattened_triangles,
        scene.build_s * 1e3,
        scene.bytes as f64 / 1e6,
        scene.flattened_triangles as f64 * bytes_per_flat_triangle / 1e9,
        scene.flattened_triangles as f64 * bytes_per_flat_triangle / scene.bytes as f64
    );
    for (name, rays) in ray_sets(&scene.scene) {
        let count = rays.len() / 32;
        let (seconds, _) = trace(&context, &scene.scene, &query, &rays);
        println!("10k {name}: instanced {:.2} M rays/s", count as f64 / seconds / 1e6);
    }
}
