//! Traces of generated rays and reduced traces done around a backend's plain [`Backend::trace`]: the rays made on
//! the host into a scratch buffer, the hits reduced on the host, both across the rayon pool. Every backend's
//! default; the wgpu backend does on the device what it can and comes here for the rest.

use super::{Backend, BackendAccel, RaySource};
use crate::error::Result;
use crate::format::RayFormat;
use crate::query::{Query, TraceOutput, TraceStats};
use crate::reduce::{Partial, Reduction};

/// The rays of `rays` packed in `format`: the caller's bytes, or made into `scratch`.
pub fn packed<'a>(rays: RaySource<'a>, format: RayFormat, scratch: &'a mut Vec<u8>) -> &'a [u8] {
    match rays {
        RaySource::Packed(bytes) => bytes,
        RaySource::Generated { generator, first, count } => {
            scratch.clear();
            scratch.resize(count * format.size(), 0);
            generator.fill_parallel(format, first, scratch);
            scratch
        }
    }
}

/// [`Backend::trace_source`] with the rays made on the host.
pub fn trace_source<B: Backend + ?Sized>(
    backend: &B,
    accel: &dyn BackendAccel,
    query: &Query,
    rays: RaySource<'_>,
    out: TraceOutput<'_>,
) -> Result<TraceStats> {
    let mut scratch = Vec::new();
    backend.trace(accel, query, packed(rays, query.ray_format, &mut scratch), out)
}

/// [`Backend::trace_reduced`] with the rays made and the hits reduced on the host: traced with the reduction's
/// [`Reduction::traced_query`] into scratch buffers, then reduced.
pub fn trace_reduced<B: Backend + ?Sized>(
    backend: &B,
    accel: &dyn BackendAccel,
    query: &Query,
    rays: RaySource<'_>,
    first_ray: u64,
    reduction: &Reduction,
) -> Result<(Partial, TraceStats)> {
    let mut scratch = Vec::new();
    let rays = packed(rays, query.ray_format, &mut scratch);
    let traced = reduction.traced_query(query);
    let layout = traced.output_layout(rays.len())?;
    let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
    let stats = backend.trace(accel, &traced, rays, TraceOutput { hits: &mut hits, counts: &mut counts })?;
    Ok((reduction.reduce_piece_parallel(&traced, first_ray, rays, &hits, &counts), stats))
}
