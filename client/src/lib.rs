//! rayd's client: the mirror of the `rayd.v1` contract, and the library behind `rayctl`.
//!
//! A [`Client`] connects once (with an optional bearer token) and then lists devices, uploads buffers, builds
//! accels from [`Mesh`](rayd_engine::mesh::Mesh)es loaded by [`load_mesh`] (OBJ, PLY, glTF/GLB), and traces
//! packed ray buffers. [`Client::trace`] picks `TraceBatch` or `TraceStream` by itself from the sizes involved and
//! returns one [`TraceResult`] either way; [`HitView`] and [`RayView`] read packed buffers in place with the
//! engine's formats. Enum and message conversions between the contract and the engine live in [`convert`].
//!
//! ```no_run
//! use rayd_client::{Client, ClientOptions, load_mesh};
//! use rayd_engine::{accel::BuildFlags, format::*, query::Query, raygen::Camera};
//! # async fn demo() -> rayd_client::Result<()> {
//! let client = Client::connect("http://127.0.0.1:50051", ClientOptions::default()).await?;
//! let mesh = load_mesh("bunny.ply")?;
//! client.build_mesh("bunny", &mesh, "", BuildFlags::PREFER_FAST_TRACE).await?;
//! let (lo, hi) = mesh.bounds();
//! let rays = Camera::framing(lo, hi, 640, 480).rays(RayFormat::OriginDirection);
//! let query = Query::closest(RayFormat::OriginDirection, HitFormat::TTriid);
//! let traced = client.trace("bunny", &query, rays.into()).await?;
//! let hits = traced.hit_view().iter().filter(|h| h.is_hit()).count();
//! # Ok(()) }
//! ```

mod auth;
mod bench;
mod build;
mod client;
pub mod convert;
mod error;
mod health;
mod instances;
mod lidar;
pub mod memory;
mod mesh;
mod reduce;
mod render;
mod route;
mod saved;
mod scene;
mod secondary;
mod stream;
mod trace;
mod upload;
mod view;

pub use bench::{BenchOptions, BenchReport};
pub use client::{Client, ClientOptions, ClientTls, DEFAULT_SERVER};
pub use error::{Error, Result};
pub use health::{RAYD_SERVICE, ServingStatus, check_health};
pub use lidar::LidarScan;
pub use mesh::load_mesh;
pub use rayd_proto as proto;
pub use reduce::ReducedTrace;
pub use render::{Image, Shading, shade};
pub use route::{ROUTE_HEADER, Ring, Router, route_key};
pub use scene::{InstanceMotion, MotionKey, Scale, Scene, SceneInstance, SceneMotion};
pub use secondary::{PrimaryRays, SecondaryRays};
pub use stream::{AccelArg, BufferArg, Event, EventId, Operation, Stream};
pub use trace::{TraceParts, TraceResult, add_stats, append_bits, output_layout, output_layout_of_rays};
pub use upload::TemporaryBuffers;
pub use view::{HitView, RayView};
