//! Reduced traces: the server sums the hits up where it traces them and sends only the result (an image, a
//! point cloud, counts …), so neither rays nor hits cross the network.

use bytes::Bytes;
use rayd_engine::query::Query;
use rayd_engine::raygen::Generator;
use rayd_engine::reduce::Reduction;
use rayd_proto as proto;
use rayd_proto::trace_batch_request::Rays;

use crate::client::Client;
use crate::convert::{generator_to_proto, reduction_to_proto, trace_query};
use crate::error::{Error, Result};

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

impl ReducedTrace {
    /// The reduction a `TraceBatch` answer (or a stream's trace operation) carries; an error when it has none.
    pub(crate) fn from_response(response: proto::TraceBatchResponse) -> std::result::Result<ReducedTrace, String> {
        let reduced = response.reduced.ok_or("a reduced trace answered without its reduction")?;
        Ok(ReducedTrace { data: reduced.data, dropped: reduced.dropped, stats: response.stats.unwrap_or_default() })
    }
}
