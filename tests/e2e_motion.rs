//! End to end against the real `rayd`: motion blur over the network. A vertex-motion mesh and an SRT motion
//! transform under a motion instance accel, built through `rayd-client` and traced with per-ray times; their
//! motion options read back through `info`; a NaN time, bad motion inputs and the `max_motion_keys` limit refused
//! with the right codes and fields.

mod common;
mod daemon;

use bytes::Bytes;
use common::{f32_at, pack_rays, u32_at};
use daemon::Daemon;
use rayd_client::{Client, ClientOptions, proto};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, Ray, RayFormat};
use rayd_engine::geometry::{
    INSTANCE_RECORD_BYTES, InstanceFlags, InstanceRecord, MotionFlags, MotionOptions, TransformInput,
};
use rayd_engine::glam::{Vec3, Vec3A};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use tonic::Code;

/// 4-byte words of a `full` hit record.
const FULL_WORDS: usize = 20;

/// The unit right triangle in z = 0, moved by `offset`.
fn triangle_at(offset: Vec3) -> Mesh {
    Mesh { positions: vec![offset, Vec3::X + offset, Vec3::Y + offset], triangles: vec![[0, 1, 2]] }
}

/// Full-format hits of rays straight down from z = 10 at `(x, y, time)`: (t, instance id) per ray.
async fn down_at(client: &Client, accel: &str, rays: &[(f32, f32, f32)]) -> Vec<(f32, u32)> {
    let rays: Vec<Ray> = rays
        .iter()
        .map(|&(x, y, time)| Ray { origin: Vec3A::new(x, y, 10.0), direction: -Vec3A::Z, time, ..Ray::default() })
        .collect();
    let query = Query::closest(RayFormat::Full, HitFormat::Full);
    let traced = client.trace(accel, &query, Bytes::from(pack_rays(&rays, RayFormat::Full))).await.unwrap();
    let hits = traced.hits();
    (0..rays.len()).map(|r| (f32_at(hits, FULL_WORDS * r), u32_at(hits, FULL_WORDS * r + 3))).collect()
}

/// For each hit, whether it is a hit at distance 10 (within rounding of the watertight test); misses are false.
fn hit_at_10(hits: &[(f32, u32)]) -> Vec<bool> {
    hits.iter().map(|&(t, _)| (t - 10.0).abs() < 1e-5).collect()
}

/// One instance record, packed.
fn record_bytes(record: &InstanceRecord) -> Vec<u8> {
    let mut bytes = vec![0u8; INSTANCE_RECORD_BYTES];
    record.encode(&mut bytes);
    bytes
}

/// Motion over `[begin, end]` with `keys` keys and `flags`.
fn motion(keys: u32, begin: f32, end: f32, flags: MotionFlags) -> MotionOptions {
    MotionOptions { keys, time_begin: begin, time_end: end, flags }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn moving_meshes_and_transforms_trace_at_each_rays_time() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();

    // Vertex motion: the triangle slides 4 along x over [0, 2] and vanishes after.
    let keys = [triangle_at(Vec3::ZERO), triangle_at(Vec3::new(4.0, 0.0, 0.0))];
    let sliding = motion(2, 0.0, 2.0, MotionFlags::END_VANISH);
    let info = client.build_moving_mesh("slide", &keys, "", BuildFlags::empty(), &sliding).await.unwrap();
    let shown = info.options.unwrap().motion.unwrap();
    assert_eq!((shown.keys, shown.time_begin, shown.time_end), (2, 0.0, 2.0));
    assert!(shown.end_vanish && !shown.start_vanish);
    let bounds = info.bounds.unwrap();
    assert_eq!((bounds.min.unwrap().x, bounds.max.unwrap().x), (0.0, 5.0), "bounds cover every time");
    let hits = down_at(&client, "slide", &[(0.2, 0.2, 0.0), (2.2, 0.2, 1.0), (2.2, 0.2, 0.0), (0.2, 0.2, -5.0)]).await;
    assert_eq!(hit_at_10(&hits), [true, true, false, true], "at t = 0, 1, 0; clamped before the range");
    let after = down_at(&client, "slide", &[(4.2, 0.2, 2.0), (4.2, 0.2, 2.5)]).await;
    assert_eq!(hit_at_10(&after), [true, false], "there at the end, vanished after");

    // An SRT transform turns a static triangle 90° about z over [0, 1]; a motion instance accel places it.
    client.build_mesh("tri", &triangle_at(Vec3::ZERO), "", BuildFlags::empty()).await.unwrap();
    let identity = [1., 0., 0., 0., 1., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0.];
    let mut turned = identity;
    (turned[11], turned[12]) = (std::f32::consts::FRAC_1_SQRT_2, std::f32::consts::FRAC_1_SQRT_2);
    let srt =
        TransformInput::SrtMotion { keys: vec![identity, turned], motion: motion(2, 0.0, 1.0, MotionFlags::empty()) };
    let spin = client.build_transform_input("spin", "", "tri", &srt).await.unwrap();
    assert_eq!((spin.kind(), spin.depth), (proto::AccelKind::SrtMotionTransform, 2));
    let record = InstanceRecord {
        transform: [1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 1.],
        instance_id: 5,
        mask: 0xFF,
        flags: InstanceFlags::empty(),
        child: 0,
    };
    let mut request = proto::BuildAccelRequest {
        name: "scene".into(),
        inputs: vec![proto::BuildInput {
            input: Some(proto::build_input::Input::Instances(proto::InstanceInput {
                children: vec![proto::AccelRef { r#ref: Some(proto::accel_ref::Ref::Name("spin".into())) }],
                instances: Some(proto::instance_input::Instances::Records(proto::DataSource {
                    source: Some(proto::data_source::Source::Inline(Bytes::from(record_bytes(&record)))),
                })),
            })),
        }],
        options: Some(proto::BuildOptions {
            motion: Some(proto::MotionOptions { keys: 3, time_begin: 0.0, time_end: 1.0, ..Default::default() }),
            ..Default::default()
        }),
        ..Default::default()
    };
    let scene = client.build(request.clone()).await.unwrap();
    assert_eq!(scene.options.unwrap().motion.unwrap().keys, 3);
    // At t = 0 the triangle spans +x; at t = 1 it spans +y and −x (turned 90°); the instance lifts it to z = 1.
    let hits = down_at(&client, "scene", &[(0.6, 0.2, 0.0), (0.6, 0.2, 1.0), (-0.2, 0.6, 1.0), (-0.2, 0.6, 0.0)]).await;
    assert_eq!(hits.iter().map(|h| h.1).collect::<Vec<_>>(), [5, u32::MAX, 5, u32::MAX]);
    assert!((hits[0].0 - 9.0).abs() < 1e-5 && (hits[2].0 - 9.0).abs() < 1e-5, "{hits:?}");

    // Bad input, precisely refused.
    request.name = "too-many-keys".into();
    request.options.as_mut().unwrap().motion.as_mut().unwrap().keys = 65;
    let error = client.build(request.clone()).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
    assert!(error.to_string().contains("max_motion_keys"), "{error}");
    request.options.as_mut().unwrap().motion.as_mut().unwrap().keys = 2;
    request.options.as_mut().unwrap().motion.as_mut().unwrap().time_end = 0.0;
    let error = client.build(request).await.unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(error.to_string().contains("time_end"), "{error}");
    let three_keys = motion(3, 0.0, 1.0, MotionFlags::empty());
    let error = client.build_moving_mesh("short", &keys, "", BuildFlags::empty(), &three_keys).await.unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(error.to_string().contains("motion_vertices"), "{error}");
    let both = proto::TransformInput {
        child: Some(proto::AccelRef { r#ref: Some(proto::accel_ref::Ref::Name("tri".into())) }),
        transform: vec![1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0.],
        srt_keys: [identity, turned].concat(),
        ..Default::default()
    };
    let error = client
        .build(proto::BuildAccelRequest {
            name: "both".into(),
            inputs: vec![proto::BuildInput { input: Some(proto::build_input::Input::Transform(both.clone())) }],
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(error.to_string().contains("inputs[0].transform"), "{error}");
    // Motion keys without motion options (one key): refused by name.
    let unset = proto::TransformInput { transform: Vec::new(), ..both.clone() };
    let error = client
        .build(proto::BuildAccelRequest {
            name: "unset".into(),
            inputs: vec![proto::BuildInput { input: Some(proto::build_input::Input::Transform(unset)) }],
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(error.to_string().contains("transform.motion.keys") && error.to_string().contains("at least 2"), "{error}");
    // A transform's build ignores the build options, even ones a mesh's build refuses (both preferences, more motion
    // keys than max_motion_keys).
    let still = proto::TransformInput { srt_keys: Vec::new(), ..both };
    let ignored = proto::BuildOptions {
        prefer_fast_trace: true,
        prefer_fast_build: true,
        motion: Some(proto::MotionOptions { keys: 1000, ..Default::default() }),
        ..Default::default()
    };
    let built = client
        .build(proto::BuildAccelRequest {
            name: "still".into(),
            inputs: vec![proto::BuildInput { input: Some(proto::build_input::Input::Transform(still)) }],
            options: Some(ignored),
            ..Default::default()
        })
        .await
        .expect("a transform built whatever the options");
    assert!(built.options.is_some_and(|o| o.allow_update && o.allow_compaction), "a transform's own options");

    // A NaN time fails the whole batch before anything is traced.
    let rays = [Ray { origin: Vec3A::new(0.2, 0.2, 10.0), direction: -Vec3A::Z, time: f32::NAN, ..Ray::default() }];
    let query = Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::T);
    let bytes = Bytes::from(pack_rays(&rays, RayFormat::OriginTminDirectionTmaxTime));
    let error = client.trace("slide", &query, bytes).await.unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(error.to_string().contains("rays.time") && error.to_string().contains("ray 0"), "{error}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_file_moves_its_instances() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let teapot = std::env::current_dir().unwrap().join("../shared/data/meshes/teapot.obj");
    let text = format!(
        r#"{{
            "meshes": {{ "teapot": {teapot:?} }},
            "motion": {{ "keys": 2, "time": [0, 1] }},
            "instances": [{{ "mesh": "teapot", "id": 3,
              "motion": {{ "time": [0, 1], "end_vanish": true, "keys": [{{}}, {{ "translate": [10, 0, 0] }}] }} }}]
        }}"#
    );
    let scene: rayd_client::Scene = serde_json::from_str(&text).unwrap();
    let info = client.build_scene("tea", "", &scene, BuildFlags::empty()).await.unwrap();
    assert_eq!(info.options.unwrap().motion.unwrap().keys, 2);
    let moving = client.accel("tea.0.motion").await.unwrap();
    assert_eq!(moving.kind(), proto::AccelKind::SrtMotionTransform);
    let bounds = client.accel("tea.teapot").await.unwrap().bounds.unwrap();
    let (lo, hi) = (bounds.min.unwrap(), bounds.max.unwrap());
    let (x, y) = ((lo.x + hi.x) / 2.0, (lo.y + hi.y) / 2.0);
    let hits = down_at(&client, "tea", &[(x, y, 0.0), (x, y, 1.0), (x + 10.0, y, 0.0), (x + 10.0, y, 1.0)]).await;
    let ids: Vec<u32> = hits.iter().map(|h| h.1).collect();
    assert_eq!(ids, [3, u32::MAX, u32::MAX, 3], "{hits:?}");
    let gone = down_at(&client, "tea", &[(x + 10.0, y, 1.5)]).await;
    assert_eq!(gone[0].1, u32::MAX, "vanished after its range");
}
