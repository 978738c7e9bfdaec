//! Rays made and hits reduced on the CPU in cache-sized parts (`backend::host::PART_RAYS`): the same answers as
//! the rays packed beforehand, traced whole and reduced whole.

mod common;

use std::sync::Arc;

use glam::Vec3;
use rayd_engine::accel::BuildOptions;
use rayd_engine::backend::RaySource;
use rayd_engine::backend::host::PART_RAYS;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::BuildInput;
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::raygen::{Camera, Generator, PixelSampling};
use rayd_engine::reduce::{IdKind, Image, ImageChannel, PixelEncoding, PointCloud, PointEncoding, Reduction};
use rayd_engine::{Accel, Context, Device};

/// 97 × 90 pixels, 3 jittered samples each: 26,190 rays, several parts, none a multiple of a part.
const WIDTH: u32 = 97;
const HEIGHT: u32 = 90;
const SAMPLES: u32 = 3;

/// The bunny on the CPU, and a jittered camera framing it.
fn scene() -> (Context, Arc<Accel>, Generator) {
    let bunny = common::shared_mesh("stanford-bunny");
    let (lo, hi) = bunny.bounds();
    let context = Context::new(Device::cpu());
    let packed = bunny.pack();
    let accel = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let camera = Camera::framing(lo, hi, WIDTH, HEIGHT);
    let generator = Generator::Pinhole(camera, PixelSampling { samples: SAMPLES, jitter_seed: Some(5) });
    generator.check().unwrap();
    assert!(generator.count() as usize > 3 * PART_RAYS);
    (context, accel, generator)
}

/// Every ray of `generator`, made on the server's CPU.
fn generated(generator: &Generator) -> RaySource<'_> {
    RaySource::Generated { generator, first: 0, count: generator.count() as usize }
}

/// (hits, counts) of `query` over `rays` packed beforehand, traced whole.
fn traced_whole(context: &Context, accel: &Accel, query: &Query, rays: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let layout = query.output_layout(rays.len()).unwrap();
    let (mut hits, mut counts) = (vec![0xEE; layout.hits], vec![0xEE; layout.counts]);
    context.trace(accel, query, rays, TraceOutput { hits: &mut hits, counts: &mut counts }).unwrap();
    (hits, counts)
}

#[test]
fn generated_rays_traced_in_parts_give_the_records_of_the_packed_rays() {
    let (context, accel, generator) = scene();
    let queries = [
        Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV),
        Query { kind: QueryKind::Any, ..Query::closest(RayFormat::OriginDirection, HitFormat::Bitmask) },
        Query { kind: QueryKind::Count, ..Query::closest(RayFormat::Full, HitFormat::T) },
        Query { kind: QueryKind::All, max_hits_per_ray: 3, ..Query::closest(RayFormat::Full, HitFormat::TTriid) },
    ];
    for query in queries {
        let (hits, counts) = traced_whole(&context, &accel, &query, &generator.rays(query.ray_format));
        let (mut part_hits, mut part_counts) = (vec![0xEE; hits.len()], vec![0xEE; counts.len()]);
        let out = TraceOutput { hits: &mut part_hits, counts: &mut part_counts };
        let stats = context.trace_source(&accel, &query, generated(&generator), out).unwrap();
        assert_eq!(stats.rays, generator.count(), "{query:?}");
        assert!(part_hits == hits && part_counts == counts, "{query:?}");
    }
    let none = RaySource::Generated { generator: &generator, first: 7, count: 0 };
    let query = queries[0];
    let stats = context.trace_source(&accel, &query, none, TraceOutput { hits: &mut [], counts: &mut [] }).unwrap();
    assert_eq!(stats.rays, 0, "no rays, no records");
    let (partial, stats) = context.trace_reduced(&accel, &query, none, 7, &Reduction::Counts).unwrap();
    assert_eq!((Reduction::Counts.finish(partial, 0).unwrap().bytes.len(), stats.rays), (24, 0));
}

#[test]
fn generated_rays_reduced_in_parts_give_the_reduction_of_every_hit() {
    let (context, accel, generator) = scene();
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    let rays = generator.count();
    let image = |channel, encoding| {
        Reduction::Image(Image { width: WIDTH, rays_per_pixel: SAMPLES, channel, encoding, near: 0.0, far: 1.0 })
    };
    let cloud = PointCloud { encoding: PointEncoding::Int32, step: 1e-4, origin: Vec3::ZERO, ray_indices: true };
    let reductions = [
        Reduction::Counts,
        Reduction::Histogram { bins: 16, t_min: 0.0, t_max: 1.0 },
        Reduction::IdCounts(IdKind::Primitive),
        // 270 rays a group: parts of 31 groups (8,370 rays).
        Reduction::NearestPerGroup { group: 270 },
        image(ImageChannel::Depth, PixelEncoding::Float32),
        image(ImageChannel::Normal, PixelEncoding::Unorm16),
        Reduction::PointCloud(cloud),
        Reduction::CompactHits { t_far: 1.0 },
    ];
    for reduction in reductions {
        reduction.check(&query, rays).unwrap();
        let traced = reduction.traced_query(&query);
        let packed = generator.rays(traced.ray_format);
        let (hits, counts) = traced_whole(&context, &accel, &traced, &packed);
        let whole = reduction.reduce_all(&traced, &packed, &hits, &counts).unwrap();
        let (partial, stats) = context.trace_reduced(&accel, &query, generated(&generator), 0, &reduction).unwrap();
        assert_eq!(stats.rays, rays, "{reduction:?}");
        assert_eq!(reduction.finish(partial, rays).unwrap(), whole, "{reduction:?}");
    }
}

/// A camera of one row of the most rays a camera may make (2^48: 2^31 pixels of 2^17 samples, and an odd row just
/// under it): a range of its rays is traced as consecutive rays. Rows wider still (2^62 rays, more than `usize` can
/// count four of) once made the tiles of a band overflow; cameras that large are refused now.
#[test]
fn rays_of_the_widest_rows_a_camera_may_make_are_traced_as_consecutive_rays() {
    let (context, accel, framing) = scene();
    let Generator::Pinhole(camera, _) = framing else { unreachable!() };
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriid);
    let row = |width, samples| {
        Generator::Pinhole(Camera { width, height: 1, ..camera }, PixelSampling { samples, jitter_seed: None })
    };
    let refused = row(1 << 31, 1 << 31).check().unwrap_err();
    assert!(refused.to_string().contains("generator.samples_per_pixel"), "{refused}");
    for (width, samples) in [(1 << 31, 1 << 17), (2_147_549_185, 131_068)] {
        let generator = row(width, samples);
        generator.check().unwrap();
        assert_eq!(generator.image_rows(0), None, "{width} × {samples}");
        let count = 3 * PART_RAYS + 17;
        let mut rays = vec![0; count * query.ray_format.size()];
        generator.fill(query.ray_format, 5, &mut rays);
        let (hits, counts) = traced_whole(&context, &accel, &query, &rays);
        let mut part_hits = vec![0xEE; hits.len()];
        let source = RaySource::Generated { generator: &generator, first: 5, count };
        let out = TraceOutput { hits: &mut part_hits, counts: &mut [] };
        assert_eq!(context.trace_source(&accel, &query, source, out).unwrap().rays, count as u64);
        assert!(part_hits == hits && counts.is_empty(), "{width} × {samples}");
        let (partial, _) = context.trace_reduced(&accel, &query, source, 5, &Reduction::Counts).unwrap();
        assert_eq!(Reduction::Counts.finish(partial, count as u64).unwrap().bytes.len(), 24);
    }
}
