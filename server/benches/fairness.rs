//! Fair scheduling under a flood: tenant `flood` keeps a device saturated with 1M-ray batches from its callers at
//! once while a probe traces one ray at a time, (1) on an idle server, (2) as tenant `probe` during the flood, and
//! (3) as the flood's own tenant during the flood (one queue: first come, first served), to show what the per-tenant
//! queues buy; then (4) as tenant `probe` while the flood traces costly rays (every ray crosses a pile of copies of
//! one triangle), to show what pieces sized by time buy; then (5) tenant `probe` traces batches of
//! [`PROBE_BATCH_RAYS`] camera rays one after another, on the idle server and beside the costly flood, to show what
//! charging tenants by time buys (charged by rays, the probe got the costly flood's ray rate); and last (6) both
//! probes while the flood builds the bunny again and again, to show how builds share the device with traces. Prints
//! one table; run with `cargo bench -p rayd-server --bench fairness`; `FAIRNESS_DEVICE` names the device (`cpu:0`
//! unless set, e.g. `wgpu:0`), `FAIRNESS_PILE_RAYS` the costly flood's rays a batch (65,536 unless set) and
//! `FAIRNESS_PILE` the copies of the triangle in its pile (20,000 unless set), `FAIRNESS_FLOOD_CALLERS` the flood's
//! callers (2 unless set). The server runs in this process (its
//! own runtime threads) with the embedded defaults and any `RAYD_…` variable set (e.g.
//! `RAYD_SCHEDULER_GPU_WORKERS=1`); the clients talk to it over TCP.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bytes::Bytes;
use rayd_client::{Client, ClientOptions};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::glam::{Vec3, Vec3A};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use rayd_engine::raygen::Camera;
use rayd_server::config::{KeyConfig, Role, TenantConfig};

/// mimalloc keeps freed pages for reuse: large ray and hit messages then cost no fresh page faults each call.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

const FLOOD_KEY: &str = "flood-write-key-0123456789";
const PROBE_KEY: &str = "probe-write-key-0123456789";
/// One-ray traces timed on the idle server (after 100 untimed ones) and, unless that takes too long, under a flood.
const PROBES: usize = 2000;
/// Shortest time over which the flood's rate is measured.
const FLOOD_WINDOW: Duration = Duration::from_secs(10);
/// Longest time the probe traces under a flood: a flood that holds the device for seconds at a time (pieces that
/// are not sized by time) leaves it a few traces.
const PROBE_TIME_LIMIT: Duration = Duration::from_secs(60);
/// Rays of the probe's batches, traced one after another to measure its throughput beside the costly flood.
const PROBE_BATCH_RAYS: usize = 16_384;
/// Callers of the flood (`FAIRNESS_FLOOD_CALLERS`, 2 unless set), each with one round (a 1M-ray batch, or a build)
/// in flight at all times.
fn flood_callers() -> usize {
    std::env::var("FAIRNESS_FLOOD_CALLERS").map_or(2, |n| n.parse().expect("a number of callers"))
}

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

/// How long a probe goes on: at least `calls` traces and `window`, at most [`PROBE_TIME_LIMIT`].
#[derive(Clone, Copy)]
struct Until {
    /// Traces at least.
    calls: usize,
    /// Time at least.
    window: Duration,
}

/// What a probe measured: its traces' latencies, sorted, and the rays it had traced a second.
struct Probed {
    latencies: Vec<Duration>,
    rays_per_second: f64,
}

/// Traces of `rays` one after another, until `until`.
async fn probe(client: &Client, query: &Query, rays: &Bytes, until: Until) -> Probed {
    let (start, batch_rays) = (Instant::now(), rays.len() / query.ray_format.size());
    let mut latencies = Vec::new();
    while (latencies.len() < until.calls || start.elapsed() < until.window) && start.elapsed() < PROBE_TIME_LIMIT {
        let sent = Instant::now();
        client.trace("bunny", query, rays.clone()).await.unwrap();
        latencies.push(sent.elapsed());
    }
    let rays_per_second = (latencies.len() * batch_rays) as f64 / start.elapsed().as_secs_f64();
    latencies.sort();
    Probed { latencies, rays_per_second }
}

/// What a flood does again and again: trace a batch of rays through one of its accels, or build a mesh (and
/// destroy it).
#[derive(Clone)]
enum Flood {
    /// Traces `rays` through `accel`, counting rays.
    Trace { accel: &'static str, rays: Bytes },
    /// Builds `mesh` on `device`, counting triangles.
    Build { mesh: Arc<Mesh>, device: String },
}

impl Flood {
    /// What the flood counts, a round.
    fn units(&self, query: &Query) -> u64 {
        match self {
            Flood::Trace { rays, .. } => (rays.len() / query.ray_format.size()) as u64,
            Flood::Build { mesh, .. } => mesh.triangles.len() as u64,
        }
    }

    /// Its name in the log.
    fn name(&self) -> &str {
        match self {
            Flood::Trace { accel, .. } => accel,
            Flood::Build { .. } => "builds",
        }
    }

    /// One round, as `caller` of the flood.
    async fn round(&self, client: &Client, query: &Query, caller: usize) {
        match self {
            Flood::Trace { accel, rays } => {
                client.trace(accel, query, rays.clone()).await.unwrap();
            }
            Flood::Build { mesh, device } => {
                let name = format!("built-{caller}");
                client.build_mesh(&name, mesh, device, BuildFlags::empty()).await.unwrap();
                client.destroy_accel(&name).await.unwrap();
            }
        }
    }
}

/// Probes with `probe_rays` while the flood runs, once each flood caller has had two rounds done, for at least
/// [`PROBES`] probes and [`FLOOD_WINDOW`] (so that the flood's rate counts many whole rounds); what the probe
/// measured, and the flood's rays (or triangles built) per second meanwhile.
async fn under_flood(
    flood_client: &Client,
    flood: &Flood,
    prober: &Client,
    query: &Query,
    probe_rays: &Bytes,
) -> (Probed, f64) {
    let (stop, done) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicU64::new(0)));
    let units = flood.units(query);
    let callers: Vec<_> = (0..flood_callers())
        .map(|caller| {
            let (client, flood, query, stop, done) =
                (flood_client.clone(), flood.clone(), *query, Arc::clone(&stop), Arc::clone(&done));
            tokio::spawn(async move {
                while !stop.load(Ordering::Acquire) {
                    flood.round(&client, &query, caller).await;
                    done.fetch_add(units, Ordering::AcqRel);
                }
            })
        })
        .collect();
    eprintln!("flooding {} …", flood.name());
    while done.load(Ordering::Acquire) < 2 * flood_callers() as u64 * units {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    eprintln!("probing …");
    let (before, start) = (done.load(Ordering::Acquire), Instant::now());
    let probed = probe(prober, query, probe_rays, Until { calls: PROBES, window: FLOOD_WINDOW }).await;
    let flood_rate = (done.load(Ordering::Acquire) - before) as f64 / start.elapsed().as_secs_f64();
    stop.store(true, Ordering::Release);
    for caller in callers {
        caller.await.unwrap();
    }
    (probed, flood_rate)
}

/// The pile of `copies` of one triangle (every ray through it tests each), and `count` rays that cross it.
fn pile(copies: usize, count: usize) -> (Mesh, Bytes) {
    let mesh = Mesh { positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y], triangles: vec![[0, 1, 2]; copies] };
    let ray = rayd_engine::format::Ray {
        origin: Vec3A::new(0.25, 0.25, 1.0),
        direction: Vec3A::NEG_Z,
        tmax: f32::INFINITY,
        ..Default::default()
    };
    let format = RayFormat::OriginTminDirectionTmax;
    let mut rays = vec![0; count * format.size()];
    rays.chunks_exact_mut(format.size()).for_each(|record| format.encode(&ray, record));
    (mesh, Bytes::from(rays))
}

fn main() {
    let meshes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/meshes");
    let bunny = Mesh::load_obj(meshes.join("stanford-bunny.obj")).expect("the shared bunny");
    let (lo, hi) = bunny.bounds();
    let rays = Bytes::from(Camera::framing(lo, hi, 1024, 1024).rays(RayFormat::OriginTminDirectionTmax));
    let one_ray = rays.slice(512 * 1024 * 32..512 * 1024 * 32 + 32);
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
    let device = std::env::var("FAIRNESS_DEVICE").unwrap_or_else(|_| "cpu:0".into());
    let pile_rays = std::env::var("FAIRNESS_PILE_RAYS").map_or(1 << 16, |n| n.parse().expect("a number of rays"));
    let pile_copies = std::env::var("FAIRNESS_PILE").map_or(20_000, |n| n.parse().expect("a number of triangles"));
    let (pile, through_pile) = pile(pile_copies, pile_rays);

    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let config = rayd_server::Config {
            tenants: vec![tenant("flood", FLOOD_KEY), tenant("probe", PROBE_KEY)],
            ..rayd_server::Config::load(None, std::env::vars()).expect("the RAYD_… variables make a configuration")
        };
        tokio::spawn(rayd_server::run(config, listener, None, std::future::pending()));
        let connect = |key: &str| {
            let options = ClientOptions { token: Some(key.into()), ..ClientOptions::default() };
            Client::connect(&url, options)
        };
        let (flood, prober, same_tenant) =
            (connect(FLOOD_KEY).await.unwrap(), connect(PROBE_KEY).await.unwrap(), connect(FLOOD_KEY).await.unwrap());
        for client in [&flood, &prober] {
            client.build_mesh("bunny", &bunny, &device, BuildFlags::empty()).await.unwrap();
        }
        flood.build_mesh("pile", &pile, &device, BuildFlags::empty()).await.unwrap();

        probe(&prober, &query, &one_ray, Until { calls: 100, window: Duration::ZERO }).await;
        let idle = probe(&prober, &query, &one_ray, Until { calls: PROBES, window: Duration::ZERO }).await;
        let bunny_flood = Flood::Trace { accel: "bunny", rays: rays.clone() };
        let fair = under_flood(&flood, &bunny_flood, &prober, &query, &one_ray).await;
        let shared = under_flood(&flood, &bunny_flood, &same_tenant, &query, &one_ray).await;
        let pile_flood = Flood::Trace { accel: "pile", rays: through_pile };
        let costly = under_flood(&flood, &pile_flood, &prober, &query, &one_ray).await;
        let batch = rays.slice(..PROBE_BATCH_RAYS * query.ray_format.size());
        let idle_batches = probe(&prober, &query, &batch, Until { calls: 0, window: FLOOD_WINDOW }).await;
        let costly_batches = under_flood(&flood, &pile_flood, &prober, &query, &batch).await;
        let build_flood = Flood::Build { mesh: Arc::new(bunny), device: device.clone() };
        let builds = under_flood(&flood, &build_flood, &prober, &query, &one_ray).await;
        let builds_batches = under_flood(&flood, &build_flood, &prober, &query, &batch).await;

        let (idle_p50, idle_p99) = (percentile(&idle.latencies, 0.5), percentile(&idle.latencies, 0.99));
        println!(
            "{device}; flood: bunny, 1M camera rays a batch, closest, t; costly flood: {pile_rays} rays a batch \
             through a pile of {pile_copies} copies of one triangle; {} flood callers; probes of the \
             bunny (one ray, or {PROBE_BATCH_RAYS} camera rays a batch), under a flood for {} s and {PROBES} probes \
             at least, {} s at most",
            flood_callers(),
            FLOOD_WINDOW.as_secs(),
            PROBE_TIME_LIMIT.as_secs()
        );
        println!(
            "probe                                          p50 µs     p90 µs     p99 µs     max µs  p99/idle p50  \
             p99/idle p99  probe Mrays/s  flood Mrays/s"
        );
        let row = |name: &str, probed: &Probed, idle: (f64, f64), flood_rate: Option<f64>| {
            let (l, p99) = (&probed.latencies, percentile(&probed.latencies, 0.99));
            println!(
                "{name:<45} {:9.0}  {:9.0}  {:9.0}  {:9.0}  {:11.1}×  {:11.1}×  {:13.3}  {}",
                percentile(l, 0.5),
                percentile(l, 0.9),
                p99,
                percentile(l, 1.0),
                p99 / idle.0,
                p99 / idle.1,
                probed.rays_per_second / 1e6,
                flood_rate.map_or("-".into(), |r| format!("{:.3}", r / 1e6))
            );
        };
        let idle_batch = (percentile(&idle_batches.latencies, 0.5), percentile(&idle_batches.latencies, 0.99));
        row("idle server", &idle, (idle_p50, idle_p99), None);
        row("tenant probe during the flood", &fair.0, (idle_p50, idle_p99), Some(fair.1));
        row("flood's own tenant during the flood", &shared.0, (idle_p50, idle_p99), Some(shared.1));
        row("tenant probe during the costly flood", &costly.0, (idle_p50, idle_p99), Some(costly.1));
        row("idle server, batches", &idle_batches, idle_batch, None);
        row("tenant probe's batches during the costly flood", &costly_batches.0, idle_batch, Some(costly_batches.1));
        row("tenant probe during the build flood", &builds.0, (idle_p50, idle_p99), Some(builds.1));
        row("tenant probe's batches during the build flood", &builds_batches.0, idle_batch, Some(builds_batches.1));
        println!(
            "({} probes under the flood, {} as its own tenant, {} under the costly flood, {} under the build flood; \
             batches: {} idle, {} under the costly flood, {} under the build flood; the build flood's rate is M \
             triangles built a second)",
            fair.0.latencies.len(),
            shared.0.latencies.len(),
            costly.0.latencies.len(),
            builds.0.latencies.len(),
            idle_batches.latencies.len(),
            costly_batches.0.latencies.len(),
            builds_batches.0.latencies.len()
        );
    });
}
