//! Reduced traces: the server sums the hits up where it traces them and sends only the result (an image, a
//! point cloud, counts …), so neither rays nor hits cross the network.

use bytes::Bytes;
use futures_util::{Stream, StreamExt};
use rayd_engine::query::Query;
use rayd_engine::raygen::Generator;
use rayd_engine::reduce::{PixelEncoding, Reduction};
use rayd_proto as proto;
use rayd_proto::trace_batch_request::Rays;

use crate::client::Client;
use crate::convert::{generated_ray_count, generator_to_proto, reduction_to_proto, trace_query};
use crate::error::{Error, Result};
use crate::memory::{append, reserved};
use crate::trace::add_stats;

/// What a reduced trace returned.
#[derive(Debug, Clone)]
pub struct ReducedTrace {
    /// The reduction's result, laid out as its [`Reduction`] variant documents.
    pub data: Bytes,
    /// Items left out (points outside an integer point cloud's range).
    pub dropped: u64,
    /// What the server did.
    pub stats: proto::TraceStats,
}

impl Client {
    /// Traces the rays of `generator` (made by the server) against the accel called `accel` and returns only
    /// `reduction` of their hits, in one `TraceBatch` call.
    pub async fn trace_generated_reduced(
        &self,
        accel: &str,
        query: &Query,
        generator: &Generator,
        reduction: &Reduction,
    ) -> Result<ReducedTrace> {
        self.trace_reduced_call(accel, query, Rays::RaysGenerator(generator_to_proto(generator)), reduction).await
    }

    /// [`Client::trace_generated_reduced`] for answers of any size: an image (not PNG, its width and rays a pixel
    /// given) or a point cloud (without ray indices) whose answer could pass
    /// [`ClientOptions::batch_limit_bytes`](crate::ClientOptions::batch_limit_bytes) is traced in one call per range
    /// of rays whose answer cannot (whole rows of the image), `stream_window` of them at once as in
    /// [`Client::trace_generated`], and the ranges' answers one after another are the whole's. Any other reduction
    /// goes in one call.
    pub async fn trace_generated_reduced_in_ranges(
        &self,
        accel: &str,
        query: &Query,
        generator: &Generator,
        reduction: &Reduction,
    ) -> Result<ReducedTrace> {
        let total = usize::try_from(generated_ray_count(generator)).unwrap_or(usize::MAX);
        match self.rays_per_reduced_call(query, reduction) {
            Some(per_call) if per_call < total => {
                let generator = generator_to_proto(generator);
                self.trace_reduced_in_ranges(accel, query, generator, reduction, total, per_call).await
            }
            _ => self.trace_generated_reduced(accel, query, generator, reduction).await,
        }
    }

    /// Traces packed `rays` against the accel called `accel` and returns only `reduction` of their hits, in one
    /// `TraceBatch` call.
    pub async fn trace_reduced(
        &self,
        accel: &str,
        query: &Query,
        rays: Bytes,
        reduction: &Reduction,
    ) -> Result<ReducedTrace> {
        self.trace_reduced_call(accel, query, Rays::RaysInline(rays), reduction).await
    }

    /// The most rays a call of a trace reduced by `reduction` may take for its answer to fit in a batch: whole rows
    /// of an image not compressed whose width and rays a pixel are given (at least one row), any number of rays of a
    /// point cloud without ray indices; `None` for a reduction whose ranges' answers, one after another, are not
    /// the whole's (or an image whose rows the server takes from the camera).
    fn rays_per_reduced_call(&self, query: &Query, reduction: &Reduction) -> Option<usize> {
        let (unit_rays, unit_bytes) = match reduction {
            Reduction::Image(image)
                if image.encoding != PixelEncoding::Png && image.width > 0 && image.rays_per_pixel > 0 =>
            {
                (image.width as usize * image.rays_per_pixel as usize, image.width as usize * image.pixel_bytes())
            }
            Reduction::PointCloud(cloud) if !cloud.ray_indices => (1, query.records_per_ray() * cloud.record_bytes()),
            _ => return None,
        };
        let units = (self.options.batch_limit_bytes / unit_bytes.max(1))
            .min(self.options.max_rays_per_call / unit_rays.max(1))
            .max(1);
        Some(units * unit_rays)
    }

    /// Traces the `total` rays of `generator` reduced by `reduction` in ranges of `per_call` rays, and joins their
    /// answers in ray order.
    async fn trace_reduced_in_ranges(
        &self,
        accel: &str,
        query: &Query,
        generator: proto::RayGenerator,
        reduction: &Reduction,
        total: usize,
        per_call: usize,
    ) -> Result<ReducedTrace> {
        let what = || format!("the reduction of {total} rays");
        let known_bytes = reduction.answer_bytes(query, total as u64).unwrap_or(0);
        let data = reserved(usize::try_from(known_bytes).unwrap_or(usize::MAX), what)?;
        let answers = self.range_answers(accel, query, generator, Some(reduction_to_proto(reduction)), total, per_call);
        joined(data, answers, what).await
    }

    /// One reduced `TraceBatch` call.
    async fn trace_reduced_call(
        &self,
        accel: &str,
        query: &Query,
        rays: Rays,
        reduction: &Reduction,
    ) -> Result<ReducedTrace> {
        let request = proto::TraceBatchRequest {
            query: Some(trace_query(accel, query)),
            rays: Some(rays),
            reduction: Some(reduction_to_proto(reduction)),
            ..Default::default()
        };
        let response = self.rpc_for(accel).trace_batch(request).await?.into_inner();
        ReducedTrace::from_response(response).map_err(Error::Protocol)
    }
}

/// The reductions of consecutive ranges of rays that `answers` carries, as one: their data one after another (after
/// what `data` holds, named by `what`), their dropped items and statistics summed (saturating at `u64::MAX`).
async fn joined(
    mut data: Vec<u8>,
    mut answers: impl Stream<Item = Result<(usize, proto::TraceBatchResponse)>> + Unpin,
    what: impl Fn() -> String,
) -> Result<ReducedTrace> {
    let (mut dropped, mut stats) = (0u64, proto::TraceStats::default());
    while let Some((_, response)) = answers.next().await.transpose()? {
        let part = ReducedTrace::from_response(response).map_err(Error::Protocol)?;
        append(&mut data, &part.data, &what)?;
        dropped = dropped.saturating_add(part.dropped);
        add_stats(&mut stats, &part.stats);
    }
    Ok(ReducedTrace { data: data.into(), dropped, stats })
}

impl ReducedTrace {
    /// The reduction a `TraceBatch` answer (or a stream's trace operation) carries; an error when it has none.
    pub(crate) fn from_response(response: proto::TraceBatchResponse) -> std::result::Result<ReducedTrace, String> {
        let reduced = response.reduced.ok_or("a reduced trace answered without its reduction")?;
        Ok(ReducedTrace { data: reduced.data, dropped: reduced.dropped, stats: response.stats.unwrap_or_default() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A range's answer of `data` with `dropped` items left out.
    fn answer(data: &'static [u8], dropped: u64) -> Result<(usize, proto::TraceBatchResponse)> {
        let reduced = proto::ReducedHits { data: Bytes::from_static(data), dropped };
        Ok((1, proto::TraceBatchResponse { reduced: Some(reduced), ..Default::default() }))
    }

    #[tokio::test]
    async fn ranges_are_joined_in_order_and_their_dropped_items_summed_saturating() {
        let answers = futures_util::stream::iter([answer(b"ab", 3), answer(b"c", u64::MAX)]);
        let whole = joined(b"_".to_vec(), answers, || unreachable!("4 bytes fit")).await.unwrap();
        assert_eq!((whole.data.as_ref(), whole.dropped), (b"_abc".as_ref(), u64::MAX));
    }
}
