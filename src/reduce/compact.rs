//! Compact hits: every ray's hit in a few bytes, for callers who need all hits but not 16–20 bytes of each.
//!
//! Rays are encoded in blocks of [`COMPACT_BLOCK_RAYS`]; within a block each ray takes
//! - `t` as a little-endian u16: `round((t − lo)/(hi − lo) · 65534)` clamped to 0 ..= 65,534, where `lo` is the
//!   ray's `tmin` and `hi` is the smaller of its `tmax` and `t_far` (0 when `hi ≤ lo`); 65,535 is a miss and ends
//!   the ray's record;
//! - for a hit, when the hit format has them: the primitive id, then the instance id, each as the zigzag LEB128
//!   varint of its difference (wrapping, as i32) from the same id of the previous hit in the block (0 before the
//!   block's first hit);
//! - then, when the hit format has them, `u` and `v` as u16 `round(x · 65535)`.
//!
//! Decoding needs the rays ([`decode_compact`]); the error in `t` is at most `(hi − lo)/131068`.

use super::Partial;
use crate::error::{Error, Result};
use crate::format::{Hit, HitFormat};
use crate::query::Query;

/// Rays whose ids are delta-encoded from each other; every block starts from 0.
pub const COMPACT_BLOCK_RAYS: u32 = 1024;

/// The u16 of a miss.
const MISS_T16: u16 = u16::MAX;

/// What a hit format puts in a compact record beyond `t`.
struct Fields {
    prim: bool,
    inst: bool,
    uv: bool,
}

/// The fields of `format` in a compact record, or INVALID_ARGUMENT naming `query.hit_format`.
fn fields(format: HitFormat) -> Result<Fields> {
    match format {
        HitFormat::T => Ok(Fields { prim: false, inst: false, uv: false }),
        HitFormat::TTriid => Ok(Fields { prim: true, inst: false, uv: false }),
        HitFormat::TTriidUV => Ok(Fields { prim: true, inst: false, uv: true }),
        HitFormat::TTriidInstid => Ok(Fields { prim: true, inst: true, uv: false }),
        HitFormat::TTriidInstidUV => Ok(Fields { prim: true, inst: true, uv: true }),
        other => Err(super::invalid(
            "query.hit_format",
            format!("compact hits encode t, ids and u, v; not {}", other.name()),
        )),
    }
}

/// Checks `t_far` and the hit format.
pub(super) fn check(query: &Query, t_far: f32) -> Result<()> {
    fields(query.hit_format)?;
    if !(t_far.is_finite() && t_far > 0.0) {
        return Err(super::invalid("reduction.compact.t_far", format!("{t_far} must be finite and > 0")));
    }
    Ok(())
}

/// The range `t` is quantized over for a ray of `tmin`, `tmax`.
fn range(tmin: f32, tmax: f32, t_far: f32) -> (f32, f32) {
    (tmin, tmax.min(t_far))
}

/// Encodes one piece whose first ray is `first_ray` (a multiple of [`COMPACT_BLOCK_RAYS`]), hits in the query's
/// own format.
pub(super) fn encode(traced: &Query, t_far: f32, first_ray: u64, rays: &[u8], hits: &[u8]) -> Partial {
    let fields = fields(traced.hit_format).expect("checked");
    let ray_size = traced.ray_format.size();
    let mut bytes = Vec::with_capacity(rays.len() / ray_size * 4);
    let (mut prim, mut inst) = (0u32, 0u32);
    for (index, ray) in rays.chunks_exact(ray_size).enumerate() {
        if (first_ray + index as u64).is_multiple_of(u64::from(COMPACT_BLOCK_RAYS)) {
            (prim, inst) = (0, 0);
        }
        let hit = traced.hit_format.read(hits, index);
        if !hit.is_hit() {
            bytes.extend_from_slice(&MISS_T16.to_le_bytes());
            continue;
        }
        let ray = traced.ray_format.decode(ray);
        let (lo, hi) = range(ray.tmin, ray.tmax, t_far);
        // In f64: hi − lo can pass f32's range (tmin −3e38, tmax 3e38).
        let (t, lo, hi) = (f64::from(hit.t), f64::from(lo), f64::from(hi));
        let q = if hi > lo { ((t - lo) / (hi - lo)).clamp(0.0, 1.0) * 65534.0 } else { 0.0 };
        bytes.extend_from_slice(&(q.round() as u16).to_le_bytes());
        if fields.prim {
            push_varint(&mut bytes, zigzag(hit.prim_id.wrapping_sub(prim) as i32));
            prim = hit.prim_id;
        }
        if fields.inst {
            push_varint(&mut bytes, zigzag(hit.inst_id.wrapping_sub(inst) as i32));
            inst = hit.inst_id;
        }
        if fields.uv {
            for x in [hit.u, hit.v] {
                bytes.extend_from_slice(&((x.clamp(0.0, 1.0) * 65535.0).round() as u16).to_le_bytes());
            }
        }
    }
    Partial::Ordered { bytes, dropped: 0 }
}

/// Decodes compact hits of `rays` (packed in `query.ray_format`, the batch from its first ray) into hits of
/// `query.hit_format`, with the `t_far` they were encoded with. INVALID_ARGUMENT if the bytes do not hold exactly
/// those rays' records.
pub fn decode_compact(query: &Query, t_far: f32, rays: &[u8], bytes: &[u8]) -> Result<Vec<Hit>> {
    let fields = fields(query.hit_format)?;
    let truncated = || Error::InvalidBlob("compact hits end inside a record".into());
    let mut at = 0usize;
    let mut take = |n: usize| -> Result<&[u8]> {
        let slice = bytes.get(at..at + n).ok_or_else(truncated)?;
        at += n;
        Ok(slice)
    };
    let mut hits = Vec::with_capacity(rays.len() / query.ray_format.size());
    let (mut prim, mut inst) = (0u32, 0u32);
    for (index, ray) in rays.chunks_exact(query.ray_format.size()).enumerate() {
        if (index as u64).is_multiple_of(u64::from(COMPACT_BLOCK_RAYS)) {
            (prim, inst) = (0, 0);
        }
        let q = u16::from_le_bytes(take(2)?.try_into().expect("2 bytes"));
        if q == MISS_T16 {
            hits.push(Hit::MISS);
            continue;
        }
        let ray = query.ray_format.decode(ray);
        let (lo, hi) = range(ray.tmin, ray.tmax, t_far);
        let (wide_lo, wide_hi) = (f64::from(lo), f64::from(hi));
        let t = if hi > lo { (wide_lo + f64::from(q) / 65534.0 * (wide_hi - wide_lo)) as f32 } else { lo };
        let mut hit = Hit { t, ..Hit::MISS };
        if fields.prim {
            prim = prim.wrapping_add(unzigzag(read_varint(&mut take)?) as u32);
            hit.prim_id = prim;
        }
        if fields.inst {
            inst = inst.wrapping_add(unzigzag(read_varint(&mut take)?) as u32);
            hit.inst_id = inst;
        }
        if fields.uv {
            let mut unorm =
                || -> Result<f32> { Ok(f32::from(u16::from_le_bytes(take(2)?.try_into().expect("2"))) / 65535.0) };
            (hit.u, hit.v) = (unorm()?, unorm()?);
        }
        hits.push(hit);
    }
    if at != bytes.len() {
        return Err(Error::InvalidBlob(format!("{} bytes follow the last ray's record", bytes.len() - at)));
    }
    Ok(hits)
}

/// Zigzag: small magnitudes of either sign become small unsigned numbers.
fn zigzag(value: i32) -> u32 {
    ((value << 1) ^ (value >> 31)) as u32
}

/// The inverse of [`zigzag`].
fn unzigzag(value: u32) -> i32 {
    ((value >> 1) as i32) ^ -((value & 1) as i32)
}

/// Appends `value` as LEB128: 7 bits a byte, least significant first, the high bit set on all but the last.
fn push_varint(out: &mut Vec<u8>, mut value: u32) {
    while value >= 0x80 {
        out.push((value as u8) | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
}

/// Reads a LEB128 value of at most 5 bytes through `take`.
fn read_varint<'a>(take: &mut impl FnMut(usize) -> Result<&'a [u8]>) -> Result<u32> {
    let mut value = 0u32;
    for shift in (0..35).step_by(7) {
        let byte = take(1)?[0];
        value |= u32::from(byte & 0x7f).checked_shl(shift).unwrap_or(0);
        if byte & 0x80 == 0 {
            return Ok(value);
        }
    }
    Err(Error::InvalidBlob("a varint longer than 5 bytes".into()))
}
