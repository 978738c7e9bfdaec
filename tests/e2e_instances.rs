//! End to end against the real `rayd`: instance accels (rayd's records and Prime's form) and static transforms
//! built through `rayd-client`, traced with the full hit format (instance paths), the `max_graph_depth` limit,
//! children that cannot be destroyed while placed, and bad instance inputs refused by field.

mod common;
mod daemon;

use bytes::Bytes;
use common::{f32_at, pack_rays, u32_at};
use daemon::Daemon;
use rayd_client::{Client, ClientOptions, proto};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, Ray, RayFormat};
use rayd_engine::geometry::{InstanceFlags, InstanceRecord};
use rayd_engine::glam::{Vec3, Vec3A};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use tonic::Code;

/// 4-byte words of a `full` hit record.
const FULL_WORDS: usize = 20;

/// A 3×4 row-major translation.
fn translation(x: f32, y: f32, z: f32) -> [f32; 12] {
    [1.0, 0.0, 0.0, x, 0.0, 1.0, 0.0, y, 0.0, 0.0, 1.0, z]
}

/// An instance record of child `child` with id `id`, visible to every ray.
fn record(child: u32, id: u32, transform: [f32; 12]) -> InstanceRecord {
    InstanceRecord { transform, instance_id: id, mask: 0xFF, flags: InstanceFlags::empty(), child }
}

/// Full-format hits of rays straight down from z = 10 at each `(x, y)`: (t, instance path) per ray.
async fn down_at(client: &Client, accel: &str, points: &[(f32, f32)]) -> Vec<(f32, Vec<u32>)> {
    let rays: Vec<Ray> = points
        .iter()
        .map(|&(x, y)| Ray { origin: Vec3A::new(x, y, 10.0), direction: -Vec3A::Z, ..Ray::default() })
        .collect();
    let query = Query::closest(RayFormat::Full, HitFormat::Full);
    let traced = client.trace(accel, &query, Bytes::from(pack_rays(&rays, RayFormat::Full))).await.unwrap();
    let hits = traced.hits();
    (0..points.len())
        .map(|r| {
            let path = (0..u32_at(hits, FULL_WORDS * r + 10) as usize).map(|s| u32_at(hits, FULL_WORDS * r + 12 + s));
            (f32_at(hits, FULL_WORDS * r), path.collect())
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn instance_accels_and_transforms_trace_through_the_service() {
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_GRAPH_DEPTH", "3"), ("RAYD_LIMITS_MAX_ACCEL_BYTES", "1000000")]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let limits = client.server_info().await.unwrap().limits.unwrap();
    assert_eq!((limits.max_graph_depth, limits.max_accel_bytes), (3, 1_000_000));
    let triangle = common::unit_triangle();
    client.build_mesh("tri", &triangle, "", BuildFlags::empty()).await.unwrap();
    let lifted = client.build_transform("lifted", "", "tri", translation(0.0, 0.0, 2.0)).await.unwrap();
    assert_eq!((lifted.kind(), lifted.depth), (proto::AccelKind::Transform, 2));
    let instances = [
        record(0, 7, translation(0.0, 0.0, 5.0)),
        record(0, 8, translation(3.0, 0.0, 5.0)),
        record(1, 9, translation(10.0, 0.0, 0.0)),
    ];
    let scene = client.build_instances("scene", "", &["tri", "lifted"], &instances, BuildFlags::empty()).await.unwrap();
    assert_eq!(
        (scene.kind(), scene.instance_count, scene.depth, scene.triangle_count),
        (proto::AccelKind::Instances, 3, 3, 0)
    );
    let bounds = scene.bounds.unwrap();
    assert_eq!((bounds.min.unwrap().x, bounds.max.unwrap().x, bounds.max.unwrap().z), (0.0, 11.0, 5.0));

    let hits = down_at(&client, "scene", &[(0.25, 0.25), (3.25, 0.25), (10.25, 0.25), (5.0, 5.0)]).await;
    assert_eq!(hits[0], (5.0, vec![7]));
    assert_eq!(hits[1], (5.0, vec![8]));
    assert_eq!(hits[2], (8.0, vec![9]), "through the instance and the transform below it");
    assert_eq!(hits[3], (-1.0, vec![]));

    // One level too many for max_graph_depth = 3.
    let above = [record(0, 1, translation(0.0, 0.0, 0.0))];
    let error = client.build_instances("deeper", "", &["scene"], &above, BuildFlags::empty()).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted);
    assert!(error.to_string().contains("max_graph_depth"), "{error}");

    // Placed children stay until what places them is destroyed.
    for child in ["tri", "lifted"] {
        let error = client.destroy_accel(child).await.unwrap_err();
        assert_eq!(error.code(), Code::FailedPrecondition, "{child}: {error}");
    }
    assert_eq!(client.accels().await.unwrap().len(), 3, "a refused destroy leaves the accel listed");

    // Prime's form: an instance list and 4×3 transforms; ids are the instances' indices.
    let transforms: Vec<u8> = [translation(0.0, 0.0, 1.0), translation(3.0, 0.0, 4.0)]
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let inline =
        |bytes: Vec<u8>| Some(proto::DataSource { source: Some(proto::data_source::Source::Inline(bytes.into())) });
    let prime = proto::InstanceInput {
        children: vec![rayd_client::convert::accel_ref("tri")],
        instances: Some(proto::instance_input::Instances::Prime(proto::PrimeInstances {
            child_indices: inline([0u32, 0].iter().flat_map(|i| i.to_le_bytes()).collect()),
            transforms: inline(transforms),
            transform_format: proto::TransformFormat::Float4x3.into(),
        })),
    };
    let request = |name: &str, inputs: Vec<proto::build_input::Input>| proto::BuildAccelRequest {
        name: name.into(),
        inputs: inputs.into_iter().map(|input| proto::BuildInput { input: Some(input) }).collect(),
        ..Default::default()
    };
    client.build(request("prime", vec![proto::build_input::Input::Instances(prime.clone())])).await.unwrap();
    let hits = down_at(&client, "prime", &[(0.25, 0.25), (3.25, 0.25)]).await;
    assert_eq!(hits, [(9.0, vec![0]), (6.0, vec![1])]);

    // Bad inputs, refused by field.
    let error = client
        .build_instances("bad", "", &["tri"], &[record(1, 0, translation(0.0, 0.0, 0.0))], BuildFlags::empty())
        .await
        .unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument);
    assert!(error.to_string().contains("instances.records[0]: child index 1"), "{error}");
    let mixed = vec![
        proto::build_input::Input::Instances(prime),
        proto::build_input::Input::Triangles(proto::TriangleInput::default()),
    ];
    let error = client.build(request("mixed", mixed)).await.unwrap_err();
    assert!(error.to_string().contains("only input"), "{error}");
    let error = client.build_instances("ghost", "", &["nope"], &[], BuildFlags::empty()).await.unwrap_err();
    assert_eq!(error.code(), Code::NotFound);
    // Instances whose accel could not be built within max_accel_bytes are refused before they are made.
    let many = vec![record(0, 0, translation(0.0, 0.0, 0.0)); 20_000];
    let error = client.build_instances("many", "", &["tri"], &many, BuildFlags::empty()).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted);
    assert!(
        error.to_string().contains("the bytes of an instance accel of 20000 instances")
            && error.to_string().contains("max_accel_bytes = 1000000"),
        "{error}"
    );

    for name in ["scene", "prime", "lifted", "tri"] {
        client.destroy_accel(name).await.unwrap_or_else(|e| panic!("{name}: {e}"));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn updates_refit_in_place_and_placing_accels_refuse_traces_until_updated_too() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let triangle = common::unit_triangle();
    let lowered = Mesh { positions: triangle.positions.iter().map(|p| *p - Vec3::Z).collect(), ..triangle.clone() };
    let tri = client.build_mesh("tri", &triangle, "", BuildFlags::ALLOW_UPDATE).await.unwrap();
    let placed = [record(0, 7, translation(0.0, 0.0, 5.0))];
    client.build_instances("scene", "", &["tri"], &placed, BuildFlags::ALLOW_UPDATE).await.unwrap();
    assert_eq!(down_at(&client, "scene", &[(0.25, 0.25)]).await[0], (5.0, vec![7]));

    let updated = client.update_mesh("tri", &lowered).await.unwrap();
    assert_eq!((updated.handle, updated.bounds.unwrap().min.unwrap().z), (tri.handle, -1.0), "same accel, moved");
    assert_eq!(down_at(&client, "tri", &[(0.25, 0.25)]).await[0], (11.0, vec![]));
    let query = Query::closest(RayFormat::Full, HitFormat::Full);
    let ray = Ray { origin: Vec3A::new(0.25, 0.25, 10.0), direction: -Vec3A::Z, ..Ray::default() };
    let stale = client.trace("scene", &query, Bytes::from(pack_rays(&[ray], RayFormat::Full))).await.unwrap_err();
    assert_eq!(stale.code(), Code::FailedPrecondition, "{stale}");
    assert!(stale.to_string().contains("before an update"), "{stale}");
    // So is a copy of it (without a data directory as with one, which keeps only current versions).
    let copy = client.copy_accel("scene", "scene-copy", "", false).await.unwrap_err();
    assert_eq!(copy.code(), Code::FailedPrecondition, "{copy}");
    assert!(copy.to_string().contains("before an update"), "{copy}");

    // The scene is updated with the same child (now its new version) and a new placement, on a stream.
    let stream = client.create_stream().await.unwrap();
    let moved = [record(0, 7, translation(0.0, 0.0, 2.0))];
    let mut records = vec![0u8; 64];
    moved[0].encode(&mut records);
    let input = proto::InstanceInput {
        children: vec![rayd_client::convert::accel_ref("tri")],
        instances: Some(proto::instance_input::Instances::Records(proto::DataSource {
            source: Some(proto::data_source::Source::Inline(records.into())),
        })),
    };
    let update = proto::UpdateAccelRequest {
        accel: Some(rayd_client::convert::accel_ref("scene")),
        inputs: vec![proto::BuildInput { input: Some(proto::build_input::Input::Instances(input)) }],
    };
    let refit = stream.update(update).await.unwrap();
    stream.synchronize().await.unwrap();
    assert_eq!(refit.result().unwrap().unwrap().bounds.unwrap().max.unwrap().z, 1.0);
    assert_eq!(down_at(&client, "scene", &[(0.25, 0.25)]).await[0], (9.0, vec![7]), "moved and refreshed");

    // An update of another structure, or of an accel built without allow_update, is refused by name.
    let two = Mesh { positions: triangle.positions.clone(), triangles: vec![[0, 1, 2], [0, 2, 1]] };
    let error = client.update_mesh("tri", &two).await.unwrap_err();
    assert_eq!(error.code(), Code::FailedPrecondition);
    assert!(error.to_string().contains("2 triangles where the build had 1"), "{error}");
    client.build_mesh("fixed", &triangle, "", BuildFlags::empty()).await.unwrap();
    let error = client.update_mesh("fixed", &lowered).await.unwrap_err();
    assert!(error.to_string().contains("ALLOW_UPDATE"), "{error}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ray_through_a_pile_of_instances_of_piles_is_stopped_at_its_work_and_named() {
    // 1,000 instances of 1,000 instances of 1,000 copies of one triangle: a ray through them would test 10^9
    // triangles, holding the thread that traces it for minutes (the first, of unknown cost, on a thread that answers
    // calls). The default `scheduler.cpu_ray_work` (2^20) stops it.
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let pile = Mesh { positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y], triangles: vec![[0, 1, 2]; 1000] };
    client.build_mesh("pile", &pile, "", BuildFlags::empty()).await.unwrap();
    let records: Vec<InstanceRecord> = (0..1000).map(|id| record(0, id, translation(0.0, 0.0, 0.0))).collect();
    client.build_instances("piles", "", &["pile"], &records, BuildFlags::empty()).await.unwrap();
    client.build_instances("deep", "", &["piles"], &records, BuildFlags::empty()).await.unwrap();
    let down = |x: f32| Ray { origin: Vec3A::new(x, 0.25, 10.0), direction: -Vec3A::Z, ..Ray::default() };
    let query = Query::closest(RayFormat::Full, HitFormat::TTriid);
    let one = Bytes::from(pack_rays(&[down(0.25)], RayFormat::Full));
    let refused = client.trace("deep", &query, one.clone()).await.expect_err("10^9 tests a ray within 2^20");
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused}");
    assert!(refused.to_string().contains("scheduler.cpu_ray_work"), "{refused}");
    // The service goes on: a ray beside the pile traces through the graph, and one through the pile itself.
    let beside = client.trace("deep", &query, Bytes::from(pack_rays(&[down(5.0)], RayFormat::Full))).await.unwrap();
    assert!(!HitFormat::TTriid.read(beside.hits(), 0).is_hit());
    let traced = client.trace("pile", &query, one).await.unwrap();
    assert_eq!(HitFormat::TTriid.read(traced.hits(), 0).prim_id, 0, "the lowest id of the tie");
}
