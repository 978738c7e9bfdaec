//! One accel in a blob, apart from its backend's payload: kind, options, counts, child references, the structure
//! an update must keep and a transform's keys (layout in the [module documentation](super)). Reading checks each
//! field on its own and against the others; resolving the references is the caller's.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;

use super::wire::{Reader, Wire, invalid, put, put_array, u32_at};
use crate::accel::{AccelKind, BuildFlags, BuildOptions, TRANSFORM_FLAGS};
use crate::backend::Shape;
use crate::context::{Accel, Retained};
use crate::error::Result;
use crate::geometry::motion::Bounds;
use crate::geometry::{
    GeometryFlags, InputStructure, MotionFlags, MotionOptions, SRT_KEY_FLOATS, Structure, Transform, TransformInput,
};

/// Set in a child reference that names an external accel (by its position in the external list); clear in one
/// that names an earlier accel of the blob (by its position among them).
pub(crate) const EXTERNAL_BIT: u32 = 1 << 31;

/// The kind's code in a blob.
pub(crate) fn kind_code(kind: AccelKind) -> u32 {
    match kind {
        AccelKind::Triangles => 0,
        AccelKind::Instances => 1,
        AccelKind::Transform => 2,
        AccelKind::MatrixMotionTransform => 3,
        AccelKind::SrtMotionTransform => 4,
    }
}

/// The kind of a code.
pub(crate) fn kind_of(code: u32) -> Result<AccelKind> {
    [
        AccelKind::Triangles,
        AccelKind::Instances,
        AccelKind::Transform,
        AccelKind::MatrixMotionTransform,
        AccelKind::SrtMotionTransform,
    ]
    .into_iter()
    .find(|&kind| kind_code(kind) == code)
    .ok_or_else(|| invalid(format!("unknown accel kind {code}")))
}

impl Wire for InputStructure {
    const SIZE: usize = 32;

    fn put(&self, bytes: &mut [u8]) {
        (self.triangles as u64).put(&mut bytes[..8]);
        (self.offset, self.flags.bits()).put(&mut bytes[8..16]);
        self.topology.put(&mut bytes[16..24]);
        self.masks.put(&mut bytes[24..32]);
    }

    fn get(bytes: &[u8]) -> Self {
        InputStructure {
            triangles: usize::try_from(u64::get(&bytes[..8])).unwrap_or(usize::MAX),
            offset: u32_at(bytes, 8),
            flags: GeometryFlags::from_bits_retain(u32_at(bytes, 12)),
            topology: u64::get(&bytes[16..24]),
            masks: u64::get(&bytes[24..32]),
        }
    }
}

/// Appends the entry of `accel`, whose children `refs` names, and its backend's payload.
pub(crate) fn write(out: &mut Vec<u8>, accel: &Accel, refs: &HashMap<*const Accel, u32>) -> Result<()> {
    let info = accel.info();
    let motion = &info.options.motion;
    put(out, &kind_code(info.kind));
    let flags = if info.kind.is_transform() { BuildFlags::empty() } else { info.options.flags };
    put(out, &flags.bits());
    put(out, &motion.keys);
    put(out, &[motion.time_begin, motion.time_end]);
    put(out, &motion.flags.bits());
    put(out, &info.triangle_count);
    put(out, &info.geometry_count);
    put(out, &info.instance_count);
    let children = accel.children();
    let codes: Vec<u32> = children.iter().map(|c| refs[&Arc::as_ptr(c)]).collect();
    put_array(out, &codes);
    let retained = accel.retained();
    put_array(out, retained.structure.as_ref().map_or(&[][..], |s| &s.inputs));
    match &retained.transform {
        Some(TransformInput::Static(matrix)) => put_array(out, std::slice::from_ref(matrix)),
        Some(TransformInput::MatrixMotion { keys, .. }) => put_array(out, keys),
        Some(TransformInput::SrtMotion { keys, .. }) => put_array(out, keys),
        None => put_array::<[f32; 12]>(out, &[]),
    }
    let length_at = out.len();
    put(out, &0u64);
    accel.backend_accel().encode(children, out)?;
    let length = (out.len() - length_at - 8) as u64;
    length.put(&mut out[length_at..length_at + 8]);
    Ok(())
}

/// The fewest bytes an entry takes: kind, build flags, motion options (16 bytes) and counts (20 bytes), then the
/// element counts of its three arrays and its payload's length (8 bytes each), everything else empty.
pub(crate) const LEAST_ENTRY_BYTES: u64 = 4 + 4 + 16 + 20 + 3 * 8 + 8;

/// One accel as a blob describes it, checked, its children not yet resolved.
#[derive(Debug)]
pub(crate) struct Entry<'a> {
    /// Kind and counts.
    pub(crate) shape: Shape,
    /// Build options (motion included).
    pub(crate) options: BuildOptions,
    /// Child references (see [`EXTERNAL_BIT`]), distinct.
    pub(crate) children: Vec<u32>,
    /// The structure and transform input it keeps.
    pub(crate) retained: Retained,
    /// A transform's input, checked.
    pub(crate) transform: Option<Transform>,
    /// The backend's payload.
    pub(crate) payload: &'a [u8],
}

impl<'a> Entry<'a> {
    /// Reads the next entry: that of accel `index`, which may refer to the accels before it and to `external`
    /// external accels.
    pub(crate) fn read(reader: &mut Reader<'a>, index: usize, external: usize) -> Result<Entry<'a>> {
        let kind = kind_of(reader.value("kind")?)?;
        let options = read_options(reader)?;
        let shape = Shape {
            kind,
            triangle_count: reader.value("triangle count")?,
            geometry_count: reader.value("geometry count")?,
            instance_count: reader.value("instance count")?,
        };
        check_shape(&shape, &options)?;
        let options = if kind.is_transform() { BuildOptions { flags: TRANSFORM_FLAGS, ..options } } else { options };
        let children: Vec<u32> = reader.array("children")?;
        check_children(&children, kind, index, external)?;
        let inputs: Vec<InputStructure> = reader.array("structure")?;
        let structure = check_structure(inputs, &shape, &options)?;
        let input = read_transform(reader, kind, &options.motion)?;
        let transform =
            input.as_ref().map(TransformInput::check).transpose().map_err(|e| invalid(format!("transform: {e}")))?;
        let length: u64 = reader.value("payload length")?;
        let payload = reader.take(usize::try_from(length).unwrap_or(usize::MAX), "payload")?;
        Ok(Entry { shape, options, children, retained: Retained { structure, transform: input }, transform, payload })
    }
}

/// Reads build flags and motion options, and checks them as a build would.
fn read_options(reader: &mut Reader<'_>) -> Result<BuildOptions> {
    let flags: u32 = reader.value("build flags")?;
    let flags = BuildFlags::from_bits(flags).ok_or_else(|| invalid(format!("unknown build flags {flags:#x}")))?;
    let keys = reader.value("motion keys")?;
    let [time_begin, time_end] = reader.value("motion time range")?;
    let motion_flags: u32 = reader.value("motion flags")?;
    let motion_flags = MotionFlags::from_bits(motion_flags)
        .ok_or_else(|| invalid(format!("unknown motion flags {motion_flags:#x}")))?;
    let options = BuildOptions { flags, motion: MotionOptions { keys, time_begin, time_end, flags: motion_flags } };
    options.validate().map_err(|e| invalid(e.to_string()))?;
    Ok(options)
}

/// Checks that the counts and options fit the kind.
fn check_shape(shape: &Shape, options: &BuildOptions) -> Result<()> {
    let fits = match shape.kind {
        AccelKind::Triangles => shape.geometry_count > 0 && shape.instance_count == 0,
        AccelKind::Instances => shape.triangle_count == 0 && shape.geometry_count == 0,
        AccelKind::Transform | AccelKind::MatrixMotionTransform | AccelKind::SrtMotionTransform => {
            *shape == Shape { kind: shape.kind, triangle_count: 0, geometry_count: 0, instance_count: 0 }
                && options.flags.is_empty()
        }
    };
    if !fits {
        return Err(invalid(format!(
            "counts or flags that a {:?} accel cannot have: {shape:?}, {options:?}",
            shape.kind
        )));
    }
    Ok(())
}

/// Checks the child references of accel `index` of `kind`: distinct, each naming an earlier accel or one of
/// `external`, one for a transform and none for a geometry accel.
fn check_children(children: &[u32], kind: AccelKind, index: usize, external: usize) -> Result<()> {
    let expected = match kind {
        AccelKind::Triangles => Some(0),
        AccelKind::Instances => None,
        AccelKind::Transform | AccelKind::MatrixMotionTransform | AccelKind::SrtMotionTransform => Some(1),
    };
    if let Some(expected) = expected
        && expected != children.len()
    {
        return Err(invalid(format!("{} children; a {kind:?} accel has {expected}", children.len())));
    }
    let mut seen = HashSet::with_capacity(children.len());
    for (position, &code) in children.iter().enumerate() {
        let (target, limit, what) = match code & EXTERNAL_BIT {
            0 => (code as usize, index, "earlier accels"),
            _ => ((code & !EXTERNAL_BIT) as usize, external, "external accels"),
        };
        if target >= limit {
            return Err(invalid(format!("child {position} names {target} of {limit} {what}")));
        }
        if !seen.insert(code) {
            return Err(invalid(format!("child {position} repeats an earlier child reference")));
        }
    }
    Ok(())
}

/// Checks the stored structure: one input per geometry, summing to the triangle count, for a geometry accel
/// that allows updates, and none otherwise.
fn check_structure(inputs: Vec<InputStructure>, shape: &Shape, options: &BuildOptions) -> Result<Option<Structure>> {
    let kept = shape.kind == AccelKind::Triangles && options.flags.contains(BuildFlags::ALLOW_UPDATE);
    if !kept {
        return match inputs.len() {
            0 => Ok(None),
            n => Err(invalid(format!("a structure of {n} inputs where none is kept"))),
        };
    }
    if inputs.len() != shape.geometry_count as usize {
        return Err(invalid(format!("a structure of {} inputs for {} geometries", inputs.len(), shape.geometry_count)));
    }
    let total = inputs.iter().try_fold(0u64, |sum, i| sum.checked_add(i.triangles as u64));
    if total != Some(shape.triangle_count) {
        return Err(invalid(format!("a structure whose triangles do not add up to {}", shape.triangle_count)));
    }
    if let Some(i) = inputs.iter().position(|i| GeometryFlags::from_bits(i.flags.bits()).is_none()) {
        return Err(invalid(format!("structure input {i}: unknown geometry flags")));
    }
    Ok(Some(Structure { inputs }))
}

/// Reads a transform's keys (none for other kinds), with the accel's motion options.
fn read_transform(reader: &mut Reader<'_>, kind: AccelKind, motion: &MotionOptions) -> Result<Option<TransformInput>> {
    let input = match kind {
        AccelKind::Transform => match reader.array::<[f32; 12]>("transform keys")?.as_slice() {
            [matrix] if *motion == MotionOptions::STATIC => Some(TransformInput::Static(*matrix)),
            keys => return Err(invalid(format!("a static transform with {} keys and {motion:?}", keys.len()))),
        },
        AccelKind::MatrixMotionTransform => {
            Some(TransformInput::MatrixMotion { keys: reader.array("transform keys")?, motion: *motion })
        }
        AccelKind::SrtMotionTransform => Some(TransformInput::SrtMotion {
            keys: reader.array::<[f32; SRT_KEY_FLOATS]>("transform keys")?,
            motion: *motion,
        }),
        AccelKind::Triangles | AccelKind::Instances => match reader.array::<[f32; 12]>("transform keys")?.len() {
            0 => None,
            n => return Err(invalid(format!("{n} transform keys for a {kind:?} accel"))),
        },
    };
    Ok(input)
}

/// What a blob records of an external accel, to check the one given at load: its kind, and its bounds (which
/// the accels placing it were built over).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct ExternalRecord {
    /// The kind's code.
    pub(crate) kind: u32,
    /// Its info's bounds.
    pub(crate) bounds: Bounds,
}

impl ExternalRecord {
    /// The record of `accel`.
    pub(crate) fn of(accel: &Accel) -> ExternalRecord {
        ExternalRecord { kind: kind_code(accel.info().kind), bounds: accel.info().bounds }
    }

    /// Whether `other` records bit-identical bounds.
    pub(crate) fn same_bounds(&self, other: &ExternalRecord) -> bool {
        let bits = |r: &ExternalRecord| [r.bounds.0, r.bounds.1].map(|v| v.to_array().map(f32::to_bits));
        bits(self) == bits(other)
    }
}

impl Wire for ExternalRecord {
    const SIZE: usize = 28;

    fn put(&self, bytes: &mut [u8]) {
        self.kind.put(&mut bytes[..4]);
        self.bounds.put(&mut bytes[4..28]);
    }

    fn get(bytes: &[u8]) -> Self {
        ExternalRecord { kind: u32_at(bytes, 0), bounds: Bounds::get(&bytes[4..28]) }
    }
}
