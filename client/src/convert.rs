//! The one place where the contract's enums and messages meet the engine's types. Names on the command line and
//! in JSON output are the engine's (`RayFormat::name` and friends); numbers on the wire are the contract's.

use bytes::Bytes;
use glam::Vec3;
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{IndexFormat, MotionFlags, MotionOptions, VertexFormat};
use rayd_engine::query::{Query, QueryKind};
use rayd_engine::raygen::{Bounce, Generator, PixelSampling, Primary, Secondary};
use rayd_engine::reduce::{IdKind, ImageChannel, PixelEncoding, PointEncoding, Reduction};
use rayd_proto as proto;

/// Defines, from one table of variant pairs, the conversion of an engine enum to the contract's enum and back
/// (from the wire's `i32`, where UNSPECIFIED and unknown numbers give `None`).
macro_rules! mirror {
    ($to:ident, $from:ident: $engine:ident <=> $proto:ident { $($e:ident <=> $p:ident),+ $(,)? }) => {
        #[doc = concat!("The contract's `", stringify!($proto), "` for an engine `", stringify!($engine), "`.")]
        pub fn $to(value: $engine) -> proto::$proto {
            match value {
                $($engine::$e => proto::$proto::$p,)+
            }
        }

        #[doc = concat!("The engine's `", stringify!($engine), "` for a wire value of `", stringify!($proto),
            "`; `None` for UNSPECIFIED or a number this client does not know.")]
        pub fn $from(value: i32) -> Option<$engine> {
            match proto::$proto::try_from(value).ok()? {
                $(proto::$proto::$p => Some($engine::$e),)+
                #[allow(unreachable_patterns)]
                _ => None,
            }
        }
    };
}

mirror!(ray_format_to_proto, ray_format_from_proto: RayFormat <=> RayFormat {
    OriginDirection <=> OriginDirection,
    OriginTminDirectionTmax <=> OriginTminDirectionTmax,
    OriginMaskDirectionTmax <=> OriginMaskDirectionTmax,
    OriginTminDirectionTmaxTime <=> OriginTminDirectionTmaxTime,
    Full <=> Full,
});

mirror!(hit_format_to_proto, hit_format_from_proto: HitFormat <=> HitFormat {
    Bitmask <=> Bitmask,
    T <=> T,
    TTriid <=> TTriid,
    TTriidUV <=> TTriidUV,
    TTriidInstid <=> TTriidInstid,
    TTriidInstidUV <=> TTriidInstidUV,
    Full <=> Full,
});

mirror!(query_kind_to_proto, query_kind_from_proto: QueryKind <=> QueryType {
    Closest <=> Closest,
    Any <=> Any,
    All <=> All,
    Count <=> Count,
});

mirror!(vertex_format_to_proto, vertex_format_from_proto: VertexFormat <=> VertexFormat {
    Float3 <=> Float3,
    Float4 <=> Float4,
});

mirror!(index_format_to_proto, index_format_from_proto: IndexFormat <=> IndexFormat {
    U32x3 <=> Uint32x3,
    U16x3 <=> Uint16x3,
});

/// Reaches one flag field of the contract's build options.
type FlagField = fn(&mut proto::BuildOptions) -> &mut bool;

/// Each build flag beside the contract's field that carries it.
const BUILD_FLAG_FIELDS: [(BuildFlags, FlagField); 5] = [
    (BuildFlags::PREFER_FAST_TRACE, |o| &mut o.prefer_fast_trace),
    (BuildFlags::PREFER_FAST_BUILD, |o| &mut o.prefer_fast_build),
    (BuildFlags::ALLOW_UPDATE, |o| &mut o.allow_update),
    (BuildFlags::ALLOW_COMPACTION, |o| &mut o.allow_compaction),
    (BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS, |o| &mut o.allow_random_vertex_access),
];

/// The contract's build options for engine build flags.
pub fn build_options_to_proto(flags: BuildFlags) -> proto::BuildOptions {
    let mut options = proto::BuildOptions::default();
    for (flag, field) in BUILD_FLAG_FIELDS {
        *field(&mut options) = flags.contains(flag);
    }
    options
}

/// The contract's motion options (unset for a static object).
pub fn motion_to_proto(motion: &MotionOptions) -> Option<proto::MotionOptions> {
    (!motion.is_static()).then(|| proto::MotionOptions {
        keys: motion.keys,
        time_begin: motion.time_begin,
        time_end: motion.time_end,
        start_vanish: motion.flags.contains(MotionFlags::START_VANISH),
        end_vanish: motion.flags.contains(MotionFlags::END_VANISH),
    })
}

/// The engine's build flags for the contract's build options.
pub fn build_flags_from_proto(mut options: proto::BuildOptions) -> BuildFlags {
    BUILD_FLAG_FIELDS.into_iter().filter(|(_, field)| *field(&mut options)).map(|(flag, _)| flag).collect()
}

/// The lower-case names of a set of build flags (`prefer_fast_trace`, `allow_update`, …).
pub fn build_flag_names(flags: BuildFlags) -> Vec<String> {
    flags.iter_names().map(|(name, _)| name.to_lowercase()).collect()
}

/// Names the accel called `name`.
pub fn accel_ref(name: &str) -> proto::AccelRef {
    proto::AccelRef { r#ref: Some(proto::accel_ref::Ref::Name(name.to_owned())) }
}

/// Names the buffer with server-given id `id`.
pub fn buffer_ref(id: &str) -> proto::BufferRef {
    proto::BufferRef { r#ref: Some(proto::buffer_ref::Ref::Id(id.to_owned())) }
}

/// The contract's trace query for an engine query on the accel called `accel`.
pub fn trace_query(accel: &str, query: &Query) -> proto::TraceQuery {
    trace_query_ref(accel_ref(accel), query)
}

/// The contract's trace query for an engine query on the accel `accel` names. Ray flag bits are the same numbers
/// in both (`RayFlag` mirrors `RayFlags`).
pub fn trace_query_ref(accel: proto::AccelRef, query: &Query) -> proto::TraceQuery {
    proto::TraceQuery {
        accel: Some(accel),
        query: query_kind_to_proto(query.kind).into(),
        ray_format: ray_format_to_proto(query.ray_format).into(),
        hit_format: hit_format_to_proto(query.hit_format).into(),
        ray_flags: query.flags.bits(),
        max_hits_per_ray: query.max_hits_per_ray,
    }
}

/// The box of an accel as engine vectors; `None` when the server sent none or the accel has no triangles.
pub fn bounds(info: &proto::AccelInfo) -> Option<(Vec3, Vec3)> {
    let vec3 = |v: Option<proto::Vec3>| v.map(|v| Vec3::new(v.x, v.y, v.z));
    let bounds = info.bounds?;
    let (lo, hi) = (vec3(bounds.min)?, vec3(bounds.max)?);
    lo.cmple(hi).all().then_some((lo, hi))
}

/// A device backend's name in lower case (`cpu`, `wgpu`), or `unknown`.
pub fn backend_name(backend: i32) -> &'static str {
    match proto::Backend::try_from(backend) {
        Ok(proto::Backend::Cpu) => "cpu",
        Ok(proto::Backend::Wgpu) => "wgpu",
        _ => "unknown",
    }
}

/// The contract's form of an engine ray generator (all of its rays).
pub fn generator_to_proto(generator: &Generator) -> proto::RayGenerator {
    use proto::ray_generator::Kind;
    let vec3 = |v: Vec3| Some(proto::Vec3 { x: v.x, y: v.y, z: v.z });
    let packed = |points: &[Vec3]| -> Bytes {
        points.iter().flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect::<Vec<u8>>().into()
    };
    let sampling =
        |s: &PixelSampling| Some(proto::PixelSampling { samples_per_pixel: s.samples, jitter_seed: s.jitter_seed });
    let kind = match generator {
        Generator::Pinhole(c, s) => Kind::Pinhole(proto::PinholeCamera {
            eye: vec3(c.eye),
            target: vec3(c.target),
            up: vec3(c.up),
            fov_y_degrees: c.fov_y_degrees,
            width: c.width,
            height: c.height,
            sampling: sampling(s),
        }),
        Generator::Orthographic(c, s) => Kind::Orthographic(proto::OrthographicCamera {
            eye: vec3(c.eye),
            target: vec3(c.target),
            up: vec3(c.up),
            view_height: c.view_height,
            width: c.width,
            height: c.height,
            sampling: sampling(s),
        }),
        Generator::Lidar(l) => Kind::Lidar(proto::LidarScan {
            origin: vec3(l.origin),
            forward: vec3(l.forward),
            up: vec3(l.up),
            elevations_degrees: l.elevations_degrees.clone(),
            steps: l.steps,
            min_range: l.min_range,
            max_range: l.max_range,
            time_begin: l.time.0,
            time_end: l.time.1,
        }),
        Generator::Sphere(s) => Kind::Sphere(proto::SphereSampling {
            points: packed(&s.points),
            normals: packed(&s.normals),
            samples: s.samples,
            min_distance: s.min_distance,
            max_distance: s.max_distance,
            seed: s.seed,
        }),
        Generator::Secondary(s) => Kind::Secondary(Box::new(secondary_to_proto(s))),
    };
    proto::RayGenerator { kind: Some(kind), ..Default::default() }
}

/// Rays the server makes from `generator` as [`generator_to_proto`] sends it: [`Generator::count`], but with a
/// camera's 0 samples a pixel read as 1, as the contract's `PixelSampling` has it (the engine would count 0).
pub(crate) fn generated_ray_count(generator: &Generator) -> u64 {
    let once = |sampling: &PixelSampling| PixelSampling { samples: 1, ..*sampling };
    match generator {
        Generator::Pinhole(camera, sampling) if sampling.samples == 0 => {
            Generator::Pinhole(*camera, once(sampling)).count()
        }
        Generator::Orthographic(camera, sampling) if sampling.samples == 0 => {
            Generator::Orthographic(*camera, once(sampling)).count()
        }
        Generator::Secondary(Secondary { primary: Primary::Generated(primary), .. }) => generated_ray_count(primary),
        other => other.count(),
    }
}

/// The contract's form of engine secondary rays: their primary rays and hits inline (or the primary generator).
fn secondary_to_proto(s: &Secondary) -> proto::SecondaryRays {
    use proto::secondary_rays::{Primary as P, PrimaryHits};
    let (primary, format) = match &s.primary {
        Primary::Packed(format, bytes) => (P::PrimaryRaysInline(bytes.clone()), ray_format_to_proto(*format).into()),
        Primary::Generated(generator) => (P::PrimaryGenerator(Box::new(generator_to_proto(generator))), 0),
    };
    proto::SecondaryRays {
        primary: Some(primary),
        primary_ray_format: format,
        primary_hits: Some(PrimaryHits::PrimaryHitsInline(s.hits.clone())),
        bounce: Some(bounce_to_proto(s.bounce)),
        offset: s.offset,
    }
}

/// The contract's form of what a secondary ray does.
pub fn bounce_to_proto(bounce: Bounce) -> proto::secondary_rays::Bounce {
    use proto::secondary_rays::Bounce as B;
    match bounce {
        Bounce::Reflect => B::Reflect(proto::Reflect {}),
        Bounce::TowardsLight(l) => B::TowardsLight(proto::Vec3 { x: l.x, y: l.y, z: l.z }),
    }
}

/// The contract's form of an engine reduction.
pub fn reduction_to_proto(reduction: &Reduction) -> proto::Reduction {
    use proto::reduction::Kind;
    let kind = match reduction {
        Reduction::Counts => Kind::Counts(proto::HitCountsReduction {}),
        Reduction::Image(image) => Kind::Image(proto::ImageReduction {
            width: image.width,
            rays_per_pixel: image.rays_per_pixel,
            channel: match image.channel {
                ImageChannel::Depth => proto::ImageChannel::Depth,
                ImageChannel::Normal => proto::ImageChannel::Normal,
            } as i32,
            encoding: match image.encoding {
                PixelEncoding::Float32 => proto::PixelEncoding::Float32,
                PixelEncoding::Unorm16 => proto::PixelEncoding::Unorm16,
                PixelEncoding::Png => proto::PixelEncoding::Png,
            } as i32,
            near: image.near,
            far: image.far,
        }),
        Reduction::Histogram { bins, t_min, t_max } => {
            Kind::Histogram(proto::HistogramReduction { bins: *bins, t_min: *t_min, t_max: *t_max })
        }
        Reduction::IdCounts(by) => Kind::IdCounts(proto::IdCountsReduction {
            by: match by {
                IdKind::Instance => proto::IdKind::Instance,
                IdKind::Geometry => proto::IdKind::Geometry,
                IdKind::Primitive => proto::IdKind::Primitive,
            } as i32,
        }),
        Reduction::NearestPerGroup { group } => Kind::Nearest(proto::NearestPerGroupReduction { group: *group }),
        Reduction::PointCloud(cloud) => Kind::PointCloud(proto::PointCloudReduction {
            encoding: match cloud.encoding {
                PointEncoding::Float32 => proto::PointEncoding::Float32,
                PointEncoding::Int32 => proto::PointEncoding::Int32,
                PointEncoding::Int16 => proto::PointEncoding::Int16,
            } as i32,
            step: cloud.step,
            origin: Some(proto::Vec3 { x: cloud.origin.x, y: cloud.origin.y, z: cloud.origin.z }),
            ray_indices: cloud.ray_indices,
        }),
        Reduction::CompactHits { t_far } => Kind::Compact(proto::CompactHitsReduction { t_far: *t_far }),
    };
    proto::Reduction { kind: Some(kind) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_engine_enum_round_trips_through_its_wire_number() {
        for format in RayFormat::ALL {
            assert_eq!(ray_format_from_proto(ray_format_to_proto(format).into()), Some(format));
        }
        for format in HitFormat::ALL {
            assert_eq!(hit_format_from_proto(hit_format_to_proto(format).into()), Some(format));
        }
        for kind in QueryKind::ALL {
            assert_eq!(query_kind_from_proto(query_kind_to_proto(kind).into()), Some(kind));
        }
        for format in [VertexFormat::Float3, VertexFormat::Float4] {
            assert_eq!(vertex_format_from_proto(vertex_format_to_proto(format).into()), Some(format));
        }
        for format in [IndexFormat::U32x3, IndexFormat::U16x3] {
            assert_eq!(index_format_from_proto(index_format_to_proto(format).into()), Some(format));
        }
    }

    #[test]
    fn wire_numbers_match_the_contract_and_unspecified_is_none() {
        assert_eq!(i32::from(ray_format_to_proto(RayFormat::OriginTminDirectionTmax)), 2);
        assert_eq!(i32::from(hit_format_to_proto(HitFormat::TTriidUV)), 4);
        assert_eq!(i32::from(query_kind_to_proto(QueryKind::Count)), 4);
        assert_eq!(i32::from(index_format_to_proto(IndexFormat::U16x3)), 2);
        assert_eq!(ray_format_from_proto(0), None);
        assert_eq!(hit_format_from_proto(99), None);
    }

    #[test]
    fn build_flags_map_to_their_own_fields() {
        let flags = BuildFlags::PREFER_FAST_BUILD | BuildFlags::ALLOW_COMPACTION;
        let options = build_options_to_proto(flags);
        assert!(options.prefer_fast_build && options.allow_compaction);
        assert!(!options.prefer_fast_trace && !options.allow_update && !options.allow_random_vertex_access);
        assert_eq!(build_flags_from_proto(options), flags);
        assert_eq!(build_flags_from_proto(build_options_to_proto(BuildFlags::all())), BuildFlags::all());
        assert_eq!(build_flag_names(flags), ["prefer_fast_build", "allow_compaction"]);
    }

    #[test]
    fn query_keeps_flags_and_names_the_accel() {
        let mut query = Query::closest(RayFormat::Full, HitFormat::T);
        query.flags = rayd_engine::format::RayFlags::CULL_FRONT_FACING;
        let wire = trace_query("bunny", &query);
        assert_eq!(wire.ray_flags, proto::RayFlag::CullFrontFacing as u32);
        assert_eq!(wire.accel, Some(accel_ref("bunny")));
        assert_eq!(wire.query, proto::QueryType::Closest as i32);
    }

    #[test]
    fn empty_or_missing_bounds_are_none() {
        let v = |x| Some(proto::Vec3 { x, y: 0.0, z: 0.0 });
        let mut info = proto::AccelInfo::default();
        assert_eq!(bounds(&info), None);
        info.bounds = Some(proto::Bounds { min: v(1.0), max: v(-1.0) });
        assert_eq!(bounds(&info), None);
        info.bounds = Some(proto::Bounds { min: v(-1.0), max: v(1.0) });
        assert_eq!(bounds(&info), Some((Vec3::new(-1.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0))));
    }

    #[test]
    fn a_camera_of_0_samples_a_pixel_counts_1_ray_a_pixel_as_the_server_makes_them() {
        use rayd_engine::raygen::{Camera, Orthographic};
        let sampling = |samples| PixelSampling { samples, jitter_seed: None };
        let camera = Camera::framing(Vec3::ZERO, Vec3::ONE, 4, 3);
        let (eye, target, up) = (Vec3::Z, Vec3::ZERO, Vec3::Y);
        let orthographic = Orthographic { eye, target, up, view_height: 1.0, width: 5, height: 2 };
        assert_eq!(generated_ray_count(&Generator::Pinhole(camera, sampling(0))), 12);
        assert_eq!(generated_ray_count(&Generator::Pinhole(camera, sampling(3))), 36);
        assert_eq!(generated_ray_count(&Generator::Orthographic(orthographic, sampling(0))), 10);
        let primary = Primary::Generated(Box::new(Generator::Pinhole(camera, sampling(0))));
        let secondary = Secondary { primary, hits: Bytes::new(), bounce: Bounce::Reflect, offset: 0.0 };
        assert_eq!(generated_ray_count(&Generator::Secondary(secondary)), 12, "a ray a primary ray");
    }
}
