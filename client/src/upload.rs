//! `UploadBuffer`: a header, then the data in slices of one shared `Bytes` (no copies on the client), or as a stream
//! of parts yields it (a file read a part at a time).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};

use bytes::Bytes;
use futures_util::{Stream, StreamExt};
use rayd_proto as proto;
use rayd_proto::upload_buffer_request::Part;

use crate::client::Client;
use crate::convert::buffer_ref;
use crate::error::{Error, Result};

impl Client {
    /// Uploads `data` as a new server buffer, named `name` unless it is empty, in messages of
    /// [`ClientOptions::upload_chunk_bytes`](crate::ClientOptions::upload_chunk_bytes).
    pub async fn upload_buffer(&self, name: &str, data: Bytes) -> Result<proto::BufferInfo> {
        let requests = upload_requests(name, data, self.options.upload_chunk_bytes);
        Ok(self.rpc.clone().upload_buffer(tokio_stream::iter(requests)).await?.into_inner())
    }

    /// Uploads the `size_bytes` bytes that `parts` yields (cut anywhere: each part is one data message, so keep them
    /// within [`ClientOptions::upload_chunk_bytes`](crate::ClientOptions::upload_chunk_bytes)) as a new server
    /// buffer, named `name` unless it is empty, holding one part at a time. The first error of `parts` ends the
    /// upload and is what this returns; the server keeps nothing of it (an upload that had sent every byte before
    /// the error is deleted again).
    pub async fn upload_buffer_parts(
        &self,
        name: &str,
        size_bytes: u64,
        parts: impl Stream<Item = Result<Bytes>> + Send + 'static,
    ) -> Result<proto::BufferInfo> {
        let failed: Arc<Mutex<Option<Error>>> = Arc::default();
        let failure = Arc::clone(&failed);
        let data = parts.scan((), move |(), part| {
            std::future::ready(match part {
                Ok(data) => Some(request(Part::Data(data))),
                Err(error) => {
                    *failure.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = Some(error);
                    None
                }
            })
        });
        let requests = futures_util::stream::once(std::future::ready(header(name, size_bytes))).chain(data);
        let answer = self.rpc.clone().upload_buffer(requests).await;
        let failure = failed.lock().unwrap_or_else(std::sync::PoisonError::into_inner).take();
        match (answer, failure) {
            (answer, None) => Ok(answer?.into_inner()),
            (Ok(kept), Some(error)) => {
                // Best effort, as for a temporary buffer.
                let _ = self.delete_buffer(&kept.into_inner().id).await;
                Err(error)
            }
            (Err(_), Some(error)) => Err(error),
        }
    }

    /// Uploads `data` as a temporary buffer, calls `call` with a reference to it, and deletes the buffer again
    /// whatever the call's outcome, also if this future is dropped first ([`TemporaryBuffers`]).
    pub(crate) async fn with_temporary_buffer<T, Call: Future<Output = Result<T>>>(
        &self,
        data: Bytes,
        call: impl FnOnce(proto::BufferRef) -> Call,
    ) -> Result<T> {
        let mut temporary = TemporaryBuffers::new(self);
        let id = self.upload_buffer(&temporary.name_next(), data).await?.id;
        let result = call(buffer_ref(&id)).await;
        let _ = temporary.delete().await;
        result
    }

    /// Waits for the deletes of temporary buffers that calls dropped midway (by a timeout, a `select!`, a Ctrl-C)
    /// left running on their own tasks. A program about to end calls it (within a timeout of its own: a server that
    /// does not answer holds it): ending the runtime would cancel them, leaving the buffers on the server.
    pub async fn finish_clean_ups(&self) {
        let running = std::mem::take(&mut *self.clean_ups.0.lock().expect("never held across a panic"));
        for delete in running {
            let _ = delete.await;
        }
    }
}

/// The deletes that dropped [`TemporaryBuffers`] left running, shared by a client and its clones
/// ([`Client::finish_clean_ups`]).
#[derive(Debug, Clone, Default)]
pub(crate) struct CleanUps(Arc<Mutex<Vec<tokio::task::JoinHandle<()>>>>);

/// Server buffers made for one call's own use, deleted when it is over: by [`TemporaryBuffers::delete`], or, where
/// the call's future is dropped midway (a timeout, a `select!`, a Ctrl-C), by a task of their own
/// ([`Client::finish_clean_ups`] waits for those). Each is named (`tmp-PID-NANOS-N`: this process's id, the time,
/// and a count of its names) and held before its upload starts, so that one whose upload was interrupted just as
/// the server kept it, before its id came back, is deleted too. A buffer left behind only counts against the
/// tenant's limits.
#[derive(Debug)]
pub struct TemporaryBuffers {
    /// The client that makes and deletes them.
    client: Client,
    /// Their names.
    names: Vec<String>,
}

impl TemporaryBuffers {
    /// None yet, made and deleted through `client`.
    pub fn new(client: &Client) -> TemporaryBuffers {
        TemporaryBuffers { client: client.clone(), names: Vec::new() }
    }

    /// A name for one more buffer, held: deleted with the others whether or not a buffer of it is made.
    pub fn name_next(&mut self) -> String {
        let name = temporary_buffer_name();
        self.names.push(name.clone());
        name
    }

    /// The names held so far.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Deletes them now, by a task of their own, and returns the first failure (a name of which no buffer was made
    /// is no failure). They stay held until the task has ended: if this future is dropped first, the drop deletes
    /// them again by a task that [`Client::finish_clean_ups`] waits for.
    pub async fn delete(mut self) -> Result<()> {
        let (client, names) = (self.client.clone(), self.names.clone());
        let deleted = tokio::spawn(async move { delete_all(&client, names).await }).await;
        self.names.clear();
        deleted.unwrap_or_else(|stopped| {
            Err(tonic::Status::cancelled(format!("deleting temporary buffers: {stopped}")).into())
        })
    }
}

impl Drop for TemporaryBuffers {
    fn drop(&mut self) {
        let names = std::mem::take(&mut self.names);
        if let (false, Ok(runtime)) = (names.is_empty(), tokio::runtime::Handle::try_current()) {
            let client = self.client.clone();
            let delete = runtime.spawn(async move {
                let _ = delete_all(&client, names).await;
            });
            let mut running = self.client.clean_ups.0.lock().expect("never held across a panic");
            running.retain(|delete| !delete.is_finished());
            running.push(delete);
        }
    }
}

/// A name no other buffer has, for a temporary one ([`TemporaryBuffers`]).
fn temporary_buffer_name() -> String {
    static NAMED: AtomicU64 = AtomicU64::new(0);
    let since_epoch = SystemTime::now().duration_since(UNIX_EPOCH).unwrap_or_default().as_nanos();
    let count = NAMED.fetch_add(1, Ordering::Relaxed);
    format!("tmp-{}-{since_epoch}-{count}", std::process::id())
}

/// Deletes the buffers called `names` through `client`, each tried whatever came of the others; the first failure
/// other than NOT_FOUND (no buffer of that name was made, or it was deleted already).
async fn delete_all(client: &Client, names: Vec<String>) -> Result<()> {
    let mut first_failure = Ok(());
    for name in names {
        let named = proto::BufferRef { r#ref: Some(proto::buffer_ref::Ref::Name(name)) };
        let deleted = client.rpc.clone().delete_buffer(proto::DeleteBufferRequest { buffer: Some(named) }).await;
        if let Err(status) = deleted
            && status.code() != tonic::Code::NotFound
        {
            first_failure = first_failure.and(Err(status.into()));
        }
    }
    first_failure
}

/// The messages of one upload: the header, then `data` in slices of at most `chunk_bytes`.
fn upload_requests(name: &str, data: Bytes, chunk_bytes: usize) -> Vec<proto::UploadBufferRequest> {
    let chunk_bytes = chunk_bytes.max(1);
    let chunks =
        (0..data.len()).step_by(chunk_bytes).map(|start| data.slice(start..(start + chunk_bytes).min(data.len())));
    std::iter::once(header(name, data.len() as u64)).chain(chunks.map(|chunk| request(Part::Data(chunk)))).collect()
}

/// The first message of an upload of `size_bytes` bytes named `name`.
fn header(name: &str, size_bytes: u64) -> proto::UploadBufferRequest {
    request(Part::Header(proto::UploadBufferHeader { name: name.to_owned(), size_bytes }))
}

/// The message of one part of an upload.
fn request(part: Part) -> proto::UploadBufferRequest {
    proto::UploadBufferRequest { part: Some(part) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_comes_first_then_slices_that_cover_the_data_once() {
        let data = Bytes::from((0..10u8).collect::<Vec<_>>());
        let requests = upload_requests("verts", data.clone(), 4);
        let parts: Vec<_> = requests.into_iter().map(|r| r.part.unwrap()).collect();
        assert_eq!(parts[0], Part::Header(proto::UploadBufferHeader { name: "verts".into(), size_bytes: 10 }));
        let chunks: Vec<Bytes> = parts[1..]
            .iter()
            .map(|p| match p {
                Part::Data(d) => d.clone(),
                Part::Header(_) => panic!("a second header"),
            })
            .collect();
        assert_eq!(chunks.iter().map(Bytes::len).collect::<Vec<_>>(), [4, 4, 2]);
        assert_eq!(chunks.concat(), data);
        assert_eq!(chunks[0].as_ptr(), data.as_ptr(), "slices share the caller's bytes");
        assert_eq!(upload_requests("", Bytes::new(), 4).len(), 1, "an empty buffer is a header alone");
    }
}
