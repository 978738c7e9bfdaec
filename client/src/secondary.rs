//! Secondary rays made by the server from an earlier trace's hits that stayed on the server (a hits buffer): the
//! primary rays are a generator's or a rays buffer's, so neither they, their hits nor the new rays cross the network
//! (or the caller's own, sent with the request).

use bytes::Bytes;
use rayd_engine::format::RayFormat;
use rayd_engine::query::Query;
use rayd_engine::raygen::{Bounce, Generator};
use rayd_proto as proto;
use rayd_proto::trace_batch_request::Rays;

use crate::client::Client;
use crate::convert::{bounce_to_proto, generator_to_proto, ray_format_to_proto, trace_query};
use crate::error::Result;
use crate::trace::TraceResult;

/// Where the primary rays of [`SecondaryRays`] are.
#[derive(Debug, Clone, PartialEq)]
pub enum PrimaryRays {
    /// Made by this generator (the one the earlier trace used).
    Generated(Generator),
    /// Packed in a server-side buffer, in this format.
    Buffer(proto::BufferRef, RayFormat),
    /// Packed in this format and sent with the request (the caller's own rays, e.g. a ray file).
    Inline(Bytes, RayFormat),
}

/// Rays that continue an earlier trace from its hits, which a `closest` or `any` trace wrote to a server-side buffer
/// in the `Full` hit format (see `SecondaryRays` in the contract for the rules).
#[derive(Debug, Clone, PartialEq)]
pub struct SecondaryRays {
    /// The earlier trace's rays.
    pub primary: PrimaryRays,
    /// The buffer its hits were written to.
    pub hits_buffer: proto::BufferRef,
    /// Reflect, or head for a point light.
    pub bounce: Bounce,
    /// World units that origins move off the surface.
    pub offset: f32,
}

impl SecondaryRays {
    /// The contract's generator for these rays.
    pub fn to_proto(&self) -> proto::RayGenerator {
        use proto::secondary_rays::{Primary as P, PrimaryHits};
        let (primary, format) = match &self.primary {
            PrimaryRays::Generated(generator) => (P::PrimaryGenerator(Box::new(generator_to_proto(generator))), 0),
            PrimaryRays::Buffer(buffer, format) => {
                (P::PrimaryRaysBuffer(buffer.clone()), ray_format_to_proto(*format).into())
            }
            PrimaryRays::Inline(rays, format) => {
                (P::PrimaryRaysInline(rays.clone()), ray_format_to_proto(*format).into())
            }
        };
        let secondary = proto::SecondaryRays {
            primary: Some(primary),
            primary_ray_format: format,
            primary_hits: Some(PrimaryHits::PrimaryHitsBuffer(self.hits_buffer.clone())),
            bounce: Some(bounce_to_proto(self.bounce)),
            offset: self.offset,
        };
        proto::RayGenerator {
            kind: Some(proto::ray_generator::Kind::Secondary(Box::new(secondary))),
            ..Default::default()
        }
    }
}

impl Client {
    /// Traces `secondary` rays (made by the server) against the accel called `accel`, in one `TraceBatch` call; the
    /// hits come back as for any trace, one record a primary ray.
    pub async fn trace_secondary(&self, accel: &str, query: &Query, secondary: &SecondaryRays) -> Result<TraceResult> {
        let request = proto::TraceBatchRequest {
            query: Some(trace_query(accel, query)),
            rays: Some(Rays::RaysGenerator(secondary.to_proto())),
            ..Default::default()
        };
        let response = self.rpc_for(accel).trace_batch(request).await?.into_inner();
        let rays = response.stats.as_ref().map_or(0, |s| s.rays) as usize;
        TraceResult::from_batch(query, rays * query.ray_format.size(), response)
    }
}
