//! Buffer upload (client streaming) and download (server streaming).

use std::pin::Pin;
use std::sync::Arc;

use bytes::{Bytes, BytesMut};
use rayd_proto as pb;
use tokio_stream::Stream;
use tonic::Streaming;

use crate::error::{ServiceError, ServiceResult};
use crate::service::outbox::outbox;
use crate::tenant::{BufferEntry, BufferReservation, Tenant};

/// Bytes per downloaded message when the request gives none.
const DEFAULT_CHUNK_BYTES: u64 = 1 << 20;

/// Most bytes reserved for an upload before its data arrives.
const UPLOAD_RESERVE_BYTES: u64 = 64 << 20;

/// The stream of a download.
pub type ChunkStream = Pin<Box<dyn Stream<Item = Result<pb::BufferChunk, tonic::Status>> + Send>>;

/// The contract's description of a buffer.
pub fn info(entry: &BufferEntry) -> pb::BufferInfo {
    pb::BufferInfo { id: entry.id.clone(), name: entry.name.clone(), size_bytes: entry.size_bytes }
}

/// The buffer a reference names.
pub fn resolve(tenant: &Tenant, reference: Option<&pb::BufferRef>, field: &str) -> ServiceResult<(BufferEntry, Bytes)> {
    match reference.and_then(|r| r.r#ref.as_ref()) {
        Some(pb::buffer_ref::Ref::Id(id)) => tenant.buffer(Some(id), None).map_err(|e| e.in_field(field)),
        Some(pb::buffer_ref::Ref::Name(name)) => tenant.buffer(None, Some(name)).map_err(|e| e.in_field(field)),
        Some(pb::buffer_ref::Ref::Operation(_)) => Err(super::operation_outside_stream(field)),
        None => Err(ServiceError::invalid(field, "a buffer id or name is required")),
    }
}

/// A buffer being received: its header was checked against the limits, its data grows as it arrives.
#[derive(Debug)]
pub struct Upload {
    /// The declared name and size.
    header: pb::UploadBufferHeader,
    /// What arrived so far.
    data: BytesMut,
    /// The declared size and the buffer's place, reserved against the tenant's `max_total_buffer_bytes` and
    /// `max_buffers` until the upload ends.
    reserved: BufferReservation,
}

impl Upload {
    /// Starts an upload after checking its name and declared size; a header alone never reserves the whole
    /// declared size.
    pub fn begin(tenant: &Tenant, header: pb::UploadBufferHeader) -> ServiceResult<Upload> {
        let reserved = tenant.reserve_new_buffers("header.name", &[(&header.name, header.size_bytes)])?;
        let reserved = reserved.into_iter().next().expect("a reservation a buffer");
        let data = BytesMut::with_capacity(header.size_bytes.min(UPLOAD_RESERVE_BYTES) as usize);
        Ok(Upload { header, data, reserved })
    }

    /// Appends `chunk`; more than the declared size is INVALID_ARGUMENT.
    pub fn push(&mut self, chunk: &[u8]) -> ServiceResult<()> {
        if self.data.len() as u64 + chunk.len() as u64 > self.header.size_bytes {
            return Err(ServiceError::invalid(
                "data",
                format!("more than the declared {} bytes", self.header.size_bytes),
            ));
        }
        self.data.extend_from_slice(chunk);
        Ok(())
    }

    /// Bytes received so far.
    pub fn received(&self) -> u64 {
        self.data.len() as u64
    }

    /// Whether every declared byte has arrived.
    pub fn is_complete(&self) -> bool {
        self.received() == self.header.size_bytes
    }

    /// Keeps the data as a buffer, if all of it came.
    pub fn finish(self, tenant: &Tenant) -> ServiceResult<BufferEntry> {
        if !self.is_complete() {
            return Err(ServiceError::invalid(
                "data",
                format!("{} bytes received, {} declared", self.received(), self.header.size_bytes),
            ));
        }
        let Upload { header, data, reserved } = self;
        tenant.create_buffer("header.name", &header.name, data.freeze(), reserved)
    }
}

/// Receives a header and the data chunks, checking the declared size against the limits before anything else.
pub async fn upload(
    tenant: Arc<Tenant>,
    mut stream: Streaming<pb::UploadBufferRequest>,
) -> ServiceResult<pb::BufferInfo> {
    let header = match stream.message().await {
        Ok(Some(pb::UploadBufferRequest { part: Some(pb::upload_buffer_request::Part::Header(h)) })) => h,
        Ok(_) => return Err(ServiceError::invalid("header", "the first message of an upload must be its header")),
        Err(status) => return Err(ServiceError::Transport(status)),
    };
    let mut upload = Upload::begin(&tenant, header)?;
    while let Some(message) = stream.message().await.map_err(ServiceError::Transport)? {
        let Some(pb::upload_buffer_request::Part::Data(chunk)) = message.part else {
            return Err(ServiceError::invalid("header", "only the first message may be a header"));
        };
        upload.push(&chunk)?;
    }
    keep(tenant, upload).await
}

/// Keeps an upload whose data has come, off the async runtime (with a data directory the buffer is written to disk).
/// A caller that has gone by then (a client interrupted after its last byte, a stream cancelled) would never learn
/// the buffer's id, so nothing is kept for it.
pub async fn keep(tenant: Arc<Tenant>, upload: Upload) -> ServiceResult<pb::BufferInfo> {
    let kept = super::blocking_for_caller(move |caller| {
        caller.check(|| "the upload was not kept".into())?;
        upload.finish(&tenant)
    });
    Ok(info(&kept.await?))
}

/// The buffer a download reads and its range in chunks (zero-copy slices).
pub fn download_chunks(
    tenant: &Tenant,
    request: &pb::DownloadBufferRequest,
) -> ServiceResult<(BufferEntry, impl Iterator<Item = pb::BufferChunk> + Send + 'static)> {
    let (entry, bytes) = resolve(tenant, request.buffer.as_ref(), "buffer")?;
    let size = bytes.len() as u64;
    if request.offset > size {
        return Err(ServiceError::invalid(
            "offset",
            format!("{} is past the end of the {size}-byte buffer", request.offset),
        ));
    }
    let end = if request.length == 0 { size } else { request.offset.saturating_add(request.length) };
    if end > size {
        return Err(ServiceError::invalid("length", format!("offset + length = {end} is past the end ({size} bytes)")));
    }
    let limit = tenant.limits().max_message_bytes.saturating_sub(1024).max(1);
    let chunk = if request.chunk_bytes == 0 { DEFAULT_CHUNK_BYTES } else { request.chunk_bytes as u64 }.min(limit);
    let chunks = (request.offset..end).step_by(chunk as usize).map(move |offset| {
        let stop = (offset + chunk).min(end);
        pb::BufferChunk { offset, data: bytes.slice(offset as usize..stop as usize) }
    });
    Ok((entry, chunks))
}

/// Streams a range of a buffer, holding one of the tenant's `max_streams` places while it lasts (it holds the
/// buffer's bytes, even past a delete), through an outbox of `stream_window` chunks: a client that reads none for
/// `stream_stall_seconds` gets the download failed, as a stream's.
pub fn download(tenant: &Tenant, request: &pb::DownloadBufferRequest) -> ServiceResult<ChunkStream> {
    let (_, chunks) = download_chunks(tenant, request)?;
    let place = tenant.streams().place(tenant.limits().max_streams)?;
    let (sender, chunks_sent) =
        outbox(tenant.limits().window() as usize, tenant.limits().stream_stall(), "DownloadBuffer", tenant.name());
    tokio::spawn(async move {
        for chunk in chunks {
            if sender.send(Ok(chunk)).await.is_err() {
                break;
            }
        }
    });
    Ok(Box::pin(place.held_by(chunks_sent)))
}

/// Deletes a buffer (off the async runtime: it waits for the lock that orders the tenant's changes, and removes a
/// file).
pub async fn delete(tenant: Arc<Tenant>, request: pb::DeleteBufferRequest) -> ServiceResult<()> {
    super::blocking(move || tenant.delete_buffer(&resolve(&tenant, request.buffer.as_ref(), "buffer")?.0)).await
}
