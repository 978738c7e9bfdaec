//! rayctl's command line: global options, one subcommand a job, and parsers for the engine's format names,
//! camera views and durations.

use std::path::PathBuf;
use std::time::Duration;

use clap::builder::{PossibleValuesParser, TypedValueParser};
use clap::{Args, Parser, Subcommand, ValueEnum};
use glam::Vec3;
use rayd_client::{DEFAULT_SERVER, Shading};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFlags, RayFormat};
use rayd_engine::query::{Query, QueryKind};

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
    /// For an https:// server: the CA certificate (PEM) that signed its certificate.
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
    /// Show every tenant's usage against its quotas (an admin key where tenants are configured).
    Stats,
    /// Write a file of packed rays: a camera's (framing the accel by default) or random rays in its box.
    Rays(RaysArgs),
    /// Trace a file of packed rays.
    Trace(TraceArgs),
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

/// `rayctl trace`.
#[derive(Debug, Args)]
pub struct TraceArgs {
    /// The accel's name.
    #[arg(long, value_name = "NAME")]
    pub accel: String,
    /// A file of packed rays, no header.
    #[arg(long, value_name = "FILE", required_unless_present = "pixels")]
    pub rays: Option<PathBuf>,
    /// Instead of a ray file: a pinhole camera of W×H pixels whose rays the server makes itself (no ray crosses
    /// the network), framing the accel's box or placed by `--camera`.
    #[arg(long, value_name = "WxH", value_parser = parse_pixels, conflicts_with = "rays")]
    pub pixels: Option<(u32, u32)>,
    /// The camera of `--pixels`, as for `render`.
    #[arg(long, value_name = "EYE,TARGET,UP,FOVY", value_parser = parse_view, allow_hyphen_values = true,
          conflicts_with = "rays")]
    pub camera: Option<View>,
    /// How the rays are packed (or made, with `--pixels`).
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
    #[arg(long, value_name = "N", conflicts_with = "camera")]
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
    let values = text
        .split(',')
        .map(|v| v.trim().parse::<f32>().map_err(|e| format!("{v:?}: {e}")))
        .collect::<Result<Vec<_>, _>>()?;
    match values[..] {
        [t] if t.is_finite() => Ok((t, t)),
        [start, end] if start.is_finite() && end.is_finite() && start <= end => Ok((start, end)),
        _ => Err(format!("expected a finite number T or a span T0,T1 with T0 <= T1, got {text:?}")),
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
    #[arg(long, value_name = "LO,HI", default_value = "-25,15", value_parser = parse_times, allow_hyphen_values = true)]
    pub elevations: (f32, f32),
    /// Azimuth steps a revolution.
    #[arg(long, value_name = "N", default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..))]
    pub steps: u32,
    /// Nearest range (the rays' tmin).
    #[arg(long, value_name = "R", default_value_t = 0.0)]
    pub min_range: f32,
    /// Farthest range (the rays' tmax; default unlimited).
    #[arg(long, value_name = "R", default_value_t = f32::INFINITY)]
    pub max_range: f32,
    /// The PLY file to write.
    #[arg(short = 'o', long = "output", value_name = "FILE.ply")]
    pub output: PathBuf,
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

/// Where a camera stands and looks.
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

/// `rayctl bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// The accel's name.
    #[arg(long, value_name = "NAME")]
    pub accel: String,
    /// Rays a call.
    #[arg(long, value_name = "N", default_value_t = 65536, value_parser = clap::value_parser!(u64).range(1..))]
    pub batch: u64,
    /// Calls in flight at once.
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

/// Parses `ex,ey,ez,tx,ty,tz,ux,uy,uz,fovy`.
fn parse_view(text: &str) -> Result<View, String> {
    let numbers: Vec<f32> = text
        .split(',')
        .map(|n| n.trim().parse::<f32>().map_err(|e| format!("{n:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let [ex, ey, ez, tx, ty, tz, ux, uy, uz, fov] = numbers[..] else {
        return Err(format!("expected 10 comma-separated numbers, got {}", numbers.len()));
    };
    if !(fov > 0.0 && fov < 180.0) {
        return Err(format!("the field of view must be between 0 and 180 degrees, not {fov}"));
    }
    let (eye, target, up) = (Vec3::new(ex, ey, ez), Vec3::new(tx, ty, tz), Vec3::new(ux, uy, uz));
    if !(eye - target).is_finite() || eye == target || (target - eye).cross(up).length_squared() == 0.0 {
        return Err("the eye must differ from the target and up must not be parallel to the view".into());
    }
    Ok(View { eye, target, up, fov_y_degrees: fov })
}

/// Parses a positive number of seconds.
fn parse_seconds(text: &str) -> Result<Duration, String> {
    let seconds: f64 = text.parse().map_err(|e| format!("{text:?}: {e}"))?;
    Duration::try_from_secs_f64(seconds)
        .ok()
        .filter(|d| !d.is_zero())
        .ok_or_else(|| format!("{text}: not a positive duration"))
}

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
        for bad in ["0,0,5,0,0,0,0,1,0", "0,0,5,0,0,0,0,1,0,200", "0,0,0,0,0,0,0,1,0,40", "0,5,0,0,0,0,0,1,0,40"] {
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
