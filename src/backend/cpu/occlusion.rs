//! The order in which a wide node's lanes are tried by rays that walk them in lane order (any-hit rays, and closest-hit
//! rays after their two nearest lanes): each subtree ranked by how likely it is to stop an any-hit ray that enters its
//! box, for what it costs. For independent trials that end at the first success, trying them by decreasing chance over
//! cost is the order of least expected cost; a ray only tries the lanes it enters, so the chance that counts is the
//! one given that the ray is inside the box.
//!
//! The chances are those of isotropic random lines (Cauchy's formula: such a line meets a convex body with a chance
//! proportional to its surface area, and a flat triangle of area `a` as a body of surface `2a`): inside a box of half
//! surface area `s`, a leaf's triangles of summed area `a` are met with a chance of `a / s`, capped at 1 (overlaps
//! ignored); an inner node is stopped by either child, each met with the chance of its box inside the parent's,
//! independently. The costs are the surface area heuristic's: a leaf costs a visit and a test a triangle, an inner
//! node a visit and its children's costs weighted by the chance of entering them. Measured in BENCHMARKS.md ("Lanes
//! ordered by the chance of stopping a ray").

use glam::Vec3;

use super::bvh::Node;

/// For every node of a depth-first binary BVH (children after their parents) over triangles whose slots hold
/// `corners`: the chance that its subtree stops an any-hit ray inside its box, over the subtree's expected cost. Lanes
/// are best tried by decreasing rank.
pub(super) fn stop_chance_per_cost(binary: &[Node], corners: &[[Vec3; 3]]) -> Vec<f32> {
    let mut chance = vec![0.0f32; binary.len()];
    let mut cost = vec![0.0f32; binary.len()];
    for n in (0..binary.len()).rev() {
        let node = &binary[n];
        let area = node.half_area().max(f32::MIN_POSITIVE);
        let slots = node.index as usize..(node.index + node.count) as usize;
        (chance[n], cost[n]) = if node.count > 0 {
            let triangles: f32 = corners[slots].iter().map(|[a, b, c]| 0.5 * (*b - *a).cross(*c - *a).length()).sum();
            ((triangles / area).min(1.0), 1.0 + node.count as f32)
        } else {
            let children = [slots.start, slots.start + 1];
            let entered = children.map(|child| binary[child].half_area() / area);
            let [left, right] = [0, 1].map(|i| (entered[i] * chance[children[i]]).min(1.0));
            let expected_cost = 1.0 + entered[0] * cost[children[0]] + entered[1] * cost[children[1]];
            (1.0 - (1.0 - left) * (1.0 - right), expected_cost)
        };
    }
    chance.iter().zip(&cost).map(|(chance, cost)| chance / cost).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(min: Vec3, max: Vec3, index: u32, count: u32) -> Node {
        Node { min, index, max, count }
    }

    /// A triangle spanning the unit square at height `z`, cut to `fraction` of its size along x.
    fn triangle(z: f32, fraction: f32) -> [Vec3; 3] {
        [Vec3::new(0.0, 0.0, z), Vec3::new(fraction, 0.0, z), Vec3::new(0.0, 1.0, z)]
    }

    #[test]
    fn a_leaf_ranks_by_its_triangles_area_in_its_box_over_its_cost() {
        let unit = node(Vec3::ZERO, Vec3::ONE, 0, 1);
        // Half surface 3, triangle area 0.5: chance 1/6 over cost 2.
        let rank = stop_chance_per_cost(&[unit], &[triangle(0.5, 1.0)])[0];
        assert!((rank - 1.0 / 12.0).abs() < 1e-6, "{rank}");
        // A flat box (half surface 1) with triangles of summed area 1: chance 1 (the cap), cost 3.
        let flat = node(Vec3::ZERO, Vec3::new(1.0, 1.0, 0.0), 0, 2);
        let rank = stop_chance_per_cost(&[flat], &[triangle(0.0, 1.0); 2])[0];
        assert!((rank - 1.0 / 3.0).abs() < 1e-6, "{rank}");
    }

    #[test]
    fn an_inner_node_combines_its_children_as_independent_chances() {
        // Two unit-cube leaves side by side in a 2×1×1 box (half surface 5; each child's, 3, entered with chance 3/5).
        let binary = [
            node(Vec3::ZERO, Vec3::new(2.0, 1.0, 1.0), 1, 0),
            node(Vec3::ZERO, Vec3::ONE, 0, 1),
            node(Vec3::X, Vec3::new(2.0, 1.0, 1.0), 1, 1),
        ];
        let ranks = stop_chance_per_cost(&binary, &[triangle(0.5, 1.0), triangle(0.5, 0.5)]);
        let (left, right) = (0.5 / 3.0, 0.25 / 3.0);
        let chance = 1.0 - (1.0 - 0.6 * left) * (1.0 - 0.6 * right);
        let cost = 1.0 + 0.6 * 2.0 + 0.6 * 2.0;
        assert!((ranks[0] - chance / cost).abs() < 1e-6, "{ranks:?}");
        // The leaf with the larger triangle ranks first; a sliver's leaf last.
        assert!(ranks[1] > ranks[2] && ranks[2] > stop_chance_per_cost(&binary, &[triangle(0.5, 1e-4); 2])[2]);
    }
}
