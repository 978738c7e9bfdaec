//! Transforms that place one accel: static (OptiX `OptixStaticTransform`), matrix motion
//! (`OptixMatrixMotionTransform`: a 3×4 matrix a key, interpolated per element) and SRT motion
//! (`OptixSRTMotionTransform`: scale/shear/pivot, a quaternion interpolated by nlerp, a translation; C = T·R·S).

use glam::{Affine3A, Mat3A, Quat, Vec3, Vec3A};

use super::instance::Placement;
use super::motion::{Bounds, EMPTY, MotionOptions, Piece, TimeSpan, corners, is_empty, lerp, map_bounds, pad, union};
use crate::error::{Error, Result};

/// Floats of one SRT key.
pub const SRT_KEY_FLOATS: usize = 16;

/// Parts each segment of a motion transform is cut into when its boxes over time are computed.
const BOUND_CUTS: usize = 8;

/// Parts each segment of a motion transform's [`box_motion`] is checked in when its boxes at the keys are fitted. A
/// fit holds what moves within a part as if it filled the part at every time of it, and each transform of a chain
/// adds its own such widening to its child's: finer parts keep the sum small (six transforms each sliding a unit box
/// by 0.63 over 64 keys: a box over all of time 0.8% longer than its path with 8 parts, 0.25% with 32).
const KEY_FIT_CUTS: usize = 32;

/// About how many segments a motion transform's boxes are kept at over its time range ([`box_motion`]): enough to
/// follow a child that moves between the transform's keys, and for the boxes that parents fit at their own keys from
/// them to be nearly as tight as those they would fit from the transform's boxes worked out anew.
const BOX_SEGMENTS: u32 = 64;

/// A transform as a caller gives it.
#[derive(Debug, Clone, PartialEq)]
pub enum TransformInput {
    /// One object-to-world 3×4 row-major matrix (`m00 m01 m02 tx | m10 m11 m12 ty | m20 m21 m22 tz`).
    Static([f32; 12]),
    /// One 3×4 row-major matrix a motion key (at least 2 keys).
    MatrixMotion {
        /// The matrices, as many as `motion.keys`.
        keys: Vec<[f32; 12]>,
        /// Keys, time range and vanish flags.
        motion: MotionOptions,
    },
    /// One SRT key a motion key (at least 2 keys): `sx a b pvx sy c pvy sz pvz qx qy qz qw tx ty tz`, the
    /// seeds' layout: S = `[sx a b pvx | 0 sy c pvy | 0 0 sz pvz]`, R the quaternion `(qx, qy, qz, qw)`, T the
    /// translation `(tx, ty, tz)`; the key's transform is C = T·R·S.
    SrtMotion {
        /// The keys, as many as `motion.keys`.
        keys: Vec<[f32; SRT_KEY_FLOATS]>,
        /// Keys, time range and vanish flags.
        motion: MotionOptions,
    },
}

/// One SRT key, checked: its quaternion normalized.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SrtKey {
    /// Scale, shear and pivot: the upper triangle `sx a b | sy c | sz` and `(pvx, pvy, pvz)`.
    scale: [f32; 9],
    /// The rotation, unit length.
    rotation: Quat,
    /// The translation after the rotation.
    translation: Vec3,
}

/// A checked transform: what traversal asks for its placement at a ray's time.
#[derive(Debug, Clone, PartialEq)]
pub enum Transform {
    /// The same placement at every time.
    Static(Placement),
    /// Matrices interpolated per element.
    Matrix {
        /// One affine map a key.
        keys: Vec<Affine3A>,
        /// Its motion.
        motion: MotionOptions,
    },
    /// SRT keys.
    Srt {
        /// One key a key.
        keys: Vec<SrtKey>,
        /// Its motion.
        motion: MotionOptions,
    },
}

/// The error for key `key` of a transform.
fn bad_key(key: usize, rule: impl Into<String>) -> Error {
    Error::InvalidBuildInput { input: 0, field: "transform.keys", element: Some(key as u64), rule: rule.into() }
}

/// The affine map of a 3×4 row-major matrix, if finite and invertible.
fn affine(key: usize, matrix: &[f32; 12]) -> Result<Affine3A> {
    Placement::new(matrix).map(|p| p.object_to_world).ok_or_else(|| bad_key(key, "must be finite and invertible"))
}

impl SrtKey {
    /// Reads and checks key `key`: finite, S invertible (`sx·sy·sz ≠ 0`), a non-zero quaternion (normalized here).
    fn new(key: usize, v: &[f32; SRT_KEY_FLOATS]) -> Result<SrtKey> {
        if !v.iter().all(|x| x.is_finite()) {
            return Err(bad_key(key, "every SRT value must be finite"));
        }
        let [sx, a, b, pvx, sy, c, pvy, sz, pvz, qx, qy, qz, qw, tx, ty, tz] = *v;
        if sx * sy * sz == 0.0 {
            return Err(bad_key(key, "scale sx·sy·sz is 0: S must be invertible"));
        }
        let rotation = Quat::from_xyzw(qx, qy, qz, qw);
        let length = rotation.length();
        let rotation = if length > 0.0 && length.is_finite() {
            rotation / length
        } else {
            // Its length overflows or underflows f32: normalized by way of its largest component.
            let largest = [qx, qy, qz, qw].into_iter().fold(0.0, |most: f32, q| most.max(q.abs()));
            if largest == 0.0 {
                return Err(bad_key(key, "the quaternion (qx, qy, qz, qw) must not be 0"));
            }
            let scaled = rotation / largest;
            scaled / scaled.length()
        };
        Ok(SrtKey { scale: [sx, a, b, sy, c, sz, pvx, pvy, pvz], rotation, translation: Vec3::new(tx, ty, tz) })
    }

    /// S as an affine map.
    fn scale_map(&self) -> Affine3A {
        let [sx, a, b, sy, c, sz, pvx, pvy, pvz] = self.scale;
        Affine3A::from_cols(
            Vec3A::new(sx, 0.0, 0.0),
            Vec3A::new(a, sy, 0.0),
            Vec3A::new(b, c, sz),
            Vec3A::new(pvx, pvy, pvz),
        )
    }

    /// The key `f` of the way from `self` to `next`: S and T per element, R by nlerp.
    fn interpolate(&self, next: &SrtKey, f: f32) -> SrtKey {
        let mut scale = [0.0; 9];
        for (i, s) in scale.iter_mut().enumerate() {
            *s = self.scale[i] * (1.0 - f) + next.scale[i] * f;
        }
        let rotation = (self.rotation * (1.0 - f) + next.rotation * f).normalize();
        SrtKey { scale, rotation, translation: lerp(self.translation, next.translation, f) }
    }

    /// The key as the wgpu kernel reads it: `sx a b sy c sz pvx pvy pvz` (S's upper triangle, then the pivot),
    /// `qx qy qz qw` (R, unit length), `tx ty tz`.
    #[cfg(feature = "wgpu")]
    pub(crate) fn floats(&self) -> [f32; SRT_KEY_FLOATS] {
        let ([s0, s1, s2, s3, s4, s5, s6, s7, s8], q, t) = (self.scale, self.rotation, self.translation);
        [s0, s1, s2, s3, s4, s5, s6, s7, s8, q.x, q.y, q.z, q.w, t.x, t.y, t.z]
    }

    /// C = T·R·S.
    fn combined(&self) -> Affine3A {
        Affine3A::from_rotation_translation(self.rotation, self.translation) * self.scale_map()
    }
}

impl TransformInput {
    /// Bytes its motion keys take once built (none for a static transform): [`Transform::key_bytes`].
    pub fn key_bytes(&self) -> u64 {
        match self {
            TransformInput::Static(_) => 0,
            TransformInput::MatrixMotion { keys, .. } => key_bytes::<Affine3A>(keys.len()),
            TransformInput::SrtMotion { keys, .. } => key_bytes::<SrtKey>(keys.len()),
        }
    }

    /// Bytes its boxes at the keys take once built (none for a static transform): [`Transform::key_bounds`].
    pub fn key_bounds_bytes(&self) -> u64 {
        match self {
            TransformInput::Static(_) => 0,
            TransformInput::MatrixMotion { motion, .. } | TransformInput::SrtMotion { motion, .. } => {
                key_bytes::<Bounds>(box_motion(motion).keys as usize)
            }
        }
    }

    /// Checks the transform: matrices finite and invertible, SRT keys as [`SrtKey`] says, as many keys as the
    /// motion options (at least 2 for motion transforms), quaternions of neighbouring SRT keys less than 180°
    /// apart (a positive dot product, as the seeds require for nlerp's shortest path).
    pub fn check(&self) -> Result<Transform> {
        match self {
            TransformInput::Static(matrix) => {
                Placement::new(matrix).map(Transform::Static).ok_or_else(|| Error::InvalidBuildInput {
                    input: 0,
                    field: "transform",
                    element: None,
                    rule: "must be finite and invertible".into(),
                })
            }
            TransformInput::MatrixMotion { keys, motion } => {
                check_motion(motion, keys.len())?;
                let keys = keys.iter().enumerate().map(|(k, m)| affine(k, m)).collect::<Result<_>>()?;
                Ok(Transform::Matrix { keys, motion: *motion })
            }
            TransformInput::SrtMotion { keys, motion } => {
                check_motion(motion, keys.len())?;
                let keys: Vec<SrtKey> =
                    keys.iter().enumerate().map(|(k, v)| SrtKey::new(k, v)).collect::<Result<_>>()?;
                if let Some(k) = keys.windows(2).position(|pair| pair[0].rotation.dot(pair[1].rotation) <= 0.0) {
                    return Err(bad_key(
                        k + 1,
                        format!("its quaternion is 180° or more from key {k}'s (dot product not positive): add keys"),
                    ));
                }
                Ok(Transform::Srt { keys, motion: *motion })
            }
        }
    }
}

/// Checks a motion transform's options against its key count.
fn check_motion(motion: &MotionOptions, keys: usize) -> Result<()> {
    let fail = |rule| Error::InvalidBuildInput { input: 0, field: "transform.motion", element: None, rule };
    motion.check().map_err(fail)?;
    if motion.is_static() {
        return Err(fail("a motion transform needs at least 2 motion keys".into()));
    }
    motion.check_key_count(keys, "transform.keys")
}

/// The motion of the boxes a motion transform of `motion` keeps ([`Transform::key_bounds`]): its time range and
/// flags, each of its segments cut into the most equal parts that keep them within [`BOX_SEGMENTS`] (one part when
/// it has more), so that its own keys are among theirs. Motion of fewer than 2 keys, which [`TransformInput::check`]
/// refuses, is taken as 2 keys' (no division by zero for an input not yet checked).
fn box_motion(motion: &MotionOptions) -> MotionOptions {
    let segments = motion.keys.max(2) - 1;
    MotionOptions { keys: segments * (BOX_SEGMENTS / segments).max(1) + 1, ..*motion }
}

/// Bytes that `keys` motion keys of type `K` take.
fn key_bytes<K>(keys: usize) -> u64 {
    (keys * size_of::<K>()) as u64
}

impl Transform {
    /// Bytes its motion keys take (none for a static transform).
    pub fn key_bytes(&self) -> u64 {
        match self {
            Transform::Static(_) => 0,
            Transform::Matrix { keys, .. } => key_bytes::<Affine3A>(keys.len()),
            Transform::Srt { keys, .. } => key_bytes::<SrtKey>(keys.len()),
        }
    }

    /// Its motion options (static for a static transform).
    pub fn motion(&self) -> MotionOptions {
        match self {
            Transform::Static(_) => MotionOptions::STATIC,
            Transform::Matrix { motion, .. } | Transform::Srt { motion, .. } => *motion,
        }
    }

    /// The placement at `time`; `None` when the transform has vanished then, or its interpolated map is singular
    /// (nothing below it can be hit at that time).
    #[inline]
    pub fn placement_at(&self, time: f32) -> Option<Placement> {
        match self {
            Transform::Static(placement) => Some(*placement),
            Transform::Matrix { keys, motion } => {
                let k = motion.locate(time)?;
                let next = &keys[(k.segment + 1).min(keys.len() - 1)];
                Placement::from_affine(interpolate_affine(&keys[k.segment], next, k.fraction))
            }
            Transform::Srt { keys, motion } => {
                let k = motion.locate(time)?;
                let next = &keys[(k.segment + 1).min(keys.len() - 1)];
                Placement::from_affine(keys[k.segment].interpolate(next, k.fraction).combined())
            }
        }
    }

    /// Boxes at the keys of its [`box_motion`] whose interpolation holds the child, placed, at every time, given the
    /// child's box over any span (`child`; see [`MotionOptions::fit_key_bounds`]); none for a static transform.
    /// With them, [`Transform::bounds_with_keys`] bounds a motion transform over any span without asking its child:
    /// a chain of motion transforms each asking its child for every piece of a span would ask the bottom of the
    /// chain a number of times that grows exponentially with its depth.
    pub fn key_bounds(&self, child: &dyn Fn(TimeSpan) -> Bounds) -> Vec<Bounds> {
        match self {
            Transform::Static(_) => Vec::new(),
            Transform::Matrix { motion, .. } | Transform::Srt { motion, .. } => {
                box_motion(motion).fit_key_bounds(KEY_FIT_CUTS, |span| self.bounds_during(span, child))
            }
        }
    }

    /// A box holding the child, placed, at every time of `span`: the interpolation of `keys` (its
    /// [`Transform::key_bounds`]) for a motion transform; the child's box during `span` (`child`), placed, for a
    /// static one.
    pub fn bounds_with_keys(&self, keys: &[Bounds], span: TimeSpan, child: &dyn Fn(TimeSpan) -> Bounds) -> Bounds {
        match self {
            Transform::Static(placement) => placement.place_bounds(child(span)),
            Transform::Matrix { motion, .. } | Transform::Srt { motion, .. } => {
                box_motion(motion).bounds_of_keys(keys, span)
            }
        }
    }

    /// A box holding the child, placed, at every time of `span`, given the child's box over any span (`child`),
    /// which it asks for each piece of `span` (see [`MotionOptions::pieces`]).
    fn bounds_during(&self, span: TimeSpan, child: &dyn Fn(TimeSpan) -> Bounds) -> Bounds {
        let motion = match self {
            Transform::Static(placement) => return placement.place_bounds(child(span)),
            Transform::Matrix { motion, .. } | Transform::Srt { motion, .. } => motion,
        };
        motion.pieces(span, BOUND_CUTS).into_iter().fold(EMPTY, |acc, piece| {
            let piece_bounds = match piece {
                Piece::Held { span, key } => self.placed_at_key(key, child(span)),
                Piece::Moving { span, segment, from, to } => self.placed_moving(segment, from, to, child(span)),
            };
            union(acc, piece_bounds)
        })
    }

    /// `inner` placed by key `key`.
    fn placed_at_key(&self, key: usize, inner: Bounds) -> Bounds {
        match self {
            Transform::Static(placement) => placement.place_bounds(inner),
            Transform::Matrix { keys, .. } => map_bounds(&keys[key], inner),
            Transform::Srt { keys, .. } => pad(map_bounds(&keys[key].combined(), inner)),
        }
    }

    /// A box holding `inner` (which holds the child throughout) placed by the transform at every fraction from
    /// `from` to `to` of segment `segment`.
    fn placed_moving(&self, segment: usize, from: f32, to: f32, inner: Bounds) -> Bounds {
        if is_empty(&inner) {
            return inner;
        }
        match self {
            Transform::Static(placement) => placement.place_bounds(inner),
            // A point placed by the interpolated matrix moves on the segment between its places at both ends.
            Transform::Matrix { keys, .. } => {
                let at = |f: f32| interpolate_affine(&keys[segment], &keys[segment + 1], f);
                pad(union(map_bounds(&at(from), inner), map_bounds(&at(to), inner)))
            }
            Transform::Srt { keys, .. } => {
                let (start, end) = (
                    keys[segment].interpolate(&keys[segment + 1], from),
                    keys[segment].interpolate(&keys[segment + 1], to),
                );
                // S moves points linearly: both ends' boxes hold the scaled child.
                let scaled = union(map_bounds(&start.scale_map(), inner), map_bounds(&end.scale_map(), inner));
                // nlerp turns about one axis through the origin by the angle between the ends' quaternions: a point
                // runs on a circular arc, within its sagitta ρ·(1 − cos(δ/2)) of the chord between its ends.
                let rotate = |q: Quat| map_bounds(&Affine3A::from_quat(q), scaled);
                let angle = 2.0 * start.rotation.dot(end.rotation).abs().min(1.0).acos();
                let radius = corners(scaled).map(Vec3::length).into_iter().fold(0.0, f32::max);
                let sagitta = radius * 2.0 * (angle / 4.0).sin().powi(2);
                let turned = union(rotate(start.rotation), rotate(end.rotation));
                let t = (start.translation.min(end.translation), start.translation.max(end.translation));
                pad((turned.0 - sagitta + t.0, turned.1 + sagitta + t.1))
            }
        }
    }
}

/// The matrix `f` of the way from `a` to `b`, per element.
#[inline]
fn interpolate_affine(a: &Affine3A, b: &Affine3A, f: f32) -> Affine3A {
    Affine3A {
        matrix3: Mat3A::from_cols(
            a.matrix3.x_axis * (1.0 - f) + b.matrix3.x_axis * f,
            a.matrix3.y_axis * (1.0 - f) + b.matrix3.y_axis * f,
            a.matrix3.z_axis * (1.0 - f) + b.matrix3.z_axis * f,
        ),
        translation: a.translation * (1.0 - f) + b.translation * f,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::motion::MotionFlags;

    const IDENTITY_SRT: [f32; 16] = [1., 0., 0., 0., 1., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0.];

    fn two_keys() -> MotionOptions {
        over_one(2)
    }

    /// `keys` keys over [0, 1].
    fn over_one(keys: u32) -> MotionOptions {
        MotionOptions { keys, time_begin: 0.0, time_end: 1.0, flags: MotionFlags::empty() }
    }

    /// A child's box over any span.
    type Child<'a> = Box<dyn Fn(TimeSpan) -> Bounds + 'a>;

    /// The box over any span of `bottom` under `levels` (the lowest first), each bounded from its key boxes as a
    /// transform node bounds itself.
    fn chain<'a>(levels: &'a [Transform], bottom: Child<'a>) -> Child<'a> {
        levels.iter().fold(bottom, |below, t| {
            let keys = t.key_bounds(&*below);
            Box::new(move |span| t.bounds_with_keys(&keys, span, &*below))
        })
    }

    /// A matrix motion transform of `keys` keys over [0, 1] that slides along x and turns about z by a quarter.
    fn sliding(keys: u32) -> Transform {
        let key = |k: u32| {
            let (sin, cos) = (k as f32 / (keys - 1) as f32 * std::f32::consts::FRAC_PI_2).sin_cos();
            [cos, -sin, 0., 0.01 * k as f32, sin, cos, 0., 0., 0., 0., 1., 0.]
        };
        TransformInput::MatrixMotion { keys: (0..keys).map(key).collect(), motion: over_one(keys) }.check().unwrap()
    }

    /// An SRT motion transform of `keys` keys over [0, 1] that turns about z by a quarter about a pivot and moves
    /// along x by 3.
    fn turning(keys: u32) -> Transform {
        let key = |k: u32| {
            let f = k as f32 / (keys - 1) as f32;
            let mut srt = IDENTITY_SRT;
            (srt[11], srt[12]) = (f * std::f32::consts::FRAC_PI_4).sin_cos();
            (srt[13], srt[3]) = (3.0 * f, -1.0);
            srt
        };
        TransformInput::SrtMotion { keys: (0..keys).map(key).collect(), motion: over_one(keys) }.check().unwrap()
    }

    /// A static transform that stretches along x and lifts along z.
    fn stretched() -> Transform {
        TransformInput::Static([2., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 1.]).check().unwrap()
    }

    /// A box that does not move.
    fn still(_: TimeSpan) -> Bounds {
        (Vec3::new(0.5, -0.5, 0.0), Vec3::new(2.0, 0.5, 1.0))
    }

    #[test]
    fn srt_rotation_of_60_degrees_about_z_is_reached_at_the_end() {
        let half = std::f32::consts::FRAC_PI_6;
        let mut turned = IDENTITY_SRT;
        turned[11] = half.sin();
        turned[12] = half.cos();
        let t = TransformInput::SrtMotion { keys: vec![IDENTITY_SRT, turned], motion: two_keys() }.check().unwrap();
        let p = t.placement_at(1.0).unwrap().object_to_world.transform_point3(Vec3::X);
        assert!((p - Vec3::new(0.5, 3f32.sqrt() / 2.0, 0.0)).length() < 1e-6, "{p}");
        assert_eq!(t.placement_at(0.0).unwrap().object_to_world.transform_point3(Vec3::X), Vec3::X);
    }

    #[test]
    fn bounds_during_hold_the_placed_child_at_sampled_times() {
        let mut turned = IDENTITY_SRT;
        (turned[11], turned[12]) = (std::f32::consts::FRAC_1_SQRT_2, std::f32::consts::FRAC_1_SQRT_2);
        turned[13] = 3.0;
        turned[3] = -1.0; // pivot
        let srt = TransformInput::SrtMotion { keys: vec![IDENTITY_SRT, turned], motion: two_keys() }.check().unwrap();
        let matrix = TransformInput::MatrixMotion {
            keys: vec![
                [1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0.],
                [0., -2., 0., 1., 1., 0., 0., 2., 0., 0., 1., 0.],
            ],
            motion: two_keys(),
        }
        .check()
        .unwrap();
        let child = |_: TimeSpan| (Vec3::new(0.5, -0.5, 0.0), Vec3::new(2.0, 0.5, 1.0));
        for t in [srt, matrix] {
            let whole = t.bounds_during(TimeSpan { start: 0.0, end: 1.0 }, &child);
            for i in 0..=200 {
                let time = i as f32 / 200.0;
                let placement = t.placement_at(time).unwrap();
                for c in corners(child(TimeSpan::at(time))) {
                    let p = placement.object_to_world.transform_point3(c);
                    assert!(p.cmpge(whole.0).all() && p.cmple(whole.1).all(), "{p} outside {whole:?} at {time}");
                }
            }
        }
    }

    #[test]
    fn quaternions_of_any_finite_nonzero_length_are_normalized() {
        let turned = |q: [f32; 4]| {
            let mut key = IDENTITY_SRT;
            key[9..13].copy_from_slice(&q);
            TransformInput::SrtMotion { keys: vec![IDENTITY_SRT, key], motion: two_keys() }.check()
        };
        // 60° about z, at lengths whose squares overflow or underflow f32, and at 1.
        let half = std::f32::consts::FRAC_PI_6;
        let expected = turned([0.0, 0.0, half.sin(), half.cos()]).unwrap().placement_at(1.0).unwrap();
        for scale in [1e20, 1e-23, 1e-30] {
            let t = turned([0.0, 0.0, half.sin() * scale, half.cos() * scale]).unwrap();
            let p = t.placement_at(1.0).unwrap().object_to_world.transform_point3(Vec3::X);
            let q = expected.object_to_world.transform_point3(Vec3::X);
            assert!((p - q).length() < 1e-6, "scale {scale}: {p} against {q}");
        }
        let zero = turned([0.0; 4]).unwrap_err().to_string();
        assert!(zero.contains("must not be 0"), "{zero}");
    }

    #[test]
    fn bad_keys_are_refused_with_their_index() {
        let flipped = {
            let mut k = IDENTITY_SRT;
            k[12] = -1.0;
            k
        };
        let err = TransformInput::SrtMotion { keys: vec![IDENTITY_SRT, flipped], motion: two_keys() }.check();
        assert!(matches!(err, Err(Error::InvalidBuildInput { element: Some(1), .. })), "{err:?}");
        let flat = {
            let mut k = IDENTITY_SRT;
            k[7] = 0.0;
            k
        };
        assert!(TransformInput::SrtMotion { keys: vec![IDENTITY_SRT, flat], motion: two_keys() }.check().is_err());
        let one = TransformInput::MatrixMotion { keys: vec![[0.0; 12]], motion: MotionOptions::STATIC };
        assert!(one.check().is_err(), "a motion transform needs 2 keys");
        let short = TransformInput::MatrixMotion {
            keys: vec![[1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0.]],
            motion: two_keys(),
        };
        assert!(short.check().is_err(), "key count must match");
    }

    #[test]
    fn a_chain_of_motion_transforms_asks_its_bottom_as_often_whatever_its_depth() {
        // Matrix and SRT motion transforms of 64 keys and static ones, each over the last, bounded at the keys of an
        // instance accel of 64 keys placing the top: only the lowest asks the bottom for its box, the others ask
        // the boxes kept at the keys of the transform below them.
        let levels = [sliding(64), turning(64), stretched(), sliding(64)];
        let levels = [&levels[..], &levels[..]].concat();
        let asked_for_depth = |depth: usize| {
            let asked = std::cell::Cell::new(0);
            let bottom = Box::new(|span| {
                asked.set(asked.get() + 1);
                still(span)
            });
            over_one(64).fit_key_bounds(BOUND_CUTS, chain(&levels[..depth], bottom));
            asked.get()
        };
        let one = asked_for_depth(1);
        for depth in 2..=levels.len() {
            assert_eq!(asked_for_depth(depth), one, "questions of the bottom under {depth} transforms and under one");
        }
        // The lowest transform's fit asks for its box at its 64 keys, before and after them and over each part of its
        // segments, each of which asks the bottom for the few pieces it covers.
        let fitted = 64 + 2 + 63 * KEY_FIT_CUTS;
        assert!(one <= 3 * fitted, "{one} questions of the bottom for {fitted} of the lowest transform");
    }

    #[test]
    fn the_boxes_of_a_chain_hold_its_bottom_placed_at_sampled_times() {
        let levels = [turning(2), sliding(3), stretched(), turning(64)];
        let top = chain(&levels, Box::new(still));
        let whole = top(TimeSpan { start: 0.0, end: 1.0 });
        for i in 0..=500 {
            let time = i as f32 / 500.0;
            let at_time = top(TimeSpan::at(time));
            let placed = levels.iter().map(|t| t.placement_at(time).unwrap().object_to_world);
            let to_world = placed.rev().fold(Affine3A::IDENTITY, |map, level| map * level);
            for p in corners(still(TimeSpan::at(time))).map(|c| to_world.transform_point3(c)) {
                for (what, b) in [("over [0, 1]", whole), ("at its time", at_time)] {
                    assert!(p.cmpge(b.0).all() && p.cmple(b.1).all(), "{p} outside the box {what} {b:?} at {time}");
                }
            }
        }
    }

    #[test]
    fn motion_transforms_over_nothing_hold_nothing() {
        for t in [sliding(2), turning(64)] {
            let keys = t.key_bounds(&|_| EMPTY);
            for span in [TimeSpan::ALL, TimeSpan::at(0.0), TimeSpan::at(0.5), TimeSpan { start: 0.2, end: 2.0 }] {
                let b = t.bounds_with_keys(&keys, span, &|_| EMPTY);
                assert!(is_empty(&b), "{span:?}: {b:?}");
            }
        }
    }

    #[test]
    fn parents_fit_boxes_from_key_bounds_nearly_as_tight_as_from_the_transform_itself() {
        // The sum of the boxes' extents.
        let size = |boxes: &[Bounds]| boxes.iter().map(|(min, max)| (*max - *min).element_sum()).sum::<f32>();
        // A child that moves up and down through 64 keys.
        let wave: Vec<Bounds> = (0..64)
            .map(|k| (k as f32 / 63.0 * 12.0).sin())
            .map(|y| (Vec3::new(-0.5, y - 0.5, 0.0), Vec3::new(0.5, y + 0.5, 0.0)))
            .collect();
        let waving = |span| over_one(64).bounds_of_keys(&wave, span);
        let children: [(&str, &dyn Fn(TimeSpan) -> Bounds); 2] = [("a still child", &still), ("a waving one", &waving)];
        let transforms =
            [("sliding", sliding(2)), ("turning", turning(2)), ("sliding", sliding(64)), ("turning", turning(64))];
        for ((kind, t), (what, child)) in transforms.iter().flat_map(|t| children.map(|c| (t, c))) {
            let keys = t.key_bounds(child);
            // Parents fitting their boxes at their keys as an instance accel does.
            for parent in [1, 2, 3, 64].map(over_one) {
                let anew = size(&parent.fit_key_bounds(BOUND_CUTS, |span| t.bounds_during(span, child)));
                let kept = size(&parent.fit_key_bounds(BOUND_CUTS, |span| t.bounds_with_keys(&keys, span, child)));
                let case =
                    format!("{kind} by {} keys over {what} in a parent of {} keys", t.motion().keys, parent.keys);
                assert!(kept <= anew * 1.01, "{case}: boxes of {kept} from the kept keys against {anew}");
            }
        }
    }
}
