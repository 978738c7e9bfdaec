//! Load from the client side: concurrent tasks trace batches of random rays in a loop for a fixed time, and the
//! latencies of every call are kept for percentiles.

use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use glam::Vec3;
use rayd_engine::query::Query;
use rayd_proto as proto;
use tokio::task::JoinSet;

use crate::client::Client;
use crate::convert::bounds;
use crate::error::{Error, Result};
use crate::memory::random_rays;

/// What to run.
#[derive(Debug, Clone, Copy)]
pub struct BenchOptions {
    /// Rays a call.
    pub batch: usize,
    /// Calls in flight at once (one task each), at most the server's `max_concurrent_operations` for this tenant:
    /// a larger number is lowered to it ([`BenchReport::concurrency`]), as more calls would be refused.
    pub concurrency: usize,
    /// How long tasks keep starting new calls.
    pub duration: Duration,
    /// The query every call makes.
    pub query: Query,
}

/// What a run measured.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchReport {
    /// Rays traced, over all calls.
    pub rays: u64,
    /// Rays with a hit, as the server counted them.
    pub rays_hit: u64,
    /// From the first call's start to the last call's end.
    pub elapsed: Duration,
    /// Time the server spent tracing, summed over calls.
    pub server_time: Duration,
    /// Every call's end-to-end latency, sorted.
    pub latencies: Vec<Duration>,
    /// Calls kept in flight: [`BenchOptions::concurrency`], lowered to the server's `max_concurrent_operations`.
    pub concurrency: usize,
}

impl BenchReport {
    /// Calls made.
    pub fn batches(&self) -> usize {
        self.latencies.len()
    }

    /// Rays a second, end to end.
    pub fn rays_per_second(&self) -> f64 {
        self.rays as f64 / self.elapsed.as_secs_f64().max(f64::MIN_POSITIVE)
    }

    /// The latency at quantile `q` in `[0, 1]` (nearest rank), or zero without calls.
    pub fn latency(&self, q: f64) -> Duration {
        let rank = (q * self.latencies.len() as f64).ceil() as usize;
        self.latencies
            .get(rank.saturating_sub(1).min(self.latencies.len().saturating_sub(1)))
            .copied()
            .unwrap_or_default()
    }
}

/// One task's share of a run.
#[derive(Debug, Default)]
struct TaskTally {
    /// Rays this task traced.
    rays: u64,
    /// Rays with a hit among them.
    rays_hit: u64,
    /// Server tracing time of this task's calls, in nanoseconds.
    server_ns: u64,
    /// This task's call latencies.
    latencies: Vec<Duration>,
}

impl TaskTally {
    /// Counts one call that took `latency` and traced `rays` rays, with the server's `stats` for it.
    fn count_call(&mut self, latency: Duration, rays: usize, stats: &proto::TraceStats) {
        self.latencies.push(latency);
        self.add(rays as u64, stats.rays_hit, stats.trace_ns);
    }

    /// Adds another task's tally to this one.
    fn absorb(&mut self, other: TaskTally) {
        self.add(other.rays, other.rays_hit, other.server_ns);
        self.latencies.extend(other.latencies);
    }

    /// Adds rays, rays hit and server time, each sum saturating at `u64::MAX`.
    fn add(&mut self, rays: u64, rays_hit: u64, server_ns: u64) {
        self.rays = self.rays.saturating_add(rays);
        self.rays_hit = self.rays_hit.saturating_add(rays_hit);
        self.server_ns = self.server_ns.saturating_add(server_ns);
    }
}

impl Client {
    /// Runs `options.concurrency` tasks (at most the server's `max_concurrent_operations`) that each trace batches of
    /// random rays (origins in the accel's box, uniform directions, a different seed a task) against `accel` until
    /// `options.duration` is over, calling `on_batch` with the ray count after every call. The first failed call ends the run with its error.
    pub async fn bench(
        &self,
        accel: &str,
        options: &BenchOptions,
        on_batch: Arc<dyn Fn(usize) + Send + Sync>,
    ) -> Result<BenchReport> {
        let info = self.accel(accel).await?;
        let (lo, hi) = bounds(&info).ok_or_else(|| Error::InvalidArgument(format!("accel {accel}: no triangles")))?;
        let limits = self.server_info().await?.limits.unwrap_or_default();
        let concurrency = capped(options.concurrency, limits.max_concurrent_operations as usize);
        let batches = random_batches(lo, hi, options, concurrency)?;
        let start = Instant::now();
        let deadline = start + options.duration;
        let mut tasks = JoinSet::new();
        for rays in batches {
            let (client, accel, query, on_batch) = (self.clone(), accel.to_owned(), options.query, on_batch.clone());
            tasks.spawn(async move {
                let mut tally = TaskTally::default();
                while Instant::now() < deadline {
                    let call = Instant::now();
                    let traced = client.trace(&accel, &query, rays.clone()).await?;
                    tally.count_call(call.elapsed(), traced.rays(), traced.stats());
                    on_batch(traced.rays());
                }
                Ok::<_, Error>(tally)
            });
        }
        let mut total = TaskTally::default();
        while let Some(joined) = tasks.join_next().await {
            let tally = joined.map_err(|e| Error::Protocol(format!("a bench task failed: {e}")))??;
            total.absorb(tally);
        }
        total.latencies.sort_unstable();
        Ok(BenchReport {
            rays: total.rays,
            rays_hit: total.rays_hit,
            elapsed: start.elapsed(),
            server_time: Duration::from_nanos(total.server_ns),
            latencies: total.latencies,
            concurrency,
        })
    }
}

/// One batch of `options.batch` random rays in the box `[lo, hi]` for each of `tasks` tasks, seeded by the task's
/// index ([`random_rays`]: sizes this process cannot hold are an error, not an abort).
fn random_batches(lo: Vec3, hi: Vec3, options: &BenchOptions, tasks: usize) -> Result<Vec<Bytes>> {
    let made = |seed| random_rays(lo, hi, options.batch, seed, options.query.ray_format).map(Bytes::from);
    (0..tasks as u64).map(made).collect()
}

/// `asked` calls in flight (at least 1), at most `limit` (0: none known).
fn capped(asked: usize, limit: usize) -> usize {
    let asked = asked.max(1);
    if limit == 0 { asked } else { asked.min(limit) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_use_the_nearest_rank() {
        let report = BenchReport {
            rays: 1000,
            rays_hit: 10,
            elapsed: Duration::from_secs(2),
            server_time: Duration::ZERO,
            latencies: (1..=100).map(Duration::from_millis).collect(),
            concurrency: 1,
        };
        assert_eq!(report.latency(0.5), Duration::from_millis(50));
        assert_eq!(report.latency(0.9), Duration::from_millis(90));
        assert_eq!(report.latency(0.99), Duration::from_millis(99));
        assert_eq!(report.latency(1.0), Duration::from_millis(100));
        assert_eq!(report.latency(0.0), Duration::from_millis(1));
        assert_eq!(report.rays_per_second(), 500.0);
        assert_eq!(BenchReport { latencies: vec![], ..report }.latency(0.5), Duration::ZERO);
    }

    #[test]
    fn concurrency_is_lowered_to_the_servers_limit() {
        assert_eq!(capped(200, 64), 64);
        assert_eq!(capped(4, 64), 4);
        assert_eq!(capped(0, 64), 1, "at least one call");
        assert_eq!(capped(200, 0), 200, "no limit known");
    }

    #[test]
    fn tallies_past_u64_saturate() {
        let most = proto::TraceStats { rays_hit: u64::MAX, trace_ns: u64::MAX, ..Default::default() };
        let mut task = TaskTally::default();
        task.count_call(Duration::from_millis(1), 8, &most);
        task.count_call(Duration::from_millis(2), 8, &most);
        let mut total = TaskTally { rays: u64::MAX, ..TaskTally::default() };
        total.absorb(task);
        assert_eq!((total.rays, total.rays_hit, total.server_ns), (u64::MAX, u64::MAX, u64::MAX));
        assert_eq!(total.latencies, [Duration::from_millis(1), Duration::from_millis(2)]);
    }
}
