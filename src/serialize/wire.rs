//! The little-endian building blocks of a blob: fixed-size values ([`Wire`]), arrays of them (a u64 element count,
//! then the elements) and a [`Reader`] that checks every length against the bytes left before it takes or
//! allocates anything.

use glam::Vec3;

use crate::error::{Error, Result};
use crate::geometry::motion::Bounds;

/// A value of a fixed size in a blob, little-endian.
pub(crate) trait Wire: Sized {
    /// Bytes of one value.
    const SIZE: usize;
    /// Writes the value into `bytes`, which are [`Wire::SIZE`] long.
    fn put(&self, bytes: &mut [u8]);
    /// Reads a value from `bytes`, which are [`Wire::SIZE`] long.
    fn get(bytes: &[u8]) -> Self;
}

/// The four bytes at `at`.
#[inline(always)]
fn word(bytes: &[u8], at: usize) -> [u8; 4] {
    [bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]
}

/// The little-endian u32 at byte `at`.
#[inline(always)]
pub(crate) fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(word(bytes, at))
}

/// The little-endian f32 at byte `at`.
#[inline(always)]
pub(crate) fn f32_at(bytes: &[u8], at: usize) -> f32 {
    f32::from_le_bytes(word(bytes, at))
}

/// Writes `value` at byte `at`.
#[inline(always)]
pub(crate) fn put_u32_at(bytes: &mut [u8], at: usize, value: u32) {
    bytes[at..at + 4].copy_from_slice(&value.to_le_bytes());
}

/// Writes `value` at byte `at`.
#[inline(always)]
fn put_f32_at(bytes: &mut [u8], at: usize, value: f32) {
    bytes[at..at + 4].copy_from_slice(&value.to_le_bytes());
}

impl Wire for u32 {
    const SIZE: usize = 4;

    fn put(&self, bytes: &mut [u8]) {
        put_u32_at(bytes, 0, *self);
    }

    fn get(bytes: &[u8]) -> Self {
        u32_at(bytes, 0)
    }
}

impl Wire for u64 {
    const SIZE: usize = 8;

    fn put(&self, bytes: &mut [u8]) {
        bytes[..8].copy_from_slice(&self.to_le_bytes());
    }

    fn get(bytes: &[u8]) -> Self {
        u64::from_le_bytes(std::array::from_fn(|i| bytes[i]))
    }
}

impl Wire for (u32, u32) {
    const SIZE: usize = 8;

    fn put(&self, bytes: &mut [u8]) {
        put_u32_at(bytes, 0, self.0);
        put_u32_at(bytes, 4, self.1);
    }

    fn get(bytes: &[u8]) -> Self {
        (u32_at(bytes, 0), u32_at(bytes, 4))
    }
}

impl<const N: usize> Wire for [f32; N] {
    const SIZE: usize = 4 * N;

    fn put(&self, bytes: &mut [u8]) {
        for (i, &value) in self.iter().enumerate() {
            put_f32_at(bytes, 4 * i, value);
        }
    }

    fn get(bytes: &[u8]) -> Self {
        std::array::from_fn(|i| f32_at(bytes, 4 * i))
    }
}

impl Wire for Vec3 {
    const SIZE: usize = 12;

    fn put(&self, bytes: &mut [u8]) {
        self.to_array().put(bytes);
    }

    fn get(bytes: &[u8]) -> Self {
        Vec3::from_array(Wire::get(bytes))
    }
}

impl Wire for [Vec3; 3] {
    const SIZE: usize = 36;

    fn put(&self, bytes: &mut [u8]) {
        for (i, corner) in self.iter().enumerate() {
            corner.put(&mut bytes[12 * i..12 * i + 12]);
        }
    }

    fn get(bytes: &[u8]) -> Self {
        std::array::from_fn(|i| Vec3::get(&bytes[12 * i..12 * i + 12]))
    }
}

impl Wire for Bounds {
    const SIZE: usize = 24;

    fn put(&self, bytes: &mut [u8]) {
        self.0.put(&mut bytes[..12]);
        self.1.put(&mut bytes[12..24]);
    }

    fn get(bytes: &[u8]) -> Self {
        (Vec3::get(&bytes[..12]), Vec3::get(&bytes[12..24]))
    }
}

/// Appends one value.
pub(crate) fn put<T: Wire>(out: &mut Vec<u8>, value: &T) {
    let start = out.len();
    out.resize(start + T::SIZE, 0);
    value.put(&mut out[start..]);
}

/// Appends an array: its element count (u64), then its elements.
pub(crate) fn put_array<T: Wire>(out: &mut Vec<u8>, values: &[T]) {
    put(out, &(values.len() as u64));
    let start = out.len();
    out.resize(start + values.len() * T::SIZE, 0);
    for (value, bytes) in values.iter().zip(out[start..].chunks_exact_mut(T::SIZE)) {
        value.put(bytes);
    }
}

/// Appends an optional part: a u32 presence flag (0 or 1), then the part written by `write`.
pub(crate) fn put_optional<T>(out: &mut Vec<u8>, part: Option<&T>, write: impl FnOnce(&mut Vec<u8>, &T)) {
    put(out, &u32::from(part.is_some()));
    if let Some(part) = part {
        write(out, part);
    }
}

/// The error of a damaged or inconsistent blob.
pub(crate) fn invalid(what: impl Into<String>) -> Error {
    Error::InvalidBlob(what.into())
}

/// Reads a blob front to back; every read is checked against the bytes left, and fails naming `what` was read.
#[derive(Debug)]
pub(crate) struct Reader<'a> {
    /// The bytes not read yet.
    rest: &'a [u8],
}

impl<'a> Reader<'a> {
    /// A reader of `bytes`.
    pub(crate) fn new(bytes: &'a [u8]) -> Reader<'a> {
        Reader { rest: bytes }
    }

    /// The next `len` bytes.
    pub(crate) fn take(&mut self, len: usize, what: &str) -> Result<&'a [u8]> {
        if len > self.rest.len() {
            return Err(invalid(format!("{what}: {len} bytes needed, only {} left (truncated?)", self.rest.len())));
        }
        let (head, rest) = self.rest.split_at(len);
        self.rest = rest;
        Ok(head)
    }

    /// The next value.
    pub(crate) fn value<T: Wire>(&mut self, what: &str) -> Result<T> {
        self.take(T::SIZE, what).map(T::get)
    }

    /// The next array (a u64 element count, then the elements); the count is checked against the bytes left
    /// before anything is allocated.
    pub(crate) fn array<T: Wire>(&mut self, what: &str) -> Result<Vec<T>> {
        let count: u64 = self.value(what)?;
        let left = self.rest.len();
        let bytes =
            usize::try_from(count).ok().and_then(|c| c.checked_mul(T::SIZE)).filter(|&b| b <= left).ok_or_else(
                || invalid(format!("{what}: {count} elements of {} bytes, only {left} bytes left", T::SIZE)),
            )?;
        Ok(self.take(bytes, what)?.chunks_exact(T::SIZE).map(T::get).collect())
    }

    /// An optional part (a u32 presence flag, 0 or 1, then the part read by `read`).
    pub(crate) fn optional<T>(&mut self, what: &str, read: impl FnOnce(&mut Self) -> Result<T>) -> Result<Option<T>> {
        match self.value::<u32>(what)? {
            0 => Ok(None),
            1 => read(self).map(Some),
            flag => Err(invalid(format!("{what}: presence flag {flag}, not 0 or 1"))),
        }
    }

    /// Fails unless every byte was read.
    pub(crate) fn finish(&self, what: &str) -> Result<()> {
        match self.rest.len() {
            0 => Ok(()),
            left => Err(invalid(format!("{what}: {left} bytes left over after its end"))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_round_trip_and_hostile_counts_are_refused_before_allocating() {
        let mut out = Vec::new();
        let corners = vec![[Vec3::X, Vec3::Y, Vec3::new(1.5, -2.0, f32::INFINITY)]; 3];
        put_array(&mut out, &corners);
        put(&mut out, &7u32);
        let mut reader = Reader::new(&out);
        assert_eq!(reader.array::<[Vec3; 3]>("corners").unwrap(), corners);
        assert_eq!(reader.value::<u32>("seven").unwrap(), 7);
        reader.finish("test").unwrap();

        let mut huge = Vec::new();
        put(&mut huge, &(u64::MAX / 2));
        let err = Reader::new(&huge).array::<u32>("masks").unwrap_err();
        assert!(matches!(&err, Error::InvalidBlob(m) if m.starts_with("masks: ")), "{err}");
        assert!(Reader::new(&[1, 0, 0]).value::<u32>("short").is_err());
        assert!(Reader::new(&[2, 0, 0, 0]).optional("flag", |r| r.value::<u32>("x")).is_err());
        assert!(Reader::new(&[0]).finish("rest").is_err());
    }
}
