//! Mesh files into engine [`Mesh`]es, chosen by extension: OBJ through the engine, PLY through
//! `ply-rs-bw`, glTF and GLB through `gltf`.

mod gltf;
mod ply;

use std::fmt::Display;
use std::path::Path;

use rayd_engine::mesh::{LoadError, Mesh};

/// Loads every triangle of a `.obj`, `.ply`, `.gltf` or `.glb` file (extension case ignored) into one mesh.
/// Polygons are triangulated (OBJ and PLY as fans); glTF scenes are flattened with their node transforms.
pub fn load_mesh(path: impl AsRef<Path>) -> Result<Mesh, LoadError> {
    let path = path.as_ref();
    let extension = path.extension().and_then(|e| e.to_str()).unwrap_or_default().to_ascii_lowercase();
    let mesh = match extension.as_str() {
        "obj" => return Mesh::load_obj(path),
        "ply" => ply::load(path),
        "gltf" | "glb" => gltf::load(path),
        _ => Err(format!("unknown mesh extension {extension:?} (expected obj, ply, gltf or glb)")),
    };
    mesh.and_then(checked).map_err(|reason| load_error(path, reason))
}

/// A [`LoadError`] for `path`.
fn load_error(path: &Path, reason: impl Display) -> LoadError {
    LoadError { path: path.display().to_string(), reason: reason.to_string() }
}

/// `mesh` if it has triangles and every index names a vertex.
fn checked(mesh: Mesh) -> Result<Mesh, String> {
    if mesh.triangles.is_empty() {
        return Err("no triangles".into());
    }
    let vertices = mesh.positions.len();
    if let Some((t, corners)) =
        mesh.triangles.iter().enumerate().find(|(_, t)| t.iter().any(|&i| i as usize >= vertices))
    {
        return Err(format!("triangle {t} {corners:?} names a vertex beyond the {vertices} there are"));
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_extensions_and_bad_indices_are_refused_with_the_path() {
        let error = load_mesh("scene.stl").unwrap_err();
        assert_eq!(error.path, "scene.stl");
        assert!(error.reason.contains("stl"), "{}", error.reason);
        let mesh = Mesh { positions: vec![glam::Vec3::ZERO; 3], triangles: vec![[0, 1, 3]] };
        assert!(checked(mesh).unwrap_err().contains("triangle 0"));
        assert_eq!(checked(Mesh::default()).unwrap_err(), "no triangles");
    }

    #[test]
    fn obj_goes_through_the_engine() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("quad.OBJ");
        std::fs::write(&path, "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n").unwrap();
        let mesh = load_mesh(&path).unwrap();
        assert_eq!((mesh.positions.len(), mesh.triangles.len()), (4, 2));
    }
}
