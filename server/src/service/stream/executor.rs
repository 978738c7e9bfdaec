//! Runs a stream's operations one at a time, in order, and answers each in turn.

use std::sync::Arc;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use prost::Message;
use rayd_proto as pb;
use rayd_proto::operation_result::Outcome;
use rayd_proto::stream_request::Op;
use rayd_proto::stream_response::Kind;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tonic::Status;

use super::products::{Producer, Products};
use super::{Abort, Answer, Queued};
use crate::error::{ServiceError, ServiceResult};
use crate::service::outbox::Outbox;
use crate::service::{accels, buffers, reader_ended, trace};
use crate::streams::{StreamSlot, Waitable};
use crate::tenant::Tenant;

/// Most messages a download in a stream is answered with: they are made together before the first is sent (each
/// a slice of the buffer, no copy), so that tiny chunks of a large buffer cannot fill the server's memory.
const MAX_DOWNLOAD_CHUNKS: usize = 1 << 16;

/// The state of one stream's executor.
#[derive(Debug)]
pub struct Executor {
    /// Whose objects the operations act on.
    tenant: Arc<Tenant>,
    /// The stream's place in the tenant's table, where its progress is published.
    slot: StreamSlot,
    /// What earlier operations made.
    products: Products,
    /// A message taken off the queue by an upload that it did not belong to; it is the next one to run.
    pending: Option<Queued>,
}

impl Executor {
    /// The executor of the stream in `slot`.
    pub fn new(tenant: Arc<Tenant>, slot: StreamSlot) -> Executor {
        let products = Products::remembering(tenant.limits().max_stream_products as usize);
        Executor { tenant, slot, products, pending: None }
    }

    /// Runs until the queue ends (the client half-closed and everything ran), the call goes away, or the stream
    /// is aborted. Dropping the queue and the slot on the way out frees what the stream held and closes it.
    pub async fn run(
        mut self,
        mut queue: mpsc::Receiver<Queued>,
        reader: JoinHandle<()>,
        answers: Outbox<Answer>,
        abort: Arc<Abort>,
    ) {
        // However this ends (a panic too), the reader stops, if it is still reading.
        let _stops_reader = abort.token.clone().drop_guard();
        'operations: loop {
            let responses = tokio::select! {
                biased;
                () = abort.cancelled() => break,
                () = answers.closed() => break,
                responses = self.next(&mut queue) => responses,
            };
            let Some(responses) = responses else {
                // The client's last operation, unless the reader panicked: then the call ends with INTERNAL.
                if let Err(status) = reader_ended(reader).await {
                    abort.abort(Some(status));
                }
                break;
            };
            for response in responses {
                let answer = Answer { _held: self.tenant.streams().hold(response.encoded_len() as u64), response };
                tokio::select! {
                    biased;
                    () = abort.cancelled() => break 'operations,
                    sent = answers.send(Ok(answer)) => if sent.is_err() { break 'operations },
                }
            }
        }
        if abort.is_cancelled() && !abort.has_reason() {
            // Cancelled (CancelStream, or the call reset): the answers not yet sent are dropped, and the call ends
            // with CANCELLED. A message the reader could not take ends it with its own status instead, after them.
            answers.fail(|held| Status::cancelled(format!("the stream was cancelled: {held} unsent answers dropped")));
        }
    }

    /// Runs the next operation and returns its answer (preceded by a download's data); `None` once the queue has
    /// ended.
    async fn next(&mut self, queue: &mut mpsc::Receiver<Queued>) -> Option<Vec<pb::StreamResponse>> {
        loop {
            let item = match self.pending.take() {
                Some(item) => item,
                None => queue.recv().await?,
            };
            // Data with no operation to take it belongs to an upload that was refused.
            if let Queued::Op { id, op, .. } = item {
                return Some(self.answer(id, op, queue).await);
            }
        }
    }

    /// Runs operation `id` and makes its answer.
    async fn answer(&mut self, id: u64, mut op: Op, queue: &mut mpsc::Receiver<Queued>) -> Vec<pb::StreamResponse> {
        let producer = Producer::of(&op);
        let name = op_name(&op);
        let mut responses = Vec::new();
        // An operation refused before it starts (it uses what a failed operation did not make) has no times.
        let (result, started, finished, took) = match self.products.resolve(id, &mut op) {
            Ok(()) => {
                let (started, clock) = (unix_ns(), Instant::now());
                let result = self.execute(id, op, queue, &mut responses).await;
                self.products.record(id, producer, &result);
                (result, started, unix_ns(), Some(clock.elapsed()))
            }
            Err(refused) => (Err(self.products.record_refused(id, producer, refused)), 0, 0, None),
        };
        self.slot.finished(id);
        let (status, outcome) = match result {
            Ok(outcome) => (Status::ok(""), outcome),
            Err(error) => {
                responses.clear();
                (Status::from(error), None)
            }
        };
        crate::metrics::stream_operation(self.tenant.name(), name, status.code(), took);
        responses.push(pb::StreamResponse {
            kind: Some(Kind::Result(pb::OperationResult {
                operation: id,
                code: status.code() as i32,
                message: status.message().to_owned(),
                started_unix_ns: started,
                finished_unix_ns: finished,
                outcome,
            })),
        });
        responses
    }

    /// Does what `op` says; a download's data goes into `chunks`.
    async fn execute(
        &mut self,
        id: u64,
        op: Op,
        queue: &mut mpsc::Receiver<Queued>,
        chunks: &mut Vec<pb::StreamResponse>,
    ) -> ServiceResult<Option<Outcome>> {
        let tenant = &self.tenant;
        Ok(match op {
            Op::Upload(upload) => Some(Outcome::Buffer(self.upload(id, upload, queue).await?)),
            Op::UploadData(_) => return Err(ServiceError::invalid("upload_data", "data without an upload")),
            Op::Build(request) => Some(Outcome::Accel(accels::build(Arc::clone(tenant), request).await?)),
            Op::CopyAccel(request) => Some(Outcome::Accel(accels::copy(Arc::clone(tenant), request).await?)),
            Op::UpdateAccel(request) => Some(Outcome::Accel(accels::update(Arc::clone(tenant), request).await?)),
            Op::Trace(request) => Some(Outcome::Trace(trace::batch(Arc::clone(tenant), request).await?)),
            Op::Download(request) => {
                let (entry, parts) = buffers::download_chunks(tenant, &request)?;
                let messages = parts.size_hint().0;
                if messages > MAX_DOWNLOAD_CHUNKS {
                    return Err(ServiceError::invalid(
                        "download.chunk_bytes",
                        format!("{messages} chunks; a stream's download sends at most {MAX_DOWNLOAD_CHUNKS}"),
                    ));
                }
                chunks.extend(parts.map(|chunk| pb::StreamResponse { kind: Some(Kind::DownloadChunk(chunk)) }));
                Some(Outcome::Buffer(buffers::info(&entry)))
            }
            Op::DeleteBuffer(request) => {
                buffers::delete(Arc::clone(tenant), request).await?;
                None
            }
            Op::DestroyAccel(request) => {
                accels::destroy(Arc::clone(tenant), request).await?;
                None
            }
            Op::RecordEvent(_) => None,
            Op::WaitEvent(event) => {
                self.wait(id, &event).await?;
                None
            }
        })
    }

    /// Receives upload `id`: its first data, then the data messages that follow it on the queue.
    async fn upload(
        &mut self,
        id: u64,
        upload: pb::StreamUpload,
        queue: &mut mpsc::Receiver<Queued>,
    ) -> ServiceResult<pb::BufferInfo> {
        let header = upload.header.ok_or_else(|| ServiceError::invalid("upload.header", "required"))?;
        let mut receiving = buffers::Upload::begin(&self.tenant, header)?;
        let mut held = self.tenant.streams().hold(0);
        receiving.push(&upload.first_data)?;
        held.grow(upload.first_data.len() as u64);
        while !receiving.is_complete() {
            match queue.recv().await {
                Some(Queued::UploadData { id: of, data, .. }) if of == id => {
                    receiving.push(&data)?;
                    held.grow(data.len() as u64);
                }
                other => {
                    self.pending = other;
                    break;
                }
            }
        }
        buffers::keep(Arc::clone(&self.tenant), receiving).await
    }

    /// Waits until operation `event.operation` of stream `event.stream_id` has finished (or that stream closed).
    async fn wait(&self, id: u64, event: &pb::WaitEvent) -> ServiceResult<()> {
        if event.stream_id == self.slot.id {
            if event.operation >= id {
                return Err(ServiceError::invalid(
                    "wait_event.operation",
                    format!(
                        "operation {} of this stream comes after this wait ({id}): it would never finish",
                        event.operation
                    ),
                ));
            }
            // Earlier operations of this stream have finished: that is the stream's order.
            return Ok(());
        }
        if let Waitable::Open(mut progress) =
            self.tenant.streams().waitable(event.stream_id).map_err(|e| e.in_field("wait_event.stream_id"))?
        {
            // An error means the other stream's slot is gone: it closed, so there is nothing left to wait for.
            let _ = progress.wait_for(|p| p.closed || p.finished >= event.operation).await;
        }
        Ok(())
    }
}

/// The operation's name in metrics.
fn op_name(op: &Op) -> &'static str {
    match op {
        Op::Upload(_) | Op::UploadData(_) => "upload",
        Op::Build(_) => "build",
        Op::CopyAccel(_) => "copy_accel",
        Op::UpdateAccel(_) => "update_accel",
        Op::Trace(_) => "trace",
        Op::Download(_) => "download",
        Op::DeleteBuffer(_) => "delete_buffer",
        Op::DestroyAccel(_) => "destroy_accel",
        Op::RecordEvent(_) => "record_event",
        Op::WaitEvent(_) => "wait_event",
    }
}

/// Now, in nanoseconds since the Unix epoch.
fn unix_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}
