//! `OpenStream`: an ordered, asynchronous queue of operations per call (the semantics are in streams.proto).
//!
//! A reader task takes messages off the call into a bounded queue; an executor task runs the operations one at a
//! time, in order, and sends their answers through a bounded outbox (failed, its answers dropped, when the client
//! reads none for `stream_stall_seconds`). Everything queued or unsent is counted in
//! the tenant's stream bytes. Cancelling the call (or a rule broken by a message) aborts both tasks, which drops
//! the queued work and the unsent answers.

mod executor;
mod products;
mod reader;

use std::pin::Pin;
use std::sync::{Arc, Mutex};

use bytes::Bytes;
use rayd_proto as pb;
use rayd_proto::stream_request::Op;
use tokio::sync::mpsc;
use tokio_stream::{Stream, StreamExt};
use tokio_util::sync::CancellationToken;
use tonic::{Status, Streaming};

use super::outbox::outbox;
use crate::error::ServiceResult;
use crate::streams::Held;
use crate::tenant::Tenant;

/// The response stream of `OpenStream`.
pub type ResponseStream = Pin<Box<dyn Stream<Item = Result<pb::StreamResponse, Status>> + Send>>;

/// A message waiting for the executor, its bytes counted while it waits.
#[derive(Debug)]
enum Queued {
    /// An operation.
    Op {
        /// Its id.
        id: u64,
        /// What to do (never `UploadData`).
        op: Op,
        /// Its bytes, counted.
        _held: Held,
    },
    /// More data of upload `id`.
    UploadData {
        /// The upload's operation id.
        id: u64,
        /// The bytes.
        data: Bytes,
        /// Its bytes, counted.
        _held: Held,
    },
}

/// An answer waiting to be sent, its bytes counted until the call takes it.
#[derive(Debug)]
struct Answer {
    /// The message.
    response: pb::StreamResponse,
    /// Its bytes, counted.
    _held: Held,
}

/// How a stream is stopped early, shared by its two tasks.
#[derive(Debug)]
struct Abort {
    /// Cancelled when the stream must stop.
    token: CancellationToken,
    /// The status the call ends with, when a message broke the rules (the first reason wins).
    reason: Mutex<Option<Status>>,
}

impl Abort {
    /// Stops both tasks; `reason` (if any) ends the call after the answers already sent.
    fn abort(&self, reason: Option<Status>) {
        if let Some(status) = reason {
            self.reason.lock().expect("not poisoned").get_or_insert(status);
        }
        self.token.cancel();
    }

    /// Completes once the stream must stop (also when CancelStream cancelled it).
    async fn cancelled(&self) {
        self.token.cancelled().await
    }

    /// Whether the stream must stop.
    fn is_cancelled(&self) -> bool {
        self.token.is_cancelled()
    }

    /// Whether a reason to end the call with was given.
    fn has_reason(&self) -> bool {
        self.reason.lock().expect("not poisoned").is_some()
    }

    /// The status to end the call with, if any.
    fn take_reason(&self) -> Option<Status> {
        self.reason.lock().expect("not poisoned").take()
    }
}

/// Opens a stream for `tenant` over `requests`.
pub fn open(tenant: Arc<Tenant>, requests: Streaming<pb::StreamRequest>) -> ServiceResult<ResponseStream> {
    let (slot, place) = tenant.streams().open(tenant.limits().max_streams)?;
    let window = tenant.limits().window();
    let (queue, queued) = mpsc::channel(window as usize);
    // One place more than the window, for the `opened` message.
    let (answers, answered) = outbox(window as usize + 1, tenant.limits().stream_stall(), "OpenStream", tenant.name());
    let opened = pb::StreamResponse {
        kind: Some(pb::stream_response::Kind::Opened(pb::StreamOpened { stream_id: slot.id, window })),
    };
    let held = tenant.streams().hold(0);
    answers.try_send(Ok(Answer { response: opened, _held: held })).expect("an empty outbox has room");
    let abort = Arc::new(Abort { token: slot.cancel.clone(), reason: Mutex::default() });
    let reader = tokio::spawn(reader::run(requests, queue, Arc::clone(tenant.streams()), Arc::clone(&abort)));
    tokio::spawn(executor::Executor::new(tenant, slot).run(queued, reader, answers, Arc::clone(&abort)));
    let answers = answered.map(|answer| answer.map(|answer| answer.response));
    let ending = tokio_stream::iter(std::iter::once_with(move || abort.take_reason())).filter_map(|r| r.map(Err));
    // The stream's place goes with the call: once its last answer has been sent, or the call is gone.
    Ok(Box::pin(place.held_by(answers.chain(ending))))
}
