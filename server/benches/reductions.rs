//! Rays made and hits reduced on the server: a 4-megapixel camera render of the bunny through `rayd` over
//! loopback, with every hit returned (plain, gRPC zstd, compact encoding) and with reductions (depth and normal
//! images, counts), one call at a time and several in flight (rounds of calls, and a flow of calls each started as
//! another ends), against the engine in-process. Prints one table with rays/s, two shares — of the engine's rate
//! tracing the same rays made beforehand ("% engine"), and of the engine's rate doing the very same generated (and
//! reduced) trace in-process ("% same i-p", the rate of the work rayd wraps), both in-process traces timed between
//! the row's own calls so that a share compares runs of the same few seconds — and the bytes a ray puts on the wire
//! (and what zstd/gzip would make of them). Run with `cargo bench -p rayd-server --bench reductions`;
//! `RAYD_BENCH_DEVICE=wgpu:0` measures on a GPU device instead of `cpu:0` (the in-process rows then trace on that
//! device too, and the kernel time of the rays-sent trace is printed below it). With `RUST_LOG` set (e.g.
//! `RUST_LOG=rayd_engine=debug`), the engine's and the server's logs go to stderr: the wgpu backend logs each
//! trace's kernel, submitting and finishing time at debug level.

use std::time::Instant;

use bytes::Bytes;
use rayd_client::{Client, ClientOptions};
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::backend::RaySource;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::BuildInput;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, TraceOutput};
use rayd_engine::raygen::{Camera, Generator, PixelSampling};
use rayd_engine::reduce::{Image, ImageChannel, PixelEncoding, Reduction};
use rayd_engine::{Context, Device};
use tonic::codec::CompressionEncoding;
use tracing_subscriber::EnvFilter;

#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Pixels a side: 2048² ≈ 4.2 M rays.
const SIDE: u32 = 2048;
/// Timed runs of each row (after one warm-up); the median is reported.
const RUNS: usize = 5;
/// Calls in flight at once in the concurrent rows.
const IN_FLIGHT: usize = 4;
/// Calls of a flow row, `IN_FLIGHT` of them at a time.
const FLOW_CALLS: usize = 16;

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// What a row measured: medians over `RUNS` rounds of seconds a call through rayd, and of the in-process traces run
/// between its calls; and the bytes the last call returned.
struct Timings {
    /// Seconds a call through rayd.
    call: f64,
    /// Seconds the engine takes in-process with the rays made beforehand (the reference of "% engine").
    engine: f64,
    /// Seconds the same work takes in-process (the reference of "% same i-p").
    same: f64,
    /// The last call's reply.
    last: Bytes,
}

/// Times `call` (a call through rayd) after a warm-up, `RUNS` rounds, each also timing `in_process` (seconds of the
/// engine's trace of the rays made beforehand, and of the same work in-process) right after the call: a row's shares
/// compare runs of the same few seconds, not of the bench's start (this machine's rate drifts by ±10% over a run).
async fn interleaved<F: std::future::Future<Output = Bytes>>(
    mut call: impl FnMut() -> F,
    mut in_process: impl FnMut() -> (f64, f64),
) -> Timings {
    let mut last = call().await;
    let (mut calls, mut engine, mut same) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..RUNS {
        let start = Instant::now();
        last = call().await;
        calls.push(start.elapsed().as_secs_f64());
        let (engine_seconds, same_seconds) = in_process();
        engine.push(engine_seconds);
        same.push(same_seconds);
    }
    Timings { call: median(calls), engine: median(engine), same: median(same), last }
}

/// Bytes of `data` compressed as gRPC would with zstd (level 3, tonic's default) and gzip (level 6).
fn compressed(data: &[u8]) -> (usize, usize) {
    use std::io::Write;
    let zstd = zstd::bulk::compress(data, 3).expect("zstd").len();
    let mut gzip = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::new(6));
    gzip.write_all(data).expect("gzip");
    (zstd, gzip.finish().expect("gzip").len())
}

fn main() {
    if std::env::var_os("RUST_LOG").is_some() {
        tracing_subscriber::fmt().with_env_filter(EnvFilter::from_default_env()).with_writer(std::io::stderr).init();
    }
    let meshes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/meshes");
    let bunny = Mesh::load_obj(meshes.join("stanford-bunny.obj")).expect("the shared bunny");
    let (lo, hi) = bunny.bounds();
    let camera = Camera::framing(lo, hi, SIDE, SIDE);
    let generator = Generator::Pinhole(camera, PixelSampling { samples: 1, jitter_seed: None });
    let rays_per_call = generator.count() as f64;
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriidUV);

    // In-process: the engine alone on the same rays, made beforehand, into a reused hit buffer.
    let device_id = std::env::var("RAYD_BENCH_DEVICE").unwrap_or_else(|_| "cpu:0".into());
    let device =
        Device::all().into_iter().find(|d| d.info().id == device_id).expect("the device RAYD_BENCH_DEVICE names");
    let context = Context::new(device);
    let packed = bunny.pack();
    let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let rays = generator.rays(query.ray_format);
    let hits = std::sync::Mutex::new(vec![0u8; rays.len() / query.ray_format.size() * 16]);
    // Seconds (and kernel seconds, on a GPU) of the engine tracing the rays made beforehand.
    let trace_sent = || {
        let mut hits = hits.lock().unwrap();
        let start = Instant::now();
        let stats = context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
        (start.elapsed().as_secs_f64(), stats.device_nanos as f64 * 1e-9)
    };
    let engine_seconds = || trace_sent().0;
    let (engine, kernel): (Vec<f64>, Vec<f64>) = (0..RUNS).map(|_| trace_sent()).unzip();
    let (engine, kernel) = (median(engine), median(kernel));
    let all_rays = RaySource::Generated { generator: &generator, first: 0, count: generator.count() as usize };
    // Seconds of the same generated trace in-process, every hit returned.
    let generated_every_hit = || {
        let mut hits = hits.lock().unwrap();
        let start = Instant::now();
        context.trace_source(&accel, &query, all_rays, TraceOutput { hits: &mut hits, counts: &mut [] }).unwrap();
        start.elapsed().as_secs_f64()
    };
    // Seconds of the same generated trace in-process, the hits reduced where they are traced (on a GPU: in the
    // kernel): what each reduced row through rayd does, without the service around it.
    let generated_reduced = |reduction: &Reduction| {
        let start = Instant::now();
        let (partial, _) = context.trace_reduced(&accel, &query, all_rays, 0, reduction).unwrap();
        reduction.finish(partial, generator.count()).unwrap();
        start.elapsed().as_secs_f64()
    };
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        tokio::spawn(rayd_server::run(rayd_server::Config::default(), listener, None, std::future::pending()));
        let client = Client::connect(&url, ClientOptions::default()).await.unwrap();
        client.build_mesh("bunny", &bunny, &device_id, BuildFlags::empty()).await.unwrap();
        let zstd_options = ClientOptions { compression: Some(CompressionEncoding::Zstd), ..ClientOptions::default() };
        let zstd_client = Client::connect(&url, zstd_options).await.unwrap();

        let mrays = |seconds: f64| rays_per_call / seconds / 1e6;
        println!(
            "bunny, {SIDE}×{SIDE} camera ({} rays), closest, on {device_id}, {} CPU threads",
            rays_per_call,
            rayon::current_num_threads()
        );
        println!(
            "{:<64} {:>9} {:>8} {:>10} {:>9} {:>9} {:>9}",
            "", "Mrays/s", "% engine", "% same i-p", "B/ray", "zstd B/r", "gzip B/r"
        );
        println!(
            "{:<64} {:>9.2} {:>8.1}",
            "engine in-process (rays made beforehand), t_triid_u_v",
            mrays(engine),
            100.0
        );
        if kernel > 0.0 {
            let what = "  of which the kernel (GPU timestamps)";
            println!("{what:<64} {:>9.2} {:>8.1}", mrays(kernel), 100.0 * engine / kernel);
        }
        // A row through rayd: its rate, its share of the engine's rate with rays sent and of the same generated
        // (and reduced) trace in-process, both timed between its calls, and the bytes of its reply.
        let row = |what: &str, timings: &Timings| {
            let (zstd, gzip) = compressed(&timings.last);
            let per_ray = |bytes: usize| bytes as f64 / rays_per_call;
            println!(
                "{what:<64} {:>9.2} {:>8.1} {:>10.1} {:>9.2} {:>9.2} {:>9.2}",
                mrays(timings.call),
                100.0 * timings.engine / timings.call,
                100.0 * timings.same / timings.call,
                per_ray(timings.last.len()),
                per_ray(zstd),
                per_ray(gzip)
            );
        };
        // An in-process rate and its share of the engine's, both timed in the same rounds.
        let in_process_row = |what: &str, timings: &Timings| {
            println!("{what:<64} {:>9.2} {:>8.1}", mrays(timings.same), 100.0 * timings.engine / timings.same);
        };
        let every_hit = || (engine_seconds(), generated_every_hit());

        let full = interleaved(
            || async { client.trace_generated("bunny", &query, &generator).await.unwrap().hits().clone() },
            every_hit,
        )
        .await;
        assert_eq!(full.last.len(), rays.len() / query.ray_format.size() * 16, "every hit");
        in_process_row("  the same in-process: generated, every hit", &full);
        row("generated, every hit t_triid_u_v", &full);
        let zstd = interleaved(
            || async { zstd_client.trace_generated("bunny", &query, &generator).await.unwrap().hits().clone() },
            every_hit,
        )
        .await;
        row("generated, every hit t_triid_u_v, gRPC zstd", &Timings { last: full.last.clone(), ..zstd });

        let (near, far) = (0.0, (hi - lo).length() * 4.0);
        let reductions = [
            ("generated, compact hits (t_triid_u_v)", Reduction::CompactHits { t_far: far }),
            ("generated, depth image float32", image(ImageChannel::Depth, PixelEncoding::Float32, near, far)),
            ("generated, depth image 16-bit PNG", image(ImageChannel::Depth, PixelEncoding::Png, near, far)),
            ("generated, normal image unorm16", image(ImageChannel::Normal, PixelEncoding::Unorm16, near, far)),
            ("generated, hit counts", Reduction::Counts),
        ];
        for (what, reduction) in reductions {
            let (trace_seconds, kernel_seconds) =
                (std::sync::Mutex::new(Vec::new()), std::sync::Mutex::new(Vec::new()));
            let timings = interleaved(
                || async {
                    let reduced =
                        client.trace_generated_reduced("bunny", &query, &generator, &reduction).await.unwrap();
                    trace_seconds.lock().unwrap().push(reduced.stats.trace_ns as f64 * 1e-9);
                    kernel_seconds.lock().unwrap().push(reduced.stats.device_ns as f64 * 1e-9);
                    reduced.data
                },
                || (engine_seconds(), generated_reduced(&reduction)),
            )
            .await;
            row(what, &timings);
            in_process_row("  the same in-process", &timings);
            let trace = median(trace_seconds.into_inner().unwrap());
            let what = "  of which the server's trace";
            println!("{what:<64} {:>9.2} {:>8.1}", mrays(trace), 100.0 * timings.engine / trace);
            let kernel = median(kernel_seconds.into_inner().unwrap());
            if kernel > 0.0 {
                let what = "  of which the device's kernels (GPU timestamps)";
                println!("{what:<64} {:>9.2} {:>8.1}", mrays(kernel), 100.0 * timings.engine / kernel);
            }
        }

        // Several callers at once keep the device busy (a GPU idling between calls lowers its clock); over one
        // connection, and over one connection a call (whose replies are then copied on several cores at once). A
        // round of calls started together and awaited together; and a flow of calls, a new one started as each ends,
        // as a caller rendering frame after frame keeps the device fed.
        let spread_options = ClientOptions { connections: IN_FLIGHT, ..ClientOptions::default() };
        let spread_client = Client::connect(&url, spread_options).await.unwrap();
        let depth = image(ImageChannel::Depth, PixelEncoding::Float32, near, far);
        let concurrent = [
            ("depth image float32, 4 calls at once", &client, depth.clone(), IN_FLIGHT),
            ("hit counts, 4 calls at once", &client, Reduction::Counts, IN_FLIGHT),
            ("depth image float32, 4 calls at once, 4 connections", &spread_client, depth.clone(), IN_FLIGHT),
            ("hit counts, 4 calls at once, 4 connections", &spread_client, Reduction::Counts, IN_FLIGHT),
            ("depth image float32, 16 calls 4 in flight, 4 connections", &spread_client, depth, FLOW_CALLS),
            ("hit counts, 16 calls 4 in flight, 4 connections", &spread_client, Reduction::Counts, FLOW_CALLS),
        ];
        for (what, client, reduction, calls) in concurrent {
            let kernel_seconds = std::sync::Mutex::new(Vec::new());
            let timings = interleaved(
                || async {
                    let call = || {
                        let (client, generator, reduction) = (client.clone(), generator.clone(), reduction.clone());
                        async move { client.trace_generated_reduced("bunny", &query, &generator, &reduction).await }
                    };
                    let mut in_flight: tokio::task::JoinSet<_> = (0..IN_FLIGHT).map(|_| call()).collect();
                    let (mut started, mut last) = (IN_FLIGHT, Bytes::new());
                    while let Some(ended) = in_flight.join_next().await {
                        let reduced = ended.unwrap().unwrap();
                        kernel_seconds.lock().unwrap().push(reduced.stats.device_ns as f64 * 1e-9);
                        last = reduced.data;
                        if started < calls {
                            in_flight.spawn(call());
                            started += 1;
                        }
                    }
                    last
                },
                || (engine_seconds(), generated_reduced(&reduction)),
            )
            .await;
            let engine = timings.engine;
            row(&format!("generated, {what}"), &Timings { call: timings.call / calls as f64, ..timings });
            // The kernels of the calls in flight together: where the device is busy all the time, their rate is the
            // end-to-end rate.
            let kernel = median(kernel_seconds.into_inner().unwrap());
            if kernel > 0.0 {
                let what = "  of which the device's kernels (GPU timestamps)";
                println!("{what:<64} {:>9.2} {:>8.1}", mrays(kernel), 100.0 * engine / kernel);
            }
        }
    });
}

/// An image reduction of one ray a pixel, `SIDE` wide.
fn image(channel: ImageChannel, encoding: PixelEncoding, near: f32, far: f32) -> Reduction {
    Reduction::Image(Image { width: SIDE, rays_per_pixel: 1, channel, encoding, near, far })
}
