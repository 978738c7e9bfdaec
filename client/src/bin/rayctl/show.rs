//! How rayctl prints the contract's messages: aligned tables and key-value blocks for people, JSON objects for
//! scripts (numbers stay numbers; bytes in bytes, times in milliseconds).

use rayd_client::convert::{
    backend_name, bounds, build_flag_names, build_flags_from_proto, hit_format_from_proto, query_kind_from_proto,
    ray_format_from_proto,
};
use rayd_client::proto::{self, AccelInfo, BufferInfo, Device, TenantInfo};
use serde_json::{Value, json};

/// What a command prints: the same result for scripts and for people.
pub struct Output {
    /// Printed with `--json`.
    pub json: Value,
    /// Printed otherwise.
    pub text: String,
}

/// Nanoseconds as milliseconds.
pub fn ms(nanos: u64) -> f64 {
    nanos as f64 / 1e6
}

/// An `f32` as the `f64` with the same shortest decimal form, so JSON shows `0.1` rather than
/// `0.10000000149011612`.
fn shortest(x: f32) -> f64 {
    x.to_string().parse().unwrap_or(f64::from(x))
}

/// A byte count for people: B, KiB, MiB or GiB.
pub fn bytes(n: u64) -> String {
    let units = ["B", "KiB", "MiB", "GiB", "TiB"];
    let power = units.iter().enumerate().rev().find(|&(i, _)| n >= 1u64 << (10 * i)).map_or(0, |(i, _)| i);
    match power {
        0 => format!("{n} B"),
        _ => format!("{:.1} {}", n as f64 / (1u64 << (10 * power)) as f64, units[power]),
    }
}

/// Rows under a header, each column as wide as its widest cell, two spaces apart.
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut widths: Vec<usize> = header.iter().map(|h| h.len()).collect();
    for row in rows {
        for (width, cell) in widths.iter_mut().zip(row) {
            *width = (*width).max(cell.chars().count());
        }
    }
    let line = |cells: Vec<&str>| {
        let padded: Vec<String> = cells.iter().zip(&widths).map(|(cell, width)| format!("{cell:width$}")).collect();
        padded.join("  ").trim_end().to_owned()
    };
    std::iter::once(line(header.to_vec()))
        .chain(rows.iter().map(|row| line(row.iter().map(String::as_str).collect())))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The engine names of a device's formats and query kinds, unknown numbers left out.
fn capabilities(device: &Device) -> [Vec<&'static str>; 3] {
    [
        device.ray_formats.iter().filter_map(|&f| ray_format_from_proto(f)).map(|f| f.name()).collect(),
        device.hit_formats.iter().filter_map(|&f| hit_format_from_proto(f)).map(|f| f.name()).collect(),
        device.query_types.iter().filter_map(|&q| query_kind_from_proto(q)).map(|q| q.name()).collect(),
    ]
}

/// `rayctl devices`.
pub fn devices(devices: &[Device]) -> Output {
    let json = devices
        .iter()
        .map(|d| {
            let [ray_formats, hit_formats, query_types] = capabilities(d);
            json!({
                "id": d.id, "backend": backend_name(d.backend), "name": d.name, "memory_bytes": d.memory_bytes,
                "parallelism": d.parallelism, "ray_formats": ray_formats, "hit_formats": hit_formats,
                "query_types": query_types,
            })
        })
        .collect::<Vec<_>>();
    let rows: Vec<Vec<String>> = devices
        .iter()
        .map(|d| {
            let [_, _, queries] = capabilities(d);
            let backend = backend_name(d.backend).to_owned();
            vec![
                d.id.clone(),
                backend,
                bytes(d.memory_bytes),
                d.parallelism.to_string(),
                queries.join(","),
                d.name.clone(),
            ]
        })
        .collect();
    let formats = devices.iter().map(|d| {
        let [rays, hits, _] = capabilities(d);
        format!("{}: ray formats {}; hit formats {}", d.id, rays.join(", "), hits.join(", "))
    });
    let text = std::iter::once(table(&["ID", "BACKEND", "MEMORY", "PARALLELISM", "QUERIES", "NAME"], &rows))
        .chain(formats)
        .collect::<Vec<_>>()
        .join("\n");
    Output { json: json!({ "devices": json }), text }
}

/// One accel as a JSON object.
fn accel_json(info: &AccelInfo) -> Value {
    let (min, max) = bounds(info).map(|(lo, hi)| (lo.to_array().map(shortest), hi.to_array().map(shortest))).unzip();
    json!({
        "name": info.name, "handle": info.handle, "device": info.device, "size_bytes": info.size_bytes,
        "kind": kind_name(info.kind()), "triangle_count": info.triangle_count, "geometry_count": info.geometry_count,
        "instance_count": info.instance_count, "depth": info.depth, "compacted_size_bytes": info.compacted_size_bytes, "build_ms": ms(info.build_ns),
        "options": build_flag_names(build_flags_from_proto(info.options.unwrap_or_default())),
        "motion": info.options.and_then(|o| o.motion).map(|m| json!({
            "keys": m.keys, "time_begin": m.time_begin, "time_end": m.time_end,
            "start_vanish": m.start_vanish, "end_vanish": m.end_vanish,
        })),
        "bounds": min.map(|min| json!({ "min": min, "max": max })),
    })
}

/// An accel's motion options in words: `-` when static.
fn motion_text(info: &AccelInfo) -> String {
    let Some(m) = info.options.and_then(|o| o.motion) else { return "-".into() };
    let vanish = match (m.start_vanish, m.end_vanish) {
        (false, false) => "",
        (true, false) => ", vanishes before",
        (false, true) => ", vanishes after",
        (true, true) => ", vanishes outside",
    };
    format!("{} keys over [{}, {}]{vanish}", m.keys, m.time_begin, m.time_end)
}

/// An accel kind's lower-case name.
fn kind_name(kind: proto::AccelKind) -> &'static str {
    match kind {
        proto::AccelKind::Unspecified => "unspecified",
        proto::AccelKind::Triangles => "triangles",
        proto::AccelKind::Instances => "instances",
        proto::AccelKind::Transform => "transform",
        proto::AccelKind::MatrixMotionTransform => "matrix_motion_transform",
        proto::AccelKind::SrtMotionTransform => "srt_motion_transform",
    }
}

/// `rayctl info` and `rayctl build`: one accel.
pub fn accel(info: &AccelInfo) -> Output {
    let flags = build_flag_names(build_flags_from_proto(info.options.unwrap_or_default()));
    let bounds = bounds(info).map_or("empty".into(), |(lo, hi)| format!("{lo} .. {hi}"));
    let fields = [
        ("name", info.name.clone()),
        ("handle", info.handle.clone()),
        ("device", info.device.clone()),
        ("kind", kind_name(info.kind()).into()),
        ("triangles", info.triangle_count.to_string()),
        ("geometries", info.geometry_count.to_string()),
        ("instances", info.instance_count.to_string()),
        ("graph depth", info.depth.to_string()),
        ("size", bytes(info.size_bytes)),
        ("compacted size", info.compacted_size_bytes.map_or("-".into(), bytes)),
        ("build time", format!("{:.2} ms", ms(info.build_ns))),
        ("options", if flags.is_empty() { "-".into() } else { flags.join(", ") }),
        ("motion", motion_text(info)),
        ("bounds", bounds),
    ];
    let text = fields.iter().map(|(key, value)| format!("{:16}{value}", format!("{key}:"))).collect::<Vec<_>>();
    Output { json: accel_json(info), text: text.join("\n") }
}

/// `rayctl load`: the root accel, and how many were loaded.
pub fn loaded(accels: &[AccelInfo]) -> Output {
    let Some(root) = accels.last() else {
        return Output { json: json!({ "accels": [] }), text: "loaded nothing".into() };
    };
    let shown = accel(root);
    Output {
        json: json!({ "accels": accels.iter().map(accel_json).collect::<Vec<_>>() }),
        text: format!("loaded {} accel(s)\n{}", accels.len(), shown.text),
    }
}

/// `rayctl accels`.
pub fn accels(accels: &[AccelInfo]) -> Output {
    let rows: Vec<Vec<String>> = accels
        .iter()
        .map(|a| {
            let build = format!("{:.1} ms", ms(a.build_ns));
            vec![
                a.name.clone(),
                a.device.clone(),
                a.triangle_count.to_string(),
                bytes(a.size_bytes),
                build,
                a.handle.clone(),
            ]
        })
        .collect();
    Output {
        json: json!({ "accels": accels.iter().map(accel_json).collect::<Vec<_>>() }),
        text: table(&["NAME", "DEVICE", "TRIANGLES", "SIZE", "BUILD", "HANDLE"], &rows),
    }
}

/// `rayctl buffers`.
pub fn buffers(buffers: &[BufferInfo]) -> Output {
    let json = buffers.iter().map(|b| json!({ "id": b.id, "name": b.name, "size_bytes": b.size_bytes }));
    let rows: Vec<Vec<String>> =
        buffers.iter().map(|b| vec![b.id.clone(), b.name.clone(), bytes(b.size_bytes)]).collect();
    Output { json: json!({ "buffers": json.collect::<Vec<_>>() }), text: table(&["ID", "NAME", "SIZE"], &rows) }
}

/// `rayctl stats`: each tenant's usage against its quotas.
pub fn stats(tenants: &[TenantInfo]) -> Output {
    let of = |used: String, limit: String| format!("{used} / {limit}");
    let rows: Vec<Vec<String>> = tenants
        .iter()
        .map(|t| {
            let (u, l) = (t.usage.unwrap_or_default(), t.limits.unwrap_or_default());
            vec![
                t.name.clone(),
                t.share.to_string(),
                of(u.accels.to_string(), l.max_accels.to_string()),
                of(bytes(u.accel_bytes), bytes(l.max_total_accel_bytes)),
                of(u.buffers.to_string(), l.max_buffers.to_string()),
                of(bytes(u.buffer_bytes), bytes(l.max_total_buffer_bytes)),
                of(u.streams.to_string(), l.max_streams.to_string()),
                of(u.operations.to_string(), l.max_concurrent_operations.to_string()),
            ]
        })
        .collect();
    let json = tenants.iter().map(|t| {
        let (u, l) = (t.usage.unwrap_or_default(), t.limits.unwrap_or_default());
        json!({
            "name": t.name,
            "share": t.share,
            "accels": u.accels, "max_accels": l.max_accels,
            "accel_bytes": u.accel_bytes, "max_total_accel_bytes": l.max_total_accel_bytes,
            "buffers": u.buffers, "max_buffers": l.max_buffers,
            "buffer_bytes": u.buffer_bytes, "max_total_buffer_bytes": l.max_total_buffer_bytes,
            "streams": u.streams, "max_streams": l.max_streams,
            "operations": u.operations, "max_concurrent_operations": l.max_concurrent_operations,
            "max_rays_per_second": l.max_rays_per_second,
        })
    });
    let header = ["TENANT", "SHARE", "ACCELS", "ACCEL BYTES", "BUFFERS", "BUFFER BYTES", "STREAMS", "OPERATIONS"];
    Output { json: json!({ "tenants": json.collect::<Vec<_>>() }), text: table(&header, &rows) }
}

#[cfg(test)]
mod tests {
    use rayd_client::proto;

    use super::*;

    #[test]
    fn byte_counts_pick_the_largest_whole_unit() {
        assert_eq!(bytes(0), "0 B");
        assert_eq!(bytes(1023), "1023 B");
        assert_eq!(bytes(1536), "1.5 KiB");
        assert_eq!(bytes(64 << 20), "64.0 MiB");
        assert_eq!(bytes(3 << 30), "3.0 GiB");
    }

    #[test]
    fn tables_align_columns() {
        let rows = vec![vec!["bunny".to_owned(), "69451".to_owned()], vec!["a".to_owned(), "1".to_owned()]];
        assert_eq!(table(&["NAME", "TRIANGLES"], &rows), "NAME   TRIANGLES\nbunny  69451\na      1");
    }

    #[test]
    fn accel_json_has_engine_names_and_numbers() {
        let v = |x| Some(proto::Vec3 { x, y: x, z: x });
        let info = AccelInfo {
            name: "bunny".into(),
            triangle_count: 3,
            build_ns: 2_500_000,
            options: Some(proto::BuildOptions { prefer_fast_trace: true, ..Default::default() }),
            bounds: Some(proto::Bounds { min: v(-1.0), max: v(0.1) }),
            ..Default::default()
        };
        let output = accel(&info);
        assert_eq!(output.json["options"], json!(["prefer_fast_trace"]));
        assert_eq!(output.json["build_ms"], json!(2.5));
        assert_eq!(output.json["bounds"]["max"], json!([0.1, 0.1, 0.1]));
        assert_eq!(output.json["compacted_size_bytes"], Value::Null);
        assert!(output.text.contains("triangles:      3"), "{}", output.text);
    }

    #[test]
    fn devices_list_their_formats_by_engine_name() {
        let device = Device {
            id: "cpu:0".into(),
            backend: proto::Backend::Cpu.into(),
            ray_formats: vec![proto::RayFormat::OriginDirection.into()],
            hit_formats: vec![proto::HitFormat::TTriidUV.into(), 99],
            query_types: vec![proto::QueryType::Any.into()],
            ..Default::default()
        };
        let output = devices(&[device]);
        assert_eq!(output.json["devices"][0]["hit_formats"], json!(["t_triid_u_v"]));
        assert_eq!(output.json["devices"][0]["backend"], json!("cpu"));
        assert!(
            output.text.contains("cpu:0: ray formats origin_direction; hit formats t_triid_u_v"),
            "{}",
            output.text
        );
    }
}
