//! Secondary rays for `rayctl trace --reflect` / `--towards-light`: their primary rays (a file or a generator) and
//! the primaries' hits (a file or a server-side buffer). Files go up as temporary buffers of the accel's scene, read
//! and sent a part at a time, so that rayctl holds neither whole; the server makes the secondary rays from them.

use rayd_client::{Client, Error, PrimaryRays, Result, SecondaryRays, TemporaryBuffers, proto};
use rayd_engine::format::RayFormat;
use rayd_engine::raygen::Bounce;

use crate::commands::RaySource;
use crate::parts::PackedFile;

/// Where the primaries' hits are.
pub enum PrimaryHits {
    /// In a file (`--primary-hits`).
    File(PackedFile),
    /// In a server-side buffer of this name (`--primary-hits-buffer`).
    Buffer(String),
}

/// Secondary rays as `rayctl trace` is given them.
pub struct Bounced {
    /// The primary rays (a file's are packed in `ray_format`).
    pub primary: RaySource,
    /// The format of a ray file's rays.
    pub ray_format: RayFormat,
    /// Their hits, `full` records, one a primary ray.
    pub hits: PrimaryHits,
    /// Reflect, or head for a point light.
    pub bounce: Bounce,
    /// World units that origins move off the surface.
    pub offset: f32,
}

/// Deletes the buffers of `temporary` (uploaded for one trace), for at most [`CLEAN_UP_TIME`](crate::CLEAN_UP_TIME);
/// where that fails, says so on standard error, naming them (`rayctl buffers` lists them by name). The command's
/// own outcome stands.
pub async fn delete(temporary: TemporaryBuffers) {
    let names = temporary.names().join(", ");
    if names.is_empty() {
        return;
    }
    let why = match tokio::time::timeout(crate::CLEAN_UP_TIME, temporary.delete()).await {
        Ok(Ok(())) => return,
        Ok(Err(failed)) => failed.to_string(),
        Err(_) => format!("no answer within {} s", crate::CLEAN_UP_TIME.as_secs()),
    };
    crate::warn(&format!("temporary buffers may be left on the server ({why}): {names} (`rayctl buffers` lists them)"));
}

impl Bounced {
    /// The number of primary rays, where known before reading (not for a pipe).
    pub fn rays(&self) -> Option<u64> {
        match &self.primary {
            RaySource::File(file) => file.bytes().map(|bytes| bytes / self.ray_format.size() as u64),
            RaySource::Generator(generator) => Some(generator.count()),
        }
    }

    /// Refuses a hits file that does not hold one record a primary ray, where both sizes are known.
    pub fn check(&self) -> Result<()> {
        let PrimaryHits::File(hits) = &self.hits else { return Ok(()) };
        let record = hits.record_bytes() as u64;
        match (hits.bytes(), self.rays()) {
            (Some(bytes), Some(rays)) if bytes != rays.saturating_mul(record) => Err(Error::InvalidArgument(format!(
                "{}: {} hit records ({bytes} bytes), but there are {rays} primary rays: give the hits of a \
                     trace of the same rays",
                hits.named(),
                bytes / record
            ))),
            _ => Ok(()),
        }
    }

    /// The secondary rays as the server takes them, their files uploaded through `node` (the accel's scene's) as
    /// temporary buffers, each noted in `temporary` as soon as it is made (the caller deletes them once the trace
    /// has ended, or failed).
    pub async fn on_server(self, node: &Client, temporary: &mut TemporaryBuffers) -> Result<SecondaryRays> {
        let primary = match self.primary {
            RaySource::File(file) => PrimaryRays::Buffer(upload(node, file, temporary).await?, self.ray_format),
            RaySource::Generator(generator) => PrimaryRays::Generated(generator),
        };
        let hits_buffer = match self.hits {
            PrimaryHits::File(file) => upload(node, file, temporary).await?,
            PrimaryHits::Buffer(name) => proto::BufferRef { r#ref: Some(proto::buffer_ref::Ref::Name(name)) },
        };
        Ok(SecondaryRays { primary, hits_buffer, bounce: self.bounce, offset: self.offset })
    }
}

/// Uploads `file` through `node` as a new buffer named and noted in `temporary`, a part at a time (a pipe, whose
/// size is not known before, is read whole first), and returns a reference to it.
async fn upload(node: &Client, file: PackedFile, temporary: &mut TemporaryBuffers) -> Result<proto::BufferRef> {
    let name = temporary.name_next();
    let buffer = match file.bytes() {
        Some(bytes) => {
            let parts = file.chunks(node.options().upload_chunk_bytes);
            node.upload_buffer_parts(&name, bytes, parts).await?
        }
        None => node.upload_buffer(&name, file.read().await?).await?,
    };
    Ok(rayd_client::convert::buffer_ref(&buffer.id))
}
