//! The batch driver of CPU-side tracing: rays are split into chunks traced in parallel with rayon; in a chunk each
//! ray is decoded once, handed to the backend's closure in groups of consecutive rays ([`GROUP_RAYS`], so that a
//! backend can trace coherent ones together) and written in place. Nothing is allocated per ray. The rays are
//! handed over decoded, not prepared ([`crate::intersect::PreparedRay`]): a backend prepares what its tests need,
//! which for rays traced together is much less than a prepared ray each.

use rayon::prelude::*;

use super::{Collector, Query, QueryKind, TraceOutput, TraceStats};
use crate::error::Result;
use crate::format::{Hit, Ray};
use crate::intersect::traced;

/// Rays per parallel chunk; a multiple of 8 so that bitmask outputs split on byte boundaries.
pub const CHUNK_RAYS: usize = 1024;

/// Consecutive rays handed to the backend at once (the last group of a chunk may be smaller).
pub const GROUP_RAYS: usize = 16;

/// Checks the buffers, then traces every ray of `rays` with `traverse` and writes its records into `out`.
/// `traverse` gets up to [`GROUP_RAYS`] consecutive rays (as [`traced`] makes them: the query's flags added) with a
/// collector each, offers each ray's candidate triangles to its collector and adds what it did to the stats; it gets
/// working state (a traversal stack) made once per chunk by `new_state`.
pub fn trace_batch<S, N, F>(
    query: &Query,
    rays: &[u8],
    out: TraceOutput<'_>,
    new_state: N,
    traverse: F,
) -> Result<TraceStats>
where
    N: Fn() -> S + Sync,
    F: Fn(&mut S, &[Ray], &mut [Collector<'_>], &mut TraceStats) + Sync,
{
    let layout = query.output_layout(rays.len())?;
    out.check(&layout)?;
    let ray_size = query.ray_format.size();
    let records_per_ray = query.records_per_ray();
    let hit_chunk = query.hit_format.buffer_len(CHUNK_RAYS * records_per_ray);
    if let Some(last) = out.hits.last_mut() {
        // Clears the unused high bits of a bitmask's last byte; every other byte is fully rewritten.
        *last = 0;
    }
    let trace_chunk = |rays: &[u8], hits: &mut [u8], counts: &mut [u8]| {
        let mut stats = TraceStats::default();
        let mut state = new_state();
        let all = query.kind == QueryKind::All;
        let mut scratch = vec![Hit::MISS; if all { records_per_ray * GROUP_RAYS } else { 0 }];
        let mut parts = scratch.chunks_mut(records_per_ray.max(1));
        // A group's rays and collectors, made once a chunk and restarted for every group.
        let unused = traced(&Ray::default(), query.flags);
        let mut decoded = [unused; GROUP_RAYS];
        let mut collectors: [Collector<'_>; GROUP_RAYS] = std::array::from_fn(|_| {
            let part = if all { parts.next().expect("a scratch part a ray") } else { &mut [] };
            Collector::new(query, &unused, part)
        });
        for (group, bytes) in rays.chunks(ray_size * GROUP_RAYS).enumerate() {
            let first = group * GROUP_RAYS;
            let len = bytes.len() / ray_size;
            // Decoded by a loop compiled once a ray format, without a match a ray.
            query.ray_format.specialized(
                #[inline(always)]
                |format| {
                    let slots = decoded.iter_mut().zip(&mut collectors).zip(bytes.chunks_exact(format.size()));
                    for ((ray, collector), bytes) in slots {
                        *ray = traced(&format.decode(bytes), query.flags);
                        collector.restart(ray);
                    }
                },
            );
            traverse(&mut state, &decoded[..len], &mut collectors[..len], &mut stats);
            query.hit_format.specialized(
                #[inline(always)]
                |format| {
                    for (i, collector) in collectors[..len].iter().enumerate() {
                        let index = first + i;
                        collector.write(format, hits, index * records_per_ray, counts, index);
                    }
                },
            );
            stats.rays_hit += collectors[..len].iter().map(|collector| u64::from(collector.found())).sum::<u64>();
            stats.rays += len as u64;
        }
        stats
    };
    if layout.rays <= CHUNK_RAYS {
        // One chunk: traced on the caller's thread, without a hop to the thread pool (small-batch latency).
        return Ok(trace_chunk(rays, out.hits, out.counts));
    }
    let hit_chunks: Vec<&mut [u8]> = out.hits.chunks_mut(hit_chunk.max(1)).collect();
    let count_chunks: Vec<&mut [u8]> = if query.kind.has_counts() {
        out.counts.chunks_mut(CHUNK_RAYS * 4).collect()
    } else {
        hit_chunks.iter().map(|_| Default::default()).collect()
    };
    let stats = rays
        .par_chunks(CHUNK_RAYS * ray_size)
        .zip(hit_chunks.into_par_iter().zip(count_chunks))
        .map(|(rays, (hits, counts))| trace_chunk(rays, hits, counts))
        .reduce(TraceStats::default, |mut a, b| {
            a.add(&b);
            a
        });
    Ok(stats)
}
