// The trace pipeline: one thread a ray. It decodes the ray from the caller's packed bytes, walks the accel's graph
// of 4-wide nodes (all lanes' boxes tested at once with the box test of `src/intersect/aabb.rs`, entered lanes
// visited nearest first, the same pop re-check as `src/backend/cpu/traverse.rs`; an instance leaf's visible
// instances in order, each child traversed in the instance's space before the next), tests triangles as
// `src/intersect/triangle.rs` does, collects hits as `src/query/collect.rs` does and writes the caller's hit
// format. Prepended by `layout.wgsl`, followed by `generate.wgsl` (rays made on the device) and `reduce.wgsl`
// (the image reduction's pass). The walk is while-while (Aila and Laine): a thread tests nodes until it has
// a leaf, then that leaf's triangles, so the threads of a subgroup do the same kind of work at the same time.
//
// Instance levels without recursion: the walk is one loop over one stack. Entering an instance or transform
// pushes a marker, moves one level down (the ray carried into the child's space, the level's origin, direction,
// object and record kept) and enters the child's BVH; popping the marker restores the level above. An instance
// leaf with more instances to visit first pushes a resume entry for them. Stack entries: a lane (`node ·
// NODE_WIDTH + lane`, entry distance bits rounded down: `key_distance`), a marker (`MARKER`), a resume entry
// (`RESUME | next slot`, end slot).
//
// Compiled into one pipeline a `kernel::Variant` (the pipeline constants below): what a graph or query does not
// use is compiled away.
//
// Float `min`, `max` and `clamp` ignore a NaN operand, as Rust's `f32::min` and `f32::max` do (WGSL leaves it
// undefined; `spirv.rs` writes them as SPIR-V's `NMin`, `NMax`, `NClamp`, which define it so).

// The accel's graph (uploaded once; `layout::GpuGraph`).
@group(0) @binding(0) var<storage, read> nodes: array<Node>;
// Lane boxes at motion keys, 6 floats a box (`layout.rs`).
@group(0) @binding(1) var<storage, read> node_boxes: array<f32>;
// Triangle corners at motion keys, 3 vectors a triangle (`layout.rs`).
@group(0) @binding(2) var<storage, read> corners: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> prims: array<Prim>;
// Objects, instance records and transform keys (`layout.rs`).
@group(0) @binding(4) var<storage, read> graph: array<u32>;

// The chunk (`batch::Slot`).
@group(1) @binding(0) var<uniform> params: Params;
// The caller's rays, packed in `params.ray_format`; or a generator's numbers (`generate.wgsl`).
@group(1) @binding(1) var<storage, read> rays: array<u32>;
// The caller's hit records, packed in `params.hit_format` (atomic for the bitmask's shared words).
@group(1) @binding(2) var<storage, read_write> hits: array<atomic<u32>>;
// `TALLY_WORDS` words of statistics, then one count a ray.
@group(1) @binding(3) var<storage, read_write> tallies: array<atomic<u32>>;
// For `all` queries: `records_per_ray` sorted hits a ray, 3 vectors each (`batch.rs`, `load_entry`).
@group(1) @binding(4) var<storage, read_write> scratch: array<vec4<u32>>;

// Pipeline constants (`kernel::Variant`): whether the traced graph has instance or transform levels below its
// root, and whether anything in it moves (motion keys).
override LEVELS: bool = true;
override MOTION: bool = true;
// The query kind (its index in `QueryKind::ALL`) and whether the hit format is `full` (whose normals need the
// graph's transforms again).
override QUERY_KIND: u32 = 0u;
override FULL_HITS: bool = true;
// Where the rays come from: the caller's packed rays, or a generator (`GENERATOR_*` in `generate.wgsl`).
override GENERATOR: u32 = 0u;
// Threads of a workgroup, one a ray (set to `kernel::WORKGROUP_SIZE`).
override WORKGROUP_SIZE: u32 = 64u;

// Entries of the traversal stack (`kernel::STACK_SIZE`): the host refuses graphs whose rays could need more.
const STACK_SIZE: u32 = 128u;
// Levels of a graph at most (`geometry::MAX_GRAPH_DEPTH`): the traced accel's, then one an instance or transform.
const MAX_LEVELS: u32 = 8u;
// Stack entries that are not lanes.
const MARKER: u32 = 0xffffffffu;
const RESUME: u32 = 0x80000000u;
// A level record naming a transform's object (otherwise it is an instance record's offset).
const TRANSFORM_RECORD: u32 = 0x80000000u;
// No node to visit.
const NONE: u32 = 0xffffffffu;
// `intersect::aabb::SLACK`.
const SLACK: f32 = 1e-6;
// `RayFlags`.
const CULL_BACK_FACING: u32 = 1u;
const CULL_FRONT_FACING: u32 = 2u;
const TERMINATE_ON_FIRST_HIT: u32 = 4u;
// `GeometryFlags::DISABLE_FACE_CULLING`.
const DISABLE_FACE_CULLING: u32 = 1u;
// `InstanceFlags`.
const INSTANCE_DISABLE_FACE_CULLING: u32 = 1u;
const INSTANCE_FLIP_FACING: u32 = 2u;
// `MotionFlags`.
const START_VANISH: u32 = 1u;
const END_VANISH: u32 = 2u;
// `QueryKind::ALL` indices.
const CLOSEST: u32 = 0u;
const ANY: u32 = 1u;
const ALL: u32 = 2u;
const COUNT: u32 = 3u;
// `HitFormat::ALL` indices.
const BITMASK: u32 = 0u;
const HIT_T: u32 = 1u;
const HIT_T_TRIID: u32 = 2u;
const HIT_T_TRIID_U_V: u32 = 3u;
const HIT_T_TRIID_INSTID: u32 = 4u;
const HIT_T_TRIID_INSTID_U_V: u32 = 5u;
const HIT_FULL: u32 = 6u;
// `format::MISS_ID`, `format::MISS_T`.
const MISS_ID: u32 = 0xffffffffu;
const MISS_T: f32 = -1.0;
const BACK_FACE_BIT: u32 = 0x80000000u;

fn is_nan(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7fffffffu) > 0x7f800000u;
}

// Whether `x` is neither infinite nor NaN (bit test: a GPU compiler may assume no NaN in float comparisons).
fn is_finite_f32(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

fn infinity() -> f32 {
    return bitcast<f32>(0x7f800000u);
}

// A ray with the constants of the box and triangle tests (`intersect::PreparedRay`).
struct PreparedRay {
    origin: vec3<f32>,
    direction: vec3<f32>,
    tmin: f32,
    tmax: f32,
    time: f32,
    mask: u32,
    // Instance visibility (8 bits; 0xff for rays without one).
    visibility: u32,
    flags: u32,
    kx: u32,
    ky: u32,
    kz: u32,
    shear: vec3<f32>,
    inv_direction: vec3<f32>,
    // By axis, the row of a `Node`'s `boxes` where the ray enters the lanes' slabs (`lo` for a direction that is
    // not negative, `hi` otherwise), and where it leaves them.
    entry_rows: vec3<u32>,
    exit_rows: vec3<u32>,
}

fn ray_f32(word: u32) -> f32 {
    return bitcast<f32>(rays[word]);
}

fn ray_vec3(word: u32) -> vec3<f32> {
    return vec3<f32>(ray_f32(word), ray_f32(word + 1u), ray_f32(word + 2u));
}

// Decodes ray `index` of the chunk (`RayFormat::decode`) and prepares it (`PreparedRay::new`).
fn load_ray(index: u32) -> PreparedRay {
    let format = params.ray_format;
    // Words a ray: `RayFormat::size` / 4 of each format in `RayFormat::ALL` order (6, 8, 8, 9, 12).
    let words = select(select(select(8u, 6u, format == 0u), 9u, format == 3u), 12u, format == 4u);
    let base = index * words;
    var r: PreparedRay;
    r.origin = ray_vec3(base);
    r.tmin = 0.0;
    r.tmax = infinity();
    r.time = 0.0;
    r.mask = 0u;
    r.visibility = 0xffu;
    r.flags = 0u;
    if format == 0u {
        r.direction = ray_vec3(base + 3u);
    } else {
        r.direction = ray_vec3(base + 4u);
        r.tmax = ray_f32(base + 7u);
        if format == 2u {
            r.mask = rays[base + 3u];
        } else {
            r.tmin = ray_f32(base + 3u);
        }
        if format >= 3u {
            r.time = ray_f32(base + 8u);
        }
        if format == 4u {
            r.mask = rays[base + 9u];
            r.flags = rays[base + 10u] & 7u;
            r.visibility = rays[base + 11u] & 0xffu;
        }
    }
    r.flags = r.flags | params.query_flags;
    return oriented(r.origin, r.direction, r);
}

// `base` with another origin and direction (`PreparedRay::transformed`): the constants recomputed.
fn oriented(origin: vec3<f32>, direction: vec3<f32>, base: PreparedRay) -> PreparedRay {
    var r = base;
    r.origin = origin;
    r.direction = direction;
    let d = r.direction;
    // `intersect::PreparedRay::new`: a direction that is not finite hits nothing.
    if !(is_finite_f32(d.x) && is_finite_f32(d.y) && is_finite_f32(d.z)) {
        r.tmax = -infinity();
    }
    let a = abs(d);
    var kz = 2u;
    if a.x >= a.y && a.x >= a.z {
        kz = 0u;
    } else if a.y >= a.z {
        kz = 1u;
    }
    var kx = (kz + 1u) % 3u;
    var ky = (kx + 1u) % 3u;
    if d[kz] < 0.0 {
        let swap = kx;
        kx = ky;
        ky = swap;
    }
    r.kx = kx;
    r.ky = ky;
    r.kz = kz;
    r.shear = vec3<f32>(d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]);
    r.inv_direction = select(vec3<f32>(1.0) / d, vec3<f32>(infinity()), d == vec3<f32>(0.0));
    let negative = d < vec3<f32>(0.0);
    r.entry_rows = select(vec3<u32>(0u, 1u, 2u), vec3<u32>(3u, 4u, 5u), negative);
    r.exit_rows = select(vec3<u32>(3u, 4u, 5u), vec3<u32>(0u, 1u, 2u), negative);
    return r;
}

fn graph_f32(word: u32) -> f32 {
    return bitcast<f32>(graph[word]);
}

fn graph_vec3(word: u32) -> vec3<f32> {
    return vec3<f32>(graph_f32(word), graph_f32(word + 1u), graph_f32(word + 2u));
}

// The object record at word `offset` of `graph`.
fn load_object(offset: u32) -> Object {
    return Object(graph[offset], graph[offset + 1u], graph[offset + 2u], graph_f32(offset + 3u),
        graph_f32(offset + 4u), graph[offset + 5u], graph[offset + 6u], graph[offset + 7u], graph[offset + 8u],
        graph[offset + 9u]);
}

// Where a time falls among an object's keys (`MotionOptions::locate`).
struct KeyTime {
    present: bool,
    segment: u32,
    fraction: f32,
}

fn locate(object: Object, time: f32) -> KeyTime {
    let keys = object.keys;
    if !MOTION || keys <= 1u {
        return KeyTime(true, 0u, 0.0);
    }
    let last_segment = keys - 2u;
    if time > object.time_end {
        return KeyTime((object.motion_flags & END_VANISH) == 0u, last_segment, 1.0);
    }
    if time < object.time_begin || is_nan(time) {
        return KeyTime((object.motion_flags & START_VANISH) == 0u || is_nan(time), 0u, 0.0);
    }
    let u = (time - object.time_begin) / (object.time_end - object.time_begin) * f32(keys - 1u);
    let segment = min(u32(max(u, 0.0)), last_segment);
    return KeyTime(true, segment, clamp(u - f32(segment), 0.0, 1.0));
}

// `motion::lerp`.
fn lerp3(a: vec3<f32>, b: vec3<f32>, f: f32) -> vec3<f32> {
    return a * (1.0 - f) + b * f;
}

// An affine map (`glam::Affine3A`): `m · p + t`; `valid` is false where none exists (vanished, singular).
struct Affine {
    valid: bool,
    m: mat3x3<f32>,
    t: vec3<f32>,
}

fn is_finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

fn all_finite(v: vec3<f32>) -> bool {
    return is_finite(v.x) && is_finite(v.y) && is_finite(v.z);
}

// The map of the 12 floats (columns) at word `word` of `graph`.
fn affine_at(word: u32) -> Affine {
    return Affine(true, mat3x3<f32>(graph_vec3(word), graph_vec3(word + 3u), graph_vec3(word + 6u)),
        graph_vec3(word + 9u));
}

// The world-to-object map of an object-to-world map (`Placement::from_affine`, glam's inverse): invalid when
// singular or when the inverse is not finite.
fn world_to_object(a: Affine) -> Affine {
    let x = a.m[0];
    let y = a.m[1];
    let z = a.m[2];
    let tmp0 = cross(y, z);
    let tmp1 = cross(z, x);
    let tmp2 = cross(x, y);
    let det = dot(z, tmp2);
    if det == 0.0 || !is_finite(det) {
        return Affine(false, a.m, a.t);
    }
    let inv_det = 1.0 / det;
    let m = transpose(mat3x3<f32>(tmp0 * inv_det, tmp1 * inv_det, tmp2 * inv_det));
    let t = -(m * a.t);
    let valid = all_finite(m[0]) && all_finite(m[1]) && all_finite(m[2]) && all_finite(t);
    return Affine(valid, m, t);
}

// `interpolate_affine`: matrix motion keys at `first` and `next`, per element.
fn matrix_key(first: u32, next: u32, f: f32) -> Affine {
    let a = affine_at(first);
    let b = affine_at(next);
    return Affine(true, mat3x3<f32>(lerp3(a.m[0], b.m[0], f), lerp3(a.m[1], b.m[1], f), lerp3(a.m[2], b.m[2], f)),
        lerp3(a.t, b.t, f));
}

fn graph_vec4(word: u32) -> vec4<f32> {
    return vec4<f32>(graph_f32(word), graph_f32(word + 1u), graph_f32(word + 2u), graph_f32(word + 3u));
}

// `SrtKey::interpolate` then `SrtKey::combined` (C = T·R·S) of the SRT keys at `first` and `next`.
fn srt_key(first: u32, next: u32, f: f32) -> Affine {
    var s: array<f32, 9>;
    for (var i = 0u; i < 9u; i++) {
        s[i] = graph_f32(first + i) * (1.0 - f) + graph_f32(next + i) * f;
    }
    let blended = graph_vec4(first + 9u) * (1.0 - f) + graph_vec4(next + 9u) * f;
    let q = blended * (1.0 / length(blended));
    let t = lerp3(graph_vec3(first + 13u), graph_vec3(next + 13u), f);
    // `Mat3A::from_quat`.
    let x2 = q.x + q.x;
    let y2 = q.y + q.y;
    let z2 = q.z + q.z;
    let xx = q.x * x2;
    let xy = q.x * y2;
    let xz = q.x * z2;
    let yy = q.y * y2;
    let yz = q.y * z2;
    let zz = q.z * z2;
    let wx = q.w * x2;
    let wy = q.w * y2;
    let wz = q.w * z2;
    let r = mat3x3<f32>(
        vec3<f32>(1.0 - (yy + zz), xy + wz, xz - wy),
        vec3<f32>(xy - wz, 1.0 - (xx + zz), yz + wx),
        vec3<f32>(xz + wy, yz - wx, 1.0 - (xx + yy)),
    );
    // S: `sx a b | sy c | sz` and the pivot.
    let scale = mat3x3<f32>(vec3<f32>(s[0], 0.0, 0.0), vec3<f32>(s[1], s[3], 0.0), vec3<f32>(s[2], s[4], s[5]));
    let pivot = vec3<f32>(s[6], s[7], s[8]);
    return Affine(true, r * scale, r * pivot + t);
}

// A transform object's world-to-object map at `time` (`Transform::placement_at`).
fn transform_at(object: Object, time: f32) -> Affine {
    if object.kind == OBJECT_STATIC_TRANSFORM {
        return affine_at(object.base);
    }
    let k = locate(object, time);
    if !k.present {
        return Affine(false, mat3x3<f32>(), vec3<f32>());
    }
    let next = min(k.segment + 1u, object.keys - 1u);
    if object.kind == OBJECT_MATRIX_TRANSFORM {
        return world_to_object(matrix_key(object.base + k.segment * 12u, object.base + next * 12u, k.fraction));
    }
    return world_to_object(srt_key(object.base + k.segment * 16u, object.base + next * 16u, k.fraction));
}

// The traversal's current level: its object, where the ray's time falls in its keys, the ray in its space, and
// what the instances above change about its hits (`query::InstanceScope`).
var<private> cur: Object;
var<private> cur_at: KeyTime;
var<private> cur_ray: PreparedRay;
var<private> flip_facing: bool;
var<private> no_culling: bool;
// Per level (0 the traced accel's): its object, what entered it (an instance record's offset, or
// `TRANSFORM_RECORD` and a transform's object), the ray's origin and direction in its space, and (bit `level`)
// its facing and culling state.
var<private> level: u32;
var<private> level_object: array<u32, MAX_LEVELS>;
var<private> level_record: array<u32, MAX_LEVELS>;
var<private> level_origin: array<vec3<f32>, MAX_LEVELS>;
var<private> level_direction: array<vec3<f32>, MAX_LEVELS>;
var<private> flip_bits: u32;
var<private> no_culling_bits: u32;
// The traversal stack.
var<private> stack: array<vec2<u32>, STACK_SIZE>;
var<private> stack_len: u32;

fn box_corner(word: u32) -> vec3<f32> {
    return vec3<f32>(node_boxes[word], node_boxes[word + 1u], node_boxes[word + 2u]);
}

// The entry and exit distances of four boxes, narrowed one axis at a time.
struct Slabs {
    near: vec4<f32>,
    far: vec4<f32>,
}

// `slabs` narrowed by the boxes' planes where the ray enters (`entry`) and leaves (`exit`) them along the axis
// whose ray origin and inverse direction are given (`intersect::aabb::intersect`'s loop body, four lanes at once).
fn slab(slabs: Slabs, entry: vec4<f32>, exit: vec4<f32>, o: f32, inv: f32) -> Slabs {
    return Slabs(max(slabs.near, (entry - o) * inv), min(slabs.far, (exit - o) * inv));
}

// Which lanes of a node the ray enters within `[ray.tmin, tmax]`, and where; the lanes' indices and counts.
struct LaneHits {
    entered: vec4<bool>,
    near: vec4<f32>,
    index: vec4<u32>,
    count: vec4<u32>,
}

// Lanes of a node that hold a child (the boxes a node visit tests, as the CPU counts them).
fn occupied(index: vec4<u32>) -> u32 {
    let full = index != vec4<u32>(EMPTY_LANE);
    return u32(full.x) + u32(full.y) + u32(full.z) + u32(full.w);
}

// Lane `lane` of `v`, chosen with selects.
fn lane_of(v: vec4<u32>, lane: u32) -> u32 {
    return select(select(select(v.w, v.z, lane == 2u), v.y, lane == 1u), v.x, lane == 0u);
}

// The lanes' boxes of node `node` of the current object, a moving BVH's, at the ray's time (interpolated between
// its motion keys), as a `Node`'s rows.
fn moving_boxes(node: u32) -> LaneRows {
    var b: LaneRows;
    for (var lane = 0u; lane < NODE_WIDTH; lane++) {
        let first = cur.box_base + (((node - cur.first) * NODE_WIDTH + lane) * cur.keys + cur_at.segment) * 6u;
        let lo = lerp3(box_corner(first), box_corner(first + 6u), cur_at.fraction);
        let hi = lerp3(box_corner(first + 3u), box_corner(first + 9u), cur_at.fraction);
        b[0][lane] = lo.x;
        b[1][lane] = lo.y;
        b[2][lane] = lo.z;
        b[3][lane] = hi.x;
        b[4][lane] = hi.y;
        b[5][lane] = hi.z;
    }
    return b;
}

// Node `node`'s lanes tested against `[ray.tmin, tmax]` (`intersect::aabb::intersect`, same operations, same
// NaN rule, same slack); empty lanes are never entered.
fn test_lanes(node: u32, tmax: f32) -> LaneHits {
    let r = cur_ray;
    let index = nodes[node].index;
    let count = nodes[node].count;
    var slabs = Slabs(vec4<f32>(r.tmin), vec4<f32>(tmax));
    if MOTION && cur.keys > 1u {
        let b = moving_boxes(node);
        let n = r.direction < vec3<f32>(0.0);
        slabs = slab(slabs, select(b[0], b[3], n.x), select(b[3], b[0], n.x), r.origin.x, r.inv_direction.x);
        slabs = slab(slabs, select(b[1], b[4], n.y), select(b[4], b[1], n.y), r.origin.y, r.inv_direction.y);
        slabs = slab(slabs, select(b[2], b[5], n.z), select(b[5], b[2], n.z), r.origin.z, r.inv_direction.z);
    } else {
        // The rows the ray needs, read where they lie rather than chosen with selects.
        let boxes = &nodes[node].boxes;
        let entry = r.entry_rows;
        let exit = r.exit_rows;
        slabs = slab(slabs, (*boxes)[entry.x], (*boxes)[exit.x], r.origin.x, r.inv_direction.x);
        slabs = slab(slabs, (*boxes)[entry.y], (*boxes)[exit.y], r.origin.y, r.inv_direction.y);
        slabs = slab(slabs, (*boxes)[entry.z], (*boxes)[exit.z], r.origin.z, r.inv_direction.z);
    }
    let near = slabs.near - abs(slabs.near) * SLACK;
    let far = slabs.far + abs(slabs.far) * SLACK;
    return LaneHits((near <= far) & (index != vec4<u32>(EMPTY_LANE)), near, index, count);
}


// Triangle slot `slot` of geometry object `object`, its corners at `at`.
fn triangle_at(object: Object, slot: u32, at: KeyTime) -> array<vec3<f32>, 3> {
    let first = object.corner_base + ((slot - object.base) * object.keys + at.segment) * 3u;
    if !MOTION || object.keys <= 1u {
        return array<vec3<f32>, 3>(corners[first].xyz, corners[first + 1u].xyz, corners[first + 2u].xyz);
    }
    let f = at.fraction;
    return array<vec3<f32>, 3>(
        lerp3(corners[first].xyz, corners[first + 3u].xyz, f),
        lerp3(corners[first + 1u].xyz, corners[first + 4u].xyz, f),
        lerp3(corners[first + 2u].xyz, corners[first + 5u].xyz, f),
    );
}

// `a·b − c·d` with one rounding, from the exact products' error terms (the CPU recomputes it in f64).
fn exact_difference(a: f32, b: f32, c: f32, d: f32) -> f32 {
    let ab = a * b;
    let cd = c * d;
    return (ab - cd) + (fma(a, b, -ab) - fma(c, d, -cd));
}

// `triangle::perturbed_sign`.
fn perturbed_sign(p: vec2<f32>, q: vec2<f32>) -> f32 {
    let e = q - p;
    if e.y != 0.0 {
        return -sign(e.y);
    }
    if e.x != 0.0 {
        return sign(e.x);
    }
    return 0.0;
}

fn on_edge_inside(f: f32, s: f32, p: vec2<f32>, q: vec2<f32>) -> bool {
    return f != 0.0 || s * perturbed_sign(p, q) > 0.0;
}

// An intersection before range and culling checks (`triangle::TriangleHit`).
struct TriangleHit {
    hit: bool,
    t: f32,
    u: f32,
    v: f32,
    back_face: bool,
}

const NO_TRIANGLE_HIT = TriangleHit(false, 0.0, 0.0, 0.0, false);

// Component `k` of `v`, chosen with selects rather than a dynamic index (which a compiler may put in memory).
fn component(v: vec3<f32>, k: u32) -> f32 {
    return select(select(v.z, v.y, k == 1u), v.x, k == 0u);
}

// The watertight test with the edge rule (`triangle::intersect`).
fn intersect_triangle(ray: PreparedRay, tri: array<vec3<f32>, 3>) -> TriangleHit {
    let kx = ray.kx;
    let ky = ray.ky;
    let kz = ray.kz;
    let a = tri[0] - ray.origin;
    let b = tri[1] - ray.origin;
    let c = tri[2] - ray.origin;
    let sx = ray.shear.x;
    let sy = ray.shear.y;
    let sz = ray.shear.z;
    let ax = component(a, kx) - sx * component(a, kz);
    let ay = component(a, ky) - sy * component(a, kz);
    let bx = component(b, kx) - sx * component(b, kz);
    let by = component(b, ky) - sy * component(b, kz);
    let cx = component(c, kx) - sx * component(c, kz);
    let cy = component(c, ky) - sy * component(c, kz);
    var u = cx * by - cy * bx;
    var v = ax * cy - ay * cx;
    var w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        u = exact_difference(cx, by, cy, bx);
        v = exact_difference(ax, cy, ay, cx);
        w = exact_difference(bx, ay, by, ax);
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return NO_TRIANGLE_HIT;
    }
    let det = u + v + w;
    if det == 0.0 || !is_finite_f32(det) {
        return NO_TRIANGLE_HIT;
    }
    if u == 0.0 || v == 0.0 || w == 0.0 {
        let s = sign(det);
        let pa = vec2<f32>(ax, ay);
        let pb = vec2<f32>(bx, by);
        let pc = vec2<f32>(cx, cy);
        if !(on_edge_inside(u, s, pc, pb) && on_edge_inside(v, s, pa, pc) && on_edge_inside(w, s, pb, pa)) {
            return NO_TRIANGLE_HIT;
        }
    }
    let az = sz * component(a, kz);
    let bz = sz * component(b, kz);
    let cz = sz * component(c, kz);
    let t = (u * az + v * bz + w * cz) / det;
    if !is_finite_f32(t) {
        return NO_TRIANGLE_HIT;
    }
    return TriangleHit(true, t, v / det, w / det, det < 0.0);
}

// The collector of one ray (`query::Collector`), in private variables.
var<private> kind: u32;
var<private> ray_tmax: f32;
var<private> ray_time: f32;
var<private> terminate_on_first_hit: bool;
var<private> has_best: bool;
var<private> best_t: f32;
var<private> best_slot: u32;
var<private> best_u: f32;
var<private> best_v: f32;
var<private> best_back: bool;
// The levels and level records of the best hit's place (`level`, `level_record` when it was offered).
var<private> best_levels: u32;
var<private> best_records: array<u32, MAX_LEVELS>;
var<private> hit_count: u32;
// For `all`: the first entry of this ray's sorted hits in `scratch`, and how many are in use.
var<private> sorted_base: u32;
var<private> sorted_len: u32;
var<private> done: bool;

// `Collector::cull_tmax`.
fn cull_tmax() -> f32 {
    if kind == CLOSEST && has_best {
        return best_t;
    }
    return ray_tmax;
}

// An instance path (`format::InstancePath`): user ids top to bottom, then `MISS_ID`.
struct Path {
    ids: array<u32, MAX_LEVELS>,
    len: u32,
}

// The instance path of the place that `levels` level records describe (transforms add no id).
fn path_of(records: array<u32, MAX_LEVELS>, levels: u32) -> Path {
    var path: Path;
    for (var i = 0u; i < MAX_LEVELS; i++) {
        path.ids[i] = MISS_ID;
    }
    path.len = 0u;
    for (var l = 1u; l <= levels; l++) {
        let record = records[l];
        if (record & TRANSFORM_RECORD) == 0u {
            path.ids[path.len] = graph[record + 12u];
            path.len += 1u;
        }
    }
    return path;
}

// Whether path `a` orders before `b` (`InstancePath`'s derived order: ids, then length); `equal` when neither.
struct Order {
    less: bool,
    equal: bool,
}

fn compare_paths(a: Path, b: Path) -> Order {
    for (var i = 0u; i < MAX_LEVELS; i++) {
        if a.ids[i] != b.ids[i] {
            return Order(a.ids[i] < b.ids[i], false);
        }
    }
    return Order(a.len < b.len, a.len == b.len);
}

// A hit of the collector: where it is (slot, level records) and what it reports.
struct Entry {
    t: f32,
    slot: u32,
    u: f32,
    v: f32,
    back_face: bool,
    levels: u32,
    records: array<u32, MAX_LEVELS>,
}

// Whether `a` is reported before `b` (`collect::precedes`): smaller t, then instance path, geometry id, primitive id.
fn precedes(a: Entry, b: Entry) -> bool {
    if a.t != b.t {
        return a.t < b.t;
    }
    let paths = compare_paths(path_of(a.records, a.levels), path_of(b.records, b.levels));
    if !paths.equal {
        return paths.less;
    }
    let pa = prims[a.slot];
    let pb = prims[b.slot];
    if pa.geom_id != pb.geom_id {
        return pa.geom_id < pb.geom_id;
    }
    return pa.prim_id < pb.prim_id;
}

// Entry `i` of `scratch`: `(t, slot | back face, u, v)`, `(levels, records 1–3)`, `(records 4–7)`.
fn load_entry(i: u32) -> Entry {
    let a = scratch[3u * i];
    let b = scratch[3u * i + 1u];
    let c = scratch[3u * i + 2u];
    let records = array<u32, MAX_LEVELS>(0u, b.y, b.z, b.w, c.x, c.y, c.z, c.w);
    return Entry(bitcast<f32>(a.x), a.y & ~BACK_FACE_BIT, bitcast<f32>(a.z), bitcast<f32>(a.w),
        (a.y & BACK_FACE_BIT) != 0u, b.x, records);
}

fn store_entry(i: u32, e: Entry) {
    let r = e.records;
    scratch[3u * i] = vec4<u32>(bitcast<u32>(e.t), e.slot | select(0u, BACK_FACE_BIT, e.back_face), bitcast<u32>(e.u),
        bitcast<u32>(e.v));
    scratch[3u * i + 1u] = vec4<u32>(e.levels, r[1], r[2], r[3]);
    scratch[3u * i + 2u] = vec4<u32>(r[4], r[5], r[6], r[7]);
}

// `Collector::insert_sorted`.
fn insert_sorted(entry: Entry) {
    let capacity = params.records_per_ray;
    if sorted_len == capacity && !precedes(entry, load_entry(sorted_base + capacity - 1u)) {
        return;
    }
    var position = min(sorted_len, capacity - 1u);
    loop {
        if position == 0u {
            break;
        }
        let previous = load_entry(sorted_base + position - 1u);
        if !precedes(entry, previous) {
            break;
        }
        store_entry(sorted_base + position, previous);
        position -= 1u;
    }
    store_entry(sorted_base + position, entry);
    sorted_len = min(sorted_len + 1u, capacity);
}

// The best hit so far as an entry.
fn best_entry() -> Entry {
    return Entry(best_t, best_slot, best_u, best_v, best_back, best_levels, best_records);
}

// `Collector::offer`, for a hit at the current level.
fn offer(t: f32, slot: u32, u: f32, v: f32, back_face: bool) {
    if hit_count != 0xffffffffu {
        hit_count += 1u;
    }
    done = terminate_on_first_hit || kind == ANY;
    let entry = Entry(t, slot, u, v, back_face, level, level_record);
    if kind == ALL {
        insert_sorted(entry);
    } else if kind == ANY && has_best {
        // Keep the first hit found.
    } else if !has_best || precedes(entry, best_entry()) {
        has_best = true;
        best_t = t;
        best_slot = slot;
        best_u = u;
        best_v = v;
        best_back = back_face;
        best_levels = level;
        if LEVELS {
            best_records = level_record;
        }
    }
}

// `query::consider_triangle`: mask, intersection, range, culling (facing as the instances above decide it).
fn consider_triangle(slot: u32) {
    // The slot's ids and flags are read only when the ray's mask or culling flags need them.
    if cur_ray.mask != 0u && (cur_ray.mask & prims[slot].mask) != 0u {
        return;
    }
    let hit = intersect_triangle(cur_ray, triangle_at(cur, slot, cur_at));
    if !hit.hit {
        return;
    }
    if !(hit.t >= cur_ray.tmin && hit.t <= cull_tmax()) {
        return;
    }
    let back_face = hit.back_face != flip_facing;
    let culling = cur_ray.flags & (CULL_BACK_FACING | CULL_FRONT_FACING);
    if culling != 0u && !no_culling && (prims[slot].geometry_flags & DISABLE_FACE_CULLING) == 0u {
        let culled = select(CULL_FRONT_FACING, CULL_BACK_FACING, back_face);
        if (cur_ray.flags & culled) != 0u {
            return;
        }
    }
    offer(hit.t, slot, hit.u, hit.v, back_face);
}

// What the walk did, for the statistics and `params.max_ray_work`.
var<private> nodes_visited: u32;
var<private> triangle_tests: u32;

// Whether the ray has taken more than `params.max_ray_work` node visits and triangle tests; if so its walk ends
// (the stack emptied). Asked at each leaf and each instance leaf, which every walk past the work reaches often: the
// nodes between them are no more than a BVH holds.
fn past_work() -> bool {
    let past = nodes_visited + triangle_tests > params.max_ray_work;
    if past {
        stack_len = 0u;
    }
    return past;
}

fn push(a: u32, b: u32) {
    stack[stack_len] = vec2<u32>(a, b);
    stack_len += 1u;
}

// Moves one level down, into the child object `child` that `record` places with `to` (world to object) and
// instance flags `flags`; pushes the marker that restores the current level.
fn descend(record: u32, child: u32, to: Affine, flags: u32) {
    push(MARKER, 0u);
    let origin = to.m * level_origin[level] + to.t;
    let direction = to.m * level_direction[level];
    level += 1u;
    level_object[level] = child;
    level_record[level] = record;
    level_origin[level] = origin;
    level_direction[level] = direction;
    flip_facing = flip_facing != ((flags & INSTANCE_FLIP_FACING) != 0u);
    no_culling = no_culling || (flags & INSTANCE_DISABLE_FACE_CULLING) != 0u;
    let bit = 1u << level;
    flip_bits = select(flip_bits & ~bit, flip_bits | bit, flip_facing);
    no_culling_bits = select(no_culling_bits & ~bit, no_culling_bits | bit, no_culling);
    cur_ray = oriented(origin, direction, cur_ray);
}

// Back to the level above (a marker was popped).
fn restore() {
    level -= 1u;
    cur_ray = oriented(level_origin[level], level_direction[level], cur_ray);
    cur = load_object(level_object[level]);
    cur_at = locate(cur, ray_time);
    flip_facing = ((flip_bits >> level) & 1u) != 0u;
    no_culling = ((no_culling_bits >> level) & 1u) != 0u;
}

// Enters object `first` at the current level (through any transforms, each a level further down): the root node
// of the BVH to walk (its lanes test the ray against the root's children), or `NONE` when the ray cannot reach
// anything in it at its time.
fn enter(first: u32) -> u32 {
    var object = first;
    loop {
        cur = load_object(object);
        if LEVELS && cur.kind >= OBJECT_STATIC_TRANSFORM {
            let to = transform_at(cur, ray_time);
            if !to.valid {
                return NONE;
            }
            descend(TRANSFORM_RECORD | object, cur.first, to, 0u);
            object = cur.first;
            continue;
        }
        cur_at = locate(cur, ray_time);
        if !cur_at.present || cur.node_count == 0u {
            return NONE;
        }
        break;
    }
    return cur.first;
}

// Visits instances `first .. end` of the current instance accel: enters the first one the ray sees (after pushing
// a resume entry for the rest); `NONE` when none is seen, its child holds nothing to walk or the ray is past its
// work ([`past_work`]).
fn visit_instances(first: u32, end: u32) -> u32 {
    if past_work() {
        return NONE;
    }
    for (var slot = first; slot < end; slot++) {
        let record = cur.base + slot * INSTANCE_WORDS;
        if (cur_ray.visibility & graph[record + 13u]) == 0u {
            continue;
        }
        if slot + 1u < end {
            push(RESUME | (slot + 1u), end);
        }
        let child = graph[record + 15u];
        descend(record, child, affine_at(record), graph[record + 14u]);
        return enter(child);
    }
    return NONE;
}

// Sort keys of the lanes that the ray enters (`0xffffffff` for the others): the entry distance's bits made to order
// as unsigned integers (sign bit flipped, or every bit for a negative distance), the lane in the two lowest bits.
fn lane_keys(hits: LaneHits) -> vec4<u32> {
    let bits = bitcast<vec4<u32>>(hits.near);
    let ordered = bits ^ select(vec4<u32>(0x80000000u), vec4<u32>(0xffffffffu), bits >= vec4<u32>(0x80000000u));
    let keys = (ordered & vec4<u32>(~3u)) | vec4<u32>(0u, 1u, 2u, 3u);
    return select(vec4<u32>(0xffffffffu), keys, hits.entered);
}

// The entry distance of a lane key: the lane's own rounded down by its two lowest bits, never above it, so the pop
// re-check (`near > cull_tmax()`) never drops a lane that the exact distance would keep; only ties within four
// units in the last place are ordered by lane.
fn key_distance(key: u32) -> f32 {
    let ordered = key & ~3u;
    return bitcast<f32>(ordered ^ select(0xffffffffu, 0x80000000u, ordered >= 0x80000000u));
}

// Sorts the lanes of node `node` that the ray enters by entry distance (then lane, on equal keys), pushes all but
// the nearest (farthest first, so the nearer pop first) and returns the nearest's lane reference (`node ·
// NODE_WIDTH + lane`), or `NONE` when the ray enters none. Four keys, five compare-exchanges, no branches.
fn push_lanes(node: u32, hits: LaneHits) -> u32 {
    let keys = lane_keys(hits);
    let low = min(keys.xz, keys.yw);
    let high = max(keys.xz, keys.yw);
    let k0 = min(low.x, low.y);
    let k3 = max(high.x, high.y);
    let k1 = min(max(low.x, low.y), min(high.x, high.y));
    let k2 = max(max(low.x, low.y), min(high.x, high.y));
    let entered = u32(hits.entered.x) + u32(hits.entered.y) + u32(hits.entered.z) + u32(hits.entered.w);
    let base = node * NODE_WIDTH;
    if entered > 3u {
        push(base + (k3 & 3u), bitcast<u32>(key_distance(k3)));
    }
    if entered > 2u {
        push(base + (k2 & 3u), bitcast<u32>(key_distance(k2)));
    }
    if entered > 1u {
        push(base + (k1 & 3u), bitcast<u32>(key_distance(k1)));
    }
    return select(NONE, base + (k0 & 3u), entered > 0u);
}

// A leaf lane's triangle slots.
struct Slots {
    first: u32,
    end: u32,
}

// Walks nodes until it reaches a geometry leaf the ray enters, which it returns; an empty range when the walk is
// over. `current` is the node whose lanes are tested next (`NONE`: the next lane comes off the stack), the stack
// holds the lanes entered but not yet visited, nearest on top. Inner lanes, instance leaves and markers are handled
// here, so that the threads of a subgroup test nodes together and triangles together (a while-while walk).
fn next_leaf(current_node: u32) -> Slots {
    var current = current_node;
    loop {
        // The lane to visit: its index and count.
        var index: u32;
        var count: u32;
        if current != NONE {
            let hits = test_lanes(current, cull_tmax());
            nodes_visited += occupied(hits.index);
            let lane_ref = push_lanes(current, hits);
            current = NONE;
            if lane_ref == NONE {
                continue;
            }
            index = lane_of(hits.index, lane_ref % NODE_WIDTH);
            count = lane_of(hits.count, lane_ref % NODE_WIDTH);
        } else {
            if stack_len == 0u {
                return Slots(0u, 0u);
            }
            stack_len -= 1u;
            let entry = stack[stack_len];
            let a = entry.x;
            let b = entry.y;
            if LEVELS && a == MARKER {
                restore();
                continue;
            }
            if LEVELS && (a & RESUME) != 0u {
                current = visit_instances(a & ~RESUME, b);
                continue;
            }
            if bitcast<f32>(b) > cull_tmax() {
                continue;
            }
            index = nodes[a / NODE_WIDTH].index[a % NODE_WIDTH];
            count = nodes[a / NODE_WIDTH].count[a % NODE_WIDTH];
        }
        if count == 0u {
            current = index;
        } else if LEVELS && cur.kind != OBJECT_TRIANGLES {
            current = visit_instances(index, index + count);
        } else {
            return Slots(index, index + count);
        }
    }
    return Slots(0u, 0u);
}

// The walk of `traverse::walk` through every level of the graph: leaf after leaf, nearest first.
fn traverse(world: PreparedRay) {
    cur_ray = world;
    level = 0u;
    level_object[0] = params.root;
    level_origin[0] = world.origin;
    level_direction[0] = world.direction;
    flip_facing = false;
    no_culling = false;
    flip_bits = 0u;
    no_culling_bits = 0u;
    stack_len = 0u;
    var current = enter(params.root);
    loop {
        let leaf = next_leaf(current);
        current = NONE;
        if leaf.first == leaf.end || past_work() {
            return;
        }
        for (var slot = leaf.first; slot < leaf.end; slot++) {
            triangle_tests += 1u;
            consider_triangle(slot);
            if done {
                return;
            }
        }
    }
}

fn store(word: u32, value: u32) {
    atomicStore(&hits[word], value);
}

// The object a level record places: an instance's child, or a transform's.
fn child_of(record: u32) -> u32 {
    if (record & TRANSFORM_RECORD) != 0u {
        return graph[(record & ~TRANSFORM_RECORD) + 5u];
    }
    return graph[record + 15u];
}

// A hit's unit normal in world space, on its front side (`consider_triangle`'s normal, `normalize_or_zero`).
fn world_normal(e: Entry) -> vec3<f32> {
    var object = params.root;
    if e.levels > 0u {
        object = child_of(e.records[e.levels]);
    }
    let geometry = load_object(object);
    let tri = triangle_at(geometry, e.slot, locate(geometry, ray_time));
    var n = cross(tri[1] - tri[0], tri[2] - tri[0]);
    var flipped = false;
    for (var l = e.levels; l > 0u; l--) {
        let record = e.records[l];
        var to: Affine;
        if (record & TRANSFORM_RECORD) != 0u {
            to = transform_at(load_object(record & ~TRANSFORM_RECORD), ray_time);
        } else {
            to = affine_at(record);
            flipped = flipped != ((graph[record + 14u] & INSTANCE_FLIP_FACING) != 0u);
        }
        // The normal-to-world map is the world-to-object map's transpose.
        n = transpose(to.m) * n;
    }
    if flipped {
        n = -n;
    }
    let rcp = 1.0 / length(n);
    if !is_nan(rcp) && rcp != infinity() && rcp > 0.0 {
        return n * rcp;
    }
    return vec3<f32>(0.0);
}

// Writes hit record `record` of the chunk (`HitFormat::write`); a miss when `present` is false.
fn write_record(record: u32, present: bool, e: Entry) {
    let format = params.hit_format;
    if format == BITMASK {
        if present {
            atomicOr(&hits[record / 32u], 1u << (record % 32u));
        }
        return;
    }
    var prim = Prim(MISS_ID, MISS_ID, 0u, 0u);
    var hit_t = MISS_T;
    var hit_u = 0.0;
    var hit_v = 0.0;
    var path: Path;
    for (var i = 0u; i < MAX_LEVELS; i++) {
        path.ids[i] = MISS_ID;
    }
    path.len = 0u;
    if present {
        prim = prims[e.slot];
        hit_t = e.t;
        hit_u = e.u;
        hit_v = e.v;
        path = path_of(e.records, e.levels);
    }
    var inst_id = MISS_ID;
    if path.len > 0u {
        inst_id = path.ids[path.len - 1u];
    }
    let w = record * params.record_words;
    store(w, bitcast<u32>(hit_t));
    switch format {
        case HIT_T_TRIID: {
            store(w + 1u, prim.prim_id);
        }
        case HIT_T_TRIID_U_V: {
            store(w + 1u, prim.prim_id);
            store(w + 2u, bitcast<u32>(hit_u));
            store(w + 3u, bitcast<u32>(hit_v));
        }
        case HIT_T_TRIID_INSTID: {
            store(w + 1u, prim.prim_id);
            store(w + 2u, inst_id);
        }
        case HIT_T_TRIID_INSTID_U_V: {
            store(w + 1u, prim.prim_id);
            store(w + 2u, inst_id);
            store(w + 3u, bitcast<u32>(hit_u));
            store(w + 4u, bitcast<u32>(hit_v));
        }
        case HIT_FULL: {
            var normal = vec3<f32>(0.0);
            if FULL_HITS && present {
                normal = world_normal(e);
            }
            store(w + 1u, prim.prim_id);
            store(w + 2u, prim.geom_id);
            store(w + 3u, inst_id);
            store(w + 4u, bitcast<u32>(hit_u));
            store(w + 5u, bitcast<u32>(hit_v));
            store(w + 6u, bitcast<u32>(normal.x));
            store(w + 7u, bitcast<u32>(normal.y));
            store(w + 8u, bitcast<u32>(normal.z));
            store(w + 9u, select(0u, 1u, present && e.back_face));
            store(w + 10u, path.len);
            store(w + 11u, 0u);
            for (var i = 0u; i < 8u; i++) {
                store(w + 12u + i, path.ids[i]);
            }
        }
        default: {}
    }
}

// Writes ray `index`'s records and count (`Collector::write`).
fn write_ray(index: u32) {
    let first = index * params.records_per_ray;
    if kind == ALL {
        for (var slot = 0u; slot < params.records_per_ray; slot++) {
            write_record(first + slot, slot < sorted_len, load_entry(sorted_base + slot));
        }
    } else {
        write_record(first, has_best, best_entry());
    }
    if kind == ALL || kind == COUNT {
        atomicStore(&tallies[TALLY_WORDS + index], hit_count);
    }
}

// Per workgroup: rays hit, nodes visited, triangle tests, added to the tallies once.
var<workgroup> group_tallies: array<atomic<u32>, 3>;

// Adds `value` to the 64-bit tally at words `low`, `low + 1`.
fn add_wide(low: u32, value: u32) {
    let before = atomicAdd(&tallies[low], value);
    if before > 0xffffffffu - value {
        atomicAdd(&tallies[low + 1u], 1u);
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn trace(@builtin(global_invocation_id) global: vec3<u32>, @builtin(local_invocation_index) local: u32) {
    if local == 0u {
        atomicStore(&group_tallies[0], 0u);
        atomicStore(&group_tallies[1], 0u);
        atomicStore(&group_tallies[2], 0u);
    }
    workgroupBarrier();
    let index = global.x;
    if index < params.ray_count {
        var ray: PreparedRay;
        if GENERATOR == GENERATOR_NONE {
            ray = load_ray(index);
        } else {
            ray = generated_ray(index);
        }
        kind = QUERY_KIND;
        ray_tmax = ray.tmax;
        ray_time = ray.time;
        terminate_on_first_hit = (ray.flags & TERMINATE_ON_FIRST_HIT) != 0u;
        has_best = false;
        best_levels = 0u;
        hit_count = 0u;
        sorted_base = index * params.records_per_ray;
        sorted_len = 0u;
        done = false;
        nodes_visited = 0u;
        triangle_tests = 0u;
        traverse(ray);
        write_ray(index);
        // Stopped at its work, or past it when its walk ended.
        if nodes_visited + triangle_tests > params.max_ray_work {
            atomicAdd(&tallies[OVER_RAY_WORK], 1u);
        }
        atomicAdd(&group_tallies[0], select(0u, 1u, hit_count > 0u));
        atomicAdd(&group_tallies[1], nodes_visited);
        atomicAdd(&group_tallies[2], triangle_tests);
    }
    workgroupBarrier();
    if local == 0u {
        atomicAdd(&tallies[0], atomicLoad(&group_tallies[0]));
        add_wide(1u, atomicLoad(&group_tallies[1]));
        add_wide(3u, atomicLoad(&group_tallies[2]));
    }
}
