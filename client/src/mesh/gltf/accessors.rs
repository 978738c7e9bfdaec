//! A primitive's positions and indices read from its accessors, with every offset, stride and count checked against
//! the buffers (the `gltf` crate's readers panic on some malformed files: found by the `meshes` fuzz target). Only
//! what a triangle mesh needs: float VEC3 positions, unsigned scalar indices, dense (sparse accessors are refused).

use ::gltf::accessor::{Accessor, DataType, Dimensions};
use glam::Vec3;

/// The bytes of each of `accessor`'s elements, `size` bytes each, checked to lie inside its buffer view and buffer.
fn elements<'b>(
    accessor: &Accessor,
    size: usize,
    buffers: &'b [Vec<u8>],
) -> Result<impl Iterator<Item = &'b [u8]>, String> {
    if accessor.sparse().is_some() {
        return Err("sparse accessors are not supported".into());
    }
    let view = accessor.view().ok_or("an accessor without a bufferView")?;
    let buffer = buffers.get(view.buffer().index()).ok_or("a bufferView of a buffer the file does not have")?;
    let viewed = view
        .offset()
        .checked_add(view.length())
        .and_then(|end| buffer.get(view.offset()..end))
        .ok_or_else(|| format!("bufferView {} lies beyond its buffer of {} bytes", view.index(), buffer.len()))?;
    let stride = view.stride().unwrap_or(size);
    if stride < size {
        return Err(format!("bufferView {}: byteStride {stride} is less than an element's {size} bytes", view.index()));
    }
    let (count, offset) = (accessor.count(), accessor.offset());
    let span = match count {
        0 => Some(0),
        n => (n - 1).checked_mul(stride).and_then(|s| s.checked_add(size)),
    };
    let bytes = span.and_then(|span| viewed.get(offset..offset.checked_add(span)?)).ok_or_else(|| {
        format!(
            "{count} elements of {size} bytes, {stride} apart, from byte {offset} lie beyond bufferView {} of {} bytes",
            view.index(),
            viewed.len()
        )
    })?;
    Ok((0..count).map(move |i| &bytes[i * stride..i * stride + size]))
}

/// A little-endian f32 at `at` in `bytes`.
fn f32_at(bytes: &[u8], at: usize) -> f32 {
    f32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

/// The positions `accessor` holds: float VEC3.
pub(super) fn positions(accessor: &Accessor, buffers: &[Vec<u8>]) -> Result<Vec<Vec3>, String> {
    match (accessor.data_type(), accessor.dimensions()) {
        (DataType::F32, Dimensions::Vec3) => {}
        (kind, dimensions) => return Err(format!("positions must be float VEC3, not {kind:?} {dimensions:?}")),
    }
    Ok(elements(accessor, 12, buffers)?.map(|e| Vec3::new(f32_at(e, 0), f32_at(e, 4), f32_at(e, 8))).collect())
}

/// The indices `accessor` holds: unsigned byte, short or int scalars.
pub(super) fn indices(accessor: &Accessor, buffers: &[Vec<u8>]) -> Result<Vec<u32>, String> {
    let size = match (accessor.data_type(), accessor.dimensions()) {
        (DataType::U8, Dimensions::Scalar) => 1,
        (DataType::U16, Dimensions::Scalar) => 2,
        (DataType::U32, Dimensions::Scalar) => 4,
        (kind, dimensions) => return Err(format!("indices must be unsigned scalars, not {kind:?} {dimensions:?}")),
    };
    Ok(elements(accessor, size, buffers)?
        .map(|e| {
            let mut le = [0u8; 4];
            le[..size].copy_from_slice(e);
            u32::from_le_bytes(le)
        })
        .collect())
}
