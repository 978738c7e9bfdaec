//! Tracing: one `TraceBatch` call when the rays and hits fit in a message, otherwise a `TraceStream` of ray
//! chunks with a bounded window, reassembled in order. Callers get the same [`TraceResult`] either way.

use std::sync::Arc;

use bytes::Bytes;
use futures_util::{Stream, StreamExt};
use rayd_engine::format::RayFormat;
use rayd_engine::query::{OutputLayout, Query};
use rayd_engine::raygen::Generator;
use rayd_proto as proto;
use rayd_proto::{trace_batch_request, trace_stream_request};
use tokio::sync::Semaphore;

use crate::client::Client;
use crate::convert::{generator_to_proto, trace_query};
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
        let layout = query.output_layout(rays).map_err(|e| Error::InvalidArgument(e.to_string()))?;
        check_lengths("the batch", (response.hits.len(), response.counts.len()), (layout.hits, layout.counts))?;
        Ok(TraceResult {
            query: *query,
            rays: layout.rays,
            hits: response.hits,
            counts: response.counts,
            stats: response.stats.unwrap_or_default(),
        })
    }

    /// Ray `ray`'s count (hits found for `all`, crossings for `count`), or `None` when the query has no counts.
    pub fn count(&self, ray: usize) -> Option<u32> {
        let bytes = self.counts.get(4 * ray..4 * ray + 4)?;
        Some(u32::from_le_bytes(bytes.try_into().expect("4 bytes")))
    }
}

impl Client {
    /// Traces packed `rays` (whole records of `query.ray_format`) against the accel called `accel`. Goes through
    /// `TraceBatch` when the rays and the expected hits and counts each fit in
    /// [`ClientOptions::batch_limit_bytes`](crate::ClientOptions::batch_limit_bytes), else through `TraceStream`.
    pub async fn trace(&self, accel: &str, query: &Query, rays: Bytes) -> Result<TraceResult> {
        let layout = query.output_layout(rays.len()).map_err(|e| Error::InvalidArgument(e.to_string()))?;
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
    /// `query.ray_format` (a format with time keeps a lidar's times). One `TraceBatch` call when the hits fit in
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
        let total = usize::try_from(generator.count()).unwrap_or(usize::MAX);
        self.trace_in_ranges(accel, query, generator_to_proto(generator), total).await
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
        let ray_size = query.ray_format.size();
        let layout =
            query.output_layout(total.saturating_mul(ray_size)).map_err(|e| Error::InvalidArgument(e.to_string()))?;
        let (limit, max_rays) = (self.options.batch_limit_bytes, self.options.max_rays_per_call);
        let per_call = if layout.hits + layout.counts <= limit && total <= max_rays {
            total
        } else {
            // Generated rays cost nothing on the wire: only the hits and counts must fit.
            chunk_rays(&Query { ray_format: RayFormat::OriginDirection, ..*query }, limit, max_rays)
        };
        let mut parts = self.range_answers(accel, query, generator, None, total, per_call).map(|answer| {
            answer.and_then(|(rays, response)| TraceResult::from_batch(query, rays * ray_size, response))
        });
        if per_call >= total {
            // One call (none for no rays): its answer's buffers as they are.
            return parts.next().await.unwrap_or_else(|| TraceResult::from_batch(query, 0, Default::default()));
        }
        let (mut hits, mut counts) = reserved_answer(&layout)?;
        let mut stats = proto::TraceStats::default();
        while let Some(part) = parts.next().await.transpose()? {
            hits.extend_from_slice(&part.hits);
            counts.extend_from_slice(&part.counts);
            add_stats(&mut stats, &part.stats);
        }
        Ok(TraceResult { query: *query, rays: total, hits: hits.into(), counts: counts.into(), stats })
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

    /// A `TraceStream` of chunks of [`chunk_rays`] rays (never more bytes than a batch), at most `stream_window` of
    /// them unanswered.
    async fn trace_stream(
        &self,
        accel: &str,
        query: &Query,
        rays: Bytes,
        layout: &OutputLayout,
    ) -> Result<TraceResult> {
        let (mut hits, mut counts) = reserved_answer(layout)?;
        let chunk_bytes = self.options.stream_chunk_bytes.min(self.options.batch_limit_bytes);
        let chunk_rays = chunk_rays(query, chunk_bytes, self.options.max_rays_per_call);
        let chunk_bytes = chunk_rays * query.ray_format.size();
        let chunks: Vec<Bytes> =
            (0..rays.len()).step_by(chunk_bytes).map(|s| rays.slice(s..(s + chunk_bytes).min(rays.len()))).collect();
        let window = CloseOnDrop(Arc::new(Semaphore::new(self.options.stream_window.max(1))));
        let first = trace_stream_request::Part::Query(trace_query(accel, query));
        let paced =
            futures_util::stream::unfold((chunks.into_iter(), window.0.clone()), |(mut chunks, window)| async {
                let chunk = chunks.next()?;
                window.acquire().await.ok()?.forget();
                Some((trace_stream_request::Part::Rays(chunk), (chunks, window)))
            });
        let requests = futures_util::stream::once(async { first })
            .chain(paced)
            .map(|part| proto::TraceStreamRequest { part: Some(part) });
        let mut responses = self.rpc_for(accel).trace_stream(requests).await?.into_inner();

        let mut stats = proto::TraceStats::default();
        let mut next_ray = 0;
        while let Some(chunk) = responses.message().await? {
            if chunk.first_ray != next_ray as u64 || next_ray >= layout.rays {
                return Err(Error::Protocol(format!(
                    "a stream chunk starts at ray {} where ray {next_ray} of {} was due",
                    chunk.first_ray, layout.rays
                )));
            }
            let n = chunk_rays.min(layout.rays - next_ray);
            let expected = query.output_layout(n * query.ray_format.size()).expect("checked for the whole batch");
            check_lengths("a stream chunk", (chunk.hits.len(), chunk.counts.len()), (expected.hits, expected.counts))?;
            hits.extend_from_slice(&chunk.hits);
            counts.extend_from_slice(&chunk.counts);
            add_stats(&mut stats, &chunk.stats.unwrap_or_default());
            next_ray += n;
            window.0.add_permits(1);
        }
        if next_ray != layout.rays {
            return Err(Error::Protocol(format!("the stream ended after {next_ray} of {} rays", layout.rays)));
        }
        Ok(TraceResult { query: *query, rays: layout.rays, hits: hits.into(), counts: counts.into(), stats })
    }
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

/// Adds a chunk's statistics to the running total.
pub(crate) fn add_stats(total: &mut proto::TraceStats, chunk: &proto::TraceStats) {
    total.rays += chunk.rays;
    total.rays_hit += chunk.rays_hit;
    total.nodes_visited += chunk.nodes_visited;
    total.triangle_tests += chunk.triangle_tests;
    total.trace_ns += chunk.trace_ns;
    total.device_ns += chunk.device_ns;
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
