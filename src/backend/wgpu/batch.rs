//! Batches on the device. Rays are traced in chunks whose buffers each fit one storage binding and whose
//! workgroups fit one dispatch; chunk `i` runs in slot `i % 2`, so while the device traces one chunk the host
//! copies the previous chunk's results out and the next chunk's rays in (double buffering). A slot's buffers,
//! staging included, are kept by the backend and reused by later traces; they grow when a trace needs more.
//!
//! A slot's buffers (bind group 1 of the trace pipeline), every value a little-endian 32-bit word:
//! - `params`: the chunk's [`Params`] (uniform).
//! - `rays`: the chunk's rays, the caller's bytes unchanged (`RayFormat` layout), ray `i` at `i·size`; or, when
//!   the rays are made on the device, the generator's numbers for the chunk ([`DeviceGenerator::words`]).
//! - `hits`: the chunk's hit records in the caller's `HitFormat` layout, record `r` at `r·size`; for the
//!   bitmask, record `r` is bit `r % 32` of word `r / 32` (which is bit `r % 8` of byte `r / 8`, as in the
//!   caller's buffer), the words cleared before the dispatch. A chunk starts at a multiple of 32 rays, so its
//!   records start on a word boundary of the caller's bitmask.
//! - `tallies`: [`TALLY_WORDS`] words of statistics (`0 rays_hit | 4 nodes_visited low | 8 nodes_visited high |
//!   12 triangle_tests low | 16 triangle_tests high | 20 rays past max_ray_work | 24..32 zero`), cleared before the
//!   dispatch, then, for the counting kinds, one count a ray.
//! - `scratch`: for `all` queries, `records_per_ray` sorted hits a ray, 48 bytes each: `0 t f32 | 4 slot u32
//!   (bit 31: back face) | 8 u f32 | 12 v f32 | 16 levels u32 | 20 records u32×7` (what entered each instance
//!   level below the root, top to bottom: an instance record's offset in `graph`, or bit 31 and a transform's
//!   object offset); 48 unused bytes for the other kinds.
//! - `reduced`: for the image reduction, `pixel_words` words a pixel (`reduce.wgsl`); 4 unused bytes otherwise.
//! - `upload` (mappable, copied to `rays`; unused for generated rays) and `readback` (mappable: what the trace
//!   gives back — `hits`, `reduced` or nothing — then `tallies`, then the kernel's start and end timestamps): the
//!   staging buffers. An idle slot's `upload` is mapped, ready for the next chunk's rays.
//! - `timestamps`, where the adapter has timestamp queries: a query set of 2 (the trace pass's start and end) and
//!   the 16 bytes it resolves into (two u64 ticks); without them the readback's last 16 bytes stay unused.

use std::sync::mpsc::{Receiver, TryRecvError, channel};
use std::time::{Duration, Instant};

use rayon::prelude::*;

#[cfg(doc)]
use super::WgpuOptions;
use super::device::Opened;
use super::kernel::{Params, Rays, WORKGROUP_SIZE};
use super::layout::GpuGraph;
use super::offload::{DeviceGenerator, OnDevice, encode_pixels};
use crate::error::{Error, Result};
use crate::format::{HitFormat, read_u32};
use crate::query::{Query, QueryKind, TraceOutput, TraceStats};
use crate::reduce::Image;

/// Slots a trace keeps in flight.
pub(super) const SLOTS: usize = 2;
/// Bytes of idle slots a device keeps for later traces: a little more than a trace of ordinary chunks takes (a slot
/// of 2^18 full rays and closest hits takes about 67 MB). Larger slots, made for a large trace (an `all` query of
/// many hits a ray, chunks as large as a binding) or for traces at once, are let go once they end, so that they do
/// not stay for the process's life.
const MAX_IDLE_SLOT_BYTES: u64 = 256 << 20;
/// The word of `tallies` that counts the rays whose walk passed `max_ray_work` (`OVER_RAY_WORK` in `layout.wgsl`).
const OVER_RAY_WORK: usize = 5;
/// Words of statistics at the head of `tallies` (`TALLY_WORDS` in `layout.wgsl`).
const TALLY_WORDS: usize = 8;
/// Bytes of those words.
const TALLY_BYTES: u64 = 4 * TALLY_WORDS as u64;
/// Bytes of the two resolved timestamps.
const TIMESTAMP_BYTES: u64 = 16;
/// Bytes of one `all` scratch entry.
const SCRATCH_ENTRY_BYTES: u64 = 48;
/// Rays of a chunk at most unless [`WgpuOptions::max_chunk_rays`] says otherwise: large enough to keep a GPU busy,
/// small enough that copying one chunk out overlaps tracing the next.
pub(super) const MAX_CHUNK_RAYS: usize = 1 << 18;
/// The same for rays made on the device and reduced there: with nothing to upload and a few bytes a pixel to read
/// back, larger chunks lose little overlap and save each chunk's start and drain (on an H100, a 4-megapixel image's
/// hit counts through rayd ran 69% faster than in chunks of 2^18 rays, its depth image 18%; on an H200 the kernels of
/// such an image took 19–20% less time in two chunks of 2^21 than in four of 2^20, and 20% more in eight of 2^19;
/// BENCHMARKS.md).
pub(super) const MAX_ON_DEVICE_CHUNK_RAYS: usize = 1 << 21;
/// Rays one dispatch can cover: 65,535 workgroups (WebGPU's per-dimension limit) of [`WORKGROUP_SIZE`].
const MAX_DISPATCH_RAYS: usize = 65_535 * WORKGROUP_SIZE as usize;
/// Chunks start at multiples of this many rays (and of a reduction's pixel), so that bitmask chunks start on word
/// boundaries.
const CHUNK_ALIGN: usize = 32;

/// Where a trace's rays come from.
#[derive(Debug, Clone, Copy)]
pub(super) enum Input<'a> {
    /// The caller's rays, packed in the query's format.
    Packed(&'a [u8]),
    /// Made on the device.
    Generated(DeviceGenerator<'a>),
}

/// What a trace gives back besides its statistics.
#[derive(Debug)]
pub(super) enum Output<'a> {
    /// Every hit record and count, into the caller's buffers.
    Hits(TraceOutput<'a>),
    /// Each pixel of `image` (its `rays_per_pixel` rays) reduced on the device to [`OnDevice::pixel_words`] words
    /// (`reduce.wgsl`), then encoded into `pixels` as each chunk comes back.
    Pixels {
        /// The image.
        image: Image,
        /// The whole batch's pixels, in the image's encoding.
        pixels: &'a mut [u8],
    },
    /// Nothing else: the statistics count the rays hit.
    Tallies,
}

impl Output<'_> {
    /// Rays whose results go together (a pixel's), 1 but for pixels.
    fn group_rays(&self) -> usize {
        match self {
            Output::Pixels { image, .. } => image.rays_per_pixel as usize,
            _ => 1,
        }
    }

    /// Bytes a chunk of `rays` rays gives back (a multiple of 4, as copies need): its hit records, its pixels, or
    /// none.
    fn chunk_bytes(&self, query: &Query, rays: usize) -> u64 {
        match self {
            Output::Hits(_) => (query.hit_format.buffer_len(rays * query.records_per_ray()) as u64).next_multiple_of(4),
            Output::Pixels { image, .. } => {
                (rays / image.rays_per_pixel as usize) as u64 * 4 * u64::from(OnDevice::pixel_words(image))
            }
            Output::Tallies => 0,
        }
    }
}

/// The byte sizes of a slot's buffers.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct Capacity {
    /// `rays` and `upload`.
    rays: u64,
    /// `hits` (a multiple of 4).
    hits: u64,
    /// `tallies`.
    tallies: u64,
    /// `scratch`.
    scratch: u64,
    /// `reduced` (at least 4).
    reduced: u64,
    /// What `readback` gives back before `tallies`.
    given_back: u64,
}

impl Capacity {
    /// What a chunk of `rays` rays of `query` needs, its rays from `input`, giving back `output`.
    fn for_chunk(query: &Query, rays: usize, input: &Input<'_>, output: &Output<'_>) -> Capacity {
        let records = rays * query.records_per_ray();
        let reduced = match output {
            Output::Pixels { .. } => output.chunk_bytes(query, rays),
            _ => 0,
        };
        Capacity {
            rays: match input {
                Input::Packed(_) => (rays * query.ray_format.size()) as u64,
                Input::Generated(generator) => 4 * generator.most_words(rays) as u64,
            },
            hits: (query.hit_format.buffer_len(records) as u64).next_multiple_of(4),
            tallies: TALLY_BYTES + if query.kind.has_counts() { 4 * rays as u64 } else { 0 },
            scratch: if query.kind == QueryKind::All {
                records as u64 * SCRATCH_ENTRY_BYTES
            } else {
                SCRATCH_ENTRY_BYTES
            },
            reduced: reduced.max(4),
            given_back: output.chunk_bytes(query, rays),
        }
    }

    /// Bytes of a slot of this capacity: its buffers, staging included.
    fn bytes(&self) -> u64 {
        2 * self.rays + self.hits + self.tallies + self.scratch + self.reduced + self.readback()
    }

    /// Bytes of `readback`: what is given back, the tallies and the timestamps.
    fn readback(&self) -> u64 {
        self.given_back + self.tallies + TIMESTAMP_BYTES
    }

    /// The largest buffer, the readback staging included (a buffer, if not a binding, of at most the adapter's
    /// `max_buffer_size`).
    fn largest(&self) -> u64 {
        self.rays.max(self.hits).max(self.tallies).max(self.scratch).max(self.reduced).max(self.readback())
    }

    /// Whether every buffer is at least as large as `need`'s.
    fn holds(&self, need: &Capacity) -> bool {
        self.rays >= need.rays
            && self.hits >= need.hits
            && self.tallies >= need.tallies
            && self.scratch >= need.scratch
            && self.reduced >= need.reduced
            && self.given_back >= need.given_back
    }

    /// This capacity grown to hold `need`: the larger of each buffer, unless a buffer would then pass `limit` (the
    /// readback staging adds one trace's bytes given back to another's tallies, and can pass what each fit), when
    /// `need`'s own.
    fn grown_to(self, need: Capacity, limit: u64) -> Capacity {
        let grown = Capacity {
            rays: self.rays.max(need.rays),
            hits: self.hits.max(need.hits),
            tallies: self.tallies.max(need.tallies),
            scratch: self.scratch.max(need.scratch),
            reduced: self.reduced.max(need.reduced),
            given_back: self.given_back.max(need.given_back),
        };
        if grown.largest() <= limit { grown } else { need }
    }
}

/// How a batch is cut into chunks.
#[derive(Debug, Clone, Copy)]
pub(super) struct Plan {
    /// Rays in the batch.
    rays: usize,
    /// Rays of every chunk but the last: a multiple of [`CHUNK_ALIGN`] and of the output's pixel.
    chunk_rays: usize,
    /// What a full chunk needs.
    need: Capacity,
}

/// What bounds a trace's chunks besides its query.
#[derive(Debug, Clone, Copy)]
pub(super) struct ChunkLimits {
    /// Bytes of the largest buffer (a binding, or the readback staging).
    pub binding_bytes: u64,
    /// Rays of a chunk.
    pub chunk_rays: usize,
    /// Bytes of the trace's [`SLOTS`] slots together, staging included ([`WgpuOptions::max_trace_bytes`]).
    pub trace_bytes: u64,
}

impl Plan {
    /// The largest chunks (up to `limits.chunk_rays`) whose every buffer fits `limits.binding_bytes`, whose slots fit
    /// `limits.trace_bytes` together and whose workgroups fit one dispatch; RESOURCE_EXHAUSTED if even one aligned
    /// chunk does not fit (or, for pixels, if a chunk cannot hold whole pixels: the caller then reduces on the host).
    pub fn new(
        query: &Query,
        rays: usize,
        input: &Input<'_>,
        output: &Output<'_>,
        limits: ChunkLimits,
    ) -> Result<Plan> {
        let align = lcm(CHUNK_ALIGN, output.group_rays());
        let most = limits.chunk_rays.clamp(CHUNK_ALIGN, MAX_DISPATCH_RAYS) / align * align;
        if most == 0 {
            return Err(Error::TooLarge {
                what: "a wgpu chunk of whole pixels",
                unit: "rays",
                requested: align as u64,
                limit: limits.chunk_rays as u64,
            });
        }
        let mut chunk_rays = rays.next_multiple_of(align).clamp(align, most);
        loop {
            let need = Capacity::for_chunk(query, chunk_rays, input, output);
            let slots = need.bytes().saturating_mul(SLOTS as u64);
            if need.largest() <= limits.binding_bytes && slots <= limits.trace_bytes {
                return Ok(Plan { rays, chunk_rays, need });
            }
            if chunk_rays == align {
                return Err(if need.largest() > limits.binding_bytes {
                    Error::TooLarge {
                        what: "a wgpu chunk of its fewest rays, 32 or a pixel's (max_hits_per_ray too large)",
                        unit: "bytes",
                        requested: need.largest(),
                        limit: limits.binding_bytes,
                    }
                } else {
                    Error::TooLarge {
                        what: "the buffers of a wgpu trace in chunks of its fewest rays, 32 or a pixel's \
                               (max_hits_per_ray too large for the trace buffer limit, rayd's scheduler.gpu_trace_bytes)",
                        unit: "bytes",
                        requested: slots,
                        limit: limits.trace_bytes,
                    }
                });
            }
            chunk_rays = (chunk_rays / 2).next_multiple_of(align);
        }
    }
}

/// The least common multiple of two positive numbers.
fn lcm(a: usize, b: usize) -> usize {
    let (mut x, mut y) = (a, b);
    while y != 0 {
        (x, y) = (y, x % y);
    }
    a / x * b
}

/// One chunk's buffers on the device (see the module documentation).
pub(super) struct Slot {
    /// What its buffers hold.
    capacity: Capacity,
    /// The chunk's uniform block.
    params: wgpu::Buffer,
    /// Staging for the rays: mapped while the slot is idle.
    upload: wgpu::Buffer,
    /// The rays the kernel reads.
    rays: wgpu::Buffer,
    /// The hit records the kernel writes.
    hits: wgpu::Buffer,
    /// Statistics and counts the kernel writes.
    tallies: wgpu::Buffer,
    /// The image reduction's pixels.
    reduced: wgpu::Buffer,
    /// Staging for what the trace gives back, `tallies` and the timestamps.
    readback: wgpu::Buffer,
    /// The kernel's timestamp queries and the buffer they resolve into, where the adapter has them.
    timestamps: Option<(wgpu::QuerySet, wgpu::Buffer)>,
    /// Bind group 1 over the slot's buffers (it keeps `scratch`, which nothing else uses, alive).
    bind_group: wgpu::BindGroup,
}

impl Slot {
    /// A slot of `capacity`, its upload buffer mapped; RESOURCE_EXHAUSTED if the device has no memory left for it.
    fn new(opened: &Opened, capacity: Capacity) -> Result<Slot> {
        opened.checked("making a trace's buffers", || Slot::make(opened, capacity))
    }

    /// The buffers of [`Slot::new`].
    fn make(opened: &Opened, capacity: Capacity) -> Slot {
        use wgpu::BufferUsages as U;
        let buffer = |label: &str, size: u64, usage: U, mapped: bool| {
            opened.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: mapped,
            })
        };
        let params = buffer("rayd params", size_of::<Params>() as u64, U::UNIFORM | U::COPY_DST, false);
        let upload = buffer("rayd upload", capacity.rays, U::MAP_WRITE | U::COPY_SRC, true);
        let rays = buffer("rayd rays", capacity.rays, U::STORAGE | U::COPY_DST, false);
        let hits = buffer("rayd hits", capacity.hits, U::STORAGE | U::COPY_SRC | U::COPY_DST, false);
        let tallies = buffer("rayd tallies", capacity.tallies, U::STORAGE | U::COPY_SRC | U::COPY_DST, false);
        let scratch = buffer("rayd scratch", capacity.scratch, U::STORAGE, false);
        let reduced = buffer("rayd reduced", capacity.reduced, U::STORAGE | U::COPY_SRC, false);
        let readback = buffer("rayd readback", capacity.readback(), U::MAP_READ | U::COPY_DST, false);
        let timestamps = opened.timestamp_period.map(|_| {
            let queries = opened.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("rayd kernel time"),
                ty: wgpu::QueryType::Timestamp,
                count: 2,
            });
            (queries, buffer("rayd timestamps", TIMESTAMP_BYTES, U::QUERY_RESOLVE | U::COPY_SRC, false))
        });
        let bind_group = opened.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("rayd batch"),
            layout: &opened.kernel.batch_layout,
            entries: &[&params, &rays, &hits, &tallies, &scratch, &reduced]
                .iter()
                .enumerate()
                .map(|(binding, buffer)| wgpu::BindGroupEntry {
                    binding: binding as u32,
                    resource: buffer.as_entire_binding(),
                })
                .collect::<Vec<_>>(),
        });
        Slot { capacity, params, upload, rays, hits, tallies, reduced, readback, timestamps, bind_group }
    }
}

/// Keeps the smallest of the idle slots `pool`, as many as take at most [`MAX_IDLE_SLOT_BYTES`], and lets go of the
/// others, ordered so that the largest kept are taken first.
fn trim_idle(pool: &mut Vec<Slot>) {
    keep_within(pool, |slot| slot.capacity.bytes(), MAX_IDLE_SLOT_BYTES);
}

/// Sorts `items` by `bytes` and keeps the smallest, as many as take at most `budget` bytes together.
fn keep_within<T>(items: &mut Vec<T>, bytes: impl Fn(&T) -> u64, budget: u64) {
    items.sort_by_key(&bytes);
    let mut kept = 0u64;
    items.retain(|item| {
        kept = kept.saturating_add(bytes(item));
        kept <= budget
    });
}

/// The rays of one chunk.
#[derive(Debug, Clone, Copy)]
struct Chunk {
    /// Index of its first ray in the batch.
    first: usize,
    /// Rays in it.
    rays: usize,
}

/// A chunk submitted and not yet copied out.
struct InFlight {
    /// Which rays.
    chunk: Chunk,
    /// What its buffers hold.
    need: Capacity,
    /// Its submission.
    submission: wgpu::SubmissionIndex,
    /// Reports the readback buffer mapped.
    read: Receiver<Result<(), wgpu::BufferAsyncError>>,
    /// Reports the upload buffer mapped again (packed rays only).
    write: Option<Receiver<Result<(), wgpu::BufferAsyncError>>>,
}

/// The little-endian u64 at byte `at` of `bytes`.
fn u64_at(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"))
}

/// Nanoseconds between the start and end timestamps resolved into `pair` (two little-endian u64 ticks) at `period`
/// nanoseconds a tick.
fn elapsed_nanos(pair: &[u8], period: f32) -> u64 {
    let (start, end) = (u64_at(pair, 0), u64_at(pair, 8));
    (end.saturating_sub(start) as f64 * f64::from(period)) as u64
}

/// Sets `pipeline` (the trace's), the accel's and the slot's bind groups, and dispatches one thread a ray.
fn dispatch_trace(
    pass: &mut wgpu::ComputePass<'_>,
    pipeline: &wgpu::ComputePipeline,
    accel: &GpuGraph,
    slot: &Slot,
    rays: usize,
) {
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, &accel.bind_group, &[]);
    pass.set_bind_group(1, &slot.bind_group, &[]);
    pass.dispatch_workgroups((rays as u32).div_ceil(WORKGROUP_SIZE), 1, 1);
}

/// The error of a device that failed mid-trace.
fn device_error(what: &str, error: impl std::fmt::Display) -> Error {
    Error::FailedPrecondition(format!("the wgpu device failed {what}: {error}"))
}

/// Asks for `buffer` to be mapped once the work that uses it is done; the receiver reports it.
fn request_map(buffer: &wgpu::Buffer, mode: wgpu::MapMode, size: u64) -> Receiver<Result<(), wgpu::BufferAsyncError>> {
    let (sender, receiver) = channel();
    buffer.slice(..size).map_async(mode, move |result| {
        // The trace may have failed and dropped the receiver: nobody is waiting then.
        let _ = sender.send(result);
    });
    receiver
}

/// Waits until `receiver` reports its mapping (polling the device until `submission` is done), for the device's
/// answer timeout at most: past it the device is taken as hung, and lost ([`Opened::hung`]).
fn wait_mapped(
    opened: &Opened,
    receiver: &Receiver<Result<(), wgpu::BufferAsyncError>>,
    submission: &wgpu::SubmissionIndex,
) -> Result<()> {
    let deadline = Instant::now() + opened.answer_timeout;
    loop {
        match receiver.try_recv() {
            Ok(result) => return result.map_err(|e| device_error("mapping a buffer", e)),
            Err(TryRecvError::Disconnected) => return Err(device_error("mapping a buffer", "the request was dropped")),
            Err(TryRecvError::Empty) => {
                let timeout = Some(deadline.saturating_duration_since(Instant::now()));
                let wait = wgpu::PollType::Wait { submission_index: Some(submission.clone()), timeout };
                match opened.device.poll(wait) {
                    Err(wgpu::PollError::Timeout) => return Err(opened.hung()),
                    polled => polled.map_err(|e| device_error("tracing", e))?,
                };
                // A lost device may never report the mapping.
                if let Some(lost) = opened.lost() {
                    return Err(lost);
                }
                // Another thread's poll may be delivering the callback right now.
                std::thread::yield_now();
            }
        }
    }
}

/// Traces the batch of `plan` with `query` against `accel`, its rays from `input`, into `output`, through [`SLOTS`]
/// slots of the plan's needs: taken from the device's idle ones (made or grown as needed) and given back after, unless
/// the trace failed, since their state is then unknown.
pub(super) fn trace(
    opened: &Opened,
    accel: &GpuGraph,
    query: &Query,
    plan: &Plan,
    ray_work: u32,
    input: Input<'_>,
    output: Output<'_>,
) -> Result<TraceStats> {
    if plan.rays == 0 {
        return Ok(TraceStats::default());
    }
    let started = Instant::now();
    let mut slots = take_idle(opened);
    ready_slots(opened, &mut slots, plan.need)?;
    let mut params = Params { root: accel.root, ..Params::for_query(query, ray_work) };
    if let Output::Pixels { image, .. } = output {
        (params.group_rays, params.pixel_words) = (image.rays_per_pixel, OnDevice::pixel_words(&image));
    }
    let stats = run_chunks(opened, accel, query, plan, &params, input, output, &slots, started)?;
    give_back_idle(opened, slots);
    Ok(stats)
}

/// Up to [`SLOTS`] of the device's idle slots, the largest first.
fn take_idle(opened: &Opened) -> Vec<Slot> {
    let mut pool = opened.idle_slots.lock().unwrap_or_else(|e| e.into_inner());
    let keep = pool.len().saturating_sub(SLOTS);
    pool.split_off(keep)
}

/// Gives `slots` back to the device's idle ones, which keep what their budget allows ([`trim_idle`]).
fn give_back_idle(opened: &Opened, slots: Vec<Slot>) {
    let mut pool = opened.idle_slots.lock().unwrap_or_else(|e| e.into_inner());
    pool.extend(slots);
    trim_idle(&mut pool);
}

/// Makes `slots` [`SLOTS`] slots that hold `need`, growing or adding what it lacks.
fn ready_slots(opened: &Opened, slots: &mut Vec<Slot>, need: Capacity) -> Result<()> {
    for index in 0..SLOTS {
        match slots.get(index) {
            Some(slot) if slot.capacity.holds(&need) => {}
            Some(slot) => slots[index] = Slot::new(opened, slot.capacity.grown_to(need, opened.binding_limit(None)))?,
            None => slots.push(Slot::new(opened, need)?),
        }
    }
    Ok(())
}

/// The chunk loop of [`trace`] (which started at `started`); logs its timings at debug level.
#[allow(clippy::too_many_arguments)]
fn run_chunks(
    opened: &Opened,
    accel: &GpuGraph,
    query: &Query,
    plan: &Plan,
    params: &Params,
    input: Input<'_>,
    mut output: Output<'_>,
    slots: &[Slot],
    started: Instant,
) -> Result<TraceStats> {
    let mut stats = TraceStats::default();
    // Host time submitting (rays copied into staging) and finishing (waiting, results copied out), for the log.
    let (mut submitting, mut finishing) = (Duration::ZERO, Duration::ZERO);
    let mut finish_one = |slot: usize, flight: InFlight, output: &mut Output<'_>, stats: &mut TraceStats| {
        let start = Instant::now();
        let finished = finish(opened, &slots[slot], flight, query, params.max_ray_work, output, stats);
        finishing += start.elapsed();
        finished
    };
    let mut in_flight: [Option<InFlight>; SLOTS] = Default::default();
    for (index, first) in (0..plan.rays).step_by(plan.chunk_rays).enumerate() {
        let slot = index % SLOTS;
        if let Some(flight) = in_flight[slot].take() {
            finish_one(slot, flight, &mut output, &mut stats)?;
        }
        let chunk = Chunk { first, rays: plan.chunk_rays.min(plan.rays - first) };
        let start = Instant::now();
        let submitted = opened.checked("submitting a chunk of rays", || {
            submit(opened, accel, &slots[slot], query, params, chunk, &input, &output)
        });
        // The scope's error, then the submission's own.
        in_flight[slot] = Some(submitted??);
        submitting += start.elapsed();
    }
    let mut rest: Vec<(usize, InFlight)> =
        in_flight.into_iter().enumerate().filter_map(|(slot, flight)| Some((slot, flight?))).collect();
    rest.sort_by_key(|(_, flight)| flight.chunk.first);
    for (slot, flight) in rest {
        finish_one(slot, flight, &mut output, &mut stats)?;
    }
    tracing::debug!(
        rays = plan.rays,
        chunk_rays = plan.chunk_rays,
        kernel_ms = stats.device_nanos as f64 * 1e-6,
        submitting_ms = submitting.as_secs_f64() * 1e3,
        finishing_ms = finishing.as_secs_f64() * 1e3,
        total_ms = started.elapsed().as_secs_f64() * 1e3,
        "wgpu trace"
    );
    Ok(stats)
}

/// Launches [`time_launches`] times at most: two timestamps each fill a query set of 4,096 (wgpu's limit).
const MAX_LAUNCHES: u32 = 2048;

/// GPU time of each of `launches` launches of the trace kernel over all of `rays` (a query checked against them),
/// one after another with the rays and hits kept on the device: the kernel timed the way GPU ray tracers are
/// compared (one launch over a resident batch), at the clock that back-to-back work keeps. FAILED_PRECONDITION
/// without timestamp queries, INVALID_ARGUMENT for `launches` outside 1 ..= 2,048, RESOURCE_EXHAUSTED if the batch
/// does not fit one chunk.
pub(super) fn time_launches(
    opened: &Opened,
    accel: &GpuGraph,
    query: &Query,
    rays: &[u8],
    launches: u32,
) -> Result<Vec<Duration>> {
    let Some(period) = opened.timestamp_period else {
        return Err(Error::FailedPrecondition("the adapter has no timestamp queries to time launches with".into()));
    };
    if !(1..=MAX_LAUNCHES).contains(&launches) {
        return Err(Error::InvalidQuery {
            field: "launches",
            rule: format!("must be 1 to {MAX_LAUNCHES}, not {launches}"),
        });
    }
    let count = rays.len() / query.ray_format.size();
    let (input, output) = (Input::Packed(rays), Output::Tallies);
    // One slot of the whole batch, for a benchmark that asked for it: no trace budget.
    let limits = ChunkLimits { binding_bytes: opened.binding_limit(None), chunk_rays: count, trace_bytes: u64::MAX };
    let plan = Plan::new(query, count, &input, &output, limits)?;
    if plan.chunk_rays < count {
        return Err(Error::TooLarge {
            what: "rays of one launch",
            unit: "rays",
            requested: count as u64,
            limit: plan.chunk_rays as u64,
        });
    }
    let slot = Slot::new(opened, plan.need)?;
    let pipeline = opened.kernel.pipeline(opened, accel.variant.for_query(query))?;
    let bytes = u64::from(launches) * TIMESTAMP_BYTES;
    let (readback, submission) = opened.checked("timing launches", || {
        opened.queue.write_buffer(&slot.rays, 0, rays);
        // A benchmark's launches: no ray is stopped.
        let params = Params { ray_count: count as u32, root: accel.root, ..Params::for_query(query, u32::MAX) };
        opened.queue.write_buffer(&slot.params, 0, bytemuck::bytes_of(&params));
        let queries = opened.device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("rayd launches"),
            ty: wgpu::QueryType::Timestamp,
            count: 2 * launches,
        });
        let buffer = |usage| {
            opened.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("rayd launches"),
                size: bytes,
                usage,
                mapped_at_creation: false,
            })
        };
        let resolved = buffer(wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC);
        let readback = buffer(wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST);
        let mut encoder =
            opened.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("rayd launches") });
        for launch in 0..launches {
            let timestamp_writes = wgpu::ComputePassTimestampWrites {
                query_set: &queries,
                beginning_of_pass_write_index: Some(2 * launch),
                end_of_pass_write_index: Some(2 * launch + 1),
            };
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("rayd launch"),
                timestamp_writes: Some(timestamp_writes),
            });
            dispatch_trace(&mut pass, pipeline, accel, &slot, count);
        }
        encoder.resolve_query_set(&queries, 0..2 * launches, &resolved, 0);
        encoder.copy_buffer_to_buffer(&resolved, 0, &readback, 0, bytes);
        let submission = opened.queue.submit([encoder.finish()]);
        (readback, submission)
    })?;
    wait_mapped(opened, &request_map(&readback, wgpu::MapMode::Read, bytes), &submission)?;
    let ticks = readback.slice(..).get_mapped_range().map_err(|e| device_error("mapping the timestamps", e))?;
    Ok(ticks
        .chunks_exact(TIMESTAMP_BYTES as usize)
        .map(|pair| Duration::from_nanos(elapsed_nanos(pair, period)))
        .collect())
}

/// Puts the chunk's rays on the device — its packed rays copied into `slot`'s (mapped) upload buffer, or the
/// generator's block written — and submits the dispatches (the trace, then the pixel reduction if `output` has
/// pixels) and the copies into the readback buffer; then asks for the staging buffers to be mapped when that work
/// is done.
#[allow(clippy::too_many_arguments)]
fn submit(
    opened: &Opened,
    accel: &GpuGraph,
    slot: &Slot,
    query: &Query,
    params: &Params,
    chunk: Chunk,
    input: &Input<'_>,
    output: &Output<'_>,
) -> Result<InFlight> {
    let need = Capacity::for_chunk(query, chunk.rays, input, output);
    let mut encoder =
        opened.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("rayd trace") });
    let mut params = Params { ray_count: chunk.rays as u32, ..*params };
    let rays = match input {
        Input::Packed(rays) => {
            let size = query.ray_format.size();
            let mut staging = slot
                .upload
                .slice(..need.rays)
                .get_mapped_range_mut()
                .map_err(|e| device_error("mapping the ray staging buffer", e))?;
            upload_spread(staging.slice(..), &rays[chunk.first * size..(chunk.first + chunk.rays) * size]);
            drop(staging);
            slot.upload.unmap();
            encoder.copy_buffer_to_buffer(&slot.upload, 0, &slot.rays, 0, need.rays);
            Rays::Packed
        }
        Input::Generated(generator) => {
            params.first_ray = generator.first + chunk.first as u32;
            let words = generator.words(params.first_ray, chunk.rays);
            opened.queue.write_buffer(&slot.rays, 0, bytemuck::cast_slice(&words));
            generator.rays
        }
    };
    opened.queue.write_buffer(&slot.params, 0, bytemuck::bytes_of(&params));
    let trace = opened.kernel.pipeline(opened, super::kernel::Variant { rays, ..accel.variant.for_query(query) })?;
    let reduce = match output {
        Output::Pixels { .. } => Some(opened.kernel.reduce_pixels(opened)?),
        _ => None,
    };
    if query.hit_format == HitFormat::Bitmask {
        encoder.clear_buffer(&slot.hits, 0, Some(need.hits));
    }
    encoder.clear_buffer(&slot.tallies, 0, Some(TALLY_BYTES));
    {
        let timestamp_writes = slot.timestamps.as_ref().map(|(queries, _)| wgpu::ComputePassTimestampWrites {
            query_set: queries,
            beginning_of_pass_write_index: Some(0),
            end_of_pass_write_index: Some(1),
        });
        let mut pass =
            encoder.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("rayd trace"), timestamp_writes });
        dispatch_trace(&mut pass, trace, accel, slot, chunk.rays);
        if let (Output::Pixels { image, .. }, Some(reduce)) = (output, reduce) {
            // Dispatches of one pass see each other's writes: the reduction reads the records just traced.
            pass.set_pipeline(reduce);
            pass.dispatch_workgroups((chunk.rays as u32 / image.rays_per_pixel).div_ceil(WORKGROUP_SIZE), 1, 1);
        }
    }
    let given_back = match output {
        Output::Hits(_) => Some(&slot.hits),
        Output::Pixels { .. } => Some(&slot.reduced),
        Output::Tallies => None,
    };
    if let Some(buffer) = given_back {
        encoder.copy_buffer_to_buffer(buffer, 0, &slot.readback, 0, need.given_back);
    }
    encoder.copy_buffer_to_buffer(&slot.tallies, 0, &slot.readback, need.given_back, need.tallies);
    if let Some((queries, resolved)) = &slot.timestamps {
        encoder.resolve_query_set(queries, 0..2, resolved, 0);
        encoder.copy_buffer_to_buffer(resolved, 0, &slot.readback, need.given_back + need.tallies, TIMESTAMP_BYTES);
    }
    let submission = opened.queue.submit([encoder.finish()]);
    let read = request_map(&slot.readback, wgpu::MapMode::Read, need.given_back + need.tallies + TIMESTAMP_BYTES);
    let write =
        matches!(input, Input::Packed(_)).then(|| request_map(&slot.upload, wgpu::MapMode::Write, slot.capacity.rays));
    Ok(InFlight { chunk, need, submission, read, write })
}

/// Bytes a task of [`copy_spread`].
const COPY_PIECE_BYTES: usize = 1 << 20;

/// Copies `from` (a staging buffer's mapped bytes) into `to` (the caller's; the same length) a MiB a task on the
/// rayon pool. One thread was the bottleneck of transfers: on the H100's host it copied 1.5–10 GB/s out of a mapped
/// buffer (the low end when the destination's pages are touched for the first time, as a fresh output buffer's
/// are), 16 threads 37–48 GB/s, while the device fills the staging buffer at 30–44 GB/s (BENCHMARKS.md,
/// "Transfers spread over cores").
fn copy_spread(to: &mut [u8], from: &[u8]) {
    to.par_chunks_mut(COPY_PIECE_BYTES)
        .zip(from.par_chunks(COPY_PIECE_BYTES))
        .for_each(|(to, from)| to.copy_from_slice(from));
}

/// Copies `from` (the caller's rays) into `staging` (a mapped staging range, write-only; the same length) a MiB a
/// task on the rayon pool, as [`copy_spread`] does the other way.
fn upload_spread(mut staging: wgpu::WriteOnly<'_, [u8]>, from: &[u8]) {
    assert_eq!(staging.len(), from.len(), "a staging range and the rays copied into it differ in length");
    let start = StagingStart(staging.as_raw_element_ptr());
    from.par_chunks(COPY_PIECE_BYTES).enumerate().for_each(|(piece, bytes)| {
        // SAFETY: `start` is the first of `from.len()` writable bytes, which `staging` borrows mutably until this
        // function returns; each task writes only its own piece of them (disjoint ranges), and none reads them —
        // the use `WriteOnly::as_raw_ptr` documents (writes from several threads).
        unsafe {
            std::ptr::copy_nonoverlapping(bytes.as_ptr(), start.at(piece * COPY_PIECE_BYTES), bytes.len());
        }
    });
}

/// The first byte of a mapped staging range, shared by the tasks of [`upload_spread`].
struct StagingStart(std::ptr::NonNull<u8>);

impl StagingStart {
    /// The byte `offset` bytes further.
    fn at(&self, offset: usize) -> *mut u8 {
        self.0.as_ptr().wrapping_add(offset)
    }
}

// SAFETY: the tasks of `upload_spread` write disjoint bytes of a range borrowed for the whole copy (see there).
unsafe impl Sync for StagingStart {}

/// Waits for a chunk, copies what it gives back into `output` and adds its statistics; leaves the slot idle
/// (upload mapped, readback unmapped).
fn finish(
    opened: &Opened,
    slot: &Slot,
    flight: InFlight,
    query: &Query,
    ray_work: u32,
    output: &mut Output<'_>,
    stats: &mut TraceStats,
) -> Result<()> {
    wait_mapped(opened, &flight.read, &flight.submission)?;
    if let Some(write) = &flight.write {
        wait_mapped(opened, write, &flight.submission)?;
    }
    let InFlight { chunk, need, .. } = flight;
    {
        let view = slot
            .readback
            .slice(..need.given_back + need.tallies + TIMESTAMP_BYTES)
            .get_mapped_range()
            .map_err(|e| device_error("mapping the hit staging buffer", e))?;
        let tallies = &view[need.given_back as usize..(need.given_back + need.tallies) as usize];
        let ticks = &view[(need.given_back + need.tallies) as usize..];
        // The trace fails (its slots are dropped, not given back).
        let over = read_u32(tallies, 4 * OVER_RAY_WORK);
        if over > 0 {
            let device = opened.name.clone();
            return Err(Error::RayWork {
                device,
                rays: u64::from(over),
                limit: ray_work,
                setting: "scheduler.gpu_ray_work",
            });
        }
        match output {
            Output::Hits(TraceOutput { hits, counts }) => {
                let per_ray = query.records_per_ray();
                let start = query.hit_format.buffer_len(chunk.first * per_ray);
                let len = query.hit_format.buffer_len(chunk.rays * per_ray);
                copy_spread(&mut hits[start..start + len], &view[..len]);
                if query.kind.has_counts() {
                    copy_spread(
                        &mut counts[4 * chunk.first..4 * (chunk.first + chunk.rays)],
                        &tallies[TALLY_BYTES as usize..TALLY_BYTES as usize + 4 * chunk.rays],
                    );
                }
            }
            Output::Pixels { image, pixels } => {
                let (first, len) = (chunk.first / image.rays_per_pixel as usize, need.given_back as usize);
                let count = len / (4 * OnDevice::pixel_words(image) as usize);
                let encoded = image.pixel_bytes();
                encode_pixels(image, &view[..len], &mut pixels[first * encoded..(first + count) * encoded]);
            }
            Output::Tallies => {}
        }
        let wide =
            |word: usize| u64::from(read_u32(tallies, 4 * word)) | u64::from(read_u32(tallies, 4 * word + 4)) << 32;
        stats.add(&TraceStats {
            rays: chunk.rays as u64,
            rays_hit: u64::from(read_u32(tallies, 0)),
            nodes_visited: wide(1),
            triangle_tests: wide(3),
            device_nanos: opened.timestamp_period.map_or(0, |period| elapsed_nanos(ticks, period)),
            // A chunk with such rays fails above.
            rays_past_work: 0,
        });
    }
    slot.readback.unmap();
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn idle_slots_are_kept_smallest_first_within_the_budget() {
        let mut sizes = vec![300, 10, 500, 40, 10];
        keep_within(&mut sizes, |&bytes| bytes, 400);
        assert_eq!(sizes, [10, 10, 40, 300], "the 500 goes; the largest kept is taken first (last)");
        let mut huge = vec![u64::MAX, 1];
        keep_within(&mut huge, |&bytes| bytes, 400);
        assert_eq!(huge, [1]);
        let ordinary = Capacity::for_chunk(
            &Query::closest(crate::format::RayFormat::Full, HitFormat::Full),
            MAX_CHUNK_RAYS,
            &Input::Packed(&[]),
            &Output::Hits(TraceOutput { hits: &mut [], counts: &mut [] }),
        );
        assert!(SLOTS as u64 * ordinary.bytes() <= MAX_IDLE_SLOT_BYTES, "a trace's ordinary slots stay");
    }

    #[test]
    fn an_idle_slot_grows_to_a_traces_need_within_the_limit_or_is_made_anew() {
        let (gives_back, counts) =
            (Capacity { given_back: 900, ..Capacity::default() }, Capacity { tallies: 900, ..Capacity::default() });
        let grown = gives_back.grown_to(counts, 2000);
        assert!(grown.holds(&gives_back) && grown.holds(&counts), "each buffer the larger");
        // Each fits 1,000 bytes alone; grown, the readback (given back, tallies and timestamps) would not.
        assert!(gives_back.largest() <= 1000 && counts.largest() <= 1000 && grown.largest() > 1000);
        assert_eq!(gives_back.grown_to(counts, 1000), counts, "made anew for the trace's own need");
    }

    #[test]
    fn a_chunks_readback_staging_fits_the_limit_as_its_bindings_do() {
        // Counts: the hits are given back, and the counts with the tallies after them, so the readback staging is
        // the largest buffer of a chunk.
        let rays_of_24_bytes = crate::format::RayFormat::OriginDirection;
        let query = Query { kind: QueryKind::Count, ..Query::closest(rays_of_24_bytes, HitFormat::Full) };
        let (rays, output) = (1 << 16, Output::Hits(TraceOutput { hits: &mut [], counts: &mut [] }));
        let whole = Capacity::for_chunk(&query, rays, &Input::Packed(&[]), &output);
        let bindings = whole.rays.max(whole.hits).max(whole.tallies).max(whole.scratch).max(whole.reduced);
        assert!(whole.readback() > bindings);
        let limits = |binding_bytes| ChunkLimits { binding_bytes, chunk_rays: rays, trace_bytes: u64::MAX };
        let plan = Plan::new(&query, rays, &Input::Packed(&[]), &output, limits(bindings)).unwrap();
        assert!(plan.chunk_rays < rays && plan.need.readback() <= bindings, "{} rays a chunk", plan.chunk_rays);
        let plan = Plan::new(&query, rays, &Input::Packed(&[]), &output, limits(whole.readback())).unwrap();
        assert_eq!(plan.chunk_rays, rays);
    }

    #[test]
    fn a_traces_slots_fit_its_budget_and_ordinary_chunks_fit_the_default() {
        let output = Output::Hits(TraceOutput { hits: &mut [], counts: &mut [] });
        let limits = |trace_bytes| ChunkLimits { binding_bytes: u64::MAX, chunk_rays: MAX_CHUNK_RAYS, trace_bytes };
        let closest = Query::closest(crate::format::RayFormat::Full, HitFormat::Full);
        let default = limits(super::super::DEFAULT_MAX_TRACE_BYTES);
        let plan = Plan::new(&closest, 1 << 24, &Input::Packed(&[]), &output, default).unwrap();
        assert_eq!(plan.chunk_rays, MAX_CHUNK_RAYS, "ordinary chunks are not cut");
        // 256 hits a ray: a full chunk's slots take gigabytes, so chunks are cut until two slots fit the budget.
        let all = Query { kind: QueryKind::All, max_hits_per_ray: 256, ..closest };
        let whole = SLOTS as u64 * Capacity::for_chunk(&all, MAX_CHUNK_RAYS, &Input::Packed(&[]), &output).bytes();
        assert!(whole > 8 << 30, "{whole} bytes");
        let plan = Plan::new(&all, 1 << 24, &Input::Packed(&[]), &output, default).unwrap();
        let slots = SLOTS as u64 * plan.need.bytes();
        assert!(
            slots <= default.trace_bytes && 2 * slots > default.trace_bytes,
            "{} rays, {slots} bytes",
            plan.chunk_rays
        );
        // A budget too small for two 32-ray chunks is refused, naming it.
        let Err(Error::TooLarge { what, requested, limit, .. }) =
            Plan::new(&all, 1 << 24, &Input::Packed(&[]), &output, limits(1 << 20))
        else {
            panic!("a 1 MiB budget for 256 hits a ray")
        };
        assert!(what.contains("gpu_trace_bytes") && requested > limit && limit == 1 << 20, "{what}");
    }
}
