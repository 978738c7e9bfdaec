//! Rays made on the server: how fast each generator makes its rays on one core, packed in
//! `origin_tmin_direction_tmax_time` a part of 8,192 rays at a time, as the CPU backend makes them for a trace
//! (`backend::host::PART_RAYS`), after a part of each is checked against its rays made one by one. Prints one table
//! of M rays/s (median of 5 runs over 4,194,304 rays); run with `cargo bench --bench generators`. A trace of the
//! bunny runs at 20–50 M rays/s a core, so a generator much slower than a few hundred M rays/s shows in a generated
//! trace's rate.

use std::time::Instant;

use glam::Vec3;
use rayd_engine::backend::host::PART_RAYS;
use rayd_engine::format::{Ray, RayFormat};
use rayd_engine::raygen::{Camera, Generator, Lidar, LidarFrame, Orthographic, PixelSampling, SphereSampling};

/// Rays each generator makes a run.
const RAYS: u64 = 1 << 22;
/// Timed runs; the median is reported.
const RUNS: usize = 5;

/// Checks a part of `generator`'s rays, from an odd first ray, against the same rays made one by one from their
/// index where the generator has such a form (cameras, lidars), and against their point and unit length otherwise.
fn check(generator: &Generator, format: RayFormat) {
    let first = RAYS / 2 + 3;
    let mut part = vec![0u8; PART_RAYS * format.size()];
    generator.fill(format, first, &mut part);
    let made = |i: usize| format.decode(&part[i * format.size()..(i + 1) * format.size()]);
    for i in 0..PART_RAYS {
        let index = first + i as u64;
        let ray = made(i);
        let expected = match generator {
            Generator::Pinhole(..) | Generator::Orthographic(..) => generator.camera_frame().unwrap().ray(index),
            Generator::Lidar(lidar) => {
                let (frame, channels) = (LidarFrame::new(lidar), lidar.elevations_degrees.len() as u64);
                frame.ray(frame.step(index / channels), frame.channel((index % channels) as usize))
            }
            Generator::Sphere(sphere) => {
                let point = sphere.points[(index / u64::from(sphere.samples)) as usize];
                assert!((ray.direction.length() - 1.0).abs() < 1e-5, "ray {index} has a unit direction");
                Ray { origin: point.into(), direction: ray.direction, ..ray }
            }
            Generator::Secondary(_) => unreachable!("not benchmarked"),
        };
        assert_eq!(ray, expected, "ray {index}");
    }
}

/// Seconds to make all `RAYS` rays of `generator`, a part at a time into one reused buffer.
fn make(generator: &Generator, format: RayFormat) -> f64 {
    let mut part = vec![0u8; PART_RAYS * format.size()];
    let start = Instant::now();
    for first in (0..RAYS).step_by(PART_RAYS) {
        generator.fill(format, first, &mut part);
        std::hint::black_box(&part);
    }
    start.elapsed().as_secs_f64()
}

fn main() {
    let format = RayFormat::OriginTminDirectionTmaxTime;
    let camera = Camera {
        eye: Vec3::new(0.0, 0.0, 3.0),
        target: Vec3::ZERO,
        up: Vec3::Y,
        fov_y_degrees: 40.0,
        width: 2048,
        height: 2048,
    };
    let centres = PixelSampling { samples: 1, jitter_seed: None };
    let jittered = PixelSampling { samples: 4, jitter_seed: Some(7) };
    let orthographic = Orthographic {
        eye: camera.eye,
        target: camera.target,
        up: camera.up,
        view_height: 2.0,
        width: 2048,
        height: 2048,
    };
    let lidar = Lidar {
        origin: Vec3::ZERO,
        forward: Vec3::X,
        up: Vec3::Z,
        elevations_degrees: (0..64).map(|channel| channel as f32 * 0.5 - 16.0).collect(),
        steps: (RAYS / 64) as u32,
        min_range: 0.1,
        max_range: 100.0,
        time: (0.0, 0.1),
    };
    let points: Vec<Vec3> = (0..RAYS / 64).map(|i| Vec3::new(i as f32, 0.0, 0.0)).collect();
    let sphere = |normals: Vec<Vec3>| SphereSampling {
        points: points.clone(),
        normals,
        samples: 64,
        min_distance: 1e-3,
        max_distance: 10.0,
        seed: 3,
    };
    let generators = [
        ("pinhole 2048², pixel centres", Generator::Pinhole(camera, centres)),
        (
            "pinhole 1024² × 4 jittered samples",
            Generator::Pinhole(Camera { width: 1024, height: 1024, ..camera }, jittered),
        ),
        ("orthographic 2048², pixel centres", Generator::Orthographic(orthographic, centres)),
        ("lidar, 64 channels × 65,536 steps", Generator::Lidar(lidar)),
        ("sphere, 65,536 points × 64 samples", Generator::Sphere(sphere(Vec::new()))),
        ("hemisphere, 65,536 points × 64 samples", Generator::Sphere(sphere(vec![Vec3::Z; points.len()]))),
    ];
    println!("{:<42} {:>9}", format!("{} rays, one core, {}", RAYS, format.name()), "Mrays/s");
    for (what, generator) in generators {
        generator.check().expect("a valid generator");
        assert_eq!(generator.count(), RAYS, "{what}");
        check(&generator, format);
        make(&generator, format);
        let mut times: Vec<f64> = (0..RUNS).map(|_| make(&generator, format)).collect();
        times.sort_by(f64::total_cmp);
        println!("{what:<42} {:>9.1}", RAYS as f64 / times[RUNS / 2] / 1e6);
    }
}
