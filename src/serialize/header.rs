//! The blob header (its layout is in the [module documentation](super)): sealed last, over the finished payload,
//! and read first: the magic, the checksum (damage), then compatibility (format version, byte order, backend
//! layout), then the lengths.

use super::entry::{ExternalRecord, LEAST_ENTRY_BYTES};
use super::wire::{Wire, invalid, put_u32_at, u32_at};
use crate::backend::BackendKind;
use crate::error::{Error, Result};

/// The first bytes of every blob.
pub(crate) const MAGIC: [u8; 8] = *b"RAYDACCL";
/// Bytes of the header; the payload follows.
pub(crate) const HEADER_BYTES: usize = 48;
/// The format version this build writes and reads.
pub(crate) const FORMAT_VERSION: u32 = 1;
/// The byte-order marker, as written little-endian: bytes `04 03 02 01`.
pub(crate) const BYTE_ORDER: u32 = 0x0102_0304;

/// Offset of the CRC-32 of every byte after it.
const CRC_AT: usize = 8;
/// Offset of the byte-order marker; the checksum covers everything from here.
const BYTE_ORDER_AT: usize = 12;
/// Offset of the format version.
const VERSION_AT: usize = 16;
/// Offset of the backend kind.
const BACKEND_AT: usize = 20;
/// Offset of the backend's payload layout version.
const LAYOUT_AT: usize = 24;
/// Offset of the number of accels embedded.
const ACCELS_AT: usize = 28;
/// Offset of the number of external accels.
const EXTERNAL_AT: usize = 32;
/// Offset of the reserved word (0).
const RESERVED_AT: usize = 36;
/// Offset of the payload's length (u64).
const PAYLOAD_AT: usize = 40;

/// The backend kind's code in a blob.
fn backend_code(kind: BackendKind) -> u32 {
    match kind {
        BackendKind::Cpu => 1,
        BackendKind::Wgpu => 2,
    }
}

/// What a blob's header says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Header {
    /// The backend kind's code.
    pub(crate) backend: u32,
    /// The backend's payload layout version.
    pub(crate) layout: u32,
    /// Accels embedded.
    pub(crate) accels: u32,
    /// Accels referred to.
    pub(crate) external: u32,
}

impl Header {
    /// The header of a blob for `kind`'s layout `layout`.
    pub(crate) fn new(kind: BackendKind, layout: u32, accels: u32, external: u32) -> Header {
        Header { backend: backend_code(kind), layout, accels, external }
    }

    /// Writes the header into the first [`HEADER_BYTES`] of `blob` (the payload follows them) and seals it with
    /// the checksum.
    pub(crate) fn seal(&self, blob: &mut [u8]) {
        let payload = (blob.len() - HEADER_BYTES) as u64;
        blob[..CRC_AT].copy_from_slice(&MAGIC);
        for (at, value) in [
            (BYTE_ORDER_AT, BYTE_ORDER),
            (VERSION_AT, FORMAT_VERSION),
            (BACKEND_AT, self.backend),
            (LAYOUT_AT, self.layout),
            (ACCELS_AT, self.accels),
            (EXTERNAL_AT, self.external),
            (RESERVED_AT, 0),
        ] {
            put_u32_at(blob, at, value);
        }
        blob[PAYLOAD_AT..HEADER_BYTES].copy_from_slice(&payload.to_le_bytes());
        let crc = crc32fast::hash(&blob[BYTE_ORDER_AT..]);
        put_u32_at(blob, CRC_AT, crc);
    }

    /// Reads and checks the header of `blob`: the magic, the checksum (INVALID_ARGUMENT when it does not match),
    /// the format version and byte order (FAILED_PRECONDITION when this build cannot read them), the payload's
    /// length against the blob's and the counts.
    pub(crate) fn read(blob: &[u8]) -> Result<Header> {
        if blob.get(..CRC_AT) != Some(&MAGIC[..]) {
            return Err(invalid("it does not start with the magic bytes \"RAYDACCL\": not an accel blob"));
        }
        if blob.len() < HEADER_BYTES {
            return Err(invalid(format!("{} bytes, shorter than the {HEADER_BYTES}-byte header", blob.len())));
        }
        let word = |at| u32_at(blob, at);
        let (stored, computed) = (word(CRC_AT), crc32fast::hash(&blob[BYTE_ORDER_AT..]));
        let byte_order = word(BYTE_ORDER_AT);
        if stored != computed {
            if byte_order == BYTE_ORDER.swap_bytes() && stored.swap_bytes() == computed {
                return Err(incompatible("byte order", "big-endian".into(), "little-endian".into()));
            }
            return Err(invalid(format!(
                "checksum {stored:#010x} does not match its contents' {computed:#010x}: the blob is damaged or \
                 truncated"
            )));
        }
        if byte_order != BYTE_ORDER {
            return Err(incompatible(
                "byte-order marker",
                format!("{byte_order:#010x}"),
                format!("{BYTE_ORDER:#010x}"),
            ));
        }
        let version = word(VERSION_AT);
        if version != FORMAT_VERSION {
            return Err(incompatible("format version", version.to_string(), FORMAT_VERSION.to_string()));
        }
        let reserved = word(RESERVED_AT);
        if reserved != 0 {
            return Err(invalid(format!("reserved header word is {reserved}, not 0")));
        }
        let payload = u64::from_le_bytes(std::array::from_fn(|i| blob[PAYLOAD_AT + i]));
        let actual = (blob.len() - HEADER_BYTES) as u64;
        if payload != actual {
            return Err(invalid(format!("the header gives {payload} payload bytes, the blob has {actual}")));
        }
        let header = Header {
            backend: word(BACKEND_AT),
            layout: word(LAYOUT_AT),
            accels: word(ACCELS_AT),
            external: word(EXTERNAL_AT),
        };
        if header.accels == 0 {
            return Err(invalid("the header counts no accel"));
        }
        // Counts the payload cannot hold are refused before anything (a caller's names for the accels) is sized by
        // them: the external records' array, then every record and entry, take bytes of it.
        let least =
            8 + u64::from(header.external) * ExternalRecord::SIZE as u64 + u64::from(header.accels) * LEAST_ENTRY_BYTES;
        if least > payload {
            return Err(invalid(format!(
                "the header counts {} accels and {} external ones, which take at least {least} payload bytes; the \
                 blob has {payload}",
                header.accels, header.external
            )));
        }
        Ok(header)
    }

    /// Checks that a device of `kind`, whose payload layout is `layout`, can read the blob (FAILED_PRECONDITION
    /// naming the field otherwise). Every backend stores the host structure (a wgpu accel uploads it), so a blob
    /// saved on any backend this build knows loads on any device, in the same layout.
    pub(crate) fn check_backend(&self, kind: BackendKind, layout: u32) -> Result<()> {
        if !BackendKind::ALL.map(backend_code).contains(&self.backend) {
            let known = BackendKind::ALL.map(|kind| format!("{} ({kind:?})", backend_code(kind)));
            return Err(incompatible("backend", self.backend.to_string(), known.join(" or ")));
        }
        if self.layout != layout {
            return Err(incompatible(
                "backend layout version",
                self.layout.to_string(),
                format!("{layout} ({kind:?} backend)"),
            ));
        }
        Ok(())
    }
}

/// The error of a blob this build cannot read.
fn incompatible(field: &'static str, found: String, supported: String) -> Error {
    Error::IncompatibleBlob { field, found, supported }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::ErrorKind;

    fn sealed(payload: &[u8]) -> Vec<u8> {
        let mut blob = vec![0u8; HEADER_BYTES];
        blob.extend_from_slice(payload);
        Header::new(BackendKind::Cpu, 7, 1, 2).seal(&mut blob);
        blob
    }

    #[test]
    fn a_sealed_header_reads_back_and_its_fields_sit_where_documented() {
        // The least payload one accel and two external ones take: the records' count, two records and one entry.
        let least = 8 + 2 * 28 + LEAST_ENTRY_BYTES as usize;
        let blob = sealed(&vec![0; least]);
        assert_eq!(Header::read(&blob).unwrap(), Header { backend: 1, layout: 7, accels: 1, external: 2 });
        assert_eq!(&blob[..8], b"RAYDACCL");
        assert_eq!(&blob[12..16], &[4, 3, 2, 1]);
        assert_eq!(u32_at(&blob, 16), 1);
        assert_eq!(u32_at(&blob, 8), crc32fast::hash(&blob[12..]));
        assert_eq!(blob[40] as usize, least, "payload length");
        let short = Header::read(&sealed(&vec![0; least - 1])).unwrap_err().to_string();
        assert!(short.contains("at least 140 payload bytes"), "{short}");
        Header::read(&blob).unwrap().check_backend(BackendKind::Cpu, 7).unwrap();
        Header::read(&blob).unwrap().check_backend(BackendKind::Wgpu, 7).expect("a CPU blob loads on a GPU");
        let other = Header::read(&blob).unwrap().check_backend(BackendKind::Cpu, 8).unwrap_err();
        assert_eq!(other.kind(), ErrorKind::FailedPrecondition);
    }

    #[test]
    fn a_big_endian_blob_is_incompatible_not_damaged() {
        let mut blob = sealed(&[0; 256]);
        for at in [BYTE_ORDER_AT, VERSION_AT] {
            let value = u32_at(&blob, at).swap_bytes();
            put_u32_at(&mut blob, at, value);
        }
        let crc = crc32fast::hash(&blob[BYTE_ORDER_AT..]).swap_bytes();
        put_u32_at(&mut blob, CRC_AT, crc);
        let err = Header::read(&blob).unwrap_err();
        assert!(matches!(err, Error::IncompatibleBlob { field: "byte order", .. }), "{err}");
    }
}
