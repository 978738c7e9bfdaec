//! The connection to a rayd server and its simple calls (devices, accels, buffers). Uploads, builds and traces
//! live in their own modules as further `impl Client` blocks.

use rayd_proto as proto;
use rayd_proto::rayd_client::RaydClient;
use tonic::codec::CompressionEncoding;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::channel::Change;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

use crate::auth::Auth;
use crate::convert::{accel_ref, buffer_ref};
use crate::error::{Error, Result, chain};
use crate::upload::CleanUps;

/// The server URL used when none is given.
pub const DEFAULT_SERVER: &str = "http://127.0.0.1:50051";

/// 1 MiB.
const MIB: usize = 1 << 20;

/// How a [`Client`] talks to the server. `Default` matches the server's defaults.
#[derive(Debug, Clone)]
pub struct ClientOptions {
    /// Sent as `authorization: Bearer <token>` with every call, when set.
    pub token: Option<String>,
    /// Largest message sent or received; the server's default `max_message_bytes` is 64 MiB.
    pub max_message_bytes: usize,
    /// A trace goes through one `TraceBatch` call when its rays and its hits each fit in this many bytes, and
    /// through `TraceStream` otherwise.
    pub batch_limit_bytes: usize,
    /// Ray bytes per `TraceStream` chunk (rounded down to whole rays, a multiple of 8).
    pub stream_chunk_bytes: usize,
    /// `TraceStream` chunks sent and not yet answered, at most (keeps memory bounded on both sides).
    pub stream_window: usize,
    /// Rays in one `TraceBatch` call or one `TraceStream` chunk, at most (the server's `max_rays_per_batch`).
    pub max_rays_per_call: usize,
    /// Meshes whose packed vertices and indices together are smaller than this go inline in `BuildAccel`;
    /// larger ones are uploaded as buffers first.
    pub inline_mesh_bytes: usize,
    /// Bytes per `UploadBuffer` data message (and per upload message of a stream).
    pub upload_chunk_bytes: usize,
    /// Bytes of a [`Stream`](crate::Stream)'s operations sent and not yet answered, at most: enqueueing waits
    /// beyond it (an operation larger than this waits until it is alone in flight).
    pub stream_bytes_in_flight: usize,
    /// TLS for `https://` servers: the CA to trust (else the platform's are not used: give one) and, for mutual
    /// TLS, the client's certificate and key. Refused (INVALID_ARGUMENT) for a server URL of another scheme.
    pub tls: Option<ClientTls>,
    /// Compress the messages sent, and ask the server to compress its replies, with this encoding (rayd accepts
    /// and sends zstd and gzip). Worth it on slow links; on loopback it costs more CPU than it saves.
    pub compression: Option<CompressionEncoding>,
    /// HTTP/2 connections the calls are spread over, at least 1: each call goes to the less busy of two of them
    /// picked at random. One serves most callers; one with several large replies in flight at once (images, hit
    /// buffers) has their bytes copied on as many cores at once with as many connections (a connection's bytes go
    /// through one task at each end).
    pub connections: usize,
}

/// The PEM files of a TLS connection.
#[derive(Debug, Clone, Default)]
pub struct ClientTls {
    /// The CA certificate(s) that signed the server's certificate, PEM.
    pub ca_cert: Option<Vec<u8>>,
    /// The client's certificate chain and private key, PEM, for servers that require one.
    pub identity: Option<(Vec<u8>, Vec<u8>)>,
}

impl ClientTls {
    /// tonic's configuration of it.
    fn config(&self) -> ClientTlsConfig {
        let mut config = ClientTlsConfig::new();
        if let Some(ca) = &self.ca_cert {
            config = config.ca_certificate(Certificate::from_pem(ca));
        }
        if let Some((cert, key)) = &self.identity {
            config = config.identity(Identity::from_pem(cert, key));
        }
        config
    }
}

impl Default for ClientOptions {
    fn default() -> Self {
        ClientOptions {
            token: None,
            max_message_bytes: 64 * MIB,
            batch_limit_bytes: 32 * MIB,
            stream_chunk_bytes: 4 * MIB,
            stream_window: 4,
            max_rays_per_call: 1 << 24,
            inline_mesh_bytes: 8 * MIB,
            upload_chunk_bytes: MIB,
            stream_bytes_in_flight: 64 * MIB,
            tls: None,
            compression: None,
            connections: 1,
        }
    }
}

impl ClientOptions {
    /// Lowers every option that the server's limits bound.
    fn fit_to(&mut self, limits: &proto::Limits) {
        let server = |value: u64| usize::try_from(value).unwrap_or(usize::MAX);
        self.max_message_bytes = self.max_message_bytes.min(server(limits.max_message_bytes));
        // Half a message: room for the request's other fields (an over-limit request fails as an opaque h2 reset).
        let half_message = self.max_message_bytes / 2;
        self.batch_limit_bytes = self.batch_limit_bytes.min(half_message);
        self.inline_mesh_bytes = self.inline_mesh_bytes.min(half_message);
        self.upload_chunk_bytes = self.upload_chunk_bytes.min(half_message).max(1);
        self.max_rays_per_call = self.max_rays_per_call.min(server(limits.max_rays_per_batch)).max(1);
        self.stream_window = self.stream_window.min(limits.stream_window as usize).max(1);
    }
}

/// The generated stub, with the token interceptor.
pub(crate) type RpcClient = RaydClient<InterceptedService<Channel, Auth>>;

/// A connection to one rayd server (over [`ClientOptions::connections`] HTTP/2 connections). Cheap to clone; clones
/// share the connections and may be used concurrently.
#[derive(Debug, Clone)]
pub struct Client {
    /// The generated stub, with the token interceptor and the message limits applied.
    pub(crate) rpc: RpcClient,
    /// The connection under `rpc`, for stubs that carry a scene's routing header.
    channel: Channel,
    /// The interceptor of `rpc` (token, and the scene of [`Client::for_scene`]), for making routed ones.
    auth: Auth,
    /// Thresholds that pick between call shapes (inline or buffer, batch or stream).
    pub(crate) options: ClientOptions,
    /// Deletes of temporary buffers left running by calls dropped midway, shared by the clones.
    pub(crate) clean_ups: CleanUps,
}

impl Client {
    /// Connects to `url` (e.g. [`DEFAULT_SERVER`]) now, so that an unreachable server is reported here, and
    /// lowers the options' message size, rays per call and stream window to the server's limits.
    pub async fn connect(url: &str, mut options: ClientOptions) -> Result<Client> {
        let auth = Auth::new(options.token.as_deref())?;
        let endpoint = endpoint(url, options.tls.as_ref())?;
        let first = connect_channel(endpoint.clone(), url).await?;
        let mut rpc = RaydClient::with_interceptor(first.clone(), auth.clone());
        let info = rpc.get_server_info(proto::GetServerInfoRequest {}).await?.into_inner();
        if let Some(limits) = info.limits {
            options.fit_to(&limits);
        }
        let channel = match options.connections {
            0 | 1 => first,
            connections => spread(&endpoint, connections),
        };
        let rpc = stub(&channel, auth.clone(), &options);
        Ok(Client { rpc, channel, auth, options, clean_ups: CleanUps::default() })
    }

    /// This client with every call — buffers, streams and listings included — sent for accel `accel`'s scene (its
    /// name up to the first `.`): behind a proxy that hashes [`ROUTE_HEADER`](crate::ROUTE_HEADER), they all reach
    /// the node that holds the scene. Calls that name an accel always carry that accel's scene by themselves; this
    /// is for the others, e.g. uploading a buffer that a build of the scene will use, or opening a stream for it.
    pub fn for_scene(&self, accel: &str) -> Client {
        let auth = self.auth.routed(accel);
        Client {
            rpc: stub(&self.channel, auth.clone(), &self.options),
            channel: self.channel.clone(),
            auth,
            ..self.clone()
        }
    }

    /// A stub whose calls carry accel `accel`'s routing header.
    pub(crate) fn rpc_for(&self, accel: &str) -> RpcClient {
        stub(&self.channel, self.auth.routed(accel), &self.options)
    }

    /// The options this client was made with.
    pub fn options(&self) -> &ClientOptions {
        &self.options
    }

    /// Every tenant's usage against its quotas (needs an admin key where tenants are configured).
    pub async fn tenants(&self) -> Result<Vec<proto::TenantInfo>> {
        Ok(self.rpc.clone().list_tenants(proto::ListTenantsRequest {}).await?.into_inner().tenants)
    }

    /// The server's version and the limits it holds requests to.
    pub async fn server_info(&self) -> Result<proto::ServerInfo> {
        Ok(self.rpc.clone().get_server_info(proto::GetServerInfoRequest {}).await?.into_inner())
    }

    /// Every device of the server, `cpu:0` first.
    pub async fn devices(&self) -> Result<Vec<proto::Device>> {
        Ok(self.rpc.clone().list_devices(proto::ListDevicesRequest {}).await?.into_inner().devices)
    }

    /// The accel called `name`.
    pub async fn accel(&self, name: &str) -> Result<proto::AccelInfo> {
        let request = proto::GetAccelRequest { accel: Some(accel_ref(name)) };
        Ok(self.rpc_for(name).get_accel(request).await?.into_inner())
    }

    /// Every accel of this tenant, in creation order.
    pub async fn accels(&self) -> Result<Vec<proto::AccelInfo>> {
        Ok(self.rpc.clone().list_accels(proto::ListAccelsRequest {}).await?.into_inner().accels)
    }

    /// Copies the accel called `source` to a new accel `name` on `device` (empty: the source's); with `compact`, a
    /// compacted copy (the source must allow compaction). The copy is made on the source's node: behind a router,
    /// give it a name of the same scene (`farm.copy`), else calls naming it are sent to another node.
    pub async fn copy_accel(&self, source: &str, name: &str, device: &str, compact: bool) -> Result<proto::AccelInfo> {
        let request = copy_request(accel_ref(source), name, device, compact);
        Ok(self.rpc_for(source).copy_accel(request).await?.into_inner())
    }

    /// Destroys the accel called `name` (traces already running on it finish first).
    pub async fn destroy_accel(&self, name: &str) -> Result<()> {
        let request = proto::DestroyAccelRequest { accel: Some(accel_ref(name)) };
        self.rpc_for(name).destroy_accel(request).await?;
        Ok(())
    }

    /// Every buffer of this tenant.
    pub async fn buffers(&self) -> Result<Vec<proto::BufferInfo>> {
        Ok(self.rpc.clone().list_buffers(proto::ListBuffersRequest {}).await?.into_inner().buffers)
    }

    /// Deletes the buffer with server-given id `id`.
    pub async fn delete_buffer(&self, id: &str) -> Result<()> {
        let request = proto::DeleteBufferRequest { buffer: Some(buffer_ref(id)) };
        self.rpc.clone().delete_buffer(request).await?;
        Ok(())
    }
}

/// HTTP/2 flow-control window of each call's reply: bytes the server may send before the client has read them. Large
/// replies (images, hit buffers of millions of rays) then flow without waiting for window updates.
const REPLY_WINDOW_BYTES: u32 = 8 << 20;
/// Largest HTTP/2 frame the client accepts: fewer, larger frames for large replies.
const REPLY_FRAME_BYTES: u32 = 1 << 20;

/// The endpoint of `url`, with `tls` when given (only for an `https://` URL: over plain HTTP it would be ignored).
pub(crate) fn endpoint(url: &str, tls: Option<&ClientTls>) -> Result<Endpoint> {
    let endpoint = Endpoint::from_shared(url.to_owned())
        .map_err(|e| Error::InvalidArgument(format!("server URL {url:?}: {}", chain(&e))))?
        .initial_stream_window_size(REPLY_WINDOW_BYTES)
        .initial_connection_window_size(2 * REPLY_WINDOW_BYTES)
        .max_frame_size(REPLY_FRAME_BYTES);
    match tls {
        Some(_) if endpoint.uri().scheme_str() != Some("https") => Err(Error::InvalidArgument(format!(
            "server URL {url:?}: TLS options (a CA certificate, a client certificate and key) need an https:// URL"
        ))),
        // A certificate or key that cannot be used is the caller's to fix, not the server's to answer.
        Some(tls) => endpoint
            .tls_config(tls.config())
            .map_err(|e| Error::InvalidArgument(format!("TLS options for {url:?}: {}", chain(&e)))),
        None => Ok(endpoint),
    }
}

/// Connects to `endpoint` now (the server at `url`).
pub(crate) async fn connect_channel(endpoint: Endpoint, url: &str) -> Result<Channel> {
    let connected = endpoint.tcp_nodelay(true).connect().await;
    connected.map_err(|e| Error::Connect { url: url.to_owned(), reason: chain(&e) })
}

/// A channel over `connections` connections to `endpoint` (made as calls need them), each call sent on the less
/// busy of two picked at random (tower's power-of-two-choices balancer).
fn spread(endpoint: &Endpoint, connections: usize) -> Channel {
    let (channel, changes) = Channel::balance_channel(connections);
    for key in 0..connections {
        // The change queue holds `connections` changes: each one fits.
        let inserted = changes.try_send(Change::Insert(key, endpoint.clone().tcp_nodelay(true)));
        inserted.expect("room in the change queue for every connection");
    }
    channel
}

/// The generated stub over `channel` with interceptor `auth` and `options`' message limits.
fn stub(channel: &Channel, auth: Auth, options: &ClientOptions) -> RpcClient {
    let stub = RaydClient::with_interceptor(channel.clone(), auth)
        .max_decoding_message_size(options.max_message_bytes)
        .max_encoding_message_size(options.max_message_bytes);
    match options.compression {
        Some(encoding) => stub.send_compressed(encoding).accept_compressed(encoding),
        None => stub,
    }
}

/// A `CopyAccel` request.
pub(crate) fn copy_request(
    source: proto::AccelRef,
    name: &str,
    device: &str,
    compact: bool,
) -> proto::CopyAccelRequest {
    proto::CopyAccelRequest { accel: Some(source), name: name.to_owned(), device: device.to_owned(), compact }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tls_options_are_refused_for_a_server_url_that_is_not_https() {
        let tls = ClientTls { ca_cert: Some(b"PEM".to_vec()), identity: None };
        let error = endpoint("http://127.0.0.1:50051", Some(&tls)).expect_err("TLS over plain HTTP");
        assert_eq!(error.code(), tonic::Code::InvalidArgument);
        assert!(error.to_string().contains("https://"), "{error}");
        assert!(endpoint("http://127.0.0.1:50051", None).is_ok(), "plain HTTP without TLS options");
        assert!(endpoint("https://127.0.0.1:50051", Some(&ClientTls::default())).is_ok(), "TLS over https://");
    }
}
