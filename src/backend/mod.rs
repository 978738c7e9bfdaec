//! The backend seam: whole batches in, whole hit buffers out. Each device kind implements [`Backend`]; callers
//! go through [`crate::Context`] and never see which backend runs their work.

pub mod cpu;
pub mod host;
#[cfg(feature = "wgpu")]
pub mod wgpu;

use std::any::Any;
use std::sync::Arc;
use std::time::Duration;

use glam::Vec3;

use crate::accel::{AccelKind, BuildOptions, MemoryUsage};
use crate::backend::cpu::CpuAccel;
use crate::context::Accel;
use crate::error::{Error, Result};
use crate::geometry::motion::{Bounds, TimeSpan};
use crate::geometry::{BuildInput, PlacedInstance, Transform};
use crate::query::{Query, TraceOutput, TraceStats};
use crate::raygen::Generator;
use crate::reduce::{Partial, Reduction};

/// Node visits and triangle tests a ray may take on any device unless set otherwise
/// ([`cpu::CpuBackend::with_max_ray_work`], `wgpu::WgpuOptions::max_ray_work`): 2^20, hundreds of times what a ray
/// through an ordinary scene takes (the bunny's random rays take about 60), a few milliseconds of a core and a few
/// seconds of a thread on an H100.
pub const DEFAULT_MAX_RAY_WORK: u32 = 1 << 20;

/// Which implementation a device uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum BackendKind {
    /// `obvhs`-built BVHs traced on the host's cores with rayon.
    Cpu,
    /// The same BVHs, built on the host and traced by WGSL compute kernels on a wgpu (Vulkan) adapter (see
    /// [`wgpu`](crate::backend::wgpu)). Listed only in builds with the `wgpu` feature.
    Wgpu,
}

impl BackendKind {
    /// Every kind, in builds with or without the `wgpu` feature.
    pub const ALL: [BackendKind; 2] = [BackendKind::Cpu, BackendKind::Wgpu];
}

/// What a device is and can do.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DeviceInfo {
    /// Stable id, e.g. `cpu:0`.
    pub id: String,
    /// The backend that runs it.
    pub kind: BackendKind,
    /// Human-readable name.
    pub name: String,
    /// Memory the device can use, in bytes (host memory for the CPU).
    pub memory_bytes: u64,
    /// Worker threads (CPU) or compute units.
    pub parallelism: u32,
}

/// What a build made (or a blob describes), besides its options: its kind and the counts its info reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shape {
    /// Triangles, instances or a transform.
    pub kind: AccelKind,
    /// Triangles given.
    pub triangle_count: u64,
    /// Geometries given.
    pub geometry_count: u32,
    /// Instances given.
    pub instance_count: u64,
}

/// A built acceleration structure as a backend holds it.
pub trait BackendAccel: Any + Send + Sync {
    /// Bytes it occupies.
    fn size_bytes(&self) -> u64;
    /// Bytes an exact copy of it ([`BackendAccel::duplicate`]) occupies: its compacted size.
    fn compacted_size_bytes(&self) -> u64;
    /// An exact-size copy (compacted) that traces the same.
    fn duplicate(&self) -> Box<dyn BackendAccel>;
    /// A box around every triangle it holds at every time of `span` (`min > max` when there are none). Parents
    /// bound moving children with it; `TimeSpan::ALL` gives the accel's box over all of time.
    fn bounds_during(&self, span: TimeSpan) -> Bounds;
    /// The corners of triangle `prim_id` of geometry `geom_id`, if the accel kept random vertex access and the
    /// triangle exists.
    fn triangle_vertices(&self, geom_id: u32, prim_id: u32) -> Option<[Vec3; 3]>;
    /// Appends the payload that [`Backend::decode`] reads back (see [`crate::serialize`]); instances name their
    /// children by position in `children`, the accel's distinct children. A transform writes none: it is rebuilt
    /// from its input.
    fn encode(&self, children: &[Arc<Accel>], out: &mut Vec<u8>) -> Result<()>;
    /// The host structure (the CPU backend's) it is built on, where the backend keeps one (both backends do):
    /// instance accels and transforms read their children through it, and copies between devices start from it.
    fn host(&self) -> Option<&CpuAccel>;
    /// For downcasting to the backend's own type.
    fn as_any(&self) -> &dyn Any;
}

/// One kind of device. Every method works on whole batches.
pub trait Backend: Send + Sync {
    /// Describes the device.
    fn info(&self) -> DeviceInfo;
    /// Upper bounds of the memory that [`Backend::build`] will use for these inputs and options.
    fn compute_memory_usage(&self, inputs: &[BuildInput<'_>], options: &BuildOptions) -> Result<MemoryUsage>;
    /// Validates the inputs and builds an accel over them, asking `go_on` between the build's phases whether to go on
    /// (told no, it stops there with [`crate::Error::Stopped`]).
    fn build(
        &self,
        inputs: &[BuildInput<'_>],
        options: &BuildOptions,
        go_on: &dyn Fn() -> bool,
    ) -> Result<Box<dyn BackendAccel>>;
    /// Upper bounds of the memory that [`Backend::build_instances`] will use for `instances` instances, besides
    /// [`Backend::placed_children_bytes`].
    fn compute_instance_arrays_memory_usage(&self, instances: usize, options: &BuildOptions) -> Result<MemoryUsage>;
    /// Bytes that an instance accel or transform of this backend holds for `children` (the distinct accels it
    /// places, of this backend) besides its own arrays, at most: none where children are read where they are.
    fn placed_children_bytes(&self, _children: &[&Accel]) -> Result<u64> {
        Ok(0)
    }
    /// Builds an instance accel over checked instances, whose children must be accels of this backend.
    fn build_instances(&self, instances: &[PlacedInstance], options: &BuildOptions) -> Result<Box<dyn BackendAccel>>;
    /// A refitted copy of `accel` (a geometry accel of this backend built with `ALLOW_UPDATE`) with the positions
    /// of `inputs`, whose structure the caller checked.
    fn update(&self, accel: &dyn BackendAccel, inputs: &[BuildInput<'_>]) -> Result<Box<dyn BackendAccel>>;
    /// A refitted copy of `accel` (an instance accel of this backend built with `ALLOW_UPDATE`) with `instances`.
    fn update_instances(&self, accel: &dyn BackendAccel, instances: &[PlacedInstance])
    -> Result<Box<dyn BackendAccel>>;
    /// Places `child` (an accel of this backend) under a checked transform.
    fn build_transform(&self, transform: &Transform, child: &Arc<Accel>) -> Result<Box<dyn BackendAccel>>;
    /// The version of the payload layout [`BackendAccel::encode`] writes; it changes whenever the layout does.
    fn layout_version(&self) -> u32;
    /// Reads the payload of a geometry or instance accel of `shape` built with `options` (both checked) and placing
    /// `children`, checking everything that traversal, updates and vertex access rely on: INVALID_ARGUMENT naming
    /// what is wrong.
    fn decode(
        &self,
        shape: &Shape,
        options: &BuildOptions,
        payload: &[u8],
        children: &[Arc<Accel>],
    ) -> Result<Box<dyn BackendAccel>>;
    /// An accel of this device made from `host`, the host structure of a geometry accel of another device (a copy
    /// between devices).
    fn adopt(&self, host: &CpuAccel) -> Result<Box<dyn BackendAccel>>;
    /// Traces every ray of `rays` against `accel` (built by this backend) and writes the results in place.
    fn trace(&self, accel: &dyn BackendAccel, query: &Query, rays: &[u8], out: TraceOutput<'_>) -> Result<TraceStats>;
    /// The kernel time of each of `launches` launches over all of `rays` kept on the device, one after another
    /// ([`Context::time_launches`](crate::Context::time_launches)); FAILED_PRECONDITION by default: only a device
    /// with a trace kernel and timestamps has it.
    fn time_launches(
        &self,
        accel: &dyn BackendAccel,
        query: &Query,
        rays: &[u8],
        launches: u32,
    ) -> Result<Vec<Duration>> {
        let _ = (accel, query, rays, launches);
        Err(Error::FailedPrecondition(format!("{} has no trace kernel to time", self.info().id)))
    }
    /// [`Backend::trace`] of rays that may be generated: by default made on the host ([`host::trace_source`]); a
    /// backend that can make them where it traces does.
    fn trace_source(
        &self,
        accel: &dyn BackendAccel,
        query: &Query,
        rays: RaySource<'_>,
        out: TraceOutput<'_>,
    ) -> Result<TraceStats> {
        host::trace_source(self, accel, query, rays, out)
    }
    /// Traces `rays` (the first being ray `first_ray` of the batch; a whole number of the reduction's groups) and
    /// reduces their hits with a checked `reduction`: the piece's partial. By default the hits are reduced on the
    /// host ([`host::trace_reduced`]); a backend that can reduce where it traces does.
    fn trace_reduced(
        &self,
        accel: &dyn BackendAccel,
        query: &Query,
        rays: RaySource<'_>,
        first_ray: u64,
        reduction: &Reduction,
    ) -> Result<(Partial, TraceStats)> {
        host::trace_reduced(self, accel, query, rays, first_ray, reduction, host::MOST_REDUCED_HIT_BYTES)
    }
}

/// The rays of a trace as a backend receives them.
#[derive(Debug, Clone, Copy)]
pub enum RaySource<'a> {
    /// Packed in the query's ray format.
    Packed(&'a [u8]),
    /// Rays `first .. first + count` of a checked generator that holds them, made where they are traced.
    Generated {
        /// What makes them.
        generator: &'a Generator,
        /// The generator's index of the first.
        first: u64,
        /// How many.
        count: usize,
    },
}

impl<'a> RaySource<'a> {
    /// Rays `range` of it (indices from its first ray; `range.end` at most its rays): for packed rays whole records
    /// of `ray_size` bytes.
    pub fn part(&self, range: std::ops::Range<usize>, ray_size: usize) -> RaySource<'a> {
        match *self {
            RaySource::Packed(bytes) => RaySource::Packed(&bytes[range.start * ray_size..range.end * ray_size]),
            RaySource::Generated { generator, first, .. } => {
                RaySource::Generated { generator, first: first + range.start as u64, count: range.len() }
            }
        }
    }

    /// Bytes its rays take packed: the caller's bytes (perhaps not whole records), or whole records.
    pub fn packed_len(&self, ray_size: usize) -> usize {
        match self {
            RaySource::Packed(rays) => rays.len(),
            RaySource::Generated { count, .. } => count * ray_size,
        }
    }
}
