//! End to end against the real `rayd`: streams (`OpenStream`) through `rayd-client`, and by hand where a test must
//! break the rules or hold a stream half-open. Order within a stream (server timestamps), products named before
//! they exist, overlap of two streams, an event ordering work across streams, errors that are not sticky,
//! cancellation returning the server's accounted memory to its baseline, bounded buffering, and many streams at
//! once under `max_streams`.

mod common;
mod daemon;
mod reference;

use std::time::Duration;

use bytes::Bytes;
use daemon::Daemon;
use rayd_client::proto::rayd_client::RaydClient;
use rayd_client::{Client, ClientOptions, Error, EventId, Operation, TraceResult, proto};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, Ray, RayFormat};
use rayd_engine::glam::Vec3A;
use rayd_engine::query::{Query, QueryKind};
use reference::{BUNNY_TRIANGLES, bunny};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::transport::Channel;

/// The closest-hit query of most traces here.
fn closest() -> Query {
    Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV)
}

/// A client of `daemon`.
async fn connect(daemon: &Daemon, options: ClientOptions) -> Client {
    Client::connect(&daemon.url(), options).await.expect("the client connects to rayd")
}

/// What the tenant holds now, as the server accounts it.
async fn usage(client: &Client) -> proto::Usage {
    client.server_info().await.expect("GetServerInfo").usage.expect("ServerInfo.usage")
}

/// Polls the tenant's usage (for up to 20 s) until `settled` holds, and returns it; panics with the last one.
async fn usage_when(client: &Client, what: &str, settled: impl Fn(&proto::Usage) -> bool) -> proto::Usage {
    let mut last = usage(client).await;
    for _ in 0..200 {
        if settled(&last) {
            return last;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
        last = usage(client).await;
    }
    panic!("{what}: the server's usage never settled; last {last:?}")
}

/// Asserts that a stream's trace is what the engine makes of the same rays in this process.
fn assert_as_engine(traced: &Operation<TraceResult>, query: &Query, rays: &[u8], what: &str) {
    let traced = traced.result().expect("answered").expect("the trace succeeded");
    let stats = traced.stats();
    bunny().trace(query, rays).assert_answer(traced.hits(), traced.counts(), (stats.rays, stats.rays_hit), what);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_runs_its_operations_in_order_on_products_named_before_they_exist() {
    let daemon = Daemon::start(&[]);
    // Small thresholds: the mesh goes up as two uploads of several messages each, named by the build by operation.
    let options = ClientOptions { inline_mesh_bytes: 64 << 10, upload_chunk_bytes: 256 << 10, ..Default::default() };
    let client = connect(&daemon, options).await;
    let stream = client.create_stream().await.expect("a stream opens");
    let bunny = bunny();
    let build = stream.build_mesh("bunny", &bunny.mesh, "", BuildFlags::empty()).await.unwrap();
    let rays = Bytes::from(bunny.camera_rays(RayFormat::OriginTminDirectionTmax, 64, 48));
    let any = Query { kind: QueryKind::Any, hit_format: HitFormat::Bitmask, ..closest() };
    let traced = [
        stream.trace(&build, &closest(), rays.clone()).await.unwrap(),
        stream.trace(&build, &any, rays.clone()).await.unwrap(),
    ];
    // Three downloaded chunks of 1 MiB and a short one: the download is reassembled in order.
    let payload: Bytes = (0..(3 << 20) + 12345).map(|i: u32| (i.wrapping_mul(2_654_435_761) >> 24) as u8).collect();
    let upload = stream.upload("payload", payload.clone()).await.unwrap();
    let download = stream.download(&upload).await.unwrap();

    stream.synchronize().await.expect("every operation succeeds");
    assert!(stream.query(), "after synchronize the stream is idle");
    let accel = build.result().unwrap().unwrap();
    assert_eq!((accel.name.as_str(), accel.triangle_count), ("bunny", BUNNY_TRIANGLES));
    assert_as_engine(&traced[0], &closest(), &rays, "closest hits on a stream");
    assert_as_engine(&traced[1], &any, &rays, "any-hit bitmask on a stream");
    assert_eq!(download.result().unwrap().unwrap(), payload, "the downloaded buffer is the uploaded one");
    assert_eq!(upload.result().unwrap().unwrap().size_bytes, payload.len() as u64);

    // Server timestamps: each operation started after the one before it finished.
    let ran = [build.ran_unix_ns(), traced[0].ran_unix_ns(), traced[1].ran_unix_ns()]
        .into_iter()
        .chain([upload.ran_unix_ns(), download.ran_unix_ns()])
        .map(|ran| ran.expect("answered"))
        .collect::<Vec<_>>();
    let ids = [build.id(), traced[0].id(), traced[1].id(), upload.id(), download.id()];
    assert_eq!(ids, [3, 6, 7, 8, 9], "uploads 1 and 2, build 3, deletes 4 and 5, then the rest in enqueue order");
    for pair in ran.windows(2) {
        assert!(pair[0].0 <= pair[0].1 && pair[0].1 <= pair[1].0, "operations overlap within a stream: {ran:?}");
    }
    // The mesh's two buffers were deleted by operations 4 and 5, after the build used them.
    let buffers: Vec<_> = client.buffers().await.unwrap().into_iter().map(|b| b.name).collect();
    assert_eq!(buffers, ["payload"]);
    stream.finish().await.expect("a clean finish");
    assert_eq!(client.accel("bunny").await.unwrap().handle, accel.handle, "products outlive their stream");
    usage_when(&client, "after finish", |u| u.streams == 0 && u.stream_bytes == 0).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_copies_and_compacts_what_it_built() {
    let daemon = Daemon::start(&[]);
    let client = connect(&daemon, ClientOptions::default()).await;
    let stream = client.create_stream().await.unwrap();
    let bunny = bunny();
    let build = stream.build_mesh("bunny", &bunny.mesh, "", BuildFlags::ALLOW_COMPACTION).await.unwrap();
    let compacted = stream.copy_accel(&build, "bunny.compact", "", true).await.unwrap();
    let rays = Bytes::from(bunny.camera_rays(RayFormat::OriginTminDirectionTmax, 32, 24));
    let traced = stream.trace(&compacted, &closest(), rays.clone()).await.unwrap();
    let copied = stream.copy_accel("bunny.compact", "bunny.copy", "", false).await.unwrap();
    let again = stream.copy_accel(&copied, "bunny.again", "", true).await.unwrap();
    let refused = stream.copy_accel("nothing", "bunny.never", "", false).await.unwrap();
    let Err(Error::Operations(failed)) = stream.synchronize().await else { panic!("the last copy fails") };
    assert_eq!(failed.iter().map(|(id, s)| (*id, s.code())).collect::<Vec<_>>(), [(refused.id(), Code::NotFound)]);
    let again = again.result().unwrap().expect("copies keep their source's options, compaction included");
    let (source, compacted) = (build.result().unwrap().unwrap(), compacted.result().unwrap().unwrap());
    assert!(compacted.size_bytes <= source.compacted_size_bytes.unwrap(), "{compacted:?} against {source:?}");
    assert_eq!(compacted.triangle_count, source.triangle_count);
    assert_as_engine(&traced, &closest(), &rays, "a trace on the compacted copy");
    assert_eq!(copied.result().unwrap().unwrap().size_bytes, compacted.size_bytes);
    assert_eq!(again.size_bytes, compacted.size_bytes, "compacting a compacted accel changes nothing");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_streams_run_at_the_same_time_and_an_event_orders_work_between_them() {
    let daemon = Daemon::start(&[]);
    let client = connect(&daemon, ClientOptions::default()).await;
    let bunny = bunny();
    client.build_mesh("bunny", &bunny.mesh, "", BuildFlags::empty()).await.unwrap();
    let (a, b) = (client.create_stream().await.unwrap(), client.create_stream().await.unwrap());
    assert_ne!(a.id(), b.id());

    // Overlap: a long trace on each stream, enqueued together.
    let rays = Bytes::from(bunny.camera_rays(RayFormat::OriginTminDirectionTmax, 640, 480));
    let on_a = a.trace("bunny", &closest(), rays.clone()).await.unwrap();
    let on_b = b.trace("bunny", &closest(), rays.clone()).await.unwrap();
    a.synchronize().await.unwrap();
    b.synchronize().await.unwrap();
    let ((a_start, a_end), (b_start, b_end)) = (on_a.ran_unix_ns().unwrap(), on_b.ran_unix_ns().unwrap());
    assert!(
        a_start < b_end && b_start < a_end,
        "the two traces ran at the same time: a {a_start}..{a_end}, b {b_start}..{b_end}"
    );
    assert_as_engine(&on_a, &closest(), &rays, "stream a");
    assert_as_engine(&on_b, &closest(), &rays, "stream b");

    // An event: b traces an accel that a builds, by name, after waiting for the event a records after the build.
    let built_on_a = a.build_mesh("later", &bunny.mesh, "", BuildFlags::PREFER_FAST_TRACE).await.unwrap();
    let event = a.record_event().await.unwrap();
    b.wait_event(&event).await.unwrap();
    let small = Bytes::from(bunny.camera_rays(RayFormat::OriginTminDirectionTmax, 32, 24));
    let on_b = b.trace("later", &closest(), small.clone()).await.unwrap();
    b.synchronize().await.expect("b's trace found the accel a built: the event held it back");
    event.wait().await.unwrap();
    assert!(event.query(), "a waited event has completed");
    let recorded = event.completed_unix_ns().unwrap();
    assert!(built_on_a.ran_unix_ns().unwrap().1 <= recorded, "the event completes after the build before it");
    assert!(on_b.ran_unix_ns().unwrap().0 >= recorded, "b's trace started after the event completed");
    assert_as_engine(&on_b, &closest(), &small, "the trace after the event");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_operation_reports_on_its_handle_and_at_synchronize_and_the_stream_goes_on() {
    let daemon = Daemon::start(&[]);
    let client = connect(&daemon, ClientOptions::default()).await;
    let bunny = bunny();
    client.build_mesh("bunny", &bunny.mesh, "", BuildFlags::empty()).await.unwrap();
    let rays = Bytes::from(bunny.camera_rays(RayFormat::OriginTminDirectionTmax, 32, 24));
    let stream = client.create_stream().await.unwrap();
    let missing = stream.trace("missing", &closest(), rays.clone()).await.unwrap();
    let bad_build = stream.build_mesh("not a name!", &bunny.mesh, "", BuildFlags::empty()).await.unwrap();
    let on_failed = stream.trace(&bad_build, &closest(), rays.clone()).await.unwrap();
    let fine = stream.trace("bunny", &closest(), rays.clone()).await.unwrap();

    let Err(Error::Operations(failed)) = stream.synchronize().await else { panic!("synchronize reports failures") };
    let codes: Vec<_> = failed.iter().map(|(id, status)| (*id, status.code())).collect();
    assert_eq!(codes, [(1, Code::NotFound), (2, Code::InvalidArgument), (3, Code::FailedPrecondition)]);
    assert!(failed[2].1.message().contains("trace.query.accel: operation 2 failed"), "{:?}", failed[2].1);
    let Some(Err(Error::Operation { operation: 1, status })) = missing.result() else { panic!("the handle fails") };
    assert!(status.message().contains("\"missing\""), "{status:?}");
    assert_eq!(on_failed.result().unwrap().unwrap_err().code(), Code::FailedPrecondition);
    assert_eq!(on_failed.ran_unix_ns(), Some((0, 0)), "refused before it started: no times");
    assert!(missing.ran_unix_ns().is_some_and(|(started, _)| started > 0), "failed once started: its times");
    assert_as_engine(&fine, &closest(), &rays, "the operation after the failures ran");
    stream.record_event().await.unwrap();
    stream.synchronize().await.expect("failures are reported once");
}

#[tokio::test]
async fn a_stream_remembers_its_latest_max_stream_products_products() {
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_STREAM_PRODUCTS", "1")]);
    let client = connect(&daemon, ClientOptions::default()).await;
    let bunny = bunny();
    let rays = Bytes::from(bunny.camera_rays(RayFormat::OriginTminDirectionTmax, 8, 8));
    let stream = client.create_stream().await.unwrap();
    let first = stream.build_mesh("first", &bunny.mesh, "", BuildFlags::empty()).await.unwrap();
    let second = stream.build_mesh("second", &bunny.mesh, "", BuildFlags::empty()).await.unwrap();
    let on_first = stream.trace(&first, &closest(), rays.clone()).await.unwrap();
    let on_second = stream.trace(&second, &closest(), rays.clone()).await.unwrap();
    let Err(Error::Operations(failed)) = stream.synchronize().await else { panic!("the forgotten product is refused") };
    let codes: Vec<_> = failed.iter().map(|(id, status)| (*id, status.code())).collect();
    assert_eq!(codes, [(3, Code::FailedPrecondition)], "only the trace naming the first build fails");
    let message = failed[0].1.message();
    assert!(message.contains("operation 1 made no accel, or is older than the products this stream"), "{message}");
    assert!(message.contains("max_stream_products = 1"), "{message}");
    assert!(on_first.result().unwrap().is_err());
    assert_as_engine(&on_second, &closest(), &rays, "the latest product is remembered");
    // What the first build made is still the tenant's: a call names it by its name.
    assert_eq!(client.trace("first", &closest(), rays).await.unwrap().rays(), 64);
}

/// A stream opened by hand: the way to send its messages, its answers, and its id.
struct RawStream {
    /// Messages to send.
    sender: mpsc::Sender<proto::StreamRequest>,
    /// The answers.
    answers: tonic::Streaming<proto::StreamResponse>,
    /// The server's id.
    id: u64,
}

/// Opens a stream by hand on `channel`.
async fn open_raw(channel: &Channel) -> RawStream {
    let (sender, requests) = mpsc::channel(1);
    let mut rpc = RaydClient::new(channel.clone()).max_decoding_message_size(usize::MAX);
    let mut answers = rpc.open_stream(ReceiverStream::new(requests)).await.unwrap().into_inner();
    let Some(proto::stream_response::Kind::Opened(opened)) = answers.message().await.unwrap().unwrap().kind else {
        panic!("the first message opens the stream")
    };
    RawStream { sender, answers, id: opened.stream_id }
}

/// Sends `messages` from a task of their own (sending blocks once the server stops reading), which keeps the
/// request side open until it is aborted or the sender is dropped after the last message.
fn send_all(
    sender: mpsc::Sender<proto::StreamRequest>,
    messages: Vec<(u64, proto::stream_request::Op)>,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        for (operation, op) in messages {
            if sender.send(proto::StreamRequest { operation, op: Some(op) }).await.is_err() {
                return;
            }
        }
        std::future::pending::<()>().await;
    })
}

/// A trace of inline `rays` on the accel `accel`.
fn trace_op(accel: &str, rays: Bytes) -> proto::stream_request::Op {
    proto::stream_request::Op::Trace(proto::TraceBatchRequest {
        query: Some(rayd_client::convert::trace_query(accel, &closest())),
        rays: Some(proto::trace_batch_request::Rays::RaysInline(rays)),
        ..Default::default()
    })
}

/// Upload `size` bytes, of which `first` come with the header.
fn upload_op(size: u64, first: Bytes) -> proto::stream_request::Op {
    let header = proto::UploadBufferHeader { name: String::new(), size_bytes: size };
    proto::stream_request::Op::Upload(proto::StreamUpload { header: Some(header), first_data: first })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_a_stream_frees_what_it_held_and_its_buffering_is_bounded() {
    let daemon = Daemon::start(&[("RAYD_LIMITS_STREAM_WINDOW", "4")]);
    let client = connect(&daemon, ClientOptions::default()).await;
    client.build_mesh("bunny", &bunny().mesh, "", BuildFlags::empty()).await.unwrap();
    let base = usage(&client).await;
    assert_eq!((base.streams, base.stream_bytes), (0, 0));
    let traces_run = || daemon.metric("rayd_stream_operations_total", &["op=\"trace\""]).unwrap_or(0.0);
    let ran_before = traces_run();

    // x is opened and left idle: its operation 1 never comes, so waiting for it blocks.
    let channel = Channel::from_shared(daemon.url()).unwrap().connect_lazy();
    let x = open_raw(&channel).await;
    // y, on a connection of its own, waits for x's operation 1, then 16 traces of 1 MiB of rays queue behind it.
    let (y_channel, y_connection) = daemon.cuttable_channel().await;
    let y = open_raw(&y_channel).await;
    let ray = 1 << 20;
    let wait = proto::stream_request::Op::WaitEvent(proto::WaitEvent { stream_id: x.id, operation: 1 });
    let traces = (2..18).map(|id| (id, trace_op("bunny", Bytes::from(vec![0u8; ray]))));
    let y_sending = send_all(y.sender, std::iter::once((1, wait)).chain(traces).collect());
    let held = usage_when(&client, "y's queue filling", |u| u.stream_bytes >= 4 * ray as u64).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let held = usage(&client).await.stream_bytes.max(held.stream_bytes);
    // The window's 4 queued messages and the one the reader holds: 5 traces of 16, however long y waits.
    assert!(held <= 5 * (ray as u64 + 1024), "the server read {held} bytes ahead");

    // z is in the middle of an upload: 3 of 8 MiB have come.
    let z = open_raw(&channel).await;
    let data = proto::stream_request::Op::UploadData(Bytes::from(vec![7u8; 1 << 20]));
    let z_messages = vec![(1, upload_op(8 << 20, Bytes::from(vec![7u8; 1 << 20]))), (1, data.clone()), (1, data)];
    let z_sending = send_all(z.sender, z_messages);
    let holding = usage_when(&client, "z's upload", |u| u.stream_bytes >= held + (3 << 20)).await;
    assert_eq!(holding.streams, 3);

    // y's client disconnects: its connection is cut (its request side is held back by flow control, so the call
    // could not even be reset). z is cancelled by CancelStream, its call left open; it ends with CANCELLED.
    y_connection.shutdown(std::net::Shutdown::Both).unwrap();
    let mut rpc = RaydClient::new(channel.clone());
    rpc.cancel_stream(proto::CancelStreamRequest { stream_id: z.id }).await.expect("CancelStream");
    let mut z_answers = z.answers;
    let ended = loop {
        match z_answers.message().await {
            Ok(Some(_)) => continue,
            ended => break ended,
        }
    };
    assert_eq!(ended.unwrap_err().code(), Code::Cancelled, "a cancelled stream's call ends with CANCELLED");
    let after = usage_when(&client, "after cancelling", |u| u.streams == 1 && u.stream_bytes == 0).await;
    drop((y.answers, y_sending, z_sending));
    assert_eq!((after.object_bytes, after.buffers, after.accels), (base.object_bytes, base.buffers, base.accels));
    assert_eq!(traces_run(), ran_before, "no queued trace of the cancelled stream ran");
    drop(x);
    usage_when(&client, "after x", |u| u.streams == 0).await;
    let unknown = rpc.cancel_stream(proto::CancelStreamRequest { stream_id: 99 }).await.unwrap_err();
    assert_eq!(unknown.code(), Code::NotFound);
    assert_eq!(unknown.message(), "stream_id: stream \"99\" not found");

    // Dropping a client library stream cancels it too: of three long traces, at most the running one finishes.
    let stream = client.create_stream().await.unwrap();
    let rays = Bytes::from(bunny().camera_rays(RayFormat::OriginTminDirectionTmax, 640, 480));
    let handles = [
        stream.trace("bunny", &closest(), rays.clone()).await.unwrap(),
        stream.trace("bunny", &closest(), rays.clone()).await.unwrap(),
        stream.trace("bunny", &closest(), rays).await.unwrap(),
    ];
    drop(stream);
    for handle in &handles {
        assert_eq!(handle.wait().await.unwrap_err().code(), Code::Cancelled, "an unanswered operation fails");
    }
    let after = usage_when(&client, "after dropping", |u| u.streams == 0 && u.stream_bytes == 0).await;
    assert_eq!(after.object_bytes, base.object_bytes);
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(traces_run() <= ran_before + 1.0, "queued traces were dropped, not run");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_a_stream_whose_answers_wait_unread_drops_them_and_ends_with_cancelled() {
    let daemon = Daemon::start(&[("RAYD_LIMITS_STREAM_WINDOW", "2")]);
    let client = connect(&daemon, ClientOptions::default()).await;
    client.build_mesh("bunny", &bunny().mesh, "", BuildFlags::empty()).await.unwrap();
    // 12 traces whose answers (4.9 MB of hits each, more than the client's 2 MiB stream window) are not read: flow
    // control stops the first, the window's answers wait in the server and the next one waits for room.
    let rays = Bytes::from(bunny().camera_rays(RayFormat::OriginTminDirectionTmax, 640, 480));
    let hit_bytes = 640 * 480 * closest().hit_format.size().unwrap() as u64;
    let channel = Channel::from_shared(daemon.url()).unwrap().connect_lazy();
    let w = open_raw(&channel).await;
    let traces_run = || daemon.metric("rayd_stream_operations_total", &["op=\"trace\""]).unwrap_or(0.0);
    let sending = send_all(w.sender, (1..=12).map(|id| (id, trace_op("bunny", rays.clone()))).collect());
    // Three traces run: the first answer taken by the call (which flow control then holds), the second waiting in
    // the window at least. (The bytes held alone could be the reader's traces before any answer, and with answers
    // smaller than the window the call took all of them in time: both seen.)
    let started = std::time::Instant::now();
    while traces_run() < 3.0 {
        assert!(started.elapsed().as_secs() < 60, "{} traces ran", traces_run());
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let waiting = 2 * hit_bytes;
    let held = usage_when(&client, "answers waiting", |u| u.stream_bytes >= waiting).await;
    // On another connection: this one's window is full of the stream's unread answers and unsent rays.
    let mut rpc = RaydClient::new(Channel::from_shared(daemon.url()).unwrap().connect_lazy());
    rpc.cancel_stream(proto::CancelStreamRequest { stream_id: w.id }).await.unwrap();
    // The answers held are dropped at once; the stream's place goes once its call has ended (below).
    usage_when(&client, "after cancelling", |u| u.stream_bytes == 0).await;
    let mut answers = w.answers;
    let mut answered = 0;
    let ended = loop {
        match answers.message().await {
            Ok(Some(_)) => answered += 1,
            ended => break ended,
        }
    };
    let ended = ended.expect_err("a cancelled stream's call does not end with OK");
    assert_eq!(ended.code(), Code::Cancelled, "{ended}");
    let dropped: u64 = ended.message().split(": ").nth(1).and_then(|m| m.split(' ').next()?.parse().ok()).unwrap_or(0);
    assert!(dropped > 0 && ended.message().contains("unsent answers dropped"), "{ended}");
    assert!(answered < 12, "{answered} answers came of 12; {} bytes were held", held.stream_bytes);
    usage_when(&client, "after the call ended", |u| u.streams == 0).await;
    drop(sending);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_holds_back_enqueueing_beyond_its_bytes_in_flight() {
    let daemon = Daemon::start(&[]);
    let options = ClientOptions { stream_bytes_in_flight: 3 << 20, ..Default::default() };
    let client = connect(&daemon, options).await;
    client.build_mesh("bunny", &bunny().mesh, "", BuildFlags::empty()).await.unwrap();
    // Another client's stream, idle: its operation 1 never comes, so waiting for it holds this stream.
    let channel = Channel::from_shared(daemon.url()).unwrap().connect_lazy();
    let other = open_raw(&channel).await;
    let stream = client.create_stream().await.unwrap();
    let held = stream.wait_event(EventId { stream_id: other.id, operation: 1 }).await.unwrap();
    // 1 MiB of rays a trace: two fit in 3 MiB with the wait; the third must wait for room.
    let rays = Bytes::from(vec![0u8; 1 << 20]);
    let mut queued = Vec::new();
    for _ in 0..2 {
        queued.push(stream.trace("bunny", &closest(), rays.clone()).await.unwrap());
    }
    let third = tokio::time::timeout(Duration::from_millis(500), stream.trace("bunny", &closest(), rays.clone())).await;
    assert!(third.is_err(), "enqueueing beyond stream_bytes_in_flight waits");
    assert!(!held.is_done() && !stream.query());
    // Once the other stream closes, the wait completes, the traces run and room comes back.
    drop(other);
    queued.push(stream.trace("bunny", &closest(), rays.clone()).await.unwrap());
    stream.synchronize().await.unwrap();
    assert!(held.is_done() && queued.iter().all(|t| t.result().unwrap().is_ok()));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_message_that_breaks_the_rules_ends_the_stream_with_its_status() {
    let daemon = Daemon::start(&[]);
    let channel = Channel::from_shared(daemon.url()).unwrap().connect_lazy();
    let cases = [
        (vec![(2, proto::stream_request::Op::RecordEvent(proto::RecordEvent {}))], "operation: 2 received where 1"),
        (
            vec![
                (1, upload_op(4, Bytes::from_static(b"ab"))),
                (1, proto::stream_request::Op::UploadData(Bytes::from_static(b"cde"))),
            ],
            "more bytes than upload 1 declared",
        ),
        (vec![(1, proto::stream_request::Op::UploadData(Bytes::from_static(b"x")))], "not the upload"),
    ];
    for (messages, expected) in cases {
        let mut raw = open_raw(&channel).await;
        send_all(raw.sender, messages);
        let status = loop {
            match raw.answers.message().await {
                Ok(Some(_)) => continue,
                Ok(None) => panic!("the stream ended without an error ({expected})"),
                Err(status) => break status,
            }
        };
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        assert!(status.message().contains(expected), "{status:?} should say {expected:?}");
    }
    // A reference to a stream operation outside a stream.
    let by_operation = proto::AccelRef { r#ref: Some(proto::accel_ref::Ref::Operation(1)) };
    let request = proto::GetAccelRequest { accel: Some(by_operation) };
    let error = RaydClient::new(channel).get_accel(request).await.unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument);
    assert!(error.message().contains("stream operation"), "{error:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_download_of_too_many_chunks_fails_and_the_stream_goes_on() {
    let daemon = Daemon::start(&[]);
    let channel = Channel::from_shared(daemon.url()).unwrap().connect_lazy();
    let mut raw = open_raw(&channel).await;
    let by_upload = || Some(proto::BufferRef { r#ref: Some(proto::buffer_ref::Ref::Operation(1)) });
    let download = |chunk_bytes| {
        let request = proto::DownloadBufferRequest { buffer: by_upload(), chunk_bytes, ..Default::default() };
        proto::stream_request::Op::Download(request)
    };
    // 200,000 bytes in chunks of 1 byte (200,000 messages, beyond the limit), then of 4 bytes (50,000).
    let messages = vec![(1, upload_op(200_000, Bytes::from(vec![7u8; 200_000]))), (2, download(1)), (3, download(4))];
    send_all(raw.sender, messages);
    let (mut results, mut chunks) = (Vec::new(), 0);
    while results.len() < 3 {
        match raw.answers.message().await.unwrap().expect("every operation is answered").kind {
            Some(proto::stream_response::Kind::Result(result)) => results.push(result),
            Some(proto::stream_response::Kind::DownloadChunk(_)) => chunks += 1,
            _ => {}
        }
    }
    assert_eq!(results.iter().map(|r| (r.operation, r.code)).collect::<Vec<_>>(), [(1, 0), (2, 3), (3, 0)]);
    assert!(results[1].message.contains("download.chunk_bytes: 200000 chunks"), "{:?}", results[1].message);
    assert_eq!(chunks, 50_000, "the download of 4-byte chunks, within the limit, ran");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn many_streams_trace_at_once_up_to_max_streams() {
    const STREAMS: u32 = 24;
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_STREAMS", &STREAMS.to_string())]);
    let client = connect(&daemon, ClientOptions::default()).await;
    let bunny = bunny();
    client.build_mesh("bunny", &bunny.mesh, "", BuildFlags::empty()).await.unwrap();
    let buffer = client.upload_buffer("bytes", Bytes::from_static(b"a few bytes")).await.unwrap();
    let mut streams = Vec::new();
    for _ in 0..STREAMS {
        streams.push(client.create_stream().await.expect("a stream within max_streams"));
    }
    let refused = client.create_stream().await.expect_err("one stream too many");
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(refused.to_string().contains("max_streams"), "{refused}");
    // A TraceStream call is a stream too: it holds a place for as long as it lasts.
    let mut rpc = RaydClient::new(Channel::from_shared(daemon.url()).unwrap().connect_lazy());
    let (requests, queued) = mpsc::channel(1);
    let query = proto::trace_stream_request::Part::Query(rayd_client::convert::trace_query("bunny", &closest()));
    requests.send(proto::TraceStreamRequest { part: Some(query.clone()) }).await.unwrap();
    let refused = rpc.trace_stream(ReceiverStream::new(queued)).await.expect_err("a trace stream too many");
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(refused.message().contains("max_streams"), "{refused:?}");
    // So is a download: it holds its buffer's bytes while it lasts, even past a delete.
    let refused = client.download_buffer(&buffer.id).await.expect_err("a download too many");
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(refused.to_string().contains("max_streams"), "{refused}");

    let rays = Bytes::from(bunny.camera_rays(RayFormat::OriginTminDirectionTmax, 48, 32));
    let mut tasks = tokio::task::JoinSet::new();
    for stream in streams {
        let rays = rays.clone();
        tasks.spawn(async move {
            let mut traced = Vec::new();
            for _ in 0..3 {
                traced.push(stream.trace("bunny", &closest(), rays.clone()).await.unwrap());
            }
            stream.synchronize().await.unwrap();
            stream.finish().await.unwrap();
            traced
        });
    }
    let mut answered = 0;
    while let Some(traced) = tasks.join_next().await {
        for operation in traced.unwrap() {
            assert_as_engine(&operation, &closest(), &rays, "one of many streams");
            answered += 1;
        }
    }
    assert_eq!(answered, 3 * STREAMS);
    usage_when(&client, "after every stream finished", |u| u.streams == 0).await;
    client.create_stream().await.expect("places are freed when streams end");
    let (requests, queued) = mpsc::channel(1);
    requests.send(proto::TraceStreamRequest { part: Some(query) }).await.unwrap();
    let answers = rpc.trace_stream(ReceiverStream::new(queued)).await.expect("a trace stream within max_streams");
    usage_when(&client, "with a trace stream open", |u| u.streams == 1).await;
    drop((requests, answers));
    usage_when(&client, "after the trace stream ended", |u| u.streams == 0).await;
    assert_eq!(client.download_buffer(&buffer.id).await.unwrap(), Bytes::from_static(b"a few bytes"));
    usage_when(&client, "after the download", |u| u.streams == 0).await;
}

/// A moving build on a stream whose every motion key is a buffer uploaded earlier on the stream, named by its
/// operation: the keys are found (they once were refused as "a stream operation … only an operation of the same
/// stream may name", though `vertices` and `indices` were found), and a ray at each key's time hits the triangle
/// where that key puts it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_moving_build_names_every_key_by_an_upload_of_its_stream() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    let stream = client.create_stream().await.unwrap();
    // One triangle at z = 1 at time 0, z = 2 at time 0.5 and z = 3 at time 1.
    let triangle_at = |z: f32| Bytes::from([0.0, 0.0, z, 1.0, 0.0, z, 0.0, 1.0, z].map(f32::to_le_bytes).concat());
    let mut keys = Vec::new();
    for z in [1.0, 2.0, 3.0] {
        keys.push(stream.upload("", triangle_at(z)).await.unwrap());
    }
    let indices = stream.upload("", Bytes::from([0u32, 1, 2].map(u32::to_le_bytes).concat())).await.unwrap();
    let by_operation = |upload: &Operation<proto::BufferInfo>| proto::DataSource {
        source: Some(proto::data_source::Source::Buffer(proto::BufferRef {
            r#ref: Some(proto::buffer_ref::Ref::Operation(upload.id())),
        })),
    };
    let triangles = proto::TriangleInput {
        vertices: Some(by_operation(&keys[0])),
        motion_vertices: keys[1..].iter().map(by_operation).collect(),
        vertex_format: proto::VertexFormat::Float3.into(),
        indices: Some(by_operation(&indices)),
        index_format: proto::IndexFormat::Uint32x3.into(),
        ..Default::default()
    };
    let motion = proto::MotionOptions { keys: 3, time_begin: 0.0, time_end: 1.0, ..Default::default() };
    let request = proto::BuildAccelRequest {
        name: "moving".into(),
        inputs: vec![proto::BuildInput { input: Some(proto::build_input::Input::Triangles(triangles)) }],
        options: Some(proto::BuildOptions { motion: Some(motion), ..Default::default() }),
        ..Default::default()
    };
    let build = stream.build(request).await.unwrap();
    stream.synchronize().await.unwrap();
    assert_eq!(build.result().unwrap().unwrap().triangle_count, 1);
    // Rays up the z axis through the triangle at times 0, 0.5 and 1: they meet it at z = 1, 2 and 3.
    let query = Query::closest(RayFormat::Full, HitFormat::T);
    let rays: Vec<u8> = [0.0f32, 0.5, 1.0]
        .iter()
        .flat_map(|&time| {
            let (origin, direction) = (Vec3A::new(0.25, 0.25, 0.0), Vec3A::Z);
            let ray = Ray { origin, direction, time, ..Ray::default() };
            let mut bytes = vec![0u8; RayFormat::Full.size()];
            RayFormat::Full.encode(&ray, &mut bytes);
            bytes
        })
        .collect();
    let hits = client.trace("moving", &query, Bytes::from(rays)).await.unwrap();
    let t: Vec<f32> = hits.hits().chunks_exact(4).map(|t| f32::from_le_bytes(t.try_into().unwrap())).collect();
    assert_eq!(t, [1.0, 2.0, 3.0]);
}
