//! Incoherent batches traced in an order that groups rays by where they start and which way they head: the rays of a
//! large batch whose neighbours head different ways (random rays, scattered secondary rays) are copied into
//! [`BUCKETS`] runs — by the octant of their direction and the cell of their origin in a 4×4×4 grid over the batch's
//! origins, each run keeping the batch's order — traced in that order, and their records and counts put back in the
//! caller's order. Rays of one run meet many of the same nodes and triangles one after another, which the caches and
//! the branch predictors then keep: the walk of a million random rays takes 7–19% less time (BENCHMARKS.md,
//! "Incoherent batches traced in runs of neighbours"). The gain needs the whole batch (runs of thousands of rays),
//! so the copies are made with streaming accesses: the rays read in order and written to one of [`BUCKETS`] places,
//! and put back the same way. Coherent batches (a camera's, a lidar's) are traced as they come: their order is as
//! good, and packets need it. Each ray is traced alone either way, so every record, count and statistic is the same.

use glam::Vec3A;
use rayon::prelude::*;

use super::CpuAccel;
use super::bvh::Footprint;
use super::large_pages::LargePageArray;
use crate::error::Result;
use crate::format::RayFormat;
use crate::query::{Query, TraceOutput, TraceStats};

/// Batches of fewer rays are traced as they come: the runs pay only where thousands of rays share each.
pub const MIN_REORDERED_RAYS: usize = 1 << 16;

/// Rays ordered at once, at most: a larger batch is ordered and traced a window of this many rays after another, so
/// that the copies (about 54 bytes a ray for 16-byte records) stay bounded.
pub const WINDOW_RAYS: usize = 1 << 20;

/// Batches through smaller accels are traced as they come: an accel that the processor's caches hold (the 4 MB bunny)
/// gains 5–8% of the walk from the runs, about what making them costs; the 69 MB tiled scene gains 15–20%.
pub const MIN_REORDERED_ACCEL_BYTES: u64 = 16 << 20;

/// Traces the batch `rays` of `query` through `accel` with `trace` ([`crate::query::trace_batch`]'s contract): where
/// the accel takes at least [`MIN_REORDERED_ACCEL_BYTES`] (its own nodes and triangles; an instance accel's children
/// are not counted), window by window of [`WINDOW_RAYS`], each in its [`LocalityOrder`] when it has one; as they come
/// otherwise. The same outputs and statistics either way.
pub fn trace_in_locality_order(
    accel: &CpuAccel,
    query: &Query,
    rays: &[u8],
    out: TraceOutput<'_>,
    trace: impl Fn(&[u8], TraceOutput<'_>) -> Result<TraceStats>,
) -> Result<TraceStats> {
    let size = query.ray_format.size();
    if accel.footprint(Footprint::Exact) < MIN_REORDERED_ACCEL_BYTES || rays.len() < MIN_REORDERED_RAYS * size {
        return trace(rays, out);
    }
    out.check(&query.output_layout(rays.len())?)?;
    // Windows of a multiple of 8 rays (their outputs split on a bitmask's bytes), the last one what is left.
    let count = rays.len() / size;
    let windows: Vec<_> = (0..count).step_by(WINDOW_RAYS).map(|first| first..count.min(first + WINDOW_RAYS)).collect();
    let mut stats = TraceStats::default();
    for (window, out) in windows.iter().zip(out.split(query, &windows)) {
        let rays = &rays[window.start * size..window.end * size];
        stats.add(&match LocalityOrder::of(query, rays) {
            Some(order) => order.trace(query, rays, out, &trace)?,
            None => trace(rays, out)?,
        });
    }
    Ok(stats)
}

/// Pairs of consecutive rays a batch's coherence is judged by, spread over the batch.
const SAMPLED_PAIRS: usize = 256;

/// Two consecutive rays are coherent when their directions are at most about 11° apart (the cosine of the angle
/// between them at least this); a batch is reordered when fewer than half of its sampled pairs are.
const COHERENT_COSINE: f32 = 0.98;

/// Rays whose origins bound the grid of cells (a box of every origin would take a pass over the batch).
const SAMPLED_ORIGINS: usize = 1024;

/// Cells along each axis of the batch's box of origins.
const CELLS: u32 = 4;

/// The last cell's index, as a float.
const LAST_CELL: f32 = (CELLS - 1) as f32;

/// Runs a reordered batch is traced in: an octant and an origin cell each.
const BUCKETS: usize = 8 * (CELLS * CELLS * CELLS) as usize;

/// Rays a task of the parallel passes takes.
const TASK_RAYS: usize = 1 << 14;

/// Where each ray of a batch is traced: its place in an order that runs through the batch's rays octant by octant and
/// cell by cell ([`LocalityOrder::of`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LocalityOrder {
    /// For each ray, its place in tracing order: a permutation of the batch's indices (by construction: the
    /// counting sort of [`LocalityOrder::of`] hands out each bucket's run of places once each).
    places: Vec<u32>,
}

impl LocalityOrder {
    /// The order for the batch `rays` of `query`, or `None` when it is traced as it comes: fewer than
    /// [`MIN_REORDERED_RAYS`] rays or more than [`WINDOW_RAYS`], or a coherent batch (at least half of
    /// [`SAMPLED_PAIRS`] pairs of consecutive rays, spread over the batch, head within about 11° of each other).
    pub fn of(query: &Query, rays: &[u8]) -> Option<LocalityOrder> {
        let format = query.ray_format;
        let size = format.size();
        let count = rays.len() / size;
        if !(MIN_REORDERED_RAYS..=WINDOW_RAYS).contains(&count) {
            return None;
        }
        let direction = |i: usize| format.decode(&rays[i * size..(i + 1) * size]).direction;
        let step = (count - 1) / SAMPLED_PAIRS;
        let coherent = (0..SAMPLED_PAIRS)
            .filter(|k| {
                let (a, b) = (direction(k * step), direction(k * step + 1));
                a.dot(b) >= COHERENT_COSINE * (a.length_squared() * b.length_squared()).sqrt()
            })
            .count();
        if 2 * coherent >= SAMPLED_PAIRS {
            return None;
        }
        let buckets = buckets(format, rays);
        // A counting sort across the rayon pool: each task's rays of a bucket are placed after the earlier tasks'
        // rays of that bucket, which follow the earlier buckets' runs.
        let counts: Vec<[u32; BUCKETS]> = buckets
            .par_chunks(TASK_RAYS)
            .map(|task| {
                let mut counts = [0u32; BUCKETS];
                for &bucket in task {
                    counts[usize::from(bucket)] += 1;
                }
                counts
            })
            .collect();
        let mut firsts = vec![[0u32; BUCKETS]; counts.len()];
        let mut next = 0;
        for bucket in 0..BUCKETS {
            for (firsts, counts) in firsts.iter_mut().zip(&counts) {
                (firsts[bucket], next) = (next, next + counts[bucket]);
            }
        }
        let mut places = vec![0u32; count];
        let tasks = places.par_chunks_mut(TASK_RAYS).zip(buckets.par_chunks(TASK_RAYS));
        tasks.zip(firsts).for_each(|((places, buckets), mut next)| {
            for (place, &bucket) in places.iter_mut().zip(buckets) {
                *place = next[usize::from(bucket)];
                next[usize::from(bucket)] += 1;
            }
        });
        Some(LocalityOrder { places })
    }

    /// Traces the batch `rays` of `query` with `trace` ([`crate::query::trace_batch`]'s contract) in this order:
    /// the rays copied into it, traced into scratch outputs, each ray's records and count put back in its place in
    /// `out`. The copies lie on large pages where Linux gives them (fewer page faults and address translations).
    pub fn trace(
        &self,
        query: &Query,
        rays: &[u8],
        out: TraceOutput<'_>,
        trace: impl FnOnce(&[u8], TraceOutput<'_>) -> Result<TraceStats>,
    ) -> Result<TraceStats> {
        out.check(&query.output_layout(rays.len())?)?;
        let mut ordered = LargePageArray::zeroed(rays.len());
        // SAFETY: `places` is a permutation (the type's invariant).
        for_item_size(query.ray_format.size(), |item| unsafe { scatter(item, rays, &mut ordered, &self.places) });
        let (mut hits, mut counts) = (LargePageArray::zeroed(out.hits.len()), LargePageArray::zeroed(out.counts.len()));
        let stats = trace(&ordered, TraceOutput { hits: &mut hits, counts: &mut counts })?;
        let records = query.records_per_ray();
        match query.hit_format.size() {
            Some(size) => for_item_size(records * size, |item| gather(item, &hits, out.hits, &self.places)),
            None => gather_bits(records, &hits, out.hits, &self.places),
        }
        for_item_size(4, |item| gather(item, &counts, out.counts, &self.places));
        Ok(stats)
    }
}

/// Each ray's bucket: the octant of its direction (sign bits, z highest), then its origin's cell (x fastest) in the
/// box of the origins of [`SAMPLED_ORIGINS`] rays spread over the batch (an origin outside it counts in the nearest
/// cell). Made across the rayon pool.
fn buckets(format: RayFormat, rays: &[u8]) -> Vec<u16> {
    let size = format.size();
    let count = rays.len() / size;
    let origin = |i: usize| format.decode(&rays[i * size..(i + 1) * size]).origin;
    let sampled = (0..SAMPLED_ORIGINS).map(|k| origin(k * (count - 1) / (SAMPLED_ORIGINS - 1)));
    let (lo, hi) = sampled.fold((Vec3A::INFINITY, Vec3A::NEG_INFINITY), |(lo, hi), o| (lo.min(o), hi.max(o)));
    // A box of no width, or not finite, puts every origin in cell 0 along that axis. (Arrays, not `Vec3A`s: glam's
    // indexing of a `Vec3A` by a variable is a chain of selects.)
    let scale = (Vec3A::splat(CELLS as f32) / (hi - lo)).to_array().map(|s| if s.is_finite() { s } else { 0.0 });
    let lo = lo.to_array();
    let bucket = |format: RayFormat, bytes: &[u8]| {
        let ray = format.decode(bytes);
        let (d, origin) = (ray.direction, ray.origin.to_array());
        let octant = u32::from(d.x < 0.0) | u32::from(d.y < 0.0) << 1 | u32::from(d.z < 0.0) << 2;
        // Clamped to the grid (a NaN stays NaN, which `as` takes to 0), so every origin falls in a cell.
        let cell = |axis: usize| ((origin[axis] - lo[axis]) * scale[axis]).clamp(0.0, LAST_CELL) as u32;
        (((octant * CELLS + cell(2)) * CELLS + cell(1)) * CELLS + cell(0)) as u16
    };
    let mut buckets = vec![0u16; count];
    buckets.par_chunks_mut(TASK_RAYS).zip(rays.par_chunks(TASK_RAYS * size)).for_each(|(buckets, task)| {
        // A loop compiled once a ray format, without a match a ray.
        format.specialized(|format| {
            for (to, bytes) in buckets.iter_mut().zip(task.chunks_exact(size)) {
                *to = bucket(format, bytes);
            }
        })
    });
    buckets
}

/// The sizes of the items that are copied: rays, records, counts (so that each copy is compiled for its size; a copy
/// of a size known only at run time is a call).
#[derive(Clone, Copy)]
enum ItemSize {
    /// One of the sizes rays, records and counts come in.
    Known(usize),
    /// Another (a record of several hits).
    Other(usize),
}

/// Calls `copy` with `bytes` as an [`ItemSize`].
fn for_item_size(bytes: usize, copy: impl FnOnce(ItemSize)) {
    copy(match bytes {
        4 | 8 | 12 | 16 | 20 | 24 | 32 | 36 | 48 | 80 => ItemSize::Known(bytes),
        _ => ItemSize::Other(bytes),
    })
}

/// Copies each `item`-sized item `i` of `from` to place `places[i]` of `to`, across the rayon pool: read in order,
/// written to the runs.
///
/// # Safety
/// `places` must not hold an index twice (tasks on other threads write to `to` at once, each its own places).
unsafe fn scatter(item: ItemSize, from: &[u8], to: &mut [u8], places: &[u32]) {
    macro_rules! sized {
        ($($n:literal)*) => {
            match item {
                $(ItemSize::Known($n) => {
                    let to = SharedItems::<$n>::new(to);
                    from.as_chunks::<$n>().0.par_chunks(TASK_RAYS).zip(places.par_chunks(TASK_RAYS)).for_each(
                        |(from, places)| {
                            for (item, &place) in from.iter().zip(places) {
                                // SAFETY: no other task writes this place (the contract).
                                unsafe { to.write(place as usize, item) };
                            }
                        },
                    );
                })*
                ItemSize::Known(n) | ItemSize::Other(n) => {
                    for (item, &place) in from.chunks_exact(n).zip(places) {
                        to[place as usize * n..][..n].copy_from_slice(item);
                    }
                }
            }
        };
    }
    sized!(4 8 12 16 20 24 32 36 48 80);
}

/// A buffer of `N`-byte items that tasks on several threads write at once, each to items no other task writes.
struct SharedItems<'a, const N: usize> {
    /// The first item.
    start: *mut [u8; N],
    /// Items.
    len: usize,
    /// The buffer is borrowed mutably for `'a`.
    _buffer: std::marker::PhantomData<&'a mut [u8]>,
}

// SAFETY: writes from several threads go to distinct items (the contract of `SharedItems::write`).
unsafe impl<const N: usize> Sync for SharedItems<'_, N> {}

impl<'a, const N: usize> SharedItems<'a, N> {
    /// `buffer`'s whole items.
    fn new(buffer: &'a mut [u8]) -> Self {
        let items = buffer.as_chunks_mut::<N>().0;
        SharedItems { start: items.as_mut_ptr(), len: items.len(), _buffer: std::marker::PhantomData }
    }

    /// Writes item `index` (panics past the last).
    ///
    /// # Safety
    /// No other thread may write or read item `index` while the buffer is shared.
    #[inline(always)]
    unsafe fn write(&self, index: usize, item: &[u8; N]) {
        assert!(index < self.len, "item {index} of {}", self.len);
        // SAFETY: within the buffer (checked above), which lives for 'a; nobody else touches the item (the contract).
        unsafe { self.start.add(index).write(*item) };
    }
}

/// Copies to each `item`-sized item `i` of `to` the item at place `places[i]` of `from`: written in order, read from
/// the runs; across the rayon pool.
fn gather(item: ItemSize, from: &[u8], to: &mut [u8], places: &[u32]) {
    macro_rules! sized {
        ($($n:literal)*) => {
            match item {
                $(ItemSize::Known($n) => {
                    let from = from.as_chunks::<$n>().0;
                    let to = to.as_chunks_mut::<$n>().0;
                    to.par_chunks_mut(TASK_RAYS).zip(places.par_chunks(TASK_RAYS)).for_each(|(to, places)| {
                        for (item, &place) in to.iter_mut().zip(places) {
                            *item = from[place as usize];
                        }
                    });
                })*
                ItemSize::Known(n) | ItemSize::Other(n) => {
                    to.par_chunks_mut(TASK_RAYS * n).zip(places.par_chunks(TASK_RAYS)).for_each(|(to, places)| {
                        for (item, &place) in to.chunks_exact_mut(n).zip(places) {
                            item.copy_from_slice(&from[place as usize * n..][..n]);
                        }
                    });
                }
            }
        };
    }
    sized!(4 8 12 16 20 24 32 36 48 80);
}

/// [`gather`] for a bitmask, `records` bits a ray (the last byte's unused bits left clear).
fn gather_bits(records: usize, from: &[u8], to: &mut [u8], places: &[u32]) {
    let bits = places.len() * records;
    let bit = |record: usize| {
        let (ray, within) = (record / records, record % records);
        let at = places[ray] as usize * records + within;
        from[at / 8] >> (at % 8) & 1
    };
    to.par_chunks_mut(TASK_RAYS).enumerate().for_each(|(task, bytes)| {
        for (offset, byte) in bytes.iter_mut().enumerate() {
            let first = (task * TASK_RAYS + offset) * 8;
            *byte = (first..(first + 8).min(bits)).fold(0, |byte, record| byte | bit(record) << (record - first));
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::{HitFormat, Ray};
    use crate::query::QueryKind;

    /// `count` rays packed `origin_tmin_direction_tmax`, each made by `ray` from its index.
    fn packed(count: usize, ray: impl Fn(usize) -> Ray) -> Vec<u8> {
        let format = RayFormat::OriginTminDirectionTmax;
        let mut bytes = vec![0u8; count * format.size()];
        for (i, record) in bytes.chunks_exact_mut(format.size()).enumerate() {
            format.encode(&ray(i), record);
        }
        bytes
    }

    /// A ray whose numbers come from `i` by a hash: scattered origins and directions.
    fn scattered(i: usize) -> Ray {
        let u = |k: u64| {
            let x = (i as u64 * 8 + k + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            ((x ^ x >> 29).wrapping_mul(0xBF58_476D_1CE4_E5B9) >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
        };
        Ray {
            origin: Vec3A::new(u(0), u(1), u(2)) * 10.0,
            direction: Vec3A::new(u(3), u(4), u(5)),
            tmax: f32::INFINITY,
            ..Ray::default()
        }
    }

    #[test]
    fn incoherent_batches_run_through_octants_then_cells_in_their_order_and_coherent_ones_are_not_reordered() {
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        let format = query.ray_format;
        let rays = packed(MIN_REORDERED_RAYS, scattered);
        let order = LocalityOrder::of(&query, &rays).expect("scattered rays are reordered");
        // Ray indices in tracing order.
        let mut traced = vec![u32::MAX; MIN_REORDERED_RAYS];
        for (ray, &place) in order.places.iter().enumerate() {
            traced[place as usize] = ray as u32;
        }
        assert!(!traced.contains(&u32::MAX), "a permutation");
        let ray = |i: u32| format.decode(&rays[i as usize * format.size()..][..format.size()]);
        // The bucket of each ray as the order's rule says, computed apart: octant (z's sign highest), then the cell
        // in the box of origins, which these rays fill to within a few thousandths.
        let bucket = |i: u32| {
            let r = ray(i);
            let octant = (r.direction.z < 0.0, r.direction.y < 0.0, r.direction.x < 0.0);
            let cell = ((r.origin + 10.0) / 5.0).floor().clamp(Vec3A::ZERO, Vec3A::splat(3.0));
            (octant, cell.z as u32, cell.y as u32, cell.x as u32)
        };
        let buckets = buckets(format, &rays);
        let off_cell = traced.iter().filter(|&&i| {
            let (o, z, y, x) = bucket(i);
            let expected = (((u32::from(o.0) * 4 + u32::from(o.1) * 2 + u32::from(o.2)) * 4 + z) * 4 + y) * 4 + x;
            u32::from(buckets[i as usize]) != expected
        });
        assert!(off_cell.count() < MIN_REORDERED_RAYS / 100, "rays on the cells' borders may differ, few others");
        // Runs by bucket, each ray after the earlier rays of its bucket.
        assert!(traced.windows(2).all(|w| (buckets[w[0] as usize], w[0]) < (buckets[w[1] as usize], w[1])));
        assert!(buckets.iter().collect::<std::collections::HashSet<_>>().len() == BUCKETS, "every bucket used");

        // Too few rays, or a camera's (neighbours heading the same way), are traced as they come.
        assert_eq!(LocalityOrder::of(&query, &packed(MIN_REORDERED_RAYS - 1, scattered)), None);
        let fan = |i: usize| Ray { direction: Vec3A::new(1.0, i as f32 * 1e-5, 0.5), ..scattered(i) };
        assert_eq!(LocalityOrder::of(&query, &packed(MIN_REORDERED_RAYS, fan)), None);
    }

    #[test]
    fn a_large_accel_gives_every_query_the_same_outputs_in_locality_order_as_in_the_batchs() {
        // A wavy terrain of 2 · 419² triangles: an accel above the size that is reordered.
        let n = 420u32;
        let height = |x: u32, y: u32| ((x as f32 * 0.37).sin() + (y as f32 * 0.23).cos()) * 3.0;
        let positions = (0..n * n).map(|i| glam::Vec3::new((i % n) as f32, (i / n) as f32, height(i % n, i / n)));
        let quads = (0..n - 1).flat_map(|y| (0..n - 1).map(move |x| y * n + x));
        let triangles = quads.flat_map(|v| [[v, v + 1, v + n + 1], [v, v + n + 1, v + n]]).collect();
        let mesh = crate::mesh::Mesh { positions: positions.collect(), triangles };
        let packed = mesh.pack();
        let context = crate::Context::new(crate::Device::cpu());
        let input = [crate::geometry::BuildInput::Triangles(packed.input())];
        let accel = context.build_accel(&input, &crate::accel::BuildOptions::default()).unwrap();
        // Its size as allocated is at least its exact footprint, which decides; both are far above the threshold.
        let size = accel.info().size_bytes;
        assert!(size >= MIN_REORDERED_ACCEL_BYTES + (MIN_REORDERED_ACCEL_BYTES >> 2), "{size} bytes");
        // Random rays through the terrain's box, one window and a bit more.
        let (lo, hi) = mesh.bounds();
        let format = RayFormat::OriginTminDirectionTmax;
        let rays = crate::raygen::random_rays(lo - 5.0, hi + 5.0, WINDOW_RAYS + 24, 3, format);
        for (kind, hit_format) in [
            (QueryKind::Closest, HitFormat::TTriidUV),
            (QueryKind::Any, HitFormat::Bitmask),
            (QueryKind::All, HitFormat::T),
            (QueryKind::Count, HitFormat::TTriid),
        ] {
            let query = Query { kind, max_hits_per_ray: 3, ..Query::closest(format, hit_format) };
            assert!(LocalityOrder::of(&query, &rays[..WINDOW_RAYS * format.size()]).is_some(), "reordered");
            let layout = query.output_layout(rays.len()).unwrap();
            let (mut hits, mut counts) = (vec![0xA5; layout.hits], vec![0xA5; layout.counts]);
            let stats = context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut counts });
            // The same rays in pieces too small to be reordered, in their order.
            let pieces = crate::query::split_from(rays.len() / format.size(), 0, MIN_REORDERED_RAYS / 2);
            let (mut piece_hits, mut piece_counts) = (vec![0x5A; layout.hits], vec![0x5A; layout.counts]);
            let out = TraceOutput { hits: &mut piece_hits, counts: &mut piece_counts };
            let mut piece_stats = TraceStats::default();
            for (piece, out) in pieces.iter().zip(out.split(&query, &pieces)) {
                let rays = &rays[piece.start * format.size()..piece.end * format.size()];
                piece_stats.add(&context.trace(&accel, &query, rays, out).unwrap());
            }
            let case = format!("{} {}", kind.name(), hit_format.name());
            assert!(hits == piece_hits, "{case}: hits");
            assert!(counts == piece_counts, "{case}: counts");
            let stats = stats.unwrap();
            assert_eq!((stats.rays, stats.rays_hit), (piece_stats.rays, piece_stats.rays_hit), "{case}");
            let work = |s: &TraceStats| (s.nodes_visited, s.triangle_tests);
            assert_eq!(work(&stats), work(&piece_stats), "{case}");
            assert!(stats.rays_hit > stats.rays / 10 && stats.rays_hit < stats.rays, "{case}: {stats:?}");
        }
    }

    #[test]
    fn records_and_counts_are_put_back_in_the_callers_order() {
        // A stand-in trace that marks each ray it is given with its index (kept in the origin's x) in every byte of
        // its records and count, or in its bitmask bits: each ray's outputs must come back in its own place.
        let format = RayFormat::OriginTminDirectionTmax;
        let count = MIN_REORDERED_RAYS + 3;
        let rays = packed(count, |i| Ray { origin: Vec3A::new(i as f32, 0.0, 0.0), ..scattered(i) });
        let label = |i: usize| (i % 251) as u8;
        let marked = |i: usize, within: usize| i.is_multiple_of(3) != (within == 1);
        for hit_format in HitFormat::ALL {
            for (kind, max_hits) in [(QueryKind::Closest, 1), (QueryKind::All, 2), (QueryKind::Count, 1)] {
                let query = Query { kind, max_hits_per_ray: max_hits, ..Query::closest(format, hit_format) };
                let order = LocalityOrder::of(&query, &rays).expect("reordered");
                let layout = query.output_layout(rays.len()).unwrap();
                let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
                let records = query.records_per_ray();
                let record = hit_format.size().map(|size| size * records);
                let out = TraceOutput { hits: &mut hits, counts: &mut counts };
                let stats = order.trace(&query, &rays, out, |ordered, out| {
                    for (j, ray) in ordered.chunks_exact(format.size()).enumerate() {
                        let i = format.decode(ray).origin.x as usize;
                        match record {
                            Some(record) => out.hits[j * record..][..record].fill(label(i)),
                            None => (0..records).filter(|&within| marked(i, within)).for_each(|within| {
                                out.hits[(j * records + within) / 8] |= 1 << ((j * records + within) % 8);
                            }),
                        }
                        if !out.counts.is_empty() {
                            out.counts[j * 4..][..4].fill(label(i));
                        }
                    }
                    Ok(TraceStats { rays: 7, ..TraceStats::default() })
                });
                let case = format!("{} {}", hit_format.name(), kind.name());
                assert_eq!(stats.unwrap().rays, 7, "{case}: the trace's statistics");
                match record {
                    Some(record) => assert!(
                        hits.chunks_exact(record).enumerate().all(|(i, r)| r.iter().all(|&b| b == label(i))),
                        "{case}"
                    ),
                    None => {
                        let bit = |at: usize| hits[at / 8] >> (at % 8) & 1 == 1;
                        assert!((0..count * records).all(|at| bit(at) == marked(at / records, at % records)), "{case}");
                        assert!((count * records..hits.len() * 8).all(|at| !bit(at)), "{case}: unused bits clear");
                    }
                }
                assert!(counts.chunks_exact(4).enumerate().all(|(i, c)| c.iter().all(|&b| b == label(i))), "{case}");
            }
        }
    }
}
