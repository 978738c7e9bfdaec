//! GPU trace throughput on the first wgpu adapter: the tiled scene of the CPU benches (every shared mesh placed on
//! a grid until at least a million triangles), as one geometry accel and as an instance accel over one geometry
//! accel a mesh; coherent rays (a 1024×1024 pinhole camera) and incoherent ones (2^20 random rays in the scene's
//! box); closest and any hit. Rays `origin_tmin_direction_tmax` (32 bytes), hits `t_triid_u_v` (16 bytes).
//!
//! Each case is checked before it is timed: the GPU's records must agree with the CPU backend's on at least
//! 99.99% of the rays (hit or miss; for closest hit also the primitive and `t` within 1e-4 relative). Then
//! [`RUNS`] traces (after [`WARMUP`] of back-to-back traces) give the kernels' time as the GPU's timestamps measure
//! it (summed over the batch's chunks; median and best), and the trace call's time end to end (median; rays from
//! host memory to hits in host memory: staging copies, transfers, dispatches and readback included). Printed as a
//! Markdown table. The best kernel time is there because a GPU busy only part of the time lowers its clock (an
//! H100 went from 1980 to 345 MHz between traces): the best run is the one at the highest clock.
//!
//! Then the kernel alone, timed as GPU ray tracers are compared (OptiX's figures in `../shared/MEASURED.md` are GPU
//! time a launch over a batch already on the device): 220 launches over the whole million rays, kept on the device,
//! back to back (`Context::time_launches`), the first 200 untimed so that the clock is up; median and best.
//!
//! Then the flat scene's closest hits again with chunks (one dispatch each) of 2^16, 2^18 (the default) and 2^20
//! rays: fewer, larger dispatches against less overlap of copies with tracing.
//!
//! `cargo bench --bench wgpu` (no adapter: a notice and nothing measured).

// The bench uses the shared scenes, not the CPU benches' thread helpers.
#[allow(dead_code)]
mod common;

use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::{Affine3A, Vec3};
use rayd_engine::accel::BuildOptions;
use rayd_engine::backend::wgpu::WgpuOptions;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{BuildInput, Instance, InstanceFlags, Placement};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput, TraceStats};
use rayd_engine::raygen::{Camera, random_rays};
use rayd_engine::{Accel, Context, Device};

use common::{TILED_MIN_TRIANGLES, scenes, tiled_meshes};

/// Timed traces a case.
const RUNS: usize = 20;
/// Untimed back-to-back traces before them, to raise the GPU's clock.
const WARMUP: Duration = Duration::from_millis(500);
/// Ray layout.
const RAY_FORMAT: RayFormat = RayFormat::OriginTminDirectionTmax;
/// Hit layout.
const HIT_FORMAT: HitFormat = HitFormat::TTriidUV;
/// Camera image side: 1024×1024 = 1,048,576 rays.
const CAMERA_SIDE: u32 = 1024;
/// Random rays: as many as the camera's.
const RANDOM_RAYS: usize = 1 << 20;
/// Seed of the random rays (the CPU trace bench's).
const RANDOM_SEED: u64 = 7;

/// One scene built on the CPU (the reference) and on the GPU.
struct Built {
    /// Its name in the table.
    name: String,
    /// Triangles in it.
    triangles: usize,
    /// The CPU's context and accel.
    cpu: (Context, Arc<Accel>),
    /// The GPU's context and accel.
    gpu: (Context, Arc<Accel>),
    /// Seconds the GPU build took (host build and upload).
    gpu_build: f64,
}

/// The placements of [`Mesh::tiled`]: each mesh (scaled to a unit cube at the origin) and where it goes.
fn tiled_placements(meshes: &[Mesh]) -> Vec<(usize, Vec3)> {
    let per_cycle: usize = meshes.iter().map(|m| m.triangles.len()).sum();
    let copies = TILED_MIN_TRIANGLES.div_ceil(per_cycle) * meshes.len();
    let side = (copies as f32).sqrt().ceil() as usize;
    (0..copies)
        .map(|c| (c % meshes.len(), Vec3::new((c % side) as f32 * 1.25, 0.0, (c / side) as f32 * 1.25)))
        .collect()
}

/// The tiled scene as an instance accel in `context`: one geometry accel a mesh, one instance a placement.
fn instanced(context: &Context, meshes: &[Mesh]) -> Arc<Accel> {
    let accels: Vec<Arc<Accel>> = meshes
        .iter()
        .map(|m| {
            let packed = m.normalized_at(Vec3::ZERO).pack();
            context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).expect("builds")
        })
        .collect();
    let instances: Vec<Instance> = tiled_placements(meshes)
        .into_iter()
        .enumerate()
        .map(|(i, (mesh, centre))| Instance {
            transform: Placement::rows(&Affine3A::from_translation(centre)),
            instance_id: i as u32,
            mask: 0xFF,
            flags: InstanceFlags::empty(),
            child: Arc::clone(&accels[mesh]),
        })
        .collect();
    context.build_instance_accel(&instances, &BuildOptions::default()).expect("builds")
}

/// Builds `build` on the CPU and on `device`, timing the GPU's.
fn built(name: String, triangles: usize, device: &Device, build: impl Fn(&Context) -> Arc<Accel>) -> Built {
    let cpu = Context::new(Device::cpu());
    let cpu_accel = build(&cpu);
    let gpu = Context::new(device.clone());
    let start = Instant::now();
    let gpu_accel = build(&gpu);
    Built { name, triangles, cpu: (cpu, cpu_accel), gpu: (gpu, gpu_accel), gpu_build: start.elapsed().as_secs_f64() }
}

/// Traces `rays` into a fresh hit buffer.
fn trace(context: &Context, accel: &Accel, query: &Query, rays: &[u8]) -> (Vec<u8>, TraceStats) {
    let mut hits = vec![0u8; query.output_layout(rays.len()).expect("valid query").hits];
    let stats =
        context.trace(accel, query, rays, TraceOutput { hits: &mut hits, counts: &mut [] }).expect("trace succeeds");
    (hits, stats)
}

/// Rays on which the GPU's records differ from the CPU's (any hit: only hit or miss).
fn differing(kind: QueryKind, cpu: &[u8], gpu: &[u8]) -> usize {
    (0..cpu.len() / 16)
        .filter(|&i| {
            let (c, g) = (HIT_FORMAT.read(cpu, i), HIT_FORMAT.read(gpu, i));
            c.is_hit() != g.is_hit()
                || (kind == QueryKind::Closest
                    && c.is_hit()
                    && (c.prim_id != g.prim_id || (c.t - g.t).abs() > 1e-4 * c.t.abs().max(g.t.abs()).max(1.0)))
        })
        .count()
}

/// The median of `values`.
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Checks and times one case; prints its table row.
fn run(scene: &Built, rays_name: &str, rays: &[u8], kind: QueryKind) {
    let query = Query { kind, ..Query::closest(RAY_FORMAT, HIT_FORMAT) };
    let count = rays.len() / RAY_FORMAT.size();
    let (want, _) = trace(&scene.cpu.0, &scene.cpu.1, &query, rays);
    let (got, stats) = trace(&scene.gpu.0, &scene.gpu.1, &query, rays);
    let wrong = differing(kind, &want, &got);
    assert!(wrong as f64 <= count as f64 * 1e-4, "{}: {wrong} of {count} rays differ", scene.name);
    let warming = Instant::now();
    while warming.elapsed() < WARMUP {
        trace(&scene.gpu.0, &scene.gpu.1, &query, rays);
    }
    let (mut kernel, mut end_to_end) = (Vec::new(), Vec::new());
    for _ in 0..RUNS {
        let start = Instant::now();
        let (_, stats) = trace(&scene.gpu.0, &scene.gpu.1, &query, rays);
        end_to_end.push(start.elapsed().as_secs_f64());
        kernel.push(stats.device_nanos as f64 * 1e-9);
    }
    let best = kernel.iter().copied().fold(f64::INFINITY, f64::min);
    let (kernel, end_to_end) = (median(kernel), median(end_to_end));
    let rate =
        |seconds: f64| if seconds > 0.0 { format!("{:.3}", count as f64 / seconds * 1e-9) } else { "–".into() };
    println!(
        "| {} ({} tris) | {rays_name} | {kind:?} | {:.1}% | {wrong} | {} | {} | {} | {:.2} | {:.2} | {:.0}% | {:.1} | {:.1} |",
        scene.name,
        scene.triangles,
        100.0 * stats.rays_hit as f64 / count as f64,
        rate(kernel),
        rate(best),
        rate(end_to_end),
        kernel * 1e3,
        end_to_end * 1e3,
        100.0 * (1.0 - kernel / end_to_end),
        stats.nodes_visited as f64 / count as f64,
        stats.triangle_tests as f64 / count as f64,
    );
}

/// Launches a kernel-only case makes back to back: the first [`WARMUP_LAUNCHES`] raise the GPU's clock, the rest
/// are timed.
const LAUNCHES: u32 = 220;
/// Untimed launches before the timed ones.
const WARMUP_LAUNCHES: usize = 200;

/// The kernel alone, as GPU ray tracers are compared: launches over the whole batch kept on the device, one after
/// another (`Context::time_launches`), by GPU timestamps; prints the median and best of the timed launches.
fn launches(scene: &Built, rays_name: &str, rays: &[u8], kind: QueryKind) {
    let query = Query { kind, ..Query::closest(RAY_FORMAT, HIT_FORMAT) };
    let times = scene.gpu.0.time_launches(&scene.gpu.1, &query, rays, LAUNCHES).expect("the adapter times launches");
    let seconds: Vec<f64> = times[WARMUP_LAUNCHES..].iter().map(|t| t.as_secs_f64()).collect();
    let best = seconds.iter().copied().fold(f64::INFINITY, f64::min);
    let count = (rays.len() / RAY_FORMAT.size()) as f64;
    let median = median(seconds);
    println!(
        "| {} | {rays_name} | {kind:?} | {:.3} | {:.3} | {:.3} |",
        scene.name,
        count / median * 1e-9,
        count / best * 1e-9,
        median * 1e3
    );
}

/// The first wgpu adapter as a device with `options`.
fn gpu(options: WgpuOptions) -> Option<Device> {
    Device::wgpu(options).into_iter().next()
}

fn main() {
    let Some(device) = gpu(WgpuOptions::default()) else {
        eprintln!("skipped: no wgpu adapter");
        return;
    };
    println!("device: {}; {RUNS} timed traces a case (after {WARMUP:?} of untimed ones)\n", device.info().name);
    let tiled = scenes().into_iter().find(|s| s.name == "tiled").expect("the tiled scene");
    let meshes = tiled_meshes();
    let triangles = tiled.mesh.triangles.len();
    let flat = |context: &Context| {
        context.build_accel(&[BuildInput::Triangles(tiled.packed.input())], &BuildOptions::default()).expect("builds")
    };
    let scenes = [
        built("tiled".into(), triangles, &device, flat),
        built("tiled, instanced".into(), triangles, &device, |context| instanced(context, &meshes)),
    ];
    for scene in &scenes {
        println!("GPU build of {}: {:.2} s (host build and upload)", scene.name, scene.gpu_build);
    }
    let header = "| scene | rays | query | hit rate | rays differing from the CPU | kernel G rays/s | kernel best | \
                  end-to-end G rays/s | kernel ms | end-to-end ms | not in kernels | boxes/ray | triangles/ray |\n\
                  |---|---|---|---|---|---|---|---|---|---|---|---|---|";
    println!("\n{header}");
    let (lo, hi) = tiled.mesh.bounds();
    let batches = [
        ("camera", Camera::framing(lo, hi, CAMERA_SIDE, CAMERA_SIDE).rays(RAY_FORMAT)),
        ("random", random_rays(lo, hi, RANDOM_RAYS, RANDOM_SEED, RAY_FORMAT)),
    ];
    for scene in &scenes {
        for (rays_name, rays) in &batches {
            for kind in [QueryKind::Closest, QueryKind::Any] {
                run(scene, rays_name, rays, kind);
            }
        }
    }
    println!(
        "\nThe kernel alone: {LAUNCHES} launches over the whole batch on the device, back to back; the last {} timed\n\n\
         | scene | rays | query | G rays/s (median) | G rays/s (best) | ms a launch |\n|---|---|---|---|---|---|",
        LAUNCHES as usize - WARMUP_LAUNCHES
    );
    for scene in &scenes {
        for (rays_name, rays) in &batches {
            for kind in [QueryKind::Closest, QueryKind::Any] {
                launches(scene, rays_name, rays, kind);
            }
        }
    }
    println!("\n{header}");
    for shift in [16, 18, 20] {
        let options = WgpuOptions { max_chunk_rays: Some(1 << shift), ..WgpuOptions::default() };
        let device = gpu(options).expect("the adapter is still there");
        let scene = built(format!("tiled, chunks of 2^{shift} rays"), triangles, &device, flat);
        for (rays_name, rays) in &batches {
            run(&scene, rays_name, rays, QueryKind::Closest);
        }
    }
}
