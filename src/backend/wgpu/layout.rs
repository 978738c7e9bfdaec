//! A geometry accel on the device: the CPU backend's arrays, copied once into four storage buffers (bind group 0
//! of the trace pipeline). Every value is a little-endian 32-bit word; `f32` is IEEE-754 binary32.
//!
//! - `nodes`: the depth-first BVH nodes, 32 bytes each, exactly [`Node`]:
//!   `0 min.xyz f32×3 | 12 index u32 | 16 max.xyz f32×3 | 28 count u32` (with motion, each box is the node's box
//!   over all of time). One zero node when the accel has none (`node_count` 0 tells the kernel).
//! - `node_boxes`: with motion, node `i`'s box at key `k` at byte `(i·keys + k)·24`:
//!   `0 min.xyz f32×3 | 12 max.xyz f32×3`. Static accels: one zero box, never read.
//! - `corners`: triangle slot `s`'s corners at key `k` at byte `(s·keys + k)·36`: `0 v0.xyz | 12 v1.xyz |
//!   24 v2.xyz`, f32 each (leaf order, then the never-traversed degenerate triangles, as on the host).
//! - `prims`: per slot, 16 bytes ([`Prim`]): `0 geom_id u32 | 4 prim_id u32 | 8 mask u32 (0 without masks) |
//!   12 geometry_flags u32`.

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

use super::device::Opened;
use super::kernel::STACK_SIZE;
use crate::backend::cpu::TriangleBvh;
use crate::backend::cpu::bvh::Node;
use crate::error::{Error, Result};

/// The ids and acceptance data of one triangle slot (`Prim` in `layout.wgsl`).
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
#[repr(C)]
struct Prim {
    /// Geometry id.
    geom_id: u32,
    /// Primitive id.
    prim_id: u32,
    /// Prime mask.
    mask: u32,
    /// Flags of the triangle's geometry.
    geometry_flags: u32,
}

/// An accel's buffers on the device.
#[derive(Debug)]
pub(super) struct GpuTriangles {
    /// Bind group 0 over the four buffers (which it keeps alive).
    pub bind_group: wgpu::BindGroup,
    /// Nodes in `nodes` (0 when no triangle can be hit).
    pub node_count: u32,
    /// Bytes of the four buffers.
    bytes: u64,
}

/// The words of `node`.
fn node_words(node: &Node) -> [u32; 8] {
    let (min, max) = (node.min.to_array().map(f32::to_bits), node.max.to_array().map(f32::to_bits));
    [min[0], min[1], min[2], node.index, max[0], max[1], max[2], node.count]
}

impl GpuTriangles {
    /// Uploads `bvh`'s arrays. FAILED_PRECONDITION if the BVH is deeper than the kernel's stack; RESOURCE_EXHAUSTED
    /// if an array exceeds what the adapter can bind.
    pub fn upload(opened: &Opened, bvh: &TriangleBvh) -> Result<GpuTriangles> {
        if bvh.depth > STACK_SIZE {
            return Err(Error::FailedPrecondition(format!(
                "the accel's BVH is {} levels deep; the wgpu kernel's stack holds {STACK_SIZE}",
                bvh.depth
            )));
        }
        let mut nodes: Vec<u32> = bvh.nodes.iter().flat_map(node_words).collect();
        let boxes: Vec<f32> = bvh.node_keys.as_ref().map_or(Vec::new(), |keys| {
            keys.boxes.iter().flat_map(|(min, max)| min.to_array().into_iter().chain(max.to_array())).collect()
        });
        let corners: Vec<f32> = bvh.corners.iter().flat_map(|c| c.iter().flat_map(|v| v.to_array())).collect();
        let prims: Vec<Prim> = bvh
            .refs
            .iter()
            .enumerate()
            .map(|(slot, r)| Prim {
                geom_id: r.geom_id,
                prim_id: r.prim_id,
                mask: bvh.masks.as_ref().map_or(0, |m| m[slot]),
                geometry_flags: bvh.geometry_flags[r.geom_id as usize].bits(),
            })
            .collect();
        if nodes.is_empty() {
            nodes.resize(8, 0);
        }
        let limit = opened.binding_limit(None);
        let mut bytes = 0;
        let mut buffer = |name: &str, contents: &[u8]| -> Result<wgpu::Buffer> {
            // Bindings must not be empty: an empty array gets one zero word.
            let contents = if contents.is_empty() { &[0u8; 16][..] } else { contents };
            if contents.len() as u64 > limit {
                return Err(Error::TooLarge {
                    what: "the accel's device arrays",
                    requested: contents.len() as u64,
                    limit,
                });
            }
            bytes += contents.len() as u64;
            Ok(opened.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(name),
                contents,
                usage: wgpu::BufferUsages::STORAGE,
            }))
        };
        let buffers = [
            buffer("rayd nodes", bytemuck::cast_slice(&nodes))?,
            buffer("rayd node boxes", bytemuck::cast_slice(&boxes))?,
            buffer("rayd corners", bytemuck::cast_slice(&corners))?,
            buffer("rayd prims", bytemuck::cast_slice(&prims))?,
        ];
        let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
            .iter()
            .enumerate()
            .map(|(binding, buffer)| wgpu::BindGroupEntry {
                binding: binding as u32,
                resource: buffer.as_entire_binding(),
            })
            .collect();
        let bind_group = opened.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("rayd accel"),
            layout: &opened.kernel.accel_layout,
            entries: &entries,
        });
        Ok(GpuTriangles { bind_group, node_count: bvh.nodes.len() as u32, bytes })
    }

    /// Bytes the accel occupies on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}
