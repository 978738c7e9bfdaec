//! What the wgpu backend does on the device that the host does for other backends ([`crate::backend::host`]):
//! camera generators expanded by the kernel (`shaders/generate.wgsl`), the image reduction's pixels made by its
//! pass (`shaders/reduce.wgsl`), and hit counts taken from the kernel's tallies. So only the reduction, not every
//! ray and hit, crosses the bus. Other generators (lidar, sphere, secondary rays) and other reductions stay on
//! the host.

use glam::Vec3;
use rayon::prelude::*;

use super::batch::{GENERATOR_WORDS, GeneratorBlock, Input};
use super::kernel::Rays;
use crate::query::{Query, QueryKind, TraceStats};
use crate::raygen::Generator;
use crate::reduce::{Image, ImageChannel, PARALLEL_SPLIT_RAYS, Partial, Reduction};

/// The kernel's input for rays `first .. first + count` of a checked `generator`: `None` unless it is a camera
/// whose rays there have 32-bit indices (the kernel's).
pub(super) fn generated(generator: &Generator, first: u64, count: usize) -> Option<Input<'static>> {
    let frame = generator.camera_frame()?;
    if first.checked_add(count as u64)? > 1 << 32 {
        return None;
    }
    let seed = frame.sampling.jitter_seed.unwrap_or(0);
    let vec = |v: Vec3| v.to_array().map(f32::to_bits);
    let mut block: GeneratorBlock = [0; GENERATOR_WORDS];
    block[0..3].copy_from_slice(&vec(frame.eye));
    block[3..6].copy_from_slice(&vec(frame.forward));
    block[6..9].copy_from_slice(&vec(frame.right));
    block[9..12].copy_from_slice(&vec(frame.up));
    block[12..16].copy_from_slice(&[frame.half.0, frame.half.1, frame.size.0, frame.size.1].map(f32::to_bits));
    block[16..21].copy_from_slice(&[
        frame.width,
        frame.sampling.samples,
        u32::from(frame.sampling.jitter_seed.is_some()),
        seed as u32,
        (seed >> 32) as u32,
    ]);
    let rays = if frame.pinhole { Rays::Pinhole } else { Rays::Orthographic };
    Some(Input::Generated { rays, block, first: first as u32 })
}

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

    /// The partial of a piece whose trace gave back `pixels` (for an image) and `stats`.
    pub fn partial(&self, pixels: &[u8], stats: &TraceStats) -> Partial {
        match self {
            OnDevice::Counts => Partial::Sums(vec![stats.rays, stats.rays_hit, stats.rays_hit]),
            OnDevice::Image(image) => {
                let pixel_bytes = 4 * OnDevice::pixel_words(image) as usize;
                let parts: Vec<Vec<u8>> = pixels
                    .par_chunks(PARALLEL_SPLIT_RAYS * pixel_bytes)
                    .map(|part| {
                        let mut out = Vec::with_capacity(part.len());
                        for pixel in part.chunks_exact(pixel_bytes) {
                            let word = |i: usize| f32::from_le_bytes(pixel[4 * i..4 * i + 4].try_into().unwrap());
                            match image.channel {
                                ImageChannel::Depth => image.push_depth(Some(word(0)).filter(|t| *t >= 0.0), &mut out),
                                ImageChannel::Normal => {
                                    let hit = word(3).to_bits() != 0;
                                    image.push_normal(hit.then(|| Vec3::new(word(0), word(1), word(2))), &mut out)
                                }
                            }
                        }
                        out
                    })
                    .collect();
                Partial::Ordered { bytes: parts.concat(), dropped: 0 }
            }
        }
    }
}
