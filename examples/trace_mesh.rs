//! Traces rays through OBJ meshes with rayd's engine and prints what it measured as one line of JSON.
//!
//! ```text
//! cargo run --release --example trace_mesh -- --mesh bunny.obj --png bunny.png
//! cargo run --release --example trace_mesh -- --mesh a.obj --mesh b.obj --tiled 1000000 --rays random
//! cargo run --release --example trace_mesh -- --mesh bunny.obj --slivers 256
//! ```
//!
//! The meshes are concatenated into one geometry (or, with `--tiled`, laid out by [`Mesh::tiled`]; with
//! `--slivers`, a floor and long thin triangles are added by [`Mesh::with_floor_and_slivers`]); rays are
//! camera rays framing the scene or random rays in its box, packed `origin_tmin_direction_tmax`; hits are
//! `t_triid_u_v` unless `--hit-format` names another (`t`, or `bitmask`: one bit a ray, what an occlusion query
//! such as Embree's `rtcOccluded` answers). The JSON has `build_ms` (median of `--builds` builds), `trace_ms`
//! (median of `--repeat` traces), `mrays_per_s`, `rays`, `hits`, `triangles`, `threads` (rayon's; set
//! `RAYON_NUM_THREADS` to change it), and the trace's `nodes_per_ray` and `triangles_per_ray` (boxes tested and
//! triangles tested a ray: what the speed pays for). `--export DIR` writes the raw little-endian buffers
//! (`vertices.f32`, `indices.u32`, `rays.bin`, `hits.bin`) so that another tracer can run exactly the same rays;
//! `--png FILE` writes the camera image, shaded by the cosine between ray and normal.

use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::{Parser, ValueEnum};
use rayd_engine::accel::{BuildFlags, BuildOptions};
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::geometry::BuildInput;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind, TraceOutput, TraceStats};
use rayd_engine::raygen::{Camera, random_rays};
use rayd_engine::{Context, Device};

/// The ray layout every trace uses.
const RAY_FORMAT: RayFormat = RayFormat::OriginTminDirectionTmax;

/// Command-line options.
#[derive(Debug, Parser)]
#[command(about = "Trace rays through OBJ meshes with rayd's engine and print timings as JSON")]
struct Args {
    /// An OBJ file; repeat the flag for several meshes.
    #[arg(long = "mesh", value_name = "PATH", required = true)]
    meshes: Vec<PathBuf>,
    /// Tile the meshes (each scaled to a unit cube) on a grid until the scene has at least this many triangles.
    #[arg(long, value_name = "MIN_TRIANGLES")]
    tiled: Option<usize>,
    /// Add a floor and this many slivers across the scene: triangles of very uneven sizes (seed 7).
    #[arg(long, value_name = "COUNT")]
    slivers: Option<usize>,
    /// Build preference; the engine's default (balanced) when left out.
    #[arg(long, value_enum)]
    prefer: Option<Prefer>,
    /// Which rays to trace.
    #[arg(long, value_enum, default_value_t = Rays::Camera)]
    rays: Rays,
    /// Camera image width.
    #[arg(long, default_value_t = 1024)]
    width: u32,
    /// Camera image height.
    #[arg(long, default_value_t = 1024)]
    height: u32,
    /// Number of random rays.
    #[arg(long, default_value_t = 1 << 20)]
    count: usize,
    /// Query kind.
    #[arg(long, value_enum, default_value_t = Kind::Closest)]
    query: Kind,
    /// Hit record layout.
    #[arg(long, value_enum, default_value_t = Format::TTriidUV)]
    hit_format: Format,
    /// Traces to time; the median is reported.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    repeat: u32,
    /// Builds to time; the median is reported (the last build is traced).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    builds: u32,
    /// Write the scene, rays and hits as raw buffers into this directory.
    #[arg(long, value_name = "DIR")]
    export: Option<PathBuf>,
    /// Write a grayscale image of the hits (camera rays only).
    #[arg(long, value_name = "FILE")]
    png: Option<PathBuf>,
}

/// `--prefer` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
enum Prefer {
    /// `BuildFlags::PREFER_FAST_TRACE`.
    FastTrace,
    /// `BuildFlags::PREFER_FAST_BUILD`.
    FastBuild,
}

/// `--rays` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Rays {
    /// One ray per pixel of `Camera::framing` the scene's box.
    Camera,
    /// `raygen::random_rays` in the scene's box, seed 7.
    Random,
}

/// `--query` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
enum Kind {
    /// The closest hit.
    Closest,
    /// Any hit.
    Any,
}

/// `--hit-format` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Format {
    /// `t_triid_u_v`: distance, triangle id and barycentrics, 16 bytes a ray.
    #[value(name = "t-triid-u-v")]
    TTriidUV,
    /// `t`: the distance alone, 4 bytes a ray.
    T,
    /// `bitmask`: one bit a ray, 1 = hit.
    Bitmask,
}

impl Format {
    /// The engine's hit format.
    fn hit_format(self) -> HitFormat {
        match self {
            Format::TTriidUV => HitFormat::TTriidUV,
            Format::T => HitFormat::T,
            Format::Bitmask => HitFormat::Bitmask,
        }
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = Args::parse();
    if args.png.is_some() && args.rays != Rays::Camera {
        return Err("--png needs --rays camera".into());
    }
    if args.png.is_some() && args.hit_format != Format::TTriidUV {
        return Err("--png needs --hit-format t-triid-u-v".into());
    }
    let meshes = args.meshes.iter().map(Mesh::load_obj).collect::<Result<Vec<_>, _>>()?;
    let scene = match args.tiled {
        Some(min_triangles) => Mesh::tiled(&meshes, min_triangles),
        None => concatenate(&meshes),
    };
    let scene = match args.slivers {
        Some(slivers) => scene.with_floor_and_slivers(slivers, 7),
        None => scene,
    };
    let packed = scene.pack();

    let flags = match args.prefer {
        Some(Prefer::FastTrace) => BuildFlags::PREFER_FAST_TRACE,
        Some(Prefer::FastBuild) => BuildFlags::PREFER_FAST_BUILD,
        None => BuildFlags::empty(),
    };
    let context = Context::new(Device::cpu());
    let mut build_times_ms = Vec::new();
    let mut accel = None;
    for _ in 0..args.builds {
        drop(accel.take());
        let start = Instant::now();
        accel = Some(context.build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::new(flags))?);
        build_times_ms.push(start.elapsed().as_secs_f64() * 1e3);
    }
    let accel = accel.expect("at least one build");
    let build_ms = median(build_times_ms);

    let (lo, hi) = scene.bounds();
    let camera = Camera::framing(lo, hi, args.width, args.height);
    let rays = match args.rays {
        Rays::Camera => camera.rays(RAY_FORMAT),
        Rays::Random => random_rays(lo, hi, args.count, 7, RAY_FORMAT),
    };
    let kind = match args.query {
        Kind::Closest => QueryKind::Closest,
        Kind::Any => QueryKind::Any,
    };
    let hit_format = args.hit_format.hit_format();
    let query = Query { kind, ..Query::closest(RAY_FORMAT, hit_format) };
    let ray_count = rays.len() / RAY_FORMAT.size();
    let mut hits = vec![0u8; hit_format.buffer_len(ray_count)];
    let mut times_ms = Vec::new();
    let mut stats = TraceStats::default();
    for _ in 0..args.repeat {
        let start = Instant::now();
        stats = context.trace(&accel, &query, &rays, TraceOutput { hits: &mut hits, counts: &mut [] })?;
        times_ms.push(start.elapsed().as_secs_f64() * 1e3);
    }
    let trace_ms = median(times_ms);

    if let Some(dir) = &args.export {
        std::fs::create_dir_all(dir)?;
        std::fs::write(dir.join("vertices.f32"), &packed.vertices)?;
        std::fs::write(dir.join("indices.u32"), &packed.indices)?;
        std::fs::write(dir.join("rays.bin"), &rays)?;
        std::fs::write(dir.join("hits.bin"), &hits)?;
    }
    if let Some(path) = &args.png {
        write_png(path, &scene, &camera, &rays, &hits)?;
    }
    println!(
        "{{\"build_ms\": {build_ms:.3}, \"trace_ms\": {trace_ms:.3}, \"mrays_per_s\": {:.3}, \"rays\": {ray_count}, \
         \"hits\": {}, \"triangles\": {}, \"threads\": {}, \"nodes_per_ray\": {:.2}, \"triangles_per_ray\": {:.2}}}",
        ray_count as f64 / trace_ms / 1e3,
        stats.rays_hit,
        scene.triangles.len(),
        rayon::current_num_threads(),
        stats.nodes_visited as f64 / ray_count as f64,
        stats.triangle_tests as f64 / ray_count as f64,
    );
    Ok(())
}

/// The median of `values` (the upper one of an even count).
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// All meshes as one, in order, so triangle ids run on from one mesh to the next.
fn concatenate(meshes: &[Mesh]) -> Mesh {
    let mut scene = Mesh::default();
    for mesh in meshes {
        let base = scene.positions.len() as u32;
        scene.positions.extend(&mesh.positions);
        scene.triangles.extend(mesh.triangles.iter().map(|t| t.map(|i| i + base)));
    }
    scene
}

/// Writes the camera image: a hit pixel is shaded by |cos| of the angle between its ray and the triangle's
/// normal, a missed one is black.
fn write_png(
    path: &Path,
    scene: &Mesh,
    camera: &Camera,
    rays: &[u8],
    hits: &[u8],
) -> Result<(), Box<dyn std::error::Error>> {
    let hit_size = HitFormat::TTriidUV.size().expect("a byte format");
    let pixels: Vec<u8> = rays
        .chunks_exact(RAY_FORMAT.size())
        .zip(hits.chunks_exact(hit_size))
        .map(|(ray, hit)| {
            let t = f32::from_le_bytes(hit[0..4].try_into().expect("4 bytes"));
            if t < 0.0 {
                return 0;
            }
            let prim_id = u32::from_le_bytes(hit[4..8].try_into().expect("4 bytes"));
            let [a, b, c] = scene.corners(prim_id as usize);
            let normal = (b - a).cross(c - a).normalize_or_zero();
            let direction = glam::Vec3::from(RAY_FORMAT.decode(ray).direction);
            (40.0 + 215.0 * normal.dot(direction).abs()) as u8
        })
        .collect();
    let mut encoder =
        png::Encoder::new(std::io::BufWriter::new(std::fs::File::create(path)?), camera.width, camera.height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.write_header()?.write_image_data(&pixels)?;
    Ok(())
}
