//! Typed, zero-copy views over packed ray and hit buffers: they borrow the bytes (e.g. a trace result's `Bytes`)
//! and decode one record at a time with the engine's formats.

use rayd_engine::format::{Hit, HitFormat, Ray, RayFormat};

use crate::error::{Error, Result};

/// A packed ray buffer read as rays.
#[derive(Debug, Clone, Copy)]
pub struct RayView<'a> {
    /// The packed records, a whole number of them.
    bytes: &'a [u8],
    /// How each record is packed.
    format: RayFormat,
}

impl<'a> RayView<'a> {
    /// A view of `bytes` as rays of `format`; fails unless the length is a whole number of rays.
    pub fn new(bytes: &'a [u8], format: RayFormat) -> Result<RayView<'a>> {
        if !bytes.len().is_multiple_of(format.size()) {
            return Err(Error::InvalidArgument(format!(
                "rays: {} bytes is not a whole number of {}-byte {} rays",
                bytes.len(),
                format.size(),
                format.name()
            )));
        }
        Ok(RayView { bytes, format })
    }

    /// Number of rays.
    pub fn len(&self) -> usize {
        self.bytes.len() / self.format.size()
    }

    /// Whether there are no rays.
    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Ray `index`, decoded; fields the format lacks have [`Ray::default`]'s values. Panics past the end.
    pub fn get(&self, index: usize) -> Ray {
        let size = self.format.size();
        self.format.decode(&self.bytes[index * size..(index + 1) * size])
    }

    /// Every ray, in order.
    pub fn iter(&self) -> impl ExactSizeIterator<Item = Ray> + '_ {
        (0..self.len()).map(|i| self.get(i))
    }
}

/// A packed hit buffer read as hits.
#[derive(Debug, Clone, Copy)]
pub struct HitView<'a> {
    /// The packed records (for the bitmask, `ceil(len / 8)` bytes).
    bytes: &'a [u8],
    /// How each record is packed.
    format: HitFormat,
    /// Number of records; needed because a bitmask's byte length does not say it.
    len: usize,
}

impl<'a> HitView<'a> {
    /// A view of `records` hit records of `format` in `bytes`; fails unless the length is exactly
    /// `format.buffer_len(records)`. For an `all` query there are `max_hits_per_ray` records a ray, those of ray
    /// `r` at `r * max_hits_per_ray ..`.
    pub fn new(bytes: &'a [u8], format: HitFormat, records: usize) -> Result<HitView<'a>> {
        let expected = format.buffer_len(records);
        if bytes.len() != expected {
            return Err(Error::InvalidArgument(format!(
                "hits: {records} {} records take {expected} bytes, not {}",
                format.name(),
                bytes.len()
            )));
        }
        Ok(HitView { bytes, format, len: records })
    }

    /// Number of records.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether there are no records.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Whether record `index` is a hit, for every format: the bitmask's bit, a primitive id other than −1, or in
    /// the `t` format (no id) `t >= 0` ([`Hit::is_hit`]).
    pub fn is_hit(&self, index: usize) -> bool {
        self.get(index).is_hit()
    }

    /// Record `index`, decoded by [`HitFormat::read`]: fields the format does not carry read as in [`Hit::MISS`], a
    /// bitmask hit as `t = 0`. Panics past the end.
    pub fn get(&self, index: usize) -> Hit {
        assert!(index < self.len, "record {index} of {}", self.len);
        self.format.read(self.bytes, index)
    }

    /// Every record, in order.
    pub fn iter(&self) -> impl ExactSizeIterator<Item = Hit> + '_ {
        (0..self.len).map(|i| self.get(i))
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3A;
    use rayd_engine::format::{InstancePath, MISS_ID};

    use super::*;

    /// A hit with every field set, its normal already unit length so that `full` round-trips it exactly.
    const HIT: Hit = Hit {
        t: 2.5,
        prim_id: 7,
        geom_id: 3,
        inst_id: 9,
        inst_path: InstancePath::EMPTY.push(4).push(9),
        u: 0.25,
        v: 0.5,
        normal: Vec3A::new(0.0, -1.0, 0.0),
        back_face: true,
    };

    /// `hits` packed in `format` with the engine's own writer.
    fn packed(format: HitFormat, hits: &[Hit]) -> Vec<u8> {
        let mut bytes = vec![0u8; format.buffer_len(hits.len())];
        for (i, hit) in hits.iter().enumerate() {
            format.write(&mut bytes, i, hit);
        }
        bytes
    }

    /// `value` if the format carries the field, else `default`.
    fn pick<T>(carried: bool, value: T, default: T) -> T {
        if carried { value } else { default }
    }

    #[test]
    fn every_format_reads_back_the_fields_it_carries_and_misses_stay_misses() {
        for format in HitFormat::ALL {
            let bytes = packed(format, &[HIT, Hit::MISS]);
            let view = HitView::new(&bytes, format, 2).unwrap();
            let (hit, miss) = (view.get(0), view.get(1));
            assert!(view.is_hit(0) && hit.is_hit() && !view.is_hit(1) && !miss.is_hit(), "{format:?}");
            assert_eq!(miss, Hit::MISS, "{format:?}");
            let carries = |name: &str| match format {
                HitFormat::Bitmask => false,
                HitFormat::T => name == "t",
                HitFormat::TTriid => matches!(name, "t" | "prim"),
                HitFormat::TTriidUV => matches!(name, "t" | "prim" | "uv"),
                HitFormat::TTriidInstid => matches!(name, "t" | "prim" | "inst"),
                HitFormat::TTriidInstidUV => matches!(name, "t" | "prim" | "inst" | "uv"),
                HitFormat::Full => true,
            };
            assert_eq!(hit.t, pick(carries("t"), HIT.t, 0.0), "{format:?}");
            assert_eq!(hit.prim_id, pick(carries("prim"), HIT.prim_id, MISS_ID), "{format:?}");
            assert_eq!(hit.inst_id, pick(carries("inst"), HIT.inst_id, MISS_ID), "{format:?}");
            assert_eq!((hit.u, hit.v), pick(carries("uv"), (HIT.u, HIT.v), (0.0, 0.0)), "{format:?}");
            assert_eq!(hit.geom_id, pick(carries("full"), HIT.geom_id, MISS_ID), "{format:?}");
            assert_eq!(hit.normal, pick(carries("full"), HIT.normal, Vec3A::ZERO), "{format:?}");
            assert_eq!(hit.back_face, pick(carries("full"), true, false), "{format:?}");
            assert_eq!(hit.inst_path, pick(carries("full"), HIT.inst_path, InstancePath::EMPTY), "{format:?}");
        }
    }

    #[test]
    fn bitmask_view_needs_the_record_count_and_reads_bits_lsb_first() {
        let hits: Vec<Hit> = (0..11).map(|i| if i % 3 == 0 { HIT } else { Hit::MISS }).collect();
        let bytes = packed(HitFormat::Bitmask, &hits);
        assert_eq!(bytes, [0b0100_1001, 0b0000_0010]);
        let view = HitView::new(&bytes, HitFormat::Bitmask, 11).unwrap();
        assert_eq!(
            view.iter().map(|h| h.is_hit()).collect::<Vec<_>>(),
            hits.iter().map(Hit::is_hit).collect::<Vec<_>>()
        );
        assert!(HitView::new(&bytes, HitFormat::Bitmask, 17).is_err());
        assert!(HitView::new(&bytes[..15.min(bytes.len())], HitFormat::T, 4).is_err());
    }

    #[test]
    fn ray_view_decodes_each_record_and_rejects_partial_rays() {
        let format = RayFormat::OriginTminDirectionTmax;
        let rays: Vec<Ray> =
            (0..3).map(|i| Ray { origin: Vec3A::splat(i as f32), tmin: 0.5, tmax: 9.0, ..Ray::default() }).collect();
        let mut bytes = vec![0u8; 3 * format.size()];
        for (ray, slot) in rays.iter().zip(bytes.chunks_exact_mut(format.size())) {
            format.encode(ray, slot);
        }
        let view = RayView::new(&bytes, format).unwrap();
        assert_eq!(view.len(), 3);
        assert_eq!(view.iter().collect::<Vec<_>>(), rays);
        assert!(RayView::new(&bytes[..40], format).is_err());
    }
}
