//! What each rayctl command does: read local files, call the library, and shape the answer for [`show`].

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bytes::Bytes;
use glam::Vec3;
use indicatif::{ProgressBar, ProgressStyle};
use rayd_client::convert::bounds;
use rayd_client::{
    BenchOptions, Client, ClientOptions, ClientTls, Error, Result, Scene, ServingStatus, TemporaryBuffers,
    check_health, load_mesh,
};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::RayFormat;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{OutputLayout, Query, QueryKind};
use rayd_engine::raygen::{Camera, Generator, Lidar, Orthographic, SphereSampling, fill_random_rays, uniform};
use serde_json::json;
use tokio::signal::unix::{Signal, SignalKind, signal};

use crate::args::{
    AroundPointsArgs, BenchArgs, BuildArgs, Cli, Command, LidarArgs, LidarScanArgs, RaysArgs, RenderArgs, SceneArgs,
    TraceArgs, View,
};
use crate::bounced::{Bounced, PrimaryHits};
use crate::parts::{self, OutFile, Outputs, PackedFile, Written};
use crate::show::{self, Output, ms};

/// Connects to the server and runs the command.
pub async fn run(cli: &Cli) -> Result<Output> {
    let max_message_bytes = usize::try_from(cli.max_message_bytes).unwrap_or(usize::MAX);
    let identity = match (&cli.client_cert, &cli.client_key) {
        (Some(cert), Some(key)) => {
            Some((read_pem("--client-cert", cert, Pem::Certificate)?, read_pem("--client-key", key, Pem::PrivateKey)?))
        }
        _ => None,
    };
    let ca_cert = cli.ca_cert.as_ref().map(|ca| read_pem("--ca-cert", ca, Pem::Certificate)).transpose()?;
    let tls = (ca_cert.is_some() || identity.is_some()).then_some(ClientTls { ca_cert, identity });
    if let Command::Health { service, timeout } = &cli.command {
        return health(&cli.server, tls.as_ref(), service, *timeout).await;
    }
    let options = ClientOptions {
        token: cli.token.clone(),
        tls,
        max_message_bytes,
        batch_limit_bytes: max_message_bytes / 2,
        connections: cli.connections as usize,
        ..ClientOptions::default()
    };
    let client = Client::connect(&cli.server, options).await?;
    let outcome = match &cli.command {
        // These clean up what they made themselves when Ctrl-C ends them (accels, temporary buffers, files).
        Command::Scene(args) => scene(&client, args).await,
        Command::Trace(args) => trace(&client, args).await,
        Command::Rays(args) => rays(&client, args).await,
        command => until_interrupted(ctrl_c()?, run_on(&client, command, cli.json)).await,
    };
    // The temporary buffers of calls that a Ctrl-C dropped are deleted before rayctl ends (its runtime's end would
    // cancel their deletes), unless the server does not answer.
    let _ = tokio::time::timeout(crate::CLEAN_UP_TIME, client.finish_clean_ups()).await;
    outcome
}

/// Runs `command` (one that needs nothing cleaned up beyond the client's temporary buffers) through `client`; `json`:
/// whether the output is JSON.
async fn run_on(client: &Client, command: &Command, json: bool) -> Result<Output> {
    match command {
        Command::Devices => Ok(show::devices(&client.devices().await?)),
        Command::Build(args) => build(client, args).await,
        Command::Accels => Ok(show::accels(&client.accels().await?)),
        Command::Info { name } => Ok(show::accel(&client.accel(name).await?)),
        Command::Update { name, mesh } => {
            Ok(show::accel(&client.update_mesh(name, &mesh_off_thread(mesh).await?).await?))
        }
        Command::Copy { source, name, device, compact } => {
            Ok(show::accel(&client.copy_accel(source, name, device, *compact).await?))
        }
        Command::Compact { source, name, device } => {
            Ok(show::accel(&client.copy_accel(source, name, device, true).await?))
        }
        Command::Save { name, output } => {
            let blob = client.save_accel(name).await?;
            parts::write_whole(output, &[&blob]).await?;
            let file = output.display().to_string();
            Ok(Output {
                json: json!({ "accel": name, "file": file, "bytes": blob.len() }),
                text: format!("saved {name} to {file} ({} bytes)", blob.len()),
            })
        }
        Command::Load { file, name, device } => {
            let blob = tokio::fs::read(file).await.map_err(|e| Error::io(file, e))?;
            let stem = || file.file_stem().unwrap_or_default().to_string_lossy().into_owned();
            let loaded = client.load_accel(&name.clone().unwrap_or_else(stem), device, blob.into()).await?;
            Ok(show::loaded(&loaded))
        }
        Command::Rm { name } => {
            client.destroy_accel(name).await?;
            Ok(Output { json: json!({ "destroyed": name }), text: format!("destroyed {name}") })
        }
        Command::Buffers => Ok(show::buffers(&client.buffers().await?)),
        Command::RmBuffer { buffer } if buffer.is_empty() => {
            Err(Error::InvalidArgument("rm-buffer: give a buffer's id or name, not an empty one".into()))
        }
        Command::RmBuffer { buffer } => {
            let buffers = client.buffers().await?;
            // An id first: unnamed buffers have only theirs.
            let found = buffers.iter().find(|b| b.id == *buffer).or_else(|| buffers.iter().find(|b| b.name == *buffer));
            let found =
                found.ok_or_else(|| tonic::Status::not_found(format!("no buffer has id or name {buffer:?}")))?;
            client.delete_buffer(&found.id).await?;
            let (id, name) = (&found.id, &found.name);
            Ok(Output { json: json!({ "deleted": id, "name": name }), text: format!("deleted buffer {id} {name}") })
        }
        Command::Stats => Ok(show::stats(&client.tenants().await?)),
        Command::Render(args) => render(client, args).await,
        Command::Lidar(args) => lidar(client, args).await,
        Command::Bench(args) => bench(client, args, json).await,
        Command::Health { .. } => unreachable!("answered before connecting"),
        Command::Scene(_) | Command::Trace(_) | Command::Rays(_) => unreachable!("run with their own clean-ups"),
    }
}

/// What a PEM file given to a TLS option must hold.
#[derive(Debug, Clone, Copy)]
enum Pem {
    /// One certificate or more.
    Certificate,
    /// A private key (PKCS#8, PKCS#1 or SEC1).
    PrivateKey,
}

impl Pem {
    /// What it is called in messages.
    fn name(self) -> &'static str {
        match self {
            Pem::Certificate => "PEM certificate",
            Pem::PrivateKey => "PEM private key",
        }
    }

    /// Whether `line` begins a block of it.
    fn begins(self, line: &str) -> bool {
        match self {
            Pem::Certificate => line == "-----BEGIN CERTIFICATE-----",
            Pem::PrivateKey => line.starts_with("-----BEGIN ") && line.ends_with("PRIVATE KEY-----"),
        }
    }
}

/// The bytes of the PEM file `path` given for `option`, which must hold `kind`: INVALID_ARGUMENT naming the option
/// and the file otherwise, before anything connects.
fn read_pem(option: &str, path: &Path, kind: Pem) -> Result<Vec<u8>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    if !String::from_utf8_lossy(&bytes).lines().any(|line| kind.begins(line.trim_end())) {
        return Err(Error::InvalidArgument(format!("{option} {}: holds no {}", path.display(), kind.name())));
    }
    Ok(bytes)
}

/// `rayctl health`: the status, or an `UNAVAILABLE` error naming it when it is not SERVING.
async fn health(url: &str, tls: Option<&ClientTls>, service: &str, timeout: Duration) -> Result<Output> {
    let status = check_health(url, tls, service, timeout).await?;
    if status != ServingStatus::Serving {
        let what = if service.is_empty() { "the server" } else { service };
        return Err(Error::Status(tonic::Status::unavailable(format!("{what}: {}", status.as_str_name()))));
    }
    Ok(Output {
        json: json!({ "service": service, "status": status.as_str_name() }),
        text: status.as_str_name().into(),
    })
}

/// `rayctl build`: the accel is named after the file unless `--name` says otherwise.
async fn build(client: &Client, args: &BuildArgs) -> Result<Output> {
    let mesh = mesh_off_thread(&args.mesh).await?;
    let stem = || args.mesh.file_stem().unwrap_or_default().to_string_lossy().into_owned();
    let name = args.name.clone().unwrap_or_else(stem);
    Ok(show::accel(&client.build_mesh(&name, &mesh, &args.device, args.flags()).await?))
}

/// The mesh file `path`, read and parsed on a blocking thread, so that Ctrl-C is seen meanwhile (a pipe waits for
/// its writer; a large mesh takes seconds to parse).
async fn mesh_off_thread(path: &Path) -> Result<Mesh> {
    let path = path.to_owned();
    let loading = tokio::task::spawn_blocking(move || load_mesh(&path));
    loading.await.map_err(|e| Error::Status(tonic::Status::internal(format!("loading a mesh: {e}"))))?
}

/// `rayctl scene`: named after the file unless `--name` says otherwise.
async fn scene(client: &Client, args: &SceneArgs) -> Result<Output> {
    let scene = Scene::load(&args.file)?;
    let name = args.name.clone().unwrap_or_else(|| args.file.file_stem().unwrap_or_default().to_string_lossy().into());
    let interrupt = ctrl_c()?;
    let mut building = Vec::new();
    let built = client.build_scene_noting(&name, &args.device, &scene, BuildFlags::empty(), &mut building);
    match until_interrupted(interrupt, built).await {
        Ok(info) => Ok(show::accel(&info)),
        Err(failed) => {
            // A server that does not answer does not hold rayctl (as for temporary buffers).
            let left = match tokio::time::timeout(crate::CLEAN_UP_TIME, client.destroy_in_reverse(&building)).await {
                Ok(left) => left.map(|(left, why)| (left, why.to_string())),
                Err(_) => Some((building, format!("no answer within {} s", crate::CLEAN_UP_TIME.as_secs()))),
            };
            if let Some((left, why)) = left {
                crate::warn(&format!("accels may be left on the server ({why}): {}", left.join(", ")));
            }
            Err(failed)
        }
    }
}

/// `rayctl trace`: the rays are read from their file and the hits written to `--out` a part at a time
/// ([`parts`]), so that rayctl holds neither whole; the wall time counts everything from the start (lookups, the
/// reading and the writing), all of which Ctrl-C interrupts.
async fn trace(client: &Client, args: &TraceArgs) -> Result<Output> {
    let interrupt = ctrl_c()?;
    let start = Instant::now();
    let query = args.query.query(args.ray_format, args.hit_format);
    let options = ray_count_options(args);
    let node = client.for_scene(&args.accel);
    let mut temporary = TemporaryBuffers::new(&node);
    let traced = async {
        let rays = traced_rays(client, args).await?;
        let layout = rays.layout(&query)?;
        let outputs = match &args.out {
            Some(out) => {
                let outputs = Outputs::create(out, query.kind.has_counts(), rays.file()).await?;
                if let Some(layout) = &layout {
                    outputs.check_room(layout, &options)?;
                }
                Some(outputs)
            }
            None => None,
        };
        let parts = match rays {
            TracedRays::File(file) => {
                let chunks = file.chunks(client.part_rays(&query) * query.ray_format.size());
                client.trace_parts(&args.accel, &query, chunks).await?
            }
            TracedRays::Generated(generator) => client.trace_generated_parts(&args.accel, &query, &generator).await?,
            TracedRays::Bounced(bounced) => {
                let secondary = bounced.on_server(&node, &mut temporary).await?;
                client.trace_secondary_parts(&args.accel, &query, &secondary).await?
            }
        };
        parts::write(parts, outputs, layout.map(|l| l.rays)).await
    };
    let written = until_interrupted(interrupt, traced).await;
    crate::bounced::delete(temporary).await;
    let Written { rays, stats } = written.map_err(asked_by(options))?;
    let wall = start.elapsed();
    let wall_ms = wall.as_secs_f64() * 1e3;
    let json = json!({
        "rays": rays, "hits": stats.rays_hit, "server_ms": ms(stats.trace_ns), "wall_ms": wall_ms,
        "nodes_visited": stats.nodes_visited, "triangle_tests": stats.triangle_tests,
    });
    let text = format!(
        "{rays} rays, {} hit ({:.1}%), server {:.2} ms, wall {wall_ms:.2} ms ({:.2} M rays/s end to end)",
        stats.rays_hit,
        100.0 * stats.rays_hit as f64 / rays.max(1) as f64,
        ms(stats.trace_ns),
        rays as f64 / wall.as_secs_f64().max(f64::MIN_POSITIVE) / 1e6,
    );
    Ok(Output { json, text })
}

/// Ctrl-C, listened for from now on (instead of ending the process): a command that makes what an interruption must
/// clean up listens before it makes any of it, then runs its work [`until_interrupted`].
fn ctrl_c() -> Result<Signal> {
    signal(SignalKind::interrupt())
        .map_err(|e| Error::Status(tonic::Status::internal(format!("cannot listen for Ctrl-C: {e}"))))
}

/// Runs `work` until it ends or `ctrl_c` comes, which ends it as a failure would (CANCELLED): what it held is
/// dropped with it, so files written beside their places are removed (and the caller deletes what it noted, such as
/// temporary buffers).
async fn until_interrupted<T>(mut ctrl_c: Signal, work: impl Future<Output = Result<T>>) -> Result<T> {
    tokio::select! {
        done = work => return done,
        _ = ctrl_c.recv() => {}
    }
    // A second Ctrl-C ends rayctl at once, cleaning nothing more up (status 130, as a shell reports SIGINT).
    tokio::spawn(async move {
        ctrl_c.recv().await;
        std::process::exit(130)
    });
    Err(Error::Status(tonic::Status::cancelled("interrupted by Ctrl-C")))
}

/// The options of `rayctl trace` that set how many rays it traces and how many hit records a ray has, as given.
fn ray_count_options(args: &TraceArgs) -> String {
    let samples = args.samples;
    let source = if let Some(file) = &args.rays {
        format!("--rays {}", file.display())
    } else if let Some((width, height)) = args.pixels {
        format!("--pixels {width}x{height} --samples {samples}")
    } else if args.lidar {
        format!("--channels {} --steps {}", args.lidar_scan.channels, args.lidar_scan.steps)
    } else if let Some(file) = &args.around.points {
        format!("--points {} --samples {samples}", file.display())
    } else {
        format!("--point ×{} --samples {samples}", args.around.point.len())
    };
    match args.query.query {
        QueryKind::All => format!("{source} --max-hits {}", args.query.max_hits),
        _ => source,
    }
}

/// `error`, a refusal for memory told as the doing of `options` (the command-line options that asked for that
/// much).
fn asked_by(options: String) -> impl FnOnce(Error) -> Error {
    move |error| match error {
        Error::Memory { what, bytes } => Error::Memory { what: format!("{options}: {what}"), bytes },
        error => error,
    }
}

/// The accel's box, which must hold triangles.
async fn accel_bounds(client: &Client, accel: &str) -> Result<(glam::Vec3, glam::Vec3)> {
    let info = client.accel(accel).await?;
    bounds(&info).ok_or_else(|| Error::InvalidArgument(format!("accel {accel}: no triangles to frame")))
}

/// The camera of `view`, or one framing the accel's box.
async fn camera(client: &Client, accel: &str, view: Option<View>, width: u32, height: u32) -> Result<Camera> {
    Ok(match view {
        Some(view) => {
            Camera { eye: view.eye, target: view.target, up: view.up, fov_y_degrees: view.fov_y_degrees, width, height }
        }
        None => {
            let (lo, hi) = accel_bounds(client, accel).await?;
            Camera::framing(lo, hi, width, height)
        }
    })
}

/// The rays `rayctl trace` starts from: a file's, or a generator's that the server expands.
pub enum RaySource {
    /// Packed in `--ray-format`, in `--rays`.
    File(PackedFile),
    /// Made by the server.
    Generator(Generator),
}

/// What `rayctl trace` sends: the rays of a file, a generator, or secondary rays made on the server.
enum TracedRays {
    /// Packed rays, sent from their file a part at a time.
    File(PackedFile),
    /// A generator the server expands.
    Generated(Generator),
    /// Secondary rays, made on the server from primary rays and their hits.
    Bounced(Box<Bounced>),
}

impl TracedRays {
    /// The file read as the trace goes, if the rays are one.
    fn file(&self) -> Option<&PackedFile> {
        match self {
            TracedRays::File(file) => Some(file),
            _ => None,
        }
    }

    /// The hits and counts that tracing them with `query` makes, where known before tracing (not for rays from a
    /// pipe).
    fn layout(&self, query: &Query) -> Result<Option<OutputLayout>> {
        let rays = match self {
            TracedRays::File(file) => file.bytes().map(|bytes| bytes / query.ray_format.size() as u64),
            TracedRays::Generated(generator) => Some(generator.count()),
            TracedRays::Bounced(bounced) => bounced.rays(),
        };
        rays.map(|rays| rayd_client::output_layout_of_rays(query, rays)).transpose()
    }
}

/// What `rayctl trace` traces: its rays ([`ray_source`]), or, with `--reflect` or `--towards-light`, the secondary
/// rays they make at their hits.
async fn traced_rays(client: &Client, args: &TraceArgs) -> Result<TracedRays> {
    let source = ray_source(client, args).await?;
    let secondary = &args.secondary;
    let Some(bounce) = secondary.bounce() else {
        return Ok(match source {
            RaySource::File(file) => TracedRays::File(file),
            RaySource::Generator(generator) => TracedRays::Generated(generator),
        });
    };
    let hits = match (&secondary.primary_hits, &secondary.primary_hits_buffer) {
        (Some(file), _) => PrimaryHits::File(PackedFile::primary_hits(file).await?),
        (None, Some(name)) => PrimaryHits::Buffer(name.clone()),
        (None, None) => unreachable!("clap requires --primary-hits or --primary-hits-buffer with a bounce"),
    };
    let bounced = Bounced { primary: source, ray_format: args.ray_format, hits, bounce, offset: secondary.offset };
    bounced.check()?;
    Ok(TracedRays::Bounced(Box::new(bounced)))
}

/// The rays of `rayctl trace`'s one ray source: `--rays`, `--pixels`, `--lidar`, or `--point`/`--points`.
async fn ray_source(client: &Client, args: &TraceArgs) -> Result<RaySource> {
    if let Some(file) = &args.rays {
        return Ok(RaySource::File(PackedFile::rays(file, args.ray_format).await?));
    }
    let generator = if let Some((width, height)) = args.pixels {
        let sampling = args.pixel_sampling();
        match args.orthographic {
            Some(view) => {
                let (eye, target, up, view_height) = (view.eye, view.target, view.up, view.view_height);
                Generator::Orthographic(Orthographic { eye, target, up, view_height, width, height }, sampling)
            }
            None => Generator::Pinhole(camera(client, &args.accel, args.camera, width, height).await?, sampling),
        }
    } else if args.lidar {
        Generator::Lidar(lidar_scan(client, &args.accel, &args.lidar_scan).await?)
    } else {
        Generator::Sphere(around_points(&args.around, args.samples)?)
    };
    Ok(RaySource::Generator(generator))
}

/// The lidar of `scan`, its sensor by default above the middle of the accel's box's front face (+z).
async fn lidar_scan(client: &Client, accel: &str, scan: &LidarScanArgs) -> Result<Lidar> {
    let origin = match scan.origin {
        Some(origin) => origin,
        None => {
            let (lo, hi) = accel_bounds(client, accel).await?;
            Vec3::new((lo.x + hi.x) * 0.5, (lo.y + hi.y) * 0.5, hi.z + (hi - lo).z)
        }
    };
    Ok(scan.lidar(origin))
}

/// `samples` rays around each point of `--point` or `--points`, on the hemisphere of its normal where normals are
/// given.
fn around_points(around: &AroundPointsArgs, samples: u32) -> Result<SphereSampling> {
    let (points, normals) = match &around.points {
        Some(file) => {
            let normals = around.normals.as_ref().map(|file| packed_points(file)).transpose()?;
            let points = packed_points(file)?;
            if points.is_empty() {
                let what = format!("--points {}: no points (1 to 65,536 of them)", file.display());
                return Err(Error::InvalidArgument(what));
            }
            (points, normals.unwrap_or_default())
        }
        None => (around.point.clone(), around.normal.clone()),
    };
    Ok(SphereSampling {
        points,
        normals,
        samples,
        min_distance: around.min_distance,
        max_distance: around.max_distance,
        seed: around.seed,
    })
}

/// The vectors packed in `file`: x, y, z little-endian f32 each, 12 bytes a vector.
fn packed_points(file: &Path) -> Result<Vec<Vec3>> {
    let bytes = read_file(file)?;
    if !bytes.len().is_multiple_of(12) {
        let what = format!("{}: {} bytes is not a whole number of 12-byte x, y, z points", file.display(), bytes.len());
        return Err(Error::InvalidArgument(what));
    }
    let f32_at = |at: &[u8]| f32::from_le_bytes(at.try_into().expect("4 bytes"));
    Ok(bytes.chunks_exact(12).map(|p| Vec3::new(f32_at(&p[..4]), f32_at(&p[4..8]), f32_at(&p[8..]))).collect())
}

/// The bytes of a file the command reads.
fn read_file(file: &Path) -> Result<Bytes> {
    std::fs::read(file).map(Bytes::from).map_err(|e| Error::io(file, e))
}

/// Rays `rayctl rays` makes and writes at a time.
const RAYS_A_PART: usize = 1 << 16;

/// `rayctl rays`: camera or random rays for an accel, packed into a file for `trace`, made and written a part at a
/// time (a plain or new file is written beside itself and renamed into place, as `trace --out` is).
async fn rays(client: &Client, args: &RaysArgs) -> Result<Output> {
    let format = args.ray_format;
    let time = match args.time {
        Some(span) => {
            let offset = format.time_offset().ok_or_else(|| {
                Error::InvalidArgument(format!("--time: ray format {} carries no time", format.name()))
            })?;
            Some((span, offset))
        }
        None => None,
    };
    let (count, options, maker) = match args.random {
        Some(count) => {
            let (lo, hi) = accel_bounds(client, &args.accel).await?;
            (count, format!("--random {count}"), RayMaker::Random { lo, hi, seed: args.seed })
        }
        None => {
            if args.camera.is_some() {
                // Not needed for its box, but the rays are for it: a name that is wrong is better said now.
                client.accel(&args.accel).await?;
            }
            let camera = camera(client, &args.accel, args.camera, args.width, args.height).await?;
            let count = args.width as usize * args.height as usize;
            (count, format!("--width {} --height {}", args.width, args.height), RayMaker::Camera(camera))
        }
    };
    let interrupt = ctrl_c()?;
    let size = format.size();
    let what = || format!("{count} {} rays", format.name());
    let written = async {
        let mut out = OutFile::create(&args.output, None).await?;
        out.check_room((count as u64).saturating_mul(size as u64), &options, what)?;
        let mut part = vec![0u8; RAYS_A_PART.min(count) * size];
        for first in (0..count).step_by(RAYS_A_PART) {
            let rays = &mut part[..RAYS_A_PART.min(count - first) * size];
            maker.fill(format, first as u64, rays);
            if let Some(((start, end), offset)) = time {
                for (i, ray) in (first as u64..).zip(rays.chunks_exact_mut(size)) {
                    let time = start + (end - start) * uniform(args.seed ^ 0x7153, i);
                    ray[offset..offset + 4].copy_from_slice(&time.to_le_bytes());
                }
            }
            out.write(rays).await?;
            // Writes to the page cache finish before the next part is made, so the loop would never wait: it
            // yields, for Ctrl-C to be seen.
            tokio::task::yield_now().await;
        }
        out.finish().await
    };
    until_interrupted(interrupt, written).await?;
    let file = args.output.display().to_string();
    Ok(Output {
        json: json!({ "file": file, "rays": count, "ray_format": format.name() }),
        text: format!("wrote {count} {} rays to {file}", format.name()),
    })
}

/// What `rayctl rays` makes its rays with.
enum RayMaker {
    /// Random rays in the accel's box.
    Random { lo: Vec3, hi: Vec3, seed: u64 },
    /// A camera's, row by row.
    Camera(Camera),
}

impl RayMaker {
    /// Fills `out` with its rays from ray `first` on.
    fn fill(&self, format: RayFormat, first: u64, out: &mut [u8]) {
        match self {
            RayMaker::Random { lo, hi, seed } => fill_random_rays(*lo, *hi, *seed, format, first, out),
            RayMaker::Camera(camera) => camera.fill_rays(format, first, out),
        }
    }
}

/// `rayctl render`: without `--camera`, a camera framing the accel's box.
async fn render(client: &Client, args: &RenderArgs) -> Result<Output> {
    let camera = camera(client, &args.accel, args.camera, args.width, args.height).await?;
    let start = Instant::now();
    let image = client.render(&args.accel, &camera, args.shading.into()).await?;
    let wall_ms = start.elapsed().as_secs_f64() * 1e3;
    parts::write_whole(&args.output, &[&image.png()?]).await?;
    let file = args.output.display().to_string();
    Ok(Output {
        json: json!({ "file": file, "width": image.width, "height": image.height, "wall_ms": wall_ms }),
        text: format!("wrote {file} ({}×{}, traced in {wall_ms:.1} ms)", image.width, image.height),
    })
}

/// `rayctl lidar`: one revolution, the returns written as PLY.
async fn lidar(client: &Client, args: &LidarArgs) -> Result<Output> {
    let lidar = lidar_scan(client, &args.accel, &args.scan).await?;
    let start = Instant::now();
    let scan = client.lidar(&args.accel, &lidar).await?;
    let wall_ms = start.elapsed().as_secs_f64() * 1e3;
    parts::write_whole(&args.output, &[scan.ply_header().as_bytes(), &scan.points]).await?;
    let file = args.output.display().to_string();
    Ok(Output {
        json: json!({ "file": file, "rays": scan.rays, "points": scan.len(), "wall_ms": wall_ms }),
        text: format!("wrote {file} ({} returns of {} rays, in {wall_ms:.1} ms)", scan.len(), scan.rays),
    })
}

/// `rayctl bench`, with a progress bar over the run's duration unless `--json`.
async fn bench(client: &Client, args: &BenchArgs, json: bool) -> Result<Output> {
    let options = BenchOptions {
        batch: args.batch as usize,
        concurrency: args.concurrency as usize,
        duration: args.duration,
        query: args.query.query(args.ray_format, args.hit_format),
    };
    let bar = progress_bar(args.duration, json);
    let (rays, start, ticker) = (Arc::new(AtomicU64::new(0)), Instant::now(), bar.clone());
    let on_batch = Arc::new(move |n: usize| {
        let total = rays.fetch_add(n as u64, Ordering::Relaxed) + n as u64;
        let elapsed = start.elapsed();
        ticker.set_position(elapsed.as_millis() as u64);
        ticker.set_message(format!("{total} rays, {:.2} M rays/s", total as f64 / elapsed.as_secs_f64() / 1e6));
    });
    let report = client.bench(&args.accel, &options, on_batch).await;
    bar.finish_and_clear();
    let report = report.map_err(asked_by(format!("--batch {} --concurrency {}", args.batch, args.concurrency)))?;
    let latency_ms = |q| report.latency(q).as_secs_f64() * 1e3;
    let (p50, p90, p99) = (latency_ms(0.5), latency_ms(0.9), latency_ms(0.99));
    let lowered = if report.concurrency < options.concurrency {
        format!(" (lowered from {}: the server's max_concurrent_operations)", options.concurrency)
    } else {
        String::new()
    };
    let json = json!({
        "rays": report.rays, "hits": report.rays_hit, "batches": report.batches(), "concurrency": report.concurrency,
        "seconds": report.elapsed.as_secs_f64(), "rays_per_s": report.rays_per_second(),
        "server_ms": report.server_time.as_secs_f64() * 1e3, "p50_ms": p50, "p90_ms": p90, "p99_ms": p99,
    });
    let text = format!(
        "{} batches of {} rays, {} in flight{lowered}, {:.2} s: {:.3} M rays/s ({:.1}% hit; server trace time {:.2} s \
         summed over calls)\n\
         latency p50 {p50:.2} ms  p90 {p90:.2} ms  p99 {p99:.2} ms",
        report.batches(),
        options.batch,
        report.concurrency,
        report.elapsed.as_secs_f64(),
        report.rays_per_second() / 1e6,
        100.0 * report.rays_hit as f64 / report.rays.max(1) as f64,
        report.server_time.as_secs_f64(),
    );
    Ok(Output { json, text })
}

/// A bar that fills over `duration` (hidden for JSON output).
fn progress_bar(duration: Duration, hidden: bool) -> ProgressBar {
    if hidden {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(duration.as_millis() as u64);
    let style = ProgressStyle::with_template("{spinner} {elapsed:>3} [{wide_bar}] {msg}").expect("a valid template");
    bar.set_style(style.progress_chars("=> "));
    bar.enable_steady_tick(Duration::from_millis(100));
    bar
}
