//! `UploadBuffer`: a header, then the data in slices of one shared `Bytes` (no copies on the client).

use bytes::Bytes;
use rayd_proto as proto;
use rayd_proto::upload_buffer_request::Part;

use crate::client::Client;
use crate::convert::buffer_ref;
use crate::error::Result;

impl Client {
    /// Uploads `data` as a new server buffer, named `name` unless it is empty, in messages of
    /// [`ClientOptions::upload_chunk_bytes`](crate::ClientOptions::upload_chunk_bytes).
    pub async fn upload_buffer(&self, name: &str, data: Bytes) -> Result<proto::BufferInfo> {
        let requests = upload_requests(name, data, self.options.upload_chunk_bytes);
        Ok(self.rpc.clone().upload_buffer(tokio_stream::iter(requests)).await?.into_inner())
    }

    /// Uploads `data` as a temporary buffer, calls `call` with a reference to it, and deletes the buffer again
    /// whatever the call's outcome.
    pub(crate) async fn with_temporary_buffer<T, Call: Future<Output = Result<T>>>(
        &self,
        data: Bytes,
        call: impl FnOnce(proto::BufferRef) -> Call,
    ) -> Result<T> {
        let buffer = self.upload_buffer("", data).await?;
        let result = call(buffer_ref(&buffer.id)).await;
        // Best effort: a buffer left behind only counts against the tenant's limits.
        let _ = self.delete_buffer(&buffer.id).await;
        result
    }
}

/// The messages of one upload: the header, then `data` in slices of at most `chunk_bytes`.
fn upload_requests(name: &str, data: Bytes, chunk_bytes: usize) -> Vec<proto::UploadBufferRequest> {
    let header = proto::UploadBufferHeader { name: name.to_owned(), size_bytes: data.len() as u64 };
    let chunk_bytes = chunk_bytes.max(1);
    let chunks =
        (0..data.len()).step_by(chunk_bytes).map(|start| data.slice(start..(start + chunk_bytes).min(data.len())));
    std::iter::once(Part::Header(header))
        .chain(chunks.map(Part::Data))
        .map(|part| proto::UploadBufferRequest { part: Some(part) })
        .collect()
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
