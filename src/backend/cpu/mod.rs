//! The CPU backend: BVHs built by `obvhs`, laid out by [`bvh`], traced by [`traverse`] over rayon chunks.

mod bvh;
mod traverse;

use crate::accel::{BuildOptions, MemoryUsage};
use crate::backend::{Backend, BackendAccel, BackendKind, DeviceInfo};
use crate::error::{Error, Result};
use crate::geometry::{BuildInput, gather, triangle_counts};
use crate::query::{Query, TraceOutput, TraceStats, trace_batch};

pub use bvh::CpuAccel;

/// The CPU device. It uses rayon's current thread pool, so a caller can bound its threads with
/// `ThreadPool::install`.
#[derive(Debug, Default)]
pub struct CpuBackend;

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
        let counts = triangle_counts(inputs)?;
        let has_masks = inputs.iter().any(|BuildInput::Triangles(t)| t.masks.is_some());
        Ok(bvh::memory_bounds(counts.iter().sum(), inputs.len(), has_masks, options))
    }

    fn build(&self, inputs: &[BuildInput<'_>], options: &BuildOptions) -> Result<Box<dyn BackendAccel>> {
        options.validate()?;
        let triangles = gather(inputs)?;
        Ok(Box::new(CpuAccel::build(triangles, options)))
    }

    fn trace(&self, accel: &dyn BackendAccel, query: &Query, rays: &[u8], out: TraceOutput<'_>) -> Result<TraceStats> {
        let accel = accel
            .as_any()
            .downcast_ref::<CpuAccel>()
            .ok_or_else(|| Error::FailedPrecondition("the accel was built on another device".into()))?;
        trace_batch(
            query,
            rays,
            out,
            || accel.new_stack(),
            |stack, ray, collector, stats| accel.traverse(stack, ray, collector, stats),
        )
    }
}

/// Total host memory, from `/proc/meminfo` where there is one.
fn host_memory_bytes() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
            let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
            Some(kib * 1024)
        })
        .unwrap_or(0)
}
