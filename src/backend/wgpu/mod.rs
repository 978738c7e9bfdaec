//! The wgpu backend: accels built on the host by the CPU backend's builders, their graphs flattened ([`graph`]) and
//! uploaded once ([`layout`]), traced by a WGSL compute kernel ([`kernel`], `shaders/`; its SPIR-V written by
//! [`spirv`]) in chunks that fit the adapter's limits ([`batch`]), on every Vulkan adapter that wgpu enumerates
//! ([`device`]).
//!
//! What runs on the GPU: traversal and hit collection for every accel kind — geometry accels (static or with
//! vertex motion), instance accels (visibility masks, instance flags, motion keys) and static, matrix motion and
//! SRT motion transforms, in graphs as deep as the engine allows — at per-ray times, in every ray format, hit
//! format and query kind, with ray flags and Prime masks. Rays of camera and lidar generators are made by the
//! kernel, and image and count reductions made on the device, so that only the reduction crosses the bus
//! ([`offload`]). One kernel walks every level of 4-wide nodes: entering an instance or transform it carries the ray
//! into the child's space and pushes a marker that restores it. It is compiled into one pipeline a graph shape,
//! query and ray source ([`kernel::Variant`]), so that a static geometry accel's
//! closest-hit trace carries none of the instance, motion or `all`-query machinery. Refused (FAILED_PRECONDITION):
//! graphs whose rays could need more than the kernel's 128 stack entries.
//!
//! Results agree with the CPU backend up to rounding: the kernel runs the same watertight test, edge rule and tie
//! rule, its arithmetic operation by operation as the CPU's (no multiply and add fused: [`spirv`]), but a GPU
//! divides less exactly and may fuse the arithmetic of the boxes and of the rays' transforms, so `t`, `u` and `v`
//! can differ in the last bits and a ray through an edge can pick the neighbouring triangle. The traversal order differs (4-wide nodes here,
//! 8-wide on the CPU), which only `any` queries and terminate-on-first-hit rays can see: they may stop at another
//! hit, equally valid.

mod batch;
mod device;
mod graph;
mod kernel;
mod layout;
mod offload;
mod opening;
mod spirv;

use std::any::Any;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use glam::Vec3;

use crate::accel::{BuildOptions, MemoryUsage};
use crate::backend::cpu::{CpuAccel, CpuBackend, cpu};
use crate::backend::{Backend, BackendAccel, DEFAULT_MAX_RAY_WORK, DeviceInfo, RaySource, Shape, host};
use crate::context::Accel;
use crate::error::{Error, Result};
use crate::geometry::motion::{Bounds, TimeSpan};
use crate::geometry::{BuildInput, PlacedInstance, Transform, triangle_counts};
use crate::query::{Query, TraceOutput, TraceStats};
use crate::reduce::{Partial, Reduction};

use batch::{Input, Output};
use device::{Gpu, Opened};
use layout::{DeviceArray, GpuGraph};
use offload::{DeviceGenerator, OnDevice};

/// Settings of a wgpu device.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct WgpuOptions {
    /// Caps the bytes of each per-chunk buffer a trace binds (rays, hits, counts, `all` scratch) below the
    /// adapter's `max_storage_buffer_binding_size`; `None` uses the adapter's limit. Smaller chunks mean more
    /// dispatches: tests use it to split small batches.
    pub max_binding_bytes: Option<u64>,
    /// Caps the rays of a chunk (when `None`: 2^21 for rays made on the device and reduced there, 2^18 otherwise;
    /// the bindings and a dispatch's workgroups cap it too). Larger chunks mean fewer dispatches but less overlap of
    /// copies with tracing: benches sweep it.
    pub max_chunk_rays: Option<usize>,
    /// Caps the bytes of the buffers one trace holds on the device (its two chunks' buffers, staging included):
    /// chunks of many records a ray (`all` queries) are cut to fit; `None`: [`DEFAULT_MAX_TRACE_BYTES`]. The traces
    /// running at once, times this, bound what tracing takes of the device's memory (and, for the staging, of the
    /// host's), besides at most 256 MiB of idle buffers kept for later traces (a trace that takes one up, and grows
    /// it to its chunks, holds it on top of its own).
    pub max_trace_bytes: Option<u64>,
    /// Caps the node visits and triangle tests of one ray; `None`: [`DEFAULT_MAX_RAY_WORK`]. Nothing stops a GPU's
    /// walk from outside once it runs: it holds the device from every other trace meanwhile, and one past a minute
    /// takes the device as hung ([`device::ANSWER_TIMEOUT`]). A ray stops at this cap, and its trace fails
    /// (RESOURCE_EXHAUSTED) instead.
    pub max_ray_work: Option<u32>,
}

/// [`WgpuOptions::max_trace_bytes`] unless set: 1 GiB, about eight times what a trace of ordinary chunks (2^18 rays
/// and their closest hits) holds.
pub const DEFAULT_MAX_TRACE_BYTES: u64 = 1 << 30;

/// One wgpu adapter as a device.
pub struct WgpuBackend {
    /// The adapter, and its device once opened.
    gpu: Arc<Gpu>,
    /// Chunk limits.
    options: WgpuOptions,
    /// Builds, updates and serialization run on the host, as on the CPU backend.
    host: CpuBackend,
}

impl std::fmt::Debug for WgpuBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WgpuBackend").field("adapter", &self.gpu.index()).field("options", &self.options).finish()
    }
}

/// A backend for every adapter wgpu enumerates (an empty list on a machine without one).
pub fn backends(options: WgpuOptions) -> Vec<WgpuBackend> {
    device::adapters()
        .iter()
        .map(|gpu| WgpuBackend { gpu: Arc::clone(gpu), options, host: CpuBackend::default() })
        .collect()
}

/// An accel of the wgpu backend: the host's structure (which builds, updates, bounds, vertex access,
/// serialization and parents use) and its graph on the device (which traces use).
#[derive(Debug, Clone)]
pub struct WgpuAccel {
    /// The CPU backend's accel.
    host: CpuAccel,
    /// Its graph's arrays on the device, shared by copies of the accel (uploaded anew, for all of them, after the
    /// device is lost).
    device: Arc<DeviceCopy>,
}

/// An accel's graph on the device, uploaded again from the host structure when the device it was on is lost.
#[derive(Debug)]
struct DeviceCopy {
    /// The graph, on the device of its [`GpuGraph::generation`].
    graph: Mutex<Arc<GpuGraph>>,
    /// Bytes of its buffers (the same on every device).
    bytes: u64,
}

impl DeviceCopy {
    /// The graph on `opened`, first uploaded there from `host` if it was on a device that was lost. UNAVAILABLE if
    /// `opened` is itself a lost device that a later one replaced (the graph is on that one already).
    fn on(&self, opened: &Opened, host: &CpuAccel) -> Result<Arc<GpuGraph>> {
        let mut graph = self.graph.lock().unwrap_or_else(|e| e.into_inner());
        match graph.generation.cmp(&opened.generation) {
            std::cmp::Ordering::Equal => {}
            std::cmp::Ordering::Less => *graph = Arc::new(GpuGraph::upload(opened, host)?),
            std::cmp::Ordering::Greater => {
                let replaced = || Error::DeviceLost { device: opened.name.clone(), detail: "replaced".into() };
                return Err(opened.lost().unwrap_or_else(replaced));
            }
        }
        Ok(Arc::clone(&graph))
    }
}

impl BackendAccel for WgpuAccel {
    /// The host's arrays as allocated plus the device's buffers, which hold the arrays of every accel below it too
    /// (copies of an accel share the device buffers but each counts them).
    fn size_bytes(&self) -> u64 {
        self.host.size_bytes() + self.device.bytes
    }

    fn compacted_size_bytes(&self) -> u64 {
        self.host.compacted_size_bytes() + self.device.bytes
    }

    fn duplicate(&self) -> Box<dyn BackendAccel> {
        Box::new(self.clone())
    }

    fn bounds_during(&self, span: TimeSpan) -> Bounds {
        self.host.bounds_during(span)
    }

    fn triangle_vertices(&self, geom_id: u32, prim_id: u32) -> Option<[Vec3; 3]> {
        self.host.triangle_vertices(geom_id, prim_id)
    }

    fn encode(&self, children: &[Arc<Accel>], out: &mut Vec<u8>) -> Result<()> {
        self.host.encode(children, out)
    }

    fn host(&self) -> Option<&CpuAccel> {
        Some(&self.host)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl WgpuBackend {
    /// The adapter's device, opened on first use and again after it is lost.
    fn opened(&self) -> Result<Arc<Opened>> {
        self.gpu.open()
    }

    /// Uploads the graph of a host accel the CPU backend made.
    fn upload(&self, host: Box<dyn BackendAccel>) -> Result<Box<dyn BackendAccel>> {
        self.adopt(cpu(host.as_ref())?)
    }
}

/// An accel's bytes (host structure and device copy) at most, in multiples of the host structure's bound. The
/// device holds the host's triangles and ids once more, but its 4-wide nodes can take twice the bytes of the host's
/// binary nodes (every wide node has at least two lanes, 128 bytes for two 32-byte binary nodes at worst; a root
/// that is a leaf has one, within the bound's fixed bytes) and motion keys a box a lane, empty lanes included: at
/// most twice the host's bound, so three in all.
const DEVICE_COPY_BOUND: u64 = 3;

impl Backend for WgpuBackend {
    /// `name` is the adapter's, with its driver and type. wgpu reports neither memory nor compute units: a
    /// software adapter (lavapipe) reports the host's memory and threads; other adapters report 0 (unknown).
    fn info(&self) -> DeviceInfo {
        self.gpu.info()
    }

    /// The host's bound and [`DEVICE_COPY_BOUND`] − 1 times it for the device copy. Triangles whose corners
    /// cannot be bound on the adapter are refused here, before a build would make their host structure.
    fn compute_memory_usage(&self, inputs: &[BuildInput<'_>], options: &BuildOptions) -> Result<MemoryUsage> {
        let host = self.host.compute_memory_usage(inputs, options)?;
        let triangles = triangle_counts(inputs, options.motion.keys as usize)?.into_iter().sum::<usize>();
        let corners = DeviceArray::corner_bytes(triangles as u64, u64::from(options.motion.keys));
        // The adapter's limit: this runs where a call is answered, and opening the device there would hold it up.
        DeviceArray::CORNERS.check_fits(self.gpu.binding_limit(), corners)?;
        Ok(MemoryUsage { output_bytes: DEVICE_COPY_BOUND * host.output_bytes, ..host })
    }

    fn build(
        &self,
        inputs: &[BuildInput<'_>],
        options: &BuildOptions,
        go_on: &dyn Fn() -> bool,
    ) -> Result<Box<dyn BackendAccel>> {
        let host = self.host.build(inputs, options, go_on)?;
        // The upload, the last phase, up to twice the host's bytes on the device.
        if !go_on() {
            return Err(Error::Stopped);
        }
        self.upload(host)
    }

    /// The host's bound and [`DEVICE_COPY_BOUND`] − 1 times it for the instance accel's own arrays on the device.
    fn compute_instance_arrays_memory_usage(&self, instances: usize, options: &BuildOptions) -> Result<MemoryUsage> {
        let host = self.host.compute_instance_arrays_memory_usage(instances, options)?;
        Ok(MemoryUsage { output_bytes: DEVICE_COPY_BOUND * host.output_bytes, ..host })
    }

    /// The children's device graphs: an instance accel's or transform's graph holds every accel below it once more
    /// (a grandchild that two children share is counted twice here, held once).
    fn placed_children_bytes(&self, children: &[&Accel]) -> Result<u64> {
        children.iter().map(|child| Ok(wgpu_accel(child.backend_accel())?.device.bytes)).sum()
    }

    fn build_instances(&self, instances: &[PlacedInstance], options: &BuildOptions) -> Result<Box<dyn BackendAccel>> {
        self.upload(self.host.build_instances(instances, options)?)
    }

    fn update(&self, accel: &dyn BackendAccel, inputs: &[BuildInput<'_>]) -> Result<Box<dyn BackendAccel>> {
        self.upload(self.host.update(&wgpu_accel(accel)?.host, inputs)?)
    }

    fn update_instances(
        &self,
        accel: &dyn BackendAccel,
        instances: &[PlacedInstance],
    ) -> Result<Box<dyn BackendAccel>> {
        self.upload(self.host.update_instances(&wgpu_accel(accel)?.host, instances)?)
    }

    fn build_transform(&self, transform: &Transform, child: &Arc<Accel>) -> Result<Box<dyn BackendAccel>> {
        self.upload(self.host.build_transform(transform, child)?)
    }

    /// The CPU backend's payload layout: a wgpu accel serializes its host structure.
    fn layout_version(&self) -> u32 {
        self.host.layout_version()
    }

    fn decode(
        &self,
        shape: &Shape,
        options: &BuildOptions,
        payload: &[u8],
        children: &[Arc<Accel>],
    ) -> Result<Box<dyn BackendAccel>> {
        self.upload(self.host.decode(shape, options, payload, children)?)
    }

    /// Uploads the host structure's graph.
    fn adopt(&self, host: &CpuAccel) -> Result<Box<dyn BackendAccel>> {
        let opened = self.opened()?;
        let graph = GpuGraph::upload(&opened, host).map_err(|e| opened.or_lost(e))?;
        let device = DeviceCopy { bytes: graph.bytes(), graph: Mutex::new(Arc::new(graph)) };
        Ok(Box::new(WgpuAccel { host: host.clone(), device: Arc::new(device) }))
    }

    fn trace(&self, accel: &dyn BackendAccel, query: &Query, rays: &[u8], out: TraceOutput<'_>) -> Result<TraceStats> {
        self.trace_source(accel, query, RaySource::Packed(rays), out)
    }

    fn time_launches(
        &self,
        accel: &dyn BackendAccel,
        query: &Query,
        rays: &[u8],
        launches: u32,
    ) -> Result<Vec<Duration>> {
        query.output_layout(rays.len())?;
        self.on_device(wgpu_accel(accel)?, |opened, graph| batch::time_launches(opened, graph, query, rays, launches))
    }

    /// Camera and lidar generators' rays are made by the kernel; other generators' on the host.
    fn trace_source(
        &self,
        accel: &dyn BackendAccel,
        query: &Query,
        rays: RaySource<'_>,
        out: TraceOutput<'_>,
    ) -> Result<TraceStats> {
        let input = match rays {
            RaySource::Packed(rays) => Input::Packed(rays),
            RaySource::Generated { generator, first, count } => match DeviceGenerator::input(generator, first, count) {
                Some(input) => input,
                None => return host::trace_source(self, accel, query, rays, out),
            },
        };
        let layout = query.output_layout(rays.packed_len(query.ray_format.size()))?;
        out.check(&layout)?;
        let accel = wgpu_accel(accel)?;
        if layout.rays == 0 {
            // Nothing to trace: the device is neither opened nor given the accel (which may mean an upload).
            return Ok(TraceStats::default());
        }
        let output = Output::Hits(out);
        let plan = self.plan(query, layout.rays, &input, &output)?;
        self.run(accel, query, &plan, input, output)
    }

    /// Images and the counts of closest and any queries are reduced on the device ([`offload`]), with camera and
    /// lidar rays made there too; other reductions on the host.
    fn trace_reduced(
        &self,
        accel: &dyn BackendAccel,
        query: &Query,
        rays: RaySource<'_>,
        first_ray: u64,
        reduction: &Reduction,
    ) -> Result<(Partial, TraceStats)> {
        let Some(on_device) = OnDevice::of(reduction, query) else {
            return host::trace_reduced(self, accel, query, rays, first_ray, reduction, host::MOST_REDUCED_HIT_BYTES);
        };
        let traced = reduction.traced_query(query);
        // Checks the query and that packed rays are whole records, as a trace does.
        let count = traced.output_layout(rays.packed_len(query.ray_format.size()))?.rays;
        if count == 0 {
            // Reduced on the host: nothing is opened or uploaded for no rays.
            return host::trace_reduced(self, accel, query, rays, first_ray, reduction, host::MOST_REDUCED_HIT_BYTES);
        }
        let mut scratch = Vec::new();
        let input = match rays {
            RaySource::Generated { generator, first, count } => DeviceGenerator::input(generator, first, count),
            RaySource::Packed(_) => None,
        }
        .unwrap_or_else(|| Input::Packed(host::packed(rays, query.ray_format, &mut scratch)));
        let mut pixels = Vec::new();
        let output = match &on_device {
            OnDevice::Image(image) => {
                // Zeroed by the allocator (fresh pages are): a 16 MiB buffer cleared on this thread took milliseconds.
                pixels = vec![0; count / image.rays_per_pixel as usize * image.pixel_bytes()];
                Output::Pixels { image: *image, pixels: &mut pixels }
            }
            OnDevice::Counts => Output::Tallies,
        };
        // A pixel too large for one chunk is reduced on the host.
        let Ok(plan) = self.plan(&traced, count, &input, &output) else {
            return host::trace_reduced(self, accel, query, rays, first_ray, reduction, host::MOST_REDUCED_HIT_BYTES);
        };
        let stats = self.run(wgpu_accel(accel)?, &traced, &plan, input, output)?;
        Ok((on_device.partial(pixels, &stats), stats))
    }
}

impl WgpuBackend {
    /// How a batch of `rays` rays of `query`, from `input` into `output`, is cut into chunks on this adapter.
    fn plan(&self, query: &Query, rays: usize, input: &Input<'_>, output: &Output<'_>) -> Result<batch::Plan> {
        let default = match (input, output) {
            (Input::Generated(_), Output::Pixels { .. } | Output::Tallies) => batch::MAX_ON_DEVICE_CHUNK_RAYS,
            _ => batch::MAX_CHUNK_RAYS,
        };
        let limits = batch::ChunkLimits {
            binding_bytes: self.opened()?.binding_limit(self.options.max_binding_bytes),
            chunk_rays: self.options.max_chunk_rays.unwrap_or(default),
            trace_bytes: self.options.max_trace_bytes.unwrap_or(DEFAULT_MAX_TRACE_BYTES),
        };
        batch::Plan::new(query, rays, input, output, limits)
    }

    /// Traces the batch of `plan` through the slot pool.
    fn run(
        &self,
        accel: &WgpuAccel,
        query: &Query,
        plan: &batch::Plan,
        input: Input<'_>,
        output: Output<'_>,
    ) -> Result<TraceStats> {
        let ray_work = self.options.max_ray_work.unwrap_or(DEFAULT_MAX_RAY_WORK);
        self.on_device(accel, |opened, graph| batch::trace(opened, graph, query, plan, ray_work, input, output))
    }

    /// Runs `work` with the device and `accel`'s graph on it (uploaded anew if the device was lost since); an error
    /// of a device lost meanwhile is UNAVAILABLE.
    fn on_device<T>(&self, accel: &WgpuAccel, work: impl FnOnce(&Opened, &GpuGraph) -> Result<T>) -> Result<T> {
        let opened = self.opened()?;
        let done = accel.device.on(&opened, &accel.host).and_then(|graph| work(&opened, &graph));
        done.map_err(|e| opened.or_lost(e))
    }
}

/// The wgpu structure of `accel`; FAILED_PRECONDITION for an accel of another device.
fn wgpu_accel(accel: &dyn BackendAccel) -> Result<&WgpuAccel> {
    accel
        .as_any()
        .downcast_ref::<WgpuAccel>()
        .ok_or_else(|| Error::FailedPrecondition("the accel was built on another device".into()))
}

#[cfg(test)]
mod tests {
    use glam::Vec3A;

    use super::*;
    use crate::ErrorKind;
    use crate::format::{HitFormat, Ray, RayFormat};
    use crate::geometry::TriangleInput;
    use crate::mesh::Mesh;

    /// The tests here lose a device or fill the adapter's memory: one at a time.
    static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

    /// A backend on a device of its own, opened on the first adapter; `None` (and a note) without an adapter unless
    /// `RAYD_REQUIRE_GPU=1`.
    fn backend_alone() -> Option<WgpuBackend> {
        let Some(gpu) = device::adapters().first() else {
            assert_ne!(std::env::var("RAYD_REQUIRE_GPU").as_deref(), Ok("1"), "RAYD_REQUIRE_GPU=1 but no adapter");
            eprintln!("skipped: no wgpu adapter");
            return None;
        };
        Some(WgpuBackend { gpu: Arc::new(gpu.alone()), options: WgpuOptions::default(), host: CpuBackend::default() })
    }

    /// The bunny (`../shared/data/meshes/stanford-bunny.obj`), built and uploaded by `backend`.
    fn bunny(backend: &WgpuBackend) -> Result<Box<dyn BackendAccel>> {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/meshes/stanford-bunny.obj");
        let packed = Mesh::load_obj(path).unwrap_or_else(|e| panic!("{e}")).pack();
        let input: [BuildInput<'_>; 1] =
            [BuildInput::Triangles(TriangleInput::indexed(&packed.vertices, &packed.indices))];
        backend.build(&input, &BuildOptions::default(), &|| true)
    }

    /// `side`² rays along +z through the bunny's box, packed as origins and directions.
    fn rays_through(accel: &dyn BackendAccel, side: usize) -> Vec<u8> {
        let (low, high) = accel.bounds_during(TimeSpan::at(0.0));
        let (low, high) = (Vec3A::from(low), Vec3A::from(high));
        let format = RayFormat::OriginDirection;
        let mut packed = vec![0; side * side * format.size()];
        for (index, bytes) in packed.chunks_exact_mut(format.size()).enumerate() {
            let across = Vec3A::new((index % side) as f32 + 0.5, (index / side) as f32 + 0.5, 0.0) / side as f32;
            let origin = low + (high - low) * across - Vec3A::Z;
            format.encode(&Ray { origin, direction: Vec3A::Z, ..Ray::default() }, bytes);
        }
        packed
    }

    /// The closest hits of `rays` on `accel`, or the trace's error.
    fn closest_hits(backend: &WgpuBackend, accel: &dyn BackendAccel, rays: &[u8]) -> Result<Vec<u8>> {
        let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriidUV);
        let layout = query.output_layout(rays.len())?;
        let mut hits = vec![0xEE; layout.hits];
        backend.trace(accel, &query, rays, TraceOutput { hits: &mut hits, counts: &mut [] })?;
        Ok(hits)
    }

    #[test]
    fn a_lost_device_fails_its_call_unavailable_and_the_next_call_traces_on_a_new_device() {
        let _alone = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
        let Some(backend) = backend_alone() else { return };
        let accel = bunny(&backend).unwrap();
        let copy = accel.duplicate();
        let rays = rays_through(accel.as_ref(), 64);
        let before = closest_hits(&backend, accel.as_ref(), &rays).unwrap();
        let first = backend.opened().unwrap();
        assert!(before.chunks_exact(16).any(|hit| hit[0..4] != f32::INFINITY.to_le_bytes()), "some rays hit");

        first.device.destroy();
        // Empty traces answer without opening a device or uploading the accel to it.
        let graph = |accel: &dyn BackendAccel| Arc::clone(&wgpu_accel(accel).unwrap().device.graph.lock().unwrap());
        assert!(closest_hits(&backend, accel.as_ref(), &[]).unwrap().is_empty());
        let counts = Query::closest(RayFormat::OriginDirection, HitFormat::T);
        let empty = RaySource::Packed(&[]);
        backend.trace_reduced(accel.as_ref(), &counts, empty, 0, &Reduction::Counts).unwrap();
        assert_eq!(graph(accel.as_ref()).generation, first.generation, "still the first device's upload");
        let failed = closest_hits(&backend, accel.as_ref(), &rays).unwrap_err();
        assert_eq!(failed.kind(), ErrorKind::Unavailable, "{failed}");
        assert!(failed.to_string().starts_with("wgpu:0 was lost (Destroyed"), "{failed}");

        assert_eq!(closest_hits(&backend, accel.as_ref(), &rays).unwrap(), before, "uploaded anew, traced as before");
        let second = backend.opened().unwrap();
        assert_ne!(second.generation, first.generation, "a new device");
        assert_eq!(graph(accel.as_ref()).generation, second.generation, "on the new device");
        assert_eq!(closest_hits(&backend, copy.as_ref(), &rays).unwrap(), before);
        assert!(Arc::ptr_eq(&graph(accel.as_ref()), &graph(copy.as_ref())), "a copy shares the new upload");
        let stale = first.lost().expect("the first device is lost");
        assert_eq!(stale.kind(), ErrorKind::Unavailable);
        let rebuilt = bunny(&backend).unwrap();
        assert_eq!(closest_hits(&backend, rebuilt.as_ref(), &rays).unwrap(), before, "accels built after the loss");
    }

    #[test]
    fn a_device_that_does_not_answer_in_time_is_taken_as_lost_and_opened_anew() {
        let _alone = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
        let Some(backend) = backend_alone() else { return };
        // No time at all to answer: a trace whose chunk is not done when it first looks takes the device as hung.
        let impatient = WgpuBackend { gpu: Arc::new(backend.gpu.alone().answering_within(Duration::ZERO)), ..backend };
        let accel = bunny(&impatient).unwrap();
        let rays = rays_through(accel.as_ref(), 512);
        let first = impatient.opened().unwrap();
        // A fast GPU may finish a chunk before the trace first looks: a few tries (lavapipe never is that fast).
        let hung = (0..10).find_map(|_| closest_hits(&impatient, accel.as_ref(), &rays).err());
        let hung = hung.expect("a trace that found its chunk unanswered");
        assert_eq!(hung.kind(), ErrorKind::Unavailable, "{hung}");
        assert!(hung.to_string().contains("Hung: no answer to a trace in 0ns"), "{hung}");
        assert!(first.lost().is_some(), "the device is taken as lost");
        let second = impatient.opened().unwrap();
        assert_ne!(second.generation, first.generation, "the next call opens a new device");
    }

    #[test]
    #[ignore = "fills the GPU's memory: run it with --ignored on a GPU that nothing else uses"]
    fn running_out_of_device_memory_is_resource_exhausted_and_the_device_goes_on() {
        let _alone = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
        let Some(backend) = backend_alone() else { return };
        if backend.gpu.software() {
            eprintln!("skipped: a software adapter's memory is the host's, which this test would fill");
            return;
        }
        let accel = bunny(&backend).unwrap();
        let (rays, more_rays) = (rays_through(accel.as_ref(), 64), rays_through(accel.as_ref(), 1024));
        let before = closest_hits(&backend, accel.as_ref(), &rays).unwrap();
        let opened = backend.opened().unwrap();
        // The device filled with buffers of halving sizes, until not even a MiB more is made.
        let mut filler = Vec::new();
        let mut size = opened.device.limits().max_buffer_size.min(1 << 32);
        while size >= 1 << 20 {
            let descriptor = wgpu::BufferDescriptor {
                label: None,
                size,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            };
            match opened.checked("filling the device", || opened.device.create_buffer(&descriptor)) {
                Ok(buffer) => filler.push(buffer),
                Err(full) => {
                    assert_eq!(full.kind(), ErrorKind::ResourceExhausted, "{full}");
                    size /= 2;
                }
            }
        }
        assert!(filler.len() > 1, "{} buffers filled the device", filler.len());

        let Err(refused) = bunny(&backend) else { panic!("an accel was uploaded to a full device") };
        assert_eq!(refused.kind(), ErrorKind::ResourceExhausted, "{refused}");
        assert!(refused.to_string().starts_with("wgpu:0 ran out of memory uploading an accel: "), "{refused}");
        let refused = closest_hits(&backend, accel.as_ref(), &more_rays).unwrap_err();
        assert_eq!(refused.kind(), ErrorKind::ResourceExhausted, "{refused}");
        assert!(refused.to_string().starts_with("wgpu:0 ran out of memory making a trace's buffers: "), "{refused}");

        drop(filler);
        assert_eq!(closest_hits(&backend, accel.as_ref(), &rays).unwrap(), before, "the device goes on");
        let rebuilt = bunny(&backend).unwrap();
        assert_eq!(closest_hits(&backend, rebuilt.as_ref(), &rays).unwrap(), before);
        let all = closest_hits(&backend, accel.as_ref(), &more_rays).unwrap();
        assert_eq!(all.len(), 1024 * 1024 * 16);
    }
}
