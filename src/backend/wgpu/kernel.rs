//! The trace pipeline: its WGSL source (`shaders/layout.wgsl` then `shaders/trace.wgsl`), its bind group layouts
//! and the uniform block each chunk gets.

use bytemuck::{Pod, Zeroable};

use crate::format::{HitFormat, RayFormat};
use crate::query::{Query, QueryKind};

/// The kernel's source: the shared structs, then the trace pipeline.
const SOURCE: &str = concat!(include_str!("shaders/layout.wgsl"), include_str!("shaders/trace.wgsl"));

/// Entries of the kernel's traversal stack (`STACK_SIZE` in `trace.wgsl`): an accel whose rays could need more is
/// refused. A BVH walk holds at most one pending node a level below its root; each instance level adds a resume
/// entry and a marker, each transform a marker.
pub(super) const STACK_SIZE: usize = 64;

/// Threads of a workgroup (`@workgroup_size` in `trace.wgsl`), one a ray.
pub(super) const WORKGROUP_SIZE: u32 = 64;

/// The uniform block of one chunk (`Params` in `layout.wgsl`), 32 bytes: `0 ray_count | 4 ray_format |
/// 8 hit_format | 12 query_kind | 16 query_flags | 20 records_per_ray | 24 record_words | 28 root`, every field a
/// little-endian u32. Formats and kinds are their indices in [`RayFormat::ALL`], [`HitFormat::ALL`] and
/// [`QueryKind::ALL`].
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
#[repr(C)]
pub(super) struct Params {
    /// Rays in the chunk.
    pub ray_count: u32,
    /// The ray format's index.
    pub ray_format: u32,
    /// The hit format's index.
    pub hit_format: u32,
    /// The query kind's index.
    pub query_kind: u32,
    /// The query's ray flags.
    pub query_flags: u32,
    /// Hit records a ray.
    pub records_per_ray: u32,
    /// Words a hit record (0 for the bitmask).
    pub record_words: u32,
    /// The traced accel's object: its offset in the `graph` buffer.
    pub root: u32,
}

/// The index of `value` in `all`.
fn index_of<T: PartialEq>(all: &[T], value: &T) -> u32 {
    all.iter().position(|v| v == value).expect("listed") as u32
}

impl Params {
    /// The query's part of the block; the accel's and the chunk's fields are 0 until filled.
    pub fn for_query(query: &Query) -> Params {
        Params {
            ray_format: index_of(&RayFormat::ALL, &query.ray_format),
            hit_format: index_of(&HitFormat::ALL, &query.hit_format),
            query_kind: index_of(&QueryKind::ALL, &query.kind),
            query_flags: query.flags.bits(),
            records_per_ray: query.records_per_ray() as u32,
            record_words: query.hit_format.size().map_or(0, |size| size as u32 / 4),
            ..Params::zeroed()
        }
    }
}

/// The compiled pipeline.
pub(super) struct Kernel {
    /// The trace pipeline.
    pub pipeline: wgpu::ComputePipeline,
    /// Group 0: an accel's buffers (nodes, node key boxes, corners, prims, graph).
    pub accel_layout: wgpu::BindGroupLayout,
    /// Group 1: a chunk's buffers (params, rays, hits, tallies, scratch).
    pub batch_layout: wgpu::BindGroupLayout,
}

/// A storage buffer entry of a bind group layout.
fn storage(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

impl Kernel {
    /// Compiles the pipeline on `device`.
    pub fn new(device: &wgpu::Device) -> Kernel {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("rayd trace"),
            source: wgpu::ShaderSource::Wgsl(SOURCE.into()),
        });
        let accel_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("rayd accel"),
            entries: &[storage(0, true), storage(1, true), storage(2, true), storage(3, true), storage(4, true)],
        });
        let params = wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: wgpu::BufferSize::new(size_of::<Params>() as u64),
            },
            count: None,
        };
        let batch_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("rayd batch"),
            entries: &[params, storage(1, true), storage(2, false), storage(3, false), storage(4, false)],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("rayd trace"),
            bind_group_layouts: &[Some(&accel_layout), Some(&batch_layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("rayd trace"),
            layout: Some(&layout),
            module: &module,
            entry_point: Some("trace"),
            compilation_options: wgpu::PipelineCompilationOptions::default(),
            cache: None,
        });
        Kernel { pipeline, accel_layout, batch_layout }
    }
}
