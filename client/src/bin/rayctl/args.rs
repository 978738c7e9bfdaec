//! rayctl's command line: global options, one subcommand a job, and parsers for the engine's format names,
//! camera views, vectors and durations.

use std::path::PathBuf;
use std::time::Duration;

use clap::builder::{PossibleValuesParser, TypedValueParser};
use clap::{ArgGroup, Args, Parser, Subcommand, ValueEnum};
use glam::Vec3;
use rayd_client::{DEFAULT_SERVER, Shading};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFlags, RayFormat};
use rayd_engine::query::{Query, QueryKind};
use rayd_engine::raygen::{Bounce, Lidar, PixelSampling};

/// Command-line client of the rayd ray-tracing service.
#[derive(Debug, Parser)]
#[command(name = "rayctl", version)]
pub struct Cli {
    /// The server's URL.
    #[arg(long, global = true, env = "RAYD_SERVER", default_value = DEFAULT_SERVER)]
    pub server: String,
    /// Sent as `authorization: Bearer <T>` with every call.
    #[arg(long, value_name = "T", global = true, env = "RAYD_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// For an https:// server: the CA certificate (PEM) that signed its certificate. The TLS options are refused
    /// for a server URL that is not https://.
    #[arg(long, value_name = "FILE", global = true, env = "RAYD_CA_CERT")]
    pub ca_cert: Option<PathBuf>,
    /// For a server that requires client certificates (mutual TLS): this client's certificate (PEM).
    #[arg(long, value_name = "FILE", global = true, env = "RAYD_CLIENT_CERT", requires = "client_key")]
    pub client_cert: Option<PathBuf>,
    /// The private key (PEM) of --client-cert.
    #[arg(long, value_name = "FILE", global = true, env = "RAYD_CLIENT_KEY", requires = "client_cert")]
    pub client_key: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long, global = true)]
    pub json: bool,
    /// The server's largest message; traces whose rays or hits pass half of it are streamed.
    #[arg(long, value_name = "BYTES", global = true, env = "RAYD_MAX_MESSAGE_BYTES", default_value_t = 64 << 20,
          value_parser = clap::value_parser!(u64).range(1 << 16..), hide_short_help = true)]
    pub max_message_bytes: u64,
    /// HTTP/2 connections to spread the calls over: more copy the replies of calls in flight at once (`bench
    /// --concurrency`) on more cores.
    #[arg(long, value_name = "N", global = true, env = "RAYD_CONNECTIONS", default_value_t = 1,
          value_parser = clap::value_parser!(u32).range(1..=64), hide_short_help = true)]
    pub connections: u32,
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// rayctl's commands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// List the server's devices.
    Devices,
    /// Build an accel from a mesh file (.obj, .ply, .gltf, .glb).
    Build(BuildArgs),
    /// Build a scene file (JSON: meshes and instances of them) as an instance accel over one accel per mesh.
    Scene(SceneArgs),
    /// List the accels.
    Accels,
    /// Show one accel.
    Info {
        /// The accel's name.
        name: String,
    },
    /// Update (refit) an accel built with --allow-update from a mesh file of the same topology.
    Update {
        /// The accel's name.
        name: String,
        /// The mesh file with the new vertex positions.
        #[arg(long, value_name = "FILE")]
        mesh: PathBuf,
    },
    /// Copy an accel, or make a compacted copy of one (built with --allow-compaction).
    Copy {
        /// The accel to copy.
        source: String,
        /// The copy's name.
        name: String,
        /// The copy's device (default: the source's).
        #[arg(long, value_name = "ID", default_value = "")]
        device: String,
        /// Make a compacted copy.
        #[arg(long)]
        compact: bool,
    },
    /// Make a compacted copy of an accel built with --allow-compaction (the same as `copy --compact`).
    Compact {
        /// The accel to compact.
        source: String,
        /// The compacted copy's name.
        name: String,
        /// The copy's device (default: the source's).
        #[arg(long, value_name = "ID", default_value = "")]
        device: String,
    },
    /// Save an accel and everything below it to a file (a versioned, checksummed blob).
    Save {
        /// The accel's name.
        name: String,
        /// The file to write.
        #[arg(short = 'o', long = "output", value_name = "FILE")]
        output: PathBuf,
    },
    /// Load a file written by `save`: the root gets `--name`, the accels below it NAME.1, NAME.2, ….
    Load {
        /// The file to read.
        file: PathBuf,
        /// The root accel's name (default: the file's name without its extension).
        #[arg(long, value_name = "NAME")]
        name: Option<String>,
        /// The device (default: cpu:0).
        #[arg(long, value_name = "ID", default_value = "")]
        device: String,
    },
    /// Destroy an accel.
    Rm {
        /// The accel's name.
        name: String,
    },
    /// List the server-side buffers (uploads left behind, trace outputs).
    Buffers,
    /// Delete a server-side buffer (one left behind, or a trace's output once downloaded).
    RmBuffer {
        /// The buffer's id, as `rayctl buffers` lists it, or its name.
        buffer: String,
    },
    /// Show every tenant's usage against its quotas (an admin key where tenants are configured).
    Stats,
    /// Write a file of packed rays: a camera's (framing the accel by default) or random rays in its box.
    Rays(RaysArgs),
    /// Trace a file of packed rays, or rays the server makes itself (a pinhole or orthographic camera, a lidar,
    /// samples around points), or the secondary rays of either from their hits.
    Trace(Box<TraceArgs>),
    /// Render a PNG picture of an accel through the trace API.
    Render(RenderArgs),
    /// Scan an accel with a spinning lidar made by the server and write the returns as a PLY point cloud.
    Lidar(LidarArgs),
    /// Load the server with concurrent batches of random rays and report throughput and latency.
    Bench(BenchArgs),
    /// Ask the server's gRPC health service (`grpc.health.v1.Health/Check`, no token needed); exits with 0 only
    /// when the service is SERVING (a container health check).
    Health {
        /// The service to ask about; "" for the server as a whole.
        #[arg(long, value_name = "NAME", default_value = rayd_client::RAYD_SERVICE)]
        service: String,
        /// Seconds to connect and answer.
        #[arg(long, value_name = "S", default_value = "5", value_parser = parse_seconds)]
        timeout: Duration,
    },
}

/// `rayctl build`.
#[derive(Debug, Args)]
pub struct BuildArgs {
    /// The mesh file.
    #[arg(long, value_name = "FILE")]
    pub mesh: PathBuf,
    /// The accel's name (default: the file's name without extension).
    #[arg(long)]
    pub name: Option<String>,
    /// The device to build on (default: cpu:0).
    #[arg(long, value_name = "ID", default_value = "")]
    pub device: String,
    /// Trade build time against trace speed.
    #[arg(long, value_enum)]
    pub prefer: Option<Prefer>,
    /// Let the accel be updated (refit) later.
    #[arg(long)]
    pub allow_update: bool,
    /// Let the accel be compacted later (it reports its compacted size).
    #[arg(long)]
    pub allow_compaction: bool,
}

/// `rayctl scene`.
#[derive(Debug, Args)]
pub struct SceneArgs {
    /// The scene file (see the README's "Scenes" section).
    #[arg(long, value_name = "FILE")]
    pub file: PathBuf,
    /// The instance accel's name (default: the file's name without extension); meshes become `<name>.<mesh>`.
    #[arg(long)]
    pub name: Option<String>,
    /// The device to build on (default: cpu:0).
    #[arg(long, value_name = "ID", default_value = "")]
    pub device: String,
}

/// `--prefer`'s choices.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Prefer {
    /// Spend more build time for faster traces.
    FastTrace,
    /// Build as fast as possible.
    FastBuild,
}

impl BuildArgs {
    /// The build flags these options ask for.
    pub fn flags(&self) -> BuildFlags {
        let mut flags = match self.prefer {
            Some(Prefer::FastTrace) => BuildFlags::PREFER_FAST_TRACE,
            Some(Prefer::FastBuild) => BuildFlags::PREFER_FAST_BUILD,
            None => BuildFlags::empty(),
        };
        flags.set(BuildFlags::ALLOW_UPDATE, self.allow_update);
        flags.set(BuildFlags::ALLOW_COMPACTION, self.allow_compaction);
        flags
    }
}

/// The query options `trace` and `bench` share.
#[derive(Debug, Args)]
pub struct QueryArgs {
    /// What is reported per ray.
    #[arg(long, value_name = "KIND", default_value = "closest", value_parser = named(&QueryKind::ALL, QueryKind::name))]
    pub query: QueryKind,
    /// Hit records a ray for `--query all`.
    #[arg(long, value_name = "N", default_value_t = 8)]
    pub max_hits: u32,
}

impl QueryArgs {
    /// The full query, with these formats.
    pub fn query(&self, ray_format: RayFormat, hit_format: HitFormat) -> Query {
        Query { kind: self.query, ray_format, hit_format, flags: RayFlags::empty(), max_hits_per_ray: self.max_hits }
    }
}

/// The ray sources of `rayctl trace` other than `--pixels`, which the camera's options conflict with. (An option
/// that `requires` one source is let through when another source is given: clap lets a required argument be missing
/// when it conflicts with one present, as every source does with the others. Requiring a group has no such leniency.)
const SOURCES_BUT_PIXELS: [&str; 4] = ["rays", "lidar", "point", "points"];

/// `rayctl trace`: the rays are a file's (`--rays`) or made by the server from one generator (`--pixels`,
/// `--lidar`, `--point`/`--points`), exactly one of them; `--reflect` or `--towards-light` traces, instead, the
/// secondary rays those rays make at their hits.
#[derive(Debug, Args)]
#[command(group(ArgGroup::new("ray_source").required(true).args(["rays", "pixels", "lidar", "point", "points"])))]
#[command(group(ArgGroup::new("pixels_or_points").multiple(true).args(["pixels", "point", "points"])))]
pub struct TraceArgs {
    /// The accel's name.
    #[arg(long, value_name = "NAME")]
    pub accel: String,
    /// A file of packed rays, no header.
    #[arg(long, value_name = "FILE", conflicts_with = "lidar_scan")]
    pub rays: Option<PathBuf>,
    /// Instead of a ray file: a camera of W×H pixels whose rays the server makes itself (no ray crosses the
    /// network): a pinhole framing the accel's box or placed by `--camera`, or an orthographic one placed by
    /// `--orthographic`; rays pixel by pixel, row by row from the top left, `--samples` a pixel.
    #[arg(long, value_name = "WxH", value_parser = parse_pixels, conflicts_with = "lidar_scan")]
    pub pixels: Option<(u32, u32)>,
    /// The camera of `--pixels`, as for `render`.
    #[arg(long, value_name = "EYE,TARGET,UP,FOVY", value_parser = parse_view, allow_hyphen_values = true,
          conflicts_with_all = SOURCES_BUT_PIXELS)]
    pub camera: Option<View>,
    /// Makes the camera of `--pixels` orthographic: ten numbers, eye x,y,z, target x,y,z, up x,y,z, and the height
    /// in world units of the image rectangle centred on the eye (its width follows W/H); parallel rays along
    /// target − eye.
    #[arg(long, value_name = "EYE,TARGET,UP,HEIGHT", value_parser = parse_orthographic, allow_hyphen_values = true,
          conflicts_with_all = SOURCES_BUT_PIXELS, conflicts_with = "camera")]
    pub orthographic: Option<OrthographicView>,
    /// Rays a pixel of `--pixels` (through its centre, or `--jitter`ed), or a point of `--point`/`--points`.
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..),
          requires = "pixels_or_points")]
    pub samples: u32,
    /// Sends each ray of `--pixels` through a point uniform in its pixel, drawn from SEED, instead of its centre.
    #[arg(long, value_name = "SEED", conflicts_with_all = SOURCES_BUT_PIXELS)]
    pub jitter: Option<u64>,
    /// Instead of a ray file: one revolution of a spinning lidar whose rays the server makes, set by the lidar
    /// options below as for `rayctl lidar`; rays step by step, channel by channel.
    #[arg(long)]
    pub lidar: bool,
    /// How the rays are packed (or made by the server, without `--rays`; secondary rays are made in it too).
    #[arg(long, value_name = "FMT", value_parser = named(&RayFormat::ALL, RayFormat::name))]
    pub ray_format: RayFormat,
    /// How hits are packed.
    #[arg(long, value_name = "FMT", value_parser = named(&HitFormat::ALL, HitFormat::name))]
    pub hit_format: HitFormat,
    /// The query.
    #[command(flatten)]
    pub query: QueryArgs,
    /// Write the packed hits here (and the counts of `all`/`count` to FILE.counts).
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// The lidar of `--lidar`.
    #[command(flatten, next_help_heading = "Lidar options (with --lidar)")]
    pub lidar_scan: LidarScanArgs,
    /// Rays around points instead of a ray file.
    #[command(flatten, next_help_heading = "Sampling around points (instead of a ray file)")]
    pub around: AroundPointsArgs,
    /// Secondary rays of the rays instead of the rays.
    #[command(flatten, next_help_heading = "Secondary rays (from the rays' hits)")]
    pub secondary: SecondaryArgs,
}

/// `rayctl trace`'s rays from given points in random directions (ambient occlusion, visibility): `--samples` a
/// point, uniform on the sphere, or cosine-distributed around each point's normal when normals are given.
#[derive(Debug, Args)]
#[command(group(ArgGroup::new("sphere_points").args(["point", "points"])))]
pub struct AroundPointsArgs {
    /// Instead of a ray file: rays from this point, made by the server; repeat for more points (1 to 65,536).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true,
          conflicts_with = "lidar_scan")]
    pub point: Vec<Vec3>,
    /// Instead of a ray file or `--point`: rays from the points in FILE, packed x, y, z little-endian f32 (12 bytes a
    /// point, no header).
    #[arg(long, value_name = "FILE", conflicts_with = "lidar_scan")]
    pub points: Option<PathBuf>,
    /// The normal of each `--point`, in the same order (one a point): samples on the hemisphere around it.
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true,
          conflicts_with_all = ["rays", "pixels", "lidar", "points"])]
    pub normal: Vec<Vec3>,
    /// The normals of `--points`, one a point, packed as they are: samples on the hemisphere around each.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["rays", "pixels", "lidar", "point"])]
    pub normals: Option<PathBuf>,
    /// Seed of the rays' directions.
    #[arg(long, default_value_t = 7, requires = "sphere_points")]
    pub seed: u64,
    /// Where the rays start along their direction (their tmin), to leave the surface a point lies on.
    #[arg(long, value_name = "D", default_value_t = 0.0, requires = "sphere_points", value_parser = parse_distance)]
    pub min_distance: f32,
    /// How far the rays reach (their tmax; default unlimited).
    #[arg(long, value_name = "D", default_value_t = f32::INFINITY, requires = "sphere_points",
          value_parser = parse_reach)]
    pub max_distance: f32,
}

/// `rayctl trace`'s secondary rays, made by the server: ray i starts where ray i hit (moved `--offset` off the
/// surface) and reflects, or heads for a point light; a ray that missed makes one that hits nothing.
#[derive(Debug, Args)]
#[command(group(ArgGroup::new("bounce").args(["reflect", "towards_light"])))]
#[command(group(ArgGroup::new("primary_hits_from").args(["primary_hits", "primary_hits_buffer"])))]
pub struct SecondaryArgs {
    /// Trace, instead of the rays, their mirror reflections about the geometric normal at their hits.
    #[arg(long, requires = "primary_hits_from")]
    pub reflect: bool,
    /// Trace, instead of the rays, shadow rays from their hits towards a point light at X,Y,Z, each reaching the
    /// light (use `--query any`).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true,
          requires = "primary_hits_from")]
    pub towards_light: Option<Vec3>,
    /// The rays' hits: a file of `full` hit records, one a ray, as `rayctl trace --query closest` (or `any`)
    /// `--hit-format full --out FILE` writes them for the same rays. The file (and that of `--rays`) goes up as a
    /// temporary server buffer, deleted again afterwards: a part at a time, or read whole first from a pipe.
    #[arg(long, value_name = "FILE", requires = "bounce")]
    pub primary_hits: Option<PathBuf>,
    /// Instead of `--primary-hits`: the server-side buffer called NAME that holds them (a trace's hits buffer), so
    /// the hits do not cross the network.
    #[arg(long, value_name = "NAME", requires = "bounce")]
    pub primary_hits_buffer: Option<String>,
    /// World units (≥ 0) that the secondary rays' origins move off the surface, so that a ray does not hit the
    /// triangle it leaves.
    #[arg(long, value_name = "D", default_value_t = 0.0, requires = "bounce", value_parser = parse_distance)]
    pub offset: f32,
}

impl SecondaryArgs {
    /// What the secondary rays do at their primary ray's hit; `None` to trace the rays themselves.
    pub fn bounce(&self) -> Option<Bounce> {
        match (self.reflect, self.towards_light) {
            (true, _) => Some(Bounce::Reflect),
            (false, Some(light)) => Some(Bounce::TowardsLight(light)),
            (false, None) => None,
        }
    }
}

impl TraceArgs {
    /// Where the rays of `--pixels` pass through their pixel.
    pub fn pixel_sampling(&self) -> PixelSampling {
        PixelSampling { samples: self.samples, jitter_seed: self.jitter }
    }
}

/// `rayctl rays`.
#[derive(Debug, Args)]
pub struct RaysArgs {
    /// The accel whose box the rays are made for.
    #[arg(long, value_name = "NAME")]
    pub accel: String,
    /// Camera pixels a row.
    #[arg(long, value_name = "W", default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub width: u32,
    /// Camera rows.
    #[arg(long, value_name = "H", default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub height: u32,
    /// The camera, as for `render` (default: framing the accel's box).
    #[arg(long, value_name = "EYE,TARGET,UP,FOVY", value_parser = parse_view, allow_hyphen_values = true)]
    pub camera: Option<View>,
    /// Instead of a camera: this many rays with origins uniform in the accel's box and uniform directions.
    #[arg(long, value_name = "N", conflicts_with_all = ["camera", "width", "height"])]
    pub random: Option<usize>,
    /// Seed of the random rays.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// How the rays are packed.
    #[arg(long, value_name = "FMT", default_value = "origin_tmin_direction_tmax",
          value_parser = named(&RayFormat::ALL, RayFormat::name))]
    pub ray_format: RayFormat,
    /// Motion blur: every ray at time T, or each at a time uniform in [T0, T1] (seeded by `--seed`). Needs a ray
    /// format with time (`origin_tmin_direction_tmax_time` or `full`); without it rays are at time 0.
    #[arg(long, value_name = "T|T0,T1", value_parser = parse_times, allow_hyphen_values = true)]
    pub time: Option<(f32, f32)>,
    /// The file to write.
    #[arg(short = 'o', long = "output", value_name = "FILE")]
    pub output: PathBuf,
}

/// `T` or `T0,T1`: a span of time (`T0 ≤ T1`, finite).
fn parse_times(text: &str) -> Result<(f32, f32), String> {
    if text.contains(',') {
        return parse_span(text);
    }
    match text.trim().parse::<f32>() {
        Ok(t) if t.is_finite() => Ok((t, t)),
        _ => Err(format!("expected a finite number T or a span T0,T1 with T0 <= T1, got {text:?}")),
    }
}

/// `LO,HI`: two finite numbers, `LO ≤ HI`.
fn parse_span(text: &str) -> Result<(f32, f32), String> {
    let values: Vec<Option<f32>> = text.split(',').map(|v| v.trim().parse::<f32>().ok()).collect();
    match values[..] {
        [Some(low), Some(high)] if low.is_finite() && high.is_finite() && low <= high => Ok((low, high)),
        _ => Err(format!("expected two finite numbers LO,HI with LO <= HI, got {text:?}")),
    }
}

/// A distance in world units: a finite number ≥ 0. A number past f32's range is refused, not taken as `inf`.
fn parse_distance(text: &str) -> Result<f32, String> {
    match text.trim().parse::<f32>() {
        Ok(d) if d >= 0.0 && d.is_finite() => Ok(d),
        _ => Err(format!("expected a distance: a number >= 0 of at most {:e}; got {text:?}", f32::MAX)),
    }
}

/// How far rays reach: a distance ([`parse_distance`]), or `inf` for no limit.
fn parse_reach(text: &str) -> Result<f32, String> {
    match text.trim().trim_start_matches('+').to_ascii_lowercase().as_str() {
        "inf" | "infinity" => Ok(f32::INFINITY),
        _ => parse_distance(text).map_err(|e| format!("{e} (or inf)")),
    }
}

/// `rayctl render`.
#[derive(Debug, Args)]
pub struct RenderArgs {
    /// The accel's name.
    #[arg(long, value_name = "NAME")]
    pub accel: String,
    /// Pixels a row.
    #[arg(long, value_name = "W", default_value_t = 800, value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub width: u32,
    /// Rows.
    #[arg(long, value_name = "H", default_value_t = 600, value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub height: u32,
    /// Ten numbers: eye x,y,z, target x,y,z, up x,y,z, vertical field of view in degrees (default: framing the
    /// accel's box).
    #[arg(long, value_name = "EYE,TARGET,UP,FOVY", value_parser = parse_view, allow_hyphen_values = true)]
    pub camera: Option<View>,
    /// What the colours show.
    #[arg(long, value_enum, default_value = "normal")]
    pub shading: ShadingArg,
    /// The PNG file to write.
    #[arg(short = 'o', long = "output", value_name = "FILE.png")]
    pub output: PathBuf,
}

/// `rayctl lidar`.
#[derive(Debug, Args)]
pub struct LidarArgs {
    /// The accel's name.
    #[arg(long, value_name = "NAME")]
    pub accel: String,
    /// The lidar.
    #[command(flatten)]
    pub scan: LidarScanArgs,
    /// The PLY file to write.
    #[arg(short = 'o', long = "output", value_name = "FILE.ply")]
    pub output: PathBuf,
}

/// A spinning lidar, as `rayctl lidar` and `rayctl trace --lidar` take it: for each of `--steps` azimuths around
/// `--up`, one ray a channel.
#[derive(Debug, Args)]
#[group(id = "lidar_scan", multiple = true)]
pub struct LidarScanArgs {
    /// The sensor's position (default: above the middle of the accel's box's front face, +z).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub origin: Option<Vec3>,
    /// Azimuth 0 (default −z).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true, default_value = "0,0,-1")]
    pub forward: Vec3,
    /// The rotation axis (default +y).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true, default_value = "0,1,0")]
    pub up: Vec3,
    /// Channels, their elevations spread evenly over `--elevations`.
    #[arg(long, value_name = "N", default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub channels: u32,
    /// Lowest and highest channel elevation in degrees.
    #[arg(long, value_name = "LO,HI", default_value = "-25,15", value_parser = parse_span, allow_hyphen_values = true)]
    pub elevations: (f32, f32),
    /// Azimuth steps a revolution.
    #[arg(long, value_name = "N", default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..))]
    pub steps: u32,
    /// Nearest range (the rays' tmin).
    #[arg(long, value_name = "R", default_value_t = 0.0, value_parser = parse_distance)]
    pub min_range: f32,
    /// Farthest range (the rays' tmax; default unlimited).
    #[arg(long, value_name = "R", default_value_t = f32::INFINITY, value_parser = parse_reach)]
    pub max_range: f32,
    /// Motion scenes: the revolution fires at time T, or over [T0, T1] (step s of N at T0 + (T1 − T0)·s/N).
    #[arg(long, value_name = "T|T0,T1", default_value = "0", value_parser = parse_times, allow_hyphen_values = true)]
    pub time: (f32, f32),
}

impl LidarScanArgs {
    /// The lidar these options describe, its sensor at `origin` (`--origin`, or the default the caller works out).
    pub fn lidar(&self, origin: Vec3) -> Lidar {
        let (low, high) = self.elevations;
        let last = self.channels - 1;
        let spread = |c: u32| if last == 0 { low } else { low + (high - low) * c as f32 / last as f32 };
        Lidar {
            origin,
            forward: self.forward,
            up: self.up,
            elevations_degrees: (0..self.channels).map(spread).collect(),
            steps: self.steps,
            min_range: self.min_range,
            max_range: self.max_range,
            time: self.time,
        }
    }
}

/// Parses `WxH`: pixels a row and rows, each 1 to 16,384.
fn parse_pixels(text: &str) -> Result<(u32, u32), String> {
    let size = |n: &str| n.trim().parse::<u32>().ok().filter(|n| (1..=16384).contains(n));
    match text.split_once('x').map(|(w, h)| (size(w), size(h))) {
        Some((Some(width), Some(height))) => Ok((width, height)),
        _ => Err(format!("expected WxH with each from 1 to 16384, got {text:?}")),
    }
}

/// Parses `x,y,z`.
fn parse_vec3(text: &str) -> Result<Vec3, String> {
    let numbers: Vec<f32> = text
        .split(',')
        .map(|n| n.trim().parse::<f32>().map_err(|e| format!("{n:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match numbers[..] {
        [x, y, z] if numbers.iter().all(|n| n.is_finite()) => Ok(Vec3::new(x, y, z)),
        _ => Err(format!("expected 3 finite comma-separated numbers, got {text:?}")),
    }
}

/// `--shading`'s choices.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ShadingArg {
    /// Surface normal as colour.
    Normal,
    /// Distance as brightness.
    Depth,
}

impl From<ShadingArg> for Shading {
    fn from(shading: ShadingArg) -> Shading {
        match shading {
            ShadingArg::Normal => Shading::Normal,
            ShadingArg::Depth => Shading::Depth,
        }
    }
}

/// Where a pinhole camera stands and looks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// Position of the eye.
    pub eye: Vec3,
    /// Point looked at.
    pub target: Vec3,
    /// Up direction.
    pub up: Vec3,
    /// Vertical field of view, in degrees.
    pub fov_y_degrees: f32,
}

/// Where an orthographic camera stands and looks, and how much it sees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrthographicView {
    /// Centre of the image rectangle.
    pub eye: Vec3,
    /// A point looked towards: the rays run along `target − eye`.
    pub target: Vec3,
    /// Up direction.
    pub up: Vec3,
    /// Height of the image rectangle, in world units.
    pub view_height: f32,
}

/// `rayctl bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// The accel's name.
    #[arg(long, value_name = "NAME")]
    pub accel: String,
    /// Rays a call.
    #[arg(long, value_name = "N", default_value_t = 65536, value_parser = clap::value_parser!(u64).range(1..))]
    pub batch: u64,
    /// Calls in flight at once. More than the server's max_concurrent_operations (for this tenant) would be
    /// refused: they are lowered to it, and the report says so.
    #[arg(long, value_name = "C", default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub concurrency: u64,
    /// Seconds to run.
    #[arg(long, value_name = "S", default_value = "10", value_parser = parse_seconds)]
    pub duration: Duration,
    /// How the random rays are packed.
    #[arg(long, value_name = "FMT", default_value = "origin_tmin_direction_tmax",
          value_parser = named(&RayFormat::ALL, RayFormat::name))]
    pub ray_format: RayFormat,
    /// How hits are packed.
    #[arg(long, value_name = "FMT", default_value = "t_triid_u_v", value_parser = named(&HitFormat::ALL, HitFormat::name))]
    pub hit_format: HitFormat,
    /// The query.
    #[command(flatten)]
    pub query: QueryArgs,
}

/// A parser that accepts the `name` of any of `all` (and lists them in help and errors).
fn named<T: Copy + Send + Sync + 'static>(
    all: &'static [T],
    name: fn(T) -> &'static str,
) -> impl TypedValueParser<Value = T> {
    PossibleValuesParser::new(all.iter().map(|&value| name(value)))
        .map(move |chosen| *all.iter().find(|&&value| name(value) == chosen).expect("one of the possible values"))
}

/// Parses ten comma-separated numbers: eye x,y,z, target x,y,z, up x,y,z and one more.
fn ten_numbers(text: &str) -> Result<[f32; 10], String> {
    let numbers: Vec<f32> = text
        .split(',')
        .map(|n| n.trim().parse::<f32>().map_err(|e| format!("{n:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let count = numbers.len();
    numbers.try_into().map_err(|_| format!("expected 10 comma-separated numbers, got {count}"))
}

/// The eye, target and up of the first nine of `numbers`, which must make a view: finite, the eye apart from the
/// target, up not along the view.
fn placement(numbers: &[f32; 10]) -> Result<(Vec3, Vec3, Vec3), String> {
    let [ex, ey, ez, tx, ty, tz, ux, uy, uz, _] = *numbers;
    let (eye, target, up) = (Vec3::new(ex, ey, ez), Vec3::new(tx, ty, tz), Vec3::new(ux, uy, uz));
    if numbers[..9].iter().any(|n| !n.is_finite()) || !(eye - target).is_finite() {
        return Err("the eye, the target and up must be finite".into());
    }
    let across = (target - eye).cross(up).length_squared();
    if eye == target || !across.is_finite() || across == 0.0 {
        return Err("the eye must differ from the target and up must not be parallel to the view".into());
    }
    Ok((eye, target, up))
}

/// Parses `ex,ey,ez,tx,ty,tz,ux,uy,uz,fovy`.
fn parse_view(text: &str) -> Result<View, String> {
    let numbers = ten_numbers(text)?;
    let fov = numbers[9];
    if !(fov > 0.0 && fov < 180.0) {
        return Err(format!("the field of view must be between 0 and 180 degrees, not {fov}"));
    }
    let (eye, target, up) = placement(&numbers)?;
    Ok(View { eye, target, up, fov_y_degrees: fov })
}

/// Parses `ex,ey,ez,tx,ty,tz,ux,uy,uz,height`.
fn parse_orthographic(text: &str) -> Result<OrthographicView, String> {
    let numbers = ten_numbers(text)?;
    let height = numbers[9];
    if !(height.is_finite() && height > 0.0) {
        return Err(format!("the view height must be a positive number of world units, not {height}"));
    }
    let (eye, target, up) = placement(&numbers)?;
    Ok(OrthographicView { eye, target, up, view_height: height })
}

/// Parses a positive number of seconds.
fn parse_seconds(text: &str) -> Result<Duration, String> {
    let seconds: f64 = text.parse().map_err(|e| format!("{text:?}: {e}"))?;
    Duration::try_from_secs_f64(seconds)
        .ok()
        .filter(|d| !d.is_zero() && d.as_secs() <= MAX_SECONDS)
        .ok_or_else(|| format!("{text}: not a positive duration of at most {MAX_SECONDS} s"))
}

/// Longest duration an option takes (about 31 years): a deadline that far from now is still a time.
const MAX_SECONDS: u64 = 1_000_000_000;

#[cfg(test)]
mod tests {
    use super::*;

    /// Parses a command line that starts after `rayctl`.
    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("rayctl").chain(args.iter().copied()))
    }

    #[test]
    fn global_options_go_before_or_after_the_command() {
        let cli = parse(&["--server", "http://h:1", "--json", "devices"]).unwrap();
        assert_eq!((cli.server.as_str(), cli.json), ("http://h:1", true));
        assert_eq!(cli.max_message_bytes, 64 << 20);
        assert!(matches!(cli.command, Command::Devices));
        let cli = parse(&["info", "bunny", "--token", "t0k", "--server", "http://h:2"]).unwrap();
        assert_eq!((cli.server.as_str(), cli.token.as_deref()), ("http://h:2", Some("t0k")));
        assert!(matches!(cli.command, Command::Info { name } if name == "bunny"));
    }

    #[test]
    fn trace_takes_engine_format_names() {
        let cli = parse(&[
            "trace",
            "--accel",
            "a",
            "--rays",
            "r.bin",
            "--ray-format",
            "origin_tmin_direction_tmax",
            "--hit-format",
            "t_triid_u_v",
            "--query",
            "all",
            "--max-hits",
            "3",
            "--out",
            "h.bin",
        ])
        .unwrap();
        let Command::Trace(trace) = cli.command else { panic!("not trace") };
        let query = trace.query.query(trace.ray_format, trace.hit_format);
        assert_eq!(query.ray_format, RayFormat::OriginTminDirectionTmax);
        assert_eq!(query.hit_format, HitFormat::TTriidUV);
        assert_eq!((query.kind, query.max_hits_per_ray), (QueryKind::All, 3));
        assert_eq!(trace.out, Some(PathBuf::from("h.bin")));
        let error = parse(&["trace", "--accel", "a", "--rays", "r", "--ray-format", "prime", "--hit-format", "t"]);
        let error = error.unwrap_err();
        assert_eq!(error.kind(), clap::error::ErrorKind::InvalidValue);
        assert!(error.to_string().contains("origin_direction"), "the error lists the valid names");
    }

    #[test]
    fn durations_are_positive_and_at_most_a_billion_seconds() {
        assert_eq!(parse_seconds("1.5"), Ok(Duration::from_millis(1500)));
        assert_eq!(parse_seconds("1e9"), Ok(Duration::from_secs(MAX_SECONDS)));
        for refused in ["0", "-1", "1e19", "inf", "NaN"] {
            let error = parse_seconds(refused).unwrap_err();
            assert!(error.contains("not a positive duration of at most 1000000000 s"), "{refused}: {error}");
        }
        let error = parse(&["bench", "--accel", "a", "--duration", "1e19"]).unwrap_err();
        assert_eq!(error.kind(), clap::error::ErrorKind::ValueValidation, "{error}");
    }

    #[test]
    fn trace_takes_a_ray_file_or_pixels_made_by_the_server() {
        let formats = ["--ray-format", "origin_direction", "--hit-format", "t"];
        let with = |extra: &[&str]| parse(&[&["trace", "--accel", "a"], extra, &formats[..]].concat());
        let cli = with(&["--pixels", "64x48", "--camera", "0,0,5,0,0,0,0,1,0,40"]).unwrap();
        let Command::Trace(trace) = cli.command else { panic!("not trace") };
        assert_eq!((trace.pixels, trace.rays), (Some((64, 48)), None));
        assert!(with(&[]).is_err(), "--rays or --pixels is required");
        assert!(with(&["--rays", "r.bin", "--pixels", "4x4"]).is_err(), "not both");
        assert!(with(&["--pixels", "0x4"]).is_err() && with(&["--pixels", "4"]).is_err(), "sane sizes");
        assert!(with(&["--rays", "r.bin", "--camera", "0,0,5,0,0,0,0,1,0,40"]).is_err(), "a camera needs --pixels");
    }

    #[test]
    fn trace_makes_every_generator_from_its_own_options() {
        let formats = ["--ray-format", "origin_direction", "--hit-format", "t"];
        let trace = |extra: &[&str]| match parse(&[&["trace", "--accel", "a"], extra, &formats[..]].concat()) {
            Ok(Cli { command: Command::Trace(trace), .. }) => trace,
            other => panic!("{extra:?}: {other:?}"),
        };
        let camera = trace(&["--pixels", "8x6", "--orthographic", "0,0,5,0,0,0,0,1,0,2.5", "--samples", "4"]);
        let view = camera.orthographic.expect("an orthographic camera");
        assert_eq!((view.eye, view.target, view.view_height), (Vec3::new(0.0, 0.0, 5.0), Vec3::ZERO, 2.5));
        assert_eq!(camera.pixel_sampling(), PixelSampling { samples: 4, jitter_seed: None });
        let jittered = trace(&["--pixels", "8x6", "--jitter", "9"]);
        assert_eq!(jittered.pixel_sampling(), PixelSampling { samples: 1, jitter_seed: Some(9) });

        let scan = trace(&["--lidar", "--channels", "3", "--elevations", "-10,10", "--steps", "5", "--time", "0,1"]);
        assert!(scan.lidar && scan.rays.is_none());
        let lidar = scan.lidar_scan.lidar(Vec3::X);
        assert_eq!((lidar.origin, lidar.steps, lidar.time), (Vec3::X, 5, (0.0, 1.0)));
        assert_eq!(lidar.elevations_degrees, [-10.0, 0.0, 10.0]);
        assert_eq!(trace(&["--lidar"]).lidar_scan.lidar(Vec3::X).time, (0.0, 0.0), "at time 0 by default");

        let around = trace(&["--point", "0,0,0", "--point", "1,-2,3", "--normal", "0,1,0", "--normal", "0,0,-1"]);
        assert_eq!(around.around.point, [Vec3::ZERO, Vec3::new(1.0, -2.0, 3.0)]);
        assert_eq!(around.around.normal, [Vec3::Y, Vec3::NEG_Z]);
        assert_eq!((around.samples, around.around.seed, around.around.max_distance), (1, 7, f32::INFINITY));

        let shadows =
            trace(&["--rays", "r", "--towards-light", "1,-2,3", "--primary-hits-buffer", "h", "--offset", "1"]);
        assert_eq!(shadows.secondary.bounce(), Some(Bounce::TowardsLight(Vec3::new(1.0, -2.0, 3.0))));
        assert_eq!((shadows.secondary.primary_hits_buffer.as_deref(), shadows.secondary.offset), (Some("h"), 1.0));
        let reflections = trace(&["--pixels", "4x4", "--reflect", "--primary-hits", "h.bin"]);
        assert_eq!(reflections.secondary.bounce(), Some(Bounce::Reflect));
        assert_eq!(trace(&["--rays", "r"]).secondary.bounce(), None, "the rays themselves");
    }

    #[test]
    fn options_that_would_be_ignored_or_overflow_are_refused() {
        let formats = ["--ray-format", "origin_direction", "--hit-format", "t"];
        let traced = |extra: &[&str]| parse(&[&["trace", "--accel", "a"], extra, &formats[..]].concat());
        let refused = |parsed: Result<Cli, clap::Error>, kind| assert_eq!(parsed.unwrap_err().kind(), kind);
        let invalid = clap::error::ErrorKind::ValueValidation;
        refused(traced(&["--lidar", "--elevations", "-10"]), invalid);
        refused(traced(&["--lidar", "--elevations", "10,-10"]), invalid);
        refused(traced(&["--lidar", "--min-range", "1e39"]), invalid);
        refused(traced(&["--lidar", "--max-range=-1"]), invalid);
        refused(traced(&["--point", "0,0,0", "--max-distance", "NaN"]), invalid);
        refused(traced(&["--rays", "r", "--reflect", "--primary-hits", "h", "--offset", "3e38e"]), invalid);
        refused(traced(&["--rays", "r", "--reflect", "--primary-hits", "h", "--offset", "inf"]), invalid);
        refused(traced(&["--lidar", "--min-range", "inf"]), invalid);
        let Cli { command: Command::Trace(scan), .. } = traced(&["--lidar", "--max-range", "inf"]).unwrap() else {
            panic!("not trace")
        };
        assert_eq!((scan.lidar_scan.min_range, scan.lidar_scan.max_range), (0.0, f32::INFINITY));
        let rays = |extra: &[&str]| parse(&[&["rays", "--accel", "a", "-o", "r.bin"], extra].concat());
        for ignored in ["--width", "--height"] {
            refused(rays(&["--random", "100", ignored, "64"]), clap::error::ErrorKind::ArgumentConflict);
        }
        assert!(rays(&["--random", "100"]).is_ok() && rays(&["--width", "64"]).is_ok());
    }

    #[test]
    fn trace_refuses_two_ray_sources_and_options_without_theirs() {
        let formats = ["--ray-format", "origin_direction", "--hit-format", "t"];
        let with = |extra: &[&str]| parse(&[&["trace", "--accel", "a"], extra, &formats[..]].concat());
        let (view, orthographic) = ("0,0,5,0,0,0,0,1,0,40", "0,0,5,0,0,0,0,1,0,2");
        let refused: [&[&str]; 20] = [
            &["--rays", "r", "--lidar"],
            &["--pixels", "4x4", "--point", "0,0,0"],
            &["--point", "0,0,0", "--points", "p.bin"],
            &["--lidar", "--points", "p.bin"],
            &["--channels", "4"],
            &["--rays", "r", "--channels", "4"],
            &["--pixels", "4x4", "--steps", "4"],
            &["--point", "0,0,0", "--origin", "0,0,0"],
            &["--rays", "r", "--samples", "2"],
            &["--lidar", "--jitter", "1"],
            &["--rays", "r", "--orthographic", orthographic],
            &["--pixels", "4x4", "--camera", view, "--orthographic", orthographic],
            &["--pixels", "4x4", "--orthographic", "0,0,5,0,0,0,0,1,0,0"],
            &["--point", "0,0,0", "--normals", "n.bin"],
            &["--rays", "r", "--seed", "3"],
            &["--rays", "r", "--reflect"],
            &["--rays", "r", "--primary-hits", "h.bin"],
            &["--rays", "r", "--reflect", "--towards-light", "1,1,1", "--primary-hits", "h.bin"],
            &["--rays", "r", "--reflect", "--primary-hits", "h.bin", "--primary-hits-buffer", "h"],
            &["--rays", "r", "--offset", "0.1"],
        ];
        for extra in refused {
            assert!(with(extra).is_err(), "{extra:?} is refused");
        }
    }

    #[test]
    fn lidar_keeps_its_options_and_their_defaults() {
        let cli = parse(&["lidar", "--accel", "a", "-o", "s.ply", "--channels", "2", "--min-range", "0.5"]).unwrap();
        let Command::Lidar(lidar) = cli.command else { panic!("not lidar") };
        let made = lidar.scan.lidar(Vec3::ZERO);
        assert_eq!((made.forward, made.up, made.steps, made.min_range), (Vec3::NEG_Z, Vec3::Y, 1024, 0.5));
        assert_eq!(
            (made.elevations_degrees, made.max_range, made.time),
            (vec![-25.0, 15.0], f32::INFINITY, (0.0, 0.0))
        );
    }

    #[test]
    fn build_flags_follow_the_options_and_prefer_is_exclusive() {
        let cli = parse(&["build", "--mesh", "m.ply", "--prefer", "fast-build", "--allow-compaction"]).unwrap();
        let Command::Build(build) = cli.command else { panic!("not build") };
        assert_eq!(build.flags(), BuildFlags::PREFER_FAST_BUILD | BuildFlags::ALLOW_COMPACTION);
        assert_eq!((build.name, build.device.as_str()), (None, ""));
        assert!(parse(&["build", "--mesh", "m.ply", "--prefer", "fast"]).is_err());
        assert!(parse(&["build"]).is_err(), "--mesh is required");
    }

    #[test]
    fn render_camera_needs_ten_sane_numbers() {
        let cli = parse(&["render", "--accel", "a", "-o", "x.png", "--camera", "0,0,5,0,0,0,0,1,0,40"]).unwrap();
        let Command::Render(render) = cli.command else { panic!("not render") };
        let view = render.camera.unwrap();
        assert_eq!((view.eye, view.up, view.fov_y_degrees), (Vec3::new(0.0, 0.0, 5.0), Vec3::Y, 40.0));
        assert_eq!((render.width, render.height, render.shading), (800, 600, ShadingArg::Normal));
        let cli = parse(&["render", "--accel", "a", "-o", "x.png", "--camera", "-1,-2,-3,0,0,0,0,1,0,60"]).unwrap();
        let Command::Render(render) = cli.command else { panic!("not render") };
        assert_eq!(render.camera.unwrap().eye, Vec3::new(-1.0, -2.0, -3.0), "negative numbers are values");
        let unbounded = ["0,0,5,0,0,0,0,inf,0,40", "0,0,5,0,0,0,NaN,1,0,40", "3e38,0,0,-3e38,0,0,0,1,0,40"];
        for bad in ["0,0,5,0,0,0,0,1,0", "0,0,5,0,0,0,0,1,0,200", "0,0,0,0,0,0,0,1,0,40", "0,5,0,0,0,0,0,1,0,40"]
            .into_iter()
            .chain(unbounded)
        {
            assert!(parse(&["render", "--accel", "a", "-o", "x.png", "--camera", bad]).is_err(), "{bad}");
        }
        assert!(parse(&["render", "--accel", "a"]).is_err(), "-o is required");
    }

    #[test]
    fn bench_defaults_and_duration() {
        let cli = parse(&["bench", "--accel", "a", "--duration", "2.5"]).unwrap();
        let Command::Bench(bench) = cli.command else { panic!("not bench") };
        assert_eq!((bench.batch, bench.concurrency), (65536, 4));
        assert_eq!(bench.duration, Duration::from_millis(2500));
        assert_eq!((bench.ray_format, bench.hit_format), (RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV));
        assert_eq!(bench.query.query, QueryKind::Closest);
        assert!(parse(&["bench", "--accel", "a", "--duration", "0"]).is_err());
        assert!(parse(&["bench", "--accel", "a", "--concurrency", "0"]).is_err());
    }

    #[test]
    fn health_asks_about_rayd_within_five_seconds_by_default() {
        let Command::Health { service, timeout } = parse(&["health"]).unwrap().command else { panic!("not health") };
        assert_eq!((service.as_str(), timeout), ("rayd.v1.Rayd", Duration::from_secs(5)));
        let Command::Health { service, .. } = parse(&["health", "--service", ""]).unwrap().command else {
            panic!("not health")
        };
        assert_eq!(service, "", "the server as a whole");
    }
}
