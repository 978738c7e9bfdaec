//! End to end against the real `rayd` binary through the generated tonic client: the shared bunny built inline and
//! from uploaded buffers, traced by batch, by stream and into server buffers, byte for byte as the engine traces
//! it in this process; health and reflection; the status code of every bad input and limit, with the server still
//! serving after each; a graceful shutdown under load; and the metrics.

mod common;
mod daemon;
mod reference;

use daemon::{Daemon, sample};
use rayd_engine::format::{HitFormat, Ray, RayFlags, RayFormat};
use rayd_engine::query::{Query, QueryKind};
use rayd_proto as pb;
use rayd_proto::rayd_client::RaydClient;
use reference::{BUNNY_TRIANGLES, Expected, assert_same_bytes, bunny};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Code, Response, Status, Streaming};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

/// The generated client over one connection.
type Client = RaydClient<Channel>;

/// Bytes per uploaded message.
const UPLOAD_CHUNK_BYTES: usize = 256 << 10;

/// A connection to `daemon`.
async fn channel(daemon: &Daemon) -> Channel {
    Channel::from_shared(daemon.url()).expect("a valid URL").connect().await.expect("rayd accepts connections")
}

/// The rayd client over `channel`, accepting replies up to the server's default message limit.
fn rayd(channel: Channel) -> Client {
    RaydClient::new(channel).max_decoding_message_size(64 << 20)
}

/// A rayd client on a new connection to `daemon`.
async fn connect(daemon: &Daemon) -> Client {
    rayd(channel(daemon).await)
}

/// Asserts that a call failed with `code` and a message that mentions `mention`, then that the server still
/// answers a call.
async fn assert_refused<T: std::fmt::Debug>(
    client: &mut Client,
    result: Result<Response<T>, Status>,
    code: Code,
    mention: &str,
) {
    let status = result.expect_err(&format!("a {code:?} error mentioning {mention:?}"));
    assert_eq!(status.code(), code, "{status:?}");
    assert!(status.message().contains(mention), "{:?} does not mention {mention:?}", status.message());
    still_serving(client).await;
}

/// Asserts that the server answers ListDevices with the CPU first.
async fn still_serving(client: &mut Client) {
    let devices = client.list_devices(pb::ListDevicesRequest {}).await.expect("rayd still serves").into_inner();
    assert_eq!(devices.devices[0].id, "cpu:0");
}

/// The contract's enum value of a ray format, looked up by name (`RAY_FORMAT_<NAME>`).
fn ray_format(format: RayFormat) -> i32 {
    let name = format!("RAY_FORMAT_{}", format.name().to_uppercase());
    pb::RayFormat::from_str_name(&name).unwrap_or_else(|| panic!("the contract has {name}")) as i32
}

/// The contract's enum value of a hit format, looked up by name.
fn hit_format(format: HitFormat) -> i32 {
    let name = format!("HIT_FORMAT_{}", format.name().to_uppercase());
    pb::HitFormat::from_str_name(&name).unwrap_or_else(|| panic!("the contract has {name}")) as i32
}

/// The contract's enum value of a query kind, looked up by name.
fn query_type(kind: QueryKind) -> i32 {
    let name = format!("QUERY_TYPE_{}", kind.name().to_uppercase());
    pb::QueryType::from_str_name(&name).unwrap_or_else(|| panic!("the contract has {name}")) as i32
}

/// Names an accel by name.
fn by_name(name: &str) -> Option<pb::AccelRef> {
    Some(pb::AccelRef { r#ref: Some(pb::accel_ref::Ref::Name(name.into())) })
}

/// Names an accel by handle.
fn by_handle(handle: &str) -> Option<pb::AccelRef> {
    Some(pb::AccelRef { r#ref: Some(pb::accel_ref::Ref::Handle(handle.into())) })
}

/// Names a buffer by id or name.
fn buffer(reference: pb::buffer_ref::Ref) -> Option<pb::BufferRef> {
    Some(pb::BufferRef { r#ref: Some(reference) })
}

/// The contract's form of an engine query on the accel named `accel`.
fn trace_query(accel: &str, query: &Query) -> pb::TraceQuery {
    pb::TraceQuery {
        accel: by_name(accel),
        query: query_type(query.kind),
        ray_format: ray_format(query.ray_format),
        hit_format: hit_format(query.hit_format),
        ray_flags: query.flags.bits(),
        max_hits_per_ray: if query.kind == QueryKind::All { query.max_hits_per_ray } else { 0 },
    }
}

/// Data given inline.
fn inline(bytes: &[u8]) -> pb::data_source::Source {
    pb::data_source::Source::Inline(bytes.to_vec().into())
}

/// Data from an uploaded buffer.
fn from_buffer(reference: pb::buffer_ref::Ref) -> pb::data_source::Source {
    pb::data_source::Source::Buffer(buffer(reference).expect("a reference"))
}

/// A triangle input of float3 vertices and u32×3 indices.
fn triangles(vertices: pb::data_source::Source, indices: pb::data_source::Source) -> pb::BuildInput {
    pb::BuildInput {
        input: Some(pb::build_input::Input::Triangles(pb::TriangleInput {
            vertices: Some(pb::DataSource { source: Some(vertices) }),
            vertex_format: pb::VertexFormat::Float3 as i32,
            indices: Some(pb::DataSource { source: Some(indices) }),
            index_format: pb::IndexFormat::Uint32x3 as i32,
            ..Default::default()
        })),
    }
}

/// The right triangle (0,0,0) (1,0,0) (0,1,0), inline, with these vertex indices.
fn triangle(indices: [u32; 3]) -> pb::BuildInput {
    let vertices: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.].iter().flat_map(|v| v.to_le_bytes()).collect();
    let indices: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
    triangles(inline(&vertices), inline(&indices))
}

/// `count` rays straight down onto [`triangle`] from 1 above it (each hits at t = 1), in `origin_direction`.
fn down_rays(count: usize) -> Vec<u8> {
    let format = RayFormat::OriginDirection;
    let ray = Ray { origin: [0.25, 0.25, 1.0].into(), direction: [0.0, 0.0, -1.0].into(), ..Ray::default() };
    let mut bytes = vec![0u8; count * format.size()];
    bytes.chunks_exact_mut(format.size()).for_each(|slot| format.encode(&ray, slot));
    bytes
}

/// Builds an accel named `name` from `inputs` on the default device with the default options.
async fn build(
    client: &mut Client,
    name: &str,
    inputs: Vec<pb::BuildInput>,
) -> Result<Response<pb::AccelInfo>, Status> {
    client.build_accel(pb::BuildAccelRequest { name: name.into(), inputs, ..Default::default() }).await
}

/// Traces inline rays in one call.
async fn trace_batch(
    client: &mut Client,
    query: pb::TraceQuery,
    rays: &[u8],
) -> Result<Response<pb::TraceBatchResponse>, Status> {
    let rays = Some(pb::trace_batch_request::Rays::RaysInline(rays.to_vec().into()));
    client.trace_batch(pb::TraceBatchRequest { query: Some(query), rays, ..Default::default() }).await
}

/// The first message of a trace stream.
fn stream_query(query: pb::TraceQuery) -> pb::TraceStreamRequest {
    pb::TraceStreamRequest { part: Some(pb::trace_stream_request::Part::Query(query)) }
}

/// A chunk of rays of a trace stream.
fn stream_rays(rays: &[u8]) -> pb::TraceStreamRequest {
    pb::TraceStreamRequest { part: Some(pb::trace_stream_request::Part::Rays(rays.to_vec().into())) }
}

/// The header message of an upload.
fn upload_header(name: &str, size_bytes: u64) -> pb::UploadBufferRequest {
    let header = pb::UploadBufferHeader { name: name.into(), size_bytes };
    pb::UploadBufferRequest { part: Some(pb::upload_buffer_request::Part::Header(header)) }
}

/// A data message of an upload.
fn upload_data(bytes: &[u8]) -> pb::UploadBufferRequest {
    pb::UploadBufferRequest { part: Some(pb::upload_buffer_request::Part::Data(bytes.to_vec().into())) }
}

/// Uploads `data` as a buffer named `name` (empty: unnamed), in chunks.
async fn upload(client: &mut Client, name: &str, data: &[u8]) -> Result<Response<pb::BufferInfo>, Status> {
    let messages =
        std::iter::once(upload_header(name, data.len() as u64)).chain(data.chunks(UPLOAD_CHUNK_BYTES).map(upload_data));
    client.upload_buffer(tokio_stream::iter(messages.collect::<Vec<_>>())).await
}

/// Downloads a range of a buffer in `chunk_bytes` messages, checking that the chunks come in order.
async fn download(
    client: &mut Client,
    reference: pb::buffer_ref::Ref,
    offset: u64,
    length: u64,
    chunk_bytes: u32,
) -> Vec<u8> {
    let request = pb::DownloadBufferRequest { buffer: buffer(reference), offset, length, chunk_bytes };
    let mut chunks = client.download_buffer(request).await.expect("the download starts").into_inner();
    let mut bytes = Vec::new();
    while let Some(chunk) = chunks.message().await.expect("every chunk arrives") {
        assert_eq!(chunk.offset, offset + bytes.len() as u64, "chunks in order");
        assert!(chunk_bytes == 0 || chunk.data.len() <= chunk_bytes as usize, "chunks of at most {chunk_bytes} bytes");
        bytes.extend_from_slice(&chunk.data);
    }
    bytes
}

/// Every buffer, by ListBuffers.
async fn list_buffers(client: &mut Client) -> Vec<pb::BufferInfo> {
    client.list_buffers(pb::ListBuffersRequest {}).await.expect("ListBuffers").into_inner().buffers
}

/// Asserts that the service's answer is the engine's, byte for byte.
fn assert_traced_as_expected(response: &pb::TraceBatchResponse, expected: &Expected, what: &str) {
    let stats = response.stats.as_ref().expect("stats");
    expected.assert_answer(&response.hits, &response.counts, (stats.rays, stats.rays_hit), what);
}

/// Queries covering every query kind, the ray formats with and without tmin, mask and flags, and hit formats from
/// one bit to 48 bytes a record.
fn queries() -> Vec<Query> {
    let closest = Query::closest;
    vec![
        closest(RayFormat::OriginDirection, HitFormat::TTriidUV),
        Query { kind: QueryKind::Any, ..closest(RayFormat::OriginTminDirectionTmax, HitFormat::Bitmask) },
        Query { kind: QueryKind::All, max_hits_per_ray: 4, ..closest(RayFormat::Full, HitFormat::Full) },
        Query { kind: QueryKind::Count, ..closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::T) },
        Query {
            flags: RayFlags::CULL_BACK_FACING,
            ..closest(RayFormat::OriginMaskDirectionTmax, HitFormat::TTriidInstidUV)
        },
    ]
}

#[tokio::test]
async fn the_bunny_built_inline_or_from_buffers_traces_to_the_engines_bytes() {
    let daemon = Daemon::start(&[]);
    let mut client = connect(&daemon).await;
    let bunny = bunny();
    let (vertices, indices) = (&bunny.packed.vertices, &bunny.packed.indices);
    let vertex_buffer = upload(&mut client, "bunny.vertices", vertices).await.expect("vertices upload").into_inner();
    let index_buffer = upload(&mut client, "", indices).await.expect("indices upload").into_inner();
    assert!(vertex_buffer.id.starts_with("buf-") && index_buffer.id.starts_with("buf-"), "{vertex_buffer:?}");
    assert_ne!(vertex_buffer.id, index_buffer.id);
    assert_eq!((vertex_buffer.name.as_str(), vertex_buffer.size_bytes), ("bunny.vertices", vertices.len() as u64));
    assert_eq!((index_buffer.name.as_str(), index_buffer.size_bytes), ("", indices.len() as u64));

    use pb::buffer_ref::Ref;
    let builds = [
        ("bunny-inline", inline(vertices), inline(indices)),
        (
            "bunny-by-name-and-id",
            from_buffer(Ref::Name("bunny.vertices".into())),
            from_buffer(Ref::Id(index_buffer.id.clone())),
        ),
        ("bunny-by-id", from_buffer(Ref::Id(vertex_buffer.id.clone())), from_buffer(Ref::Id(index_buffer.id.clone()))),
    ];
    let mut built = Vec::new();
    for (name, vertices, indices) in builds {
        let info =
            build(&mut client, name, vec![triangles(vertices, indices)]).await.expect("the bunny builds").into_inner();
        let expected = bunny.info();
        assert_eq!((info.name.as_str(), info.device.as_str()), (name, "cpu:0"));
        assert_eq!((info.triangle_count, info.geometry_count), (BUNNY_TRIANGLES, 1), "{name}");
        assert!(info.size_bytes > 0 && info.size_bytes == expected.size_bytes, "{name}: {} bytes", info.size_bytes);
        let bounds = info.bounds.as_ref().expect("bounds");
        let corner = |v: &Option<pb::Vec3>| v.as_ref().map(|v| [v.x, v.y, v.z]).expect("a corner");
        assert_eq!(
            [corner(&bounds.min), corner(&bounds.max)],
            [expected.bounds.0.to_array(), expected.bounds.1.to_array()]
        );
        assert_eq!(bunny.mesh.bounds(), expected.bounds, "the bounds are the mesh's box");
        built.push(info);
    }
    let listed = client.list_accels(pb::ListAccelsRequest {}).await.expect("ListAccels").into_inner().accels;
    assert_eq!(listed, built, "ListAccels gives every accel in creation order");
    let got = client.get_accel(pb::GetAccelRequest { accel: by_handle(&built[1].handle) }).await.expect("GetAccel");
    assert_eq!(got.into_inner(), built[1]);

    for query in queries() {
        let rays = bunny.camera_rays(query.ray_format, 96, 72);
        let expected = bunny.trace(&query, &rays);
        assert!(0 < expected.stats.rays_hit && expected.stats.rays_hit < expected.stats.rays, "rays hit and miss");
        for info in &built {
            let what = format!("{query:?} on {}", info.name);
            let response = trace_batch(&mut client, trace_query(&info.name, &query), &rays).await.expect(&what);
            assert_traced_as_expected(response.get_ref(), &expected, &what);
        }
    }

    let query = queries().remove(0);
    let rays = bunny.camera_rays(query.ray_format, 96, 72);
    upload(&mut client, "camera.rays", &rays).await.expect("rays upload");
    let request = pb::TraceBatchRequest {
        query: Some(trace_query("bunny-inline", &query)),
        rays: buffer(Ref::Name("camera.rays".into())).map(pb::trace_batch_request::Rays::RaysBuffer),
        ..Default::default()
    };
    let response = client.trace_batch(request).await.expect("a trace of uploaded rays");
    assert_traced_as_expected(response.get_ref(), &bunny.trace(&query, &rays), "rays from a buffer");
}

#[tokio::test]
async fn stream_chunks_and_hit_buffers_hold_the_engines_bytes() {
    let daemon = Daemon::start(&[]);
    let mut client = connect(&daemon).await;
    let bunny = bunny();
    build(&mut client, "bunny", vec![triangles(inline(&bunny.packed.vertices), inline(&bunny.packed.indices))])
        .await
        .expect("the bunny builds");

    let query =
        Query { kind: QueryKind::Count, ..Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriid) };
    let rays = bunny.camera_rays(query.ray_format, 128, 96);
    let expected = bunny.trace(&query, &rays);
    let chunk_rays = [1000, 1, 4096, 128 * 96 - 5097];
    let mut messages = vec![stream_query(trace_query("bunny", &query))];
    let mut rest = rays.as_slice();
    for count in chunk_rays {
        let (chunk, tail) = rest.split_at(count * query.ray_format.size());
        messages.push(stream_rays(chunk));
        rest = tail;
    }
    let mut responses =
        client.trace_stream(tokio_stream::iter(messages)).await.expect("the stream starts").into_inner();
    let (mut hits, mut counts, mut first_ray) = (Vec::new(), Vec::new(), 0);
    for count in chunk_rays {
        let response = responses.message().await.expect("every chunk is traced").expect("a response a chunk");
        assert_eq!(response.first_ray, first_ray);
        assert_eq!(response.stats.as_ref().expect("stats").rays, count as u64);
        hits.extend_from_slice(&response.hits);
        counts.extend_from_slice(&response.counts);
        first_ray += count as u64;
    }
    assert!(responses.message().await.expect("a clean end").is_none(), "one response a chunk");
    assert_same_bytes(&hits, &expected.hits, "streamed hits");
    assert_same_bytes(&counts, &expected.counts, "streamed counts");

    let query =
        Query { kind: QueryKind::All, max_hits_per_ray: 3, ..Query::closest(RayFormat::Full, HitFormat::TTriidUV) };
    let rays = bunny.camera_rays(query.ray_format, 64, 48);
    let expected = bunny.trace(&query, &rays);
    let request = pb::TraceBatchRequest {
        query: Some(trace_query("bunny", &query)),
        rays: Some(pb::trace_batch_request::Rays::RaysInline(rays.into())),
        hits_buffer_name: "bunny.hits".into(),
        ..Default::default()
    };
    let response = client.trace_batch(request).await.expect("a trace into buffers").into_inner();
    assert!(response.hits.is_empty() && response.counts.is_empty(), "nothing inline");
    let hits_buffer = response.hits_buffer.expect("the hits buffer");
    let counts_buffer = response.counts_buffer.expect("the counts buffer");
    assert_eq!((hits_buffer.name.as_str(), hits_buffer.size_bytes), ("bunny.hits", expected.hits.len() as u64));
    assert_eq!(
        (counts_buffer.name.as_str(), counts_buffer.size_bytes),
        ("bunny.hits.counts", expected.counts.len() as u64)
    );

    use pb::buffer_ref::Ref;
    let hits = download(&mut client, Ref::Name("bunny.hits".into()), 0, 0, 5000).await;
    assert_same_bytes(&hits, &expected.hits, "downloaded hits");
    let counts = download(&mut client, Ref::Id(counts_buffer.id.clone()), 0, 0, 0).await;
    assert_same_bytes(&counts, &expected.counts, "downloaded counts");
    let range = download(&mut client, Ref::Id(hits_buffer.id.clone()), 100, 1000, 300).await;
    assert_same_bytes(&range, &expected.hits[100..1100], "a downloaded range");

    assert_eq!(list_buffers(&mut client).await, [hits_buffer.clone(), counts_buffer.clone()]);
    let delete = pb::DeleteBufferRequest { buffer: buffer(Ref::Name("bunny.hits".into())) };
    client.delete_buffer(delete.clone()).await.expect("DeleteBuffer");
    assert_eq!(list_buffers(&mut client).await, [counts_buffer]);
    let result = client.delete_buffer(delete).await;
    assert_refused(&mut client, result, Code::NotFound, "bunny.hits").await;
    let gone = pb::DownloadBufferRequest { buffer: buffer(Ref::Id(hits_buffer.id.clone())), ..Default::default() };
    let result = client.download_buffer(gone).await;
    assert_refused(&mut client, result, Code::NotFound, &hits_buffer.id).await;

    // No rays: both buffers still, empty (a script downloads `<name>.counts` whatever the batch's size).
    let empty = pb::TraceBatchRequest {
        query: Some(trace_query("bunny", &query)),
        rays: Some(pb::trace_batch_request::Rays::RaysInline(Default::default())),
        hits_buffer_name: "none.hits".into(),
        ..Default::default()
    };
    let response = client.trace_batch(empty).await.expect("an empty trace into buffers").into_inner();
    let (hits_buffer, counts_buffer) = (response.hits_buffer.expect("hits"), response.counts_buffer.expect("counts"));
    assert_eq!((hits_buffer.name.as_str(), hits_buffer.size_bytes), ("none.hits", 0));
    assert_eq!((counts_buffer.name.as_str(), counts_buffer.size_bytes), ("none.hits.counts", 0));
}

#[tokio::test]
async fn health_is_serving_and_reflection_lists_the_rayd_services() {
    let daemon = Daemon::start(&[]);
    let channel = channel(&daemon).await;
    let mut health = HealthClient::new(channel.clone());
    for service in ["rayd.v1.Rayd", ""] {
        let response = health.check(HealthCheckRequest { service: service.into() }).await.expect("health check");
        assert_eq!(response.into_inner().status(), ServingStatus::Serving, "service {service:?}");
    }

    use tonic_reflection::pb::v1::ServerReflectionRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    let requests =
        [MessageRequest::ListServices(String::new()), MessageRequest::FileContainingSymbol("rayd.v1.Rayd".into())]
            .map(|request| ServerReflectionRequest { host: String::new(), message_request: Some(request) });
    let mut reflection = ServerReflectionClient::new(channel);
    let mut responses =
        reflection.server_reflection_info(tokio_stream::iter(requests)).await.expect("reflection").into_inner();
    let answer = |message: Option<_>| {
        message.and_then(|m: tonic_reflection::pb::v1::ServerReflectionResponse| m.message_response)
    };
    let Some(MessageResponse::ListServicesResponse(list)) = answer(responses.message().await.expect("a service list"))
    else {
        panic!("ListServices answers with a service list");
    };
    let services: Vec<&str> = list.service.iter().map(|s| s.name.as_str()).collect();
    for service in ["rayd.v1.Rayd", "grpc.health.v1.Health", "grpc.reflection.v1.ServerReflection"] {
        assert!(services.contains(&service), "{service} in {services:?}");
    }
    let Some(MessageResponse::FileDescriptorResponse(files)) = answer(responses.message().await.expect("descriptors"))
    else {
        panic!("FileContainingSymbol answers with file descriptors");
    };
    let names_service_proto = |file: &Vec<u8>| file.windows(21).any(|w| w == b"rayd/v1/service.proto");
    assert!(files.file_descriptor_proto.iter().any(names_service_proto), "rayd/v1/service.proto is served");
}

#[tokio::test]
async fn malformed_requests_get_their_codes_and_the_server_keeps_serving() {
    let daemon = Daemon::start(&[]);
    let mut client = connect(&daemon).await;
    let result = build(&mut client, "tri", vec![triangle([0, 1, 3])]).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "indices").await;
    let both = pb::BuildOptions { prefer_fast_trace: true, prefer_fast_build: true, ..Default::default() };
    let request = pb::BuildAccelRequest {
        name: "tri".into(),
        inputs: vec![triangle([0, 1, 2])],
        options: Some(both),
        ..Default::default()
    };
    let result = client.build_accel(request).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "PREFER_FAST_BUILD").await;
    let request = pb::BuildAccelRequest {
        name: "tri".into(),
        device: "gpu:7".into(),
        inputs: vec![triangle([0, 1, 2])],
        ..Default::default()
    };
    let result = client.build_accel(request).await;
    assert_refused(&mut client, result, Code::NotFound, "gpu:7").await;
    let result = build(&mut client, "bad name!", vec![triangle([0, 1, 2])]).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "name").await;
    let tri = build(&mut client, "tri", vec![triangle([0, 1, 2])]).await.expect("a valid build").into_inner();
    let result = build(&mut client, "tri", vec![triangle([0, 1, 2])]).await;
    assert_refused(&mut client, result, Code::AlreadyExists, "tri").await;

    let result = client.get_accel(pb::GetAccelRequest { accel: by_name("missing") }).await;
    assert_refused(&mut client, result, Code::NotFound, "missing").await;
    let result = client.get_accel(pb::GetAccelRequest { accel: by_handle("acc-999") }).await;
    assert_refused(&mut client, result, Code::NotFound, "acc-999").await;
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::T);
    let result = trace_batch(&mut client, trace_query("missing", &query), &[0; 32]).await;
    assert_refused(&mut client, result, Code::NotFound, "missing").await;

    let result = trace_batch(&mut client, trace_query("tri", &query), &[0; 33]).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "rays_inline: 33 bytes is not a multiple of 32").await;
    let counts = pb::Reduction { kind: Some(pb::reduction::Kind::Counts(pb::HitCountsReduction {})) };
    let rays = Some(pb::trace_batch_request::Rays::RaysInline(vec![0; 33].into()));
    let request = pb::TraceBatchRequest {
        query: Some(trace_query("tri", &query)),
        rays,
        reduction: Some(counts),
        ..Default::default()
    };
    let result = client.trace_batch(request).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "rays_inline: 33 bytes").await;
    // A huge name is shown by its start and its length only (1 MiB of control characters once made a message of
    // several times its size, logged whole).
    let huge_name: String = "\u{1}".repeat(1 << 20);
    for result in [
        client.get_accel(pb::GetAccelRequest { accel: by_name(&huge_name) }).await.map(|_| ()),
        build(&mut client, &huge_name, vec![triangle([0, 1, 2])]).await.map(|_| ()),
    ] {
        let status = result.expect_err("a name that names nothing, or that is too long");
        assert!(status.message().len() < 1024 && status.message().contains("(1048576 bytes)"), "{}", status.message());
    }
    let unspecified_rays = pb::TraceQuery { ray_format: 0, ..trace_query("tri", &query) };
    let result = trace_batch(&mut client, unspecified_rays, &[0; 32]).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "query.ray_format").await;
    let unspecified_hits = pb::TraceQuery { hit_format: 0, ..trace_query("tri", &query) };
    let result = trace_batch(&mut client, unspecified_hits, &[0; 32]).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "query.hit_format").await;
    let unknown_kind = pb::TraceQuery { query: 99, ..trace_query("tri", &query) };
    let result = trace_batch(&mut client, unknown_kind, &[0; 32]).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "query.query").await;
    let unknown_flags = pb::TraceQuery { ray_flags: 8, ..trace_query("tri", &query) };
    let result = trace_batch(&mut client, unknown_flags, &[0; 32]).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "query.ray_flags").await;
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 1, ..query };
    let no_hits = pb::TraceQuery { max_hits_per_ray: 0, ..trace_query("tri", &all) };
    let result = trace_batch(&mut client, no_hits, &[0; 32]).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "max_hits_per_ray").await;
    let too_many_hits = pb::TraceQuery { max_hits_per_ray: 257, ..trace_query("tri", &all) };
    let result = trace_batch(&mut client, too_many_hits, &[0; 32]).await;
    assert_refused(&mut client, result, Code::ResourceExhausted, "max_hits_per_ray").await;

    let result = client.trace_stream(tokio_stream::iter([stream_rays(&[0; 32])])).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "query").await;

    let unknown_buffer = buffer(pb::buffer_ref::Ref::Name("nowhere".into()));
    let request = pb::TraceBatchRequest {
        query: Some(trace_query("tri", &query)),
        rays: unknown_buffer.clone().map(pb::trace_batch_request::Rays::RaysBuffer),
        ..Default::default()
    };
    let result = client.trace_batch(request).await;
    assert_refused(&mut client, result, Code::NotFound, "nowhere").await;
    let result = build(
        &mut client,
        "tri-2",
        vec![triangles(from_buffer(pb::buffer_ref::Ref::Name("nowhere".into())), inline(&[0; 12]))],
    )
    .await;
    assert_refused(&mut client, result, Code::NotFound, "nowhere").await;
    let result = client.delete_buffer(pb::DeleteBufferRequest { buffer: unknown_buffer }).await;
    assert_refused(&mut client, result, Code::NotFound, "nowhere").await;

    let rays = down_rays(1);
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let response =
        trace_batch(&mut client, trace_query("tri", &query), &rays).await.expect("a valid trace").into_inner();
    assert_eq!(response.hits, 1f32.to_le_bytes().as_slice(), "the ray hits at t = 1");
    let handle = by_handle(&tri.handle);
    client.destroy_accel(pb::DestroyAccelRequest { accel: handle.clone() }).await.expect("DestroyAccel");
    assert!(client.list_accels(pb::ListAccelsRequest {}).await.expect("ListAccels").into_inner().accels.is_empty());
    let result = trace_batch(&mut client, trace_query("tri", &query), &rays).await;
    assert_refused(&mut client, result, Code::NotFound, "tri").await;
    let result = client.destroy_accel(pb::DestroyAccelRequest { accel: handle }).await;
    assert_refused(&mut client, result, Code::NotFound, &tri.handle).await;
}

/// Small limits, so that every one of them can be reached with a single triangle.
const SMALL_LIMITS: [(&str, &str); 6] = [
    ("RAYD_LIMITS_MAX_RAYS_PER_BATCH", "1000"),
    ("RAYD_LIMITS_MAX_MESSAGE_BYTES", "65536"),
    ("RAYD_LIMITS_MAX_BUFFER_BYTES", "16384"),
    ("RAYD_LIMITS_MAX_BUFFERS", "2"),
    ("RAYD_LIMITS_MAX_HITS_PER_RAY", "8"),
    ("RAYD_LIMITS_MAX_ACCELS", "2"),
];

#[tokio::test]
async fn accel_and_trace_limits_are_resource_exhausted_and_the_server_keeps_serving() {
    let daemon = Daemon::start(&SMALL_LIMITS);
    let mut client = connect(&daemon).await;
    build(&mut client, "tri", vec![triangle([0, 1, 2])]).await.expect("a first accel");
    build(&mut client, "tri-2", vec![triangle([0, 1, 2])]).await.expect("a second accel");
    let result = build(&mut client, "tri-3", vec![triangle([0, 1, 2])]).await;
    assert_refused(&mut client, result, Code::ResourceExhausted, "max_accels").await;

    // 1000 16-byte records fit the 64 KiB messages; eight a ray (an `all` query) do not.
    let closest = Query::closest(RayFormat::OriginDirection, HitFormat::TTriidUV);
    let response = trace_batch(&mut client, trace_query("tri", &closest), &down_rays(1000)).await;
    assert_eq!(response.expect("max_rays_per_batch rays").into_inner().stats.expect("stats").rays, 1000);
    let result = trace_batch(&mut client, trace_query("tri", &closest), &down_rays(1001)).await;
    let naming = "rays in one batch (rays_inline): 1001 exceeds limits.max_rays_per_batch = 1000";
    assert_refused(&mut client, result, Code::ResourceExhausted, naming).await;
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 8, ..closest };
    let result = trace_batch(&mut client, trace_query("tri", &all), &down_rays(1000)).await;
    assert_refused(&mut client, result, Code::ResourceExhausted, "max_message_bytes").await;
    let too_many_hits = pb::TraceQuery { max_hits_per_ray: 9, ..trace_query("tri", &all) };
    let result = trace_batch(&mut client, too_many_hits, &down_rays(1)).await;
    assert_refused(&mut client, result, Code::ResourceExhausted, "max_hits_per_ray").await;
    // tonic refuses a message larger than max_message_bytes before rayd sees it, with OUT_OF_RANGE.
    let result = trace_batch(&mut client, trace_query("tri", &closest), &down_rays(3000)).await;
    assert_refused(&mut client, result, Code::OutOfRange, "65536").await;

    // After a chunk of 5 rays, answered: rayd's own refusal names the chunk by its first ray.
    for (rays, code, mention) in
        [(1001, Code::ResourceExhausted, "chunk from ray 5: "), (3000, Code::OutOfRange, "65536")]
    {
        let messages =
            [stream_query(trace_query("tri", &closest)), stream_rays(&down_rays(5)), stream_rays(&down_rays(rays))];
        let mut responses =
            client.trace_stream(tokio_stream::iter(messages)).await.expect("the stream starts").into_inner();
        let answered = responses.message().await.expect("the first chunk is answered").expect("an answer");
        assert_eq!(answered.stats.expect("stats").rays, 5);
        let status = responses.message().await.expect_err("the chunk is refused");
        assert_eq!(status.code(), code, "a chunk of {rays} rays: {status:?}");
        assert!(status.message().contains(mention), "{status:?} does not mention {mention:?}");
        if code == Code::ResourceExhausted {
            assert!(status.message().starts_with(mention), "{status:?}");
            assert!(status.message().contains("rays in one batch (rays): 1001 exceeds limits.max_rays_per_batch"));
        }
        still_serving(&mut client).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn buffer_limits_and_bad_uploads_are_refused_and_the_server_keeps_serving() {
    let mut daemon = Daemon::start(&SMALL_LIMITS);
    let mut client = connect(&daemon).await;
    let result = client.upload_buffer(tokio_stream::iter([upload_data(&[1; 8])])).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "header").await;
    let short = [upload_header("short", 100), upload_data(&[1; 50])];
    let result = client.upload_buffer(tokio_stream::iter(short)).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "declared").await;
    let long = [upload_header("long", 10), upload_data(&[1; 8]), upload_data(&[1; 8])];
    let result = client.upload_buffer(tokio_stream::iter(long)).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "declared").await;
    let result = client.upload_buffer(tokio_stream::iter([upload_header("huge", 16385)])).await;
    let naming = r#"buffer "huge" (header.name): 16385 exceeds limits.max_buffer_bytes = 16384"#;
    assert_refused(&mut client, result, Code::ResourceExhausted, naming).await;
    // A data message above max_message_bytes is refused by the gRPC layer, as in every other call.
    let oversized = [upload_header("oversized", 16384), upload_data(&[1; 70000])];
    let result = client.upload_buffer(tokio_stream::iter(oversized)).await;
    assert_refused(&mut client, result, Code::OutOfRange, "65536").await;

    build(&mut client, "tri", vec![triangle([0, 1, 2])]).await.expect("an accel");
    let into_buffers = |query: &Query, rays: usize| pb::TraceBatchRequest {
        query: Some(trace_query("tri", query)),
        rays: Some(pb::trace_batch_request::Rays::RaysInline(down_rays(rays).into())),
        hits_buffer_name: "hits".into(),
        ..Default::default()
    };
    let closest = Query::closest(RayFormat::OriginDirection, HitFormat::Full);
    let result = client.trace_batch(into_buffers(&closest, 1000)).await;
    let naming = r#"buffer "hits" (hits_buffer_name)"#;
    assert_refused(&mut client, result, Code::ResourceExhausted, naming).await;
    assert!(list_buffers(&mut client).await.is_empty(), "no buffer was made by a refused call");

    let largest = upload(&mut client, "largest", &[7; 16384]).await.expect("a max_buffer_bytes buffer").into_inner();
    let second = upload(&mut client, "", &[7; 10]).await.expect("a second buffer").into_inner();
    let result = upload(&mut client, "third", &[7; 10]).await;
    assert_refused(&mut client, result, Code::ResourceExhausted, "max_buffers").await;
    let result = upload(&mut client, "largest", &[7; 10]).await;
    assert_refused(&mut client, result, Code::AlreadyExists, "largest").await;
    let delete = pb::DeleteBufferRequest { buffer: buffer(pb::buffer_ref::Ref::Id(largest.id)) };
    client.delete_buffer(delete).await.expect("DeleteBuffer");
    assert_eq!(list_buffers(&mut client).await, std::slice::from_ref(&second));
    // Room for the hits buffer but not for its counts buffer: the trace makes neither.
    let count = Query { kind: QueryKind::Count, ..closest };
    let result = client.trace_batch(into_buffers(&count, 10)).await;
    assert_refused(&mut client, result, Code::ResourceExhausted, "max_buffers").await;
    assert_eq!(list_buffers(&mut client).await, std::slice::from_ref(&second), "the refused trace left no buffer");
    // Names that cannot be buffers', refused before the trace, naming the request's field.
    let named =
        |query: &Query, name: &str| pb::TraceBatchRequest { hits_buffer_name: name.into(), ..into_buffers(query, 1) };
    let result = client.trace_batch(named(&closest, "a/b")).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "hits_buffer_name: \"a/b\"").await;
    let longest = "n".repeat(128);
    let result = client.trace_batch(named(&count, &longest)).await;
    let rule = "hits_buffer_name: 128 characters: at most 121 with counts, whose buffer's name adds \".counts\"";
    assert_refused(&mut client, result, Code::InvalidArgument, rule).await;
    let save = pb::SaveAccelRequest { accel: by_name("tri"), buffer_name: "a/b".into() };
    let result = client.save_accel(save).await;
    assert_refused(&mut client, result, Code::InvalidArgument, "buffer_name: \"a/b\"").await;
    assert_eq!(list_buffers(&mut client).await, [second], "the refused calls left no buffer");
    upload(&mut client, "third", &[7; 10]).await.expect("room for a buffer again");
    let save = pb::SaveAccelRequest { accel: by_name("tri"), buffer_name: "third".into() };
    let result = client.save_accel(save).await;
    assert_refused(&mut client, result, Code::AlreadyExists, "\"third\"").await;

    // With the client's idle connection still open.
    let exit = tokio::task::block_in_place(|| daemon.stop());
    assert_eq!(exit.code(), Some(0), "a clean exit after every refusal: {exit:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_lets_a_running_trace_finish_then_exits_zero() {
    let mut daemon = Daemon::start(&[]);
    let channel = channel(&daemon).await;
    let mut client = rayd(channel.clone());
    let bunny = bunny();
    build(&mut client, "bunny", vec![triangles(inline(&bunny.packed.vertices), inline(&bunny.packed.indices))])
        .await
        .expect("the bunny builds");
    let mut health = HealthClient::new(channel.clone());
    let watched = HealthCheckRequest { service: "rayd.v1.Rayd".into() };
    let mut watch = health.watch(watched).await.expect("a health watch").into_inner();
    assert_eq!(watch.message().await.expect("a status").expect("a first status").status(), ServingStatus::Serving);

    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let rays = bunny.camera_rays(query.ray_format, 1024, 1024);
    let expected = bunny.trace(&query, &rays);
    let mut chunks = rays.chunks((1 << 17) * query.ray_format.size());
    let (sender, receiver) = mpsc::channel(2);
    sender.send(stream_query(trace_query("bunny", &query))).await.expect("the stream is open");
    let mut responses =
        client.trace_stream(ReceiverStream::new(receiver)).await.expect("the stream starts").into_inner();
    sender.send(stream_rays(chunks.next().expect("a first chunk"))).await.expect("the stream is open");
    let first = responses.message().await.expect("the first chunk is traced").expect("a response");

    daemon.terminate();
    let status = watch.message().await.expect("a status").expect("a status change").status();
    assert_eq!(status, ServingStatus::NotServing, "health goes NOT_SERVING on SIGTERM");
    for chunk in chunks {
        sender.send(stream_rays(chunk)).await.expect("the stream is still open");
    }
    drop(sender);
    let mut hits = first.hits.to_vec();
    while let Some(response) = responses.message().await.expect("chunks sent after SIGTERM are still traced") {
        assert_eq!(response.first_ray as usize, hits.len() / 4);
        hits.extend_from_slice(&response.hits);
    }
    assert_same_bytes(&hits, &expected.hits, "hits of a stream that outlived SIGTERM");

    drop((watch, health, responses, client, channel));
    let exit = tokio::task::block_in_place(|| daemon.wait());
    assert_eq!(exit.code(), Some(0), "{exit:?}");
    let url = daemon.url();
    assert!(Channel::from_shared(url).expect("a URL").connect().await.is_err(), "no connection after the exit");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_left_open_delays_the_exit_by_the_grace_period_only() {
    let mut daemon = Daemon::start(&[("RAYD_SHUTDOWN_GRACE_SECONDS", "1")]);
    let channel = channel(&daemon).await;
    let mut health = HealthClient::new(channel.clone());
    let watched = HealthCheckRequest { service: "rayd.v1.Rayd".into() };
    let mut watch = health.watch(watched).await.expect("a health watch").into_inner();
    assert_eq!(watch.message().await.expect("a status").expect("a first status").status(), ServingStatus::Serving);
    daemon.terminate();
    // The watch stays open: only the grace period (1 s) lets rayd exit; 30 s bounds the test, it measures nothing.
    let exit = tokio::task::block_in_place(|| daemon.wait_at_most(std::time::Duration::from_secs(30)));
    let exit = exit.expect("rayd exits once the grace period is over, though a stream is still open");
    assert_eq!(exit.code(), Some(0), "{exit:?}");
    drop((watch, health, channel));
}

#[tokio::test]
async fn metrics_count_the_rays_traced_and_the_errors_by_code() {
    let daemon = Daemon::start(&[]);
    let mut client = connect(&daemon).await;
    build(&mut client, "tri", vec![triangle([0, 1, 2])]).await.expect("a valid build");
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    trace_batch(&mut client, trace_query("tri", &query), &down_rays(1000)).await.expect("a batch");
    let messages =
        [stream_query(trace_query("tri", &query)), stream_rays(&down_rays(300)), stream_rays(&down_rays(200))];
    let mut responses = client.trace_stream(tokio_stream::iter(messages)).await.expect("a stream").into_inner();
    while responses.message().await.expect("every chunk is traced").is_some() {}

    let metrics = daemon.admin_get("/metrics");
    assert_eq!(sample(&metrics, "rayd_rays_traced_total", &[]), Some(1500.0), "{metrics}");
    // A batch and two chunks: three traces, as the metric's description says.
    assert_eq!(sample(&metrics, "rayd_trace_batches_total", &[]), Some(3.0), "{metrics}");
    assert!(
        metrics.contains("# HELP rayd_trace_batches_total traces that ended: a TraceBatch call, a TraceStream chunk")
    );
    assert!(metrics.contains("# HELP rayd_request_duration_seconds time from"), "{metrics}");
    let labels = ["method=\"TraceBatch\"", "tenant=\"default\""];
    assert_eq!(sample(&metrics, "rayd_requests_total", &labels), Some(1.0), "{metrics}");
    assert!(!metrics.contains("rayd_errors_total"), "no error yet:\n{metrics}");
    let result = client.get_accel(pb::GetAccelRequest { accel: by_name("missing") }).await;
    assert_refused(&mut client, result, Code::NotFound, "missing").await;
    let metrics = daemon.admin_get("/metrics");
    let labels = ["method=\"GetAccel\"", "tenant=\"default\"", "code=\"NotFound\""];
    assert_eq!(sample(&metrics, "rayd_errors_total", &labels), Some(1.0), "{metrics}");
    assert_eq!(daemon.admin_get("/healthz"), "ok\n");

    // A stream whose chunk fails counts as an error of its call, though the call was answered as it opened.
    let messages = [stream_query(trace_query("tri", &query)), stream_rays(&[0; 5])];
    let mut responses = client.trace_stream(tokio_stream::iter(messages)).await.expect("a stream").into_inner();
    let refused = responses.message().await.expect_err("5 bytes are no whole ray");
    assert_eq!(refused.code(), Code::InvalidArgument, "{refused:?}");
    // The server counts an error about when the client hears of it: waited for, 30 s a bound against hanging.
    let errors_of = async |code: &str| {
        let labels = ["method=\"TraceStream\"", "tenant=\"default\"", &format!("code=\"{code}\"")];
        let errors = || sample(&daemon.admin_get("/metrics"), "rayd_errors_total", &labels);
        let since = std::time::Instant::now();
        while errors().is_none() && since.elapsed() < std::time::Duration::from_secs(30) {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
        errors()
    };
    assert_eq!(errors_of("InvalidArgument").await, Some(1.0));
    // A call whose deadline passes before it is answered (a stream whose query never comes): the server drops it
    // unanswered, and counts it as cancelled.
    // The deadline is only sent (the `grpc-timeout` header), not kept by the client too: a client that reset the call
    // at its own deadline raced the server's, which then could see the request stream end first (an empty stream:
    // INVALID_ARGUMENT) rather than drop the call.
    let mut request = tonic::Request::new(tokio_stream::pending::<pb::TraceStreamRequest>());
    request.metadata_mut().insert("grpc-timeout", "50m".parse().unwrap());
    let late = tokio::time::timeout(std::time::Duration::from_secs(60), client.trace_stream(request));
    let late = late.await.expect("the server keeps its deadline").expect_err("no query before the deadline");
    assert!(matches!(late.code(), Code::Cancelled | Code::DeadlineExceeded), "{late:?}");
    assert_eq!(errors_of("Cancelled").await, Some(1.0), "{}", daemon.admin_get("/metrics"));
}

/// Each chunk of a trace stream traces the accel its query names as it is when the chunk comes, as a call of its own
/// would: after an update, the new version (a stream once kept tracing the version it began with, even after the
/// accel was destroyed); after a destroy, NOT_FOUND naming `query.accel`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trace_streams_chunks_trace_the_accel_as_it_is_when_they_come() {
    let daemon = Daemon::start(&[]);
    let mut client = connect(&daemon).await;
    let updatable = Some(pb::BuildOptions { allow_update: true, ..Default::default() });
    let request = pb::BuildAccelRequest {
        name: "tri".into(),
        inputs: vec![triangle([0, 1, 2])],
        options: updatable,
        ..Default::default()
    };
    client.build_accel(request).await.expect("a valid build");
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let (sender, receiver) = mpsc::channel(2);
    sender.send(stream_query(trace_query("tri", &query))).await.expect("the stream is open");
    let mut responses =
        client.trace_stream(ReceiverStream::new(receiver)).await.expect("the stream starts").into_inner();
    let next_t = async |responses: &mut Streaming<pb::TraceStreamResponse>| {
        sender.send(stream_rays(&down_rays(1))).await.expect("the stream is open");
        let hits = responses.message().await.map(|response| response.expect("a response").hits);
        hits.map(|hits| f32::from_le_bytes(hits[..4].try_into().expect("a t")))
    };
    assert_eq!(next_t(&mut responses).await.expect("traced"), 1.0, "the triangle at z = 0, 1 below the rays");
    // The triangle moved 1 down: the next chunk meets it 2 below.
    let lowered: Vec<u8> = [0f32, 0., -1., 1., 0., -1., 0., 1., -1.].iter().flat_map(|v| v.to_le_bytes()).collect();
    let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect();
    let update =
        pb::UpdateAccelRequest { accel: by_name("tri"), inputs: vec![triangles(inline(&lowered), inline(&indices))] };
    client.update_accel(update).await.expect("an update");
    assert_eq!(next_t(&mut responses).await.expect("traced"), 2.0, "the chunk after the update traced the old version");
    client.destroy_accel(pb::DestroyAccelRequest { accel: by_name("tri") }).await.expect("a destroy");
    let gone = next_t(&mut responses).await.expect_err("a chunk traced an accel destroyed before it came");
    assert_eq!(gone.code(), Code::NotFound, "{gone}");
    assert!(gone.message().contains("query.accel"), "{gone}");
    // The accel memory gauge counted the update's version, so the destroy took it back to nothing.
    let metrics = daemon.admin_get("/metrics");
    assert_eq!(sample(&metrics, "rayd_accel_bytes", &["tenant=\"default\""]), Some(0.0), "{metrics}");
}
