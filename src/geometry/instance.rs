//! Instances and static transforms, after OptiX 7's `OptixInstance` and `OptixStaticTransform` (and Prime's
//! instance lists): placements of already-built accels in a parent's space.

use std::sync::Arc;

use glam::{Affine3A, Mat3A, Vec3, Vec3A};

use super::motion::map_bounds;
use crate::context::Accel;
use crate::error::{Error, Result};

/// The deepest traversable graph: a geometry accel counts 1, each instance accel and transform above it 1 more.
pub const MAX_GRAPH_DEPTH: u32 = 8;

bitflags::bitflags! {
    /// Per-instance flags (OptiX `OptixInstanceFlags`). They apply to everything below the instance; nested
    /// instances combine them (culling stays disabled once disabled, flips cancel in pairs).
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
    pub struct InstanceFlags: u32 {
        /// Ray flags that cull front or back faces do not apply below this instance.
        const DISABLE_FACE_CULLING = 1;
        /// Front and back faces swap below this instance (for mirroring transforms, whose world-space winding
        /// is reversed; facing is otherwise decided in object space).
        const FLIP_FACING = 1 << 1;
    }
}

/// One instance of an instance accel.
#[derive(Debug, Clone)]
pub struct Instance {
    /// Object-to-world transform, a 3×4 row-major matrix: `[m00 m01 m02 tx | m10 m11 m12 ty | m20 m21 m22 tz]`.
    pub transform: [f32; 12],
    /// The user's id for it, reported by hits (the instance-id hit formats, the full format's path).
    pub instance_id: u32,
    /// Visibility mask (8 bits): a ray sees the instance when `ray.visibility & mask != 0`.
    pub mask: u8,
    /// Facing and culling flags.
    pub flags: InstanceFlags,
    /// What is placed: a geometry accel, an instance accel, or a transform.
    pub child: Arc<Accel>,
}

/// An invertible affine placement, with the forms traversal uses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placement {
    /// Object to world.
    pub object_to_world: Affine3A,
    /// World to object: rays are carried into the child's space with it.
    pub world_to_object: Affine3A,
    /// Carries object-space normals to world space (the inverse transpose of the linear part).
    pub normal_to_world: Mat3A,
}

impl Placement {
    /// The placement of a 3×4 row-major matrix; `None` unless it is finite and invertible.
    pub fn new(matrix: &[f32; 12]) -> Option<Placement> {
        if !matrix.iter().all(|m| m.is_finite()) {
            return None;
        }
        let [m00, m01, m02, tx, m10, m11, m12, ty, m20, m21, m22, tz] = *matrix;
        Placement::from_affine(Affine3A::from_cols(
            Vec3A::new(m00, m10, m20),
            Vec3A::new(m01, m11, m21),
            Vec3A::new(m02, m12, m22),
            Vec3A::new(tx, ty, tz),
        ))
    }

    /// The placement of an object-to-world map; `None` unless it is invertible with a finite inverse.
    #[inline]
    pub fn from_affine(object_to_world: Affine3A) -> Option<Placement> {
        let determinant = object_to_world.matrix3.determinant();
        if determinant == 0.0 || !determinant.is_finite() {
            return None;
        }
        let world_to_object = object_to_world.inverse();
        let inverse_is_finite = world_to_object.matrix3.to_cols_array().iter().all(|m| m.is_finite())
            && world_to_object.translation.is_finite();
        inverse_is_finite.then(|| Placement {
            object_to_world,
            world_to_object,
            normal_to_world: world_to_object.matrix3.transpose(),
        })
    }

    /// An affine transform as the 3×4 row-major matrix instances and transforms take (the inverse of
    /// [`Placement::new`]'s reading).
    pub fn rows(affine: &Affine3A) -> [f32; 12] {
        let (m, t) = (affine.matrix3, affine.translation);
        [
            m.x_axis.x, m.y_axis.x, m.z_axis.x, t.x, //
            m.x_axis.y, m.y_axis.y, m.z_axis.y, t.y, //
            m.x_axis.z, m.y_axis.z, m.z_axis.z, t.z,
        ]
    }

    /// The box around `bounds` (min, max) once placed; an empty box (`min > max`) stays empty.
    pub fn place_bounds(&self, bounds: (Vec3, Vec3)) -> (Vec3, Vec3) {
        map_bounds(&self.object_to_world, bounds)
    }
}

/// An instance checked for a build: its placement is invertible and its graph not too deep.
#[derive(Debug, Clone)]
pub struct PlacedInstance {
    /// Where it is.
    pub placement: Placement,
    /// The user's id.
    pub instance_id: u32,
    /// Visibility mask.
    pub mask: u8,
    /// Flags.
    pub flags: InstanceFlags,
    /// What is placed.
    pub child: Arc<Accel>,
}

/// Checks instance `index`'s transform and the depth its child makes.
pub fn place(index: usize, instance: &Instance) -> Result<PlacedInstance> {
    let placement = Placement::new(&instance.transform).ok_or_else(|| Error::InvalidBuildInput {
        input: 0,
        field: "instances.transform",
        element: Some(index as u64),
        rule: "must be finite and invertible".into(),
    })?;
    check_depth(instance.child.info().depth, "instances.child", Some(index))?;
    Ok(PlacedInstance {
        placement,
        instance_id: instance.instance_id,
        mask: instance.mask,
        flags: instance.flags,
        child: Arc::clone(&instance.child),
    })
}

/// Checks that placing a child of depth `child_depth` stays within [`MAX_GRAPH_DEPTH`].
pub fn check_depth(child_depth: u32, field: &'static str, element: Option<usize>) -> Result<()> {
    if child_depth >= MAX_GRAPH_DEPTH {
        return Err(Error::InvalidBuildInput {
            input: 0,
            field,
            element: element.map(|e| e as u64),
            rule: format!(
                "its child is {child_depth} levels deep: the graph would have {} levels, more than {MAX_GRAPH_DEPTH}",
                child_depth + 1
            ),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placements_are_row_major_invertible_and_carry_normals() {
        // Scale x by 2, then translate by (1, 2, 3).
        let placement = Placement::new(&[2.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 2.0, 0.0, 0.0, 1.0, 3.0]).unwrap();
        let p = placement.object_to_world.transform_point3a(Vec3A::new(1.0, 1.0, 1.0));
        assert_eq!(p, Vec3A::new(3.0, 3.0, 4.0));
        assert_eq!(placement.world_to_object.transform_point3a(p), Vec3A::new(1.0, 1.0, 1.0));
        // A normal of a plane x = y stays perpendicular to the placed plane.
        let normal = placement.normal_to_world * Vec3A::new(1.0, -1.0, 0.0);
        let along = placement.object_to_world.transform_vector3a(Vec3A::new(1.0, 1.0, 0.0));
        assert!(normal.dot(along).abs() < 1e-6);
        assert_eq!(
            placement.place_bounds((Vec3::ZERO, Vec3::ONE)),
            (Vec3::new(1.0, 2.0, 3.0), Vec3::new(3.0, 3.0, 4.0))
        );
        let matrix = [2.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 2.0, 0.0, 0.0, 1.0, 3.0];
        assert_eq!(Placement::rows(&Placement::new(&matrix).unwrap().object_to_world), matrix, "rows read back");
        assert!(Placement::new(&[0.0; 12]).is_none(), "singular");
        assert!(Placement::new(&[f32::NAN, 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0.]).is_none(), "not finite");
        let empty = (Vec3::ONE, Vec3::ZERO);
        assert_eq!(placement.place_bounds(empty), empty);
    }
}
