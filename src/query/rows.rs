//! Rays that follow the rows of an image — a camera's, pixel after pixel and row after row; a lidar's, channel after
//! channel at each step — found from the rays themselves, and the groups the batch driver makes of them: 4×4 tiles,
//! neighbours in both directions, instead of 16 consecutive rays of one row. A backend that traces a group together
//! (the CPU's packets) then follows narrower beams: about 15% faster on camera rays (BENCHMARKS.md, "Camera rays
//! grouped in tiles"). Which rays go together changes no ray's answer.

use std::ops::Range;

use crate::format::{Ray, RayFormat};

/// Rays a tile row and tile rows a tile: a group of [`super::GROUP_RAYS`].
const TILE: usize = 4;

/// Widest image looked for (the search reads up to about two of its rows).
const MAX_WIDTH: usize = 1 << 14;

/// A step from one ray to the next this many times a row's ordinary step ends the row; and the ray below one may be
/// at most this many ordinary steps away from it.
const ROW_END: f32 = 4.0;

/// The rows of an image that a batch's rays follow: ray `first + r·width + c` is row `r`'s ray `c`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageRows {
    /// Rays a row.
    pub width: usize,
    /// The first ray that starts a row: the rays before it end a row begun before the batch.
    pub first: usize,
}

impl ImageRows {
    /// Narrowest rows traced in tiles: two tiles (narrower tiles would make groups too small for a backend's
    /// packets).
    pub const MIN_WIDTH: usize = 2 * TILE;

    /// Widest rows a generator's rays are known to follow ([`crate::raygen::Generator::image_rows`]): wider ones are
    /// traced as consecutive rays, so that a band's rays ([`ImageRows::band`]) and their multiples stay far within
    /// `usize` (a camera's row of `width × samples` rays may reach 2^64).
    pub const MAX_GENERATED_WIDTH: usize = u32::MAX as usize;

    /// The rows that `rays` (packed in `format`) follow, if they do for sixteen rows (four for the narrowest): the
    /// first two row ends are where a ray is much farther from the one before than a row's first rays are from each
    /// other ([`ROW_END`] times, origins and directions together), the width is the distance between them, and it
    /// holds if the next row ends where it should and a ray's neighbour one row down is near it. Anything else —
    /// random rays, rows too narrow or too wide, rays of several pixels' samples in turn — is not an image.
    pub fn find(format: RayFormat, rays: &[u8]) -> Option<ImageRows> {
        let size = format.size();
        let count = rays.len() / size;
        if count < TILE * Self::MIN_WIDTH {
            return None;
        }
        let ray = |i: usize| format.decode(&rays[i * size..(i + 1) * size]);
        let apart = |a: usize, b: usize| distance(&ray(a), &ray(b));
        // A row's ordinary step: the least of the first three (one of them may cross a row's end).
        let step = (0..3).map(|i| apart(i, i + 1)).fold(f32::INFINITY, f32::min);
        if !(step > 0.0 && step.is_finite()) {
            return None;
        }
        // The steps from each ray to the next, each ray decoded once, over an eighth of the batch at most (rows must
        // be 16 at least: the search then costs about 1% of tracing them).
        let searched = (count / 8).max(TILE * Self::MIN_WIDTH).min(count).min(2 * MAX_WIDTH + 1);
        let steps = (1..searched).scan(ray(0), |previous, i| {
            let next = ray(i);
            Some(distance(&std::mem::replace(previous, next), &next))
        });
        let mut ends = steps.enumerate().filter(|&(_, apart)| apart > ROW_END * step).map(|(i, _)| i);
        let (end, next_end) = (ends.next()?, ends.next()?);
        let width = next_end - end;
        let first = (end + 1) % width;
        let is_end = |i: usize| i + 1 >= count || apart(i, i + 1) > ROW_END * step;
        let middle = first + width / 2;
        let image = (Self::MIN_WIDTH..=MAX_WIDTH).contains(&width)
            && end < width
            && first + TILE * width <= count
            && is_end(next_end + width)
            && apart(middle, middle + width) <= ROW_END * step;
        image.then_some(ImageRows { width, first })
    }

    /// The same rows seen from ray `offset` on (indices from there).
    pub fn from_ray(self, offset: usize) -> ImageRows {
        let behind = offset % self.width;
        ImageRows { first: (self.first + self.width - behind) % self.width, ..self }
    }

    /// Rays of a band: the rows of a tile.
    pub fn band(&self) -> usize {
        TILE * self.width
    }

    /// Rays in about `size` rays' worth of whole bands (at least one), in multiples of the fewest bands that make a
    /// multiple of `align` rays; `None` where that overflows.
    pub fn bands_of(&self, size: usize, align: usize) -> Option<usize> {
        let band = self.band();
        let step = align / greatest_common_divisor(band, align);
        (size / band).max(1).div_ceil(step).checked_mul(step)?.checked_mul(band)
    }
}

/// The greatest common divisor of `a` and `b` (Euclid's).
fn greatest_common_divisor(a: usize, b: usize) -> usize {
    if b == 0 { a } else { greatest_common_divisor(b, a % b) }
}

/// `count` rays split into ranges of `size` from ray `first` on: the first range also takes the rays before `first`,
/// the last the rays after the last whole range (so that one range split again is one range).
pub fn split_from(count: usize, first: usize, size: usize) -> Vec<Range<usize>> {
    let ranges = (count.saturating_sub(first) / size).max(1);
    let end = |k: usize| if k == ranges { count } else { first + k * size };
    (0..ranges).map(|k| if k == 0 { 0 } else { end(k) }..end(k + 1)).collect()
}

/// How far apart two rays are: the sum of their origins' and directions' coordinate differences.
fn distance(a: &Ray, b: &Ray) -> f32 {
    (a.origin - b.origin).abs().element_sum() + (a.direction - b.direction).abs().element_sum()
}

/// A group of rays of a chunk: up to [`TILE`] runs of consecutive rays, by index in the chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Group {
    /// The runs (first ray, rays); those past `len` are unused.
    runs: [(usize, usize); TILE],
    /// Runs used.
    len: usize,
}

impl Group {
    /// The group's runs of consecutive rays, (first ray, rays), in the order their rays are handed over.
    pub fn runs(&self) -> &[(usize, usize)] {
        &self.runs[..self.len]
    }

    /// `rays` consecutive rays from `first`.
    fn run(first: usize, rays: usize) -> Group {
        let mut runs = [(0, 0); TILE];
        runs[0] = (first, rays);
        Group { runs, len: 1 }
    }

    /// The tile of rows of `width` rays whose top left ray is `corner`, `columns` rays wide.
    fn tile(corner: usize, width: usize, columns: usize) -> Group {
        Group { runs: std::array::from_fn(|row| (corner + row * width, columns)), len: TILE }
    }
}

/// The groups of the chunk holding rays `chunk` of the batch (in its ray indices; the groups' are the chunk's own):
/// where the chunk holds whole bands of `rows` (a band: the [`TILE`] rows of a row of tiles), their tiles, left to
/// right and band after band; elsewhere `group` consecutive rays at a time.
pub fn groups(chunk: Range<usize>, rows: Option<ImageRows>, group: usize) -> impl Iterator<Item = Group> {
    let start = chunk.start;
    // The tiled part: whole bands, from the first row start in the chunk.
    let tiled = match rows {
        Some(rows) if chunk.end >= rows.first => {
            let from = chunk.start.max(rows.first);
            let from = from + (rows.band() - (from - rows.first) % rows.band()) % rows.band();
            let bands = chunk.end.saturating_sub(from) / rows.band();
            from.min(chunk.end)..from.min(chunk.end) + bands * rows.band()
        }
        _ => chunk.start..chunk.start,
    };
    let consecutive = move |range: Range<usize>| {
        range.clone().step_by(group).map(move |first| Group::run(first - start, group.min(range.end - first)))
    };
    let width = rows.map_or(1, |rows| rows.width);
    let tiles = tiled.clone().step_by(TILE * width).flat_map(move |band| {
        (0..width).step_by(TILE).map(move |column| Group::tile(band + column - start, width, TILE.min(width - column)))
    });
    consecutive(chunk.start..tiled.start).chain(tiles).chain(consecutive(tiled.end..chunk.end))
}

#[cfg(test)]
mod tests {
    use glam::{Vec3, Vec3A};

    use super::*;
    use crate::raygen::{Camera, Generator, PixelSampling};

    /// A group's ray indices, run after run.
    fn rays(group: &Group) -> Vec<usize> {
        group.runs().iter().flat_map(|&(first, rays)| first..first + rays).collect()
    }

    fn camera(width: u32, height: u32) -> Generator {
        let camera = Camera::framing(Vec3::splat(-1.0), Vec3::splat(1.0), width, height);
        Generator::Pinhole(camera, PixelSampling { samples: 1, jitter_seed: None })
    }

    #[test]
    fn a_cameras_rows_are_found_from_wherever_its_rays_start() {
        let format = RayFormat::OriginDirection;
        let rays = camera(100, 40).rays(format);
        assert_eq!(ImageRows::find(format, &rays), Some(ImageRows { width: 100, first: 0 }));
        // From the middle of a row: the first row start is where the next row begins.
        let from = 37 * format.size();
        assert_eq!(ImageRows::find(format, &rays[from..]), Some(ImageRows { width: 100, first: 63 }));
        assert_eq!(ImageRows { width: 100, first: 0 }.from_ray(37), ImageRows { width: 100, first: 63 });
        assert_eq!(ImageRows { width: 100, first: 63 }.from_ray(263), ImageRows { width: 100, first: 0 });
        assert_eq!(ImageRows { width: 100, first: 63 }.from_ray(70), ImageRows { width: 100, first: 93 });
        // From a row's last ray.
        let from = 99 * format.size();
        assert_eq!(ImageRows::find(format, &rays[from..]), Some(ImageRows { width: 100, first: 1 }));
    }

    #[test]
    fn what_is_not_an_image_has_no_rows() {
        let format = RayFormat::OriginDirection;
        // Random rays.
        let random = crate::raygen::random_rays(Vec3::ZERO, Vec3::ONE, 4096, 7, format);
        assert_eq!(ImageRows::find(format, &random), None);
        // Fewer than four rows.
        let rays = camera(100, 3).rays(format);
        assert_eq!(ImageRows::find(format, &rays), None);
        // Rows too narrow for two tiles.
        let rays = camera(6, 50).rays(format);
        assert_eq!(ImageRows::find(format, &rays), None);
        // Every ray the same.
        assert_eq!(ImageRows::find(format, &[0u8; 24 * 100]), None);
        // Rows whose neighbour one row down is far away: each row's rays turned by a different angle.
        let turned: Vec<u8> = (0..400)
            .flat_map(|i: u32| {
                let (row, column) = ((i / 40) as f32, (i % 40) as f32);
                let ray = Ray {
                    origin: Vec3A::ZERO,
                    direction: Vec3A::new(column * 0.01 + row * 5.0, 1.0, 0.0),
                    ..Ray::default()
                };
                let mut bytes = [0u8; 24];
                format.encode(&ray, &mut bytes);
                bytes
            })
            .collect();
        assert_eq!(ImageRows::find(format, &turned), None);
    }

    #[test]
    fn ranges_from_a_first_ray_take_the_rays_before_it_and_the_rest() {
        assert_eq!(split_from(100, 3, 40), [0..43, 43..100]);
        assert_eq!(split_from(123, 3, 40), [0..43, 43..83, 83..123]);
        // One range, the whole.
        assert_eq!(split_from(30, 3, 40).as_slice(), std::slice::from_ref(&(0..30)));
        assert_eq!(split_from(0, 0, 40).as_slice(), std::slice::from_ref(&(0..0)));
    }

    #[test]
    fn groups_cover_the_chunk_once_in_tiles_where_bands_are_whole() {
        let rows = ImageRows { width: 10, first: 3 };
        for chunk in [0..97, 3..83, 43..123, 0..2, 50..60] {
            let groups: Vec<Group> = groups(chunk.clone(), Some(rows), 16).collect();
            let mut seen: Vec<usize> = groups.iter().flat_map(rays).collect();
            seen.sort_unstable();
            assert_eq!(seen, (0..chunk.len()).collect::<Vec<_>>(), "chunk {chunk:?}");
            assert!(groups.iter().all(|g| rays(g).len() <= 16));
        }
        // Rays 3..43 are the first band: its first tile is rows 0–3's first four rays, its last their last two.
        let tiles: Vec<Vec<usize>> = groups(0..50, Some(rows), 16).map(|g| rays(&g)).collect();
        assert_eq!(tiles[0], [0, 1, 2]);
        assert_eq!(tiles[1], [3, 4, 5, 6, 13, 14, 15, 16, 23, 24, 25, 26, 33, 34, 35, 36]);
        assert_eq!(tiles[3], [11, 12, 21, 22, 31, 32, 41, 42]);
        assert_eq!(tiles[4], (43..50).collect::<Vec<_>>());
        // Without rows, consecutive rays.
        let runs: Vec<Vec<usize>> = groups(5..40, None, 16).map(|g| rays(&g)).collect();
        assert_eq!(runs, [(0..16).collect::<Vec<_>>(), (16..32).collect(), (32..35).collect()]);
    }
}
