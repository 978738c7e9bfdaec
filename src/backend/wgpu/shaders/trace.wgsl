// The trace pipeline: one thread a ray. It decodes the ray from the caller's packed bytes, walks the geometry
// accel's BVH as `src/backend/cpu/traverse.rs` does (nearer child first, same box test, same pop re-check),
// tests triangles as `src/intersect/triangle.rs` does, collects hits as `src/query/collect.rs` does and writes
// the caller's hit format. Prepended by `layout.wgsl`.

// The accel (uploaded once; `layout::GpuTriangles`).
@group(0) @binding(0) var<storage, read> nodes: array<Node>;
// With motion: node `i`'s box at key `k` is the 6 floats (min.xyz, max.xyz) at `(i·keys + k)·6`.
@group(0) @binding(1) var<storage, read> node_boxes: array<f32>;
// Triangle slot `s`'s corners at key `k`: the 9 floats (v0, v1, v2) at `(s·keys + k)·9`.
@group(0) @binding(2) var<storage, read> corners: array<f32>;
@group(0) @binding(3) var<storage, read> prims: array<Prim>;

// The chunk (`batch::Slot`).
@group(1) @binding(0) var<uniform> params: Params;
// The caller's rays, packed in `params.ray_format`.
@group(1) @binding(1) var<storage, read> rays: array<u32>;
// The caller's hit records, packed in `params.hit_format` (atomic for the bitmask's shared words).
@group(1) @binding(2) var<storage, read_write> hits: array<atomic<u32>>;
// `TALLY_WORDS` words of statistics, then one count a ray.
@group(1) @binding(3) var<storage, read_write> tallies: array<atomic<u32>>;
// For `all` queries: `records_per_ray` sorted hits a ray, each (t bits, slot | back face << 31, u bits, v bits).
@group(1) @binding(4) var<storage, read_write> scratch: array<vec4<u32>>;

// Entries of the traversal stack: the kernel refuses accels deeper than this (`kernel::STACK_SIZE`).
const STACK_SIZE: u32 = 64u;
// `intersect::aabb::SLACK`.
const SLACK: f32 = 1e-6;
// `RayFlags`.
const CULL_BACK_FACING: u32 = 1u;
const CULL_FRONT_FACING: u32 = 2u;
const TERMINATE_ON_FIRST_HIT: u32 = 4u;
// `GeometryFlags::DISABLE_FACE_CULLING`.
const DISABLE_FACE_CULLING: u32 = 1u;
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

// `f32::max` / `f32::min`: a NaN operand is ignored.
fn max_num(a: f32, b: f32) -> f32 {
    return select(max(a, b), a, is_nan(b));
}

fn min_num(a: f32, b: f32) -> f32 {
    return select(min(a, b), a, is_nan(b));
}

// A ray with the constants of the box and triangle tests (`intersect::PreparedRay`).
struct PreparedRay {
    origin: vec3<f32>,
    direction: vec3<f32>,
    tmin: f32,
    tmax: f32,
    time: f32,
    mask: u32,
    flags: u32,
    kx: u32,
    ky: u32,
    kz: u32,
    shear: vec3<f32>,
    inv_direction: vec3<f32>,
}

fn ray_f32(word: u32) -> f32 {
    return bitcast<f32>(rays[word]);
}

fn ray_vec3(word: u32) -> vec3<f32> {
    return vec3<f32>(ray_f32(word), ray_f32(word + 1u), ray_f32(word + 2u));
}

// Decodes ray `index` of the chunk (`RayFormat::decode`) and prepares it (`PreparedRay::new`).
fn load_ray(index: u32) -> PreparedRay {
    var sizes = array<u32, 5>(6u, 8u, 8u, 9u, 12u);
    let format = params.ray_format;
    let base = index * sizes[format];
    var r: PreparedRay;
    r.origin = ray_vec3(base);
    r.tmin = 0.0;
    r.tmax = infinity();
    r.time = 0.0;
    r.mask = 0u;
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
        }
    }
    r.flags = r.flags | params.query_flags;
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
    return r;
}

// Where the ray's time falls among the accel's keys (`MotionOptions::locate`).
struct KeyTime {
    present: bool,
    segment: u32,
    fraction: f32,
}

fn locate(time: f32) -> KeyTime {
    let keys = params.keys;
    if keys <= 1u {
        return KeyTime(true, 0u, 0.0);
    }
    let last_segment = keys - 2u;
    if time > params.time_end {
        return KeyTime((params.motion_flags & END_VANISH) == 0u, last_segment, 1.0);
    }
    if time < params.time_begin || is_nan(time) {
        return KeyTime((params.motion_flags & START_VANISH) == 0u || is_nan(time), 0u, 0.0);
    }
    let u = (time - params.time_begin) / (params.time_end - params.time_begin) * f32(keys - 1u);
    let segment = min(u32(max(u, 0.0)), last_segment);
    return KeyTime(true, segment, clamp(u - f32(segment), 0.0, 1.0));
}

// `motion::lerp`.
fn lerp3(a: vec3<f32>, b: vec3<f32>, f: f32) -> vec3<f32> {
    return a * (1.0 - f) + b * f;
}

fn box_corner(word: u32) -> vec3<f32> {
    return vec3<f32>(node_boxes[word], node_boxes[word + 1u], node_boxes[word + 2u]);
}

// Result of the box test: whether the ray's range reaches the box, and where it enters it.
struct BoxHit {
    hit: bool,
    near: f32,
}

// Node `node`'s box at `at` tested against `[ray.tmin, tmax]` (`intersect::aabb::intersect`).
fn test_node(ray: PreparedRay, node: u32, at: KeyTime, tmax: f32) -> BoxHit {
    var lo: vec3<f32>;
    var hi: vec3<f32>;
    if params.keys <= 1u {
        lo = nodes[node].min;
        hi = nodes[node].max;
    } else {
        let first = (node * params.keys + at.segment) * 6u;
        lo = lerp3(box_corner(first), box_corner(first + 6u), at.fraction);
        hi = lerp3(box_corner(first + 3u), box_corner(first + 9u), at.fraction);
    }
    var near = ray.tmin;
    var far = tmax;
    for (var axis = 0u; axis < 3u; axis++) {
        let negative = ray.direction[axis] < 0.0;
        let entry = select(lo[axis], hi[axis], negative);
        let exit = select(hi[axis], lo[axis], negative);
        let o = ray.origin[axis];
        let inv = ray.inv_direction[axis];
        near = max_num(near, (entry - o) * inv);
        far = min_num(far, (exit - o) * inv);
    }
    let widened_near = near - abs(near) * SLACK;
    let widened_far = far + abs(far) * SLACK;
    return BoxHit(widened_near <= widened_far, widened_near);
}

fn corner(word: u32) -> vec3<f32> {
    return vec3<f32>(corners[word], corners[word + 1u], corners[word + 2u]);
}

// Triangle slot `slot`'s corners at `at`.
fn triangle_at(slot: u32, at: KeyTime) -> array<vec3<f32>, 3> {
    let first = (slot * params.keys + at.segment) * 9u;
    if params.keys <= 1u {
        return array<vec3<f32>, 3>(corner(first), corner(first + 3u), corner(first + 6u));
    }
    let f = at.fraction;
    return array<vec3<f32>, 3>(
        lerp3(corner(first), corner(first + 9u), f),
        lerp3(corner(first + 3u), corner(first + 12u), f),
        lerp3(corner(first + 6u), corner(first + 15u), f),
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
    let ax = a[kx] - sx * a[kz];
    let ay = a[ky] - sy * a[kz];
    let bx = b[kx] - sx * b[kz];
    let by = b[ky] - sy * b[kz];
    let cx = c[kx] - sx * c[kz];
    let cy = c[ky] - sy * c[kz];
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
    let az = sz * a[kz];
    let bz = sz * b[kz];
    let cz = sz * c[kz];
    let t = (u * az + v * bz + w * cz) / det;
    if !is_finite_f32(t) {
        return NO_TRIANGLE_HIT;
    }
    return TriangleHit(true, t, v / det, w / det, det < 0.0);
}

// The collector of one ray (`query::Collector`), in private variables.
var<private> kind: u32;
var<private> ray_tmax: f32;
var<private> terminate_on_first_hit: bool;
var<private> has_best: bool;
var<private> best_t: f32;
var<private> best_slot: u32;
var<private> best_u: f32;
var<private> best_v: f32;
var<private> best_back: bool;
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

// Whether a hit at `(t, slot)` is reported before one at `(other_t, other_slot)`: smaller t, then ids.
fn precedes(t: f32, slot: u32, other_t: f32, other_slot: u32) -> bool {
    if t != other_t {
        return t < other_t;
    }
    let a = prims[slot];
    let b = prims[other_slot];
    if a.geom_id != b.geom_id {
        return a.geom_id < b.geom_id;
    }
    return a.prim_id < b.prim_id;
}

fn entry_t(entry: vec4<u32>) -> f32 {
    return bitcast<f32>(entry.x);
}

fn entry_slot(entry: vec4<u32>) -> u32 {
    return entry.y & ~BACK_FACE_BIT;
}

// `Collector::insert_sorted`.
fn insert_sorted(entry: vec4<u32>) {
    let capacity = params.records_per_ray;
    let t = entry_t(entry);
    let slot = entry_slot(entry);
    if sorted_len == capacity {
        let last = scratch[sorted_base + capacity - 1u];
        if !precedes(t, slot, entry_t(last), entry_slot(last)) {
            return;
        }
    }
    var at = min(sorted_len, capacity - 1u);
    loop {
        if at == 0u {
            break;
        }
        let previous = scratch[sorted_base + at - 1u];
        if !precedes(t, slot, entry_t(previous), entry_slot(previous)) {
            break;
        }
        scratch[sorted_base + at] = previous;
        at -= 1u;
    }
    scratch[sorted_base + at] = entry;
    sorted_len = min(sorted_len + 1u, capacity);
}

// `Collector::offer`.
fn offer(t: f32, slot: u32, u: f32, v: f32, back_face: bool) {
    if hit_count != 0xffffffffu {
        hit_count += 1u;
    }
    done = terminate_on_first_hit || kind == ANY;
    if kind == ALL {
        insert_sorted(vec4<u32>(bitcast<u32>(t), slot | select(0u, BACK_FACE_BIT, back_face), bitcast<u32>(u),
            bitcast<u32>(v)));
    } else if kind == ANY && has_best {
        // Keep the first hit found.
    } else if !has_best || precedes(t, slot, best_t, best_slot) {
        has_best = true;
        best_t = t;
        best_slot = slot;
        best_u = u;
        best_v = v;
        best_back = back_face;
    }
}

// `query::consider_triangle` at the top level (no instance above): mask, intersection, range, culling.
fn consider_triangle(ray: PreparedRay, slot: u32, at: KeyTime) {
    let prim = prims[slot];
    if (ray.mask & prim.mask) != 0u {
        return;
    }
    let hit = intersect_triangle(ray, triangle_at(slot, at));
    if !hit.hit {
        return;
    }
    if !(hit.t >= ray.tmin && hit.t <= cull_tmax()) {
        return;
    }
    if (prim.geometry_flags & DISABLE_FACE_CULLING) == 0u {
        let culled = select(CULL_FRONT_FACING, CULL_BACK_FACING, hit.back_face);
        if (ray.flags & culled) != 0u {
            return;
        }
    }
    offer(hit.t, slot, hit.u, hit.v, hit.back_face);
}

// What the walk did, for the statistics.
var<private> nodes_visited: u32;
var<private> triangle_tests: u32;

// The walk of `traverse::walk` over a geometry accel.
fn traverse(ray: PreparedRay) {
    if params.node_count == 0u {
        return;
    }
    let at = locate(ray.time);
    if !at.present {
        return;
    }
    nodes_visited += 1u;
    if !test_node(ray, 0u, at, cull_tmax()).hit {
        return;
    }
    var stack_node: array<u32, STACK_SIZE>;
    var stack_near: array<f32, STACK_SIZE>;
    var len = 0u;
    var current = 0u;
    loop {
        let node = nodes[current];
        var has_next = false;
        var next = 0u;
        if node.count > 0u {
            for (var slot = node.index; slot < node.index + node.count; slot++) {
                triangle_tests += 1u;
                consider_triangle(ray, slot, at);
                if done {
                    return;
                }
            }
        } else {
            let tmax = cull_tmax();
            let left = node.index;
            let right = node.index + 1u;
            nodes_visited += 2u;
            let near_left = test_node(ray, left, at, tmax);
            let near_right = test_node(ray, right, at, tmax);
            if near_left.hit && near_right.hit {
                has_next = true;
                if near_right.near < near_left.near {
                    stack_node[len] = left;
                    stack_near[len] = near_left.near;
                    next = right;
                } else {
                    stack_node[len] = right;
                    stack_near[len] = near_right.near;
                    next = left;
                }
                len += 1u;
            } else if near_left.hit {
                has_next = true;
                next = left;
            } else if near_right.hit {
                has_next = true;
                next = right;
            }
        }
        if !has_next {
            loop {
                if len == 0u {
                    return;
                }
                len -= 1u;
                if stack_near[len] <= cull_tmax() {
                    next = stack_node[len];
                    break;
                }
            }
        }
        current = next;
    }
}

fn store(word: u32, value: u32) {
    atomicStore(&hits[word], value);
}

// Writes hit record `record` of the chunk (`HitFormat::write`); a miss when `present` is false.
fn write_record(record: u32, present: bool, t: f32, slot: u32, u: f32, v: f32, back_face: bool, at: KeyTime) {
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
    if present {
        prim = prims[slot];
        hit_t = t;
        hit_u = u;
        hit_v = v;
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
            store(w + 2u, MISS_ID);
        }
        case HIT_T_TRIID_INSTID_U_V: {
            store(w + 1u, prim.prim_id);
            store(w + 2u, MISS_ID);
            store(w + 3u, bitcast<u32>(hit_u));
            store(w + 4u, bitcast<u32>(hit_v));
        }
        case HIT_FULL: {
            var normal = vec3<f32>(0.0);
            if present {
                let tri = triangle_at(slot, at);
                let n = cross(tri[1] - tri[0], tri[2] - tri[0]);
                // `Vec3A::normalize_or_zero`.
                let rcp = 1.0 / length(n);
                if !is_nan(rcp) && rcp != infinity() && rcp > 0.0 {
                    normal = n * rcp;
                }
            }
            store(w + 1u, prim.prim_id);
            store(w + 2u, prim.geom_id);
            store(w + 3u, MISS_ID);
            store(w + 4u, bitcast<u32>(hit_u));
            store(w + 5u, bitcast<u32>(hit_v));
            store(w + 6u, bitcast<u32>(normal.x));
            store(w + 7u, bitcast<u32>(normal.y));
            store(w + 8u, bitcast<u32>(normal.z));
            store(w + 9u, select(0u, 1u, present && back_face));
            store(w + 10u, 0u);
            store(w + 11u, 0u);
            for (var i = 12u; i < 20u; i++) {
                store(w + i, MISS_ID);
            }
        }
        default: {}
    }
}

// Writes ray `index`'s records and count (`Collector::write`).
fn write_ray(index: u32, at: KeyTime) {
    let first = index * params.records_per_ray;
    if kind == ALL {
        for (var slot = 0u; slot < params.records_per_ray; slot++) {
            let entry = scratch[sorted_base + slot];
            let present = slot < sorted_len;
            write_record(first + slot, present, entry_t(entry), entry_slot(entry), bitcast<f32>(entry.z),
                bitcast<f32>(entry.w), (entry.y & BACK_FACE_BIT) != 0u, at);
        }
    } else {
        write_record(first, has_best, best_t, best_slot, best_u, best_v, best_back, at);
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

@compute @workgroup_size(64)
fn trace(@builtin(global_invocation_id) global: vec3<u32>, @builtin(local_invocation_index) local: u32) {
    if local == 0u {
        atomicStore(&group_tallies[0], 0u);
        atomicStore(&group_tallies[1], 0u);
        atomicStore(&group_tallies[2], 0u);
    }
    workgroupBarrier();
    let index = global.x;
    if index < params.ray_count {
        let ray = load_ray(index);
        kind = params.query_kind;
        ray_tmax = ray.tmax;
        terminate_on_first_hit = (ray.flags & TERMINATE_ON_FIRST_HIT) != 0u;
        has_best = false;
        hit_count = 0u;
        sorted_base = index * params.records_per_ray;
        sorted_len = 0u;
        done = false;
        nodes_visited = 0u;
        triangle_tests = 0u;
        traverse(ray);
        write_ray(index, locate(ray.time));
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
