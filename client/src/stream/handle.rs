//! Handles to a stream's operations and events: they become ready when the answer arrives (at the latest when a
//! synchronize returns), and can be waited on or polled on their own.

use std::sync::Arc;

use tonic::Status;

use super::state::{Outcome, Shared, Slot};
use crate::error::{Error, Result};

/// One enqueued operation; `T` is what it produces (`()` for none).
#[derive(Debug)]
pub struct Operation<T> {
    /// Its id in its stream.
    id: u64,
    /// Where its answer lands.
    slot: Arc<Slot>,
    /// Its stream's shared state.
    shared: Arc<Shared>,
    /// Takes the product out of a successful answer (`None` when it holds another kind).
    extract: fn(&Outcome) -> Option<T>,
}

impl<T> Operation<T> {
    /// A handle to operation `id`, whose answer lands in `slot`.
    pub(crate) fn new(id: u64, slot: Arc<Slot>, shared: Arc<Shared>, extract: fn(&Outcome) -> Option<T>) -> Self {
        Operation { id, slot, shared, extract }
    }

    /// Its id in its stream (1, 2, 3 … in enqueue order).
    pub fn id(&self) -> u64 {
        self.id
    }

    /// Whether its answer has arrived, or its stream broke before it did (never blocks): either way
    /// [`Operation::result`] has it.
    pub fn is_done(&self) -> bool {
        self.slot.answer.get().is_some()
    }

    /// Its product or its error, once answered (always after a synchronize that covered it).
    pub fn result(&self) -> Option<Result<T>> {
        let answer = self.slot.answer.get()?;
        Some(match &answer.result {
            Ok(outcome) => (self.extract)(outcome)
                .ok_or_else(|| Error::Protocol(format!("operation {} got the wrong outcome", self.id))),
            Err(status) => Err(Error::Operation { operation: self.id, status: status.clone() }),
        })
    }

    /// Waits for this operation alone, then returns its product or its error.
    pub async fn wait(&self) -> Result<T> {
        self.shared.answered(self.id).await;
        self.result().unwrap_or_else(|| Err(broken(self.id)))
    }

    /// When it started and finished on the server, in nanoseconds since the Unix epoch; `None` until answered,
    /// `(0, 0)` when it never ran.
    pub fn ran_unix_ns(&self) -> Option<(u64, u64)> {
        self.slot.answer.get().map(|answer| answer.ran_unix_ns)
    }

    /// Whether it was enqueued on the stream with this shared state.
    pub(crate) fn is_on(&self, shared: &Arc<Shared>) -> bool {
        Arc::ptr_eq(&self.shared, shared)
    }
}

/// A point recorded in a stream: it completes when every operation enqueued on that stream before it has
/// finished. Other streams can wait for it ([`Stream::wait_event`](super::Stream::wait_event)). If its stream
/// breaks first, it never completes, and [`Event::wait`] returns the stream's error at once.
#[derive(Debug)]
pub struct Event {
    /// The record operation.
    pub(crate) record: Operation<()>,
}

/// What names an event on the server: the recording stream's id and the record operation's id. Plain data, so an
/// event recorded by another client (another process) can be waited on once its id is passed along.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EventId {
    /// The recording stream's server id.
    pub stream_id: u64,
    /// The record operation's id in that stream.
    pub operation: u64,
}

impl Event {
    /// The event's name on the server.
    pub fn id(&self) -> EventId {
        EventId { stream_id: self.record.shared.stream_id, operation: self.record.id }
    }

    /// Whether the event has completed (never blocks); false for good once it cannot (its stream broke first), and
    /// [`Event::wait`] then returns the error at once.
    pub fn query(&self) -> bool {
        self.record.result().is_some_and(|result| result.is_ok())
    }

    /// When the record operation finished on the server (nanoseconds since the Unix epoch), once completed.
    pub fn completed_unix_ns(&self) -> Option<u64> {
        self.record.ran_unix_ns().filter(|_| self.query()).map(|(_, finished)| finished)
    }

    /// Waits until the event has completed; fails if its stream broke first.
    pub async fn wait(&self) -> Result<()> {
        self.record.wait().await
    }
}

impl From<&Event> for EventId {
    fn from(event: &Event) -> Self {
        event.id()
    }
}

/// The error of an operation whose stream broke before answering it.
fn broken(id: u64) -> Error {
    Error::Operation { operation: id, status: Status::cancelled("the stream broke before the answer came") }
}
