//! Pictures of a scene for a person to look at, made through the trace API: one primary ray a pixel, made by the
//! server from a camera and reduced by it to an image of depths or normals (neither rays nor hits cross the
//! network), shaded here and written as PNG.

use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::query::Query;
use rayd_engine::raygen::{Camera, Generator, PixelSampling};
use rayd_engine::reduce::{ImageChannel, PixelEncoding, Reduction};

use crate::client::Client;
use crate::error::{Error, Result};

/// Colour of pixels whose ray hit nothing (dark grey).
const BACKGROUND: [u8; 3] = [40, 40, 40];

/// How a hit becomes a colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shading {
    /// The unit geometric normal, turned to face the camera, as RGB = 0.5 + 0.5·n.
    Normal,
    /// Distance: nearest hit white, farthest dark.
    Depth,
}

impl Shading {
    /// The image channel this shading colours.
    pub fn channel(self) -> ImageChannel {
        match self {
            Shading::Normal => ImageChannel::Normal,
            Shading::Depth => ImageChannel::Depth,
        }
    }
}

/// An 8-bit RGB picture, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Pixels a row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// `width × height` RGB triples.
    pub rgb: Vec<u8>,
}

impl Image {
    /// The picture encoded as a PNG file's bytes.
    pub fn png(&self) -> Result<Vec<u8>> {
        let mut bytes = Vec::new();
        let mut encoder = png::Encoder::new(&mut bytes, self.width, self.height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let encoded = encoder.write_header().and_then(|mut writer| {
            writer.write_image_data(&self.rgb)?;
            writer.finish()
        });
        encoded.map_err(|e| Error::InvalidArgument(format!("the picture cannot be encoded as PNG: {e}")))?;
        Ok(bytes)
    }
}

impl Client {
    /// Renders the accel called `accel` as `camera` sees it: one closest-hit ray through each pixel's centre, made
    /// by the server from the camera and reduced by it to a float32 image of depths or normals (in ranges of rows
    /// where the image could pass half a message: [`Client::trace_generated_reduced_in_ranges`]).
    pub async fn render(&self, accel: &str, camera: &Camera, shading: Shading) -> Result<Image> {
        let query = Query::closest(RayFormat::OriginDirection, HitFormat::T);
        let centres = PixelSampling { samples: 1, jitter_seed: None };
        let image = rayd_engine::reduce::Image {
            width: camera.width,
            rays_per_pixel: 1,
            channel: shading.channel(),
            encoding: PixelEncoding::Float32,
            near: 0.0,
            far: 0.0,
        };
        let generator = Generator::Pinhole(*camera, centres);
        let traced =
            self.trace_generated_reduced_in_ranges(accel, &query, &generator, &Reduction::Image(image)).await?;
        let expected = camera.width as usize * camera.height as usize * if shading == Shading::Normal { 12 } else { 4 };
        if traced.data.len() != expected {
            let got = traced.data.len();
            return Err(Error::Protocol(format!("an image of {got} bytes, {expected} expected")));
        }
        Ok(shade(&traced.data, camera.width, camera.height, shading))
    }
}

/// Colours a float32 image of the reduction's channel for `shading` (depth: 4 bytes a pixel, +∞ for a miss;
/// normal: 12 bytes, the normal facing the ray, zero for a miss).
pub fn shade(pixels: &[u8], width: u32, height: u32, shading: Shading) -> Image {
    let floats: Vec<f32> = pixels.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes"))).collect();
    let unit = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let rgb = match shading {
        Shading::Normal => floats
            .chunks_exact(3)
            .flat_map(|n| {
                if n == [0.0; 3] {
                    BACKGROUND
                } else {
                    [unit(0.5 + 0.5 * n[0]), unit(0.5 + 0.5 * n[1]), unit(0.5 + 0.5 * n[2])]
                }
            })
            .collect(),
        Shading::Depth => {
            let hits = || floats.iter().copied().filter(|t| t.is_finite());
            let (near, far) =
                hits().fold((f32::INFINITY, f32::NEG_INFINITY), |(near, far), t| (near.min(t), far.max(t)));
            floats
                .iter()
                .flat_map(|&t| match t.is_finite() {
                    true => [unit(1.0 - 0.8 * (t - near) / (far - near).max(f32::MIN_POSITIVE)); 3],
                    false => BACKGROUND,
                })
                .collect()
        }
    };
    Image { width, height, rgb }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn misses_are_background_normals_are_colours_and_depth_brightens_near_hits() {
        let floats = |values: &[f32]| values.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>();
        let normals = floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 0.0]);
        let image = shade(&normals, 3, 1, Shading::Normal);
        assert_eq!(image.rgb, [40, 40, 40, 255, 128, 128, 0, 128, 128]);
        let depths = floats(&[f32::INFINITY, 1.0, 3.0]);
        let image = shade(&depths, 3, 1, Shading::Depth);
        assert_eq!(image.rgb, [40, 40, 40, 255, 255, 255, 51, 51, 51]);
    }

    #[test]
    fn png_has_the_picture_size() {
        let png = Image { width: 2, height: 1, rgb: vec![1, 2, 3, 4, 5, 6] }.png().unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(png));
        let info = decoder.read_info().unwrap().info().clone();
        assert_eq!((info.width, info.height, info.color_type), (2, 1, png::ColorType::Rgb));
    }
}
