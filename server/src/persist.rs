//! Persistence under `--data-dir`: every buffer and accel of a tenant lives in a file of its own, written
//! atomically (a temporary file in the same directory, fsync, rename over the old one, fsync of the directory), so
//! a crash or `kill -9` at any moment leaves either the old or the new file, never a torn one. The write is two
//! steps: [`Store::prepare_buffer`] or [`Store::prepare_accel`] writes and syncs the temporary file, which takes as
//! long as the object is large; [`Prepared::put`] renames it into place, which is quick, so that callers can order
//! the renames of concurrent changes under a lock without holding it through the writes. At start the files are
//! read back; one that is unreadable, corrupt or of another format is reported and skipped, never fatal.
//!
//! Layout: `<data-dir>/tenants/<tenant>/buffers/<id>.buf` and `<data-dir>/tenants/<tenant>/accels/<handle>.acc`.
//! Each file: `0 magic "RAYDOBJ1" | 8 record length u32 (LE) | 12 record (JSON) | payload | CRC-32 u32 (LE) of
//! everything before it`. The payload is a buffer's bytes, or an accel's blob (`rayd_engine::serialize`) with its
//! children referred to, not embedded: the record lists them, and they are restored first. `<data-dir>/tenants/
//! <tenant>/issued` is a file of the same form whose record is the number past every id and handle given so far
//! ([`Store::highest_issued`]), and whose payload is empty.

use std::fs::{self, File};
use std::io::{self, ErrorKind, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};

use bytes::Bytes;
use serde::{Deserialize, Serialize};

/// The first bytes of every file.
const MAGIC: &[u8; 8] = b"RAYDOBJ1";
/// Suffix of files being written.
const TEMPORARY: &str = "tmp";

/// What a buffer file records besides the bytes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BufferRecord {
    /// `buf-N`.
    pub id: String,
    /// The caller's name, or empty.
    pub name: String,
}

/// A child of a stored accel, as it was when the accel was stored.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChildRecord {
    /// Its handle.
    pub handle: String,
    /// Its version (updates so far) then.
    pub version: u64,
}

/// What an accel file records besides the blob.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct AccelRecord {
    /// The tenant's name for it.
    pub name: String,
    /// `acc-N`.
    pub handle: String,
    /// Its device.
    pub device: String,
    /// How long its build took.
    pub build_ns: u64,
    /// Updates so far.
    pub version: u64,
    /// The accels it places, in the blob's order of external references.
    pub children: Vec<ChildRecord>,
}

/// The objects read back from a store.
#[derive(Debug, Default)]
pub struct Stored {
    /// Buffers, by id order.
    pub buffers: Vec<(BufferRecord, Bytes)>,
    /// Accels, in no particular order (children are not necessarily first).
    pub accels: Vec<(AccelRecord, Bytes)>,
    /// Files skipped, and why.
    pub skipped: Vec<(PathBuf, String)>,
}

/// One tenant's directory.
#[derive(Debug)]
pub struct Store {
    /// `<data-dir>/tenants/<tenant>/buffers`.
    buffers: PathBuf,
    /// `<data-dir>/tenants/<tenant>/accels`.
    accels: PathBuf,
    /// `<data-dir>/tenants/<tenant>/issued`: [`Store::highest_issued`], as last written.
    issued_file: PathBuf,
    /// [`Store::highest_issued`] (held while it is raised: raises are written in turn).
    issued: Mutex<u64>,
    /// Numbers temporary files, so concurrent writes of one object never share one.
    next_temporary: AtomicU64,
}

/// What `issued` holds.
#[derive(Debug, Serialize, Deserialize)]
struct IssuedRecord {
    /// [`Store::highest_issued`].
    highest: u64,
}

/// [`Store::highest_issued`] is raised this far past the number that needs it, so that it is written once in this
/// many new objects, not for each.
const ISSUED_STEP: u64 = 1024;

/// The number in a `prefix-N` id or handle (`buf-7`, `acc-12`).
pub fn id_number(id: &str) -> Option<u64> {
    id.split_once('-')?.1.parse().ok()
}

impl Store {
    /// Opens (creating it if needed) tenant `tenant`'s directory under `data_dir`, and removes temporary files a
    /// crash left behind (one that cannot be removed is left, with a warning).
    pub fn open(data_dir: &Path, tenant: &str) -> io::Result<Store> {
        let root = data_dir.join("tenants").join(tenant);
        // Numbered from the time, so that a temporary file an earlier run could not remove is not reused.
        let since_epoch = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        let next_temporary = AtomicU64::new(since_epoch.as_nanos() as u64);
        let issued_file = root.join("issued");
        let issued = match read::<IssuedRecord>(&issued_file) {
            Ok((record, _)) => record.highest,
            Err(why) => {
                if issued_file.exists() {
                    tracing::warn!(path = %issued_file.display(), %why, "the highest id issued is not known");
                }
                0
            }
        };
        let store = Store {
            buffers: root.join("buffers"),
            accels: root.join("accels"),
            issued_file,
            issued: Mutex::new(issued),
            next_temporary,
        };
        for dir in [&store.buffers, &store.accels, &root] {
            fs::create_dir_all(dir)?;
            for entry in fs::read_dir(dir)? {
                let path = entry?.path();
                // One that cannot be removed (a directory of that name, say) is left: it is never read.
                if path.extension().is_some_and(|e| e == TEMPORARY)
                    && let Err(e) = fs::remove_file(&path)
                {
                    tracing::warn!(path = %path.display(), %e, "a temporary file could not be removed");
                }
            }
        }
        // Directories just made are durable once their parents are synced: up to the data directory.
        for dir in [&store.buffers, &store.accels, &root, &data_dir.join("tenants"), data_dir] {
            File::open(dir)?.sync_all()?;
        }
        Ok(store)
    }

    /// Writes a buffer's file, to replace any file of the same id once [put](Prepared::put).
    pub fn prepare_buffer(&self, record: &BufferRecord, data: &[u8]) -> io::Result<Prepared> {
        self.remember_issued(&record.id)?;
        self.prepare(self.buffers.join(format!("{}.buf", record.id)), record, data)
    }

    /// Writes an accel's file, to replace any file of the same handle once [put](Prepared::put).
    pub fn prepare_accel(&self, record: &AccelRecord, blob: &[u8]) -> io::Result<Prepared> {
        self.remember_issued(&record.handle)?;
        self.prepare(self.accels.join(format!("{}.acc", record.handle)), record, blob)
    }

    /// Forgets a buffer.
    pub fn remove_buffer(&self, id: &str) -> io::Result<()> {
        remove(&self.buffers, &format!("{id}.buf"))
    }

    /// Forgets an accel.
    pub fn remove_accel(&self, handle: &str) -> io::Result<()> {
        remove(&self.accels, &format!("{handle}.acc"))
    }

    /// A number at or above that of every id and handle (of a buffer or an accel) whose file was ever written here,
    /// deleted since or not: numbers at start go past it, so that no id or handle a client was given names another
    /// object after a restart.
    pub fn highest_issued(&self) -> u64 {
        *self.issued.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Raises [`Store::highest_issued`] past `id`'s number, durably, before a file of that id is written (in steps:
    /// a write in [`ISSUED_STEP`] new objects). Deletes need no write, so a full disk can still be freed.
    fn remember_issued(&self, id: &str) -> io::Result<()> {
        let Some(number) = id_number(id) else { return Ok(()) };
        let mut issued = self.issued.lock().unwrap_or_else(PoisonError::into_inner);
        if number > *issued {
            let highest = number.saturating_add(ISSUED_STEP);
            self.prepare(self.issued_file.clone(), &IssuedRecord { highest }, &[])?.put()?;
            *issued = highest;
        }
        Ok(())
    }

    /// Reads every stored object back; files that cannot be read, or whose record names another object than the
    /// file does, are listed in [`Stored::skipped`].
    pub fn read_all(&self) -> io::Result<Stored> {
        let mut stored = Stored::default();
        for path in files(&self.buffers, "buf")? {
            match read(&path).and_then(|(record, data)| named_as_file(&path, record, |r: &BufferRecord| &r.id, data)) {
                Ok(object) => stored.buffers.push(object),
                Err(reason) => stored.skipped.push((path, reason)),
            }
        }
        for path in files(&self.accels, "acc")? {
            match read(&path).and_then(|(record, blob)| named_as_file(&path, record, |r: &AccelRecord| &r.handle, blob))
            {
                Ok(object) => stored.accels.push(object),
                Err(reason) => stored.skipped.push((path, reason)),
            }
        }
        Ok(stored)
    }

    /// Writes record and payload to a temporary file beside `path` and syncs it: the first step of writing `path`
    /// atomically.
    fn prepare(&self, path: PathBuf, record: &impl Serialize, payload: &[u8]) -> io::Result<Prepared> {
        let record = serde_json::to_vec(record).map_err(io::Error::other)?;
        let record_len = u32::try_from(record.len()).map_err(io::Error::other)?;
        let number = self.next_temporary.fetch_add(1, Ordering::Relaxed);
        // Removes the temporary file if writing it fails.
        let prepared = Prepared { temporary: path.with_extension(format!("{number}.{TEMPORARY}")), path };
        let mut file = io::BufWriter::with_capacity(1 << 20, File::create(&prepared.temporary)?);
        let mut crc = crc32fast::Hasher::new();
        for part in [&MAGIC[..], &record_len.to_le_bytes(), &record, payload] {
            crc.update(part);
            file.write_all(part)?;
        }
        file.write_all(&crc.finalize().to_le_bytes())?;
        file.into_inner().map_err(io::IntoInnerError::into_error)?.sync_all()?;
        Ok(prepared)
    }
}

/// An object's file written and synced under a temporary name, not yet in place: [`Prepared::put`] puts it there;
/// dropped without that, the temporary file is removed.
#[derive(Debug)]
#[must_use = "a prepared file is removed unless it is put in place"]
pub struct Prepared {
    /// The file's name once in place.
    path: PathBuf,
    /// Its name until then.
    temporary: PathBuf,
}

impl Prepared {
    /// Renames the file into place, replacing the object's old file, and syncs the directory (opened first, so
    /// that running out of file descriptors fails the put before it changes anything).
    pub fn put(self) -> io::Result<()> {
        let directory = File::open(self.path.parent().expect("a file in a directory"))?;
        fs::rename(&self.temporary, &self.path)?;
        directory.sync_all()
    }
}

impl Drop for Prepared {
    fn drop(&mut self) {
        // After a rename the temporary name is gone, and this fails harmlessly.
        let _ = fs::remove_file(&self.temporary);
    }
}

/// Removes `dir/name` durably; a file that is already gone is fine. The directory is opened first, as in
/// [`Prepared::put`].
fn remove(dir: &Path, name: &str) -> io::Result<()> {
    let directory = File::open(dir)?;
    match fs::remove_file(dir.join(name)) {
        Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
        _ => {}
    }
    directory.sync_all()
}

/// The data directory held by this process: a lock on `<data-dir>/lock`, let go when dropped or when the process
/// ends, however it ends. Two rayd processes on one data directory would overwrite each other's files.
#[derive(Debug)]
pub struct DataDirLock {
    /// The locked file; none where the directory cannot be written (nor then overwritten by anyone).
    _file: Option<File>,
}

impl DataDirLock {
    /// Makes `data_dir` if needed and takes its lock; an error of kind `WouldBlock` if another process holds it.
    pub fn take(data_dir: &Path) -> io::Result<DataDirLock> {
        fs::create_dir_all(data_dir)?;
        let path = data_dir.join("lock");
        match fs::OpenOptions::new().create(true).append(true).open(&path) {
            Ok(made) => drop(made),
            // One there already is locked as it is. Where none can be made (a read-only, forbidden or full
            // directory), rayd starts unlocked, as before it had locks, and says so.
            Err(_) if path.exists() => {}
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::ReadOnlyFilesystem | ErrorKind::PermissionDenied | ErrorKind::StorageFull
                ) =>
            {
                tracing::warn!(path = %path.display(), %e, "the data directory is not locked");
                return Ok(DataDirLock { _file: None });
            }
            Err(e) => return Err(e),
        }
        // Held open read-only where the lock allows it: a file open for writing would keep its file system from
        // being remounted read-only. Over NFS an exclusive lock needs the file open for writing.
        let read_only = File::open(&path)?;
        let file = match read_only.try_lock() {
            Err(fs::TryLockError::Error(_)) => {
                let writable = fs::OpenOptions::new().read(true).write(true).open(&path)?;
                writable.try_lock().map(|()| writable)
            }
            locked => locked.map(|()| read_only),
        };
        match file {
            Ok(file) => Ok(DataDirLock { _file: Some(file) }),
            Err(fs::TryLockError::WouldBlock) => Err(ErrorKind::WouldBlock.into()),
            Err(fs::TryLockError::Error(e)) => Err(e),
        }
    }
}

/// The files of `dir` with extension `extension`, sorted.
fn files(dir: &Path, extension: &str) -> io::Result<Vec<PathBuf>> {
    let mut paths: Vec<PathBuf> = fs::read_dir(dir)?
        .map(|entry| entry.map(|e| e.path()))
        .filter(|path| path.as_ref().map_or(true, |p| p.extension().is_some_and(|e| e == extension)))
        .collect::<io::Result<_>>()?;
    paths.sort();
    Ok(paths)
}

/// `record` and its `payload`, if the record's id (`id`) is the file's name: an object is deleted by removing the file
/// its id names, so one read from another file would come back after its delete.
fn named_as_file<R>(path: &Path, record: R, id: impl Fn(&R) -> &String, payload: Bytes) -> Result<(R, Bytes), String> {
    match path.file_stem().is_some_and(|stem| *stem == **id(&record)) {
        true => Ok((record, payload)),
        false => Err(format!("its record names {:?}, not the file's name", id(&record))),
    }
}

/// Reads and checks one file: its record and payload, or why it cannot be used. Only a regular file is read: a link,
/// a pipe or a device could hold startup forever or fill the memory.
fn read<R: for<'de> Deserialize<'de>>(path: &Path) -> Result<(R, Bytes), String> {
    let kind = fs::symlink_metadata(path).map_err(|e| format!("cannot be read: {e}"))?.file_type();
    if !kind.is_file() {
        return Err("not a regular file (a link, a pipe, a device or a directory)".into());
    }
    let bytes = fs::read(path).map_err(|e| format!("cannot be read: {e}"))?;
    let body_len = bytes.len().checked_sub(4).filter(|&n| n >= 12).ok_or("too short to be an object file")?;
    let (body, crc) = bytes.split_at(body_len);
    if &body[..8] != MAGIC {
        return Err("not an object file (bad magic)".into());
    }
    if crc32fast::hash(body).to_le_bytes() != crc {
        return Err("checksum mismatch: the file is damaged".into());
    }
    let record_len = u32::from_le_bytes(body[8..12].try_into().expect("4 bytes")) as usize;
    let record_end =
        12usize.checked_add(record_len).filter(|&end| end <= body_len).ok_or("record overruns the file")?;
    let record = serde_json::from_slice(&body[12..record_end]).map_err(|e| format!("bad record: {e}"))?;
    let mut bytes = Bytes::from(bytes);
    bytes.truncate(body_len);
    Ok((record, bytes.slice(record_end..)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("rayd-persist-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn objects_round_trip_and_damaged_files_are_skipped_with_a_reason() {
        let dir = scratch("round-trip");
        let store = Store::open(&dir, "default").unwrap();
        let buffer = BufferRecord { id: "buf-3".into(), name: "rays".into() };
        store.prepare_buffer(&buffer, b"some bytes").unwrap().put().unwrap();
        let accel = AccelRecord {
            name: "scene".into(),
            handle: "acc-9".into(),
            device: "cpu:0".into(),
            build_ns: 5,
            version: 2,
            children: vec![ChildRecord { handle: "acc-4".into(), version: 1 }],
        };
        store.prepare_accel(&accel, b"blob").unwrap().put().unwrap();
        let other = store.prepare_accel(&AccelRecord { handle: "acc-10".into(), ..accel.clone() }, b"other").unwrap();
        let dropped = store.prepare_accel(&AccelRecord { handle: "acc-11".into(), ..accel.clone() }, b"no").unwrap();
        drop(dropped);
        let accel_files = fs::read_dir(dir.join("tenants/default/accels")).unwrap().count();
        assert_eq!(accel_files, 2, "acc-9's file and acc-10's temporary one; none left of acc-11's");
        other.put().unwrap();
        let damaged = dir.join("tenants/default/accels/acc-10.acc");
        let mut bytes = fs::read(&damaged).unwrap();
        bytes[20] ^= 1;
        fs::write(&damaged, bytes).unwrap();
        fs::write(dir.join("tenants/default/buffers/buf-4.buf"), b"RAYD").unwrap();
        fs::write(dir.join("tenants/default/buffers/buf-5.0.tmp"), b"half-written").unwrap();
        fs::create_dir(dir.join("tenants/default/accels/acc-12.0.tmp")).unwrap();
        // A file whose record names another object, and a link to a file.
        fs::copy(dir.join("tenants/default/buffers/buf-3.buf"), dir.join("tenants/default/buffers/buf-7.buf")).unwrap();
        std::os::unix::fs::symlink(
            dir.join("tenants/default/buffers/buf-3.buf"),
            dir.join("tenants/default/buffers/buf-8.buf"),
        )
        .unwrap();

        let store = Store::open(&dir, "default").unwrap();
        let stored = store.read_all().unwrap();
        assert_eq!(stored.buffers, vec![(buffer, Bytes::from_static(b"some bytes"))]);
        assert_eq!(stored.accels, vec![(accel, Bytes::from_static(b"blob"))]);
        let reasons: Vec<&str> = stored.skipped.iter().map(|(_, why)| why.as_str()).collect();
        let expected = [
            "too short to be an object file",
            "its record names \"buf-3\", not the file's name",
            "not a regular file (a link, a pipe, a device or a directory)",
            "checksum mismatch: the file is damaged",
        ];
        assert_eq!(reasons, expected);
        assert!(!dir.join("tenants/default/buffers/buf-5.0.tmp").exists(), "temporary files are cleared");
        assert!(dir.join("tenants/default/accels/acc-12.0.tmp").is_dir(), "what cannot be removed is left");

        store.remove_accel("acc-9").unwrap();
        store.remove_accel("acc-9").unwrap();
        assert!(store.read_all().unwrap().accels.is_empty());
        assert_eq!(Store::open(&dir, "default").unwrap().highest_issued(), 3 + ISSUED_STEP, "past every file written");
        fs::remove_dir_all(&dir).unwrap();
    }
}
