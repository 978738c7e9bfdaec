//! What the service costs over the engine: 1M-ray batches traced in-process and through `rayd` over loopback (in
//! one `TraceBatch`, and streamed in chunks by `rayd-client`), the same rays made by the server from a camera
//! generator (only hits cross the wire), and the round-trip latency of a 1-ray trace. Each row also gives the CPU
//! time of the process per batch: client and server share the cores, so what the transport costs in CPU is what
//! tracing cannot use. Prints one table; run with `cargo bench -p rayd-server --bench overhead`. The server runs in
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
/// Chunk size of the streamed row: rays of one chunk are traced while the next are received.
const STREAM_CHUNK_BYTES: usize = 2 << 20;
/// 1-ray calls timed for the latency percentiles (after as many warm-up calls).
const LATENCY_CALLS: usize = 3000;

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// CPU time this process has used so far (all threads, user and system), in seconds.
fn cpu_seconds() -> f64 {
    // SAFETY: getrusage only writes the rusage it is given, which is plain data (all zeros is a valid value).
    let usage = unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_SELF, &mut usage);
        usage
    };
    let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    seconds(usage.ru_utime) + seconds(usage.ru_stime)
}

/// The wall times of timed runs and the CPU time they took together.
#[derive(Default)]
struct Runs {
    /// Wall time of each timed run, seconds.
    walls: Vec<f64>,
    /// CPU seconds of the process over the timed runs.
    cpu: f64,
}

impl Runs {
    /// Records one run that started at `start` (wall) and `cpu_start` (process CPU).
    fn record(&mut self, start: Instant, cpu_start: f64) {
        self.walls.push(start.elapsed().as_secs_f64());
        self.cpu += cpu_seconds() - cpu_start;
    }

    /// Median wall time, seconds.
    fn median(&self) -> f64 {
        median(self.walls.clone())
    }

    /// CPU milliseconds per run (both cores together).
    fn cpu_ms_per_run(&self) -> f64 {
        self.cpu * 1e3 / self.walls.len() as f64
    }
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
    let mut engine = Runs::default();
    for _ in 0..BATCH_RUNS {
        let (start, cpu) = (Instant::now(), cpu_seconds());
        context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
        engine.record(start, cpu);
    }
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

        let mut service = Runs::default();
        let mut server_times = Vec::new();
        for run in 0..=BATCH_RUNS {
            let (start, cpu) = (Instant::now(), cpu_seconds());
            let reply = client.trace_batch(request(rays.clone())).await.unwrap().into_inner();
            if run > 0 {
                service.record(start, cpu);
                server_times.push(reply.stats.unwrap().trace_ns as f64 * 1e-9);
            }
            assert_eq!(reply.hits, engine_hits, "the service returns the engine's bytes");
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
        let mut generated_runs = Runs::default();
        for run in 0..=BATCH_RUNS {
            let (start, cpu) = (Instant::now(), cpu_seconds());
            let reply = client.trace_batch(generated.clone()).await.unwrap().into_inner();
            if run > 0 {
                generated_runs.record(start, cpu);
            }
            assert_eq!(reply.hits, engine_hits, "the generated rays are the camera's");
        }

        // The same rays through rayd-client's TraceStream: chunks pipelined, so receiving, tracing and answering
        // overlap.
        let options = rayd_client::ClientOptions {
            batch_limit_bytes: STREAM_CHUNK_BYTES,
            stream_chunk_bytes: STREAM_CHUNK_BYTES,
            ..Default::default()
        };
        let streaming = rayd_client::Client::connect(&format!("http://{address}"), options).await.unwrap();
        let mut streamed = Runs::default();
        for run in 0..=BATCH_RUNS {
            let (start, cpu) = (Instant::now(), cpu_seconds());
            let result = streaming.trace("bunny", &query, rays.clone()).await.unwrap();
            if run > 0 {
                streamed.record(start, cpu);
            }
            assert_eq!(result.hits(), &engine_hits, "the stream returns the engine's bytes");
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
        let engine_time = engine.median();
        println!("bunny, {ray_count} camera rays, closest, t_triid_u_v, {} threads", rayon::current_num_threads());
        println!("{:<58} {:>9} {:>10} {:>13} {:>14}", "", "Mrays/s", "ms", "% in-process", "CPU ms/batch");
        let row = |name: &str, runs: &Runs| {
            let time = runs.median();
            println!(
                "{name:<58} {:>9.2} {:>10.1} {:>13.1} {:>14.0}",
                mrays(time),
                time * 1e3,
                100.0 * engine_time / time,
                runs.cpu_ms_per_run()
            );
        };
        row("engine in-process", &engine);
        row("rayd TraceBatch, rays sent", &service);
        row("rayd TraceBatch, rays made by the server (RayGenerator)", &generated_runs);
        row(&format!("rayd TraceStream, rays sent ({} MiB chunks)", STREAM_CHUNK_BYTES >> 20), &streamed);
        println!("tracing inside the rayd TraceBatch call: {:.1} ms (median)", median(server_times) * 1e3);
        println!(
            "1-ray TraceBatch round trip: p50 {:.0} µs, p90 {:.0} µs, p99 {:.0} µs ({LATENCY_CALLS} calls)",
            percentile(&latencies, 0.5).as_secs_f64() * 1e6,
            percentile(&latencies, 0.9).as_secs_f64() * 1e6,
            percentile(&latencies, 0.99).as_secs_f64() * 1e6
        );
    });
}
