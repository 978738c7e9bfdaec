//! What the wgpu backend does on the device that the host does for other backends ([`crate::backend::host`]):
//! camera and lidar generators expanded by the kernel (`shaders/generate.wgsl`), the image reduction's pixels made
//! by its pass (`shaders/reduce.wgsl`), and hit counts taken from the kernel's tallies. So only the reduction, not
//! every ray and hit, crosses the bus. Other generators (sphere sampling, whose random directions need exact sines, and
//! secondary rays) and other reductions stay on the host.

use glam::Vec3;
use rayon::prelude::*;

use super::batch::Input;
use super::kernel::Rays;
use crate::query::{Query, QueryKind, TraceStats};
use crate::raygen::{Generator, LidarFrame};
use crate::reduce::{Image, ImageChannel, PARALLEL_SPLIT_RAYS, Partial, Reduction};

/// A generator whose rays the kernel makes (`generate.wgsl`): a camera or a lidar, for a batch of rays with 32-bit
/// indices.
#[derive(Debug, Clone, Copy)]
pub(super) struct DeviceGenerator<'a> {
    /// The generator.
    generator: &'a Generator,
    /// Its pipeline.
    pub rays: Rays,
    /// The generator's index of the batch's first ray.
    pub first: u32,
}

impl<'a> DeviceGenerator<'a> {
    /// The kernel's generator for rays `first .. first + count` of a checked `generator`: `None` unless it is a
    /// camera or a lidar whose rays there have 32-bit indices.
    pub fn input(generator: &'a Generator, first: u64, count: usize) -> Option<Input<'a>> {
        let rays = match generator {
            Generator::Pinhole(..) => Rays::Pinhole,
            Generator::Orthographic(..) => Rays::Orthographic,
            Generator::Lidar(..) => Rays::Lidar,
            _ => return None,
        };
        if first.checked_add(count as u64)? > 1 << 32 {
            return None;
        }
        Some(Input::Generated(DeviceGenerator { generator, rays, first: first as u32 }))
    }

    /// Words [`DeviceGenerator::words`] writes for a chunk of `rays` rays at most.
    pub fn most_words(&self, rays: usize) -> usize {
        match self.generator {
            Generator::Lidar(lidar) => {
                let channels = lidar.elevations_degrees.len();
                LIDAR_HEADER_WORDS + 2 * channels + 3 * (rays.div_ceil(channels) + 1)
            }
            _ => CAMERA_WORDS,
        }
    }

    /// The generator's numbers for the chunk of rays `first .. first + rays` as the kernel reads them (layouts in
    /// `generate.wgsl`): a camera's frame, or a lidar's frame, its channels' elevations and the chunk's steps.
    pub fn words(&self, first: u32, rays: usize) -> Vec<u32> {
        let vec = |v: Vec3| v.to_array().map(f32::to_bits);
        let mut words = Vec::with_capacity(self.most_words(rays));
        if let Generator::Lidar(lidar) = self.generator {
            let frame = LidarFrame::new(lidar);
            let channels = lidar.elevations_degrees.len() as u64;
            let steps = u64::from(first) / channels..=(u64::from(first) + rays as u64 - 1) / channels;
            for v in [lidar.origin, frame.forward, frame.left, frame.up] {
                words.extend(vec(v));
            }
            words.extend([
                lidar.min_range.to_bits(),
                lidar.max_range.to_bits(),
                channels as u32,
                *steps.start() as u32,
            ]);
            for channel in (0..lidar.elevations_degrees.len()).map(|c| frame.channel(c)) {
                words.extend([channel.sin, channel.cos].map(f32::to_bits));
            }
            for step in steps.map(|s| frame.step(s)) {
                words.extend([step.sin, step.cos, step.time].map(f32::to_bits));
            }
            return words;
        }
        let frame = self.generator.camera_frame().expect("a camera");
        let seed = frame.sampling.jitter_seed.unwrap_or(0);
        for v in [frame.eye, frame.forward, frame.right, frame.up] {
            words.extend(vec(v));
        }
        words.extend([frame.half.0, frame.half.1, frame.size.0, frame.size.1].map(f32::to_bits));
        words.extend([
            frame.width,
            frame.sampling.samples,
            u32::from(frame.sampling.jitter_seed.is_some()),
            seed as u32,
            (seed >> 32) as u32,
        ]);
        words
    }
}

/// Words of a camera's block.
const CAMERA_WORDS: usize = 21;
/// Words of a lidar's block before its channels.
const LIDAR_HEADER_WORDS: usize = 16;

/// The bits of a depth pixel whose rays all missed (`NONE` in `reduce.wgsl`: a NaN, which no hit's `t` is).
const MISSED_PIXEL: u32 = u32::MAX;

/// A reduction the device makes.
#[derive(Debug, Clone, Copy)]
pub(super) enum OnDevice {
    /// An image: its pixels made by the pixel pass, encoded on the host.
    Image(Image),
    /// Counts of a closest or any query: rays and rays hit, from the tallies.
    Counts,
}

impl OnDevice {
    /// How the device makes `reduction` of `query`, if it can.
    pub fn of(reduction: &Reduction, query: &Query) -> Option<OnDevice> {
        match reduction {
            Reduction::Image(image) => Some(OnDevice::Image(*image)),
            Reduction::Counts if matches!(query.kind, QueryKind::Closest | QueryKind::Any) => Some(OnDevice::Counts),
            _ => None,
        }
    }

    /// Words a pixel of the pixel pass writes (`reduce.wgsl`).
    pub fn pixel_words(image: &Image) -> u32 {
        match image.channel {
            ImageChannel::Depth => 1,
            ImageChannel::Normal => 4,
        }
    }

    /// The partial of a piece whose trace gave back `image_bytes` (for an image: its pixels, encoded by
    /// [`encode_pixels`] as each chunk came back) and `stats`.
    pub fn partial(&self, image_bytes: Vec<u8>, stats: &TraceStats) -> Partial {
        match self {
            OnDevice::Counts => Partial::Sums(vec![stats.rays, stats.rays_hit, stats.rays_hit]),
            OnDevice::Image(_) => Partial::Ordered { bytes: image_bytes, dropped: 0 },
        }
    }
}

/// Encodes the pixel pass's `pixels` (`pixel_words` little-endian words a pixel, `reduce.wgsl`) of `image` into
/// `out`, those pixels' place in the image, on the rayon pool: straight out of the mapped staging buffer into the
/// image, with no intermediate copy (a 16 MiB buffer zeroed on one thread cost milliseconds a 4-megapixel image).
pub(super) fn encode_pixels(image: &Image, pixels: &[u8], out: &mut [u8]) {
    let (pixel_bytes, encoded_bytes) = (4 * OnDevice::pixel_words(image) as usize, image.pixel_bytes());
    out.par_chunks_mut(PARALLEL_SPLIT_RAYS * encoded_bytes)
        .zip(pixels.par_chunks(PARALLEL_SPLIT_RAYS * pixel_bytes))
        .for_each(|(out, part)| {
            for (pixel, out) in part.chunks_exact(pixel_bytes).zip(out.chunks_exact_mut(encoded_bytes)) {
                let word = |i: usize| f32::from_le_bytes(pixel[4 * i..4 * i + 4].try_into().unwrap());
                match image.channel {
                    ImageChannel::Depth => {
                        let hit = word(0).to_bits() != MISSED_PIXEL;
                        image.write_depth(hit.then(|| word(0)), out)
                    }
                    ImageChannel::Normal => {
                        let hit = word(3).to_bits() != 0;
                        image.write_normal(hit.then(|| Vec3::new(word(0), word(1), word(2))), out)
                    }
                }
            }
        });
}
