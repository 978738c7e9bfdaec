//! Secondary rays made by the server from an earlier trace's hits that stayed on the server (a hits buffer): the
//! primary rays are a generator's or a rays buffer's, so neither they, their hits nor the new rays cross the network
//! (or the caller's own, sent with the request). Hits and primary rays too large to go with a request go through
//! temporary buffers, and the rays are traced in ranges whose hits fit in a message.

use bytes::Bytes;
use rayd_engine::format::RayFormat;
use rayd_engine::query::Query;
use rayd_engine::raygen::{Bounce, Generator, Primary, Secondary};
use rayd_proto as proto;

use crate::client::Client;
use crate::convert::{bounce_to_proto, generated_ray_count, generator_to_proto, ray_format_to_proto};
use crate::error::{Error, Result};
use crate::trace::{TraceParts, TraceResult};

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
    /// Traces `secondary` rays (made by the server) against the accel called `accel`; the hits come back as for any
    /// trace, one record a primary ray. One `TraceBatch` call when the hits fit in
    /// [`ClientOptions::batch_limit_bytes`](crate::ClientOptions::batch_limit_bytes), else one per range of rays
    /// whose hits do, as in [`Client::trace_generated`]. Inline primary rays larger than `batch_limit_bytes` are
    /// uploaded first as a temporary buffer of the accel's scene (deleted again whatever the outcome), so that the
    /// calls do not carry them; primary rays in a buffer are counted by its size (one `ListBuffers` call).
    pub async fn trace_secondary(&self, accel: &str, query: &Query, secondary: &SecondaryRays) -> Result<TraceResult> {
        let node = self.for_scene(accel);
        let total = node.primary_ray_count(&secondary.primary).await?;
        match &secondary.primary {
            PrimaryRays::Inline(rays, format) if rays.len() > self.options.batch_limit_bytes => {
                node.with_temporary_buffer(rays.clone(), |buffer| {
                    let uploaded = SecondaryRays { primary: PrimaryRays::Buffer(buffer, *format), ..secondary.clone() };
                    node.trace_in_ranges(accel, query, uploaded.to_proto(), total)
                })
                .await
            }
            _ => node.trace_in_ranges(accel, query, secondary.to_proto(), total).await,
        }
    }

    /// Traces `secondary` rays as [`Client::trace_secondary`] does, but yields each call's result as it comes back
    /// instead of holding the hits whole. Nothing is uploaded: inline primary rays go with every call, so send large
    /// ones as a buffer ([`Client::upload_buffer_parts`] uploads a file a part at a time).
    pub async fn trace_secondary_parts(
        &self,
        accel: &str,
        query: &Query,
        secondary: &SecondaryRays,
    ) -> Result<TraceParts> {
        let node = self.for_scene(accel);
        let total = node.primary_ray_count(&secondary.primary).await?;
        node.generated_parts(accel, query, secondary.to_proto(), total)
    }

    /// Traces the engine's `secondary` rays, whose hits (and packed primary rays) are too large to go with every
    /// call: the hits as a temporary buffer of the accel's scene, deleted again whatever the outcome, the primary
    /// rays as [`Client::trace_secondary`] sends them.
    pub(crate) async fn trace_uploaded_secondary(
        &self,
        accel: &str,
        query: &Query,
        secondary: &Secondary,
    ) -> Result<TraceResult> {
        let node = self.for_scene(accel);
        let primary = match &secondary.primary {
            Primary::Packed(format, rays) => PrimaryRays::Inline(rays.clone(), *format),
            Primary::Generated(generator) => PrimaryRays::Generated((**generator).clone()),
        };
        node.with_temporary_buffer(secondary.hits.clone(), |hits_buffer| async {
            let uploaded = SecondaryRays { primary, hits_buffer, bounce: secondary.bounce, offset: secondary.offset };
            node.trace_secondary(accel, query, &uploaded).await
        })
        .await
    }

    /// The number of `primary` rays; those in a buffer by its size, as `ListBuffers` reports it.
    async fn primary_ray_count(&self, primary: &PrimaryRays) -> Result<usize> {
        Ok(match primary {
            PrimaryRays::Generated(generator) => usize::try_from(generated_ray_count(generator)).unwrap_or(usize::MAX),
            PrimaryRays::Inline(rays, format) => rays.len() / format.size(),
            PrimaryRays::Buffer(buffer, format) => self.buffer_bytes(buffer).await? / format.size(),
        })
    }

    /// The size of the buffer `buffer` names by id or by name, from `ListBuffers`.
    async fn buffer_bytes(&self, buffer: &proto::BufferRef) -> Result<usize> {
        use proto::buffer_ref::Ref;
        let buffers = self.buffers().await?;
        let (found, wanted) = match &buffer.r#ref {
            Some(Ref::Id(id)) => (buffers.iter().find(|info| info.id == *id), format!("with id {id:?}")),
            Some(Ref::Name(name)) => (buffers.iter().find(|info| info.name == *name), format!("called {name:?}")),
            _ => return Err(Error::InvalidArgument("primary_rays_buffer: name the buffer by id or by name".into())),
        };
        let missing = || Error::Status(tonic::Status::not_found(format!("primary_rays_buffer: no buffer {wanted}")));
        Ok(usize::try_from(found.ok_or_else(missing)?.size_bytes).unwrap_or(usize::MAX))
    }
}

/// Bytes that `secondary` carries in a request: its hits, and its primary rays when they are packed.
pub(crate) fn inline_bytes(secondary: &Secondary) -> usize {
    let primary = match &secondary.primary {
        Primary::Packed(_, rays) => rays.len(),
        Primary::Generated(_) => 0,
    };
    secondary.hits.len() + primary
}
