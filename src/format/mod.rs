//! Packed little-endian ray and hit buffers: the one place where a ray is decoded and a hit encoded.
//!
//! Every layout is documented byte by byte on its enum variant. All fields are little-endian; `f32` is IEEE-754
//! binary32, `u32`/`i32` are 32-bit integers. Buffers carry no header: a ray buffer is `count × size` bytes.

pub mod hit;
pub mod ray;

pub use hit::{Hit, HitFormat, INSTANCE_PATH_SLOTS, InstancePath, MISS_ID, MISS_T};
pub use ray::{Ray, RayFlags, RayFormat};

/// Reads a little-endian `f32` at `offset`.
#[inline(always)]
pub(crate) fn read_f32(bytes: &[u8], offset: usize) -> f32 {
    f32::from_le_bytes(bytes[offset..offset + 4].try_into().expect("4 bytes"))
}

/// Reads a little-endian `u32` at `offset`.
#[inline(always)]
pub(crate) fn read_u32(bytes: &[u8], offset: usize) -> u32 {
    u32::from_le_bytes(bytes[offset..offset + 4].try_into().expect("4 bytes"))
}

/// Writes `value` little-endian at `offset`.
#[inline(always)]
pub(crate) fn write_u32(bytes: &mut [u8], offset: usize, value: u32) {
    bytes[offset..offset + 4].copy_from_slice(&value.to_le_bytes());
}

/// Writes `value` little-endian at `offset`.
#[inline(always)]
pub(crate) fn write_f32(bytes: &mut [u8], offset: usize, value: f32) {
    write_u32(bytes, offset, value.to_bits());
}
