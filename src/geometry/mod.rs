//! Build inputs (what a caller hands over) and their validation into one flat list of triangles.

mod gather;
mod input;
mod instance;
mod instance_records;
pub mod motion;
mod structure;
mod transform;

pub use gather::{GatheredTriangles, TriangleRef, gather, is_degenerate, is_degenerate_throughout, triangle_counts};
pub use input::{BuildInput, GeometryFlags, IndexBuffer, IndexFormat, TriangleInput, VertexBuffer, VertexFormat};
pub use instance::{Instance, InstanceFlags, MAX_GRAPH_DEPTH, PlacedInstance, Placement, check_depth, place};
pub use instance_records::{
    INSTANCE_RECORD_BYTES, InstanceRecord, TransformFormat, instances_from_prime, instances_from_records,
};
pub use motion::{MotionFlags, MotionOptions};
pub(crate) use structure::InputStructure;
pub use structure::Structure;
pub use transform::{SRT_KEY_FLOATS, SrtKey, Transform, TransformInput};
