//! The transport's limits against the real `rayd` (issue 13, point 5): the HTTP/2 settings of `[transport]` are
//! the ones a client is sent; a client that opens and resets streams faster than the server takes them up
//! (rapid reset) gets GOAWAY while other connections are served; a unary message over `max_message_bytes` is
//! refused without being read into memory; and a long `TraceStream` moves more than any one message may hold
//! (256 MiB of rays here, `RAYD_BIG_STREAM_MIB` to set; 1.9 GiB by hand with `--ignored`).

mod common;
mod daemon;
mod reference;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

use bytes::Bytes;
use daemon::Daemon;
use rayd_client::proto;
use rayd_client::proto::rayd_client::RaydClient;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::query::Query;
use reference::bunny;
use tonic::Code;
use tonic::transport::Channel;

/// HTTP/2 frame types (RFC 9113, section 6).
const SETTINGS: u8 = 0x4;
const HEADERS: u8 = 0x1;
const RST_STREAM: u8 = 0x3;
const GOAWAY: u8 = 0x7;
/// The GOAWAY error code for a peer that generates excessive load.
const ENHANCE_YOUR_CALM: u32 = 0xb;

/// One HTTP/2 frame, encoded.
fn frame(kind: u8, flags: u8, stream: u32, payload: &[u8]) -> Vec<u8> {
    let mut bytes = (payload.len() as u32).to_be_bytes()[1..].to_vec();
    bytes.extend([kind, flags]);
    bytes.extend(stream.to_be_bytes());
    bytes.extend(payload);
    bytes
}

/// Reads one frame: its type, flags and payload.
fn read_frame(connection: &mut TcpStream) -> std::io::Result<(u8, u8, Vec<u8>)> {
    let mut head = [0u8; 9];
    connection.read_exact(&mut head)?;
    let len = u32::from_be_bytes([0, head[0], head[1], head[2]]) as usize;
    let mut payload = vec![0u8; len];
    connection.read_exact(&mut payload)?;
    Ok((head[3], head[4], payload))
}

/// A raw HTTP/2 connection to `daemon` after the client preface and an empty SETTINGS frame; returns it and the
/// server's SETTINGS as `(identifier, value)` pairs.
fn raw_connection(daemon: &Daemon) -> (TcpStream, Vec<(u16, u32)>) {
    let mut connection = TcpStream::connect(daemon.grpc_addr()).unwrap();
    connection.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    connection.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n").unwrap();
    connection.write_all(&frame(SETTINGS, 0, 0, &[])).unwrap();
    loop {
        let (kind, flags, payload) = read_frame(&mut connection).unwrap();
        if kind == SETTINGS && flags & 1 == 0 {
            let settings = payload
                .chunks_exact(6)
                .map(|s| (u16::from_be_bytes([s[0], s[1]]), u32::from_be_bytes([s[2], s[3], s[4], s[5]])))
                .collect();
            return (connection, settings);
        }
    }
}

/// A HEADERS block (HPACK, no Huffman coding, no new table entries) of a `POST` of `path`: `:method POST` and
/// `:scheme http` indexed (static entries 3 and 6), `:path` a literal with its name indexed (entry 4).
fn request_headers(path: &str) -> Vec<u8> {
    let mut block = vec![0x83, 0x86, 0x04, path.len() as u8];
    block.extend(path.as_bytes());
    block
}

#[test]
fn the_configured_http2_settings_are_sent_and_rapid_resets_get_goaway() {
    let daemon = Daemon::start(&[
        ("RAYD_TRANSPORT_MAX_CONCURRENT_STREAMS", "7"),
        ("RAYD_TRANSPORT_MAX_FRAME_BYTES", "32768"),
        ("RAYD_TRANSPORT_STREAM_WINDOW_BYTES", "262144"),
        ("RAYD_TRANSPORT_MAX_HEADER_LIST_BYTES", "8192"),
        ("RAYD_TRANSPORT_MAX_PENDING_ACCEPT_RESET_STREAMS", "5"),
    ]);
    let (mut connection, settings) = raw_connection(&daemon);
    // SETTINGS_INITIAL_WINDOW_SIZE (4), SETTINGS_MAX_FRAME_SIZE (5), SETTINGS_MAX_CONCURRENT_STREAMS (3),
    // SETTINGS_MAX_HEADER_LIST_SIZE (6).
    for (id, value) in [(3, 7), (4, 262_144), (5, 32_768), (6, 8192)] {
        assert!(settings.contains(&(id, value)), "setting {id} = {value} in {settings:?}");
    }

    // Rapid reset: 50 requests, each reset at once, in one write.
    let mut burst = frame(SETTINGS, 1, 0, &[]);
    let headers = request_headers("/rayd.v1.Rayd/GetServerInfo");
    for stream in (1..100).step_by(2) {
        burst.extend(frame(HEADERS, 0x4, stream, &headers));
        burst.extend(frame(RST_STREAM, 0, stream, &8u32.to_be_bytes()));
    }
    // The server may close the connection while the burst is still being written.
    let _ = connection.write_all(&burst);
    let goaway = loop {
        match read_frame(&mut connection) {
            Ok((GOAWAY, _, payload)) => break Some(u32::from_be_bytes(payload[4..8].try_into().unwrap())),
            Ok(_) => continue,
            Err(_) => break None,
        }
    };
    assert_eq!(goaway, Some(ENHANCE_YOUR_CALM), "GOAWAY with ENHANCE_YOUR_CALM for the rapid resets");

    // Other connections are served.
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut rpc = RaydClient::connect(daemon.url()).await.unwrap();
        rpc.get_server_info(proto::GetServerInfoRequest {}).await.expect("another connection is served");
    });
}

/// The `Vm…` line `field` of `/proc/PID/status`, in bytes.
fn proc_status_bytes(pid: u32, field: &str) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with(field)).unwrap_or_else(|| panic!("no {field} line"));
    line.split_whitespace().nth(1).and_then(|v| v.parse::<u64>().ok()).expect("a size in kB") * 1024
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_unary_message_over_the_limit_is_refused_without_being_read_into_memory() {
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_MESSAGE_BYTES", &(16 << 20).to_string())]);
    let channel = Channel::from_shared(daemon.url()).unwrap().connect().await.unwrap();
    let mut rpc = RaydClient::new(channel).max_encoding_message_size(usize::MAX);
    rpc.get_server_info(proto::GetServerInfoRequest {}).await.unwrap();
    let peak_before = proc_status_bytes(daemon.pid(), "VmHWM:");
    let oversized = 256 << 20;
    let request = proto::TraceBatchRequest {
        query: Some(rayd_client::convert::trace_query(
            "absent",
            &Query::closest(RayFormat::OriginDirection, HitFormat::T),
        )),
        rays: Some(proto::trace_batch_request::Rays::RaysInline(Bytes::from(vec![0u8; oversized]))),
        ..Default::default()
    };
    let status = rpc.trace_batch(request).await.unwrap_err();
    assert_eq!(status.code(), Code::OutOfRange, "{status:?}");
    let grew = proc_status_bytes(daemon.pid(), "VmHWM:").saturating_sub(peak_before);
    assert!(grew < 32 << 20, "rayd's peak resident memory grew by {grew} bytes for a refused {oversized}-byte message");
    rpc.get_server_info(proto::GetServerInfoRequest {}).await.expect("still serving");
}

/// Streams `total_mib` MiB of rays (one chunk of camera rays on the bunny, sent again and again) through one
/// `TraceStream` and checks every chunk's answer against the engine's.
async fn big_stream(total_mib: u64) {
    let daemon = Daemon::start(&[]);
    let client = rayd_client::Client::connect(&daemon.url(), Default::default()).await.unwrap();
    client.build_mesh("bunny", &bunny().mesh, "", rayd_engine::accel::BuildFlags::empty()).await.unwrap();
    let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    // 1024 × 1024 rays of 24 bytes: 24 MiB a chunk.
    let chunk = Bytes::from(bunny().camera_rays(query.ray_format, 1024, 1024));
    let expected = bunny().trace(&query, &chunk);
    let chunks = (total_mib << 20).div_ceil(chunk.len() as u64);
    let first = proto::TraceStreamRequest {
        part: Some(proto::trace_stream_request::Part::Query(rayd_client::convert::trace_query("bunny", &query))),
    };
    let rays = (0..chunks)
        .map(move |_| proto::TraceStreamRequest { part: Some(proto::trace_stream_request::Part::Rays(chunk.clone())) });
    let mut rpc = RaydClient::connect(daemon.url()).await.unwrap().max_decoding_message_size(usize::MAX);
    let requests = tokio_stream::iter(std::iter::once(first).chain(rays));
    let mut answers = rpc.trace_stream(requests).await.unwrap().into_inner();
    let (mut answered, mut rays_traced) = (0u64, 0u64);
    let start = std::time::Instant::now();
    while let Some(answer) = answers.message().await.unwrap() {
        let stats = answer.stats.unwrap();
        assert_eq!(answer.first_ray, rays_traced, "chunk {answered} starts where the last ended");
        expected.assert_answer(
            &answer.hits,
            &answer.counts,
            (stats.rays, stats.rays_hit),
            &format!("chunk {answered}"),
        );
        rays_traced += stats.rays;
        answered += 1;
    }
    assert_eq!(answered, chunks, "every chunk answered");
    let seconds = start.elapsed().as_secs_f64();
    let bytes = chunks * (24 << 20);
    println!(
        "TraceStream: {chunks} chunks, {:.2} GiB of rays ({rays_traced} rays) in {seconds:.1} s: {:.0} MiB/s",
        bytes as f64 / (1u64 << 30) as f64,
        bytes as f64 / (1 << 20) as f64 / seconds
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trace_stream_carries_more_rays_than_any_message() {
    let mib = std::env::var("RAYD_BIG_STREAM_MIB").ok().and_then(|v| v.parse().ok()).unwrap_or(256);
    big_stream(mib).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "1.9 GiB of rays: run by hand (RELIABILITY.md)"]
async fn a_trace_stream_carries_1_9_gib_of_rays() {
    big_stream(1946).await;
}
