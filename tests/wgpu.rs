//! The wgpu backend against the CPU backend: every ray format × hit format × query kind on the bunny, a random
//! soup with masks, flags and two geometries, a vertex-motion mesh and a graph of instance accels and transforms
//! (visibility masks, instance flags, ties, static, matrix and SRT motion, a motion instance accel); large
//! batches; batches split into many chunks; copies between devices (two GPU devices too); what the backend refuses.
//!
//! The two backends run the same algorithm, but a GPU divides less exactly and may fuse the multiplies and adds of
//! the box tests and the rays' transforms, so answers are compared with tolerances (issue 8): a ray agrees when hit/miss, primitive, geometry and instance ids, facing and counts are
//! equal, `t` is within 1e-4 relative and u, v and the normal within 1e-3; at least 99.99% of rays must agree over
//! each test (on lavapipe they are usually all bit-identical).
//!
//! Adapter policy: without an adapter these tests print a notice and pass, unless `RAYD_REQUIRE_GPU=1` (CI sets
//! it), where they fail. The engine enumerates `WGPU_BACKEND`'s backends, Vulkan when it is unset.

mod common;

use common::{gpu_with, input_with_masks, pack_rays, random_rays, random_soup, shared_mesh};
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::{Affine3A, Quat, Vec3, Vec3A};
use rayd_engine::accel::{AccelKind, BuildOptions};
use rayd_engine::backend::wgpu::WgpuOptions;
use rayd_engine::backend::{BackendKind, RaySource};
use rayd_engine::format::{HitFormat, Ray, RayFlags, RayFormat};
use rayd_engine::geometry::{
    BuildInput, GeometryFlags, Instance, InstanceFlags, MotionFlags, MotionOptions, Placement, TransformInput,
    TriangleInput,
};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::raygen::{Camera, Generator, Lidar, Orthographic, PixelSampling};
use rayd_engine::reduce::{Image, ImageChannel, PixelEncoding, Reduction};
use rayd_engine::{Accel, Context, Device, Error, ErrorKind};

/// The first wgpu device with default options.
fn gpu() -> Option<Device> {
    gpu_with(WgpuOptions::default())
}

/// Agreement counts over a test.
#[derive(Debug, Default)]
struct Agreement {
    /// Rays compared.
    rays: usize,
    /// Rays whose results differ beyond the tolerances.
    differing: usize,
}

impl Agreement {
    /// Asserts that at least 99.99% of rays agreed.
    fn check(&self) {
        eprintln!("{} of {} rays differ", self.differing, self.rays);
        assert!(self.rays > 0);
        assert!(self.differing as f64 <= self.rays as f64 * 1e-4, "{} of {} rays differ", self.differing, self.rays);
    }
}

/// Whether two floats are within `tolerance`, relative to the larger magnitude (absolute below 1).
fn close(a: f32, b: f32, tolerance: f32) -> bool {
    a == b || (a - b).abs() <= tolerance * a.abs().max(b.abs()).max(1.0)
}

/// Traces `rays` with `query` on `accel` in `context`; returns (hits, counts).
fn trace(context: &Context, accel: &Accel, query: &Query, rays: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let layout = query.output_layout(rays.len()).unwrap();
    let (mut hits, mut counts) = (vec![0xEE; layout.hits], vec![0xEE; layout.counts]);
    context.trace(accel, query, rays, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
    (hits, counts)
}

/// One scene built on both devices.
struct Scene {
    /// The reference.
    cpu: (Context, Arc<Accel>),
    /// The device under test.
    gpu: (Context, Arc<Accel>),
}

impl Scene {
    /// Builds `inputs` with `options` on the CPU and on `device`.
    fn new(device: &Device, inputs: &[BuildInput<'_>], options: &BuildOptions) -> Scene {
        Scene::built(device, |context| context.build_accel(inputs, options).unwrap())
    }

    /// The accel `build` makes in a context of the CPU and in one of `device`.
    fn built(device: &Device, build: impl Fn(&Context) -> Arc<Accel>) -> Scene {
        let on = |device: Device| {
            let context = Context::new(device);
            let accel = build(&context);
            (context, accel)
        };
        Scene { cpu: on(Device::cpu()), gpu: on(device.clone()) }
    }

    /// Traces `rays` (packed in `query.ray_format`) on both and adds the comparison to `agreement`.
    fn compare(&self, query: &Query, rays: &[u8], agreement: &mut Agreement) {
        let cpu = trace(&self.cpu.0, &self.cpu.1, query, rays);
        let gpu = trace(&self.gpu.0, &self.gpu.1, query, rays);
        compare_hits(query, rays, (&cpu.0, &cpu.1), (&gpu.0, &gpu.1), agreement);
    }

    /// Compares every ray format × hit format × query kind on `rays`, with query flags varied across kinds.
    fn compare_everything(&self, rays: &[Ray], agreement: &mut Agreement) {
        for ray_format in RayFormat::ALL {
            let packed = pack_rays(rays, ray_format);
            for hit_format in HitFormat::ALL {
                for (k, kind) in QueryKind::ALL.into_iter().enumerate() {
                    let flags = [RayFlags::empty(), RayFlags::CULL_BACK_FACING, RayFlags::CULL_FRONT_FACING][k % 3];
                    let query = Query { kind, ray_format, hit_format, flags, max_hits_per_ray: 3 };
                    self.compare(&query, &packed, agreement);
                }
            }
        }
    }
}

/// Compares the hits and counts of `rays` (packed in `query.ray_format`) traced on the CPU and on the GPU and adds
/// the comparison to `agreement`.
fn compare_hits(
    query: &Query,
    rays: &[u8],
    (cpu_hits, cpu_counts): (&[u8], &[u8]),
    (gpu_hits, gpu_counts): (&[u8], &[u8]),
    agreement: &mut Agreement,
) {
    let ray_count = rays.len() / query.ray_format.size();
    let per_ray = query.records_per_ray();
    let format = query.hit_format;
    for ray in 0..ray_count {
        // Which hit an `any` query, or a ray that terminates on its first hit, stops at depends on the traversal
        // order (the CPU walks 8-wide nodes, the GPU 4-wide ones): only whether it hit must agree.
        let terminates = query.kind == QueryKind::Any
            || query.flags.contains(RayFlags::TERMINATE_ON_FIRST_HIT)
            || query.ray_format == RayFormat::Full && {
                let at = ray * query.ray_format.size();
                RayFormat::Full
                    .decode(&rays[at..at + RayFormat::Full.size()])
                    .flags
                    .contains(RayFlags::TERMINATE_ON_FIRST_HIT)
            };
        if terminates {
            let hit = |hits: &[u8]| format.read(hits, ray * per_ray).is_hit();
            if hit(cpu_hits) != hit(gpu_hits) {
                agreement.differing += 1;
            }
            continue;
        }
        let records_agree = (ray * per_ray..(ray + 1) * per_ray).all(|record| {
            let (c, g) = (format.read(cpu_hits, record), format.read(gpu_hits, record));
            c.is_hit() == g.is_hit()
                && (c.prim_id, c.geom_id, c.inst_id, c.inst_path, c.back_face)
                    == (g.prim_id, g.geom_id, g.inst_id, g.inst_path, g.back_face)
                && close(c.t, g.t, 1e-4)
                && close(c.u, g.u, 1e-3)
                && close(c.v, g.v, 1e-3)
                && (c.normal - g.normal).abs().max_element() <= 1e-3
        });
        let counts_agree =
            !query.kind.has_counts() || cpu_counts[4 * ray..4 * ray + 4] == gpu_counts[4 * ray..4 * ray + 4];
        if !(records_agree && counts_agree) {
            agreement.differing += 1;
            if agreement.differing <= 5 {
                eprintln!("{query:?}: ray {ray} differs");
            }
        }
    }
    if format == HitFormat::Bitmask {
        assert_eq!(cpu_hits.last(), gpu_hits.last(), "{query:?}: the bitmask's last byte (unused bits 0)");
    }
    agreement.rays += ray_count;
}

/// Random rays through the unit cube with every field randomized (see `common::random_rays`).
fn rays(count: usize, seed: u64) -> Vec<Ray> {
    random_rays(count, seed)
}

/// Rays from a ring of cameras around the unit cube's centre, aimed at it, full range: they hit often.
fn camera_rays(count: usize) -> Vec<Ray> {
    (0..count)
        .map(|i| {
            let f = i as f32 / count as f32;
            let angle = f * std::f32::consts::TAU * 7.0;
            let origin = Vec3A::new(0.5 + 2.0 * angle.cos(), 0.5 + (f - 0.5), 0.5 + 2.0 * angle.sin());
            let target =
                Vec3A::new(0.5, 0.5, 0.5) + Vec3A::new((f * 97.0).sin(), (f * 61.0).cos(), (f * 37.0).sin()) * 0.3;
            Ray { origin, direction: target - origin, ..Ray::default() }
        })
        .collect()
}

fn bunny() -> Mesh {
    shared_mesh("stanford-bunny").normalized_at(Vec3::splat(0.5))
}

#[test]
fn the_bunny_agrees_in_every_format_and_query_kind() {
    let Some(device) = gpu() else { return };
    assert_eq!(device.info().kind, BackendKind::Wgpu);
    assert!(device.info().id.starts_with("wgpu:"));
    let mesh = bunny().pack();
    let scene = Scene::new(&device, &[BuildInput::Triangles(mesh.input())], &BuildOptions::default());
    let mut agreement = Agreement::default();
    let mut rays = rays(700, 1);
    rays.extend(camera_rays(700));
    scene.compare_everything(&rays, &mut agreement);
    agreement.check();
}

#[test]
fn a_soup_with_masks_flags_and_two_geometries_agrees() {
    let Some(device) = gpu() else { return };
    let (a, b) = (random_soup(1500, 7).pack(), random_soup(800, 8).pack());
    let masks: Vec<u8> = (0..1500u32).flat_map(|i| (1u32 << (i % 5)).to_le_bytes()).collect();
    let inputs = [
        input_with_masks(&a.vertices, &a.indices, &masks),
        BuildInput::Triangles(TriangleInput {
            flags: GeometryFlags::DISABLE_FACE_CULLING,
            primitive_index_offset: 100,
            ..b.input()
        }),
    ];
    let scene = Scene::new(&device, &inputs, &BuildOptions::default());
    let mut agreement = Agreement::default();
    scene.compare_everything(&rays(1200, 2), &mut agreement);
    agreement.check();
}

/// The bunny moving and deforming over 3 keys in [0.2, 0.8], vanishing before and after.
fn moving_bunny_inputs() -> (Vec<u8>, Vec<Vec<u8>>, MotionOptions) {
    let mesh = bunny();
    let key = |k: usize| Mesh {
        positions: mesh
            .positions
            .iter()
            .map(|&p| p + Vec3::new(0.15 * k as f32, 0.05 * (p.y * 9.0 + k as f32).sin(), 0.0))
            .collect(),
        triangles: mesh.triangles.clone(),
    };
    let motion = MotionOptions {
        keys: 3,
        time_begin: 0.2,
        time_end: 0.8,
        flags: MotionFlags::START_VANISH | MotionFlags::END_VANISH,
    };
    (mesh.pack().indices, (0..3).map(|k| key(k).pack().vertices).collect(), motion)
}

#[test]
fn a_vertex_motion_mesh_agrees_at_every_ray_time() {
    let Some(device) = gpu() else { return };
    let (indices, keys, motion) = moving_bunny_inputs();
    let later: Vec<&[u8]> = keys[1..].iter().map(Vec::as_slice).collect();
    let inputs = [BuildInput::Triangles(TriangleInput {
        motion_vertices: &later,
        ..TriangleInput::indexed(&keys[0], &indices)
    })];
    let scene = Scene::new(&device, &inputs, &BuildOptions { motion, ..BuildOptions::default() });
    let mut rays = rays(600, 3);
    rays.extend(camera_rays(600).into_iter().enumerate().map(|(i, r)| Ray { time: i as f32 / 600.0, ..r }));
    let mut agreement = Agreement::default();
    scene.compare_everything(&rays, &mut agreement);
    agreement.check();
}

#[test]
fn large_batches_agree_for_closest_and_any() {
    let Some(device) = gpu() else { return };
    let mesh = bunny().pack();
    let scene = Scene::new(&device, &[BuildInput::Triangles(mesh.input())], &BuildOptions::default());
    let mut rays = rays(200_000, 4);
    rays.extend(camera_rays(200_000));
    let packed = pack_rays(&rays, RayFormat::OriginTminDirectionTmax);
    let mut agreement = Agreement::default();
    for kind in [QueryKind::Closest, QueryKind::Any] {
        let query = Query { kind, ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV) };
        scene.compare(&query, &packed, &mut agreement);
    }
    agreement.check();
}

/// Rays whose range reaches behind their origin (negative `tmin`; a third with a negative `tmax` too, so only
/// behind): the kernel orders and re-checks lanes entered at negative distances like any others. Every hit format
/// (a hit behind the origin is a 1 bit in the bitmask on both), every query kind; and the reductions the device
/// makes, which count and image such hits (a record naming a primitive is a hit, whatever its `t`).
#[test]
fn ranges_behind_the_origin_agree() {
    let Some(device) = gpu() else { return };
    let scene = bunny_scene(&device);
    let rays: Vec<Ray> = rays(3000, 11)
        .into_iter()
        .enumerate()
        .map(|(i, ray)| Ray { tmin: -3.0, tmax: if i % 3 == 0 { -0.25 } else { ray.tmax }, ..ray })
        .collect();
    let mut agreement = Agreement::default();
    for ray_format in [RayFormat::OriginTminDirectionTmax, RayFormat::Full] {
        let packed = pack_rays(&rays, ray_format);
        for hit_format in HitFormat::ALL {
            for kind in QueryKind::ALL {
                let query = Query { kind, max_hits_per_ray: 3, ..Query::closest(ray_format, hit_format) };
                scene.compare(&query, &packed, &mut agreement);
            }
        }
    }
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
    let packed = pack_rays(&rays, query.ray_format);
    let count = rays.len() as u64;
    for reduction in reductions(100, 1, count) {
        let reduce = |(context, accel): &(Context, Arc<Accel>)| {
            let (partial, _) = context.trace_reduced(accel, &query, RaySource::Packed(&packed), 0, &reduction).unwrap();
            reduction.finish(partial, count).unwrap().bytes
        };
        compare_reduced(&reduction, count, &reduce(&scene.cpu), &reduce(&scene.gpu), &mut agreement);
    }
    agreement.check();
    // The test is about hits behind the origins: there are many.
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    let (hits, _) = trace(&scene.cpu.0, &scene.cpu.1, &query, &pack_rays(&rays, query.ray_format));
    let behind = hits.chunks_exact(16).filter(|hit| f32::from_le_bytes(hit[..4].try_into().unwrap()) < 0.0).count();
    assert!(behind > rays.len() / 10, "{behind} of {} rays hit behind their origin", rays.len());
}

/// `Context::time_launches` (the kernel-only benchmark's measurement) times each launch by the GPU's timestamps, and
/// is refused where there is no kernel or the rays are not whole.
#[test]
fn kernel_launches_are_timed_one_by_one_and_refused_without_a_kernel() {
    let Some(device) = gpu() else { return };
    let scene = bunny_scene(&device);
    let packed = pack_rays(&camera_rays(4096), RayFormat::OriginTminDirectionTmax);
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    let (context, accel) = &scene.gpu;
    let start = Instant::now();
    let times = context.time_launches(accel, &query, &packed, 3).unwrap();
    let elapsed = start.elapsed();
    assert_eq!(times.len(), 3);
    assert!(times.iter().all(|t| !t.is_zero()), "{times:?}");
    assert!(times.iter().sum::<Duration>() <= elapsed, "{times:?} within {elapsed:?}");
    let none = context.time_launches(accel, &query, &packed, 0).unwrap_err();
    assert_eq!(none.kind(), ErrorKind::InvalidArgument, "{none}");
    let torn = context.time_launches(accel, &query, &packed[..packed.len() - 1], 1).unwrap_err();
    assert_eq!(torn.kind(), ErrorKind::InvalidArgument, "{torn}");
    let (cpu, cpu_accel) = &scene.cpu;
    let refused = cpu.time_launches(cpu_accel, &query, &packed, 1).unwrap_err();
    assert_eq!(refused.kind(), ErrorKind::FailedPrecondition, "{refused}");
}

/// A pinhole camera (3 jittered samples a pixel) and an orthographic one (pixel centres, and 2 jittered samples a
/// pixel with a seed whose high word is set too) looking at the bunny.
fn cameras() -> [Generator; 3] {
    let pinhole = Camera::framing(Vec3::ZERO, Vec3::ONE, 40, 30);
    let orthographic = Orthographic {
        eye: Vec3::new(0.4, 0.6, 3.0),
        target: Vec3::splat(0.5),
        up: Vec3::Y,
        view_height: 1.2,
        width: 37,
        height: 29,
    };
    [
        Generator::Pinhole(pinhole, PixelSampling { samples: 3, jitter_seed: Some(7) }),
        Generator::Orthographic(orthographic, PixelSampling { samples: 1, jitter_seed: None }),
        Generator::Orthographic(orthographic, PixelSampling { samples: 2, jitter_seed: Some(0x0123_4567_89ab_cdef) }),
    ]
}

/// The bunny on the CPU and on `device`.
fn bunny_scene(device: &Device) -> Scene {
    let mesh = bunny().pack();
    Scene::new(device, &[BuildInput::Triangles(mesh.input())], &BuildOptions::default())
}

/// A lidar beside the bunny whose ranges skip its near side and cut its far side.
fn lidar() -> Generator {
    Generator::Lidar(Lidar {
        origin: Vec3::new(0.5, 0.5, -0.8),
        forward: Vec3::Z,
        up: Vec3::Y,
        elevations_degrees: (0..16).map(|c| -20.0 + 2.5 * c as f32).collect(),
        steps: 90,
        min_range: 1.2,
        max_range: 1.3,
        time: (0.0, 1.0),
    })
}

#[test]
fn camera_and_lidar_rays_made_on_the_device_agree_with_the_hosts() {
    // Chunks of 320 rays at most: each range below takes several, each chunk starting at another generator index (for
    // the lidar, inside a step).
    let Some(device) = gpu_with(WgpuOptions { max_chunk_rays: Some(320), ..WgpuOptions::default() }) else {
        return;
    };
    let scene = bunny_scene(&device);
    let mut agreement = Agreement::default();
    for generator in cameras().into_iter().chain([lidar()]) {
        generator.check().unwrap();
        // A range that does not start at the generator's first ray.
        let (first, count) = (101, generator.count() as usize - 101);
        for (kind, ray_format, hit_format) in [
            (QueryKind::Closest, RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV),
            (QueryKind::Any, RayFormat::OriginDirection, HitFormat::T),
            (QueryKind::Count, RayFormat::Full, HitFormat::Full),
            // Formats without a lidar's tmin, or without its tmin and tmax: refused for it, as on the CPU.
            (QueryKind::Closest, RayFormat::OriginMaskDirectionTmax, HitFormat::TTriid),
            (QueryKind::Closest, RayFormat::OriginDirection, HitFormat::T),
        ] {
            let query = Query { kind, ..Query::closest(ray_format, hit_format) };
            let layout = query.output_layout(count * ray_format.size()).unwrap();
            let (mut hits, mut counts) = (vec![0xEE; layout.hits], vec![0xEE; layout.counts]);
            let made_there = RaySource::Generated { generator: &generator, first, count };
            let output = TraceOutput { hits: &mut hits, counts: &mut counts };
            let traced = scene.gpu.0.trace_source(&scene.gpu.1, &query, made_there, output);
            if let Err(lost) = generator.check_format(ray_format) {
                assert_eq!(traced.unwrap_err().to_string(), lost.to_string(), "{ray_format:?}");
                continue;
            }
            let stats = traced.unwrap();
            let mut packed = vec![0; count * ray_format.size()];
            generator.fill(ray_format, first, &mut packed);
            let cpu = trace(&scene.cpu.0, &scene.cpu.1, &query, &packed);
            assert_eq!(stats.rays, count as u64);
            compare_hits(&query, &packed, (&cpu.0, &cpu.1), (&hits, &counts), &mut agreement);
        }
    }
    agreement.check();
}

/// The reductions the device makes for a camera of `width` pixels a row and `samples` rays a pixel, and one whose
/// pixels are too large for a chunk (`rays` a multiple of 600), which the host makes.
fn reductions(width: u32, samples: u32, rays: u64) -> Vec<Reduction> {
    let image = |channel, encoding| Image { width, rays_per_pixel: samples, channel, encoding, near: 1.0, far: 2.5 };
    let mut reductions = vec![
        Reduction::Image(image(ImageChannel::Depth, PixelEncoding::Float32)),
        Reduction::Image(image(ImageChannel::Depth, PixelEncoding::Unorm16)),
        Reduction::Image(image(ImageChannel::Normal, PixelEncoding::Float32)),
        Reduction::Image(image(ImageChannel::Normal, PixelEncoding::Unorm16)),
        Reduction::Counts,
    ];
    if rays.is_multiple_of(600) {
        reductions.push(Reduction::Image(Image {
            width: 1,
            rays_per_pixel: 600,
            ..image(ImageChannel::Depth, PixelEncoding::Float32)
        }));
    }
    reductions
}

/// Compares two answers of `reduction` (of `rays` rays) and adds the comparison to `agreement`, a pixel (or the
/// counts) at a time: depths within 1e-4 relative, normal components within 1e-3 (33 in 16 bits), rays hit within
/// 1e-4 of the rays.
fn compare_reduced(reduction: &Reduction, rays: u64, cpu: &[u8], gpu: &[u8], agreement: &mut Agreement) {
    assert_eq!(cpu.len(), gpu.len(), "{reduction:?}");
    let Reduction::Image(image) = reduction else {
        let word = |bytes: &[u8], i: usize| u64::from_le_bytes(bytes[8 * i..8 * i + 8].try_into().unwrap());
        assert_eq!(word(cpu, 0), rays);
        assert_eq!(word(gpu, 0), rays);
        assert!(word(cpu, 1).abs_diff(word(gpu, 1)) as f64 <= rays as f64 * 1e-4, "{reduction:?}");
        assert_eq!(word(gpu, 1), word(gpu, 2), "a closest query's hits are its rays hit");
        return;
    };
    let (values, float) = match (image.channel, image.encoding) {
        (ImageChannel::Depth, PixelEncoding::Float32) => (1, true),
        (ImageChannel::Normal, PixelEncoding::Float32) => (3, true),
        (ImageChannel::Depth, _) => (1, false),
        (ImageChannel::Normal, _) => (3, false),
    };
    let value = |bytes: &[u8], i: usize| match float {
        true => f32::from_le_bytes(bytes[4 * i..4 * i + 4].try_into().unwrap()),
        false => f32::from(u16::from_le_bytes(bytes[2 * i..2 * i + 2].try_into().unwrap())),
    };
    let pixels = cpu.len() / values / if float { 4 } else { 2 };
    for pixel in 0..pixels {
        let agree = (pixel * values..(pixel + 1) * values).all(|i| {
            let (c, g) = (value(cpu, i), value(gpu, i));
            match (image.channel, float) {
                (ImageChannel::Depth, true) => close(c, g, 1e-4),
                (ImageChannel::Depth, false) => (c - g).abs() <= 1.0 || c.max(g) == 65535.0 && c == g,
                (ImageChannel::Normal, true) => (c - g).abs() <= 1e-3,
                (ImageChannel::Normal, false) => (c - g).abs() <= 33.0,
            }
        });
        if !agree {
            agreement.differing += 1;
            eprintln!("{reduction:?}: pixel {pixel} differs");
        }
    }
    agreement.rays += pixels;
}

#[test]
fn image_and_count_reductions_made_on_the_device_agree_with_the_hosts() {
    // Chunks of 500 rays at most: whole pixels of 2 or 3 rays take 480 (a multiple of 32 and of 2 or 3), pixels of
    // 600 none.
    let Some(device) = gpu_with(WgpuOptions { max_chunk_rays: Some(500), ..WgpuOptions::default() }) else {
        return;
    };
    let scene = bunny_scene(&device);
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let mut agreement = Agreement::default();
    for generator in cameras() {
        let (width, samples) = match &generator {
            Generator::Pinhole(camera, sampling) => (camera.width, sampling.samples),
            Generator::Orthographic(camera, sampling) => (camera.width, sampling.samples),
            _ => unreachable!("cameras"),
        };
        let count = generator.count();
        let packed = generator.rays(query.ray_format);
        for reduction in reductions(width, samples, count) {
            reduction.check(&query, count).unwrap();
            let reduce = |(context, accel): &(Context, Arc<Accel>), rays| {
                let (partial, stats) = context.trace_reduced(accel, &query, rays, 0, &reduction).unwrap();
                assert_eq!(stats.rays, count);
                reduction.finish(partial, count).unwrap().bytes
            };
            let cpu = reduce(&scene.cpu, RaySource::Packed(&packed));
            // Rays made by the kernel, and rays sent.
            let made_there = RaySource::Generated { generator: &generator, first: 0, count: count as usize };
            for rays in [made_there, RaySource::Packed(&packed)] {
                compare_reduced(&reduction, count, &cpu, &reduce(&scene.gpu, rays), &mut agreement);
            }
        }
    }
    agreement.check();
}

#[test]
fn traces_run_at_once_on_one_device_answer_as_each_alone() {
    // Small chunks, so that the traces' chunks interleave on the device; rayd's GPU scheduler runs two at once.
    let Some(device) = gpu_with(WgpuOptions { max_chunk_rays: Some(512), ..WgpuOptions::default() }) else {
        return;
    };
    let scene = bunny_scene(&device);
    let (context, accel) = (&scene.gpu.0, &*scene.gpu.1);
    let closest = Query::closest(RayFormat::OriginDirection, HitFormat::TTriidUV);
    let any = Query { kind: QueryKind::Any, ..closest };
    let (random, camera) =
        (pack_rays(&rays(3000, 21), closest.ray_format), pack_rays(&camera_rays(3000), closest.ray_format));
    let [generator, ..] = cameras();
    let image = Reduction::Image(Image {
        width: 40,
        rays_per_pixel: 3,
        channel: ImageChannel::Depth,
        encoding: PixelEncoding::Float32,
        near: 1.0,
        far: 2.5,
    });
    let render = || {
        let rays = RaySource::Generated { generator: &generator, first: 0, count: generator.count() as usize };
        let (partial, _) = context.trace_reduced(accel, &closest, rays, 0, &image).unwrap();
        (image.finish(partial, generator.count()).unwrap().bytes.to_vec(), Vec::new())
    };
    let traces: [&(dyn Fn() -> (Vec<u8>, Vec<u8>) + Sync); 3] =
        [&|| trace(context, accel, &closest, &random), &|| trace(context, accel, &any, &camera), &render];
    let alone: Vec<_> = traces.iter().map(|traced| traced()).collect();
    std::thread::scope(|scope| {
        let running: Vec<_> =
            traces.iter().map(|traced| scope.spawn(move || (0..6).map(|_| traced()).collect::<Vec<_>>())).collect();
        for ((running, alone), name) in running.into_iter().zip(&alone).zip(["closest", "any", "image"]) {
            assert!(running.join().unwrap().iter().all(|traced| traced == alone), "{name} changed beside the others");
        }
    });
}

/// Traces the bunny on `device` with 2,500 random and 2,500 camera rays (seed `seed`) by each of `queries` (kind, hit
/// format, records a ray) and checks the hits against the CPU's; then returns the error of an `all` query of
/// `too_many` full records a ray.
fn bunny_in_chunks(device: Device, seed: u64, queries: &[(QueryKind, HitFormat, u32)], too_many: u32) -> Error {
    let mesh = bunny().pack();
    let scene = Scene::new(&device, &[BuildInput::Triangles(mesh.input())], &BuildOptions::default());
    let mut rays = rays(2500, seed);
    rays.extend(camera_rays(2500));
    let packed = pack_rays(&rays, RayFormat::Full);
    let mut agreement = Agreement::default();
    for &(kind, hit_format, hits) in queries {
        let query = Query { kind, hit_format, max_hits_per_ray: hits, ..Query::closest(RayFormat::Full, hit_format) };
        scene.compare(&query, &packed, &mut agreement);
    }
    agreement.check();
    let query =
        Query { kind: QueryKind::All, max_hits_per_ray: too_many, ..Query::closest(RayFormat::Full, HitFormat::Full) };
    let layout = query.output_layout(packed.len()).unwrap();
    let (mut hits, mut counts) = (vec![0; layout.hits], vec![0; layout.counts]);
    let traced = scene.gpu.0.trace(&scene.gpu.1, &query, &packed, TraceOutput { hits: &mut hits, counts: &mut counts });
    traced.expect_err("records that cannot fit")
}

#[test]
fn batches_larger_than_one_binding_are_split_into_chunks() {
    // 8 KiB bindings: 170 full rays a chunk at most (32 for `all`, whose 5 sorted hits a ray take 240 bytes of
    // scratch), so 5,000 rays take dozens of chunks through both slots.
    let Some(device) = gpu_with(WgpuOptions { max_binding_bytes: Some(8192), ..WgpuOptions::default() }) else {
        return;
    };
    let queries = [
        (QueryKind::Closest, HitFormat::Full, 5),
        (QueryKind::All, HitFormat::Bitmask, 5),
        (QueryKind::Count, HitFormat::TTriid, 5),
    ];
    // A chunk of 32 rays with 1,000 full records each cannot fit 8 KiB.
    let error = bunny_in_chunks(device, 5, &queries, 1000);
    assert_eq!(error.kind(), ErrorKind::ResourceExhausted);
}

#[test]
fn traces_within_a_small_buffer_budget_agree_with_the_cpu_and_those_that_cannot_fit_are_refused() {
    // 1 MiB for a trace's two slots: an `all` query of 64 full hits a ray takes about 13 KiB a ray there (records,
    // sorted scratch, readback), so 5,000 rays go in chunks of 32 rays.
    let budget = 1 << 20;
    let Some(device) = gpu_with(WgpuOptions { max_trace_bytes: Some(budget), ..WgpuOptions::default() }) else {
        return;
    };
    let queries = [
        (QueryKind::Closest, HitFormat::Full, 1),
        (QueryKind::All, HitFormat::Full, 64),
        (QueryKind::Count, HitFormat::TTriid, 1),
    ];
    // Two chunks of 32 rays with 256 full records each do not fit 1 MiB: refused, naming the limit.
    let error = bunny_in_chunks(device, 7, &queries, 256);
    assert_eq!(error.kind(), ErrorKind::ResourceExhausted);
    let message = error.to_string();
    assert!(message.contains("gpu_trace_bytes") && message.contains(&budget.to_string()), "{message}");
}

#[test]
fn rays_past_their_work_fail_the_trace_by_name_and_the_device_goes_on() {
    // 3,000 copies of one triangle: a ray through them tests each (the closest hit is the lowest id of a tie).
    let copies = 3000;
    let vertices: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
    let indices: Vec<u8> = [0u32, 1, 2].repeat(copies).iter().flat_map(|i| i.to_le_bytes()).collect();
    let input = [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))];
    // 100 rays through the pile, 100 beside it.
    let down = |x: f32| Ray { origin: Vec3A::new(x, 0.25, 1.0), direction: -Vec3A::Z, ..Ray::default() };
    let rays: Vec<Ray> = (0..200).map(|i| down(if i % 2 == 0 { 0.25 } else { 5.0 })).collect();
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriid);
    let packed = pack_rays(&rays, RayFormat::OriginDirection);
    let Some(strict) = gpu_with(WgpuOptions { max_ray_work: Some(1024), ..WgpuOptions::default() }) else { return };
    let context = Context::new(strict);
    let accel = context.build_accel(&input, &BuildOptions::default()).unwrap();
    let layout = query.output_layout(packed.len()).unwrap();
    let (mut hits, mut counts) = (vec![0; layout.hits], vec![0; layout.counts]);
    let output = TraceOutput { hits: &mut hits, counts: &mut counts };
    let error = context.trace(&accel, &query, &packed, output).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::ResourceExhausted, "{error}");
    let message = error.to_string();
    assert!(message.contains("100 rays") && message.contains("1024") && message.contains("gpu_ray_work"), "{message}");
    // The rays beside the pile trace on the same device.
    let beside: Vec<Ray> = rays.iter().copied().skip(1).step_by(2).collect();
    let (hits, _) = trace(&context, &accel, &query, &pack_rays(&beside, RayFormat::OriginDirection));
    assert!((0..beside.len()).all(|i| !HitFormat::TTriid.read(&hits, i).is_hit()));
    // A pile of instances (the walk's work multiplies with its levels): 600 instances of a pile of 3 triangles.
    let three = [BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices[..36]))];
    let child = context.build_accel(&three, &BuildOptions::default()).unwrap();
    let none = InstanceFlags::empty();
    let placed: Vec<Instance> = (0..600).map(|id| instance(&child, Affine3A::IDENTITY, id, 0xFF, none)).collect();
    let piled = context.build_instance_accel(&placed, &BuildOptions::default()).unwrap();
    let layout = query.output_layout(packed.len()).unwrap();
    let (mut hits, mut counts) = (vec![0; layout.hits], vec![0; layout.counts]);
    let output = TraceOutput { hits: &mut hits, counts: &mut counts };
    let error = context.trace(&piled, &query, &packed, output).unwrap_err();
    assert!(error.to_string().contains("100 rays") && error.to_string().contains("gpu_ray_work"), "{error}");
    // With the default work, every ray agrees with the CPU.
    let Some(device) = gpu() else { return };
    let mut agreement = Agreement::default();
    Scene::new(&device, &input, &BuildOptions::default()).compare(&query, &packed, &mut agreement);
    agreement.check();
}

#[test]
fn instance_accels_and_transforms_are_bounded_with_the_device_copies_of_what_they_place() {
    let Some(device) = gpu() else { return };
    let context = Context::new(device);
    let packed = bunny().pack();
    let bunny = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let options = BuildOptions::default();
    let transform = TransformInput::Static(rows(Affine3A::from_translation(Vec3::X)));
    let usage = context.compute_transform_memory_usage(&transform, &bunny, &options).unwrap();
    let moved = context.build_transform(&transform, &bunny).unwrap();
    assert!(moved.info().size_bytes <= usage.output_bytes, "{} > {usage:?}", moved.info().size_bytes);
    // The bunny thrice and the transform over it: the bunny's graph is held once more, and counted twice.
    let none = InstanceFlags::empty();
    let placed: Vec<Instance> = (0..3)
        .map(|id| instance(&bunny, Affine3A::from_translation(Vec3::Y * id as f32), id, 0xFF, none))
        .chain([instance(&moved, Affine3A::IDENTITY, 3, 0xFF, none)])
        .collect();
    let usage = context.compute_instance_memory_usage(&placed, &options).unwrap();
    let scene = context.build_instance_accel(&placed, &options).unwrap();
    let size = scene.info().size_bytes;
    assert!(size <= usage.output_bytes, "{size} > {usage:?}");
    // Without the children's copies the bound would not hold.
    let own = context.compute_instance_arrays_memory_usage(placed.len(), &options).unwrap();
    assert!(size > own.output_bytes, "{size} against {own:?}");
    // A child of another device is refused as the build refuses it.
    let elsewhere = Context::new(Device::cpu());
    let cpu_bunny = elsewhere.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let error = context.compute_transform_memory_usage(&transform, &cpu_bunny, &options).unwrap_err();
    assert!(error.to_string().contains("another device"), "{error}");
}

#[test]
fn updates_copies_and_empty_batches_work() {
    let Some(device) = gpu() else { return };
    let context = Context::new(device);
    let (first, second) = (random_soup(300, 11).pack(), random_soup(300, 12).pack());
    let options = BuildOptions { flags: rayd_engine::accel::BuildFlags::ALLOW_UPDATE, ..BuildOptions::default() };
    let accel = context.build_accel(&[BuildInput::Triangles(first.input())], &options).unwrap();
    assert!(accel.info().size_bytes > 0);
    let updated = context.update_accel(&accel, &[BuildInput::Triangles(second.input())]).unwrap();
    let copy = context.copy_accel(&updated, false).unwrap();
    // The reference is updated the same way. Terminate-on-first-hit rays stop at a hit that depends on the BVH and
    // on the traversal order (the CPU walks 8-wide nodes, the GPU 4-wide ones): for them only hit or miss must agree.
    let reference = Context::new(Device::cpu());
    let built = reference.build_accel(&[BuildInput::Triangles(first.input())], &options).unwrap();
    let expected = reference.update_accel(&built, &[BuildInput::Triangles(second.input())]).unwrap();
    let query = Query::closest(RayFormat::Full, HitFormat::TTriid);
    let random = rays(500, 6);
    let packed = pack_rays(&random, RayFormat::Full);
    let (want, _) = trace(&reference, &expected, &query, &packed);
    for accel in [&updated, &copy] {
        let (got, _) = trace(&context, accel, &query, &packed);
        let differing = (0..500)
            .filter(|&i| {
                let (g, w) = (HitFormat::TTriid.read(&got, i), HitFormat::TTriid.read(&want, i));
                match random[i].flags.contains(RayFlags::TERMINATE_ON_FIRST_HIT) {
                    true => g.is_hit() != w.is_hit(),
                    false => g.prim_id != w.prim_id,
                }
            })
            .count();
        assert!(differing == 0, "{differing} rays differ after the update");
    }
    let (hits, counts) = trace(&context, &copy, &query, &[]);
    assert!(hits.is_empty() && counts.is_empty());
    assert_eq!(accel.info().kind, AccelKind::Triangles);
}

/// A 3×4 row-major matrix of `affine`.
fn rows(affine: Affine3A) -> [f32; 12] {
    Placement::rows(&affine)
}

/// An instance of `child`.
fn instance(child: &Arc<Accel>, to_world: Affine3A, instance_id: u32, mask: u8, flags: InstanceFlags) -> Instance {
    Instance { transform: rows(to_world), instance_id, mask, flags, child: Arc::clone(child) }
}

/// An SRT key: scale `s`, quaternion `q`, translation `t` (no shear, no pivot).
fn srt(s: Vec3, q: Quat, t: Vec3) -> [f32; 16] {
    [s.x, 0.0, 0.0, 0.0, s.y, 0.0, 0.0, s.z, 0.0, q.x, q.y, q.z, q.w, t.x, t.y, t.z]
}

/// A graph of every kind of node, three levels of instances and transforms deep, in `context`: the bunny and a
/// soup with masks and a culling-exempt geometry, placed plainly, mirrored (flipped and not), exempt from culling,
/// three times at the same place (ties, broken by instance id), under a static transform, a matrix motion
/// transform and an SRT motion transform (vanishing after its range), beside the vertex-motion bunny, under a
/// motion instance accel; each instance with its own visibility mask.
fn every_kind_of_graph(context: &Context) -> Arc<Accel> {
    let bunny = bunny().pack();
    let soup = random_soup(600, 21).pack();
    let masks: Vec<u8> = (0..600u32).flat_map(|i| (1u32 << (i % 3)).to_le_bytes()).collect();
    let soup_inputs = [input_with_masks(&soup.vertices, &soup.indices, &masks)];
    let bunny_accel = context.build_accel(&[BuildInput::Triangles(bunny.input())], &BuildOptions::default()).unwrap();
    let soup_accel = context.build_accel(&soup_inputs, &BuildOptions::default()).unwrap();
    let (indices, keys, motion) = moving_bunny_inputs();
    let later: Vec<&[u8]> = keys[1..].iter().map(Vec::as_slice).collect();
    let moving_inputs = [BuildInput::Triangles(TriangleInput {
        motion_vertices: &later,
        ..TriangleInput::indexed(&keys[0], &indices)
    })];
    let moving = context.build_accel(&moving_inputs, &BuildOptions { motion, ..BuildOptions::default() }).unwrap();
    let centre = Vec3::splat(0.5);
    let about_centre = |a: Affine3A| Affine3A::from_translation(centre) * a * Affine3A::from_translation(-centre);
    let mirror = about_centre(Affine3A::from_scale(Vec3::new(-1.0, 1.0, 1.0)));
    let shrunk = about_centre(Affine3A::from_scale(Vec3::splat(0.6)));
    let still = context
        .build_transform(
            &TransformInput::Static(rows(Affine3A::from_translation(Vec3::new(0.3, 0.0, 0.1)))),
            &bunny_accel,
        )
        .unwrap();
    let two_keys = MotionOptions { keys: 2, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
    let sliding = TransformInput::MatrixMotion {
        keys: vec![rows(shrunk), rows(Affine3A::from_translation(Vec3::new(0.2, 0.1, 0.0)) * shrunk)],
        motion: two_keys,
    };
    let sliding = context.build_transform(&sliding, &soup_accel).unwrap();
    let turning = TransformInput::SrtMotion {
        keys: (0..3)
            .map(|k| srt(Vec3::splat(0.8), Quat::from_rotation_y(0.6 * k as f32), Vec3::new(0.1, 0.05 * k as f32, 0.2)))
            .collect(),
        motion: MotionOptions { keys: 3, time_begin: 0.1, time_end: 0.9, flags: MotionFlags::END_VANISH },
    };
    let turning = context.build_transform(&turning, &bunny_accel).unwrap();
    let none = InstanceFlags::empty();
    let inner = [
        instance(&bunny_accel, Affine3A::IDENTITY, 7, 0x01, none),
        instance(&bunny_accel, Affine3A::IDENTITY, 3, 0x01, none),
        instance(&bunny_accel, Affine3A::IDENTITY, 5, 0x03, none),
        instance(&bunny_accel, mirror, 8, 0x02, InstanceFlags::FLIP_FACING),
        instance(&bunny_accel, mirror * shrunk, 9, 0x04, none),
        instance(
            &soup_accel,
            Affine3A::from_translation(Vec3::new(0.0, 0.2, 0.0)),
            10,
            0x08,
            InstanceFlags::DISABLE_FACE_CULLING,
        ),
        instance(&still, Affine3A::IDENTITY, 11, 0x10, none),
    ];
    let inner = context.build_instance_accel(&inner, &BuildOptions::default()).unwrap();
    let top = [
        instance(&inner, Affine3A::IDENTITY, 20, 0xFF, none),
        instance(
            &inner,
            Affine3A::from_translation(Vec3::new(0.5, 0.4, -0.3)) * shrunk,
            21,
            0x0F,
            InstanceFlags::FLIP_FACING,
        ),
        instance(&sliding, Affine3A::IDENTITY, 22, 0x30, none),
        instance(&turning, Affine3A::from_translation(Vec3::new(-0.2, 0.0, 0.0)), 23, 0xC0, none),
        instance(&moving, Affine3A::IDENTITY, 24, 0x41, none),
    ];
    context.build_instance_accel(&top, &BuildOptions { motion: two_keys, ..BuildOptions::default() }).unwrap()
}

/// Rays with every visibility mask and times over the motion ranges (and beyond them).
fn graph_rays(count: usize, seed: u64) -> Vec<Ray> {
    let mut rays = rays(count, seed);
    rays.extend(camera_rays(count));
    for (i, ray) in rays.iter_mut().enumerate() {
        ray.visibility = [0xFF, 0x01, 0x02, 0x04, 0x08, 0x10, 0x30, 0xC0, 0x40, 0x00][i % 10];
        ray.time = (i % 23) as f32 / 20.0 - 0.05;
    }
    rays
}

#[test]
fn an_instance_graph_of_every_kind_of_node_agrees_in_every_format_and_query_kind() {
    let Some(device) = gpu() else { return };
    let scene = Scene::built(&device, every_kind_of_graph);
    assert_eq!(scene.gpu.1.info().kind, AccelKind::Instances);
    assert_eq!(scene.gpu.1.info().depth, 4);
    let mut agreement = Agreement::default();
    scene.compare_everything(&graph_rays(500, 31), &mut agreement);
    agreement.check();
    // The graph is hit through every level, and the tie between the three coinciding bunnies goes to id 3.
    let query = Query::closest(RayFormat::Full, HitFormat::Full);
    let rays: Vec<Ray> = camera_rays(400).into_iter().map(|r| Ray { visibility: 0x01, ..r }).collect();
    let (hits, _) = trace(&scene.gpu.0, &scene.gpu.1, &query, &pack_rays(&rays, RayFormat::Full));
    let paths: Vec<Vec<u32>> = (0..rays.len())
        .map(|i| HitFormat::Full.read(&hits, i))
        .filter(|h| h.is_hit())
        .map(|h| h.inst_path.ids().to_vec())
        .collect();
    assert!(paths.len() > 100, "{} of 400 camera rays hit", paths.len());
    assert!(paths.iter().all(|p| p == &[20, 3] || p == &[21, 3] || p == &[24]), "{paths:?}");
}

#[test]
fn geometry_accels_copy_between_devices_and_graphs_stay_on_theirs() {
    let Some(device) = gpu() else { return };
    let (cpu, gpu) = (Context::new(Device::cpu()), Context::new(device));
    let mesh = bunny().pack();
    let options = BuildOptions { flags: rayd_engine::accel::BuildFlags::ALLOW_COMPACTION, ..BuildOptions::default() };
    let on_cpu = cpu.build_accel(&[BuildInput::Triangles(mesh.input())], &options).unwrap();
    let to_gpu = gpu.copy_accel(&on_cpu, true).unwrap();
    let back = cpu.copy_accel(&to_gpu, false).unwrap();
    assert_eq!(to_gpu.info().triangle_count, on_cpu.info().triangle_count);
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    let packed = pack_rays(&camera_rays(2000), RayFormat::OriginTminDirectionTmax);
    let (want, _) = trace(&cpu, &on_cpu, &query, &packed);
    let (got, _) = trace(&gpu, &to_gpu, &query, &packed);
    let (again, _) = trace(&cpu, &back, &query, &packed);
    assert_eq!(want, again, "a copy to the GPU and back traces the same bytes on the CPU");
    let differing = (0..2000)
        .filter(|&i| {
            let (c, g) = (HitFormat::TTriidUV.read(&want, i), HitFormat::TTriidUV.read(&got, i));
            c.prim_id != g.prim_id || !close(c.t, g.t, 1e-4)
        })
        .count();
    assert!(differing <= 1, "{differing} of 2000 rays differ on the copy");
    // Instance accels place accels of their own device, and are copied only there.
    let identity = instance(&on_cpu, Affine3A::IDENTITY, 0, 0xFF, InstanceFlags::empty());
    let error = gpu.build_instance_accel(&[identity], &BuildOptions::default()).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition, "{error}");
    let placed = gpu
        .build_instance_accel(&[instance(&to_gpu, Affine3A::IDENTITY, 0, 0xFF, InstanceFlags::empty())], &options)
        .unwrap();
    let error = cpu.copy_accel(&placed, false).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition, "{error}");
    assert!(error.to_string().contains("geometry accels are"), "{error}");
    let copy = gpu.copy_accel(&placed, true).unwrap();
    let (placed_hits, _) = trace(&gpu, &copy, &query, &packed);
    assert_eq!(placed_hits, got, "an identity instance traces as its child");

    // Another device of the same backend (here a second handle on the one adapter, which the engine treats as it
    // treats a second GPU) shares no memory with the first: a geometry accel is uploaded there; a graph, whose
    // children stay, is not copied there.
    let Some(second) = gpu_with(WgpuOptions::default()) else { return };
    let second = Context::new(second);
    let to_second = second.copy_accel(&to_gpu, false).unwrap();
    assert_eq!(trace(&second, &to_second, &query, &packed).0, got, "the copy on the second device traces the same");
    let error = second.copy_accel(&placed, false).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition, "{error}");
    let over_first = instance(&to_gpu, Affine3A::IDENTITY, 0, 0xFF, InstanceFlags::empty());
    let error = second.build_instance_accel(&[over_first], &BuildOptions::default()).unwrap_err();
    assert!(error.to_string().contains("of another device"), "{error}");
    // Nor does it trace the first device's accels (its kernel would bind another device's buffers).
    let layout = query.output_layout(packed.len()).unwrap();
    let (mut hits, mut counts) = (vec![0; layout.hits], vec![0; layout.counts]);
    let error = second.trace(&to_gpu, &query, &packed, TraceOutput { hits: &mut hits, counts: &mut counts });
    let error = error.unwrap_err();
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition, "{error}");
    assert!(error.to_string().contains("traces accels of its own device only"), "{error}");
}

#[test]
fn a_scene_saved_on_one_backend_loads_on_the_other_and_traces_as_it_did() {
    let Some(device) = gpu() else { return };
    let (cpu, gpu) = (Context::new(Device::cpu()), Context::new(device));
    let mesh = bunny().pack();
    let built = cpu.build_accel(&[BuildInput::Triangles(mesh.input())], &BuildOptions::default()).unwrap();
    let moved = Affine3A::from_translation(Vec3::new(0.05, 0.02, 0.0));
    let placed = [
        instance(&built, Affine3A::IDENTITY, 1, 0xFF, InstanceFlags::empty()),
        instance(&built, moved, 2, 0xFF, InstanceFlags::empty()),
    ];
    let on_cpu = cpu.build_instance_accel(&placed, &BuildOptions::default()).unwrap();
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::Full);
    let packed = pack_rays(&camera_rays(2000), RayFormat::OriginTminDirectionTmax);
    let (want, _) = trace(&cpu, &on_cpu, &query, &packed);

    let to_gpu =
        gpu.deserialize_accel(&cpu.serialize_accel(&on_cpu, &[]).unwrap(), &[]).expect("a CPU blob on the GPU");
    let on_gpu = to_gpu.last().unwrap();
    assert_eq!(on_gpu.info().kind, AccelKind::Instances);
    let (got, _) = trace(&gpu, on_gpu, &query, &packed);
    let hits = (0..2000).filter(|&i| HitFormat::Full.read(&want, i).is_hit()).count();
    let differing = (0..2000)
        .filter(|&i| {
            let (c, g) = (HitFormat::Full.read(&want, i), HitFormat::Full.read(&got, i));
            c.prim_id != g.prim_id || c.inst_path.ids() != g.inst_path.ids() || !close(c.t, g.t, 1e-4)
        })
        .count();
    assert!(hits > 500 && differing <= 1, "{hits} hits; {differing} of 2000 rays differ on the GPU");

    let back = cpu.deserialize_accel(&gpu.serialize_accel(on_gpu, &[]).unwrap(), &[]).expect("a GPU blob on the CPU");
    let (again, _) = trace(&cpu, back.last().unwrap(), &query, &packed);
    assert_eq!(again, want, "the GPU's blob is the host structure the CPU built");
}

#[test]
fn triangles_whose_corners_no_binding_can_hold_are_refused_before_their_build() {
    let Some(device) = gpu() else { return };
    // 2^20 copies of one triangle at 64 motion keys: 3 GiB of corners on the device, more than a binding of any
    // adapter can hold (wgpu's bindings are at most 4 GiB − 1 bytes; 2 GiB and less are usual).
    let vertices: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|x| x.to_le_bytes()).collect();
    let indices: Vec<u8> = [0u32, 1, 2].iter().cycle().take(3 << 20).flat_map(|i| i.to_le_bytes()).collect();
    let moving = vec![&vertices[..]; 63];
    let input = TriangleInput { motion_vertices: &moving, ..TriangleInput::indexed(&vertices, &indices) };
    let motion = MotionOptions { keys: 64, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
    let options = BuildOptions { motion, ..BuildOptions::default() };
    let error = Context::new(device).compute_memory_usage(&[BuildInput::Triangles(input)], &options).unwrap_err();
    assert_eq!(error.kind(), ErrorKind::ResourceExhausted, "{error}");
    let message = error.to_string();
    assert!(message.contains("triangle corners on the device") && message.contains("3221225472 bytes"), "{message}");
}

#[test]
fn an_accel_deeper_than_the_kernels_stack_is_refused_by_name_and_kept_on_the_cpu() {
    let Some(device) = gpu() else { return };
    // Triangles nested in ever smaller copies of each other: the BVH over them is a chain, one level a triangle (64 of
    // them: obvhs's PLOC pairs neighbours where a pass of more stalls). Instance accels over 64 nested copies of the
    // level below, twice, make chains of their own on top of it.
    let mesh = Mesh {
        positions: (0..64)
            .flat_map(|k| {
                let s = 0.97f32.powi(k);
                [Vec3::ZERO, Vec3::new(s, 0.0, 0.0), Vec3::new(0.0, s, s * 0.5)]
            })
            .collect(),
        triangles: (0..64u32).map(|k| [3 * k, 3 * k + 1, 3 * k + 2]).collect(),
    };
    let packed = mesh.pack();
    let inputs = [BuildInput::Triangles(packed.input())];
    let nest = |context: &Context, child: &Arc<Accel>| {
        let copies: Vec<Instance> = (0..64)
            .map(|k| {
                instance(
                    child,
                    Affine3A::from_scale(Vec3::splat(0.97f32.powi(k))),
                    k as u32,
                    0xFF,
                    InstanceFlags::empty(),
                )
            })
            .collect();
        context.build_instance_accel(&copies, &BuildOptions::default())
    };
    let gpu = Context::new(device);
    let error = gpu
        .build_accel(&inputs, &BuildOptions::default())
        .and_then(|geometry| nest(&gpu, &geometry))
        .and_then(|once| nest(&gpu, &once))
        .expect_err("too deep for the GPU");
    assert_eq!(error.kind(), ErrorKind::FailedPrecondition, "{error}");
    assert!(error.to_string().contains("stack entries"), "{error}");
    let cpu = Context::new(Device::cpu());
    let geometry = cpu.build_accel(&inputs, &BuildOptions::default()).unwrap();
    nest(&cpu, &nest(&cpu, &geometry).unwrap()).expect("the CPU has no such limit");
}

#[test]
fn a_build_told_not_to_go_on_before_its_upload_keeps_nothing_on_the_device() {
    let Some(device) = gpu() else { return };
    let packed = random_soup(500, 3).pack();
    let inputs = [BuildInput::Triangles(packed.input())];
    let context = Context::new(device);
    // The host's three questions, then the upload's.
    let asked = std::sync::atomic::AtomicUsize::new(0);
    let go_on = || asked.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1 < 4;
    let stopped = context.build_accel_while(&inputs, &BuildOptions::default(), &go_on).unwrap_err();
    assert_eq!(stopped, rayd_engine::Error::Stopped);
    assert_eq!(asked.into_inner(), 4, "stopped at the upload's question");
    assert!(context.accel_handles().is_empty() && context.memory_in_use() == 0);
    let built = context.build_accel_while(&inputs, &BuildOptions::default(), &|| true).unwrap();
    assert_eq!(context.accel_handles(), [built.handle()]);
}
