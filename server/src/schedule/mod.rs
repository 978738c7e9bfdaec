//! Device work, queued per tenant and served fairly. Each device has a [`Scheduler`]: a few worker threads that take
//! tasks from a [`FairQueue`] in which every tenant has its own queue, weighted by its share. A trace is cut into
//! pieces of at most [`CHUNK_RAYS`] rays on the CPU ([`PART_RAYS`] for rays a generator makes whose hits are reduced;
//! either well under a millisecond), so a tenant that floods the device with million-ray batches holds a worker for
//! one piece at a time, and another tenant's ray waits for at most one piece per worker. Pieces of costly rays have
//! fewer rays, so that each holds a worker for about the scheduler's piece time ([`PieceSizer`]), down to one granule
//! of rays on the CPU and [`GPU_SMALLEST_PIECE_RAYS`] on a GPU, below which a piece is no quicker; a trace queues its
//! pieces one at a time, each as the one before starts, under the trace's arrival number, so that a tenant's traces
//! are still served in arrival order. Tenants are charged the time their pieces hold a worker, so a tenant of costly
//! rays gets as much of the device as one of cheap rays, not as many rays.
//!
//! On the CPU, a task that fits in one piece runs on the caller's thread when a worker slot is free and nothing is
//! queued: an idle server answers a small trace without a hop to another thread, and a busy one queues it like any
//! other (a trace known to take more than a millisecond is queued too: the caller's thread answers every call). A
//! GPU's tasks always run on its workers: a GPU piece may hold the device for seconds (a costly scene, or another
//! tenant's piece ahead of it in the device's queue), and the caller's thread is one of the few that answer every
//! call of the server.

mod fair;
mod pieces;

use std::collections::HashMap;
use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

pub use fair::{FairQueue, Flow};
pub use pieces::{Pace, PieceLimits, PieceSizer};
use rayd_engine::Device;
use rayd_engine::backend::BackendKind;
use rayd_engine::backend::host::PART_RAYS;
use rayd_engine::query::CHUNK_RAYS;

use crate::config::SchedulerConfig;

/// Rays per piece on a GPU when the caller sends the rays: large enough for the backend to overlap its transfers
/// with tracing within a piece (several of its chunks), small enough that another tenant's trace waits for
/// milliseconds, not for a whole batch.
pub const GPU_PIECE_RAYS: usize = 1 << 20;

/// Rays per piece on a GPU when the server makes the rays (a generator): nothing is uploaded, so a piece is the
/// kernels' time alone — about 6 ms for 2^22 camera rays on an H100 at the clock the service runs at — and the
/// device idles between pieces (the host finishes one before the next is queued) a quarter as often as with
/// pieces of [`GPU_PIECE_RAYS`]: on an H100, counts through rayd +9% and depth images +27% (BENCHMARKS.md,
/// "Larger GPU pieces for rays made on the server").
pub const GPU_GENERATED_PIECE_RAYS: usize = 1 << 22;

/// Rays of a GPU piece at least, however costly its rays. On an H100, rays through a pile of 100,000 triangles ran at
/// 0.93 M rays/s in pieces of 2^20 rays, and pieces sized to 100 ms stalled them (BENCHMARKS.md, "Pieces sized by
/// time on an NVIDIA H100"), likely because a GPU runs each ray's tests one after another on one thread: a piece of
/// fewer rays than it runs at once takes about as long as a full one, and cutting pieces smaller makes them slower a
/// ray, not quicker. This is the wgpu backend's largest chunk, which fills an H100.
pub const GPU_SMALLEST_PIECE_RAYS: usize = 1 << 18;

/// Work the scheduler runs; it reports its own results.
pub type Task = Box<dyn FnOnce() + Send>;

/// The fair scheduler of one device.
#[derive(Debug)]
pub struct Scheduler {
    /// What the workers share with the callers.
    shared: Arc<Shared>,
    /// Rays per piece on this device, for rays sent.
    piece_rays: usize,
    /// Rays per piece on this device, for rays made by a generator whose hits are returned.
    generated_piece_rays: usize,
    /// Rays per piece on this device, for rays made by a generator whose hits are reduced.
    reduced_piece_rays: usize,
    /// Rays of a piece at least, however long they take ([`PieceLimits::smallest`]).
    smallest_piece_rays: usize,
    /// About how long a piece may hold a worker ([`PieceSizer`]).
    piece_time: Duration,
    /// Traces that arrived so far ([`Scheduler::arrival`]).
    arrivals: AtomicU64,
    /// Whether a caller may run a task of one piece itself ([`Scheduler::try_slot`]).
    callers_run_small_tasks: bool,
}

/// The queue and the slots, behind one lock.
#[derive(Debug)]
struct Shared {
    /// Tasks waiting, the slots taken and whether the scheduler was dropped.
    state: Mutex<State>,
    /// Signalled when a task is queued, a slot is given back or the scheduler closes.
    changed: Condvar,
    /// Tasks that may run at once (worker threads, and callers running a small task themselves).
    slots: usize,
}

/// The state under [`Shared::state`].
#[derive(Default)]
struct State {
    /// Tasks waiting.
    queue: FairQueue<Task>,
    /// Slots taken by running tasks.
    busy: usize,
    /// Set when the scheduler is dropped: the workers finish what is queued and exit.
    closed: bool,
}

impl std::fmt::Debug for State {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("State").field("queued", &self.queue.len()).field("busy", &self.busy).finish()
    }
}

/// A slot taken by a caller running a task itself; given back when dropped.
#[derive(Debug)]
pub struct Slot<'a> {
    /// The scheduler's shared state.
    shared: &'a Shared,
}

impl Drop for Slot<'_> {
    fn drop(&mut self) {
        self.shared.lock().busy -= 1;
        self.shared.changed.notify_one();
    }
}

impl Shared {
    /// The state; a panic elsewhere while it was held leaves nothing half-done in it, so poisoning is ignored.
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// One worker: takes the next task whenever a slot is free, until the scheduler closes and the queue is empty.
    fn work(&self) {
        loop {
            let (task, charge) = {
                let mut state = self.lock();
                loop {
                    if state.busy < self.slots
                        && let Some(served) = state.queue.pop()
                    {
                        state.busy += 1;
                        break served;
                    }
                    if state.closed && state.queue.is_empty() {
                        return;
                    }
                    state = self.changed.wait(state).unwrap_or_else(|poisoned| poisoned.into_inner());
                }
            };
            let start = Instant::now();
            // A task reports its own failures; one that panics anyway must not take its slot and charge with it.
            let _ = std::panic::catch_unwind(AssertUnwindSafe(task));
            let took = start.elapsed();
            let mut state = self.lock();
            state.queue.settle(charge, took);
            state.busy -= 1;
            drop(state);
            self.changed.notify_one();
        }
    }
}

impl Scheduler {
    /// A scheduler with `workers` threads (at least one) named after `device`, cutting traces into pieces of
    /// `piece_rays` rays at most, and of about `piece_time` each ([`PieceSizer`]). The workers run at nice value
    /// `nice` (0 to 19, above the runtime's threads' 0), so that the threads that receive calls and send answers get
    /// a core as soon as they have work: a small trace is then queued, and answered, without waiting for the
    /// scheduler of the operating system.
    pub fn new(device: &str, workers: usize, piece_rays: usize, piece_time: Duration, nice: u32) -> Scheduler {
        let slots = workers.max(1);
        let shared = Arc::new(Shared { state: Mutex::default(), changed: Condvar::new(), slots });
        for worker in 0..slots {
            let shared = Arc::clone(&shared);
            std::thread::Builder::new()
                .name(format!("rayd-{device}-{worker}"))
                .spawn(move || {
                    lower_priority(nice);
                    shared.work()
                })
                .expect("a worker thread can be started");
        }
        let piece_rays = piece_rays.max(1);
        Scheduler {
            shared,
            piece_rays,
            generated_piece_rays: piece_rays,
            reduced_piece_rays: piece_rays,
            smallest_piece_rays: 1,
            piece_time,
            arrivals: AtomicU64::new(0),
            callers_run_small_tasks: true,
        }
    }

    /// The same, but every task runs on the workers: [`Scheduler::try_slot`] gives no slot.
    pub fn with_every_task_on_the_workers(mut self) -> Scheduler {
        self.callers_run_small_tasks = false;
        self
    }

    /// The same, but cutting traces of rays made by a generator into pieces of `rays` rays.
    pub fn with_generated_pieces(mut self, rays: usize) -> Scheduler {
        (self.generated_piece_rays, self.reduced_piece_rays) = (rays.max(1), rays.max(1));
        self
    }

    /// The same, but cutting traces of rays made by a generator and reduced into pieces of `rays` rays.
    pub fn with_reduced_pieces(mut self, rays: usize) -> Scheduler {
        self.reduced_piece_rays = rays.max(1);
        self
    }

    /// The same, but never cutting a piece below `rays` rays, however long they take.
    pub fn with_smallest_pieces(mut self, rays: usize) -> Scheduler {
        self.smallest_piece_rays = rays.max(1);
        self
    }

    /// The scheduler of `device` as `config` sets it: on the CPU one worker per core (`workers` 0) or `workers`, and
    /// pieces of one engine chunk, or of one engine part ([`PART_RAYS`], which a worker traces alone) for rays made by
    /// a generator and reduced (BENCHMARKS.md, "Reduced pieces of a part on the CPU": +2–6% for counts and images;
    /// the same pieces for every hit of generated rays lost 25%, so those stay one chunk), of about `piece_ms` each;
    /// on a GPU `gpu_workers` workers and pieces of [`GPU_PIECE_RAYS`], or [`GPU_GENERATED_PIECE_RAYS`] for rays made
    /// by a generator, of about `gpu_piece_ms` each but at least [`GPU_SMALLEST_PIECE_RAYS`]. The workers run at
    /// `worker_nice`.
    pub fn for_device(device: &Device, config: &SchedulerConfig) -> Scheduler {
        let (info, nice) = (device.info(), config.worker_nice);
        match info.kind {
            BackendKind::Cpu => {
                let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
                let workers = if config.workers == 0 { cores } else { config.workers as usize };
                let time = Duration::from_millis(config.piece_ms.into());
                Scheduler::new(&info.id, workers, CHUNK_RAYS, time, nice).with_reduced_pieces(PART_RAYS)
            }
            BackendKind::Wgpu => {
                let time = Duration::from_millis(config.gpu_piece_ms.into());
                Scheduler::new(&info.id, config.gpu_workers as usize, GPU_PIECE_RAYS, time, nice)
                    .with_generated_pieces(GPU_GENERATED_PIECE_RAYS)
                    .with_smallest_pieces(GPU_SMALLEST_PIECE_RAYS)
                    .with_every_task_on_the_workers()
            }
        }
    }

    /// What a piece may hold: of rays made by a generator when `generated` (whose hits are reduced when `reduced`),
    /// of rays sent otherwise.
    pub fn piece_limits(&self, generated: bool, reduced: bool) -> PieceLimits {
        let largest = match (generated, reduced) {
            (false, _) => self.piece_rays,
            (true, false) => self.generated_piece_rays,
            (true, true) => self.reduced_piece_rays,
        };
        PieceLimits { largest, smallest: self.smallest_piece_rays, time: self.piece_time }
    }

    /// A slot for the caller to run one small task itself, if callers may
    /// ([`Scheduler::with_every_task_on_the_workers`] says they may not), one is free and no task is waiting (so it
    /// never overtakes queued work).
    pub fn try_slot(&self) -> Option<Slot<'_>> {
        if !self.callers_run_small_tasks {
            return None;
        }
        let mut state = self.shared.lock();
        if state.busy < self.shared.slots && state.queue.is_empty() {
            state.busy += 1;
            return Some(Slot { shared: &self.shared });
        }
        None
    }

    /// A number for a trace that arrives now: larger than every earlier one's ([`Scheduler::submit`]'s `order`).
    pub fn arrival(&self) -> u64 {
        self.arrivals.fetch_add(1, Ordering::Relaxed)
    }

    /// Queues `task` of `flow`, estimated to hold a worker for `estimate` (the flow is charged the time it takes),
    /// behind the flow's tasks of the same or an earlier `order` ([`Scheduler::arrival`]) and ahead of those of a
    /// later one.
    pub fn submit(&self, flow: &Flow, order: u64, estimate: Duration, task: Task) {
        self.shared.lock().queue.push(flow, order, estimate, task);
        self.shared.changed.notify_one();
    }
}

impl Drop for Scheduler {
    fn drop(&mut self) {
        self.shared.lock().closed = true;
        self.shared.changed.notify_all();
    }
}

/// The schedulers of a server's devices, by device id.
#[derive(Debug, Default)]
pub struct Schedulers {
    /// One per device.
    by_device: HashMap<String, Scheduler>,
}

impl Schedulers {
    /// One scheduler per device, as `config` sets them ([`Scheduler::for_device`]).
    pub fn new(devices: &[Device], config: &SchedulerConfig) -> Schedulers {
        let by_device = devices.iter().map(|d| (d.info().id.clone(), Scheduler::for_device(d, config))).collect();
        Schedulers { by_device }
    }

    /// The scheduler of device `id`, if the server has it.
    pub fn get(&self, id: &str) -> Option<&Scheduler> {
        self.by_device.get(id)
    }
}

/// Sets the calling thread's nice value to `nice` (on Linux a nice value is a thread's own); elsewhere, or if the
/// system refuses, the thread keeps its priority.
fn lower_priority(nice: u32) {
    #[cfg(target_os = "linux")]
    // SAFETY: setpriority takes plain integers and changes only the calling thread (`who` 0); it cannot fail
    // unsafely, only return an error, which is ignored (the thread then keeps its priority).
    unsafe {
        libc::setpriority(libc::PRIO_PROCESS, 0, nice.min(19) as libc::c_int);
    }
    #[cfg(not(target_os = "linux"))]
    let _ = nice;
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc;

    const SECOND: Duration = Duration::from_secs(1);
    const MILLISECOND: Duration = Duration::from_millis(1);

    /// A task that says `name` on `done` when it runs.
    fn say(done: &mpsc::Sender<&'static str>, name: &'static str) -> Task {
        let done = done.clone();
        Box::new(move || done.send(name).unwrap())
    }

    fn flow(name: &str) -> Flow {
        Flow { name: name.into(), share: 1 }
    }

    #[test]
    fn queued_tasks_of_a_newcomer_overtake_a_flood() {
        // One worker, held by a task until released, so the order of the rest is the queue's alone.
        let scheduler = Scheduler::new("test", 1, 8, SECOND, 0);
        let (release, gate) = mpsc::channel::<()>();
        let (done, finished) = mpsc::channel::<&'static str>();
        let flood = flow("a");
        scheduler.submit(&flood, 0, MILLISECOND, Box::new(move || gate.recv().unwrap()));
        for _ in 0..100 {
            scheduler.submit(&flood, 0, MILLISECOND, say(&done, "a"));
        }
        scheduler.submit(&flow("b"), 1, MILLISECOND, say(&done, "b"));
        assert!(scheduler.try_slot().is_none(), "work is queued: a caller may not run its own ahead of it");
        release.send(()).unwrap();
        let order: Vec<_> = (0..101).map(|_| finished.recv().unwrap()).collect();
        let b_at = order.iter().position(|&n| n == "b").unwrap();
        assert!(b_at <= 1, "b was served {b_at}th: {order:?}");
    }

    #[test]
    fn a_flow_is_charged_the_time_its_tasks_hold_a_worker() {
        // Both flows' tasks are estimated at 1 ms; a's hold the one worker for 200 ms, b's for microseconds. Charged
        // by estimate they would alternate (a's second task served third); charged by time, b's tasks go before a's
        // second until they too have held the worker for 200 ms (all 20 of them, unless the machine stalls them for
        // that long: a margin for a loaded CI machine, where 50 ms was within reach of one stall).
        let scheduler = Scheduler::new("test", 1, 8, SECOND, 0);
        let (release, gate) = mpsc::channel::<()>();
        let (done, finished) = mpsc::channel::<&'static str>();
        scheduler.submit(&flow("gate"), 0, MILLISECOND, Box::new(move || gate.recv().unwrap()));
        for _ in 0..3 {
            let done = done.clone();
            let slow = move || {
                std::thread::sleep(Duration::from_millis(200));
                done.send("a").unwrap()
            };
            scheduler.submit(&flow("a"), 0, MILLISECOND, Box::new(slow));
        }
        for _ in 0..20 {
            scheduler.submit(&flow("b"), 0, MILLISECOND, say(&done, "b"));
        }
        release.send(()).unwrap();
        let order: Vec<_> = (0..23).map(|_| finished.recv().unwrap()).collect();
        let second_a = order.iter().enumerate().filter(|(_, n)| **n == "a").nth(1).unwrap().0;
        assert!(second_a > 10, "{order:?}");
    }

    #[test]
    fn a_task_that_panics_leaves_its_worker_and_slot_to_the_next() {
        let scheduler = Scheduler::new("test", 1, 8, SECOND, 0);
        let (done, finished) = mpsc::channel();
        scheduler.submit(&flow("a"), 0, MILLISECOND, Box::new(|| panic!("a task's bug")));
        scheduler.submit(&flow("a"), 0, MILLISECOND, say(&done, "next"));
        assert_eq!(finished.recv_timeout(10 * SECOND), Ok("next"), "one slot: the panicked task's was given back");
        // The worker gives the next task's slot back just after the task has said so (CI once saw it still taken).
        let since = Instant::now();
        while scheduler.try_slot().is_none() {
            assert!(since.elapsed() < 10 * SECOND, "the slot was never given back");
            std::thread::sleep(MILLISECOND);
        }
    }

    #[test]
    fn rays_made_by_a_generator_are_cut_into_their_own_pieces() {
        let pieces = |scheduler: &Scheduler| {
            [(false, false), (true, false), (true, true)]
                .map(|(generated, reduced)| scheduler.piece_limits(generated, reduced).largest)
        };
        let scheduler = Scheduler::new("test", 1, 8, SECOND, 0);
        assert_eq!(pieces(&scheduler), [8, 8, 8]);
        let scheduler = scheduler.with_generated_pieces(32);
        assert_eq!(pieces(&scheduler), [8, 32, 32]);
        assert_eq!(pieces(&scheduler.with_reduced_pieces(64)), [8, 32, 64]);
        // The CPU's pieces are one engine chunk, or one engine part for generated rays reduced, of `piece_ms` each.
        let config = SchedulerConfig { workers: 1, worker_nice: 0, piece_ms: 7, ..SchedulerConfig::default() };
        let cpu = Scheduler::for_device(&rayd_engine::Device::cpu(), &config);
        assert_eq!(pieces(&cpu), [CHUNK_RAYS, CHUNK_RAYS, PART_RAYS]);
        assert_eq!(cpu.piece_limits(true, true).time, Duration::from_millis(7));
        // Costly rays on the CPU may come one granule at a time; a GPU keeps its smallest pieces for every kind.
        assert_eq!(cpu.piece_limits(false, false).smallest, 1);
        let gpu = Scheduler::new("test", 1, 1 << 20, SECOND, 0).with_smallest_pieces(GPU_SMALLEST_PIECE_RAYS);
        assert_eq!([false, true].map(|reduced| gpu.piece_limits(true, reduced).smallest), [1 << 18; 2]);
    }

    #[test]
    fn an_idle_scheduler_lends_its_slots_to_callers() {
        let scheduler = Scheduler::new("test", 2, 8, SECOND, 0);
        let first = scheduler.try_slot().expect("idle");
        let second = scheduler.try_slot().expect("two slots");
        assert!(scheduler.try_slot().is_none(), "both slots taken");
        drop(first);
        assert!(scheduler.try_slot().is_some());
        drop(second);
        // A GPU's: none, idle or not.
        let gpu = Scheduler::new("test", 2, 8, SECOND, 0).with_every_task_on_the_workers();
        assert!(gpu.try_slot().is_none(), "a caller ran a task of a scheduler whose tasks run on its workers");
    }

    #[test]
    fn workers_wait_for_slots_that_callers_hold() {
        let scheduler = Scheduler::new("test", 1, 8, SECOND, 0);
        let slot = scheduler.try_slot().expect("idle");
        let (done, finished) = mpsc::channel();
        scheduler.submit(&flow("a"), 0, MILLISECOND, say(&done, "a"));
        assert!(finished.recv_timeout(std::time::Duration::from_millis(50)).is_err(), "ran beside a held slot");
        drop(slot);
        finished.recv_timeout(std::time::Duration::from_secs(10)).expect("runs once the slot is back");
    }
}
