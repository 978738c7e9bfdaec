//! Adapters and their devices. Every adapter that wgpu enumerates on the backends of `WGPU_BACKEND` (Vulkan when
//! it is unset) is a device `wgpu:N`, in enumeration order. Enumeration happens once a process; an adapter's wgpu
//! device (with the kernel's shader module; its pipelines are compiled as traces need them) is opened on first use
//! and shared by every context and backend on it.

use std::sync::{Arc, OnceLock};

use super::kernel::Kernel;
use crate::backend::cpu::host_memory_bytes;
use crate::backend::{BackendKind, DeviceInfo};
use crate::error::{Error, Result};

/// One adapter.
pub(super) struct Gpu {
    /// Its position in the enumeration: the `N` of `wgpu:N`.
    index: usize,
    /// The adapter, to open its device.
    adapter: wgpu::Adapter,
    /// Its device, once opened (or why it could not be).
    opened: OnceLock<Result<Opened>>,
}

/// An opened adapter: its device, queue and the trace pipeline.
pub(super) struct Opened {
    /// The device, created with the adapter's own limits.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// The trace pipeline and its bind group layouts.
    pub kernel: Kernel,
    /// Nanoseconds a timestamp tick, where the adapter has timestamp queries (traces then time their kernels).
    pub timestamp_period: Option<f32>,
}

impl Opened {
    /// The largest buffer a trace binds: the adapter's storage binding limit, lowered to `cap` if given.
    pub fn binding_limit(&self, cap: Option<u64>) -> u64 {
        let limits = self.device.limits();
        let adapter = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        cap.map_or(adapter, |cap| cap.min(adapter))
    }
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
                .map(|(index, adapter)| Arc::new(Gpu { index, adapter, opened: OnceLock::new() }))
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
        let software = info.device_type == wgpu::DeviceType::Cpu;
        let threads = std::thread::available_parallelism().map_or(0, |n| n.get() as u32);
        DeviceInfo {
            id: format!("wgpu:{}", self.index),
            kind: BackendKind::Wgpu,
            name: format!("{} ({:?} {:?}, {})", info.name, info.backend, info.device_type, info.driver_info),
            memory_bytes: if software { host_memory_bytes() } else { 0 },
            parallelism: if software { threads } else { 0 },
        }
    }

    /// The opened device; FAILED_PRECONDITION if the adapter refused it.
    pub fn open(&self) -> Result<&Opened> {
        self.opened
            .get_or_init(|| {
                let timestamps = self.adapter.features() & wgpu::Features::TIMESTAMP_QUERY;
                let descriptor = wgpu::DeviceDescriptor {
                    label: Some("rayd"),
                    // The kernel is handed to the driver as SPIR-V (`spirv.rs`); every Vulkan adapter has this.
                    required_features: timestamps | wgpu::Features::PASSTHROUGH_SHADERS,
                    required_limits: self.adapter.limits(),
                    ..wgpu::DeviceDescriptor::default()
                };
                let (device, queue) = pollster::block_on(self.adapter.request_device(&descriptor)).map_err(|e| {
                    Error::FailedPrecondition(format!("wgpu:{}: opening the device failed: {e}", self.index))
                })?;
                let kernel = Kernel::new(&device);
                let timestamp_period = (!timestamps.is_empty()).then(|| queue.get_timestamp_period());
                Ok(Opened { device, queue, kernel, timestamp_period })
            })
            .as_ref()
            .map_err(Clone::clone)
    }
}
