//! Mesh files into engine [`Mesh`]es, chosen by extension: OBJ through the engine, PLY through
//! `ply-rs-bw`, glTF and GLB through `gltf`.

mod gltf;
mod ply;

use std::fmt::Display;
use std::path::Path;

use rayd_engine::mesh::{LoadError, Mesh};

use crate::error::{Error, Result};

/// Loads every triangle of a `.obj`, `.ply`, `.gltf` or `.glb` file (extension case ignored) into one mesh.
/// Polygons are triangulated (OBJ and PLY as fans); glTF scenes are flattened with their node transforms. A file
/// that cannot be read is an [`Error::Io`] (NOT_FOUND when it is missing), as for any other local file; one that
/// is not a mesh of its format is an [`Error::Mesh`] (INVALID_ARGUMENT).
pub fn load_mesh(path: impl AsRef<Path>) -> Result<Mesh> {
    let path = path.as_ref();
    let format = MeshFormat::of(path)?;
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    Ok(format.parse(path, &bytes)?)
}

/// The formats [`load_mesh`] reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum MeshFormat {
    /// Wavefront OBJ.
    Obj,
    /// Stanford PLY, ASCII or binary.
    Ply,
    /// glTF 2.0, as JSON (`.gltf`) or binary (`.glb`).
    Gltf,
}

impl MeshFormat {
    /// The format of the file at `path`, by its extension.
    pub(crate) fn of(path: &Path) -> Result<MeshFormat, LoadError> {
        let extension = path.extension().and_then(|e| e.to_str()).unwrap_or_default().to_ascii_lowercase();
        match extension.as_str() {
            "obj" => Ok(MeshFormat::Obj),
            "ply" => Ok(MeshFormat::Ply),
            "gltf" | "glb" => Ok(MeshFormat::Gltf),
            _ => {
                Err(load_error(path, format!("unknown mesh extension {extension:?} (expected obj, ply, gltf or glb)")))
            }
        }
    }

    /// The mesh of `bytes`, the contents of the file at `path` (a glTF file's external buffers are read beside it).
    pub(crate) fn parse(self, path: &Path, bytes: &[u8]) -> Result<Mesh, LoadError> {
        let mesh = match self {
            MeshFormat::Obj => Mesh::parse_obj(bytes),
            MeshFormat::Ply => ply::parse(bytes),
            MeshFormat::Gltf => gltf::parse(bytes, path.parent().unwrap_or(Path::new("."))),
        };
        mesh.and_then(checked).map_err(|reason| load_error(path, reason))
    }
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
        let Err(Error::Mesh(error)) = load_mesh("scene.stl") else { panic!("an unknown extension is a mesh error") };
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

    #[test]
    fn a_missing_file_is_not_found_with_its_path_and_a_file_that_is_no_mesh_an_invalid_argument() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing.ply");
        let error = load_mesh(&missing).unwrap_err();
        assert_eq!(error.code(), tonic::Code::NotFound, "{error}");
        assert!(error.to_string().starts_with(&missing.display().to_string()), "{error}");
        let broken = dir.path().join("broken.obj");
        std::fs::write(&broken, "f 1 2 3\n").unwrap();
        assert_eq!(load_mesh(&broken).unwrap_err().code(), tonic::Code::InvalidArgument);
    }
}
