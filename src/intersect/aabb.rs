//! Conservative slab test of a ray against an axis-aligned box.
//!
//! A direction component of 0 has the reciprocal +∞. The near and far planes are chosen by the direction's sign
//! once per ray, so the only NaN that can arise is `0 × ∞` for an origin exactly on a slab plane of a zero
//! direction component, which means "inside that slab"; `f32::max`/`f32::min` ignore a NaN operand, which is
//! exactly that. Both ends of the interval are widened by [`SLACK`] (relative) so that rounding never culls a
//! box holding a triangle hit that the triangle test would accept, ties at equal `t` included.

use glam::Vec3A;

use super::PreparedRay;

/// Relative widening of the box interval (about 8 ulps): covers the rounding of the slab test and of the
/// triangle test's `t`.
pub const SLACK: f32 = 1e-6;

/// Returns the entry distance if the ray's range `[tmin, tmax]` overlaps the box `[min, max]`.
#[inline(always)]
pub fn intersect(ray: &PreparedRay, min: Vec3A, max: Vec3A, tmin: f32, tmax: f32) -> Option<f32> {
    slabs(ray.origin, ray.inv_direction, ray.negative, (min, max), (tmin, tmax))
}

/// Whether the ray from `origin` along `direction`, not prepared yet, overlaps the box `[min, max]` within `[tmin,
/// tmax]`: what [`intersect`] answers for the ray once prepared ([`PreparedRay::from_traced`] takes its reciprocals and
/// signs from [`reciprocals`] and [`negative`] too), at the cost of one division, without the triangle test's
/// projection axes and shear.
#[inline(always)]
pub fn reaches(origin: Vec3A, direction: Vec3A, min: Vec3A, max: Vec3A, tmin: f32, tmax: f32) -> bool {
    slabs(origin, reciprocals(direction), negative(direction), (min, max), (tmin, tmax)).is_some()
}

/// `1/direction`, with +∞ for zero components (of either sign).
#[inline(always)]
pub fn reciprocals(direction: Vec3A) -> Vec3A {
    Vec3A::select(direction.cmpeq(Vec3A::ZERO), Vec3A::INFINITY, Vec3A::ONE / direction)
}

/// Per axis, whether `direction` is negative there: whether the box's maxima are the planes a ray meets first.
#[inline(always)]
pub fn negative(direction: Vec3A) -> [bool; 3] {
    [direction.x < 0.0, direction.y < 0.0, direction.z < 0.0]
}

/// The slab test of the ray from `origin` with reciprocals `inv_direction` and signs `negative` against the box `(min,
/// max)` within `(tmin, tmax)`: the entry distance, widened by [`SLACK`], if the ray overlaps it.
#[inline(always)]
fn slabs(
    origin: Vec3A,
    inv_direction: Vec3A,
    negative: [bool; 3],
    (min, max): (Vec3A, Vec3A),
    (tmin, tmax): (f32, f32),
) -> Option<f32> {
    let mut near = tmin;
    let mut far = tmax;
    for axis in 0..3 {
        let (lo, hi) = if negative[axis] { (max[axis], min[axis]) } else { (min[axis], max[axis]) };
        let inv = inv_direction[axis];
        let o = origin[axis];
        near = near.max((lo - o) * inv);
        far = far.min((hi - o) * inv);
    }
    let near = near - near.abs() * SLACK;
    let far = far + far.abs() * SLACK;
    (near <= far).then_some(near)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::{Ray, RayFlags};

    fn ray(origin: Vec3A, direction: Vec3A) -> PreparedRay {
        PreparedRay::new(&Ray { origin, direction, ..Ray::default() }, RayFlags::empty())
    }

    #[test]
    fn entry_distance_and_misses() {
        let r = ray(Vec3A::new(-2.0, 0.5, 0.5), Vec3A::X);
        let near = intersect(&r, Vec3A::ZERO, Vec3A::ONE, 0.0, f32::INFINITY).unwrap();
        assert!((near - 2.0).abs() < 1e-5);
        assert!(intersect(&r, Vec3A::ZERO, Vec3A::ONE, 0.0, 1.5).is_none());
        assert!(intersect(&r, Vec3A::ZERO, Vec3A::ONE, 3.5, 9.0).is_none());
        let away = ray(Vec3A::new(-2.0, 0.5, 0.5), -Vec3A::X);
        assert!(intersect(&away, Vec3A::ZERO, Vec3A::ONE, 0.0, f32::INFINITY).is_none());
    }

    #[test]
    fn zero_direction_components_on_and_off_the_slab_planes() {
        for direction in [Vec3A::X, Vec3A::new(1.0, -0.0, 0.0)] {
            // Origin exactly on the y = 0 and z = 1 planes of the box, travelling along x only.
            let on_plane = ray(Vec3A::new(-1.0, 0.0, 1.0), direction);
            assert!(intersect(&on_plane, Vec3A::ZERO, Vec3A::ONE, 0.0, f32::INFINITY).is_some());
            let outside = ray(Vec3A::new(-1.0, 1.5, 0.5), direction);
            assert!(intersect(&outside, Vec3A::ZERO, Vec3A::ONE, 0.0, f32::INFINITY).is_none());
        }
        // A flat box (zero thickness) hit face-on.
        let r = ray(Vec3A::new(0.5, 0.5, 2.0), -Vec3A::Z);
        assert!(intersect(&r, Vec3A::new(0.0, 0.0, 1.0), Vec3A::new(1.0, 1.0, 1.0), 0.0, f32::INFINITY).is_some());
    }

    #[test]
    fn a_ray_not_prepared_reaches_exactly_the_boxes_its_prepared_form_intersects() {
        // Directions with zero components of either sign, origins on, inside and outside the slab planes, a NaN, and
        // ranges that end inside, before and behind the box.
        let components = [-2.0, -0.5, -0.0, 0.0, 0.5, 1.0, f32::NAN];
        let (min, max) = (Vec3A::new(-1.0, 0.0, 0.5), Vec3A::new(1.0, 0.0, 2.0));
        let (mut reached, mut missed) = (0, 0);
        for (i, &x) in components.iter().enumerate() {
            for (j, &y) in components.iter().enumerate() {
                for (k, &z) in components.iter().enumerate() {
                    let direction = Vec3A::new(x, y, z);
                    let origin = Vec3A::new([-3.0, -1.0, 0.0, 1.0][i % 4], [0.0, 2.0, -1.0][j % 3], [0.5, 3.0][k % 2]);
                    for (tmin, tmax) in [(0.0, f32::INFINITY), (-5.0, 1.0), (0.0, 0.25), (2.0, 1.0)] {
                        let prepared = ray(origin, direction);
                        let want = intersect(&prepared, min, max, tmin, tmax).is_some();
                        assert_eq!(reaches(origin, direction, min, max, tmin, tmax), want, "{origin} {direction}");
                        if want { reached += 1 } else { missed += 1 }
                    }
                }
            }
        }
        assert!(reached > 100 && missed > 100, "{reached} reached, {missed} missed");
    }

    #[test]
    fn negative_tmin_reaches_behind_the_origin() {
        let r = ray(Vec3A::new(5.0, 0.5, 0.5), Vec3A::X);
        assert!(intersect(&r, Vec3A::ZERO, Vec3A::ONE, 0.0, f32::INFINITY).is_none());
        assert!(intersect(&r, Vec3A::ZERO, Vec3A::ONE, -10.0, f32::INFINITY).is_some());
    }
}
