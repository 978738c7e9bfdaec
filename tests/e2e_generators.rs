//! End to end: ray generators expanded by the server. For each kind (pinhole with jittered samples, orthographic
//! through pixel centres and jittered, lidar with per-ray time, sphere and hemisphere sampling around surface points)
//! and each query kind, the hits of a
//! `TraceBatch` carrying only the generator are byte for byte those of the same rays expanded on the client
//! (`Generator::rays`) and sent; bad numbers answer INVALID_ARGUMENT naming the field, too many rays in one call
//! RESOURCE_EXHAUSTED naming the limit, and a range of a generator traces as the same rays sent. Secondary rays
//! (reflections, shadow rays) made by the server from a hits buffer trace as the same rays made on the client from
//! the downloaded hits.

mod common;
mod daemon;

use bytes::Bytes;
use daemon::Daemon;
use rayd_client::convert::{generator_to_proto, trace_query};
use rayd_client::{Client, ClientOptions, PrimaryRays, SecondaryRays};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::glam::Vec3;
use rayd_engine::query::{Query, QueryKind};
use rayd_engine::raygen::{
    Bounce, Camera, Generator, Lidar, Orthographic, PixelSampling, Primary, Secondary, SphereSampling,
};
use rayd_proto::rayd_client::RaydClient;
use rayd_proto::{self as proto, trace_batch_request};
use tonic::Code;

/// One generator of each kind, aimed at the box `[lo, hi]`, with surface points from `mesh`; cameras with and
/// without jitter, sphere sampling with and without normals.
fn generators(mesh: &rayd_engine::mesh::Mesh) -> Vec<Generator> {
    let (lo, hi) = mesh.bounds();
    let centre = (lo + hi) * 0.5;
    let camera = Camera::framing(lo, hi, 40, 30);
    let jittered = PixelSampling { samples: 3, jitter_seed: Some(11) };
    let orthographic = Orthographic {
        eye: centre + Vec3::Z * (hi - lo).length(),
        target: centre,
        up: Vec3::Y,
        view_height: (hi - lo).y * 1.2,
        width: 32,
        height: 32,
    };
    let lidar = Lidar {
        origin: centre + Vec3::new(0.0, 0.0, (hi - lo).z),
        forward: Vec3::NEG_Z,
        up: Vec3::Y,
        elevations_degrees: vec![-20.0, -10.0, 0.0, 10.0, 20.0],
        steps: 180,
        min_range: 0.001,
        max_range: 10.0,
        time: (0.0, 0.1),
    };
    let triangles = &mesh.triangles[..50];
    let corners = |t: &[u32; 3]| t.map(|i| mesh.positions[i as usize]);
    let points = triangles.iter().map(|t| corners(t).iter().sum::<Vec3>() / 3.0).collect();
    let normals = triangles.iter().map(|t| {
        let [a, b, c] = corners(t);
        (b - a).cross(c - a)
    });
    let sphere = SphereSampling {
        points,
        normals: normals.collect(),
        samples: 16,
        min_distance: 1e-4,
        max_distance: 0.05,
        seed: 5,
    };
    // A seed with both 32-bit words set, and directions uniform on the whole sphere around the same points.
    let jittered_orthographic = PixelSampling { samples: 2, jitter_seed: Some(0x0123_4567_89ab_cdef) };
    let uniform_sphere = SphereSampling { normals: Vec::new(), seed: 6, ..sphere.clone() };
    vec![
        Generator::Pinhole(camera, jittered),
        Generator::Orthographic(orthographic, PixelSampling { samples: 1, jitter_seed: None }),
        Generator::Orthographic(orthographic, jittered_orthographic),
        Generator::Lidar(lidar),
        Generator::Sphere(sphere),
        Generator::Sphere(uniform_sphere),
    ]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn generated_rays_trace_as_the_same_rays_sent() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let bunny = common::shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    for generator in generators(&bunny) {
        generator.check().unwrap();
        for kind in [QueryKind::Closest, QueryKind::Any, QueryKind::All, QueryKind::Count] {
            let query = Query {
                kind,
                max_hits_per_ray: 4,
                ..Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::TTriidUV)
            };
            let what = format!("{kind:?} of {generator:?}");
            let generated = client.trace_generated("bunny", &query, &generator).await.expect(&what);
            let sent = client.trace("bunny", &query, Bytes::from(generator.rays(query.ray_format))).await.unwrap();
            assert_eq!(generated.rays() as u64, generator.count(), "{what}");
            assert!(generated.hits() == sent.hits() && generated.counts() == sent.counts(), "{what}");
            assert!(generated.stats().rays_hit > 0, "{what}: something is hit");
        }
    }

    let bad_fov = Camera { fov_y_degrees: 0.0, ..Camera::framing(Vec3::ZERO, Vec3::ONE, 4, 4) };
    let centres = PixelSampling { samples: 1, jitter_seed: None };
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
    let error = client.trace_generated("bunny", &query, &Generator::Pinhole(bad_fov, centres)).await.unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(error.to_string().contains("generator.fov_y_degrees"), "{error}");

    // One call for more rays than a batch may hold (the client would split it into ranges that fit).
    let mut raw = RaydClient::connect(daemon.url()).await.unwrap();
    let request = |generator: proto::RayGenerator| proto::TraceBatchRequest {
        query: Some(trace_query("bunny", &query)),
        rays: Some(trace_batch_request::Rays::RaysGenerator(generator)),
        ..Default::default()
    };
    let huge = Generator::Pinhole(Camera::framing(Vec3::ZERO, Vec3::ONE, 8192, 8192), centres);
    let Err(status) = raw.trace_batch(request(generator_to_proto(&huge))).await else { panic!("too many rays traced") };
    assert_eq!(status.code(), Code::ResourceExhausted, "{status}");
    assert!(status.message().contains("(rays_generator): 67108864 exceeds limits.max_rays_per_batch"), "{status}");
    let past_the_end = proto::RayGenerator { first_ray: 8192 * 8192, ..generator_to_proto(&huge) };
    let Err(status) = raw.trace_batch(request(past_the_end)).await else { panic!("a range past the end traced") };
    assert_eq!(status.code(), Code::InvalidArgument, "{status}");
    assert!(status.message().contains("generator.first_ray"), "{status}");
    let range = proto::RayGenerator { first_ray: 100, ray_count: 20, ..generator_to_proto(&huge) };
    let hits = raw.trace_batch(request(range)).await.unwrap().into_inner().hits;
    let mut rays = vec![0u8; 20 * query.ray_format.size()];
    huge.fill(query.ray_format, 100, &mut rays);
    let expected = client.trace("bunny", &query, Bytes::from(rays)).await.unwrap();
    assert!(hits == expected.hits(), "a range traces as the same rays sent");
    // An image whose pixels the camera gives: from the start of a row, its rows; from within one, refused (its
    // pixels would straddle the camera's rows).
    let image = proto::Reduction { kind: Some(proto::reduction::Kind::Image(proto::ImageReduction::default())) };
    let imaged = |first_ray| proto::TraceBatchRequest {
        reduction: Some(image),
        ..request(proto::RayGenerator { first_ray, ray_count: 2 * 8192, ..generator_to_proto(&huge) })
    };
    let rows = raw.trace_batch(imaged(3 * 8192)).await.unwrap().into_inner();
    assert_eq!(rows.reduced.unwrap().data.len(), 2 * 8192 * 4, "two rows of float32 depths");
    let Err(status) = raw.trace_batch(imaged(3 * 8192 + 5)).await else { panic!("an image from within a row") };
    assert_eq!(status.code(), Code::InvalidArgument, "{status}");
    assert!(status.message().contains("generator.first_ray"), "{status}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn secondary_rays_from_a_hits_buffer_trace_as_the_same_rays_made_on_the_client() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let bunny = common::shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    let (lo, hi) = bunny.bounds();
    let camera =
        Generator::Pinhole(Camera::framing(lo, hi, 48, 36), PixelSampling { samples: 2, jitter_seed: Some(9) });
    let format = RayFormat::OriginTminDirectionTmaxTime;
    let buffer = |name: &str| proto::BufferRef { r#ref: Some(proto::buffer_ref::Ref::Name(name.into())) };

    // The primary trace leaves its hits (with normals) on the server; its rays are also uploaded, for the variant
    // whose primaries are a rays buffer.
    let mut raw = RaydClient::connect(daemon.url()).await.unwrap();
    let primary_query = Query::closest(format, HitFormat::Full);
    let request = proto::TraceBatchRequest {
        query: Some(trace_query("bunny", &primary_query)),
        rays: Some(trace_batch_request::Rays::RaysGenerator(generator_to_proto(&camera))),
        hits_buffer_name: "primary-hits".into(),
        ..Default::default()
    };
    let written = raw.trace_batch(request).await.unwrap().into_inner();
    let hits = client.download_buffer(&written.hits_buffer.unwrap().id).await.unwrap();
    client.upload_buffer("primary-rays", Bytes::from(camera.rays(format))).await.unwrap();

    let light = hi + (hi - lo);
    for (bounce, kind) in [(Bounce::Reflect, QueryKind::Closest), (Bounce::TowardsLight(light), QueryKind::Any)] {
        let query = Query { kind, ..Query::closest(format, HitFormat::TTriid) };
        let offset = 1e-4;
        // The client's expansion of the same rays, from the downloaded hits, traced as rays sent.
        let made_here = Generator::Secondary(Secondary {
            primary: Primary::Generated(Box::new(camera.clone())),
            hits: hits.clone(),
            bounce,
            offset,
        });
        let sent = client.trace("bunny", &query, Bytes::from(made_here.rays(format))).await.unwrap();
        assert!(sent.stats().rays_hit > 0 && sent.stats().rays_hit < camera.count(), "{bounce:?}: some rays hit");
        for primary in [PrimaryRays::Generated(camera.clone()), PrimaryRays::Buffer(buffer("primary-rays"), format)] {
            let what = format!("{bounce:?} of {primary:?}");
            let secondary = SecondaryRays { primary, hits_buffer: buffer("primary-hits"), bounce, offset };
            let traced = client.trace_secondary("bunny", &query, &secondary).await.expect(&what);
            assert_eq!(traced.rays() as u64, camera.count(), "{what}");
            assert!(traced.hits() == sent.hits(), "{what}: the hits of the rays made on the client");
        }
        // The same generator with its primaries and hits inline.
        let inline = client.trace_generated("bunny", &query, &made_here).await.unwrap();
        assert!(inline.hits() == sent.hits(), "{bounce:?} inline");
    }

    // Hits that are not one record a primary ray, and a buffer that does not exist.
    let short = client.upload_buffer("short-hits", hits.slice(..80 * 10)).await.unwrap();
    let query = Query::closest(format, HitFormat::T);
    let refused = |hits_buffer| SecondaryRays {
        primary: PrimaryRays::Generated(camera.clone()),
        hits_buffer,
        bounce: Bounce::Reflect,
        offset: 0.0,
    };
    let error = client.trace_secondary("bunny", &query, &refused(buffer(&short.name))).await.unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(error.to_string().contains("generator.secondary.primary_hits"), "{error}");
    let error = client.trace_secondary("bunny", &query, &refused(buffer("no-such-hits"))).await.unwrap_err();
    assert_eq!(error.code(), Code::NotFound, "{error}");
}
