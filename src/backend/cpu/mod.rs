//! The CPU backend: BVHs built by `obvhs` ([`bvh`]) over triangles ([`triangles`]) or placed instances
//! ([`instances`]), traced by [`traverse`] over rayon chunks. A static geometry accel is also collapsed to 8-wide
//! nodes ([`wide`], from [`collapse`], lanes ranked by `occlusion`) with its corners in blocks of four ([`blocks`]): one
//! ray walks them with AVX2 box tests; coherent rays walk them together as packets of 8 (AVX2) or 16 (AVX-512)
//! (`packet`, its registers in `ray_lanes`, the triangle filter both share in `filter`), and through static instance
//! accels too, carried into each instance's space together (`instance_packets`). A moving accel's nodes (geometry or
//! instances) are collapsed to 8-wide ones too, with their lanes' boxes at each key, interpolated at each ray's time
//! (`moving_wide`); coherent rays walk moving accels (geometry or instances) together too, each at its own time
//! (`moving_packets`). Answers are the same whichever way a ray is traced.

mod blocks;
pub(crate) mod bvh;
pub(crate) mod collapse;
#[cfg(target_arch = "x86_64")]
mod filter;
#[cfg(target_arch = "x86_64")]
mod instance_packets;
mod instances;
pub mod large_pages;
#[cfg(target_arch = "x86_64")]
mod moving_packets;
mod moving_wide;
mod occlusion;
#[cfg(target_arch = "x86_64")]
mod packet;
mod persist;
#[cfg(target_arch = "x86_64")]
mod ray_lanes;
mod traverse;
mod triangles;
mod turns;
mod wide;

use std::any::Any;
use std::sync::Arc;

use glam::Vec3;

use crate::accel::{BuildOptions, MemoryUsage};
use crate::backend::{Backend, BackendAccel, BackendKind, DEFAULT_MAX_RAY_WORK, DeviceInfo, RaySource, Shape, host};
use crate::context::Accel;
use crate::error::{Error, Result};
use crate::format::Ray;
use crate::geometry::motion::{Bounds, TimeSpan};
use crate::geometry::{BuildInput, PlacedInstance, Transform, gather, triangle_counts};
use crate::query::{Collector, ImageRows, Query, TraceOutput, TraceStats, trace_batch, trace_batch_here};
use crate::reduce::{Partial, Reduction};

use bvh::Footprint;
#[cfg(feature = "wgpu")]
pub(crate) use instances::cpu_child;
pub use instances::{InstanceBvh, TransformNode};
use traverse::Stacks;
pub use triangles::TriangleBvh;

/// The CPU device. It uses rayon's current thread pool, so a caller can bound its threads with
/// `ThreadPool::install`.
#[derive(Debug, Clone, Copy)]
pub struct CpuBackend {
    /// Node visits and triangle tests a ray may take ([`CpuBackend::with_max_ray_work`]).
    max_ray_work: u32,
}

impl Default for CpuBackend {
    fn default() -> Self {
        CpuBackend::with_max_ray_work(DEFAULT_MAX_RAY_WORK)
    }
}

impl CpuBackend {
    /// A CPU backend whose rays may take at most `max_ray_work` node visits and triangle tests each (16 times it a
    /// group of up to 16 neighbouring rays traced together). A geometry accel's walk is bounded by its own size,
    /// but an instance graph multiplies a ray's work level by level (a pile of instances of piles, a few megabytes,
    /// makes billions of tests a ray), and a piece of a trace cannot be stopped from outside once it runs: it would
    /// hold a worker, or the thread that answers calls, for hours. So a ray past the limit enters no more instances,
    /// and its trace fails with [`Error::RayWork`] (RESOURCE_EXHAUSTED).
    pub fn with_max_ray_work(max_ray_work: u32) -> CpuBackend {
        CpuBackend { max_ray_work }
    }

    /// `stats` of a trace, or [`Error::RayWork`] if a ray of it was stopped at the work limit.
    fn within_work(&self, stats: TraceStats) -> Result<TraceStats> {
        match stats.rays_past_work {
            0 => Ok(stats),
            rays => Err(Error::RayWork {
                device: "cpu:0".into(),
                rays,
                limit: self.max_ray_work,
                setting: "scheduler.cpu_ray_work",
            }),
        }
    }

    /// How a part of a trace in parts is traced on the CPU: by the batch driver on the calling thread
    /// ([`trace_batch_here`]).
    fn part_tracer<'a>(
        &'a self,
        accel: &'a CpuAccel,
    ) -> impl Fn(&Query, &[u8], Option<ImageRows>, TraceOutput<'_>) -> Result<TraceStats> + Sync + 'a {
        move |query, rays, rows, out| {
            let work = u64::from(self.max_ray_work);
            let stats = trace_batch_here(query, rays, rows, out, work, || accel.new_stacks(), walk(accel))?;
            self.within_work(stats)
        }
    }
}

/// A CPU accel of any kind.
#[derive(Debug, Clone)]
pub enum CpuAccel {
    /// A geometry accel (boxed: its arrays' headers make it several times the size of the other kinds).
    Triangles(Box<TriangleBvh>),
    /// An instance accel.
    Instances(InstanceBvh),
    /// A static transform.
    Transform(TransformNode),
}

impl CpuAccel {
    /// Bytes it occupies, counted as `footprint` says.
    fn footprint(&self, footprint: Footprint) -> u64 {
        match self {
            CpuAccel::Triangles(bvh) => bvh.size_bytes(footprint),
            CpuAccel::Instances(bvh) => bvh.size_bytes(footprint),
            CpuAccel::Transform(node) => node.size_bytes(),
        }
    }

    /// Stack entries a trace through it needs.
    fn stack_size(&self) -> usize {
        match self {
            CpuAccel::Triangles(bvh) => bvh.stack_size(),
            CpuAccel::Instances(bvh) => bvh.stack_size,
            CpuAccel::Transform(node) => node.stack_size,
        }
    }
}

impl BackendAccel for CpuAccel {
    fn size_bytes(&self) -> u64 {
        self.footprint(Footprint::Allocated)
    }

    fn compacted_size_bytes(&self) -> u64 {
        self.footprint(Footprint::Exact)
    }

    fn duplicate(&self) -> Box<dyn BackendAccel> {
        Box::new(self.clone())
    }

    fn bounds_during(&self, span: TimeSpan) -> Bounds {
        match self {
            CpuAccel::Triangles(bvh) => bvh.bounds_during(span),
            CpuAccel::Instances(bvh) => bvh.bounds_during(span),
            CpuAccel::Transform(node) if span == TimeSpan::ALL => node.bounds(),
            CpuAccel::Transform(node) => node.bounds_during(span),
        }
    }

    fn triangle_vertices(&self, geom_id: u32, prim_id: u32) -> Option<[Vec3; 3]> {
        match self {
            CpuAccel::Triangles(bvh) => bvh.triangle_vertices(geom_id, prim_id),
            CpuAccel::Instances(_) | CpuAccel::Transform(_) => None,
        }
    }

    fn encode(&self, children: &[Arc<Accel>], out: &mut Vec<u8>) -> Result<()> {
        self.encode_payload(children, out)
    }

    fn host(&self) -> Option<&CpuAccel> {
        Some(self)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl Backend for CpuBackend {
    fn info(&self) -> DeviceInfo {
        DeviceInfo {
            id: "cpu:0".into(),
            kind: BackendKind::Cpu,
            name: format!("CPU ({} threads)", rayon::current_num_threads()),
            memory_bytes: host_memory_bytes(),
            parallelism: rayon::current_num_threads() as u32,
        }
    }

    fn compute_memory_usage(&self, inputs: &[BuildInput<'_>], options: &BuildOptions) -> Result<MemoryUsage> {
        options.validate()?;
        let counts = triangle_counts(inputs, options.motion.keys as usize)?;
        let has_masks = inputs.iter().any(|BuildInput::Triangles(t)| t.masks.is_some());
        Ok(triangles::memory_bounds(counts.iter().sum(), inputs.len(), has_masks, options))
    }

    fn build(
        &self,
        inputs: &[BuildInput<'_>],
        options: &BuildOptions,
        go_on: &dyn Fn() -> bool,
    ) -> Result<Box<dyn BackendAccel>> {
        options.validate()?;
        let triangles = gather(inputs, options.motion.keys as usize)?;
        Ok(Box::new(CpuAccel::Triangles(Box::new(TriangleBvh::build(triangles, options, go_on)?))))
    }

    fn compute_instance_arrays_memory_usage(&self, instances: usize, options: &BuildOptions) -> Result<MemoryUsage> {
        options.validate()?;
        Ok(instances::memory_bounds(instances, options))
    }

    fn build_instances(&self, instances: &[PlacedInstance], options: &BuildOptions) -> Result<Box<dyn BackendAccel>> {
        Ok(Box::new(CpuAccel::Instances(InstanceBvh::build(instances, options)?)))
    }

    fn build_transform(&self, transform: &Transform, child: &Arc<Accel>) -> Result<Box<dyn BackendAccel>> {
        Ok(Box::new(CpuAccel::Transform(TransformNode::build(transform, child)?)))
    }

    fn update(&self, accel: &dyn BackendAccel, inputs: &[BuildInput<'_>]) -> Result<Box<dyn BackendAccel>> {
        let CpuAccel::Triangles(bvh) = cpu(accel)? else {
            return Err(Error::FailedPrecondition("only a geometry accel is updated with triangles".into()));
        };
        let triangles = gather(inputs, bvh.motion.keys as usize)?;
        let refitted = bvh.refit(&triangles).ok_or_else(instances::not_updatable)?;
        Ok(Box::new(CpuAccel::Triangles(Box::new(refitted))))
    }

    fn update_instances(
        &self,
        accel: &dyn BackendAccel,
        instances: &[PlacedInstance],
    ) -> Result<Box<dyn BackendAccel>> {
        let CpuAccel::Instances(bvh) = cpu(accel)? else {
            return Err(Error::FailedPrecondition("only an instance accel is updated with instances".into()));
        };
        Ok(Box::new(CpuAccel::Instances(bvh.refit(instances)?)))
    }

    fn layout_version(&self) -> u32 {
        persist::LAYOUT_VERSION
    }

    fn decode(
        &self,
        shape: &Shape,
        options: &BuildOptions,
        payload: &[u8],
        children: &[Arc<Accel>],
    ) -> Result<Box<dyn BackendAccel>> {
        Ok(Box::new(CpuAccel::decode_payload(shape, options, payload, children)?))
    }

    /// An exact-size copy of the host structure.
    fn adopt(&self, host: &CpuAccel) -> Result<Box<dyn BackendAccel>> {
        Ok(Box::new(host.clone()))
    }

    fn trace(&self, accel: &dyn BackendAccel, query: &Query, rays: &[u8], out: TraceOutput<'_>) -> Result<TraceStats> {
        let accel = cpu(accel)?;
        let work = u64::from(self.max_ray_work);
        let stats = trace_batch(query, rays, out, work, || accel.new_stacks(), walk(accel))?;
        self.within_work(stats)
    }

    fn trace_source(
        &self,
        accel: &dyn BackendAccel,
        query: &Query,
        rays: RaySource<'_>,
        out: TraceOutput<'_>,
    ) -> Result<TraceStats> {
        host::trace_source_in_parts(self, accel, query, rays, out, &self.part_tracer(cpu(accel)?))
    }

    fn trace_reduced(
        &self,
        accel: &dyn BackendAccel,
        query: &Query,
        rays: RaySource<'_>,
        first_ray: u64,
        reduction: &Reduction,
    ) -> Result<(Partial, TraceStats)> {
        host::trace_reduced_in_parts(query, rays, first_ray, reduction, &self.part_tracer(cpu(accel)?))
    }
}

/// How the batch driver walks a group of rays through `accel` ([`CpuAccel::traverse_group`]).
fn walk(accel: &CpuAccel) -> impl Fn(&mut Stacks, &[Ray], &mut [Collector<'_>], &mut TraceStats) + Sync + '_ {
    |stacks, rays, collectors, stats| accel.traverse_group(stacks, rays, collectors, stats)
}

/// The CPU structure of `accel`; FAILED_PRECONDITION for an accel of another device.
pub(crate) fn cpu(accel: &dyn BackendAccel) -> Result<&CpuAccel> {
    accel
        .as_any()
        .downcast_ref::<CpuAccel>()
        .ok_or_else(|| Error::FailedPrecondition("the accel was built on another device".into()))
}

/// The indices of the set bits of `mask`, lowest first.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn set_bits(mask: u32) -> impl Iterator<Item = usize> {
    let mut rest = mask;
    std::iter::from_fn(move || {
        let bit = (rest != 0).then(|| rest.trailing_zeros() as usize);
        rest &= rest.wrapping_sub(1);
        bit
    })
}

/// Total host memory, from `/proc/meminfo` where there is one.
pub(crate) fn host_memory_bytes() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
            let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
            Some(kib * 1024)
        })
        .unwrap_or(0)
}
