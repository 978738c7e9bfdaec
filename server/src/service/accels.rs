//! Accel calls shared by the unary handlers and stream operations: build, destroy, and reading references.

use std::sync::Arc;

use rayd_engine::accel::MemoryUsage;
use rayd_proto as pb;

use super::{blocking, blocking_for_caller, inputs};
use crate::convert;
use crate::error::{ServiceError, ServiceResult};
use crate::tenant::{AccelEntry, Tenant};

/// The accel a reference names.
pub fn resolve(tenant: &Tenant, reference: Option<&pb::AccelRef>, field: &str) -> ServiceResult<AccelEntry> {
    match reference.and_then(|r| r.r#ref.as_ref()) {
        Some(pb::accel_ref::Ref::Name(name)) => tenant.accel(Some(name), None).map_err(|e| e.in_field(field)),
        Some(pb::accel_ref::Ref::Handle(handle)) => tenant.accel(None, Some(handle)).map_err(|e| e.in_field(field)),
        Some(pb::accel_ref::Ref::Operation(_)) => Err(super::operation_outside_stream(field)),
        None => Err(ServiceError::invalid(field, "an accel name or handle is required")),
    }
}

/// The contract's description of an accel.
pub fn info(entry: &AccelEntry) -> pb::AccelInfo {
    convert::accel_info(entry.accel.info(), &entry.handle, &entry.name, &entry.device, entry.build_ns)
}

/// Builds an accel (off the async runtime, its inputs' resolution too, which reads their bytes and expands their
/// instances; not kept if the caller goes first).
pub async fn build(tenant: Arc<Tenant>, request: pb::BuildAccelRequest) -> ServiceResult<pb::AccelInfo> {
    let entry = blocking_for_caller(move |caller| {
        let resolved = inputs::resolve(&tenant, &request.device, &request.inputs)?;
        let options = inputs::options(&tenant, &resolved, request.options.as_ref())?;
        tenant.build_accel(
            &request.name,
            &request.device,
            caller,
            |context| resolved.memory_usage(context, &options),
            |context| resolved.build(context, &options, &|| caller.is_there()),
        )
    })
    .await?;
    Ok(info(&entry))
}

/// Destroys an accel; traces running on it finish first. Off the async runtime: it waits for the lock that orders
/// the tenant's changes, which a load of many accels holds while it writes their files, and removes a file.
pub async fn destroy(tenant: Arc<Tenant>, request: pb::DestroyAccelRequest) -> ServiceResult<()> {
    blocking(move || tenant.destroy_accel(&resolve(&tenant, request.accel.as_ref(), "accel")?)).await
}

/// Copies an accel, or makes a compacted copy (off the async runtime; not kept if the caller goes first).
pub async fn copy(tenant: Arc<Tenant>, request: pb::CopyAccelRequest) -> ServiceResult<pb::AccelInfo> {
    let source = resolve(&tenant, request.accel.as_ref(), "accel")?;
    // A copy of an accel that places an old version of another would place it too: it could neither trace nor be
    // stored (a data directory keeps only current versions), so it is refused as a trace of the source is.
    source.accel.check_current()?;
    let device = if request.device.is_empty() { source.device.clone() } else { request.device.clone() };
    let entry = blocking_for_caller(move |caller| {
        tenant.build_accel(
            &request.name,
            &device,
            caller,
            |_| Ok(MemoryUsage { output_bytes: source.accel.info().size_bytes, ..MemoryUsage::default() }),
            |context| context.copy_accel(&source.accel, request.compact),
        )
    })
    .await?;
    Ok(info(&entry))
}

/// Updates (refits) an accel in place (off the async runtime, its inputs' resolution too; not started if the caller
/// goes first).
pub async fn update(tenant: Arc<Tenant>, request: pb::UpdateAccelRequest) -> ServiceResult<pb::AccelInfo> {
    let entry = resolve(&tenant, request.accel.as_ref(), "accel")?;
    let updated = blocking_for_caller(move |caller| {
        let resolved = inputs::resolve(&tenant, &entry.device, &request.inputs)?;
        tenant.update_accel(&entry, caller, |context| resolved.update(context, &entry.accel))
    })
    .await?;
    Ok(info(&updated))
}

/// Serializes an accel and everything below it into a new buffer (off the async runtime; not kept if the caller
/// goes first).
pub async fn save(tenant: Arc<Tenant>, request: pb::SaveAccelRequest) -> ServiceResult<pb::BufferInfo> {
    let entry = resolve(&tenant, request.accel.as_ref(), "accel")?;
    let buffer =
        blocking_for_caller(move |caller| tenant.save_accel(&entry, "buffer_name", &request.buffer_name, caller))
            .await?;
    Ok(super::buffers::info(&buffer))
}

/// Recreates the accels of a saved blob (off the async runtime; not kept if the caller goes first).
pub async fn load(tenant: Arc<Tenant>, request: pb::LoadAccelRequest) -> ServiceResult<pb::LoadAccelResponse> {
    let blob = inputs::data(&tenant, request.blob.as_ref(), "blob")?
        .ok_or_else(|| ServiceError::invalid("blob", "a blob is required"))?;
    let entries =
        blocking_for_caller(move |caller| tenant.load_accels(&request.name, &request.device, caller, &blob)).await?;
    Ok(pb::LoadAccelResponse { accels: entries.iter().map(info).collect() })
}
