//! `rayd`, the ray-tracing service: the gRPC service over the engine, the admin endpoint, and their life cycle.
//!
//! [`run`] takes its listeners and its shutdown future from the caller, so tests bind port 0 and stop it
//! cleanly; `main.rs` only reads the configuration and signals.

mod access;
mod admin;
pub mod config;
mod convert;
mod error;
mod metrics;
mod persist;
mod registry;
mod schedule;
mod service;
mod streams;
mod tenant;

use std::future::Future;

use rayd_engine::Device;
use rayd_proto::rayd_server::RaydServer;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tonic::codec::CompressionEncoding;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::server::TcpIncoming;

pub use config::{Config, Limits};
pub use service::RaydService;

/// The devices rayd serves: the CPU, each ray taking at most `scheduler.cpu_ray_work` steps, then (with the `wgpu`
/// feature) every wgpu adapter, each trace on one holding at most `scheduler.gpu_trace_bytes` of buffers, each ray
/// taking at most `scheduler.gpu_ray_work` steps.
fn devices(scheduler: &config::SchedulerConfig) -> Vec<Device> {
    #[cfg(feature = "wgpu")]
    let gpus = Device::wgpu(rayd_engine::backend::wgpu::WgpuOptions {
        max_trace_bytes: Some(scheduler.gpu_trace_bytes),
        max_ray_work: Some(scheduler.gpu_ray_work),
        ..Default::default()
    });
    #[cfg(not(feature = "wgpu"))]
    let gpus = Vec::new();
    std::iter::once(Device::cpu_with_max_ray_work(scheduler.cpu_ray_work)).chain(gpus).collect()
}

/// Serves the gRPC service on `listener` and the admin endpoint on `admin` until `shutdown` completes; then the
/// health service reports NOT_SERVING, no new connection is accepted, and calls in flight finish before it
/// returns — or `shutdown_grace_seconds` pass, whichever comes first.
pub async fn run(
    config: Config,
    listener: TcpListener,
    admin: Option<TcpListener>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let metrics = metrics::install();
    rayd_engine::backend::cpu::large_pages::set_enabled(config.large_pages);
    let max_message = usize::try_from(config.limits.max_message_bytes).unwrap_or(usize::MAX);
    let service = RaydService::new(devices(&config.scheduler), &config)?;
    let tenants = service.tenants();
    // Compressed messages are accepted, and replies compressed for clients that ask (grpc-accept-encoding).
    let rayd = RaydServer::new(service)
        .max_decoding_message_size(max_message)
        .max_encoding_message_size(max_message)
        .accept_compressed(CompressionEncoding::Zstd)
        .accept_compressed(CompressionEncoding::Gzip)
        .send_compressed(CompressionEncoding::Zstd)
        .send_compressed(CompressionEncoding::Gzip);
    // Calls without a known key are refused before any of their messages is read.
    let rayd = InterceptedService::new(rayd, move |request| tenants.admit(request));
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<RaydServer<RaydService>>().await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(rayd_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;

    let (stop, stopped) = watch::channel(false);
    let wait_for_stop = move |mut receiver: watch::Receiver<bool>| async move {
        let _ = receiver.wait_for(|stop| *stop).await;
    };
    let admin_task =
        admin.map(|listener| tokio::spawn(admin::serve(listener, metrics, wait_for_stop(stopped.clone()))));
    let grpc_stop = wait_for_stop(stopped.clone());
    let grace = std::time::Duration::from_secs(config.shutdown_grace_seconds);
    let grace_over = async move {
        wait_for_stop(stopped).await;
        tokio::time::sleep(grace).await;
    };
    tokio::spawn(async move {
        shutdown.await;
        tracing::info!("shutting down: finishing calls in flight");
        health.set_not_serving::<RaydServer<RaydService>>().await;
        let _ = stop.send(true);
    });
    let mut builder = http2(tonic::transport::Server::builder(), &config.transport);
    if let Some(tls) = &config.tls {
        builder = builder.tls_config(server_tls(tls)?)?;
    }
    let server = builder
        .add_service(health_service)
        .add_service(reflection)
        .add_service(rayd)
        .serve_with_incoming_shutdown(TcpIncoming::from(listener).with_nodelay(Some(true)), grpc_stop);
    tokio::select! {
        served = server => served?,
        () = grace_over => tracing::warn!(seconds = grace.as_secs(), "grace period over: exiting with calls still open"),
    }
    if let Some(task) = admin_task {
        task.await??;
    }
    tracing::info!("stopped");
    Ok(())
}

/// `server` with the HTTP/2 limits of `transport`.
fn http2(server: tonic::transport::Server, transport: &config::TransportConfig) -> tonic::transport::Server {
    let keepalive = transport.keepalive_interval_seconds;
    server
        .max_concurrent_streams(transport.max_concurrent_streams)
        .http2_max_pending_accept_reset_streams(Some(transport.max_pending_accept_reset_streams as usize))
        .http2_max_local_error_reset_streams(Some(transport.max_local_error_reset_streams as usize))
        .http2_max_header_list_size(transport.max_header_list_bytes)
        .max_frame_size(transport.max_frame_bytes)
        .initial_stream_window_size(transport.stream_window_bytes)
        .initial_connection_window_size(transport.connection_window_bytes)
        .http2_keepalive_interval((keepalive > 0).then(|| std::time::Duration::from_secs(keepalive)))
        .http2_keepalive_timeout(Some(std::time::Duration::from_secs(transport.keepalive_timeout_seconds)))
}

/// The rustls configuration of `tls`: the server's identity and, for mutual TLS, the CAs of client certificates.
fn server_tls(
    tls: &config::TlsConfig,
) -> Result<tonic::transport::ServerTlsConfig, Box<dyn std::error::Error + Send + Sync>> {
    let read = |path: &std::path::Path, what: &str| {
        std::fs::read(path).map_err(|e| format!("tls.{what} {}: {e}", path.display()))
    };
    let identity = tonic::transport::Identity::from_pem(read(&tls.cert, "cert")?, read(&tls.key, "key")?);
    let mut server = tonic::transport::ServerTlsConfig::new().identity(identity);
    if let Some(ca) = &tls.client_ca {
        server = server.client_ca_root(tonic::transport::Certificate::from_pem(read(ca, "client_ca")?));
    }
    Ok(server)
}
