//! The batch driver of CPU-side tracing: rays are split into chunks traced in parallel with rayon, each ray is
//! decoded once, traversed by the backend's closure and written in place. Nothing is allocated per ray.

use rayon::prelude::*;

use super::{Collector, Query, QueryKind, TraceOutput, TraceStats};
use crate::error::Result;
use crate::format::Hit;
use crate::intersect::PreparedRay;

/// Rays per parallel chunk; a multiple of 8 so that bitmask outputs split on byte boundaries.
pub const CHUNK_RAYS: usize = 1024;

/// Checks the buffers, then traces every ray of `rays` with `traverse` and writes its records into `out`.
/// `traverse` offers the ray's candidate triangles to the collector and adds what it did to the stats; it gets
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
    F: Fn(&mut S, &PreparedRay, &mut Collector<'_>, &mut TraceStats) + Sync,
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
        let mut scratch = vec![Hit::MISS; if query.kind == QueryKind::All { records_per_ray } else { 0 }];
        for (index, bytes) in rays.chunks_exact(ray_size).enumerate() {
            let ray = PreparedRay::new(&query.ray_format.decode(bytes), query.flags);
            let mut collector = Collector::new(query, &ray, &mut scratch);
            traverse(&mut state, &ray, &mut collector, &mut stats);
            collector.write(query, hits, index * records_per_ray, counts, index);
            stats.rays += 1;
            stats.rays_hit += u64::from(collector.found());
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
