//! Streams: ordered, asynchronous queues of operations on the server (the semantics are in streams.proto),
//! mirrored as CUDA streams are used:
//!
//! ```no_run
//! # use rayd_client::{Client, ClientOptions};
//! # use rayd_engine::{accel::BuildFlags, format::*, mesh::Mesh, query::Query};
//! # async fn demo(client: Client, mesh: Mesh, rays: bytes::Bytes) -> rayd_client::Result<()> {
//! let stream = client.create_stream().await?;
//! let bunny = stream.build_mesh("bunny", &mesh, "", BuildFlags::PREFER_FAST_TRACE).await?;
//! let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriid);
//! let traced = stream.trace(&bunny, &query, rays).await?; // enqueued: nothing waited for yet
//! stream.synchronize().await?; // every operation so far has finished, and none failed
//! let hits = traced.result().expect("answered by now")?.hits().len();
//! # Ok(()) }
//! ```
//!
//! Enqueueing returns as soon as the operation is handed to the transport; it only waits when the operations
//! in flight already hold [`ClientOptions::stream_bytes_in_flight`](crate::ClientOptions::stream_bytes_in_flight).
//! An operation whose message would pass the server's `max_message_bytes` is refused when enqueued
//! (INVALID_ARGUMENT naming it), and the stream goes on: sent, it would end the whole call.
//! Once an enqueue call has numbered its operation (it has waited for room in flight), the operation is sent in
//! full even if the call's future is dropped before it returns (a timeout, a `select!`): the operation runs in its
//! turn and a synchronize covers it, but there is no handle to it.
//! Dropping a [`Stream`] cancels it: the server drops its queued operations, and unanswered handles fail.

mod handle;
mod receive;
mod state;

use std::sync::Arc;

use bytes::Bytes;
use rayd_engine::accel::BuildFlags;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use rayd_engine::raygen::Generator;
use rayd_engine::reduce::Reduction;
use rayd_proto as proto;
use rayd_proto::data_source::Source;
use rayd_proto::stream_request::Op;
use rayd_proto::trace_batch_request::Rays;
use tokio::sync::{Mutex, OwnedMutexGuard, Semaphore, mpsc};
use tokio::task::JoinHandle;
use tokio_stream::wrappers::ReceiverStream;

pub use handle::{Event, EventId, Operation};
use state::{Expect, Outcome, Shared, Slot, Unanswered};

use crate::build::{mesh_request, packed};
use crate::client::{Client, ClientOptions, RpcClient, copy_request};
use crate::convert::{generated_ray_count, generator_to_proto, reduction_to_proto, trace_query_ref};
use crate::error::{Error, Result};
use crate::reduce::ReducedTrace;
use crate::trace::{TraceResult, inline_trace, output_layout, output_layout_of_rays};

/// Messages queued for the transport before enqueueing waits.
const REQUEST_QUEUE: usize = 16;

/// Bytes of a `StreamRequest`'s `operation` field at most: a one-byte key and a varint of up to ten bytes.
const OPERATION_FIELD_BYTES: usize = 11;

/// Names an accel in a stream operation.
#[derive(Debug, Clone, Copy)]
pub enum AccelArg<'a> {
    /// By the tenant's name for it.
    Name(&'a str),
    /// By its handle.
    Handle(&'a str),
    /// The accel a build operation makes: by operation on its own stream (so it can be used before it exists),
    /// by handle on another stream once it is built.
    Built(&'a Operation<proto::AccelInfo>),
}

/// Names a buffer in a stream operation.
#[derive(Debug, Clone, Copy)]
pub enum BufferArg<'a> {
    /// By the caller's name for it.
    Name(&'a str),
    /// By its server id.
    Id(&'a str),
    /// The buffer an upload operation makes: by operation on its own stream, by id on another once uploaded.
    Uploaded(&'a Operation<proto::BufferInfo>),
}

impl<'a> From<&'a str> for AccelArg<'a> {
    fn from(name: &'a str) -> Self {
        AccelArg::Name(name)
    }
}

impl<'a> From<&'a proto::AccelInfo> for AccelArg<'a> {
    fn from(info: &'a proto::AccelInfo) -> Self {
        AccelArg::Handle(&info.handle)
    }
}

impl<'a> From<&'a Operation<proto::AccelInfo>> for AccelArg<'a> {
    fn from(build: &'a Operation<proto::AccelInfo>) -> Self {
        AccelArg::Built(build)
    }
}

impl<'a> From<&'a proto::BufferInfo> for BufferArg<'a> {
    fn from(info: &'a proto::BufferInfo) -> Self {
        BufferArg::Id(&info.id)
    }
}

impl<'a> From<&'a Operation<proto::BufferInfo>> for BufferArg<'a> {
    fn from(upload: &'a Operation<proto::BufferInfo>) -> Self {
        BufferArg::Uploaded(upload)
    }
}

/// One open stream. Its methods take `&self`: operations enqueued from several tasks are numbered and run in
/// the order the enqueue calls got their turn.
#[derive(Debug)]
pub struct Stream {
    /// What the handles and the receiving task share.
    shared: Arc<Shared>,
    /// The way to the call; `None` once finished. Held from numbering an operation until its messages are sent, so
    /// operations go out whole and in id order.
    sender: Arc<Mutex<Option<RequestSender>>>,
    /// Bytes of unanswered operations, bounded.
    in_flight: Arc<Semaphore>,
    /// The bound, in bytes.
    in_flight_bytes: u32,
    /// Bytes per upload message.
    upload_chunk_bytes: usize,
    /// The largest message the server accepts: a larger operation is refused before it is sent.
    max_message_bytes: usize,
    /// Meshes smaller than this go inline in the build.
    inline_mesh_bytes: usize,
    /// The task that reads answers.
    receiver: JoinHandle<()>,
    /// The connection, for cancelling the stream when it is dropped unfinished.
    rpc: Option<RpcClient>,
}

/// The sending end of a stream's requests.
type RequestSender = mpsc::Sender<proto::StreamRequest>;

impl Client {
    /// Opens a stream (one `OpenStream` call). Its operations may name any accel, so it carries no scene of its
    /// own: open it on [`Client::for_scene`] to send it to a scene's node behind a router.
    pub async fn create_stream(&self) -> Result<Stream> {
        let (sender, requests) = mpsc::channel(REQUEST_QUEUE);
        let mut responses = self.rpc.clone().open_stream(ReceiverStream::new(requests)).await?.into_inner();
        let opened = match responses.message().await? {
            Some(proto::StreamResponse { kind: Some(proto::stream_response::Kind::Opened(opened)) }) => opened,
            _ => return Err(Error::Protocol("a stream did not start with its `opened` message".into())),
        };
        let shared = Arc::new(Shared::new(opened.stream_id));
        let receiver = tokio::spawn(receive::answers(responses, Arc::clone(&shared)));
        Ok(Stream::new(&self.options, shared, sender, receiver, Some(self.rpc.clone())))
    }
}

impl Stream {
    /// A stream set up by `options` that sends its requests through `sender`, its answers read by `receiver` into
    /// `shared`; `rpc` cancels it when it is dropped unfinished.
    fn new(
        options: &ClientOptions,
        shared: Arc<Shared>,
        sender: RequestSender,
        receiver: JoinHandle<()>,
        rpc: Option<RpcClient>,
    ) -> Stream {
        let in_flight_bytes = u32::try_from(options.stream_bytes_in_flight).unwrap_or(u32::MAX).max(1);
        Stream {
            shared,
            sender: Arc::new(Mutex::new(Some(sender))),
            in_flight: Arc::new(Semaphore::new(in_flight_bytes as usize)),
            in_flight_bytes,
            upload_chunk_bytes: options.upload_chunk_bytes.max(1),
            max_message_bytes: options.max_message_bytes,
            inline_mesh_bytes: options.inline_mesh_bytes,
            receiver,
            rpc,
        }
    }

    /// The server's id of this stream.
    pub fn id(&self) -> u64 {
        self.shared.stream_id
    }

    /// Enqueues an upload of `data` as a new buffer, named `name` unless it is empty.
    pub async fn upload(&self, name: &str, data: Bytes) -> Result<Operation<proto::BufferInfo>> {
        let header = proto::UploadBufferHeader { name: name.to_owned(), size_bytes: data.len() as u64 };
        let first = data.slice(..self.upload_chunk_bytes.min(data.len()));
        let rest = (first.len()..data.len())
            .step_by(self.upload_chunk_bytes)
            .map(|start| data.slice(start..(start + self.upload_chunk_bytes).min(data.len())))
            .collect();
        let op = Op::Upload(proto::StreamUpload { header: Some(header), first_data: first });
        self.enqueue(op, rest, Expect::Buffer, |o| if let Outcome::Buffer(b) = o { Some(b.clone()) } else { None })
            .await
    }

    /// Enqueues a build from a request made by hand (its buffer references may name earlier uploads of this
    /// stream by operation).
    pub async fn build(&self, request: proto::BuildAccelRequest) -> Result<Operation<proto::AccelInfo>> {
        self.enqueue(Op::Build(request), Vec::new(), Expect::Accel, accel_outcome).await
    }

    /// Enqueues the build of accel `name` on `device` from one mesh. Meshes of at least
    /// [`ClientOptions::inline_mesh_bytes`](crate::ClientOptions::inline_mesh_bytes) are enqueued as two uploads,
    /// the build naming them by operation, and two deletes after it.
    pub async fn build_mesh(
        &self,
        name: &str,
        mesh: &Mesh,
        device: &str,
        flags: BuildFlags,
    ) -> Result<Operation<proto::AccelInfo>> {
        let (vertices, indices) = packed(mesh);
        if vertices.len() + indices.len() < self.inline_mesh_bytes {
            return self
                .build(mesh_request(name, device, flags, vec![Source::Inline(vertices)], Source::Inline(indices)))
                .await;
        }
        let vertices = self.upload("", vertices).await?;
        let indices = self.upload("", indices).await?;
        let by_operation = |upload: &Operation<proto::BufferInfo>| {
            Source::Buffer(proto::BufferRef { r#ref: Some(proto::buffer_ref::Ref::Operation(upload.id())) })
        };
        let build = self
            .build(mesh_request(name, device, flags, vec![by_operation(&vertices)], by_operation(&indices)))
            .await?;
        self.delete_buffer(&vertices).await?;
        self.delete_buffer(&indices).await?;
        Ok(build)
    }

    /// Enqueues an update (refit) from a request made by hand (its references may name earlier operations).
    pub async fn update(&self, request: proto::UpdateAccelRequest) -> Result<Operation<proto::AccelInfo>> {
        self.enqueue(Op::UpdateAccel(request), Vec::new(), Expect::Accel, accel_outcome).await
    }

    /// Enqueues a copy of an accel named `name` on `device` (empty: the source's); with `compact`, a compacted copy.
    pub async fn copy_accel<'a>(
        &self,
        accel: impl Into<AccelArg<'a>>,
        name: &str,
        device: &str,
        compact: bool,
    ) -> Result<Operation<proto::AccelInfo>> {
        let request = copy_request(self.accel_ref(accel.into())?, name, device, compact);
        self.enqueue(Op::CopyAccel(request), Vec::new(), Expect::Accel, accel_outcome).await
    }

    /// Enqueues a trace of packed `rays` (whole records of `query.ray_format`), the hits returned in the answer.
    pub async fn trace<'a>(
        &self,
        accel: impl Into<AccelArg<'a>>,
        query: &Query,
        rays: Bytes,
    ) -> Result<Operation<TraceResult>> {
        let ray_bytes = rays.len();
        output_layout(query, ray_bytes)?;
        let request = inline_trace(trace_query_ref(self.accel_ref(accel.into())?, query), rays);
        self.enqueue(Op::Trace(request), Vec::new(), Expect::Trace(*query, ray_bytes), |o| match o {
            Outcome::Trace(result) => Some(result.clone()),
            _ => None,
        })
        .await
    }

    /// Enqueues a trace of the rays `generator` describes (made by the server), the hits returned in the answer.
    pub async fn trace_generated<'a>(
        &self,
        accel: impl Into<AccelArg<'a>>,
        query: &Query,
        generator: &Generator,
    ) -> Result<Operation<TraceResult>> {
        let ray_bytes = output_layout_of_rays(query, generated_ray_count(generator))?.rays * query.ray_format.size();
        let request = proto::TraceBatchRequest {
            query: Some(trace_query_ref(self.accel_ref(accel.into())?, query)),
            rays: Some(Rays::RaysGenerator(generator_to_proto(generator))),
            ..Default::default()
        };
        self.enqueue(Op::Trace(request), Vec::new(), Expect::Trace(*query, ray_bytes), |o| match o {
            Outcome::Trace(result) => Some(result.clone()),
            _ => None,
        })
        .await
    }

    /// Enqueues a trace of packed `rays` whose answer is only `reduction` of the hits.
    pub async fn trace_reduced<'a>(
        &self,
        accel: impl Into<AccelArg<'a>>,
        query: &Query,
        rays: Bytes,
        reduction: &Reduction,
    ) -> Result<Operation<ReducedTrace>> {
        self.enqueue_reduced(accel.into(), query, Rays::RaysInline(rays), reduction).await
    }

    /// Enqueues a trace of the rays `generator` describes (made by the server) whose answer is only `reduction` of
    /// the hits: neither rays nor hits cross the network.
    pub async fn trace_generated_reduced<'a>(
        &self,
        accel: impl Into<AccelArg<'a>>,
        query: &Query,
        generator: &Generator,
        reduction: &Reduction,
    ) -> Result<Operation<ReducedTrace>> {
        self.enqueue_reduced(accel.into(), query, Rays::RaysGenerator(generator_to_proto(generator)), reduction).await
    }

    /// Enqueues a reduced trace of `rays`.
    async fn enqueue_reduced(
        &self,
        accel: AccelArg<'_>,
        query: &Query,
        rays: Rays,
        reduction: &Reduction,
    ) -> Result<Operation<ReducedTrace>> {
        let request = proto::TraceBatchRequest {
            query: Some(trace_query_ref(self.accel_ref(accel)?, query)),
            rays: Some(rays),
            reduction: Some(reduction_to_proto(reduction)),
            ..Default::default()
        };
        self.enqueue(Op::Trace(request), Vec::new(), Expect::Reduced, |o| match o {
            Outcome::Reduced(reduced) => Some(reduced.clone()),
            _ => None,
        })
        .await
    }

    /// Enqueues a download of a whole buffer.
    pub async fn download<'a>(&self, buffer: impl Into<BufferArg<'a>>) -> Result<Operation<Bytes>> {
        let request =
            proto::DownloadBufferRequest { buffer: Some(self.buffer_ref(buffer.into())?), ..Default::default() };
        self.enqueue(Op::Download(request), Vec::new(), Expect::Download, |o| match o {
            Outcome::Bytes(data) => Some(data.clone()),
            _ => None,
        })
        .await
    }

    /// Enqueues the deletion of a buffer.
    pub async fn delete_buffer<'a>(&self, buffer: impl Into<BufferArg<'a>>) -> Result<Operation<()>> {
        let request = proto::DeleteBufferRequest { buffer: Some(self.buffer_ref(buffer.into())?) };
        self.enqueue_unit(Op::DeleteBuffer(request)).await
    }

    /// Enqueues the destruction of an accel.
    pub async fn destroy_accel<'a>(&self, accel: impl Into<AccelArg<'a>>) -> Result<Operation<()>> {
        let request = proto::DestroyAccelRequest { accel: Some(self.accel_ref(accel.into())?) };
        self.enqueue_unit(Op::DestroyAccel(request)).await
    }

    /// Records an event: it completes when everything enqueued on this stream before it has finished.
    pub async fn record_event(&self) -> Result<Event> {
        Ok(Event { record: self.enqueue_unit(Op::RecordEvent(proto::RecordEvent {})).await? })
    }

    /// Makes the operations enqueued after this one wait until `event` (of any stream of this tenant, also another
    /// client's) has completed. An event of a stream that has closed is complete.
    pub async fn wait_event(&self, event: impl Into<EventId>) -> Result<Operation<()>> {
        let EventId { stream_id, operation } = event.into();
        let wait = proto::WaitEvent { stream_id, operation };
        self.enqueue_unit(Op::WaitEvent(wait)).await
    }

    /// Waits until every operation enqueued so far has finished. Fails with [`Error::Operations`] listing the
    /// operations that failed since the previous synchronize (later operations still ran: errors are not
    /// sticky), or with the stream's own error if it broke.
    pub async fn synchronize(&self) -> Result<()> {
        let sent = self.shared.book().sent;
        if let Some(broken) = self.shared.answered(sent).await {
            return Err(Error::Status(broken));
        }
        let failures = std::mem::take(&mut self.shared.book().failures);
        if failures.is_empty() { Ok(()) } else { Err(Error::Operations(failures)) }
    }

    /// Whether every operation enqueued so far has finished, or the stream broke: then nothing more will run, and
    /// [`Stream::synchronize`] returns the stream's error (never blocks).
    pub fn query(&self) -> bool {
        self.shared.is_answered(self.shared.book().sent) || self.shared.progress.borrow().broken.is_some()
    }

    /// Synchronizes, then closes the stream cleanly: returns once the server has ended the call with OK (dropping
    /// the call before its end was read would reset it).
    pub async fn finish(mut self) -> Result<()> {
        let synchronized = self.synchronize().await;
        self.sender.lock().await.take();
        self.rpc = None;
        // The receiving task ends with the call: the server ends it once the requests have ended and all ran.
        let _ = (&mut self.receiver).await;
        synchronized
    }

    /// Enqueues an operation with no product.
    async fn enqueue_unit(&self, op: Op) -> Result<Operation<()>> {
        self.enqueue(op, Vec::new(), Expect::Nothing, |o| matches!(o, Outcome::Nothing).then_some(())).await
    }

    /// Numbers `op`, books its slot and sends it (followed by `upload_data` messages, each smaller than a
    /// message), once the bytes in flight leave room for it. An `op` larger than a message is refused, unsent.
    /// Once booked, the messages are sent by a task of their own, so that dropping this future cannot leave the
    /// operation unsent or cut short, which would stall or break the stream.
    async fn enqueue<T>(
        &self,
        op: Op,
        upload_data: Vec<Bytes>,
        expect: Expect,
        extract: fn(&Outcome) -> Option<T>,
    ) -> Result<Operation<T>> {
        self.check_message_size(&op)?;
        let bytes = op.encoded_len() + upload_data.iter().map(Bytes::len).sum::<usize>();
        let permits = u32::try_from(bytes).unwrap_or(u32::MAX).clamp(1, self.in_flight_bytes);
        let permit = Arc::clone(&self.in_flight)
            .acquire_many_owned(permits)
            .await
            .map_err(|_| Error::InvalidArgument("the stream is closed".into()))?;
        let turn = Arc::clone(&self.sender).lock_owned().await;
        let sender = turn.clone().ok_or_else(|| Error::InvalidArgument("the stream is finished".into()))?;
        if let Some(broken) = self.shared.progress.borrow().broken.clone() {
            return Err(Error::Status(broken));
        }
        let slot = Arc::new(Slot { expect, answer: Default::default() });
        let id = {
            let mut book = self.shared.book();
            book.sent += 1;
            let id = book.sent;
            book.unanswered.push_back(Unanswered { id, slot: Arc::clone(&slot), _permit: permit });
            id
        };
        let messages = std::iter::once(op).chain(upload_data.into_iter().map(Op::UploadData));
        // The task runs on if this future is dropped; waiting for it keeps enqueueing paced by the transport.
        let _ = tokio::spawn(send_in_turn(turn, sender, id, messages)).await;
        Ok(Operation::new(id, slot, Arc::clone(&self.shared), extract))
    }

    /// Refuses `op` when its message would pass the server's `max_message_bytes`: the server would end the whole
    /// stream over it, where a refusal here fails this operation alone.
    fn check_message_size(&self, op: &Op) -> Result<()> {
        let bytes = op.encoded_len() + OPERATION_FIELD_BYTES;
        if bytes > self.max_message_bytes {
            return Err(Error::InvalidArgument(format!(
                "a stream operation of {bytes} bytes passes the server's max_message_bytes ({}): upload large data \
                 as a buffer first, or send it in smaller operations",
                self.max_message_bytes
            )));
        }
        Ok(())
    }

    /// The contract's reference for `accel`.
    fn accel_ref(&self, accel: AccelArg<'_>) -> Result<proto::AccelRef> {
        use proto::accel_ref::Ref;
        let by = match accel {
            AccelArg::Name(name) => Ref::Name(name.to_owned()),
            AccelArg::Handle(handle) => Ref::Handle(handle.to_owned()),
            AccelArg::Built(build) if build.is_on(&self.shared) => Ref::Operation(build.id()),
            AccelArg::Built(build) => Ref::Handle(finished_elsewhere(build)?.handle),
        };
        Ok(proto::AccelRef { r#ref: Some(by) })
    }

    /// The contract's reference for `buffer`.
    fn buffer_ref(&self, buffer: BufferArg<'_>) -> Result<proto::BufferRef> {
        use proto::buffer_ref::Ref;
        let by = match buffer {
            BufferArg::Name(name) => Ref::Name(name.to_owned()),
            BufferArg::Id(id) => Ref::Id(id.to_owned()),
            BufferArg::Uploaded(upload) if upload.is_on(&self.shared) => Ref::Operation(upload.id()),
            BufferArg::Uploaded(upload) => Ref::Id(finished_elsewhere(upload)?.id),
        };
        Ok(proto::BufferRef { r#ref: Some(by) })
    }
}

/// Sends operation `id`'s `messages` in order, holding the stream's `turn` to send until they are all sent (so the
/// next operation's messages follow them); stops early only when the call is gone, and the receiving task then
/// fails the operation with the reason.
async fn send_in_turn(
    turn: OwnedMutexGuard<Option<RequestSender>>,
    sender: RequestSender,
    id: u64,
    messages: impl Iterator<Item = Op>,
) {
    for op in messages {
        if sender.send(proto::StreamRequest { operation: id, op: Some(op) }).await.is_err() {
            break;
        }
    }
    drop(turn);
}

/// The accel description in an answer.
fn accel_outcome(outcome: &Outcome) -> Option<proto::AccelInfo> {
    if let Outcome::Accel(info) = outcome { Some(info.clone()) } else { None }
}

/// The product of an operation of another stream, which must have finished (else name its product by name, after
/// waiting on an event recorded after it).
fn finished_elsewhere<T>(operation: &Operation<T>) -> Result<T> {
    operation.result().unwrap_or_else(|| {
        Err(Error::InvalidArgument(format!(
            "operation {} of another stream has not finished: name its product by name, after waiting on an event \
             recorded after it",
            operation.id()
        )))
    })
}

impl Drop for Stream {
    /// Cancels an unfinished stream (a `CancelStream` call, sent in the background): the server drops the queued
    /// operations and frees what the stream held. Unanswered handles fail with CANCELLED.
    fn drop(&mut self) {
        if let (Some(mut rpc), Ok(runtime)) = (self.rpc.take(), tokio::runtime::Handle::try_current()) {
            let request = proto::CancelStreamRequest { stream_id: self.shared.stream_id };
            // Best effort: if it cannot be sent, the call's reset (or the connection's end) cancels the stream.
            runtime.spawn(async move { rpc.cancel_stream(request).await });
        }
        self.receiver.abort();
        self.shared.break_with(tonic::Status::cancelled("the stream was dropped"));
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    /// A stream whose requests come out of the returned receiver, which holds `queued` of them before enqueueing
    /// waits, and whose answers come only as a test gives them.
    fn unconnected(queued: usize, upload_chunk_bytes: usize) -> (Stream, mpsc::Receiver<proto::StreamRequest>) {
        let (sender, requests) = mpsc::channel(queued);
        let options = ClientOptions { upload_chunk_bytes, ..ClientOptions::default() };
        let stream = Stream::new(&options, Arc::new(Shared::new(7)), sender, tokio::spawn(async {}), None);
        (stream, requests)
    }

    /// The operation id and kind of each of the next `count` requests, or of as many as come within a second.
    async fn next_requests(requests: &mut mpsc::Receiver<proto::StreamRequest>, count: usize) -> Vec<(u64, String)> {
        let mut received = Vec::new();
        while received.len() < count {
            match tokio::time::timeout(Duration::from_secs(1), requests.recv()).await {
                Ok(Some(request)) => received.push((request.operation, kind_name(request.op))),
                _ => break,
            }
        }
        received
    }

    /// The name of a request's kind.
    fn kind_name(op: Option<Op>) -> String {
        match op {
            Some(Op::Upload(_)) => "upload".into(),
            Some(Op::UploadData(_)) => "data".into(),
            Some(Op::RecordEvent(_)) => "record".into(),
            other => format!("{other:?}"),
        }
    }

    #[tokio::test]
    async fn an_enqueue_given_up_once_booked_still_sends_its_messages_whole_and_before_the_next() {
        let (stream, mut requests) = unconnected(1, 2);
        let upload = stream.upload("", Bytes::from_static(b"abcdefgh"));
        let given_up = tokio::time::timeout(Duration::from_millis(50), upload).await;
        assert!(given_up.is_err(), "the transport holds one message, so the upload waits");
        let (event, received) = tokio::join!(stream.record_event(), next_requests(&mut requests, 5));
        let expected = [(1, "upload"), (1, "data"), (1, "data"), (1, "data"), (2, "record")];
        assert_eq!(received, expected.map(|(id, kind)| (id, kind.to_owned())));
        assert_eq!(event.expect("enqueued").id().operation, 2);
    }

    #[tokio::test]
    async fn finish_returns_once_the_call_has_ended() {
        let (sender, mut requests) = mpsc::channel(1);
        let ended = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let ended_by_server = Arc::clone(&ended);
        // The server's part: it ends the call a moment after the requests have ended.
        let receiver = tokio::spawn(async move {
            while requests.recv().await.is_some() {}
            tokio::time::sleep(Duration::from_millis(50)).await;
            ended_by_server.store(true, std::sync::atomic::Ordering::Release);
        });
        let stream = Stream::new(&ClientOptions::default(), Arc::new(Shared::new(7)), sender, receiver, None);
        stream.finish().await.expect("nothing failed");
        assert!(ended.load(std::sync::atomic::Ordering::Acquire), "finish returned before the call's end was read");
    }

    #[tokio::test]
    async fn after_a_break_the_stream_is_idle_and_events_that_never_ran_have_not_completed() {
        let (stream, _requests) = unconnected(8, 1024);
        let (done, pending) = (stream.record_event().await.unwrap(), stream.record_event().await.unwrap());
        assert!(!stream.query());
        stream.shared.answer(1, Ok(Outcome::Nothing), (5, 9)).unwrap();
        assert!(done.query() && done.completed_unix_ns() == Some(9));
        stream.shared.break_with(tonic::Status::unavailable("the connection dropped"));
        assert!(!pending.query() && pending.completed_unix_ns().is_none(), "it never ran");
        assert!(pending.wait().await.is_err(), "waiting gives the error");
        assert!(stream.query(), "nothing more will run");
        assert!(stream.synchronize().await.is_err(), "synchronize gives the error");
    }
}
