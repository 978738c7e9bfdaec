//! Ray generators: a batch described by a few numbers and expanded where it is traced, ray by ray from its index,
//! so any range of it can be made on its own (by each piece of a trace, on any thread) with the same bytes.
//!
//! Every generator names its rays `0 .. count()` in a documented order, and every random number is
//! [`uniform`]`(seed, index·8 + k)` for the ray's index and a small `k` that says what it is for.

use std::f32::consts::TAU;

use glam::{Vec3, Vec3A};

use rayon::prelude::*;

use super::{Bounce, Camera, Secondary, sin_cos, tan, uniform};
#[cfg(target_arch = "x86_64")]
use crate::cpu_features::{has_avx2, has_avx512};
use crate::error::{Error, Result};
use crate::format::{Ray, RayFormat};
use crate::query::ImageRows;
use crate::reduce::PARALLEL_SPLIT_RAYS;

/// Rays a camera makes at once ([`CameraFrame::fill`]), a lane each: arrays the compiler keeps in vector registers
/// (one AVX-512 register, two AVX2 ones).
const CAMERA_BLOCK: usize = 16;

/// Most channels of a lidar and most points of a sphere generator.
pub const MAX_GENERATOR_POINTS: usize = 1 << 16;

/// Where the rays of a camera pass through their pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelSampling {
    /// Rays per pixel, at least 1: ray `i` is sample `i % samples` of pixel `i / samples` (pixels row by row, row
    /// 0 at the top).
    pub samples: u32,
    /// Without a seed every ray passes through its pixel's centre; with one, through a point uniform in the pixel
    /// (`k` = 0, 1 for x, y).
    pub jitter_seed: Option<u64>,
}

/// An orthographic camera: parallel rays from a rectangle around the eye.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orthographic {
    /// Centre of the image rectangle.
    pub eye: Vec3,
    /// A point the camera looks towards (the rays' direction is `target − eye`, normalized).
    pub target: Vec3,
    /// Up direction (need not be orthogonal to the view direction).
    pub up: Vec3,
    /// Height of the image rectangle in world units; its width follows the pixels' aspect ratio.
    pub view_height: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

/// A spinning lidar: for each of `steps` azimuths around `up`, one ray per channel.
#[derive(Debug, Clone, PartialEq)]
pub struct Lidar {
    /// Position of the sensor.
    pub origin: Vec3,
    /// Azimuth 0: the first column fires along this direction (projected on the plane across `up`).
    pub forward: Vec3,
    /// The rotation axis; azimuths turn counter-clockwise seen from its tip.
    pub up: Vec3,
    /// Each channel's elevation above the plane across `up`, in degrees, −90 to 90.
    pub elevations_degrees: Vec<f32>,
    /// Azimuth steps per revolution: ray `i` is channel `i % channels` of step `i / channels`, at azimuth
    /// `360° · step / steps`.
    pub steps: u32,
    /// Nearest range (the rays' `tmin`; directions are unit vectors, so `t` is a distance).
    pub min_range: f32,
    /// Farthest range (the rays' `tmax`).
    pub max_range: f32,
    /// Time of the first step and time after the last: step `s` fires at `begin + (end − begin) · s / steps`. Equal
    /// times fire every ray at that time.
    pub time: (f32, f32),
}

/// Rays in random directions around given points (ambient occlusion, visibility).
#[derive(Debug, Clone, PartialEq)]
pub struct SphereSampling {
    /// The points rays start from.
    pub points: Vec<Vec3>,
    /// Empty, for directions uniform on the sphere; or one normal a point, for directions cosine-distributed on the
    /// hemisphere around it (as ambient occlusion wants).
    pub normals: Vec<Vec3>,
    /// Rays per point: ray `i` is sample `i % samples` of point `i / samples`.
    pub samples: u32,
    /// Rays start this far along their direction (`tmin`), to leave the surface a point lies on.
    pub min_distance: f32,
    /// And reach this far (`tmax`).
    pub max_distance: f32,
    /// Seed of the directions (`k` = 0, 1).
    pub seed: u64,
}

/// A batch of rays described by a few numbers.
#[derive(Debug, Clone, PartialEq)]
pub enum Generator {
    /// A pinhole camera ([`Camera::ray`] through each sample point).
    Pinhole(Camera, PixelSampling),
    /// An orthographic camera.
    Orthographic(Orthographic, PixelSampling),
    /// A spinning lidar.
    Lidar(Lidar),
    /// Rays around points.
    Sphere(SphereSampling),
    /// Rays that continue an earlier trace from its hits.
    Secondary(Secondary),
}

/// Fails with INVALID_ARGUMENT naming `field` unless `ok`.
pub(super) fn require(ok: bool, field: &'static str, rule: impl FnOnce() -> String) -> Result<()> {
    if ok { Ok(()) } else { Err(Error::InvalidQuery { field, rule: rule() }) }
}

/// Checks that every coordinate of `values` is finite.
fn finite(field: &'static str, values: &[Vec3]) -> Result<()> {
    let bad = values.iter().position(|v| !v.is_finite());
    require(bad.is_none(), field, || format!("must be finite (entry {})", bad.unwrap_or(0)))
}

/// Checks that each of the named vectors is finite, naming the first that is not.
fn finite_fields(fields: &[(&'static str, Vec3)]) -> Result<()> {
    fields.iter().try_for_each(|&(field, value)| require(value.is_finite(), field, || "must be finite".into()))
}

/// Checks that a view direction and an up vector make a [`frame`]: INVALID_ARGUMENT naming `view_field` when the
/// direction is zero (`view_rule` says what it must be), `up_field` when up is zero or parallel to it.
fn check_frame(
    view_field: &'static str,
    view_rule: &str,
    direction: Vec3,
    up_field: &'static str,
    up: Vec3,
) -> Result<()> {
    let forward = unit(direction);
    require(forward != Vec3::ZERO, view_field, || view_rule.into())?;
    require(unit(forward.cross(up)) != Vec3::ZERO, up_field, || {
        "must not be zero or parallel to the view direction".into()
    })
}

/// An orthonormal frame looking along `direction` with `up` as close to up as can be (both checked by
/// [`check_frame`]).
fn frame(direction: Vec3, up: Vec3) -> (Vec3, Vec3, Vec3) {
    let forward = unit(direction);
    let right = unit(forward.cross(up));
    (forward, right, right.cross(forward))
}

/// The unit vector along `v` (glam's `normalize`), or zero where `v` has no direction (zero, or not finite). A
/// finite vector too long or too short for its squared length to be a normal `f32` (1e20, 1e-22) is scaled first.
pub(super) fn unit(v: Vec3) -> Vec3 {
    if v.length_squared().is_normal() || !v.is_finite() {
        return v.normalize_or_zero();
    }
    (v / v.abs().max_element()).normalize_or_zero()
}

impl PixelSampling {
    /// Ray `index`'s pixel (x, y) in an image `width` pixels across.
    fn pixel(&self, width: u32, index: u64) -> (u32, u32) {
        let pixel = index / u64::from(self.samples);
        ((pixel % u64::from(width)) as u32, (pixel / u64::from(width)) as u32)
    }

    /// Ray `index`'s point in its pixel, in `[0, 1)²`.
    fn point(&self, index: u64) -> (f32, f32) {
        match self.jitter_seed {
            None => (0.5, 0.5),
            Some(seed) => (uniform(seed, index * 8), uniform(seed, index * 8 + 1)),
        }
    }
}

/// Most rays a camera makes (width × height × samples per pixel): far more than any trace, and few enough that a
/// ray's number, its jitter's counters (8 a ray) and a block's last lane stay within u64.
const MAX_CAMERA_RAYS: u64 = 1 << 48;

/// Checks a camera's image size and sampling.
fn check_image(width: u32, height: u32, sampling: &PixelSampling) -> Result<()> {
    require(width > 0, "generator.width", || "must be at least 1".into())?;
    require(height > 0, "generator.height", || "must be at least 1".into())?;
    require(sampling.samples > 0, "generator.samples_per_pixel", || "must be at least 1".into())?;
    let pixels = u64::from(width) * u64::from(height);
    require(pixels <= MAX_CAMERA_RAYS, "generator.width", || {
        format!("{width}×{height} pixels are more than 2^48 rays")
    })?;
    let rays = pixels.saturating_mul(u64::from(sampling.samples));
    require(rays <= MAX_CAMERA_RAYS, "generator.samples_per_pixel", || {
        format!("{width}×{height} pixels × {} samples is more than 2^48 rays", sampling.samples)
    })
}

/// Checks a camera's eye, target and up: finite, and a frame.
fn check_camera_frame(eye: Vec3, target: Vec3, up: Vec3) -> Result<()> {
    finite_fields(&[("generator.eye", eye), ("generator.target", target), ("generator.up", up)])?;
    check_frame("generator.target", "must differ from the eye", target - eye, "generator.up", up)
}

impl Generator {
    /// Checks that rays packed in `format` keep the range the generator gives its rays (a lidar's or a sphere's
    /// `tmin` above 0 or finite `tmax`, a shadow ray's `tmax`): rays that lost it would reach past what was asked;
    /// and a lidar's times other than 0: its rays would all be traced at time 0. INVALID_ARGUMENT naming
    /// `query.ray_format` and the generator's field otherwise.
    pub fn check_format(&self, format: RayFormat) -> Result<()> {
        let range =
            |field: &str, value: f32, unset: f32| (value != unset).then(|| format!("generator.{field} ({value})"));
        // What sets the rays' tmin and tmax, where the generator sets them.
        let (tmin, tmax) = match self {
            Generator::Pinhole(..) | Generator::Orthographic(..) => (None, None),
            Generator::Lidar(lidar) => {
                (range("min_range", lidar.min_range, 0.0), range("max_range", lidar.max_range, f32::INFINITY))
            }
            Generator::Sphere(sphere) => (
                range("min_distance", sphere.min_distance, 0.0),
                range("max_distance", sphere.max_distance, f32::INFINITY),
            ),
            Generator::Secondary(secondary) => match secondary.bounce {
                Bounce::Reflect => (None, None),
                Bounce::TowardsLight(_) => {
                    (None, Some("generator.secondary.towards_light (the light's distance)".into()))
                }
            },
        };
        for (set, carried, what) in [(tmin, format.has_tmin(), "tmin"), (tmax, format.has_tmax(), "tmax")] {
            if let Some(set) = set.filter(|_| !carried) {
                return Err(Error::InvalidQuery {
                    field: "query.ray_format",
                    rule: format!(
                        "{} rays carry no {what}, which {set} sets: use a format with tmin and tmax",
                        format.name()
                    ),
                });
            }
        }
        if let Generator::Lidar(lidar) = self
            && lidar.time != (0.0, 0.0)
            && format.time_offset().is_none()
        {
            let (begin, end) = lidar.time;
            return Err(Error::InvalidQuery {
                field: "query.ray_format",
                rule: format!(
                    "{} rays carry no time, which generator.time ({begin}, {end}) sets: use a format with time",
                    format.name()
                ),
            });
        }
        Ok(())
    }

    /// Checks the numbers: finite, in range, a frame that exists; INVALID_ARGUMENT naming the field.
    pub fn check(&self) -> Result<()> {
        match self {
            Generator::Pinhole(camera, sampling) => {
                check_camera_frame(camera.eye, camera.target, camera.up)?;
                let fov = camera.fov_y_degrees;
                require(fov > 0.0 && fov < 180.0, "generator.fov_y_degrees", || format!("{fov} must be in (0, 180)"))?;
                check_image(camera.width, camera.height, sampling)
            }
            Generator::Orthographic(camera, sampling) => {
                check_camera_frame(camera.eye, camera.target, camera.up)?;
                let h = camera.view_height;
                require(h.is_finite() && h > 0.0, "generator.view_height", || format!("{h} must be positive"))?;
                check_image(camera.width, camera.height, sampling)?;
                // Its half width as the frame works it out ([`Generator::camera_frame`]).
                let half_width = h * 0.5 * camera.width as f32 / camera.height as f32;
                require(half_width.is_finite(), "generator.view_height", || {
                    format!("{h} makes a view of {}×{} pixels too wide for f32", camera.width, camera.height)
                })
            }
            Generator::Lidar(lidar) => {
                finite_fields(&[
                    ("generator.origin", lidar.origin),
                    ("generator.forward", lidar.forward),
                    ("generator.up", lidar.up),
                ])?;
                check_frame("generator.forward", "must not be zero", lidar.forward, "generator.up", lidar.up)?;
                let channels = lidar.elevations_degrees.len();
                require((1..=MAX_GENERATOR_POINTS).contains(&channels), "generator.elevations_degrees", || {
                    format!("{channels} channels; 1 to {MAX_GENERATOR_POINTS}")
                })?;
                let bad = lidar.elevations_degrees.iter().position(|e| !(-90.0..=90.0).contains(e));
                require(bad.is_none(), "generator.elevations_degrees", || {
                    format!("channel {} must be −90 to 90 degrees", bad.unwrap_or(0))
                })?;
                require(lidar.steps > 0, "generator.steps", || "must be at least 1".into())?;
                check_range(("generator.min_range", "generator.max_range"), lidar.min_range, lidar.max_range)?;
                let (begin, end) = lidar.time;
                // Its span must be finite too, so that every step's time is a number.
                require((end - begin).is_finite(), "generator.time", || {
                    "must be finite, and so must end − begin".into()
                })
            }
            Generator::Sphere(sphere) => {
                let points = sphere.points.len();
                require((1..=MAX_GENERATOR_POINTS).contains(&points), "generator.points", || {
                    format!("{points} points; 1 to {MAX_GENERATOR_POINTS}")
                })?;
                finite("generator.points", &sphere.points)?;
                require(sphere.normals.is_empty() || sphere.normals.len() == points, "generator.normals", || {
                    format!("{} normals for {points} points: none, or one a point", sphere.normals.len())
                })?;
                let bad = sphere.normals.iter().position(|&n| unit(n) == Vec3::ZERO);
                require(bad.is_none(), "generator.normals", || {
                    format!("normal {} must be finite and non-zero", bad.unwrap_or(0))
                })?;
                require(sphere.samples > 0, "generator.samples", || "must be at least 1".into())?;
                let fields = ("generator.min_distance", "generator.max_distance");
                check_range(fields, sphere.min_distance, sphere.max_distance)
            }
            Generator::Secondary(secondary) => secondary.check(),
        }
    }

    /// Rays it makes (saturating: a count beyond `u64` is refused by any limit anyway).
    pub fn count(&self) -> u64 {
        match self {
            Generator::Pinhole(Camera { width, height, .. }, s)
            | Generator::Orthographic(Orthographic { width, height, .. }, s) => {
                (u64::from(*width) * u64::from(*height)).saturating_mul(u64::from(s.samples))
            }
            Generator::Lidar(l) => u64::from(l.steps) * l.elevations_degrees.len() as u64,
            Generator::Sphere(s) => s.points.len() as u64 * u64::from(s.samples),
            Generator::Secondary(s) => s.count(),
        }
    }

    /// The image rows that its rays from `first` on follow, in their indices from `first` ([`ImageRows`]): a camera's
    /// rows of pixels (with their samples), a lidar's steps (a row of its channels each); none for the others, nor
    /// for rows narrower than [`ImageRows::MIN_WIDTH`] or wider than [`ImageRows::MAX_GENERATED_WIDTH`].
    pub fn image_rows(&self, first: u64) -> Option<ImageRows> {
        let width = match self {
            Generator::Pinhole(Camera { width, .. }, s) | Generator::Orthographic(Orthographic { width, .. }, s) => {
                u64::from(*width) * u64::from(s.samples)
            }
            Generator::Lidar(l) => l.elevations_degrees.len() as u64,
            Generator::Sphere(_) | Generator::Secondary(_) => return None,
        };
        let width = usize::try_from(width)
            .ok()
            .filter(|width| (ImageRows::MIN_WIDTH..=ImageRows::MAX_GENERATED_WIDTH).contains(width))?;
        Some(ImageRows { width, first: 0 }.from_ray((first % width as u64) as usize))
    }

    /// Packs rays `first .. first + out.len() / format.size()` in `format` into `out`. The generator must have
    /// passed [`Generator::check`] and hold those rays.
    pub fn fill(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        format.specialized(
            #[inline(always)]
            |format| self.fill_as(format, first, out),
        )
    }

    /// [`Generator::fill`] for a format known where it is inlined.
    #[inline(always)]
    fn fill_as(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        let size = format.size();
        match self {
            Generator::Pinhole(..) | Generator::Orthographic(..) => {
                self.camera_frame().expect("a camera").fill(format, first, out);
            }
            Generator::Lidar(lidar) => {
                // Each step's azimuth worked out once, not for every ray; each channel's elevation too where the
                // rays cover every channel, and a ray's own otherwise (a secondary trace makes its primaries 64 at a
                // time: a table of 65,536 channels for each block made a million secondary rays take 12 s, not 0.1).
                let frame = LidarFrame::new(lidar);
                let channels = lidar.elevations_degrees.len();
                let table: Vec<LidarChannel> = match out.len() / size >= channels {
                    true => (0..channels).map(|c| frame.channel(c)).collect(),
                    false => Vec::new(),
                };
                let channel_of = |c: usize| table.get(c).copied().unwrap_or_else(|| frame.channel(c));
                let (mut step, mut channel) = (first / channels as u64, (first % channels as u64) as usize);
                let mut at = frame.step(step);
                for slot in out.chunks_exact_mut(size) {
                    format.encode(&frame.ray(at, channel_of(channel)), slot);
                    channel += 1;
                    if channel == channels {
                        (step, channel) = (step + 1, 0);
                        at = frame.step(step);
                    }
                }
            }
            Generator::Sphere(sphere) => {
                // Each point's hemisphere frame worked out once, not for every sample.
                let samples = u64::from(sphere.samples);
                let frame_of = |point: usize| sphere.normals.get(point).map(|normal| HemisphereFrame::new(*normal));
                let (mut point, mut sample) = ((first / samples) as usize, first % samples);
                let mut frame = frame_of(point);
                for (index, slot) in (first..).zip(out.chunks_exact_mut(size)) {
                    let (u0, u1) = (uniform(sphere.seed, index * 8), uniform(sphere.seed, index * 8 + 1));
                    let direction = match &frame {
                        None => uniform_sphere(u0, u1),
                        Some(frame) => frame.cosine_sample(u0, u1),
                    };
                    let ray = Ray {
                        origin: sphere.points[point].into(),
                        direction,
                        tmin: sphere.min_distance,
                        tmax: sphere.max_distance,
                        ..Ray::default()
                    };
                    format.encode(&ray, slot);
                    sample += 1;
                    if sample == samples {
                        (point, sample) = (point + 1, 0);
                        frame = frame_of(point);
                    }
                }
            }
            Generator::Secondary(secondary) => secondary.fill(format, first, out),
        }
    }

    /// [`Generator::fill`] across the rayon pool, in parts of [`PARALLEL_SPLIT_RAYS`] rays: the same bytes, sooner
    /// for a large range.
    pub fn fill_parallel(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        let part_bytes = PARALLEL_SPLIT_RAYS * format.size();
        out.par_chunks_mut(part_bytes)
            .enumerate()
            .for_each(|(part, out)| self.fill(format, first + (part * PARALLEL_SPLIT_RAYS) as u64, out));
    }

    /// Every ray, packed in `format` (for callers that want the buffer itself, e.g. to compare).
    pub fn rays(&self, format: RayFormat) -> Vec<u8> {
        let mut bytes = vec![0u8; self.count() as usize * format.size()];
        self.fill(format, 0, &mut bytes);
        bytes
    }
}

/// Checks a `tmin`/`tmax` pair, given by the `fields` named: finite `tmin` ≥ 0, `tmax` ≥ `tmin` (may be +∞).
fn check_range(fields: (&'static str, &'static str), min: f32, max: f32) -> Result<()> {
    let rule = || format!("range {min} .. {max}: need 0 ≤ min ≤ max, min finite");
    require(min.is_finite() && min >= 0.0, fields.0, rule)?;
    require(!max.is_nan() && max >= min, fields.1, rule)
}

/// A camera generator's frame, computed once for many rays: what [`Generator::fill`] (and the wgpu kernel, from
/// the same numbers) makes each of its rays from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraFrame {
    /// A pinhole camera (rays from `eye` through the image), or an orthographic one (parallel rays from the image
    /// rectangle around `eye`).
    pub pinhole: bool,
    /// The eye, or the image rectangle's centre.
    pub eye: Vec3,
    /// The view direction, unit.
    pub forward: Vec3,
    /// Image x per unit of `sx`, unit.
    pub right: Vec3,
    /// Image y per unit of `sy`, unit.
    pub up: Vec3,
    /// Half the image's extent across and up: at distance 1 (pinhole), in world units (orthographic).
    pub half: (f32, f32),
    /// Pixels across and up, as floats.
    pub size: (f32, f32),
    /// Pixels across.
    pub width: u32,
    /// Where rays pass through their pixel.
    pub sampling: PixelSampling,
}

impl CameraFrame {
    /// The camera's ray `index`: its pixel and point in it (`PixelSampling`), through image point (`px`, `py`) in
    /// pixels, (0, 0) the top left corner; `sx`, `sy` = (`px` / width · 2 − 1) · half width, (1 − `py` / height · 2)
    /// · half height. Pinhole: from the eye along `forward + right·sx + up·sy`, normalized; orthographic: from
    /// `eye + right·sx + up·sy` along `forward`. `tmin` 0, `tmax` +∞.
    pub fn ray(&self, index: u64) -> Ray {
        let (x, y) = self.sampling.pixel(self.width, index);
        self.ray_in_pixel(x, y, index)
    }

    /// Writes rays `first`, `first + 1`, … packed in `format` into `out` (a whole number of rays): the bits of
    /// [`CameraFrame::ray`] for each, made [`CAMERA_BLOCK`] at a time, the pixel stepped from ray to ray instead of
    /// divided out of every index; compiled for AVX-512 or AVX2 where the CPU has them (its divisions and square
    /// roots are what making camera rays waits on).
    pub fn fill(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        #[cfg(target_arch = "x86_64")]
        if has_avx512() {
            // SAFETY: the CPU has AVX-512F and the AVX2 features, as just checked.
            return unsafe { self.fill_avx512(format, first, out) };
        }
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has the AVX2 features, as just checked.
            return unsafe { self.fill_avx2(format, first, out) };
        }
        self.fill_blocks(format, first, out);
    }

    /// [`CameraFrame::fill_blocks`] compiled for AVX-512.
    ///
    /// # Safety
    /// The CPU must have AVX-512F and the features [`has_avx2`] checks.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn fill_avx512(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        self.fill_blocks(format, first, out);
    }

    /// [`CameraFrame::fill_blocks`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must have the features [`has_avx2`] checks.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn fill_avx2(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        self.fill_blocks(format, first, out);
    }

    /// [`CameraFrame::fill`] in blocks of [`CAMERA_BLOCK`] rays, compiled once a format.
    #[inline(always)]
    fn fill_blocks(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        format.specialized(
            #[inline(always)]
            |format| {
                let size = format.size();
                let samples = self.sampling.samples;
                let (mut x, mut y) = self.sampling.pixel(self.width, first);
                let (mut sample, mut index) = ((first % u64::from(samples)) as u32, first);
                let (mut px, mut py) = ([0.0; CAMERA_BLOCK], [0.0; CAMERA_BLOCK]);
                // One ray a pixel through its centre ([`PixelSampling::point`]'s (0.5, 0.5)).
                let centres = samples == 1 && self.sampling.jitter_seed.is_none();
                for block in out.chunks_mut(CAMERA_BLOCK * size) {
                    if centres && self.width - x >= CAMERA_BLOCK as u32 {
                        // A block of pixel centres within a row: the common case, without a test a lane.
                        for lane in 0..CAMERA_BLOCK {
                            (px[lane], py[lane]) = ((x + lane as u32) as f32 + 0.5, y as f32 + 0.5);
                        }
                        x += CAMERA_BLOCK as u32;
                        if x == self.width {
                            (x, y) = (0, y + 1);
                        }
                    } else {
                        // Every lane is made, also past the end of a last, short block (its rays are dropped).
                        for lane in 0..CAMERA_BLOCK {
                            let (dx, dy) = self.sampling.point(index + lane as u64);
                            (px[lane], py[lane]) = (x as f32 + dx, y as f32 + dy);
                            sample += 1;
                            if sample == samples {
                                (sample, x) = (0, x + 1);
                                if x == self.width {
                                    // Past the last row only in lanes past the end, whose rays are dropped.
                                    (x, y) = (0, y.wrapping_add(1));
                                }
                            }
                        }
                    }
                    index += CAMERA_BLOCK as u64;
                    let [ax, ay, az] = self.through(&px, &py);
                    for (lane, slot) in block.chunks_exact_mut(size).enumerate() {
                        format.encode(&self.ray_through(Vec3A::new(ax[lane], ay[lane], az[lane])), slot);
                    }
                }
            },
        );
    }

    /// Ray `index`, in pixel (`x`, `y`).
    #[inline(always)]
    fn ray_in_pixel(&self, x: u32, y: u32, index: u64) -> Ray {
        let (dx, dy) = self.sampling.point(index);
        let [[x], [y], [z]] = self.through(&[x as f32 + dx], &[y as f32 + dy]);
        self.ray_through(Vec3A::new(x, y, z))
    }

    /// The ray made of a point [`CameraFrame::through`] gives: from the eye along it (pinhole), or from it along the
    /// view direction (orthographic).
    #[inline(always)]
    fn ray_through(&self, point: Vec3A) -> Ray {
        let (origin, direction) = if self.pinhole { (self.eye.into(), point) } else { (point, self.forward.into()) };
        Ray { origin, direction, ..Ray::default() }
    }

    /// The points the rays through `N` image points (`px`, `py`) in pixels are made of, a lane each, axis by axis:
    /// a pinhole's unit directions `forward + right·sx + up·sy`, an orthographic camera's origins `eye + right·sx +
    /// up·sy` (`sx`, `sy` as in [`CameraFrame::ray`]). Lane by lane, the same IEEE operations in the same order
    /// (no fused multiply-adds), so a ray has the same bits whichever block and lane make it; plain loops over the
    /// lanes, which the compiler turns into vector instructions as wide as the features it compiles for.
    #[inline(always)]
    fn through<const N: usize>(&self, px: &[f32; N], py: &[f32; N]) -> [[f32; N]; 3] {
        let (mut sx, mut sy) = ([0.0; N], [0.0; N]);
        for lane in 0..N {
            sx[lane] = (px[lane] / self.size.0 * 2.0 - 1.0) * self.half.0;
            sy[lane] = (1.0 - py[lane] / self.size.1 * 2.0) * self.half.1;
        }
        let base = if self.pinhole { self.forward } else { self.eye };
        let mut points = [[0.0; N]; 3];
        for (axis, along) in points.iter_mut().enumerate() {
            for lane in 0..N {
                along[lane] = base[axis] + self.right[axis] * sx[lane] + self.up[axis] * sy[lane];
            }
        }
        if self.pinhole {
            let [x, y, z] = &mut points;
            for lane in 0..N {
                let recip = 1.0 / (x[lane] * x[lane] + y[lane] * y[lane] + z[lane] * z[lane]).sqrt();
                (x[lane], y[lane], z[lane]) = (x[lane] * recip, y[lane] * recip, z[lane] * recip);
            }
        }
        points
    }
}

impl Generator {
    /// The frame of a checked camera generator (pinhole or orthographic); `None` for the others.
    pub fn camera_frame(&self) -> Option<CameraFrame> {
        let (pinhole, eye, target, up, half_height, width, height, sampling) = match self {
            Generator::Pinhole(c, s) => {
                (true, c.eye, c.target, c.up, tan(c.fov_y_degrees.to_radians() * 0.5), c.width, c.height, s)
            }
            Generator::Orthographic(c, s) => (false, c.eye, c.target, c.up, c.view_height * 0.5, c.width, c.height, s),
            _ => return None,
        };
        let (forward, right, up) = frame(target - eye, up);
        Some(CameraFrame {
            pinhole,
            eye,
            forward,
            right,
            up,
            half: (half_height * width as f32 / height as f32, half_height),
            size: (width as f32, height as f32),
            width,
            sampling: *sampling,
        })
    }
}

/// A lidar's frame: what [`Generator::fill`] (and the wgpu kernel, from the same numbers) makes its rays from. A ray
/// is made from its step's [`LidarStep`] and its channel's [`LidarChannel`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LidarFrame<'a> {
    /// The lidar.
    pub lidar: &'a Lidar,
    /// Azimuth 0, unit.
    pub forward: Vec3,
    /// Azimuth 90°, unit.
    pub left: Vec3,
    /// The rotation axis, unit.
    pub up: Vec3,
}

/// A lidar step's azimuth and time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LidarStep {
    /// Sine of the azimuth.
    pub sin: f32,
    /// Cosine of the azimuth.
    pub cos: f32,
    /// When the step fires.
    pub time: f32,
}

/// A lidar channel's elevation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LidarChannel {
    /// Sine of the elevation.
    pub sin: f32,
    /// Cosine of the elevation.
    pub cos: f32,
}

impl LidarFrame<'_> {
    /// The frame of a checked lidar.
    pub fn new(lidar: &Lidar) -> LidarFrame<'_> {
        // `up` is the axis; azimuth 0 is `forward` laid on the plane across it. One at right angles to it already
        // takes the camera's frame, as before forward could be tilted, so that such lidars make the bytes they made.
        let (forward, right, up) = if lidar.forward.dot(lidar.up) == 0.0 {
            frame(lidar.forward, lidar.up)
        } else {
            let axis = unit(lidar.up);
            let right = unit(lidar.forward.cross(axis));
            (axis.cross(right), right, axis)
        };
        LidarFrame { lidar, forward, left: -right, up }
    }

    /// Step `step`: azimuth `2π · step / steps`, time `begin + (end − begin) · step / steps`.
    pub fn step(&self, step: u64) -> LidarStep {
        let fraction = step as f32 / self.lidar.steps as f32;
        let (sin, cos) = sin_cos(TAU * fraction);
        let (begin, end) = self.lidar.time;
        LidarStep { sin, cos, time: begin + (end - begin) * fraction }
    }

    /// Channel `channel`'s elevation.
    pub fn channel(&self, channel: usize) -> LidarChannel {
        let (sin, cos) = sin_cos(self.lidar.elevations_degrees[channel].to_radians());
        LidarChannel { sin, cos }
    }

    /// The ray of `step` and `channel`: from the origin along `(forward·cos a + left·sin a)·cos e + up·sin e`,
    /// normalized; `tmin`, `tmax` the ranges, the step's time.
    pub fn ray(&self, step: LidarStep, channel: LidarChannel) -> Ray {
        let direction = (self.forward * step.cos + self.left * step.sin) * channel.cos + self.up * channel.sin;
        Ray {
            origin: self.lidar.origin.into(),
            direction: direction.normalize().into(),
            tmin: self.lidar.min_range,
            tmax: self.lidar.max_range,
            time: step.time,
            ..Ray::default()
        }
    }
}

/// A direction uniform on the unit sphere from two uniform numbers.
fn uniform_sphere(u0: f32, u1: f32) -> Vec3A {
    let z = 1.0 - 2.0 * u0;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let (sin, cos) = sin_cos(TAU * u1);
    Vec3A::new(r * cos, r * sin, z)
}

/// A point's hemisphere of directions around its normal, for cosine-distributed samples.
struct HemisphereFrame {
    /// The unit normal.
    normal: Vec3,
    /// A unit tangent, …
    tangent: Vec3,
    /// … and the unit vector across both ([`Vec3::any_orthonormal_pair`] of the normal).
    bitangent: Vec3,
}

impl HemisphereFrame {
    /// The frame around `normal` (finite and non-zero), normalized.
    fn new(normal: Vec3) -> HemisphereFrame {
        let normal = unit(normal);
        let (tangent, bitangent) = normal.any_orthonormal_pair();
        HemisphereFrame { normal, tangent, bitangent }
    }

    /// A direction on the hemisphere, cosine-distributed, from two uniform numbers.
    #[inline(always)]
    fn cosine_sample(&self, u0: f32, u1: f32) -> Vec3A {
        let r = u0.sqrt();
        let (sin, cos) = sin_cos(TAU * u1);
        let local = self.tangent * (r * cos) + self.bitangent * (r * sin) + self.normal * (1.0 - u0).max(0.0).sqrt();
        local.normalize().into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Camera {
        Camera {
            eye: Vec3::new(0.0, 0.0, 5.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_degrees: 45.0,
            width: 8,
            height: 6,
        }
    }

    const CENTRES: PixelSampling = PixelSampling { samples: 1, jitter_seed: None };

    #[test]
    fn a_pinhole_generator_through_pixel_centres_is_the_camera() {
        let camera = camera();
        let generated = Generator::Pinhole(camera, CENTRES).rays(RayFormat::OriginTminDirectionTmax);
        assert_eq!(generated, camera.rays(RayFormat::OriginTminDirectionTmax));
    }

    #[test]
    fn any_range_is_made_as_in_the_whole() {
        let lidar = Generator::Lidar(Lidar {
            origin: Vec3::new(1.0, 2.0, 3.0),
            forward: Vec3::X,
            up: Vec3::Z,
            // More channels than a part below has rays: its channels are worked out ray by ray.
            elevations_degrees: (0..40).map(|c| c as f32 - 20.0).collect(),
            steps: 100,
            min_range: 0.5,
            max_range: 100.0,
            time: (0.0, 0.1),
        });
        let sphere = Generator::Sphere(SphereSampling {
            points: vec![Vec3::ZERO, Vec3::ONE],
            normals: vec![Vec3::Z, Vec3::X],
            samples: 64,
            min_distance: 1e-3,
            max_distance: 10.0,
            seed: 3,
        });
        let jittered = Generator::Pinhole(camera(), PixelSampling { samples: 4, jitter_seed: Some(9) });
        let format = RayFormat::OriginTminDirectionTmaxTime;
        for generator in [lidar, sphere, jittered] {
            generator.check().unwrap();
            generator.check_format(format).unwrap();
            let whole = generator.rays(format);
            let size = format.size();
            // From within a point's (a step's, a pixel's) rays, and across to the next point's.
            for first in [5, 60, 75] {
                let mut part = vec![0u8; 17 * size];
                generator.fill(format, first as u64, &mut part);
                assert_eq!(part, whole[first * size..(first + 17) * size], "{generator:?} from ray {first}");
            }
        }
    }

    #[test]
    fn a_format_that_cannot_keep_a_generators_range_is_refused_naming_both() {
        let lidar = |min_range: f32, max_range: f32| {
            Generator::Lidar(Lidar {
                origin: Vec3::ZERO,
                forward: Vec3::X,
                up: Vec3::Z,
                elevations_degrees: vec![0.0],
                steps: 4,
                min_range,
                max_range,
                time: (0.0, 0.0),
            })
        };
        let refusal = |generator: Generator, format: RayFormat| match generator.check_format(format) {
            Err(Error::InvalidQuery { field, rule }) => format!("{field}: {rule}"),
            other => panic!("{other:?}"),
        };
        let unlimited = lidar(0.0, f32::INFINITY);
        for format in RayFormat::ALL {
            unlimited.check_format(format).unwrap();
            Generator::Pinhole(camera(), CENTRES).check_format(format).unwrap();
        }
        assert_eq!(
            refusal(lidar(0.5, f32::INFINITY), RayFormat::OriginMaskDirectionTmax),
            "query.ray_format: origin_mask_direction_tmax rays carry no tmin, which generator.min_range (0.5) sets: \
             use a format with tmin and tmax"
        );
        lidar(0.0, 20.0).check_format(RayFormat::OriginMaskDirectionTmax).unwrap();
        let far = refusal(lidar(0.0, 20.0), RayFormat::OriginDirection);
        assert!(far.contains("no tmax, which generator.max_range (20) sets"), "{far}");
        lidar(0.5, 20.0).check_format(RayFormat::OriginTminDirectionTmax).unwrap();
        let Generator::Lidar(scan) = lidar(0.0, f32::INFINITY) else { unreachable!() };
        let revolving = Generator::Lidar(Lidar { time: (0.0, 0.5), ..scan });
        revolving.check_format(RayFormat::OriginTminDirectionTmaxTime).unwrap();
        assert_eq!(
            refusal(revolving, RayFormat::OriginTminDirectionTmax),
            "query.ray_format: origin_tmin_direction_tmax rays carry no time, which generator.time (0, 0.5) sets: use \
             a format with time"
        );
    }

    #[test]
    fn cameras_and_lidars_rays_follow_rows_that_a_search_of_their_rays_finds_too() {
        let lidar_of = |channels: usize| {
            Generator::Lidar(Lidar {
                origin: Vec3::ZERO,
                forward: Vec3::X,
                up: Vec3::Z,
                elevations_degrees: (0..channels).map(|c| c as f32 - 8.0).collect(),
                steps: 512,
                min_range: 0.5,
                max_range: 100.0,
                time: (0.0, 0.0),
            })
        };
        let wide = Camera { width: 40, height: 30, ..camera() };
        let format = RayFormat::OriginTminDirectionTmax;
        for (generator, width) in [(Generator::Pinhole(wide, CENTRES), 40), (lidar_of(16), 16)] {
            for first in [0, 7, 40 * 3 + 39] {
                let rows = generator.image_rows(first as u64);
                assert_eq!(rows, Some(ImageRows { width, first: (width - first % width) % width }));
                let rays = generator.rays(format);
                assert_eq!(ImageRows::find(format, &rays[first * format.size()..]), rows, "{generator:?} from {first}");
            }
        }
        // Samples of a pixel in turn: a row is a pixel row's rays.
        let sampled = Generator::Pinhole(wide, PixelSampling { samples: 3, jitter_seed: Some(1) });
        assert_eq!(sampled.image_rows(5), Some(ImageRows { width: 120, first: 115 }));
        let sphere = Generator::Sphere(SphereSampling {
            points: vec![Vec3::ZERO],
            normals: vec![],
            samples: 64,
            min_distance: 0.0,
            max_distance: 1.0,
            seed: 1,
        });
        assert_eq!(sphere.image_rows(0), None);
        // A lidar of four channels: too narrow for tiles.
        assert_eq!(lidar_of(4).image_rows(0), None);
    }

    #[test]
    fn camera_rays_made_in_blocks_are_those_made_by_index() {
        // 4 samples a pixel (jittered or not), 8 pixels a row; and one ray a pixel through its centre, 40 or 32
        // pixels a row (whole blocks of a row's centres, ending at the row's end or before a block that crosses
        // it). Starts within a pixel or a block, at a row's end and at the last ray; blocks of rays made at once that
        // end anywhere; every format.
        let Camera { eye, target, up, height, .. } = camera();
        let cases = [(4, Some(9), 8), (4, None, 8), (1, None, 40), (1, None, 32)];
        for (samples, jitter_seed, width) in cases {
            let sampling = PixelSampling { samples, jitter_seed };
            let pinhole = Camera { width, ..camera() };
            let orthographic = Orthographic { eye, target, up, view_height: 3.0, width, height };
            for generator in [Generator::Pinhole(pinhole, sampling), Generator::Orthographic(orthographic, sampling)] {
                let frame = generator.camera_frame().unwrap();
                let count = u64::from(width * height * samples);
                for (first, format) in
                    [0, 3, 5, 31, 32, 33, 101, count - 1].into_iter().zip(RayFormat::ALL.iter().cycle())
                {
                    let mut made = vec![0; (count - first) as usize * format.size()];
                    frame.fill(*format, first, &mut made);
                    for (index, slot) in (first..count).zip(made.chunks_exact(format.size())) {
                        let mut expected = vec![0; format.size()];
                        format.encode(&frame.ray(index), &mut expected);
                        assert_eq!(slot, expected, "{generator:?} from ray {first} in {format:?}: ray {index}");
                    }
                }
            }
        }
    }

    #[test]
    fn lidar_rays_turn_counter_clockwise_rise_with_elevation_and_spread_time() {
        let lidar = Lidar {
            origin: Vec3::ZERO,
            forward: Vec3::X,
            up: Vec3::Z,
            elevations_degrees: vec![0.0, 90.0],
            steps: 4,
            min_range: 0.0,
            max_range: 50.0,
            time: (1.0, 2.0),
        };
        let rays = Generator::Lidar(lidar.clone()).rays(RayFormat::Full);
        let ray = |i: usize| RayFormat::Full.decode(&rays[i * RayFormat::Full.size()..]);
        assert!((ray(0).direction - Vec3A::X).length() < 1e-6, "step 0, channel 0 along forward");
        assert!((ray(1).direction - Vec3A::Z).length() < 1e-6, "channel 1 straight up");
        assert!((ray(2).direction - Vec3A::Y).length() < 1e-6, "a quarter turn counter-clockwise about +z");
        assert_eq!((ray(2).time, ray(7).time, ray(7).tmax), (1.25, 1.75, 50.0));
        // Made in turn (each step's azimuth once), the rays are those of their step and channel, from any first ray.
        let frame = LidarFrame::new(&lidar);
        for first in 0..8 {
            let mut part = vec![0u8; (8 - first) * RayFormat::Full.size()];
            Generator::Lidar(lidar.clone()).fill(RayFormat::Full, first as u64, &mut part);
            let by_index = (first..8).flat_map(|index| {
                let mut record = [0u8; 48];
                RayFormat::Full.encode(&frame.ray(frame.step(index as u64 / 2), frame.channel(index % 2)), &mut record);
                record
            });
            assert_eq!(part, by_index.collect::<Vec<u8>>(), "from ray {first}");
        }
    }

    /// `samples` rays from the origin around `normal`, reaching 1, seeded with `seed`.
    fn around_the_origin(normal: Vec3, samples: u32, seed: u64) -> Generator {
        Generator::Sphere(SphereSampling {
            points: vec![Vec3::ZERO],
            normals: vec![normal],
            samples,
            min_distance: 0.0,
            max_distance: 1.0,
            seed,
        })
    }

    #[test]
    fn hemisphere_samples_stay_above_their_normal() {
        let normal = Vec3::new(1.0, 2.0, -0.5).normalize();
        let sphere = around_the_origin(normal, 1000, 1);
        let rays = sphere.rays(RayFormat::OriginDirection);
        let mean_cos: f32 = rays
            .chunks_exact(RayFormat::OriginDirection.size())
            .map(|b| Vec3::from(RayFormat::OriginDirection.decode(b).direction).dot(normal))
            .inspect(|&c| assert!(c >= -1e-6))
            .sum::<f32>()
            / 1000.0;
        assert!((mean_cos - 2.0 / 3.0).abs() < 0.03, "cosine-distributed: E[cos] = 2/3, got {mean_cos}");
    }

    /// SplitMix64's finalizer of `seed` XOR (`index` · 0x9e3779b97f4a7c15 mod 2^64), written out from the contract
    /// (trace.proto, `RayGenerator`) apart from the engine's `mix`, so that a change of either fails a test.
    fn documented_splitmix64(seed: u64, index: u64) -> u64 {
        let mut z = seed ^ index.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// The contract's random number `k` of ray `ray`: u(seed, ray·8 + k) = (z >> 40) / 2^24.
    fn documented_uniform(seed: u64, ray: u64, k: u64) -> f32 {
        (documented_splitmix64(seed, ray * 8 + k) >> 40) as f32 / 16_777_216.0
    }

    /// Ray `index` of `rays`, packed in `format`.
    fn ray_at(rays: &[u8], format: RayFormat, index: u64) -> Ray {
        format.decode(&rays[index as usize * format.size()..])
    }

    #[test]
    fn the_documented_random_numbers_are_splitmix64() {
        // With seed 0, index n is SplitMix64's state after n steps from 0: its published outputs (Steele, Lea and
        // Flood; Vigna's splitmix64.c) are n = 1, 2, 3, 4, here ray 0's k = 1 .. 4.
        let published = [0xe220_a839_7b1d_cdaf, 0x6e78_9e6a_a1b9_65f4, 0x06c4_5d18_8009_454f, 0xf88b_b8a8_724c_81ec];
        for (n, expected) in (1..).zip(published) {
            assert_eq!(documented_splitmix64(0, n), expected, "output {n}");
        }
        for (seed, index) in [(0, 1), (7, 0), (0x0123_4567_89ab_cdef, 8 * 1_000_003 + 1), (u64::MAX, 12_345)] {
            assert_eq!(uniform(seed, index), documented_uniform(seed, index / 8, index % 8), "u({seed}, {index})");
        }
    }

    #[test]
    fn jittered_camera_rays_pass_through_the_documented_point_of_their_pixel() {
        // Pixels of one world unit around the origin, looking down −z: ray i's point (px, py) in the image, in
        // pixels from the top left, is (x + u(seed, i·8), y + u(seed, i·8 + 1)) for its pixel (x, y) = (p % width,
        // p / width), p = i / samples.
        let (width, height, samples, seed) = (5, 4, 3, 0x0123_4567_89ab_cdef);
        let sampling = PixelSampling { samples, jitter_seed: Some(seed) };
        let orthographic = Orthographic {
            eye: Vec3::ZERO,
            target: Vec3::NEG_Z,
            up: Vec3::Y,
            view_height: height as f32,
            width,
            height,
        };
        // A 90° field of view: the image plane at distance 1 is 2 high and 2·width/height wide.
        let pinhole = Camera { eye: Vec3::ZERO, target: Vec3::NEG_Z, up: Vec3::Y, fov_y_degrees: 90.0, width, height };
        let format = RayFormat::Full;
        let orthographic_rays = Generator::Orthographic(orthographic, sampling).rays(format);
        let pinhole_rays = Generator::Pinhole(pinhole, sampling).rays(format);
        let rays = u64::from(width * height * samples);
        for i in [0, 1, 2, 3, 7, 31, rays - 1] {
            let pixel = i / u64::from(samples);
            let (x, y) = ((pixel % u64::from(width)) as f32, (pixel / u64::from(width)) as f32);
            let (px, py) = (x + documented_uniform(seed, i, 0), y + documented_uniform(seed, i, 1));
            // Image point (px, py) is (px − width/2, height/2 − py) in world units across and up.
            let (across, up) = (px - width as f32 / 2.0, height as f32 / 2.0 - py);
            let parallel = ray_at(&orthographic_rays, format, i);
            let expected_origin = Vec3A::new(across, up, 0.0);
            assert!((parallel.origin - expected_origin).length() < 1e-5, "orthographic ray {i}: {parallel:?}");
            assert_eq!(parallel.direction, Vec3A::NEG_Z, "orthographic ray {i}");
            let through_eye = ray_at(&pinhole_rays, format, i);
            let expected_direction = Vec3A::new(across, up, -(height as f32) / 2.0).normalize();
            assert_eq!(through_eye.origin, Vec3A::ZERO, "pinhole ray {i}");
            assert!((through_eye.direction - expected_direction).length() < 1e-5, "pinhole ray {i}: {through_eye:?}");
        }
    }

    #[test]
    fn sphere_samples_take_the_documented_random_numbers_in_order() {
        // Ray i is sample i % samples of point i / samples, from u0 = u(seed, i·8) and u1 = u(seed, i·8 + 1). On the
        // sphere (the engine's mapping; the contract names only the numbers): z = 1 − 2·u0, azimuth 2π·u1 about +z.
        // On a hemisphere: cosine-distributed, at cos θ = √(1 − u0) from the normal.
        let (samples, seed) = (4, 0xfedc_ba98_7654_3210);
        let points = vec![Vec3::new(1.0, 2.0, 3.0), Vec3::new(-4.0, 5.0, -6.0), Vec3::new(0.5, 0.0, 0.25)];
        let normals = vec![Vec3::X, Vec3::new(0.0, -2.0, 0.0), Vec3::new(1.0, 1.0, 1.0)];
        let uniform_sphere =
            SphereSampling { points, normals: Vec::new(), samples, min_distance: 0.25, max_distance: 8.0, seed };
        let hemisphere = SphereSampling { normals: normals.clone(), ..uniform_sphere.clone() };
        let format = RayFormat::OriginTminDirectionTmax;
        let sphere_rays = Generator::Sphere(uniform_sphere.clone()).rays(format);
        let hemisphere_rays = Generator::Sphere(hemisphere).rays(format);
        for i in [0, 1, 3, 4, 6, 11] {
            let point = (i / u64::from(samples)) as usize;
            let (u0, u1) = (documented_uniform(seed, i, 0), documented_uniform(seed, i, 1));
            let ray = ray_at(&sphere_rays, format, i);
            assert_eq!(ray.origin, Vec3A::from(uniform_sphere.points[point]), "ray {i} starts at point {point}");
            assert_eq!((ray.tmin, ray.tmax), (0.25, 8.0), "ray {i}");
            let z = 1.0 - 2.0 * u0;
            let (sin, cos) = (std::f32::consts::TAU * u1).sin_cos();
            let r = (1.0 - z * z).sqrt();
            let expected = Vec3A::new(r * cos, r * sin, z);
            assert!((ray.direction - expected).length() < 1e-5, "sphere ray {i}: {:?}, {expected:?}", ray.direction);
            let ray = ray_at(&hemisphere_rays, format, i);
            assert_eq!(ray.origin, Vec3A::from(uniform_sphere.points[point]), "ray {i} starts at point {point}");
            let cos_theta = Vec3::from(ray.direction).dot(normals[point].normalize());
            assert!((cos_theta - (1.0 - u0).sqrt()).abs() < 1e-5, "hemisphere ray {i}: cos θ {cos_theta}, u0 {u0}");
        }
    }

    #[test]
    fn bad_numbers_are_refused_naming_the_field() {
        let mut flat = camera();
        flat.up = Vec3::new(0.0, 0.0, -1.0);
        let error = Generator::Pinhole(flat, CENTRES).check().unwrap_err().to_string();
        assert!(error.contains("generator.up") && error.contains("parallel"), "{error}");
        let blind = Camera { target: camera().eye, ..camera() };
        let error = Generator::Pinhole(blind, CENTRES).check().unwrap_err().to_string();
        assert!(error.contains("generator.target") && error.contains("differ from the eye"), "{error}");
        let Camera { eye, target, width, height, .. } = camera();
        let lost = Orthographic { eye, target, up: Vec3::NAN, view_height: 3.0, width, height };
        let error = Generator::Orthographic(lost, CENTRES).check().unwrap_err().to_string();
        assert!(error.contains("generator.up") && error.contains("finite"), "{error}");
        let wide = Camera { fov_y_degrees: 180.0, ..camera() };
        assert!(Generator::Pinhole(wide, CENTRES).check().unwrap_err().to_string().contains("fov_y_degrees"));
        let none = PixelSampling { samples: 0, jitter_seed: None };
        assert!(Generator::Pinhole(camera(), none).check().unwrap_err().to_string().contains("samples_per_pixel"));
        let sphere = around_the_origin(Vec3::ZERO, 1, 0);
        assert!(sphere.check().unwrap_err().to_string().contains("generator.normals"));
        // Finite times whose span is not: the first step's time would be NaN.
        let lidar = Lidar {
            origin: Vec3::ZERO,
            forward: Vec3::X,
            up: Vec3::Z,
            elevations_degrees: vec![0.0],
            steps: 4,
            min_range: 0.0,
            max_range: 1.0,
            time: (-3e38, 3e38),
        };
        assert!(Generator::Lidar(lidar.clone()).check().unwrap_err().to_string().contains("generator.time"));
        // Each field of a pair named when it is the one at fault.
        let error = |generator: Generator| generator.check().unwrap_err().to_string();
        assert!(error(Generator::Pinhole(Camera { height: 0, ..camera() }, CENTRES)).contains("generator.height"));
        let unreached = Lidar { max_range: f32::NAN, time: (0.0, 0.0), ..lidar.clone() };
        assert!(error(Generator::Lidar(unreached)).contains("generator.max_range"));
        let behind = Lidar { min_range: -1.0, time: (0.0, 0.0), ..lidar };
        assert!(error(Generator::Lidar(behind)).contains("generator.min_range"));
        // A view height whose width passes f32's range.
        let Camera { eye, target, up, .. } = camera();
        let vast = Orthographic { eye, target, up, view_height: 2e38, width: 4, height: 1 };
        assert!(error(Generator::Orthographic(vast, CENTRES)).contains("generator.view_height"));
        // Cameras of up to 2^48 rays, no more: their rays' numbers and jitter counters stay within u64.
        let most = PixelSampling { samples: 1 << 16, jitter_seed: Some(1) };
        let largest = Camera { width: 1 << 16, height: 1 << 16, ..camera() };
        Generator::Pinhole(largest, most).check().expect("2^48 rays");
        let over = PixelSampling { samples: (1 << 16) + 1, ..most };
        assert!(error(Generator::Pinhole(largest, over)).contains("generator.samples_per_pixel"));
        let huge = Camera { width: u32::MAX, height: u32::MAX, ..camera() };
        let sampling = PixelSampling { samples: u32::MAX, jitter_seed: None };
        assert!(error(Generator::Pinhole(huge, sampling)).contains("more than 2^48 rays"));
    }

    #[test]
    fn vectors_too_long_or_too_short_for_their_squared_length_still_give_a_direction() {
        let far_apart = Camera { eye: Vec3::new(-1e20, 0.0, 0.0), target: Vec3::new(1e20, 0.0, 0.0), ..camera() };
        let frame = Generator::Pinhole(far_apart, CENTRES).camera_frame().unwrap();
        assert_eq!((frame.forward, frame.right.length()), (Vec3::X, 1.0));
        for normal in [1e20, 1e-22, 1e-30].map(|x| Vec3::new(x, 0.0, 0.0)) {
            let generator = around_the_origin(normal, 8, 0);
            generator.check().unwrap();
            let rays = generator.rays(RayFormat::OriginDirection);
            let directions = rays.chunks_exact(24).map(|ray| RayFormat::OriginDirection.decode(ray).direction);
            assert!(directions.into_iter().all(|d| d.x > 0.0 && (d.length() - 1.0).abs() < 1e-6), "{normal}");
        }
        assert_eq!((unit(Vec3::new(1e-22, 0.0, 0.0)), unit(Vec3::new(0.0, -3e19, 0.0))), (Vec3::X, Vec3::NEG_Y));
        assert_eq!(unit(Vec3::ZERO), Vec3::ZERO);
        assert_eq!(unit(Vec3::new(f32::INFINITY, 0.0, 0.0)), Vec3::ZERO);
    }

    #[test]
    fn a_lidar_spins_about_up_from_forward_laid_on_the_plane_across_it() {
        let lidar = Lidar {
            origin: Vec3::ZERO,
            forward: Vec3::new(1.0, 0.0, 1.0),
            up: Vec3::Z,
            elevations_degrees: vec![0.0],
            steps: 4,
            min_range: 0.0,
            max_range: 1.0,
            time: (0.0, 0.0),
        };
        let rays = Generator::Lidar(lidar.clone()).rays(RayFormat::OriginDirection);
        let ray = |i: usize| RayFormat::OriginDirection.decode(&rays[i * 24..]).direction;
        for (step, expected) in [Vec3A::X, Vec3A::Y, -Vec3A::X, -Vec3A::Y].into_iter().enumerate() {
            assert!((ray(step) - expected).length() < 1e-6, "step {step}: {}", ray(step));
        }
        // Off every axis, and nearly along up: still level with the plane across up, a quarter turn apart.
        for (forward, up) in [((8.999999, -3.0, 12.0), (3.0, -1.0, 4.0)), ((1.0, 1.0000001, 0.0), (1.0, 1.0, 0.0))] {
            let (forward, up) = (Vec3::from(forward), Vec3::from(up));
            let tilted = Lidar { forward, up, steps: 4, ..lidar.clone() };
            let rays = Generator::Lidar(tilted).rays(RayFormat::OriginDirection);
            let ray = |i: usize| Vec3::from(RayFormat::OriginDirection.decode(&rays[i * 24..]).direction);
            for step in 0..4 {
                assert!(ray(step).dot(up.normalize()).abs() < 1e-6 && (ray(step).length() - 1.0).abs() < 1e-6);
                assert!(ray(step).dot(ray((step + 1) % 4)).abs() < 1e-6, "{forward} {up}: step {step}");
            }
            assert!(ray(0).dot(forward) > 0.0, "azimuth 0 towards forward");
        }
    }

    #[test]
    fn camera_rays_of_an_image_as_wide_as_u32_allows_are_those_made_by_index() {
        let widest = Camera { width: u32::MAX, height: 2, ..camera() };
        let frame = Generator::Pinhole(widest, CENTRES).camera_frame().unwrap();
        let (first, format) = (u64::from(u32::MAX) - 15, RayFormat::OriginDirection);
        let mut made = vec![0; 32 * format.size()];
        frame.fill(format, first, &mut made);
        for (index, slot) in (first..).zip(made.chunks_exact(format.size())) {
            let mut expected = vec![0; format.size()];
            format.encode(&frame.ray(index), &mut expected);
            assert_eq!(slot, expected, "ray {index}");
        }
    }

    /// The bytes of generators whose rays take sines and tangents, as a CRC-32 each: a client and a server expand a
    /// generator byte for byte whatever platform each runs on (`proto/rayd/v1/trace.proto`), which the standard
    /// library's `sin_cos` and `tan` (the platform C library's) do not give — glibc's and musl's differ in the last
    /// bit for 2.5% of angles and 14% of tangents, and these generators meet such angles, so this test fails on
    /// glibc with them. The numbers change only with a deliberate change of what the generators make, which breaks
    /// clients expanding with an earlier engine and must be documented as such.
    #[test]
    fn generators_make_the_same_bytes_on_every_platform() {
        let format = RayFormat::OriginTminDirectionTmaxTime;
        let crc = |generator: &Generator| crc32fast::hash(&generator.rays(format));
        let cameras: Vec<u32> = [20.0, 33.3, 45.0, 47.0, 60.0, 75.5, 90.0, 120.0]
            .into_iter()
            .map(|fov_y_degrees| {
                let camera = Camera { fov_y_degrees, width: 16, height: 9, ..camera() };
                crc(&Generator::Pinhole(camera, PixelSampling { samples: 2, jitter_seed: Some(5) }))
            })
            .collect();
        let lidar = Generator::Lidar(Lidar {
            origin: Vec3::new(1.0, 2.0, 3.0),
            forward: Vec3::new(1.0, 0.5, 0.0),
            up: Vec3::Z,
            elevations_degrees: (0..32).map(|c| c as f32 * 1.3 - 25.0).collect(),
            steps: 720,
            min_range: 0.5,
            max_range: 100.0,
            time: (0.0, 0.1),
        });
        let sphere = |normals: Vec<Vec3>| {
            Generator::Sphere(SphereSampling {
                points: vec![Vec3::ZERO, Vec3::new(1.0, -2.0, 0.5)],
                normals,
                samples: 4096,
                min_distance: 1e-3,
                max_distance: 10.0,
                seed: 11,
            })
        };
        let made = (cameras, crc(&lidar), crc(&sphere(vec![])), crc(&sphere(vec![Vec3::Z, Vec3::new(1.0, 2.0, -0.5)])));
        let cameras =
            vec![3804399255, 512915786, 3235026635, 2181344225, 4139667928, 2425252289, 2265301782, 2630309932];
        let expected = (cameras, 2284413029, 3053845655, 3021315813);
        assert_eq!(made, expected, "(pinhole cameras, lidar, sphere, hemisphere)");
    }
}
