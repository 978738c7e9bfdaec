//! Per-ray collection of hits: the one place where a candidate triangle becomes a hit, where the tie rule is
//! applied and where a ray's result is written into the caller's buffers.

use glam::{Mat3A, Vec3, Vec3A};

use super::{Query, QueryKind, TraceStats};
use crate::format::hit::write_bitmask_run;
use crate::format::{Hit, HitFormat, InstancePath, Ray, RayFlags, write_u32};
use crate::geometry::{GeometryFlags, InstanceFlags, PlacedInstance, Placement, TriangleRef};
use crate::intersect::PreparedRay;
use crate::intersect::triangle::{self, TriangleHit};

/// A triangle offered to a ray, with everything the acceptance rules need.
#[derive(Debug, Clone, Copy)]
pub struct TriangleCandidate<'a> {
    /// The triangle's corners.
    pub corners: &'a [Vec3; 3],
    /// The ids its hits report.
    pub id: TriangleRef,
    /// Its Prime mask.
    pub mask: u32,
    /// Its geometry's flags.
    pub geometry_flags: GeometryFlags,
}

/// Where a triangle is met: the instances above it and what they change about its hits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InstanceScope {
    /// The instances above, top to bottom.
    pub path: InstancePath,
    /// Front and back faces are swapped (an odd number of `FLIP_FACING` instances above).
    pub flip_facing: bool,
    /// Face culling is off (a `DISABLE_FACE_CULLING` instance above).
    pub no_culling: bool,
    /// Carries the geometry's normals to world space; `None` at the top level.
    pub normal_to_world: Option<Mat3A>,
}

impl InstanceScope {
    /// The scope of a traced accel itself: no instance above.
    pub const WORLD: InstanceScope =
        InstanceScope { path: InstancePath::EMPTY, flip_facing: false, no_culling: false, normal_to_world: None };

    /// The scope below `instance`.
    pub fn enter(&self, instance: &PlacedInstance) -> InstanceScope {
        InstanceScope {
            path: self.path.push(instance.instance_id),
            flip_facing: self.flip_facing ^ instance.flags.contains(InstanceFlags::FLIP_FACING),
            no_culling: self.no_culling || instance.flags.contains(InstanceFlags::DISABLE_FACE_CULLING),
            ..self.through(&instance.placement)
        }
    }

    /// The scope below a static transform.
    pub fn through(&self, placement: &Placement) -> InstanceScope {
        let normal_to_world = match self.normal_to_world {
            Some(outer) => outer * placement.normal_to_world,
            None => placement.normal_to_world,
        };
        InstanceScope { normal_to_world: Some(normal_to_world), ..*self }
    }
}

/// What orders hits for reporting: smaller `t`, then the smaller instance path, geometry id and primitive id.
type ReportKey = (f32, InstancePath, u32, u32);

/// The report key of `hit`.
#[inline(always)]
fn report_key(hit: &Hit) -> ReportKey {
    (hit.t, hit.inst_path, hit.geom_id, hit.prim_id)
}

/// Whether `a` is reported before `b`.
#[inline]
fn precedes(a: &Hit, b: &Hit) -> bool {
    report_key(a) < report_key(b)
}

/// Tests one triangle, met in `scope`, against the ray (in the triangle's space) and offers the hit, if it is
/// accepted, to `collector`: the mask rule, the intersection, the `[tmin, tmax]` range (inclusive) and face
/// culling, in that order.
#[inline(always)]
pub fn consider_triangle(
    ray: &PreparedRay,
    candidate: &TriangleCandidate<'_>,
    scope: &InstanceScope,
    collector: &mut Collector<'_>,
) {
    if ray.mask & candidate.mask != 0 {
        return;
    }
    if let Some(hit) = triangle::intersect(ray, candidate.corners) {
        accept_hit(ray.tmin, ray.flags, candidate, scope, collector, hit);
    }
}

/// The rest of [`consider_triangle`] once the ray's line meets the triangle at `hit` (and the mask rule let it be
/// tested): the range (from the ray's `tmin`), face culling (by the ray's `flags`), and the offer to `collector`.
/// Tracers that intersect a triangle with many rays at once go on from here for each ray that meets it.
#[inline(always)]
pub fn accept_hit(
    tmin: f32,
    flags: RayFlags,
    candidate: &TriangleCandidate<'_>,
    scope: &InstanceScope,
    collector: &mut Collector<'_>,
    hit: TriangleHit,
) {
    if !(hit.t >= tmin && hit.t <= collector.cull_tmax()) {
        return;
    }
    let back_face = hit.back_face ^ scope.flip_facing;
    if !scope.no_culling && !candidate.geometry_flags.contains(GeometryFlags::DISABLE_FACE_CULLING) {
        let culled = if back_face { RayFlags::CULL_BACK_FACING } else { RayFlags::CULL_FRONT_FACING };
        if flags.contains(culled) {
            return;
        }
    }
    let normal = match collector.wants_normal {
        true => {
            let [v0, v1, v2] = candidate.corners;
            let normal = Vec3A::from((*v1 - *v0).cross(*v2 - *v0));
            let normal = scope.normal_to_world.map_or(normal, |to_world| to_world * normal);
            if scope.flip_facing { -normal } else { normal }
        }
        false => Vec3A::ZERO,
    };
    collector.offer(AcceptedHit { hit, back_face, normal, id: candidate.id, path: &scope.path });
}

/// A hit [`accept_hit`] accepted, as it hands it to the collector: its parts, the instance path by reference. A hit
/// the collector keeps is written into its place field by field ([`AcceptedHit::write_into`]): a [`Hit`] built first
/// and then copied in whole is read back by wide loads before its narrow stores have landed, a stall that cost 10% of
/// an any-hit camera trace.
#[derive(Clone, Copy)]
pub struct AcceptedHit<'a> {
    /// The triangle test's hit (its `back_face` before the instances' flips).
    hit: TriangleHit,
    /// Whether the ray saw the back face, flips applied.
    back_face: bool,
    /// The normal, in world space, or zero where the format has none ([`HitFormat::has_normal`]).
    normal: Vec3A,
    /// The triangle's ids.
    id: TriangleRef,
    /// The instances above it.
    path: &'a InstancePath,
}

impl AcceptedHit<'_> {
    /// Whether it is reported before `other` ([`precedes`]).
    #[inline(always)]
    fn precedes(&self, other: &Hit) -> bool {
        (self.hit.t, *self.path, self.id.geom_id, self.id.prim_id) < report_key(other)
    }

    /// Overwrites `hit` with it, field by field.
    #[inline(always)]
    fn write_into(&self, hit: &mut Hit) {
        hit.t = self.hit.t;
        hit.prim_id = self.id.prim_id;
        hit.geom_id = self.id.geom_id;
        hit.inst_id = self.path.last();
        hit.inst_path = *self.path;
        hit.u = self.hit.u;
        hit.v = self.hit.v;
        hit.normal = self.normal;
        hit.back_face = self.back_face;
    }

    /// It as a hit.
    fn to_hit(self) -> Hit {
        let mut hit = Hit::MISS;
        self.write_into(&mut hit);
        hit
    }
}

/// Collects the hits of one ray according to the query kind.
#[derive(Debug)]
pub struct Collector<'s> {
    /// What is being collected.
    kind: QueryKind,
    /// The largest `t` still worth testing ([`Collector::cull_tmax`]): the ray's own `tmax`, then, for closest-hit
    /// queries, the closest hit's `t`. Kept up to date by [`Collector::offer`], since traversal reads it at every
    /// leaf.
    cull_tmax: f32,
    /// Set by the ray's or the query's `TERMINATE_ON_FIRST_HIT`.
    terminate_on_first_hit: bool,
    /// Whether the hits' normals are written ([`HitFormat::has_normal`]); the hits offered carry a zero normal
    /// otherwise, which saves a cross product an accepted hit.
    wants_normal: bool,
    /// Whether an `any` query keeps the hit it stops at: not for the bitmask format, whose record says only whether
    /// there is one ([`Collector::found`]).
    keeps_any_hit: bool,
    /// The first hit in report order so far (closest, any, count), once there is one ([`Collector::found`]); stale
    /// before.
    best: Hit,
    /// Hits accepted so far.
    count: u32,
    /// For `all`: the first hits in report order, sorted; `len` of them are in use.
    sorted: &'s mut [Hit],
    /// Entries of `sorted` in use.
    len: usize,
    /// Whether traversal may stop.
    done: bool,
    /// The work of the ray's chunk ([`TraceStats::work`]) past which the ray enters no more instances: what its
    /// group of rays may take, set by the batch driver; unbounded until then.
    work_ceiling: u64,
}

impl<'s> Collector<'s> {
    /// A collector for one ray, as [`crate::intersect::traced`] makes it; `scratch` must hold `max_hits_per_ray`
    /// entries for `all` queries (it is unused by the other kinds).
    #[inline]
    pub fn new(query: &Query, ray: &Ray, scratch: &'s mut [Hit]) -> Self {
        Collector {
            kind: query.kind,
            cull_tmax: ray.tmax,
            terminate_on_first_hit: ray.flags.contains(RayFlags::TERMINATE_ON_FIRST_HIT),
            wants_normal: query.hit_format.has_normal(),
            keeps_any_hit: query.hit_format != HitFormat::Bitmask,
            best: Hit::MISS,
            count: 0,
            sorted: scratch,
            len: 0,
            done: false,
            work_ceiling: u64::MAX,
        }
    }

    /// The largest `t` still worth testing: the closest hit's `t` for closest-hit queries (inclusive, so that ties
    /// reach the tie rule), the ray's `tmax` otherwise.
    #[inline(always)]
    pub fn cull_tmax(&self) -> f32 {
        self.cull_tmax
    }

    /// Makes it collect for `ray` from the start, as [`Collector::new`] would, keeping its scratch; the ray may enter
    /// instances while its chunk's work is at most `work_ceiling` ([`Collector::stop_past`]).
    #[inline(always)]
    pub fn restart(&mut self, ray: &Ray, work_ceiling: u64) {
        self.cull_tmax = ray.tmax;
        self.terminate_on_first_hit = ray.flags.contains(RayFlags::TERMINATE_ON_FIRST_HIT);
        self.count = 0;
        self.len = 0;
        self.done = false;
        self.work_ceiling = work_ceiling;
    }

    /// Stops the ray if its chunk's work so far (`stats`') passed its ceiling, counting it in
    /// [`TraceStats::rays_past_work`] (its answer is incomplete: the trace fails), and says whether it did: the
    /// collector is then done and culls every box, so that the ray's walk ends at once. Asked before the ray enters an
    /// instance, where a graph multiplies a ray's work.
    #[inline(always)]
    pub(crate) fn stop_past(&mut self, stats: &mut TraceStats) -> bool {
        if stats.work() <= self.work_ceiling {
            return false;
        }
        stats.rays_past_work += 1;
        self.work_ceiling = u64::MAX;
        self.done = true;
        self.cull_tmax = f32::NEG_INFINITY;
        true
    }

    /// Whether the order in which boxes are entered matters to the answer's cost: a closest-hit query prunes by its
    /// nearest hit so far, so it wants boxes nearest first; `all` and `count` must see every hit whatever the order,
    /// and `any` stops at whichever it finds first.
    #[inline(always)]
    pub fn wants_nearest_first(&self) -> bool {
        self.kind == QueryKind::Closest
    }

    /// Whether the ray may be traced with others, in an order of boxes they decide together: true unless it is a
    /// closest-hit ray that terminates on its first hit (which then stops at the first hit nearest first, as alone).
    /// Other answers do not depend on that order, but for which hit an `any` query stops at.
    #[inline(always)]
    pub fn may_share_order(&self) -> bool {
        !(self.kind == QueryKind::Closest && self.terminate_on_first_hit)
    }

    /// Whether traversal can stop: an `any` query or a terminate-on-first-hit ray has its hit.
    #[inline(always)]
    pub fn done(&self) -> bool {
        self.done
    }

    /// Whether an accepted hit tells it only that the ray has one, which ends it: an `any` query that keeps no hit
    /// (the bitmask format). A hit is then offered without its parts ([`Collector::offer_found`]).
    #[inline(always)]
    pub fn keeps_no_hit(&self) -> bool {
        self.kind == QueryKind::Any && !self.keeps_any_hit
    }

    /// Takes an accepted hit when it [`Collector::keeps_no_hit`], as [`Collector::offer`] would.
    #[inline(always)]
    pub fn offer_found(&mut self) {
        debug_assert!(self.keeps_no_hit());
        self.count = self.count.saturating_add(1);
        self.done = true;
    }

    /// Takes an accepted hit.
    #[inline(always)]
    pub fn offer(&mut self, hit: AcceptedHit<'_>) {
        let first = !self.found();
        self.count = self.count.saturating_add(1);
        match self.kind {
            QueryKind::Closest | QueryKind::Count => {
                if first || hit.precedes(&self.best) {
                    if self.kind == QueryKind::Closest {
                        self.cull_tmax = hit.hit.t;
                    }
                    hit.write_into(&mut self.best);
                }
                self.done = self.terminate_on_first_hit;
            }
            // The first hit found is kept.
            QueryKind::Any => {
                if first && self.keeps_any_hit {
                    hit.write_into(&mut self.best);
                }
                self.done = true;
            }
            QueryKind::All => {
                self.insert_sorted(hit.to_hit());
                self.done = self.terminate_on_first_hit;
            }
        }
    }

    /// Keeps the `sorted.len()` first hits in report order.
    fn insert_sorted(&mut self, hit: Hit) {
        let capacity = self.sorted.len();
        if self.len == capacity && !precedes(&hit, &self.sorted[capacity - 1]) {
            return;
        }
        let mut at = self.len.min(capacity - 1);
        while at > 0 && precedes(&hit, &self.sorted[at - 1]) {
            self.sorted[at] = self.sorted[at - 1];
            at -= 1;
        }
        self.sorted[at] = hit;
        self.len = (self.len + 1).min(capacity);
    }

    /// Whether the ray hit anything.
    pub fn found(&self) -> bool {
        self.count > 0
    }

    /// Writes this ray's records in `format` (starting at record `first_record` of `hits`) and, for counting kinds,
    /// its count at u32 index `ray` of `counts`.
    #[inline(always)]
    pub fn write(&self, format: HitFormat, hits: &mut [u8], first_record: usize, counts: &mut [u8], ray: usize) {
        if self.kind == QueryKind::All {
            for slot in 0..self.sorted.len() {
                let hit = if slot < self.len { &self.sorted[slot] } else { &Hit::MISS };
                format.write(hits, first_record + slot, hit);
            }
        } else if format == HitFormat::Bitmask {
            // Whether there is a hit, which is all the record says (an `any` query keeps no hit for it).
            write_bitmask_run(hits, first_record, u32::from(self.found()), 1);
        } else {
            format.write(hits, first_record, if self.found() { &self.best } else { &Hit::MISS });
        }
        self.write_count(counts, ray);
    }

    /// For counting kinds, writes this ray's count at u32 index `ray` of `counts`.
    #[inline(always)]
    fn write_count(&self, counts: &mut [u8], ray: usize) {
        if self.kind.has_counts() {
            write_u32(counts, 4 * ray, self.count);
        }
    }

    /// A bit for each of `collectors` (at most 32; the first in bit 0) that found a hit, gathered without a branch.
    #[inline(always)]
    pub fn found_bits(collectors: &[Collector<'_>]) -> u32 {
        debug_assert!(collectors.len() <= 32);
        collectors.iter().enumerate().fold(0, |bits, (bit, collector)| bits | u32::from(collector.found()) << bit)
    }

    /// Writes the records (`records_per_ray` a ray) and counts of a group of `collectors`, whose rays are `runs` of
    /// consecutive rays ((first ray, rays), in the collectors' order), as [`Collector::write`] does each; `found` is
    /// their [`Collector::found_bits`]. A bitmask of one record a ray is written from `found` a run at once
    /// ([`write_bitmask_run`]): neighbouring rays' bits share bytes.
    #[inline(always)]
    pub fn write_group(
        collectors: &[Collector<'_>],
        found: u32,
        runs: &[(usize, usize)],
        format: HitFormat,
        hits: &mut [u8],
        records_per_ray: usize,
        counts: &mut [u8],
    ) {
        let Some(kind) = collectors.first().map(|collector| collector.kind) else { return };
        // Runs: each one's first ray, where its collectors start in the group, and its collectors.
        let runs = || {
            runs.iter().scan(0, |at, &(first, run)| {
                *at += run;
                Some((first, *at - run, &collectors[*at - run..*at]))
            })
        };
        if format == HitFormat::Bitmask && kind != QueryKind::All {
            // A one-record kind writes its best hit if it found one (a hit), else a miss.
            for (first, start, run_collectors) in runs() {
                write_bitmask_run(hits, first, found >> start, run_collectors.len());
                if kind.has_counts() {
                    for (ray, collector) in (first..).zip(run_collectors) {
                        collector.write_count(counts, ray);
                    }
                }
            }
            return;
        }
        for (first, _, run_collectors) in runs() {
            for (ray, collector) in (first..).zip(run_collectors) {
                collector.write(format, hits, ray * records_per_ray, counts, ray);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::RayFormat;
    use crate::geometry::TriangleRef;

    #[test]
    fn a_group_is_written_as_its_records_one_by_one_and_a_bitmask_bit_says_whether_the_ray_found_a_hit() {
        let corners = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let candidate = TriangleCandidate {
            corners: &corners,
            id: TriangleRef { geom_id: 0, prim_id: 5 },
            mask: 0,
            geometry_flags: GeometryFlags::empty(),
        };
        let met = TriangleHit { t: 2.0, u: 0.25, v: 0.5, back_face: false };
        for kind in [QueryKind::Any, QueryKind::Closest, QueryKind::Count] {
            let query = Query { kind, ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::Bitmask) };
            let ray = Ray::default();
            let collector = |hits: bool| {
                let mut collector = Collector::new(&query, &ray, &mut []);
                if hits {
                    accept_hit(0.0, RayFlags::empty(), &candidate, &InstanceScope::WORLD, &mut collector, met);
                }
                collector
            };
            let (hit, missed) = (collector(true), collector(false));
            // Record 1 hits and record 2 misses, written one by one; the other bits are kept.
            let mut counts = [0u8; 12];
            let mut one_by_one = [0b1111_0101u8];
            hit.write(HitFormat::Bitmask, &mut one_by_one, 1, &mut counts, 1);
            missed.write(HitFormat::Bitmask, &mut one_by_one, 2, &mut counts, 2);
            assert_eq!(one_by_one, [0b1111_0011], "{kind:?}");
            // A group of four in two runs (rays 1, 2 and 6, 7: a hit, a miss, a miss, a hit), in every format, as
            // its records and counts written one by one; the other records and counts are kept.
            let group = [collector(true), collector(false), collector(false), collector(true)];
            let (runs, rays) = ([(1, 2), (6, 2)], [1, 2, 6, 7]);
            for format in HitFormat::ALL {
                let before: Vec<u8> = (0..format.buffer_len(9)).map(|i| (37 * i + 11) as u8).collect();
                let counts_before: Vec<u8> = (0..4 * 9).map(|i| (29 * i + 3) as u8).collect();
                let (mut by_group, mut by_record) = (before.clone(), before.clone());
                let (mut group_counts, mut record_counts) = (counts_before.clone(), counts_before.clone());
                let found = Collector::found_bits(&group);
                assert_eq!(found, 0b1001, "{kind:?}");
                Collector::write_group(&group, found, &runs, format, &mut by_group, 1, &mut group_counts);
                for (collector, ray) in group.iter().zip(rays) {
                    collector.write(format, &mut by_record, ray, &mut record_counts, ray);
                }
                assert_eq!(by_group, by_record, "{kind:?} {format:?}");
                assert_eq!(group_counts, record_counts, "{kind:?} {format:?}");
            }
        }
    }
}
