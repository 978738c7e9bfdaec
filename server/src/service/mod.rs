//! The gRPC handlers. Each one validates and converts its request, calls the tenant's logic (off the async
//! runtime when it is heavy), and converts the result; errors become statuses in [`crate::error`].

mod accels;
mod buffers;
mod inputs;
mod outbox;
mod stream;
mod trace;

use std::sync::Arc;

use rayd_engine::Device;
use rayd_proto as pb;
use rayd_proto::rayd_server::Rayd;
use tonic::{Request, Response, Status, Streaming};

use crate::access::Tenants;
use crate::config::{Config, Limits, Role};
use crate::convert;
use crate::error::{ServiceError, ServiceResult};
use crate::metrics::observe;
use crate::persist::{DataDirLock, Store};
use crate::schedule::Schedulers;
use crate::tenant::{Caller, Tenant};

/// Shared state of every call.
#[derive(Debug)]
pub struct RaydService {
    /// The devices of this server.
    devices: Vec<Device>,
    /// The tenants, and how a call reaches its own.
    tenants: Arc<Tenants>,
    /// The data directory's lock, held while the service lives.
    _data_dir: Option<DataDirLock>,
}

impl RaydService {
    /// A service over `devices` with the configured tenants (or one default tenant without authentication), each
    /// held to its limits; with a data directory, each tenant's objects are restored from its directory (what
    /// cannot be restored is logged and skipped) and persisted there from now on.
    pub fn new(devices: Vec<Device>, config: &Config) -> Result<RaydService, ServiceError> {
        let data_dir = config.data_dir.as_deref().map(lock_data_dir).transpose()?;
        let schedulers = Arc::new(Schedulers::new(&devices, &config.scheduler));
        let make = |name: &str, limits: Limits, share: u32| -> Result<Arc<Tenant>, ServiceError> {
            let mut tenant = Tenant::new(name, limits, share, &devices, Arc::clone(&schedulers));
            if let Some(dir) = &config.data_dir {
                let store = Store::open(dir, name)
                    .map_err(|e| ServiceError::storage(format!("opening tenant {name:?}'s directory"), e))?;
                tenant = tenant.with_store(store);
                restore_logged(name, &tenant)?;
            }
            Ok(Arc::new(tenant))
        };
        let tenants = if config.tenants.is_empty() {
            Tenants::open(make("default", config.limits, 1)?)
        } else {
            let mut keys = Vec::new();
            for configured in &config.tenants {
                let tenant = make(&configured.name, configured.limits, configured.share)?;
                keys.extend(configured.keys.iter().map(|k| (k.key.clone(), k.role, Arc::clone(&tenant))));
            }
            Tenants::with_keys(keys)
        };
        let tenants = Arc::new(tenants);
        Ok(RaydService { devices, tenants, _data_dir: data_dir })
    }

    /// The tenants, and how a call reaches its own ([`Tenants::admit`] runs ahead of the service).
    pub fn tenants(&self) -> Arc<Tenants> {
        Arc::clone(&self.tenants)
    }

    /// The tenant a request acts for, if its key may make `call`, which needs `needs`.
    fn caller<T>(&self, request: &Request<T>, call: &str, needs: Role) -> Result<Arc<Tenant>, Status> {
        self.tenants.caller(request, call, needs)
    }
}

/// Takes the lock of the data directory `dir` (made if needed); FAILED_PRECONDITION if another process holds it.
fn lock_data_dir(dir: &std::path::Path) -> Result<DataDirLock, ServiceError> {
    DataDirLock::take(dir).map_err(|e| match e.kind() {
        std::io::ErrorKind::WouldBlock => ServiceError::Precondition(format!(
            "data directory {}: another process holds its lock ({}): one rayd a data directory",
            dir.display(),
            dir.join("lock").display()
        )),
        _ => ServiceError::storage(format!("locking data directory {}", dir.display()), e),
    })
}

/// Restores `tenant`'s objects, logging what was restored and what was skipped (and why).
fn restore_logged(name: &str, tenant: &Tenant) -> Result<(), ServiceError> {
    let start = std::time::Instant::now();
    let restored = tenant.restore()?;
    for (object, why) in &restored.skipped {
        tracing::warn!(tenant = name, %object, %why, "not restored");
    }
    tracing::info!(
        tenant = name,
        buffers = restored.buffers,
        accels = restored.accels,
        stale = restored.stale,
        skipped = restored.skipped.len(),
        ms = start.elapsed().as_millis() as u64,
        "restored the data directory"
    );
    Ok(())
}

/// Runs blocking work (builds, loads, writes to the data directory) on tokio's blocking pool so the async runtime keeps
/// serving. A panic in it (a bug, here or in a backend) fails the call with INTERNAL, as a trace's piece does.
async fn blocking<T: Send + 'static>(work: impl FnOnce() -> ServiceResult<T> + Send + 'static) -> ServiceResult<T> {
    tokio::task::spawn_blocking(work).await.unwrap_or_else(|failed| Err(ServiceError::Internal(failed.to_string())))
}

/// How a streaming call's request reader ended, asked once its messages have ended: a reader that panicked (a bug)
/// let its queue go as one that read the client's last message does, and the call must not then end OK.
async fn reader_ended(reader: tokio::task::JoinHandle<()>) -> Result<(), Status> {
    match reader.await {
        Err(failed) if failed.is_panic() => {
            Err(Status::internal("the task reading this call's requests panicked (a bug): no requests follow"))
        }
        _ => Ok(()),
    }
}

/// Runs `work` off the async runtime for a caller that goes when this future is dropped ([`Caller`]): what `work`
/// makes is then not kept.
async fn blocking_for_caller<T: Send + 'static>(
    work: impl FnOnce(&Caller) -> ServiceResult<T> + Send + 'static,
) -> ServiceResult<T> {
    let (caller, _present) = Caller::watched();
    blocking(move || work(&caller)).await
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
        let tenant = self.caller(&request, "GetServerInfo", Role::Read)?;
        observe("GetServerInfo", tenant.name().to_owned(), async {
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
        request: Request<pb::ListDevicesRequest>,
    ) -> Result<Response<pb::ListDevicesResponse>, Status> {
        let tenant = self.caller(&request, "ListDevices", Role::Read)?;
        observe("ListDevices", tenant.name().to_owned(), async {
            let devices = self.devices.iter().map(|d| convert::device(d.info())).collect();
            Ok(pb::ListDevicesResponse { devices })
        })
        .await
    }

    async fn list_tenants(
        &self,
        request: Request<pb::ListTenantsRequest>,
    ) -> Result<Response<pb::ListTenantsResponse>, Status> {
        let tenant = self.caller(&request, "ListTenants", Role::Admin)?;
        observe("ListTenants", tenant.name().to_owned(), async {
            let tenants = self
                .tenants
                .all()
                .iter()
                .map(|tenant| pb::TenantInfo {
                    name: tenant.name().into(),
                    usage: Some(convert::usage(&tenant.usage())),
                    limits: Some(convert::limits(tenant.limits())),
                    share: tenant.share(),
                })
                .collect();
            Ok(pb::ListTenantsResponse { tenants })
        })
        .await
    }

    async fn upload_buffer(
        &self,
        request: Request<Streaming<pb::UploadBufferRequest>>,
    ) -> Result<Response<pb::BufferInfo>, Status> {
        let tenant = self.caller(&request, "UploadBuffer", Role::Write)?;
        observe("UploadBuffer", tenant.name().to_owned(), buffers::upload(tenant, request.into_inner())).await
    }

    type DownloadBufferStream = buffers::ChunkStream;

    async fn download_buffer(
        &self,
        request: Request<pb::DownloadBufferRequest>,
    ) -> Result<Response<Self::DownloadBufferStream>, Status> {
        let tenant = self.caller(&request, "DownloadBuffer", Role::Read)?;
        observe("DownloadBuffer", tenant.name().to_owned(), async { buffers::download(&tenant, request.get_ref()) })
            .await
    }

    async fn delete_buffer(
        &self,
        request: Request<pb::DeleteBufferRequest>,
    ) -> Result<Response<pb::DeleteBufferResponse>, Status> {
        let tenant = self.caller(&request, "DeleteBuffer", Role::Write)?;
        observe("DeleteBuffer", tenant.name().to_owned(), async {
            buffers::delete(Arc::clone(&tenant), request.into_inner()).await?;
            Ok(pb::DeleteBufferResponse {})
        })
        .await
    }

    async fn list_buffers(
        &self,
        request: Request<pb::ListBuffersRequest>,
    ) -> Result<Response<pb::ListBuffersResponse>, Status> {
        let tenant = self.caller(&request, "ListBuffers", Role::Read)?;
        observe("ListBuffers", tenant.name().to_owned(), async {
            Ok(pb::ListBuffersResponse { buffers: tenant.buffers().iter().map(buffers::info).collect() })
        })
        .await
    }

    async fn compute_memory_usage(
        &self,
        request: Request<pb::ComputeMemoryUsageRequest>,
    ) -> Result<Response<pb::MemoryUsage>, Status> {
        let tenant = self.caller(&request, "ComputeMemoryUsage", Role::Read)?;
        // Off the async runtime: resolving the inputs reads their bytes (up to whole buffers) and checks them.
        let name = tenant.name().to_owned();
        observe(
            "ComputeMemoryUsage",
            name,
            blocking(move || {
                let request = request.into_inner();
                let resolved = inputs::resolve(&tenant, &request.device, &request.inputs)?;
                let options = inputs::options(&tenant, &resolved, request.options.as_ref())?;
                let (_, context) = tenant.context(&request.device)?;
                Ok(convert::memory_usage(&resolved.memory_usage(context, &options)?))
            }),
        )
        .await
    }

    async fn build_accel(&self, request: Request<pb::BuildAccelRequest>) -> Result<Response<pb::AccelInfo>, Status> {
        let tenant = self.caller(&request, "BuildAccel", Role::Write)?;
        observe("BuildAccel", tenant.name().to_owned(), accels::build(tenant, request.into_inner())).await
    }

    async fn update_accel(&self, request: Request<pb::UpdateAccelRequest>) -> Result<Response<pb::AccelInfo>, Status> {
        let tenant = self.caller(&request, "UpdateAccel", Role::Write)?;
        observe("UpdateAccel", tenant.name().to_owned(), accels::update(tenant, request.into_inner())).await
    }

    async fn copy_accel(&self, request: Request<pb::CopyAccelRequest>) -> Result<Response<pb::AccelInfo>, Status> {
        let tenant = self.caller(&request, "CopyAccel", Role::Write)?;
        observe("CopyAccel", tenant.name().to_owned(), accels::copy(tenant, request.into_inner())).await
    }

    async fn get_accel(&self, request: Request<pb::GetAccelRequest>) -> Result<Response<pb::AccelInfo>, Status> {
        let tenant = self.caller(&request, "GetAccel", Role::Read)?;
        observe("GetAccel", tenant.name().to_owned(), async {
            Ok(accels::info(&accels::resolve(&tenant, request.get_ref().accel.as_ref(), "accel")?))
        })
        .await
    }

    async fn list_accels(
        &self,
        request: Request<pb::ListAccelsRequest>,
    ) -> Result<Response<pb::ListAccelsResponse>, Status> {
        let tenant = self.caller(&request, "ListAccels", Role::Read)?;
        observe("ListAccels", tenant.name().to_owned(), async {
            Ok(pb::ListAccelsResponse { accels: tenant.accels().iter().map(accels::info).collect() })
        })
        .await
    }

    async fn destroy_accel(
        &self,
        request: Request<pb::DestroyAccelRequest>,
    ) -> Result<Response<pb::DestroyAccelResponse>, Status> {
        let tenant = self.caller(&request, "DestroyAccel", Role::Write)?;
        observe("DestroyAccel", tenant.name().to_owned(), async {
            accels::destroy(Arc::clone(&tenant), request.into_inner()).await?;
            Ok(pb::DestroyAccelResponse {})
        })
        .await
    }

    async fn save_accel(&self, request: Request<pb::SaveAccelRequest>) -> Result<Response<pb::BufferInfo>, Status> {
        let tenant = self.caller(&request, "SaveAccel", Role::Write)?;
        observe("SaveAccel", tenant.name().to_owned(), accels::save(tenant, request.into_inner())).await
    }

    async fn load_accel(
        &self,
        request: Request<pb::LoadAccelRequest>,
    ) -> Result<Response<pb::LoadAccelResponse>, Status> {
        let tenant = self.caller(&request, "LoadAccel", Role::Write)?;
        observe("LoadAccel", tenant.name().to_owned(), accels::load(tenant, request.into_inner())).await
    }

    async fn trace_batch(
        &self,
        request: Request<pb::TraceBatchRequest>,
    ) -> Result<Response<pb::TraceBatchResponse>, Status> {
        let tenant = self.caller(&request, "TraceBatch", Role::Read)?;
        observe("TraceBatch", tenant.name().to_owned(), trace::batch(tenant, request.into_inner())).await
    }

    type TraceStreamStream = trace::ResponseStream;

    async fn trace_stream(
        &self,
        request: Request<Streaming<pb::TraceStreamRequest>>,
    ) -> Result<Response<Self::TraceStreamStream>, Status> {
        let tenant = self.caller(&request, "TraceStream", Role::Read)?;
        observe("TraceStream", tenant.name().to_owned(), trace::stream(tenant, request.into_inner())).await
    }

    type OpenStreamStream = stream::ResponseStream;

    async fn open_stream(
        &self,
        request: Request<Streaming<pb::StreamRequest>>,
    ) -> Result<Response<Self::OpenStreamStream>, Status> {
        let tenant = self.caller(&request, "OpenStream", Role::Write)?;
        observe("OpenStream", tenant.name().to_owned(), async { stream::open(tenant, request.into_inner()) }).await
    }

    async fn cancel_stream(
        &self,
        request: Request<pb::CancelStreamRequest>,
    ) -> Result<Response<pb::CancelStreamResponse>, Status> {
        let tenant = self.caller(&request, "CancelStream", Role::Write)?;
        observe("CancelStream", tenant.name().to_owned(), async {
            tenant.streams().cancel(request.get_ref().stream_id).map_err(|e| e.in_field("stream_id"))?;
            Ok(pb::CancelStreamResponse {})
        })
        .await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn blocking_work_that_panics_fails_its_call_with_internal() {
        let failed = blocking(|| -> ServiceResult<()> { panic!("a bug in a build") }).await.unwrap_err();
        assert!(matches!(&failed, ServiceError::Internal(why) if why.contains("a bug in a build")), "{failed}");
        assert_eq!(blocking(|| Ok(7)).await.unwrap(), 7);
    }

    #[tokio::test]
    async fn a_reader_that_panicked_ends_its_call_with_internal() {
        let panicked = reader_ended(tokio::spawn(async { panic!("a bug in a reader") })).await.unwrap_err();
        assert_eq!(panicked.code(), tonic::Code::Internal, "{panicked:?}");
        assert!(reader_ended(tokio::spawn(async {})).await.is_ok(), "a reader that returned");
    }

    #[test]
    fn one_service_a_data_directory() {
        let dir = tempfile::tempdir().unwrap();
        let config = Config { data_dir: Some(dir.path().join("data")), ..Config::default() };
        let first = RaydService::new(vec![Device::cpu()], &config).unwrap();
        let Err(refused) = RaydService::new(vec![Device::cpu()], &config) else { panic!("a second service started") };
        let status = Status::from(refused);
        assert_eq!(status.code(), tonic::Code::FailedPrecondition);
        assert!(status.message().contains("another process holds its lock"), "{}", status.message());
        drop(first);
        RaydService::new(vec![Device::cpu()], &config).unwrap();
    }
}
