//! glTF 2.0 (`.gltf` with embedded `data:` or external `.bin` buffers, and binary `.glb`) through the `gltf` crate
//! without its image decoders. Every triangle-list primitive (mode TRIANGLES) of the default scene (else the first
//! scene) is taken, placed by its node's world transform; a file without scenes gives every mesh untransformed.
//! Points, lines, strips and fans are skipped. External URIs are plain relative paths (no percent-decoding).

use std::path::Path;

use ::gltf::buffer::Source;
use ::gltf::mesh::Mode;
use ::gltf::{Document, Gltf, Node};
use base64::Engine;
use glam::{Mat4, Vec3};
use rayd_engine::mesh::Mesh;

/// Reads the glTF or GLB file at `path`.
pub(super) fn load(path: &Path) -> Result<Mesh, String> {
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    let Gltf { document, mut blob } = Gltf::from_slice(&bytes).map_err(|e| e.to_string())?;
    let folder = path.parent().unwrap_or(Path::new("."));
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
        Some(scene) => scene.nodes().try_for_each(|node| add_node(&node, Mat4::IDENTITY, &buffers, &mut mesh))?,
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

/// Adds `node`'s mesh and its children's, placed by `parent` times the node's own transform.
fn add_node(node: &Node, parent: Mat4, buffers: &[Vec<u8>], out: &mut Mesh) -> Result<(), String> {
    let world = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
    if let Some(mesh) = node.mesh() {
        add_mesh(&mesh, world, buffers, out)?;
    }
    node.children().try_for_each(|child| add_node(&child, world, buffers, out))
}

/// Adds every mesh of a document that has no scene, untransformed.
fn add_all_meshes(document: &Document, buffers: &[Vec<u8>], out: &mut Mesh) -> Result<(), String> {
    document.meshes().try_for_each(|mesh| add_mesh(&mesh, Mat4::IDENTITY, buffers, out))
}

/// Adds the triangle-list primitives of `mesh`, vertices moved by `transform`.
fn add_mesh(mesh: &::gltf::Mesh, transform: Mat4, buffers: &[Vec<u8>], out: &mut Mesh) -> Result<(), String> {
    for primitive in mesh.primitives().filter(|p| p.mode() == Mode::Triangles) {
        let reader = primitive.reader(|buffer| buffers.get(buffer.index()).map(Vec::as_slice));
        let where_ = || format!("mesh {} primitive {}", mesh.index(), primitive.index());
        let positions = reader.read_positions().ok_or_else(|| format!("{}: positions cannot be read", where_()))?;
        let base = out.positions.len() as u32;
        out.positions.extend(positions.map(|p| transform.transform_point3(Vec3::from(p))));
        let corners: Vec<u32> = match reader.read_indices() {
            Some(indices) => indices.into_u32().map(|i| base + i).collect(),
            None => (base..out.positions.len() as u32).collect(),
        };
        out.triangles.extend(corners.chunks_exact(3).map(|t| [t[0], t[1], t[2]]));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
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

    /// Writes `files` into a fresh temporary folder and loads the first through the public entry point.
    fn load_files(files: &[(&str, &[u8])]) -> Result<Mesh, rayd_engine::mesh::LoadError> {
        let dir = tempfile::tempdir().unwrap();
        for (name, bytes) in files {
            std::fs::write(dir.path().join(name), bytes).unwrap();
        }
        crate::mesh::load_mesh(dir.path().join(files[0].0))
    }

    #[test]
    fn embedded_base64_buffer_gives_the_transformed_indexed_triangle() {
        let buffer = triangle_buffer();
        let uri = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&buffer)
        );
        let mesh = load_files(&[("tri.gltf", document(&uri, buffer.len(), true).as_bytes())]).unwrap();
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
}
