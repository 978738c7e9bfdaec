//! The real `rayd` for end-to-end tests: the workspace's binaries, built fresh once per test process by the test's
//! own profile, and a daemon started on port 0 with its own environment, stopped by SIGTERM like in production.
#![allow(dead_code)] // Each end-to-end test file uses its own part of the harness.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, PoisonError};

/// The workspace binaries the tests run.
const BINARIES: [&str; 2] = ["rayd", "rayctl"];

/// `target/<profile>`, where cargo puts the binaries: the test executable is `target/<profile>/deps/<test>`.
fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("the test executable's path");
    exe.parent().and_then(Path::parent).expect("the test executable is in target/<profile>/deps").to_path_buf()
}

/// The cargo target directory this test was built in.
pub fn target_dir() -> PathBuf {
    profile_dir().parent().expect("target/<profile> has a parent").to_path_buf()
}

/// The path of the workspace binary `name` (`rayd` or `rayctl`). The workspace's binaries are built once per test
/// process, with the profile and target directory of this test, so a test never runs a stale binary.
pub fn binary(name: &str) -> PathBuf {
    static BUILT: Mutex<bool> = Mutex::new(false);
    assert!(BINARIES.contains(&name), "no workspace binary {name:?}");
    let mut built = BUILT.lock().unwrap_or_else(PoisonError::into_inner);
    if !*built {
        cargo_build();
        *built = true;
    }
    profile_dir().join(format!("{name}{}", std::env::consts::EXE_SUFFIX))
}

/// Removes from `command`'s environment every `RAYD_…` variable of the test's own (`rayd` reads its configuration
/// from them, `rayctl` its server and token), so that only what a test sets reaches the binary.
pub fn without_rayd_env(command: &mut Command) -> &mut Command {
    for (key, _) in std::env::vars_os().filter(|(key, _)| key.as_encoded_bytes().starts_with(b"RAYD_")) {
        command.env_remove(key);
    }
    command
}

/// The variables cargo sets for a test process (names or name prefixes).
const TEST_ENV_PREFIXES: [&str; 8] = [
    "CARGO_MANIFEST_",
    "CARGO_PKG_",
    "CARGO_CRATE_NAME",
    "CARGO_BIN_NAME",
    "CARGO_PRIMARY_PACKAGE",
    "CARGO_TARGET_TMPDIR",
    "CARGO_RUSTC_CURRENT_DIR",
    "OUT_DIR",
];

/// Runs `cargo build --workspace --bins --tests` for this test's profile and target directory. The whole workspace
/// with its tests resolves dependency features exactly as `cargo test --workspace` does, so after that command only
/// the binaries themselves are compiled; a build of one package (`-p`) would rebuild many dependencies with that
/// package's own features (minutes, in CI).
fn cargo_build() {
    let profile_dir = profile_dir();
    let profile = profile_dir.file_name().and_then(|p| p.to_str()).expect("a UTF-8 profile directory");
    let mut cargo = Command::new(env!("CARGO"));
    cargo
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["build", "--workspace", "--bins", "--tests", "--target-dir"])
        .arg(target_dir());
    // `debug` holds the dev profile's output; every other profile's directory is named after it.
    if profile != "debug" {
        cargo.args(["--profile", profile]);
    }
    // What cargo set for this test process (its package's name, manifest, …) is not the caller's environment:
    // build scripts that watch such variables (ring's) would see a change and rebuild.
    for (key, _) in std::env::vars_os() {
        let key_text = key.to_string_lossy();
        if TEST_ENV_PREFIXES.iter().any(|prefix| key_text.starts_with(prefix)) {
            cargo.env_remove(&key);
        }
    }
    let output = cargo.output().expect("cargo runs");
    assert!(
        output.status.success(),
        "cargo build of the binaries failed:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

/// A running `rayd`; killed if still running when dropped, its log printed if the test failed (and deleted
/// otherwise).
pub struct Daemon {
    /// The process.
    child: Child,
    /// Its standard output, held open after the first line so that rayd never writes to a closed pipe.
    _stdout: BufReader<ChildStdout>,
    /// Where the gRPC service listens, from the first line.
    grpc: SocketAddr,
    /// Where the admin HTTP endpoint listens, from the first line.
    admin: SocketAddr,
    /// rayd's standard error (its log), kept in a file so it can never fill a pipe and block the daemon.
    log: PathBuf,
}

impl Daemon {
    /// Starts `rayd --listen 127.0.0.1:0 --admin-listen 127.0.0.1:0` with `envs` (e.g.
    /// `("RAYD_LIMITS_MAX_RAYS_PER_BATCH", "1000")`) and no other `RAYD_…` variable, and reads the addresses from
    /// the first line of its output.
    pub fn start(envs: &[(&str, &str)]) -> Daemon {
        static STARTED: AtomicUsize = AtomicUsize::new(0);
        let logs = Path::new(env!("CARGO_TARGET_TMPDIR")).join("rayd-logs");
        std::fs::create_dir_all(&logs).expect("the log directory can be created");
        let log = logs.join(format!("{}-{}.log", std::process::id(), STARTED.fetch_add(1, Ordering::Relaxed)));
        let mut command = Command::new(binary("rayd"));
        without_rayd_env(&mut command).args(["--listen", "127.0.0.1:0", "--admin-listen", "127.0.0.1:0"]);
        let stderr = std::fs::File::create(&log).expect("the log file can be created");
        let mut child = command
            .env("NO_COLOR", "1")
            .envs(envs.iter().copied())
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(stderr)
            .spawn()
            .expect("rayd starts");
        let mut stdout = BufReader::new(child.stdout.take().expect("piped stdout"));
        let mut line = String::new();
        stdout.read_line(&mut line).expect("rayd's standard output can be read");
        let Some((grpc, admin)) = parse_listening(&line) else {
            let _ = child.kill();
            let _ = child.wait();
            let log = std::fs::read_to_string(&log).unwrap_or_default();
            panic!("rayd's first line is {line:?}, not `rayd listening on grpc=… admin=…`; its log:\n{log}");
        };
        Daemon { child, _stdout: stdout, grpc, admin, log }
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Resident memory of the process now (`VmRSS` of `/proc/PID/status`), in bytes.
    pub fn resident_bytes(&self) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).expect("/proc/PID/status");
        let line = status.lines().find(|l| l.starts_with("VmRSS:")).expect("a VmRSS line");
        let kib: u64 = line.split_whitespace().nth(1).and_then(|v| v.parse().ok()).expect("VmRSS in kB");
        kib * 1024
    }

    /// The gRPC address.
    pub fn grpc_addr(&self) -> SocketAddr {
        self.grpc
    }

    /// A channel over one TCP connection to the gRPC service, and a handle on that connection to cut it as a
    /// vanishing client would.
    pub async fn cuttable_channel(&self) -> (tonic::transport::Channel, TcpStream) {
        let connection = TcpStream::connect(self.grpc).expect("rayd accepts connections");
        let kept = connection.try_clone().expect("the connection can be shared");
        connection.set_nonblocking(true).expect("a non-blocking connection");
        let mut connection = Some(connection);
        let connector = tower::service_fn(move |_| {
            let taken = connection.take().ok_or_else(|| std::io::Error::other("one connection only"));
            async move {
                let stream = tokio::net::TcpStream::from_std(taken?)?;
                Ok::<_, std::io::Error>(hyper_util::rt::TokioIo::new(stream))
            }
        });
        let channel = tonic::transport::Channel::from_shared(self.url()).expect("a valid URL");
        (channel.connect_with_connector(connector).await.expect("the channel connects"), kept)
    }

    /// The gRPC endpoint as a URL, `http://IP:PORT`, for tonic clients and `rayctl --server`.
    pub fn url(&self) -> String {
        format!("http://{}", self.grpc)
    }

    /// The body of an HTTP/1.0 GET of `path` on the admin endpoint; panics unless the status is 200.
    pub fn admin_get(&self, path: &str) -> String {
        let mut connection = TcpStream::connect(self.admin).expect("the admin endpoint accepts connections");
        write!(connection, "GET {path} HTTP/1.0\r\nHost: {}\r\n\r\n", self.admin).expect("the request is sent");
        let mut response = String::new();
        connection.read_to_string(&mut response).expect("the response is read to its end");
        let (head, body) = response.split_once("\r\n\r\n").unwrap_or_else(|| panic!("no HTTP head in {response:?}"));
        let status = head.lines().next().unwrap_or_default();
        assert!(status.split(' ').nth(1) == Some("200"), "GET {path}: {status}");
        body.to_string()
    }

    /// The sum of the Prometheus samples `name` whose labels include every one of `labels` (`key="value"`) on
    /// the admin endpoint's `/metrics` ([`sample`]), or `None` while there is no such series (a counter never
    /// incremented).
    pub fn metric(&self, name: &str, labels: &[&str]) -> Option<f64> {
        sample(&self.admin_get("/metrics"), name, labels)
    }

    /// Sends SIGTERM, the signal that starts a graceful shutdown, without waiting.
    pub fn terminate(&self) {
        let status = Command::new("kill").args(["-TERM", &self.child.id().to_string()]).status().expect("kill runs");
        assert!(status.success(), "kill -TERM {} failed", self.child.id());
    }

    /// Waits for the process to exit.
    pub fn wait(&mut self) -> ExitStatus {
        self.child.wait().expect("rayd can be waited for")
    }

    /// Waits for the process to exit, at most `limit` (a bound against hanging, not a measurement).
    pub fn wait_at_most(&mut self, limit: std::time::Duration) -> Option<ExitStatus> {
        let deadline = std::time::Instant::now() + limit;
        loop {
            if let Some(status) = self.child.try_wait().expect("rayd can be waited for") {
                return Some(status);
            }
            if std::time::Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }

    /// Kills the process with SIGKILL (`kill -9`: no chance to finish anything) and waits for it.
    pub fn kill(&mut self) {
        self.child.kill().expect("rayd can be killed");
        self.child.wait().expect("rayd can be waited for");
    }

    /// Sends SIGTERM and waits for the exit.
    pub fn stop(&mut self) -> ExitStatus {
        self.terminate();
        self.wait()
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
        if std::thread::panicking() {
            let log = std::fs::read_to_string(&self.log).unwrap_or_default();
            eprintln!("--- rayd log ({}) ---\n{log}", self.log.display());
        } else {
            let _ = std::fs::remove_file(&self.log);
        }
    }
}

/// The gRPC and admin addresses of `rayd listening on grpc=IP:PORT admin=IP:PORT`.
fn parse_listening(line: &str) -> Option<(SocketAddr, SocketAddr)> {
    let fields = line.trim_end().strip_prefix("rayd listening on ")?;
    let (grpc, admin) = fields.split_once(' ')?;
    Some((grpc.strip_prefix("grpc=")?.parse().ok()?, admin.strip_prefix("admin=")?.parse().ok()?))
}

/// The sum of the Prometheus samples `name` whose labels include every one of `labels` (`key="value"`): of a counter
/// with other labels besides (`code`, `device`), every series; none where no series matches.
pub fn sample(metrics: &str, name: &str, labels: &[&str]) -> Option<f64> {
    let values = metrics.lines().filter_map(|line| {
        let (series, value) = line.rsplit_once(' ')?;
        let (series_name, series_labels) = series.split_once('{').unwrap_or((series, ""));
        let matches = series_name == name && labels.iter().all(|label| series_labels.contains(label));
        matches.then(|| value.parse::<f64>().expect("a numeric sample"))
    });
    values.fold(None, |sum, value| Some(sum.unwrap_or(0.0) + value))
}
