//! Traces of generated rays and reduced traces done around a backend's plain [`Backend::trace`]: the rays made on
//! the host, the hits reduced on the host, across the rayon pool. Two ways:
//! - whole: every ray made into one scratch buffer, traced, then reduced ([`trace_source`], [`trace_reduced`]):
//!   every backend's default, and what the wgpu backend comes to for what it cannot do on the device (a GPU wants
//!   large dispatches);
//! - in parts of [`PART_RAYS`] ([`trace_source_in_parts`], [`trace_reduced_in_parts`]): each worker makes, traces
//!   and reduces a part while its rays and hits are in the core's cache, in buffers it reuses from part to part,
//!   for backends that trace on the host's cores (the CPU). Nothing the size of the batch is allocated, touched for
//!   the first time (page faults) or streamed through memory. A part is traced on its worker's thread alone (the
//!   backend's [`TracePart`]): the parts are what runs in parallel.

use std::ops::Range;
use std::sync::Mutex;

use rayon::prelude::*;

use super::{Backend, BackendAccel, RaySource};
use crate::error::Result;
use crate::format::RayFormat;
use crate::query::{CHUNK_RAYS, ImageRows, Query, TraceOutput, TraceStats};
use crate::raygen::Generator;
use crate::reduce::{Partial, Reduction};

/// Rays a part of a trace done in parts (a whole number of the batch driver's chunks): 8,192 rays of 24–48 bytes
/// and their hits fit a core's second-level cache.
pub const PART_RAYS: usize = 8 * CHUNK_RAYS;

/// The rays of `rays` packed in `format`: the caller's bytes, or made into `scratch` across the rayon pool.
pub fn packed<'a>(rays: RaySource<'a>, format: RayFormat, scratch: &'a mut Vec<u8>) -> &'a [u8] {
    packed_by(rays, format, scratch, Generator::fill_parallel)
}

/// [`packed`], the rays made by `fill` ([`Generator::fill`] or [`Generator::fill_parallel`]).
fn packed_by<'a>(
    rays: RaySource<'a>,
    format: RayFormat,
    scratch: &'a mut Vec<u8>,
    fill: impl FnOnce(&Generator, RayFormat, u64, &mut [u8]),
) -> &'a [u8] {
    match rays {
        RaySource::Packed(bytes) => bytes,
        RaySource::Generated { generator, first, count } => {
            size_for_overwrite(scratch, count * format.size());
            fill(generator, format, first, scratch);
            scratch
        }
    }
}

/// [`Backend::trace_source`] with the rays made on the host.
pub fn trace_source<B: Backend + ?Sized>(
    backend: &B,
    accel: &dyn BackendAccel,
    query: &Query,
    rays: RaySource<'_>,
    out: TraceOutput<'_>,
) -> Result<TraceStats> {
    let mut scratch = Vec::new();
    backend.trace(accel, query, packed(rays, query.ray_format, &mut scratch), out)
}

/// [`Backend::trace_reduced`] with the rays made and the hits reduced on the host: traced with the reduction's
/// [`Reduction::traced_query`] into scratch buffers, then reduced.
pub fn trace_reduced<B: Backend + ?Sized>(
    backend: &B,
    accel: &dyn BackendAccel,
    query: &Query,
    rays: RaySource<'_>,
    first_ray: u64,
    reduction: &Reduction,
) -> Result<(Partial, TraceStats)> {
    let mut scratch = PartScratch::default();
    let traced = reduction.traced_query(query);
    let trace = |rays: &[u8], out: TraceOutput<'_>| backend.trace(accel, &traced, rays, out);
    trace_then_reduce(&traced, rays, &mut scratch, Generator::fill_parallel, trace, |rays, hits, counts| {
        reduction.reduce_piece_parallel(&traced, first_ray, rays, hits, counts)
    })
}

/// Packs `rays` (made by `fill` into `scratch` when generated), traces them with `trace` (with the query `traced`)
/// into `scratch`'s hit and count buffers, and reduces them with `reduce` (given the packed rays, hits and counts):
/// what a piece or a part of a reduced trace does.
fn trace_then_reduce(
    traced: &Query,
    rays: RaySource<'_>,
    scratch: &mut PartScratch,
    fill: impl FnOnce(&Generator, RayFormat, u64, &mut [u8]),
    trace: impl FnOnce(&[u8], TraceOutput<'_>) -> Result<TraceStats>,
    reduce: impl FnOnce(&[u8], &[u8], &[u8]) -> Partial,
) -> Result<(Partial, TraceStats)> {
    let PartScratch { rays: made, hits, counts } = scratch;
    let rays = packed_by(rays, traced.ray_format, made, fill);
    let layout = traced.output_layout(rays.len())?;
    // Every record and count is written by the trace.
    size_for_overwrite(hits, layout.hits);
    size_for_overwrite(counts, layout.counts);
    let stats = trace(rays, TraceOutput { hits, counts })?;
    Ok((reduce(rays, hits, counts), stats))
}

/// How a backend traces a part of a trace done in parts, on the calling thread: [`Backend::trace`] of the part's
/// packed rays, told the image rows they follow when the part's generator knows them
/// ([`crate::query::trace_batch_here`] for the CPU).
pub type TracePart<'a> = dyn Fn(&Query, &[u8], Option<ImageRows>, TraceOutput<'_>) -> Result<TraceStats> + Sync + 'a;

/// The image rows that rays `part` of `rays` follow, in the part's ray indices: the generator's
/// ([`Generator::image_rows`]), or for packed rays those `packed_rows` found once for all of them.
fn part_rows(rays: &RaySource<'_>, part: &Range<usize>, packed_rows: Option<ImageRows>) -> Option<ImageRows> {
    match rays {
        RaySource::Generated { generator, first, .. } => generator.image_rows(first + part.start as u64),
        RaySource::Packed(_) => packed_rows.map(|rows| rows.from_ray(part.start)),
    }
}

/// Makes `buffer` `len` bytes long for contents about to be written whole: one too small is replaced by a buffer the
/// allocator hands out zeroed (fresh pages, not written here: a batch-sized buffer zero-filled on one thread costs
/// milliseconds, and its pages are better first touched by the threads that fill them); one with room, reused from
/// an earlier part, keeps its stale bytes up to its old length (only bytes past it are zeroed).
fn size_for_overwrite(buffer: &mut Vec<u8>, len: usize) {
    if buffer.capacity() < len {
        *buffer = vec![0; len];
    } else {
        buffer.resize(len, 0);
    }
}

/// The buffers of a reduced trace's piece, or of a worker's parts (reused from part to part).
#[derive(Default)]
struct PartScratch {
    /// The part's rays, when they are made.
    rays: Vec<u8>,
    /// Its hit records.
    hits: Vec<u8>,
    /// Its per-ray counts.
    counts: Vec<u8>,
}

/// Runs `each` on the parts of `part` rays of a trace of `rays` rays (the last may be shorter), with a worker's
/// scratch buffers, and returns the results in ray order: a single part on the caller's thread, without a hop to
/// the thread pool (rayd's CPU pieces are one part each), more across the pool.
fn in_parts<R: Send>(
    rays: usize,
    part: usize,
    each: impl Fn(&mut PartScratch, Range<usize>) -> Result<R> + Sync,
) -> Result<Vec<R>> {
    if rays <= part {
        return Ok(vec![each(&mut PartScratch::default(), 0..rays)?]);
    }
    (0..rays.div_ceil(part))
        .into_par_iter()
        .map_init(PartScratch::default, |scratch, index| each(scratch, index * part..((index + 1) * part).min(rays)))
        .collect()
}

/// [`trace_source`] in parts of [`PART_RAYS`]: generated rays made a part at a time (packed rays go to
/// [`Backend::trace`] as they are). The same records.
pub fn trace_source_in_parts<B: Backend + ?Sized>(
    backend: &B,
    accel: &dyn BackendAccel,
    query: &Query,
    rays: RaySource<'_>,
    out: TraceOutput<'_>,
    trace_part: &TracePart<'_>,
) -> Result<TraceStats> {
    let RaySource::Generated { .. } = rays else { return trace_source(backend, accel, query, rays, out) };
    let layout = query.output_layout(rays.packed_len(query.ray_format.size()))?;
    out.check(&layout)?;
    if layout.rays == 0 {
        return Ok(TraceStats::default());
    }
    // Each part's records and counts, behind a lock of their own for the worker that traces it. Parts start on
    // byte boundaries of a bitmask: `PART_RAYS` is a multiple of 8.
    let hit_bytes = query.output_layout(PART_RAYS * query.ray_format.size())?.hits;
    let hits: Vec<Mutex<&mut [u8]>> = out.hits.chunks_mut(hit_bytes.max(1)).map(Mutex::new).collect();
    let counts: Vec<Mutex<&mut [u8]>> = match query.kind.has_counts() {
        true => out.counts.chunks_mut(PART_RAYS * 4).map(Mutex::new).collect(),
        false => hits.iter().map(|_| Mutex::new(Default::default())).collect(),
    };
    let ray_size = query.ray_format.size();
    let stats = in_parts(layout.rays, PART_RAYS, |scratch, range| {
        let index = range.start / PART_RAYS;
        let (mut hits, mut counts) = (hits[index].lock().unwrap(), counts[index].lock().unwrap());
        let rows = part_rows(&rays, &range, None);
        let rays = packed_by(rays.part(range, ray_size), query.ray_format, &mut scratch.rays, Generator::fill);
        trace_part(query, rays, rows, TraceOutput { hits: &mut hits, counts: &mut counts })
    })?;
    Ok(sum(&stats))
}

/// [`trace_reduced`] in parts of about [`PART_RAYS`] (whole groups of the reduction), each made, traced and reduced
/// by one worker; the parts' partials folded in ray order. The same partial.
pub fn trace_reduced_in_parts(
    query: &Query,
    rays: RaySource<'_>,
    first_ray: u64,
    reduction: &Reduction,
    trace_part: &TracePart<'_>,
) -> Result<(Partial, TraceStats)> {
    let traced = reduction.traced_query(query);
    let layout = traced.output_layout(rays.packed_len(traced.ray_format.size()))?;
    let packed_rows = match rays {
        RaySource::Packed(bytes) => ImageRows::find(traced.ray_format, bytes),
        RaySource::Generated { .. } => None,
    };
    let group = reduction.group_rays();
    let ray_size = traced.ray_format.size();
    let reduced = in_parts(layout.rays, PART_RAYS.div_ceil(group) * group, |scratch, range| {
        let first = first_ray + range.start as u64;
        let rows = part_rows(&rays, &range, packed_rows);
        let part = rays.part(range, ray_size);
        let trace = |rays: &[u8], out: TraceOutput<'_>| trace_part(&traced, rays, rows, out);
        trace_then_reduce(&traced, part, scratch, Generator::fill, trace, |rays, hits, counts| {
            reduction.reduce_piece(&traced, first, rays, hits, counts)
        })
    })?;
    let (partials, stats): (Vec<Partial>, Vec<TraceStats>) = reduced.into_iter().unzip();
    let mut folded = reduction.empty();
    folded.merge_all(partials);
    Ok((folded, sum(&stats)))
}

/// The statistics of a trace's parts added up.
fn sum(parts: &[TraceStats]) -> TraceStats {
    parts.iter().fold(TraceStats::default(), |mut all, part| {
        all.add(part);
        all
    })
}
