
// The image reduction on the device (`reduce::Image`), dispatched after the trace over the same chunk: one thread a
// pixel of `params.group_rays` consecutive rays (one record each: closest or any, in a format whose word 1 is the
// primitive id), the nearest of their hits (records naming a primitive, as `Hit::is_hit`; the first of equal `t`,
// as `reduce::nearest`) written to `reduced` as the pixel's depth (`params.pixel_words` 1: `t`, which is negative
// for a hit behind the ray's origin, or `NONE`'s bits, a NaN, for a miss) or its normal turned to face the ray (4
// words: x, y, z f32, then 1 for a hit; all 0 for a miss). The host encodes the pixels (`Image::write_depth`,
// `Image::write_normal`).
@group(1) @binding(5) var<storage, read_write> reduced: array<u32>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn reduce_pixels(@builtin(global_invocation_id) global: vec3<u32>) {
    let pixel = global.x;
    let group = params.group_rays;
    if pixel >= params.ray_count / group {
        return;
    }
    var nearest = NONE;
    var nearest_t = 0.0;
    for (var ray = pixel * group; ray < (pixel + 1u) * group; ray++) {
        let t = bitcast<f32>(atomicLoad(&hits[ray * params.record_words]));
        let hit = atomicLoad(&hits[ray * params.record_words + 1u]) != MISS_ID;
        if hit && (nearest == NONE || t < nearest_t) {
            nearest = ray;
            nearest_t = t;
        }
    }
    if params.pixel_words == 1u {
        reduced[pixel] = select(NONE, bitcast<u32>(nearest_t), nearest != NONE);
        return;
    }
    var normal = vec4<u32>(0u);
    if nearest != NONE {
        // A `full` record: the normal at word 6, the back-face flag at word 9.
        let w = nearest * params.record_words;
        let bits = vec3<u32>(atomicLoad(&hits[w + 6u]), atomicLoad(&hits[w + 7u]), atomicLoad(&hits[w + 8u]));
        var n = bitcast<vec3<f32>>(bits);
        if atomicLoad(&hits[w + 9u]) != 0u {
            n = -n;
        }
        normal = vec4<u32>(bitcast<vec3<u32>>(n), 1u);
    }
    let at = 4u * pixel;
    reduced[at] = normal.x;
    reduced[at + 1u] = normal.y;
    reduced[at + 2u] = normal.z;
    reduced[at + 3u] = normal.w;
}
