
// Rays made on the device from a generator's numbers (`GENERATOR` ≠ 0; `raygen::Generator::fill` on the host makes
// the same rays, up to rounding): the `rays` binding then holds the generator's block for the chunk
// (`offload::DeviceGenerator::words`), and ray `index` of the chunk is the generator's ray `params.first_ray + index`.
//
// A camera's block (f32 unless marked; `raygen::CameraFrame`): 0 eye (pinhole) or image centre (orthographic) xyz |
// 3 forward xyz | 6 right xyz | 9 up xyz | 12 half width | 13 half height (at distance 1 for the pinhole, in world
// units for the orthographic camera) | 14 width | 15 height | 16 width u32 | 17 samples a pixel u32 | 18 jittered
// u32 (0 or 1) | 19 jitter seed low u32 | 20 jitter seed high u32.
//
// A lidar's block (`raygen::LidarFrame`): 0 origin xyz | 3 forward xyz | 6 left xyz | 9 up xyz | 12 min range | 13 max
// range | 14 channels u32 | 15 the step of the chunk's first ray u32 | 16 each channel's (sin, cos) of its elevation
// | then each step of the chunk, from that one: (sin, cos) of its azimuth, its time. The sines and times are the
// host's, so that only multiplies and adds are left to the GPU.

// `GENERATOR` values (`kernel::Rays`): the packed rays of the caller, a pinhole camera, an orthographic camera, a
// lidar.
const GENERATOR_NONE: u32 = 0u;
const GENERATOR_PINHOLE: u32 = 1u;
const GENERATOR_ORTHOGRAPHIC: u32 = 2u;
const GENERATOR_LIDAR: u32 = 3u;

// 64-bit integers are (low, high) words. The high word of the 64-bit product `a · b`.
fn mul_high(a: u32, b: u32) -> u32 {
    let al = a & 0xffffu;
    let ah = a >> 16u;
    let bl = b & 0xffffu;
    let bh = b >> 16u;
    let ll = al * bl;
    let lh = al * bh;
    let hl = ah * bl;
    let middle = (ll >> 16u) + (lh & 0xffffu) + (hl & 0xffffu);
    return ah * bh + (lh >> 16u) + (hl >> 16u) + (middle >> 16u);
}

// The low 64 bits of `a · b`.
fn mul64(a: vec2<u32>, b: vec2<u32>) -> vec2<u32> {
    return vec2<u32>(a.x * b.x, mul_high(a.x, b.x) + a.x * b.y + a.y * b.x);
}

// `z ^ (z >> shift)` for a shift in 1 ..= 31.
fn xor_shift(z: vec2<u32>, shift: u32) -> vec2<u32> {
    return z ^ vec2<u32>((z.x >> shift) | (z.y << (32u - shift)), z.y >> shift);
}

// `raygen::uniform(seed, index)`: SplitMix64's finalizer of `seed ^ index · φ`, its top 24 bits over 2^24 (exact).
fn uniform_float(seed: vec2<u32>, index: vec2<u32>) -> f32 {
    var z = seed ^ mul64(index, vec2<u32>(0x7f4a7c15u, 0x9e3779b9u));
    z = mul64(xor_shift(z, 30u), vec2<u32>(0x1ce4e5b9u, 0xbf58476du));
    z = mul64(xor_shift(z, 27u), vec2<u32>(0x133111ebu, 0x94d049bbu));
    z = xor_shift(z, 31u);
    return f32(z.y >> 8u) / 16777216.0;
}

fn block_f32(word: u32) -> f32 {
    return bitcast<f32>(rays[word]);
}

fn block_vec3(word: u32) -> vec3<f32> {
    return vec3<f32>(block_f32(word), block_f32(word + 1u), block_f32(word + 2u));
}

// Ray `index` of the chunk made by the generator.
fn generated_ray(index: u32) -> PreparedRay {
    if GENERATOR == GENERATOR_LIDAR {
        return lidar_ray(index);
    }
    return camera_ray(index);
}

// A unit vector as glam's `normalize` makes it: times the reciprocal of the length.
fn unit(v: vec3<f32>) -> vec3<f32> {
    return v * (1.0 / sqrt(dot(v, v)));
}

// Ray `index` of the chunk made by the lidar (`LidarFrame::ray`), with what its ray format keeps (as the host's
// rays are packed in it): `tmin` in the formats that carry one, `tmax` likewise, the time in those with times.
fn lidar_ray(index: u32) -> PreparedRay {
    let ray_index = params.first_ray + index;
    let channels = rays[14u];
    let channel = 16u + 2u * (ray_index % channels);
    let step = 16u + 2u * channels + 3u * (ray_index / channels - rays[15u]);
    let azimuth = block_vec3(3u) * block_f32(step + 1u) + block_vec3(6u) * block_f32(step);
    let direction = unit(azimuth * block_f32(channel + 1u) + block_vec3(9u) * block_f32(channel));
    // Ray formats in `RayFormat::ALL` order: origin_direction, origin_tmin_direction_tmax,
    // origin_mask_direction_tmax, origin_tmin_direction_tmax_time, full.
    let format = params.ray_format;
    var r: PreparedRay;
    r.tmin = select(0.0, block_f32(12u), format == 1u || format >= 3u);
    r.tmax = select(infinity(), block_f32(13u), format >= 1u);
    r.time = select(0.0, block_f32(step + 2u), format >= 3u);
    r.mask = 0u;
    r.visibility = 0xffu;
    r.flags = params.query_flags;
    return oriented(block_vec3(0u), direction, r);
}

// Ray `index` of the chunk made by the camera generator (`PixelSampling::sample`, then `PinholeView::ray` or the
// orthographic camera's formula), prepared like a decoded ray: `tmin` 0, `tmax` +∞, time 0, no mask, every
// instance visible, the query's flags.
fn camera_ray(index: u32) -> PreparedRay {
    let ray_index = params.first_ray + index;
    let samples = rays[17u];
    let pixel = ray_index / samples;
    let width = rays[16u];
    var point = vec2<f32>(f32(pixel % width), f32(pixel / width)) + vec2<f32>(0.5);
    if rays[18u] != 0u {
        let seed = vec2<u32>(rays[19u], rays[20u]);
        // The 64-bit index `ray_index · 8 + k`.
        let at = vec2<u32>(ray_index << 3u, ray_index >> 29u);
        point = vec2<f32>(f32(pixel % width), f32(pixel / width))
            + vec2<f32>(uniform_float(seed, at), uniform_float(seed, at | vec2<u32>(1u, 0u)));
    }
    let sx = (point.x / block_f32(14u) * 2.0 - 1.0) * block_f32(12u);
    let sy = (1.0 - point.y / block_f32(15u) * 2.0) * block_f32(13u);
    let eye = block_vec3(0u);
    let forward = block_vec3(3u);
    let right = block_vec3(6u);
    let up = block_vec3(9u);
    var origin = eye;
    var direction = forward;
    if GENERATOR == GENERATOR_PINHOLE {
        direction = unit(forward + right * sx + up * sy);
    } else {
        origin = eye + right * sx + up * sy;
    }
    var r: PreparedRay;
    r.tmin = 0.0;
    r.tmax = infinity();
    r.time = 0.0;
    r.mask = 0u;
    r.visibility = 0xffu;
    r.flags = params.query_flags;
    return oriented(origin, direction, r);
}
