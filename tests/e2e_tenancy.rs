//! End to end against the real `rayd` with configured tenants: every call of the contract × {no key, an unknown
//! key, a read key, a write key, an admin key} against the role it needs; the client's calls on one tenant's
//! objects × {a read key, a write key, an admin key of another tenant}, each with its expected code; another
//! tenant's objects answer NOT_FOUND exactly as missing ones do; both rotated keys work; per-tenant limits and
//! quotas; usage through ListTenants, `rayctl stats` and metric labels; persisted tenants in separate directories.

mod common;
mod daemon;

use std::future::Future;
use std::path::{Path, PathBuf};

use bytes::Bytes;
use common::pack_rays;
use daemon::Daemon;
use rayd_client::{Client, ClientOptions, Error};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, Ray, RayFormat};
use rayd_engine::glam::{Vec3, Vec3A};
use rayd_engine::query::Query;
use tonic::Code;

const ACME_WRITE: &str = "acme-write-key-0123456789";
const ACME_WRITE_NEXT: &str = "acme-write-key-rotated-9876";
const ACME_READ: &str = "acme-read-key-0123456789";
const BETA_ADMIN: &str = "beta-admin-key-0123456789";

/// A configuration file with tenants `acme` (two write keys, a read key, share 3, at most 3 accels) and `beta` (an admin
/// key), and a data directory.
fn config(dir: &Path) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let path = dir.join("rayd.toml");
    let text = format!(
        r#"data_dir = {data:?}
[[tenants]]
name = "acme"
keys = [
  {{ key = "{ACME_WRITE}", role = "write" }},
  {{ key = "{ACME_WRITE_NEXT}", role = "write" }},
  {{ key = "{ACME_READ}", role = "read" }},
]
share = 3
limits = {{ max_accels = 3 }}

[[tenants]]
name = "beta"
keys = [{{ key = "{BETA_ADMIN}", role = "admin" }}]
"#,
        data = dir.join("data")
    );
    std::fs::write(&path, text).unwrap();
    path
}

/// A client sending `token`.
async fn client(daemon: &Daemon, token: Option<&str>) -> Client {
    let options = ClientOptions { token: token.map(str::to_owned), ..ClientOptions::default() };
    Client::connect(&daemon.url(), options).await.unwrap()
}

/// The code a call ends with (`Ok` for success).
async fn code<T>(call: impl Future<Output = Result<T, Error>>) -> Code {
    call.await.map_or_else(|e| e.code(), |_| Code::Ok)
}

/// One closest-hit trace of a ray down onto the unit triangle.
fn one_ray() -> Bytes {
    let ray = Ray { origin: Vec3A::new(0.2, 0.2, 1.0), direction: -Vec3A::Z, ..Ray::default() };
    Bytes::from(pack_rays(&[ray], RayFormat::OriginTminDirectionTmax))
}

/// The codes of one call of each kind made with `caller` on the objects named `accel` and `buffer` (new objects
/// are named after `fresh`), in the order of [`CALLS`].
async fn codes(caller: &Client, accel: &str, buffer: &str, fresh: &str) -> Vec<Code> {
    let triangle = common::unit_triangle();
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
    vec![
        code(caller.server_info()).await,
        code(caller.devices()).await,
        code(caller.accels()).await,
        code(caller.accel(accel)).await,
        code(caller.buffers()).await,
        code(caller.download_buffer(buffer)).await,
        code(caller.trace(accel, &query, one_ray())).await,
        code(caller.build_mesh(fresh, &triangle, "", BuildFlags::empty())).await,
        code(caller.copy_accel(accel, &format!("{fresh}.copy"), "", false)).await,
        code(caller.save_accel(accel)).await,
        code(caller.create_stream()).await,
        code(caller.destroy_accel(accel)).await,
        code(caller.delete_buffer(buffer)).await,
        // Last: ids are per tenant, so a new buffer may take the id of another tenant's.
        code(caller.upload_buffer("", Bytes::from_static(b"1234"))).await,
    ]
}

/// The roles of keys, as the server orders them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Role {
    Read,
    Write,
    Admin,
}

/// Every call of the contract, made with the generated stub (so that it reaches the server whatever the key), with
/// the role it needs and the code it ended with. Requests are minimal: past the key check most fail validation,
/// which is not what is looked at here.
async fn every_call(daemon: &Daemon, token: Option<&str>) -> Vec<(&'static str, Role, Code)> {
    use rayd_client::proto::{self, rayd_client::RaydClient};
    let header: Option<tonic::metadata::MetadataValue<_>> = token.map(|t| format!("Bearer {t}").parse().unwrap());
    let channel = tonic::transport::Endpoint::from_shared(daemon.url()).unwrap().connect().await.unwrap();
    let mut rpc = RaydClient::with_interceptor(channel, move |mut request: tonic::Request<()>| {
        if let Some(value) = &header {
            request.metadata_mut().insert("authorization", value.clone());
        }
        Ok(request)
    });
    let accel = || Some(rayd_client::convert::accel_ref("tri"));
    let buffer = || Some(rayd_client::convert::buffer_ref("buf-1"));
    vec![
        ("GetServerInfo", Role::Read, of(rpc.get_server_info(proto::GetServerInfoRequest {}).await)),
        ("ListDevices", Role::Read, of(rpc.list_devices(proto::ListDevicesRequest {}).await)),
        ("ListAccels", Role::Read, of(rpc.list_accels(proto::ListAccelsRequest {}).await)),
        ("GetAccel", Role::Read, of(rpc.get_accel(proto::GetAccelRequest { accel: accel() }).await)),
        ("ListBuffers", Role::Read, of(rpc.list_buffers(proto::ListBuffersRequest {}).await)),
        (
            "DownloadBuffer",
            Role::Read,
            of(rpc.download_buffer(proto::DownloadBufferRequest { buffer: buffer(), ..Default::default() }).await),
        ),
        (
            "ComputeMemoryUsage",
            Role::Read,
            of(rpc.compute_memory_usage(proto::ComputeMemoryUsageRequest::default()).await),
        ),
        ("TraceBatch", Role::Read, of(rpc.trace_batch(proto::TraceBatchRequest::default()).await)),
        (
            "TraceStream",
            Role::Read,
            of(rpc.trace_stream(tokio_stream::iter(Vec::<proto::TraceStreamRequest>::new())).await),
        ),
        ("BuildAccel", Role::Write, of(rpc.build_accel(proto::BuildAccelRequest::default()).await)),
        ("UpdateAccel", Role::Write, of(rpc.update_accel(proto::UpdateAccelRequest::default()).await)),
        ("CopyAccel", Role::Write, of(rpc.copy_accel(proto::CopyAccelRequest::default()).await)),
        ("SaveAccel", Role::Write, of(rpc.save_accel(proto::SaveAccelRequest::default()).await)),
        ("LoadAccel", Role::Write, of(rpc.load_accel(proto::LoadAccelRequest::default()).await)),
        ("DestroyAccel", Role::Write, of(rpc.destroy_accel(proto::DestroyAccelRequest::default()).await)),
        (
            "UploadBuffer",
            Role::Write,
            of(rpc.upload_buffer(tokio_stream::iter(Vec::<proto::UploadBufferRequest>::new())).await),
        ),
        ("DeleteBuffer", Role::Write, of(rpc.delete_buffer(proto::DeleteBufferRequest::default()).await)),
        ("OpenStream", Role::Write, of(rpc.open_stream(tokio_stream::iter(Vec::<proto::StreamRequest>::new())).await)),
        ("CancelStream", Role::Write, of(rpc.cancel_stream(proto::CancelStreamRequest { stream_id: 1 }).await)),
        ("ListTenants", Role::Admin, of(rpc.list_tenants(proto::ListTenantsRequest {}).await)),
    ]
}

/// Checks that each call of `answers` was refused for its key (`UNAUTHENTICATED` without one, or with an unknown
/// one; `PERMISSION_DENIED` when `role` is below what the call needs) or let through otherwise.
fn check_key(answers: &[(&str, Role, Code)], role: Option<Role>, case: &str) {
    for &(call, needs, code) in answers {
        let expected = match role {
            None => Some(Code::Unauthenticated),
            Some(role) if role < needs => Some(Code::PermissionDenied),
            Some(_) => None,
        };
        match expected {
            Some(refusal) => assert_eq!(code, refusal, "{case}: {call}"),
            None => assert!(
                ![Code::Unauthenticated, Code::PermissionDenied].contains(&code),
                "{case}: {call} must get past the key check, got {code:?}"
            ),
        }
    }
}

/// The code a call of the generated stub ended with.
fn of<T>(result: Result<tonic::Response<T>, tonic::Status>) -> Code {
    result.map_or_else(|status| status.code(), |_| Code::Ok)
}

/// The calls [`codes`] makes: the first seven need a read key, the others a write key.
const CALLS: usize = 14;
/// How many of [`CALLS`] only read.
const READS: usize = 7;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_call_answers_by_key_role_and_tenant() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("rayd-tenancy-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let daemon = Daemon::start(&[("RAYD_CONFIG", config(&dir).to_str().unwrap())]);
    let acme = client(&daemon, Some(ACME_WRITE)).await;
    let triangle = common::unit_triangle();
    acme.build_mesh("tri", &triangle, "", BuildFlags::empty()).await.unwrap();
    let buffer = acme.upload_buffer("data", Bytes::from_static(b"acme's bytes")).await.unwrap();

    check_key(&every_call(&daemon, None).await, None, "no key");
    check_key(&every_call(&daemon, Some("no-such-key-at-all-000000")).await, None, "an unknown key");
    check_key(&every_call(&daemon, Some(ACME_READ)).await, Some(Role::Read), "a read key");
    check_key(&every_call(&daemon, Some(ACME_WRITE)).await, Some(Role::Write), "a write key");
    check_key(&every_call(&daemon, Some(BETA_ADMIN)).await, Some(Role::Admin), "an admin key");
    let error = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap_err();
    assert_eq!(error.code(), Code::Unauthenticated, "the client reports it at once: {error}");

    let read = codes(&client(&daemon, Some(ACME_READ)).await, "tri", &buffer.id, "x").await;
    let mut expected = vec![Code::Ok; READS];
    expected.extend([Code::PermissionDenied; CALLS - READS]);
    assert_eq!(read, expected, "a read key reads and traces, and may do nothing else");

    // Another tenant, even with an admin key, sees none of acme's objects: NOT_FOUND, as for missing ones.
    let beta = client(&daemon, Some(BETA_ADMIN)).await;
    let foreign = codes(&beta, "tri", &buffer.id, "beta1").await;
    let missing = codes(&beta, "nothing", "buf-999", "beta2").await;
    assert_eq!(foreign, missing, "another tenant's objects look exactly like missing ones");
    assert_eq!([foreign[3], foreign[5], foreign[6]], [Code::NotFound; 3], "get, download, trace");
    let names: Vec<String> = beta.accels().await.unwrap().into_iter().map(|a| a.name).collect();
    assert_eq!(names, ["beta1", "beta2"], "beta lists only its own accels");
    assert_eq!(acme.accel("tri").await.unwrap().name, "tri", "acme's accel is untouched");
    assert_eq!(acme.download_buffer(&buffer.id).await.unwrap(), Bytes::from_static(b"acme's bytes"));

    // Both write keys of acme work (rotation); acme's own limit of 3 accels holds.
    let next = client(&daemon, Some(ACME_WRITE_NEXT)).await;
    let write = codes(&next, "tri", &buffer.id, "acme1").await;
    assert_eq!(write, vec![Code::Ok; CALLS], "a write key may do everything on its tenant's objects");
    // Builds until the limit: each one kept, or refused by it (acme may hold some accels already).
    for name in ["a", "b", "c"] {
        if let Err(error) = acme.build_mesh(name, &triangle, "", BuildFlags::empty()).await {
            assert!(error.code() == Code::ResourceExhausted && error.to_string().contains("max_accels = 3"), "{error}");
        }
    }
    let error = acme.build_mesh("d", &triangle, "", BuildFlags::empty()).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
    assert!(error.to_string().contains("max_accels = 3"), "{error}");
    assert!(dir.join("data/tenants/acme/accels").is_dir() && dir.join("data/tenants/beta/accels").is_dir());

    // Usage against quotas: admin keys only, through the API and `rayctl stats`; metrics carry the tenant.
    assert_eq!(acme.tenants().await.unwrap_err().code(), Code::PermissionDenied, "a write key may not list tenants");
    let tenants = beta.tenants().await.unwrap();
    let names: Vec<&str> = tenants.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["acme", "beta"]);
    let (usage, limits) = (tenants[0].usage.unwrap(), tenants[0].limits.unwrap());
    assert_eq!((usage.accels, limits.max_accels), (acme.accels().await.unwrap().len() as u32, 3));
    let stats = std::process::Command::new(daemon::binary("rayctl"))
        .args(["--server", &daemon.url(), "--token", BETA_ADMIN, "--json", "stats"])
        .output()
        .unwrap();
    assert!(stats.status.success(), "{}", String::from_utf8_lossy(&stats.stderr));
    let stats: serde_json::Value = serde_json::from_slice(&stats.stdout).unwrap();
    assert_eq!(stats["tenants"][0]["name"], "acme", "{stats}");
    assert_eq!(stats["tenants"][0]["max_accels"], 3, "{stats}");
    assert_eq!((stats["tenants"][0]["share"].as_u64(), stats["tenants"][1]["share"].as_u64()), (Some(3), Some(1)));
    let traced = |tenant: &str| daemon.metric("rayd_rays_traced_total", &[&format!("tenant=\"{tenant}\"")]);
    assert!(traced("acme").is_some_and(|rays| rays >= 1.0), "acme's rays are counted under its name");
    assert_eq!(traced("beta"), None, "beta traced nothing");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `rayd` configured with one tenant `name`, its write key `key` and its `limits` (TOML inline-table keys), and the
/// directory that holds the configuration (`case` names it).
fn one_tenant(case: &str, name: &str, key: &str, limits: &str) -> (Daemon, PathBuf) {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("rayd-{case}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("rayd.toml");
    let text = format!(
        r#"[[tenants]]
name = "{name}"
keys = [{{ key = "{key}", role = "write" }}]
limits = {{ {limits} }}
"#
    );
    std::fs::write(&path, text).unwrap();
    (Daemon::start(&[("RAYD_CONFIG", path.to_str().unwrap())]), dir)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tenant_quotas_refuse_before_anything_is_made() {
    let key = "gamma-write-key-0123456789";
    let limits = "max_total_buffer_bytes = 10, max_total_accel_bytes = 6000, max_rays_per_second = 100";
    let (daemon, dir) = one_tenant("quotas", "gamma", key, limits);
    let gamma = client(&daemon, Some(key)).await;
    let limits = gamma.server_info().await.unwrap().limits.unwrap();
    assert_eq!((limits.max_total_buffer_bytes, limits.max_rays_per_second), (10, 100), "the tenant's own quotas");

    gamma.upload_buffer("a", Bytes::from_static(b"12345678")).await.unwrap();
    let error = gamma.upload_buffer("b", Bytes::from_static(b"12345678")).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
    assert!(error.to_string().contains("max_total_buffer_bytes = 10"), "{error}");
    assert_eq!(gamma.buffers().await.unwrap().len(), 1, "nothing of the refused upload remains");

    let triangle = common::unit_triangle();
    gamma.build_mesh("tri", &triangle, "", BuildFlags::empty()).await.unwrap();
    let sphere = common::icosphere(3, Vec3::ZERO);
    let error = gamma.build_mesh("sphere", &sphere, "", BuildFlags::empty()).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
    assert!(error.to_string().contains("max_total_accel_bytes = 6000"), "{error}");
    assert_eq!(gamma.accels().await.unwrap().len(), 1, "nothing of the refused build remains");

    // 100 rays a second: a batch of 1000 runs (into debt), the next one is refused until the allowance refills.
    let rays: Vec<Ray> =
        (0..1000).map(|_| Ray { origin: Vec3A::new(0.2, 0.2, 1.0), direction: -Vec3A::Z, ..Ray::default() }).collect();
    let rays = Bytes::from(pack_rays(&rays, RayFormat::OriginTminDirectionTmax));
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
    gamma.trace("tri", &query, rays.clone()).await.unwrap();
    let error = gamma.trace("tri", &query, one_ray()).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
    assert!(error.to_string().contains("max_rays_per_second = 100"), "{error}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn loads_are_checked_by_their_loaded_bytes() {
    // A blob whose accel takes more bytes loaded than the blob does, made by the engine as the server makes it.
    let sphere = common::icosphere(5, Vec3::ZERO);
    let packed = sphere.pack();
    let engine = rayd_engine::Context::new(rayd_engine::Device::cpu());
    let inputs = [rayd_engine::geometry::BuildInput::Triangles(packed.input())];
    let built = engine.build_accel(&inputs, &rayd_engine::accel::BuildOptions::default()).unwrap();
    let blob = engine.serialize_accel(&built, &[]).unwrap();
    let loaded = engine.deserialize_accel(&blob, &[]).unwrap()[0].info().size_bytes;
    assert!(loaded > blob.len() as u64, "loaded {loaded} bytes from a blob of {}", blob.len());
    let between = (loaded + blob.len() as u64) / 2;

    let zeta = "zeta-write-key-0123456789";
    let (daemon, dir) = one_tenant("loaded", "zeta", zeta, &format!("max_total_accel_bytes = {between}"));

    // The blob fits zeta's max_total_accel_bytes; the accel loaded from it does not.
    let zeta = client(&daemon, Some(zeta)).await;
    let error = zeta.load_accel("sphere", "", Bytes::from(blob)).await.unwrap_err();
    assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
    assert!(error.to_string().contains(&format!("max_total_accel_bytes = {between}")), "{error}");
    assert!(zeta.accels().await.unwrap().is_empty(), "nothing of the refused load remains");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn loads_are_checked_against_the_tenants_graph_depth_and_motion_keys() {
    use rayd_engine::geometry::{BuildInput, MotionFlags, MotionOptions, TransformInput};
    // Blobs the engine makes as the server saves them: a transform over a triangle (2 levels), whose motion has 3
    // keys.
    let engine = rayd_engine::Context::new(rayd_engine::Device::cpu());
    let packed = common::icosphere(1, Vec3::ZERO).pack();
    let inputs = [BuildInput::Triangles(packed.input())];
    let child = engine.build_accel(&inputs, &rayd_engine::accel::BuildOptions::default()).unwrap();
    let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
    let motion = MotionOptions { keys: 3, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
    let moving = TransformInput::MatrixMotion { keys: vec![identity; 3], motion };
    let transform = engine.build_transform(&moving, &child).unwrap();
    let blob = Bytes::from(engine.serialize_accel(&transform, &[]).unwrap());

    let key = "eta-write-key-0123456789";
    for (case, limits, named) in [
        (
            "deep-load",
            "max_graph_depth = 1",
            "levels of accel 1 of the blob, loaded: 2 exceeds limits.max_graph_depth = 1",
        ),
        (
            "keyed-load",
            "max_motion_keys = 2",
            "motion keys of accel 1 of the blob, loaded: 3 exceeds limits.max_motion_keys = 2",
        ),
    ] {
        let (daemon, dir) = one_tenant(case, "eta", key, limits);
        let eta = client(&daemon, Some(key)).await;
        let error = eta.load_accel("moving", "", blob.clone()).await.unwrap_err();
        assert_eq!(error.code(), Code::ResourceExhausted, "{error}");
        assert!(error.to_string().contains(named), "{error}");
        assert!(eta.accels().await.unwrap().is_empty(), "nothing of the refused load remains");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// A call without a known key is refused before its message is read: one beyond `max_message_bytes` is answered
/// UNAUTHENTICATED, not OUT_OF_RANGE (which it gets with a key), so that unauthenticated callers cannot make the server
/// receive and decompress large messages. The Bearer scheme's name is matched in any case.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn keys_are_checked_before_messages_are_read() {
    let key = "delta-write-key-0123456789";
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("rayd-early-keys-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("rayd.toml");
    std::fs::write(&path, format!("[[tenants]]\nname = \"delta\"\nkeys = [{{ key = \"{key}\", role = \"write\" }}]\n"))
        .unwrap();
    let daemon = Daemon::start(&[("RAYD_CONFIG", path.to_str().unwrap()), ("RAYD_LIMITS_MAX_MESSAGE_BYTES", "65536")]);
    let mut raw = rayd_proto::rayd_client::RaydClient::connect(daemon.url()).await.unwrap();
    let large = || {
        let rays = Some(rayd_proto::trace_batch_request::Rays::RaysInline(vec![0; 100_000].into()));
        tonic::Request::new(rayd_proto::TraceBatchRequest { rays, ..Default::default() })
    };
    let refused = raw.trace_batch(large()).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated, "{refused:?}");
    let mut request = large();
    request.metadata_mut().insert("authorization", format!("bearer  {key}").parse().unwrap());
    let refused = raw.trace_batch(request).await.unwrap_err();
    assert_eq!(refused.code(), Code::OutOfRange, "a known key, then the message's size: {refused:?}");
    let _ = std::fs::remove_dir_all(&dir);
}
