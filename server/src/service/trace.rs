//! `TraceBatch` (one call) and `TraceStream` (ordered chunks with bounded buffering).

use std::pin::Pin;
use std::sync::Arc;

use bytes::Bytes;
use rayd_engine::query::Query;
use rayd_engine::reduce::Reduction;
use rayd_proto as pb;
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tonic::{Status, Streaming};

use super::outbox::outbox;
use super::{accels, blocking, buffers};
use crate::convert;
use crate::error::{ServiceError, ServiceResult};
use crate::tenant::{AccelEntry, MAX_NAME_CHARS, Rays, Tenant, TraceResult};

/// The response stream of `TraceStream`.
pub type ResponseStream = Pin<Box<dyn Stream<Item = Result<pb::TraceStreamResponse, Status>> + Send>>;

/// The request field that names the buffers a trace writes its hits and counts to.
const HITS_BUFFER_NAME: &str = "hits_buffer_name";

/// What the name of a trace's counts buffer adds to its hits buffer's.
const COUNTS_SUFFIX: &str = ".counts";

/// The name of the buffer a trace writes its counts to, beside its hits buffer `hits`.
fn counts_buffer_name(hits: &str) -> String {
    format!("{hits}{COUNTS_SUFFIX}")
}

/// Room left in a reply message for everything but the hit and count bytes.
const REPLY_OVERHEAD_BYTES: u64 = 4096;

/// The accel and engine query of a `TraceQuery`.
fn resolve_query(tenant: &Tenant, query: Option<&pb::TraceQuery>) -> ServiceResult<(AccelEntry, Query)> {
    let query = query.ok_or_else(|| ServiceError::invalid("query", "required"))?;
    let accel = accels::resolve(tenant, query.accel.as_ref(), "query.accel")?;
    Ok((accel, convert::query(query, tenant.limits().max_hits_per_ray)?))
}

/// Checks that the hits and counts of `rays` rays fit in one reply message.
fn check_reply_size(tenant: &Tenant, query: &Query, rays: u64) -> ServiceResult<()> {
    let layout = query.output_layout(rays as usize * query.ray_format.size())?;
    ServiceError::check_limit(
        || {
            format!(
                "the reply to {} rays ({} hit and {} count bytes); use TraceStream or hits_buffer_name",
                layout.rays, layout.hits, layout.counts
            )
        },
        (layout.hits + layout.counts) as u64 + REPLY_OVERHEAD_BYTES,
        "max_message_bytes",
        tenant.limits().max_message_bytes,
    )
}

/// Fails with RESOURCE_EXHAUSTED naming `max_message_bytes` if a reduction's answer of `bytes` bytes cannot be sent:
/// before the trace where its size is known then ([`Reduction::answer_bytes`]), after it otherwise (and while it
/// runs, by the records its pieces leave: [`crate::tenant`]'s trace).
fn check_reduced_size(tenant: &Tenant, bytes: u64) -> ServiceResult<()> {
    ServiceError::check_limit(
        || format!("the reduction's {bytes} bytes; reduce ranges of the batch in several calls"),
        bytes + REPLY_OVERHEAD_BYTES,
        "max_message_bytes",
        tenant.limits().max_message_bytes,
    )
}

/// Traces `rays` (through the fair scheduler of the accel's device), reduced by `reduction` if given, and counts
/// them in the metrics.
async fn trace(
    tenant: &Arc<Tenant>,
    accel: AccelEntry,
    query: Query,
    rays: Rays,
    reduction: Option<Arc<Reduction>>,
) -> ServiceResult<TraceResult> {
    let result = tenant.trace(&accel, &query, rays, reduction).await?;
    crate::metrics::traced(tenant.name(), &result);
    Ok(result)
}

/// The rays of request field `field`, packed in `query`'s ray format: whole records only.
fn packed(bytes: Bytes, query: &Query, field: &str) -> ServiceResult<Rays> {
    query.ray_format.whole_rays(bytes.len()).map_err(|rule| ServiceError::invalid(field, rule))?;
    Ok(Rays::Packed(bytes))
}

/// One batch in one call.
pub async fn batch(tenant: Arc<Tenant>, request: pb::TraceBatchRequest) -> ServiceResult<pb::TraceBatchResponse> {
    let (accel, query) = resolve_query(&tenant, request.query.as_ref())?;
    let (rays, rays_field) = match request.rays {
        Some(pb::trace_batch_request::Rays::RaysInline(bytes)) => {
            (packed(bytes, &query, "rays_inline")?, "rays_inline")
        }
        Some(pb::trace_batch_request::Rays::RaysBuffer(reference)) => {
            let bytes = buffers::resolve(&tenant, Some(&reference), "rays_buffer")?.1;
            (packed(bytes, &query, "rays_buffer")?, "rays_buffer")
        }
        Some(pb::trace_batch_request::Rays::RaysGenerator(generator)) => {
            let buffer =
                |reference: &pb::BufferRef, field: &str| Ok(buffers::resolve(&tenant, Some(reference), field)?.1);
            let (generator, range) = convert::generator(&generator, &buffer)?;
            (Rays::Generated(Arc::new(generator), range), "rays_generator")
        }
        None => return Err(ServiceError::invalid("rays", "rays_inline, rays_buffer or rays_generator is required")),
    };
    let ray_count = rays.count(query.ray_format.size());
    tenant.check_batch_rays(rays_field, ray_count)?;
    let to_buffer = !request.hits_buffer_name.is_empty();
    if let Some(reduction) = &request.reduction {
        if to_buffer {
            return Err(ServiceError::invalid("hits_buffer_name", "cannot be combined with a reduction"));
        }
        let generator = match &rays {
            Rays::Generated(generator, range) => Some((generator.as_ref(), range.start)),
            Rays::Packed(_) => None,
        };
        let reduction = convert::reduction(reduction, generator)?;
        reduction.check(&query, ray_count)?;
        if let Some(bytes) = reduction.answer_bytes(&query, ray_count) {
            check_reduced_size(&tenant, bytes)?;
        }
        return reduced(&tenant, accel, query, rays, reduction).await;
    }
    let mut reserved = None;
    if to_buffer {
        let layout = query.output_layout(ray_count as usize * query.ray_format.size())?;
        let (hits, counts) = (&request.hits_buffer_name, counts_buffer_name(&request.hits_buffer_name));
        let mut buffers = vec![(hits.as_str(), layout.hits as u64)];
        // A counting query gets its counts buffer even for no rays (empty, as its hits buffer is).
        if query.kind.has_counts() {
            let most = MAX_NAME_CHARS - COUNTS_SUFFIX.len();
            if hits.len() > most {
                let rule = format!(
                    "{} characters: at most {most} with counts, whose buffer's name adds \"{COUNTS_SUFFIX}\"",
                    hits.len()
                );
                return Err(ServiceError::invalid(HITS_BUFFER_NAME, rule));
            }
            buffers.push((&counts, layout.counts as u64));
        }
        // The buffers' bytes are reserved while the trace writes them (as an upload's are), so that traces at
        // once cannot make more than max_total_buffer_bytes of them.
        reserved = Some(tenant.reserve_new_buffers(HITS_BUFFER_NAME, &buffers)?);
    } else {
        check_reply_size(&tenant, &query, ray_count)?;
    }
    let result = trace(&tenant, accel, query, rays, None).await?;
    let stats = Some(convert::trace_stats(&result.stats, result.trace_ns));
    if !to_buffer {
        return Ok(pb::TraceBatchResponse { hits: result.hits, counts: result.counts, stats, ..Default::default() });
    }
    // With a data directory the buffers are written to disk: off the async runtime.
    blocking(move || {
        let mut reserved = reserved.into_iter().flatten();
        let mut next = || {
            reserved.next().ok_or_else(|| ServiceError::Internal("a buffer the trace writes was not reserved".into()))
        };
        let name = &request.hits_buffer_name;
        let hits_buffer = tenant.create_buffer(HITS_BUFFER_NAME, name, result.hits, next()?)?;
        let counts_buffer = if !query.kind.has_counts() {
            None
        } else {
            // Both buffers or neither: when the counts buffer cannot be made, the hits buffer is taken back.
            match next().and_then(|reserved| {
                tenant.create_buffer(HITS_BUFFER_NAME, &counts_buffer_name(name), result.counts, reserved)
            }) {
                Ok(entry) => Some(buffers::info(&entry)),
                Err(error) => {
                    // The call's answer is why the counts failed; a hits buffer that cannot be taken back is logged.
                    if let Err(left) = tenant.delete_buffer(&hits_buffer) {
                        tracing::warn!(buffer = hits_buffer.id, %left, "a hits buffer without its counts was left");
                    }
                    return Err(error);
                }
            }
        };
        Ok(pb::TraceBatchResponse {
            hits_buffer: Some(buffers::info(&hits_buffer)),
            counts_buffer,
            stats,
            ..Default::default()
        })
    })
    .await
}

/// One batch reduced by `reduction` (checked): only the reduction comes back, if it fits a message.
async fn reduced(
    tenant: &Arc<Tenant>,
    accel: AccelEntry,
    query: Query,
    rays: Rays,
    reduction: Reduction,
) -> ServiceResult<pb::TraceBatchResponse> {
    let result = trace(tenant, accel, query, rays, Some(Arc::new(reduction))).await?;
    let reduced = result.reduced.expect("a reduced trace has a reduction");
    check_reduced_size(tenant, reduced.bytes.len() as u64)?;
    Ok(pb::TraceBatchResponse {
        reduced: Some(pb::ReducedHits { data: reduced.bytes, dropped: reduced.dropped }),
        stats: Some(convert::trace_stats(&result.stats, result.trace_ns)),
        ..Default::default()
    })
}

/// Ordered chunks: each ray chunk is traced and answered in turn. A reader takes up to `stream_window` chunks off
/// the connection ahead of the one being traced, so receiving overlaps tracing, and up to `stream_window` answers
/// wait to be sent while the next chunk traces; past those windows nothing more is read, so memory stays bounded on
/// both sides. A client that reads no answer for `stream_stall_seconds` gets the stream failed (the outbox).
pub async fn stream(
    tenant: Arc<Tenant>,
    mut requests: Streaming<pb::TraceStreamRequest>,
) -> ServiceResult<ResponseStream> {
    let first = requests.message().await.map_err(ServiceError::Transport)?;
    let header = match first.and_then(|m| m.part) {
        Some(pb::trace_stream_request::Part::Query(header)) => header,
        _ => return Err(ServiceError::invalid("query", "the first message of a trace stream must be its query")),
    };
    // Checked now, so that a stream of a missing accel fails at once; each chunk finds the accel again, so that it
    // traces the accel as it is when the chunk comes (updated, or gone: NOT_FOUND), as a call of its own would.
    let (_, query) = resolve_query(&tenant, Some(&header))?;
    // One of the tenant's `max_streams` places for as long as the call lasts (its response stream holds it): each
    // stream's chunks and answers are bounded by the window, so the places bound them all.
    let place = tenant.streams().place(tenant.limits().max_streams)?;
    let accel = header.accel;
    let window = tenant.limits().window() as usize;
    let (chunk_sender, mut chunks) = mpsc::channel(window);
    let reader = tokio::spawn(async move {
        loop {
            let message = tokio::select! {
                // The tracer has ended (the call ended, or a chunk failed): nothing more is read, and the request
                // stream is let go at once rather than when the client next sends.
                () = chunk_sender.closed() => break,
                message = requests.message() => message,
            };
            let chunk = match message {
                Ok(None) => break,
                // A chunk that could not be received (e.g. above max_message_bytes) keeps tonic's status.
                Err(status) => Err(status),
                Ok(Some(message)) => match message.part {
                    Some(pb::trace_stream_request::Part::Rays(rays)) => Ok(rays),
                    _ => Err(ServiceError::invalid("query", "only the first message may be a query").into()),
                },
            };
            let failed = chunk.is_err();
            // The tracer gone (the call ended), or a bad chunk passed on: nothing more is read.
            if chunk_sender.send(chunk).await.is_err() || failed {
                break;
            }
        }
    });
    let (answers, stream) = outbox(window, tenant.limits().stream_stall(), "TraceStream", tenant.name());
    tokio::spawn(async move {
        let mut first_ray = 0u64;
        loop {
            let Some(chunk) = chunks.recv().await else {
                // The client's last chunk, unless the reader panicked.
                if let Err(status) = super::reader_ended(reader).await {
                    let _ = answers.send(Err(status)).await;
                }
                break;
            };
            let reply = match chunk {
                // Given up when the call ends (the client went, or its deadline passed), as a TraceBatch is: the
                // chunk's trace is abandoned, not run for nobody after the call's stream place is free.
                Ok(rays) => tokio::select! {
                    reply = answer_chunk(&tenant, accel.as_ref(), query, rays, first_ray) => reply.map_err(Status::from),
                    () = answers.closed() => break,
                },
                Err(status) => Err(status),
            };
            let reply = reply.map_err(|refused| in_chunk(refused, first_ray));
            let failed = reply.as_ref().err().cloned();
            if let Ok(response) = &reply {
                first_ray += response.stats.as_ref().map_or(0, |s| s.rays);
            }
            // A failure that reaches no client (it reset the call, or went) is no error of the server's answer.
            if answers.send(reply).await.is_err() {
                break;
            }
            if let Some(status) = failed {
                crate::metrics::stream_chunk_failed(tenant.name(), &status);
                break;
            }
        }
    });
    Ok(Box::pin(place.held_by(stream)))
}

/// The status of a stream's chunk that failed, its message naming the chunk by its first ray (ray numbers in the
/// rest of the message count from there).
fn in_chunk(status: Status, first_ray: u64) -> Status {
    Status::new(status.code(), format!("chunk from ray {first_ray}: {}", status.message()))
}

/// Traces one chunk of a stream on the accel that `accel` names now.
async fn answer_chunk(
    tenant: &Arc<Tenant>,
    accel: Option<&pb::AccelRef>,
    query: Query,
    rays: Bytes,
    first_ray: u64,
) -> ServiceResult<pb::TraceStreamResponse> {
    let rays = Rays::Packed(rays);
    check_reply_size(tenant, &query, rays.count(query.ray_format.size()))?;
    let accel = accels::resolve(tenant, accel, "query.accel")?;
    let result = trace(tenant, accel, query, rays, None).await?;
    Ok(pb::TraceStreamResponse {
        first_ray,
        hits: result.hits,
        counts: result.counts,
        stats: Some(convert::trace_stats(&result.stats, result.trace_ns)),
    })
}
