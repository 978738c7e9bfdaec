//! PLY (ASCII or binary) through `ply-rs-bw`: vertex `x y z` of any scalar type, faces as `vertex_indices` or
//! `vertex_index` lists of any integer type, triangulated as fans. Other elements and properties are ignored.

use glam::Vec3;
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{Property, PropertyAccess, PropertyAccessResult};
use rayd_engine::mesh::Mesh;

/// One element of any kind, keeping only what a mesh needs.
#[derive(Debug, Default)]
struct Element {
    /// `x y z` when the element is a vertex.
    position: [f32; 3],
    /// The polygon's corners when the element is a face.
    corners: Vec<u32>,
}

impl PropertyAccess for Element {
    fn new() -> Self {
        Element::default()
    }

    fn set_property(&mut self, name: &str, property: Property) -> PropertyAccessResult {
        let stored = if let Some(axis) = ["x", "y", "z"].iter().position(|&axis| axis == name) {
            property.to_f32_lossy().map(|v| self.position[axis] = v)
        } else if matches!(name, "vertex_indices" | "vertex_index") {
            property.to_u32_list().map(|corners| self.corners = corners)
        } else {
            return PropertyAccessResult::Ignored;
        };
        stored.map_or(PropertyAccessResult::UnsupportedType, |()| PropertyAccessResult::Set)
    }
}

/// Parses the bytes of a PLY file.
pub(super) fn parse(mut bytes: &[u8]) -> Result<Mesh, String> {
    let ply = Parser::<Element>::new().read_ply(&mut bytes).map_err(|e| e.to_string())?;
    let vertex = ply.header.elements.get("vertex").ok_or("no vertex element")?;
    if let Some(axis) = ["x", "y", "z"].into_iter().find(|axis| !vertex.properties.contains_key(*axis)) {
        return Err(format!("vertices have no {axis} property"));
    }
    let elements = |name| ply.payload.get(name).map(Vec::as_slice).unwrap_or_default();
    let positions = elements("vertex").iter().map(|v| Vec3::from(v.position)).collect();
    let triangles = elements("face")
        .iter()
        .flat_map(|face| {
            let c = &face.corners;
            (2..c.len()).map(move |k| [c[0], c[k - 1], c[k]])
        })
        .collect();
    Ok(Mesh { positions, triangles })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Parses `text` as the file `name` is parsed, with the checks of every format.
    fn load_text(name: &str, text: &str) -> Result<Mesh, rayd_engine::mesh::LoadError> {
        let path = std::path::Path::new(name);
        crate::mesh::MeshFormat::of(path)?.parse(path, text.as_bytes())
    }

    #[test]
    fn ascii_ply_with_doubles_and_a_quad_becomes_a_fan() {
        let mesh = load_text(
            "quad.ply",
            "ply\nformat ascii 1.0\ncomment a unit quad and a triangle\n\
             element vertex 5\nproperty double x\nproperty double y\nproperty float z\nproperty uchar red\n\
             element face 2\nproperty list uchar int vertex_indices\nend_header\n\
             0 0 0 255\n1 0 0 0\n1 1 0 0\n0 1 0 0\n0.5 0.5 2.5 9\n4 0 1 2 3\n3 4 1 0\n",
        )
        .unwrap();
        assert_eq!(mesh.positions.len(), 5);
        assert_eq!(mesh.positions[4], Vec3::new(0.5, 0.5, 2.5));
        assert_eq!(mesh.triangles, [[0, 1, 2], [0, 2, 3], [4, 1, 0]]);
    }

    #[test]
    fn vertex_index_lists_of_unsigned_ints_are_read_too() {
        let mesh = load_text(
            "tri.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
             element face 1\nproperty list uchar uint vertex_index\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 2 1 0\n",
        )
        .unwrap();
        assert_eq!(mesh.triangles, [[2, 1, 0]]);
    }

    #[test]
    fn missing_axes_faces_or_negative_indices_are_errors() {
        let no_z = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n0 0\n";
        assert!(load_text("a.ply", no_z).unwrap_err().reason.contains("no z"));
        let no_faces = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
                        property float z\nend_header\n0 0 0\n";
        assert_eq!(load_text("b.ply", no_faces).unwrap_err().reason, "no triangles");
        let negative = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                        property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
                        0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n";
        assert!(load_text("c.ply", negative).is_err());
    }
}
