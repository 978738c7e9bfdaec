//! What an update must keep: the structure of a triangle build (per input: triangle count, primitive-index offset,
//! flags, the bytes of its indices and masks), as a key to compare, after the seed's DynamicAccel.

use super::{BuildInput, GeometryFlags, triangle_counts};
use crate::error::Result;

/// The structure of one triangle input (its fields are open to the crate for serialization).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct InputStructure {
    /// Triangles.
    pub(crate) triangles: usize,
    /// Primitive-index offset.
    pub(crate) offset: u32,
    /// Flags.
    pub(crate) flags: GeometryFlags,
    /// Hash of the index bytes and format (0 for a soup).
    pub(crate) topology: u64,
    /// Hash of the mask bytes (0 without masks).
    pub(crate) masks: u64,
}

/// The structure of a triangle build.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Structure {
    /// One per input.
    pub(crate) inputs: Vec<InputStructure>,
}

/// A hash of `bytes` under `tag` that stays the same across Rust releases and machines (it is persisted with
/// updatable accels): the CRC-32 of tag and bytes above their length.
fn hash(bytes: &[u8], tag: &str) -> u64 {
    let mut crc = crc32fast::Hasher::new();
    crc.update(tag.as_bytes());
    crc.update(bytes);
    (u64::from(crc.finalize()) << 32) | (bytes.len() as u64 & 0xFFFF_FFFF)
}

impl Structure {
    /// The structure of `inputs` (validated as a build with `keys` motion keys would be: an update must give as
    /// many vertex buffers per input as the build).
    pub fn of(inputs: &[BuildInput<'_>], keys: usize) -> Result<Structure> {
        let counts = triangle_counts(inputs, keys)?;
        let inputs = inputs
            .iter()
            .zip(counts)
            .map(|(BuildInput::Triangles(input), triangles)| InputStructure {
                triangles,
                offset: input.primitive_index_offset,
                flags: input.flags,
                topology: input.indices.map_or(0, |i| hash(i.data, i.format.name())),
                masks: input.masks.map_or(0, |m| hash(m, "masks")),
            })
            .collect();
        Ok(Structure { inputs })
    }

    /// How the motion keys of `inputs` (`vertices` and each of `motion_vertices`) differ from the build's `keys`,
    /// in words; `None` when every input gives as many. (An update that gives another number of keys changes the
    /// structure, which [`Structure::of`] refuses as a malformed build.)
    pub fn key_difference(inputs: &[BuildInput<'_>], keys: usize) -> Option<String> {
        inputs.iter().enumerate().find_map(|(i, BuildInput::Triangles(input))| {
            let given = input.motion_vertices.len() + 1;
            (given != keys).then(|| format!("input {i}: {given} motion keys where the build had {keys}"))
        })
    }

    /// How `other` differs from this structure, in words; `None` when they are the same.
    pub fn difference(&self, other: &Structure) -> Option<String> {
        if self.inputs.len() != other.inputs.len() {
            return Some(format!("{} build inputs where the build had {}", other.inputs.len(), self.inputs.len()));
        }
        self.inputs.iter().zip(&other.inputs).enumerate().find_map(|(i, (was, now))| {
            let what = if was.triangles != now.triangles {
                format!("{} triangles where the build had {}", now.triangles, was.triangles)
            } else if was.offset != now.offset {
                "a different primitive_index_offset".into()
            } else if was.flags != now.flags {
                "different flags".into()
            } else if was.topology != now.topology {
                "different indices (topology)".into()
            } else if was.masks != now.masks {
                "different masks".into()
            } else {
                return None;
            };
            Some(format!("input {i}: {what}"))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::TriangleInput;

    #[test]
    fn counts_topology_and_masks_make_the_structure_positions_do_not() {
        let vertices = [0u8; 36];
        let moved = [1u8; 36];
        let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect();
        let turned: Vec<u8> = [0u32, 2, 1].iter().flat_map(|i| i.to_le_bytes()).collect();
        let of = |v: &[u8], i: &[u8]| Structure::of(&[BuildInput::Triangles(TriangleInput::indexed(v, i))], 1).unwrap();
        let built = of(&vertices, &indices);
        assert_eq!(built.difference(&of(&moved, &indices)), None, "new positions keep the structure");
        assert_eq!(built.difference(&of(&vertices, &turned)).unwrap(), "input 0: different indices (topology)");
        let masks = [0u8; 4];
        let masked = TriangleInput { masks: Some(&masks), ..TriangleInput::indexed(&vertices, &indices) };
        let with_masks = Structure::of(&[BuildInput::Triangles(masked)], 1).unwrap();
        assert_eq!(built.difference(&with_masks).unwrap(), "input 0: different masks");
        let two = Structure::of(&[BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices)); 2], 1).unwrap();
        assert_eq!(built.difference(&two).unwrap(), "2 build inputs where the build had 1");
        let one_key = [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
        assert_eq!(Structure::key_difference(&one_key, 1), None);
        assert_eq!(Structure::key_difference(&one_key, 3).unwrap(), "input 0: 1 motion keys where the build had 3");
    }
}
