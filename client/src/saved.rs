//! `SaveAccel` and `LoadAccel`: an accel and everything below it to a versioned, checksummed blob and back, through
//! a temporary server buffer (`DownloadBuffer` and `UploadBuffer` move the bytes).

use bytes::{Bytes, BytesMut};
use rayd_proto as proto;
use rayd_proto::data_source::Source;
use tokio_stream::StreamExt;

use crate::client::Client;
use crate::convert::{accel_ref, buffer_ref};
use crate::error::Result;

impl Client {
    /// The bytes of server buffer `id`, as `DownloadBuffer` streams them.
    pub async fn download_buffer(&self, id: &str) -> Result<Bytes> {
        let request = proto::DownloadBufferRequest { buffer: Some(buffer_ref(id)), ..Default::default() };
        let mut chunks = self.rpc.clone().download_buffer(request).await?.into_inner();
        let mut data = BytesMut::new();
        while let Some(chunk) = chunks.next().await {
            data.extend_from_slice(&chunk?.data);
        }
        Ok(data.freeze())
    }

    /// Serializes the accel called `name` and everything below it, and downloads the blob; the server buffer that
    /// held it is deleted again, whatever the outcome.
    pub async fn save_accel(&self, name: &str) -> Result<Bytes> {
        let request = proto::SaveAccelRequest { accel: Some(accel_ref(name)), buffer_name: String::new() };
        let node = self.for_scene(name);
        let buffer = node.rpc.clone().save_accel(request).await?.into_inner();
        let blob = node.download_buffer(&buffer.id).await;
        // Best effort: a buffer left behind only counts against the tenant's limits.
        let _ = node.delete_buffer(&buffer.id).await;
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
