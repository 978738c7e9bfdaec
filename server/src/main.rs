//! `rayd [--listen ADDR] [--admin-listen ADDR] [--config FILE] [--data-dir DIR] [--insecure]`: reads the
//! configuration, binds, prints where it listens, and serves until SIGTERM or Ctrl-C.

use std::net::SocketAddr;
use std::path::PathBuf;

use clap::Parser;
use clap::builder::TypedValueParser;
use rayd_server::Config;
use tokio::net::TcpListener;

/// mimalloc keeps freed pages for reuse: large ray and hit messages then cost no fresh page faults each call.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Command-line flags; each also reads its `RAYD_…` variable. Flags win over the file and the environment.
#[derive(Debug, Parser)]
#[command(version, about = "rayd: a ray-tracing service daemon")]
struct Cli {
    /// Address of the gRPC service [default: 127.0.0.1:50051].
    #[arg(long, env = "RAYD_LISTEN")]
    listen: Option<SocketAddr>,
    /// Address of the admin HTTP endpoint (/metrics, /healthz) [default: 127.0.0.1:9464]; "off" disables it.
    #[arg(long, env = "RAYD_ADMIN_LISTEN")]
    admin_listen: Option<String>,
    /// TOML configuration file.
    #[arg(long, env = "RAYD_CONFIG")]
    config: Option<PathBuf>,
    /// Directory for persisted state; empty for none (over the file's).
    #[arg(long, env = "RAYD_DATA_DIR", value_parser = clap::builder::OsStringValueParser::new().map(PathBuf::from))]
    data_dir: Option<PathBuf>,
    /// Allow listening on a non-loopback address without authentication (no tenants configured).
    #[arg(long, env = "RAYD_INSECURE")]
    insecure: bool,
}

/// Loads the configuration: defaults, file, environment, then flags.
fn configure(cli: Cli) -> Result<Config, Box<dyn std::error::Error + Send + Sync>> {
    let mut config = Config::load(cli.config.as_deref(), std::env::vars())?;
    if let Some(listen) = cli.listen {
        config.listen = listen;
    }
    match cli.admin_listen.as_deref() {
        None => {}
        Some("off") => config.admin_listen = None,
        Some(address) => {
            config.admin_listen = Some(address.parse().map_err(|e| format!("--admin-listen {address:?}: {e}"))?)
        }
    }
    if let Some(dir) = cli.data_dir {
        config.data_dir = Config::directory_or_none(dir);
    }
    config.insecure |= cli.insecure;
    config.check_exposure()?;
    Ok(config)
}

/// Completes on SIGTERM or Ctrl-C.
async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term =
            tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).expect("SIGTERM handler");
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
}

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let config = configure(Cli::parse())?;
    let filter = tracing_subscriber::EnvFilter::try_from_env("RAYD_LOG").unwrap_or_else(|_| "info".into());
    let logs = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    match config.log_format.as_str() {
        "json" => logs.json().init(),
        "text" => logs.init(),
        other => return Err(format!("log_format {other:?}: must be \"text\" or \"json\"").into()),
    }
    let listener = TcpListener::bind(config.listen).await.map_err(|e| format!("--listen {}: {e}", config.listen))?;
    let admin = match config.admin_listen {
        Some(address) => Some(TcpListener::bind(address).await.map_err(|e| format!("--admin-listen {address}: {e}"))?),
        None => None,
    };
    let admin_address = admin.as_ref().map(|a| a.local_addr()).transpose()?;
    // The first line of standard output says where rayd listens (tests and scripts read it).
    println!(
        "rayd listening on grpc={} admin={}",
        listener.local_addr()?,
        admin_address.map_or("off".to_string(), |a| a.to_string())
    );
    tracing::info!(grpc = %listener.local_addr()?, admin = ?admin_address, limits = ?config.limits, "rayd started");
    rayd_server::run(config, listener, admin, shutdown_signal()).await
}
