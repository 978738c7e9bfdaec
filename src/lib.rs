//! rayd's engine: triangle acceleration structures and OptiX-Prime-style batch ray queries.
//!
//! A [`Context`] on a [`Device`] builds accels from [`geometry::BuildInput`]s and traces packed ray buffers
//! ([`format::RayFormat`]) into packed hit buffers ([`format::HitFormat`]) with a [`query::Query`]. Every
//! backend implements [`backend::Backend`] and shares the formats, the intersection tests ([`intersect`]) and the
//! per-ray hit collection ([`query`]), so results are identical in convention on all of them.
//!
//! ```
//! use rayd_engine::{Context, Device, accel::BuildOptions, format::*, geometry::*, query::*};
//! let vertices: Vec<u8> = [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0].iter().flat_map(|v| v.to_le_bytes()).collect();
//! let indices: Vec<u8> = [0u32, 1, 2].iter().flat_map(|v| v.to_le_bytes()).collect();
//! let context = Context::new(Device::cpu());
//! let accel = context.build_accel(&[BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices))], &BuildOptions::default())?;
//! let mut rays = vec![0u8; 32];
//! RayFormat::OriginTminDirectionTmax.encode(&Ray { origin: [0.25, 0.25, 1.0].into(), direction: [0.0, 0.0, -1.0].into(), ..Ray::default() }, &mut rays);
//! let mut hits = vec![0u8; 8];
//! let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriid);
//! context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] })?;
//! assert_eq!(f32::from_le_bytes(hits[0..4].try_into().unwrap()), 1.0);
//! # Ok::<(), rayd_engine::Error>(())
//! ```

pub mod accel;
pub mod backend;
mod context;
mod cpu_features;
pub mod error;
pub mod format;
pub mod geometry;
pub mod intersect;
pub mod mesh;
pub mod oracle;
pub mod query;
pub mod raygen;
pub mod reduce;
pub mod serialize;

pub use context::{Accel, AccelHandle, BufferHandle, Context, Device};
pub use error::{Error, ErrorKind, Result};
/// The vector types of the public API.
pub use glam;
