//! Scenes and rays shared by the engine's integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

use glam::{Vec3, Vec3A};
use rayd_engine::Device;
use rayd_engine::backend::wgpu::WgpuOptions;
use rayd_engine::format::{Ray, RayFlags, RayFormat};
use rayd_engine::geometry::{BuildInput, TriangleInput};
use rayd_engine::mesh::Mesh;
use rayd_engine::raygen::uniform;

/// The first wgpu device with `options`, or `None` (after a notice) on a machine without an adapter; panics
/// instead when `RAYD_REQUIRE_GPU=1`.
pub fn gpu_with(options: WgpuOptions) -> Option<Device> {
    if let Some(device) = Device::wgpu(options).into_iter().next() {
        return Some(device);
    }
    if std::env::var("RAYD_REQUIRE_GPU").as_deref() == Ok("1") {
        panic!("RAYD_REQUIRE_GPU=1 but wgpu found no adapter (install mesa-vulkan-drivers for lavapipe)");
    }
    eprintln!("skipped: no wgpu adapter (set RAYD_REQUIRE_GPU=1 to fail instead)");
    None
}

/// `../shared/data/meshes/NAME.obj`.
pub fn shared_mesh(name: &str) -> Mesh {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/meshes").join(format!("{name}.obj"));
    Mesh::load_obj(&path).unwrap_or_else(|e| panic!("{e}"))
}

/// A unit right triangle in the plane z = 0, front facing +z.
pub fn unit_triangle() -> Mesh {
    Mesh { positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y], triangles: vec![[0, 1, 2]] }
}

/// A closed sphere: an icosahedron subdivided `levels` times, vertices shared between triangles, radius 1 around
/// `centre`, counter-clockwise seen from outside.
pub fn icosphere(levels: u32, centre: Vec3) -> Mesh {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut positions: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut triangles: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..levels {
        let mut midpoints = std::collections::HashMap::new();
        let mut midpoint = |a: u32, b: u32, positions: &mut Vec<Vec3>| {
            *midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
                positions.push(((positions[a as usize] + positions[b as usize]) * 0.5).normalize());
                positions.len() as u32 - 1
            })
        };
        triangles = triangles
            .iter()
            .flat_map(|&[a, b, c]| {
                let ab = midpoint(a, b, &mut positions);
                let bc = midpoint(b, c, &mut positions);
                let ca = midpoint(c, a, &mut positions);
                [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
            })
            .collect();
    }
    Mesh { positions: positions.into_iter().map(|p| p + centre).collect(), triangles }
}

/// A triangle soup of `count` random triangles in the unit cube, sizes from tiny to large, a third of them
/// sharing a vertex with the previous one.
pub fn random_soup(count: usize, seed: u64) -> Mesh {
    let mut mesh = Mesh::default();
    let u = |k: u64| uniform(seed, k);
    for i in 0..count as u64 {
        let base = i * 16;
        let anchor = if i % 3 == 2 {
            mesh.positions[mesh.positions.len() - 1]
        } else {
            Vec3::new(u(base), u(base + 1), u(base + 2))
        };
        let size = 0.5f32.powf(u(base + 3) * 8.0);
        let corner = |k: u64| anchor + (Vec3::new(u(base + k), u(base + k + 1), u(base + k + 2)) - 0.5) * size;
        let first = mesh.positions.len() as u32;
        mesh.positions.extend([anchor, corner(4), corner(7)]);
        mesh.triangles.push([first, first + 1, first + 2]);
    }
    mesh
}

/// `count` random rays through the unit cube with every field randomized: tmin, tmax, time, mask and flags.
pub fn random_rays(count: usize, seed: u64) -> Vec<Ray> {
    (0..count as u64)
        .map(|i| {
            let u = |k: u64| uniform(seed, i * 16 + k);
            let origin = Vec3A::new(u(0), u(1), u(2)) * 3.0 - 1.0;
            let target = Vec3A::new(u(3), u(4), u(5));
            let tmin = if u(6) < 0.5 { 0.0 } else { u(7) * 0.5 };
            let tmax = if u(8) < 0.5 { f32::INFINITY } else { tmin + u(9) * 2.0 };
            let flags =
                if u(10) < 0.7 { RayFlags::empty() } else { RayFlags::from_bits_truncate((u(11) * 8.0) as u32) };
            Ray {
                origin,
                direction: (target - origin) * (0.5 + u(12)),
                tmin,
                tmax,
                time: u(13),
                mask: if u(14) < 0.5 { 0 } else { 1 << (u(15) * 4.0) as u32 },
                visibility: 0xFF,
                flags,
            }
        })
        .collect()
}

/// Packs rays in `format`.
pub fn pack_rays(rays: &[Ray], format: RayFormat) -> Vec<u8> {
    let mut bytes = vec![0u8; rays.len() * format.size()];
    for (ray, slot) in rays.iter().zip(bytes.chunks_exact_mut(format.size())) {
        format.encode(ray, slot);
    }
    bytes
}

/// A triangle input over a packed mesh with masks.
pub fn input_with_masks<'a>(vertices: &'a [u8], indices: &'a [u8], masks: &'a [u8]) -> BuildInput<'a> {
    BuildInput::Triangles(TriangleInput { masks: Some(masks), ..TriangleInput::indexed(vertices, indices) })
}

/// Reads little-endian f32 `index` of a buffer.
pub fn f32_at(bytes: &[u8], index: usize) -> f32 {
    f32::from_le_bytes(bytes[4 * index..4 * index + 4].try_into().unwrap())
}

/// Reads little-endian u32 `index` of a buffer.
pub fn u32_at(bytes: &[u8], index: usize) -> u32 {
    u32::from_le_bytes(bytes[4 * index..4 * index + 4].try_into().unwrap())
}
