//! rayd's gRPC contract, package `rayd.v1`, generated from the `.proto` files beside this crate (the single
//! source of truth; nothing here is edited by hand). Bulk `bytes` fields are `bytes::Bytes`, so buffers move
//! without copies.

#[allow(missing_docs, clippy::all)]
mod generated {
    tonic::include_proto!("rayd.v1");
}

pub use generated::*;

/// The encoded `FileDescriptorSet` of every rayd `.proto` file, for gRPC server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/rayd_descriptor.bin"));
