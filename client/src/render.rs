//! Pictures of a scene for a person to look at, made through the trace API: one primary ray a pixel, shaded by
//! the surface normal or by depth, written as PNG.

use std::path::Path;

use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::query::Query;
use rayd_engine::raygen::{Camera, Generator, PixelSampling};

use crate::client::Client;
use crate::error::{Error, Result};
use crate::view::HitView;

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
    /// The hit format that carries what this shading needs.
    pub fn hit_format(self) -> HitFormat {
        match self {
            Shading::Normal => HitFormat::Full,
            Shading::Depth => HitFormat::T,
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
    /// Writes the picture as a PNG file.
    pub fn write_png(&self, path: &Path) -> Result<()> {
        let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), self.width, self.height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let encoded = encoder.write_header().and_then(|mut writer| writer.write_image_data(&self.rgb));
        encoded.map_err(|e| Error::io(path, std::io::Error::other(e)))
    }
}

impl Client {
    /// Renders the accel called `accel` as `camera` sees it (one closest-hit ray through each pixel's centre,
    /// made by the server from the camera: no ray crosses the network).
    pub async fn render(&self, accel: &str, camera: &Camera, shading: Shading) -> Result<Image> {
        let query = Query::closest(RayFormat::OriginDirection, shading.hit_format());
        let centres = PixelSampling { samples: 1, jitter_seed: None };
        let traced = self.trace_generated(accel, &query, &Generator::Pinhole(*camera, centres)).await?;
        Ok(shade(&traced.hit_view(), camera.width, camera.height, shading))
    }
}

/// Colours one hit record a pixel (hits in `shading.hit_format()`).
pub fn shade(hits: &HitView, width: u32, height: u32, shading: Shading) -> Image {
    let (near, far) = hits
        .iter()
        .filter(|h| h.is_hit())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(near, far), h| (near.min(h.t), far.max(h.t)));
    let rgb = hits
        .iter()
        .flat_map(|hit| {
            if !hit.is_hit() {
                return BACKGROUND;
            }
            let unit = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
            match shading {
                Shading::Normal => {
                    let facing = if hit.back_face { -hit.normal } else { hit.normal };
                    facing.to_array().map(|n| unit(0.5 + 0.5 * n))
                }
                Shading::Depth => [unit(1.0 - 0.8 * (hit.t - near) / (far - near).max(f32::MIN_POSITIVE)); 3],
            }
        })
        .collect();
    Image { width, height, rgb }
}

#[cfg(test)]
mod tests {
    use glam::Vec3A;
    use rayd_engine::format::Hit;

    use super::*;

    #[test]
    fn misses_are_background_normals_face_the_camera_and_depth_brightens_near_hits() {
        let format = HitFormat::Full;
        let hits = [
            Hit::MISS,
            Hit { t: 1.0, normal: Vec3A::X, ..Hit::MISS },
            Hit { t: 3.0, normal: Vec3A::X, back_face: true, ..Hit::MISS },
        ];
        let mut bytes = vec![0u8; format.buffer_len(3)];
        for (i, hit) in hits.iter().enumerate() {
            format.write(&mut bytes, i, hit);
        }
        let view = HitView::new(&bytes, format, 3).unwrap();
        let image = shade(&view, 3, 1, Shading::Normal);
        assert_eq!(image.rgb, [40, 40, 40, 255, 128, 128, 0, 128, 128]);
        let image = shade(&view, 3, 1, Shading::Depth);
        assert_eq!(image.rgb, [40, 40, 40, 255, 255, 255, 51, 51, 51]);
    }

    #[test]
    fn png_has_the_picture_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("picture.png");
        Image { width: 2, height: 1, rgb: vec![1, 2, 3, 4, 5, 6] }.write_png(&path).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let info = decoder.read_info().unwrap().info().clone();
        assert_eq!((info.width, info.height, info.color_type), (2, 1, png::ColorType::Rgb));
    }
}
