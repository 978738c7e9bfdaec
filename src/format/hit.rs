//! Hit formats: OptiX Prime's six, and a full one with every id, the barycentrics and the normal.

use glam::Vec3A;

use super::{read_f32, read_u32, write_f32, write_u32};

/// `t` written for a ray that hit nothing (Prime: any `t < 0` is a miss).
pub const MISS_T: f32 = -1.0;
/// Id written for "none": a missed ray's primitive, geometry and instance, and the instance of a hit outside any
/// instance (as `i32` it reads −1).
pub const MISS_ID: u32 = u32::MAX;

/// Instance ids a hit record has room for: more than the deepest graph can stack above a geometry.
pub const INSTANCE_PATH_SLOTS: usize = 8;

/// The user ids of the instances a hit was found through, top (the traced accel's instance) to bottom (the
/// instance of the geometry accel); unused slots hold [`MISS_ID`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct InstancePath {
    /// The ids, then [`MISS_ID`]s.
    ids: [u32; INSTANCE_PATH_SLOTS],
    /// How many ids there are.
    len: u8,
}

impl InstancePath {
    /// The path of a hit outside any instance.
    pub const EMPTY: InstancePath = InstancePath { ids: [MISS_ID; INSTANCE_PATH_SLOTS], len: 0 };

    /// The path one instance further down. The graph depth limit keeps paths shorter than the slots; a push
    /// beyond them panics.
    pub const fn push(mut self, instance_id: u32) -> InstancePath {
        self.ids[self.len as usize] = instance_id;
        self.len += 1;
        self
    }

    /// The ids, top to bottom.
    pub fn ids(&self) -> &[u32] {
        &self.ids[..self.len as usize]
    }

    /// The bottom instance's id (the one the instance-id hit formats report), or [`MISS_ID`].
    pub fn last(&self) -> u32 {
        self.ids().last().copied().unwrap_or(MISS_ID)
    }
}

/// One intersection, as the engine reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the ray, in units of the ray direction's length.
    pub t: f32,
    /// Primitive id: the build input's primitive-index offset plus the triangle's index in that input.
    pub prim_id: u32,
    /// Geometry id: the index of the build input.
    pub geom_id: u32,
    /// The user id of the instance just above the geometry, or [`MISS_ID`] outside any instance.
    pub inst_id: u32,
    /// Every instance above the geometry, top to bottom.
    pub inst_path: InstancePath,
    /// Barycentric weight of the triangle's second vertex.
    pub u: f32,
    /// Barycentric weight of the third vertex: hit point = (1−u−v)·v0 + u·v1 + v·v2.
    pub v: f32,
    /// Geometric normal `(v1−v0)×(v2−v0)`, not normalized; the front face is the side it points to.
    pub normal: Vec3A,
    /// Whether the ray saw the triangle's back face (`dot(direction, normal) > 0`).
    pub back_face: bool,
}

impl Hit {
    /// What a missed ray reports.
    pub const MISS: Hit = Hit {
        t: MISS_T,
        prim_id: MISS_ID,
        geom_id: MISS_ID,
        inst_id: MISS_ID,
        inst_path: InstancePath::EMPTY,
        u: 0.0,
        v: 0.0,
        normal: Vec3A::ZERO,
        back_face: false,
    };

    /// Whether this is a real hit: it names a primitive, or (read from a record without ids: the `t` format, a
    /// bitmask read as `t = 0`) its `t` is ≥ 0, Prime's rule. A hit behind the ray's origin (`tmin` < 0) names its
    /// primitive, so it is a hit here; in the `t` format alone it cannot be told from a miss.
    pub fn is_hit(&self) -> bool {
        self.prim_id != MISS_ID || self.t >= 0.0
    }
}

/// How hits are packed in a hit buffer. Offsets in bytes; every field is 4 bytes, little-endian; ids are
/// `i32` with −1 for none. A miss has `t` = −1, ids −1, `u` = `v` = 0 and a zero normal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum HitFormat {
    /// Prime `HIT_BITMASK`: one bit a record, 1 = hit. Record `i` is bit `i % 8` (least significant first) of
    /// byte `i / 8`; the buffer is `ceil(records / 8)` bytes and unused high bits of the last byte are 0.
    Bitmask,
    /// Prime `HIT_T`, 4 bytes: `0 t f32`.
    T,
    /// Prime `HIT_T_TRIID`, 8 bytes: `0 t f32 | 4 prim_id i32`.
    TTriid,
    /// Prime `HIT_T_TRIID_U_V`, 16 bytes: `0 t f32 | 4 prim_id i32 | 8 u f32 | 12 v f32`.
    TTriidUV,
    /// Prime `HIT_T_TRIID_INSTID`, 12 bytes: `0 t f32 | 4 prim_id i32 | 8 inst_id i32` (the user id of the
    /// instance just above the geometry; −1 outside any instance).
    TTriidInstid,
    /// Prime `HIT_T_TRIID_INSTID_U_V`, 20 bytes: `0 t f32 | 4 prim_id i32 | 8 inst_id i32 | 12 u f32 | 16 v f32`.
    TTriidInstidUV,
    /// 80 bytes: `0 t f32 | 4 prim_id i32 | 8 geom_id i32 | 12 inst_id i32 | 16 u f32 | 20 v f32 |
    /// 24 normal.xyz f32×3 (unit geometric normal, world space, on the front side) | 36 flags u32 (bit 0: back
    /// face hit) | 40 path_len u32 (instances above the geometry) | 44 reserved u32 (0) | 48 inst_path i32×8 (their
    /// user ids, top to bottom, then −1)`.
    Full,
}

impl HitFormat {
    /// Every hit format, in the order of the contract's enum.
    pub const ALL: [HitFormat; 7] = [
        HitFormat::Bitmask,
        HitFormat::T,
        HitFormat::TTriid,
        HitFormat::TTriidUV,
        HitFormat::TTriidInstid,
        HitFormat::TTriidInstidUV,
        HitFormat::Full,
    ];

    /// Bytes per record, or `None` for [`HitFormat::Bitmask`] (one bit a record).
    pub const fn size(self) -> Option<usize> {
        match self {
            HitFormat::Bitmask => None,
            HitFormat::T => Some(4),
            HitFormat::TTriid => Some(8),
            HitFormat::TTriidInstid => Some(12),
            HitFormat::TTriidUV => Some(16),
            HitFormat::TTriidInstidUV => Some(20),
            HitFormat::Full => Some(80),
        }
    }

    /// Whether records of this format carry the hit's normal (and so the tracer must compute it).
    pub const fn has_normal(self) -> bool {
        matches!(self, HitFormat::Full)
    }

    /// Bytes needed for `records` hit records.
    pub const fn buffer_len(self, records: usize) -> usize {
        match self.size() {
            None => records.div_ceil(8),
            Some(size) => records * size,
        }
    }

    /// The format's name in lower case, as used by the contract and `rayctl`.
    pub const fn name(self) -> &'static str {
        match self {
            HitFormat::Bitmask => "bitmask",
            HitFormat::T => "t",
            HitFormat::TTriid => "t_triid",
            HitFormat::TTriidUV => "t_triid_u_v",
            HitFormat::TTriidInstid => "t_triid_instid",
            HitFormat::TTriidInstidUV => "t_triid_instid_u_v",
            HitFormat::Full => "full",
        }
    }

    /// Looks a format up by [`HitFormat::name`].
    pub fn from_name(name: &str) -> Option<HitFormat> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Reads record `index` of a hit buffer (laid out as [`HitFormat::write`] takes it). Fields the format does not
    /// carry read as in [`Hit::MISS`]; a bitmask hit, which carries no distance, reads as `t = 0` so that
    /// [`Hit::is_hit`] holds. The `full` format's normal reads as written: unit length.
    #[inline(always)]
    pub fn read(self, buffer: &[u8], index: usize) -> Hit {
        let Some(size) = self.size() else {
            let hit = buffer[index / 8] & (1 << (index % 8)) != 0;
            return if hit { Hit { t: 0.0, ..Hit::MISS } } else { Hit::MISS };
        };
        let b = &buffer[index * size..(index + 1) * size];
        let (f32_at, u32_at) = (|offset| read_f32(b, offset), |offset| read_u32(b, offset));
        let mut hit = Hit { t: f32_at(0), ..Hit::MISS };
        match self {
            HitFormat::Bitmask | HitFormat::T => {}
            HitFormat::TTriid => hit.prim_id = u32_at(4),
            HitFormat::TTriidUV => (hit.prim_id, hit.u, hit.v) = (u32_at(4), f32_at(8), f32_at(12)),
            HitFormat::TTriidInstid => (hit.prim_id, hit.inst_id) = (u32_at(4), u32_at(8)),
            HitFormat::TTriidInstidUV => {
                (hit.prim_id, hit.inst_id, hit.u, hit.v) = (u32_at(4), u32_at(8), f32_at(12), f32_at(16));
            }
            HitFormat::Full => {
                (hit.prim_id, hit.geom_id, hit.inst_id) = (u32_at(4), u32_at(8), u32_at(12));
                (hit.u, hit.v) = (f32_at(16), f32_at(20));
                hit.normal = Vec3A::new(f32_at(24), f32_at(28), f32_at(32));
                hit.back_face = u32_at(36) & 1 != 0;
                let path_len = (u32_at(40) as usize).min(INSTANCE_PATH_SLOTS);
                hit.inst_path = (0..path_len).fold(InstancePath::EMPTY, |path, slot| path.push(u32_at(48 + 4 * slot)));
            }
        }
        hit
    }

    /// Record `index`'s `t` when it is a hit ([`Hit::is_hit`]), reading no more of it than that takes: what
    /// [`HitFormat::read`] gives, for reductions that want no more.
    #[inline(always)]
    pub fn hit_t(self, buffer: &[u8], index: usize) -> Option<f32> {
        let Some(size) = self.size() else { return (buffer[index / 8] & (1 << (index % 8)) != 0).then_some(0.0) };
        let record = &buffer[index * size..(index + 1) * size];
        let t = read_f32(record, 0);
        let prim_id = if self == HitFormat::T { MISS_ID } else { read_u32(record, 4) };
        // `|`, not `||`: a select, not a branch (half the records of a typical trace are misses, in no order).
        ((prim_id != MISS_ID) | (t >= 0.0)).then_some(t)
    }

    /// Calls `f` with this format as a constant, once in each arm of a match, so that a loop in `f` writing many
    /// records ([`HitFormat::write`]) is compiled once a format, without a match a record.
    #[inline(always)]
    pub fn specialized<R>(self, mut f: impl FnMut(HitFormat) -> R) -> R {
        match self {
            HitFormat::Bitmask => f(HitFormat::Bitmask),
            HitFormat::T => f(HitFormat::T),
            HitFormat::TTriid => f(HitFormat::TTriid),
            HitFormat::TTriidUV => f(HitFormat::TTriidUV),
            HitFormat::TTriidInstid => f(HitFormat::TTriidInstid),
            HitFormat::TTriidInstidUV => f(HitFormat::TTriidInstidUV),
            HitFormat::Full => f(HitFormat::Full),
        }
    }

    /// Writes record `index` of a hit buffer. For byte formats `buffer` may be the whole buffer or any slice
    /// that starts on a record boundary, with `index` relative to it; for the bitmask it must start on a byte
    /// boundary (`index` relative to its first bit).
    #[inline(always)]
    pub fn write(self, buffer: &mut [u8], index: usize, hit: &Hit) {
        let Some(size) = self.size() else {
            // Without a branch: hits and misses come in no order a predictor could learn.
            let (byte, shift) = (&mut buffer[index / 8], index % 8);
            *byte = (*byte & !(1 << shift)) | (u8::from(hit.is_hit()) << shift);
            return;
        };
        let b = &mut buffer[index * size..(index + 1) * size];
        write_f32(b, 0, hit.t);
        match self {
            HitFormat::Bitmask | HitFormat::T => {}
            HitFormat::TTriid => write_u32(b, 4, hit.prim_id),
            HitFormat::TTriidUV => {
                write_u32(b, 4, hit.prim_id);
                write_f32(b, 8, hit.u);
                write_f32(b, 12, hit.v);
            }
            HitFormat::TTriidInstid => {
                write_u32(b, 4, hit.prim_id);
                write_u32(b, 8, hit.inst_id);
            }
            HitFormat::TTriidInstidUV => {
                write_u32(b, 4, hit.prim_id);
                write_u32(b, 8, hit.inst_id);
                write_f32(b, 12, hit.u);
                write_f32(b, 16, hit.v);
            }
            HitFormat::Full => {
                write_u32(b, 4, hit.prim_id);
                write_u32(b, 8, hit.geom_id);
                write_u32(b, 12, hit.inst_id);
                write_f32(b, 16, hit.u);
                write_f32(b, 20, hit.v);
                let unit = hit.normal.normalize_or_zero();
                for axis in 0..3 {
                    write_f32(b, 24 + 4 * axis, unit[axis]);
                }
                write_u32(b, 36, u32::from(hit.back_face));
                write_u32(b, 40, hit.inst_path.len as u32);
                write_u32(b, 44, 0);
                for (slot, id) in hit.inst_path.ids.iter().enumerate() {
                    write_u32(b, 48 + 4 * slot, *id);
                }
            }
        }
    }
}

/// Writes `len` consecutive records of a [`HitFormat::Bitmask`] buffer from record `first` at once (`len` ≤ 32):
/// bit `i` of `bits` is record `first + i`'s (1 = hit); the buffer's other bits are kept. One merge a run (of the
/// eight bytes from the run's first; a merge a byte near the buffer's end) instead of one a record: the records of
/// neighbouring rays share bytes, and a merge a record makes each wait on the store before it. `buffer` starts on a
/// byte boundary, as for [`HitFormat::write`].
#[inline(always)]
pub fn write_bitmask_run(buffer: &mut [u8], first: usize, bits: u32, len: usize) {
    debug_assert!(len <= 32);
    let shift = first % 8;
    let mask = ((1u64 << len) - 1) << shift;
    let value = (u64::from(bits) << shift) & mask;
    // One merge of the eight bytes from the first, where the buffer has them (the run's bits, at most 39, lie in them).
    if let Some(window) = buffer.get_mut(first / 8..first / 8 + 8) {
        let window: &mut [u8; 8] = window.try_into().expect("eight bytes");
        *window = ((u64::from_le_bytes(*window) & !mask) | value).to_le_bytes();
        return;
    }
    let bytes = &mut buffer[first / 8..(first + len).div_ceil(8)];
    for (k, byte) in bytes.iter_mut().enumerate() {
        let (mask, value) = ((mask >> (8 * k)) as u8, (value >> (8 * k)) as u8);
        *byte = (*byte & !mask) | value;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bitmask_sets_and_clears_single_bits_lsb_first() {
        let hit = Hit { t: 1.0, ..Hit::MISS };
        let mut bits = vec![0u8; HitFormat::Bitmask.buffer_len(10)];
        assert_eq!(bits.len(), 2);
        HitFormat::Bitmask.write(&mut bits, 0, &hit);
        HitFormat::Bitmask.write(&mut bits, 9, &hit);
        assert_eq!(bits, [0b0000_0001, 0b0000_0010]);
        HitFormat::Bitmask.write(&mut bits, 0, &Hit::MISS);
        assert_eq!(bits, [0, 0b0000_0010]);
    }

    #[test]
    fn a_run_of_bitmask_records_is_written_as_record_by_record_and_keeps_its_neighbours() {
        let mut next = 0x2545_f491_4f6c_dd1d_u64;
        let mut random = move || {
            next ^= next << 13;
            next ^= next >> 7;
            next ^= next << 17;
            next
        };
        for first in 0..20 {
            for len in 0..=32 {
                let before: Vec<u8> = (0..8).map(|_| random() as u8).collect();
                let bits = random() as u32;
                let (mut by_run, mut by_record) = (before.clone(), before.clone());
                write_bitmask_run(&mut by_run, first, bits, len);
                for i in 0..len {
                    let hit = if bits >> i & 1 == 1 { Hit { t: 1.0, ..Hit::MISS } } else { Hit::MISS };
                    HitFormat::Bitmask.write(&mut by_record, first + i, &hit);
                }
                assert_eq!(by_run, by_record, "{len} records from {first}");
            }
        }
    }

    #[test]
    fn a_hit_behind_the_origin_is_a_hit_in_every_format_with_ids_and_in_the_bitmask() {
        let behind = Hit { t: -0.5, prim_id: 3, ..Hit::MISS };
        assert!(behind.is_hit() && !Hit::MISS.is_hit());
        for format in HitFormat::ALL {
            let mut record = vec![0u8; format.buffer_len(1)];
            format.write(&mut record, 0, &behind);
            // The `t` format has no id: by Prime's rule its negative t reads as a miss (the contract says so).
            assert_eq!(format.read(&record, 0).is_hit(), format != HitFormat::T, "{format:?}");
        }
    }

    #[test]
    fn the_t_of_a_hit_is_what_a_whole_record_says() {
        let hits = [Hit { t: 2.5, prim_id: 7, ..Hit::MISS }, Hit::MISS, Hit { t: -0.5, prim_id: 3, ..Hit::MISS }];
        for format in HitFormat::ALL {
            let mut records = vec![0u8; format.buffer_len(hits.len())];
            for (index, hit) in hits.iter().enumerate() {
                format.write(&mut records, index, hit);
            }
            for index in 0..hits.len() {
                let read = format.read(&records, index);
                assert_eq!(format.hit_t(&records, index), read.is_hit().then_some(read.t), "{format:?} {index}");
            }
        }
    }

    #[test]
    fn full_format_writes_every_field_at_its_offset() {
        let hit = Hit {
            t: 2.5,
            prim_id: 7,
            geom_id: 3,
            inst_id: 5,
            inst_path: InstancePath::EMPTY.push(4).push(5),
            u: 0.25,
            v: 0.5,
            normal: Vec3A::new(0.0, 0.0, -4.0),
            back_face: true,
        };
        let mut b = vec![0xffu8; 80];
        HitFormat::Full.write(&mut b, 0, &hit);
        assert_eq!(read_f32(&b, 0), 2.5);
        assert_eq!(read_u32(&b, 4), 7);
        assert_eq!(read_u32(&b, 8), 3);
        assert_eq!(read_u32(&b, 12), 5);
        assert_eq!((read_f32(&b, 16), read_f32(&b, 20)), (0.25, 0.5));
        assert_eq!((read_f32(&b, 24), read_f32(&b, 28), read_f32(&b, 32)), (0.0, 0.0, -1.0));
        assert_eq!(read_u32(&b, 36), 1);
        assert_eq!((read_u32(&b, 40), read_u32(&b, 44)), (2, 0));
        let path: Vec<i32> = (0..8).map(|slot| read_u32(&b, 48 + 4 * slot) as i32).collect();
        assert_eq!(path, [4, 5, -1, -1, -1, -1, -1, -1]);
        assert_eq!(HitFormat::Full.read(&b, 0), Hit { normal: Vec3A::new(0.0, 0.0, -1.0), ..hit }, "read back");
        HitFormat::Full.write(&mut b, 0, &Hit::MISS);
        assert_eq!(HitFormat::Full.read(&b, 0), Hit::MISS);
        assert_eq!((read_u32(&b, 12) as i32, read_u32(&b, 40), read_u32(&b, 48) as i32), (-1, 0, -1));
    }

    #[test]
    fn byte_formats_place_prime_fields() {
        let hit = Hit { t: 1.5, prim_id: 42, inst_id: 9, u: 0.125, v: 0.375, ..Hit::MISS };
        let mut b = vec![0u8; 20];
        HitFormat::TTriidInstidUV.write(&mut b, 0, &hit);
        assert_eq!(read_f32(&b, 0), 1.5);
        assert_eq!(read_u32(&b, 4), 42);
        assert_eq!(read_u32(&b, 8), 9);
        assert_eq!((read_f32(&b, 12), read_f32(&b, 16)), (0.125, 0.375));
        let mut b = vec![0u8; 16];
        HitFormat::TTriidUV.write(&mut b, 0, &hit);
        assert_eq!((read_u32(&b, 4), read_f32(&b, 8), read_f32(&b, 12)), (42, 0.125, 0.375));
        for format in HitFormat::ALL {
            assert_eq!(HitFormat::from_name(format.name()), Some(format));
        }
    }
}
