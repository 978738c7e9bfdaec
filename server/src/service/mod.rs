//! The gRPC handlers. Each one validates and converts its request, calls the tenant's logic (off the async
//! runtime when it is heavy), and converts the result; errors become statuses in [`crate::error`].

mod accels;
mod buffers;
mod inputs;
mod stream;
mod trace;

use std::sync::Arc;

use rayd_engine::Device;
use rayd_proto as pb;
use rayd_proto::rayd_server::Rayd;
use tonic::{Request, Response, Status, Streaming};

use crate::convert;
use crate::error::{ServiceError, ServiceResult};
use crate::metrics::observe;
use crate::persist::Store;
use crate::tenant::Tenant;

/// Shared state of every call.
#[derive(Debug)]
pub struct RaydService {
    /// The devices of this server.
    devices: Vec<Device>,
    /// The single tenant of a server without tenant configuration.
    tenant: Arc<Tenant>,
}

impl RaydService {
    /// A service over `devices` with one default tenant held to `limits`; with a `store`, the tenant's objects
    /// are restored from it (what cannot be restored is logged and skipped) and persisted in it from now on.
    pub fn new(
        devices: Vec<Device>,
        limits: crate::config::Limits,
        store: Option<Store>,
    ) -> Result<RaydService, ServiceError> {
        let mut tenant = Tenant::new(limits, &devices);
        if let Some(store) = store {
            tenant = tenant.with_store(store);
            let start = std::time::Instant::now();
            let restored = tenant.restore()?;
            for (object, why) in &restored.skipped {
                tracing::warn!(%object, %why, "not restored");
            }
            tracing::info!(
                buffers = restored.buffers,
                accels = restored.accels,
                stale = restored.stale,
                skipped = restored.skipped.len(),
                ms = start.elapsed().as_millis() as u64,
                "restored the data directory"
            );
        }
        Ok(RaydService { devices, tenant: Arc::new(tenant) })
    }

    /// The tenant a request acts for.
    fn tenant<T>(&self, _request: &Request<T>) -> Arc<Tenant> {
        Arc::clone(&self.tenant)
    }
}

/// Runs blocking work (builds, traces) on tokio's blocking pool so the async runtime keeps serving.
async fn blocking<T: Send + 'static>(work: impl FnOnce() -> ServiceResult<T> + Send + 'static) -> ServiceResult<T> {
    tokio::task::spawn_blocking(work).await.expect("blocking work does not panic")
}

/// The error for a reference to a stream operation made outside any stream.
fn operation_outside_stream(field: &str) -> ServiceError {
    ServiceError::invalid(field, "names a stream operation, which only an operation of the same stream may do")
}

#[tonic::async_trait]
impl Rayd for RaydService {
    async fn get_server_info(
        &self,
        request: Request<pb::GetServerInfoRequest>,
    ) -> Result<Response<pb::ServerInfo>, Status> {
        let tenant = self.tenant(&request);
        observe("GetServerInfo", async {
            Ok(pb::ServerInfo {
                version: env!("CARGO_PKG_VERSION").into(),
                limits: Some(convert::limits(tenant.limits())),
                usage: Some(convert::usage(&tenant.usage())),
            })
        })
        .await
    }

    async fn list_devices(
        &self,
        _: Request<pb::ListDevicesRequest>,
    ) -> Result<Response<pb::ListDevicesResponse>, Status> {
        observe("ListDevices", async {
            let devices = self.devices.iter().map(|d| convert::device(d.info())).collect();
            Ok(pb::ListDevicesResponse { devices })
        })
        .await
    }

    async fn upload_buffer(
        &self,
        request: Request<Streaming<pb::UploadBufferRequest>>,
    ) -> Result<Response<pb::BufferInfo>, Status> {
        let tenant = self.tenant(&request);
        observe("UploadBuffer", buffers::upload(tenant, request.into_inner())).await
    }

    type DownloadBufferStream = buffers::ChunkStream;

    async fn download_buffer(
        &self,
        request: Request<pb::DownloadBufferRequest>,
    ) -> Result<Response<Self::DownloadBufferStream>, Status> {
        let tenant = self.tenant(&request);
        observe("DownloadBuffer", async { buffers::download(&tenant, request.get_ref()) }).await
    }

    async fn delete_buffer(
        &self,
        request: Request<pb::DeleteBufferRequest>,
    ) -> Result<Response<pb::DeleteBufferResponse>, Status> {
        let tenant = self.tenant(&request);
        observe("DeleteBuffer", async {
            buffers::delete(&tenant, request.get_ref())?;
            Ok(pb::DeleteBufferResponse {})
        })
        .await
    }

    async fn list_buffers(
        &self,
        request: Request<pb::ListBuffersRequest>,
    ) -> Result<Response<pb::ListBuffersResponse>, Status> {
        let tenant = self.tenant(&request);
        observe("ListBuffers", async {
            Ok(pb::ListBuffersResponse { buffers: tenant.buffers().iter().map(buffers::info).collect() })
        })
        .await
    }

    async fn compute_memory_usage(
        &self,
        request: Request<pb::ComputeMemoryUsageRequest>,
    ) -> Result<Response<pb::MemoryUsage>, Status> {
        let tenant = self.tenant(&request);
        observe("ComputeMemoryUsage", async {
            let request = request.into_inner();
            let resolved = inputs::resolve(&tenant, &request.device, &request.inputs)?;
            let options = inputs::options(&tenant, request.options.as_ref())?;
            let (_, context) = tenant.context(&request.device)?;
            Ok(convert::memory_usage(&resolved.memory_usage(context, &options)?))
        })
        .await
    }

    async fn build_accel(&self, request: Request<pb::BuildAccelRequest>) -> Result<Response<pb::AccelInfo>, Status> {
        let tenant = self.tenant(&request);
        observe("BuildAccel", accels::build(tenant, request.into_inner())).await
    }

    async fn update_accel(&self, request: Request<pb::UpdateAccelRequest>) -> Result<Response<pb::AccelInfo>, Status> {
        let tenant = self.tenant(&request);
        observe("UpdateAccel", accels::update(tenant, request.into_inner())).await
    }

    async fn copy_accel(&self, request: Request<pb::CopyAccelRequest>) -> Result<Response<pb::AccelInfo>, Status> {
        let tenant = self.tenant(&request);
        observe("CopyAccel", accels::copy(tenant, request.into_inner())).await
    }

    async fn get_accel(&self, request: Request<pb::GetAccelRequest>) -> Result<Response<pb::AccelInfo>, Status> {
        let tenant = self.tenant(&request);
        observe("GetAccel", async {
            Ok(accels::info(&accels::resolve(&tenant, request.get_ref().accel.as_ref(), "accel")?))
        })
        .await
    }

    async fn list_accels(
        &self,
        request: Request<pb::ListAccelsRequest>,
    ) -> Result<Response<pb::ListAccelsResponse>, Status> {
        let tenant = self.tenant(&request);
        observe("ListAccels", async {
            Ok(pb::ListAccelsResponse { accels: tenant.accels().iter().map(accels::info).collect() })
        })
        .await
    }

    async fn destroy_accel(
        &self,
        request: Request<pb::DestroyAccelRequest>,
    ) -> Result<Response<pb::DestroyAccelResponse>, Status> {
        let tenant = self.tenant(&request);
        observe("DestroyAccel", async {
            accels::destroy(&tenant, request.get_ref())?;
            Ok(pb::DestroyAccelResponse {})
        })
        .await
    }

    async fn save_accel(&self, request: Request<pb::SaveAccelRequest>) -> Result<Response<pb::BufferInfo>, Status> {
        let tenant = self.tenant(&request);
        observe("SaveAccel", accels::save(tenant, request.into_inner())).await
    }

    async fn load_accel(
        &self,
        request: Request<pb::LoadAccelRequest>,
    ) -> Result<Response<pb::LoadAccelResponse>, Status> {
        let tenant = self.tenant(&request);
        observe("LoadAccel", accels::load(tenant, request.into_inner())).await
    }

    async fn trace_batch(
        &self,
        request: Request<pb::TraceBatchRequest>,
    ) -> Result<Response<pb::TraceBatchResponse>, Status> {
        let tenant = self.tenant(&request);
        observe("TraceBatch", trace::batch(tenant, request.into_inner())).await
    }

    type TraceStreamStream = trace::ResponseStream;

    async fn trace_stream(
        &self,
        request: Request<Streaming<pb::TraceStreamRequest>>,
    ) -> Result<Response<Self::TraceStreamStream>, Status> {
        let tenant = self.tenant(&request);
        observe("TraceStream", trace::stream(tenant, request.into_inner())).await
    }

    type OpenStreamStream = stream::ResponseStream;

    async fn open_stream(
        &self,
        request: Request<Streaming<pb::StreamRequest>>,
    ) -> Result<Response<Self::OpenStreamStream>, Status> {
        let tenant = self.tenant(&request);
        observe("OpenStream", async { stream::open(tenant, request.into_inner()) }).await
    }

    async fn cancel_stream(
        &self,
        request: Request<pb::CancelStreamRequest>,
    ) -> Result<Response<pb::CancelStreamResponse>, Status> {
        let tenant = self.tenant(&request);
        observe("CancelStream", async {
            tenant.streams().cancel(request.get_ref().stream_id)?;
            Ok(pb::CancelStreamResponse {})
        })
        .await
    }
}
