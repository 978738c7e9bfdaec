//! A tenant's open streams: their ids, how far each has run (what events wait on), and the bytes they hold.

use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};

use dashmap::DashMap;
use tokio::sync::watch;
use tokio_stream::{Stream, StreamExt};
use tokio_util::sync::CancellationToken;

use crate::error::{ServiceError, ServiceResult};

/// How far a stream has run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Progress {
    /// Every operation up to this id has finished.
    pub finished: u64,
    /// The stream has ended: nothing more will run on it.
    pub closed: bool,
}

/// The open streams of one tenant.
#[derive(Debug, Default)]
pub struct Streams {
    /// The id the next stream gets; ids start at 1 and are never reused.
    next_id: AtomicU64,
    /// Streams open now.
    open_count: AtomicU32,
    /// Each open stream, by id.
    open: DashMap<u64, OpenStream>,
    /// Bytes held by every stream: queued operations, partial uploads, unsent answers.
    held_bytes: Arc<AtomicU64>,
}

/// What the table keeps of an open stream.
#[derive(Debug)]
struct OpenStream {
    /// Its progress.
    progress: watch::Receiver<Progress>,
    /// Cancels it.
    cancel: CancellationToken,
}

/// One open stream's entry in the table; dropping it marks the stream closed (nothing more runs on it).
#[derive(Debug)]
pub struct StreamSlot {
    /// The stream's id.
    pub id: u64,
    /// Where its progress is published.
    progress: watch::Sender<Progress>,
    /// Cancelled when the stream must stop (by CancelStream, or by the stream itself).
    pub cancel: CancellationToken,
    /// The table it belongs to.
    streams: Arc<Streams>,
}

/// A place among a tenant's `max_streams`, an `OpenStream`'s or a `TraceStream`'s, held for as long as its call
/// lasts (its last answers sent, or the call gone); freed when dropped.
#[derive(Debug)]
pub struct Place {
    /// The table whose count it holds one of.
    streams: Arc<Streams>,
}

impl Place {
    /// `stream` (a call's answers), holding this place until it is dropped: until the call has ended.
    pub fn held_by<S: Stream>(self, stream: S) -> impl Stream<Item = S::Item> {
        stream.map(move |answer| {
            let _held = &self;
            answer
        })
    }
}

impl Drop for Place {
    fn drop(&mut self) {
        self.streams.open_count.fetch_sub(1, Ordering::AcqRel);
    }
}

/// Bytes a stream holds, counted in its tenant's usage until dropped.
#[derive(Debug)]
pub struct Held {
    /// The bytes counted.
    bytes: u64,
    /// The tenant's total.
    total: Arc<AtomicU64>,
}

/// What waiting for another stream's operation comes to.
#[derive(Debug)]
pub enum Waitable {
    /// The stream is open: wait on its progress.
    Open(watch::Receiver<Progress>),
    /// The stream has closed: it has no work left to wait for.
    Closed,
}

impl Streams {
    /// Takes a place among the streams open unless `max_streams` are open already (RESOURCE_EXHAUSTED naming it).
    pub fn place(self: &Arc<Self>, max_streams: u32) -> ServiceResult<Place> {
        let admitted =
            self.open_count.fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| (n < max_streams).then_some(n + 1));
        if let Err(open) = admitted {
            return Err(ServiceError::Limit {
                what: "streams open at once".into(),
                requested: open as u64 + 1,
                limit: "max_streams",
                allowed: max_streams as u64,
            });
        }
        Ok(Place { streams: Arc::clone(self) })
    }

    /// Opens a stream unless `max_streams` are open already: its entry (an id, its progress, a way to cancel it),
    /// and its place.
    pub fn open(self: &Arc<Self>, max_streams: u32) -> ServiceResult<(StreamSlot, Place)> {
        let place = self.place(max_streams)?;
        let id = self.next_id.fetch_add(1, Ordering::Relaxed) + 1;
        let (progress, receiver) = watch::channel(Progress::default());
        let cancel = CancellationToken::new();
        self.open.insert(id, OpenStream { progress: receiver, cancel: cancel.clone() });
        Ok((StreamSlot { id, progress, cancel, streams: Arc::clone(self) }, place))
    }

    /// Cancels stream `id` if it is open; NOT_FOUND for an id never given out.
    pub fn cancel(&self, id: u64) -> ServiceResult<()> {
        self.check_issued(id)?;
        if let Some(stream) = self.open.get(&id) {
            stream.cancel.cancel();
        }
        Ok(())
    }

    /// Fails with NOT_FOUND unless stream `id` was given out.
    fn check_issued(&self, id: u64) -> ServiceResult<()> {
        if id == 0 || id > self.next_id.load(Ordering::Relaxed) {
            return Err(ServiceError::NotFound { what: "stream", name: id.to_string(), field: String::new() });
        }
        Ok(())
    }

    /// What waiting on stream `id` comes to; NOT_FOUND for an id never given out.
    pub fn waitable(&self, id: u64) -> ServiceResult<Waitable> {
        self.check_issued(id)?;
        Ok(self.open.get(&id).map_or(Waitable::Closed, |stream| Waitable::Open(stream.progress.clone())))
    }

    /// Counts `bytes` as held by a stream until the returned guard is dropped.
    pub fn hold(&self, bytes: u64) -> Held {
        self.held_bytes.fetch_add(bytes, Ordering::Relaxed);
        Held { bytes, total: Arc::clone(&self.held_bytes) }
    }

    /// Streams open now.
    pub fn open_count(&self) -> u32 {
        self.open_count.load(Ordering::Relaxed)
    }

    /// Bytes all streams hold now.
    pub fn held_bytes(&self) -> u64 {
        self.held_bytes.load(Ordering::Relaxed)
    }
}

impl StreamSlot {
    /// Publishes that every operation up to `operation` has finished.
    pub fn finished(&self, operation: u64) {
        self.progress.send_modify(|p| p.finished = operation);
    }
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        self.streams.open.remove(&self.id);
        self.progress.send_modify(|p| p.closed = true);
    }
}

impl Held {
    /// Counts `bytes` more.
    pub fn grow(&mut self, bytes: u64) {
        self.total.fetch_add(bytes, Ordering::Relaxed);
        self.bytes += bytes;
    }
}

impl Drop for Held {
    fn drop(&mut self) {
        self.total.fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slots_are_limited_numbered_and_leave_a_closed_mark_behind() {
        let streams = Arc::new(Streams::default());
        let (first, first_place) = streams.open(2).unwrap();
        let (second, _second_place) = streams.open(2).unwrap();
        assert_eq!((first.id, second.id), (1, 2));
        assert!(matches!(streams.open(2), Err(ServiceError::Limit { limit: "max_streams", .. })));
        let Waitable::Open(mut progress) = streams.waitable(1).unwrap() else { panic!("stream 1 is open") };
        first.finished(3);
        assert_eq!(progress.borrow_and_update().finished, 3);
        drop(first);
        assert!(progress.borrow().closed);
        // Closed, its call may still be sending its last answers: the place is held until that ends.
        assert!(matches!(streams.place(2), Err(ServiceError::Limit { limit: "max_streams", .. })));
        drop(first_place);
        assert!(matches!(streams.waitable(1).unwrap(), Waitable::Closed));
        assert!(matches!(streams.waitable(9), Err(ServiceError::NotFound { .. })));
        streams.cancel(2).unwrap();
        assert!(second.cancel.is_cancelled());
        streams.cancel(1).expect("cancelling a closed stream is not an error");
        assert!(matches!(streams.cancel(9), Err(ServiceError::NotFound { .. })));
        let (third, _third_place) = streams.open(2).unwrap();
        assert_eq!(third.id, 3, "ids are not reused; the freed place is");
        assert_eq!(streams.open_count(), 2);
        assert!(matches!(streams.place(2), Err(ServiceError::Limit { limit: "max_streams", .. })));
    }

    #[test]
    fn held_bytes_count_until_dropped() {
        let streams = Streams::default();
        let mut held = streams.hold(10);
        held.grow(5);
        let other = streams.hold(1);
        assert_eq!(streams.held_bytes(), 16);
        drop(held);
        assert_eq!(streams.held_bytes(), 1);
        drop(other);
        assert_eq!(streams.held_bytes(), 0);
    }
}
