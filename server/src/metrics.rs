//! Prometheus metrics: calls, latency and errors per method and tenant, rays traced, accels and their bytes. Rendered at
//! the admin endpoint's `/metrics`.

use std::future::Future;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use metrics::{Unit, counter, describe_counter, describe_gauge, describe_histogram, gauge, histogram};
use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle};
use tonic::{Code, Response, Status};

use crate::error::ServiceError;
use crate::tenant::{AccelEntry, TraceResult};

/// Latency buckets, in seconds: 50 µs to 60 s.
const LATENCY_BUCKETS: [f64; 14] =
    [5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 0.1, 0.5, 2.0, 10.0, 60.0];

/// How often the recorder's upkeep folds recorded latencies into their buckets.
pub const UPKEEP_PERIOD: Duration = Duration::from_secs(5);

/// Installs the process-wide recorder once, with its upkeep thread, and returns its handle.
///
/// The recorder keeps every recorded histogram sample until an upkeep (or a render of `/metrics`) folds them into
/// the buckets: without the upkeep thread a server nobody scrapes grows by every call it answers (the hour soak
/// measured +152 MiB over 2.1 M operations).
pub fn install() -> PrometheusHandle {
    static HANDLE: OnceLock<PrometheusHandle> = OnceLock::new();
    HANDLE
        .get_or_init(|| {
            let handle = PrometheusBuilder::new()
                .set_buckets(&LATENCY_BUCKETS)
                .expect("non-empty buckets")
                .install_recorder()
                .expect("the only metrics recorder of the process");
            describe();
            let upkept = handle.clone();
            std::thread::Builder::new()
                .name("rayd-metrics-upkeep".into())
                .spawn(move || {
                    loop {
                        std::thread::sleep(UPKEEP_PERIOD);
                        upkept.run_upkeep();
                    }
                })
                .expect("a thread for the metrics upkeep");
            handle
        })
        .clone()
}

/// Describes every metric: the `# HELP` lines of `/metrics`.
fn describe() {
    describe_counter!("rayd_requests_total", "gRPC calls answered or dropped, by method and tenant");
    describe_histogram!(
        "rayd_request_duration_seconds",
        Unit::Seconds,
        "time from a call's arrival to its answer (a stream's: to its opening), by method and tenant"
    );
    describe_counter!(
        "rayd_errors_total",
        "failed calls by method, tenant and gRPC code, and failed TraceStream chunks (method TraceStream); a call \
         dropped before its answer (caller gone, deadline passed) counts with code Cancelled"
    );
    describe_counter!(
        "rayd_rays_traced_total",
        "rays a device traced for the tenant (TraceBatch calls, TraceStream chunks, stream trace operations), \
         counted once the trace ends, even if the call then fails (e.g. its hits buffer cannot be kept)"
    );
    describe_counter!("rayd_rays_hit_total", "of rayd_rays_traced_total, the rays that hit something");
    describe_counter!(
        "rayd_trace_batches_total",
        "traces that ended: a TraceBatch call, a TraceStream chunk or a stream's trace operation is one each"
    );
    describe_counter!(
        "rayd_trace_pieces_total",
        "pieces of queued traces by outcome: traced, failed, or skipped (its trace was abandoned first)"
    );
    describe_histogram!(
        "rayd_trace_piece_seconds",
        Unit::Seconds,
        "how long a piece of a trace held its device (the time the fair queue charged), by tenant and device"
    );
    describe_histogram!(
        "rayd_trace_queue_seconds",
        Unit::Seconds,
        "how long a trace waited in its device's queue before its first piece started (or it gave up)"
    );
    describe_gauge!("rayd_accels", "accels the tenant holds");
    describe_gauge!("rayd_accel_bytes", Unit::Bytes, "bytes of the accels the tenant holds (their size_bytes)");
    describe_counter!(
        "rayd_streams_stalled_total",
        "TraceStream, OpenStream and DownloadBuffer calls failed RESOURCE_EXHAUSTED because their client read no \
         answer for limits.stream_stall_seconds, by method and tenant"
    );
    describe_counter!(
        "rayd_stream_operations_total",
        "OpenStream operations that finished, by tenant, op and gRPC code"
    );
    describe_histogram!(
        "rayd_stream_operation_duration_seconds",
        Unit::Seconds,
        "how long an OpenStream operation that started ran, by tenant and op"
    );
}

/// Runs one call's logic for `tenant` (labels are bounded: tenants come from the configuration), records its latency
/// and outcome, and turns its error into a status. A call whose future is dropped before it answers (its caller went
/// away or its deadline passed) is recorded too, with code `Cancelled`.
pub async fn observe<T>(
    method: &'static str,
    tenant: String,
    call: impl Future<Output = Result<T, ServiceError>>,
) -> Result<Response<T>, Status> {
    let mut unanswered = Unanswered(Some(Call { method, tenant, start: Instant::now() }));
    let result = call.await.map_err(Status::from);
    if let Some(call) = unanswered.0.take() {
        call.record(result.as_ref().err());
    }
    result.map(Response::new)
}

/// A call being answered: what its metrics are recorded under.
struct Call {
    /// The RPC.
    method: &'static str,
    /// The calling tenant.
    tenant: String,
    /// When the call's logic started.
    start: Instant,
}

impl Call {
    /// Records the call's latency, and its `error` if it failed.
    fn record(self, error: Option<&Status>) {
        let (method, tenant) = (self.method, self.tenant);
        let labels = [("method", method.to_owned()), ("tenant", tenant.clone())];
        histogram!("rayd_request_duration_seconds", &labels).record(self.start.elapsed().as_secs_f64());
        counter!("rayd_requests_total", &labels).increment(1);
        if let Some(status) = error {
            count_error(method, &tenant, status, "request failed");
        }
    }
}

/// Counts a failed call (or a part of one) of `method` for `tenant` by its status's code, and logs it as `what`: a
/// failure of the server's own (INTERNAL, UNAVAILABLE, DATA_LOSS, UNKNOWN) as a warning; one the request or its
/// caller caused (a bad argument, a limit, a missing object, a deadline, …) at debug level only, so that a client
/// retrying a refused call does not flood the log.
fn count_error(method: &'static str, tenant: &str, status: &Status, what: &'static str) {
    let code = status.code();
    let labels = [("method", method.to_owned()), ("tenant", tenant.to_owned()), ("code", format!("{code:?}"))];
    counter!("rayd_errors_total", &labels).increment(1);
    let message = status.message();
    match code {
        Code::Internal | Code::Unavailable | Code::DataLoss | Code::Unknown => {
            tracing::warn!(method, tenant, ?code, message, "{what}")
        }
        _ => tracing::debug!(method, tenant, ?code, message, "{what}"),
    }
}

/// Records its call, if still held when dropped, as cancelled: the call's future was dropped before it answered.
struct Unanswered(Option<Call>);

impl Drop for Unanswered {
    fn drop(&mut self) {
        if let Some(call) = self.0.take() {
            call.record(Some(&Status::cancelled("the caller went away or its deadline passed before the answer")));
        }
    }
}

/// Counts a `TraceStream` chunk of `tenant` whose failure (which ends its stream) was sent to the client as an error
/// of the call, which [`observe`] recorded as answered once the stream opened.
pub fn stream_chunk_failed(tenant: &str, status: &Status) {
    count_error("TraceStream", tenant, status, "chunk failed");
}

/// Counts a `method` stream of `tenant` failed because its client read no answer for `limits.stream_stall_seconds`,
/// and logs it with the `held` answers dropped.
pub fn stream_stalled(method: &'static str, tenant: &str, held: usize) {
    tracing::warn!(method, tenant, held, "a stream's client stopped reading: stream failed");
    counter!("rayd_streams_stalled_total", "method" => method, "tenant" => tenant.to_owned()).increment(1);
}

/// Counts a finished trace of `tenant` (labels are bounded: tenants come from the configuration), and logs it at
/// debug level with the pieces it was cut into.
pub fn traced(tenant: &str, result: &TraceResult) {
    let stats = &result.stats;
    tracing::debug!(tenant, rays = stats.rays, pieces = result.pieces, ms = result.trace_ns as f64 * 1e-6, "traced");
    let tenant = tenant.to_owned();
    counter!("rayd_rays_traced_total", "tenant" => tenant.clone()).increment(stats.rays);
    counter!("rayd_rays_hit_total", "tenant" => tenant.clone()).increment(stats.rays_hit);
    counter!("rayd_trace_batches_total", "tenant" => tenant).increment(1);
}

/// Counts a piece of a queued trace of `tenant` by its `outcome`: `traced`, `failed`, or `skipped`: it found its
/// trace abandoned (the caller went away, its deadline passed, or another piece failed) and took no rays.
pub fn piece(tenant: &str, outcome: &'static str) {
    counter!("rayd_trace_pieces_total", "tenant" => tenant.to_owned(), "outcome" => outcome).increment(1);
}

/// A piece of `tenant`'s trace held `device` for `took`: a worker's time, which the fair queue charged the tenant, or
/// the caller's own thread's, for a trace of one piece run there while nothing was queued.
pub fn piece_time(tenant: &str, device: &str, took: Duration) {
    let labels = [("tenant", tenant.to_owned()), ("device", device.to_owned())];
    histogram!("rayd_trace_piece_seconds", &labels).record(took.as_secs_f64());
}

/// Records how long a trace of `tenant` waited in its device's queue before its first piece started.
pub fn queued(tenant: &str, waited: Duration) {
    histogram!("rayd_trace_queue_seconds", "tenant" => tenant.to_owned()).record(waited.as_secs_f64());
}

/// Counts a new accel of `tenant`.
pub fn accel_built(tenant: &str, entry: &AccelEntry) {
    gauge!("rayd_accels", "tenant" => tenant.to_owned()).increment(1.0);
    gauge!("rayd_accel_bytes", "tenant" => tenant.to_owned()).increment(entry.accel.info().size_bytes as f64);
    tracing::info!(
        tenant,
        name = entry.name,
        handle = entry.handle,
        bytes = entry.accel.info().size_bytes,
        build_ms = entry.build_ns / 1_000_000,
        "accel built"
    );
}

/// Counts the bytes of `tenant`'s accel updated from version `old` to `new` (their sizes may differ).
pub fn accel_updated(tenant: &str, old: &AccelEntry, new: &AccelEntry) {
    let change = new.accel.info().size_bytes as f64 - old.accel.info().size_bytes as f64;
    gauge!("rayd_accel_bytes", "tenant" => tenant.to_owned()).increment(change);
}

/// Counts a destroyed accel of `tenant`.
pub fn accel_destroyed(tenant: &str, entry: &AccelEntry) {
    gauge!("rayd_accels", "tenant" => tenant.to_owned()).decrement(1.0);
    gauge!("rayd_accel_bytes", "tenant" => tenant.to_owned()).decrement(entry.accel.info().size_bytes as f64);
    tracing::info!(tenant, name = entry.name, handle = entry.handle, "accel destroyed");
}

/// Counts one finished stream operation of `tenant`, and records how long it ran if it started (`took`; an operation
/// refused before it starts, for using what a failed one did not make, ran for no time).
pub fn stream_operation(tenant: &str, op: &'static str, code: tonic::Code, took: Option<Duration>) {
    let tenant = tenant.to_owned();
    if let Some(took) = took {
        let labels = [("tenant", tenant.clone()), ("op", op.to_owned())];
        histogram!("rayd_stream_operation_duration_seconds", &labels).record(took.as_secs_f64());
    }
    counter!("rayd_stream_operations_total", "tenant" => tenant, "op" => op, "code" => format!("{code:?}"))
        .increment(1);
}
