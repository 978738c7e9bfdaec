//! Validation of build inputs, and their flattening into one list of triangles that every backend builds from.

use glam::{DVec3, Vec3};

use super::input::{BuildInput, GeometryFlags, IndexFormat, TriangleInput};
use crate::error::{Error, Result};
use crate::format::{read_f32, read_u32};

/// Where a gathered triangle came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TriangleRef {
    /// Index of the build input.
    pub geom_id: u32,
    /// The input's primitive-index offset plus the triangle's index in the input.
    pub prim_id: u32,
}

/// Every triangle of a build, validated, in input order.
#[derive(Debug, Clone, Default)]
pub struct GatheredTriangles {
    /// Motion keys (1 without motion).
    pub keys: usize,
    /// The three corners of each triangle at each key: triangle `i`'s at key `k` are at `i·keys + k`.
    pub vertices: Vec<[Vec3; 3]>,
    /// The ids each triangle reports, parallel to `vertices`.
    pub refs: Vec<TriangleRef>,
    /// Prime masks parallel to `vertices`, when any input has masks (inputs without them give 0).
    pub masks: Option<Vec<u32>>,
    /// Flags of each input, indexed by geometry id.
    pub geometry_flags: Vec<GeometryFlags>,
}

impl GatheredTriangles {
    /// Number of triangles.
    pub fn len(&self) -> usize {
        self.refs.len()
    }

    /// Whether there are no triangles.
    pub fn is_empty(&self) -> bool {
        self.refs.is_empty()
    }

    /// The corners of triangle `index` at every key.
    pub fn corners(&self, index: usize) -> &[[Vec3; 3]] {
        &self.vertices[index * self.keys..(index + 1) * self.keys]
    }

    /// The mask of triangle `index` (0 without masks).
    pub fn mask(&self, index: usize) -> u32 {
        self.masks.as_ref().map_or(0, |m| m[index])
    }
}

/// Whether a triangle has zero area: its edge cross product, computed exactly (f64 holds the products of f32
/// differences without rounding for all but extreme exponents), is the zero vector. Such triangles are legal
/// and never hit.
pub fn is_degenerate(corners: &[Vec3; 3]) -> bool {
    has_no_area(corners.map(|v| v.as_dvec3()))
}

/// Whether a moving triangle, its corners at each key in `keys`, has zero area at every time: at every key and
/// halfway between neighbouring keys (in f64, exact as in [`is_degenerate`] for all but extreme exponents), so that
/// its edge cross product, a quadratic in time along each segment, is zero all along it. For one key,
/// [`is_degenerate`].
pub fn is_degenerate_throughout(keys: &[[Vec3; 3]]) -> bool {
    let halfway = |pair: &[[Vec3; 3]]| std::array::from_fn(|c| (pair[0][c].as_dvec3() + pair[1][c].as_dvec3()) * 0.5);
    keys.iter().all(is_degenerate) && keys.windows(2).all(|pair| has_no_area(halfway(pair)))
}

/// Whether the triangle `[a, b, c]` has a zero edge cross product.
fn has_no_area([a, b, c]: [DVec3; 3]) -> bool {
    (b - a).cross(c - a) == DVec3::ZERO
}

/// Validates `inputs` for a build with `keys` motion keys and returns each input's triangle count. Errors name the
/// input, the field, the element and the rule.
pub fn triangle_counts(inputs: &[BuildInput<'_>], keys: usize) -> Result<Vec<usize>> {
    if inputs.is_empty() {
        return Err(Error::InvalidBuildOptions("a build needs at least one build input".into()));
    }
    let counts = inputs
        .iter()
        .enumerate()
        .map(|(index, BuildInput::Triangles(triangles))| check_triangle_input(index, triangles, keys))
        .collect::<Result<Vec<_>>>()?;
    let total: usize = counts.iter().sum();
    if total >= u32::MAX as usize {
        return Err(Error::TooLarge {
            what: "triangles of one build",
            unit: "triangles",
            requested: total as u64,
            limit: u32::MAX as u64 - 1,
        });
    }
    Ok(counts)
}

/// Validates `inputs` for a build with `keys` motion keys (see [`triangle_counts`]) and flattens them into one
/// list of triangles.
pub fn gather(inputs: &[BuildInput<'_>], keys: usize) -> Result<GatheredTriangles> {
    let counts = triangle_counts(inputs, keys)?;
    let total: usize = counts.iter().sum();
    let any_masks = inputs.iter().any(|BuildInput::Triangles(t)| t.masks.is_some());
    let mut out = GatheredTriangles {
        keys,
        vertices: Vec::with_capacity(total * keys),
        refs: Vec::with_capacity(total),
        masks: any_masks.then(|| Vec::with_capacity(total)),
        geometry_flags: Vec::with_capacity(inputs.len()),
    };
    for (geom_id, (BuildInput::Triangles(input), count)) in inputs.iter().zip(counts).enumerate() {
        append_triangles(&mut out, geom_id as u32, input, count);
    }
    Ok(out)
}

/// Checks one input against every rule and returns its triangle count.
fn check_triangle_input(input: usize, t: &TriangleInput<'_>, keys: usize) -> Result<usize> {
    let fail = |field, element: Option<u64>, rule: String| Error::InvalidBuildInput { input, field, element, rule };
    if t.motion_vertices.len() + 1 != keys {
        return Err(fail(
            "motion_vertices",
            None,
            format!(
                "{} vertex buffers given besides `vertices`; the build's {keys} motion keys need {}",
                t.motion_vertices.len(),
                keys.saturating_sub(1)
            ),
        ));
    }
    let vertex_size = t.vertices.format.size();
    let stride = t.vertices.stride.map_or(vertex_size, |s| s as usize);
    if stride < vertex_size || !stride.is_multiple_of(4) {
        return Err(fail(
            "vertices.stride",
            None,
            format!(
                "stride {stride} must be a multiple of 4 and at least {vertex_size} bytes for {:?}",
                t.vertices.format
            ),
        ));
    }
    let bytes = t.vertices.data.len();
    if !bytes.is_multiple_of(stride) {
        return Err(fail("vertices", None, format!("byte length {bytes} is not a multiple of the stride {stride}")));
    }
    let vertex_count = bytes / stride;
    for (key, data) in std::iter::once(t.vertices.data).chain(t.motion_vertices.iter().copied()).enumerate() {
        let field = if key == 0 { "vertices" } else { "motion_vertices" };
        if data.len() != bytes {
            return Err(fail(
                field,
                Some(key as u64 - 1),
                format!("{} bytes for motion key {key}, `vertices` has {bytes}: keys share the layout", data.len()),
            ));
        }
        for v in 0..vertex_count {
            for axis in 0..3 {
                let value = read_f32(data, v * stride + 4 * axis);
                if !value.is_finite() {
                    let element = if key == 0 { v as u64 } else { (key - 1) as u64 };
                    return Err(fail(
                        field,
                        Some(element),
                        format!("key {key}, vertex {v}: coordinate {axis} is {value}; vertices must be finite"),
                    ));
                }
            }
        }
    }
    let triangle_count = match t.indices {
        Some(indices) => {
            let size = indices.format.triangle_size();
            let len = indices.data.len();
            if !len.is_multiple_of(size) {
                return Err(fail(
                    "indices",
                    None,
                    format!("byte length {len} is not a multiple of {size} ({:?})", indices.format),
                ));
            }
            for tri in 0..len / size {
                for corner in 0..3 {
                    let index = read_index(indices.data, indices.format, tri * 3 + corner) as usize;
                    if index >= vertex_count {
                        return Err(fail(
                            "indices",
                            Some(tri as u64),
                            format!("corner {corner} is vertex {index}, beyond the {vertex_count} vertices"),
                        ));
                    }
                }
            }
            len / size
        }
        None => {
            if !vertex_count.is_multiple_of(3) {
                return Err(fail(
                    "vertices",
                    None,
                    format!("{vertex_count} vertices without indices is not a multiple of 3"),
                ));
            }
            vertex_count / 3
        }
    };
    if triangle_count == 0 {
        let field = if t.indices.is_some() { "indices" } else { "vertices" };
        return Err(fail(field, None, "the input has no triangles".into()));
    }
    if let Some(masks) = t.masks
        && masks.len() != 4 * triangle_count
    {
        return Err(fail(
            "masks",
            None,
            format!("{} bytes given, 4 per triangle needs {}", masks.len(), 4 * triangle_count),
        ));
    }
    let last_id = t.primitive_index_offset as u64 + triangle_count as u64 - 1;
    if last_id >= u32::MAX as u64 {
        return Err(fail(
            "primitive_index_offset",
            None,
            format!(
                "offset {} + {triangle_count} triangles overflows the 32-bit primitive id",
                t.primitive_index_offset
            ),
        ));
    }
    Ok(triangle_count)
}

/// Reads index `i` (counting single indices, not triangles).
fn read_index(data: &[u8], format: IndexFormat, i: usize) -> u32 {
    match format {
        IndexFormat::U32x3 => read_u32(data, 4 * i),
        IndexFormat::U16x3 => u16::from_le_bytes([data[2 * i], data[2 * i + 1]]) as u32,
    }
}

/// Appends a checked input's triangles.
fn append_triangles(out: &mut GatheredTriangles, geom_id: u32, t: &TriangleInput<'_>, count: usize) {
    let stride = t.vertices.stride.map_or(t.vertices.format.size(), |s| s as usize);
    let vertex = |data: &[u8], v: usize| {
        Vec3::new(read_f32(data, v * stride), read_f32(data, v * stride + 4), read_f32(data, v * stride + 8))
    };
    for tri in 0..count {
        let corner = |c: usize| match t.indices {
            Some(indices) => read_index(indices.data, indices.format, 3 * tri + c) as usize,
            None => 3 * tri + c,
        };
        let corners = [corner(0), corner(1), corner(2)];
        for data in std::iter::once(t.vertices.data).chain(t.motion_vertices.iter().copied()) {
            out.vertices.push(corners.map(|v| vertex(data, v)));
        }
        out.refs.push(TriangleRef { geom_id, prim_id: t.primitive_index_offset + tri as u32 });
        if let Some(masks) = out.masks.as_mut() {
            masks.push(t.masks.map_or(0, |m| read_u32(m, 4 * tri)));
        }
    }
    out.geometry_flags.push(t.flags);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{IndexBuffer, VertexBuffer, VertexFormat};

    fn f32_bytes(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn u32_bytes(values: &[u32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    #[test]
    fn interleaved_float4_u16_input_gathers_the_right_corners() {
        // Stride 20: position (float4) + one extra float per vertex.
        let vertices = f32_bytes(&[0., 0., 0., 1., 9., 1., 0., 0., 1., 9., 0., 1., 0., 1., 9., 0., 0., 1., 1., 9.]);
        let indices: Vec<u8> = [0u16, 1, 2, 0, 2, 3].iter().flat_map(|v| v.to_le_bytes()).collect();
        let masks = u32_bytes(&[5, 6]);
        let input = TriangleInput {
            vertices: VertexBuffer { data: &vertices, format: VertexFormat::Float4, stride: Some(20) },
            motion_vertices: &[],
            indices: Some(IndexBuffer { data: &indices, format: IndexFormat::U16x3 }),
            masks: Some(&masks),
            flags: GeometryFlags::DISABLE_FACE_CULLING,
            primitive_index_offset: 100,
        };
        let g = gather(&[BuildInput::Triangles(input)], 1).unwrap();
        assert_eq!(g.len(), 2);
        assert_eq!(g.vertices[1], [Vec3::ZERO, Vec3::Y, Vec3::Z]);
        assert_eq!(g.refs[1], TriangleRef { geom_id: 0, prim_id: 101 });
        assert_eq!(g.masks, Some(vec![5, 6]));
        assert_eq!(g.geometry_flags, vec![GeometryFlags::DISABLE_FACE_CULLING]);
    }

    #[test]
    fn every_rule_names_input_field_and_element() {
        let good_v = f32_bytes(&[0., 0., 0., 1., 0., 0., 0., 1., 0.]);
        fn soup(v: &[u8]) -> TriangleInput<'_> {
            TriangleInput {
                vertices: VertexBuffer { data: v, format: VertexFormat::Float3, stride: None },
                motion_vertices: &[],
                indices: None,
                masks: None,
                flags: GeometryFlags::empty(),
                primitive_index_offset: 0,
            }
        }
        let check = |inputs: &[TriangleInput<'_>], field: &str, element: Option<u64>| {
            let inputs: Vec<_> = inputs.iter().copied().map(BuildInput::Triangles).collect();
            match gather(&inputs, 1) {
                Err(Error::InvalidBuildInput { input, field: f, element: e, .. }) => {
                    assert_eq!((input, f, e), (inputs.len() - 1, field, element));
                }
                other => panic!("expected an error on {field}, got {other:?}"),
            }
        };
        let nan = f32_bytes(&[0., 0., 0., 1., f32::NAN, 0., 0., 1., 0.]);
        check(&[soup(&good_v), soup(&nan)], "vertices", Some(1));
        let inf = f32_bytes(&[0., 0., 0., 1., 0., 0., 0., 1., f32::INFINITY]);
        check(&[soup(&inf)], "vertices", Some(2));
        check(&[soup(&good_v[..35])], "vertices", None);
        check(&[soup(&good_v[..24])], "vertices", None);
        check(&[soup(&[])], "vertices", None);
        let out_of_range = u32_bytes(&[0, 1, 3]);
        check(&[TriangleInput::indexed(&good_v, &out_of_range)], "indices", Some(0));
        let ragged = u32_bytes(&[0, 1, 2, 0]);
        check(&[TriangleInput::indexed(&good_v, &ragged)], "indices", None);
        check(&[TriangleInput::indexed(&good_v, &[])], "indices", None);
        let short_masks = [0u8; 3];
        check(&[TriangleInput { masks: Some(&short_masks), ..soup(&good_v) }], "masks", None);
        let bad_stride = TriangleInput {
            vertices: VertexBuffer { data: &good_v, format: VertexFormat::Float3, stride: Some(8) },
            ..soup(&good_v)
        };
        check(&[bad_stride], "vertices.stride", None);
        check(&[TriangleInput { primitive_index_offset: u32::MAX, ..soup(&good_v) }], "primitive_index_offset", None);
        assert!(matches!(gather(&[], 1), Err(Error::InvalidBuildOptions(_))));
    }

    #[test]
    fn zero_area_triangles_are_degenerate_and_thin_ones_are_not() {
        assert!(is_degenerate(&[Vec3::ZERO, Vec3::X, Vec3::X * 2.0]));
        assert!(is_degenerate(&[Vec3::ONE; 3]));
        assert!(!is_degenerate(&[Vec3::ZERO, Vec3::X, Vec3::new(2.0, 1e-30, 0.0)]));
        // Moving: lines at both keys, with or without area in between.
        let flat = [Vec3::ZERO, Vec3::X, Vec3::X * 2.0];
        let (still, swapped) = ([flat, flat], [flat, [Vec3::ZERO, Vec3::X * 2.0, Vec3::X]]);
        assert!(is_degenerate_throughout(&still) && is_degenerate_throughout(&swapped));
        let opening = [flat, [Vec3::ZERO, Vec3::Y * 2.0, Vec3::Y]];
        assert!(opening.iter().all(is_degenerate) && !is_degenerate_throughout(&opening), "a triangle in between");
        assert!(!is_degenerate_throughout(&[flat, [Vec3::ZERO, Vec3::X, Vec3::Y]]));
    }
}
