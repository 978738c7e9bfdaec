//! Secondary rays: rays that continue an earlier trace from its hits — a reflection, or a shadow ray towards a point
//! light — made ray by ray from the primary ray and its hit record, like every other generator.
//!
//! Ray `i` starts where primary ray `i` hit (`origin + t · direction`), moved `offset` world units along the hit's
//! geometric normal to the side the primary ray came from. A reflection goes along the mirrored unit direction
//! (`tmin` 0, `tmax` +∞); a shadow ray along the unit direction to the light, reaching the light less `offset`. A
//! primary ray that missed gives a ray with a zero direction, which hits nothing. Time, mask, visibility and flags
//! are the primary ray's.

use bytes::Bytes;
use glam::{Vec3, Vec3A};

use super::generator::{Generator, require, unit};
use crate::error::Result;
use crate::format::{HitFormat, Ray, RayFormat};

/// Bytes of one primary hit record (the `Full` hit format: it carries the geometric normal).
const HIT_BYTES: usize = 80;
/// Byte offset of the normal in a `Full` hit record.
const NORMAL_OFFSET: usize = 24;
/// Primary rays made at a time from a generator, on the stack.
const PRIMARY_BLOCK: usize = 64;

/// Where the primary rays come from.
#[derive(Debug, Clone, PartialEq)]
pub enum Primary {
    /// Packed rays in this format (a server-side buffer, or the caller's).
    Packed(RayFormat, Bytes),
    /// Made by a generator (not itself secondary).
    Generated(Box<Generator>),
}

/// What a secondary ray does at its primary ray's hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Bounce {
    /// Mirror reflection about the geometric normal.
    Reflect,
    /// Towards a point light at this position (a shadow ray: trace with an `any` query).
    TowardsLight(Vec3),
}

/// Rays that continue an earlier trace from its hits.
#[derive(Debug, Clone, PartialEq)]
pub struct Secondary {
    /// The earlier trace's rays.
    pub primary: Primary,
    /// Its hits: one `Full` record a primary ray (a `closest` or `any` trace).
    pub hits: Bytes,
    /// What each ray does at its primary's hit.
    pub bounce: Bounce,
    /// How far origins move off the surface (world units, ≥ 0), so a ray does not hit the triangle it leaves.
    pub offset: f32,
}

impl Primary {
    /// Primary rays.
    fn count(&self) -> u64 {
        match self {
            Primary::Packed(format, bytes) => (bytes.len() / format.size()) as u64,
            Primary::Generated(generator) => generator.count(),
        }
    }

    /// Calls `each` with primary rays `first ..` in order, one for each slot of `out` (`size` bytes a slot).
    fn for_each(&self, first: u64, out: &mut [u8], size: usize, mut each: impl FnMut(&mut [u8], &Ray, u64)) {
        match self {
            Primary::Packed(format, bytes) => {
                let ray_size = format.size();
                for (i, slot) in out.chunks_exact_mut(size).enumerate() {
                    let index = first + i as u64;
                    let at = index as usize * ray_size;
                    each(slot, &format.decode(&bytes[at..at + ray_size]), index);
                }
            }
            Primary::Generated(generator) => {
                // The richest format: every field a generator sets.
                let format = RayFormat::Full;
                let mut block = [0u8; PRIMARY_BLOCK * RayFormat::Full.size()];
                for (b, slots) in out.chunks_mut(PRIMARY_BLOCK * size).enumerate() {
                    let block_first = first + (b * PRIMARY_BLOCK) as u64;
                    let rays = &mut block[..slots.len() / size * format.size()];
                    generator.fill(format, block_first, rays);
                    for (i, (slot, ray)) in
                        slots.chunks_exact_mut(size).zip(rays.chunks_exact(format.size())).enumerate()
                    {
                        each(slot, &format.decode(ray), block_first + i as u64);
                    }
                }
            }
        }
    }
}

impl Secondary {
    /// Checks the parts: packed primary rays (at least one) whose times are numbers, a primary that is not itself
    /// secondary, one `Full` hit record a primary ray, a finite light, a finite offset ≥ 0; INVALID_ARGUMENT naming
    /// the field.
    pub fn check(&self) -> Result<()> {
        match &self.primary {
            Primary::Packed(format, bytes) => {
                require(bytes.len().is_multiple_of(format.size()), "generator.secondary.primary_rays", || {
                    format!(
                        "{} bytes is not a whole number of {}-byte {} rays",
                        bytes.len(),
                        format.size(),
                        format.name()
                    )
                })?;
                // A secondary ray takes its primary ray's time: a NaN one is refused as in packed rays.
                let nan = format.first_nan_time(bytes);
                require(nan.is_none(), "generator.secondary.primary_rays", || {
                    format!("ray {} has time NaN; a ray's time must be a number", nan.unwrap_or(0))
                })?;
                require(!bytes.is_empty(), "generator.secondary.primary_rays", || "must hold at least one ray".into())?;
            }
            Primary::Generated(generator) => {
                require(
                    !matches!(**generator, Generator::Secondary(_)),
                    "generator.secondary.primary_generator",
                    || "must not itself be secondary".into(),
                )?;
                generator.check()?
            }
        }
        let rays = self.primary.count();
        let records = self.hits.len() / HIT_BYTES;
        require(
            self.hits.len().is_multiple_of(HIT_BYTES) && records as u64 == rays,
            "generator.secondary.primary_hits",
            || {
                format!(
                    "{} bytes must be one {}-byte {} hit record for each of the {rays} primary rays",
                    self.hits.len(),
                    HIT_BYTES,
                    HitFormat::Full.name()
                )
            },
        )?;
        if let Bounce::TowardsLight(light) = self.bounce {
            require(light.is_finite(), "generator.secondary.towards_light", || "must be finite".into())?;
        }
        let offset = self.offset;
        require(offset.is_finite() && offset >= 0.0, "generator.secondary.offset", || {
            format!("{offset} must be finite and ≥ 0")
        })
    }

    /// Rays it makes: one a primary ray.
    pub fn count(&self) -> u64 {
        self.primary.count()
    }

    /// Packs rays `first .. first + out.len() / format.size()` in `format` into `out` (checked, and holding them).
    pub fn fill(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        self.primary.for_each(first, out, format.size(), |slot, primary, index| {
            let at = index as usize * HIT_BYTES;
            format.encode(&self.ray(primary, &self.hits[at..at + HIT_BYTES]), slot);
        });
    }

    /// The secondary ray of `primary` and its `Full` hit record.
    fn ray(&self, primary: &Ray, hit: &[u8]) -> Ray {
        let f32_at = |at: usize| f32::from_le_bytes(hit[at..at + 4].try_into().expect("4 bytes"));
        let t = f32_at(0);
        let missed = Ray { direction: Vec3A::ZERO, ..*primary };
        if !HitFormat::Full.read(hit, 0).is_hit() {
            return missed;
        }
        // Made unit here: the records may be the caller's. One without a direction, or a hit at no finite t,
        // makes a ray that hits nothing, as a miss does.
        let normal = unit(Vec3::new(f32_at(NORMAL_OFFSET), f32_at(NORMAL_OFFSET + 4), f32_at(NORMAL_OFFSET + 8)));
        if normal == Vec3::ZERO || !t.is_finite() {
            return missed;
        }
        let normal = Vec3A::from(normal);
        // The normal on the side the primary ray came from.
        let facing = if normal.dot(primary.direction) > 0.0 { -normal } else { normal };
        let origin = primary.origin + primary.direction * t + facing * self.offset;
        let (direction, tmax) = match self.bounce {
            Bounce::Reflect => {
                let d = primary.direction.normalize_or_zero();
                ((d - 2.0 * d.dot(normal) * normal).normalize_or_zero(), f32::INFINITY)
            }
            Bounce::TowardsLight(light) => {
                let to_light = Vec3A::from(light) - origin;
                let distance = to_light.length();
                (to_light.normalize_or_zero(), (distance - self.offset).max(0.0))
            }
        };
        Ray { origin, direction, tmin: 0.0, tmax, ..*primary }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::Hit;

    /// A `Full` hit record at `t` with the unit `normal` on primitive 0, or a miss's record where `t` < 0.
    fn hit(t: f32, normal: Vec3) -> Vec<u8> {
        let hit = match t < 0.0 {
            true => Hit::MISS,
            false => Hit { t, prim_id: 0, normal: normal.into(), ..Hit::MISS },
        };
        let mut record = vec![0u8; HIT_BYTES];
        HitFormat::Full.write(&mut record, 0, &hit);
        record
    }

    /// Two primary rays down onto the plane y = 0 (a hit at t = 2 on a normal facing down, so the facing side is
    /// up; and a miss), packed with time and the secondary rays they make.
    fn secondary(bounce: Bounce) -> Vec<Ray> {
        secondary_after(bounce, hit(2.0, Vec3::NEG_Y))
    }

    /// [`secondary`]'s rays with `first` as the first primary ray's hit record.
    fn secondary_after(bounce: Bounce, first: Vec<u8>) -> Vec<Ray> {
        let down = Ray {
            origin: Vec3A::new(0.0, 2.0, 0.0),
            direction: Vec3A::new(1.0, -1.0, 0.0),
            time: 0.5,
            ..Ray::default()
        };
        let format = RayFormat::OriginTminDirectionTmaxTime;
        let mut rays = vec![0u8; 2 * format.size()];
        format.encode(&down, &mut rays[..format.size()]);
        format.encode(&down, &mut rays[format.size()..]);
        let hits = [first, hit(-1.0, Vec3::ZERO)].concat();
        let secondary = Secondary {
            primary: Primary::Packed(format, Bytes::from(rays)),
            hits: Bytes::from(hits),
            bounce,
            offset: 0.01,
        };
        secondary.check().unwrap();
        let mut out = vec![0u8; 2 * format.size()];
        secondary.fill(format, 0, &mut out);
        out.chunks_exact(format.size()).map(|r| format.decode(r)).collect()
    }

    #[test]
    fn a_reflection_leaves_the_hit_point_on_the_incoming_side_mirrored() {
        let [reflected, missed] = secondary(Bounce::Reflect).try_into().unwrap();
        assert_eq!(reflected.origin, Vec3A::new(2.0, 0.01, 0.0));
        let expected = Vec3A::new(1.0, 1.0, 0.0).normalize();
        assert!((reflected.direction - expected).length() < 1e-6, "{:?}", reflected.direction);
        assert_eq!((reflected.tmin, reflected.tmax, reflected.time), (0.0, f32::INFINITY, 0.5));
        assert_eq!(missed.direction, Vec3A::ZERO, "a miss makes a ray that hits nothing");
    }

    #[test]
    fn the_callers_hit_records_are_made_unit_or_make_rays_that_hit_nothing() {
        // A normal twice as long: the same rays.
        assert_eq!(secondary_after(Bounce::Reflect, hit(2.0, Vec3::new(0.0, -2.0, 0.0))), secondary(Bounce::Reflect));
        for (t, normal) in [(2.0, Vec3::ZERO), (2.0, Vec3::NAN), (f32::INFINITY, Vec3::NEG_Y)] {
            let [made, _] = secondary_after(Bounce::Reflect, hit(t, normal)).try_into().unwrap();
            assert_eq!(made.direction, Vec3A::ZERO, "t {t}, normal {normal}: hits nothing");
        }
    }

    #[test]
    fn a_shadow_ray_heads_for_the_light_and_stops_short_of_it() {
        let [shadow, _] = secondary(Bounce::TowardsLight(Vec3::new(2.0, 4.01, 0.0))).try_into().unwrap();
        assert_eq!(shadow.origin, Vec3A::new(2.0, 0.01, 0.0));
        assert_eq!(shadow.direction, Vec3A::Y);
        assert!((shadow.tmax - 3.99).abs() < 1e-6, "{}", shadow.tmax);
    }

    #[test]
    fn primaries_from_a_generator_give_the_rays_their_packed_bytes_give() {
        let camera = super::super::Camera::framing(Vec3::ZERO, Vec3::ONE, 13, 11);
        let generator = Generator::Pinhole(camera, super::super::PixelSampling { samples: 1, jitter_seed: Some(3) });
        let count = generator.count() as usize;
        let hits: Vec<u8> =
            (0..count).flat_map(|i| hit(if i % 3 == 0 { -1.0 } else { i as f32 * 0.1 }, Vec3::Z)).collect();
        let format = RayFormat::Full;
        let packed = Primary::Packed(format, Bytes::from(generator.rays(format)));
        let make = |primary| {
            let secondary =
                Secondary { primary, hits: Bytes::from(hits.clone()), bounce: Bounce::Reflect, offset: 1e-3 };
            secondary.check().unwrap();
            let mut out = vec![0u8; (count - 5) * format.size()];
            secondary.fill(format, 5, &mut out);
            out
        };
        assert_eq!(make(Primary::Generated(Box::new(generator))), make(packed));
    }

    #[test]
    fn bad_parts_are_refused_naming_the_field() {
        let format = RayFormat::OriginDirection;
        let refused = |secondary: Secondary| match secondary.check() {
            Err(crate::error::Error::InvalidQuery { field, .. }) => field,
            other => panic!("{other:?}"),
        };
        let base = Secondary {
            primary: Primary::Packed(format, Bytes::from(vec![0u8; 2 * format.size()])),
            hits: Bytes::from(vec![0u8; 2 * HIT_BYTES]),
            bounce: Bounce::Reflect,
            offset: 0.0,
        };
        base.check().unwrap();
        let short = Secondary { hits: Bytes::from(vec![0u8; HIT_BYTES]), ..base.clone() };
        assert_eq!(refused(short), "generator.secondary.primary_hits");
        let ragged = Secondary { primary: Primary::Packed(format, Bytes::from(vec![0u8; 25])), ..base.clone() };
        assert_eq!(refused(ragged), "generator.secondary.primary_rays");
        let none = Secondary { primary: Primary::Packed(format, Bytes::new()), hits: Bytes::new(), ..base.clone() };
        assert_eq!(refused(none), "generator.secondary.primary_rays");
        let timed = RayFormat::Full;
        let mut rays = vec![0u8; 2 * timed.size()];
        timed.encode(&Ray { time: f32::NAN, ..Ray::default() }, &mut rays[timed.size()..]);
        let at_nan = Secondary { primary: Primary::Packed(timed, Bytes::from(rays)), ..base.clone() };
        assert_eq!(refused(at_nan), "generator.secondary.primary_rays", "ray 1's time is NaN");
        let nested =
            Secondary { primary: Primary::Generated(Box::new(Generator::Secondary(base.clone()))), ..base.clone() };
        assert_eq!(refused(nested), "generator.secondary.primary_generator");
        // Shadow rays need their tmax (the light's distance) in the format they are traced in; reflections do not.
        let shadows = Generator::Secondary(Secondary { bounce: Bounce::TowardsLight(Vec3::Y), ..base.clone() });
        let lost = shadows.check_format(RayFormat::OriginDirection).unwrap_err().to_string();
        assert!(lost.contains("no tmax, which generator.secondary.towards_light"), "{lost}");
        shadows.check_format(RayFormat::OriginMaskDirectionTmax).unwrap();
        Generator::Secondary(base.clone()).check_format(RayFormat::OriginDirection).unwrap();
        let light = Secondary { bounce: Bounce::TowardsLight(Vec3::NAN), ..base.clone() };
        assert_eq!(refused(light), "generator.secondary.towards_light");
        assert_eq!(refused(Secondary { offset: -1.0, ..base }), "generator.secondary.offset");
    }
}
