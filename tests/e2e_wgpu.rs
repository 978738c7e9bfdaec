//! End to end against the real `rayd`: it lists the wgpu adapters after `cpu:0`, builds the bunny on `wgpu:0` and
//! traces it by TraceBatch with the hits the CPU device gives (`t` within 1e-4 relative, same primitive); copies it
//! from `cpu:0` by CopyAccel, instances it twice on `wgpu:0` and traces that with the instance ids the CPU gives. Its
//! GPU traces hold 1 MiB of buffers at most (`scheduler.gpu_trace_bytes`): 4,000 rays go in chunks that fit, and an
//! `all` query too large for it is refused naming the key. A ray may take 1,024 node visits and triangle tests
//! (`scheduler.gpu_ray_work`): one through a pile of 2,000 triangles is refused naming the key.
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
use rayd_engine::format::{HitFormat, Ray, RayFlags, RayFormat};
use rayd_engine::geometry::{InstanceFlags, InstanceRecord};
use rayd_engine::mesh::Mesh;
use rayd_engine::query::Query;
use rayd_proto as proto;

#[tokio::test]
async fn rayd_lists_wgpu_devices_and_traces_copied_and_instanced_accels_on_one() {
    let daemon =
        Daemon::start(&[("RAYD_SCHEDULER_GPU_TRACE_BYTES", "1048576"), ("RAYD_SCHEDULER_GPU_RAY_WORK", "1024")]);
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
    let random = random_rays(4000, 9);
    let rays = Bytes::from(pack_rays(&random, RayFormat::Full));
    let on_cpu = client.trace("cpu", &query, rays.clone()).await.unwrap();
    let on_gpu = client.trace("gpu", &query, rays.clone()).await.unwrap();
    // A ray that terminates on its first hit may stop at any hit (which one depends on the traversal order: the
    // CPU's 8-wide nodes and the GPU's 4-wide ones differ): only whether it hit must agree.
    let differing = |rays: &[rayd_engine::format::Ray], format: HitFormat, a: &Bytes, b: &Bytes| {
        (0..rays.len())
            .filter(|&i| {
                let (c, g) = (format.read(a, i), format.read(b, i));
                match rays[i].flags.contains(RayFlags::TERMINATE_ON_FIRST_HIT) {
                    true => (c.t >= 0.0) != (g.t >= 0.0),
                    false => {
                        (c.prim_id, c.inst_id) != (g.prim_id, g.inst_id)
                            || (c.t - g.t).abs() > 1e-4 * c.t.abs().max(1.0)
                    }
                }
            })
            .count()
    };
    assert_eq!(
        differing(&random, HitFormat::TTriid, on_cpu.hits(), on_gpu.hits()),
        0,
        "rays differing on cpu:0 and wgpu:0"
    );
    assert!(on_gpu.stats().rays_hit > 0);
    // 256 full hits a ray: two chunks of 32 rays take about 3.4 MiB of buffers.
    let all = Query {
        kind: rayd_engine::query::QueryKind::All,
        max_hits_per_ray: 256,
        ..Query::closest(RayFormat::Full, HitFormat::Full)
    };
    let refused = client.trace("gpu", &all, rays.clone()).await.expect_err("256 hits a ray within 1 MiB");
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted, "{refused}");
    assert!(refused.to_string().contains("scheduler.gpu_trace_bytes"), "{refused}");
    // An empty batch is answered (it waited forever on a GPU, whose traces all go through its workers).
    let empty = tokio::time::timeout(std::time::Duration::from_secs(60), client.trace("gpu", &query, Bytes::new()));
    let empty = empty.await.expect("an empty batch is answered").unwrap();
    assert_eq!((empty.rays(), empty.hits().len()), (0, 0));
    // The kernels' time is within the trace's, and there is none on the CPU.
    let (gpu_stats, cpu_stats) = (on_gpu.stats(), on_cpu.stats());
    eprintln!("wgpu:0 kernels {} ns of a {} ns trace", gpu_stats.device_ns, gpu_stats.trace_ns);
    assert!(gpu_stats.device_ns <= gpu_stats.trace_ns, "{gpu_stats:?}");
    assert_eq!(cpu_stats.device_ns, 0);
    // A copy from cpu:0 traces there; two instances of it (one visible to half the rays) trace as on the CPU.
    let copy = client.copy_accel("cpu", "copied", "wgpu:0", false).await.unwrap();
    assert_eq!(copy.device, "wgpu:0");
    let shifted = [1.0, 0.0, 0.0, 0.3, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
    let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
    let records = [
        InstanceRecord { transform: identity, instance_id: 4, mask: 0xFF, flags: InstanceFlags::empty(), child: 0 },
        InstanceRecord { transform: shifted, instance_id: 9, mask: 0x01, flags: InstanceFlags::empty(), child: 0 },
    ];
    // A child on another device cannot be placed: the request is valid, the child is in the wrong place.
    let misplaced = client.build_instances("mixed", "wgpu:0", &["cpu"], &records, BuildFlags::empty()).await;
    let misplaced = misplaced.expect_err("a cpu:0 child in a wgpu:0 instance accel");
    assert_eq!(misplaced.code(), tonic::Code::FailedPrecondition, "{misplaced}");
    assert!(misplaced.to_string().contains("is on device cpu:0"), "{misplaced}");
    for (name, device, child) in [("two-cpu", "cpu:0", "cpu"), ("two-gpu", "wgpu:0", "copied")] {
        client.build_instances(name, device, &[child], &records, BuildFlags::empty()).await.unwrap();
    }
    let query = Query::closest(RayFormat::Full, HitFormat::TTriidInstid);
    let mut seen_by_halves = random_rays(4000, 10);
    for (i, ray) in seen_by_halves.iter_mut().enumerate() {
        ray.visibility = if i % 2 == 0 { 0x01 } else { 0x02 };
    }
    let rays = Bytes::from(pack_rays(&seen_by_halves, RayFormat::Full));
    let on_cpu = client.trace("two-cpu", &query, rays.clone()).await.unwrap();
    let on_gpu = client.trace("two-gpu", &query, rays).await.unwrap();
    let differ = differing(&seen_by_halves, HitFormat::TTriidInstid, on_cpu.hits(), on_gpu.hits());
    assert_eq!(differ, 0, "instanced rays differing");
    let shifted_hits = (0..4000).filter(|&i| HitFormat::TTriidInstid.read(on_gpu.hits(), i).inst_id == 9).count();
    assert!(shifted_hits > 0, "the instance only even rays see is hit");
    // A ray through 2,000 copies of a triangle takes more than the 1,024 node visits and triangle tests a ray may take
    // here (`scheduler.gpu_ray_work`): its trace is refused naming the key; the CPU traces it.
    let pile = Mesh { positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y], triangles: vec![[0, 1, 2]; 2000] };
    client.build_mesh("pile", &pile, "wgpu:0", BuildFlags::empty()).await.unwrap();
    client.build_mesh("pile-cpu", &pile, "cpu:0", BuildFlags::empty()).await.unwrap();
    let down = Ray { origin: glam::Vec3A::new(0.25, 0.25, 1.0), direction: -glam::Vec3A::Z, ..Ray::default() };
    let one = Bytes::from(pack_rays(&[down], RayFormat::Full));
    let refused = client.trace("pile", &query, one.clone()).await.expect_err("2,000 tests a ray within 1,024");
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted, "{refused}");
    assert!(refused.to_string().contains("scheduler.gpu_ray_work"), "{refused}");
    let traced = client.trace("pile-cpu", &query, one).await.unwrap();
    assert_eq!(HitFormat::TTriidInstid.read(traced.hits(), 0).prim_id, 0, "the lowest id of the tie");
}
