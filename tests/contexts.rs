//! Contexts: build-input errors through the public API, build options, accel info, random vertex access,
//! memory accounting, determinism across thread counts and chunking, and builds that never block traces.

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use bytes::Bytes;
use common::{icosphere, pack_rays, random_rays, shared_mesh};
use glam::Vec3;
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{BuildInput, TransformInput, TriangleInput};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::raygen::Camera;
use rayd_engine::{AccelHandle, Context, Device, Error, ErrorKind};

#[test]
fn bad_build_input_is_an_invalid_argument_naming_input_field_and_element() {
    let context = Context::new(Device::cpu());
    let good = icosphere(1, Vec3::ZERO).pack();
    let mut bad_indices = good.indices.clone();
    bad_indices[12 * 5 + 4..12 * 5 + 8].copy_from_slice(&9999u32.to_le_bytes());
    let inputs = [
        BuildInput::Triangles(good.input()),
        BuildInput::Triangles(TriangleInput::indexed(&good.vertices, &bad_indices)),
    ];
    let error = context.build_accel(&inputs, &BuildOptions::default()).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::InvalidArgument);
    assert!(
        matches!(error, Error::InvalidBuildInput { input: 1, field: "indices", element: Some(5), .. }),
        "{error:?}"
    );
    assert_eq!(error.to_string(), "build input 1: indices[5]: corner 1 is vertex 9999, beyond the 42 vertices");
    assert_eq!(context.memory_in_use(), 0, "nothing half-built remains");
    assert!(context.accel_handles().is_empty());

    let both = BuildOptions::new(BuildFlags::PREFER_FAST_BUILD | BuildFlags::PREFER_FAST_TRACE);
    let error = context.build_accel(&[BuildInput::Triangles(good.input())], &both).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::InvalidArgument);
    assert!(error.to_string().contains("mutually exclusive"));
    assert!(context.compute_memory_usage(&[BuildInput::Triangles(good.input())], &both).is_err());
    assert!(context.compute_memory_usage(&inputs, &BuildOptions::default()).is_err());
}

#[test]
fn bad_trace_buffers_are_rejected_before_anything_is_written() {
    let context = Context::new(Device::cpu());
    let mesh = icosphere(1, Vec3::ZERO).pack();
    let accel = context.build_accel(&[BuildInput::Triangles(mesh.input())], &BuildOptions::default()).unwrap();
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriid);
    let rays = vec![0u8; 32 * 10];
    let mut hits = vec![7u8; 8 * 10];
    let cases: [(&[u8], usize, usize, &str); 3] =
        [(&rays[..31], 80, 0, "rays"), (&rays, 79, 0, "hits"), (&rays, 80, 4, "counts")];
    for (rays, hit_len, count_len, buffer) in cases {
        let mut counts = vec![0u8; count_len];
        let out = TraceOutput { hits: &mut hits[..hit_len], counts: &mut counts };
        let error = context.trace(&accel, &query, rays, out).unwrap_err();
        assert!(matches!(error, Error::BufferSize { buffer: b, .. } if b == buffer), "{error:?}");
        assert_eq!(error.kind(), ErrorKind::InvalidArgument);
    }
    assert!(hits.iter().all(|&b| b == 7));
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 0, ..query };
    let error = context.trace(&accel, &all, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap_err();
    assert!(matches!(error, Error::InvalidQuery { field: "max_hits_per_ray", .. }));
}

#[test]
fn accels_report_sizes_and_give_vertices_back_only_when_allowed() {
    let context = Context::new(Device::cpu());
    let bunny = shared_mesh("stanford-bunny");
    let packed = bunny.pack();
    let inputs = [BuildInput::Triangles(TriangleInput { primitive_index_offset: 10, ..packed.input() })];
    let options = BuildOptions::new(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS | BuildFlags::ALLOW_COMPACTION);
    let accel = context.build_accel(&inputs, &options).unwrap();
    let info = *accel.info();
    assert_eq!(info.triangle_count, bunny.triangles.len() as u64);
    assert_eq!(info.geometry_count, 1);
    assert!(info.size_bytes > 36 * info.triangle_count);
    assert_eq!(info.compacted_size_bytes, Some(info.size_bytes));
    assert_eq!(context.memory_in_use(), info.size_bytes);
    for prim in [0usize, 1234, bunny.triangles.len() - 1] {
        assert_eq!(accel.triangle_vertices(0, prim as u32 + 10).unwrap(), bunny.corners(prim));
    }
    assert!(accel.triangle_vertices(0, 9).is_err());
    assert!(accel.triangle_vertices(0, bunny.triangles.len() as u32 + 10).is_err());
    assert!(accel.triangle_vertices(1, 10).is_err());

    let plain = context.build_accel(&inputs, &BuildOptions::default()).unwrap();
    assert_eq!(plain.triangle_vertices(0, 10).unwrap_err().kind(), ErrorKind::FailedPrecondition);
    assert_eq!(plain.info().compacted_size_bytes, None);
    assert!(plain.info().size_bytes < info.size_bytes, "random access costs memory");
}

#[test]
fn destroying_frees_memory_and_handles_are_not_found_afterwards() {
    let context = Context::new(Device::cpu());
    let mesh = icosphere(2, Vec3::ZERO).pack();
    let first = context.build_accel(&[BuildInput::Triangles(mesh.input())], &BuildOptions::default()).unwrap();
    let buffer = context.create_buffer(Bytes::from(vec![1u8; 4096]));
    assert_eq!(context.memory_in_use(), first.info().size_bytes + 4096);
    let handle = first.handle();
    drop(first);
    context.destroy_accel(handle).unwrap();
    assert_eq!(context.memory_in_use(), 4096);
    assert_eq!(context.accel(handle).unwrap_err().kind(), ErrorKind::NotFound);
    assert_eq!(context.destroy_accel(handle).unwrap_err().kind(), ErrorKind::NotFound);
    assert_eq!(context.accel(AccelHandle(999)).unwrap_err().to_string(), "accel 999 not found");
    assert_eq!(context.buffer(buffer).unwrap().len(), 4096);
    context.destroy_buffer(buffer).unwrap();
    assert_eq!(context.memory_in_use(), 0);
    assert!(context.buffer(buffer).is_err());
}

#[test]
fn a_trace_holding_an_accel_keeps_it_alive_until_it_finishes() {
    let context = Context::new(Device::cpu());
    let mesh = icosphere(2, Vec3::ZERO).pack();
    let accel = context.build_accel(&[BuildInput::Triangles(mesh.input())], &BuildOptions::default()).unwrap();
    let size = accel.info().size_bytes;
    context.destroy_accel(accel.handle()).unwrap();
    assert_eq!(context.memory_in_use(), size, "still held by this caller");
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let rays = pack_rays(&random_rays(100, 1), RayFormat::OriginDirection);
    let mut hits = vec![0u8; 400];
    context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
    drop(accel);
    assert_eq!(context.memory_in_use(), 0);
}

#[test]
fn results_are_the_same_bytes_whatever_the_thread_count_or_the_split() {
    let context = Context::new(Device::cpu());
    let packed = shared_mesh("stanford-bunny").pack();
    let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let (lo, hi) = shared_mesh("stanford-bunny").bounds();
    let rays = Camera::framing(lo, hi, 160, 120).rays(RayFormat::OriginTminDirectionTmax);
    let query = Query {
        kind: QueryKind::All,
        max_hits_per_ray: 4,
        ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::Full)
    };
    let layout = query.output_layout(rays.len()).unwrap();
    let trace = |threads: usize, rays: &[u8]| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let layout = query.output_layout(rays.len()).unwrap();
        let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
        pool.install(|| context.trace(&accel, &query, rays, TraceOutput { hits: &mut hits, counts: &mut counts }))
            .unwrap();
        (hits, counts)
    };
    let one = trace(1, &rays);
    assert_eq!(one, trace(3, &rays));
    // Split at a ray that is not on a chunk boundary.
    let split = 32 * 1000 + 32 * 7;
    let (head, tail) = (trace(2, &rays[..split]), trace(2, &rays[split..]));
    assert_eq!([head.0, tail.0].concat(), one.0);
    assert_eq!([head.1, tail.1].concat(), one.1);
    assert!(one.1.chunks(4).any(|c| c != [0; 4]), "some rays hit");
    assert_eq!(layout.rays, 160 * 120);
}

#[test]
fn a_cameras_rays_traced_in_tiles_answer_as_in_runs_too_short_for_tiles() {
    let context = Context::new(Device::cpu());
    let packed = shared_mesh("stanford-bunny").pack();
    let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let (lo, hi) = shared_mesh("stanford-bunny").bounds();
    let format = RayFormat::OriginTminDirectionTmax;
    let rays = Camera::framing(lo, hi, 96, 64).rays(format);
    let queries = [
        Query::closest(format, HitFormat::TTriidUV),
        Query { kind: QueryKind::Count, ..Query::closest(format, HitFormat::TTriid) },
        Query { kind: QueryKind::All, max_hits_per_ray: 3, ..Query::closest(format, HitFormat::T) },
        // Which hit an `any` query stops at may depend on the rays traced with it; whether it hits does not.
        Query { kind: QueryKind::Any, ..Query::closest(format, HitFormat::Bitmask) },
    ];
    let trace = |query: &Query, rays: &[u8]| {
        let layout = query.output_layout(rays.len()).unwrap();
        let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
        context.trace(&accel, query, rays, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
        (hits, counts)
    };
    for query in &queries {
        // From a row's start, and from the middle of one (its rays before the first whole row are not tiled; a
        // bitmask's chunks then keep to bytes and the rows go unused).
        for first in [0, 96 * 5 + 37] {
            let rays = &rays[first * format.size()..];
            let rows = rayd_engine::query::batch_chunks(query, rays).0;
            let tiled = query.hit_format != HitFormat::Bitmask || first == 0;
            assert_eq!(rows.map(|r| r.width), tiled.then_some(96), "{:?} from {first}", query.kind);
            // Each ray's hit records (a bitmask's bit), and its count.
            let per_ray = |(hits, counts): (Vec<u8>, Vec<u8>), rays: usize| -> Vec<(Vec<u8>, Vec<u8>)> {
                let records = query.records_per_ray();
                (0..rays)
                    .map(|i| {
                        let hit = match query.hit_format.size() {
                            None => vec![hits[i / 8] >> (i % 8) & 1],
                            Some(size) => hits[i * records * size..(i + 1) * records * size].to_vec(),
                        };
                        (hit, counts.get(4 * i..4 * i + 4).unwrap_or_default().to_vec())
                    })
                    .collect()
            };
            let size = format.size();
            let in_runs: Vec<_> =
                rays.chunks(7 * size).flat_map(|run| per_ray(trace(query, run), run.len() / size)).collect();
            let whole = per_ray(trace(query, rays), rays.len() / size);
            assert!(whole == in_runs, "{:?} from {first}", query.kind);
        }
    }
}

#[test]
fn building_an_accel_never_blocks_traces_on_another() {
    let context = Arc::new(Context::new(Device::cpu()));
    let small = icosphere(3, Vec3::ZERO).pack();
    let accel = context.build_accel(&[BuildInput::Triangles(small.input())], &BuildOptions::default()).unwrap();
    let meshes: Vec<Mesh> = ["stanford-bunny", "ogre", "nefertiti"].map(shared_mesh).into();
    let big = Mesh::tiled(&meshes, 1_500_000).pack();
    let building = Arc::new(AtomicBool::new(true));
    let traces_during_build = Arc::new(AtomicUsize::new(0));
    let builder = {
        let (context, building) = (Arc::clone(&context), Arc::clone(&building));
        std::thread::spawn(move || {
            let result = context.build_accel(&[BuildInput::Triangles(big.input())], &BuildOptions::default());
            building.store(false, Ordering::SeqCst);
            result.map(|a| a.info().triangle_count)
        })
    };
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let rays = pack_rays(&random_rays(64, 3), RayFormat::OriginDirection);
    let mut hits = vec![0u8; 64 * 4];
    while building.load(Ordering::SeqCst) {
        context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
        if building.load(Ordering::SeqCst) {
            traces_during_build.fetch_add(1, Ordering::SeqCst);
        }
    }
    assert!(builder.join().unwrap().unwrap() >= 1_500_000);
    assert!(traces_during_build.load(Ordering::SeqCst) > 0, "no trace completed while the big build ran");
}

/// Hits of the bunny's camera rays on `accel`.
fn camera_hits(context: &Context, accel: &rayd_engine::Accel, mesh: &Mesh) -> Vec<u8> {
    let (lo, hi) = mesh.bounds();
    let rays = Camera::framing(lo, hi, 64, 48).rays(RayFormat::OriginDirection);
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriidUV);
    let mut hits = vec![0u8; query.output_layout(rays.len()).unwrap().hits];
    context.trace(accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
    hits
}

#[test]
fn copies_and_compacted_copies_trace_as_the_source_within_the_reported_size() {
    let context = Context::new(Device::cpu());
    let other = Context::new(Device::cpu());
    let mesh = shared_mesh("stanford-bunny");
    let packed = mesh.pack();
    let input = [BuildInput::Triangles(packed.input())];
    let compactable = context.build_accel(&input, &BuildOptions::new(BuildFlags::ALLOW_COMPACTION)).unwrap();
    let compacted_size = compactable.info().compacted_size_bytes.expect("reported with ALLOW_COMPACTION");
    assert!(compacted_size <= compactable.info().size_bytes);
    let compacted = other.copy_accel(&compactable, true).unwrap();
    assert!(compacted.info().size_bytes <= compacted_size, "{} > {compacted_size}", compacted.info().size_bytes);
    assert_eq!(other.memory_in_use(), compacted.info().size_bytes, "the copy is charged to the context it is in");
    let expected = camera_hits(&context, &compactable, &mesh);
    assert!(expected.chunks_exact(16).any(|h| f32::from_le_bytes(h[..4].try_into().unwrap()) >= 0.0));
    assert_eq!(camera_hits(&other, &compacted, &mesh), expected, "the compacted copy traces the same");
    assert_eq!(
        (compacted.info().options, compacted.info().triangle_count),
        (compactable.info().options, compactable.info().triangle_count)
    );
    context.destroy_accel(compactable.handle()).unwrap();
    assert_eq!(camera_hits(&other, &compacted, &mesh), expected, "a copy does not depend on its source");

    let plain = context.build_accel(&input, &BuildOptions::default()).unwrap();
    assert_eq!(plain.info().compacted_size_bytes, None);
    let error = context.copy_accel(&plain, true).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition);
    assert_eq!(camera_hits(&context, &context.copy_accel(&plain, false).unwrap(), &mesh), expected);
}

#[test]
fn transforms_can_always_be_updated_and_compacted_and_say_so() {
    let context = Context::new(Device::cpu());
    let mesh = shared_mesh("stanford-bunny");
    let packed = mesh.pack();
    let child = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let identity = [1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0.];
    let placed = context.build_transform(&TransformInput::Static(identity), &child).unwrap();
    let flags = placed.info().options.flags;
    assert!(flags.contains(BuildFlags::ALLOW_UPDATE | BuildFlags::ALLOW_COMPACTION), "{flags:?}");
    let compacted = context.copy_accel(&placed, true).unwrap();
    assert!(compacted.info().size_bytes <= placed.info().compacted_size_bytes.expect("reported"));
    let expected = camera_hits(&context, &child, &mesh);
    assert_eq!(camera_hits(&context, &compacted, &mesh), expected, "the compacted copy places the child as it was");
    let moved = [1., 0., 0., 5., 0., 1., 0., 0., 0., 0., 1., 0.];
    let updated = context.update_transform(&placed, &TransformInput::Static(moved), &child).unwrap();
    assert_ne!(camera_hits(&context, &updated, &mesh), expected, "the update moved the child out of view");
}

#[test]
fn a_build_told_not_to_go_on_stops_between_its_phases_and_keeps_nothing() {
    let packed = icosphere(3, Vec3::ZERO).pack();
    let inputs = [BuildInput::Triangles(packed.input())];
    let options = BuildOptions::default();
    let rays = pack_rays(&random_rays(256, 5), RayFormat::OriginTminDirectionTmax);
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    let hits = |context: &Context, accel| {
        let mut out = vec![0u8; query.output_layout(rays.len()).unwrap().hits];
        context.trace(accel, &query, &rays, TraceOutput { hits: &mut out, counts: &mut [] }).unwrap();
        out
    };
    // Told to go on, it asks three times and builds what build_accel builds.
    let context = Context::new(Device::cpu());
    let asked = AtomicUsize::new(0);
    let go_on = || {
        asked.fetch_add(1, Ordering::SeqCst);
        true
    };
    let built = context.build_accel_while(&inputs, &options, &go_on).unwrap();
    let plain = context.build_accel(&inputs, &options).unwrap();
    assert_eq!(asked.load(Ordering::SeqCst), 3, "one question before each phase after the boxes");
    assert_eq!(built.info().size_bytes, plain.info().size_bytes);
    assert_eq!(hits(&context, &built), hits(&context, &plain));
    // Told no at any of its questions, it stops there: no accel is kept and no memory is left in use.
    for stop_at in 1..=3 {
        let context = Context::new(Device::cpu());
        let asked = AtomicUsize::new(0);
        let go_on = || asked.fetch_add(1, Ordering::SeqCst) + 1 < stop_at;
        let stopped = context.build_accel_while(&inputs, &options, &go_on).unwrap_err();
        assert_eq!(stopped, Error::Stopped, "stopped at question {stop_at}");
        assert_eq!(stopped.kind(), ErrorKind::FailedPrecondition);
        assert_eq!(asked.load(Ordering::SeqCst), stop_at, "no question after the answer no");
        assert!(context.accel_handles().is_empty() && context.memory_in_use() == 0, "stopped at {stop_at}");
    }
}
