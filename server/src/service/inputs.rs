//! Build inputs of a request, resolved to what outlives the blocking build: triangle bytes (inline or from
//! buffers, shared), or instances and transforms over resolved child accels.

use std::sync::Arc;

use bytes::Bytes;
use rayd_engine::accel::{BuildOptions, MemoryUsage};
use rayd_engine::geometry::{
    BuildInput, GeometryFlags, INSTANCE_RECORD_BYTES, IndexBuffer, IndexFormat, Instance, MotionOptions,
    TransformFormat, TransformInput, TriangleInput, VertexBuffer, VertexFormat, instances_from_prime,
    instances_from_records,
};
use rayd_engine::{Accel, Context};
use rayd_proto as pb;

use super::accels;
use crate::convert;
use crate::error::{ServiceError, ServiceResult};
use crate::tenant::Tenant;

/// What a build is over, resolved.
#[derive(Debug)]
pub enum Resolved {
    /// Triangle inputs: a geometry accel.
    Triangles(Vec<OwnedTriangles>),
    /// Instances: an instance accel.
    Instances(Vec<Instance>),
    /// A transform (static or moving) over one child.
    Transform {
        /// Its matrix or keys.
        transform: TransformInput,
        /// The child.
        child: Arc<Accel>,
    },
}

impl Resolved {
    /// Upper bounds of the build's memory on `context`.
    pub fn memory_usage(&self, context: &Context, options: &BuildOptions) -> rayd_engine::Result<MemoryUsage> {
        match self {
            Resolved::Triangles(owned) => with_inputs(owned, |inputs| context.compute_memory_usage(inputs, options)),
            Resolved::Instances(instances) => context.compute_instance_memory_usage(instances, options),
            Resolved::Transform { transform, child } => {
                context.compute_transform_memory_usage(transform, child, options)
            }
        }
    }

    /// Builds it on `context`.
    pub fn build(
        &self,
        context: &Context,
        options: &BuildOptions,
        go_on: &dyn Fn() -> bool,
    ) -> rayd_engine::Result<Arc<Accel>> {
        match self {
            Resolved::Triangles(owned) => {
                with_inputs(owned, |inputs| context.build_accel_while(inputs, options, go_on))
            }
            Resolved::Instances(instances) => context.build_instance_accel(instances, options),
            Resolved::Transform { transform, child } => context.build_transform(transform, child),
        }
    }

    /// Updates `accel` with these inputs on `context`.
    pub fn update(&self, context: &Context, accel: &Accel) -> rayd_engine::Result<Arc<Accel>> {
        match self {
            Resolved::Triangles(owned) => with_inputs(owned, |inputs| context.update_accel(accel, inputs)),
            Resolved::Instances(instances) => context.update_instance_accel(accel, instances),
            Resolved::Transform { transform, child } => context.update_transform(accel, transform, child),
        }
    }

    /// Levels of the graph it would head, below it: its deepest child's (0 for triangles).
    fn child_depth(&self) -> u32 {
        match self {
            Resolved::Triangles(_) => 0,
            Resolved::Instances(instances) => instances.iter().map(|i| i.child.info().depth).max().unwrap_or(0),
            Resolved::Transform { child, .. } => child.info().depth,
        }
    }
}

/// A triangle input whose bytes are owned (shared `Bytes`, never copied).
#[derive(Debug)]
pub struct OwnedTriangles {
    /// Vertex bytes.
    vertices: Bytes,
    /// Vertex bytes of motion keys 1, 2, ….
    motion_vertices: Vec<Bytes>,
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

/// Calls `call` with the engine's view of `owned`.
fn with_inputs<R>(owned: &[OwnedTriangles], call: impl FnOnce(&[BuildInput<'_>]) -> R) -> R {
    let motion: Vec<Vec<&[u8]>> = owned.iter().map(|o| o.motion_vertices.iter().map(|b| &b[..]).collect()).collect();
    let inputs: Vec<_> = owned.iter().zip(&motion).map(|(o, motion)| o.as_input(motion)).collect();
    call(&inputs)
}

impl OwnedTriangles {
    /// The engine's view of this input, with `motion_vertices` the slices of its motion keys' bytes.
    fn as_input<'a>(&'a self, motion_vertices: &'a [&'a [u8]]) -> BuildInput<'a> {
        BuildInput::Triangles(TriangleInput {
            vertices: VertexBuffer { data: &self.vertices, format: self.vertex_format, stride: self.stride },
            motion_vertices,
            indices: self.indices.as_ref().map(|(data, format)| IndexBuffer { data, format: *format }),
            masks: self.masks.as_deref(),
            flags: self.flags,
            primitive_index_offset: self.primitive_index_offset,
        })
    }
}

/// Resolves the inputs of a build on `device` (or of an update, or of a memory bound asked for), and checks the depth
/// of the graph it would head against `max_graph_depth`. Reads every input's bytes and expands instances: call it off
/// the async runtime.
pub fn resolve(tenant: &Tenant, device: &str, inputs: &[pb::BuildInput]) -> ServiceResult<Resolved> {
    use pb::build_input::Input;
    let places = |input: &pb::BuildInput| matches!(input.input, Some(Input::Instances(_) | Input::Transform(_)));
    let resolved = match inputs {
        [] => return Err(ServiceError::invalid("inputs", "a build needs at least one input")),
        [only] if places(only) => match &only.input {
            Some(Input::Instances(instances)) => Resolved::Instances(resolve_instances(tenant, device, instances)?),
            Some(Input::Transform(transform)) => resolve_transform(tenant, device, transform)?,
            _ => return Err(ServiceError::invalid("inputs[0]", "a build input must be set")),
        },
        _ if inputs.iter().any(places) => {
            return Err(ServiceError::invalid(
                "inputs",
                "an instance or transform input must be the build's only input",
            ));
        }
        _ => Resolved::Triangles(
            inputs
                .iter()
                .enumerate()
                .map(|(i, input)| resolve_triangles(tenant, i, input))
                .collect::<Result<_, _>>()?,
        ),
    };
    let depth = resolved.child_depth() + 1;
    ServiceError::check_limit(
        || "levels of the accel's graph (this build's, above the deepest child its inputs name)".into(),
        u64::from(depth),
        "max_graph_depth",
        u64::from(tenant.limits().max_graph_depth),
    )?;
    Ok(resolved)
}

/// The child accel `reference` names, which must be on `device` (FAILED_PRECONDITION otherwise: the request is well
/// formed, the child is where it cannot be placed).
fn child(tenant: &Tenant, device: &str, reference: Option<&pb::AccelRef>, field: &str) -> ServiceResult<Arc<Accel>> {
    let entry = accels::resolve(tenant, reference, field)?;
    let (device, _) = tenant.context(device)?;
    if entry.device != device {
        return Err(ServiceError::Precondition(format!(
            "{field}: accel {:?} is on device {}, the build on {device}; copy it there first (CopyAccel)",
            entry.name, entry.device
        )));
    }
    Ok(entry.accel)
}

/// The instances of an instance input.
fn resolve_instances(tenant: &Tenant, device: &str, input: &pb::InstanceInput) -> ServiceResult<Vec<Instance>> {
    use pb::instance_input::Instances;
    let children: Vec<Arc<Accel>> = input
        .children
        .iter()
        .enumerate()
        .map(|(i, reference)| child(tenant, device, Some(reference), &format!("inputs[0].instances.children[{i}]")))
        .collect::<Result<_, _>>()?;
    let required = |field: &str| ServiceError::invalid(field, "required");
    Ok(match &input.instances {
        Some(Instances::Records(records)) => {
            let records = data(tenant, Some(records), "inputs[0].instances.records")?
                .ok_or_else(|| required("inputs[0].instances.records"))?;
            check_instance_count(tenant, device, records.len() / INSTANCE_RECORD_BYTES)?;
            instances_from_records(&records, &children)?
        }
        Some(Instances::Prime(prime)) => {
            let field = |name: &str| format!("inputs[0].instances.prime.{name}");
            let indices = data(tenant, prime.child_indices.as_ref(), &field("child_indices"))?
                .ok_or_else(|| required(&field("child_indices")))?;
            let transforms = data(tenant, prime.transforms.as_ref(), &field("transforms"))?
                .ok_or_else(|| required(&field("transforms")))?;
            let format = match pb::TransformFormat::try_from(prime.transform_format) {
                Ok(pb::TransformFormat::Float4x4) => TransformFormat::Float4x4,
                Ok(pb::TransformFormat::Float4x3) => TransformFormat::Float4x3,
                _ => return Err(ServiceError::invalid(field("transform_format"), "must be FLOAT4X4 or FLOAT4X3")),
            };
            check_instance_count(tenant, device, indices.len() / size_of::<u32>())?;
            instances_from_prime(&indices, &transforms, format, &children)?
        }
        None => return Err(ServiceError::invalid("inputs[0].instances", "records or prime is required")),
    })
}

/// RESOURCE_EXHAUSTED before `count` instances are made when even the smallest instance accel over them (its default
/// build) would pass `max_accel_bytes`: the instances' records, up to a buffer's size, are not expanded for an accel
/// that cannot be built (nor for an update, whose count is its build's, nor for the memory bound of one).
fn check_instance_count(tenant: &Tenant, device: &str, count: usize) -> ServiceResult<()> {
    let (_, context) = tenant.context(device)?;
    let bytes = context.compute_instance_arrays_memory_usage(count, &BuildOptions::default())?.output_bytes;
    ServiceError::check_limit(
        || format!("the bytes of an instance accel of {count} instances"),
        bytes,
        "max_accel_bytes",
        tenant.limits().max_accel_bytes,
    )
}

/// The matrix or keys and the child of a transform input.
fn resolve_transform(tenant: &Tenant, device: &str, input: &pb::TransformInput) -> ServiceResult<Resolved> {
    let field = |name: &str| format!("inputs[0].transform.{name}");
    let given = [
        ("transform", input.transform.len()),
        ("matrix_keys", input.matrix_keys.len()),
        ("srt_keys", input.srt_keys.len()),
    ];
    let transform = match given.map(|(_, len)| len > 0) {
        [true, false, false] => TransformInput::Static(input.transform.as_slice().try_into().map_err(|_| {
            ServiceError::invalid(field("transform"), format!("{} values given, 12 needed", input.transform.len()))
        })?),
        [false, true, false] => {
            let motion = transform_motion(tenant, input.motion.as_ref())?;
            TransformInput::MatrixMotion { keys: keys(&input.matrix_keys, &field("matrix_keys"), &motion)?, motion }
        }
        [false, false, true] => {
            let motion = transform_motion(tenant, input.motion.as_ref())?;
            TransformInput::SrtMotion { keys: keys(&input.srt_keys, &field("srt_keys"), &motion)?, motion }
        }
        _ => {
            let set: Vec<&str> = given.iter().filter(|(_, len)| *len > 0).map(|(name, _)| *name).collect();
            return Err(ServiceError::invalid(
                "inputs[0].transform",
                format!("exactly one of transform, matrix_keys and srt_keys must be given; given: {set:?}"),
            ));
        }
    };
    Ok(Resolved::Transform { transform, child: child(tenant, device, input.child.as_ref(), &field("child"))? })
}

/// A motion transform's motion options: at least 2 keys, within `max_motion_keys`.
fn transform_motion(tenant: &Tenant, motion: Option<&pb::MotionOptions>) -> ServiceResult<MotionOptions> {
    let motion = convert::motion_options(motion);
    let field = "inputs[0].transform.motion.keys";
    if motion.is_static() {
        return Err(ServiceError::invalid(
            field,
            format!("a motion transform needs at least 2 keys, got {}", motion.keys),
        ));
    }
    check_motion_keys(tenant, &motion, field)?;
    Ok(motion)
}

/// The engine's build options of a request for `resolved`, within the tenant's `max_motion_keys`; a transform's build
/// ignores them (its input's motion moves it).
pub fn options(
    tenant: &Tenant,
    resolved: &Resolved,
    options: Option<&pb::BuildOptions>,
) -> ServiceResult<BuildOptions> {
    if let Resolved::Transform { .. } = resolved {
        return Ok(BuildOptions::default());
    }
    let options = convert::build_options(options);
    check_motion_keys(tenant, &options.motion, "options.motion.keys")?;
    Ok(options)
}

/// Checks motion options against the tenant's `max_motion_keys`.
fn check_motion_keys(tenant: &Tenant, motion: &MotionOptions, field: &str) -> ServiceResult<()> {
    ServiceError::check_limit(
        || format!("motion keys ({field})"),
        u64::from(motion.keys),
        "max_motion_keys",
        u64::from(tenant.limits().max_motion_keys),
    )
}

/// `values` cut into keys of `N` floats, as many as `motion` has keys.
fn keys<const N: usize>(values: &[f32], field: &str, motion: &MotionOptions) -> ServiceResult<Vec<[f32; N]>> {
    let needed = N * motion.keys as usize;
    if values.len() != needed {
        return Err(ServiceError::invalid(
            field,
            format!("{} values given; {} motion keys of {N} need {needed}", values.len(), motion.keys),
        ));
    }
    Ok(values.chunks_exact(N).map(|key| key.try_into().expect("chunks of N")).collect())
}

/// Resolves triangle input `index`.
fn resolve_triangles(tenant: &Tenant, index: usize, input: &pb::BuildInput) -> ServiceResult<OwnedTriangles> {
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
    let motion_vertices = t
        .motion_vertices
        .iter()
        .enumerate()
        .map(|(key, source)| {
            let name = field(&format!("motion_vertices[{key}]"));
            data(tenant, Some(source), &name)?.ok_or_else(|| ServiceError::invalid(name, "vertices are required"))
        })
        .collect::<Result<_, _>>()?;
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
        motion_vertices,
        vertex_format,
        stride: (t.vertex_stride_bytes != 0).then_some(t.vertex_stride_bytes),
        indices,
        masks: data(tenant, t.masks.as_ref(), &field("masks"))?,
        flags,
        primitive_index_offset: t.primitive_index_offset,
    })
}

/// The bytes of a data source: inline, or a buffer's (shared, not copied).
pub fn data(tenant: &Tenant, source: Option<&pb::DataSource>, field: &str) -> ServiceResult<Option<Bytes>> {
    let Some(source) = source.and_then(|s| s.source.as_ref()) else { return Ok(None) };
    match source {
        pb::data_source::Source::Inline(bytes) => Ok(Some(bytes.clone())),
        pb::data_source::Source::Buffer(reference) => {
            Ok(Some(super::buffers::resolve(tenant, Some(reference), field)?.1))
        }
    }
}
