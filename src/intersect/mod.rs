//! The geometric tests every backend shares: a ray prepared once, its watertight triangle test and its
//! conservative box test.

pub mod aabb;
pub mod triangle;

use glam::{Affine3A, Vec3A};

use crate::format::{Ray, RayFlags};

/// A ray with the per-ray constants of the triangle and box tests computed once.
#[derive(Debug, Clone, Copy)]
pub struct PreparedRay {
    /// Origin.
    pub origin: Vec3A,
    /// Direction (not normalized).
    pub direction: Vec3A,
    /// Smallest accepted `t` (inclusive).
    pub tmin: f32,
    /// Largest accepted `t` (inclusive), as given by the caller; −∞ (nothing accepted) when the direction is not
    /// finite.
    pub tmax: f32,
    /// The time the scene is intersected at.
    pub time: f32,
    /// Prime mask.
    pub mask: u32,
    /// Instance visibility mask.
    pub visibility: u8,
    /// The ray's flags together with the query's.
    pub flags: RayFlags,
    /// Axis along which the direction is largest in magnitude; the triangle test projects along it.
    pub kz: usize,
    /// First axis of the projection plane (swapped with `ky` when the direction along `kz` is negative, which
    /// keeps the winding of projected triangles).
    pub kx: usize,
    /// Second axis of the projection plane.
    pub ky: usize,
    /// Shear constants of the watertight test: `dir[kx]/dir[kz]`, `dir[ky]/dir[kz]`, `1/dir[kz]`.
    pub shear: Vec3A,
    /// `1/direction`, with +∞ for zero components (see [`aabb`]).
    pub inv_direction: Vec3A,
    /// Per axis, whether the direction is negative: which slab plane a ray meets first.
    pub negative: [bool; 3],
}

/// `ray` as the tests see it: `query_flags` added to its own flags, and nothing accepted (`tmax` −∞) when its
/// direction is not finite (`formats.proto`; a zero direction needs no rule of its own: its shear is NaN, which no
/// triangle test passes). What [`PreparedRay::new`] starts from, and what batch drivers hand their backends.
#[inline(always)]
pub fn traced(ray: &Ray, query_flags: RayFlags) -> Ray {
    Ray {
        tmax: if ray.direction.is_finite() { ray.tmax } else { f32::NEG_INFINITY },
        flags: ray.flags | query_flags,
        ..*ray
    }
}

impl PreparedRay {
    /// Prepares `ray`, adding `query_flags` to its own flags ([`traced`]).
    #[inline]
    pub fn new(ray: &Ray, query_flags: RayFlags) -> PreparedRay {
        PreparedRay::from_traced(&traced(ray, query_flags))
    }

    /// Prepares a ray that [`traced`] made (as batch drivers hand them over).
    #[inline]
    pub fn from_traced(ray: &Ray) -> PreparedRay {
        let d = ray.direction;
        let abs = d.abs();
        let (kz, [x, y]) = if abs.x >= abs.y && abs.x >= abs.z {
            (0, [1, 2])
        } else if abs.y >= abs.z {
            (1, [2, 0])
        } else {
            (2, [0, 1])
        };
        let axes = d.to_array();
        let (kx, ky) = if axes[kz] < 0.0 { (y, x) } else { (x, y) };
        // One division of three lanes each (the same quotients as three scalar ones).
        let shear = Vec3A::new(axes[kx], axes[ky], 1.0) / Vec3A::splat(axes[kz]);
        let inv_direction = aabb::reciprocals(d);
        PreparedRay {
            origin: ray.origin,
            direction: d,
            tmin: ray.tmin,
            tmax: ray.tmax,
            time: ray.time,
            mask: ray.mask,
            visibility: ray.visibility,
            flags: ray.flags,
            kz,
            kx,
            ky,
            shear,
            inv_direction,
            negative: aabb::negative(d),
        }
    }

    /// The same ray in another space (e.g. an instance's object space). `t` keeps its meaning: the direction is
    /// carried over unnormalized.
    #[inline]
    pub fn transformed(&self, to: &Affine3A) -> PreparedRay {
        let (origin, direction) = self.carried(to);
        self.moved(origin, direction)
    }

    /// This ray's origin and direction in the space `to` maps into: what [`PreparedRay::transformed`] prepares, before
    /// it is (to test a box there first: [`aabb::reaches`]).
    #[inline(always)]
    pub fn carried(&self, to: &Affine3A) -> (Vec3A, Vec3A) {
        carry(self.origin, self.direction, to)
    }

    /// This ray from `origin` along `direction` (as [`PreparedRay::carried`] gives them), with its range, time,
    /// masks and flags, prepared.
    #[inline]
    pub fn moved(&self, origin: Vec3A, direction: Vec3A) -> PreparedRay {
        let ray = Ray {
            origin,
            direction,
            tmin: self.tmin,
            tmax: self.tmax,
            time: self.time,
            mask: self.mask,
            visibility: self.visibility,
            flags: self.flags,
        };
        PreparedRay::new(&ray, RayFlags::empty())
    }
}

/// `origin` and `direction` in the space `to` maps into.
#[inline(always)]
fn carry(origin: Vec3A, direction: Vec3A, to: &Affine3A) -> (Vec3A, Vec3A) {
    (to.transform_point3a(origin), to.transform_vector3a(direction))
}

/// `ray` (as [`traced`] makes it) carried into the space `to` maps into, as [`traced`] makes it there: the ray that
/// [`PreparedRay::transformed`] prepares from `ray` prepared, bit for bit (so that rays carried together into an
/// instance, [`PreparedRay::from_traced`] of each, meet what each meets alone).
#[inline(always)]
pub fn carried(ray: &Ray, to: &Affine3A) -> Ray {
    let (origin, direction) = carry(ray.origin, ray.direction, to);
    traced(&Ray { origin, direction, ..*ray }, RayFlags::empty())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The projection axes of a ray with direction `d`.
    fn axes(d: [f32; 3]) -> (usize, usize, usize) {
        let ray = PreparedRay::new(&Ray { direction: d.into(), ..Ray::default() }, RayFlags::empty());
        (ray.kz, ray.kx, ray.ky)
    }

    #[test]
    fn the_projection_axis_is_the_largest_component_with_ties_and_nans_resolved_in_axis_order() {
        // Largest magnitude wins; the plane's axes follow it cyclically, swapped when that component is negative.
        assert_eq!(axes([3.0, 1.0, 2.0]), (0, 1, 2));
        assert_eq!(axes([-3.0, 1.0, 2.0]), (0, 2, 1));
        assert_eq!(axes([1.0, -3.0, 2.0]), (1, 0, 2));
        assert_eq!(axes([1.0, 2.0, 3.0]), (2, 0, 1));
        assert_eq!(axes([1.0, 2.0, -3.0]), (2, 1, 0));
        // Ties go to the earlier axis.
        assert_eq!(axes([2.0, 2.0, 2.0]), (0, 1, 2));
        assert_eq!(axes([1.0, 2.0, 2.0]), (1, 2, 0));
        // A NaN component loses every comparison, and so does a component compared with it.
        assert_eq!(axes([f32::NAN, 1.0, 2.0]), (2, 0, 1));
        assert_eq!(axes([1.0, f32::NAN, 0.5]), (2, 0, 1));
        assert_eq!(axes([1.0, 0.5, f32::NAN]), (2, 0, 1));
    }
}
