//! Reductions of the contract into the engine's.

use rayd_engine::glam::Vec3;
use rayd_engine::raygen::Generator;
use rayd_engine::reduce::{
    IdKind, Image, ImageChannel, MAX_GROUP_RAYS, PixelEncoding, PointCloud, PointEncoding, Reduction,
};
use rayd_proto as pb;

use crate::error::{ServiceError, ServiceResult};

/// The enum value `value` of a contract enum, or INVALID_ARGUMENT naming `field`.
fn known<T: TryFrom<i32>>(value: i32, field: &str) -> ServiceResult<T> {
    T::try_from(value).map_err(|_| ServiceError::invalid(field, format!("{value} is not a known value")))
}

/// The engine's reduction for `r` (checked against the query and rays later, by the engine). An image's width and
/// rays per pixel left 0 come from `generator` when it is a camera (given with the first ray it makes).
pub fn reduction(r: &pb::Reduction, generator: Option<(&Generator, u64)>) -> ServiceResult<Reduction> {
    use pb::reduction::Kind;
    Ok(match r.kind.as_ref().ok_or_else(|| ServiceError::invalid("reduction", "a kind is required"))? {
        Kind::Counts(_) => Reduction::Counts,
        Kind::Image(image) => Reduction::Image(self::image(image, generator)?),
        Kind::Histogram(h) => Reduction::Histogram { bins: h.bins, t_min: h.t_min, t_max: h.t_max },
        Kind::IdCounts(ids) => Reduction::IdCounts(match known(ids.by, "reduction.id_counts.by")? {
            pb::IdKind::Unspecified | pb::IdKind::Instance => IdKind::Instance,
            pb::IdKind::Geometry => IdKind::Geometry,
            pb::IdKind::Primitive => IdKind::Primitive,
        }),
        Kind::Nearest(n) => Reduction::NearestPerGroup { group: n.group },
        Kind::PointCloud(cloud) => Reduction::PointCloud(PointCloud {
            encoding: match known(cloud.encoding, "reduction.point_cloud.encoding")? {
                pb::PointEncoding::Unspecified | pb::PointEncoding::Float32 => PointEncoding::Float32,
                pb::PointEncoding::Int32 => PointEncoding::Int32,
                pb::PointEncoding::Int16 => PointEncoding::Int16,
            },
            step: cloud.step,
            origin: cloud.origin.as_ref().map_or(Vec3::ZERO, |o| Vec3::new(o.x, o.y, o.z)),
            ray_indices: cloud.ray_indices,
        }),
        Kind::Compact(compact) => Reduction::CompactHits { t_far: compact.t_far },
    })
}

/// The engine's image, with the camera generator's width and samples where the request leaves them 0.
fn image(image: &pb::ImageReduction, generator: Option<(&Generator, u64)>) -> ServiceResult<Image> {
    let (camera, first_ray) = match generator {
        Some((Generator::Pinhole(camera, sampling), first)) => (Some((camera.width, sampling.samples)), first),
        Some((Generator::Orthographic(camera, sampling), first)) => (Some((camera.width, sampling.samples)), first),
        _ => (None, 0),
    };
    let width = match (image.width, camera) {
        (0, Some((width, _))) => width,
        (0, None) => {
            return Err(ServiceError::invalid("reduction.image.width", "required unless a camera makes the rays"));
        }
        (width, _) => width,
    };
    let rays_per_pixel = match (image.rays_per_pixel, camera) {
        (0, Some((_, samples))) if samples > MAX_GROUP_RAYS => {
            let rule = format!("{samples} rays a pixel are more than an image reduction takes ({MAX_GROUP_RAYS})");
            return Err(ServiceError::invalid("generator.samples_per_pixel", rule));
        }
        (0, Some((_, samples))) => samples,
        (0, None) => 1,
        (rays, _) => rays,
    };
    // Pixels and rows taken from the camera are the camera's only from the start of one of its rows.
    let row = u64::from(width) * u64::from(rays_per_pixel);
    let from_camera = camera.is_some() && (image.width == 0 || image.rays_per_pixel == 0);
    if from_camera && !first_ray.is_multiple_of(row) {
        let rule = format!("{first_ray} is not the start of a row ({row} rays) of the image the camera's pixels make");
        return Err(ServiceError::invalid("generator.first_ray", rule));
    }
    Ok(Image {
        width,
        rays_per_pixel,
        channel: match known(image.channel, "reduction.image.channel")? {
            pb::ImageChannel::Unspecified | pb::ImageChannel::Depth => ImageChannel::Depth,
            pb::ImageChannel::Normal => ImageChannel::Normal,
        },
        encoding: match known(image.encoding, "reduction.image.encoding")? {
            pb::PixelEncoding::Unspecified | pb::PixelEncoding::Float32 => PixelEncoding::Float32,
            pb::PixelEncoding::Unorm16 => PixelEncoding::Unorm16,
            pb::PixelEncoding::Png => PixelEncoding::Png,
        },
        near: image.near,
        far: image.far,
    })
}
