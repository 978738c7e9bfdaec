//! End to end: fair scheduling between tenants. Tenant `flood` keeps the CPU device saturated with 1M-ray batches
//! from two callers at once while tenant `probe` traces one ray at a time. The probe's rays are served between the
//! flood's pieces: while the probe makes all of its traces, the flood finishes at most the batch each caller had
//! running and one more. First come, first served would make every probe trace wait behind whole batches.
//! (Latencies are printed for the record; the figures that count are in BENCHMARKS.md, from
//! `cargo bench -p rayd-server --bench fairness`.)

mod common;
mod daemon;

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bytes::Bytes;
use daemon::Daemon;
use rayd_client::{Client, ClientOptions};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::query::Query;
use rayd_engine::raygen::Camera;

const FLOOD_KEY: &str = "flood-write-key-0123456789";
const PROBE_KEY: &str = "probe-write-key-0123456789";
/// One-ray traces the probe makes under load.
const PROBES: usize = 50;

async fn client(daemon: &Daemon, key: &str) -> Client {
    let options = ClientOptions { token: Some(key.into()), ..ClientOptions::default() };
    Client::connect(&daemon.url(), options).await.unwrap()
}

/// Median and largest of `latencies`, in microseconds.
fn summary(mut latencies: Vec<Duration>) -> (u128, u128) {
    latencies.sort();
    (latencies[latencies.len() / 2].as_micros(), latencies[latencies.len() - 1].as_micros())
}

/// `PROBES` one-ray traces, one after another.
async fn probe(client: &Client, query: &Query, ray: &Bytes) -> Vec<Duration> {
    let mut latencies = Vec::with_capacity(PROBES);
    for _ in 0..PROBES {
        let start = Instant::now();
        let result = client.trace("bunny", query, ray.clone()).await.unwrap();
        latencies.push(start.elapsed());
        assert_eq!(result.rays(), 1);
    }
    latencies
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn one_ray_traces_are_served_between_the_pieces_of_a_flood() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("rayd-fairness-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("rayd.toml");
    let config = format!(
        "[[tenants]]\nname = \"flood\"\nkeys = [{{ key = \"{FLOOD_KEY}\", role = \"write\" }}]\n\
         [[tenants]]\nname = \"probe\"\nkeys = [{{ key = \"{PROBE_KEY}\", role = \"write\" }}]\n"
    );
    std::fs::write(&path, config).unwrap();
    let daemon = Daemon::start(&[("RAYD_CONFIG", path.to_str().unwrap())]);
    let (flood, probe_client) = (client(&daemon, FLOOD_KEY).await, client(&daemon, PROBE_KEY).await);
    let bunny = common::shared_mesh("stanford-bunny");
    for c in [&flood, &probe_client] {
        c.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    }
    let (lo, hi) = bunny.bounds();
    let rays = Bytes::from(Camera::framing(lo, hi, 1024, 1024).rays(RayFormat::OriginTminDirectionTmax));
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
    let one_ray = rays.slice(512 * 1024 * 32..512 * 1024 * 32 + 32);
    let idle = summary(probe(&probe_client, &query, &one_ray).await);

    let (stop, finished) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicU64::new(0)));
    let callers: Vec<_> = (0..2)
        .map(|_| {
            let (flood, rays, stop, finished) = (flood.clone(), rays.clone(), Arc::clone(&stop), Arc::clone(&finished));
            tokio::spawn(async move {
                while !stop.load(Ordering::Acquire) {
                    let result = flood.trace("bunny", &query, rays.clone()).await.unwrap();
                    assert_eq!(result.rays(), 1 << 20);
                    finished.fetch_add(1, Ordering::AcqRel);
                }
            })
        })
        .collect();
    // Steady state: both callers have had a batch traced and keep the next ones coming.
    while finished.load(Ordering::Acquire) < 2 {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let before = finished.load(Ordering::Acquire);
    let loaded = probe(&probe_client, &query, &one_ray).await;
    let during = finished.load(Ordering::Acquire) - before;
    stop.store(true, Ordering::Release);
    for caller in callers {
        caller.await.unwrap();
    }
    let loaded = summary(loaded);
    eprintln!(
        "probe: idle p50 {} µs, max {} µs; under the flood p50 {} µs, max {} µs; flood batches meanwhile: {during}",
        idle.0, idle.1, loaded.0, loaded.1
    );
    assert!(
        during <= 4,
        "the flood finished {during} 1M-ray batches while the probe made {PROBES} one-ray traces: the probe waited \
         behind whole batches"
    );
}
