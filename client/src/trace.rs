//! Tracing: one `TraceBatch` call when the rays and hits fit in a message, otherwise a `TraceStream` of ray
//! chunks with a bounded window, reassembled in order. Callers get the same [`TraceResult`] either way, or, to hold
//! neither the rays nor the hits whole, the result of each part as it comes back ([`TraceParts`]).

use std::sync::{Arc, Mutex};

use bytes::{Bytes, BytesMut};
use futures_util::stream::BoxStream;
use futures_util::{Stream, StreamExt};
use rayd_engine::format::RayFormat;
use rayd_engine::query::{OutputLayout, Query};
use rayd_engine::raygen::Generator;
use rayd_proto as proto;
use rayd_proto::{trace_batch_request, trace_stream_request};
use tokio::sync::Semaphore;
use tokio::sync::mpsc::error::TryRecvError;

use crate::client::Client;
use crate::convert::{generated_ray_count, generator_to_proto, trace_query};
use crate::error::{Error, Result};
use crate::memory::reserved;
use crate::secondary::inline_bytes;
use crate::view::HitView;

/// What a trace returned. Its buffers' lengths were checked against the query, so its views cannot fail.
#[derive(Debug, Clone)]
pub struct TraceResult {
    /// The query that was traced, which says how `hits` is packed.
    query: Query,
    /// Number of rays traced.
    rays: usize,
    /// Hit records in `query.hit_format`, `query.records_per_ray()` a ray.
    hits: Bytes,
    /// For `all` and `count` queries one little-endian `u32` a ray; empty otherwise.
    counts: Bytes,
    /// The server's statistics, summed over chunks when the trace was streamed.
    stats: proto::TraceStats,
}

impl TraceResult {
    /// The query that was traced.
    pub fn query(&self) -> &Query {
        &self.query
    }

    /// Number of rays traced.
    pub fn rays(&self) -> usize {
        self.rays
    }

    /// The packed hit records: `query().records_per_ray()` a ray, those of ray `r` first at `r * records_per_ray`.
    pub fn hits(&self) -> &Bytes {
        &self.hits
    }

    /// For `all` and `count` queries the packed counts, one little-endian `u32` a ray; empty otherwise.
    pub fn counts(&self) -> &Bytes {
        &self.counts
    }

    /// The server's statistics (summed over chunks when the trace was streamed).
    pub fn stats(&self) -> &proto::TraceStats {
        &self.stats
    }

    /// The hit records, decoded on demand.
    pub fn hit_view(&self) -> HitView<'_> {
        HitView::new(&self.hits, self.query.hit_format, self.rays * self.query.records_per_ray())
            .expect("lengths are checked when the result is made")
    }

    /// The result of tracing `rays` bytes of `query.ray_format` records, from a `TraceBatch` answer (or a stream's
    /// trace operation); fails with [`Error::Protocol`] when its lengths do not fit the query.
    pub(crate) fn from_batch(query: &Query, rays: usize, response: proto::TraceBatchResponse) -> Result<TraceResult> {
        let stats = response.stats.unwrap_or_default();
        TraceResult::checked(query, rays, "the batch", response.hits, response.counts, stats)
    }

    /// The result of tracing `rays` bytes of `query.ray_format` records, answered (by `what`) with `hits`, `counts`
    /// and `stats`; fails with [`Error::Protocol`] when their lengths do not fit the query.
    fn checked(
        query: &Query,
        rays: usize,
        what: &str,
        hits: Bytes,
        counts: Bytes,
        stats: proto::TraceStats,
    ) -> Result<TraceResult> {
        let layout = output_layout(query, rays)?;
        check_lengths(what, (hits.len(), counts.len()), (layout.hits, layout.counts))?;
        Ok(TraceResult { query: *query, rays: layout.rays, hits, counts, stats })
    }

    /// This whole result as the stream of one part.
    pub fn into_parts(self) -> TraceParts {
        futures_util::stream::once(std::future::ready(Ok(self))).boxed()
    }

    /// Ray `ray`'s count (hits found for `all`, crossings for `count`), or `None` when the query has no counts.
    pub fn count(&self, ray: usize) -> Option<u32> {
        let bytes = self.counts.get(4 * ray..4 * ray + 4)?;
        Some(u32::from_le_bytes(bytes.try_into().expect("4 bytes")))
    }
}

/// The results of a trace part by part, in ray order, as the server answers them: each a [`TraceResult`] of the
/// part's rays (its ray numbers continue the part before). The first error ends the stream.
pub type TraceParts = BoxStream<'static, Result<TraceResult>>;

impl Client {
    /// Traces packed `rays` (whole records of `query.ray_format`) against the accel called `accel`. Goes through
    /// `TraceBatch` when the rays and the expected hits and counts each fit in
    /// [`ClientOptions::batch_limit_bytes`](crate::ClientOptions::batch_limit_bytes), else through `TraceStream`.
    pub async fn trace(&self, accel: &str, query: &Query, rays: Bytes) -> Result<TraceResult> {
        let layout = output_layout(query, rays.len())?;
        let limit = self.options.batch_limit_bytes;
        if rays.len() <= limit && layout.hits + layout.counts <= limit && layout.rays <= self.options.max_rays_per_call
        {
            self.trace_batch(accel, query, rays).await
        } else {
            self.trace_stream(accel, query, rays, &layout).await
        }
    }

    /// Traces the rays of `generator`, which the server makes itself (no ray crosses the network), against the
    /// accel called `accel`; the hits come back in the generator's ray order. The rays are made in
    /// `query.ray_format` (a lidar with times other than 0 needs a format with time). One `TraceBatch` call when the hits fit in
    /// [`ClientOptions::batch_limit_bytes`](crate::ClientOptions::batch_limit_bytes), else one per range of rays
    /// whose hits do, `stream_window` of them at once. Secondary rays whose hits and packed primary rays together
    /// pass `batch_limit_bytes` go through temporary buffers of the accel's scene instead of with every call (see
    /// [`Client::trace_secondary`]).
    pub async fn trace_generated(&self, accel: &str, query: &Query, generator: &Generator) -> Result<TraceResult> {
        if let Generator::Secondary(secondary) = generator
            && inline_bytes(secondary) > self.options.batch_limit_bytes
        {
            return self.trace_uploaded_secondary(accel, query, secondary).await;
        }
        let total = usize::try_from(generated_ray_count(generator)).unwrap_or(usize::MAX);
        self.trace_in_ranges(accel, query, generator_to_proto(generator), total).await
    }

    /// Traces the rays of `generator` as [`Client::trace_generated`] does, but yields each call's result as it comes
    /// back instead of holding the hits whole (secondary rays whose hits go through a temporary buffer come back in
    /// one part).
    pub async fn trace_generated_parts(&self, accel: &str, query: &Query, generator: &Generator) -> Result<TraceParts> {
        if let Generator::Secondary(secondary) = generator
            && inline_bytes(secondary) > self.options.batch_limit_bytes
        {
            return Ok(self.trace_uploaded_secondary(accel, query, secondary).await?.into_parts());
        }
        let total = usize::try_from(generated_ray_count(generator)).unwrap_or(usize::MAX);
        self.generated_parts(accel, query, generator_to_proto(generator), total)
    }

    /// The results of the `total` rays of `generator`, traced in ranges whose hits each fit in a batch, one part a
    /// range.
    pub(crate) fn generated_parts(
        &self,
        accel: &str,
        query: &Query,
        generator: proto::RayGenerator,
        total: usize,
    ) -> Result<TraceParts> {
        let (_, per_call) = self.generated_calls(query, total)?;
        Ok(self.range_parts(accel, query, generator, total, per_call))
    }

    /// Traces the `total` rays of `generator` in ranges (`first_ray`, `ray_count`) whose hits each fit in a batch,
    /// as [`Client::trace_generated`] describes.
    pub(crate) async fn trace_in_ranges(
        &self,
        accel: &str,
        query: &Query,
        generator: proto::RayGenerator,
        total: usize,
    ) -> Result<TraceResult> {
        let (layout, per_call) = self.generated_calls(query, total)?;
        if per_call >= total {
            // One call (none for no rays): its answer's buffers as they are.
            let mut parts = self.range_parts(accel, query, generator, total, per_call);
            return parts.next().await.unwrap_or_else(|| TraceResult::from_batch(query, 0, Default::default()));
        }
        let answer = reserved_answer(&layout)?;
        concatenate(answer, query, total, self.range_parts(accel, query, generator, total, per_call)).await
    }

    /// The hits and counts of `total` generated rays of `query`, and the rays of one `TraceBatch` call of them: all
    /// of them when their hits and counts fit in a batch, else as many as keep each call's hits and counts within
    /// one.
    fn generated_calls(&self, query: &Query, total: usize) -> Result<(OutputLayout, usize)> {
        let layout = output_layout_of_rays(query, total as u64)?;
        let (limit, max_rays) = (self.options.batch_limit_bytes, self.options.max_rays_per_call);
        let per_call = if layout.hits.saturating_add(layout.counts) <= limit && layout.rays <= max_rays {
            layout.rays
        } else {
            // Generated rays cost nothing on the wire: only the hits and counts must fit.
            chunk_rays(&Query { ray_format: RayFormat::OriginDirection, ..*query }, limit, max_rays)
        };
        Ok((layout, per_call))
    }

    /// The results of [`Client::range_answers`] (no reduction), one part a call.
    fn range_parts(
        &self,
        accel: &str,
        query: &Query,
        generator: proto::RayGenerator,
        total: usize,
        per_call: usize,
    ) -> TraceParts {
        let (query, ray_size) = (*query, query.ray_format.size());
        self.range_answers(accel, &query, generator, None, total, per_call)
            .map(move |answer| {
                answer.and_then(|(rays, response)| TraceResult::from_batch(&query, rays * ray_size, response))
            })
            .boxed()
    }

    /// The answers of `TraceBatch` calls over the ranges (`first_ray`, `ray_count`) of at most `per_call` of
    /// `generator`'s `total` rays, in ray order, `stream_window` calls in flight: each range's ray count and the
    /// server's answer, its hits reduced by `reduction` where one is given.
    pub(crate) fn range_answers(
        &self,
        accel: &str,
        query: &Query,
        generator: proto::RayGenerator,
        reduction: Option<proto::Reduction>,
        total: usize,
        per_call: usize,
    ) -> impl Stream<Item = Result<(usize, proto::TraceBatchResponse)>> + use<> {
        let rpc = self.rpc_for(accel);
        let request =
            proto::TraceBatchRequest { query: Some(trace_query(accel, query)), reduction, ..Default::default() };
        let per_call = per_call.max(1);
        let calls = (0..total).step_by(per_call).map(move |first| {
            let count = per_call.min(total - first);
            let range = proto::RayGenerator { first_ray: first as u64, ray_count: count as u64, ..generator.clone() };
            let request = proto::TraceBatchRequest {
                rays: Some(trace_batch_request::Rays::RaysGenerator(range)),
                ..request.clone()
            };
            let mut rpc = rpc.clone();
            async move { Ok::<_, Error>((count, rpc.trace_batch(request).await?.into_inner())) }
        });
        futures_util::stream::iter(calls).buffered(self.options.stream_window.max(1))
    }

    /// One `TraceBatch` call; the result's buffers are the response's own, not copies.
    async fn trace_batch(&self, accel: &str, query: &Query, rays: Bytes) -> Result<TraceResult> {
        let ray_bytes = rays.len();
        let request = inline_trace(trace_query(accel, query), rays);
        let response = self.rpc_for(accel).trace_batch(request).await?.into_inner();
        TraceResult::from_batch(query, ray_bytes, response)
    }

    /// A `TraceStream` of `rays`, reassembled ([`Client::trace_parts`]).
    async fn trace_stream(
        &self,
        accel: &str,
        query: &Query,
        rays: Bytes,
        layout: &OutputLayout,
    ) -> Result<TraceResult> {
        let answer = reserved_answer(layout)?;
        let parts = self.trace_parts(accel, query, futures_util::stream::once(std::future::ready(Ok(rays)))).await?;
        concatenate(answer, query, layout.rays, parts).await
    }

    /// Rays of one part of [`Client::trace_parts`] for `query`: chunks of a multiple of this many rays are sent
    /// without being cut into smaller parts.
    pub fn part_rays(&self, query: &Query) -> usize {
        let chunk_bytes = self.options.stream_chunk_bytes.min(self.options.batch_limit_bytes);
        chunk_rays(query, chunk_bytes, self.options.max_rays_per_call)
    }

    /// Traces the packed rays that `chunks` yields (records of `query.ray_format`, cut anywhere) against the accel
    /// called `accel` through one `TraceStream`, and yields the result of each part of [`Client::part_rays`] rays as
    /// it comes back, in ray order, with at most `stream_window` parts unanswered: neither the rays nor the hits are
    /// held whole. A part is a slice of a chunk where the chunk holds it whole (chunks of a multiple of
    /// [`Client::part_rays`] rays are never copied). An error of `chunks`, or rays that end within a record, ends
    /// the trace with that error once the parts sent before it are answered. Read the parts as they come: the
    /// server fails a stream whose answers wait unread for `stream_stall_seconds` (60 s by default).
    pub async fn trace_parts(
        &self,
        accel: &str,
        query: &Query,
        chunks: impl Stream<Item = Result<Bytes>> + Send + 'static,
    ) -> Result<TraceParts> {
        let (query, ray_size) = (*query, query.ray_format.size());
        let parts = Recut {
            chunks: chunks.boxed(),
            pending: Bytes::new(),
            carried: BytesMut::new(),
            part_bytes: self.part_rays(&query) * ray_size,
            ray_format: query.ray_format,
            ended: false,
        };
        let window = CloseOnDrop(Arc::new(Semaphore::new(self.options.stream_window.max(1))));
        let (sent, sent_parts) = tokio::sync::mpsc::unbounded_channel::<usize>();
        let failed = Arc::new(Mutex::new(None));
        let sending = Sending { parts, window: window.0.clone(), sent, failed: Arc::clone(&failed) };
        let paced = futures_util::stream::unfold(sending, move |mut sending| async move {
            let part = match sending.parts.next().await? {
                Ok(part) => part,
                Err(e) => {
                    *sending.failed.lock().expect("no panic holds it") = Some(e);
                    return None;
                }
            };
            sending.window.acquire().await.ok()?.forget();
            sending.sent.send(part.len() / ray_size).ok()?;
            Some((trace_stream_request::Part::Rays(part), sending))
        });
        let first = trace_stream_request::Part::Query(trace_query(accel, &query));
        let requests = futures_util::stream::once(async { first })
            .chain(paced)
            .map(|part| proto::TraceStreamRequest { part: Some(part) });
        let responses = self.rpc_for(accel).trace_stream(requests).await?.into_inner();
        let receiving = Receiving { responses, sent_parts, next_ray: 0, window, failed, ended: false };
        Ok(futures_util::stream::unfold(receiving, move |mut receiving| async move {
            let part = receiving.next_part(&query).await?;
            Some((part, receiving))
        })
        .boxed())
    }
}

/// Rays in chunks cut anywhere, re-cut into parts of `part_bytes` (the last may be shorter): a part that a chunk
/// holds whole is a slice of it; one that spans chunks is copied together.
struct Recut {
    /// The rays as they come.
    chunks: BoxStream<'static, Result<Bytes>>,
    /// What is left of the chunk being cut.
    pending: Bytes,
    /// A part being put together from pieces of chunks.
    carried: BytesMut,
    /// Bytes of a part: a multiple of the ray format's record.
    part_bytes: usize,
    /// The rays' format.
    ray_format: RayFormat,
    /// Set once `chunks` ended, or failed.
    ended: bool,
}

impl Recut {
    /// The next part; `None` after the last.
    async fn next(&mut self) -> Option<Result<Bytes>> {
        loop {
            if self.carried.is_empty() && self.pending.len() >= self.part_bytes {
                return Some(Ok(self.pending.split_to(self.part_bytes)));
            }
            if !self.carried.is_empty() && !self.pending.is_empty() {
                let take = (self.part_bytes - self.carried.len()).min(self.pending.len());
                self.carried.extend_from_slice(&self.pending.split_to(take));
                if self.carried.len() == self.part_bytes {
                    return Some(Ok(self.carried.split().freeze()));
                }
                continue;
            }
            // Less than a part is left of the chunk, with nothing carried, or nothing is left of it.
            if self.ended {
                return self.last_part();
            }
            match self.chunks.next().await {
                Some(Ok(chunk)) => {
                    self.carried.extend_from_slice(&std::mem::take(&mut self.pending));
                    self.pending = chunk;
                }
                Some(Err(e)) => {
                    self.ended = true;
                    (self.carried, self.pending) = (BytesMut::new(), Bytes::new());
                    return Some(Err(e));
                }
                None => self.ended = true,
            }
        }
    }

    /// What is left once the chunks ended, short of a part: the last part (a slice of the last chunk where that
    /// holds it), `None` when nothing is left, or the refusal of rays that end within a record.
    fn last_part(&mut self) -> Option<Result<Bytes>> {
        let last =
            if self.carried.is_empty() { std::mem::take(&mut self.pending) } else { self.carried.split().freeze() };
        let size = self.ray_format.size();
        match last.len() {
            0 => None,
            bytes if bytes.is_multiple_of(size) => Some(Ok(last)),
            bytes => Some(Err(Error::InvalidArgument(format!(
                "the rays end within a record: {} bytes after the last whole {size}-byte {} record",
                bytes % size,
                self.ray_format.name()
            )))),
        }
    }
}

/// The sending side of [`Client::trace_parts`].
struct Sending {
    /// The rays, cut into parts.
    parts: Recut,
    /// Parts that may be sent before more are answered.
    window: Arc<Semaphore>,
    /// The rays of each part sent, in order, for the receiving side.
    sent: tokio::sync::mpsc::UnboundedSender<usize>,
    /// The error that ended the rays, if one did.
    failed: Arc<Mutex<Option<Error>>>,
}

/// The receiving side of [`Client::trace_parts`].
struct Receiving {
    /// The server's answers, one a part.
    responses: tonic::Streaming<proto::TraceStreamResponse>,
    /// The rays of each part sent and not yet answered, in order.
    sent_parts: tokio::sync::mpsc::UnboundedReceiver<usize>,
    /// The first ray of the next part due.
    next_ray: usize,
    /// The sending side's window, closed when the trace ends.
    window: CloseOnDrop,
    /// The error that ended the rays, if one did.
    failed: Arc<Mutex<Option<Error>>>,
    /// Set once the trace ended, well or not.
    ended: bool,
}

impl Receiving {
    /// The next part's result, checked against the part sent; `None` once the trace ended well.
    async fn next_part(&mut self, query: &Query) -> Option<Result<TraceResult>> {
        if self.ended {
            return None;
        }
        let part = match self.responses.message().await {
            Ok(Some(chunk)) => Some(self.check(query, chunk)),
            Ok(None) => self.why_ended().map(Err),
            Err(status) => Some(Err(status.into())),
        };
        self.ended = !matches!(part, Some(Ok(_)));
        if self.ended {
            // Nothing more is sent once the trace ended, well or not.
            self.window.0.close();
        }
        part
    }

    /// The result of the part `chunk` answers, once checked: it starts at the next ray due and holds the hits and
    /// counts of the part's rays.
    fn check(&mut self, query: &Query, chunk: proto::TraceStreamResponse) -> Result<TraceResult> {
        let Ok(rays) = self.sent_parts.try_recv() else {
            return Err(Error::Protocol(format!(
                "a stream chunk answered ray {} where no part was due",
                chunk.first_ray
            )));
        };
        if chunk.first_ray != self.next_ray as u64 {
            return Err(Error::Protocol(format!(
                "a stream chunk starts at ray {} where ray {} was due",
                chunk.first_ray, self.next_ray
            )));
        }
        let stats = chunk.stats.unwrap_or_default();
        let part = TraceResult::checked(
            query,
            rays * query.ray_format.size(),
            "a stream chunk",
            chunk.hits,
            chunk.counts,
            stats,
        )?;
        self.next_ray += rays;
        self.window.0.add_permits(1);
        Ok(part)
    }

    /// Why the trace ended before every part was answered, if it did: the rays' own error, or parts sent and never
    /// answered.
    fn why_ended(&mut self) -> Option<Error> {
        if let Some(failed) = self.failed.lock().expect("no panic holds it").take() {
            return Some(failed);
        }
        let next_ray = self.next_ray;
        match self.sent_parts.try_recv() {
            Ok(unanswered) => Some(Error::Protocol(format!(
                "the stream ended at ray {next_ray}, before the part of {unanswered} rays from there was answered"
            ))),
            // The sending side is dropped once every part is sent: alive, it still had rays to send.
            Err(TryRecvError::Empty) => {
                Some(Error::Protocol(format!("the stream ended at ray {next_ray}, before every ray was sent")))
            }
            Err(TryRecvError::Disconnected) => None,
        }
    }
}

/// The whole result of a trace of `rays` rays from its `parts`, appended in ray order to `answer` (buffers with room
/// for all the hits and counts); [`Error::Protocol`] where the parts do not add up to it.
async fn concatenate(
    answer: (Vec<u8>, Vec<u8>),
    query: &Query,
    rays: usize,
    mut parts: TraceParts,
) -> Result<TraceResult> {
    let ((mut hits, mut counts), mut stats, mut traced) = (answer, proto::TraceStats::default(), 0);
    while let Some(part) = parts.next().await.transpose()? {
        append_hits(&mut hits, query, traced, &part.hits, part.rays);
        counts.extend_from_slice(&part.counts);
        add_stats(&mut stats, &part.stats);
        traced += part.rays;
    }
    if traced != rays {
        return Err(Error::Protocol(format!("the trace ended after {traced} of {rays} rays")));
    }
    let ray_bytes = rays * query.ray_format.size();
    TraceResult::checked(query, ray_bytes, "the parts together", hits.into(), counts.into(), stats)
}

/// Appends the hits of a part of `part_rays` rays to those of the `rays_before` rays before it in `hits`. Bitmask
/// hits are shifted into place where the rays before end within a byte.
fn append_hits(hits: &mut Vec<u8>, query: &Query, rays_before: usize, part: &[u8], part_rays: usize) {
    if query.hit_format.size().is_some() {
        hits.extend_from_slice(part);
    } else {
        let records_per_ray = query.records_per_ray();
        append_bits(hits, rays_before * records_per_ray, part, part_rays * records_per_ray);
    }
}

/// Appends the first `count` bits of `part` to the first `filled` bits of `bits`, both packed least significant bit
/// first as bitmask hits are; the unused bits of the last byte are left 0, as the contract has them.
pub fn append_bits(bits: &mut Vec<u8>, filled: usize, part: &[u8], count: usize) {
    let shift = filled % 8;
    if shift == 0 {
        bits.extend_from_slice(part);
    } else {
        for &byte in part {
            if let Some(last) = bits.last_mut() {
                *last |= byte << shift;
            }
            bits.push(byte >> (8 - shift));
        }
    }
    let end = filled + count;
    bits.truncate(end.div_ceil(8));
    if let Some(last) = bits.last_mut()
        && !end.is_multiple_of(8)
    {
        *last &= (1 << (end % 8)) - 1;
    }
}

/// The hits and counts that `ray_bytes` of packed rays traced with `query` make; [`Error::InvalidArgument`] where
/// the engine refuses the query or the length (not whole rays).
pub fn output_layout(query: &Query, ray_bytes: usize) -> Result<OutputLayout> {
    query.output_layout(ray_bytes).map_err(|e| Error::InvalidArgument(e.to_string()))
}

/// The hits and counts that `rays` rays (made by a generator, or counted from a file's size) traced with `query`
/// make, as [`output_layout`] checks them; [`Error::InvalidArgument`] where the rays' bytes pass `usize::MAX`.
pub fn output_layout_of_rays(query: &Query, rays: u64) -> Result<OutputLayout> {
    let size = query.ray_format.size();
    let ray_bytes = usize::try_from(rays).ok().and_then(|rays| rays.checked_mul(size)).ok_or_else(|| {
        Error::InvalidArgument(format!("{rays} rays of {size} bytes each: more bytes than this machine addresses"))
    })?;
    output_layout(query, ray_bytes)
}

/// A `TraceBatch` request for inline `rays`, with the hits returned inline.
pub(crate) fn inline_trace(query: proto::TraceQuery, rays: Bytes) -> proto::TraceBatchRequest {
    proto::TraceBatchRequest {
        query: Some(query),
        rays: Some(trace_batch_request::Rays::RaysInline(rays)),
        ..Default::default()
    }
}

/// Rays per stream chunk: as many as keep the chunk's rays, and its hits and counts, within `chunk_bytes`, and at
/// most `max_rays`, rounded down to a multiple of 8 (so bitmask chunks end on a byte and concatenate exactly), at
/// least 8 (or `max_rays` when that is smaller).
pub(crate) fn chunk_rays(query: &Query, chunk_bytes: usize, max_rays: usize) -> usize {
    let hit_bytes = query.hit_format.size().unwrap_or(1) * query.records_per_ray();
    let count_bytes = if query.kind.has_counts() { 4 } else { 0 };
    let per_ray = query.ray_format.size().max(hit_bytes + count_bytes);
    ((chunk_bytes / per_ray).min(max_rays) / 8 * 8).max(8).min(max_rays.max(1))
}

/// Empty buffers with room for the hits and the counts of `layout`; [`Error::Memory`] where they cannot be allocated.
fn reserved_answer(layout: &OutputLayout) -> Result<(Vec<u8>, Vec<u8>)> {
    let rays = layout.rays;
    let hits = reserved(layout.hits, || format!("the hits of {rays} rays"))?;
    Ok((hits, reserved(layout.counts, || format!("the counts of {rays} rays"))?))
}

/// Fails with [`Error::Protocol`] unless the (hits, counts) byte lengths are the expected ones.
fn check_lengths(what: &str, got: (usize, usize), expected: (usize, usize)) -> Result<()> {
    if got != expected {
        return Err(Error::Protocol(format!(
            "{what} returned {} hit and {} count bytes where {} and {} were due",
            got.0, got.1, expected.0, expected.1
        )));
    }
    Ok(())
}

/// Adds a part's statistics (a chunk's, a call's) to a running total, each sum saturating at `u64::MAX`.
pub fn add_stats(total: &mut proto::TraceStats, chunk: &proto::TraceStats) {
    total.rays = total.rays.saturating_add(chunk.rays);
    total.rays_hit = total.rays_hit.saturating_add(chunk.rays_hit);
    total.nodes_visited = total.nodes_visited.saturating_add(chunk.nodes_visited);
    total.triangle_tests = total.triangle_tests.saturating_add(chunk.triangle_tests);
    total.trace_ns = total.trace_ns.saturating_add(chunk.trace_ns);
    total.device_ns = total.device_ns.saturating_add(chunk.device_ns);
}

/// Closes the stream's window when the call ends, so the request stream stops waiting for permits that will
/// never come (the server failed, or the caller gave up).
struct CloseOnDrop(Arc<Semaphore>);

impl Drop for CloseOnDrop {
    fn drop(&mut self) {
        self.0.close();
    }
}

#[cfg(test)]
mod tests {
    use rayd_engine::format::{HitFormat, RayFormat};
    use rayd_engine::query::QueryKind;

    use super::*;

    /// Every part that `chunks` of `format` rays re-cut into parts of `part_rays` make, in order.
    async fn recut(chunks: Vec<Result<Bytes>>, part_rays: usize, format: RayFormat) -> Vec<Result<Bytes>> {
        let part_bytes = part_rays * format.size();
        let (pending, carried, chunks) = (Bytes::new(), BytesMut::new(), futures_util::stream::iter(chunks).boxed());
        let mut recut = Recut { chunks, pending, carried, part_bytes, ray_format: format, ended: false };
        let mut parts = Vec::new();
        while let Some(part) = recut.next().await {
            parts.push(part);
        }
        parts
    }

    #[tokio::test]
    async fn rays_cut_anywhere_come_out_in_whole_parts_and_a_part_a_chunk_holds_is_not_copied() {
        let format = RayFormat::OriginDirection;
        let size = format.size();
        let rays = Bytes::from((0..100 * size).map(|i| i as u8).collect::<Vec<u8>>());
        let cuts = [0, 1, size - 1, 30 * size, 30 * size + 5, 71 * size, 100 * size];
        let chunks = cuts.windows(2).map(|cut| Ok(rays.slice(cut[0]..cut[1]))).collect();
        let parts: Vec<Bytes> = recut(chunks, 16, format).await.into_iter().map(Result::unwrap).collect();
        let sizes: Vec<usize> = parts.iter().map(|part| part.len() / size).collect();
        assert_eq!(sizes, [16, 16, 16, 16, 16, 16, 4], "whole parts but the last");
        assert_eq!(parts.concat(), rays, "the rays in order");

        let parts = recut(vec![Ok(rays.clone())], 16, format).await;
        let starts: Vec<*const u8> = parts.iter().map(|part| part.as_ref().unwrap().as_ptr()).collect();
        assert_eq!(starts[0], rays.as_ptr(), "slices of the chunk");
        assert_eq!(starts[6], rays[96 * size..].as_ptr());

        let parts = recut(vec![Ok(rays.slice(..3 * size)), Ok(rays.slice(3 * size..3 * size + 5))], 16, format).await;
        let error = parts.into_iter().next().expect("a part").unwrap_err().to_string();
        assert_eq!(error, "the rays end within a record: 5 bytes after the last whole 24-byte origin_direction record");
    }

    #[test]
    fn chunks_are_whole_multiples_of_8_rays_sized_by_the_larger_side() {
        let query = Query::closest(RayFormat::OriginDirection, HitFormat::Full);
        assert_eq!(
            chunk_rays(&query, 4 << 20, usize::MAX),
            (4 << 20) / 80 / 8 * 8,
            "80-byte hits outweigh 24-byte rays"
        );
        let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::Bitmask);
        assert_eq!(chunk_rays(&query, 4 << 20, usize::MAX), (4 << 20) / 32);
        let query =
            Query { kind: QueryKind::All, max_hits_per_ray: 1000, ..Query::closest(RayFormat::Full, HitFormat::Full) };
        assert_eq!(chunk_rays(&query, 4 << 20, usize::MAX) % 8, 0);
        assert_eq!(chunk_rays(&query, 4 << 20, usize::MAX), (4 << 20) / 80004 / 8 * 8);
        assert_eq!(chunk_rays(&query, 1000, usize::MAX), 8, "never fewer than 8 rays");
        assert_eq!(chunk_rays(&query, 4 << 20, 20), 16, "the server's max_rays_per_batch caps chunks");
        assert_eq!(chunk_rays(&query, 4 << 20, 5), 5, "below 8 rays only when the server allows fewer");
    }

    #[test]
    fn rays_whose_bytes_pass_the_address_space_are_invalid_arguments_not_a_saturated_length() {
        let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
        let error = output_layout_of_rays(&query, u64::MAX / 8).unwrap_err();
        assert!(matches!(error, Error::InvalidArgument(_)), "{error:?}");
        assert!(error.to_string().contains("rays of 24 bytes each: more bytes than this machine"), "{error}");
        assert_eq!(output_layout_of_rays(&query, 1000).unwrap().hits, 4000);
    }

    /// A bitmask result of one ray a flag of `hits`, as a part of a trace.
    fn bitmask_part(hits: &[bool]) -> TraceResult {
        let mut packed = vec![0u8; hits.len().div_ceil(8)];
        for (ray, _) in hits.iter().enumerate().filter(|(_, hit)| **hit) {
            packed[ray / 8] |= 1 << (ray % 8);
        }
        TraceResult {
            query: Query::closest(RayFormat::OriginDirection, HitFormat::Bitmask),
            rays: hits.len(),
            hits: packed.into(),
            counts: Bytes::new(),
            stats: proto::TraceStats::default(),
        }
    }

    /// `parts` as the parts of a trace.
    fn as_parts(parts: Vec<TraceResult>) -> TraceParts {
        futures_util::stream::iter(parts.into_iter().map(Ok)).boxed()
    }

    #[tokio::test]
    async fn bitmask_parts_of_fewer_than_8_rays_are_joined_bit_by_bit() {
        let hits: Vec<bool> = (0..13).map(|ray| ray % 3 == 0 || ray == 4).collect();
        let query = Query::closest(RayFormat::OriginDirection, HitFormat::Bitmask);
        let parts = as_parts(hits.chunks(5).map(bitmask_part).collect());
        let whole = concatenate((Vec::new(), Vec::new()), &query, hits.len(), parts).await.unwrap();
        assert_eq!(whole.hits(), bitmask_part(&hits).hits());
        assert_eq!(whole.hit_view().iter().map(|hit| hit.is_hit()).collect::<Vec<_>>(), hits);
    }

    #[tokio::test]
    async fn parts_whose_hits_do_not_make_the_whole_are_a_protocol_error() {
        let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
        let stats = proto::TraceStats::default();
        let short = TraceResult { query, rays: 2, hits: Bytes::from_static(&[0; 4]), counts: Bytes::new(), stats };
        let error = concatenate((Vec::new(), Vec::new()), &query, 2, as_parts(vec![short])).await.unwrap_err();
        assert!(matches!(error, Error::Protocol(_)), "{error}");
    }

    #[test]
    fn statistics_summed_past_u64_saturate() {
        let most = proto::TraceStats {
            rays: u64::MAX,
            rays_hit: u64::MAX,
            nodes_visited: u64::MAX,
            triangle_tests: u64::MAX,
            trace_ns: u64::MAX,
            device_ns: u64::MAX,
        };
        let mut total = most;
        add_stats(&mut total, &most);
        assert_eq!(total, most);
        // Below the top, each field is summed.
        let few = |n| proto::TraceStats {
            rays: n,
            rays_hit: n + 1,
            nodes_visited: n + 2,
            triangle_tests: n + 3,
            trace_ns: n + 4,
            device_ns: n + 5,
        };
        let mut total = few(2);
        add_stats(&mut total, &few(3));
        assert_eq!(
            total,
            proto::TraceStats {
                rays: 5,
                rays_hit: 7,
                nodes_visited: 9,
                triangle_tests: 11,
                trace_ns: 13,
                device_ns: 15
            }
        );
    }

    #[test]
    fn counts_are_read_per_ray_and_absent_without_them() {
        let result = TraceResult {
            query: Query::closest(RayFormat::OriginDirection, HitFormat::T),
            rays: 2,
            hits: Bytes::from([1.0f32, -1.0].iter().flat_map(|t| t.to_le_bytes()).collect::<Vec<_>>()),
            counts: Bytes::from([3u32, 0].iter().flat_map(|c| c.to_le_bytes()).collect::<Vec<_>>()),
            stats: proto::TraceStats::default(),
        };
        assert_eq!((result.count(0), result.count(1), result.count(2)), (Some(3), Some(0), None));
        assert!(result.hit_view().is_hit(0) && !result.hit_view().is_hit(1));
    }
}
