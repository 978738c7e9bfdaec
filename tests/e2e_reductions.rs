//! End to end: reductions made by the server. For every kind (counts, depth and normal images in each encoding,
//! histogram, per-id counts, nearest per group, point clouds) over generated rays cut into several pieces, the
//! reduction that comes back is byte for byte the engine's reduction of the full hits of the same rays traced and
//! returned whole; a reduction over packed rays likewise; per-id counts by geometry on an accel of two geometries,
//! and by geometry and instance on an instance accel placing it twice, likewise; bad combinations answer INVALID_ARGUMENT naming the field,
//! a reduction larger than a message RESOURCE_EXHAUSTED naming the limit;
//! calls compressed with zstd or gzip answer the same bytes; generated and reduced traces on an `OpenStream` stream
//! answer what single calls do.

mod common;
mod daemon;

use bytes::Bytes;
use daemon::Daemon;
use rayd_client::{Client, ClientOptions, proto};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{InstanceFlags, InstanceRecord};
use rayd_engine::glam::Vec3;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind};
use rayd_engine::raygen::{Camera, Generator, Lidar, PixelSampling};
use rayd_engine::reduce::{IdKind, Image, ImageChannel, PixelEncoding, PointCloud, PointEncoding, Reduced, Reduction};
use tonic::Code;
use tonic::codec::CompressionEncoding;

/// Every reduction kind, with the generator it is tried on: a jittered camera of 3 rays a pixel (3,600 rays, so
/// pieces of the server's 1,024-ray kind end on pixel boundaries only if it aligns them) and a lidar.
fn cases(mesh: &rayd_engine::mesh::Mesh) -> Vec<(Generator, Reduction)> {
    let (lo, hi) = mesh.bounds();
    let camera =
        Generator::Pinhole(Camera::framing(lo, hi, 40, 30), PixelSampling { samples: 3, jitter_seed: Some(7) });
    let lidar = Generator::Lidar(Lidar {
        origin: (lo + hi) * 0.5 + Vec3::new(0.0, 0.0, (hi - lo).z),
        forward: Vec3::NEG_Z,
        up: Vec3::Y,
        elevations_degrees: vec![-15.0, -5.0, 0.0, 5.0, 15.0],
        steps: 400,
        min_range: 0.001,
        max_range: 10.0,
        time: (0.0, 0.0),
    });
    let (near, far) = (0.1, 0.4);
    let image = |channel, encoding| Image { width: 40, rays_per_pixel: 3, channel, encoding, near, far };
    // Steps of a micrometre: an i16 holds ±3.3 cm of the bunny's 16 cm, so some of its points are dropped.
    let cloud = |encoding| PointCloud { encoding, step: 1e-6, origin: (lo + hi) * 0.5, ray_indices: true };
    let mut cases = vec![
        (camera.clone(), Reduction::Counts),
        (camera.clone(), Reduction::Histogram { bins: 64, t_min: 0.15, t_max: 0.3 }),
        // As many bins as a histogram may have: far more than a piece has hits.
        (camera.clone(), Reduction::Histogram { bins: 1 << 20, t_min: 0.15, t_max: 0.3 }),
        (camera.clone(), Reduction::IdCounts(IdKind::Primitive)),
        (camera.clone(), Reduction::IdCounts(IdKind::Instance)),
        (camera.clone(), Reduction::NearestPerGroup { group: 3 }),
        (camera.clone(), Reduction::CompactHits { t_far: 1.0 }),
        (lidar.clone(), Reduction::PointCloud(cloud(PointEncoding::Float32))),
        (lidar.clone(), Reduction::PointCloud(cloud(PointEncoding::Int16))),
        (lidar, Reduction::PointCloud(cloud(PointEncoding::Int32))),
    ];
    for channel in [ImageChannel::Depth, ImageChannel::Normal] {
        for encoding in [PixelEncoding::Float32, PixelEncoding::Unorm16, PixelEncoding::Png] {
            cases.push((camera.clone(), Reduction::Image(image(channel, encoding))));
        }
    }
    cases
}

/// Traces `generator`'s rays on `accel` with `query`, reduced by the server, and asserts that the answer is byte for
/// byte the engine's reduction of the full hits of the same rays traced and returned whole, with as many items
/// dropped, every ray traced and something hit. Returns that reduction of the full hits.
async fn assert_reduced_as_full_hits(
    client: &Client,
    accel: &str,
    query: &Query,
    generator: &Generator,
    reduction: &Reduction,
) -> Reduced {
    let what = format!("{reduction:?} of {generator:?} with a {:?} query on {accel}", query.kind);
    let reduced = client.trace_generated_reduced(accel, query, generator, reduction).await.expect(&what);
    let traced = reduction.traced_query(query);
    let rays = generator.rays(traced.ray_format);
    let full = client.trace(accel, &traced, Bytes::from(rays.clone())).await.unwrap();
    let expected = reduction.reduce_all(&traced, &rays, full.hits(), full.counts()).unwrap();
    assert!(reduced.data == expected.bytes, "{what}: {} bytes, {} expected", reduced.data.len(), expected.bytes.len());
    assert_eq!(reduced.dropped, expected.dropped, "{what}");
    assert_eq!(reduced.stats.rays, generator.count(), "{what}");
    assert!(reduced.stats.rays_hit > 0 && !reduced.data.is_empty(), "{what}: something is hit");
    expected
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reductions_equal_the_reduction_of_full_hits() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let bunny = common::shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    for (generator, reduction) in cases(&bunny) {
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriid);
        let what = format!("{reduction:?} of {generator:?}");
        let expected = assert_reduced_as_full_hits(&client, "bunny", &query, &generator, &reduction).await;
        if let Reduction::PointCloud(PointCloud { encoding: PointEncoding::Int16, .. }) = reduction {
            assert!(expected.dropped > 0, "{what}: some returns lie beyond an i16 of micrometre steps");
        }

        // The same reduction of the rays sent, with a counting query.
        let all = Query { kind: QueryKind::All, max_hits_per_ray: 3, ..query };
        if reduction.check(&all, generator.count()).is_ok() {
            let rays = generator.rays(all.ray_format);
            let sent = client.trace_reduced("bunny", &all, Bytes::from(rays.clone()), &reduction).await.expect(&what);
            let traced = reduction.traced_query(&all);
            let full = client.trace("bunny", &traced, Bytes::from(rays.clone())).await.unwrap();
            let expected = reduction.reduce_all(&traced, &rays, full.hits(), full.counts());
            assert!(sent.data == expected.unwrap().bytes, "{what} with an `all` query of sent rays");
        }
    }
}

/// A build input of `mesh`'s triangles (float3 vertices, u32×3 indices), inline.
fn inline_triangles(mesh: &Mesh) -> proto::BuildInput {
    let packed = mesh.pack();
    let inline =
        |bytes: Vec<u8>| Some(proto::DataSource { source: Some(proto::data_source::Source::Inline(bytes.into())) });
    proto::BuildInput {
        input: Some(proto::build_input::Input::Triangles(proto::TriangleInput {
            vertices: inline(packed.vertices),
            vertex_format: proto::VertexFormat::Float3.into(),
            indices: inline(packed.indices),
            index_format: proto::IndexFormat::Uint32x3.into(),
            ..Default::default()
        })),
    }
}

/// The ids an `IdCounts` answer counts hits of, ascending (12 bytes an id: id i32 | count u64).
fn counted_ids(bytes: &[u8]) -> Vec<i32> {
    bytes.chunks_exact(12).map(|pair| i32::from_le_bytes(pair[..4].try_into().unwrap())).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn id_counts_by_geometry_and_instance_equal_the_reduction_of_full_hits() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    // Two spheres side by side, geometries 0 and 1 of one accel; an instance accel places that accel twice, one
    // above the other, as instances 7 and 8.
    let spheres = [common::icosphere(2, Vec3::new(-1.5, 0.0, 0.0)), common::icosphere(2, Vec3::new(1.5, 0.0, 0.0))];
    let request = proto::BuildAccelRequest {
        name: "spheres".into(),
        inputs: spheres.iter().map(inline_triangles).collect(),
        ..Default::default()
    };
    let geometries = client.build(request).await.unwrap();
    let placed = |instance_id, y| InstanceRecord {
        transform: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, y, 0.0, 0.0, 1.0, 0.0],
        instance_id,
        mask: 0xFF,
        flags: InstanceFlags::empty(),
        child: 0,
    };
    let instances = [placed(7, -1.5), placed(8, 1.5)];
    let pair = client.build_instances("pair", "", &["spheres"], &instances, BuildFlags::empty()).await.unwrap();
    // A jittered camera of 3 rays a pixel that sees the whole accel.
    let camera = |info: &proto::AccelInfo| {
        let bounds = info.bounds.unwrap();
        let corner = |v: Option<proto::Vec3>| v.map(|v| Vec3::new(v.x, v.y, v.z)).unwrap();
        let frame = Camera::framing(corner(bounds.min), corner(bounds.max), 40, 30);
        Generator::Pinhole(frame, PixelSampling { samples: 3, jitter_seed: Some(7) })
    };
    let closest = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriid);
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 3, ..closest };
    for (accel, info, kind, ids) in [
        ("spheres", &geometries, IdKind::Geometry, [0, 1]),
        ("pair", &pair, IdKind::Geometry, [0, 1]),
        ("pair", &pair, IdKind::Instance, [7, 8]),
    ] {
        for query in [closest, all] {
            let reduction = Reduction::IdCounts(kind);
            let expected = assert_reduced_as_full_hits(&client, accel, &query, &camera(info), &reduction).await;
            let what = format!("{kind:?} on {accel}, {:?} query", query.kind);
            assert_eq!(counted_ids(&expected.bytes), ids, "{what}: every id is hit");
        }
    }
}

/// A float32 depth image over `0 .. far`, its width and samples taken from the camera generator.
fn float_depths(far: f32) -> Image {
    Image {
        width: 0,
        rays_per_pixel: 0,
        channel: ImageChannel::Depth,
        encoding: PixelEncoding::Float32,
        near: 0.0,
        far,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_reductions_name_their_field() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let bunny = common::shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    let (lo, hi) = bunny.bounds();
    let camera = Camera::framing(lo, hi, 8, 8);
    let rays = Bytes::from(camera.rays(RayFormat::OriginDirection));
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let refused = |error: rayd_client::Error, code: Code, field: &str| {
        assert_eq!(error.code(), code, "{error}");
        assert!(error.to_string().contains(field), "{error} names {field}");
    };
    let image = float_depths(0.0);
    // Packed rays carry no camera to take the width from.
    let error = client.trace_reduced("bunny", &query, rays.clone(), &Reduction::Image(image)).await.unwrap_err();
    refused(error, Code::InvalidArgument, "reduction.image.width");
    let seven = Reduction::Image(Image { width: 7, ..image });
    let error = client.trace_reduced("bunny", &query, rays.clone(), &seven).await.unwrap_err();
    refused(error, Code::InvalidArgument, "reduction.image.width");
    let any_count = Query { kind: QueryKind::Count, ..query };
    let eight = Reduction::Image(Image { width: 8, ..image });
    let error = client.trace_reduced("bunny", &any_count, rays.clone(), &eight).await.unwrap_err();
    refused(error, Code::InvalidArgument, "query.query");
    let histogram = Reduction::Histogram { bins: 0, t_min: 0.0, t_max: 1.0 };
    let error = client.trace_reduced("bunny", &query, rays.clone(), &histogram).await.unwrap_err();
    refused(error, Code::InvalidArgument, "reduction.histogram.bins");
    // A camera generator gives the image its width; the 8×8 depths come back.
    let centres = PixelSampling { samples: 1, jitter_seed: None };
    let generated = Generator::Pinhole(camera, centres);
    let depths = client.trace_generated_reduced("bunny", &query, &generated, &Reduction::Image(image)).await.unwrap();
    assert_eq!(depths.data.len(), 8 * 8 * 4);
    // Its samples, when an image reduction cannot take that many rays a pixel, are named as the camera's.
    let crowded = Generator::Pinhole(camera, PixelSampling { samples: (1 << 16) + 1, jitter_seed: None });
    let error = client.trace_generated_reduced("bunny", &query, &crowded, &Reduction::Image(image)).await.unwrap_err();
    refused(error, Code::InvalidArgument, "generator.samples_per_pixel");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reduction_larger_than_a_message_is_refused_by_the_limit() {
    // 1 MiB: the bunny's 1.25 MB of vertices and indices are uploaded in chunks the client fits to the limit.
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_MESSAGE_BYTES", "1048576")]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let bunny = common::shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    let (lo, hi) = bunny.bounds();
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let depth = |side: u32| {
        let camera =
            Generator::Pinhole(Camera::framing(lo, hi, side, side), PixelSampling { samples: 1, jitter_seed: None });
        (camera, Reduction::Image(float_depths(1.0)))
    };
    // 600 × 600 float32 depths are 1,440,000 bytes: more than a 1 MiB message.
    let (camera, image) = depth(600);
    let error = client.trace_generated_reduced("bunny", &query, &camera, &image).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
    assert!(error.to_string().contains("the reduction's 1440000 bytes"), "{error}");
    assert!(error.to_string().contains("max_message_bytes"), "{error}");
    // 500 × 500 are 1,000,000 bytes: they fit.
    let (camera, image) = depth(500);
    let fits = client.trace_generated_reduced("bunny", &query, &camera, &image).await.unwrap();
    assert_eq!(fits.data.len(), 500 * 500 * 4);
    // The points of 600 × 600 rays (16 bytes a hit, about 2 MB), whose size only the trace tells: refused once the
    // pieces traced so far have passed the limit, before the rest are traced.
    let (camera, _) = depth(600);
    let points = PointCloud { encoding: PointEncoding::Float32, step: 1.0, origin: Vec3::ZERO, ray_indices: true };
    let cloud = Reduction::PointCloud(points);
    let error = client.trace_generated_reduced("bunny", &query, &camera, &cloud).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
    assert!(error.to_string().contains("the reduction's records so far"), "{error}");
    assert!(error.to_string().contains("max_message_bytes"), "{error}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn generators_and_reductions_on_a_stream_answer_what_single_calls_do() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let bunny = common::shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriid);
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 3, ..query };
    let cases = cases(&bunny);

    // Every case enqueued on one stream: generated and reduced; the same rays sent and reduced (with an `all`
    // query where the reduction takes one); the generated rays' full hits.
    let stream = client.create_stream().await.unwrap();
    let mut enqueued = Vec::new();
    for (generator, reduction) in &cases {
        let generated = stream.trace_generated_reduced("bunny", &query, generator, reduction).await.unwrap();
        let sent_query = if reduction.check(&all, generator.count()).is_ok() { all } else { query };
        let rays = Bytes::from(generator.rays(sent_query.ray_format));
        let sent = stream.trace_reduced("bunny", &sent_query, rays.clone(), reduction).await.unwrap();
        let full = stream.trace_generated("bunny", &query, generator).await.unwrap();
        enqueued.push((generated, (sent_query, rays, sent), full));
    }
    stream.synchronize().await.unwrap();

    for ((generator, reduction), (generated, (sent_query, rays, sent), full)) in cases.iter().zip(enqueued) {
        let what = format!("{reduction:?} of {generator:?} on a stream");
        let expected = client.trace_generated_reduced("bunny", &query, generator, reduction).await.unwrap();
        let generated = generated.wait().await.expect(&what);
        assert!(
            generated.data == expected.data,
            "{what}: {} bytes, {} expected",
            generated.data.len(),
            expected.data.len()
        );
        assert_eq!((generated.dropped, generated.stats.rays), (expected.dropped, generator.count()), "{what}");
        let expected = client.trace_reduced("bunny", &sent_query, rays, reduction).await.unwrap();
        assert!(sent.wait().await.expect(&what).data == expected.data, "{what}: rays sent, {:?}", sent_query.kind);
        let expected = client.trace_generated("bunny", &query, generator).await.unwrap();
        let full = full.wait().await.expect(&what);
        assert!(full.hits() == expected.hits() && full.hits().len() as u64 == generator.count() * 8, "{what}: hits");
    }
    stream.finish().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compressed_calls_answer_the_same_bytes() {
    let daemon = Daemon::start(&[]);
    let plain = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let bunny = common::shared_mesh("stanford-bunny");
    plain.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    let (lo, hi) = bunny.bounds();
    let rays = Bytes::from(Camera::framing(lo, hi, 64, 64).rays(RayFormat::OriginDirection));
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriidUV);
    let expected = plain.trace("bunny", &query, rays.clone()).await.unwrap();
    for encoding in [CompressionEncoding::Zstd, CompressionEncoding::Gzip] {
        let options = ClientOptions { compression: Some(encoding), ..ClientOptions::default() };
        let compressed = Client::connect(&daemon.url(), options).await.unwrap();
        let traced = compressed.trace("bunny", &query, rays.clone()).await.expect("a compressed trace");
        assert!(traced.hits() == expected.hits(), "{encoding:?}: the same hits");
    }
}
