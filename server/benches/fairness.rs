//! Fair scheduling under a flood: tenant `flood` keeps the CPU device saturated with 1M-ray batches from two
//! callers at once while a probe traces one ray at a time, (1) on an idle server, (2) as tenant `probe` during the
//! flood, and (3) as the flood's own tenant during the flood (one queue: first come, first served), to show what the
//! per-tenant queues buy. Prints one table; run with `cargo bench -p rayd-server --bench fairness`. The server runs
//! in this process (its own runtime threads), the clients talk to it over TCP.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bytes::Bytes;
use rayd_client::{Client, ClientOptions};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use rayd_engine::raygen::Camera;
use rayd_server::config::{KeyConfig, Role, TenantConfig};

/// mimalloc keeps freed pages for reuse: large ray and hit messages then cost no fresh page faults each call.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

const FLOOD_KEY: &str = "flood-write-key-0123456789";
const PROBE_KEY: &str = "probe-write-key-0123456789";
/// One-ray traces timed in each phase (after 100 untimed ones).
const PROBES: usize = 2000;
/// Shortest time over which the flood's rate is measured.
const FLOOD_WINDOW: Duration = Duration::from_secs(10);
/// Callers of the flood, each with one 1M-ray batch in flight at all times.
const FLOOD_CALLERS: usize = 2;

fn tenant(name: &str, key: &str) -> TenantConfig {
    TenantConfig {
        name: name.into(),
        keys: vec![KeyConfig { key: key.into(), role: Role::Write }],
        share: 1,
        limits: rayd_server::Limits::default(),
    }
}

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize].as_secs_f64() * 1e6
}

/// One-ray traces one after another; their latencies, sorted.
async fn probe(client: &Client, query: &Query, ray: &Bytes) -> Vec<Duration> {
    let mut latencies = Vec::with_capacity(PROBES);
    for call in 0..PROBES + 100 {
        let start = Instant::now();
        client.trace("bunny", query, ray.clone()).await.unwrap();
        if call >= 100 {
            latencies.push(start.elapsed());
        }
    }
    latencies.sort();
    latencies
}

/// Probes while the flood runs; the probe latencies and the flood's rays per second, measured over at least
/// [`FLOOD_WINDOW`] (the probes keep going until it has passed, so the rate counts many whole batches).
async fn under_flood(
    flood: &Client,
    prober: &Client,
    query: &Query,
    rays: &Bytes,
    ray: &Bytes,
) -> (Vec<Duration>, f64) {
    let (stop, traced) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicU64::new(0)));
    let callers: Vec<_> = (0..FLOOD_CALLERS)
        .map(|_| {
            let (flood, rays, query, stop, traced) =
                (flood.clone(), rays.clone(), *query, Arc::clone(&stop), Arc::clone(&traced));
            tokio::spawn(async move {
                while !stop.load(Ordering::Acquire) {
                    let result = flood.trace("bunny", &query, rays.clone()).await.unwrap();
                    traced.fetch_add(result.rays() as u64, Ordering::AcqRel);
                }
            })
        })
        .collect();
    while traced.load(Ordering::Acquire) < 2 << 20 {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let (before, start) = (traced.load(Ordering::Acquire), Instant::now());
    let mut latencies = probe(prober, query, ray).await;
    while start.elapsed() < FLOOD_WINDOW {
        latencies.extend(probe(prober, query, ray).await);
    }
    latencies.sort();
    let flood_rate = (traced.load(Ordering::Acquire) - before) as f64 / start.elapsed().as_secs_f64();
    stop.store(true, Ordering::Release);
    for caller in callers {
        caller.await.unwrap();
    }
    (latencies, flood_rate)
}

fn main() {
    let meshes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/meshes");
    let bunny = Mesh::load_obj(meshes.join("stanford-bunny.obj")).expect("the shared bunny");
    let (lo, hi) = bunny.bounds();
    let rays = Bytes::from(Camera::framing(lo, hi, 1024, 1024).rays(RayFormat::OriginTminDirectionTmax));
    let one_ray = rays.slice(512 * 1024 * 32..512 * 1024 * 32 + 32);
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);

    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let config = rayd_server::Config {
            tenants: vec![tenant("flood", FLOOD_KEY), tenant("probe", PROBE_KEY)],
            ..rayd_server::Config::default()
        };
        tokio::spawn(rayd_server::run(config, listener, None, std::future::pending()));
        let connect = |key: &str| {
            let options = ClientOptions { token: Some(key.into()), ..ClientOptions::default() };
            Client::connect(&url, options)
        };
        let (flood, prober, same_tenant) =
            (connect(FLOOD_KEY).await.unwrap(), connect(PROBE_KEY).await.unwrap(), connect(FLOOD_KEY).await.unwrap());
        for client in [&flood, &prober] {
            client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
        }

        let idle = probe(&prober, &query, &one_ray).await;
        let (fair, fair_rate) = under_flood(&flood, &prober, &query, &rays, &one_ray).await;
        let (shared, shared_rate) = under_flood(&flood, &same_tenant, &query, &rays, &one_ray).await;

        let (idle_p50, idle_p99) = (percentile(&idle, 0.5), percentile(&idle, 0.99));
        println!(
            "bunny, 1M camera rays a batch, closest, t; {FLOOD_CALLERS} flood callers; at least {PROBES} one-ray \
             probes per row (and {} s under the flood)",
            FLOOD_WINDOW.as_secs()
        );
        println!("probe                                   p50 µs   p90 µs   p99 µs  p99/idle p50  p99/idle p99  flood Mrays/s");
        let row = |name: &str, l: &[Duration], rate: Option<f64>| {
            let p99 = percentile(l, 0.99);
            println!(
                "{name:<38} {:7.0}  {:7.0}  {:7.0}  {:11.1}×  {:11.1}×  {}",
                percentile(l, 0.5),
                percentile(l, 0.9),
                p99,
                p99 / idle_p50,
                p99 / idle_p99,
                rate.map_or("-".into(), |r| format!("{:.2}", r / 1e6))
            );
        };
        row("idle server", &idle, None);
        row("tenant probe during the flood", &fair, Some(fair_rate));
        row("flood's own tenant during the flood", &shared, Some(shared_rate));
        println!("({} probes under the flood, {} as its own tenant)", fair.len(), shared.len());
    });
}
