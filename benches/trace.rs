//! Trace throughput (M rays/s): the bunny, the tiled million-triangle scene and the uneven one (the bunny with a
//! floor and slivers: triangles of very uneven sizes), coherent rays (a 1024×1024
//! pinhole camera) and incoherent ones (2^20 random rays in the scene's box), closest and any hit, on one thread
//! and on all of them. Rays `origin_tmin_direction_tmax`, hits `t_triid_u_v`; accels built with default options.
//!
//! Every kernel is checked before it is timed: a sample of closest hits must equal the brute-force oracle's
//! record for record, any-hit must agree with it on which rays hit, hit rates must be plausible, and the run
//! on the bench's own thread configuration must write exactly the bytes of the reference run.
//!
//! `cargo bench --bench trace`; filter with e.g. `cargo bench --bench trace -- trace/bunny/camera`.

mod common;

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, SamplingMode, Throughput, criterion_group, criterion_main};
use rayd_engine::accel::BuildOptions;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{BuildInput, GatheredTriangles, gather};
use rayd_engine::query::{Query, QueryKind, TraceOutput, TraceStats};
use rayd_engine::raygen::{Camera, random_rays, uniform};
use rayd_engine::{Accel, Context, Device, oracle};
use rayon::prelude::*;

use common::{Scene, in_pool, one_thread_pool, scenes, thread_configs};

/// Measurement time of a bench, unless 10 traces take longer.
const MEASUREMENT_TIME: Duration = Duration::from_secs(5);
/// Ray layout of every bench.
const RAY_FORMAT: RayFormat = RayFormat::OriginTminDirectionTmax;
/// Hit layout of every bench.
const HIT_FORMAT: HitFormat = HitFormat::TTriidUV;
/// Camera image side: 1024×1024 = 1,048,576 rays.
const CAMERA_SIDE: u32 = 1024;
/// Random rays: as many as the camera's.
const RANDOM_RAYS: usize = 1 << 20;
/// Seed of the random rays.
const RANDOM_SEED: u64 = 7;
/// Rays of each batch checked against the brute-force oracle: this many spread over the batch, and as many
/// spread over the rays that hit.
const ORACLE_SAMPLE: usize = 128;
/// Seed of the oracle's random sample.
const ORACLE_SEED: u64 = 99;

/// A query of `kind` in the bench formats.
fn query(kind: QueryKind) -> Query {
    Query { kind, ..Query::closest(RAY_FORMAT, HIT_FORMAT) }
}

/// One little-endian f32 or u32 field of a hit record.
fn field(record: &[u8], offset: usize) -> [u8; 4] {
    record[offset..offset + 4].try_into().expect("4 bytes")
}

/// The `t` of a hit record.
fn hit_t(record: &[u8]) -> f32 {
    f32::from_le_bytes(field(record, 0))
}

/// Traces `rays` into a fresh hit buffer with the current pool.
fn trace(context: &Context, accel: &Accel, query: &Query, rays: &[u8]) -> (Vec<u8>, TraceStats) {
    let layout = query.output_layout(rays.len()).expect("valid query");
    let mut hits = vec![0u8; layout.hits];
    let stats =
        context.trace(accel, query, rays, TraceOutput { hits: &mut hits, counts: &mut [] }).expect("trace succeeds");
    (hits, stats)
}

/// A ray batch's reference results (closest and any, traced once on the global pool) after checking them.
struct Reference {
    /// Closest-hit records.
    closest: Vec<u8>,
    /// Any-hit records.
    any: Vec<u8>,
}

impl Reference {
    /// Traces and checks a batch: counts, hit rate within `hit_rate`, a sample against the oracle, any versus
    /// closest. Panics on any disagreement.
    fn checked(
        context: &Context,
        accel: &Accel,
        triangles: &GatheredTriangles,
        label: &str,
        rays: &[u8],
        hit_rate: std::ops::RangeInclusive<f64>,
    ) -> Reference {
        let start = Instant::now();
        let size = HIT_FORMAT.size().expect("byte format");
        let count = rays.len() / RAY_FORMAT.size();
        let (closest, closest_stats) = trace(context, accel, &query(QueryKind::Closest), rays);
        let (any, any_stats) = trace(context, accel, &query(QueryKind::Any), rays);
        for (kind, hits, stats) in [("closest", &closest, &closest_stats), ("any", &any, &any_stats)] {
            assert_eq!(stats.rays, count as u64, "{label} {kind}: rays traced");
            let written = hits.chunks_exact(size).filter(|r| hit_t(r) >= 0.0).count() as u64;
            assert_eq!(written, stats.rays_hit, "{label} {kind}: hit records written versus rays_hit");
            eprintln!(
                "check {label}/{kind}: {} of {count} rays hit ({:.1}%), {:.1} nodes and {:.1} triangle tests a ray",
                stats.rays_hit,
                100.0 * stats.rays_hit as f64 / count as f64,
                stats.nodes_visited as f64 / count as f64,
                stats.triangle_tests as f64 / count as f64,
            );
        }
        let rate = closest_stats.rays_hit as f64 / count as f64;
        assert!(closest_stats.rays_hit > 0, "{label}: no ray hit");
        assert!(hit_rate.contains(&rate), "{label}: implausible hit rate {rate:.3}, expected {hit_rate:?}");
        for (c, a) in closest.chunks_exact(size).zip(any.chunks_exact(size)) {
            assert_eq!(hit_t(c) >= 0.0, hit_t(a) >= 0.0, "{label}: any and closest disagree on whether a ray hits");
            assert!(hit_t(a) < 0.0 || hit_t(a) >= hit_t(c), "{label}: an any hit closer than the closest hit");
        }
        // A sample against the brute-force oracle: rays picked at random, and as many of the rays that the accel
        // says hit, spread evenly over them.
        let mut picked: Vec<usize> =
            (0..ORACLE_SAMPLE as u64).map(|k| (uniform(ORACLE_SEED, k) as f64 * count as f64) as usize).collect();
        let hit_rays: Vec<usize> = (0..count).filter(|&i| hit_t(&closest[i * size..(i + 1) * size]) >= 0.0).collect();
        picked.extend(hit_rays.iter().step_by((hit_rays.len() / ORACLE_SAMPLE).max(1)).take(ORACLE_SAMPLE));
        let ray_size = RAY_FORMAT.size();
        let sample: Vec<u8> = picked.iter().flat_map(|&i| &rays[i * ray_size..(i + 1) * ray_size]).copied().collect();
        let oracle_query = query(QueryKind::Closest);
        let mut expected = vec![0u8; oracle_query.output_layout(sample.len()).expect("valid query").hits];
        // In small pieces, so that the oracle's brute force runs on every thread.
        expected.par_chunks_mut(16 * size).zip(sample.par_chunks(16 * ray_size)).for_each(|(hits, rays)| {
            oracle::trace(triangles, &oracle_query, rays, TraceOutput { hits, counts: &mut [] })
                .expect("oracle trace succeeds");
        });
        let mut oracle_hits = 0;
        for (k, &i) in picked.iter().enumerate() {
            let want = &expected[k * size..(k + 1) * size];
            let got = &closest[i * size..(i + 1) * size];
            assert_eq!(got, want, "{label}: closest hit of ray {i} differs from the oracle's");
            oracle_hits += usize::from(hit_t(want) >= 0.0);
        }
        assert!(oracle_hits > 0, "{label}: no sampled ray hits");
        eprintln!(
            "check {label}: {} sampled rays equal the oracle's closest hits ({oracle_hits} hits); checks took {:.1} s",
            picked.len(),
            start.elapsed().as_secs_f64()
        );
        Reference { closest, any }
    }

    /// The reference records of `kind`.
    fn hits(&self, kind: QueryKind) -> &[u8] {
        match kind {
            QueryKind::Closest => &self.closest,
            QueryKind::Any => &self.any,
            _ => unreachable!("only closest and any are benched"),
        }
    }
}

/// The camera's and the random batch's rays for a scene, with the hit rates accepted for each.
fn ray_batches(scene: &Scene) -> [(&'static str, Vec<u8>, std::ops::RangeInclusive<f64>); 2] {
    let (lo, hi) = scene.mesh.bounds();
    [
        ("camera", Camera::framing(lo, hi, CAMERA_SIDE, CAMERA_SIDE).rays(RAY_FORMAT), 0.05..=0.98),
        ("random", random_rays(lo, hi, RANDOM_RAYS, RANDOM_SEED, RAY_FORMAT), 0.02..=0.98),
    ]
}

/// Every trace bench.
fn trace_benches(c: &mut Criterion) {
    let context = Context::new(Device::cpu());
    let one_thread = one_thread_pool();
    eprintln!("trace: all-threads = {} rayon threads", rayon::current_num_threads());
    let mut start = Instant::now();
    for scene in scenes() {
        let inputs = [BuildInput::Triangles(scene.packed.input())];
        let accel = context.build_accel(&inputs, &BuildOptions::default()).expect("build succeeds");
        let triangles = gather(&inputs, 1).expect("valid inputs");
        eprintln!(
            "trace/{}: {} triangles, accel {} bytes; loaded and built in {:.1} s",
            scene.name,
            scene.triangles(),
            accel.info().size_bytes,
            start.elapsed().as_secs_f64()
        );
        let mut group = c.benchmark_group(format!("trace/{}", scene.name));
        group.sample_size(10).warm_up_time(Duration::from_secs(1)).sampling_mode(SamplingMode::Flat);
        for (batch, rays, hit_rate) in ray_batches(&scene) {
            let label = format!("{}/{batch}", scene.name);
            let reference = Reference::checked(&context, &accel, &triangles, &label, &rays, hit_rate);
            let count = rays.len() / RAY_FORMAT.size();
            group.throughput(Throughput::Elements(count as u64));
            for kind in [QueryKind::Closest, QueryKind::Any] {
                let query = query(kind);
                let mut hits = vec![0u8; query.output_layout(rays.len()).expect("valid query").hits];
                for (threads, pool) in thread_configs(&one_thread) {
                    let id = format!("{batch}/{}/{threads}", kind.name());
                    // The kernel as timed, once, checked against the reference.
                    hits.fill(0xa5);
                    let start = Instant::now();
                    let stats = in_pool(pool, || {
                        context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] })
                    })
                    .expect("trace succeeds");
                    // Room for 10 samples of at least one trace each, however slow the machine.
                    group.measurement_time(MEASUREMENT_TIME.max(start.elapsed() * 12));
                    assert_eq!(stats.rays, count as u64, "{label}/{id}: rays traced");
                    assert!(hits == reference.hits(kind), "{label}/{id}: hits differ from the reference run");
                    group.bench_function(&id, |b| {
                        in_pool(pool, || {
                            b.iter(|| {
                                let out = TraceOutput { hits: &mut hits, counts: &mut [] };
                                black_box(context.trace(&accel, &query, black_box(&rays), out).expect("trace succeeds"))
                            })
                        })
                    });
                }
            }
        }
        group.finish();
        start = Instant::now();
    }
}

criterion_group!(benches, trace_benches);
criterion_main!(benches);
