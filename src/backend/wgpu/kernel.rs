//! The trace pipelines: their WGSL source (`shaders/layout.wgsl`, `trace.wgsl`, `generate.wgsl`, `reduce.wgsl`),
//! the variants it is compiled into, the image reduction's pipeline, their bind group layouts and the uniform block
//! each chunk gets.

use std::sync::OnceLock;

use bytemuck::{Pod, Zeroable};

use super::device::Opened;
use super::spirv::Source;
use crate::error::Result;
use crate::format::{HitFormat, RayFormat};
use crate::query::{Query, QueryKind};

/// The kernel's source: the shared structs, the trace pipeline, rays made on the device, the pixel reduction.
pub(super) const SOURCE: &str = concat!(
    include_str!("shaders/layout.wgsl"),
    include_str!("shaders/trace.wgsl"),
    include_str!("shaders/generate.wgsl"),
    include_str!("shaders/reduce.wgsl"),
);

/// Entries of the kernel's traversal stack (`STACK_SIZE` in `trace.wgsl`): an accel whose rays could need more is
/// refused. A BVH walk holds at most `NODE_WIDTH − 1` pending lanes a node on its way down; each instance level adds
/// a resume entry and a marker, each transform a marker.
pub(super) const STACK_SIZE: usize = 128;

/// Threads of a workgroup, one a ray (the pipeline constant `WORKGROUP_SIZE` of `trace.wgsl` is set to it).
pub(super) const WORKGROUP_SIZE: u32 = 64;

/// What a pipeline is specialised for (the pipeline constants of `trace.wgsl`): the driver compiles away the
/// instance levels and motion keys of graphs that have none, every query kind but the traced one's, and the
/// normals of hit formats without them. Fewer live values a thread, more threads a multiprocessor.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct Variant {
    /// The graph has instance or transform levels below its root (`LEVELS`).
    pub levels: bool,
    /// Something in the graph has motion keys (`MOTION`).
    pub motion: bool,
    /// The query kind's index in [`QueryKind::ALL`] (`QUERY_KIND`).
    pub kind: u32,
    /// The hit format is [`HitFormat::Full`] (`FULL_HITS`).
    pub full_hits: bool,
    /// Where the rays come from (`GENERATOR`).
    pub rays: Rays,
}

/// Where a pipeline's rays come from (the values of `GENERATOR_*` in `generate.wgsl`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[repr(u32)]
pub(super) enum Rays {
    /// The caller's rays, packed.
    #[default]
    Packed = 0,
    /// A pinhole camera generator.
    Pinhole = 1,
    /// An orthographic camera generator.
    Orthographic = 2,
    /// A lidar generator.
    Lidar = 3,
}

/// Pipelines a kernel can hold: one a [`Variant`].
const VARIANTS: usize = 4 * QueryKind::ALL.len() * 2 * 2 * 2;

impl Variant {
    /// The graph's part of a variant; [`Variant::for_query`] adds the query's.
    pub fn for_graph(levels: bool, motion: bool) -> Variant {
        Variant { levels, motion, ..Variant::default() }
    }

    /// This graph variant for tracing `query`.
    pub fn for_query(self, query: &Query) -> Variant {
        Variant { kind: index_of(&QueryKind::ALL, &query.kind), full_hits: query.hit_format == HitFormat::Full, ..self }
    }

    /// Its pipeline's index in [`Kernel`].
    fn index(self) -> usize {
        (((self.rays as usize * QueryKind::ALL.len() + self.kind as usize) * 2 + usize::from(self.full_hits)) * 2
            + usize::from(self.motion))
            * 2
            + usize::from(self.levels)
    }
}

/// The uniform block of one chunk (`Params` in `layout.wgsl`), 44 bytes: `0 ray_count | 4 ray_format |
/// 8 hit_format | 12 query_flags | 16 records_per_ray | 20 record_words | 24 root | 28 first_ray | 32 group_rays |
/// 36 pixel_words | 40 max_ray_work`, every field a little-endian u32.
/// Formats are their indices in [`RayFormat::ALL`] and [`HitFormat::ALL`]; the query kind is the pipeline's
/// ([`Variant`]).
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
#[repr(C)]
pub(super) struct Params {
    /// Rays in the chunk.
    pub ray_count: u32,
    /// The ray format's index.
    pub ray_format: u32,
    /// The hit format's index.
    pub hit_format: u32,
    /// The query's ray flags.
    pub query_flags: u32,
    /// Hit records a ray.
    pub records_per_ray: u32,
    /// Words a hit record (0 for the bitmask).
    pub record_words: u32,
    /// The traced accel's object: its offset in the `graph` buffer.
    pub root: u32,
    /// Generated rays: the generator's index of the chunk's first ray.
    pub first_ray: u32,
    /// The image reduction: rays a pixel.
    pub group_rays: u32,
    /// The image reduction: words a pixel (1 depth, 4 normal; 0 without it).
    pub pixel_words: u32,
    /// Node visits and triangle tests a ray may take ([`super::WgpuOptions::max_ray_work`]).
    pub max_ray_work: u32,
}

/// The index of `value` in `all`.
fn index_of<T: PartialEq>(all: &[T], value: &T) -> u32 {
    all.iter().position(|v| v == value).expect("listed") as u32
}

impl Params {
    /// The query's part of the block, rays taking up to `ray_work` node visits and triangle tests; the accel's and
    /// the chunk's fields are 0 until filled.
    pub fn for_query(query: &Query, ray_work: u32) -> Params {
        Params {
            max_ray_work: ray_work,
            ray_format: index_of(&RayFormat::ALL, &query.ray_format),
            hit_format: index_of(&HitFormat::ALL, &query.hit_format),
            query_flags: query.flags.bits(),
            records_per_ray: query.records_per_ray() as u32,
            record_words: query.hit_format.size().map_or(0, |size| size as u32 / 4),
            ..Params::zeroed()
        }
    }
}

/// The trace pipelines, compiled on first use, one a [`Variant`].
pub(super) struct Kernel {
    /// The WGSL they are made from (each pipeline gets its own SPIR-V module, its constants applied).
    source: Source,
    /// Their layout (the two bind group layouts).
    layout: wgpu::PipelineLayout,
    /// By [`Variant::index`].
    pipelines: [OnceLock<wgpu::ComputePipeline>; VARIANTS],
    /// The image reduction's pass (`reduce_pixels`).
    reduce_pixels: OnceLock<wgpu::ComputePipeline>,
    /// Group 0: an accel's buffers (nodes, node key boxes, corners, prims, graph).
    pub accel_layout: wgpu::BindGroupLayout,
    /// Group 1: a chunk's buffers (params, rays, hits, tallies, scratch, reduced).
    pub batch_layout: wgpu::BindGroupLayout,
}

/// The pipeline `cell` holds, or the one `compile` makes, kept in `cell` only if it compiled (two threads asking at
/// once for one not compiled yet may both compile it: the first kept is used).
fn kept(
    cell: &OnceLock<wgpu::ComputePipeline>,
    compile: impl FnOnce() -> Result<wgpu::ComputePipeline>,
) -> Result<&wgpu::ComputePipeline> {
    if let Some(pipeline) = cell.get() {
        return Ok(pipeline);
    }
    let pipeline = compile()?;
    Ok(cell.get_or_init(|| pipeline))
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
    /// Parses the kernel's source and makes its layouts on `device`.
    ///
    /// The pipelines' SPIR-V is written without naga's run-time checks (index clamps, loop counters, division
    /// guards), which cost a third of the kernel's speed on an H100 (BENCHMARKS.md), and without the zero
    /// initializers of the arrays that [`super::spirv`] names. That is sound because:
    /// - storage buffers are indexed by offsets the host wrote and checked (`graph.rs`, `layout.rs`, the chunk sizes
    ///   of `batch.rs`), and Vulkan's robust buffer access (which wgpu enables) backs that up;
    /// - private arrays: the traversal stack never holds more than `STACK_SIZE` entries (`GpuGraph::upload` refuses
    ///   graphs that could need more), levels never exceed `MAX_LEVELS` (= `MAX_GRAPH_DEPTH`, which builds
    ///   enforce), an `all` query's hit entries read back from `scratch` carry the level count this same invocation
    ///   wrote there (`tests` below check the WGSL constants against the Rust ones), and the arrays left
    ///   uninitialized are written before they are read;
    /// - every loop ends: BVH nodes form trees whose children follow their parent (built so, or checked when
    ///   loaded), instance graphs have no cycles (an accel only places accels that existed before it), and the
    ///   other loops count to fixed bounds;
    /// - integer divisions and remainders are by non-zero constants.
    pub fn new(device: &wgpu::Device) -> Kernel {
        let source = Source::new(SOURCE);
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
            entries: &[
                params,
                storage(1, true),
                storage(2, false),
                storage(3, false),
                storage(4, false),
                storage(5, false),
            ],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("rayd trace"),
            bind_group_layouts: &[Some(&accel_layout), Some(&batch_layout)],
            immediate_size: 0,
        });
        Kernel {
            source,
            layout,
            pipelines: std::array::from_fn(|_| OnceLock::new()),
            reduce_pixels: OnceLock::new(),
            accel_layout,
            batch_layout,
        }
    }

    /// The pipeline of `variant`, compiled on `opened`'s device the first time it is asked for (as
    /// [`Opened::checked`] says, an error if the driver fails it; nothing is kept then, so the next trace that needs
    /// it compiles it again).
    pub fn pipeline(&self, opened: &Opened, variant: Variant) -> Result<&wgpu::ComputePipeline> {
        kept(&self.pipelines[variant.index()], || {
            let constants = [
                ("LEVELS", f64::from(u8::from(variant.levels))),
                ("MOTION", f64::from(u8::from(variant.motion))),
                ("QUERY_KIND", f64::from(variant.kind)),
                ("FULL_HITS", f64::from(u8::from(variant.full_hits))),
                ("GENERATOR", f64::from(variant.rays as u32)),
                ("WORKGROUP_SIZE", f64::from(WORKGROUP_SIZE)),
            ];
            opened.checked("compiling the trace kernel", || self.compile(&opened.device, "trace", &constants))
        })
    }

    /// The image reduction's pipeline, compiled as [`Kernel::pipeline`] compiles the trace's.
    pub fn reduce_pixels(&self, opened: &Opened) -> Result<&wgpu::ComputePipeline> {
        kept(&self.reduce_pixels, || {
            let constants = [("WORKGROUP_SIZE", f64::from(WORKGROUP_SIZE))];
            opened
                .checked("compiling the image reduction", || self.compile(&opened.device, "reduce_pixels", &constants))
        })
    }

    /// The entry point `entry` with the pipeline constants `constants`, as SPIR-V handed to the driver as is.
    fn compile(&self, device: &wgpu::Device, entry: &str, constants: &[(&str, f64)]) -> wgpu::ComputePipeline {
        let spirv = self.source.spirv(entry, constants);
        let entry_points =
            [wgpu::PassthroughShaderEntryPoint { name: entry.into(), workgroup_size: (WORKGROUP_SIZE, 1, 1) }];
        // SAFETY: naga wrote and validated this SPIR-V from the kernel's WGSL; what `Kernel::new` lists makes
        // running it without naga's checks and the dropped initializers sound.
        let module = unsafe {
            device.create_shader_module_passthrough(wgpu::ShaderModuleDescriptorPassthrough {
                label: Some(entry),
                entry_points: entry_points.as_slice().into(),
                spirv: Some(spirv.into()),
                ..wgpu::ShaderModuleDescriptorPassthrough::default()
            })
        };
        device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(entry),
            layout: Some(&self.layout),
            module: &module,
            entry_point: Some(entry),
            compilation_options: wgpu::PipelineCompilationOptions::default(),
            cache: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::wgpu::layout::NODE_WIDTH;
    use crate::geometry::MAX_GRAPH_DEPTH;

    /// The kernel's bounds that its unchecked accesses rely on are the host's (see `Kernel::new`).
    #[test]
    fn the_kernels_bounds_are_the_hosts() {
        assert!(SOURCE.contains(&format!("const STACK_SIZE: u32 = {STACK_SIZE}u;")));
        assert!(SOURCE.contains(&format!("const MAX_LEVELS: u32 = {MAX_GRAPH_DEPTH}u;")));
        assert!(SOURCE.contains(&format!("const NODE_WIDTH: u32 = {NODE_WIDTH}u;")));
        assert!(SOURCE.contains(&format!("override WORKGROUP_SIZE: u32 = {WORKGROUP_SIZE}u;")));
    }
}
