//! End to end against two real `rayd` nodes: client-side routing by scene. A `Router` over both places each scene
//! where its `Ring` says — meshes, instance accels and the temporary buffers of uploaded meshes all on one node —
//! and the node that does not hold a scene answers NOT_FOUND naming it.

mod daemon;

use daemon::Daemon;
use glam::Vec3;
use rayd_client::{ClientOptions, Ring, Router, route_key};
use rayd_engine::accel::BuildFlags;
use rayd_engine::geometry::{InstanceFlags, InstanceRecord};
use rayd_engine::mesh::Mesh;
use tonic::Code;

/// A tetrahedron, big enough in bytes (with `inline_mesh_bytes` of 0) to go through uploaded buffers.
fn tetrahedron() -> Mesh {
    Mesh {
        positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z],
        triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_router_keeps_each_scene_whole_on_the_node_its_ring_names() {
    let nodes = [Daemon::start(&[]), Daemon::start(&[])];
    let urls: Vec<String> = nodes.iter().map(Daemon::url).collect();
    let options = ClientOptions { inline_mesh_bytes: 0, ..ClientOptions::default() };
    let router = Router::connect(&urls, options).await.unwrap();
    let scenes: Vec<String> = (0..12).map(|i| format!("scene{i}")).collect();
    for scene in &scenes {
        let part = format!("{scene}.part");
        router.client(&part).build_mesh(&part, &tetrahedron(), "", BuildFlags::empty()).await.unwrap();
        let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let record =
            InstanceRecord { transform: identity, instance_id: 0, mask: 0xFF, flags: InstanceFlags::empty(), child: 0 };
        router.client(scene).build_instances(scene, "", &[&part], &[record], BuildFlags::empty()).await.unwrap();
    }

    let ring = Ring::new(urls.clone());
    let mut held = Vec::new();
    for (i, client) in router.clients().iter().enumerate() {
        let mut names: Vec<String> = client.accels().await.unwrap().into_iter().map(|a| a.name).collect();
        names.sort();
        let mut expected: Vec<String> = scenes
            .iter()
            .filter(|s| ring.node_for(&route_key(s).unwrap()) == Some(i))
            .flat_map(|s| [s.clone(), format!("{s}.part")])
            .collect();
        expected.sort();
        assert_eq!(names, expected, "node {i} holds the scenes its ring names, whole");
        assert!(client.buffers().await.unwrap().is_empty(), "node {i}: the temporary buffers were deleted");
        held.push(names.len());
    }
    assert!(held.iter().all(|&n| n > 0), "both nodes are used: {held:?}");

    let home = ring.node_for("scene0").unwrap();
    let error = router.clients()[1 - home].accel("scene0").await.unwrap_err();
    assert_eq!(error.code(), Code::NotFound);
    assert!(error.to_string().contains("\"scene0\""), "{error}");
    assert_eq!(router.client("scene0.part").accel("scene0.part").await.unwrap().name, "scene0.part");
}
