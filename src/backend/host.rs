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

use std::cell::RefCell;
use std::ops::Range;
use std::sync::Mutex;

use rayon::prelude::*;

use super::{Backend, BackendAccel, RaySource};
use crate::error::Result;
use crate::format::RayFormat;
use crate::query::{CHUNK_RAYS, ImageRows, Query, TraceOutput, TraceStats, split_from};
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

/// Most bytes of hit records and counts that a backend reducing on the host ([`trace_reduced`]) holds at once.
pub const MOST_REDUCED_HIT_BYTES: usize = 256 << 20;

/// [`Backend::trace_reduced`] with the rays made and the hits reduced on the host: traced with the reduction's
/// [`Reduction::traced_query`] into scratch buffers, then reduced, in slices of whole groups of the reduction
/// whose hits and counts take at most `most_hit_bytes` ([`MOST_REDUCED_HIT_BYTES`] for a GPU: its piece of 2^22
/// generated rays of an `all` query would need 80 GiB at once), the slices' partials folded in ray order.
pub fn trace_reduced<B: Backend + ?Sized>(
    backend: &B,
    accel: &dyn BackendAccel,
    query: &Query,
    rays: RaySource<'_>,
    first_ray: u64,
    reduction: &Reduction,
    most_hit_bytes: usize,
) -> Result<(Partial, TraceStats)> {
    let traced = reduction.traced_query(query);
    let ray_size = traced.ray_format.size();
    let count = traced.output_layout(rays.packed_len(ray_size))?.rays;
    let ray_bytes = traced.records_per_ray() * traced.hit_format.size().unwrap_or(1) + 4;
    let group = reduction.group_rays();
    let slice = (most_hit_bytes / ray_bytes / group).max(1) * group;
    let trace = |rays: &[u8], out: TraceOutput<'_>| backend.trace(accel, &traced, rays, out);
    let mut scratch = PartScratch::default();
    let (mut folded, mut stats) = (reduction.empty(), TraceStats::default());
    for start in (0..count).step_by(slice) {
        let range = start..(start + slice).min(count);
        let first = first_ray + start as u64;
        let (partial, traced_stats) = trace_then_reduce(
            &traced,
            rays.part(range, ray_size),
            &mut scratch,
            Generator::fill_parallel,
            trace,
            |rays, hits, counts| reduction.reduce_piece_parallel(&traced, first, rays, hits, counts),
        )?;
        folded.merge(partial);
        stats.add(&traced_stats);
    }
    Ok((folded, stats))
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

/// The parts of a trace of `rays` rays: [`PART_RAYS`] (rounded up to a multiple of `align`) each; or, for rays that
/// follow image rows (`rows`) whose bands of tiles keep to `align`, about as many rays in whole bands, the first part
/// also taking the rays before the first row start, the last the rest — so that the parts' rays are traced in tiles
/// however wide the image.
fn parts(rays: usize, rows: Option<ImageRows>, align: usize) -> Vec<Range<usize>> {
    let uniform = PART_RAYS.div_ceil(align) * align;
    let Some(rows) = rows.filter(|rows| rows.first.is_multiple_of(align)) else { return split_from(rays, 0, uniform) };
    match rows.bands_of(PART_RAYS, align) {
        Some(part) if part <= 4 * PART_RAYS => split_from(rays, rows.first, part),
        _ => split_from(rays, 0, uniform),
    }
}

thread_local! {
    /// The scratch buffers of the single-part traces a thread runs, kept from one to the next: rayd's CPU workers
    /// trace piece after piece of one part each, which would otherwise each take fresh buffers and have them zeroed
    /// (a part's rays and hits, a few hundred KiB). A thread keeps its largest part's: a few times [`PART_RAYS`]
    /// rays' worth at most ([`parts`]).
    static SINGLE_PART_SCRATCH: RefCell<PartScratch> = RefCell::default();
}

/// Runs `each` on `parts` of a trace (given its index and range), with a worker's scratch buffers, and returns the
/// results in ray order: a single part on the caller's thread with the thread's own buffers, without a hop to the
/// thread pool (rayd's CPU pieces are one part each), more across the pool.
fn in_parts<R: Send>(
    parts: &[Range<usize>],
    each: impl Fn(&mut PartScratch, usize, Range<usize>) -> Result<R> + Sync,
) -> Result<Vec<R>> {
    if let [only] = parts {
        let result = SINGLE_PART_SCRATCH.with(|scratch| match scratch.try_borrow_mut() {
            Ok(mut scratch) => each(&mut scratch, 0, only.clone()),
            // A trace within a trace on this thread (none today) takes buffers of its own.
            Err(_) => each(&mut PartScratch::default(), 0, only.clone()),
        });
        return Ok(vec![result?]);
    }
    (0..parts.len())
        .into_par_iter()
        .map_init(PartScratch::default, |scratch, index| each(scratch, index, parts[index].clone()))
        .collect()
}

/// [`trace_source`] in parts of about [`PART_RAYS`] ([`parts`]): generated rays made a part at a time (packed rays go to
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
    // Parts start on byte boundaries of a bitmask (multiples of 8 rays); each one's records and counts, behind a lock
    // of their own for the worker that traces it.
    let ray_size = query.ray_format.size();
    let parts = parts(layout.rays, part_rows(&rays, &(0..layout.rays), None), 8);
    let outputs: Vec<Mutex<TraceOutput<'_>>> = out.split(query, &parts).into_iter().map(Mutex::new).collect();
    let stats = in_parts(&parts, |scratch, index, range| {
        let TraceOutput { hits, counts } = &mut *outputs[index].lock().unwrap();
        let rows = part_rows(&rays, &range, None);
        let rays = packed_by(rays.part(range, ray_size), query.ray_format, &mut scratch.rays, Generator::fill);
        trace_part(query, rays, rows, TraceOutput { hits, counts })
    })?;
    Ok(sum(&stats))
}

/// [`trace_reduced`] in parts of about [`PART_RAYS`] (whole groups of the reduction: [`parts`]), each made, traced
/// and reduced by one worker; the parts' partials folded in ray order. The same partial.
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
    let ray_size = traced.ray_format.size();
    let parts = parts(layout.rays, part_rows(&rays, &(0..layout.rays), packed_rows), reduction.group_rays());
    let reduced = in_parts(&parts, |scratch, _, range| {
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

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use crate::accel::BuildOptions;
    use crate::backend::cpu::CpuBackend;
    use crate::format::HitFormat;
    use crate::geometry::{BuildInput, TriangleInput};
    use crate::query::QueryKind;
    use crate::raygen::{Camera, PixelSampling};
    use crate::reduce::{Image, ImageChannel, PixelEncoding, PointCloud, PointEncoding};

    #[test]
    fn a_reduction_on_the_host_in_slices_is_the_reduction_traced_whole() {
        // A wavy sheet of 2 × 16 × 16 triangles, two layers of it (so that an `all` query meets several).
        let height = |x: usize, y: usize| ((x * 7 + y * 3) % 5) as f32 * 0.05;
        let mut corners = Vec::new();
        for layer in [0.0f32, 0.5] {
            for (x, y) in (0..=16).flat_map(|y| (0..=16).map(move |x| (x, y))) {
                corners.extend([x as f32, y as f32, height(x, y) + layer]);
            }
        }
        let vertices: Vec<u8> = corners.iter().flat_map(|c| c.to_le_bytes()).collect();
        let at = |layer: usize, x: usize, y: usize| (layer * 17 * 17 + y * 17 + x) as u32;
        let indices: Vec<u8> = (0..2)
            .flat_map(|layer| (0..16).flat_map(move |y| (0..16).map(move |x| (layer, x, y))))
            .flat_map(|(l, x, y)| {
                [at(l, x, y), at(l, x + 1, y), at(l, x, y + 1), at(l, x + 1, y), at(l, x + 1, y + 1), at(l, x, y + 1)]
            })
            .flat_map(u32::to_le_bytes)
            .collect();
        let input = [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
        let accel = CpuBackend::default().build(&input, &BuildOptions::default(), &|| true).unwrap();
        let camera = Camera::framing(Vec3::new(0.0, 0.0, 0.0), Vec3::new(16.0, 16.0, 1.0), 40, 30);
        let generator = Generator::Pinhole(camera, PixelSampling { samples: 3, jitter_seed: Some(4) });
        let rays = RaySource::Generated { generator: &generator, first: 0, count: 3_600 };
        let closest = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        let all = Query { kind: QueryKind::All, max_hits_per_ray: 4, ..closest };
        let cloud = PointCloud { encoding: PointEncoding::Float32, step: 1.0, origin: Vec3::ZERO, ray_indices: true };
        let depths = Image {
            width: 40,
            rays_per_pixel: 3,
            channel: ImageChannel::Depth,
            encoding: PixelEncoding::Float32,
            near: 0.0,
            far: 1.0,
        };
        let cases = [
            (closest, Reduction::Counts),
            (all, Reduction::Histogram { bins: 32, t_min: 0.0, t_max: 40.0 }),
            (all, Reduction::PointCloud(cloud)),
            (closest, Reduction::NearestPerGroup { group: 3 }),
            (closest, Reduction::Image(depths)),
        ];
        for (query, reduction) in cases {
            let reduced = |most_hit_bytes| {
                let (partial, stats) =
                    trace_reduced(&CpuBackend::default(), accel.as_ref(), &query, rays, 7, &reduction, most_hit_bytes)
                        .unwrap();
                (reduction.finish(partial, 3_600).unwrap(), stats.rays)
            };
            let whole = reduced(usize::MAX);
            assert!(!whole.0.bytes.is_empty() && whole.1 == 3_600, "{reduction:?}");
            // Slices of a few groups' hits, the last shorter.
            assert_eq!(reduced(2_000), whole, "{reduction:?} in slices");
        }
    }

    #[test]
    fn parts_are_whole_bands_of_tiles_where_they_keep_to_the_alignment() {
        let lengths = |parts: Vec<Range<usize>>| parts.iter().map(|p| p.len()).collect::<Vec<_>>();
        // No rows: parts of PART_RAYS, the last taking the rest.
        assert_eq!(lengths(parts(3 * PART_RAYS + 5, None, 8)), [PART_RAYS, PART_RAYS, PART_RAYS + 5]);
        // A 4K image's band is larger than a part: a band a part, from the first row start.
        let wide = ImageRows { width: 3840, first: 40 };
        assert_eq!(parts(40 + 3 * 15_360 + 7, Some(wide), 8)[..2], [0..15_400, 15_400..30_760]);
        // 97 pixels of 3 samples a row, images of 3 rays a pixel: seven bands of 1,164 rays a part.
        let sampled = ImageRows { width: 291, first: 0 };
        assert_eq!(lengths(parts(3 * 8_148, Some(sampled), 3)), [8_148; 3]);
        // Groups of 270 rays: the bands that keep to them are too many for a part; parts of whole groups instead.
        assert_eq!(lengths(parts(2 * 8_370, Some(sampled), 270)), [8_370; 2]);
        // Rows wider than anything traced (a generator's range of a huge image): parts of whole groups.
        let huge = ImageRows { width: 1 << 48, first: 0 };
        assert_eq!(lengths(parts(2 * 65_535, Some(huge), 65_535)), [65_535; 2]);
        // Rows that start off the alignment: parts of whole groups.
        assert_eq!(lengths(parts(2 * PART_RAYS, Some(ImageRows { width: 291, first: 5 }), 8)), [PART_RAYS; 2]);
    }
}
