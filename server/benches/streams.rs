//! Streams against unary calls, through `rayd-client` and an in-process `rayd` over TCP loopback: 1,000 small
//! traces pipelined on one stream versus 1,000 `TraceBatch` calls one after another, and an upload overlapped with
//! tracing on two streams versus the same work serially on one. Every trace's hits are checked against the engine
//! in this process before anything is reported. Run with `cargo bench -p rayd-server --bench streams`.

use std::time::Instant;

use bytes::Bytes;
use rayd_client::{Client, ClientOptions};
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::BuildInput;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, TraceOutput};
use rayd_engine::raygen::Camera;
use rayd_engine::{Context, Device};

/// The allocator `rayd` itself runs with.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Small traces in each pipelined or unary run.
const SMALL_TRACES: usize = 1000;
/// Timed runs of each measurement; the median is reported.
const RUNS: usize = 5;
/// Bytes uploaded in the overlap measurement.
const UPLOAD_BYTES: usize = 256 << 20;
/// Rays traced (in batches of `OVERLAP_BATCH_RAYS`) in the overlap measurement.
const OVERLAP_BATCHES: usize = 8;
/// Rays per batch of the overlap measurement.
const OVERLAP_BATCH_RAYS: usize = 1 << 17;

/// The median of `values`.
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Seconds `work` takes, median of [`RUNS`] after one warm-up run.
async fn timed<F: std::future::Future<Output = ()>>(mut work: impl FnMut() -> F) -> f64 {
    work().await;
    let mut times = Vec::new();
    for _ in 0..RUNS {
        let start = Instant::now();
        work().await;
        times.push(start.elapsed().as_secs_f64());
    }
    median(times)
}

fn main() {
    let meshes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/meshes");
    let bunny = Mesh::load_obj(meshes.join("stanford-bunny.obj")).expect("the shared bunny");
    let (lo, hi) = bunny.bounds();
    let format = RayFormat::OriginTminDirectionTmax;
    let rays = Bytes::from(Camera::framing(lo, hi, 1024, 1024).rays(format));
    let query = Query::closest(format, HitFormat::TTriidUV);
    let (ray_size, hit_size) = (format.size(), 16);

    // The engine's hits for every ray, to check each answer against.
    let packed = bunny.pack();
    let context = Context::new(Device::cpu());
    let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let mut expected = vec![0u8; rays.len() / ray_size * hit_size];
    context.trace(&accel, &query, &rays, TraceOutput { hits: &mut expected, counts: &mut [] }).unwrap();
    let expected_hits = |first_ray: usize, hits: &[u8]| {
        assert_eq!(hits, &expected[first_ray * hit_size..first_ray * hit_size + hits.len()], "the engine's bytes");
    };

    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        tokio::spawn(rayd_server::run(rayd_server::Config::default(), listener, None, std::future::pending()));
        let client = Client::connect(&url, ClientOptions::default()).await.unwrap();
        client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
        println!("bunny, closest, t_triid_u_v, {} threads, median of {RUNS} runs", rayon::current_num_threads());

        for rays_per_trace in [64usize, 1024] {
            let chunk = |i: usize| rays.slice(i * rays_per_trace * ray_size..(i + 1) * rays_per_trace * ray_size);
            let unary = timed(|| async {
                for i in 0..SMALL_TRACES {
                    let traced = client.trace("bunny", &query, chunk(i)).await.unwrap();
                    expected_hits(i * rays_per_trace, traced.hits());
                }
            })
            .await;
            let pipelined = timed(|| async {
                let stream = client.create_stream().await.unwrap();
                let mut handles = Vec::with_capacity(SMALL_TRACES);
                for i in 0..SMALL_TRACES {
                    handles.push(stream.trace("bunny", &query, chunk(i)).await.unwrap());
                }
                stream.finish().await.unwrap();
                for (i, handle) in handles.iter().enumerate() {
                    expected_hits(i * rays_per_trace, handle.result().unwrap().unwrap().hits());
                }
            })
            .await;
            let mrays = |seconds: f64| (SMALL_TRACES * rays_per_trace) as f64 / seconds / 1e6;
            println!(
                "{SMALL_TRACES} traces of {rays_per_trace} rays: unary TraceBatch {:.1} ms ({:.2} Mrays/s), one stream \
                 {:.1} ms ({:.2} Mrays/s), {:.2}x",
                unary * 1e3,
                mrays(unary),
                pipelined * 1e3,
                mrays(pipelined),
                unary / pipelined
            );
        }

        let upload: Bytes =
            (0..UPLOAD_BYTES).map(|i| (i as u32).wrapping_mul(2_654_435_761).to_le_bytes()[3]).collect();
        let batch = |i: usize| rays.slice(i * OVERLAP_BATCH_RAYS * ray_size..(i + 1) * OVERLAP_BATCH_RAYS * ray_size);
        let check = |handles: &[rayd_client::Operation<rayd_client::TraceResult>]| {
            for (i, handle) in handles.iter().enumerate() {
                expected_hits(i * OVERLAP_BATCH_RAYS, handle.result().unwrap().unwrap().hits());
            }
        };
        let serial = timed(|| async {
            let stream = client.create_stream().await.unwrap();
            let uploaded = stream.upload("", upload.clone()).await.unwrap();
            let mut handles = Vec::new();
            for i in 0..OVERLAP_BATCHES {
                handles.push(stream.trace("bunny", &query, batch(i)).await.unwrap());
            }
            let deleted = stream.delete_buffer(&uploaded).await.unwrap();
            stream.finish().await.unwrap();
            deleted.result().unwrap().unwrap();
            check(&handles);
        })
        .await;
        let overlapped = timed(|| async {
            let (uploading, tracing) = (client.create_stream().await.unwrap(), client.create_stream().await.unwrap());
            let upload_side = async {
                let uploaded = uploading.upload("", upload.clone()).await.unwrap();
                uploading.delete_buffer(&uploaded).await.unwrap();
                uploading.synchronize().await.unwrap();
            };
            let trace_side = async {
                let mut handles = Vec::new();
                for i in 0..OVERLAP_BATCHES {
                    handles.push(tracing.trace("bunny", &query, batch(i)).await.unwrap());
                }
                tracing.synchronize().await.unwrap();
                handles
            };
            let ((), handles) = tokio::join!(upload_side, trace_side);
            check(&handles);
        })
        .await;
        println!(
            "upload {} MiB + trace {} rays: serial on one stream {:.1} ms, two streams {:.1} ms, {:.2}x",
            UPLOAD_BYTES >> 20,
            OVERLAP_BATCHES * OVERLAP_BATCH_RAYS,
            serial * 1e3,
            overlapped * 1e3,
            serial / overlapped
        );
    });
}
