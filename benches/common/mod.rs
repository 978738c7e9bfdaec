//! What the benches share: the scenes (the bunny, a tiled scene of at least a million triangles made from every
//! shared mesh, and the bunny with a floor and slivers: triangles of very uneven sizes), loaded from `../shared/data/meshes` beside the checkout, and a helper that runs a
//! closure on one thread or on all of them.

use std::path::{Path, PathBuf};

use rayd_engine::mesh::{Mesh, PackedMesh};
use rayon::ThreadPool;

/// The shared meshes the tiled scene cycles through, in placement order.
pub const TILED_MESHES: [&str; 8] =
    ["beast", "cow", "fandisk", "nefertiti", "ogre", "spot", "stanford-bunny", "teapot"];
/// The tiled scene's minimum triangle count (whole cycles of [`TILED_MESHES`] are placed until it is reached).
pub const TILED_MIN_TRIANGLES: usize = 1_000_000;
/// Slivers of the uneven scene ([`Mesh::with_floor_and_slivers`]).
pub const UNEVEN_SLIVERS: usize = 256;
/// Seed of the uneven scene's slivers.
pub const UNEVEN_SEED: u64 = 7;

/// A scene ready to build.
pub struct Scene {
    /// Its name in bench ids.
    pub name: &'static str,
    /// The triangles (for bounds and counts).
    pub mesh: Mesh,
    /// The same, packed as build-input bytes.
    pub packed: PackedMesh,
}

impl Scene {
    /// Packs `mesh` under `name`.
    fn new(name: &'static str, mesh: Mesh) -> Scene {
        let packed = mesh.pack();
        Scene { name, mesh, packed }
    }

    /// Number of triangles.
    pub fn triangles(&self) -> u64 {
        self.mesh.triangles.len() as u64
    }
}

/// The folder of the shared meshes.
fn mesh_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/meshes")
}

/// Loads the shared mesh `name`.
fn load(name: &str) -> Mesh {
    let path = mesh_dir().join(format!("{name}.obj"));
    Mesh::load_obj(&path).unwrap_or_else(|e| panic!("cannot load a bench mesh: {e}"))
}

/// The shared meshes of [`TILED_MESHES`], in that order.
pub fn tiled_meshes() -> Vec<Mesh> {
    TILED_MESHES.iter().map(|name| load(name)).collect()
}

/// The bunny, the tiled scene, then the uneven one.
pub fn scenes() -> Vec<Scene> {
    let meshes = tiled_meshes();
    let bunny = meshes[TILED_MESHES.iter().position(|&n| n == "stanford-bunny").expect("bunny listed")].clone();
    let tiled = Mesh::tiled(&meshes, TILED_MIN_TRIANGLES);
    let uneven = bunny.with_floor_and_slivers(UNEVEN_SLIVERS, UNEVEN_SEED);
    vec![Scene::new("bunny", bunny), Scene::new("tiled", tiled), Scene::new("uneven", uneven)]
}

/// The thread configurations every bench runs under: a one-thread pool, and rayon's global pool.
pub fn thread_configs(one: &ThreadPool) -> [(&'static str, Option<&ThreadPool>); 2] {
    [("1-thread", Some(one)), ("all-threads", None)]
}

/// Runs `f` in `pool`, or in the caller's (global) pool for `None`.
pub fn in_pool<R: Send>(pool: Option<&ThreadPool>, f: impl FnOnce() -> R + Send) -> R {
    match pool {
        Some(pool) => pool.install(f),
        None => f(),
    }
}

/// A pool of one thread.
pub fn one_thread_pool() -> ThreadPool {
    rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("a one-thread rayon pool")
}
