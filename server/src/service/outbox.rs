//! The answers of a streaming call: a bounded queue between the task that makes them and the response stream that
//! sends them, failed when the client stops reading. HTTP/2 flow control stops the sending when the client reads
//! nothing, the queue then fills and the maker waits; if it waits longer than the stall limit, the answers held are
//! dropped and the stream ends with RESOURCE_EXHAUSTED naming `limits.stream_stall_seconds` (seen by the client
//! when it reads again), so a client that stops reading holds server memory for a bounded time only.

use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::task::{Context, Poll, Waker};
use std::time::Duration;

use tokio::sync::mpsc;
use tokio_stream::Stream;
use tonic::Status;

/// A new outbox of `window` answers (at least one) for a `method` call of `tenant`, whose maker gives up after
/// waiting `stall` for room (`None`: waits as long as the call lasts).
pub fn outbox<T>(
    window: usize,
    stall: Option<Duration>,
    method: &'static str,
    tenant: &str,
) -> (Outbox<T>, Answers<T>) {
    let (sender, receiver) = mpsc::channel(window.max(1));
    let shared = Arc::new(Mutex::new(Shared { queued: Some(receiver), failure: None, waker: None }));
    let call = (method, tenant.to_owned());
    (Outbox { sender, shared: Arc::downgrade(&shared), stall, call }, Answers { shared })
}

/// The maker's end.
#[derive(Debug)]
pub struct Outbox<T> {
    /// Into the queue.
    sender: mpsc::Sender<Result<T, Status>>,
    /// What the response stream reads (weak: when the call drops its response stream, the queue goes with it and
    /// the outbox is closed).
    shared: Weak<Mutex<Shared<T>>>,
    /// How long a send waits for room before the stream is failed.
    stall: Option<Duration>,
    /// The call's method and tenant, which a stall is counted under.
    call: (&'static str, String),
}

/// An answer that was not queued: the call ended, or its client stopped reading (the stream is failed).
#[derive(Debug)]
pub struct Undelivered;

/// The response stream's end: the answers in order, then the failure if the client stalled.
#[derive(Debug)]
pub struct Answers<T> {
    /// What the outbox writes.
    shared: Arc<Mutex<Shared<T>>>,
}

/// The queue, the failure that replaces it and the response stream's waker.
#[derive(Debug)]
struct Shared<T> {
    /// Answers waiting to be sent; taken (and dropped) when the stream is failed.
    queued: Option<mpsc::Receiver<Result<T, Status>>>,
    /// The status the stream ends with after a stall.
    failure: Option<Status>,
    /// Wakes the response stream when it waits on a queue that is taken away.
    waker: Option<Waker>,
}

fn lock<T>(shared: &Mutex<Shared<T>>) -> MutexGuard<'_, Shared<T>> {
    shared.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl<T> Outbox<T> {
    /// Queues `answer` (an answer or the status that ends the call), waiting for room at most the stall limit.
    pub async fn send(&self, answer: Result<T, Status>) -> Result<(), Undelivered> {
        let sent = match self.stall {
            None => self.sender.send(answer).await,
            Some(stall) => match tokio::time::timeout(stall, self.sender.send(answer)).await {
                Ok(sent) => sent,
                Err(_) => {
                    let (method, tenant) = (self.call.0, self.call.1.as_str());
                    self.fail(|held| {
                        crate::metrics::stream_stalled(method, tenant, held);
                        Status::resource_exhausted(format!(
                            "the client read no answer for {} s (limits.stream_stall_seconds): the stream is \
                                 failed and the {held} answers it held are dropped",
                            stall.as_secs()
                        ))
                    });
                    return Err(Undelivered);
                }
            },
        };
        sent.map_err(|_| Undelivered)
    }

    /// Queues `answer` if there is room now (the first answer of a call always has room).
    pub fn try_send(&self, answer: Result<T, Status>) -> Result<(), Undelivered> {
        self.sender.try_send(answer).map_err(|_| Undelivered)
    }

    /// Resolves when nothing more can be delivered: the call ended, or the stream was failed.
    pub async fn closed(&self) {
        self.sender.closed().await
    }

    /// Drops the answers held and ends the stream with the status that `why` makes of their count (after a stall,
    /// or when the stream is cancelled).
    pub fn fail(&self, why: impl FnOnce(usize) -> Status) {
        let Some(shared) = self.shared.upgrade() else { return };
        let mut shared = lock(&shared);
        let held = shared.queued.take().map_or(0, |queue| queue.len());
        shared.failure = Some(why(held));
        if let Some(waker) = shared.waker.take() {
            waker.wake();
        }
    }
}

impl<T> Drop for Outbox<T> {
    /// An outbox dropped while its thread panics belongs to a task that panicked (a bug; the runtime drops a
    /// panicked task's future as the panic unwinds): the answers queued are still sent, then the call ends with
    /// INTERNAL rather than as if the task had made its last answer.
    fn drop(&mut self) {
        if !std::thread::panicking() {
            return;
        }
        let Some(shared) = self.shared.upgrade() else { return };
        lock(&shared).failure.get_or_insert_with(|| {
            Status::internal("the task answering this call panicked (a bug): no answers follow the ones sent")
        });
    }
}

impl<T> Stream for Answers<T> {
    type Item = Result<T, Status>;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let mut shared = lock(&self.shared);
        if let Some(queue) = shared.queued.as_mut() {
            match queue.poll_recv(cx) {
                Poll::Ready(Some(answer)) => return Poll::Ready(Some(answer)),
                Poll::Ready(None) => shared.queued = None,
                Poll::Pending => {
                    shared.waker = Some(cx.waker().clone());
                    return Poll::Pending;
                }
            }
        }
        Poll::Ready(shared.failure.take().map(Err))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio_stream::StreamExt;

    #[tokio::test]
    async fn answers_come_in_order_and_end_when_the_maker_is_done() {
        let (outbox, mut answers) = outbox::<u32>(2, Some(Duration::from_secs(5)), "Test", "t");
        let maker = tokio::spawn(async move {
            for n in 0..5 {
                outbox.send(Ok(n)).await.unwrap();
            }
        });
        let mut got = Vec::new();
        while let Some(answer) = answers.next().await {
            got.push(answer.unwrap());
        }
        maker.await.unwrap();
        assert_eq!(got, [0, 1, 2, 3, 4]);
    }

    #[tokio::test]
    async fn a_reader_that_stalls_gets_the_failure_after_what_was_left() {
        let (outbox, mut answers) = outbox::<u32>(2, Some(Duration::from_millis(50)), "Test", "t");
        outbox.send(Ok(0)).await.unwrap();
        outbox.send(Ok(1)).await.unwrap();
        assert!(outbox.send(Ok(2)).await.is_err(), "no room for 50 ms: the stream is failed");
        let failure = answers.next().await.expect("the failure").expect_err("held answers are dropped");
        assert_eq!(failure.code(), tonic::Code::ResourceExhausted);
        assert!(failure.message().contains("limits.stream_stall_seconds"), "{failure:?}");
        assert!(failure.message().contains("the 2 answers"), "{failure:?}");
        assert!(answers.next().await.is_none(), "and the stream ends");
        assert!(outbox.send(Ok(3)).await.is_err(), "nothing more is queued");
    }

    #[tokio::test]
    async fn a_maker_that_panics_ends_the_call_with_internal_after_its_answers() {
        let (outbox, mut answers) = outbox::<u32>(2, Some(Duration::from_secs(5)), "Test", "t");
        let maker = tokio::spawn(async move {
            outbox.send(Ok(0)).await.unwrap();
            panic!("a bug in the maker");
        });
        assert!(maker.await.unwrap_err().is_panic());
        assert_eq!(answers.next().await.unwrap().unwrap(), 0, "what was queued is still sent");
        let failure = answers.next().await.expect("the failure").expect_err("the call does not end OK");
        assert_eq!(failure.code(), tonic::Code::Internal, "{failure:?}");
        assert!(answers.next().await.is_none(), "and the stream ends");
    }

    #[tokio::test]
    async fn dropping_the_answers_closes_the_outbox() {
        let (outbox, answers) = outbox::<u32>(2, Some(Duration::from_secs(5)), "Test", "t");
        outbox.send(Ok(0)).await.unwrap();
        drop(answers);
        tokio::time::timeout(Duration::from_secs(5), outbox.closed()).await.expect("closed when the call ends");
        assert!(outbox.send(Ok(1)).await.is_err());
    }

    #[tokio::test]
    async fn without_a_stall_limit_the_maker_waits_for_the_reader() {
        let (outbox, mut answers) = outbox::<u32>(1, None, "Test", "t");
        outbox.send(Ok(0)).await.unwrap();
        let waiting = tokio::spawn(async move { outbox.send(Ok(1)).await.is_ok() });
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert!(!waiting.is_finished(), "waits while the reader reads nothing");
        assert_eq!(answers.next().await.unwrap().unwrap(), 0);
        assert!(waiting.await.unwrap(), "then delivers");
        assert_eq!(answers.next().await.unwrap().unwrap(), 1);
    }
}
