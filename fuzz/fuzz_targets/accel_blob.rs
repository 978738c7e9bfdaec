//! Serialized accels (`rayd_engine::serialize`), as `LoadAccel` and a restart read them: arbitrary bytes behind a
//! valid magic and checksum (so that the fuzzer explores the parser, not the CRC), with no external accels. No
//! panic, no allocation beyond what the blob's own length bounds, and an error of the contract's kinds when refused;
//! an accepted blob serializes again.

#![no_main]

use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use rayd_engine::{Context, Device, ErrorKind};

fuzz_target!(|data: &[u8]| {
    static CONTEXT: OnceLock<Context> = OnceLock::new();
    let context = CONTEXT.get_or_init(|| Context::new(Device::cpu()));
    let mut blob = b"RAYDACCL\0\0\0\0".to_vec();
    blob.extend_from_slice(data);
    let crc = crc32fast::hash(&blob[12..]);
    blob[8..12].copy_from_slice(&crc.to_le_bytes());
    // The contract's kinds: a damaged blob, or one of another version or layout.
    let contract = |kind| matches!(kind, ErrorKind::InvalidArgument | ErrorKind::FailedPrecondition);
    if let Err(refused) = rayd_engine::serialize::blob_summary(&blob) {
        assert!(contract(refused.kind()), "its summary: {refused}");
    }
    match context.deserialize_accel(&blob, &[]) {
        Ok(accels) => {
            let root = accels.last().expect("a loaded blob has a root");
            context.serialize_accel(root, &[]).expect("what was loaded serializes again");
            for accel in accels.iter().rev() {
                let _ = context.destroy_accel(accel.handle());
            }
        }
        Err(refused) => assert!(contract(refused.kind()), "{refused}"),
    }
});
