//! Lidar scans made and reduced by the server: a spinning lidar's rays are generated where they are traced and
//! only the returns' points come back, written as a PLY point cloud.

use bytes::Bytes;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::glam::Vec3;
use rayd_engine::query::Query;
use rayd_engine::raygen::{Generator, Lidar};
use rayd_engine::reduce::{PointCloud, PointEncoding, Reduction};

use crate::client::Client;
use crate::error::{Error, Result};
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
        check_points(data.len(), stats.rays)?;
        Ok(LidarScan { points: data, rays: stats.rays })
    }
}

/// Fails with [`Error::Protocol`] unless `bytes` of a scan's points are whole 12-byte points, at most one a ray of
/// `rays` (a PLY file's header would count fewer points than its body holds).
fn check_points(bytes: usize, rays: u64) -> Result<()> {
    if bytes.is_multiple_of(12) && bytes as u64 / 12 <= rays {
        return Ok(());
    }
    Err(Error::Protocol(format!(
        "{bytes} bytes of points from {rays} rays: not whole 12-byte points, one a ray at most"
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scan_answered_with_part_of_a_point_or_more_points_than_rays_is_a_protocol_error() {
        assert!(check_points(0, 0).is_ok() && check_points(24, 2).is_ok());
        for (bytes, rays) in [(13, 5), (36, 2)] {
            let error = check_points(bytes, rays).unwrap_err();
            assert!(matches!(error, Error::Protocol(_)), "{error:?}");
            assert!(error.to_string().contains(&format!("{bytes} bytes of points from {rays} rays")), "{error}");
        }
    }
}
