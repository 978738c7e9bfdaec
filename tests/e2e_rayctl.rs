//! End to end against the real `rayd` binary through the real `rayctl`, as a person or a script runs it from the
//! repository root: the shared bunny built from its file, listed and shown; camera rays written to a file, traced
//! with hits (and counts) written to files byte for byte as the engine traces that file in this process; a PNG
//! picture equal to the engine's hits shaded in this process; a short bench's report, its calls in flight lowered to
//! the server's max_concurrent_operations; and the exit codes and `error: <Code>: …` lines of a missing accel, a bad
//! option, an unreachable server and TLS options for an http:// URL, and a quiet end when the output's reader has
//! gone. Rays made by the server from `rayctl trace`'s generator options (cameras, lidar, samples around points,
//! secondary rays, also from hits larger than a message) trace as the engine's expansion of the generator those
//! options describe, sent as a ray file. Pictures and scans larger than a message are the engine's too; a scene that
//! fails leaves no accel behind; a ray file larger than a message (or a pipe) is traced a part at a time as the
//! engine traces it, and a trace that fails midway leaves the files it was writing as they were; a bench's rays more
//! than rayctl can allocate, and rays or hits more than their file's file system has room for, are refused naming
//! the options; a missing local file is NOT_FOUND naming it, whatever it holds.

mod common;
mod daemon;
mod reference;

use std::collections::HashSet;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use bytes::Bytes;
use daemon::Daemon;
use rayd_client::{Client, ClientOptions, Shading, shade};
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::glam::Vec3;
use rayd_engine::query::{Query, QueryKind};
use rayd_engine::raygen::{
    Bounce, Camera, Generator, Lidar, Orthographic, PixelSampling, Primary, Secondary, SphereSampling, random_rays,
    uniform,
};
use rayd_engine::reduce::{Image, PixelEncoding, PointCloud, PointEncoding, Reduction};
use reference::{BUNNY_TRIANGLES, assert_same_bytes, bunny};
use serde_json::Value;

/// The reference camera's size for `rayctl rays`.
const CAMERA: (u32, u32) = (96, 72);

/// The picture's size for `rayctl render`.
const PICTURE: (u32, u32) = (64, 48);

/// A server URL where nothing listens.
const NOWHERE: &str = "http://127.0.0.1:1";

/// Runs `rayctl --server SERVER ARGS` in the repository root, with none of the test's `RAYD_…` variables.
fn rayctl(server: &str, args: &[&str]) -> Output {
    rayctl_command(server, args).output().expect("rayctl runs")
}

/// The command [`rayctl`] runs.
fn rayctl_command(server: &str, args: &[&str]) -> Command {
    let mut command = Command::new(daemon::binary("rayctl"));
    daemon::without_rayd_env(&mut command).current_dir(env!("CARGO_MANIFEST_DIR")).args(["--server", server]);
    command.args(args).env("NO_COLOR", "1");
    command
}

/// What a run printed, for failure messages.
fn printed(output: &Output) -> String {
    let (stdout, stderr) = (String::from_utf8_lossy(&output.stdout), String::from_utf8_lossy(&output.stderr));
    format!("{}\n--- stdout\n{stdout}--- stderr\n{stderr}", output.status)
}

/// Builds the shared bunny as accel `bunny` with `rayctl build`; what it printed.
fn build_bunny(server: &str) -> String {
    succeeds(server, &["build", "--mesh", "../shared/data/meshes/stanford-bunny.obj", "--name", "bunny"])
}

/// Runs rayctl and returns its standard output, panicking unless it exits 0.
fn succeeds(server: &str, args: &[&str]) -> String {
    let output = rayctl(server, args);
    assert!(output.status.success(), "rayctl {args:?}: {}", printed(&output));
    String::from_utf8(output.stdout).expect("UTF-8 output")
}

/// Runs `rayctl --json ARGS` and returns the one JSON object it prints.
fn json(server: &str, args: &[&str]) -> Value {
    let args: Vec<&str> = std::iter::once("--json").chain(args.iter().copied()).collect();
    let stdout = succeeds(server, &args);
    let value: Value = serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("rayctl {args:?}: {e}: {stdout}"));
    assert!(value.is_object(), "rayctl {args:?} prints an object: {value}");
    value
}

/// Runs rayctl, asserts that it exits with `code` and prints nothing on standard output, and returns its standard
/// error.
fn fails(server: &str, args: &[&str], code: i32) -> String {
    let output = rayctl(server, args);
    assert_eq!(output.status.code(), Some(code), "rayctl {args:?}: {}", printed(&output));
    assert!(output.stdout.is_empty(), "rayctl {args:?}: {}", printed(&output));
    String::from_utf8(output.stderr).expect("UTF-8 errors")
}

/// A directory of its own for the files one test has rayctl write; removed when the test passes, kept for a look
/// when it fails.
struct Scratch(PathBuf);

impl Scratch {
    /// An empty `target/tmp/NAME-PID`.
    fn new(name: &str) -> Scratch {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("the scratch directory can be created");
        Scratch(dir)
    }

    /// The path of `file` in the directory, as an argument for rayctl.
    fn path(&self, file: &str) -> String {
        self.0.join(file).into_os_string().into_string().expect("a UTF-8 scratch path")
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// The bytes of a file rayctl wrote.
fn read(path: &str) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// A JSON number, as `f64`.
fn number(value: &Value, key: &str) -> f64 {
    value[key].as_f64().unwrap_or_else(|| panic!("a number {key:?} in {value}"))
}

/// The width, height, colour type and pixels of a PNG file.
fn decode_png(path: &str) -> (u32, u32, png::ColorType, Vec<u8>) {
    let file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let mut reader = png::Decoder::new(std::io::BufReader::new(file)).read_info().expect("a PNG header");
    let mut pixels = vec![0; reader.output_buffer_size().expect("a sane PNG size")];
    let frame = reader.next_frame(&mut pixels).expect("PNG pixels");
    pixels.truncate(frame.buffer_size());
    (frame.width, frame.height, frame.color_type, pixels)
}

#[test]
fn rayctl_builds_traces_renders_benches_and_removes_the_bunny_as_the_engine_does() {
    let daemon = Daemon::start(&[]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl");
    let bunny = bunny();

    let built = build_bunny(&server);
    let triangles = BUNNY_TRIANGLES.to_string();
    let shows = |line: &str| line.split_whitespace().eq(["triangles:", triangles.as_str()]);
    assert!(built.lines().any(shows), "build shows the accel:\n{built}");
    let accels = json(&server, &["accels"]);
    let [info] = accels["accels"].as_array().expect("a list of accels").as_slice() else {
        panic!("one accel: {accels}");
    };
    assert_eq!(*info, json(&server, &["info", "bunny"]), "info shows the accel as accels lists it");
    assert_eq!((info["name"].as_str(), info["device"].as_str()), (Some("bunny"), Some("cpu:0")), "{info}");
    assert_eq!(info["triangle_count"], BUNNY_TRIANGLES, "{info}");
    assert_eq!(info["geometry_count"], 1, "{info}");
    assert_eq!(info["size_bytes"], bunny.info().size_bytes, "the same accel as the engine builds here");
    let corner = |key: &str| serde_json::from_value::<[f32; 3]>(info["bounds"][key].clone()).expect("3 numbers");
    let (lo, hi) = bunny.info().bounds;
    assert_eq!([corner("min"), corner("max")], [lo.to_array(), hi.to_array()], "bounds that read back exactly");
    assert_eq!(json(&server, &["buffers"])["buffers"], Value::Array(vec![]), "an inline build leaves no buffer");

    let (width, height) = CAMERA;
    let rays_file = scratch.path("camera.rays");
    let size = [width.to_string(), height.to_string()];
    let written =
        json(&server, &["rays", "--accel", "bunny", "--width", &size[0], "--height", &size[1], "-o", &rays_file]);
    assert_eq!(written["rays"], width * height, "{written}");
    assert_eq!(written["ray_format"], "origin_tmin_direction_tmax", "{written}");
    let rays = read(&rays_file);
    let camera = bunny.camera_rays(RayFormat::OriginTminDirectionTmax, width, height);
    assert_same_bytes(&rays, &camera, "rays framing the accel's box: the reference camera's");
    // Motion blur: the same camera rays, each at a time in [0.25, 0.75].
    let timed_file = scratch.path("timed.rays");
    let format = "origin_tmin_direction_tmax_time";
    let args = ["rays", "--accel", "bunny", "--width", &size[0], "--height", &size[1], "--ray-format", format];
    json(&server, &[&args[..], &["--time", "0.25,0.75", "-o", &timed_file]].concat());
    let timed = read(&timed_file);
    let with_time = bunny.camera_rays(RayFormat::OriginTminDirectionTmaxTime, width, height);
    let times: Vec<f32> =
        timed.chunks_exact(36).map(|ray| f32::from_le_bytes(ray[32..36].try_into().unwrap())).collect();
    assert!(times.iter().all(|t| (0.25..=0.75).contains(t)), "times in the span");
    assert!(times.iter().any(|&t| t != times[0]), "times spread over the span");
    let untimed = |bytes: &[u8]| bytes.chunks_exact(36).flat_map(|ray| ray[..32].to_vec()).collect::<Vec<u8>>();
    assert_same_bytes(&untimed(&timed), &untimed(&with_time), "the same rays apart from their times");
    let stderr = fails(&server, &["rays", "--accel", "bunny", "--time", "1", "-o", &timed_file], 1);
    assert!(stderr.contains("--time") && stderr.contains("carries no time"), "{stderr}");
    // A camera of its own does not need the accel's box, but the accel must be there all the same.
    let camera = ["--camera", "0,0,1,0,0,0,0,1,0,40", "-o", &timed_file];
    let stderr = fails(&server, &[&["rays", "--accel", "nothing"], &camera[..]].concat(), 1);
    assert!(stderr.starts_with("error: NotFound: ") && stderr.contains("nothing"), "{stderr}");

    let trace = |kind: &str, out: &str| {
        let formats = ["--ray-format", "origin_tmin_direction_tmax", "--hit-format", "t_triid_u_v"];
        let mut args = vec!["trace", "--accel", "bunny", "--rays", rays_file.as_str()];
        args.extend(formats.into_iter().chain(["--query", kind, "--out", out]));
        json(&server, &args)
    };
    let closest = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    for query in [closest, Query { kind: QueryKind::Count, ..closest }] {
        let kind = query.kind.name();
        let expected = bunny.trace(&query, &rays);
        assert!(0 < expected.stats.rays_hit && expected.stats.rays_hit < expected.stats.rays, "rays hit and miss");
        let hits_file = scratch.path(&format!("camera.{kind}"));
        let report = trace(kind, &hits_file);
        assert!(number(&report, "server_ms") >= 0.0 && number(&report, "wall_ms") >= 0.0, "{kind}: {report}");
        let counts_file = format!("{hits_file}.counts");
        let counts = if query.kind.has_counts() {
            read(&counts_file)
        } else {
            assert!(!Path::new(&counts_file).exists(), "{kind}: no counts file");
            Vec::new()
        };
        let count = |key: &str| report[key].as_u64().unwrap_or_else(|| panic!("a count {key:?} in {report}"));
        let stats = (count("rays"), count("hits"));
        expected.assert_answer(&read(&hits_file), &counts, stats, &format!("{kind}: the files and the report"));
    }
    // The same camera's rays made by the server (`--pixels`): the same hits, and no ray file.
    let pixels = format!("{width}x{height}");
    let generated_file = scratch.path("generated.hits");
    let formats = ["--ray-format", "origin_tmin_direction_tmax", "--hit-format", "t_triid_u_v"];
    let mut args = vec!["trace", "--accel", "bunny", "--pixels", pixels.as_str(), "--out", generated_file.as_str()];
    args.extend(formats);
    let report = json(&server, &args);
    let expected = bunny.trace(&closest, &rays);
    let stats = (report["rays"].as_u64().unwrap_or(0), report["hits"].as_u64().unwrap_or(0));
    expected.assert_answer(&read(&generated_file), &[], stats, "--pixels: the file and the report");

    let (width, height) = PICTURE;
    let png_file = scratch.path("bunny.png");
    let size = [width.to_string(), height.to_string()];
    let rendered =
        json(&server, &["render", "--accel", "bunny", "--width", &size[0], "--height", &size[1], "-o", &png_file]);
    assert_eq!(
        (rendered["width"].as_u64(), rendered["height"].as_u64()),
        (Some(width.into()), Some(height.into())),
        "{rendered}"
    );
    let (png_width, png_height, colour, pixels) = decode_png(&png_file);
    assert_eq!((png_width, png_height, colour), (width, height, png::ColorType::Rgb));
    let colours: HashSet<&[u8]> = pixels.chunks_exact(3).collect();
    assert!(colours.len() > 1, "not one flat colour: {colours:?}");
    assert_same_bytes(&pixels, &bunny_picture(width, height), "the picture's pixels");
    // A file that cannot be written fails the command (a full disk: /dev/full), saves and scans too.
    for args in [&["render", "--accel", "bunny", "-o", "/dev/full"][..], &["save", "bunny", "-o", "/dev/full"]] {
        let stderr = fails(&server, args, 1);
        assert!(stderr.contains("/dev/full: No space left on device"), "{args:?}: {stderr}");
    }

    // A lidar scan: the returns of the same rays traced in-process, as PLY vertices.
    let ply_file = scratch.path("scan.ply");
    let (lo, hi) = bunny.mesh.bounds();
    let lidar = Lidar {
        origin: Vec3::new((lo.x + hi.x) * 0.5, (lo.y + hi.y) * 0.5, hi.z + (hi - lo).z),
        forward: Vec3::NEG_Z,
        up: Vec3::Y,
        elevations_degrees: (0..16).map(|c| -25.0 + 40.0 * c as f32 / 15.0).collect(),
        steps: 90,
        min_range: 0.0,
        max_range: f32::INFINITY,
        time: (0.0, 0.0),
    };
    let origin = vec3_arg(lidar.origin);
    let args = ["lidar", "--accel", "bunny", "--channels", "16", "--steps", "90", "--origin", &origin, "-o", &ply_file];
    let scanned = json(&server, &args);
    let expected = bunny_scan(lidar);
    assert!(expected.len() > 12 * 100, "the scan sees the bunny");
    assert_scan(&scanned, &read(&ply_file), &expected);

    let args =
        ["bench", "--accel", "bunny", "--batch", "1000", "--concurrency", "2", "--duration", "1", "--connections", "2"];
    let report = json(&server, &args);
    assert!(number(&report, "rays_per_s") > 0.0, "{report}");
    let (p50, p90, p99) = (number(&report, "p50_ms"), number(&report, "p90_ms"), number(&report, "p99_ms"));
    assert!(0.0 < p50 && p50 <= p90 && p90 <= p99, "latency percentiles in order: {report}");
    let batches = report["batches"].as_u64().expect("a batch count");
    assert!(batches > 0 && report["rays"] == batches * 1000, "whole batches of 1000 rays: {report}");

    assert_eq!(json(&server, &["rm", "bunny"])["destroyed"], "bunny");
    let stderr = fails(&server, &["info", "bunny"], 1);
    assert!(stderr.starts_with("error: NotFound: ") && stderr.contains("bunny"), "{stderr}");
    assert_eq!(json(&server, &["accels"])["accels"], Value::Array(vec![]), "no accel left");
}

#[test]
fn bench_keeps_at_most_the_servers_max_concurrent_operations_in_flight_and_says_so() {
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_CONCURRENT_OPERATIONS", "2")]);
    let server = daemon.url();
    build_bunny(&server);
    // Sixteen calls at once against a limit of two: without the cap, the first refused call ends the run.
    let args = ["bench", "--accel", "bunny", "--batch", "4096", "--concurrency", "16", "--duration", "0.5"];
    let report = json(&server, &args);
    assert_eq!(report["concurrency"], 2, "{report}");
    assert!(report["batches"].as_u64().is_some_and(|batches| batches > 0), "{report}");
    let text = succeeds(&server, &args);
    assert!(text.contains("2 in flight (lowered from 16: the server's max_concurrent_operations)"), "{text}");
}

#[test]
fn a_reader_of_the_output_that_has_gone_ends_rayctl_quietly() {
    let daemon = Daemon::start(&[]);
    let mut command = Command::new(daemon::binary("rayctl"));
    daemon::without_rayd_env(&mut command).args(["--server", &daemon.url(), "devices"]);
    let mut child = command.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().expect("rayctl runs");
    // The reader goes before rayctl has connected, let alone printed (`rayctl devices | true`).
    drop(child.stdout.take());
    let output = child.wait_with_output().expect("rayctl ends");
    assert!(output.status.success(), "rayctl devices with its reader gone: {}", printed(&output));
    assert!(output.stderr.is_empty(), "no panic, no error: {}", printed(&output));
}

#[test]
fn usage_errors_exit_2_before_connecting_and_an_unreachable_server_or_tls_over_http_exit_1() {
    let args = ["trace", "--accel", "bunny", "--rays", "r.bin", "--ray-format", "prime", "--hit-format", "t"];
    let stderr = fails(NOWHERE, &args, 2);
    assert!(
        stderr.contains("prime") && stderr.contains("origin_tmin_direction_tmax"),
        "names the valid formats: {stderr}"
    );
    let stderr = fails(NOWHERE, &["--connections", "0", "devices"], 2);
    assert!(stderr.contains("--connections") && stderr.contains("0"), "names the flag: {stderr}");
    let stderr = fails(NOWHERE, &["devices"], 1);
    assert!(stderr.starts_with("error: Unavailable: ") && stderr.contains(NOWHERE), "{stderr}");
    let scratch = Scratch::new("e2e-rayctl-pem");
    let pem = scratch.path("both.pem");
    let blocks =
        ["CERTIFICATE", "PRIVATE KEY"].map(|kind| format!("-----BEGIN {kind}-----\nAAAA\n-----END {kind}-----\n"));
    std::fs::write(&pem, blocks.concat()).unwrap();
    for tls in [&["--ca-cert", &pem][..], &["--client-cert", &pem, "--client-key", &pem]] {
        for command in ["devices", "health"] {
            let stderr = fails(NOWHERE, &[tls, &[command]].concat(), 1);
            let refused = stderr.starts_with("error: InvalidArgument: ") && stderr.contains("https://");
            assert!(refused, "TLS options for an http:// URL are refused, not ignored: {stderr}");
        }
    }
    // Files that hold no PEM block of their kind are refused by option and file, before anything connects.
    let https = "https://127.0.0.1:1";
    let stderr = fails(https, &["--ca-cert", "Cargo.toml", "devices"], 1);
    assert!(stderr.starts_with("error: InvalidArgument: --ca-cert Cargo.toml: holds no PEM certificate"), "{stderr}");
    let stderr = fails(https, &["--client-cert", &pem, "--client-key", "Cargo.toml", "health"], 1);
    assert!(
        stderr.starts_with("error: InvalidArgument: --client-key Cargo.toml: holds no PEM private key"),
        "{stderr}"
    );
}

#[test]
fn rayctl_builds_a_scene_file_as_an_instance_accel_over_its_meshes_and_renders_it() {
    let daemon = Daemon::start(&[]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-scene");
    let meshes = std::fs::canonicalize("../shared/data/meshes").expect("the shared meshes");
    let scene = serde_json::json!({
        "meshes": { "cow": meshes.join("cow.obj"), "teapot": meshes.join("teapot.obj") },
        "instances": [
            { "mesh": "cow" },
            { "mesh": "teapot", "translate": [3, 0, 0], "scale": 0.2, "id": 40 },
            { "mesh": "cow", "translate": [-3, 0, 0], "rotate": [0, 1, 0, 180], "scale": [1, 1, -1], "flip_facing": true },
        ]
    });
    let file = scratch.path("farm.json");
    std::fs::write(&file, scene.to_string()).unwrap();
    let info = json(&server, &["scene", "--file", &file]);
    assert_eq!((info["name"].as_str(), info["kind"].as_str()), (Some("farm"), Some("instances")), "{info}");
    assert_eq!((info["instance_count"].as_u64(), info["depth"].as_u64()), (Some(3), Some(2)), "{info}");
    let names: Vec<String> = json(&server, &["accels"])["accels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["name"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(names, ["farm.cow", "farm.teapot", "farm"], "one accel per mesh, then the scene");
    let picture = scratch.path("farm.png");
    succeeds(&server, &["render", "--accel", "farm", "-o", &picture, "--width", "64", "--height", "48"]);
    let (_, _, _, pixels) = decode_png(&picture);
    assert!(pixels.iter().any(|&p| p != pixels[0]), "the render shows something");
    // Save the scene to a file and load it back under another name: the same picture.
    let saved = scratch.path("farm.rayd");
    let report = json(&server, &["save", "farm", "-o", &saved]);
    assert_eq!(report["bytes"].as_u64(), std::fs::metadata(&saved).ok().map(|m| m.len()), "{report}");
    let loaded = json(&server, &["load", &saved, "--name", "barn"]);
    let loaded_names: Vec<&str> =
        loaded["accels"].as_array().unwrap().iter().map(|a| a["name"].as_str().unwrap()).collect();
    assert_eq!(loaded_names, ["barn.1", "barn.2", "barn"], "the meshes, then the scene");
    let again = scratch.path("barn.png");
    succeeds(&server, &["render", "--accel", "barn", "-o", &again, "--width", "64", "--height", "48"]);
    assert_eq!(decode_png(&again).3, pixels, "the loaded scene renders the same picture");
    let damaged = scratch.path("damaged.rayd");
    let mut bytes = std::fs::read(&saved).unwrap();
    bytes.truncate(bytes.len() / 2);
    std::fs::write(&damaged, bytes).unwrap();
    let refused = fails(&server, &["load", &damaged], 1);
    assert!(refused.contains("InvalidArgument"), "{refused}");
    let copy = json(&server, &["copy", "farm", "farm.copy"]);
    assert_eq!((copy["kind"].as_str(), copy["instance_count"].as_u64()), (Some("instances"), Some(3)), "{copy}");
    succeeds(&server, &["rm", "farm"]);
    let refused = fails(&server, &["rm", "farm.cow"], 1);
    assert!(refused.contains("FailedPrecondition"), "the copy still places the cow: {refused}");
    let refused = fails(&server, &["copy", "farm.copy", "farm.small", "--compact"], 1);
    assert!(refused.contains("FailedPrecondition") && refused.contains("ALLOW_COMPACTION"), "{refused}");
    let refused = fails(&server, &["compact", "farm.copy", "farm.small"], 1);
    assert!(refused.contains("ALLOW_COMPACTION"), "{refused}");
    let cow = meshes.join("cow.obj");
    let built = json(&server, &["build", "--mesh", cow.to_str().unwrap(), "--name", "cow", "--allow-compaction"]);
    let small = json(&server, &["compact", "cow", "cow.small"]);
    assert!(small["size_bytes"].as_u64() <= built["compacted_size_bytes"].as_u64(), "{small} {built}");
    let broken = scratch.path("broken.json");
    std::fs::write(&broken, r#"{ "meshes": {}, "instances": [{ "mesh": "nothing" }] }"#).unwrap();
    let refused = fails(&server, &["scene", "--file", &broken], 1);
    assert!(refused.contains("instances[0].mesh"), "{refused}");
}

/// The RGB pixels of `rayctl render`'s default picture of the bunny: the normal of the closest hit of one ray a
/// pixel, rays as in `Bunny::camera_rays`, reduced to an image of normals as the engine reduces a whole batch at once,
/// shaded.
fn bunny_picture(width: u32, height: u32) -> Vec<u8> {
    let image = Image {
        width,
        rays_per_pixel: 1,
        channel: Shading::Normal.channel(),
        encoding: PixelEncoding::Float32,
        near: 0.0,
        far: 0.0,
    };
    let reduction = Reduction::Image(image);
    let query = reduction.traced_query(&Query::closest(RayFormat::OriginDirection, HitFormat::T));
    let rays = bunny().camera_rays(query.ray_format, width, height);
    let expected = bunny().trace(&query, &rays);
    let normals = reduction.reduce_all(&query, &rays, &expected.hits, &expected.counts).expect("an image");
    shade(&normals.bytes, width, height, Shading::Normal).rgb
}

/// The points of `rayctl lidar`'s scan of the bunny with `lidar`: the returns of its rays traced in-process, as
/// float32 x, y, z.
fn bunny_scan(lidar: Lidar) -> Vec<u8> {
    let query = Query::closest(RayFormat::OriginTminDirectionTmaxTime, HitFormat::T);
    let rays = Generator::Lidar(lidar).rays(query.ray_format);
    let returns = bunny().trace(&query, &rays);
    let points = Reduction::PointCloud(PointCloud {
        encoding: PointEncoding::Float32,
        step: 0.0,
        origin: Vec3::ZERO,
        ray_indices: false,
    });
    points.reduce_all(&query, &rays, &returns.hits, &[]).expect("a point cloud").bytes.to_vec()
}

/// Asserts that `rayctl --json lidar`'s report and PLY file hold the `expected` points.
fn assert_scan(report: &Value, ply: &[u8], expected: &[u8]) {
    assert_eq!(report["points"].as_u64(), Some(expected.len() as u64 / 12), "{report}");
    let header_end = ply.windows(11).position(|w| w == b"end_header\n").expect("a PLY header") + 11;
    let header = String::from_utf8_lossy(&ply[..header_end]);
    assert!(header.contains(&format!("element vertex {}\n", expected.len() / 12)), "{header}");
    assert_same_bytes(&ply[header_end..], expected, "the scan's points");
}

/// `x,y,z` as rayctl takes a vector (each `f32` printed so that it parses back to itself).
fn vec3_arg(v: Vec3) -> String {
    format!("{},{},{}", v.x, v.y, v.z)
}

/// Vectors packed as rayctl's `--points` and `--normals` files hold them: x, y, z little-endian f32 each.
fn packed_vectors(vectors: &[Vec3]) -> Vec<u8> {
    vectors.iter().flat_map(|v| v.to_array()).flat_map(f32::to_le_bytes).collect()
}

/// One `rayctl --json trace` of an accel, with its hits and counts files.
struct Traced {
    /// The hit records written to `--out`.
    hits: Vec<u8>,
    /// The counts written to `--out`.counts (empty without them).
    counts: Vec<u8>,
    /// The JSON report.
    report: Value,
}

#[test]
fn rayctl_traces_rays_made_by_the_server_as_the_engine_makes_them_sent_in_a_file() {
    let daemon = Daemon::start(&[]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-generators");
    let mesh_file = std::fs::canonicalize("../shared/data/meshes/stanford-bunny.obj").expect("the shared bunny");
    let mesh_file = mesh_file.to_str().expect("a UTF-8 path");
    succeeds(&server, &["build", "--mesh", mesh_file, "--name", "bunny"]);
    let bunny = bunny();
    let (lo, hi) = bunny.info().bounds;
    let (centre, size) = ((lo + hi) * 0.5, hi - lo);
    // The bunny moving by its own width along x over time [0, 1], for the lidar's times.
    let scene = serde_json::json!({
        "meshes": { "bunny": mesh_file },
        "motion": { "keys": 2, "time": [0, 1] },
        "instances": [{ "mesh": "bunny", "motion": { "time": [0, 1], "keys": [{}, { "translate": [size.x, 0, 0] }] } }]
    });
    let scene_file = scratch.path("moving.json");
    std::fs::write(&scene_file, scene.to_string()).unwrap();
    succeeds(&server, &["scene", "--file", &scene_file, "--name", "moving"]);

    let ray_format = RayFormat::OriginTminDirectionTmaxTime;
    let trace = |accel: &str, name: &str, rays: &[&str], query: &[&str], hit_format: &str| {
        let out = scratch.path(name);
        let formats = ["--ray-format", ray_format.name(), "--hit-format", hit_format, "--out", out.as_str()];
        let report = json(&server, &[&["trace", "--accel", accel][..], rays, query, &formats].concat());
        let counts = std::fs::read(format!("{out}.counts")).unwrap_or_default();
        Traced { hits: read(&out), counts, report }
    };
    // Traces `args` with the generator options under test, and the rays `expected` makes, sent in a file: the same
    // hits, counts and report counts; some rays hit and some miss.
    let check = |what: &str, accel: &str, args: &[&str], expected: &Generator, query: &[&str], hit_format: &str| {
        let made = trace(accel, &format!("{what}.hits"), args, query, hit_format);
        let rays_file = scratch.path(&format!("{what}.rays"));
        std::fs::write(&rays_file, expected.rays(ray_format)).unwrap();
        let sent = trace(accel, &format!("{what}.sent"), &["--rays", &rays_file], query, hit_format);
        assert_same_bytes(&made.hits, &sent.hits, &format!("{what}: hits"));
        assert_same_bytes(&made.counts, &sent.counts, &format!("{what}: counts"));
        let counted = |report: &Value| (report["rays"].as_u64(), report["hits"].as_u64());
        assert_eq!(counted(&made.report), counted(&sent.report), "{what}: {} {}", made.report, sent.report);
        let (rays, hit) = (made.report["rays"].as_u64().unwrap(), made.report["hits"].as_u64().unwrap());
        assert_eq!(rays, expected.count(), "{what}: {}", made.report);
        assert!(0 < hit && hit < rays, "{what}: rays hit and miss: {}", made.report);
    };
    let closest = ["--query", "closest"];

    // Cameras: a jittered pinhole framing the box, and an orthographic one, both with several rays a pixel.
    let jittered = PixelSampling { samples: 3, jitter_seed: Some(11) };
    let pinhole = Generator::Pinhole(Camera::framing(lo, hi, 40, 30), jittered);
    let args = ["--pixels", "40x30", "--samples", "3", "--jitter", "11"];
    check("pinhole", "bunny", &args, &pinhole, &closest, "t_triid_u_v");
    let orthographic = Orthographic {
        eye: centre + Vec3::new(0.2, 0.1, 1.0) * size.length(),
        target: centre,
        up: Vec3::Y,
        view_height: size.y * 1.2,
        width: 32,
        height: 24,
    };
    let view = [orthographic.eye, orthographic.target, orthographic.up].map(vec3_arg).join(",");
    let view = format!("{view},{}", orthographic.view_height);
    let args = ["--pixels", "32x24", "--orthographic", &view, "--samples", "2", "--jitter", "4"];
    let sampling = PixelSampling { samples: 2, jitter_seed: Some(4) };
    check("orthographic", "bunny", &args, &Generator::Orthographic(orthographic, sampling), &closest, "t_triid");

    // A lidar sweeping the moving bunny over the revolution's times, every hit up to 4 a ray.
    let lidar = Lidar {
        origin: centre + Vec3::new(-0.3 * size.x, 0.1 * size.y, 1.5 * size.z),
        forward: Vec3::new(0.1, 0.0, -1.0),
        up: Vec3::new(0.0, 1.0, 0.1),
        elevations_degrees: vec![-30.0, -15.0, 0.0, 15.0, 30.0],
        steps: 360,
        min_range: 0.9 * size.z,
        max_range: 3.0 * size.z,
        time: (0.0, 1.0),
    };
    let args = format!(
        "--lidar --origin {} --forward {} --up {} --channels 5 --elevations -30,30 --steps 360 --min-range {} \
         --max-range {} --time 0,1",
        vec3_arg(lidar.origin),
        vec3_arg(lidar.forward),
        vec3_arg(lidar.up),
        lidar.min_range,
        lidar.max_range,
    );
    let args: Vec<&str> = args.split_whitespace().collect();
    let all = ["--query", "all", "--max-hits", "4"];
    check("lidar", "moving", &args, &Generator::Lidar(lidar), &all, "t_triid_instid");

    // Samples around surface points: on the hemisphere of each point's normal (given as options, then as files),
    // and on the whole sphere.
    let triangles = &bunny.mesh.triangles[..50];
    let corners = |t: &[u32; 3]| t.map(|i| bunny.mesh.positions[i as usize]);
    let points: Vec<Vec3> = triangles.iter().map(|t| corners(t).iter().sum::<Vec3>() / 3.0).collect();
    let normals: Vec<Vec3> = triangles.iter().map(corners).map(|[a, b, c]| (b - a).cross(c - a)).collect();
    let around = SphereSampling {
        points: points.clone(),
        normals: normals.clone(),
        samples: 16,
        min_distance: 1e-4,
        max_distance: 0.05,
        seed: 5,
    };
    let options = |flag: &'static str, vectors: &[Vec3]| -> Vec<String> {
        vectors.iter().flat_map(|&v| [flag.to_owned(), vec3_arg(v)]).collect()
    };
    let (listed_points, listed_normals) = (options("--point", &points), options("--normal", &normals));
    let sampling = ["--samples", "16", "--seed", "5", "--min-distance", "0.0001", "--max-distance", "0.05"];
    let args: Vec<&str> = listed_points.iter().chain(&listed_normals).map(String::as_str).chain(sampling).collect();
    let count = ["--query", "count"];
    check("hemispheres", "bunny", &args, &Generator::Sphere(around.clone()), &count, "t_triid");
    let (points_file, normals_file) = (scratch.path("points.bin"), scratch.path("normals.bin"));
    std::fs::write(&points_file, packed_vectors(&points)).unwrap();
    std::fs::write(&normals_file, packed_vectors(&normals)).unwrap();
    let args = [&["--points", &points_file, "--normals", &normals_file][..], &sampling].concat();
    check("hemisphere-files", "bunny", &args, &Generator::Sphere(around.clone()), &count, "t_triid");
    let sphere = SphereSampling {
        normals: Vec::new(),
        samples: 4,
        min_distance: 0.0,
        max_distance: f32::INFINITY,
        seed: 3,
        ..around
    };
    let args = ["--points", &points_file, "--samples", "4", "--seed", "3"];
    check("spheres", "bunny", &args, &Generator::Sphere(sphere), &closest, "t");
    std::fs::write(&points_file, &packed_vectors(&points)[..13]).unwrap();
    let formats = ["--ray-format", ray_format.name(), "--hit-format", "t"];
    let refused = fails(&server, &[&["trace", "--accel", "bunny", "--points", &points_file][..], &formats].concat(), 1);
    assert!(refused.starts_with("error: InvalidArgument: ") && refused.contains("12-byte"), "{refused}");
    std::fs::write(&points_file, b"").unwrap();
    let refused = fails(&server, &[&["trace", "--accel", "bunny", "--points", &points_file][..], &formats].concat(), 1);
    assert!(refused.starts_with(&format!("error: InvalidArgument: --points {points_file}: no points")), "{refused}");

    // Secondary rays: reflections of the jittered camera's rays at their hits in a file, then shadow rays of a ray
    // file's rays towards a light, their hits in a server-side buffer.
    let primary_file = scratch.path("primary.full");
    let args = ["--pixels", "40x30", "--samples", "3", "--jitter", "11"];
    let primary = trace("bunny", "primary.full", &args, &closest, "full");
    let reflect = Secondary {
        primary: Primary::Generated(Box::new(pinhole.clone())),
        hits: Bytes::from(primary.hits),
        bounce: Bounce::Reflect,
        offset: 1e-4,
    };
    let args = [&args[..], &["--reflect", "--primary-hits", &primary_file, "--offset", "0.0001"]].concat();
    check("reflections", "bunny", &args, &Generator::Secondary(reflect), &closest, "t_triid_u_v");

    let rays_file = scratch.path("camera.rays");
    let camera_rays = Camera::framing(lo, hi, 48, 36).rays(ray_format);
    std::fs::write(&rays_file, &camera_rays).unwrap();
    let primary = trace("bunny", "camera.full", &["--rays", &rays_file], &closest, "full");
    let runtime = tokio::runtime::Runtime::new().expect("a tokio runtime");
    runtime.block_on(async {
        let client = Client::connect(&server, ClientOptions::default()).await.expect("the client connects");
        client.upload_buffer("camera-hits", Bytes::from(primary.hits.clone())).await.expect("the hits upload");
    });
    let light = hi + size;
    let shadows = Secondary {
        primary: Primary::Packed(ray_format, Bytes::from(camera_rays)),
        hits: Bytes::from(primary.hits),
        bounce: Bounce::TowardsLight(light),
        offset: 2e-4,
    };
    let light = vec3_arg(light);
    let args =
        ["--rays", &rays_file, "--towards-light", &light, "--primary-hits-buffer", "camera-hits", "--offset", "0.0002"];
    check("shadows", "bunny", &args, &Generator::Secondary(shadows), &["--query", "any"], "t");
}

#[test]
fn secondary_rays_from_hits_larger_than_a_message_are_traced_through_temporary_buffers_in_ranges() {
    // README's example at a smaller scale: 64 KiB messages, and a camera whose 80-byte hits take 288 KB.
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_MESSAGE_BYTES", "65536")]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-large-secondary");
    build_bunny(&server);
    let (lo, hi) = bunny().info().bounds;
    // With tmax: shadow rays stop at their light.
    let ray_format = RayFormat::OriginTminDirectionTmax;
    let trace = |rays: &[&str], hit_format: &str, out: &str| {
        let formats = ["--ray-format", ray_format.name(), "--hit-format", hit_format, "--out", out];
        json(&server, &[&["trace", "--accel", "bunny"][..], rays, &formats].concat())
    };
    // Traces `args` and the rays `expected` makes, sent in a file: the same hits and report counts.
    let check = |what: &str, args: &[&str], expected: &Generator| {
        let (made, sent, rays_file) =
            (scratch.path(&format!("{what}.hits")), scratch.path("sent"), scratch.path("rays"));
        let report = trace(args, "full", &made);
        std::fs::write(&rays_file, expected.rays(ray_format)).unwrap();
        let expected_report = trace(&["--rays", &rays_file], "full", &sent);
        assert_same_bytes(&read(&made), &read(&sent), &format!("{what}: hits"));
        assert_eq!((report["rays"].as_u64(), report["hits"].as_u64()), (Some(3600), expected_report["hits"].as_u64()));
    };

    let camera = ["--pixels", "40x30", "--samples", "3", "--jitter", "11"];
    let pinhole =
        Generator::Pinhole(Camera::framing(lo, hi, 40, 30), PixelSampling { samples: 3, jitter_seed: Some(11) });
    let primary_file = scratch.path("primary.hits");
    trace(&camera, "full", &primary_file);
    let hits = Bytes::from(read(&primary_file));
    let reflect = Secondary {
        primary: Primary::Generated(Box::new(pinhole.clone())),
        hits: hits.clone(),
        bounce: Bounce::Reflect,
        offset: 1e-4,
    };
    let args = [&camera[..], &["--reflect", "--primary-hits", &primary_file, "--offset", "0.0001"]].concat();
    check("reflections", &args, &Generator::Secondary(reflect.clone()));

    // A file's rays as the primaries, both the rays (115 KB) and their hits uploaded.
    let camera_rays = scratch.path("camera.rays");
    std::fs::write(&camera_rays, pinhole.rays(ray_format)).unwrap();
    let camera_hits = scratch.path("camera.hits");
    trace(&["--rays", &camera_rays], "full", &camera_hits);
    let light = hi + (hi - lo);
    let shadows = Secondary {
        primary: Primary::Packed(ray_format, Bytes::from(read(&camera_rays))),
        hits: Bytes::from(read(&camera_hits)),
        bounce: Bounce::TowardsLight(light),
        offset: 2e-4,
    };
    let light = vec3_arg(light);
    let args =
        ["--rays", &camera_rays, "--towards-light", &light, "--primary-hits", &camera_hits, "--offset", "0.0002"];
    check("shadows", &args, &Generator::Secondary(shadows));
    let args = [&camera[..], &["--towards-light", &light, "--primary-hits", &primary_file]].concat();
    let formats = ["--ray-format", "origin_direction", "--hit-format", "t"];
    let refused = fails(&server, &[&["trace", "--accel", "bunny"][..], &args, &formats].concat(), 1);
    assert!(
        refused.contains("origin_direction rays carry no tmax"),
        "shadow rays that would pass the light: {refused}"
    );

    // Hits already on the server: only the reflections' hits, more than a message, need ranges.
    let runtime = tokio::runtime::Runtime::new().expect("a tokio runtime");
    runtime.block_on(async {
        let client = Client::connect(&server, ClientOptions::default()).await.expect("the client connects");
        client.upload_buffer("camera-hits", hits).await.expect("the hits upload");
    });
    let args = [&camera[..], &["--reflect", "--primary-hits-buffer", "camera-hits", "--offset", "0.0001"]].concat();
    check("reflections-from-buffer", &args, &Generator::Secondary(reflect.clone()));

    // Hits through a pipe, whose size rayctl learns by reading it.
    let (piped_out, expected_out) = (scratch.path("piped.hits"), scratch.path("reflections.hits"));
    let args = [&camera[..], &["--reflect", "--primary-hits", "/dev/stdin", "--offset", "0.0001"]].concat();
    let formats = ["--ray-format", ray_format.name(), "--hit-format", "full", "--out", &piped_out];
    let mut rayctl_piped = rayctl_command(&server, &[&["trace", "--accel", "bunny"][..], &args, &formats].concat())
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut pipe = rayctl_piped.stdin.take().unwrap();
    let hits_in = read(&primary_file);
    let writer = std::thread::spawn(move || std::io::Write::write_all(&mut pipe, &hits_in));
    let piped = rayctl_piped.wait_with_output().unwrap();
    writer.join().unwrap().expect("the hits go through the pipe");
    assert!(piped.status.success(), "{}", printed(&piped));
    assert_same_bytes(&read(&piped_out), &read(&expected_out), "reflections of piped hits");

    // Hits of other rays are refused before anything is sent, naming the file and both counts.
    let few_hits = scratch.path("few.hits");
    std::fs::write(&few_hits, &read(&primary_file)[..800]).unwrap();
    let args = [&camera[..], &["--reflect", "--primary-hits", &few_hits]].concat();
    let formats = ["--ray-format", ray_format.name(), "--hit-format", "t"];
    let refused = fails(&server, &[&["trace", "--accel", "bunny"][..], &args, &formats].concat(), 1);
    let named = format!("--primary-hits {few_hits}: 10 hit records (800 bytes), but there are 3600 primary rays");
    assert!(refused.starts_with(&format!("error: InvalidArgument: {named}")), "{refused}");
    // A trace that fails after its files went up (no such accel) leaves no temporary buffer behind.
    let args = ["--rays", &camera_rays, "--reflect", "--primary-hits", &camera_hits];
    let refused = fails(&server, &[&["trace", "--accel", "nowhere"][..], &args, &formats].concat(), 1);
    assert!(refused.starts_with("error: NotFound: "), "{refused}");

    let buffers = json(&server, &["buffers"]);
    let names: Vec<&str> = buffers["buffers"].as_array().unwrap().iter().filter_map(|b| b["name"].as_str()).collect();
    assert_eq!(names, ["camera-hits"], "the temporary buffers are deleted: {buffers}");
}

#[test]
fn ctrl_c_during_a_trace_rays_or_a_build_leaves_no_temporary_buffer_and_no_partial_output() {
    // 64 KiB messages, so that the 80 MB of hits take many messages to go up.
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_MESSAGE_BYTES", "65536")]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-ctrl-c");
    build_bunny(&server);
    let (rays, hits, out) = (scratch.path("camera.rays"), scratch.path("camera.hits"), scratch.path("out.hits"));
    let formats = ["--ray-format", "origin_direction"];
    succeeds(
        &server,
        &[&["rays", "--accel", "bunny", "--width", "1024", "--height", "1024", "-o", &rays][..], &formats].concat(),
    );
    let trace = ["trace", "--accel", "bunny", "--rays", &rays];
    succeeds(&server, &[&trace[..], &formats, &["--hit-format", "full", "--out", &hits]].concat());
    let rays_bytes = std::fs::metadata(&rays).unwrap().len();

    // Once the rays have gone up (the hits are going up after them), Ctrl-C.
    let runtime = tokio::runtime::Runtime::new().expect("a tokio runtime");
    let client = runtime.block_on(Client::connect(&server, ClientOptions::default())).expect("the client connects");
    let buffers = || runtime.block_on(client.buffers()).expect("the buffers");
    let args =
        [&trace[..], &formats, &["--reflect", "--primary-hits", &hits, "--hit-format", "t", "--out", &out]].concat();
    let rays_up = || buffers().iter().any(|buffer| buffer.size_bytes == rays_bytes);
    interrupt_when(&server, &args, |_| rays_up(), "the rays went up");
    assert!(buffers().is_empty(), "temporary buffers left behind: {:?}", buffers());
    // Hits from a pipe whose writer neither writes nor closes it: the read is given up at Ctrl-C.
    let args = [&trace[..], &formats, &["--reflect", "--primary-hits", "/dev/stdin", "--hit-format", "t"]].concat();
    interrupt_when(&server, &args, |_| rays_up(), "the rays went up, before the piped hits");
    assert!(buffers().is_empty(), "temporary buffers left behind: {:?}", buffers());
    let left = || std::fs::read_dir(&scratch.0).unwrap().map(|entry| entry.unwrap().file_name()).collect::<Vec<_>>();
    assert_eq!(left().len(), 2, "only the rays and their hits: {:?}", left());

    // `rayctl rays` too: interrupted while it writes beside `-o` (244 MiB of rays), it leaves nothing.
    let many = scratch.path("many.rays");
    let args = ["rays", "--accel", "bunny", "--random", "8000000", "-o", &many];
    interrupt_when(&server, &args, |_| left().len() > 2, "something was written beside -o");
    assert_eq!(left().len(), 2, "only the rays and their hits: {:?}", left());

    // `rayctl build` of a mesh larger than a message, whose arrays go up as temporary buffers: interrupted once the
    // first is up, it leaves no buffer (their deletes were cancelled as rayctl ended) and no accel, unless this test
    // saw the buffers only once the build had ended (a loaded machine), when the accel is whole.
    let args = ["build", "--mesh", "../shared/data/meshes/ogre.obj", "--name", "interrupted"];
    interrupt_when(&server, &args, |_| !buffers().is_empty(), "the mesh's first buffer went up");
    assert!(buffers().is_empty(), "temporary buffers left behind: {:?}", buffers());
    let accels = accel_names(&server);
    assert!(accels == ["bunny"] || accels == ["bunny", "interrupted"], "{accels:?}");

    // What a rayctl killed mid-call leaves is deleted with `rayctl rm-buffer`, by id or by name.
    let left = [("", Bytes::from_static(b"unnamed")), ("named", Bytes::from_static(b"named"))];
    let ids: Vec<String> =
        left.into_iter().map(|(name, data)| runtime.block_on(client.upload_buffer(name, data)).unwrap().id).collect();
    let deleted = json(&server, &["rm-buffer", &ids[0]]);
    assert_eq!((deleted["deleted"].as_str(), deleted["name"].as_str()), (Some(ids[0].as_str()), Some("")), "{deleted}");
    assert_eq!(json(&server, &["rm-buffer", "named"])["deleted"].as_str(), Some(ids[1].as_str()));
    assert!(buffers().is_empty(), "both deleted: {:?}", buffers());
    let refused = fails(&server, &["rm-buffer", ""], 1);
    assert!(refused.starts_with("error: InvalidArgument: rm-buffer: give a buffer's id or name"), "{refused}");
    let refused = fails(&server, &["rm-buffer", "named"], 1);
    assert!(refused.starts_with("error: NotFound: no buffer has id or name \"named\""), "{refused}");

    // Rays from a named pipe that no writer opens: Ctrl-C while rayctl waits in its open (a thread of it in the
    // openat system call, 257 on x86-64), then once it has opened it and its writer (this test) writes nothing.
    let fifo = scratch.path("rays.fifo");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let args = ["trace", "--accel", "bunny", "--rays", &fifo, "--ray-format", "origin_direction", "--hit-format", "t"];
    if cfg!(target_arch = "x86_64") {
        let in_openat = |pid: u32| {
            let threads = std::fs::read_dir(format!("/proc/{pid}/task")).into_iter().flatten().flatten();
            threads.into_iter().any(|thread| {
                std::fs::read_to_string(thread.path().join("syscall")).is_ok_and(|call| call.starts_with("257 "))
            })
        };
        // Still there 200 ms later: the pipe's open, not one of the quick ones before Ctrl-C is listened for.
        let in_openat = |pid: u32| {
            in_openat(pid) && {
                std::thread::sleep(std::time::Duration::from_millis(200));
                in_openat(pid)
            }
        };
        interrupt_when(&server, &args, in_openat, "rayctl waits to open the pipe");
        // Hits or rays into a named pipe that no reader opens: the same.
        let out_fifo = scratch.path("out.fifo");
        assert!(Command::new("mkfifo").arg(&out_fifo).status().unwrap().success());
        let args = [&trace[..], &formats, &["--hit-format", "t", "--out", &out_fifo]].concat();
        interrupt_when(&server, &args, in_openat, "rayctl waits to open the pipe of --out");
        let args = ["rays", "--accel", "bunny", "--random", "1000", "-o", &out_fifo];
        interrupt_when(&server, &args, in_openat, "rayctl waits to open the pipe of -o");
    }
    let writer = std::cell::RefCell::new(None);
    // Opening a pipe's writing end without waiting succeeds once it has a reader (Linux's O_NONBLOCK).
    let opened_by_rayctl = |_| {
        let open = std::fs::OpenOptions::new().write(true).custom_flags(0o4000).open(&fifo);
        open.map(|file| writer.replace(Some(file))).is_ok()
    };
    interrupt_when(&server, &args, opened_by_rayctl, "rayctl opened the pipe");
}

/// Runs rayctl with `args` (its standard input a pipe kept open and empty), sends it SIGINT (Ctrl-C) as soon as
/// `ready` holds of its process id (`what`, waited for up to 60 s), and checks that it ended within 30 s as a failure saying so.
fn interrupt_when(server: &str, args: &[&str], ready: impl Fn(u32) -> bool, what: &str) {
    let mut rayctl = rayctl_command(server, args)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let _open_stdin = rayctl.stdin.take();
    let waiting_since = std::time::Instant::now();
    while !ready(rayctl.id()) {
        assert!(waiting_since.elapsed().as_secs() < 60, "never: {what}");
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    // Stopped at once, so that the work left cannot end before the signal is seen (a trace of `rays` was once seen
    // to end first), then interrupted and continued: the pending SIGINT is delivered as it goes on.
    for signal in ["-STOP", "-INT", "-CONT"] {
        let sent = Command::new("kill").args([signal, &rayctl.id().to_string()]).status().unwrap();
        assert!(sent.success(), "kill {signal}");
    }
    let interrupted_at = std::time::Instant::now();
    while rayctl.try_wait().unwrap().is_none() {
        if interrupted_at.elapsed().as_secs() >= 30 {
            rayctl.kill().unwrap();
            panic!("rayctl went on for 30 s after Ctrl-C ({what})");
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let output = rayctl.wait_with_output().unwrap();
    assert_eq!(output.status.code(), Some(1), "{}", printed(&output));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.starts_with("error: Cancelled: interrupted by Ctrl-C"), "{stderr}");
}

#[test]
fn pictures_and_scans_larger_than_a_message_are_traced_in_ranges_into_the_same_files() {
    // 64 KiB messages: the picture's 83 KB of normals and the scan's points each pass a message, so that one call
    // cannot carry them.
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_MESSAGE_BYTES", "65536")]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-large-reductions");
    build_bunny(&server);

    let (width, height) = (96, 72);
    assert!(width * height * 12 > 65536, "the normals pass a message");
    let png_file = scratch.path("bunny.png");
    let size = [width.to_string(), height.to_string()];
    json(&server, &["render", "--accel", "bunny", "--width", &size[0], "--height", &size[1], "-o", &png_file]);
    let (png_width, png_height, _, pixels) = decode_png(&png_file);
    assert_eq!((png_width, png_height), (width, height));
    assert_same_bytes(&pixels, &bunny_picture(width, height), "the picture's pixels");

    // From the middle of the bunny's box, most rays of a narrow fan of channels hit it.
    let (lo, hi) = bunny().mesh.bounds();
    let lidar = Lidar {
        origin: (lo + hi) * 0.5,
        forward: Vec3::NEG_Z,
        up: Vec3::Y,
        elevations_degrees: (0..32).map(|c| -10.0 + 20.0 * c as f32 / 31.0).collect(),
        steps: 512,
        min_range: 0.0,
        max_range: f32::INFINITY,
        time: (0.0, 0.0),
    };
    let expected = bunny_scan(lidar.clone());
    assert!(expected.len() > 65536, "the points pass a message: {} bytes", expected.len());
    let ply_file = scratch.path("scan.ply");
    let origin = vec3_arg(lidar.origin);
    let args = ["--channels", "32", "--elevations", "-10,10", "--steps", "512", "--origin", &origin, "-o", &ply_file];
    let scanned = json(&server, &[&["lidar", "--accel", "bunny"][..], &args].concat());
    assert_eq!(scanned["rays"].as_u64(), Some(32 * 512), "{scanned}");
    assert_scan(&scanned, &read(&ply_file), &expected);
}

#[test]
fn bitmask_hits_of_parts_that_end_within_a_byte_are_written_as_one_bitmask() {
    // A server that traces at most 5 rays a batch: rayctl's parts end within a byte of the bitmask.
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_RAYS_PER_BATCH", "5")]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-bits");
    build_bunny(&server);
    let format = RayFormat::OriginDirection;
    let rays = bunny().camera_rays(format, 13, 7);
    let (rays_file, hits_file) = (scratch.path("camera.rays"), scratch.path("camera.bits"));
    std::fs::write(&rays_file, &rays).unwrap();
    let query = Query { kind: QueryKind::Any, ..Query::closest(format, HitFormat::Bitmask) };
    let expected = bunny().trace(&query, &rays);
    assert!(0 < expected.stats.rays_hit && expected.stats.rays_hit < expected.stats.rays, "rays hit and miss");
    let trace = ["trace", "--accel", "bunny", "--rays", &rays_file, "--ray-format", format.name()];
    let options = ["--query", "any", "--hit-format", "bitmask", "--out", &hits_file];
    let report = json(&server, &[&trace[..], &options].concat());
    assert_eq!(report["rays"].as_u64(), Some(91), "{report}");
    assert_same_bytes(&read(&hits_file), &expected.hits, "91 rays' bits from parts of 5 rays");
}

#[test]
fn a_ray_file_larger_than_a_message_is_traced_a_part_at_a_time_and_a_failed_trace_leaves_the_files_as_they_were() {
    // 64 KiB messages: the file's 2.9 MB of rays, and their hits, go in many parts each way.
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_MESSAGE_BYTES", "65536")]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-parts");
    build_bunny(&server);
    let format = RayFormat::OriginTminDirectionTmaxTime;
    // rayctl rays makes more rays than one of its parts (65,536), camera and random, as the engine makes them.
    let rays_file = scratch.path("camera.rays");
    let made = ["rays", "--accel", "bunny", "--ray-format", format.name(), "-o", &rays_file];
    json(&server, &[&made[..], &["--width", "320", "--height", "256", "--time", "0.25,0.75", "--seed", "9"]].concat());
    let mut rays = read(&rays_file);
    let mut camera = bunny().camera_rays(format, 320, 256);
    for (i, ray) in camera.chunks_exact_mut(format.size()).enumerate() {
        let time = 0.25 + 0.5 * uniform(9 ^ 0x7153, i as u64);
        ray[32..36].copy_from_slice(&time.to_le_bytes());
    }
    assert_same_bytes(&rays, &camera, "the camera's rays, each at its own time");
    json(&server, &[&made[..], &["--random", "70000", "--seed", "5"]].concat());
    let (lo, hi) = bunny().info().bounds;
    assert_same_bytes(&read(&rays_file), &random_rays(lo, hi, 70_000, 5, format), "the random rays");
    std::fs::write(&rays_file, &rays).unwrap();
    let query = Query { kind: QueryKind::All, max_hits_per_ray: 3, ..Query::closest(format, HitFormat::TTriid) };
    let expected = bunny().trace(&query, &rays);
    assert!(0 < expected.stats.rays_hit && expected.stats.rays_hit < expected.stats.rays, "rays hit and miss");
    let (hits_file, counts_file) = (scratch.path("camera.all"), scratch.path("camera.all.counts"));
    let args = [
        "trace",
        "--accel",
        "bunny",
        "--rays",
        &rays_file,
        "--ray-format",
        format.name(),
        "--hit-format",
        "t_triid",
        "--query",
        "all",
        "--max-hits",
        "3",
        "--out",
        &hits_file,
    ];
    let report = json(&server, &args);
    let count = |key: &str| report[key].as_u64().unwrap_or_else(|| panic!("a count {key:?} in {report}"));
    let stats = (count("rays"), count("hits"));
    expected.assert_answer(&read(&hits_file), &read(&counts_file), stats, "the files and the report");

    let (hits, counts) = (read(&hits_file), read(&counts_file));

    // The same rays through a pipe (rayctl cannot know their number before they end): the same files.
    let piped = [&args[..4], &["/dev/stdin"], &args[5..]].concat();
    let output = rayctl_command(&server, &piped).stdin(std::fs::File::open(&rays_file).unwrap()).output().unwrap();
    assert!(output.status.success(), "{}", printed(&output));
    assert!(read(&hits_file) == hits && read(&counts_file) == counts, "the piped rays' hits and counts");

    // An --out that is the ray file itself is refused: it would be overwritten while it is read.
    let stderr = fails(&server, &[&args[..args.len() - 1], &[&rays_file]].concat(), 1);
    assert!(
        stderr.starts_with(&format!("error: InvalidArgument: --out {rays_file}: is the file of --rays {rays_file}")),
        "{stderr}"
    );

    // Hits to standard output, itself a file: the file holds the hits alone, the report goes to standard error.
    // Counts have no file beside a device: refused.
    let other = Scratch::new("e2e-rayctl-stdout");
    let (file_out, stdout_out) = (other.path("closest.hits"), other.path("stdout.hits"));
    let closest = [&args[..9], &["--out"]].concat();
    json(&server, &[&closest[..], &[&file_out]].concat());
    let to_stdout = rayctl_command(&server, &[&closest[..], &["/dev/stdout"]].concat())
        .stdout(std::fs::File::create(&stdout_out).unwrap())
        .output()
        .unwrap();
    assert!(to_stdout.status.success(), "{}", printed(&to_stdout));
    assert!(read(&stdout_out) == read(&file_out), "only the hits on standard output");
    assert!(String::from_utf8_lossy(&to_stdout.stderr).contains(" rays, "), "{}", printed(&to_stdout));
    // Appended to (`>> file`): what the file held stays, the hits follow it.
    std::fs::write(&stdout_out, b"before").unwrap();
    let appended = rayctl_command(&server, &[&closest[..], &["/dev/stdout"]].concat())
        .stdout(std::fs::OpenOptions::new().append(true).open(&stdout_out).unwrap())
        .output()
        .unwrap();
    assert!(appended.status.success(), "{}", printed(&appended));
    assert!(read(&stdout_out) == [&b"before"[..], &read(&file_out)].concat(), "the hits after what was there");
    // To a pipe whose reader has gone (`| head -c 0`): rayctl ends quietly, as other tools do.
    let mut unread = rayctl_command(&server, &[&closest[..], &["/dev/stdout"]].concat())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(unread.stdout.take());
    let unread = unread.wait_with_output().unwrap();
    assert!(unread.status.success() && unread.stderr.is_empty(), "{}", printed(&unread));
    let stderr = fails(&server, &[&args[..args.len() - 1], &["/dev/null"]].concat(), 1);
    assert!(stderr.contains("--out /dev/null: the counts of this query go to /dev/null.counts"), "{stderr}");
    let counted = rayctl_command(&server, &[&args[..args.len() - 1], &["/dev/stdout"]].concat())
        .stdout(std::fs::File::create(&stdout_out).unwrap())
        .output()
        .unwrap();
    assert_eq!(counted.status.code(), Some(1), "{}", printed(&counted));
    assert!(
        String::from_utf8_lossy(&counted.stderr).contains("which standard output has not"),
        "{}",
        printed(&counted)
    );

    // A NaN time in the last ray: the server refuses its part after the parts before it were written.
    let last = rays.len() - 4;
    rays[last..].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&rays_file, &rays).unwrap();
    let stderr = fails(&server, &args, 1);
    // The message names the last part by its first ray, and the ray within it: together, the file's last ray.
    let numbers: Vec<u64> = stderr.split(|c: char| !c.is_ascii_digit()).filter_map(|n| n.parse().ok()).collect();
    assert!(
        stderr.starts_with("error: InvalidArgument: chunk from ray ") && stderr.contains("has time NaN"),
        "{stderr}"
    );
    assert!(matches!(numbers[..], [first, within] if first > 0 && first + within == 320 * 256 - 1), "{stderr}");
    assert!(read(&hits_file) == hits && read(&counts_file) == counts, "the earlier files stay as they were");
    let names: Vec<_> = std::fs::read_dir(scratch.path("")).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names.len(), 3, "no half-written file stays beside them: {names:?}");

    // Not whole rays: refused before anything is sent, naming the file.
    std::fs::write(&rays_file, &rays[..format.size() * 3 + 1]).unwrap();
    let stderr = fails(&server, &args, 1);
    let names =
        format!("error: InvalidArgument: --rays {rays_file}: 109 bytes is not a multiple of 36 ({})", format.name());
    assert!(stderr.starts_with(&names), "{stderr}");
}

/// The names of the server's accels, in creation order.
fn accel_names(server: &str) -> Vec<String> {
    let accels = json(server, &["accels"]);
    accels["accels"].as_array().expect("a list of accels").iter().map(|a| a["name"].as_str().unwrap().into()).collect()
}

#[test]
fn a_scene_that_fails_leaves_no_accel_behind_and_builds_once_its_cause_is_fixed() {
    // Five accels at most: a scene of three beside one of two cannot be kept whole.
    let daemon = Daemon::start(&[("RAYD_LIMITS_MAX_ACCELS", "5")]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-scene-failures");
    let meshes = std::fs::canonicalize("../shared/data/meshes").expect("the shared meshes");
    let (cow, teapot) = (meshes.join("cow.obj"), meshes.join("teapot.obj"));

    // A mesh file that is missing: refused before anything is built, naming the file.
    let missing = scratch.path("missing.obj");
    let scene = serde_json::json!({
        "meshes": { "a": cow, "b": missing },
        "instances": [{ "mesh": "a" }, { "mesh": "b", "translate": [3, 0, 0] }]
    });
    let half = scratch.path("half.json");
    std::fs::write(&half, scene.to_string()).unwrap();
    let refused = fails(&server, &["scene", "--file", &half], 1);
    assert!(refused.starts_with("error: NotFound: ") && refused.contains(&missing), "{refused}");
    assert_eq!(accel_names(&server), Vec::<String>::new(), "nothing built");
    std::fs::copy(&teapot, &missing).unwrap();
    succeeds(&server, &["scene", "--file", &half]);
    assert_eq!(accel_names(&server), ["half.a", "half.b", "half"]);

    // A build the server refuses after the scene's first accels (its instance accel, a sixth accel): the mesh and
    // the motion transform placing it are destroyed again, the transform first (the mesh cannot go while placed).
    let scene = serde_json::json!({
        "meshes": { "cow": cow },
        "instances": [{ "mesh": "cow", "motion": { "time": [0, 1], "keys": [{}, { "translate": [1, 0, 0] }] } }]
    });
    let moving = scratch.path("moving.json");
    std::fs::write(&moving, scene.to_string()).unwrap();
    let refused = fails(&server, &["scene", "--file", &moving], 1);
    assert!(refused.starts_with("error: ResourceExhausted: ") && refused.contains("max_accels"), "{refused}");
    assert_eq!(accel_names(&server), ["half.a", "half.b", "half"], "only what was there before");

    // A scene whose name is taken is refused before anything is built.
    succeeds(&server, &["build", "--mesh", teapot.to_str().unwrap(), "--name", "barn"]);
    let refused = fails(&server, &["scene", "--file", &moving, "--name", "barn"], 1);
    assert!(refused.starts_with("error: AlreadyExists: ") && refused.contains("barn"), "{refused}");
    assert_eq!(accel_names(&server), ["half.a", "half.b", "half", "barn"], "only what was there before");
    // Room made and the name freed, the same command builds.
    for name in ["barn", "half", "half.a"] {
        succeeds(&server, &["rm", name]);
    }
    let built = json(&server, &["scene", "--file", &moving, "--name", "barn"]);
    assert_eq!((built["name"].as_str(), built["instance_count"].as_u64()), (Some("barn"), Some(1)), "{built}");
    assert_eq!(accel_names(&server), ["half.b", "barn.cow", "barn.0.motion", "barn"]);
}

#[test]
fn ctrl_c_during_a_scene_destroys_what_it_built() {
    let daemon = Daemon::start(&[]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-scene-ctrl-c");
    let ogre = std::fs::canonicalize("../shared/data/meshes/ogre.obj").expect("the shared ogre");
    // Ctrl-C once the first of sixteen meshes is built.
    let scene = serde_json::json!({
        "meshes": (0..16).map(|m| (format!("m{m:02}"), serde_json::json!(ogre))).collect::<serde_json::Map<_, _>>(),
        "instances": (0..16).map(|m| serde_json::json!({ "mesh": format!("m{m:02}") })).collect::<Vec<_>>()
    });
    let many = scratch.path("many.json");
    std::fs::write(&many, scene.to_string()).unwrap();
    let first_built = |_| accel_names(&server).iter().any(|name| name.starts_with("many."));
    interrupt_when(&server, &["scene", "--file", &many], first_built, "the first mesh was built");
    assert_eq!(accel_names(&server), Vec::<String>::new(), "what was built is destroyed again");
}

#[test]
fn rays_more_than_rayctl_can_allocate_or_files_without_room_are_refused_naming_the_options() {
    let daemon = Daemon::start(&[]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-memory");
    build_bunny(&server);
    // 2^45 rays of 32 bytes (and 2^50 rays' 4-byte hits) pass any address space: no machine can hold them.
    let rays_file = scratch.path("random.rays");
    let args = ["bench", "--accel", "bunny", "--batch", "35184372088832", "--duration", "1"];
    let stderr = fails(&server, &args, 1);
    assert!(stderr.starts_with("error: ResourceExhausted: ") && stderr.contains("--batch 35184372088832 "), "{stderr}");
    assert!(stderr.contains("more than this process can allocate"), "{stderr}");
    // rayctl rays and trace hold a few parts, not the whole rays or hits: what they refuse is a file with no room.
    let stderr = fails(&server, &["rays", "--accel", "bunny", "--random", "35184372088832", "-o", &rays_file], 1);
    let names = format!(
        "{rays_file}: --random 35184372088832: 35184372088832 origin_tmin_direction_tmax rays take 1125899906842624 \
         bytes, more than the "
    );
    assert!(stderr.starts_with("error: ResourceExhausted: ") && stderr.contains(&names), "{stderr}");
    // Through a link to a plain file: refused before the file is emptied.
    let (kept, link) = (scratch.path("kept.rays"), scratch.path("link.rays"));
    std::fs::write(&kept, b"keep").unwrap();
    std::os::unix::fs::symlink(&kept, &link).unwrap();
    let stderr = fails(&server, &["rays", "--accel", "bunny", "--random", "35184372088832", "-o", &link], 1);
    assert!(stderr.starts_with(&format!("error: ResourceExhausted: {link}: --random 35184372088832: ")), "{stderr}");
    assert_eq!(read(&kept), b"keep", "the linked file is left as it was");
    let hits_file = scratch.path("huge.hits");
    let pixels = ["--pixels", "16384x16384", "--samples", "4194304"];
    let args = [&["trace", "--accel", "bunny", "--ray-format", "origin_direction", "--hit-format", "t"][..], &pixels];
    let stderr = fails(&server, &[&args.concat()[..], &["--out", &hits_file]].concat(), 1);
    let names = format!(
        "{hits_file}: --pixels 16384x16384 --samples 4194304: the hits and counts of 1125899906842624 rays take \
         4503599627370496 bytes, more than the "
    );
    assert!(stderr.starts_with("error: ResourceExhausted: ") && stderr.contains(&names), "{stderr}");
    assert!(stderr.trim_end().ends_with(" bytes free there"), "{stderr}");
    let mut names: Vec<_> = std::fs::read_dir(scratch.path("")).unwrap().map(|e| e.unwrap().file_name()).collect();
    names.sort();
    assert_eq!(names, ["kept.rays", "link.rays"], "no file written, none half-written beside them");
    let formats = ["--ray-format", "origin_direction", "--hit-format", "t"];
    let report =
        json(&server, &[&["trace", "--accel", "bunny", "--pixels", "64x48", "--samples", "2"][..], &formats].concat());
    assert_eq!(report["rays"], 64 * 48 * 2, "rayctl still traces what it can hold: {report}");
}

#[test]
fn a_missing_local_file_is_not_found_naming_it_whatever_the_file_holds() {
    let daemon = Daemon::start(&[]);
    let server = daemon.url();
    let scratch = Scratch::new("e2e-rayctl-missing-files");
    succeeds(&server, &["build", "--mesh", "../shared/data/meshes/cow.obj", "--name", "cow", "--allow-update"]);
    let (mesh, ply, rays, scene, points) = (
        scratch.path("missing.obj"),
        scratch.path("missing.ply"),
        scratch.path("missing.rays"),
        scratch.path("missing.json"),
        scratch.path("missing.points"),
    );
    let missing: [(&[&str], &str); 5] = [
        (&["build", "--mesh", &mesh], &mesh),
        (&["update", "cow", "--mesh", &ply], &ply),
        (&["trace", "--accel", "cow", "--rays", &rays, "--ray-format", "origin_direction", "--hit-format", "t"], &rays),
        (&["scene", "--file", &scene], &scene),
        (
            &["trace", "--accel", "cow", "--points", &points, "--ray-format", "origin_direction", "--hit-format", "t"],
            &points,
        ),
    ];
    for (args, file) in missing {
        let stderr = fails(&server, args, 1);
        assert!(stderr.starts_with(&format!("error: NotFound: {file}: ")), "{args:?}: {stderr}");
    }
    // A file that is there but no mesh of its format is the request's fault.
    let broken = scratch.path("broken.obj");
    std::fs::write(&broken, "f 1 2 3\n").unwrap();
    let stderr = fails(&server, &["build", "--mesh", &broken], 1);
    assert!(stderr.starts_with(&format!("error: InvalidArgument: {broken}: ")), "{stderr}");
    assert_eq!(accel_names(&server), ["cow"]);
}
