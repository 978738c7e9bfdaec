//! Acceleration-structure build options, memory-usage figures and the description of a built accel.

use glam::Vec3;

use crate::error::{Error, Result};
use crate::geometry::MotionOptions;

bitflags::bitflags! {
    /// Build flags, after OptiX 7's `OptixBuildFlags`.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
    pub struct BuildFlags: u32 {
        /// Spend more build time for faster traces. Excludes `PREFER_FAST_BUILD`.
        const PREFER_FAST_TRACE = 1;
        /// Build as fast as possible at some cost in trace speed. Excludes `PREFER_FAST_TRACE`.
        const PREFER_FAST_BUILD = 1 << 1;
        /// The accel may later be updated (refit) with new positions of the same structure.
        const ALLOW_UPDATE = 1 << 2;
        /// The accel reports a compacted size and may later be compacted.
        const ALLOW_COMPACTION = 1 << 3;
        /// The triangles' vertices can be read back from the accel ([`crate::Accel::triangle_vertices`]).
        const ALLOW_RANDOM_VERTEX_ACCESS = 1 << 4;
    }
}

/// Options of one build.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BuildOptions {
    /// Build flags.
    pub flags: BuildFlags,
    /// Motion keys, time range and vanish flags (static by default). A geometry accel with `K` keys takes `K`
    /// vertex buffers per input; an instance accel's keys only bound its instances over time (and its vanish flags
    /// hide them outside its range). A transform's are its own.
    pub motion: MotionOptions,
}

impl BuildOptions {
    /// Static options with the given flags.
    pub fn new(flags: BuildFlags) -> Self {
        BuildOptions { flags, motion: MotionOptions::STATIC }
    }

    /// Checks that the flags can be combined and the motion options are valid.
    pub fn validate(&self) -> Result<()> {
        self.motion.check().map_err(|rule| Error::InvalidBuildOptions(format!("motion: {rule}")))?;
        if self.flags.contains(BuildFlags::PREFER_FAST_TRACE | BuildFlags::PREFER_FAST_BUILD) {
            return Err(Error::InvalidBuildOptions(
                "flags PREFER_FAST_TRACE and PREFER_FAST_BUILD are mutually exclusive".into(),
            ));
        }
        Ok(())
    }
}

/// Upper bounds of the memory a build (and a later update) uses, as `optixAccelComputeMemoryUsage` reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MemoryUsage {
    /// Bytes of the built accel ([`AccelInfo::size_bytes`] never exceeds it).
    pub output_bytes: u64,
    /// Bytes of working memory the build needs besides its output.
    pub temp_bytes: u64,
    /// Bytes of working memory an update needs (0 without `ALLOW_UPDATE`).
    pub temp_update_bytes: u64,
}

/// The flags of every transform, whatever its build was given: it can always be updated, and compacted (a
/// compacted copy is a copy). A blob stores none for a transform.
pub const TRANSFORM_FLAGS: BuildFlags = BuildFlags::ALLOW_UPDATE.union(BuildFlags::ALLOW_COMPACTION);

/// What an accel is built over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum AccelKind {
    /// Triangles (a geometry accel).
    Triangles,
    /// Instances of other accels (an instance accel).
    Instances,
    /// One other accel under a static transform.
    Transform,
    /// One other accel under a matrix motion transform.
    MatrixMotionTransform,
    /// One other accel under an SRT motion transform.
    SrtMotionTransform,
}

impl AccelKind {
    /// Whether it is a transform (static or moving).
    pub fn is_transform(self) -> bool {
        matches!(self, AccelKind::Transform | AccelKind::MatrixMotionTransform | AccelKind::SrtMotionTransform)
    }
}

/// What is known about a built accel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AccelInfo {
    /// What it is built over.
    pub kind: AccelKind,
    /// Bytes the accel occupies on its device.
    pub size_bytes: u64,
    /// Triangles given to the build (degenerate ones included).
    pub triangle_count: u64,
    /// Build inputs (geometries) of a geometry accel; 0 otherwise.
    pub geometry_count: u32,
    /// Instances of an instance accel; 0 otherwise.
    pub instance_count: u64,
    /// Levels of the traversable graph it heads: 1 for a geometry accel, one more than its deepest child
    /// otherwise.
    pub depth: u32,
    /// The options it was built with.
    pub options: BuildOptions,
    /// With `ALLOW_COMPACTION`: the size a compacted copy would have.
    pub compacted_size_bytes: Option<u64>,
    /// The box around every triangle at every time, in the accel's own space (`min > max` when there are none).
    pub bounds: (Vec3, Vec3),
}
