//! Watertight ray/triangle intersection (Woop, Benthin, Wald 2013, "Watertight Ray/Triangle Intersection"),
//! with a consistent rule for rays that pass exactly through an edge or a vertex.
//!
//! The triangle is translated to the ray origin, permuted so the ray runs along the largest direction axis, and
//! sheared so the ray becomes the +z axis. The three 2D edge functions `U`, `V`, `W` of the projected triangle
//! are the barycentric weights of v0, v1, v2 scaled by `det = U + V + W`. Shared vertices project to the same
//! f32 values whichever triangle they belong to, and a shared edge's function in one triangle is exactly the
//! negation of its function in the other, so no ray slips between two triangles of a closed mesh.
//!
//! **Edge and vertex rule.** When an edge function is exactly 0 (after the f64 recomputation of the paper) the
//! ray is treated as moved by an infinitesimal offset in a fixed direction of the projection plane, so that of
//! two triangles sharing that edge and facing the same way exactly one is hit, and of a fan around a vertex
//! exactly one. A ray crossing a closed mesh through an edge is therefore counted once, which keeps `count`
//! queries' inside/outside parity exact; a ray grazing a silhouette edge is counted 0 or 2 times.
//!
//! **Facing.** The front face is the side that the geometric normal `(v1−v0)×(v2−v0)` points to (counter-
//! clockwise vertices seen from the ray's side, as in OptiX). The ray sees the back face when
//! `dot(direction, normal) > 0`, which is `det < 0` here.
//!
//! **Range.** A hit is reported at `t` when `tmin ≤ t ≤ tmax`, both ends inclusive; the caller compares.
//!
//! **Magnitudes.** Everything is computed in f32 (the edge functions again in f64 when one is 0). Where the edge
//! functions or `t` overflow (a triangle's extent squared times its distance from the ray origin beyond about
//! 1e38, such as a triangle 1e13 across 5e12 away; extents beyond about 1e19; a `t` beyond f32's range) or the edge functions underflow to 0 (a triangle less than about 1e-19 across), the triangle is missed:
//! never reported at an infinite or NaN `t`.

use glam::Vec3;

use super::PreparedRay;

/// An intersection of a ray with one triangle, before range and culling checks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangleHit {
    /// Distance along the ray.
    pub t: f32,
    /// Barycentric weight of v1.
    pub u: f32,
    /// Barycentric weight of v2.
    pub v: f32,
    /// Whether the ray sees the back face.
    pub back_face: bool,
}

impl TriangleHit {
    /// The hit at `t` of a triangle whose edge functions are `u`, `v`, `w` with sum `det`: `v / det` and `w / det`
    /// are the barycentric weights of v1 and v2, and the ray sees the back face where `det < 0`.
    #[inline(always)]
    pub fn from_edges(t: f32, det: f32, v: f32, w: f32) -> TriangleHit {
        TriangleHit { t, u: v / det, v: w / det, back_face: det < 0.0 }
    }
}

/// The sign that an edge function which is exactly 0 takes once the ray is moved by the infinitesimal offset
/// `(δ, δ²)` in the projection plane. For the function `cross2(p, q)` of the edge from `p` to `q` the derivative
/// along that offset is `-(q−p).y` first, then `(q−p).x`.
#[inline]
fn perturbed_sign(p: (f32, f32), q: (f32, f32)) -> f32 {
    let (ex, ey) = (q.0 - p.0, q.1 - p.1);
    if ey != 0.0 {
        -ey.signum()
    } else if ex != 0.0 {
        ex.signum()
    } else {
        0.0
    }
}

/// A triangle in the ray's sheared space: its corners relative to the origin along the ray's axis (`az`, `bz`,
/// `cz`), projected onto the plane across the ray (`ax` … `cy`), and the edge functions `u`, `v`, `w` computed in f32.
struct Projected {
    az: f32,
    bz: f32,
    cz: f32,
    ax: f32,
    ay: f32,
    bx: f32,
    by: f32,
    cx: f32,
    cy: f32,
    u: f32,
    v: f32,
    w: f32,
}

impl Projected {
    /// Translates, permutes and shears `corners` into the ray's space.
    #[inline(always)]
    fn new(ray: &PreparedRay, corners: &[Vec3; 3]) -> Projected {
        let (kx, ky, kz) = (ray.kx, ray.ky, ray.kz);
        let o = ray.origin;
        let a = (glam::Vec3A::from(corners[0]) - o).to_array();
        let b = (glam::Vec3A::from(corners[1]) - o).to_array();
        let c = (glam::Vec3A::from(corners[2]) - o).to_array();
        let (sx, sy) = (ray.shear.x, ray.shear.y);
        let (az, bz, cz) = (a[kz], b[kz], c[kz]);
        let ax = a[kx] - sx * az;
        let ay = a[ky] - sy * az;
        let bx = b[kx] - sx * bz;
        let by = b[ky] - sy * bz;
        let cx = c[kx] - sx * cz;
        let cy = c[ky] - sy * cz;
        let u = cx * by - cy * bx;
        let v = ax * cy - ay * cx;
        let w = bx * ay - by * ax;
        Projected { az, bz, cz, ax, ay, bx, by, cx, cy, u, v, w }
    }
}

/// Whether [`intersect`] may find a hit: false only when its f32 edge functions are all nonzero and of mixed
/// signs, where it returns `None` without more work. Computed without branches, so that a leaf's triangles can be
/// filtered before any is intersected (the rejections, about half of the tests and unpredictable, cost a
/// mispredicted branch each when taken one at a time).
#[inline(always)]
pub fn may_hit(ray: &PreparedRay, corners: &[Vec3; 3]) -> bool {
    let Projected { u, v, w, .. } = Projected::new(ray, corners);
    let zero = (u == 0.0) | (v == 0.0) | (w == 0.0);
    let mixed = ((u < 0.0) | (v < 0.0) | (w < 0.0)) & ((u > 0.0) | (v > 0.0) | (w > 0.0));
    zero | !mixed
}

/// Intersects `ray` with the triangle `corners`; `None` when the ray's line misses it (or it is edge-on).
#[inline(always)]
pub fn intersect(ray: &PreparedRay, corners: &[Vec3; 3]) -> Option<TriangleHit> {
    let Projected { az, bz, cz, ax, ay, bx, by, cx, cy, mut u, mut v, mut w } = Projected::new(ray, corners);
    if u == 0.0 || v == 0.0 || w == 0.0 {
        let (ax, ay, bx, by, cx, cy) = (ax as f64, ay as f64, bx as f64, by as f64, cx as f64, cy as f64);
        u = (cx * by - cy * bx) as f32;
        v = (ax * cy - ay * cx) as f32;
        w = (bx * ay - by * ax) as f32;
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    if u == 0.0 || v == 0.0 || w == 0.0 {
        let s = det.signum();
        let on_edge_inside = |f: f32, p, q| f != 0.0 || s * perturbed_sign(p, q) > 0.0;
        let inside = on_edge_inside(u, (cx, cy), (bx, by))
            && on_edge_inside(v, (ax, ay), (cx, cy))
            && on_edge_inside(w, (bx, by), (ax, ay));
        if !inside {
            return None;
        }
    }
    let sz = ray.shear.z;
    let (az, bz, cz) = (sz * az, sz * bz, sz * cz);
    let t = (u * az + v * bz + w * cz) / det;
    if !t.is_finite() {
        return None;
    }
    Some(TriangleHit::from_edges(t, det, v, w))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::{Ray, RayFlags};
    use glam::Vec3A;

    fn prepared(origin: Vec3A, direction: Vec3A) -> PreparedRay {
        PreparedRay::new(&Ray { origin, direction, ..Ray::default() }, RayFlags::empty())
    }

    #[test]
    fn hit_reports_distance_barycentrics_and_facing() {
        let tri = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0)];
        // The normal is +z; a ray travelling -z sees the front face.
        let hit = intersect(&prepared(Vec3A::new(0.25, 0.5, 2.0), -Vec3A::Z), &tri).unwrap();
        assert_eq!(hit.t, 2.0);
        assert!((hit.u - 0.25).abs() < 1e-6 && (hit.v - 0.5).abs() < 1e-6);
        assert!(!hit.back_face);
        let hit = intersect(&prepared(Vec3A::new(0.25, 0.5, -3.0), Vec3A::Z * 2.0), &tri).unwrap();
        assert_eq!(hit.t, 1.5);
        assert!(hit.back_face);
        assert!(intersect(&prepared(Vec3A::new(0.75, 0.75, 2.0), -Vec3A::Z), &tri).is_none());
    }

    #[test]
    fn facing_matches_the_sign_of_direction_dot_normal_on_every_axis() {
        let tri = [Vec3::new(0.1, 0.2, 0.3), Vec3::new(1.1, -0.2, 0.4), Vec3::new(0.3, 0.9, -0.5)];
        let normal = Vec3A::from((tri[1] - tri[0]).cross(tri[2] - tri[0]));
        let centre = Vec3A::from((tri[0] + tri[1] + tri[2]) / 3.0);
        for direction in [Vec3A::X, -Vec3A::X, Vec3A::Y, -Vec3A::Y, Vec3A::Z, -Vec3A::Z, Vec3A::new(0.3, -0.2, 0.9)] {
            let hit = intersect(&prepared(centre - direction * 5.0, direction), &tri);
            let Some(hit) = hit else { continue };
            assert_eq!(hit.back_face, direction.dot(normal) > 0.0, "direction {direction}");
            assert!((hit.t - 5.0).abs() < 1e-5);
        }
    }

    #[test]
    fn may_hit_rules_out_only_triangles_that_intersect_misses() {
        // Rays through a grid of points over triangles of a small lattice (so many rays meet edges and vertices
        // exactly), from several directions.
        let corner = |i: i32, j: i32| Vec3::new(i as f32 * 0.5, j as f32 * 0.5, ((i * 7 + j * 3) % 5) as f32 * 0.1);
        let triangles: Vec<[Vec3; 3]> = (0..4)
            .flat_map(|i| {
                (0..4).flat_map(move |j| {
                    [
                        [corner(i, j), corner(i + 1, j), corner(i + 1, j + 1)],
                        [corner(i, j), corner(i + 1, j + 1), corner(i, j + 1)],
                    ]
                })
            })
            .collect();
        let (mut ruled_out, mut hits) = (0, 0);
        for direction in [-Vec3A::Z, Vec3A::new(0.2, -0.1, -1.0), Vec3A::new(-1.0, 0.3, 0.1), Vec3A::new(0.0, 1.0, 0.0)]
        {
            for x in 0..=16 {
                for y in 0..=16 {
                    let point = Vec3A::new(x as f32 * 0.125, y as f32 * 0.125, 0.2);
                    let ray = prepared(point - direction * 3.0, direction);
                    for triangle in &triangles {
                        let hit = intersect(&ray, triangle);
                        if !may_hit(&ray, triangle) {
                            assert!(hit.is_none(), "ruled out but hit: {point} {direction} {triangle:?}");
                            ruled_out += 1;
                        }
                        hits += usize::from(hit.is_some());
                    }
                }
            }
        }
        assert!(ruled_out > hits && hits > 0, "{ruled_out} ruled out, {hits} hits");
    }

    #[test]
    fn a_ray_through_a_shared_edge_or_vertex_hits_exactly_one_triangle() {
        // A square split along its diagonal, and a fan of six triangles around the origin.
        let square = [
            [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 0.0)],
            [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)],
        ];
        let fan: Vec<[Vec3; 3]> = (0..6)
            .map(|i| {
                let angle = |k: i32| std::f32::consts::TAU * (k % 6) as f32 / 6.0;
                let p = |k| Vec3::new(angle(k).cos(), angle(k).sin(), 0.0);
                [Vec3::ZERO, p(i), p(i + 1)]
            })
            .collect();
        for direction in [-Vec3A::Z, Vec3A::Z, Vec3A::new(0.1, -0.3, -1.0), Vec3A::new(-0.7, 0.2, 1.0)] {
            for point in [Vec3A::new(0.5, 0.5, 0.0), Vec3A::new(0.25, 0.25, 0.0)] {
                let ray = prepared(point - direction * 3.0, direction);
                let hits = square.iter().filter(|t| intersect(&ray, t).is_some()).count();
                assert_eq!(hits, 1, "square diagonal at {point}, direction {direction}");
            }
            let ray = prepared(-direction * 3.0, direction);
            assert_eq!(fan.iter().filter(|t| intersect(&ray, t).is_some()).count(), 1, "fan, direction {direction}");
        }
    }
}
