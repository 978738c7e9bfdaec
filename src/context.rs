//! Devices and contexts. A context belongs to one device and owns everything built on it: its accels and
//! buffers are freed when they are destroyed, or when the context is dropped.

use std::collections::HashSet;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::Duration;

use bytes::Bytes;
use dashmap::DashMap;
use glam::Vec3;

use crate::accel::{AccelInfo, AccelKind, BuildFlags, BuildOptions, MemoryUsage, TRANSFORM_FLAGS};
use crate::backend::cpu::CpuBackend;
#[cfg(feature = "wgpu")]
use crate::backend::wgpu::WgpuOptions;
use crate::backend::{Backend, BackendAccel, BackendKind, DeviceInfo, RaySource, Shape};
use crate::error::{Error, Result};
use crate::geometry::motion::TimeSpan;
use crate::geometry::{
    BuildInput, Instance, PlacedInstance, Structure, Transform, TransformInput, check_depth, place, triangle_counts,
};
use crate::query::{Query, TraceOutput, TraceStats};
use crate::reduce::{Partial, Reduction};

/// A device that contexts can be created on.
#[derive(Clone)]
pub struct Device {
    /// What the device is.
    info: DeviceInfo,
    /// The implementation every context on this device calls.
    backend: Arc<dyn Backend>,
}

impl std::fmt::Debug for Device {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Device").field("info", &self.info).finish()
    }
}

impl Device {
    /// The CPU device, always present, its rays held to the default work ([`Device::cpu_with_max_ray_work`]).
    pub fn cpu() -> Device {
        Device::cpu_with_max_ray_work(crate::backend::DEFAULT_MAX_RAY_WORK)
    }

    /// The CPU device, each of its rays taking at most `max_ray_work` node visits and triangle tests
    /// ([`CpuBackend::with_max_ray_work`]).
    pub fn cpu_with_max_ray_work(max_ray_work: u32) -> Device {
        let backend = Arc::new(CpuBackend::with_max_ray_work(max_ray_work));
        Device { info: backend.info(), backend }
    }

    /// Every device of this machine: the CPU first, then (with the `wgpu` feature) every wgpu adapter as
    /// `wgpu:0`, `wgpu:1`, … ([`Device::wgpu`]).
    pub fn all() -> Vec<Device> {
        let cpu = std::iter::once(Device::cpu());
        #[cfg(feature = "wgpu")]
        let cpu = cpu.chain(Device::wgpu(WgpuOptions::default()));
        cpu.collect()
    }

    /// A device for every adapter that wgpu enumerates on the backends of `WGPU_BACKEND` (Vulkan when unset), with
    /// `options`; none on a machine without one. Adapters are enumerated once a process, and each adapter's wgpu
    /// device is opened once, on first use, and shared by every device made for it.
    #[cfg(feature = "wgpu")]
    pub fn wgpu(options: WgpuOptions) -> Vec<Device> {
        crate::backend::wgpu::backends(options)
            .into_iter()
            .map(|backend| {
                let backend: Arc<dyn Backend> = Arc::new(backend);
                Device { info: backend.info(), backend }
            })
            .collect()
    }

    /// What the device is.
    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }
}

/// Names an accel within its context.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct AccelHandle(pub u64);

/// Names a buffer within its context.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BufferHandle(pub u64);

/// Bytes counted against a context while the object that holds this lives.
#[derive(Debug)]
struct Charge {
    /// Bytes charged.
    bytes: u64,
    /// The context's running total.
    total: Arc<AtomicU64>,
}

impl Charge {
    /// Adds `bytes` to `total` until dropped.
    fn new(bytes: u64, total: &Arc<AtomicU64>) -> Charge {
        total.fetch_add(bytes, Ordering::Relaxed);
        Charge { bytes, total: Arc::clone(total) }
    }
}

impl Drop for Charge {
    fn drop(&mut self) {
        self.total.fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

/// What an accel keeps of its inputs besides the backend's structure.
#[derive(Debug, Clone, Default)]
pub(crate) struct Retained {
    /// With `ALLOW_UPDATE`, a geometry accel's structure, which updates must keep.
    pub(crate) structure: Option<Structure>,
    /// A transform's input as given (its checked form normalizes SRT quaternions), for serialization.
    pub(crate) transform: Option<TransformInput>,
}

/// A built acceleration structure. Traces may hold it while it is destroyed; its memory is freed when the last
/// holder lets go.
pub struct Accel {
    /// Its handle in the context.
    handle: AccelHandle,
    /// Sizes, counts and options.
    info: AccelInfo,
    /// The backend's structure.
    data: Box<dyn BackendAccel>,
    /// The backend that built it.
    backend: BackendKind,
    /// The device it lives on (its backend's instance): accels of two devices of one backend (two GPUs) do not
    /// share memory.
    home: Arc<dyn Backend>,
    /// The accels it places (its instances' children, a transform's child): kept alive while it lives.
    children: Vec<Arc<Accel>>,
    /// Live accels that place this one (in any of its versions); while there are any it cannot be destroyed.
    referrers: Arc<AtomicUsize>,
    /// Set when an update replaced this version: accels that still place it are stale and refuse traces.
    superseded: AtomicBool,
    /// Set when it was restored over a newer version of a child than it was built over: it refuses traces
    /// until it is updated.
    stale: AtomicBool,
    /// What it keeps of its inputs besides the backend's structure.
    retained: Retained,
    /// Keeps the context's memory total honest.
    _charge: Charge,
}

impl Drop for Accel {
    fn drop(&mut self) {
        for child in &self.children {
            child.referrers.fetch_sub(1, Ordering::AcqRel);
        }
    }
}

impl std::fmt::Debug for Accel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Accel").field("handle", &self.handle).field("info", &self.info).finish()
    }
}

impl Accel {
    /// Its handle.
    pub fn handle(&self) -> AccelHandle {
        self.handle
    }

    /// Sizes, counts and build options.
    pub fn info(&self) -> &AccelInfo {
        &self.info
    }

    /// Fails with FAILED_PRECONDITION if this accel, or one below it, places an accel in a version an update has
    /// replaced: its results would be stale.
    pub fn check_current(&self) -> Result<()> {
        if self.stale.load(Ordering::Acquire) {
            return Err(Error::FailedPrecondition(format!(
                "accel {} was saved over an older version of an accel it places (updated since): update accel {} \
                 (with the same children) to trace it",
                self.handle.0, self.handle.0
            )));
        }
        for child in &self.children {
            if child.superseded.load(Ordering::Acquire) {
                return Err(Error::FailedPrecondition(format!(
                    "accel {} places accel {} as it was before an update: update accel {} (with the same children) \
                     to trace the new one",
                    self.handle.0, child.handle.0, self.handle.0
                )));
            }
            child.check_current()?;
        }
        Ok(())
    }

    /// The accels it places (its instances' children or a transform's child), each once.
    pub fn children(&self) -> &[Arc<Accel>] {
        &self.children
    }

    /// Whether `other` is a version of this accel (an update keeps the accel's handle and its count of referrers;
    /// a copy, a load or an accel of another context with the same handle number is another accel).
    pub(crate) fn is_version_of(&self, other: &Accel) -> bool {
        Arc::ptr_eq(&self.referrers, &other.referrers)
    }

    /// Fails with FAILED_PRECONDITION if an update replaced this version of the accel, or if it or one below it
    /// is stale ([`Accel::check_current`]).
    pub(crate) fn check_latest(&self) -> Result<()> {
        if self.superseded.load(Ordering::Acquire) {
            return Err(Error::FailedPrecondition(format!(
                "this version of accel {} was replaced by an update: use its current version",
                self.handle.0
            )));
        }
        self.check_current()
    }

    /// The backend's structure, for backends tracing through instances.
    pub(crate) fn backend_accel(&self) -> &dyn BackendAccel {
        self.data.as_ref()
    }

    /// The backend that built it.
    pub(crate) fn backend_kind(&self) -> BackendKind {
        self.backend
    }

    /// What it keeps of its inputs.
    pub(crate) fn retained(&self) -> &Retained {
        &self.retained
    }

    /// The corners of triangle `prim_id` (as hits report it) of geometry `geom_id`. Needs
    /// `ALLOW_RANDOM_VERTEX_ACCESS` at build.
    pub fn triangle_vertices(&self, geom_id: u32, prim_id: u32) -> Result<[Vec3; 3]> {
        if !self.info.options.flags.contains(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS) {
            return Err(Error::FailedPrecondition("the accel was built without ALLOW_RANDOM_VERTEX_ACCESS".into()));
        }
        self.data.triangle_vertices(geom_id, prim_id).ok_or_else(|| Error::InvalidQuery {
            field: "prim_id",
            rule: format!("geometry {geom_id} has no primitive {prim_id}"),
        })
    }
}

/// The kind of accel a transform input makes.
fn transform_kind(transform: &TransformInput) -> AccelKind {
    match transform {
        TransformInput::Static(_) => AccelKind::Transform,
        TransformInput::MatrixMotion { .. } => AccelKind::MatrixMotionTransform,
        TransformInput::SrtMotion { .. } => AccelKind::SrtMotionTransform,
    }
}

/// No live accel has `handle`.
fn not_found(handle: AccelHandle) -> Error {
    Error::NotFound { what: "accel", id: handle.0 }
}

/// Accel `handle` cannot be destroyed: `referrers` live accels place it.
fn placed_by(handle: AccelHandle, referrers: usize) -> Error {
    Error::FailedPrecondition(format!(
        "accel {} is placed by {referrers} live instance accel(s) or transform(s); destroy them first",
        handle.0
    ))
}

/// The bit of an accel's referrers that [`Context::destroy_accel`] sets, in the same step as it finds none: a build
/// that would place the accel after that is refused ([`refer_to`]).
const DESTROYED: usize = 1 << (usize::BITS - 1);

/// `children` without repeats (in the order of their first appearance), each counting one more referrer;
/// FAILED_PRECONDITION, counting none, if one was destroyed since it was looked up. (While the count is taken back,
/// a destroy of a child counted so far is refused, as it would be had the build been kept.)
fn refer_to(children: Vec<Arc<Accel>>) -> Result<Vec<Arc<Accel>>> {
    let mut seen = HashSet::with_capacity(children.len());
    let children: Vec<Arc<Accel>> = children.into_iter().filter(|c| seen.insert(Arc::as_ptr(c))).collect();
    for (counted, child) in children.iter().enumerate() {
        if child.referrers.fetch_add(1, Ordering::AcqRel) & DESTROYED != 0 {
            for referred in &children[..=counted] {
                referred.referrers.fetch_sub(1, Ordering::AcqRel);
            }
            return Err(Error::FailedPrecondition(format!(
                "accel {} was destroyed after it was named to be placed",
                child.handle.0
            )));
        }
    }
    Ok(children)
}

/// A buffer held by a context.
#[derive(Debug)]
struct Buffer {
    /// The bytes (shared, never copied).
    data: Bytes,
    /// Keeps the context's memory total honest.
    _charge: Charge,
}

/// Everything one user has built on one device.
#[derive(Debug)]
pub struct Context {
    /// The device its work runs on.
    device: Device,
    /// Live accels by handle.
    accels: DashMap<AccelHandle, Arc<Accel>>,
    /// Live buffers by handle.
    buffers: DashMap<BufferHandle, Buffer>,
    /// The next handle to give out (accels and buffers share the sequence, so a handle is never reused; contexts
    /// made by [`Context::sharing_handles`] share it too, so their handles never collide).
    next_handle: Arc<AtomicU64>,
    /// Bytes held by live accels and buffers.
    bytes_in_use: Arc<AtomicU64>,
}

impl Context {
    /// An empty context on `device`.
    pub fn new(device: Device) -> Context {
        Context {
            device,
            accels: DashMap::new(),
            buffers: DashMap::new(),
            next_handle: Arc::new(AtomicU64::new(1)),
            bytes_in_use: Arc::new(AtomicU64::new(0)),
        }
    }

    /// An empty context on `device` that takes its handles from `other`'s sequence: one user's contexts on several
    /// devices then never give out the same handle.
    pub fn sharing_handles(device: Device, other: &Context) -> Context {
        Context { next_handle: Arc::clone(&other.next_handle), ..Context::new(device) }
    }

    /// The device the context runs on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The implementation the context's work runs on.
    pub(crate) fn backend(&self) -> &dyn Backend {
        self.device.backend.as_ref()
    }

    /// Bytes held by the context's live accels and buffers.
    pub fn memory_in_use(&self) -> u64 {
        self.bytes_in_use.load(Ordering::Relaxed)
    }

    /// Upper bounds of the memory that building these inputs would use.
    pub fn compute_memory_usage(&self, inputs: &[BuildInput<'_>], options: &BuildOptions) -> Result<MemoryUsage> {
        self.device.backend.compute_memory_usage(inputs, options)
    }

    /// Upper bounds of the memory that building an instance accel over `instances` would use: its own arrays
    /// ([`Context::compute_instance_arrays_memory_usage`]) and, on a device whose instance accels hold copies of what
    /// they place (wgpu), those copies, in its output and once more in its working memory while they are uploaded.
    /// FAILED_PRECONDITION for a child of another device, as the build.
    pub fn compute_instance_memory_usage(&self, instances: &[Instance], options: &BuildOptions) -> Result<MemoryUsage> {
        let own = self.compute_instance_arrays_memory_usage(instances.len(), options)?;
        self.with_placed_children(own, instances.iter().map(|instance| &instance.child))
    }

    /// Upper bounds of the memory that the arrays of an instance accel of `count` instances would take, whatever
    /// they place: a lower bound of what its build takes where children are copied
    /// ([`Context::compute_instance_memory_usage`]), and its bound where they are not (the CPU).
    pub fn compute_instance_arrays_memory_usage(&self, count: usize, options: &BuildOptions) -> Result<MemoryUsage> {
        self.device.backend.compute_instance_arrays_memory_usage(count, options)
    }

    /// Upper bounds of the memory that building `transform` over `child` would use: an instance accel's of one
    /// instance, its motion keys twice, as built and as given (kept for updates and saves; no larger a key), and its
    /// boxes at the keys. A transform that its build would refuse is refused here too.
    pub fn compute_transform_memory_usage(
        &self,
        transform: &TransformInput,
        child: &Arc<Accel>,
        options: &BuildOptions,
    ) -> Result<MemoryUsage> {
        transform.check()?;
        let one = self.compute_instance_arrays_memory_usage(1, options)?;
        let keys = 2 * transform.key_bytes() + transform.key_bounds_bytes();
        self.with_placed_children(MemoryUsage { output_bytes: one.output_bytes + keys, ..one }, [child].into_iter())
    }

    /// `own` with what an instance accel or transform holds for the distinct accels among `children` beyond its own
    /// arrays ([`Backend::placed_children_bytes`]): in its output, and in its working memory.
    fn with_placed_children<'a>(
        &self,
        own: MemoryUsage,
        children: impl Iterator<Item = &'a Arc<Accel>>,
    ) -> Result<MemoryUsage> {
        let mut seen = HashSet::new();
        let mut distinct = Vec::new();
        for child in children.filter(|child| seen.insert(Arc::as_ptr(child))) {
            self.check_device(child, "places")?;
            distinct.push(child.as_ref());
        }
        let copies = self.device.backend.placed_children_bytes(&distinct)?;
        Ok(MemoryUsage {
            output_bytes: own.output_bytes.saturating_add(copies),
            temp_bytes: own.temp_bytes.saturating_add(copies),
            ..own
        })
    }

    /// Validates the inputs and builds an accel over them. No lock is held while building, so traces on other
    /// accels go on.
    pub fn build_accel(&self, inputs: &[BuildInput<'_>], options: &BuildOptions) -> Result<Arc<Accel>> {
        self.build_accel_while(inputs, options, &|| true)
    }

    /// As [`Context::build_accel`], asking `go_on` between the build's phases whether to go on: told no, the build
    /// stops there with [`Error::Stopped`] (a server stops a build whose caller has gone). obvhs's tree build, most of
    /// a build's time, cannot stop midway: told no during it, the build stops once it ends.
    pub fn build_accel_while(
        &self,
        inputs: &[BuildInput<'_>],
        options: &BuildOptions,
        go_on: &dyn Fn() -> bool,
    ) -> Result<Arc<Accel>> {
        let data = self.device.backend.build(inputs, options, go_on)?;
        let keys = options.motion.keys as usize;
        let shape = Shape {
            kind: AccelKind::Triangles,
            triangle_count: triangle_counts(inputs, keys)?.iter().sum::<usize>() as u64,
            geometry_count: inputs.len() as u32,
            instance_count: 0,
        };
        let structure =
            options.flags.contains(BuildFlags::ALLOW_UPDATE).then(|| Structure::of(inputs, keys)).transpose()?;
        self.register(shape, options, data, Vec::new(), Retained { structure, transform: None })
    }

    /// Updates (refits) a geometry accel built with `ALLOW_UPDATE` with new vertex positions of the same structure
    /// (per input: triangle count, indices, masks, flags, offset, as many motion keys; FAILED_PRECONDITION naming
    /// the difference otherwise). The accel keeps its handle; traces already running finish on the old version,
    /// and accels that place it refuse traces until they are updated too. A triangle without area now is never
    /// hit, and one built without area is hit once an update gives it some.
    pub fn update_accel(&self, accel: &Accel, inputs: &[BuildInput<'_>]) -> Result<Arc<Accel>> {
        let built = accel.retained.structure.as_ref().ok_or_else(|| {
            Error::FailedPrecondition("the accel is not a geometry accel built with ALLOW_UPDATE".into())
        })?;
        let keys = accel.info.options.motion.keys as usize;
        let difference = match Structure::key_difference(inputs, keys) {
            Some(keys_differ) => Some(keys_differ),
            None => built.difference(&Structure::of(inputs, keys)?),
        };
        if let Some(difference) = difference {
            return Err(Error::FailedPrecondition(format!(
                "the update's structure differs from the build's: {difference}"
            )));
        }
        let data = self.device.backend.update(accel.data.as_ref(), inputs)?;
        self.replace(accel, data, Vec::new(), accel.retained.clone())
    }

    /// Updates (refits) an instance accel built with `ALLOW_UPDATE` with new instances: as many, each placing the
    /// same accel (in its current version), with new transforms, ids, masks or flags. As [`Context::update_accel`]
    /// otherwise.
    pub fn update_instance_accel(&self, accel: &Accel, instances: &[Instance]) -> Result<Arc<Accel>> {
        let placed: Vec<PlacedInstance> =
            instances.iter().enumerate().map(|(index, instance)| place(index, instance)).collect::<Result<_>>()?;
        let data = self.device.backend.update_instances(accel.data.as_ref(), &placed)?;
        self.replace(accel, data, placed.into_iter().map(|p| p.child).collect(), accel.retained.clone())
    }

    /// Updates a transform with new keys (or a new matrix) over `child`, which must be the accel it places (in its
    /// current version). The transform keeps its kind and motion options (FAILED_PRECONDITION otherwise). As
    /// [`Context::update_accel`] otherwise.
    pub fn update_transform(
        &self,
        accel: &Accel,
        transform: &TransformInput,
        child: &Arc<Accel>,
    ) -> Result<Arc<Accel>> {
        match accel.children.as_slice() {
            [placed] if transform_kind(transform) == accel.info.kind && placed.is_version_of(child) => {}
            _ => {
                return Err(Error::FailedPrecondition(format!(
                    "accel {} is not a {:?} placing accel {}",
                    accel.handle.0,
                    transform_kind(transform),
                    child.handle.0
                )));
            }
        }
        let checked = transform.check()?;
        if checked.motion() != accel.info.options.motion {
            return Err(Error::FailedPrecondition(format!(
                "the update's motion options {:?} differ from the transform's {:?}",
                checked.motion(),
                accel.info.options.motion
            )));
        }
        let data = self.device.backend.build_transform(&checked, child)?;
        let retained = Retained { structure: None, transform: Some(transform.clone()) };
        self.replace(accel, data, vec![Arc::clone(child)], retained)
    }

    /// Builds an instance accel over already-built accels (geometry accels, instance accels, transforms, of this
    /// device). Each transform must be finite and invertible, and the graph at most
    /// [`MAX_GRAPH_DEPTH`](crate::geometry::MAX_GRAPH_DEPTH) levels deep. The children cannot be destroyed while
    /// the instance accel lives.
    pub fn build_instance_accel(&self, instances: &[Instance], options: &BuildOptions) -> Result<Arc<Accel>> {
        options.validate()?;
        let placed: Vec<PlacedInstance> =
            instances.iter().enumerate().map(|(index, instance)| place(index, instance)).collect::<Result<_>>()?;
        for instance in &placed {
            self.check_device(&instance.child, "places")?;
        }
        let data = self.device.backend.build_instances(&placed, options)?;
        let shape = Shape {
            kind: AccelKind::Instances,
            triangle_count: 0,
            geometry_count: 0,
            instance_count: placed.len() as u64,
        };
        let children = placed.into_iter().map(|p| p.child).collect();
        self.register(shape, options, data, children, Retained::default())
    }

    /// Places `child` under a transform (static, matrix motion or SRT motion), as a traversable that instances can
    /// point at; its info's motion options are the transform's. A transform can always be updated and compacted (a
    /// compacted copy is a copy): its flags are [`TRANSFORM_FLAGS`]. The child cannot be destroyed while the
    /// transform lives.
    pub fn build_transform(&self, transform: &TransformInput, child: &Arc<Accel>) -> Result<Arc<Accel>> {
        let checked: Transform = transform.check()?;
        check_depth(child.info.depth, "child", None)?;
        self.check_device(child, "places")?;
        let data = self.device.backend.build_transform(&checked, child)?;
        let shape = Shape { kind: transform_kind(transform), triangle_count: 0, geometry_count: 0, instance_count: 0 };
        let options = BuildOptions { flags: TRANSFORM_FLAGS, motion: checked.motion() };
        let retained = Retained { structure: None, transform: Some(transform.clone()) };
        self.register(shape, &options, data, vec![Arc::clone(child)], retained)
    }

    /// Copies `source` (from this or another context) into this context, as `rtpModelCopy` does; with `compact`, as
    /// `optixAccelCompact` does: the copy then occupies at most the source's `compacted_size_bytes`, and the source
    /// must allow compaction. The copy traces as the source does, has its options and places the same children.
    /// (Every copy is exact-size on the CPU backend.) A geometry accel may be copied from another device (its host
    /// structure is copied, or uploaded); an instance accel or transform only to a device that reads its children
    /// where they stay: its own, or the CPU from the CPU (FAILED_PRECONDITION: copy the children, then build it
    /// there). Two GPU devices of one backend share no memory.
    pub fn copy_accel(&self, source: &Accel, compact: bool) -> Result<Arc<Accel>> {
        if compact && !source.info.options.flags.contains(BuildFlags::ALLOW_COMPACTION) {
            return Err(Error::FailedPrecondition("compaction needs an accel built with ALLOW_COMPACTION".into()));
        }
        let data = if self.shares_memory_with(source) {
            source.data.duplicate()
        } else {
            let host = source.data.host().filter(|_| source.info.kind == AccelKind::Triangles).ok_or_else(|| {
                Error::FailedPrecondition(format!(
                    "copying a {:?} {:?} accel to another {:?} device is not supported (geometry accels are): copy \
                     its children and build it there",
                    source.backend, source.info.kind, self.device.info.kind
                ))
            })?;
            self.device.backend.adopt(host)?
        };
        let shape = Shape {
            kind: source.info.kind,
            triangle_count: source.info.triangle_count,
            geometry_count: source.info.geometry_count,
            instance_count: source.info.instance_count,
        };
        let copy =
            self.register(shape, &source.info.options, data, source.children.clone(), source.retained.clone())?;
        if source.stale.load(Ordering::Acquire) {
            // It places what the source places, as old: it refuses traces as the source does.
            self.mark_stale(&copy);
        }
        Ok(copy)
    }

    /// FAILED_PRECONDITION unless `accel` lives where this context's device can read it (an instance accel or
    /// transform places accels of its own device, a trace traces them): `use_` says which (`places`, `traces`).
    fn check_device(&self, accel: &Accel, use_: &str) -> Result<()> {
        if !self.shares_memory_with(accel) {
            return Err(Error::FailedPrecondition(format!(
                "accel {} is a {:?} accel of another device: a {:?} device {use_} accels of its own device only",
                accel.handle.0, accel.backend, self.device.info.kind
            )));
        }
        Ok(())
    }

    /// Whether this context's device reads `accel` where it is: it lives on this device, or both are the CPU's
    /// (host memory is one).
    pub(crate) fn shares_memory_with(&self, accel: &Accel) -> bool {
        let cpu = BackendKind::Cpu;
        std::ptr::addr_eq(Arc::as_ptr(&accel.home), Arc::as_ptr(&self.device.backend))
            || (accel.backend == cpu && self.device.info.kind == cpu)
    }

    /// Gives a built (or deserialized) structure a handle, its description and its memory charge; counts it as a
    /// referrer of each of its distinct `children` (FAILED_PRECONDITION if one was destroyed meanwhile).
    pub(crate) fn register(
        &self,
        shape: Shape,
        options: &BuildOptions,
        data: Box<dyn BackendAccel>,
        children: Vec<Arc<Accel>>,
        retained: Retained,
    ) -> Result<Arc<Accel>> {
        let children = refer_to(children)?;
        let size_bytes = data.size_bytes();
        let info = AccelInfo {
            kind: shape.kind,
            size_bytes,
            triangle_count: shape.triangle_count,
            geometry_count: shape.geometry_count,
            instance_count: shape.instance_count,
            depth: 1 + children.iter().map(|c| c.info.depth).max().unwrap_or(0),
            options: *options,
            compacted_size_bytes: options
                .flags
                .contains(BuildFlags::ALLOW_COMPACTION)
                .then(|| data.compacted_size_bytes()),
            bounds: data.bounds_during(TimeSpan::ALL),
        };
        let handle = AccelHandle(self.next_handle.fetch_add(1, Ordering::Relaxed));
        let accel = Arc::new(Accel {
            handle,
            info,
            data,
            backend: self.device.info.kind,
            home: Arc::clone(&self.device.backend),
            children,
            referrers: Arc::default(),
            superseded: AtomicBool::new(false),
            stale: AtomicBool::new(false),
            retained,
            _charge: Charge::new(size_bytes, &self.bytes_in_use),
        });
        self.accels.insert(handle, Arc::clone(&accel));
        Ok(accel)
    }

    /// Puts `data` (an update of `old`, placing `children`, keeping `retained`) in `old`'s place: same handle and
    /// options, the referrers shared; `old` is marked superseded. `old` must be the accel's current version
    /// (FAILED_PRECONDITION otherwise: updating a replaced version would drop the update made since).
    fn replace(
        &self,
        old: &Accel,
        data: Box<dyn BackendAccel>,
        children: Vec<Arc<Accel>>,
        retained: Retained,
    ) -> Result<Arc<Accel>> {
        let size_bytes = data.size_bytes();
        let info = AccelInfo {
            size_bytes,
            compacted_size_bytes: old.info.compacted_size_bytes.map(|_| data.compacted_size_bytes()),
            bounds: data.bounds_during(TimeSpan::ALL),
            ..old.info
        };
        let accel = Arc::new(Accel {
            handle: old.handle,
            info,
            data,
            backend: old.backend,
            home: Arc::clone(&old.home),
            children: refer_to(children)?,
            referrers: Arc::clone(&old.referrers),
            superseded: AtomicBool::new(false),
            stale: AtomicBool::new(false),
            retained,
            _charge: Charge::new(size_bytes, &self.bytes_in_use),
        });
        let mut current = self.accels.get_mut(&old.handle).ok_or_else(|| not_found(old.handle))?;
        if !std::ptr::eq(Arc::as_ptr(&current), old) {
            return Err(Error::FailedPrecondition(format!(
                "this version of accel {} was replaced by an update: update its current version",
                old.handle.0
            )));
        }
        *current = Arc::clone(&accel);
        drop(current);
        old.superseded.store(true, Ordering::Release);
        Ok(accel)
    }

    /// Puts `old` back in the place of `new`, its update ([`Context::update_accel`] and the like), when what had to
    /// follow the update failed (a server could not store it): `old` is the current version again, accels placing
    /// it trace again, and `new` is superseded. FAILED_PRECONDITION when `new` is no longer the current version.
    pub fn undo_update(&self, old: &Arc<Accel>, new: &Accel) -> Result<()> {
        let mut current = self.accels.get_mut(&old.handle).ok_or_else(|| not_found(old.handle))?;
        if old.handle != new.handle || !std::ptr::eq(Arc::as_ptr(&current), new) {
            return Err(Error::FailedPrecondition(format!(
                "this update of accel {} is not its current version: it cannot be undone",
                old.handle.0
            )));
        }
        *current = Arc::clone(old);
        drop(current);
        new.superseded.store(true, Ordering::Release);
        old.superseded.store(false, Ordering::Release);
        Ok(())
    }

    /// Marks `accel` stale: it places an older version of a child than the one it now places (as when it is
    /// restored after that child was updated), so it refuses traces until it is updated.
    pub fn mark_stale(&self, accel: &Accel) {
        accel.stale.store(true, Ordering::Release);
    }

    /// Makes every handle given out from now on greater than `past` (for restoring objects under the handles
    /// they had, without collisions).
    pub fn advance_handles(&self, past: u64) {
        self.next_handle.fetch_max(past.saturating_add(1), Ordering::Relaxed);
    }

    /// The accel named by `handle`.
    pub fn accel(&self, handle: AccelHandle) -> Result<Arc<Accel>> {
        self.accels.get(&handle).map(|a| Arc::clone(&a)).ok_or_else(|| not_found(handle))
    }

    /// Handles of the live accels, in creation order.
    pub fn accel_handles(&self) -> Vec<AccelHandle> {
        let mut handles: Vec<_> = self.accels.iter().map(|a| *a.key()).collect();
        handles.sort();
        handles
    }

    /// Destroys an accel; traces already holding it finish first. An accel that live instance accels or
    /// transforms place cannot be destroyed (FAILED_PRECONDITION): destroy them first.
    pub fn destroy_accel(&self, handle: AccelHandle) -> Result<()> {
        self.destroy_accel_after(handle, || Ok::<_, Error>(()))
    }

    /// [`Context::destroy_accel`] with `before` run once the accel is marked destroyed (nothing places it, and no
    /// build can come to) and before it leaves the context, e.g. to remove what a server keeps of it: if `before`
    /// fails, the mark is taken back and its error returned, the accel staying as it was (a build that tried to
    /// place it meanwhile was refused).
    pub fn destroy_accel_after<E: From<Error>>(
        &self,
        handle: AccelHandle,
        before: impl FnOnce() -> std::result::Result<(), E>,
    ) -> std::result::Result<(), E> {
        let accel = self.accel(handle)?;
        // Marked destroyed only while nothing places it, in one step: a build placing it meanwhile either counted
        // itself first (and the destroy is refused) or is refused itself.
        if let Err(referrers) = accel.referrers.compare_exchange(0, DESTROYED, Ordering::AcqRel, Ordering::Acquire) {
            let refused = if referrers & DESTROYED != 0 { not_found(handle) } else { placed_by(handle, referrers) };
            return Err(refused.into());
        }
        if let Err(failed) = before() {
            // Builds refused by the mark took their counts back; any still taking theirs back keep them consistent.
            accel.referrers.fetch_and(!DESTROYED, Ordering::AcqRel);
            return Err(failed);
        }
        Ok(self.accels.remove(&handle).map(drop).ok_or_else(|| not_found(handle))?)
    }

    /// What [`Context::destroy_accel`] would refuse now: an unknown accel (NOT_FOUND), or one that live instance
    /// accels or transforms place (FAILED_PRECONDITION).
    pub fn check_destroyable(&self, handle: AccelHandle) -> Result<()> {
        let referrers = self.accel(handle)?.referrers.load(Ordering::Acquire) & !DESTROYED;
        if referrers > 0 {
            return Err(placed_by(handle, referrers));
        }
        Ok(())
    }

    /// Keeps `data` in the context and returns its handle.
    pub fn create_buffer(&self, data: Bytes) -> BufferHandle {
        let handle = BufferHandle(self.next_handle.fetch_add(1, Ordering::Relaxed));
        let charge = Charge::new(data.len() as u64, &self.bytes_in_use);
        self.buffers.insert(handle, Buffer { data, _charge: charge });
        handle
    }

    /// The bytes of a buffer (shared, not copied).
    pub fn buffer(&self, handle: BufferHandle) -> Result<Bytes> {
        self.buffers.get(&handle).map(|b| b.data.clone()).ok_or(Error::NotFound { what: "buffer", id: handle.0 })
    }

    /// Destroys a buffer.
    pub fn destroy_buffer(&self, handle: BufferHandle) -> Result<()> {
        self.buffers.remove(&handle).map(drop).ok_or(Error::NotFound { what: "buffer", id: handle.0 })
    }

    /// Traces `rays` against `accel` and writes the results into `out` in place. FAILED_PRECONDITION when the
    /// accel places an accel in a version an update has replaced (update the placing accel first).
    pub fn trace(&self, accel: &Accel, query: &Query, rays: &[u8], out: TraceOutput<'_>) -> Result<TraceStats> {
        self.check_trace(accel, query, RaySource::Packed(rays))?;
        self.device.backend.trace(accel.data.as_ref(), query, rays, out)
    }

    /// For benchmarks that compare a GPU's trace kernel with other engines' (which time one launch over a batch
    /// already on the device): the kernel time of each of `launches` launches of `query` over all of `rays`,
    /// uploaded once and traced again and again back to back, by the GPU's timestamps. The hits stay on the
    /// device. FAILED_PRECONDITION on a device without a kernel or timestamps (the CPU), INVALID_ARGUMENT for
    /// `launches` outside 1 ..= 2,048, RESOURCE_EXHAUSTED when the rays do not fit one launch.
    pub fn time_launches(&self, accel: &Accel, query: &Query, rays: &[u8], launches: u32) -> Result<Vec<Duration>> {
        self.check_trace(accel, query, RaySource::Packed(rays))?;
        self.device.backend.time_launches(accel.data.as_ref(), query, rays, launches)
    }

    /// [`Context::trace`] of rays that may be generated (a checked generator's rays are made where they are traced,
    /// on the device when its backend can).
    pub fn trace_source(
        &self,
        accel: &Accel,
        query: &Query,
        rays: RaySource<'_>,
        out: TraceOutput<'_>,
    ) -> Result<TraceStats> {
        self.check_trace(accel, query, rays)?;
        self.device.backend.trace_source(accel.data.as_ref(), query, rays, out)
    }

    /// Traces `rays` (ray `first_ray` of the batch first; whole groups of the reduction) against `accel` and
    /// reduces their hits with `reduction` (checked against the query and the batch): the piece's partial, to be
    /// folded with the other pieces' ([`Reduction::finish`]).
    pub fn trace_reduced(
        &self,
        accel: &Accel,
        query: &Query,
        rays: RaySource<'_>,
        first_ray: u64,
        reduction: &Reduction,
    ) -> Result<(Partial, TraceStats)> {
        self.check_trace(accel, query, rays)?;
        self.device.backend.trace_reduced(accel.data.as_ref(), query, rays, first_ray, reduction)
    }

    /// What every trace checks before its backend runs: the accel is current and on this context's device, packed
    /// rays' times are numbers (a checked generator makes only such times), and the query's ray format keeps a
    /// generator's ranges.
    fn check_trace(&self, accel: &Accel, query: &Query, rays: RaySource<'_>) -> Result<()> {
        accel.check_current()?;
        self.check_device(accel, "traces")?;
        match rays {
            RaySource::Packed(rays) => query.check_times(rays),
            RaySource::Generated { generator, .. } => generator.check_format(query.ray_format),
        }
    }
}
