//! Scene description files: meshes and instances of them in JSON, built as one geometry accel per mesh and an
//! instance accel over them, so people can host real scenes without writing code.
//!
//! ```json
//! {
//!   "meshes": { "bunny": "stanford-bunny.obj", "cow": "meshes/cow.obj" },
//!   "instances": [
//!     { "mesh": "bunny" },
//!     { "mesh": "cow", "translate": [2, 0, 0], "rotate": [0, 1, 0, 90], "scale": [1, 1, -1],
//!       "id": 7, "mask": 1, "flip_facing": true, "disable_face_culling": false },
//!     { "mesh": "bunny", "transform": [1, 0, 0, 0,  0, 1, 0, 3,  0, 0, 1, 0] }
//!   ]
//! }
//! ```
//!
//! Mesh paths are relative to the scene file. An instance is placed by `transform` (3×4 row-major, object to world)
//! or else by `scale` (one number or three), then `rotate` (axis x y z and degrees), then `translate`. `id`
//! defaults to the instance's index, `mask` to 255 (every ray sees it), the flags to false.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{Affine3A, Quat, Vec3};
use rayd_engine::accel::BuildFlags;
use rayd_engine::geometry::{InstanceFlags, InstanceRecord, Placement};
use rayd_proto as proto;
use serde::Deserialize;

use crate::client::Client;
use crate::error::{Error, Result};
use crate::mesh::load_mesh;

/// A scene file, parsed.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Mesh files by the name instances use.
    pub meshes: BTreeMap<String, PathBuf>,
    /// The instances.
    pub instances: Vec<SceneInstance>,
}

/// One instance of a scene file.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneInstance {
    /// The mesh it places (a key of [`Scene::meshes`]).
    pub mesh: String,
    /// Object to world, 3×4 row-major; overrides `scale`, `rotate` and `translate`.
    pub transform: Option<[f32; 12]>,
    /// Scale: one factor or three.
    pub scale: Option<Scale>,
    /// Rotation: axis x y z, then degrees.
    pub rotate: Option<[f32; 4]>,
    /// Translation.
    pub translate: Option<[f32; 3]>,
    /// The id hits report (default: the instance's index).
    pub id: Option<u32>,
    /// Visibility mask (default 255).
    pub mask: Option<u8>,
    /// Swap front and back faces.
    #[serde(default)]
    pub flip_facing: bool,
    /// Ignore ray flags that cull faces.
    #[serde(default)]
    pub disable_face_culling: bool,
}

/// A uniform or per-axis scale.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum Scale {
    /// The same on every axis.
    Uniform(f32),
    /// Per axis.
    Axes([f32; 3]),
}

impl Scene {
    /// Reads a scene file; mesh paths become relative to its directory.
    pub fn load(path: &Path) -> Result<Scene> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let mut scene: Scene = serde_json::from_str(&text)
            .map_err(|e| Error::InvalidArgument(format!("scene {}: {e}", path.display())))?;
        let dir = path.parent().unwrap_or(Path::new(""));
        for file in scene.meshes.values_mut() {
            *file = dir.join(&*file);
        }
        Ok(scene)
    }

    /// The instance records, their children indexing the meshes in name order.
    pub fn records(&self) -> Result<Vec<InstanceRecord>> {
        let names: Vec<&String> = self.meshes.keys().collect();
        self.instances
            .iter()
            .enumerate()
            .map(|(index, instance)| {
                let child = names.iter().position(|name| **name == instance.mesh).ok_or_else(|| {
                    Error::InvalidArgument(format!("instances[{index}].mesh: no mesh is called {:?}", instance.mesh))
                })?;
                let mut flags = InstanceFlags::empty();
                flags.set(InstanceFlags::FLIP_FACING, instance.flip_facing);
                flags.set(InstanceFlags::DISABLE_FACE_CULLING, instance.disable_face_culling);
                Ok(InstanceRecord {
                    transform: instance.transform.unwrap_or_else(|| Placement::rows(&instance.placement())),
                    instance_id: instance.id.unwrap_or(index as u32),
                    mask: instance.mask.unwrap_or(0xFF),
                    flags,
                    child: child as u32,
                })
            })
            .collect()
    }
}

impl SceneInstance {
    /// Scale, then rotation, then translation.
    fn placement(&self) -> Affine3A {
        let scale = match self.scale {
            None => Vec3::ONE,
            Some(Scale::Uniform(s)) => Vec3::splat(s),
            Some(Scale::Axes(axes)) => Vec3::from(axes),
        };
        let rotation = self.rotate.map_or(Quat::IDENTITY, |[x, y, z, degrees]| {
            Quat::from_axis_angle(Vec3::new(x, y, z).normalize_or(Vec3::Z), degrees.to_radians())
        });
        Affine3A::from_scale_rotation_translation(scale, rotation, Vec3::from(self.translate.unwrap_or_default()))
    }
}

impl Client {
    /// Builds `scene` on `device`: each mesh as accel `<name>.<mesh>`, then the instance accel `name` over them
    /// (with `flags`). Returns the instance accel's description.
    pub async fn build_scene(
        &self,
        name: &str,
        device: &str,
        scene: &Scene,
        flags: BuildFlags,
    ) -> Result<proto::AccelInfo> {
        let records = scene.records()?;
        let mut children = Vec::with_capacity(scene.meshes.len());
        for (mesh, file) in &scene.meshes {
            let child = format!("{name}.{mesh}");
            self.build_mesh(&child, &load_mesh(file)?, device, BuildFlags::empty()).await?;
            children.push(child);
        }
        let children: Vec<&str> = children.iter().map(String::as_str).collect();
        self.build_instances(name, device, &children, &records, flags).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instances_are_placed_scale_rotate_translate_or_by_matrix() {
        let text = r#"{
            "meshes": { "b": "b.obj", "a": "a.obj" },
            "instances": [
                { "mesh": "b", "scale": 2, "rotate": [0, 0, 1, 90], "translate": [1, 2, 3], "mask": 3, "flip_facing": true },
                { "mesh": "a", "transform": [1, 0, 0, 5, 0, 1, 0, 6, 0, 0, 1, 7], "id": 40 }
            ]
        }"#;
        let scene: Scene = serde_json::from_str(text).unwrap();
        let records = scene.records().unwrap();
        assert_eq!((records[0].child, records[1].child), (1, 0), "children index the meshes in name order");
        assert_eq!((records[0].instance_id, records[0].mask, records[0].flags), (0, 3, InstanceFlags::FLIP_FACING));
        // x ↦ scaled by 2, turned 90° about z (x → y), moved by (1, 2, 3): (1, 0, 0) goes to (1, 4, 3).
        let m = records[0].transform;
        let x = [m[0] + m[3], m[4] + m[7], m[8] + m[11]];
        assert!((x[0] - 1.0).abs() < 1e-5 && (x[1] - 4.0).abs() < 1e-5 && (x[2] - 3.0).abs() < 1e-5, "{x:?}");
        assert_eq!((records[1].instance_id, records[1].mask, records[1].transform[3]), (40, 0xFF, 5.0));
        let bad: Scene = serde_json::from_str(r#"{ "meshes": {}, "instances": [{ "mesh": "x" }] }"#).unwrap();
        assert!(bad.records().unwrap_err().to_string().contains("instances[0].mesh: no mesh is called \"x\""));
        assert!(serde_json::from_str::<Scene>(r#"{ "meshes": {}, "instances": [], "extra": 1 }"#).is_err());
    }
}
