//! The wide nodes of a motion BVH (a moving geometry accel's or a motion instance accel's): its binary nodes collapsed
//! into a [`WideTree`] (each leaf lane holding its binary leaf's slots) by their boxes' areas on average over time,
//! with each node's lanes' boxes at every motion key, which a walk interpolates at the ray's time, eight lanes at once,
//! as the binary walk interpolates a node's box ([`NodeKeys::at`]).

use super::bvh::{Footprint, Node, NodeKeys, VecLen};
use super::collapse::Lane;
use super::wide::{Tree, WIDTH, WideNode, WideTree, occupied};
use crate::geometry::motion::KeyTime;

/// A motion BVH collapsed to [`WIDTH`] children a node, with its lanes' boxes at each key.
#[derive(Debug, Clone, Default)]
pub(super) struct MovingWideTree {
    /// The nodes, with each lane's box holding its boxes at every time (read for its index and count, and by packet
    /// walks' tests that rule lanes out).
    tree: WideTree,
    /// Motion keys (at least 2 where there are nodes).
    keys: usize,
    /// Node `n`'s lanes' boxes at key `k` in `lo` and `hi` of entry `n·keys + k` (their `index` and `count` unused).
    key_boxes: Vec<WideNode>,
}

impl MovingWideTree {
    /// Collapses the depth-first binary motion BVH `binary`, whose boxes at each key `node_keys` holds: by the areas of
    /// the nodes' boxes on average over time ([`NodeKeys::time_averaged`]), as the binary tree was built.
    pub fn collapse(binary: &[Node], node_keys: &NodeKeys) -> MovingWideTree {
        let keys = node_keys.keys;
        let (mut tree, lanes) = WideTree::collapse_with_lanes(&node_keys.time_averaged(binary));
        let at_key = |lanes: &[Lane], key: usize| {
            let mut node = WideNode::EMPTY;
            for (lane, binary) in lanes[..occupied(lanes)].iter().enumerate() {
                let (min, max) = node_keys.boxes[binary.binary as usize * keys + key];
                node.set_box(lane, min, max);
            }
            node
        };
        let mut key_boxes = Vec::with_capacity(lanes.len() / WIDTH * keys);
        key_boxes.extend(lanes.chunks(WIDTH).flat_map(|lanes| (0..keys).map(move |key| at_key(lanes, key))));
        let children = lanes.chunks(WIDTH).map(occupied);
        for ((node, children), at_keys) in tree.nodes_mut().iter_mut().zip(children).zip(key_boxes.chunks(keys)) {
            for lane in 0..children {
                for axis in 0..3 {
                    let (lo, hi) = (at_keys.iter().map(|k| k.lo[axis][lane]), at_keys.iter().map(|k| k.hi[axis][lane]));
                    node.lo[axis][lane] = holding(lo, f32::min, -1.0);
                    node.hi[axis][lane] = holding(hi, f32::max, 1.0);
                }
            }
        }
        MovingWideTree { tree, keys, key_boxes }
    }

    /// Its nodes as a walk reads them: each lane's box holds the lane's boxes at every time
    /// ([`MovingWideTree::collapse`]), for tests that rule lanes out; walks that enter lanes test
    /// [`MovingWideTree::boxes_at`].
    #[inline(always)]
    pub fn tree(&self) -> Tree<'_> {
        self.tree.tree()
    }

    /// The boxes of node `node`'s lanes at `at`, in `lo` and `hi`: each lane's two key boxes interpolated with the
    /// operations of [`NodeKeys::at`] (so the same box as the binary node in the lane has at that time).
    #[inline(always)]
    pub fn boxes_at(&self, node: usize, at: KeyTime) -> WideNode {
        let ((a, b), f) = (self.segment_boxes(node, at.segment), at.fraction);
        let lerp = |a: &[[f32; WIDTH]; 3], b: &[[f32; WIDTH]; 3]| {
            std::array::from_fn(|axis| std::array::from_fn(|lane| a[axis][lane] * (1.0 - f) + b[axis][lane] * f))
        };
        WideNode { lo: lerp(&a.lo, &b.lo), hi: lerp(&a.hi, &b.hi), ..WideNode::EMPTY }
    }

    /// Node `node`'s lanes' boxes at the two keys of segment `segment` (in `lo` and `hi`).
    #[inline(always)]
    pub fn segment_boxes(&self, node: usize, segment: usize) -> (&WideNode, &WideNode) {
        let first = node * self.keys + segment;
        (&self.key_boxes[first], &self.key_boxes[first + 1])
    }

    /// Stack entries a walk needs.
    pub fn stack_size(&self) -> usize {
        self.tree.stack_size()
    }

    /// Bytes it occupies.
    pub fn size_bytes(&self, footprint: Footprint) -> u64 {
        self.tree.size_bytes(footprint) + (footprint.of(&self.key_boxes as &dyn VecLen) * size_of::<WideNode>()) as u64
    }

    /// The most bytes the wide nodes of a motion BVH over `leaves` leaves with `keys` keys take.
    pub const fn most_bytes(leaves: u64, keys: u64) -> u64 {
        WideTree::most_nodes(leaves as usize) as u64 * ((1 + keys) * size_of::<WideNode>() as u64 + 1)
    }
}

/// Where a plane of a lane's box at every time lies at most: `bound` (`f32::min` for a minimum, `f32::max` for a
/// maximum) of its places `at_keys` at the keys, moved outward (`outward` −1 or 1) by 2⁻²⁰ of their largest magnitude.
/// The interpolation of two keys' planes rounds at most 2⁻²² of the larger magnitude away from the exact value (three
/// roundings of values no larger than it, and `1 − f`'s), which lies between them: the margin holds it four times.
pub(super) fn holding(at_keys: impl Iterator<Item = f32> + Clone, bound: fn(f32, f32) -> f32, outward: f32) -> f32 {
    const MARGIN: f32 = 1.0 / (1 << 20) as f32;
    let magnitude = at_keys.clone().fold(0.0, |most: f32, x| most.max(x.abs()));
    let plane = at_keys.reduce(bound).expect("a plane at every key");
    plane + outward * magnitude * MARGIN
}

#[cfg(test)]
mod tests {
    use glam::Vec3;

    use super::*;
    use crate::accel::BuildOptions;
    use crate::backend::cpu::CpuAccel;
    use crate::backend::cpu::instances::cpu_child;
    use crate::backend::cpu::packet::tests::lattice;
    use crate::geometry::{BuildInput, MotionFlags, MotionOptions, TriangleInput};
    use crate::{Context, Device};

    #[test]
    fn each_lanes_box_at_a_time_is_its_binary_nodes_box_then() {
        // The packet tests' lattice at three keys: as it is, moved, and each vertex scattered.
        let (_, mesh) = lattice(false);
        let bytes = |points: &[Vec3]| -> Vec<u8> {
            points.iter().flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect()
        };
        let moved: Vec<Vec3> = mesh.positions.iter().map(|&p| p + Vec3::new(0.3, -0.1, 0.2)).collect();
        let scattered: Vec<Vec3> = mesh
            .positions
            .iter()
            .enumerate()
            .map(|(i, &p)| p + 0.05 * Vec3::new((i % 7) as f32, (i % 3) as f32, (i % 5) as f32))
            .collect();
        let (moved, scattered) = (bytes(&moved), bytes(&scattered));
        let packed = mesh.pack();
        let motion_vertices = [&moved[..], &scattered[..]];
        let input = TriangleInput { motion_vertices: &motion_vertices, ..packed.input() };
        let motion = MotionOptions { keys: 3, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
        let context = Context::new(Device::cpu());
        let accel = context
            .build_accel(&[BuildInput::Triangles(input)], &BuildOptions { motion, ..BuildOptions::default() })
            .unwrap();
        let CpuAccel::Triangles(bvh) = cpu_child(&accel).unwrap() else { panic!("a geometry accel") };
        let keys = bvh.node_keys.as_ref().expect("a motion accel");
        let (tree, lanes) = WideTree::collapse_with_lanes(&keys.time_averaged(&bvh.nodes));
        assert!(tree.tree().nodes.len() > 10, "{} wide nodes", tree.tree().nodes.len());
        let mut compared = 0;
        for time in [0.0, 0.1, 0.37, 0.5, 0.5001, 0.9, 1.0] {
            let at = bvh.motion.locate(time).unwrap();
            for (node, lanes) in lanes.chunks(WIDTH).enumerate() {
                let boxes = bvh.moving.boxes_at(node, at);
                for (lane, binary) in lanes[..occupied(lanes)].iter().enumerate() {
                    let (min, max) = keys.at(binary.binary, at);
                    let lo = Vec3::from_array(std::array::from_fn(|axis| boxes.lo[axis][lane]));
                    let hi = Vec3::from_array(std::array::from_fn(|axis| boxes.hi[axis][lane]));
                    assert_eq!((lo, hi), (min.into(), max.into()), "node {node}, lane {lane}, time {time}");
                    compared += 1;
                }
            }
        }
        assert!(compared > 100, "{compared} lanes compared");
        // The nodes' own boxes hold each lane's box at every time (packets rule lanes out by them).
        for time in (0..=1000).map(|i| i as f32 / 1000.0) {
            let at = bvh.motion.locate(time).unwrap();
            for (node, wide) in bvh.moving.tree().nodes.iter().enumerate() {
                let boxes = bvh.moving.boxes_at(node, at);
                for (axis, lane) in
                    (0..3).flat_map(|axis| (0..occupied(&lanes[node * WIDTH..][..WIDTH])).map(move |l| (axis, l)))
                {
                    assert!(wide.lo[axis][lane] <= boxes.lo[axis][lane], "node {node} lane {lane} at {time}");
                    assert!(wide.hi[axis][lane] >= boxes.hi[axis][lane], "node {node} lane {lane} at {time}");
                }
            }
        }
    }

    /// A plane interpolated between two keys' places as a walk interpolates it ([`MovingWideTree::boxes_at`]).
    fn interpolated(a: f32, b: f32, f: f32) -> f32 {
        a * (1.0 - f) + b * f
    }

    fn coordinate() -> impl proptest::strategy::Strategy<Value = f32> {
        use proptest::prelude::*;
        prop_oneof![-1e6f32..1e6, -1.0f32..1.0, (-1e30f32..1e30), Just(0.0), Just(1.0), Just(-3.0e-7)]
    }

    proptest::proptest! {
        #[test]
        fn a_plane_interpolated_at_any_time_lies_within_what_holds_it(
            a in coordinate(),
            b in coordinate(),
            same in proptest::bool::ANY,
            f in 0.0f32..=1.0,
        ) {
            let b = if same { a } else { b };
            let planes = [a, b].into_iter();
            let (lowest, highest) = (holding(planes.clone(), f32::min, -1.0), holding(planes, f32::max, 1.0));
            let at = interpolated(a, b, f);
            proptest::prop_assert!(lowest <= at && at <= highest, "{a}, {b} at {f}: {at} outside {lowest} ..= {highest}");
        }
    }
}
