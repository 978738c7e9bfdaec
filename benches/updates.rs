//! Refit against rebuild on deforming shared meshes, trace speed after a large deformation (refitted against a
//! fresh build), and the compaction ratio of each mesh. Prints one table; run with `cargo bench --bench updates`.
//! Every refitted accel's hits are compared with the fresh build's before its speed is printed.

use std::time::Instant;

use glam::Vec3;
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::BuildInput;
use rayd_engine::mesh::{Mesh, PackedMesh};
use rayd_engine::query::{Query, TraceOutput};
use rayd_engine::raygen::Camera;
use rayd_engine::{Accel, Context, Device};

/// Timed repetitions; the median is reported.
const RUNS: usize = 5;

/// The median seconds of [`RUNS`] calls of `f`.
fn median_seconds(mut f: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..RUNS)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[RUNS / 2]
}

/// `mesh` (unit-sized) twisted about y by `amount` radians per unit of height and stretched by `1 + amount` in y.
fn deformed(mesh: &Mesh, amount: f32) -> Mesh {
    let positions = mesh
        .positions
        .iter()
        .map(|p| {
            let (sin, cos) = (amount * p.y).sin_cos();
            Vec3::new(p.x * cos - p.z * sin, p.y * (1.0 + amount), p.x * sin + p.z * cos)
        })
        .collect();
    Mesh { positions, triangles: mesh.triangles.clone() }
}

/// The build input of a packed mesh.
fn input(packed: &PackedMesh) -> [BuildInput<'_>; 1] {
    [BuildInput::Triangles(packed.input())]
}

/// Seconds a trace of `rays` takes (median), and its hits.
fn trace(context: &Context, accel: &Accel, query: &Query, rays: &[u8]) -> (f64, Vec<u8>) {
    let mut hits = vec![0u8; query.output_layout(rays.len()).unwrap().hits];
    let seconds = median_seconds(|| {
        _ = context.trace(accel, query, rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap()
    });
    (seconds, hits)
}

fn main() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/meshes");
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "obj"))
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    names.sort();
    let context = Context::new(Device::cpu());
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriidUV);
    let updatable = BuildOptions::new(BuildFlags::ALLOW_UPDATE | BuildFlags::ALLOW_COMPACTION);
    println!("{} threads; deformation: twist 1 rad per unit height and stretch 2x in y", rayon::current_num_threads());
    println!("mesh | triangles | rebuild ms | refit ms | speed-up | trace refitted / fresh | compacted / built size");
    for name in names {
        let mesh = Mesh::load_obj(dir.join(format!("{name}.obj"))).unwrap().normalized_at(Vec3::ZERO);
        let (packed, bent) = (mesh.pack(), deformed(&mesh, 1.0).pack());
        let accel = context.build_accel(&input(&packed), &updatable).unwrap();
        let rebuild = median_seconds(|| {
            let fresh = context.build_accel(&input(&bent), &updatable).unwrap();
            context.destroy_accel(fresh.handle()).unwrap();
        });
        // Each refit updates the current version (one an update replaced cannot be updated again).
        let mut refitted = std::sync::Arc::clone(&accel);
        let refit = median_seconds(|| refitted = context.update_accel(&refitted, &input(&bent)).unwrap());
        let fresh = context.build_accel(&input(&bent), &BuildOptions::default()).unwrap();
        let (lo, hi) = fresh.info().bounds;
        let rays = Camera::framing(lo, hi, 1024, 1024).rays(RayFormat::OriginDirection);
        let (refitted_s, refitted_hits) = trace(&context, &refitted, &query, &rays);
        let (fresh_s, fresh_hits) = trace(&context, &fresh, &query, &rays);
        assert!(refitted_hits == fresh_hits, "{name}: the refitted accel must hit as the fresh build does");
        let info = accel.info();
        println!(
            "{name} | {} | {:.1} | {:.2} | {:.1}x | {:.2} | {:.3}",
            mesh.triangles.len(),
            rebuild * 1e3,
            refit * 1e3,
            rebuild / refit,
            fresh_s / refitted_s,
            info.compacted_size_bytes.unwrap() as f64 / info.size_bytes as f64
        );
        for handle in [accel.handle(), fresh.handle()] {
            context.destroy_accel(handle).unwrap();
        }
    }
}
