//! The reductions on hand-made hits: each result against numbers worked out here, and pieces folded in order
//! against the whole batch.

use glam::{Vec3, Vec3A};

use super::*;
use crate::format::{Hit, Ray, RayFormat};

/// `rays` packed (origin-direction) with their hits packed in `format`.
fn batch(format: HitFormat, rays: &[Ray], hits: &[Hit]) -> (Query, Vec<u8>, Vec<u8>) {
    let query = Query::closest(RayFormat::OriginDirection, format);
    let mut ray_bytes = vec![0u8; rays.len() * query.ray_format.size()];
    for (ray, slot) in rays.iter().zip(ray_bytes.chunks_exact_mut(query.ray_format.size())) {
        query.ray_format.encode(ray, slot);
    }
    let mut hit_bytes = vec![0u8; format.buffer_len(hits.len())];
    for (i, hit) in hits.iter().enumerate() {
        format.write(&mut hit_bytes, i, hit);
    }
    (query, ray_bytes, hit_bytes)
}

/// A ray from `origin` along +x.
fn along_x(origin: [f32; 3]) -> Ray {
    Ray { origin: origin.into(), direction: Vec3A::X, ..Ray::default() }
}

/// A hit at `t` on primitive `prim` of geometry `geom` in instance `inst`, normal +y.
fn hit(t: f32, prim: u32, geom: u32, inst: u32) -> Hit {
    Hit { t, prim_id: prim, geom_id: geom, inst_id: inst, normal: Vec3A::Y, ..Hit::MISS }
}

fn u64s(bytes: &[u8]) -> Vec<u64> {
    bytes.chunks_exact(8).map(|b| u64::from_le_bytes(b.try_into().unwrap())).collect()
}

fn reduce(reduction: &Reduction, format: HitFormat, hits: &[Hit]) -> Reduced {
    let rays = vec![along_x([0.0; 3]); hits.len()];
    let (query, rays, hits) = batch(format, &rays, hits);
    reduction.reduce_all(&query, &rays, &hits, &[]).unwrap()
}

#[test]
fn counts_and_histogram_count_what_was_hit() {
    let hits = [hit(0.5, 0, 0, 0), Hit::MISS, hit(2.0, 1, 0, 0), hit(9.99, 2, 0, 0), hit(10.0, 3, 0, 0)];
    assert_eq!(u64s(&reduce(&Reduction::Counts, HitFormat::T, &hits).bytes), [5, 4, 4]);
    let histogram = Reduction::Histogram { bins: 4, t_min: 1.0, t_max: 10.0 };
    // Bins of width 2.25 from 1: 2.0 in bin 0, 9.99 in bin 3; 0.5 below, 10.0 at or above.
    assert_eq!(u64s(&reduce(&histogram, HitFormat::T, &hits).bytes), [1, 0, 0, 1, 1, 1]);
}

#[test]
fn hits_behind_the_origin_are_counted_imaged_and_placed() {
    // Negative t: rays whose tmin < 0 hit behind their origins. Each reduction traces with a format that has ids.
    let hits = [hit(-0.5, 0, 0, 0), Hit::MISS, hit(-2.0, 1, 0, 0)];
    let traced =
        |reduction: &Reduction| reduction.traced_query(&Query::closest(RayFormat::OriginDirection, HitFormat::T));
    let counted = |reduction: Reduction| reduce(&reduction, traced(&reduction).hit_format, &hits).bytes;
    assert_eq!(u64s(&counted(Reduction::Counts)), [3, 2, 2]);
    let histogram = Reduction::Histogram { bins: 2, t_min: -3.0, t_max: 1.0 };
    // Bins [−3, −1) and [−1, 1), then below and above.
    assert_eq!(u64s(&counted(histogram)), [1, 1, 0, 0]);
    let depth = Image {
        width: 3,
        rays_per_pixel: 1,
        channel: ImageChannel::Depth,
        encoding: PixelEncoding::Float32,
        near: 0.0,
        far: 1.0,
    };
    let floats: Vec<f32> =
        counted(Reduction::Image(depth)).chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
    assert_eq!(floats, [-0.5, f32::INFINITY, -2.0]);
    let cloud = PointCloud { encoding: PointEncoding::Float32, step: 0.01, origin: Vec3::ZERO, ray_indices: false };
    let points: Vec<f32> = counted(Reduction::PointCloud(cloud))
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert_eq!(points, [-0.5, 0.0, 0.0, -2.0, 0.0, 0.0]);
}

#[test]
fn id_counts_are_sorted_by_signed_id_with_none_first() {
    let hits = [hit(1.0, 7, 2, 5), hit(1.0, 7, 1, crate::format::MISS_ID), Hit::MISS, hit(2.0, 3, 2, 5)];
    let pairs = |bytes: &[u8]| -> Vec<(i32, u64)> {
        bytes
            .chunks_exact(12)
            .map(|c| (i32::from_le_bytes(c[..4].try_into().unwrap()), u64::from_le_bytes(c[4..].try_into().unwrap())))
            .collect()
    };
    let by = |kind| pairs(&reduce(&Reduction::IdCounts(kind), HitFormat::Full, &hits).bytes);
    assert_eq!(by(IdKind::Instance), [(-1, 1), (5, 2)]);
    assert_eq!(by(IdKind::Geometry), [(1, 1), (2, 2)]);
    assert_eq!(by(IdKind::Primitive), [(3, 1), (7, 2)]);
}

#[test]
fn nearest_per_group_keeps_the_first_of_the_nearest() {
    let hits = [hit(3.0, 0, 0, 0), hit(1.0, 1, 0, 0), hit(1.0, 2, 0, 0), Hit::MISS, Hit::MISS, Hit::MISS];
    let reduced = reduce(&Reduction::NearestPerGroup { group: 3 }, HitFormat::TTriid, &hits);
    assert_eq!(HitFormat::TTriid.read(&reduced.bytes, 0).prim_id, 1);
    assert!(!HitFormat::TTriid.read(&reduced.bytes, 1).is_hit());
    assert_eq!(reduced.bytes.len(), 16);
    // −0 and +0 are equal t: the first ray's hit.
    let zeros = [hit(0.0, 1, 0, 0), hit(-0.0, 2, 0, 0)];
    let reduced = reduce(&Reduction::NearestPerGroup { group: 2 }, HitFormat::TTriid, &zeros);
    assert_eq!(HitFormat::TTriid.read(&reduced.bytes, 0).prim_id, 1);
}

#[test]
fn images_write_depth_and_facing_normals_in_each_encoding() {
    let back = Hit { back_face: true, ..hit(4.0, 0, 0, 0) };
    let hits = [hit(2.0, 0, 0, 0), Hit::MISS, back, hit(1.0, 0, 0, 0)];
    let image = |channel, encoding| {
        Reduction::Image(Image { width: 2, rays_per_pixel: 1, channel, encoding, near: 1.0, far: 3.0 })
    };
    let floats = |b: &[u8]| b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect::<Vec<_>>();
    let depth = reduce(&image(ImageChannel::Depth, PixelEncoding::Float32), HitFormat::Full, &hits);
    assert_eq!(floats(&depth.bytes), [2.0, f32::INFINITY, 4.0, 1.0]);
    let depth16 = reduce(&image(ImageChannel::Depth, PixelEncoding::Unorm16), HitFormat::Full, &hits);
    let u16s = |b: &[u8]| b.chunks_exact(2).map(|c| u16::from_le_bytes(c.try_into().unwrap())).collect::<Vec<_>>();
    assert_eq!(u16s(&depth16.bytes), [32767, 65535, 65534, 0]);
    let normals = reduce(&image(ImageChannel::Normal, PixelEncoding::Float32), HitFormat::Full, &hits);
    assert_eq!(floats(&normals.bytes), [0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 1.0, 0.0]);
    let normals16 = reduce(&image(ImageChannel::Normal, PixelEncoding::Unorm16), HitFormat::Full, &hits);
    assert_eq!(&u16s(&normals16.bytes)[..6], [32768, 65535, 32768, 0, 0, 0]);

    // The PNG holds the 16-bit values, two rows of two.
    let png = reduce(&image(ImageChannel::Normal, PixelEncoding::Png), HitFormat::Full, &hits);
    let mut reader = png::Decoder::new(std::io::Cursor::new(png.bytes.to_vec())).read_info().unwrap();
    let mut samples = vec![0u8; reader.output_buffer_size().unwrap()];
    let frame = reader.next_frame(&mut samples).unwrap();
    assert_eq!(
        (frame.width, frame.height, frame.color_type, frame.bit_depth),
        (2, 2, png::ColorType::Rgb, png::BitDepth::Sixteen)
    );
    let big_endian: Vec<u16> = samples.chunks_exact(2).map(|c| u16::from_be_bytes([c[0], c[1]])).collect();
    assert_eq!(big_endian, u16s(&normals16.bytes));
}

#[test]
fn point_clouds_place_hits_on_their_rays_and_drop_what_an_encoding_cannot_hold() {
    let rays = [along_x([1.0, 2.0, 3.0]), along_x([0.0; 3]), along_x([0.0; 3])];
    let hits = [hit(0.5, 0, 0, 0), Hit::MISS, hit(400.0, 0, 0, 0)];
    let (query, ray_bytes, hit_bytes) = batch(HitFormat::T, &rays, &hits);
    let cloud =
        |encoding, ray_indices| PointCloud { encoding, step: 0.01, origin: Vec3::new(1.0, 0.0, 0.0), ray_indices };
    let reduce =
        |cloud, first_ray| Reduction::PointCloud(cloud).reduce_piece(&query, first_ray, &ray_bytes, &hit_bytes, &[]);
    let floats = reduce(cloud(PointEncoding::Float32, true), 10);
    let Partial::Ordered { bytes, dropped: 0 } = floats else { panic!("{floats:?}") };
    let expected: Vec<u8> = [1.5f32, 2.0, 3.0]
        .iter()
        .flat_map(|f| f.to_le_bytes())
        .chain(10u32.to_le_bytes())
        .chain([400.0f32, 0.0, 0.0].iter().flat_map(|f| f.to_le_bytes()))
        .chain(12u32.to_le_bytes())
        .collect();
    assert_eq!(bytes, expected);
    assert_eq!(2 * cloud(PointEncoding::Float32, true).record_bytes(), expected.len(), "two points and their rays");

    // In i16 steps of 0.01 from (1, 0, 0): (0.5, 2, 3) → (50, 200, 300); 399 / 0.01 is out of range.
    let int16 = reduce(cloud(PointEncoding::Int16, false), 0);
    let expected: Vec<u8> = [50i16, 200, 300].iter().flat_map(|c| c.to_le_bytes()).collect();
    assert_eq!(cloud(PointEncoding::Int16, false).record_bytes(), expected.len(), "one point");
    assert_eq!(int16, Partial::Ordered { bytes: expected, dropped: 1 });
    let int32 = reduce(cloud(PointEncoding::Int32, false), 0);
    let Partial::Ordered { bytes, dropped: 0 } = int32 else { panic!("{int32:?}") };
    assert_eq!((bytes.len(), 2 * cloud(PointEncoding::Int32, false).record_bytes()), (24, 24));
}

#[test]
fn pieces_folded_in_order_equal_the_whole_batch() {
    let hits: Vec<Hit> =
        (0..60).map(|i| if i % 7 == 3 { Hit::MISS } else { hit((i * 37 % 23) as f32, i % 5, i % 3, i % 4) }).collect();
    let rays: Vec<Ray> = (0..60).map(|i| along_x([i as f32, 0.0, 0.0])).collect();
    let (query, ray_bytes, hit_bytes) = batch(HitFormat::Full, &rays, &hits);
    let reductions = [
        Reduction::Counts,
        Reduction::Histogram { bins: 5, t_min: 2.0, t_max: 20.0 },
        Reduction::IdCounts(IdKind::Instance),
        Reduction::NearestPerGroup { group: 4 },
        Reduction::Image(Image {
            width: 3,
            rays_per_pixel: 4,
            channel: ImageChannel::Normal,
            encoding: PixelEncoding::Png,
            near: 0.0,
            far: 1.0,
        }),
        Reduction::PointCloud(PointCloud {
            encoding: PointEncoding::Int32,
            step: 0.5,
            origin: Vec3::ZERO,
            ray_indices: true,
        }),
    ];
    for reduction in reductions {
        reduction.check(&query, 60).unwrap();
        let whole = reduction.reduce_all(&query, &ray_bytes, &hit_bytes, &[]).unwrap();
        let (ray_size, hit_size) = (query.ray_format.size(), query.hit_format.size().unwrap());
        let mut folded = reduction.empty();
        for first in (0..60).step_by(12) {
            let rays = &ray_bytes[first * ray_size..(first + 12) * ray_size];
            let hits = &hit_bytes[first * hit_size..(first + 12) * hit_size];
            folded.merge(reduction.reduce_piece(&query, first as u64, rays, hits, &[]));
        }
        assert_eq!(reduction.finish(folded, 60).unwrap(), whole, "{reduction:?}");
    }
}

#[test]
fn bad_numbers_name_their_field() {
    let closest = Query::closest(RayFormat::OriginDirection, HitFormat::T);
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 2, ..closest };
    let field = |reduction: Reduction, query: &Query, rays: u64| match reduction.check(query, rays) {
        Err(Error::InvalidQuery { field, .. }) => field,
        other => panic!("{reduction:?}: {other:?}"),
    };
    let image = Image {
        width: 4,
        rays_per_pixel: 2,
        channel: ImageChannel::Depth,
        encoding: PixelEncoding::Unorm16,
        near: 1.0,
        far: 1.0,
    };
    assert_eq!(field(Reduction::Image(image), &closest, 16), "reduction.image.far");
    assert_eq!(field(Reduction::Image(Image { near: f32::NAN, ..image }), &closest, 16), "reduction.image.near");
    let vast = Image { near: -3e38, far: 3e38, ..image };
    assert_eq!(field(Reduction::Image(vast), &closest, 16), "reduction.image.far", "far − near past f32");
    let png = Image { encoding: PixelEncoding::Png, far: 2.0, ..image };
    assert_eq!(field(Reduction::Image(png), &closest, 0), "reduction.image.encoding", "a PNG of no rows");
    assert!(Reduction::Image(Image { encoding: PixelEncoding::Float32, ..png }).check(&closest, 0).is_ok());
    assert_eq!(field(Reduction::Image(Image { far: 2.0, ..image }), &closest, 12), "reduction.image.width");
    assert_eq!(field(Reduction::Image(Image { width: 0, ..image }), &closest, 16), "reduction.image.width");
    assert_eq!(field(Reduction::Image(Image { far: 2.0, ..image }), &all, 16), "query.query");
    assert_eq!(
        field(Reduction::Histogram { bins: 0, t_min: 0.0, t_max: 1.0 }, &closest, 1),
        "reduction.histogram.bins"
    );
    assert_eq!(
        field(Reduction::Histogram { bins: 1, t_min: 1.0, t_max: 1.0 }, &closest, 1),
        "reduction.histogram.t_max"
    );
    assert_eq!(
        field(Reduction::Histogram { bins: 1, t_min: f32::NAN, t_max: 1.0 }, &closest, 1),
        "reduction.histogram.t_min"
    );
    assert_eq!(field(Reduction::NearestPerGroup { group: 3 }, &closest, 10), "reduction.nearest.group");
    let bitmask = Query { hit_format: HitFormat::Bitmask, ..closest };
    assert_eq!(field(Reduction::NearestPerGroup { group: 1 }, &bitmask, 10), "query.hit_format");
    let cloud = PointCloud { encoding: PointEncoding::Int16, step: 0.0, origin: Vec3::ZERO, ray_indices: false };
    assert_eq!(field(Reduction::PointCloud(cloud), &closest, 1), "reduction.point_cloud.step");
    let indexed = PointCloud { encoding: PointEncoding::Float32, ray_indices: true, ..cloud };
    assert!(Reduction::PointCloud(indexed).check(&closest, 1 << 32).is_ok());
    assert_eq!(field(Reduction::PointCloud(indexed), &closest, (1 << 32) + 1), "reduction.point_cloud.ray_indices");
    assert!(Reduction::Counts.check(&all, 7).is_ok());
}

#[test]
fn compact_hits_decode_to_the_hits_within_their_quantization() {
    let count = 2 * COMPACT_BLOCK_RAYS as usize + 300;
    let rays: Vec<Ray> = (0..count)
        .map(|i| Ray { tmin: 0.5, tmax: if i % 3 == 0 { 4.0 } else { f32::INFINITY }, ..along_x([0.0; 3]) })
        .collect();
    let hits: Vec<Hit> = (0..count)
        .map(|i| match i % 5 {
            0 => Hit::MISS,
            _ => Hit {
                u: (i % 7) as f32 / 7.0,
                v: (i % 11) as f32 / 22.0,
                ..hit(0.5 + (i % 13) as f32 * 0.25, (i * 7919 % 100_000) as u32, 0, (i % 4) as u32)
            },
        })
        .collect();
    let (query, _, hit_bytes) = batch(HitFormat::TTriidInstidUV, &rays, &hits);
    // A ray format that carries each ray's range.
    let query = Query { ray_format: RayFormat::OriginTminDirectionTmax, ..query };
    let mut ray_bytes = vec![0u8; count * query.ray_format.size()];
    for (ray, slot) in rays.iter().zip(ray_bytes.chunks_exact_mut(query.ray_format.size())) {
        query.ray_format.encode(ray, slot);
    }
    let t_far = 3.0;
    let compact = Reduction::CompactHits { t_far };
    compact.check(&query, count as u64).unwrap();
    // Encoded in pieces of one block each and folded, as the server does.
    let (ray_size, hit_size) = (query.ray_format.size(), query.hit_format.size().unwrap());
    let mut folded = compact.empty();
    for first in (0..count).step_by(COMPACT_BLOCK_RAYS as usize) {
        let end = (first + COMPACT_BLOCK_RAYS as usize).min(count);
        let piece = compact.reduce_piece(
            &query,
            first as u64,
            &ray_bytes[first * ray_size..end * ray_size],
            &hit_bytes[first * hit_size..end * hit_size],
            &[],
        );
        folded.merge(piece);
    }
    let encoded = compact.finish(folded, count as u64).unwrap().bytes;
    assert!(encoded.len() < count * 10, "{} bytes for {count} rays", encoded.len());
    let decoded = decode_compact(&query, t_far, &ray_bytes, &encoded).unwrap();
    for (i, (got, want)) in decoded.iter().zip(&hits).enumerate() {
        assert_eq!((got.is_hit(), got.prim_id, got.inst_id), (want.is_hit(), want.prim_id, want.inst_id), "ray {i}");
        if want.is_hit() {
            let (lo, hi) = (0.5, rays[i].tmax.min(t_far));
            let expected_t = want.t.clamp(lo, hi);
            assert!((got.t - expected_t).abs() <= (hi - lo) / 131068.0 * 1.01, "ray {i}: {} for {}", got.t, want.t);
            assert!((got.u - want.u).abs() <= 1.0 / 131070.0 + 1e-7 && (got.v - want.v).abs() <= 1.0 / 131070.0 + 1e-7);
        }
    }
    assert!(decode_compact(&query, t_far, &ray_bytes, &encoded[..encoded.len() - 1]).is_err(), "truncated");
    let full = Query { hit_format: HitFormat::Full, ..query };
    assert!(compact.check(&full, 1).is_err(), "FULL has no compact form");
    assert!(Reduction::CompactHits { t_far: f32::INFINITY }.check(&query, 1).is_err());

    // A range wider than f32 holds (tmin −3e38 to t_far 3e38): t still within the bound.
    let wide = Ray { tmin: -3e38, tmax: f32::INFINITY, ..along_x([0.0; 3]) };
    let mut wide_ray = vec![0u8; query.ray_format.size()];
    query.ray_format.encode(&wide, &mut wide_ray);
    let wide_hit = [hit(1e38, 1, 0, 0)];
    let (_, _, wide_hit_bytes) = batch(query.hit_format, &[wide], &wide_hit);
    let wide_compact = Reduction::CompactHits { t_far: 3e38 };
    let encoded = wide_compact.reduce_all(&query, &wide_ray, &wide_hit_bytes, &[]).unwrap().bytes;
    let decoded = decode_compact(&query, 3e38, &wide_ray, &encoded).unwrap();
    let bound = (3e38f64 + 3e38) / 131068.0;
    assert!((f64::from(decoded[0].t) - 1e38).abs() <= bound * 1.01, "{}", decoded[0].t);
}

#[test]
fn a_piece_reduced_in_parallel_parts_equals_it_reduced_at_once() {
    let count = 3 * PARALLEL_SPLIT_RAYS + 123 * 3;
    let hits: Vec<Hit> = (0..count)
        .map(|i| if i % 7 == 3 { Hit::MISS } else { hit((i * 37 % 23) as f32, i as u32 % 5, 0, 0) })
        .collect();
    let rays: Vec<Ray> = (0..count).map(|i| along_x([i as f32, 0.0, 0.0])).collect();
    let (query, ray_bytes, hit_bytes) = batch(HitFormat::TTriid, &rays, &hits);
    let cloud = PointCloud { encoding: PointEncoding::Float32, step: 0.0, origin: Vec3::ZERO, ray_indices: true };
    for reduction in [
        Reduction::Histogram { bins: 7, t_min: 1.0, t_max: 20.0 },
        Reduction::NearestPerGroup { group: 3 },
        Reduction::PointCloud(cloud),
        Reduction::CompactHits { t_far: 30.0 },
    ] {
        let at_once = reduction.reduce_piece(&query, 1 << 20, &ray_bytes, &hit_bytes, &[]);
        let parallel = reduction.reduce_piece_parallel(&query, 1 << 20, &ray_bytes, &hit_bytes, &[]);
        assert!(at_once == parallel, "{reduction:?}");
    }
    // Counts trace a bitmask: its parts begin within the bytes.
    let (query, ray_bytes, hit_bytes) = batch(HitFormat::Bitmask, &rays, &hits);
    assert_eq!(Reduction::Counts.traced_query(&query).hit_format, HitFormat::Bitmask);
    // Hit or miss needs no nearest hit: a closest-hit query's counts are traced as an any-hit one; others as they are.
    assert_eq!(Reduction::Counts.traced_query(&query).kind, QueryKind::Any);
    for kind in [QueryKind::All, QueryKind::Count] {
        assert_eq!(Reduction::Counts.traced_query(&Query { kind, ..query }).kind, kind);
    }
    assert_eq!(Reduction::Histogram { bins: 1, t_min: 0.0, t_max: 1.0 }.traced_query(&query).kind, QueryKind::Closest);
    let parallel = Reduction::Counts.reduce_piece_parallel(&query, 0, &ray_bytes, &hit_bytes, &[]);
    let hit = hits.iter().filter(|hit| hit.is_hit()).count() as u64;
    assert_eq!(parallel, Partial::Sums(vec![count as u64, hit, hit]));
}
