//! Takes a stream's messages off the call, checks their numbering, and queues them for the executor. The queue
//! is bounded: when it is full the reader stops reading and HTTP/2 flow control holds the client back.

use std::sync::Arc;

use prost::Message;
use rayd_proto as pb;
use rayd_proto::stream_request::Op;
use tokio::sync::mpsc;
use tonic::Streaming;

use super::{Abort, Queued};
use crate::error::{ServiceError, ServiceResult};
use crate::streams::Streams;

/// Reads until the client half-closes (the queue then ends and the executor drains it), the call breaks, or a
/// message breaks the rules (the stream is aborted with that status).
pub async fn run(
    mut requests: Streaming<pb::StreamRequest>,
    queue: mpsc::Sender<Queued>,
    streams: Arc<Streams>,
    abort: Arc<Abort>,
) {
    let mut numbering = Numbering::default();
    loop {
        let message = tokio::select! {
            () = abort.cancelled() => return,
            message = requests.message() => message,
        };
        let request = match message {
            Ok(Some(request)) => request,
            Ok(None) => return,
            Err(status) => return abort.abort(Some(status)),
        };
        let held = streams.hold(request.encoded_len() as u64);
        let item = match numbering.check(request) {
            Ok((id, Op::UploadData(data))) => Queued::UploadData { id, data, _held: held },
            Ok((id, op)) => Queued::Op { id, op, _held: held },
            Err(error) => return abort.abort(Some(error.into())),
        };
        tokio::select! {
            () = abort.cancelled() => return,
            sent = queue.send(item) => if sent.is_err() { return },
        }
    }
}

/// The numbering rules: operations 1, 2, 3 … in order; upload data right after its upload, never more than
/// declared.
#[derive(Debug, Default)]
struct Numbering {
    /// The last operation id received.
    last: u64,
    /// When the last operation is an upload: the bytes it may still receive.
    upload_left: Option<u64>,
}

impl Numbering {
    /// Checks one message; returns its operation id and its operation.
    fn check(&mut self, request: pb::StreamRequest) -> ServiceResult<(u64, Op)> {
        let id = request.operation;
        let op = request.op.ok_or_else(|| ServiceError::invalid("op", format!("operation {id}: an op is required")))?;
        if let Op::UploadData(data) = &op {
            let left = self.upload_left.filter(|_| id == self.last).ok_or_else(|| {
                ServiceError::invalid("upload_data", format!("operation {id} is not the upload that was sent last"))
            })?;
            let left = left
                .checked_sub(data.len() as u64)
                .ok_or_else(|| ServiceError::invalid("upload_data", format!("more bytes than upload {id} declared")))?;
            self.upload_left = Some(left);
            return Ok((id, op));
        }
        if id != self.last + 1 {
            return Err(ServiceError::invalid(
                "operation",
                format!(
                    "{id} received where {} was expected (operations are numbered 1, 2, 3 … in order)",
                    self.last + 1
                ),
            ));
        }
        self.last = id;
        self.upload_left = match &op {
            Op::Upload(upload) => {
                let declared = upload.header.as_ref().map_or(0, |h| h.size_bytes);
                Some(declared.checked_sub(upload.first_data.len() as u64).ok_or_else(|| {
                    ServiceError::invalid("upload.first_data", format!("more bytes than upload {id} declared"))
                })?)
            }
            _ => None,
        };
        Ok((id, op))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(operation: u64, op: Op) -> pb::StreamRequest {
        pb::StreamRequest { operation, op: Some(op) }
    }

    fn upload(size_bytes: u64, first: &'static [u8]) -> Op {
        let header = pb::UploadBufferHeader { name: String::new(), size_bytes };
        Op::Upload(pb::StreamUpload { header: Some(header), first_data: first.into() })
    }

    #[test]
    fn operations_are_numbered_in_order_and_uploads_take_exactly_their_declared_bytes() {
        let mut numbering = Numbering::default();
        numbering.check(message(1, Op::RecordEvent(pb::RecordEvent {}))).unwrap();
        numbering.check(message(2, upload(5, b"ab"))).unwrap();
        numbering.check(message(2, Op::UploadData(b"cd".as_slice().into()))).unwrap();
        let over = numbering.check(message(2, Op::UploadData(b"ef".as_slice().into()))).unwrap_err();
        assert!(over.to_string().contains("more bytes than upload 2 declared"), "{over}");
        numbering.check(message(2, Op::UploadData(b"e".as_slice().into()))).unwrap();
        let skipped = numbering.check(message(4, Op::RecordEvent(pb::RecordEvent {}))).unwrap_err();
        assert!(skipped.to_string().contains("4 received where 3 was expected"), "{skipped}");
        numbering.check(message(3, Op::RecordEvent(pb::RecordEvent {}))).unwrap();
        let stray = numbering.check(message(3, Op::UploadData(b"x".as_slice().into()))).unwrap_err();
        assert!(stray.to_string().contains("not the upload that was sent last"), "{stray}");
        assert!(numbering.check(message(4, upload(1, b"xy"))).is_err());
        assert!(numbering.check(pb::StreamRequest { operation: 4, op: None }).is_err());
    }
}
