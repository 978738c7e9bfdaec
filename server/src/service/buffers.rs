//! Buffer upload (client streaming) and download (server streaming).

use std::pin::Pin;
use std::sync::Arc;

use bytes::BytesMut;
use rayd_proto as pb;
use tokio_stream::Stream;
use tonic::Streaming;

use crate::error::{ServiceError, ServiceResult};
use crate::tenant::{BufferEntry, Tenant};

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
pub fn resolve(tenant: &Tenant, reference: &pb::BufferRef) -> ServiceResult<BufferEntry> {
    match &reference.r#ref {
        Some(pb::buffer_ref::Ref::Id(id)) => Ok(tenant.buffer(Some(id), None)?.0),
        Some(pb::buffer_ref::Ref::Name(name)) => Ok(tenant.buffer(None, Some(name))?.0),
        None => Err(ServiceError::invalid("buffer", "a buffer id or name is required")),
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
    tenant.check_new_buffer(&header.name, header.size_bytes)?;
    // Grows as data arrives: a header alone never reserves the whole declared size.
    let mut data = BytesMut::with_capacity(header.size_bytes.min(UPLOAD_RESERVE_BYTES) as usize);
    while let Some(message) = stream.message().await.map_err(ServiceError::Transport)? {
        let Some(pb::upload_buffer_request::Part::Data(chunk)) = message.part else {
            return Err(ServiceError::invalid("header", "only the first message may be a header"));
        };
        if data.len() as u64 + chunk.len() as u64 > header.size_bytes {
            return Err(ServiceError::invalid("data", format!("more than the declared {} bytes", header.size_bytes)));
        }
        data.extend_from_slice(&chunk);
    }
    if data.len() as u64 != header.size_bytes {
        return Err(ServiceError::invalid(
            "data",
            format!("{} bytes received, {} declared", data.len(), header.size_bytes),
        ));
    }
    Ok(info(&tenant.create_buffer(&header.name, data.freeze())?))
}

/// Streams a range of a buffer as zero-copy slices.
pub fn download(tenant: &Tenant, request: &pb::DownloadBufferRequest) -> ServiceResult<ChunkStream> {
    let reference = request.buffer.as_ref().ok_or_else(|| ServiceError::invalid("buffer", "required"))?;
    let entry = resolve(tenant, reference)?;
    let (_, bytes) = tenant.buffer(Some(&entry.id), None)?;
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
        Ok(pb::BufferChunk { offset, data: bytes.slice(offset as usize..stop as usize) })
    });
    Ok(Box::pin(tokio_stream::iter(chunks)))
}
