//! Packed instance buffers, as the contract carries them: rayd's 64-byte records, and Prime's instance list with
//! a separate transform buffer. Both become [`Instance`]s over a list of children the caller resolved.

use std::sync::Arc;

use super::{Instance, InstanceFlags};
use crate::context::Accel;
use crate::error::{Error, Result};
use crate::format::{read_f32, read_u32, write_f32, write_u32};

/// Bytes of one instance record: `0 transform f32×12 (3×4 row-major) | 48 instance_id u32 | 52 mask u32 (low 8
/// bits) | 56 flags u32 ([`InstanceFlags`]) | 60 child u32 (index into the children)`.
pub const INSTANCE_RECORD_BYTES: usize = 64;

/// One instance record, its child named by index.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InstanceRecord {
    /// Object-to-world, 3×4 row-major.
    pub transform: [f32; 12],
    /// The user's id.
    pub instance_id: u32,
    /// Visibility mask.
    pub mask: u8,
    /// Flags.
    pub flags: InstanceFlags,
    /// Index of its child in the build's list of children.
    pub child: u32,
}

impl InstanceRecord {
    /// Reads a record from exactly [`INSTANCE_RECORD_BYTES`] bytes (higher mask bits and unknown flags are ignored).
    pub fn decode(bytes: &[u8]) -> InstanceRecord {
        InstanceRecord {
            transform: std::array::from_fn(|i| read_f32(bytes, 4 * i)),
            instance_id: read_u32(bytes, 48),
            mask: read_u32(bytes, 52) as u8,
            flags: InstanceFlags::from_bits_truncate(read_u32(bytes, 56)),
            child: read_u32(bytes, 60),
        }
    }

    /// Writes the record into exactly [`INSTANCE_RECORD_BYTES`] bytes.
    pub fn encode(&self, bytes: &mut [u8]) {
        for (i, value) in self.transform.iter().enumerate() {
            write_f32(bytes, 4 * i, *value);
        }
        write_u32(bytes, 48, self.instance_id);
        write_u32(bytes, 52, u32::from(self.mask));
        write_u32(bytes, 56, self.flags.bits());
        write_u32(bytes, 60, self.child);
    }
}

/// How a Prime transform buffer is packed (row-major, object to world).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TransformFormat {
    /// 64 bytes: a 4×4 matrix whose last row must be `0 0 0 1`.
    Float4x4,
    /// 48 bytes: the first three rows of a 4×4 matrix.
    Float4x3,
}

impl TransformFormat {
    /// Bytes of one transform.
    pub const fn size(self) -> usize {
        match self {
            TransformFormat::Float4x4 => 64,
            TransformFormat::Float4x3 => 48,
        }
    }
}

/// An error in instance `element` of field `field`.
fn invalid(field: &'static str, element: Option<usize>, rule: String) -> Error {
    Error::InvalidBuildInput { input: 0, field, element: element.map(|e| e as u64), rule }
}

/// The child at `index`, for instance `element`.
fn child(children: &[Arc<Accel>], index: u32, field: &'static str, element: usize) -> Result<Arc<Accel>> {
    children.get(index as usize).cloned().ok_or_else(|| {
        invalid(field, Some(element), format!("child index {index} is not below the {} children", children.len()))
    })
}

/// Checks that `len` bytes hold whole items of `size` bytes; returns how many.
fn whole(len: usize, size: usize, field: &'static str) -> Result<usize> {
    if !len.is_multiple_of(size) {
        return Err(invalid(field, None, format!("{len} bytes is not a whole number of {size}-byte items")));
    }
    Ok(len / size)
}

/// The instances of packed records over `children`.
pub fn instances_from_records(records: &[u8], children: &[Arc<Accel>]) -> Result<Vec<Instance>> {
    whole(records.len(), INSTANCE_RECORD_BYTES, "instances.records")?;
    records
        .chunks_exact(INSTANCE_RECORD_BYTES)
        .enumerate()
        .map(|(i, bytes)| {
            let record = InstanceRecord::decode(bytes);
            Ok(Instance {
                transform: record.transform,
                instance_id: record.instance_id,
                mask: record.mask,
                flags: record.flags,
                child: child(children, record.child, "instances.records", i)?,
            })
        })
        .collect()
}

/// The instances of a Prime instance list (`u32` child indices) and transform buffer over `children`: instance
/// `i` has id `i`, mask 0xFF and no flags.
pub fn instances_from_prime(
    child_indices: &[u8],
    transforms: &[u8],
    format: TransformFormat,
    children: &[Arc<Accel>],
) -> Result<Vec<Instance>> {
    let count = whole(child_indices.len(), 4, "instances.prime.child_indices")?;
    let transform_count = whole(transforms.len(), format.size(), "instances.prime.transforms")?;
    if transform_count != count {
        return Err(invalid(
            "instances.prime.transforms",
            None,
            format!("{transform_count} transforms for {count} instances"),
        ));
    }
    (0..count)
        .map(|i| {
            let matrix = &transforms[i * format.size()..(i + 1) * format.size()];
            if format == TransformFormat::Float4x4 && (12..16).map(|k| read_f32(matrix, 4 * k)).ne([0.0, 0.0, 0.0, 1.0])
            {
                return Err(invalid("instances.prime.transforms", Some(i), "the last row must be 0 0 0 1".into()));
            }
            Ok(Instance {
                transform: std::array::from_fn(|k| read_f32(matrix, 4 * k)),
                instance_id: i as u32,
                mask: 0xFF,
                flags: InstanceFlags::empty(),
                child: child(children, read_u32(child_indices, 4 * i), "instances.prime.child_indices", i)?,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_round_trip_at_their_offsets() {
        let record = InstanceRecord {
            transform: std::array::from_fn(|i| i as f32 + 0.5),
            instance_id: 77,
            mask: 0x81,
            flags: InstanceFlags::FLIP_FACING,
            child: 3,
        };
        let mut bytes = [0u8; INSTANCE_RECORD_BYTES];
        record.encode(&mut bytes);
        assert_eq!(InstanceRecord::decode(&bytes), record);
        assert_eq!((read_f32(&bytes, 4), read_u32(&bytes, 48), read_u32(&bytes, 52)), (1.5, 77, 0x81));
        assert_eq!((read_u32(&bytes, 56), read_u32(&bytes, 60)), (2, 3));
        write_u32(&mut bytes, 52, 0xFF01);
        assert_eq!(InstanceRecord::decode(&bytes).mask, 0x01, "bits above the 8 of the mask are ignored");
    }

    #[test]
    fn bad_lengths_and_indices_are_named() {
        let error = instances_from_records(&[0u8; 65], &[]).unwrap_err();
        assert!(error.to_string().contains("instances.records: 65 bytes is not a whole number of 64-byte"), "{error}");
        let mut record = [0u8; INSTANCE_RECORD_BYTES];
        write_u32(&mut record, 60, 2);
        let error = instances_from_records(&record, &[]).unwrap_err();
        assert!(
            error.to_string().contains("instances.records[0]: child index 2 is not below the 0 children"),
            "{error}"
        );
        let error = instances_from_prime(&[0u8; 8], &[0u8; 48], TransformFormat::Float4x3, &[]).unwrap_err();
        assert!(error.to_string().contains("1 transforms for 2 instances"), "{error}");
        let error = instances_from_prime(&[0u8; 4], &[0u8; 64], TransformFormat::Float4x4, &[]).unwrap_err();
        assert!(error.to_string().contains("transforms[0]: the last row must be 0 0 0 1"), "{error}");
    }
}
