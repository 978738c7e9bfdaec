//! Build inputs of a request, resolved to bytes (inline or from buffers) that outlive the blocking build.

use bytes::Bytes;
use rayd_engine::geometry::{
    BuildInput, GeometryFlags, IndexBuffer, IndexFormat, TriangleInput, VertexBuffer, VertexFormat,
};
use rayd_proto as pb;

use crate::error::{ServiceError, ServiceResult};
use crate::tenant::Tenant;

/// A triangle input whose bytes are owned (shared `Bytes`, never copied).
#[derive(Debug)]
pub struct OwnedTriangles {
    /// Vertex bytes.
    vertices: Bytes,
    /// How positions are stored.
    vertex_format: VertexFormat,
    /// Bytes between vertices, if not tightly packed.
    stride: Option<u32>,
    /// Index bytes and their format.
    indices: Option<(Bytes, IndexFormat)>,
    /// Mask bytes.
    masks: Option<Bytes>,
    /// Geometry flags.
    flags: GeometryFlags,
    /// Primitive-index offset.
    primitive_index_offset: u32,
}

impl OwnedTriangles {
    /// The engine's view of this input.
    pub fn as_input(&self) -> BuildInput<'_> {
        BuildInput::Triangles(TriangleInput {
            vertices: VertexBuffer { data: &self.vertices, format: self.vertex_format, stride: self.stride },
            indices: self.indices.as_ref().map(|(data, format)| IndexBuffer { data, format: *format }),
            masks: self.masks.as_deref(),
            flags: self.flags,
            primitive_index_offset: self.primitive_index_offset,
        })
    }
}

/// Resolves every input of a request.
pub fn resolve(tenant: &Tenant, inputs: &[pb::BuildInput]) -> ServiceResult<Vec<OwnedTriangles>> {
    inputs.iter().enumerate().map(|(i, input)| resolve_one(tenant, i, input)).collect()
}

/// Resolves input `index`.
fn resolve_one(tenant: &Tenant, index: usize, input: &pb::BuildInput) -> ServiceResult<OwnedTriangles> {
    let field = |name: &str| format!("inputs[{index}].triangles.{name}");
    let Some(pb::build_input::Input::Triangles(t)) = &input.input else {
        return Err(ServiceError::invalid(format!("inputs[{index}]"), "a build input must be set"));
    };
    let vertex_format = match pb::VertexFormat::try_from(t.vertex_format) {
        Ok(pb::VertexFormat::Float3) => VertexFormat::Float3,
        Ok(pb::VertexFormat::Float4) => VertexFormat::Float4,
        _ => return Err(ServiceError::invalid(field("vertex_format"), "must be VERTEX_FORMAT_FLOAT3 or _FLOAT4")),
    };
    let vertices = data(tenant, t.vertices.as_ref(), &field("vertices"))?
        .ok_or_else(|| ServiceError::invalid(field("vertices"), "vertices are required"))?;
    let indices = match data(tenant, t.indices.as_ref(), &field("indices"))? {
        None => None,
        Some(bytes) => {
            let format = match pb::IndexFormat::try_from(t.index_format) {
                Ok(pb::IndexFormat::Uint32x3) => IndexFormat::U32x3,
                Ok(pb::IndexFormat::Uint16x3) => IndexFormat::U16x3,
                _ => return Err(ServiceError::invalid(field("index_format"), "must be set when indices are given")),
            };
            Some((bytes, format))
        }
    };
    let mut flags = GeometryFlags::empty();
    flags.set(GeometryFlags::DISABLE_FACE_CULLING, t.disable_face_culling);
    Ok(OwnedTriangles {
        vertices,
        vertex_format,
        stride: (t.vertex_stride_bytes != 0).then_some(t.vertex_stride_bytes),
        indices,
        masks: data(tenant, t.masks.as_ref(), &field("masks"))?,
        flags,
        primitive_index_offset: t.primitive_index_offset,
    })
}

/// The bytes of a data source: inline, or a buffer's (shared, not copied).
fn data(tenant: &Tenant, source: Option<&pb::DataSource>, field: &str) -> ServiceResult<Option<Bytes>> {
    let Some(source) = source.and_then(|s| s.source.as_ref()) else { return Ok(None) };
    match source {
        pb::data_source::Source::Inline(bytes) => Ok(Some(bytes.clone())),
        pb::data_source::Source::Buffer(reference) => {
            Ok(Some(super::buffers::resolve(tenant, Some(reference), field)?.1))
        }
    }
}
