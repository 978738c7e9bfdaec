//! End to end against the real `rayd` with `--data-dir`: buffers and accels (geometry, motion, transforms, instance
//! accels) survive `kill -9` and a restart with the same handles, names and trace bytes; an accel left stale by an
//! update of its child comes back stale; destroyed objects stay gone; damaged files are skipped (with what depends
//! on them) without stopping the server; and a `kill -9` in the middle of a stream of builds and updates leaves
//! every object either whole or absent. Also `SaveAccel`/`LoadAccel` through the client.

mod common;
mod daemon;

use std::path::{Path, PathBuf};

use bytes::Bytes;
use common::{pack_rays, random_rays, shared_mesh};
use daemon::Daemon;
use rayd_client::{Client, ClientOptions};
use rayd_engine::accel::BuildFlags;
use rayd_engine::format::{HitFormat, Ray, RayFormat};
use rayd_engine::geometry::{
    INSTANCE_RECORD_BYTES, InstanceFlags, InstanceRecord, MotionFlags, MotionOptions, TransformInput,
};
use rayd_engine::glam::Vec3;
use rayd_engine::mesh::Mesh;
use rayd_engine::query::{Query, QueryKind};
use tonic::Code;

/// A fresh data directory for one test.
fn data_dir(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("rayd-data-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// Starts `rayd` on `dir` and connects.
async fn start(dir: &Path) -> (Daemon, Client) {
    let daemon = Daemon::start(&[("RAYD_DATA_DIR", dir.to_str().unwrap())]);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    (daemon, client)
}

/// Rays through the scene's box at random times in [0, 1], full format.
fn rays() -> Bytes {
    let mut rays: Vec<Ray> = random_rays(4000, 17);
    for (i, ray) in rays.iter_mut().enumerate() {
        ray.origin *= 2.0;
        ray.time = (i % 100) as f32 / 100.0;
        ray.visibility = 0xFF;
        ray.flags = Default::default();
    }
    Bytes::from(pack_rays(&rays, RayFormat::Full))
}

/// Closest-hit and `all` answers of `rays` on `accel`, as bytes.
async fn answers(client: &Client, accel: &str, rays: &Bytes) -> Vec<Bytes> {
    let closest = Query::closest(RayFormat::Full, HitFormat::Full);
    let all = Query { kind: QueryKind::All, max_hits_per_ray: 4, ..closest };
    let mut out = Vec::new();
    for query in [closest, all] {
        let traced = client.trace(accel, &query, rays.clone()).await.unwrap();
        out.push(Bytes::copy_from_slice(traced.hits()));
    }
    out
}

/// One instance record.
fn record(child: u32, id: u32, x: f32) -> InstanceRecord {
    InstanceRecord {
        transform: [1., 0., 0., x, 0., 1., 0., 0., 0., 0., 1., 0.],
        instance_id: id,
        mask: 0xFF,
        flags: InstanceFlags::empty(),
        child,
    }
}

/// Every accel's (name, handle, size), sorted by name.
async fn listing(client: &Client) -> Vec<(String, String, u64)> {
    let mut all: Vec<_> =
        client.accels().await.unwrap().into_iter().map(|a| (a.name, a.handle, a.size_bytes)).collect();
    all.sort();
    all
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn objects_survive_kill_9_and_come_back_as_they_were() {
    let dir = data_dir("survive");
    let (mut daemon, client) = start(&dir).await;
    let bunny = shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::ALLOW_UPDATE).await.unwrap();
    let moved = Mesh { positions: bunny.positions.iter().map(|p| *p + Vec3::X * 0.3).collect(), ..bunny.clone() };
    let motion = MotionOptions { keys: 2, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::END_VANISH };
    client.build_moving_mesh("walk", &[bunny.clone(), moved], "", BuildFlags::empty(), &motion).await.unwrap();
    let identity = [1., 0., 0., 0., 1., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0.];
    let mut turned = identity;
    (turned[11], turned[12]) = (0.5, 0.866_025_4);
    let spin = TransformInput::SrtMotion { keys: vec![identity, turned], motion };
    client.build_transform_input("spin", "", "walk", &spin).await.unwrap();
    let records = [record(0, 1, 0.0), record(1, 2, 0.5), record(0, 3, -0.5)];
    client.build_instances("scene", "", &["bunny", "spin"], &records, BuildFlags::empty()).await.unwrap();
    client.build_instances("above", "", &["bunny"], &records[..1], BuildFlags::ALLOW_UPDATE).await.unwrap();
    let kept = client.upload_buffer("kept", Bytes::from_static(b"0123456789")).await.unwrap();
    let rays = rays();
    let before = answers(&client, "scene", &rays).await;
    let walk_before = answers(&client, "walk", &rays).await;
    // Updating the child leaves "above" stale until it is updated too; "scene" placed the old bunny too.
    client.update_mesh("bunny", &bunny).await.unwrap();
    let listed = listing(&client).await;

    daemon.kill();
    let (mut daemon, client) = start(&dir).await;
    assert_eq!(listing(&client).await, listed, "the same names, handles and sizes");
    assert_eq!(client.download_buffer(&kept.id).await.unwrap(), Bytes::from_static(b"0123456789"));
    assert_eq!(answers(&client, "walk", &rays).await, walk_before, "the moving mesh traces the same bytes");
    for stale in ["scene", "above"] {
        let error = client.trace(stale, &Query::closest(RayFormat::Full, HitFormat::T), rays.clone()).await;
        assert_eq!(error.unwrap_err().code(), Code::FailedPrecondition, "{stale} places the bunny before its update");
    }
    let mut bytes = vec![0u8; INSTANCE_RECORD_BYTES];
    records[0].encode(&mut bytes);
    let update = rayd_client::proto::UpdateAccelRequest {
        accel: Some(rayd_client::convert::accel_ref("above")),
        inputs: vec![rayd_client::proto::BuildInput {
            input: Some(rayd_client::proto::build_input::Input::Instances(rayd_client::proto::InstanceInput {
                children: vec![rayd_client::convert::accel_ref("bunny")],
                instances: Some(rayd_client::proto::instance_input::Instances::Records(
                    rayd_client::proto::DataSource {
                        source: Some(rayd_client::proto::data_source::Source::Inline(bytes.into())),
                    },
                )),
            })),
        }],
    };
    client.update(update).await.unwrap();
    client.trace("above", &Query::closest(RayFormat::Full, HitFormat::T), rays.clone()).await.unwrap();
    // The scene was saved before the update: rebuilt over the same children it answers as before.
    client.destroy_accel("scene").await.unwrap();
    client.build_instances("scene", "", &["bunny", "spin"], &records, BuildFlags::empty()).await.unwrap();
    assert_eq!(answers(&client, "scene", &rays).await, before, "same bytes as before the restart");
    client.delete_buffer(&kept.id).await.unwrap();
    client.destroy_accel("above").await.unwrap();
    let listed = listing(&client).await;

    daemon.kill();
    let (_daemon, client) = start(&dir).await;
    assert_eq!(listing(&client).await, listed, "destroyed accels stay gone, updates stay");
    assert!(client.buffers().await.unwrap().is_empty(), "deleted buffers stay gone");
    assert_eq!(answers(&client, "scene", &rays).await, before);
    let fresh = client.build_mesh("fresh", &bunny, "", BuildFlags::empty()).await.unwrap();
    assert!(listed.iter().all(|(_, handle, _)| *handle != fresh.handle), "new handles never reuse restored ones");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn damaged_files_are_skipped_with_what_depends_on_them() {
    let dir = data_dir("damaged");
    let (mut daemon, client) = start(&dir).await;
    let triangle = common::unit_triangle();
    let damaged = client.build_mesh("damaged", &triangle, "", BuildFlags::empty()).await.unwrap();
    client.build_instances("above", "", &["damaged"], &[record(0, 1, 0.0)], BuildFlags::empty()).await.unwrap();
    client.build_mesh("intact", &triangle, "", BuildFlags::empty()).await.unwrap();
    daemon.stop();
    let file = dir.join(format!("tenants/default/accels/{}.acc", damaged.handle));
    let mut bytes = std::fs::read(&file).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x40;
    std::fs::write(&file, bytes).unwrap();
    std::fs::write(dir.join("tenants/default/accels/acc-999.acc"), b"not an accel").unwrap();

    let (_daemon, client) = start(&dir).await;
    let names: Vec<String> = listing(&client).await.into_iter().map(|(name, _, _)| name).collect();
    assert_eq!(names, ["intact"], "the damaged accel, the one above it and the garbage are skipped");
    let new = client.build_mesh("new", &triangle, "", BuildFlags::empty()).await.unwrap();
    let number: u64 = new.handle.strip_prefix("acc-").and_then(|n| n.parse().ok()).unwrap();
    assert!(number > 999, "a new accel takes no skipped file's handle: {}", new.handle);
    let garbage = std::fs::read(dir.join("tenants/default/accels/acc-999.acc")).unwrap();
    assert_eq!(garbage, b"not an accel", "skipped files stay as they were");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_kill_9_during_builds_and_updates_leaves_every_object_whole_or_absent() {
    let dir = data_dir("torn");
    let bunny = shared_mesh("stanford-bunny");
    let (mut daemon, client) = start(&dir).await;
    let finished = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let writer = {
        let (client, bunny, finished) = (client.clone(), bunny.clone(), std::sync::Arc::clone(&finished));
        tokio::spawn(async move {
            for i in 0.. {
                let name = format!("b{i}");
                if client.build_mesh(&name, &bunny, "", BuildFlags::ALLOW_UPDATE).await.is_err()
                    || client.update_mesh(&name, &bunny).await.is_err()
                {
                    return i;
                }
                finished.store(i + 1, std::sync::atomic::Ordering::SeqCst);
            }
            unreachable!()
        })
    };
    // Kill while builds and updates (and their writes) are going on: after a few, at an odd moment.
    while finished.load(std::sync::atomic::Ordering::SeqCst) < 3 {
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
    tokio::time::sleep(std::time::Duration::from_millis(37)).await;
    daemon.kill();
    let built = writer.await.unwrap();
    assert!(built >= 3, "builds finished before the kill");

    let (_daemon, client) = start(&dir).await;
    let restored = listing(&client).await;
    assert!(restored.len() >= built, "every acknowledged build is back: {} of {built}", restored.len());
    let rays = Bytes::from(pack_rays(&random_rays(500, 3), RayFormat::Full));
    let reference = client.build_mesh("reference", &bunny, "", BuildFlags::empty()).await.unwrap();
    let expected = answers(&client, &reference.name, &rays).await;
    for (name, _, _) in &restored {
        assert_eq!(answers(&client, name, &rays).await, expected, "{name} is whole");
    }
    let leftovers: Vec<_> = std::fs::read_dir(dir.join("tenants/default/accels"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|name| !name.ends_with(".acc"))
        .collect();
    assert!(leftovers.is_empty(), "no temporary file survives a restart: {leftovers:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_saved_scene_loads_back_under_a_new_name_and_bad_blobs_are_refused() {
    let dir = data_dir("load");
    let (mut daemon, client) = start(&dir).await;
    let bunny = shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    let records = [record(0, 1, 0.0), record(0, 2, 0.5)];
    client.build_instances("scene", "", &["bunny"], &records, BuildFlags::empty()).await.unwrap();
    let blob = client.save_accel("scene").await.unwrap();
    assert!(client.buffers().await.unwrap().is_empty(), "the temporary buffer is gone");
    let loaded = client.load_accel("copy", "", blob.clone()).await.unwrap();
    let names: Vec<&str> = loaded.iter().map(|a| a.name.as_str()).collect();
    assert_eq!(names, ["copy.1", "copy"], "the child first, the root last");
    let rays = rays();
    assert_eq!(answers(&client, "copy", &rays).await, answers(&client, "scene", &rays).await);
    let error = client.load_accel("copy", "", blob.clone()).await.unwrap_err();
    assert_eq!(error.code(), Code::AlreadyExists, "{error}");
    let mut damaged = blob.to_vec();
    let last = damaged.len() - 1;
    damaged[last] ^= 1;
    let error = client.load_accel("other", "", damaged.into()).await.unwrap_err();
    assert_eq!(error.code(), Code::InvalidArgument, "{error}");
    assert!(client.accel("other").await.is_err(), "nothing of a refused blob stays");

    let expected = answers(&client, "scene", &rays).await;
    daemon.kill();
    let (_daemon, client) = start(&dir).await;
    let names: Vec<String> = listing(&client).await.into_iter().map(|(name, _, _)| name).collect();
    assert_eq!(names.len(), 4, "the scene, its child and the loaded copies come back: {names:?}");
    assert_eq!(answers(&client, "copy", &rays).await, expected, "the loaded scene as it was");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A tmpfs of a few MiB mounted on a fresh directory, to fill up and to make read-only (the tests run as root, as
/// in CI); unmounted when dropped.
struct SmallDisk {
    /// Where it is mounted.
    dir: PathBuf,
}

impl SmallDisk {
    /// Mounts a tmpfs of `mib` MiB.
    fn mount(name: &str, mib: u32) -> SmallDisk {
        let dir = data_dir(name);
        std::fs::create_dir_all(&dir).unwrap();
        let disk = SmallDisk { dir };
        disk.mount_command(&["-t", "tmpfs", "-o", &format!("size={mib}m"), "tmpfs"]);
        disk
    }

    /// Remounts it read-only (`ro`) or writable (`rw`).
    fn remount(&self, mode: &str) {
        self.mount_command(&["-o", &format!("remount,{mode}")]);
    }

    /// Runs `mount ARGS DIR`.
    fn mount_command(&self, args: &[&str]) {
        let output = std::process::Command::new("mount").args(args).arg(&self.dir).output().expect("mount runs");
        assert!(
            output.status.success(),
            "mount {args:?} failed (needs root, as CI has): {}",
            String::from_utf8_lossy(&output.stderr)
        );
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg("-l").arg(&self.dir).status();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_skipped_object_does_not_come_back_over_a_newer_one_of_its_name() {
    let dir = data_dir("superseded");
    let (mut daemon, client) = start(&dir).await;
    let first = client.upload_buffer("a", Bytes::from(vec![1u8; 600])).await.unwrap();
    let old = client.upload_buffer("b", Bytes::from(vec![2u8; 600])).await.unwrap();
    daemon.stop();
    // Started under a lower limit, "b" does not fit: it is skipped, its file left for the operator.
    let lower = [("RAYD_DATA_DIR", dir.to_str().unwrap()), ("RAYD_LIMITS_MAX_TOTAL_BUFFER_BYTES", "1000")];
    let mut daemon = Daemon::start(&lower);
    let client = Client::connect(&daemon.url(), ClientOptions::default()).await.unwrap();
    assert_eq!(buffer_ids(&client).await, std::slice::from_ref(&first.id), "b is skipped");
    client.delete_buffer(&first.id).await.unwrap();
    let new = client.upload_buffer("b", Bytes::from(vec![3u8; 600])).await.unwrap();
    daemon.stop();

    // Started again with room for both: the new "b", which its client was told of, comes back, not the old one.
    let (_daemon, client) = start(&dir).await;
    let buffers: Vec<(String, String)> = client.buffers().await.unwrap().into_iter().map(|b| (b.id, b.name)).collect();
    assert_eq!(buffers, [(new.id.clone(), "b".to_owned())]);
    assert_eq!(client.download_buffer(&new.id).await.unwrap(), vec![3u8; 600]);
    assert!(dir.join(format!("tenants/default/buffers/{}.buf", old.id)).exists(), "the old file stays as it was");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ids_and_handles_of_deleted_objects_are_not_given_again_after_a_restart() {
    let dir = data_dir("deleted-ids");
    let (mut daemon, client) = start(&dir).await;
    let triangle = common::unit_triangle();
    client.upload_buffer("kept", Bytes::from_static(b"kept")).await.unwrap();
    let deleted = client.upload_buffer("deleted", Bytes::from_static(b"gone")).await.unwrap();
    client.build_mesh("kept", &triangle, "", BuildFlags::empty()).await.unwrap();
    let destroyed = client.build_mesh("destroyed", &triangle, "", BuildFlags::empty()).await.unwrap();
    client.delete_buffer(&deleted.id).await.unwrap();
    client.destroy_accel("destroyed").await.unwrap();
    daemon.kill();

    let (_daemon, client) = start(&dir).await;
    let buffer = client.upload_buffer("new", Bytes::from_static(b"new")).await.unwrap();
    let accel = client.build_mesh("new", &triangle, "", BuildFlags::empty()).await.unwrap();
    let number = |id: &str| id.split_once('-').and_then(|(_, n)| n.parse::<u64>().ok()).unwrap();
    assert!(number(&buffer.id) > number(&deleted.id), "{} after {} was deleted", buffer.id, deleted.id);
    assert!(number(&accel.handle) > number(&destroyed.handle), "{} after {}", accel.handle, destroyed.handle);
    let gone = client.download_buffer(&deleted.id).await.expect_err("a deleted id names nothing");
    assert_eq!(gone.code(), Code::NotFound, "{gone}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The ids of the tenant's buffers, in creation order.
async fn buffer_ids(client: &Client) -> Vec<String> {
    client.buffers().await.unwrap().into_iter().map(|b| b.id).collect()
}

/// Uploads blocks of `size` bytes until the server refuses one; returns the ids stored and the refusal.
async fn upload_until_refused(client: &Client, size: usize, ids: &mut Vec<String>) -> rayd_client::Error {
    let block = Bytes::from(vec![7u8; size]);
    for _ in 0..64 {
        match client.upload_buffer(&format!("block{}", ids.len()), block.clone()).await {
            Ok(info) => ids.push(info.id),
            Err(refused) => return refused,
        }
    }
    panic!("64 blocks of {size} bytes fitted on a small disk");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_or_read_only_data_directory_refuses_writes_by_code_and_serving_goes_on() {
    let disk = SmallDisk::mount("small-disk", 48);
    let (mut daemon, client) = start(&disk.dir).await;
    let bunny = shared_mesh("stanford-bunny");
    client.build_mesh("bunny", &bunny, "", BuildFlags::empty()).await.unwrap();
    client.build_mesh("moving", &bunny, "", BuildFlags::ALLOW_UPDATE).await.unwrap();
    let moved = Mesh {
        positions: bunny.positions.iter().map(|p| *p + Vec3::new(0.01, 0.0, 0.0)).collect(),
        triangles: bunny.triangles.clone(),
    };
    let rays = rays();
    let expected = answers(&client, "bunny", &rays).await;
    // An update that cannot be stored changes nothing: the old version traces (and comes back after a restart).
    let refused_update = |code: Code, why: &'static str| {
        let (client, moved, rays, expected) = (&client, &moved, &rays, &expected);
        async move {
            let refused = client.update_mesh("moving", moved).await.expect_err(why);
            assert_eq!(refused.code(), code, "{refused}");
            assert!(refused.to_string().contains(r#"storing accel "moving""#), "{refused}");
            let traced = answers(client, "moving", rays).await;
            assert!(&traced == expected, "the update that failed ({why}) is undone: other hits");
        }
    };

    // Full: 4 MiB blocks, then 64 KiB ones, until the disk has less than 64 KiB left.
    let mut stored = Vec::new();
    for size in [4 << 20, 64 << 10] {
        let full = upload_until_refused(&client, size, &mut stored).await;
        assert_eq!(full.code(), Code::ResourceExhausted, "{full}");
        assert!(full.to_string().contains("storing buffer") && full.to_string().contains("No space left"), "{full}");
    }
    assert_eq!(buffer_ids(&client).await, stored, "refused buffers are not kept");
    let full = client.build_mesh("bunny2", &bunny, "", BuildFlags::empty()).await.expect_err("no room for an accel");
    assert_eq!(full.code(), Code::ResourceExhausted, "{full}");
    assert!(full.to_string().contains(r#"storing accel "bunny2""#), "{full}");
    assert_eq!(listing(&client).await.len(), 2, "the refused accel is not kept");
    assert_eq!(answers(&client, "bunny", &rays).await, expected, "tracing goes on with a full disk");
    refused_update(Code::ResourceExhausted, "a full disk").await;
    client.delete_buffer(&stored.remove(0)).await.unwrap();
    stored.push(client.upload_buffer("after", Bytes::from(vec![1u8; 1 << 20])).await.unwrap().id);

    // Read-only: nothing can be stored or removed, and nothing changes; tracing goes on.
    disk.remount("ro");
    let read_only = client.build_mesh("bunny3", &bunny, "", BuildFlags::empty()).await.expect_err("read-only");
    assert_eq!(read_only.code(), Code::FailedPrecondition, "{read_only}");
    assert!(read_only.to_string().contains("Read-only file system"), "{read_only}");
    let read_only = client.destroy_accel("bunny").await.expect_err("its file cannot be removed");
    assert_eq!(read_only.code(), Code::FailedPrecondition, "{read_only}");
    assert!(read_only.to_string().contains("removing the file of accel"), "{read_only}");
    let read_only = client.delete_buffer(&stored[0]).await.expect_err("its file cannot be removed");
    assert_eq!(read_only.code(), Code::FailedPrecondition, "{read_only}");
    let before = listing(&client).await;
    assert_eq!(before.len(), 2, "the accel whose destroy failed stays");
    assert_eq!(buffer_ids(&client).await, stored, "the buffer whose delete failed stays");
    assert_eq!(answers(&client, "bunny", &rays).await, expected, "tracing goes on with a read-only disk");
    refused_update(Code::FailedPrecondition, "a read-only disk").await;

    // What was acknowledged is what comes back.
    disk.remount("rw");
    daemon.stop();
    let (_daemon, client) = start(&disk.dir).await;
    assert_eq!(listing(&client).await, before);
    assert_eq!(buffer_ids(&client).await, stored);
    assert_eq!(answers(&client, "bunny", &rays).await, expected);
    assert!(answers(&client, "moving", &rays).await == expected, "the refused updates came back undone: other hits");
    for id in &stored {
        client.delete_buffer(id).await.unwrap();
    }
    client.update_mesh("moving", &moved).await.expect("room for the update again");
    assert!(answers(&client, "moving", &rays).await != expected, "an update that is kept changes the hits");
}
