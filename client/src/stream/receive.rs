//! The task that reads a stream's answers, in order, and hands each to its operation's slot.

use std::sync::Arc;

use bytes::{Bytes, BytesMut};
use rayd_proto as proto;
use rayd_proto::operation_result::Outcome as Produced;
use rayd_proto::stream_response::Kind;
use tonic::{Code, Status, Streaming};

use super::state::{Expect, Outcome, Shared};
use crate::reduce::ReducedTrace;
use crate::trace::TraceResult;

/// Reads answers until the server ends the stream or the call breaks; then fails whatever is still unanswered.
pub(crate) async fn answers(mut responses: Streaming<proto::StreamResponse>, shared: Arc<Shared>) {
    let mut download = BytesMut::new();
    let end = loop {
        let response = match responses.message().await {
            Ok(Some(response)) => response,
            Ok(None) => break Status::cancelled("the stream was closed"),
            Err(status) => break status,
        };
        match response.kind {
            Some(Kind::DownloadChunk(chunk)) => download.extend_from_slice(&chunk.data),
            Some(Kind::Result(result)) => {
                if let Err(broken) = answer(&shared, result, download.split().freeze()) {
                    break Status::internal(format!("the server broke the contract: {broken}"));
                }
            }
            _ => break Status::internal("the server broke the contract: a stream message that is not an answer"),
        }
    };
    shared.break_with(end);
}

/// Hands one answer (and the download data before it) to its slot.
fn answer(shared: &Shared, result: proto::OperationResult, data: Bytes) -> Result<(), String> {
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

/// What a successful answer is made into; an answer of the wrong kind is an INTERNAL error for its operation.
fn outcome(id: u64, expect: &Expect, produced: Option<Produced>, data: Bytes) -> Result<Outcome, Status> {
    let wrong = || Status::internal(format!("the server broke the contract: operation {id} got the wrong outcome"));
    match (expect, produced) {
        (Expect::Nothing, None) => Ok(Outcome::Nothing),
        (Expect::Buffer, Some(Produced::Buffer(info))) => Ok(Outcome::Buffer(info)),
        (Expect::Accel, Some(Produced::Accel(info))) => Ok(Outcome::Accel(info)),
        (Expect::Download, Some(Produced::Buffer(_))) => Ok(Outcome::Bytes(data)),
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
