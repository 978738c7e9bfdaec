//! What a stream's handles and its receiving task share: the operations waiting for answers, the answers, and
//! how far the stream has come.

use std::collections::VecDeque;
use std::sync::{Mutex, OnceLock};

use bytes::Bytes;
use rayd_engine::query::Query;
use rayd_proto as proto;
use tokio::sync::{OwnedSemaphorePermit, watch};
use tonic::Status;

use crate::reduce::ReducedTrace;
use crate::trace::TraceResult;

/// What an operation's answer is made into.
#[derive(Debug)]
pub(crate) enum Expect {
    /// No outcome (delete, destroy, events).
    Nothing,
    /// A new buffer's description (upload).
    Buffer,
    /// A new accel's description (build).
    Accel,
    /// Hits of `rays` bytes traced with the query.
    Trace(Query, usize),
    /// A reduction of a trace's hits.
    Reduced,
    /// The downloaded bytes.
    Download,
}

/// An operation's answer, made into what it was expected to be.
#[derive(Debug, Clone)]
pub(crate) enum Outcome {
    /// Nothing to return.
    Nothing,
    /// A buffer's description.
    Buffer(proto::BufferInfo),
    /// An accel's description.
    Accel(proto::AccelInfo),
    /// A trace's hits.
    Trace(TraceResult),
    /// A reduction of a trace's hits.
    Reduced(ReducedTrace),
    /// Downloaded bytes.
    Bytes(Bytes),
}

/// The answer to one operation.
#[derive(Debug)]
pub(crate) struct Answer {
    /// What it produced, or why it failed.
    pub result: Result<Outcome, Status>,
    /// When it ran on the server (nanoseconds since the Unix epoch; 0 when it never ran).
    pub ran_unix_ns: (u64, u64),
}

/// Where one operation's answer lands.
#[derive(Debug)]
pub(crate) struct Slot {
    /// What the answer is made into.
    pub expect: Expect,
    /// Set once, when the answer arrives or the stream breaks.
    pub answer: OnceLock<Answer>,
}

/// How far a stream has come.
#[derive(Debug, Clone, Default)]
pub(crate) struct Progress {
    /// Every operation up to this id has been answered.
    pub answered: u64,
    /// Why the stream broke, once it has: no more answers will come.
    pub broken: Option<Status>,
}

/// An operation sent and not yet answered.
#[derive(Debug)]
pub(crate) struct Unanswered {
    /// Its id.
    pub id: u64,
    /// Where its answer goes.
    pub slot: std::sync::Arc<Slot>,
    /// Its share of the bytes in flight, given back with the answer.
    pub _permit: OwnedSemaphorePermit,
}

/// The state shared by a stream's handles and its receiving task.
#[derive(Debug)]
pub(crate) struct Shared {
    /// The server's id of the stream.
    pub stream_id: u64,
    /// Operations waiting for answers, in id order, and failures not yet reported by a synchronize.
    pub book: Mutex<Book>,
    /// How far the stream has come, for waiters.
    pub progress: watch::Sender<Progress>,
}

/// The ledger of a stream's operations.
#[derive(Debug, Default)]
pub(crate) struct Book {
    /// The id of the last operation sent.
    pub sent: u64,
    /// Operations sent and not answered, oldest first.
    pub unanswered: VecDeque<Unanswered>,
    /// Failed operations since the last synchronize.
    pub failures: Vec<(u64, Status)>,
}

impl Shared {
    /// The shared state of stream `stream_id`.
    pub fn new(stream_id: u64) -> Shared {
        Shared { stream_id, book: Mutex::default(), progress: watch::Sender::new(Progress::default()) }
    }

    /// The ledger, locked.
    pub fn book(&self) -> std::sync::MutexGuard<'_, Book> {
        self.book.lock().expect("not poisoned")
    }

    /// Waits until operation `id` has been answered or the stream broke; returns the reason if it broke first.
    pub async fn answered(&self, id: u64) -> Option<Status> {
        let mut progress = self.progress.subscribe();
        let progress = progress.wait_for(|p| p.answered >= id || p.broken.is_some()).await.ok()?;
        if progress.answered >= id { None } else { progress.broken.clone() }
    }

    /// Whether operation `id` has been answered.
    pub fn is_answered(&self, id: u64) -> bool {
        self.progress.borrow().answered >= id
    }

    /// Records the answer to the oldest unanswered operation, which must be `id`.
    pub fn answer(&self, id: u64, result: Result<Outcome, Status>, ran_unix_ns: (u64, u64)) -> Result<(), String> {
        let mut book = self.book();
        let Some(front) = book.unanswered.pop_front() else {
            return Err(format!("an answer to operation {id}, which was never sent"));
        };
        if front.id != id {
            return Err(format!("an answer to operation {id} where operation {} was due", front.id));
        }
        if let Err(status) = &result {
            book.failures.push((id, status.clone()));
        }
        let _ = front.slot.answer.set(Answer { result, ran_unix_ns });
        drop(book);
        self.progress.send_modify(|p| p.answered = id);
        Ok(())
    }

    /// Fails every unanswered operation with `status` and marks the stream broken.
    pub fn break_with(&self, status: Status) {
        let mut book = self.book();
        for unanswered in book.unanswered.drain(..) {
            let _ = unanswered.slot.answer.set(Answer { result: Err(status.clone()), ran_unix_ns: (0, 0) });
        }
        drop(book);
        self.progress.send_modify(|p| {
            p.broken.get_or_insert(status);
        });
    }
}
