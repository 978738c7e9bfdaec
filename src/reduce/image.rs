//! The image reduction: each pixel's nearest hit as a depth or a normal, in float32, 16-bit or a 16-bit PNG.

use glam::Vec3;

use super::invalid;
use crate::error::{Error, Result};
use crate::format::HitFormat;

/// An image of the nearest hit among each pixel's `rays_per_pixel` consecutive rays, pixels row by row from the top
/// left (the order of the camera generators). Its height is the batch's rays / (`width` × `rays_per_pixel`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Image {
    /// Pixels a row, at least 1.
    pub width: u32,
    /// Consecutive rays a pixel, 1 to [`super::MAX_GROUP_RAYS`].
    pub rays_per_pixel: u32,
    /// What a pixel shows.
    pub channel: ImageChannel,
    /// How a pixel is written.
    pub encoding: PixelEncoding,
    /// For depth in 16 bits: the distance written as 0 …
    pub near: f32,
    /// … and the distance written as 65,534 (farther hits clamp to it; 65,535 is a miss).
    pub far: f32,
}

/// What an image's pixel shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageChannel {
    /// The nearest hit's `t` (a distance for unit directions). Float32: a miss is +∞.
    Depth,
    /// The unit geometric normal in world space, turned to face the ray. A miss is (0, 0, 0).
    Normal,
}

/// How an image's pixels are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelEncoding {
    /// Little-endian f32 per channel (depth: 4 bytes a pixel, normal: 12).
    Float32,
    /// Little-endian u16 per channel: depth `round((t − near)/(far − near) · 65534)` clamped to 0 ..= 65,534 and
    /// 65,535 for a miss; normal `round((0.5 + 0.5·n) · 65535)` per component, 0 for a miss.
    Unorm16,
    /// The [`PixelEncoding::Unorm16`] values as a 16-bit PNG (grey for depth, RGB for normals), compressed for speed
    /// (the `png` crate's `Fast` level) rather than size.
    Png,
}

impl ImageChannel {
    /// The hit format that carries what this channel needs (the primitive id at least: it tells a hit behind the
    /// ray's origin from a miss).
    pub fn hit_format(self) -> HitFormat {
        match self {
            ImageChannel::Depth => HitFormat::TTriid,
            ImageChannel::Normal => HitFormat::Full,
        }
    }

    /// Values a pixel.
    fn channels(self) -> usize {
        match self {
            ImageChannel::Depth => 1,
            ImageChannel::Normal => 3,
        }
    }
}

impl Image {
    /// Checks the image against a batch of `rays`.
    pub(super) fn check(&self, rays: u64) -> Result<()> {
        if self.width == 0 {
            return Err(invalid("reduction.image.width", "must be at least 1".into()));
        }
        super::check_groups("reduction.image.rays_per_pixel", self.rays_per_pixel, rays)?;
        let row = u64::from(self.width) * u64::from(self.rays_per_pixel);
        if !rays.is_multiple_of(row) {
            let rule =
                format!("{rays} rays are not whole rows of {} pixels × {} rays", self.width, self.rays_per_pixel);
            return Err(invalid("reduction.image.width", rule));
        }
        let quantized = self.encoding != PixelEncoding::Float32 && self.channel == ImageChannel::Depth;
        if quantized {
            // far − near too: the depth is (t − near)/(far − near), in f32 on every device.
            let rule =
                || format!("near {} and far {} must be finite with near < far, far − near finite", self.near, self.far);
            if !self.near.is_finite() {
                return Err(invalid("reduction.image.near", rule()));
            }
            if !(self.far.is_finite() && self.near < self.far && (self.far - self.near).is_finite()) {
                return Err(invalid("reduction.image.far", rule()));
            }
        }
        if self.encoding == PixelEncoding::Png && rays == 0 {
            return Err(invalid(
                "reduction.image.encoding",
                "a PNG has at least one row: the batch has no rays".into(),
            ));
        }
        Ok(())
    }

    /// Bytes a pixel takes before any PNG compression.
    pub fn pixel_bytes(&self) -> usize {
        let value = if self.encoding == PixelEncoding::Float32 { 4 } else { 2 };
        self.channel.channels() * value
    }

    /// The pixels of `rays` rays (whole pixels) whose records are `hits`, traced in `format`
    /// ([`ImageChannel::hit_format`]), row by row.
    #[inline(always)]
    pub(super) fn pixels(&self, format: HitFormat, hits: &[u8], rays: usize) -> Vec<u8> {
        match (self.channel, self.encoding, self.rays_per_pixel) {
            // The commonest image, a float32 depth of one ray a pixel, with these as constants in its loop: no
            // match a pixel, and each pixel a select of its record's `t` (a hit) or +∞ (a miss).
            (ImageChannel::Depth, PixelEncoding::Float32, 1) => {
                let depth = Image {
                    channel: ImageChannel::Depth,
                    encoding: PixelEncoding::Float32,
                    rays_per_pixel: 1,
                    ..*self
                };
                depth.pixels_as(format, hits, rays)
            }
            _ => self.pixels_as(format, hits, rays),
        }
    }

    /// [`Image::pixels`], inlined where the image is known.
    #[inline(always)]
    fn pixels_as(&self, format: HitFormat, hits: &[u8], rays: usize) -> Vec<u8> {
        let (rays_per_pixel, pixel_bytes) = (self.rays_per_pixel as usize, self.pixel_bytes());
        let mut out = vec![0u8; rays / rays_per_pixel * pixel_bytes];
        for (pixel, first) in out.chunks_exact_mut(pixel_bytes).zip((0..rays).step_by(rays_per_pixel)) {
            let index = match rays_per_pixel {
                1 => first,
                _ => super::nearest(format, hits, first..first + rays_per_pixel),
            };
            self.write_pixel(format, hits, index, pixel);
        }
        out
    }

    /// Writes into `out` ([`Image::pixel_bytes`]) the pixel of record `index` of `hits` (its pixel's nearest,
    /// traced in [`ImageChannel::hit_format`]).
    #[inline(always)]
    fn write_pixel(&self, format: HitFormat, hits: &[u8], index: usize, out: &mut [u8]) {
        match self.channel {
            ImageChannel::Depth => self.write_depth(format.hit_t(hits, index), out),
            ImageChannel::Normal => {
                let hit = format.read(hits, index);
                let facing = if hit.back_face { -hit.normal } else { hit.normal };
                self.write_normal(hit.is_hit().then_some(facing.into()), out)
            }
        }
    }

    /// Writes into `out` ([`Image::pixel_bytes`]) a depth pixel whose nearest hit is at `t` (`None`: every ray of
    /// the pixel missed).
    #[inline(always)]
    pub fn write_depth(&self, t: Option<f32>, out: &mut [u8]) {
        match (self.encoding, t) {
            (PixelEncoding::Float32, t) => out[..4].copy_from_slice(&t.unwrap_or(f32::INFINITY).to_le_bytes()),
            (_, t) => {
                let depth = t.map_or(65535.0, |t| ((t - self.near) / (self.far - self.near)).clamp(0.0, 1.0) * 65534.0);
                self.write_u16(depth.round() as u16, out);
            }
        }
    }

    /// Writes into `out` ([`Image::pixel_bytes`]) a normal pixel whose nearest hit has the unit normal `facing`,
    /// turned to face the ray (`None`: every ray of the pixel missed).
    #[inline(always)]
    pub fn write_normal(&self, facing: Option<Vec3>, out: &mut [u8]) {
        let value_bytes = self.pixel_bytes() / 3;
        for (n, out) in facing.map_or([0.0; 3], |n| n.to_array()).into_iter().zip(out.chunks_exact_mut(value_bytes)) {
            match (self.encoding, facing.is_some()) {
                (PixelEncoding::Float32, _) => out.copy_from_slice(&n.to_le_bytes()),
                (_, true) => self.write_u16(((0.5 + 0.5 * n) * 65535.0).round() as u16, out),
                (_, false) => self.write_u16(0, out),
            }
        }
    }

    /// Writes a 16-bit value: little-endian for [`PixelEncoding::Unorm16`], big-endian for [`PixelEncoding::Png`]
    /// (PNG's sample order, so that [`Image::finish`] compresses the pixels as they are).
    #[inline(always)]
    fn write_u16(&self, value: u16, out: &mut [u8]) {
        let bytes = if self.encoding == PixelEncoding::Png { value.to_be_bytes() } else { value.to_le_bytes() };
        out[..2].copy_from_slice(&bytes);
    }

    /// The whole image from its pixels in order, for a batch of `rays`: the pixels themselves, or a PNG of them.
    pub(super) fn finish(&self, pixels: Vec<u8>, rays: u64) -> Result<Vec<u8>> {
        if self.encoding != PixelEncoding::Png {
            return Ok(pixels);
        }
        let height = rays / (u64::from(self.width) * u64::from(self.rays_per_pixel));
        let height = u32::try_from(height).map_err(|_| invalid("reduction.image.width", "too many rows".into()))?;
        let mut png = Vec::new();
        let mut encoder = png::Encoder::new(&mut png, self.width, height);
        encoder.set_color(match self.channel.channels() {
            1 => png::ColorType::Grayscale,
            _ => png::ColorType::Rgb,
        });
        encoder.set_depth(png::BitDepth::Sixteen);
        // For speed: a 2048² depth image encodes in 13 ms instead of 198 (the default's) and takes 1.9× the bytes,
        // still a fifteenth of the float32 image's (BENCHMARKS.md).
        encoder.set_compression(png::Compression::Fast);
        // The pixels are PNG samples already (big-endian: `Image::write_u16`).
        let written = encoder.write_header().and_then(|mut writer| writer.write_image_data(&pixels));
        written
            .map_err(|e| Error::InvalidQuery { field: "reduction.image", rule: format!("PNG encoding failed: {e}") })?;
        Ok(png)
    }
}
