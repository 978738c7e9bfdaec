//! `compute_memory_usage`, `compute_instance_memory_usage` and `compute_transform_memory_usage` give true upper bounds: a counting allocator measures
//! what each build really holds afterwards (output) and at its peak (output + temp), for every preset, on real and
//! random meshes, static and moving (two and three motion keys), and for instance accels of many instances, with and
//! without motion keys.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use common::{random_soup, shared_mesh};
use rayd_engine::accel::{BuildFlags, BuildOptions, MemoryUsage};
use rayd_engine::geometry::{
    BuildInput, Instance, InstanceFlags, MotionFlags, MotionOptions, TransformInput, TriangleInput,
};
use rayd_engine::mesh::Mesh;
use rayd_engine::{Accel, Context, Device};

/// Counts live heap bytes and their peak.
struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn grew(bytes: usize) {
    let live = LIVE.fetch_add(bytes, Ordering::SeqCst) + bytes;
    PEAK.fetch_max(live, Ordering::SeqCst);
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        grew(layout.size());
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LIVE.fetch_sub(layout.size(), Ordering::SeqCst);
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > layout.size() {
            grew(new_size - layout.size());
        } else {
            LIVE.fetch_sub(layout.size() - new_size, Ordering::SeqCst);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Builds `inputs` with `options` and checks that what the build holds afterwards and at its peak stays within what
/// `compute_memory_usage` reported for them.
fn check_build(case: &str, inputs: &[BuildInput<'_>], options: &BuildOptions, triangles: usize) {
    let context = Context::new(Device::cpu());
    let usage = context.compute_memory_usage(inputs, options).unwrap();
    check_within(case, usage, options, triangles, || context.build_accel(inputs, options).unwrap());
}

/// Runs `build` (of `items` triangles or instances with `options`) and checks that what it holds afterwards and at
/// its peak stays within `usage`.
fn check_within(
    case: &str,
    usage: MemoryUsage,
    options: &BuildOptions,
    items: usize,
    build: impl FnOnce() -> Arc<Accel>,
) {
    let before = LIVE.load(Ordering::SeqCst);
    PEAK.store(before, Ordering::SeqCst);
    let accel = build();
    let held = LIVE.load(Ordering::SeqCst) - before;
    let peak = PEAK.load(Ordering::SeqCst) - before;
    let size = accel.info().size_bytes;
    eprintln!(
        "{case}: size {size} (bound {}), held {held}, peak {peak}, temp {} (bound {}), {:.0} temp bytes an item",
        usage.output_bytes,
        peak - held,
        usage.temp_bytes,
        (peak - held) as f64 / items as f64
    );
    assert!(size <= usage.output_bytes, "{case}: size {size} > {}", usage.output_bytes);
    assert!(held as u64 <= usage.output_bytes, "{case}: held {held} > {}", usage.output_bytes);
    assert!(peak as u64 <= usage.output_bytes + usage.temp_bytes, "{case}: peak {peak} beyond output + temp");
    assert_eq!(usage.temp_update_bytes > 0, options.flags.contains(BuildFlags::ALLOW_UPDATE));
}

/// One test: the counting allocator counts every thread's allocations, so no other test may run beside it.
#[test]
fn builds_stay_within_the_reported_output_and_temp_sizes() {
    // Start rayon's pool before measuring: its threads' fixed allocations are not a build's.
    rayon::broadcast(|_| ());
    static_builds();
    motion_builds();
    instance_builds();
    transform_builds();
}

/// Every preset, with and without masks, on real and random meshes.
fn static_builds() {
    let meshes: Vec<(&str, Mesh)> = vec![
        ("bunny", shared_mesh("stanford-bunny")),
        ("nefertiti", shared_mesh("nefertiti")),
        ("soup-50k", random_soup(50_000, 5)),
        ("soup-3", random_soup(3, 6)),
    ];
    let flag_sets = [
        BuildFlags::empty(),
        BuildFlags::PREFER_FAST_BUILD,
        BuildFlags::PREFER_FAST_TRACE | BuildFlags::ALLOW_UPDATE,
        BuildFlags::ALLOW_RANDOM_VERTEX_ACCESS | BuildFlags::ALLOW_COMPACTION,
    ];
    for (name, mesh) in &meshes {
        let packed = mesh.pack();
        let masks: Vec<u8> = vec![0; mesh.triangles.len() * 4];
        for flags in flag_sets {
            for with_masks in [false, true] {
                let input = TriangleInput { masks: with_masks.then_some(masks.as_slice()), ..packed.input() };
                let case = format!("{name}, {flags:?}, masks {with_masks}");
                check_build(&case, &[BuildInput::Triangles(input)], &BuildOptions::new(flags), mesh.triangles.len());
            }
        }
    }
}

/// Moving meshes with two and three keys, with and without updates.
fn motion_builds() {
    for (name, mesh) in [("bunny", shared_mesh("stanford-bunny")), ("soup-50k", random_soup(50_000, 7))] {
        let packed = mesh.pack();
        for keys in [2u32, 3] {
            // Every key after the first moves the mesh by a tenth of its size along the diagonal.
            let (lo, hi) = mesh.bounds();
            let step = (hi - lo) * 0.1;
            let moved: Vec<Vec<u8>> = (1..keys)
                .map(|k| {
                    let positions = mesh.positions.iter().map(|&p| p + step * k as f32);
                    positions.flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect()
                })
                .collect();
            let motion_vertices: Vec<&[u8]> = moved.iter().map(Vec::as_slice).collect();
            let input = TriangleInput { motion_vertices: &motion_vertices, ..packed.input() };
            for flags in [BuildFlags::empty(), BuildFlags::PREFER_FAST_TRACE | BuildFlags::ALLOW_UPDATE] {
                let motion = MotionOptions { keys, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
                let options = BuildOptions { motion, ..BuildOptions::new(flags) };
                let case = format!("{name}, {keys} keys, {flags:?}");
                check_build(&case, &[BuildInput::Triangles(input)], &options, mesh.triangles.len());
            }
        }
    }
}

/// Instance accels of a few and of many instances of one mesh, at random places and turns, static and with two and
/// three keys, with and without updates.
fn instance_builds() {
    let context = Context::new(Device::cpu());
    let packed = shared_mesh("teapot").pack();
    let child = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let mut seed = 11u32;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 17;
        seed ^= seed << 5;
        seed as f32 / u32::MAX as f32
    };
    for count in [3, 40_000] {
        let instances: Vec<Instance> = (0..count)
            .map(|id| {
                let (turn, at) = (next() * std::f32::consts::TAU, [next(), next(), next()].map(|x| x * 500.0));
                let (sin, cos) = turn.sin_cos();
                Instance {
                    transform: [cos, -sin, 0.0, at[0], sin, cos, 0.0, at[1], 0.0, 0.0, 1.0, at[2]],
                    instance_id: id,
                    mask: 0xFF,
                    flags: InstanceFlags::empty(),
                    child: Arc::clone(&child),
                }
            })
            .collect();
        for keys in [1u32, 2, 3] {
            for flags in [BuildFlags::empty(), BuildFlags::PREFER_FAST_TRACE | BuildFlags::ALLOW_UPDATE] {
                let motion = MotionOptions { keys, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
                let options = BuildOptions { motion, ..BuildOptions::new(flags) };
                let usage = context.compute_instance_memory_usage(&instances, &options).unwrap();
                let case = format!("{count} instances, {keys} keys, {flags:?}");
                check_within(&case, usage, &options, instances.len(), || {
                    context.build_instance_accel(&instances, &options).unwrap()
                });
            }
        }
    }
}

/// Static, matrix and SRT motion transforms of up to 64 keys (whose keys a bound of one instance once left out).
fn transform_builds() {
    let context = Context::new(Device::cpu());
    let packed = shared_mesh("teapot").pack();
    let child = context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default()).unwrap();
    let moved = |k: usize| [1.0, 0.0, 0.0, k as f32, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
    let srt_moved = |k: usize| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, k as f32, 0.0, 0.0];
    let options = BuildOptions::default();
    for keys in [2, 64] {
        let motion = MotionOptions { keys: keys as u32, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() };
        let transforms = [
            ("static", TransformInput::Static(moved(1))),
            ("matrix", TransformInput::MatrixMotion { keys: (0..keys).map(moved).collect(), motion }),
            ("SRT", TransformInput::SrtMotion { keys: (0..keys).map(srt_moved).collect(), motion }),
        ];
        for (kind, transform) in transforms {
            let usage = context.compute_transform_memory_usage(&transform, &child, &options).unwrap();
            let case = format!("{kind} transform, {keys} keys");
            check_within(&case, usage, &options, 1, || context.build_transform(&transform, &child).unwrap());
        }
    }
    // A transform that its build refuses (motion keys without motion: one key) is refused here too.
    let one_key = TransformInput::MatrixMotion { keys: vec![moved(0)], motion: MotionOptions::default() };
    let refused = context.compute_transform_memory_usage(&one_key, &child, &options).unwrap_err();
    assert!(refused.to_string().contains("at least 2 motion keys"), "{refused}");
}
