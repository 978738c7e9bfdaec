//! How many rays a trace's pieces take. A piece holds a worker (and, on a GPU, the device's queue) until it ends and
//! cannot be stopped midway, so pieces are sized by time as well as by rays: at most the device's largest piece, and
//! about the device's piece time at the rate at which the trace's own pieces ran, or, for its first piece, the last
//! trace of the same accel and query kind. Rays that cost a thousand times the usual (a pile of triangles that every
//! ray crosses) then come in pieces a thousand times smaller, and another tenant's trace waits for about one piece
//! time, not for seconds.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use rayd_engine::query::QueryKind;

/// What a device allows one piece.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PieceLimits {
    /// Rays at most.
    pub largest: usize,
    /// Rays at least, however long they take (but for the batch's last rays): on a GPU, pieces cut below the rays it
    /// runs at once stalled costly rays ([`crate::schedule::GPU_SMALLEST_PIECE_RAYS`]).
    pub smallest: usize,
    /// About how long it may hold a worker.
    pub time: Duration,
}

/// A trace's first piece when nothing is known of what its rays cost: this fraction of the largest piece (on a GPU,
/// 2^14 of 2^20 rays: a few milliseconds of an ordinary scene's kernels).
const PROBE_FRACTION: usize = 64;
/// A piece has at most this many times the rays of the piece measured last, so that a cheap first piece (rays that
/// miss everything, say) does not size the next one for seconds of costly rays.
const GROWTH: usize = 4;

/// How fast an accel's rays were traced, per query kind: nanoseconds a ray of its latest piece. Shared by the
/// accel's versions (an update seldom changes what a ray costs much).
#[derive(Debug, Default)]
pub struct Pace([AtomicU64; QueryKind::ALL.len()]);

impl Pace {
    /// Nanoseconds a ray of `kind`, if one was measured.
    pub fn get(&self, kind: QueryKind) -> Option<f64> {
        let bits = self.0[kind_index(kind)].load(Ordering::Relaxed);
        (bits != 0).then(|| f64::from_bits(bits))
    }

    /// Records `ns_per_ray` (positive) for `kind`.
    pub fn set(&self, kind: QueryKind, ns_per_ray: f64) {
        self.0[kind_index(kind)].store(ns_per_ray.max(f64::MIN_POSITIVE).to_bits(), Ordering::Relaxed);
    }

    /// Records `ns_per_ray` (positive) for `kind` if it is above the pace known, or none is known; at once, so that
    /// traces raising it together never lower it (positive floats order as their bits do).
    pub fn raise(&self, kind: QueryKind, ns_per_ray: f64) {
        self.0[kind_index(kind)].fetch_max(ns_per_ray.max(f64::MIN_POSITIVE).to_bits(), Ordering::Relaxed);
    }
}

/// `kind`'s place in [`QueryKind::ALL`].
fn kind_index(kind: QueryKind) -> usize {
    QueryKind::ALL.iter().position(|&k| k == kind).expect("every kind is in ALL")
}

/// Sizes the pieces of one trace as they are taken.
#[derive(Debug, Clone)]
pub struct PieceSizer {
    /// Every piece is a multiple of this many rays (rays reduced together, or whole bytes of a bitmask).
    granule: usize,
    /// Rays of a piece at most: the device's largest, as a multiple of the granule.
    largest: usize,
    /// Rays of a piece at least: the device's smallest, as a multiple of the granule, at most the largest.
    smallest: usize,
    /// The device's piece time, in nanoseconds.
    time_ns: f64,
    /// Rays of the next piece.
    next: usize,
    /// Rays of a trace's first piece when nothing is known of what its rays cost.
    probe: usize,
    /// Nanoseconds a ray at the rate last learned or known, if any.
    ns_per_ray: Option<f64>,
}

impl PieceSizer {
    /// Sizes pieces within `limits`, each a multiple of `granule` rays (at least one granule, even when the largest
    /// piece is smaller; at least the smallest piece, rounded up to a granule, unless that is above the largest),
    /// starting at the rate `known` (nanoseconds a ray, of an earlier trace) or, when nothing is
    /// known, with a probe of 1/[`PROBE_FRACTION`] of the largest piece.
    pub fn new(limits: PieceLimits, granule: usize, known: Option<f64>) -> PieceSizer {
        let granule = granule.max(1);
        let largest = (limits.largest / granule).max(1) * granule;
        let smallest = limits.smallest.max(1).next_multiple_of(granule).min(largest);
        let time_ns = limits.time.as_nanos() as f64;
        let mut sizer =
            PieceSizer { granule, largest, smallest, time_ns, next: largest, probe: largest, ns_per_ray: known };
        sizer.probe = sizer.fit((largest / PROBE_FRACTION) as f64);
        sizer.next = match known {
            Some(ns_per_ray) => sizer.fit(time_ns / ns_per_ray),
            None => sizer.probe,
        };
        sizer
    }

    /// Whether a piece of `rays` rays says what the accel's rays cost, for the pace that sizes later traces: at
    /// least a probe's rays. A trace of a few rays, whose fixed cost (on a GPU, a millisecond a piece) counted as the
    /// cost of its rays, would otherwise size the next large trace's pieces a thousand times too small.
    pub fn teaches_pace(&self, rays: usize) -> bool {
        rays >= self.probe
    }

    /// Rays of the next piece: a multiple of the granule, at least one granule and at most the largest piece.
    pub fn next(&self) -> usize {
        self.next
    }

    /// Learns from a piece of `rays` rays that took `took`: the next piece is what the piece time holds at that
    /// rate, but at most [`GROWTH`] times `rays`. Returns the rate, in nanoseconds a ray.
    pub fn learn(&mut self, rays: usize, took: Duration) -> f64 {
        let ns_per_ray = (took.as_nanos() as f64).max(1.0) / rays.max(1) as f64;
        self.next = self.fit((self.time_ns / ns_per_ray).min((rays * GROWTH) as f64));
        self.ns_per_ray = Some(ns_per_ray);
        ns_per_ray
    }

    /// About how long a piece of `rays` rays will hold a worker: at the rate last learned or known, or, when no rate
    /// is known, the piece time for a probe's rays and a share of it for fewer (a probe takes at most about the piece
    /// time, unless its rays are costlier than any seen).
    pub fn estimate(&self, rays: usize) -> Duration {
        let unknown = || self.time_ns * (rays as f64 / self.probe as f64).min(1.0);
        Duration::from_nanos(self.ns_per_ray.map_or_else(unknown, |ns| ns * rays as f64) as u64)
    }

    /// `rays` rounded down to the granule, within the smallest and the largest piece.
    fn fit(&self, rays: f64) -> usize {
        let granules = (rays / self.granule as f64).floor();
        // A float beyond usize's range saturates, and is then capped.
        ((granules as usize).saturating_mul(self.granule)).clamp(self.smallest, self.largest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: PieceLimits = PieceLimits { largest: 1 << 20, smallest: 1, time: Duration::from_millis(100) };

    #[test]
    fn a_trace_of_unknown_cost_starts_with_a_probe_and_grows_by_steps_while_its_pieces_are_quick() {
        let mut sizer = PieceSizer::new(LIMITS, 32, None);
        assert_eq!(sizer.next(), (1 << 20) / PROBE_FRACTION);
        // 10 ns a ray: the time would hold 10^7 rays, but a piece grows 4× at most, then stops at the largest.
        let mut sizes = Vec::new();
        for _ in 0..4 {
            let rays = sizer.next();
            sizer.learn(rays, Duration::from_nanos(10 * rays as u64));
            sizes.push(sizer.next());
        }
        assert_eq!(sizes, [1 << 16, 1 << 18, 1 << 20, 1 << 20]);
    }

    #[test]
    fn costly_rays_get_pieces_that_fit_the_piece_time() {
        let mut sizer = PieceSizer::new(LIMITS, 32, Some(10.0));
        assert_eq!(sizer.next(), 1 << 20, "a known cheap rate starts at the largest piece");
        // 36 s for 2^20 rays (34 µs a ray): 100 ms holds 2,912 rays, rounded down to the granule.
        let rate = sizer.learn(1 << 20, Duration::from_secs(36));
        assert!((rate - 36e9 / f64::from(1 << 20)).abs() < 1e-6);
        assert_eq!(sizer.next(), 2912);
        assert_eq!(sizer.next() % 32, 0);
        // The same rate known from an earlier trace sizes the first piece at once.
        assert_eq!(PieceSizer::new(LIMITS, 32, Some(rate)).next(), 2912);
    }

    #[test]
    fn pieces_stay_whole_granules_between_one_granule_and_the_largest() {
        // Rays so costly that one granule takes longer than the piece time: one granule still.
        let mut sizer = PieceSizer::new(LIMITS, 96, None);
        sizer.learn(96, Duration::from_secs(5));
        assert_eq!(sizer.next(), 96);
        // The largest piece rounded down to the granule; a granule above the largest is still one granule.
        assert_eq!(PieceSizer::new(LIMITS, 96, Some(1e-3)).next(), (1 << 20) / 96 * 96);
        let huge = PieceSizer::new(PieceLimits { largest: 1000, ..LIMITS }, 4096, Some(1.0));
        assert_eq!(huge.next(), 4096);
        // A piece that took no measurable time.
        let mut sizer = PieceSizer::new(LIMITS, 1, None);
        sizer.learn(100, Duration::ZERO);
        assert_eq!(sizer.next(), 400);
    }

    #[test]
    fn a_piece_is_estimated_at_the_rate_last_learned_or_at_the_piece_time() {
        let mut sizer = PieceSizer::new(LIMITS, 32, None);
        assert_eq!(sizer.estimate(sizer.next()), LIMITS.time, "nothing known: the piece time for a probe");
        assert_eq!(sizer.estimate(sizer.next() / 4), LIMITS.time / 4, "and a share of it for fewer rays");
        sizer.learn(1000, Duration::from_millis(2));
        assert_eq!(sizer.estimate(3000), Duration::from_millis(6));
        assert_eq!(PieceSizer::new(LIMITS, 32, Some(250.0)).estimate(4), Duration::from_nanos(1000));
    }

    #[test]
    fn pieces_stay_at_least_the_smallest_however_costly_their_rays() {
        // A GPU's smallest piece: rays of 34 µs fill 100 ms with 2,912, but pieces keep 2^18, the probe too.
        let gpu = PieceLimits { smallest: 1 << 18, ..LIMITS };
        let mut sizer = PieceSizer::new(gpu, 32, None);
        assert_eq!(sizer.next(), 1 << 18, "the probe is no smaller");
        sizer.learn(1 << 20, Duration::from_secs(36));
        assert_eq!(sizer.next(), 1 << 18);
        // Rounded up to the granule, and never above the largest.
        assert_eq!(PieceSizer::new(PieceLimits { smallest: 100, ..LIMITS }, 32, Some(1e9)).next(), 128);
        assert_eq!(PieceSizer::new(PieceLimits { largest: 64, smallest: 1000, ..LIMITS }, 32, Some(1e9)).next(), 64);
    }

    #[test]
    fn only_pieces_of_a_probe_or_more_teach_the_pace() {
        let sizer = PieceSizer::new(LIMITS, 32, Some(10.0));
        assert!(sizer.teaches_pace((1 << 20) / PROBE_FRACTION));
        assert!(!sizer.teaches_pace((1 << 20) / PROBE_FRACTION - 32), "a small trace's fixed cost is no ray's");
        // With a largest piece of one granule, every piece teaches it.
        assert!(PieceSizer::new(PieceLimits { largest: 16, ..LIMITS }, 32, None).teaches_pace(32));
    }

    #[test]
    fn a_pace_remembers_each_query_kind_apart() {
        let pace = Pace::default();
        assert_eq!(pace.get(QueryKind::Closest), None);
        pace.set(QueryKind::Closest, 250.0);
        pace.set(QueryKind::All, 0.0);
        assert_eq!(pace.get(QueryKind::Closest), Some(250.0));
        assert_eq!(pace.get(QueryKind::Any), None);
        assert!(pace.get(QueryKind::All).is_some_and(|ns| ns > 0.0), "a zero rate is stored as the least positive");
        // Raised, never lowered; and raised from none.
        pace.raise(QueryKind::Closest, 100.0);
        assert_eq!(pace.get(QueryKind::Closest), Some(250.0));
        pace.raise(QueryKind::Closest, 4000.5);
        assert_eq!(pace.get(QueryKind::Closest), Some(4000.5));
        pace.raise(QueryKind::Any, 7.0);
        assert_eq!(pace.get(QueryKind::Any), Some(7.0));
    }
}
