//! A tenant's traces: checked against its limits, then cut into pieces that the fair scheduler of the accel's
//! device serves among every tenant's pieces ([`crate::schedule`]). Each piece writes in place into its share of
//! one hit buffer and one counts buffer, which are handed back whole, without copying, when the last piece is done.

use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use bytes::{Bytes, BytesMut};
use rayd_engine::Accel;
use rayd_engine::backend::RaySource;
use rayd_engine::query::{OutputLayout, Query, TraceOutput, TraceStats};
use rayd_engine::raygen::Generator;
use rayd_engine::reduce::{Partial, Reduction};
use tokio::sync::oneshot;

use super::quota::Running;
use super::{AccelEntry, Tenant, TraceResult};
use crate::error::{ServiceError, ServiceResult};
use crate::schedule::{Pace, PieceSizer, Scheduler};

/// The rays of a trace.
#[derive(Debug, Clone)]
pub enum Rays {
    /// Packed in the query's ray format, as sent.
    Packed(Bytes),
    /// Made by a checked generator, piece by piece, where they are traced: its rays in the range (non-empty,
    /// within the generator).
    Generated(Arc<Generator>, std::ops::Range<u64>),
}

impl Rays {
    /// Rays in the batch, for records of `ray_size` bytes.
    pub fn count(&self, ray_size: usize) -> u64 {
        match self {
            Rays::Packed(bytes) => (bytes.len() / ray_size) as u64,
            Rays::Generated(_, range) => range.end - range.start,
        }
    }

    /// Bytes the rays take packed (whole records only for a generator).
    fn byte_len(&self, ray_size: usize) -> usize {
        match self {
            Rays::Packed(bytes) => bytes.len(),
            Rays::Generated(_, range) => (range.end - range.start) as usize * ray_size,
        }
    }

    /// The rays in bytes `range` of the packed batch: a slice of the sent bytes, or the generator's rays there.
    fn piece(&self, query: &Query, range: std::ops::Range<usize>) -> RaySource<'_> {
        match self {
            Rays::Packed(bytes) => RaySource::Packed(&bytes[range]),
            Rays::Generated(generator, rays) => {
                let size = query.ray_format.size();
                let first = rays.start + (range.start / size) as u64;
                RaySource::Generated { generator, first, count: range.len() / size }
            }
        }
    }
}

impl Tenant {
    /// Fails with RESOURCE_EXHAUSTED naming `max_rays_per_batch` (and `field`, which holds the rays) if a batch of
    /// `rays` rays is too large.
    pub fn check_batch_rays(&self, field: &str, rays: u64) -> ServiceResult<()> {
        ServiceError::check_limit(
            || format!("rays in one batch ({field})"),
            rays,
            "max_rays_per_batch",
            self.limits.max_rays_per_batch,
        )
    }

    /// Traces `rays` against `accel` into fresh reply buffers — or, with a `reduction` (checked by the caller),
    /// into its result — once the limits allow it, through the fair scheduler of the accel's device. A trace of at
    /// most one piece, and at most [`CALLER_TRACE_TIME`] at its rays' known cost, runs right here when the device
    /// lends its callers a free slot (the CPU's, with nothing queued: [`crate::schedule::Scheduler::try_slot`]).
    pub async fn trace(
        self: &Arc<Self>,
        accel: &AccelEntry,
        query: &Query,
        rays: Rays,
        reduction: Option<Arc<Reduction>>,
    ) -> ServiceResult<TraceResult> {
        let ray_size = query.ray_format.size();
        // A TraceStream chunk's field; the other calls checked theirs, naming it.
        self.check_batch_rays("rays", rays.count(ray_size))?;
        let layout = match &reduction {
            None => query.output_layout(rays.byte_len(ray_size))?,
            Some(_) => OutputLayout { rays: rays.count(ray_size) as usize, hits: 0, counts: 0 },
        };
        let operation = self.quotas.start(self.limits.max_concurrent_operations)?;
        if let Rays::Packed(bytes) = &rays {
            // Checked on the whole batch, so that the error names the ray by its index in the batch.
            query.check_times(bytes)?;
        }
        let scheduler = self.schedulers.get(&accel.device).ok_or_else(|| ServiceError::NotFound {
            what: "device",
            name: accel.device.clone(),
            field: String::new(),
        })?;
        // Taken last: a request refused for another reason spends none of the allowance.
        self.quotas.take_rays(layout.rays as u64, self.limits.max_rays_per_second)?;
        // Rays that reduce together stay in one piece; pieces of hits are whole bytes of a bitmask.
        let granule = reduction.as_ref().map_or(HIT_GRANULE, |r| r.group_rays());
        let generated = matches!(rays, Rays::Generated(..));
        let limits = scheduler.piece_limits(generated, reduction.is_some());
        let known = accel.pace.get(query.kind);
        let sizer = PieceSizer::new(limits, granule, known);
        let first_piece = sizer.next();
        // Whether the trace may run on this thread, one of the few that answer every call of the server: at most
        // [`CALLER_TRACE_TIME`] at the rays' known cost. A trace of rays of unknown cost may (it teaches the cost).
        let quick = known.is_none() || sizer.estimate(layout.rays) <= CALLER_TRACE_TIME;
        let first_estimate = sizer.estimate(first_piece.min(layout.rays));
        let untaken = (BytesMut::zeroed(layout.hits), BytesMut::zeroed(layout.counts));
        let job = Arc::new(TraceJob {
            tenant: Arc::clone(self),
            accel: Arc::clone(&accel.accel),
            pace: Arc::clone(&accel.pace),
            device: accel.device.clone(),
            order: scheduler.arrival(),
            arrived: Instant::now(),
            query: *query,
            reduction,
            rays,
            abandoned: AtomicBool::new(false),
            progress: Mutex::new(Progress::new(sizer, untaken, operation)),
        });
        // A quick trace of one piece runs here if the device lends a slot; an empty one always does (it has no work).
        let slot = (layout.rays <= first_piece && quick).then(|| scheduler.try_slot()).flatten();
        if slot.is_some() || layout.rays == 0 {
            let piece = job.progress().take_piece(&job).expect("every ray is left").0;
            let Piece { index, rays, output } = piece;
            let (traced, took) = job.trace_piece_timed(rays.clone(), output);
            let mut progress = job.progress();
            // Whatever its rays, it teaches their cost if none is known or it held this thread too long: a trace of a
            // few costly rays must not run here again and again.
            progress.record(&job, index, rays, took, traced, Teach::IfStalled);
            return progress.finish(&job);
        }
        let (reply, result) = oneshot::channel();
        job.progress().reply = Some(reply);
        let _abandon_if_dropped = Abandon(Arc::clone(&job));
        job.queue_next(scheduler, first_estimate);
        let result = result.await.map_err(|_| ServiceError::Internal("a trace ended without an answer".into()))??;
        Ok(result)
    }
}

/// Longest a trace may run on the thread that took its call, at its rays' known cost ([`crate::schedule::Pace`]):
/// a thread of the async runtime, which answers every call, so a costly trace there would stall the others. A trace
/// that takes longer gains nothing measurable from skipping the hand-off to a worker (tens of microseconds).
const CALLER_TRACE_TIME: Duration = Duration::from_millis(1);

/// Which pieces teach the accel's pace ([`Progress::record`]).
#[derive(Debug, Clone, Copy)]
enum Teach {
    /// A piece with rays on the caller's thread, when no pace is known or it held the thread longer than
    /// [`CALLER_TRACE_TIME`]: it raises the pace, never lowers it (a few cheap rays, say misses, must not make costly
    /// ones look cheap; a few rays' fixed cost, microseconds, must not make every ray look costly).
    IfStalled,
    /// Pieces of a probe's rays or more ([`PieceSizer::teaches_pace`]).
    FromAProbe,
}

/// Pieces of hit records are multiples of this many rays, so that the pieces of a bitmask (one bit a ray) are
/// whole bytes, and whole words for the devices that write it by words.
const HIT_GRANULE: usize = 32;

/// A trace cut into pieces as it goes: each piece, as it starts, queues the next (sized by how long the pieces so
/// far took: [`PieceSizer`]); the piece that finishes last answers the caller.
struct TraceJob {
    /// Whose trace it is.
    tenant: Arc<Tenant>,
    /// What is traced (kept alive while pieces wait).
    accel: Arc<Accel>,
    /// How fast the accel's rays were traced lately; learns from this trace's pieces.
    pace: Arc<Pace>,
    /// The device the accel lives on.
    device: String,
    /// When it arrived at the device's scheduler: its pieces go ahead of later traces' of the same tenant.
    order: u64,
    /// When it arrived, for the time it waited before its first piece started.
    arrived: Instant,
    /// What is asked of every ray.
    query: Query,
    /// What the hits are reduced to, if not returned.
    reduction: Option<Arc<Reduction>>,
    /// Every ray of the trace.
    rays: Rays,
    /// Set when the caller went away or a piece failed: no further piece is taken.
    abandoned: AtomicBool,
    /// The pieces taken and what they finished so far.
    progress: Mutex<Progress>,
}

/// The pieces' results, gathered.
struct Progress {
    /// Each piece's output in ray order, once traced.
    outputs: Vec<Option<PieceOutput>>,
    /// Bytes of the batch's rays taken by pieces so far.
    taken: usize,
    /// What pieces have not taken of the hit and counts buffers yet (empty for a reduction).
    untaken: (BytesMut, BytesMut),
    /// Sizes the pieces.
    sizer: PieceSizer,
    /// Pieces taken and not finished.
    running: usize,
    /// Whether a piece is queued and has not started (it holds the job, and so its rays and buffers).
    queued: bool,
    /// The partials of a reduction that folds in any order ([`Reduction::folds_in_any_order`]), folded as their
    /// pieces finish: a trace of thousands of pieces keeps one, not thousands.
    folded: Option<Partial>,
    /// The bytes of the pieces' ordered records so far, which the answer will hold
    /// ([`Reduction::answer_holds_the_records`]).
    ordered_bytes: u64,
    /// The sum of the finished pieces' statistics.
    stats: TraceStats,
    /// The first failure of a piece: the answer.
    failure: Option<ServiceError>,
    /// When the first piece started.
    started: Option<Instant>,
    /// Where the answer goes (none while a caller traces the whole batch itself).
    reply: Option<oneshot::Sender<ServiceResult<TraceResult>>>,
    /// The trace's place among the tenant's operations running at once, let go as the answer is sent, or else with
    /// the job: pieces of an abandoned trace still queued hold its rays and buffers until they are skipped, so it
    /// counts as running until then (a tenant cannot pile up abandoned traces beyond `max_concurrent_operations`).
    operation: Option<Running>,
}

/// A piece taken: the rays it traces and where its output goes.
struct Piece {
    /// Its place among the trace's pieces.
    index: usize,
    /// Its rays: bytes of the packed batch.
    rays: std::ops::Range<usize>,
    /// Its share of the hit and counts buffers (empty for a reduction).
    output: (BytesMut, BytesMut),
}

/// What a piece leaves: its share of the hit and counts buffers, or its reduction.
enum PieceOutput {
    /// Hit records and counts, written in place.
    Hits(BytesMut, BytesMut),
    /// The piece's hits, reduced.
    Reduced(Partial),
    /// The piece's hits, reduced and folded into [`Progress::folded`].
    Folded,
}

/// Abandons the job when the caller's future is dropped (the client went away or its deadline passed).
struct Abandon(Arc<TraceJob>);

impl Drop for Abandon {
    fn drop(&mut self) {
        self.0.abandoned.store(true, Ordering::Release);
    }
}

/// Answers the caller with an internal error when a piece's task panics outside its trace (a bug in recording or
/// joining the pieces: [`TraceJob::trace_piece_timed`] catches the engine's own): the caller's future holds the job
/// and so the reply's sender, and would otherwise wait for an answer that never comes. The job is abandoned, so its
/// pieces still queued are skipped; its operation's place goes with the job, once they are.
struct AnswerOnPanic<'a>(&'a TraceJob);

impl Drop for AnswerOnPanic<'_> {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            return;
        }
        let job = self.0;
        job.abandoned.store(true, Ordering::Release);
        if let Some(reply) = job.progress().reply.take() {
            let what = format!("the server's bookkeeping of a trace on device {:?} panicked (a bug)", job.device);
            let _ = reply.send(Err(ServiceError::Internal(what)));
        }
    }
}

impl TraceJob {
    /// The job's progress. A panic while it was held ([`AnswerOnPanic`]) leaves the lock poisoned and the job
    /// abandoned: later pieces only find that they have nothing to take.
    fn progress(&self) -> MutexGuard<'_, Progress> {
        self.progress.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Queues the job's next piece, estimated to take `estimate` (the fair queue charges the tenant the time it
    /// takes; the piece takes its rays when it starts).
    fn queue_next(self: &Arc<Self>, scheduler: &Scheduler, estimate: Duration) {
        self.progress().queued = true;
        let job = Arc::clone(self);
        scheduler.submit(&self.tenant.flow, self.order, estimate, Box::new(move || job.run_next()));
    }

    /// Takes the next piece, queues the one after it, traces it, and answers when it was the last; takes none when
    /// no rays are left or the job was abandoned (and answers when nothing else runs).
    fn run_next(self: &Arc<Self>) {
        // Declared first, so dropped last: after any lock a panic below leaves held.
        let _answer_on_panic = AnswerOnPanic(self);
        let mut progress = self.progress();
        progress.queued = false;
        let Some((piece, after)) = progress.take_piece(self) else {
            if progress.taken < self.rays.byte_len(self.query.ray_format.size()) {
                crate::metrics::piece(&self.tenant.name, "skipped");
            }
            if progress.started.is_none() {
                // Given up before its first piece: it waited until now.
                crate::metrics::queued(&self.tenant.name, self.arrived.elapsed());
            }
            return self.answer_if_done(&mut progress);
        };
        drop(progress);
        if let Some(estimate) = after
            && let Some(scheduler) = self.tenant.schedulers.get(&self.device)
        {
            self.queue_next(scheduler, estimate);
        }
        let Piece { index, rays, output } = piece;
        let (traced, took) = self.trace_piece_timed(rays.clone(), output);
        crate::metrics::piece(&self.tenant.name, if traced.is_ok() { "traced" } else { "failed" });
        let mut progress = self.progress();
        progress.record(self, index, rays, took, traced, Teach::FromAProbe);
        self.answer_if_done(&mut progress);
    }

    /// Traces the rays in bytes `rays` of the batch into `output` (its share of the reply buffers), or into a
    /// scratch buffer that the job's reduction reduces.
    fn trace_piece(
        &self,
        rays: std::ops::Range<usize>,
        (mut hits, mut counts): (BytesMut, BytesMut),
    ) -> ServiceResult<(PieceOutput, TraceStats)> {
        let context = self.tenant.context(&self.device)?.1;
        let first_ray = (rays.start / self.query.ray_format.size()) as u64;
        let rays = self.rays.piece(&self.query, rays);
        let Some(reduction) = &self.reduction else {
            let output = TraceOutput { hits: &mut hits, counts: &mut counts };
            let stats = context.trace_source(&self.accel, &self.query, rays, output)?;
            return Ok((PieceOutput::Hits(hits, counts), stats));
        };
        let (reduced, stats) = context.trace_reduced(&self.accel, &self.query, rays, first_ray, reduction)?;
        Ok((PieceOutput::Reduced(reduced), stats))
    }

    /// [`TraceJob::trace_piece`], where a bug in the engine fails this trace, not the thread (a worker, or the
    /// caller's: one of those that answer every call) nor the other pieces waiting on it; and how long it took,
    /// also recorded as the tenant's device time.
    fn trace_piece_timed(
        &self,
        rays: std::ops::Range<usize>,
        output: (BytesMut, BytesMut),
    ) -> (ServiceResult<(PieceOutput, TraceStats)>, Duration) {
        let first_ray = rays.start / self.query.ray_format.size();
        let start = Instant::now();
        let traced =
            std::panic::catch_unwind(AssertUnwindSafe(|| self.trace_piece(rays, output))).unwrap_or_else(|_| {
                Err(ServiceError::Internal(format!("tracing the piece from ray {first_ray} panicked")))
            });
        let took = start.elapsed();
        crate::metrics::piece_time(&self.tenant.name, &self.device, took);
        (traced, took)
    }

    /// Sends the answer if no piece runs and none is left to take (every ray taken, or the job abandoned), once.
    fn answer_if_done(&self, progress: &mut Progress) {
        let all_taken = progress.taken == self.rays.byte_len(self.query.ray_format.size());
        if progress.running == 0
            && (all_taken || self.abandoned.load(Ordering::Acquire))
            && let Some(reply) = progress.reply.take()
        {
            // Rays left untaken: the caller went away (nobody wants the answer, so none is made) or a piece failed.
            let answer = match progress.failure.take() {
                Some(failure) => Err(failure),
                None if !all_taken => Err(abandoned()),
                None => progress.finish(self),
            };
            // Let go before the caller hears, so that its next operation finds the place free; but a piece still
            // queued (the caller went, or a piece failed, while the one before it ran) holds the job's rays and
            // buffers until it is skipped, and the place goes with the job then.
            if !progress.queued {
                progress.operation = None;
            }
            let _ = reply.send(answer);
        }
    }
}

impl Progress {
    /// Nothing taken yet: pieces sized by `sizer` take their shares of `untaken` (the reply's hit and counts buffers);
    /// the trace holds `operation` until it answers.
    fn new(sizer: PieceSizer, untaken: (BytesMut, BytesMut), operation: Running) -> Progress {
        Progress {
            outputs: Vec::new(),
            taken: 0,
            untaken,
            sizer,
            running: 0,
            queued: false,
            folded: None,
            ordered_bytes: 0,
            stats: TraceStats::default(),
            failure: None,
            started: None,
            reply: None,
            operation: Some(operation),
        }
    }

    /// The next piece of `job` (as many rays as the sizer says, or those left), and about how long the piece after
    /// it will take, if rays are left; none when no rays are left or the job was abandoned.
    fn take_piece(&mut self, job: &TraceJob) -> Option<(Piece, Option<Duration>)> {
        let ray_size = job.query.ray_format.size();
        let total = job.rays.byte_len(ray_size);
        // An empty batch is one empty piece.
        let none_left = self.taken == total && (total > 0 || !self.outputs.is_empty());
        if none_left || job.abandoned.load(Ordering::Acquire) {
            return None;
        }
        let rays = self.taken..total.min(self.taken + self.sizer.next() * ray_size);
        self.taken = rays.end;
        let output = match job.reduction {
            Some(_) => (BytesMut::new(), BytesMut::new()),
            None => {
                let layout = job.query.output_layout(rays.len()).expect("a whole number of rays");
                (self.untaken.0.split_to(layout.hits), self.untaken.1.split_to(layout.counts))
            }
        };
        if self.started.is_none() {
            crate::metrics::queued(&job.tenant.name, job.arrived.elapsed());
            self.started = Some(Instant::now());
        }
        self.outputs.push(None);
        self.running += 1;
        let left = (total - self.taken) / ray_size;
        let piece = Piece { index: self.outputs.len() - 1, rays, output };
        Some((piece, (left > 0).then(|| self.sizer.estimate(self.sizer.next().min(left)))))
    }

    /// Records how piece `index` of `job` went (`traced`, the rays in bytes `rays` of the batch, taking `took`):
    /// its output kept ([`Progress::keep`]) and its statistics added, its rate taught to the sizer and, as `teach`
    /// says, to the accel's pace; or the job's first failure, which abandons it.
    fn record(
        &mut self,
        job: &TraceJob,
        index: usize,
        rays: std::ops::Range<usize>,
        took: Duration,
        traced: ServiceResult<(PieceOutput, TraceStats)>,
        teach: Teach,
    ) {
        match traced.and_then(|(output, stats)| Ok((self.keep(job, output)?, stats))) {
            Ok((output, stats)) => {
                let rays = rays.len() / job.query.ray_format.size();
                let ns_per_ray = self.sizer.learn(rays, took);
                // An empty batch's piece teaches nothing.
                match teach {
                    Teach::FromAProbe if rays > 0 && self.sizer.teaches_pace(rays) => {
                        job.pace.set(job.query.kind, ns_per_ray)
                    }
                    Teach::IfStalled
                        if rays > 0 && (job.pace.get(job.query.kind).is_none() || took > CALLER_TRACE_TIME) =>
                    {
                        job.pace.raise(job.query.kind, ns_per_ray)
                    }
                    _ => {}
                }
                self.stats.add(&stats);
                self.outputs[index] = Some(output);
            }
            Err(error) => {
                job.abandoned.store(true, Ordering::Release);
                self.failure.get_or_insert(error);
            }
        }
        self.running -= 1;
    }

    /// What is kept of a piece's `output`: a reduction that folds in any order folded into [`Progress::folded`]; the
    /// rest as it is, once ordered records that pass `max_message_bytes` have failed the trace (its answer could not
    /// be sent: the pieces left are skipped).
    fn keep(&mut self, job: &TraceJob, output: PieceOutput) -> ServiceResult<PieceOutput> {
        let (Some(reduction), PieceOutput::Reduced(partial)) = (&job.reduction, &output) else { return Ok(output) };
        if reduction.folds_in_any_order() {
            let PieceOutput::Reduced(partial) = output else { unreachable!("matched above") };
            self.folded.get_or_insert_with(|| reduction.empty()).merge(partial);
            return Ok(PieceOutput::Folded);
        }
        if let Partial::Ordered { bytes, .. } = partial
            && reduction.answer_holds_the_records()
        {
            self.ordered_bytes += bytes.len() as u64;
            ServiceError::check_limit(
                || {
                    format!(
                        "the reduction's records so far ({} bytes); reduce ranges of the batch in several calls",
                        self.ordered_bytes
                    )
                },
                self.ordered_bytes,
                "max_message_bytes",
                job.tenant.limits().max_message_bytes,
            )?;
        }
        Ok(output)
    }

    /// The answer once every piece of `job` is done: the first failure, or the outputs joined back into whole
    /// buffers, or the pieces' reductions folded in ray order.
    fn finish(&mut self, job: &TraceJob) -> ServiceResult<TraceResult> {
        if let Some(failure) = self.failure.take() {
            return Err(failure);
        }
        let mut outputs = std::mem::take(&mut self.outputs).into_iter();
        let mut trace = TraceResult { stats: self.stats, pieces: outputs.len(), ..Default::default() };
        match &job.reduction {
            None => {
                let Some(Some(PieceOutput::Hits(mut hits, mut counts))) = outputs.next() else {
                    return Err(abandoned());
                };
                for output in outputs {
                    let Some(PieceOutput::Hits(more_hits, more_counts)) = output else { return Err(abandoned()) };
                    // The pieces were split off one buffer in order, so joining them back copies nothing.
                    hits.unsplit(more_hits);
                    counts.unsplit(more_counts);
                }
                (trace.hits, trace.counts) = (hits.freeze(), counts.freeze());
            }
            Some(reduction) => {
                let mut partials = Vec::with_capacity(outputs.len());
                for output in outputs {
                    match output {
                        Some(PieceOutput::Reduced(partial)) => partials.push(partial),
                        Some(PieceOutput::Folded) => {}
                        _ => return Err(abandoned()),
                    }
                }
                let mut folded = self.folded.take().unwrap_or_else(|| reduction.empty());
                folded.merge_all(partials);
                let rays = job.rays.count(job.query.ray_format.size());
                trace.reduced = Some(reduction.finish(folded, rays)?);
            }
        }
        trace.trace_ns = self.started.map_or(0, |started| started.elapsed().as_nanos() as u64);
        Ok(trace)
    }
}

/// The answer of a trace whose caller went away (nobody reads it).
fn abandoned() -> ServiceError {
    ServiceError::Transport(tonic::Status::cancelled("the caller went away before the trace finished"))
}

#[cfg(test)]
mod tests {
    use rayd_engine::Device;
    use rayd_engine::accel::BuildOptions;
    use rayd_engine::format::{HitFormat, Ray, RayFormat};
    use rayd_engine::geometry::{BuildInput, TriangleInput};
    use rayd_engine::glam::Vec3A;
    use rayd_engine::query::QueryKind;
    use rayd_engine::reduce::Reduction;

    use super::*;
    use crate::config::{Limits, SchedulerConfig};
    use crate::schedule::Schedulers;
    use crate::tenant::Caller;
    use crate::tenant::DEFAULT_DEVICE;

    /// Copies of one triangle in the pile: every ray through it tests each (20 million tests a 1,024-ray piece,
    /// far more than a millisecond on any core).
    const PILE: usize = 20_000;

    /// A tenant on a CPU with two workers, whose pieces may take `piece_ms`, with the pile built as `pile`.
    fn tenant_with_a_pile(piece_ms: u32) -> (Arc<Tenant>, AccelEntry) {
        let devices = [Device::cpu()];
        let config = SchedulerConfig { workers: 2, piece_ms, ..SchedulerConfig::default() };
        tenant_with_a_pile_on("t", Limits::default(), Arc::new(Schedulers::new(&devices, &config)))
    }

    /// Tenant `name` with `limits` on a CPU served by `schedulers`, with the pile built as `pile`.
    fn tenant_with_a_pile_on(name: &str, limits: Limits, schedulers: Arc<Schedulers>) -> (Arc<Tenant>, AccelEntry) {
        let tenant = Arc::new(Tenant::new(name, limits, 1, &[Device::cpu()], schedulers));
        let vertices: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
        let indices: Vec<u8> = [0u32, 1, 2].repeat(PILE).iter().flat_map(|i| i.to_le_bytes()).collect();
        let input = [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
        let options = BuildOptions::default();
        let entry = tenant
            .build_accel(
                "pile",
                DEFAULT_DEVICE,
                &Caller::default(),
                |context| context.compute_memory_usage(&input, &options),
                |context| context.build_accel(&input, &options),
            )
            .unwrap();
        (tenant, entry)
    }

    /// `count` rays: every third misses the pile, the rest cross it.
    fn rays(count: usize) -> Bytes {
        rays_at(count, |i| if i % 3 == 0 { 5.0 } else { 0.25 })
    }

    /// `count` rays down the z axis, ray `i` at x = `x(i)` (and y = 0.25): through the pile for x within 0 to 0.75.
    fn rays_at(count: usize, x: impl Fn(usize) -> f32) -> Bytes {
        let format = RayFormat::OriginTminDirectionTmax;
        let mut bytes = vec![0; count * format.size()];
        for (i, record) in bytes.chunks_exact_mut(format.size()).enumerate() {
            let ray = Ray {
                origin: Vec3A::new(x(i), 0.25, 1.0),
                direction: Vec3A::new(0.0, 0.0, -1.0),
                tmax: f32::INFINITY,
                ..Ray::default()
            };
            format.encode(&ray, record);
        }
        Bytes::from(bytes)
    }

    /// Traces `rays` for `tenant` on a runtime of its own, reduced by `reduction` if given.
    fn trace(
        tenant: &Arc<Tenant>,
        entry: &AccelEntry,
        query: &Query,
        rays: Rays,
        reduction: Option<Reduction>,
    ) -> TraceResult {
        let runtime = tokio::runtime::Builder::new_current_thread().build().unwrap();
        runtime.block_on(tenant.trace(entry, query, rays, reduction.map(Arc::new))).unwrap()
    }

    #[test]
    fn costly_rays_are_cut_into_pieces_of_the_piece_time_and_answer_the_same_bytes() {
        let (tenant, entry) = tenant_with_a_pile(1);
        let rays = rays(4096);
        let closest = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        let any = Query { kind: QueryKind::Any, hit_format: HitFormat::Bitmask, ..closest };
        let all = Query { kind: QueryKind::All, hit_format: HitFormat::TTriid, max_hits_per_ray: 3, ..closest };
        // An any-hit ray stops at the pile's first triangle: cheap rays, in pieces as large as usual.
        for (query, costly) in [(closest, true), (any, false), (all, true)] {
            let kind = query.kind;
            assert_eq!(entry.pace.get(kind), None, "nothing traced yet");
            let traced = trace(&tenant, &entry, &query, Rays::Packed(rays.clone()), None);
            let pace = entry.pace.get(kind).expect("the trace taught the accel's pace");
            if costly {
                // Pieces of 1,024 rays (the CPU's largest) would be four; a millisecond holds a few dozen rays.
                assert!(traced.pieces > 16, "{kind:?}: {} pieces", traced.pieces);
                assert!(pace > 1e3, "{kind:?}: {pace} ns a ray through {PILE} triangles");
            }
            // The same bytes as one trace of the whole batch by the engine.
            let layout = query.output_layout(rays.len()).unwrap();
            let (mut hits, mut counts) = (vec![0; layout.hits], vec![0; layout.counts]);
            let whole = tenant.context(DEFAULT_DEVICE).unwrap().1;
            whole
                .trace_source(
                    &entry.accel,
                    &query,
                    RaySource::Packed(&rays),
                    TraceOutput { hits: &mut hits, counts: &mut counts },
                )
                .unwrap();
            assert_eq!((&traced.hits[..], &traced.counts[..]), (&hits[..], &counts[..]), "{kind:?}");
        }
        // A one-ray trace, whose time is mostly its fixed cost, does not teach the accel's pace.
        let pace = entry.pace.get(QueryKind::Closest);
        let one = rays.slice(..RayFormat::OriginTminDirectionTmax.size());
        assert_eq!(trace(&tenant, &entry, &closest, Rays::Packed(one), None).stats.rays, 1);
        assert_eq!(entry.pace.get(QueryKind::Closest), pace);
        // Rays reduced in groups of three stay whole groups in every piece: the nearest hit of each group is the
        // engine's over the whole batch.
        let reduction = Reduction::NearestPerGroup { group: 3 };
        let rays = rays.slice(..rays.len() / 96 * 96);
        let query = Query { hit_format: HitFormat::T, ..closest };
        let traced = trace(&tenant, &entry, &query, Rays::Packed(rays.clone()), Some(reduction.clone()));
        assert!(traced.pieces > 16, "{} pieces", traced.pieces);
        let whole = tenant.context(DEFAULT_DEVICE).unwrap().1;
        let (partial, _) = whole.trace_reduced(&entry.accel, &query, RaySource::Packed(&rays), 0, &reduction).unwrap();
        let count = (rays.len() / query.ray_format.size()) as u64;
        assert_eq!(traced.reduced, Some(reduction.finish(partial, count).unwrap()));
    }

    #[test]
    fn traces_given_up_while_queued_hold_their_places_until_their_pieces_are_skipped() {
        // A long trace's pieces go ahead of the tenant's later traces; those given up meanwhile keep their rays in
        // their queued pieces, so they count against max_concurrent_operations until the pieces are skipped.
        let devices = [Device::cpu()];
        let config = SchedulerConfig { workers: 2, piece_ms: 1, ..SchedulerConfig::default() };
        let limits = Limits { max_concurrent_operations: 4, ..Limits::default() };
        let (tenant, entry) = tenant_with_a_pile_on("t", limits, Arc::new(Schedulers::new(&devices, &config)));
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
        let operations = || tenant.usage().operations;
        std::thread::scope(|scope| {
            let long = scope.spawn(|| trace(&tenant, &entry, &query, Rays::Packed(rays_at(16384, |_| 0.25)), None));
            while entry.pace.get(QueryKind::Closest).is_none() {
                std::thread::yield_now();
            }
            let runtime = tokio::runtime::Builder::new_current_thread().enable_time().build().unwrap();
            runtime.block_on(async {
                for _ in 0..3 {
                    let given_up = tenant.trace(&entry, &query, Rays::Packed(rays(64)), None);
                    assert!(tokio::time::timeout(Duration::from_millis(1), given_up).await.is_err(), "still queued");
                }
                assert_eq!(operations(), 4, "the long trace and the three given up");
                let refused = tenant.trace(&entry, &query, Rays::Packed(rays(64)), None).await.unwrap_err();
                assert!(refused.to_string().contains("max_concurrent_operations = 4"), "{refused}");
            });
            assert_eq!(long.join().unwrap().stats.rays, 16384);
        });
        // Their pieces are skipped once the long trace's are done: a bound against hanging, not a measurement.
        let since = Instant::now();
        while operations() > 0 {
            assert!(since.elapsed() < Duration::from_secs(60), "{} operations still held", operations());
            std::thread::yield_now();
        }
    }

    /// A job of `rays` closest-hit rays of `tenant` on `entry`, holding one of its operation places and answering
    /// the returned receiver, as [`Tenant::trace`] makes one; nothing is queued.
    fn job_of(
        tenant: &Arc<Tenant>,
        entry: &AccelEntry,
        rays: Bytes,
    ) -> (Arc<TraceJob>, oneshot::Receiver<ServiceResult<TraceResult>>) {
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
        let scheduler = tenant.schedulers.get(DEFAULT_DEVICE).unwrap();
        let sizer = PieceSizer::new(scheduler.piece_limits(false, false), HIT_GRANULE, None);
        let layout = query.output_layout(rays.len()).unwrap();
        let untaken = (BytesMut::zeroed(layout.hits), BytesMut::zeroed(layout.counts));
        let job = TraceJob {
            tenant: Arc::clone(tenant),
            accel: Arc::clone(&entry.accel),
            pace: Arc::clone(&entry.pace),
            device: DEFAULT_DEVICE.into(),
            order: scheduler.arrival(),
            arrived: Instant::now(),
            query,
            reduction: None,
            rays: Rays::Packed(rays),
            abandoned: AtomicBool::new(false),
            progress: Mutex::new(Progress::new(sizer, untaken, tenant.quotas.start(1).unwrap())),
        };
        let (reply, answer) = oneshot::channel();
        job.progress().reply = Some(reply);
        (Arc::new(job), answer)
    }

    #[test]
    fn a_trace_given_up_between_pieces_holds_its_place_until_its_queued_piece_is_skipped() {
        let (tenant, entry) = tenant_with_a_pile(10);
        let (job, mut answer) = job_of(&tenant, &entry, rays(4096));
        // A piece runs, as a worker runs it, with the next one queued (flagged here, not handed to a worker); the
        // caller goes meanwhile.
        let (Piece { index, rays, output }, after) = job.progress().take_piece(&job).expect("rays are left");
        assert!(after.is_some(), "more pieces follow");
        job.progress().queued = true;
        drop(Abandon(Arc::clone(&job)));
        let (traced, took) = job.trace_piece_timed(rays.clone(), output);
        let mut progress = job.progress();
        progress.record(&job, index, rays, took, traced, Teach::FromAProbe);
        job.answer_if_done(&mut progress);
        drop(progress);
        assert!(matches!(answer.try_recv(), Ok(Err(ServiceError::Transport(_)))), "the caller is answered");
        assert_eq!(tenant.usage().operations, 1, "the queued piece holds the rays: the place is held");
        // The queued piece runs: it takes nothing, and the place goes with the job.
        job.run_next();
        drop(job);
        assert_eq!(tenant.usage().operations, 0, "the trace's place let go with the job");
    }

    #[test]
    fn a_panic_outside_the_engine_answers_the_caller_and_lets_its_place_go() {
        let (tenant, entry) = tenant_with_a_pile(10);
        let (job, mut answer) = job_of(&tenant, &entry, rays(64));
        let panicked = std::panic::catch_unwind(AssertUnwindSafe(|| {
            let _answer_on_panic = AnswerOnPanic(job.as_ref());
            let _held = job.progress.lock().unwrap();
            panic!("a bug while the progress is locked");
        }));
        assert!(panicked.is_err());
        match answer.try_recv() {
            Ok(Err(ServiceError::Internal(what))) => assert!(what.contains("panicked"), "{what}"),
            Ok(Err(other)) => panic!("expected an internal error, got {other}"),
            Ok(Ok(_)) | Err(_) => panic!("expected an internal error, got an answer or none"),
        }
        assert!(job.abandoned.load(Ordering::Acquire), "no further piece is taken");
        assert_eq!(tenant.usage().operations, 1, "held while the job (its pieces still queued) lives");
        drop(job);
        assert_eq!(tenant.usage().operations, 0, "the trace's place let go with the job");
    }

    #[test]
    fn a_trace_known_to_take_long_runs_on_a_worker_and_a_few_rays_of_unknown_cost_teach_it() {
        // Pieces of up to a minute: 1,024 rays through the pile fit one piece, and take far more than a millisecond.
        // (With a second, one ray timed on a loaded machine at over a millisecond cut the 1,024 into two pieces.)
        let (tenant, entry) = tenant_with_a_pile(60_000);
        let closest = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        assert_eq!(entry.pace.get(QueryKind::Closest), None);
        // One ray of unknown cost runs on the caller's thread, and teaches what the pile's rays cost.
        trace(&tenant, &entry, &closest, Rays::Packed(rays_at(1, |_| 0.25)), None);
        let ns_per_ray = entry.pace.get(QueryKind::Closest).expect("the one ray taught the pace");
        assert!(ns_per_ray * 1024.0 > 1e6, "1,024 rays take more than a millisecond: {ns_per_ray} ns a ray");
        // A trace known to take longer than a millisecond leaves the caller's thread (the only one of this runtime)
        // free: a task spawned on it before runs while the trace waits for its worker. (Run on the caller's thread,
        // the trace would be answered in its first poll, before the task.)
        let runtime = tokio::runtime::Builder::new_current_thread().build().unwrap();
        let rays = Rays::Packed(rays_at(1024, |_| 0.25));
        let ran_first = runtime.block_on(async {
            let task = tokio::spawn(async {});
            let traced = tenant.trace(&entry, &closest, rays, None).await.unwrap();
            assert_eq!((traced.stats.rays, traced.pieces), (1024, 1), "one piece");
            task.is_finished()
        });
        assert!(ran_first, "the trace ran on the caller's thread and held it");
    }

    #[test]
    fn an_empty_batch_is_answered_at_once() {
        let (tenant, entry) = tenant_with_a_pile(10);
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        let traced = trace(&tenant, &entry, &query, Rays::Packed(Bytes::new()), None);
        assert_eq!((traced.hits.len(), traced.stats.rays, traced.pieces), (0, 0, 1));
    }

    #[test]
    fn a_tenant_of_cheap_rays_beside_costly_ones_is_served_as_much_time_not_as_many_rays() {
        // Tenant `costly` traces rays through the pile (each holds a worker for a quarter of a millisecond or more)
        // from two threads; tenant `cheap` traces batches of rays that miss the pile from two threads meanwhile.
        let devices = [Device::cpu()];
        let config = SchedulerConfig { workers: 2, piece_ms: 1, ..SchedulerConfig::default() };
        let schedulers = Arc::new(Schedulers::new(&devices, &config));
        let (costly, costly_pile) = tenant_with_a_pile_on("costly", Limits::default(), Arc::clone(&schedulers));
        let (cheap, cheap_pile) = tenant_with_a_pile_on("cheap", Limits::default(), schedulers);
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
        let (costly_rays, missing) = (rays_at(2048, |_| 0.25), rays_at(1024, |_| 5.0));
        let (costly_done, cheap_traced) = (AtomicBool::new(false), std::sync::atomic::AtomicU64::new(0));
        // The cheap rays traced by the time the first costly trace was answered.
        let cheap_rays = std::thread::scope(|scope| {
            let costly_traces: Vec<_> = (0..2)
                .map(|_| {
                    scope.spawn(|| {
                        let traced = trace(&costly, &costly_pile, &query, Rays::Packed(costly_rays.clone()), None);
                        assert_eq!(traced.stats.rays, 2048);
                        cheap_traced.load(Ordering::Acquire)
                    })
                })
                .collect();
            for _ in 0..2 {
                scope.spawn(|| {
                    while !costly_done.load(Ordering::Acquire) {
                        let traced = trace(&cheap, &cheap_pile, &query, Rays::Packed(missing.clone()), None);
                        cheap_traced.fetch_add(traced.stats.rays, Ordering::AcqRel);
                    }
                });
            }
            let cheap_rays = costly_traces.into_iter().map(|t| t.join().unwrap()).min();
            costly_done.store(true, Ordering::Release);
            cheap_rays.expect("two costly traces")
        });
        // While both costly traces ran, `cheap` was served about as many rays as `costly` when charged by rays (3,000
        // to 7,000 here: after each of its batches it waits for 32 costly pieces); charged by time, it is served
        // whenever a worker is free: millions.
        assert!(cheap_rays > 4 * 4096, "{cheap_rays} cheap rays beside 4,096 costly ones");
    }
}
