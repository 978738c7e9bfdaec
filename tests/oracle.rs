//! The CPU backend against the brute-force oracle: the same bytes for every ray format × hit format × query
//! kind on random soups with several geometries, masks, culling flags and random ray ranges.

mod common;

use common::{pack_rays, random_rays, random_soup, u32_at};
use proptest::prelude::*;
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::format::{HitFormat, Ray, RayFlags, RayFormat};
use rayd_engine::geometry::{BuildInput, GeometryFlags, TriangleInput, gather};
use rayd_engine::query::{Query, QueryKind, TraceOutput};
use rayd_engine::{Context, Device, oracle};

/// Two geometries over one random soup: the first half with masks and a primitive offset, the second with face
/// culling disabled.
struct Scene {
    vertices: Vec<u8>,
    first: Vec<u8>,
    second: Vec<u8>,
    masks: Vec<u8>,
}

impl Scene {
    fn new(triangles: usize, seed: u64) -> Scene {
        let packed = random_soup(triangles, seed).pack();
        let split = (triangles / 2) * 12;
        let masks = (0..triangles / 2).flat_map(|i| (1u32 << (i % 5) >> 1).to_le_bytes()).collect();
        Scene {
            vertices: packed.vertices,
            first: packed.indices[..split].to_vec(),
            second: packed.indices[split..].to_vec(),
            masks,
        }
    }

    fn inputs(&self) -> Vec<BuildInput<'_>> {
        vec![
            BuildInput::Triangles(TriangleInput {
                masks: Some(&self.masks),
                primitive_index_offset: 1000,
                ..TriangleInput::indexed(&self.vertices, &self.first)
            }),
            BuildInput::Triangles(TriangleInput {
                flags: GeometryFlags::DISABLE_FACE_CULLING,
                ..TriangleInput::indexed(&self.vertices, &self.second)
            }),
        ]
    }
}

/// Traces with both the CPU backend and the oracle; returns (cpu hits, cpu counts, oracle hits, oracle counts).
fn trace_both(scene: &Scene, options: BuildOptions, query: &Query, rays: &[u8]) -> [Vec<u8>; 4] {
    let context = Context::new(Device::cpu());
    let accel = context.build_accel(&scene.inputs(), &options).unwrap();
    let layout = query.output_layout(rays.len()).unwrap();
    let mut out =
        [vec![0xA5; layout.hits], vec![0xA5; layout.counts], vec![0x5A; layout.hits], vec![0x5A; layout.counts]];
    let [cpu_hits, cpu_counts, oracle_hits, oracle_counts] = &mut out;
    context.trace(&accel, query, rays, TraceOutput { hits: cpu_hits, counts: cpu_counts }).unwrap();
    let triangles = gather(&scene.inputs(), 1).unwrap();
    oracle::trace(&triangles, query, rays, TraceOutput { hits: oracle_hits, counts: oracle_counts }).unwrap();
    out
}

fn rays_without_early_exit(count: usize, seed: u64) -> Vec<Ray> {
    let mut rays = random_rays(count, seed);
    for ray in &mut rays {
        ray.flags.remove(RayFlags::TERMINATE_ON_FIRST_HIT);
    }
    rays
}

#[test]
fn every_format_and_query_gives_the_oracles_bytes() {
    let scene = Scene::new(300, 11);
    let rays = rays_without_early_exit(600, 12);
    let mut hit_rays = 0;
    for ray_format in RayFormat::ALL {
        let packed = pack_rays(&rays, ray_format);
        for hit_format in HitFormat::ALL {
            for kind in QueryKind::ALL {
                let query = Query { kind, ray_format, hit_format, flags: RayFlags::empty(), max_hits_per_ray: 3 };
                let [cpu_hits, cpu_counts, oracle_hits, oracle_counts] =
                    trace_both(&scene, BuildOptions::default(), &query, &packed);
                let case = format!("{} × {} × {}", ray_format.name(), hit_format.name(), kind.name());
                assert_eq!(cpu_counts, oracle_counts, "{case}: counts");
                if kind == QueryKind::Any {
                    // Any hit may be a different one: compare hit/miss only (the bitmask format is exactly that).
                    continue;
                }
                assert_eq!(cpu_hits, oracle_hits, "{case}: hits");
                if hit_format == HitFormat::Bitmask && kind == QueryKind::Closest {
                    hit_rays = cpu_hits.iter().map(|b| b.count_ones()).sum();
                }
            }
            let any = Query {
                kind: QueryKind::Any,
                ray_format,
                hit_format: HitFormat::Bitmask,
                ..Query::closest(ray_format, hit_format)
            };
            let [cpu_hits, _, oracle_hits, _] = trace_both(&scene, BuildOptions::default(), &any, &packed);
            assert_eq!(cpu_hits, oracle_hits, "{}: any hit/miss", ray_format.name());
        }
    }
    // The scene is not trivial: a good share of the rays hit, and not all.
    assert!(hit_rays > 60 && hit_rays < 540, "{hit_rays} of 600 rays hit");
}

#[test]
fn any_reports_a_real_hit_and_query_flags_apply_to_every_ray() {
    let scene = Scene::new(200, 21);
    let rays = pack_rays(&rays_without_early_exit(500, 22), RayFormat::Full);
    let any = Query { kind: QueryKind::Any, ..Query::closest(RayFormat::Full, HitFormat::TTriid) };
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 64, ..any };
    let [cpu_any, _, _, _] = trace_both(&scene, BuildOptions::default(), &any, &rays);
    let [_, _, oracle_all, oracle_counts] = trace_both(&scene, BuildOptions::default(), &all, &rays);
    for ray in 0..500 {
        let (t, prim) = (common::f32_at(&cpu_any, 2 * ray), u32_at(&cpu_any, 2 * ray + 1));
        let count = u32_at(&oracle_counts, ray) as usize;
        assert!(count <= 64);
        let listed = (0..count).any(|k| {
            let slot = 2 * (ray * 64 + k);
            common::f32_at(&oracle_all, slot) == t && u32_at(&oracle_all, slot + 1) == prim
        });
        assert_eq!(t >= 0.0, count > 0, "ray {ray}");
        assert!(t < 0.0 || listed, "ray {ray}: any-hit (t {t}, prim {prim}) is not one of the oracle's hits");
    }
    for flags in [RayFlags::CULL_BACK_FACING, RayFlags::CULL_FRONT_FACING, RayFlags::TERMINATE_ON_FIRST_HIT] {
        let query = Query { kind: QueryKind::Count, flags, ..Query::closest(RayFormat::Full, HitFormat::Bitmask) };
        let [cpu_hits, cpu_counts, oracle_hits, oracle_counts] =
            trace_both(&scene, BuildOptions::default(), &query, &rays);
        assert_eq!(cpu_hits, oracle_hits, "{flags:?}");
        if flags == RayFlags::TERMINATE_ON_FIRST_HIT {
            assert!((0..500).all(|r| u32_at(&cpu_counts, r) <= 1));
        } else {
            assert_eq!(cpu_counts, oracle_counts, "{flags:?}");
        }
    }
}

/// Rays whose range reaches behind their origin (a negative `tmin`; some with a negative `tmax` too, so only behind)
/// and rays starting at `tmin` −0: the box test widens their intervals at every node where rays with `tmin ≥ 0` carry
/// the widening in their reciprocals, and both must give the oracle's bytes.
#[test]
fn ranges_reaching_behind_the_origin_give_the_oracles_bytes() {
    let scene = Scene::new(300, 31);
    let mut rays = rays_without_early_exit(600, 32);
    for (i, ray) in rays.iter_mut().enumerate() {
        // The rays head for the soup: turned around, they find it behind them.
        match i % 4 {
            0 => (ray.direction, ray.tmin) = (-ray.direction, -3.0),
            1 => (ray.direction, ray.tmin, ray.tmax) = (-ray.direction, -3.0, -0.25),
            2 => ray.tmin = -0.0,
            _ => {}
        }
    }
    let rays = pack_rays(&rays, RayFormat::OriginTminDirectionTmax);
    for kind in QueryKind::ALL {
        let hit_format = if kind == QueryKind::Any { HitFormat::Bitmask } else { HitFormat::TTriid };
        let query =
            Query { kind, max_hits_per_ray: 3, ..Query::closest(RayFormat::OriginTminDirectionTmax, hit_format) };
        let [cpu_hits, cpu_counts, oracle_hits, oracle_counts] =
            trace_both(&scene, BuildOptions::default(), &query, &rays);
        assert_eq!(cpu_counts, oracle_counts, "{}: counts", kind.name());
        assert_eq!(cpu_hits, oracle_hits, "{}: hits", kind.name());
        if kind == QueryKind::Closest {
            // Hits behind the origin are there: closest hits at negative distances.
            let behind = (0..600)
                .filter(|&r| common::f32_at(&cpu_hits, 2 * r) < 0.0 && u32_at(&cpu_hits, 2 * r + 1) != u32::MAX);
            let behind = behind.count();
            assert!(behind > 60, "{behind} hits behind their origins");
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn random_scenes_match_the_oracle_for_every_build_preset(
        seed in any::<u64>(),
        triangles in 2usize..400,
        preset in 0usize..3,
        kind in prop::sample::select(QueryKind::ALL.to_vec()),
    ) {
        let scene = Scene::new(triangles, seed);
        let flags = [BuildFlags::empty(), BuildFlags::PREFER_FAST_BUILD, BuildFlags::PREFER_FAST_TRACE][preset];
        let rays = pack_rays(&rays_without_early_exit(300, seed ^ 0xff), RayFormat::Full);
        let hit_format = if kind == QueryKind::Any { HitFormat::Bitmask } else { HitFormat::Full };
        let query = Query { kind, max_hits_per_ray: 5, ..Query::closest(RayFormat::Full, hit_format) };
        let [cpu_hits, cpu_counts, oracle_hits, oracle_counts] = trace_both(&scene, BuildOptions::new(flags), &query, &rays);
        prop_assert_eq!(cpu_counts, oracle_counts);
        prop_assert_eq!(cpu_hits, oracle_hits);
    }
}
