//! Load and soak against the real `rayd` (issue 13, point 3): many clients at once mix builds, batch traces,
//! chunked `TraceStream` traces, `OpenStream` streams, uploads and deletes for a bounded time
//! (`RAYD_SOAK_SECONDS`, 30 by default; an hour by hand). Every answer must be right and every error an expected
//! quota rejection (`max_accels`); latencies (p50/p99 by kind) are printed for RELIABILITY.md, never asserted; and
//! once the load has stopped and its objects are gone, rayd's resident memory must come back to within
//! `RAYD_SOAK_RSS_BOUND_MIB` (64 MiB by default) of what it was after a warm-up round of the same mix.

mod common;
mod daemon;
mod reference;

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use daemon::Daemon;
use rayd_client::{Client, ClientOptions, Error};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::glam::Vec3;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use reference::{Expected, bunny};
use tonic::Code;

/// Clients at once.
const CLIENTS: usize = 8;
/// Accels per tenant: low enough that the builders run into it.
const MAX_ACCELS: usize = 12;

/// An environment variable's number, or `default`.
fn env_or(name: &str, default: u64) -> u64 {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// What one kind of operation did under load.
#[derive(Default)]
struct Tally {
    /// Latency of every success.
    latencies: Vec<Duration>,
    /// Refusals by a quota (RESOURCE_EXHAUSTED), expected.
    refused: u64,
}

/// Every kind's tally, shared by the clients.
type Tallies = Arc<Mutex<BTreeMap<&'static str, Tally>>>;

/// Rays and the engine's answer for them.
struct Workload {
    /// Closest-hit query of every trace.
    query: Query,
    /// A camera's rays on the bunny: 96 × 96, 288 KiB, above the streaming client's batch limit.
    rays: Bytes,
    /// What the engine answers.
    expected: Expected,
    /// A small closed mesh the clients build and destroy.
    sphere: Mesh,
}

impl Workload {
    fn new() -> Workload {
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        let rays = bunny().camera_rays(query.ray_format, 96, 96);
        let expected = bunny().trace(&query, &rays);
        Workload { query, rays: Bytes::from(rays), expected, sphere: common::icosphere(3, Vec3::ZERO) }
    }

    /// Checks a traced answer against the engine's.
    fn check(&self, traced: &rayd_client::TraceResult, what: &str) {
        let stats = traced.stats();
        self.expected.assert_answer(traced.hits(), traced.counts(), (stats.rays, stats.rays_hit), what);
    }
}

/// One client's loop: operation `k` of client `c` is kind `(c + k) % 6`, until `until`.
async fn client_loop(
    batch: Client,
    streaming: Client,
    c: usize,
    until: Instant,
    work: Arc<Workload>,
    tallies: Tallies,
) -> Vec<String> {
    let mut built: Vec<String> = Vec::new();
    let mut k = 0usize;
    while Instant::now() < until {
        let start = Instant::now();
        let (kind, outcome): (&'static str, Result<(), Error>) = match (c + k) % 6 {
            0 => {
                let name = format!("s{c}-{k}");
                let result = batch.build_mesh(&name, &work.sphere, "", BuildFlags::empty()).await;
                if result.is_ok() {
                    built.push(name);
                }
                ("build", result.map(drop))
            }
            1 => (
                "trace_batch",
                batch.trace("bunny", &work.query, work.rays.clone()).await.map(|t| work.check(&t, "batch")),
            ),
            2 => (
                "trace_stream",
                streaming.trace("bunny", &work.query, work.rays.clone()).await.map(|t| work.check(&t, "chunks")),
            ),
            3 => ("open_stream", stream_round(&batch, c, k, &work).await),
            4 => match built.first().cloned() {
                Some(name) => ("destroy", batch.destroy_accel(&name).await.map(|()| drop(built.remove(0)))),
                // Nothing of this client's to destroy: not counted as a destroy that succeeded.
                None => ("destroy_nothing", Ok(())),
            },
            _ => {
                let upload = batch.upload_buffer("", Bytes::from(vec![c as u8; 256 << 10])).await;
                (
                    "upload_delete",
                    match upload {
                        Ok(info) => batch.delete_buffer(&info.id).await,
                        Err(e) => Err(e),
                    },
                )
            }
        };
        let mut tallies = tallies.lock().unwrap();
        let tally = tallies.entry(kind).or_default();
        match outcome {
            Ok(()) => tally.latencies.push(start.elapsed()),
            Err(e) if e.code() == Code::ResourceExhausted && e.to_string().contains("max_accels") => tally.refused += 1,
            Err(e) => panic!("client {c}, operation {k} ({kind}): an unexpected error: {e}"),
        }
        k += 1;
    }
    built
}

/// On one `OpenStream` stream: build a sphere, trace the bunny, destroy the sphere, finish.
async fn stream_round(client: &Client, c: usize, k: usize, work: &Workload) -> Result<(), Error> {
    let stream = client.create_stream().await?;
    let name = format!("t{c}-{k}");
    let build = stream.build_mesh(&name, &work.sphere, "", BuildFlags::empty()).await?;
    let traced = stream.trace("bunny", &work.query, work.rays.clone()).await?;
    let destroyed = stream.destroy_accel(&build).await?;
    stream.finish().await.or_else(|e| if built_refused(&build) { Ok(()) } else { Err(e) })?;
    work.check(&traced.wait().await?, "stream");
    match build.wait().await {
        Ok(_) => destroyed.wait().await,
        Err(e) => Err(e),
    }
}

/// Whether a stream's build was refused by the accel quota (then its destroy fails as its product's dependant).
fn built_refused(build: &rayd_client::Operation<rayd_client::proto::AccelInfo>) -> bool {
    matches!(build.result(), Some(Err(e)) if e.code() == Code::ResourceExhausted)
}

/// The `q` quantile of `latencies` (sorted in place).
fn quantile(latencies: &mut [Duration], q: f64) -> Duration {
    latencies.sort_unstable();
    latencies.get(((latencies.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or_default()
}

/// Runs every client for `seconds` and returns the names of the accels they left behind.
async fn load(daemon: &Daemon, seconds: u64, work: &Arc<Workload>, tallies: &Tallies) -> Vec<(Client, String)> {
    let until = Instant::now() + Duration::from_secs(seconds);
    let streaming_options =
        ClientOptions { batch_limit_bytes: 64 << 10, stream_chunk_bytes: 32 << 10, ..Default::default() };
    let mut tasks = Vec::new();
    for c in 0..CLIENTS {
        let batch = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
        let streaming = Client::connect(&daemon.url(), streaming_options.clone()).await.unwrap();
        let (work, tallies) = (Arc::clone(work), Arc::clone(tallies));
        tasks.push(tokio::spawn(async move {
            let left = client_loop(batch.clone(), streaming, c, until, work, tallies).await;
            left.into_iter().map(|name| (batch.clone(), name)).collect::<Vec<_>>()
        }));
    }
    let mut left = Vec::new();
    for task in tasks {
        left.extend(task.await.expect("a client's loop"));
    }
    left
}

/// Destroys what a load left.
async fn clean_up(left: Vec<(Client, String)>) {
    for (client, name) in left {
        client.destroy_accel(&name).await.unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn many_clients_mixing_every_call_get_right_answers_and_memory_comes_back() {
    let seconds = env_or("RAYD_SOAK_SECONDS", 30);
    let bound = env_or("RAYD_SOAK_RSS_BOUND_MIB", 64) << 20;
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_ACCELS", &MAX_ACCELS.to_string())]);
    let admin = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    admin.build_mesh("bunny", &bunny().mesh, "", BuildFlags::empty()).await.unwrap();
    let work = Arc::new(Workload::new());

    // A warm-up round of the same mix, then the baseline.
    let warm_up: Tallies = Arc::default();
    clean_up(load(&daemon, 3, &work, &warm_up).await).await;
    let baseline = daemon.resident_bytes();

    let tallies: Tallies = Arc::default();
    let start = Instant::now();
    clean_up(load(&daemon, seconds, &work, &tallies).await).await;
    let elapsed = start.elapsed();
    let peak = daemon.resident_bytes();
    let info = admin.server_info().await.unwrap().usage.unwrap();
    assert_eq!((info.accels, info.buffers, info.streams, info.stream_bytes), (1, 0, 0, 0), "only the bunny is left");

    let mut all = Vec::new();
    let mut tallies = std::mem::take(&mut *tallies.lock().unwrap());
    println!("soak: {CLIENTS} clients × 2 connections for {:.1} s", elapsed.as_secs_f64());
    let kinds = ["build", "trace_batch", "trace_stream", "open_stream", "destroy", "upload_delete"];
    assert!(kinds.iter().all(|kind| tallies.contains_key(kind)), "every kind ran: {:?}", tallies.keys());
    for (kind, tally) in tallies.iter_mut().filter(|(kind, _)| **kind != "destroy_nothing") {
        let n = tally.latencies.len();
        all.extend_from_slice(&tally.latencies);
        let (p50, p99) = (quantile(&mut tally.latencies, 0.5), quantile(&mut tally.latencies, 0.99));
        println!("  {kind:<14} {n:>7} ok  {:>5} quota-refused  p50 {p50:>10.2?}  p99 {p99:>10.2?}", tally.refused);
        assert!(n > 0, "{kind}: at least one succeeded");
    }
    let (p50, p99) = (quantile(&mut all, 0.5), quantile(&mut all, 0.99));
    println!(
        "  all            {:>7} ok  ({:.0}/s)  p50 {p50:.2?}  p99 {p99:.2?}",
        all.len(),
        all.len() as f64 / elapsed.as_secs_f64()
    );

    // Resident memory after the load, its objects destroyed: back within the bound of the warm baseline.
    let mut resident = daemon.resident_bytes();
    for _ in 0..50 {
        if resident <= baseline + bound {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
        resident = daemon.resident_bytes();
    }
    let mib = |bytes: u64| bytes as f64 / (1 << 20) as f64;
    println!(
        "  resident: baseline {:.1} MiB, after the load {:.1} MiB, settled {:.1} MiB",
        mib(baseline),
        mib(peak),
        mib(resident)
    );
    assert!(
        resident <= baseline + bound,
        "resident {:.1} MiB, more than {:.0} MiB above the baseline {:.1} MiB",
        mib(resident),
        mib(bound),
        mib(baseline)
    );
}
