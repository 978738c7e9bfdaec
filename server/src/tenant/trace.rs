//! A tenant's traces: checked against its limits, then cut into pieces that the fair scheduler of the accel's
//! device serves among every tenant's pieces ([`crate::schedule`]). Each piece writes in place into its share of
//! one hit buffer and one counts buffer, which are handed back whole, without copying, when the last piece is done.

use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use bytes::{Bytes, BytesMut};
use rayd_engine::Accel;
use rayd_engine::backend::RaySource;
use rayd_engine::query::{OutputLayout, Query, TraceOutput, TraceStats};
use rayd_engine::raygen::Generator;
use rayd_engine::reduce::{Partial, Reduction};
use tokio::sync::oneshot;

use super::{AccelEntry, Tenant, TraceResult};
use crate::error::{ServiceError, ServiceResult};
use crate::schedule::{Scheduler, Task};

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
    /// Fails with RESOURCE_EXHAUSTED naming `max_rays_per_batch` if a batch of `rays` rays is too large.
    pub fn check_batch_rays(&self, rays: u64) -> ServiceResult<()> {
        ServiceError::check_limit(
            || "rays in one batch".into(),
            rays,
            "max_rays_per_batch",
            self.limits.max_rays_per_batch,
        )
    }

    /// Traces `rays` against `accel` into fresh reply buffers — or, with a `reduction` (checked by the caller),
    /// into its result — once the limits allow it, through the fair scheduler of the accel's device. A trace of at
    /// most one piece runs right here when the device lends its callers a free slot (the CPU's, with nothing
    /// queued: [`crate::schedule::Scheduler::try_slot`]).
    pub async fn trace(
        self: &Arc<Self>,
        accel: &AccelEntry,
        query: &Query,
        rays: Rays,
        reduction: Option<Arc<Reduction>>,
    ) -> ServiceResult<TraceResult> {
        let ray_size = query.ray_format.size();
        self.check_batch_rays(rays.count(ray_size))?;
        let layout = match &reduction {
            None => query.output_layout(rays.byte_len(ray_size))?,
            Some(_) => OutputLayout { rays: rays.count(ray_size) as usize, hits: 0, counts: 0 },
        };
        let _running = self.quotas.start(self.limits.max_concurrent_operations)?;
        self.quotas.take_rays(layout.rays as u64, self.limits.max_rays_per_second)?;
        if let Rays::Packed(bytes) = &rays {
            // Checked on the whole batch, so that the error names the ray by its index in the batch.
            query.check_times(bytes)?;
        }
        let scheduler = self.schedulers.get(&accel.device).ok_or_else(|| ServiceError::NotFound {
            what: "device",
            name: accel.device.clone(),
            field: String::new(),
        })?;
        // Rays that reduce together stay in one piece.
        let group = reduction.as_ref().map_or(1, |r| r.group_rays());
        let generated = matches!(rays, Rays::Generated(..));
        let piece_rays = (scheduler.piece_rays(generated, reduction.is_some()) / group).max(1) * group;
        let job = Arc::new(TraceJob {
            tenant: Arc::clone(self),
            accel: Arc::clone(&accel.accel),
            device: accel.device.clone(),
            query: *query,
            reduction,
            rays,
            abandoned: AtomicBool::new(false),
            progress: Mutex::new(Progress::default()),
        });
        if layout.rays <= piece_rays
            && let Some(_slot) = scheduler.try_slot()
        {
            let output = (BytesMut::zeroed(layout.hits), BytesMut::zeroed(layout.counts));
            let start = Instant::now();
            let (output, stats) = job.trace_piece_caught(0..job.rays.byte_len(ray_size), output)?;
            let mut progress =
                Progress { outputs: vec![Some(output)], stats, started: Some(start), ..Default::default() };
            return Ok(progress.finish(&job)?.trace);
        }
        let (reply, result) = oneshot::channel();
        let _abandon_if_dropped = Abandon(Arc::clone(&job));
        let queued = Instant::now();
        job.submit(scheduler, piece_rays, layout, reply);
        let result = result.await.map_err(|_| ServiceError::Internal("a trace ended without an answer".into()))??;
        crate::metrics::queued(&self.name, result.trace_start.duration_since(queued));
        Ok(result.trace)
    }
}

/// A trace cut into pieces; the worker that finishes its last piece answers the caller.
struct TraceJob {
    /// Whose trace it is.
    tenant: Arc<Tenant>,
    /// What is traced (kept alive while pieces wait).
    accel: Arc<Accel>,
    /// The device the accel lives on.
    device: String,
    /// What is asked of every ray.
    query: Query,
    /// What the hits are reduced to, if not returned.
    reduction: Option<Arc<Reduction>>,
    /// Every ray of the trace.
    rays: Rays,
    /// Set when the caller went away or a piece failed: the pieces not started yet are skipped.
    abandoned: AtomicBool,
    /// What the pieces finished so far.
    progress: Mutex<Progress>,
}

/// The pieces' results, gathered.
#[derive(Default)]
struct Progress {
    /// Each piece's output, once traced.
    outputs: Vec<Option<PieceOutput>>,
    /// The partials of a reduction that folds in any order ([`Reduction::folds_in_any_order`]), folded as their
    /// pieces finish: a trace of thousands of pieces keeps one, not thousands.
    folded: Option<Partial>,
    /// The bytes of the pieces' ordered records so far, which the answer will hold
    /// ([`Reduction::answer_holds_the_records`]).
    ordered_bytes: u64,
    /// Pieces not finished (or skipped) yet.
    remaining: usize,
    /// The sum of the finished pieces' statistics.
    stats: TraceStats,
    /// The first failure of a piece: the answer.
    failure: Option<ServiceError>,
    /// When the first piece started.
    started: Option<Instant>,
    /// Where the answer goes.
    reply: Option<oneshot::Sender<ServiceResult<Finished>>>,
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

/// A finished trace and when its first piece started.
struct Finished {
    /// The whole trace's result.
    trace: TraceResult,
    /// When its first piece started (the end of its wait in the queue).
    trace_start: Instant,
}

/// Abandons the job when the caller's future is dropped (the client went away or its deadline passed).
struct Abandon(Arc<TraceJob>);

impl Drop for Abandon {
    fn drop(&mut self) {
        self.0.abandoned.store(true, Ordering::Release);
    }
}

impl TraceJob {
    /// Cuts the output buffers (sized by `layout`; empty for a reduction) into the shares of pieces of
    /// `piece_rays` rays and queues every piece.
    fn submit(
        self: &Arc<Self>,
        scheduler: &Scheduler,
        piece_rays: usize,
        layout: OutputLayout,
        reply: oneshot::Sender<ServiceResult<Finished>>,
    ) {
        let ray_size = self.query.ray_format.size();
        let piece_bytes = piece_rays * ray_size;
        let total = self.rays.byte_len(ray_size);
        let pieces = total.div_ceil(piece_bytes);
        {
            let mut progress = self.progress.lock().expect("not poisoned");
            progress.outputs = (0..pieces).map(|_| None).collect();
            progress.remaining = pieces;
            progress.reply = Some(reply);
        }
        let (mut hits, mut counts) = (BytesMut::zeroed(layout.hits), BytesMut::zeroed(layout.counts));
        let tasks: Vec<(u64, Task)> = (0..pieces)
            .map(|index| {
                let start = index * piece_bytes;
                let len = piece_bytes.min(total - start);
                let output = match self.reduction {
                    Some(_) => (BytesMut::new(), BytesMut::new()),
                    None => {
                        let piece = self.query.output_layout(len).expect("a whole number of rays");
                        (hits.split_to(piece.hits), counts.split_to(piece.counts))
                    }
                };
                let job = Arc::clone(self);
                let task: Task = Box::new(move || job.run(index, start..start + len, output));
                ((len / ray_size) as u64, task)
            })
            .collect();
        let flow = &self.tenant.flow;
        scheduler.submit(flow, tasks);
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
    /// caller's: one of those that answer every call) nor the other pieces waiting on it.
    fn trace_piece_caught(
        &self,
        rays: std::ops::Range<usize>,
        output: (BytesMut, BytesMut),
    ) -> ServiceResult<(PieceOutput, TraceStats)> {
        let first_ray = rays.start / self.query.ray_format.size();
        std::panic::catch_unwind(AssertUnwindSafe(|| self.trace_piece(rays, output)))
            .unwrap_or_else(|_| Err(ServiceError::Internal(format!("tracing the piece from ray {first_ray} panicked"))))
    }

    /// Traces piece `index` (the rays in bytes `rays`) into `output`, unless the job was abandoned, and answers
    /// when it was the last.
    fn run(&self, index: usize, rays: std::ops::Range<usize>, output: (BytesMut, BytesMut)) {
        let traced = if self.abandoned.load(Ordering::Acquire) {
            None
        } else {
            let start = Instant::now();
            self.progress.lock().expect("not poisoned").started.get_or_insert(start);
            Some(self.trace_piece_caught(rays, output))
        };
        let outcome = match &traced {
            Some(Ok(_)) => "traced",
            Some(Err(_)) => "failed",
            None => "skipped",
        };
        crate::metrics::piece(&self.tenant.name, outcome);
        let mut progress = self.progress.lock().expect("not poisoned");
        match traced.map(|traced| traced.and_then(|(output, stats)| Ok((progress.take(self, output)?, stats)))) {
            Some(Ok((output, stats))) => {
                progress.stats.add(&stats);
                progress.outputs[index] = Some(output);
            }
            Some(Err(error)) => {
                self.abandoned.store(true, Ordering::Release);
                progress.failure.get_or_insert(error);
            }
            None => {}
        }
        progress.remaining -= 1;
        if progress.remaining == 0 {
            let answer = progress.finish(self);
            if let Some(reply) = progress.reply.take() {
                // The caller may have gone: then nobody wants the answer.
                let _ = reply.send(answer);
            }
        }
    }
}

impl Progress {
    /// What is kept of a piece's `output`: a reduction that folds in any order folded into [`Progress::folded`]; the
    /// rest as it is, once ordered records that pass `max_message_bytes` have failed the trace (its answer could not
    /// be sent: the pieces left are skipped).
    fn take(&mut self, job: &TraceJob, output: PieceOutput) -> ServiceResult<PieceOutput> {
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
    fn finish(&mut self, job: &TraceJob) -> ServiceResult<Finished> {
        if let Some(failure) = self.failure.take() {
            return Err(failure);
        }
        let trace_start = self.started.unwrap_or_else(Instant::now);
        let mut outputs = std::mem::take(&mut self.outputs).into_iter();
        let mut trace = TraceResult { stats: self.stats, ..Default::default() };
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
        trace.trace_ns = trace_start.elapsed().as_nanos() as u64;
        Ok(Finished { trace, trace_start })
    }
}

/// The answer of a trace whose caller went away (nobody reads it).
fn abandoned() -> ServiceError {
    ServiceError::Transport(tonic::Status::cancelled("the caller went away before the trace finished"))
}
