//! Configuration: embedded defaults, overlaid by an optional TOML file, by `RAYD_…` environment variables and by
//! command-line flags, in that order.
//!
//! Every key of the file can also be set from the environment as `RAYD_<SECTION>_<KEY>` in upper case, e.g.
//! `RAYD_LIMITS_MAX_RAYS_PER_BATCH=1000000`; top-level keys as `RAYD_<KEY>` (`RAYD_LISTEN`).

mod tenants;
mod transport;

use std::net::SocketAddr;
use std::path::PathBuf;

use rayd_engine::geometry::motion::MAX_MOTION_KEYS;
use serde::{Deserialize, Serialize};
pub use tenants::{KeyConfig, MIN_KEY_CHARS, Role, TenantConfig};
pub use transport::TransportConfig;

/// The most worker threads a device's scheduler may be given.
pub const MAX_WORKERS: u32 = 1024;

/// The most traces a GPU device's scheduler may run at once.
pub const MAX_GPU_WORKERS: u32 = 16;

/// The longest piece time a scheduler may be given, in milliseconds.
pub const MAX_PIECE_MS: u32 = 60_000;

/// The least and the most bytes of device buffers one GPU trace may be given (1 MiB, 1 TiB).
pub const GPU_TRACE_BYTES: std::ops::RangeInclusive<u64> = 1 << 20..=1 << 40;

/// The least and the most node visits and triangle tests a ray may take on a GPU (2^10, 2^25): 64 rays of a
/// workgroup, each up to twice the most, keep the kernel's 32-bit statistics of the workgroup from wrapping, and
/// more would let a chunk pass its device's answer timeout (2^20 is seconds of an H100's thread).
pub const GPU_RAY_WORK: std::ops::RangeInclusive<u32> = 1 << 10..=1 << 25;

/// The least and the most node visits and triangle tests a ray may take on the CPU (2^10, 2^32 − 1).
pub const CPU_RAY_WORK: std::ops::RangeInclusive<u32> = 1 << 10..=u32::MAX;

/// Everything `rayd` can be configured with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Address of the gRPC service.
    pub listen: SocketAddr,
    /// Address of the admin HTTP endpoint (`/metrics`, `/healthz`); none (`off` in the file and the environment)
    /// disables it.
    #[serde(with = "address_or_off")]
    pub admin_listen: Option<SocketAddr>,
    /// Directory where every buffer and accel is persisted and restored from at start; none (empty in the file and
    /// the environment, so that `RAYD_DATA_DIR=` switches a file's off) keeps them in memory only.
    pub data_dir: Option<PathBuf>,
    /// Log output: `text` or `json`.
    pub log_format: String,
    /// After SIGTERM, how long calls in flight (and open streams, such as health watches) may go on before rayd
    /// exits anyway.
    pub shutdown_grace_seconds: u64,
    /// Request limits (of the default tenant, and of configured tenants where they set none of their own).
    pub limits: Limits,
    /// Tenants and their API keys. None: one default tenant, no authentication (for loopback use).
    pub tenants: Vec<TenantConfig>,
    /// TLS for the gRPC service; none serves plaintext.
    pub tls: Option<TlsConfig>,
    /// Allow a non-loopback `listen` without authentication (`--insecure`).
    pub insecure: bool,
    /// How device work is scheduled.
    pub scheduler: SchedulerConfig,
    /// HTTP/2 limits of the gRPC connections.
    pub transport: TransportConfig,
    /// Ask Linux for 2 MiB pages for the arrays that CPU traversals read at random (the wide nodes and corner blocks
    /// of geometry accels of 2 MiB or more): incoherent rays through large scenes wait less for page-table walks.
    /// Only advice to the kernel (transparent huge pages in `madvise` or `always` mode); no memory is added.
    pub large_pages: bool,
}

/// The fair schedulers of the devices (traces are queued per tenant and served by share; see `tenants.share`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SchedulerConfig {
    /// Threads that trace on the CPU device, 0 to 1024; 0: one per core.
    pub workers: u32,
    /// Traces a GPU device runs at once, 1 to 16: with two, one trace's host work (its first chunk's submission,
    /// its last chunk's results copied out, its reduction finished) overlaps another's kernels (BENCHMARKS.md,
    /// "Two traces at once on a GPU"); each trace in flight holds its own staging buffers.
    pub gpu_workers: u32,
    /// The tracing threads' nice value, 0 to 19 (Linux): above the threads that receive calls and send answers, so
    /// those get a core at once and small traces are not held up behind large ones on a busy machine.
    pub worker_nice: u32,
    /// About how long one piece of a trace may hold a CPU worker, in milliseconds, 1 to 60,000: rays that cost more
    /// than usual are traced in pieces of fewer rays, so that another tenant's trace waits about this long for a
    /// running piece (longer where one granule of rays costs more, or where a trace's first piece is sized by an
    /// earlier trace of cheaper rays of the same accel and query kind).
    pub piece_ms: u32,
    /// The same for a GPU device, 1 to 60,000 (a piece holds one of its workers and its queue); a GPU piece keeps at
    /// least 2^18 rays (the wgpu backend's chunk) however long they take.
    pub gpu_piece_ms: u32,
    /// Bytes of device buffers one GPU trace holds at most (its two chunks' rays, hits, `all` scratch and staging),
    /// 1 MiB to 1 TiB: chunks of many hits a ray are cut to fit, and a query whose 32-ray chunks cannot is
    /// RESOURCE_EXHAUSTED naming this key. `gpu_workers` times this bounds what traces take of a GPU's memory (and,
    /// for their staging, of the host's), besides 256 MiB of idle buffers kept for later traces (which a trace may
    /// take up and grow).
    pub gpu_trace_bytes: u64,
    /// Node visits and triangle tests one ray may take on a GPU, 2^10 to 2^25: a GPU walks a ray to its end once
    /// started, holding the device from every other trace meanwhile (and a chunk that takes a minute takes the
    /// device as hung), so a trace with a ray that would take more is RESOURCE_EXHAUSTED naming this key. The
    /// default, 2^20, is hundreds of times what a ray through an ordinary scene takes, and seconds of a GPU thread.
    pub gpu_ray_work: u32,
    /// Node visits and triangle tests one ray may take on the CPU (16 times it a group of up to 16 neighbouring rays
    /// traced together), 2^10 to 2^32 − 1: an instance graph multiplies a ray's work level by level, and a piece of a
    /// trace cannot be stopped once it runs (it would hold a worker, or a thread that answers calls, for hours), so
    /// a ray past this enters no more instances and its trace is RESOURCE_EXHAUSTED naming this key. The default,
    /// 2^20, is the GPU's.
    pub cpu_ray_work: u32,
}

impl Default for SchedulerConfig {
    fn default() -> Self {
        SchedulerConfig {
            workers: 0,
            gpu_workers: 2,
            worker_nice: 10,
            piece_ms: 10,
            gpu_piece_ms: 100,
            gpu_trace_bytes: 1 << 30,
            gpu_ray_work: rayd_engine::backend::DEFAULT_MAX_RAY_WORK,
            cpu_ray_work: rayd_engine::backend::DEFAULT_MAX_RAY_WORK,
        }
    }
}

impl SchedulerConfig {
    /// Checks every value against its range, naming the first one outside it.
    fn check(&self) -> Result<(), String> {
        if self.workers > MAX_WORKERS {
            return Err(format!("scheduler.workers = {} must be 0 (one per core) to {MAX_WORKERS}", self.workers));
        }
        if !(1..=MAX_GPU_WORKERS).contains(&self.gpu_workers) {
            return Err(format!("scheduler.gpu_workers = {} must be 1 to {MAX_GPU_WORKERS}", self.gpu_workers));
        }
        if self.worker_nice > 19 {
            return Err(format!("scheduler.worker_nice = {} must be 0 to 19", self.worker_nice));
        }
        for (name, ms) in [("piece_ms", self.piece_ms), ("gpu_piece_ms", self.gpu_piece_ms)] {
            if !(1..=MAX_PIECE_MS).contains(&ms) {
                return Err(format!("scheduler.{name} = {ms} must be 1 to {MAX_PIECE_MS}"));
            }
        }
        if !GPU_TRACE_BYTES.contains(&self.gpu_trace_bytes) {
            let (least, most) = GPU_TRACE_BYTES.into_inner();
            return Err(format!("scheduler.gpu_trace_bytes = {} must be {least} to {most}", self.gpu_trace_bytes));
        }
        if !GPU_RAY_WORK.contains(&self.gpu_ray_work) {
            let (least, most) = GPU_RAY_WORK.into_inner();
            return Err(format!("scheduler.gpu_ray_work = {} must be {least} to {most}", self.gpu_ray_work));
        }
        if !CPU_RAY_WORK.contains(&self.cpu_ray_work) {
            let (least, most) = CPU_RAY_WORK.into_inner();
            return Err(format!("scheduler.cpu_ray_work = {} must be {least} to {most}", self.cpu_ray_work));
        }
        Ok(())
    }
}

/// TLS of the gRPC service (rustls).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// The server's certificate chain, PEM.
    pub cert: PathBuf,
    /// Its private key, PEM.
    pub key: PathBuf,
    /// With it, clients must present a certificate signed by one of these CAs (mutual TLS), PEM.
    pub client_ca: Option<PathBuf>,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            listen: "127.0.0.1:50051".parse().expect("valid address"),
            admin_listen: Some("127.0.0.1:9464".parse().expect("valid address")),
            data_dir: None,
            log_format: "text".into(),
            shutdown_grace_seconds: 30,
            limits: Limits::default(),
            tenants: Vec::new(),
            tls: None,
            insecure: false,
            scheduler: SchedulerConfig::default(),
            transport: TransportConfig::default(),
            large_pages: true,
        }
    }
}

/// Most products a stream may be configured to remember ([`Limits::max_stream_products`]).
const MAX_STREAM_PRODUCTS: u32 = 1 << 24;

/// Limits that protect the server; a request beyond one is refused before anything is allocated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Limits {
    /// Largest gRPC message, in either direction (bytes). Server-wide: the gRPC layer applies it to every call
    /// before the caller's tenant is known, so a tenant's `limits` may not set another.
    pub max_message_bytes: u64,
    /// Most rays in one `TraceBatch` call or one `TraceStream` chunk.
    pub max_rays_per_batch: u64,
    /// Largest `max_hits_per_ray` of an `all` query.
    pub max_hits_per_ray: u32,
    /// Largest accel, by `compute_memory_usage`'s output bound (bytes).
    pub max_accel_bytes: u64,
    /// Most accels per tenant.
    pub max_accels: u32,
    /// Largest buffer (bytes).
    pub max_buffer_bytes: u64,
    /// Most buffers per tenant, those being made (uploads, traces into buffers) counted.
    pub max_buffers: u32,
    /// Per `TraceStream`: chunks read ahead of the one being traced, and answers waiting to be sent. Per
    /// `OpenStream` stream: messages read ahead of the running operation, and answers waiting to be sent. 0 is
    /// taken as 1 ([`Limits::window`]).
    pub stream_window: u32,
    /// Seconds a `TraceStream`, `OpenStream` or `DownloadBuffer` stream waits with its answers unread (all
    /// `stream_window` places full) before it is failed with RESOURCE_EXHAUSTED and the answers it holds are
    /// dropped; 0 waits as long as the call lasts.
    pub stream_stall_seconds: u64,
    /// Most streams (`OpenStream`, `TraceStream` and `DownloadBuffer` calls) open at once per tenant.
    pub max_streams: u32,
    /// Deepest traversable graph an accel may head (a geometry accel is 1 level, each instance accel or transform
    /// above it 1 more); 1 to 8.
    pub max_graph_depth: u32,
    /// Most motion keys of one accel or motion transform; 1 to 1024.
    pub max_motion_keys: u32,
    /// Most bytes of all of a tenant's accels together.
    pub max_total_accel_bytes: u64,
    /// Most bytes of all of a tenant's buffers together, those being made counted (an upload by its declared size,
    /// a trace into buffers by its output's).
    pub max_total_buffer_bytes: u64,
    /// Rays a tenant may trace per second, averaged over a second (a batch may exceed the rest of the second's
    /// allowance; the next ones are refused with RESOURCE_EXHAUSTED until it refills); 0 means no limit.
    pub max_rays_per_second: u64,
    /// Builds, updates, copies, loads, saves and traces a tenant may have running at once.
    pub max_concurrent_operations: u32,
    /// Per `OpenStream` stream: the creating operations (uploads, builds, copies, traces into buffers) whose
    /// products, or failures, later operations may name by operation id; older ones are forgotten. 1 to 2^24.
    pub max_stream_products: u32,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_message_bytes: 64 << 20,
            max_rays_per_batch: 1 << 24,
            max_hits_per_ray: 256,
            max_accel_bytes: 8 << 30,
            max_accels: 1024,
            max_buffer_bytes: 4 << 30,
            max_buffers: 4096,
            stream_window: 4,
            stream_stall_seconds: 60,
            max_streams: 64,
            max_graph_depth: rayd_engine::geometry::MAX_GRAPH_DEPTH,
            max_motion_keys: 64,
            max_total_accel_bytes: 32 << 30,
            max_total_buffer_bytes: 16 << 30,
            max_rays_per_second: 0,
            max_concurrent_operations: 64,
            max_stream_products: 4096,
        }
    }
}

impl Limits {
    /// The stream window in force: [`Limits::stream_window`], at least 1 (a stream reads one message at a time).
    pub fn window(&self) -> u32 {
        self.stream_window.max(1)
    }

    /// How long a stream's answers may wait unread ([`Limits::stream_stall_seconds`]); `None` for no limit.
    pub fn stream_stall(&self) -> Option<std::time::Duration> {
        (self.stream_stall_seconds > 0).then(|| std::time::Duration::from_secs(self.stream_stall_seconds))
    }

    /// Checks the limits that have a range; errors name the key under `section`.
    fn check(&self, section: &str) -> Result<(), String> {
        let depth = self.max_graph_depth;
        if !(1..=rayd_engine::geometry::MAX_GRAPH_DEPTH).contains(&depth) {
            return Err(format!(
                "{section}.max_graph_depth = {depth} must be 1 to {}",
                rayd_engine::geometry::MAX_GRAPH_DEPTH
            ));
        }
        let keys = self.max_motion_keys;
        if !(1..=MAX_MOTION_KEYS).contains(&keys) {
            return Err(format!("{section}.max_motion_keys = {keys} must be 1 to {MAX_MOTION_KEYS}"));
        }
        let products = self.max_stream_products;
        if !(1..=MAX_STREAM_PRODUCTS).contains(&products) {
            return Err(format!("{section}.max_stream_products = {products} must be 1 to {MAX_STREAM_PRODUCTS}"));
        }
        Ok(())
    }
}

/// Why a configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("config file {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file or an environment variable holds a bad value.
    #[error("config: {0}")]
    Invalid(String),
}

impl Config {
    /// Builds the configuration from the embedded defaults, the TOML `file` if given, then every `RAYD_…` variable
    /// of `env` that names a key.
    pub fn load(
        file: Option<&std::path::Path>,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Config, ConfigError> {
        let mut table = toml::Table::try_from(Config::default()).map_err(|e| ConfigError::Invalid(e.to_string()))?;
        if let Some(path) = file {
            let text =
                std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.into(), source })?;
            let overlay: toml::Table =
                text.parse().map_err(|e| ConfigError::Invalid(format!("{}: {e}", path.display())))?;
            merge(&mut table, overlay);
        }
        let env: Vec<(String, String)> = env.into_iter().filter(|(k, _)| k.starts_with("RAYD_")).collect();
        overlay_env(&mut table, "RAYD", &env)?;
        overlay_optional_env(&mut table, &env);
        inherit_limits(&mut table);
        let mut config: Config = table.try_into().map_err(|e: toml::de::Error| ConfigError::Invalid(e.to_string()))?;
        config.data_dir = config.data_dir.and_then(Config::directory_or_none);
        config.limits.check("limits").map_err(ConfigError::Invalid)?;
        config.transport.check().map_err(ConfigError::Invalid)?;
        config.scheduler.check().map_err(ConfigError::Invalid)?;
        for (i, tenant) in config.tenants.iter().enumerate() {
            tenant.limits.check(&format!("tenants[{i}].limits")).map_err(ConfigError::Invalid)?;
            let (own, server) = (tenant.limits.max_message_bytes, config.limits.max_message_bytes);
            if own != server {
                return Err(ConfigError::Invalid(format!(
                    "tenants[{i}].limits.max_message_bytes = {own}: the gRPC layer's limit is one for every tenant; \
                     set it under [limits] (now {server})"
                )));
            }
        }
        tenants::check(&config.tenants).map_err(ConfigError::Invalid)?;
        Ok(config)
    }

    /// `dir` as a data directory: none where it is empty.
    pub fn directory_or_none(dir: PathBuf) -> Option<PathBuf> {
        (!dir.as_os_str().is_empty()).then_some(dir)
    }
}

impl Config {
    /// Refuses a non-loopback `listen` without authentication (no tenants) unless `insecure` is set.
    pub fn check_exposure(&self) -> Result<(), ConfigError> {
        if !self.listen.ip().is_loopback() && self.tenants.is_empty() && !self.insecure {
            return Err(ConfigError::Invalid(format!(
                "refusing to listen on {} without authentication: configure [[tenants]] with keys, or pass \
                 --insecure (RAYD_INSECURE=true) to serve anyone who can reach it",
                self.listen
            )));
        }
        Ok(())
    }
}

/// Gives each tenant the server's `[limits]` under the keys it sets itself.
fn inherit_limits(table: &mut toml::Table) {
    let Some(toml::Value::Table(server)) = table.get("limits").cloned() else { return };
    let Some(toml::Value::Array(tenants)) = table.get_mut("tenants") else { return };
    for tenant in tenants {
        let Some(tenant) = tenant.as_table_mut() else { continue };
        let own = match tenant.remove("limits") {
            Some(toml::Value::Table(own)) => own,
            _ => toml::Table::new(),
        };
        let mut limits = server.clone();
        merge(&mut limits, own);
        tenant.insert("limits".into(), toml::Value::Table(limits));
    }
}

/// Copies every key of `overlay` into `base`, descending into tables.
fn merge(base: &mut toml::Table, overlay: toml::Table) {
    for (key, value) in overlay {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(inner)), toml::Value::Table(value)) => merge(inner, value),
            (_, value) => {
                base.insert(key, value);
            }
        }
    }
}

/// Sets each key of `table` for which `PREFIX_KEY` is in `env`. Values are read as TOML integers and booleans
/// (`true`, `false`) and otherwise taken as strings (addresses, paths).
fn overlay_env(table: &mut toml::Table, prefix: &str, env: &[(String, String)]) -> Result<(), ConfigError> {
    let keys: Vec<String> = table.keys().cloned().collect();
    for key in keys {
        let name = format!("{prefix}_{}", key.to_uppercase());
        if let Some(toml::Value::Table(inner)) = table.get_mut(&key) {
            overlay_env(inner, &name, env)?;
            continue;
        }
        if let Some((_, raw)) = env.iter().find(|(k, _)| *k == name) {
            let value = match (raw.parse::<i64>(), raw.parse::<bool>()) {
                (Ok(integer), _) => toml::Value::Integer(integer),
                (_, Ok(boolean)) => toml::Value::Boolean(boolean),
                _ => toml::Value::String(raw.clone()),
            };
            table.insert(key, value);
        }
    }
    Ok(())
}

/// An optional address as the file and the environment write it: the address, or `off` for none.
mod address_or_off {
    use std::net::SocketAddr;

    use serde::{Deserialize, Deserializer, Serializer};

    /// The word for none.
    const OFF: &str = "off";

    /// Writes `address`, or `off`.
    pub fn serialize<S: Serializer>(address: &Option<SocketAddr>, serializer: S) -> Result<S::Ok, S::Error> {
        match address {
            Some(address) => serializer.collect_str(address),
            None => serializer.serialize_str(OFF),
        }
    }

    /// Reads an address, or `off`.
    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<SocketAddr>, D::Error> {
        let text = String::deserialize(deserializer)?;
        if text == OFF {
            return Ok(None);
        }
        let address = text.parse().map_err(|e| serde::de::Error::custom(format!("{text:?}: {e} (or \"{OFF}\")")))?;
        Ok(Some(address))
    }
}

/// The keys that may hold nothing, as their paths from the top of the file: absent from the defaults' table when
/// none, so [`overlay_env`] cannot find them there.
const OPTIONAL_KEYS: [&[&str]; 4] = [&["data_dir"], &["tls", "cert"], &["tls", "key"], &["tls", "client_ca"]];

/// Sets each of [`OPTIONAL_KEYS`] for which `RAYD_<PATH>` is in `env` (as a string), making the tables on its path.
fn overlay_optional_env(table: &mut toml::Table, env: &[(String, String)]) {
    'keys: for path in OPTIONAL_KEYS {
        let name = format!("RAYD_{}", path.join("_").to_uppercase());
        let Some((_, raw)) = env.iter().find(|(k, _)| *k == name) else { continue };
        let (key, sections) = path.split_last().expect("a key's path is not empty");
        let mut inner = &mut *table;
        for section in sections {
            let entry = inner.entry(section.to_string()).or_insert_with(|| toml::Value::Table(toml::Table::new()));
            // A file that made the section something else is refused as it is when the file is read.
            let Some(section_table) = entry.as_table_mut() else { continue 'keys };
            inner = section_table;
        }
        inner.insert(key.to_string(), toml::Value::String(raw.clone()));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
        pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect()
    }

    #[test]
    fn defaults_need_nothing() {
        let config = Config::load(None, env(&[("HOME", "/root")])).unwrap();
        assert_eq!(config, Config::default());
        assert_eq!(config.listen.to_string(), "127.0.0.1:50051");
    }

    #[test]
    fn file_then_environment_override_defaults() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rayd.toml");
        std::fs::write(&path, "listen = \"0.0.0.0:7000\"\n[limits]\nmax_rays_per_batch = 1000\nmax_buffers = 3\n")
            .unwrap();
        let config = Config::load(
            Some(&path),
            env(&[
                ("RAYD_LIMITS_MAX_BUFFERS", "9"),
                ("RAYD_ADMIN_LISTEN", "127.0.0.1:1"),
                ("RAYD_LARGE_PAGES", "false"),
            ]),
        )
        .unwrap();
        assert_eq!(config.listen.to_string(), "0.0.0.0:7000");
        assert_eq!(config.limits.max_rays_per_batch, 1000);
        assert_eq!(config.limits.max_buffers, 9);
        assert_eq!(config.admin_listen.unwrap().to_string(), "127.0.0.1:1");
        assert!(!config.large_pages && Config::default().large_pages);
    }

    #[test]
    fn tenants_inherit_the_server_limits_they_do_not_set_and_bad_tenants_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rayd.toml");
        let good = r#"
            [limits]
            max_buffers = 7
            [[tenants]]
            name = "acme"
            keys = [{ key = "0123456789abcdef", role = "write" }, { key = "fedcba9876543210", role = "read" }]
            limits = { max_accels = 3 }
        "#;
        std::fs::write(&path, good).unwrap();
        let config = Config::load(Some(&path), env(&[])).unwrap();
        let acme = &config.tenants[0];
        assert_eq!((acme.limits.max_accels, acme.limits.max_buffers), (3, 7), "its own, then the server's");
        assert_eq!(acme.keys[1].role, Role::Read);
        assert_eq!(acme.share, 1, "the default share");
        for (bad, why) in [
            (good.replace("fedcba9876543210", "0123456789abcdef"), "unique"),
            (good.replace("\"fedcba9876543210\"", "\"short\""), "shorter than 16"),
            (good.replace("\"acme\"", "\"a/b\""), "[A-Za-z0-9._-]"),
            (good.replace("role = \"read\"", "role = \"root\""), "root"),
            (good.replace("max_accels = 3", "max_graph_depth = 9"), "tenants[0].limits.max_graph_depth"),
            (good.replace("max_accels = 3", "max_message_bytes = 1048576"), "tenants[0].limits.max_message_bytes"),
            (good.replace("name = \"acme\"", "name = \"acme\"\nshare = 0"), "tenants[0].share = 0 must be 1 to 1000"),
            (
                format!(
                    "{good}\n[[tenants]]\nname = \"ACME\"\nkeys = [{{ key = \"0000111122223333\", role = \"read\" }}]"
                ),
                "tenants[1].name \"ACME\" is used twice (\"acme\"; names are compared without case)",
            ),
        ] {
            std::fs::write(&path, bad).unwrap();
            let error = Config::load(Some(&path), env(&[])).unwrap_err().to_string();
            assert!(error.contains(why), "{why}: {error}");
        }
    }

    #[test]
    fn keys_that_may_hold_nothing_are_set_from_the_environment_too() {
        let tls = [("RAYD_TLS_CERT", "/etc/rayd/cert.pem"), ("RAYD_TLS_KEY", "/etc/rayd/key.pem")];
        let config = Config::load(None, env(&[tls[0], tls[1], ("RAYD_DATA_DIR", "/data")])).unwrap();
        let expected =
            TlsConfig { cert: "/etc/rayd/cert.pem".into(), key: "/etc/rayd/key.pem".into(), client_ca: None };
        assert_eq!(config.tls, Some(expected));
        assert_eq!(config.data_dir, Some(PathBuf::from("/data")));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rayd.toml");
        std::fs::write(&path, "data_dir = \"/var/lib/rayd\"").unwrap();
        let switched_off = Config::load(Some(&path), env(&[("RAYD_DATA_DIR", "")])).unwrap();
        assert_eq!(switched_off.data_dir, None, "an empty directory is none");
        let half = Config::load(None, env(&tls[..1])).unwrap_err().to_string();
        assert!(half.contains("key"), "{half}");
        let off = Config::load(None, env(&[("RAYD_ADMIN_LISTEN", "off")])).unwrap();
        assert_eq!((off.admin_listen, Config::default().admin_listen.is_some()), (None, true));
        let moved = Config::load(None, env(&[("RAYD_ADMIN_LISTEN", "127.0.0.1:9000")])).unwrap();
        assert_eq!(moved.admin_listen, Some("127.0.0.1:9000".parse().unwrap()));
    }

    #[test]
    fn unknown_keys_and_bad_values_are_errors_naming_them() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rayd.toml");
        std::fs::write(&path, "[limits]\nmax_rayz = 1\n").unwrap();
        let error = Config::load(Some(&path), env(&[])).unwrap_err().to_string();
        assert!(error.contains("max_rayz"), "{error}");
        let error = Config::load(None, env(&[("RAYD_LIMITS_MAX_BUFFERS", "lots")])).unwrap_err().to_string();
        assert!(error.contains("max_buffers"), "{error}");
        for (value, error) in [("0", Some("scheduler.gpu_workers = 0 must be 1 to 16")), ("16", None)] {
            let loaded = Config::load(None, env(&[("RAYD_SCHEDULER_GPU_WORKERS", value)]));
            match error {
                Some(error) => assert_eq!(loaded.unwrap_err().to_string(), format!("config: {error}")),
                None => assert_eq!(loaded.unwrap().scheduler.gpu_workers, 16),
            }
        }
        for (key, value, error) in [
            ("RAYD_SCHEDULER_PIECE_MS", "0", "scheduler.piece_ms = 0 must be 1 to 60000"),
            ("RAYD_SCHEDULER_GPU_PIECE_MS", "60001", "scheduler.gpu_piece_ms = 60001 must be 1 to 60000"),
            ("RAYD_SCHEDULER_WORKER_NICE", "20", "scheduler.worker_nice = 20 must be 0 to 19"),
            (
                "RAYD_SCHEDULER_GPU_TRACE_BYTES",
                "1048575",
                "scheduler.gpu_trace_bytes = 1048575 must be 1048576 to 1099511627776",
            ),
            ("RAYD_SCHEDULER_GPU_RAY_WORK", "1023", "scheduler.gpu_ray_work = 1023 must be 1024 to 33554432"),
            ("RAYD_SCHEDULER_CPU_RAY_WORK", "1023", "scheduler.cpu_ray_work = 1023 must be 1024 to 4294967295"),
        ] {
            let error_message = Config::load(None, env(&[(key, value)])).unwrap_err().to_string();
            assert_eq!(error_message, format!("config: {error}"));
        }
        let edges = [
            ("RAYD_SCHEDULER_GPU_PIECE_MS", "60000"),
            ("RAYD_SCHEDULER_GPU_TRACE_BYTES", "1048576"),
            ("RAYD_SCHEDULER_GPU_RAY_WORK", "33554432"),
            ("RAYD_SCHEDULER_CPU_RAY_WORK", "1024"),
        ];
        let scheduler = Config::load(None, env(&edges)).unwrap().scheduler;
        assert_eq!(
            (scheduler.gpu_piece_ms, scheduler.gpu_trace_bytes, scheduler.gpu_ray_work, scheduler.cpu_ray_work),
            (60_000, 1 << 20, 1 << 25, 1 << 10)
        );
    }
}
