//! Watertightness: rays aimed exactly at shared vertices and edges of closed meshes never slip through, and
//! crossing counts give a consistent inside/outside answer, on the CPU and on the first wgpu device (adapter policy
//! as in `tests/wgpu.rs`).

mod common;

use common::{f32_at, gpu_with, icosphere, pack_rays, shared_mesh, u32_at};
use glam::{Vec3, Vec3A};
use rayd_engine::accel::BuildOptions;
use rayd_engine::backend::wgpu::WgpuOptions;
use rayd_engine::format::{HitFormat, Ray, RayFormat};
use rayd_engine::geometry::BuildInput;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::raygen::uniform;
use rayd_engine::{Context, Device};

/// The CPU, and the first wgpu device where there is one.
fn devices() -> Vec<Device> {
    std::iter::once(Device::cpu()).chain(gpu_with(WgpuOptions::default())).collect()
}

/// Traces a count query on `device` and returns (closest t, crossings) per ray.
fn crossings(device: &Device, mesh: &Mesh, rays: &[Ray]) -> Vec<(f32, u32)> {
    let packed = mesh.pack();
    let context = Context::new(device.clone());
    let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let query = Query { kind: QueryKind::Count, ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T) };
    let rays = pack_rays(rays, RayFormat::OriginTminDirectionTmax);
    let layout = query.output_layout(rays.len()).unwrap();
    let (mut hits, mut counts) = (vec![0; layout.hits], vec![0; layout.counts]);
    context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
    (0..layout.rays).map(|i| (f32_at(&hits, i), u32_at(&counts, i))).collect()
}

/// Every directed edge appears once and its reverse once: the mesh is closed and consistently oriented.
fn is_closed(mesh: &Mesh) -> bool {
    let mut edges = std::collections::HashMap::new();
    for t in &mesh.triangles {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            *edges.entry((a, b)).or_insert(0) += 1;
        }
    }
    edges.iter().all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1))
}

/// Points on the mesh to aim at: every vertex and every edge midpoint.
fn vertices_and_edge_midpoints(mesh: &Mesh) -> Vec<Vec3> {
    let mut points = mesh.positions.clone();
    for t in &mesh.triangles {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            if a < b {
                points.push((mesh.positions[a as usize] + mesh.positions[b as usize]) * 0.5);
            }
        }
    }
    points
}

fn ray_towards(from: Vec3, to: Vec3) -> Ray {
    Ray { origin: from.into(), direction: Vec3A::from(to - from), ..Ray::default() }
}

#[test]
fn rays_from_inside_a_sphere_through_every_vertex_and_edge_cross_exactly_once() {
    let centre = Vec3::new(0.1, -0.2, 0.3);
    let sphere = icosphere(3, centre);
    assert!(is_closed(&sphere));
    let targets = vertices_and_edge_midpoints(&sphere);
    let mut rays: Vec<Ray> = targets.iter().map(|&p| ray_towards(centre, p)).collect();
    // And from off-centre points, so that the rays meet vertices and edges at other angles.
    for k in 0..4u64 {
        let offset = Vec3::new(uniform(k, 0), uniform(k, 1), uniform(k, 2)) * 0.8 - 0.4;
        rays.extend(targets.iter().map(|&p| ray_towards(centre + offset, p)));
    }
    for device in devices() {
        let on = &device.info().id;
        for (i, (t, count)) in crossings(&device, &sphere, &rays).into_iter().enumerate() {
            assert!(t > 0.0, "{on}: ray {i} escaped the closed sphere");
            assert_eq!(count, 1, "{on}: ray {i} crossed the sphere {count} times");
        }
    }
}

#[test]
fn crossing_parity_is_the_same_in_every_direction_on_closed_shared_meshes() {
    let (devices, mut checked) = (devices(), 0);
    for name in ["cow", "spot", "fandisk", "nefertiti"] {
        let mesh = shared_mesh(name);
        assert!(is_closed(&mesh), "{name} is expected to be closed");
        let (lo, hi) = mesh.bounds();
        let mut rays = Vec::new();
        const POINTS: u64 = 48;
        const DIRECTIONS: usize = 16;
        for p in 0..POINTS {
            let from = lo + (hi - lo) * Vec3::new(uniform(p, 0), uniform(p, 1), uniform(p, 2));
            for d in 0..DIRECTIONS as u64 {
                // Half the rays go exactly through a vertex, half through an edge midpoint.
                let triangle = mesh.triangles[(uniform(p, 10 + d) * mesh.triangles.len() as f32) as usize];
                let (a, b) = (mesh.positions[triangle[0] as usize], mesh.positions[triangle[1] as usize]);
                rays.push(ray_towards(from, if d % 2 == 0 { a } else { (a + b) * 0.5 }));
            }
        }
        for device in &devices {
            let on = &device.info().id;
            let results = crossings(device, &mesh, &rays);
            let mut inside_points = 0;
            for (p, point_results) in results.chunks(DIRECTIONS).enumerate() {
                let parity = point_results[0].1 % 2;
                for (d, &(t, count)) in point_results.iter().enumerate() {
                    let disagree = format!("{on}: {name}: point {p}, ray {d}: {count} crossings disagree with ray 0");
                    assert_eq!(count % 2, parity, "{disagree}");
                    assert!(parity == 0 || t > 0.0, "{on}: {name}: point {p}, ray {d} escaped from inside");
                }
                inside_points += parity;
            }
            // Both inside and outside points were tested.
            assert!(inside_points > 0 && inside_points < POINTS as u32, "{on}: {name}: {inside_points} inside");
            checked += 1;
        }
    }
    assert!(checked == 4 * devices.len(), "{checked} meshes and devices checked");
}
