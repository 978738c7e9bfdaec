//! Motion blur, after OptiX 7's `OptixMotionOptions` and OptiX 6.5's motion chapter: motion options (keys evenly
//! spaced over a time range, and what happens outside it), where a ray's time falls among the keys, the one
//! interpolation formula every backend uses, and conservative boxes over spans of time.
//!
//! A ray at time `t` meets each accel and motion transform as it is at `t`, each with its own options. With
//! `K` keys over `[begin, end]`, key `k` is at `begin + k·(end − begin)/(K − 1)`. Inside the range,
//! `u = (t − begin)/(end − begin)·(K − 1)`, the segment is `s = min(⌊u⌋, K − 2)` and the fraction `f = u − s`;
//! values between keys `s` and `s + 1` are `(1 − f)·a + f·b` (in f32, in that order). Before `begin` the first key
//! holds (or, with [`MotionFlags::START_VANISH`], the object is not there); after `end` the last key holds (or,
//! with [`MotionFlags::END_VANISH`], it is gone). One key means static: range and flags are then ignored.

use glam::{Affine3A, Vec3};

use crate::error::{Error, Result};

/// The most motion keys one accel or motion transform may have.
pub const MAX_MOTION_KEYS: u32 = 1024;

bitflags::bitflags! {
    /// What an object does outside its time range (OptiX `OptixMotionFlags`, OptiX 6.5 border modes).
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
    pub struct MotionFlags: u32 {
        /// Not there at times before `time_begin` (default: as at `time_begin`).
        const START_VANISH = 1;
        /// Not there at times after `time_end` (default: as at `time_end`).
        const END_VANISH = 1 << 1;
    }
}

/// The motion of one accel or motion transform.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionOptions {
    /// Motion keys, at least 1; 1 means static.
    pub keys: u32,
    /// Time of the first key.
    pub time_begin: f32,
    /// Time of the last key; greater than `time_begin` when there are 2 keys or more.
    pub time_end: f32,
    /// Behaviour outside the range.
    pub flags: MotionFlags,
}

impl Default for MotionOptions {
    fn default() -> Self {
        MotionOptions::STATIC
    }
}

/// A box: `(min, max)`, empty when `min > max` on some axis.
pub type Bounds = (Vec3, Vec3);

/// The box that holds nothing.
pub const EMPTY: Bounds = (Vec3::INFINITY, Vec3::NEG_INFINITY);

/// The smallest box holding both.
pub fn union(a: Bounds, b: Bounds) -> Bounds {
    (a.0.min(b.0), a.1.max(b.1))
}

/// Whether the box holds nothing.
pub fn is_empty(b: &Bounds) -> bool {
    b.0.cmpgt(b.1).any()
}

/// The time average of the box an item has when its key boxes `keys` (evenly spaced in time, as motion keys are) are
/// interpolated: each plane's mean by the trapezoid rule. A moving BVH's topology is built over these boxes, so that
/// its surface-area cost weighs the box the rays meet at their times, not the path over all of time (which counts an
/// item moving by more than its size as if it filled that path). The union of the keys when there is one key, when
/// one of them is empty, or when the mean is not finite (planes near the largest floats, or infinite ones).
pub fn time_average(keys: impl ExactSizeIterator<Item = Bounds>) -> Bounds {
    let segments = keys.len().saturating_sub(1);
    let (mut mean, mut union_of_keys, mut any_empty) = ((Vec3::ZERO, Vec3::ZERO), EMPTY, false);
    for (key, b) in keys.enumerate() {
        // Each term weighed before it is added, so that the sum of finite planes stays finite.
        let weight = if key == 0 || key == segments { 0.5 } else { 1.0 } / segments.max(1) as f32;
        mean = (mean.0 + b.0 * weight, mean.1 + b.1 * weight);
        (union_of_keys, any_empty) = (union(union_of_keys, b), any_empty || is_empty(&b));
    }
    let finite = mean.0.is_finite() && mean.1.is_finite();
    if segments == 0 || any_empty || !finite { union_of_keys } else { mean }
}

/// The eight corners of a box.
pub(crate) fn corners((min, max): Bounds) -> [Vec3; 8] {
    std::array::from_fn(|i| {
        Vec3::new(
            if i & 1 == 0 { min.x } else { max.x },
            if i & 2 == 0 { min.y } else { max.y },
            if i & 4 == 0 { min.z } else { max.z },
        )
    })
}

/// The box around `inner` mapped by `map` (empty stays empty).
pub(crate) fn map_bounds(map: &Affine3A, inner: Bounds) -> Bounds {
    if is_empty(&inner) {
        return inner;
    }
    corners(inner).iter().map(|&p| map.transform_point3(p)).fold(EMPTY, |acc, p| union(acc, (p, p)))
}

/// `(1 − f)·a + f·b`, the interpolation between two keys (exact at `f` = 0 and 1).
#[inline(always)]
pub fn lerp(a: Vec3, b: Vec3, f: f32) -> Vec3 {
    a * (1.0 - f) + b * f
}

/// Where a time falls: between key `segment` and the next, `fraction` of the way.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyTime {
    /// The key before the time (the last segment's start after the range).
    pub segment: usize,
    /// From 0 (at key `segment`) to 1 (at the next key); 0 for a static object.
    pub fraction: f32,
}

/// A span of time, `start ≤ end`; the ends may be infinite.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeSpan {
    /// Earliest time.
    pub start: f32,
    /// Latest time.
    pub end: f32,
}

impl TimeSpan {
    /// All of time.
    pub const ALL: TimeSpan = TimeSpan { start: f32::NEG_INFINITY, end: f32::INFINITY };

    /// One instant.
    pub fn at(time: f32) -> TimeSpan {
        TimeSpan { start: time, end: time }
    }

    /// The overlap of two spans, if any.
    fn clip(&self, start: f32, end: f32) -> Option<TimeSpan> {
        let clipped = TimeSpan { start: self.start.max(start), end: self.end.min(end) };
        (clipped.start <= clipped.end).then_some(clipped)
    }
}

/// Part of a span of time, as an object moves through it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Piece {
    /// The object holds still as at `key` (outside its range, or a static object).
    Held {
        /// When.
        span: TimeSpan,
        /// The key that holds.
        key: usize,
    },
    /// The object moves between key `segment` and the next, from `from` to `to` of the way.
    Moving {
        /// When.
        span: TimeSpan,
        /// The segment's first key.
        segment: usize,
        /// Fraction at the span's start.
        from: f32,
        /// Fraction at the span's end.
        to: f32,
    },
}

impl MotionOptions {
    /// No motion.
    pub const STATIC: MotionOptions =
        MotionOptions { keys: 1, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };

    /// Whether the object is static (one key).
    pub fn is_static(&self) -> bool {
        self.keys <= 1
    }

    /// Checks the options; the error is the rule broken.
    pub fn check(&self) -> std::result::Result<(), String> {
        if self.keys == 0 || self.keys > MAX_MOTION_KEYS {
            return Err(format!("{} motion keys; 1 to {MAX_MOTION_KEYS} are allowed", self.keys));
        }
        if !self.is_static() && !(self.time_end - self.time_begin).is_finite() {
            // Its length too: key times and a time's place among the keys are worked out from it.
            return Err(format!(
                "time range [{}, {}] must be finite, and so must its length",
                self.time_begin, self.time_end
            ));
        }
        if !self.is_static() && self.time_begin >= self.time_end {
            return Err(format!(
                "time_end {} must be greater than time_begin {} with {} keys",
                self.time_end, self.time_begin, self.keys
            ));
        }
        Ok(())
    }

    /// Checks that `count` keys were given for these options; errors name `field`.
    pub fn check_key_count(&self, count: usize, field: &'static str) -> Result<()> {
        if count != self.keys as usize {
            return Err(Error::InvalidBuildInput {
                input: 0,
                field,
                element: None,
                rule: format!("{count} keys given, the motion options have {}", self.keys),
            });
        }
        Ok(())
    }

    /// The time of key `key`.
    pub fn key_time(&self, key: usize) -> f32 {
        if self.is_static() {
            return self.time_begin;
        }
        let last = (self.keys - 1) as f32;
        self.time_begin + (self.time_end - self.time_begin) * (key as f32 / last)
    }

    /// Where `time` falls among the keys; `None` when the object has vanished at that time. A NaN time is
    /// refused before tracing; here it holds the first key.
    #[inline(always)]
    pub fn locate(&self, time: f32) -> Option<KeyTime> {
        if self.is_static() {
            return Some(KeyTime { segment: 0, fraction: 0.0 });
        }
        let last_segment = self.keys as usize - 2;
        if time > self.time_end {
            return (!self.flags.contains(MotionFlags::END_VANISH))
                .then_some(KeyTime { segment: last_segment, fraction: 1.0 });
        }
        if time < self.time_begin || time.is_nan() {
            return (!self.flags.contains(MotionFlags::START_VANISH) || time.is_nan())
                .then_some(KeyTime { segment: 0, fraction: 0.0 });
        }
        let u = (time - self.time_begin) / (self.time_end - self.time_begin) * (self.keys - 1) as f32;
        let segment = (u as usize).min(last_segment);
        Some(KeyTime { segment, fraction: (u - segment as f32).clamp(0.0, 1.0) })
    }

    /// The pieces of `span` during which the object holds a key or moves along one segment; each segment is cut
    /// into `cuts` equal parts (so that bounds over a piece can be tight), and parts where the object has
    /// vanished are left out.
    pub fn pieces(&self, span: TimeSpan, cuts: usize) -> Vec<Piece> {
        if self.is_static() {
            return vec![Piece::Held { span, key: 0 }];
        }
        let mut pieces = Vec::new();
        let (begin, end) = (self.time_begin, self.time_end);
        if !self.flags.contains(MotionFlags::START_VANISH)
            && let Some(before) = span.clip(f32::NEG_INFINITY, begin)
        {
            pieces.push(Piece::Held { span: before, key: 0 });
        }
        let segments = self.keys as usize - 1;
        let parts = segments * cuts;
        let time = |x: f32| if x >= 1.0 { end } else { begin + (end - begin) * x };
        let start_of = |part: usize| time(part as f32 / parts as f32);
        // Each part starts no earlier than the one before (but for rounding at the range's end, which one more part
        // each side covers): those that may overlap the span are found by bisection rather than by trying each.
        let first = first_of(parts, |part| start_of(part + 1) >= span.start).saturating_sub(1);
        let after_last = (first_of(parts, |part| start_of(part) > span.end) + 1).min(parts);
        for part in first..after_last {
            let (lo, hi) = (part as f32 / parts as f32, (part + 1) as f32 / parts as f32);
            let Some(clipped) = span.clip(time(lo), time(hi)) else { continue };
            let segment = part / cuts;
            // As `locate` computes it, within this segment.
            let fraction = |t: f32| ((t - begin) / (end - begin) * segments as f32 - segment as f32).clamp(0.0, 1.0);
            pieces.push(Piece::Moving {
                span: clipped,
                segment,
                from: fraction(clipped.start),
                to: fraction(clipped.end),
            });
        }
        if !self.flags.contains(MotionFlags::END_VANISH)
            && let Some(after) = span.clip(end, f32::INFINITY)
        {
            pieces.push(Piece::Held { span: after, key: self.keys as usize - 1 });
        }
        pieces
    }

    /// The box over `span` of an object whose boxes at the keys are `keys` (one per key) and whose box between
    /// keys is their interpolation (the union of both keys' boxes where one is empty, such as an object with nothing
    /// to hit: interpolating an empty box's infinite planes gives NaN).
    pub fn bounds_of_keys(&self, keys: &[Bounds], span: TimeSpan) -> Bounds {
        self.pieces(span, 1).iter().fold(EMPTY, |acc, piece| {
            let b = match *piece {
                Piece::Held { key, .. } => keys[key],
                Piece::Moving { segment, .. } if is_empty(&keys[segment]) || is_empty(&keys[segment + 1]) => {
                    union(keys[segment], keys[segment + 1])
                }
                Piece::Moving { segment, from, to, .. } => {
                    let (a, b) = (keys[segment], keys[segment + 1]);
                    union((lerp(a.0, b.0, from), lerp(a.1, b.1, from)), (lerp(a.0, b.0, to), lerp(a.1, b.1, to)))
                }
            };
            union(acc, b)
        })
    }

    /// Boxes at the keys whose interpolation, at any time, holds what `during` bounds at that time, for an object
    /// (such as a placed child) whose box over any span `during` can tell but which need not move linearly. A
    /// static object gets one box over all of time. Each segment is checked in `cuts` parts and both of its key
    /// boxes are widened until their interpolation holds every part; before and after the range the end keys hold
    /// all that the object can be (it is not clamped by these options), unless a vanish flag removes that time.
    pub fn fit_key_bounds(&self, cuts: usize, during: impl Fn(TimeSpan) -> Bounds) -> Vec<Bounds> {
        if self.is_static() {
            return vec![during(TimeSpan::ALL)];
        }
        let keys = self.keys as usize;
        let key_span = |segment: usize| TimeSpan { start: self.key_time(segment), end: self.key_time(segment + 1) };
        let mut boxes: Vec<Bounds> = (0..keys).map(|k| during(TimeSpan::at(self.key_time(k)))).collect();
        if !self.flags.contains(MotionFlags::START_VANISH) {
            boxes[0] = union(boxes[0], during(TimeSpan { start: f32::NEG_INFINITY, end: self.time_begin }));
        }
        if !self.flags.contains(MotionFlags::END_VANISH) {
            boxes[keys - 1] = union(boxes[keys - 1], during(TimeSpan { start: self.time_end, end: f32::INFINITY }));
        }
        // An empty key box (the object is elsewhere in time) takes what the segments beside it hold, so that the
        // interpolation stays finite.
        for (k, key_box) in boxes.iter_mut().enumerate() {
            if is_empty(key_box) {
                let before = if k > 0 { during(key_span(k - 1)) } else { EMPTY };
                let after = if k + 1 < keys { during(key_span(k)) } else { EMPTY };
                *key_box = union(before, after);
            }
        }
        if boxes.iter().all(is_empty) {
            return boxes;
        }
        let any = boxes.iter().copied().filter(|b| !is_empty(b)).fold(EMPTY, union);
        for b in boxes.iter_mut().filter(|b| is_empty(b)) {
            *b = any;
        }
        for segment in 0..keys - 1 {
            let (start, end) = (self.key_time(segment), self.key_time(segment + 1));
            let (mut lower, mut raise) = (Vec3::ZERO, Vec3::ZERO);
            for cut in 0..cuts {
                let (lo, hi) = (cut as f32 / cuts as f32, (cut + 1) as f32 / cuts as f32);
                let at = |x: f32| if x >= 1.0 { end } else { start + (end - start) * x };
                let part = during(TimeSpan { start: at(lo), end: at(hi) });
                if is_empty(&part) {
                    continue;
                }
                let (a, b) = (boxes[segment], boxes[segment + 1]);
                for f in [lo, hi] {
                    lower = lower.max(lerp(a.0, b.0, f) - part.0);
                    raise = raise.max(part.1 - lerp(a.1, b.1, f));
                }
            }
            for k in [segment, segment + 1] {
                boxes[k] = (boxes[k].0 - lower, boxes[k].1 + raise);
            }
        }
        boxes.into_iter().map(pad).collect()
    }
}

/// The first of `0..count` for which `holds` holds (`count` if none), given that it holds for every one after one for
/// which it does.
fn first_of(count: usize, holds: impl Fn(usize) -> bool) -> usize {
    let (mut low, mut high) = (0, count);
    while low < high {
        let middle = low + (high - low) / 2;
        if holds(middle) { high = middle } else { low = middle + 1 }
    }
    low
}

/// Widens a box computed through transforms or fitting by a few ulps of its coordinates, so that rounding never
/// leaves part of the object outside it.
pub fn pad(b: Bounds) -> Bounds {
    if is_empty(&b) {
        return b;
    }
    let slack = (b.0.abs().max(b.1.abs())) * 4e-7;
    (b.0 - slack, b.1 + slack)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(keys: u32, time_begin: f32, time_end: f32, flags: MotionFlags) -> MotionOptions {
        MotionOptions { keys, time_begin, time_end, flags }
    }

    #[test]
    fn times_fall_on_evenly_spaced_keys_and_clamp_or_vanish_outside() {
        let m = options(3, -1.0, 1.5, MotionFlags::empty());
        m.check().unwrap();
        assert_eq!(m.locate(-1.0), Some(KeyTime { segment: 0, fraction: 0.0 }));
        assert_eq!(m.locate(0.25), Some(KeyTime { segment: 1, fraction: 0.0 }));
        assert_eq!(m.locate(0.875), Some(KeyTime { segment: 1, fraction: 0.5 }));
        assert_eq!(m.locate(1.5), Some(KeyTime { segment: 1, fraction: 1.0 }));
        assert_eq!(m.locate(-7.0), Some(KeyTime { segment: 0, fraction: 0.0 }));
        assert_eq!(m.locate(9.0), Some(KeyTime { segment: 1, fraction: 1.0 }));
        let vanishing = options(3, -1.0, 1.5, MotionFlags::START_VANISH | MotionFlags::END_VANISH);
        assert_eq!(vanishing.locate(-1.001), None);
        assert_eq!(vanishing.locate(1.501), None);
        assert!(vanishing.locate(1.5).is_some() && vanishing.locate(-1.0).is_some());
        assert_eq!(MotionOptions::STATIC.locate(42.0), Some(KeyTime { segment: 0, fraction: 0.0 }));
        assert_eq!(m.key_time(1), 0.25);
    }

    #[test]
    fn a_time_average_weighs_the_end_keys_half_and_falls_back_to_the_union_when_a_key_is_empty_or_it_is_not_finite() {
        let at = |x: f32| (Vec3::splat(x), Vec3::splat(x + 1.0));
        assert_eq!(time_average([at(0.0), at(4.0)].into_iter()), at(2.0));
        // Segments of one length: (0/2 + 4 + 2/2) / 2.
        assert_eq!(time_average([at(0.0), at(4.0), at(2.0)].into_iter()), at(2.5));
        assert_eq!(time_average([at(3.0)].into_iter()), at(3.0));
        assert_eq!(time_average([at(0.0), EMPTY, at(2.0)].into_iter()), (Vec3::ZERO, Vec3::splat(3.0)));
        assert!(is_empty(&time_average(std::iter::empty())));
        // Planes near the largest floats (the two ends' sum, 3·2¹²⁷, is past them): the weighed sum stays finite;
        // infinite planes give the union.
        let huge = 1.5 * 2f32.powi(127);
        let far = (Vec3::splat(huge), Vec3::splat(huge));
        assert_eq!(time_average([far, far, far].into_iter()), far);
        let unbounded = (Vec3::splat(f32::NEG_INFINITY), Vec3::splat(f32::INFINITY));
        assert_eq!(time_average([at(0.0), unbounded].into_iter()), unbounded);
    }

    #[test]
    fn bad_options_are_refused() {
        assert!(options(0, 0.0, 1.0, MotionFlags::empty()).check().is_err());
        assert!(options(2, 1.0, 1.0, MotionFlags::empty()).check().is_err());
        assert!(options(2, 0.0, f32::INFINITY, MotionFlags::empty()).check().is_err());
        assert!(options(MAX_MOTION_KEYS + 1, 0.0, 1.0, MotionFlags::empty()).check().is_err());
        assert!(options(1, 5.0, 5.0, MotionFlags::START_VANISH).check().is_ok(), "static ignores the range");
    }

    #[test]
    fn fitted_key_bounds_hold_a_nonlinear_path() {
        // A point on a circle of radius 1, a quarter turn over [0, 1]: its chord misses the arc's middle.
        let at = |t: f32| {
            let angle = t.clamp(0.0, 1.0) * std::f32::consts::FRAC_PI_2;
            Vec3::new(angle.cos(), angle.sin(), 0.0)
        };
        let during = |span: TimeSpan| {
            let (a, b) = (span.start.max(-1.0), span.end.min(2.0));
            (0..=64).map(|i| at(a + (b - a) * i as f32 / 64.0)).fold(EMPTY, |acc, p| union(acc, (p, p)))
        };
        let m = options(2, 0.0, 1.0, MotionFlags::empty());
        let keys = m.fit_key_bounds(8, during);
        for i in 0..=100 {
            let t = i as f32 / 100.0;
            let k = m.locate(t).unwrap();
            let (lo, hi) = (lerp(keys[0].0, keys[1].0, k.fraction), lerp(keys[0].1, keys[1].1, k.fraction));
            let p = at(t);
            assert!(p.cmpge(lo - 1e-3).all() && p.cmple(hi + 1e-3).all(), "t {t}: {p} outside {lo}..{hi}");
        }
        assert_eq!(m.bounds_of_keys(&keys, TimeSpan::ALL), union(keys[0], keys[1]));
    }

    #[test]
    fn pieces_follow_each_other_part_by_part_over_the_span_within_the_range() {
        let m = options(5, -1.0, 3.0, MotionFlags::empty());
        let span = |start, end| TimeSpan { start, end };
        let spans = [
            (TimeSpan::ALL, 32),
            (TimeSpan::at(0.0), 2), // key 1, where parts 7 and 8 meet
            (TimeSpan::at(0.1), 1),
            (TimeSpan::at(-1.0), 1),
            (TimeSpan::at(3.0), 1),
            (span(0.3, 0.31), 1),
            (span(-0.1, 1.2), 11),
            (span(2.9, 10.0), 1),
            (span(-5.0, -2.0), 0),
            (TimeSpan::at(7.0), 0),
        ];
        for (span, parts) in spans {
            let moving: Vec<TimeSpan> = m
                .pieces(span, 8)
                .into_iter()
                .filter_map(|piece| match piece {
                    Piece::Moving { span, .. } => Some(span),
                    Piece::Held { .. } => None,
                })
                .collect();
            assert_eq!(moving.len(), parts, "{span:?}: {moving:?}");
            if let Some(inside) = span.clip(-1.0, 3.0) {
                assert_eq!((moving[0].start, moving[parts - 1].end), (inside.start, inside.end), "{span:?}");
            }
            assert!(moving.windows(2).all(|pair| pair[0].end == pair[1].start), "{span:?}: {moving:?}");
        }
    }
}
