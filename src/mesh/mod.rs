//! Triangle meshes for tests, benchmarks and tools: OBJ loading ([`obj`]), packing into build-input bytes, a
//! large scene tiled from several meshes, and a scene of very uneven triangle sizes.

use std::path::Path;

use glam::Vec3;

use crate::geometry::TriangleInput;
use crate::raygen::uniform;

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
        Mesh::parse_obj(&bytes).map_err(error)
    }

    /// Parses the bytes of an OBJ file as [`Mesh::load_obj`] loads it, for a caller that read the file itself.
    pub fn parse_obj(bytes: &[u8]) -> Result<Mesh, String> {
        let text = std::str::from_utf8(bytes).map_err(|e| format!("not UTF-8 text: {e}"))?;
        let mesh = obj::parse(text)?;
        if mesh.triangles.is_empty() {
            return Err("no triangles".into());
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

    /// This mesh with triangles of very different sizes added: a floor of two triangles under it, three times as
    /// wide and deep as its box, and `slivers` needles, each from a point of the box to another one at least half
    /// its diagonal away, a thousandth of the diagonal wide at the far end (points from `seed`). Long thin triangles
    /// crossing a scene have boxes that overlap most of it, which a BVH without spatial splits handles worst. A mesh
    /// without a finite box is returned as it is.
    pub fn with_floor_and_slivers(&self, slivers: usize, seed: u64) -> Mesh {
        let (lo, hi) = self.bounds();
        let (size, middle) = (hi - lo, (lo + hi) * 0.5);
        let mut scene = self.clone();
        if !size.is_finite() {
            return scene;
        }
        let mut add = |corners: [Vec3; 3]| {
            let base = scene.positions.len() as u32;
            scene.positions.extend(corners);
            scene.triangles.push([base, base + 1, base + 2]);
        };
        let floor = |x: f32, z: f32| Vec3::new(middle.x + 1.5 * size.x * x, lo.y, middle.z + 1.5 * size.z * z);
        add([floor(-1.0, -1.0), floor(1.0, 1.0), floor(1.0, -1.0)]);
        add([floor(-1.0, -1.0), floor(-1.0, 1.0), floor(1.0, 1.0)]);
        let diagonal = size.length();
        let mut draws = 0u64;
        let mut point = || {
            draws += 3;
            lo + size * Vec3::new(uniform(seed, draws - 3), uniform(seed, draws - 2), uniform(seed, draws - 1))
        };
        for _ in 0..slivers {
            let start = point();
            let end = loop {
                let end = point();
                if end.distance(start) >= 0.5 * diagonal {
                    break end;
                }
            };
            let across = (end - start).normalize().any_orthonormal_vector() * (1e-3 * diagonal);
            add([start, end, end + across]);
        }
        scene
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_floor_and_slivers_are_added_after_the_meshs_own_triangles() {
        let cube_corners = [Vec3::ZERO, Vec3::new(1.0, 2.0, 0.0), Vec3::new(0.0, 2.0, 3.0)];
        let mesh = Mesh { positions: cube_corners.to_vec(), triangles: vec![[0, 1, 2]] };
        let scene = mesh.with_floor_and_slivers(50, 7);
        assert_eq!(scene.triangles.len(), 1 + 2 + 50);
        assert_eq!(scene.corners(0), mesh.corners(0));
        let diagonal = Vec3::new(1.0, 2.0, 3.0).length();
        let area = |c: [Vec3; 3]| 0.5 * (c[1] - c[0]).cross(c[2] - c[0]).length();
        // The floor: at the bottom of the box, 3 × 1 by 3 × 3 in all.
        let floor = area(scene.corners(1)) + area(scene.corners(2));
        assert!((floor - 27.0).abs() < 1e-4, "floor area {floor}");
        assert!((1..3).all(|t| scene.corners(t).iter().all(|c| c.y == 0.0)));
        for sliver in 3..scene.triangles.len() {
            let [start, end, side] = scene.corners(sliver);
            assert!(start.distance(end) >= 0.5 * diagonal, "sliver {sliver} too short");
            assert!((end.distance(side) - 1e-3 * diagonal).abs() < 1e-6, "sliver {sliver} width");
            assert!([start, end].iter().all(|p| p.cmpge(Vec3::ZERO).all() && p.cmple(Vec3::new(1.0, 2.0, 3.0)).all()));
        }
        assert_eq!(scene, mesh.with_floor_and_slivers(50, 7), "the same seed gives the same scene");
        assert_eq!(Mesh::default().with_floor_and_slivers(5, 7), Mesh::default());
    }
}
