//! Ray formats: OptiX Prime's three, and two that carry a per-ray time for motion blur.

use glam::{Vec3A, Vec4};

use super::{read_f32, read_u32, write_f32, write_u32};

bitflags::bitflags! {
    /// Per-ray flags (the `flags` field of [`RayFormat::Full`]); a query's flags are OR-ed into every ray's.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
    pub struct RayFlags: u32 {
        /// Skip triangles whose back face the ray sees (see [`crate::intersect::triangle`] for facing).
        const CULL_BACK_FACING = 1;
        /// Skip triangles whose front face the ray sees.
        const CULL_FRONT_FACING = 1 << 1;
        /// Stop at the first hit found, whatever the query (it is then not necessarily the closest).
        const TERMINATE_ON_FIRST_HIT = 1 << 2;
    }
}

/// A decoded ray. Formats without a field give it its default: `tmin` 0, `tmax` +∞, `time` 0, `mask` 0,
/// `visibility` 0xFF, `flags` empty.
///
/// Laid out in field order (`repr(C)`): the CPU's packets read the first 48 bytes (origin, direction, then `tmin`,
/// `tmax`, `time` and `mask`) 16 at a time.
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C)]
pub struct Ray {
    /// Origin, in world units.
    pub origin: Vec3A,
    /// Direction; need not be normalized, and `t` is measured in units of its length.
    pub direction: Vec3A,
    /// Smallest accepted hit distance (inclusive).
    pub tmin: f32,
    /// Largest accepted hit distance (inclusive).
    pub tmax: f32,
    /// The time at which the scene is intersected (motion blur); 0 for formats without time.
    pub time: f32,
    /// Prime masking: a triangle is skipped when `mask & triangle_mask != 0`.
    pub mask: u32,
    /// OptiX instance visibility: the ray sees an instance when `visibility & instance_mask != 0`.
    pub visibility: u8,
    /// Per-ray flags; unknown bits are ignored.
    pub flags: RayFlags,
}

impl Default for Ray {
    fn default() -> Self {
        Ray {
            origin: Vec3A::ZERO,
            direction: Vec3A::Z,
            tmin: 0.0,
            tmax: f32::INFINITY,
            time: 0.0,
            mask: 0,
            visibility: 0xFF,
            flags: RayFlags::empty(),
        }
    }
}

/// How rays are packed in a ray buffer. Offsets are in bytes; every field is 4 bytes, little-endian.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RayFormat {
    /// Prime `RAY_ORIGIN_DIRECTION`, 24 bytes: `0 origin.xyz f32×3 | 12 direction.xyz f32×3`.
    /// `tmin` = 0, `tmax` = +∞.
    OriginDirection,
    /// Prime `RAY_ORIGIN_TMIN_DIRECTION_TMAX`, 32 bytes:
    /// `0 origin.xyz f32×3 | 12 tmin f32 | 16 direction.xyz f32×3 | 28 tmax f32`.
    OriginTminDirectionTmax,
    /// Prime `RAY_ORIGIN_MASK_DIRECTION_TMAX`, 32 bytes:
    /// `0 origin.xyz f32×3 | 12 mask u32 | 16 direction.xyz f32×3 | 28 tmax f32`. `tmin` = 0.
    OriginMaskDirectionTmax,
    /// 36 bytes: `0 origin.xyz f32×3 | 12 tmin f32 | 16 direction.xyz f32×3 | 28 tmax f32 | 32 time f32`.
    OriginTminDirectionTmaxTime,
    /// Everything, 48 bytes, 16-byte aligned records:
    /// `0 origin.xyz f32×3 | 12 tmin f32 | 16 direction.xyz f32×3 | 28 tmax f32 | 32 time f32 | 36 mask u32 |
    /// 40 flags u32 ([`RayFlags`]) | 44 visibility u32 (low 8 bits: the instance visibility mask; higher bits
    /// ignored)`. A full ray with visibility 0 sees no instance (as in OptiX); other formats see every instance.
    Full,
}

impl RayFormat {
    /// Every ray format, in the order of the contract's enum.
    pub const ALL: [RayFormat; 5] = [
        RayFormat::OriginDirection,
        RayFormat::OriginTminDirectionTmax,
        RayFormat::OriginMaskDirectionTmax,
        RayFormat::OriginTminDirectionTmaxTime,
        RayFormat::Full,
    ];

    /// Bytes per ray.
    pub const fn size(self) -> usize {
        match self {
            RayFormat::OriginDirection => 24,
            RayFormat::OriginTminDirectionTmax | RayFormat::OriginMaskDirectionTmax => 32,
            RayFormat::OriginTminDirectionTmaxTime => 36,
            RayFormat::Full => 48,
        }
    }

    /// The format's name in lower case, as used by the contract and `rayctl`.
    pub const fn name(self) -> &'static str {
        match self {
            RayFormat::OriginDirection => "origin_direction",
            RayFormat::OriginTminDirectionTmax => "origin_tmin_direction_tmax",
            RayFormat::OriginMaskDirectionTmax => "origin_mask_direction_tmax",
            RayFormat::OriginTminDirectionTmaxTime => "origin_tmin_direction_tmax_time",
            RayFormat::Full => "full",
        }
    }

    /// Whether a ray of this format carries its `tmin` (without it, a ray starts at 0).
    pub const fn has_tmin(self) -> bool {
        !matches!(self, RayFormat::OriginDirection | RayFormat::OriginMaskDirectionTmax)
    }

    /// Whether a ray of this format carries its `tmax` (without it, a ray reaches +∞).
    pub const fn has_tmax(self) -> bool {
        !matches!(self, RayFormat::OriginDirection)
    }

    /// Byte offset of the time within a ray, for the formats that carry one.
    pub const fn time_offset(self) -> Option<usize> {
        match self {
            RayFormat::OriginTminDirectionTmaxTime | RayFormat::Full => Some(32),
            _ => None,
        }
    }

    /// The first of packed `rays` whose time (in the formats that carry one) is NaN, if any.
    pub fn first_nan_time(self, rays: &[u8]) -> Option<usize> {
        let offset = self.time_offset()?;
        rays.chunks_exact(self.size()).position(|ray| super::read_f32(ray, offset).is_nan())
    }

    /// How many rays `bytes` bytes of rays packed in this format hold; the rule they break when they are not whole
    /// rays.
    pub fn whole_rays(self, bytes: usize) -> Result<usize, String> {
        let size = self.size();
        if !bytes.is_multiple_of(size) {
            return Err(format!("{bytes} bytes is not a multiple of {size} ({})", self.name()));
        }
        Ok(bytes / size)
    }

    /// Looks a format up by [`RayFormat::name`].
    pub fn from_name(name: &str) -> Option<RayFormat> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Decodes one ray from exactly [`RayFormat::size`] bytes.
    #[inline(always)]
    pub fn decode(self, b: &[u8]) -> Ray {
        // Where the record has 16 bytes from a vector, they are read whole (a `Vec3A`'s fourth float is unused).
        let vec3 = |offset: usize| match b.get(offset..offset + 16) {
            Some(quarter) => Vec3A::from_vec4(Vec4::from_array(std::array::from_fn(|i| read_f32(quarter, 4 * i)))),
            None => Vec3A::new(read_f32(b, offset), read_f32(b, offset + 4), read_f32(b, offset + 8)),
        };
        let origin = vec3(0);
        let direction = if matches!(self, RayFormat::OriginDirection) { vec3(12) } else { vec3(16) };
        let mut ray = Ray { origin, direction, ..Ray::default() };
        match self {
            RayFormat::OriginDirection => {}
            RayFormat::OriginTminDirectionTmax => {
                ray.tmin = read_f32(b, 12);
                ray.tmax = read_f32(b, 28);
            }
            RayFormat::OriginMaskDirectionTmax => {
                ray.mask = read_u32(b, 12);
                ray.tmax = read_f32(b, 28);
            }
            RayFormat::OriginTminDirectionTmaxTime => {
                ray.tmin = read_f32(b, 12);
                ray.tmax = read_f32(b, 28);
                ray.time = read_f32(b, 32);
            }
            RayFormat::Full => {
                ray.tmin = read_f32(b, 12);
                ray.tmax = read_f32(b, 28);
                ray.time = read_f32(b, 32);
                ray.mask = read_u32(b, 36);
                ray.flags = RayFlags::from_bits_truncate(read_u32(b, 40));
                ray.visibility = read_u32(b, 44) as u8;
            }
        }
        ray
    }

    /// Calls `f` with this format as a constant, once in each arm of a match, so that a loop in `f` packing many
    /// rays ([`RayFormat::encode`]) is compiled once a format, without a match a ray.
    #[inline(always)]
    pub fn specialized<R>(self, mut f: impl FnMut(RayFormat) -> R) -> R {
        match self {
            RayFormat::OriginDirection => f(RayFormat::OriginDirection),
            RayFormat::OriginTminDirectionTmax => f(RayFormat::OriginTminDirectionTmax),
            RayFormat::OriginMaskDirectionTmax => f(RayFormat::OriginMaskDirectionTmax),
            RayFormat::OriginTminDirectionTmaxTime => f(RayFormat::OriginTminDirectionTmaxTime),
            RayFormat::Full => f(RayFormat::Full),
        }
    }

    /// Encodes one ray into exactly [`RayFormat::size`] bytes; fields the format lacks are dropped.
    #[inline(always)]
    pub fn encode(self, ray: &Ray, b: &mut [u8]) {
        let put3 = |b: &mut [u8], offset: usize, v: Vec3A| {
            for axis in 0..3 {
                write_f32(b, offset + 4 * axis, v[axis]);
            }
        };
        put3(b, 0, ray.origin);
        if self == RayFormat::OriginDirection {
            put3(b, 12, ray.direction);
            return;
        }
        put3(b, 16, ray.direction);
        write_f32(b, 28, ray.tmax);
        match self {
            RayFormat::OriginMaskDirectionTmax => write_u32(b, 12, ray.mask),
            _ => write_f32(b, 12, ray.tmin),
        }
        if matches!(self, RayFormat::OriginTminDirectionTmaxTime | RayFormat::Full) {
            write_f32(b, 32, ray.time);
        }
        if self == RayFormat::Full {
            write_u32(b, 36, ray.mask);
            write_u32(b, 40, ray.flags.bits());
            write_u32(b, 44, u32::from(ray.visibility));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_format_round_trips_the_fields_it_carries() {
        let ray = Ray {
            origin: Vec3A::new(1.0, -2.0, 3.5),
            direction: Vec3A::new(0.25, 0.5, -1.0),
            tmin: 0.125,
            tmax: 99.0,
            time: 0.75,
            mask: 0xdead_beef,
            visibility: 0x5a,
            flags: RayFlags::CULL_BACK_FACING | RayFlags::TERMINATE_ON_FIRST_HIT,
        };
        for format in RayFormat::ALL {
            let mut bytes = vec![0u8; format.size()];
            format.encode(&ray, &mut bytes);
            let back = format.decode(&bytes);
            assert_eq!(back.origin, ray.origin, "{format:?}");
            assert_eq!(back.direction, ray.direction, "{format:?}");
            let has_tmin = !matches!(format, RayFormat::OriginDirection | RayFormat::OriginMaskDirectionTmax);
            assert_eq!(back.tmin, if has_tmin { ray.tmin } else { 0.0 }, "{format:?}");
            let has_tmax = format != RayFormat::OriginDirection;
            assert_eq!(back.tmax, if has_tmax { ray.tmax } else { f32::INFINITY }, "{format:?}");
            let has_time = matches!(format, RayFormat::OriginTminDirectionTmaxTime | RayFormat::Full);
            assert_eq!(back.time, if has_time { ray.time } else { 0.0 }, "{format:?}");
            let has_mask = matches!(format, RayFormat::OriginMaskDirectionTmax | RayFormat::Full);
            assert_eq!(back.mask, if has_mask { ray.mask } else { 0 }, "{format:?}");
            assert_eq!(back.flags, if format == RayFormat::Full { ray.flags } else { RayFlags::empty() });
            assert_eq!(back.visibility, if format == RayFormat::Full { ray.visibility } else { 0xFF });
            assert_eq!(RayFormat::from_name(format.name()), Some(format));
        }
    }

    #[test]
    fn prime_layout_puts_tmin_between_origin_and_direction() {
        let mut bytes = [0u8; 32];
        for (i, v) in [1.0f32, 2.0, 3.0, 0.5, 4.0, 5.0, 6.0, 7.0].iter().enumerate() {
            bytes[4 * i..4 * i + 4].copy_from_slice(&v.to_le_bytes());
        }
        let ray = RayFormat::OriginTminDirectionTmax.decode(&bytes);
        assert_eq!(ray.origin, Vec3A::new(1.0, 2.0, 3.0));
        assert_eq!(ray.tmin, 0.5);
        assert_eq!(ray.direction, Vec3A::new(4.0, 5.0, 6.0));
        assert_eq!(ray.tmax, 7.0);
    }
}
