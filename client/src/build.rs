//! `BuildAccel` from a [`Mesh`]: small meshes go inline, large ones are uploaded as temporary buffers first.

use bytes::Bytes;
use rayd_engine::accel::BuildFlags;
use rayd_engine::geometry::{IndexFormat, VertexFormat};
use rayd_engine::mesh::Mesh;
use rayd_proto as proto;
use rayd_proto::data_source::Source;

use crate::client::Client;
use crate::convert::{accel_ref, buffer_ref, build_options_to_proto, index_format_to_proto, vertex_format_to_proto};
use crate::error::Result;

impl Client {
    /// Builds an accel from a request made by hand.
    pub async fn build(&self, request: proto::BuildAccelRequest) -> Result<proto::AccelInfo> {
        Ok(self.rpc.clone().build_accel(request).await?.into_inner())
    }

    /// Builds an accel called `name` on `device` (empty means `cpu:0`) from one mesh (geometry 0). Meshes of at
    /// least [`ClientOptions::inline_mesh_bytes`](crate::ClientOptions::inline_mesh_bytes) are uploaded as two
    /// buffers that are deleted again once the build is over, whatever its outcome.
    pub async fn build_mesh(
        &self,
        name: &str,
        mesh: &Mesh,
        device: &str,
        flags: BuildFlags,
    ) -> Result<proto::AccelInfo> {
        self.with_mesh(mesh, |vertices, indices| self.build(mesh_request(name, device, flags, vertices, indices))).await
    }

    /// Updates (refits) an accel in place from a request made by hand.
    pub async fn update(&self, request: proto::UpdateAccelRequest) -> Result<proto::AccelInfo> {
        Ok(self.rpc.clone().update_accel(request).await?.into_inner())
    }

    /// Updates (refits) the accel called `name`, built with `allow_update` from a mesh of the same topology, with
    /// `mesh`'s vertex positions. Large meshes go through temporary buffers as in [`Client::build_mesh`].
    pub async fn update_mesh(&self, name: &str, mesh: &Mesh) -> Result<proto::AccelInfo> {
        self.with_mesh(mesh, |vertices, indices| {
            let inputs = mesh_request(name, "", BuildFlags::empty(), vertices, indices).inputs;
            self.update(proto::UpdateAccelRequest { accel: Some(accel_ref(name)), inputs })
        })
        .await
    }

    /// Calls `call` with a mesh's vertices and indices: inline below
    /// [`ClientOptions::inline_mesh_bytes`](crate::ClientOptions::inline_mesh_bytes), else as two uploaded buffers
    /// that are deleted again once the call is over, whatever its outcome.
    async fn with_mesh<Call: Future<Output = Result<proto::AccelInfo>>>(
        &self,
        mesh: &Mesh,
        call: impl Fn(Source, Source) -> Call,
    ) -> Result<proto::AccelInfo> {
        let (vertices, indices) = packed(mesh);
        if vertices.len() + indices.len() < self.options.inline_mesh_bytes {
            return call(Source::Inline(vertices), Source::Inline(indices)).await;
        }
        let mut uploaded = Vec::new();
        let result = async {
            for data in [vertices, indices] {
                uploaded.push(self.upload_buffer("", data).await?.id);
            }
            let by_id = |id: &str| Source::Buffer(buffer_ref(id));
            call(by_id(&uploaded[0]), by_id(&uploaded[1])).await
        }
        .await;
        for id in &uploaded {
            // Best effort: a buffer left behind only counts against the tenant's limits.
            let _ = self.delete_buffer(id).await;
        }
        result
    }
}

/// A mesh's tightly packed float3 vertices and u32×3 indices.
pub(crate) fn packed(mesh: &Mesh) -> (Bytes, Bytes) {
    let packed = mesh.pack();
    (Bytes::from(packed.vertices), Bytes::from(packed.indices))
}

/// The request that builds accel `name` on `device` from one mesh's packed vertices and indices.
pub(crate) fn mesh_request(
    name: &str,
    device: &str,
    flags: BuildFlags,
    vertices: Source,
    indices: Source,
) -> proto::BuildAccelRequest {
    proto::BuildAccelRequest {
        name: name.to_owned(),
        device: device.to_owned(),
        inputs: vec![triangles(vertices, indices)],
        options: Some(build_options_to_proto(flags)),
    }
}

/// A build input of tightly packed float3 vertices and u32×3 indices.
fn triangles(vertices: Source, indices: Source) -> proto::BuildInput {
    let source = |source| Some(proto::DataSource { source: Some(source) });
    proto::BuildInput {
        input: Some(proto::build_input::Input::Triangles(proto::TriangleInput {
            vertices: source(vertices),
            vertex_format: vertex_format_to_proto(VertexFormat::Float3).into(),
            indices: source(indices),
            index_format: index_format_to_proto(IndexFormat::U32x3).into(),
            ..Default::default()
        })),
    }
}
