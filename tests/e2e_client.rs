//! End to end against the real `rayd` binary through the `rayd-client` library: the server's limits as
//! GetServerInfo reports them; the shared bunny, loaded by the client's mesh loader, built inline and through
//! uploaded buffers (deleted again afterwards, even when the build fails); traces by TraceBatch and by TraceStream,
//! chosen by the client from its options, byte for byte as the engine traces in this process; `HitView` against
//! decoding by hand; the server's errors surfacing with their gRPC codes; calls in flight together spread over
//! the connections a client asks for; and the routing header on every call of a trace of rays the server makes
//! (secondary rays from hits larger than a message among them, through a temporary buffer), as a proxy in front of
//! rayd sees it; and a stream operation larger than a message refused before it is sent, the stream going on.

mod common;
mod daemon;
mod reference;

use std::convert::Infallible;
use std::path::Path;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};

use common::{f32_at, u32_at};
use daemon::Daemon;
use rayd_client::{Client, ClientOptions, ROUTE_HEADER, TraceResult, load_mesh};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, MISS_ID, MISS_T, RayFormat};
use rayd_engine::query::{Query, QueryKind};
use rayd_engine::raygen::{Bounce, Camera, Generator, PixelSampling, Primary, Secondary};
use reference::{BUNNY_TRIANGLES, Expected, bunny};
use tonic::Code;
use tonic::body::Body;
use tonic::codegen::http;
use tonic::transport::server::TcpIncoming;
use tonic::transport::{Channel, Server};
use tower::ServiceExt;

/// The daemon's `max_rays_per_batch`: set, so that GetServerInfo has something to report, and above every trace
/// here.
const MAX_RAYS_PER_BATCH: u64 = 100_000;

/// The daemon's `max_buffers`: exactly the two an uploaded mesh needs, so that a buffer left behind by one upload
/// makes the next one fail.
const MAX_BUFFERS: u32 = 2;

/// The reference camera's size: 6912 rays, a few hundred kilobytes of them.
const CAMERA: (u32, u32) = (96, 72);

/// The daemon's `rayd_requests_total` of each of `methods` (0 for one never called): the calls that show which
/// path a client took.
fn requests(daemon: &Daemon, methods: &[&str]) -> Vec<u64> {
    let count = |method: &str| daemon.metric("rayd_requests_total", &[&format!("method=\"{method}\"")]);
    methods.iter().map(|&method| count(method).unwrap_or(0.0) as u64).collect()
}

/// Options with which the bunny takes every path meant for large data: its mesh is uploaded as two buffers, each
/// in several messages, and a trace of the reference camera's rays goes through TraceStream in several chunks,
/// the last one short, at most two of them in flight.
fn small_messages() -> ClientOptions {
    ClientOptions {
        inline_mesh_bytes: 64 << 10,
        upload_chunk_bytes: 256 << 10,
        batch_limit_bytes: 64 << 10,
        stream_chunk_bytes: 16 << 10,
        stream_window: 2,
        ..ClientOptions::default()
    }
}

/// A client of `daemon` with `options`.
async fn connect(daemon: &Daemon, options: ClientOptions) -> Client {
    Client::connect(&daemon.url(), options).await.expect("the client connects to rayd")
}

/// The version in `server/Cargo.toml`, which rayd reports as its own.
fn server_version() -> &'static str {
    let manifest = include_str!("../server/Cargo.toml");
    let version = manifest.lines().find_map(|line| line.strip_prefix("version = \"")?.strip_suffix('"'));
    version.expect("server/Cargo.toml has a version line")
}

/// The closest hit with `t_triid_u_v` records, the hit bitmask of an `any` query, and the `all` and `count`
/// queries with their counts, all on the same rays.
fn queries() -> [Query; 4] {
    let closest = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    [
        closest,
        Query { kind: QueryKind::Any, hit_format: HitFormat::Bitmask, ..closest },
        Query { kind: QueryKind::All, max_hits_per_ray: 4, ..closest },
        Query { kind: QueryKind::Count, ..closest },
    ]
}

/// Asserts that a client's trace result is the engine's, byte for byte.
fn assert_traced_as_expected(traced: &TraceResult, expected: &Expected, what: &str) {
    let stats = traced.stats();
    expected.assert_answer(traced.hits(), traced.counts(), (stats.rays, stats.rays_hit), what);
    assert_eq!(traced.rays() as u64, expected.stats.rays, "{what}: rays of the result");
}

/// Record `r` of a `t_triid_u_v` hit buffer, decoded by hand: four little-endian words, t (f32), triangle (u32),
/// u and v (f32).
fn record(hits: &[u8], r: usize) -> (f32, u32, f32, f32) {
    (f32_at(hits, 4 * r), u32_at(hits, 4 * r + 1), f32_at(hits, 4 * r + 2), f32_at(hits, 4 * r + 3))
}

/// Asserts that the views of the results of [`queries`] read what decoding their bytes by hand gives, for the
/// first hit, the first miss and two more rays.
fn assert_views_decode_as_by_hand([closest, any, all, count]: &[TraceResult; 4]) {
    let hits = &closest.hits()[..];
    let rays = closest.rays();
    let first_hit = (0..rays).find(|&r| record(hits, r).0 >= 0.0).expect("a ray hits the bunny");
    let first_miss = (0..rays).find(|&r| record(hits, r).0 < 0.0).expect("a ray misses the bunny");
    let view = closest.hit_view();
    assert_eq!(view.len(), rays, "one record a ray");
    for r in [first_hit, first_miss, rays / 2, rays - 1] {
        let hit = view.get(r);
        let (t, triangle, u, v) = record(hits, r);
        assert_eq!((hit.t, hit.prim_id, hit.u, hit.v), (t, triangle, u, v), "closest hit of ray {r}");
        assert_eq!((view.is_hit(r), hit.is_hit()), (t >= 0.0, t >= 0.0), "ray {r}");
        // The bitmask: bit r % 8 of byte r / 8, least significant first.
        let bit = (any.hits()[r / 8] >> (r % 8)) & 1 == 1;
        assert_eq!((any.hit_view().is_hit(r), bit), (t >= 0.0, t >= 0.0), "hit bit of ray {r}");
        for (result, what) in [(all, "all"), (count, "count")] {
            assert_eq!(result.count(r), Some(u32_at(result.counts(), r)), "{what}: count of ray {r}");
        }
        // `all`: records r·4 .. r·4+4, the hits first (as many as fit), then misses.
        let found = all.count(r).expect("counts") as usize;
        let all_view = all.hit_view();
        for k in 0..4 {
            let hit = all_view.get(4 * r + k);
            assert_eq!((hit.t, hit.prim_id, hit.u, hit.v), record(&all.hits()[..], 4 * r + k), "all: ray {r} hit {k}");
            assert_eq!(hit.is_hit(), k < found, "all: ray {r} hit {k} of {found}");
        }
    }
    let (hit, miss) = (view.get(first_hit), view.get(first_miss));
    assert!((hit.prim_id as u64) < BUNNY_TRIANGLES && hit.t > 0.0, "{hit:?}");
    assert!(hit.u >= 0.0 && hit.v >= 0.0 && hit.u + hit.v <= 1.0 + 1e-6, "barycentrics of {hit:?}");
    assert_eq!((miss.t, miss.prim_id), (MISS_T, MISS_ID));
    assert_eq!(all.hit_view().len(), 4 * rays, "four records a ray");
}

#[tokio::test]
async fn the_client_builds_and_traces_the_bunny_as_the_engine_does_and_reports_server_errors_by_code() {
    let (max_rays, max_buffers) = (MAX_RAYS_PER_BATCH.to_string(), MAX_BUFFERS.to_string());
    let daemon =
        Daemon::start(&[("RAYD_LIMITS_MAX_RAYS_PER_BATCH", &max_rays), ("RAYD_LIMITS_MAX_BUFFERS", &max_buffers)]);
    let direct = connect(&daemon, ClientOptions::default()).await;
    let small = connect(&daemon, small_messages()).await;

    let info = direct.server_info().await.expect("GetServerInfo");
    assert_eq!(info.version, server_version());
    let limits = info.limits.expect("the limits");
    assert_eq!((limits.max_rays_per_batch, limits.max_buffers), (MAX_RAYS_PER_BATCH, MAX_BUFFERS), "as set");
    let defaults = ClientOptions::default();
    assert_eq!(
        (limits.max_message_bytes, limits.stream_window),
        (defaults.max_message_bytes as u64, defaults.stream_window as u32),
        "limits left alone keep the server's defaults, which the client's defaults match"
    );

    let bunny = bunny();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/meshes/stanford-bunny.obj");
    let mesh = load_mesh(&path).expect("the client loads the bunny");
    assert!(mesh == bunny.mesh, "the client's loader reads the bunny as the engine does");
    let uploads = ["UploadBuffer", "DeleteBuffer"];
    let inline = direct.build_mesh("bunny", &mesh, "", BuildFlags::empty()).await.expect("an inline build");
    assert_eq!(requests(&daemon, &uploads), [0, 0], "{uploads:?} calls of an inline build");
    let uploaded =
        small.build_mesh("bunny-uploaded", &mesh, "", BuildFlags::empty()).await.expect("a build from buffers");
    assert_eq!(requests(&daemon, &uploads), [2, 2], "{uploads:?} calls: vertices and indices");
    assert!(direct.buffers().await.expect("ListBuffers").is_empty(), "the mesh's buffers are deleted after the build");
    for info in [&inline, &uploaded] {
        let expected = bunny.info();
        assert_eq!((info.triangle_count, info.geometry_count), (BUNNY_TRIANGLES, 1), "{}", info.name);
        assert_eq!(info.size_bytes, expected.size_bytes, "{}", info.name);
        assert_eq!(rayd_client::convert::bounds(info), Some(expected.bounds), "{}", info.name);
    }
    assert_eq!(direct.accels().await.expect("ListAccels"), [inline.clone(), uploaded.clone()]);

    let (width, height) = CAMERA;
    // For each query, the first result that the client reassembled from stream chunks.
    let mut streamed = Vec::new();
    for (i, query) in queries().into_iter().enumerate() {
        let rays = bunny.camera_rays(query.ray_format, width, height);
        let expected = bunny.trace(&query, &rays);
        assert!(0 < expected.stats.rays_hit && expected.stats.rays_hit < expected.stats.rays, "rays hit and miss");
        for accel in [&inline.name, &uploaded.name] {
            for (client, path) in [(&direct, "TraceBatch"), (&small, "TraceStream")] {
                let what = format!("{query:?} on {accel} through {path}");
                let result = client.trace(accel, &query, rays.clone().into()).await.expect(&what);
                assert_traced_as_expected(&result, &expected, &what);
                if path == "TraceStream" && streamed.len() == i {
                    streamed.push(result);
                }
            }
        }
    }
    let traces = queries().len() as u64 * 2;
    assert_eq!(
        requests(&daemon, &["TraceBatch", "TraceStream"]),
        [traces, traces],
        "TraceBatch and TraceStream calls: the default options trace the camera in one batch, the small ones stream it"
    );
    assert_views_decode_as_by_hand(&streamed.try_into().expect("one result a query"));

    let query = queries()[0];
    let rays = bunny.camera_rays(query.ray_format, width, height);
    for client in [&direct, &small] {
        let error = client.trace("nowhere", &query, rays.clone().into()).await.expect_err("an unknown accel");
        assert_eq!(error.code(), Code::NotFound, "{error}");
        assert!(error.to_string().contains("nowhere"), "{error}");
    }
    let error = direct.accel("nowhere").await.expect_err("an unknown accel");
    assert_eq!(error.code(), Code::NotFound, "{error}");
    let error = direct.destroy_accel("nowhere").await.expect_err("an unknown accel");
    assert_eq!(error.code(), Code::NotFound, "{error}");
    for client in [&direct, &small] {
        let error = client.build_mesh("bunny", &mesh, "", BuildFlags::empty()).await.expect_err("a taken name");
        assert_eq!(error.code(), Code::AlreadyExists, "{error}");
        assert!(error.to_string().contains("bunny"), "{error}");
    }
    assert_eq!(requests(&daemon, &uploads), [4, 4], "{uploads:?} calls: the second build from buffers failed");
    assert!(direct.buffers().await.expect("ListBuffers").is_empty(), "a failed build deletes its buffers too");

    direct.destroy_accel("bunny").await.expect("DestroyAccel");
    assert_eq!(direct.accels().await.expect("ListAccels"), [uploaded]);
    let error = small.trace("bunny", &query, rays.into()).await.expect_err("a destroyed accel");
    assert_eq!(error.code(), Code::NotFound, "{error}");
}

#[tokio::test]
async fn the_client_keeps_every_call_within_the_servers_max_rays_per_batch() {
    const LIMIT: u64 = 1000;
    let limit = LIMIT.to_string();
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_RAYS_PER_BATCH", &limit)]);
    let client = connect(&daemon, ClientOptions::default()).await;
    assert_eq!(client.options().max_rays_per_call as u64, LIMIT, "taken from GetServerInfo at connect");
    let bunny = bunny();
    client.build_mesh("bunny", &bunny.mesh, "", BuildFlags::empty()).await.expect("an inline build");
    let (width, height) = CAMERA;
    for query in queries() {
        let rays = bunny.camera_rays(query.ray_format, width, height);
        let expected = bunny.trace(&query, &rays);
        let traced = client.trace("bunny", &query, rays.into()).await.expect("a trace above the server's limit");
        assert_traced_as_expected(&traced, &expected, &format!("{query:?} in chunks of at most {LIMIT} rays"));
    }
    assert_eq!(requests(&daemon, &["TraceBatch", "TraceStream"]), [0, 4], "6912 rays > 1000: every trace streams");
}

/// Established TCP connections of this process whose far end is `port` (IPv4 and IPv6, from `/proc/net`, its
/// sockets known by their inodes in `/proc/self/fd`: other processes' sockets, such as a server's own end of a
/// connection whose client port happens to be `port`, are not counted).
fn established_to(port: u16) -> usize {
    let ours: std::collections::HashSet<String> = std::fs::read_dir("/proc/self/fd")
        .into_iter()
        .flatten()
        .filter_map(|entry| std::fs::read_link(entry.ok()?.path()).ok())
        .filter_map(|target| {
            let target = target.to_string_lossy().into_owned();
            Some(target.strip_prefix("socket:[")?.strip_suffix(']')?.to_owned())
        })
        .collect();
    let table = |path: &str| std::fs::read_to_string(path).unwrap_or_default();
    let rows = table("/proc/net/tcp") + &table("/proc/net/tcp6");
    // Columns: slot, local address:port, remote address:port, state (01: established), …, inode (the tenth); ports
    // in hex.
    let column = |row: &str, n: usize| row.split_whitespace().nth(n).map(str::to_owned);
    let remote_port = |row: &str| column(row, 2)?.rsplit(':').next().map(str::to_owned);
    let wanted = format!("{port:04X}");
    rows.lines()
        .filter(|row| remote_port(row) == Some(wanted.clone()) && column(row, 3).as_deref() == Some("01"))
        .filter(|row| column(row, 9).is_some_and(|inode| ours.contains(&inode)))
        .count()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn calls_in_flight_together_are_spread_over_the_connections_asked_for() {
    let daemon = Daemon::start(&[]);
    let one = connect(&daemon, ClientOptions::default()).await;
    let bunny = bunny();
    one.build_mesh("bunny", &bunny.mesh, "", BuildFlags::empty()).await.expect("an inline build");
    let port = daemon.grpc_addr().port();
    let before = established_to(port);
    let three = connect(&daemon, ClientOptions { connections: 3, ..ClientOptions::default() }).await;
    let (width, height) = CAMERA;
    let query = queries()[0];
    let rays = bunny.camera_rays(query.ray_format, width, height);
    let expected = bunny.trace(&query, &rays);
    // The balancer opens its connections as calls need them and sends calls only on those that are ready: on a
    // loaded machine a round of calls was once over before the third connection was up (2 were seen). Rounds go on
    // until three are up, or fail the test after many.
    let mut opened = 0;
    for _round in 0..20 {
        let calls: Vec<_> = (0..12)
            .map(|_| {
                let (client, rays) = (three.clone(), rays.clone());
                tokio::spawn(async move { client.trace("bunny", &query, rays.into()).await })
            })
            .collect();
        for call in calls {
            let traced = call.await.expect("the call's task").expect("a trace over three connections");
            assert_traced_as_expected(&traced, &expected, "a trace over three connections");
        }
        opened = established_to(port).saturating_sub(before);
        if opened >= 3 {
            break;
        }
    }
    // Three connections at least, and not one a call: the client's first connection (which asked for the server's
    // limits) may linger as it closes, and on a loaded machine the balancer was once seen to have reconnected all
    // three (7 in all; the cause was not found), which a user would not mind.
    assert!((3..12).contains(&opened), "{opened} connections for a client of three, for rounds of 12 calls");
}

#[tokio::test]
async fn a_stream_refuses_an_operation_larger_than_a_message_and_goes_on() {
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_MESSAGE_BYTES", "65536")]);
    let client = connect(&daemon, ClientOptions::default()).await;
    let bunny = bunny();
    client.build_mesh("bunny", &bunny.mesh, "", BuildFlags::empty()).await.expect("a build from buffers");
    let stream = client.create_stream().await.expect("OpenStream");
    let query = queries()[0];
    let (width, height) = CAMERA;
    let rays = bunny.camera_rays(query.ray_format, width, height);
    let error = stream.trace("bunny", &query, rays.clone().into()).await.expect_err("221 KB of rays in one message");
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(error.to_string().contains("max_message_bytes (65536)"), "{error}");
    let few = rays[..100 * query.ray_format.size()].to_vec();
    let traced = stream.trace("bunny", &query, few.clone().into()).await.expect("a trace that fits");
    stream.synchronize().await.expect("the stream goes on");
    let traced = traced.result().expect("answered after synchronize").expect("traced");
    assert_traced_as_expected(&traced, &bunny.trace(&query, &few), "a trace after the refused one");
    stream.finish().await.expect("the stream ends cleanly");
}

/// The calls a [`Recorder`] passed on, in order: each one's path (`/rayd.v1.Rayd/TraceBatch`) and routing header.
type Recorded = Arc<Mutex<Vec<(String, Option<String>)>>>;

/// A gRPC proxy in front of rayd, as a router would be: it notes each call's path and routing header, then passes
/// the call on unchanged.
#[derive(Clone)]
struct Recorder {
    /// The connection to rayd.
    upstream: Channel,
    /// What it has seen so far.
    calls: Recorded,
}

impl tower::Service<http::Request<Body>> for Recorder {
    type Response = http::Response<Body>;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Infallible>> + Send>>;

    fn poll_ready(&mut self, _: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, request: http::Request<Body>) -> Self::Future {
        let route = request.headers().get(ROUTE_HEADER).and_then(|value| value.to_str().ok()).map(str::to_owned);
        self.calls.lock().unwrap().push((request.uri().path().to_owned(), route));
        let upstream = self.upstream.clone();
        Box::pin(async move {
            let answer = upstream.oneshot(request).await;
            Ok(answer.unwrap_or_else(|e| tonic::Status::unavailable(format!("the proxy: {e}")).into_http()))
        })
    }
}

/// Starts a [`Recorder`] in front of `daemon` on a port of its own; its URL, and the calls it records.
async fn recording_proxy(daemon: &Daemon) -> (String, Recorded) {
    let upstream = Channel::from_shared(daemon.url()).unwrap().connect().await.expect("the proxy reaches rayd");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("a port for the proxy");
    let url = format!("http://{}", listener.local_addr().unwrap());
    let calls = Recorded::default();
    let recorder = Recorder { upstream, calls: Arc::clone(&calls) };
    tokio::spawn(Server::builder().serve_with_incoming(recorder, TcpIncoming::from(listener)));
    (url, calls)
}

/// Takes the calls recorded so far, leaving none.
fn take_calls(calls: &Recorded) -> Vec<(String, Option<String>)> {
    std::mem::take(&mut *calls.lock().unwrap())
}

#[tokio::test(flavor = "multi_thread")]
async fn every_call_of_a_trace_of_rays_the_server_makes_carries_its_accels_scene() {
    let daemon = Daemon::start(&[]);
    let (proxy, calls) = recording_proxy(&daemon).await;
    let client = Client::connect(&proxy, small_messages()).await.expect("the client connects through the proxy");
    let bunny = bunny();
    client.build_mesh("farm.bunny", &bunny.mesh, "", BuildFlags::empty()).await.expect("a build");
    let (lo, hi) = bunny.info().bounds;
    let (width, height) = CAMERA;
    let camera =
        Generator::Pinhole(Camera::framing(lo, hi, width, height), PixelSampling { samples: 1, jitter_seed: None });
    // 80-byte hits of 6912 rays: several ranges of the small options' 64 KiB batches.
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::Full);
    take_calls(&calls);
    let traced = client.trace_generated("farm.bunny", &query, &camera).await.expect("a trace of camera rays");
    assert_eq!(traced.rays(), (width * height) as usize);
    let seen = take_calls(&calls);
    assert!(seen.len() > 1, "the camera is traced in ranges: {seen:?}");
    for (path, route) in &seen {
        assert_eq!((path.as_str(), route.as_deref()), ("/rayd.v1.Rayd/TraceBatch", Some("farm")), "{seen:?}");
    }

    // Their reflections, from hits far larger than a message: the hits go to a temporary buffer of the scene, the
    // reflections are traced in ranges naming it, and the buffer is deleted again.
    let reflections = Generator::Secondary(Secondary {
        primary: Primary::Generated(Box::new(camera)),
        hits: traced.hits().clone(),
        bounce: Bounce::Reflect,
        offset: 1e-4,
    });
    let reflected = client.trace_generated("farm.bunny", &query, &reflections).await.expect("reflections");
    let seen = take_calls(&calls);
    let paths: Vec<&str> = seen.iter().map(|(path, _)| path.trim_start_matches("/rayd.v1.Rayd/")).collect();
    let traces = paths.len() - 2;
    assert!(traces > 1, "the reflections are traced in ranges: {paths:?}");
    let expected_paths = [&["UploadBuffer"][..], &vec!["TraceBatch"; traces], &["DeleteBuffer"]].concat();
    assert_eq!(paths, expected_paths);
    assert!(seen.iter().all(|(_, route)| route.as_deref() == Some("farm")), "{seen:?}");
    assert!(client.buffers().await.expect("ListBuffers").is_empty(), "the hits' buffer is deleted");
    let sent = client.trace("farm.bunny", &query, reflections.rays(query.ray_format).into()).await.expect("sent rays");
    assert_eq!(reflected.rays(), sent.rays());
    assert!(reflected.hits() == sent.hits(), "the server's reflections are the engine's");
}

#[tokio::test]
async fn an_upload_from_parts_that_fail_keeps_nothing_and_returns_their_error() {
    let daemon = Daemon::start(&[]);
    let client = connect(&daemon, ClientOptions::default()).await;
    let part = || Ok(bytes::Bytes::from(vec![7u8; 1000]));
    let failing = || Err(rayd_client::Error::InvalidArgument("the file changed while it was read".into()));
    // Parts that fail midway, and parts that fail after every declared byte went up (the server had all it asked
    // for): the error is the parts', and no buffer is left.
    for (parts, what) in [(vec![part(), failing(), part()], "midway"), (vec![part(), part(), failing()], "at the end")]
    {
        let uploaded = client.upload_buffer_parts("", 2000, tokio_stream::iter(parts)).await;
        let error = uploaded.expect_err(what);
        assert_eq!(error.to_string(), "the file changed while it was read", "{what}");
        assert!(client.buffers().await.unwrap().is_empty(), "{what}: a buffer was left");
    }
    // Parts that hold what they declared, cut anywhere, make the buffer.
    let parts = [vec![1u8; 3], vec![2u8; 1500], vec![3u8; 497]].map(|p| Ok(bytes::Bytes::from(p)));
    let info = client.upload_buffer_parts("whole", 2000, tokio_stream::iter(parts)).await.unwrap();
    assert_eq!(info.size_bytes, 2000);
    let data = client.download_buffer(&info.id).await.unwrap();
    assert_eq!(data, [vec![1u8; 3], vec![2u8; 1500], vec![3u8; 497]].concat());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn temporary_buffers_of_a_call_given_up_midway_are_deleted_all_the_same() {
    let daemon = Daemon::start(&[]);
    let client = connect(&daemon, ClientOptions::default()).await;
    // Sixteen bunnies side by side (1.1M triangles): uploaded as buffers, and a build long enough to give up during.
    let bunny = &bunny().mesh;
    let mut mesh = rayd_engine::mesh::Mesh { positions: Vec::new(), triangles: Vec::new() };
    for copy in 0..16 {
        let first = mesh.positions.len() as u32;
        let offset = rayd_engine::glam::Vec3::new(copy as f32 * 0.2, 0.0, 0.0);
        mesh.positions.extend(bunny.positions.iter().map(|&p| p + offset));
        mesh.triangles.extend(bunny.triangles.iter().map(|t| t.map(|i| i + first)));
    }
    let building = {
        let client = client.clone();
        tokio::spawn(async move { client.build_mesh("herd", &mesh, "", BuildFlags::empty()).await })
    };
    // Given up while the build runs (both buffers are up, and the client has their ids: it asked for the build).
    let started = std::time::Instant::now();
    let building_now = || async {
        let usage = client.server_info().await.unwrap().usage.unwrap();
        usage.buffers == 2 && usage.operations == 1
    };
    while !building_now().await {
        assert!(started.elapsed().as_secs() < 60, "the build never ran");
        tokio::time::sleep(std::time::Duration::from_millis(1)).await;
    }
    building.abort();
    let _ = building.await;
    let given_up = std::time::Instant::now();
    while !client.buffers().await.unwrap().is_empty() {
        assert!(given_up.elapsed().as_secs() < 30, "buffers left behind: {:?}", client.buffers().await.unwrap());
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
}
