//! Queries: what a trace asks for (closest, any, all, count), how its outputs are sized, and the per-ray
//! collection of hits that every backend shares.

mod batch;
mod collect;
mod rows;

pub use batch::{CHUNK_RAYS, GROUP_RAYS, batch_chunks, trace_batch, trace_batch_here};
pub use collect::{AcceptedHit, Collector, InstanceScope, TriangleCandidate, accept_hit, consider_triangle};
pub use rows::{ImageRows, split_from};

use crate::error::{Error, Result};
use crate::format::{HitFormat, RayFlags, RayFormat};

/// What a trace reports for each ray.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum QueryKind {
    /// The closest hit in `[tmin, tmax]`; of hits at the same `t`, the one with the lowest (instance path, geometry
    /// id, primitive id). One hit record a ray; no counts.
    Closest,
    /// Any hit in `[tmin, tmax]` (Prime's `ANY`): traversal stops at the first one found, so `t` and the ids are
    /// those of some hit, not necessarily the closest. One hit record a ray; no counts.
    Any,
    /// Every hit in `[tmin, tmax]`, sorted by `t` then (instance path, geometry id, primitive id): `max_hits_per_ray`
    /// hit records a ray (unused ones are misses), and a count a ray: the number of hits found, which is larger than
    /// `max_hits_per_ray` exactly when hits were left out (overflow).
    All,
    /// The number of crossings in `[tmin, tmax]` (for inside/outside tests: see the edge rule in
    /// [`crate::intersect::triangle`]), in the counts buffer, and the closest hit in the hit buffer.
    Count,
}

impl QueryKind {
    /// Every query kind.
    pub const ALL: [QueryKind; 4] = [QueryKind::Closest, QueryKind::Any, QueryKind::All, QueryKind::Count];

    /// The kind's name in lower case, as used by the contract and `rayctl`.
    pub const fn name(self) -> &'static str {
        match self {
            QueryKind::Closest => "closest",
            QueryKind::Any => "any",
            QueryKind::All => "all",
            QueryKind::Count => "count",
        }
    }

    /// Looks a kind up by [`QueryKind::name`].
    pub fn from_name(name: &str) -> Option<QueryKind> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// Whether the query writes a counts buffer.
    pub const fn has_counts(self) -> bool {
        matches!(self, QueryKind::All | QueryKind::Count)
    }
}

/// A complete description of a trace, apart from its buffers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Query {
    /// What is reported per ray.
    pub kind: QueryKind,
    /// How the ray buffer is packed.
    pub ray_format: RayFormat,
    /// How hit records are packed.
    pub hit_format: HitFormat,
    /// Flags applied to every ray, in addition to each ray's own.
    pub flags: RayFlags,
    /// For [`QueryKind::All`]: hit records per ray, at least 1. Ignored by the other kinds.
    pub max_hits_per_ray: u32,
}

impl Query {
    /// A closest-hit query with the given formats and no flags.
    pub fn closest(ray_format: RayFormat, hit_format: HitFormat) -> Query {
        Query { kind: QueryKind::Closest, ray_format, hit_format, flags: RayFlags::empty(), max_hits_per_ray: 1 }
    }

    /// Hit records written per ray.
    pub fn records_per_ray(&self) -> usize {
        match self.kind {
            QueryKind::All => self.max_hits_per_ray as usize,
            _ => 1,
        }
    }

    /// Checks that every ray's time (in the formats that carry one) is a number: a NaN time makes the whole batch
    /// INVALID_ARGUMENT, naming the first such ray. Infinite times are fine (they clamp or vanish).
    pub fn check_times(&self, rays: &[u8]) -> Result<()> {
        match self.ray_format.first_nan_time(rays) {
            None => Ok(()),
            Some(index) => Err(Error::InvalidQuery {
                field: "rays.time",
                rule: format!("ray {index} has time NaN; a ray's time must be a number"),
            }),
        }
    }

    /// Checks the query and the ray buffer's length, and returns the number of rays and the byte lengths the hit
    /// and counts buffers must have (`counts` is 0 for kinds without counts).
    pub fn output_layout(&self, ray_bytes: usize) -> Result<OutputLayout> {
        if self.kind == QueryKind::All && self.max_hits_per_ray == 0 {
            return Err(Error::InvalidQuery {
                field: "max_hits_per_ray",
                rule: "must be at least 1 for an `all` query".into(),
            });
        }
        let rays = self.ray_format.whole_rays(ray_bytes).map_err(|rule| Error::BufferSize { buffer: "rays", rule })?;
        let records = rays.checked_mul(self.records_per_ray()).ok_or(Error::TooLarge {
            what: "hit records",
            unit: "records",
            requested: u64::MAX,
            limit: usize::MAX as u64,
        })?;
        let hits = match self.hit_format.size() {
            None => records.div_ceil(8),
            Some(size) => records.checked_mul(size).ok_or(Error::TooLarge {
                what: "hit buffer",
                unit: "bytes",
                requested: u64::MAX,
                limit: usize::MAX as u64,
            })?,
        };
        let counts = if self.kind.has_counts() { rays * 4 } else { 0 };
        Ok(OutputLayout { rays, hits, counts })
    }
}

/// The sizes that a query's outputs must have for a given ray buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OutputLayout {
    /// Number of rays.
    pub rays: usize,
    /// Bytes of the hit buffer.
    pub hits: usize,
    /// Bytes of the counts buffer (one little-endian u32 a ray), 0 when the query has no counts.
    pub counts: usize,
}

/// Where a trace writes its results, in place.
#[derive(Debug)]
pub struct TraceOutput<'a> {
    /// Hit records, packed in the query's hit format.
    pub hits: &'a mut [u8],
    /// One little-endian u32 a ray, for the kinds that count ([`QueryKind::has_counts`]); empty otherwise.
    pub counts: &'a mut [u8],
}

impl<'a> TraceOutput<'a> {
    /// The outputs of consecutive `ranges` of rays from the first (checked outputs of `query`; ranges that start on a
    /// byte of a bitmask), split off these in turn.
    pub fn split(self, query: &Query, ranges: &[std::ops::Range<usize>]) -> Vec<TraceOutput<'a>> {
        let (mut hits, mut counts) = (self.hits, self.counts);
        let mut outputs = Vec::with_capacity(ranges.len());
        for range in ranges {
            let hit_bytes = query.hit_format.buffer_len(range.len() * query.records_per_ray()).min(hits.len());
            let count_bytes = if query.kind.has_counts() { 4 * range.len() } else { 0 };
            let (range_hits, rest_hits) = std::mem::take(&mut hits).split_at_mut(hit_bytes);
            let (range_counts, rest_counts) = std::mem::take(&mut counts).split_at_mut(count_bytes);
            outputs.push(TraceOutput { hits: range_hits, counts: range_counts });
            (hits, counts) = (rest_hits, rest_counts);
        }
        outputs
    }

    /// Checks the buffers' lengths against `layout`.
    pub fn check(&self, layout: &OutputLayout) -> Result<()> {
        if self.hits.len() != layout.hits {
            return Err(Error::BufferSize {
                buffer: "hits",
                rule: format!("{} bytes given, {} rays need {}", self.hits.len(), layout.rays, layout.hits),
            });
        }
        if self.counts.len() != layout.counts {
            return Err(Error::BufferSize {
                buffer: "counts",
                rule: format!("{} bytes given, this query needs {}", self.counts.len(), layout.counts),
            });
        }
        Ok(())
    }
}

/// What a trace did, summed over its rays.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TraceStats {
    /// Rays traced.
    pub rays: u64,
    /// Rays with at least one hit.
    pub rays_hit: u64,
    /// Acceleration-structure nodes whose boxes were tested.
    pub nodes_visited: u64,
    /// Ray/triangle tests made.
    pub triangle_tests: u64,
    /// Nanoseconds the device spent in trace kernels, where it measures them (wgpu adapters with timestamp
    /// queries); 0 elsewhere.
    pub device_nanos: u64,
    /// Rays stopped for passing the work a ray may take on the device (their answers incomplete: a backend fails
    /// such a trace with [`crate::Error::RayWork`]).
    pub rays_past_work: u64,
}

impl TraceStats {
    /// Adds `other` to `self`.
    pub fn add(&mut self, other: &TraceStats) {
        self.rays += other.rays;
        self.rays_hit += other.rays_hit;
        self.nodes_visited += other.nodes_visited;
        self.triangle_tests += other.triangle_tests;
        self.device_nanos += other.device_nanos;
        self.rays_past_work += other.rays_past_work;
    }

    /// Node visits and triangle tests so far: the work a ray's limit counts.
    #[inline(always)]
    pub fn work(&self) -> u64 {
        self.nodes_visited + self.triangle_tests
    }
}
