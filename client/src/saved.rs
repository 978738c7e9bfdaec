//! `SaveAccel` and `LoadAccel`: an accel and everything below it to a versioned, checksummed blob and back, through
//! a temporary server buffer (`DownloadBuffer` and `UploadBuffer` move the bytes).

use bytes::Bytes;
use rayd_proto as proto;
use rayd_proto::data_source::Source;
use tokio_stream::StreamExt;

use crate::client::Client;
use crate::convert::{accel_ref, buffer_ref};
use crate::error::{Error, Result};
use crate::memory::append;
use crate::upload::TemporaryBuffers;

/// A whole buffer's bytes put together from the chunks a download streams, checked as they come: each must start
/// where the bytes before it end.
#[derive(Debug, Default)]
pub(crate) struct Download {
    /// The bytes so far.
    data: Vec<u8>,
}

impl Download {
    /// Appends `chunk`; [`Error::Protocol`] unless it starts where the bytes so far end, [`Error::Memory`] where this
    /// process cannot hold them.
    pub fn push(&mut self, chunk: &proto::BufferChunk) -> Result<()> {
        let so_far = self.data.len();
        if chunk.offset != so_far as u64 {
            return Err(Error::Protocol(format!(
                "a download chunk starts at byte {} where byte {so_far} was due",
                chunk.offset
            )));
        }
        append(&mut self.data, &chunk.data, || format!("the download's first {so_far} bytes and its next chunk"))
    }

    /// The bytes of a buffer of `size_bytes`; [`Error::Protocol`] unless the chunks held that many.
    pub fn whole(self, size_bytes: u64) -> Result<Bytes> {
        let got = self.data.len();
        if got as u64 != size_bytes {
            return Err(Error::Protocol(format!("a download of a {size_bytes}-byte buffer came with {got} bytes")));
        }
        Ok(self.data.into())
    }
}

impl Client {
    /// The bytes of server buffer `id`, as `DownloadBuffer` streams them; [`Error::Protocol`] where the chunks do
    /// not follow one another.
    pub async fn download_buffer(&self, id: &str) -> Result<Bytes> {
        Ok(self.download_chunks(id).await?.data.into())
    }

    /// The chunks of server buffer `id`, put together.
    async fn download_chunks(&self, id: &str) -> Result<Download> {
        let request = proto::DownloadBufferRequest { buffer: Some(buffer_ref(id)), ..Default::default() };
        let mut chunks = self.rpc.clone().download_buffer(request).await?.into_inner();
        let mut download = Download::default();
        while let Some(chunk) = chunks.next().await {
            download.push(&chunk?)?;
        }
        Ok(download)
    }

    /// Serializes the accel called `name` and everything below it, and downloads the blob; the server buffer that
    /// held it is deleted again, whatever the outcome.
    pub async fn save_accel(&self, name: &str) -> Result<Bytes> {
        let node = self.for_scene(name);
        let mut temporary = TemporaryBuffers::new(&node);
        let buffer_name = temporary.name_next();
        let request = proto::SaveAccelRequest { accel: Some(accel_ref(name)), buffer_name };
        let buffer = node.rpc.clone().save_accel(request).await?.into_inner();
        let id = buffer.id;
        let blob = node.download_chunks(&id).await.and_then(|download| download.whole(buffer.size_bytes));
        let _ = temporary.delete().await;
        blob
    }

    /// Recreates the accels of a blob [`Client::save_accel`] made, on `device`: the root called `name`, the accels
    /// below it `name.1`, `name.2`, … (children first). Blobs of at least
    /// [`ClientOptions::inline_mesh_bytes`](crate::ClientOptions::inline_mesh_bytes) go through a temporary buffer.
    pub async fn load_accel(&self, name: &str, device: &str, blob: Bytes) -> Result<Vec<proto::AccelInfo>> {
        let load = |source| proto::LoadAccelRequest {
            name: name.to_owned(),
            device: device.to_owned(),
            blob: Some(proto::DataSource { source: Some(source) }),
        };
        let node = self.for_scene(name);
        if blob.len() < self.options.inline_mesh_bytes {
            return Ok(node.rpc.clone().load_accel(load(Source::Inline(blob))).await?.into_inner().accels);
        }
        node.with_temporary_buffer(blob, |buffer| {
            let (request, mut rpc) = (load(Source::Buffer(buffer)), node.rpc.clone());
            async move { Ok(rpc.load_accel(request).await?.into_inner().accels) }
        })
        .await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A chunk of `data` at `offset`.
    fn chunk(offset: u64, data: &'static [u8]) -> proto::BufferChunk {
        proto::BufferChunk { offset, data: Bytes::from_static(data) }
    }

    #[test]
    fn chunks_are_put_together_only_in_order_and_to_the_buffers_size() {
        let mut download = Download::default();
        download.push(&chunk(0, b"abc")).unwrap();
        download.push(&chunk(3, b"de")).unwrap();
        let error = download.push(&chunk(2, b"x")).unwrap_err();
        assert!(matches!(&error, Error::Protocol(why) if why.contains("at byte 2 where byte 5")), "{error}");
        let error = download.push(&chunk(9, b"x")).unwrap_err();
        assert!(matches!(error, Error::Protocol(_)), "a gap: {error}");
        assert!(matches!(Download { data: b"abcde".to_vec() }.whole(6), Err(Error::Protocol(_))), "a short buffer");
        assert_eq!(download.whole(5).unwrap(), b"abcde".as_ref());
    }
}
