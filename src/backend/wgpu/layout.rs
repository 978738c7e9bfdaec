//! An accel on the device: its graph flattened ([`super::graph`]) into five storage buffers (bind group 0 of the
//! trace pipeline), uploaded once at build, update or load. Every value is a little-endian 32-bit word; `f32` is
//! IEEE-754 binary32. An instance accel or transform holds copies of everything below it (each distinct accel
//! once), so the kernel traverses the whole graph from its own buffers.
//!
//! - `nodes`: every BVH's nodes collapsed to [`NODE_WIDTH`] (4) lanes a node ([`collapse`]), the root first, 128
//!   bytes each, by field then lane: `0 lo.x f32×4 | 16 lo.y | 32 lo.z | 48 hi.x | 64 hi.y | 80 hi.z | 96 index u32×4
//!   | 112 count u32×4`. Lane `l` holds one child's box `lo .. hi` and what it is: an inner child (`count` 0, its
//!   node at `index` of this array), a geometry leaf (the triangle slots `index .. index + count` of `prims`), an
//!   instance leaf (the instances `index .. index + count` of its object, counted from its first record), or
//!   nothing (`index` `0xffffffff`; the occupied lanes come first). With motion each box is the child's box over
//!   all of time.
//! - `node_boxes`: with motion, lane `l` of node `i`'s box at key `k` at float
//!   `box_base + (((i − first)·4 + l)·keys + k)·6` of its object: `min.xyz, max.xyz` (zeros for an empty lane).
//!   One zero box when no BVH moves.
//! - `corners`: triangle slot `s`'s corners at key `k` from vector `corner_base + ((s − base)·keys + k)·3` of its
//!   object, 16 bytes a corner: `v0.xyz 0 | v1.xyz 0 | v2.xyz 0` (leaf order, then the never-traversed degenerate
//!   triangles; those held collapsed, as on the host).
//! - `prims`: per triangle slot, 16 bytes ([`Prim`]): `0 geom_id u32 | 4 prim_id u32 | 8 mask u32 (0 without
//!   masks) | 12 geometry_flags u32`.
//! - `graph`: words. An object (a BVH or transform, [`OBJECT_WORDS`] words at its offset): `0 kind` ([`ObjectKind`])
//!   `| 1 keys | 2 motion_flags | 3 time_begin f32 | 4 time_end f32 | 5 first | 6 node_count | 7 box_base | 8 base |
//!   9 corner_base`, where `first` is a BVH's root node (a transform's child object) and `base` a geometry accel's
//!   first triangle slot, an instance accel's first instance record or a transform's first key. An instance record
//!   ([`INSTANCE_WORDS`] words): `0 world_to_object f32×12` (columns: x axis, y axis, z axis, translation) `|
//!   12 instance_id | 13 mask | 14 flags | 15 child object`. Transform keys: a static transform's world-to-object
//!   map (12 floats, columns); a matrix motion transform's object-to-world map a key (12 floats, columns); an SRT
//!   motion transform's 16 floats a key (`sx a b sy c sz pvx pvy pvz qx qy qz qw tx ty tz`, unit quaternion).

use bytemuck::{Pod, Zeroable};
use wgpu::BufferUsages;

use super::device::Opened;
use super::graph;
use super::kernel::{STACK_SIZE, Variant};
use crate::backend::cpu::CpuAccel;
#[cfg(doc)]
use crate::backend::cpu::collapse::collapse;
use crate::error::{Error, Result};

/// The ids and acceptance data of one triangle slot (`Prim` in `layout.wgsl`).
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
#[repr(C)]
pub(super) struct Prim {
    /// Geometry id.
    pub geom_id: u32,
    /// Primitive id.
    pub prim_id: u32,
    /// Prime mask.
    pub mask: u32,
    /// Flags of the triangle's geometry.
    pub geometry_flags: u32,
}

/// Lanes of a device node (`NODE_WIDTH` in `layout.wgsl`).
pub(super) const NODE_WIDTH: usize = 4;
/// Words of a device node: six box coordinates, an index and a count a lane.
pub(super) const NODE_WORDS: usize = 8 * NODE_WIDTH;

/// Words of an object record in `graph` (`OBJECT_WORDS` in `layout.wgsl`).
pub(super) const OBJECT_WORDS: usize = 10;
/// Words of an instance record in `graph` (`INSTANCE_WORDS` in `layout.wgsl`).
pub(super) const INSTANCE_WORDS: usize = 16;

/// What an object is (`OBJECT_*` in `layout.wgsl`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum ObjectKind {
    /// A geometry accel's BVH.
    Triangles = 0,
    /// An instance accel's BVH.
    Instances = 1,
    /// A static transform.
    StaticTransform = 2,
    /// A matrix motion transform.
    MatrixTransform = 3,
    /// An SRT motion transform.
    SrtTransform = 4,
}

/// One of an accel's five arrays on the device, each in one storage binding.
#[derive(Debug, Clone, Copy)]
pub(super) struct DeviceArray {
    /// Its buffer's label.
    label: &'static str,
    /// What it holds, and that it must fit a binding, as errors name it.
    what: &'static str,
}

impl DeviceArray {
    const NODES: DeviceArray = DeviceArray {
        label: "rayd nodes",
        what: "the accel's BVH nodes on the device (in one storage binding of the adapter)",
    };
    const NODE_BOXES: DeviceArray = DeviceArray {
        label: "rayd node boxes",
        what: "the accel's motion node boxes on the device (in one storage binding of the adapter)",
    };
    /// Triangle corners: 48 bytes a triangle a motion key.
    pub(super) const CORNERS: DeviceArray = DeviceArray {
        label: "rayd corners",
        what: "the accel's triangle corners on the device (48 bytes a triangle a motion key, in one storage binding \
               of the adapter)",
    };
    const PRIMS: DeviceArray = DeviceArray {
        label: "rayd prims",
        what: "the accel's triangle ids on the device (in one storage binding of the adapter)",
    };
    const GRAPH: DeviceArray = DeviceArray {
        label: "rayd graph",
        what: "the accel's objects, instances and transform keys on the device (in one storage binding of the \
               adapter)",
    };

    /// Bytes of the corners of `triangles` triangles at `keys` motion keys.
    pub(super) fn corner_bytes(triangles: u64, keys: u64) -> u64 {
        triangles.saturating_mul(keys.max(1)).saturating_mul(3 * size_of::<[f32; 4]>() as u64)
    }

    /// RESOURCE_EXHAUSTED naming the array and the adapter's binding limit, `limit`, if `bytes` of it cannot be
    /// bound.
    pub(super) fn check_fits(self, limit: u64, bytes: u64) -> Result<()> {
        if bytes > limit {
            return Err(Error::TooLarge { what: self.what, unit: "bytes", requested: bytes, limit });
        }
        Ok(())
    }
}

/// An accel's buffers on the device.
#[derive(Debug)]
pub(super) struct GpuGraph {
    /// Bind group 0 over the five buffers (which it keeps alive).
    pub bind_group: wgpu::BindGroup,
    /// The root object's offset in `graph`.
    pub root: u32,
    /// The trace pipeline it needs.
    pub variant: Variant,
    /// Bytes of the five buffers.
    bytes: u64,
    /// The [`Opened::generation`] of the device it is on.
    pub generation: u64,
}

impl GpuGraph {
    /// Flattens and uploads the graph under `host`. FAILED_PRECONDITION if a ray through it could need more stack
    /// than the kernel's; RESOURCE_EXHAUSTED if an array exceeds what the adapter can bind or the device has no
    /// memory left for it.
    pub fn upload(opened: &Opened, host: &CpuAccel) -> Result<GpuGraph> {
        let flat = graph::flatten(host)?;
        if flat.stack > STACK_SIZE {
            return Err(Error::FailedPrecondition(format!(
                "a ray through the accel's BVHs and instance levels needs {} stack entries; the wgpu kernel's stack \
                 holds {STACK_SIZE}",
                flat.stack
            )));
        }
        let mut bytes = 0;
        let mut buffer = |array: DeviceArray, contents: &[u8]| -> Result<wgpu::Buffer> {
            // Bindings must not be empty: an empty array gets zero words.
            let contents = if contents.is_empty() { &[0u8; 32][..] } else { contents };
            array.check_fits(opened.binding_limit(None), contents.len() as u64)?;
            bytes += contents.len() as u64;
            let size = (contents.len() as u64).next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT);
            let descriptor = wgpu::BufferDescriptor {
                label: Some(array.label),
                size,
                usage: BufferUsages::STORAGE,
                mapped_at_creation: true,
            };
            // Made under the scope, filled after it: a buffer the device had no memory for cannot be mapped.
            let made = opened.checked("uploading an accel", || opened.device.create_buffer(&descriptor))?;
            let mut mapped = made.get_mapped_range_mut(..).map_err(|e| {
                opened.or_lost(Error::FailedPrecondition(format!("mapping the accel's {} failed: {e}", array.label)))
            })?;
            mapped.slice(..contents.len()).copy_from_slice(contents);
            drop(mapped);
            made.unmap();
            Ok(made)
        };
        let buffers = [
            buffer(DeviceArray::NODES, bytemuck::cast_slice(&flat.nodes))?,
            buffer(DeviceArray::NODE_BOXES, bytemuck::cast_slice(&flat.boxes))?,
            buffer(DeviceArray::CORNERS, bytemuck::cast_slice(&flat.corners))?,
            buffer(DeviceArray::PRIMS, bytemuck::cast_slice(&flat.prims))?,
            buffer(DeviceArray::GRAPH, bytemuck::cast_slice(&flat.graph))?,
        ];
        let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
            .iter()
            .enumerate()
            .map(|(binding, buffer)| wgpu::BindGroupEntry {
                binding: binding as u32,
                resource: buffer.as_entire_binding(),
            })
            .collect();
        let bind_group = opened.checked("binding an accel", || {
            opened.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("rayd accel"),
                layout: &opened.kernel.accel_layout,
                entries: &entries,
            })
        })?;
        Ok(GpuGraph { bind_group, root: flat.root, variant: flat.variant, bytes, generation: opened.generation })
    }

    /// Bytes the accel occupies on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}
