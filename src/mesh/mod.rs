//! Triangle meshes for tests, benchmarks and tools: OBJ loading ([`obj`]), packing into build-input bytes, and a
//! large scene tiled from several meshes.

use std::path::Path;

use glam::Vec3;

use crate::geometry::TriangleInput;

mod obj;

/// Why a mesh could not be loaded.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {reason}")]
pub struct LoadError {
    /// The file.
    pub path: String,
    /// What went wrong.
    pub reason: String,
}

/// An indexed triangle mesh.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Three vertex indices a triangle.
    pub triangles: Vec<[u32; 3]>,
}

/// A mesh packed as little-endian build-input bytes (float3 vertices, u32×3 indices).
#[derive(Debug, Clone)]
pub struct PackedMesh {
    /// Tightly packed float3 positions.
    pub vertices: Vec<u8>,
    /// Tightly packed u32×3 indices.
    pub indices: Vec<u8>,
}

impl PackedMesh {
    /// A build input over these bytes.
    pub fn input(&self) -> TriangleInput<'_> {
        TriangleInput::indexed(&self.vertices, &self.indices)
    }
}

impl Mesh {
    /// Loads every object of an OBJ file into one mesh (polygons are split into fans).
    pub fn load_obj(path: impl AsRef<Path>) -> Result<Mesh, LoadError> {
        let path = path.as_ref();
        let error = |reason: String| LoadError { path: path.display().to_string(), reason };
        let bytes = std::fs::read(path).map_err(|e| error(e.to_string()))?;
        let text = std::str::from_utf8(&bytes).map_err(|e| error(format!("not UTF-8 text: {e}")))?;
        let mesh = obj::parse(text).map_err(error)?;
        if mesh.triangles.is_empty() {
            return Err(error("no triangles".into()));
        }
        Ok(mesh)
    }

    /// The smallest box holding every vertex.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.positions.iter().fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &p| (lo.min(p), hi.max(p)))
    }

    /// The corners of triangle `index`.
    pub fn corners(&self, index: usize) -> [Vec3; 3] {
        self.triangles[index].map(|v| self.positions[v as usize])
    }

    /// Packs the mesh as build-input bytes.
    pub fn pack(&self) -> PackedMesh {
        PackedMesh {
            vertices: self.positions.iter().flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect(),
            indices: self.triangles.iter().flatten().flat_map(|i| i.to_le_bytes()).collect(),
        }
    }

    /// A copy scaled uniformly to fit a unit cube and moved so its box's centre is at `centre`.
    pub fn normalized_at(&self, centre: Vec3) -> Mesh {
        let (lo, hi) = self.bounds();
        let scale = 1.0 / (hi - lo).max_element().max(f32::MIN_POSITIVE);
        let middle = (lo + hi) * 0.5;
        Mesh {
            positions: self.positions.iter().map(|&p| (p - middle) * scale + centre).collect(),
            triangles: self.triangles.clone(),
        }
    }

    /// A scene of at least `min_triangles` triangles: `meshes`, each scaled to a unit cube, placed in turn on a
    /// square grid (1.25 units apart) until the count is reached.
    pub fn tiled(meshes: &[Mesh], min_triangles: usize) -> Mesh {
        let per_cycle: usize = meshes.iter().map(|m| m.triangles.len()).sum();
        let copies = min_triangles.div_ceil(per_cycle.max(1)).max(1) * meshes.len();
        let side = (copies as f32).sqrt().ceil() as usize;
        let mut scene = Mesh::default();
        for copy in 0..copies {
            let centre = Vec3::new((copy % side) as f32 * 1.25, 0.0, (copy / side) as f32 * 1.25);
            let placed = meshes[copy % meshes.len()].normalized_at(centre);
            let base = scene.positions.len() as u32;
            scene.positions.extend(placed.positions);
            scene.triangles.extend(placed.triangles.iter().map(|t| t.map(|i| i + base)));
            if scene.triangles.len() >= min_triangles && copy % meshes.len() == meshes.len() - 1 {
                break;
            }
        }
        scene
    }
}
