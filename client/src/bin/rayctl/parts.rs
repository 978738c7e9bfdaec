//! Files a part at a time: `rayctl trace` reads rays from `--rays` a part at a time and writes hits to `--out` (and
//! counts to `--out`.counts) as each part comes back, and `rayctl rays` writes its rays as it makes them, so that
//! rayctl holds a few parts, never the whole rays or hits.

use std::io::ErrorKind;
use std::os::fd::AsFd;
use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use bytes::{Bytes, BytesMut};
use futures_util::{Stream, StreamExt};
use rayd_client::{Error, Result, TraceParts, proto};
use rayd_engine::format::{HitFormat, RayFormat};
use rayd_engine::query::OutputLayout;
use tokio::io::{AsyncReadExt, AsyncWriteExt, BufWriter};

/// A file of packed records that `rayctl trace` reads (`--rays`, `--primary-hits`), opened: a plain file checked to
/// hold whole records, or a pipe or device read to its end.
pub struct PackedFile {
    /// It, open at its start.
    file: std::fs::File,
    /// Its size in bytes, where it is a plain file.
    size: Option<u64>,
    /// Its device and inode.
    identity: (u64, u64),
    /// What it holds.
    records: Records,
}

/// What a [`PackedFile`] holds, and where.
struct Records {
    /// Where the file is.
    path: PathBuf,
    /// The option that named it (`--rays`).
    option: &'static str,
    /// Bytes of one record.
    record_bytes: usize,
    /// The records' format.
    format: &'static str,
}

impl Records {
    /// The option and the path, as messages name the file (`--rays rays.bin`).
    fn named(&self) -> String {
        format!("{} {}", self.option, self.path.display())
    }

    /// The refusal of `bytes` bytes that are not whole records.
    fn check_whole(&self, bytes: u64) -> Result<()> {
        if bytes.is_multiple_of(self.record_bytes as u64) {
            return Ok(());
        }
        let (named, size, format) = (self.named(), self.record_bytes, self.format);
        Err(Error::InvalidArgument(format!("{named}: {bytes} bytes is not a multiple of {size} ({format})")))
    }

    /// The refusal of a file that held `size` bytes when it was opened and of which `read` bytes were read.
    fn changed(&self, size: u64, read: u64) -> Error {
        let named = self.named();
        let read = if read > size { format!("more than {size}") } else { read.to_string() };
        Error::InvalidArgument(format!(
            "{named}: the file changed while it was read: {size} bytes when opened, {read} read"
        ))
    }
}

impl PackedFile {
    /// The ray file `--rays` at `path`, of rays packed in `format`.
    pub async fn rays(path: &Path, format: RayFormat) -> Result<PackedFile> {
        PackedFile::open(Records {
            path: path.into(),
            option: "--rays",
            record_bytes: format.size(),
            format: format.name(),
        })
        .await
    }

    /// The hits file `--primary-hits` at `path`, of `full` hit records.
    pub async fn primary_hits(path: &Path) -> Result<PackedFile> {
        let full = HitFormat::Full;
        let record_bytes = full.size().expect("full records have a size");
        let records = Records { path: path.into(), option: "--primary-hits", record_bytes, format: full.name() };
        PackedFile::open(records).await
    }

    /// The file `records` says, opened on a blocking thread: opening a pipe waits for its writer, and Ctrl-C must
    /// still be seen.
    async fn open(records: Records) -> Result<PackedFile> {
        let opening = tokio::task::spawn_blocking(move || PackedFile::open_now(records));
        opening.await.map_err(|e| Error::Status(tonic::Status::internal(format!("opening a file: {e}"))))?
    }

    /// The file `records` says, opened on this thread.
    fn open_now(records: Records) -> Result<PackedFile> {
        let file = std::fs::File::open(&records.path).map_err(|e| Error::io(&records.path, e))?;
        let metadata = file.metadata().map_err(|e| Error::io(&records.path, e))?;
        let size = metadata.is_file().then_some(metadata.len());
        let packed = PackedFile { file, size, identity: (metadata.dev(), metadata.ino()), records };
        if let Some(bytes) = packed.bytes() {
            packed.records.check_whole(bytes)?;
        }
        Ok(packed)
    }

    /// Its size in bytes, known for a plain file (not for a pipe).
    pub fn bytes(&self) -> Option<u64> {
        self.size
    }

    /// Bytes of one of its records.
    pub fn record_bytes(&self) -> usize {
        self.records.record_bytes
    }

    /// The option that named it and its path, as messages name it (`--rays rays.bin`).
    pub fn named(&self) -> String {
        self.records.named()
    }

    /// The whole file, read on a blocking thread: the future can be dropped (at a Ctrl-C) while a pipe's writer is
    /// still writing.
    pub async fn read(self) -> Result<Bytes> {
        let mut bytes = Vec::new();
        let mut file = tokio::fs::File::from_std(self.file);
        file.read_to_end(&mut bytes).await.map_err(|e| Error::io(&self.records.path, e))?;
        self.records.check_whole(bytes.len() as u64)?;
        Ok(bytes.into())
    }

    /// Whether `other` is this very file (the same inode of the same device), however either is named.
    fn is(&self, other: &std::fs::Metadata) -> bool {
        self.identity == (other.dev(), other.ino())
    }

    /// The file's bytes in chunks of whole records, `chunk_bytes` rounded down to them (the last chunk may be
    /// shorter), read as they are asked for; a file that ends within a record, or (a plain file) that is read to
    /// more or fewer bytes than it held when it was opened, ends the chunks with an error naming it.
    pub fn chunks(self, chunk_bytes: usize) -> impl Stream<Item = Result<Bytes>> + Send + 'static {
        let PackedFile { file, records, size, .. } = self;
        let chunk_bytes = (chunk_bytes / records.record_bytes).max(1) * records.record_bytes;
        let state = Some((tokio::fs::File::from_std(file), 0u64));
        futures_util::stream::unfold((records, state), move |(records, state)| async move {
            let (mut file, read) = state?;
            let mut chunk = BytesMut::zeroed(chunk_bytes);
            let filled = match fill(&mut file, &mut chunk).await {
                Ok(0) => {
                    let shrunk = size.filter(|&size| size != read).map(|size| records.changed(size, read));
                    return shrunk.map(|refused| (Err(refused), (records, None)));
                }
                Ok(filled) => filled,
                Err(e) => {
                    let error = Error::io(&records.path, e);
                    return Some((Err(error), (records, None)));
                }
            };
            let read = read + filled as u64;
            let grown = size.filter(|&size| read > size).map(|size| Err(records.changed(size, read)));
            match grown.unwrap_or_else(|| records.check_whole(read)) {
                Err(refused) => Some((Err(refused), (records, None))),
                Ok(()) => {
                    chunk.truncate(filled);
                    Some((Ok(chunk.freeze()), (records, Some((file, read)))))
                }
            }
        })
    }
}

/// Reads from `file` until `chunk` is full or the file ends; the bytes read.
async fn fill(file: &mut tokio::fs::File, chunk: &mut [u8]) -> std::io::Result<usize> {
    let mut filled = 0;
    while filled < chunk.len() {
        match file.read(&mut chunk[filled..]).await? {
            0 => break,
            n => filled += n,
        }
    }
    Ok(filled)
}

/// What a trace written part by part traced.
pub struct Written {
    /// Rays traced.
    pub rays: usize,
    /// The server's statistics, summed over the parts.
    pub stats: proto::TraceStats,
}

/// Where `rayctl trace` writes: `--out` and, for queries with counts, `--out`.counts. A plain file (or a new one) is
/// written beside itself and renamed into place once the trace ends well, so that a trace that fails leaves the
/// files as they were; a link or a device (`/dev/stdout`) is written through as it is, and left as it is on failure.
pub struct Outputs {
    /// `--out`.
    hits: OutFile,
    /// `--out`.counts.
    counts: Option<OutFile>,
}

impl Outputs {
    /// The outputs of `out` (counts too when `counts`), refused when one of them is the file `read` that the trace
    /// reads as it goes (writing would overwrite it while it is read).
    pub async fn create(out: &Path, counts: bool, read: Option<&PackedFile>) -> Result<Outputs> {
        if counts && std::fs::metadata(out).is_ok_and(|target| !target.is_file()) {
            return Err(Error::InvalidArgument(format!(
                "--out {}: the counts of this query go to {}, beside --out, which a device or a pipe has not: give \
                 --out a file",
                out.display(),
                counts_path(out).display()
            )));
        }
        let counts = counts.then(|| counts_path(out));
        let hits = OutFile::create(out, read).await?;
        if counts.is_some() && standard_output_taken() {
            return Err(Error::InvalidArgument(format!(
                "--out {}: the counts of this query go beside --out, which standard output has not: give --out a file",
                out.display()
            )));
        }
        let counts = match counts {
            Some(path) => Some(OutFile::create(&path, read).await?),
            None => None,
        };
        Ok(Outputs { hits, counts })
    }

    /// Fails with a `ResourceExhausted` error naming `options` unless the file systems written have room for the
    /// hits and counts of `layout` (a device or a pipe is not checked).
    pub fn check_room(&self, layout: &OutputLayout, options: &str) -> Result<()> {
        // Both files go to one file system unless a link sends one elsewhere: each must hold both.
        let needed = (layout.hits as u64).saturating_add(layout.counts as u64);
        let what = || format!("the hits and counts of {} rays", layout.rays);
        for file in std::iter::once(&self.hits).chain(&self.counts) {
            file.check_room(needed, options, what)?;
        }
        Ok(())
    }

    /// Writes out what is buffered, then puts the files in their places one right after the other (nothing is
    /// awaited between the two, so an interruption cannot leave new hits beside old counts).
    async fn finish(mut self) -> Result<()> {
        self.hits.flush().await?;
        if let Some(counts) = &mut self.counts {
            counts.flush().await?;
        }
        self.hits.put()?;
        self.counts.map_or(Ok(()), OutFile::put)
    }
}

/// Consumes `parts`, writing each part's hits and counts to `outputs` where given, which take their places once every
/// part is written and the rays traced are `expected_rays` (where known).
pub async fn write(parts: TraceParts, mut outputs: Option<Outputs>, expected_rays: Option<usize>) -> Result<Written> {
    let written = write_all(parts, outputs.as_mut()).await?;
    if let Some(expected) = expected_rays
        && written.rays != expected
    {
        return Err(Error::Protocol(format!("the trace ended after {} of {expected} rays", written.rays)));
    }
    if let Some(outputs) = outputs {
        outputs.finish().await?;
    }
    Ok(written)
}

/// Where the counts of hits written to `out` go: `out`.counts.
fn counts_path(out: &Path) -> PathBuf {
    let mut counts = out.as_os_str().to_owned();
    counts.push(".counts");
    counts.into()
}

/// A file being written: a new or plain file beside itself, renamed into place at the end; anything else through
/// itself.
pub struct OutFile {
    /// Where it goes.
    path: PathBuf,
    /// The file written beside it, renamed into place at the end; `None` when `path` is written through.
    beside: Option<tempfile::TempPath>,
    /// Set for a plain file written through a link until it is emptied, just before the first write.
    empty_first: bool,
    /// Its writer.
    writer: BufWriter<tokio::fs::File>,
}

impl OutFile {
    /// The file at `path`: a new or plain file is written beside itself (with the old file's permissions), anything
    /// else (a link, a device, a pipe) through itself, opened on a blocking thread (opening a pipe waits for its
    /// reader, and Ctrl-C must still be seen). Refused when it is the file `read`, which the trace reads as it goes.
    pub async fn create(path: &Path, read: Option<&PackedFile>) -> Result<OutFile> {
        let io = |e| Error::io(path, e);
        if let (Some(read), Ok(target)) = (read, std::fs::metadata(path))
            && read.is(&target)
        {
            return Err(Error::InvalidArgument(format!(
                "--out {}: is the file of {} itself, which it would overwrite while reading it",
                path.display(),
                read.named()
            )));
        }
        let (file, beside) = match std::fs::symlink_metadata(path) {
            Ok(existing) if !existing.is_file() => {
                // Not emptied yet: a plain file behind a link is emptied once checked for room, at the first write.
                let through = path.to_path_buf();
                let opening = tokio::task::spawn_blocking(move || {
                    std::fs::OpenOptions::new().write(true).create(true).truncate(false).open(through)
                });
                let opened = opening.await.map_err(|e| Error::Status(tonic::Status::internal(e.to_string())))?;
                (opened.map_err(io)?, None)
            }
            existing => {
                let directory = match path.parent() {
                    Some(parent) if !parent.as_os_str().is_empty() => parent,
                    _ => Path::new("."),
                };
                let mut builder = tempfile::Builder::new();
                let permissions = existing.map_or_else(|_| std::fs::Permissions::from_mode(0o666), |m| m.permissions());
                builder.prefix(".rayctl-").suffix(".partial").permissions(permissions);
                let (file, beside) = builder.tempfile_in(directory).map_err(io)?.into_parts();
                (file, Some(beside))
            }
        };
        // Standard output is written through the descriptor rayctl was given, at its offset and with its append
        // flag, and never emptied: `>> file` appends, and what the shell wrote before stays.
        let standard_output = is_standard_output(&file);
        let file = if standard_output {
            STANDARD_OUTPUT_TAKEN.store(true, Ordering::Relaxed);
            std::fs::File::from(std::io::stdout().as_fd().try_clone_to_owned().map_err(io)?)
        } else {
            file
        };
        let empty_first = !standard_output && beside.is_none() && file.metadata().map_err(io)?.is_file();
        let writer = BufWriter::with_capacity(1 << 20, tokio::fs::File::from_std(file));
        Ok(OutFile { path: path.into(), beside, writer, empty_first })
    }

    /// Empties a plain file written through a link before anything is written to it.
    async fn empty_once(&mut self) -> Result<()> {
        if std::mem::take(&mut self.empty_first) {
            self.writer.get_mut().set_len(0).await.map_err(|e| Error::io(&self.path, e))?;
        }
        Ok(())
    }

    /// Fails with a `ResourceExhausted` error naming `options` unless its file system has room for `needed` bytes
    /// of `what` (a device or a pipe is not checked).
    pub fn check_room(&self, needed: u64, options: &str, what: impl FnOnce() -> String) -> Result<()> {
        match self.free_bytes()? {
            Some(free) if needed > free => {
                let why = format!("{options}: {} take {needed} bytes, more than the {free} bytes free there", what());
                Err(Error::io(&self.path, std::io::Error::new(ErrorKind::StorageFull, why)))
            }
            _ => Ok(()),
        }
    }

    /// Bytes free for it on its file system; `None` for a device or a pipe.
    fn free_bytes(&self) -> Result<Option<u64>> {
        let Some(beside) = &self.beside else {
            // A plain file behind a link gives its room back when it is emptied (standard output is not).
            return match std::fs::metadata(&self.path) {
                Ok(target) if target.is_file() => {
                    let given_back = if self.empty_first { target.len() } else { 0 };
                    Ok(Some(statvfs_free(&self.path)?.saturating_add(given_back)))
                }
                _ => Ok(None),
            };
        };
        statvfs_free(beside).map(Some)
    }

    /// Appends `bytes`.
    pub async fn write(&mut self, bytes: &[u8]) -> Result<()> {
        self.empty_once().await?;
        self.writer.write_all(bytes).await.map_err(|e| Error::io(&self.path, e))
    }

    /// Writes out what is buffered and puts the file in its place.
    pub async fn finish(mut self) -> Result<()> {
        self.flush().await?;
        self.put()
    }

    /// Writes out what is buffered.
    async fn flush(&mut self) -> Result<()> {
        self.empty_once().await?;
        self.writer.flush().await.map_err(|e| Error::io(&self.path, e))
    }

    /// Puts a file written beside its place there (a file written through is there already).
    fn put(self) -> Result<()> {
        if let Some(beside) = self.beside {
            beside.persist(&self.path).map_err(|e| Error::io(&self.path, e.error))?;
        }
        Ok(())
    }
}

/// Set once a file written is this process's standard output (`--out /dev/stdout`): the report then goes to
/// standard error, so that the data written there stays whole.
static STANDARD_OUTPUT_TAKEN: AtomicBool = AtomicBool::new(false);

/// Whether a file written was this process's standard output.
pub fn standard_output_taken() -> bool {
    STANDARD_OUTPUT_TAKEN.load(Ordering::Relaxed)
}

/// Whether `file` is what standard output is (the same file, device or pipe).
fn is_standard_output(file: &std::fs::File) -> bool {
    let identity = |stat: rustix::fs::Stat| (stat.st_dev, stat.st_ino);
    match (rustix::fs::fstat(file), rustix::fs::fstat(std::io::stdout())) {
        (Ok(written), Ok(stdout)) => identity(written) == identity(stdout),
        _ => false,
    }
}

/// Writes `parts` one after the other as the whole file `path`, as [`OutFile`] writes (a plain or new file beside
/// itself, put in place once all is written).
pub async fn write_whole(path: &Path, parts: &[&[u8]]) -> Result<()> {
    let mut out = OutFile::create(path, None).await?;
    for part in parts {
        out.write(part).await?;
    }
    out.finish().await
}

/// Bytes free to this user on the file system of `path`.
fn statvfs_free(path: &Path) -> Result<u64> {
    let stats = rustix::fs::statvfs(path).map_err(|e| Error::io(path, e.into()))?;
    Ok(stats.f_bavail.saturating_mul(stats.f_frsize))
}

/// Consumes `parts`, writing them to `outputs` where given. Bitmask hits of parts that end within a byte (a server
/// whose `max_rays_per_batch` is below 8 makes such parts) are shifted into place: a last byte that is not full yet
/// waits for the next part's bits.
async fn write_all(mut parts: TraceParts, mut outputs: Option<&mut Outputs>) -> Result<Written> {
    let mut written = Written { rays: 0, stats: proto::TraceStats::default() };
    // Bitmask hits: the bits written, and the bytes not written yet (the last one, while it is not full).
    let (mut bits, mut unwritten) = (0usize, Vec::new());
    while let Some(part) = parts.next().await.transpose()? {
        if let Some(outputs) = &mut outputs {
            match part.query().hit_format.size() {
                Some(_) => outputs.hits.write(part.hits()).await?,
                None => {
                    let count = part.rays() * part.query().records_per_ray();
                    rayd_client::append_bits(&mut unwritten, bits % 8, part.hits(), count);
                    bits += count;
                    let full = unwritten.len() - usize::from(!bits.is_multiple_of(8));
                    outputs.hits.write(&unwritten[..full]).await?;
                    unwritten.drain(..full);
                }
            }
            if let Some(counts) = &mut outputs.counts {
                counts.write(part.counts()).await?;
            }
        }
        written.rays += part.rays();
        rayd_client::add_stats(&mut written.stats, part.stats());
    }
    if let Some(outputs) = outputs {
        outputs.hits.write(&unwritten).await?;
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use futures_util::StreamExt;

    use super::*;

    /// The chunks of a ray file of `rays` 24-byte rays, changed to `changed` rays once opened.
    async fn chunks_of_a_changed_file(rays: usize, changed: usize) -> Vec<Result<Bytes>> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rays.bin");
        std::fs::write(&path, vec![0u8; 24 * rays]).unwrap();
        let file = PackedFile::rays(&path, RayFormat::OriginDirection).await.unwrap();
        std::fs::write(&path, vec![0u8; 24 * changed]).unwrap();
        file.chunks(24 * 4).collect().await
    }

    #[tokio::test]
    async fn a_ray_file_that_changes_while_read_is_refused_naming_it() {
        let whole = chunks_of_a_changed_file(10, 10).await;
        let lengths: Vec<usize> = whole.into_iter().map(|chunk| chunk.unwrap().len()).collect();
        assert_eq!(lengths, [96, 96, 48]);
        for (changed, read) in [(6, "144"), (12, "more than 240")] {
            let chunks = chunks_of_a_changed_file(10, changed).await;
            let error = chunks.into_iter().find_map(Result::err).expect("an error");
            let expected = format!("the file changed while it was read: 240 bytes when opened, {read} read");
            assert!(matches!(&error, Error::InvalidArgument(e) if e.contains(&expected)), "{error:?}");
            assert!(error.to_string().starts_with("--rays "), "{error}");
        }
    }
}
