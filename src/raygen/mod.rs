//! Ray batches made from a few numbers: a pinhole camera, uniformly random rays, and the [`Generator`]s that the
//! server expands itself (cameras, lidar, sphere sampling, secondary rays from an earlier trace's hits). Deterministic for a given seed, whatever the thread
//! count.

mod generator;
mod secondary;

pub use generator::{
    CameraFrame, Generator, Lidar, LidarChannel, LidarFrame, LidarStep, MAX_GENERATOR_POINTS, Orthographic,
    PixelSampling, SphereSampling,
};
pub use secondary::{Bounce, Primary, Secondary};

use glam::{Vec3, Vec3A};

use crate::format::{Ray, RayFormat};

/// A pinhole camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Position of the eye.
    pub eye: Vec3,
    /// Point the camera looks at.
    pub target: Vec3,
    /// Up direction (need not be orthogonal to the view direction).
    pub up: Vec3,
    /// Vertical field of view, in degrees.
    pub fov_y_degrees: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Camera {
    /// A camera that sees the whole box `[lo, hi]` from the front-right-above, 45° field of view.
    pub fn framing(lo: Vec3, hi: Vec3, width: u32, height: u32) -> Camera {
        let centre = (lo + hi) * 0.5;
        let radius = (hi - lo).length() * 0.5;
        let direction = Vec3::new(0.5, 0.8, 1.0).normalize();
        Camera {
            eye: centre + direction * radius * 2.0,
            target: centre,
            up: Vec3::Y,
            fov_y_degrees: 45.0,
            width,
            height,
        }
    }

    /// The ray through the centre of pixel (`x`, `y`), row 0 at the top; unit direction, `tmin` 0, `tmax` +∞.
    pub fn ray(&self, x: u32, y: u32) -> Ray {
        let forward = (self.target - self.eye).normalize();
        let right = forward.cross(self.up).normalize();
        let up = right.cross(forward);
        let half_height = tan(self.fov_y_degrees.to_radians() * 0.5);
        let half_width = half_height * self.width as f32 / self.height as f32;
        let sx = ((x as f32 + 0.5) / self.width as f32 * 2.0 - 1.0) * half_width;
        let sy = (1.0 - (y as f32 + 0.5) / self.height as f32 * 2.0) * half_height;
        let direction = (forward + right * sx + up * sy).normalize();
        Ray { origin: self.eye.into(), direction: direction.into(), ..Ray::default() }
    }

    /// All pixels' rays, row by row, packed in `format`.
    pub fn rays(&self, format: RayFormat) -> Vec<u8> {
        let mut bytes = vec![0u8; self.width as usize * self.height as usize * format.size()];
        self.fill_rays(format, 0, &mut bytes);
        bytes
    }

    /// Fills `out` (a whole number of rays) with the rays of [`Camera::rays`] from ray `first` on, for a caller that
    /// makes them a part at a time.
    pub fn fill_rays(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        for (i, slot) in (first..).zip(out.chunks_exact_mut(format.size())) {
            let (x, y) = ((i % u64::from(self.width)) as u32, (i / u64::from(self.width)) as u32);
            format.encode(&self.ray(x, y), slot);
        }
    }
}

/// `(sin x, cos x)` with the same bits on every platform: the `libm` crate's, a port of musl's in plain IEEE
/// arithmetic. The standard library's are the platform C library's, and glibc's and musl's differ in the last bit
/// for about 2.5% of angles; every ray maker here takes its sines from this function, so that a client expands a
/// generator byte for byte as the server does, whatever either runs on.
fn sin_cos(x: f32) -> (f32, f32) {
    libm::sincosf(x)
}

/// `tan x` with the same bits on every platform, as [`sin_cos`] (glibc's and musl's differ for about 14% of
/// angles: a camera's field of view, and so all its rays).
fn tan(x: f32) -> f32 {
    libm::tanf(x)
}

/// A 64-bit hash of (`seed`, `index`) (SplitMix64's finalizer), so every ray is made independently.
fn mix(seed: u64, index: u64) -> u64 {
    let mut z = seed ^ index.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// A uniform float in `[0, 1)` from the hash of (`seed`, `index`).
pub fn uniform(seed: u64, index: u64) -> f32 {
    (mix(seed, index) >> 40) as f32 / (1u64 << 24) as f32
}

/// `count` rays with origins uniform in the box `[lo, hi]` and directions uniform on the unit sphere, packed in
/// `format`; `tmin` 0, `tmax` +∞.
pub fn random_rays(lo: Vec3, hi: Vec3, count: usize, seed: u64, format: RayFormat) -> Vec<u8> {
    let mut bytes = vec![0u8; count * format.size()];
    fill_random_rays(lo, hi, seed, format, 0, &mut bytes);
    bytes
}

/// Fills `out` (a whole number of rays) with the rays [`random_rays`] makes from ray `first` on, for a caller that
/// holds the buffer (allocated as it sees fit) or makes the rays a part at a time.
pub fn fill_random_rays(lo: Vec3, hi: Vec3, seed: u64, format: RayFormat, first: u64, out: &mut [u8]) {
    for (i, slot) in (first..).zip(out.chunks_exact_mut(format.size())) {
        let u = |k: u64| uniform(seed, i * 8 + k);
        let origin = lo + (hi - lo) * Vec3::new(u(0), u(1), u(2));
        let z = 1.0 - 2.0 * u(3);
        let phi = std::f32::consts::TAU * u(4);
        let r = (1.0 - z * z).max(0.0).sqrt();
        let (sin, cos) = sin_cos(phi);
        let direction = Vec3A::new(r * cos, r * sin, z);
        format.encode(&Ray { origin: origin.into(), direction, ..Ray::default() }, slot);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_made_a_part_at_a_time_are_the_rays_made_at_once() {
        let format = RayFormat::OriginTminDirectionTmax;
        let camera = Camera::framing(Vec3::ZERO, Vec3::ONE, 7, 5);
        let (lo, hi) = (Vec3::splat(-1.0), Vec3::ONE);
        let whole = [camera.rays(format), random_rays(lo, hi, 35, 3, format)];
        let fill = |which: usize, first: u64, out: &mut [u8]| match which {
            0 => camera.fill_rays(format, first, out),
            _ => fill_random_rays(lo, hi, 3, format, first, out),
        };
        for (which, whole) in whole.iter().enumerate() {
            let mut parts = vec![0u8; whole.len()];
            // Parts of 1, 6, 11 and 17 rays.
            for (first, end) in [(0, 1), (1, 7), (7, 18), (18, 35)] {
                fill(which, first, &mut parts[first as usize * format.size()..end * format.size()]);
            }
            assert_eq!(&parts, whole, "maker {which}");
            assert!(whole.chunks_exact(format.size()).any(|ray| ray != &whole[..format.size()]), "rays differ");
        }
    }
}
