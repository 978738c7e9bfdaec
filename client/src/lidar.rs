//! Lidar scans made and reduced by the server: a spinning lidar's rays are generated where they are traced and
//! only the returns' points come back, written as a PLY point cloud.

use bytes::Bytes;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::glam::Vec3;
use rayd_engine::query::Query;
use rayd_engine::raygen::{Generator, Lidar};
use rayd_engine::reduce::{PointCloud, PointEncoding, Reduction};

use crate::client::Client;
use crate::error::Result;
use crate::reduce::ReducedTrace;

/// The returns of one lidar revolution.
#[derive(Debug, Clone)]
pub struct LidarScan {
    /// Hit points, x, y, z as little-endian f32, in firing order (step by step, channel by channel).
    pub points: Bytes,
    /// Rays fired.
    pub rays: u64,
}

impl LidarScan {
    /// Number of returns.
    pub fn len(&self) -> usize {
        self.points.len() / 12
    }

    /// Whether no ray returned.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The header of a binary little-endian PLY file of the returns as `x y z` float vertices, which
    /// [`LidarScan::points`] follow.
    pub fn ply_header(&self) -> String {
        format!(
            "ply\nformat binary_little_endian 1.0\ncomment rayd lidar scan, {} rays\nelement vertex {}\n\
             property float x\nproperty float y\nproperty float z\nend_header\n",
            self.rays,
            self.len()
        )
    }
}

impl Client {
    /// Scans the accel called `accel` with `lidar` (closest hits, at the lidar's times): the server makes the rays
    /// and returns only the hit points (in ranges of rays where they could pass half a message:
    /// [`Client::trace_generated_reduced_in_ranges`]).
    pub async fn lidar(&self, accel: &str, lidar: &Lidar) -> Result<LidarScan> {
        let query = Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::T);
        let points = PointCloud { encoding: PointEncoding::Float32, step: 0.0, origin: Vec3::ZERO, ray_indices: false };
        let generator = Generator::Lidar(lidar.clone());
        let reduction = Reduction::PointCloud(points);
        let ReducedTrace { data, stats, .. } =
            self.trace_generated_reduced_in_ranges(accel, &query, &generator, &reduction).await?;
        Ok(LidarScan { points: data, rays: stats.rays })
    }
}
