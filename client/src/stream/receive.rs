//! The task that reads a stream's answers, in order, and hands each to its operation's slot.

use std::sync::Arc;

use rayd_proto as proto;
use rayd_proto::operation_result::Outcome as Produced;
use rayd_proto::stream_response::Kind;
use tonic::{Code, Status, Streaming};

use super::state::{Expect, Outcome, Shared};
use crate::reduce::ReducedTrace;
use crate::saved::Download;
use crate::trace::TraceResult;

/// Reads answers until the server ends the stream or the call breaks (a download chunk out of order, or more than
/// this process can hold, breaks it too); then fails whatever is still unanswered.
pub(crate) async fn answers(mut responses: Streaming<proto::StreamResponse>, shared: Arc<Shared>) {
    let mut download = Download::default();
    let end = loop {
        let response = match responses.message().await {
            Ok(Some(response)) => response,
            Ok(None) => break Status::cancelled("the stream was closed"),
            Err(status) => break status,
        };
        match response.kind {
            Some(Kind::DownloadChunk(chunk)) => {
                if let Err(e) = download.push(&chunk) {
                    break Status::new(e.code(), e.to_string());
                }
            }
            Some(Kind::Result(result)) => {
                if let Err(broken) = answer(&shared, result, std::mem::take(&mut download)) {
                    break Status::internal(format!("the server broke the contract: {broken}"));
                }
            }
            _ => break Status::internal("the server broke the contract: a stream message that is not an answer"),
        }
    };
    shared.break_with(end);
}

/// Hands one answer (and the download data before it) to its slot.
fn answer(shared: &Shared, result: proto::OperationResult, data: Download) -> Result<(), String> {
    let id = result.operation;
    let ran = (result.started_unix_ns, result.finished_unix_ns);
    let slot = shared.book().unanswered.front().map(|u| Arc::clone(&u.slot));
    let outcome = if result.code != 0 {
        Err(Status::new(Code::from(result.code), result.message))
    } else {
        let expect = slot.as_ref().map_or(&Expect::Nothing, |s| &s.expect);
        outcome(id, expect, result.outcome, data)
    };
    shared.answer(id, outcome, ran)
}

/// What a successful answer is made into; an answer of the wrong kind, or a download of the wrong size, is an
/// INTERNAL error for its operation.
fn outcome(id: u64, expect: &Expect, produced: Option<Produced>, data: Download) -> Result<Outcome, Status> {
    let wrong = || Status::internal(format!("the server broke the contract: operation {id} got the wrong outcome"));
    match (expect, produced) {
        (Expect::Nothing, None) => Ok(Outcome::Nothing),
        (Expect::Buffer, Some(Produced::Buffer(info))) => Ok(Outcome::Buffer(info)),
        (Expect::Accel, Some(Produced::Accel(info))) => Ok(Outcome::Accel(info)),
        (Expect::Download, Some(Produced::Buffer(info))) => data
            .whole(info.size_bytes)
            .map(Outcome::Bytes)
            .map_err(|e| Status::internal(format!("operation {id}: {e}"))),
        (Expect::Trace(query, rays), Some(Produced::Trace(response))) => {
            TraceResult::from_batch(query, *rays, response)
                .map(Outcome::Trace)
                .map_err(|e| Status::internal(format!("operation {id}: {e}")))
        }
        (Expect::Reduced, Some(Produced::Trace(response))) => ReducedTrace::from_response(response)
            .map(Outcome::Reduced)
            .map_err(|e| Status::internal(format!("operation {id}: {e}"))),
        _ => Err(wrong()),
    }
}

#[cfg(test)]
mod tests {
    use bytes::Bytes;

    use super::*;

    /// The download of one chunk of `data`.
    fn downloaded(data: &'static [u8]) -> Download {
        let mut download = Download::default();
        download.push(&proto::BufferChunk { offset: 0, data: Bytes::from_static(data) }).unwrap();
        download
    }

    #[test]
    fn a_download_answer_must_bring_the_whole_buffer() {
        let buffer = |size_bytes| Some(Produced::Buffer(proto::BufferInfo { size_bytes, ..Default::default() }));
        let whole = outcome(3, &Expect::Download, buffer(4), downloaded(b"abcd")).unwrap();
        assert!(matches!(whole, Outcome::Bytes(data) if data == b"abcd".as_ref()));
        let error = outcome(3, &Expect::Download, buffer(5), downloaded(b"abcd")).unwrap_err();
        assert_eq!(error.code(), Code::Internal);
        assert!(error.message().starts_with("operation 3: the server broke the contract"), "{}", error.message());
    }
}
