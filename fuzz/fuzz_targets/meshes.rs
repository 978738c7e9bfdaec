//! The mesh loaders of `rayctl` (`rayd_client::load_mesh`): arbitrary bytes as an OBJ, PLY, glTF or GLB file (the
//! first byte picks the extension). No panic; a mesh that loads has triangles, and every index names a vertex.

#![no_main]

use libfuzzer_sys::fuzz_target;

/// The extensions the loaders know.
const EXTENSIONS: [&str; 4] = ["obj", "ply", "gltf", "glb"];

fuzz_target!(|data: &[u8]| {
    let Some((&pick, file)) = data.split_first() else { return };
    let extension = EXTENSIONS[pick as usize % EXTENSIONS.len()];
    // A folder of its own, so that a glTF's relative URIs find nothing else.
    let dir = std::env::temp_dir().join(format!("rayd-fuzz-meshes-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("a temporary folder");
    let path = dir.join(format!("mesh.{extension}"));
    std::fs::write(&path, file).expect("the file is written");
    if let Ok(mesh) = rayd_client::load_mesh(&path) {
        assert!(!mesh.triangles.is_empty(), "a loaded mesh has triangles");
        let vertices = mesh.positions.len();
        assert!(mesh.triangles.iter().flatten().all(|&i| (i as usize) < vertices), "an index beyond the vertices");
    }
});
