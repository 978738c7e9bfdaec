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
//!
//! Motion blur: an instance's `motion` moves its mesh (in the mesh's own space, before the instance's placement)
//! through keys evenly spaced over `time`, each a `scale`, `rotate` and `translate` as above, interpolated as an
//! SRT motion transform (rotations by nlerp, the shorter way round; turns of 180° or more between keys need more
//! keys). `start_vanish` / `end_vanish` remove it before or after `time`. The scene's own `motion` gives the
//! instance accel motion keys (tighter boxes for moving instances) and its range and vanish flags:
//!
//! ```json
//! {
//!   "meshes": { "cow": "meshes/cow.obj" },
//!   "motion": { "keys": 2, "time": [0, 1] },
//!   "instances": [
//!     { "mesh": "cow", "translate": [0, 0, -5],
//!       "motion": { "time": [0, 1], "keys": [{}, { "translate": [1, 0, 0], "rotate": [0, 1, 0, 45] }] } }
//!   ]
//! }
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{Affine3A, Quat, Vec3};
use rayd_engine::accel::BuildFlags;
use rayd_engine::geometry::{InstanceFlags, InstanceRecord, MotionFlags, MotionOptions, Placement, TransformInput};
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
    /// The instance accel's motion options (default: static).
    pub motion: Option<SceneMotion>,
    /// The instances.
    pub instances: Vec<SceneInstance>,
}

/// Motion options in a scene file.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneMotion {
    /// Motion keys of the instance accel (1 or more).
    pub keys: u32,
    /// Time of the first and the last key.
    pub time: [f32; 2],
    /// Not there before the range.
    #[serde(default)]
    pub start_vanish: bool,
    /// Not there after the range.
    #[serde(default)]
    pub end_vanish: bool,
}

/// The motion of one instance: keys evenly spaced over `time`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InstanceMotion {
    /// Time of the first and the last key.
    pub time: [f32; 2],
    /// Where the mesh is at each key, in its own space: at least 2.
    pub keys: Vec<MotionKey>,
    /// Not there before the range.
    #[serde(default)]
    pub start_vanish: bool,
    /// Not there after the range.
    #[serde(default)]
    pub end_vanish: bool,
}

/// One key of an instance's motion: scale, then rotation, then translation (each optional).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionKey {
    /// Scale: one factor or three.
    pub scale: Option<Scale>,
    /// Rotation: axis x y z, then degrees.
    pub rotate: Option<[f32; 4]>,
    /// Translation.
    pub translate: Option<[f32; 3]>,
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
    /// Motion of the mesh under the instance.
    pub motion: Option<InstanceMotion>,
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

    /// The instance records. Their children index the meshes in name order, then the motion transforms of the
    /// moving instances ([`Scene::motion_transforms`]) in instance order. Checked as the server would check them, so
    /// that a scene it would refuse is refused before anything is built: INVALID_ARGUMENT naming the instance whose
    /// mesh does not exist, whose transform is not finite and invertible, or whose motion is not a motion
    /// transform's (2 keys or more over a finite time range, keys finite, S invertible …), or naming `motion` for the
    /// scene's own motion options.
    pub fn records(&self) -> Result<Vec<InstanceRecord>> {
        self.motion_options().check().map_err(|rule| Error::InvalidArgument(format!("motion: {rule}")))?;
        for (index, _, transform) in self.motion_transforms() {
            let refused = |e: rayd_engine::Error| Error::InvalidArgument(format!("instances[{index}].motion: {e}"));
            transform.check().map_err(refused)?;
        }
        let names: Vec<&String> = self.meshes.keys().collect();
        let mut moving = 0;
        self.instances
            .iter()
            .enumerate()
            .map(|(index, instance)| {
                let mesh = names.iter().position(|name| **name == instance.mesh).ok_or_else(|| {
                    Error::InvalidArgument(format!("instances[{index}].mesh: no mesh is called {:?}", instance.mesh))
                })?;
                let child = match instance.motion {
                    Some(_) => {
                        moving += 1;
                        names.len() + moving - 1
                    }
                    None => mesh,
                };
                let transform = instance.transform.unwrap_or_else(|| Placement::rows(&instance.placement()));
                if Placement::new(&transform).is_none() {
                    let rule = "must be finite and invertible";
                    return Err(Error::InvalidArgument(format!("instances[{index}].transform: {rule}")));
                }
                let mut flags = InstanceFlags::empty();
                flags.set(InstanceFlags::FLIP_FACING, instance.flip_facing);
                flags.set(InstanceFlags::DISABLE_FACE_CULLING, instance.disable_face_culling);
                Ok(InstanceRecord {
                    transform,
                    instance_id: instance.id.unwrap_or(index as u32),
                    mask: instance.mask.unwrap_or(0xFF),
                    flags,
                    child: child as u32,
                })
            })
            .collect()
    }
}

impl Scene {
    /// The motion transform of each moving instance, in instance order: (instance index, mesh name, transform).
    pub fn motion_transforms(&self) -> Vec<(usize, &str, TransformInput)> {
        self.instances
            .iter()
            .enumerate()
            .filter_map(|(index, instance)| {
                let motion = instance.motion.as_ref()?;
                let mut previous = Quat::IDENTITY;
                let keys = motion
                    .keys
                    .iter()
                    .map(|key| {
                        let (scale, mut rotation, translation) = parts(key.scale, key.rotate, key.translate);
                        // The same rotation the shorter way round from the previous key.
                        if rotation.dot(previous) < 0.0 {
                            rotation = -rotation;
                        }
                        previous = rotation;
                        let [qx, qy, qz, qw] = rotation.to_array();
                        let (s, t) = (scale, translation);
                        [s.x, 0.0, 0.0, 0.0, s.y, 0.0, 0.0, s.z, 0.0, qx, qy, qz, qw, t.x, t.y, t.z]
                    })
                    .collect::<Vec<_>>();
                let options = MotionOptions {
                    keys: keys.len() as u32,
                    time_begin: motion.time[0],
                    time_end: motion.time[1],
                    flags: vanish_flags(motion.start_vanish, motion.end_vanish),
                };
                Some((index, instance.mesh.as_str(), TransformInput::SrtMotion { keys, motion: options }))
            })
            .collect()
    }

    /// The instance accel's motion options.
    pub fn motion_options(&self) -> MotionOptions {
        self.motion.as_ref().map_or(MotionOptions::STATIC, |m| MotionOptions {
            keys: m.keys,
            time_begin: m.time[0],
            time_end: m.time[1],
            flags: vanish_flags(m.start_vanish, m.end_vanish),
        })
    }
}

/// Motion flags from a scene file's booleans.
fn vanish_flags(start: bool, end: bool) -> MotionFlags {
    let mut flags = MotionFlags::empty();
    flags.set(MotionFlags::START_VANISH, start);
    flags.set(MotionFlags::END_VANISH, end);
    flags
}

/// A scene file's scale, rotation and translation (each optional) as glam's parts.
fn parts(scale: Option<Scale>, rotate: Option<[f32; 4]>, translate: Option<[f32; 3]>) -> (Vec3, Quat, Vec3) {
    let scale = match scale {
        None => Vec3::ONE,
        Some(Scale::Uniform(s)) => Vec3::splat(s),
        Some(Scale::Axes(axes)) => Vec3::from(axes),
    };
    let rotation = rotate.map_or(Quat::IDENTITY, |[x, y, z, degrees]| {
        Quat::from_axis_angle(Vec3::new(x, y, z).normalize_or(Vec3::Z), degrees.to_radians())
    });
    (scale, rotation, Vec3::from(translate.unwrap_or_default()))
}

impl SceneInstance {
    /// Scale, then rotation, then translation.
    fn placement(&self) -> Affine3A {
        let (scale, rotation, translation) = parts(self.scale, self.rotate, self.translate);
        Affine3A::from_scale_rotation_translation(scale, rotation, translation)
    }
}

impl Client {
    /// Builds `scene` on `device`: each mesh as accel `<name>.<mesh>`, each moving instance's SRT motion transform
    /// as `<name>.<instance index>.motion`, then the instance accel `name` over them (with `flags` and the scene's
    /// motion options). Returns the instance accel's description. Every mesh file is loaded, and the instances
    /// checked, before anything is built; when a build fails, the accels this call built are destroyed again, the
    /// last first (a call that fails leaves the server as it was, so that the same call can be made again).
    pub async fn build_scene(
        &self,
        name: &str,
        device: &str,
        scene: &Scene,
        flags: BuildFlags,
    ) -> Result<proto::AccelInfo> {
        let mut building = Vec::new();
        let result = self.build_scene_noting(name, device, scene, flags, &mut building).await;
        if result.is_err() {
            self.destroy_in_reverse(&building).await;
        }
        result
    }

    /// [`Client::build_scene`] without the clean-up: the name of each accel is pushed onto `building` before its
    /// build starts, so that a caller that drops the call midway (an interrupted command) can destroy what it made
    /// with [`Client::destroy_in_reverse`].
    pub async fn build_scene_noting(
        &self,
        name: &str,
        device: &str,
        scene: &Scene,
        flags: BuildFlags,
        building: &mut Vec<String>,
    ) -> Result<proto::AccelInfo> {
        let records = scene.records()?;
        let meshes =
            scene.meshes.iter().map(|(mesh, file)| Ok((mesh, load_mesh(file)?))).collect::<Result<Vec<_>>>()?;
        // Names taken are refused before anything is built: what `building` notes is this call's alone, even where
        // it is dropped while the server refuses a name.
        let names = scene.meshes.keys().map(|mesh| format!("{name}.{mesh}"));
        let transforms = scene.motion_transforms();
        let names = names.chain(transforms.iter().map(|(index, _, _)| format!("{name}.{index}.motion")));
        let existing = self.accels().await?;
        if let Some(taken) = names.chain([name.to_owned()]).find(|new| existing.iter().any(|a| &a.name == new)) {
            return Err(Error::Status(tonic::Status::already_exists(format!("accel {taken:?} already exists"))));
        }
        let mut children = Vec::new();
        for (mesh, loaded) in &meshes {
            let child = format!("{name}.{mesh}");
            noted(building, &child, self.build_mesh(&child, loaded, device, BuildFlags::empty())).await?;
            children.push(child);
        }
        for (index, mesh, transform) in transforms {
            let child = format!("{name}.{index}.motion");
            let placed = format!("{name}.{mesh}");
            noted(building, &child, self.build_transform_input(&child, device, &placed, &transform)).await?;
            children.push(child);
        }
        let children: Vec<&str> = children.iter().map(String::as_str).collect();
        let motion = scene.motion_options();
        noted(building, name, self.build_moving_instances(name, device, &children, &records, flags, &motion)).await
    }

    /// Destroys the accels called `names` that exist, the last first (so that an accel goes before those it
    /// places); best effort, as the clean-up of a call that has already failed. Returns those it could not
    /// destroy, with the first reason.
    pub async fn destroy_in_reverse(&self, names: &[String]) -> Option<(Vec<String>, Error)> {
        let mut left: Option<(Vec<String>, Error)> = None;
        for name in names.iter().rev() {
            match self.destroy_accel(name).await {
                Ok(()) => {}
                Err(e) if e.code() == tonic::Code::NotFound => {}
                Err(e) => left.get_or_insert_with(|| (Vec::new(), e)).0.push(name.clone()),
            }
        }
        left
    }
}

/// Runs `build`, the build of accel `name`, noted in `building` while it runs and after it succeeds: one that fails
/// made nothing (and its name may be another accel's, which must stay).
async fn noted<T>(building: &mut Vec<String>, name: &str, build: impl Future<Output = Result<T>>) -> Result<T> {
    building.push(name.to_owned());
    let built = build.await;
    if built.is_err() {
        building.pop();
    }
    built
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

    #[test]
    fn moving_instances_get_srt_transforms_after_the_meshes() {
        let text = r#"{
            "meshes": { "a": "a.obj" },
            "motion": { "keys": 3, "time": [-1, 2], "end_vanish": true },
            "instances": [
                { "mesh": "a" },
                { "mesh": "a", "motion": { "time": [0, 1], "start_vanish": true,
                  "keys": [{ "rotate": [0, 0, 1, 170] }, { "scale": 2, "rotate": [0, 0, 1, -170], "translate": [1, 2, 3] }] } }
            ]
        }"#;
        let scene: Scene = serde_json::from_str(text).unwrap();
        let records = scene.records().unwrap();
        assert_eq!((records[0].child, records[1].child), (0, 1), "the moving instance places its transform");
        assert_eq!(scene.motion_options().keys, 3);
        assert_eq!(scene.motion_options().flags, MotionFlags::END_VANISH);
        let transforms = scene.motion_transforms();
        let [(1, "a", TransformInput::SrtMotion { keys, motion })] = transforms.as_slice() else {
            panic!("one SRT transform: {transforms:?}")
        };
        assert_eq!((motion.keys, motion.time_begin, motion.time_end), (2, 0.0, 1.0));
        assert_eq!(motion.flags, MotionFlags::START_VANISH);
        assert_eq!((keys[1][0], keys[1][4], keys[1][7], &keys[1][13..]), (2.0, 2.0, 2.0, &[1.0, 2.0, 3.0][..]));
        let (q0, q1) = (Quat::from_slice(&keys[0][9..13]), Quat::from_slice(&keys[1][9..13]));
        assert!(q0.dot(q1) > 0.0, "-170° is taken the short way from 170° (20° apart), not 340° round");
        assert!(TransformInput::SrtMotion { keys: keys.clone(), motion: *motion }.check().is_ok());
    }

    #[test]
    fn instances_the_server_would_refuse_are_refused_naming_them_before_anything_is_built() {
        let refused = |instance: &str, motion: &str| {
            let text =
                format!(r#"{{ "meshes": {{ "a": "a.obj" }}, {motion} "instances": [{{ "mesh": "a" }}, {instance}] }}"#);
            let scene: Scene = serde_json::from_str(&text).unwrap();
            scene.records().unwrap_err().to_string()
        };
        let one_key = r#"{ "mesh": "a", "motion": { "time": [0, 1], "keys": [{ "translate": [1, 0, 0] }] } }"#;
        let backwards = r#"{ "mesh": "a", "motion": { "time": [1, 0], "keys": [{}, { "translate": [1, 0, 0] }] } }"#;
        let flat = r#"{ "mesh": "a", "scale": [1, 0, 1] }"#;
        let singular = r#"{ "mesh": "a", "transform": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0] }"#;
        for (instance, field) in [(one_key, "instances[1].motion: "), (backwards, "instances[1].motion: ")] {
            let error = refused(instance, "");
            assert!(error.starts_with(field) && error.contains("key"), "{error}");
        }
        for instance in [flat, singular] {
            assert_eq!(refused(instance, ""), "instances[1].transform: must be finite and invertible");
        }
        let error = refused(r#"{ "mesh": "a" }"#, r#""motion": { "keys": 2, "time": [1, 1] },"#);
        assert!(error.starts_with("motion: time_end 1 must be greater than time_begin 1"), "{error}");
    }
}
