//! Faults against the real `rayd` (issue 13, point 4): a deadline that passes during a long trace and a client
//! that vanishes mid-trace stop the trace at its next piece (which takes no rays: one piece `skipped` in
//! `rayd_trace_pieces_total`); an upload in progress reserves its declared size against the tenant's buffer quota,
//! and a client that vanishes mid-upload leaves nothing behind and frees the reservation; a client that never reads
//! a `TraceStream`'s answers holds a bounded number of chunks and nothing more is traced for it, and past
//! `stream_stall_seconds` its stream is failed (RESOURCE_EXHAUSTED) and the answers held dropped, as are an
//! `OpenStream` stream's and a download's; a build whose caller goes (a deadline, a dropped stream) keeps nothing;
//! through all of it the server answers everyone else correctly.

mod common;
mod daemon;
mod reference;

use std::time::Duration;

use bytes::Bytes;
use daemon::Daemon;
use rayd_client::proto::rayd_client::RaydClient;
use rayd_client::{Client, ClientOptions, proto};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use reference::bunny;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::transport::Channel;

/// Rays a piece of a CPU trace.
const PIECE_RAYS: usize = 1024;

/// The closest-hit query of every trace here.
fn closest() -> Query {
    Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV)
}

/// `rayd_trace_pieces_total{outcome}` of the default tenant.
fn pieces(daemon: &Daemon, outcome: &str) -> u64 {
    daemon.metric("rayd_trace_pieces_total", &[&format!("outcome=\"{outcome}\"")]).unwrap_or(0.0) as u64
}

/// Polls (for up to 60 s) until `settled` holds of the pieces traced and skipped so far; returns them. The skips are
/// read first: a trace's pieces run one after another on the one worker, so the count of traced pieces read after a
/// skip holds every piece traced before it (read the other way round, a piece that ended between the two reads
/// would be missing, and a later wait for "more traced than that" would end at once).
async fn pieces_when(daemon: &Daemon, what: &str, settled: impl Fn(u64, u64) -> bool) -> (u64, u64) {
    for _ in 0..600 {
        let skipped = pieces(daemon, "skipped");
        let traced = pieces(daemon, "traced");
        if settled(traced, skipped) {
            return (traced, skipped);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!(
        "{what}: the pieces never settled: traced {}, skipped {}",
        pieces(daemon, "traced"),
        pieces(daemon, "skipped")
    )
}

/// A slow scene: a pile of copies of one triangle, which every ray through it crosses copy after copy.
fn pile() -> Mesh {
    let triangle = common::icosphere(0, rayd_engine::glam::Vec3::ZERO);
    Mesh { triangles: vec![triangle.triangles[0]; 20_000], ..triangle }
}

/// `pieces` pieces of rays into the pile, all through it (the closest query must test every copy).
fn pile_rays(pieces: usize) -> Bytes {
    let mesh = pile();
    let [a, b, c] = mesh.corners(0);
    let centre = (a + b + c) / 3.0;
    let ray = rayd_engine::format::Ray {
        origin: (centre * 3.0).into(),
        direction: (-centre * 2.0).into(),
        ..Default::default()
    };
    Bytes::from(common::pack_rays(&vec![ray; pieces * PIECE_RAYS], RayFormat::OriginTminDirectionTmax))
}

/// Asserts that the bunny still traces to the engine's bytes.
async fn still_right(client: &Client) {
    let rays = bunny().camera_rays(RayFormat::OriginTminDirectionTmax, 32, 32);
    let traced = client.trace("bunny", &closest(), Bytes::from(rays.clone())).await.expect("a trace after the fault");
    let stats = traced.stats();
    bunny().trace(&closest(), &rays).assert_answer(
        traced.hits(),
        traced.counts(),
        (stats.rays, stats.rays_hit),
        "after",
    );
}

/// Polls (for up to 60 s, a bound against hanging) until a `method` stream has been failed for its stall.
async fn stalled(daemon: &Daemon, method: &str) {
    let label = format!("method=\"{method}\"");
    for _ in 0..600 {
        if daemon.metric("rayd_streams_stalled_total", &[&label]).is_some_and(|count| count >= 1.0) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("no {method} stream was failed for its stall within 60 s");
}

/// Reads a stream's answers until it ends with a status: how many came first, and the status.
async fn read_until_status<T>(answers: &mut tonic::Streaming<T>) -> (usize, tonic::Status) {
    let mut delivered = 0;
    loop {
        match answers.message().await {
            Ok(Some(_)) => delivered += 1,
            Ok(None) => panic!("the stalled stream ended without a status after {delivered} answers"),
            Err(status) => return (delivered, status),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_passed_deadline_or_a_vanished_client_stops_a_long_trace_at_its_next_piece() {
    // Pieces of the largest size (1,024 rays) after the first few, however long they take: a whole trace takes this
    // many pieces or more.
    let total = 64u64;
    let daemon = Daemon::start(&[("RAYD_SCHEDULER_WORKERS", "1"), ("RAYD_SCHEDULER_PIECE_MS", "60000")]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    client.build_mesh("bunny", &bunny().mesh, "", BuildFlags::empty()).await.unwrap();
    client.build_mesh("pile", &pile(), "", BuildFlags::empty()).await.unwrap();
    let rays = pile_rays(total as usize);
    let request = |rays: Bytes| proto::TraceBatchRequest {
        query: Some(rayd_client::convert::trace_query("pile", &closest())),
        rays: Some(proto::trace_batch_request::Rays::RaysInline(rays)),
        ..Default::default()
    };

    // A deadline that passes after the first piece started.
    let channel = Channel::from_shared(daemon.url()).unwrap().connect().await.unwrap();
    let mut rpc = RaydClient::new(channel).max_decoding_message_size(usize::MAX);
    let mut call = tonic::Request::new(request(rays.clone()));
    call.set_timeout(Duration::from_millis(1500));
    let status = rpc.trace_batch(call).await.unwrap_err();
    // The client gives up at its deadline (CANCELLED, "Timeout expired") as the server does (DEADLINE_EXCEEDED).
    assert!(matches!(status.code(), Code::DeadlineExceeded | Code::Cancelled), "{status:?}");
    // The next piece, queued when the piece running at the deadline started, finds the trace abandoned and takes no
    // rays (one worker: it runs once that piece has ended, so nothing is traced after it).
    let (traced, skipped) = pieces_when(&daemon, "after the deadline", |_, s| s >= 1).await;
    assert_eq!(skipped, 1, "one piece skipped, and the trace ended there");
    assert!(
        traced < total,
        "the trace stopped at the deadline: {traced} pieces, where the whole takes {total} or more"
    );
    println!("deadline: {traced} pieces traced, then one skipped");
    // Each piece that ran was timed for the tenant's device time (no trace ran on the caller's thread so far): one
    // time a piece traced, once the piece that was running when the skip was counted (if one was) is counted too.
    let timed = |series: &str| daemon.metric(series, &["tenant=\"default\"", "device=\"cpu:0\""]);
    let one_time_a_piece = |t: u64, _| timed("rayd_trace_piece_seconds_count") == Some(t as f64);
    let (traced, _) = pieces_when(&daemon, "one time a piece traced", one_time_a_piece).await;
    assert!(traced < total, "{traced} pieces");
    assert!(timed("rayd_trace_piece_seconds_sum").is_some_and(|seconds| seconds > 0.0));

    // A client that vanishes in the middle of a trace: its connection is cut once a piece has been traced.
    let (channel, connection) = daemon.cuttable_channel().await;
    let mut rpc = RaydClient::new(channel).max_decoding_message_size(usize::MAX);
    let rays_again = rays.clone();
    let calling = tokio::spawn(async move { rpc.trace_batch(request(rays_again)).await });
    pieces_when(&daemon, "the second trace starting", |t, _| t > traced).await;
    connection.shutdown(std::net::Shutdown::Both).unwrap();
    assert!(calling.await.unwrap().is_err(), "the cut call fails");
    let (traced_now, skipped_now) = pieces_when(&daemon, "after the cut", |_, s| s >= 2).await;
    assert_eq!(skipped_now, 2, "one piece skipped, and the trace ended there");
    assert!(traced_now - traced < total, "the trace stopped at the cut: {} pieces", traced_now - traced);
    println!("cut: {} pieces traced, then one skipped", traced_now - traced);

    // The same for a TraceStream's chunk, which traced on for nobody once its call had ended.
    let (channel, connection) = daemon.cuttable_channel().await;
    let mut rpc = RaydClient::new(channel).max_decoding_message_size(usize::MAX);
    let (sending, requests) = mpsc::channel(2);
    let query = rayd_client::convert::trace_query("pile", &closest());
    for part in [proto::trace_stream_request::Part::Query(query), proto::trace_stream_request::Part::Rays(rays)] {
        sending.send(proto::TraceStreamRequest { part: Some(part) }).await.unwrap();
    }
    let streaming = tokio::spawn(async move { rpc.trace_stream(ReceiverStream::new(requests)).await.map(drop) });
    pieces_when(&daemon, "the stream's chunk starting", |t, _| t > traced_now).await;
    connection.shutdown(std::net::Shutdown::Both).unwrap();
    drop(sending);
    let _ = streaming.await;
    let (traced_last, skipped_last) = pieces_when(&daemon, "after the stream's cut", |_, s| s >= 3).await;
    assert_eq!(skipped_last, 3, "one piece skipped, and the chunk's trace ended there");
    assert!(traced_last - traced_now < total, "the chunk stopped at the cut: {} pieces", traced_last - traced_now);

    let usage = client.server_info().await.unwrap().usage.unwrap();
    assert_eq!(usage.operations, 0, "nothing is left running");
    still_right(&client).await;
    // A one-ray trace on the idle server runs on the calling thread: its time is the tenant's device time too.
    let before = timed("rayd_trace_piece_seconds_count").unwrap();
    let one_ray = Bytes::from(bunny().camera_rays(RayFormat::OriginTminDirectionTmax, 1, 1));
    client.trace("bunny", &closest(), one_ray).await.unwrap();
    assert_eq!(timed("rayd_trace_piece_seconds_count"), Some(before + 1.0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_vanishing_mid_upload_leaves_nothing_and_a_reader_that_never_reads_is_bounded_then_failed() {
    let (window, stall_seconds) = (2u64, 6u64);
    let daemon = Daemon::start(&[
        ("RAYD_LIMITS_STREAM_WINDOW", &window.to_string()),
        ("RAYD_LIMITS_STREAM_STALL_SECONDS", &stall_seconds.to_string()),
        ("RAYD_LIMITS_MAX_TOTAL_BUFFER_BYTES", &(96u64 << 20).to_string()),
    ]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    client.build_mesh("bunny", &bunny().mesh, "", BuildFlags::empty()).await.unwrap();
    let before = client.server_info().await.unwrap().usage.unwrap();

    // An upload of 64 MiB cut after 3 MiB.
    let (channel, connection) = daemon.cuttable_channel().await;
    let (sender, requests) = mpsc::channel(4);
    let mut rpc = RaydClient::new(channel.clone());
    let uploading = tokio::spawn(async move { rpc.upload_buffer(ReceiverStream::new(requests)).await });
    let header = proto::UploadBufferHeader { name: "cut".into(), size_bytes: 64 << 20 };
    sender
        .send(proto::UploadBufferRequest { part: Some(proto::upload_buffer_request::Part::Header(header)) })
        .await
        .unwrap();
    for _ in 0..3 {
        let data = proto::upload_buffer_request::Part::Data(Bytes::from(vec![1u8; 1 << 20]));
        sender.send(proto::UploadBufferRequest { part: Some(data) }).await.unwrap();
    }
    // While it is in progress its 64 MiB are reserved: another upload of 40 MiB would outgrow the tenant's 96 MiB.
    let other = Bytes::from(vec![2u8; 40 << 20]);
    let refused = client.upload_buffer("other", other.clone()).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused}");
    assert!(refused.to_string().contains("max_total_buffer_bytes"), "{refused}");
    connection.shutdown(std::net::Shutdown::Both).unwrap();
    assert!(uploading.await.unwrap().is_err(), "the cut upload fails");
    drop(sender);
    // The cut upload's reservation is released (once the server has seen the connection go).
    let mut accepted = None;
    for _ in 0..100 {
        match client.upload_buffer("other", other.clone()).await {
            Ok(info) => {
                accepted = Some(info);
                break;
            }
            Err(e) if e.code() == Code::ResourceExhausted => tokio::time::sleep(Duration::from_millis(100)).await,
            Err(e) => panic!("{e}"),
        }
    }
    let accepted = accepted.expect("the upload fits once the cut one is gone");
    client.delete_buffer(&accepted.id).await.unwrap();

    // A TraceStream whose client sends chunk after chunk and never reads an answer.
    let (channel, connection) = daemon.cuttable_channel().await;
    let mut rpc = RaydClient::new(channel);
    let batches = || daemon.metric("rayd_trace_batches_total", &[]).unwrap_or(0.0) as u64;
    let batches_before = batches();
    let rays = Bytes::from(bunny().camera_rays(RayFormat::OriginTminDirectionTmax, 256, 256));
    let first = proto::TraceStreamRequest {
        part: Some(proto::trace_stream_request::Part::Query(rayd_client::convert::trace_query("bunny", &closest()))),
    };
    let chunks = (0..1000)
        .map(move |_| proto::TraceStreamRequest { part: Some(proto::trace_stream_request::Part::Rays(rays.clone())) });
    let mut answers =
        rpc.trace_stream(tokio_stream::iter(std::iter::once(first).chain(chunks))).await.unwrap().into_inner();
    still_right(&client).await;
    // The server traces until its answers fill the window and the transport's buffers, waits for room for the stall
    // limit, then fails the stream: a server that traced on without bound would trace all 1000 chunks and never stall.
    stalled(&daemon, "TraceStream").await;
    // One batch is `still_right`'s.
    let traced = batches() - batches_before - 1;
    // Answers waiting to be sent (the window), the one being sent, and what HTTP/2's flow-control windows take.
    assert!(traced <= window + 8, "{traced} chunks were traced for a client that read none of them");
    println!("stalled reader: {traced} of 1000 chunks traced");
    // The answers the server held are dropped and the stream is failed: a client that reads again gets what was
    // already on its way, then the status naming the limit.
    let (delivered, failure) = read_until_status(&mut answers).await;
    assert_eq!(failure.code(), Code::ResourceExhausted, "{failure:?}");
    assert!(failure.message().contains("limits.stream_stall_seconds"), "{failure:?}");
    assert!(
        (delivered as u64) < traced,
        "{delivered} answers delivered of {traced} traced: the held ones were dropped"
    );
    println!("stalled reader: failed after {stall_seconds} s; {delivered} answers were already on their way");
    assert_eq!(batches() - batches_before - 1, traced, "nothing more was traced for the failed stream");
    connection.shutdown(std::net::Shutdown::Both).unwrap();

    // The same for an OpenStream stream whose client enqueues traces and never reads a result.
    let (channel, connection) = daemon.cuttable_channel().await;
    let mut rpc = RaydClient::new(channel);
    let rays = Bytes::from(bunny().camera_rays(RayFormat::OriginTminDirectionTmax, 256, 256));
    let trace = move |operation| proto::StreamRequest {
        operation,
        op: Some(proto::stream_request::Op::Trace(proto::TraceBatchRequest {
            query: Some(rayd_client::convert::trace_query("bunny", &closest())),
            rays: Some(proto::trace_batch_request::Rays::RaysInline(rays.clone())),
            ..Default::default()
        })),
    };
    let mut results = rpc.open_stream(tokio_stream::iter((1..=1000).map(trace))).await.unwrap().into_inner();
    stalled(&daemon, "OpenStream").await;
    let (delivered, failure) = read_until_status(&mut results).await;
    assert_eq!(failure.code(), Code::ResourceExhausted, "{failure:?}");
    assert!(failure.message().contains("limits.stream_stall_seconds"), "{failure:?}");
    println!("stalled OpenStream reader: failed after {stall_seconds} s; {delivered} answers were on their way");
    connection.shutdown(std::net::Shutdown::Both).unwrap();

    // The same for a download of 40 chunks of 1 MiB whose client reads none.
    let large = client.upload_buffer("large", Bytes::from(vec![3u8; 40 << 20])).await.unwrap();
    let (channel, connection) = daemon.cuttable_channel().await;
    let request = proto::DownloadBufferRequest {
        buffer: Some(proto::BufferRef { r#ref: Some(proto::buffer_ref::Ref::Id(large.id.clone())) }),
        chunk_bytes: 1 << 20,
        ..Default::default()
    };
    let mut chunks = RaydClient::new(channel).download_buffer(request).await.unwrap().into_inner();
    stalled(&daemon, "DownloadBuffer").await;
    let (delivered, failure) = read_until_status(&mut chunks).await;
    assert_eq!(failure.code(), Code::ResourceExhausted, "{failure:?}");
    assert!(failure.message().contains("limits.stream_stall_seconds"), "{failure:?}");
    assert!(delivered < 40, "{delivered} chunks delivered: the held ones were dropped");
    println!("stalled download: failed after {stall_seconds} s; {delivered} chunks were on their way");
    connection.shutdown(std::net::Shutdown::Both).unwrap();
    client.delete_buffer(&large.id).await.unwrap();

    let after = client.server_info().await.unwrap().usage.unwrap();
    assert_eq!((after.buffers, after.object_bytes, after.operations), (before.buffers, before.object_bytes, 0));
    still_right(&client).await;
}

/// Polls (for up to 60 s) until the default tenant's running operations satisfy `settled`.
async fn operations_when(client: &Client, what: &str, settled: impl Fn(u32) -> bool) {
    for _ in 0..12_000 {
        if settled(client.server_info().await.unwrap().usage.unwrap().operations) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    panic!("{what}: the running operations never settled");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_build_whose_caller_goes_is_not_kept() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    // 1.3 M triangles: a build that takes far longer than the deadline below.
    let packed = common::icosphere(8, rayd_engine::glam::Vec3::ZERO).pack();
    let vertices = client.upload_buffer("", Bytes::from(packed.vertices)).await.unwrap().id;
    let indices = client.upload_buffer("", Bytes::from(packed.indices)).await.unwrap().id;
    let buffer = |id: &str| proto::DataSource {
        source: Some(proto::data_source::Source::Buffer(rayd_client::convert::buffer_ref(id))),
    };
    let request = proto::BuildAccelRequest {
        name: "big".into(),
        inputs: vec![proto::BuildInput {
            input: Some(proto::build_input::Input::Triangles(proto::TriangleInput {
                vertices: Some(buffer(&vertices)),
                vertex_format: rayd_client::convert::vertex_format_to_proto(
                    rayd_engine::geometry::VertexFormat::Float3,
                )
                .into(),
                indices: Some(buffer(&indices)),
                index_format: rayd_client::convert::index_format_to_proto(rayd_engine::geometry::IndexFormat::U32x3)
                    .into(),
                ..Default::default()
            })),
        }],
        ..Default::default()
    };
    let nothing_kept = |when: &'static str| {
        let client = client.clone();
        async move {
            operations_when(&client, when, |running| running == 0).await;
            let accels = client.accels().await.unwrap();
            assert!(accels.is_empty(), "{when}: {accels:?}");
            let usage = client.server_info().await.unwrap().usage.unwrap();
            assert_eq!((usage.accels, usage.accel_bytes), (0, 0), "{when}");
        }
    };

    // A deadline that passes while the accel is being built.
    let channel = Channel::from_shared(daemon.url()).unwrap().connect().await.unwrap();
    let mut call = tonic::Request::new(request.clone());
    call.set_timeout(Duration::from_millis(50));
    let status = RaydClient::new(channel).build_accel(call).await.unwrap_err();
    assert!(matches!(status.code(), Code::DeadlineExceeded | Code::Cancelled), "{status:?}");
    nothing_kept("after the deadline").await;

    // A stream cancelled while its build runs (dropping a stream cancels it).
    let stream = client.create_stream().await.unwrap();
    let build = stream.build(request.clone()).await.unwrap();
    operations_when(&client, "the stream's build starting", |running| running >= 1).await;
    drop(stream);
    assert_eq!(build.wait().await.unwrap_err().code(), Code::Cancelled);
    nothing_kept("after the stream was cancelled").await;

    // What they held was let go: the same build for a caller that waits is kept.
    let info = client.build(request).await.unwrap();
    assert_eq!(info.triangle_count, 1_310_720);
    assert_eq!(client.accels().await.unwrap().len(), 1);
}
