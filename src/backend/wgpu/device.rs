//! Adapters and their devices. Every adapter that wgpu enumerates on the backends of `WGPU_BACKEND` (Vulkan when
//! it is unset) is a device `wgpu:N`, in enumeration order. Enumeration happens once a process; an adapter's wgpu
//! device (with the kernel's shader module; its pipelines are compiled as traces need them) is opened on first use
//! and shared by every context and backend on it (a device the adapter refused is asked for again after
//! [`super::opening::REFUSAL_KEPT`]). A device that is lost (reset, removed or failed: the driver
//! reports it) fails the calls on it with UNAVAILABLE and is opened anew by the next call; accels are uploaded to
//! the new device as they are next traced (`super::DeviceCopy`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use super::batch::Slot;
use super::kernel::Kernel;
use super::opening::Opening;
use crate::backend::cpu::host_memory_bytes;
use crate::backend::{BackendKind, DeviceInfo};
use crate::error::{Error, Result};

/// One adapter.
pub(super) struct Gpu {
    /// Its position in the enumeration: the `N` of `wgpu:N`.
    index: usize,
    /// The adapter, to open its device.
    adapter: wgpu::Adapter,
    /// Its device once opened (or why the adapter refused it); replaced when it is lost.
    opened: Mutex<Opening<Opened>>,
    /// How long a trace waits for the device's answer before it takes the device as hung ([`ANSWER_TIMEOUT`]).
    answer_timeout: Duration,
}

/// How long a trace waits for the device's answer to one chunk before it takes the device as hung, and so lost: a
/// chunk takes milliseconds on a GPU (seconds on a software one, or for the costliest rays), so a device that has
/// not answered in a minute will not. Without it, a GPU that hangs without its driver reporting it lost would hold
/// the device's traces, and their callers' operations, for good.
pub const ANSWER_TIMEOUT: Duration = Duration::from_secs(60);

/// Devices opened in this process: the next one's [`Opened::generation`].
static OPENINGS: AtomicU64 = AtomicU64::new(0);

/// An opened adapter: its device, queue and the trace pipeline.
pub(super) struct Opened {
    /// `wgpu:N`, for messages.
    pub name: String,
    /// Which opening of a device in this process it is: what was made on a device remembers it.
    pub generation: u64,
    /// Why the device was lost, once the driver reports it.
    lost: Arc<OnceLock<String>>,
    /// Idle per-chunk buffer sets (staging included), reused by later traces; a trace takes two and gives them back,
    /// and the pool keeps the smallest within a budget ([`super::batch::trim_idle`]).
    pub idle_slots: Mutex<Vec<Slot>>,
    /// The device, created with the adapter's own limits.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// The trace pipeline and its bind group layouts.
    pub kernel: Kernel,
    /// Nanoseconds a timestamp tick, where the adapter has timestamp queries (traces then time their kernels).
    pub timestamp_period: Option<f32>,
    /// How long a trace waits for the device's answer to a chunk before it takes the device as hung.
    pub answer_timeout: Duration,
}

impl Opened {
    /// The largest buffer a trace binds: the adapter's storage binding limit, lowered to `cap` if given.
    pub fn binding_limit(&self, cap: Option<u64>) -> u64 {
        binding_limit(&self.device.limits(), cap)
    }

    /// Runs `work`, the device calls of `what`, under error scopes: RESOURCE_EXHAUSTED if the device had no memory
    /// left for an object it makes (what it made is then unusable, and is dropped), FAILED_PRECONDITION if the driver
    /// failed it (an internal error), UNAVAILABLE if the device was lost. wgpu loses the device itself when memory
    /// runs out for some objects (staging, command buffers, bind groups): UNAVAILABLE then too.
    pub fn checked<T>(&self, what: &'static str, work: impl FnOnce() -> T) -> Result<T> {
        let (done, Caught { validation, memory, internal }) = caught(&self.device, work);
        if let Some(error) = internal {
            let failed = Error::FailedPrecondition(format!("{}: the driver failed {what}: {error}", self.name));
            return Err(self.or_lost(failed));
        }
        if let Some(error) = memory {
            // Objects made from one the device had no memory for fail validation: the memory is the cause.
            return Err(self.or_lost(Error::DeviceMemory {
                device: self.name.clone(),
                what,
                detail: error.to_string(),
            }));
        }
        if let Some(error) = validation {
            // Objects of a lost device fail validation too; otherwise it is a bug: a panic.
            return Err(self.lost().unwrap_or_else(|| panic!("the wgpu device refused {what}: {error}")));
        }
        Ok(done)
    }

    /// `error` of a call on this device, or UNAVAILABLE naming why the device was lost if it was: whatever failed
    /// on a lost device failed because of that.
    pub fn or_lost(&self, error: Error) -> Error {
        self.lost().unwrap_or(error)
    }

    /// Takes the device as lost, for not having answered a trace within [`Opened::answer_timeout`], and returns
    /// UNAVAILABLE naming why (or why the driver lost it meanwhile): the next call opens the device anew.
    pub fn hung(&self) -> Error {
        let _ = self.lost.set(format!("Hung: no answer to a trace in {:?}", self.answer_timeout));
        let why = self.lost.get().cloned().unwrap_or_default();
        Error::DeviceLost { device: self.name.clone(), detail: why }
    }

    /// UNAVAILABLE naming why the device was lost, if it was. Polls the device first, which is when wgpu reports a
    /// loss that it has not reported yet.
    pub fn lost(&self) -> Option<Error> {
        // An error of the poll itself is seen by the call's own waits.
        let _ = self.device.poll(wgpu::PollType::Poll);
        let why = self.lost.get()?;
        Some(Error::DeviceLost { device: self.name.clone(), detail: why.clone() })
    }
}

/// The errors of each kind that wgpu reported while some work ran on a device.
struct Caught {
    /// Validation errors (the first).
    validation: Option<wgpu::Error>,
    /// Out-of-memory errors (the first).
    memory: Option<wgpu::Error>,
    /// The driver's internal errors (the first).
    internal: Option<wgpu::Error>,
}

/// Runs `work`, device calls on `device`, under an error scope of each kind, and returns its result with the errors
/// they caught.
fn caught<T>(device: &wgpu::Device, work: impl FnOnce() -> T) -> (T, Caught) {
    let validation = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let memory = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
    let internal = device.push_error_scope(wgpu::ErrorFilter::Internal);
    let done = work();
    // Popped in the reverse order of their pushes.
    let internal = pollster::block_on(internal.pop());
    let memory = pollster::block_on(memory.pop());
    let validation = pollster::block_on(validation.pop());
    (done, Caught { validation, memory, internal })
}

/// The largest storage binding of a device with `limits`, lowered to `cap` if given.
fn binding_limit(limits: &wgpu::Limits, cap: Option<u64>) -> u64 {
    let adapter = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
    cap.map_or(adapter, |cap| cap.min(adapter))
}

/// The wgpu instance and its adapters, enumerated once.
static ADAPTERS: OnceLock<(wgpu::Instance, Vec<Arc<Gpu>>)> = OnceLock::new();

/// Every adapter of this machine on the backends of `WGPU_BACKEND` (default: Vulkan).
pub(super) fn adapters() -> &'static [Arc<Gpu>] {
    &ADAPTERS
        .get_or_init(|| {
            let backends = wgpu::Backends::from_env().unwrap_or(wgpu::Backends::VULKAN);
            let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
                backends,
                ..wgpu::InstanceDescriptor::new_without_display_handle()
            });
            let adapters = pollster::block_on(instance.enumerate_adapters(backends))
                .into_iter()
                .enumerate()
                .map(|(index, adapter)| {
                    Arc::new(Gpu { index, adapter, opened: Mutex::default(), answer_timeout: ANSWER_TIMEOUT })
                })
                .collect();
            (instance, adapters)
        })
        .1
}

impl Gpu {
    /// The `N` of `wgpu:N`.
    pub fn index(&self) -> usize {
        self.index
    }

    /// The device description (see [`super::WgpuBackend::info`]).
    pub fn info(&self) -> DeviceInfo {
        let info = self.adapter.get_info();
        let software = self.software();
        let threads = std::thread::available_parallelism().map_or(0, |n| n.get() as u32);
        DeviceInfo {
            id: self.name(),
            kind: BackendKind::Wgpu,
            name: format!("{} ({:?} {:?}, {})", info.name, info.backend, info.device_type, info.driver_info),
            memory_bytes: if software { host_memory_bytes() } else { 0 },
            parallelism: if software { threads } else { 0 },
        }
    }

    /// Another handle on the same adapter, which opens a device of its own: tests lose or fill it without touching the
    /// device that the others share.
    #[cfg(test)]
    pub fn alone(&self) -> Gpu {
        Gpu {
            index: self.index,
            adapter: self.adapter.clone(),
            opened: Mutex::default(),
            answer_timeout: ANSWER_TIMEOUT,
        }
    }

    /// The same, whose traces take the device as hung after `timeout` without its answer.
    #[cfg(test)]
    pub fn answering_within(self, timeout: Duration) -> Gpu {
        Gpu { answer_timeout: timeout, ..self }
    }

    /// [`Opened::binding_limit`] without opening the device, which is opened with the adapter's own limits.
    pub fn binding_limit(&self) -> u64 {
        binding_limit(&self.adapter.limits(), None)
    }

    /// Whether the adapter is the CPU (lavapipe): its memory is the host's.
    pub fn software(&self) -> bool {
        self.adapter.get_info().device_type == wgpu::DeviceType::Cpu
    }

    /// The opened device, opened now if it was not or was lost ([`Opening::get`]): FAILED_PRECONDITION if the
    /// adapter refused it (given again for [`super::opening::REFUSAL_KEPT`], then tried again), UNAVAILABLE if it
    /// refused a device to replace a lost one (the next call tries again).
    pub fn open(&self) -> Result<Arc<Opened>> {
        let mut opened = self.opened.lock().unwrap_or_else(|e| e.into_inner());
        opened.get(Instant::now(), |current| current.lost.get().cloned(), || self.open_device(), || self.name())
    }

    /// `wgpu:N`.
    fn name(&self) -> String {
        format!("wgpu:{}", self.index)
    }

    /// Opens a device on the adapter, with the adapter's own limits, and compiles the kernel's module.
    fn open_device(&self) -> Result<Opened> {
        let name = self.name();
        let timestamps = self.adapter.features() & wgpu::Features::TIMESTAMP_QUERY;
        let descriptor = wgpu::DeviceDescriptor {
            label: Some("rayd"),
            // The kernel is handed to the driver as SPIR-V (`spirv.rs`); every Vulkan adapter has this.
            required_features: timestamps | wgpu::Features::PASSTHROUGH_SHADERS,
            required_limits: self.adapter.limits(),
            ..wgpu::DeviceDescriptor::default()
        };
        let (device, queue) = pollster::block_on(self.adapter.request_device(&descriptor))
            .map_err(|e| Error::FailedPrecondition(format!("{name}: opening the device failed: {e}")))?;
        let lost = Arc::new(OnceLock::new());
        let reported = Arc::clone(&lost);
        device.set_device_lost_callback(move |reason, message| {
            let _ = reported.set(format!("{reason:?}: {message}"));
        });
        // wgpu's own handler of errors outside an error scope panics; such an error is logged, and the objects it
        // left unusable fail the checked calls that use them.
        let logged = name.clone();
        device.on_uncaptured_error(Arc::new(move |error| {
            tracing::error!(device = logged, %error, "a wgpu error outside the checked calls");
        }));
        // An adapter that cannot take the kernel's bindings (fewer storage buffers a shader stage than it binds),
        // or whose driver fails them, is refused here, naming why.
        let (kernel, Caught { validation, memory, internal }) = caught(&device, || Kernel::new(&device));
        if let Some(error) = internal.or(validation).or(memory) {
            return Err(Error::FailedPrecondition(format!("{name}: the device cannot take rayd's kernel: {error}")));
        }
        let timestamp_period = (!timestamps.is_empty()).then(|| queue.get_timestamp_period());
        let generation = OPENINGS.fetch_add(1, Ordering::Relaxed);
        let answer_timeout = self.answer_timeout;
        Ok(Opened {
            name,
            generation,
            lost,
            idle_slots: Mutex::default(),
            device,
            queue,
            kernel,
            timestamp_period,
            answer_timeout,
        })
    }
}
