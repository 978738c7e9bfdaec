//! The batch driver of CPU-side tracing: rays are split into chunks traced in parallel with rayon; in a chunk each
//! ray is decoded once, handed to the backend's closure in groups ([`GROUP_RAYS`], so that a backend can trace
//! coherent ones together) and written in place. A group is 16 consecutive rays, or, where the rays follow an
//! image's rows ([`ImageRows`]), a 4×4 tile of them. Nothing is allocated per ray. The rays are handed over decoded,
//! not prepared ([`crate::intersect::PreparedRay`]): a backend prepares what its tests need, which for rays traced
//! together is much less than a prepared ray each.

use std::ops::Range;

use rayon::prelude::*;

use super::rows::{ImageRows, groups, split_from};
use super::{Collector, Query, QueryKind, TraceOutput, TraceStats};
use crate::error::Result;
use crate::format::{Hit, HitFormat, Ray};
use crate::intersect::traced;

/// Rays per parallel chunk (at least: rays that follow an image's rows are chunked by whole bands of tiles); a
/// multiple of 8 so that bitmask outputs split on byte boundaries.
pub const CHUNK_RAYS: usize = 1024;

/// Rays handed to the backend at once (the last group of a chunk may be smaller).
pub const GROUP_RAYS: usize = 16;

/// How the driver splits a batch: the image rows its rays follow, if any, and its chunks (ranges of rays, each traced
/// on one thread; one chunk is traced on the caller's thread). Chunks are [`CHUNK_RAYS`] rays, or with rows whole
/// bands of tiles; the first also takes the rays before the first row start, the last the rays after the last whole
/// chunk (so that a chunk split again is one chunk). They start on multiples of 8 rays for a bitmask hit format (rows
/// whose first start is not one are then not used).
pub fn batch_chunks(query: &Query, rays: &[u8]) -> (Option<ImageRows>, Vec<Range<usize>>) {
    let count = rays.len() / query.ray_format.size();
    let bitmask = query.hit_format == HitFormat::Bitmask;
    let rows = ImageRows::find(query.ray_format, rays).filter(|rows| !bitmask || rows.first.is_multiple_of(8));
    // Bands of rows no wider than `ImageRows::find` finds: no overflow.
    let banded = rows.and_then(|rows| Some((rows.first, rows.bands_of(CHUNK_RAYS, 8)?)));
    let (first, chunk) = banded.unwrap_or((0, CHUNK_RAYS));
    (rows, split_from(count, first, chunk))
}

/// Checks the buffers, then traces every ray of `rays` with `traverse` and writes its records into `out`, in the
/// chunks of [`batch_chunks`], in parallel. `traverse` gets a group of up to [`GROUP_RAYS`] neighbouring rays (as
/// [`traced`] makes them: the query's flags added) with a collector each, offers each ray's candidate triangles to
/// its collector and adds what it did to the stats; it gets working state (a traversal stack) made once per chunk by
/// `new_state`. A ray whose walk would take more than `max_ray_work` node visits and triangle tests (counted over
/// its group, checked as it enters an instance) is stopped, and counted in [`TraceStats::rays_past_work`].
pub fn trace_batch<S, N, F>(
    query: &Query,
    rays: &[u8],
    out: TraceOutput<'_>,
    max_ray_work: u64,
    new_state: N,
    traverse: F,
) -> Result<TraceStats>
where
    N: Fn() -> S + Sync,
    F: Fn(&mut S, &[Ray], &mut [Collector<'_>], &mut TraceStats) + Sync,
{
    let out = checked(query, rays, out)?;
    let (rows, chunks) = batch_chunks(query, rays);
    let trace_chunk = |range: Range<usize>, hits: &mut [u8], counts: &mut [u8]| {
        trace_chunk(query, rays, rows, range, (hits, counts), max_ray_work, &new_state, &traverse)
    };
    if let [only] = chunks.as_slice() {
        // One chunk: traced on the caller's thread, without a hop to the thread pool (small-batch latency).
        return Ok(trace_chunk(only.clone(), out.hits, out.counts));
    }
    let outputs = out.split(query, &chunks);
    let stats = chunks.into_par_iter().zip(outputs).map(|(range, out)| trace_chunk(range, out.hits, out.counts));
    Ok(stats.reduce(TraceStats::default, |mut a, b| {
        a.add(&b);
        a
    }))
}

/// [`trace_batch`] on this thread, as one chunk, with the image rows the caller knows the rays follow (a generator's:
/// [`crate::raygen::Generator::image_rows`]) instead of looking for them: a part of a trace that runs in parts,
/// which are traced in parallel already.
pub fn trace_batch_here<S, F>(
    query: &Query,
    rays: &[u8],
    rows: Option<ImageRows>,
    out: TraceOutput<'_>,
    max_ray_work: u64,
    new_state: impl Fn() -> S,
    traverse: F,
) -> Result<TraceStats>
where
    F: Fn(&mut S, &[Ray], &mut [Collector<'_>], &mut TraceStats),
{
    let out = checked(query, rays, out)?;
    let count = rays.len() / query.ray_format.size();
    Ok(trace_chunk(query, rays, rows, 0..count, (out.hits, out.counts), max_ray_work, &new_state, &traverse))
}

/// `out`, once checked against the query's layout for `rays`, its bitmask's unused last bits cleared.
fn checked<'o>(query: &Query, rays: &[u8], out: TraceOutput<'o>) -> Result<TraceOutput<'o>> {
    out.check(&query.output_layout(rays.len())?)?;
    if let Some(last) = out.hits.last_mut() {
        // Clears the unused high bits of a bitmask's last byte; every other byte is fully rewritten.
        *last = 0;
    }
    Ok(out)
}

/// Traces the rays `range` of `rays` (following `rows`, if given, in the batch's indices) in groups, writing their
/// records and counts into `hits` and `counts` (the chunk's own, from its first ray). A group's rays may enter
/// instances until the chunk's work has grown by `max_ray_work` times [`GROUP_RAYS`] ([`Collector::stop_past`]).
#[allow(clippy::too_many_arguments)]
fn trace_chunk<S>(
    query: &Query,
    rays: &[u8],
    rows: Option<ImageRows>,
    range: Range<usize>,
    (hits, counts): (&mut [u8], &mut [u8]),
    max_ray_work: u64,
    new_state: &impl Fn() -> S,
    traverse: &impl Fn(&mut S, &[Ray], &mut [Collector<'_>], &mut TraceStats),
) -> TraceStats {
    let ray_size = query.ray_format.size();
    let records_per_ray = query.records_per_ray();
    let rays = &rays[range.start * ray_size..range.end * ray_size];
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
    // What a group of rays may take together, at most: each ray's share.
    let group_work = max_ray_work.saturating_mul(GROUP_RAYS as u64);
    for group in groups(range, rows, GROUP_RAYS) {
        let work_ceiling = stats.work().saturating_add(group_work);
        // Decoded by a loop compiled once a ray format, without a match a ray.
        let len = query.ray_format.specialized(
            #[inline(always)]
            |format| {
                let mut len = 0;
                for &(first, run) in group.runs() {
                    let bytes = &rays[first * ray_size..(first + run) * ray_size];
                    let slots = decoded[len..].iter_mut().zip(&mut collectors[len..]);
                    for ((ray, collector), bytes) in slots.zip(bytes.chunks_exact(format.size())) {
                        *ray = traced(&format.decode(bytes), query.flags);
                        collector.restart(ray, work_ceiling);
                    }
                    len += run;
                }
                len
            },
        );
        traverse(&mut state, &decoded[..len], &mut collectors[..len], &mut stats);
        let found = Collector::found_bits(&collectors[..len]);
        let group_collectors = &collectors[..len];
        query.hit_format.specialized(
            #[inline(always)]
            |format| {
                Collector::write_group(group_collectors, found, group.runs(), format, hits, records_per_ray, counts)
            },
        );
        stats.rays_hit += u64::from(found.count_ones());
        stats.rays += len as u64;
    }
    stats
}
