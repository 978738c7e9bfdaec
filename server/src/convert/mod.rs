//! Conversions between the contract's messages and the engine's types. Field names in errors are the
//! contract's.

use rayd_engine::accel::{AccelInfo, AccelKind, BuildFlags, BuildOptions, MemoryUsage};
use rayd_engine::backend::{BackendKind, DeviceInfo};
use rayd_engine::format::{HitFormat, RayFlags, RayFormat};
use rayd_engine::geometry::{MotionFlags, MotionOptions};
use rayd_engine::query::{Query, QueryKind, TraceStats};
use rayd_proto as pb;

use crate::error::{ServiceError, ServiceResult};

mod generator;
mod reduction;
pub use generator::generator;
pub use reduction::reduction;

/// The engine value numbered `value` in the contract, whose enums number the engine's `ALL` lists from 1 (0 is
/// UNSPECIFIED); the test below checks that the names agree.
fn numbered<T: Copy>(all: &[T], value: i32, field: &str, what: &str) -> ServiceResult<T> {
    let index = usize::try_from(value).ok().and_then(|v| v.checked_sub(1));
    index
        .and_then(|i| all.get(i).copied())
        .ok_or_else(|| ServiceError::invalid(field, format!("{value} is not a {what}")))
}

/// The engine's ray format for a contract enum value.
pub fn ray_format(value: i32, field: &str) -> ServiceResult<RayFormat> {
    numbered(&RayFormat::ALL, value, field, "ray format")
}

/// The engine's hit format for a contract enum value.
pub fn hit_format(value: i32, field: &str) -> ServiceResult<HitFormat> {
    numbered(&HitFormat::ALL, value, field, "hit format")
}

/// The engine's query for a contract `TraceQuery` (the accel is resolved elsewhere).
pub fn query(q: &pb::TraceQuery, max_hits_per_ray: u32) -> ServiceResult<Query> {
    let kind = match pb::QueryType::try_from(q.query) {
        Ok(pb::QueryType::Unspecified | pb::QueryType::Closest) => QueryKind::Closest,
        Ok(pb::QueryType::Any) => QueryKind::Any,
        Ok(pb::QueryType::All) => QueryKind::All,
        Ok(pb::QueryType::Count) => QueryKind::Count,
        Err(_) => return Err(ServiceError::invalid("query.query", format!("{} is not a query type", q.query))),
    };
    let flags = RayFlags::from_bits(q.ray_flags)
        .ok_or_else(|| ServiceError::invalid("query.ray_flags", format!("unknown bits in {:#x}", q.ray_flags)))?;
    if kind == QueryKind::All {
        ServiceError::check_limit(
            || "query.max_hits_per_ray".into(),
            q.max_hits_per_ray as u64,
            "max_hits_per_ray",
            max_hits_per_ray as u64,
        )?;
        if q.max_hits_per_ray == 0 {
            return Err(ServiceError::invalid("query.max_hits_per_ray", "must be at least 1 for QUERY_TYPE_ALL"));
        }
    }
    Ok(Query {
        kind,
        ray_format: ray_format(q.ray_format, "query.ray_format")?,
        hit_format: hit_format(q.hit_format, "query.hit_format")?,
        flags,
        max_hits_per_ray: q.max_hits_per_ray.max(1),
    })
}

/// The engine's build options (checked by the engine when it builds).
pub fn build_options(options: Option<&pb::BuildOptions>) -> BuildOptions {
    let Some(o) = options else { return BuildOptions::default() };
    let mut flags = BuildFlags::empty();
    flags.set(BuildFlags::PREFER_FAST_TRACE, o.prefer_fast_trace);
    flags.set(BuildFlags::PREFER_FAST_BUILD, o.prefer_fast_build);
    flags.set(BuildFlags::ALLOW_UPDATE, o.allow_update);
    flags.set(BuildFlags::ALLOW_COMPACTION, o.allow_compaction);
    flags.set(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS, o.allow_random_vertex_access);
    BuildOptions { flags, motion: motion_options(o.motion.as_ref()) }
}

/// The engine's motion options: unset, or 0 keys, is static.
pub fn motion_options(motion: Option<&pb::MotionOptions>) -> MotionOptions {
    let Some(m) = motion else { return MotionOptions::STATIC };
    let mut flags = MotionFlags::empty();
    flags.set(MotionFlags::START_VANISH, m.start_vanish);
    flags.set(MotionFlags::END_VANISH, m.end_vanish);
    MotionOptions { keys: m.keys.max(1), time_begin: m.time_begin, time_end: m.time_end, flags }
}

/// The contract's motion options (unset for a static object).
fn motion_options_message(motion: &MotionOptions) -> Option<pb::MotionOptions> {
    (!motion.is_static()).then(|| pb::MotionOptions {
        keys: motion.keys,
        time_begin: motion.time_begin,
        time_end: motion.time_end,
        start_vanish: motion.flags.contains(MotionFlags::START_VANISH),
        end_vanish: motion.flags.contains(MotionFlags::END_VANISH),
    })
}

/// The contract's build options.
pub fn build_options_message(options: &BuildOptions) -> pb::BuildOptions {
    let has = |flag| options.flags.contains(flag);
    pb::BuildOptions {
        prefer_fast_trace: has(BuildFlags::PREFER_FAST_TRACE),
        prefer_fast_build: has(BuildFlags::PREFER_FAST_BUILD),
        allow_update: has(BuildFlags::ALLOW_UPDATE),
        allow_compaction: has(BuildFlags::ALLOW_COMPACTION),
        allow_random_vertex_access: has(BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS),
        motion: motion_options_message(&options.motion),
    }
}

/// The contract's accel description.
pub fn accel_info(info: &AccelInfo, handle: &str, name: &str, device: &str, build_ns: u64) -> pb::AccelInfo {
    let vec3 = |v: rayd_engine::glam::Vec3| pb::Vec3 { x: v.x, y: v.y, z: v.z };
    pb::AccelInfo {
        handle: handle.into(),
        name: name.into(),
        device: device.into(),
        size_bytes: info.size_bytes,
        triangle_count: info.triangle_count,
        geometry_count: info.geometry_count,
        options: Some(build_options_message(&info.options)),
        compacted_size_bytes: info.compacted_size_bytes,
        build_ns,
        bounds: Some(pb::Bounds { min: Some(vec3(info.bounds.0)), max: Some(vec3(info.bounds.1)) }),
        kind: match info.kind {
            AccelKind::Triangles => pb::AccelKind::Triangles,
            AccelKind::Instances => pb::AccelKind::Instances,
            AccelKind::Transform => pb::AccelKind::Transform,
            AccelKind::MatrixMotionTransform => pb::AccelKind::MatrixMotionTransform,
            AccelKind::SrtMotionTransform => pb::AccelKind::SrtMotionTransform,
        }
        .into(),
        instance_count: info.instance_count,
        depth: info.depth,
    }
}

/// The contract's memory usage.
pub fn memory_usage(usage: &MemoryUsage) -> pb::MemoryUsage {
    pb::MemoryUsage {
        output_bytes: usage.output_bytes,
        temp_bytes: usage.temp_bytes,
        temp_update_bytes: usage.temp_update_bytes,
    }
}

/// The contract's trace statistics.
pub fn trace_stats(stats: &TraceStats, trace_ns: u64) -> pb::TraceStats {
    pb::TraceStats {
        rays: stats.rays,
        rays_hit: stats.rays_hit,
        nodes_visited: stats.nodes_visited,
        triangle_tests: stats.triangle_tests,
        trace_ns,
        device_ns: stats.device_nanos,
    }
}

/// The contract's description of the limits.
pub fn limits(limits: &crate::config::Limits) -> pb::Limits {
    pb::Limits {
        max_message_bytes: limits.max_message_bytes,
        max_rays_per_batch: limits.max_rays_per_batch,
        max_hits_per_ray: limits.max_hits_per_ray,
        max_accel_bytes: limits.max_accel_bytes,
        max_accels: limits.max_accels,
        max_buffer_bytes: limits.max_buffer_bytes,
        max_buffers: limits.max_buffers,
        stream_window: limits.window(),
        max_streams: limits.max_streams,
        max_graph_depth: limits.max_graph_depth,
        max_motion_keys: limits.max_motion_keys,
        max_total_accel_bytes: limits.max_total_accel_bytes,
        max_total_buffer_bytes: limits.max_total_buffer_bytes,
        max_rays_per_second: limits.max_rays_per_second,
        max_concurrent_operations: limits.max_concurrent_operations,
        stream_stall_seconds: limits.stream_stall_seconds,
        max_stream_products: limits.max_stream_products,
    }
}

/// The contract's description of a tenant's holdings.
pub fn usage(usage: &crate::tenant::Usage) -> pb::Usage {
    pb::Usage {
        accels: usage.accels,
        buffers: usage.buffers,
        object_bytes: usage.object_bytes,
        streams: usage.streams,
        stream_bytes: usage.stream_bytes,
        accel_bytes: usage.accel_bytes,
        buffer_bytes: usage.buffer_bytes,
        operations: usage.operations,
    }
}

/// The contract's device description.
pub fn device(info: &DeviceInfo) -> pb::Device {
    pb::Device {
        id: info.id.clone(),
        backend: match info.kind {
            BackendKind::Cpu => pb::Backend::Cpu as i32,
            BackendKind::Wgpu => pb::Backend::Wgpu as i32,
        },
        name: info.name.clone(),
        memory_bytes: info.memory_bytes,
        parallelism: info.parallelism,
        ray_formats: (1..=RayFormat::ALL.len() as i32).collect(),
        hit_formats: (1..=HitFormat::ALL.len() as i32).collect(),
        query_types: (1..=QueryKind::ALL.len() as i32).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contract_enums_map_to_the_engine_by_name() {
        for (i, format) in RayFormat::ALL.iter().enumerate() {
            let proto = pb::RayFormat::try_from(i as i32 + 1).unwrap();
            assert_eq!(proto.as_str_name().to_lowercase(), format!("ray_format_{}", format.name()));
            assert_eq!(ray_format(i as i32 + 1, "f").unwrap(), *format);
        }
        for (i, format) in HitFormat::ALL.iter().enumerate() {
            let proto = pb::HitFormat::try_from(i as i32 + 1).unwrap();
            assert_eq!(proto.as_str_name().to_lowercase(), format!("hit_format_{}", format.name()));
            assert_eq!(hit_format(i as i32 + 1, "f").unwrap(), *format);
        }
        for (i, kind) in QueryKind::ALL.iter().enumerate() {
            let proto = pb::QueryType::try_from(i as i32 + 1).unwrap();
            assert_eq!(proto.as_str_name().to_lowercase(), format!("query_type_{}", kind.name()));
        }
        assert!(ray_format(0, "query.ray_format").unwrap_err().to_string().starts_with("query.ray_format"));
        assert!(hit_format(99, "query.hit_format").is_err());
    }
}
