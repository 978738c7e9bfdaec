//! Reductions: a trace's hits summed up where they are traced, so that a caller who wants a picture, a point
//! cloud or a few numbers receives that instead of every hit record.
//!
//! A trace with a reduction is traced piece by piece as usual, each piece into a scratch hit buffer of the format
//! the reduction needs ([`Reduction::traced_query`]); each piece is reduced on its own into a [`Partial`]
//! ([`Reduction::reduce_piece`]), and the partials are folded in ray order ([`Partial::merge`]) and encoded once
//! at the end ([`Reduction::finish`]). Pieces never split a group of rays that reduce together
//! ([`Reduction::group_rays`]), so the result does not depend on how the batch was cut.

mod cloud;
mod compact;
mod image;
mod partial;

pub use cloud::{PointCloud, PointEncoding};
pub use compact::{COMPACT_BLOCK_RAYS, decode_compact};
pub use image::{Image, ImageChannel, PixelEncoding};
pub use partial::Partial;

use bytes::Bytes;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::format::HitFormat;
use crate::query::{Query, QueryKind};

/// Rays of the parts a large piece is split into, to be generated and reduced across the rayon pool.
pub const PARALLEL_SPLIT_RAYS: usize = 1 << 14;

/// Most rays a group (an image's pixel, a nearest-hit group) may have.
pub const MAX_GROUP_RAYS: u32 = 1 << 16;
/// Most bins of a histogram.
pub const MAX_HISTOGRAM_BINS: u32 = 1 << 20;

/// What a trace answers instead of every hit record.
#[derive(Debug, Clone, PartialEq)]
pub enum Reduction {
    /// Three little-endian u64: rays, rays with a hit, and hits (the sum of the counts for `all` and `count`
    /// queries; equal to rays with a hit otherwise).
    Counts,
    /// An image of the nearest hit of each pixel's rays ([`Image`]).
    Image(Image),
    /// How many hit records fall in each of `bins` equal bins of `t` over `[t_min, t_max)`: `bins + 2`
    /// little-endian u64, the bins in order, then the hits below `t_min`, then those at or above `t_max`.
    Histogram {
        /// Number of bins, 1 to [`MAX_HISTOGRAM_BINS`].
        bins: u32,
        /// Start of the first bin (finite).
        t_min: f32,
        /// End of the last bin (finite, above `t_min`).
        t_max: f32,
    },
    /// Hit records per id: 12 bytes per id that was hit at least once, by ascending id as i32 (−1, "none",
    /// first): id i32 | count u64.
    IdCounts(IdKind),
    /// The nearest hit of each group of `group` consecutive rays, one record a group in the query's hit format
    /// (a group whose rays all missed reports a miss; of equal `t`, the first ray's hit).
    NearestPerGroup {
        /// Rays a group, 1 to [`MAX_GROUP_RAYS`]; the batch must be a whole number of groups.
        group: u32,
    },
    /// The hit points, in ray order ([`PointCloud`]).
    PointCloud(PointCloud),
    /// Every ray's hit in the query's hit format, compactly: `t` in 16 bits of the ray's range, ids delta-encoded
    /// as varints, `u`, `v` in 16 bits (layout in [`decode_compact`]'s module).
    CompactHits {
        /// Where the range of a ray without a finite `tmax` ends (finite, > 0).
        t_far: f32,
    },
}

/// Which id [`Reduction::IdCounts`] counts by.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IdKind {
    /// The user id of the instance just above the geometry (−1 outside instances).
    Instance,
    /// The index of the build input.
    Geometry,
    /// The primitive id.
    Primitive,
}

impl Reduction {
    /// Checks the reduction against the query and the batch's `rays`: INVALID_ARGUMENT naming the field.
    pub fn check(&self, query: &Query, rays: u64) -> Result<()> {
        let needs_one_hit_a_ray = || match query.kind {
            QueryKind::Closest | QueryKind::Any => Ok(()),
            kind => {
                Err(invalid("query.query", format!("this reduction needs a closest or any query, not {}", kind.name())))
            }
        };
        match self {
            Reduction::Counts => Ok(()),
            Reduction::Image(image) => {
                needs_one_hit_a_ray()?;
                image.check(rays)
            }
            Reduction::Histogram { bins, t_min, t_max } => {
                if *bins == 0 || *bins > MAX_HISTOGRAM_BINS {
                    return Err(invalid(
                        "reduction.histogram.bins",
                        format!("{bins} is not in 1..={MAX_HISTOGRAM_BINS}"),
                    ));
                }
                if !(t_min.is_finite() && t_max.is_finite() && t_min < t_max) {
                    let rule = format!("[{t_min}, {t_max}) must be finite and non-empty");
                    let field =
                        if t_min.is_finite() { "reduction.histogram.t_max" } else { "reduction.histogram.t_min" };
                    return Err(invalid(field, rule));
                }
                Ok(())
            }
            Reduction::IdCounts(_) => Ok(()),
            Reduction::NearestPerGroup { group } => {
                needs_one_hit_a_ray()?;
                if query.hit_format == HitFormat::Bitmask {
                    return Err(invalid(
                        "query.hit_format",
                        "a nearest hit needs a hit format with t, not bitmask".into(),
                    ));
                }
                check_groups("reduction.nearest.group", *group, rays)
            }
            Reduction::PointCloud(cloud) => cloud.check(rays),
            Reduction::CompactHits { t_far } => {
                needs_one_hit_a_ray()?;
                compact::check(query, *t_far)
            }
        }
    }

    /// Whether pieces' partials fold into the same answer in any order (counters that add up), so that a trace may
    /// fold each piece's as it comes instead of keeping them all until the last.
    pub fn folds_in_any_order(&self) -> bool {
        matches!(self, Reduction::Counts | Reduction::Histogram { .. } | Reduction::IdCounts(_))
    }

    /// The answer's bytes for a batch of `rays` rays, where they are known before the trace: counts, a histogram, an
    /// image not compressed, a nearest hit a group.
    pub fn answer_bytes(&self, query: &Query, rays: u64) -> Option<u64> {
        match self {
            Reduction::Counts => Some(24),
            Reduction::Histogram { bins, .. } => Some((u64::from(*bins) + 2) * 8),
            Reduction::Image(image) if image.encoding != PixelEncoding::Png => {
                Some(rays / u64::from(image.rays_per_pixel) * image.pixel_bytes() as u64)
            }
            Reduction::NearestPerGroup { group } => {
                Some(rays / u64::from(*group) * query.hit_format.size().unwrap_or(0) as u64)
            }
            _ => None,
        }
    }

    /// Whether the answer holds every byte of the pieces' [`Partial::Ordered`] records (all but a PNG image, which
    /// compresses them): while the pieces come, their records' bytes tell what the answer will at least take.
    pub fn answer_holds_the_records(&self) -> bool {
        !matches!(self, Reduction::Image(Image { encoding: PixelEncoding::Png, .. }))
    }

    /// Consecutive rays that reduce together and so must be traced in one piece.
    pub fn group_rays(&self) -> usize {
        match self {
            Reduction::Image(image) => image.rays_per_pixel as usize,
            Reduction::NearestPerGroup { group } => *group as usize,
            Reduction::CompactHits { .. } => COMPACT_BLOCK_RAYS as usize,
            _ => 1,
        }
    }

    /// The query each piece is traced with: `query` with the smallest hit format that carries what the reduction
    /// needs, and counts of a closest-hit query traced as an any-hit one (whether a ray hits is the same either way,
    /// and an any-hit walk stops at the first hit it finds).
    pub fn traced_query(&self, query: &Query) -> Query {
        let hit_format = match self {
            // A bit a record says hit or miss (`Hit::is_hit`, a hit behind the ray's origin too): all counts need.
            Reduction::Counts => HitFormat::Bitmask,
            // The primitive id tells a hit behind the ray's origin from a miss (`Hit::is_hit`).
            Reduction::Histogram { .. } | Reduction::PointCloud(_) => HitFormat::TTriid,
            Reduction::Image(image) => image.channel.hit_format(),
            Reduction::IdCounts(IdKind::Instance) => HitFormat::TTriidInstid,
            Reduction::IdCounts(IdKind::Geometry) => HitFormat::Full,
            Reduction::IdCounts(IdKind::Primitive) => HitFormat::TTriid,
            Reduction::NearestPerGroup { .. } | Reduction::CompactHits { .. } => query.hit_format,
        };
        let kind = match (self, query.kind) {
            (Reduction::Counts, QueryKind::Closest) => QueryKind::Any,
            (_, kind) => kind,
        };
        Query { hit_format, kind, ..*query }
    }

    /// Reduces one traced piece: its `rays` (packed in `traced.ray_format`, the first being ray `first_ray` of the
    /// batch), their `hits` and `counts` as traced with `traced` ([`Reduction::traced_query`]).
    pub fn reduce_piece(&self, traced: &Query, first_ray: u64, rays: &[u8], hits: &[u8], counts: &[u8]) -> Partial {
        // The loops below compiled once a hit format, each record read without a match on it.
        traced.hit_format.specialized(
            #[inline(always)]
            |hit_format| self.reduce_records(&Query { hit_format, ..*traced }, first_ray, rays, hits, counts),
        )
    }

    /// [`Reduction::reduce_piece`] for a hit format known where it is inlined.
    #[inline(always)]
    fn reduce_records(&self, traced: &Query, first_ray: u64, rays: &[u8], hits: &[u8], counts: &[u8]) -> Partial {
        let ray_count = rays.len() / traced.ray_format.size();
        let records = traced.records_per_ray();
        let hit_records =
            || (0..ray_count * records).map(move |i| traced.hit_format.read(hits, i)).filter(|hit| hit.is_hit());
        match self {
            Reduction::Counts => {
                let rays_hit = match (traced.hit_format, records) {
                    // A bit a ray (the bitmask counts are traced in): whole bytes counted at once.
                    (HitFormat::Bitmask, 1) => {
                        let whole = hits[..ray_count / 8].iter().map(|byte| u64::from(byte.count_ones())).sum::<u64>();
                        let rest = (ray_count / 8 * 8..ray_count).filter(|&ray| hits[ray / 8] & (1 << (ray % 8)) != 0);
                        whole + rest.count() as u64
                    }
                    _ => (0..ray_count).filter(|&ray| traced.hit_format.hit_t(hits, ray * records).is_some()).count()
                        as u64,
                };
                let hit_total = match traced.kind.has_counts() {
                    true => counts.chunks_exact(4).map(|c| u64::from(u32::from_le_bytes(c.try_into().unwrap()))).sum(),
                    false => rays_hit,
                };
                Partial::Sums(vec![ray_count as u64, rays_hit, hit_total])
            }
            Reduction::Histogram { bins, t_min, t_max } => {
                let width = (f64::from(*t_max) - f64::from(*t_min)) / f64::from(*bins);
                let slot = |t: f32| {
                    if t < *t_min {
                        *bins
                    } else if t >= *t_max {
                        *bins + 1
                    } else {
                        (((f64::from(t) - f64::from(*t_min)) / width) as u32).min(*bins - 1)
                    }
                };
                let slots = (0..ray_count * records).filter_map(|i| traced.hit_format.hit_t(hits, i)).map(slot);
                Partial::counted(*bins as usize + 2, slots, ray_count * records)
            }
            Reduction::IdCounts(kind) => {
                let mut counts = std::collections::BTreeMap::new();
                for hit in hit_records() {
                    let id = match kind {
                        IdKind::Instance => hit.inst_id,
                        IdKind::Geometry => hit.geom_id,
                        IdKind::Primitive => hit.prim_id,
                    };
                    *counts.entry(id as i32).or_insert(0u64) += 1;
                }
                Partial::Keyed(counts)
            }
            Reduction::NearestPerGroup { group } => {
                let size = traced.hit_format.size().expect("checked: not a bitmask");
                let mut out = Vec::with_capacity(ray_count / *group as usize * size);
                for first in (0..ray_count).step_by(*group as usize) {
                    let nearest = nearest(traced.hit_format, hits, first..first + *group as usize);
                    out.extend_from_slice(&hits[nearest * size..(nearest + 1) * size]);
                }
                Partial::Ordered { bytes: out, dropped: 0 }
            }
            Reduction::Image(image) => {
                Partial::Ordered { bytes: image.pixels(traced.hit_format, hits, ray_count), dropped: 0 }
            }
            Reduction::PointCloud(cloud) => cloud.reduce(traced, first_ray, rays, hits),
            Reduction::CompactHits { t_far } => compact::encode(traced, *t_far, first_ray, rays, hits),
        }
    }

    /// [`Reduction::reduce_piece`] of a large piece, split into parts of about [`PARALLEL_SPLIT_RAYS`] rays (whole
    /// groups) reduced on the rayon pool and folded in order: the same partial, sooner.
    pub fn reduce_piece_parallel(
        &self,
        traced: &Query,
        first_ray: u64,
        rays: &[u8],
        hits: &[u8],
        counts: &[u8],
    ) -> Partial {
        let group = self.group_rays();
        let split = (PARALLEL_SPLIT_RAYS / group).max(1) * group;
        let (ray_size, records) = (traced.ray_format.size(), traced.records_per_ray());
        // Where the records of a part begin (a bitmask is traced only for counts, whose parts of 2^14 rays begin on
        // byte boundaries).
        let hits_before = |rays: usize| traced.hit_format.buffer_len(rays * records);
        let count_size = if counts.is_empty() { 0 } else { 4 };
        let ray_count = rays.len() / ray_size;
        let parts: Vec<Partial> = (0..ray_count.div_ceil(split))
            .into_par_iter()
            .map(|part| {
                let range = part * split..((part + 1) * split).min(ray_count);
                self.reduce_piece(
                    traced,
                    first_ray + range.start as u64,
                    &rays[range.start * ray_size..range.end * ray_size],
                    &hits[hits_before(range.start)..hits_before(range.end)],
                    &counts[range.start * count_size..range.end * count_size],
                )
            })
            .collect();
        let mut folded = self.empty();
        folded.merge_all(parts);
        folded
    }

    /// The reduction's answer from every piece's partial folded in ray order, for a batch of `rays` rays.
    pub fn finish(&self, folded: Partial, rays: u64) -> Result<Reduced> {
        let (bytes, dropped) = match folded {
            Partial::Sums(sums) => (sums.iter().flat_map(|s| s.to_le_bytes()).collect(), 0),
            Partial::SparseSums { len, counts } => {
                let mut bytes = vec![0u8; len * 8];
                for (index, count) in counts {
                    bytes[index as usize * 8..][..8].copy_from_slice(&count.to_le_bytes());
                }
                (bytes, 0)
            }
            Partial::Keyed(counts) => {
                let pairs =
                    counts.iter().flat_map(|(id, count)| id.to_le_bytes().into_iter().chain(count.to_le_bytes()));
                (pairs.collect(), 0)
            }
            Partial::Ordered { bytes, dropped } => match self {
                Reduction::Image(image) => (image.finish(bytes, rays)?, dropped),
                _ => (bytes, dropped),
            },
        };
        Ok(Reduced { bytes: Bytes::from(bytes), dropped })
    }

    /// The empty partial that pieces' partials fold into.
    pub fn empty(&self) -> Partial {
        match self {
            Reduction::Counts => Partial::Sums(vec![0; 3]),
            Reduction::Histogram { bins, .. } => Partial::SparseSums { len: *bins as usize + 2, counts: Vec::new() },
            Reduction::IdCounts(_) => Partial::Keyed(Default::default()),
            _ => Partial::Ordered { bytes: Vec::new(), dropped: 0 },
        }
    }

    /// Reduces a whole batch that was traced with [`Reduction::traced_query`] in one go (what the pieces of a
    /// trace compute together): for tests and for callers that hold every hit.
    pub fn reduce_all(&self, traced: &Query, rays: &[u8], hits: &[u8], counts: &[u8]) -> Result<Reduced> {
        let ray_count = (rays.len() / traced.ray_format.size()) as u64;
        self.finish(self.reduce_piece_parallel(traced, 0, rays, hits, counts), ray_count)
    }
}

/// A reduction's answer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reduced {
    /// The encoded result (layout documented on each [`Reduction`] variant).
    pub bytes: Bytes,
    /// Items left out because they could not be encoded (points outside an INT16 point cloud's range).
    pub dropped: u64,
}

/// The index of the nearest hit among `rays` (the first of equal `t`), or the first ray when all missed.
#[inline(always)]
pub(super) fn nearest(format: HitFormat, hits: &[u8], rays: std::ops::Range<usize>) -> usize {
    let mut nearest = (rays.start, None);
    for index in rays {
        if let Some(t) = format.hit_t(hits, index)
            && nearest.1.is_none_or(|nearest: f32| t < nearest)
        {
            nearest = (index, Some(t));
        }
    }
    nearest.0
}

/// Checks that a group of `group` rays is allowed and that `rays` is a whole number of groups.
fn check_groups(field: &'static str, group: u32, rays: u64) -> Result<()> {
    if group == 0 || group > MAX_GROUP_RAYS {
        return Err(invalid(field, format!("{group} is not in 1..={MAX_GROUP_RAYS}")));
    }
    if !rays.is_multiple_of(u64::from(group)) {
        return Err(invalid(field, format!("{rays} rays are not a whole number of groups of {group}")));
    }
    Ok(())
}

/// INVALID_ARGUMENT naming `field` (the contract's name for it).
fn invalid(field: &'static str, rule: String) -> Error {
    Error::InvalidQuery { field, rule }
}

#[cfg(test)]
mod tests;
