//! End to end against the real `rayd`: it lists the wgpu adapters after `cpu:0`, builds the bunny on `wgpu:0` and
//! traces it by TraceBatch with the hits the CPU device gives (`t` within 1e-4 relative, same primitive).
//!
//! Adapter policy as in `tests/wgpu.rs`: without one, a notice and a pass, unless `RAYD_REQUIRE_GPU=1`.

mod common;
mod daemon;

use bytes::Bytes;
use common::{pack_rays, random_rays, shared_mesh};
use daemon::Daemon;
use glam::Vec3;
use rayd_client::{Client, ClientOptions};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::query::Query;
use rayd_proto as proto;

#[tokio::test]
async fn rayd_lists_wgpu_devices_and_traces_a_geometry_accel_on_one() {
    let daemon = Daemon::start(&[]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.expect("the client connects");
    let devices = client.devices().await.unwrap();
    assert_eq!(devices[0].id, "cpu:0");
    let Some(gpu) = devices.iter().find(|d| d.id == "wgpu:0") else {
        if std::env::var("RAYD_REQUIRE_GPU").as_deref() == Ok("1") {
            panic!("RAYD_REQUIRE_GPU=1 but rayd lists no wgpu device: {devices:?}");
        }
        eprintln!("skipped: rayd lists no wgpu device (set RAYD_REQUIRE_GPU=1 to fail instead)");
        return;
    };
    assert_eq!(gpu.backend, proto::Backend::Wgpu as i32);
    let bunny = shared_mesh("stanford-bunny").normalized_at(Vec3::splat(0.5));
    client.build_mesh("cpu", &bunny, "cpu:0", BuildFlags::empty()).await.unwrap();
    let info = client.build_mesh("gpu", &bunny, "wgpu:0", BuildFlags::empty()).await.unwrap();
    assert_eq!(info.device, "wgpu:0");
    let query = Query::closest(RayFormat::Full, HitFormat::TTriid);
    let rays = Bytes::from(pack_rays(&random_rays(4000, 9), RayFormat::Full));
    let on_cpu = client.trace("cpu", &query, rays.clone()).await.unwrap();
    let on_gpu = client.trace("gpu", &query, rays).await.unwrap();
    let read = |hits: &Bytes, i| HitFormat::TTriid.read(hits, i);
    let differing = (0..4000)
        .filter(|&i| {
            let (c, g) = (read(on_cpu.hits(), i), read(on_gpu.hits(), i));
            c.prim_id != g.prim_id || (c.t - g.t).abs() > 1e-4 * c.t.abs().max(1.0)
        })
        .count();
    assert_eq!(differing, 0, "rays whose hits differ between cpu:0 and wgpu:0");
    assert!(on_gpu.stats().rays_hit > 0);
}
