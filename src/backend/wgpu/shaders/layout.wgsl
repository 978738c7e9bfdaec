// Shared by every pipeline of the wgpu backend: the structs and constants whose byte layouts the host writes.
// Each names the Rust item it must match; change both together.

// `kernel::Params` (src/backend/wgpu/kernel.rs), 44 bytes, one uniform buffer a chunk.
struct Params {
    // Rays in this chunk.
    ray_count: u32,
    // The ray format: its index in `RayFormat::ALL`.
    ray_format: u32,
    // The hit format: its index in `HitFormat::ALL`.
    hit_format: u32,
    // `RayFlags` bits OR-ed into every ray's.
    query_flags: u32,
    // Hit records a ray (`Query::records_per_ray`).
    records_per_ray: u32,
    // Words (4 bytes) a hit record, 0 for the bitmask.
    record_words: u32,
    // The traced accel's object: its word offset in `graph`.
    root: u32,
    // Generated rays: the generator's index of the chunk's first ray.
    first_ray: u32,
    // The image reduction: rays a pixel, and words a pixel (1 depth, 4 normal; 0 without a reduction).
    group_rays: u32,
    pixel_words: u32,
    // Node visits and triangle tests a ray may take: a ray past them stops (at its next leaf or instance leaf), and
    // a ray whose walk passed them is counted in the tallies' word `OVER_RAY_WORK` (the host then fails the trace).
    max_ray_work: u32,
}

// A device node (`layout::NODE_WORDS` words, `layout.rs`): `NODE_WIDTH` lanes, by field then lane. A lane is an
// inner child (`count` 0, its node at `index`), a leaf (`count` primitives or instances from `index`) or empty
// (`index` `EMPTY_LANE`).
struct Node {
    // The lanes' boxes, a row a plane: `lo.x, lo.y, lo.z, hi.x, hi.y, hi.z` (a row indexed by axis, plus 3 for `hi`).
    boxes: LaneRows,
    index: vec4<u32>,
    count: vec4<u32>,
}

// Six rows of four lanes: the lanes' boxes of a node.
alias LaneRows = array<vec4<f32>, 6>;

// `layout::NODE_WIDTH`.
const NODE_WIDTH: u32 = 4u;
// `collapse::EMPTY_LANE`.
const EMPTY_LANE: u32 = 0xffffffffu;

// `layout::Prim` (src/backend/wgpu/layout.rs), 16 bytes a triangle slot.
struct Prim {
    geom_id: u32,
    prim_id: u32,
    // Prime mask (0 without masks).
    mask: u32,
    // `GeometryFlags` bits of the triangle's geometry.
    geometry_flags: u32,
}

// An object record of `graph` (`layout::OBJECT_WORDS` words, read by `load_object`).
struct Object {
    // `layout::ObjectKind`.
    kind: u32,
    // Motion keys, 1 when static.
    keys: u32,
    // `MotionFlags` bits.
    motion_flags: u32,
    // The motion range.
    time_begin: f32,
    time_end: f32,
    // A BVH's root node; a transform's child object.
    first: u32,
    // A BVH's nodes (0 when it holds nothing to hit); 0 for a transform.
    node_count: u32,
    // A motion BVH's first key box (float offset in `node_boxes`).
    box_base: u32,
    // A geometry accel's first triangle slot, an instance accel's first instance record, a transform's first key.
    base: u32,
    // A geometry accel's first corner (its index in `corners`).
    corner_base: u32,
}

const OBJECT_WORDS: u32 = 10u;
// `layout::INSTANCE_WORDS`: `0 world_to_object f32×12 | 12 instance_id | 13 mask | 14 flags | 15 child`.
const INSTANCE_WORDS: u32 = 16u;
// `layout::ObjectKind`.
const OBJECT_TRIANGLES: u32 = 0u;
const OBJECT_INSTANCES: u32 = 1u;
const OBJECT_STATIC_TRANSFORM: u32 = 2u;
const OBJECT_MATRIX_TRANSFORM: u32 = 3u;
const OBJECT_SRT_TRANSFORM: u32 = 4u;

// Words at the head of the tallies buffer before the per-ray counts (`batch::TALLY_WORDS`): 0 rays hit,
// 1–2 nodes visited (low, high), 3–4 triangle tests (low, high), 5 rays whose walk passed `max_ray_work`
// (`batch::OVER_RAY_WORK`), 6–7 zero.
const TALLY_WORDS: u32 = 8u;
const OVER_RAY_WORK: u32 = 5u;
