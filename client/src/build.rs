//! `BuildAccel` from a [`Mesh`]: small meshes go inline, large ones are uploaded as temporary buffers first.

use bytes::Bytes;
use rayd_engine::accel::BuildFlags;
use rayd_engine::geometry::{IndexFormat, MotionOptions, VertexFormat};
use rayd_engine::mesh::Mesh;
use rayd_proto as proto;
use rayd_proto::data_source::Source;

use crate::client::Client;
use crate::convert::{
    accel_ref, buffer_ref, build_options_to_proto, index_format_to_proto, motion_to_proto, vertex_format_to_proto,
};
use crate::error::Result;
use crate::upload::TemporaryBuffers;

impl Client {
    /// Builds an accel from a request made by hand (sent for the scene of its name: buffers it uses must have been
    /// uploaded through [`Client::for_scene`] where a router places scenes).
    pub async fn build(&self, request: proto::BuildAccelRequest) -> Result<proto::AccelInfo> {
        let mut rpc = self.rpc_for(&request.name);
        Ok(rpc.build_accel(request).await?.into_inner())
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
        self.build_moving_mesh(name, std::slice::from_ref(mesh), device, flags, &MotionOptions::STATIC).await
    }

    /// Builds a motion geometry accel called `name` on `device` from one mesh at each of `motion`'s keys (the
    /// same topology: `keys[0]`'s indices are used), vertex positions interpolated between keys. Large meshes go
    /// through temporary buffers as in [`Client::build_mesh`].
    pub async fn build_moving_mesh(
        &self,
        name: &str,
        keys: &[Mesh],
        device: &str,
        flags: BuildFlags,
        motion: &MotionOptions,
    ) -> Result<proto::AccelInfo> {
        let node = self.for_scene(name);
        node.with_meshes(keys, |vertices, indices| {
            let mut request = mesh_request(name, device, flags, vertices, indices);
            request.options.get_or_insert_default().motion = motion_to_proto(motion);
            node.build(request)
        })
        .await
    }

    /// Updates (refits) an accel in place from a request made by hand (sent for the accel's scene when it is named).
    pub async fn update(&self, request: proto::UpdateAccelRequest) -> Result<proto::AccelInfo> {
        let mut rpc = match request.accel.as_ref().and_then(|accel| accel.r#ref.as_ref()) {
            Some(proto::accel_ref::Ref::Name(name)) => self.rpc_for(name),
            _ => self.rpc.clone(),
        };
        Ok(rpc.update_accel(request).await?.into_inner())
    }

    /// Updates (refits) the accel called `name`, built with `allow_update` from a mesh of the same topology, with
    /// `mesh`'s vertex positions. Large meshes go through temporary buffers as in [`Client::build_mesh`].
    pub async fn update_mesh(&self, name: &str, mesh: &Mesh) -> Result<proto::AccelInfo> {
        let node = self.for_scene(name);
        node.with_meshes(std::slice::from_ref(mesh), |vertices, indices| {
            let inputs = mesh_request(name, "", BuildFlags::empty(), vertices, indices).inputs;
            node.update(proto::UpdateAccelRequest { accel: Some(accel_ref(name)), inputs })
        })
        .await
    }

    /// Calls `call` with the vertices of each of `meshes` (motion keys of one topology) and the first one's
    /// indices: inline below [`ClientOptions::inline_mesh_bytes`](crate::ClientOptions::inline_mesh_bytes) in all,
    /// else as uploaded buffers that are deleted again once the call is over, whatever its outcome.
    async fn with_meshes<Call: Future<Output = Result<proto::AccelInfo>>>(
        &self,
        meshes: &[Mesh],
        call: impl Fn(Vec<Source>, Source) -> Call,
    ) -> Result<proto::AccelInfo> {
        let (vertices, indices): (Vec<Bytes>, Vec<Bytes>) = meshes.iter().map(packed).unzip();
        let indices = indices.into_iter().next().unwrap_or_default();
        let total = vertices.iter().map(Bytes::len).sum::<usize>() + indices.len();
        if total < self.options.inline_mesh_bytes {
            return call(vertices.into_iter().map(Source::Inline).collect(), Source::Inline(indices)).await;
        }
        let mut temporary = TemporaryBuffers::new(self);
        let result = async {
            let mut uploaded = Vec::new();
            for data in vertices.into_iter().chain([indices]) {
                uploaded.push(self.upload_buffer(&temporary.name_next(), data).await?.id);
            }
            let by_id = |id: &String| Source::Buffer(buffer_ref(id));
            let (indices, vertices) = uploaded.split_last().expect("the indices were uploaded");
            call(vertices.iter().map(by_id).collect(), by_id(indices)).await
        }
        .await;
        let _ = temporary.delete().await;
        result
    }
}

/// A mesh's tightly packed float3 vertices and u32×3 indices.
pub(crate) fn packed(mesh: &Mesh) -> (Bytes, Bytes) {
    let packed = mesh.pack();
    (Bytes::from(packed.vertices), Bytes::from(packed.indices))
}

/// The request that builds accel `name` on `device` from one mesh's packed vertices (one buffer a motion key) and
/// indices.
pub(crate) fn mesh_request(
    name: &str,
    device: &str,
    flags: BuildFlags,
    vertices: Vec<Source>,
    indices: Source,
) -> proto::BuildAccelRequest {
    proto::BuildAccelRequest {
        name: name.to_owned(),
        device: device.to_owned(),
        inputs: vec![triangles(vertices, indices)],
        options: Some(build_options_to_proto(flags)),
    }
}

/// A build input of tightly packed float3 vertices (one buffer a motion key) and u32×3 indices.
fn triangles(vertices: Vec<Source>, indices: Source) -> proto::BuildInput {
    let source = |source| proto::DataSource { source: Some(source) };
    let mut vertices = vertices.into_iter().map(source);
    proto::BuildInput {
        input: Some(proto::build_input::Input::Triangles(proto::TriangleInput {
            vertices: vertices.next(),
            motion_vertices: vertices.collect(),
            vertex_format: vertex_format_to_proto(VertexFormat::Float3).into(),
            indices: Some(source(indices)),
            index_format: index_format_to_proto(IndexFormat::U32x3).into(),
            ..Default::default()
        })),
    }
}
