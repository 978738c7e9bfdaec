//! The wide nodes of a motion BVH (a moving geometry accel's or a motion instance accel's): its binary nodes collapsed
//! as a static instance accel's are ([`WideTree`], each leaf lane holding its binary leaf's slots), with each node's
//! lanes' boxes at every motion key, which a walk interpolates at the ray's time, eight lanes at once, as the binary
//! walk interpolates a node's box ([`NodeKeys::at`]).

use super::bvh::{Footprint, Node, NodeKeys, VecLen};
use super::collapse::Lane;
use super::wide::{Tree, WIDTH, WideNode, WideTree, occupied};
use crate::geometry::motion::KeyTime;

/// A motion BVH collapsed to [`WIDTH`] children a node, with its lanes' boxes at each key.
#[derive(Debug, Clone, Default)]
pub(super) struct MovingWideTree {
    /// The nodes, with each lane's box over all of time (read for its index and count).
    tree: WideTree,
    /// Motion keys (at least 2 where there are nodes).
    keys: usize,
    /// Node `n`'s lanes' boxes at key `k` in `lo` and `hi` of entry `n·keys + k` (their `index` and `count` unused).
    key_boxes: Vec<WideNode>,
}

impl MovingWideTree {
    /// Collapses the depth-first binary motion BVH `binary`, whose boxes at each key `node_keys` holds.
    pub fn collapse(binary: &[Node], node_keys: &NodeKeys) -> MovingWideTree {
        let (tree, lanes) = WideTree::collapse_with_lanes(binary);
        let keys = node_keys.keys;
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
        MovingWideTree { tree, keys, key_boxes }
    }

    /// Its nodes as a walk reads them.
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
        let (tree, lanes) = WideTree::collapse_with_lanes(&bvh.nodes);
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
    }
}
