//! `BuildAccel` over instances and transforms: instance accels from packed records, static transforms.

use bytes::Bytes;
use rayd_engine::accel::BuildFlags;
use rayd_engine::geometry::{INSTANCE_RECORD_BYTES, InstanceRecord, MotionOptions, TransformInput};
use rayd_proto as proto;

use crate::client::Client;
use crate::convert::{accel_ref, build_options_to_proto, motion_to_proto};
use crate::error::Result;

impl Client {
    /// Builds an instance accel called `name` on `device` over `instances`, whose `child` fields index
    /// `children` (names of accels on that device). The records go inline.
    pub async fn build_instances(
        &self,
        name: &str,
        device: &str,
        children: &[&str],
        instances: &[InstanceRecord],
        flags: BuildFlags,
    ) -> Result<proto::AccelInfo> {
        self.build_moving_instances(name, device, children, instances, flags, &MotionOptions::STATIC).await
    }

    /// [`Client::build_instances`] with motion options: a motion instance accel, whose keys bound moving children
    /// more tightly and whose vanish flags hide its instances outside its range.
    pub async fn build_moving_instances(
        &self,
        name: &str,
        device: &str,
        children: &[&str],
        instances: &[InstanceRecord],
        flags: BuildFlags,
        motion: &MotionOptions,
    ) -> Result<proto::AccelInfo> {
        let mut records = vec![0u8; instances.len() * INSTANCE_RECORD_BYTES];
        for (record, bytes) in instances.iter().zip(records.chunks_exact_mut(INSTANCE_RECORD_BYTES)) {
            record.encode(bytes);
        }
        let input = proto::InstanceInput {
            children: children.iter().map(|child| accel_ref(child)).collect(),
            instances: Some(proto::instance_input::Instances::Records(proto::DataSource {
                source: Some(proto::data_source::Source::Inline(Bytes::from(records))),
            })),
        };
        let mut request = build_request(name, device, proto::build_input::Input::Instances(input), flags);
        request.options.get_or_insert_default().motion = motion_to_proto(motion);
        self.build(request).await
    }

    /// Builds a static transform called `name` on `device` placing the accel called `child` with `transform`
    /// (object to world, 3×4 row-major).
    pub async fn build_transform(
        &self,
        name: &str,
        device: &str,
        child: &str,
        transform: [f32; 12],
    ) -> Result<proto::AccelInfo> {
        self.build_transform_input(name, device, child, &TransformInput::Static(transform)).await
    }

    /// Builds a transform of any kind (static, matrix motion or SRT motion) called `name` on `device` placing the
    /// accel called `child`.
    pub async fn build_transform_input(
        &self,
        name: &str,
        device: &str,
        child: &str,
        transform: &TransformInput,
    ) -> Result<proto::AccelInfo> {
        let mut input = proto::TransformInput { child: Some(accel_ref(child)), ..Default::default() };
        match transform {
            TransformInput::Static(matrix) => input.transform = matrix.to_vec(),
            TransformInput::MatrixMotion { keys, motion } => {
                input.matrix_keys = keys.concat();
                input.motion = motion_to_proto(motion);
            }
            TransformInput::SrtMotion { keys, motion } => {
                input.srt_keys = keys.concat();
                input.motion = motion_to_proto(motion);
            }
        }
        self.build(build_request(name, device, proto::build_input::Input::Transform(input), BuildFlags::empty())).await
    }
}

/// A build request with one input.
fn build_request(
    name: &str,
    device: &str,
    input: proto::build_input::Input,
    flags: BuildFlags,
) -> proto::BuildAccelRequest {
    proto::BuildAccelRequest {
        name: name.to_owned(),
        device: device.to_owned(),
        inputs: vec![proto::BuildInput { input: Some(input) }],
        options: Some(build_options_to_proto(flags)),
    }
}
