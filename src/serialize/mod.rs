//! Serialization of accels: a versioned, checksummed blob that carries an accel and the accels below it, and its
//! careful reading back (an incompatible or corrupt blob is refused with a precise error, never trusted).
//!
//! A blob holds an accel (the root) and every accel below it that is not external, each once (an accel placed by
//! many instances, or reached along many paths, is stored once and shared again when loaded), children before
//! their parents, the root last. External accels are referred to by their position in the list given to
//! [`Context::serialize_accel`]; [`Context::deserialize_accel`] must be given accels of the same kinds in the same
//! order (checked). Given ones with other bounds than those recorded (newer versions, as when a parent is restored
//! after its child was updated), the instance accels built over them load stale: they refuse traces until they
//! are updated (see [`Context::mark_stale`]). A loaded accel traces bit for bit as the original,
//! reports the same [`AccelInfo`](crate::accel::AccelInfo) (its `size_bytes` is that of an exact-size copy, as
//! after [`Context::copy_accel`]), and keeps what updates, compaction and random vertex access need. Only the
//! current version of an accel is serialized; an accel whose graph is stale is refused.
//!
//! # Layout
//!
//! Every number is little-endian; `f32` values are stored as their bits. An *array* is a `u64` element count
//! followed by the elements; an *optional* part is a `u32` presence flag (0 or 1) followed by the part.
//!
//! The header, 48 bytes:
//!
//! | offset | size | field |
//! |-------:|-----:|-------|
//! | 0  | 8 | magic `RAYDACCL` |
//! | 8  | 4 | CRC-32 (IEEE, as `crc32fast` computes it) of every byte from offset 12 to the end of the blob |
//! | 12 | 4 | byte-order marker `0x01020304` (bytes `04 03 02 01`) |
//! | 16 | 4 | format version: 1 |
//! | 20 | 4 | backend saved on: 1 = CPU, 2 = wgpu (its payload is the CPU layout); either loads on any device |
//! | 24 | 4 | the backend's payload layout version ([`Backend::layout_version`](crate::backend::Backend)); CPU: 1 |
//! | 28 | 4 | accels embedded, at least 1 (the root is the last) |
//! | 32 | 4 | external accels |
//! | 36 | 4 | reserved, 0 |
//! | 40 | 8 | payload bytes: the blob's length − 48 |
//!
//! Reading checks the magic, then the checksum (a mismatch means damage: INVALID_ARGUMENT), then compatibility:
//! byte order, format version, backend kind (one this build knows) and layout version (FAILED_PRECONDITION naming
//! the field, the blob's value and the supported one), then the lengths.
//!
//! The payload:
//!
//! 1. an array of external records, one per external accel, 28 bytes each: `u32` kind code, bounds as `f32`
//!    min.xyz, max.xyz;
//! 2. one entry per embedded accel:
//!    - `u32` kind: 0 triangles, 1 instances, 2 static transform, 3 matrix motion transform, 4 SRT motion
//!      transform;
//!    - `u32` build flags (0 for a transform, which has [`TRANSFORM_FLAGS`](crate::accel::TRANSFORM_FLAGS));
//!      motion options: `u32` keys, `f32` time_begin, `f32` time_end, `u32` motion flags;
//!    - `u64` triangle count, `u32` geometry count, `u64` instance count (as the accel's info reports them);
//!    - an array of `u32` child references, the accel's distinct children in the order they were first placed:
//!      bit 31 clear names an earlier accel of the blob by its position, bit 31 set names external accel
//!      `reference & 0x7fff_ffff`;
//!    - an array of the structure an update must keep, for a geometry accel with `ALLOW_UPDATE` (empty
//!      otherwise): per input 32 bytes, `u64` triangles, `u32` primitive-index offset, `u32` geometry flags, `u64`
//!      topology hash, `u64` mask hash;
//!    - an array of transform keys, as [`TransformInput`](crate::geometry::TransformInput) takes them (empty but
//!      for transforms): 12 `f32` a key (static: one key; matrix motion), 16 `f32` a key (SRT motion); the
//!      transform's motion options are the entry's;
//!    - `u64` payload length, then the backend's payload (empty for transforms, which are rebuilt from their
//!      keys and child). The CPU backend's is described in `backend/cpu/persist.rs`.
//!
//! # Trust
//!
//! Reading never trusts a blob: every length is checked against the bytes left before anything is allocated,
//! every count, index, range, flag, option, transform and triangle corner is checked (as a build would check
//! them, and as traversal relies on them), child references may only name earlier accels or the external ones,
//! graph depths and traversal stack sizes are recomputed, and a failure destroys every accel already made from the
//! blob.

mod entry;
mod header;
mod read;
pub(crate) mod wire;
mod write;

use std::sync::Arc;

use crate::context::{Accel, Context};
use crate::error::Result;
use header::{FORMAT_VERSION, Header};

/// What a blob's header says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlobSummary {
    /// The blob format's version.
    pub format_version: u32,
    /// Accels embedded in it (the root last).
    pub accels: u32,
    /// Accels it refers to without embedding them, which a load must supply in order.
    pub external: u32,
    /// Bytes of the whole blob.
    pub total_bytes: u64,
}

/// Reads a blob's header (checked, checksum included; the backend fields are checked by a load, against the
/// context's device).
pub fn blob_summary(blob: &[u8]) -> Result<BlobSummary> {
    let header = Header::read(blob)?;
    Ok(BlobSummary {
        format_version: FORMAT_VERSION,
        accels: header.accels,
        external: header.external,
        total_bytes: blob.len() as u64,
    })
}

impl Context {
    /// Serializes `accel` and every accel below it that is not one of `external` (which are referred to by their
    /// position in that list instead of being embedded). Every accel must be of this context's device and the
    /// accel's graph current (FAILED_PRECONDITION otherwise).
    pub fn serialize_accel(&self, accel: &Arc<Accel>, external: &[Arc<Accel>]) -> Result<Vec<u8>> {
        write::blob(self, accel, external)
    }

    /// Creates in this context every accel a blob embeds, children first, the root last, and returns them;
    /// `external` supplies, in order, the accels the blob refers to (as many, of the recorded kinds and this
    /// context's device; those whose bounds changed since leave the instance accels over them stale). A damaged
    /// or inconsistent blob is INVALID_ARGUMENT, one this build cannot read FAILED_PRECONDITION; on any error no
    /// accel is left behind.
    pub fn deserialize_accel(&self, blob: &[u8], external: &[Arc<Accel>]) -> Result<Vec<Arc<Accel>>> {
        read::accels(self, blob, external)
    }
}
