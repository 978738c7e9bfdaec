//! Build throughput (M triangles/s, reported by criterion as Melem/s): the bunny, the tiled million-triangle scene
//! and the uneven one (the bunny with a floor and slivers), with default options, `PREFER_FAST_BUILD` and `PREFER_FAST_TRACE`, on one thread and
//! on all of them.
//!
//! Before timing, each preset is built once on the bench's threads and checked (triangle count, and a small
//! camera's closest hits equal to those of the scene's first build: every preset finds the same closest hits),
//! and a memory report is printed on stderr (lines starting `memory`): the accel's `AccelInfo::size_bytes`,
//! bytes per triangle, and `compute_memory_usage`'s output and temp bounds.
//!
//! `cargo bench --bench build`; filter with e.g. `cargo bench --bench build -- build/bunny`.

mod common;

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, SamplingMode, Throughput, criterion_group, criterion_main};
use rayd_engine::accel::{AccelInfo, BuildFlags, BuildOptions, MemoryUsage};
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::BuildInput;
use rayd_engine::query::{Query, TraceOutput};
use rayd_engine::raygen::Camera;
use rayd_engine::{Accel, Context, Device};

use common::{in_pool, one_thread_pool, scenes, thread_configs};

/// The presets benched, with their names in bench ids.
const PRESETS: [(&str, BuildFlags); 3] = [
    ("default", BuildFlags::empty()),
    ("fast-build", BuildFlags::PREFER_FAST_BUILD),
    ("fast-trace", BuildFlags::PREFER_FAST_TRACE),
];
/// Measurement time of a bench, unless 10 builds take longer.
const MEASUREMENT_TIME: Duration = Duration::from_secs(5);
/// Side of the small camera image that checks each build.
const CHECK_SIDE: u32 = 128;

/// Closest-hit records (t, triangle id, u, v) of `rays` against `accel`.
fn closest_hits(context: &Context, accel: &Accel, rays: &[u8]) -> (Vec<u8>, u64) {
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    let mut hits = vec![0u8; query.output_layout(rays.len()).expect("valid query").hits];
    let stats =
        context.trace(accel, &query, rays, TraceOutput { hits: &mut hits, counts: &mut [] }).expect("trace succeeds");
    (hits, stats.rays_hit)
}

/// `bytes` in MiB.
fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 20) as f64
}

/// Prints the memory figures of a build of `scene` with `preset`.
fn report_memory(scene: &str, preset: &str, triangles: u64, info: &AccelInfo, usage: &MemoryUsage) {
    let per_triangle = |bytes: u64| bytes as f64 / triangles as f64;
    eprintln!(
        "memory {scene}/{preset} ({triangles} triangles): AccelInfo.size_bytes {} ({:.1} MiB, {:.1} B/triangle); \
         compute_memory_usage output_bytes {} ({:.1} MiB, {:.1} B/triangle), temp_bytes {} ({:.1} MiB, \
         {:.1} B/triangle){}",
        info.size_bytes,
        mib(info.size_bytes),
        per_triangle(info.size_bytes),
        usage.output_bytes,
        mib(usage.output_bytes),
        per_triangle(usage.output_bytes),
        usage.temp_bytes,
        mib(usage.temp_bytes),
        per_triangle(usage.temp_bytes),
        if info.size_bytes > usage.output_bytes { " -- WARNING: size exceeds the output bound" } else { "" },
    );
}

/// Every build bench.
fn build_benches(c: &mut Criterion) {
    let context = Context::new(Device::cpu());
    let one_thread = one_thread_pool();
    eprintln!("build: all-threads = {} rayon threads", rayon::current_num_threads());
    for scene in scenes() {
        let triangles = scene.triangles();
        let inputs = [BuildInput::Triangles(scene.packed.input())];
        let (lo, hi) = scene.mesh.bounds();
        let check_rays = Camera::framing(lo, hi, CHECK_SIDE, CHECK_SIDE).rays(RayFormat::OriginTminDirectionTmax);
        let mut reference: Option<Vec<u8>> = None;
        let mut group = c.benchmark_group(format!("build/{}", scene.name));
        group
            .sample_size(10)
            .warm_up_time(Duration::from_secs(1))
            .sampling_mode(SamplingMode::Flat)
            .throughput(Throughput::Elements(triangles));
        for (preset, flags) in PRESETS {
            let options = BuildOptions::new(flags);
            let usage = context.compute_memory_usage(&inputs, &options).expect("memory usage");
            for (threads, pool) in thread_configs(&one_thread) {
                let id = format!("{preset}/{threads}");
                // The build as timed, once: checked, measured for the memory report, and timed to size the bench.
                let start = Instant::now();
                let accel = in_pool(pool, || context.build_accel(&inputs, &options)).expect("build succeeds");
                let elapsed = start.elapsed();
                let info = *accel.info();
                assert_eq!(info.triangle_count, triangles, "build/{}/{id}: triangle count", scene.name);
                let (hits, rays_hit) = closest_hits(&context, &accel, &check_rays);
                assert!(rays_hit > 0, "build/{}/{id}: the check camera sees nothing", scene.name);
                match &reference {
                    None => reference = Some(hits),
                    Some(reference) => {
                        assert!(hits == *reference, "build/{}/{id}: hits differ from the first build's", scene.name)
                    }
                }
                context.destroy_accel(accel.handle()).expect("accel is live");
                drop(accel);
                if pool.is_none() {
                    report_memory(scene.name, preset, triangles, &info, &usage);
                }
                // Room for 10 samples of at least one build each, however slow the machine.
                group.measurement_time(MEASUREMENT_TIME.max(elapsed * 12));
                group.bench_function(&id, |b| {
                    in_pool(pool, || {
                        b.iter(|| {
                            // Destroyed at once, so that the context does not keep every accel built.
                            let accel = context.build_accel(black_box(&inputs), &options).expect("build succeeds");
                            context.destroy_accel(accel.handle()).expect("accel is live");
                            black_box(accel)
                        })
                    })
                });
            }
        }
        group.finish();
    }
}

criterion_group!(benches, build_benches);
criterion_main!(benches);
