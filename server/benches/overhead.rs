//! What the service costs over the engine: 1M-ray batches traced in-process and through `rayd` over loopback,
//! the same rays made by the server from a camera generator (only hits cross the wire), and the round-trip latency
//! of a 1-ray trace. Prints one table; run with `cargo bench -p rayd-server --bench overhead`. The server runs in
//! this process (its own runtime threads), the client talks to it over TCP.

use std::time::{Duration, Instant};

use bytes::Bytes;
use rayd_engine::accel::BuildOptions;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::BuildInput;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, TraceOutput};
use rayd_engine::raygen::{Camera, Generator, PixelSampling};
use rayd_engine::{Context, Device};
use rayd_proto as pb;
use rayd_proto::rayd_client::RaydClient;
use tonic::transport::Channel;

/// mimalloc keeps freed pages for reuse: large ray and hit messages then cost no fresh page faults each call.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Timed repetitions of each large batch; the median is reported.
const BATCH_RUNS: usize = 7;
/// 1-ray calls timed for the latency percentiles (after as many warm-up calls).
const LATENCY_CALLS: usize = 3000;

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let meshes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/meshes");
    let bunny = Mesh::load_obj(meshes.join("stanford-bunny.obj")).expect("the shared bunny");
    let packed = bunny.pack();
    let (lo, hi) = bunny.bounds();
    let rays = Bytes::from(Camera::framing(lo, hi, 1024, 1024).rays(RayFormat::OriginTminDirectionTmax));
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    let ray_count = rays.len() / 32;

    // In-process: the engine alone, writing into a reused hit buffer.
    let context = Context::new(Device::cpu());
    let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let mut hits = vec![0u8; ray_count * 16];
    let engine_times: Vec<f64> = (0..BATCH_RUNS)
        .map(|_| {
            let start = Instant::now();
            context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
            start.elapsed().as_secs_f64()
        })
        .collect();
    let engine_hits = Bytes::from(hits);

    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap();
        tokio::spawn(rayd_server::run(rayd_server::Config::default(), listener, None, std::future::pending()));
        let channel =
            Channel::from_shared(format!("http://{address}")).unwrap().tcp_nodelay(true).connect().await.unwrap();
        let mut client =
            RaydClient::new(channel).max_decoding_message_size(64 << 20).max_encoding_message_size(64 << 20);
        let inline = |bytes: &[u8]| {
            Some(pb::DataSource { source: Some(pb::data_source::Source::Inline(Bytes::copy_from_slice(bytes))) })
        };
        let build = pb::BuildAccelRequest {
            name: "bunny".into(),
            inputs: vec![pb::BuildInput {
                input: Some(pb::build_input::Input::Triangles(pb::TriangleInput {
                    vertices: inline(&packed.vertices),
                    vertex_format: pb::VertexFormat::Float3 as i32,
                    indices: inline(&packed.indices),
                    index_format: pb::IndexFormat::Uint32x3 as i32,
                    ..Default::default()
                })),
            }],
            ..Default::default()
        };
        client.build_accel(build).await.unwrap();
        let trace_query = pb::TraceQuery {
            accel: Some(pb::AccelRef { r#ref: Some(pb::accel_ref::Ref::Name("bunny".into())) }),
            query: pb::QueryType::Closest as i32,
            ray_format: pb::RayFormat::OriginTminDirectionTmax as i32,
            hit_format: pb::HitFormat::TTriidUV as i32,
            ..Default::default()
        };
        let request = |rays: Bytes| pb::TraceBatchRequest {
            query: Some(trace_query.clone()),
            rays: Some(pb::trace_batch_request::Rays::RaysInline(rays)),
            ..Default::default()
        };

        let mut service_times = Vec::new();
        let mut server_times = Vec::new();
        for run in 0..=BATCH_RUNS {
            let start = Instant::now();
            let reply = client.trace_batch(request(rays.clone())).await.unwrap().into_inner();
            let elapsed = start.elapsed().as_secs_f64();
            assert_eq!(reply.hits, engine_hits, "the service returns the engine's bytes");
            if run > 0 {
                service_times.push(elapsed);
                server_times.push(reply.stats.unwrap().trace_ns as f64 * 1e-9);
            }
        }

        // The same camera as a generator: the server makes the rays, only hits cross the wire.
        let camera = Camera::framing(lo, hi, 1024, 1024);
        let generated = pb::TraceBatchRequest {
            query: Some(trace_query.clone()),
            rays: Some(pb::trace_batch_request::Rays::RaysGenerator(rayd_client::convert::generator_to_proto(
                &Generator::Pinhole(camera, PixelSampling { samples: 1, jitter_seed: None }),
            ))),
            ..Default::default()
        };
        let mut generated_times = Vec::new();
        for run in 0..=BATCH_RUNS {
            let start = Instant::now();
            let reply = client.trace_batch(generated.clone()).await.unwrap().into_inner();
            let elapsed = start.elapsed().as_secs_f64();
            assert_eq!(reply.hits, engine_hits, "the generated rays are the camera's");
            if run > 0 {
                generated_times.push(elapsed);
            }
        }

        let one_ray = rays.slice(0..32);
        let mut latencies = Vec::with_capacity(LATENCY_CALLS);
        for call in 0..2 * LATENCY_CALLS {
            let start = Instant::now();
            client.trace_batch(request(one_ray.clone())).await.unwrap();
            if call >= LATENCY_CALLS {
                latencies.push(start.elapsed());
            }
        }
        latencies.sort();

        let mrays = |seconds: f64| ray_count as f64 / seconds / 1e6;
        let (engine, service, server) = (median(engine_times), median(service_times), median(server_times));
        println!("bunny, {ray_count} camera rays, closest, t_triid_u_v, {} threads", rayon::current_num_threads());
        println!("engine in-process        {:8.2} Mrays/s  ({:.1} ms)", mrays(engine), engine * 1e3);
        println!(
            "rayd TraceBatch, loopback {:7.2} Mrays/s  ({:.1} ms end to end, {:.1} ms tracing in the server)",
            mrays(service),
            service * 1e3,
            server * 1e3
        );
        println!("service / in-process      {:7.1} %", 100.0 * engine / service);
        let generated = median(generated_times);
        println!(
            "rayd TraceBatch, rays made by the server (RayGenerator) {:7.2} Mrays/s ({:.1} ms), {:.1} % of in-process",
            mrays(generated),
            generated * 1e3,
            100.0 * engine / generated
        );
        println!(
            "1-ray TraceBatch round trip: p50 {:.0} µs, p90 {:.0} µs, p99 {:.0} µs ({LATENCY_CALLS} calls)",
            percentile(&latencies, 0.5).as_secs_f64() * 1e6,
            percentile(&latencies, 0.9).as_secs_f64() * 1e6,
            percentile(&latencies, 0.99).as_secs_f64() * 1e6
        );
    });
}
