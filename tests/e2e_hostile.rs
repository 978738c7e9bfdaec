//! End to end against the real `rayd` (issue 13, point 2): tenant `hostile` sends every hostile geometry and ray
//! the contract has a rule for (NaN and infinite coordinates, indices at u32::MAX, degenerate and extreme
//! triangles, a pile of one triangle repeated, rays with zero direction, tmin > tmax, NaN origins and times) while
//! tenant `bystander` traces the bunny over and over; each hostile input is refused with INVALID_ARGUMENT naming
//! it or traced by its documented rule, and every one of the bystander's answers is the engine's, byte for byte.

mod common;
mod daemon;
mod reference;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use bytes::Bytes;
use common::pack_rays;
use daemon::Daemon;
use rayd_client::{Client, ClientOptions, Error};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, Ray, RayFormat};
use rayd_engine::glam::{Vec3, Vec3A};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind};
use reference::bunny;
use tonic::Code;

const HOSTILE_KEY: &str = "hostile-write-key-0123456789";
const BYSTANDER_KEY: &str = "bystander-write-key-0123456789";

/// Copies of one triangle in the pile (`RAYD_HOSTILE_COPIES` to try more, e.g. 10000000 by hand).
fn pile_copies() -> usize {
    std::env::var("RAYD_HOSTILE_COPIES").ok().and_then(|v| v.parse().ok()).unwrap_or(1_000_000)
}

/// A configuration with the two tenants.
fn config() -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("rayd-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("rayd.toml");
    let tenant = |name: &str, key: &str| {
        format!("[[tenants]]\nname = \"{name}\"\nkeys = [{{ key = \"{key}\", role = \"write\" }}]\n")
    };
    std::fs::write(&path, tenant("hostile", HOSTILE_KEY) + &tenant("bystander", BYSTANDER_KEY)).unwrap();
    path
}

/// A client with `key`.
async fn client(daemon: &Daemon, key: &str) -> Client {
    Client::connect(&daemon.url(), ClientOptions { token: Some(key.into()), ..ClientOptions::default() }).await.unwrap()
}

/// A mesh of `triangles` over `positions`.
fn mesh(positions: &[[f32; 3]], triangles: &[[u32; 3]]) -> Mesh {
    Mesh { positions: positions.iter().map(|&p| Vec3::from(p)).collect(), triangles: triangles.to_vec() }
}

/// The triangle `(-s, -s, 5) (s, -s, 5) (0, s, 5)`, facing −z, around the z axis.
fn triangle(size: f32) -> Mesh {
    mesh(&[[-size, -size, 5.0], [size, -size, 5.0], [0.0, size, 5.0]], &[[0, 1, 2]])
}

/// A ray from `origin` along `direction` over `[tmin, tmax]` at `time`.
fn ray(origin: [f32; 3], direction: [f32; 3], tmin: f32, tmax: f32, time: f32) -> Ray {
    Ray { origin: Vec3A::from(origin), direction: Vec3A::from(direction), tmin, tmax, time, ..Ray::default() }
}

/// The query of the hostile traces: closest, with t, primitive id and barycentrics, rays with a time.
fn query(kind: QueryKind) -> Query {
    Query { kind, ..Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::TTriidUV) }
}

/// Traces `rays` with `kind` on `accel` and returns each ray's `(t, prim_id)` and its count (0 without counts).
async fn trace(client: &Client, accel: &str, kind: QueryKind, rays: &[Ray]) -> Result<Vec<(f32, u32, u32)>, Error> {
    let query = query(kind);
    let packed = Bytes::from(pack_rays(rays, query.ray_format));
    let result = client.trace(accel, &query, packed).await?;
    let view = result.hit_view();
    Ok((0..rays.len())
        .map(|i| {
            let hit = view.get(i);
            (hit.t, hit.prim_id, result.count(i).unwrap_or(0))
        })
        .collect())
}

/// Asserts that `call` failed with INVALID_ARGUMENT and a message holding every one of `naming`.
fn assert_invalid<T: std::fmt::Debug>(call: Result<T, Error>, naming: &[&str], what: &str) {
    let error = call.expect_err(what);
    assert_eq!(error.code(), Code::InvalidArgument, "{what}: {error}");
    let message = error.to_string();
    for part in naming {
        assert!(message.contains(part), "{what}: {message:?} does not name {part:?}");
    }
}

/// The bystander's loop: the bunny traced until `stop`, every answer checked against the engine's; returns how
/// many answers were checked.
fn bystander(client: Client, stop: Arc<AtomicBool>, checked: Arc<AtomicU64>) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
        let rays = bunny().camera_rays(query.ray_format, 96, 64);
        let expected = bunny().trace(&query, &rays);
        let rays = Bytes::from(rays);
        while !stop.load(Ordering::Acquire) {
            let traced = client.trace("bunny", &query, rays.clone()).await.expect("the bystander's trace");
            let stats = traced.stats();
            expected.assert_answer(traced.hits(), traced.counts(), (stats.rays, stats.rays_hit), "bystander");
            checked.fetch_add(1, Ordering::Release);
        }
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn hostile_inputs_get_their_rule_or_invalid_argument_and_another_tenant_is_unaffected() {
    let config = config();
    let daemon = Daemon::start(&[("RAYD_CONFIG", config.to_str().unwrap())]);
    let (hostile, calm) = (client(&daemon, HOSTILE_KEY).await, client(&daemon, BYSTANDER_KEY).await);
    calm.build_mesh("bunny", &bunny().mesh, "", BuildFlags::empty()).await.unwrap();
    let (stop, checked) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicU64::new(0)));
    let watching = bystander(calm.clone(), Arc::clone(&stop), Arc::clone(&checked));
    let build = |name: &'static str, mesh: Mesh| {
        let hostile = hostile.clone();
        async move { hostile.build_mesh(name, &mesh, "", BuildFlags::empty()).await }
    };
    let (nan, inf) = (f32::NAN, f32::INFINITY);

    // Geometry that no rule can trace: refused, naming the input, the field and the element.
    for (what, bad) in [("NaN", nan), ("+inf", inf), ("-inf", -inf)] {
        let call = build("bad", mesh(&[[0.0, 0.0, 0.0], [1.0, bad, 0.0], [0.0, 1.0, 0.0]], &[[0, 1, 2]])).await;
        assert_invalid(call, &["build input 0", "vertices", "finite"], &format!("a {what} coordinate"));
    }
    let call = build("bad", mesh(&[[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], &[[0, 1, u32::MAX]])).await;
    assert_invalid(call, &["build input 0", "indices", &u32::MAX.to_string()], "an index at u32::MAX");

    // Geometry traced by its rule: all vertices equal is degenerate, never hit; denormal, 1e-30-sized and
    // 1e30-sized triangles are legal and missed, as `formats.proto` says (binary32 cannot hold their products); a
    // pile of copies of one triangle is hit at the lowest primitive id and counted once a copy.
    let down = |x: f32| ray([x, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, inf, 0.0);
    build("point", mesh(&[[0.0, 0.0, 5.0]; 3], &[[0, 1, 2]])).await.unwrap();
    assert_eq!(trace(&hostile, "point", QueryKind::Count, &[down(0.0)]).await.unwrap(), [(-1.0, u32::MAX, 0)]);
    let sizes = [
        ("denormal", 1e-40, false),
        ("tiny", 1e-30, false),
        ("small", 1e-6, true),
        ("huge", 1e18, true),
        ("vast", 1e30, false),
    ];
    for (name, size, hit) in sizes {
        build(name, triangle(size)).await.unwrap();
        let traced = trace(&hostile, name, QueryKind::Closest, &[down(0.0)]).await.unwrap();
        let expected = if hit { (5.0, 0, 0) } else { (-1.0, u32::MAX, 0) };
        assert_eq!(traced, [expected], "a triangle of size {size:e}");
    }
    let copies = pile_copies();
    let pile = Mesh { triangles: vec![[0, 1, 2]; copies], ..triangle(1.0) };
    build("pile", pile).await.unwrap();
    let rays = [down(0.0), down(0.2), down(2.0)];
    let closest = trace(&hostile, "pile", QueryKind::Closest, &rays).await.unwrap();
    assert_eq!(closest, [(5.0, 0, 0), (5.0, 0, 0), (-1.0, u32::MAX, 0)], "the tie rule: the lowest primitive id");
    let counted = trace(&hostile, "pile", QueryKind::Count, &rays).await.unwrap();
    let counts: Vec<u32> = counted.iter().map(|c| c.2).collect();
    assert_eq!(counts, [copies as u32, copies as u32, 0], "every copy is crossed once");

    // Rays traced by their rule: a zero, NaN or infinite direction, tmin > tmax, a NaN or infinite origin, a NaN
    // tmin or tmax hit nothing; an infinite time is clamped; a NaN time fails the whole batch, naming the ray.
    let rays = [
        ray([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0, inf, 0.0),
        ray([0.0, 0.0, 0.0], [0.0, nan, 1.0], 0.0, inf, 0.0),
        ray([0.0, 0.0, 0.0], [0.0, 0.0, inf], 0.0, inf, 0.0),
        ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 6.0, 4.0, 0.0),
        ray([nan, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, inf, 0.0),
        ray([0.0, 0.0, -inf], [0.0, 0.0, 1.0], 0.0, inf, 0.0),
        ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], nan, inf, 0.0),
        ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, nan, 0.0),
        ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, inf, inf),
    ];
    let mut expected = vec![(-1.0, u32::MAX, 0); rays.len() - 1];
    expected.push((5.0, 0, 0));
    assert_eq!(trace(&hostile, "small", QueryKind::Closest, &rays).await.unwrap(), expected);
    let mut timed = rays.to_vec();
    timed[3].time = nan;
    assert_invalid(trace(&hostile, "small", QueryKind::Closest, &timed).await, &["rays.time", "ray 3"], "a NaN time");

    stop.store(true, Ordering::Release);
    watching.await.expect("every answer of the bystander was the engine's");
    assert!(checked.load(Ordering::Acquire) > 0, "the bystander traced while the hostile tenant sent its inputs");
    let listed = hostile.accels().await.unwrap().into_iter().map(|a| a.name).collect::<Vec<_>>();
    assert!(!listed.contains(&"bad".to_string()), "nothing of a refused build is left: {listed:?}");
}
