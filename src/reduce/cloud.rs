//! The point-cloud reduction: the hit points of a trace (a lidar scan's returns), in ray order, in a compact
//! encoding.

use glam::Vec3;

use super::Partial;
use crate::error::Result;
use crate::query::Query;

/// Every hit point `p = origin + t·direction` (computed in f32, a multiply then an add per component), one record
/// a hit record in ray order: the point, then, if `ray_indices`, the ray's index in the batch as a little-endian
/// u32.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointCloud {
    /// How a point is written.
    pub encoding: PointEncoding,
    /// The quantization step of the integer encodings, in world units (> 0).
    pub step: f32,
    /// The point the integer encodings are relative to.
    pub origin: Vec3,
    /// Whether each point is followed by its ray's index.
    pub ray_indices: bool,
}

/// How a point is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PointEncoding {
    /// x, y, z as little-endian f32 (12 bytes).
    Float32,
    /// `round((p − origin) / step)` per component as little-endian i32 (12 bytes); points out of range are left
    /// out and counted.
    Int32,
    /// The same as i16 (6 bytes).
    Int16,
}

impl PointCloud {
    /// Checks the step and origin of the integer encodings, and that a batch of `rays` has u32 ray indices where
    /// they are asked for.
    pub(super) fn check(&self, rays: u64) -> Result<()> {
        if self.ray_indices && rays > 1 << 32 {
            let rule = format!("the batch's {rays} rays have indices past u32's: at most 2^32 rays with them");
            return Err(super::invalid("reduction.point_cloud.ray_indices", rule));
        }
        if self.encoding != PointEncoding::Float32 {
            if !(self.step.is_finite() && self.step > 0.0) {
                return Err(super::invalid(
                    "reduction.point_cloud.step",
                    format!("{} must be finite and > 0", self.step),
                ));
            }
            if !self.origin.is_finite() {
                return Err(super::invalid("reduction.point_cloud.origin", "must be finite".into()));
            }
        }
        Ok(())
    }

    /// Bytes a point takes in the answer: the point in its encoding, then its ray's index where asked for.
    pub fn record_bytes(&self) -> usize {
        let point = match self.encoding {
            PointEncoding::Float32 | PointEncoding::Int32 => 12,
            PointEncoding::Int16 => 6,
        };
        point + if self.ray_indices { 4 } else { 0 }
    }

    /// The points of one piece, whose first ray is `first_ray` of the batch (hits in [`crate::format::HitFormat::TTriid`]).
    pub(super) fn reduce(&self, traced: &Query, first_ray: u64, rays: &[u8], hits: &[u8]) -> Partial {
        let (ray_size, records) = (traced.ray_format.size(), traced.records_per_ray());
        let (mut bytes, mut dropped) = (Vec::new(), 0);
        for (index, ray) in rays.chunks_exact(ray_size).enumerate() {
            let ray = traced.ray_format.decode(ray);
            for record in index * records..(index + 1) * records {
                let hit = traced.hit_format.read(hits, record);
                if !hit.is_hit() {
                    continue;
                }
                let point = Vec3::from(ray.origin) + Vec3::from(ray.direction) * hit.t;
                if self.push_point(point, &mut bytes) {
                    if self.ray_indices {
                        bytes.extend_from_slice(&((first_ray + index as u64) as u32).to_le_bytes());
                    }
                } else {
                    dropped += 1;
                }
            }
        }
        Partial::Ordered { bytes, dropped }
    }

    /// Appends `point` encoded; false (nothing appended) if it is out of the encoding's range.
    fn push_point(&self, point: Vec3, out: &mut Vec<u8>) -> bool {
        let range = match self.encoding {
            PointEncoding::Float32 => {
                point.to_array().iter().for_each(|c| out.extend_from_slice(&c.to_le_bytes()));
                return true;
            }
            PointEncoding::Int32 => i64::from(i32::MIN)..=i64::from(i32::MAX),
            PointEncoding::Int16 => i64::from(i16::MIN)..=i64::from(i16::MAX),
        };
        let quantized = ((point - self.origin) / self.step).round();
        // `as` saturates, so a huge value stays out of range; a point that is not finite is left out too.
        let components = quantized.to_array().map(|c| c as i64);
        if !quantized.is_finite() || components.iter().any(|c| !range.contains(c)) {
            return false;
        }
        for c in components {
            match self.encoding {
                PointEncoding::Int16 => out.extend_from_slice(&(c as i16).to_le_bytes()),
                _ => out.extend_from_slice(&(c as i32).to_le_bytes()),
            }
        }
        true
    }
}
