//! Restart time with about 1 GB of persisted accels: `rayd` (in-process, with a data directory) builds accels over
//! a tiled mesh of the shared meshes until they hold 1 GiB, shuts down, and starts again on the same directory;
//! the time from the second start to the first answer listing every accel is the restart time. Before any figure
//! is printed, a trace on each restored accel is checked against the same trace before the restart, byte for
//! byte. Run with `cargo bench -p rayd-server --bench restart`.

use std::time::{Duration, Instant};

use bytes::Bytes;
use rayd_client::{Client, ClientOptions};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::glam::Vec3;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use rayd_engine::raygen::random_rays;
use tokio::sync::oneshot;

/// Bytes of accels to persist.
const TARGET_BYTES: u64 = 1 << 30;
/// Triangles of each accel.
const TRIANGLES: usize = 2_000_000;

/// Starts `rayd` on `data_dir`; it stops when the returned sender is dropped or sent to.
async fn start(data_dir: &std::path::Path) -> (String, oneshot::Sender<()>, tokio::task::JoinHandle<()>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let config = rayd_server::Config { data_dir: Some(data_dir.to_path_buf()), ..rayd_server::Config::default() };
    let (stop, stopped) = oneshot::channel::<()>();
    let server = tokio::spawn(async move {
        rayd_server::run(config, listener, None, async move {
            let _ = stopped.await;
        })
        .await
        .unwrap();
    });
    (url, stop, server)
}

/// Connects, retrying until the server answers `ListAccels` (it serves once its directory is restored).
async fn connect_when_serving(url: &str) -> (Client, usize) {
    loop {
        if let Ok(client) = Client::connect(url, ClientOptions::default()).await
            && let Ok(accels) = client.accels().await
        {
            return (client, accels.len());
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

fn main() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/meshes");
    let mut names: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    names.sort();
    let meshes: Vec<Mesh> = names
        .iter()
        .filter(|p| p.extension().is_some_and(|e| e == "obj"))
        .map(|p| Mesh::load_obj(p).unwrap().normalized_at(Vec3::ZERO))
        .collect();
    let tiled = Mesh::tiled(&meshes, TRIANGLES);
    let (lo, hi) = tiled.bounds();
    let rays = Bytes::from(random_rays(lo, hi, 100_000, 5, RayFormat::OriginTminDirectionTmax));
    let query = Query::closest(RayFormat::OriginTminDirectionTmax, HitFormat::TTriidUV);
    let data_dir = std::env::temp_dir().join(format!("rayd-restart-bench-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&data_dir);

    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let (url, stop, server) = start(&data_dir).await;
        let (client, _) = connect_when_serving(&url).await;
        let (mut total, mut before) = (0u64, Vec::new());
        let build_start = Instant::now();
        while total < TARGET_BYTES {
            let name = format!("tiled-{}", before.len());
            let info = client.build_mesh(&name, &tiled, "", BuildFlags::empty()).await.unwrap();
            total += info.size_bytes;
            before.push((name.clone(), client.trace(&name, &query, rays.clone()).await.unwrap().hits().to_vec()));
        }
        let build_s = build_start.elapsed().as_secs_f64();
        drop(client);
        let _ = stop.send(());
        server.await.unwrap();
        let on_disk: u64 = std::fs::read_dir(data_dir.join("tenants/default/accels"))
            .unwrap()
            .map(|e| e.unwrap().metadata().unwrap().len())
            .sum();

        let restart = Instant::now();
        let (url, stop, server) = start(&data_dir).await;
        let (client, listed) = connect_when_serving(&url).await;
        let restart_s = restart.elapsed().as_secs_f64();
        assert_eq!(listed, before.len(), "every accel is back");
        for (name, hits) in &before {
            let traced = client.trace(name, &query, rays.clone()).await.unwrap();
            assert!(traced.hits() == hits.as_slice(), "{name} traces the same bytes after the restart");
        }
        drop(client);
        let _ = stop.send(());
        server.await.unwrap();
        println!("{} threads; {} accels of {TRIANGLES} triangles", rayon::current_num_threads(), before.len());
        println!("accels | accel bytes | file bytes | build + persist s | restart s | restored GB/s");
        println!(
            "{} | {total} | {on_disk} | {build_s:.1} | {restart_s:.2} | {:.2}",
            before.len(),
            on_disk as f64 / restart_s / 1e9
        );
    });
    let _ = std::fs::remove_dir_all(&data_dir);
}
