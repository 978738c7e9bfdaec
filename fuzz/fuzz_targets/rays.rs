//! Ray and hit buffers: arbitrary bytes traced as rays of every format, with every query kind and hit format,
//! against a small mesh; then every hit record read back. No panic; a buffer that is not whole records, or a
//! NaN time, is refused; every other buffer traces (hostile values follow the rules of `formats.proto`).

#![no_main]

use std::sync::{Arc, OnceLock};

use libfuzzer_sys::fuzz_target;
use rayd_engine::accel::BuildOptions;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::{BuildInput, TriangleInput};
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::{Accel, Context, Device};

/// A CPU context and a tetrahedron built in it.
fn scene() -> &'static (Context, Arc<Accel>) {
    static SCENE: OnceLock<(Context, Arc<Accel>)> = OnceLock::new();
    SCENE.get_or_init(|| {
        let context = Context::new(Device::cpu());
        let corners: [[f32; 3]; 4] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let vertices: Vec<u8> = corners.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
        let indices: Vec<u8> =
            [[0u32, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]].iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
        let input = BuildInput::Triangles(TriangleInput::indexed(&vertices, &indices));
        let accel = context.build_accel(&[input], &BuildOptions::default()).expect("the tetrahedron builds");
        (context, accel)
    })
}

fuzz_target!(|data: &[u8]| {
    let Some((&pick, rays)) = data.split_first() else { return };
    let (context, accel) = scene();
    let ray_format = RayFormat::ALL[pick as usize % RayFormat::ALL.len()];
    let hit_format = HitFormat::ALL[(pick as usize / 8) % HitFormat::ALL.len()];
    let kind = QueryKind::ALL[(pick as usize / 64) % QueryKind::ALL.len()];
    let query = Query { kind, max_hits_per_ray: 4, ..Query::closest(ray_format, hit_format) };
    let whole = rays.len().is_multiple_of(ray_format.size());
    let Ok(layout) = query.output_layout(rays.len()) else {
        assert!(!whole, "whole records are refused: {} bytes of {}", rays.len(), ray_format.name());
        return;
    };
    let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
    if query.check_times(rays).is_err() {
        return;
    }
    let traced = context.trace(accel, &query, rays, TraceOutput { hits: &mut hits, counts: &mut counts });
    if let Err(refused) = traced {
        panic!("whole records without a NaN time are refused: {refused}");
    }
    if hit_format != HitFormat::Bitmask {
        let per_ray = query.records_per_ray();
        for record in 0..layout.rays * per_ray {
            let hit = hit_format.read(&hits, record);
            let ray = ray_format.decode(&rays[record / per_ray * ray_format.size()..]);
            // The documented range rule: a hit lies in [tmin, tmax], both inclusive.
            let in_range = ray.tmin <= hit.t && hit.t <= ray.tmax;
            assert!(!hit.is_hit() || in_range, "record {record}: t = {} outside [{}, {}]", hit.t, ray.tmin, ray.tmax);
        }
    }
});
