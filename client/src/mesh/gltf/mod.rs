//! glTF 2.0 (`.gltf` with embedded `data:` or external `.bin` buffers, and binary `.glb`) through the `gltf` crate
//! without its image decoders. Every triangle-list primitive (mode TRIANGLES) of the default scene (else the first
//! scene) is taken, placed by its node's world transform; a file without scenes gives every mesh untransformed.
//! Points, lines, strips and fans are skipped. External URIs are plain relative paths (no percent-decoding).
//! Positions and indices are read by [`accessors`], which checks every offset against the buffers.

use std::path::Path;

use ::gltf::buffer::Source;
use ::gltf::mesh::Mode;
use ::gltf::{Document, Gltf, Node, Semantic};
use base64::Engine;
use glam::Mat4;
use rayd_engine::mesh::Mesh;

mod accessors;

/// The size of a GLB header: magic, version, total length.
const GLB_HEADER_BYTES: u32 = 12;

/// Refuses a GLB whose header gives a total length shorter than the header itself, which the `gltf` crate
/// subtracts from without a check (a panic in debug builds; found by the `meshes` fuzz target).
fn check_glb_length(bytes: &[u8]) -> Result<(), String> {
    match bytes {
        [b'g', b'l', b'T', b'F', _, _, _, _, l0, l1, l2, l3, ..] => {
            let length = u32::from_le_bytes([*l0, *l1, *l2, *l3]);
            match length >= GLB_HEADER_BYTES {
                true => Ok(()),
                false => Err(format!("GLB header: length {length} is shorter than the {GLB_HEADER_BYTES}-byte header")),
            }
        }
        _ => Ok(()),
    }
}

/// Refuses a primitive whose POSITION names an accessor the file does not have, which the `gltf` crate's
/// validation indexes without a check (a panic; found by the `meshes` fuzz target). The rest is its validation's.
fn check_position_accessors(root: &::gltf::json::Root) -> Result<(), String> {
    let positions = ::gltf::json::validation::Checked::Valid(::gltf::Semantic::Positions);
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            if let Some(accessor) = primitive.attributes.get(&positions)
                && accessor.value() >= root.accessors.len()
            {
                return Err(format!(
                    "meshes[{m}].primitives[{p}].attributes.POSITION: accessor {} of {}",
                    accessor.value(),
                    root.accessors.len()
                ));
            }
        }
    }
    Ok(())
}

/// Parses the bytes of a glTF or GLB file whose external buffers are files in `folder`.
pub(super) fn parse(bytes: &[u8], folder: &Path) -> Result<Mesh, String> {
    check_glb_length(bytes)?;
    let Gltf { document, mut blob } = Gltf::from_slice_without_validation(bytes).map_err(|e| e.to_string())?;
    check_position_accessors(document.as_json())?;
    let document = Document::from_json(document.into_json()).map_err(|e| e.to_string())?;
    let buffers = document
        .buffers()
        .map(|buffer| {
            let data = match buffer.source() {
                Source::Bin => blob.take().ok_or("a buffer refers to a GLB binary chunk that is missing or taken")?,
                Source::Uri(uri) => read_uri(uri, folder)?,
            };
            match data.len() >= buffer.length() {
                true => Ok(data),
                false => {
                    Err(format!("buffer {} holds {} of its {} bytes", buffer.index(), data.len(), buffer.length()))
                }
            }
        })
        .collect::<Result<Vec<_>, String>>()?;
    let mut mesh = Mesh::default();
    match document.default_scene().or_else(|| document.scenes().next()) {
        Some(scene) => add_trees(scene.nodes(), document.nodes().len(), &buffers, &mut mesh)?,
        None => add_all_meshes(&document, &buffers, &mut mesh)?,
    }
    Ok(mesh)
}

/// The bytes a buffer URI names: a base64 `data:` URI, or a file relative to the glTF file's folder.
fn read_uri(uri: &str, folder: &Path) -> Result<Vec<u8>, String> {
    if let Some(data) = uri.strip_prefix("data:") {
        let (_, encoded) = data.split_once(";base64,").ok_or("a data: URI that is not base64")?;
        return base64::engine::general_purpose::STANDARD.decode(encoded).map_err(|e| format!("data: URI: {e}"));
    }
    let file = folder.join(uri);
    std::fs::read(&file).map_err(|e| format!("{}: {e}", file.display()))
}

/// Adds the meshes of `roots` (of a document of `node_count` nodes) and of their descendants, depth first, each
/// placed by its node's world transform. glTF nodes form strict trees (no node is a child of two nodes): a node
/// reached twice (a cycle, a node with two parents, or a root listed twice) is refused, naming it, where it would
/// recurse forever or copy its subtree again at every level. Walked without recursion, so a chain of any depth fits.
fn add_trees<'a>(
    roots: impl Iterator<Item = Node<'a>>,
    node_count: usize,
    buffers: &[Vec<u8>],
    out: &mut Mesh,
) -> Result<(), String> {
    let mut reached = vec![false; node_count];
    let mut pending: Vec<(Node, Mat4)> = roots.map(|root| (root, Mat4::IDENTITY)).collect();
    pending.reverse();
    while let Some((node, parent)) = pending.pop() {
        if std::mem::replace(&mut reached[node.index()], true) {
            return Err(format!(
                "node {} is reached twice: glTF nodes form trees (no cycles, one parent)",
                node.index()
            ));
        }
        let world = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
        if let Some(mesh) = node.mesh() {
            add_mesh(&mesh, world, buffers, out)?;
        }
        // Children in their order: the first is taken next.
        let first_child = pending.len();
        pending.extend(node.children().map(|child| (child, world)));
        pending[first_child..].reverse();
    }
    Ok(())
}

/// Adds every mesh of a document that has no scene, untransformed.
fn add_all_meshes(document: &Document, buffers: &[Vec<u8>], out: &mut Mesh) -> Result<(), String> {
    document.meshes().try_for_each(|mesh| add_mesh(&mesh, Mat4::IDENTITY, buffers, out))
}

/// Adds the triangle-list primitives of `mesh`, vertices moved by `transform`.
fn add_mesh(mesh: &::gltf::Mesh, transform: Mat4, buffers: &[Vec<u8>], out: &mut Mesh) -> Result<(), String> {
    for primitive in mesh.primitives().filter(|p| p.mode() == Mode::Triangles) {
        let in_primitive = |e: String| format!("mesh {} primitive {}: {e}", mesh.index(), primitive.index());
        let positions = primitive.get(&Semantic::Positions).ok_or_else(|| in_primitive("no POSITION".into()))?;
        let positions = accessors::positions(&positions, buffers).map_err(in_primitive)?;
        let corners = match primitive.indices() {
            Some(indices) => accessors::indices(&indices, buffers).map_err(in_primitive)?,
            None => (0..positions.len()).map(|i| i as u32).collect(),
        };
        if let Some(corner) = corners.iter().find(|&&i| i as usize >= positions.len()) {
            return Err(in_primitive(format!("index {corner} of {} vertices", positions.len())));
        }
        let base = u32::try_from(out.positions.len())
            .ok()
            .filter(|base| base.checked_add(positions.len() as u32).is_some() && positions.len() <= u32::MAX as usize)
            .ok_or_else(|| in_primitive("more than 2^32 vertices in all".into()))?;
        out.positions.extend(positions.into_iter().map(|p| transform.transform_point3(p)));
        out.triangles.extend(corners.chunks_exact(3).map(|t| [base + t[0], base + t[1], base + t[2]]));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    /// Little-endian bytes of a buffer holding three float3 positions, then three u16 indices (padded to 4 bytes).
    fn triangle_buffer() -> Vec<u8> {
        let positions = [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let mut bytes: Vec<u8> = positions.iter().flat_map(|v| v.to_le_bytes()).collect();
        bytes.extend([2u16, 1, 0, 0].iter().flat_map(|i| i.to_le_bytes()));
        bytes
    }

    /// A minimal glTF document around one buffer URI: one indexed triangle in a node moved by +10 on x, and, when
    /// `points`, a second primitive in POINTS mode that must be skipped.
    fn document(uri: &str, length: usize, points: bool) -> String {
        let extra_primitive = if points { r#",{"attributes":{"POSITION":0},"mode":0}"# } else { "" };
        format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],
            "nodes":[{{"mesh":0,"translation":[10,0,0]}}],
            "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}{extra_primitive}]}}],
            "buffers":[{{"uri":"{uri}","byteLength":{length}}}],
            "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":36}},{{"buffer":0,"byteOffset":36,"byteLength":6}}],
            "accessors":[
              {{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
              {{"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"}}]}}"#
        )
    }

    /// [`document`] with the triangle buffer embedded as a base64 `data:` URI.
    fn embedded_document(points: bool) -> String {
        let buffer = triangle_buffer();
        let encoded = base64::engine::general_purpose::STANDARD.encode(&buffer);
        document(&format!("data:application/octet-stream;base64,{encoded}"), buffer.len(), points)
    }

    /// Writes `files` into a fresh temporary folder and parses the first as its file is parsed, with the checks
    /// of every format.
    fn load_files(files: &[(&str, &[u8])]) -> Result<Mesh, rayd_engine::mesh::LoadError> {
        let dir = tempfile::tempdir().unwrap();
        for (name, bytes) in files {
            std::fs::write(dir.path().join(name), bytes).unwrap();
        }
        let (path, bytes) = (dir.path().join(files[0].0), files[0].1);
        crate::mesh::MeshFormat::of(&path)?.parse(&path, bytes)
    }

    #[test]
    fn embedded_base64_buffer_gives_the_transformed_indexed_triangle() {
        let mesh = load_files(&[("tri.gltf", embedded_document(true).as_bytes())]).unwrap();
        assert_eq!(mesh.positions, [Vec3::new(10.0, 0.0, 0.0), Vec3::new(11.0, 0.0, 0.0), Vec3::new(10.0, 1.0, 0.0)]);
        assert_eq!(mesh.triangles, [[2, 1, 0]], "the POINTS primitive adds nothing");
    }

    #[test]
    fn external_bin_is_read_beside_the_gltf_and_short_buffers_are_errors() {
        let buffer = triangle_buffer();
        let text = document("tri.bin", buffer.len(), false);
        let mesh = load_files(&[("tri.gltf", text.as_bytes()), ("tri.bin", &buffer)]).unwrap();
        assert_eq!(mesh.triangles.len(), 1);
        let error = load_files(&[("tri.gltf", text.as_bytes()), ("tri.bin", &buffer[..20])]).unwrap_err();
        assert!(error.reason.contains("holds 20 of its"), "{}", error.reason);
        assert!(load_files(&[("tri.gltf", text.as_bytes())]).unwrap_err().reason.contains("tri.bin"));
    }

    #[test]
    fn glb_takes_its_buffer_from_the_binary_chunk() {
        let buffer = triangle_buffer();
        let json = document("", buffer.len(), false).replace(r#""uri":"","#, "");
        let json = format!("{json:<width$}", width = json.len().next_multiple_of(4));
        let mut glb = Vec::new();
        let total = 12 + 8 + json.len() + 8 + buffer.len();
        glb.extend(b"glTF".iter().chain(&2u32.to_le_bytes()).chain(&(total as u32).to_le_bytes()));
        glb.extend((json.len() as u32).to_le_bytes().iter().chain(b"JSON").chain(json.as_bytes()));
        glb.extend((buffer.len() as u32).to_le_bytes().iter().chain(b"BIN\0").chain(&buffer));
        let mesh = load_files(&[("tri.glb", &glb)]).unwrap();
        assert_eq!(mesh.triangles, [[2, 1, 0]]);
        assert_eq!(mesh.positions[1], Vec3::new(11.0, 0.0, 0.0));
    }

    #[test]
    fn nodes_are_taken_as_trees_in_order_and_a_node_reached_twice_is_refused() {
        let text = embedded_document(false);
        let with_nodes = |roots: &str, nodes: &str| {
            let changed = text.replace(r#""scenes":[{"nodes":[0]}]"#, &format!(r#""scenes":[{{"nodes":{roots}}}]"#));
            let changed =
                changed.replace(r#""nodes":[{"mesh":0,"translation":[10,0,0]}]"#, &format!(r#""nodes":{nodes}"#));
            assert_ne!(changed, text);
            load_files(&[("tri.gltf", changed.as_bytes())])
        };
        // Node 0 holds node 2 then node 1; each child's triangle comes in the order the children are listed, placed
        // by its parent's transform times its own.
        let placed = r#"[{"translation":[10,0,0],"children":[2,1]},{"mesh":0,"translation":[0,1,0]},{"mesh":0}]"#;
        let mesh = with_nodes("[0]", placed).unwrap();
        assert_eq!(mesh.triangles, [[2, 1, 0], [5, 4, 3]]);
        assert_eq!((mesh.positions[0], mesh.positions[3]), (Vec3::new(10.0, 0.0, 0.0), Vec3::new(10.0, 1.0, 0.0)));
        // A chain 100,000 nodes deep, its mesh at the end: walked without recursion (it overflowed the stack).
        let chain: Vec<String> = (1..100_000).map(|i| format!(r#"{{"children":[{i}]}}"#)).collect();
        let chain = format!(r#"[{},{{"mesh":0}}]"#, chain.join(","));
        assert_eq!(with_nodes("[0]", &chain).unwrap().triangles.len(), 1);
        // A cycle (recursion without end), a node with two parents, a root listed twice (copies of subtrees).
        for (roots, nodes, twice) in [
            ("[0]", r#"[{"children":[1]},{"mesh":0,"children":[0]}]"#, 0),
            ("[0]", r#"[{"children":[1,2]},{"children":[3]},{"children":[3]},{"mesh":0}]"#, 3),
            ("[0,0]", r#"[{"mesh":0}]"#, 0),
        ] {
            let error = with_nodes(roots, nodes).unwrap_err();
            assert!(error.reason.contains(&format!("node {twice} is reached twice")), "{}", error.reason);
        }
    }

    #[test]
    fn glb_with_a_length_shorter_than_its_header_is_refused() {
        // The `meshes` fuzz target's crash (2026-11-23): a GLB header of length 0.
        let crash = b"glTF22%\0\0\0\0\0\0\x0022  1";
        let error = load_files(&[("crash.glb", crash)]).unwrap_err();
        assert!(error.reason.contains("length 0 is shorter than the 12-byte header"), "{}", error.reason);
    }

    #[test]
    fn position_accessor_beyond_the_accessors_is_refused() {
        // The `meshes` fuzz target's second crash (2026-11-23): a document whose `accessors` key was misspelt.
        let text = embedded_document(false).replace(r#""accessors""#, r#""accessorw""#);
        let error = load_files(&[("tri.gltf", text.as_bytes())]).unwrap_err();
        assert!(error.reason.contains("POSITION: accessor 0 of 0"), "{}", error.reason);
    }

    #[test]
    fn accessors_of_the_wrong_kind_or_beyond_their_view_are_refused() {
        let text = embedded_document(false);
        let refused = |from: &str, to: &str| {
            let changed = text.replace(from, to);
            assert_ne!(changed, text);
            load_files(&[("tri.gltf", changed.as_bytes())]).unwrap_err().reason
        };
        // The `meshes` fuzz target's third crash (2026-11-23): signed 16-bit indices.
        let signed = refused(r#""componentType":5123"#, r#""componentType":5122"#);
        assert!(signed.contains("mesh 0 primitive 0: indices must be unsigned scalars, not I16"), "{signed}");
        let count = refused(r#""count":3,"type":"SCALAR""#, r#""count":4,"type":"SCALAR""#);
        assert!(count.contains("4 elements of 2 bytes, 2 apart, from byte 0 lie beyond bufferView 1 of 6"), "{count}");
        let index = refused(&text[text.find("\"indices\"").unwrap()..][..11], r#""indices":0"#);
        assert!(index.contains("indices must be unsigned scalars, not F32 Vec3"), "{index}");
        let stride = refused(r#""byteLength":36}"#, r#""byteLength":36,"byteStride":8}"#);
        assert!(stride.contains("byteStride 8 is less than an element's 12 bytes"), "{stride}");
    }
}
