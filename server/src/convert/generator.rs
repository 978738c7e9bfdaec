//! Ray generators of the contract into the engine's.

use std::ops::Range;

use bytes::Bytes;
use rayd_engine::glam::Vec3;
use rayd_engine::raygen::{
    Bounce, Camera, Generator, Lidar, Orthographic, PixelSampling, Primary, Secondary, SphereSampling,
};
use rayd_proto as pb;

use super::ray_format;
use crate::error::{ServiceError, ServiceResult};

/// `v`, or INVALID_ARGUMENT naming `field` when it is missing.
fn vec3(v: Option<&pb::Vec3>, field: &str) -> ServiceResult<Vec3> {
    let v = v.ok_or_else(|| ServiceError::invalid(format!("generator.{field}"), "required"))?;
    Ok(Vec3::new(v.x, v.y, v.z))
}

/// Packed little-endian float triples, 12 bytes each.
fn vec3s(bytes: &Bytes, field: &str) -> ServiceResult<Vec<Vec3>> {
    if !bytes.len().is_multiple_of(12) {
        return Err(ServiceError::invalid(
            format!("generator.{field}"),
            format!("{} bytes is not a whole number of 12-byte float32 x, y, z triples", bytes.len()),
        ));
    }
    let f = |b: &[u8]| f32::from_le_bytes(b.try_into().expect("4 bytes"));
    Ok(bytes.chunks_exact(12).map(|c| Vec3::new(f(&c[0..4]), f(&c[4..8]), f(&c[8..12]))).collect())
}

fn sampling(s: Option<&pb::PixelSampling>) -> PixelSampling {
    let s = s.cloned().unwrap_or_default();
    PixelSampling { samples: s.samples_per_pixel.max(1), jitter_seed: s.jitter_seed }
}

/// The bytes of a server-side buffer a generator names, by reference and field (the caller's tenant's buffers).
pub type BufferBytes<'a> = dyn Fn(&pb::BufferRef, &str) -> ServiceResult<Bytes> + 'a;

/// The engine's generator for `g`, checked (INVALID_ARGUMENT naming the field), and the range of its rays to trace;
/// `buffer` reads the buffers a secondary generator names.
pub fn generator(g: &pb::RayGenerator, buffer: &BufferBytes) -> ServiceResult<(Generator, Range<u64>)> {
    let generator = kind(g, buffer)?;
    generator.check()?;
    let all = generator.count();
    let end = if g.ray_count == 0 { all } else { g.first_ray.saturating_add(g.ray_count) };
    if g.first_ray >= all || end > all {
        return Err(ServiceError::invalid(
            "generator.first_ray",
            format!("rays {} .. {end} are not all among the generator's {all}", g.first_ray),
        ));
    }
    Ok((generator, g.first_ray..end))
}

/// The engine's generator of `g`'s kind, not yet checked.
fn kind(g: &pb::RayGenerator, buffer: &BufferBytes) -> ServiceResult<Generator> {
    use pb::ray_generator::Kind;
    Ok(match g.kind.as_ref().ok_or_else(|| ServiceError::invalid("generator", "a kind is required"))? {
        Kind::Pinhole(c) => Generator::Pinhole(
            Camera {
                eye: vec3(c.eye.as_ref(), "eye")?,
                target: vec3(c.target.as_ref(), "target")?,
                up: vec3(c.up.as_ref(), "up")?,
                fov_y_degrees: c.fov_y_degrees,
                width: c.width,
                height: c.height,
            },
            sampling(c.sampling.as_ref()),
        ),
        Kind::Orthographic(c) => Generator::Orthographic(
            Orthographic {
                eye: vec3(c.eye.as_ref(), "eye")?,
                target: vec3(c.target.as_ref(), "target")?,
                up: vec3(c.up.as_ref(), "up")?,
                view_height: c.view_height,
                width: c.width,
                height: c.height,
            },
            sampling(c.sampling.as_ref()),
        ),
        Kind::Lidar(l) => Generator::Lidar(Lidar {
            origin: vec3(l.origin.as_ref(), "origin")?,
            forward: vec3(l.forward.as_ref(), "forward")?,
            up: vec3(l.up.as_ref(), "up")?,
            elevations_degrees: l.elevations_degrees.clone(),
            steps: l.steps,
            min_range: l.min_range,
            max_range: l.max_range,
            time: (l.time_begin, l.time_end),
        }),
        Kind::Sphere(s) => Generator::Sphere(SphereSampling {
            points: vec3s(&s.points, "points")?,
            normals: vec3s(&s.normals, "normals")?,
            samples: s.samples,
            min_distance: s.min_distance,
            max_distance: s.max_distance,
            seed: s.seed,
        }),
        Kind::Secondary(s) => Generator::Secondary(secondary(s, buffer)?),
    })
}

/// The engine's secondary rays for `s`, their buffers read.
fn secondary(s: &pb::SecondaryRays, buffer: &BufferBytes) -> ServiceResult<Secondary> {
    use pb::secondary_rays::{Bounce as B, Primary as P, PrimaryHits as H};
    let field = |name: &str| format!("generator.secondary.{name}");
    let packed = |bytes| -> ServiceResult<Primary> {
        Ok(Primary::Packed(ray_format(s.primary_ray_format, &field("primary_ray_format"))?, bytes))
    };
    let primary = match s.primary.as_ref() {
        Some(P::PrimaryRaysInline(bytes)) => packed(bytes.clone())?,
        Some(P::PrimaryRaysBuffer(reference)) => packed(buffer(reference, &field("primary_rays_buffer"))?)?,
        Some(P::PrimaryGenerator(generator)) => Primary::Generated(Box::new(kind(generator, buffer)?)),
        None => {
            return Err(ServiceError::invalid(
                field("primary"),
                "primary rays (inline, buffer or generator) are required",
            ));
        }
    };
    let hits = match s.primary_hits.as_ref() {
        Some(H::PrimaryHitsInline(bytes)) => bytes.clone(),
        Some(H::PrimaryHitsBuffer(reference)) => buffer(reference, &field("primary_hits_buffer"))?,
        None => return Err(ServiceError::invalid(field("primary_hits"), "the primary rays' hits are required")),
    };
    let bounce = match s.bounce.as_ref() {
        Some(B::Reflect(_)) => Bounce::Reflect,
        Some(B::TowardsLight(light)) => Bounce::TowardsLight(Vec3::new(light.x, light.y, light.z)),
        None => return Err(ServiceError::invalid(field("bounce"), "reflect or towards_light is required")),
    };
    Ok(Secondary { primary, hits, bounce, offset: s.offset })
}
