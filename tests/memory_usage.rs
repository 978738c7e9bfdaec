//! `compute_memory_usage` gives true upper bounds: a counting allocator measures what each build really holds
//! afterwards (output) and at its peak (output + temp), for every preset, on real and random meshes.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use common::{random_soup, shared_mesh};
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::geometry::{BuildInput, TriangleInput};
use rayd_engine::mesh::Mesh;
use rayd_engine::{Context, Device};

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

#[test]
fn builds_stay_within_the_reported_output_and_temp_sizes() {
    // Start rayon's pool before measuring: its threads' fixed allocations are not a build's.
    rayon::broadcast(|_| ());
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
                let inputs = [BuildInput::Triangles(input)];
                let options = BuildOptions::new(flags);
                let context = Context::new(Device::cpu());
                let usage = context.compute_memory_usage(&inputs, &options).unwrap();
                let before = LIVE.load(Ordering::SeqCst);
                PEAK.store(before, Ordering::SeqCst);
                let accel = context.build_accel(&inputs, &options).unwrap();
                let held = LIVE.load(Ordering::SeqCst) - before;
                let peak = PEAK.load(Ordering::SeqCst) - before;
                let case = format!("{name}, {flags:?}, masks {with_masks}");
                let size = accel.info().size_bytes;
                eprintln!(
                    "{case}: size {size} (bound {}), held {held}, peak {peak}, temp {} (bound {}), {:.0} temp bytes/triangle",
                    usage.output_bytes,
                    peak - held,
                    usage.temp_bytes,
                    (peak - held) as f64 / mesh.triangles.len() as f64
                );
                assert!(size <= usage.output_bytes, "{case}: size {size} > {}", usage.output_bytes);
                assert!(held as u64 <= usage.output_bytes, "{case}: held {held} > {}", usage.output_bytes);
                assert!(
                    peak as u64 <= usage.output_bytes + usage.temp_bytes,
                    "{case}: peak {peak} beyond output + temp"
                );
                assert_eq!(usage.temp_update_bytes > 0, flags.contains(BuildFlags::ALLOW_UPDATE));
            }
        }
    }
}
