//! Collapsing a binary BVH into a wide one at the least surface-area cost: which binary inner nodes become wide nodes
//! (the others are opened, their children taking lanes of the wide node above) is chosen to make the summed surface
//! area of the wide nodes, what a ray's expected node visits are proportional to, as small as the width allows (the
//! leaves stay as they are, so their cost does not change). The CPU's 8-wide nodes ([`super::wide`]) and the wgpu
//! backend's 4-wide ones are both made from this.

use super::bvh::Node;

/// A lane no binary node is in.
pub(crate) const EMPTY_LANE: u32 = u32::MAX;

/// One lane of a wide node.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Lane {
    /// The binary node in it, [`EMPTY_LANE`] when none.
    pub binary: u32,
    /// For an inner binary node: the wide node its subtree became; otherwise [`EMPTY_LANE`].
    pub child: u32,
}

/// A binary BVH collapsed to `width` lanes a node.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Collapsed {
    /// Lanes of the wide nodes, `width` a node, the root's first; a node's occupied lanes come before its empty
    /// ones. Empty when the binary BVH was.
    pub lanes: Vec<Lane>,
    /// Longest root-to-leaf path, in wide nodes.
    pub depth: usize,
    /// Entries a nearest-first walk's stack holds at most: over root-to-leaf paths, the sum of each node's occupied
    /// lanes but one (the lanes it leaves waiting).
    pub stack_need: usize,
}

/// Collapses a depth-first binary BVH into nodes of `width` (≥ 2) lanes, at the least summed surface area of its wide
/// nodes ([`Plan`]), each node's lanes in the order [`Plan::open`] gives them. A binary root that is a leaf becomes the
/// one lane of the one wide node.
pub(crate) fn collapse(binary: &[Node], width: usize) -> Collapsed {
    assert!(width >= 2, "a wide node has at least two lanes");
    if binary.is_empty() {
        return Collapsed::default();
    }
    let plan = Plan::new(binary, width);
    let empty = Lane { binary: EMPTY_LANE, child: EMPTY_LANE };
    let mut collapsed =
        Collapsed { lanes: Vec::with_capacity((binary.len() / 2 + 1) * width), depth: 0, stack_need: 0 };
    collapsed.lanes.resize(width, empty);
    // (binary node whose subtree a wide node holds, that wide node, its level, lanes left waiting above it)
    let mut pending = vec![(0usize, 0usize, 1usize, 0usize)];
    let mut lanes = Vec::with_capacity(width);
    while let Some((source, target, level, waiting)) = pending.pop() {
        collapsed.depth = collapsed.depth.max(level);
        lanes.clear();
        if binary[source].count > 0 {
            lanes.push(source);
        } else {
            plan.open(source, &mut lanes);
        }
        let waiting = waiting + lanes.len() - 1;
        collapsed.stack_need = collapsed.stack_need.max(waiting);
        for (lane, &n) in lanes.iter().enumerate() {
            let child = if binary[n].count > 0 {
                EMPTY_LANE
            } else {
                let child = collapsed.lanes.len() / width;
                collapsed.lanes.extend(std::iter::repeat_n(empty, width));
                pending.push((n, child, level + 1, waiting));
                child as u32
            };
            collapsed.lanes[target * width + lane] = Lane { binary: n as u32, child };
        }
    }
    collapsed
}

/// The most wide nodes of `width` lanes that [`collapse`] makes of a binary BVH of `leaves` leaves, which the memory
/// bounds count on: `width / 2` for every `width − 1` leaves, and one more. That many would follow if every wide node
/// with an inner lane had all `width` lanes (its lanes being the wide nodes below it and its leaves), which the
/// least-area collapse does not promise: it leaves a lane empty where opening an inner lane would add more area than
/// it saves. Random trees (boxes of every shape, splits at random, in the middle and at one end) of up to 300 leaves,
/// and trees grown to the most nodes by a search that changed their boxes and splits one at a time, never came above
/// 9/16 of their leaves in 8-wide nodes (the bound is 4/7); the tests check the bound on random trees of those kinds.
pub(crate) const fn most_nodes(leaves: usize, width: usize) -> usize {
    (width / 2 * leaves).div_ceil(width - 1) + 1
}

/// For every binary node and every number of lanes up to the width, the cheapest way to lay its subtree out in that
/// many lanes of a wide node, found bottom-up (children come after their parents): as one lane (a leaf, or an inner
/// node that becomes a wide node of its own, costing its surface area and its children's spread over a whole node),
/// or with its children spread over the lanes, some to the left child and the rest to the right.
struct Plan<'a> {
    /// The binary BVH.
    binary: &'a [Node],
    /// Lanes a wide node has.
    width: usize,
    /// `cost[n·width + i − 1]`: the least summed surface area of the wide nodes below and at node `n` laid out in at
    /// most `i` lanes.
    cost: Vec<f32>,
    /// `left[n·width + i − 1]`: for `i` ≥ 2, how many of the `i` lanes node `n`'s left child takes where node `n` is
    /// spread over them; 0 where it takes one lane instead.
    left: Vec<u8>,
}

impl<'a> Plan<'a> {
    /// The plan of `binary` for nodes of `width` lanes.
    fn new(binary: &'a [Node], width: usize) -> Plan<'a> {
        let mut plan =
            Plan { binary, width, cost: vec![0.0; binary.len() * width], left: vec![0; binary.len() * width] };
        // A leaf takes one lane, whatever it is offered, and no wide node: its costs stay 0.
        for n in (0..binary.len()).rev().filter(|&n| binary[n].count == 0) {
            let own_node = plan.area(n) + plan.best_spread(n, width).0;
            plan.cost[n * width] = own_node;
            for i in 2..=width {
                let (spread, k) = plan.best_spread(n, i);
                // Ties go to spreading: the same cost with one wide node fewer.
                let at = n * width + i - 1;
                (plan.cost[at], plan.left[at]) = if spread <= own_node { (spread, k as u8) } else { (own_node, 0) };
            }
        }
        plan
    }

    /// The cheapest spread of inner node `n`'s children over at most `i` (≥ 2) lanes: its cost, and the lanes its
    /// left child takes.
    fn best_spread(&self, n: usize, i: usize) -> (f32, usize) {
        let (l, r) = (self.binary[n].index as usize * self.width, (self.binary[n].index as usize + 1) * self.width);
        let (left, right) = (&self.cost[l..l + i - 1], &self.cost[r..r + i - 1]);
        // The first of the cheapest, in a loop the compiler keeps free of bounds checks.
        let mut best = (left[0] + right[i - 2], 1);
        for (k, (&to_left, &to_right)) in left.iter().zip(right.iter().rev()).enumerate().skip(1) {
            if to_left + to_right < best.0 {
                best = (to_left + to_right, k + 1);
            }
        }
        best
    }

    /// Fills `lanes` with the lanes of inner node `n`'s wide node as the plan lays them out. They are opened in the
    /// order a greedy collapse would open them, the largest in surface area first, each opened node's place taken by
    /// the last lane and its children appended: the lane order the GPU's any-hit walk follows, which the greedy
    /// collapse made good for occlusion (a large leaf near the root, such as a floor, keeps an early lane). The CPU's
    /// wide nodes rank their lanes again, by their chance of stopping a ray for its cost ([`super::occlusion`]).
    fn open(&self, n: usize, lanes: &mut Vec<usize>) {
        // Each lane with the lanes it may take.
        let mut budgets: Vec<(usize, usize)> = self.split(n, self.width).to_vec();
        let spreads = |(n, i): (usize, usize)| i >= 2 && self.left[n * self.width + i - 1] != 0;
        while let Some(at) = (0..budgets.len())
            .filter(|&at| spreads(budgets[at]))
            .max_by(|&a, &b| self.area(budgets[a].0).total_cmp(&self.area(budgets[b].0)))
        {
            let (n, i) = budgets.swap_remove(at);
            budgets.extend(self.split(n, i));
        }
        lanes.extend(budgets.iter().map(|&(n, _)| n));
    }

    /// Inner node `n`'s children with the lanes each takes where the node is spread over at most `i` (≥ 2) lanes.
    fn split(&self, n: usize, i: usize) -> [(usize, usize); 2] {
        let (l, r) = (self.binary[n].index as usize, self.binary[n].index as usize + 1);
        let k = match self.left[n * self.width + i - 1] {
            0 => self.best_spread(n, i).1,
            k => usize::from(k),
        };
        [(l, k), (r, i - k)]
    }

    /// Node `n`'s surface area (half of it).
    fn area(&self, n: usize) -> f32 {
        self.binary[n].half_area()
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;

    /// A complete depth-first binary tree of `leaves` (a power of two) unit-box leaves along x.
    fn complete(leaves: u32) -> Vec<Node> {
        fn build(binary: &mut Vec<Node>, at: usize, first: u32, leaves: u32) {
            if leaves == 1 {
                let x = first as f32;
                binary[at] =
                    Node { min: Vec3::new(x, 0.0, 0.0), index: first, max: Vec3::new(x + 1.0, 1.0, 1.0), count: 1 };
                return;
            }
            let child = binary.len();
            binary.push(binary[at]);
            binary.push(binary[at]);
            build(binary, child, first, leaves / 2);
            build(binary, child + 1, first + leaves / 2, leaves / 2);
            let (l, r) = (binary[child], binary[child + 1]);
            binary[at] = Node { min: l.min.min(r.min), index: child as u32, max: l.max.max(r.max), count: 0 };
        }
        let mut binary = vec![Node { min: Vec3::ZERO, index: 0, max: Vec3::ZERO, count: 0 }];
        build(&mut binary, 0, 0, leaves);
        binary
    }

    #[test]
    fn every_leaf_lands_in_one_lane_and_inner_lanes_name_their_wide_node() {
        let binary = complete(16);
        for (width, depth) in [(2, 4), (4, 2), (8, 2)] {
            let collapsed = collapse(&binary, width);
            assert_eq!(collapsed.depth, depth, "width {width}");
            // A complete tree: every node on a path is full but the last level's.
            let full_levels = (collapsed.lanes.len() / width).min(depth);
            assert!(collapsed.stack_need <= full_levels * (width - 1), "width {width}");
            assert!(collapsed.stack_need >= width - 1, "width {width}: the root leaves its other lanes waiting");
            let mut leaves = Vec::new();
            for node in collapsed.lanes.chunks(width) {
                let occupied = node.iter().take_while(|l| l.binary != EMPTY_LANE).count();
                assert!(node[occupied..].iter().all(|l| l.binary == EMPTY_LANE), "empty lanes come last");
                for lane in &node[..occupied] {
                    let binary_node = binary[lane.binary as usize];
                    if binary_node.count > 0 {
                        assert_eq!(lane.child, EMPTY_LANE);
                        leaves.push(binary_node.index);
                    } else {
                        // The wide node it became starts with one of its descendants.
                        let first = collapsed.lanes[lane.child as usize * width];
                        assert!(first.binary > lane.binary);
                    }
                }
            }
            leaves.sort();
            assert_eq!(leaves, (0..16).collect::<Vec<_>>(), "width {width}");
            assert!(collapsed.lanes[..width].iter().all(|l| l.binary != EMPTY_LANE), "the root is filled");
        }
    }

    /// A depth-first binary BVH over `boxes` (each a leaf of one primitive), split at the points `splits` picks
    /// (given a range of two boxes or more, a point strictly inside it).
    fn tree(boxes: &[(Vec3, Vec3)], splits: &mut impl FnMut(usize, usize) -> usize) -> Vec<Node> {
        fn build(
            binary: &mut Vec<Node>,
            at: usize,
            leaves: std::ops::Range<usize>,
            boxes: &[(Vec3, Vec3)],
            splits: &mut impl FnMut(usize, usize) -> usize,
        ) {
            if leaves.len() == 1 {
                let (min, max) = boxes[leaves.start];
                binary[at] = Node { min, index: leaves.start as u32, max, count: 1 };
                return;
            }
            let split = splits(leaves.start, leaves.end);
            let child = binary.len();
            binary.extend([binary[at]; 2]);
            build(binary, child, leaves.start..split, boxes, splits);
            build(binary, child + 1, split..leaves.end, boxes, splits);
            let (l, r) = (binary[child], binary[child + 1]);
            binary[at] = Node { min: l.min.min(r.min), index: child as u32, max: l.max.max(r.max), count: 0 };
        }
        let mut binary = vec![Node { min: Vec3::ZERO, index: 0, max: Vec3::ZERO, count: 0 }];
        build(&mut binary, 0, 0..boxes.len(), boxes, splits);
        binary
    }

    /// Half the surface area of binary node `n`'s box.
    fn area(binary: &[Node], n: usize) -> f32 {
        binary[n].half_area()
    }

    /// The least summed area of wide nodes over every way to collapse `binary` into nodes of `width` lanes, by trying
    /// every set of inner nodes that could be wide nodes (the root always is one): a set is a collapse when each of its
    /// nodes' lanes (its descendants down to the next leaf or node of the set) number at most `width`.
    fn least_area_by_trying_all(binary: &[Node], width: usize) -> f32 {
        let inner: Vec<usize> = (1..binary.len()).filter(|&n| binary[n].count == 0).collect();
        assert!(inner.len() < 16, "{} inner nodes to try", inner.len());
        let lanes = |wide: &[bool], n: usize| {
            let mut count = 0;
            let mut open = vec![binary[n].index as usize, binary[n].index as usize + 1];
            while let Some(m) = open.pop() {
                match binary[m].count > 0 || wide[m] {
                    true => count += 1,
                    false => open.extend([binary[m].index as usize, binary[m].index as usize + 1]),
                }
            }
            count
        };
        (0..1u32 << inner.len())
            .filter_map(|set| {
                let mut wide = vec![false; binary.len()];
                wide[0] = true;
                for (bit, &n) in inner.iter().enumerate() {
                    wide[n] = set >> bit & 1 == 1;
                }
                let nodes: Vec<usize> = (0..binary.len()).filter(|&n| wide[n]).collect();
                nodes.iter().all(|&n| lanes(&wide, n) <= width).then(|| nodes.iter().map(|&n| area(binary, n)).sum())
            })
            .min_by(f32::total_cmp)
            .expect("the binary tree itself is a collapse")
    }

    /// Numbers below the one asked for, from a xorshift generator seeded with `seed` (not 0).
    fn below(mut seed: u64) -> impl FnMut(usize) -> usize {
        move |below| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed % below as u64) as usize
        }
    }

    #[test]
    fn the_wide_nodes_have_the_least_summed_area_of_every_collapse() {
        // Random trees of 6–13 leaves of random boxes, split at random points; narrow nodes, so that choices abound.
        let mut next = below(0x2545_f491_4f6c_dd1d);
        let mut better_than_greedy = 0;
        for _ in 0..60 {
            let leaves = 6 + next(8);
            let boxes: Vec<(Vec3, Vec3)> = (0..leaves)
                .map(|_| {
                    let min = Vec3::new(next(100) as f32, next(100) as f32, next(100) as f32);
                    (min, min + Vec3::new(1.0 + next(40) as f32, 1.0 + next(40) as f32, 1.0 + next(40) as f32))
                })
                .collect();
            let binary = tree(&boxes, &mut |start, end| start + 1 + next(end - start - 1));
            for width in [3, 4] {
                let collapsed = collapse(&binary, width);
                let wide_nodes = std::iter::once(0).chain(
                    collapsed.lanes.iter().filter(|lane| lane.child != EMPTY_LANE).map(|lane| lane.binary as usize),
                );
                let summed: f32 = wide_nodes.map(|n| area(&binary, n)).sum();
                let least = least_area_by_trying_all(&binary, width);
                assert!((summed - least).abs() <= least * 1e-5, "width {width}: {summed} against the least {least}");
                better_than_greedy += usize::from(summed < greedy_area(&binary, width) * (1.0 - 1e-5));
            }
        }
        assert!(better_than_greedy > 0, "no tree where opening the largest node first is not the best");
    }

    #[test]
    fn the_wide_nodes_number_at_most_the_bound() {
        // Trees of 2–300 leaves: boxes at random, long thin boxes along random axes (the kind that came nearest the
        // bound), and boxes nested in one another; split at random points, in the middle and after the first leaf.
        let mut next = below(0x9e37_79b9_7f4a_7c15);
        let mut starved = 0;
        for trial in 0..600 {
            let leaves = 2 + next(if trial % 2 == 0 { 40 } else { 300 });
            let boxes: Vec<(Vec3, Vec3)> = (0..leaves)
                .map(|i| {
                    let min = Vec3::new(next(100) as f32, next(100) as f32, next(100) as f32);
                    let mut size = Vec3::new(1.0 + next(50) as f32, 1.0 + next(50) as f32, 1.0 + next(50) as f32);
                    match trial % 3 {
                        0 => (min, min + size),
                        1 => {
                            size[next(3)] = 100.0 + next(2000) as f32;
                            (min, min + size)
                        }
                        _ => (Vec3::ZERO, Vec3::splat(1.0 + i as f32)),
                    }
                })
                .collect();
            let kind = next(3);
            let binary = tree(&boxes, &mut |start, end| match kind {
                0 => start + 1 + next(end - start - 1),
                1 => (start + end) / 2,
                _ => start + 1,
            });
            for width in [4, 8] {
                let collapsed = collapse(&binary, width);
                let nodes = collapsed.lanes.len() / width;
                assert!(nodes <= most_nodes(leaves, width), "{leaves} leaves, width {width}: {nodes} nodes");
                let has_room_and_an_inner_lane = |node: &[Lane]| {
                    node.iter().any(|lane| lane.binary == EMPTY_LANE)
                        && node.iter().any(|lane| lane.child != EMPTY_LANE)
                };
                starved += collapsed.lanes.chunks(width).filter(|node| has_room_and_an_inner_lane(node)).count();
            }
        }
        assert!(starved > 0, "no node with an empty lane above a wide node: the trees do not test the bound's doubt");
    }

    /// The summed area of the wide nodes that opening the inner lane of largest area first, while there is room, makes.
    fn greedy_area(binary: &[Node], width: usize) -> f32 {
        let mut pending = vec![0usize];
        let mut summed = 0.0;
        while let Some(n) = pending.pop() {
            summed += area(binary, n);
            let mut lanes = vec![binary[n].index as usize, binary[n].index as usize + 1];
            while lanes.len() < width {
                let widest = (0..lanes.len())
                    .filter(|&l| binary[lanes[l]].count == 0)
                    .max_by(|&a, &b| area(binary, lanes[a]).total_cmp(&area(binary, lanes[b])));
                let Some(lane) = widest else { break };
                let inner = lanes.swap_remove(lane);
                lanes.extend([binary[inner].index as usize, binary[inner].index as usize + 1]);
            }
            pending.extend(lanes.into_iter().filter(|&l| binary[l].count == 0));
        }
        summed
    }

    #[test]
    fn a_leaf_root_is_one_lane_and_nothing_is_empty() {
        let leaf = [Node { min: Vec3::ZERO, index: 0, max: Vec3::ONE, count: 3 }];
        let collapsed = collapse(&leaf, 4);
        assert_eq!(collapsed.lanes[0], Lane { binary: 0, child: EMPTY_LANE });
        assert!(collapsed.lanes[1..].iter().all(|l| l.binary == EMPTY_LANE));
        assert_eq!((collapsed.depth, collapsed.stack_need), (1, 0));
        assert_eq!(collapse(&[], 4), Collapsed::default());
    }
}
