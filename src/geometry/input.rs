//! The triangle build input, after OptiX 7's `OptixBuildInputTriangleArray` and Prime's buffer descriptors.

bitflags::bitflags! {
    /// Per-build-input (per-geometry) flags.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
    pub struct GeometryFlags: u32 {
        /// Ray flags that cull front or back faces do not apply to this geometry's triangles.
        const DISABLE_FACE_CULLING = 1;
    }
}

/// How vertex positions are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum VertexFormat {
    /// `x y z` as three little-endian f32 (12 bytes).
    Float3,
    /// `x y z w` as four little-endian f32 (16 bytes); `w` is ignored.
    Float4,
}

impl VertexFormat {
    /// Bytes of one tightly packed vertex.
    pub const fn size(self) -> usize {
        match self {
            VertexFormat::Float3 => 12,
            VertexFormat::Float4 => 16,
        }
    }
}

/// How triangle indices are stored: three indices a triangle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum IndexFormat {
    /// Three little-endian u32 a triangle (12 bytes).
    U32x3,
    /// Three little-endian u16 a triangle (6 bytes).
    U16x3,
}

impl IndexFormat {
    /// The format's name in lower case (`u32x3`, `u16x3`).
    pub const fn name(self) -> &'static str {
        match self {
            IndexFormat::U32x3 => "u32x3",
            IndexFormat::U16x3 => "u16x3",
        }
    }

    /// Bytes of one triangle's indices.
    pub const fn triangle_size(self) -> usize {
        match self {
            IndexFormat::U32x3 => 12,
            IndexFormat::U16x3 => 6,
        }
    }
}

/// Vertex positions, possibly interleaved with other attributes.
#[derive(Debug, Clone, Copy)]
pub struct VertexBuffer<'a> {
    /// The bytes; their length must be a multiple of the stride.
    pub data: &'a [u8],
    /// How one position is stored at the start of each vertex.
    pub format: VertexFormat,
    /// Bytes from one vertex to the next; `None` means tightly packed (the format's size). A multiple of 4, at
    /// least the format's size.
    pub stride: Option<u32>,
}

/// Triangle indices into the vertex buffer.
#[derive(Debug, Clone, Copy)]
pub struct IndexBuffer<'a> {
    /// The bytes; their length must be a multiple of the format's triangle size.
    pub data: &'a [u8],
    /// How the indices are stored.
    pub format: IndexFormat,
}

/// One geometry made of triangles; its position in the build's input list is its geometry id.
#[derive(Debug, Clone, Copy)]
pub struct TriangleInput<'a> {
    /// Vertex positions (of the first motion key, with motion).
    pub vertices: VertexBuffer<'a>,
    /// With motion: the vertex bytes of motion keys 1, 2, … (one fewer than the build's motion keys), each laid out
    /// as `vertices` is (format, stride, vertex count). Empty for a static build.
    pub motion_vertices: &'a [&'a [u8]],
    /// Indices; `None` makes the vertices a triangle soup (vertices 3i, 3i+1, 3i+2 form triangle i).
    pub indices: Option<IndexBuffer<'a>>,
    /// Optional Prime triangle masks: one little-endian u32 a triangle; a ray skips the triangle when
    /// `ray.mask & triangle_mask != 0`. Without masks every triangle has mask 0.
    pub masks: Option<&'a [u8]>,
    /// Flags for every triangle of this input.
    pub flags: GeometryFlags,
    /// Added to the triangle's index in this input to make the primitive id that hits report.
    pub primitive_index_offset: u32,
}

impl<'a> TriangleInput<'a> {
    /// A tightly packed float3 vertex buffer with u32×3 indices, no motion, no masks, no flags, offset 0.
    pub fn indexed(vertices: &'a [u8], indices: &'a [u8]) -> Self {
        TriangleInput {
            vertices: VertexBuffer { data: vertices, format: VertexFormat::Float3, stride: None },
            motion_vertices: &[],
            indices: Some(IndexBuffer { data: indices, format: IndexFormat::U32x3 }),
            masks: None,
            flags: GeometryFlags::empty(),
            primitive_index_offset: 0,
        }
    }
}

/// One input of an acceleration-structure build. All inputs of one build are of the same kind.
#[derive(Debug, Clone, Copy)]
pub enum BuildInput<'a> {
    /// A geometry made of triangles.
    Triangles(TriangleInput<'a>),
}
