// Shared by every pipeline of the wgpu backend: the structs whose byte layouts the host writes. Each names the
// Rust type it must match; change both together.

// `kernel::Params` (src/backend/wgpu/kernel.rs), 48 bytes, one uniform buffer a chunk.
struct Params {
    // Rays in this chunk.
    ray_count: u32,
    // The ray format: its index in `RayFormat::ALL`.
    ray_format: u32,
    // The hit format: its index in `HitFormat::ALL`.
    hit_format: u32,
    // The query kind: its index in `QueryKind::ALL`.
    query_kind: u32,
    // `RayFlags` bits OR-ed into every ray's.
    query_flags: u32,
    // Hit records a ray (`Query::records_per_ray`).
    records_per_ray: u32,
    // Motion keys of the accel, 1 when static.
    keys: u32,
    // `MotionFlags` bits of the accel.
    motion_flags: u32,
    // The accel's motion range.
    time_begin: f32,
    time_end: f32,
    // Nodes of the accel, 0 when it holds no hittable triangle.
    node_count: u32,
    // Words (4 bytes) a hit record, 0 for the bitmask.
    record_words: u32,
}

// `cpu::bvh::Node` (src/backend/cpu/bvh.rs), 32 bytes: `0 min.xyz | 12 index | 16 max.xyz | 28 count`.
struct Node {
    min: vec3<f32>,
    index: u32,
    max: vec3<f32>,
    count: u32,
}

// `layout::Prim` (src/backend/wgpu/layout.rs), 16 bytes a triangle slot.
struct Prim {
    geom_id: u32,
    prim_id: u32,
    // Prime mask (0 without masks).
    mask: u32,
    // `GeometryFlags` bits of the triangle's geometry.
    geometry_flags: u32,
}

// Words at the head of the tallies buffer before the per-ray counts (`batch::TALLY_WORDS`): 0 rays hit,
// 1–2 nodes visited (low, high), 3–4 triangle tests (low, high), 5–7 zero.
const TALLY_WORDS: u32 = 8u;
